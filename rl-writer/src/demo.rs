//! A small analytic ray tracer over a built-in box scene, instrumented the way the paper's
//! Figure 4 shows (add a ray, descend into its children, ascend). It gives `rtvtk demo`, the
//! benchmarks and the tests real-looking ray trees until the renderers crate's tracers are used.

use store::{Kind, RayFields};

use crate::recorder::{Payload, TreeBuilder};

/// Where a tracer sends its rays: a [`TreeBuilder`] or a plain list.
pub trait Emit {
    fn add(&mut self, ray: &RayFields);
    fn descend(&mut self);
    fn ascend(&mut self);
}

impl Emit for TreeBuilder {
    fn add(&mut self, ray: &RayFields) {
        self.add_ray(ray, Payload::NONE);
    }
    fn descend(&mut self) {
        TreeBuilder::descend(self);
    }
    fn ascend(&mut self) {
        TreeBuilder::ascend(self);
    }
}

/// Rays of one tree with explicit parents, in recording order.
#[derive(Clone, Debug, Default)]
pub struct RayList {
    pub rays: Vec<(Option<u32>, RayFields)>,
    stack: Vec<u32>,
}

impl Emit for RayList {
    fn add(&mut self, ray: &RayFields) {
        self.rays.push((self.stack.last().copied(), *ray));
    }
    fn descend(&mut self) {
        self.stack.push(self.rays.len() as u32 - 1);
    }
    fn ascend(&mut self) {
        self.stack.pop();
    }
}

