//! rtvtk on a Ballista cluster: a scheduler and executors that know the trace tables, the ray
//! functions and aggregates and rtvtk's scan operators (through [`query::codec::TraceCodec`]
//! layered over Ballista's own codecs), and a client session that plans locally and runs there.
//!
//! Datasets are plain directories every node reads by the same path (a shared file system);
//! the `rays` scan has one partition per segment left after pruning, planned as a file scan of
//! one file group per segment ([`query::SliceableScans`]) so that Ballista hands each task only
//! its own segments; the scan stage spreads over the executors' task slots and only aggregated
//! rows are shuffled.

mod dictionaries;
mod subqueries;

use std::net::SocketAddr;
use std::sync::Arc;

use ballista::prelude::{SessionConfigExt, SessionContextExt};
use ballista_core::config::TaskSchedulingPolicy;
use ballista_core::error::BallistaError;
use ballista_core::serde::{BallistaLogicalExtensionCodec, BallistaPhysicalExtensionCodec};
use datafusion::execution::SessionState;
use datafusion::execution::runtime_env::RuntimeEnvBuilder;
use datafusion::execution::session_state::SessionStateBuilder;
use datafusion::physical_optimizer::optimizer::PhysicalOptimizer;
use datafusion::prelude::{SessionConfig, SessionContext};
use datafusion_proto::logical_plan::LogicalExtensionCodec;
use datafusion_proto::physical_plan::PhysicalExtensionCodec;
use query::TraceSource;
use query::codec::TraceCodec;

/// What can go wrong starting or using a cluster.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Query(#[from] query::Error),
    #[error(transparent)]
    DataFusion(#[from] datafusion::error::DataFusionError),
    #[error(transparent)]
    Ballista(#[from] BallistaError),
    #[error("cluster address `{url}`: {message} (expected df://HOST:PORT)")]
    Url { url: String, message: String },
    #[error("cannot reach the scheduler at {addr} (is `rtvtk cluster scheduler` running there?)")]
    Unreachable { addr: String, source: std::io::Error },
    #[error(
        "executor timeout {given} s is too short: a busy executor reports only every 5 s, so it must be at least {MIN_EXECUTOR_TIMEOUT_S} s"
    )]
    ExecutorTimeout { given: u64 },
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What the scheduler does to a stage's plan before it ships a task: cut the leaves down to the
/// task's partitions (Ballista's own function, re-exported so that tests and tools can check
/// that a task of a scan stage reads only its own segments).
pub use ballista_scheduler::state::task_builder::restrict_plan_to_partitions;

/// The logical codec every node and client uses: rtvtk's tables and functions, then Ballista's.
pub fn logical_codec() -> Arc<dyn LogicalExtensionCodec> {
    Arc::new(TraceCodec::with_fallback(
        Arc::new(BallistaLogicalExtensionCodec::default()),
        Arc::new(BallistaPhysicalExtensionCodec::default()),
    ))
}

/// The physical codec every node and client uses: the cluster's own operator
/// ([`dictionaries::CastBackExec`]), rtvtk's operators and functions, then Ballista's.
pub fn physical_codec() -> Arc<dyn PhysicalExtensionCodec> {
    Arc::new(dictionaries::ClusterCodec {
        inner: Arc::new(TraceCodec::with_fallback(
            Arc::new(BallistaLogicalExtensionCodec::default()),
            Arc::new(BallistaPhysicalExtensionCodec::default()),
        )),
    })
}

/// The scheduler's sessions: DataFusion's and Ballista's rules, and rtvtk's `SmallGroups` (the
/// partial half of small-domain group-bys, one task per scan partition, so it spreads over the
/// executors like the stock operator) and `SliceableScans` (each task of a scan stage reads
/// only its own segments). `CountByKey` is left out: it gathers every partition into
/// one task, which would put a whole scan on one executor; the stock two-phase aggregation
/// shuffles its partial counts instead.
fn scheduler_session(config: SessionConfig) -> datafusion::common::Result<SessionState> {
    let mut rules = PhysicalOptimizer::new().rules;
    rules.push(Arc::new(query::SmallGroups));
    rules.push(Arc::new(dictionaries::PlainAcrossStages));
    // Last: the segment scans as file scans, which Ballista cuts down to each task's segments.
    rules.push(Arc::new(query::SliceableScans));
    Ok(SessionStateBuilder::new()
        .with_default_features()
        .with_config(config)
        .with_runtime_env(Arc::new(RuntimeEnvBuilder::new().build()?))
        .with_optimizer_rules(ballista_core::optimizer::ballista_default_optimizer_rules())
        .with_physical_optimizer_rules(rules)
        .build())
}

/// The shortest executor timeout a scheduler accepts. Under pull scheduling an executor's poll
/// for work is its heartbeat, and an executor whose every task slot is taken polls only every
/// 5 s (Ballista's `HEARTBEAT_POLL_INTERVAL`). A shorter timeout takes a busy executor for dead
/// while it works, and resets its stages again and again: a CI run's query, with one of two
/// executors killed and a 4 s timeout, retried its join stage 18 times in 240 s and never ended.
pub const MIN_EXECUTOR_TIMEOUT_S: u64 = 10;

