//! BVH what-ifs from recorded rays: replay a trace's rays against other acceleration structures
//! over the same triangles and count what each costs, beside the structures' SAH costs (Bikker,
//! "Representative Ray Sets", 2025: recorded rays predict traversal cost better than the SAH).
//!
//! Every structure is a [`ReplayTree`] (nodes with any number of children, leaves with triangle
//! lists), replayed by one counting traversal, so the counts compare: nodes visited, child boxes
//! tested, triangles tested. The builds are obvhs's PLOC at its presets and leaf sizes 1–8, a
//! binned SAH (top-down, 16 bins on centroids), an 8-wide collapse, and any recorded tree
//! (`bvh_nodes`).

use std::time::{Duration, Instant};

use glam::Vec3A;
use obvhs::BvhBuildParams;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::triangle::Triangle;

use crate::geometry::{Ray, intersect_triangle};

/// A node: its box and either children (`count` of them from `first` in
/// [`ReplayTree::children`]) or, for a leaf, triangles (`count` from `first` in
/// [`ReplayTree::prims`]).
#[derive(Clone, Copy, Debug)]
pub struct ReplayNode {
    pub min: Vec3A,
    pub max: Vec3A,
    pub leaf: bool,
    pub first: u32,
    pub count: u32,
}

/// An acceleration structure to replay rays against; node 0 is the root.
#[derive(Clone, Debug, Default)]
pub struct ReplayTree {
    pub nodes: Vec<ReplayNode>,
    pub children: Vec<u32>,
    pub prims: Vec<u32>,
}

/// A recorded node: parent (None at the root), box min and max, leaf flag, leaf triangles.
pub type RecordedNode = (Option<u32>, Vec3A, Vec3A, bool, Vec<u32>);

/// What replaying rays against one tree cost, summed over the rays.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ReplayCost {
    pub rays: u64,
    pub nodes: u64,
    pub boxes: u64,
    pub tris: u64,
}

impl ReplayCost {
    fn add(&mut self, o: &ReplayCost) {
        self.rays += o.rays;
        self.nodes += o.nodes;
        self.boxes += o.boxes;
        self.tris += o.tris;
    }

    /// Box and triangle tests per ray (the measured counterpart of the SAH cost with unit costs).
    pub fn tests_per_ray(&self) -> f64 {
        if self.rays == 0 { 0.0 } else { (self.boxes + self.tris) as f64 / self.rays as f64 }
    }
}

/// γ(3) of Pharr et al.: the slab test's far distance grows by 2γ(3), so it is conservative.
const GAMMA3: f32 = 3.0 * f32::EPSILON * 0.5 / (1.0 - 3.0 * f32::EPSILON * 0.5);

fn surface_area(min: Vec3A, max: Vec3A) -> f64 {
    let d = (max - min).max(Vec3A::ZERO);
    2.0 * (f64::from(d.x) * f64::from(d.y) + f64::from(d.y) * f64::from(d.z) + f64::from(d.z) * f64::from(d.x))
}

impl ReplayTree {
    /// The tree of an obvhs binary BVH.
    fn from_bvh2(bvh: &obvhs::bvh2::Bvh2) -> ReplayTree {
        let mut t = ReplayTree { prims: bvh.primitive_indices.clone(), ..Default::default() };
        for n in &bvh.nodes {
            let leaf = n.prim_count > 0;
            let (first, count) = if leaf {
                (n.first_index, n.prim_count)
            } else {
                let at = t.children.len() as u32;
                t.children.extend([n.first_index, n.first_index + 1]);
                (at, 2)
            };
            t.nodes.push(ReplayNode { min: n.aabb.min, max: n.aabb.max, leaf, first, count });
        }
        t
    }

