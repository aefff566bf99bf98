#![allow(clippy::unwrap_used)]
//! Numerical robustness: BVH against brute force, watertightness, extreme scales, grazing rays,
//! degenerate triangles, NaN/Inf input.

use glam::Vec3A;
use renderers::geometry::{Ray, intersect_triangle};
use renderers::sampling::Rng;
use renderers::{BuiltinScene, Bvh, Camera, Material, RenderOptions, Scene, TraversalStats};

fn brute(tris: &[[Vec3A; 3]], ray: &Ray) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    for (i, t) in tris.iter().enumerate() {
        if let Some(h) = intersect_triangle(ray, t[0], t[1], t[2], 0.0, best.map_or(f32::INFINITY, |b| b.0)) {
            best = Some((h.t, i as u32));
        }
    }
    best
}

fn random_dir(rng: &mut Rng) -> Vec3A {
    loop {
        let v = Vec3A::new(rng.next_f32() * 2.0 - 1.0, rng.next_f32() * 2.0 - 1.0, rng.next_f32() * 2.0 - 1.0);
        let l = v.length_squared();
        if l > 1e-4 && l <= 1.0 {
            return v / l.sqrt();
        }
    }
}

#[test]
fn bvh_is_valid_and_matches_brute_force() {
    for sub in [1, 6] {
        let scene = BuiltinScene::Cornell.build(sub).unwrap();
        let bvh = Bvh::build(&scene.tris);
        bvh.validate(scene.tris.len()).unwrap();
        let mut rng = Rng::for_sample(7, 1, 2, 3);
        for i in 0..3000 {
            let o = Vec3A::new(
                rng.next_f32() * 556.0,
                rng.next_f32() * 548.0,
                rng.next_f32() * 559.0 - (i % 2) as f32 * 700.0,
            );
            let ray = Ray::new(o, random_dir(&mut rng));
            let mut st = TraversalStats::default();
            let got = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut st, None).map(|h| (h.t, h.prim));
            let want = brute(&scene.tris, &ray);
            assert_eq!(got.map(|g| g.0), want.map(|w| w.0), "ray {i} from {o:?}");
            if got.is_some() {
                assert!(st.tris >= 1 && st.boxes >= 1 && st.nodes >= 1);
            }
            let any = bvh.any_hit(&ray, 0.0, f32::INFINITY, &mut TraversalStats::default());
            assert_eq!(any.is_some(), want.is_some());
        }
    }
}

/// A closed cube [-1, 1]^3 tessellated n × n per face, wound outwards.
fn closed_cube(n: u32, scale: f32, offset: Vec3A) -> Vec<[Vec3A; 3]> {
    let mut tris = Vec::new();
    for axis in 0..3 {
        for side in [-1.0f32, 1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let p = |a: f32, b: f32| {
                let mut c = [0.0; 3];
                c[axis] = side;
                c[u] = a;
                c[v] = b;
                Vec3A::from_array(c) * scale + offset
            };
            for i in 0..n {
                for j in 0..n {
                    let a0 = -1.0 + 2.0 * i as f32 / n as f32;
                    let a1 = -1.0 + 2.0 * (i + 1) as f32 / n as f32;
                    let b0 = -1.0 + 2.0 * j as f32 / n as f32;
                    let b1 = -1.0 + 2.0 * (j + 1) as f32 / n as f32;
                    tris.push([p(a0, b0), p(a1, b0), p(a1, b1)]);
                    tris.push([p(a0, b0), p(a1, b1), p(a0, b1)]);
                }
            }
        }
    }
    tris
}

