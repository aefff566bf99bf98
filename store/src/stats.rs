//! Statistics of a trace, computed as segments are sealed and kept in the manifest.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::Kind;
use crate::columns::RayColumns;
use crate::schema::KindTable;

/// An axis-aligned box; empty until a finite point is added.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Default for Bounds {
    fn default() -> Self {
        Self { min: [f32::INFINITY; 3], max: [f32::NEG_INFINITY; 3] }
    }
}

impl Bounds {
    pub fn is_empty(&self) -> bool {
        (0..3).any(|i| self.min[i] > self.max[i])
    }

    /// Grows the box to hold `p` if all its coordinates are finite.
    #[inline]
    pub fn add(&mut self, p: [f32; 3]) {
        if all_finite(p) {
            self.grow(p);
        }
    }

    /// Grows the bounds to `p`, known finite: plain `<`/`>` compile to min/max instructions
    /// (no NaN can reach them), unlike the NaN-aware `f32::min`/`max`.
    #[inline(always)]
    fn grow(&mut self, p: [f32; 3]) {
        for ((lo, hi), c) in self.min.iter_mut().zip(self.max.iter_mut()).zip(p) {
            *lo = if c < *lo { c } else { *lo };
            *hi = if c > *hi { c } else { *hi };
        }
    }

    pub fn merge(&mut self, other: &Bounds) {
        if !other.is_empty() {
            self.add(other.min);
            self.add(other.max);
        }
    }
}

/// The pixels a set of trees belongs to: an inclusive rectangle, empty until a tree is added.
/// Segments carry theirs in the manifest, so a lookup by pixel opens only the segments whose
/// rectangle holds the pixel (manifests written before it have none: every segment is a candidate).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PixelBounds {
    pub min: [u32; 2],
    pub max: [u32; 2],
}

impl Default for PixelBounds {
    fn default() -> Self {
        Self { min: [u32::MAX; 2], max: [0; 2] }
    }
}

impl PixelBounds {
    pub fn is_empty(&self) -> bool {
        self.min[0] > self.max[0] || self.min[1] > self.max[1]
    }

    /// Grows the rectangle to hold pixel `p`.
    #[inline]
    pub fn add(&mut self, p: [u32; 2]) {
        for ((lo, hi), c) in self.min.iter_mut().zip(self.max.iter_mut()).zip(p) {
            *lo = (*lo).min(c);
            *hi = (*hi).max(c);
        }
    }

    pub fn merge(&mut self, other: &PixelBounds) {
        if !other.is_empty() {
            self.add(other.min);
            self.add(other.max);
        }
    }

    /// Whether pixel `p` is inside.
    pub fn contains(&self, p: [u32; 2]) -> bool {
        (0..2).all(|i| self.min[i] <= p[i] && p[i] <= self.max[i])
    }
}

/// Ray and tree counts by kind and depth, and the scene bounds the rays span.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub rays: u64,
    pub trees: u64,
    /// Rays missing everything (no hit distance).
    pub misses: u64,
    /// Rays with a NaN or infinite origin or direction component.
    pub non_finite: u64,
    /// Ray counts per kind name, indexed by depth.
    pub rays_by_kind_depth: BTreeMap<String, Vec<u64>>,
    /// Tree counts indexed by the tree's deepest ray depth.
    pub trees_by_max_depth: Vec<u64>,
    /// Bounds of the finite ray origins (absent while empty).
    #[serde(default, skip_serializing_if = "Bounds::is_empty")]
    pub origin_bounds: Bounds,
    /// Bounds of the finite hit points (origin + t · direction; absent while empty).
    #[serde(default, skip_serializing_if = "Bounds::is_empty")]
    pub hit_bounds: Bounds,
    /// The pixels of the trees (absent while empty, and in manifests written before 2026-12-05).
    #[serde(default, skip_serializing_if = "PixelBounds::is_empty")]
    pub pixel_bounds: PixelBounds,
}

