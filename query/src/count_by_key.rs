//! Counting group-bys on one integer key, the shape of the cell histograms analysts ask for
//! (`SELECT morton3(..) AS m, count(*) FROM rays GROUP BY m`, direction bins, primitive ids):
//! [`CountByKey`] is a physical optimizer rule that replaces DataFusion's two-phase hash
//! aggregation (a partial aggregate per partition, a hash repartition, a final aggregate) by one
//! [`CountByKeyExec`] when every aggregate is a plain `count`.
//!
//! Why: with millions of distinct keys the stock operator's hash tables outgrow the caches, and each
//! row costs several cache misses (control bytes, group index, key, accumulator), twice (partial and
//! final). Here each input partition counts into 256 radix buckets of open-addressing tables whose
//! slots hold the key and its counts side by side (one cache line per row), and the buckets of
//! different partitions are merged bucket by bucket (each bucket's table fits in cache), in
//! parallel. Memory is charged to the session's memory pool, so a memory limit is an error, not an
//! out-of-memory kill.

use std::borrow::Cow;
use std::fmt;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Int64Array, RecordBatch, UInt64Array};
use arrow::buffer::NullBuffer;
use arrow::compute::cast;
use arrow::datatypes::{DataType, Int64Type, SchemaRef, UInt64Type};
use datafusion::common::config::ConfigOptions;
use datafusion::common::runtime::SpawnedTask;
use datafusion::common::tree_node::{Transformed, TreeNode, TreeNodeRecursion};
use datafusion::error::{DataFusionError, Result};
use datafusion::execution::TaskContext;
use datafusion::execution::memory_pool::{MemoryConsumer, MemoryReservation};
use datafusion::physical_expr::expressions::Literal;
use datafusion::physical_expr::{EquivalenceProperties, PhysicalExpr};
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_plan::aggregates::{AggregateExec, AggregateMode};
use datafusion::physical_plan::execution_plan::{Boundedness, EmissionType};
use datafusion::physical_plan::metrics::{BaselineMetrics, ExecutionPlanMetricsSet, MetricsSet};
use datafusion::physical_plan::stream::RecordBatchStreamAdapter;
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlan, ExecutionPlanProperties, Partitioning, PlanProperties,
    SendableRecordBatchStream,
};
use futures::StreamExt;

/// Radix buckets per partition (the top bits of a key's hash).
const BUCKET_BITS: u32 = 8;
const BUCKETS: usize = 1 << BUCKET_BITS;

/// The physical optimizer rule; [`crate::session`] runs it before DataFusion's distribution
/// enforcement, so the plan above it is planned for its single output partition.
#[derive(Debug, Default)]
pub struct CountByKey;

