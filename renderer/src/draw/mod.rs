//! Draw pipelines (`draw.wgsl`, `composite.wgsl`): smooth-shaded triangles from the deformed vertex
//! and normal buffers with the lungs' index buffer, or one camera-facing splat per vertex
//! (instanced quads), in the scene's look, at the scene's MSAA sample count.
//!
//! A frame draws in phases (`LungRenderer::render_with`): **opaque** (depth written), then
//! **translucent** (depth tested, not written: weighted blended OIT targets and their composite, or
//! additive light), then **overlay** (no depth test: what must show whatever is in front of it).
//! What falls in which phase depends on the look:
//!
//! | look        | opaque        | translucent                    | overlay |
//! |-------------|---------------|--------------------------------|---------|
//! | opaque      | lungs         | —                              | tumour  |
//! | translucent | tumour        | lungs (OIT, fresnel rim)       | —       |
//! | see-through | tumour        | lungs (additive light)         | —       |
//!
//! Every vertex carries a [`SurfaceAttr`]: its [`Material`] (what it is) instead of a code hidden
//! in the position's `w`, its lobe code (0 unknown, 1 RUL, 2 RML, 3 RLL, 4 LUL, 5 LLL) and whether
//! it lies on a fissure (a triangle of it spans two lobes).
//!
//! **Lobes colour mode**: every lung vertex also carries its signed distances from the oblique and
//! horizontal fissure planes (normalised lung coordinates over the rest mesh's bounding box, the
//! planes its lobe codes were classified by: `lung_model::mesh::lobes`). They are affine in the
//! rest position, so interpolated across a triangle they are exact: the fragment shader colours by
//! their signs and draws each fissure where its distance crosses zero, about 2 px wide whatever
//! the distance (`fwidth`: screen-space derivatives, which lavapipe and every GPU have). The line is
//! straight across each triangle and continuous across its edges — a smooth curve on the surface,
//! not the zig-zag along triangle edges that interpolated per-vertex lobe codes gave — drawn in
//! every look and eye with no extra pass or geometry. Splats have no triangle to interpolate over:
//! a splat on a fissure vertex (a triangle of it spans two lobes) is drawn in the line colour.
//! Dark lines on the opaque and translucent looks; light lines on the see-through look (an
//! additive display shows dark as nothing).

use lung_model::scene::{ColorMode, DrawMode, Look};

use crate::camera::EyeUniform;

/// What a frame draws ([`phases`]): the lungs (the look's pipeline) or every tumour. The HUD is not
/// one: it is drawn over the finished frame (`hud`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Drawable {
    /// Both lungs.
    Lungs,
    /// Every tumour.
    Tumours,
}

/// A look's phases as the encoder runs them (the table above as data): what the first render pass
/// draws, in order — the opaque phase, then what needs no targets of its own (the overlay drawn
/// without depth test, the see-through look's additive light) — and what the OIT pass draws
/// (weighted blended targets, then their composite; empty: no such pass).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Phases {
    /// The first pass's drawables, in drawing order.
    pub first_pass: &'static [Drawable],
    /// The OIT pass's drawables.
    pub oit: &'static [Drawable],
}

/// The phases of `look`.
pub const fn phases(look: Look) -> Phases {
    use Drawable::{Lungs, Tumours};
    match look {
        // Opaque lungs, then the tumour as an overlay through the lungs it lies inside.
        Look::Opaque => Phases {
            first_pass: &[Lungs, Tumours],
            oit: &[],
        },
        // The opaque tumour, then the lungs' light added over it.
        Look::SeeThrough => Phases {
            first_pass: &[Tumours, Lungs],
            oit: &[],
        },
        // The opaque tumour; the lungs blended order-independently over it.
        Look::Translucent => Phases {
            first_pass: &[Tumours],
            oit: &[Lungs],
        },
    }
}

