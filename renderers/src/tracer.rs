//! The tracers: a Kajiya-style path tracer with next-event estimation and a recursive Whitted
//! tracer. Both describe every ray they trace in a [`SampleRecord`], which the render driver
//! hands to `rl` (rays, kinds, parents, hit primitives, traversal counts, throughput, radiance).

use glam::Vec3A;
use rl::Kind;

use crate::bvh::{Bvh, Hit, TraversalStats};
use crate::geometry::{Ray, offset_point};
use crate::material::{self, Lobe, fresnel, reflect};
use crate::sampling::{Rng, triangle_point};
use crate::scene::{MaterialKind, Scene};

/// A bug to inject on purpose, to be found with the toolkit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bug {
    /// The paper's Figure 1: shadow rays leaving upward-facing diffuse surfaces after the first
    /// bounce are mirrored about the vertical axis, so many are aimed at no light. Visibility
    /// comes from the wrong direction, shading from the right one: the image still looks plausible.
    ShadowDir,
    /// A zero light-sampling pdf where the light is seen at a grazing angle (cosine below 0.1):
    /// the shadow ray's weight divides by it, so its throughput is infinite and the pixel NaN or
    /// infinite (the "NaN pixel" of many renderers' issue trackers).
    Nan,
    /// Secondary rays start at the hit point itself, not offset off the surface by its float
    /// error bound: about half of them hit the surface they leave (self-intersection, acne).
    NoOffset,
    /// Secondary rays start a fixed step (1% of the scene's diagonal) along their direction:
    /// near corners and thin parts they start behind a surface they never hit (light leaks).
    Leak,
}

impl Bug {
    /// Every bug, in the order of `--inject-bug`'s help.
    pub const ALL: [Bug; 4] = [Bug::ShadowDir, Bug::Nan, Bug::NoOffset, Bug::Leak];

    /// The bug's name on the command line and in a dataset's `inject_bug` attribute.
    pub fn name(self) -> &'static str {
        match self {
            Bug::ShadowDir => "shadow-dir",
            Bug::Nan => "nan",
            Bug::NoOffset => "no-offset",
            Bug::Leak => "leak",
        }
    }

    /// The bug named `s`; an error listing the names otherwise.
    pub fn parse(s: &str) -> Result<Bug, String> {
        Bug::ALL.into_iter().find(|b| b.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Bug::ALL.iter().map(|b| b.name()).collect();
            format!("unknown bug {s:?}: expected one of {}", names.join(", "))
        })
    }
}

/// One traced ray as recorded.
#[derive(Clone, Copy, Debug)]
pub struct RecRay {
    pub parent: Option<u32>,
    pub origin: Vec3A,
    pub dir: Vec3A,
    pub t: Option<f32>,
    pub prim: Option<u32>,
    pub kind: Kind,
    /// The weight of what this ray carries in the pixel estimate.
    pub throughput: Vec3A,
    /// The radiance this ray carries back to its origin.
    pub radiance: Vec3A,
    pub material: Option<u32>,
    pub stats: TraversalStats,
    /// Range in `SampleRecord::visits` of the nodes this ray visited (when recording visits).
    pub visits: (u32, u32),
    /// Where in the tracer's source the ray was traced (the recording's `site`).
    pub site: &'static std::panic::Location<'static>,
}

impl RecRay {
    /// A ray traced for its closest hit (radiance is filled in once known).
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    fn traced(
        scene: &Scene,
        parent: Option<u32>,
        ray: &Ray,
        hit: Option<Hit>,
        kind: Kind,
        throughput: Vec3A,
        stats: TraversalStats,
        visits: (u32, u32),
    ) -> RecRay {
        RecRay {
            parent,
            origin: ray.origin,
            dir: ray.dir,
            t: hit.map(|h| h.t),
            prim: hit.map(|h| h.prim),
            kind,
            throughput,
            radiance: Vec3A::ZERO,
            material: hit.map(|h| scene.tri_material[h.prim as usize]),
            stats,
            visits,
            site: std::panic::Location::caller(),
        }
    }

