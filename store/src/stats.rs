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
}

/// Whether every coordinate is finite: the exponent bits are not all ones (bit tests instead of
/// classifying each float).
#[inline(always)]
fn all_finite(v: [f32; 3]) -> bool {
    const EXP: u32 = 0x7f80_0000;
    v.iter().fold(true, |ok, c| ok & (c.to_bits() & EXP != EXP))
}

fn bump(v: &mut Vec<u64>, i: usize, by: u64) {
    if v.len() <= i {
        v.resize(i + 1, 0);
    }
    v[i] += by;
}

impl Stats {
    /// Statistics of the rays and trees held in `cols`.
    pub fn of_columns(cols: &RayColumns, kinds: &KindTable) -> Stats {
        Self::of_columns_with(cols, kinds, true)
    }

    /// Counts by kind and depth, and — when `with_bounds` — bounds, misses and non-finite rays
    /// (otherwise the caller adds every ray with [`Stats::add_ray`] in its own pass).
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
            let (t, hit) = (&cols.t[..n], &cols.hit[..n]);
            for i in 0..n {
                s.add_ray([ox[i], oy[i], oz[i]], [dx[i], dy[i], dz[i]], t[i], hit[i]);
            }
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

    /// Adds another set of statistics into this one.
    pub fn merge(&mut self, other: &Stats) {
        self.rays += other.rays;
        self.trees += other.trees;
        self.misses += other.misses;
        self.non_finite += other.non_finite;
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
    }

    /// Ray counts per kind.
    pub fn rays_by_kind(&self) -> BTreeMap<String, u64> {
        self.rays_by_kind_depth.iter().map(|(k, v)| (k.clone(), v.iter().sum())).collect()
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
