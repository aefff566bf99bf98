//! The `.slt` runner shared by `tests/slt.rs` (in-process sessions) and `tests/cluster.rs` (a
//! Ballista cluster): the same files, the same expected answers.
#![allow(dead_code)]

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use arrow::array::{Array, RecordBatch};
use arrow::datatypes::DataType;
use arrow::util::display::{ArrayFormatter, FormatOptions};
use datafusion::error::DataFusionError;
use datafusion::prelude::SessionContext;
use sqllogictest::DBOutput;

pub struct Trace {
    pub ctx: SessionContext,
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

/// A result column's type letter in the `.slt` files: `I`, `R`, `B` (boolean), `T`, or `?`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ColType {
    Integer,
    Float,
    Bool,
    Text,
    Any,
}

impl sqllogictest::ColumnType for ColType {
    fn from_char(value: char) -> Option<Self> {
        Some(match value {
            'I' => Self::Integer,
            'R' => Self::Float,
            'B' => Self::Bool,
            'T' => Self::Text,
            _ => Self::Any,
        })
    }

    fn to_char(&self) -> char {
        match self {
            Self::Integer => 'I',
            Self::Float => 'R',
            Self::Bool => 'B',
            Self::Text => 'T',
            Self::Any => '?',
        }
    }
}

fn column_type(t: &DataType) -> ColType {
    match t {
        t if t.is_integer() => ColType::Integer,
        t if t.is_floating() => ColType::Float,
        DataType::Boolean => ColType::Bool,
        _ => ColType::Text,
    }
}

#[async_trait::async_trait]
impl sqllogictest::AsyncDB for Trace {
    type Error = DataFusionError;
    type ColumnType = ColType;

    async fn run(&mut self, sql: &str) -> Result<DBOutput<ColType>, DataFusionError> {
        let df = self.ctx.sql(sql).await?;
        let types: Vec<ColType> = df.schema().fields().iter().map(|f| column_type(f.data_type())).collect();
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

/// Makes the session each `.slt` file runs against.
pub type Factory =
    Arc<dyn Fn() -> Pin<Box<dyn Future<Output = Result<SessionContext, DataFusionError>> + Send>> + Send + Sync>;

/// The `.slt` files of `tests/slt`, sorted.
pub fn files() -> Vec<std::path::PathBuf> {
    // At run time: a target directory reused from a checkout elsewhere keeps env!'s old path.
    let dir = std::path::PathBuf::from(
        std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_else(|| env!("CARGO_MANIFEST_DIR").into()),
    )
    .join("tests/slt");
    let mut files: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.retain(|p| p.extension().is_some_and(|e| e == "slt"));
    files.sort();
    assert!(files.len() >= 3, "slt files in {}", dir.display());
    files
}

/// Runs every `.slt` file against sessions from `factory`; the failures, one text per file. With
/// `complete`, first rewrites each file's expected results with what the sessions answer (the
/// runner's completion mode: `RTVTK_SLT_COMPLETE=1 cargo nextest run --test slt`); review the diff
/// before committing it.
pub fn run_all(rt: &tokio::runtime::Runtime, factory: Factory, complete: bool) -> Vec<String> {
    let mut failures = Vec::new();
    for file in &files() {
        let factory = factory.clone();
        let result = rt.block_on(async {
            let mut runner = sqllogictest::Runner::new(move || {
                let f = factory.clone();
                async move { Ok(Trace { ctx: f().await? }) }
            });
            if complete {
                runner
                    .update_test_file(
                        file,
                        " ",
                        sqllogictest::default_validator,
                        sqllogictest::default_normalizer,
                        sqllogictest::default_column_validator,
                    )
                    .await
                    .map_err(|e| e.to_string())?;
            }
            runner.run_file_async(file).await.map_err(|e| e.display(true).to_string())
        });
        if let Err(e) = result {
            failures.push(format!("{}:\n{e}", file.display()));
        }
    }
    failures
}

/// The traces the `.slt` files query, recorded under `dir`: `good`, `bad` (the shadow-direction
/// bug) and `plain` (`good` exported with plain columns).
pub fn sources(dir: &std::path::Path) -> Vec<query::TraceSource> {
    const SETTINGS: [&str; 11] =
        ["--scene", "cornell", "--size", "16x12", "--spp", "2", "--threads", "1", "--seed", "0", "--record-visits"];
    let (good, bad) = crate::common::record_good_and_bad(dir, &SETTINGS);
    let plain = dir.join("plain");
    crate::common::ok(&["export", good.to_str().unwrap(), plain.to_str().unwrap()]);
    [("good", &good), ("bad", &bad), ("plain", &plain)]
        .iter()
        .map(|(n, p)| query::TraceSource { name: n.to_string(), path: p.to_path_buf() })
        .collect()
}
