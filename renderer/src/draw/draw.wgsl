// Drawing the deformed lungs: shaded triangles or camera-facing point splats, one eye per draw, in
// one of three looks (renderer/src/draw/mod.rs):
//
//   opaque       fs_opaque_*   lit tissue, depth-tested and written
//   translucent  fs_oit_*      lit tissue with a fresnel rim into weighted blended OIT targets
//                              (McGuire & Bavoil 2013), then composite.wgsl over the opaque image
//   see-through  fs_glow_*     emitted light for an additive display (black is transparent)
//
// Per vertex: the deformed position (xyz; w belongs to the compute pass), the normal with the
// colour mode's scalar field in w (deform.wgsl, vertex_normals), and the surface attribute
// (material id, lobe code 0..5 (0 unknown), fissure flag; the signed distances from the oblique and
// horizontal fissure planes: draw/mod.rs, SurfaceAttr).

struct Eye {
    view_proj: mat4x4<f32>,
    // Body (mesh) frame → tracker room frame: the patient registration.
    model: mat4x4<f32>,
    // Eye position in the room frame (w unused).
    eye_pos: vec4<f32>,
    // Camera right and up axes in the room frame; w of right = splat radius in mm.
    cam_right: vec4<f32>,
    cam_up: vec4<f32>,
};

struct Style {
    // What colour shows: 0 tissue, 1 displacement, 2 ventilation, 3 lobes
    // (lung_model::scene::ColorMode).
    color_mode: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    // Linear albedo per lobe code (0 unknown, 1 RUL, 2 RML, 3 RLL, 4 LUL, 5 LLL).
    lobes: array<vec4<f32>, 6>,
};

const LOBES_MODE: u32 = 3u;

@group(0) @binding(0) var<uniform> eye: Eye;
@group(0) @binding(1) var<uniform> style: Style;

// Material ids (draw/mod.rs, Material).
const RIGHT_LUNG: u32 = 0u;
const LEFT_LUNG: u32 = 1u;
const TUMOUR: u32 = 2u;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) @interpolate(flat) material: u32,
    @location(2) corner: vec2<f32>,
    // Smooth normal in the room frame (triangles; zero where the compute pass had no area).
    @location(3) normal: vec3<f32>,
    // The colour mode's field at the vertex (displacement mm, or expansion relative to FRC).
    @location(4) field: f32,
    // The lung has lobe codes (1) or not (0: drawn grey, no fissures).
    @location(5) @interpolate(flat) lobed: u32,
    // The splat's vertex lies on a fissure (1) or not (0).
    @location(6) @interpolate(flat) fissure: u32,
    // Signed distances from the oblique fissure (> 0: lower lobe) and the horizontal one (> 0:
    // below it), affine in the rest position, so interpolated exactly: their zeros are the
    // fissures, straight across each triangle and continuous across its edges.
    @location(7) fissure_d: vec2<f32>,
};

// A ramp through four colours, t in [0, 1].
fn ramp4(t: f32, a: vec3<f32>, b: vec3<f32>, c: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let s = clamp(t, 0.0, 1.0) * 3.0;
    if (s < 1.0) {
        return mix(a, b, s);
    }
    if (s < 2.0) {
        return mix(b, c, s - 1.0);
    }
    return mix(c, d, s - 2.0);
}

// The lobe code of a fragment from its fissure distances, 0 on a lung without lobe codes.
fn lobe_code(material: u32, lobed: u32, d: vec2<f32>) -> u32 {
    if (lobed == 0u) {
        return 0u;
    }
    if (material == LEFT_LUNG) {
        return select(4u, 5u, d.x > 0.0);
    }
    if (d.x > 0.0) {
        return 3u;
    }
    return select(1u, 2u, d.y > 0.0);
}

// Coverage (0..1) of the fissure line at signed distance `d` from it, `fw` its screen-space change
// per pixel: 1 within a pixel of it, fading out by 2 (about 2 px wide whatever the distance).
fn fissure_edge(d: f32, fw: f32) -> f32 {
    return 1.0 - smoothstep(1.0, 2.0, abs(d) / max(fw, 1e-9));
}

// How much of the fissure line covers a fragment: the oblique fissure, and on the right lung the
// horizontal one above it. The derivatives are taken first, in uniform control flow.
fn fissure(in: VsOut, splat: bool) -> f32 {
    let d = in.fissure_d;
    let fw = fwidth(d);
    // No line on tumours, outside the lobes mode, or on a lung without lobe codes.
    if (style.color_mode != LOBES_MODE || in.material == TUMOUR || in.lobed == 0u) {
        return 0.0;
    }
    if (splat) {
        return f32(in.fissure);
    }
    var c = fissure_edge(d.x, fw.x);
    if (in.material == RIGHT_LUNG && d.x <= 0.0) {
        c = max(c, fissure_edge(d.y, fw.y));
    }
    return c;
}

// The fissure line's colour: dark on tissue, light on an additive display.
const FISSURE_DARK = vec3<f32>(0.004, 0.004, 0.008);
const FISSURE_LIGHT = vec3<f32>(0.95, 0.95, 0.90);

