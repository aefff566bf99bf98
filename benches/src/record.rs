//! `rtvtk bench record`: recording overhead. The same `rtvtk record` command (scene, seed,
//! threads) runs with write-mode recording and with `--no-record`, alternating, each in its own
//! process; the wall times, their medians and ratios are printed.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};

use crate::dir_bytes;
use crate::query::median;

/// Wall seconds of `rtvtk record ARGS --out OUT --quiet [--no-record]`. Both runs write the same
/// PNG and EXR beside OUT (a recording writes them into OUT by default, `--no-record` writes none
/// unless asked: left to the defaults, image output would be counted as recording overhead).
fn timed_record(exe: &Path, args: &[String], out: &Path, record: bool) -> Result<f64> {
    if out.exists() {
        std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    }
    let mut cmd = Command::new(exe);
    cmd.arg("record").args(args).arg("--out").arg(out).arg("--quiet");
    let dir = out.parent().unwrap_or(out);
    cmd.arg("--image").arg(dir.join("image.png")).arg("--exr").arg(dir.join("image.exr"));
    if !record {
        cmd.arg("--no-record");
    }
    let t = Instant::now();
    let status = cmd.status().with_context(|| format!("running {}", exe.display()))?;
    let secs = t.elapsed().as_secs_f64();
    if !status.success() {
        bail!("`rtvtk record {}` failed ({status})", args.join(" "));
    }
    Ok(secs)
}

pub fn run(runs: usize, args: &[String]) -> Result<()> {
    if let Some(a) =
        args.iter().find(|a| matches!(a.as_str(), "--out" | "--no-record" | "--quiet" | "--image" | "--exr"))
    {
        bail!("bench record sets {a} itself; give only the scene, size, spp, threads, writers, ... of `rtvtk record`");
    }
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let out = tmp.path().join("trace");
    println!(
        "## rtvtk bench record: `rtvtk record {}`, with and without recording, {runs} alternating pairs\n",
        args.join(" ")
    );
    println!("| pair | record s | no-record s | ratio |");
    println!("|---|---|---|---|");
    let (mut rec, mut norec, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..runs.max(1) {
        let a = timed_record(&exe, args, &out, true)?;
        let b = timed_record(&exe, args, &out, false)?;
        println!("| {} | {a:.3} | {b:.3} | {:.3}x |", i + 1, a / b);
        rec.push(a);
        norec.push(b);
        ratios.push(a / b);
    }
    let (mr, mn) = (median(&rec), median(&norec));
    timed_record(&exe, args, &out, true)?;
    let ds = rl::Dataset::open(&out)?;
    let bytes = dir_bytes(&out);
    println!(
        "\nmedian: record {mr:.3} s, no-record {mn:.3} s: overhead {:.3}x (median of the pair ratios {:.3}x, range {:.3}–{:.3}x)",
        mr / mn,
        median(&ratios),
        ratios.iter().copied().fold(f64::INFINITY, f64::min),
        ratios.iter().copied().fold(0.0, f64::max),
    );
    println!(
        "recorded {} trees, {} rays, {:.1} MB ({:.1} B/ray); wall times include scene loading and the BVH build",
        ds.tree_count(),
        ds.ray_count(),
        bytes as f64 / 1e6,
        bytes as f64 / ds.ray_count().max(1) as f64
    );
    Ok(())
}
