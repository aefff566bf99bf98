#![allow(clippy::unwrap_used)]
//! Store-level tests: round trips, bit-exact floats, payload types, and bad input.

use std::fs;
use std::path::Path;

use arrow::array::{Array, AsArray};
use arrow::datatypes::{DataType, Float32Type, Int64Type};
use store::FORMAT_VERSION;
use store::{
    BytesPayload, Dataset, DatasetWriter, Error, Kind, KindTable, ListValue, PayloadField, PayloadSchema, RayColumns,
    RayFields, TreeId, TreeRow, Value, WriteOptions,
};

fn ray(o: [f32; 3], d: [f32; 3], t: Option<f32>, kind: Kind) -> RayFields {
    RayFields { origin: o, direction: d, t, kind, prim: t.map(|_| 3) }
}

/// Appends a tree of `n` rays (a chain: each ray the child of the previous) to `cols`.
fn chain(cols: &mut RayColumns, schema: &PayloadSchema, id: u64, n: u32, pixel: [u32; 2]) {
    let first = cols.len() as u64;
    let mut mism = Vec::new();
    for i in 0..n {
        let parent = if i == 0 { store::NONE_U32 } else { i - 1 };
        let kind = if i == 0 { Kind::CAMERA } else { Kind::DIFFUSE };
        let f = ray([i as f32, id as f32, 0.5], [0.0, 0.0, -1.0], Some(1.5 + i as f32), kind);
        cols.push_core(id, i, parent, i as u16, &f);
        if !schema.fields.is_empty() || schema.bytes.is_some() {
            let rgb = [i as f32, 0.25, 0.5];
            let vals = [Value::List(ListValue::F32(&rgb)), Value::I64(id as i64 * 100 + i as i64)];
            let n = schema.fields.len();
            cols.push_payload(schema, &vals[..n], Some(&(id as u32).to_le_bytes()), &mut mism);
        }
    }
    assert!(mism.is_empty(), "{mism:?}");
    cols.trees.push(TreeRow {
        tree_id: id,
        pixel_x: pixel[0],
        pixel_y: pixel[1],
        sample: 0,
        ray_count: n,
        max_depth: n.saturating_sub(1) as u16,
        first_row: first,
    });
}

fn write_dataset(dir: &Path, schema: PayloadSchema, trees_per_segment: &[u64]) {
    write_dataset_with(dir, schema, trees_per_segment, WriteOptions::default());
}

fn write_dataset_with(dir: &Path, schema: PayloadSchema, trees_per_segment: &[u64], options: WriteOptions) {
    write_dataset_with_tables(dir, schema, trees_per_segment, options, &[]);
}

/// [`write_dataset_with`], and whole-dataset `tables` beside the segments.
fn write_dataset_with_tables(
    dir: &Path,
    schema: PayloadSchema,
    trees_per_segment: &[u64],
    options: WriteOptions,
    tables: &[(&str, arrow::array::RecordBatch)],
) {
    let w = DatasetWriter::create(dir, schema.clone(), options).unwrap();
    for (name, batch) in tables {
        w.write_table(name, batch).unwrap();
    }
    let kinds = KindTable::default();
    let mut id = 0;
    for &n in trees_per_segment {
        let mut seg = w.open_segment().unwrap();
        let mut cols = RayColumns::new(&schema);
        for _ in 0..n {
            chain(&mut cols, &schema, id, (id % 5 + 1) as u32, [(id % 7) as u32, (id % 3) as u32]);
            id += 1;
        }
        seg.write(cols, &schema, &kinds).unwrap();
        seg.seal(&w, &kinds).unwrap();
    }
    w.mark_complete().unwrap();
}

fn payload_schema() -> PayloadSchema {
    PayloadSchema::new(
        vec![
            PayloadField::list("throughput", DataType::Float32, 3).unwrap(),
            PayloadField::scalar("tag", DataType::Int64).unwrap(),
        ],
        Some(BytesPayload::Fixed(4)),
    )
    .unwrap()
}

#[test]
fn round_trip_with_payload_and_random_access() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write_dataset(&path, payload_schema(), &[50, 70]);
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree_count(), 120);
    assert_eq!(ds.manifest().segments.len(), 2);
    let expected_rays: u64 = (0..120u64).map(|i| i % 5 + 1).sum();
    assert_eq!(ds.ray_count(), expected_rays);

    let t = ds.tree(TreeId(77)).unwrap();
    assert_eq!(t.rays.len(), 3);
    assert_eq!(t.info.pixel, [77 % 7, 77 % 3]);
    assert_eq!(t.rays[2].parent, Some(1));
    assert_eq!(t.rays[2].depth, 2);
    assert_eq!(t.path_to_root(2), vec![2, 1, 0]);
    assert_eq!(t.children(0).count(), 1);
    let tp = t.column("throughput").unwrap().as_fixed_size_list();
    assert_eq!(tp.value(2).as_primitive::<Float32Type>().values().to_vec(), vec![2.0, 0.25, 0.5]);
    assert_eq!(t.column("tag").unwrap().as_primitive::<Int64Type>().value(1), 7701);
    assert_eq!(t.column("payload").unwrap().as_fixed_size_binary().value(0), 77u32.to_le_bytes());

    // All trees of a pixel, and a sequential scan that sees every tree once.
    let at = ds.trees_at_pixel(3, 1, None).unwrap();
    assert!(!at.is_empty());
    assert!(at.iter().all(|t| t.info.pixel == [3, 1]));
    let n = (0..120u64).filter(|i| i % 7 == 3 && i % 3 == 1).count();
    assert_eq!(at.len(), n);
    let mut seen: Vec<u64> = ds.trees().map(|t| t.unwrap().info.id.0).collect();
    seen.sort_unstable();
    assert_eq!(seen, (0..120).collect::<Vec<_>>());
    assert!(matches!(ds.tree(TreeId(5000)), Err(Error::NoSuchTree(5000))));
    let report = ds.check();
    assert!(report.is_ok(), "{:?}", report.errors);
    assert_eq!(report.rays, expected_rays);
}

/// Fetches on several threads at once share the one fetch helper (one holds it, the others
/// decode all columns themselves): every thread must get each tree exactly as a fetch alone does.
#[test]
fn fetches_on_many_threads_at_once_read_the_same_trees() {
    let (_dir, path) = sample_dataset();
    let ds = Dataset::open(&path).unwrap();
    let alone: Vec<_> = (0..80).map(|i| ds.tree(TreeId(i)).unwrap().batch).collect();
    std::thread::scope(|s| {
        for t in 0..4u64 {
            let (ds, alone) = (&ds, &alone);
            s.spawn(move || {
                for k in 0..160u64 {
                    let i = (k * 7 + t * 31) % 80;
                    assert_eq!(ds.tree(TreeId(i)).unwrap().batch, alone[i as usize], "tree {i} on thread {t}");
                }
            });
        }
    });
}

