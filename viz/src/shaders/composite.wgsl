// Lays one layer over the picture so far (premultiplied alpha). A layer drawn in scene space is
// hidden where the occluder (the depth-only rasterization of the scene) is nearer.
//
// The depth targets are bound as unfilterable float textures, not `texture_depth_2d`: WGSL's
// `textureLoad` of a depth texture has no GLSL form (wgpu's GL backend), a float view of a
// Depth32Float texture loads the same value on every backend (`pipeline.rs` declares the layout).

struct Comp {
    // layer near, far; occluder near, far
    ranges: vec4<f32>,
    // depth test on (x > 0.5), relative bias (y)
    params: vec4<f32>,
};

@group(0) @binding(0) var<uniform> comp: Comp;
@group(0) @binding(1) var layer_color: texture_2d<f32>;
@group(0) @binding(2) var layer_depth: texture_2d<f32>;
@group(0) @binding(3) var occ_depth: texture_2d<f32>;

@vertex
fn vs(@builtin(vertex_index) vi: u32) -> @builtin(position) vec4<f32> {
    let x = f32((vi << 1u) & 2u);
    let y = f32(vi & 2u);
    return vec4<f32>(x * 2.0 - 1.0, 1.0 - y * 2.0, 0.0, 1.0);
}

fn linear(d: f32, near: f32, far: f32) -> f32 {
    return far * near / max(far - d * (far - near), 1e-30);
}

@fragment
fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<i32>(pos.xy);
    let c = textureLoad(layer_color, p, 0);
    if c.a <= 0.0 {
        discard;
    }
    if comp.params.x > 0.5 {
        let ld = textureLoad(layer_depth, p, 0).r;
        let od = textureLoad(occ_depth, p, 0).r;
        if od < 1.0 && ld < 1.0 {
            let l = linear(ld, comp.ranges.x, comp.ranges.y);
            let o = linear(od, comp.ranges.z, comp.ranges.w);
            if l > o * (1.0 + comp.params.y) {
                discard;
            }
        }
    }
    return c;
}
