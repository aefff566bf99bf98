//! Counting group-bys on one integer key, the shape of the cell histograms analysts ask for
//! (`SELECT morton3(..) AS m, count(*) FROM rays GROUP BY m`, direction bins, primitive ids):
//! [`CountByKey`] is a physical optimizer rule that replaces DataFusion's two-phase hash
//! aggregation (a partial aggregate per partition, a hash repartition, a final aggregate) by one
//! [`CountByKeyExec`] when every aggregate is a plain `count`.
//!
//! Why: with millions of distinct keys the stock operator's hash tables outgrow the caches, and each
//! row costs several cache misses (control bytes, group index, key, accumulator), twice (partial and
//! final). Here one worker per target partition reads its share of the input partitions, buffers
//! the keys in 256 radix buckets (by the top bits of a hash) and, every few million rows, adds
//! them to the bucket's open-addressing table, one bucket at a time, so that each table (the key
//! and its counts side by side in a slot) is read into cache once per flush rather than missed on
//! every row; the workers' tables are then merged bucket by bucket, in parallel.
//!
//! Memory is charged to the session's memory pool. When the pool refuses a worker more, the
//! worker writes its tables to a spill file in the session's temporary directory (one run, bucket
//! by bucket), empties them and goes on; the merge then reads each bucket's runs back and merges
//! that bucket alone, so it holds about 1/256 of the groups per merging task. Each worker and
//! merging task is held to its share of the limit. Only a share too small for one batch's keys is
//! an error (resources exhausted, naming the operator), never an out-of-memory kill. `EXPLAIN ANALYZE` shows `spill_count` (runs written) and `spilled_bytes`.

use std::borrow::Cow;
use std::fmt;
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Int64Array, RecordBatch, UInt64Array};
use arrow::buffer::NullBuffer;
use arrow::compute::cast;
use arrow::datatypes::{DataType, Int64Type, SchemaRef, UInt64Type};
use datafusion::common::config::ConfigOptions;
use datafusion::common::runtime::SpawnedTask;
use datafusion::common::tree_node::TreeNodeRecursion;
use datafusion::error::{DataFusionError, Result};
use datafusion::execution::memory_pool::{MemoryConsumer, MemoryLimit, MemoryPool, MemoryReservation};
use datafusion::execution::{DiskManager, SpillFile, SpillWriter, TaskContext};
use datafusion::physical_expr::expressions::Literal;
use datafusion::physical_expr::{EquivalenceProperties, PhysicalExpr};
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_plan::aggregates::{AggregateExec, AggregateMode};
use datafusion::physical_plan::execution_plan::{Boundedness, EmissionType};
use datafusion::physical_plan::metrics::{BaselineMetrics, Count, ExecutionPlanMetricsSet, MetricBuilder, MetricsSet};
use datafusion::physical_plan::stream::RecordBatchReceiverStreamBuilder;
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlan, ExecutionPlanProperties, Partitioning, PlanProperties,
    SendableRecordBatchStream,
};
use futures::StreamExt;
use tokio::sync::mpsc::Sender;

use crate::plan_util::{Walk, replace_nodes};

mod merge;
mod spill;
mod table;
use merge::*;
use spill::*;
use table::*;

/// Radix buckets per partition (the top bits of a key's hash).
const BUCKET_BITS: u32 = 8;
const BUCKETS: usize = 1 << BUCKET_BITS;

/// The physical optimizer rule; [`crate::session`] runs it before DataFusion's distribution
/// enforcement, so the plan above it is planned for its single output partition.
#[derive(Debug, Default)]
pub struct CountByKey;

impl PhysicalOptimizerRule for CountByKey {
    fn optimize(&self, plan: Arc<dyn ExecutionPlan>, _config: &ConfigOptions) -> Result<Arc<dyn ExecutionPlan>> {
        replace_nodes(plan, Walk::Down, CountByKeyExec::replacing)
    }

    fn name(&self) -> &str {
        "CountByKey"
    }

    fn schema_check(&self) -> bool {
        true
    }
}

/// What an output count column counts.
#[derive(Clone, Copy, Debug)]
enum Counted {
    /// Every row of the group (`count(*)`, `count(1)`).
    Rows,
    /// The rows where the `i`-th counted expression is not NULL.
    Valid(usize),
}

impl Counted {
    /// Which of a slot's counts (after the key) it is: the row count, then one per expression.
    fn column(self) -> usize {
        match self {
            Counted::Rows => 0,
            Counted::Valid(i) => 1 + i,
        }
    }
}

