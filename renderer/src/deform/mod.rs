//! The per-frame deformation compute pass (`deform.wgsl`): every vertex of both lungs in the scene's
//! mode (precomputed, basis, sh or direct — EQUATIONS.md §2.4, §3), then smooth vertex normals from
//! the moved positions, once per frame, into the buffers every eye draws from (the seed deformed
//! per eye in the vertex shader and lost half its stereo rate). Only the mode's data is uploaded.

use wgpu::util::DeviceExt;

use ipc_types::MAX_COEFFS;
use lung_model::deform::modes::{CpuLung, DeformMode, ModeData, ModeLoadError, VertexTriangles};
use lung_model::deform::LungModel;
use lung_model::kernel::KernelFile;
use lung_model::mesh::Side;

/// Threads per workgroup; must match `@workgroup_size` in `deform.wgsl`.
pub const WORKGROUP: u32 = 256;

/// One lung as the renderer holds it: which lung, its kernel's identity and its mode's data.
#[derive(Debug, Clone)]
pub struct RenderLung {
    /// Which lung.
    pub side: Side,
    /// Identity of the kernel it was loaded from (0: built in memory).
    pub kernel_id: u64,
    /// Mesh and mode data (the CPU reference uses the same).
    pub lung: CpuLung,
    /// The tumour the kernel was baked with, drawn in its own colour (seed §8.2).
    pub tumour: Option<lung_model::kernel::TumourMeta>,
    /// Lobe code per vertex ([`lung_model::mesh::lobes::Lobe`]), from the kernel's lobe section;
    /// `None` for a kernel baked before lobes existed (the lobes colour mode then draws the lung
    /// grey and says so).
    pub lobes: Option<Vec<u8>>,
}

impl RenderLung {
    /// The lung of `kernel` in `mode` (only the sections the mode needs are read).
    pub fn from_kernel(kernel: &KernelFile, mode: DeformMode) -> Result<Self, ModeLoadError> {
        Ok(Self {
            side: kernel.meta().side,
            kernel_id: kernel.id(),
            lung: CpuLung::from_kernel(kernel, mode)?,
            tumour: kernel.meta().tumour.clone(),
            lobes: kernel.lobes()?.map(<[u8]>::to_vec),
        })
    }

    /// A precomputed-mode lung from a model built in memory (tests), with the lobe codes a bake
    /// writes for its mesh (`lung_model::mesh::lobes::classify`).
    pub fn from_model(model: &LungModel) -> Self {
        Self {
            side: model.side,
            kernel_id: model.kernel_id,
            lung: CpuLung::new(
                model.mesh.clone(),
                Vec::new(),
                ModeData::Precomputed {
                    unit: model.unit_displacement.clone(),
                },
            ),
            tumour: None,
            lobes: Some(lung_model::mesh::lobes::classify(model.side, &model.mesh)),
        }
    }

    /// The lobe code of every vertex, if the kernel had them (one per vertex; anything else is
    /// treated as none).
    pub fn lobe_codes(&self) -> Option<&[u8]> {
        self.lobes.as_deref().filter(|c| c.len() == self.lung.len())
    }

    /// The deformation mode.
    pub fn mode(&self) -> DeformMode {
        self.lung.data.mode()
    }
}

/// Per vertex, the summed area of its incident triangles, mm² (the expansion field's rest value;
/// `deform.wgsl`'s `vertex_normals` sums the same triangles after deformation).
pub fn incident_areas(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Vec<f32> {
    let mut area = vec![0.0f32; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| glam::Vec3::from(positions[i as usize]));
        let twice = (b - a).cross(c - a).length();
        for &i in t {
            area[i as usize] += 0.5 * twice;
        }
    }
    area
}