/// A process forked after a fetch started the fetch helper has no helper thread: its fetches
/// must decode alone, not wait for a job no thread will run (Python's `multiprocessing` forks).
#[cfg(target_os = "linux")]
#[test]
fn a_forked_process_fetches_without_the_helper_thread() {
    let (_dir, path) = sample_dataset();
    let ds = Dataset::open(&path).unwrap();
    let expected = ds.tree(TreeId(77)).unwrap().batch;
    // SAFETY: the child only fetches and leaves with `_exit`; the test's process has no other
    // thread holding a lock the child needs (nextest runs each test in its own process).
    let pid = unsafe { libc::fork() };
    assert!(pid >= 0, "fork failed");
    if pid == 0 {
        // SAFETY: the default action of SIGALRM ends the child if the fetch hangs.
        unsafe { libc::alarm(20) };
        let same = ds.tree(TreeId(77)).map(|t| t.batch == expected).unwrap_or(false);
        // SAFETY: leaving the child without running the parent's destructors.
        unsafe { libc::_exit(if same { 0 } else { 1 }) };
    }
    let mut status = 0;
    // SAFETY: waiting for the child made above.
    let waited = unsafe { libc::waitpid(pid, &mut status, 0) };
    assert_eq!(waited, pid);
    assert!(!libc::WIFSIGNALED(status), "the forked fetch hung (ended by signal {})", libc::WTERMSIG(status));
    assert_eq!(libc::WEXITSTATUS(status), 0, "the forked fetch read a different tree");
}

#[test]
fn nan_and_infinities_round_trip_bit_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    let schema = PayloadSchema::default();
    let w = DatasetWriter::create(&path, schema.clone(), WriteOptions::default()).unwrap();
    let weird = [
        f32::NAN,
        f32::from_bits(0x7fc0_1234),
        f32::from_bits(0xffff_ffff),
        f32::INFINITY,
        f32::NEG_INFINITY,
        -0.0,
        f32::MIN_POSITIVE / 2.0,
        f32::MAX,
    ];
    let mut cols = RayColumns::new(&schema);
    for (i, &v) in weird.iter().enumerate() {
        let f = ray([v, -v, 1.0], [v, 0.0, v], Some(v), Kind::SHADOW);
        cols.push_core(0, i as u32, if i == 0 { store::NONE_U32 } else { 0 }, u16::from(i > 0), &f);
    }
    cols.trees.push(TreeRow {
        tree_id: 0,
        pixel_x: 0,
        pixel_y: 0,
        sample: 0,
        ray_count: weird.len() as u32,
        max_depth: 1,
        first_row: 0,
    });
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    seg.write(cols, &schema, &kinds).unwrap();
    seg.seal(&w, &kinds).unwrap();
    let ds = Dataset::open(&path).unwrap();
    let t = ds.tree(TreeId(0)).unwrap();
    for (i, &v) in weird.iter().enumerate() {
        let r = t.rays[i];
        assert_eq!(r.origin[0].to_bits(), v.to_bits(), "origin_x of ray {i}");
        assert_eq!(r.origin[1].to_bits(), (-v).to_bits(), "origin_y of ray {i}");
        assert_eq!(r.direction[2].to_bits(), v.to_bits(), "dir_z of ray {i}");
        assert_eq!(r.t.unwrap().to_bits(), v.to_bits(), "t of ray {i}");
    }
    assert_eq!(ds.stats().non_finite, 5, "NaN/Inf rays are counted, not dropped");
    assert!(ds.check().is_ok());
}

#[test]
fn unused_things_are_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write_dataset(&path, PayloadSchema::default(), &[10]);
    let ds = Dataset::open(&path).unwrap();
    let names: Vec<String> = ds.ray_schema().fields().iter().map(|f| f.name().clone()).collect();
    assert!(!names.contains(&"payload".to_string()));
    assert_eq!(names.len(), store::CORE_COLUMN_COUNT);
    // Only camera and diffuse rays were recorded: only those kinds exist.
    let kinds: Vec<&String> = ds.manifest().kinds.keys().collect();
    assert_eq!(kinds, vec!["camera", "diffuse"]);
    let text = fs::read_to_string(path.join("manifest.json")).unwrap();
    assert!(!text.contains("\"payload\""), "{text}");
}

fn sample_dataset() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write_dataset(&path, payload_schema(), &[40, 40]);
    (dir, path)
}

#[test]
fn truncated_segment_is_named() {
    let (_d, path) = sample_dataset();
    let f = path.join("segments/000002.rays.parquet");
    let len = fs::metadata(&f).unwrap().len();
    fs::OpenOptions::new().write(true).open(&f).unwrap().set_len(len / 2).unwrap();
    let err = Dataset::open(&path).err().unwrap();
    assert!(matches!(err, Error::SizeMismatch { segment: 2, .. }), "{err}");
    assert!(err.to_string().contains("000002.rays.parquet"), "{err}");
}

#[test]
fn missing_segment_is_named() {
    let (_d, path) = sample_dataset();
    fs::remove_file(path.join("segments/000001.rays.parquet")).unwrap();
    let err = Dataset::open(&path).err().unwrap();
    assert!(matches!(err, Error::MissingFile { segment: 1, .. }), "{err}");
    assert!(err.to_string().contains("000001.rays.parquet"), "{err}");
}

/// A segment's tree file missing, truncated or corrupted costs that segment's trees alone: the
/// dataset opens, the segment's rays and every other segment stay readable, and a read of its
/// trees (or `verify_trees`) names the segment and the file.
#[test]
fn a_broken_tree_file_costs_its_segments_trees_alone() {
    type Damage = fn(&std::path::Path, &std::path::Path);
    let damages: [(&str, Damage); 3] = [
        ("missing", |_, f| fs::remove_file(f).unwrap()),
        ("truncated", |_, f| {
            let len = fs::metadata(f).unwrap().len();
            fs::OpenOptions::new().write(true).open(f).unwrap().set_len(len / 2).unwrap();
        }),
        ("bad CRC", |_, f| {
            let mut bytes = fs::read(f).unwrap();
            let mid = bytes.len() / 3;
            bytes[mid] ^= 0x5a;
            fs::write(f, bytes).unwrap();
        }),
    ];
    for (what, damage) in damages {
        let (_d, path) = sample_dataset();
        let f = path.join("segments/000001.trees.parquet");
        damage(&path, &f);
        let ds = Dataset::open(&path).unwrap_or_else(|e| panic!("{what}: {e}"));
        let err = ds.verify_trees(0).err().unwrap_or_else(|| panic!("{what}: segment 1 verified"));
        assert!(matches!(err, Error::TreeTable { segment: 1, .. }), "{what}: {err}");
        assert!(err.to_string().contains("000001.trees.parquet"), "{what}: {err}");
        ds.verify_trees(1).unwrap_or_else(|e| panic!("{what}: segment 2: {e}"));
        // Segment 2's trees and every segment's ray columns are read as before.
        assert_eq!(ds.segment_tree_entries(1).unwrap().len(), 40, "{what}");
        for seg in 0..2 {
            let rows: usize = ds
                .segment_columns_in(seg, &["tree_id".to_string()], None, 1024)
                .unwrap()
                .map(|b| b.unwrap().num_rows())
                .sum();
            assert_eq!(rows as u64, ds.manifest().segments[seg].rays.rows, "{what}");
        }
        if what != "bad CRC" {
            let err = ds.segment_tree_entries(0).err().unwrap_or_else(|| panic!("{what}: read"));
            assert!(err.to_string().contains("segment 1's tree table"), "{what}: {err}");
        }
    }
}

