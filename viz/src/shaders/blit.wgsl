// A picture (the path-traced image, a heatmap) stretched over the whole layer.

struct Blit {
    // opacity, unused x3
    params: vec4<f32>,
};

@group(0) @binding(0) var<uniform> blit: Blit;
@group(0) @binding(1) var pic: texture_2d<f32>;
@group(0) @binding(2) var pic_sampler: sampler;

struct BOut {
    @builtin(position) pos: vec4<f32>,
    @location(0) uv: vec2<f32>,
};

@vertex
fn vs(@builtin(vertex_index) vi: u32) -> BOut {
    let x = f32((vi << 1u) & 2u);
    let y = f32(vi & 2u);
    var o: BOut;
    o.pos = vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
    o.uv = vec2<f32>(x, y);
    return o;
}

@fragment
fn fs(v: BOut) -> @location(0) vec4<f32> {
    let c = textureSample(pic, pic_sampler, v.uv);
    let a = c.a * blit.params.x;
    return vec4<f32>(c.rgb * a, a);
}
