//! The tables of a trace dataset in a DataFusion session.
//!
//! - `rays`: every ray, streamed through the store one partition per segment (see `scan`): only
//!   the projected columns are read, origins and directions are decoded only when used, and
//!   filters on tree, pixel, sample, depth and kind skip segments, trees and row groups.
//! - `trees`: the segments' tree tables (plain Parquet in every format version).
//! - `ray_paths`: every ray's path from its root as kind letters (`C D D S L`), for
//!   light-path-expression filters with `regexp_like`.
//! - every whole-dataset table the recording wrote (`triangles`, `lights`, `bvh_nodes`,
//!   `ray_nodes`, a renderer's own), its schema checked against the known one; a table that
//!   fails the check is unavailable alone (its queries say why), the rest stay queryable.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::RecordBatch;
use arrow::datatypes::SchemaRef;
use datafusion::catalog::MemorySchemaProvider;
use datafusion::common::TableReference;
use datafusion::common::tree_node::TreeNodeRecursion;
use datafusion::datasource::TableProvider;
use datafusion::datasource::file_format::parquet::ParquetFormat;
use datafusion::datasource::listing::{ListingOptions, ListingTable, ListingTableConfig, ListingTableUrl};
use datafusion::execution::TaskContext;
use datafusion::execution::session_state::SessionStateBuilder;
use datafusion::physical_expr::{EquivalenceProperties, PhysicalExpr};
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_optimizer::optimizer::PhysicalOptimizer;
use datafusion::physical_plan::execution_plan::{Boundedness, EmissionType};
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlan, Partitioning, PlanProperties, SendableRecordBatchStream,
};
use datafusion::prelude::{SessionConfig, SessionContext};
use store::Dataset;

use crate::count_by_key::CountByKey;
use crate::functions::{SceneContext, register_functions};
use crate::scan::{RaysTable, stream};
use crate::small_groups::SmallGroups;
use crate::unavailable::Unavailable;
use crate::{Error, Result};

/// A dataset the engine serves from this process: its name (the schema of its tables) and the
/// dataset, opened once.
#[derive(Clone)]
pub struct Registered {
    pub name: String,
    pub dataset: Arc<Dataset>,
}

/// A dataset to query, under a name (its tables are `NAME.rays`, `NAME.trees`, ...).
#[derive(Clone, Debug)]
pub struct TraceSource {
    pub name: String,
    pub path: PathBuf,
}

impl TraceSource {
    /// `NAME=PATH`, or a bare path named after its last component.
    pub fn parse(arg: &str) -> Self {
        match arg.split_once('=') {
            Some((name, path)) if !name.is_empty() && !name.contains('/') => {
                Self { name: name.to_string(), path: PathBuf::from(path) }
            }
            _ => {
                let path = PathBuf::from(arg);
                let stem = path.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
                let name: String = stem.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect();
                let name = if name.is_empty() || name.starts_with(|c: char| c.is_ascii_digit()) {
                    format!("t_{name}")
                } else {
                    name
                };
                Self { name, path }
            }
        }
    }
}

/// A session over `sources`: each dataset's tables in the schema named after it, the first one's
/// also unqualified (`rays`, `trees`, ...), and the ray functions (scene-dependent ones, such as
/// `aims_at_light` and `morton3`, use the first dataset's scene).
pub async fn session(sources: &[TraceSource]) -> Result<SessionContext> {
    session_with(sources, &SessionOptions::default()).await
}

/// Settings of a session.
#[derive(Clone, Debug, Default)]
pub struct SessionOptions {
    /// Bytes the operators may hold (sorts, joins and aggregations spill or fail beyond it);
    /// when None, [`default_memory_limit`]: a share of this machine's memory.
    pub memory_limit: Option<usize>,
    /// DataFusion's own aggregation for every group-by: rtvtk's [`CountByKey`] and [`SmallGroups`]
    /// rules left out (to compare the two on the same query).
    pub stock_aggregation: bool,
}

/// [`session`] with settings.
pub async fn session_with(sources: &[TraceSource], options: &SessionOptions) -> Result<SessionContext> {
    let ctx = SessionContext::new_with_state(session_state(options)?);
    register_datasets(&ctx, &open_sources(sources)?).await?;
    Ok(ctx)
}

