//! # renderer: the breathing lungs on the GPU
//!
//! Each frame: one compute pass deforms every vertex of both lungs in the scene's mode (EQUATIONS.md
//! §2.4 and §3: precomputed `p + s·u`, the exact basis, spherical harmonics eq. 7.7 or eq. 7.1 over
//! the stored rows, plus each lung's rigid offset) and computes smooth vertex normals from the moved
//! surface; then the draw phases (opaque, translucent, overlay: [`draw`]) draw those buffers once
//! per eye (mono, or side-by-side stereo from the HMD pose with a per-eye IPD offset, or each eye of
//! an HMD optics file), registered to the tracked patient pose (by a fixed offset, or the patient's
//! calibration file: [`camera::Rig`]), in the scene's look and colour mode, multisampled (4×,
//! resolved into the single-sample image) unless `[render] msaa = 1`.
//! Headless: an offscreen texture, read back to PNG on request. GPU time comes from timestamp
//! queries where the adapter has them.
//!
//! The lungs come from the scene's kernel files (`lung-model`); the renderer never bakes. Frames
//! arrive from the engine through the port traits of `transport` ([`session::Session`]).
//!
//! Allocation on the frame path: lungdyn allocates nothing per frame; wgpu itself allocates command
//! buffers and staging memory for `write_buffer` inside its own pools.

pub mod camera;
pub mod deform;
pub mod display;
pub mod draw;
pub mod governor;
pub mod governor_memory;
pub mod gpu;
pub mod hud;
pub mod lod;
pub mod lod_cache;
pub mod options;
pub mod predict;
pub mod present;
pub mod process;
pub mod record;
pub mod session;
pub mod tumour;
pub mod window;
pub mod xr;
#[cfg(feature = "openxr")]
pub mod xr_runtime;

pub use deform::{LungInputs, RenderLung, UploadError};
use ipc_types::{Pose, MAX_COEFFS};
use lung_model::scene::{ColorMode, DrawMode, Governor, Lod, Look, RenderScene};
use wgpu::util::DeviceExt;

use crate::gpu::Gpu;

/// What one frame draws.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DrawState {
    /// Deformation scale per lung slot (right, left).
    pub deform_scale: [f32; 2],
    /// Rigid offset per lung slot (right, left), body frame, mm.
    pub offset_mm: [[f32; 3]; 2],
    /// Collapse towards the hilum per lung slot, `c ∈ [0, 1]` (0: none; EQUATIONS.md §4.1).
    pub collapse: [f32; 2],
    /// The hilum per lung slot, body frame, mm (used where `collapse` is not 0).
    pub hilum_mm: [[f32; 3]; 2],
    /// Deformation coefficients per lung slot: force weights (basis, direct) or SH force
    /// coefficients (sh); unused in the precomputed mode.
    pub coeffs: [[f32; MAX_COEFFS]; 2],
    /// Patient reference pose (registration).
    pub patient: Pose,
    /// HMD pose (camera).
    pub hmd: Pose,
    /// How far to trust the patient pose: the background says so on screen.
    pub pose_warning: PoseWarning,
}

/// What the frame shows about the patient pose (the engine's `PATIENT_POSE_HELD`/`_STALE`): in an
/// optical see-through HMD black is transparent, so a held pose veils the view amber and a stale
/// one red, and the lungs are never shown as if placed on a live pose.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PoseWarning {
    /// Live pose: the normal background.
    #[default]
    None,
    /// The last good pose, held within the scene's staleness limit.
    Held,
    /// Held past the limit, or none ever arrived.
    Stale,
    /// No engine frame for a while ([`ipc_types::report_flags::ENGINE_DOWN`]): the engine is
    /// restarting; lungs and pose are the last frame's (violet veil, and the window title says so).
    EngineDown,
    /// The scene breathes with the patient's signal and it is lost (the engine's `SIGNAL_LOST`):
    /// the model breathes, carried on from the signal's last volume, not the patient (blue veil).
    SignalLost,
}

impl PoseWarning {
    /// From the engine frame's state bits.
    pub fn of_engine_state(state: u32) -> Self {
        use ipc_types::engine_state as e;
        if state & e::PATIENT_POSE_STALE != 0 {
            PoseWarning::Stale
        } else if state & e::PATIENT_POSE_HELD != 0 {
            PoseWarning::Held
        } else if state & e::SIGNAL_LOST != 0 {
            PoseWarning::SignalLost
        } else {
            PoseWarning::None
        }
    }

    fn background(self, look: Look) -> wgpu::Color {
        match self {
            // An additive display shows black as the world behind it.
            PoseWarning::None if look == Look::SeeThrough => wgpu::Color::BLACK,
            PoseWarning::None => BACKGROUND,
            PoseWarning::Held => wgpu::Color {
                r: 0.16,
                g: 0.09,
                b: 0.0,
                a: 1.0,
            },
            PoseWarning::Stale => wgpu::Color {
                r: 0.22,
                g: 0.01,
                b: 0.01,
                a: 1.0,
            },
            PoseWarning::EngineDown => wgpu::Color {
                r: 0.14,
                g: 0.03,
                b: 0.22,
                a: 1.0,
            },
            PoseWarning::SignalLost => wgpu::Color {
                r: 0.0,
                g: 0.07,
                b: 0.18,
                a: 1.0,
            },
        }
    }
}

/// Timing of one submitted frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameTiming {
    /// Monotonic time right after `queue.submit`.
    pub submit_ns: u64,
    /// GPU time from the first timestamp (compute begin) to the last (render end), if measured.
    pub gpu_ns: Option<u64>,
    /// Monotonic time at which the wait on this submission's fence returned: the frame's GPU work
    /// is done (0 if the wait failed).
    pub gpu_done_ns: u64,
}

struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
    period_ns: f32,
}

/// The translucent look's weighted blended OIT targets.
struct OitTargets {
    /// Multisampled accumulation and revealage (MSAA on), resolved into the two below.
    multisampled: Option<(wgpu::TextureView, wgpu::TextureView)>,
    accum: wgpu::TextureView,
    reveal: wgpu::TextureView,
    /// The composite's binding of `accum` and `reveal`.
    group: wgpu::BindGroup,
}

/// Every lung vertex's surface attribute ([`draw::lung_surface`]), both lungs concatenated.
fn surface_buffer(device: &wgpu::Device, lungs: &[RenderLung]) -> wgpu::Buffer {
    let surface: Vec<draw::SurfaceAttr> = lungs
        .iter()
        .flat_map(|l| {
            draw::lung_surface(
                l.side.index(),
                &l.lung.positions,
                &l.lung.triangles,
                l.lobe_codes(),
            )
        })
        .collect();
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("lungdyn surface attributes"),
        contents: bytemuck::cast_slice(&surface),
        usage: wgpu::BufferUsages::VERTEX,
    })
}

/// The rest lungs' bounding box (finite positions), mm; none without a vertex.
fn lung_box(lungs: &[RenderLung]) -> Option<(glam::Vec3, glam::Vec3)> {
    lungs
        .iter()
        .flat_map(|l| l.lung.positions.iter())
        .map(|&p| glam::Vec3::from(p))
        .filter(|p| p.is_finite())
        .fold(None, |b: Option<(glam::Vec3, glam::Vec3)>, p| {
            Some(b.map_or((p, p), |(lo, hi)| (lo.min(p), hi.max(p))))
        })
}

/// The GPU's two timestamps around a frame's passes, where the adapter has them.
fn timestamps(gpu: &Gpu) -> Option<Timestamps> {
    let device = &gpu.device;
    gpu.timestamps.then(|| Timestamps {
        set: device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("lungdyn timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: 2,
        }),
        resolve: device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lungdyn timestamp resolve"),
            size: 16,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        }),
        read: device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lungdyn timestamp read"),
            size: 16,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        }),
        period_ns: gpu.queue.get_timestamp_period(),
    })
}

/// The draw levels of detail of both lungs in one index buffer ([`lod`]).
struct DrawLevels {
    index: wgpu::Buffer,
    /// Every level's indices (what `index` holds), level 0 first.
    indices: Vec<u32>,
    ranges: Vec<std::ops::Range<u32>>,
    triangles: Vec<u32>,
    /// A level the topology check refused, per lung, said at start.
    refused: Vec<String>,
    /// Where large lungs' levels came from or went ([`lod_cache`]), said at start.
    cached: Vec<String>,
    /// The level a fixed `lod = N` draws (the coarsest the meshes have when they are too small).
    fixed: usize,
}

impl DrawLevels {
    /// Simplified here at load: none with `lod = "off"` or splats (one splat per vertex: nothing
    /// to simplify).
    fn build(device: &wgpu::Device, settings: &RenderScene, lungs: &[RenderLung]) -> Self {
        let coarsest = match (settings.mode, settings.lod) {
            (DrawMode::Points, _) | (_, Lod::Off) => 0,
            (_, Lod::Auto) => lung_model::scene::MAX_LOD_LEVEL,
            (_, Lod::Level(n)) => n,
        };
        let cache = lod_cache::dir_from_env();
        let (per_lung, sources): (Vec<_>, Vec<_>) = lungs
            .iter()
            .map(|l| {
                lod_cache::lung_levels(
                    &l.lung.positions,
                    &l.lung.triangles,
                    coarsest,
                    cache.as_deref(),
                )
            })
            .unzip();
        let cached = lungs
            .iter()
            .zip(&sources)
            .filter_map(|(l, s)| s.describe(l.side.name()))
            .collect();
        // A level the topology check refused ends that lung's levels; the start line says so.
        let refused: Vec<String> = lungs
            .iter()
            .zip(&per_lung)
            .filter_map(|(l, b)| {
                let (k, why) = b.refused.as_ref()?;
                Some(format!(
                    "the {} lung's level {k} not drawn: {why}",
                    l.side.name()
                ))
            })
            .collect();
        let per_lung: Vec<_> = per_lung.into_iter().map(|b| b.levels).collect();
        let counts: Vec<u32> = lungs.iter().map(|l| l.lung.len() as u32).collect();
        let levels = lod::Levels::join(&per_lung, &counts);
        let triangles: Vec<u32> = (0..levels.ranges.len())
            .map(|k| levels.triangles(k))
            .collect();
        let index = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn indices"),
            contents: bytemuck::cast_slice(&levels.indices),
            usage: wgpu::BufferUsages::INDEX,
        });
        let fixed = match settings.lod {
            Lod::Level(n) => (n as usize).min(levels.ranges.len().saturating_sub(1)),
            _ => 0,
        };
        Self {
            index,
            indices: levels.indices,
            ranges: levels.ranges,
            triangles,
            refused,
            cached,
            fixed,
        }
    }
}

/// The frame's colour target (resolved, sampled, copied out), shared by every [`Variant`].
struct Targets {
    color: wgpu::Texture,
    /// Whether the colour target may be viewed as plain bytes (no sRGB decode).
    bytes_views: bool,
}

