//! The BVH: built with obvhs (PLOC + reinsertion), traversed by our own code that counts what
//! each ray costs and can list the nodes it visits.
//!
//! Traversal: the binary tree is collapsed into 8-wide nodes whose child boxes are tested as eight
//! SIMD lanes (exact float boxes, conservative slab test after Ize 2013, NaN-free for axis-parallel
//! rays); children are visited nearest first, leaves are tested as soon as their box is hit, and
//! stack entries carry their entry distance so nothing is re-tested on the way back. The same code
//! is compiled twice, once for AVX2 (one 256-bit operation per step, picked at run time where the
//! CPU has it) and once for the target's baseline (two SSE operations on x86_64); both give
//! bit-identical results. Each child slot keeps its binary node id, so `nodes_visited` and the
//! `ray_nodes` table name nodes of the `bvh_nodes` table (collapsed intermediate nodes are not
//! entered, hence not counted).
//! `rtvtk bench trace` compares it with obvhs's stock traversals and Embree on the same rays.

/// Set on a visited leaf's id in a visit list when one of its triangles was hit (in the ray's
/// interval at that moment): leaf visits without it are false-positive box tests.
pub const VISIT_HIT: u32 = 1 << 31;

use std::mem::MaybeUninit;
use std::time::Duration;

use arrow::array::RecordBatch;
use glam::{Vec3A, Vec4};
use obvhs::BvhBuildParams;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::triangle::Triangle;

use crate::geometry::{Ray, TriHit, intersect_triangle};

/// What one traversal cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalStats {
    /// Nodes entered (their box was hit and they were processed).
    pub nodes: u32,
    /// Ray/box tests.
    pub boxes: u32,
    /// Ray/triangle tests.
    pub tris: u32,
}

/// A hit: distance, triangle (index into the scene's triangles) and barycentrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub prim: u32,
    pub u: f32,
    pub v: f32,
}

/// See [`Bvh::layout`].
#[derive(Clone, Copy, Debug)]
pub struct BvhLayout {
    pub wide_nodes: usize,
    pub leaf_blocks: usize,
    pub bytes: usize,
    pub mean_leaf_tris: f64,
}

#[derive(Clone, Copy, Debug)]
struct Node {
    min: Vec3A,
    max: Vec3A,
    /// Inner: index of the first child (the second follows). Leaf: first slot in `prims`.
    first: u32,
    /// 0 for inner nodes.
    count: u32,
}

/// Children per node of the tree traversal uses: eight boxes tested by one 256-bit SIMD operation
/// per step where the CPU has AVX2 (chosen at run time), two 128-bit ones elsewhere.
const W: usize = 8;

/// A `W`-wide node collapsed from the binary tree: the child boxes as SIMD lanes, per axis.
/// Empty slots have min = max = +∞ and count `EMPTY`; `slab_w` masks them out by their counts.
/// Exactly four cache lines: what only recording needs (the children's ids) lives beside, in
/// `Bvh::ids_w`.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct NodeW {
    min: [[f32; W]; 3],
    max: [[f32; W]; 3],
    /// Inner child: index into `nodes_w`. Leaf child: index into `blocks` (at most four
    /// triangles) or first slot in `prims` (more).
    child: [u32; W],
    /// 0 for an inner child, the triangle count for a leaf, `u32::MAX` for an empty slot.
    count: [u32; W],
}

const _: () = assert!(std::mem::size_of::<NodeW>() == 32 * W);

/// Traversal stack entries kept inline: a visit pushes at most `W - 1`, so this holds any path of
/// up to 73 wide nodes (a binary tree of depth 73 at least; `rtvtk bench trace` prints the binary
/// depth, 28 for 608K triangles). Deeper trees spill onto the heap (`Stack::spill`).
const STACK: usize = 64 * W;

/// The traversal stack: `STACK` entries inline, left uninitialized until pushed (zeroing them
/// would be a 2–4 KB memset per ray, more than a short ray's whole traversal); pushes beyond
/// them go to a heap vector, allocated only then, so no subtree is ever dropped.
struct Stack<T: Copy> {
    items: [MaybeUninit<T>; STACK],
    len: usize,
    /// Entries pushed while `items` was full (the newest on top). Non-empty only while `len ==
    /// STACK`, so popping it first keeps last-in first-out order.
    spill: Vec<T>,
}

impl<T: Copy> Stack<T> {
    #[inline(always)]
    fn new() -> Self {
        Stack { items: [const { MaybeUninit::uninit() }; STACK], len: 0, spill: Vec::new() }
    }