    /// A tree from nodes given by parent (None at the root), bounds and leaf triangles, as a
    /// renderer's `bvh_nodes` table holds them; an error when they do not form one tree.
    pub fn from_parents(nodes: &[RecordedNode]) -> Result<ReplayTree, String> {
        let n = nodes.len();
        let roots: Vec<usize> = (0..n).filter(|&i| nodes[i].0.is_none()).collect();
        if roots.len() != 1 {
            return Err(format!("{} roots among {n} nodes, expected one", roots.len()));
        }
        let mut kids: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (i, node) in nodes.iter().enumerate() {
            if let Some(p) = node.0 {
                let p = p as usize;
                if p >= n || p == i {
                    return Err(format!("node {i} has parent {p}, not another of the {n} nodes"));
                }
                kids[p].push(i as u32);
            }
        }
        // Renumber breadth-first from the root (node 0), so any order of rows is accepted.
        let mut order = vec![roots[0] as u32];
        let mut new_id = vec![u32::MAX; n];
        new_id[roots[0]] = 0;
        let mut i = 0;
        while i < order.len() {
            for &k in &kids[order[i] as usize] {
                if new_id[k as usize] != u32::MAX {
                    return Err(format!("node {k} is reached twice"));
                }
                new_id[k as usize] = order.len() as u32;
                order.push(k);
            }
            i += 1;
        }
        if order.len() != n {
            return Err(format!("{} of {n} nodes are not under the root", n - order.len()));
        }
        let mut t = ReplayTree::default();
        for &old in &order {
            let (_, min, max, leaf, prims) = &nodes[old as usize];
            let (first, count) = if *leaf {
                let at = t.prims.len() as u32;
                t.prims.extend_from_slice(prims);
                (at, prims.len() as u32)
            } else {
                let at = t.children.len() as u32;
                t.children.extend(kids[old as usize].iter().map(|&k| new_id[k as usize]));
                (at, kids[old as usize].len() as u32)
            };
            t.nodes.push(ReplayNode { min: *min, max: *max, leaf: *leaf, first, count });
        }
        Ok(t)
    }

    /// The tree collapsed to `width`-wide nodes: each node's children are replaced by their
    /// children, the largest (by surface area) inner child first, until `width` are gathered.
    pub fn collapsed(&self, width: usize) -> ReplayTree {
        let mut out = ReplayTree { prims: self.prims.clone(), ..Default::default() };
        if self.nodes.is_empty() {
            return out;
        }
        // Breadth-first over the old tree, emitting wide nodes; old ids queued with new ids.
        let mut queue = vec![0u32];
        let mut i = 0;
        out.nodes.push(self.nodes[0]);
        while i < queue.len() {
            let old = self.nodes[queue[i] as usize];
            let new = i;
            i += 1;
            if old.leaf {
                out.nodes[new] = old;
                continue;
            }
            let mut kids: Vec<u32> = self.kids(&old).to_vec();
            while kids.len() < width {
                let pick = kids
                    .iter()
                    .enumerate()
                    .filter(|(_, k)| {
                        let n = &self.nodes[**k as usize];
                        !n.leaf && kids.len() - 1 + n.count as usize <= width
                    })
                    .max_by(|a, b| {
                        let area = |k: u32| surface_area(self.nodes[k as usize].min, self.nodes[k as usize].max);
                        area(*a.1).total_cmp(&area(*b.1))
                    })
                    .map(|(j, _)| j);
                let Some(j) = pick else { break };
                let k = kids.swap_remove(j);
                kids.extend_from_slice(self.kids(&self.nodes[k as usize]));
            }
            let at = out.children.len() as u32;
            for &k in &kids {
                out.children.push(queue.len() as u32);
                queue.push(k);
                out.nodes.push(self.nodes[k as usize]);
            }
            out.nodes[new] =
                ReplayNode { min: old.min, max: old.max, leaf: false, first: at, count: kids.len() as u32 };
        }
        out
    }

    fn kids(&self, n: &ReplayNode) -> &[u32] {
        &self.children[n.first as usize..(n.first + n.count) as usize]
    }

