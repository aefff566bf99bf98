//! The `rays` table: a scan through the store that reads only the projected columns and uses the
//! tree index to skip what filters rule out.
//!
//! Filters on `tree_id`, `pixel_x`, `pixel_y`, `sample`, `depth`, `ray` and `kind` (comparisons with
//! constants, `IN` lists, `BETWEEN`, and `OR`s of them on one column) are pushed down:
//! - segments are skipped by their tree-id range and their per-kind, per-depth ray counts;
//! - within a segment, the tree table picks the trees whose id, pixel, sample and deepest ray can
//!   match, and only their rows are read (the row groups and pages outside them are not touched).
//!
//! The pruning is conservative (DataFusion still applies every filter to the rows read), and
//! `EXPLAIN` shows what it pushed and how much it kept: `RaysScanExec: ... pushed=[tree_id = 7],
//! segments=1/12, trees=1/23692797, rows=6/100000002`.
//!
//! `pixel_x`, `pixel_y` and `sample` are not stored with the rays: the scan adds them from the tree
//! table (only when the query uses them).

use std::collections::BTreeSet;
use std::sync::Arc;
use store::scene::col;

use arrow::array::{Array, AsArray, RecordBatch, RecordBatchOptions, UInt32Array};
use arrow::datatypes::{SchemaRef, UInt64Type};
use datafusion::catalog::Session;
use datafusion::common::ScalarValue;
use datafusion::common::tree_node::TreeNodeRecursion;
use datafusion::datasource::{TableProvider, TableType};
use datafusion::error::DataFusionError;
use datafusion::execution::TaskContext;
use datafusion::logical_expr::{Expr, Operator, TableProviderFilterPushDown};
use datafusion::physical_expr::{EquivalenceProperties, PhysicalExpr};
use datafusion::physical_plan::execution_plan::{Boundedness, EmissionType};
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlan, Partitioning, PlanProperties, SendableRecordBatchStream,
};
use store::{Dataset, RaySelection, SegmentAccess, TreeEntry};

use store::TREE_COLUMNS;

/// The `rays` table of a dataset (any encoding).
pub(crate) struct RaysTable {
    pub(crate) ds: Arc<Dataset>,
    schema: SchemaRef,
}

impl std::fmt::Debug for RaysTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RaysTable({})", self.ds.dir().display())
    }
}

impl RaysTable {
    pub(crate) fn new(ds: Arc<Dataset>) -> Self {
        let schema = with_site_text(&store::ray_table_schema(&ds.ray_schema()), has_sites(&ds));
        Self { ds, schema }
    }
}

#[async_trait::async_trait]
impl TableProvider for RaysTable {
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }

    fn table_type(&self) -> TableType {
        TableType::Base
    }

    fn supports_filters_pushdown(
        &self,
        filters: &[&Expr],
    ) -> datafusion::error::Result<Vec<TableProviderFilterPushDown>> {
        Ok(filters
            .iter()
            .map(|f| match constraint(f) {
                Some(_) => TableProviderFilterPushDown::Inexact,
                None => TableProviderFilterPushDown::Unsupported,
            })
            .collect())
    }

    async fn scan(
        &self,
        _state: &dyn Session,
        projection: Option<&Vec<usize>>,
        filters: &[Expr],
        _limit: Option<usize>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        let schema = match projection {
            Some(p) => Arc::new(self.schema.project(p)?),
            None => self.schema.clone(),
        };
        let pushdown = Pushdown::of(filters);
        let ds = self.ds.clone();
        // Loading tree tables reads files: off the async threads.
        let parts = tokio::task::spawn_blocking(move || pushdown.plan(&ds).map(|p| (pushdown, p)))
            .await
            .map_err(|e| DataFusionError::External(Box::new(e)))?
            .map_err(|e| DataFusionError::External(Box::new(e)))?;
        Ok(Arc::new(RaysScanExec::new(self.ds.clone(), schema, parts.0, parts.1)))
    }
}

