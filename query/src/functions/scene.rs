//! What the scene-dependent functions (`aims_at_light`, `morton3`, `scene_hit`) know of a
//! dataset's scene.

use arrow::array::{AsArray, RecordBatch};
use arrow::datatypes::Float32Type;
use store::Dataset;

use crate::Result;

/// What scene-dependent functions know about the scene.
#[derive(Clone, Debug, Default)]
pub struct SceneContext {
    /// Bounds of the finite origins and hit points, when any.
    pub bounds: Option<([f64; 3], [f64; 3])>,
    /// Emitter triangles (v0, v1, v2).
    pub lights: Vec<[[f64; 3]; 3]>,
    /// Why the dataset's `lights` table cannot be read, when it is broken: `aims_at_light`
    /// then fails naming it (instead of answering as if the scene had no emitters), while the
    /// session and every other function work.
    pub lights_unavailable: Option<String>,
    /// The dataset's triangles for `scene_hit`, read at first use (None: no dataset).
    pub triangles: Option<std::sync::Arc<SceneTriangles>>,
}

impl SceneContext {
    /// The scene of a dataset: bounds from its statistics, emitters from its `lights` table
    /// (`Dataset::table` has checked it whole: size, checksum and `store::scene::lights_schema`).
    /// A broken `lights` table does not fail it: the scene has no emitters and says why
    /// (`lights_unavailable`), so only the functions that need emitters fail.
    pub fn of(ds: &Dataset) -> Self {
        let place = ds.dir().display().to_string();
        let from_table = ds
            .table(store::scene::LIGHTS_TABLE)
            .map_err(crate::Error::from)
            .and_then(|lights| Self::from_parts(ds.stats(), lights.as_ref(), &place));
        let mut scene = match from_table {
            Ok(s) => s,
            Err(e) => {
                let mut s = Self::from_parts(ds.stats(), None, &place).unwrap_or_default();
                s.lights_unavailable = Some(e.to_string());
                s
            }
        };
        scene.triangles = Some(SceneTriangles::shared(ds.dir()));
        scene
    }

    /// The scene from a trace's statistics and its `lights` table, if any (`place` names the
    /// trace in errors).
    pub fn from_parts(stats: &store::Stats, lights_table: Option<&RecordBatch>, place: &str) -> Result<Self> {
        let (o, h) = (&stats.origin_bounds, &stats.hit_bounds);
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
        if let Some(batch) = lights_table {
            let mut cols = Vec::with_capacity(9);
            for name in store::scene::col::VERTEX.iter().flatten() {
                let c = batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>().cloned());
                cols.push(c.ok_or_else(|| store::Error::Table {
                    name: store::scene::LIGHTS_TABLE.into(),
                    path: place.into(),
                    message: format!("column `{name}` is missing or not Float32"),
                })?);
            }
            for r in 0..batch.num_rows() {
                let p = |v: usize| [0, 1, 2].map(|a| f64::from(cols[v * 3 + a].value(r)));
                lights.push([p(0), p(1), p(2)]);
            }
        }
        Ok(Self { bounds, lights, lights_unavailable: None, triangles: None })
    }
}

/// A dataset's triangles for `scene_hit`, read from its `triangles` table and put in a BVH at
/// first use (a session that never replays a ray never reads them).
pub struct SceneTriangles {
    /// The dataset's directory.
    pub dir: std::path::PathBuf,
    bvh: std::sync::OnceLock<std::result::Result<TriangleBvh, String>>,
}

impl std::fmt::Debug for SceneTriangles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SceneTriangles({})", self.dir.display())
    }
}

impl SceneTriangles {
    pub fn new(dir: std::path::PathBuf) -> Self {
        Self { dir, bvh: std::sync::OnceLock::new() }
    }

