// Ray styles beyond opaque lines (`splat.rs`), rasterized in a compute pass: one invocation per
// segment (or box of twelve edges) walks the pixels its line covers and adds into a per-pixel
// accumulation buffer of five u32 words with atomics. Nothing is binned or blended, so millions of
// segments cost no rasterizer memory, the result does not depend on draw order, and no float
// blending is needed (wgpu's GL backend has none on many drivers). The idea is Schütz et al.'s
// compute rasterization of points (2021), for lines:
//
// - density: [rays, red sum, green sum, blue sum, unused] (colours 0..255);
// - alpha (weighted blended order-independent transparency, McGuire & Bavoil 2013, in fixed
//   point): [sum of w, red, green, blue sums of colour*w, sum of -ln(1 - a)] (the weight w in
//   1/255: the ray colour's own alpha times a depth weight; the log transmittance in 1/4096).
//
// The geometry is `lines.wgsl`'s (prepended): near-plane clipping (`clip_line`), lines
// `view.viewport.z` pixels wide, the colour gradient of mode 1. A pixel covered behind the
// occluder (the scene's depth) adds nothing: with no depth of its own per pixel, the layer is
// hidden behind surfaces here, not in the compositor.

@group(0) @binding(2) var<storage, read_write> acc: array<atomic<u32>>;
@group(0) @binding(3) var occ_depth: texture_2d<f32>;
@group(0) @binding(4) var<uniform> splat: Splat;

const WORDS: u32 = 5u;
// At most this many pixels along a line's major axis (a clipped line lies within the picture,
// which wgpu limits to 16384 on a side) and across it (a line is at most this wide).
const MAX_ALONG: i32 = 16384;
const MAX_ACROSS: i32 = 64;

fn lin_depth(d: f32, near: f32, far: f32) -> f32 {
    return far * near / max(far - d * (far - near), 1e-30);
}

