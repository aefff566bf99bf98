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
    /// `trees`, `bvh_nodes`, `lights`, `ray_nodes`), then the query. Without a query (the last
    /// item is a dataset), an interactive prompt with history reads queries ending in `;`.
    #[arg(required = true, num_args = 1..)]
    items: Vec<String>,
    #[arg(long, value_enum, default_value = "table")]
    format: Format,
    /// Where to write (required for parquet; stdout otherwise).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the plan (logical and physical, with pushed-down filters) instead of running.
    #[arg(long)]
    explain: bool,
    /// Memory the query's operators may hold, e.g. `2GiB` or `512MiB` (default: 80% of this
    /// machine's memory; beyond it sorts, joins and group-bys spill to disk).
    #[arg(long, value_parser = parse_bytes)]
    memory_limit: Option<usize>,
    /// Print the query's wall time (seconds, after the session is open) to stderr.
    #[arg(long)]
    timing: bool,
    /// Run every group-by through DataFusion's own aggregation (rtvtk's CountByKey and
    /// SmallGroups operators off), to compare the two.
    #[arg(long)]
    stock_aggregation: bool,
    /// Run on a Ballista cluster (`df://HOST:PORT`, see `rtvtk cluster`): planned here, executed
    /// by its executors, which read the datasets by the same paths.
    #[arg(long, value_name = "df://HOST:PORT")]
    pub cluster: Option<String>,
}

/// `123`, `512KiB`, `64MiB`, `2GiB` (also KB/MB/GB as powers of 1000).
pub fn parse_bytes(s: &str) -> std::result::Result<usize, String> {
    let t = s.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: f64 = num.parse().map_err(|_| format!("{s:?}: expected a size such as 512MiB or 2GiB"))?;
    let mult = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "kib" | "k" => 1024.0,
        "mib" | "m" => 1024.0 * 1024.0,
        "gib" | "g" => 1024.0 * 1024.0 * 1024.0,
        "kb" => 1e3,
        "mb" => 1e6,
        "gb" => 1e9,
        u => return Err(format!("{s:?}: unknown unit {u:?} (expected B, KiB, MiB, GiB, KB, MB or GB)")),
    };
    Ok((n * mult) as usize)
}

/// Whether a command-line item names a dataset (rather than being the query).
pub fn is_dataset(item: &str) -> bool {
    let path = query::TraceSource::parse(item).path;
    path.join(store::MANIFEST_FILE).is_file()
}

pub fn run(a: &SqlArgs) -> Result<()> {
    let (last, rest) = a.items.split_last().context("expected datasets and a query")?;
    let interactive = is_dataset(last);
    let datasets = if interactive { &a.items[..] } else { rest };
    if datasets.is_empty() {
        bail!("no dataset given: expected `rtvtk sql DATASET... \"QUERY\"` ({last:?} is not a dataset directory)");
    }
    let sources: Vec<query::TraceSource> = datasets.iter().map(|d| query::TraceSource::parse(d)).collect();
    let rt = crate::runtime()?;
    rt.block_on(async {
        let options = query::SessionOptions { memory_limit: a.memory_limit, stock_aggregation: a.stock_aggregation };
        let ctx = crate::query_engine(a.cluster.as_deref(), &sources, &options).await?;
        if interactive {
            return prompt(&ctx, a).await;
        }
        let start = std::time::Instant::now();
        let batches = execute(&ctx, last, a).await?;
        if a.timing {
            eprintln!("query seconds: {:.6}", start.elapsed().as_secs_f64());
        }
        write(&batches, a.format, a.out.as_deref())?;
        if a.timing
            && let Some(peak) = peak_rss_bytes()
        {
            eprintln!("peak rss bytes: {peak}");
        }
        Ok(())
    })
}

/// This process's peak resident set (Linux `VmHWM`: of this program image only, unlike
/// `ru_maxrss`, which keeps the spawning parent's peak across `exec`).
pub fn peak_rss_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
    let kb: u64 = line.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kb * 1024)
}