#[test]
fn no_ray_leaks_through_shared_edges_and_vertices() {
    for (scale, offset) in [
        (1.0, Vec3A::ZERO),
        (1e-4, Vec3A::ZERO),
        (1e5, Vec3A::ZERO),
        (1e3, Vec3A::new(1e6, -2e6, 5e5)),
        (1.0, Vec3A::new(1e4, -2e4, 5e3)),
    ] {
        let tris = closed_cube(8, scale, offset);
        let bvh = Bvh::build(&tris);
        bvh.validate(tris.len()).unwrap();
        let mut rng = Rng::for_sample(1, 0, 0, 0);
        let mut aimed = 0;
        // Rays from inside aimed exactly at vertices and edge points of the tessellation.
        for t in &tris {
            for target in [t[0], t[1], t[2], (t[0] + t[1]) * 0.5, (t[1] + t[2]) * 0.5, (t[0] + t[2]) * 0.5] {
                let o = offset + Vec3A::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5) * scale;
                let ray = Ray::new(o, (target - o).normalize());
                let hit = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut TraversalStats::default(), None);
                assert!(hit.is_some(), "ray from {o:?} towards {target:?} leaked (scale {scale})");
                aimed += 1;
            }
        }
        assert!(aimed > 2000);
    }
}

#[test]
fn grazing_rays_neither_leak_nor_self_intersect() {
    let tris = closed_cube(16, 1.0, Vec3A::ZERO);
    let bvh = Bvh::build(&tris);
    let mut rng = Rng::for_sample(2, 0, 0, 0);
    for _ in 0..5000 {
        // Start just above the floor, heading almost parallel to it, slightly down.
        let o = renderers::geometry::offset_point(
            Vec3A::new(rng.next_f32() * 1.8 - 0.9, -1.0, rng.next_f32() * 1.8 - 0.9),
            Vec3A::Y,
        );
        let a = rng.next_f32() * std::f32::consts::TAU;
        let dip = -(10f32).powf(-(1.0 + rng.next_f32() * 5.0));
        let d = Vec3A::new(a.cos(), dip, a.sin()).normalize();
        let hit = bvh.intersect(&Ray::new(o, d), 0.0, f32::INFINITY, &mut TraversalStats::default(), None);
        let hit = hit.expect("a grazing ray inside a closed box must hit it");
        assert!(hit.t > 0.0 && hit.t.is_finite());
        // Rising grazing rays from the floor must not hit the floor itself.
        let up = Vec3A::new(a.cos(), -dip, a.sin()).normalize();
        let h = bvh.intersect(&Ray::new(o, up), 0.0, f32::INFINITY, &mut TraversalStats::default(), None).unwrap();
        let p = o + up * h.t;
        assert!(p.y > -1.0 + 1e-6 || p.x.abs() > 0.999 || p.z.abs() > 0.999, "self-intersection at {p:?}");
    }
}

#[test]
fn degenerate_and_non_finite_triangles_are_skipped_and_counted() {
    let v = |x: f32, y: f32, z: f32| Vec3A::new(x, y, z);
    let tris = vec![
        [v(0.0, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)],
        [v(0.0, 0.0, 0.0), v(1.0, 1.0, 1.0), v(2.0, 2.0, 2.0)], // collinear
        [v(1.0, 1.0, 1.0), v(1.0, 1.0, 1.0), v(0.0, 1.0, 0.0)], // repeated vertex
        [v(f32::NAN, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)],
        [v(f32::INFINITY, 0.0, 0.0), v(1.0, 0.0, 0.0), v(0.0, 1.0, 0.0)],
    ];
    let cam = Camera { position: v(0.0, 0.0, 5.0), target: Vec3A::ZERO, up: Vec3A::Y, fov_y: 40.0 };
    let s = Scene::new("t", tris, vec![0; 5], vec![Material::diffuse("d", [0.5; 3])], cam).unwrap();
    assert_eq!(s.report.triangles, 1);
    assert_eq!(s.report.degenerate_skipped, 4);
    // A ray with NaN direction hits nothing and does not panic.
    let bvh = Bvh::build(&s.tris);
    let r = Ray::new(v(0.2, 0.2, 5.0), v(f32::NAN, 0.0, -1.0));
    assert!(bvh.intersect(&r, 0.0, f32::INFINITY, &mut TraversalStats::default(), None).is_none());
    let r = Ray::new(v(0.2, 0.2, 5.0), v(0.0, 0.0, -1.0));
    assert!(bvh.intersect(&r, 0.0, f32::INFINITY, &mut TraversalStats::default(), None).is_some());
}

