//! `rtvtk bench gpu`: the GPU tracer beside the CPU, in the same run — primary rays per second
//! (same rays, hits compared), path-traced samples and rays per second by kind, frames of one
//! sample per pixel per second, and recording throughput.

use std::time::Instant;

use anyhow::{Context, Result, bail};
use renderers::geometry::Ray;
use renderers::{Bvh, RenderOptions, RenderStats, TraversalStats};
use rl::{Kind, Recorder, RecorderOptions};

use crate::query::median;

/// What `rtvtk bench gpu` measures.
pub struct GpuBench {
    pub rounds: usize,
    /// Samples per pixel of a GPU path-tracing round.
    pub spp: u32,
    /// Measure the CPU beside the GPU.
    pub cpu: bool,
    /// Also record one sample per pixel with each tracer.
    pub record: bool,
}

pub fn run(scene_name: &str, subdivide: u32, (w, h): (u32, u32), o: &GpuBench) -> Result<()> {
    let scene = renderers::load_scene(scene_name, None, subdivide.max(1))?;
    let bvh = std::sync::Arc::new(Bvh::build(&scene.tris));
    let mut gpu = gpu_tracer::GpuTracer::new(&scene, &bvh).context("the GPU tracer")?;
    let n = f64::from(w) * f64::from(h);
    let threads = std::thread::available_parallelism().map_or(1, |c| c.get());
    let rounds = o.rounds;
    println!(
        "scene {} ({} triangles), {w}x{h}, GPU: {}, CPU: {threads} threads{}",
        scene.name,
        scene.tris.len(),
        gpu.adapter(),
        if cfg!(debug_assertions) {
            " (a dev build: the CPU figures are not fair baselines; use --release)"
        } else {
            ""
        }
    );

    // Primary rays. One warm-up of each (pipeline compilation, page faults), then interleaved rounds.
    let mut gpu_hits = gpu.primary_hits(w, h)?;
    let (mut gs, mut cs) = (Vec::new(), Vec::new());
    let mut cpu_hits = if o.cpu { Some(cpu_primary(&scene, &bvh, w, h, threads)) } else { None };
    for _ in 0..rounds {
        let t = Instant::now();
        gpu_hits = gpu.primary_hits(w, h)?;
        gs.push(t.elapsed().as_secs_f64());
        if o.cpu {
            let t = Instant::now();
            cpu_hits = Some(cpu_primary(&scene, &bvh, w, h, threads));
            cs.push(t.elapsed().as_secs_f64());
        }
    }
    println!();
    println!("## Primary rays (closest hit, one per pixel centre)");
    println!("| tracer | s per frame (median of {rounds}) | Mrays/s |");
    println!("|---|---|---|");
    let g = median(&gs);
    println!("| GPU (compute, incl. upload of the camera and read-back of the hits) | {g:.4} | {:.2} |", n / g / 1e6);
    if let Some(cpu_hits) = &cpu_hits {
        let differ = gpu_hits.iter().zip(cpu_hits).filter(|(g, c)| g.prim != **c).count();
        if differ * 500 > gpu_hits.len() {
            bail!("the GPU and CPU disagree on {differ} of {} pixels", gpu_hits.len());
        }
        let c = median(&cs);
        println!("| CPU BVH, {threads} threads | {c:.4} | {:.2} |", n / c / 1e6);
        println!("GPU / CPU: {:.2}x the rays per second; {differ} pixels differ", c / g);
    }

    // The path tracer: rounds of `spp` samples per pixel into one progressive image.
    let depth = RenderOptions::default().max_depth;
    let mut p = gpu.progressive(w, h, 1, depth)?;
    gpu.trace(&mut p, 1)?;
    let mut gpu_rounds = Vec::new();
    for _ in 0..rounds {
        let before = p.rays_by_kind;
        let t = Instant::now();
        gpu.trace(&mut p, o.spp)?;
        let secs = t.elapsed().as_secs_f64();
        let kinds: Vec<u64> = p.rays_by_kind.iter().zip(&before).map(|(a, b)| a - b).collect();
        gpu_rounds.push((secs, kinds));
    }
    gpu_rounds.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (gsecs, gkinds) = gpu_rounds[gpu_rounds.len() / 2].clone();
    let gsamples = n * f64::from(o.spp);
    println!();
    println!("## Path tracing (max depth {depth}, next-event estimation, Russian roulette; no recording)");
    println!(
        "| tracer | samples | s (median of {rounds}) | Msamples/s | 1-spp frames/s | Mrays/s all | camera | shadow | diffuse | specular | transmission |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let row = |name: &str, samples: f64, secs: f64, kinds: &[u64]| {
        let total: u64 = kinds.iter().sum();
        let per = |k: usize| format!("{:.2}", kinds.get(k).copied().unwrap_or(0) as f64 / secs / 1e6);
        println!(
            "| {name} | {samples} | {secs:.4} | {:.3} | {:.2} | {:.2} | {} | {} | {} | {} | {} |",
            samples / secs / 1e6,
            samples / n / secs,
            total as f64 / secs / 1e6,
            per(0),
            per(1),
            per(2),
            per(3),
            per(4)
        );
    };
    row("GPU", gsamples, gsecs, &gkinds);
    let fps = 1.0 / (gsecs / f64::from(o.spp));
    if o.cpu {
        // One sample per pixel on every core, the same scene and size.
        let opts = RenderOptions { width: w, height: h, spp: 1, threads, ..Default::default() };
        let mut cpu_rounds: Vec<(f64, RenderStats)> = Vec::new();
        for _ in 0..rounds.min(3) {
            let (_, stats) = renderers::render(&scene, &bvh, renderers::TracerChoice::Path, &opts, None, &|_| {})?;
            cpu_rounds.push((stats.secs, stats));
        }
        cpu_rounds.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (csecs, cstats) = &cpu_rounds[cpu_rounds.len() / 2];
        let ck: Vec<u64> = (0..5u8).map(|k| kind_count(cstats, Kind(k))).collect();
        row(&format!("CPU, {threads} threads"), n, *csecs, &ck);
        println!("GPU / CPU: {:.2}x the samples per second", (gsamples / gsecs) / (n / csecs));
    }
    println!(
        "real time at {w}x{h} (60 frames of one sample per pixel per second): {:.1} frames/s, {}",
        fps,
        if fps >= 60.0 { "reached" } else { "not reached on this adapter" }
    );

    // The traversal order, the layout choice the shader makes: the nearer hit child first
    // (pushing the farther) against always the first child, same rays, interleaved rounds.
    println!();
    println!("## Traversal order (same BVH layout; median of {rounds} interleaved rounds)");
    println!("| child order | primary s | primary Mrays/s | path s ({} spp) | path Msamples/s |", o.spp);
    println!("|---|---|---|---|---|");
    let mut by_order: Vec<(bool, Vec<f64>, Vec<f64>)> =
        vec![(true, Vec::new(), Vec::new()), (false, Vec::new(), Vec::new())];
    for _ in 0..rounds {
        for (nearer, prim, path) in by_order.iter_mut() {
            gpu.set_nearer_child_first(*nearer);
            let t = Instant::now();
            gpu.primary_hits(w, h)?;
            prim.push(t.elapsed().as_secs_f64());
            let mut q = gpu.progressive(w, h, 2, depth)?;
            let t = Instant::now();
            gpu.trace(&mut q, o.spp)?;
            path.push(t.elapsed().as_secs_f64());
        }
    }
    gpu.set_nearer_child_first(true);
    for (nearer, prim, path) in &by_order {
        let (a, b) = (median(prim), median(path));
        println!(
            "| {} | {a:.4} | {:.2} | {b:.4} | {:.3} |",
            if *nearer { "nearer first (used)" } else { "first child first" },
            n / a / 1e6,
            gsamples / b / 1e6
        );
    }
    let (p0, p1) = (median(&by_order[0].1), median(&by_order[1].1));
    let (q0, q1) = (median(&by_order[0].2), median(&by_order[1].2));
    println!("nearer-first speed-up: primary {:.2}x, path {:.2}x", p1 / p0, q1 / q0);

    if o.record {
        println!();
        println!("## Recording one sample per pixel (every ray, through rl into a dataset)");
        println!("| tracer | rays | s | Mrays recorded/s |");
        println!("|---|---|---|---|");
        let opts = RenderOptions { width: w, height: h, spp: 1, threads, ..Default::default() };
        let cpu =
            renderers::CpuTracer::new(renderers::TracerChoice::Path, std::sync::Arc::new(scene.clone()), bvh.clone())?;
        let mut tracers: Vec<(&str, &dyn renderers::Tracer)> = vec![("GPU", &gpu)];
        if o.cpu {
            tracers.push(("CPU", &cpu));
        }
        for (name, tracer) in tracers {
            let dir = tempfile::tempdir()?;
            let rec = Recorder::create(
                dir.path().join("t"),
                RecorderOptions { payload: renderers::payload_schema(), ..Default::default() },
            )?;
            let t = Instant::now();
            let (_, stats) = tracer.render(&opts, Some(&rec), &|_| {})?;
            let summary = rec.finish()?;
            let secs = t.elapsed().as_secs_f64();
            if summary.rays != stats.rays {
                bail!("{name}: traced {} rays, recorded {}", stats.rays, summary.rays);
            }
            println!("| {name} | {} | {secs:.3} | {:.3} |", summary.rays, summary.rays as f64 / secs / 1e6);
        }
    }
    Ok(())
}

fn kind_count(s: &RenderStats, k: Kind) -> u64 {
    s.rays_by_kind.iter().find(|(kind, _)| *kind == k).map_or(0, |(_, n)| *n)
}

/// The closest triangle of every pixel's primary ray, on the CPU BVH, rows split over threads.
fn cpu_primary(scene: &renderers::Scene, bvh: &Bvh, w: u32, h: u32, threads: usize) -> Vec<Option<u32>> {
    let mut out = vec![None; (w * h) as usize];
    let rows = (h as usize).div_ceil(threads.max(1)).max(1);
    std::thread::scope(|s| {
        for (k, chunk) in out.chunks_mut(rows * w as usize).enumerate() {
            s.spawn(move || {
                for (i, o) in chunk.iter_mut().enumerate() {
                    let (x, y) = ((i % w as usize) as u32, (k * rows + i / w as usize) as u32);
                    let d = scene.camera.direction(x as f32 + 0.5, y as f32 + 0.5, w, h);
                    let ray = Ray::new(scene.camera.position, d);
                    *o = bvh.intersect(&ray, 0.0, f32::INFINITY, &mut TraversalStats::default(), None).map(|h| h.prim);
                }
            });
        }
    });
    out
}
