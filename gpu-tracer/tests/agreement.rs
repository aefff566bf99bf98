#![allow(clippy::unwrap_used)]
//! The GPU traversal finds, pixel for pixel, the triangle the CPU BVH finds for the same primary
//! ray: on the built-in scenes and on the Cornell box scaled by 1e-4 and 1e5 and moved 1e6 away
//! from the origin. Needs a GPU adapter (lavapipe in CI: `apt-get install mesa-vulkan-drivers`).

use glam::Vec3A;
use gpu_tracer::GpuTracer;
use renderers::geometry::Ray;
use renderers::{BuiltinScene, Bvh, Scene, TraversalStats};

/// The scene with every point p moved to p * scale + offset (triangles and camera).
fn moved(mut s: Scene, scale: f32, offset: Vec3A) -> Scene {
    let f = |p: Vec3A| p * scale + offset;
    for t in &mut s.tris {
        *t = t.map(f);
    }
    s.camera.position = f(s.camera.position);
    s.camera.target = f(s.camera.target);
    s
}

fn compare(name: &str, scene: &Scene, w: u32, h: u32) {
    let bvh = Bvh::build(&scene.tris);
    let gpu = GpuTracer::new(scene, &bvh).expect("a GPU adapter (lavapipe: apt-get install mesa-vulkan-drivers)");
    let hits = gpu.primary_hits(w, h).unwrap();
    assert_eq!(hits.len(), (w * h) as usize);
    let (mut same, mut differ, mut hit) = (0usize, Vec::new(), 0usize);
    for y in 0..h {
        for x in 0..w {
            let d = scene.camera.direction(x as f32 + 0.5, y as f32 + 0.5, w, h);
            let ray = Ray::new(scene.camera.position, d);
            let cpu = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut TraversalStats::default(), None);
            let g = hits[(y * w + x) as usize];
            hit += usize::from(cpu.is_some());
            match (cpu, g.prim) {
                (None, None) => same += 1,
                (Some(c), Some(p)) if c.prim == p => {
                    assert!(
                        (c.t - g.t).abs() <= 1e-4 * c.t,
                        "{name} pixel {x},{y}: t {} on the CPU, {} on the GPU",
                        c.t,
                        g.t
                    );
                    same += 1;
                }
                // A ray through a shared edge may take either triangle, at the same distance.
                (Some(c), Some(_)) if (c.t - g.t).abs() <= 1e-4 * c.t => same += 1,
                (c, _) => differ.push((x, y, c.map(|c| (c.prim, c.t)), g)),
            }
        }
    }
    eprintln!("{name}: {w}x{h}, {hit} hits, {} pixels differ", differ.len());
    // The GPU has no f64 re-test of exact-edge cases: allow a few pixels, never more than 0.2 %.
    assert!(
        differ.len() * 500 <= (w * h) as usize,
        "{name}: {} of {} pixels differ: {:?}",
        differ.len(),
        w * h,
        &differ[..differ.len().min(8)]
    );
    assert!(hit * 2 > (w * h) as usize, "{name}: the camera sees the scene ({hit} hits)");
    assert!(same + differ.len() == (w * h) as usize);
}

#[test]
fn primary_hits_match_the_cpu_bvh_on_every_builtin_scene() {
    for (name, s) in [
        ("cornell", BuiltinScene::Cornell),
        ("cornell-glass", BuiltinScene::CornellGlass),
        ("glossy", BuiltinScene::Glossy),
    ] {
        compare(name, &s.build(1).unwrap(), 96, 72);
    }
}

#[test]
fn primary_hits_match_at_extreme_scales_and_far_from_the_origin() {
    let base = BuiltinScene::Cornell.build(1).unwrap();
    for (scale, offset) in [(1e-4, Vec3A::ZERO), (1e5, Vec3A::ZERO), (1.0, Vec3A::new(1e6, -1e6, 1e6))] {
        compare(&format!("cornell x{scale} + {offset}"), &moved(base.clone(), scale, offset), 64, 48);
    }
}

#[test]
fn bad_sizes_are_errors() {
    let s = BuiltinScene::Cornell.build(1).unwrap();
    let gpu = GpuTracer::new(&s, &Bvh::build(&s.tris)).unwrap();
    assert!(gpu.primary_hits(0, 10).unwrap_err().to_string().contains("image size 0x10"));
    // A scene without triangles: every ray misses.
    let mut empty = s.clone();
    empty.tris.clear();
    let g = GpuTracer::new(&empty, &Bvh::build(&empty.tris)).unwrap();
    assert!(g.primary_hits(8, 8).unwrap().iter().all(|h| h.prim.is_none()));
}