/// Colour format of the offscreen target (sRGB bytes, what a PNG stores).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Weighted blended OIT: Σ w·α·c and Σ w·α (half floats: the weights reach 3·10³).
pub const ACCUM_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
/// Weighted blended OIT: Π (1 − α).
pub const REVEAL_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R8Unorm;

/// The winding of a mesh triangle seen from outside, in clip space, under a model matrix of
/// determinant `model_determinant`: the meshes wind counter-clockwise seen from outside in the
/// body frame ([`lung_model::mesh::TriMesh`]); a reflection (negative determinant) reverses that.
pub const fn front_face(model_determinant: f64) -> wgpu::FrontFace {
    if model_determinant < 0.0 {
        wgpu::FrontFace::Cw
    } else {
        wgpu::FrontFace::Ccw
    }
}

/// The front face of every pipeline here: the lungs and the tumour are drawn through the body →
/// room model matrix (`camera::Rig::model`), whose determinant is always
/// [`lung_model::frame::BODY_TO_RAS_DETERMINANT`] (−1: the body frame is left-handed, issue 19).
/// Splats are built in the room from the camera's axes and are never culled, so their winding does
/// not matter.
pub const MESH_FRONT_FACE: wgpu::FrontFace = front_face(lung_model::frame::BODY_TO_RAS_DETERMINANT);

/// What a vertex is: `draw.wgsl` picks its colour by this (the first byte of [`SurfaceAttr`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Material {
    /// The right lung (slot 0).
    RightLung = 0,
    /// The left lung (slot 1).
    LeftLung = 1,
    /// A tumour.
    Tumour = 2,
}

impl Material {
    /// The lung of slot `slot` (0 right, 1 left).
    pub fn lung(slot: usize) -> Self {
        if slot == 1 {
            Material::LeftLung
        } else {
            Material::RightLung
        }
    }
}

/// Per-vertex surface attribute: `attr` (`Uint8x4`, location 2) is the material, lobe code (0 =
/// unknown), fissure flag (1: a triangle of this vertex spans two lobes) and one reserved byte;
/// `fissure_d` (`Snorm16x2`, location 7) the vertex's signed distances from the oblique and
/// horizontal fissure planes in normalised lung coordinates
/// (`lung_model::mesh::lobes::Fissures::signed`, each within ±1), 0 without lobes.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct SurfaceAttr {
    /// Material, lobe code, fissure flag, reserved.
    pub attr: [u8; 4],
    /// Signed fissure distances as snorm16.
    pub fissure_d: [i16; 2],
}

/// The attribute of a vertex of `material` with lobe code `lobe`, on a fissure or not (no fissure
/// distances).
pub fn surface(material: Material, lobe: u8, fissure: bool) -> SurfaceAttr {
    SurfaceAttr {
        attr: [material as u8, lobe, fissure as u8, 0],
        fissure_d: [0; 2],
    }
}

/// The surface attributes of one lung of rest `positions` in slot `slot`: with `lobes` (one code
/// per vertex: [`crate::RenderLung::lobe_codes`]), each vertex's code, whether a triangle of it
/// spans two lobes, and its signed distances from the fissure planes over the rest mesh's bounding
/// box (the planes the codes were classified by: `lung_model::mesh::lobes::classify`); without,
/// code 0.
pub fn lung_surface(
    slot: usize,
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    lobes: Option<&[u8]>,
) -> Vec<SurfaceAttr> {
    use lung_model::mesh::{lobes as lb, Side};
    let material = Material::lung(slot);
    let Some(codes) = lobes else {
        return vec![surface(material, 0, false); positions.len()];
    };
    let side = if slot == 1 { Side::Left } else { Side::Right };
    let snorm = |d: f64| (d.clamp(-1.0, 1.0) * 32767.0).round() as i16;
    let mut out: Vec<SurfaceAttr> = codes
        .iter()
        .zip(lb::fissure_distances(side, positions))
        .map(|(&c, d)| SurfaceAttr {
            fissure_d: d.map(snorm),
            ..surface(material, c, false)
        })
        .collect();
    for t in triangles {
        let [a, b, c] = t.map(|i| i as usize);
        if codes[a] != codes[b] || codes[b] != codes[c] {
            for i in [a, b, c] {
                out[i].attr[2] = 1;
            }
        }
    }
    out
}

