//! The one way a process reaches SQL over traces: an [`Engine`] answers `stream(sql)` and
//! `catalog()` from a session in this process, a Ballista session planned here and run on a
//! cluster, or an `rtvtk serve` service through Flight SQL. The CLI, the viewer's console, plots
//! and layers, `serve` and `cluster` all ask one; each dataset is opened once per process (the
//! engine keeps the `Arc<Dataset>` it registered, for the readers that go straight to the store).

use std::future::Future;
use std::sync::Arc;

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use arrow_flight::sql::client::FlightSqlServiceClient;
use datafusion::execution::SendableRecordBatchStream;
use datafusion::physical_plan::stream::RecordBatchStreamAdapter;
use datafusion::prelude::SessionContext;
use futures::{StreamExt, TryStreamExt};
use store::Dataset;
use tokio::runtime::Handle;
use tonic::transport::Channel;

use crate::tables::{Registered, SessionOptions, TraceSource, open_sources, register_datasets, session_state};
use crate::{Error, Result};

/// Tables (schema-qualified outside `public`) and functions an engine answers for.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Catalog {
    pub tables: Vec<String>,
    pub functions: Vec<String>,
}

enum Backend {
    /// In this process, or planned here and run on a Ballista cluster.
    Session(SessionContext),
    /// An `rtvtk serve` service (Flight SQL); a new client per query over one channel.
    Flight { url: String, channel: Channel, token: Option<String> },
}

/// A runtime the engine made for itself (sync callers). The last engine may be dropped anywhere:
/// outside a runtime its threads are joined (for a second at most), inside one (a task holding
/// the last reference) they are told to stop and left to end on their own.
struct Owned(Option<tokio::runtime::Runtime>);

impl Drop for Owned {
    fn drop(&mut self) {
        if let Some(rt) = self.0.take() {
            if Handle::try_current().is_ok() {
                rt.shutdown_background();
            } else {
                rt.shutdown_timeout(std::time::Duration::from_secs(1));
            }
        }
    }
}

/// SQL over traces, wherever it runs (see the module's text).
pub struct Engine {
    backend: Backend,
    datasets: Vec<Registered>,
    handle: Handle,
    /// Over a trace in memory (`Engine::live`).
    live: bool,
    /// Queries run so far (`queries_run`).
    queries: std::sync::atomic::AtomicU64,
    _owned: Option<Arc<Owned>>,
}

impl std::fmt::Debug for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Engine({})", self.describe())
    }
}

fn current() -> Result<Handle> {
    Handle::try_current()
        .map_err(|_| Error::Service("an engine is made inside a Tokio runtime (or through Engine::blocking)".into()))
}

impl Engine {
    fn new(backend: Backend, datasets: Vec<Registered>, live: bool) -> Result<Engine> {
        Ok(Engine { backend, datasets, handle: current()?, live, queries: Default::default(), _owned: None })
    }

    /// Opens `sources` (each dataset once) in a session in this process: each dataset's tables
    /// in the schema named after it, the first one's also unqualified, and the ray functions over
    /// the first one's scene.
    pub async fn open(sources: &[TraceSource], options: &SessionOptions) -> Result<Engine> {
        Engine::with_datasets(open_sources(sources)?, options).await
    }

    /// A session in this process over datasets already open (the viewer's, Python's).
    pub async fn with_datasets(datasets: Vec<Registered>, options: &SessionOptions) -> Result<Engine> {
        let ctx = SessionContext::new_with_state(session_state(options)?);
        register_datasets(&ctx, &datasets).await?;
        Engine::new(Backend::Session(ctx), datasets, false)
    }

    /// A session in this process over a trace held in memory and growing while it is recorded
    /// (see `live`): its tables unqualified, read anew at every query; the ray functions over
    /// its scene as it is now (lights and bounds).
    pub async fn live(trace: Arc<dyn crate::LiveTrace>, options: &SessionOptions) -> Result<Engine> {
        let ctx = SessionContext::new_with_state(session_state(options)?);
        for (name, table) in crate::live::tables(&trace)? {
            ctx.register_table(name.as_str(), table)?;
        }
        crate::functions::register_functions(&ctx, Arc::new(crate::live::scene(&trace)?));
        Engine::new(Backend::Session(ctx), Vec::new(), true)
    }

