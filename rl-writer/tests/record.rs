#![allow(clippy::unwrap_used)]
//! The recording API end to end: modes, threads, nesting, payloads, misuse and failures.

use std::collections::HashMap;
use std::time::Duration;

use arrow::array::AsArray;
use arrow::datatypes::{DataType, Float32Type};
use rl::{
    BytesPayload, Dataset, Error, Kind, ListValue, Payload, PayloadField, PayloadSchema, RayFields, RayId, Reader,
    Recorder, RecorderOptions, TreeId, Value,
};

fn f(kind: Kind, t: Option<f32>) -> RayFields {
    RayFields { origin: [1.0, 2.0, 3.0], direction: [0.0, 1.0, 0.0], t, kind, prim: t.map(|_| 9) }
}

#[test]
fn depth_first_recording_matches_figure_4() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    let mut tree = rec.begin_tree(3, 4, 1);
    tree.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE); // 0
    tree.descend();
    tree.add_ray(&f(Kind::SHADOW, None), Payload::NONE); // 1
    tree.add_ray(&f(Kind::SPECULAR, Some(2.0)), Payload::NONE); // 2
    tree.descend();
    tree.add_ray(&f(Kind::SHADOW, Some(0.5)), Payload::NONE); // 3
    tree.ascend();
    tree.add_ray(&f(Kind::TRANSMISSION, Some(3.0)), Payload::NONE); // 4
    tree.ascend();
    let id = tree.end();
    rec.finish().unwrap();

    let ds = Dataset::open(&path).unwrap();
    let t = ds.tree(id).unwrap();
    let parents: Vec<_> = t.rays.iter().map(|r| r.parent).collect();
    assert_eq!(parents, vec![None, Some(0), Some(0), Some(2), Some(0)]);
    let depths: Vec<_> = t.rays.iter().map(|r| r.depth).collect();
    assert_eq!(depths, vec![0, 1, 1, 2, 1]);
    assert_eq!(t.rays[1].t, None);
    assert_eq!(t.rays[1].prim, None);
    assert_eq!(t.rays[4].kind, Kind::TRANSMISSION);
    assert_eq!((t.info.pixel, t.info.sample, t.info.max_depth), ([3, 4], 1, 2));
    assert!(ds.manifest().complete);
    assert!(ds.check().is_ok());
}

#[test]
fn breadth_first_with_explicit_parents_and_interleaved_trees() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    // A wavefront renderer: two trees open at once on one thread, filled bounce by bounce.
    let mut a = rec.begin_tree(0, 0, 0);
    let mut b = rec.begin_tree(1, 0, 0);
    let ra = a.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
    let rb = b.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
    let a1 = a.add_ray_under(ra, &f(Kind::DIFFUSE, Some(1.0)), Payload::NONE);
    b.add_ray_under(rb, &f(Kind::SHADOW, None), Payload::NONE);
    a.add_ray_under(ra, &f(Kind::SHADOW, None), Payload::NONE);
    a.add_ray_under(a1, &f(Kind::DIFFUSE, None), Payload::NONE);
    let (ida, idb) = (b.end(), a.end());
    rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    let ta = ds.tree(idb).unwrap();
    assert_eq!(ta.info.pixel, [0, 0]);
    assert_eq!(ta.rays.iter().map(|r| r.depth).collect::<Vec<_>>(), vec![0, 1, 1, 2]);
    assert_eq!(ta.path_to_root(3), vec![3, 1, 0]);
    assert_eq!(ds.tree(ida).unwrap().rays.len(), 2);
}

