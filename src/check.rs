//! `rtvtk check`: verify every invariant of a dataset.

use std::path::Path;

use anyhow::Result;
use rl::Dataset;
use serde_json::json;

pub fn run(dir: &Path, as_json: bool) -> Result<i32> {
    let ds = Dataset::open(dir)?;
    let r = ds.check();
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
            "{}: {} segments, {} trees, {} rays checked; {} errors, {} warnings",
            if r.is_ok() { "ok" } else { "FAILED" },
            r.segments,
            r.trees,
            r.rays,
            r.errors.len(),
            r.warnings.len()
        );
    }
    Ok(if r.is_ok() { 0 } else { 1 })
}
