#![allow(clippy::unwrap_used)]
//! A GPU trace is a dataset like any other: every ray the GPU traced is recorded as the CPU
//! tracers record theirs, trees replay exactly, and its ray statistics are the CPU tracer's.

use std::path::Path;

use gpu_tracer::GpuTracer;
use renderers::{BuiltinScene, Bvh, RenderOptions, Scene};
use rl::{Kind, Recorder, RecorderOptions};
use store::Dataset;

fn record(
    scene: &Scene,
    opts: &RenderOptions,
    dir: &Path,
    gpu: Option<&GpuTracer>,
) -> (renderers::Film, renderers::RenderStats) {
    let bvh = Bvh::build(&scene.tris);
    let rec =
        Recorder::create(dir, RecorderOptions { payload: renderers::payload_schema(), ..Default::default() }).unwrap();
    let tracer = if gpu.is_some() { renderers::TracerChoice::Gpu } else { renderers::TracerChoice::Path };
    renderers::describe_recording(&rec, scene, &bvh, tracer, opts).unwrap();
    let out = match gpu {
        Some(g) => g.render_recorded(opts, Some(&rec), &|_| {}).unwrap(),
        None => renderers::render(scene, &bvh, tracer, opts, Some(&rec), &|_| {}).unwrap(),
    };
    rec.finish().unwrap();
    out
}

fn f32s(t: &store::Tree, col: &str) -> Vec<f32> {
    use arrow::array::AsArray;
    let list = t.column(col).unwrap().as_fixed_size_list();
    list.values().as_primitive::<arrow::datatypes::Float32Type>().values().to_vec()
}

#[test]
fn a_gpu_trace_is_a_dataset_like_any_other() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::CornellGlass.build(1).unwrap();
    let gpu = GpuTracer::new(&scene, &Bvh::build(&scene.tris)).unwrap();
    let (w, h, spp) = (24, 20, 4);
    let opts = RenderOptions { width: w, height: h, spp, threads: 2, seed: 5, ..Default::default() };
    let (film, stats) = record(&scene, &opts, &tmp.path().join("gpu"), Some(&gpu));
    let ds = Dataset::open(tmp.path().join("gpu")).unwrap();
    let report = ds.check();
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(ds.ray_count(), stats.rays);
    assert_eq!(ds.tree_count(), u64::from(w * h * spp));
    assert_eq!(stats.samples, u64::from(w * h * spp));
    let kinds = ds.stats().rays_by_kind();
    for (k, n) in &stats.rays_by_kind {
        let name = store::KindTable::default().name(*k).unwrap().to_string();
        assert_eq!(kinds[&name], *n, "{name}: recorded as many as traced");
    }
    for k in ["camera", "shadow", "diffuse", "specular", "transmission"] {
        assert!(kinds[k] > 0, "the glass box traces {k} rays");
    }
    // Every camera ray carries its sample's radiance back: their mean is the pixel.
    let mut sums = vec![glam::Vec3A::ZERO; (w * h) as usize];
    for t in ds.trees() {
        let t = t.unwrap();
        let rad = f32s(&t, "radiance");
        let root = t.rays.iter().find(|r| r.parent.is_none()).unwrap();
        assert_eq!(root.kind, Kind::CAMERA);
        assert_eq!(t.rays.iter().filter(|r| r.parent.is_none()).count(), 1, "one camera ray per tree");
        let i = root.index as usize * 3;
        sums[(t.info.pixel[1] * w + t.info.pixel[0]) as usize] += glam::Vec3A::new(rad[i], rad[i + 1], rad[i + 2]);
        for r in &t.rays {
            if let Some(p) = r.parent {
                let parent = &t.rays[p as usize];
                if r.kind != Kind::SHADOW {
                    assert_eq!(parent.depth + 1, r.depth, "a traced ray is one deeper than its parent");
                }
            }
        }
    }
    for (i, (s, p)) in sums.iter().zip(&film.pixels).enumerate() {
        let mean = *s / spp as f32;
        assert!((mean - *p).abs().max_element() <= 1e-4 * (1.0 + p.max_element()), "pixel {i}: {mean} vs {p}");
    }
    // Immediate mode: one pixel sample traced again is the same tree, ray for ray.
    let (x, y, s) = (11, 9, 2);
    let one = RenderOptions { window: Some([x, y, x + 1, y + 1]), samples: Some(s..s + 1), ..opts.clone() };
    record(&scene, &one, &tmp.path().join("one"), Some(&gpu));
    let again = Dataset::open(tmp.path().join("one")).unwrap();
    let a = again.trees_at_pixel(x, y, Some(s)).unwrap();
    let b = ds.trees_at_pixel(x, y, Some(s)).unwrap();
    assert_eq!((a.len(), b.len()), (1, 1));
    assert!(a[0].rays.len() >= 2);
    assert_eq!(format!("{:?}", a[0].rays), format!("{:?}", b[0].rays));
    assert_eq!(again.tree_count(), 1);
}

