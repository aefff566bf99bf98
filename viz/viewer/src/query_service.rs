//! Queries off the UI thread: the console's SQL, the inspector's lookups, the plots and the tree
//! navigation run as tasks on the runtime of the one engine the render worker opened with the
//! dataset (`query::Engine`: the session in this process, or an `rtvtk serve` service through
//! Flight SQL), so the layers and the console ask the same engine. Every request can be
//! cancelled; replies come back on a channel the UI polls each frame.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::time::Instant;

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use futures::StreamExt;
use query::{Catalog, Engine};

use crate::Result;

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

/// The queries of the UI, on the engine it was handed.
pub struct QueryService {
    engine: std::result::Result<Arc<Engine>, String>,
    tx: Sender<Reply>,
    rx: Receiver<Reply>,
    running: HashMap<Tag, tokio::task::AbortHandle>,
    wake: Arc<dyn Fn() + Send + Sync>,
    /// Set while a dataset is being opened or a service connected (queries wait for it).
    pub connecting: bool,
    /// The engine's tables and functions, asked for when it was handed over.
    catalog: Arc<std::sync::Mutex<Catalog>>,
}

/// Runs `sql` on `engine`, keeping at most [`MAX_ROWS`] rows.
async fn run(engine: &Engine, sql: &str) -> std::result::Result<(SchemaRef, Vec<RecordBatch>, bool), String> {
    let mut stream = engine.stream(sql).await.map_err(|e| e.to_string())?;
    let schema = stream.schema();
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

impl QueryService {
    pub fn new(wake: Arc<dyn Fn() + Send + Sync>) -> Result<QueryService> {
        let (tx, rx) = channel();
        Ok(QueryService {
            engine: Err("no dataset is open: there is nothing to query".into()),
            tx,
            rx,
            running: HashMap::new(),
            wake,
            connecting: false,
            catalog: Arc::default(),
        })
    }

    /// The engine queries go to from now on (`Err`: why there is none); running queries are
    /// cancelled, and its catalog is asked for (a [`Tag::Catalog`] reply).
    pub fn set_engine(&mut self, engine: std::result::Result<Arc<Engine>, String>) {
        for (_, h) in self.running.drain() {
            h.abort();
        }
        self.engine = engine;
        self.connecting = true;
        let (tx, wake) = (self.tx.clone(), self.wake.clone());
        let result = match &self.engine {
            Ok(engine) => {
                let (e, catalog) = (engine.clone(), self.catalog.clone());
                engine.spawn(async move {
                    let result = match e.catalog().await {
                        Ok(c) => {
                            if let Ok(mut held) = catalog.lock() {
                                *held = c;
                            }
                            Ok(QueryResult::new(
                                String::new(),
                                Arc::new(arrow::datatypes::Schema::empty()),
                                Vec::new(),
                                0.0,
                                false,
                            ))
                        }
                        Err(e) => Err(e.to_string()),
                    };
                    let _ = tx.send(Reply { tag: Tag::Catalog, result });
                    wake();
                });
                return;
            }
            Err(why) => Err(why.clone()),
        };
        if let Ok(mut held) = self.catalog.lock() {
            *held = Catalog::default();
        }
        let _ = tx.send(Reply { tag: Tag::Catalog, result });
        wake();
    }

    /// The engine queries go to.
    pub fn engine(&self) -> Option<&Arc<Engine>> {
        self.engine.as_ref().ok()
    }

    /// Runs `sql` for `tag`, cancelling that tag's previous query.
    pub fn submit(&mut self, tag: Tag, sql: String) {
        self.cancel(&tag);
        let (tx, wake) = (self.tx.clone(), self.wake.clone());
        let engine = match &self.engine {
            Ok(e) => e.clone(),
            Err(why) => {
                let _ = tx.send(Reply { tag, result: Err(why.clone()) });
                wake();
                return;
            }
        };
        let t = tag.clone();
        let e = engine.clone();
        let h = engine.spawn(async move {
            let t0 = Instant::now();
            let result = run(&e, &sql).await.map(|(schema, batches, truncated)| {
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

    /// Tables and functions, for the console's list: what the engine said when it was handed over.
    pub fn catalog(&self) -> (Vec<String>, Vec<String>) {
        self.catalog.lock().map(|c| (c.tables.clone(), c.functions.clone())).unwrap_or_default()
    }
}
