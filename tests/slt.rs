#![allow(clippy::unwrap_used)]
//! SQL behaviour as `.slt` files (`tests/slt/*.slt`), run by `sqllogictest` — DataFusion's own
//! method — against sessions over small deterministic traces recorded here:
//! - `good` (unqualified too): the Cornell box, 16×12 pixels, 2 samples, one thread, with the
//!   visited-node table;
//! - `bad`: the same with `--inject-bug shadow-dir`;
//! - `plain`: `good` exported with plain columns.
//!
//! To regenerate the expected results after an intended change, run this test with
//! `RTVTK_SLT_COMPLETE=1` (sqllogictest's completion mode rewrites every file with the answers
//! it gets) and review the diff. `tests/cluster.rs` runs the same files against a Ballista cluster.

use std::sync::Arc;

use datafusion::error::DataFusionError;

mod common;
mod slt_db;

#[test]
fn sql_logic_tests() {
    let tmp = tempfile::tempdir().unwrap();
    let sources = slt_db::sources(tmp.path());
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let factory: slt_db::Factory = Arc::new(move || {
        let sources = sources.clone();
        Box::pin(async move { query::session(&sources).await.map_err(|e| DataFusionError::External(Box::new(e))) })
    });
    let complete = std::env::var_os("RTVTK_SLT_COMPLETE").is_some();
    let failures = slt_db::run_all(&rt, factory, complete);
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}
