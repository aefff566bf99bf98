//! `rtvtk converge`: error of the path tracers against time and samples per pixel.

use std::path::Path;

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use renderers::converge::{ConvergencePoint, log_log_slope, measure, write_plots};

/// A tracer `rtvtk converge` measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Tracer {
    /// The CPU path tracer on every core.
    Cpu,
    /// The GPU path tracer (wgpu compute).
    Gpu,
}

impl Tracer {
    fn name(self) -> &'static str {
        match self {
            Tracer::Cpu => "cpu",
            Tracer::Gpu => "gpu",
        }
    }
}

/// `rtvtk converge`: error of each tracer against time, as a table, a CSV and a plot, all
/// against one CPU reference.
pub fn run(
    scene: &str,
    (w, h): (u32, u32),
    reference_spp: u32,
    spps: &[u32],
    out: &Path,
    threads: Option<usize>,
    tracers: &[Tracer],
) -> Result<()> {
    let mut tracers = tracers.to_vec();
    tracers.dedup();
    if tracers.is_empty() {
        bail!("--tracer: name at least one of cpu, gpu");
    }
    if spps.is_empty() || spps.iter().any(|&s| s == 0 || s >= reference_spp) {
        bail!("--spp: sample counts must be positive and below the reference's {reference_spp}");
    }
    let scene = renderers::load_scene(scene, None, 1)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let base = renderers::RenderOptions { width: w, height: h, threads, ..Default::default() };
    // The GPU first: without an adapter the command fails before the long reference render.
    let gpu = match tracers.contains(&Tracer::Gpu) {
        true => {
            let g = gpu_tracer::GpuTracer::new(&scene, &bvh).context("the GPU tracer")?;
            // The first dispatch pays for driver-side shader work: not part of any point.
            g.render(w, h, 1, 0, base.max_depth)?;
            Some(g)
        }
        false => None,
    };
    eprintln!("rendering the {reference_spp}-spp CPU reference of {} at {w}x{h} ...", scene.name);
    let reference = renderers::converge::reference(&scene, &bvh, &base, reference_spp)?;
    let mut curves: Vec<(Tracer, Vec<ConvergencePoint>)> = Vec::new();
    for &t in &tracers {
        eprintln!("measuring the {} tracer ...", t.name());
        let points = match (&gpu, t) {
            (Some(g), Tracer::Gpu) => measure(&reference, 0, spps, |spp, seed| {
                g.render(w, h, spp, (seed ^ (seed >> 32)) as u32, base.max_depth).map_err(anyhow::Error::from)
            })?,
            _ => measure(&reference, 0, spps, |spp, seed| {
                let opts = renderers::RenderOptions { spp, seed, ..base.clone() };
                renderers::render(&scene, &bvh, &opts, None, &|_| {}).map(|(img, _)| img).map_err(anyhow::Error::from)
            })?,
        };
        curves.push((t, points));
    }
    std::fs::create_dir_all(out)?;
    reference.write_exr(&out.join("reference.exr"))?;
    reference.write_png(&out.join("reference.png"), 1.0)?;
    let mut csv = String::from("tracer,spp,seconds,rmse,rel_mse\n");
    println!("| tracer | spp | seconds | RMSE | relMSE |");
    println!("|---|---|---|---|---|");
    for (t, points) in &curves {
        for p in points {
            println!("| {} | {} | {:.4} | {:.5} | {:.6} |", t.name(), p.spp, p.secs, p.rmse, p.rel_mse);
            csv.push_str(&format!("{},{},{},{},{}\n", t.name(), p.spp, p.secs, p.rmse, p.rel_mse));
        }
    }
    std::fs::write(out.join("convergence.csv"), csv)?;
    let named: Vec<(&str, &[ConvergencePoint])> = curves.iter().map(|(t, p)| (t.name(), p.as_slice())).collect();
    write_plots(&named, &out.join("convergence.png"))?;
    println!();
    for (t, points) in &curves {
        let by_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rmse)).collect::<Vec<_>>());
        let by_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rmse)).collect::<Vec<_>>());
        let rel_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rel_mse.sqrt())).collect::<Vec<_>>());
        let rel_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rel_mse.sqrt())).collect::<Vec<_>>());
        println!(
            "{}: log-log slopes (Monte Carlo: -0.5): RMSE {by_spp:.3} vs spp, {by_time:.3} vs time; sqrt(relMSE) {rel_spp:.3} vs spp, {rel_time:.3} vs time",
            t.name()
        );
    }
    if let (Some((_, a)), Some((_, b))) = (curves.first(), curves.get(1)) {
        // Same sample counts: the time ratio is the speed-up, the error ratio ~1 for one estimator.
        let ratio = |f: &dyn Fn(&ConvergencePoint) -> f64| {
            let r: Vec<f64> = a.iter().zip(b).map(|(p, q)| f(q) / f(p)).collect();
            (r.iter().map(|x| x.ln()).sum::<f64>() / r.len() as f64).exp()
        };
        println!(
            "{} against {} at the same spp (geometric mean): time {:.3}x, RMSE {:.3}x",
            curves[1].0.name(),
            curves[0].0.name(),
            ratio(&|p| p.secs.max(1e-9)),
            ratio(&|p| p.rmse.max(1e-12))
        );
    }
    if let Some(g) = &gpu {
        println!("GPU: {}", g.adapter());
    }
    println!(
        "wrote {}/convergence.csv, convergence.png (per tracer: RMSE and sqrt(relMSE); grey slope -1/2), reference.exr",
        out.display()
    );
    Ok(())
}