#[test]
fn many_threads_many_trees() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let options = RecorderOptions { chunk_rays: 500, segment_rays: 3000, workers: 2, ..Default::default() };
    let rec = Recorder::create(&path, options).unwrap();
    let (w, h, spp) = (40u32, 30u32, 2u32);
    std::thread::scope(|s| {
        for th in 0..4u32 {
            let rec = rec.clone();
            s.spawn(move || {
                for y in (th..h).step_by(4) {
                    for x in 0..w {
                        for sample in 0..spp {
                            let mut tree = rec.begin_tree(x, y, sample);
                            rl::demo::trace_pixel(&mut tree, x, y, sample, w, h);
                            tree.end();
                        }
                    }
                }
            });
        }
    });
    let summary = rec.finish().unwrap();
    assert_eq!(summary.trees, u64::from(w * h * spp));
    let ds = Dataset::open(&path).unwrap();
    assert!(ds.manifest().segments.len() > 2, "small segments were sealed as they filled");
    assert_eq!(ds.tree_count(), u64::from(w * h * spp));
    assert_eq!(ds.ray_count(), summary.rays);
    // Every tree equals what the deterministic tracer produces for its pixel and sample.
    for y in (0..h).step_by(7) {
        for x in (0..w).step_by(5) {
            let trees = ds.trees_at_pixel(x, y, None).unwrap();
            assert_eq!(trees.len(), spp as usize);
            for t in trees {
                let want = rl::demo::pixel_rays(x, y, t.info.sample, w, h);
                assert_eq!(t.rays.len(), want.rays.len());
                for (got, (parent, fields)) in t.rays.iter().zip(&want.rays) {
                    assert_eq!(got.parent, *parent);
                    assert_eq!(got.origin, fields.origin);
                    assert_eq!(got.direction, fields.direction);
                    assert_eq!(got.t, fields.t);
                    assert_eq!(got.kind, fields.kind);
                    assert_eq!(got.prim, fields.prim);
                }
            }
        }
    }
    let report = ds.check();
    assert!(report.is_ok(), "{:?}", report.errors);
    let s = ds.stats();
    assert_eq!(s.rays_by_kind().values().sum::<u64>(), s.rays);
    assert_eq!(s.rays_by_kind()["camera"], u64::from(w * h * spp));
    assert!(!s.origin_bounds.is_empty() && s.hit_bounds.max[1] <= 1.01);
}

#[test]
fn typed_and_bytes_payloads_and_custom_kinds() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let payload = PayloadSchema::new(
        vec![
            PayloadField::list("throughput", DataType::Float32, 3).unwrap(),
            PayloadField::scalar("pdf", DataType::Float64).unwrap(),
            PayloadField::scalar("inside", DataType::Boolean).unwrap(),
        ],
        Some(BytesPayload::Variable),
    )
    .unwrap();
    let options = RecorderOptions { payload, kinds: vec!["photon".into()], ..Default::default() };
    let rec = Recorder::create(&path, options).unwrap();
    let photon = rec.register_kind("photon").unwrap();
    let probe = rec.register_kind("probe").unwrap();
    assert!(photon.0 >= Kind::FIRST_CUSTOM && probe.0 > photon.0);
    let mut tree = rec.begin_tree(0, 0, 0);
    let rgb = [0.5f32, 0.25, 1.0];
    tree.add_ray(
        &f(photon, Some(1.0)),
        Payload {
            values: &[Value::List(ListValue::F32(&rgb)), Value::F64(0.125), Value::Bool(true)],
            bytes: Some(b"hello"),
        },
    );
    tree.descend();
    tree.add_ray(&f(probe, None), Payload::values(&[Value::Null, Value::F64(2.0), Value::Bool(false)]));
    tree.ascend();
    let id = tree.end();
    rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    let t = ds.tree(id).unwrap();
    assert_eq!(t.rays[0].kind, photon);
    assert_eq!(t.rays[1].kind, probe);
    assert_eq!(ds.kinds().name(probe), Some("probe"));
    let tp = t.column("throughput").unwrap().as_fixed_size_list();
    assert_eq!(tp.value(0).as_primitive::<Float32Type>().values().to_vec(), rgb.to_vec());
    assert!(arrow::array::Array::is_null(tp, 1));
    let bytes = t.column("payload").unwrap().as_binary::<i32>();
    assert_eq!(bytes.value(0), b"hello");
    assert_eq!(ds.manifest().payload.len(), 3);
    assert_eq!(ds.manifest().payload[0].type_name, "float32[3]");
}

