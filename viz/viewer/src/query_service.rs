//! Queries off the UI thread: the console's SQL, the inspector's lookups and the tree navigation
//! run as tasks on their own runtime, against the local session over the open datasets or an
//! `rtvtk serve` service through Flight SQL. Every request can be cancelled; replies come back on
//! a channel the UI polls each frame.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::time::Instant;

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use arrow_flight::sql::client::FlightSqlServiceClient;
use datafusion::prelude::SessionContext;
use futures::{StreamExt, TryStreamExt};
use tonic::transport::Channel;

use crate::{Error, Result};

/// Rows a console result keeps (the table scrolls through all of them, virtualized).
pub const MAX_ROWS: usize = 5_000_000;

/// A finished query.
#[derive(Clone)]
pub struct QueryResult {
    pub sql: String,
    pub schema: SchemaRef,
    pub batches: Vec<RecordBatch>,
    /// First row of each batch (for random access by row).
    pub starts: Vec<usize>,
    pub rows: usize,
    pub secs: f64,
    /// More rows existed than [`MAX_ROWS`].
    pub truncated: bool,
}

impl QueryResult {
    fn new(sql: String, schema: SchemaRef, batches: Vec<RecordBatch>, secs: f64, truncated: bool) -> QueryResult {
        let mut starts = Vec::with_capacity(batches.len());
        let mut rows = 0;
        for b in &batches {
            starts.push(rows);
            rows += b.num_rows();
        }
        QueryResult { sql, schema, batches, starts, rows, secs, truncated }
    }

    /// The batch and row within it of result row `row`.
    pub fn locate(&self, row: usize) -> Option<(&RecordBatch, usize)> {
        if row >= self.rows {
            return None;
        }
        let i = self.starts.partition_point(|&s| s <= row).checked_sub(1)?;
        Some((&self.batches[i], row - self.starts[i]))
    }

    /// Row `row`'s value of column `name` as a string (`None`: no such column or row).
    pub fn value(&self, row: usize, name: &str) -> Option<String> {
        let (b, r) = self.locate(row)?;
        let c = b.column_by_name(name)?;
        let f = arrow::util::display::ArrayFormatter::try_new(c.as_ref(), &Default::default()).ok()?;
        Some(f.value(r).to_string())
    }

    /// Row `row`'s value of an integer column.
    pub fn int(&self, row: usize, name: &str) -> Option<u64> {
        self.value(row, name)?.parse().ok()
    }
}

/// Who asked (so replies find their place in the UI).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum Tag {
    Console,
    Inspect,
    InspectTree,
    /// Tree navigation of a rays component: the tree to show next.
    NextTree(u64),
    Plot,
    Catalog,
}

pub struct Reply {
    pub tag: Tag,
    pub result: std::result::Result<QueryResult, String>,
}

enum Backend {
    Local(SessionContext),
    Flight(FlightSqlServiceClient<Channel>),
    None(String),
}

/// Where queries go.
#[derive(Clone, Debug, PartialEq)]
pub enum Target {
    /// The local session over these datasets (the first is also unqualified).
    Local(Vec<PathBuf>),
    /// An `rtvtk serve` service; a bearer token when the service asks for one.
    Flight { url: String, token: Option<String> },
}

pub struct QueryService {
    runtime: tokio::runtime::Runtime,
    backend: Arc<tokio::sync::Mutex<Backend>>,
    tx: Sender<Reply>,
    rx: Receiver<Reply>,
    running: HashMap<Tag, tokio::task::AbortHandle>,
    wake: Arc<dyn Fn() + Send + Sync>,
    pub target: Target,
    /// Set while the backend is being opened or connected.
    pub connecting: bool,
    /// A service's tables and functions, asked for through its `information_schema` on connecting.
    remote_catalog: Arc<std::sync::Mutex<(Vec<String>, Vec<String>)>>,
}