#[test]
fn gpu_and_cpu_traces_have_the_same_ray_statistics() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::CornellGlass.build(1).unwrap();
    let gpu = GpuTracer::new(&scene, &Bvh::build(&scene.tris)).unwrap();
    let opts = RenderOptions { width: 32, height: 24, spp: 16, threads: 2, seed: 1, ..Default::default() };
    record(&scene, &opts, &tmp.path().join("cpu"), None);
    record(&scene, &opts, &tmp.path().join("gpu"), Some(&gpu));
    let c = Dataset::open(tmp.path().join("cpu")).unwrap().stats().rays_by_kind_depth.clone();
    let g = Dataset::open(tmp.path().join("gpu")).unwrap().stats().rays_by_kind_depth.clone();
    let mut compared = 0;
    for (kind, by_depth) in &c {
        for (depth, &n) in by_depth.iter().enumerate() {
            let m = g.get(kind).and_then(|v| v.get(depth)).copied().unwrap_or(0);
            if n < 300 {
                continue;
            }
            // counts of independent paths: a few standard deviations of a Poisson count, and 3 %
            let tol = 5.0 * (n as f64).sqrt() + 0.03 * n as f64;
            eprintln!("{kind:>13} depth {depth}: cpu {n:>7} gpu {m:>7}");
            assert!((m as f64 - n as f64).abs() <= tol, "{kind} at depth {depth}: {n} on the CPU, {m} on the GPU");
            compared += 1;
        }
    }
    assert!(compared >= 10, "compared {compared} (kind, depth) cells");
}

#[test]
fn what_the_gpu_cannot_record_is_an_error() {
    let scene = BuiltinScene::Cornell.build(1).unwrap();
    let gpu = GpuTracer::new(&scene, &Bvh::build(&scene.tris)).unwrap();
    let base = RenderOptions { width: 8, height: 8, spp: 1, ..Default::default() };
    let tmp = tempfile::tempdir().unwrap();
    let rec = Recorder::create(
        tmp.path().join("t"),
        RecorderOptions { payload: renderers::payload_schema(), ..Default::default() },
    )
    .unwrap();
    let err = |o: RenderOptions| gpu.render_recorded(&o, Some(&rec), &|_| {}).err().unwrap().to_string();
    assert!(err(RenderOptions { record_visits: true, ..base.clone() }).contains("BVH nodes"));
    assert!(err(RenderOptions { window: Some([4, 4, 9, 5]), ..base.clone() }).contains("window 4,4,9,5"));
    assert!(err(RenderOptions { max_depth: 64, ..base.clone() }).contains("depth 63 at most"));
    assert!(err(RenderOptions { samples: Some(3..3), ..base.clone() }).contains("empty"));
    // Nothing was recorded by the refused calls; the recorder still works.
    assert_eq!(rec.finish().unwrap().trees, 0);
}
