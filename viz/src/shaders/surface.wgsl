// Triangles read from a storage buffer (no vertex buffers): vertex i is corner i % 3 of
// triangle i / 3. Modes (view.params.w): 0 opaque, 1 alpha-blended, 2 wireframe.

struct Tri {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec4<f32>,
    // rgb, and a = 2 for emitters (drawn unshaded)
    color: vec4<f32>,
};

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> tris: array<Tri>;

struct VOut {
    @builtin(position) pos: vec4<f32>,
    @location(0) color: vec3<f32>,
    @location(1) bary: vec3<f32>,
};

@vertex
fn vs(@builtin(vertex_index) vi: u32) -> VOut {
    let t = tris[vi / 3u];
    let k = vi % 3u;
    var p = t.a.xyz;
    var bary = vec3<f32>(1.0, 0.0, 0.0);
    if k == 1u {
        p = t.b.xyz;
        bary = vec3<f32>(0.0, 1.0, 0.0);
    } else if k == 2u {
        p = t.c.xyz;
        bary = vec3<f32>(0.0, 0.0, 1.0);
    }
    let c = cross(t.b.xyz - t.a.xyz, t.c.xyz - t.a.xyz);
    let n = c / max(length(c), 1e-30);
    let l = normalize(view.params.xyz);
    var shade = 0.3 + 0.7 * abs(dot(n, l));
    if t.color.a > 1.5 {
        shade = 1.0;
    }
    var o: VOut;
    o.pos = view.view_proj * vec4<f32>(p, 1.0);
    o.color = t.color.rgb * shade;
    o.bary = bary;
    return o;
}

@fragment
fn fs(v: VOut) -> @location(0) vec4<f32> {
    let opacity = view.viewport.w;
    if view.params.w > 1.5 {
        let d = fwidth(v.bary) * view.viewport.z;
        let e = smoothstep(vec3<f32>(0.0), d, v.bary);
        let edge = 1.0 - min(min(e.x, e.y), e.z);
        if edge < 0.02 {
            discard;
        }
        let a = edge * opacity;
        return vec4<f32>(v.color * a, a);
    }
    return vec4<f32>(v.color * opacity, opacity);
}

// Picking: the scene's depth only, no id (the composition layer), so the ids of the layers
// above it hide behind geometry as their pixels do.
@fragment
fn fs_pick_depth(v: VOut) -> @location(0) vec2<u32> {
    return vec2<u32>(0u, 0u);
}
