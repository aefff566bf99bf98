// Ray styles beyond opaque lines (`splat.rs`): the segments of `lines.wgsl` are rasterized as
// before, but each fragment adds into a per-pixel accumulation buffer of five u32 words with
// atomics instead of writing a colour, so the result does not depend on draw order and needs no
// float blending (wgpu's GL backend has none on many drivers):
//
// - density: [rays, red sum, green sum, blue sum, unused] (colours 0..255);
// - alpha (weighted blended order-independent transparency, McGuire & Bavoil 2013, in fixed
//   point): [sum of w, red, green, blue sums of colour*w, sum of -ln(1 - a)] (the weight w in
//   1/255: the ray colour's own alpha times a depth weight; the log transmittance in 1/4096).
//
// A fragment behind the occluder (the scene's depth) adds nothing: with no depth of its own per
// pixel, the layer is hidden behind surfaces here, not in the compositor.

@group(0) @binding(2) var<storage, read_write> acc: array<atomic<u32>>;
@group(0) @binding(3) var occ_depth: texture_2d<f32>;
@group(0) @binding(4) var<uniform> splat: Splat;

const WORDS: u32 = 5u;

fn lin_depth(d: f32, near: f32, far: f32) -> f32 {
    return far * near / max(far - d * (far - near), 1e-30);
}

@fragment
fn fs_accum(v: LOut) {
    let p = vec2<u32>(v.pos.xy);
    if p.x >= splat.size.x || p.y >= splat.size.y {
        discard;
    }
    let l = lin_depth(v.pos.z, splat.ranges.x, splat.ranges.y);
    if splat.params.z > 0.5 {
        let od = textureLoad(occ_depth, vec2<i32>(p), 0).r;
        if od < 1.0 && l > lin_depth(od, splat.ranges.z, splat.ranges.w) * (1.0 + splat.params.y) {
            discard;
        }
    }
    let i = (p.y * splat.size.x + p.x) * WORDS;
    var g = 1.0;
    if view.params.w > 0.5 {
        g = 0.25 + 0.75 * clamp(v.s, 0.0, 1.0);
    }
    let rgb = vec3<u32>(clamp(v.color.rgb * g, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0 + 0.5);
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
    let a = clamp(v.color.a * view.viewport.w, 0.0, 0.999);
    // Nearer fragments weigh more (McGuire & Bavoil's depth weight, bounded to 0.1..1).
    let zn = clamp((l - splat.ranges.x) / max(splat.ranges.y - splat.ranges.x, 1e-30), 0.0, 1.0);
    let w = max(0.1, pow(1.0 - zn, 3.0));
    // The colour weight leaves out the layer's opacity, the same for every ray (it cancels in
    // the average, and a small one would round every weight to zero).
    let q = u32(clamp(v.color.a, 0.0, 1.0) * w * 255.0 + 0.5);
    // Bounded sums (checked before adding; fragments in flight overshoot by far less than the
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