/// `SELECT key, count(..), .. GROUP BY key` over its input's partitions, one output partition.
#[derive(Debug)]
pub struct CountByKeyExec {
    input: Arc<dyn ExecutionPlan>,
    key: Arc<dyn PhysicalExpr>,
    key_name: String,
    /// Expressions whose non-NULL values are counted (`count(expr)` with a non-literal argument).
    args: Vec<Arc<dyn PhysicalExpr>>,
    /// Per output count column, what it counts, and its name for EXPLAIN.
    outputs: Vec<(Counted, String)>,
    schema: SchemaRef,
    properties: Arc<PlanProperties>,
    metrics: ExecutionPlanMetricsSet,
}

/// Keys this operator takes: 32- and 64-bit integers. Narrower keys have at most 65,536 groups,
/// which DataFusion's own aggregation already keeps in cache (and with less memory).
fn is_wide_integer(t: &DataType) -> bool {
    matches!(t, DataType::Int32 | DataType::Int64 | DataType::UInt32 | DataType::UInt64)
}

impl CountByKeyExec {
    /// The replacement of an aggregation (its final half, over the partial half, or a single-phase
    /// one) when it groups by one integer expression and computes only plain counts; None when it
    /// does not have that shape.
    fn replacing(node: &Arc<dyn ExecutionPlan>) -> Result<Option<Self>> {
        let Some(agg) = node.downcast_ref::<AggregateExec>() else { return Ok(None) };
        let raw = match agg.mode() {
            AggregateMode::Final | AggregateMode::FinalPartitioned => {
                match agg.input().downcast_ref::<AggregateExec>() {
                    Some(p) if *p.mode() == AggregateMode::Partial => p,
                    _ => return Ok(None),
                }
            }
            AggregateMode::Single | AggregateMode::SinglePartitioned => agg,
            _ => return Ok(None),
        };
        let group = raw.group_expr();
        let out = agg.schema();
        if group.has_grouping_set()
            || group.expr().len() != 1
            || agg.limit_options().is_some()
            || raw.limit_options().is_some()
            || raw.filter_expr().iter().any(Option::is_some)
            || out.fields().len() != 1 + raw.aggr_expr().len()
        {
            return Ok(None);
        }
        let (key, key_name) = group.expr()[0].clone();
        let input = raw.input().clone();
        let key_type = key.data_type(&input.schema())?;
        if !is_wide_integer(&key_type) || out.field(0).data_type() != &key_type {
            return Ok(None);
        }
        let mut args: Vec<Arc<dyn PhysicalExpr>> = Vec::new();
        let mut outputs = Vec::new();
        for (i, a) in raw.aggr_expr().iter().enumerate() {
            let exprs = a.expressions();
            if a.fun().name() != "count"
                || a.is_distinct()
                || !a.order_bys().is_empty()
                || exprs.len() != 1
                || out.field(1 + i).data_type() != &DataType::Int64
            {
                return Ok(None);
            }
            let counted = match exprs[0].downcast_ref::<Literal>() {
                Some(l) if !l.value().is_null() => Counted::Rows,
                _ => {
                    args.push(exprs[0].clone());
                    Counted::Valid(args.len() - 1)
                }
            };
            outputs.push((counted, a.name().to_string()));
        }
        if args.len() > 64 {
            return Ok(None);
        }
        let properties = Arc::new(PlanProperties::new(
            EquivalenceProperties::new(out.clone()),
            Partitioning::UnknownPartitioning(1),
            EmissionType::Final,
            Boundedness::Bounded,
        ));
        Ok(Some(Self {
            input,
            key,
            key_name,
            args,
            outputs,
            schema: out,
            properties,
            metrics: ExecutionPlanMetricsSet::new(),
        }))
    }

    fn stride(&self) -> usize {
        2 + self.args.len()
    }
}

impl DisplayAs for CountByKeyExec {
    fn fmt_as(&self, _t: DisplayFormatType, f: &mut fmt::Formatter) -> fmt::Result {
        let aggr: Vec<&str> = self.outputs.iter().map(|(_, n)| n.as_str()).collect();
        write!(
            f,
            "CountByKeyExec: gby=[{} as {}], aggr=[{}], buckets={BUCKETS}",
            self.key,
            self.key_name,
            aggr.join(", ")
        )
    }
}

impl ExecutionPlan for CountByKeyExec {
    fn name(&self) -> &str {
        "CountByKeyExec"
    }

    fn properties(&self) -> &Arc<PlanProperties> {
        &self.properties
    }

    fn children(&self) -> Vec<&Arc<dyn ExecutionPlan>> {
        vec![&self.input]
    }

    fn benefits_from_input_partitioning(&self) -> Vec<bool> {
        vec![true]
    }