/// Uniform block of `deform.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DeformParams {
    /// Scale per lung slot (right, left), then `1 − collapse` per slot (right, left).
    pub scale: [f32; 4],
    /// Rigid offset per lung slot (xyz mm, w unused).
    pub offset: [[f32; 4]; 2],
    /// Force weights per lung slot (basis, direct).
    pub weights: [[f32; 4]; 2],
    /// Vertex count.
    pub count: u32,
    /// The field the normals pass writes into each normal's w ([`Field`] as u32).
    pub field: u32,
    /// Vertices of a draw level's list moved this frame (the governor's "drawn vertices only");
    /// 0: every vertex.
    pub listed: u32,
    /// Padding to 16 bytes.
    pub _pad: u32,
    /// Per slot: first vertex, SH coefficients per vertex, first SH word (two 16-bit coefficients
    /// each), the coefficients summed (fewer than stored where the governor capped the bands; the
    /// frame's force coefficients past them are 0).
    pub lung_info: [[u32; 4]; 2],
    /// SH force coefficients times their index's scale, `F_k·scale_k`, 64 per slot (0 past the
    /// lung's count).
    pub sh_f: [[f32; 4]; 32],
}

/// Why the lungs cannot be put on this GPU.
#[derive(Debug, thiserror::Error)]
pub enum UploadError {
    /// A buffer is larger than the adapter allows.
    #[error("the {what} need a {mib:.0} MiB GPU buffer, the adapter ({adapter}) allows {limit_mib:.0} MiB; use a lighter [lungs] mode (basis or sh), or fewer vertices")]
    TooLarge {
        /// Which data.
        what: &'static str,
        /// Size needed, MiB.
        mib: f64,
        /// Adapter limit, MiB.
        limit_mib: f64,
        /// Adapter.
        adapter: String,
    },
    /// The lungs are in different modes.
    #[error("the lungs are loaded in different modes ({0} and {1})")]
    MixedModes(DeformMode, DeformMode),
    /// An index would not fit 32 bits.
    #[error("the {0} exceed 2^32 entries")]
    Index(&'static str),
}

/// Per-frame inputs of the pass: scale, rigid offset and coefficients per lung slot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungInputs {
    /// Deformation scale per slot (right, left).
    pub scale: [f32; 2],
    /// Rigid offset per slot, mm.
    pub offset: [[f32; 3]; 2],
    /// Collapse towards the hilum per slot, `c ∈ [0, 1]` (EQUATIONS.md §4.1).
    pub collapse: [f32; 2],
    /// The hilum per slot, mm.
    pub hilum: [[f32; 3]; 2],
    /// Coefficients per slot (weights or SH force coefficients, as the mode needs).
    pub coeffs: [[f32; MAX_COEFFS]; 2],
}

/// The per-vertex scalar the normals pass writes into each normal's `w`, for the colour modes
/// (`lung_model::scene::ColorMode`); `draw.wgsl` maps it to a colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[repr(u32)]
pub enum Field {
    /// Nothing (0): the tissue colour needs no field.
    #[default]
    None = 0,
    /// Distance from the rest (FRC) position, mm.
    Displacement = 1,
    /// Local expansion relative to FRC, `(A/A₀)^(3/2) − 1` of the vertex's incident area.
    Expansion = 2,
}

struct Dispatch {
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    /// The buffers bound, kept to bind a draw level's list instead ([`LevelPass`]); empty for a
    /// dispatch that always runs over every vertex (the direct mode's forces).
    bindings: Vec<(u32, wgpu::Buffer)>,
}

/// Binding of a draw level's vertex list in `deform.wgsl`.
const LISTED: u32 = 17;

/// The deformation of one draw level's vertices only (the governor's
/// [`crate::governor::Step::DrawnOnly`]): the vertices its triangles use, and the bind groups
/// that list them, with the normals from its triangles.
struct LevelPass {
    /// Vertices listed.
    count: u32,
    /// Per mode dispatch, its group for this level (`None`: the dispatch's own, over every node).
    groups: Vec<Option<wgpu::BindGroup>>,
    /// The normals' group over this level's triangles.
    normals: Option<wgpu::BindGroup>,
}

/// What the normals pass reads for a draw level: the vertices its triangles use, per such vertex
/// its incident triangles of the level as a CSR, and its incident area at rest.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Incidence {
    /// The vertices, global indices ascending.
    pub vertices: Vec<u32>,
    /// Per listed vertex, its range in `tris` (one more entry than vertices).
    pub ptr: Vec<u32>,
    /// Incident triangles, as their numbers in the list.
    pub tris: Vec<u32>,
    /// Σ of each listed vertex's incident triangles' areas at rest, mm².
    pub rest_area: Vec<f32>,
}