    /// The SAH cost with unit costs: per inner node its children's box tests, per leaf its
    /// triangle tests, each weighted by the node's surface area over the root's.
    pub fn sah_cost(&self) -> f64 {
        let Some(root) = self.nodes.first() else { return 0.0 };
        let ra = surface_area(root.min, root.max);
        if ra <= 0.0 {
            return 0.0;
        }
        self.nodes.iter().map(|n| surface_area(n.min, n.max) / ra * f64::from(n.count)).sum()
    }

    /// Nodes and the mean triangles per leaf.
    pub fn shape(&self) -> (usize, f64) {
        let leaves: Vec<&ReplayNode> = self.nodes.iter().filter(|n| n.leaf).collect();
        let tris: u64 = leaves.iter().map(|n| u64::from(n.count)).sum();
        (self.nodes.len(), if leaves.is_empty() { 0.0 } else { tris as f64 / leaves.len() as f64 })
    }

    /// The closest hit of `ray` in (tmin, tmax) on `tris` (its distance and triangle), counting
    /// what the traversal tested into `cost`. Children are visited nearest first.
    pub fn closest(
        &self,
        tris: &[[Vec3A; 3]],
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        cost: &mut ReplayCost,
    ) -> Option<(f32, u32)> {
        cost.rays += 1;
        if self.nodes.is_empty() {
            return None;
        }
        let mut best: Option<(f32, u32)> = None;
        let mut far = tmax;
        let mut stack: Vec<(u32, f32)> = Vec::with_capacity(64);
        cost.boxes += 1;
        let root = &self.nodes[0];
        if let Some(t) = slab(ray, root.min, root.max, tmin, far) {
            stack.push((0, t));
        }
        let mut hits: Vec<(f32, u32)> = Vec::with_capacity(8);
        while let Some((id, entry)) = stack.pop() {
            if entry > far {
                continue;
            }
            let n = &self.nodes[id as usize];
            cost.nodes += 1;
            if n.leaf {
                for &p in &self.prims[n.first as usize..(n.first + n.count) as usize] {
                    cost.tris += 1;
                    let [v0, v1, v2] = tris[p as usize];
                    if let Some(h) = intersect_triangle(ray, v0, v1, v2, tmin, far) {
                        far = h.t;
                        best = Some((h.t, p));
                    }
                }
                continue;
            }
            hits.clear();
            for &k in self.kids(n) {
                cost.boxes += 1;
                let c = &self.nodes[k as usize];
                if let Some(t) = slab(ray, c.min, c.max, tmin, far) {
                    hits.push((t, k));
                }
            }
            // Farthest pushed first: the nearest is popped next.
            hits.sort_by(|a, b| b.0.total_cmp(&a.0));
            stack.extend(hits.iter().map(|&(t, k)| (k, t)));
        }
        best
    }
}

/// The slab test: the entry distance when the ray meets the box within (tmin, tmax).
#[inline(always)]
fn slab(ray: &Ray, min: Vec3A, max: Vec3A, tmin: f32, tmax: f32) -> Option<f32> {
    let t0 = (min - ray.origin) * ray.inv_dir;
    let t1 = (max - ray.origin) * ray.inv_dir;
    let near = t0.min(t1).max_element().max(tmin);
    let far = t0.max(t1).min_element() * (1.0 + 2.0 * GAMMA3);
    (near <= far.min(tmax)).then_some(near)
}

/// A build to compare.
pub struct Build {
    pub name: String,
    pub tree: ReplayTree,
    pub build_time: Duration,
}

/// obvhs's PLOC at `params` with `leaf` triangles per leaf at most.
fn ploc(tris: &[[Vec3A; 3]], params: BvhBuildParams, leaf: u32) -> ReplayTree {
    let input: Vec<Triangle> = tris.iter().map(|t| Triangle { v0: t[0], v1: t[1], v2: t[2] }).collect();
    let params = BvhBuildParams { max_prims_per_leaf: leaf, ..params };
    ReplayTree::from_bvh2(&build_bvh2_from_tris(&input, params, &mut Duration::default()))
}