    /// The process's one `SceneTriangles` of dataset `dir` (a BVH is built once per process, not
    /// per session or per decoded plan of a distributed engine's tasks), rebuilt when the
    /// dataset's manifest has changed since.
    pub fn shared(dir: &std::path::Path) -> std::sync::Arc<Self> {
        use std::collections::HashMap;
        use std::sync::{Arc, Mutex, OnceLock};
        type Cache = Mutex<HashMap<std::path::PathBuf, (Option<std::time::SystemTime>, Arc<SceneTriangles>)>>;
        static CACHE: OnceLock<Cache> = OnceLock::new();
        let stamp = std::fs::metadata(dir.join(store::MANIFEST_FILE)).and_then(|m| m.modified()).ok();
        let cache = CACHE.get_or_init(Default::default);
        let Ok(mut c) = cache.lock() else { return Arc::new(Self::new(dir.to_path_buf())) };
        match c.get(dir) {
            Some((s, t)) if *s == stamp && stamp.is_some() => t.clone(),
            _ => {
                let t = Arc::new(Self::new(dir.to_path_buf()));
                c.insert(dir.to_path_buf(), (stamp, t.clone()));
                t
            }
        }
    }

    /// The BVH over the triangles; an error naming the dataset when it has no `triangles` table
    /// or the table cannot be read.
    pub fn bvh(&self) -> std::result::Result<&TriangleBvh, String> {
        self.bvh
            .get_or_init(|| {
                let place = self.dir.display().to_string();
                let ds = Dataset::open(&self.dir).map_err(|e| e.to_string())?;
                let batch = ds.table(store::scene::TRIANGLES_TABLE).map_err(|e| e.to_string())?.ok_or_else(|| {
                    format!(
                        "{place} has no `{}` table: replaying rays needs the scene's triangles",
                        store::scene::TRIANGLES_TABLE
                    )
                })?;
                let mut cols = Vec::with_capacity(9);
                for name in store::scene::col::VERTEX.iter().flatten() {
                    let c = batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>().cloned());
                    cols.push(
                        c.ok_or_else(|| format!("{place}: triangles column `{name}` is missing or not Float32"))?,
                    );
                }
                let tris: Vec<[[f64; 3]; 3]> = (0..batch.num_rows())
                    .map(|r| [0, 1, 2].map(|v| [0, 1, 2].map(|a| f64::from(cols[v * 3 + a].value(r)))))
                    .collect();
                Ok(TriangleBvh::new(tris))
            })
            .as_ref()
            .map_err(Clone::clone)
    }
}

/// Triangles in an obvhs BVH, for closest hits decided by the watertight f64 test of
/// `store::geom`. The boxes are padded (by 2^-20 of their largest coordinate) so a box test in
/// f32 never drops a triangle the f64 test would hit, axis-aligned walls (flat boxes) included.
pub struct TriangleBvh {
    bvh: obvhs::bvh2::Bvh2,
    tris: Vec<[[f64; 3]; 3]>,
}

impl TriangleBvh {
    pub fn new(tris: Vec<[[f64; 3]; 3]>) -> Self {
        use obvhs::aabb::Aabb;
        let boxes: Vec<Aabb> = tris
            .iter()
            .map(|t| {
                let v = t.map(|p| glam::Vec3A::new(p[0] as f32, p[1] as f32, p[2] as f32));
                let mut b = Aabb::from_points(&v);
                let pad = b.min.abs().max(b.max.abs()).max_element() * (1.0 / 1048576.0) + f32::MIN_POSITIVE;
                b.min -= glam::Vec3A::splat(pad);
                b.max += glam::Vec3A::splat(pad);
                b
            })
            .collect();
        let params = obvhs::BvhBuildParams { max_prims_per_leaf: 4, ..obvhs::BvhBuildParams::fast_build() };
        let mut took = std::time::Duration::ZERO;
        let bvh = obvhs::bvh2::builder::build_bvh2(&boxes, params, &mut took);
        Self { bvh, tris }
    }