/// Opens each dataset of `sources` (once).
pub fn open_sources(sources: &[TraceSource]) -> Result<Vec<Registered>> {
    sources
        .iter()
        .map(|s| Ok(Registered { name: s.name.clone(), dataset: Arc::new(Dataset::open(&s.path)?) }))
        .collect()
}

/// The configuration of rtvtk's sessions: information schema, Parquet pruning and filter pushdown.
pub fn session_config() -> SessionConfig {
    SessionConfig::new()
        .with_information_schema(true)
        .with_parquet_pruning(true)
        .with_parquet_page_index_pruning(true)
        .set_bool("datafusion.execution.parquet.pushdown_filters", true)
}

/// The memory a session's operators may hold when none is given: 80% of this machine's memory
/// (or of the control group's limit, when lower), as DuckDB's default is; beyond it a sort, join
/// or aggregation (DataFusion's, or rtvtk's counting group-by) spills to the temporary directory,
/// and rtvtk's small-key group-by sends its partial groups on early, instead of the process being
/// killed for memory. None (unlimited) where the machine's memory is not known (outside Linux).
pub fn default_memory_limit() -> Option<usize> {
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|m| {
        let kb = m
            .lines()
            .find_map(|l| l.strip_prefix("MemTotal:"))?
            .trim()
            .strip_suffix("kB")?
            .trim()
            .parse::<u64>()
            .ok()?;
        Some(kb * 1024)
    })?;
    // cgroup v2, then v1 ("max" or a huge number where unlimited).
    let group = ["/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"]
        .iter()
        .find_map(|p| std::fs::read_to_string(p).ok()?.trim().parse::<u64>().ok());
    let bytes = group.map_or(total, |g| g.min(total));
    usize::try_from(bytes / 5 * 4).ok()
}

/// A session state with rtvtk's settings and physical operators, no tables or ray functions yet
/// (see [`register_datasets`]).
pub fn session_state(options: &SessionOptions) -> Result<datafusion::execution::SessionState> {
    let mut runtime = datafusion::execution::runtime_env::RuntimeEnvBuilder::new();
    if let Some(limit) = options.memory_limit.or_else(default_memory_limit) {
        runtime = runtime.with_memory_pool(crate::memory::session_pool(limit));
    }
    Ok(SessionStateBuilder::new()
        .with_config(session_config())
        .with_runtime_env(runtime.build_arc()?)
        .with_default_features()
        .with_physical_optimizer_rules(if options.stock_aggregation {
            PhysicalOptimizer::new().rules
        } else {
            physical_optimizer_rules()
        })
        .build())
}

/// Registers datasets already open in `ctx` (each in the schema named after it, the first one's
/// tables also unqualified), the ray functions over the first dataset's scene, and each
/// dataset's `numerics` view (`crate::numerics`).
pub async fn register_datasets(ctx: &SessionContext, datasets: &[Registered]) -> Result<()> {
    let mut names = std::collections::HashSet::new();
    for (i, d) in datasets.iter().enumerate() {
        if !names.insert(d.name.clone()) {
            return Err(Error::DuplicateName { name: d.name.clone() });
        }
        register_dataset(ctx, &d.name, &d.dataset, i == 0).await?;
    }
    let scene = match datasets.first() {
        Some(d) => SceneContext::of(&d.dataset),
        None => SceneContext::default(),
    };
    register_functions(ctx, Arc::new(scene));
    // The `numerics` views read the ray functions; the scene's (lights, triangles) are the first
    // dataset's, so only its view has the checks that need them.
    for (i, d) in datasets.iter().enumerate() {
        crate::numerics::register_view(ctx, &d.name, &d.dataset, i == 0, i == 0).await?;
    }
    Ok(())
}

/// DataFusion's physical optimizer rules with rtvtk's: [`CountByKey`] (counting group-bys on one
/// integer key, such as Morton cells) just before distribution is enforced, and [`SmallGroups`]
/// (group-bys on small-domain keys such as kind and depth) last. Sessions built
/// elsewhere (Ballista's, for example) run the same queries without them, only slower.
pub fn physical_optimizer_rules() -> Vec<Arc<dyn PhysicalOptimizerRule + Send + Sync>> {
    let mut rules = PhysicalOptimizer::new().rules;
    let at = rules.iter().position(|r| r.name() == "EnsureRequirements" || r.name() == "EnforceDistribution");
    rules.insert(at.unwrap_or(0), Arc::new(CountByKey));
    // Last: it keeps the partial aggregate's partitioning, so distribution is settled first.
    rules.push(Arc::new(SmallGroups));
    rules
}

