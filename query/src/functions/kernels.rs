//! What the ray functions' kernels share: float arguments read as they come (Float32 or
//! Float64), rows with a NULL, NaN or infinite value skipped, signatures of n floats.

use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Int64Array, PrimitiveArray};
use arrow::datatypes::{ArrowPrimitiveType, DataType, Float32Type, Float64Type, Int64Type};
use datafusion::error::DataFusionError;
use datafusion::logical_expr::{ColumnarValue, Signature, TypeSignature, Volatility};

/// A function's kernel over its arguments' columns.
pub(super) type Kernel = Arc<dyn Fn(&[ColumnarValue]) -> datafusion::error::Result<ColumnarValue> + Send + Sync>;

pub(super) fn arrays(args: &[ColumnarValue]) -> datafusion::error::Result<Vec<ArrayRef>> {
    ColumnarValue::values_to_arrays(args)
}

/// `N` float columns of one type: Float32 columns are read as they are (no cast to Float64).
pub(super) enum Floats<'a, const N: usize> {
    F32([&'a PrimitiveArray<Float32Type>; N]),
    F64([&'a PrimitiveArray<Float64Type>; N]),
}

impl<'a, const N: usize> Floats<'a, N> {
    /// The first `N` arguments, all Float32 or all Float64 (as the signatures ask).
    pub(super) fn of(a: &'a [ArrayRef]) -> datafusion::error::Result<Self> {
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

    pub(super) fn len(&self) -> usize {
        match self {
            Self::F32(c) => c.first().map_or(0, |c| c.len()),
            Self::F64(c) => c.first().map_or(0, |c| c.len()),
        }
    }

    /// Calls `f(row, values)` for every row whose values are all non-null and finite, in order.
    pub(super) fn each_valid(&self, f: impl FnMut(usize, [f64; N])) {
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
pub(super) fn float_signature(n: usize, int_param: bool) -> Signature {
    let variant = |t: DataType| {
        let mut v = vec![t; n];
        if int_param {
            v.push(DataType::Int64);
        }
        TypeSignature::Exact(v)
    };
    Signature::one_of(vec![variant(DataType::Float32), variant(DataType::Float64)], Volatility::Immutable)
}

/// A row-wise function of `N` float arguments (and, with `int_param`, one integer last): rows
/// with a NULL, NaN or infinite float, or a NULL integer, give NULL; `f` may give NULL too.
pub(super) fn rowwise<const N: usize, T, A>(
    name: &str,
    int_param: bool,
    f: impl Fn([f64; N], Option<i64>) -> Option<T> + Send + Sync + 'static,
) -> Kernel
where
    T: Clone,
    A: Array + FromIterator<Option<T>> + 'static,
{
    let fname = name.to_string();
    let fun: Kernel = Arc::new(move |args: &[ColumnarValue]| {
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
    fun
}
