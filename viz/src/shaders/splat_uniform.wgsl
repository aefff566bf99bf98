// The styles' uniform, shared by `splat.wgsl`, `splat_reduce.wgsl` and `splat_resolve.wgsl`
// (each is compiled with this prepended) and laid out as `SplatUniform` in `splat.rs`.
struct Splat {
    // layer near, far; occluder near, far
    ranges: vec4<f32>,
    // style (1 alpha, 2 density), relative depth bias, occluder present (> 0.5), log scale (> 0.5)
    params: vec4<f32>,
    // width, height, pixels, colour map (1) or the rays' own colours (0)
    size: vec4<u32>,
    // opacity, unused x3
    extra: vec4<f32>,
};

