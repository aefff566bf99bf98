#![allow(clippy::unwrap_used)]
//! Known answers (white furnace, energy), OBJ/MTL, determinism, the injected bug, and that every
//! traced ray is recorded.

use std::collections::HashMap;
use std::path::Path;

use glam::Vec3A;
use renderers::geometry::Ray;
use renderers::sampling::Rng;
use renderers::scene::MaterialKind;
use renderers::{Bug, BuiltinScene, Bvh, Camera, Material, RenderOptions, Scene, TracerChoice, TraversalStats};
use rl::{Dataset, Kind, Recorder, RecorderOptions};

/// A closed cube, wound inwards, every face diffuse with albedo `a` and emission `le`.
fn furnace(a: f32, le: f32) -> Scene {
    let mut tris = Vec::new();
    for axis in 0..3 {
        for side in [-1.0f32, 1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let p = |x: f32, y: f32| {
                let mut c = [0.0; 3];
                c[axis] = side;
                c[u] = x;
                c[v] = y;
                Vec3A::from_array(c)
            };
            tris.push([p(-1.0, -1.0), p(1.0, -1.0), p(1.0, 1.0)]);
            tris.push([p(-1.0, -1.0), p(1.0, 1.0), p(-1.0, 1.0)]);
        }
    }
    let mut m = Material::diffuse("furnace", [a; 3]);
    m.emission = Vec3A::splat(le);
    let cam =
        Camera { position: Vec3A::new(0.1, 0.2, 0.3), target: Vec3A::new(0.0, 0.0, -1.0), up: Vec3A::Y, fov_y: 90.0 };
    let n = tris.len();
    Scene::new("furnace", tris, vec![0; n], vec![m], cam).unwrap()
}

#[test]
fn white_furnace_matches_the_analytic_radiance() {
    for (a, le) in [(0.5f32, 1.0f32), (0.8, 0.5)] {
        let scene = furnace(a, le);
        let bvh = Bvh::build(&scene.tris);
        let opts = RenderOptions {
            width: 24,
            height: 24,
            spp: 32,
            seed: 11,
            max_depth: 200,
            threads: 2,
            ..Default::default()
        };
        let (film, _) = renderers::render(&scene, &bvh, TracerChoice::Path, &opts, None, &|_| {}).unwrap();
        let v: Vec<f32> = film.pixels.iter().map(|p| p.x).collect();
        let n = v.len() as f32;
        let mean = v.iter().sum::<f32>() / n;
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / (n - 1.0);
        let sigma = (var / n).sqrt();
        let expected = le / (1.0 - a);
        assert!(
            (mean - expected).abs() < 4.0 * sigma + 0.005 * expected,
            "albedo {a}, emission {le}: mean {mean} vs analytic {expected} (σ of mean {sigma})"
        );
    }
}

#[test]
fn no_material_creates_energy() {
    let mut rng = Rng::for_sample(5, 0, 0, 0);
    let mats = [
        Material::diffuse("d", [0.9, 0.5, 0.1]),
        Material {
            kind: MaterialKind::Glossy,
            specular: Vec3A::splat(0.6),
            exponent: 50.0,
            ..Material::diffuse("g", [0.4, 0.4, 0.4])
        },
        Material {
            kind: MaterialKind::Glossy,
            specular: Vec3A::splat(0.9),
            exponent: 2.0,
            ..Material::diffuse("g2", [0.1, 0.1, 0.1])
        },
        Material { kind: MaterialKind::Mirror, specular: Vec3A::splat(0.95), ..Material::diffuse("m", [0.0; 3]) },
    ];
    let n = Vec3A::Y;
    for m in &mats {
        for k in 0..20 {
            // Directional albedo E[f cos / pdf] for an incoming direction at elevation k.
            let theta = (k as f32 + 0.5) / 20.0 * std::f32::consts::FRAC_PI_2;
            let d = -Vec3A::new(theta.sin(), theta.cos(), 0.0);
            let mut sum = Vec3A::ZERO;
            let count = 20_000;
            for _ in 0..count {
                if let Some(s) = renderers::material::sample(m, n, d, &mut rng) {
                    assert!(s.weight.is_finite());
                    sum += s.weight;
                }
            }
            let albedo = sum / count as f32;
            assert!(albedo.max_element() <= 1.0 + 0.02, "{}: albedo {albedo:?} at θ={theta}", m.name);
        }
    }
    // Fresnel: reflected + transmitted = 1 at every angle, total internal reflection beyond critical.
    for k in 0..=10 {
        let c = k as f32 / 10.0;
        let (f, _) = renderers::material::fresnel(c, 1.0, 1.5);
        assert!((0.0..=1.0).contains(&f));
        let (f_in, _) = renderers::material::fresnel(c, 1.5, 1.0);
        if c < (1.0f32 - (1.0 / 1.5f32).powi(2)).sqrt() {
            assert_eq!(f_in, 1.0, "total internal reflection at cos {c}");
        }
    }
}

fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn obj_and_mtl_materials_and_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    write(
        d,
        "m.mtl",
        "newmtl white\nKd 0.8 0.8 0.8\nnewmtl shiny\nKd 0.5 0.5 0.5\nKs 0.8 0.8 0.8\nNs 64\nnewmtl mirror\nKs 0.9 0.9 0.9\nillum 5\n\
         newmtl glass\nNi 1.45\nd 0.1\nillum 7\nnewmtl lamp\nKd 0 0 0\nKe 10 10 10\n",
    );
    let obj = write(
        d,
        "s.obj",
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 2 2\n\
         usemtl white\nf 1 2 3\nusemtl shiny\nf 1 3 4\nusemtl mirror\nf 1 2 4\nusemtl glass\nf 2 3 4\nusemtl lamp\nf 1 2 3\n\
         f 1 1 5\n",
    );
    let s = renderers::load_obj(&obj, None).unwrap();
    let kind = |name: &str| s.materials.iter().find(|m| m.name == name).unwrap().kind;
    assert_eq!(kind("white"), MaterialKind::Diffuse);
    assert_eq!(kind("shiny"), MaterialKind::Glossy);
    assert_eq!(kind("mirror"), MaterialKind::Mirror);
    assert_eq!(kind("glass"), MaterialKind::Dielectric);
    let shiny = s.materials.iter().find(|m| m.name == "shiny").unwrap();
    assert!((shiny.diffuse + shiny.specular).max_element() <= 1.0 + 1e-6, "scaled to conserve energy");
    assert_eq!(s.materials.iter().find(|m| m.name == "glass").unwrap().ior, 1.45);
    assert_eq!(s.report.emitters, 1);
    assert_eq!(s.report.degenerate_skipped, 1);
    assert_eq!(s.report.triangles, 5);

    let bad = write(d, "nan.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n");
    let e = renderers::load_obj(&bad, None).err().unwrap().to_string();
    assert!(e.contains("nan.obj:3") && e.contains("NaN"), "{e}");
    let bad = write(d, "inf.obj", "v 0 0 0\nv 1 0 inf\nv 0 1 0\nf 1 2 3\n");
    assert!(renderers::load_obj(&bad, None).err().unwrap().to_string().contains("inf.obj:2"));
    let bad = write(d, "short.obj", "v 0 0\n");
    assert!(renderers::load_obj(&bad, None).err().unwrap().to_string().contains("short.obj:1"));
    let bad = write(d, "face.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
    let e = renderers::load_obj(&bad, None).err().unwrap().to_string();
    assert!(e.contains("face.obj"), "{e}");
    let bad = write(d, "nomtl.obj", "mtllib missing.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    let e = renderers::load_obj(&bad, None).err().unwrap().to_string();
    assert!(e.contains("nomtl.obj") && e.contains("material library"), "{e}");
    let e = renderers::load_obj(&d.join("absent.obj"), None).err().unwrap().to_string();
    assert!(e.contains("absent.obj"), "{e}");
    let bad = write(d, "empty.obj", "v 0 0 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n");
    assert!(renderers::load_obj(&bad, None).err().unwrap().to_string().contains("no usable triangles"));
}

fn record(scene: &Scene, opts: &RenderOptions, dir: &Path) -> (renderers::Film, renderers::RenderStats) {
    record_with(scene, TracerChoice::Path, opts, dir)
}

fn record_with(
    scene: &Scene,
    tracer: TracerChoice,
    opts: &RenderOptions,
    dir: &Path,
) -> (renderers::Film, renderers::RenderStats) {
    let bvh = Bvh::build(&scene.tris);
    let rec =
        Recorder::create(dir, RecorderOptions { payload: renderers::payload_schema(), ..Default::default() }).unwrap();
    renderers::describe_recording(&rec, scene, &bvh, tracer, opts).unwrap();
    let out = renderers::render(scene, &bvh, tracer, opts, Some(&rec), &|_| {}).unwrap();
    rec.finish().unwrap();
    out
}

#[test]
fn every_traced_ray_is_recorded_with_its_costs() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::CornellGlass.build(1).unwrap();
    let opts = RenderOptions { width: 24, height: 24, spp: 4, threads: 2, record_visits: true, ..Default::default() };
    let (_, stats) = record(&scene, &opts, &tmp.path().join("t"));
    let ds = Dataset::open(tmp.path().join("t")).unwrap();
    assert_eq!(ds.ray_count(), stats.rays);
    assert_eq!(ds.tree_count(), 24 * 24 * 4);
    assert!(ds.check().is_ok());
    let kinds = ds.stats().rays_by_kind();
    assert!(kinds["transmission"] > 0 && kinds["specular"] > 0 && kinds["shadow"] > 0 && kinds["diffuse"] > 0);
    let nodes = ds.table("bvh_nodes").unwrap().unwrap();
    assert_eq!(nodes.num_rows(), Bvh::build(&scene.tris).node_count());
    assert_eq!(ds.table("lights").unwrap().unwrap().num_rows(), 2);
    assert_eq!(ds.manifest().attributes["scene"], "cornell-glass");
    // Visited-node lists agree with the per-ray counts.
    let visits = ds.table("ray_nodes").unwrap().unwrap();
    // Leaf visits that found a triangle, per ray.
    let mut leaf_hits = std::collections::HashMap::<(u64, u32), u32>::new();
    {
        use arrow::array::{Array, AsArray};
        use arrow::datatypes::{UInt32Type, UInt64Type};
        let ids = visits.column_by_name("tree_id").unwrap().as_primitive::<UInt64Type>();
        let rays = visits.column_by_name("ray").unwrap().as_primitive::<UInt32Type>();
        let steps = visits.column_by_name("step").unwrap().as_primitive::<UInt32Type>();
        let nodes = visits.column_by_name("node_id").unwrap().as_primitive::<UInt32Type>();
        let hit = visits.column_by_name("leaf_hit").unwrap().as_boolean();
        let leaves = nodes_table_leaves(&ds);
        for i in 0..visits.num_rows() {
            if steps.value(i) == 0 {
                assert_eq!(nodes.value(i), 0, "every visit list starts at the root");
            }
            let leaf = leaves[nodes.value(i) as usize];
            assert_eq!(hit.is_valid(i), leaf, "leaf_hit is set exactly on leaves");
            if hit.is_valid(i) && hit.value(i) {
                *leaf_hits.entry((ids.value(i), rays.value(i))).or_default() += 1;
            }
        }
    }
    let mut sum_nodes = 0u64;
    for t in ds.trees() {
        let t = t.unwrap();
        let nv =
            arrow::array::AsArray::as_primitive::<arrow::datatypes::UInt32Type>(t.column("nodes_visited").unwrap());
        for r in &t.rays {
            let n = u64::from(nv.value(r.index as usize));
            sum_nodes += n;
            let hits = leaf_hits.get(&(t.info.id.0, r.index)).copied().unwrap_or(0);
            if r.kind == Kind::SHADOW {
                assert!(hits <= 1, "an any-hit traversal stops at its first hit");
            } else {
                assert_eq!(hits > 0, r.t.is_some(), "a closest-hit ray hits in some leaf exactly when it hits");
            }
            let boxes =
                arrow::array::AsArray::as_primitive::<arrow::datatypes::UInt32Type>(t.column("box_tests").unwrap());
            assert!(boxes.value(r.index as usize) >= 1, "every traced ray tests at least the root box");
            if r.kind == Kind::CAMERA && r.t.is_some() {
                assert!(n >= 2, "a camera ray that hits entered the root and a leaf");
            }
        }
    }
    assert_eq!(visits.num_rows() as u64, sum_nodes);

    // A scene without glass records no transmission kind at all.
    let plain = BuiltinScene::Cornell.build(1).unwrap();
    let (_, _) =
        record(&plain, &RenderOptions { width: 16, height: 16, spp: 2, ..Default::default() }, &tmp.path().join("p"));
    let ds = Dataset::open(tmp.path().join("p")).unwrap();
    assert!(!ds.manifest().kinds.contains_key("transmission"));
    assert!(ds.table("ray_nodes").unwrap().is_none());
}

