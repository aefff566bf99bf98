//! Helpers shared by the command-line integration tests: run `rtvtk`, record a trace, read a
//! query's single value. Each test binary uses some of them.
#![allow(dead_code, clippy::unwrap_used)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs `rtvtk ARGS`.
pub fn rtvtk(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rtvtk")).args(args).output().unwrap()
}

/// Runs `rtvtk ARGS`, asserting success; its stdout.
pub fn ok(args: &[&str]) -> String {
    let out = rtvtk(args);
    assert!(out.status.success(), "rtvtk {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).to_string()
}

/// `rtvtk record ARGS --out DIR`, asserting success.
pub fn record(dir: &Path, args: &[&str]) {
    ok(&[&["record"], args, &["--out", dir.to_str().unwrap()]].concat());
}

/// The single value `rtvtk sql DATASETS QUERY` prints (CSV, header skipped).
pub fn scalar(datasets: &[&str], query: &str) -> String {
    let out = ok(&[&["sql"], datasets, &[query, "--format", "csv"]].concat());
    out.lines().nth(1).unwrap_or_default().trim().to_string()
}