    #[inline(always)]
    fn push(&mut self, v: T) {
        match self.items.get_mut(self.len) {
            Some(slot) => {
                slot.write(v);
                self.len += 1;
            }
            None => self.spill.push(v),
        }
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<T> {
        if !self.spill.is_empty() {
            return self.spill.pop();
        }
        self.len = self.len.checked_sub(1)?;
        // SAFETY: entries below the old `len` were written by `push`.
        Some(unsafe { self.items[self.len].assume_init() })
    }
}

impl NodeW {
    /// Occupied slots (boxes a visit tests).
    #[inline(always)]
    fn slots(&self) -> u32 {
        occupied_mask(&self.count).count_ones()
    }
}

const EMPTY: u32 = u32::MAX;

/// Up to four triangles of one leaf as SIMD lanes: `v[vertex][axis]`.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct LeafBlock {
    v: [[Vec4; 3]; 3],
    prim: [u32; 4],
    count: u32,
    /// First slot in `prims`/`verts` (for the exact scalar fallback).
    first: u32,
}

/// The closest of up to four triangles hit in (tmin, tmax): watertight (Woop et al. 2013) on four
/// lanes at once. A lane exactly on an edge (U, V or W = 0) sends the whole block to the scalar
/// test, which decides such cases in double precision. `skip` masks out one primitive.
#[inline(always)]
fn intersect_block(b: &LeafBlock, ray: &Ray, tmin: f32, tmax: f32, skip: u32) -> Result<Option<(TriHit, u32)>, ()> {
    let (kx, ky, kz) = (ray.kx, ray.ky, ray.kz);
    let o = [Vec4::splat(ray.origin[kx]), Vec4::splat(ray.origin[ky]), Vec4::splat(ray.origin[kz])];
    let rel = |vtx: usize| [b.v[vtx][kx] - o[0], b.v[vtx][ky] - o[1], b.v[vtx][kz] - o[2]];
    let (a, bb, c) = (rel(0), rel(1), rel(2));
    let (sx, sy) = (Vec4::splat(ray.sx), Vec4::splat(ray.sy));
    let ax = a[0] - sx * a[2];
    let ay = a[1] - sy * a[2];
    let bx = bb[0] - sx * bb[2];
    let by = bb[1] - sy * bb[2];
    let cx = c[0] - sx * c[2];
    let cy = c[1] - sy * c[2];
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    let zero = Vec4::ZERO;
    let lanes = (1u32 << b.count) - 1;
    if (u.cmpeq(zero) | v.cmpeq(zero) | w.cmpeq(zero)).bitmask() & lanes != 0 {
        return Err(());
    }
    let neg = u.cmplt(zero) | v.cmplt(zero) | w.cmplt(zero);
    let pos = u.cmpgt(zero) | v.cmpgt(zero) | w.cmpgt(zero);
    let det = u + v + w;
    let sz = Vec4::splat(ray.sz);
    // Same operations, in the same order, as the scalar test: results are bit-identical.
    let inv_det = Vec4::ONE / det;
    let t = (u * (sz * a[2]) + v * (sz * bb[2]) + w * (sz * c[2])) * inv_det;
    let ok = !(neg & pos) & det.cmpne(zero) & t.cmpgt(Vec4::splat(tmin)) & t.cmplt(Vec4::splat(tmax));
    let mut mask = ok.bitmask() & lanes;
    let mut best: Option<(TriHit, u32)> = None;
    while mask != 0 {
        let i = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        if b.prim[i] == skip || !t[i].is_finite() {
            continue;
        }
        if best.as_ref().is_none_or(|(h, _)| t[i] < h.t) {
            best = Some((TriHit { t: t[i], u: v[i] * inv_det[i], v: w[i] * inv_det[i] }, b.prim[i]));
        }
    }
    Ok(best)
}

/// A binary BVH over triangles.
pub struct Bvh {
    nodes: Vec<Node>,
    /// The `W`-wide tree traversal uses; empty when the root is a leaf.
    nodes_w: Vec<NodeW>,
    /// The binary-tree ids (and `bvh_nodes` ids) of each wide node's children, for recording visits.
    ids_w: Vec<[u32; W]>,
    /// Leaf triangles as SIMD blocks, indexed by `NodeW::child` of leaf slots.
    blocks: Vec<LeafBlock>,
    /// Triangle index per leaf slot.
    prims: Vec<u32>,
    /// Triangle vertices per leaf slot (copied for locality).
    verts: Vec<[Vec3A; 3]>,
    parents: Vec<u32>,
    depth: u32,
}

