// The GPU tracer's progressive image, tone-mapped where it accumulates: the two halves' sums
// (even and odd batches; per pixel the RGB sum and the sample count) are averaged, scaled by
// the exposure and encoded as sRGB, as `renderers::Film::to_srgb8` does on the CPU. Nothing is
// read back to draw it.

struct FilmParams {
    // film width, film height, exposure, opacity
    params: vec4<f32>,
    // target width, target height, unused x2
    dest: vec4<f32>,
};

@group(0) @binding(0) var<uniform> film: FilmParams;
@group(0) @binding(1) var<storage, read> even: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> odd: array<vec4<f32>>;

@vertex
fn vs(@builtin(vertex_index) vi: u32) -> @builtin(position) vec4<f32> {
    let x = f32((vi << 1u) & 2u);
    let y = f32(vi & 2u);
    return vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
}

// NaN and Inf are indeterminate in WGSL arithmetic: test the bits (all exponent bits set).
fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn srgb(x: f32) -> f32 {
    var v = 0.0;
    if finite(x) {
        v = clamp(x, 0.0, 1.0);
    }
    if v <= 0.0031308 {
        return 12.92 * v;
    }
    return 1.055 * pow(v, 1.0 / 2.4) - 0.055;
}

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let size = vec2<u32>(film.params.xy);
    let p = min(vec2<u32>(pos.xy * film.params.xy / film.dest.xy), size - vec2<u32>(1u));
    let i = p.y * size.x + p.x;
    let s = even[i] + odd[i];
    var c = vec3<f32>(0.0);
    if s.w > 0.0 {
        c = s.rgb / s.w * film.params.z;
    }
    let a = film.params.w;
    return vec4<f32>(vec3<f32>(srgb(c.r), srgb(c.g), srgb(c.b)) * a, a);
}