/// The builds `analyze bvh --whatif` compares over `tris`: PLOC at obvhs's presets (leaf 4),
/// PLOC slow (the tracers' build) at leaf sizes 1, 2, 8, a binned SAH (leaf 4), and the tracers'
/// build collapsed 8-wide.
pub fn builds(tris: &[[Vec3A; 3]]) -> Vec<Build> {
    let mut out = Vec::new();
    let mut timed = |name: &str, f: &dyn Fn() -> ReplayTree| {
        let t0 = Instant::now();
        let tree = f();
        out.push(Build { name: name.to_string(), tree, build_time: t0.elapsed() });
    };
    timed("ploc fastest, leaf 4", &|| ploc(tris, BvhBuildParams::fastest_build(), 4));
    timed("ploc fast, leaf 4", &|| ploc(tris, BvhBuildParams::fast_build(), 4));
    timed("ploc medium, leaf 4", &|| ploc(tris, BvhBuildParams::medium_build(), 4));
    timed("ploc slow, leaf 4 (the tracers')", &|| ploc(tris, BvhBuildParams::slow_build(), 4));
    timed("ploc very slow, leaf 4", &|| ploc(tris, BvhBuildParams::very_slow_build(), 4));
    for leaf in [1, 2, 8] {
        timed(&format!("ploc slow, leaf {leaf}"), &|| ploc(tris, BvhBuildParams::slow_build(), leaf));
    }
    timed("binned sah, leaf 4", &|| binned_sah(tris, 4));
    timed("ploc slow, leaf 4, 8-wide", &|| ploc(tris, BvhBuildParams::slow_build(), 4).collapsed(8));
    out
}