/// The interactive prompt: statements end with `;`; `\d` lists the tables, `\d TABLE` shows
/// one's columns, `\q` quits. History is kept in `$HOME/.rtvtk_history`.
async fn prompt(ctx: &query::Engine, a: &SqlArgs) -> Result<()> {
    use rustyline::error::ReadlineError;
    let mut rl = rustyline::DefaultEditor::new().context("starting the prompt")?;
    let history = std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".rtvtk_history"));
    if let Some(h) = &history {
        let _ = rl.load_history(h);
    }
    eprintln!(
        "rtvtk sql: statements end with ';'. \\d lists tables, \\d TABLE its columns, \\df the ray functions, \\df NAME any function, \\q quits."
    );
    let mut buffer = String::new();
    loop {
        let line = match rl.readline(if buffer.is_empty() { "rtvtk> " } else { "   ... " }) {
            Ok(l) => l,
            Err(ReadlineError::Interrupted) => {
                buffer.clear();
                continue;
            }
            Err(ReadlineError::Eof) => break,
            Err(e) => return Err(e).context("reading the prompt"),
        };
        let trimmed = line.trim();
        if buffer.is_empty() && trimmed.starts_with('\\') {
            let _ = rl.add_history_entry(trimmed);
            let mut words = trimmed.split_whitespace();
            let query = match (words.next(), words.next()) {
                (Some("\\q"), _) => break,
                (Some("\\d"), None) => "SELECT table_schema, table_name FROM information_schema.tables \
                    WHERE table_schema <> 'information_schema' ORDER BY table_schema, table_name"
                    .to_string(),
                (Some("\\d"), Some(t)) => {
                    let (schema, table) = t.split_once('.').unwrap_or(("public", t));
                    format!(
                        "SELECT column_name, data_type, is_nullable FROM information_schema.columns \
                         WHERE table_schema = '{}' AND table_name = '{}' ORDER BY ordinal_position",
                        schema.replace('\'', "''"),
                        table.replace('\'', "''")
                    )
                }
                (Some("\\df"), name) => df_query(name),
                _ => {
                    eprintln!("unknown command {trimmed:?}: \\d, \\d TABLE, \\df, \\df NAME or \\q");
                    continue;
                }
            };
            run_one(ctx, &query, a).await;
            continue;
        }
        if !buffer.is_empty() {
            buffer.push('\n');
        }
        buffer.push_str(&line);
        if trimmed.ends_with(';') {
            let statement = std::mem::take(&mut buffer);
            let _ = rl.add_history_entry(statement.as_str());
            run_one(ctx, statement.trim().trim_end_matches(';'), a).await;
        }
    }
    if let Some(h) = &history {
        let _ = rl.save_history(h);
    }
    Ok(())
}

/// Runs a read-only query (its plan with `--explain`) to completion.
async fn execute(ctx: &query::Engine, query: &str, a: &SqlArgs) -> Result<Vec<RecordBatch>> {
    let text = if a.explain { format!("EXPLAIN {query}") } else { query.to_string() };
    ctx.collect(&text).await.map_err(|e| anyhow::anyhow!("{e}"))
}

/// Runs one statement of the prompt, printing its result or its error (the prompt goes on).
async fn run_one(ctx: &query::Engine, query: &str, a: &SqlArgs) {
    let result = async {
        let batches = execute(ctx, query, a).await?;
        let format = if matches!(a.format, Format::Parquet) { Format::Table } else { a.format };
        write(&batches, format, None)
    };
    if let Err(e) = result.await {
        eprintln!("error: {e:#}");
    }
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
                w.write(&nested_as_text(b)?)?;
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

/// `batch` with its list, struct and map columns as text (`[a, b]`, `{x: 1}`, as the table
/// format prints them): CSV has no nested values, and every format must print every result.
fn nested_as_text(batch: &RecordBatch) -> Result<RecordBatch> {
    use datafusion::arrow::array::{ArrayRef, StringBuilder};
    use datafusion::arrow::datatypes::{DataType, Field, Schema};
    use datafusion::arrow::util::display::{ArrayFormatter, FormatOptions};
    if !batch.schema().fields().iter().any(|f| f.data_type().is_nested()) {
        return Ok(batch.clone());
    }
    let mut fields = Vec::with_capacity(batch.num_columns());
    let mut columns: Vec<ArrayRef> = Vec::with_capacity(batch.num_columns());
    for (f, c) in batch.schema().fields().iter().zip(batch.columns()) {
        if !f.data_type().is_nested() {
            fields.push(f.as_ref().clone());
            columns.push(c.clone());
            continue;
        }
        let fmt = ArrayFormatter::try_new(c.as_ref(), &FormatOptions::default())?;
        let mut text = StringBuilder::with_capacity(c.len(), c.len() * 16);
        for i in 0..c.len() {
            if c.is_null(i) { text.append_null() } else { text.append_value(fmt.value(i).to_string()) }
        }
        fields.push(Field::new(f.name(), DataType::Utf8, true));
        columns.push(std::sync::Arc::new(text.finish()));
    }
    Ok(RecordBatch::try_new(std::sync::Arc::new(Schema::new(fields)), columns)?)
}

/// The query behind `\df` (the ray functions, with their descriptions) and `\df NAME` (any
/// function): DataFusion's `information_schema.routines`, which carries each function's
/// documentation.
fn df_query(name: Option<&str>) -> String {
    let filter = match name {
        Some(n) => format!("routine_name = '{}'", n.replace('\'', "''")),
        None => {
            let names: Vec<String> = query::ray_functions().iter().map(|(name, _)| format!("'{name}'")).collect();
            format!("routine_name IN ({})", names.join(", "))
        }
    };
    format!(
        "SELECT DISTINCT routine_name AS function, function_type, syntax_example, description \
         FROM information_schema.routines WHERE {filter} ORDER BY function"
    )
}