// Adds one covered pixel `p` at depth `z` (0..1, the rasterizer's) and position `s` (0 at the
// segment's start, 1 at its end) in `color`.
fn splat_pixel(p: vec2<i32>, z: f32, s: f32, color: vec4<f32>) {
    if p.x < 0 || p.y < 0 || u32(p.x) >= splat.size.x || u32(p.y) >= splat.size.y || z < 0.0 || z > 1.0 {
        return;
    }
    let l = lin_depth(z, splat.ranges.x, splat.ranges.y);
    if splat.params.z > 0.5 {
        let od = textureLoad(occ_depth, p, 0).r;
        if od < 1.0 && l > lin_depth(od, splat.ranges.z, splat.ranges.w) * (1.0 + splat.params.y) {
            return;
        }
    }
    let i = (u32(p.y) * splat.size.x + u32(p.x)) * WORDS;
    var g = 1.0;
    if view.params.w > 0.5 {
        g = 0.25 + 0.75 * clamp(s, 0.0, 1.0);
    }
    let rgb = vec3<u32>(clamp(color.rgb * g, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0 + 0.5);
    if splat.params.x > 1.5 {
        // Colour sums stop at 2^24 rays (they would wrap past 2^32); the count goes on.
        let n = atomicAdd(&acc[i], 1u);
        // A colour map needs only the count.
        if n < 16777216u && splat.size.w == 0u {
            atomicAdd(&acc[i + 1u], rgb.r);
            atomicAdd(&acc[i + 2u], rgb.g);
            atomicAdd(&acc[i + 3u], rgb.b);
        }
        return;
    }
    let a = clamp(color.a * view.viewport.w, 0.0, 0.999);
    // Nearer pixels weigh more (McGuire & Bavoil's depth weight, bounded to 0.1..1).
    let zn = clamp((l - splat.ranges.x) / max(splat.ranges.y - splat.ranges.x, 1e-30), 0.0, 1.0);
    let w = max(0.1, pow(1.0 - zn, 3.0));
    // The colour weight leaves out the layer's opacity, the same for every ray (it cancels in
    // the average, and a small one would round every weight to zero).
    let q = u32(clamp(color.a, 0.0, 1.0) * w * 255.0 + 0.5);
    // Bounded sums (checked before adding; invocations in flight overshoot by far less than the
    // headroom to 2^32): past them the average colour and the opacity no longer change.
    if q > 0u && atomicLoad(&acc[i]) < 8388608u {
        atomicAdd(&acc[i], q);
        atomicAdd(&acc[i + 1u], rgb.r * q);
        atomicAdd(&acc[i + 2u], rgb.g * q);
        atomicAdd(&acc[i + 3u], rgb.b * q);
    }
    if atomicLoad(&acc[i + 4u]) < 1048576u {
        atomicAdd(&acc[i + 4u], u32(-log(1.0 - a) * 4096.0 + 0.5));
    }
}

// The pixels of the line from `pa` to `pb` (world space), `width` pixels wide: clipped to the
// near plane as `line_vertex` does, then walked one pixel column (or row) at a time along its
// major axis, covering the pixel centres within the line's width across it. The depth (z/w) is
// affine in screen space; `s` is interpolated perspective-correctly (boxes' edges, `edge`, have
// s = 1 throughout, as `vs_box` draws them).
fn splat_line(pa: vec3<f32>, pb: vec3<f32>, width: f32, color: vec4<f32>, edge: bool) {
    let clipped = clip_line(pa, pb);
    if !clipped.visible {
        return;
    }
    let ca = clipped.ca;
    let cb = clipped.cb;
    let sa = clipped.sa;
    let sb = clipped.sb;
    if ca.w <= 0.0 || cb.w <= 0.0 {
        return;
    }
    let size = vec2<f32>(view.viewport.xy);
    // Framebuffer coordinates: x right, y down, pixel centres at +0.5.
    let a = vec2<f32>((ca.x / ca.w * 0.5 + 0.5) * size.x, (0.5 - ca.y / ca.w * 0.5) * size.y);
    let b = vec2<f32>((cb.x / cb.w * 0.5 + 0.5) * size.x, (0.5 - cb.y / cb.w * 0.5) * size.y);
    let za = ca.z / ca.w;
    let zb = cb.z / cb.w;
    let wa = 1.0 / ca.w;
    let wb = 1.0 / cb.w;
    let d = b - a;
    let half = max(width, 1.0) * 0.5;
    // Along the major axis `m`, across it the other; a point (zero length) is a square.
    let xmajor = abs(d.x) >= abs(d.y);
    var am = a.x;
    var an = a.y;
    var dm = d.x;
    var dn = d.y;
    var limit_m = size.x;
    var limit_n = size.y;
    if !xmajor {
        am = a.y;
        an = a.x;
        dm = d.y;
        dn = d.x;
        limit_m = size.y;
        limit_n = size.x;
    }
    let len = length(d);
    // The line's half width across the major axis (a slanted line covers more of a column) and
    // its half-width extension past each end along it, as the quad of `line_vertex` has.
    var across = half;
    var ext = half;
    if len > 1e-4 {
        across = half * len / abs(dm);
        ext = half * abs(dm) / len;
    }
    var lo = min(am, am + dm) - ext;
    var hi = max(am, am + dm) + ext;
    // Only the part of the line whose pixels across it can lie in the picture.
    if abs(dn) > 1e-6 {
        let u0 = (-across - an) / dn;
        let u1 = (limit_n + across - an) / dn;
        let ulo = max(min(u0, u1), 0.0);
        let uhi = min(max(u0, u1), 1.0);
        if ulo > uhi {
            return;
        }
        lo = max(lo, min(am + dm * ulo, am + dm * uhi) - ext - 1.0);
        hi = min(hi, max(am + dm * ulo, am + dm * uhi) + ext + 1.0);
    } else if an < -across || an > limit_n + across {
        return;
    }
    // Pixel columns whose centres lie in [lo, hi), clipped to the picture.
    // (Clamped as floats first: a point near the camera plane lies far outside the picture.)
    let m0 = i32(clamp(ceil(lo - 0.5), 0.0, limit_m));
    let m1 = i32(clamp(ceil(hi - 0.5), 0.0, min(limit_m, f32(MAX_ALONG))));
    let rows = min(i32(ceil(2.0 * across)) + 1, MAX_ACROSS);
    for (var m = m0; m < m1; m++) {
        let x = f32(m) + 0.5;
        // Position along the line (0 at a, 1 at b), clamped for the ends' extensions.
        var u = 0.0;
        if abs(dm) > 1e-4 {
            u = clamp((x - am) / dm, 0.0, 1.0);
        }
        let c = an + dn * u;
        let z = mix(za, zb, u);
        var s = 1.0;
        if !edge {
            s = mix(sa * wa, sb * wb, u) / mix(wa, wb, u);
        }
        let n0 = i32(clamp(ceil(c - across - 0.5), -1.0, limit_n));
        for (var k = 0; k < rows; k++) {
            let n = n0 + k;
            let y = f32(n) + 0.5;
            if y >= c + across || f32(n) >= limit_n {
                break;
            }
            if n < 0 {
                continue;
            }
            var p = vec2<i32>(m, n);
            if !xmajor {
                p = vec2<i32>(n, m);
            }
            splat_pixel(p, z, s, color);
        }
    }
}

// The index of the invocation's item: workgroups of 64, dispatched in two dimensions where one
// would exceed the per-dimension limit (`dispatch_2d`), every view.params.y-th item in a preview.
fn item_index(wg: vec3<u32>, nwg: vec3<u32>, local: u32) -> u32 {
    return ((wg.y * nwg.x + wg.x) * 64u + local) * max(u32(view.params.y), 1u);
}

// Segments: view.params.y is the stride of a preview (every stride-th segment is drawn).
@compute @workgroup_size(64)
fn cs_seg(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let k = item_index(wg, nwg, li);
    if k >= arrayLength(&segs) {
        return;
    }
    let s = segs[k];
    var width = view.viewport.z;
    if (s.flags & 1u) != 0u {
        width = width * 2.5;
    }
    splat_line(s.a, s.b, width, unpack4x8unorm(s.color), false);
}

// Boxes: `a` is the minimum corner, `b` the maximum; their twelve edges.
@compute @workgroup_size(64)
fn cs_box(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let k = item_index(wg, nwg, li);
    if k >= arrayLength(&segs) {
        return;
    }
    let bx = segs[k];
    var width = view.viewport.z;
    if (bx.flags & 1u) != 0u {
        width = width * 2.0;
    }
    var e_from = array<u32, 12>(0u, 1u, 3u, 2u, 4u, 5u, 7u, 6u, 0u, 1u, 2u, 3u);
    var e_to = array<u32, 12>(1u, 3u, 2u, 0u, 5u, 7u, 6u, 4u, 4u, 5u, 6u, 7u);
    for (var e = 0u; e < 12u; e++) {
        let i = e_from[e];
        let j = e_to[e];
        let pi = vec3<f32>(select(bx.a.x, bx.b.x, (i & 1u) != 0u), select(bx.a.y, bx.b.y, (i & 2u) != 0u), select(bx.a.z, bx.b.z, (i & 4u) != 0u));
        let pj = vec3<f32>(select(bx.a.x, bx.b.x, (j & 1u) != 0u), select(bx.a.y, bx.b.y, (j & 2u) != 0u), select(bx.a.z, bx.b.z, (j & 4u) != 0u));
        splat_line(pi, pj, width, unpack4x8unorm(bx.color), true);
    }
}