#[test]
fn any_sample_replays_identically() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::Glossy.build(1).unwrap();
    let full = RenderOptions { width: 20, height: 16, spp: 3, seed: 42, threads: 2, ..Default::default() };
    record(&scene, &full, &tmp.path().join("full"));
    let (x, y, s) = (13, 9, 2);
    let one = RenderOptions { window: Some([x, y, x + 1, y + 1]), samples: Some(s..s + 1), threads: 1, ..full.clone() };
    record(&scene, &one, &tmp.path().join("one"));
    let a = Dataset::open(tmp.path().join("full")).unwrap().trees_at_pixel(x, y, Some(s)).unwrap();
    let b = Dataset::open(tmp.path().join("one")).unwrap().trees_at_pixel(x, y, Some(s)).unwrap();
    assert_eq!((a.len(), b.len()), (1, 1));
    assert_eq!(a[0].rays, b[0].rays);
    assert!(a[0].rays.len() > 1);
    for col in ["throughput", "radiance", "nodes_visited"] {
        assert_eq!(a[0].column(col).unwrap(), b[0].column(col).unwrap(), "{col}");
    }
}

/// Whether a ray from `o` along `d` reaches an emitter of the scene (ignoring occluders).
fn aims_at_light(scene: &Scene, o: Vec3A, d: Vec3A) -> bool {
    let ray = Ray::new(o, d);
    scene.lights.iter().any(|&l| {
        let [a, b, c] = scene.tris[l as usize];
        renderers::geometry::intersect_triangle(&ray, a, b, c, 0.0, f32::INFINITY).is_some()
    })
}