// Linear-light albedo of a fragment.
fn albedo(material: u32, field: f32, lobed: u32, d: vec2<f32>) -> vec3<f32> {
    if (material == TUMOUR) {
        // Yellow-green, far from every lung colour of every mode.
        return vec3<f32>(0.55, 0.92, 0.12);
    }
    if (style.color_mode == LOBES_MODE) {
        return style.lobes[lobe_code(material, lobed, d)].rgb;
    }
    if (style.color_mode == 1u) {
        // Displacement from rest: 0 → 20 mm, dark blue → teal → green → yellow.
        return ramp4(field / 20.0, vec3<f32>(0.05, 0.04, 0.30), vec3<f32>(0.02, 0.32, 0.45),
                     vec3<f32>(0.18, 0.62, 0.20), vec3<f32>(0.95, 0.85, 0.10));
    }
    if (style.color_mode == 2u) {
        // Expansion: collapsing (−10 %) blue, none white, +30 % red.
        let white = vec3<f32>(0.80, 0.80, 0.80);
        if (field < 0.0) {
            return mix(white, vec3<f32>(0.05, 0.20, 0.85), clamp(-field / 0.10, 0.0, 1.0));
        }
        return mix(white, vec3<f32>(0.85, 0.06, 0.04), clamp(field / 0.30, 0.0, 1.0));
    }
    // Tissue: the salmon pink of an aerated lung's pleura (linear light); the right lung a little
    // warmer than the left so the two read apart where they meet in a view.
    return select(vec3<f32>(0.74, 0.33, 0.30), vec3<f32>(0.68, 0.30, 0.36), material == LEFT_LUNG);
}

// Surface terms seen from the eye: n faces the viewer.
struct Lit {
    colour: vec3<f32>,
    // 1 − |n·v|: 0 facing the eye, 1 at the silhouette.
    edge: f32,
};

// Lung tissue under a lamp at the viewer's upper left (a head- or theatre light): wrapped diffuse
// (light bleeds past the terminator as in a scattering medium), a soft specular of the wet pleura,
// and a red subsurface tint where the direct light fades, in place of a hard black shadow.
fn tissue(n_in: vec3<f32>, world: vec3<f32>, base: vec3<f32>) -> Lit {
    let v = normalize(eye.eye_pos.xyz - world);
    // Face the viewer (a back face in the translucent looks, or a silhouette vertex's normal).
    let n = select(-n_in, n_in, dot(n_in, v) >= 0.0);
    let l = normalize(v + 0.45 * eye.cam_up.xyz - 0.30 * eye.cam_right.xyz);
    let wrap = 0.45;
    let ndl = dot(n, l);
    let diffuse = max((ndl + wrap) / (1.0 + wrap), 0.0);
    let h = normalize(l + v);
    let ndv = max(dot(n, v), 0.0);
    // Schlick's fresnel (F0 = 0.03, water) on a broad lobe plus a narrower sheen.
    let fresnel = 0.03 + 0.97 * pow(1.0 - max(dot(h, v), 0.0), 5.0);
    let spec = (0.10 * pow(max(dot(n, h), 0.0), 24.0) + 0.22 * pow(max(dot(n, h), 0.0), 180.0))
        * (0.4 + 3.0 * fresnel);
    let scatter = vec3<f32>(0.55, 0.10, 0.08) * (1.0 - smoothstep(0.0, 0.6, ndl + wrap)) * 0.35;
    let ambient = 0.16;
    var out: Lit;
    out.colour = base * (ambient + 0.84 * diffuse) + scatter * base.r + vec3<f32>(spec);
    out.edge = 1.0 - ndv;
    return out;
}

fn vs_common(p: vec3<f32>, normal: vec4<f32>, surface: vec4<u32>, fissure_d: vec2<f32>) -> VsOut {
    var out: VsOut;
    let world = eye.model * vec4<f32>(p, 1.0);
    out.clip = eye.view_proj * world;
    out.world = world.xyz;
    out.material = surface.x;
    out.corner = vec2<f32>(0.0, 0.0);
    // The registration is a rigid transform: its upper 3×3 rotates normals.
    out.normal = (eye.model * vec4<f32>(normal.xyz, 0.0)).xyz;
    out.field = normal.w;
    out.lobed = u32(surface.y != 0u);
    out.fissure = surface.z;
    out.fissure_d = fissure_d;
    return out;
}

@vertex
fn vs_triangles(@location(0) p: vec4<f32>, @location(1) n: vec4<f32>, @location(2) surface: vec4<u32>, @location(7) fissure_d: vec2<f32>) -> VsOut {
    return vs_common(p.xyz, n, surface, fissure_d);
}

fn triangle_normal(in: VsOut) -> vec3<f32> {
    let len = length(in.normal);
    if (len < 0.5) {
        // A vertex with no area around it (degenerate neighbourhood): the face's own normal.
        return normalize(cross(dpdx(in.world), dpdy(in.world)));
    }
    return in.normal / len;
}

// Two triangles per splat, expanded from the instance's deformed position.
const CORNERS = array<vec2<f32>, 6>(
    vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, -1.0), vec2<f32>(1.0, 1.0),
    vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, 1.0), vec2<f32>(-1.0, 1.0),
);

