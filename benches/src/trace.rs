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

use crate::query::median;

struct BenchRay {
    o: Vec3A,
    d: Vec3A,
    tmax: f32,
}

/// Seconds of one call of each traversal per round, rounds interleaved (see `--rounds`).
struct Timings {
    secs: Vec<Vec<f64>>,
    hits: Vec<u64>,
}

impl Timings {
    fn run(rounds: u32, fs: &mut [Box<dyn FnMut() -> u64 + '_>]) -> Timings {
        let mut secs = vec![Vec::new(); fs.len()];
        let mut hits = vec![0; fs.len()];
        for _ in 0..rounds {
            for (i, f) in fs.iter_mut().enumerate() {
                let t = Instant::now();
                hits[i] = std::hint::black_box(f());
                secs[i].push(t.elapsed().as_secs_f64());
            }
        }
        Timings { secs, hits }
    }

    fn best(&self, i: usize) -> f64 {
        self.secs[i].iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// Median over rounds of time(j) / time(i): how many times faster i was than j in a round.
    fn ratio(&self, i: usize, j: usize) -> f64 {
        let r: Vec<f64> = self.secs[i].iter().zip(&self.secs[j]).map(|(a, b)| b / a).collect();
        median(&r)
    }
}

/// Rays of `set` for which `hit` says yes (the counts are compared across traversals).
fn count_hits(set: &[&BenchRay], mut hit: impl FnMut(&BenchRay) -> bool) -> u64 {
    set.iter().map(|r| u64::from(hit(r))).sum()
}

pub fn run(subdivide: u32, rotate: bool, width: u32, spp: u32, rounds: u32) -> Result<()> {
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
    let ctx = TraceCtx::new(&scene, &bvh, 6, None, false);
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
    let l = bvh.layout();
    println!(
        "layout: {} wide nodes, {} leaf blocks, {:.1} MB; {:.2} triangles per leaf",
        l.wide_nodes,
        l.leaf_blocks,
        l.bytes as f64 / 1e6,
        l.mean_leaf_tris
    );
    println!(
        "timing: {rounds} rounds, each running every traversal once in turn; Mrays/s from the best round, ratios are medians of per-round ratios"
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
        // Ours, counting its work into `st`.
        let ours = |r: &BenchRay, st: &mut TraversalStats| {
            let ray = Ray::new(r.o, r.d);
            if shadow {
                bvh.any_hit(&ray, 0.0, r.tmax, st).is_some()
            } else {
                bvh.intersect(&ray, 0.0, r.tmax, st, None).is_some()
            }
        };
        // Work counts, from a pass of their own (the timed passes count too, and throw it away).
        let mut st = TraversalStats::default();
        count_hits(&set, |r| ours(r, &mut st));
        let mut fs: Vec<Box<dyn FnMut() -> u64 + '_>> = vec![
            Box::new(|| {
                let mut st = TraversalStats::default();
                let hits = count_hits(&set, |r| ours(r, &mut st));
                std::hint::black_box(st);
                hits
            }),
            Box::new(|| {
                count_hits(&set, |r| {
                    let ray = ORay::new(r.o, r.d, 0.0, r.tmax);
                    if shadow {
                        let mut found = false;
                        b2.ray_traverse_anyhit(ray, |ray, id| {
                            found |= tris[b2.primitive_indices[id] as usize].intersect(ray) < ray.tmax;
                        });
                        found
                    } else {
                        let mut h = RayHit::none();
                        b2.ray_traverse(ray, &mut h, |ray, id| tris[b2.primitive_indices[id] as usize].intersect(ray))
                    }
                })
            }),
            Box::new(|| {
                count_hits(&set, |r| {
                    let ray = ORay::new(r.o, r.d, 0.0, r.tmax);
                    let intersect = |ray: &ORay, id: usize| tris[cw.primitive_indices[id] as usize].intersect(ray);
                    if shadow {
                        !cw.ray_traverse_miss(ray, intersect)
                    } else {
                        cw.ray_traverse(ray, &mut RayHit::none(), intersect)
                    }
                })
            }),
        ];
        #[cfg(feature = "embree")]
        if let Some(e) = &embree {
            let set = &set;
            fs.push(Box::new(move || {
                count_hits(set, |r| {
                    if shadow { e.occluded(r.o, r.d, r.tmax) } else { e.intersect(r.o, r.d, r.tmax).is_some() }
                })
            }));
        }
        let with_embree = fs.len() == 4;
        let tm = Timings::run(rounds, &mut fs);
        drop(fs);
        let (ours, stock2, stock_cw) = (tm.best(0), tm.best(1), tm.best(2));
        let (hits_ours, hits_b2, hits_cw) = (tm.hits[0], tm.hits[1], tm.hits[2]);
        let emb = with_embree.then(|| (tm.best(3), tm.hits[3], tm.ratio(0, 3)));
        let n = set.len() as f64;
        let name = store::KindTable::default().name(kind).unwrap_or("?").to_string();
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:.2} | {} | {:.2}x | {} | {:.1} | {:.1} |",
            set.len(),
            n / ours / 1e6,
            n / stock2 / 1e6,
            n / stock_cw / 1e6,
            emb.map_or("n/a".into(), |(s, _, _)| format!("{:.2}", n / s / 1e6)),
            tm.ratio(0, 2),
            emb.map_or("n/a".into(), |(_, _, r)| format!("{r:.2}x")),
            st.boxes as f64 / n,
            st.tris as f64 / n
        );
        if let Some((_, h, _)) = emb
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