impl Incidence {
    /// The vertices a draw level's `indices` (global, three per triangle) use, their incident
    /// triangles among those, and their incident areas at `rest` (every vertex's rest position).
    pub fn of_level(indices: &[u32], rest: &[[f32; 3]]) -> Self {
        let mut slot = vec![u32::MAX; rest.len()];
        for &i in indices {
            slot[i as usize] = 0;
        }
        let mut vertices = Vec::new();
        for (i, s) in slot.iter_mut().enumerate() {
            if *s == 0 {
                *s = vertices.len() as u32;
                vertices.push(i as u32);
            }
        }
        // The level over its own vertices: the CSR and the areas as the full mesh's are built.
        let local: Vec<[u32; 3]> = indices
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]].map(|i| slot[i as usize]))
            .collect();
        let at_rest: Vec<[f32; 3]> = vertices.iter().map(|&i| rest[i as usize]).collect();
        let VertexTriangles { ptr, tris } = VertexTriangles::of(&local, vertices.len());
        Self {
            rest_area: incident_areas(&at_rest, &local),
            vertices,
            ptr,
            tris,
        }
    }
}

/// Uploads storage buffers within the adapter's binding limit, counting the bytes.
struct Uploader<'d> {
    device: &'d wgpu::Device,
    adapter: &'d str,
    limit: u64,
    uploaded: u64,
}

impl Uploader<'_> {
    /// A storage buffer of `bytes` (`what` names it in the error when it exceeds the limit).
    fn storage(
        &mut self,
        what: &'static str,
        label: &str,
        bytes: &[u8],
        extra: wgpu::BufferUsages,
    ) -> Result<wgpu::Buffer, UploadError> {
        // wgpu refuses zero-sized bindings: keep one element.
        let bytes: &[u8] = if bytes.is_empty() { &[0u8; 16] } else { bytes };
        if bytes.len() as u64 > self.limit {
            return Err(UploadError::TooLarge {
                what,
                mib: bytes.len() as f64 / 1048576.0,
                limit_mib: self.limit as f64 / 1048576.0,
                adapter: self.adapter.to_string(),
            });
        }
        self.uploaded += bytes.len() as u64;
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: wgpu::BufferUsages::STORAGE | extra,
            }))
    }
}

/// Makes a compute dispatch of `deform.wgsl`'s entry points.
struct Maker<'d> {
    device: &'d wgpu::Device,
    module: wgpu::ShaderModule,
}

impl Maker<'_> {
    /// The pipeline of `entry` (an auto layout: exactly the bindings it uses) and its bind group;
    /// an entry point that moves listed vertices binds [`LISTED`] among `bindings`.
    fn make(&self, entry: &str, bindings: &[(u32, &wgpu::Buffer)]) -> Dispatch {
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &self.module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            });
        let group = self.group(&pipeline, entry, bindings);
        let listable = bindings.iter().any(|(b, _)| *b == LISTED);
        Dispatch {
            pipeline,
            group,
            bindings: if listable {
                bindings
                    .iter()
                    .map(|(b, buf)| (*b, (*buf).clone()))
                    .collect()
            } else {
                Vec::new()
            },
        }
    }

    /// A bind group of `pipeline` over `bindings`.
    fn group(
        &self,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        bindings: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
            .iter()
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: *binding,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// `d`'s group with `replace`'s buffers in their bindings' places (`None` for a dispatch
    /// over every node).
    fn regroup(&self, d: &Dispatch, replace: &[(u32, &wgpu::Buffer)]) -> Option<wgpu::BindGroup> {
        if d.bindings.is_empty() {
            return None;
        }
        let bindings: Vec<(u32, &wgpu::Buffer)> = d
            .bindings
            .iter()
            .map(|(b, buf)| {
                let with = replace.iter().find(|(r, _)| r == b).map(|(_, x)| *x);
                (*b, with.unwrap_or(buf))
            })
            .collect();
        Some(self.group(&d.pipeline, "lungdyn drawn level", &bindings))
    }
}

/// The buffers every dispatch binds: the parameters (0), the rest positions (1), the deformed
/// positions (3), and an empty vertex list bound at [`LISTED`] (the shader reads a list only when
/// the frame moves a draw level's vertices, with that level's list bound instead).
struct Shared {
    params: wgpu::Buffer,
    base: wgpu::Buffer,
    deformed: wgpu::Buffer,
    listed: wgpu::Buffer,
}

