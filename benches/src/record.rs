//! `rtvtk bench record`: recording overhead. The same `rtvtk record` command (scene, seed,
//! threads) runs with write-mode recording and with `--no-record`, alternating, each in its own
//! process; the wall times, their medians and ratios are printed. Without a command, the standard
//! suite: the Cornell box and the 1M-triangle box at 1, 2 and all tracing threads, one table.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};

use crate::dir_bytes;
use crate::query::median;

/// Wall seconds of `rtvtk record ARGS --out OUT --quiet [--no-record]`. Both runs write the same
/// PNG and EXR beside OUT (a recording writes them into OUT by default, `--no-record` writes none
/// unless asked: left to the defaults, image output would be counted as recording overhead).
/// A recording first removes the last one's OUT; `--no-record` leaves OUT as it is.
fn timed_record(exe: &Path, args: &[String], out: &Path, record: bool) -> Result<f64> {
    if record && out.exists() {
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

/// The medians of one configuration's alternating pairs.
struct Overhead {
    record: f64,
    no_record: f64,
    /// Lowest and highest pair ratio.
    range: (f64, f64),
    trees: u64,
    rays: u64,
    bytes_per_ray: f64,
}

/// Runs `runs` alternating pairs of `rtvtk record ARGS` with and without recording, printing a
/// row per pair; the rays and bytes are those of the last pair's recording.
fn measure(exe: &Path, args: &[String], runs: usize, out: &Path) -> Result<Overhead> {
    println!("| pair | record s | no-record s | ratio |");
    println!("|---|---|---|---|");
    let (mut rec, mut norec, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..runs.max(1) {
        let a = timed_record(exe, args, out, true)?;
        let b = timed_record(exe, args, out, false)?;
        println!("| {} | {a:.3} | {b:.3} | {:.3}x |", i + 1, a / b);
        rec.push(a);
        norec.push(b);
        ratios.push(a / b);
    }
    let ds = rl::Dataset::open(out)?;
    let rays = ds.ray_count();
    Ok(Overhead {
        trees: ds.tree_count(),
        record: median(&rec),
        no_record: median(&norec),
        range: (ratios.iter().copied().fold(f64::INFINITY, f64::min), ratios.iter().copied().fold(0.0, f64::max)),
        rays,
        bytes_per_ray: dir_bytes(out) as f64 / rays.max(1) as f64,
    })
}

fn refuse_own_flags(args: &[String]) -> Result<()> {
    if let Some(a) =
        args.iter().find(|a| matches!(a.as_str(), "--out" | "--no-record" | "--quiet" | "--image" | "--exr"))
    {
        bail!("bench record sets {a} itself; give only the scene, size, spp, threads, writers, ... of `rtvtk record`");
    }
    Ok(())
}

/// `rtvtk bench record [ARGS]`: with ARGS, that one `rtvtk record` command; without, the
/// standard suite ([`SUITE`] at 1, 2 and all tracing threads).
pub fn run(runs: usize, args: &[String]) -> Result<()> {
    if args.is_empty() {
        return suite(runs);
    }
    refuse_own_flags(args)?;
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let out = tmp.path().join("trace");
    println!(
        "## rtvtk bench record: `rtvtk record {}`, with and without recording, {runs} alternating pairs\n",
        args.join(" ")
    );
    let o = measure(&exe, args, runs, &out)?;
    println!(
        "\nmedian: record {:.3} s, no-record {:.3} s: overhead {:.3}x (pair ratios {:.3}–{:.3}x)",
        o.record,
        o.no_record,
        o.record / o.no_record,
        o.range.0,
        o.range.1,
    );
    println!(
        "recorded {} trees, {} rays ({:.1} B/ray); wall times include scene loading and the BVH build",
        o.trees, o.rays, o.bytes_per_ray
    );
    Ok(())
}

/// The standard scenes of the recording-overhead goals (issue 45): the path-traced Cornell box,
/// ~25M rays, whose tracers outrun recording most; the same box split into ~1M triangles,
/// ~12.5M rays, where tracing costs more per ray.
const SUITE: [(&str, &str); 2] = [
    ("Cornell box, 384²×32", "--size 384x384 --spp 32"),
    ("1M triangles (--subdivide 128), 384²×16", "--subdivide 128 --size 384x384 --spp 16"),
];

/// Tracing thread counts of the suite: 1, 2 and all cores (each once).
fn suite_threads() -> Vec<usize> {
    let all = std::thread::available_parallelism().map_or(1, usize::from);
    let mut t = vec![1, 2, all];
    t.sort_unstable();
    t.dedup();
    t
}

fn suite(runs: usize) -> Result<()> {
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let out = tmp.path().join("trace");
    let threads = suite_threads();
    println!(
        "## rtvtk bench record: the standard scenes at {} tracing threads, with and without recording, {runs} alternating pairs each\n",
        threads.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")
    );
    let mut rows = Vec::new();
    for (name, scene) in SUITE {
        for &t in &threads {
            let args: Vec<String> =
                scene.split_whitespace().map(str::to_string).chain(["--threads".into(), t.to_string()]).collect();
            println!("### {name}, {t} thread(s): `rtvtk record {}`\n", args.join(" "));
            let o = measure(&exe, &args, runs, &out)?;
            println!();
            rows.push((name, t, o));
        }
    }
    println!("| scene | threads | rays | record s | no-record s | overhead | pair range | B/ray |");
    println!("|---|---|---|---|---|---|---|---|");
    for (name, t, o) in &rows {
        println!(
            "| {name} | {t} | {} | {:.3} | {:.3} | {:.3}x | {:.3}–{:.3}x | {:.1} |",
            o.rays,
            o.record,
            o.no_record,
            o.record / o.no_record,
            o.range.0,
            o.range.1,
            o.bytes_per_ray
        );
    }
    println!("\nmedians of the pairs; wall times end to end (scene loading, the BVH build and sealing included)");
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_suite_runs_one_two_and_all_threads_once_each() {
        let t = super::suite_threads();
        let all = std::thread::available_parallelism().map_or(1, usize::from);
        assert_eq!(&t[..2], &[1, 2]);
        assert!(t.contains(&all));
        assert!(t.windows(2).all(|w| w[0] < w[1]), "{t:?}");
    }
}
