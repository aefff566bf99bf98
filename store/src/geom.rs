//! The geometry every crate shares: the angle between directions, the octahedral map of the
//! sphere onto a square, and the watertight ray/triangle test where a hit must be decided exactly
//! (in f64). The codec, the SQL functions and the viewer use these; the tracers' f32 watertight
//! test (`renderers::geometry`) is the same algorithm in single precision for speed, and a test
//! there checks that the two agree.

/// The angle between two directions in radians, atan2(|a × b|, a · b) (accurate for tiny
/// angles); `None` when either is zero or not finite.
pub fn angle_between(a: [f64; 3], b: [f64; 3]) -> Option<f64> {
    if a.iter().chain(b.iter()).any(|v| !v.is_finite()) {
        return None;
    }
    let c = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let cross = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let zero = |v: [f64; 3]| v == [0.0; 3];
    (!zero(a) && !zero(b)).then(|| cross.atan2(dot))
}

/// [`angle_between`] of f32 directions; NaN where it is `None`.
pub fn angle_between_f32(a: [f32; 3], b: [f32; 3]) -> f64 {
    angle_between(a.map(f64::from), b.map(f64::from)).unwrap_or(f64::NAN)
}

/// The octahedral map: a direction to a point of the square [-1, 1]² (the upper hemisphere maps
/// to the inner diamond, the lower one is folded over its edges). `None` for a zero or
/// non-finite direction. Signed zeros count as positive, so the map is a function of the value.
pub fn oct_fold(d: [f64; 3]) -> Option<[f64; 2]> {
    let l1 = d[0].abs() + d[1].abs() + d[2].abs();
    if !(l1.is_finite() && l1 > 0.0) {
        return None;
    }
    let (x, y) = (d[0] / l1, d[1] / l1);
    if d[2] < 0.0 {
        let sign = |v: f64| if v >= 0.0 { 1.0 } else { -1.0 };
        return Some([(1.0 - y.abs()) * sign(x), (1.0 - x.abs()) * sign(y)]);
    }
    Some([x, y])
}

/// The inverse of [`oct_fold`]: a point of [-1, 1]² to a unit direction.
pub fn oct_unfold(p: [f64; 2]) -> [f64; 3] {
    let [x, y] = p;
    let z = 1.0 - x.abs() - y.abs();
    let sign = |v: f64| if v >= 0.0 { 1.0 } else { -1.0 };
    let (x, y) = if z < 0.0 { ((1.0 - y.abs()) * sign(x), (1.0 - x.abs()) * sign(y)) } else { (x, y) };
    let l = (x * x + y * y + z * z).sqrt();
    [x / l, y / l, z / l]
}