#[test]
fn injected_shadow_bug_is_in_the_trace_but_not_in_the_look() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::Cornell.build(1).unwrap();
    let base = RenderOptions { width: 32, height: 32, spp: 8, seed: 9, threads: 2, ..Default::default() };
    let mut wrong = HashMap::new();
    let mut means = HashMap::new();
    for bug in [None, Some(Bug::ShadowDir)] {
        let dir = tmp.path().join(format!("{bug:?}"));
        let (film, _) = record(&scene, &RenderOptions { bug, ..base.clone() }, &dir);
        let ds = Dataset::open(&dir).unwrap();
        let (mut total, mut bad) = (0, 0);
        for t in ds.trees() {
            for r in t.unwrap().rays.iter().filter(|r| r.kind == Kind::SHADOW) {
                total += 1;
                if !aims_at_light(&scene, Vec3A::from_array(r.origin), Vec3A::from_array(r.direction)) {
                    bad += 1;
                }
            }
        }
        assert!(total > 1000);
        wrong.insert(bug.is_some(), bad as f64 / total as f64);
        means.insert(bug.is_some(), film.mean());
    }
    assert_eq!(wrong[&false], 0.0, "a correct trace has no shadow ray aimed at no light");
    assert!(wrong[&true] > 0.05, "the bug leaves wrong shadow rays: {}", wrong[&true]);
    let rel = ((means[&true] - means[&false]).abs() / means[&false]).max_element();
    assert!(rel < 0.1, "the image still looks plausible: mean differs {:.1}%", rel * 100.0);
}

#[test]
fn whitted_tracer_records_shadow_specular_and_transmission_rays() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = BuiltinScene::CornellGlass.build(1).unwrap();
    let opts = RenderOptions { width: 24, height: 24, spp: 1, threads: 2, ..Default::default() };
    let (film, stats) = record_with(&scene, TracerChoice::Whitted, &opts, &tmp.path().join("w"));
    assert!(film.pixels.iter().all(|p| p.is_finite()));
    let ds = Dataset::open(tmp.path().join("w")).unwrap();
    assert_eq!(ds.ray_count(), stats.rays);
    let k = ds.stats().rays_by_kind();
    assert!(k["shadow"] > 0 && k["specular"] > 0 && k["transmission"] > 0);
    assert!(!k.contains_key("diffuse"), "Whitted traces no diffuse bounces");
    assert!(ds.check().is_ok());
    let _ = TraversalStats::default();
}

