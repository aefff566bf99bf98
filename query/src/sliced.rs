//! rtvtk's segment scans as file scans, for engines that hand each task a slice of a scan.
//!
//! The `rays` and `ray_paths` scans have one partition per segment. A distributed engine runs a
//! scan stage as tasks, each owning some of the stage's partitions, and has to cut every leaf of
//! the stage down to those partitions. Ballista 55 does that only for DataFusion's own sources
//! (a `FileScanConfig`'s file groups, in-memory partitions, shuffle reads): any other leaf is
//! left whole, so each of N tasks would read all N segments.
//!
//! [`SliceableScans`] therefore rewrites each segment scan into a `DataSourceExec` over a
//! `FileScanConfig` whose file group `i` is the scan's partition `i` (one "file": the segment's
//! ray file, tagged with the partition it stands for). The engine slices the file groups; the
//! file source ([`SegmentFiles`]) opens a file by running that partition of the scan, with the
//! pruning the planner did (segments, row ranges, pushed filters) unchanged. The codec carries
//! the scan and the task's partitions, so a task's plan names only its own segments.
//!
//! In-process sessions keep the plain scans (nothing slices them there).

use std::any::Any;
use std::sync::Arc;

use datafusion::common::tree_node::{Transformed, TransformedResult, TreeNode, TreeNodeRecursion};
use datafusion::config::ConfigOptions;
use datafusion::datasource::listing::PartitionedFile;
use datafusion::datasource::physical_plan::{
    FileGroup, FileOpenFuture, FileOpener, FileScanConfig, FileScanConfigBuilder, FileSource,
};
use datafusion::datasource::source::DataSourceExec;
use datafusion::datasource::table_schema::TableSchema;
use datafusion::error::{DataFusionError, Result};
use datafusion::execution::object_store::ObjectStoreUrl;
use datafusion::physical_expr::PhysicalExpr;
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_plan::metrics::ExecutionPlanMetricsSet;
use datafusion::physical_plan::{DisplayAs, DisplayFormatType, ExecutionPlan, SendableRecordBatchStream};
use futures::StreamExt;

use crate::scan::RaysScanExec;
use crate::tables::RayPathsExec;

/// A segment scan: the leaf whose partitions become file groups.
#[derive(Clone, Debug)]
pub(crate) enum SegmentLeaf {
    Rays(Arc<RaysScanExec>),
    Paths(Arc<RayPathsExec>),
}

impl SegmentLeaf {
    /// The segment scan `plan` is, if it is one.
    pub(crate) fn of(plan: &Arc<dyn ExecutionPlan>) -> Option<Self> {
        if let Some(p) = plan.downcast_ref::<RaysScanExec>() {
            return Some(Self::Rays(Arc::new(p.clone())));
        }
        plan.downcast_ref::<RayPathsExec>().map(|p| Self::Paths(Arc::new(p.clone())))
    }

    pub(crate) fn plan(&self) -> Arc<dyn ExecutionPlan> {
        match self {
            Self::Rays(p) => p.clone(),
            Self::Paths(p) => p.clone(),
        }
    }

    pub(crate) fn partitions(&self) -> usize {
        self.plan().properties().output_partitioning().partition_count()
    }

    fn read(&self, partition: usize) -> SendableRecordBatchStream {
        match self {
            Self::Rays(p) => p.read(partition),
            Self::Paths(p) => p.read(partition),
        }
    }

    /// The ray file partition `i` reads (path and bytes; the dataset's directory where the
    /// partition reads no segment), for the engine's display and statistics.
    fn file(&self, i: usize) -> (String, u64) {
        let (ds, segment) = match self {
            Self::Rays(p) => (&p.ds, p.parts.get(i).map(|part| part.segment)),
            Self::Paths(p) => (p.dataset(), Some(i)),
        };
        match segment.and_then(|s| ds.manifest().segments.get(s)) {
            Some(seg) => (ds.dir().join(&seg.rays.path).to_string_lossy().into_owned(), seg.rays.bytes),
            None => (ds.dir().to_string_lossy().into_owned(), 0),
        }
    }
}

/// Which partition of its scan a file of a [`SegmentFiles`] scan stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct LeafPartition(usize);

/// The file source of a rewritten segment scan: a file is a partition of the scan.
#[derive(Clone)]
pub struct SegmentFiles {
    leaf: SegmentLeaf,
    table_schema: TableSchema,
    metrics: ExecutionPlanMetricsSet,
}

impl SegmentFiles {
    pub(crate) fn leaf(&self) -> &SegmentLeaf {
        &self.leaf
    }
}

struct SegmentOpener {
    leaf: SegmentLeaf,
}

impl FileOpener for SegmentOpener {
    fn open(&self, file: PartitionedFile) -> Result<FileOpenFuture> {
        let Some(&LeafPartition(i)) = file.extension::<LeafPartition>() else {
            return Err(DataFusionError::Internal(format!(
                "{}: a file of an rtvtk segment scan without the partition it stands for",
                file.object_meta.location
            )));
        };
        if i >= self.leaf.partitions() {
            return Err(DataFusionError::Internal(format!(
                "{}: partition {i} of a scan with {}",
                file.object_meta.location,
                self.leaf.partitions()
            )));
        }
        let stream = self.leaf.read(i);
        Ok(Box::pin(async move { Ok(stream.boxed()) }))
    }
}

