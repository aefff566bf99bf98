// Closest-hit ray tracing over the renderers' binary BVH, one compute invocation per ray:
// a stack traversal (near child first) with the slab test of `renderers::bvh` and the
// watertight ray/triangle test of `renderers::geometry` (Woop et al. 2013), both in f32.

struct Node {
    min: vec3<f32>,
    // inner: first child (the second follows); leaf: first triangle slot
    first: u32,
    max: vec3<f32>,
    // 0 for inner nodes
    count: u32,
};

struct Tri {
    // xyz: vertex 0; w: the scene triangle's index (bits)
    v0: vec4<f32>,
    v1: vec4<f32>,
    v2: vec4<f32>,
};

struct Camera {
    position: vec4<f32>,
    forward: vec4<f32>,
    right: vec4<f32>,
    up: vec4<f32>,
    // tan(fov_y / 2), aspect, width, height
    params: vec4<f32>,
};

@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read> nodes: array<Node>;
@group(0) @binding(2) var<storage, read> tris: array<Tri>;
// per pixel: the triangle hit (0xffffffff: a miss) and the hit distance's bits
@group(0) @binding(3) var<storage, read_write> hits: array<vec2<u32>>;

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
    inv: vec3<f32>,
    // the watertight test's shear: permuted axes and constants
    k: vec3<u32>,
    s: vec3<f32>,
};

fn component(v: vec3<f32>, i: u32) -> f32 {
    if i == 0u {
        return v.x;
    }
    if i == 1u {
        return v.y;
    }
    return v.z;
}

fn make_ray(o: vec3<f32>, d: vec3<f32>) -> Ray {
    var r: Ray;
    r.o = o;
    r.d = d;
    // 1/d with components below 1e-30 in magnitude clamped first (never 0 * inf in the slab test)
    let tiny = vec3<f32>(1e-30);
    let clamped = select(d, select(-tiny, tiny, d >= vec3<f32>(0.0)), abs(d) < tiny);
    r.inv = vec3<f32>(1.0) / clamped;
    let a = abs(d);
    var kz = 2u;
    if a.x > a.y {
        if a.x > a.z {
            kz = 0u;
        }
    } else if a.y > a.z {
        kz = 1u;
    }
    var kx = (kz + 1u) % 3u;
    var ky = (kx + 1u) % 3u;
    if component(d, kz) < 0.0 {
        let t = kx;
        kx = ky;
        ky = t;
    }
    let sz = 1.0 / component(d, kz);
    r.k = vec3<u32>(kx, ky, kz);
    r.s = vec3<f32>(component(d, kx) * sz, component(d, ky) * sz, sz);
    return r;
}

// Entry distance of the ray into the box within (0, tmax), or -1.
fn slab(r: Ray, lo: vec3<f32>, hi: vec3<f32>, tmax: f32) -> f32 {
    let t0 = (lo - r.o) * r.inv;
    let t1 = (hi - r.o) * r.inv;
    let tn = min(t0, t1);
    let tf = max(t0, t1);
    let enter = max(max(tn.x, tn.y), max(tn.z, 0.0));
    // the exit distance widened by 2γ(3), γ(3) = 3ε/2 / (1 - 3ε/2), keeps the test conservative
    // (Pharr et al.; the same bound as renderers::bvh)
    let exit = min(min(tf.x, tf.y), min(tf.z, tmax)) * (1.0 + 2.0 * 1.7881396e-7);
    if enter <= exit {
        return enter;
    }
    return -1.0;
}

// The watertight test: (hit distance in (0, tmax), or -1; barycentrics of vertices 1 and 2).
fn triangle(r: Ray, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>, tmax: f32) -> vec3<f32> {
    let a = v0 - r.o;
    let b = v1 - r.o;
    let c = v2 - r.o;
    let ax = component(a, r.k.x) - r.s.x * component(a, r.k.z);
    let ay = component(a, r.k.y) - r.s.y * component(a, r.k.z);
    let bx = component(b, r.k.x) - r.s.x * component(b, r.k.z);
    let by = component(b, r.k.y) - r.s.y * component(b, r.k.z);
    let cx = component(c, r.k.x) - r.s.x * component(c, r.k.z);
    let cy = component(c, r.k.y) - r.s.y * component(c, r.k.z);
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    let det = u + v + w;
    if det == 0.0 {
        return vec3<f32>(-1.0, 0.0, 0.0);
    }
    let az = r.s.z * component(a, r.k.z);
    let bz = r.s.z * component(b, r.k.z);
    let cz = r.s.z * component(c, r.k.z);
    let inv = 1.0 / det;
    let t = (u * az + v * bz + w * cz) * inv;
    if t > 0.0 && t < tmax {
        return vec3<f32>(t, v * inv, w * inv);
    }
    return vec3<f32>(-1.0, 0.0, 0.0);
}