@vertex
fn vs_splats(@builtin(vertex_index) vi: u32, @location(0) p: vec4<f32>, @location(1) n: vec4<f32>, @location(2) surface: vec4<u32>, @location(7) fissure_d: vec2<f32>) -> VsOut {
    let corner = CORNERS[vi];
    let radius = eye.cam_right.w;
    let centre = (eye.model * vec4<f32>(p.xyz, 1.0)).xyz;
    let world = centre + (eye.cam_right.xyz * corner.x + eye.cam_up.xyz * corner.y) * radius;
    var out = vs_common(p.xyz, n, surface, fissure_d);
    out.clip = eye.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    out.corner = corner;
    out.normal = vec3<f32>(0.0, 0.0, 0.0);
    return out;
}

// The sphere impostor's normal at a splat fragment (inside the disc: see outside_splat).
fn splat_normal(in: VsOut) -> vec3<f32> {
    let r2 = dot(in.corner, in.corner);
    let to_eye = normalize(eye.eye_pos.xyz - in.world);
    return normalize(eye.cam_right.xyz * in.corner.x + eye.cam_up.xyz * in.corner.y + to_eye * sqrt(max(1.0 - r2, 0.0)));
}

fn outside_splat(in: VsOut) -> bool {
    return dot(in.corner, in.corner) > 1.0;
}

// ---- opaque ----

fn lit(in: VsOut, splat: bool) -> Lit {
    var n: vec3<f32>;
    if (splat) {
        n = splat_normal(in);
    } else {
        n = triangle_normal(in);
    }
    return tissue(n, in.world, albedo(in.material, in.field, in.lobed, in.fissure_d));
}

fn opaque(in: VsOut, splat: bool) -> vec4<f32> {
    let line = fissure(in, splat);
    return vec4<f32>(mix(lit(in, splat).colour, FISSURE_DARK, line), 1.0);
}

@fragment
fn fs_opaque_triangles(in: VsOut) -> @location(0) vec4<f32> {
    return opaque(in, false);
}

@fragment
fn fs_opaque_splats(in: VsOut) -> @location(0) vec4<f32> {
    if (outside_splat(in)) {
        discard;
    }
    return opaque(in, true);
}

// ---- translucent: weighted blended order-independent transparency ----

struct Oit {
    // Σ w·α·c (rgb) and Σ w·α (a): blended One, One.
    @location(0) accum: vec4<f32>,
    // Π (1 − α): blended Zero, OneMinusSrc.
    @location(1) reveal: f32,
};

fn oit(lit: Lit, world: vec3<f32>, line: f32) -> Oit {
    // Facing the eye the tissue is a veil (α 0.28); at the silhouette, where the eye looks through
    // more of it, nearly opaque and brighter: the fresnel rim that shows the lungs' outline. A
    // fissure line is nearly opaque, so it reads through the veil.
    let rim = pow(lit.edge, 3.0);
    let alpha = max(mix(0.28, 0.92, rim), 0.85 * line);
    let c = mix(lit.colour + vec3<f32>(0.95, 0.70, 0.65) * 0.35 * rim, FISSURE_DARK, line);
    // McGuire & Bavoil's depth weight (their eq. 9, in the eye's distance): nearer surfaces weigh
    // more, so the near wall of a lung wins over its far wall and over the other lung behind it.
    // Scaled for views about a metre away; clamped to stay within half-float range.
    let d = length(eye.eye_pos.xyz - world) / 1000.0;
    let w = alpha * clamp(1.0 / (1e-5 + pow(d, 8.0)), 1e-2, 3e3);
    var out: Oit;
    out.accum = vec4<f32>(c * alpha * w, alpha * w);
    out.reveal = alpha;
    return out;
}

@fragment
fn fs_oit_triangles(in: VsOut) -> Oit {
    let line = fissure(in, false);
    return oit(lit(in, false), in.world, line);
}

@fragment
fn fs_oit_splats(in: VsOut) -> Oit {
    if (outside_splat(in)) {
        discard;
    }
    return oit(lit(in, true), in.world, fissure(in, true));
}

// ---- see-through: an additive display adds light; black shows the patient unchanged ----

fn glow(lit: Lit, line: f32) -> vec4<f32> {
    // Little light where the surface faces the eye (the patient stays visible through it), most at
    // the silhouette: the lungs read as lit outlines with a faint fill. A fissure is a lit line.
    let rim = pow(lit.edge, 2.5);
    let strength = 0.10 + 0.85 * rim;
    let c = lit.colour * strength + vec3<f32>(0.25, 0.18, 0.16) * rim;
    return vec4<f32>(mix(c, FISSURE_LIGHT, line), 1.0);
}

@fragment
fn fs_glow_triangles(in: VsOut) -> @location(0) vec4<f32> {
    let line = fissure(in, false);
    return glow(lit(in, false), line);
}

@fragment
fn fs_glow_splats(in: VsOut) -> @location(0) vec4<f32> {
    if (outside_splat(in)) {
        discard;
    }
    return glow(lit(in, true), fissure(in, true));
}
