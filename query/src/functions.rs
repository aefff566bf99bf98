//! Ray functions for SQL, registered in any `SessionContext` (also a Ballista one):
//!
//! | function | returns | meaning |
//! |---|---|---|
//! | `octant(dx, dy, dz)` | UInt8 | bit 0: dx < 0, bit 1: dy < 0, bit 2: dz < 0 |
//! | `angle_between(ax, ay, az, bx, by, bz)` | Float64 | angle between two directions, radians |
//! | `dir_bin(dx, dy, dz, n)` | UInt32 | cell of the direction on an n × n octahedral map |
//! | `ray_aabb_hit(ox, oy, oz, dx, dy, dz, min_x, min_y, min_z, max_x, max_y, max_z)` | Boolean | the ray (t ≥ 0) enters the box |
//! | `morton3(x, y, z, bits)` | UInt64 | Morton code of a point over the scene bounds, `bits` (1..=21) per axis |
//! | `aims_at_light(ox, oy, oz, dx, dy, dz)` | Boolean | the ray's line hits an emitter triangle in front of its origin |
//! | `ray_point(ox, oy, oz, dx, dy, dz, t)` | Struct {x, y, z} | the point `o + t·d` (`ray_point(..)['x']`); NULL for a miss |
//!
//! Aggregates:
//!
//! | function | returns | meaning |
//! |---|---|---|
//! | `dir_coherence(dx, dy, dz)` | Float64 | mean resultant length of the normalized directions: 1 when all are parallel, near 0 for directions spread over the sphere |
//! | `origin_spread(x, y, z)` | Float64 | root-mean-square distance of the points from their centroid (numerically stable far from the origin) |
//!
//! NaN or infinite inputs give NULL, never an error. Scene-dependent functions use the scene of
//! the session's first dataset: its bounds (origins and hit points) and its `lights` table.

use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, BooleanArray, Float64Array, UInt8Array, UInt32Array, UInt64Array};
use arrow::datatypes::{DataType, Float32Type, Float64Type, Int64Type, UInt64Type};
use datafusion::common::ScalarValue;
use datafusion::error::DataFusionError;
use datafusion::logical_expr::{Accumulator, ColumnarValue, ScalarUDF, Volatility, create_udaf, create_udf};
use datafusion::prelude::SessionContext;
use store::Dataset;

use crate::Result;

/// What scene-dependent functions know about the scene.
#[derive(Clone, Debug, Default)]
pub struct SceneContext {
    /// Bounds of the finite origins and hit points, when any.
    pub bounds: Option<([f64; 3], [f64; 3])>,
    /// Emitter triangles (v0, v1, v2).
    pub lights: Vec<[[f64; 3]; 3]>,
}

impl SceneContext {
    /// The scene of a dataset: bounds from its statistics, emitters from its `lights` table.
    pub fn of(ds: &Dataset) -> Result<Self> {
        let st = ds.stats();
        let (o, h) = (&st.origin_bounds, &st.hit_bounds);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for b in [o, h] {
            if !b.is_empty() {
                for k in 0..3 {
                    lo[k] = lo[k].min(f64::from(b.min[k]));
                    hi[k] = hi[k].max(f64::from(b.max[k]));
                }
            }
        }
        let bounds = (lo[0] <= hi[0]).then_some((lo, hi));
        let mut lights = Vec::new();
        if let Some(batch) = ds.table("lights")? {
            let col =
                |name: &str| batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>().cloned());
            let mut cols = Vec::with_capacity(9);
            for v in 0..3 {
                for axis in ["x", "y", "z"] {
                    cols.push(col(&format!("v{v}_{axis}")));
                }
            }
            if cols.iter().all(Option::is_some) {
                let cols: Vec<_> = cols.into_iter().flatten().collect();
                for r in 0..batch.num_rows() {
                    let p = |v: usize| [0, 1, 2].map(|a| f64::from(cols[v * 3 + a].value(r)));
                    lights.push([p(0), p(1), p(2)]);
                }
            }
        }
        Ok(Self { bounds, lights })
    }
}