struct Hit {
    prim: u32,
    t: f32,
    // the leaf slot hit (its vertices: tris[slot]) and the barycentrics of vertices 1 and 2
    slot: u32,
    b: vec2<f32>,
};

const NONE: u32 = 0xffffffffu;

// Visit the nearer of two hit children first (false: always the first child; `rtvtk bench gpu`
// measures both).
override NEARER_FIRST: bool = true;

// What the last traversal cost (renderers::TraversalStats over this binary BVH): nodes entered,
// ray/box tests, ray/triangle tests.
var<private> st_nodes: u32;
var<private> st_boxes: u32;
var<private> st_tris: u32;

// The one traversal: the closest hit in (0, tmax) of any triangle but `skip` (NONE: none
// skipped), or with `any_hit` the first hit found.
fn traverse(r: Ray, tmax: f32, skip: u32, any_hit: bool) -> Hit {
    var best = Hit(NONE, tmax, 0u, vec2<f32>(0.0));
    let root = nodes[0];
    st_nodes = 0u;
    st_boxes = 1u;
    st_tris = 0u;
    if root.count == NONE || slab(r, root.min, root.max, best.t) < 0.0 {
        return best;
    }
    var stack: array<u32, 64>;
    var sp = 0u;
    var node = 0u;
    loop {
        let n = nodes[node];
        st_nodes += 1u;
        if n.count > 0u {
            st_tris += n.count;
            for (var i = n.first; i < n.first + n.count; i++) {
                let tri = tris[i];
                let prim = bitcast<u32>(tri.v0.w);
                let t = triangle(r, tri.v0.xyz, tri.v1.xyz, tri.v2.xyz, best.t);
                if t.x > 0.0 && prim != skip {
                    best = Hit(prim, t.x, i, t.yz);
                    if any_hit {
                        return best;
                    }
                }
            }
        } else {
            let a = nodes[n.first];
            let b = nodes[n.first + 1u];
            st_boxes += 2u;
            let ta = slab(r, a.min, a.max, best.t);
            let tb = slab(r, b.min, b.max, best.t);
            if ta >= 0.0 && tb >= 0.0 {
                // the nearer child next, the other on the stack
                if ta <= tb || !NEARER_FIRST {
                    node = n.first;
                    stack[sp] = n.first + 1u;
                } else {
                    node = n.first + 1u;
                    stack[sp] = n.first;
                }
                sp = min(sp + 1u, 63u);
                continue;
            }
            if ta >= 0.0 {
                node = n.first;
                continue;
            }
            if tb >= 0.0 {
                node = n.first + 1u;
                continue;
            }
        }
        if sp == 0u {
            break;
        }
        sp -= 1u;
        node = stack[sp];
    }
    return best;
}

fn closest(r: Ray, tmax: f32) -> Hit {
    return traverse(r, tmax, NONE, false);
}

@compute @workgroup_size(8, 8)
fn primary(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(cam.params.z);
    let h = u32(cam.params.w);
    if id.x >= w || id.y >= h {
        return;
    }
    // renderers::Camera::direction at the pixel's centre
    let px = f32(id.x) + 0.5;
    let py = f32(id.y) + 0.5;
    let sx = (2.0 * px / f32(w) - 1.0) * cam.params.x * cam.params.y;
    let sy = (1.0 - 2.0 * py / f32(h)) * cam.params.x;
    let d = normalize(cam.forward.xyz + cam.right.xyz * sx + cam.up.xyz * sy);
    let hit = closest(make_ray(cam.position.xyz, d), 3.4028235e38);
    hits[id.y * w + id.x] = vec2<u32>(hit.prim, bitcast<u32>(hit.t));
}

