//! `rtvtk export`: a copy of a dataset with plain float columns.

use std::path::Path;

use anyhow::{Context, Result};
use rl::Dataset;

/// `rtvtk export`: a copy of a dataset with plain float columns.
#[derive(clap::Args)]
pub struct ExportArgs {
    pub dataset: std::path::PathBuf,
    /// Where to write the plain copy (must not exist or be empty).
    pub out: std::path::PathBuf,
}

impl ExportArgs {
    pub fn run(&self) -> Result<()> {
        run(&self.dataset, &self.out)
    }
}

/// `rtvtk export`: a plain copy of a dataset.
pub fn run(dataset: &Path, out: &Path) -> Result<()> {
    let ds = Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    let m = store::export_plain(&ds, out).with_context(|| format!("exporting to {}", out.display()))?;
    let bytes: u64 = m.segments.iter().map(|s| s.rays.bytes + s.trees.bytes).sum();
    println!(
        "exported {} rays in {} segments ({} encoding -> plain), {} bytes: {}",
        m.stats.rays,
        m.segments.len(),
        ds.encoding().name(),
        bytes,
        out.display()
    );
    Ok(())
}