/// A top-down binned SAH build (16 bins per axis on the triangles' centroids, unit costs),
/// splitting until `leaf` triangles or no split is cheaper than a leaf.
pub fn binned_sah(tris: &[[Vec3A; 3]], leaf: u32) -> ReplayTree {
    const BINS: usize = 16;
    let boxes: Vec<(Vec3A, Vec3A, Vec3A)> = tris
        .iter()
        .map(|t| {
            let (lo, hi) = (t[0].min(t[1]).min(t[2]), t[0].max(t[1]).max(t[2]));
            (lo, hi, (lo + hi) * 0.5)
        })
        .collect();
    let mut idx: Vec<u32> = (0..tris.len() as u32).collect();
    let mut tree = ReplayTree::default();
    if tris.is_empty() {
        return tree;
    }
    let bound = |ids: &[u32]| {
        ids.iter().fold((Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY)), |(a, b), &i| {
            let (lo, hi, _) = boxes[i as usize];
            (a.min(lo), b.max(hi))
        })
    };
    // (node id, range in idx)
    let (lo, hi) = bound(&idx);
    tree.nodes.push(ReplayNode { min: lo, max: hi, leaf: true, first: 0, count: 0 });
    let mut work = vec![(0usize, 0usize, idx.len())];
    while let Some((node, a, b)) = work.pop() {
        let ids = &mut idx[a..b];
        let (lo, hi) = (tree.nodes[node].min, tree.nodes[node].max);
        let n = ids.len();
        let mut split: Option<(f64, usize, f32)> = None;
        if n > leaf as usize {
            let (clo, chi) =
                ids.iter().fold((Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY)), |(x, y), &i| {
                    (x.min(boxes[i as usize].2), y.max(boxes[i as usize].2))
                });
            for axis in 0..3 {
                let (c0, c1) = (clo[axis], chi[axis]);
                if c1 <= c0 {
                    continue;
                }
                let scale = BINS as f32 / (c1 - c0);
                let bin = |c: f32| (((c - c0) * scale) as usize).min(BINS - 1);
                let mut bins = [(Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY), 0usize); BINS];
                for &i in ids.iter() {
                    let (l, h, c) = boxes[i as usize];
                    let e = &mut bins[bin(c[axis])];
                    e.0 = e.0.min(l);
                    e.1 = e.1.max(h);
                    e.2 += 1;
                }
                let mut right = vec![(0.0f64, 0usize); BINS];
                let (mut rl, mut rh, mut rc) = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY), 0);
                for k in (1..BINS).rev() {
                    rl = rl.min(bins[k].0);
                    rh = rh.max(bins[k].1);
                    rc += bins[k].2;
                    right[k] = (surface_area(rl, rh), rc);
                }
                let (mut ll, mut lh, mut lc) = (Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY), 0);
                for k in 0..BINS - 1 {
                    ll = ll.min(bins[k].0);
                    lh = lh.max(bins[k].1);
                    lc += bins[k].2;
                    let (ra, rc) = right[k + 1];
                    if lc == 0 || rc == 0 {
                        continue;
                    }
                    let cost = surface_area(ll, lh) * lc as f64 + ra * rc as f64;
                    if split.is_none_or(|s| cost < s.0) {
                        split = Some((cost, axis, c0 + (k + 1) as f32 / scale));
                    }
                }
            }
        }
        // Split when cheaper than a leaf (two box tests plus the children's triangles, against
        // all triangles here), or when the leaf would be over the size.
        let leaf_cost = surface_area(lo, hi) * n as f64;
        let take = split.filter(|s| 2.0 * surface_area(lo, hi) + s.0 < leaf_cost || n > 4 * leaf as usize);
        let Some((_, axis, at)) = take else {
            tree.nodes[node].first = tree.prims.len() as u32;
            tree.nodes[node].count = n as u32;
            tree.prims.extend_from_slice(ids);
            continue;
        };
        let mut m = partition_front(ids, |i| boxes[*i as usize].2[axis] < at);
        if m == 0 || m == n {
            m = n / 2;
        }
        let kids = tree.nodes.len();
        let (l0, l1) = bound(&ids[..m]);
        let (r0, r1) = bound(&ids[m..]);
        tree.nodes.push(ReplayNode { min: l0, max: l1, leaf: true, first: 0, count: 0 });
        tree.nodes.push(ReplayNode { min: r0, max: r1, leaf: true, first: 0, count: 0 });
        let at_child = tree.children.len() as u32;
        tree.children.extend([kids as u32, kids as u32 + 1]);
        tree.nodes[node] = ReplayNode { min: lo, max: hi, leaf: false, first: at_child, count: 2 };
        work.push((kids, a, a + m));
        work.push((kids + 1, a + m, b));
    }
    tree
}

/// Moves the elements that satisfy `f` to the front; how many there are.
fn partition_front<T>(v: &mut [T], f: impl Fn(&T) -> bool) -> usize {
    let mut m = 0;
    for i in 0..v.len() {
        if f(&v[i]) {
            v.swap(i, m);
            m += 1;
        }
    }
    m
}

/// A recorded ray to replay: kind, origin, direction, recorded distance (None: a miss).
#[derive(Clone, Copy, Debug)]
pub struct RecordedRay {
    pub kind: u8,
    pub origin: Vec3A,
    pub dir: Vec3A,
    pub t: Option<f32>,
    /// Whether the recording's `t` is a closest hit (not an any-hit occlusion test).
    pub closest: bool,
}

/// One build's replay: cost per kind (index by kind), time, and how many closest-hit rays found
/// the recorded hit (up to float ties) among those checked.
#[derive(Clone, Debug, Default)]
pub struct Replay {
    pub by_kind: Vec<(u8, ReplayCost)>,
    pub total: ReplayCost,
    pub time: Duration,
    pub checked: u64,
    pub agree: u64,
    /// The first rays (by index in the replayed slice) whose replayed hit disagrees: the recorded
    /// and the replayed distance.
    pub disagree: Vec<(usize, Option<f32>, Option<f32>)>,
}

