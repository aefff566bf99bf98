// Ray segments and BVH box edges as screen-space quads read from storage buffers, the way
// rerun's re_renderer draws lines: no vertex buffers, no instancing; vertex i belongs to quad
// i / 6. A segment of zero length is drawn as a square point.

struct Seg {
    a: vec3<f32>,
    // RGBA8 colour
    color: u32,
    b: vec3<f32>,
    // bit 0: selected
    flags: u32,
};

@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> segs: array<Seg>;

struct LOut {
    @builtin(position) pos: vec4<f32>,
    @location(0) color: vec4<f32>,
    // 0 at the segment's start, 1 at its end
    @location(1) s: f32,
    // Index of the segment or box in the layer (picking): instance index (the draw's first
    // instance is the buffer's first index) plus the index within the buffer.
    @location(2) @interpolate(flat) id: u32,
};

// A line's ends in clip space, clipped against the near plane (z >= 0 in wgpu's clip space,
// linearly in clip space), with their positions along the line (0 at its start, 1 at its end);
// `visible` is false when the whole line lies behind the near plane. Shared with `splat.wgsl`.
struct Clipped {
    ca: vec4<f32>,
    cb: vec4<f32>,
    sa: f32,
    sb: f32,
    visible: bool,
};

fn clip_line(pa: vec3<f32>, pb: vec3<f32>) -> Clipped {
    var c: Clipped;
    c.ca = view.view_proj * vec4<f32>(pa, 1.0);
    c.cb = view.view_proj * vec4<f32>(pb, 1.0);
    c.sa = 0.0;
    c.sb = 1.0;
    c.visible = !(c.ca.z < 0.0 && c.cb.z < 0.0);
    if c.ca.z < 0.0 {
        let f = c.ca.z / (c.ca.z - c.cb.z);
        c.ca = mix(c.ca, c.cb, f);
        c.sa = f;
    } else if c.cb.z < 0.0 {
        let f = c.cb.z / (c.cb.z - c.ca.z);
        c.cb = mix(c.cb, c.ca, f);
        c.sb = 1.0 - f;
    }
    return c;
}

fn line_vertex(pa: vec3<f32>, pb: vec3<f32>, corner: u32, width: f32, color: vec4<f32>) -> LOut {
    var o: LOut;
    o.color = color;
    let clipped = clip_line(pa, pb);
    if !clipped.visible {
        o.pos = vec4<f32>(2.0, 2.0, 2.0, 1.0);
        o.s = 0.0;
        return o;
    }
    let ca = clipped.ca;
    let cb = clipped.cb;
    let sa = clipped.sa;
    let sb = clipped.sb;
    let na = ca.xy / ca.w;
    let nb = cb.xy / cb.w;
    let half = view.viewport.xy * 0.5;
    var d = (nb - na) * half;
    let len = length(d);
    var dir = vec2<f32>(1.0, 0.0);
    if len > 1e-4 {
        dir = d / len;
    }
    let perp = vec2<f32>(-dir.y, dir.x);
    // Two triangles: (0,1,2) (2,1,3) over corners (end, side).
    var ends = array<u32, 6>(0u, 0u, 1u, 1u, 0u, 1u);
    var sides = array<f32, 6>(-1.0, 1.0, -1.0, -1.0, 1.0, 1.0);
    let end = ends[corner];
    let side = sides[corner];
    var c = ca;
    var n = na;
    var along = -1.0;
    o.s = sa;
    if end == 1u {
        c = cb;
        n = nb;
        along = 1.0;
        o.s = sb;
    }
    let off_px = perp * side * width * 0.5 + dir * along * width * 0.5;
    let off = off_px / half;
    o.pos = vec4<f32>((n + off) * c.w, c.z, c.w);
    return o;
}

// Segments: view.params.y is the stride of a preview (every stride-th segment is drawn; 1 or
// less: all). Picking draws with params.y < 2, so ids are always segment indices.
@vertex
fn vs_seg(@builtin(vertex_index) vi: u32, @builtin(instance_index) first: u32) -> LOut {
    let stride = max(u32(view.params.y), 1u);
    let k = (vi / 6u) * stride;
    let s = segs[k];
    var width = view.viewport.z;
    var color = unpack4x8unorm(s.color);
    if (s.flags & 1u) != 0u {
        width = width * 2.5;
    }
    var o = line_vertex(s.a, s.b, vi % 6u, width, color);
    o.id = first + k;
    return o;
}

// Boxes: `a` is the minimum corner, `b` the maximum; 12 edges of 6 vertices each.
@vertex
fn vs_box(@builtin(vertex_index) vi: u32, @builtin(instance_index) first: u32) -> LOut {
    let bx = segs[vi / 72u];
    let e = (vi % 72u) / 6u;
    var e_from = array<u32, 12>(0u, 1u, 3u, 2u, 4u, 5u, 7u, 6u, 0u, 1u, 2u, 3u);
    var e_to = array<u32, 12>(1u, 3u, 2u, 0u, 5u, 7u, 6u, 4u, 4u, 5u, 6u, 7u);
    let i = e_from[e];
    let j = e_to[e];
    let pi = vec3<f32>(select(bx.a.x, bx.b.x, (i & 1u) != 0u), select(bx.a.y, bx.b.y, (i & 2u) != 0u), select(bx.a.z, bx.b.z, (i & 4u) != 0u));
    let pj = vec3<f32>(select(bx.a.x, bx.b.x, (j & 1u) != 0u), select(bx.a.y, bx.b.y, (j & 2u) != 0u), select(bx.a.z, bx.b.z, (j & 4u) != 0u));
    var width = view.viewport.z;
    if (bx.flags & 1u) != 0u {
        width = width * 2.0;
    }
    var o = line_vertex(pi, pj, vi % 6u, width, unpack4x8unorm(bx.color));
    o.s = 1.0;
    o.id = first + vi / 72u;
    return o;
}

@fragment
fn fs_line(v: LOut) -> @location(0) vec4<f32> {
    // Mode 1: direction as a gradient from dim at the origin to full colour at the end.
    var g = 1.0;
    if view.params.w > 0.5 {
        g = 0.25 + 0.75 * clamp(v.s, 0.0, 1.0);
    }
    let a = v.color.a * view.viewport.w;
    return vec4<f32>(v.color.rgb * g * a, a);
}

// Picking: the layer's slot (params.x of the pick draw) and the item's index + 1 (0: nothing).
@fragment
fn fs_pick(v: LOut) -> @location(0) vec2<u32> {
    return vec2<u32>(u32(view.params.x), v.id + 1u);
}