/// Watertight ray/triangle intersection (Woop, Benthin and Wald 2013) in f64, two-sided: the
/// distance `t > 0` along `d` at which the ray from `o` hits the triangle, or `None`. A ray
/// through an edge or a vertex hits (no tolerance either way), a ray parallel to the plane or with
/// NaN/Inf input does not.
pub fn ray_triangle(o: [f64; 3], d: [f64; 3], tri: &[[f64; 3]; 3]) -> Option<f64> {
    if o.iter().chain(d.iter()).chain(tri.iter().flatten()).any(|v| !v.is_finite()) {
        return None;
    }
    let kz = (0..3).max_by(|&i, &j| d[i].abs().total_cmp(&d[j].abs())).unwrap_or(2);
    if d[kz] == 0.0 {
        return None;
    }
    let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
    if d[kz] < 0.0 {
        std::mem::swap(&mut kx, &mut ky);
    }
    let (sx, sy, sz) = (d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]);
    let rel = |v: [f64; 3]| [v[0] - o[0], v[1] - o[1], v[2] - o[2]];
    let (a, b, c) = (rel(tri[0]), rel(tri[1]), rel(tri[2]));
    let (ax, ay) = (a[kx] - sx * a[kz], a[ky] - sy * a[kz]);
    let (bx, by) = (b[kx] - sx * b[kz], b[ky] - sy * b[kz]);
    let (cx, cy) = (c[kx] - sx * c[kz], c[ky] - sy * c[kz]);
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let t = (u * sz * a[kz] + v * sz * b[kz] + w * sz * c[kz]) / det;
    (t > 0.0).then_some(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_of_zero_parallel_tiny_and_opposite_directions() {
        assert_eq!(angle_between([0.0; 3], [1.0, 0.0, 0.0]), None);
        assert_eq!(angle_between([f64::NAN, 0.0, 1.0], [1.0, 0.0, 0.0]), None);
        assert!(angle_between_f32([0.0; 3], [1.0, 0.0, 0.0]).is_nan());
        assert_eq!(angle_between([2.0, 0.0, 0.0], [1.0, 0.0, 0.0]), Some(0.0));
        let tiny = angle_between([1.0, 0.0, 0.0], [1.0, 1e-9, 0.0]).unwrap();
        assert!((tiny - 1e-9).abs() < 1e-18, "{tiny}");
        let pi = angle_between([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]).unwrap();
        assert!((pi - std::f64::consts::PI).abs() < 1e-15);
    }

    #[test]
    fn octahedral_map_round_trips_and_covers_the_square() {
        for i in 0..2000 {
            let a = f64::from(i) * 0.7;
            let z = f64::from(i) / 1000.0 - 1.0;
            let r = (1.0 - z * z).sqrt();
            let d = [r * a.cos(), r * a.sin(), z];
            let p = oct_fold(d).unwrap();
            assert!(p[0].abs() <= 1.0 && p[1].abs() <= 1.0);
            let back = oct_unfold(p);
            assert!(angle_between(d, back).unwrap() < 1e-12, "{d:?} -> {p:?} -> {back:?}");
        }
        assert_eq!(oct_fold([0.0; 3]), None);
        assert_eq!(oct_fold([-0.0, 0.5, -0.5]), oct_fold([0.0, 0.5, -0.5]));
    }

    #[test]
    fn watertight_test_decides_edges_exactly() {
        let tri = [[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 1.0]];
        // Both sides, forward only.
        assert_eq!(ray_triangle([0.2, 0.0, 0.2], [0.0, 1.0, 0.0], &tri), Some(1.0));
        assert_eq!(ray_triangle([0.2, 2.0, 0.2], [0.0, -1.0, 0.0], &tri), Some(1.0));
        assert_eq!(ray_triangle([0.2, 0.0, 0.2], [0.0, -1.0, 0.0], &tri), None);
        assert_eq!(ray_triangle([0.2, 0.0, 0.2], [1.0, 0.0, 0.0], &tri), None, "parallel");
        // Through the hypotenuse's midpoint: a hit; a hair outside it: a miss.
        assert!(ray_triangle([0.5, 0.0, 0.5], [0.0, 1.0, 0.0], &tri).is_some());
        assert!(ray_triangle([0.5 + 1e-12, 0.0, 0.5], [0.0, 1.0, 0.0], &tri).is_none());
        // Through a vertex: a hit. NaN/Inf: a miss.
        assert!(ray_triangle([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], &tri).is_some());
        assert!(ray_triangle([f64::NAN, 0.0, 0.0], [0.0, 1.0, 0.0], &tri).is_none());
        assert!(ray_triangle([0.2, 0.0, 0.2], [0.0, f64::INFINITY, 0.0], &tri).is_none());
        // A degenerate triangle is never hit.
        let line = [[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [2.0, 1.0, 0.0]];
        assert!(ray_triangle([0.5, 0.0, 0.0], [0.0, 1.0, 0.0], &line).is_none());
        // Two triangles sharing an edge: a ray along the shared edge's points hits one of them.
        let other = [[1.0, 1.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]];
        for k in 0..=100 {
            let s = f64::from(k) / 100.0;
            let o = [1.0 - s, 0.0, s];
            let hits = [&tri, &other].iter().filter(|t| ray_triangle(o, [0.0, 1.0, 0.0], t).is_some()).count();
            assert!(hits >= 1, "gap at {o:?}");
        }
    }
}