#[test]
fn misuse_is_reported_by_finish_and_data_is_kept() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let payload = PayloadSchema::new(vec![PayloadField::scalar("w", DataType::Float32).unwrap()], None).unwrap();
    let rec = Recorder::create(&path, RecorderOptions { payload, ..Default::default() }).unwrap();
    let mut t = rec.begin_tree(0, 0, 0);
    t.descend(); // nothing to descend into
    t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::values(&[Value::F64(1.0)])); // wrong type
    t.ascend(); // above the root
    t.add_ray_under(RayId(40), &f(Kind::SHADOW, None), Payload::NONE); // no such parent
    let id = t.end();
    let unended = rec.begin_tree(1, 1, 0);
    drop(unended);
    let err = rec.finish().err().unwrap();
    let Error::Misuse { count, first } = &err else { panic!("{err}") };
    assert_eq!(*count, 5, "{first:?}");
    let msg = err.to_string();
    assert!(msg.contains("descend") && msg.contains("`w` expected float32") && msg.contains("never ended"), "{msg}");
    let ds = Dataset::open(&path).unwrap();
    let tree = ds.tree(id).unwrap();
    assert_eq!(tree.rays.len(), 2);
    assert!(arrow::array::Array::is_null(tree.column("w").unwrap(), 0));
    assert!(ds.check().is_ok());
}

#[test]
fn write_failure_is_reported_and_sealed_trees_survive() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    for i in 0..100 {
        let mut t = rec.begin_tree(i, 0, 0);
        t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
        t.end();
    }
    rec.flush().unwrap();
    // The segment directory becomes unwritable (a file stands in its place; works as root too).
    std::fs::rename(path.join("segments"), path.join("segments.away")).unwrap();
    std::fs::write(path.join("segments"), b"not a directory").unwrap();
    for i in 0..100 {
        let mut t = rec.begin_tree(i, 1, 0);
        t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
        t.end();
    }
    let err = rec.finish().err().unwrap();
    assert!(matches!(err, Error::Write { lost_trees: 100, .. }), "{err}");
    assert!(err.to_string().contains("segments"), "{err}");
    std::fs::remove_file(path.join("segments")).unwrap();
    std::fs::rename(path.join("segments.away"), path.join("segments")).unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree_count(), 100);
    assert!(!ds.manifest().complete);
    assert!(ds.check().is_ok());
}

#[test]
fn memory_budget_bounds_what_waits_for_the_workers() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let budget = 1 << 20;
    let options = RecorderOptions { memory_budget: budget, chunk_rays: 4096, ..Default::default() };
    let rec = Recorder::create(&path, options).unwrap();
    for i in 0..20_000u32 {
        let mut t = rec.begin_tree(i % 100, i / 100, 0);
        rl::demo::trace_pixel(&mut t, i % 100, i / 100, 0, 100, 200);
        t.end();
    }
    let s = rec.finish().unwrap();
    assert!(s.rays > 60_000);
    assert!(s.peak_buffered_bytes > 0);
    // One chunk may exceed what is left of the budget; never more than budget + one chunk.
    let chunk_bytes = 4096 * 60;
    assert!(s.peak_buffered_bytes as usize <= budget + chunk_bytes, "peak {} > budget {budget}", s.peak_buffered_bytes);
}

#[test]
fn immediate_mode_is_readable_while_recording() {
    let (rec, trace) = Recorder::immediate(RecorderOptions::default()).unwrap();
    let reader = trace.clone();
    let (tx, rx) = std::sync::mpsc::channel::<TreeId>();
    let viewer = std::thread::spawn(move || {
        // The viewer sees each tree as soon as it ends, while recording goes on.
        let mut seen = HashMap::new();
        while let Ok(id) = rx.recv_timeout(Duration::from_secs(10)) {
            let t = reader.tree(id).unwrap().expect("ended tree is visible at once");
            seen.insert(id, t.rays.len());
        }
        seen
    });
    let mut want = HashMap::new();
    for i in 0..200u32 {
        let mut t = rec.begin_tree(i % 20, i / 20, 0);
        rl::demo::trace_pixel(&mut t, i % 20, i / 20, 0, 20, 10);
        let n = t.ray_count() as usize;
        let id = t.end();
        want.insert(id, n);
        tx.send(id).unwrap();
    }
    drop(tx);
    let seen = viewer.join().unwrap();
    assert_eq!(seen, want);
    assert_eq!(trace.trees_at_pixel(3, 2, None).unwrap().len(), 1);
    let s = rec.finish().unwrap();
    assert_eq!(s.trees, 200);
    assert_eq!(trace.stats().trees, 200);
    // Read mode works over immediate mode too.
    let mut r = Reader::new(Box::new(trace));
    assert!(r.read_tree().unwrap().is_some());
    assert!(r.read_ray().unwrap().is_some());
}

