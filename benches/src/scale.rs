//! `rtvtk bench scale`: how time and memory grow with a trace's length. Each step records a
//! Cornell-box trace of about N rays, then runs what a user runs on a whole trace, each command
//! in its own fresh process, with its wall time and peak resident set: `record`, `info`, `check`,
//! one pixel's trees (`tree --pixel`), one tree by id (`tree --tree`), 2000 random tree fetches
//! (`bench fetch`, whose latencies are printed too), SQL at one pixel, a per-pixel group-by, and
//! the viewer's first ray picture (`render` of a 100K-ray sample). The table ends with each command's growth
//! from the first step to the last beside the growth of the rays: linear time grows as the rays
//! do, random access and bounded memory do not grow.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};

use crate::dir_bytes;
use crate::query::run_measured;

/// What `rtvtk bench scale` runs.
pub struct ScaleArgs {
    /// Ray counts, one trace each (about: the image size is chosen from a calibration run).
    pub steps: Vec<u64>,
    /// Samples per pixel of every trace.
    pub spp: u32,
    /// Where the traces go (default: a temporary directory); each is removed after its step
    /// unless `keep`.
    pub dir: Option<PathBuf>,
    pub keep: bool,
    /// Also time the viewer's first picture (`render`; needs a GPU adapter, lavapipe will do).
    pub render: bool,
    /// `--memory-limit` of the SQL commands (default: theirs).
    pub memory_limit: Option<String>,
}

/// One command's wall seconds and peak resident bytes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Cost {
    secs: f64,
    rss: u64,
}

/// Runs `rtvtk ARGS` in a fresh process: its cost, and its stdout. A failure is an error naming
/// the command and the end of what it printed.
pub(crate) fn measured(exe: &Path, args: &[String]) -> Result<(Cost, String)> {
    let mut cmd = Command::new(exe);
    cmd.args(args);
    let t = Instant::now();
    let (out, rss) = run_measured(&mut cmd).with_context(|| format!("running {}", exe.display()))?;
    let secs = t.elapsed().as_secs_f64();
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(8).collect();
        bail!(
            "`rtvtk {}` failed ({}):\n{}",
            args.join(" "),
            out.status,
            tail.into_iter().rev().collect::<Vec<_>>().join("\n")
        );
    }
    Ok((Cost { secs, rss }, String::from_utf8_lossy(&out.stdout).into_owned()))
}

/// Bytes free on the file system holding `dir` (None where unknown).
fn free_bytes(dir: &Path) -> Option<u64> {
    #[cfg(unix)]
    {
        use std::os::unix::ffi::OsStrExt;
        let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
        // SAFETY: an all-zero statvfs is a valid value; statvfs writes it for a valid C path.
        let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
        // SAFETY: `c` is a NUL-terminated path and `s` is valid for writes.
        if unsafe { libc::statvfs(c.as_ptr(), &mut s) } != 0 {
            return None;
        }
        Some(s.f_bavail as u64 * s.f_frsize as u64)
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        None
    }
}

/// `10M`, `2.5M`, `1B`, `200K`, `5000`: a ray count.
pub fn parse_count(s: &str) -> std::result::Result<u64, String> {
    let t = s.trim();
    let (num, mult) = match t.chars().last().map(|c| c.to_ascii_uppercase()) {
        Some('K') => (&t[..t.len() - 1], 1e3),
        Some('M') => (&t[..t.len() - 1], 1e6),
        Some('B' | 'G') => (&t[..t.len() - 1], 1e9),
        _ => (t, 1.0),
    };
    match num.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 1.0 / mult && v * mult <= 1e12 => Ok((v * mult).round() as u64),
        _ => Err(format!("{s:?}: expected a ray count such as 5000, 200K, 10M or 1B")),
    }
}

/// The image side and samples per pixel of a trace of about `rays` rays, at `per_sample` rays
/// per sample and `spp` samples per pixel (at least 8x8 pixels).
fn size_for(rays: u64, per_sample: f64, spp: u32) -> u32 {
    let pixels = rays as f64 / (per_sample * f64::from(spp));
    (pixels.sqrt().round() as u32).max(8)
}

fn mib(b: u64) -> f64 {
    b as f64 / f64::from(1 << 20)
}