/// Whether `v` is finite: its exponent bits are not all ones (a bit test instead of classifying
/// the float, which vectorizes).
#[inline(always)]
fn finite(v: f32) -> bool {
    const EXP: u32 = 0x7f80_0000;
    v.to_bits() & EXP != EXP
}

/// Whether every coordinate is finite.
#[inline(always)]
fn all_finite(v: [f32; 3]) -> bool {
    v.iter().fold(true, |ok, &c| ok & finite(c))
}

/// The least of `init` and `c` (no NaN in them), in eight lanes the compiler keeps in vector
/// registers (a single running minimum of floats is not vectorized: it would reorder NaNs).
#[inline(always)]
fn lane_min(c: &[f32], init: f32) -> f32 {
    lane_pick(c, init, |v, m| v < m)
}

/// The greatest of `init` and `c`, as [`lane_min`].
#[inline(always)]
fn lane_max(c: &[f32], init: f32) -> f32 {
    lane_pick(c, init, |v, m| v > m)
}

/// The value of `c` (or `init`) that `better` prefers to every other, in eight lanes.
#[inline(always)]
fn lane_pick(c: &[f32], init: f32, better: impl Fn(f32, f32) -> bool + Copy) -> f32 {
    let mut acc = [init; 8];
    let chunks = c.chunks_exact(8);
    let rest = chunks.remainder();
    for ch in chunks {
        for (a, &v) in acc.iter_mut().zip(ch) {
            *a = if better(v, *a) { v } else { *a };
        }
    }
    acc.iter().chain(rest).fold(init, |m, &v| if better(v, m) { v } else { m })
}

/// Adds `by` to count `i` (saturating: counts read from a manifest are not trusted).
fn bump(v: &mut Vec<u64>, i: usize, by: u64) {
    if v.len() <= i {
        v.resize(i + 1, 0);
    }
    v[i] = v[i].saturating_add(by);
}

impl Stats {
    /// Statistics of the rays and trees held in `cols`.
    pub fn of_columns(cols: &RayColumns, kinds: &KindTable) -> Stats {
        Self::of_columns_with(cols, kinds, true)
    }

    /// Counts by kind and depth, and — when `with_bounds` — bounds, misses and non-finite rays
    /// (otherwise the caller adds every ray with [`Stats::add_rays`] in its own pass).
    pub(crate) fn of_columns_with(cols: &RayColumns, kinds: &KindTable, with_bounds: bool) -> Stats {
        let n = cols.len();
        let mut s = Stats { rays: n as u64, trees: cols.trees.len() as u64, ..Default::default() };
        // Counts by kind and depth: a flat table for the usual depths, growable lists beyond.
        const SHALLOW: usize = 32;
        let mut shallow = vec![0u64; 256 * SHALLOW];
        let mut deep: Vec<Vec<u64>> = vec![Vec::new(); 256];
        for (&k, &d) in cols.kind[..n].iter().zip(&cols.depth[..n]) {
            let d = d as usize;
            if d < SHALLOW {
                shallow[k as usize * SHALLOW + d] += 1;
            } else {
                bump(&mut deep[k as usize], d, 1);
            }
        }
        if with_bounds {
            let (ox, oy, oz) = (&cols.origin[0][..n], &cols.origin[1][..n], &cols.origin[2][..n]);
            let (dx, dy, dz) = (&cols.direction[0][..n], &cols.direction[1][..n], &cols.direction[2][..n]);
            s.add_rays([ox, oy, oz], [dx, dy, dz], &cols.t[..n], &cols.hit[..n]);
        }
        for (code, mut counts) in deep.into_iter().enumerate() {
            let row = &shallow[code * SHALLOW..(code + 1) * SHALLOW];
            if let Some(last) = row.iter().rposition(|&c| c > 0) {
                if counts.len() <= last {
                    counts.resize(last + 1, 0);
                }
                for (d, &c) in row[..=last].iter().enumerate() {
                    counts[d] += c;
                }
            }
            if !counts.is_empty() {
                let name = kinds.name(Kind(code as u8)).map_or_else(|| format!("kind{code}"), str::to_string);
                s.rays_by_kind_depth.insert(name, counts);
            }
        }
        for t in &cols.trees {
            bump(&mut s.trees_by_max_depth, t.max_depth as usize, 1);
            s.pixel_bounds.add([t.pixel_x, t.pixel_y]);
        }
        s
    }