#[test]
fn corrupted_segment_is_detected_without_panic() {
    let (_d, path) = sample_dataset();
    let f = path.join("segments/000001.rays.parquet");
    let mut bytes = fs::read(&f).unwrap();
    // Flip bytes in the middle of the data pages (same size, so open succeeds).
    let mid = bytes.len() / 3;
    for b in &mut bytes[mid..mid + 64] {
        *b ^= 0x5a;
    }
    fs::write(&f, &bytes).unwrap();
    let ds = Dataset::open(&path).unwrap();
    let report = ds.check();
    assert!(!report.is_ok());
    assert!(
        report.errors[0].contains("CRC32") && report.errors[0].contains("000001.rays.parquet"),
        "{:?}",
        report.errors
    );
    // Reading every tree either fails with an error naming the file or returns data: never a panic.
    for t in ds.trees() {
        if let Err(e) = t {
            assert!(e.to_string().contains("segments/"), "{e}");
        }
    }
    // Footer destroyed: the error names the file.
    let len = bytes.len();
    for b in &mut bytes[len - 12..len - 4] {
        *b = 0xff;
    }
    fs::write(&f, &bytes).unwrap();
    let ds = Dataset::open(&path).unwrap();
    let err = ds.tree(TreeId(3)).err().unwrap();
    assert!(err.to_string().contains("000001.rays.parquet"), "{err}");
}

#[test]
fn newer_format_version_is_refused() {
    let (_d, path) = sample_dataset();
    let m = path.join("manifest.json");
    let text = fs::read_to_string(&m)
        .unwrap()
        .replace(&format!("\"format_version\": {FORMAT_VERSION}"), "\"format_version\": 99");
    fs::write(&m, text).unwrap();
    let err = Dataset::open(&path).err().unwrap();
    assert!(matches!(err, Error::NewerFormat { found: 99, supported: FORMAT_VERSION, .. }), "{err}");
    assert!(err.to_string().contains("manifest.json"));
}

