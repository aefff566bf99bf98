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
//! every row; the workers' tables are then merged bucket by bucket, in parallel. Memory is charged
//! to the session's memory pool, so a memory limit is an error, not an out-of-memory kill.

use std::borrow::Cow;
use std::fmt;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Int64Array, RecordBatch, UInt64Array};
use arrow::buffer::NullBuffer;
use arrow::compute::cast;
use arrow::datatypes::{DataType, Int64Type, SchemaRef, UInt64Type};
use datafusion::common::config::ConfigOptions;
use datafusion::common::runtime::SpawnedTask;
use datafusion::common::tree_node::TreeNodeRecursion;
use datafusion::error::{DataFusionError, Result};
use datafusion::execution::TaskContext;
use datafusion::execution::memory_pool::{MemoryConsumer, MemoryReservation};
use datafusion::physical_expr::expressions::Literal;
use datafusion::physical_expr::{EquivalenceProperties, PhysicalExpr};
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_plan::aggregates::{AggregateExec, AggregateMode};
use datafusion::physical_plan::execution_plan::{Boundedness, EmissionType};
use datafusion::physical_plan::metrics::{BaselineMetrics, ExecutionPlanMetricsSet, MetricsSet};
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlan, ExecutionPlanProperties, Partitioning, PlanProperties,
    SendableRecordBatchStream,
};
use futures::StreamExt;

use crate::plan_util::{Walk, batches_stream, replace_nodes};

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
        let mut tasks = Vec::with_capacity(workers);
        for w in 0..workers {
            let streams = (w..parts).step_by(workers).map(|p| self.input.execute(p, context.clone()));
            let streams = streams.collect::<Result<Vec<_>>>()?;
            let reservation = MemoryConsumer::new(format!("CountByKeyExec[{w}]")).register(context.memory_pool());
            let (key, args, stride) = (self.key.clone(), self.args.clone(), self.stride());
            tasks.push(SpawnedTask::spawn(count_partitions(streams, key, args, stride, reservation)));
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
        Ok(batches_stream(self.schema.clone(), answer))
    }
}

/// A key's radix bucket: the top bits of a multiplicative hash (every key bit reaches them).
#[inline]
fn bucket(key: u64) -> usize {
    (key.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> (64 - BUCKET_BITS)) as usize
}