#[test]
fn immediate_mode_evicts_oldest_trees_over_budget() {
    let options = RecorderOptions { memory_budget: 64 * 1024, ..Default::default() };
    let (rec, trace) = Recorder::immediate(options).unwrap();
    let mut ids = Vec::new();
    for i in 0..3000u32 {
        let mut t = rec.begin_tree(i, 0, 0);
        t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
        ids.push(t.end());
    }
    let s = rec.finish().unwrap();
    assert!(s.evicted_trees > 0);
    assert!(trace.tree(ids[0]).unwrap().is_none(), "oldest evicted");
    assert!(trace.tree(*ids.last().unwrap()).unwrap().is_some(), "newest kept");
    assert_eq!(trace.tree_count() as u64 + s.evicted_trees, 3000);
}

#[test]
fn read_mode_cursor() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    for i in 0..10u32 {
        let mut t = rec.begin_tree(i, 0, 0);
        for _ in 0..=i {
            t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
        }
        t.end();
    }
    rec.finish().unwrap();
    let mut r = Reader::open(&path).unwrap();
    let mut trees = 0;
    let mut rays = 0;
    while let Some(t) = r.read_tree().unwrap() {
        let n = t.rays.len();
        trees += 1;
        let mut k = 0;
        while r.read_ray().unwrap().is_some() {
            k += 1;
        }
        assert_eq!(k, n);
        rays += k;
        if !r.next_tree().unwrap() {
            break;
        }
    }
    assert_eq!((trees, rays), (10, 55));
    r.seek_tree_id(TreeId(7)).unwrap();
    assert_eq!(r.read_tree().unwrap().unwrap().info.pixel, [7, 0]);
    r.seek_ray(5);
    assert_eq!(r.read_ray().unwrap().unwrap().index, 5);
    r.reset().unwrap();
    assert_eq!(r.read_tree().unwrap().unwrap().info.id, TreeId(0));
    assert!(r.seek_tree_id(TreeId(99)).is_err());
    assert_eq!(r.stats().rays, 55);
}

#[test]
fn big_trees_and_empty_recordings() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let options = RecorderOptions { chunk_rays: 1000, ..Default::default() };
    let rec = Recorder::create(&path, options).unwrap();
    // An empty tree first, so it opens the segment.
    rec.begin_tree(9, 9, 0).end();
    rec.flush().unwrap();
    let mut t = rec.begin_tree(0, 0, 0);
    for _ in 0..5000 {
        t.add_ray(&f(Kind::DIFFUSE, Some(1.0)), Payload::NONE);
    }
    t.end();
    let empty = rec.begin_tree(1, 0, 0);
    empty.end();
    rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree(TreeId(0)).unwrap().rays.len(), 0);
    assert_eq!(ds.tree(TreeId(1)).unwrap().rays.len(), 5000);
    assert_eq!(ds.tree(TreeId(2)).unwrap().rays.len(), 0);
    assert_eq!(ds.trees().map(|t| t.unwrap().rays.len()).sum::<usize>(), 5000);
    let report = ds.check();
    assert!(report.is_ok(), "{:?}", report.errors);
    assert_eq!(report.trees, 3);

    let path2 = dir.path().join("empty");
    Recorder::create(&path2, RecorderOptions::default()).unwrap().finish().unwrap();
    let ds = Dataset::open(&path2).unwrap();
    assert_eq!(ds.tree_count(), 0);
    assert!(ds.check().is_ok());
}

/// Trees may be begun on one thread and ended on another (a wavefront renderer hands paths
/// between threads): nothing is reported as unended, and every tree is in the dataset.
#[test]
fn trees_ended_on_other_threads_are_not_reported_unended() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    let mut begun = Vec::new();
    for i in 0..200u32 {
        let mut t = rec.begin_tree(i, 0, 0);
        t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
        begun.push(t);
    }
    let (a, b): (Vec<_>, Vec<_>) = begun.into_iter().enumerate().partition(|(i, _)| i % 2 == 0);
    std::thread::scope(|s| {
        for half in [a, b] {
            s.spawn(move || {
                for (_, t) in half {
                    t.end();
                }
            });
        }
    });
    // One left open on yet another thread is reported, once.
    let rec2 = rec.clone();
    std::thread::spawn(move || std::mem::forget(rec2.begin_tree(9, 9, 9))).join().unwrap();
    let err = rec.finish().expect_err("the unended tree is reported");
    let Error::Misuse { count, first } = &err else { panic!("{err}") };
    assert_eq!(*count, 1, "{first:?}");
    assert!(first[0].starts_with("1 trees were begun and never ended"), "{first:?}");
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree_count(), 200);
}

