//! Planes of hit primitives, for predicting hit distances (format version 3).
//!
//! A ray that hits a flat primitive (a triangle) stops where it meets the primitive's plane, so
//! once the plane is known its hit distance is `(offset - n·origin) / (n·direction)`: only the
//! few units in the last place between that and the recorded `t` need storing (about half a byte
//! instead of three). The store knows nothing of the scene, so the writer learns each primitive's
//! plane from its first hit points in a segment and saves the segment's planes in the ray file's
//! key-value metadata (`rtvtk.planes`); rays flagged in `enc_dir_code` (bit 6) are predicted from
//! them. Primitives whose hit points are not coplanar (spheres, curves, ids that name something
//! else) get no plane, and their rays keep raw `t` bits.
//!
//! The planes of a segment never change once learned, so every flagged ray of the segment is
//! decoded with the plane it was encoded with, whichever ray is decoded first: one tree still
//! decodes on its own.

use std::collections::HashMap;

use base64::Engine;

/// Key-value metadata key of a ray file's planes.
pub const PLANES_KEY: &str = "rtvtk.planes";

/// Hit points collected for a primitive before its plane is fitted (and again each time as many
/// more while they are collinear, up to [`MAX_FIT_POINTS`]).
const FIT_POINTS: usize = 12;
const MAX_FIT_POINTS: usize = 4 * FIT_POINTS;
/// Primitives collecting hit points at once (bounds the learner's memory: ~350 B each).
const MAX_PENDING: usize = 1 << 15;
/// Bytes of one plane record: primitive id (u32) and normal x/y/z and offset (f64), little-endian.
const RECORD: usize = 4 + 4 * 8;

/// Maps by primitive id (one lookup per hit ray while writing: a fast hash, not SipHash).
type IdMap<V> = HashMap<u32, V, ahash::RandomState>;

/// The plane `n·p = offset` of a primitive (`n` of unit length).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Plane {
    n: [f64; 3],
    offset: f64,
}

impl Plane {
    /// The predicted hit distance of a ray, in the ray's direction units; None when the ray is
    /// parallel to the plane or the prediction is not a positive finite `f32`. The encoder and the
    /// decoder both call this on the same `f32` inputs: IEEE arithmetic makes them agree bit for bit.
    #[inline(always)]
    pub fn predict(&self, o: [f32; 3], d: [f32; 3]) -> Option<f32> {
        let n = self.n;
        let den = n[0] * f64::from(d[0]) + n[1] * f64::from(d[1]) + n[2] * f64::from(d[2]);
        let num = self.offset - (n[0] * f64::from(o[0]) + n[1] * f64::from(o[1]) + n[2] * f64::from(o[2]));
        let t = (num / den) as f32;
        (t.is_finite() && t > 0.0).then_some(t)
    }

    /// The plane through `pts` when they span one: the first point, the farthest from it, and the
    /// farthest from the line through those two. The points must all lie on it to within 1e-5 of
    /// their spread plus their distance from the origin (recorded hit points are `f32`, a few ULPs
    /// off the surface).
    fn fit(pts: &[[f64; 3]]) -> Fit {
        let Some(&p0) = pts.first() else {
            return Fit::Collinear;
        };
        let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        };
        let longest = |v: &mut dyn Iterator<Item = [f64; 3]>| v.max_by(|a, b| dot(*a, *a).total_cmp(&dot(*b, *b)));
        let Some(far) = longest(&mut pts.iter().map(|&p| sub(p, p0))) else {
            return Fit::Collinear;
        };
        let spread2 = dot(far, far);
        if !(spread2 > 0.0 && spread2.is_finite()) {
            return Fit::Collinear;
        }
        let Some(c) = longest(&mut pts.iter().map(|&p| cross(far, sub(p, p0)))) else {
            return Fit::Collinear;
        };
        let c2 = dot(c, c);
        // |c| = |far| · distance of the point from the line: demand at least 1e-4 of the spread.
        if c2.is_nan() || c2 <= spread2 * spread2 * 1e-8 {
            return Fit::Collinear;
        }
        let len = c2.sqrt();
        let n = [c[0] / len, c[1] / len, c[2] / len];
        let offset = dot(n, p0);
        let magnitude = pts.iter().flatten().fold(0.0f64, |m, c| m.max(c.abs()));
        let tolerance = (spread2.sqrt() + magnitude) * 1e-5;
        if pts.iter().all(|&p| (dot(n, p) - offset).abs() <= tolerance) {
            Fit::Plane(Plane { n, offset })
        } else {
            Fit::Curved
        }
    }
}

/// What a set of hit points says about their primitive.
enum Fit {
    Plane(Plane),
    /// Too close to a line (or a point) to tell yet.
    Collinear,
    /// Not on one plane: the primitive is not flat.
    Curved,
}

