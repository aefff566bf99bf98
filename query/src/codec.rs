//! rtvtk's tables, operators and ray functions as DataFusion protobuf extensions, so plans over
//! trace datasets can cross the wire (a Ballista cluster, or any engine built on
//! `datafusion-proto`):
//!
//! - logical: the `rays` and `ray_paths` table providers (a dataset's path; every node opens it),
//!   the tables the recording wrote (`trees`, `triangles`, ...: the dataset's path and the
//!   table's name, each node checks the files whole before its scan) and in-memory tables (the
//!   analyses' helper tables, as Arrow IPC);
//! - physical: [`RaysScanExec`](crate::scan) with its pruned segment plan (segments, row ranges,
//!   pushed filters: the scheduler's pruning is not redone per task), `RayPathsExec` and
//!   [`SmallGroupsExec`] (as the stock partial aggregate it replaces, rebuilt on decoding); a
//!   segment scan rewritten by [`SliceableScans`](crate::SliceableScans) as the scan and the
//!   partitions of the file groups left to the task;
//!   [`CountByKeyExec`](crate::CountByKeyExec) is not carried: it gathers every partition into one
//!   task, so a distributed plan keeps the stock two-phase aggregation there;
//! - functions: every ray function and aggregate, the scene-dependent ones (`morton3`,
//!   `aims_at_light`) with their scene's bounds and emitter triangles, so a node needs no function
//!   registry and no access to the scene's `lights` table.
//!
//! Anything else goes to the fallback codecs (Ballista's own, for its shuffle operators).
//! rtvtk's nodes start with [`MAGIC`], which no protobuf message can start with (field 0).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use datafusion::common::TableReference;
use datafusion::datasource::TableProvider;
use datafusion::error::{DataFusionError, Result};
use datafusion::execution::TaskContext;
use datafusion::logical_expr::{AggregateUDF, Extension, LogicalPlan, ScalarUDF};
use datafusion::physical_plan::ExecutionPlan;
use datafusion::physical_plan::empty::EmptyExec;
use datafusion::physical_plan::execution_plan::{ChildrenPropertiesMode, ReplaceChildrenOptions};
use datafusion_proto::logical_plan::{DefaultLogicalExtensionCodec, LogicalExtensionCodec};
use datafusion_proto::physical_plan::{
    DefaultPhysicalExtensionCodec, PhysicalExtensionCodec, PhysicalPlanDecodeContext, PhysicalProtoConverterExtension,
};
use datafusion_proto::protobuf::PhysicalPlanNode;
use prost::Message;
use store::Dataset;

use crate::functions::{SceneContext, is_ray_aggregate, ray_function_scene};
use crate::scan::{Pushdown, RaysScanExec, RaysTable, range_column};
use crate::small_groups::SmallGroupsExec;
use crate::tables::{RayPathsExec, RayPathsTable};
use store::SegmentAccess;

/// The first bytes of every rtvtk node.
pub const MAGIC: &[u8] = b"\0rtvtk1";

const TABLE_RAYS: u8 = b'R';
const TABLE_PATHS: u8 = b'P';
const TABLE_MEMORY: u8 = b'M';
const TABLE_RECORDED: u8 = b'V';
const EXEC_SCAN: u8 = b's';
const EXEC_PATHS: u8 = b'p';
const EXEC_SMALL_GROUPS: u8 = b'g';
const EXEC_SEGMENT_FILES: u8 = b'f';
const FUNCTION: u8 = b'F';
const AGGREGATE: u8 = b'A';

#[derive(Clone, PartialEq, Message)]
struct TableNode {
    #[prost(string, tag = "1")]
    path: String,
}

/// A table the recording wrote (`trees`, `triangles`, ...): the dataset and the table's name.
#[derive(Clone, PartialEq, Message)]
struct RecordedNode {
    #[prost(string, tag = "1")]
    path: String,
    #[prost(string, tag = "2")]
    table: String,
}

/// An in-memory table (the analyses' small helper tables): each partition as an Arrow IPC stream.
#[derive(Clone, PartialEq, Message)]
struct MemoryNode {
    #[prost(bytes = "vec", repeated, tag = "1")]
    partitions: Vec<Vec<u8>>,
}