/// Every lung's per-vertex arrays of one kind, concatenated.
fn vec4s(lungs: &[RenderLung], f: &dyn Fn(&RenderLung) -> Vec<[f32; 4]>) -> Vec<[f32; 4]> {
    lungs.iter().flat_map(f).collect()
}

/// The directions times the force scale (`k·d`), as vec4s.
fn directions(lungs: &[RenderLung], up: &mut Uploader<'_>) -> Result<wgpu::Buffer, UploadError> {
    let kd = vec4s(lungs, &|l| {
        l.lung
            .scaled_directions
            .iter()
            .map(|d| [d[0], d[1], d[2], 0.0])
            .collect()
    });
    up.storage(
        "directions",
        "lungdyn directions",
        bytemuck::cast_slice(&kd),
        wgpu::BufferUsages::empty(),
    )
}

/// The mode's data uploaded and its dispatches (eq. 7.1's two for the direct mode).
fn mode_dispatches(
    mode: DeformMode,
    lungs: &[RenderLung],
    up: &mut Uploader<'_>,
    mk: &Maker<'_>,
    b: &Shared,
) -> Result<Vec<Dispatch>, UploadError> {
    let none = wgpu::BufferUsages::empty();
    Ok(match mode {
        DeformMode::Precomputed => {
            let unit = vec4s(lungs, &|l| match &l.lung.data {
                ModeData::Precomputed { unit } => {
                    unit.iter().map(|u| [u[0], u[1], u[2], 0.0]).collect()
                }
                _ => unreachable!("one mode"),
            });
            let unit = up.storage(
                "unit displacements",
                "lungdyn unit displacement",
                bytemuck::cast_slice(&unit),
                none,
            )?;
            vec![mk.make(
                "deform_precomputed",
                &[
                    (0, &b.params),
                    (1, &b.base),
                    (2, &unit),
                    (3, &b.deformed),
                    (LISTED, &b.listed),
                ],
            )]
        }
        DeformMode::Basis => {
            let g = vec4s(lungs, &|l| match &l.lung.data {
                ModeData::Basis { g } => g.clone(),
                _ => unreachable!("one mode"),
            });
            let g = up.storage(
                "basis responses",
                "lungdyn basis responses",
                bytemuck::cast_slice(&g),
                none,
            )?;
            let kd = directions(lungs, up)?;
            vec![mk.make(
                "deform_basis",
                &[
                    (0, &b.params),
                    (1, &b.base),
                    (3, &b.deformed),
                    (4, &kd),
                    (5, &g),
                    (LISTED, &b.listed),
                ],
            )]
        }
        DeformMode::Sh => {
            // 16-bit integers in pairs, as the CPU holds them (lung_model::deform::sh_coeffs).
            let t: Vec<u32> = lungs
                .iter()
                .flat_map(|l| match &l.lung.data {
                    ModeData::Sh { t } => t.gpu_words(),
                    _ => unreachable!("one mode"),
                })
                .collect();
            let t = up.storage(
                "spherical-harmonic transfer coefficients",
                "lungdyn sh coefficients",
                bytemuck::cast_slice(&t),
                none,
            )?;
            let kd = directions(lungs, up)?;
            vec![mk.make(
                "deform_sh",
                &[
                    (0, &b.params),
                    (1, &b.base),
                    (3, &b.deformed),
                    (4, &kd),
                    (6, &t),
                    (LISTED, &b.listed),
                ],
            )]
        }
        DeformMode::Direct => direct_dispatches(lungs, up, mk, b)?,
    })
}

