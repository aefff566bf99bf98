#![allow(clippy::unwrap_used)]
//! The layered visualizer on a small recorded Cornell box: registration, depth composition,
//! lazy re-rendering, bad input, and each layer's picture against a stored PNG.
//!
//! Needs a GPU adapter: on a machine without a GPU, Mesa's lavapipe (`mesa-vulkan-drivers`) or
//! llvmpipe on wgpu's GL backend (`libegl-mesa0`); `scripts/check.sh` installs both and runs these
//! tests on each (`WGPU_BACKEND=gl` for the second) against the same stored pictures.
//! `UPDATE_SNAPSHOTS=1` rewrites them (look at them before committing).

use std::path::Path;

#[path = "../../tests/common/snapshot.rs"]
mod snapshot;
use rtvtk_viz::{ComponentId, Gpu, Pipeline, Sources, ViewCamera};
use serde_json::{Value, json};
use snapshot::snapshot;

#[path = "../../tests/common/fixture.rs"]
mod fixture;
use fixture::{H, W, dataset};

fn pipeline(layers: &[(&str, Value)]) -> Pipeline {
    let gpu = Gpu::shared().expect("a GPU adapter");
    let mut p = Pipeline::new(gpu, Sources::open(dataset()).unwrap());
    for (k, s) in layers {
        p.add(k, s).unwrap();
    }
    p
}

fn lit(img: &image::RgbaImage) -> usize {
    img.pixels().filter(|p| p.0[..3].iter().any(|c| *c > 40)).count()
}

#[test]
fn camera_rays_project_back_onto_their_pixels() {
    // Registration: the camera ray of pixel (x, y) goes through film position (x + jx, y + jy),
    // jx, jy in [0, 1): projected back it must land in that pixel, within half a pixel of its
    // centre, for every pixel (corners included).
    let s = Sources::open(dataset()).unwrap();
    let cam = s.camera.expect("the dataset records its camera");
    let frame = s.frame();
    let b = s
        .query("SELECT pixel_x, pixel_y, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays WHERE kind = 'camera'")
        .unwrap();
    let mut n = 0;
    let mut corners = 0;
    let mut worst = 0.0f64;
    for batch in &b {
        use arrow::array::AsArray;
        use arrow::datatypes::{Float32Type, UInt32Type};
        let u = |i: usize| batch.column(i).as_primitive::<UInt32Type>().clone();
        let f = |i: usize| batch.column(i).as_primitive::<Float32Type>().clone();
        let (px, py) = (u(0), u(1));
        let cols: Vec<_> = (2..9).map(f).collect();
        for r in 0..batch.num_rows() {
            let o = [0, 1, 2].map(|k| f64::from(cols[k].value(r)));
            let d = [3, 4, 5].map(|k| f64::from(cols[k].value(r)));
            use arrow::array::Array;
            let t = if cols[6].is_null(r) { 1000.0 } else { f64::from(cols[6].value(r)).min(2000.0) };
            let p = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
            let q = cam.project(p, frame.anchor, frame.radius, W, H).unwrap();
            let (x, y) = (f64::from(px.value(r)), f64::from(py.value(r)));
            let e = (q[0] - (x + 0.5)).abs().max((q[1] - (y + 0.5)).abs());
            worst = worst.max(e);
            assert!(e <= 0.5 + 1e-3, "pixel ({x}, {y}) projects to ({:.3}, {:.3})", q[0], q[1]);
            if (x == 0.0 || x == f64::from(W - 1)) && (y == 0.0 || y == f64::from(H - 1)) {
                corners += 1;
            }
            n += 1;
        }
    }
    assert_eq!(n, (W * H * 2) as usize);
    assert_eq!(corners, 8);
    assert!(worst > 0.05, "jittered camera rays should not all hit pixel centres ({worst})");
}

#[test]
fn composition_hides_a_segment_behind_the_tall_box() {
    // Two vertical segments at the tall box's x: one behind it (z = 500, box spans z 247..456),
    // one in front (z = 150). With the composition layer below, only the front one shows.
    let sql = "SELECT 370.0 AS origin_x, 60.0 AS origin_y, z AS origin_z, 0.0 AS dir_x, 1.0 AS dir_y, 0.0 AS dir_z, 200.0 AS t \
               FROM (VALUES (500.0), (150.0)) v(z)";
    let q = json!({"sql": sql, "line_width": 3.0});
    let s = Sources::open(dataset()).unwrap();
    let cam = s.camera.unwrap();
    let f = s.frame();
    let at = |z: f64| {
        let p = cam.project([370.0, 160.0, z], f.anchor, f.radius, 4 * W, 4 * H).unwrap();
        (p[0] as u32, p[1] as u32)
    };
    let (back, front) = (at(500.0), at(150.0));
    assert!(front.0 + 6 < back.0 || back.0 + 6 < front.0, "segments apart on screen: {front:?} {back:?}");
    let bright = |img: &image::RgbaImage, (x, y): (u32, u32)| img.get_pixel(x, y).0[..3].iter().any(|c| *c > 100);
    let mut with = pipeline(&[("composition", Value::Null), ("query", q.clone())]);
    with.resize(4 * W, 4 * H).unwrap();
    let img = with.snapshot(false).unwrap();
    assert!(bright(&img, front), "the segment in front of the box is visible");
    assert!(!bright(&img, back), "the segment behind the box is hidden");
    // Picking sees what the picture shows: the front segment, not the one behind the box.
    let front_pick = with.pick([front.0, front.1], 2).unwrap().expect("the front segment is picked");
    assert!(matches!(front_pick.item, rtvtk_viz::component::Picked::Row { .. }), "{front_pick:?}");
    assert_eq!(with.pick([back.0, back.1], 2).unwrap(), None, "no pick through the tall box");
    let mut without = pipeline(&[("query", q)]);
    without.resize(4 * W, 4 * H).unwrap();
    let img = without.snapshot(false).unwrap();
    assert!(bright(&img, front) && bright(&img, back), "without composition both segments show");
    assert!(without.pick([back.0, back.1], 2).unwrap().is_some(), "without composition it is picked");
}