fn arrays(args: &[ColumnarValue]) -> datafusion::error::Result<Vec<ArrayRef>> {
    ColumnarValue::values_to_arrays(args)
}

fn f64s(a: &ArrayRef) -> datafusion::error::Result<&Float64Array> {
    a.as_primitive_opt::<Float64Type>()
        .ok_or_else(|| DataFusionError::Execution(format!("expected a Float64 argument, found {}", a.data_type())))
}

/// Row `r` of `N` float columns, or None when any is null or not finite.
fn row<const N: usize>(cols: &[&Float64Array; N], r: usize) -> Option<[f64; N]> {
    let mut out = [0.0; N];
    for (o, c) in out.iter_mut().zip(cols) {
        if c.is_null(r) || !c.value(r).is_finite() {
            return None;
        }
        *o = c.value(r);
    }
    Some(out)
}

/// The angle between two directions (atan2 of the cross and dot products: accurate for tiny
/// angles); None for a zero direction.
fn angle(a: [f64; 3], b: [f64; 3]) -> Option<f64> {
    let c = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let cross = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    (cross != 0.0 || dot != 0.0).then(|| cross.atan2(dot))
}

fn float_cols<const N: usize>(a: &[ArrayRef]) -> datafusion::error::Result<[&Float64Array; N]> {
    let mut v = Vec::with_capacity(N);
    for x in a.iter().take(N) {
        v.push(f64s(x)?);
    }
    v.try_into().map_err(|_| DataFusionError::Execution(format!("expected {N} arguments")))
}

/// Möller–Trumbore, two-sided, with a small barycentric tolerance: true when the line of the ray
/// hits the triangle at t > 0.
fn hits_triangle(o: [f64; 3], d: [f64; 3], tri: &[[f64; 3]; 3]) -> bool {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (e1, e2) = (sub(tri[1], tri[0]), sub(tri[2], tri[0]));
    let p = cross(d, e2);
    let det = dot(e1, p);
    let scale = dot(e1, e1).sqrt() * dot(e2, e2).sqrt() * dot(d, d).sqrt();
    // Parallel to the plane, or NaN.
    if det.abs().partial_cmp(&(1e-12 * scale)) != Some(std::cmp::Ordering::Greater) {
        return false;
    }
    let inv = 1.0 / det;
    let s = sub(o, tri[0]);
    let u = dot(s, p) * inv;
    const EPS: f64 = 1e-5;
    if !(-EPS..=1.0 + EPS).contains(&u) {
        return false;
    }
    let q = cross(s, e1);
    let v = dot(d, q) * inv;
    if v < -EPS || u + v > 1.0 + EPS {
        return false;
    }
    dot(e2, q) * inv > 0.0
}

/// Cell of a direction on an n × n octahedral map (row-major), None for a zero direction.
fn octahedral_bin(d: [f64; 3], n: u32) -> Option<u32> {
    let l1 = d[0].abs() + d[1].abs() + d[2].abs();
    if l1 <= 0.0 {
        return None;
    }
    let (mut x, mut y) = (d[0] / l1, d[1] / l1);
    if d[2] < 0.0 {
        let (ox, oy) = (x, y);
        x = (1.0 - oy.abs()) * ox.signum();
        y = (1.0 - ox.abs()) * oy.signum();
    }
    let cell = |v: f64| (((v * 0.5 + 0.5) * f64::from(n)).floor() as u32).min(n - 1);
    Some(cell(y) * n + cell(x))
}