/// What a filter says about one column.
#[derive(Clone, Debug, PartialEq)]
enum Constraint {
    /// The column's value lies in one of these inclusive ranges.
    Range(&'static str, Vec<(u64, u64)>),
    /// The ray's kind is one of these names.
    Kind(BTreeSet<String>),
}

fn column_of(e: &Expr) -> Option<&str> {
    match e {
        Expr::Column(c) => Some(c.name.as_str()),
        // A cast keeps equal values equal and fails (NULL) on values it cannot hold, so a filter
        // through it still implies the constraint on the column.
        Expr::Cast(c) => column_of(&c.expr),
        Expr::TryCast(c) => column_of(&c.expr),
        _ => None,
    }
}

fn int_of(v: &ScalarValue) -> Option<i128> {
    Some(match v {
        ScalarValue::Int8(Some(x)) => i128::from(*x),
        ScalarValue::Int16(Some(x)) => i128::from(*x),
        ScalarValue::Int32(Some(x)) => i128::from(*x),
        ScalarValue::Int64(Some(x)) => i128::from(*x),
        ScalarValue::UInt8(Some(x)) => i128::from(*x),
        ScalarValue::UInt16(Some(x)) => i128::from(*x),
        ScalarValue::UInt32(Some(x)) => i128::from(*x),
        ScalarValue::UInt64(Some(x)) => i128::from(*x),
        ScalarValue::Dictionary(_, v) => return int_of(v),
        _ => return None,
    })
}

fn str_of(v: &ScalarValue) -> Option<String> {
    match v {
        ScalarValue::Utf8(Some(s)) | ScalarValue::LargeUtf8(Some(s)) | ScalarValue::Utf8View(Some(s)) => {
            Some(s.clone())
        }
        ScalarValue::Dictionary(_, v) => str_of(v),
        _ => None,
    }
}

fn literal(e: &Expr) -> Option<&ScalarValue> {
    match e {
        Expr::Literal(v, _) => Some(v),
        _ => None,
    }
}

pub(crate) fn range_column(name: &str) -> Option<&'static str> {
    RaySelection::column(name)
}

/// The inclusive range of u64 values an integer comparison `col op v` allows (None: no value).
fn compare_range(op: Operator, v: i128) -> Option<Option<(u64, u64)>> {
    let clamp = |x: i128| x.clamp(0, i128::from(u64::MAX)) as u64;
    let (lo, hi) = match op {
        Operator::Eq => (v, v),
        Operator::Lt => (i128::MIN, v - 1),
        Operator::LtEq => (i128::MIN, v),
        Operator::Gt => (v + 1, i128::MAX),
        Operator::GtEq => (v, i128::MAX),
        _ => return None,
    };
    Some((lo <= hi && hi >= 0 && lo <= i128::from(u64::MAX)).then(|| (clamp(lo), clamp(hi))))
}

fn swap(op: Operator) -> Option<Operator> {
    Some(match op {
        Operator::Eq => Operator::Eq,
        Operator::Lt => Operator::Gt,
        Operator::LtEq => Operator::GtEq,
        Operator::Gt => Operator::Lt,
        Operator::GtEq => Operator::LtEq,
        _ => return None,
    })
}

/// What a filter constrains, when it is one the scan can use.
fn constraint(e: &Expr) -> Option<Constraint> {
    match e {
        Expr::BinaryExpr(b) if b.op == Operator::Or => match (constraint(&b.left)?, constraint(&b.right)?) {
            (Constraint::Range(a, mut x), Constraint::Range(c, y)) if a == c => {
                x.extend(y);
                Some(Constraint::Range(a, x))
            }
            (Constraint::Kind(mut x), Constraint::Kind(y)) => {
                x.extend(y);
                Some(Constraint::Kind(x))
            }
            _ => None,
        },
        Expr::BinaryExpr(b) => {
            let (col, v, op) = match (column_of(&b.left), literal(&b.right), column_of(&b.right), literal(&b.left)) {
                (Some(c), Some(v), _, _) => (c, v, b.op),
                (_, _, Some(c), Some(v)) => (c, v, swap(b.op)?),
                _ => return None,
            };
            if col == "kind" {
                return (op == Operator::Eq).then(|| str_of(v)).flatten().map(|k| Constraint::Kind([k].into()));
            }
            let col = range_column(col)?;
            let r = compare_range(op, int_of(v)?)?;
            Some(Constraint::Range(col, r.into_iter().collect()))
        }
        Expr::InList(l) if !l.negated => {
            let col = column_of(&l.expr)?;
            if col == "kind" {
                let names = l.list.iter().map(|x| literal(x).and_then(str_of)).collect::<Option<BTreeSet<_>>>()?;
                return Some(Constraint::Kind(names));
            }
            let col = range_column(col)?;
            let mut out = Vec::new();
            for x in &l.list {
                if let Some(r) = compare_range(Operator::Eq, int_of(literal(x)?)?)? {
                    out.push(r);
                }
            }
            Some(Constraint::Range(col, out))
        }
        Expr::Between(b) if !b.negated => {
            let col = range_column(column_of(&b.expr)?)?;
            let (lo, hi) = (int_of(literal(&b.low)?)?, int_of(literal(&b.high)?)?);
            let lo = compare_range(Operator::GtEq, lo)?;
            let hi = compare_range(Operator::LtEq, hi)?;
            let r = match (lo, hi) {
                (Some((a, _)), Some((_, b))) if a <= b => vec![(a, b)],
                _ => Vec::new(),
            };
            Some(Constraint::Range(col, r))
        }
        _ => None,
    }
}

