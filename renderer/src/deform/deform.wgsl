// Precomputed deformation mode (EQUATIONS.md §2.4): p' = p + s_lung · u + o_lung, one multiply-add
// per coordinate plus the lung's rigid offset (mediastinal shift, a dropped lung). Executed once per
// frame for every vertex of both lungs; both stereo eyes draw the result.

struct Params {
    // Deformation scale per lung: x = right lung (index 0), y = left lung (index 1).
    scale: vec4<f32>,
    // Rigid offset of the right lung (xyz, mm).
    offset_right: vec4<f32>,
    // Rigid offset of the left lung (xyz, mm).
    offset_left: vec4<f32>,
    count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
};

@group(0) @binding(0) var<uniform> params: Params;
// xyz: FRC position (mm, body frame); w: lung index.
@group(0) @binding(1) var<storage, read> base: array<vec4<f32>>;
// xyz: unit displacement (mm per unit of scale); w unused.
@group(0) @binding(2) var<storage, read> unit_disp: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> deformed: array<vec4<f32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.count) {
        return;
    }
    let b = base[i];
    let left = b.w > 0.5;
    let s = select(params.scale.x, params.scale.y, left);
    let o = select(params.offset_right.xyz, params.offset_left.xyz, left);
    deformed[i] = vec4<f32>(b.xyz + s * unit_disp[i].xyz + o, b.w);
}