/// Uniform block `Style` of `draw.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct StyleUniform {
    /// 0 tissue, 1 displacement, 2 ventilation, 3 lobes.
    pub color_mode: u32,
    /// Padding to 16 bytes.
    pub _pad: [u32; 3],
    /// Linear-light albedo per lobe code (0 unknown .. 5 left lower): `Lobe::colour`.
    pub lobes: [[f32; 4]; 6],
}

/// An sRGB byte as linear light.
pub fn srgb_to_linear(c: u8) -> f32 {
    let c = c as f32 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

impl StyleUniform {
    /// The style of `color`.
    pub fn new(color: ColorMode) -> Self {
        use lung_model::mesh::lobes::Lobe;
        let mut lobes = [[0.0; 4]; 6];
        for (code, slot) in lobes.iter_mut().enumerate() {
            let lobe = Lobe::from_code(code as u8).unwrap_or(Lobe::Unknown);
            let [r, g, b] = lobe.colour().map(srgb_to_linear);
            *slot = [r, g, b, 1.0];
        }
        Self {
            color_mode: match color {
                ColorMode::Tissue => 0,
                ColorMode::Displacement => 1,
                ColorMode::Ventilation => 2,
                ColorMode::Lobes => 3,
            },
            _pad: [0; 3],
            lobes,
        }
    }
}

/// How a pipeline uses depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Depth {
    /// Test and write (opaque phase).
    Write,
    /// Test, do not write (translucent phase).
    Test,
    /// Neither (overlay phase).
    Ignore,
}

/// The pipelines of one (draw mode, look, sample count) and the per-eye uniform bindings.
pub struct DrawPipelines {
    /// The lungs in the look's pipeline (opaque, OIT or additive; triangles or splats).
    pub lungs: wgpu::RenderPipeline,
    /// The tumour, in the phase the look puts it in.
    pub tumour: wgpu::RenderPipeline,
    /// Translucent look: the composite of the OIT targets (its bind group layout).
    pub composite: Option<(wgpu::RenderPipeline, wgpu::BindGroupLayout)>,
    /// Uniform buffer per eye (left/mono, right).
    pub eye_buffers: [wgpu::Buffer; 2],
    /// The colour mode's uniform (shared by both eyes).
    pub style: wgpu::Buffer,
    /// Bind group per eye.
    pub eye_groups: [wgpu::BindGroup; 2],
}

impl DrawPipelines {
    /// Build the pipelines for `mode` in `look` with `samples` per pixel, colouring by `color`.
    pub fn new(
        device: &wgpu::Device,
        mode: DrawMode,
        look: Look,
        color: ColorMode,
        samples: u32,
    ) -> Self {
        let uniform = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let layout_bg = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lungdyn eye"),
            entries: &[uniform(0), uniform(1)],
        });
        let b = Builder {
            device,
            module: device.create_shader_module(wgpu::include_wgsl!("draw.wgsl")),
            layout: device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("lungdyn draw"),
                bind_group_layouts: &[Some(&layout_bg)],
                immediate_size: 0,
            }),
            multisample: wgpu::MultisampleState {
                count: samples,
                ..Default::default()
            },
        };
        let lungs = lung_pipeline(&b, mode, look);
        // The tumour: drawn through the opaque lungs it lies inside (the planner's target), a
        // solid body inside the translucent or glowing ones.
        let tumour = b.pipeline(
            "lungdyn tumour",
            ("vs_triangles", "fs_opaque_triangles"),
            &vertex_buffers(wgpu::VertexStepMode::Vertex),
            Some(wgpu::Face::Back),
            if look == Look::Opaque {
                Depth::Ignore
            } else {
                Depth::Write
            },
            &[colour_target(None)],
        );
        let composite = (look == Look::Translucent).then(|| composite(device));
        let (eye_buffers, style, eye_groups) = eye_bindings(device, &layout_bg, color);
        Self {
            lungs,
            tumour,
            composite,
            eye_buffers,
            style,
            eye_groups,
        }
    }
}

