//! `rtvtk sql`: SQL over one or more datasets (DataFusion), printed as a table, CSV or JSON, or
//! written to Parquet.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use datafusion::arrow::array::RecordBatch;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Format {
    Table,
    Csv,
    Json,
    Parquet,
}

#[derive(Args, Debug)]
pub struct SqlArgs {
    /// Datasets (`PATH` or `NAME=PATH`; the first one's tables are also unqualified: `rays`,
    /// `trees`, `bvh_nodes`, `lights`, `ray_nodes`), then the query.
    #[arg(required = true, num_args = 2..)]
    items: Vec<String>,
    #[arg(long, value_enum, default_value = "table")]
    format: Format,
    /// Where to write (required for parquet; stdout otherwise).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the plan (logical and physical, with pushed-down filters) instead of running.
    #[arg(long)]
    explain: bool,
}

pub fn run(a: &SqlArgs) -> Result<()> {
    let (query, datasets) = a.items.split_last().context("expected datasets and a query")?;
    let sources: Vec<query::TraceSource> = datasets.iter().map(|d| query::TraceSource::parse(d)).collect();
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the runtime")?;
    rt.block_on(async {
        let ctx = query::session(&sources).await?;
        // Read-only: no DDL, DML or SET from the command line.
        let options = datafusion::execution::context::SQLOptions::new()
            .with_allow_ddl(false)
            .with_allow_dml(false)
            .with_allow_statements(false);
        let text = if a.explain { format!("EXPLAIN {query}") } else { query.clone() };
        let df = ctx.sql_with_options(&text, options).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let batches = df.collect().await.map_err(|e| anyhow::anyhow!("{e}"))?;
        write(&batches, a.format, a.out.as_deref())
    })
}

fn write(batches: &[RecordBatch], format: Format, out: Option<&std::path::Path>) -> Result<()> {
    use std::io::Write;
    let mut sink: Box<dyn Write + Send> = match (format, out) {
        (Format::Parquet, None) => bail!("--format parquet needs --out FILE"),
        (_, Some(p)) => Box::new(std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?),
        (_, None) => Box::new(std::io::stdout()),
    };
    match format {
        Format::Table => {
            writeln!(sink, "{}", datafusion::arrow::util::pretty::pretty_format_batches(batches)?)?;
        }
        Format::Csv => {
            let mut w = datafusion::arrow::csv::Writer::new(sink);
            for b in batches {
                w.write(b)?;
            }
        }
        Format::Json => {
            let mut w = datafusion::arrow::json::LineDelimitedWriter::new(sink);
            for b in batches {
                w.write(b)?;
            }
            w.finish()?;
        }
        Format::Parquet => {
            let schema = batches.first().map(|b| b.schema()).context("the query returned no batches")?;
            let mut w = parquet::arrow::ArrowWriter::try_new(sink, schema, None)?;
            for b in batches {
                w.write(b)?;
            }
            w.close()?;
        }
    }
    Ok(())
}