    /// An engine over a session made elsewhere (a Ballista session planned here and run on the
    /// cluster, see `cluster::connect`) whose tables are `datasets`'.
    pub fn from_session(ctx: SessionContext, datasets: Vec<Registered>) -> Result<Engine> {
        Engine::new(Backend::Session(ctx), datasets, false)
    }

    /// An `rtvtk serve` service at `url` (`grpc://HOST:PORT`, `http://`, `https://`), with its
    /// bearer token when it asks for one. Fails now when nobody answers there.
    pub async fn connect(url: &str, token: Option<String>) -> Result<Engine> {
        let http = match url.strip_prefix("grpc://") {
            Some(rest) => format!("http://{rest}"),
            None => url.to_string(),
        };
        let channel = Channel::from_shared(http)
            .map_err(|e| Error::BadArgument(format!("{url} is not a service address (grpc://HOST:PORT): {e}")))?
            .connect()
            .await
            .map_err(|e| Error::Service(format!("cannot connect to {url}: {e}")))?;
        let backend = Backend::Flight { url: url.to_string(), channel, token };
        Engine::new(backend, Vec::new(), false)
    }

    /// Makes an engine from synchronous code: `make` (one of the constructors above) runs on a
    /// runtime of the engine's own, which then serves its queries ([`Engine::block_on`]).
    pub fn blocking<F>(make: F) -> Result<Engine>
    where
        F: Future<Output = Result<Engine>>,
    {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(std::thread::available_parallelism().map_or(2, |n| n.get()).min(8))
            .thread_name("rtvtk-sql")
            .enable_all()
            .build()
            .map_err(|e| Error::Service(format!("cannot start the query runtime: {e}")))?;
        let mut engine = rt.block_on(make)?;
        engine._owned = Some(Arc::new(Owned(Some(rt))));
        Ok(engine)
    }

    /// Runs `fut` to completion on the engine's runtime (from synchronous code, never from a
    /// task of a runtime).
    pub fn block_on<F: Future>(&self, fut: F) -> F::Output {
        self.handle.block_on(fut)
    }

    /// Runs `fut` as a task on the engine's runtime.
    pub fn spawn<F>(&self, fut: F) -> tokio::task::JoinHandle<F::Output>
    where
        F: Future + Send + 'static,
        F::Output: Send + 'static,
    {
        self.handle.spawn(fut)
    }

    /// The datasets this process serves (none for a service's client).
    pub fn datasets(&self) -> &[Registered] {
        &self.datasets
    }

    /// The dataset registered as `name`, or the first (the unqualified tables') for `None`.
    pub fn dataset(&self, name: Option<&str>) -> Option<Arc<Dataset>> {
        match name {
            Some(n) => self.datasets.iter().find(|d| d.name == n),
            None => self.datasets.first(),
        }
        .map(|d| d.dataset.clone())
    }

    /// The session, where it runs here (in this process or planned here for a cluster).
    pub fn session(&self) -> Option<&SessionContext> {
        match &self.backend {
            Backend::Session(ctx) => Some(ctx),
            Backend::Flight { .. } => None,
        }
    }

    /// Whether queries go to a service.
    pub fn is_remote(&self) -> bool {
        matches!(self.backend, Backend::Flight { .. })
    }

    /// Where queries run, in words.
    pub fn describe(&self) -> String {
        match &self.backend {
            Backend::Session(_) if self.live => "in-process session over a recording in memory".into(),
            Backend::Session(_) => {
                let names: Vec<&str> = self.datasets.iter().map(|d| d.name.as_str()).collect();
                format!(
                    "in-process session over {}",
                    if names.is_empty() { "no dataset".into() } else { names.join(", ") }
                )
            }
            Backend::Flight { url, .. } => format!("the service at {url}"),
        }
    }