/// Registers one open dataset's tables under `name` (`NAME.rays`, ...); with `unqualified`, also
/// as `rays`, `trees`, ...: `rays`, `trees`, `ray_paths`, `attributes` (the manifest's key/value
/// attributes: camera, image size, scene name) and every table of the manifest.
pub async fn register_dataset(ctx: &SessionContext, name: &str, ds: &Arc<Dataset>, unqualified: bool) -> Result<()> {
    let valid = !name.is_empty()
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        && !name.starts_with(|c: char| c.is_ascii_digit());
    if !valid {
        return Err(Error::BadName { name: name.to_string() });
    }
    let catalog_name = ctx.state().config().options().catalog.default_catalog.clone();
    if let Some(catalog) = ctx.catalog(&catalog_name) {
        catalog.register_schema(name, Arc::new(MemorySchemaProvider::new()))?;
    }
    // `ray_paths` marks the rays that reached an emitter: it needs a sound `lights` table.
    let ray_paths: Arc<dyn TableProvider> = match RayPathsTable::new(ds.clone()) {
        Ok(t) => Arc::new(t),
        Err(e) => Arc::new(Unavailable::new("ray_paths", ray_paths_schema(), format!("it is made from {e}"))),
    };
    let mut tables: Vec<(String, Arc<dyn TableProvider>)> =
        vec![("rays".into(), Arc::new(RaysTable::new(ds.clone()))), ("ray_paths".into(), ray_paths)];
    if !ds.table_names().iter().any(|n| n == ATTRIBUTES_TABLE) {
        tables.push((ATTRIBUTES_TABLE.into(), attributes_table(ds)?));
    }
    // `trees` and every whole-dataset table the recording wrote (`triangles`, `lights`,
    // `bvh_nodes`, ...), with its file's schema checked against the known one (`store::scene`)
    // and the manifest's now and the file checked whole before its first scan; a table that
    // fails either is unavailable alone, and a query of it says why.
    let recorded = ds.table_names().into_iter().filter(|n| !["rays", "trees", "ray_paths"].contains(&n.as_str()));
    for table in std::iter::once("trees".to_string()).chain(recorded) {
        if let Some(provider) = recorded_table(ds, &table)? {
            tables.push((table, provider));
        }
    }
    for (table_name, table) in tables {
        ctx.register_table(TableReference::partial(name, table_name.as_str()), table.clone())?;
        if unqualified {
            ctx.register_table(table_name.as_str(), table)?;
        }
    }
    Ok(())
}

/// The table of a dataset's manifest attributes.
pub const ATTRIBUTES_TABLE: &str = "attributes";

/// `attributes(key, value)`: the manifest's attributes (camera, image size, scene, ...), so that
/// a client of a service reads them as it reads any table.
fn attributes_table(ds: &Dataset) -> Result<Arc<dyn TableProvider>> {
    let attrs = &ds.manifest().attributes;
    let batch = attributes_batch(attrs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|e| Error::DataFusion(e.into()))?;
    Ok(Arc::new(datafusion::datasource::MemTable::try_new(attributes_schema(), vec![vec![batch]])?))
}

/// The schema of the `attributes` table.
pub(crate) fn attributes_schema() -> SchemaRef {
    use arrow::datatypes::{DataType, Field, Schema};
    Arc::new(Schema::new(vec![Field::new("key", DataType::Utf8, false), Field::new("value", DataType::Utf8, false)]))
}

/// The `attributes` table's rows.
pub(crate) fn attributes_batch<'a>(
    pairs: impl Iterator<Item = (&'a str, &'a str)>,
) -> std::result::Result<RecordBatch, arrow::error::ArrowError> {
    let (keys, values): (Vec<&str>, Vec<&str>) = pairs.unzip();
    RecordBatch::try_new(
        attributes_schema(),
        vec![Arc::new(arrow::array::StringArray::from(keys)), Arc::new(arrow::array::StringArray::from(values))],
    )
}

