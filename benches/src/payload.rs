//! `rtvtk bench payload`: the bytes of path-tracer traces with their payload (throughput,
//! radiance, material, traversal counts) against pyarrow's default zstd Parquet of the same ray
//! table, as issue 45 measures them: the dataset lossless, with the lossy payload option
//! (`--payload-bits`), and with lossy payload and `oct16` directions. Each recording is a
//! `rtvtk record` process; the plain copy comes from `rtvtk export`; pyarrow (`python3`) writes
//! the baseline with its defaults and `compression="zstd"`.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

use crate::dir_bytes_where;

/// What to record: each scene (`cornell`, `cornell-glass`, `glossy` or an OBJ file) at `size`
/// (`WxH`) and `spp`, and the mantissa bits of each lossy payload variant.
pub struct PayloadArgs {
    pub scenes: Vec<String>,
    pub size: String,
    pub spp: u32,
    pub bits: Vec<u8>,
}

/// Runs `rtvtk ARGS` (failing with its stderr's tail when it fails).
fn rtvtk(exe: &Path, args: &[&str]) -> Result<()> {
    let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    crate::scale::measured(exe, &args).map(|_| ())
}

/// pyarrow's default zstd Parquet of the plain copy's ray files: (rays, bytes).
fn pyarrow_baseline(plain: &Path, out: &Path) -> Result<(u64, u64)> {
    let script = "import sys, glob, os, pyarrow as pa, pyarrow.parquet as pq\n\
        files = sorted(glob.glob(os.path.join(sys.argv[1], 'segments', '*.rays.parquet')))\n\
        t = pa.concat_tables([pq.read_table(f) for f in files])\n\
        pq.write_table(t, sys.argv[2], compression='zstd')\n\
        print(t.num_rows, os.path.getsize(sys.argv[2]))\n";
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(plain)
        .arg(out)
        .output()
        .context("running python3 for the pyarrow baseline")?;
    if !o.status.success() {
        let err = String::from_utf8_lossy(&o.stderr);
        bail!(
            "the pyarrow baseline needs python3 with pyarrow (`python3 -m pip install pyarrow`): {}",
            err.lines().last().unwrap_or("").trim()
        );
    }
    let s = String::from_utf8_lossy(&o.stdout);
    let mut it = s.split_whitespace().map(|v| v.parse::<u64>());
    match (it.next(), it.next()) {
        (Some(Ok(rows)), Some(Ok(bytes))) if rows > 0 => Ok((rows, bytes)),
        _ => bail!("unexpected answer from the pyarrow baseline: {s:?}"),
    }
}

pub fn run(a: &PayloadArgs) -> Result<()> {
    if a.scenes.is_empty() {
        bail!("bench payload needs at least one scene");
    }
    if let Some(b) = a.bits.iter().find(|b| !(1..=22).contains(*b)) {
        bail!("--bits {b}: expected mantissa bits from 1 to 22");
    }
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    println!(
        "## rtvtk bench payload: path tracer with its payload, {} at {} spp; bytes against pyarrow's default zstd Parquet of the same ray table\n",
        a.size, a.spp
    );
    println!(
        "| scene | rays | dataset | B/ray (ray files) | vs pyarrow (ray files) | vs pyarrow (whole dataset, no images) |"
    );
    println!("|---|---|---|---|---|---|");
    for (k, scene) in a.scenes.iter().enumerate() {
        let spp = a.spp.to_string();
        let base = ["record", "--scene", scene.as_str(), "--size", a.size.as_str(), "--spp", spp.as_str(), "--quiet"];
        let mut variants: Vec<(String, Vec<String>)> = vec![("lossless".into(), Vec::new())];
        for b in &a.bits {
            variants.push((format!("payload {b} bits"), vec!["--payload-bits".into(), b.to_string()]));
        }
        if let Some(b) = a.bits.first() {
            variants.push((
                format!("payload {b} bits, oct16"),
                vec!["--payload-bits".into(), b.to_string(), "--encoding".into(), "oct16".into()],
            ));
        }
        let dirs: Vec<PathBuf> = (0..variants.len()).map(|v| tmp.path().join(format!("s{k}-v{v}"))).collect();
        for ((_, extra), dir) in variants.iter().zip(&dirs) {
            let mut args: Vec<&str> = base.to_vec();
            args.extend(extra.iter().map(String::as_str));
            let d = dir.to_string_lossy().to_string();
            args.extend(["--out", d.as_str()]);
            rtvtk(&exe, &args)?;
        }
        let plain = tmp.path().join(format!("s{k}-plain"));
        rtvtk(&exe, &["export", &dirs[0].to_string_lossy(), &plain.to_string_lossy()])?;
        let (rays, baseline) = pyarrow_baseline(&plain, &tmp.path().join(format!("s{k}-pyarrow.parquet")))?;
        println!(
            "| {scene} | {rays} | pyarrow default zstd (baseline) | {:.2} | 1.000x | — |",
            baseline as f64 / rays as f64
        );
        for ((name, _), dir) in variants.iter().zip(&dirs) {
            let ray_files = dir_bytes_where(dir, &|n| n.ends_with(".rays.parquet"));
            let whole = dir_bytes_where(dir, &|n| !(n.ends_with(".png") || n.ends_with(".exr")));
            println!(
                "| {scene} | {rays} | {name} | {:.2} | {:.3}x | {:.3}x |",
                ray_files as f64 / rays as f64,
                ray_files as f64 / baseline as f64,
                whole as f64 / baseline as f64
            );
        }
        // The plain copy's rays are the lossless recording's: the baseline and every variant hold
        // the same rays only if each recording traced the same trees.
        for dir in &dirs[1..] {
            let m = store::Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
            if m.ray_count() != rays {
                bail!("{}: {} rays, the lossless recording {rays}", dir.display(), m.ray_count());
            }
        }
    }
    println!(
        "\nLossy payload: float payload values rounded to N mantissa bits (relative error at most 2^-(N+1)); oct16: directions quantized to 16 bits per octahedral coordinate."
    );
    Ok(())
}
