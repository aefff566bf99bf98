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
    println!("adapter: {}, {}x{}, dataset {} rays", gpu.describe(), w, h, total);
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
                occluder: None,
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
    whole_frames(sources, gpu, counts.first().copied().unwrap_or(0), (w, h), frames)
}

/// The whole pipeline's frame (image, composition and `n` rays, composited), as the viewer's
/// window samples it from the GPU, beside the same frame read back as RGBA8 (how a frame crossed
/// to the window before the window shared the pipeline's device). Frames alternate, so both see
/// the same machine.
fn whole_frames(sources: Sources, gpu: Gpu, n: u64, (w, h): (u32, u32), frames: usize) -> Result<()> {
    let mut p = rtvtk_viz::Pipeline::new(gpu, sources);
    p.resize(w, h)?;
    if p.sources.picture.is_some() {
        p.add("image", &serde_json::Value::Null)?;
    }
    if p.sources.scene.is_some() {
        p.add("composition", &serde_json::Value::Null)?;
    }
    p.add("rays", &serde_json::json!({"max_rays": n, "line_width": 1.0}))?;
    p.render()?;
    p.gpu.wait()?;
    let (mut on_gpu, mut read_back) = (Vec::new(), Vec::new());
    let mut cam = p.camera();
    for i in 0..2 * frames {
        cam.orbit(0.002, 0.0);
        p.set_camera(cam)?;
        let t = Instant::now();
        let out = p.render()?.clone();
        if i % 2 == 0 {
            p.gpu.wait()?;
            on_gpu.push(t.elapsed().as_secs_f64());
        } else {
            p.gpu.read_rgba(&out)?;
            read_back.push(t.elapsed().as_secs_f64());
        }
    }
    let (g, r) = (median(&mut on_gpu), median(&mut read_back));
    println!();
    println!("whole frame (image, composition, {n} rays; {w}x{h}), median of {frames} each, interleaved:");
    println!("| frame | ms | frames/s |");
    println!("|---|---|---|");
    println!("| left on the GPU (the viewer's window samples it) | {:.2} | {:.1} |", g * 1e3, 1.0 / g);
    println!("| read back as RGBA8 (a PNG; the window before) | {:.2} | {:.1} |", r * 1e3, 1.0 / r);
    println!("read-back costs {:.2} ms a frame ({:.2}x)", (r - g) * 1e3, r / g);
    Ok(())
}