/// Eq. 7.1 on the GPU: the transfer columns of both lungs as one CSR (source indices offset by the
/// lungs before), the box coordinates, a force buffer; the force pass, then the gather.
fn direct_dispatches(
    lungs: &[RenderLung],
    up: &mut Uploader<'_>,
    mk: &Maker<'_>,
    b: &Shared,
) -> Result<Vec<Dispatch>, UploadError> {
    let none = wgpu::BufferUsages::empty();
    let vertices: usize = lungs.iter().map(|l| l.lung.len()).sum();
    let mut ptr: Vec<u32> = Vec::with_capacity(vertices + 1);
    let mut src: Vec<u32> = Vec::new();
    let mut val: Vec<f32> = Vec::new();
    let mut nhat: Vec<[f32; 4]> = Vec::new();
    ptr.push(0);
    let mut first = 0u32;
    for l in lungs {
        let ModeData::Direct {
            columns, nhat: nh, ..
        } = &l.lung.data
        else {
            unreachable!("one mode")
        };
        let (p, s, v) = columns.raw();
        let at = *ptr.last().unwrap_or(&0) as u64;
        for w in p.windows(2) {
            let end = at + w[1];
            ptr.push(u32::try_from(end).map_err(|_| UploadError::Index("transfer rows"))?);
        }
        src.extend(s.iter().map(|&j| j + first));
        val.extend_from_slice(v);
        nhat.extend_from_slice(nh);
        first += l.lung.len() as u32;
    }
    let ptr = up.storage(
        "transfer rows",
        "lungdyn col ptr",
        bytemuck::cast_slice(&ptr),
        none,
    )?;
    let src = up.storage(
        "transfer rows",
        "lungdyn col src",
        bytemuck::cast_slice(&src),
        none,
    )?;
    let val = up.storage(
        "transfer rows",
        "lungdyn col val",
        bytemuck::cast_slice(&val),
        none,
    )?;
    let nhat = up.storage(
        "box coordinates",
        "lungdyn nhat",
        bytemuck::cast_slice(&nhat),
        none,
    )?;
    let force = up.storage(
        "forces",
        "lungdyn force",
        bytemuck::cast_slice(&vec![0.0f32; vertices]),
        none,
    )?;
    let kd = directions(lungs, up)?;
    Ok(vec![
        mk.make(
            "direct_force",
            &[(0, &b.params), (1, &b.base), (7, &nhat), (8, &force)],
        ),
        mk.make(
            "deform_direct",
            &[
                (0, &b.params),
                (1, &b.base),
                (3, &b.deformed),
                (4, &kd),
                (8, &force),
                (9, &ptr),
                (10, &src),
                (11, &val),
                (LISTED, &b.listed),
            ],
        ),
    ])
}

/// The vertex normals' pass: each vertex's incident triangles (CSR), the triangles, the rest
/// incident areas (for the expansion field).
fn normals_dispatch(
    lungs: &[RenderLung],
    up: &mut Uploader<'_>,
    mk: &Maker<'_>,
    b: &Shared,
    normals: &wgpu::Buffer,
) -> Result<Dispatch, UploadError> {
    let none = wgpu::BufferUsages::empty();
    let mut inc_ptr: Vec<u32> = vec![0];
    let mut inc_tris: Vec<u32> = Vec::new();
    let mut indices: Vec<u32> = Vec::new();
    let mut rest_area: Vec<f32> = Vec::new();
    let (mut vfirst, mut tfirst) = (0u32, 0u32);
    for l in lungs {
        let inc = &l.lung.incidence;
        let at = *inc_ptr.last().unwrap_or(&0);
        inc_ptr.extend(inc.ptr[1..].iter().map(|&p| p + at));
        inc_tris.extend(inc.tris.iter().map(|&t| t + tfirst));
        indices.extend(l.lung.triangles.iter().flat_map(|t| t.map(|v| v + vfirst)));
        rest_area.extend(incident_areas(&l.lung.positions, &l.lung.triangles));
        vfirst += l.lung.len() as u32;
        tfirst += l.lung.triangles.len() as u32;
    }
    let inc_ptr = up.storage(
        "normal data",
        "lungdyn inc ptr",
        bytemuck::cast_slice(&inc_ptr),
        none,
    )?;
    let inc_tris = up.storage(
        "normal data",
        "lungdyn inc tris",
        bytemuck::cast_slice(&inc_tris),
        none,
    )?;
    let indices = up.storage(
        "normal data",
        "lungdyn triangle indices",
        bytemuck::cast_slice(&indices),
        none,
    )?;
    let rest_area = up.storage(
        "normal data",
        "lungdyn rest areas",
        bytemuck::cast_slice(&rest_area),
        none,
    )?;
    Ok(mk.make(
        "vertex_normals",
        &[
            (0, &b.params),
            (1, &b.base),
            (16, &rest_area),
            (3, &b.deformed),
            (12, normals),
            (13, &inc_ptr),
            (14, &inc_tris),
            (15, &indices),
            (LISTED, &b.listed),
        ],
    ))
}