impl FileSource for SegmentFiles {
    fn create_file_opener(
        &self,
        _object_store: Arc<dyn datafusion::object_store::ObjectStore>,
        _base_config: &FileScanConfig,
        _partition: usize,
    ) -> Result<Arc<dyn FileOpener>> {
        Ok(Arc::new(SegmentOpener { leaf: self.leaf.clone() }))
    }

    fn table_schema(&self) -> &TableSchema {
        &self.table_schema
    }

    fn with_batch_size(&self, _batch_size: usize) -> Arc<dyn FileSource> {
        Arc::new(self.clone())
    }

    fn metrics(&self) -> &ExecutionPlanMetricsSet {
        &self.metrics
    }

    fn file_type(&self) -> &str {
        "rtvtk_segments"
    }

    fn fmt_extra(&self, t: DisplayFormatType, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, ", reads=")?;
        match &self.leaf {
            SegmentLeaf::Rays(p) => p.fmt_as(t, f),
            SegmentLeaf::Paths(p) => p.fmt_as(t, f),
        }
    }

    /// A file group is one partition of the scan: never split or merged.
    fn supports_repartitioning(&self) -> bool {
        false
    }

    fn repartitioned(
        &self,
        _target_partitions: usize,
        _repartition_file_min_size: usize,
        _output_ordering: Option<datafusion::physical_expr::LexOrdering>,
        _config: &FileScanConfig,
    ) -> Result<Option<FileScanConfig>> {
        Ok(None)
    }

    fn apply_expressions(
        &self,
        _f: &mut dyn FnMut(&Arc<dyn PhysicalExpr>) -> Result<TreeNodeRecursion>,
    ) -> Result<TreeNodeRecursion> {
        Ok(TreeNodeRecursion::Continue)
    }
}

/// The file scan of `leaf`'s partitions, `groups[g]` being the partitions of file group `g`
/// (one each, as [`SliceableScans`] makes them; a task's slice keeps some of the groups).
pub(crate) fn file_scan(leaf: SegmentLeaf, groups: &[Vec<usize>], limit: Option<usize>) -> Arc<DataSourceExec> {
    let file_groups = groups
        .iter()
        .map(|g| {
            FileGroup::new(
                g.iter()
                    .map(|&i| {
                        let (path, bytes) = leaf.file(i);
                        PartitionedFile::new(path, bytes).with_extension(LeafPartition(i))
                    })
                    .collect(),
            )
        })
        .collect();
    let schema = leaf.plan().schema();
    let source = Arc::new(SegmentFiles { leaf, table_schema: TableSchema::from(schema), metrics: Default::default() });
    let config = FileScanConfigBuilder::new(ObjectStoreUrl::local_filesystem(), source)
        .with_file_groups(file_groups)
        .with_limit(limit)
        .build();
    DataSourceExec::from_data_source(config)
}

/// A rewritten segment scan's parts.
pub(crate) struct FileScanParts<'a> {
    pub(crate) files: &'a SegmentFiles,
    /// The file groups, as partitions of the scan.
    pub(crate) groups: Vec<Vec<usize>>,
    /// The row limit pushed into the file scan.
    pub(crate) limit: Option<usize>,
}

/// The parts of `plan` when it is a rewritten segment scan.
pub(crate) fn parts_of(plan: &Arc<dyn ExecutionPlan>) -> Option<FileScanParts<'_>> {
    let exec = plan.downcast_ref::<DataSourceExec>()?;
    let source: &dyn Any = exec.data_source().as_ref();
    let config = source.downcast_ref::<FileScanConfig>()?;
    let files = config.file_source().downcast_ref::<SegmentFiles>()?;
    let groups = config
        .file_groups
        .iter()
        .map(|g| g.files().iter().filter_map(|f| f.extension::<LeafPartition>().map(|p| p.0)).collect())
        .collect();
    Some(FileScanParts { files, groups, limit: config.limit })
}

/// Rewrites every `rays` / `ray_paths` scan into a file scan of one file group per partition,
/// which a distributed engine (Ballista) slices to each task's partitions. For the scheduler's
/// sessions only: in-process plans keep the plain scans.
#[derive(Debug, Default)]
pub struct SliceableScans;

impl PhysicalOptimizerRule for SliceableScans {
    fn optimize(&self, plan: Arc<dyn ExecutionPlan>, _config: &ConfigOptions) -> Result<Arc<dyn ExecutionPlan>> {
        plan.transform_up(|p| match SegmentLeaf::of(&p) {
            Some(leaf) => {
                let groups: Vec<Vec<usize>> = (0..leaf.partitions()).map(|i| vec![i]).collect();
                Ok(Transformed::yes(file_scan(leaf, &groups, None) as Arc<dyn ExecutionPlan>))
            }
            None => Ok(Transformed::no(p)),
        })
        .data()
    }

    fn name(&self) -> &str {
        "SliceableScans"
    }

    fn schema_check(&self) -> bool {
        true
    }
}
