//! The path payload predicted (format version 4): throughput by colour, radiance from the path's
//! arithmetic. What a path tracer records comes back bit for bit through every read (whole
//! segments, projected columns in batches that cut trees, row subsets, one tree), and so does
//! any other value.
#![allow(clippy::unwrap_used)]

use std::path::Path;

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float32Type};
use store::{
    Dataset, DatasetWriter, Encoding, Kind, KindTable, ListValue, PayloadField, PayloadSchema, RayColumns, RayFields,
    TreeRow, Value, WriteOptions,
};

mod common;
use common::Rng;

fn schema() -> PayloadSchema {
    PayloadSchema::new(
        vec![
            PayloadField::list("throughput", DataType::Float32, 3).unwrap(),
            PayloadField::list("radiance", DataType::Float32, 3).unwrap(),
        ],
        None,
    )
    .unwrap()
}

/// (kind, parent, throughput, radiance or None for "gathered after it", gathered before it)
/// A triple as written, None for null.
type Rgb = Option<[f32; 3]>;

type PathRay = (Kind, u32, [f32; 3], Option<[f32; 3]>, [f32; 3]);

/// Trees as the path tracer records them (camera ray; per bounce a shadow ray toward an emitter
/// and the next bounce; radiance `(l - gathered before) / throughput`), every 9th tree with
/// arbitrary values instead (NaN, infinities, nulls, zero throughput) that must round-trip too.
/// Returns the columns and each ray's radiance and throughput as written (None for null).
fn paths(n: u64) -> (RayColumns, Vec<Rgb>, Vec<Rgb>) {
    let schema = schema();
    let mut rng = Rng(0x2545_F491_4F6C_DD1D);
    let mut cols = RayColumns::new(&schema);
    let mut expected = Vec::new();
    let mut expected_thr = Vec::new();
    let mut mismatches = Vec::new();
    for id in 0..n {
        let first = cols.len() as u64;
        let mut rays: Vec<PathRay> = vec![];
        let (mut beta, mut l) = ([1.0f32; 3], [0.0f32; 3]);
        rays.push((Kind::CAMERA, store::NONE_U32, beta, None, l));
        let mut chain = 0u32;
        for _ in 0..(rng.next() % 6) {
            let albedo = [0.73, 0.2 + 0.5 * rng.f(), 0.12];
            let s = rng.f() * 4.0;
            let w = [0, 1, 2].map(|c| beta[c] * (albedo[c] / std::f32::consts::PI) * s);
            let e = if rng.f() < 0.6 { [17.0, 12.0, 4.0] } else { [0.0; 3] };
            for c in 0..3 {
                l[c] += w[c] * e[c];
            }
            rays.push((Kind::SHADOW, chain, w, Some(e), l));
            beta = [0, 1, 2].map(|c| beta[c] * albedo[c]);
            rays.push((Kind::DIFFUSE, chain, beta, None, l));
            chain = rays.len() as u32 - 1;
        }
        let odd = id % 9 == 4;
        let specials = [f32::NAN, f32::INFINITY, -0.0, 0.0, 1e-40, f32::MAX, -2.5];
        let mut depths: Vec<u16> = Vec::new();
        for (k, &(kind, parent, thr, rad, before)) in rays.iter().enumerate() {
            let mut thr = thr;
            let mut rad =
                rad.unwrap_or_else(|| [0, 1, 2].map(|c| if thr[c] > 0.0 { (l[c] - before[c]) / thr[c] } else { 0.0 }));
            let (mut thr_ok, mut rad_ok) = (true, true);
            if odd {
                thr = [0, 1, 2].map(|c| specials[(k + c + id as usize) % specials.len()]);
                rad = [0, 1, 2].map(|c| specials[(2 * k + c) % specials.len()]);
                thr_ok = k % 3 != 1;
                rad_ok = k % 4 != 2;
            }
            let depth = if parent == store::NONE_U32 { 0 } else { depths[parent as usize] + 1 };
            depths.push(depth);
            let f =
                RayFields { origin: [1.0, 2.0, 3.0], direction: [0.0, 0.0, 1.0], t: Some(5.0), kind, prim: Some(3) };
            cols.push_core(id, k as u32, parent, depth, &f);
            fn v(ok: bool, x: &[f32; 3]) -> Value<'_> {
                if ok { Value::List(ListValue::F32(x)) } else { Value::Null }
            }
            let (tv, rv) = (v(thr_ok, &thr), v(rad_ok, &rad));
            cols.push_payload(&schema, &[tv, rv], None, &mut mismatches);
            expected.push(rad_ok.then_some(rad));
            expected_thr.push(thr_ok.then_some(thr));
        }
        let count = cols.len() as u64 - first;
        let max_depth = depths.iter().copied().max().unwrap_or(0);
        cols.trees.push(TreeRow {
            tree_id: id,
            pixel_x: (id % 64) as u32,
            pixel_y: (id / 64) as u32,
            sample: 0,
            ray_count: count as u32,
            max_depth,
            first_row: first,
        });
    }
    assert!(mismatches.is_empty());
    (cols, expected, expected_thr)
}

