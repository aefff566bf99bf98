//! `rtvtk check`: verify every invariant of a dataset.

use std::path::Path;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use rl::Dataset;
use serde_json::json;

/// `rtvtk check`: every invariant of a dataset (exit status 1 when one is broken).
#[derive(clap::Args)]
pub struct CheckArgs {
    pub dataset: std::path::PathBuf,
    #[arg(long)]
    pub json: bool,
}

impl CheckArgs {
    pub fn run(&self) -> Result<i32> {
        run(&self.dataset, self.json)
    }
}

pub fn run(dir: &Path, as_json: bool) -> Result<i32> {
    let ds = Dataset::open(dir)?;
    // A bar in rays (stderr, hidden when it is not a terminal); segments are checked in parallel.
    let bar = ProgressBar::new(ds.ray_count());
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} checking [{bar:40}] {human_pos}/{human_len} rays {elapsed_precise} eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let t0 = std::time::Instant::now();
    let r = ds.check_with(&|rays| bar.inc(rays));
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    if as_json {
        println!("{}", serde_json::to_string_pretty(&json!({"ok": r.is_ok(), "report": r}))?);
    } else {
        for e in &r.errors {
            println!("error: {e}");
        }
        for w in &r.warnings {
            println!("warning: {w}");
        }
        println!(
            "{}: {} segments, {} trees, {} rays checked in {secs:.2} s ({:.1} Mrays/s); {} errors, {} warnings",
            if r.is_ok() { "ok" } else { "FAILED" },
            r.segments,
            r.trees,
            r.rays,
            r.rays as f64 / secs.max(1e-9) / 1e6,
            r.errors.len(),
            r.warnings.len()
        );
    }
    Ok(if r.is_ok() { 0 } else { 1 })
}
