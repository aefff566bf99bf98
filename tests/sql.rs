#![allow(clippy::unwrap_used)]
//! `rtvtk sql` end to end: the tables of encoded and plain datasets, the ray functions, the
//! paper's shadow-ray bug as a query, several datasets side by side, and bad input.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

mod common;
use common::{WRONG_SHADOWS, rtvtk, scalar};

const SETTINGS: [&str; 8] = ["--scene", "cornell", "--size", "40x30", "--spp", "4", "--threads", "2"];

fn record(dir: &Path, extra: &[&str]) {
    common::record(dir, &[&SETTINGS[..], extra].concat());
}

/// A lossless recording under `dir` and its plain export: (encoded, plain).
fn record_and_export(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let (enc, plain) = (dir.join("enc"), dir.join("plain"));
    record(&enc, &[]);
    assert!(rtvtk(&["export", enc.to_str().unwrap(), plain.to_str().unwrap()]).status.success());
    (enc, plain)
}

#[test]
fn the_shadow_ray_bug_is_a_query() {
    let tmp = tempfile::tempdir().unwrap();
    let (good, bad) = common::record_good_and_bad(tmp.path(), &SETTINGS);
    let wrong_good: u64 = scalar(&[good.to_str().unwrap()], WRONG_SHADOWS).parse().unwrap();
    let wrong_bad: u64 = scalar(&[bad.to_str().unwrap()], WRONG_SHADOWS).parse().unwrap();
    assert_eq!(wrong_good, 0, "a correct trace has no shadow ray aiming at no light");
    assert!(wrong_bad > 0, "the injected bug must show");
    // Every wrong one leaves an upward-facing diffuse surface after the first bounce (the bug's condition).
    let q = "SELECT count(*) FROM rays r JOIN rays p ON r.tree_id = p.tree_id AND r.parent = p.ray \
             WHERE r.kind = 'shadow' AND r.depth >= 2 \
             AND NOT aims_at_light(r.origin_x, r.origin_y, r.origin_z, r.dir_x, r.dir_y, r.dir_z)";
    let deep: u64 = scalar(&[bad.to_str().unwrap()], q).parse().unwrap();
    assert_eq!(deep, wrong_bad);
}

/// Source-code orientation (the paper's future work): with `--sites` every ray records the line
/// of the tracer that traced it, and grouping the wrong shadow rays by `site` names the line
/// that spawns them.
#[test]
fn recording_sites_name_the_line_that_spawns_wrong_shadow_rays() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("bad");
    common::record(&bad, &[&SETTINGS[..], &["--inject-bug", "shadow-dir", "--sites"]].concat());
    let b = bad.to_str().unwrap();
    let root = std::env::var_os("CARGO_MANIFEST_DIR")
        .map_or_else(|| env!("CARGO_MANIFEST_DIR").into(), std::path::PathBuf::from);
    let source = std::fs::read_to_string(root.join("renderers/src/tracer.rs")).unwrap();
    let line = source.lines().position(|l| l.contains("push(&mut rec, RecRay::shadow(")).unwrap() + 1;
    let q = WRONG_SHADOWS.replace("count(*)", "site, count(*)") + " GROUP BY site";
    let out = common::ok(&["sql", b, &q, "--format", "csv"]);
    let rows: Vec<&str> = out.lines().skip(1).collect();
    let wrong = scalar(&[b], WRONG_SHADOWS);
    assert_eq!(rows, vec![format!("renderers/src/tracer.rs:{line},{wrong}")], "{out}");
    // Every ray has a site, and the sites table lists each once.
    assert_eq!(scalar(&[b], "SELECT count(*) FROM rays WHERE site IS NULL"), "0");
    let sites: u64 = scalar(&[b], "SELECT count(DISTINCT site) FROM rays").parse().unwrap();
    assert_eq!(scalar(&[b], "SELECT count(*) FROM sites").parse::<u64>().unwrap(), sites);
    // Without --sites there is no site column.
    let plain = tmp.path().join("plain");
    common::record(&plain, &SETTINGS);
    let e = common::rtvtk(&["sql", plain.to_str().unwrap(), "SELECT site FROM rays"]);
    assert!(!e.status.success() && String::from_utf8_lossy(&e.stderr).contains("site"));
}