    /// A shadow ray towards emitter `target` at distance `dist`, blocked by `occluder` if any:
    /// recorded up to the blocker, or up to the light it reached.
    #[allow(clippy::too_many_arguments)]
    #[track_caller]
    fn shadow(
        scene: &Scene,
        parent: u32,
        ray: &Ray,
        target: u32,
        dist: f32,
        occluder: Option<Hit>,
        throughput: Vec3A,
        stats: TraversalStats,
        visits: (u32, u32),
    ) -> RecRay {
        let prim = occluder.map_or(target, |o| o.prim);
        RecRay {
            parent: Some(parent),
            origin: ray.origin,
            dir: ray.dir,
            t: Some(occluder.map_or(dist, |o| o.t)),
            prim: Some(prim),
            kind: Kind::SHADOW,
            throughput,
            radiance: if occluder.is_none() { scene.material_of(target).emission } else { Vec3A::ZERO },
            material: Some(scene.tri_material[prim as usize]),
            stats,
            visits,
            site: std::panic::Location::caller(),
        }
    }
}

/// The rays of one pixel sample (kept only when `keep` is set; always counted by kind).
#[derive(Clone, Debug)]
pub struct SampleRecord {
    pub keep: bool,
    pub rays: Vec<RecRay>,
    pub visits: Vec<u32>,
    pub counts: [u64; 256],
}

impl SampleRecord {
    pub fn new(keep: bool) -> Self {
        Self { keep, rays: Vec::new(), visits: Vec::new(), counts: [0; 256] }
    }

    /// Forgets the rays of the last sample (counts go on).
    pub fn clear(&mut self) {
        self.rays.clear();
        self.visits.clear();
    }
}

/// What the tracers share.
pub struct TraceCtx<'a> {
    pub scene: &'a Scene,
    pub bvh: &'a Bvh,
    pub max_depth: u32,
    pub bug: Option<Bug>,
    pub record_visits: bool,
    /// How far `Bug::Leak` pushes secondary rays along their direction (1% of the diagonal).
    leak_step: f32,
}

impl<'a> TraceCtx<'a> {
    pub fn new(scene: &'a Scene, bvh: &'a Bvh, max_depth: u32, bug: Option<Bug>, record_visits: bool) -> Self {
        let (lo, hi) = scene.bounds();
        let diag = (hi - lo).length();
        let leak_step = if diag.is_finite() { 0.01 * diag } else { 0.0 };
        TraceCtx { scene, bvh, max_depth, bug, record_visits, leak_step }
    }

    /// Where a secondary ray leaving surface point `p` on the side of normal `n` in direction
    /// `dir` starts: off the surface by its float error bound (`offset_point`), or where an
    /// injected bug puts it.
    fn spawn(&self, p: Vec3A, n: Vec3A, dir: Vec3A) -> Vec3A {
        match self.bug {
            Some(Bug::NoOffset) => p,
            Some(Bug::Leak) => p + dir * self.leak_step,
            _ => offset_point(p, n),
        }
    }
    fn closest(&self, ray: &Ray, rec: &mut Option<&mut SampleRecord>) -> (Option<Hit>, TraversalStats, (u32, u32)) {
        let mut st = TraversalStats::default();
        match rec {
            Some(r) if self.record_visits && r.keep => {
                let start = r.visits.len() as u32;
                let h = self.bvh.intersect(ray, 0.0, f32::INFINITY, &mut st, Some(&mut r.visits));
                (h, st, (start, r.visits.len() as u32))
            }
            _ => (self.bvh.intersect(ray, 0.0, f32::INFINITY, &mut st, None), st, (0, 0)),
        }
    }