/// Found by the reader's fuzz harness: a segment path of "/" read the root directory as a ray
/// file. A listed file must lie inside the dataset.
#[test]
fn a_listed_file_outside_the_dataset_is_refused() {
    let (_d, path) = sample_dataset();
    let m = path.join("manifest.json");
    let good: serde_json::Value = serde_json::from_slice(&fs::read(&m).unwrap()).unwrap();
    for bad in ["/", "/etc/passwd", "../elsewhere.parquet", "segments/../../x", ""] {
        let mut json = good.clone();
        json["segments"][1]["rays"]["path"] = serde_json::Value::String(bad.into());
        fs::write(&m, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
        let err = Dataset::open(&path).err().unwrap();
        assert!(matches!(err, Error::Manifest { .. }), "{bad}: {err}");
        let text = err.to_string();
        assert!(text.contains("manifest.json") && text.contains("segments[1].rays.path"), "{bad}: {text}");
    }
    fs::write(&m, serde_json::to_vec_pretty(&good).unwrap()).unwrap();
    assert!(Dataset::open(&path).is_ok());
}

#[test]
fn malformed_manifest_is_named() {
    let (_d, path) = sample_dataset();
    fs::write(path.join("manifest.json"), "{\"format\": \"rtvtk-trace\", \"format_version\": 1, \"segm").unwrap();
    let err = Dataset::open(&path).err().unwrap();
    assert!(matches!(err, Error::Manifest { .. }), "{err}");
    assert!(err.to_string().contains("manifest.json"), "{err}");
    fs::write(path.join("manifest.json"), "{\"format\": \"something-else\"}").unwrap();
    assert!(Dataset::open(&path).err().unwrap().to_string().contains("format"));
}

#[test]
fn payload_type_that_does_not_match_the_file_is_named() {
    let (_d, path) = sample_dataset();
    let m = path.join("manifest.json");
    let text = fs::read_to_string(&m).unwrap().replace("\"int64\"", "\"float64\"");
    fs::write(&m, text).unwrap();
    let ds = Dataset::open(&path).unwrap();
    let err = ds.tree(TreeId(0)).err().unwrap();
    assert!(matches!(&err, Error::Schema { field, .. } if field == "tag"), "{err}");
    assert!(err.to_string().contains("Float64") && err.to_string().contains("Int64"), "{err}");
}

#[test]
fn payload_values_that_do_not_match_are_reported_and_stored_as_null() {
    let schema = payload_schema();
    let mut cols = RayColumns::new(&schema);
    let f = ray([0.0; 3], [0.0, 0.0, 1.0], None, Kind::CAMERA);
    cols.push_core(0, 0, store::NONE_U32, 0, &f);
    let mut mism = Vec::new();
    let short = [1.0f32, 2.0];
    cols.push_payload(&schema, &[Value::List(ListValue::F32(&short)), Value::F32(1.0)], Some(&[1, 2, 3]), &mut mism);
    assert_eq!(mism.len(), 3, "{mism:?}");
    assert_eq!(mism[0].column, "throughput");
    assert_eq!(mism[1].column, "tag");
    assert_eq!(mism[2].column, "payload");
    let batch = cols.to_ray_batch(&schema, &KindTable::default()).unwrap();
    assert!(batch.column_by_name("throughput").unwrap().is_null(0));
    assert!(batch.column_by_name("tag").unwrap().is_null(0));
    assert!(batch.column_by_name("payload").unwrap().is_null(0));
}

#[test]
fn bad_payload_declarations_are_refused() {
    assert!(PayloadField::scalar("t", DataType::Float32).is_err(), "core column name");
    assert!(PayloadField::scalar("bad name", DataType::Float32).is_err());
    assert!(PayloadField::scalar("s", DataType::Utf8).is_err());
    assert!(PayloadField::list("l", DataType::Boolean, 3).is_err());
    assert!(PayloadField::list("l", DataType::Float32, 0).is_err());
    let f = PayloadField::scalar("a", DataType::Float32).unwrap();
    assert!(PayloadSchema::new(vec![f.clone(), f], None).is_err());
    assert!(PayloadSchema::new(vec![], Some(BytesPayload::Fixed(0))).is_err());
    for ty in [DataType::Float16, DataType::UInt8, DataType::Boolean, DataType::Date32] {
        let f = PayloadField::scalar("x", ty).unwrap();
        assert_eq!(PayloadField::from_type_name("x", &f.type_name()).unwrap(), f);
    }
}

#[test]
fn creating_over_an_existing_dataset_is_refused() {
    let (_d, path) = sample_dataset();
    let err = DatasetWriter::create(&path, PayloadSchema::default(), WriteOptions::default()).err().unwrap();
    assert!(matches!(err, Error::NotEmpty { .. }), "{err}");
    // ... and the existing data is untouched.
    assert_eq!(Dataset::open(&path).unwrap().tree_count(), 80);
}

#[test]
fn one_tree_fetch_reads_few_pages() {
    // Many trees across several row groups: a fetch must see exactly its own rows.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    let schema = PayloadSchema::default();
    let opts = WriteOptions { row_group_rows: 1000, page_rows: 100, ..Default::default() };
    let w = DatasetWriter::create(&path, schema.clone(), opts).unwrap();
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    let mut cols = RayColumns::new(&schema);
    for id in 0..2000u64 {
        chain(&mut cols, &schema, id, (id % 5 + 1) as u32, [id as u32, 0]);
    }
    seg.write(cols, &schema, &kinds).unwrap();
    seg.seal(&w, &kinds).unwrap();
    let ds = Dataset::open(&path).unwrap();
    for id in (0..2000u64).step_by(37) {
        let t = ds.tree(TreeId(id)).unwrap();
        assert_eq!(t.rays.len() as u64, id % 5 + 1);
        assert!(t.rays.iter().all(|r| r.origin[1] == id as f32));
    }
    let tree_ids = ds
        .tree(TreeId(1999))
        .unwrap()
        .batch
        .column_by_name("tree_id")
        .unwrap()
        .as_primitive::<arrow::datatypes::UInt64Type>()
        .values()
        .to_vec();
    assert!(tree_ids.iter().all(|&i| i == 1999));
    assert!(ds.check().is_ok());
}

#[test]
fn tree_lookups_by_id_range_read_the_right_pages() {
    // Enough trees for a multi-page tree table; lookups through the page index must give exactly
    // the trees a full read filters to, whatever the ranges.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    write_dataset(&path, PayloadSchema::default(), &[60_000, 5_000]);
    let full = Dataset::open(&path).unwrap();
    let all: Vec<_> = (0..2).flat_map(|i| full.segment_tree_entries(i).unwrap().to_vec()).collect();
    let cases: &[&[(u64, u64)]] = &[
        &[(0, 0)],
        &[(12_345, 12_345)],
        &[(19_990, 20_010)],
        &[(100, 200), (40_000, 40_003), (59_999, 60_001)],
        &[(64_999, u64::MAX)],
        &[(70_000, 80_000)],
        &[(u64::MAX, u64::MAX)],
    ];
    for ranges in cases {
        let want: Vec<_> = all
            .iter()
            .filter(|e| ranges.iter().any(|&(lo, hi)| lo <= e.info.id.0 && e.info.id.0 <= hi))
            .copied()
            .collect();
        // A fresh open: nothing cached, so the page-index path is taken.
        let ds = Dataset::open(&path).unwrap();
        let filter = store::TreeFilter { tree_id: Some(ranges.to_vec()), ..Default::default() };
        let got: Vec<_> = (0..2).flat_map(|i| ds.segment_tree_entries_where(i, &filter).unwrap()).collect();
        assert_eq!(got, want, "{ranges:?}");
        // And the cached path agrees.
        let got: Vec<_> = (0..2).flat_map(|i| full.segment_tree_entries_where(i, &filter).unwrap()).collect();
        assert_eq!(got, want, "{ranges:?} (cached)");
    }
}

/// A pixel's trees found from a fresh open (only the segments whose manifest pixel bounds hold
/// it, and in them only the tree-table pages whose pixel statistics can) are exactly those the
/// whole index finds, for every pixel, with and without a sample; a pixel no tree has gives none.
#[test]
fn pixel_lookups_without_the_index_agree_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    let schema = PayloadSchema::default();
    let w = DatasetWriter::create(&path, schema.clone(), WriteOptions::default()).unwrap();
    let kinds = KindTable::default();
    // Three segments, each a band of image rows traced tile by tile with 4 samples per pixel (as
    // the tracers do), ~50K trees per segment: several pages per tree table.
    let (width, band, spp) = (256u32, 48u32, 4u32);
    let mut id = 0u64;
    for s in 0..3u32 {
        let mut seg = w.open_segment().unwrap();
        let mut cols = RayColumns::new(&schema);
        for ty in (s * band..(s + 1) * band).step_by(16) {
            for tx in (0..width).step_by(16) {
                for y in ty..ty + 16 {
                    for x in tx..tx + 16 {
                        for sample in 0..spp {
                            chain(&mut cols, &schema, id, (id % 3 + 1) as u32, [x, y]);
                            cols.trees.last_mut().unwrap().sample = sample;
                            id += 1;
                        }
                    }
                }
            }
        }
        seg.write(cols, &schema, &kinds).unwrap();
        seg.seal(&w, &kinds).unwrap();
    }
    w.mark_complete().unwrap();
    let ds = Dataset::open(&path).unwrap();
    for (i, seg) in ds.manifest().segments.iter().enumerate() {
        let pb = seg.stats.pixel_bounds;
        assert_eq!((pb.min, pb.max), ([0, i as u32 * band], [width - 1, (i as u32 + 1) * band - 1]), "segment {i}");
    }
    assert_eq!(ds.manifest().stats.pixel_bounds.max, [width - 1, 3 * band - 1]);
    let pixels = [[0, 0], [255, 143], [17, 47], [17, 48], [200, 95], [200, 96], [3, 100], [255, 144], [256, 0]];
    let full = Dataset::open(&path).unwrap();
    full.tree_entries().unwrap(); // loads the whole index
    for [x, y] in pixels {
        for sample in [None, Some(0), Some(3), Some(4)] {
            let fresh = Dataset::open(&path).unwrap();
            let got = fresh.tree_entries_at_pixel(x, y, sample).unwrap();
            let want = full.tree_entries_at_pixel(x, y, sample).unwrap();
            assert_eq!(got, want, "pixel ({x}, {y}) sample {sample:?}");
            let expected = if x < width && y < 3 * band { sample.map_or(spp, |s| u32::from(s < spp)) } else { 0 };
            assert_eq!(got.len() as u32, expected, "pixel ({x}, {y}) sample {sample:?}");
            assert!(got.iter().all(|e| e.info.pixel == [x, y]));
        }
    }
    assert!(ds.check().errors.is_empty(), "{:?}", ds.check().errors);
    // Bounds that leave out a tree's pixel are named by `check`.
    let manifest = path.join("manifest.json");
    let mut m: serde_json::Value = serde_json::from_str(&fs::read_to_string(&manifest).unwrap()).unwrap();
    m["segments"][1]["stats"]["pixel_bounds"]["max"][1] = serde_json::json!(60);
    fs::write(&manifest, serde_json::to_string(&m).unwrap()).unwrap();
    let errors = Dataset::open(&path).unwrap().check().errors;
    assert!(
        errors.iter().any(|e| e.contains("segment 2") && e.contains("outside the manifest's pixel bounds")),
        "{errors:?}"
    );
}

