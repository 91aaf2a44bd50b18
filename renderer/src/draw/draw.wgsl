// Drawing the deformed lungs: shaded triangles or camera-facing point splats, one eye per draw.

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

@group(0) @binding(0) var<uniform> eye: Eye;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) world: vec3<f32>,
    @location(1) lung: f32,
    @location(2) corner: vec2<f32>,
    // Smooth normal in the room frame (triangles; zero where the compute pass had no area).
    @location(3) normal: vec3<f32>,
};

fn lung_colour(lung: f32) -> vec3<f32> {
    // A tumour (w = 2, renderer/src/tumour.rs): yellow-green, far from the lungs' hues.
    if (lung > 1.5) {
        return vec3<f32>(0.62, 0.95, 0.22);
    }
    // Right lung slightly warmer than the left, so the two read apart in an overlay.
    return select(vec3<f32>(0.93, 0.52, 0.50), vec3<f32>(0.88, 0.50, 0.62), lung > 0.5);
}

fn shade(n_in: vec3<f32>, world: vec3<f32>, lung: f32) -> vec4<f32> {
    let to_eye = normalize(eye.eye_pos.xyz - world);
    // Face the viewer (a silhouette vertex's interpolated normal may point slightly away).
    let n = select(-n_in, n_in, dot(n_in, to_eye) >= 0.0);
    let light = normalize(to_eye + vec3<f32>(0.0, 0.0, 0.6));
    let diffuse = max(dot(n, light), 0.0);
    let h = normalize(light + to_eye);
    let spec = pow(max(dot(n, h), 0.0), 40.0) * 0.25;
    let rim = pow(1.0 - max(dot(n, to_eye), 0.0), 3.0) * 0.25;
    let c = lung_colour(lung) * (0.22 + 0.78 * diffuse) + vec3<f32>(spec + rim);
    return vec4<f32>(c, 1.0);
}

@vertex
fn vs_triangles(@location(0) p: vec4<f32>, @location(1) n: vec4<f32>) -> VsOut {
    var out: VsOut;
    let world = eye.model * vec4<f32>(p.xyz, 1.0);
    out.clip = eye.view_proj * world;
    out.world = world.xyz;
    out.lung = p.w;
    out.corner = vec2<f32>(0.0, 0.0);
    // The registration is a rigid transform: its upper 3×3 rotates normals.
    out.normal = (eye.model * vec4<f32>(n.xyz, 0.0)).xyz;
    return out;
}

@fragment
fn fs_triangles(in: VsOut) -> @location(0) vec4<f32> {
    let len = length(in.normal);
    var n = in.normal / max(len, 1e-20);
    if (len < 0.5) {
        // A vertex with no area around it (degenerate neighbourhood): the face's own normal.
        n = normalize(cross(dpdx(in.world), dpdy(in.world)));
    }
    return shade(n, in.world, in.lung);
}

// Two triangles per splat, expanded from the instance's deformed position.
const CORNERS = array<vec2<f32>, 6>(
    vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, -1.0), vec2<f32>(1.0, 1.0),
    vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, 1.0), vec2<f32>(-1.0, 1.0),
);

@vertex
fn vs_splats(@builtin(vertex_index) vi: u32, @location(0) p: vec4<f32>) -> VsOut {
    var out: VsOut;
    let corner = CORNERS[vi];
    let radius = eye.cam_right.w;
    let centre = eye.model * vec4<f32>(p.xyz, 1.0);
    let world = centre.xyz + (eye.cam_right.xyz * corner.x + eye.cam_up.xyz * corner.y) * radius;
    out.clip = eye.view_proj * vec4<f32>(world, 1.0);
    out.world = world;
    out.lung = p.w;
    out.corner = corner;
    out.normal = vec3<f32>(0.0, 0.0, 0.0);
    return out;
}

@fragment
fn fs_splats(in: VsOut) -> @location(0) vec4<f32> {
    let r2 = dot(in.corner, in.corner);
    if (r2 > 1.0) {
        discard;
    }
    // Sphere impostor normal in the camera's frame.
    let to_eye = normalize(eye.eye_pos.xyz - in.world);
    let n = normalize(eye.cam_right.xyz * in.corner.x + eye.cam_up.xyz * in.corner.y + to_eye * sqrt(1.0 - r2));
    return shade(n, in.world, in.lung);
}