/// The pass over draw level `indices` (global corners, three per triangle) only: its vertex
/// list, the mode dispatches regrouped to list them, the normals from its triangles.
fn level_pass(
    indices: &[u32],
    rest: &[[f32; 3]],
    up: &mut Uploader<'_>,
    mk: &Maker<'_>,
    dispatches: &[Dispatch],
    normals: Option<&Dispatch>,
) -> Result<LevelPass, UploadError> {
    let none = wgpu::BufferUsages::empty();
    let inc = Incidence::of_level(indices, rest);
    let listed = up.storage(
        "draw level data",
        "lungdyn drawn vertices",
        bytemuck::cast_slice(&inc.vertices),
        none,
    )?;
    let groups = dispatches
        .iter()
        .map(|d| mk.regroup(d, &[(LISTED, &listed)]))
        .collect();
    let normals = match normals {
        Some(d) => {
            let buffers = [
                ("lungdyn level inc ptr", bytemuck::cast_slice(&inc.ptr)),
                ("lungdyn level inc tris", bytemuck::cast_slice(&inc.tris)),
                ("lungdyn level indices", bytemuck::cast_slice(indices)),
                (
                    "lungdyn level rest areas",
                    bytemuck::cast_slice(&inc.rest_area),
                ),
            ]
            .map(|(label, bytes)| up.storage("draw level data", label, bytes, none));
            let [ptr, tris, corners, area] = buffers;
            let (ptr, tris, corners, area) = (ptr?, tris?, corners?, area?);
            mk.regroup(
                d,
                &[
                    (13, &ptr),
                    (14, &tris),
                    (15, &corners),
                    (16, &area),
                    (LISTED, &listed),
                ],
            )
        }
        None => None,
    };
    Ok(LevelPass {
        count: inc.vertices.len() as u32,
        groups,
        normals,
    })
}

/// GPU buffers and pipelines of the deformation pass.
pub struct DeformPass {
    mode: DeformMode,
    field: Field,
    dispatches: Vec<Dispatch>,
    normals_pass: Option<Dispatch>,
    /// Per draw level from 1, the pass over its vertices only (empty: not built).
    levels: Vec<LevelPass>,
    params: wgpu::Buffer,
    lung_info: [[u32; 4]; 2],
    /// Per slot, the scale of each SH coefficient index (`T ≈ q·scale/32767`; 0 beyond the lung's
    /// count and in other modes), folded into the frame's force coefficients.
    sh_scale: [[f32; MAX_COEFFS]; 2],
    /// Deformed positions (xyz mm, w lung slot): the vertex buffer of the draw passes.
    pub deformed: wgpu::Buffer,
    /// Smooth vertex normals (xyz, w 0): the draw's second vertex buffer.
    pub normals: wgpu::Buffer,
    /// Vertex count over all lungs.
    pub count: u32,
    /// Bytes uploaded for the mode's data (positions, directions, mode arrays, normals data).
    pub uploaded_bytes: u64,
}

