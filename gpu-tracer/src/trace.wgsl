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

// Hit distance of the watertight test in (0, tmax), or -1.
fn triangle(r: Ray, v0: vec3<f32>, v1: vec3<f32>, v2: vec3<f32>, tmax: f32) -> f32 {
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
        return -1.0;
    }
    let det = u + v + w;
    if det == 0.0 {
        return -1.0;
    }
    let az = r.s.z * component(a, r.k.z);
    let bz = r.s.z * component(b, r.k.z);
    let cz = r.s.z * component(c, r.k.z);
    let t = (u * az + v * bz + w * cz) / det;
    if t > 0.0 && t < tmax {
        return t;
    }
    return -1.0;
}

struct Hit {
    prim: u32,
    t: f32,
};

fn closest(r: Ray, tmax_in: f32) -> Hit {
    var best = Hit(0xffffffffu, tmax_in);
    let root = nodes[0];
    if root.count == 0xffffffffu || slab(r, root.min, root.max, best.t) < 0.0 {
        return best;
    }
    var stack: array<u32, 64>;
    var sp = 0u;
    var node = 0u;
    loop {
        let n = nodes[node];
        if n.count > 0u {
            for (var i = n.first; i < n.first + n.count; i++) {
                let tri = tris[i];
                let t = triangle(r, tri.v0.xyz, tri.v1.xyz, tri.v2.xyz, best.t);
                if t > 0.0 {
                    best = Hit(bitcast<u32>(tri.v0.w), t);
                }
            }
        } else {
            let a = nodes[n.first];
            let b = nodes[n.first + 1u];
            let ta = slab(r, a.min, a.max, best.t);
            let tb = slab(r, b.min, b.max, best.t);
            if ta >= 0.0 && tb >= 0.0 {
                // the nearer child next, the other on the stack
                if ta <= tb {
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