#[test]
fn tables_match_the_store_for_encoded_and_plain_datasets() {
    let tmp = tempfile::tempdir().unwrap();
    let (enc, plain) = record_and_export(tmp.path());
    let info: Value = serde_json::from_slice(&rtvtk(&["info", enc.to_str().unwrap(), "--json"]).stdout).unwrap();
    for d in [&enc, &plain] {
        let d = d.to_str().unwrap();
        assert_eq!(scalar(&[d], "SELECT count(*) FROM rays"), info["rays"].to_string());
        assert_eq!(scalar(&[d], "SELECT count(*) FROM trees"), info["trees"].to_string());
        assert_eq!(
            scalar(&[d], "SELECT count(*) FROM rays WHERE kind = 'shadow'"),
            info["rays_by_kind"]["shadow"].to_string()
        );
        assert_eq!(scalar(&[d], "SELECT count(*) FROM rays WHERE t IS NULL"), info["misses"].to_string());
        assert!(scalar(&[d], "SELECT count(*) FROM bvh_nodes").parse::<u64>().unwrap() > 0);
        assert_eq!(scalar(&[d], "SELECT count(*) FROM lights"), "2");
    }
    // The decoded floats are the exported ones, bit for bit (sums in the same order per tree).
    let q = "SELECT sum(CAST(origin_x AS DOUBLE) * 3 + CAST(dir_y AS DOUBLE)) FROM rays WHERE tree_id < 50";
    assert_eq!(scalar(&[enc.to_str().unwrap()], q), scalar(&[plain.to_str().unwrap()], q));
    // Columns read without decoding (projection without origins or directions) agree too.
    let q = "SELECT sum(CAST(t AS DOUBLE)), sum(prim), sum(depth), count(DISTINCT kind) FROM rays";
    assert_eq!(scalar(&[enc.to_str().unwrap()], q), scalar(&[plain.to_str().unwrap()], q));
    // Two datasets under names, compared in one query.
    let both = [&format!("a={}", enc.display()), &format!("b={}", plain.display())].map(|s| s.to_string());
    let q = "SELECT (SELECT count(*) FROM a.rays) - (SELECT count(*) FROM b.rays)";
    assert_eq!(scalar(&[both[0].as_str(), both[1].as_str()], q), "0");
}