/// Whether a replayed closest hit agrees with the recorded one: both miss, or the distances agree
/// within 1e-4 relative plus 2^-16 of the origin's magnitude (the f32 error of a distance to
/// triangles with coordinates that large; a float tie between triangles gives the same distance).
fn agrees(origin: Vec3A, recorded: Option<f32>, replayed: Option<f32>) -> bool {
    match (recorded, replayed) {
        (None, None) => true,
        (Some(a), Some(b)) => {
            (a - b).abs() <= 1e-4 * a.abs().max(b.abs()) + origin.abs().max_element().max(1.0) / 65536.0
        }
        _ => false,
    }
}

/// Replays `rays` against `tree` over `tris` (closest hits in (0, ∞); occlusion rays up to their
/// recorded distance), on `threads` threads.
pub fn replay(tree: &ReplayTree, tris: &[[Vec3A; 3]], rays: &[RecordedRay], threads: usize) -> Replay {
    let t0 = Instant::now();
    let chunk = rays.len().div_ceil(threads.max(1)).max(1);
    type Part = (Vec<ReplayCost>, u64, u64, Vec<(usize, Option<f32>, Option<f32>)>);
    let parts: Vec<Part> = std::thread::scope(|s| {
        let handles: Vec<_> = rays
            .chunks(chunk)
            .enumerate()
            .map(|(c, part)| {
                s.spawn(move || {
                    let mut by = vec![ReplayCost::default(); 256];
                    let (mut checked, mut agree, mut disagree) = (0u64, 0u64, Vec::new());
                    for (i, r) in part.iter().enumerate() {
                        let ray = Ray::new(r.origin, r.dir);
                        let tmax = if r.closest { f32::INFINITY } else { r.t.unwrap_or(f32::INFINITY) };
                        let hit = tree.closest(tris, &ray, 0.0, tmax, &mut by[r.kind as usize]);
                        if r.closest {
                            checked += 1;
                            if agrees(r.origin, r.t, hit.map(|h| h.0)) {
                                agree += 1;
                            } else if disagree.len() < 5 {
                                disagree.push((c * chunk + i, r.t, hit.map(|h| h.0)));
                            }
                        }
                    }
                    (by, checked, agree, disagree)
                })
            })
            .collect();
        handles.into_iter().filter_map(|h| h.join().ok()).collect()
    });
    let mut out = Replay { time: t0.elapsed(), ..Default::default() };
    let mut by = vec![ReplayCost::default(); 256];
    for (part, c, a, d) in parts {
        out.disagree.extend(d);
        for (k, p) in part.iter().enumerate() {
            by[k].add(p);
        }
        out.checked += c;
        out.agree += a;
    }
    for (k, c) in by.iter().enumerate() {
        if c.rays > 0 {
            out.by_kind.push((k as u8, *c));
            out.total.add(c);
        }
    }
    out
}

/// A representative subset of `rays`: every `1/share`-th ray of each stratum (kind, direction
/// octant, origin cell of a 4×4×4 grid over the origins' bounds), at least one per stratum.
pub fn representative(rays: &[RecordedRay], share: f64) -> Vec<RecordedRay> {
    let (lo, hi) = rays.iter().fold((Vec3A::splat(f32::INFINITY), Vec3A::splat(f32::NEG_INFINITY)), |(a, b), r| {
        if r.origin.is_finite() { (a.min(r.origin), b.max(r.origin)) } else { (a, b) }
    });
    let ext = (hi - lo).max(Vec3A::splat(f32::MIN_POSITIVE));
    let key = |r: &RecordedRay| {
        let c = ((r.origin - lo) / ext * 4.0).clamp(Vec3A::ZERO, Vec3A::splat(3.0));
        let cell = if c.is_finite() { c.x as u32 + 4 * c.y as u32 + 16 * c.z as u32 } else { 64 };
        let oct = u32::from(r.dir.x < 0.0) | u32::from(r.dir.y < 0.0) << 1 | u32::from(r.dir.z < 0.0) << 2;
        (u32::from(r.kind) << 10) | (oct << 7) | cell
    };
    let every = (1.0 / share.clamp(1e-9, 1.0)).round().max(1.0) as u64;
    let mut seen = std::collections::HashMap::new();
    let mut out = Vec::new();
    for r in rays {
        let n = seen.entry(key(r)).or_insert(0u64);
        if n.is_multiple_of(every) {
            out.push(*r);
        }
        *n += 1;
    }
    out
}