impl DeformPass {
    /// Upload `lungs` (all in one mode) and build the pass; `normals`: also compute vertex normals
    /// each frame (triangle drawing); `field`: the scalar each normal's w carries (a field other
    /// than [`Field::None`] runs the normals pass whatever `normals` says); `levels`: the draw
    /// levels from 1 (global corners, three per triangle) whose vertices alone it may move
    /// ([`Self::encode_at`]; empty: always every vertex).
    pub fn new(
        device: &wgpu::Device,
        adapter: &str,
        lungs: &[RenderLung],
        normals: bool,
        field: Field,
        levels: &[&[u32]],
    ) -> Result<Self, UploadError> {
        let normals = normals || field != Field::None;
        let mode = lungs
            .first()
            .map(RenderLung::mode)
            .unwrap_or(DeformMode::Precomputed);
        if let Some(other) = lungs.iter().map(RenderLung::mode).find(|m| *m != mode) {
            return Err(UploadError::MixedModes(mode, other));
        }
        let mut up = Uploader {
            device,
            adapter,
            limit: device.limits().max_storage_buffer_binding_size as u64,
            uploaded: 0,
        };
        let none = wgpu::BufferUsages::empty();
        // Vertex arrays, both lungs concatenated (w of a position = the lung's slot).
        let mut base: Vec<[f32; 4]> = Vec::new();
        let mut lung_info = [[0u32; 4]; 2];
        let mut sh_first = 0u32;
        let mut sh_scale = [[0.0f32; MAX_COEFFS]; 2];
        for l in lungs {
            let slot = l.side.index();
            let (n_coeffs, words) = match &l.lung.data {
                ModeData::Sh { t } => {
                    sh_scale[slot][..t.n_coeffs()].copy_from_slice(t.scale());
                    (t.n_coeffs() as u32, t.gpu_words_per_vertex() as u32)
                }
                _ => (0, 0),
            };
            lung_info[slot] = [base.len() as u32, n_coeffs, sh_first, n_coeffs];
            sh_first = sh_first
                .checked_add(words.saturating_mul(l.lung.len() as u32))
                .ok_or(UploadError::Index("spherical-harmonic coefficients"))?;
            let w = slot as f32;
            base.extend(l.lung.positions.iter().map(|p| [p[0], p[1], p[2], w]));
        }
        let count = base.len() as u32;
        let drawn = wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_SRC;
        let bufs = Shared {
            params: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("lungdyn deform params"),
                size: std::mem::size_of::<DeformParams>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            base: up.storage(
                "positions",
                "lungdyn base positions",
                bytemuck::cast_slice(&base),
                none,
            )?,
            deformed: up.storage(
                "deformed positions",
                "lungdyn deformed positions",
                bytemuck::cast_slice(&base),
                drawn,
            )?,
            listed: up.storage("draw level data", "lungdyn no list", &[], none)?,
        };
        let normals_buf = up.storage(
            "normals",
            "lungdyn normals",
            bytemuck::cast_slice(&vec![[0.0f32; 4]; base.len()]),
            drawn,
        )?;
        // Entry points and the bindings each uses (auto layouts hold exactly those).
        let maker = Maker {
            device,
            module: device.create_shader_module(wgpu::include_wgsl!("deform.wgsl")),
        };
        let dispatches = mode_dispatches(mode, lungs, &mut up, &maker, &bufs)?;
        let normals_pass = if normals {
            Some(normals_dispatch(
                lungs,
                &mut up,
                &maker,
                &bufs,
                &normals_buf,
            )?)
        } else {
            None
        };
        let rest: Vec<[f32; 3]> = base.iter().map(|p| [p[0], p[1], p[2]]).collect();
        let levels = levels
            .iter()
            .map(|indices| {
                level_pass(
                    indices,
                    &rest,
                    &mut up,
                    &maker,
                    &dispatches,
                    normals_pass.as_ref(),
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            mode,
            field,
            dispatches,
            normals_pass,
            levels,
            params: bufs.params,
            lung_info,
            sh_scale,
            deformed: bufs.deformed,
            normals: normals_buf,
            count,
            uploaded_bytes: up.uploaded,
        })
    }

    /// The mode the pass runs.
    pub fn mode(&self) -> DeformMode {
        self.mode
    }

    /// Whether the pass computes vertex normals.
    pub fn has_normals(&self) -> bool {
        self.normals_pass.is_some()
    }

    /// The pass over draw level `level`'s vertices only, where built (level 0: none).
    fn level(&self, level: usize) -> Option<&LevelPass> {
        level.checked_sub(1).and_then(|k| self.levels.get(k))
    }

    /// Draw levels (from 1) whose vertices alone the pass can move.
    pub fn listed_levels(&self) -> usize {
        self.levels.len()
    }

    /// Vertices the pass moves at `level` ([`Self::encode_at`]): every vertex at level 0 or a
    /// level not built.
    pub fn moved_at(&self, level: usize) -> u32 {
        self.level(level).map_or(self.count, |l| l.count)
    }

    /// Sum at most `bands` spherical-harmonic bands (`bands`² coefficients) per lung from the next
    /// frame on, 0: every band the kernel holds (the governor's accuracy step; nothing in other
    /// modes). The frame's force coefficients past the cap are dropped, so a vertex moves as a
    /// kernel of that many bands would move it with these coefficients.
    pub fn cap_sh_bands(&mut self, bands: u8) {
        let cap = if bands == 0 {
            u32::MAX
        } else {
            u32::from(bands) * u32::from(bands)
        };
        for info in &mut self.lung_info {
            info[3] = info[1].min(cap);
        }
    }

    /// Set this frame's per-lung scales, rigid offsets and coefficients.
    pub fn set_lungs(&self, queue: &wgpu::Queue, inputs: &LungInputs) {
        self.set_lungs_at(queue, inputs, 0);
    }

    /// As [`Self::set_lungs`], for a pass over draw level `level`'s vertices only
    /// ([`Self::encode_at`] with the same level).
    pub fn set_lungs_at(&self, queue: &wgpu::Queue, inputs: &LungInputs, level: usize) {
        // `h + (1 − c)(p − h) + s·u + o = (1 − c)·p + s·u + (o + c·h)`: the shader scales the rest
        // position by `keep = 1 − c` (scale.zw) and the offset carries `c·h`; at c = 0 both are the
        // healthy lung's exactly (×1.0, +0.0).
        let o = |slot: usize| {
            let (v, c, h) = (
                inputs.offset[slot],
                inputs.collapse[slot],
                inputs.hilum[slot],
            );
            if c == 0.0 {
                [v[0], v[1], v[2], 0.0]
            } else {
                [v[0] + c * h[0], v[1] + c * h[1], v[2] + c * h[2], 0.0]
            }
        };
        let mut p = DeformParams {
            scale: [
                inputs.scale[0],
                inputs.scale[1],
                1.0 - inputs.collapse[0],
                1.0 - inputs.collapse[1],
            ],
            offset: [o(0), o(1)],
            weights: [[0.0; 4]; 2],
            count: self.count,
            field: self.field as u32,
            listed: self.level(level).map_or(0, |l| l.count),
            _pad: 0,
            lung_info: self.lung_info,
            sh_f: [[0.0; 4]; 32],
        };
        for slot in 0..2 {
            let c = &inputs.coeffs[slot];
            p.weights[slot] = [c[0], c[1], c[2], c[3]];
            // `F_k·scale_k`: the shader multiplies by `unpack2x16snorm(q) = q/32767` (0 past the
            // lung's coefficient count, so a pad half never meets a stale coefficient).
            // Past the coefficients summed (the governor's cap) 0 as well: the shader's last pair
            // may hold one.
            let summed = self.lung_info[slot][3] as usize;
            for k in 0..MAX_COEFFS {
                let scale = self.sh_scale[slot][k];
                p.sh_f[slot * 16 + k / 4][k % 4] = if scale == 0.0 || k >= summed {
                    0.0
                } else {
                    c[k] * scale
                };
            }
        }
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&p));
    }

    /// Record the compute pass: the mode's dispatches, then the normals.
    pub fn encode(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
    ) {
        self.encode_at(encoder, timestamps, 0);
    }

    /// As [`Self::encode`], moving only draw level `level`'s vertices (and their normals from its
    /// triangles) where that level's pass was built, every vertex otherwise; the parameters must
    /// have been set for the same level ([`Self::set_lungs_at`]). The vertices moved are where
    /// the full pass puts them, bit for bit; the others keep the last frame that moved them.
    pub fn encode_at(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        timestamps: Option<wgpu::ComputePassTimestampWrites<'_>>,
        level: usize,
    ) {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("lungdyn deform"),
            timestamp_writes: timestamps,
        });
        let listed = self.level(level);
        // A dispatch over the level's list where it has one for it, else over every vertex.
        let mut run = |d: &Dispatch, group: Option<&wgpu::BindGroup>| {
            let n = match (group, listed) {
                (Some(_), Some(l)) => l.count,
                _ => self.count,
            };
            pass.set_pipeline(&d.pipeline);
            pass.set_bind_group(0, group.unwrap_or(&d.group), &[]);
            pass.dispatch_workgroups(n.div_ceil(WORKGROUP), 1, 1);
        };
        for (k, d) in self.dispatches.iter().enumerate() {
            run(d, listed.and_then(|l| l.groups[k].as_ref()));
        }
        if let Some(d) = &self.normals_pass {
            run(d, listed.and_then(|l| l.normals.as_ref()));
        }
    }
}