/// The filters the scan uses, as one selection.
#[derive(Clone, Debug, Default)]
pub(crate) struct Pushdown {
    pub(crate) selection: RaySelection,
    /// The pushed filters as SQL, for `EXPLAIN`.
    pub(crate) shown: Vec<String>,
}

impl Pushdown {
    fn of(filters: &[Expr]) -> Self {
        let mut p = Pushdown::default();
        for f in filters {
            let Some(c) = constraint(f) else { continue };
            p.shown.push(f.to_string());
            match c {
                Constraint::Range(col, r) => p.selection.keep(col, r),
                Constraint::Kind(k) => p.selection.keep_kinds(k),
            }
        }
        p
    }

    /// The segments (and rows within them) that can hold matching rays.
    fn plan(&self, ds: &Dataset) -> store::Result<Vec<SegmentAccess>> {
        Ok(ds.plan(&self.selection)?.segments)
    }
}

/// Rows per batch of a `rays` scan: DataFusion's own default batch size. Against 64K-row batches
/// (`store::READ_BATCH_ROWS`) on a 25M-ray trace of 12 segments, release build: a two-column scan
/// peaks at 104-109 instead of 183-189 MB in the same time (0.34-0.37 s), origins and `t`
/// decode in 1.24 instead of 1.58 s, octants, check-style and per-pixel queries unchanged, and a
/// 5.9M-group `tree_id` group-by under a 300 MiB limit peaks 6% higher (605 against 570 MB).
const SCAN_BATCH_ROWS: usize = 8 * 1024;

/// Reads the `rays` table's partitions: one per segment left after pruning.
#[derive(Clone)]
pub(crate) struct RaysScanExec {
    pub(crate) ds: Arc<Dataset>,
    pub(crate) schema: SchemaRef,
    pub(crate) pushdown: Pushdown,
    pub(crate) parts: Vec<SegmentAccess>,
    properties: Arc<PlanProperties>,
    /// The `sites` table's texts, read once per plan by the first partition that needs them.
    site_texts: std::sync::OnceLock<Arc<arrow::array::StringArray>>,
}

impl std::fmt::Debug for RaysScanExec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RaysScanExec({})", self.ds.dir().display())
    }
}

impl RaysScanExec {
    pub(crate) fn new(ds: Arc<Dataset>, schema: SchemaRef, pushdown: Pushdown, parts: Vec<SegmentAccess>) -> Self {
        let properties = Arc::new(PlanProperties::new(
            EquivalenceProperties::new(schema.clone()),
            Partitioning::UnknownPartitioning(parts.len().max(1)),
            EmissionType::Incremental,
            Boundedness::Bounded,
        ));
        Self { ds, schema, pushdown, parts, properties, site_texts: std::sync::OnceLock::new() }
    }

    /// Whether a partition is answered from its segment's per-kind, per-depth ray counts: when the
    /// query uses no column but `kind` and `depth` (counts, group-bys and filters on them), those
    /// counts are the two columns run-length encoded, up to row order (which SQL leaves open), so
    /// the ray file is not read. Datasets without the counts (or with counts that do not add up to
    /// the segment's rays) are read.
    fn answered_by_counts(&self, part: &SegmentAccess) -> bool {
        let seg = &self.ds.manifest().segments[part.segment];
        let total: u64 = seg.stats.rays_by_kind_depth.values().flatten().sum();
        part.rows.is_none()
            && self.schema.fields().iter().all(|f| f.name() == "kind" || f.name() == "depth")
            && total == seg.rays.rows
    }

