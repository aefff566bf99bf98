//! SQL over a trace held in memory and growing while a renderer records (an immediate-mode
//! recording, `rl::MemoryTrace`): its tables are read anew at every query, so a query sees every
//! ray recorded before it started. The same tables and functions as a dataset's, in the same
//! [`Engine`](crate::Engine): `rays`, `trees`, `attributes` and the whole-recording tables
//! (`triangles`, `lights`, ...) written before the engine was made. `ray_paths` is a dataset's
//! alone (it reads the store's segments).

use std::sync::Arc;

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use datafusion::datasource::TableProvider;
use datafusion::datasource::memory::MemorySourceConfig;
use datafusion::physical_plan::ExecutionPlan;

use crate::Result;
use crate::functions::SceneContext;

/// What a trace in memory offers SQL. `query` does not depend on the recorder (`rl`); whoever
/// holds an `rl::MemoryTrace` implements this over it (a few one-line forwards).
pub trait LiveTrace: Send + Sync + 'static {
    /// The `rays` table's schema (`store::ray_table_schema` of the recording's payload).
    fn ray_schema(&self) -> SchemaRef;
    /// The rays held now, in `ray_schema`.
    fn rays(&self) -> store::Result<Vec<RecordBatch>>;
    /// The trees held now, in `store::tree_schema`.
    fn trees(&self) -> store::Result<Vec<RecordBatch>>;
    /// A whole-recording table (`triangles`, `lights`, ...), if written.
    fn table(&self, name: &str) -> Option<RecordBatch>;
    /// The names of the whole-recording tables written so far.
    fn table_names(&self) -> Vec<String>;
    /// The recording's attributes (camera, image size, ...).
    fn attributes(&self) -> Vec<(String, String)>;
    /// Statistics of everything recorded so far (the scene bounds of `morton3`).
    fn stats(&self) -> store::Stats;
}

type Read = dyn Fn() -> store::Result<Vec<RecordBatch>> + Send + Sync;

/// A table whose batches are read when a query scans it.
struct LiveTable {
    schema: SchemaRef,
    read: Box<Read>,
}

impl std::fmt::Debug for LiveTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "LiveTable({} columns)", self.schema.fields().len())
    }
}

#[async_trait::async_trait]
impl TableProvider for LiveTable {
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }

    fn table_type(&self) -> datafusion::datasource::TableType {
        datafusion::datasource::TableType::Base
    }

    async fn scan(
        &self,
        state: &dyn datafusion::catalog::Session,
        projection: Option<&Vec<usize>>,
        _filters: &[datafusion::logical_expr::Expr],
        _limit: Option<usize>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        let batches = (self.read)().map_err(|e| datafusion::error::DataFusionError::External(Box::new(e)))?;
        // The batches dealt round-robin over the session's partitions, so scans run in parallel.
        let n = state.config().target_partitions().max(1).min(batches.len().max(1));
        let mut partitions = vec![Vec::new(); n];
        for (i, b) in batches.into_iter().enumerate() {
            partitions[i % n].push(b);
        }
        Ok(MemorySourceConfig::try_new_exec(&partitions, self.schema.clone(), projection.cloned())?)
    }
}

/// The tables of `trace` by name, each read at every scan.
pub(crate) fn tables(trace: &Arc<dyn LiveTrace>) -> Result<Vec<(String, Arc<dyn TableProvider>)>> {
    let mut out: Vec<(String, Arc<dyn TableProvider>)> = Vec::new();
    let t = trace.clone();
    out.push(("rays".into(), Arc::new(LiveTable { schema: trace.ray_schema(), read: Box::new(move || t.rays()) })));
    let t = trace.clone();
    out.push(("trees".into(), Arc::new(LiveTable { schema: store::tree_schema(), read: Box::new(move || t.trees()) })));
    let t = trace.clone();
    let attributes =
        LiveTable { schema: crate::tables::attributes_schema(), read: Box::new(move || attributes_batches(&t)) };
    out.push((crate::tables::ATTRIBUTES_TABLE.into(), Arc::new(attributes)));
    for name in trace.table_names() {
        let Some(first) = trace.table(&name) else { continue };
        let t = trace.clone();
        let n = name.clone();
        let read = move || Ok(t.table(&n).into_iter().collect());
        out.push((name, Arc::new(LiveTable { schema: first.schema(), read: Box::new(read) })));
    }
    Ok(out)
}

fn attributes_batches(t: &Arc<dyn LiveTrace>) -> store::Result<Vec<RecordBatch>> {
    let attrs = t.attributes();
    let batch = crate::tables::attributes_batch(attrs.iter().map(|(k, v)| (k.as_str(), v.as_str()))).map_err(|e| {
        store::Error::Table {
            name: crate::tables::ATTRIBUTES_TABLE.into(),
            path: "(the recording in memory)".into(),
            message: e.to_string(),
        }
    })?;
    Ok(vec![batch])
}

/// What the scene-dependent functions know of `trace` now: bounds from its statistics, emitters
/// from its `lights` table.
pub(crate) fn scene(trace: &Arc<dyn LiveTrace>) -> Result<SceneContext> {
    SceneContext::from_parts(
        &trace.stats(),
        trace.table(store::scene::LIGHTS_TABLE).as_ref(),
        "the recording in memory",
    )
}
