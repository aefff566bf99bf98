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
//! Float arguments are three (or seven, twelve) Float32 columns read as they are, or Float64
//! (mixed arguments and integer literals coerce to Float64). NaN or infinite inputs give NULL,
//! never an error. Scene-dependent functions use the scene of
//! the session's first dataset: its bounds (origins and hit points) and its `lights` table.

use std::marker::PhantomData;
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, AsArray, BooleanArray, Float64Array, Int64Array, PrimitiveArray, UInt8Array, UInt32Array,
    UInt64Array,
};
use arrow::datatypes::{
    ArrowPrimitiveType, DataType, Field, FieldRef, Float32Type, Float64Type, Int64Type, UInt64Type,
};
use datafusion::common::ScalarValue;
use datafusion::error::DataFusionError;
use datafusion::logical_expr::function::{AccumulatorArgs, StateFieldsArgs};
use datafusion::logical_expr::{
    Accumulator, AggregateUDF, AggregateUDFImpl, ColumnarValue, EmitTo, GroupsAccumulator, ScalarUDF, Signature,
    SimpleScalarUDF, TypeSignature, Volatility,
};
use datafusion::prelude::SessionContext;
use store::Dataset;

use crate::Result;

/// A ray function's documentation.
#[derive(Clone, Copy, Debug)]
pub struct RayFunction {
    pub name: &'static str,
    pub description: &'static str,
    pub example: &'static str,
    /// (argument, meaning)
    pub args: &'static [(&'static str, &'static str)],
}

const fn f(
    name: &'static str,
    description: &'static str,
    example: &'static str,
    args: &'static [(&'static str, &'static str)],
) -> RayFunction {
    RayFunction { name, description, example, args }
}

/// What each ray function is, for `SHOW FUNCTIONS`, `information_schema.routines` and
/// `rtvtk sql`'s `\df`.
pub const RAY_FUNCTIONS: [RayFunction; 9] = [
    f(
        "octant",
        "Octant of a direction: bit 0 set for dx < 0, bit 1 for dy < 0, bit 2 for dz < 0 (UInt8); NULL for NULL, NaN or infinite components.",
        "octant(dir_x, dir_y, dir_z)",
        &[("dx, dy, dz", "the direction")],
    ),
    f(
        "angle_between",
        "Angle between two directions in radians (Float64, 0..pi); NULL when either is zero, NaN or infinite.",
        "angle_between(dir_x, dir_y, dir_z, 0, -1, 0)",
        &[("ax, ay, az", "the first direction"), ("bx, by, bz", "the second direction")],
    ),
    f(
        "dir_bin",
        "Cell of a direction on an n x n octahedral map (UInt32, 0..n*n); NULL for a zero direction or n outside 1..=65535.",
        "dir_bin(dir_x, dir_y, dir_z, 16)",
        &[("dx, dy, dz", "the direction"), ("n", "cells per side of the map")],
    ),
    f(
        "ray_aabb_hit",
        "Whether the ray (t >= 0) enters the axis-aligned box (Boolean, slab test).",
        "ray_aabb_hit(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, min_x, min_y, min_z, max_x, max_y, max_z)",
        &[("ox, oy, oz", "the origin"), ("dx, dy, dz", "the direction"), ("min_*, max_*", "the box corners")],
    ),
    f(
        "morton3",
        "Morton code (UInt64) of a point's cell over the scene bounds (origins and hit points of the session's first dataset), `bits` per axis.",
        "morton3(origin_x, origin_y, origin_z, 10)",
        &[("x, y, z", "the point"), ("bits", "bits per axis, 1..=21")],
    ),
    f(
        "aims_at_light",
        "Whether the ray's line hits an emitter triangle of the scene (its `lights` table) in front of its origin (Boolean, watertight test): false for a shadow ray that points at no light, the paper's bug.",
        "aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)",
        &[("ox, oy, oz", "the origin"), ("dx, dy, dz", "the direction")],
    ),
    f(
        "ray_point",
        "The point o + t*d as a struct {x, y, z} of Float64 (`ray_point(..)['x']`); NULL for a miss (NULL t).",
        "ray_point(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t)['x']",
        &[("ox, oy, oz", "the origin"), ("dx, dy, dz", "the direction"), ("t", "the distance along it")],
    ),
    f(
        "dir_coherence",
        "Aggregate: mean resultant length of the normalized directions (Float64): 1 when all are parallel, near 0 for directions spread over the sphere.",
        "dir_coherence(dir_x, dir_y, dir_z)",
        &[("dx, dy, dz", "the directions")],
    ),
    f(
        "origin_spread",
        "Aggregate: root-mean-square distance of the points from their centroid (Float64), numerically stable far from the origin.",
        "origin_spread(origin_x, origin_y, origin_z)",
        &[("x, y, z", "the points")],
    ),
];

