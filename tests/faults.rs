#![allow(clippy::unwrap_used)]
//! Fault injection: every table a dataset can hold, damaged every way a file can be, costs that
//! table alone. For each table (the scene's `triangles` and `lights`, `bvh_nodes`, `ray_nodes`,
//! `sites`, a recorded `attributes` table, a renderer's own table, and the segments' tree tables)
//! and each damage (another schema with the manifest's size and CRC made to match, truncated,
//! missing, a flipped byte, garbage with the manifest's CRC made to match):
//! - SQL on `rays` still answers, with the same counts as before;
//! - a query of the broken table (or of what is made from it) fails naming it;
//! - `check` fails naming it, and `info` reports it unavailable;
//! - `render` still draws the other layers (the rays' pixels are there) and says why a layer is
//!   left out;
//! - the `numerics` view and its checks table answer, naming a check left out for the table.

mod common;
#[path = "common/fixture.rs"]
#[allow(dead_code)]
mod fixture;

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use arrow::array::{Int32Array, RecordBatch, StringArray, UInt32Array};
use arrow::datatypes::{DataType, Field, Schema};
use serde_json::Value;

const W: u32 = 24;
const H: u32 = 18;

/// A recording with every table a dataset can hold (sites, a recorded `attributes` table and a
/// renderer's own beside the scene's), made once per process.
fn base() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("trace");
        let options = rl::RecorderOptions { payload: renderers::payload_schema(), sites: true, ..Default::default() };
        fixture::record_cornell(&dir, [W, H], options, |rec| {
            let kv =
                Schema::new(vec![Field::new("key", DataType::Utf8, false), Field::new("value", DataType::Utf8, false)]);
            let attrs = RecordBatch::try_new(
                Arc::new(kv),
                vec![Arc::new(StringArray::from(vec!["renderer"])), Arc::new(StringArray::from(vec!["faults test"]))],
            )
            .unwrap();
            rec.write_table("attributes", attrs).unwrap();
            let own = Schema::new(vec![Field::new("material", DataType::UInt32, false)]);
            let own = RecordBatch::try_new(Arc::new(own), vec![Arc::new(UInt32Array::from(vec![1, 2, 3]))]).unwrap();
            rec.write_table("renderer_notes", own).unwrap();
        });
        (tmp, dir)
    })
    .1
}

/// A copy of the base recording in `to`.
fn copy(to: &Path) {
    fn walk(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            let target = to.join(e.file_name());
            if e.file_type().unwrap().is_dir() {
                walk(&e.path(), &target);
            } else {
                std::fs::copy(e.path(), target).unwrap();
            }
        }
    }
    walk(base(), to);
}

#[derive(Clone, Copy, Debug)]
enum Damage {
    /// A Parquet file of other columns, the manifest's size and CRC made to match it.
    WrongSchema,
    Truncated,
    Missing,
    /// A byte flipped in the middle: the size is right, the CRC is not.
    BadCrc,
    /// Garbage bytes of the same size, the manifest's CRC made to match them.
    Garbage,
}

const DAMAGES: [Damage; 5] = [Damage::WrongSchema, Damage::Truncated, Damage::Missing, Damage::BadCrc, Damage::Garbage];

fn manifest(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap()
}

/// The manifest entry of `table` (`trees`: segment 0's tree file).
fn entry<'a>(m: &'a mut Value, table: &str) -> &'a mut Value {
    if table == "trees" { &mut m["segments"][0]["trees"] } else { &mut m["tables"][table] }
}

