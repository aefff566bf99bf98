//! The ray aggregates `dir_coherence(dx, dy, dz)` and `origin_spread(x, y, z)`: statistics of
//! 3-vectors aggregated in parts and merged, with a `GroupsAccumulator` (one pass per batch over
//! all groups).

use std::marker::PhantomData;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, BooleanArray, Float64Array, UInt64Array};
use arrow::datatypes::{DataType, Field, FieldRef, Float64Type, UInt64Type};
use datafusion::common::ScalarValue;
use datafusion::error::DataFusionError;
use datafusion::logical_expr::function::{AccumulatorArgs, StateFieldsArgs};
use datafusion::logical_expr::{
    Accumulator, AggregateUDF, AggregateUDFImpl, Documentation, EmitTo, GroupsAccumulator, Signature,
};

use super::doc;
use super::kernels::{Floats, float_signature};

/// A statistic of 3-vectors that DataFusion aggregates in parts and merges: the aggregate
/// `NAME(x, y, z)` gives [`XyzStat::value`] as a Float64. Rows with a NULL, NaN or infinite
/// coordinate are left out.
pub(crate) trait XyzStat: std::fmt::Debug + Default + Clone + Send + Sync + 'static {
    const NAME: &'static str;
    /// Its text for `SHOW FUNCTIONS`, `\\df` and the README (the only copy).
    fn documentation() -> Documentation;
    /// Adds one vector (the statistic decides which ones count).
    fn add(&mut self, v: [f64; 3]);
    /// Adds another partial statistic.
    fn merge(&mut self, other: &Self);
    /// The statistic, None without vectors.
    fn value(&self) -> Option<f64>;
    /// Types of the partial state's columns.
    fn state_types() -> Vec<DataType>;
    /// Partial states as columns (one row each).
    fn to_state(stats: &[Self]) -> Vec<ArrayRef>;
    /// Partial states from columns as [`XyzStat::to_state`] writes them.
    fn from_state(states: &[ArrayRef]) -> datafusion::error::Result<Vec<Self>>;
}

/// The DataFusion accumulator of any [`XyzStat`] without groups.
#[derive(Debug, Default)]
struct XyzAccumulator<S>(S);

impl<S: XyzStat> Accumulator for XyzAccumulator<S> {
    fn update_batch(&mut self, values: &[ArrayRef]) -> datafusion::error::Result<()> {
        Floats::<3>::of(values)?.each_valid(|_, v| self.0.add(v));
        Ok(())
    }

    fn evaluate(&mut self) -> datafusion::error::Result<ScalarValue> {
        Ok(ScalarValue::Float64(self.0.value()))
    }

    fn size(&self) -> usize {
        std::mem::size_of_val(self)
    }

    fn state(&mut self) -> datafusion::error::Result<Vec<ScalarValue>> {
        S::to_state(std::slice::from_ref(&self.0)).iter().map(|a| ScalarValue::try_from_array(a, 0)).collect()
    }

    fn merge_batch(&mut self, states: &[ArrayRef]) -> datafusion::error::Result<()> {
        for s in S::from_state(states)? {
            self.0.merge(&s);
        }
        Ok(())
    }
}

/// The grouped accumulator of any [`XyzStat`]: one statistic per group, updated in one pass
/// over a batch (DataFusion's per-group adapter would split every batch by group first).
#[derive(Debug, Default)]
struct XyzGroups<S>(Vec<S>);

impl<S: XyzStat> GroupsAccumulator for XyzGroups<S> {
    fn update_batch(
        &mut self,
        values: &[ArrayRef],
        group_indices: &[usize],
        opt_filter: Option<&BooleanArray>,
        total_num_groups: usize,
    ) -> datafusion::error::Result<()> {
        self.0.resize_with(total_num_groups, S::default);
        let stats = &mut self.0;
        Floats::<3>::of(values)?.each_valid(|r, v| {
            if opt_filter.is_none_or(|f| f.is_valid(r) && f.value(r))
                && let Some(s) = group_indices.get(r).and_then(|&g| stats.get_mut(g))
            {
                s.add(v);
            }
        });
        Ok(())
    }

    fn evaluate(&mut self, emit_to: EmitTo) -> datafusion::error::Result<ArrayRef> {
        let done = emit_to.take_needed(&mut self.0);
        Ok(Arc::new(done.iter().map(S::value).collect::<Float64Array>()))
    }

    fn state(&mut self, emit_to: EmitTo) -> datafusion::error::Result<Vec<ArrayRef>> {
        Ok(S::to_state(&emit_to.take_needed(&mut self.0)))
    }

    fn merge_batch(
        &mut self,
        values: &[ArrayRef],
        group_indices: &[usize],
        total_num_groups: usize,
    ) -> datafusion::error::Result<()> {
        self.0.resize_with(total_num_groups, S::default);
        for (s, &g) in S::from_state(values)?.iter().zip(group_indices) {
            if let Some(mine) = self.0.get_mut(g) {
                mine.merge(s);
            }
        }
        Ok(())
    }