/// The documentation of ray function `name` (from [`RAY_FUNCTIONS`]).
fn documentation_of(name: &str) -> Option<datafusion::logical_expr::Documentation> {
    let RayFunction { description, example, args, .. } = RAY_FUNCTIONS.iter().find(|f| f.name == name)?;
    let section = datafusion::logical_expr::DocSection {
        include: true,
        label: "Ray functions (rtvtk)",
        description: Some("functions over the rays of a trace"),
    };
    let mut b = datafusion::logical_expr::Documentation::builder(section, *description, *example);
    for (arg, what) in args.iter() {
        b = b.with_argument(*arg, *what);
    }
    Some(b.build())
}

/// A ray function with its documentation: a `ScalarUDFImpl` over the function's kernel, so
/// `SHOW FUNCTIONS` and `information_schema.routines` describe it.
#[derive(Debug, PartialEq, Eq, Hash)]
struct Documented {
    inner: ScalarUDF,
    doc: Option<datafusion::logical_expr::Documentation>,
    /// The scene a scene-dependent function was made for (sent with it to a cluster's nodes).
    scene: Option<SceneRef>,
}

/// A scene, compared and hashed by identity (a function made for it is the same function).
#[derive(Clone, Debug)]
struct SceneRef(Arc<SceneContext>);

impl PartialEq for SceneRef {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Eq for SceneRef {}

impl std::hash::Hash for SceneRef {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        std::ptr::hash(Arc::as_ptr(&self.0), state);
    }
}

impl datafusion::logical_expr::ScalarUDFImpl for Documented {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn aliases(&self) -> &[String] {
        self.inner.aliases()
    }
    fn signature(&self) -> &Signature {
        self.inner.signature()
    }
    fn return_type(&self, arg_types: &[DataType]) -> datafusion::error::Result<DataType> {
        self.inner.return_type(arg_types)
    }
    fn return_field_from_args(
        &self,
        args: datafusion::logical_expr::ReturnFieldArgs,
    ) -> datafusion::error::Result<FieldRef> {
        self.inner.return_field_from_args(args)
    }
    fn invoke_with_args(
        &self,
        args: datafusion::logical_expr::ScalarFunctionArgs,
    ) -> datafusion::error::Result<ColumnarValue> {
        self.inner.invoke_with_args(args)
    }
    fn coerce_types(&self, arg_types: &[DataType]) -> datafusion::error::Result<Vec<DataType>> {
        self.inner.coerce_types(arg_types)
    }
    fn documentation(&self) -> Option<&datafusion::logical_expr::Documentation> {
        self.doc.as_ref()
    }
}

/// `udf` with its entry of [`RAY_FUNCTIONS`] as documentation.
fn documented(udf: ScalarUDF) -> ScalarUDF {
    let doc = documentation_of(udf.name());
    ScalarUDF::new_from_impl(Documented { inner: udf, doc, scene: None })
}

/// [`documented`] for a function of `scene`.
fn documented_for(udf: ScalarUDF, scene: &Arc<SceneContext>) -> ScalarUDF {
    let doc = documentation_of(udf.name());
    ScalarUDF::new_from_impl(Documented { inner: udf, doc, scene: Some(SceneRef(scene.clone())) })
}

/// Whether `udf` is one of the ray functions, and the scene it was made for (None for the
/// scene-independent ones).
pub(crate) fn ray_function_scene(udf: &ScalarUDF) -> Option<Option<Arc<SceneContext>>> {
    let d = udf.inner().as_ref().downcast_ref::<Documented>()?;
    Some(d.scene.as_ref().map(|s| s.0.clone()))
}

/// Whether `udaf` is one of the ray aggregates.
pub(crate) fn is_ray_aggregate(udaf: &AggregateUDF) -> bool {
    let inner = udaf.inner().as_ref();
    inner.downcast_ref::<XyzUdaf<Coherence>>().is_some() || inner.downcast_ref::<XyzUdaf<Spread>>().is_some()
}

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
        // `Dataset::table` has checked the table against `store::scene::lights_schema`.
        if let Some(batch) = ds.table(store::scene::LIGHTS_TABLE)? {
            let mut cols = Vec::with_capacity(9);
            for name in store::scene::col::VERTEX.iter().flatten() {
                let c = batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>().cloned());
                cols.push(c.ok_or_else(|| store::Error::Table {
                    name: store::scene::LIGHTS_TABLE.into(),
                    path: ds.dir().to_path_buf(),
                    message: format!("column `{name}` is missing or not Float32"),
                })?);
            }
            for r in 0..batch.num_rows() {
                let p = |v: usize| [0, 1, 2].map(|a| f64::from(cols[v * 3 + a].value(r)));
                lights.push([p(0), p(1), p(2)]);
            }
        }
        Ok(Self { bounds, lights })
    }
}