/// Writes with small row groups and pages (so reads cross many of them).
fn write(dir: &Path, cols: RayColumns, encoding: Encoding) {
    write_with(dir, cols, WriteOptions { row_group_rows: 1000, page_rows: 100, encoding, ..Default::default() })
}

fn write_with(dir: &Path, cols: RayColumns, opts: WriteOptions) {
    let schema = schema();
    let w = DatasetWriter::create(dir, schema.clone(), opts).unwrap();
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    seg.write(cols, &schema, &kinds).unwrap();
    seg.seal(&w, &kinds).unwrap();
    w.mark_complete().unwrap();
}

/// The bits of the `radiance` column of `batches` (None for null rows).
fn bits(batches: &[RecordBatch]) -> Vec<Option<[u32; 3]>> {
    bits_of(batches, "radiance")
}

/// The bits of a `float32[3]` column `name` of `batches` (None for null rows).
fn bits_of(batches: &[RecordBatch], name: &str) -> Vec<Option<[u32; 3]>> {
    let mut out = Vec::new();
    for b in batches {
        let l = b.column_by_name(name).unwrap().as_fixed_size_list();
        let v = l.values().as_primitive::<Float32Type>();
        for i in 0..l.len() {
            out.push(l.is_valid(i).then(|| [0, 1, 2].map(|c| v.value(3 * i + c).to_bits())));
        }
    }
    out
}

#[test]
fn path_radiance_round_trips_through_every_read() {
    let (cols, expected, thr) = paths(700);
    let to_bits = |v: Vec<Option<[f32; 3]>>| -> Vec<Option<[u32; 3]>> {
        v.iter().map(|r| r.map(|v| v.map(f32::to_bits))).collect()
    };
    let (expected, thr) = (to_bits(expected), to_bits(thr));
    for encoding in [Encoding::Lossless, Encoding::Oct(12), Encoding::Plain] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        write(&path, cols.clone(), encoding);
        let ds = Dataset::open(&path).unwrap();
        let file = ds.file_schema();
        assert_eq!(file.index_of("enc_radiance_r").is_ok(), encoding != Encoding::Plain, "{encoding:?}");
        assert_eq!(file.index_of("radiance").is_ok(), encoding == Encoding::Plain, "{encoding:?}");
        assert_eq!(file.index_of("enc_throughput_b").is_ok(), encoding != Encoding::Plain, "{encoding:?}");
        // Whole segment.
        let full: Vec<RecordBatch> = ds.segment_batches(0).unwrap().map(|b| b.unwrap()).collect();
        assert_eq!(bits(&full), expected, "{encoding:?}");
        assert_eq!(bits_of(&full, "throughput"), thr, "{encoding:?}");
        // Projected, alone and beside other columns, in batches far smaller than a tree.
        for names in [
            vec!["radiance"],
            vec!["depth", "radiance", "origin_x"],
            vec!["throughput", "radiance"],
            vec!["throughput"],
        ] {
            let names: Vec<String> = names.into_iter().map(String::from).collect();
            for batch_rows in [3, 100, store::READ_BATCH_ROWS] {
                let got: Vec<RecordBatch> =
                    ds.segment_columns_in(0, &names, None, batch_rows).unwrap().map(|b| b.unwrap()).collect();
                if names.contains(&"radiance".to_string()) {
                    assert_eq!(bits(&got), expected, "{encoding:?} {names:?} {batch_rows}");
                }
                if names.contains(&"throughput".to_string()) {
                    assert_eq!(bits_of(&got, "throughput"), thr, "{encoding:?} {names:?} {batch_rows}");
                }
            }
        }
        // Row subsets (whole trees) and single trees.
        let trees = ds.segment_tree_entries(0).unwrap();
        let rows = |a: usize, b: usize| trees[a].first_row..trees[b].first_row + u64::from(trees[b].info.ray_count);
        let subset = [rows(10, 40), rows(300, 309)];
        let got: Vec<RecordBatch> = ds
            .segment_columns_in(0, &["radiance".to_string()], Some(&subset), 5)
            .unwrap()
            .map(|b| b.unwrap())
            .collect();
        let want: Vec<_> =
            subset.iter().flat_map(|r| expected[r.start as usize..r.end as usize].iter().copied()).collect();
        assert_eq!(bits(&got), want, "{encoding:?} subset");
        for e in trees.iter().step_by(37) {
            let tree = ds.load_tree(e).unwrap();
            let (a, b) = (e.first_row as usize, e.first_row as usize + e.info.ray_count as usize);
            assert_eq!(bits(std::slice::from_ref(&tree.batch)), expected[a..b], "{encoding:?} tree {}", e.info.id.0);
            assert_eq!(bits_of(&[tree.batch], "throughput"), thr[a..b], "{encoding:?} tree {}", e.info.id.0);
        }
    }
}