type V = [f32; 3];
fn add(a: V, b: V) -> V {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: V, b: V) -> V {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn mul(a: V, s: f32) -> V {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn dot(a: V, b: V) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: V) -> V {
    mul(a, 1.0 / dot(a, a).sqrt())
}

/// A small deterministic random stream per (pixel, sample).
struct Rng(u64);
impl Rng {
    fn new(x: u32, y: u32, s: u32) -> Self {
        let mut r = Rng((u64::from(x) << 40) ^ (u64::from(y) << 20) ^ u64::from(s) ^ 0x9E37_79B9_7F4A_7C15);
        r.next();
        r
    }
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Mat {
    Diffuse,
    Mirror,
    Light,
}

struct Hit {
    t: f32,
    n: V,
    prim: u32,
    mat: Mat,
}

const SPHERES: [(V, f32, Mat, u32); 2] =
    [([-0.4, -0.6, -0.3], 0.4, Mat::Mirror, 100), ([0.45, -0.65, 0.3], 0.35, Mat::Diffuse, 101)];
const LIGHT_Y: f32 = 0.999;
const LIGHT_HALF: f32 = 0.25;

fn intersect(o: V, d: V) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    let mut take = |h: Hit| {
        if h.t > 1e-4 && best.as_ref().is_none_or(|b| h.t < b.t) {
            best = Some(h);
        }
    };
    // Walls of the box [-1, 1]^3, open towards +z: (axis, position, normal sign, prim).
    for (axis, pos, prim) in [(0, -1.0, 0), (0, 1.0, 1), (1, -1.0, 2), (1, 1.0, 3), (2, -1.0, 4)] {
        if d[axis] != 0.0 {
            let t = (pos - o[axis]) / d[axis];
            let p = add(o, mul(d, t));
            if (0..3).all(|k| k == axis || p[k].abs() <= 1.0) {
                let mut n = [0.0; 3];
                n[axis] = -pos;
                take(Hit { t, n, prim, mat: Mat::Diffuse });
            }
        }
    }
    if d[1] != 0.0 {
        let t = (LIGHT_Y - o[1]) / d[1];
        let p = add(o, mul(d, t));
        if p[0].abs() <= LIGHT_HALF && p[2].abs() <= LIGHT_HALF {
            take(Hit { t, n: [0.0, -1.0, 0.0], prim: 200, mat: Mat::Light });
        }
    }
    for (c, r, mat, prim) in SPHERES {
        let oc = sub(o, c);
        let b = dot(oc, d);
        let disc = b * b - (dot(oc, oc) - r * r);
        if disc >= 0.0 {
            let s = disc.sqrt();
            for t in [-b - s, -b + s] {
                if t > 1e-4 {
                    take(Hit { t, n: norm(sub(add(o, mul(d, t)), c)), prim, mat });
                    break;
                }
            }
        }
    }
    best
}

fn fields(o: V, d: V, hit: &Option<Hit>, kind: Kind) -> RayFields {
    RayFields { origin: o, direction: d, t: hit.as_ref().map(|h| h.t), kind, prim: hit.as_ref().map(|h| h.prim) }
}

fn trace(e: &mut impl Emit, rng: &mut Rng, o: V, d: V, kind: Kind, depth: u32) {
    let hit = intersect(o, d);
    e.add(&fields(o, d, &hit, kind));
    let Some(h) = hit else { return };
    if h.mat == Mat::Light || depth >= 4 {
        return;
    }
    let p = add(o, mul(d, h.t));
    let n = if dot(h.n, d) > 0.0 { mul(h.n, -1.0) } else { h.n };
    let p = add(p, mul(n, 1e-4));
    e.descend();
    match h.mat {
        Mat::Diffuse => {
            // Next-event estimation: a shadow ray to a point on the light.
            let l = [(rng.next() - 0.5) * 2.0 * LIGHT_HALF, LIGHT_Y, (rng.next() - 0.5) * 2.0 * LIGHT_HALF];
            let to_l = sub(l, p);
            let sd = norm(to_l);
            if dot(sd, n) > 0.0 {
                let sh = intersect(p, sd);
                e.add(&fields(p, sd, &sh, Kind::SHADOW));
            }
            // A cosine-weighted bounce, with Russian roulette after the first one.
            if depth < 1 || rng.next() < 0.6 {
                let (u1, u2) = (rng.next(), rng.next());
                let r = u1.sqrt();
                let phi = 2.0 * std::f32::consts::PI * u2;
                let a = if n[0].abs() > 0.9 { [0.0, 1.0, 0.0] } else { [1.0, 0.0, 0.0] };
                let t1 = norm([n[1] * a[2] - n[2] * a[1], n[2] * a[0] - n[0] * a[2], n[0] * a[1] - n[1] * a[0]]);
                let t2 = [n[1] * t1[2] - n[2] * t1[1], n[2] * t1[0] - n[0] * t1[2], n[0] * t1[1] - n[1] * t1[0]];
                let z = (1.0 - u1).max(0.0).sqrt();
                let nd = norm(add(add(mul(t1, r * phi.cos()), mul(t2, r * phi.sin())), mul(n, z)));
                trace(e, rng, p, nd, Kind::DIFFUSE, depth + 1);
            }
        }
        Mat::Mirror => {
            let rd = norm(sub(d, mul(n, 2.0 * dot(d, n))));
            trace(e, rng, p, rd, Kind::SPECULAR, depth + 1);
        }
        Mat::Light => {}
    }
    e.ascend();
}

/// Traces one sample of pixel `(x, y)` of a `width` × `height` image into `e`.
pub fn trace_pixel(e: &mut impl Emit, x: u32, y: u32, sample: u32, width: u32, height: u32) {
    let mut rng = Rng::new(x, y, sample);
    let aspect = width as f32 / height.max(1) as f32;
    let u = ((x as f32 + rng.next()) / width.max(1) as f32 * 2.0 - 1.0) * aspect;
    let v = 1.0 - (y as f32 + rng.next()) / height.max(1) as f32 * 2.0;
    let o = [0.0, 0.0, 3.4];
    let d = norm([u * 0.4, v * 0.4, -1.0]);
    trace(e, &mut rng, o, d, Kind::CAMERA, 0);
}

/// The rays of one pixel sample as a list with explicit parents.
pub fn pixel_rays(x: u32, y: u32, sample: u32, width: u32, height: u32) -> RayList {
    let mut l = RayList::default();
    trace_pixel(&mut l, x, y, sample, width, height);
    l
}