/// The vertex attributes of the three vertex buffers: position (0), normal (1; w the colour
/// field), surface attribute (2: material and lobe; 7: fissure distances).
const VERTEX_ATTRIBUTES: [&[wgpu::VertexAttribute]; 3] = [
    &[wgpu::VertexAttribute {
        format: wgpu::VertexFormat::Float32x4,
        offset: 0,
        shader_location: 0,
    }],
    &[wgpu::VertexAttribute {
        format: wgpu::VertexFormat::Float32x4,
        offset: 0,
        shader_location: 1,
    }],
    &[
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Uint8x4,
            offset: 0,
            shader_location: 2,
        },
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Snorm16x2,
            offset: 4,
            shader_location: 7,
        },
    ],
];

/// Position, normal, surface attribute: per vertex for triangles, per instance for splats.
fn vertex_buffers(
    step_mode: wgpu::VertexStepMode,
) -> Vec<Option<wgpu::VertexBufferLayout<'static>>> {
    [16u64, 16, std::mem::size_of::<SurfaceAttr>() as u64]
        .iter()
        .zip(&VERTEX_ATTRIBUTES)
        .map(|(&stride, a)| {
            Some(wgpu::VertexBufferLayout {
                array_stride: stride,
                step_mode,
                attributes: a,
            })
        })
        .collect()
}

/// The colour target in [`COLOR_FORMAT`] with `blend`.
fn colour_target(blend: Option<wgpu::BlendState>) -> Option<wgpu::ColorTargetState> {
    Some(wgpu::ColorTargetState {
        format: COLOR_FORMAT,
        blend,
        write_mask: wgpu::ColorWrites::ALL,
    })
}

/// Light (or weight) that adds: `src + dst`.
const ADDITIVE: wgpu::BlendComponent = wgpu::BlendComponent {
    src_factor: wgpu::BlendFactor::One,
    dst_factor: wgpu::BlendFactor::One,
    operation: wgpu::BlendOperation::Add,
};

/// What every draw pipeline shares: `draw.wgsl`, the eye's layout, the sample count.
struct Builder<'d> {
    device: &'d wgpu::Device,
    module: wgpu::ShaderModule,
    layout: wgpu::PipelineLayout,
    multisample: wgpu::MultisampleState,
}

impl Builder<'_> {
    /// A triangle-list pipeline of `(vertex, fragment)` entry points.
    fn pipeline(
        &self,
        label: &str,
        (vs, fs): (&str, &str),
        buffers: &[Option<wgpu::VertexBufferLayout<'_>>],
        cull_mode: Option<wgpu::Face>,
        depth: Depth,
        targets: &[Option<wgpu::ColorTargetState>],
    ) -> wgpu::RenderPipeline {
        self.device
            .create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&self.layout),
                vertex: wgpu::VertexState {
                    module: &self.module,
                    entry_point: Some(vs),
                    compilation_options: Default::default(),
                    buffers,
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    front_face: MESH_FRONT_FACE,
                    cull_mode,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(depth == Depth::Write),
                    depth_compare: Some(if depth == Depth::Ignore {
                        wgpu::CompareFunction::Always
                    } else {
                        wgpu::CompareFunction::Less
                    }),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: self.multisample,
                fragment: Some(wgpu::FragmentState {
                    module: &self.module,
                    entry_point: Some(fs),
                    compilation_options: Default::default(),
                    targets,
                }),
                multiview_mask: None,
                cache: None,
            })
    }
}