fn damage(dir: &Path, table: &str, how: Damage) {
    let mut m = manifest(dir);
    let file = dir.join(entry(&mut m, table)["path"].as_str().unwrap());
    let len = std::fs::metadata(&file).unwrap().len();
    let fix_manifest = |m: &mut Value| {
        let bytes = std::fs::read(&file).unwrap();
        let e = entry(m, table);
        e["bytes"] = bytes.len().into();
        e["crc32"] = crc32fast::hash(&bytes).into();
        std::fs::write(dir.join("manifest.json"), serde_json::to_string(m).unwrap()).unwrap();
    };
    match how {
        Damage::WrongSchema => {
            let schema = Arc::new(Schema::new(vec![Field::new("nothing", DataType::Int32, false)]));
            let batch = RecordBatch::try_new(schema.clone(), vec![Arc::new(Int32Array::from(vec![7; 10]))]).unwrap();
            let mut w =
                parquet::arrow::ArrowWriter::try_new(std::fs::File::create(&file).unwrap(), schema, None).unwrap();
            w.write(&batch).unwrap();
            w.close().unwrap();
            fix_manifest(&mut m);
        }
        Damage::Truncated => {
            std::fs::OpenOptions::new().write(true).open(&file).unwrap().set_len(len / 2).unwrap();
        }
        Damage::Missing => std::fs::remove_file(&file).unwrap(),
        Damage::BadCrc => {
            let mut bytes = std::fs::read(&file).unwrap();
            let mid = bytes.len() / 2;
            bytes[mid] ^= 0x5a;
            std::fs::write(&file, bytes).unwrap();
        }
        Damage::Garbage => {
            let mut x = 0x9e37_79b9_7f4a_7c15_u64;
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            std::fs::write(&file, bytes).unwrap();
            fix_manifest(&mut m);
        }
    }
}

fn engine(dir: &Path) -> query::Engine {
    let sources = [query::TraceSource { name: "t".into(), path: dir.to_path_buf() }];
    query::Engine::blocking(query::Engine::open(&sources, &Default::default()))
        .unwrap_or_else(|e| panic!("the session does not open: {e}"))
}

fn answer(e: &query::Engine, sql: &str) -> Result<String, String> {
    let batches = e.block_on(e.collect(sql)).map_err(|e| e.to_string())?;
    Ok(arrow::util::pretty::pretty_format_batches(&batches).map_err(|e| e.to_string())?.to_string())
}

/// What a query of `table` is, and the name its error must carry.
fn probe(table: &str) -> (String, &'static str) {
    match table {
        // A rays query that needs the tree tables (its pixel columns) fails naming them too.
        "trees" => ("SELECT count(*) FROM trees".into(), "tree table is unavailable"),
        "lights" => ("SELECT count(*) FROM lights".into(), "`lights`"),
        t => (format!("SELECT count(*) FROM {t}"), ""),
    }
}

