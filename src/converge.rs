//! `rtvtk converge`: error of the path tracer against time and samples per pixel.

use std::path::Path;

use anyhow::Result;

/// `rtvtk converge`: error of the path tracer against time, as a table, a CSV and a plot.
pub fn run(
    scene: &str,
    (w, h): (u32, u32),
    reference_spp: u32,
    spps: &[u32],
    out: &Path,
    threads: Option<usize>,
) -> Result<()> {
    use renderers::converge::{convergence, log_log_slope, write_plot};
    let scene = renderers::load_scene(scene, None, 1)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let base = renderers::RenderOptions { width: w, height: h, threads, ..Default::default() };
    eprintln!("rendering the {reference_spp}-spp reference of {} at {w}x{h} ...", scene.name);
    let (reference, points) = convergence(&scene, &bvh, &base, reference_spp, spps)?;
    std::fs::create_dir_all(out)?;
    reference.write_exr(&out.join("reference.exr"))?;
    reference.write_png(&out.join("reference.png"), 1.0)?;
    let mut csv = String::from("spp,seconds,rmse,rel_mse\n");
    println!("| spp | seconds | RMSE | relMSE |");
    println!("|---|---|---|---|");
    for p in &points {
        println!("| {} | {:.4} | {:.5} | {:.6} |", p.spp, p.secs, p.rmse, p.rel_mse);
        csv.push_str(&format!("{},{},{},{}\n", p.spp, p.secs, p.rmse, p.rel_mse));
    }
    std::fs::write(out.join("convergence.csv"), csv)?;
    write_plot(&points, &out.join("convergence.png"))?;
    let by_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rmse)).collect::<Vec<_>>());
    let by_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rmse)).collect::<Vec<_>>());
    let rel_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rel_mse.sqrt())).collect::<Vec<_>>());
    let rel_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rel_mse.sqrt())).collect::<Vec<_>>());
    println!();
    println!(
        "log-log slopes (Monte Carlo: -0.5): RMSE {by_spp:.3} vs spp, {by_time:.3} vs time; sqrt(relMSE) {rel_spp:.3} vs spp, {rel_time:.3} vs time"
    );
    println!(
        "wrote {}/convergence.csv, convergence.png (blue RMSE, red sqrt(relMSE), grey slope -1/2), reference.exr",
        out.display()
    );
    Ok(())
}