    /// A partition's `kind` and `depth` columns from its segment's counts: only the (kind, depth)
    /// pairs the pushed filters can keep (DataFusion still applies the filters).
    fn count_batches(&self, part: &SegmentAccess) -> Box<dyn Iterator<Item = store::Result<RecordBatch>> + Send> {
        const BATCH: u64 = 64 * 1024;
        let seg = &self.ds.manifest().segments[part.segment];
        let sel = &self.pushdown.selection;
        let mut runs: Vec<(String, u16, u64)> = Vec::new();
        for (kind, counts) in &seg.stats.rays_by_kind_depth {
            if !sel.keeps_kind(kind) {
                continue;
            }
            for (d, &n) in counts.iter().enumerate() {
                if let Ok(d16) = u16::try_from(d)
                    && n > 0
                    && store::selection::in_ranges(sel.ranges(col::DEPTH), d as u64)
                {
                    let mut left = n;
                    while left > 0 {
                        let take = left.min(BATCH);
                        runs.push((kind.clone(), d16, take));
                        left -= take;
                    }
                }
            }
        }
        let schema = self.schema.clone();
        Box::new(runs.into_iter().map(move |(kind, depth, n)| {
            let n = n as usize;
            let cols = schema
                .fields()
                .iter()
                .map(|f| -> Arc<dyn Array> {
                    if f.name() == "depth" {
                        Arc::new(arrow::array::UInt16Array::from(vec![depth; n]))
                    } else {
                        let keys = arrow::array::UInt8Array::from(vec![0u8; n]);
                        let values = Arc::new(arrow::array::StringArray::from(vec![kind.as_str()]));
                        Arc::new(arrow::array::DictionaryArray::new(keys, values))
                    }
                })
                .collect();
            let options = RecordBatchOptions::new().with_row_count(Some(n));
            RecordBatch::try_new_with_options(schema.clone(), cols, &options).map_err(|e| store::Error::Arrow {
                context: "kind and depth from the segment's counts".into(),
                source: e,
            })
        }))
    }

    /// Partition `partition`'s rows (what `execute` runs; the task context is not needed).
    pub(crate) fn read(&self, partition: usize) -> SendableRecordBatchStream {
        stream(&self.schema, self.batches(partition))
    }

    /// The batches of one partition, with the tree columns added and the `site` ids as text.
    fn batches(&self, partition: usize) -> store::Result<Box<dyn Iterator<Item = store::Result<RecordBatch>> + Send>> {
        let stored = with_site_text(&self.schema, false);
        let it = self.stored_batches(partition, stored)?;
        let text =
            self.schema.field_with_name(store::scene::SITE_COLUMN).is_ok_and(|f| f.data_type() == &site_text_type());
        if !text {
            return Ok(it);
        }
        let texts = match self.site_texts.get() {
            Some(t) => t.clone(),
            None => {
                let t = site_texts(&self.ds)?;
                self.site_texts.get_or_init(|| t).clone()
            }
        };
        let schema = self.schema.clone();
        let path = self.ds.dir().join("tables/sites.parquet");
        Ok(Box::new(it.map(move |b| {
            let b = b?;
            let cols = schema
                .fields()
                .iter()
                .map(|f| {
                    let c = b
                        .column_by_name(f.name())
                        .cloned()
                        .ok_or_else(|| corrupt(&path, format!("no column {}", f.name())))?;
                    if f.name() != store::scene::SITE_COLUMN {
                        return Ok(c);
                    }
                    let keys = c
                        .as_primitive_opt::<arrow::datatypes::UInt32Type>()
                        .cloned()
                        .ok_or_else(|| corrupt(&path, "`site` is not UInt32".into()))?;
                    arrow::array::DictionaryArray::try_new(keys, texts.clone())
                        .map(|d| Arc::new(d) as Arc<dyn Array>)
                        .map_err(|e| corrupt(&path, format!("a site id is not in the sites table: {e}")))
                })
                .collect::<store::Result<Vec<_>>>()?;
            let options = RecordBatchOptions::new().with_row_count(Some(b.num_rows()));
            RecordBatch::try_new_with_options(schema.clone(), cols, &options)
                .map_err(|e| store::Error::Arrow { context: "rays with their sites".into(), source: e })
        })))
    }