    /// The triangles.
    pub fn len(&self) -> usize {
        self.tris.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// The closest hit of the ray from `o` along `d` with `tmin < t < tmax`: its distance and the
    /// triangle's row in the `triangles` table.
    pub fn closest(&self, o: [f64; 3], d: [f64; 3], tmin: f64, tmax: f64) -> Option<(f64, u32)> {
        if self.tris.is_empty() || tmin.partial_cmp(&tmax) != Some(std::cmp::Ordering::Less) {
            return None;
        }
        let ray = obvhs::ray::Ray::new(
            glam::Vec3A::new(o[0] as f32, o[1] as f32, o[2] as f32),
            glam::Vec3A::new(d[0] as f32, d[1] as f32, d[2] as f32),
            0.0,
            f32::INFINITY,
        );
        let mut best: Option<(f64, u32)> = None;
        let mut hit = obvhs::ray::RayHit::none();
        self.bvh.ray_traverse(ray, &mut hit, |_, i| {
            let prim = self.bvh.primitive_indices[i];
            match store::geom::ray_triangle(o, d, &self.tris[prim as usize]) {
                Some(t) if t > tmin && t < tmax && best.is_none_or(|b| t < b.0) => {
                    best = Some((t, prim));
                    // The f32 bound obvhs prunes boxes with, rounded away from the hit: no box the
                    // f64 test could still find closer is skipped.
                    (t as f32).next_up()
                }
                _ => f32::INFINITY,
            }
        });
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed box [0, s]^3 moved by `off`, two triangles per face (flat, axis-aligned boxes).
    fn cube(s: f64, off: f64) -> Vec<[[f64; 3]; 3]> {
        let mut tris = Vec::new();
        for axis in 0..3 {
            for side in [0.0, s] {
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                let p = |a: f64, b: f64| {
                    let mut q = [0.0; 3];
                    q[axis] = side + off;
                    q[u] = a + off;
                    q[v] = b + off;
                    q
                };
                tris.push([p(0.0, 0.0), p(s, 0.0), p(s, s)]);
                tris.push([p(0.0, 0.0), p(s, s), p(0.0, s)]);
            }
        }
        tris
    }

    fn brute(tris: &[[[f64; 3]; 3]], o: [f64; 3], d: [f64; 3], tmin: f64, tmax: f64) -> Option<f64> {
        tris.iter()
            .filter_map(|t| store::geom::ray_triangle(o, d, t))
            .filter(|&t| t > tmin && t < tmax)
            .min_by(f64::total_cmp)
    }

    #[test]
    fn closest_hits_match_brute_force_at_every_scale() {
        for (s, off) in [(1.0, 0.0), (1e-4, 0.0), (1e5, 0.0), (550.0, 1e6)] {
            let tris = cube(s, off);
            let bvh = TriangleBvh::new(tris.clone());
            assert_eq!(bvh.len(), 12);
            let mut state = 12345u64;
            let mut next = || {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            };
            let mut hits = 0;
            for _ in 0..500 {
                // From inside the box, including exactly on its walls' planes' interior.
                let o = [0, 1, 2].map(|_| off + s * (0.05 + 0.9 * next()));
                let d = [0, 1, 2].map(|_| next() * 2.0 - 1.0);
                let want = brute(&tris, o, d, 0.0, f64::INFINITY);
                let got = bvh.closest(o, d, 0.0, 1e300).map(|h| h.0);
                assert_eq!(got, want, "scale {s} offset {off}: ray {o:?} {d:?}");
                hits += usize::from(got.is_some());
                // A window that excludes the closest hit finds nothing nearer.
                if let Some(t) = want {
                    assert_eq!(bvh.closest(o, d, 0.0, t), None);
                }
            }
            assert!(hits > 450, "rays from inside a closed box hit it: {hits}");
            // Axis-aligned rays along a wall's normal hit the flat wall.
            let o = [off + 0.5 * s; 3];
            let got = bvh.closest(o, [1.0, 0.0, 0.0], 0.0, 1e300).map(|h| h.0).unwrap();
            assert!((got - (off + s - o[0])).abs() <= 1e-12 * (off + s), "scale {s} offset {off}: {got}");
        }
        assert_eq!(TriangleBvh::new(Vec::new()).closest([0.0; 3], [1.0, 0.0, 0.0], 0.0, 1.0), None);
    }
}