/// γ(3) of Pharr et al.: the relative error bound that makes the slab test conservative.
const GAMMA3: f32 = 3.0 * f32::EPSILON * 0.5 / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// 1/d with components of magnitude below 1e-30 clamped to ±1e-30 first: finite, so the SIMD
/// slab test never forms 0 · ∞ (an axis-parallel ray starting on a box plane).
#[inline(always)]
fn safe_inv(d: Vec3A) -> Vec3A {
    let tiny = Vec3A::splat(1e-30);
    let clamped = Vec3A::select(d.abs().cmplt(tiny), tiny.copysign(d), d);
    Vec3A::ONE / clamped
}

#[inline(always)]
fn slab_simd(min: Vec3A, max: Vec3A, org: Vec3A, inv: Vec3A, tmin: f32, tmax: f32) -> f32 {
    // Inputs are finite (see safe_inv), so plain comparisons stand in for the NaN-aware (and
    // slower) f32::min/max.
    // (min − o)·inv, not min·inv − o·inv: the latter cancels catastrophically for rays starting on a
    // box plane, and the conservative bound (Ize 2013) no longer holds — grazing rays leaked.
    let t1 = (min - org) * inv;
    let t2 = (max - org) * inv;
    let lo = t1.min(t2);
    let hi = t1.max(t2);
    let (lx, ly, lz) = (lo.x, lo.y, lo.z);
    let (hx, hy, hz) = (hi.x, hi.y, hi.z);
    let mut near = if lx > ly { lx } else { ly };
    near = if lz > near { lz } else { near };
    near = if tmin > near { tmin } else { near };
    let mut far = if hx < hy { hx } else { hy };
    far = if hz < far { hz } else { far };
    far = if tmax < far { tmax } else { far };
    if near <= far * (1.0 + 2.0 * GAMMA3) { near } else { f32::INFINITY }
}

/// Bit `i` set where `a[i] <= b[i]`. On x86_64 two SSE compares and mask moves (the AVX2 build
/// fuses them into one 256-bit compare and `vmovmskps`); the plain loop elsewhere (LLVM does not
/// turn it into a mask move, it reduces the lanes one by one).
#[inline(always)]
fn le_mask(a: &[f32; W], b: &[f32; W]) -> u32 {
    const _: () = assert!(W == 8, "le_mask and occupied_mask are written for 8 lanes");
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_cmple_ps, _mm_loadu_ps, _mm_movemask_ps};
        // SAFETY: SSE is part of the x86_64 baseline; the loads read lanes 0..4 and 4..8 of W = 8.
        unsafe {
            let lo = _mm_cmple_ps(_mm_loadu_ps(a.as_ptr()), _mm_loadu_ps(b.as_ptr()));
            let hi = _mm_cmple_ps(_mm_loadu_ps(a.as_ptr().add(4)), _mm_loadu_ps(b.as_ptr().add(4)));
            (_mm_movemask_ps(lo) | (_mm_movemask_ps(hi) << 4)) as u32
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    a.iter().zip(b).enumerate().fold(0, |m, (i, (x, y))| m | (u32::from(x <= y) << i))
}

/// Bit `i` set where slot `i` of the node holds a child (its count is not `EMPTY`).
#[inline(always)]
fn occupied_mask(count: &[u32; W]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            __m128i, _mm_castsi128_ps, _mm_cmpeq_epi32, _mm_loadu_si128, _mm_movemask_ps, _mm_set1_epi32,
        };
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads read lanes 0..4 and 4..8 of W = 8.
        unsafe {
            let e = _mm_set1_epi32(EMPTY as i32);
            let lo = _mm_cmpeq_epi32(_mm_loadu_si128(count.as_ptr().cast::<__m128i>()), e);
            let hi = _mm_cmpeq_epi32(_mm_loadu_si128(count.as_ptr().add(4).cast::<__m128i>()), e);
            !(_mm_movemask_ps(_mm_castsi128_ps(lo)) | (_mm_movemask_ps(_mm_castsi128_ps(hi)) << 4)) as u32 & 0xff
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    count.iter().enumerate().fold(0, |m, (i, &c)| m | (u32::from(c != EMPTY) << i))
}

/// Runs `f` (a traversal: `#[inline(always)]` all the way down) compiled for AVX2 where this CPU
/// has it (the check is cached by std), for the target's baseline otherwise. Its `W`-lane loops
/// become 256-bit operations; no fused multiply-add is formed, so results are bit-identical.
#[inline(always)]
fn fastest<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("popcnt")
        && std::arch::is_x86_feature_detected!("bmi1")
    {
        // SAFETY: the CPU has AVX2, FMA, POPCNT and BMI1 (checked just above).
        return unsafe { with_avx2(f) };
    }
    f()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,popcnt,bmi1")]
fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    f()
}