    /// Any hit of a shadow ray towards emitter `target` closer than `tmax`, listing its visits when
    /// recorded.
    fn occluded(
        &self,
        ray: &Ray,
        tmax: f32,
        target: u32,
        rec: &mut Option<&mut SampleRecord>,
    ) -> (Option<Hit>, TraversalStats, (u32, u32)) {
        let mut st = TraversalStats::default();
        match rec {
            Some(r) if self.record_visits && r.keep => {
                let start = r.visits.len() as u32;
                let h = self.bvh.any_hit_except(ray, 0.0, tmax, target, &mut st, Some(&mut r.visits));
                (h, st, (start, r.visits.len() as u32))
            }
            _ => (self.bvh.any_hit_except(ray, 0.0, tmax, target, &mut st, None), st, (0, 0)),
        }
    }

    fn hit_point(&self, h: &Hit) -> Vec3A {
        // From barycentrics: more accurate than origin + t·direction far from the origin.
        let [v0, v1, v2] = self.scene.tris[h.prim as usize];
        v0 * (1.0 - h.u - h.v) + v1 * h.u + v2 * h.v
    }

    /// Samples a point on an emitter: (point, normal, triangle, pdf per unit area).
    fn sample_light(&self, rng: &mut Rng) -> Option<(Vec3A, Vec3A, u32, f32)> {
        let s = self.scene;
        if s.lights.is_empty() || s.light_area <= 0.0 {
            return None;
        }
        let prim = s.lights[s.pick_emitter(rng.next_f32())];
        let [v0, v1, v2] = s.tris[prim as usize];
        let (b1, b2) = triangle_point(rng.next_f32(), rng.next_f32());
        let p = v0 * (1.0 - b1 - b2) + v1 * b1 + v2 * b2;
        Some((p, s.normals[prim as usize], prim, 1.0 / s.light_area))
    }
}

fn push(rec: &mut Option<&mut SampleRecord>, r: RecRay) -> u32 {
    match rec {
        Some(out) => {
            out.counts[r.kind.0 as usize] += 1;
            if out.keep {
                out.rays.push(r);
                out.rays.len() as u32 - 1
            } else {
                0
            }
        }
        None => 0,
    }
}