    /// The batches of one partition as stored (`site` as its ids), with the tree columns added,
    /// in `schema` (the scan's, `site` as stored).
    fn stored_batches(
        &self,
        partition: usize,
        schema: SchemaRef,
    ) -> store::Result<Box<dyn Iterator<Item = store::Result<RecordBatch>> + Send>> {
        let Some(part) = self.parts.get(partition) else {
            return Ok(Box::new(std::iter::empty()));
        };
        if self.answered_by_counts(part) {
            return Ok(self.count_batches(part));
        }
        let names: Vec<String> = schema.fields().iter().map(|f| f.name().clone()).collect();
        let base = self.ds.ray_schema();
        let virtual_cols: Vec<&str> =
            TREE_COLUMNS.into_iter().filter(|c| names.iter().any(|n| n == c) && base.index_of(c).is_err()).collect();
        let mut read: Vec<String> = names.iter().filter(|n| !virtual_cols.contains(&n.as_str())).cloned().collect();
        if !virtual_cols.is_empty() && !read.iter().any(|n| n == col::TREE_ID) {
            read.push(col::TREE_ID.into());
        }
        let rows = part.rows.as_deref().map(|v| v.as_slice());
        let it = self.ds.segment_columns_in(part.segment, &read, rows, SCAN_BATCH_ROWS)?;
        if virtual_cols.is_empty() {
            return Ok(it);
        }
        // The segment's tree table is read when its first batch is (engines start every
        // partition's stream at once): only the segments being read hold theirs.
        let mut entries = part.entries.clone();
        let (ds, segment) = (self.ds.clone(), part.segment);
        let path = self.ds.dir().join(&self.ds.manifest().segments[part.segment].rays.path);
        Ok(Box::new(it.map(move |b| {
            let b = b?;
            let entries: &[TreeEntry] = match &mut entries {
                Some(e) => e,
                None => {
                    ds.verify_trees(segment)?;
                    entries.insert(ds.segment_tree_entries(segment)?)
                }
            };
            let ids = b
                .column_by_name(col::TREE_ID)
                .and_then(|c| c.as_primitive_opt::<UInt64Type>())
                .ok_or_else(|| corrupt(&path, "no tree_id column".into()))?;
            let (mut px, mut py, mut ps) =
                (Vec::with_capacity(b.num_rows()), Vec::with_capacity(b.num_rows()), Vec::with_capacity(b.num_rows()));
            let mut last: Option<&TreeEntry> = None;
            for &id in ids.values() {
                let e = match last {
                    Some(e) if e.info.id.0 == id => e,
                    _ => {
                        let pos = entries
                            .binary_search_by_key(&id, |e| e.info.id.0)
                            .map_err(|_| corrupt(&path, format!("tree {id} is not in the segment's tree table")))?;
                        &entries[pos]
                    }
                };
                last = Some(e);
                px.push(e.info.pixel[0]);
                py.push(e.info.pixel[1]);
                ps.push(e.info.sample);
            }
            let mut extra = [Some(px), Some(py), Some(ps)];
            let cols = schema
                .fields()
                .iter()
                .map(|f| {
                    if let Some(k) = TREE_COLUMNS.iter().position(|c| c == f.name())
                        && b.column_by_name(f.name()).is_none()
                    {
                        let v = extra[k].take().unwrap_or_default();
                        return Ok(Arc::new(UInt32Array::from(v)) as Arc<dyn Array>);
                    }
                    b.column_by_name(f.name()).cloned().ok_or_else(|| corrupt(&path, format!("no column {}", f.name())))
                })
                .collect::<store::Result<Vec<_>>>()?;
            let options = RecordBatchOptions::new().with_row_count(Some(b.num_rows()));
            RecordBatch::try_new_with_options(schema.clone(), cols, &options)
                .map_err(|e| store::Error::Arrow { context: "rays with tree columns".into(), source: e })
        })))
    }
}