// ---------------------------------------------------------------------------------------------
// The progressive path tracer: renderers::tracer::path_sample on the GPU, one sample per pixel
// per dispatch, added to an accumulation buffer. Same camera, materials (diffuse, glossy,
// mirror, dielectric, emitters), next-event estimation on diffuse and glossy surfaces, Russian
// roulette after three bounces, the same ray offsets; its own random numbers (a PCG hash per
// pixel, sample and seed), so it agrees with the CPU in distribution, not bit for bit.

struct Material {
    // 0 diffuse, 1 glossy, 2 mirror, 3 dielectric
    kind: u32,
    exponent: f32,
    ior: f32,
    pad: f32,
    diffuse: vec4<f32>,
    specular: vec4<f32>,
    emission: vec4<f32>,
};

struct Light {
    v0: vec4<f32>,
    v1: vec4<f32>,
    v2: vec4<f32>,
    // xyz: unit normal; w: the scene triangle's index (bits)
    normal: vec4<f32>,
};

struct Frame {
    // sample index, seed, max depth, light count
    counts: vec4<u32>,
    // total emitter area, 0, 0, 0
    area: vec4<f32>,
    // the pixels this dispatch traces: x0, y0, width, height
    window: vec4<u32>,
    // recording (0 or 1), ray slots per path, the sample's index in the batch, injected bug (0 or 1)
    rec: vec4<u32>,
};

@group(0) @binding(4) var<uniform> frame: Frame;
// per scene triangle: unit geometric normal (xyz), material index (w, bits)
@group(0) @binding(5) var<storage, read> normals: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read> materials: array<Material>;
@group(0) @binding(7) var<storage, read> lights: array<Light>;
// cumulative emitter areas, as renderers::Scene::light_cdf
@group(0) @binding(8) var<storage, read> light_cdf: array<f32>;
@group(0) @binding(9) var<storage, read_write> accum: array<vec4<f32>>;

// One recorded ray (renderers::tracer::RecRay): 80 bytes.
struct RayRec {
    o: vec3<f32>,
    t: f32,
    d: vec3<f32>,
    // the triangle hit, NONE for a miss
    prim: u32,
    beta: vec3<f32>,
    // the parent's index within the path, NONE for the camera ray
    parent: u32,
    // the radiance carried back to the origin (while tracing: the path's radiance before it)
    rad: vec3<f32>,
    kind: u32,
    nodes: u32,
    boxes: u32,
    tris: u32,
    material: u32,
};

// Recording: every path writes its rays to its own slots of `scratch`, then copies them, packed,
// to `packed` at an offset taken from `totals[0]`; `spans` gets each path's (offset, count).
@group(0) @binding(10) var<storage, read_write> scratch: array<RayRec>;
@group(0) @binding(11) var<storage, read_write> packed: array<RayRec>;
@group(0) @binding(12) var<storage, read_write> spans: array<vec2<u32>>;
// [0]: rays packed so far; [1 + kind]: rays traced per kind (always counted)
@group(0) @binding(13) var<storage, read_write> totals: array<atomic<u32>, 8>;

const CAMERA: u32 = 0u;
const SHADOW: u32 = 1u;
const DIFFUSE: u32 = 2u;
const SPECULAR: u32 = 3u;
const TRANSMISSION: u32 = 4u;

var<private> rec_base: u32;
var<private> rec_n: u32;
var<private> kind_n: array<u32, 5>;

// Counts a ray of `kind` and, when recording, writes it; its index within the path (NONE when
// not recorded).
fn record(o: vec3<f32>, d: vec3<f32>, t: f32, prim: u32, beta: vec3<f32>, parent: u32, rad: vec3<f32>, kind: u32) -> u32 {
    kind_n[kind] += 1u;
    if frame.rec.x == 0u || rec_n >= frame.rec.y {
        return NONE;
    }
    var m = NONE;
    if prim != NONE {
        m = bitcast<u32>(normals[prim].w);
    }
    let i = rec_n;
    scratch[rec_base + i] = RayRec(o, t, d, prim, beta, parent, rad, kind, st_nodes, st_boxes, st_tris, m);
    rec_n += 1u;
    return i;
}