/// splitmix64's finalizer, for the slot within a bucket's table.
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
        self.reserve(1, stride);
        self.slot_reserved(key, hash, stride)
    }

    /// Grows the table (if needed) so that `additional` new keys keep it at most half full.
    fn reserve(&mut self, additional: usize, stride: usize) {
        while (self.len + additional) * 2 > self.capacity(stride) {
            self.grow(stride);
        }
    }

    /// [`Table::slot`] without the growth check: room must have been reserved.
    #[inline(always)]
    fn slot_reserved(&mut self, key: u64, hash: u64, stride: usize) -> usize {
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
        // Zeros written, not calloc's lazy zero pages: a probe reads a slot before it writes it,
        // and a write to a read-mapped zero page costs a copy-on-write fault and a TLB shootdown.
        #[expect(clippy::slow_vector_initialization, reason = "written zeros, not calloc's zero pages (see above)")]
        let words = {
            let mut words = Vec::with_capacity(capacity * stride);
            words.resize(capacity * stride, 0);
            words
        };
        let old = std::mem::replace(&mut self.words, words);
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

/// A bucket's table with one-word slots, for `count(*)` alone while every key fits in 32 bits and
/// no count can reach 2^32: the key in the high half, its count in the low half, 0 for an empty
/// slot (a stored key has a count). Half the bytes of a [`Table`] slot pair: half the cache
/// traffic per probe and half the memory.
#[derive(Default)]
struct Narrow {
    words: Vec<u64>,
    mask: usize,
    len: usize,
}

const LOW: u64 = 0xffff_ffff;

impl Narrow {
    /// Grows the table (if needed) so that `additional` new keys keep it at most half full.
    fn reserve(&mut self, additional: usize) {
        while (self.len + additional) * 2 > self.words.len() {
            let capacity = (self.words.len() * 2).max(64);
            // Zeros written, not calloc's lazy zero pages (see `Table::grow`).
            #[expect(clippy::slow_vector_initialization, reason = "written zeros, not calloc's zero pages")]
            let words = {
                let mut words = Vec::with_capacity(capacity);
                words.resize(capacity, 0);
                words
            };
            let old = std::mem::replace(&mut self.words, words);
            self.mask = capacity - 1;
            self.len = 0;
            for w in old.into_iter().filter(|&w| w != 0) {
                self.add(w >> 32, w & LOW);
            }
        }
    }

    /// Adds `n` rows to `key` (below 2^32); room must have been reserved.
    #[inline(always)]
    fn add(&mut self, key: u64, n: u64) {
        let mut i = mix(key) as usize & self.mask;
        loop {
            let w = self.words[i];
            if w == 0 {
                self.words[i] = (key << 32) | n;
                self.len += 1;
                return;
            }
            if w >> 32 == key {
                self.words[i] = w + n;
                return;
            }
            i = (i + 1) & self.mask;
        }
    }

    fn bytes(&self) -> usize {
        self.words.len() * std::mem::size_of::<u64>()
    }
}

/// Keys a worker buffers (per radix bucket) before it adds them to its tables, bucket by bucket:
/// each bucket's table is then read into cache once per flush, not missed on every row.
const PENDING_KEYS: usize = 4 << 20;

/// Bytes a worker's single direct table may reach before the worker switches to radix buckets:
/// a table this size stays in a core's L2 cache (1 MiB of the 2 MiB here), where counting straight
/// into it is faster than buffering (with 16K distinct keys the buffered path was 3x slower than
/// DataFusion's own aggregation: `cargo bench -p rtvtk-query --bench count_by_key`).
const DIRECT_BYTES: usize = 1 << 20;

/// One worker's counts: while few keys have been seen, one table counted into directly; then a
/// table per radix bucket, the keys not yet counted (with, when `count`s of expressions are asked,
/// a word of their validity bits after each key); and the counts of the NULL key.
struct Counts {
    stride: usize,
    direct: Option<Table>,
    tables: Vec<Table>,
    /// The buckets' tables while they can be [`Narrow`] (then `tables` stays empty).
    narrow: Option<Vec<Narrow>>,
    /// OR of every key seen (whether they all fit in 32 bits) and rows seen, for `narrow`.
    key_bits: u64,
    rows: u64,
    pending: Vec<Vec<u64>>,
    pending_rows: usize,
    null_key: Vec<u64>,
}

impl Counts {
    fn new(stride: usize) -> Self {
        Self {
            stride,
            direct: Some(Table::default()),
            tables: (0..BUCKETS).map(|_| Table::default()).collect(),
            narrow: (stride == 2).then(|| (0..BUCKETS).map(|_| Narrow::default()).collect()),
            key_bits: 0,
            rows: 0,
            pending: vec![Vec::new(); BUCKETS],
            pending_rows: 0,
            null_key: vec![0; stride - 1],
        }
    }

    /// Whether the narrow tables can no longer hold the keys or counts.
    fn too_wide(&self) -> bool {
        self.key_bits >> 32 != 0 || self.rows >= LOW
    }

    /// Moves the narrow tables' keys into `tables` (for good).
    fn widen(&mut self) {
        let Some(narrow) = self.narrow.take() else { return };
        for (t, n) in self.tables.iter_mut().zip(narrow) {
            t.reserve(n.len, 2);
            for w in n.words.into_iter().filter(|&w| w != 0) {
                let slot = t.slot_reserved(w >> 32, mix(w >> 32), 2);
                t.words[slot + 1] += w & LOW;
            }
        }
    }

    /// Adds the pending keys to the tables, one bucket at a time.
    fn flush(&mut self) {
        let stride = self.stride;
        if self.too_wide() {
            self.widen();
        }
        if let Some(narrow) = self.narrow.as_mut() {
            for (t, pending) in narrow.iter_mut().zip(&mut self.pending) {
                std::hint::black_box(t.words.iter().step_by(8).fold(0u64, |a, &w| a ^ w));
                for chunk in pending.chunks(1024) {
                    t.reserve(chunk.len());
                    for &key in chunk {
                        t.add(key, 1);
                    }
                }
                pending.clear();
            }
            self.pending_rows = 0;
            return;
        }
        for (t, pending) in self.tables.iter_mut().zip(&mut self.pending) {
            // Read the table into cache in order (at the prefetcher's pace) before the random probes.
            std::hint::black_box(t.words.iter().step_by(8).fold(0u64, |a, &w| a ^ w));
            // Room is reserved per chunk, not checked per key (at most a chunk's worth of slack).
            let per = if stride > 2 { 2 } else { 1 };
            for chunk in pending.chunks(1024 * per) {
                t.reserve(chunk.len() / per, stride);
                if per == 1 {
                    for &key in chunk {
                        let w = t.slot_reserved(key, mix(key), stride);
                        t.words[w + 1] += 1;
                    }
                    continue;
                }
                for row in chunk.chunks_exact(per) {
                    let w = t.slot_reserved(row[0], mix(row[0]), stride);
                    t.words[w + 1] += 1;
                    for j in 2..stride {
                        t.words[w + j] += (row[1] >> (j - 2)) & 1;
                    }
                }
            }
            pending.clear();
        }
        self.pending_rows = 0;
    }

    /// Moves the direct table's keys into the radix buckets' tables (for good: later rows are
    /// buffered) once it has outgrown [`DIRECT_BYTES`], or always when `all`.
    fn spill(&mut self, all: bool) {
        let stride = self.stride;
        if !all && self.direct.as_ref().is_none_or(|t| t.len * 2 * stride * 8 <= DIRECT_BYTES) {
            return;
        }
        let Some(direct) = self.direct.take() else { return };
        if self.too_wide() {
            self.widen();
        }
        if let Some(narrow) = self.narrow.as_mut() {
            for s in direct.words.chunks_exact(2).filter(|s| s[1] != 0) {
                let t = &mut narrow[bucket(s[0])];
                t.reserve(1);
                t.add(s[0], s[1]);
            }
            return;
        }
        for s in direct.words.chunks_exact(stride).filter(|s| s[1] != 0) {
            let t = &mut self.tables[bucket(s[0])];
            let w = t.slot(s[0], mix(s[0]), stride);
            for (b, v) in t.words[w + 1..w + stride].iter_mut().zip(&s[1..]) {
                *b += v;
            }
        }
    }

    fn bytes(&self) -> usize {
        let pending: usize = self.pending.iter().map(|p| p.capacity() * std::mem::size_of::<u64>()).sum();
        let direct = self.direct.as_ref().map_or(0, Table::bytes);
        let narrow = self.narrow.iter().flatten().map(Narrow::bytes).sum::<usize>();
        direct + narrow + pending + self.tables.iter().map(Table::bytes).sum::<usize>()
    }
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

/// Counts input partitions, one after the other, into one set of tables.
async fn count_partitions(
    streams: Vec<SendableRecordBatchStream>,
    key: Arc<dyn PhysicalExpr>,
    args: Vec<Arc<dyn PhysicalExpr>>,
    stride: usize,
    reservation: MemoryReservation,
) -> Result<(Counts, MemoryReservation)> {
    let mut c = Counts::new(stride);
    let mut bytes = 0usize;
    let mut batches = futures::stream::iter(streams).flatten();
    while let Some(batch) = batches.next().await {
        let batch = batch?;
        let rows = batch.num_rows();
        let k = key.evaluate(&batch)?.into_array(rows)?;
        let (keys, key_nulls) = key_words(&k)?;
        if c.narrow.is_some() {
            c.key_bits |= keys.iter().fold(0, |a, &k| a | k);
        }
        c.rows += rows as u64;
        let valid: Vec<Option<NullBuffer>> =
            args.iter().map(|a| Ok(a.evaluate(&batch)?.into_array(rows)?.logical_nulls())).collect::<Result<_>>()?;
        let mask = |i: usize| -> u64 {
            valid.iter().enumerate().map(|(j, v)| u64::from(v.as_ref().is_none_or(|n| n.is_valid(i))) << j).sum()
        };
        if key_nulls.is_none()
            && args.is_empty()
            && let Some(t) = c.direct.as_mut()
        {
            for chunk in keys.chunks(1024) {
                t.reserve(chunk.len(), stride);
                for &key in chunk {
                    let w = t.slot_reserved(key, mix(key), stride);
                    t.words[w + 1] += 1;
                }
            }
        } else if key_nulls.is_none() && args.is_empty() {
            for &key in keys.iter() {
                c.pending[bucket(key)].push(key);
            }
        } else {
            add_rows(&mut c, &keys, key_nulls.as_ref(), &mask, args.len());
        }
        if c.direct.is_some() {
            c.spill(false);
        } else {
            c.pending_rows += rows;
        }
        if c.pending_rows >= PENDING_KEYS {
            c.flush();
        }
        let now = c.bytes();
        if now != bytes {
            reservation.try_resize(now)?;
            bytes = now;
        }
    }
    c.spill(true);
    c.flush();
    Ok((c, reservation))
}

/// Adds rows whose keys may be NULL, or with the validity bits of counted expressions.
fn add_rows(c: &mut Counts, keys: &[u64], key_nulls: Option<&NullBuffer>, mask: &dyn Fn(usize) -> u64, args: usize) {
    for (i, &key) in keys.iter().enumerate() {
        if key_nulls.is_some_and(|n| n.is_null(i)) {
            c.null_key[0] += 1;
            let m = mask(i);
            for j in 0..args {
                c.null_key[1 + j] += (m >> j) & 1;
            }
            continue;
        }
        if let Some(t) = c.direct.as_mut() {
            let w = t.slot(key, mix(key), c.stride);
            t.words[w + 1] += 1;
            let m = mask(i);
            for j in 0..args {
                t.words[w + 2 + j] += (m >> j) & 1;
            }
            continue;
        }
        let pending = &mut c.pending[bucket(key)];
        pending.push(key);
        if args > 0 {
            pending.push(mask(i));
        }
    }
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
    let mut by_bucket: Vec<Vec<Part>> = (0..BUCKETS).map(|_| Vec::new()).collect();
    let mut reservations = Vec::new();
    let mut rows = 0u64;
    for (c, r) in counted {
        for (n, v) in null_key.iter_mut().zip(&c.null_key) {
            *n += v;
        }
        rows += c.rows;
        match c.narrow {
            Some(narrow) => narrow.into_iter().enumerate().for_each(|(b, t)| by_bucket[b].push(Part::Narrow(t))),
            None => c.tables.into_iter().enumerate().for_each(|(b, t)| by_bucket[b].push(Part::Wide(t))),
        }
        reservations.push(r);
    }
    // Narrow tables merge into a narrow table while the sum of their counts fits its low half.
    let narrow_ok = rows < LOW;
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 16);
    let per = BUCKETS.div_ceil(workers);
    let mut tasks = Vec::new();
    while !by_bucket.is_empty() {
        let rest = by_bucket.split_off(per.min(by_bucket.len()));
        let chunk = std::mem::replace(&mut by_bucket, rest);
        tasks.push(SpawnedTask::spawn(async move { merge_buckets(chunk, stride, narrow_ok) }));
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

/// One worker's table of one bucket.
enum Part {
    Wide(Table),
    Narrow(Narrow),
}

/// Merges each bucket's tables into one and lists the keys and counts.
fn merge_buckets(buckets: Vec<Vec<Part>>, stride: usize, narrow_ok: bool) -> (Vec<u64>, Vec<Vec<i64>>) {
    let mut keys = Vec::new();
    let mut counts: Vec<Vec<i64>> = vec![Vec::new(); stride - 1];
    for parts in buckets {
        if narrow_ok && parts.iter().all(|p| matches!(p, Part::Narrow(_))) {
            let mut it = parts.into_iter().filter_map(|p| match p {
                Part::Narrow(n) => Some(n),
                Part::Wide(_) => None,
            });
            let Some(mut base) = it.next() else { continue };
            for n in it {
                base.reserve(n.len);
                for w in n.words.into_iter().filter(|&w| w != 0) {
                    base.add(w >> 32, w & LOW);
                }
            }
            keys.reserve(base.len);
            for w in base.words.into_iter().filter(|&w| w != 0) {
                keys.push(w >> 32);
                counts[0].push((w & LOW) as i64);
            }
            continue;
        }
        let mut base = Table::default();
        for p in parts {
            match p {
                Part::Wide(t) if base.len == 0 => base = t,
                Part::Wide(t) => {
                    for s in t.words.chunks_exact(stride).filter(|s| s[1] != 0) {
                        let w = base.slot(s[0], mix(s[0]), stride);
                        for (b, v) in base.words[w + 1..w + stride].iter_mut().zip(&s[1..]) {
                            *b += v;
                        }
                    }
                }
                Part::Narrow(n) => {
                    base.reserve(n.len, stride);
                    for w in n.words.into_iter().filter(|&w| w != 0) {
                        let slot = base.slot_reserved(w >> 32, mix(w >> 32), stride);
                        base.words[slot + 1] += w & LOW;
                    }
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

    /// Few keys (counted in the direct table throughout) and many (spilled into the radix
    /// buckets part way); `count(*)` alone (one-word narrow tables) and with a nullable counted
    /// column; keys beyond 32 bits arriving late in one input partition only (that worker's
    /// narrow tables widen, the other's stay narrow, and the merge meets both): every group's
    /// counts are the true ones.
    #[test]
    fn direct_and_bucketed_counts_are_exact() -> Result<()> {
        use arrow::datatypes::{Field, Schema};
        use datafusion::datasource::MemTable;
        use datafusion::execution::session_state::SessionStateBuilder;
        use datafusion::prelude::{SessionConfig, SessionContext};
        let rt = tokio::runtime::Runtime::new()?;
        for (distinct, wide, sql) in [
            (37u64, false, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
            (200_000, false, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
            (37, false, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, false, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, true, "SELECT k, count(*), count(*) AS n FROM t GROUP BY k"),
            (200_000, true, "SELECT k, count(*), count(v) FROM t GROUP BY k"),
        ] {
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
            let state = SessionStateBuilder::new()
                .with_config(SessionConfig::new().with_target_partitions(2))
                .with_default_features()
                .with_physical_optimizer_rules(crate::physical_optimizer_rules())
                .build();
            let ctx = SessionContext::new_with_state(state);
            ctx.register_table("t", Arc::new(MemTable::try_new(schema, parts)?))?;
            let batches = rt.block_on(async {
                let df = ctx.sql(sql).await?;
                let plan = df.clone().create_physical_plan().await?;
                let shown = datafusion::physical_plan::displayable(plan.as_ref()).indent(true).to_string();
                assert!(shown.contains("CountByKeyExec"), "{shown}");
                df.collect().await
            })?;
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
            assert_eq!(groups, expected.len());
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