/// The planes of one segment's primitives.
#[derive(Clone, Debug, Default)]
pub struct Planes {
    map: IdMap<Plane>,
    /// The same planes indexed by primitive id, when the ids are dense enough (the decoder looks
    /// one up per hit ray; a hash lookup there cost ~10% of decoding origins).
    dense: Vec<Option<Plane>>,
}

impl Planes {
    fn new(map: IdMap<Plane>) -> Self {
        let max = map.keys().copied().max().map_or(0, |m| m as usize + 1);
        let dense = if max <= 4 * map.len() + 4096 {
            let mut dense = vec![None; max];
            for (&prim, &plane) in &map {
                dense[prim as usize] = Some(plane);
            }
            dense
        } else {
            Vec::new()
        };
        Planes { map, dense }
    }

    #[inline]
    pub(crate) fn get(&self, prim: u32) -> Option<&Plane> {
        if self.dense.is_empty() { self.map.get(&prim) } else { self.dense.get(prim as usize).and_then(Option::as_ref) }
    }

    /// Planes known.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// The metadata value: base64 of the plane records, sorted by primitive.
    pub(crate) fn to_metadata(&self) -> String {
        let mut prims: Vec<u32> = self.map.keys().copied().collect();
        prims.sort_unstable();
        let mut bytes = Vec::with_capacity(prims.len() * RECORD);
        for prim in prims {
            let p = &self.map[&prim];
            bytes.extend_from_slice(&prim.to_le_bytes());
            for v in [p.n[0], p.n[1], p.n[2], p.offset] {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        base64::engine::general_purpose::STANDARD.encode(bytes)
    }

    /// Parses [`Planes::to_metadata`]; the error says what is wrong.
    pub fn from_metadata(value: &str) -> std::result::Result<Self, String> {
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(value.trim())
            .map_err(|e| format!("{PLANES_KEY} is not base64: {e}"))?;
        if bytes.len() % RECORD != 0 {
            return Err(format!("{PLANES_KEY} holds {} bytes, not a multiple of {RECORD}", bytes.len()));
        }
        let mut map = IdMap::default();
        for rec in bytes.chunks_exact(RECORD) {
            let prim = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]);
            let f = |k: usize| {
                let mut b = [0u8; 8];
                b.copy_from_slice(&rec[4 + 8 * k..12 + 8 * k]);
                f64::from_le_bytes(b)
            };
            let plane = Plane { n: [f(0), f(1), f(2)], offset: f(3) };
            if map.insert(prim, plane).is_some() {
                return Err(format!("{PLANES_KEY} lists primitive {prim} twice"));
            }
        }
        Ok(Planes::new(map))
    }
}

/// What the learner knows of one primitive.
enum Slot {
    Plane(Plane),
    /// Hit points so far (fewer than needed, or collinear so far).
    Pending(Vec<[f64; 3]>),
    /// Its hit points are not coplanar: it collects nothing more.
    NotFlat,
}

/// Learns the planes of a segment's primitives from their hit points while it is written.
#[derive(Default)]
pub(crate) struct PlaneLearner {
    slots: IdMap<Slot>,
    /// Slots holding a list of points.
    pending: usize,
}

impl PlaneLearner {
    /// The hit distance the plane of `prim` predicts for a ray from `o` along `dir` (the
    /// direction as the decoder will see it); without a plane yet, records the hit point
    /// `o + d · t` (`d`: the recorded direction) and fits the plane once enough are in. One
    /// lookup per ray.
    #[inline]
    pub fn predict_or_observe(&mut self, prim: u32, o: [f32; 3], dir: [f32; 3], d: [f32; 3], t: f32) -> Option<f32> {
        let point = || {
            let p = [0, 1, 2].map(|k| f64::from(o[k]) + f64::from(d[k]) * f64::from(t));
            (p[0].is_finite() && p[1].is_finite() && p[2].is_finite()).then_some(p)
        };
        let pts = match self.slots.get_mut(&prim) {
            Some(Slot::Plane(plane)) => return plane.predict(o, dir),
            Some(Slot::NotFlat) => return None,
            Some(Slot::Pending(pts)) => pts,
            None => {
                if self.pending < MAX_PENDING
                    && let Some(p) = point()
                {
                    let mut pts = Vec::with_capacity(FIT_POINTS);
                    pts.push(p);
                    self.slots.insert(prim, Slot::Pending(pts));
                    self.pending += 1;
                }
                return None;
            }
        };
        pts.push(point()?);
        if !pts.len().is_multiple_of(FIT_POINTS) {
            return None;
        }
        let next = match Plane::fit(pts) {
            Fit::Plane(plane) => Slot::Plane(plane),
            Fit::Collinear if pts.len() < MAX_FIT_POINTS => return None,
            Fit::Collinear | Fit::Curved => Slot::NotFlat,
        };
        self.pending -= 1;
        self.slots.insert(prim, next);
        None
    }

