// Resolves an accumulation (`splat.wgsl`) into the layer's colour, premultiplied:
// - density: brightness (or a colour map's value) by rays per pixel, log(1 + n) / log(1 + max)
//   by default, linear n / max when asked; the hue is the mean colour of the rays at the pixel;
// - alpha: the weighted average colour, covering 1 - exp(-sum of -ln(1 - a)).

@group(0) @binding(0) var<storage, read> acc: array<u32>;
@group(0) @binding(1) var<storage, read> stats: array<u32>;
@group(0) @binding(2) var<uniform> splat: Splat;
// 256 colours of the density colour map, RGBA8.
@group(0) @binding(3) var<storage, read> lut: array<u32>;

@vertex
fn vs(@builtin(vertex_index) vi: u32) -> @builtin(position) vec4<f32> {
    let x = f32((vi << 1u) & 2u);
    let y = f32(vi & 2u);
    return vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
}

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<u32>(pos.xy);
    if p.x >= splat.size.x || p.y >= splat.size.y {
        discard;
    }
    let i = (p.y * splat.size.x + p.x) * 5u;
    let n = acc[i];
    let opacity = splat.extra.x;
    if splat.params.x > 1.5 {
        if n == 0u {
            discard;
        }
        let mx = f32(max(stats[0], 1u));
        var v = f32(n) / mx;
        if splat.params.w > 0.5 {
            v = log(1.0 + f32(n)) / log(1.0 + mx);
        }
        v = clamp(v, 0.0, 1.0);
        if splat.size.w == 1u {
            let c = unpack4x8unorm(lut[min(u32(v * 255.0 + 0.5), 255u)]);
            return vec4<f32>(c.rgb * opacity, opacity);
        }
        let m = min(n, 16777216u);
        let mean = vec3<f32>(f32(acc[i + 1u]), f32(acc[i + 2u]), f32(acc[i + 3u])) / (255.0 * f32(m));
        let a = v * opacity;
        return vec4<f32>(mean * a, a);
    }
    let r = acc[i + 4u];
    if n == 0u && r == 0u {
        discard;
    }
    let cover = (1.0 - exp(-f32(r) / 4096.0)) * select(1.0, 0.0, n == 0u);
    let mean = vec3<f32>(f32(acc[i + 1u]), f32(acc[i + 2u]), f32(acc[i + 3u])) / (255.0 * f32(max(n, 1u)));
    return vec4<f32>(clamp(mean, vec3<f32>(0.0), vec3<f32>(1.0)) * cover, cover);
}
