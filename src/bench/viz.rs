//! `rtvtk bench viz`: the ray layer's load time beside a plain SQL scan of the same columns, its
//! frame time, and its GPU memory per segment.

use std::path::Path;
use std::time::Instant;

use anyhow::{Result, bail};
use rtvtk_viz::component::{Component, ComponentId, LayerTarget, RenderCtx};
use rtvtk_viz::components::rays::Rays;
use rtvtk_viz::{Gpu, Sources};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn run(dataset: &Path, counts: &[u64], (w, h): (u32, u32), frames: usize, rounds: usize) -> Result<()> {
    let sources = Sources::open(dataset)?;
    let total = sources.dataset.as_ref().map_or(0, |d| d.ray_count());
    let gpu = Gpu::shared()?;
    println!("adapter: {} ({:?}), {}x{}, dataset {} rays", gpu.adapter.name, gpu.adapter.backend, w, h, total);
    println!("| rays | SQL scan s | layer load s | load / scan | frame ms (median) | frames/s | GPU bytes/segment |");
    println!("|---|---|---|---|---|---|---|");
    let frame = sources.frame();
    let target = LayerTarget::new(&gpu, "bench", w, h);
    for &n in counts {
        if n > total {
            bail!("the dataset has {total} rays, fewer than {n}; record a bigger one");
        }
        let sql = format!(
            "SELECT tree_id, kind, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays WHERE TRUE LIMIT {n}"
        );
        let mut scan = Vec::new();
        let mut load = Vec::new();
        let mut rays = Rays::new(ComponentId(1), &sources, &serde_json::json!({"max_rays": n, "line_width": 1.0}))?;
        for _ in 0..rounds {
            let t = Instant::now();
            let mut rows = 0u64;
            sources.query_batches(&sql, |b| {
                rows += b.num_rows() as u64;
                Ok(())
            })?;
            scan.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            rays.load(&gpu, &sources, frame)?;
            gpu.wait()?;
            load.push(t.elapsed().as_secs_f64());
            if rows != n {
                bail!("the scan returned {rows} rows, expected {n}");
            }
        }
        // Frames: orbit the camera a little each frame so every frame really draws.
        let mut cam = sources.initial_camera();
        let mut times = Vec::with_capacity(frames);
        let progress = rtvtk_viz::component::Progress::default();
        for i in 0..frames + 2 {
            cam.orbit(0.002, 0.0);
            let t = Instant::now();
            let mut ctx = RenderCtx {
                gpu: &gpu,
                sources: &sources,
                camera: &cam,
                frame,
                target: &target,
                progress: &progress,
                preview: None,
            };
            rays.render(&mut ctx)?;
            gpu.wait()?;
            if i >= 2 {
                times.push(t.elapsed().as_secs_f64());
            }
        }
        let segs = rays.segment_count().max(1);
        let (s, l, f) = (median(&mut scan), median(&mut load), median(&mut times));
        println!(
            "| {} | {:.3} | {:.3} | {:.2}x | {:.2} | {:.1} | {:.1} |",
            n,
            s,
            l,
            l / s,
            f * 1e3,
            1.0 / f,
            rays.gpu_bytes() as f64 / segs as f64
        );
        for r in rays.report() {
            println!("  {r}");
        }
    }
    Ok(())
}