impl Targets {
    /// The colour target of `size`.
    fn new(gpu: &Gpu, size: wgpu::Extent3d) -> Self {
        let device = &gpu.device;
        let attachment = wgpu::TextureUsages::RENDER_ATTACHMENT;
        // The colour target may also be viewed as plain bytes (no sRGB decode): the window's
        // present pass copies it texel for texel that way when the window is the frame's size.
        // Only where the adapter allows a texture other view formats (not wgpu's GL backend).
        let bytes_views = gpu
            .adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::VIEW_FORMATS);
        let bytes_format = [draw::COLOR_FORMAT.remove_srgb_suffix()];
        let color = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("lungdyn colour"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: draw::COLOR_FORMAT,
            usage: attachment
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: if bytes_views { &bytes_format } else { &[] },
        });
        Self { color, bytes_views }
    }
}

/// One way of drawing a frame: a look's pipelines at a sample count with their own targets (the
/// multisampled colour, depth, the translucent look's OIT targets), resolved into the shared
/// colour target. The scene's own is the first; the governor's lower qualities may add one with
/// multisampling off and one drawn opaque, built at start so a change never compiles a pipeline
/// mid-run ([`governor`]).
struct Variant {
    look: Look,
    samples: u32,
    draw: draw::DrawPipelines,
    msaa_view: Option<wgpu::TextureView>,
    depth_view: wgpu::TextureView,
    oit: Option<OitTargets>,
}

impl Variant {
    /// `look`'s pipelines for `settings` at `samples` per pixel, with targets of `size`.
    fn new(
        gpu: &Gpu,
        settings: &RenderScene,
        look: Look,
        samples: u32,
        size: wgpu::Extent3d,
    ) -> Self {
        let device = &gpu.device;
        let draw = draw::DrawPipelines::new(device, settings.mode, look, settings.color, samples);
        let texture = |label, format, sample_count, usage| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let attachment = wgpu::TextureUsages::RENDER_ATTACHMENT;
        let composite = draw.composite.as_ref().map(|c| &c.1);
        let view = |t: wgpu::Texture| t.create_view(&Default::default());
        let msaa_view = (samples > 1).then(|| {
            view(texture(
                "lungdyn colour (multisampled)",
                draw::COLOR_FORMAT,
                samples,
                attachment,
            ))
        });
        let depth = texture("lungdyn depth", draw::DEPTH_FORMAT, samples, attachment);
        let oit = composite.map(|layout| {
            let sampled = attachment | wgpu::TextureUsages::TEXTURE_BINDING;
            let accum = view(texture("lungdyn oit accum", draw::ACCUM_FORMAT, 1, sampled));
            let reveal = view(texture(
                "lungdyn oit reveal",
                draw::REVEAL_FORMAT,
                1,
                sampled,
            ));
            let multisampled = (samples > 1).then(|| {
                (
                    view(texture(
                        "lungdyn oit accum (multisampled)",
                        draw::ACCUM_FORMAT,
                        samples,
                        attachment,
                    )),
                    view(texture(
                        "lungdyn oit reveal (multisampled)",
                        draw::REVEAL_FORMAT,
                        samples,
                        attachment,
                    )),
                )
            });
            let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("lungdyn composite"),
                layout,
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: wgpu::BindingResource::TextureView(&accum),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: wgpu::BindingResource::TextureView(&reveal),
                    },
                ],
            });
            OitTargets {
                multisampled,
                accum,
                reveal,
                group,
            }
        });
        Self {
            look,
            samples,
            draw,
            msaa_view,
            depth_view: depth.create_view(&Default::default()),
            oit,
        }
    }
}

/// The renderer's GPU state for a fixed set of lungs and a fixed output size.
pub struct LungRenderer {
    deform: deform::DeformPass,
    /// The scene's way of drawing first, then those the governor's steps need ([`Variant`]).
    variants: Vec<Variant>,
    /// The variant drawn now.
    active: usize,
    /// Draw levels coarser than the chosen one (the governor's [`governor::Quality::lod_bias`]).
    lod_bias: u8,
    /// Only the drawn level's vertices deformed (the governor's
    /// [`governor::Quality::drawn_only`]).
    drawn_only: bool,
    /// What the governor may give up, in its order (empty with `[render] governor = "off"`).
    steps: Vec<governor::Step>,
    /// Every draw level's triangles over the one vertex buffer ([`lod`]), level 0 first.
    index: wgpu::Buffer,
    /// Per level, its range in `index`.
    lod_ranges: Vec<std::ops::Range<u32>>,
    /// Per level, its triangles (both lungs).
    lod_triangles: Vec<u32>,
    /// Levels the topology check refused, and the cache's reads and writes, in words for the
    /// start line (empty: none).
    lod_refused: Vec<String>,
    /// The level drawn last frame (`[render] lod = "auto"`: chosen per frame, [`lod::Chooser`]).
    lod_level: std::sync::atomic::AtomicUsize,
    /// Per vertex of both lungs: material and lobe code ([`draw::SurfaceAttr`]).
    surface: wgpu::Buffer,
    color: wgpu::Texture,
    color_view: wgpu::TextureView,
    /// The same target viewed as plain bytes (`Rgba8Unorm`), for the present pass's exact copy;
    /// `None` where the adapter allows no other view format.
    color_bytes_view: Option<wgpu::TextureView>,
    readback: wgpu::Buffer,
    padded_row: u32,
    eye_width: u32,
    height: u32,
    eyes: usize,
    settings: RenderScene,
    rig: camera::Rig,
    timestamps: Option<Timestamps>,
    tumours: Vec<tumour::TumourDraw>,
    /// Both lungs' rest box in the body frame (the front view's framing).
    lung_box: Option<(glam::Vec3, glam::Vec3)>,
}

const BACKGROUND: wgpu::Color = wgpu::Color {
    r: 0.015,
    g: 0.018,
    b: 0.024,
    a: 1.0,
};