    /// Each row as its own partial state (what DataFusion uses when it skips partial
    /// aggregation for groups nearly as many as rows).
    fn convert_to_state(
        &self,
        values: &[ArrayRef],
        opt_filter: Option<&BooleanArray>,
    ) -> datafusion::error::Result<Vec<ArrayRef>> {
        let c = Floats::<3>::of(values)?;
        let mut stats = vec![S::default(); c.len()];
        c.each_valid(|r, v| {
            if opt_filter.is_none_or(|f| f.is_valid(r) && f.value(r)) {
                stats[r].add(v);
            }
        });
        Ok(S::to_state(&stats))
    }

    fn size(&self) -> usize {
        self.0.capacity() * std::mem::size_of::<S>()
    }
}

/// The aggregate UDF of an [`XyzStat`]: three Float32 or Float64 arguments, a Float64 result.
#[derive(Debug)]
struct XyzUdaf<S> {
    signature: Signature,
    doc: Documentation,
    stat: PhantomData<fn() -> S>,
}

impl<S> PartialEq for XyzUdaf<S> {
    fn eq(&self, other: &Self) -> bool {
        self.signature == other.signature
    }
}

impl<S> Eq for XyzUdaf<S> {}

impl<S> std::hash::Hash for XyzUdaf<S> {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        self.signature.hash(state);
    }
}

impl<S: XyzStat> AggregateUDFImpl for XyzUdaf<S> {
    fn documentation(&self) -> Option<&Documentation> {
        Some(&self.doc)
    }
    fn name(&self) -> &str {
        S::NAME
    }

    fn signature(&self) -> &Signature {
        &self.signature
    }

    fn return_type(&self, _arg_types: &[DataType]) -> datafusion::error::Result<DataType> {
        Ok(DataType::Float64)
    }

    fn accumulator(&self, _args: AccumulatorArgs) -> datafusion::error::Result<Box<dyn Accumulator>> {
        Ok(Box::new(XyzAccumulator::<S>::default()))
    }

    fn state_fields(&self, args: StateFieldsArgs) -> datafusion::error::Result<Vec<FieldRef>> {
        Ok(S::state_types()
            .into_iter()
            .enumerate()
            .map(|(i, t)| Arc::new(Field::new(format!("{}[{i}]", args.name), t, true)))
            .collect())
    }

    fn groups_accumulator_supported(&self, _args: AccumulatorArgs) -> bool {
        true
    }

    fn create_groups_accumulator(
        &self,
        _args: AccumulatorArgs,
    ) -> datafusion::error::Result<Box<dyn GroupsAccumulator>> {
        Ok(Box::new(XyzGroups::<S>::default()))
    }
}

pub(super) fn xyz_aggregate<S: XyzStat>() -> AggregateUDF {
    AggregateUDF::from(XyzUdaf::<S> {
        signature: float_signature(3, false),
        doc: S::documentation(),
        stat: PhantomData,
    })
}

/// Float64 state columns (`N` of them, from `first`).
fn state_floats<const N: usize>(states: &[ArrayRef], first: usize) -> datafusion::error::Result<[&Float64Array; N]> {
    let mut v = Vec::with_capacity(N);
    for k in first..first + N {
        let c = states
            .get(k)
            .and_then(|a| a.as_primitive_opt::<Float64Type>())
            .ok_or_else(|| DataFusionError::Internal(format!("bad aggregate state: column {k} is not Float64")))?;
        v.push(c);
    }
    v.try_into().map_err(|_| DataFusionError::Internal("bad aggregate state".into()))
}

fn state_counts(states: &[ArrayRef], k: usize) -> datafusion::error::Result<&UInt64Array> {
    states
        .get(k)
        .and_then(|a| a.as_primitive_opt::<UInt64Type>())
        .ok_or_else(|| DataFusionError::Internal(format!("bad aggregate state: column {k} is not UInt64")))
}

/// Mean resultant length of directions: sums of the normalized vectors and their count.
#[derive(Clone, Debug, Default)]
pub(crate) struct Coherence {
    sum: [f64; 3],
    n: u64,
}

impl XyzStat for Coherence {
    const NAME: &'static str = "dir_coherence";

    fn documentation() -> Documentation {
        doc(
            "Aggregate: mean resultant length of the normalized directions (Float64): 1 when all are parallel, near 0 for directions spread over the sphere.",
            "dir_coherence(dir_x, dir_y, dir_z)",
            &[("dx", "x of the directions"), ("dy", "y of the directions"), ("dz", "z of the directions")],
        )
    }

    /// Adds a direction (zero ones are left out).
    fn add(&mut self, d: [f64; 3]) {
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if len > 0.0 && len.is_finite() {
            for (s, x) in self.sum.iter_mut().zip(d) {
                *s += x / len;
            }
            self.n += 1;
        }
    }