/// Slab test: true when the ray (t ≥ 0) enters the box.
fn slab_hit(o: [f64; 3], d: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> bool {
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for k in 0..3 {
        if d[k] == 0.0 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return false;
            }
            continue;
        }
        let (a, b) = ((lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    t0 <= t1
}

/// Interleaves the low 21 bits of x, y, z (x in the lowest position).
fn morton(x: u64, y: u64, z: u64) -> u64 {
    fn spread(mut v: u64) -> u64 {
        v &= 0x1f_ffff;
        v = (v | (v << 32)) & 0x1f00000000ffff;
        v = (v | (v << 16)) & 0x1f0000ff0000ff;
        v = (v | (v << 8)) & 0x100f00f00f00f00f;
        v = (v | (v << 4)) & 0x10c30c30c30c30c3;
        (v | (v << 2)) & 0x1249249249249249
    }
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}

/// A row-wise function of `N` float arguments (and, with `int_param`, one integer last): rows
/// with a NULL, NaN or infinite float, or a NULL integer, give NULL; `f` may give NULL too.
fn rowwise<const N: usize, T, A>(
    name: &str,
    int_param: bool,
    ret: DataType,
    f: impl Fn([f64; N], Option<i64>) -> Option<T> + Send + Sync + 'static,
) -> ScalarUDF
where
    A: Array + FromIterator<Option<T>> + 'static,
{
    let mut params = vec![DataType::Float64; N];
    if int_param {
        params.push(DataType::Int64);
    }
    let fname = name.to_string();
    // Float64 parameters: Float32 columns and float literals both coerce to them.
    create_udf(
        name,
        params,
        ret,
        Volatility::Immutable,
        Arc::new(move |args: &[ColumnarValue]| {
            let a = arrays(args)?;
            let c = float_cols::<N>(&a)?;
            let ints = match a.get(N).filter(|_| int_param) {
                Some(i) => Some(i.as_primitive_opt::<Int64Type>().ok_or_else(|| {
                    DataFusionError::Execution(format!("{fname}: the last argument must be an integer"))
                })?),
                None => None,
            };
            let out: A = (0..c[0].len())
                .map(|r| {
                    let v = row(&c, r)?;
                    let k = match ints {
                        Some(i) => Some(i.is_valid(r).then(|| i.value(r))?),
                        None => None,
                    };
                    f(v, k)
                })
                .collect();
            Ok(ColumnarValue::Array(Arc::new(out)))
        }),
    )
}

/// `ray_point(ox, oy, oz, dx, dy, dz, t)`: the point at `t` along the ray, as a struct.
fn ray_point_udf() -> ScalarUDF {
    let fields = point_fields();
    create_udf(
        "ray_point",
        vec![DataType::Float64; 7],
        DataType::Struct(fields.clone()),
        Volatility::Immutable,
        Arc::new(move |args: &[ColumnarValue]| {
            let a = arrays(args)?;
            let c = float_cols::<7>(&a)?;
            let n = c[0].len();
            let (mut xs, mut ys, mut zs) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
            let mut valid = Vec::with_capacity(n);
            for r in 0..n {
                match row(&c, r) {
                    Some(v) => {
                        xs.push(v[0] + v[6] * v[3]);
                        ys.push(v[1] + v[6] * v[4]);
                        zs.push(v[2] + v[6] * v[5]);
                        valid.push(true);
                    }
                    None => {
                        xs.push(0.0);
                        ys.push(0.0);
                        zs.push(0.0);
                        valid.push(false);
                    }
                }
            }
            let out = arrow::array::StructArray::try_new(
                fields.clone(),
                vec![
                    Arc::new(Float64Array::from(xs)) as ArrayRef,
                    Arc::new(Float64Array::from(ys)),
                    Arc::new(Float64Array::from(zs)),
                ],
                Some(arrow::buffer::NullBuffer::from(valid)),
            )?;
            Ok(ColumnarValue::Array(Arc::new(out)))
        }),
    )
}

fn point_fields() -> arrow::datatypes::Fields {
    use arrow::datatypes::Field;
    vec![
        Field::new("x", DataType::Float64, true),
        Field::new("y", DataType::Float64, true),
        Field::new("z", DataType::Float64, true),
    ]
    .into()
}

/// A statistic of 3-vectors that DataFusion aggregates in parts and merges: the aggregate
/// `NAME(x, y, z)` gives [`XyzStat::value`] as a Float64.
pub(crate) trait XyzStat: std::fmt::Debug + Default + Send + Sync + 'static {
    const NAME: &'static str;
    /// Adds one vector (the statistic decides which ones count).
    fn add(&mut self, v: [f64; 3]);
    /// The statistic, None without vectors.
    fn value(&self) -> Option<f64>;
    /// Types of the partial state, as [`XyzStat::state`] lists it.
    fn state_types() -> Vec<DataType>;
    fn state(&self) -> Vec<ScalarValue>;
    /// Merges partial states (columns as [`XyzStat::state_types`]).
    fn merge_states(&mut self, states: &[ArrayRef]) -> datafusion::error::Result<()>;
}

/// The DataFusion accumulator of any [`XyzStat`].
#[derive(Debug, Default)]
struct XyzAccumulator<S>(S);

impl<S: XyzStat> Accumulator for XyzAccumulator<S> {
    fn update_batch(&mut self, values: &[ArrayRef]) -> datafusion::error::Result<()> {
        let c = float_cols::<3>(values)?;
        for r in 0..c[0].len() {
            if let Some(v) = row(&c, r) {
                self.0.add(v);
            }
        }
        Ok(())
    }

    fn evaluate(&mut self) -> datafusion::error::Result<ScalarValue> {
        Ok(ScalarValue::Float64(self.0.value()))
    }

    fn size(&self) -> usize {
        std::mem::size_of_val(self)
    }

    fn state(&mut self) -> datafusion::error::Result<Vec<ScalarValue>> {
        Ok(self.0.state())
    }

    fn merge_batch(&mut self, states: &[ArrayRef]) -> datafusion::error::Result<()> {
        self.0.merge_states(states)
    }
}

/// The aggregate UDF of an [`XyzStat`]: three Float64 arguments, a Float64 result.
fn xyz_aggregate<S: XyzStat>() -> datafusion::logical_expr::AggregateUDF {
    create_udaf(
        S::NAME,
        vec![DataType::Float64; 3],
        Arc::new(DataType::Float64),
        Volatility::Immutable,
        Arc::new(|_| Ok(Box::new(XyzAccumulator::<S>::default()))),
        Arc::new(S::state_types()),
    )
}

/// Mean resultant length of directions: sums of the normalized vectors and their count.
#[derive(Debug, Default)]
pub(crate) struct Coherence {
    sum: [f64; 3],
    n: u64,
}

impl XyzStat for Coherence {
    const NAME: &'static str = "dir_coherence";

    /// Adds a direction (zero, NaN or infinite ones are left out).
    fn add(&mut self, d: [f64; 3]) {
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if len > 0.0 && len.is_finite() {
            for (s, x) in self.sum.iter_mut().zip(d) {
                *s += x / len;
            }
            self.n += 1;
        }
    }

    /// The mean resultant length.
    fn value(&self) -> Option<f64> {
        let s = self.sum;
        (self.n > 0).then(|| (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt() / self.n as f64)
    }

    fn state_types() -> Vec<DataType> {
        vec![DataType::Float64, DataType::Float64, DataType::Float64, DataType::UInt64]
    }

    fn state(&self) -> Vec<ScalarValue> {
        let mut v: Vec<ScalarValue> = self.sum.iter().map(|x| ScalarValue::Float64(Some(*x))).collect();
        v.push(ScalarValue::UInt64(Some(self.n)));
        v
    }

    fn merge_states(&mut self, states: &[ArrayRef]) -> datafusion::error::Result<()> {
        let c = float_cols::<3>(states)?;
        let n = states
            .get(3)
            .and_then(|a| a.as_primitive_opt::<UInt64Type>())
            .ok_or_else(|| DataFusionError::Internal("dir_coherence: bad state".into()))?;
        for r in 0..n.len() {
            for (s, col) in self.sum.iter_mut().zip(c) {
                *s += col.value(r);
            }
            self.n += n.value(r);
        }
        Ok(())
    }
}

/// Spread of points about their centroid: count, mean and sum of squared distances (merged with
/// Chan et al.'s formula, so points far from the origin lose no precision).
#[derive(Debug, Default)]
pub(crate) struct Spread {
    n: u64,
    mean: [f64; 3],
    m2: f64,
}

impl Spread {
    fn merge(&mut self, n: u64, mean: [f64; 3], m2: f64) {
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

    /// Adds a point (ones with a NaN or infinite coordinate are left out).
    fn add(&mut self, p: [f64; 3]) {
        if p.iter().all(|c| c.is_finite()) {
            self.merge(1, p, 0.0);
        }
    }

    /// The RMS distance from the centroid.
    fn value(&self) -> Option<f64> {
        (self.n > 0).then(|| (self.m2 / self.n as f64).max(0.0).sqrt())
    }

    fn state_types() -> Vec<DataType> {
        vec![DataType::UInt64, DataType::Float64, DataType::Float64, DataType::Float64, DataType::Float64]
    }

    fn state(&self) -> Vec<ScalarValue> {
        let mut v = vec![ScalarValue::UInt64(Some(self.n))];
        v.extend(self.mean.iter().map(|x| ScalarValue::Float64(Some(*x))));
        v.push(ScalarValue::Float64(Some(self.m2)));
        v
    }

    fn merge_states(&mut self, states: &[ArrayRef]) -> datafusion::error::Result<()> {
        let bad = || DataFusionError::Internal("origin_spread: bad state".into());
        let n = states.first().and_then(|a| a.as_primitive_opt::<UInt64Type>()).ok_or_else(bad)?;
        let c = float_cols::<4>(states.get(1..).ok_or_else(bad)?)?;
        for r in 0..n.len() {
            self.merge(n.value(r), [c[0].value(r), c[1].value(r), c[2].value(r)], c[3].value(r));
        }
        Ok(())
    }
}

/// Registers every ray function in `ctx`, scene-dependent ones over `scene`.
pub fn register_functions(ctx: &SessionContext, scene: Arc<SceneContext>) {
    ctx.register_udf(ray_point_udf());
    ctx.register_udaf(xyz_aggregate::<Coherence>());
    ctx.register_udaf(xyz_aggregate::<Spread>());
    ctx.register_udf(rowwise::<3, _, UInt8Array>("octant", false, DataType::UInt8, |d, _| {
        Some(u8::from(d[0] < 0.0) | (u8::from(d[1] < 0.0) << 1) | (u8::from(d[2] < 0.0) << 2))
    }));
    ctx.register_udf(rowwise::<6, _, Float64Array>("angle_between", false, DataType::Float64, |v, _| {
        angle([v[0], v[1], v[2]], [v[3], v[4], v[5]])
    }));
    ctx.register_udf(rowwise::<3, _, UInt32Array>("dir_bin", true, DataType::UInt32, |d, n| {
        let n = n.filter(|n| (1..=65535).contains(n))? as u32;
        octahedral_bin(d, n)
    }));
    ctx.register_udf(rowwise::<12, _, BooleanArray>("ray_aabb_hit", false, DataType::Boolean, |v, _| {
        Some(slab_hit([v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]], [v[9], v[10], v[11]]))
    }));
    let sc = scene.clone();
    ctx.register_udf(rowwise::<3, _, UInt64Array>("morton3", true, DataType::UInt64, move |p, bits| {
        let (lo, hi) = sc.bounds?;
        let bits = bits.filter(|b| (1..=21).contains(b))?;
        let max = ((1u64 << bits) - 1) as f64;
        let q = |k: usize| {
            let ext = (hi[k] - lo[k]).max(f64::MIN_POSITIVE);
            (((p[k] - lo[k]) / ext).clamp(0.0, 1.0) * max).round() as u64
        };
        Some(morton(q(0), q(1), q(2)))
    }));
    ctx.register_udf(rowwise::<6, _, BooleanArray>("aims_at_light", false, DataType::Boolean, move |v, _| {
        let (o, d) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
        Some(scene.lights.iter().any(|t| hits_triangle(o, d, t)))
    }));
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
            whole.merge(1, *p, 0.0);
        }
        let rms = (whole.m2 / whole.n as f64).sqrt();
        assert!((rms - 0.5).abs() < 1e-9, "{rms}");
        let (mut a, mut b) = (Spread::default(), Spread::default());
        for (i, p) in pts.iter().enumerate() {
            if i < 300 { a.merge(1, *p, 0.0) } else { b.merge(1, *p, 0.0) }
        }
        a.merge(b.n, b.mean, b.m2);
        assert!((a.m2 - whole.m2).abs() < 1e-6 && a.n == whole.n);
    }

    #[test]
    fn morton_interleaves_bits() {
        assert_eq!(morton(1, 0, 0), 1);
        assert_eq!(morton(0, 1, 0), 2);
        assert_eq!(morton(0, 0, 1), 4);
        assert_eq!(morton(3, 0, 0), 0b1001);
        assert_eq!(morton(0x1f_ffff, 0x1f_ffff, 0x1f_ffff), (1u64 << 63) - 1);
    }

    #[test]
    fn octahedral_bins_cover_the_sphere() {
        let n = 8;
        let mut seen = std::collections::HashSet::new();
        for i in 0..4000 {
            let z = i as f64 / 2000.0 - 1.0;
            let a = i as f64 * 2.399_963;
            let r = (1.0 - z * z).sqrt();
            let b = octahedral_bin([r * a.cos(), r * a.sin(), z], n).unwrap();
            assert!(b < n * n);
            seen.insert(b);
        }
        assert!(seen.len() as u32 > n * n * 9 / 10, "{} of {} cells", seen.len(), n * n);
        assert_eq!(octahedral_bin([0.0, 0.0, 0.0], n), None);
        // Opposite directions land in different cells.
        assert_ne!(octahedral_bin([0.3, 0.4, 0.866], n), octahedral_bin([-0.3, -0.4, -0.866], n));
    }

    #[test]
    fn slab_test_handles_axis_parallel_and_inside_rays() {
        let (lo, hi) = ([0.0; 3], [1.0; 3]);
        assert!(slab_hit([-1.0, 0.5, 0.5], [1.0, 0.0, 0.0], lo, hi));
        assert!(!slab_hit([-1.0, 0.5, 0.5], [-1.0, 0.0, 0.0], lo, hi), "pointing away");
        assert!(!slab_hit([-1.0, 1.5, 0.5], [1.0, 0.0, 0.0], lo, hi), "parallel outside");
        assert!(slab_hit([0.5, 0.5, 0.5], [0.0, 0.0, 1.0], lo, hi), "inside");
        assert!(slab_hit([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], lo, hi), "through a corner");
    }

    #[test]
    fn triangle_hits_are_two_sided_and_forward_only() {
        let tri = [[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 1.0]];
        assert!(hits_triangle([0.2, 0.0, 0.2], [0.0, 1.0, 0.0], &tri));
        assert!(hits_triangle([0.2, 2.0, 0.2], [0.0, -1.0, 0.0], &tri));
        assert!(!hits_triangle([0.2, 0.0, 0.2], [0.0, -1.0, 0.0], &tri), "behind the origin");
        assert!(!hits_triangle([0.9, 0.0, 0.9], [0.0, 1.0, 0.0], &tri), "outside");
        assert!(!hits_triangle([0.2, 0.0, 0.2], [1.0, 0.0, 0.0], &tri), "parallel");
    }
}