/// Traces one path-tracer sample through film position (fx, fy); returns its radiance estimate.
pub fn path_sample(
    ctx: &TraceCtx<'_>,
    fx: f32,
    fy: f32,
    w: u32,
    h: u32,
    rng: &mut Rng,
    mut rec: Option<&mut SampleRecord>,
) -> Vec3A {
    let scene = ctx.scene;
    let cam = &scene.camera;
    let mut ray = Ray::new(cam.position, cam.direction(fx, fy, w, h));
    let mut kind = Kind::CAMERA;
    let mut parent: Option<u32> = None;
    let mut beta = Vec3A::ONE;
    let mut l = Vec3A::ZERO;
    let mut count_emission = true;
    // (ray index, throughput when spawned, radiance gathered before it) along the path.
    let mut chain: [(u32, Vec3A, Vec3A); 64] = [(0, Vec3A::ZERO, Vec3A::ZERO); 64];
    let mut chain_len = 0usize;
    let mut depth = 0u32;
    loop {
        let (hit, st, vis) = ctx.closest(&ray, &mut rec);
        let idx = push(&mut rec, RecRay::traced(scene, parent, &ray, hit, kind, beta, st, vis));
        if chain_len < chain.len() {
            chain[chain_len] = (idx, beta, l);
            chain_len += 1;
        }
        let Some(hit) = hit else { break };
        let m = scene.material_of(hit.prim);
        let ng = scene.normals[hit.prim as usize];
        if count_emission && m.is_emissive() {
            l += beta * m.emission;
        }
        if depth >= ctx.max_depth {
            break;
        }
        let p = ctx.hit_point(&hit);
        let front = ng.dot(ray.dir) < 0.0;
        let n = if front { ng } else { -ng };
        if matches!(m.kind, MaterialKind::Diffuse | MaterialKind::Glossy) {
            // Next-event estimation: one shadow ray to a point on an emitter.
            if let Some((q, nl, lprim, pdf_area)) = ctx.sample_light(rng) {
                let origin = ctx.spawn(p, n, (q - p).normalize_or_zero());
                let to = q - origin;
                let dist2 = to.length_squared();
                let dist = dist2.sqrt();
                let wi = to / dist;
                let cos_x = n.dot(wi);
                let cos_l = nl.dot(wi).abs();
                if cos_x > 0.0 && dist > 0.0 {
                    let mut sdir = wi;
                    if ctx.bug == Some(Bug::ShadowDir) && depth >= 1 && m.kind == MaterialKind::Diffuse && n.y > 0.9 {
                        sdir = Vec3A::new(-wi.x, wi.y, -wi.z);
                    }
                    let sray = Ray::new(origin, sdir);
                    let (occ, sst, svis) = ctx.occluded(&sray, dist * (1.0 - 1e-4), lprim, &mut rec);
                    let f = material::eval(m, n, -ray.dir, wi);
                    let pdf_area = if ctx.bug == Some(Bug::Nan) && cos_l < 0.1 { 0.0 } else { pdf_area };
                    let weight = beta * f * (cos_x * cos_l / (dist2 * pdf_area));
                    if occ.is_none() {
                        l += weight * scene.material_of(lprim).emission;
                    }
                    push(&mut rec, RecRay::shadow(scene, idx, &sray, lprim, dist, occ, weight, sst, svis));
                }
            }
        }
        let Some(s) = material::sample(m, ng, ray.dir, rng) else { break };
        beta *= s.weight;
        count_emission = s.delta;
        kind = match s.lobe {
            Lobe::Diffuse => Kind::DIFFUSE,
            Lobe::Specular => Kind::SPECULAR,
            Lobe::Transmission => Kind::TRANSMISSION,
        };
        // Russian roulette after three bounces.
        if depth >= 3 {
            let q = beta.max_element().clamp(0.05, 0.95);
            if rng.next_f32() >= q {
                break;
            }
            beta /= q;
        }
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            break;
        }
        let side = if s.dir.dot(ng) > 0.0 { ng } else { -ng };
        ray = Ray::new(ctx.spawn(p, side, s.dir), s.dir);
        parent = Some(idx);
        depth += 1;
    }
    if let Some(out) = rec.filter(|r| r.keep) {
        for &(i, b, before) in &chain[..chain_len] {
            let gathered = l - before;
            let r = &mut out.rays[i as usize];
            r.radiance = Vec3A::select(b.cmpgt(Vec3A::ZERO), gathered / b, Vec3A::ZERO);
        }
    }
    l
}

/// Traces one Whitted sample through film position (fx, fy).
pub fn whitted_sample(
    ctx: &TraceCtx<'_>,
    fx: f32,
    fy: f32,
    w: u32,
    h: u32,
    rng: &mut Rng,
    mut rec: Option<&mut SampleRecord>,
) -> Vec3A {
    let cam = &ctx.scene.camera;
    let ray = Ray::new(cam.position, cam.direction(fx, fy, w, h));
    whitted(ctx, &ray, Kind::CAMERA, None, 0, Vec3A::ONE, rng, &mut rec)
}