/// `seconds` when it is a timeout a scheduler accepts (at least [`MIN_EXECUTOR_TIMEOUT_S`]).
pub fn executor_timeout(seconds: u64) -> Result<u64> {
    if seconds < MIN_EXECUTOR_TIMEOUT_S {
        return Err(Error::ExecutorTimeout { given: seconds });
    }
    Ok(seconds)
}

/// Settings of a scheduler.
#[derive(Clone, Debug)]
pub struct SchedulerOptions {
    /// Seconds without a heartbeat after which an executor is taken for dead (its tasks run again
    /// elsewhere); at least [`MIN_EXECUTOR_TIMEOUT_S`].
    pub executor_timeout_s: u64,
}

impl Default for SchedulerOptions {
    fn default() -> Self {
        Self { executor_timeout_s: 15 }
    }
}

/// Runs a scheduler on `listener` until the process ends.
pub async fn run_scheduler(listener: tokio::net::TcpListener, options: &SchedulerOptions) -> Result<()> {
    use ballista_scheduler::cluster::BallistaCluster;
    use ballista_scheduler::config::SchedulerConfig;
    use datafusion_proto::protobuf::{LogicalPlanNode, PhysicalPlanNode};
    let executor_timeout_s = executor_timeout(options.executor_timeout_s)?;
    let addr = listener.local_addr().map_err(BallistaError::from)?;
    let config = SchedulerConfig {
        bind_host: addr.ip().to_string(),
        bind_port: addr.port(),
        external_host: addr.ip().to_string(),
        executor_timeout_seconds: executor_timeout_s,
        expire_dead_executor_interval_seconds: 1,
        no_executors_grace_period_seconds: executor_timeout_s,
        override_logical_codec: Some(logical_codec()),
        override_physical_codec: Some(physical_codec()),
        override_session_builder: Some(Arc::new(scheduler_session)),
        // Executors ask for work (Spark's way): the scheduler never dials an executor, so one
        // that registers while a job waits cannot be dropped for a failed push.
        scheduling_policy: TaskSchedulingPolicy::PullStaged,
        ..SchedulerConfig::default()
    };
    config.validate()?;
    let cluster = BallistaCluster::new_from_config(&config).await?;
    let scheduler = ballista_scheduler::scheduler_process::create_scheduler::<LogicalPlanNode, PhysicalPlanNode>(
        cluster,
        Arc::new(config),
    )
    .await?;
    ballista_scheduler::scheduler_process::start_grpc_service_with_listener(listener, scheduler).await?;
    Ok(())
}

/// Settings of an executor.
#[derive(Clone, Debug)]
pub struct ExecutorOptions {
    pub scheduler_host: String,
    pub scheduler_port: u16,
    /// Address the executor's Arrow Flight service (results and shuffle data) listens on.
    pub bind: SocketAddr,
    /// Task slots (0: every core).
    pub cores: usize,
    /// Where shuffle files go (a temporary directory when None).
    pub work_dir: Option<String>,
}

/// Runs an executor until it is stopped (SIGTERM, Ctrl-C or the scheduler).
pub async fn run_executor(options: &ExecutorOptions) -> Result<()> {
    use ballista_executor::executor_process::{ExecutorProcessConfig, start_executor_process};
    // Ballista advertises the ports it is given, so a 0 (any free port) is settled here: the
    // Flight port (results, shuffle data) and the gRPC port the scheduler pushes tasks to.
    let free_port = |port: u16| -> Result<u16> {
        if port != 0 {
            return Ok(port);
        }
        let probe = std::net::TcpListener::bind((options.bind.ip(), 0)).map_err(BallistaError::from)?;
        Ok(probe.local_addr().map_err(BallistaError::from)?.port())
    };
    let port = free_port(options.bind.port())?;
    let grpc_port = free_port(0)?;
    // Ballista's own default work directory is deleted as soon as it is made; keep one for the
    // executor's lifetime.
    let temp = match &options.work_dir {
        Some(_) => None,
        None => Some(tempfile::Builder::new().prefix("rtvtk-executor-").tempdir().map_err(BallistaError::from)?),
    };
    let work_dir = match (&options.work_dir, &temp) {
        (Some(dir), _) => Some(dir.clone()),
        (None, Some(t)) => Some(t.path().to_string_lossy().into_owned()),
        (None, None) => None,
    };
    let config = ExecutorProcessConfig {
        bind_host: options.bind.ip().to_string(),
        external_host: Some(options.bind.ip().to_string()),
        port,
        grpc_port,
        scheduler_host: options.scheduler_host.clone(),
        scheduler_port: options.scheduler_port,
        scheduler_connect_timeout_seconds: 10,
        vcores: options.cores,
        work_dir,
        executor_heartbeat_interval_seconds: 2,
        task_scheduling_policy: TaskSchedulingPolicy::PullStaged,
        job_data_clean_up_interval_seconds: 300,
        job_data_ttl_seconds: 3600,
        // Every built-in function of DataFusion's default session (Ballista's default registry
        // lacks the nested ones, `cardinality` among them); rtvtk's travel with the plan.
        override_function_registry: Some(Arc::new(ballista_core::registry::BallistaFunctionRegistry::from(
            &SessionStateBuilder::new().with_default_features().build(),
        ))),
        override_logical_codec: Some(logical_codec()),
        override_physical_codec: Some(physical_codec()),
        ..ExecutorProcessConfig::default()
    };
    start_executor_process(Arc::new(config)).await?;
    drop(temp);
    Ok(())
}

