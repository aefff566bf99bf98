//! Rays, watertight ray/triangle intersection and robust secondary-ray offsets.

use glam::Vec3A;

/// A ray with what the watertight test and the box test need precomputed.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: Vec3A,
    pub dir: Vec3A,
    pub inv_dir: Vec3A,
    pub(crate) kx: usize,
    pub(crate) ky: usize,
    pub(crate) kz: usize,
    pub(crate) sx: f32,
    pub(crate) sy: f32,
    pub(crate) sz: f32,
}

impl Ray {
    pub fn new(origin: Vec3A, dir: Vec3A) -> Ray {
        let a = dir.abs();
        let kz = if a.x > a.y {
            if a.x > a.z { 0 } else { 2 }
        } else if a.y > a.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let sz = 1.0 / dir[kz];
        Ray { origin, dir, inv_dir: Vec3A::ONE / dir, kx, ky, kz, sx: dir[kx] * sz, sy: dir[ky] * sz, sz }
    }

    pub fn at(&self, t: f32) -> Vec3A {
        self.origin + self.dir * t
    }
}

/// A hit on a triangle: distance and barycentric coordinates (of v1 and v2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
}

/// γ(n) of Pharr et al.: the relative error bound of n floating-point operations.
#[inline(always)]
fn gamma(n: u32) -> f32 {
    let e = n as f32 * f32::EPSILON * 0.5;
    e / (1.0 - e)
}