/// A service's tables (schema-qualified outside `public`) and functions, from its
/// `information_schema`; empty lists where it does not answer.
async fn remote_catalog(client: &mut FlightSqlServiceClient<Channel>) -> (Vec<String>, Vec<String>) {
    let column = |r: &std::result::Result<(SchemaRef, Vec<RecordBatch>, bool), String>, names: &[&str]| {
        let Ok((schema, batches, _)) = r else { return Vec::new() };
        let q = QueryResult::new(String::new(), schema.clone(), batches.clone(), 0.0, false);
        let mut out: Vec<String> = (0..q.rows)
            .filter_map(|i| {
                let v: Vec<String> = names.iter().filter_map(|n| q.value(i, n)).collect();
                match v.as_slice() {
                    [sch, t] if sch == "public" => Some(t.clone()),
                    [sch, t] => Some(format!("{sch}.{t}")),
                    [f] => Some(f.clone()),
                    _ => None,
                }
            })
            .collect();
        out.sort();
        out.dedup();
        out
    };
    let t = run_flight(
        client,
        "SELECT table_schema, table_name FROM information_schema.tables WHERE table_schema <> 'information_schema'",
    )
    .await;
    let f = run_flight(client, "SELECT DISTINCT routine_name FROM information_schema.routines").await;
    (column(&t, &["table_schema", "table_name"]), column(&f, &["routine_name"]))
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("rtvtk-query")
        .enable_all()
        .build()
        .map_err(|e| Error::Runtime(e.to_string()))
}

async fn connect(target: &Target) -> Backend {
    match target {
        Target::Local(dirs) if dirs.is_empty() => Backend::None("no dataset is open: there is nothing to query".into()),
        Target::Local(dirs) => {
            let sources: Vec<_> = dirs
                .iter()
                .enumerate()
                .map(|(i, d)| {
                    let mut s = query::TraceSource::parse(&d.display().to_string());
                    if i == 0 {
                        s.name = "trace".into();
                    }
                    s
                })
                .collect();
            match query::session(&sources).await {
                Ok(ctx) => Backend::Local(ctx),
                Err(e) => Backend::None(format!("cannot open the datasets for SQL: {e}")),
            }
        }
        Target::Flight { url, token } => {
            let channel = match Channel::from_shared(url.clone()) {
                Ok(c) => c,
                Err(e) => return Backend::None(format!("{url} is not a service address: {e}")),
            };
            match channel.connect().await {
                Ok(ch) => {
                    let mut client = FlightSqlServiceClient::new(ch);
                    if let Some(t) = token {
                        client.set_token(t.clone());
                    }
                    Backend::Flight(client)
                }
                Err(e) => Backend::None(format!("cannot connect to {url}: {e}")),
            }
        }
    }
}

async fn run_local(
    ctx: &SessionContext,
    sql: &str,
) -> std::result::Result<(SchemaRef, Vec<RecordBatch>, bool), String> {
    let df = ctx.sql_with_options(sql, query::service::read_only_sql_options()).await.map_err(|e| e.to_string())?;
    let schema: SchemaRef = Arc::new(df.schema().as_arrow().clone());
    let mut stream = df.execute_stream().await.map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    let mut rows = 0;
    while let Some(b) = stream.next().await {
        let b = b.map_err(|e| e.to_string())?;
        rows += b.num_rows();
        out.push(b);
        if rows >= MAX_ROWS {
            return Ok((schema, out, true));
        }
    }
    Ok((schema, out, false))
}

async fn run_flight(
    client: &mut FlightSqlServiceClient<Channel>,
    sql: &str,
) -> std::result::Result<(SchemaRef, Vec<RecordBatch>, bool), String> {
    let info = client.execute(sql.to_string(), None).await.map_err(|e| e.to_string())?;
    let schema: SchemaRef = Arc::new(info.clone().try_decode_schema().map_err(|e| e.to_string())?);
    let mut out = Vec::new();
    let mut rows = 0;
    for ep in info.endpoint {
        let Some(ticket) = ep.ticket else { continue };
        let mut stream = client.do_get(ticket).await.map_err(|e| e.to_string())?;
        while let Some(b) = stream.try_next().await.map_err(|e| e.to_string())? {
            rows += b.num_rows();
            out.push(b);
            if rows >= MAX_ROWS {
                return Ok((schema, out, true));
            }
        }
    }
    Ok((schema, out, false))
}