    /// How many queries this engine has been asked (an analysis's progress, for example).
    pub fn queries_run(&self) -> u64 {
        self.queries.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Runs a read-only query (no DDL, DML or `SET`), its batches streamed as they come.
    pub async fn stream(&self, sql: &str) -> Result<SendableRecordBatchStream> {
        self.queries.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        match &self.backend {
            Backend::Session(ctx) => {
                let df = ctx.sql_with_options(sql, crate::service::read_only_sql_options()).await?;
                Ok(df.execute_stream().await?)
            }
            Backend::Flight { channel, token, .. } => {
                let info = flight_client(channel, token).execute(sql.to_string(), None).await.map_err(flight_error)?;
                let schema: SchemaRef = Arc::new(info.clone().try_decode_schema().map_err(flight_error)?);
                let tickets: Vec<_> = info.endpoint.into_iter().filter_map(|e| e.ticket).collect();
                let (channel, token) = (channel.clone(), token.clone());
                let batches = futures::stream::iter(tickets)
                    .then(move |ticket| {
                        let mut c = flight_client(&channel, &token);
                        async move { c.do_get(ticket).await }
                    })
                    .map_err(flight_error)
                    .map_ok(|s| s.map_err(flight_error))
                    .try_flatten()
                    .map_err(|e| datafusion::error::DataFusionError::External(Box::new(e)));
                Ok(Box::pin(RecordBatchStreamAdapter::new(schema, batches)))
            }
        }
    }

    /// Runs a read-only query and collects its result.
    pub async fn collect(&self, sql: &str) -> Result<Vec<RecordBatch>> {
        Ok(self.stream(sql).await?.try_collect().await?)
    }

    /// The tables and functions queries can name: the session's own, or what a service's
    /// `information_schema` says.
    pub async fn catalog(&self) -> Result<Catalog> {
        let mut catalog = match &self.backend {
            Backend::Session(ctx) => {
                let mut tables = Vec::new();
                for cat in ctx.catalog_names() {
                    let Some(c) = ctx.catalog(&cat) else { continue };
                    for sch in c.schema_names().into_iter().filter(|s| s != "information_schema") {
                        if let Some(s) = c.schema(&sch) {
                            tables.extend(s.table_names().into_iter().map(|t| qualified(&sch, t)));
                        }
                    }
                }
                let state = ctx.state();
                let functions =
                    state.scalar_functions().keys().chain(state.aggregate_functions().keys()).cloned().collect();
                Catalog { tables, functions }
            }
            Backend::Flight { .. } => {
                let strings = |batches: &[RecordBatch], col: usize| -> Result<Vec<String>> {
                    let mut out = Vec::new();
                    for b in batches {
                        let c = arrow::compute::cast(b.column(col), &arrow::datatypes::DataType::Utf8)
                            .map_err(|e| Error::DataFusion(e.into()))?;
                        let c = c.as_any().downcast_ref::<arrow::array::StringArray>();
                        out.extend(c.into_iter().flatten().map(|s| s.unwrap_or_default().to_string()));
                    }
                    Ok(out)
                };
                let t = self
                    .collect(
                        "SELECT table_schema, table_name FROM information_schema.tables \
                         WHERE table_schema <> 'information_schema'",
                    )
                    .await?;
                let tables = strings(&t, 0)?.iter().zip(strings(&t, 1)?).map(|(s, n)| qualified(s, n)).collect();
                let f = self.collect("SELECT DISTINCT routine_name FROM information_schema.routines").await?;
                Catalog { tables, functions: strings(&f, 0)? }
            }
        };
        catalog.tables.sort();
        catalog.tables.dedup();
        catalog.functions.sort();
        catalog.functions.dedup();
        Ok(catalog)
    }
}

fn qualified(schema: &str, table: String) -> String {
    if schema == "public" { table } else { format!("{schema}.{table}") }
}

/// A Flight SQL client on `channel`, sending `token` when there is one.
fn flight_client(channel: &Channel, token: &Option<String>) -> FlightSqlServiceClient<Channel> {
    let mut c = FlightSqlServiceClient::new(channel.clone());
    if let Some(t) = token {
        c.set_token(t.clone());
    }
    c
}

/// A service's error, in its words.
fn flight_error(e: impl std::fmt::Display) -> Error {
    Error::Service(e.to_string())
}