/// Every damage of `table`, each in a fresh copy of the base recording.
fn each_damage_costs_only(table: &str) {
    let clean = engine(base());
    let by_kind = "SELECT kind, count(*) AS n, max(depth) AS d FROM rays GROUP BY kind ORDER BY kind";
    let expected = answer(&clean, by_kind).unwrap();
    let rays = answer(&clean, "SELECT count(*) FROM rays").unwrap();
    let (probe_sql, name) = probe(table);
    let name = if name.is_empty() { format!("`{table}`") } else { name.to_string() };
    assert!(answer(&clean, &probe_sql).is_ok(), "{table}: the clean recording answers {probe_sql}");
    for how in DAMAGES {
        let what = format!("{table}, {how:?}");
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("t");
        copy(&dir);
        damage(&dir, table, how);

        // SQL: the rays answer as before; the broken table's queries name it.
        let e = engine(&dir);
        assert_eq!(answer(&e, "SELECT count(*) FROM rays").unwrap(), rays, "{what}");
        if table != "sites" {
            assert_eq!(answer(&e, by_kind).unwrap(), expected, "{what}");
        }
        let err = answer(&e, &probe_sql).err().unwrap_or_else(|| panic!("{what}: {probe_sql} answered"));
        assert!(err.contains(&name) && err.contains("unavailable"), "{what}: {err}");
        if table == "trees" {
            // Rays with their pixels need the segment's trees: refused naming them (a flipped
            // byte in a tree file gave wrong pixels silently before SQL checked the file whole).
            for q in ["SELECT count(*) FROM rays WHERE pixel_x = 3", "SELECT max(pixel_y) FROM rays"] {
                let err = answer(&e, q).unwrap_err();
                assert!(err.contains(&name), "{what}: {err}");
            }
        }
        // The numerics view answers, with the checks left out for the table named.
        let checks = answer(&e, "SELECT problem, missing FROM numerics_checks ORDER BY problem").unwrap();
        match table {
            "lights" => assert!(checks.contains("`lights` table is unavailable"), "{what}: {checks}"),
            "triangles" => assert!(checks.contains("`triangles` table is unavailable"), "{what}: {checks}"),
            _ => assert!(!checks.contains("unavailable"), "{what}: {checks}"),
        }
        // Its rows carry their pixels, which come from the tree tables.
        let numerics = answer(&e, "SELECT problem, count(*) FROM numerics GROUP BY problem");
        match table {
            "trees" => assert!(numerics.as_ref().is_err_and(|e| e.contains(&name)), "{what}: {numerics:?}"),
            _ => assert!(numerics.is_ok(), "{what}: {numerics:?}"),
        }
        if table == "lights" {
            let err = answer(&e, "SELECT count(*) FROM ray_paths").unwrap_err();
            assert!(err.contains("`ray_paths` is unavailable") && err.contains("`lights`"), "{what}: {err}");
            let err =
                answer(&e, &format!("SELECT count(*) FROM rays WHERE {}", query::analyze::WRONG_SHADOW)).unwrap_err();
            assert!(err.contains("aims_at_light") && err.contains("`lights`"), "{what}: {err}");
        }
        if table == "sites" {
            // The `site` column as its ids; their text needs the table.
            let err = answer(&e, "SELECT site FROM rays LIMIT 1");
            if let Ok(ids) = &err {
                assert!(!ids.contains(".rs:"), "{what}: {ids}");
            } else {
                assert!(err.as_ref().unwrap_err().contains("sites"), "{what}: {err:?}");
            }
        }

        // `check` fails naming it; `info` reports it.
        let ds = store::Dataset::open(&dir).unwrap_or_else(|e| panic!("{what}: {e}"));
        let report = ds.check();
        let needle = if table == "trees" { "tree table".to_string() } else { format!("`{table}`") };
        assert!(!report.is_ok() && report.errors.iter().any(|e| e.contains(&needle)), "{what}: {report:?}");
        let info = common::ok(&["info", dir.to_str().unwrap()]);
        let line = info.lines().find(|l| l.trim_start().starts_with("unavailable"));
        assert!(line.is_some_and(|l| l.contains(&format!("{table}:"))), "{what}: {info}");

        // `render` draws the rays (and the scene where it is not the broken table).
        let layers = ["geometry", "rays", "bvh"].map(String::from).to_vec();
        let request = rtvtk_viz::headless::RenderRequest {
            layers: Some(layers),
            size: Some([96, 72]),
            legend: false,
            // The boxes rays visited: the bvh layer then reads `ray_nodes` too.
            bvh_visited: table == "ray_nodes",
            ..Default::default()
        };
        let sources = rtvtk_viz::Sources::open(&dir).unwrap_or_else(|e| panic!("{what}: {e}"));
        let (img, notes) = rtvtk_viz::headless::render(sources, &request).unwrap_or_else(|e| panic!("{what}: {e}"));
        let lit = img.pixels().filter(|p| p.0[..3] != img.get_pixel(0, 0).0[..3]).count();
        assert!(lit > 200, "{what}: {lit} pixels drawn; {notes:?}");
        let says_why = notes.iter().any(|n| n.contains("not drawn") || n.contains("unavailable"));
        match table {
            "triangles" | "bvh_nodes" | "ray_nodes" => assert!(says_why, "{what}: {notes:?}"),
            _ => {}
        }
    }
}

#[test]
fn a_broken_triangles_table_costs_only_it() {
    each_damage_costs_only("triangles");
}

#[test]
fn a_broken_lights_table_costs_only_it() {
    each_damage_costs_only("lights");
}

#[test]
fn a_broken_bvh_nodes_table_costs_only_it() {
    each_damage_costs_only("bvh_nodes");
}

#[test]
fn a_broken_ray_nodes_table_costs_only_it() {
    each_damage_costs_only("ray_nodes");
}

#[test]
fn a_broken_sites_table_costs_only_it() {
    each_damage_costs_only("sites");
}

#[test]
fn a_broken_attributes_table_costs_only_it() {
    each_damage_costs_only("attributes");
}

#[test]
fn a_broken_renderers_own_table_costs_only_it() {
    each_damage_costs_only("renderer_notes");
}

#[test]
fn a_broken_tree_table_costs_only_it() {
    each_damage_costs_only("trees");
}
