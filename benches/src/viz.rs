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

/// Resident and peak resident memory of this process (bytes), from /proc (zero elsewhere).
pub(crate) fn rss() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name)?.trim().strip_suffix("kB")?.trim().parse::<u64>().ok())
            .unwrap_or(0)
            * 1024
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Renders `c` once into `target` from `camera` (no preview budget, no occluder).
fn render_once(
    c: &mut Rays,
    gpu: &Gpu,
    sources: &Sources,
    camera: &rtvtk_viz::ViewCamera,
    frame: rtvtk_viz::camera::Frame,
    target: &LayerTarget,
) -> Result<()> {
    let progress = rtvtk_viz::component::Progress::default();
    let mut ctx = RenderCtx { gpu, sources, camera, frame, target, progress: &progress, preview: None, occluder: None };
    c.render(&mut ctx)?;
    Ok(())
}

/// The ray styles `bench viz` draws, in its table's order.
pub const STYLES: [&str; 3] = ["lines", "alpha", "density"];

/// `frames`: timed frames per style and ray count, each after `warmup` untimed ones; `styles`:
/// those of [`STYLES`] to draw (the others' columns say "-"; none: the load alone).
pub fn run(
    dataset: &Path,
    counts: &[u64],
    (w, h): (u32, u32),
    (frames, warmup): (usize, usize),
    rounds: usize,
    styles: &[String],
) -> Result<()> {
    if let Some(bad) = styles.iter().find(|s| !STYLES.contains(&s.as_str())) {
        bail!("unknown style {bad:?}: expected some of {}", STYLES.join(", "));
    }
    let sources = Sources::open(dataset)?;
    let total = sources.dataset.as_ref().map_or(0, |d| d.ray_count());
    let gpu = Gpu::shared()?;
    println!("adapter: {}, {}x{}, dataset {} rays", gpu.describe(), w, h, total);
    println!(
        "load: the layer's load of N rays (a stratified sample of all where N is fewer) beside a SQL scan of the same \
         columns of the rows it reads; memory: resident growth over the load and frames, beside the segment buffer"
    );
    println!(
        "| rays | SQL scan s | layer load s | load / scan | lines ms | alpha ms | density ms | GPU bytes/segment | resident growth MiB | segments MiB | growth / segments |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let frame = sources.frame();
    let target = LayerTarget::new(&gpu, "bench", w, h);
    // Warm up: the pipelines of every style compiled and the device's pools allocated once, so
    // the first row's memory is the layer's own.
    {
        let mut warm = Rays::new(ComponentId(2), &sources, &serde_json::json!({"max_rays": 1000}))?;
        for style in ["lines", "alpha", "density"] {
            let mut settings = warm.settings();
            settings["style"] = serde_json::json!(style);
            warm.set_settings(&settings)?;
            render_once(&mut warm, &gpu, &sources, &sources.initial_camera(), frame, &target)?;
        }
        gpu.wait()?;
    }
    for &n in counts {
        if n > total {
            bail!("the dataset has {total} rays, fewer than {n}; record a bigger one");
        }
        // The layer reads every row and keeps a sample when N is fewer: the scan reads them all.
        let sql = "SELECT tree_id, ray, depth, kind, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays";
        let mut scan = Vec::new();
        let mut load = Vec::new();
        let mut rays = Rays::new(ComponentId(1), &sources, &serde_json::json!({"max_rays": n, "line_width": 1.0}))?;
        // Memory first, before any SQL scan in this round: resident growth over one load and the
        // frames in every style.
        let (before, _) = rss();
        rays.load(&gpu, &sources, frame)?;
        gpu.wait()?;
        let mut steps = vec![("load", rss().0)];
        // Frames in each style: orbit the camera a little each frame so every frame really draws.
        let mut per_style = Vec::new();
        for style in STYLES {
            if !styles.iter().any(|s| s == style) {
                per_style.push(None);
                continue;
            }
            let mut settings = rays.settings();
            settings["style"] = serde_json::json!(style);
            rays.set_settings(&settings)?;
            let mut cam = sources.initial_camera();
            let mut times = Vec::with_capacity(frames);
            for i in 0..frames + warmup {
                cam.orbit(0.002, 0.0);
                let t = Instant::now();
                render_once(&mut rays, &gpu, &sources, &cam, frame, &target)?;
                gpu.wait()?;
                if i >= warmup {
                    times.push(t.elapsed().as_secs_f64());
                }
            }
            per_style.push(Some(median(&mut times)));
            steps.push((style, rss().0));
        }
        let (after, _) = rss();
        for _ in 0..rounds {
            let t = Instant::now();
            let mut rows = 0u64;
            sources.query_batches(sql, |b| {
                rows += b.num_rows() as u64;
                Ok(())
            })?;
            scan.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            rays.load(&gpu, &sources, frame)?;
            gpu.wait()?;
            load.push(t.elapsed().as_secs_f64());
            if rows != total {
                bail!("the scan returned {rows} rows, expected {total}");
            }
        }
        let ms = |t: Option<f64>| t.map_or("-".to_string(), |t| format!("{:.1}", t * 1e3));
        let segs = rays.segment_count().max(1);
        let (s, l) = (median(&mut scan), median(&mut load));
        let growth = after.saturating_sub(before) as f64 / f64::from(1 << 20);
        let seg_mib = rays.gpu_bytes() as f64 / f64::from(1 << 20);
        println!(
            "| {} | {:.3} | {:.3} | {:.2}x | {} | {} | {} | {:.1} | {:.0} | {:.0} | {:.2}x |",
            n,
            s,
            l,
            l / s,
            ms(per_style[0]),
            ms(per_style[1]),
            ms(per_style[2]),
            rays.gpu_bytes() as f64 / segs as f64,
            growth,
            seg_mib,
            growth / seg_mib.max(1e-9),
        );
        let mib = |b: u64| b as f64 / f64::from(1 << 20);
        let mut last = before;
        let parts: Vec<String> = steps
            .iter()
            .map(|&(step, at)| {
                let d = mib(at) - mib(last);
                last = at;
                format!("{step} {d:+.0}")
            })
            .collect();
        println!("  resident growth by step (MiB): {}", parts.join(", "));
        for r in rays.report() {
            println!("  {r}");
        }
        drop(rays);
    }
    if styles.is_empty() {
        return Ok(());
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