#[test]
fn only_changed_layers_are_rendered_again() {
    let mut p = pipeline(&[
        ("image", Value::Null),
        ("composition", Value::Null),
        ("geometry", Value::Null),
        ("rays", json!({"pixel": [48, 54]})),
    ]);
    let counts = |p: &Pipeline| p.layers().iter().map(|l| l.renders).collect::<Vec<_>>();
    p.render().unwrap();
    assert_eq!(counts(&p), [1, 1, 1, 1]);
    p.render().unwrap();
    assert_eq!(counts(&p), [1, 1, 1, 1], "nothing changed: nothing re-rendered");
    // Only the ray layer's own camera changes.
    let rays = p.layers()[3].component.id();
    let mut c = p.camera();
    c.orbit(0.4, 0.1);
    p.layer_mut(rays).unwrap().camera = Some(c);
    p.render().unwrap();
    assert_eq!(counts(&p), [1, 1, 1, 2]);
    // The shared camera: the scene-space layers follow it, so does the image (source "auto": away
    // from the recorded camera it is traced from the view), and the ray layer keeps its own camera.
    p.set_camera(c).unwrap();
    p.render().unwrap();
    assert_eq!(counts(&p), [2, 2, 2, 2]);
    // A setting of one layer.
    let geo = p.layers()[2].component.id();
    p.layer_mut(geo).unwrap().component.set_settings(&json!({"style": "opaque"})).unwrap();
    p.render().unwrap();
    assert_eq!(counts(&p), [2, 2, 3, 2]);
    // Hidden layers do no work.
    p.layer_mut(geo).unwrap().component.set_settings(&json!({"style": "transparent"})).unwrap();
    p.layer_mut(geo).unwrap().enabled = false;
    p.render().unwrap();
    assert_eq!(counts(&p), [2, 2, 3, 2]);
    p.reorder(rays, 0).unwrap();
    assert_eq!(p.layers()[0].component.id(), rays);
    assert_eq!(
        p.remove(ComponentId(999)).err().map(|e| e.to_string()),
        Some("invalid setting: no component with id 999".into())
    );
}

#[test]
fn bad_input_gets_clear_errors() {
    let mut p = pipeline(&[]);
    let e = p.add("raytrees", &Value::Null).unwrap_err().to_string();
    assert!(e.contains("unknown layer \"raytrees\"") && e.contains("rays, bvh"), "{e}");
    p.add("query", &json!({"sql": "SELECT tree_id FROM rays LIMIT 3"})).unwrap();
    let e = p.render().map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("origin_x") && e.contains("x, y, z") && e.contains("tree_id"), "{e}");
    let mut p = pipeline(&[]);
    let e = p.add("rays", &json!({"kinds": ["camera'; DROP"]})).unwrap_err().to_string();
    assert!(e.contains("not a kind name"), "{e}");
    let e = p.add("bvh", &json!({"levels": [5, 2]})).unwrap_err().to_string();
    assert!(e.contains("empty"), "{e}");
    let e = p.add("heatmap", &json!({"map": "rainbow"})).unwrap_err().to_string();
    assert!(e.contains("viridis"), "{e}");
    let mut c = p.camera();
    c.target = c.position;
    assert!(p.set_camera(c).unwrap_err().to_string().contains("equals its target"));
    assert!(p.resize(0, 10).is_err());
    // NaN and infinite rays are skipped and counted.
    p.add("query", &json!({"sql": "SELECT 1.0 AS origin_x, 'NaN'::float AS origin_y, 0.0 AS origin_z, 0.0 AS dir_x, 1.0 AS dir_y, 0.0 AS dir_z UNION ALL SELECT 100.0, 100.0, 100.0, 0.0, 1.0, 0.0"})).unwrap();
    p.render().unwrap();
    let r = p.report().join("\n");
    assert!(r.contains("query: 1 rows drawn") && r.contains("skipped 1 of 2"), "{r}");
}

