//! Functions of directions: `octant`, `angle_between`, `dir_bin`.

use std::sync::Arc;

use arrow::array::{Array, ArrayRef, Float64Array, PrimitiveArray, UInt8Array, UInt32Array};
use arrow::datatypes::{ArrowPrimitiveType, DataType};
use datafusion::logical_expr::ColumnarValue;

use super::kernels::{Floats, Kernel, arrays, float_signature, rowwise};
use super::{RayScalar, doc};

/// `octant(dx, dy, dz)`: bit 0 for dx < 0, bit 1 for dy < 0, bit 2 for dz < 0; NULL when a
/// component is NULL, NaN or infinite. A kernel of its own (no per-row closure, no option per
/// row; finiteness packed into a validity bitmap in one pass): it is the grouping key of direction-coherence queries over every ray.
pub(super) fn octant() -> RayScalar {
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
    let fun: Kernel = Arc::new(|args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let out = match Floats::<3>::of(&a)? {
            Floats::F32(c) => kernel(&c)?,
            Floats::F64(c) => kernel(&c)?,
        };
        Ok(ColumnarValue::Array(Arc::new(out) as ArrayRef))
    });
    RayScalar::new(
        "octant",
        float_signature(3, false),
        DataType::UInt8,
        fun,
        doc(
            "Octant of a direction: bit 0 set for dx < 0, bit 1 for dy < 0, bit 2 for dz < 0 (UInt8); NULL for NULL, NaN or infinite components.",
            "octant(dir_x, dir_y, dir_z)",
            &[("dx", "x of the direction"), ("dy", "y of the direction"), ("dz", "z of the direction")],
        ),
    )
}

/// `angle_between(ax, ay, az, bx, by, bz)`.
pub(super) fn angle_between() -> RayScalar {
    let kernel =
        rowwise::<6, _, Float64Array>("angle_between", false, |v, _| angle([v[0], v[1], v[2]], [v[3], v[4], v[5]]));
    RayScalar::new(
        "angle_between",
        float_signature(6, false),
        DataType::Float64,
        kernel,
        doc(
            "Angle between two directions in radians (Float64, 0..pi); NULL when either is zero, NaN or infinite.",
            "angle_between(dir_x, dir_y, dir_z, 0, -1, 0)",
            &[
                ("ax", "x of the first direction"),
                ("ay", "y of the first direction"),
                ("az", "z of the first direction"),
                ("bx", "x of the second direction"),
                ("by", "y of the second direction"),
                ("bz", "z of the second direction"),
            ],
        ),
    )
}

/// `dir_bin(dx, dy, dz, n)`.
pub(super) fn dir_bin() -> RayScalar {
    let kernel = rowwise::<3, _, UInt32Array>("dir_bin", true, |d, n| {
        let n = n.filter(|n| (1..=65535).contains(n))? as u32;
        octahedral_bin(d, n)
    });
    RayScalar::new(
        "dir_bin",
        float_signature(3, true),
        DataType::UInt32,
        kernel,
        doc(
            "Cell of a direction on an n x n octahedral map (UInt32, 0..n*n); NULL for a zero direction or n outside 1..=65535.",
            "dir_bin(dir_x, dir_y, dir_z, 16)",
            &[
                ("dx", "x of the direction"),
                ("dy", "y of the direction"),
                ("dz", "z of the direction"),
                ("n", "cells per side of the map"),
            ],
        ),
    )
}

/// The angle between two directions (`store::geom`); None for a zero or non-finite direction.
pub(super) fn angle(a: [f64; 3], b: [f64; 3]) -> Option<f64> {
    store::geom::angle_between(a, b)
}

/// Cell of a direction on an n × n octahedral map (row-major), None for a zero direction.
pub(super) fn octahedral_bin(d: [f64; 3], n: u32) -> Option<u32> {
    let [x, y] = store::geom::oct_fold(d)?;
    let cell = |v: f64| (((v * 0.5 + 0.5) * f64::from(n)).floor() as u32).min(n - 1);
    Some(cell(y) * n + cell(x))
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
