#![allow(clippy::unwrap_used)]
//! SQL behaviour as `.slt` files (`tests/slt/*.slt`), run by `sqllogictest` — DataFusion's own
//! method — against sessions over small deterministic traces recorded here:
//! - `good` (unqualified too): the Cornell box, 16×12 pixels, 2 samples, one thread, with the
//!   visited-node table;
//! - `bad`: the same with `--inject-bug shadow-dir`;
//! - `plain`: `good` exported with plain columns.
//!
//! To regenerate an expected result after an intended change, run the query with `rtvtk sql`
//! and paste its output.

use arrow::array::{Array, RecordBatch};
use arrow::datatypes::DataType;
use arrow::util::display::{ArrayFormatter, FormatOptions};
use datafusion::error::DataFusionError;
use datafusion::prelude::SessionContext;
use sqllogictest::{DBOutput, DefaultColumnType};

struct Trace {
    ctx: SessionContext,
}

/// A cell as text: NULL, floats rounded to 6 significant digits (no trailing zeros), the rest as
/// Arrow displays it.
fn cell(col: &dyn Array, row: usize) -> Result<String, DataFusionError> {
    if col.is_null(row) {
        return Ok("NULL".into());
    }
    let float = match col.data_type() {
        DataType::Float64 => Some(col.as_any().downcast_ref::<arrow::array::Float64Array>().unwrap().value(row)),
        DataType::Float32 => {
            Some(f64::from(col.as_any().downcast_ref::<arrow::array::Float32Array>().unwrap().value(row)))
        }
        _ => None,
    };
    if let Some(v) = float {
        if !v.is_finite() {
            return Ok(format!("{v}"));
        }
        if v == 0.0 {
            return Ok("0".into());
        }
        let digits = (5 - v.abs().log10().floor() as i32).max(0) as usize;
        let s = format!("{v:.digits$}");
        let s = if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s };
        return Ok(if s == "-0" { "0".into() } else { s });
    }
    let f = ArrayFormatter::try_new(col, &FormatOptions::default())?;
    Ok(f.value(row).to_string())
}

fn column_type(t: &DataType) -> DefaultColumnType {
    match t {
        t if t.is_integer() => DefaultColumnType::Integer,
        t if t.is_floating() => DefaultColumnType::FloatingPoint,
        _ => DefaultColumnType::Text,
    }
}

#[async_trait::async_trait]
impl sqllogictest::AsyncDB for Trace {
    type Error = DataFusionError;
    type ColumnType = DefaultColumnType;

    async fn run(&mut self, sql: &str) -> Result<DBOutput<DefaultColumnType>, DataFusionError> {
        let df = self.ctx.sql(sql).await?;
        let types: Vec<DefaultColumnType> = df.schema().fields().iter().map(|f| column_type(f.data_type())).collect();
        let batches: Vec<RecordBatch> = df.collect().await?;
        if types.is_empty() {
            return Ok(DBOutput::StatementComplete(0));
        }
        let mut rows = Vec::new();
        for b in &batches {
            for r in 0..b.num_rows() {
                rows.push(b.columns().iter().map(|c| cell(c.as_ref(), r)).collect::<Result<Vec<_>, _>>()?);
            }
        }
        Ok(DBOutput::Rows { types, rows })
    }

    async fn shutdown(&mut self) {}

    fn engine_name(&self) -> &str {
        "rtvtk"
    }
}

mod common;

const SETTINGS: [&str; 11] =
    ["--scene", "cornell", "--size", "16x12", "--spp", "2", "--threads", "1", "--seed", "0", "--record-visits"];

#[test]
fn sql_logic_tests() {
    let tmp = tempfile::tempdir().unwrap();
    let (good, bad) = common::record_good_and_bad(tmp.path(), &SETTINGS);
    let plain = tmp.path().join("plain");
    common::ok(&["export", good.to_str().unwrap(), plain.to_str().unwrap()]);
    let sources: Vec<query::TraceSource> = [("good", &good), ("bad", &bad), ("plain", &plain)]
        .iter()
        .map(|(n, p)| query::TraceSource { name: n.to_string(), path: p.to_path_buf() })
        .collect();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    // At run time: a target directory reused from a checkout elsewhere keeps env!'s old path.
    let dir = std::path::PathBuf::from(
        std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_else(|| env!("CARGO_MANIFEST_DIR").into()),
    )
    .join("tests/slt");
    let mut files: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.retain(|p| p.extension().is_some_and(|e| e == "slt"));
    files.sort();
    assert!(files.len() >= 3, "slt files in {}", dir.display());
    let mut failures = Vec::new();
    for file in &files {
        let sources = sources.clone();
        let result = rt.block_on(async {
            let mut runner = sqllogictest::Runner::new(move || {
                let sources = sources.clone();
                async move {
                    Ok(Trace {
                        ctx: query::session(&sources).await.map_err(|e| DataFusionError::External(Box::new(e)))?,
                    })
                }
            });
            runner.run_file_async(file).await
        });
        if let Err(e) = result {
            failures.push(format!("{}:\n{}", file.display(), e.display(true)));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}