fn render_mean(scene: &Scene) -> (Vec3A, usize) {
    let bvh = Bvh::build(&scene.tris);
    let opts = RenderOptions { width: 32, height: 32, spp: 16, seed: 3, threads: 2, ..Default::default() };
    let (film, _) = renderers::render(scene, &bvh, renderers::TracerChoice::Path, &opts, None, &|_| {}).unwrap();
    let bad = film.pixels.iter().filter(|p| !p.is_finite()).count();
    (film.mean(), bad)
}

#[test]
fn extreme_scales_and_far_from_origin_render_the_same_image() {
    let base = BuiltinScene::Cornell.build(1).unwrap();
    let (reference, bad) = render_mean(&base);
    assert_eq!(bad, 0);
    for (s, off) in [
        (1e-4f32, Vec3A::ZERO),
        (1e5, Vec3A::ZERO),
        (1.0, Vec3A::new(1e6, 1e6, 1e6)),
        (1e-2, Vec3A::new(-3e3, 0.0, 7e3)),
    ] {
        let scene = base.transformed(s, off);
        let (mean, bad) = render_mean(&scene);
        assert_eq!(bad, 0, "non-finite pixels at scale {s} offset {off:?}");
        let rel = ((mean - reference).abs() / reference).max_element();
        assert!(rel < 0.03, "scale {s} offset {off:?}: mean {mean:?} vs {reference:?} ({:.1}% off)", rel * 100.0);
    }
}

/// A ray leaving the Cornell floor 2^-16 above it (the offset near the origin) meets the floor's
/// far-away vertices with an error in t larger than its distance to the plane: without a bound on
/// that error its sign flipped into a hit at t = 2e-5 (found by `analyze bvh --whatif`).
#[test]
fn a_ray_leaving_a_surface_near_an_axis_plane_does_not_hit_it() {
    let o = Vec3A::new(303.41833, 1.5258789e-5, 72.93194);
    let ray = Ray::new(o, Vec3A::new(0.61490256, 0.6049585, 0.5058854));
    let floor = [
        [Vec3A::new(552.8, 0.0, 0.0), Vec3A::new(0.0, 0.0, 0.0), Vec3A::new(0.0, 0.0, 559.2)],
        [Vec3A::new(552.8, 0.0, 0.0), Vec3A::new(0.0, 0.0, 559.2), Vec3A::new(549.6, 0.0, 559.2)],
    ];
    for t in &floor {
        assert_eq!(intersect_triangle(&ray, t[0], t[1], t[2], 0.0, f32::INFINITY), None);
    }
    // Coming down onto the floor from the same point's height above it still hits.
    let down = Ray::new(Vec3A::new(303.4, 100.0, 72.9), Vec3A::new(0.0, -1.0, 0.0));
    let hit = floor.iter().find_map(|t| intersect_triangle(&down, t[0], t[1], t[2], 0.0, f32::INFINITY));
    assert!((hit.unwrap().t - 100.0).abs() < 1e-4);
}

/// A bounce from the floor 0.002 from the left wall, towards it: a real hit at t = 0.0049, inside
/// the f32 error bound of the wall's 550 mm triangle, kept (decided in double precision).
#[test]
fn a_real_hit_within_the_error_bound_is_kept() {
    let o = Vec3A::new(0.0018781185, 1.5258789e-5, 477.0933);
    let ray = Ray::new(o, Vec3A::new(-0.3839554, 0.5537114, -0.7389059));
    let wall = [
        [Vec3A::new(0.0, 0.0, 559.2), Vec3A::new(0.0, 0.0, 0.0), Vec3A::new(0.0, 548.8, 0.0)],
        [Vec3A::new(0.0, 0.0, 559.2), Vec3A::new(0.0, 548.8, 0.0), Vec3A::new(0.0, 548.8, 559.2)],
    ];
    let hit = wall.iter().find_map(|t| intersect_triangle(&ray, t[0], t[1], t[2], 0.0, f32::INFINITY));
    // The recording's t (0.004885681, the tracers' f32 test) is off by the error of 550 mm
    // coordinates, 6e-6; this one is the double-precision distance.
    assert!((hit.unwrap().t - 0.004885681).abs() < 1e-5, "{hit:?}");
}