impl PhysicalOptimizerRule for CountByKey {
    fn optimize(&self, plan: Arc<dyn ExecutionPlan>, _config: &ConfigOptions) -> Result<Arc<dyn ExecutionPlan>> {
        plan.transform_down(|node| match CountByKeyExec::replacing(&node)? {
            Some(exec) => Ok(Transformed::yes(Arc::new(exec) as Arc<dyn ExecutionPlan>)),
            None => Ok(Transformed::no(node)),
        })
        .map(|t| t.data)
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

fn is_integer(t: &DataType) -> bool {
    matches!(
        t,
        DataType::Int8
            | DataType::Int16
            | DataType::Int32
            | DataType::Int64
            | DataType::UInt8
            | DataType::UInt16
            | DataType::UInt32
            | DataType::UInt64
    )
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
        if !is_integer(&key_type) || out.field(0).data_type() != &key_type {
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
        let parts = self.input.output_partitioning().partition_count();
        let mut tasks = Vec::with_capacity(parts);
        for p in 0..parts {
            let stream = self.input.execute(p, context.clone())?;
            let reservation = MemoryConsumer::new(format!("CountByKeyExec[{p}]")).register(context.memory_pool());
            let (key, args, stride) = (self.key.clone(), self.args.clone(), self.stride());
            tasks.push(SpawnedTask::spawn(count_partition(stream, key, args, stride, reservation)));
        }
        let schema = self.schema.clone();
        let outputs = self.outputs.clone();
        let stride = self.stride();
        let batch_size = context.session_config().batch_size();
        let baseline = BaselineMetrics::new(&self.metrics, partition);
        let answer = async move {
            let mut counted = Vec::with_capacity(tasks.len());
            for t in tasks {
                counted.push(t.join().await.map_err(|e| DataFusionError::ExecutionJoin(Box::new(e)))??);
            }
            let timer = baseline.elapsed_compute().timer();
            let batches = merge(counted, stride, &schema, &outputs, batch_size).await?;
            timer.done();
            baseline.record_output(batches.iter().map(RecordBatch::num_rows).sum());
            baseline.done();
            Ok::<_, DataFusionError>(batches)
        };
        let stream = futures::stream::once(answer).flat_map(|r| match r {
            Ok(batches) => futures::stream::iter(batches.into_iter().map(Ok)).left_stream(),
            Err(e) => futures::stream::iter(vec![Err(e)]).right_stream(),
        });
        Ok(Box::pin(RecordBatchStreamAdapter::new(self.schema.clone(), stream)))
    }
}

/// splitmix64's finalizer: every key bit reaches the bucket bits (top) and the slot bits (bottom).
#[inline]
fn mix(k: u64) -> u64 {
    let z = (k ^ (k >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// One bucket's open-addressing table (linear probing, at most half full). A slot is `stride`
/// words: the key, its row count (0 marks an empty slot: a stored key has at least one row), then
/// the non-NULL count of each counted expression.
#[derive(Default)]
struct Table {
    words: Vec<u64>,
    mask: usize,
    len: usize,
}

impl Table {
    fn capacity(&self, stride: usize) -> usize {
        self.words.len() / stride
    }

    /// The first word of `key`'s slot, claimed (with zero counts) when the key is new.
    #[inline]
    fn slot(&mut self, key: u64, hash: u64, stride: usize) -> usize {
        if (self.len + 1) * 2 > self.capacity(stride) {
            self.grow(stride);
        }
        let mut i = hash as usize & self.mask;
        loop {
            let w = i * stride;
            if self.words[w + 1] == 0 {
                self.words[w] = key;
                self.len += 1;
                return w;
            }
            if self.words[w] == key {
                return w;
            }
            i = (i + 1) & self.mask;
        }
    }

    fn grow(&mut self, stride: usize) {
        let capacity = (self.capacity(stride) * 2).max(64);
        let old = std::mem::replace(&mut self.words, vec![0; capacity * stride]);
        self.mask = capacity - 1;
        self.len = 0;
        for s in old.chunks_exact(stride).filter(|s| s[1] != 0) {
            let w = self.slot(s[0], mix(s[0]), stride);
            self.words[w + 1..w + stride].copy_from_slice(&s[1..]);
        }
    }

    fn bytes(&self) -> usize {
        self.words.len() * std::mem::size_of::<u64>()
    }
}

/// One input partition's counts: a table per radix bucket and the counts of the NULL key.
struct Counts {
    tables: Vec<Table>,
    null_key: Vec<u64>,
}

/// A key column as 64-bit words (signed keys by their two's complement bits) and its validity.
fn key_words(a: &ArrayRef) -> Result<(Cow<'_, [u64]>, Option<NullBuffer>)> {
    let nulls = a.logical_nulls();
    let words = match a.data_type() {
        DataType::UInt64 => Cow::Borrowed(&a.as_primitive::<UInt64Type>().values()[..]),
        DataType::Int64 => Cow::Owned(a.as_primitive::<Int64Type>().values().iter().map(|&v| v as u64).collect()),
        t if t.is_signed_integer() => {
            let wide = cast(a, &DataType::Int64)?;
            Cow::Owned(wide.as_primitive::<Int64Type>().values().iter().map(|&v| v as u64).collect())
        }
        _ => {
            let wide = cast(a, &DataType::UInt64)?;
            Cow::Owned(wide.as_primitive::<UInt64Type>().values().to_vec())
        }
    };
    Ok((words, nulls))
}

/// Counts one input partition.
async fn count_partition(
    mut stream: SendableRecordBatchStream,
    key: Arc<dyn PhysicalExpr>,
    args: Vec<Arc<dyn PhysicalExpr>>,
    stride: usize,
    reservation: MemoryReservation,
) -> Result<(Counts, MemoryReservation)> {
    let mut c = Counts { tables: (0..BUCKETS).map(|_| Table::default()).collect(), null_key: vec![0; stride - 1] };
    let mut bytes = 0usize;
    while let Some(batch) = stream.next().await {
        let batch = batch?;
        let rows = batch.num_rows();
        let k = key.evaluate(&batch)?.into_array(rows)?;
        let (keys, key_nulls) = key_words(&k)?;
        let valid: Vec<Option<NullBuffer>> =
            args.iter().map(|a| Ok(a.evaluate(&batch)?.into_array(rows)?.logical_nulls())).collect::<Result<_>>()?;
        let shift = 64 - BUCKET_BITS;
        for (i, &key) in keys.iter().enumerate() {
            let counts = if key_nulls.as_ref().is_some_and(|n| n.is_null(i)) {
                &mut c.null_key[..]
            } else {
                let h = mix(key);
                let t = &mut c.tables[(h >> shift) as usize];
                let w = t.slot(key, h, stride);
                &mut t.words[w + 1..w + stride]
            };
            counts[0] += 1;
            for (j, v) in valid.iter().enumerate() {
                counts[1 + j] += v.as_ref().is_none_or(|n| n.is_valid(i)) as u64;
            }
        }
        let now: usize = c.tables.iter().map(Table::bytes).sum();
        if now != bytes {
            reservation.try_resize(now)?;
            bytes = now;
        }
    }
    Ok((c, reservation))
}

/// Merges the partitions' counts bucket by bucket (ranges of buckets in parallel) into batches of
/// the output schema.
async fn merge(
    counted: Vec<(Counts, MemoryReservation)>,
    stride: usize,
    schema: &SchemaRef,
    outputs: &[(Counted, String)],
    batch_size: usize,
) -> Result<Vec<RecordBatch>> {
    let mut null_key = vec![0u64; stride - 1];
    let mut by_bucket: Vec<Vec<Table>> = (0..BUCKETS).map(|_| Vec::new()).collect();
    let mut reservations = Vec::new();
    for (c, r) in counted {
        for (n, v) in null_key.iter_mut().zip(&c.null_key) {
            *n += v;
        }
        for (b, t) in c.tables.into_iter().enumerate() {
            by_bucket[b].push(t);
        }
        reservations.push(r);
    }
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 16);
    let per = BUCKETS.div_ceil(workers);
    let mut tasks = Vec::new();
    while !by_bucket.is_empty() {
        let rest = by_bucket.split_off(per.min(by_bucket.len()));
        let chunk = std::mem::replace(&mut by_bucket, rest);
        tasks.push(SpawnedTask::spawn(async move { merge_buckets(chunk, stride) }));
    }
    let mut columns: Vec<(Vec<u64>, Vec<Vec<i64>>)> = Vec::new();
    for t in tasks {
        columns.push(t.join().await.map_err(|e| DataFusionError::ExecutionJoin(Box::new(e)))?);
    }
    drop(reservations);
    let key_type = schema.field(0).data_type().clone();
    let mut batches = Vec::new();
    for (keys, counts) in columns {
        let mut start = 0;
        while start < keys.len() {
            let end = (start + batch_size.max(1)).min(keys.len());
            let key: ArrayRef = Arc::new(UInt64Array::from(keys[start..end].to_vec()));
            let cols = |c: &Vec<Vec<i64>>| -> Vec<ArrayRef> {
                outputs
                    .iter()
                    .map(|(what, _)| {
                        let j = match what {
                            Counted::Rows => 0,
                            Counted::Valid(i) => 1 + i,
                        };
                        Arc::new(Int64Array::from(c[j][start..end].to_vec())) as ArrayRef
                    })
                    .collect()
            };
            batches.push(batch(schema, &key_type, key, cols(&counts))?);
            start = end;
        }
    }
    if null_key[0] > 0 {
        let key: ArrayRef = Arc::new(UInt64Array::from(vec![None::<u64>]));
        let cols = outputs
            .iter()
            .map(|(what, _)| {
                let n = match what {
                    Counted::Rows => null_key[0],
                    Counted::Valid(i) => null_key[1 + i],
                };
                Arc::new(Int64Array::from(vec![n as i64])) as ArrayRef
            })
            .collect();
        batches.push(batch(schema, &key_type, key, cols)?);
    }
    Ok(batches)
}

/// One output batch: the keys back in their type (signed keys from their bits), then the counts.
fn batch(schema: &SchemaRef, key_type: &DataType, key: ArrayRef, counts: Vec<ArrayRef>) -> Result<RecordBatch> {
    let key = if key_type.is_signed_integer() {
        let signed: Int64Array = key.as_primitive::<UInt64Type>().unary(|v| v as i64);
        cast(&signed, key_type)?
    } else {
        cast(&key, key_type)?
    };
    let mut columns = vec![key];
    columns.extend(counts);
    Ok(RecordBatch::try_new(schema.clone(), columns)?)
}

/// Merges each bucket's tables into its first and lists the keys and counts.
fn merge_buckets(buckets: Vec<Vec<Table>>, stride: usize) -> (Vec<u64>, Vec<Vec<i64>>) {
    let mut keys = Vec::new();
    let mut counts: Vec<Vec<i64>> = vec![Vec::new(); stride - 1];
    for tables in buckets {
        let mut it = tables.into_iter();
        let Some(mut base) = it.next() else { continue };
        for t in it {
            for s in t.words.chunks_exact(stride).filter(|s| s[1] != 0) {
                let w = base.slot(s[0], mix(s[0]), stride);
                for j in 1..stride {
                    base.words[w + j] += s[j];
                }
            }
        }
        keys.reserve(base.len);
        for s in base.words.chunks_exact(stride).filter(|s| s[1] != 0) {
            keys.push(s[0]);
            for (j, c) in counts.iter_mut().enumerate() {
                c.push(s[1 + j] as i64);
            }
        }
    }
    (keys, counts)
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