/// Trees written out of id order (as tracing threads end them), more than one block of tree rows
/// per segment, and a second segment that refills the first one's emptied blocks, its ids
/// interleaved with the first's: every tree file comes out sorted by id, the index merges them
/// into one order, and every tree is found by id and by pixel with its own rays.
#[test]
fn many_trees_out_of_order_seal_sorted_across_segments() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ds");
    let schema = PayloadSchema::default();
    let w = DatasetWriter::create(&path, schema.clone(), WriteOptions::default()).unwrap();
    let kinds = KindTable::default();
    let per_segment = 40_000u64;
    for s in 0..2u64 {
        let mut seg = w.open_segment().unwrap();
        // Chunks of 1000 trees; within a chunk and across chunks ids run backwards and interleave.
        for c in 0..(per_segment / 1000) {
            let mut cols = RayColumns::new(&schema);
            for k in (0..1000u64).rev() {
                // Even ids in the first segment, odd in the second: the index merges them.
                let id = (k * (per_segment / 1000) + c) * 2 + s;
                chain(&mut cols, &schema, id, (id % 3 + 1) as u32, [(id % 640) as u32, (id / 640) as u32]);
            }
            seg.write(cols, &schema, &kinds).unwrap();
        }
        seg.seal(&w, &kinds).unwrap();
    }
    w.mark_complete().unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree_count(), 2 * per_segment);
    for i in 0..2 {
        let ids: Vec<u64> = ds.segment_tree_entries(i).unwrap().iter().map(|e| e.info.id.0).collect();
        assert_eq!(ids.len() as u64, per_segment);
        assert!(ids.windows(2).all(|w| w[0] < w[1]), "segment {i}'s tree file is sorted by id");
    }
    let all = ds.tree_entries().unwrap();
    assert_eq!(all.len() as u64, 2 * per_segment);
    assert!(all.iter().enumerate().all(|(k, e)| e.info.id.0 == k as u64), "the index holds every id once, in order");
    let at = ds.trees_at_pixel(5, 3, None).unwrap();
    assert_eq!(at.iter().map(|t| t.info.id.0).collect::<Vec<_>>(), vec![3 * 640 + 5]);
    for id in [0u64, 1, 39, 40, 12_345, 39_999, 40_000, 55_555, 79_999] {
        let t = ds.tree(TreeId(id)).unwrap();
        assert_eq!(t.rays.len() as u64, id % 3 + 1, "tree {id}");
        assert_eq!(t.rays[0].origin[1], id as f32, "tree {id} has its own rays");
        assert_eq!(t.info.pixel, [(id % 640) as u32, (id / 640) as u32]);
    }
}

#[test]
fn a_known_table_that_does_not_match_its_schema_is_refused_on_write_and_on_read() {
    use std::sync::Arc;
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    let w = DatasetWriter::create(&dir, PayloadSchema::default(), WriteOptions::default()).unwrap();
    // A lights table without v1_y: refused on write, naming the table and the column.
    let full = store::scene::lights_schema();
    let fields: Vec<_> = full.fields().iter().filter(|f| f.name() != "v1_y").cloned().collect();
    let schema = Arc::new(arrow::datatypes::Schema::new(fields));
    let cols: Vec<arrow::array::ArrayRef> =
        schema.fields().iter().map(|f| arrow::array::new_empty_array(f.data_type())).collect();
    let bad = arrow::array::RecordBatch::try_new(schema, cols).unwrap();
    let e = w.write_table("lights", &bad).unwrap_err().to_string();
    assert!(e.contains("`lights`") && e.contains("`v1_y` is missing"), "{e}");
    // Written under another name and renamed in the manifest (as another tool might): refused on read.
    w.write_table("my_lights", &bad).unwrap();
    w.mark_complete().unwrap();
    let mpath = dir.join("manifest.json");
    let m = fs::read_to_string(&mpath).unwrap().replace("\"my_lights\":", "\"lights\":");
    fs::write(&mpath, m).unwrap();
    let ds = Dataset::open(&dir).unwrap();
    let e = ds.table("lights").unwrap_err().to_string();
    assert!(e.contains("`lights`") && e.contains("`v1_y` is missing"), "{e}");
}

/// `check` verifies each tree's rows against the tree table from the decoded columns: a ray whose
/// depth is not its parent's plus one, a tree table that claims another depth, and a tree id
/// written in two segments whose id ranges overlap are each named, in plain and lossless files;
/// segments whose id ranges do not overlap are not compared, and a sound trace has no error.
#[test]
fn check_names_malformed_trees_and_ids_shared_across_segments() {
    for encoding in [store::Encoding::Plain, store::Encoding::Lossless] {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ds");
        let schema = PayloadSchema::default();
        let options = WriteOptions { encoding, ..WriteOptions::default() };
        let w = DatasetWriter::create(&path, schema.clone(), options).unwrap();
        let kinds = KindTable::default();
        // Segment 1: trees 0..1000 (tree 500's third ray one level too deep, tree 700's table row
        // claiming depth 9); segment 2: tree 990 again, then 1000..1999; segment 3: 5000..5100.
        let segments: [Vec<u64>; 3] =
            [(0..1000).collect(), std::iter::once(990).chain(1000..1999).collect(), (5000..5100).collect()];
        for (s, ids) in segments.into_iter().enumerate() {
            let mut seg = w.open_segment().unwrap();
            let mut cols = RayColumns::new(&schema);
            for id in ids {
                chain(&mut cols, &schema, id, 4, [(id % 64) as u32, (id / 64) as u32]);
                if s == 0 && id == 500 {
                    let row = cols.len() - 2;
                    cols.depth[row] = 3;
                }
                if s == 0 && id == 700 {
                    cols.trees.last_mut().unwrap().max_depth = 9;
                }
            }
            seg.write(cols, &schema, &kinds).unwrap();
            seg.seal(&w, &kinds).unwrap();
        }
        w.mark_complete().unwrap();
        let report = Dataset::open(&path).unwrap().check();
        let has = |needle: &str| report.errors.iter().any(|e| e.contains(needle));
        assert!(
            has("tree 500: ray 2 at depth 3 has parent 1 at depth 1, expected one level up"),
            "{:?}",
            report.errors
        );
        assert!(has("tree 700: tree table says max depth 9, rays reach 3"), "{:?}", report.errors);
        assert!(has("tree 990 appears more than once in the dataset"), "{:?}", report.errors);
        assert_eq!(report.errors.len(), 3, "{encoding:?}: {:?}", report.errors);
        assert_eq!((report.trees, report.rays), (2100, 8400));
    }
    let (_d, path) = sample_dataset();
    let report = Dataset::open(&path).unwrap().check();
    assert!(report.is_ok(), "{:?}", report.errors);
}

