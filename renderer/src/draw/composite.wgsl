// The translucent look's composite (McGuire & Bavoil 2013): the weighted blended OIT targets that
// draw.wgsl's fs_oit_* wrote, over the opaque image, by one fullscreen triangle.

@group(0) @binding(0) var oit_accum: texture_2d<f32>;
@group(0) @binding(1) var oit_reveal: texture_2d<f32>;

@vertex
fn vs_fullscreen(@builtin(vertex_index) vi: u32) -> @builtin(position) vec4<f32> {
    let uv = vec2<f32>(f32((vi << 1u) & 2u), f32(vi & 2u));
    return vec4<f32>(uv.x * 2.0 - 1.0, 1.0 - uv.y * 2.0, 0.0, 1.0);
}

@fragment
fn fs_composite(@builtin(position) at: vec4<f32>) -> @location(0) vec4<f32> {
    let p = vec2<i32>(at.xy);
    let reveal = textureLoad(oit_reveal, p, 0).r;
    if (reveal >= 0.999) {
        discard;
    }
    let a = textureLoad(oit_accum, p, 0);
    // Average colour of the layers, over the image by their total coverage 1 − Π(1 − α).
    let c = a.rgb / clamp(a.a, 1e-4, 5e4);
    return vec4<f32>(c, 1.0 - reveal);
}
