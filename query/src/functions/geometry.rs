//! Functions of rays and scene geometry: `ray_point`, `ray_aabb_hit`, `aims_at_light`,
//! `scene_hit`.

use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, Float64Array};
use arrow::datatypes::DataType;
use datafusion::logical_expr::ColumnarValue;

use super::kernels::{Floats, Kernel, arrays, float_signature, rowwise};
use super::{RayScalar, SceneContext, doc};

/// `ray_point(ox, oy, oz, dx, dy, dz, t)`: the point at `t` along the ray, as a struct.
pub(super) fn ray_point() -> RayScalar {
    let fields = point_fields();
    let ret = DataType::Struct(fields.clone());
    let fun: Kernel = Arc::new(move |args: &[ColumnarValue]| {
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
    RayScalar::new(
        "ray_point",
        float_signature(7, false),
        ret,
        fun,
        doc(
            "The point o + t*d as a struct {x, y, z} of Float64 (`ray_point(..)['x']`); NULL for a miss (NULL t).",
            "ray_point(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t)['x']",
            &ray_args(&[("t", "the distance along it")]),
        ),
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

/// `ray_aabb_hit(ox, oy, oz, dx, dy, dz, min_x, min_y, min_z, max_x, max_y, max_z)`.
pub(super) fn ray_aabb_hit() -> RayScalar {
    let kernel = rowwise::<12, _, BooleanArray>("ray_aabb_hit", false, |v, _| {
        Some(slab_hit([v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]], [v[9], v[10], v[11]]))
    });
    RayScalar::new(
        "ray_aabb_hit",
        float_signature(12, false),
        DataType::Boolean,
        kernel,
        doc(
            "Whether the ray (t >= 0) enters the axis-aligned box (Boolean, slab test).",
            "ray_aabb_hit(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, min_x, min_y, min_z, max_x, max_y, max_z)",
            &ray_args(&[
                ("min_x", "the box's low x"),
                ("min_y", "the box's low y"),
                ("min_z", "the box's low z"),
                ("max_x", "the box's high x"),
                ("max_y", "the box's high y"),
                ("max_z", "the box's high z"),
            ]),
        ),
    )
}

/// `aims_at_light(ox, oy, oz, dx, dy, dz)` over the emitters of `scene`.
pub(super) fn aims_at_light(scene: &Arc<SceneContext>) -> RayScalar {
    let lights = scene.clone();
    let kernel: Kernel = match &scene.lights_unavailable {
        // A broken `lights` table: no answer rather than "aims at nothing" for every ray.
        Some(why) => {
            let message = store::unavailable("aims_at_light needs the scene's emitters: the `lights` table", why);
            Arc::new(move |_: &[ColumnarValue]| Err(datafusion::error::DataFusionError::Execution(message.clone())))
        }
        None => rowwise::<6, _, BooleanArray>("aims_at_light", false, move |v, _| {
            let (o, d) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
            Some(lights.lights.iter().any(|t| aims_at(o, d, t)))
        }),
    };
    RayScalar::new("aims_at_light", float_signature(6, false), DataType::Boolean, kernel, doc(
        "Whether the ray's line hits an emitter triangle of the scene (its `lights` table) in front of its origin (Boolean, watertight test; within 2^-19 of the coordinates' magnitude of its edges, the rounding of f32 positions), or passes within 1e-5 rad (0.0006°) of a point light: false for a shadow ray that points at no light, the paper's bug.",
        "aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)",
        &ray_args(&[]),
    ))
    .for_scene(scene)
}

/// `scene_hit(ox, oy, oz, dx, dy, dz, tmin, tmax)`: the closest hit of the ray on the dataset's
/// triangles (a replay of the recorded ray), in a BVH built at first use.
pub(super) fn scene_hit(scene: &Arc<SceneContext>) -> RayScalar {
    let tris = scene.triangles.clone();
    let fun: Kernel = Arc::new(move |args: &[ColumnarValue]| {
        let a = arrays(args)?;
        let c = Floats::<8>::of(&a)?;
        let bvh = match &tris {
            Some(t) => t.bvh().map_err(datafusion::error::DataFusionError::Execution)?,
            None => {
                return Err(datafusion::error::DataFusionError::Execution(
                    "scene_hit: the session has no dataset whose triangles it could replay rays against".into(),
                ));
            }
        };
        let mut out: Vec<Option<f64>> = vec![None; c.len()];
        c.each_valid(|r, v| {
            out[r] = bvh.closest([v[0], v[1], v[2]], [v[3], v[4], v[5]], v[6], v[7]).map(|h| h.0);
        });
        Ok(ColumnarValue::Array(Arc::new(Float64Array::from(out)) as ArrayRef))
    });
    RayScalar::new("scene_hit", float_signature(8, false), DataType::Float64, fun, doc(
        "The distance to the ray's closest hit on the scene's triangles (the dataset's `triangles` table, in a BVH built at first use) with tmin < t < tmax, by the watertight f64 test; NULL for none. A replay of a recorded ray: a hit closer than the recorded `t` is a surface the renderer passed through.",
        "scene_hit(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, 0.001, coalesce(t, 1e30))",
        &ray_args(&[("tmin", "hits at or before it are ignored"), ("tmax", "hits at or past it are ignored (finite)")]),
    ))
    .for_scene(scene)
}

/// A ray's arguments, origin then direction, followed by `more`.
fn ray_args<'a>(more: &[(&'a str, &'a str)]) -> Vec<(&'a str, &'a str)> {
    let mut v = vec![
        ("ox", "x of the origin"),
        ("oy", "y of the origin"),
        ("oz", "z of the origin"),
        ("dx", "x of the direction"),
        ("dy", "y of the direction"),
        ("dz", "z of the direction"),
    ];
    v.extend_from_slice(more);
    v
}

/// Whether the ray from `o` along `d` hits the triangle at t > 0: the watertight test of
/// `store::geom`, so a ray through a light's edge is decided exactly, with no tolerance.
pub(super) fn hits_triangle(o: [f64; 3], d: [f64; 3], tri: &[[f64; 3]; 3]) -> bool {
    store::geom::ray_triangle(o, d, tri).is_some()
}

/// The angle within which a ray aims at a point light: f32 directions from f32 positions round
/// to ~1e-7 rad; a renderer's jitter or a wrong direction is far larger.
pub(super) const POINT_LIGHT_ANGLE: f64 = 1e-5;

/// How far outside a light's edges a ray may cross its plane and still aim at it, relative to
/// the largest coordinate of the ray's origin and the light: 2^-19, 32 ULPs of f32. A shadow ray
/// aimed at a point sampled on the light's edge misses the exact triangle by the rounding of its
/// f32 origin and direction, which is that large 1e6 from the origin (0.02 there, against a
/// bound of 1.9); a wrong direction misses by a share of the scene.
pub(super) const LIGHT_EDGE_REL: f64 = 1.0 / 524288.0;

/// Whether the ray from `o` along `d` aims at the light `l`: a triangle it hits (or whose plane
/// it crosses, in front of its origin, within [`LIGHT_EDGE_REL`] of the coordinates' magnitude
/// of its edges), or a point light (a row whose three vertices coincide) within
/// [`POINT_LIGHT_ANGLE`] of the ray's direction, in front of its origin.
pub(super) fn aims_at(o: [f64; 3], d: [f64; 3], l: &[[f64; 3]; 3]) -> bool {
    if l[0] == l[1] && l[1] == l[2] {
        let to = [l[0][0] - o[0], l[0][1] - o[1], l[0][2] - o[2]];
        return store::geom::angle_between(d, to).is_some_and(|a| a <= POINT_LIGHT_ANGLE);
    }
    hits_triangle(o, d, l) || near_edge(o, d, l)
}

/// Whether the ray crosses the triangle's plane in front of its origin within
/// [`LIGHT_EDGE_REL`] (of the largest coordinate of `o` and the triangle) of its edges.
fn near_edge(o: [f64; 3], d: [f64; 3], l: &[[f64; 3]; 3]) -> bool {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (e1, e2) = (sub(l[1], l[0]), sub(l[2], l[0]));
    let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
    let dn = dot(d, n);
    if dn == 0.0 || !dn.is_finite() {
        return false;
    }
    let t = dot(sub(l[0], o), n) / dn;
    if !(t.is_finite() && t > 0.0) {
        return false;
    }
    let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let mag = o.iter().chain(l.iter().flatten()).fold(0.0f64, |m, v| m.max(v.abs()));
    let tol = LIGHT_EDGE_REL * mag;
    (0..3).any(|i| {
        let (a, b) = (l[i], l[(i + 1) % 3]);
        let ab = sub(b, a);
        let len2 = dot(ab, ab);
        let s = if len2 > 0.0 { (dot(sub(p, a), ab) / len2).clamp(0.0, 1.0) } else { 0.0 };
        let q = [a[0] + s * ab[0], a[1] + s * ab[1], a[2] + s * ab[2]];
        let r = sub(p, q);
        dot(r, r).sqrt() <= tol
    })
}

/// Slab test: true when the ray (t ≥ 0) enters the box.
pub(super) fn slab_hit(o: [f64; 3], d: [f64; 3], lo: [f64; 3], hi: [f64; 3]) -> bool {
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

#[cfg(test)]
mod tests {
    use super::*;

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
    fn aiming_at_a_light_allows_the_rounding_of_f32_positions_and_no_more() {
        let light = [[343.0, 548.8, 227.0], [343.0, 548.8, 332.0], [213.0, 548.8, 332.0]];
        let o = [278.0, 0.0, 280.0];
        let aim = |x: f64| [x - o[0], 548.8 - o[1], 280.0 - o[2]];
        // At the scene's scale the allowance is ~0.001 (2^-19 of 548.8): 1e-4 outside aims at it,
        // 0.01 outside (and the wrong side of the box) does not.
        assert!(!hits_triangle(o, aim(343.0 + 1e-4), &light) && aims_at(o, aim(343.0 + 1e-4), &light));
        assert!(!aims_at(o, aim(343.0 + 1e-2), &light));
        assert!(!aims_at(o, [-aim(343.0)[0], 548.8, 0.0], &light));
        // 1e6 from the origin the light's other half (edge z = 227), missed by 0.02 (a shadow ray recorded in f32 aimed at
        // a point sampled on its edge, as a far trace had): aimed at; 10 off: not.
        let other = [[343.0, 548.8, 227.0], [213.0, 548.8, 332.0], [213.0, 548.8, 227.0]];
        let far = other.map(|v| v.map(|c| c + 1e6));
        let o = [1000029.06, 1000001.0, 1000339.6];
        let to = |x: f64, z: f64| [x - o[0], far[0][1] - o[1], z - o[2]];
        assert!(aims_at(o, to(1000284.4, 1000226.98), &far));
        assert!(!aims_at(o, to(1000284.4, 1000217.0), &far));
        // Behind the origin does not count.
        assert!(!aims_at([o[0], far[0][1] + 10.0, o[2]], [0.0, 1.0, 0.0], &far));
    }

    #[test]
    fn point_lights_are_aimed_at_within_a_tiny_angle_and_in_front() {
        let p = [[1e4, 2e4, -3e4]; 3];
        let o = [1e4 + 0.25, 0.5, -3e4 - 0.125];
        let d = [p[0][0] - o[0], p[0][1] - o[1], p[0][2] - o[2]];
        assert!(aims_at(o, d, &p));
        // From far away in f32, as a renderer records it: still aimed at.
        let d32 = d.map(|v| f64::from(v as f32));
        assert!(aims_at(o, d32, &p));
        // 1e-4 rad off (2 units at 2e4): a wrong direction.
        let off = [d[0] + 2.0, d[1], d[2]];
        assert!(!aims_at(o, off, &p));
        assert!(!aims_at(o, d.map(|v| -v), &p), "away from the light");
        assert!(!aims_at(o, [0.0; 3], &p), "no direction");
        assert!(!aims_at(p[0], d, &p), "from the light itself");
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