impl LungRenderer {
    /// Upload `lungs` (what their mode needs) and create the target for `settings`, with the fixed
    /// lung offset and the scene's IPD and field of view (no calibration or optics files).
    pub fn new(
        gpu: &Gpu,
        settings: &RenderScene,
        lungs: &[RenderLung],
    ) -> Result<Self, UploadError> {
        Self::with_rig(gpu, settings, &camera::Rig::default(), lungs)
    }

    /// As [`Self::new`], placing the lungs and the eyes by `rig` (a calibration and HMD optics,
    /// [`camera::RigFiles::rig`]); with optics, each eye's image has the optics file's size.
    pub fn with_rig(
        gpu: &Gpu,
        settings: &RenderScene,
        rig: &camera::Rig,
        lungs: &[RenderLung],
    ) -> Result<Self, UploadError> {
        let device = &gpu.device;
        let (eye_width, eye_height) = rig.eye_size(settings);
        let field = match settings.color {
            ColorMode::Tissue | ColorMode::Lobes => deform::Field::None,
            ColorMode::Displacement => deform::Field::Displacement,
            ColorMode::Ventilation => deform::Field::Expansion,
        };
        let samples = msaa_samples(settings, gpu);
        let levels = DrawLevels::build(device, settings, lungs);
        // The most spherical-harmonic bands a lung deforms with (n² coefficients; 0 in other modes).
        let sh_bands = lungs
            .iter()
            .filter_map(|l| match &l.lung.data {
                lung_model::deform::modes::ModeData::Sh { t } => Some(t.n_bands() as u32),
                _ => None,
            })
            .max()
            .unwrap_or(0);
        let steps = match settings.governor {
            Governor::HoldDeadline => governor::ladder(
                settings,
                samples,
                levels.ranges.len().saturating_sub(1),
                sh_bands,
            ),
            Governor::Off => Vec::new(),
        };
        // The governor's "drawn vertices only" moves a coarser level's vertices alone: each level
        // from 1 gets its own pass, built here.
        let listed: Vec<&[u32]> = if steps.contains(&governor::Step::DrawnOnly) {
            levels.ranges[1..]
                .iter()
                .map(|r| &levels.indices[r.start as usize..r.end as usize])
                .collect()
        } else {
            Vec::new()
        };
        let deform = deform::DeformPass::new(
            device,
            &gpu.info.name,
            lungs,
            settings.mode == DrawMode::Triangles,
            field,
            &listed,
        )?;
        let surface = surface_buffer(device, lungs);
        let tumours = lungs
            .iter()
            .filter_map(|l| {
                let t = l.tumour.as_ref()?;
                Some(tumour::TumourDraw::new(
                    device,
                    l.side.index(),
                    t,
                    l.lung.data.mode(),
                ))
            })
            .collect();
        let eyes = if settings.stereo { 2 } else { 1 };
        let width = eye_width * eyes as u32;
        let size = wgpu::Extent3d {
            width,
            height: eye_height,
            depth_or_array_layers: 1,
        };
        let targets = Targets::new(gpu, size);
        // The scene's way of drawing, then each other one a number of the governor's steps reach.
        let mut variants = vec![Variant::new(gpu, settings, settings.look, samples, size)];
        for taken in 1..=steps.len() {
            let (look, n) =
                variant_of(settings.look, samples, governor::Quality::of(&steps, taken));
            if !variants.iter().any(|v| v.look == look && v.samples == n) {
                variants.push(Variant::new(gpu, settings, look, n, size));
            }
        }
        let padded_row = (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lungdyn readback"),
            size: padded_row as u64 * eye_height as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        Ok(Self {
            lung_box: lung_box(lungs),
            deform,
            variants,
            active: 0,
            lod_bias: 0,
            drawn_only: false,
            steps,
            index: levels.index,
            lod_ranges: levels.ranges,
            lod_triangles: levels.triangles,
            lod_refused: levels.refused.into_iter().chain(levels.cached).collect(),
            lod_level: levels.fixed.into(),
            surface,
            color_view: targets.color.create_view(&Default::default()),
            color_bytes_view: targets.bytes_views.then(|| {
                targets.color.create_view(&wgpu::TextureViewDescriptor {
                    format: Some(draw::COLOR_FORMAT.remove_srgb_suffix()),
                    ..Default::default()
                })
            }),
            color: targets.color,
            readback,
            padded_row,
            eye_width,
            height: eye_height,
            eyes,
            settings: settings.clone(),
            rig: *rig,
            timestamps: timestamps(gpu),
            tumours,
        })
    }

    /// The deformation mode.
    pub fn mode(&self) -> lung_model::deform::modes::DeformMode {
        self.deform.mode()
    }

    /// Bytes of lung data uploaded to the GPU.
    pub fn uploaded_bytes(&self) -> u64 {
        self.deform.uploaded_bytes
    }

    /// Image size (both eyes side by side in stereo).
    pub fn image_size(&self) -> (u32, u32) {
        (self.eye_width * self.eyes as u32, self.height)
    }

    /// The HMD pose that shows the lungs from the front of the patient registered at `patient`
    /// ([`record::front_view`]) in [`record::FRONT_VIEW_BAND`]; `None` without lungs.
    pub fn front_view(&self, patient: &Pose) -> Option<Pose> {
        self.front_view_in(patient, record::FRONT_VIEW_BAND)
    }

    /// As [`Self::front_view`], the lungs' box in `band` of the image's height (fractions from
    /// its top: what the heads-up display leaves clear, [`hud::Hud::lungs_band`]).
    pub fn front_view_in(&self, patient: &Pose, band: (f32, f32)) -> Option<Pose> {
        let b = self.lung_box?;
        let aspect = self.eye_width as f32 / self.height as f32;
        Some(record::front_view(
            self.rig.model(patient),
            b,
            self.settings.fov_y_deg,
            aspect,
            band,
        ))
    }

    /// Whether both eyes are drawn side by side.
    pub fn is_stereo(&self) -> bool {
        self.eyes == 2
    }

    /// Vertices drawn per frame (both lungs).
    pub fn vertex_count(&self) -> u32 {
        self.deform.count
    }

    /// The draw level of detail of the last frame ([`lod`]).
    pub fn lod_shown(&self) -> lod::Shown {
        let level = self.drawn_level();
        lod::Shown {
            level: level as u8,
            coarsest: self.lod_triangles.len().saturating_sub(1) as u8,
            triangles: self.lod_triangles.get(level).copied().unwrap_or(0),
            auto: self.settings.lod == Lod::Auto,
        }
    }

    /// The draw levels in words, for the start line: "LOD auto, triangles 40344 / 10084 / 2520",
    /// "LOD 1 fixed, ...", "LOD off".
    pub fn describe_lod(&self) -> String {
        let counts: Vec<String> = self.lod_triangles.iter().map(u32::to_string).collect();
        let refused: String = self.lod_refused.iter().map(|r| format!("; {r}")).collect();
        let text = match self.settings.lod {
            _ if self.settings.mode == DrawMode::Points => "LOD off (splats)".to_string(),
            Lod::Off => "LOD off".to_string(),
            Lod::Auto => format!("LOD auto, triangles {}", counts.join(" / ")),
            Lod::Level(n) => format!(
                "LOD {n} fixed ({} triangles; levels {})",
                self.lod_shown().triangles,
                counts.join(" / ")
            ),
        };
        text + &refused
    }

    /// Triangles of each draw level built (both lungs; level 0: every triangle).
    pub fn lod_triangles(&self) -> &[u32] {
        &self.lod_triangles
    }

    /// Choose this frame's draw level from the lungs' size on screen through `eyes` (both eyes
    /// the same: the larger area's), with `offset_mm` moving each lung's rest box.
    fn choose_lod(&self, eyes: &[camera::EyeUniform], offset_mm: &[[f32; 3]; 2]) {
        if self.settings.lod != Lod::Auto || self.lod_triangles.len() < 2 {
            return;
        }
        use std::sync::atomic::Ordering::Relaxed;
        let budget = self.lung_box.and_then(|(lo, hi)| {
            let offsets = offset_mm.map(glam::Vec3::from);
            let (dlo, dhi) = if offsets.iter().all(|o| o.is_finite()) {
                (offsets[0].min(offsets[1]), offsets[0].max(offsets[1]))
            } else {
                (glam::Vec3::ZERO, glam::Vec3::ZERO)
            };
            eyes.iter()
                .map(|e| lod::covered_pixels(e, (lo + dlo, hi + dhi), self.eye_width, self.height))
                .try_fold(0.0f32, |m, px| px.map(|p| m.max(p)))
                .map(|px| px * lod::TRIANGLES_PER_PIXEL)
        });
        let mut chooser = lod::Chooser::at(self.lod_level.load(Relaxed));
        let level = chooser.choose(&self.lod_triangles, budget);
        self.lod_level.store(level, Relaxed);
    }

    /// The draw level drawn: the chosen one, coarser by the governor's bias, within the levels
    /// built.
    fn drawn_level(&self) -> usize {
        let chosen = self.lod_level.load(std::sync::atomic::Ordering::Relaxed);
        (chosen + self.lod_bias as usize).min(self.lod_triangles.len().saturating_sub(1))
    }

    /// The way of drawing in use now.
    fn variant(&self) -> &Variant {
        &self.variants[self.active]
    }

    /// Samples per pixel drawn now (`[render] msaa`, or its default for this adapter; 1 where the
    /// governor turned multisampling off).
    pub fn samples(&self) -> u32 {
        self.variant().samples
    }

    /// The scene's samples per pixel, whatever the governor draws with now.
    pub fn scene_samples(&self) -> u32 {
        self.variants[0].samples
    }

    /// What the quality governor may give up here, in its order ([`governor::ladder`]; empty with
    /// `[render] governor = "off"` or nothing to give up).
    pub fn governor_steps(&self) -> &[governor::Step] {
        &self.steps
    }

    /// Vertices the deformation pass moves each frame now: every vertex, or with the governor's
    /// "drawn vertices only" those of the level drawn.
    pub fn vertices_moved(&self) -> u32 {
        self.deform.moved_at(self.moved_level())
    }

    /// Set the deformation pass's inputs for `state` at the level it moves now; that level
    /// (0: every vertex), for its encoding.
    fn set_lungs(&self, queue: &wgpu::Queue, state: &DrawState) -> usize {
        let moved = self.moved_level();
        self.deform.set_lungs_at(
            queue,
            &LungInputs {
                scale: state.deform_scale,
                offset: state.offset_mm,
                collapse: state.collapse,
                hilum: state.hilum_mm,
                coeffs: state.coeffs,
            },
            moved,
        );
        moved
    }

    /// The draw level whose vertices alone the deformation moves now (0: every vertex).
    fn moved_level(&self) -> usize {
        if self.drawn_only {
            self.drawn_level()
        } else {
            0
        }
    }

    /// Draw from the next frame on at `quality` (the governor's change): its variant — built at
    /// start for every quality the steps reach —, its draw-level bias, whether the deformation
    /// moves the drawn level's vertices only and the spherical-harmonic bands it sums (an accuracy
    /// step, where the scene allowed it).
    pub fn set_quality(&mut self, quality: governor::Quality) {
        let (look, samples) = variant_of(self.settings.look, self.variants[0].samples, quality);
        if let Some(k) = self
            .variants
            .iter()
            .position(|v| v.look == look && v.samples == samples)
        {
            self.active = k;
        }
        self.lod_bias = quality.lod_bias;
        self.drawn_only = quality.drawn_only;
        self.deform.cap_sh_bands(quality.sh_bands);
    }

    /// Draw the eyes of `eyes` from the next frame on (an OpenXR runtime's views, located per
    /// frame); the image keeps its size.
    pub fn set_eyes(&mut self, eyes: camera::HmdEyes) {
        self.rig.optics = Some(eyes);
    }

    /// The offscreen colour texture (what an OpenXR swapchain image is copied from).
    pub fn color_texture(&self) -> &wgpu::Texture {
        &self.color
    }

    /// The offscreen colour target (what the present pass samples).
    pub fn color_view(&self) -> &wgpu::TextureView {
        &self.color_view
    }

    /// The offscreen colour target viewed as plain bytes (`Rgba8Unorm`: no sRGB decode), for a
    /// present pass's texel-for-texel copy ([`present::PresentPass::new`]); `None` where the
    /// adapter allows no other view format (wgpu's GL backend).
    pub fn color_bytes_view(&self) -> Option<&wgpu::TextureView> {
        self.color_bytes_view.as_ref()
    }

    /// Deform, draw every eye, submit, and wait for the GPU. With `capture`, the image is also
    /// copied for [`Self::read_image`].
    pub fn render(&self, gpu: &Gpu, state: &DrawState, capture: bool) -> FrameTiming {
        self.render_with(gpu, state, capture, |_| {})
    }

    /// GPU time of the deformation pass alone (the mode's dispatches and the normals) for `state`,
    /// from timestamp queries around that one compute pass; `None` without timestamps. For the
    /// trade study: a frame's deformation cost apart from its drawing. The pass runs as the last
    /// frame's did: over every vertex, or with "drawn vertices only" over the last frame's level's.
    pub fn time_deform(&self, gpu: &Gpu, state: &DrawState) -> Option<u64> {
        let t = self.timestamps.as_ref()?;
        let moved = self.set_lungs(&gpu.queue, state);
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("lungdyn deform timing"),
            });
        self.deform.encode_at(
            &mut encoder,
            Some(wgpu::ComputePassTimestampWrites {
                query_set: &t.set,
                beginning_of_pass_write_index: Some(0),
                end_of_pass_write_index: Some(1),
            }),
            moved,
        );
        encoder.resolve_query_set(&t.set, 0..2, &t.resolve, 0);
        encoder.copy_buffer_to_buffer(&t.resolve, 0, &t.read, 0, 16);
        let index = gpu.queue.submit(Some(encoder.finish()));
        let _ = gpu.device.poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: None,
        });
        let ticks = read_mapped(gpu, &t.read, |bytes| {
            let a = u64::from_le_bytes(bytes[0..8].try_into().unwrap());
            let b = u64::from_le_bytes(bytes[8..16].try_into().unwrap());
            b.saturating_sub(a)
        })?;
        Some((ticks as f64 * t.period_ns as f64) as u64)
    }

    /// As [`Self::render`], with `extra` recorded into the frame's command buffer after the draw
    /// (the window's present pass), so it is submitted with the frame.
    pub fn render_with(
        &self,
        gpu: &Gpu,
        state: &DrawState,
        capture: bool,
        extra: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> FrameTiming {
        self.render_with_overlay(gpu, state, capture, |_, _, _| {}, extra)
    }

    /// As [`Self::render_with`], with `overlay` recorded right after the scene is drawn, given the
    /// final colour target and the eyes' cameras (the heads-up display, [`hud::Hud::encode`]):
    /// it is in the captured PNG and in what the window presents.
    pub fn render_with_overlay(
        &self,
        gpu: &Gpu,
        state: &DrawState,
        capture: bool,
        overlay: impl FnOnce(&mut wgpu::CommandEncoder, &wgpu::TextureView, &[camera::EyeUniform]),
        extra: impl FnOnce(&mut wgpu::CommandEncoder),
    ) -> FrameTiming {
        let queue = &gpu.queue;
        let aspect = self.eye_width as f32 / self.height as f32;
        let s = &self.settings;
        let (eyes, n) = self.rig.eyes(
            &state.hmd,
            &state.patient,
            self.eyes == 2,
            s.ipd_mm,
            s.fov_y_deg,
            aspect,
            s.splat_mm,
        );
        for (buffer, eye) in self.variant().draw.eye_buffers.iter().zip(&eyes[..n]) {
            queue.write_buffer(buffer, 0, bytemuck::bytes_of(eye));
        }
        self.choose_lod(&eyes[..n], &state.offset_mm);
        let moved = self.set_lungs(queue, state);
        for t in &self.tumours {
            let k = t.slot;
            t.update(
                queue,
                t.centre_mm(
                    state.deform_scale[k],
                    &state.coeffs[k],
                    state.collapse[k],
                    state.hilum_mm[k],
                    state.offset_mm[k],
                ),
            );
        }
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("lungdyn frame"),
            });
        self.deform.encode_at(
            &mut encoder,
            self.timestamps
                .as_ref()
                .map(|t| wgpu::ComputePassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: Some(0),
                    end_of_pass_write_index: None,
                }),
            moved,
        );
        self.encode_phases(&mut encoder, state.pose_warning, n);
        overlay(&mut encoder, &self.color_view, &eyes[..n]);
        extra(&mut encoder);
        if let Some(t) = &self.timestamps {
            encoder.resolve_query_set(&t.set, 0..2, &t.resolve, 0);
            encoder.copy_buffer_to_buffer(&t.resolve, 0, &t.read, 0, 16);
        }
        if capture {
            let (w, h) = self.image_size();
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &self.color,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &self.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(self.padded_row),
                        rows_per_image: Some(h),
                    },
                },
                wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
            );
        }
        let index = queue.submit(Some(encoder.finish()));
        let submit_ns = transport::now_ns();
        // Headless: wait for this frame, so the next one never queues behind it (one frame in flight).
        // The wait returns when the submission's fence signals: that instant on CLOCK_MONOTONIC is
        // the frame's "GPU done" (the latency harness's capture → GPU done).
        let waited = {
            let _wait = tracing::info_span!(target: transport::trace::TARGET, "GPU wait").entered();
            gpu.device.poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
        };
        let gpu_done_ns = if waited.is_ok() {
            transport::now_ns()
        } else {
            0
        };
        let gpu_ns = self.timestamps.as_ref().and_then(|t| {
            let ticks = read_mapped(gpu, &t.read, |bytes| {
                let a = u64::from_le_bytes(bytes[0..8].try_into().unwrap());
                let b = u64::from_le_bytes(bytes[8..16].try_into().unwrap());
                b.saturating_sub(a)
            })?;
            Some((ticks as f64 * t.period_ns as f64) as u64)
        });
        FrameTiming {
            submit_ns,
            gpu_ns,
            gpu_done_ns,
        }
    }

    /// Record the draw phases for `eyes` eyes, each drawable where [`draw::phases`] puts it for the
    /// look: opaque, translucent, overlay. The opaque and see-through looks take one render pass; the translucent look three (the opaque phase,
    /// the OIT targets, their composite). The opaque phase's pass resolves the multisampled image
    /// (the translucent look's composite blends over the resolved image: see `draw::composite`);
    /// the last pass writes the end timestamp.
    fn encode_phases(&self, encoder: &mut wgpu::CommandEncoder, warning: PoseWarning, eyes: usize) {
        let v = self.variant();
        let look = v.look;
        let phases = draw::phases(look);
        // The OIT targets and composite exist for the look whose phases blend (and only for it).
        let translucent = v.oit.as_ref().zip(v.draw.composite.as_ref());
        debug_assert_eq!(translucent.is_some(), !phases.oit.is_empty());
        let (target, resolve) = match &v.msaa_view {
            Some(ms) => (ms, Some(&self.color_view)),
            None => (&self.color_view, None),
        };
        let end_timestamp = || {
            self.timestamps
                .as_ref()
                .map(|t| wgpu::RenderPassTimestampWrites {
                    query_set: &t.set,
                    beginning_of_pass_write_index: None,
                    end_of_pass_write_index: Some(1),
                })
        };
        let colour = |load| {
            Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: resolve,
                ops: wgpu::Operations {
                    load,
                    store: if resolve.is_some() {
                        wgpu::StoreOp::Discard
                    } else {
                        wgpu::StoreOp::Store
                    },
                },
            })
        };
        let last = translucent.is_none();
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("lungdyn opaque"),
                color_attachments: &[colour(wgpu::LoadOp::Clear(warning.background(look)))],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &v.depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: if last {
                            wgpu::StoreOp::Discard
                        } else {
                            wgpu::StoreOp::Store
                        },
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: if last { end_timestamp() } else { None },
                occlusion_query_set: None,
                multiview_mask: None,
            });
            for &d in phases.first_pass {
                self.draw_one(d, &mut pass, eyes);
            }
        }
        let Some((oit, (composite, _))) = translucent else {
            return;
        };
        {
            let ms = oit.multisampled.as_ref();
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("lungdyn translucent"),
                color_attachments: &[
                    oit_target(&oit.accum, ms.map(|m| &m.0), wgpu::Color::TRANSPARENT),
                    oit_target(&oit.reveal, ms.map(|m| &m.1), wgpu::Color::WHITE),
                ],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &v.depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Load,
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            for &d in phases.oit {
                self.draw_one(d, &mut pass, eyes);
            }
        }
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("lungdyn composite"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.color_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Load,
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: end_timestamp(),
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_pipeline(composite);
        pass.set_bind_group(0, &oit.group, &[]);
        pass.draw(0..3, 0..1);
    }

    /// Point `pass` at eye `i`: its viewport and uniforms.
    fn set_eye(&self, pass: &mut wgpu::RenderPass<'_>, i: usize) {
        pass.set_viewport(
            (i as u32 * self.eye_width) as f32,
            0.0,
            self.eye_width as f32,
            self.height as f32,
            0.0,
            1.0,
        );
        pass.set_bind_group(0, &self.variant().draw.eye_groups[i], &[]);
    }

    /// One drawable of a phase ([`draw::phases`]) into `pass`, for each eye.
    fn draw_one(&self, d: draw::Drawable, pass: &mut wgpu::RenderPass<'_>, eyes: usize) {
        match d {
            draw::Drawable::Lungs => self.draw_lungs(pass, eyes),
            draw::Drawable::Tumours => self.draw_tumours(pass, eyes),
        }
    }

    /// Both lungs, in the look's pipeline, for each eye.
    fn draw_lungs(&self, pass: &mut wgpu::RenderPass<'_>, eyes: usize) {
        pass.set_pipeline(&self.variant().draw.lungs);
        pass.set_vertex_buffer(0, self.deform.deformed.slice(..));
        pass.set_vertex_buffer(1, self.deform.normals.slice(..));
        pass.set_vertex_buffer(2, self.surface.slice(..));
        if self.settings.mode == DrawMode::Triangles {
            pass.set_index_buffer(self.index.slice(..), wgpu::IndexFormat::Uint32);
        }
        let level = self.drawn_level();
        let triangles = self.lod_ranges.get(level).cloned().unwrap_or(0..0);
        for i in 0..eyes {
            self.set_eye(pass, i);
            match self.settings.mode {
                DrawMode::Triangles => pass.draw_indexed(triangles.clone(), 0, 0..1),
                DrawMode::Points => pass.draw(0..6, 0..self.deform.count),
            }
        }
    }

    /// Every tumour, in the phase the look puts them in ([`draw`]), for each eye.
    fn draw_tumours(&self, pass: &mut wgpu::RenderPass<'_>, eyes: usize) {
        if self.tumours.is_empty() {
            return;
        }
        pass.set_pipeline(&self.variant().draw.tumour);
        for i in 0..eyes {
            self.set_eye(pass, i);
            for t in &self.tumours {
                pass.set_vertex_buffer(0, t.positions.slice(..));
                pass.set_vertex_buffer(1, t.normals.slice(..));
                pass.set_vertex_buffer(2, t.surface.slice(..));
                pass.set_index_buffer(t.index.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..t.index_count, 0, 0..1);
            }
        }
    }

    /// The image of the last [`Self::render`] called with `capture = true`, as tightly packed
    /// sRGB RGBA8.
    pub fn read_image(&self, gpu: &Gpu) -> Option<image::RgbaImage> {
        let (w, h) = self.image_size();
        let row = self.padded_row as usize;
        let pixels = read_mapped(gpu, &self.readback, |bytes| {
            let mut out = Vec::with_capacity((w * h * 4) as usize);
            for y in 0..h as usize {
                out.extend_from_slice(&bytes[y * row..y * row + w as usize * 4]);
            }
            out
        })?;
        image::RgbaImage::from_raw(w, h, pixels)
    }

    /// Read back the deformed vertex buffer (tests compare it with the CPU reference).
    pub fn read_deformed(&self, gpu: &Gpu) -> Option<Vec<[f32; 4]>> {
        self.read_buffer(gpu, &self.deform.deformed)
    }

    /// Read back the vertex normals of the last frame (triangle drawing only).
    pub fn read_normals(&self, gpu: &Gpu) -> Option<Vec<[f32; 4]>> {
        self.deform
            .has_normals()
            .then(|| self.read_buffer(gpu, &self.deform.normals))
            .flatten()
    }

    fn read_buffer(&self, gpu: &Gpu, buffer: &wgpu::Buffer) -> Option<Vec<[f32; 4]>> {
        let size = self.deform.count as u64 * 16;
        let staging = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lungdyn deformed readback"),
            size,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        encoder.copy_buffer_to_buffer(buffer, 0, &staging, 0, size);
        let index = gpu.queue.submit(Some(encoder.finish()));
        let _ = gpu.device.poll(wgpu::PollType::Wait {
            submission_index: Some(index),
            timeout: None,
        });
        read_mapped(gpu, &staging, |bytes| {
            bytemuck::cast_slice::<u8, [f32; 4]>(bytes).to_vec()
        })
    }
}

