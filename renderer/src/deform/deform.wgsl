// The per-frame deformation pass (EQUATIONS.md §2.4 and §3): one compute pass per frame moves every
// vertex of both lungs and then computes smooth vertex normals from the moved positions; every eye
// draws from those two buffers. Entry points, one per mode (lungdyn_model::deform::modes):
//
//   (each p below is (1 − c)·p for a lung collapsing towards its hilum, EQUATIONS §4.1)
//   deform_precomputed  p + s·u + o                               (3 MACs)
//   deform_basis        p + s·(w·G)·kd + o                         (EQUATIONS §3.3, 4 MACs)
//   deform_sh           p + s·(Σ_k F_k·T_k)·kd + o                 (eq. 7.7, n² MACs on 16-bit T)
//   direct_force        f_j = w·(1, x̂, ŷ, ẑ)_j                    (eq. 6.18 for this orientation)
//   deform_direct       p + s·(Σ_j f_j·T(j, i))·kd + o             (eq. 7.1 over the stored rows)
//   vertex_normals      n_i = normalize(Σ_t (b − a) × (c − a))     (area-weighted, smooth shading)
//                       and in w the colour mode's field: |p_i − p_i⁰| (displacement, mm) or
//                       (A_i/A_i⁰)^(3/2) − 1 (expansion relative to FRC, A_i the area of the
//                       vertex's incident triangles, A_i⁰ its value at rest), else 0
//
// The CPU reference of every entry point is lung_model::deform::modes::CpuLung; the two agree to
// 1e-4 relative (tests/tests/modes_gpu.rs).
//
// Drawn vertices only (the quality governor's step, renderer/src/governor.rs): with params.listed
// > 0, invocation g moves vertex listed_vertices[g] of a draw level's vertex list instead of vertex
// g, with the same arithmetic (so each listed vertex lands where the full pass puts it, bit for
// bit), and vertex_normals reads that level's triangles: the incidence CSR and the rest areas are
// indexed by g, the triangles' corners are global vertex indices. direct_force always runs over
// every node (each gathered vertex needs every force).

struct Params {
    // Deformation scale per lung slot: x = right lung (slot 0), y = left lung (slot 1); z, w: the
    // share of the rest position kept, 1 − c, of a lung collapsing towards its hilum (EQUATIONS §4.1:
    // h + (1 − c)(p − h) + s·u + o, with c·h folded into the offset); 1 for a healthy lung.
    scale: vec4<f32>,
    // Rigid offset per slot (xyz, mm).
    offset: array<vec4<f32>, 2>,
    // Force weights (w0, wx, wy, wz) per slot: basis and direct modes.
    weights: array<vec4<f32>, 2>,
    count: u32,
    // The field vertex_normals writes into normals.w: 0 none, 1 displacement, 2 expansion.
    field: u32,
    // Vertices in listed_vertices this frame; 0: every vertex, in order.
    listed: u32,
    _pad2: u32,
    // Per slot: x = first vertex, y = SH coefficients per vertex, z = first SH word, w = the
    // coefficients summed (y, or fewer where the governor capped the bands).
    lung_info: array<vec4<u32>, 2>,
    // SH force coefficients times their index's scale, F_k·scale_k, per slot: slot s, k →
    // sh_f[s·16 + k/4][k%4] (at most 64 each; 0 past the lung's count).
    sh_f: array<vec4<f32>, 32>,
};

@group(0) @binding(0) var<uniform> params: Params;
// xyz: FRC position (mm, body frame); w: lung slot.
@group(0) @binding(1) var<storage, read> base: array<vec4<f32>>;
// xyz: unit displacement (precomputed mode).
@group(0) @binding(2) var<storage, read> unit_disp: array<vec4<f32>>;
// Deformed positions (xyz mm, w slot): the draw's vertex buffer.
@group(0) @binding(3) var<storage, read_write> deformed: array<vec4<f32>>;
// xyz: k·d_i, the direction scaled to one unit volume per unit of force.
@group(0) @binding(4) var<storage, read> kd: array<vec4<f32>>;
// Basis responses (G_0, G_x, G_y, G_z).
@group(0) @binding(5) var<storage, read> basis: array<vec4<f32>>;
// SH transfer coefficients T^i_k as 16-bit integers q, two per word (k even in the low half, a zero
// pad after an odd count), ceil(lung_info.y / 2) words per vertex: T = q·scale_k/32767, with scale_k
// folded into sh_f by the host (lung_model::deform::sh_coeffs).
@group(0) @binding(6) var<storage, read> sh_t: array<u32>;
// (1, x̂, ŷ, ẑ) per node (direct mode).
@group(0) @binding(7) var<storage, read> nhat: array<vec4<f32>>;
// Applied force per node for this frame (direct mode scratch).
@group(0) @binding(8) var<storage, read_write> force: array<f32>;
// Tᵀ in compressed rows: node i gathers (col_src[k], col_val[k]) for k in col_ptr[i]..col_ptr[i+1].
@group(0) @binding(9) var<storage, read> col_ptr: array<u32>;
@group(0) @binding(10) var<storage, read> col_src: array<u32>;
@group(0) @binding(11) var<storage, read> col_val: array<f32>;
// Smooth vertex normals (xyz unit, or 0 where the neighbourhood has no area).
@group(0) @binding(12) var<storage, read_write> normals: array<vec4<f32>>;
// Triangles incident to each vertex, and the triangles' vertex indices.
@group(0) @binding(13) var<storage, read> inc_ptr: array<u32>;
@group(0) @binding(14) var<storage, read> inc_tris: array<u32>;
@group(0) @binding(15) var<storage, read> indices: array<u32>;
// Σ of the incident triangles' areas at rest (FRC), mm², per vertex (the expansion field).
@group(0) @binding(16) var<storage, read> rest_area: array<f32>;
// A draw level's vertices (global indices, ascending), when params.listed > 0.
@group(0) @binding(17) var<storage, read> listed_vertices: array<u32>;

