// The uniform block of every scene-space pass (`ViewUniform` in camera.rs).
struct View {
    view_proj: mat4x4<f32>,
    // width, height, line width in pixels, opacity
    viewport: vec4<f32>,
    // light direction (xyz), mode (w)
    params: vec4<f32>,
};