    /// Adds one ray's origin and hit point to the bounds, and counts it as a miss or non-finite.
    #[inline]
    pub(crate) fn add_ray(&mut self, o: [f32; 3], d: [f32; 3], t: f32, hit: bool) {
        let finite_o = all_finite(o);
        self.non_finite += u64::from(!(finite_o & all_finite(d)));
        if finite_o {
            self.origin_bounds.grow(o);
        }
        if hit {
            self.hit_bounds.add([o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
        } else {
            self.misses += 1;
        }
    }

    /// [`Stats::add_ray`] for columns of rays (all slices as long as `t`): blocks whose origins and
    /// directions are all finite (nearly all of them) take branch-free loops the compiler turns
    /// into vector min/max; a block holding a NaN or an infinity goes ray by ray.
    pub(crate) fn add_rays(&mut self, o: [&[f32]; 3], d: [&[f32]; 3], t: &[f32], hit: &[bool]) {
        const BLOCK: usize = 256;
        let n = t.len().min(hit.len()).min(o.iter().chain(&d).map(|c| c.len()).min().unwrap_or(0));
        let mut start = 0;
        while start < n {
            let end = (start + BLOCK).min(n);
            let r = start..end;
            let all = |c: &[f32]| c.iter().fold(true, |ok, &v| ok & finite(v));
            if !o.iter().chain(&d).all(|c| all(&c[r.clone()])) {
                for i in r {
                    self.add_ray([o[0][i], o[1][i], o[2][i]], [d[0][i], d[1][i], d[2][i]], t[i], hit[i]);
                }
                start = end;
                continue;
            }
            let hit = &hit[r.clone()];
            let t = &t[r.clone()];
            self.misses += hit.iter().map(|&h| u64::from(!h)).sum::<u64>();
            for (k, oc) in o.iter().enumerate() {
                let oc = &oc[r.clone()];
                self.origin_bounds.min[k] = lane_min(oc, self.origin_bounds.min[k]);
                self.origin_bounds.max[k] = lane_max(oc, self.origin_bounds.max[k]);
            }
            // Hit points: a miss, or a point that overflowed, stays out of the box; a point must
            // be finite in all three coordinates, so validity is found before the min/max.
            let len = hit.len();
            let mut valid = [true; BLOCK];
            let mut p = [[0f32; BLOCK]; 3];
            for k in 0..3 {
                let (oc, dc) = (&o[k][r.clone()], &d[k][r.clone()]);
                for (i, ((pv, (&ov, &dv)), &tv)) in p[k].iter_mut().zip(oc.iter().zip(dc)).zip(t).enumerate() {
                    *pv = ov + tv * dv;
                    valid[i] &= finite(*pv);
                }
            }
            for (v, &h) in valid.iter_mut().zip(hit) {
                *v &= h;
            }
            let mut masked = [0f32; BLOCK];
            for (k, pk) in p.iter().enumerate() {
                for ((m, &v), &ok) in masked.iter_mut().zip(pk).zip(&valid) {
                    *m = if ok { v } else { f32::INFINITY };
                }
                self.hit_bounds.min[k] = lane_min(&masked[..len], self.hit_bounds.min[k]);
                for ((m, &v), &ok) in masked.iter_mut().zip(pk).zip(&valid) {
                    *m = if ok { v } else { f32::NEG_INFINITY };
                }
                self.hit_bounds.max[k] = lane_max(&masked[..len], self.hit_bounds.max[k]);
            }
            start = end;
        }
    }

    /// Adds another set of statistics into this one (saturating: a manifest's counts are not
    /// trusted, and `check` compares the sums with what the files hold).
    pub fn merge(&mut self, other: &Stats) {
        self.rays = self.rays.saturating_add(other.rays);
        self.trees = self.trees.saturating_add(other.trees);
        self.misses = self.misses.saturating_add(other.misses);
        self.non_finite = self.non_finite.saturating_add(other.non_finite);
        for (k, v) in &other.rays_by_kind_depth {
            let mine = self.rays_by_kind_depth.entry(k.clone()).or_default();
            for (d, c) in v.iter().enumerate() {
                bump(mine, d, *c);
            }
        }
        for (d, c) in other.trees_by_max_depth.iter().enumerate() {
            bump(&mut self.trees_by_max_depth, d, *c);
        }
        self.origin_bounds.merge(&other.origin_bounds);
        self.hit_bounds.merge(&other.hit_bounds);
        self.pixel_bounds.merge(&other.pixel_bounds);
    }

    /// Counts the rays of kind `from` under the name `to` (added to those already there).
    pub fn rename_kind(&mut self, from: &str, to: &str) {
        if let Some(counts) = self.rays_by_kind_depth.remove(from) {
            let mine = self.rays_by_kind_depth.entry(to.to_string()).or_default();
            for (d, c) in counts.iter().enumerate() {
                bump(mine, d, *c);
            }
        }
    }

    /// Ray counts per kind.
    pub fn rays_by_kind(&self) -> BTreeMap<String, u64> {
        self.rays_by_kind_depth
            .iter()
            .map(|(k, v)| (k.clone(), v.iter().fold(0u64, |a, &c| a.saturating_add(c))))
            .collect()
    }

    /// Ray counts per depth.
    pub fn rays_by_depth(&self) -> Vec<u64> {
        let mut out = Vec::new();
        for v in self.rays_by_kind_depth.values() {
            for (d, c) in v.iter().enumerate() {
                bump(&mut out, d, *c);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The column path gives the statistics of adding ray by ray, NaN, infinities, overflowing
    /// hit points and misses included, across block boundaries.
    #[test]
    fn columns_of_rays_give_the_stats_of_single_rays() {
        let n = 1000;
        let mut cols: [Vec<f32>; 7] = Default::default();
        let mut hit = Vec::new();
        let mut x = 12345u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x
        };
        for i in 0..n {
            for c in cols.iter_mut() {
                c.push((next() % 20_000) as f32 * 0.01 - 100.0);
            }
            hit.push(next() % 4 != 0);
            match i {
                300 => cols[0][i] = f32::NAN,
                301 => cols[4][i] = f32::INFINITY,
                302 => cols[6][i] = 3.0e38, // the hit point overflows
                700 => cols[2][i] = f32::NEG_INFINITY,
                _ => {}
            }
        }
        let mut one = Stats::default();
        for i in 0..n {
            one.add_ray([cols[0][i], cols[1][i], cols[2][i]], [cols[3][i], cols[4][i], cols[5][i]], cols[6][i], hit[i]);
        }
        let mut all = Stats::default();
        all.add_rays([&cols[0], &cols[1], &cols[2]], [&cols[3], &cols[4], &cols[5]], &cols[6], &hit);
        assert_eq!(all, one);
        assert_eq!(all.non_finite, 3);
        assert!(all.misses > 0 && !all.hit_bounds.is_empty());
        // Only finite rays in a block: still the same.
        let mut a = Stats::default();
        let mut b = Stats::default();
        a.add_rays(
            [&cols[0][..256], &cols[1][..256], &cols[2][..256]],
            [&cols[3][..256], &cols[4][..256], &cols[5][..256]],
            &cols[6][..256],
            &hit[..256],
        );
        for i in 0..256 {
            b.add_ray([cols[0][i], cols[1][i], cols[2][i]], [cols[3][i], cols[4][i], cols[5][i]], cols[6][i], hit[i]);
        }
        assert_eq!(a, b);
    }
}
