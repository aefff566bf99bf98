//! `rtvtk`: the command line of the ray tracing visualization toolkit.

#[cfg(feature = "sql")]
mod analyze;
mod args;
#[cfg(feature = "sql")]
mod bench;
mod check;
#[cfg(feature = "cluster")]
mod cluster;
mod converge;
mod demo;
mod export;
mod info;
mod record;
mod render;
#[cfg(feature = "sql")]
mod serve;
#[cfg(feature = "sql")]
mod sql;
mod tree;
#[cfg(feature = "sql")]
mod view;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "rtvtk", version, about = "Record, store, query and visualize the rays a renderer traces")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene with a CPU tracer or the GPU path tracer, recording every ray into a dataset.
    Record(Box<record::RecordArgs>),
    /// Render and record the Cornell box, then print a summary of the trace.
    Demo(demo::DemoArgs),
    /// Draw a dataset's layers (image, geometry, composition, rays, bvh, query, heatmap) into a
    /// PNG with the GPU visualizer, headless.
    Render(Box<render::RenderArgs>),
    /// Open the interactive viewer on datasets (or on a scene, `--scene cornell`, with no dataset).
    #[cfg(feature = "sql")]
    View(Box<view::ViewArgs>),
    /// Image error (RMSE, relative MSE) of the path tracers against time and samples per pixel,
    /// against a high-sample CPU reference.
    Converge(Box<converge::ConvergeArgs>),
    /// Counts, bytes per ray, kinds, payload schema and format version of a dataset.
    Info(info::InfoArgs),
    /// Print one ray tree as an indented hierarchy.
    Tree(tree::TreeArgs),
    /// Verify every invariant of a dataset (exit status 1 when one is broken).
    Check(check::CheckArgs),
    /// Copy a dataset with plain float origin and direction columns, for tools that read the
    /// Parquet files directly (DuckDB, Polars, pyarrow, Ballista).
    Export(export::ExportArgs),
    /// SQL over datasets: `rtvtk sql TRACE "SELECT kind, count(*) FROM rays GROUP BY kind"`.
    #[cfg(feature = "sql")]
    Sql(sql::SqlArgs),
    /// Canned analyses (coherence, bvh, numerics, diff) as a markdown report with PNG heatmaps.
    #[cfg(feature = "sql")]
    Analyze(analyze::AnalyzeArgs),
    /// The read-only query service: Arrow Flight SQL over datasets (any Flight SQL client: ADBC,
    /// JDBC, arrow-flight), with the same tables and functions as `rtvtk sql`.
    #[cfg(feature = "sql")]
    Serve(serve::ServeArgs),
    /// A Ballista cluster that runs rtvtk's queries: `cluster scheduler`, `cluster executor`.
    #[cfg(feature = "cluster")]
    Cluster {
        #[command(subcommand)]
        what: cluster::ClusterCommand,
    },
    /// Benchmarks, each against a baseline in the same run.
    #[cfg(feature = "sql")]
    Bench {
        #[command(subcommand)]
        what: bench::BenchCommand,
    },
    /// Built without the `sql` feature: the commands that need the SQL engine say so.
    #[cfg(not(feature = "sql"))]
    #[command(external_subcommand)]
    NeedsSql(Vec<String>),
}

/// The commands a build without the `sql` feature leaves out.
#[cfg(not(feature = "sql"))]
const SQL_COMMANDS: [&str; 5] = ["view", "sql", "analyze", "serve", "bench"];

/// The query engine over `sources`: in this process or (with `cluster`, `df://HOST:PORT`) on a
/// cluster.
#[cfg(feature = "sql")]
pub(crate) async fn query_engine(
    cluster: Option<&str>,
    sources: &[query::TraceSource],
    options: &query::SessionOptions,
) -> Result<query::Engine> {
    #[cfg(feature = "cluster")]
    return cluster::engine(cluster, sources, options).await;
    #[cfg(not(feature = "cluster"))]
    match cluster {
        Some(_) => anyhow::bail!("--cluster: this rtvtk was built without the `cluster` feature"),
        None => Ok(query::Engine::open(sources, options).await?),
    }
}