#[test]
fn ray_functions_and_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &[]);
    let d = d.to_str().unwrap();
    assert_eq!(scalar(&[d], "SELECT octant(-1.0, 2.0, -3.0)"), "5");
    assert_eq!(scalar(&[d], "SELECT octant(CAST('NaN' AS REAL), 1.0, 1.0) IS NULL"), "true");
    let a: f64 = scalar(&[d], "SELECT angle_between(1.0, 0.0, 0.0, 0.0, 1.0, 0.0)").parse().unwrap();
    assert!((a - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    // Camera rays all start at the camera: one Morton cell; hit points spread over many.
    assert_eq!(
        scalar(
            &[d],
            "SELECT count(DISTINCT morton3(origin_x, origin_y, origin_z, 10)) FROM rays WHERE kind = 'camera'"
        ),
        "1"
    );
    let cells: u64 = scalar(
        &[d],
        "SELECT count(DISTINCT morton3(origin_x + dir_x * t, origin_y + dir_y * t, origin_z + dir_z * t, 4)) \
         FROM rays WHERE t IS NOT NULL",
    )
    .parse()
    .unwrap();
    assert!(cells > 20, "{cells} cells");
    // Every ray that hit something entered the BVH's root box; some that entered hit nothing.
    let q = "SELECT count(*) FILTER (WHERE t IS NOT NULL AND NOT ray_aabb_hit(origin_x, origin_y, origin_z, \
             dir_x, dir_y, dir_z, b.min_x, b.min_y, b.min_z, b.max_x, b.max_y, b.max_z)) \
             FROM rays, bvh_nodes b WHERE b.node_id = 0";
    assert_eq!(scalar(&[d], q), "0");
    // Diffuse bounces spread over the octahedral cells of both hemispheres.
    let cells: u32 =
        scalar(&[d], "SELECT count(DISTINCT dir_bin(dir_x, dir_y, dir_z, 8)) FROM rays WHERE kind = 'diffuse'")
            .parse()
            .unwrap();
    assert!(cells > 32 && cells <= 64, "{cells}");
    // Bad SQL, unknown columns and writes are errors that say what is wrong, never a panic.
    for (q, expect) in [
        ("SELEC 1", "SELEC"),
        ("SELECT no_such_column FROM rays", "no_such_column"),
        ("SELECT octant(1.0, 2.0) FROM rays", "octant"),
        ("CREATE TABLE x AS SELECT 1", "DDL"),
    ] {
        let out = rtvtk(&["sql", d, q]);
        assert!(!out.status.success(), "{q} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expect) && !err.contains("panicked"), "{q}: {err}");
    }
}

#[test]
fn ray_paths_are_light_path_expressions() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &[]);
    let d = d.to_str().unwrap();
    assert_eq!(scalar(&[d], "SELECT count(*) FROM ray_paths"), scalar(&[d], "SELECT count(*) FROM rays"));
    // Shadow rays that reached an emitter, by path and by joining rays with lights, agree.
    let by_path: u64 =
        scalar(&[d], "SELECT count(*) FROM ray_paths WHERE regexp_like(path, '^C( D)* S L$')").parse().unwrap();
    let by_join: u64 =
        scalar(&[d], "SELECT count(*) FROM rays WHERE kind = 'shadow' AND prim IN (SELECT prim FROM lights)")
            .parse()
            .unwrap();
    assert!(by_path > 0);
    assert_eq!(by_path, by_join);
    // A ray's path has one letter per level of depth.
    assert_eq!(
        scalar(
            &[d],
            "SELECT count(*) FROM ray_paths WHERE length(replace(replace(path, ' L', ''), ' ', '')) <> depth + 1"
        ),
        "0"
    );
}

/// The same aggregate in DuckDB (on the plain export) and in rtvtk (on the lossless dataset).
#[test]
fn duckdb_and_rtvtk_agree() {
    let tmp = tempfile::tempdir().unwrap();
    let (enc, plain) = record_and_export(tmp.path());
    let q = "SELECT CAST(kind AS VARCHAR) AS k, count(*) AS n, sum(depth) AS sd, min(t) AS lo, max(t) AS hi, \
             sum(CASE WHEN dir_y > 0 THEN 1 ELSE 0 END) AS up FROM rays GROUP BY k ORDER BY k";
    let ours = rtvtk(&["sql", enc.to_str().unwrap(), q, "--format", "csv"]);
    assert!(ours.status.success(), "{}", String::from_utf8_lossy(&ours.stderr));
    let script = r#"
import sys, duckdb
d, q = sys.argv[1], sys.argv[2]
duckdb.sql(f"CREATE VIEW rays AS SELECT * FROM read_parquet('{d}/segments/*.rays.parquet')")
for r in duckdb.sql(q).fetchall():
    print(",".join(str(v) for v in r))
"#;
    let theirs = Command::new("python3").args(["-c", script, plain.to_str().unwrap(), q]).output().unwrap();
    assert!(theirs.status.success(), "{}", String::from_utf8_lossy(&theirs.stderr));
    let parse = |text: &str| -> Vec<Vec<f64>> {
        text.lines()
            .filter(|l| !l.starts_with('k'))
            .map(|l| l.split(',').skip(1).map(|v| v.parse::<f64>().unwrap()).collect())
            .collect()
    };
    let (a, b) = (parse(&String::from_utf8_lossy(&ours.stdout)), parse(&String::from_utf8_lossy(&theirs.stdout)));
    assert_eq!(a.len(), 3, "{a:?}");
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        for (u, v) in x.iter().zip(y) {
            assert!((u - v).abs() <= 1e-6 * u.abs().max(1.0), "rtvtk {x:?} vs DuckDB {y:?}");
        }
    }
}