fn half_area(n: &Node) -> f32 {
    let d = (n.max - n.min).max(Vec3A::ZERO);
    d.x * d.y + d.y * d.z + d.z * d.x
}

/// The binary nodes that become the child slots of the wide node made for inner node `root`:
/// the largest inner child is opened until all `W` slots are full.
fn wide_slots(nodes: &[Node], root: u32) -> Vec<u32> {
    let mut slots: Vec<u32> = vec![nodes[root as usize].first, nodes[root as usize].first + 1];
    while slots.len() < W {
        let open = slots
            .iter()
            .enumerate()
            .filter(|(_, c)| nodes[**c as usize].count == 0)
            .max_by(|a, b| half_area(&nodes[*a.1 as usize]).total_cmp(&half_area(&nodes[*b.1 as usize])))
            .map(|(i, _)| i);
        let Some(i) = open else { break };
        let c = slots.swap_remove(i);
        let f = nodes[c as usize].first;
        slots.push(f);
        slots.push(f + 1);
    }
    slots
}

/// Collapses the binary tree under inner node `root` into `W`-wide nodes, the root first. The
/// inner children of a wide node are stored next to each other (one allocation each time a node
/// is filled), so the siblings a ray visits one after the other share pages and nearby lines.
fn collapse(nodes: &[Node], root: u32, out: &mut Vec<NodeW>, ids: &mut Vec<[u32; W]>) {
    let inf = [f32::INFINITY; W];
    let empty = NodeW { min: [inf; 3], max: [inf; 3], child: [0; W], count: [EMPTY; W] };
    out.push(empty);
    ids.push([0; W]);
    let mut todo = vec![(root, 0usize)];
    while let Some((bin, me)) = todo.pop() {
        let slots = wide_slots(nodes, bin);
        for (k, &c) in slots.iter().enumerate() {
            let n = nodes[c as usize];
            for a in 0..3 {
                out[me].min[a][k] = n.min[a];
                out[me].max[a][k] = n.max[a];
            }
            ids[me][k] = c;
            out[me].count[k] = n.count;
            out[me].child[k] = n.first;
            if n.count == 0 {
                let child = out.len();
                out.push(empty);
                ids.push([0; W]);
                out[me].child[k] = child as u32;
                todo.push((c, child));
            }
        }
    }
}

/// Entry distances of the child boxes of `n` and the mask of the boxes hit, conservative as
/// `slab_simd`. Plain per-lane code the compiler turns into `W`-wide SIMD (inputs are finite, see
/// `safe_inv`, so plain comparisons stand in for the NaN-aware `f32::min/max`). Empty slots
/// (min = max = +∞) are masked out: with every plane at +∞ an infinite ray would "hit" them.
#[inline(always)]
fn slab_w(n: &NodeW, org: [f32; 3], inv: [f32; 3], tmin: f32, tmax: f32) -> ([f32; W], u32) {
    let mut near = [0.0f32; W];
    let mut far = [0.0f32; W];
    let mn = |a: f32, b: f32| if a < b { a } else { b };
    let mx = |a: f32, b: f32| if a > b { a } else { b };
    for i in 0..W {
        let t1x = (n.min[0][i] - org[0]) * inv[0];
        let t2x = (n.max[0][i] - org[0]) * inv[0];
        let t1y = (n.min[1][i] - org[1]) * inv[1];
        let t2y = (n.max[1][i] - org[1]) * inv[1];
        let t1z = (n.min[2][i] - org[2]) * inv[2];
        let t2z = (n.max[2][i] - org[2]) * inv[2];
        near[i] = mx(mx(mx(mn(t1x, t2x), mn(t1y, t2y)), mn(t1z, t2z)), tmin);
        far[i] = mn(mn(mn(mx(t1x, t2x), mx(t1y, t2y)), mx(t1z, t2z)), tmax) * (1.0 + 2.0 * GAMMA3);
    }
    (near, le_mask(&near, &far) & occupied_mask(&n.count))
}