    /// The planes learned.
    pub fn planes(&self) -> Planes {
        let map = self
            .slots
            .iter()
            .filter_map(|(&prim, s)| match s {
                Slot::Plane(p) => Some((prim, *p)),
                _ => None,
            })
            .collect();
        Planes::new(map)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn learn(points: &[[f32; 3]]) -> Planes {
        let mut l = PlaneLearner::default();
        for p in points {
            // A ray from the origin along p with t = 1 hits p.
            l.predict_or_observe(7, [0.0; 3], *p, *p, 1.0);
        }
        l.planes()
    }

    #[test]
    fn a_flat_primitive_predicts_hit_distances_to_a_few_ulps() {
        // Points of the tilted triangle x + 2y + 3z = 600 (scene scale ~500).
        let pts: Vec<[f32; 3]> = (0..20)
            .map(|i| {
                let (x, y) = (i as f32 * 13.7 + 5.0, (i * i % 17) as f32 * 9.1);
                [x, y, (600.0 - x - 2.0 * y) / 3.0]
            })
            .collect();
        let planes = learn(&pts);
        let plane = planes.get(7).expect("fitted");
        let (o, d) = ([10.0f32, 20.0, -400.0], [0.1f32, 0.2, 0.9746794]);
        let t = plane.predict(o, d).unwrap();
        let hit = [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t];
        assert!((hit[0] + 2.0 * hit[1] + 3.0 * hit[2] - 600.0).abs() < 1e-2, "{hit:?}");
        // Zero or non-finite directions and planes behind the origin predict nothing.
        assert_eq!(plane.predict(o, [0.0; 3]), None);
        assert_eq!(plane.predict(o, [f32::NAN, 0.0, 1.0]), None);
        assert_eq!(plane.predict(o, [-0.1, -0.2, -0.97]), None);
        // Round trip through the metadata, bit for bit.
        let back = Planes::from_metadata(&planes.to_metadata()).unwrap();
        assert_eq!(back.get(7), Some(plane));
    }

    #[test]
    fn dense_and_sparse_primitive_ids_find_their_planes() {
        let a = Plane { n: [0.0, 1.0, 0.0], offset: 2.0 };
        let b = Plane { n: [1.0, 0.0, 0.0], offset: -3.0 };
        for ids in [[5u32, 9], [5, 1 << 30], [u32::MAX - 1, 0]] {
            let map: IdMap<Plane> = [(ids[0], a), (ids[1], b)].into_iter().collect();
            let planes = Planes::new(map);
            assert_eq!(planes.dense.is_empty(), ids.iter().any(|&i| i > 10_000), "{ids:?}");
            assert_eq!(planes.get(ids[0]), Some(&a));
            assert_eq!(planes.get(ids[1]), Some(&b));
            for missing in [1u32, 7, 1 << 29, u32::MAX] {
                assert_eq!(planes.get(missing), None, "{ids:?} {missing}");
            }
            let back = Planes::from_metadata(&planes.to_metadata()).unwrap();
            assert_eq!(back.get(ids[1]), Some(&b));
        }
    }

    #[test]
    fn curved_collinear_and_non_finite_hits_get_no_plane() {
        let sphere: Vec<[f32; 3]> = (0..20)
            .map(|i| {
                let (a, b) = (i as f32 * 0.7, i as f32 * 0.3);
                [a.cos() * b.cos(), a.sin() * b.cos(), b.sin()]
            })
            .collect();
        assert!(learn(&sphere).is_empty());
        let line: Vec<[f32; 3]> = (0..20).map(|i| [i as f32, 2.0 * i as f32, 1.0]).collect();
        assert!(learn(&line).is_empty());
        let same: Vec<[f32; 3]> = vec![[1.0, 2.0, 3.0]; 20];
        assert!(learn(&same).is_empty());
        let mut l = PlaneLearner::default();
        for _ in 0..40 {
            for (prim, d) in [(1, [f32::NAN, 0.0, 1.0]), (2, [f32::INFINITY, 0.0, 1.0])] {
                assert_eq!(l.predict_or_observe(prim, [0.0; 3], d, d, 1.0), None);
            }
        }
        assert!(l.planes().is_empty());
    }

    #[test]
    fn bad_metadata_is_an_error() {
        assert!(Planes::from_metadata("not base64!").unwrap_err().contains("not base64"));
        assert!(Planes::from_metadata("AAAA").unwrap_err().contains("multiple of 36"));
        assert!(Planes::from_metadata("").unwrap().is_empty());
        let mut planes = learn(&[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0]].repeat(3));
        planes.map.insert(8, planes.map[&7]);
        let two = planes.to_metadata();
        let bytes = base64::engine::general_purpose::STANDARD.decode(&two).unwrap();
        let twice = base64::engine::general_purpose::STANDARD.encode([&bytes[..RECORD], &bytes[..RECORD]].concat());
        assert!(Planes::from_metadata(&twice).unwrap_err().contains("twice"));
    }
}