/// Filters on tree, pixel, sample, depth and kind are pushed into the scan (EXPLAIN shows what
/// was kept) and give the answers the store gives, tree by tree, on a dataset of several segments.
#[test]
fn pushed_filters_prune_and_keep_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    let args = ["record", "--scene", "cornell", "--size", "40x30", "--spp", "16", "--threads", "2"];
    let extra = ["--segment-rays", "2000", "--writers", "2", "--out", d.to_str().unwrap()];
    let out = rtvtk(&[&args[..], &extra[..]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let ds = store::Dataset::open(&d).unwrap();
    assert!(ds.manifest().segments.len() >= 2, "want several segments");
    let d = d.to_str().unwrap();
    type Pred = Box<dyn Fn(&store::TreeInfo, &store::Ray, &str) -> bool>;
    let cases: Vec<(&str, Pred)> = vec![
        ("tree_id = 77", Box::new(|i, _, _| i.id.0 == 77)),
        (
            "tree_id IN (3, 4000, 9999) OR tree_id >= 19000",
            Box::new(|i, _, _| [3, 4000, 9999].contains(&i.id.0) || i.id.0 >= 19000),
        ),
        ("pixel_x = 7 AND pixel_y = 20", Box::new(|i, _, _| i.pixel == [7, 20])),
        (
            "pixel_x BETWEEN 3 AND 5 AND sample IN (0, 15)",
            Box::new(|i, _, _| (3..=5).contains(&i.pixel[0]) && [0, 15].contains(&i.sample)),
        ),
        ("depth >= 4 AND kind = 'shadow'", Box::new(|_, r, k| r.depth >= 4 && k == "shadow")),
        (
            "depth < 2 AND kind IN ('camera', 'diffuse')",
            Box::new(|_, r, k| r.depth < 2 && (k == "camera" || k == "diffuse")),
        ),
        ("kind = 'transmission'", Box::new(|_, _, k| k == "transmission")),
        ("depth > 100", Box::new(|_, r, _| r.depth > 100)),
    ];
    for (pred, f) in &cases {
        let (mut n, mut sum_depth, mut sum_ray) = (0u64, 0u64, 0u64);
        for tree in ds.trees() {
            let tree = tree.unwrap();
            for r in &tree.rays {
                if f(&tree.info, r, ds.kinds().name(r.kind).unwrap_or("?")) {
                    n += 1;
                    sum_depth += u64::from(r.depth);
                    sum_ray += u64::from(r.index);
                }
            }
        }
        let q = format!("SELECT count(*), coalesce(sum(depth), 0), coalesce(sum(ray), 0) FROM rays WHERE {pred}");
        assert_eq!(scalar(&[d], &q), format!("{n},{sum_depth},{sum_ray}"), "{pred}");
    }
    // What the scan keeps, as EXPLAIN shows it: one tree by id, the trees of one pixel, no segment
    // for a kind the trace lacks or a depth it never reaches.
    let explain = |pred: &str| {
        let out = rtvtk(&["sql", d, &format!("SELECT count(*) FROM rays WHERE {pred}"), "--explain"]);
        assert!(out.status.success());
        let text = String::from_utf8_lossy(&out.stdout).to_string();
        let line = text.lines().find(|l| l.contains("RaysScanExec")).unwrap().to_string();
        let field = |name: &str| {
            let s = &line[line.find(&format!("{name}=")).unwrap() + name.len() + 1..];
            s.split([',', ' ', '|']).next().unwrap().to_string()
        };
        (field("segments"), field("trees"))
    };
    let total = ds.manifest().segments.len();
    assert_eq!(explain("tree_id = 77"), ("1".to_string() + "/" + &total.to_string(), format!("1/{}", ds.tree_count())));
    assert_eq!(explain("pixel_x = 7 AND pixel_y = 20 AND sample = 3").1, format!("1/{}", ds.tree_count()));
    assert_eq!(explain("kind = 'transmission'").0, format!("0/{total}"));
    assert_eq!(explain("depth > 100").0, format!("0/{total}"));
    // A filter the scan cannot use reads everything and still answers right.
    assert_eq!(explain("t > 1.0").1, format!("{0}/{0}", ds.tree_count()));
    // Kind and depth alone come from the segments' counts (the answers are compared with the
    // files' in tests/slt/tables.slt); any other column reads the files.
    let plan = |q: &str| String::from_utf8_lossy(&rtvtk(&["sql", d, q, "--explain"]).stdout).to_string();
    // Segments holding no ray of depth >= 1 (a small one sealed by the timer or at the end may
    // hold only camera rays that missed) are pruned by their depth counts first.
    let deep = ds
        .manifest()
        .segments
        .iter()
        .filter(|s| s.stats.rays_by_kind_depth.values().any(|v| v.iter().skip(1).any(|&c| c > 0)))
        .count();
    let counted = format!("segments={deep}/{total} ({deep} from their kind/depth counts)");
    let shown = plan("SELECT kind, depth, count(*) FROM rays WHERE depth >= 1 GROUP BY kind, depth");
    assert!(shown.contains(&counted), "want {counted} in {shown}");
    assert!(plan("SELECT count(*) FROM rays WHERE kind = 'shadow'").contains("from their kind/depth counts"));
    assert!(!plan("SELECT count(*) FROM rays WHERE kind = 'shadow' AND t > 1").contains("kind/depth counts"));
    assert!(!plan("SELECT count(*) FROM rays WHERE tree_id = 77").contains("kind/depth counts"));
    // Counting group-bys on one integer key run in CountByKeyExec (their answers are compared
    // with DataFusion's own aggregation in tests/slt/counts.slt); other shapes do not.
    let morton = "SELECT morton3(origin_x, origin_y, origin_z, 10) AS m, count(*) FROM rays GROUP BY m";
    assert!(plan(morton).contains("CountByKeyExec"), "{}", plan(morton));
    assert!(plan("SELECT prim, count(*), count(t) FROM rays GROUP BY prim").contains("CountByKeyExec"));
    assert!(!plan("SELECT prim, sum(1) FROM rays GROUP BY prim").contains("CountByKeyExec"));
    assert!(!plan("SELECT prim, count(*) FILTER (WHERE depth > 0) FROM rays GROUP BY prim").contains("CountByKeyExec"));
    assert!(!plan("SELECT kind, count(*) FROM rays GROUP BY kind").contains("CountByKeyExec"));
    // Keys of 8 or 16 bits (octants, depths) have few groups: DataFusion's aggregation keeps them.
    assert!(!plan("SELECT octant(dir_x, dir_y, dir_z) AS o, count(*) FROM rays GROUP BY o").contains("CountByKeyExec"));
    assert!(!plan("SELECT depth, count(t) FROM rays GROUP BY depth").contains("CountByKeyExec"));
    assert!(!plan("SELECT prim, depth, count(*) FROM rays GROUP BY prim, depth").contains("CountByKeyExec"));
    // --stock-aggregation leaves it out, with the same answer.
    let stock_plan = |q: &str| {
        String::from_utf8_lossy(&rtvtk(&["sql", d, q, "--explain", "--stock-aggregation"]).stdout).to_string()
    };
    let stock = stock_plan(morton);
    assert!(!stock.contains("CountByKeyExec") && stock.contains("AggregateExec"), "{stock}");
    let sorted = format!("{morton} ORDER BY m");
    let answer = |extra: &[&str]| {
        let out = rtvtk(&[&["sql", d, &sorted, "--format", "csv"], extra].concat());
        assert!(out.status.success());
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    let ours = answer(&[]);
    assert!(ours.lines().count() > 10, "{ours}");
    assert_eq!(ours, answer(&["--stock-aggregation"]));
    // Group-bys on small-domain keys (kind, depth, material) run their partial half in
    // SmallGroupsExec, with the same answers as DataFusion's own aggregation.
    // (Integer sums: exact in any order, so the two answers can be compared as text.)
    let by_kind = "SELECT kind, depth, avg(box_tests) AS b, sum(tri_tests) AS s, count(*) AS n, \
                   max(material) AS m FROM rays WHERE t > 0 GROUP BY kind, depth ORDER BY kind, depth";
    assert!(plan(by_kind).contains("SmallGroupsExec"), "{}", plan(by_kind));
    assert!(!stock_plan(by_kind).contains("SmallGroupsExec"));
    let answer = |extra: &[&str]| {
        let out = rtvtk(&[&["sql", d, by_kind, "--format", "csv"], extra].concat());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    let ours = answer(&[]);
    assert!(ours.lines().count() > 5, "{ours}");
    assert_eq!(ours, answer(&["--stock-aggregation"]));
    // Its tables are charged to the memory limit. Over it, the counting group-by spills them to
    // disk and answers as it does without one; under a limit too small for one batch's keys, an
    // error that says so, not a crash.
    let every_ray = "SELECT CAST(tree_id AS BIGINT) * 4096 + ray AS id, count(*) AS n FROM rays GROUP BY id";
    let sorted = |extra: &[&str]| {
        let out = rtvtk(&[&["sql", d, every_ray, "--format", "csv"], extra].concat());
        assert!(out.status.success(), "{extra:?}: {}", String::from_utf8_lossy(&out.stderr));
        let mut lines: Vec<String> = String::from_utf8_lossy(&out.stdout).lines().map(str::to_string).collect();
        lines.sort();
        lines
    };
    let unlimited = sorted(&[]);
    assert!(unlimited.len() > 1000, "{} groups", unlimited.len());
    assert_eq!(sorted(&["--memory-limit", "512KiB"]), unlimited);
    let analyzed = rtvtk(&["sql", d, &format!("EXPLAIN ANALYZE {every_ray}"), "--memory-limit", "512KiB"]);
    let shown = String::from_utf8_lossy(&analyzed.stdout);
    let line = shown.lines().find(|l| l.contains("CountByKeyExec")).unwrap_or_else(|| panic!("{shown}"));
    let spills: u64 = line
        .split("spill_count=")
        .nth(1)
        .and_then(|r| r.split(|c: char| !c.is_ascii_digit()).next()?.parse().ok())
        .unwrap_or_else(|| panic!("no spill count in {line}"));
    assert!(spills > 0, "{line}");
    let out = rtvtk(&["sql", d, every_ray, "--memory-limit", "1"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("CountByKeyExec") && !stderr.contains("panicked"), "{stderr}");
}

/// Without a query, `rtvtk sql DATASET` reads statements ending in `;` (here from a pipe); an
/// error is printed and the prompt goes on.
#[test]
fn prompt_reads_statements_until_quit() {
    use std::io::Write;
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &[]);
    let mut child = Command::new(env!("CARGO_BIN_EXE_rtvtk"))
        .args(["sql", d.to_str().unwrap(), "--format", "csv"])
        .env("HOME", tmp.path())
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let input = "SELECT nosuch FROM rays;\nSELECT count(*) AS n\n  FROM trees;\n\\d trees\n\\q\nSELECT 1;\n";
    child.stdin.take().unwrap().write_all(input.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("n\n4800\n"), "{stdout}");
    assert_eq!(stdout.matches("tree_id,UInt64").count(), 1, "{stdout}");
    assert!(stdout.contains("pixel_x,UInt32"), "{stdout}");
    assert!(stderr.contains("nosuch") && !stderr.contains("panicked"), "{stderr}");
    assert!(!stdout.contains("Int64(1)"), "nothing runs after \\q: {stdout}");
}

/// `rtvtk bench query` runs its suite in rtvtk (plain export and encoded dataset) and in DuckDB
/// on the same files, and fails when any answer differs: a cross-engine test of eight queries
/// (octants and Morton codes against DuckDB's SQL arithmetic, coherence, per-pixel averages).
#[test]
fn bench_query_answers_agree_with_duckdb() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &[]);
    let out = rtvtk(&["bench", "query", d.to_str().unwrap(), "--runs", "1"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("gave the same answers to every query"), "{text}");
    assert_eq!(text.lines().filter(|l| l.contains("x |")).count(), 9, "{text}");
}

/// Every table the recording wrote is a SQL table (the scene's `triangles` too), its schema
/// checked; a known table whose file lacks its columns is unavailable alone, with its name and
/// the reason, and `rtvtk check` reports it while the rays stay queryable.
#[test]
fn every_recorded_table_is_queryable_and_a_broken_one_is_refused_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &["--record-visits"]);
    let ds = d.to_str().unwrap();
    let scene = renderers::BuiltinScene::Cornell.build(1).unwrap();
    assert_eq!(scalar(&[ds], "SELECT count(*) FROM triangles"), scene.tris.len().to_string());
    assert_eq!(scalar(&[ds], "SELECT count(*) FROM t.triangles"), scene.tris.len().to_string());
    let emitters: u64 = scalar(&[ds], "SELECT count(*) FROM lights").parse().unwrap();
    assert_eq!(emitters, scene.lights.len() as u64);
    assert!(scalar(&[ds], "SELECT count(*) FROM bvh_nodes").parse::<u64>().unwrap() > 0);
    let rays = scalar(&[ds], "SELECT count(*) FROM rays");

    // `bvh_nodes`'s file replaced by the triangles' (none of its columns).
    let file = |name: &str| {
        let m: Value = serde_json::from_str(&std::fs::read_to_string(d.join("manifest.json")).unwrap()).unwrap();
        d.join(m["tables"][name]["path"].as_str().unwrap())
    };
    std::fs::copy(file("triangles"), file("bvh_nodes")).unwrap();
    assert_eq!(scalar(&[ds], "SELECT count(*) FROM rays"), rays, "the rays stay queryable");
    assert_eq!(scalar(&[ds], "SELECT count(*) FROM triangles"), scene.tris.len().to_string());
    let refused = |why: &str| {
        let out = rtvtk(&["sql", ds, "SELECT count(*) FROM bvh_nodes"]);
        let e = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && e.contains("`bvh_nodes`") && e.contains(why), "{e}");
    };
    refused("truncated or changed");
    // The manifest made to agree with the file's size: now its columns are what is wrong.
    let mut m: Value = serde_json::from_str(&std::fs::read_to_string(d.join("manifest.json")).unwrap()).unwrap();
    m["tables"]["bvh_nodes"]["bytes"] = std::fs::metadata(file("bvh_nodes")).unwrap().len().into();
    std::fs::write(d.join("manifest.json"), serde_json::to_string(&m).unwrap()).unwrap();
    refused("is missing");
    assert_eq!(scalar(&[ds], "SELECT count(*) FROM rays"), rays);
    let out = rtvtk(&["check", ds]);
    let report = String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{report}");
    assert!(report.contains("`bvh_nodes`") && report.contains("is missing"), "{report}");
}

/// Every output format prints every result: CSV renders list and struct values as text
/// (`SHOW FUNCTIONS` has list columns).
#[test]
fn csv_prints_nested_values_as_text() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    record(&d, &[]);
    let out = rtvtk(&["sql", d.to_str().unwrap(), "SHOW FUNCTIONS LIKE 'aims_at_light'", "--format", "csv"]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.lines().count() >= 2 && text.contains("aims_at_light") && text.contains("[ox"), "{text}");
    let out = rtvtk(&["sql", d.to_str().unwrap(), "SELECT [1, 2] AS l, named_struct('a', 1) AS s", "--format", "csv"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(String::from_utf8_lossy(&out.stdout).lines().nth(1), Some("\"[1, 2]\",{a: 1}"));
}