/// A table the recording wrote, as SQL sees it: `trees` (every segment's tree file) or a
/// whole-dataset table (`triangles`, `lights`, a renderer's own, ...): a Parquet listing over
/// its files with its checked schema, or [`Unavailable`] naming why when its schema, size or file
/// is wrong; `None` for a table the dataset does not hold. What registration and a decoded plan
/// of a distributed engine both build.
pub(crate) fn recorded_table(ds: &Arc<Dataset>, table: &str) -> Result<Option<Arc<dyn TableProvider>>> {
    let (path, extension, schema) = if table == "trees" {
        (ds.dir().join("segments"), ".trees.parquet", store::tree_schema())
    } else {
        match (ds.table_schema(table), ds.table_path(table)) {
            (Ok(Some(schema)), Some(path)) => (path, ".parquet", schema),
            (Err(e), _) => {
                let schema = store::scene::known_table_schema(table)
                    .unwrap_or_else(|| Arc::new(arrow::datatypes::Schema::empty()));
                return Ok(Some(Arc::new(Unavailable::new(table, schema, e.to_string()))));
            }
            _ => return Ok(None),
        }
    };
    let inner = listing(&path, extension, schema)?;
    Ok(Some(Arc::new(Verified { ds: ds.clone(), table: table.to_string(), inner })))
}

/// A recorded table whose files are checked whole before its first scan (sizes, checksums and
/// schemas, which the dataset remembers: `Dataset::verify_table`, `Dataset::verify_trees`), so a
/// corrupted file is refused naming the table instead of being read; then `inner` scans as it
/// would.
pub(crate) struct Verified {
    pub(crate) ds: Arc<Dataset>,
    pub(crate) table: String,
    inner: Arc<dyn TableProvider>,
}

impl Verified {
    fn verify(&self) -> std::result::Result<(), String> {
        let checked = if self.table == "trees" {
            (0..self.ds.manifest().segments.len()).try_for_each(|i| self.ds.verify_trees(i))
        } else {
            self.ds.verify_table(&self.table).map(|_| ())
        };
        checked.map_err(|e| e.to_string())
    }
}

impl std::fmt::Debug for Verified {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Verified({}, {})", self.ds.dir().display(), self.table)
    }
}

#[async_trait::async_trait]
impl TableProvider for Verified {
    fn schema(&self) -> SchemaRef {
        self.inner.schema()
    }

    fn table_type(&self) -> datafusion::datasource::TableType {
        self.inner.table_type()
    }

    fn supports_filters_pushdown(
        &self,
        filters: &[&datafusion::logical_expr::Expr],
    ) -> datafusion::error::Result<Vec<datafusion::logical_expr::TableProviderFilterPushDown>> {
        self.inner.supports_filters_pushdown(filters)
    }

    async fn scan(
        &self,
        state: &dyn datafusion::catalog::Session,
        projection: Option<&Vec<usize>>,
        filters: &[datafusion::logical_expr::Expr],
        limit: Option<usize>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        self.verify().map_err(|message| {
            datafusion::error::DataFusionError::Plan(store::unavailable(&format!("table `{}`", self.table), message))
        })?;
        self.inner.scan(state, projection, filters, limit).await
    }
}

/// A Parquet listing table over the files under `path` ending in `extension`, of `schema`.
fn listing(path: &Path, extension: &str, schema: SchemaRef) -> Result<Arc<dyn TableProvider>> {
    let mut text = path.to_string_lossy().to_string();
    if path.is_dir() && !text.ends_with('/') {
        text.push('/');
    }
    let url = ListingTableUrl::parse(&text)?;
    let options = ListingOptions::new(Arc::new(ParquetFormat::default())).with_file_extension(extension);
    let config = ListingTableConfig::new(url).with_listing_options(options).with_schema(schema);
    Ok(Arc::new(ListingTable::try_new(config)?))
}

/// Schema of `ray_paths`: each ray's path from its root as kind letters.
fn ray_paths_schema() -> SchemaRef {
    use arrow::datatypes::{DataType, Field, Schema};
    Arc::new(Schema::new(vec![
        Field::new(store::scene::col::TREE_ID, DataType::UInt64, false),
        Field::new("ray", DataType::UInt32, false),
        Field::new("depth", DataType::UInt16, false),
        Field::new("path", DataType::Utf8, false),
    ]))
}

