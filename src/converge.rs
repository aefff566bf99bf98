//! `rtvtk converge`: error of the path tracers against time and samples per pixel.

use std::path::Path;

use anyhow::{Context, Result, bail};
use renderers::TracerChoice;
use renderers::converge::{ConvergencePoint, log_log_fit, measure, write_plots};

/// `rtvtk converge`: image error against time and samples per pixel.
#[derive(clap::Args)]
pub struct ConvergeArgs {
    #[arg(long, default_value = "cornell")]
    pub scene: String,
    #[arg(long, default_value = "96x96", value_parser = crate::args::parse_size)]
    pub size: (u32, u32),
    /// Samples per pixel of the reference image.
    #[arg(long, default_value_t = 1024)]
    pub reference_spp: u32,
    /// Sample counts to measure (comma separated).
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16,32,64,128")]
    pub spp: Vec<u32>,
    /// Directory for convergence.csv, convergence.png and reference.exr.
    #[arg(long, default_value = "converge-out")]
    pub out: std::path::PathBuf,
    #[arg(long)]
    pub threads: Option<usize>,
    /// The tracers to measure side by side (comma separated): path (or cpu), gpu.
    #[arg(long, value_delimiter = ',', default_value = "path", value_parser = crate::args::parse_tracer)]
    pub tracer: Vec<TracerChoice>,
    /// Renders per point: its time is their median, shown with their spread.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub runs: u32,
}

impl ConvergeArgs {
    pub fn run(&self) -> Result<()> {
        let a = self;
        run(&a.scene, a.size, a.reference_spp, &a.spp, &a.out, a.threads, &a.tracer, a.runs)
    }
}

/// `rtvtk converge`: error of each tracer against time, as a table, a CSV and a plot, all
/// against one CPU reference.
#[allow(clippy::too_many_arguments)]
pub fn run(
    scene: &str,
    (w, h): (u32, u32),
    reference_spp: u32,
    spps: &[u32],
    out: &Path,
    threads: Option<usize>,
    tracers: &[TracerChoice],
    runs: u32,
) -> Result<()> {
    let mut tracers = tracers.to_vec();
    tracers.dedup();
    if tracers.is_empty() {
        bail!("--tracer: name at least one of path (cpu), gpu");
    }
    if tracers.contains(&TracerChoice::Whitted) {
        bail!("--tracer whitted: the Whitted tracer converges to another image than the path tracers' reference");
    }
    if spps.is_empty() || spps.iter().any(|&s| s == 0 || s >= reference_spp) {
        bail!("--spp: sample counts must be positive and below the reference's {reference_spp}");
    }
    let scene = renderers::load_scene(scene, None, 1)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let base = renderers::RenderOptions { width: w, height: h, threads, ..Default::default() };
    let (scene, bvh) = (std::sync::Arc::new(scene), std::sync::Arc::new(bvh));
    // The GPU first: without an adapter the command fails before the long reference render.
    let mut built = Vec::new();
    for &t in tracers.iter().rev() {
        let tracer = renderers::tracer(t, scene.clone(), bvh.clone()).with_context(|| format!("the {t} tracer"))?;
        if t.on_gpu() {
            // The first dispatch pays for driver-side shader work: not part of any point.
            tracer.render(&renderers::RenderOptions { spp: 1, ..base.clone() }, None, &|_| {})?;
        }
        built.insert(0, tracer);
    }
    eprintln!("rendering the {reference_spp}-spp CPU reference of {} at {w}x{h} ...", scene.name);
    let reference = renderers::converge::reference(&scene, &bvh, &base, reference_spp)?;
    let mut curves: Vec<(TracerChoice, Vec<ConvergencePoint>)> = Vec::new();
    for tracer in &built {
        let t = tracer.choice();
        eprintln!("measuring the {t} tracer ...");
        let points = measure(&reference, 0, spps, runs, |spp, seed| {
            let opts = renderers::RenderOptions { spp, seed, ..base.clone() };
            tracer.render(&opts, None, &|_| {}).map(|(img, _)| img).map_err(anyhow::Error::from)
        })?;
        curves.push((t, points));
    }
    std::fs::create_dir_all(out)?;
    reference.write_exr(&out.join("reference.exr"))?;
    reference.write_png(&out.join("reference.png"), 1.0)?;
    let mut csv = String::from("tracer,spp,seconds,seconds_min,seconds_max,runs,rmse,rel_mse\n");
    println!("| tracer | spp | seconds (median of {runs}) | min–max | RMSE | relMSE |");
    println!("|---|---|---|---|---|---|");
    for (t, points) in &curves {
        for p in points {
            println!(
                "| {} | {} | {:.4} | {:.4}–{:.4} | {:.5} | {:.6} |",
                t.name(),
                p.spp,
                p.secs,
                p.secs_min,
                p.secs_max,
                p.rmse,
                p.rel_mse
            );
            csv.push_str(&format!(
                "{},{},{},{},{},{},{},{}\n",
                t.name(),
                p.spp,
                p.secs,
                p.secs_min,
                p.secs_max,
                p.runs,
                p.rmse,
                p.rel_mse
            ));
        }
    }
    std::fs::write(out.join("convergence.csv"), csv)?;
    let named: Vec<(&str, &[ConvergencePoint])> = curves.iter().map(|(t, p)| (t.name(), p.as_slice())).collect();
    write_plots(&named, &out.join("convergence.png"))?;
    println!();
    for (t, points) in &curves {
        let by_spp = log_log_fit(&points.iter().map(|p| (f64::from(p.spp), p.rmse)).collect::<Vec<_>>());
        let by_time = log_log_fit(&points.iter().map(|p| (p.secs, p.rmse)).collect::<Vec<_>>());
        let rel_spp = log_log_fit(&points.iter().map(|p| (f64::from(p.spp), p.rel_mse.sqrt())).collect::<Vec<_>>());
        let rel_time = log_log_fit(&points.iter().map(|p| (p.secs, p.rel_mse.sqrt())).collect::<Vec<_>>());
        println!(
            "{}: log-log slopes with 95% intervals (Monte Carlo: -0.5): RMSE {by_spp} vs spp, {by_time} vs time; sqrt(relMSE) {rel_spp} vs spp, {rel_time} vs time",
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
    for device in built.iter().filter_map(|t| t.device()) {
        println!("GPU: {device}");
    }
    println!(
        "wrote {}/convergence.csv, convergence.png (per tracer: RMSE and sqrt(relMSE); grey slope -1/2), reference.exr",
        out.display()
    );
    Ok(())
}