#[test]
fn a_dataset_without_scene_tables_renders_what_it_can() {
    // Remove the triangles table and the camera from a copy: rays still draw, the geometry layer
    // is not offered, and the missing pieces are named.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("old");
    copy_dir(dataset(), &dir);
    let mpath = dir.join("manifest.json");
    let mut m: Value = serde_json::from_str(&std::fs::read_to_string(&mpath).unwrap()).unwrap();
    m["tables"].as_object_mut().unwrap().remove("triangles");
    for k in ["camera.position", "camera.target", "camera.up", "camera.fov_y", "image.png"] {
        m["attributes"].as_object_mut().unwrap().remove(k);
    }
    std::fs::write(&mpath, serde_json::to_string(&m).unwrap()).unwrap();
    std::fs::remove_file(dir.join("image.png")).unwrap();
    let s = Sources::open(&dir).unwrap();
    assert!(s.missing.iter().any(|m| m.contains("no triangles table")), "{:?}", s.missing);
    assert!(s.missing.iter().any(|m| m.contains("no camera attributes")));
    let mut p = Pipeline::new(Gpu::shared().unwrap(), s);
    let e = p.add("geometry", &Value::Null).unwrap_err().to_string();
    assert!(e.contains("not available") && e.contains("triangles"), "{e}");
    assert!(p.add("image", &Value::Null).is_err());
    p.add("rays", &json!({"max_rays": 20000})).unwrap();
    let img = p.snapshot(true).unwrap();
    assert!(lit(&img) > 500, "rays are drawn: {} lit pixels", lit(&img));
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

#[test]
fn each_layer_matches_its_stored_picture() {
    let orbit = {
        let s = Sources::open(dataset()).unwrap();
        let mut c: ViewCamera = s.camera.unwrap();
        c.position = [460.0, 480.0, -650.0];
        c.target = [278.0, 200.0, 280.0];
        c
    };
    type Case<'a> = (&'a str, Vec<(&'a str, Value)>, Option<ViewCamera>);
    let cases: Vec<Case> = vec![
        ("image", vec![("image", Value::Null)], None),
        ("geometry_wireframe", vec![("geometry", Value::Null)], Some(orbit)),
        ("geometry_opaque", vec![("geometry", json!({"style": "opaque"}))], Some(orbit)),
        ("geometry_transparent", vec![("geometry", json!({"style": "transparent", "opacity": 0.35}))], Some(orbit)),
        (
            "rays_tree",
            vec![("geometry", json!({"opacity": 0.3})), ("rays", json!({"pixel": [48, 54], "line_width": 2.0}))],
            Some(orbit),
        ),
        ("bvh_levels", vec![("bvh", json!({"levels": [0, 3]}))], Some(orbit)),
        (
            "bvh_visits",
            vec![("bvh", json!({"levels": [4, 9], "only_visited": true, "colour": "visits", "map": "inferno"}))],
            Some(orbit),
        ),
        (
            "query_hits",
            vec![
                ("geometry", json!({"opacity": 0.3})),
                (
                    "query",
                    json!({"sql": "SELECT origin_x AS x, origin_y AS y, origin_z AS z, depth FROM rays WHERE kind = 'shadow'", "colour_by": "depth", "line_width": 2.0}),
                ),
            ],
            Some(orbit),
        ),
        ("heatmap", vec![("heatmap", Value::Null)], None),
        (
            "rays_density",
            vec![
                ("geometry", json!({"opacity": 0.3})),
                ("composition", Value::Null),
                ("rays", json!({"max_rays": null, "style": "density"})),
            ],
            Some(orbit),
        ),
        (
            "query_alpha",
            vec![
                ("geometry", json!({"style": "transparent", "opacity": 0.35})),
                ("composition", Value::Null),
                (
                    "query",
                    json!({"sql": "SELECT origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t, depth FROM rays WHERE kind = 'diffuse'", "colour_by": "depth", "style": "alpha"}),
                ),
            ],
            Some(orbit),
        ),
        (
            "layered",
            vec![
                ("image", Value::Null),
                ("composition", Value::Null),
                ("rays", json!({"pixel": [48, 54], "line_width": 2.0})),
            ],
            None,
        ),
    ];
    for (name, layers, camera) in cases {
        let mut p = pipeline(&layers);
        p.resize(4 * W, 4 * H).unwrap();
        if let Some(c) = camera {
            p.set_camera(c).unwrap();
        }
        let img = p.snapshot(true).unwrap();
        assert!(lit(&img) > 100, "{name}: the picture is empty");
        snapshot(name, &img);
    }
}

#[test]
fn the_image_layer_refines_progressively_with_the_cpu_tracer() {
    // No stored image needed: the image layer path-traces the scene at the pipeline's camera, one
    // sample per pixel per idle call, and is re-rendered only when a sample was added.
    let mut p = pipeline(&[("image", json!({"source": "trace", "max_spp": 3}))]);
    let id = p.layers()[0].component.id();
    let mut changed = 0;
    for _ in 0..5 {
        if p.idle().unwrap() {
            changed += 1;
        }
        p.render().unwrap();
    }
    assert_eq!(changed, 3, "stops at max_spp");
    assert_eq!(p.layers()[0].renders, 3);
    // Its convergence curve: one point per sample from the second on, the error estimated from
    // the half images (no reference), positive and falling or level as time goes on.
    let curve = p.layers()[0].component.convergence();
    assert_eq!(curve.iter().map(|c| c.spp).collect::<Vec<_>>(), [2, 3], "{curve:?}");
    assert!(curve.iter().all(|c| c.rmse.is_finite() && c.rmse > 0.0 && c.secs > 0.0), "{curve:?}");
    assert!(curve[1].secs > curve[0].secs, "{curve:?}");
    let img = p.snapshot(false).unwrap();
    assert!(lit(&img) > (W * H / 3) as usize, "the traced Cornell box is lit: {}", lit(&img));
    // A new camera restarts the accumulation.
    let mut c = p.camera();
    c.orbit(0.2, 0.0);
    p.set_camera(c).unwrap();
    assert!(p.idle().unwrap());
    assert!(p.report().iter().any(|r| r.contains("1 samples per pixel")), "{:?}", p.report());
    assert!(p.layers()[0].component.convergence().is_empty(), "a new camera starts a new curve");
    assert!(p.layer_mut(id).is_ok());
}

#[test]
fn the_image_follows_the_camera_and_returns_to_the_recorded_picture() {
    // Source "auto" (the default): the recorded picture at the recorded camera; elsewhere the
    // view is path-traced (GPU tracer where the adapter runs it) and never the recorded picture
    // misregistered under the rays; back at the recorded camera, the recorded picture again.
    let mut p = pipeline(&[("image", json!({"max_spp": 4})), ("composition", Value::Null)]);
    assert_eq!(p.layers()[0].component.settings()["source"], "auto");
    let recorded = p.snapshot(false).unwrap();
    assert!(!p.idle().unwrap(), "at the recorded camera there is nothing to trace");
    let home = p.camera();
    let mut c = home;
    c.orbit(0.5, 0.15);
    p.set_camera(c).unwrap();
    // Before a sample is traced the moved view shows no picture at all (the background).
    let empty = p.snapshot(false).unwrap();
    assert!(lit(&empty) < (W * H / 50) as usize, "no stale picture: {} lit pixels", lit(&empty));
    let mut calls = 0;
    while p.idle().unwrap() {
        calls += 1;
        assert!(calls <= 4, "stops at max_spp");
    }
    assert!(
        p.report().iter().any(|r| r.contains("path traced") && r.contains("4 samples per pixel")),
        "{:?}",
        p.report()
    );
    let orbited = p.snapshot(false).unwrap();
    assert!(lit(&orbited) > (W * H / 3) as usize, "the orbited view is traced: {}", lit(&orbited));
    let differ = recorded.pixels().zip(orbited.pixels()).filter(|(a, b)| a != b).count();
    assert!(differ > (W * H / 4) as usize, "the orbited view is not the recorded picture: {differ} pixels differ");
    // Reset: the recorded picture, exactly.
    p.set_camera(home).unwrap();
    assert!(!p.idle().unwrap());
    assert_eq!(p.snapshot(false).unwrap(), recorded);
    assert!(!p.report().iter().any(|r| r.contains("path traced")), "{:?}", p.report());
    // The source is one of four values; anything else is refused naming them.
    let id = p.layers()[0].component.id();
    let e = p.layer_mut(id).unwrap().component.set_settings(&json!({"source": "magic"})).unwrap_err().to_string();
    assert!(e.contains("auto") && e.contains("gpu"), "{e}");
    assert_eq!(p.layers()[0].component.choices(), [("source", rtvtk_viz::components::picture::ImageSource::NAMES)]);
    for name in rtvtk_viz::components::picture::ImageSource::NAMES {
        p.layer_mut(id).unwrap().component.set_settings(&json!({ "source": name })).unwrap();
    }
}

#[test]
fn the_output_texture_is_what_a_window_samples_without_a_read_back() {
    // The viewer's window registers the pipeline's output with egui-wgpu, whose native textures
    // are gamma-space Rgba8Unorm: the picture's own bytes, the same texture frame after frame.
    let mut p = pipeline(&[("image", Value::Null), ("composition", Value::Null), ("rays", json!({"pixel": [48, 54]}))]);
    let picture = p.snapshot(false).unwrap();
    let gpu = p.gpu.clone();
    let out = p.render().unwrap().clone();
    assert_eq!(out.format(), wgpu::TextureFormat::Rgba8Unorm);
    assert_eq!(gpu.read_rgba(&out).unwrap(), picture.into_raw());
    let mut c = p.camera();
    c.orbit(0.1, 0.0);
    p.set_camera(c).unwrap();
    assert_eq!(p.render().unwrap(), &out, "the same texture, drawn again");
}

#[test]
fn where_the_gpu_tracer_cannot_run_the_image_is_traced_on_the_cpu_and_says_so() {
    // An adapter that cannot run the GPU tracer (as an old GL driver: 8 storage buffers per stage,
    // the tracer binds 12): source "gpu" traces on the CPU instead, never a failed picture, and
    // its report says why once.
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let backends = wgpu::Backends::from_env().unwrap_or(wgpu::Backends::all());
    let adapter = rtvtk_gpu::ranked(pollster::block_on(instance.enumerate_adapters(backends)))
        .into_iter()
        .next()
        .expect("a GPU adapter");
    let limits = wgpu::Limits { max_storage_buffers_per_shader_stage: 8, ..adapter.limits() };
    let desc = wgpu::DeviceDescriptor { required_limits: limits, ..rtvtk_gpu::device_descriptor(&adapter) };
    let (device, queue) = pollster::block_on(adapter.request_device(&desc)).unwrap();
    let gpu = Gpu::from_device(&adapter, device, queue);
    let e = gpu.compute_support(12).unwrap_err().to_string();
    assert!(e.contains("8 storage buffers"), "{e}");
    let mut p = Pipeline::new(gpu, Sources::open(dataset()).unwrap());
    p.add("image", &json!({"source": "gpu", "max_spp": 2})).unwrap();
    while p.idle().unwrap() {}
    let r = p.report();
    assert_eq!(
        r.iter().filter(|l| l.contains("cannot run here") && l.contains("tracing on the CPU")).count(),
        1,
        "{r:?}"
    );
    assert!(r.iter().any(|l| l.contains("path traced, 2 samples per pixel")), "{r:?}");
    assert!(!r.iter().any(|l| l.contains("on the GPU")), "{r:?}");
    assert!(lit(&p.snapshot(false).unwrap()) > (W * H / 3) as usize, "a picture all the same");
}

#[test]
fn every_choice_a_component_offers_is_a_setting_it_takes() {
    // The viewer draws `choices` as drop-downs: each value must be one the settings accept, and
    // one not offered is refused.
    let mut p = pipeline(&[]);
    let mut offered = 0;
    for info in rtvtk_viz::registry() {
        if (info.offered)(&p.sources).is_err() {
            continue;
        }
        // The query layer has no default query.
        let settings = match info.kind {
            "query" => json!({"sql": "SELECT origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays LIMIT 1"}),
            _ => Value::Null,
        };
        let id = p.add(info.kind, &settings).unwrap_or_else(|e| panic!("{}: {e}", info.kind));
        let choices = p.layers().iter().find(|l| l.component.id() == id).unwrap().component.choices();
        for (key, values) in choices {
            let c = &mut p.layer_mut(id).unwrap().component;
            for v in values {
                // As the viewer changes one setting: the others kept.
                let mut s = c.settings();
                s[key] = json!(v);
                c.set_settings(&s).unwrap_or_else(|e| panic!("{} {key}={v}: {e}", info.kind));
                assert_eq!(c.settings()[key], *v, "{} {key}", info.kind);
                offered += 1;
            }
            let mut s = c.settings();
            s[key] = json!("no-such-value");
            assert!(c.set_settings(&s).is_err(), "{} {key}", info.kind);
        }
    }
    assert!(offered >= 9, "image source, geometry style and ray tracer at least: {offered}");
}

#[test]
fn ctrl_click_traces_a_pixel_with_no_dataset_loaded() {
    // Immediate mode: the scene alone (no dataset), the ray layer traces one pixel's tree through
    // `rl` immediate mode and draws it at once; a pixel outside the view is refused.
    let scene = renderers::BuiltinScene::Cornell.build(1).unwrap();
    let sources = Sources::from_scene(scene, 4 * W, 4 * H).unwrap();
    let mut p = Pipeline::new(Gpu::shared().unwrap(), sources);
    p.add("geometry", &json!({"opacity": 0.2})).unwrap();
    let rays = p.add("rays", &Value::Null).unwrap();
    let before = p.snapshot(false).unwrap();
    let traced = p.trace_ray(rays, [2 * W, 3 * H]).unwrap().expect("the ray layer traces");
    assert!(traced.rays >= 2, "a camera ray and what it spawned: {traced:?}");
    let after = p.snapshot(true).unwrap();
    assert!(lit(&after) > lit(&before) + 50, "the traced tree is drawn: {} -> {}", lit(&before), lit(&after));
    assert!(p.legends().iter().any(|l| matches!(l, rtvtk_viz::Legend::Swatches { title, .. } if title == "ray kinds")));
    assert!(p.trace_ray(rays, [4 * W, 0]).unwrap_err().to_string().contains("outside"));
    // No dataset: layers that need one are not offered.
    assert!(p.add("heatmap", &Value::Null).unwrap_err().to_string().contains("not available"));
}

fn mean_rgb(img: &image::RgbaImage) -> f64 {
    img.pixels().map(|p| f64::from(p.0[0]) + f64::from(p.0[1]) + f64::from(p.0[2])).sum::<f64>()
        / img.pixels().len() as f64
}

#[test]
fn the_image_layer_refines_on_the_gpu_to_the_cpu_picture() {
    // Source "gpu": the GPU path tracer adds batches of samples per idle call (two equal halves,
    // so the convergence estimate works as for the CPU) until max_spp; its picture is the CPU
    // tracer's within noise.
    let mut p = pipeline(&[("image", json!({"source": "gpu", "max_spp": 64}))]);
    let mut calls = 0;
    while p.idle().unwrap() {
        calls += 1;
        assert!(calls < 64, "stops at max_spp");
    }
    assert!(p.report().iter().any(|r| r.contains("on the GPU, 64 samples per pixel")), "{:?}", p.report());
    let curve = p.layers()[0].component.convergence();
    assert!(curve.len() >= 2 && curve.last().unwrap().rmse < curve[0].rmse, "{curve:?}");
    let gpu = p.snapshot(false).unwrap();
    let mut q = pipeline(&[("image", json!({"source": "trace", "max_spp": 64}))]);
    while q.idle().unwrap() {}
    let cpu = q.snapshot(false).unwrap();
    let (g, c) = (mean_rgb(&gpu), mean_rgb(&cpu));
    eprintln!("mean sRGB sum: gpu {g:.2} cpu {c:.2}");
    assert!(lit(&gpu) > (W * H / 3) as usize);
    assert!((g / c - 1.0).abs() < 0.03, "GPU picture {g} against the CPU's {c}");
    // Back to the CPU: a new image.
    let id = p.layers()[0].component.id();
    p.layer_mut(id).unwrap().component.set_settings(&json!({"source": "trace", "max_spp": 2})).unwrap();
    assert!(p.idle().unwrap());
    assert!(p.report().iter().any(|r| r.contains("path traced, 1 samples per pixel")), "{:?}", p.report());
}

#[test]
fn ctrl_click_traces_a_pixel_on_the_gpu() {
    // Immediate mode with the GPU tracer: the pixel's rays are recorded on the GPU, handed to
    // `rl` immediate mode and drawn, as with the CPU tracer.
    let scene = renderers::BuiltinScene::CornellGlass.build(1).unwrap();
    let sources = Sources::from_scene(scene, 4 * W, 4 * H).unwrap();
    let mut p = Pipeline::new(Gpu::shared().unwrap(), sources);
    p.add("geometry", &json!({"opacity": 0.2})).unwrap();
    let rays = p.add("rays", &json!({"tracer": "gpu"})).unwrap();
    let before = p.snapshot(false).unwrap();
    let traced = p.trace_ray(rays, [2 * W, 3 * H]).unwrap().expect("the ray layer traces");
    assert!(traced.rays >= 2, "a camera ray and what it spawned: {traced:?}");
    let after = p.snapshot(true).unwrap();
    assert!(lit(&after) > lit(&before) + 50, "the traced tree is drawn: {} -> {}", lit(&before), lit(&after));
    assert!(p.trace_ray(rays, [4 * W, 0]).unwrap_err().to_string().contains("outside"));
}

/// The ray layer reads the store itself (no SQL engine): for every kind of filter it must load
/// exactly the rays the same filters select in SQL.
#[test]
fn the_ray_layer_loads_what_its_filters_select_in_sql() {
    use rtvtk_viz::components::rays::{Rays, RaysSettings};
    let gpu = Gpu::shared().expect("a GPU adapter");
    let sources = Sources::open(dataset()).unwrap();
    let some_tree: u64 = {
        let b =
            sources.query("SELECT tree_id FROM trees WHERE pixel_x = 50 AND pixel_y = 40 ORDER BY tree_id").unwrap();
        let c = b[0].column(0).as_any().downcast_ref::<arrow::array::UInt64Array>().unwrap();
        c.value(c.len() - 1)
    };
    let base = RaysSettings { max_rays: None, ..Default::default() };
    let cases = [
        base.clone(),
        RaysSettings { kinds: Some(vec!["shadow".into()]), ..base.clone() },
        RaysSettings { kinds: Some(vec!["diffuse".into(), "camera".into()]), depth: Some([1, 2]), ..base.clone() },
        RaysSettings { kinds: Some(vec![]), ..base.clone() },
        RaysSettings { pixel: Some([50, 40]), ..base.clone() },
        RaysSettings { pixel: Some([50, 40]), sample: Some(1), ..base.clone() },
        RaysSettings { sample: Some(0), depth: Some([0, 0]), ..base.clone() },
        RaysSettings { tree: Some(some_tree), ray_upto: Some(1), ..base.clone() },
        RaysSettings { tree: Some(u64::MAX), ..base.clone() },
        RaysSettings { pixel: Some([95, 71]), ..base.clone() },
        RaysSettings { max_rays: Some(1000), ..base.clone() },
    ];
    for s in cases {
        let sql = format!(
            "SELECT count(*) FROM (SELECT * FROM rays WHERE {}{})",
            s.predicate().unwrap(),
            s.max_rays.map_or(String::new(), |n| format!(" LIMIT {n}"))
        );
        let b = sources.query(&sql).unwrap();
        let want = b[0].column(0).as_any().downcast_ref::<arrow::array::Int64Array>().unwrap().value(0) as u64;
        let mut rays = Rays::new(ComponentId(1), &sources, &serde_json::to_value(&s).unwrap()).unwrap();
        rays.load(&gpu, &sources, sources.frame()).unwrap();
        assert_eq!(rays.segment_count(), want, "{s:?}");
        if s.tree == Some(some_tree) || s.pixel == Some([50, 40]) {
            assert!(want > 0, "{s:?} selects rays");
        }
    }
}

/// A cancelled load stops at its first batch, keeps what it has (nothing here), says so, and the
/// next load after `reset` loads everything.
#[test]
fn a_cancelled_ray_load_keeps_what_it_has_and_says_so() {
    use rtvtk_viz::Component;
    use rtvtk_viz::component::Progress;
    use rtvtk_viz::components::rays::Rays;
    let gpu = Gpu::shared().expect("a GPU adapter");
    let sources = Sources::open(dataset()).unwrap();
    let mut rays = Rays::new(ComponentId(1), &sources, &Value::Null).unwrap();
    let progress = Progress::default();
    progress.cancel();
    rays.load_with(&gpu, &sources, sources.frame(), &progress).unwrap();
    assert_eq!(rays.segment_count(), 0);
    assert!(rays.report().iter().any(|r| r.contains("cancelled")), "{:?}", rays.report());
    assert!(progress.get().is_none(), "the load ended");
    progress.reset();
    rays.load_with(&gpu, &sources, sources.frame(), &progress).unwrap();
    let ds = store::Dataset::open(dataset()).unwrap();
    assert_eq!(rays.segment_count(), ds.ray_count());
    assert!(!rays.report().iter().any(|r| r.contains("cancelled")), "{:?}", rays.report());
}

/// While the camera moves the viewer asks for a preview: the ray layer draws every k-th segment
/// (at most the budget), other layers are not drawn again, and clearing it draws all again.
#[test]
fn a_preview_thins_the_ray_layer_only() {
    let mut p = pipeline(&[("composition", Value::Null), ("rays", json!({"max_rays": null, "line_width": 1.0}))]);
    p.resize(4 * W, 4 * H).unwrap();
    let full = lit(&p.snapshot(false).unwrap());
    let renders = |p: &Pipeline| p.layers().iter().map(|l| l.renders).collect::<Vec<_>>();
    assert_eq!(renders(&p), [1, 1]);
    p.preview = Some(300);
    let thin = lit(&p.snapshot(false).unwrap());
    assert_eq!(renders(&p), [1, 2], "only the ray layer draws the preview");
    assert!(thin * 2 < full, "a 300-segment preview lights fewer pixels: {thin} of {full}");
    assert!(thin > 0, "but some");
    p.preview = None;
    assert_eq!(lit(&p.snapshot(false).unwrap()), full, "all segments again");
    assert_eq!(renders(&p), [1, 3]);
}

/// Segments `(x, z, colour name)` as a query: vertical, from y = 60 up 200 units.
fn vertical_segments(rows: &[(f64, f64, &str)], order: &str) -> String {
    let values: Vec<String> = rows.iter().enumerate().map(|(i, (x, z, c))| format!("({i}, {x}, {z}, '{c}')")).collect();
    format!(
        "SELECT x AS origin_x, 60.0 AS origin_y, z AS origin_z, 0.0 AS dir_x, 1.0 AS dir_y, 0.0 AS dir_z, 200.0 AS t, c \
         FROM (VALUES {}) v(k, x, z, c) ORDER BY k {order}",
        values.join(", ")
    )
}

#[test]
fn density_counts_rays_per_pixel_and_hides_those_behind_surfaces() {
    // Seven segments on one line in front of the tall box, three behind it: one pixel wide in
    // the density style, each pixel of the front line counts 7, and the composition hides the
    // three behind the box as they are counted.
    let mut rows = vec![(370.0, 150.0, "a"); 7];
    rows.extend([(370.0, 500.0, "a"); 3]);
    let q = json!({"sql": vertical_segments(&rows, "ASC"), "style": "density", "density_scale": "linear"});
    let s = Sources::open(dataset()).unwrap();
    let (cam, f) = (s.camera.unwrap(), s.frame());
    let at = |z: f64| {
        let p = cam.project([370.0, 160.0, z], f.anchor, f.radius, 4 * W, 4 * H).unwrap();
        (p[0] as u32, p[1] as u32)
    };
    let (front, back) = (at(150.0), at(500.0));
    let mut p = pipeline(&[("composition", Value::Null), ("query", q.clone())]);
    p.resize(4 * W, 4 * H).unwrap();
    let img = p.snapshot(false).unwrap();
    let report = p.report().join("\n");
    assert!(report.contains("density style, at most 7 rays on one pixel"), "{report}");
    let bar = p.legends().into_iter().find_map(|l| match l {
        rtvtk_viz::Legend::ColourBar { title, min, max, log, .. } => Some((title, min, max, log)),
        _ => None,
    });
    assert_eq!(bar, Some(("rays per pixel".to_string(), 0.0, 7.0, false)));
    let lum = |(x, y): (u32, u32)| img.get_pixel(x, y).0[..3].iter().map(|c| u32::from(*c)).max().unwrap_or(0);
    assert!(lum(front) > 150, "the front line at full density: {:?}", img.get_pixel(front.0, front.1));
    assert!(lum(back) < 40, "the line behind the box is hidden: {:?}", img.get_pixel(back.0, back.1));
    // Without the occluder the back line counts too, at 3 of 7: linear, so dimmer than the front.
    let mut p = pipeline(&[("query", q)]);
    p.resize(4 * W, 4 * H).unwrap();
    let img2 = p.snapshot(false).unwrap();
    let lum2 = |(x, y): (u32, u32)| img2.get_pixel(x, y).0[..3].iter().map(|c| u32::from(*c)).max().unwrap_or(0);
    assert!(lum2(back) > 40 && lum2(back) + 40 < lum2(front), "back {} front {}", lum2(back), lum2(front));
}

#[test]
fn the_alpha_style_does_not_depend_on_draw_order() {
    // A red and a blue line cross (different depths); drawn in either order, the alpha style
    // gives the same picture, with both colours at the crossing.
    let rows = [(300.0, 150.0, "red"), (300.0, 152.0, "blue")];
    let sql = |order: &str| {
        let v = vertical_segments(&rows, order);
        // Tilt the second: dir_x from the row's colour, so the lines cross half way up.
        v.replace("0.0 AS dir_x", "CASE WHEN c = 'blue' THEN 0.4 ELSE -0.4 END AS dir_x")
            .replace("x AS origin_x", "CASE WHEN c = 'blue' THEN x - 40.0 ELSE x + 40.0 END AS origin_x")
    };
    let draw = |order: &str| {
        // Coloured by the row number: two integer categories, in value order whatever the row order.
        let q = json!({"sql": sql(order).replace("t, c", "t, c, k"), "colour_by": "k", "style": "alpha", "opacity": 0.6, "line_width": 4.0});
        let mut p = pipeline(&[("query", q)]);
        p.resize(4 * W, 4 * H).unwrap();
        p.snapshot(false).unwrap()
    };
    let (a, b) = (draw("ASC"), draw("DESC"));
    assert!(lit(&a) > 100);
    let differ = a.pixels().zip(b.pixels()).filter(|(x, y)| x != y).count();
    assert_eq!(differ, 0, "the alpha style's picture does not depend on draw order");
    // The two colours (palette blue and orange) mix at the crossing.
    let colours: std::collections::BTreeSet<[u8; 3]> =
        a.pixels().filter(|p| p.0[..3].iter().any(|c| *c > 40)).map(|p| [p.0[0], p.0[1], p.0[2]]).collect();
    assert!(colours.len() >= 3, "two lines and their mix: {colours:?}");
}

#[test]
fn a_sample_of_many_rays_is_stratified_and_refines_to_all() {
    let s = Sources::open(dataset()).unwrap();
    let counts = s.query("SELECT kind, count(*) AS n FROM rays GROUP BY kind").unwrap();
    let mut by_kind = std::collections::BTreeMap::new();
    for b in &counts {
        use arrow::array::AsArray;
        let k = arrow::compute::cast(b.column(0), &arrow::datatypes::DataType::Utf8).unwrap();
        let n = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::UInt64).unwrap();
        for r in 0..b.num_rows() {
            by_kind.insert(
                k.as_string::<i32>().value(r).to_string(),
                n.as_primitive::<arrow::datatypes::UInt64Type>().value(r),
            );
        }
    }
    let total: u64 = by_kind.values().sum();
    let budget = total / 10;
    let mut p =
        pipeline(&[("rays", json!({"max_rays": budget, "refine": true, "style": "density", "line_width": 1.0}))]);
    p.resize(2 * W, 2 * H).unwrap();
    p.snapshot(false).unwrap();
    let report = p.report().join("\n");
    assert!(report.contains(&format!("of the {total} matching rays drawn")), "{report}");
    // Each kind gets its share (within one ray per depth stratum), not the first rows' kinds.
    let legend = p.legends();
    let entries = legend
        .iter()
        .find_map(|l| match l {
            rtvtk_viz::Legend::Swatches { title, entries } if title.starts_with("ray kinds (") => Some(entries.clone()),
            _ => None,
        })
        .expect("a ray kinds legend that says how many of how many");
    for (kind, n) in &by_kind {
        let drawn: u64 = entries
            .iter()
            .find_map(|(label, _)| label.strip_prefix(&format!("{kind} (")))
            .and_then(|v| v.trim_end_matches(')').parse().ok())
            .unwrap_or_else(|| panic!("{kind} is not in the legend {entries:?}"));
        let want = *n as f64 * budget as f64 / total as f64;
        assert!((drawn as f64 - want).abs() <= 12.0, "{kind}: drew {drawn}, its share is {want:.1}");
    }
    // Refining while idle reaches every ray.
    let mut steps = 0;
    while p.idle().unwrap() {
        p.render().unwrap();
        steps += 1;
        assert!(steps < 10, "refinement ends");
    }
    assert!(steps >= 1);
    let report = p.report().join("\n");
    assert!(!report.contains("matching rays drawn"), "all rays drawn at the end: {report}");
    let segments =
        p.report().iter().find_map(|r| r.strip_prefix("rays: ").and_then(|r| r.split(' ').next()?.parse::<u64>().ok()));
    assert_eq!(segments, Some(total), "{report}");
}

#[test]
fn legends_tell_constants_categories_and_ranges_apart() {
    let legend_of = |sql: &str| {
        let q = json!({"sql": sql, "colour_by": "v"});
        let mut p = pipeline(&[("query", q)]);
        p.snapshot(false).unwrap();
        p.legends()
    };
    let base = "SELECT origin_x AS x, origin_y AS y, origin_z AS z";
    // A constant: one swatch with its value and count, not a colour bar of five equal ticks.
    let l = legend_of(&format!("{base}, 1 AS v FROM rays WHERE kind = 'shadow' LIMIT 50"));
    match &l[..] {
        [rtvtk_viz::Legend::Swatches { entries, .. }] => {
            assert_eq!(entries.iter().map(|e| e.0.as_str()).collect::<Vec<_>>(), ["1 (50)"])
        }
        other => panic!("{other:?}"),
    }
    // A few integers (depths): categories in order, with counts that add up.
    let l = legend_of(&format!("{base}, depth AS v FROM rays WHERE depth < 3 LIMIT 400"));
    match &l[..] {
        [rtvtk_viz::Legend::Swatches { entries, .. }] => {
            let names: Vec<&str> = entries.iter().map(|e| e.0.split(' ').next().unwrap()).collect();
            assert_eq!(names, ["0", "1", "2"]);
            let sum: u64 = entries
                .iter()
                .map(|e| e.0.split('(').nth(1).unwrap().trim_end_matches(')').parse::<u64>().unwrap())
                .sum();
            assert_eq!(sum, 400);
        }
        other => panic!("{other:?}"),
    }
    // Many distinct numbers: a colour bar over their range.
    let l = legend_of(&format!("{base}, t AS v FROM rays WHERE t IS NOT NULL LIMIT 400"));
    assert!(matches!(&l[..], [rtvtk_viz::Legend::ColourBar { min, max, log: false, .. }] if min < max), "{l:?}");
}