/// The lungs' pipeline in `look`: opaque, OIT (weighted blended targets) or additive light;
/// triangles or splats.
fn lung_pipeline(b: &Builder<'_>, mode: DrawMode, look: Look) -> wgpu::RenderPipeline {
    let (vs, buffers) = match mode {
        DrawMode::Triangles => ("vs_triangles", vertex_buffers(wgpu::VertexStepMode::Vertex)),
        DrawMode::Points => ("vs_splats", vertex_buffers(wgpu::VertexStepMode::Instance)),
    };
    let fs = |triangles, splats| match mode {
        DrawMode::Triangles => triangles,
        DrawMode::Points => splats,
    };
    // Closed, outward-wound surfaces: an opaque one's back faces are never visible. The
    // translucent look shows them (the far wall through the near one); splats have no faces.
    let cull = |back: bool| (back && mode == DrawMode::Triangles).then_some(wgpu::Face::Back);
    match look {
        Look::Opaque => b.pipeline(
            "lungdyn lungs opaque",
            (vs, fs("fs_opaque_triangles", "fs_opaque_splats")),
            &buffers,
            cull(true),
            Depth::Write,
            &[colour_target(None)],
        ),
        Look::Translucent => b.pipeline(
            "lungdyn lungs translucent",
            (vs, fs("fs_oit_triangles", "fs_oit_splats")),
            &buffers,
            cull(false),
            Depth::Test,
            &[
                Some(wgpu::ColorTargetState {
                    format: ACCUM_FORMAT,
                    blend: Some(wgpu::BlendState {
                        color: ADDITIVE,
                        alpha: ADDITIVE,
                    }),
                    write_mask: wgpu::ColorWrites::ALL,
                }),
                Some(wgpu::ColorTargetState {
                    format: REVEAL_FORMAT,
                    blend: Some(wgpu::BlendState {
                        color: wgpu::BlendComponent {
                            src_factor: wgpu::BlendFactor::Zero,
                            dst_factor: wgpu::BlendFactor::OneMinusSrc,
                            operation: wgpu::BlendOperation::Add,
                        },
                        alpha: wgpu::BlendComponent::REPLACE,
                    }),
                    write_mask: wgpu::ColorWrites::ALL,
                }),
            ],
        ),
        // Light adds: the order of the surfaces does not matter, the near wall alone shows
        // the outline (back faces culled).
        Look::SeeThrough => b.pipeline(
            "lungdyn lungs see-through",
            (vs, fs("fs_glow_triangles", "fs_glow_splats")),
            &buffers,
            cull(true),
            Depth::Test,
            &[colour_target(Some(wgpu::BlendState {
                color: ADDITIVE,
                alpha: ADDITIVE,
            }))],
        ),
    }
}

/// Each eye's uniform buffer, the colour mode's uniform, and each eye's bind group over both.
fn eye_bindings(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    color: ColorMode,
) -> ([wgpu::Buffer; 2], wgpu::Buffer, [wgpu::BindGroup; 2]) {
    let eye_buffer = |label| {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: std::mem::size_of::<EyeUniform>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    };
    let eye_buffers = [eye_buffer("lungdyn eye 0"), eye_buffer("lungdyn eye 1")];
    let style = wgpu::util::DeviceExt::create_buffer_init(
        device,
        &wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn style"),
            contents: bytemuck::bytes_of(&StyleUniform::new(color)),
            usage: wgpu::BufferUsages::UNIFORM,
        },
    );
    let group = |b: &wgpu::Buffer| {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lungdyn eye"),
            layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: b.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: style.as_entire_binding(),
                },
            ],
        })
    };
    let eye_groups = [group(&eye_buffers[0]), group(&eye_buffers[1])];
    (eye_buffers, style, eye_groups)
}