/// The letter of a kind in a path: C camera, S shadow, D diffuse, R specular (reflection),
/// T transmission, X any registered kind.
fn kind_letter(kind: store::Kind) -> char {
    match kind {
        store::Kind::CAMERA => 'C',
        store::Kind::SHADOW => 'S',
        store::Kind::DIFFUSE => 'D',
        store::Kind::SPECULAR => 'R',
        store::Kind::TRANSMISSION => 'T',
        _ => 'X',
    }
}

/// `ray_paths` of one segment: for every ray, the letters of the kinds from its root down to it,
/// space separated, with `L` appended when the ray hit an emitter (`C D D S L`: a shadow ray that
/// reached the light after two bounces). Built a segment at a time.
struct PathPartition {
    ds: Arc<Dataset>,
    segment: usize,
    schema: SchemaRef,
    emitters: Arc<std::collections::HashSet<u32>>,
}

impl std::fmt::Debug for PathPartition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PathPartition({}, segment {})", self.ds.dir().display(), self.segment)
    }
}

impl PathPartition {
    fn batches(&self) -> store::Result<Vec<RecordBatch>> {
        use arrow::array::{ArrayBuilder, StringBuilder, UInt16Builder, UInt32Builder, UInt64Builder};
        let mut out = Vec::new();
        let (mut ids, mut rays, mut depths, mut paths) =
            (UInt64Builder::new(), UInt32Builder::new(), UInt16Builder::new(), StringBuilder::new());
        let mut prefix: Vec<String> = Vec::new();
        for tree in self.ds.segment_trees(self.segment)? {
            let tree = tree?;
            prefix.clear();
            for r in &tree.rays {
                let mut p = match r.parent {
                    Some(q) => {
                        let mut s = prefix.get(q as usize).cloned().unwrap_or_default();
                        s.push(' ');
                        s
                    }
                    None => String::new(),
                };
                p.push(kind_letter(r.kind));
                let mut shown = p.clone();
                if r.prim.is_some_and(|q| self.emitters.contains(&q)) {
                    shown.push_str(" L");
                }
                ids.append_value(tree.info.id.0);
                rays.append_value(r.index);
                depths.append_value(r.depth);
                paths.append_value(&shown);
                prefix.push(p);
            }
            if ids.len() >= 64 * 1024 {
                out.push(self.finish(&mut ids, &mut rays, &mut depths, &mut paths)?);
            }
        }
        if !ids.is_empty() {
            out.push(self.finish(&mut ids, &mut rays, &mut depths, &mut paths)?);
        }
        Ok(out)
    }

    fn finish(
        &self,
        ids: &mut arrow::array::UInt64Builder,
        rays: &mut arrow::array::UInt32Builder,
        depths: &mut arrow::array::UInt16Builder,
        paths: &mut arrow::array::StringBuilder,
    ) -> store::Result<RecordBatch> {
        RecordBatch::try_new(
            self.schema.clone(),
            vec![Arc::new(ids.finish()), Arc::new(rays.finish()), Arc::new(depths.finish()), Arc::new(paths.finish())],
        )
        .map_err(|e| store::Error::Arrow { context: "ray_paths".into(), source: e })
    }
}

/// The `ray_paths` table of a dataset (emitters from its `lights` table): one partition per
/// segment, built when read.
pub(crate) struct RayPathsTable {
    pub(crate) ds: Arc<Dataset>,
    emitters: Arc<std::collections::HashSet<u32>>,
}

impl std::fmt::Debug for RayPathsTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RayPathsTable({})", self.ds.dir().display())
    }
}

impl RayPathsTable {
    pub(crate) fn new(ds: Arc<Dataset>) -> Result<Self> {
        use arrow::array::AsArray;
        let mut emitters = std::collections::HashSet::new();
        if let Some(lights) = ds.table("lights")?
            && let Some(prims) =
                lights.column_by_name("prim").and_then(|c| c.as_primitive_opt::<arrow::datatypes::UInt32Type>())
        {
            emitters.extend(prims.values().iter().copied());
        }
        Ok(Self { ds, emitters: Arc::new(emitters) })
    }