/// Fuzzing the reader (a stable-toolchain harness, run with the tests): a small lossless dataset
/// with payload, several row groups and pages per file, is damaged at random — bytes flipped,
/// zeroed, spliced in or cut off in a segment file (with the manifest's size and CRC made to
/// match, so the readers trust the damage and decode it, or left stale), or a manifest field
/// replaced by a value of another type or range — and then opened, checked, scanned, and asked
/// for trees by id and pixel and for columns. Every outcome must be data or an error; a panic
/// (also one in a reader's worker thread) fails the case, and proptest shrinks it and records it
/// in `proptest-regressions/dataset.txt`, which is committed and replayed first on every run.
/// Cases: `PROPTEST_CASES` (default 256).
mod fuzz {
    use super::*;
    use proptest::prelude::*;
    use std::sync::OnceLock;

    /// The undamaged dataset, written once.
    fn base() -> &'static Path {
        static BASE: OnceLock<(tempfile::TempDir, std::path::PathBuf)> = OnceLock::new();
        let (_, path) = BASE.get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("ds");
            let options = WriteOptions { row_group_rows: 64, page_rows: 16, ..WriteOptions::default() };
            // A known table (`sites`, its schema checked) and a renderer's own (its columns
            // checked against the manifest's `columns`).
            let sites: Vec<store::scene::Site> = (0..40)
                .map(|i| store::scene::Site {
                    file: format!("src/tracer{}.rs", i % 3),
                    line: 10 + i,
                    column: 0,
                    function: (i % 2 == 0).then(|| format!("trace_{i}")),
                })
                .collect();
            let sites = store::scene::sites_batch(&sites).unwrap();
            let own = arrow::array::RecordBatch::try_from_iter([(
                "weight",
                std::sync::Arc::new(arrow::array::Float32Array::from_iter_values((0..50).map(|i| i as f32 * 0.5)))
                    as arrow::array::ArrayRef,
            )])
            .unwrap();
            let tables = [("sites", sites), ("renderer_notes", own)];
            write_dataset_with_tables(&path, payload_schema(), &[60, 45], options, &tables);
            (dir, path)
        });
        path
    }

    const FILES: [&str; 6] = [
        "segments/000001.rays.parquet",
        "segments/000001.trees.parquet",
        "segments/000002.rays.parquet",
        "segments/000002.trees.parquet",
        "tables/sites.parquet",
        "tables/renderer_notes.parquet",
    ];

    /// The manifest entry of `FILES[file]`.
    fn entry(json: &mut serde_json::Value, file: usize) -> &mut serde_json::Value {
        match FILES[file].strip_prefix("tables/").and_then(|f| f.strip_suffix(".parquet")) {
            Some(table) => &mut json["tables"][table],
            None => &mut json["segments"][file / 2][if file.is_multiple_of(2) { "rays" } else { "trees" }],
        }
    }

    #[derive(Clone, Debug)]
    enum Damage {
        /// XOR `mask` into `len` bytes from `at` (a fraction of the file).
        Flip { file: usize, at: f64, len: usize, mask: u8, fix_crc: bool },
        /// Zero `len` bytes from `at`.
        Zero { file: usize, at: f64, len: usize, fix_crc: bool },
        /// Insert `bytes` at `at`.
        Splice { file: usize, at: f64, bytes: Vec<u8>, fix_crc: bool },
        /// Cut the file at `at`.
        Truncate { file: usize, at: f64, fix_crc: bool },
        /// Replace the `leaf`-th scalar of the manifest (in document order) by `value`.
        Manifest { leaf: usize, value: serde_json::Value },
    }

    fn json_value() -> impl Strategy<Value = serde_json::Value> {
        use serde_json::json;
        prop_oneof![
            Just(json!(null)),
            Just(json!(-1)),
            Just(json!(0)),
            Just(json!(u64::MAX)),
            Just(json!(1e300)),
            Just(json!(4294967296u64)),
            Just(json!("")),
            Just(json!("segments/../../etc/passwd")),
            Just(json!([])),
            Just(json!({})),
            Just(json!(true)),
            any::<i64>().prop_map(|v| json!(v)),
            any::<u32>().prop_map(|v| json!(v)),
            "[a-z0-9_./]{0,12}".prop_map(|v| json!(v)),
        ]
    }

    fn damage() -> impl Strategy<Value = Damage> {
        let file = 0..FILES.len();
        prop_oneof![
            (file.clone(), 0.0..1.0f64, 1..64usize, 1..=255u8, any::<bool>())
                .prop_map(|(file, at, len, mask, fix_crc)| Damage::Flip { file, at, len, mask, fix_crc }),
            (file.clone(), 0.0..1.0f64, 1..256usize, any::<bool>()).prop_map(|(file, at, len, fix_crc)| Damage::Zero {
                file,
                at,
                len,
                fix_crc
            }),
            (file.clone(), 0.0..1.0f64, proptest::collection::vec(any::<u8>(), 1..32), any::<bool>())
                .prop_map(|(file, at, bytes, fix_crc)| Damage::Splice { file, at, bytes, fix_crc }),
            (file, 0.0..1.0f64, any::<bool>()).prop_map(|(file, at, fix_crc)| Damage::Truncate { file, at, fix_crc }),
            (0..400usize, json_value()).prop_map(|(leaf, value)| Damage::Manifest { leaf, value }),
        ]
    }

    /// Pointers to every scalar (non-container) value of a JSON document, in document order.
    fn leaves(v: &serde_json::Value, at: String, out: &mut Vec<String>) {
        match v {
            serde_json::Value::Object(m) => m.iter().for_each(|(k, v)| leaves(v, format!("{at}/{k}"), out)),
            serde_json::Value::Array(a) => a.iter().enumerate().for_each(|(i, v)| leaves(v, format!("{at}/{i}"), out)),
            _ => out.push(at),
        }
    }

    /// Copies the base dataset and damages the copy; says whether a segment file's bytes changed.
    fn damaged(d: &Damage) -> (tempfile::TempDir, bool) {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        fs::create_dir_all(root.join("segments")).unwrap();
        fs::create_dir_all(root.join("tables")).unwrap();
        for f in std::iter::once("manifest.json").chain(FILES) {
            fs::copy(base().join(f), root.join(f)).unwrap();
        }
        let changed = std::cell::Cell::new(false);
        let edit = |file: usize, fix_crc: bool, change: &dyn Fn(&mut Vec<u8>)| {
            let p = root.join(FILES[file]);
            let mut bytes = fs::read(&p).unwrap();
            let before = bytes.clone();
            change(&mut bytes);
            changed.set(bytes != before);
            fs::write(&p, &bytes).unwrap();
            if fix_crc {
                let m = root.join("manifest.json");
                let mut json: serde_json::Value = serde_json::from_slice(&fs::read(&m).unwrap()).unwrap();
                let entry = entry(&mut json, file);
                entry["bytes"] = serde_json::json!(bytes.len());
                entry["crc32"] = serde_json::json!(crc32fast::hash(&bytes));
                fs::write(&m, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
            }
        };
        let pos = |at: f64, len: usize| ((at * len as f64) as usize).min(len);
        match d {
            Damage::Flip { file, at, len, mask, fix_crc } => edit(*file, *fix_crc, &|b| {
                let start = pos(*at, b.len());
                let end = (start + len).min(b.len());
                b[start..end].iter_mut().for_each(|x| *x ^= mask);
            }),
            Damage::Zero { file, at, len, fix_crc } => edit(*file, *fix_crc, &|b| {
                let start = pos(*at, b.len());
                let end = (start + len).min(b.len());
                b[start..end].fill(0);
            }),
            Damage::Splice { file, at, bytes, fix_crc } => edit(*file, *fix_crc, &|b| {
                let start = pos(*at, b.len());
                b.splice(start..start, bytes.iter().copied());
            }),
            Damage::Truncate { file, at, fix_crc } => edit(*file, *fix_crc, &|b| b.truncate(pos(*at, b.len()))),
            Damage::Manifest { leaf, value } => {
                let m = root.join("manifest.json");
                let mut json: serde_json::Value = serde_json::from_slice(&fs::read(&m).unwrap()).unwrap();
                let mut all = Vec::new();
                leaves(&json, String::new(), &mut all);
                let target = &all[leaf % all.len()];
                if let Some(v) = json.pointer_mut(target) {
                    *v = value.clone();
                }
                fs::write(&m, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
            }
        }
        let changed = changed.get();
        (dir, changed)
    }

    /// Everything a reader does with a dataset; errors are fine, panics are not, and an error
    /// that reports a worker thread's panic is a panic.
    fn exercise(root: &Path) -> Result<Option<store::CheckReport>, TestCaseError> {
        let ds = match Dataset::open(root) {
            Ok(ds) => ds,
            Err(e) => {
                let msg = e.to_string();
                prop_assert!(msg.contains(&root.display().to_string()), "the error names no file: {msg}");
                return Ok(None);
            }
        };
        let no_panic = |msg: &str| !msg.contains("panicked") && !msg.contains("thread checking it failed");
        let report = ds.check();
        for e in &report.errors {
            prop_assert!(no_panic(e), "{e}");
        }
        let mut errors = Vec::new();
        for t in ds.trees().take(200) {
            if let Err(e) = t {
                errors.push(e.to_string());
            }
        }
        for id in [0u64, 3, 59, 60, 104, 1 << 40] {
            if let Err(e) = ds.tree(TreeId(id)) {
                errors.push(e.to_string());
            }
        }
        for (x, y) in [(0, 0), (3, 1), (6, 2), (7, 3)] {
            if let Err(e) = ds.trees_at_pixel(x, y, None) {
                errors.push(e.to_string());
            }
        }
        let names: Vec<String> = ds.ray_schema().fields().iter().map(|f| f.name().clone()).collect();
        for i in 0..ds.manifest().segments.len() {
            match ds.segment_columns(i, &names) {
                Ok(it) => errors.extend(it.filter_map(|b| b.err().map(|e| e.to_string()))),
                Err(e) => errors.push(e.to_string()),
            }
        }
        if let Err(e) = ds.tree_entries() {
            errors.push(e.to_string());
        }
        // Every whole-dataset table and every segment's tree table, checked and read.
        for t in ds.table_names() {
            for r in [ds.verify_table(&t).map(|_| ()), ds.table_schema(&t).map(|_| ()), ds.table(&t).map(|_| ())] {
                if let Err(e) = r {
                    errors.push(e.to_string());
                }
            }
        }
        for i in 0..ds.manifest().segments.len() {
            if let Err(e) = ds.verify_trees(i) {
                errors.push(e.to_string());
            }
        }
        for e in &errors {
            prop_assert!(no_panic(e), "{e}");
        }
        Ok(Some(report))
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            failure_persistence: Some(Box::new(proptest::test_runner::FileFailurePersistence::WithSource("regressions"))),
            ..ProptestConfig::default()
        })]

        #[test]
        fn damaged_datasets_give_errors_not_panics(d in damage()) {
            if std::env::var_os("RTVTK_FUZZ_TRACE").is_some() {
                eprintln!("case {d:?}");
            }
            let (dir, changed) = damaged(&d);
            let report = exercise(dir.path())?;
            // A segment file changed behind the manifest's back is caught by `check`.
            let stale = changed
                && match &d {
                    Damage::Flip { fix_crc, .. }
                    | Damage::Zero { fix_crc, .. }
                    | Damage::Splice { fix_crc, .. }
                    | Damage::Truncate { fix_crc, .. } => !fix_crc,
                    Damage::Manifest { .. } => false,
                };
            if let (true, Some(r)) = (stale, report) {
                prop_assert!(!r.is_ok(), "check passed a stale file: {d:?}");
                // A table changed behind the manifest's back is refused when read, too.
                let file = match &d {
                    Damage::Flip { file, .. } | Damage::Zero { file, .. } | Damage::Splice { file, .. } | Damage::Truncate { file, .. } => *file,
                    Damage::Manifest { .. } => 0,
                };
                if let Some(table) = FILES[file].strip_prefix("tables/").and_then(|f| f.strip_suffix(".parquet")) {
                    let ds = Dataset::open(dir.path()).unwrap();
                    prop_assert!(ds.table(table).is_err(), "a stale `{table}` was read: {d:?}");
                }
            }
        }
    }

    /// Cases the harness found that once hung a reader (a damaged page header that parquet's
    /// record skipping looped on): each must end, with errors or not, within a minute.
    #[test]
    fn damaged_page_headers_end() {
        let cases = [Damage::Zero { file: 0, at: 0.14422660162602433, len: 5, fix_crc: false }];
        for d in cases {
            let (tx, rx) = std::sync::mpsc::channel();
            let case = d.clone();
            std::thread::spawn(move || {
                let (dir, _) = damaged(&case);
                let ok = exercise(dir.path()).is_ok();
                let _ = tx.send(ok);
            });
            match rx.recv_timeout(std::time::Duration::from_secs(60)) {
                Ok(ok) => assert!(ok, "{d:?}"),
                Err(_) => panic!("reading the damaged dataset did not end within 60 s: {d:?}"),
            }
        }
    }

    /// The undamaged copy reads cleanly (the harness itself is sound).
    #[test]
    fn the_undamaged_copy_is_sound() {
        let (dir, changed) = damaged(&Damage::Zero { file: 0, at: 0.5, len: 0, fix_crc: false });
        assert!(!changed);
        let ds = Dataset::open(dir.path()).unwrap();
        assert!(ds.check().is_ok(), "{:?}", ds.check().errors);
        assert_eq!(ds.trees().count(), 105);
        assert_eq!(ds.table_names(), ["renderer_notes", "sites"]);
        for t in ds.table_names() {
            assert!(ds.verify_table(&t).unwrap(), "{t}");
        }
        assert!(ds.manifest().segments.iter().all(|s| s.rays.rows > 64), "several row groups per file");
    }
}

