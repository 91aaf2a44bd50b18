//! The per-frame deformation compute pass (`deform.wgsl`): `p' = p + s_lung · u + o_lung` for every
//! vertex of both lungs, once per frame, into a buffer both eyes draw from (the seed deformed per
//! eye in the vertex shader and lost half its stereo rate).

use wgpu::util::DeviceExt;

use lung_model::deform::LungModel;

/// Threads per workgroup; must match `@workgroup_size` in `deform.wgsl`.
pub const WORKGROUP: u32 = 256;

/// Uniform block of `deform.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DeformParams {
    /// Scale per lung slot (right, left, unused, unused).
    pub scale: [f32; 4],
    /// Rigid offset per lung slot (xyz mm, w unused): right, then left.
    pub offset: [[f32; 4]; 2],
    /// Vertex count.
    pub count: u32,
    /// Padding to 16 bytes.
    pub _pad: [u32; 3],
}

/// GPU buffers and pipeline of the deformation pass.
pub struct DeformPass {
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    params: wgpu::Buffer,
    /// Deformed positions (xyz mm, w lung index): the vertex buffer of the draw passes.
    pub deformed: wgpu::Buffer,
    /// Vertex count over all lungs.
    pub count: u32,
}

/// Interleave the lungs' FRC positions (w = lung index) and unit displacements for the GPU.
pub fn vertex_arrays(lungs: &[LungModel]) -> (Vec<[f32; 4]>, Vec<[f32; 4]>) {
    let mut base = Vec::new();
    let mut unit = Vec::new();
    for lung in lungs {
        let w = lung.side.index() as f32;
        base.extend(lung.mesh.positions.iter().map(|p| [p[0], p[1], p[2], w]));
        unit.extend(
            lung.unit_displacement
                .iter()
                .map(|u| [u[0], u[1], u[2], 0.0]),
        );
    }
    (base, unit)
}

impl DeformPass {
    /// Upload `lungs` and build the pass.
    pub fn new(device: &wgpu::Device, lungs: &[LungModel]) -> Self {
        let (base, unit) = vertex_arrays(lungs);
        let count = base.len() as u32;
        let storage = |label, data: &[[f32; 4]]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let base_buf = storage("lungdyn base positions", &base);
        let unit_buf = storage("lungdyn unit displacement", &unit);
        let deformed = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn deformed positions"),
            contents: bytemuck::cast_slice(&base),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::VERTEX
                | wgpu::BufferUsages::COPY_SRC,
        });
        let params = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn deform params"),
            contents: bytemuck::bytes_of(&DeformParams {
                scale: [0.0; 4],
                offset: [[0.0; 4]; 2],
                count,
                _pad: [0; 3],
            }),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let module = device.create_shader_module(wgpu::include_wgsl!("deform.wgsl"));
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("lungdyn deform"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("lungdyn deform"),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: base_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: unit_buf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: deformed.as_entire_binding(),
                },
            ],
        });
        Self {
            pipeline,
            bind_group,
            params,
            deformed,
            count,
        }
    }

    /// Set this frame's per-lung scales and rigid offsets (right, left).
    pub fn set_lungs(&self, queue: &wgpu::Queue, scales: [f32; 2], offsets: [[f32; 3]; 2]) {
        let o = |v: [f32; 3]| [v[0], v[1], v[2], 0.0];
        let p = DeformParams {
            scale: [scales[0], scales[1], 0.0, 0.0],
            offset: [o(offsets[0]), o(offsets[1])],
            count: self.count,
            _pad: [0; 3],
        };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&p));
    }

    /// Record the compute pass.
    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("lungdyn deform"),
            timestamp_writes: timestamps,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.dispatch_workgroups(self.count.div_ceil(WORKGROUP), 1, 1);
    }
}