#[allow(clippy::too_many_arguments)]
fn whitted(
    ctx: &TraceCtx<'_>,
    ray: &Ray,
    kind: Kind,
    parent: Option<u32>,
    depth: u32,
    weight: Vec3A,
    rng: &mut Rng,
    rec: &mut Option<&mut SampleRecord>,
) -> Vec3A {
    let scene = ctx.scene;
    let (hit, st, vis) = ctx.closest(ray, rec);
    let idx = push(rec, RecRay::traced(scene, parent, ray, hit, kind, weight, st, vis));
    let Some(hit) = hit else { return Vec3A::ZERO };
    let m = scene.material_of(hit.prim);
    let ng = scene.normals[hit.prim as usize];
    let n = if ng.dot(ray.dir) < 0.0 { ng } else { -ng };
    let p = ctx.hit_point(&hit);
    let mut l = m.emission;
    if depth < ctx.max_depth {
        match m.kind {
            MaterialKind::Diffuse | MaterialKind::Glossy => {
                // Each emitter as a point light at its centroid (at most 32, chosen by area).
                let k = scene.lights.len().min(32);
                for j in 0..k {
                    let li = if scene.lights.len() <= 32 { j } else { scene.pick_emitter(rng.next_f32()) };
                    let prim = scene.lights[li];
                    let [v0, v1, v2] = scene.tris[prim as usize];
                    let c = (v0 + v1 + v2) / 3.0;
                    let area = scene.emitter_area(li);
                    let scale = if scene.lights.len() <= 32 { 1.0 } else { scene.light_area / (area * k as f32) };
                    let origin = ctx.spawn(p, n, (c - p).normalize_or_zero());
                    let to = c - origin;
                    let d2 = to.length_squared();
                    let wi = to / d2.sqrt();
                    let cos_x = n.dot(wi);
                    if cos_x <= 0.0 {
                        continue;
                    }
                    let sray = Ray::new(origin, wi);
                    let (occ, sst, svis) = ctx.occluded(&sray, d2.sqrt() * (1.0 - 1e-4), prim, rec);
                    let le = scene.material_of(prim).emission;
                    let cos_l = scene.normals[prim as usize].dot(wi).abs();
                    // Bug::Nan: the same zero denominator at grazing light angles as the path tracer's pdf.
                    let denom = if ctx.bug == Some(Bug::Nan) && cos_l < 0.1 { 0.0 } else { d2 };
                    let g = m.diffuse / std::f32::consts::PI * (area * scale * cos_x * cos_l / denom);
                    if occ.is_none() {
                        l += g * le;
                    }
                    push(rec, RecRay::shadow(scene, idx, &sray, prim, d2.sqrt(), occ, weight * g, sst, svis));
                }
                if m.kind == MaterialKind::Glossy && m.specular.max_element() > 0.0 {
                    let d = reflect(ray.dir, n);
                    let r = Ray::new(ctx.spawn(p, n, d), d);
                    l += m.specular
                        * whitted(ctx, &r, Kind::SPECULAR, Some(idx), depth + 1, weight * m.specular, rng, rec);
                }
            }
            MaterialKind::Mirror => {
                let d = reflect(ray.dir, n);
                let r = Ray::new(ctx.spawn(p, n, d), d);
                l += m.specular * whitted(ctx, &r, Kind::SPECULAR, Some(idx), depth + 1, weight * m.specular, rng, rec);
            }
            MaterialKind::Dielectric => {
                let front = ng.dot(ray.dir) < 0.0;
                let (eta_i, eta_t) = if front { (1.0, m.ior) } else { (m.ior, 1.0) };
                let cos_i = n.dot(-ray.dir).clamp(0.0, 1.0);
                let (f, cos_t) = fresnel(cos_i, eta_i, eta_t);
                let d = reflect(ray.dir, n);
                let r = Ray::new(ctx.spawn(p, n, d), d);
                l += m.specular * f * whitted(ctx, &r, Kind::SPECULAR, Some(idx), depth + 1, weight * f, rng, rec);
                if f < 1.0 {
                    let eta = eta_i / eta_t;
                    let dir = (ray.dir * eta + n * (eta * cos_i - cos_t)).normalize();
                    let t = Ray::new(ctx.spawn(p, -n, dir), dir);
                    let wt = (1.0 - f) * eta * eta;
                    l += m.specular
                        * wt
                        * whitted(ctx, &t, Kind::TRANSMISSION, Some(idx), depth + 1, weight * wt, rng, rec);
                }
            }
        }
    }
    if let Some(out) = rec.as_deref_mut().filter(|r| r.keep) {
        out.rays[idx as usize].radiance = l;
    }
    l
}