impl QueryService {
    pub fn new(target: Target, wake: Arc<dyn Fn() + Send + Sync>) -> Result<QueryService> {
        let (tx, rx) = channel();
        let mut s = QueryService {
            runtime: runtime()?,
            backend: Arc::new(tokio::sync::Mutex::new(Backend::None("not connected yet".into()))),
            tx,
            rx,
            running: HashMap::new(),
            wake,
            target: target.clone(),
            connecting: false,
            remote_catalog: Arc::default(),
        };
        s.retarget(target);
        Ok(s)
    }

    /// Opens (or connects to) another target; queries wait for it.
    pub fn retarget(&mut self, target: Target) {
        self.target = target.clone();
        self.connecting = true;
        let backend = self.backend.clone();
        let (tx, wake) = (self.tx.clone(), self.wake.clone());
        let catalog = self.remote_catalog.clone();
        self.runtime.spawn(async move {
            let mut b = backend.lock().await;
            *b = connect(&target).await;
            let names = match &mut *b {
                Backend::Flight(client) => remote_catalog(client).await,
                _ => Default::default(),
            };
            if let Ok(mut c) = catalog.lock() {
                *c = names;
            }
            let result = match &*b {
                Backend::None(why) => Err(why.clone()),
                _ => Ok(QueryResult::new(
                    String::new(),
                    Arc::new(arrow::datatypes::Schema::empty()),
                    Vec::new(),
                    0.0,
                    false,
                )),
            };
            let _ = tx.send(Reply { tag: Tag::Catalog, result });
            wake();
        });
    }

    /// Runs `sql` for `tag`, cancelling that tag's previous query.
    pub fn submit(&mut self, tag: Tag, sql: String) {
        self.cancel(&tag);
        let backend = self.backend.clone();
        let (tx, wake) = (self.tx.clone(), self.wake.clone());
        let t = tag.clone();
        let h = self.runtime.spawn(async move {
            let t0 = Instant::now();
            let mut b = backend.lock().await;
            let r = match &mut *b {
                Backend::Local(ctx) => {
                    let ctx = ctx.clone();
                    drop(b);
                    run_local(&ctx, &sql).await
                }
                Backend::Flight(client) => run_flight(client, &sql).await,
                Backend::None(why) => Err(why.clone()),
            };
            let result = r.map(|(schema, batches, truncated)| {
                QueryResult::new(sql, schema, batches, t0.elapsed().as_secs_f64(), truncated)
            });
            let _ = tx.send(Reply { tag: t, result });
            wake();
        });
        self.running.insert(tag, h.abort_handle());
    }

    /// Cancels the query of `tag` (its reply never comes).
    pub fn cancel(&mut self, tag: &Tag) {
        if let Some(h) = self.running.remove(tag) {
            h.abort();
        }
    }

    pub fn is_running(&self, tag: &Tag) -> bool {
        self.running.get(tag).is_some_and(|h| !h.is_finished())
    }

    /// Replies that arrived since the last call.
    pub fn poll(&mut self) -> Vec<Reply> {
        let replies: Vec<Reply> = self.rx.try_iter().collect();
        for r in &replies {
            if r.tag == Tag::Catalog {
                self.connecting = false;
            }
            if self.running.get(&r.tag).is_some_and(|h| h.is_finished()) {
                self.running.remove(&r.tag);
            }
        }
        replies
    }

    /// Tables and functions, for the console's list: the local session's, or what a service's
    /// `information_schema` said on connecting.
    pub fn catalog(&self) -> (Vec<String>, Vec<String>) {
        let Ok(b) = self.backend.try_lock() else { return (Vec::new(), Vec::new()) };
        let Backend::Local(ctx) = &*b else {
            return self.remote_catalog.lock().map(|c| c.clone()).unwrap_or_default();
        };
        let mut tables = Vec::new();
        for cat in ctx.catalog_names() {
            let Some(c) = ctx.catalog(&cat) else { continue };
            for sch in c.schema_names() {
                if sch == "information_schema" {
                    continue;
                }
                if let Some(s) = c.schema(&sch) {
                    for t in s.table_names() {
                        tables.push(if sch == "public" { t } else { format!("{sch}.{t}") });
                    }
                }
            }
        }
        tables.sort();
        let state = ctx.state();
        let mut functions: Vec<String> =
            state.scalar_functions().keys().chain(state.aggregate_functions().keys()).cloned().collect();
        functions.sort();
        functions.dedup();
        (tables, functions)
    }
}