/// Tables are written in the background: `write_table` returns at once, `flush`/`finish` wait for
/// them, and a table that cannot be written comes back from `flush` naming the path, while the
/// trees recorded beside it are kept.
#[test]
fn tables_are_written_in_the_background_and_their_failures_reported() {
    use arrow::array::{RecordBatch, UInt32Array};
    let batch =
        || RecordBatch::try_from_iter([("id", std::sync::Arc::new(UInt32Array::from(vec![1, 2, 3])) as _)]).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    // A known table must match its schema (store::scene): refused at once, naming the column.
    let e = rec.write_table("bvh_nodes", batch()).unwrap_err().to_string();
    assert!(e.contains("`node_id` is missing"), "{e}");
    rec.write_table("my_table", batch()).unwrap();
    assert!(rec.write_table("bad name", batch()).is_err(), "a bad name is refused at once");
    let mut t = rec.begin_tree(0, 0, 0);
    t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
    let id = t.end();
    rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.table("my_table").unwrap().unwrap().num_rows(), 3);
    assert_eq!(ds.tree(id).unwrap().rays.len(), 1);

    // A file where the tables directory should be: the background write fails.
    let path = dir.path().join("trace2");
    let rec = Recorder::create(&path, RecorderOptions::default()).unwrap();
    std::fs::write(path.join("tables"), b"in the way").unwrap();
    rec.write_table("my_other_table", batch()).unwrap();
    let mut t = rec.begin_tree(1, 1, 0);
    t.add_ray(&f(Kind::CAMERA, Some(1.0)), Payload::NONE);
    let id = t.end();
    let err = rec.flush().expect_err("the failed table is reported").to_string();
    assert!(err.contains("tables"), "{err}");
    rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree(id).unwrap().rays.len(), 1);
    assert!(ds.table("my_other_table").unwrap().is_none());
}

/// Several writers share one chunk queue: `flush` returns only once every tree ended before it
/// is sealed and listed, while another thread keeps recording (its chunks may be taken before or
/// after the flush; the flushed trees are never left behind in a writer's open segment).
#[test]
fn flush_with_many_writers_seals_every_tree_ended_before_it() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("trace");
    let options =
        RecorderOptions { chunk_rays: 64, workers: 3, seal_interval: Duration::from_secs(3600), ..Default::default() };
    let rec = Recorder::create(&path, options).unwrap();
    let (w, h) = (2000u32, 2000u32);
    let stop = AtomicBool::new(false);
    std::thread::scope(|s| {
        let (rec2, stop) = (rec.clone(), &stop);
        s.spawn(move || {
            let mut i = 0u32;
            while !stop.load(Ordering::Relaxed) {
                let (x, y) = (i % w, i / w % 500);
                let mut tree = rec2.begin_tree(x, y, 0);
                rl::demo::trace_pixel(&mut tree, x, y, 0, w, h);
                tree.end();
                i += 1;
            }
        });
        for round in 0..6u32 {
            let y = 1000 + round;
            for x in 0..150 {
                let mut tree = rec.begin_tree(x, y, 0);
                rl::demo::trace_pixel(&mut tree, x, y, 0, w, h);
                tree.end();
            }
            rec.flush().unwrap();
            let ds = Dataset::open(&path).unwrap();
            for x in 0..150 {
                assert_eq!(ds.trees_at_pixel(x, y, None).unwrap().len(), 1, "round {round} pixel {x}");
            }
        }
        stop.store(true, Ordering::Relaxed);
    });
    let summary = rec.finish().unwrap();
    let ds = Dataset::open(&path).unwrap();
    assert_eq!(ds.tree_count(), summary.trees);
    assert!(ds.check().is_ok());
}