/// The type SQL shows the `site` column in: each site's text, dictionary-encoded over its id.
fn site_text_type() -> arrow::datatypes::DataType {
    use arrow::datatypes::DataType;
    DataType::Dictionary(Box::new(DataType::UInt32), Box::new(DataType::Utf8))
}

/// Whether `ds` recorded sites: a `site` payload column and a `sites` table whose columns can
/// be read (a broken one leaves `site` as its ids: the rays stay queryable).
fn has_sites(ds: &Dataset) -> bool {
    ds.ray_schema().field_with_name(store::scene::SITE_COLUMN).is_ok()
        && matches!(ds.table_schema(store::scene::SITES_TABLE), Ok(Some(_)))
}

/// `schema` with its `site` column as text (`text`) or as the stored ids.
fn with_site_text(schema: &SchemaRef, text: bool) -> SchemaRef {
    use arrow::datatypes::{DataType, Field, Schema};
    let Ok(i) = schema.index_of(store::scene::SITE_COLUMN) else { return schema.clone() };
    let t = if text { site_text_type() } else { DataType::UInt32 };
    if schema.field(i).data_type() == &t {
        return schema.clone();
    }
    let mut fields: Vec<Arc<Field>> = schema.fields().iter().cloned().collect();
    let f = fields[i].as_ref().clone().with_data_type(t);
    fields[i] = Arc::new(f);
    Arc::new(Schema::new_with_metadata(fields, schema.metadata().clone()))
}

/// Each site's text (`file:line function`), by site id, from the `sites` table.
fn site_texts(ds: &Dataset) -> store::Result<Arc<arrow::array::StringArray>> {
    let Some(t) = ds.table(store::scene::SITES_TABLE)? else {
        return Ok(Arc::new(arrow::array::StringArray::from(Vec::<String>::new())));
    };
    let bad = |m: &str| corrupt(&ds.dir().join("tables/sites.parquet"), m.to_string());
    let ids = t
        .column_by_name("site_id")
        .and_then(|c| c.as_primitive_opt::<arrow::datatypes::UInt32Type>())
        .ok_or_else(|| bad("no site_id"))?;
    let files = t.column_by_name("file").and_then(|c| c.as_string_opt::<i32>()).ok_or_else(|| bad("no file"))?;
    let lines = t
        .column_by_name("line")
        .and_then(|c| c.as_primitive_opt::<arrow::datatypes::UInt32Type>())
        .ok_or_else(|| bad("no line"))?;
    let funcs =
        t.column_by_name("function").and_then(|c| c.as_string_opt::<i32>()).ok_or_else(|| bad("no function"))?;
    let mut texts = vec![String::new(); t.num_rows()];
    for r in 0..t.num_rows() {
        let site = store::scene::Site {
            file: files.value(r).to_string(),
            line: lines.value(r),
            column: 0,
            function: funcs.is_valid(r).then(|| funcs.value(r).to_string()),
        };
        let id = ids.value(r) as usize;
        if id >= texts.len() {
            return Err(bad(&format!("site_id {id} out of range (the table has {} rows)", t.num_rows())));
        }
        texts[id] = site.text();
    }
    Ok(Arc::new(arrow::array::StringArray::from(texts)))
}

fn corrupt(path: &std::path::Path, message: String) -> store::Error {
    store::Error::Corrupt { path: path.to_path_buf(), what: "ray file".into(), message }
}

impl DisplayAs for RaysScanExec {
    fn fmt_as(&self, _t: DisplayFormatType, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let m = self.ds.manifest();
        let names: Vec<&str> = self.schema.fields().iter().map(|f| f.name().as_str()).collect();
        let trees: u64 = self.parts.iter().map(|p| p.trees).sum();
        let rays: u64 = self.parts.iter().map(|p| p.rays).sum();
        let counted = self.parts.iter().filter(|p| self.answered_by_counts(p)).count();
        write!(
            f,
            "RaysScanExec: dataset={}, encoding={}, projection=[{}], pushed=[{}], segments={}/{}{}, trees={}/{}, rows={}/{}",
            self.ds.dir().display(),
            self.ds.encoding().name(),
            names.join(", "),
            self.pushdown.shown.join(", "),
            self.parts.len(),
            m.segments.len(),
            if counted > 0 { format!(" ({counted} from their kind/depth counts)") } else { String::new() },
            trees,
            self.ds.tree_count(),
            rays,
            self.ds.ray_count(),
        )
    }
}