#[derive(Clone, PartialEq, Message)]
struct RangeNode {
    #[prost(string, tag = "1")]
    column: String,
    /// Inclusive (low, high) pairs.
    #[prost(uint64, repeated, tag = "2")]
    bounds: Vec<u64>,
}

#[derive(Clone, PartialEq, Message)]
struct PartNode {
    #[prost(uint64, tag = "1")]
    segment: u64,
    #[prost(bool, tag = "2")]
    some_rows: bool,
    /// Half-open (start, end) pairs of the rows to read, when not all.
    #[prost(uint64, repeated, tag = "3")]
    rows: Vec<u64>,
    #[prost(uint64, tag = "4")]
    trees: u64,
    #[prost(uint64, tag = "5")]
    rays: u64,
}

#[derive(Clone, PartialEq, Message)]
struct ScanNode {
    #[prost(string, tag = "1")]
    path: String,
    #[prost(string, repeated, tag = "2")]
    columns: Vec<String>,
    #[prost(message, repeated, tag = "3")]
    ranges: Vec<RangeNode>,
    #[prost(bool, tag = "4")]
    some_kinds: bool,
    #[prost(string, repeated, tag = "5")]
    kinds: Vec<String>,
    #[prost(string, repeated, tag = "6")]
    shown: Vec<String>,
    #[prost(message, repeated, tag = "7")]
    parts: Vec<PartNode>,
}

/// A segment scan as the file scan a distributed engine slices ([`crate::SliceableScans`]): the
/// scan (an rtvtk node) and the scan partitions of the file groups the task kept.
#[derive(Clone, PartialEq, Message)]
struct SegmentFilesNode {
    #[prost(bytes = "vec", tag = "1")]
    leaf: Vec<u8>,
    /// Files per group; the groups' partitions follow one another in `partitions`.
    #[prost(uint32, repeated, tag = "2")]
    group_sizes: Vec<u32>,
    #[prost(uint64, repeated, tag = "3")]
    partitions: Vec<u64>,
    #[prost(bool, tag = "4")]
    some_limit: bool,
    #[prost(uint64, tag = "5")]
    limit: u64,
}

#[derive(Clone, PartialEq, Message)]
struct PathsNode {
    #[prost(string, tag = "1")]
    path: String,
    #[prost(bool, tag = "2")]
    some_projection: bool,
    #[prost(uint32, repeated, tag = "3")]
    projection: Vec<u32>,
}

#[derive(Clone, PartialEq, Message)]
struct SceneNode {
    #[prost(bool, tag = "1")]
    has_scene: bool,
    /// min x, y, z, max x, y, z; empty when the scene has no bounds.
    #[prost(double, repeated, tag = "2")]
    bounds: Vec<f64>,
    /// Nine coordinates per emitter triangle.
    #[prost(double, repeated, tag = "3")]
    lights: Vec<f64>,
    /// The dataset directory `scene_hit` reads the triangles from; empty when none.
    #[prost(string, tag = "4")]
    triangles_dir: String,
    /// Why the scene's `lights` table is unavailable; empty when it is not broken.
    #[prost(string, tag = "5")]
    lights_unavailable: String,
}

/// The codec: rtvtk's nodes, everything else through `logical` / `physical`.
#[derive(Debug)]
pub struct TraceCodec {
    logical: Arc<dyn LogicalExtensionCodec>,
    physical: Arc<dyn PhysicalExtensionCodec>,
}

impl Default for TraceCodec {
    fn default() -> Self {
        Self::with_fallback(Arc::new(DefaultLogicalExtensionCodec {}), Arc::new(DefaultPhysicalExtensionCodec {}))
    }
}

impl TraceCodec {
    /// rtvtk's nodes, and what they do not cover through these codecs.
    pub fn with_fallback(logical: Arc<dyn LogicalExtensionCodec>, physical: Arc<dyn PhysicalExtensionCodec>) -> Self {
        Self { logical, physical }
    }
}

fn ours(buf: &[u8]) -> Option<(u8, &[u8])> {
    let rest = buf.strip_prefix(MAGIC)?;
    let (&tag, body) = rest.split_first()?;
    Some((tag, body))
}