/// Runs the steps; prints one table of every command at every step, then the growth.
pub fn run(a: &ScaleArgs) -> Result<()> {
    if a.steps.is_empty() {
        bail!("give at least one step (--steps 10M,100M)");
    }
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let tmp;
    let root = match &a.dir {
        Some(d) => {
            std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
            d.clone()
        }
        None => {
            tmp = tempfile::tempdir().context("creating a temporary directory")?;
            tmp.path().to_path_buf()
        }
    };
    let spp = a.spp.max(1);
    // Calibration: rays per sample of this scene and depth, from a small trace.
    let calib = root.join("calibration");
    let _ = std::fs::remove_dir_all(&calib);
    let side = 48u32;
    let args = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<String>>();
    let path = |p: &Path| p.to_string_lossy().into_owned();
    // A recording of side² pixels into `out` (its pictures beside the traces, not counted).
    let record = |side: u32, out: &Path| -> Result<Cost> {
        let size = format!("{side}x{side}");
        let (image, exr) = (path(&root.join("image.png")), path(&root.join("image.exr")));
        let v = args(&["record", "--size", &size, "--spp", &spp.to_string(), "--out", &path(out), "--quiet"]);
        Ok(measured(&exe, &[v, args(&["--image", &image, "--exr", &exr])].concat())?.0)
    };
    record(side, &calib)?;
    let ds = rl::Dataset::open(&calib)?;
    let per_sample = ds.ray_count() as f64 / (f64::from(side * side) * f64::from(spp));
    let per_ray_bytes = dir_bytes(&calib) as f64 / ds.ray_count().max(1) as f64;
    drop(ds);
    std::fs::remove_dir_all(&calib).with_context(|| format!("removing {}", calib.display()))?;
    let floor = crate::viz::rss().1;
    println!(
        "## rtvtk bench scale: Cornell box, path tracer, {spp} spp ({per_sample:.2} rays per sample), steps {}\n",
        a.steps.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")
    );
    println!(
        "Each command in a fresh process (page cache as the recording left it); peak resident set from wait4 \
         (at least this driver's own, {:.0} MiB).\n",
        mib(floor)
    );
    let mut names: Vec<&'static str> = Vec::new();
    // Per step: (rays, bytes, costs in `names` order).
    let mut done: Vec<(u64, u64, Vec<Cost>)> = Vec::new();
    let mut fetch_lines: Vec<String> = Vec::new();
    for &n in &a.steps {
        let side = size_for(n, per_sample, spp);
        let dir = root.join(format!("trace-{n}"));
        let _ = std::fs::remove_dir_all(&dir);
        let need = (n as f64 * per_ray_bytes * 1.1) as u64;
        if let Some(free) = free_bytes(&root)
            && free < need
        {
            bail!(
                "a trace of {n} rays needs about {:.1} GB in {}, and {:.1} GB are free",
                need as f64 / 1e9,
                root.display(),
                free as f64 / 1e9
            );
        }
        let d = path(&dir);
        let mut costs: Vec<(&'static str, Cost)> = Vec::new();
        let c = record(side, &dir)?;
        costs.push(("record", c));
        let ds = rl::Dataset::open(&dir)?;
        let rays = ds.ray_count();
        // A tree in the middle of the trace, by id.
        let segs = &ds.manifest().segments;
        let mid_tree = segs.get(segs.len() / 2).map_or(0, |s| s.tree_id_min);
        drop(ds);
        let bytes = dir_bytes(&dir);
        costs.push(("info", measured(&exe, &args(&["info", &d]))?.0));
        costs.push(("check", measured(&exe, &args(&["check", &d]))?.0));
        // A pixel away from the centre and the edges, its fourth sample (or last).
        let (px, py, s) = (side * 52 / 100, side * 78 / 100, 3.min(spp - 1));
        let (c, out) =
            measured(&exe, &args(&["tree", &d, "--pixel", &format!("{px},{py}"), "--sample", &s.to_string()]))?;
        if out.trim().is_empty() {
            bail!("`rtvtk tree {d} --pixel {px},{py} --sample {s}` printed no tree");
        }
        costs.push(("one pixel's tree (`tree --pixel`)", c));
        costs.push((
            "one tree by id (`tree --tree`)",
            measured(&exe, &args(&["tree", &d, "--tree", &mid_tree.to_string()]))?.0,
        ));
        let (c, out) = measured(&exe, &args(&["bench", "fetch", &d, "--fetches", "2000", "--no-duckdb"]))?;
        costs.push(("2000 random tree fetches in one process (`bench fetch`)", c));
        fetch_lines.push(format!(
            "{n}: {}",
            out.lines().find(|l| l.starts_with("one-tree fetch")).unwrap_or("(no fetch figures printed)")
        ));
        let mut sql = |label: &'static str, query: String, to_file: bool| -> Result<()> {
            let mut v = args(&["sql", &d, &query]);
            if let Some(m) = &a.memory_limit {
                v.extend(args(&["--memory-limit", m]));
            }
            if to_file {
                v.extend(args(&["--format", "csv", "--out", &path(&root.join("answer.csv"))]));
            }
            costs.push((label, measured(&exe, &v)?.0));
            Ok(())
        };
        sql(
            "SQL at one pixel",
            format!("SELECT count(*) FROM rays WHERE pixel_x = {px} AND pixel_y = {py} AND sample = {s}"),
            false,
        )?;
        sql(
            "per-pixel group-by (avg depth)",
            "SELECT pixel_x, pixel_y, avg(depth) FROM rays GROUP BY pixel_x, pixel_y".into(),
            true,
        )?;
        if a.render {
            let v = args(&[
                "render",
                &d,
                "--layers",
                "geometry,rays",
                "--max-rays",
                "100000",
                "--size",
                "512x512",
                "--out",
                &path(&root.join("first.png")),
            ]);
            costs.push(("first ray picture (`render`, 100K rays)", measured(&exe, &v)?.0));
        }
        if !a.keep {
            std::fs::remove_dir_all(&dir).with_context(|| format!("removing {}", dir.display()))?;
        }
        if names.is_empty() {
            names = costs.iter().map(|c| c.0).collect();
        }
        eprintln!(
            "step {n}: {rays} rays ({side}x{side}x{spp}), {:.2} GB, recorded in {:.1} s",
            bytes as f64 / 1e9,
            costs[0].1.secs
        );
        done.push((rays, bytes, costs.into_iter().map(|c| c.1).collect()));
    }
    let mut head = "| command |".to_string();
    let mut rule = "|---|".to_string();
    for (rays, bytes, _) in &done {
        head += &format!(" {rays} rays ({:.2} GB): s | MiB |", *bytes as f64 / 1e9);
        rule += "---|---|";
    }
    let growth = done.len() > 1;
    if growth {
        head += " time growth | memory growth |";
        rule += "---|---|";
    }
    println!("{head}\n{rule}");
    let (first, last) = (&done[0], &done[done.len() - 1]);
    for (k, name) in names.iter().enumerate() {
        let mut line = format!("| {name} |");
        for (_, _, costs) in &done {
            line += &format!(" {:.3} | {:.0} |", costs[k].secs, mib(costs[k].rss));
        }
        if growth {
            line += &format!(
                " {:.2}x | {:.2}x |",
                last.2[k].secs / first.2[k].secs.max(1e-9),
                last.2[k].rss as f64 / first.2[k].rss.max(1) as f64
            );
        }
        println!("{line}");
    }
    if growth {
        println!(
            "\nrays grew {:.2}x from the first step to the last: a linear-time command's time grows as much, a \
             random access's and bounded memory's stay near 1x",
            last.0 as f64 / first.0.max(1) as f64
        );
    }
    println!("\nfetch latency per step (`bench fetch`):");
    for l in &fetch_lines {
        println!("  {l}");
    }
    for (rays, bytes, costs) in &done {
        let check = costs[names.iter().position(|n| *n == "check").unwrap_or(0)];
        println!(
            "{rays} rays: {:.1} B/ray, recorded at {:.1} Mrays/s, checked at {:.1} Mrays/s",
            *bytes as f64 / (*rays).max(1) as f64,
            *rays as f64 / costs[0].secs.max(1e-9) / 1e6,
            *rays as f64 / check.secs.max(1e-9) / 1e6
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_parse_with_suffixes_and_bad_ones_are_refused() {
        assert_eq!(parse_count("5000"), Ok(5000));
        assert_eq!(parse_count("200K"), Ok(200_000));
        assert_eq!(parse_count("2.5M"), Ok(2_500_000));
        assert_eq!(parse_count("1B"), Ok(1_000_000_000));
        assert_eq!(parse_count("10m"), Ok(10_000_000));
        for bad in ["", "M", "-3M", "lots", "NaNM", "1e13"] {
            let e = parse_count(bad).unwrap_err();
            assert!(e.contains("expected a ray count"), "{bad}: {e}");
        }
    }

    #[test]
    fn image_side_gives_about_the_rays_asked_for() {
        let side = size_for(10_000_000, 5.3, 32);
        let rays = f64::from(side * side) * 5.3 * 32.0;
        assert!((rays / 1e7 - 1.0).abs() < 0.01, "{side}: {rays}");
        assert_eq!(size_for(10, 5.3, 32), 8);
    }
}