/// Ballista's log lines on stderr, at the level `RUST_LOG` names (`error`, `warn`, `info`,
/// `debug`, `trace`; `warn` by default), so a scheduler or executor says why a task failed.
pub fn init_logging() {
    struct Stderr;
    impl log::Log for Stderr {
        fn enabled(&self, m: &log::Metadata) -> bool {
            m.level() <= log::max_level()
        }
        fn log(&self, r: &log::Record) {
            if self.enabled(r.metadata()) {
                eprintln!("[{} {}] {}", r.level(), r.target(), r.args());
            }
        }
        fn flush(&self) {}
    }
    static LOGGER: Stderr = Stderr;
    let level = std::env::var("RUST_LOG")
        .ok()
        .and_then(|v| v.trim().parse::<log::LevelFilter>().ok())
        .unwrap_or(log::LevelFilter::Warn);
    if log::set_logger(&LOGGER).is_ok() {
        log::set_max_level(level);
    }
}

/// `df://HOST:PORT` as (host, port).
pub fn parse_url(url: &str) -> Result<(String, u16)> {
    let err = |message: &str| Error::Url { url: url.to_string(), message: message.to_string() };
    let rest = url.strip_prefix("df://").ok_or_else(|| err("not a df:// address"))?;
    let rest = rest.trim_end_matches('/');
    let (host, port) = rest.rsplit_once(':').ok_or_else(|| err("no port"))?;
    let port: u16 = port.parse().map_err(|_| err("the port is not a number in 1..=65535"))?;
    if host.is_empty() || port == 0 {
        return Err(err("no host or port 0"));
    }
    Ok((host.trim_start_matches('[').trim_end_matches(']').to_string(), port))
}

/// An engine whose queries are planned here and run on the cluster at `url` (`df://HOST:PORT`),
/// over the tables of `sources` (each a directory every executor can read by the same path,
/// opened here once for planning).
pub async fn connect(url: &str, sources: &[TraceSource]) -> Result<query::Engine> {
    let (host, port) = parse_url(url)?;
    // Ballista connects on the first query; say now when nobody listens there.
    let addr = format!("{host}:{port}");
    tokio::net::TcpStream::connect(&addr).await.map_err(|source| Error::Unreachable { addr, source })?;
    // Ballista's defaults for distributed plans first (scalar subqueries as joins, no dynamic
    // filters across stages, ...): setting a codec marks a config as already upgraded.
    let config = query::session_config()
        .upgrade_for_ballista()
        // The static stage planner: it plans with the scheduler session's physical rules (rtvtk's
        // `SmallGroups` and `PlainAcrossStages`); the adaptive one swaps in its own rule list.
        .with_ballista_adaptive_query_planner(false)
        .with_ballista_logical_extension_codec(logical_codec())
        .with_ballista_physical_extension_codec(physical_codec());
    let state = SessionStateBuilder::new().with_config(config).with_default_features().build();
    let ctx = SessionContext::remote_with_state(url, state).await?;
    // Ballista's planner, behind one that runs the scalar subqueries it cannot stage first.
    let inner = ctx.state().query_planner().clone();
    let state = SessionStateBuilder::new_from_existing(ctx.state())
        .with_query_planner(Arc::new(subqueries::SubqueriesFirst { inner }))
        .build();
    let ctx = SessionContext::new_with_state(state);
    // After the upgrade to Ballista (which resets the function list): tables and ray functions.
    let sources: Vec<TraceSource> = sources
        .iter()
        .map(|s| TraceSource { name: s.name.clone(), path: std::path::absolute(&s.path).unwrap_or(s.path.clone()) })
        .collect();
    let datasets = query::open_sources(&sources)?;
    query::register_datasets(&ctx, &datasets).await?;
    Ok(query::Engine::from_session(ctx, datasets)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_checked() {
        assert_eq!(parse_url("df://localhost:50050").unwrap(), ("localhost".into(), 50050));
        assert_eq!(parse_url("df://127.0.0.1:7/").unwrap(), ("127.0.0.1".into(), 7));
        for bad in ["localhost:50050", "df://localhost", "df://:1", "df://h:0", "df://h:x", "df://h:70000"] {
            let e = parse_url(bad).unwrap_err().to_string();
            assert!(e.contains(bad) && e.contains("df://HOST:PORT"), "{bad}: {e}");
        }
    }
}
