//! `morton3(x, y, z, bits)`: Morton codes of points over the scene bounds, the grouping key of
//! cell histograms over every ray.

use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Int64Array, PrimitiveArray, UInt64Array};
use arrow::datatypes::{ArrowPrimitiveType, DataType, Int64Type};
use datafusion::error::DataFusionError;
use datafusion::logical_expr::ColumnarValue;

use super::kernels::{Floats, Kernel, arrays, float_signature};
use super::{RayScalar, SceneContext, doc};

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

/// The kernel of [`morton3`].
pub(super) fn morton_kernel<T: ArrowPrimitiveType>(
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
pub(super) fn morton3(scene: &Arc<SceneContext>) -> RayScalar {
    let bounds = scene.bounds;
    let fun: Kernel = Arc::new(move |args: &[ColumnarValue]| {
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
    RayScalar::new("morton3", float_signature(3, true), DataType::UInt64, fun, doc(
        "Morton code (UInt64) of a point's cell over the scene bounds (origins and hit points of the session's first dataset), `bits` per axis.",
        "morton3(origin_x, origin_y, origin_z, 10)",
        &[("x", "x of the point"), ("y", "y of the point"), ("z", "z of the point"), ("bits", "bits per axis, 1..=21")],
    ))
    .for_scene(scene)
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::Float64Array;

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
}