/// The lossy payload option: float payload values within 2^-(bits+1) relative error, NaN,
/// infinities, zeros and the largest finite value kept, other payload columns and the core
/// columns bit-exact, the choice recorded in the manifest, and out-of-range choices refused.
#[test]
fn lossy_payload_rounds_float_mantissas_only() {
    let schema = PayloadSchema::new(
        vec![
            PayloadField::list("radiance", DataType::Float32, 3).unwrap(),
            PayloadField::scalar("pdf", DataType::Float64).unwrap(),
            PayloadField::scalar("tag", DataType::Int64).unwrap(),
        ],
        None,
    )
    .unwrap();
    let mut specials = vec![
        f32::NAN,
        f32::from_bits(0x7fc0_1234),
        f32::INFINITY,
        f32::NEG_INFINITY,
        0.0,
        -0.0,
        f32::MAX,
        -f32::MAX,
        f32::MIN_POSITIVE,
        f32::from_bits(3),
        1.0,
        1.0 + f32::EPSILON,
        -1e30,
        1e-30,
    ];
    let mut x = 0x1234_5678u32;
    for _ in 0..600 {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        specials.push(f32::from_bits(x & 0x7f7f_ffff) * if x & 1 == 0 { 1.0 } else { -1.0 });
    }
    let n = specials.len() / 3;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lossy");
    let options = WriteOptions { payload_mantissa_bits: Some(10), ..WriteOptions::default() };
    let w = DatasetWriter::create(&path, schema.clone(), options).unwrap();
    let kinds = KindTable::default();
    let mut seg = w.open_segment().unwrap();
    let mut cols = RayColumns::new(&schema);
    let mut mism = Vec::new();
    for i in 0..n {
        let f = ray([i as f32, 0.5, 0.25], [0.0, 0.0, -1.0], Some(1.5), Kind::CAMERA);
        cols.push_core(i as u64, 0, store::NONE_U32, 0, &f);
        let rgb = &specials[3 * i..3 * i + 3];
        let pdf = f64::from(rgb[0]) * std::f64::consts::PI;
        let vals = [Value::List(ListValue::F32(rgb)), Value::F64(pdf), Value::I64(i as i64 * 7 - 1_000_000_007)];
        cols.push_payload(&schema, &vals, None, &mut mism);
        cols.trees.push(TreeRow {
            tree_id: i as u64,
            pixel_x: i as u32,
            pixel_y: 0,
            sample: 0,
            ray_count: 1,
            max_depth: 0,
            first_row: i as u64,
        });
    }
    assert!(mism.is_empty(), "{mism:?}");
    seg.write(cols, &schema, &kinds).unwrap();
    seg.seal(&w, &kinds).unwrap();
    w.mark_complete().unwrap();

    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.manifest().payload_mantissa_bits, Some(10));
    let batches: Vec<_> = ds.segment_batches(0).unwrap().map(|b| b.unwrap()).collect();
    let b = arrow::compute::concat_batches(&batches[0].schema(), &batches).unwrap();
    let radiance = b.column_by_name("radiance").unwrap().as_fixed_size_list();
    let values = radiance.values().as_primitive::<Float32Type>();
    let pdf = b.column_by_name("pdf").unwrap().as_primitive::<arrow::datatypes::Float64Type>();
    let tag = b.column_by_name("tag").unwrap().as_primitive::<Int64Type>();
    let origin_x = b.column_by_name("origin_x").unwrap().as_primitive::<Float32Type>();
    for i in 0..n {
        assert_eq!(tag.value(i), i as i64 * 7 - 1_000_000_007);
        assert_eq!(origin_x.value(i), i as f32, "core columns stay exact");
        for k in 0..3 {
            let (want, got) = (specials[3 * i + k], values.value(3 * i + k));
            if want.is_nan() || want.is_infinite() || want == 0.0 {
                assert_eq!(got.to_bits(), want.to_bits(), "{want:e} kept bit for bit");
                continue;
            }
            assert!(got.is_finite(), "{want:e} rounded to {got:e}");
            assert_eq!(got.is_sign_negative(), want.is_sign_negative());
            if want.abs() >= f32::MIN_POSITIVE {
                let rel = ((f64::from(got) - f64::from(want)) / f64::from(want)).abs();
                assert!(rel <= 2f64.powi(-11), "{want:e} -> {got:e}: relative error {rel:e}");
                assert_eq!(got.to_bits() & ((1 << 13) - 1), 0, "{got:e} keeps 10 mantissa bits");
            }
        }
        let want = f64::from(specials[3 * i]) * std::f64::consts::PI;
        let got = pdf.value(i);
        if want.is_finite() && want != 0.0 {
            assert!(((got - want) / want).abs() <= 2f64.powi(-11), "pdf {want:e} -> {got:e}");
        } else {
            assert_eq!(got.to_bits(), want.to_bits());
        }
    }
    // f32::MAX would round up to infinity: it is truncated to the largest 10-bit mantissa instead.
    assert_eq!(values.value(6).to_bits(), 0x7f7f_e000, "the largest finite value does not become infinite");

    for bad in [0u8, 23, 200] {
        let options = WriteOptions { payload_mantissa_bits: Some(bad), ..WriteOptions::default() };
        let err = DatasetWriter::create(&dir.path().join(format!("bad{bad}")), schema.clone(), options).err().unwrap();
        assert!(err.to_string().contains("mantissa bits"), "{err}");
    }
}