impl ExecutionPlan for RaysScanExec {
    fn name(&self) -> &str {
        "RaysScanExec"
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
        _context: Arc<TaskContext>,
    ) -> datafusion::error::Result<SendableRecordBatchStream> {
        Ok(self.read(partition))
    }
}

/// A record-batch stream of the batches a store call yields (or of its error).
pub(crate) fn stream<I>(
    schema: &arrow::datatypes::SchemaRef,
    batches: store::Result<I>,
) -> datafusion::execution::SendableRecordBatchStream
where
    I: Iterator<Item = store::Result<arrow::array::RecordBatch>> + Send + 'static,
{
    let external = |e: store::Error| datafusion::error::DataFusionError::External(Box::new(e));
    let batches: Box<dyn Iterator<Item = datafusion::error::Result<arrow::array::RecordBatch>> + Send> = match batches {
        Ok(it) => Box::new(it.map(move |b| b.map_err(external))),
        Err(e) => Box::new(std::iter::once(Err(external(e)))),
    };
    Box::pin(datafusion::physical_plan::stream::RecordBatchStreamAdapter::new(
        schema.clone(),
        futures::stream::iter(batches),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use datafusion::prelude::{col, lit};

    #[test]
    fn comparisons_become_ranges() {
        assert_eq!(constraint(&col("tree_id").eq(lit(7u64))), Some(Constraint::Range("tree_id", vec![(7, 7)])));
        assert_eq!(constraint(&lit(3i64).lt(col("depth"))), Some(Constraint::Range("depth", vec![(4, u64::MAX)])));
        assert_eq!(constraint(&col("depth").lt(lit(0i64))), Some(Constraint::Range("depth", vec![])));
        assert_eq!(constraint(&col("depth").gt_eq(lit(-5i64))), Some(Constraint::Range("depth", vec![(0, u64::MAX)])));
        assert_eq!(
            constraint(&col("pixel_x").between(lit(2i64), lit(4i64))),
            Some(Constraint::Range("pixel_x", vec![(2, 4)]))
        );
        assert_eq!(
            constraint(&col("sample").in_list(vec![lit(1i64), lit(5i64)], false)),
            Some(Constraint::Range("sample", vec![(1, 1), (5, 5)]))
        );
        assert_eq!(
            constraint(&col("kind").eq(lit("shadow")).or(col("kind").eq(lit("camera")))),
            Some(Constraint::Kind(["camera".to_string(), "shadow".to_string()].into()))
        );
        // Not usable: other columns, inequality, negation, mixed columns, float literals.
        assert_eq!(constraint(&col("t").lt(lit(1.0))), None);
        assert_eq!(constraint(&col("depth").not_eq(lit(1i64))), None);
        assert_eq!(constraint(&col("depth").in_list(vec![lit(1i64)], true)), None);
        assert_eq!(constraint(&col("depth").eq(lit(1i64)).or(col("sample").eq(lit(1i64)))), None);
        assert_eq!(constraint(&col("depth").lt(lit(2.5))), None);
    }

    #[test]
    fn conjunctions_intersect() {
        let p = Pushdown::of(&[
            col("depth").gt_eq(lit(2i64)),
            col("depth").lt(lit(5i64)),
            col("kind").in_list(vec![lit("shadow"), lit("diffuse")], false),
            col("kind").eq(lit("shadow")),
        ]);
        assert_eq!(p.selection.ranges("depth"), Some(&[(2, 4)][..]));
        assert_eq!(p.selection.kinds(), Some(&["shadow".to_string()].into()));
        assert_eq!(p.selection.min("depth"), 2, "a lower bound on depth prunes trees by their deepest ray");
        assert!(store::selection::in_ranges(Some(&[(1, 3), (7, 9)]), 8));
        assert!(!store::selection::in_ranges(Some(&[(1, 3), (7, 9)]), 5));
        assert_eq!(store::selection::normalize(vec![(5, 6), (1, 2), (3, 3)]), vec![(1, 3), (5, 6)]);
    }
}