#[test]
fn error_falls_as_one_over_root_samples() {
    let scene = BuiltinScene::Cornell.build(1).unwrap();
    let bvh = Bvh::build(&scene.tris);
    let base = RenderOptions { width: 16, height: 16, threads: 2, ..Default::default() };
    let (_, points) = renderers::converge::convergence(&scene, &bvh, &base, 1024, &[2, 4, 8, 16, 32]).unwrap();
    // Relative RMSE weighs every pixel by its own scale; linear RMSE on a tiny image is dominated
    // by a few pixels on the edge of the (radiance 17) light, so it is only checked to fall.
    let rel = renderers::converge::log_log_slope(
        &points.iter().map(|p| (f64::from(p.spp), p.rel_mse.sqrt())).collect::<Vec<_>>(),
    );
    assert!((-0.75..=-0.3).contains(&rel), "log-log slope of relative RMSE {rel}, expected near -0.5: {points:?}");
    assert!(points.last().unwrap().rmse < points[0].rmse * 0.6);
    let tmp = tempfile::tempdir().unwrap();
    renderers::converge::write_plot(&points, &tmp.path().join("c.png")).unwrap();
    assert!(tmp.path().join("c.png").metadata().unwrap().len() > 1000);
}

/// Leaf flags of the `bvh_nodes` table, by node id.
fn nodes_table_leaves(ds: &Dataset) -> Vec<bool> {
    use arrow::array::AsArray;
    let nodes = ds.table("bvh_nodes").unwrap().unwrap();
    let leaf = nodes.column_by_name("is_leaf").unwrap().as_boolean();
    (0..nodes.num_rows()).map(|i| leaf.value(i)).collect()
}

/// The `Tracer` trait renders what `renderers::render` renders; its progressive image is the
/// mean of one-sample renders; names parse both ways and a bad one is named.
#[test]
fn the_tracer_trait_renders_as_the_driver_does() {
    use renderers::{CpuTracer, Tracer, TracerChoice};
    let scene = std::sync::Arc::new(BuiltinScene::Cornell.build(1).unwrap());
    let bvh = std::sync::Arc::new(Bvh::build(&scene.tris));
    for choice in [TracerChoice::Path, TracerChoice::Whitted] {
        let t = CpuTracer::new(choice, scene.clone(), bvh.clone()).unwrap();
        assert_eq!(t.choice(), choice);
        let opts = RenderOptions { width: 16, height: 12, spp: 2, threads: 2, ..Default::default() };
        let (a, sa) = t.render(&opts, None, &|_| {}).unwrap();
        let (b, sb) = renderers::render(&scene, &bvh, choice, &opts, None, &|_| {}).unwrap();
        assert_eq!(a.pixels, b.pixels, "{choice}");
        assert_eq!(sa.rays, sb.rays);
        let mut p = t.progressive(16, 12, 0, 8).unwrap();
        p.add(3).unwrap();
        assert_eq!(p.spp(), 3);
        let mean = p.mean().unwrap();
        let mut sum = vec![glam::Vec3A::ZERO; 16 * 12];
        for s in 0..3u64 {
            let o = RenderOptions { spp: 1, seed: s, ..opts.clone() };
            let (f, _) = renderers::render(&scene, &bvh, choice, &o, None, &|_| {}).unwrap();
            sum.iter_mut().zip(&f.pixels).for_each(|(a, b)| *a += *b);
        }
        for (m, s) in mean.pixels.iter().zip(&sum) {
            assert!((*m - *s / 3.0).abs().max_element() < 1e-5, "{choice}: {m} vs {}", *s / 3.0);
        }
    }
    for name in TracerChoice::NAMES {
        assert_eq!(name.parse::<TracerChoice>().unwrap().name(), *name);
    }
    assert_eq!("cpu".parse::<TracerChoice>().unwrap(), TracerChoice::Path);
    assert!("raymarch".parse::<TracerChoice>().unwrap_err().to_string().contains("raymarch"));
    assert!(CpuTracer::new(TracerChoice::Gpu, scene.clone(), bvh.clone()).is_err());
    let gpu_opts = RenderOptions::default();
    let gpu = renderers::render(&scene, &bvh, TracerChoice::Gpu, &gpu_opts, None, &|_| {});
    assert!(gpu.unwrap_err().to_string().contains("gpu"));
}
