//! `rtvtk bench trace`: traversal speed on the same rays, ours beside obvhs's stock traversals.

use std::time::{Duration, Instant};

use anyhow::Result;
use glam::{Quat, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::ray::{Ray as ORay, RayHit};
use obvhs::triangle::Triangle;
use renderers::geometry::Ray;
use renderers::sampling::Rng;
use renderers::tracer::{SampleRecord, TraceCtx, path_sample};
use renderers::{BuiltinScene, Bvh, TraversalStats};
use rl::Kind;

struct BenchRay {
    o: Vec3A,
    d: Vec3A,
    tmax: f32,
}

fn time<F: FnMut() -> u64>(mut f: F) -> (f64, u64) {
    // Best of three runs (the machine is shared and noisy).
    let mut best = f64::INFINITY;
    let mut check = 0;
    for _ in 0..3 {
        let t = Instant::now();
        check = f();
        best = best.min(t.elapsed().as_secs_f64());
    }
    (best, check)
}

pub fn run(subdivide: u32, rotate: bool, width: u32, spp: u32) -> Result<()> {
    let mut scene = BuiltinScene::Cornell.build(subdivide)?;
    if rotate {
        let q = Quat::from_euler(glam::EulerRot::XYZ, 0.3, 0.5, 0.2);
        let c = Vec3A::new(278.0, 274.0, 280.0);
        let rot = |v: Vec3A| Vec3A::from(q * glam::Vec3::from(v - c)) + c;
        for t in &mut scene.tris {
            *t = [rot(t[0]), rot(t[1]), rot(t[2])];
        }
        for n in &mut scene.normals {
            *n = Vec3A::from(q * glam::Vec3::from(*n));
        }
        scene.camera.position = rot(scene.camera.position);
        scene.camera.target = rot(scene.camera.target);
        scene.camera.up = Vec3A::from(q * glam::Vec3::Y);
    }
    let t = Instant::now();
    let bvh = Bvh::build(&scene.tris);
    let ours_build = t.elapsed().as_secs_f64();
    let tris: Vec<Triangle> = scene.tris.iter().map(|t| Triangle { v0: t[0], v1: t[1], v2: t[2] }).collect();
    let t = Instant::now();
    let cw =
        obvhs::cwbvh::builder::build_cwbvh_from_tris(&tris, BvhBuildParams::medium_build(), &mut Duration::default());
    let cw_build = t.elapsed().as_secs_f64();
    let b2 =
        obvhs::bvh2::builder::build_bvh2_from_tris(&tris, BvhBuildParams::medium_build(), &mut Duration::default());

    // Rays of a path-traced frame, by kind.
    let ctx = TraceCtx { scene: &scene, bvh: &bvh, max_depth: 6, bug: None, record_visits: false };
    let mut rays: Vec<(Kind, BenchRay)> = Vec::new();
    let mut rec = SampleRecord::new(true);
    for y in 0..width {
        for x in 0..width {
            for s in 0..spp {
                let mut rng = Rng::for_sample(1, x, y, s);
                rec.clear();
                path_sample(&ctx, x as f32 + 0.5, y as f32 + 0.5, width, width, &mut rng, Some(&mut rec));
                for r in &rec.rays {
                    let tmax = if r.kind == Kind::SHADOW {
                        // Shadow rays end at the light sample (or just past the blocker they found).
                        let t = r.t.unwrap_or(f32::INFINITY);
                        if r.prim.is_some_and(|p| scene.lights.contains(&p)) { t * (1.0 - 1e-4) } else { t * 1.0001 }
                    } else {
                        f32::INFINITY
                    };
                    rays.push((r.kind, BenchRay { o: r.origin, d: r.dir, tmax }));
                }
            }
        }
    }
    println!(
        "## rtvtk bench trace: Cornell box subdivided {subdivide}x ({} triangles), {}, {} rays of a {width}x{width}x{spp} path-traced frame, 1 thread",
        scene.tris.len(),
        if rotate { "rotated" } else { "axis-aligned" },
        rays.len()
    );
    println!(
        "build: ours (obvhs BVH2, slow preset with pre-splits, leaves <= 4; binary depth {}) {ours_build:.3} s, obvhs CWBVH medium {cw_build:.3} s",
        bvh.depth()
    );
    println!();
    #[cfg(feature = "embree")]
    let embree = crate::embree::EmbreeScene::new(&scene.tris);
    println!(
        "| kind | rays | ours Mrays/s | obvhs BVH2 stock | obvhs CWBVH stock | Embree 3 | ours / CWBVH | ours / Embree | boxes/ray | tris/ray |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for kind in [Kind::CAMERA, Kind::SHADOW, Kind::DIFFUSE] {
        let set: Vec<&BenchRay> = rays.iter().filter(|(k, _)| *k == kind).map(|(_, r)| r).collect();
        if set.is_empty() {
            continue;
        }
        let shadow = kind == Kind::SHADOW;
        let mut st = TraversalStats::default();
        let (ours, hits_ours) = time(|| {
            st = TraversalStats::default();
            let mut hits = 0;
            for r in &set {
                let ray = Ray::new(r.o, r.d);
                let hit = if shadow {
                    bvh.any_hit(&ray, 0.0, r.tmax, &mut st).is_some()
                } else {
                    bvh.intersect(&ray, 0.0, r.tmax, &mut st, None).is_some()
                };
                hits += u64::from(hit);
            }
            hits
        });
        let (stock2, hits_b2) = time(|| {
            let mut hits = 0;
            for r in &set {
                let ray = ORay::new(r.o, r.d, 0.0, r.tmax);
                let hit = if shadow {
                    let mut found = false;
                    b2.ray_traverse_anyhit(ray, |ray, id| {
                        found |= tris[b2.primitive_indices[id] as usize].intersect(ray) < ray.tmax;
                    });
                    found
                } else {
                    let mut h = RayHit::none();
                    b2.ray_traverse(ray, &mut h, |ray, id| tris[b2.primitive_indices[id] as usize].intersect(ray))
                };
                hits += u64::from(hit);
            }
            hits
        });
        let (stock_cw, hits_cw) = time(|| {
            let mut hits = 0;
            for r in &set {
                let ray = ORay::new(r.o, r.d, 0.0, r.tmax);
                let hit = if shadow {
                    !cw.ray_traverse_miss(ray, |ray, id| tris[cw.primitive_indices[id] as usize].intersect(ray))
                } else {
                    let mut h = RayHit::none();
                    cw.ray_traverse(ray, &mut h, |ray, id| tris[cw.primitive_indices[id] as usize].intersect(ray))
                };
                hits += u64::from(hit);
            }
            hits
        });
        #[allow(unused_mut)]
        let mut emb: Option<(f64, u64)> = None;
        #[cfg(feature = "embree")]
        if let Some(e) = &embree {
            emb = Some(time(|| {
                let mut hits = 0;
                for r in &set {
                    let hit =
                        if shadow { e.occluded(r.o, r.d, r.tmax) } else { e.intersect(r.o, r.d, r.tmax).is_some() };
                    hits += u64::from(hit);
                }
                hits
            }));
        }
        let n = set.len() as f64;
        let name = store::KindTable::default().name(kind).unwrap_or("?").to_string();
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} | {} | {:.2}x | {} | {:.1} | {:.1} |",
            set.len(),
            n / ours / 1e6,
            n / stock2 / 1e6,
            n / stock_cw / 1e6,
            emb.map_or("n/a".into(), |(s, _)| format!("{:.2}", n / s / 1e6)),
            stock_cw / ours,
            emb.map_or("n/a".into(), |(s, _)| format!("{:.2}x", s / ours)),
            st.boxes as f64 / n,
            st.tris as f64 / n
        );
        if let Some((_, h)) = emb
            && (h as f64 - hits_ours as f64).abs() > 0.002 * n
        {
            println!("  note: Embree found {h} hits, ours {hits_ours}");
        }
        let agree = |a: u64, b: u64| (a as f64 - b as f64).abs() <= 0.002 * n;
        if !agree(hits_ours, hits_cw) || !agree(hits_ours, hits_b2) {
            println!(
                "  note: hit counts differ: ours {hits_ours}, BVH2 {hits_b2}, CWBVH {hits_cw} (Möller vs watertight test)"
            );
        }
    }
    Ok(())
}