impl Bvh {
    /// Builds a BVH over `tris` (each three vertices). Empty input gives an empty BVH.
    pub fn build(tris: &[[Vec3A; 3]]) -> Bvh {
        if tris.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                nodes_w: Vec::new(),
                ids_w: Vec::new(),
                blocks: Vec::new(),
                prims: Vec::new(),
                verts: Vec::new(),
                parents: Vec::new(),
                depth: 0,
            };
        }
        let input: Vec<Triangle> = tris.iter().map(|t| Triangle { v0: t[0], v1: t[1], v2: t[2] }).collect();
        let params = BvhBuildParams { max_prims_per_leaf: 4, ..BvhBuildParams::slow_build() };
        let bvh = build_bvh2_from_tris(&input, params, &mut Duration::default());
        let nodes: Vec<Node> = bvh
            .nodes
            .iter()
            .map(|n| Node { min: n.aabb.min, max: n.aabb.max, first: n.first_index, count: n.prim_count })
            .collect();
        let prims = bvh.primitive_indices.clone();
        let verts: Vec<[Vec3A; 3]> = prims.iter().map(|&p| tris[p as usize]).collect();
        let mut parents = vec![u32::MAX; nodes.len()];
        let mut depth = 0;
        let mut stack = vec![(0u32, 0u32)];
        while let Some((i, level)) = stack.pop() {
            depth = depth.max(level);
            let n = nodes[i as usize];
            if n.count == 0 {
                for c in [n.first, n.first + 1] {
                    parents[c as usize] = i;
                    stack.push((c, level + 1));
                }
            }
        }
        let (mut nodes_w, mut ids_w) = (Vec::new(), Vec::new());
        if nodes[0].count == 0 {
            collapse(&nodes, 0, &mut nodes_w, &mut ids_w);
        }
        // One SIMD block per leaf slot of the wide tree.
        let mut blocks = Vec::new();
        for n in &mut nodes_w {
            for k in 0..W {
                // Leaves of more than four triangles keep the scalar path (child = first slot);
                // empty slots (count EMPTY) and inner children (0) have no block.
                let (first, count) = (n.child[k], n.count[k]);
                if (1..=4).contains(&count) {
                    let mut b = LeafBlock { v: [[Vec4::ZERO; 3]; 3], prim: [u32::MAX; 4], count, first };
                    for lane in 0..count as usize {
                        let slot = first as usize + lane;
                        for (vtx, p) in verts[slot].iter().enumerate() {
                            for (axis, c) in p.to_array().into_iter().enumerate() {
                                b.v[vtx][axis][lane] = c;
                            }
                        }
                        b.prim[lane] = prims[slot];
                    }
                    n.child[k] = blocks.len() as u32;
                    blocks.push(b);
                }
            }
        }
        Bvh { nodes, nodes_w, ids_w, blocks, prims, verts, parents, depth }
    }

    /// Closest hit among leaf slots `first..first + count` (scalar watertight test), narrowing `tmax`.
    #[inline(always)]
    fn leaf_closest(
        &self,
        (first, count): (u32, u32),
        ray: &Ray,
        tmin: f32,
        tmax: &mut f32,
        best: &mut Option<(TriHit, u32)>,
    ) {
        for slot in first..first + count {
            let [v0, v1, v2] = self.verts[slot as usize];
            if let Some(h) = intersect_triangle(ray, v0, v1, v2, tmin, *tmax) {
                *tmax = h.t;
                *best = Some((h, self.prims[slot as usize]));
            }
        }
    }

    /// Any hit among leaf slots `first..first + count` other than triangle `skip`.
    #[inline(always)]
    fn leaf_any(&self, (first, count): (u32, u32), ray: &Ray, tmin: f32, tmax: f32, skip: u32) -> Option<Hit> {
        (first..first + count).find_map(|slot| {
            let prim = self.prims[slot as usize];
            let [v0, v1, v2] = self.verts[slot as usize];
            (prim != skip).then(|| intersect_triangle(ray, v0, v1, v2, tmin, tmax)).flatten().map(|h| Hit {
                t: h.t,
                prim,
                u: h.u,
                v: h.v,
            })
        })
    }

    /// Tests the root box (counting it); the ray's safe inverse direction when it is entered.
    #[inline(always)]
    fn enter_root(&self, ray: &Ray, tmin: f32, tmax: f32, stats: &mut TraversalStats) -> Option<Vec3A> {
        let root = self.nodes.first()?;
        let inv = safe_inv(ray.dir);
        stats.boxes += 1;
        if slab_simd(root.min, root.max, ray.origin, inv, tmin, tmax) == f32::INFINITY {
            return None;
        }
        stats.nodes += 1;
        Some(inv)
    }

    /// Whether binary node `id` is a leaf (false for an id out of range).
    pub fn is_leaf(&self, id: u32) -> bool {
        self.nodes.get(id as usize).is_some_and(|n| n.count > 0)
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Depth of the deepest leaf (the root is level 0).
    pub fn depth(&self) -> u32 {
        self.depth
    }

    /// The binary tree as a GPU tracer flattens it: per node (min, max, first, count), the root
    /// first; an inner node (count 0) has its children at `first` and `first + 1`, a leaf its
    /// `count` triangles at slots `first..` of [`Bvh::leaf_slots`].
    pub fn binary_nodes(&self) -> Vec<([f32; 3], [f32; 3], u32, u32)> {
        self.nodes.iter().map(|n| (n.min.to_array(), n.max.to_array(), n.first, n.count)).collect()
    }

    /// Per leaf slot: the scene triangle's index and its vertices.
    pub fn leaf_slots(&self) -> impl Iterator<Item = (u32, [Vec3A; 3])> + '_ {
        self.prims.iter().copied().zip(self.verts.iter().copied())
    }

    /// What traversal reads, for benchmark reports: wide nodes, leaf blocks, their bytes, and
    /// the mean number of triangles per leaf.
    pub fn layout(&self) -> BvhLayout {
        let leaves = self.nodes.iter().filter(|n| n.count > 0).count();
        BvhLayout {
            wide_nodes: self.nodes_w.len(),
            leaf_blocks: self.blocks.len(),
            bytes: std::mem::size_of_val(self.nodes_w.as_slice()) + std::mem::size_of_val(self.blocks.as_slice()),
            mean_leaf_tris: self.prims.len() as f64 / leaves.max(1) as f64,
        }
    }

    /// Closest hit in (tmin, tmax), counting the work; lists visited nodes when `visits` is given
    /// (in visit order; a leaf whose triangles gave a closer hit carries [`VISIT_HIT`]).
    pub fn intersect(
        &self,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        stats: &mut TraversalStats,
        visits: Option<&mut Vec<u32>>,
    ) -> Option<Hit> {
        fastest(
            #[inline(always)]
            || self.intersect_in(ray, tmin, tmax, stats, visits),
        )
    }

    #[inline(always)]
    fn intersect_in(
        &self,
        ray: &Ray,
        tmin: f32,
        mut tmax: f32,
        stats: &mut TraversalStats,
        mut visits: Option<&mut Vec<u32>>,
    ) -> Option<Hit> {
        let inv = self.enter_root(ray, tmin, tmax, stats)?;
        if let Some(v) = visits.as_deref_mut() {
            v.push(0);
        }
        let mut best: Option<(TriHit, u32)> = None;
        let root = &self.nodes[0];
        if root.count > 0 {
            stats.tris += root.count;
            self.leaf_closest((root.first, root.count), ray, tmin, &mut tmax, &mut best);
            if best.is_some()
                && let Some(last) = visits.as_deref_mut().and_then(|v| v.last_mut())
            {
                *last |= VISIT_HIT;
            }
            return best.map(|(h, p)| Hit { t: h.t, prim: p, u: h.u, v: h.v });
        }
        let (org, inv) = (ray.origin.to_array(), inv.to_array());
        // Stack of (wide node, distance at which its box was entered).
        let mut stack = Stack::<(u32, f32)>::new();
        let mut node = 0u32;
        loop {
            let node_index = node as usize;
            let n = &self.nodes_w[node_index];
            let (d, mut hits) = slab_w(n, org, inv, tmin, tmax);
            stats.boxes += n.slots();
            // Hit children, nearest first.
            let mut order = [(0usize, 0.0f32); W];
            let mut k = 0;
            while hits != 0 {
                let c = hits.trailing_zeros() as usize;
                hits &= hits - 1;
                let dc = d[c];
                let mut j = k;
                while j > 0 && order[j - 1].1 > dc {
                    order[j] = order[j - 1];
                    j -= 1;
                }
                order[j] = (c, dc);
                k += 1;
            }
            let mut next: Option<(u32, f32)> = None;
            let mut deferred = [(0u32, 0.0f32); W];
            let mut nd = 0;
            for &(c, dist) in &order[..k] {
                if dist > tmax {
                    break;
                }
                stats.nodes += 1;
                if let Some(v) = visits.as_deref_mut() {
                    v.push(self.ids_w[node_index][c]);
                }
                if n.count[c] > 0 {
                    stats.tris += n.count[c];
                    let before = tmax;
                    if n.count[c] > 4 {
                        self.leaf_closest((n.child[c], n.count[c]), ray, tmin, &mut tmax, &mut best);
                    } else {
                        let b = &self.blocks[n.child[c] as usize];
                        match intersect_block(b, ray, tmin, tmax, u32::MAX) {
                            Ok(Some(hit)) => {
                                tmax = hit.0.t;
                                best = Some(hit);
                            }
                            Ok(None) => {}
                            Err(()) => self.leaf_closest((b.first, b.count), ray, tmin, &mut tmax, &mut best),
                        }
                    }
                    if tmax < before
                        && let Some(last) = visits.as_deref_mut().and_then(|v| v.last_mut())
                    {
                        *last |= VISIT_HIT;
                    }
                } else if next.is_none() {
                    next = Some((n.child[c], dist));
                } else {
                    deferred[nd] = (n.child[c], dist);
                    nd += 1;
                }
            }
            // Farther inner children wait on the stack, farthest deepest.
            for &e in deferred[..nd].iter().rev() {
                stack.push(e);
            }
            if let Some((c, _)) = next {
                node = c;
                continue;
            }
            loop {
                let Some((c, dist)) = stack.pop() else {
                    return best.map(|(h, p)| Hit { t: h.t, prim: p, u: h.u, v: h.v });
                };
                if dist <= tmax {
                    node = c;
                    break;
                }
            }
        }
    }

    /// Whether anything lies in (tmin, tmax): stops at the first hit. Returns the hit found.
    pub fn any_hit(&self, ray: &Ray, tmin: f32, tmax: f32, stats: &mut TraversalStats) -> Option<Hit> {
        self.any_hit_except(ray, tmin, tmax, u32::MAX, stats, None)
    }

    /// Like [`Bvh::any_hit`], ignoring triangle `skip`: a shadow ray's target emitter cannot occlude
    /// itself, whatever rounding does to the end of the ray far from the origin.
    pub fn any_hit_except(
        &self,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        skip: u32,
        stats: &mut TraversalStats,
        visits: Option<&mut Vec<u32>>,
    ) -> Option<Hit> {
        fastest(
            #[inline(always)]
            || self.any_hit_in(ray, tmin, tmax, skip, stats, visits),
        )
    }

    #[inline(always)]
    fn any_hit_in(
        &self,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        skip: u32,
        stats: &mut TraversalStats,
        mut visits: Option<&mut Vec<u32>>,
    ) -> Option<Hit> {
        let inv = self.enter_root(ray, tmin, tmax, stats)?;
        if let Some(v) = visits.as_deref_mut() {
            v.push(0);
        }
        let mark = |visits: Option<&mut Vec<u32>>, found: &Option<Hit>| {
            if found.is_some()
                && let Some(last) = visits.and_then(|v| v.last_mut())
            {
                *last |= VISIT_HIT;
            }
        };
        let root = &self.nodes[0];
        if root.count > 0 {
            stats.tris += root.count;
            let found = self.leaf_any((root.first, root.count), ray, tmin, tmax, skip);
            mark(visits, &found);
            return found;
        }
        let (org, inv) = (ray.origin.to_array(), inv.to_array());
        let mut stack = Stack::<u32>::new();
        stack.push(0);
        while let Some(top) = stack.pop() {
            let node_index = top as usize;
            let n = &self.nodes_w[node_index];
            let (_, mut hits) = slab_w(n, org, inv, tmin, tmax);
            stats.boxes += n.slots();
            while hits != 0 {
                let c = hits.trailing_zeros() as usize;
                hits &= hits - 1;
                stats.nodes += 1;
                if let Some(v) = visits.as_deref_mut() {
                    v.push(self.ids_w[node_index][c]);
                }
                if n.count[c] > 0 {
                    stats.tris += n.count[c];
                    let found = if n.count[c] > 4 {
                        self.leaf_any((n.child[c], n.count[c]), ray, tmin, tmax, skip)
                    } else {
                        let b = &self.blocks[n.child[c] as usize];
                        match intersect_block(b, ray, tmin, tmax, skip) {
                            Ok(h) => h.map(|(h, p)| Hit { t: h.t, prim: p, u: h.u, v: h.v }),
                            Err(()) => self.leaf_any((b.first, b.count), ray, tmin, tmax, skip),
                        }
                    };
                    if found.is_some() {
                        mark(visits, &found);
                        return found;
                    }
                } else {
                    stack.push(n.child[c]);
                }
            }
        }
        None
    }

    /// Checks the structure: children inside parents, every triangle in at least one leaf (large
    /// triangles are split across leaves),
    /// leaves bounding their triangles. Returns the first violation.
    pub fn validate(&self, triangle_count: usize) -> Result<(), String> {
        if self.nodes.is_empty() {
            return if triangle_count == 0 { Ok(()) } else { Err("empty BVH over triangles".into()) };
        }
        let mut seen = vec![0u32; triangle_count];
        let mut stack = vec![0u32];
        while let Some(i) = stack.pop() {
            let n = self.nodes[i as usize];
            if n.count == 0 {
                for c in [n.first, n.first + 1] {
                    let cn = self.nodes.get(c as usize).ok_or(format!("node {i}: child {c} out of range"))?;
                    if cn.min.cmplt(n.min).any() || cn.max.cmpgt(n.max).any() {
                        return Err(format!("node {c} is not inside its parent {i}"));
                    }
                    stack.push(c);
                }
            } else {
                for slot in n.first..n.first + n.count {
                    let p = *self.prims.get(slot as usize).ok_or(format!("leaf {i}: slot {slot} out of range"))?;
                    *seen.get_mut(p as usize).ok_or(format!("leaf {i}: triangle {p} out of range"))? += 1;
                    for v in self.verts[slot as usize] {
                        if v.cmplt(n.min).any() || v.cmpgt(n.max).any() {
                            return Err(format!("leaf {i} does not bound triangle {p}"));
                        }
                    }
                }
            }
        }
        match seen.iter().position(|&c| c == 0) {
            Some(p) => Err(format!("triangle {p} is in no leaf")),
            None => Ok(()),
        }
    }

    /// The `bvh_nodes` table: id, parent, level, bounds and leaf triangles of every node (built
    /// by `store::scene::bvh_nodes_batch`, as the C API's is).
    pub fn node_table(&self) -> Result<RecordBatch, arrow::error::ArrowError> {
        let rows: Vec<store::scene::BvhNodeRow<'_>> = self
            .nodes
            .iter()
            .zip(&self.parents)
            .map(|(node, &p)| store::scene::BvhNodeRow {
                parent: (p != u32::MAX).then_some(p),
                min: node.min.to_array(),
                max: node.max.to_array(),
                leaf: node.count > 0,
                prims: if node.count > 0 {
                    &self.prims[node.first as usize..(node.first + node.count) as usize]
                } else {
                    &[]
                },
            })
            .collect();
        store::scene::bvh_nodes_batch(&rows).map_err(arrow::error::ArrowError::InvalidArgumentError)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::sampling::Rng;
    use crate::scene::BuiltinScene;

    /// Past its inline entries the stack spills to the heap and still pops last in, first out.
    #[test]
    fn stack_spills_without_losing_entries() {
        let mut st = Stack::<u32>::new();
        let n = 3 * STACK as u32 + 5;
        for i in 0..n {
            st.push(i);
        }
        assert_eq!(st.spill.len(), n as usize - STACK);
        // Interleaved pops and pushes across the boundary.
        assert_eq!(st.pop(), Some(n - 1));
        st.push(7);
        assert_eq!(st.pop(), Some(7));
        for i in (0..n - 1).rev() {
            assert_eq!(st.pop(), Some(i));
        }
        assert_eq!(st.pop(), None);
        st.push(1);
        assert_eq!((st.pop(), st.pop()), (Some(1), None));
    }

    /// The baseline build of the traversal (`*_in`, compiled without AVX2 here) and the public
    /// entry points (the AVX2 build on a CPU that has it) agree bit for bit: hits, counts and
    /// visit lists, for closest and any hit, from inside and outside the box, axis-parallel too.
    #[test]
    fn both_builds_of_the_traversal_agree() {
        let scene = BuiltinScene::Cornell.build(12).unwrap();
        let bvh = Bvh::build(&scene.tris);
        assert!(bvh.nodes_w.len() > 8, "the test needs a tree of many wide nodes");
        let mut rng = Rng::for_sample(3, 4, 5, 6);
        for i in 0..4000 {
            let o = Vec3A::new(rng.next_f32() * 556.0, rng.next_f32() * 548.0, rng.next_f32() * 1200.0 - 600.0);
            let d = if i % 10 == 0 {
                [Vec3A::X, Vec3A::NEG_Y, Vec3A::Z][i % 3]
            } else {
                Vec3A::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5).normalize()
            };
            let ray = Ray::new(o, d);
            let tmax = if i % 4 == 0 { 300.0 } else { f32::INFINITY };
            let (mut s1, mut s2) = (TraversalStats::default(), TraversalStats::default());
            let (mut v1, mut v2) = (Vec::new(), Vec::new());
            let a = bvh.intersect_in(&ray, 0.0, tmax, &mut s1, Some(&mut v1));
            let b = bvh.intersect(&ray, 0.0, tmax, &mut s2, Some(&mut v2));
            assert_eq!(a, b, "closest hit, ray {i}");
            assert_eq!((s1, &v1), (s2, &v2), "closest-hit work, ray {i}");
            let skip = a.map_or(u32::MAX, |h| h.prim);
            let (mut s1, mut s2) = (TraversalStats::default(), TraversalStats::default());
            let a = bvh.any_hit_in(&ray, 0.0, tmax, skip, &mut s1, None);
            let b = bvh.any_hit_except(&ray, 0.0, tmax, skip, &mut s2, None);
            assert_eq!(a, b, "any hit, ray {i}");
            assert_eq!(s1, s2, "any-hit work, ray {i}");
        }
    }
}