/// Spearman's rank correlation of two equally long series (average ranks for ties); NaN for
/// fewer than two values or a constant series.
pub fn spearman(a: &[f64], b: &[f64]) -> f64 {
    fn ranks(v: &[f64]) -> Vec<f64> {
        let mut idx: Vec<usize> = (0..v.len()).collect();
        idx.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
        let mut r = vec![0.0; v.len()];
        let mut i = 0;
        while i < idx.len() {
            let mut j = i;
            while j + 1 < idx.len() && v[idx[j + 1]] == v[idx[i]] {
                j += 1;
            }
            for k in i..=j {
                r[idx[k]] = (i + j) as f64 / 2.0 + 1.0;
            }
            i = j + 1;
        }
        r
    }
    if a.len() != b.len() || a.len() < 2 {
        return f64::NAN;
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len() as f64;
    let mean = (n + 1.0) / 2.0;
    let (mut num, mut da, mut db) = (0.0, 0.0, 0.0);
    for i in 0..a.len() {
        num += (ra[i] - mean) * (rb[i] - mean);
        da += (ra[i] - mean).powi(2);
        db += (rb[i] - mean).powi(2);
    }
    if da == 0.0 || db == 0.0 { f64::NAN } else { num / (da * db).sqrt() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::BuiltinScene;
    use crate::sampling::Rng;

    fn rays(scene: &crate::Scene, n: usize) -> Vec<RecordedRay> {
        let bvh = crate::Bvh::build(&scene.tris);
        let mut rng = Rng::for_sample(1, 2, 3, 4);
        (0..n)
            .map(|i| {
                let o = Vec3A::new(rng.next_f32() * 556.0, rng.next_f32() * 548.0, rng.next_f32() * 559.0);
                let d = Vec3A::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5).normalize();
                let hit = bvh.intersect(&Ray::new(o, d), 0.0, f32::INFINITY, &mut Default::default(), None);
                RecordedRay { kind: (i % 3) as u8, origin: o, dir: d, t: hit.map(|h| h.t), closest: true }
            })
            .collect()
    }

    #[test]
    fn every_build_replays_the_recorded_closest_hits() {
        let scene = BuiltinScene::Cornell.build(4).unwrap();
        let rs = rays(&scene, 2000);
        let builds = builds(&scene.tris);
        assert!(builds.len() >= 6);
        for b in &builds {
            let r = replay(&b.tree, &scene.tris, &rs, 2);
            assert_eq!((r.checked, r.agree), (2000, 2000), "{}", b.name);
            assert_eq!(r.total.rays, 2000);
            assert!(r.total.tris > 0 && r.total.boxes > r.total.rays, "{}: {:?}", b.name, r.total);
            assert!(b.tree.sah_cost() > 0.0, "{}", b.name);
            // Leaves hold at most what was asked (the wide one keeps the leaf-4 leaves).
            let leaf = b.name.split("leaf ").nth(1).and_then(|s| s[..1].parse::<u32>().ok()).unwrap();
            let max = b.tree.nodes.iter().filter(|n| n.leaf).map(|n| n.count).max().unwrap();
            let cap = if b.name.starts_with("binned") { 4 * leaf } else { leaf };
            assert!(max <= cap, "{}: leaf of {max}", b.name);
        }
        // The 8-wide tree visits fewer nodes than its binary source and tests more boxes per node.
        let find = |n: &str| builds.iter().find(|b| b.name.starts_with(n)).unwrap();
        let (bin, wide) = (find("ploc slow, leaf 4 (the"), find("ploc slow, leaf 4, 8-wide"));
        let (rb, rw) = (replay(&bin.tree, &scene.tris, &rs, 1), replay(&wide.tree, &scene.tris, &rs, 1));
        assert!(rw.total.nodes < rb.total.nodes, "{:?} vs {:?}", rw.total, rb.total);
        assert_eq!(wide.tree.prims.len(), bin.tree.prims.len());
    }

    #[test]
    fn a_tree_from_parents_replays_like_its_source_and_bad_trees_are_refused() {
        let scene = BuiltinScene::Cornell.build(2).unwrap();
        let src = ploc(&scene.tris, BvhBuildParams::fast_build(), 2);
        // As a table would list it: parent links, leaves with their triangles, rows reversed.
        let mut parent = vec![None; src.nodes.len()];
        for (i, n) in src.nodes.iter().enumerate() {
            if !n.leaf {
                for &k in src.kids(n) {
                    parent[k as usize] = Some(i as u32);
                }
            }
        }
        let last = src.nodes.len() as u32 - 1;
        let rows: Vec<_> = (0..src.nodes.len())
            .rev()
            .map(|i| {
                let n = &src.nodes[i];
                let prims = if n.leaf {
                    src.prims[n.first as usize..(n.first + n.count) as usize].to_vec()
                } else {
                    Vec::new()
                };
                (parent[i].map(|p| last - p), n.min, n.max, n.leaf, prims)
            })
            .collect();
        let t = ReplayTree::from_parents(&rows).unwrap();
        let rs = rays(&scene, 500);
        let (a, b) = (replay(&src, &scene.tris, &rs, 1), replay(&t, &scene.tris, &rs, 1));
        assert_eq!(b.agree, 500);
        // The same boxes; only the order of children with equal entry distances differs.
        let close = |x: u64, y: u64| (x as f64 - y as f64).abs() <= 0.05 * x as f64;
        assert!(
            close(a.total.tris, b.total.tris) && close(a.total.boxes, b.total.boxes),
            "{:?} {:?}",
            a.total,
            b.total
        );
        assert!((src.sah_cost() - t.sah_cost()).abs() < 1e-9 * src.sah_cost());
        let mut two_roots = rows.clone();
        two_roots[0].0 = None;
        assert!(ReplayTree::from_parents(&two_roots).unwrap_err().contains("roots"));
        let mut bad_parent = rows;
        bad_parent[1].0 = Some(10_000_000);
        assert!(ReplayTree::from_parents(&bad_parent).is_err());
    }

    #[test]
    fn representative_subsets_and_rank_correlation() {
        let scene = BuiltinScene::Cornell.build(1).unwrap();
        let rs = rays(&scene, 50_000);
        // A tenth of each stratum, and the first ray of each (3 kinds x 8 octants x 64 cells).
        let sub = representative(&rs, 0.1);
        assert!(sub.len() >= 5000 && sub.len() <= 5000 + 3 * 8 * 64, "{}", sub.len());
        assert_eq!(representative(&rs, 1.0).len(), rs.len());
        assert!((spearman(&[1.0, 2.0, 3.0], &[10.0, 20.0, 30.0]) - 1.0).abs() < 1e-12);
        assert!((spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
        assert!((spearman(&[1.0, 2.0, 2.0, 4.0], &[1.0, 3.0, 3.0, 4.0]) - 1.0).abs() < 1e-12);
        assert!(spearman(&[1.0], &[1.0]).is_nan() && spearman(&[1.0, 1.0], &[1.0, 2.0]).is_nan());
    }
}
