//! Draw pipelines (`draw.wgsl`): smooth-shaded triangles from the deformed vertex and normal buffers
//! with the lungs' index buffer, or one camera-facing splat per vertex (instanced quads).

use crate::camera::EyeUniform;

/// Colour format of the offscreen target (sRGB bytes, what a PNG stores).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// The two pipelines and the per-eye uniform bindings.
pub struct DrawPipelines {
    /// Shaded triangles.
    pub triangles: wgpu::RenderPipeline,
    /// Point splats.
    pub splats: wgpu::RenderPipeline,
    /// The tumour: shaded triangles drawn through the lung surface (no depth test or write).
    pub tumour: wgpu::RenderPipeline,
    /// Uniform buffer per eye (left/mono, right).
    pub eye_buffers: [wgpu::Buffer; 2],
    /// Bind group per eye.
    pub eye_groups: [wgpu::BindGroup; 2],
}

impl DrawPipelines {
    /// Build both pipelines.
    pub fn new(device: &wgpu::Device) -> Self {
        let module = device.create_shader_module(wgpu::include_wgsl!("draw.wgsl"));
        let layout_bg = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("lungdyn eye"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lungdyn draw"),
            bind_group_layouts: &[Some(&layout_bg)],
            immediate_size: 0,
        });
        let position = [wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Float32x4,
            offset: 0,
            shader_location: 0,
        }];
        let normal = [wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Float32x4,
            offset: 0,
            shader_location: 1,
        }];
        let with_normals = [
            Some(wgpu::VertexBufferLayout {
                array_stride: 16,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &position,
            }),
            Some(wgpu::VertexBufferLayout {
                array_stride: 16,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &normal,
            }),
        ];
        let instanced = [Some(wgpu::VertexBufferLayout {
            array_stride: 16,
            step_mode: wgpu::VertexStepMode::Instance,
            attributes: &position,
        })];
        let pipeline = |label,
                        vs,
                        fs,
                        buffers: &[Option<wgpu::VertexBufferLayout<'_>>],
                        cull_mode,
                        through: bool| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &module,
                    entry_point: Some(vs),
                    compilation_options: Default::default(),
                    buffers,
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    front_face: wgpu::FrontFace::Ccw,
                    cull_mode,
                    ..Default::default()
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(!through),
                    depth_compare: Some(if through {
                        wgpu::CompareFunction::Always
                    } else {
                        wgpu::CompareFunction::Less
                    }),
                    stencil: Default::default(),
                    bias: Default::default(),
                }),
                multisample: Default::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &module,
                    entry_point: Some(fs),
                    compilation_options: Default::default(),
                    targets: &[Some(wgpu::ColorTargetState {
                        format: COLOR_FORMAT,
                        blend: None,
                        write_mask: wgpu::ColorWrites::ALL,
                    })],
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        // Closed, outward-wound surfaces: back faces are never visible, cull them.
        let triangles = pipeline(
            "lungdyn triangles",
            "vs_triangles",
            "fs_triangles",
            &with_normals,
            Some(wgpu::Face::Back),
            false,
        );
        let splats = pipeline(
            "lungdyn splats",
            "vs_splats",
            "fs_splats",
            &instanced,
            None,
            false,
        );
        let tumour = pipeline(
            "lungdyn tumour",
            "vs_triangles",
            "fs_triangles",
            &with_normals,
            Some(wgpu::Face::Back),
            true,
        );
        let eye_buffer = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: std::mem::size_of::<EyeUniform>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let eye_buffers = [eye_buffer("lungdyn eye 0"), eye_buffer("lungdyn eye 1")];
        let group = |b: &wgpu::Buffer| {
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("lungdyn eye"),
                layout: &layout_bg,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: b.as_entire_binding(),
                }],
            })
        };
        let eye_groups = [group(&eye_buffers[0]), group(&eye_buffers[1])];
        Self {
            triangles,
            splats,
            tumour,
            eye_buffers,
            eye_groups,
        }
    }
}