const PI: f32 = 3.14159265358979;

var<private> rng_key: u32;
var<private> rng_count: u32;

// The PCG hash (Jarzynski and Olano 2020).
fn pcg(v: u32) -> u32 {
    let state = v * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

// Uniform in [0, 1): every draw hashes (key, draw index) on its own, so no two draws of a path,
// and no two samples of a pixel, share a stream.
fn rand() -> f32 {
    rng_count += 1u;
    return f32(pcg(rng_key ^ pcg(rng_count)) >> 8u) * (1.0 / 16777216.0);
}

fn basis_t(n: vec3<f32>) -> vec3<f32> {
    let sgn = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (sgn + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(1.0 + sgn * n.x * n.x * a, sgn * b, -sgn * n.x);
}

fn basis_b(n: vec3<f32>) -> vec3<f32> {
    let sgn = select(-1.0, 1.0, n.z >= 0.0);
    let a = -1.0 / (sgn + n.z);
    let b = n.x * n.y * a;
    return vec3<f32>(b, sgn + n.y * n.y * a, -n.y);
}

fn cosine_hemisphere(n: vec3<f32>, u1: f32, u2: f32) -> vec3<f32> {
    let r = sqrt(u1);
    let phi = 2.0 * PI * u2;
    let z = sqrt(max(1.0 - u1, 0.0));
    return normalize(basis_t(n) * (r * cos(phi)) + basis_b(n) * (r * sin(phi)) + n * z);
}

fn phong_lobe(axis: vec3<f32>, e: f32, u1: f32, u2: f32) -> vec3<f32> {
    let cos_t = pow(u1, 1.0 / (e + 1.0));
    let sin_t = sqrt(max(1.0 - cos_t * cos_t, 0.0));
    let phi = 2.0 * PI * u2;
    return normalize(basis_t(axis) * (sin_t * cos(phi)) + basis_b(axis) * (sin_t * sin(phi)) + axis * cos_t);
}

fn reflect_dir(d: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    return d - n * (2.0 * dot(d, n));
}

fn luminance(c: vec3<f32>) -> f32 {
    return 0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z;
}

fn eval_bsdf(m: Material, n: vec3<f32>, wo: vec3<f32>, wi: vec3<f32>) -> vec3<f32> {
    if dot(n, wi) <= 0.0 {
        return vec3<f32>(0.0);
    }
    if m.kind == 0u {
        return m.diffuse.xyz / PI;
    }
    if m.kind == 1u {
        let c = max(dot(reflect_dir(-wo, n), wi), 0.0);
        return m.diffuse.xyz / PI + m.specular.xyz * ((m.exponent + 2.0) / (2.0 * PI) * pow(c, m.exponent));
    }
    return vec3<f32>(0.0);
}

// renderers::geometry::offset_point: a few ULPs along the normal, a fixed step near the origin.
fn offset_point(p: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    var out = p;
    for (var i = 0u; i < 3u; i++) {
        let step = i32(16.0 * n[i]);
        let bits = bitcast<i32>(p[i]);
        var moved = bitcast<f32>(bits + step);
        if p[i] < 0.0 {
            moved = bitcast<f32>(bits - step);
        }
        out[i] = select(moved, p[i] + n[i] / 65536.0, abs(p[i]) < 1.0 / 32.0);
    }
    return out;
}

// The hit point from the barycentrics (more accurate than o + t d far from the origin).
fn hit_point(h: Hit) -> vec3<f32> {
    let tri = tris[h.slot];
    return tri.v0.xyz * (1.0 - h.b.x - h.b.y) + tri.v1.xyz * h.b.x + tri.v2.xyz * h.b.y;
}

fn pick_emitter(u: f32) -> u32 {
    let count = frame.counts.w;
    let goal = u * frame.area.x;
    // the first cdf entry above the target (partition point of c <= target)
    var lo = 0u;
    var hi = count;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if light_cdf[mid] <= goal {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return min(lo, count - 1u);
}

fn path_sample(px: f32, py: f32) -> vec3<f32> {
    let w = u32(cam.params.z);
    let h = u32(cam.params.w);
    let sx = (2.0 * px / f32(w) - 1.0) * cam.params.x * cam.params.y;
    let sy = (1.0 - 2.0 * py / f32(h)) * cam.params.x;
    var ray = make_ray(cam.position.xyz, normalize(cam.forward.xyz + cam.right.xyz * sx + cam.up.xyz * sy));
    var beta = vec3<f32>(1.0);
    var l = vec3<f32>(0.0);
    var count_emission = true;
    var depth = 0u;
    var kind = CAMERA;
    var parent = NONE;
    loop {
        let hit = closest(ray, 3.4028235e38);
        let idx = record(ray.o, ray.d, hit.t, hit.prim, beta, parent, l, kind);
        if hit.prim == NONE {
            break;
        }
        let nm = normals[hit.prim];
        let m = materials[bitcast<u32>(nm.w)];
        let ng = nm.xyz;
        if count_emission && max(max(m.emission.x, m.emission.y), m.emission.z) > 0.0 {
            l += beta * m.emission.xyz;
        }
        if depth >= frame.counts.z {
            break;
        }
        let p = hit_point(hit);
        let front = dot(ng, ray.d) < 0.0;
        let n = select(-ng, ng, front);
        if (m.kind == 0u || m.kind == 1u) && frame.counts.w > 0u && frame.area.x > 0.0 {
            // next-event estimation: one shadow ray to a point on an emitter
            let li = lights[pick_emitter(rand())];
            let s1 = sqrt(rand());
            let b1 = 1.0 - s1;
            let b2 = rand() * s1;
            let q = li.v0.xyz * (1.0 - b1 - b2) + li.v1.xyz * b1 + li.v2.xyz * b2;
            let origin = offset_point(p, n);
            let to = q - origin;
            let dist2 = dot(to, to);
            let dist = sqrt(dist2);
            let wi = to / dist;
            let cos_x = dot(n, wi);
            let cos_l = abs(dot(li.normal.xyz, wi));
            if cos_x > 0.0 && dist > 0.0 {
                let lprim = bitcast<u32>(li.normal.w);
                var sdir = wi;
                // the injected bug of renderers::Bug::ShadowDir (Figure 1)
                if frame.rec.w != 0u && depth >= 1u && m.kind == 0u && n.y > 0.9 {
                    sdir = vec3<f32>(-wi.x, wi.y, -wi.z);
                }
                let blocker = traverse(make_ray(origin, sdir), dist * (1.0 - 1e-4), lprim, true);
                let f = eval_bsdf(m, n, -ray.d, wi);
                let weight = beta * f * (cos_x * cos_l * frame.area.x / dist2);
                let le = materials[bitcast<u32>(normals[lprim].w)].emission.xyz;
                let lit = blocker.prim == NONE;
                if lit {
                    l += weight * le;
                }
                _ = record(origin, sdir, select(blocker.t, dist, lit), select(blocker.prim, lprim, lit), weight, idx,
                    select(vec3<f32>(0.0), le, lit), SHADOW);
            }
        }
        // sample the material (renderers::material::sample)
        let d = ray.d;
        let wo = -d;
        var wi: vec3<f32>;
        var weight: vec3<f32>;
        var delta = false;
        if m.kind == 0u {
            wi = cosine_hemisphere(n, rand(), rand());
            if dot(n, wi) <= 0.0 {
                break;
            }
            weight = m.diffuse.xyz;
            kind = DIFFUSE;
        } else if m.kind == 1u {
            let ld = luminance(m.diffuse.xyz);
            let ls = luminance(m.specular.xyz);
            let pd = select(1.0, ld / (ld + ls), ld + ls > 0.0);
            let r = reflect_dir(d, n);
            if rand() < pd {
                wi = cosine_hemisphere(n, rand(), rand());
                kind = DIFFUSE;
            } else {
                wi = phong_lobe(r, m.exponent, rand(), rand());
                kind = SPECULAR;
            }
            let cs = dot(n, wi);
            if cs <= 0.0 {
                break;
            }
            let c = max(dot(r, wi), 0.0);
            let pdf = pd * cs / PI + (1.0 - pd) * (m.exponent + 1.0) / (2.0 * PI) * pow(c, m.exponent);
            if pdf <= 0.0 {
                break;
            }
            weight = eval_bsdf(m, n, wo, wi) * cs / pdf;
        } else if m.kind == 2u {
            wi = reflect_dir(d, n);
            weight = m.specular.xyz;
            delta = true;
            kind = SPECULAR;
        } else {
            let entering = dot(ng, wo) >= 0.0;
            let nn = select(-ng, ng, entering);
            var eta_i = m.ior;
            var eta_t = 1.0;
            if entering {
                eta_i = 1.0;
                eta_t = m.ior;
            }
            let cos_i = clamp(dot(nn, wo), 0.0, 1.0);
            let eta = eta_i / eta_t;
            let sin2_t = eta * eta * max(1.0 - cos_i * cos_i, 0.0);
            var fr = 1.0;
            var cos_t = 0.0;
            if sin2_t < 1.0 {
                cos_t = sqrt(1.0 - sin2_t);
                let rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t);
                let rp = (eta_t * cos_i - eta_i * cos_t) / (eta_t * cos_i + eta_i * cos_t);
                fr = 0.5 * (rs * rs + rp * rp);
            }
            if rand() < fr {
                wi = reflect_dir(d, nn);
                weight = m.specular.xyz;
                kind = SPECULAR;
            } else {
                wi = normalize(d * eta + nn * (eta * cos_i - cos_t));
                weight = m.specular.xyz * (eta * eta);
                kind = TRANSMISSION;
            }
            delta = true;
        }
        beta *= weight;
        count_emission = delta;
        if depth >= 3u {
            let q = clamp(max(max(beta.x, beta.y), beta.z), 0.05, 0.95);
            if rand() >= q {
                break;
            }
            beta /= q;
        }
        let bmax = max(max(beta.x, beta.y), beta.z);
        if !(bmax > 0.0) || bmax > 3.4e38 {
            break;
        }
        let side = select(-ng, ng, dot(wi, ng) > 0.0);
        ray = make_ray(offset_point(p, side), wi);
        parent = idx;
        depth += 1u;
    }
    // what each traced ray carries back: the radiance gathered after it, over its throughput
    for (var i = 0u; i < rec_n; i++) {
        let r = scratch[rec_base + i];
        if r.kind != SHADOW {
            scratch[rec_base + i].rad = select(vec3<f32>(0.0), (l - r.rad) / r.beta, r.beta > vec3<f32>(0.0));
        }
    }
    return l;
}

@compute @workgroup_size(8, 8)
fn path(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = u32(cam.params.z);
    if id.x >= frame.window.z || id.y >= frame.window.w {
        return;
    }
    let x = frame.window.x + id.x;
    let y = frame.window.y + id.y;
    let pixel = y * w + x;
    // this path's place among the batch's paths (the window's pixels, sample after sample)
    let path_index = frame.rec.z * frame.window.z * frame.window.w + id.y * frame.window.z + id.x;
    rec_base = path_index * frame.rec.y;
    rec_n = 0u;
    rng_key = pcg(pcg(pcg(frame.counts.y) + pixel) + frame.counts.x);
    rng_count = 0u;
    let fx = f32(x) + rand();
    let fy = f32(y) + rand();
    let c = path_sample(fx, fy);
    // a non-finite sample (none expected) is dropped, as a NaN would poison the pixel
    if all(c == c) && max(max(c.x, c.y), c.z) < 3.4e38 {
        accum[pixel] += vec4<f32>(c, 1.0);
    } else {
        accum[pixel] += vec4<f32>(0.0, 0.0, 0.0, 1.0);
    }
    for (var k = 0u; k < 5u; k++) {
        if kind_n[k] > 0u {
            atomicAdd(&totals[1u + k], kind_n[k]);
        }
    }
    if frame.rec.x != 0u {
        let at = atomicAdd(&totals[0], rec_n);
        for (var i = 0u; i < rec_n; i++) {
            packed[at + i] = scratch[rec_base + i];
        }
        spans[path_index] = vec2<u32>(at, rec_n);
    }
}