    /// The scan of the columns `projection` (all when None).
    pub(crate) fn exec(&self, projection: Option<Vec<usize>>) -> datafusion::error::Result<RayPathsExec> {
        let full = ray_paths_schema();
        let schema = match &projection {
            Some(p) => Arc::new(full.project(p)?),
            None => full.clone(),
        };
        let partitions = self.ds.manifest().segments.len().max(1);
        let properties = Arc::new(PlanProperties::new(
            EquivalenceProperties::new(schema.clone()),
            Partitioning::UnknownPartitioning(partitions),
            EmissionType::Incremental,
            Boundedness::Bounded,
        ));
        Ok(RayPathsExec { ds: self.ds.clone(), emitters: self.emitters.clone(), projection, schema, properties })
    }
}

#[async_trait::async_trait]
impl TableProvider for RayPathsTable {
    fn schema(&self) -> SchemaRef {
        ray_paths_schema()
    }

    fn table_type(&self) -> datafusion::datasource::TableType {
        datafusion::datasource::TableType::Base
    }

    async fn scan(
        &self,
        _state: &dyn datafusion::catalog::Session,
        projection: Option<&Vec<usize>>,
        _filters: &[datafusion::logical_expr::Expr],
        _limit: Option<usize>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        Ok(Arc::new(self.exec(projection.cloned())?))
    }
}

/// Reads `ray_paths`: partition `i` is segment `i`'s paths.
#[derive(Clone)]
pub(crate) struct RayPathsExec {
    ds: Arc<Dataset>,
    emitters: Arc<std::collections::HashSet<u32>>,
    pub(crate) projection: Option<Vec<usize>>,
    schema: SchemaRef,
    properties: Arc<PlanProperties>,
}

impl RayPathsExec {
    pub(crate) fn dataset(&self) -> &Arc<Dataset> {
        &self.ds
    }

    /// Partition `partition`'s paths (what `execute` runs; the task context is not needed).
    pub(crate) fn read(&self, partition: usize) -> SendableRecordBatchStream {
        let part = PathPartition {
            ds: self.ds.clone(),
            segment: partition,
            schema: ray_paths_schema(),
            emitters: self.emitters.clone(),
        };
        let batches = if partition < self.ds.manifest().segments.len() { part.batches() } else { Ok(Vec::new()) };
        let projection = self.projection.clone();
        let batches = batches.and_then(|b| {
            b.into_iter()
                .map(|b| match &projection {
                    Some(p) => b
                        .project(p)
                        .map_err(|e| store::Error::Arrow { context: "ray_paths projection".into(), source: e }),
                    None => Ok(b),
                })
                .collect::<store::Result<Vec<_>>>()
        });
        stream(&self.schema, batches.map(|b| b.into_iter().map(Ok)))
    }
}

impl std::fmt::Debug for RayPathsExec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RayPathsExec({})", self.ds.dir().display())
    }
}

impl DisplayAs for RayPathsExec {
    fn fmt_as(&self, _t: DisplayFormatType, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let names: Vec<&str> = self.schema.fields().iter().map(|f| f.name().as_str()).collect();
        write!(f, "RayPathsExec: dataset={}, projection=[{}]", self.ds.dir().display(), names.join(", "))
    }
}

impl ExecutionPlan for RayPathsExec {
    fn name(&self) -> &str {
        "RayPathsExec"
    }

    fn properties(&self) -> &Arc<PlanProperties> {
        &self.properties
    }

    fn children(&self) -> Vec<&Arc<dyn ExecutionPlan>> {
        Vec::new()
    }

    fn apply_expressions(
        &self,
        _f: &mut dyn FnMut(&Arc<dyn PhysicalExpr>) -> datafusion::error::Result<TreeNodeRecursion>,
    ) -> datafusion::error::Result<TreeNodeRecursion> {
        Ok(TreeNodeRecursion::Continue)
    }

    fn with_new_children(
        self: Arc<Self>,
        _children: Vec<Arc<dyn ExecutionPlan>>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        Ok(self)
    }

    fn execute(
        &self,
        partition: usize,
        _ctx: Arc<TaskContext>,
    ) -> datafusion::error::Result<SendableRecordBatchStream> {
        Ok(self.read(partition))
    }
}