/// Watertight ray/triangle intersection (Woop, Benthin and Wald 2013): no ray passes between
/// two triangles sharing an edge, including rays through edges and vertices.
#[inline(always)]
pub fn intersect_triangle(ray: &Ray, v0: Vec3A, v1: Vec3A, v2: Vec3A, tmin: f32, tmax: f32) -> Option<TriHit> {
    let a = v0 - ray.origin;
    let b = v1 - ray.origin;
    let c = v2 - ray.origin;
    let (kx, ky, kz) = (ray.kx, ray.ky, ray.kz);
    let ax = a[kx] - ray.sx * a[kz];
    let ay = a[ky] - ray.sy * a[kz];
    let bx = b[kx] - ray.sx * b[kz];
    let by = b[ky] - ray.sy * b[kz];
    let cx = c[kx] - ray.sx * c[kz];
    let cy = c[ky] - ray.sy * c[kz];
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        // Edge cases decided in double precision.
        u = (f64::from(cx) * f64::from(by) - f64::from(cy) * f64::from(bx)) as f32;
        v = (f64::from(ax) * f64::from(cy) - f64::from(ay) * f64::from(cx)) as f32;
        w = (f64::from(bx) * f64::from(ay) - f64::from(by) * f64::from(ax)) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let az = ray.sz * a[kz];
    let bz = ray.sz * b[kz];
    let cz = ray.sz * c[kz];
    let t_scaled = u * az + v * bz + w * cz;
    let inv = 1.0 / det;
    let mut t = t_scaled * inv;
    if !(t > tmin && t < tmax) {
        return None;
    }
    // pbrt's conservative bound on t's rounding error (Pharr et al., 4th ed., 6.8.6): a hit no
    // farther than it may be behind the origin, so it is decided again in double precision. A ray
    // leaving a floor at y = 0 by 2^-16 (the offset near the origin) meets the floor's 550 mm
    // vertices with an error of ~5e-5 in t: in f32 alone its sign flipped into a hit at t = 2e-5
    // (found by `analyze bvh --whatif`, whose binned-SAH leaves test the floor where the tracers'
    // do not); rejecting every hit within the bound instead lost a bounce's real hit on the wall
    // 0.005 away.
    let max_xt = ax.abs().max(bx.abs()).max(cx.abs());
    let max_yt = ay.abs().max(by.abs()).max(cy.abs());
    let max_zt = az.abs().max(bz.abs()).max(cz.abs());
    let delta_z = gamma(3) * max_zt;
    let delta_x = gamma(5) * (max_xt + max_zt);
    let delta_y = gamma(5) * (max_yt + max_zt);
    let delta_e = 2.0 * (gamma(2) * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
    let max_e = u.abs().max(v.abs()).max(w.abs());
    let delta_t = 3.0 * (gamma(3) * max_e * max_zt + delta_e * max_zt + delta_z * max_e) * inv.abs();
    if t <= delta_t {
        let d = |p: Vec3A| [f64::from(p.x), f64::from(p.y), f64::from(p.z)];
        let t64 = store::geom::ray_triangle(d(ray.origin), d(ray.dir), &[d(v0), d(v1), d(v2)])?;
        t = t64 as f32;
        if !(t > tmin && t < tmax) {
            return None;
        }
    }
    // u weighs v0, v weighs v1, w weighs v2.
    Some(TriHit { t, u: v * inv, v: w * inv })
}

/// Offsets a surface point along its normal so a ray leaving it does not hit the same surface
/// again (after Wächter and Binder, Ray Tracing Gems ch. 6): a number of ULPs in integer space far
/// from the origin, a small absolute step near it, so it works at any scale and distance from the
/// origin. Their 256 ULPs cover hit points computed as o + t·d; ours come from barycentric
/// interpolation of the vertices (error of a few ULPs), so 16 suffice — 256 moved shading points
/// 16 mm off the surfaces of a Cornell box placed 1e6 mm from the origin and darkened it by 8%.
pub fn offset_point(p: Vec3A, n: Vec3A) -> Vec3A {
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 16.0;
    let mut out = [0.0f32; 3];
    for i in 0..3 {
        let of = (INT_SCALE * n[i]) as i32;
        let bits = p[i].to_bits() as i32;
        let moved = f32::from_bits((if p[i] < 0.0 { bits - of } else { bits + of }) as u32);
        out[i] = if p[i].abs() < ORIGIN { p[i] + FLOAT_SCALE * n[i] } else { moved };
    }
    Vec3A::from_array(out)
}

/// Geometric normal (unnormalized cross product) of a triangle.
pub fn triangle_normal(v0: Vec3A, v1: Vec3A, v2: Vec3A) -> Vec3A {
    (v1 - v0).cross(v2 - v0)
}

/// True when a triangle has no area (collinear or repeated vertices) or non-finite vertices.
pub fn is_degenerate(v0: Vec3A, v1: Vec3A, v2: Vec3A) -> bool {
    let n = triangle_normal(v0, v1, v2);
    let area2 = n.length_squared();
    let ok = v0.is_finite() && v1.is_finite() && v2.is_finite() && area2.is_finite() && area2 > 0.0;
    !ok
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Rng;

    #[test]
    fn the_f32_test_agrees_with_the_f64_watertight_test_of_store() {
        // The tracers' single-precision test and `store::geom::ray_triangle` (the SQL functions'
        // and viewer's) are one algorithm: on random rays they decide the same hits (rays within
        // f32 rounding of an edge may differ) and the same distances.
        let mut rng = Rng::for_sample(7, 1, 2, 3);
        let mut r = || rng.next_f32() * 2.0 - 1.0;
        let (mut both, mut differ) = (0, 0);
        for _ in 0..20_000 {
            let tri = [Vec3A::new(r(), r(), r()), Vec3A::new(r(), r(), r()), Vec3A::new(r(), r(), r())];
            let o = Vec3A::new(r(), r(), r()) * 3.0;
            let target = (tri[0] + tri[1] + tri[2]) / 3.0 + Vec3A::new(r(), r(), r()) * 0.5;
            let d = target - o;
            let ours = intersect_triangle(&Ray::new(o, d), tri[0], tri[1], tri[2], 0.0, f32::INFINITY);
            let d64 = |v: Vec3A| v.to_array().map(f64::from);
            let exact = store::geom::ray_triangle(d64(o), d64(d), &tri.map(d64));
            match (ours, exact) {
                (Some(h), Some(t)) => {
                    both += 1;
                    assert!((f64::from(h.t) - t).abs() <= 1e-4 * t.max(1.0), "t {} vs {t}", h.t);
                }
                (None, None) => {}
                _ => differ += 1,
            }
        }
        assert!(both > 2000, "{both} hits");
        assert!(differ <= 20, "{differ} of 20000 rays decided differently");
    }
}