/// Samples per pixel for `settings` on `gpu`: the scene's `msaa`, else 4 on a GPU and 1 on a
/// software rasterizer (lavapipe shades every sample on the CPU: 4× costs it 2.3–2.6× the frame,
/// `cargo bench -p lungdyn-bench --bench render_looks`).
pub fn msaa_samples(settings: &RenderScene, gpu: &Gpu) -> u32 {
    settings
        .msaa
        .unwrap_or(if gpu.info.device_type == wgpu::DeviceType::Cpu {
            1
        } else {
            4
        })
}

/// The look and samples a frame at `quality` is drawn with, for a scene of `look` at `samples`.
fn variant_of(look: Look, samples: u32, quality: governor::Quality) -> (Look, u32) {
    (
        if quality.opaque { Look::Opaque } else { look },
        if quality.msaa_off { 1 } else { samples },
    )
}

/// A cleared OIT target: the multisampled view resolved into `single`, or `single` itself.
fn oit_target<'a>(
    single: &'a wgpu::TextureView,
    multisampled: Option<&'a wgpu::TextureView>,
    clear: wgpu::Color,
) -> Option<wgpu::RenderPassColorAttachment<'a>> {
    let (view, resolve_target) = match multisampled {
        Some(ms) => (ms, Some(single)),
        None => (single, None),
    };
    Some(wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Clear(clear),
            store: if resolve_target.is_some() {
                wgpu::StoreOp::Discard
            } else {
                wgpu::StoreOp::Store
            },
        },
    })
}

/// Map `buffer` for reading (after the GPU work that wrote it completed), run `f` on its bytes,
/// unmap. `None` if mapping failed.
pub(crate) fn read_mapped<T>(
    gpu: &Gpu,
    buffer: &wgpu::Buffer,
    f: impl FnOnce(&[u8]) -> T,
) -> Option<T> {
    buffer.map_async(wgpu::MapMode::Read, .., |_| {});
    gpu.device
        .poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: None,
        })
        .ok()?;
    let result = {
        let view = buffer.get_mapped_range(..).ok()?;
        f(&view)
    };
    buffer.unmap();
    Some(result)
}

/// Write `img` as a PNG atomically (temporary file, then rename).
pub fn write_png(
    img: &image::RgbaImage,
    path: &std::path::Path,
) -> Result<(), outfile::WriteError> {
    outfile::write_atomically(path, |w| {
        img.write_to(w, image::ImageFormat::Png)
            .map_err(std::io::Error::other)
    })
}