    fn merge(&mut self, other: &Self) {
        for (s, o) in self.sum.iter_mut().zip(other.sum) {
            *s += o;
        }
        self.n += other.n;
    }

    /// The mean resultant length.
    fn value(&self) -> Option<f64> {
        let s = self.sum;
        (self.n > 0).then(|| (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt() / self.n as f64)
    }

    fn state_types() -> Vec<DataType> {
        vec![DataType::Float64, DataType::Float64, DataType::Float64, DataType::UInt64]
    }

    fn to_state(stats: &[Self]) -> Vec<ArrayRef> {
        let mut cols: Vec<ArrayRef> =
            (0..3).map(|k| Arc::new(stats.iter().map(|s| s.sum[k]).collect::<Float64Array>()) as ArrayRef).collect();
        cols.push(Arc::new(stats.iter().map(|s| s.n).collect::<UInt64Array>()));
        cols
    }

    fn from_state(states: &[ArrayRef]) -> datafusion::error::Result<Vec<Self>> {
        let c = state_floats::<3>(states, 0)?;
        let n = state_counts(states, 3)?;
        Ok((0..n.len()).map(|r| Self { sum: [c[0].value(r), c[1].value(r), c[2].value(r)], n: n.value(r) }).collect())
    }
}

/// Spread of points about their centroid: count, mean and sum of squared distances (merged with
/// Chan et al.'s formula, so points far from the origin lose no precision).
#[derive(Clone, Debug, Default)]
pub(crate) struct Spread {
    n: u64,
    mean: [f64; 3],
    m2: f64,
}

impl Spread {
    fn merge_parts(&mut self, n: u64, mean: [f64; 3], m2: f64) {
        if n == 0 {
            return;
        }
        let total = self.n + n;
        let w = n as f64 / total as f64;
        let mut d2 = 0.0;
        for (m, x) in self.mean.iter_mut().zip(mean) {
            let d = x - *m;
            d2 += d * d;
            *m += d * w;
        }
        self.m2 += m2 + d2 * (self.n as f64) * (n as f64) / total as f64;
        self.n = total;
    }
}

impl XyzStat for Spread {
    const NAME: &'static str = "origin_spread";

    fn documentation() -> Documentation {
        doc(
            "Aggregate: root-mean-square distance of the points from their centroid (Float64), numerically stable far from the origin.",
            "origin_spread(origin_x, origin_y, origin_z)",
            &[("x", "x of the points"), ("y", "y of the points"), ("z", "z of the points")],
        )
    }

    fn add(&mut self, p: [f64; 3]) {
        self.merge_parts(1, p, 0.0);
    }

    fn merge(&mut self, other: &Self) {
        self.merge_parts(other.n, other.mean, other.m2);
    }

    /// The RMS distance from the centroid.
    fn value(&self) -> Option<f64> {
        (self.n > 0).then(|| (self.m2 / self.n as f64).max(0.0).sqrt())
    }

    fn state_types() -> Vec<DataType> {
        vec![DataType::UInt64, DataType::Float64, DataType::Float64, DataType::Float64, DataType::Float64]
    }

    fn to_state(stats: &[Self]) -> Vec<ArrayRef> {
        let mut cols: Vec<ArrayRef> = vec![Arc::new(stats.iter().map(|s| s.n).collect::<UInt64Array>())];
        for k in 0..3 {
            cols.push(Arc::new(stats.iter().map(|s| s.mean[k]).collect::<Float64Array>()));
        }
        cols.push(Arc::new(stats.iter().map(|s| s.m2).collect::<Float64Array>()));
        cols
    }

    fn from_state(states: &[ArrayRef]) -> datafusion::error::Result<Vec<Self>> {
        let n = state_counts(states, 0)?;
        let c = state_floats::<4>(states, 1)?;
        Ok((0..n.len())
            .map(|r| Self { n: n.value(r), mean: [c[0].value(r), c[1].value(r), c[2].value(r)], m2: c[3].value(r) })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_is_exact_far_from_the_origin_and_merges() {
        // Points 1e7 from the origin, 1 apart: the naive sum-of-squares formula loses it all.
        let pts: Vec<[f64; 3]> = (0..1000).map(|i| [1e7 + f64::from(i % 2), 1e7, -1e7]).collect();
        let mut whole = Spread::default();
        for p in &pts {
            whole.add(*p);
        }
        let rms = (whole.m2 / whole.n as f64).sqrt();
        assert!((rms - 0.5).abs() < 1e-9, "{rms}");
        let (mut a, mut b) = (Spread::default(), Spread::default());
        for (i, p) in pts.iter().enumerate() {
            if i < 300 { a.add(*p) } else { b.add(*p) }
        }
        a.merge(&b);
        assert!((a.m2 - whole.m2).abs() < 1e-6 && a.n == whole.n);
    }
}
