//! `rtvtk cluster scheduler|executor`: a Ballista scheduler and executors that know rtvtk's
//! tables, operators and ray functions; `--cluster df://HOST:PORT` on `sql`, `analyze` and
//! `bench query` runs their queries there.

use std::net::SocketAddr;

use anyhow::{Context, Result};
use clap::Subcommand;

#[derive(Subcommand, Debug)]
pub enum ClusterCommand {
    /// A scheduler: clients (`--cluster df://HOST:PORT`) send it plans, executors poll it for
    /// tasks. Prints `scheduler listening on HOST:PORT` once it listens.
    Scheduler {
        /// Address to listen on (port 0: a free one, printed).
        #[arg(long, default_value = "127.0.0.1:50050")]
        addr: SocketAddr,
        /// Seconds without a heartbeat before an executor is taken for dead and its tasks run
        /// elsewhere (at least 10: a busy executor reports only every 5 s).
        #[arg(long, default_value_t = 15, value_parser = executor_timeout)]
        executor_timeout: u64,
    },
    /// An executor: runs tasks of the scheduler at `--scheduler` on `--cores` slots and serves
    /// their results and shuffle data over Arrow Flight on `--addr`.
    Executor {
        /// The scheduler, HOST:PORT.
        #[arg(long)]
        scheduler: String,
        /// Task slots (default: every core).
        #[arg(long, default_value_t = 0)]
        cores: usize,
        /// Address of this executor's Flight service (port 0: a free one). Datasets must be
        /// readable here by the same paths as on the client.
        #[arg(long, default_value = "127.0.0.1:0")]
        addr: SocketAddr,
        /// Directory for shuffle files (a temporary one by default).
        #[arg(long)]
        work_dir: Option<String>,
    },
}

/// `--executor-timeout`: whole seconds, at least [`cluster::MIN_EXECUTOR_TIMEOUT_S`].
fn executor_timeout(text: &str) -> Result<u64, String> {
    let given: u64 = text.trim().parse().map_err(|_| format!("{text:?} is not a whole number of seconds"))?;
    cluster::executor_timeout(given).map_err(|e| e.to_string())
}

pub fn run(cmd: &ClusterCommand) -> Result<()> {
    cluster::init_logging();
    let rt = crate::runtime()?;
    match cmd {
        ClusterCommand::Scheduler { addr, executor_timeout } => rt.block_on(async {
            let listener = tokio::net::TcpListener::bind(addr).await.with_context(|| format!("listening on {addr}"))?;
            let local = listener.local_addr()?;
            println!("scheduler listening on {local} (clients: --cluster df://{local})");
            let options = cluster::SchedulerOptions { executor_timeout_s: *executor_timeout };
            cluster::run_scheduler(listener, &options).await.context("the scheduler stopped")
        }),
        ClusterCommand::Executor { scheduler, cores, addr, work_dir } => {
            let (host, port) = cluster::parse_url(&format!("df://{scheduler}"))
                .map_err(|_| anyhow::anyhow!("--scheduler {scheduler:?}: expected HOST:PORT"))?;
            let bind = if addr.port() == 0 {
                // Ballista advertises the port it is given: pick a free one now.
                let l = std::net::TcpListener::bind(addr).with_context(|| format!("binding {addr}"))?;
                l.local_addr()?
            } else {
                *addr
            };
            println!(
                "executor on {bind} with {} slots, scheduler {host}:{port}",
                if *cores == 0 { std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) } else { *cores }
            );
            let options = cluster::ExecutorOptions {
                scheduler_host: host,
                scheduler_port: port,
                bind,
                cores: *cores,
                work_dir: work_dir.clone(),
            };
            rt.block_on(cluster::run_executor(&options)).context("the executor stopped")
        }
    }
}

/// The engine over `sources`: in this process, or planned here and run on the cluster at `url`.
pub async fn engine(
    url: Option<&str>,
    sources: &[query::TraceSource],
    options: &query::SessionOptions,
) -> Result<query::Engine> {
    match url {
        Some(url) => Ok(cluster::connect(url, sources).await?),
        None => Ok(query::Engine::open(sources, options).await?),
    }
}