const NO_VERTEX: u32 = 0xffffffffu;

// The vertex invocation g moves: g itself, or the g-th listed one; NO_VERTEX past the end.
fn vertex_of(g: u32) -> u32 {
    if (params.listed > 0u) {
        if (g >= params.listed) {
            return NO_VERTEX;
        }
        return listed_vertices[g];
    }
    if (g >= params.count) {
        return NO_VERTEX;
    }
    return g;
}

fn slot_of(b: vec4<f32>) -> u32 {
    return select(0u, 1u, b.w > 0.5);
}

fn scale_of(slot: u32) -> f32 {
    return select(params.scale.x, params.scale.y, slot == 1u);
}

fn keep_of(slot: u32) -> f32 {
    return select(params.scale.z, params.scale.w, slot == 1u);
}

@compute @workgroup_size(256)
fn deform_precomputed(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = vertex_of(gid.x);
    if (i == NO_VERTEX) {
        return;
    }
    let b = base[i];
    let slot = slot_of(b);
    deformed[i] = vec4<f32>(keep_of(slot) * b.xyz + scale_of(slot) * unit_disp[i].xyz + params.offset[slot].xyz, b.w);
}

@compute @workgroup_size(256)
fn deform_basis(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = vertex_of(gid.x);
    if (i == NO_VERTEX) {
        return;
    }
    let b = base[i];
    let slot = slot_of(b);
    let d = dot(params.weights[slot], basis[i]);
    deformed[i] = vec4<f32>(keep_of(slot) * b.xyz + (scale_of(slot) * d) * kd[i].xyz + params.offset[slot].xyz, b.w);
}

@compute @workgroup_size(256)
fn deform_sh(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = vertex_of(gid.x);
    if (i == NO_VERTEX) {
        return;
    }
    let b = base[i];
    let slot = slot_of(b);
    let info = params.lung_info[slot];
    let n = info.y;
    let first = info.z + (i - info.x) * ((n + 1u) / 2u);
    var d = 0.0;
    // info.w coefficients are summed: all n, or fewer where the governor capped the bands (the
    // force coefficients past it are 0, so an odd cap's last pair adds nothing of the next band).
    for (var k = 0u; k < min(n, info.w); k = k + 2u) {
        // unpack2x16snorm: max(q / 32767, −1) per half; the pad half and its sh_f entry are 0.
        let t = unpack2x16snorm(sh_t[first + k / 2u]);
        let f0 = params.sh_f[slot * 16u + k / 4u][k % 4u];
        let f1 = params.sh_f[slot * 16u + (k + 1u) / 4u][(k + 1u) % 4u];
        d = d + t.x * f0 + t.y * f1;
    }
    deformed[i] = vec4<f32>(keep_of(slot) * b.xyz + (scale_of(slot) * d) * kd[i].xyz + params.offset[slot].xyz, b.w);
}

@compute @workgroup_size(256)
fn direct_force(@builtin(global_invocation_id) gid: vec3<u32>) {
    let j = gid.x;
    if (j >= params.count) {
        return;
    }
    force[j] = dot(params.weights[slot_of(base[j])], nhat[j]);
}

@compute @workgroup_size(256)
fn deform_direct(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = vertex_of(gid.x);
    if (i == NO_VERTEX) {
        return;
    }
    let b = base[i];
    let slot = slot_of(b);
    var d = 0.0;
    for (var k = col_ptr[i]; k < col_ptr[i + 1u]; k = k + 1u) {
        d = d + force[col_src[k]] * col_val[k];
    }
    deformed[i] = vec4<f32>(keep_of(slot) * b.xyz + (scale_of(slot) * d) * kd[i].xyz + params.offset[slot].xyz, b.w);
}

@compute @workgroup_size(256)
fn vertex_normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    let g = gid.x;
    let i = vertex_of(g);
    if (i == NO_VERTEX) {
        return;
    }
    var n = vec3<f32>(0.0, 0.0, 0.0);
    // Twice the incident area.
    var area2 = 0.0;
    for (var k = inc_ptr[g]; k < inc_ptr[g + 1u]; k = k + 1u) {
        let t = inc_tris[k] * 3u;
        let a = deformed[indices[t]].xyz;
        let b = deformed[indices[t + 1u]].xyz;
        let c = deformed[indices[t + 2u]].xyz;
        let x = cross(b - a, c - a);
        n = n + x;
        area2 = area2 + length(x);
    }
    let len = length(n);
    var unit = vec3<f32>(0.0, 0.0, 0.0);
    if (len > 1e-30) {
        unit = n / len;
    }
    var field = 0.0;
    if (params.field == 1u) {
        let p = deformed[i].xyz - base[i].xyz;
        field = length(p);
    } else if (params.field == 2u) {
        let a0 = rest_area[g];
        if (a0 > 0.0) {
            field = pow(0.5 * area2 / a0, 1.5) - 1.0;
        }
    }
    normals[i] = vec4<f32>(unit, field);
}