    fn apply_expressions(
        &self,
        f: &mut dyn FnMut(&Arc<dyn PhysicalExpr>) -> Result<TreeNodeRecursion>,
    ) -> Result<TreeNodeRecursion> {
        let mut r = f(&self.key)?;
        for a in &self.args {
            if r == TreeNodeRecursion::Stop {
                break;
            }
            r = f(a)?;
        }
        Ok(r)
    }

    fn with_new_children(self: Arc<Self>, children: Vec<Arc<dyn ExecutionPlan>>) -> Result<Arc<dyn ExecutionPlan>> {
        let [input] = <[_; 1]>::try_from(children)
            .map_err(|c| DataFusionError::Internal(format!("CountByKeyExec has one child, not {}", c.len())))?;
        Ok(Arc::new(Self {
            input,
            key: self.key.clone(),
            key_name: self.key_name.clone(),
            args: self.args.clone(),
            outputs: self.outputs.clone(),
            schema: self.schema.clone(),
            properties: self.properties.clone(),
            metrics: ExecutionPlanMetricsSet::new(),
        }))
    }

    fn metrics(&self) -> Option<MetricsSet> {
        Some(self.metrics.clone_inner())
    }

    fn execute(&self, partition: usize, context: Arc<TaskContext>) -> Result<SendableRecordBatchStream> {
        if partition != 0 {
            return Err(DataFusionError::Internal(format!("CountByKeyExec has one partition, not {partition}")));
        }
        // One counting worker per target partition, each reading its share of the input's
        // partitions in turn (a dataset's segments can far outnumber the cores; a table per
        // segment would multiply the memory and the merging).
        let parts = self.input.output_partitioning().partition_count();
        let workers = context.session_config().target_partitions().clamp(1, parts.max(1));
        let spill = SpillTo {
            disk: context.runtime_env().disk_manager.clone(),
            runs: MetricBuilder::new(&self.metrics).spill_count(partition),
            bytes: MetricBuilder::new(&self.metrics).spilled_bytes(partition),
        };
        let limit = match context.memory_pool().memory_limit() {
            MemoryLimit::Finite(limit) => limit,
            _ => usize::MAX,
        };
        let share = limit / workers;
        let mut tasks = Vec::with_capacity(workers);
        for w in 0..workers {
            let streams = (w..parts).step_by(workers).map(|p| self.input.execute(p, context.clone()));
            let streams = streams.collect::<Result<Vec<_>>>()?;
            let reservation = MemoryConsumer::new(format!("CountByKeyExec[{w}]")).register(context.memory_pool());
            let budget = Budget { reservation, share };
            let (key, args, stride) = (self.key.clone(), self.args.clone(), self.stride());
            let counting = count_partitions(streams, key, args, stride, budget, spill.clone());
            tasks.push(SpawnedTask::spawn(counting));
        }
        let out = Output {
            schema: self.schema.clone(),
            outputs: self.outputs.clone(),
            stride: self.stride(),
            batch_size: context.session_config().batch_size().max(1),
            baseline: BaselineMetrics::new(&self.metrics, partition),
            limit,
        };
        let pool = context.memory_pool().clone();
        let mut stream = RecordBatchReceiverStreamBuilder::new(self.schema.clone(), 2);
        let tx = stream.tx();
        stream.spawn(async move {
            let mut counted = Vec::with_capacity(tasks.len());
            for t in tasks {
                counted.push(t.join().await.map_err(|e| DataFusionError::ExecutionJoin(Box::new(e)))??);
            }
            merge(counted, &out, &spill, &pool, &tx).await?;
            out.baseline.done();
            Ok(())
        });
        Ok(stream.build())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_grow_and_keep_counts() {
        let mut t = Table::default();
        for _ in 0..3 {
            for k in 0..10_000u64 {
                let key = k << 20;
                let w = t.slot(key, mix(key), 3);
                t.words[w + 1] += 1;
                t.words[w + 2] += k % 2;
            }
        }
        assert_eq!(t.len, 10_000);
        assert!(t.len * 2 <= t.capacity(3));
        let mut seen = 0;
        for s in t.words.chunks_exact(3).filter(|s| s[1] != 0) {
            assert_eq!(s[1], 3);
            assert_eq!(s[2], 3 * ((s[0] >> 20) % 2));
            seen += 1;
        }
        assert_eq!(seen, 10_000);
    }

    /// Few keys (counted in the direct table throughout) and many (moved into the radix
    /// buckets part way); `count(*)` alone (one-word narrow tables) and with a nullable counted
    /// column; keys beyond 32 bits arriving late in one input partition only (that worker's
    /// narrow tables widen, the other's stay narrow, and the merge meets both); with no memory
    /// limit, and under one far below the tables' size (the workers spill their tables to disk
    /// again and again, and the merge reads them back bucket by bucket): every group's counts
    /// are the true ones.
    #[test]
    fn direct_and_bucketed_counts_are_exact() -> Result<()> {
        use arrow::datatypes::{Field, Schema};
        use datafusion::datasource::MemTable;
        use datafusion::execution::memory_pool::GreedyMemoryPool;
        use datafusion::execution::runtime_env::RuntimeEnvBuilder;
        use datafusion::execution::session_state::SessionStateBuilder;
        use datafusion::prelude::{SessionConfig, SessionContext};
        let rt = tokio::runtime::Runtime::new()?;
        let cases = [
            (37u64, false, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
            (200_000, false, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
            (37, false, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, false, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, true, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, true, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
        ];
        let limits = [None, Some(1 << 20)];
        for ((distinct, wide, sql), limit) in cases.into_iter().flat_map(|c| limits.map(|l| (c, l))) {
            let schema = Arc::new(Schema::new(vec![
                Field::new("k", DataType::UInt64, false),
                Field::new("v", DataType::Int32, true),
            ]));
            let rows = 600_000u64;
            let key = |i: u64| {
                let late_in_one = wide && i > rows / 2 && (i / 8192) % 3 == 1;
                (i * 7919 + i / 3) % distinct + if late_in_one { 1 << 40 } else { 0 }
            };
            let mut parts = vec![Vec::new(), Vec::new(), Vec::new()];
            for start in (0..rows).step_by(8192) {
                let end = (start + 8192).min(rows);
                let k: UInt64Array = (start..end).map(key).collect();
                let v: arrow::array::Int32Array = (start..end).map(|i| (i % 5 != 0).then_some(1)).collect();
                let b = RecordBatch::try_new(schema.clone(), vec![Arc::new(k), Arc::new(v)])?;
                parts[(start / 8192 % 3) as usize].push(b);
            }
            let mut runtime = RuntimeEnvBuilder::new();
            if let Some(l) = limit {
                runtime = runtime.with_memory_pool(Arc::new(GreedyMemoryPool::new(l)));
            }
            let state = SessionStateBuilder::new()
                .with_config(SessionConfig::new().with_target_partitions(2))
                .with_runtime_env(runtime.build_arc()?)
                .with_default_features()
                .with_physical_optimizer_rules(crate::physical_optimizer_rules())
                .build();
            let ctx = SessionContext::new_with_state(state);
            ctx.register_table("t", Arc::new(MemTable::try_new(schema, parts)?))?;
            let (batches, spills) = rt.block_on(async {
                let plan = ctx.sql(sql).await?.create_physical_plan().await?;
                let batches = datafusion::physical_plan::collect(plan.clone(), ctx.task_ctx()).await?;
                let metrics = crate::plan_util::metrics_of::<CountByKeyExec>(&plan);
                let spills = metrics.unwrap_or_else(|| panic!("no CountByKeyExec")).spill_count().unwrap_or(0);
                Ok::<_, DataFusionError>((batches, spills))
            })?;
            assert_eq!(spills > 0, limit.is_some() && distinct > 37, "{sql} under {limit:?}: {spills} spills");
            let mut expected = std::collections::HashMap::<u64, (i64, i64)>::new();
            for i in 0..rows {
                let e = expected.entry(key(i)).or_default();
                e.0 += 1;
                e.1 += if sql.contains("count(v)") { i64::from(i % 5 != 0) } else { 1 };
            }
            let mut groups = 0;
            for b in &batches {
                let k = cast(b.column(0), &DataType::UInt64)?;
                let k = k.as_primitive::<UInt64Type>();
                let (n, nv) = (b.column(1).as_primitive::<Int64Type>(), b.column(2).as_primitive::<Int64Type>());
                for r in 0..b.num_rows() {
                    assert_eq!(expected.get(&k.value(r)), Some(&(n.value(r), nv.value(r))), "key {}", k.value(r));
                    groups += 1;
                }
            }
            assert_eq!(groups, expected.len(), "{sql} under {limit:?}");
        }
        Ok(())
    }

    #[test]
    fn keys_keep_their_bits() -> Result<()> {
        let a: ArrayRef = Arc::new(arrow::array::Int8Array::from(vec![Some(-1), None, Some(127)]));
        let (w, n) = key_words(&a)?;
        assert_eq!(w[0], u64::MAX);
        assert_eq!(w[2], 127);
        assert!(n.is_some_and(|n| n.is_null(1)));
        Ok(())
    }
}