#[test]
fn predicted_radiance_costs_a_fraction_of_the_stored_floats() {
    let (cols, _, _) = paths(3000);
    let size = |encoding: Encoding| {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        // The writer's own page and row-group sizes.
        write_with(&path, cols.clone(), WriteOptions { encoding, ..Default::default() });
        let f = std::fs::File::open(path.join("segments/000001.rays.parquet")).unwrap();
        let meta =
            parquet::file::reader::FileReader::metadata(&parquet::file::reader::SerializedFileReader::new(f).unwrap())
                .clone();
        let mut by_name = std::collections::HashMap::<String, i64>::new();
        for g in meta.row_groups() {
            for c in g.columns() {
                *by_name.entry(c.column_path().parts()[0].clone()).or_default() += c.compressed_size();
            }
        }
        by_name
    };
    let (plain, lossless) = (size(Encoding::Plain), size(Encoding::Lossless));
    let sum = |names: &[&str]| names.iter().map(|n| lossless[*n]).sum::<i64>();
    let (stored, predicted) = (plain["radiance"], sum(&["enc_radiance_r", "enc_radiance_g", "enc_radiance_b"]));
    // Every ninth tree holds arbitrary values; the rest are predicted exactly.
    assert!(predicted * 2 < stored, "enc_radiance {predicted} bytes against radiance {stored}");
    // Shadow weights take a few colours (the albedo's green channel varies here, so not many).
    let predicted = sum(&["enc_throughput_r", "enc_throughput_g", "enc_throughput_b", "enc_chroma"]);
    let stored = plain["throughput"];
    assert!(predicted < stored, "enc_throughput_* and enc_chroma {predicted} bytes against throughput {stored}");
}

#[test]
fn the_lossy_payload_option_leaves_the_predicted_path_payload_exact() {
    let (cols, rad, thr) = paths(200);
    for (encoding, exact) in [(Encoding::Lossless, true), (Encoding::Plain, false)] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        write_with(
            &path,
            cols.clone(),
            WriteOptions { encoding, payload_mantissa_bits: Some(10), ..Default::default() },
        );
        let ds = Dataset::open(&path).unwrap();
        let full: Vec<RecordBatch> = ds.segment_batches(0).unwrap().map(|b| b.unwrap()).collect();
        let to_bits = |v: &[Option<[f32; 3]>]| -> Vec<Option<[u32; 3]>> {
            v.iter().map(|r| r.map(|v| v.map(f32::to_bits))).collect()
        };
        // Predicted (encoded layouts): every bit kept. Plain files: rounded as asked.
        assert_eq!(bits(&full) == to_bits(&rad), exact, "{encoding:?}");
        assert_eq!(bits_of(&full, "throughput") == to_bits(&thr), exact, "{encoding:?}");
    }
}