fn frame(tag: u8, msg: &impl Message, buf: &mut Vec<u8>) {
    buf.extend_from_slice(MAGIC);
    buf.push(tag);
    msg.encode(buf).unwrap_or_else(|_| unreachable!("a Vec grows as needed"));
}

fn bad(what: &str, e: impl std::fmt::Display) -> DataFusionError {
    DataFusionError::Internal(format!("rtvtk codec: cannot decode {what}: {e}"))
}

fn bad_encode(what: &str, e: impl std::fmt::Display) -> DataFusionError {
    DataFusionError::Internal(format!("rtvtk codec: cannot encode {what}: {e}"))
}

fn external(e: impl std::error::Error + Send + Sync + 'static) -> DataFusionError {
    DataFusionError::External(Box::new(e))
}

/// Datasets opened by decoded plans, by path, reopened when the directory changes (its
/// modification time moves when the manifest is replaced).
fn open_dataset(path: &str) -> Result<Arc<Dataset>> {
    type Cache = Mutex<HashMap<PathBuf, (Option<std::time::SystemTime>, Arc<Dataset>)>>;
    static CACHE: std::sync::OnceLock<Cache> = std::sync::OnceLock::new();
    let path = Path::new(path);
    let stamp = std::fs::metadata(path).and_then(|m| m.modified()).ok();
    let cache = CACHE.get_or_init(Default::default);
    if let Ok(c) = cache.lock()
        && let Some((s, ds)) = c.get(path)
        && *s == stamp
        && stamp.is_some()
    {
        return Ok(ds.clone());
    }
    let ds = Arc::new(Dataset::open(path).map_err(external)?);
    if let Ok(mut c) = cache.lock() {
        c.insert(path.to_path_buf(), (stamp, ds.clone()));
    }
    Ok(ds)
}

fn path_text(ds: &Dataset) -> Result<String> {
    ds.dir()
        .to_str()
        .map(str::to_string)
        .ok_or_else(|| DataFusionError::NotImplemented(format!("dataset path {} is not UTF-8", ds.dir().display())))
}

fn encode_scene(scene: Option<&SceneContext>) -> SceneNode {
    match scene {
        None => SceneNode {
            has_scene: false,
            bounds: Vec::new(),
            lights: Vec::new(),
            triangles_dir: String::new(),
            lights_unavailable: String::new(),
        },
        Some(s) => SceneNode {
            has_scene: true,
            bounds: s.bounds.map(|(lo, hi)| [lo, hi].concat()).unwrap_or_default(),
            lights: s.lights.iter().flat_map(|t| t.iter().flatten().copied()).collect(),
            triangles_dir: s.triangles.as_ref().map(|t| t.dir.to_string_lossy().into_owned()).unwrap_or_default(),
            lights_unavailable: s.lights_unavailable.clone().unwrap_or_default(),
        },
    }
}

fn decode_scene(n: &SceneNode) -> Result<SceneContext> {
    let bounds = match n.bounds.as_slice() {
        [] => None,
        [a, b, c, d, e, f] => Some(([*a, *b, *c], [*d, *e, *f])),
        other => return Err(bad("a scene", format!("{} bound values, expected 6", other.len()))),
    };
    if !n.lights.len().is_multiple_of(9) {
        return Err(bad("a scene", format!("{} light coordinates, not a multiple of 9", n.lights.len())));
    }
    let lights =
        n.lights.chunks_exact(9).map(|c| [[c[0], c[1], c[2]], [c[3], c[4], c[5]], [c[6], c[7], c[8]]]).collect();
    let triangles = (!n.triangles_dir.is_empty())
        .then(|| crate::functions::SceneTriangles::shared(std::path::Path::new(&n.triangles_dir)));
    let lights_unavailable = (!n.lights_unavailable.is_empty()).then(|| n.lights_unavailable.clone());
    Ok(SceneContext { bounds, lights, lights_unavailable, triangles })
}

