//! `rtvtk bench gpu`: primary rays per second of the GPU traversal beside the CPU BVH on every
//! core, in the same run, on the same rays (issue 26's first figure; the path tracer follows).

use std::time::Instant;

use anyhow::{Context, Result, bail};
use renderers::geometry::Ray;
use renderers::{Bvh, TraversalStats};

use crate::bench::query::median;

pub fn run(scene_name: &str, subdivide: u32, (w, h): (u32, u32), rounds: usize) -> Result<()> {
    let scene = renderers::load_scene(scene_name, None, subdivide.max(1))?;
    let bvh = Bvh::build(&scene.tris);
    let gpu = gpu_tracer::GpuTracer::new(&scene, &bvh).context("the GPU tracer")?;
    let n = f64::from(w) * f64::from(h);
    let threads = std::thread::available_parallelism().map_or(1, |c| c.get());
    println!(
        "scene {} ({} triangles), {w}x{h} primary rays, GPU: {}, CPU: {threads} threads",
        scene.name,
        scene.tris.len(),
        gpu.adapter()
    );
    // One warm-up of each (pipeline compilation, page faults), then interleaved rounds.
    let mut gpu_hits = gpu.primary_hits(w, h)?;
    let mut cpu_hits = cpu_primary(&scene, &bvh, w, h, threads);
    let (mut gs, mut cs) = (Vec::new(), Vec::new());
    for _ in 0..rounds {
        let t = Instant::now();
        gpu_hits = gpu.primary_hits(w, h)?;
        gs.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        cpu_hits = cpu_primary(&scene, &bvh, w, h, threads);
        cs.push(t.elapsed().as_secs_f64());
    }
    let differ = gpu_hits.iter().zip(&cpu_hits).filter(|(g, c)| g.prim != **c).count();
    if differ * 500 > gpu_hits.len() {
        bail!("the GPU and CPU disagree on {differ} of {} pixels", gpu_hits.len());
    }
    let (g, c) = (median(&gs), median(&cs));
    println!("| tracer | s per frame (median of {rounds}) | Mrays/s |");
    println!("|---|---|---|");
    println!("| GPU (compute, incl. upload of the camera and read-back of the hits) | {g:.4} | {:.2} |", n / g / 1e6);
    println!("| CPU BVH, {threads} threads | {c:.4} | {:.2} |", n / c / 1e6);
    println!("GPU / CPU: {:.2}x the rays per second; {differ} pixels differ", c / g);
    Ok(())
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