/// The Tokio runtime the query commands run on.
#[cfg(feature = "sql")]
pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    use anyhow::Context as _;
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the runtime")
}

/// Recording frees and allocates column buffers of a few MB per chunk on the writer threads, and
/// glibc's defaults give such blocks back to the kernel (heap trimming, one mmap each) only to
/// fault fresh zeroed pages in again: ~8% of a writer's time in `clear_page`. Keeping freed
/// memory (no trimming, blocks up to 32 MB from the heap) cuts the page faults of a recording by a
/// quarter. (One arena for all threads halved them on 2 cores, but on 16 cores the writers then
/// queued on its lock: recording overhead 1.3x → 2.9x. Not set.) A 64 MB top pad keeps a writer
/// thread's arena from unmapping a whole heap it emptied (glibc deletes such heaps whatever the
/// trim threshold): writer time in `clear_page` 12% → 7% in `bench store`. Only the recording
/// commands set this: the query commands' memory would stay at its peak.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator settings; called at start-up, before any thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}

fn main() {
    // Rust ignores SIGPIPE, so printing into a closed pipe (`rtvtk tree ... | head`) would panic;
    // restore the default: the process ends quietly, like any Unix tool.
    let cli = Cli::parse();
    // The GPU tracer as `renderers::tracer`'s GPU choice (the one factory of every tracer).
    gpu_tracer::register();
    // Except for the commands that talk over sockets (the service, its clients): a peer closing
    // its end under a write must be an error (EPIPE), not the end of the process.
    #[cfg(feature = "sql")]
    let sockets = matches!(
        cli.command,
        Command::Serve(_) | Command::View(_) | Command::Bench { what: bench::BenchCommand::Serve { .. } }
    );
    #[cfg(not(feature = "sql"))]
    let sockets = false;
    #[cfg(unix)]
    if !sockets {
        // SAFETY: setting a signal disposition to its default at start-up, before any thread exists.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    #[cfg(feature = "sql")]
    let bench_store = matches!(cli.command, Command::Bench { what: bench::BenchCommand::Store { .. } });
    #[cfg(not(feature = "sql"))]
    let bench_store = false;
    if bench_store || matches!(cli.command, Command::Demo(_) | Command::Record(_)) {
        keep_freed_memory();
    }
    let result: Result<i32> = match cli.command {
        Command::Demo(args) => args.run().map(|_| 0),
        Command::Converge(args) => args.run().map(|_| 0),
        Command::Record(args) => record::run(&args).map(|_| 0),
        Command::Render(args) => render::run(&args).map(|_| 0),
        #[cfg(feature = "sql")]
        Command::View(args) => view::run(&args).map(|_| 0),
        Command::Info(args) => args.run().map(|_| 0),
        Command::Tree(args) => args.run().map(|_| 0),
        Command::Check(args) => args.run(),
        Command::Export(args) => args.run().map(|_| 0),
        #[cfg(feature = "sql")]
        Command::Sql(args) => sql::run(&args).map(|_| 0),
        #[cfg(feature = "sql")]
        Command::Analyze(args) => analyze::run(&args).map(|_| 0),
        #[cfg(feature = "sql")]
        Command::Serve(args) => serve::run(&args).map(|_| 0),
        #[cfg(feature = "cluster")]
        Command::Cluster { what } => cluster::run(&what).map(|_| 0),
        #[cfg(feature = "sql")]
        Command::Bench { what } => bench::run(what).map(|_| 0),
        #[cfg(not(feature = "sql"))]
        Command::NeedsSql(args) => {
            let name = args.first().map_or("", String::as_str);
            if SQL_COMMANDS.contains(&name) {
                Err(anyhow::anyhow!(
                    "`rtvtk {name}` needs the SQL engine, and this rtvtk was built without it \
                     (`--no-default-features`): run it from a default build, `cargo run -- {name} ...`"
                ))
            } else {
                Err(anyhow::anyhow!("unknown command `{name}`: see `rtvtk --help`"))
            }
        }
    };
    match result {
        Ok(code) => std::process::exit(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(2);
        }
    }
}
