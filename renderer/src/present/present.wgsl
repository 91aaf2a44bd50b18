// Present pass: one fullscreen triangle copies the offscreen frame into the window's surface,
// whatever the surface's format and size (the image is scaled to the window; `fs_load` when the
// frame is exactly the window's size).

@group(0) @binding(0) var frame: texture_2d<f32>;
@group(0) @binding(1) var frame_sampler: sampler;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
};

@vertex
fn vs_main(@builtin(vertex_index) vi: u32) -> VsOut {
    // (0,0), (2,0), (0,2) in uv: covers the screen with one triangle.
    let uv = vec2<f32>(f32((vi << 1u) & 2u), f32(vi & 2u));
    var out: VsOut;
    out.clip = vec4<f32>(uv.x * 2.0 - 1.0, 1.0 - uv.y * 2.0, 0.0, 1.0);
    out.uv = uv;
    return out;
}

@fragment
fn fs_main(in: VsOut) -> @location(0) vec4<f32> {
    return textureSample(frame, frame_sampler, in.uv);
}

// The frame exactly the surface's size (a fullscreen frame made at the display's size): each pixel
// is its texel, loaded without the filtering sampler, which is most of this pass's cost on a CPU
// rasterizer (lavapipe at 1920x1080: docs/DEPLOY.md).
@fragment
fn fs_load(in: VsOut) -> @location(0) vec4<f32> {
    return textureLoad(frame, vec2<i32>(floor(in.clip.xy)), 0);
}