/// The OIT composite: a fullscreen triangle reading the (resolved) accumulation and revealage
/// textures, blended over the resolved (single-sample) colour target by the layers' coverage. Its
/// inputs are per pixel, and blending is linear in the destination, so blending over the resolved
/// opaque image gives the average of blending over each sample (to rounding) for a quarter of the
/// work at 4× MSAA.
fn composite(device: &wgpu::Device) -> (wgpu::RenderPipeline, wgpu::BindGroupLayout) {
    let module = device.create_shader_module(wgpu::include_wgsl!("composite.wgsl"));
    let texture = |binding| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::FRAGMENT,
        ty: wgpu::BindingType::Texture {
            sample_type: wgpu::TextureSampleType::Float { filterable: false },
            view_dimension: wgpu::TextureViewDimension::D2,
            multisampled: false,
        },
        count: None,
    };
    let bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("lungdyn composite"),
        entries: &[texture(0), texture(1)],
    });
    let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some("lungdyn composite"),
        bind_group_layouts: &[Some(&bgl)],
        immediate_size: 0,
    });
    let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("lungdyn composite"),
        layout: Some(&layout),
        vertex: wgpu::VertexState {
            module: &module,
            entry_point: Some("vs_fullscreen"),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: Default::default(),
        depth_stencil: None,
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module: &module,
            entry_point: Some("fs_composite"),
            compilation_options: Default::default(),
            targets: &[Some(wgpu::ColorTargetState {
                format: COLOR_FORMAT,
                blend: Some(wgpu::BlendState::ALPHA_BLENDING),
                write_mask: wgpu::ColorWrites::ALL,
            })],
        }),
        multiview_mask: None,
        cache: None,
    });
    (pipeline, bgl)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::{generate, lobes, Side};

    /// The fissure distances' signs give every vertex the lobe its code says (so the shader's
    /// colour by sign is the lobe data's), and they are exact snorm16 values of the planes.
    #[test]
    fn fissure_distances_agree_with_the_lobe_codes() {
        for (slot, side) in [(0, Side::Right), (1, Side::Left)] {
            let mesh = generate::lung(side, 2_000).unwrap();
            let codes = lobes::classify(side, &mesh);
            let attrs = lung_surface(slot, &mesh.positions, &mesh.triangles, Some(&codes));
            let mut crossing = 0;
            for (a, &code) in attrs.iter().zip(&codes) {
                assert_eq!(a.attr[1], code);
                let [o, h] = a.fissure_d;
                let lobe = match (side, o > 0) {
                    (Side::Left, true) => lobes::Lobe::LeftLower,
                    (Side::Left, false) => lobes::Lobe::LeftUpper,
                    (Side::Right, true) => lobes::Lobe::RightLower,
                    (Side::Right, false) if h > 0 => lobes::Lobe::RightMiddle,
                    (Side::Right, false) => lobes::Lobe::RightUpper,
                };
                assert_eq!(lobe.code(), code, "{side:?} {:?}", a.fissure_d);
                if side == Side::Left {
                    assert_eq!(h, 0, "no horizontal fissure on the left");
                }
                crossing += usize::from(a.attr[2] == 1);
            }
            assert!(crossing > 0, "{side:?}: some triangles span two lobes");
        }
        // Without lobe codes: code 0, no distances.
        let mesh = generate::lung(Side::Left, 200).unwrap();
        let attrs = lung_surface(1, &mesh.positions, &mesh.triangles, None);
        assert!(attrs
            .iter()
            .all(|a| *a == surface(Material::LeftLung, 0, false)));
    }
}

#[cfg(test)]
mod phase_tests {
    use super::*;

    /// Every look draws the lungs once and the tumours once; only the translucent look has an OIT
    /// pass (the renderer makes its targets and composite for that look alone: `DrawPipelines`).
    #[test]
    fn every_look_draws_each_drawable_once_and_only_translucent_blends() {
        for look in Look::ALL {
            let p = phases(look);
            let all: Vec<Drawable> = p.first_pass.iter().chain(p.oit).copied().collect();
            for d in [Drawable::Lungs, Drawable::Tumours] {
                assert_eq!(all.iter().filter(|x| **x == d).count(), 1, "{look:?} {d:?}");
            }
            assert_eq!(!p.oit.is_empty(), look == Look::Translucent, "{look:?}");
        }
    }
}