fn encode_scan(exec: &RaysScanExec) -> Result<ScanNode> {
    Ok(ScanNode {
        path: path_text(&exec.ds)?,
        columns: exec.schema.fields().iter().map(|f| f.name().clone()).collect(),
        ranges: exec
            .pushdown
            .selection
            .constrained()
            .map(|(c, r)| RangeNode { column: c.to_string(), bounds: r.iter().flat_map(|&(a, b)| [a, b]).collect() })
            .collect(),
        some_kinds: exec.pushdown.selection.kinds().is_some(),
        kinds: exec.pushdown.selection.kinds().into_iter().flatten().cloned().collect(),
        shown: exec.pushdown.shown.clone(),
        parts: exec
            .parts
            .iter()
            .map(|p| PartNode {
                segment: p.segment as u64,
                some_rows: p.rows.is_some(),
                rows: p.rows.iter().flat_map(|r| r.iter().flat_map(|r| [r.start, r.end])).collect(),
                trees: p.trees,
                rays: p.rays,
            })
            .collect(),
    })
}

fn decode_scan(n: ScanNode) -> Result<RaysScanExec> {
    let ds = open_dataset(&n.path)?;
    let table = RaysTable::new(ds.clone());
    let full = table.schema();
    let indices = n
        .columns
        .iter()
        .map(|c| full.index_of(c).map_err(|_| bad("a rays scan", format!("no column `{c}` in {}", n.path))))
        .collect::<Result<Vec<_>>>()?;
    let schema = Arc::new(full.project(&indices)?);
    let mut selection = store::RaySelection::all();
    for r in &n.ranges {
        let column = range_column(&r.column).ok_or_else(|| bad("a rays scan", format!("range column {}", r.column)))?;
        selection.keep(column, r.bounds.chunks_exact(2).map(|p| (p[0], p[1])).collect());
    }
    if n.some_kinds {
        selection.keep_kinds(n.kinds.iter().cloned().collect());
    }
    let segments = ds.manifest().segments.len();
    let parts = n
        .parts
        .iter()
        .map(|p| {
            let segment = usize::try_from(p.segment).ok().filter(|s| *s < segments).ok_or_else(|| {
                bad("a rays scan", format!("segment {} of a dataset with {segments} ({})", p.segment, n.path))
            })?;
            Ok(SegmentAccess {
                segment,
                rows: p.some_rows.then(|| Arc::new(p.rows.chunks_exact(2).map(|r| r[0]..r[1]).collect())),
                trees: p.trees,
                rays: p.rays,
                entries: None,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(RaysScanExec::new(ds, schema, Pushdown { selection, shown: n.shown }, parts))
}

fn decode_function(name: &str, body: &[u8]) -> Result<Arc<ScalarUDF>> {
    let node = SceneNode::decode(body).map_err(|e| bad(name, e))?;
    let scene = Arc::new(if node.has_scene { decode_scene(&node)? } else { SceneContext::default() });
    crate::functions::ray_scalar_functions(scene)
        .into_iter()
        .find(|f| f.name() == name)
        .map(Arc::new)
        .ok_or_else(|| bad(name, "not a ray function"))
}

fn decode_aggregate(name: &str) -> Result<Arc<AggregateUDF>> {
    crate::functions::ray_aggregates()
        .into_iter()
        .find(|f| f.name() == name)
        .map(Arc::new)
        .ok_or_else(|| bad(name, "not a ray aggregate"))
}

/// A ray function from rtvtk's bytes, or what `fallback` makes of bytes that are not rtvtk's.
fn decode_udf(
    name: &str,
    buf: &[u8],
    fallback: impl FnOnce(&[u8]) -> Result<Arc<ScalarUDF>>,
) -> Result<Arc<ScalarUDF>> {
    match ours(buf) {
        Some((FUNCTION, body)) => decode_function(name, body),
        Some((tag, _)) => Err(bad(name, format!("unknown node {tag}"))),
        None => fallback(buf),
    }
}

/// A ray aggregate from rtvtk's bytes, or what `fallback` makes of bytes that are not rtvtk's.
fn decode_udaf(
    name: &str,
    buf: &[u8],
    fallback: impl FnOnce(&[u8]) -> Result<Arc<AggregateUDF>>,
) -> Result<Arc<AggregateUDF>> {
    match ours(buf) {
        Some((AGGREGATE, _)) => decode_aggregate(name),
        Some((tag, _)) => Err(bad(name, format!("unknown node {tag}"))),
        None => fallback(buf),
    }
}

/// Writes a ray aggregate's tag; false for any other aggregate.
fn encode_aggregate(node: &AggregateUDF, buf: &mut Vec<u8>) -> bool {
    let ray = is_ray_aggregate(node);
    if ray {
        frame(AGGREGATE, &TableNode::default(), buf);
    }
    ray
}

fn encode_function(node: &ScalarUDF, buf: &mut Vec<u8>) -> bool {
    match ray_function_scene(node) {
        Some(scene) => {
            frame(FUNCTION, &encode_scene(scene.as_deref()), buf);
            true
        }
        None => false,
    }
}

impl LogicalExtensionCodec for TraceCodec {
    fn try_decode(&self, buf: &[u8], inputs: &[LogicalPlan], ctx: &TaskContext) -> Result<Extension> {
        self.logical.try_decode(buf, inputs, ctx)
    }

    fn try_encode(&self, node: &Extension, buf: &mut Vec<u8>) -> Result<()> {
        self.logical.try_encode(node, buf)
    }

    fn try_decode_table_provider(
        &self,
        buf: &[u8],
        table_ref: &TableReference,
        schema: arrow::datatypes::SchemaRef,
        ctx: &TaskContext,
    ) -> Result<Arc<dyn TableProvider>> {
        match ours(buf) {
            Some((tag @ (TABLE_RAYS | TABLE_PATHS), body)) => {
                let node = TableNode::decode(body).map_err(|e| bad("a table", e))?;
                let ds = open_dataset(&node.path)?;
                if tag == TABLE_RAYS {
                    Ok(Arc::new(RaysTable::new(ds)))
                } else {
                    Ok(Arc::new(RayPathsTable::new(ds).map_err(external)?))
                }
            }
            Some((TABLE_RECORDED, body)) => {
                let n = RecordedNode::decode(body).map_err(|e| bad("a recorded table", e))?;
                let ds = open_dataset(&n.path)?;
                crate::tables::recorded_table(&ds, &n.table)
                    .map_err(external)?
                    .ok_or_else(|| bad("a recorded table", format!("{} has no table {}", n.path, n.table)))
            }
            Some((TABLE_MEMORY, body)) => {
                let n = MemoryNode::decode(body).map_err(|e| bad("an in-memory table", e))?;
                let mut partitions = Vec::with_capacity(n.partitions.len());
                for p in &n.partitions {
                    let reader = arrow::ipc::reader::StreamReader::try_new(std::io::Cursor::new(p), None)?;
                    partitions.push(reader.collect::<std::result::Result<Vec<_>, _>>()?);
                }
                Ok(Arc::new(datafusion::datasource::MemTable::try_new(schema, partitions)?))
            }
            Some((tag, _)) => Err(bad("a table", format!("unknown node {tag}"))),
            None => self.logical.try_decode_table_provider(buf, table_ref, schema, ctx),
        }
    }

    fn try_encode_table_provider(
        &self,
        table_ref: &TableReference,
        node: Arc<dyn TableProvider>,
        buf: &mut Vec<u8>,
    ) -> Result<()> {
        if let Some(t) = node.as_ref().downcast_ref::<datafusion::datasource::MemTable>() {
            let schema = t.schema();
            let mut partitions = Vec::with_capacity(t.batches.len());
            for p in &t.batches {
                let batches = p.try_read().map_err(|_| bad_encode("an in-memory table", "it is being written"))?;
                let mut bytes = Vec::new();
                let mut w = arrow::ipc::writer::StreamWriter::try_new(&mut bytes, &schema)?;
                for b in batches.iter() {
                    w.write(b)?;
                }
                w.finish()?;
                drop(w);
                partitions.push(bytes);
            }
            frame(TABLE_MEMORY, &MemoryNode { partitions }, buf);
            return Ok(());
        }
        if let Some(t) = node.as_ref().downcast_ref::<RaysTable>() {
            frame(TABLE_RAYS, &TableNode { path: path_text(&t.ds)? }, buf);
            return Ok(());
        }
        if let Some(t) = node.as_ref().downcast_ref::<RayPathsTable>() {
            frame(TABLE_PATHS, &TableNode { path: path_text(&t.ds)? }, buf);
            return Ok(());
        }
        if let Some(t) = node.as_ref().downcast_ref::<crate::tables::Verified>() {
            frame(TABLE_RECORDED, &RecordedNode { path: path_text(&t.ds)?, table: t.table.clone() }, buf);
            return Ok(());
        }
        self.logical.try_encode_table_provider(table_ref, node, buf)
    }

    fn try_decode_file_format(
        &self,
        buf: &[u8],
        ctx: &TaskContext,
    ) -> Result<Arc<dyn datafusion::datasource::file_format::FileFormatFactory>> {
        self.logical.try_decode_file_format(buf, ctx)
    }

    fn try_encode_file_format(
        &self,
        buf: &mut Vec<u8>,
        node: Arc<dyn datafusion::datasource::file_format::FileFormatFactory>,
    ) -> Result<()> {
        self.logical.try_encode_file_format(buf, node)
    }

    fn try_decode_udf(&self, name: &str, buf: &[u8]) -> Result<Arc<ScalarUDF>> {
        decode_udf(name, buf, |b| self.logical.try_decode_udf(name, b))
    }

    fn try_encode_udf(&self, node: &ScalarUDF, buf: &mut Vec<u8>) -> Result<()> {
        if encode_function(node, buf) { Ok(()) } else { self.logical.try_encode_udf(node, buf) }
    }

    fn try_decode_udaf(&self, name: &str, buf: &[u8]) -> Result<Arc<AggregateUDF>> {
        decode_udaf(name, buf, |b| self.logical.try_decode_udaf(name, b))
    }

    fn try_encode_udaf(&self, node: &AggregateUDF, buf: &mut Vec<u8>) -> Result<()> {
        if encode_aggregate(node, buf) { Ok(()) } else { self.logical.try_encode_udaf(node, buf) }
    }
}

impl PhysicalExtensionCodec for TraceCodec {
    fn try_decode(
        &self,
        buf: &[u8],
        inputs: &[Arc<dyn ExecutionPlan>],
        ctx: &TaskContext,
        proto_converter: &dyn PhysicalProtoConverterExtension,
    ) -> Result<Arc<dyn ExecutionPlan>> {
        match ours(buf) {
            Some((EXEC_SCAN, body)) => {
                Ok(Arc::new(decode_scan(ScanNode::decode(body).map_err(|e| bad("a rays scan", e))?)?))
            }
            Some((EXEC_PATHS, body)) => {
                let n = PathsNode::decode(body).map_err(|e| bad("a ray_paths scan", e))?;
                let table = RayPathsTable::new(open_dataset(&n.path)?).map_err(external)?;
                let projection = n.some_projection.then(|| n.projection.iter().map(|&i| i as usize).collect());
                Ok(Arc::new(table.exec(projection)?))
            }
            Some((EXEC_SEGMENT_FILES, body)) => {
                let what = "a segment file scan";
                let n = SegmentFilesNode::decode(body).map_err(|e| bad(what, e))?;
                let leaf = PhysicalExtensionCodec::try_decode(self, &n.leaf, &[], ctx, proto_converter)?;
                let leaf = crate::sliced::SegmentLeaf::of(&leaf)
                    .ok_or_else(|| bad(what, format!("its scan is a {}", leaf.name())))?;
                let count = leaf.partitions();
                let mut partitions = n.partitions.iter();
                let mut groups = Vec::with_capacity(n.group_sizes.len());
                for &size in &n.group_sizes {
                    let group = partitions
                        .by_ref()
                        .take(size as usize)
                        .map(|&p| {
                            usize::try_from(p)
                                .ok()
                                .filter(|p| *p < count)
                                .ok_or_else(|| bad(what, format!("partition {p} of a scan with {count}")))
                        })
                        .collect::<Result<Vec<_>>>()?;
                    if group.len() != size as usize {
                        return Err(bad(what, "fewer partitions than its groups hold"));
                    }
                    groups.push(group);
                }
                let limit = match n.some_limit {
                    true => Some(usize::try_from(n.limit).map_err(|e| bad(what, e))?),
                    false => None,
                };
                Ok(crate::sliced::file_scan(leaf, &groups, limit))
            }
            Some((EXEC_SMALL_GROUPS, body)) => {
                // The stock partial aggregate it stands for, over a placeholder input.
                let node = PhysicalPlanNode::decode(body).map_err(|e| bad("a small-domain group-by", e))?;
                let agg = proto_converter.proto_to_execution_plan(&node, &PhysicalPlanDecodeContext::new(ctx, self))?;
                let [input] = inputs else {
                    return Err(bad("a small-domain group-by", format!("{} inputs, not one", inputs.len())));
                };
                let agg = agg.replace_children(
                    vec![input.clone()],
                    ReplaceChildrenOptions::new(ChildrenPropertiesMode::Recompute),
                )?;
                // Where the decoded aggregate no longer qualifies, it runs as it is (same answers).
                Ok(match SmallGroupsExec::replacing(&agg)? {
                    Some(exec) => Arc::new(exec),
                    None => agg,
                })
            }
            Some((tag, _)) => Err(bad("an operator", format!("unknown node {tag}"))),
            None => self.physical.try_decode(buf, inputs, ctx, proto_converter),
        }
    }

    fn try_encode(
        &self,
        node: Arc<dyn ExecutionPlan>,
        buf: &mut Vec<u8>,
        proto_converter: &dyn PhysicalProtoConverterExtension,
    ) -> Result<()> {
        if let Some(exec) = node.downcast_ref::<RaysScanExec>() {
            frame(EXEC_SCAN, &encode_scan(exec)?, buf);
            return Ok(());
        }
        if let Some(crate::sliced::FileScanParts { files, groups, limit }) = crate::sliced::parts_of(&node) {
            let mut leaf = Vec::new();
            PhysicalExtensionCodec::try_encode(self, files.leaf().plan(), &mut leaf, proto_converter)?;
            let n = SegmentFilesNode {
                leaf,
                group_sizes: groups.iter().map(|g| g.len() as u32).collect(),
                partitions: groups.iter().flatten().map(|&p| p as u64).collect(),
                some_limit: limit.is_some(),
                limit: limit.unwrap_or_default() as u64,
            };
            frame(EXEC_SEGMENT_FILES, &n, buf);
            return Ok(());
        }
        if let Some(exec) = node.downcast_ref::<RayPathsExec>() {
            let projection = exec.projection.as_ref();
            let node = PathsNode {
                path: path_text(exec.dataset())?,
                some_projection: projection.is_some(),
                projection: projection.iter().flat_map(|p| p.iter().map(|&i| i as u32)).collect(),
            };
            frame(EXEC_PATHS, &node, buf);
            return Ok(());
        }
        if let Some(exec) = node.downcast_ref::<SmallGroupsExec>() {
            // As the partial aggregate it replaces; its input travels as the node's input.
            let placeholder = Arc::new(EmptyExec::new(exec.input().schema()));
            let proto = proto_converter.execution_plan_to_proto(&exec.partial_aggregate(placeholder)?, self)?;
            frame(EXEC_SMALL_GROUPS, &proto, buf);
            return Ok(());
        }
        self.physical.try_encode(node, buf, proto_converter)
    }

    fn try_decode_udf(&self, name: &str, buf: &[u8]) -> Result<Arc<ScalarUDF>> {
        decode_udf(name, buf, |b| self.physical.try_decode_udf(name, b))
    }

    fn try_encode_udf(&self, node: &ScalarUDF, buf: &mut Vec<u8>) -> Result<()> {
        if encode_function(node, buf) { Ok(()) } else { self.physical.try_encode_udf(node, buf) }
    }

    fn try_decode_udaf(&self, name: &str, buf: &[u8]) -> Result<Arc<AggregateUDF>> {
        decode_udaf(name, buf, |b| self.physical.try_decode_udaf(name, b))
    }

    fn try_encode_udaf(&self, node: &AggregateUDF, buf: &mut Vec<u8>) -> Result<()> {
        if encode_aggregate(node, buf) { Ok(()) } else { self.physical.try_encode_udaf(node, buf) }
    }
}