fn arrays(args: &[ColumnarValue]) -> datafusion::error::Result<Vec<ArrayRef>> {
    ColumnarValue::values_to_arrays(args)
}

/// `N` float columns of one type: Float32 columns are read as they are (no cast to Float64).
enum Floats<'a, const N: usize> {
    F32([&'a PrimitiveArray<Float32Type>; N]),
    F64([&'a PrimitiveArray<Float64Type>; N]),
}

impl<'a, const N: usize> Floats<'a, N> {
    /// The first `N` arguments, all Float32 or all Float64 (as the signatures ask).
    fn of(a: &'a [ArrayRef]) -> datafusion::error::Result<Self> {
        let args = a.get(..N).ok_or_else(|| DataFusionError::Execution(format!("expected {N} float arguments")))?;
        let as_f32: Option<Vec<_>> = args.iter().map(|c| c.as_primitive_opt::<Float32Type>()).collect();
        if let Some(Ok(c)) = as_f32.map(<[_; N]>::try_from) {
            return Ok(Self::F32(c));
        }
        let as_f64: Option<Vec<_>> = args.iter().map(|c| c.as_primitive_opt::<Float64Type>()).collect();
        match as_f64.map(<[_; N]>::try_from) {
            Some(Ok(c)) => Ok(Self::F64(c)),
            _ => Err(DataFusionError::Execution(format!(
                "expected {N} Float32 or {N} Float64 arguments, found {}",
                args.iter().map(|c| c.data_type().to_string()).collect::<Vec<_>>().join(", ")
            ))),
        }
    }

    fn len(&self) -> usize {
        match self {
            Self::F32(c) => c.first().map_or(0, |c| c.len()),
            Self::F64(c) => c.first().map_or(0, |c| c.len()),
        }
    }

    /// Calls `f(row, values)` for every row whose values are all non-null and finite, in order.
    fn each_valid(&self, f: impl FnMut(usize, [f64; N])) {
        match self {
            Self::F32(c) => each_valid(c, f),
            Self::F64(c) => each_valid(c, f),
        }
    }
}

fn each_valid<T: ArrowPrimitiveType, const N: usize>(cols: &[&PrimitiveArray<T>; N], mut f: impl FnMut(usize, [f64; N]))
where
    T::Native: Into<f64>,
{
    let len = cols.first().map_or(0, |c| c.len());
    let values: [&[T::Native]; N] = cols.map(|c| c.values().as_ref());
    let nulls = cols.iter().any(|c| c.null_count() > 0);
    for r in 0..len {
        if nulls && cols.iter().any(|c| c.is_null(r)) {
            continue;
        }
        let mut v = [0.0; N];
        let mut finite = true;
        for (o, col) in v.iter_mut().zip(&values) {
            *o = col[r].into();
            finite &= o.is_finite();
        }
        if finite {
            f(r, v);
        }
    }
}

/// A signature of `n` floats (all Float32, read as they are, or all Float64: mixed arguments and
/// integer literals coerce to one of them) and, with `int_param`, an integer last.
fn float_signature(n: usize, int_param: bool) -> Signature {
    let variant = |t: DataType| {
        let mut v = vec![t; n];
        if int_param {
            v.push(DataType::Int64);
        }
        TypeSignature::Exact(v)
    };
    Signature::one_of(vec![variant(DataType::Float32), variant(DataType::Float64)], Volatility::Immutable)
}

/// The angle between two directions (`store::geom`); None for a zero or non-finite direction.
fn angle(a: [f64; 3], b: [f64; 3]) -> Option<f64> {
    store::geom::angle_between(a, b)
}

/// Whether the ray from `o` along `d` hits the triangle at t > 0: the watertight test of
/// `store::geom`, so a ray through a light's edge is decided exactly, with no tolerance.
fn hits_triangle(o: [f64; 3], d: [f64; 3], tri: &[[f64; 3]; 3]) -> bool {
    store::geom::ray_triangle(o, d, tri).is_some()
}

/// Cell of a direction on an n × n octahedral map (row-major), None for a zero direction.
fn octahedral_bin(d: [f64; 3], n: u32) -> Option<u32> {
    let [x, y] = store::geom::oct_fold(d)?;
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

/// The bits of an 11-bit value spread three apart (bit k to bit 3k).
const fn spread11(v: u64) -> u64 {
    let mut out = 0;
    let mut k = 0;
    while k < 11 {
        out |= ((v >> k) & 1) << (3 * k);
        k += 1;
    }
    out
}

const SPREAD11: [u64; 2048] = {
    let mut t = [0; 2048];
    let mut i = 0;
    while i < 2048 {
        t[i] = spread11(i as u64);
        i += 1;
    }
    t
};

/// The low 21 bits of a value spread three apart, by two table lookups.
#[inline]
fn spread21(v: u64) -> u64 {
    SPREAD11[(v & 0x7ff) as usize] | (SPREAD11[((v >> 11) & 0x3ff) as usize] << 33)
}

/// Interleaves the low 10 bits of x, y, z (x in the lowest position) by shifts and masks, in
/// 32-bit lanes.
#[inline]
fn morton10(x: i32, y: i32, z: i32) -> u32 {
    fn spread(v: i32) -> u32 {
        let v = v as u32 & 0x3ff;
        let v = (v | (v << 16)) & 0x0300_00ff;
        let v = (v | (v << 8)) & 0x0300_f00f;
        let v = (v | (v << 4)) & 0x030c_30c3;
        (v | (v << 2)) & 0x0924_9249
    }
    spread(x) | (spread(y) << 1) | (spread(z) << 2)
}

/// Interleaves the low 21 bits of x, y, z (x in the lowest position).
#[cfg(test)]
fn morton(x: u64, y: u64, z: u64) -> u64 {
    spread21(x) | (spread21(y) << 1) | (spread21(z) << 2)
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
    T: Clone,
    A: Array + FromIterator<Option<T>> + 'static,
{
    let fname = name.to_string();
    let fun = Arc::new(move |args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let c = Floats::<N>::of(&a)?;
        let ints: Option<&Int64Array> =
            match a.get(N).filter(|_| int_param) {
                Some(i) => Some(i.as_primitive_opt::<Int64Type>().ok_or_else(|| {
                    DataFusionError::Execution(format!("{fname}: the last argument must be an integer"))
                })?),
                None => None,
            };
        let mut out: Vec<Option<T>> = vec![None; c.len()];
        c.each_valid(|r, v| {
            let k = match ints {
                Some(i) if i.is_null(r) => return,
                Some(i) => Some(i.value(r)),
                None => None,
            };
            out[r] = f(v, k);
        });
        Ok(ColumnarValue::Array(Arc::new(out.into_iter().collect::<A>()) as ArrayRef))
    });
    ScalarUDF::from(SimpleScalarUDF::new_with_signature(name, float_signature(N, int_param), ret, fun))
}

/// `octant(dx, dy, dz)`: bit 0 for dx < 0, bit 1 for dy < 0, bit 2 for dz < 0; NULL when a
/// component is NULL, NaN or infinite. A kernel of its own (no per-row closure, no option per
/// row; finiteness packed into a validity bitmap in one pass): it is the grouping key of direction-coherence queries over every ray.
fn octant_udf() -> ScalarUDF {
    fn kernel<T: ArrowPrimitiveType>(c: &[&PrimitiveArray<T>; 3]) -> datafusion::error::Result<UInt8Array>
    where
        T::Native: Into<f64>,
    {
        let [x, y, z] = c.map(|a| a.values().as_ref());
        let n = x.len().min(y.len()).min(z.len());
        let comp = |v: &[T::Native], i: usize| -> f64 { v[i].into() };
        let values: Vec<u8> = (0..n)
            .map(|i| u8::from(comp(x, i) < 0.0) | (u8::from(comp(y, i) < 0.0) << 1) | (u8::from(comp(z, i) < 0.0) << 2))
            .collect();
        let finite = arrow::buffer::BooleanBuffer::collect_bool(n, |i| {
            comp(x, i).is_finite() & comp(y, i).is_finite() & comp(z, i).is_finite()
        });
        let mut nulls = arrow::buffer::NullBuffer::union(c[0].nulls(), c[1].nulls());
        nulls = arrow::buffer::NullBuffer::union(nulls.as_ref(), c[2].nulls());
        if finite.count_set_bits() < n {
            nulls = arrow::buffer::NullBuffer::union(nulls.as_ref(), Some(&arrow::buffer::NullBuffer::new(finite)));
        }
        Ok(UInt8Array::try_new(values.into(), nulls)?)
    }
    let fun = Arc::new(|args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let out = match Floats::<3>::of(&a)? {
            Floats::F32(c) => kernel(&c)?,
            Floats::F64(c) => kernel(&c)?,
        };
        Ok(ColumnarValue::Array(Arc::new(out) as ArrayRef))
    });
    ScalarUDF::from(SimpleScalarUDF::new_with_signature("octant", float_signature(3, false), DataType::UInt8, fun))
}

/// The kernel of [`morton_udf`].
fn morton_kernel<T: ArrowPrimitiveType>(
    c: &[&PrimitiveArray<T>; 3],
    bits: &Int64Array,
    bounds: Option<([f64; 3], [f64; 3])>,
) -> datafusion::error::Result<UInt64Array>
where
    T::Native: Into<f64>,
{
    let n = c.iter().map(|a| a.len()).min().unwrap_or(0).min(bits.len());
    let Some((lo, hi)) = bounds else { return Ok(UInt64Array::new_null(n)) };
    let ext = [0, 1, 2].map(|k| (hi[k] - lo[k]).max(f64::MIN_POSITIVE));
    let [x, y, z] = c.map(|a| a.values().as_ref());
    let b = &bits.values()[..n];
    let ok = |i: usize| -> bool {
        (1..=21).contains(&b[i]) && x[i].into().is_finite() && y[i].into().is_finite() && z[i].into().is_finite()
    };
    // Without early exits, so that these passes run in SIMD lanes.
    let finite = |c: &[T::Native]| c.iter().fold(true, |a, &v| a & v.into().is_finite());
    let all_ok = b.iter().fold(true, |a, v| a & (1..=21).contains(v)) && finite(x) && finite(y) && finite(z);
    // Column passes that run in SIMD lanes. Quantization multiplies by the reciprocal of the
    // extent (a division per value was the kernel's largest cost) and redoes, exactly, the rare
    // values whose scaled position lies within 1e-6 of a rounding boundary (k + 0.5): the
    // reciprocal's error is below 1e-9 there (at most 2^21 cells), so every other value rounds
    // as the division would. The exact path converts through i32 (packed instructions on
    // x86-64, exact below 2^21) and rounds half away from zero without libm's round. Up to 10 bits per axis the bits are spread by
    // shifts and masks in 32-bit lanes, beyond by table lookups. Invalid rows compute garbage
    // their NULL hides.
    let same_bits = b.first().filter(|&&b0| b.iter().all(|&v| v == b0)).copied();
    let max_of = |bits: i64| ((1i32 << bits.clamp(0, 21)) - 1) as f64;
    let mut qs = [vec![0i32; n], vec![0i32; n], vec![0i32; n]];
    for (k, (col, q)) in [x, y, z].into_iter().zip(qs.iter_mut()).enumerate() {
        let (lo, ext) = (lo[k], ext[k]);
        let exact = |v: T::Native, max: f64| -> i32 {
            let u = ((v.into() - lo) / ext).clamp(0.0, 1.0) * max;
            let t = u as i32;
            t + i32::from(u - f64::from(t) >= 0.5)
        };
        let inv = 1.0 / ext;
        // Adding 2^52 rounds to the nearest integer,
        // which then sits in the low bits (no float-to-int conversion, so the pass stays in SIMD
        // lanes); it differs from rounding half away from zero only on ties, which are near.
        const TWO52: f64 = 4_503_599_627_370_496.0;
        let fast = |v: T::Native, max: f64| -> (i32, bool) {
            let u = ((v.into() - lo) * inv).clamp(0.0, 1.0) * max;
            let r = u + TWO52;
            let f = u - (r - TWO52);
            (r.to_bits() as i32, (f.abs() - 0.5).abs() < 1e-6)
        };
        match same_bits {
            Some(bits) => {
                let max = max_of(bits);
                // Blocks of 1024: one flag per block keeps the pass in SIMD lanes; a block with a
                // value near a boundary (a few per million values) is redone exactly.
                for (qc, vc) in q.chunks_mut(1024).zip(col.chunks(1024)) {
                    let mut near = false;
                    for (q, &v) in qc.iter_mut().zip(vc) {
                        let (qv, nr) = fast(v, max);
                        *q = qv;
                        near |= nr;
                    }
                    if near {
                        qc.iter_mut().zip(vc).for_each(|(q, &v)| *q = exact(v, max));
                    }
                }
            }
            None => q.iter_mut().zip(col).zip(b).for_each(|((q, &v), &bits)| *q = exact(v, max_of(bits))),
        }
    }
    let values: Vec<u64> = if same_bits.is_some_and(|b| b <= 10) {
        let (x, y, z) = (&qs[0][..n], &qs[1][..n], &qs[2][..n]);
        let mut values = vec![0u64; n];
        for (i, o) in values.iter_mut().enumerate() {
            *o = u64::from(morton10(x[i], y[i], z[i]));
        }
        values
    } else {
        let mut values = vec![0u64; n];
        for (k, q) in qs.iter().enumerate() {
            for (o, &q) in values.iter_mut().zip(q) {
                *o |= spread21(q as u64) << k;
            }
        }
        values
    };
    let valid = if all_ok { None } else { Some(arrow::buffer::BooleanBuffer::collect_bool(n, ok)) };
    let mut nulls = arrow::buffer::NullBuffer::union(c[0].nulls(), c[1].nulls());
    nulls = arrow::buffer::NullBuffer::union(nulls.as_ref(), c[2].nulls());
    nulls = arrow::buffer::NullBuffer::union(nulls.as_ref(), bits.nulls());
    if let Some(valid) = valid {
        nulls = arrow::buffer::NullBuffer::union(nulls.as_ref(), Some(&arrow::buffer::NullBuffer::new(valid)));
    }
    Ok(UInt64Array::try_new(values.into(), nulls)?)
}

/// `morton3(x, y, z, bits)`: the Morton code of a point's cell, `bits` (1..=21) per axis, over the
/// scene bounds (each axis quantized to `round(clamp((v - lo) / (hi - lo), 0, 1) * (2^bits - 1))`);
/// NULL for a NULL, NaN or infinite coordinate, a NULL or out-of-range `bits`, or a dataset without
/// bounds. A kernel of its own (one pass for values and validity, no per-row option, rounding
/// without a libm call): it is the grouping key of cell histograms over every ray.
fn morton_udf(bounds: Option<([f64; 3], [f64; 3])>) -> ScalarUDF {
    let fun = Arc::new(move |args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let bits = a
            .get(3)
            .and_then(|b| b.as_primitive_opt::<Int64Type>())
            .ok_or_else(|| DataFusionError::Execution("morton3: the last argument must be an integer".into()))?;
        let out = match Floats::<3>::of(&a)? {
            Floats::F32(c) => morton_kernel(&c, bits, bounds)?,
            Floats::F64(c) => morton_kernel(&c, bits, bounds)?,
        };
        Ok(ColumnarValue::Array(Arc::new(out) as ArrayRef))
    });
    ScalarUDF::from(SimpleScalarUDF::new_with_signature("morton3", float_signature(3, true), DataType::UInt64, fun))
}

/// `ray_point(ox, oy, oz, dx, dy, dz, t)`: the point at `t` along the ray, as a struct.
fn ray_point_udf() -> ScalarUDF {
    let fields = point_fields();
    let ret = DataType::Struct(fields.clone());
    let fun = Arc::new(move |args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let c = Floats::<7>::of(&a)?;
        let n = c.len();
        let (mut xs, mut ys, mut zs) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        let mut valid = vec![false; n];
        c.each_valid(|r, v| {
            xs[r] = v[0] + v[6] * v[3];
            ys[r] = v[1] + v[6] * v[4];
            zs[r] = v[2] + v[6] * v[5];
            valid[r] = true;
        });
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
    });
    ScalarUDF::from(SimpleScalarUDF::new_with_signature("ray_point", float_signature(7, false), ret, fun))
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
/// `NAME(x, y, z)` gives [`XyzStat::value`] as a Float64. Rows with a NULL, NaN or infinite
/// coordinate are left out.
pub(crate) trait XyzStat: std::fmt::Debug + Default + Clone + Send + Sync + 'static {
    const NAME: &'static str;
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
    doc: Option<datafusion::logical_expr::Documentation>,
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
    fn documentation(&self) -> Option<&datafusion::logical_expr::Documentation> {
        self.doc.as_ref()
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

fn xyz_aggregate<S: XyzStat>() -> AggregateUDF {
    AggregateUDF::from(XyzUdaf::<S> {
        signature: float_signature(3, false),
        doc: documentation_of(S::NAME),
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

/// The ray aggregates.
pub fn ray_aggregates() -> Vec<AggregateUDF> {
    vec![xyz_aggregate::<Coherence>(), xyz_aggregate::<Spread>()]
}

/// The scalar ray functions, scene-dependent ones over `scene`.
pub fn ray_scalar_functions(scene: Arc<SceneContext>) -> Vec<ScalarUDF> {
    let mut out = vec![
        documented(ray_point_udf()),
        documented(octant_udf()),
        documented(rowwise::<6, _, Float64Array>("angle_between", false, DataType::Float64, |v, _| {
            angle([v[0], v[1], v[2]], [v[3], v[4], v[5]])
        })),
        documented(rowwise::<3, _, UInt32Array>("dir_bin", true, DataType::UInt32, |d, n| {
            let n = n.filter(|n| (1..=65535).contains(n))? as u32;
            octahedral_bin(d, n)
        })),
        documented(rowwise::<12, _, BooleanArray>("ray_aabb_hit", false, DataType::Boolean, |v, _| {
            Some(slab_hit([v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]], [v[9], v[10], v[11]]))
        })),
        documented_for(morton_udf(scene.bounds), &scene),
    ];
    let lights = scene.clone();
    out.push(documented_for(
        rowwise::<6, _, BooleanArray>("aims_at_light", false, DataType::Boolean, move |v, _| {
            let (o, d) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
            Some(lights.lights.iter().any(|t| hits_triangle(o, d, t)))
        }),
        &scene,
    ));
    out
}

/// Registers every ray function in `ctx`, scene-dependent ones over `scene`.
pub fn register_functions(ctx: &SessionContext, scene: Arc<SceneContext>) {
    for f in ray_scalar_functions(scene) {
        ctx.register_udf(f);
    }
    for f in ray_aggregates() {
        ctx.register_udaf(f);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_ray_function_is_documented_in_the_session() {
        let ctx =
            SessionContext::new_with_config(datafusion::prelude::SessionConfig::new().with_information_schema(true));
        register_functions(&ctx, Arc::new(SceneContext::default()));
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let batches = rt
            .block_on(async {
                ctx.sql("SELECT routine_name, description, syntax_example FROM information_schema.routines")
                    .await?
                    .collect()
                    .await
            })
            .unwrap();
        let mut found = std::collections::BTreeMap::new();
        for b in &batches {
            let text = |i: usize| arrow::compute::cast(b.column(i), &DataType::Utf8).unwrap();
            let (n, d, e) = (text(0), text(1), text(2));
            let (n, d, e) = (n.as_string::<i32>(), d.as_string::<i32>(), e.as_string::<i32>());
            for r in 0..b.num_rows() {
                found.insert(n.value(r).to_string(), (d.value(r).to_string(), e.value(r).to_string()));
            }
        }
        for RayFunction { name, description, example, .. } in RAY_FUNCTIONS {
            let (d, e) = found.get(name).unwrap_or_else(|| panic!("{name} is not in information_schema.routines"));
            assert_eq!((d.as_str(), e.as_str()), (description, example), "{name}");
            assert!(example.starts_with(name), "{name}: {example}");
        }
    }

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

    #[test]
    fn morton_interleaves_bits() {
        assert_eq!(morton(1, 0, 0), 1);
        assert_eq!(morton(0, 1, 0), 2);
        assert_eq!(morton(0, 0, 1), 4);
        assert_eq!(morton(3, 0, 0), 0b1001);
        assert_eq!(morton(0x1f_ffff, 0x1f_ffff, 0x1f_ffff), (1u64 << 63) - 1);
    }

    #[test]
    fn morton10_interleaves_like_the_tables() {
        for v in 0..1024 {
            assert_eq!(u64::from(morton10(v, 0, 0)), morton(v as u64, 0, 0));
            assert_eq!(u64::from(morton10(0, v, 0)), morton(0, v as u64, 0));
            assert_eq!(u64::from(morton10(0, 0, v)), morton(0, 0, v as u64));
        }
        let mut s = 12345u64;
        for _ in 0..10_000 {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let [x, y, z] = [s >> 10, s >> 30, s >> 50].map(|v| (v & 0x3ff) as i32);
            assert_eq!(u64::from(morton10(x, y, z)), morton(x as u64, y as u64, z as u64));
        }
    }

    /// The kernel (reciprocal, fix-up near rounding boundaries, 10-bit fast spread) gives what the
    /// definition gives — `round(clamp((v - lo) / (hi - lo), 0, 1) * (2^bits - 1))` per axis,
    /// interleaved — on values exactly at, and one ULP either side of, every rounding boundary,
    /// on random values, out of bounds and far from the origin, for 1 to 21 bits and mixed bits.
    #[test]
    fn morton_kernel_matches_the_definition() {
        let reference = |v: [f64; 3], bits: i64, lo: [f64; 3], hi: [f64; 3]| -> u64 {
            let max = ((1u64 << bits) - 1) as f64;
            let q = |k: usize| {
                let ext = (hi[k] - lo[k]).max(f64::MIN_POSITIVE);
                (((v[k] - lo[k]) / ext).clamp(0.0, 1.0) * max).round() as u64
            };
            morton(q(0), q(1), q(2))
        };
        let check = |pts: &[[f32; 3]], bits: &[i64], lo: [f64; 3], hi: [f64; 3]| {
            let cols =
                [0, 1, 2].map(|k| arrow::array::Float32Array::from(pts.iter().map(|p| p[k]).collect::<Vec<_>>()));
            let b = Int64Array::from(bits.to_vec());
            let out = morton_kernel(&[&cols[0], &cols[1], &cols[2]], &b, Some((lo, hi))).unwrap();
            for (i, p) in pts.iter().enumerate() {
                let want = reference(p.map(f64::from), bits[i], lo, hi);
                assert_eq!(out.value(i), want, "point {p:?}, {} bits, bounds {lo:?}..{hi:?}", bits[i]);
            }
        };
        let mut s = 99u64;
        let mut rnd = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for (lo, hi) in
            [([-1.37, 0.0, 2.5], [5.91, 548.8, 2.75]), ([1e6, -1e6 - 3.3, 7e5], [1e6 + 17.1, -1e6, 7e5 + 0.013])]
        {
            for bits in [1i64, 3, 7, 10, 13, 21] {
                let max = ((1u64 << bits) - 1) as f64;
                let mut pts = Vec::new();
                for j in 0..4000 {
                    // Near a rounding boundary (k + 0.5 cells), random, or outside the bounds.
                    let c = (j as f64 * 7.31).rem_euclid(max.max(1.0)).floor() + 0.5;
                    let at = |k: usize| (lo[k] + (hi[k] - lo[k]) * (c / max)) as f32;
                    let mut p = [at(0), at(1), at(2)];
                    match j % 5 {
                        1 => p = p.map(|v| f32::from_bits(v.to_bits() + 1)),
                        2 => p = p.map(|v| f32::from_bits(v.to_bits() - 1)),
                        3 => p = [0, 1, 2].map(|k| (lo[k] + (hi[k] - lo[k]) * rnd()) as f32),
                        4 => p = [0, 1, 2].map(|k| (lo[k] + (hi[k] - lo[k]) * (rnd() * 3.0 - 1.0)) as f32),
                        _ => {}
                    }
                    pts.push(p);
                }
                check(&pts, &vec![bits; pts.len()], lo, hi);
                let mixed: Vec<i64> = (0..pts.len()).map(|i| 1 + (i as i64 * 5) % 21).collect();
                check(&pts, &mixed, lo, hi);
                // Float64 points within a few ULPs of each boundary: here the reciprocal alone
                // rounds some differently (the fix-up decides them).
                let mut pts = Vec::new();
                for c in 0..(max as u64).min(3000) {
                    let c = c as f64 + 0.5;
                    for d in -3i64..=3 {
                        pts.push([0, 1, 2].map(|k| {
                            let v = lo[k] + (hi[k] - lo[k]) * (c / max);
                            f64::from_bits((v.to_bits() as i64 + d) as u64)
                        }));
                    }
                }
                let cols = [0, 1, 2].map(|k| Float64Array::from(pts.iter().map(|p| p[k]).collect::<Vec<_>>()));
                let b = Int64Array::from(vec![bits; pts.len()]);
                let out = morton_kernel(&[&cols[0], &cols[1], &cols[2]], &b, Some((lo, hi))).unwrap();
                for (i, p) in pts.iter().enumerate() {
                    assert_eq!(out.value(i), reference(*p, bits, lo, hi), "point {p:?}, {bits} bits");
                }
            }
        }
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
    fn rays_grazing_a_lights_edge_are_decided_exactly() {
        // One triangle of the Cornell box's light; its edge x = 343 runs from z = 227 to 332.
        let light = [[343.0, 548.8, 227.0], [343.0, 548.8, 332.0], [213.0, 548.8, 332.0]];
        // Straight up through the edge: a hit; 1e-4 mm outside: a miss (the old Möller–Trumbore
        // test with its 1e-5 barycentric tolerance called rays up to ~1e-3 mm outside hits).
        assert!(hits_triangle([343.0, 0.0, 280.0], [0.0, 1.0, 0.0], &light));
        assert!(!hits_triangle([343.0001, 0.0, 280.0], [0.0, 1.0, 0.0], &light));
        // Slanted rays from the floor aimed just inside and just outside the edge.
        let o = [278.0, 0.0, 280.0];
        let aim = |x: f64| [x - o[0], 548.8 - o[1], 280.0 - o[2]];
        assert!(hits_triangle(o, aim(343.0 - 1e-3), &light));
        assert!(!hits_triangle(o, aim(343.0 + 1e-3), &light));
        // Grazing: a ray in the light's plane does not hit it.
        assert!(!hits_triangle([300.0, 548.8, 0.0], [0.0, 0.0, 1.0], &light));
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
