//! # hud: the heads-up display over the drawn lungs
//!
//! Drawn in its own render pass after the scene, onto the final colour target (what the window
//! presents and the PNGs store), in every eye: text with glyphon (the bundled DejaVu Sans Mono, no
//! system fonts) and flat shapes (panels, the breath-phase bar, the PV loop) from a small pipeline.
//!
//! * **Panel** (top left): volume, tidal volume and rate; the breath-phase bar; the disease state;
//!   the latest intervention's outcome with its time; tracker health per tool; frame time and
//!   end-to-end latency; key help.
//! * **PV loop** (top right): pressure against volume over the followed lung's current breathing,
//!   the current point moving on it.
//! * **Anchored labels**: R and L beside each lung and a head/feet cue, projected from the body
//!   frame through each eye's camera, so they sit on the lungs.
//! * **Veil text**: on the held/stale pose veil, what it means.
//! * **Lobe legend** (bottom left, lobes colour mode): each lobe's abbreviation after a square of
//!   its colour; above it, in amber, which lung has no lobe data and is drawn grey.
//!
//! In stereo, the panel and PV loop are shifted by a half disparity per eye
//! ([`text::half_disparity_px`]) so they float at [`HUD_DEPTH_MM`], a comfortable reading depth,
//! rather than at infinity.
//!
//! Per frame: the lines are formatted into kept `String`s ([`text`]) and reshaped only when they
//! changed; the shapes go into a kept vertex list and one `write_buffer`. glyphon and wgpu manage
//! their own staging memory.

pub mod text;

use glam::{Mat4, Vec3, Vec4};
use glyphon::{
    fontdb, Attrs, Buffer, Cache, Color, Family, FontSystem, Metrics, Resolution, Shaping,
    SwashCache, TextArea, TextAtlas, TextBounds, TextRenderer, Viewport,
};
use ipc_types::{EngineFrame, TrackerFrame, NUM_LUNGS};

use crate::camera::EyeUniform;
use crate::PoseWarning;
use text::Standing;

/// The bundled font (DejaVu Sans Mono, Bitstream Vera licence: renderer/assets/).
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSansMono.ttf");
const FAMILY: &str = "DejaVu Sans Mono";

/// Where the HUD panel floats in stereo, mm from the eyes (1.5–2 m: comfortable to read, in front
/// of a patient at arm's length... behind the lungs only for a viewer further than this).
pub const HUD_DEPTH_MM: f32 = 1750.0;

/// Most shape vertices per frame (two eyes of panels, bar and a loop of [`text::PV_BINS`] segments,
/// or the signal trace's two lines of [`text::TRACE_POINTS`] points).
const MAX_SHAPE_VERTICES: usize = 6 * 1024;

/// What the HUD is told once: the scene's facts.
#[derive(Debug, Clone)]
pub struct HudConfig {
    /// Engine ticks per second (the clock of outcomes, the rate).
    pub tick_hz: f64,
    /// The scene's disease, in words, and its side (a lung slot), if any.
    pub disease: Option<(String, Option<usize>)>,
    /// The window's N/C/O keys act (a tension pneumothorax).
    pub interventions: bool,
    /// The scene's IPD, mm (stereo disparity).
    pub ipd_mm: f32,
    /// The scene's vertical field of view, degrees.
    pub fov_y_deg: f32,
    /// Per lung slot: the rest mesh's bounding box in the body frame (min, max), mm.
    pub lung_boxes: [Option<([f32; 3], [f32; 3])>; NUM_LUNGS],
    /// The lobes colour mode's legend (`None` in the other modes): per lung slot, `None` where no
    /// lung is loaded, else whether it has lobe codes.
    pub lobes: Option<[Option<bool>; NUM_LUNGS]>,
    /// The scene breathes with the patient's signal (`[breathing] source = "signal"`): the phase
    /// line says what drives the breath, and room is kept for its longest wording.
    pub signal: bool,
    /// The scene is a remote site (`[remote] role = "site"` or `"observer"`): while the source's
    /// patient drives its lungs (the frame's `SIGNAL_FOLLOWING`), the PV box shows the trace of
    /// the lungs' volume instead of the model's PV loop.
    pub remote_site: bool,
}

impl HudConfig {
    /// The facts of `scene` with its lungs.
    pub fn of(scene: &lung_model::scene::Scene, lungs: &[crate::RenderLung]) -> Self {
        use lung_model::scene_disease::DiseaseKind;
        let disease = scene.disease.as_ref().map(|d| {
            (
                d.kind.name().replace('-', " "),
                d.side
                    .map(|s| s.index())
                    .filter(|_| d.kind != DiseaseKind::BilateralPneumothorax),
            )
        });
        let mut lung_boxes = [None; NUM_LUNGS];
        let mut lobes = [None; NUM_LUNGS];
        for l in lungs {
            lobes[l.side.index()] = Some(l.lobe_codes().is_some());
            let (lo, hi) = l
                .lung
                .positions
                .iter()
                .map(|&p| Vec3::from(p))
                .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p), hi.max(p))
                });
            if lo.is_finite() && hi.is_finite() {
                lung_boxes[l.side.index()] = Some((lo.to_array(), hi.to_array()));
            }
        }
        Self {
            tick_hz: scene.engine.tick_hz,
            interventions: scene
                .disease
                .as_ref()
                .is_some_and(|d| d.kind == DiseaseKind::TensionPneumothorax && d.side.is_some()),
            disease,
            ipd_mm: scene.render.ipd_mm,
            fov_y_deg: scene.render.fov_y_deg,
            lung_boxes,
            lobes: (scene.render.color == lung_model::scene::ColorMode::Lobes).then_some(lobes),
            signal: scene.breathing.source == lung_model::scene::BreathSource::Signal,
            remote_site: scene.remote.as_ref().is_some_and(|r| {
                matches!(
                    r.role,
                    lung_model::scene_remote::RemoteRole::Site
                        | lung_model::scene_remote::RemoteRole::Observer
                )
            }),
        }
    }
}

/// What one frame's HUD shows, beside the engine frame (the session keeps these).
#[derive(Debug, Clone, Copy)]
pub struct HudFrame<'a> {
    /// The engine frame drawn.
    pub frame: &'a EngineFrame,
    /// The newest tracker frame, if any arrived.
    pub tracker: Option<&'a TrackerFrame>,
    /// The patient pose's state (the veil).
    pub warning: PoseWarning,
    /// CPU time of the previous frame, ns.
    pub cpu_ns: u64,
    /// GPU time of the previous frame, ns.
    pub gpu_ns: Option<u64>,
    /// End-to-end latency of the previous frame (tracker capture → submit), ns.
    pub latency_ns: Option<u64>,
    /// The draw level of detail of the previous frame ([`crate::LungRenderer::lod_shown`]).
    pub lod: crate::lod::Shown,
    /// The quality governor's report bits for the previous frame (`None`: governor off): what it
    /// gave up ([`ipc_types::report_flags::QUALITY_LOWERED`]) and whether it is at its floor.
    pub governor: Option<u32>,
    /// The latest intervention's line and how it stands.
    pub outcome: Option<(&'a str, Standing)>,
}

#[repr(C)]
#[derive(Debug, Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ShapeVertex {
    pos: [f32; 2],
    color: [f32; 4],
}

/// Panel lines, in order.
const VOLUME: usize = 0;
const PHASE: usize = 1;
const DISEASE: usize = 2;
const OUTCOME: usize = 3;
/// The outcome line's text block (in [`EyeLayout::texts`]).
pub const OUTCOME_BLOCK: usize = OUTCOME;
const TRACKER: usize = 4;
const TIMING: usize = 5;
const KEYS: usize = 6;
const PANEL_LINES: usize = 7;
/// Rows the lungs' framing leaves for the outcome line ([`Hud::lungs_band`]), and the most it
/// takes: a longer outcome is cut to these rows and ends in "…" (the full words are what
/// `lungdyn scene event` prints and the demo's log says), so the panel never grows over the lungs.
pub const OUTCOME_RESERVED_ROWS: usize = 2;
/// Other text blocks.
const LABEL_R: usize = 7;
const LABEL_L: usize = 8;
const HEAD: usize = 9;
const FEET: usize = 10;
const VEIL: usize = 11;
const PV_TITLE: usize = 12;
const LEGEND: usize = 13;
const LOBE_WARNING: usize = 14;
/// Text blocks the HUD draws (the panel's lines, then the others).
pub const BLOCKS: usize = 15;
/// Eyes smaller than this (width, or height) get the compact HUD: the panel keeps the volume, the
/// breath phase, the disease and the outcome, and drops the tracker, frame-time and key-help lines
/// so that the lungs keep half the picture (a stale or held pose still shows its veil).
const COMPACT_BELOW: (u32, u32) = (400, 300);

/// The HUD's GPU state: glyphon's atlas and renderer, the text blocks, the shapes pipeline.
pub struct Hud {
    config: HudConfig,
    font_system: FontSystem,
    swash: SwashCache,
    viewport: Viewport,
    atlas: TextAtlas,
    text: TextRenderer,
    buffers: Vec<Buffer>,
    /// What each block should say this frame, and what its buffer was last shaped with.
    lines: [String; BLOCKS],
    shaped: [String; BLOCKS],
    colors: [Color; BLOCKS],
    pipeline: wgpu::RenderPipeline,
    vertex_buffer: wgpu::Buffer,
    vertices: Vec<ShapeVertex>,
    pv: text::PvTrace,
    /// The breath drawn beside the patient's signal (shown instead of the PV loop when the scene
    /// breathes with the signal, or a site's lungs breathe with the source's patient).
    trace: text::SignalTrace,
    /// What the PV box shows now ([`text::pv_box_shows`]), its title shaped for it.
    pv_box: text::PvBox,
    eye_width: u32,
    height: u32,
    eyes: u32,
    font_px: f32,
    /// In stereo, the half disparity that floats the HUD at [`HUD_DEPTH_MM`]: each eye's parts
    /// are laid out this far inside both of its edges, then shifted by it.
    inset: f32,
    /// The compact HUD ([`COMPACT_BELOW`]).
    compact: bool,
    /// Per block, the rows and the widest row of its text when last shaped (every panel line and
    /// the legend wrap at their box's width).
    rows: [usize; BLOCKS],
    widths: [f32; BLOCKS],
    /// Panel rows the lungs' framing leaves room for.
    reserved_rows: usize,
}

const WHITE: Color = Color::rgb(235, 238, 242);
const GREY: Color = Color::rgb(165, 172, 182);
const AMBER: Color = Color::rgb(255, 196, 64);
const GREEN: Color = Color::rgb(110, 230, 140);
const RED: Color = Color::rgb(255, 96, 86);
const CYAN: Color = Color::rgb(120, 210, 255);

/// An sRGB colour with alpha as the linear values the shapes pipeline writes.
fn linear(r: u8, g: u8, b: u8, a: f32) -> [f32; 4] {
    let l = crate::draw::srgb_to_linear;
    [l(r), l(g), l(b), a]
}

/// A rectangle on the target, pixels of the whole (side-by-side) image: top left `x, y`, size
/// `w × h`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rect {
    /// Left edge.
    pub x: f32,
    /// Top edge.
    pub y: f32,
    /// Width.
    pub w: f32,
    /// Height.
    pub h: f32,
}

impl Rect {
    /// Whether the two share any area (touching edges do not).
    pub fn overlaps(&self, o: &Rect) -> bool {
        self.x < o.x + o.w && o.x < self.x + self.w && self.y < o.y + o.h && o.y < self.y + self.h
    }

    /// Whether `inner` lies wholly inside this one.
    pub fn contains(&self, inner: &Rect) -> bool {
        inner.x >= self.x
            && inner.y >= self.y
            && inner.x + inner.w <= self.x + self.w
            && inner.y + inner.h <= self.y + self.h
    }

    fn centre(&self) -> (f32, f32) {
        (self.x + self.w * 0.5, self.y + self.h * 0.5)
    }

    fn tuple(&self) -> (f32, f32, f32, f32) {
        (self.x, self.y, self.w, self.h)
    }
}

/// Where the HUD puts its parts in one eye this frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EyeLayout {
    /// The eye's part of the target.
    pub eye: Rect,
    /// The panel's backdrop (top left).
    pub panel: Rect,
    /// The PV loop's backdrop with its title row (top right).
    pub pv: Rect,
    /// The lobe legend's backdrop (bottom left, lobes colour mode).
    pub legend: Option<Rect>,
    /// The backdrops of the anchored labels R, L, head and feet as shown: `None` for one whose
    /// anchor is off-screen or that finds no room clear of the panels.
    pub labels: [Option<Rect>; 4],
    /// Each text block drawn in this eye ([`BLOCKS`], the panel's lines first): where its shaped
    /// text lies and what it is clipped to; `None` for one not drawn.
    pub texts: [Option<TextBox>; BLOCKS],
    /// The lungs' boxes (each lung's rest box moved by its offset) projected into this eye: the
    /// bounding rectangle of their corners, `None` when a corner is behind the eye or far off
    /// screen.
    pub lungs: Option<Rect>,
}

/// A text block as laid out in one eye.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TextBox {
    /// Where its shaped text lies: left, top, the widest row's width and its rows' height.
    pub text: Rect,
    /// What it is clipped to when drawn (its panel, box or backdrop).
    pub clip: Rect,
}

/// Where an anchored label whose backdrop would be `want` goes: there if it lies in `area` and
/// clear of every obstacle, else the nearest place that does, moved against an obstacle's edge
/// (`gap` pixels off it) or the area's; `None` where there is no such place. Tries every
/// combination of those edges (at most 7 × 7 for three obstacles), no allocation.
pub fn place_label(
    want: Rect,
    obstacles: &[Option<Rect>; 3],
    area: Rect,
    gap: f32,
) -> Option<Rect> {
    if want.w > area.w || want.h > area.h || !(want.x.is_finite() && want.y.is_finite()) {
        return None;
    }
    let clamp_x = |x: f32| x.clamp(area.x, area.x + area.w - want.w);
    let clamp_y = |y: f32| y.clamp(area.y, area.y + area.h - want.h);
    let mut xs = [clamp_x(want.x); 7];
    let mut ys = [clamp_y(want.y); 7];
    for (k, o) in obstacles.iter().enumerate() {
        if let Some(o) = o {
            xs[1 + 2 * k] = clamp_x(o.x - gap - want.w);
            xs[2 + 2 * k] = clamp_x(o.x + o.w + gap);
            ys[1 + 2 * k] = clamp_y(o.y - gap - want.h);
            ys[2 + 2 * k] = clamp_y(o.y + o.h + gap);
        }
    }
    let mut best: Option<(f32, Rect)> = None;
    for &x in &xs {
        for &y in &ys {
            let r = Rect { x, y, ..want };
            if !area.contains(&r) || obstacles.iter().flatten().any(|o| r.overlaps(o)) {
                continue;
            }
            let d = (x - want.x).powi(2) + (y - want.y).powi(2);
            if best.is_none_or(|(b, _)| d < b) {
                best = Some((d, r));
            }
        }
    }
    best.map(|(_, r)| r)
}

impl Hud {
    /// Set up the HUD for a target of `eyes` images of `eye_width × height` side by side.
    pub fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        config: HudConfig,
        eye_width: u32,
        height: u32,
        eyes: u32,
    ) -> Self {
        let mut db = fontdb::Database::new();
        db.load_font_data(FONT.to_vec());
        let mut font_system = FontSystem::new_with_locale_and_db("en-US".into(), db);
        let cache = Cache::new(device);
        let viewport = Viewport::new(device, &cache);
        let mut atlas = TextAtlas::new(device, queue, &cache, crate::draw::COLOR_FORMAT);
        let text = TextRenderer::new(&mut atlas, device, wgpu::MultisampleState::default(), None);
        // Readable at the HMD's resolution: a 40th of the eye's height (18 px at 720), at least
        // 11 px, 10 px in the compact HUD (its volume line then fits one row of a 320 px stereo
        // eye's panel).
        let compact = eye_width < COMPACT_BELOW.0 || height < COMPACT_BELOW.1;
        let least = if compact { 10.0 } else { 11.0 };
        let font_px = (height as f32 / 40.0).clamp(least, 40.0);
        let buffers = (0..BLOCKS)
            .map(|k| {
                let size = match k {
                    LABEL_R | LABEL_L => font_px * 1.6,
                    VEIL => font_px * 1.3,
                    PV_TITLE => font_px * 0.8,
                    _ => font_px,
                };
                // Unbounded: the panel's lines and the legend are given their wrap width below.
                Buffer::new(&mut font_system, Metrics::new(size, size * 1.25))
            })
            .collect();
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("lungdyn hud shapes"),
            source: wgpu::ShaderSource::Wgsl(include_str!("shapes.wgsl").into()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("lungdyn hud shapes"),
            bind_group_layouts: &[],
            immediate_size: 0,
        });
        let attributes = wgpu::vertex_attr_array![0 => Float32x2, 1 => Float32x4];
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("lungdyn hud shapes"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<ShapeVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &attributes,
                })],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &module,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: crate::draw::COLOR_FORMAT,
                    blend: Some(wgpu::BlendState::ALPHA_BLENDING),
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let vertex_buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("lungdyn hud shapes"),
            size: (MAX_SHAPE_VERTICES * std::mem::size_of::<ShapeVertex>()) as u64,
            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut hud = Self {
            config,
            font_system,
            swash: SwashCache::new(),
            viewport,
            atlas,
            text,
            buffers,
            lines: Default::default(),
            shaped: Default::default(),
            colors: [WHITE; BLOCKS],
            pipeline,
            vertex_buffer,
            vertices: Vec::with_capacity(MAX_SHAPE_VERTICES),
            pv: text::PvTrace::default(),
            trace: text::SignalTrace::default(),
            pv_box: text::PvBox::Loop,
            eye_width,
            height,
            eyes,
            font_px,
            inset: 0.0,
            compact,
            rows: [1; BLOCKS],
            widths: [0.0; BLOCKS],
            reserved_rows: 0,
        };
        if eyes == 2 {
            hud.inset = text::half_disparity_px(
                height,
                hud.config.fov_y_deg,
                hud.config.ipd_mm,
                HUD_DEPTH_MM,
            )
            .clamp(0.0, eye_width as f32 * 0.1);
        }
        // Every panel line wraps at the panel's width rather than being clipped (a long reply or
        // disease line on a 480 px eye); the phase word beside the bar.
        let (panel_w, m) = (hud.panel_w(), hud.margin());
        for k in 0..PANEL_LINES {
            let w = if k == PHASE {
                panel_w - 2.0 * m - hud.bar_w()
            } else {
                panel_w - m
            };
            hud.buffers[k].set_size(Some(w.max(1.0)), None);
        }
        let legend_w = (hud.content_w() - 2.0 * m).max(1.0);
        for k in [LEGEND, LOBE_WARNING] {
            hud.buffers[k].set_size(Some(legend_w), None);
        }
        hud.lines[LABEL_R].push('R');
        hud.lines[LABEL_L].push('L');
        hud.lines[HEAD].push_str("▲ head");
        hud.lines[FEET].push_str("▼ feet");
        hud.pv_box = text::pv_box_shows(&hud.config, 0);
        hud.choose_pv_title();
        hud.colors[LABEL_R] = CYAN;
        hud.colors[LABEL_L] = CYAN;
        hud.colors[HEAD] = CYAN;
        hud.colors[FEET] = CYAN;
        hud.colors[KEYS] = GREY;
        hud.colors[TIMING] = GREY;
        hud.colors[PV_TITLE] = GREY;
        hud.colors[LOBE_WARNING] = AMBER;
        hud.set_lobe_legend();
        hud.reserve_rows();
        hud
    }

    /// The PV box's title: the longest of its wordings that fits the box at this size (the axes
    /// named in full from about 1500 px wide, shorter below, "PV" alone at the smallest). A scene
    /// that breathes with the patient's signal shows the signal trace there, and says so; so does a
    /// site while the source's patient drives its lungs ([`text::PvBox`]).
    fn choose_pv_title(&mut self) {
        let room = self.pv_box(0.0).2 - 8.0;
        for &title in self.pv_box.titles() {
            self.shape(PV_TITLE, title);
            if self.widths[PV_TITLE] <= room {
                break;
            }
        }
    }

    /// Shape block `k` with `text` (one set of attributes), recording its rows and width.
    fn shape(&mut self, k: usize, text: &str) {
        let b = &mut self.buffers[k];
        b.set_text(
            text,
            &Attrs::new().family(Family::Name(FAMILY)),
            Shaping::Basic,
            None,
        );
        b.shape_until_scroll(&mut self.font_system, false);
        self.measure(k);
        self.lines[k].clear();
        self.lines[k].push_str(text);
        self.shaped[k].clear();
        self.shaped[k].push_str(text);
    }

    /// Record block `k`'s rows and widest row from its shaped buffer.
    fn measure(&mut self, k: usize) {
        let (mut rows, mut w) = (0usize, 0.0f32);
        for run in self.buffers[k].layout_runs() {
            rows += 1;
            w = w.max(run.line_w);
        }
        self.rows[k] = rows.max(1);
        self.widths[k] = w;
    }

    /// The panel rows the lungs' framing leaves room for ([`Self::lungs_band`]): one per line
    /// shown, the frame-time line's, the key help's and the disease line's longest wording (its kind and side, every lung
    /// collapsed and held) as wrapped at this size, and [`OUTCOME_RESERVED_ROWS`] for an outcome.
    /// A lung past its fold-free volume (rare: a breath deeper than its kernel was checked for) is
    /// not reserved for: its words may run over the band's top in those frames rather than every
    /// frame's lungs being framed smaller (at 320 × 240 they would cover under a tenth of the image).
    fn reserve_rows(&mut self) {
        let mut worst = EngineFrame::default();
        for l in worst.lungs.iter_mut() {
            l.flags = ipc_types::lung_flags::ACTIVE | ipc_types::lung_flags::HELD;
            l.collapse = 1.0;
        }
        let disease = self.config.disease.clone();
        let mut line = String::new();
        text::disease_line(
            &mut line,
            disease.as_ref().map(|(k, s)| (k.as_str(), *s)),
            &worst,
        );
        self.shape(DISEASE, &line);
        let disease_rows = self.rows[DISEASE];
        let keys = text::key_help(self.config.interventions);
        self.shape(KEYS, keys);
        let phase_rows = if self.config.signal {
            // The longest the line says: calibrating, or following with the longest latency and
            // a clipped signal.
            use ipc_types::engine_state as e;
            worst.state = e::SIGNAL_CALIBRATING | e::SIGNAL_LEARNING;
            text::phase_line(&mut line, &worst);
            let mut following = String::new();
            worst.state = e::SIGNAL_FOLLOWING | e::SIGNAL_CLIPPED;
            worst.signal.latency_ns = 2_000_000_000;
            text::phase_line(&mut following, &worst);
            if following.chars().count() > line.chars().count() {
                line = following;
            }
            self.shape(PHASE, &line);
            self.rows[PHASE]
        } else {
            1
        };
        // The frame-time line at its longest: two-digit times, a draw level, and the governor at
        // its floor having given up everything.
        let widest_lod = crate::lod::Shown {
            level: 5,
            coarsest: 5,
            triangles: 0,
            auto: true,
        };
        let flags = ipc_types::report_flags::quality_bits(true, 7, true)
            | ipc_types::report_flags::QUALITY_DRAWN_ONLY
            | ipc_types::report_flags::GOVERNOR_FLOOR;
        text::timing_line(
            &mut line,
            99_900_000,
            Some(99_900_000),
            &widest_lod,
            Some(flags),
            Some(99_900_000),
        );
        self.shape(TIMING, &line);
        let timing_rows = self.rows[TIMING];
        self.reserved_rows = (0..PANEL_LINES)
            .filter(|&k| self.shown_at_size(k))
            .map(|k| match k {
                PHASE => phase_rows,
                TIMING => timing_rows,
                DISEASE => disease_rows,
                KEYS => self.rows[KEYS],
                OUTCOME => OUTCOME_RESERVED_ROWS,
                _ => 1,
            })
            .sum();
    }

    /// Whether panel line `k` is shown at this size (the compact HUD drops the tracker, the frame
    /// time and the key help).
    fn shown_at_size(&self, k: usize) -> bool {
        !(self.compact && matches!(k, TRACKER | TIMING | KEYS))
    }

    /// Whether panel line `k` is shown this frame: at this size, and the outcome only once an
    /// intervention was sent (no empty row before it).
    fn shown(&self, k: usize) -> bool {
        self.shown_at_size(k) && !(k == OUTCOME && self.lines[OUTCOME].is_empty())
    }

    /// Cut the outcome's shaped text to [`OUTCOME_RESERVED_ROWS`] rows, ending in "…": the longest
    /// prefix (whole characters, trailing spaces dropped) that fits. Runs only when the outcome
    /// changed (a handful of reshapes of one short line).
    fn fit_outcome(&mut self) {
        if self.rows[OUTCOME] <= OUTCOME_RESERVED_ROWS {
            return;
        }
        let full = std::mem::take(&mut self.lines[OUTCOME]);
        let ends: Vec<usize> = full.char_indices().map(|(i, _)| i).skip(1).collect();
        let mut cut = String::with_capacity(full.len() + 3);
        let mut fits = |hud: &mut Self, end: usize| {
            cut.clear();
            cut.push_str(full[..end].trim_end());
            cut.push('…');
            let b = &mut hud.buffers[OUTCOME];
            b.set_text(
                &cut,
                &Attrs::new().family(Family::Name(FAMILY)),
                Shaping::Basic,
                None,
            );
            b.shape_until_scroll(&mut hud.font_system, false);
            hud.measure(OUTCOME);
            hud.rows[OUTCOME] <= OUTCOME_RESERVED_ROWS
        };
        // Binary search for the longest prefix that fits (fitting is monotone in the length).
        let (mut lo, mut hi) = (0usize, ends.len());
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            if fits(self, ends[mid - 1]) {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        fits(self, ends.get(lo.max(1) - 1).copied().unwrap_or(0));
        self.lines[OUTCOME] = full;
    }

    /// The band of each eye's height (fractions from its top) clear of the HUD's panel, PV loop
    /// and lobe legend, with a row below for the feet cue: where [`crate::LungRenderer::
    /// front_view_in`] frames the lungs for strips and recordings. The panel counts its
    /// reserved rows (one per line shown, two for an outcome), so the band is the same in every
    /// frame.
    pub fn lungs_band(&self) -> (f32, f32) {
        let (lh, m, h) = (self.line_height(), self.margin(), self.height as f32);
        let panel_bottom = m * 1.5 + lh * self.reserved_rows as f32;
        let (_, py, _, ph) = self.pv_box(0.0);
        let top = panel_bottom.max(py + ph) + m * 0.5;
        let legend = self.legend_rows();
        let bottom = if legend > 0 {
            self.legend_top(legend)
        } else {
            h
        } - m * 0.5
            - lh;
        (top / h, bottom / h)
    }

    /// The lobes colour mode's legend, shaped once: a square in each lobe's colour before its
    /// abbreviation, a grey square for a lung without lobe codes; and the warning line for those.
    fn set_lobe_legend(&mut self) {
        let Some(lungs) = self.config.lobes else {
            return;
        };
        let attrs = Attrs::new().family(Family::Name(FAMILY));
        let swatch = |c: [u8; 3]| attrs.clone().color(Color::rgb(c[0], c[1], c[2]));
        let mut spans: Vec<(String, Attrs)> = Vec::new();
        for (lobe, abbreviation) in text::lobe_legend(lungs) {
            spans.push(("■".into(), swatch(lobe.colour())));
            spans.push((format!(" {abbreviation}  "), attrs.clone()));
        }
        if let Some(which) = text::lungs_without_lobes(lungs) {
            let grey = lung_model::mesh::lobes::Lobe::Unknown.colour();
            spans.push(("■".into(), swatch(grey)));
            spans.push((format!(" {which}: no lobe data"), attrs.clone()));
            let warning = text::lobe_warning(lungs).unwrap_or_default();
            self.shape(LOBE_WARNING, &warning);
        }
        let legend: String = spans.iter().map(|(t, _)| t.as_str()).collect();
        let b = &mut self.buffers[LEGEND];
        b.set_rich_text(
            spans.iter().map(|(t, a)| (t.as_str(), a.clone())),
            &attrs,
            Shaping::Basic,
            None,
        );
        b.shape_until_scroll(&mut self.font_system, false);
        self.measure(LEGEND);
        // Shaped once: the per-frame reshaping sees no change.
        self.lines[LEGEND].clone_from(&legend);
        self.shaped[LEGEND] = legend;
    }

    /// The scene's facts the HUD was made with.
    pub fn config(&self) -> &HudConfig {
        &self.config
    }

    /// Format this frame's lines and colours (pure text, [`text`]).
    fn update_lines(&mut self, f: &HudFrame) {
        let tick_hz = self.config.tick_hz;
        let l = &mut self.lines;
        text::volume_line(&mut l[VOLUME], f.frame, tick_hz);
        text::phase_line(&mut l[PHASE], f.frame);
        let disease = self.config.disease.as_ref().map(|(k, s)| (k.as_str(), *s));
        text::disease_line(&mut l[DISEASE], disease, f.frame);
        self.colors[DISEASE] = if disease.is_some() || text::past_fold_free(f.frame) {
            AMBER
        } else {
            GREEN
        };
        l[OUTCOME].clear();
        if let Some((line, standing)) = f.outcome {
            l[OUTCOME].push_str(line);
            self.colors[OUTCOME] = match standing {
                Standing::Pending => AMBER,
                Standing::Done => GREEN,
                Standing::Failed => RED,
            };
        }
        let ok = text::tracker_line(&mut l[TRACKER], f.tracker);
        self.colors[TRACKER] = if ok { WHITE } else { AMBER };
        text::timing_line(
            &mut l[TIMING],
            f.cpu_ns,
            f.gpu_ns,
            &f.lod,
            f.governor,
            f.latency_ns,
        );
        l[VEIL].clear();
        if let Some(w) = text::veil_words(f.warning) {
            l[VEIL].push_str(w);
            self.colors[VEIL] = match f.warning {
                PoseWarning::Stale => RED,
                PoseWarning::SignalLost => CYAN,
                _ => AMBER,
            };
        }
        // Reshape only what changed.
        for k in 0..BLOCKS {
            if self.shown(k) && self.lines[k] != self.shaped[k] {
                let b = &mut self.buffers[k];
                if k == VEIL {
                    // The veil's words fit the eye's width (monospace: 0.6 em per character).
                    let chars = self.lines[k].chars().count().max(1) as f32;
                    let size = (self.font_px * 1.3)
                        .min(0.95 * self.eye_width as f32 / (chars * 0.6))
                        .max(6.0);
                    b.set_metrics(Metrics::new(size, size * 1.25));
                }
                b.set_text(
                    &self.lines[k],
                    &Attrs::new().family(Family::Name(FAMILY)),
                    Shaping::Basic,
                    None,
                );
                b.shape_until_scroll(&mut self.font_system, false);
                self.measure(k);
                if k == OUTCOME {
                    self.fit_outcome();
                }
                self.shaped[k].clone_from(&self.lines[k]);
            }
        }
    }

    fn push_rect(&mut self, (x, y, w, h): (f32, f32, f32, f32), color: [f32; 4]) {
        if self.vertices.len() + 6 > MAX_SHAPE_VERTICES {
            return;
        }
        let (tw, th) = ((self.eye_width * self.eyes) as f32, self.height as f32);
        let ndc = |px: f32, py: f32| [px / tw * 2.0 - 1.0, 1.0 - py / th * 2.0];
        let (a, b, c, d) = (ndc(x, y), ndc(x + w, y), ndc(x + w, y + h), ndc(x, y + h));
        for pos in [a, b, c, a, c, d] {
            self.vertices.push(ShapeVertex { pos, color });
        }
    }

    /// The signal trace in the box `inner`: the lungs' drawn volume in white, the patient's
    /// measured volume in blue, each a line broken where it has no point, the newest at the right
    /// edge marked.
    fn push_trace(&mut self, inner: (f32, f32, f32, f32)) {
        let Some(range) = self.trace.range() else {
            return;
        };
        let white = linear(230, 230, 235, 0.9);
        let blue = linear(120, 210, 255, 0.95);
        let mut prev: [Option<(f32, f32)>; 2] = [None, None];
        let mut newest = None;
        for k in 0..text::TRACE_POINTS {
            let Some(p) = self.trace.point(k) else {
                continue;
            };
            for (line, (v, colour)) in [(p.drawn_ml, white), (p.measured_ml, blue)]
                .into_iter()
                .enumerate()
            {
                let q = v.map(|v| text::SignalTrace::to_px(k, v, range, inner));
                if let (Some(a), Some(b)) = (prev[line], q) {
                    self.push_line(a, b, 2.0, colour);
                }
                prev[line] = q;
            }
            newest = p
                .drawn_ml
                .map(|v| text::SignalTrace::to_px(k, v, range, inner));
        }
        if let Some((cx, cy)) = newest {
            self.push_rect((cx - 4.5, cy - 4.5, 9.0, 9.0), linear(255, 196, 64, 1.0));
        }
    }

    fn push_line(&mut self, a: (f32, f32), b: (f32, f32), width: f32, color: [f32; 4]) {
        if self.vertices.len() + 6 > MAX_SHAPE_VERTICES {
            return;
        }
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len = (dx * dx + dy * dy).sqrt();
        if !(len.is_finite() && len > 0.0) {
            return;
        }
        let (nx, ny) = (-dy / len * width * 0.5, dx / len * width * 0.5);
        let (tw, th) = ((self.eye_width * self.eyes) as f32, self.height as f32);
        let ndc = |px: f32, py: f32| [px / tw * 2.0 - 1.0, 1.0 - py / th * 2.0];
        let p = [
            ndc(a.0 + nx, a.1 + ny),
            ndc(b.0 + nx, b.1 + ny),
            ndc(b.0 - nx, b.1 - ny),
            ndc(a.0 - nx, a.1 - ny),
        ];
        for pos in [p[0], p[1], p[2], p[0], p[2], p[3]] {
            self.vertices.push(ShapeVertex { pos, color });
        }
    }

    /// Left edge of eye `i`'s HUD parts: [`Self::inset`] inside the eye, shifted by it in stereo
    /// (the left eye's parts right, the right eye's left) so that both eyes' parts stay inside
    /// their eye.
    fn eye_origin(&self, i: u32) -> f32 {
        let shift = match (self.eyes, i) {
            (2, 0) => self.inset,
            (2, _) => -self.inset,
            _ => 0.0,
        };
        (i * self.eye_width) as f32 + self.inset + shift
    }

    /// Width of each eye's HUD area (the eye less the stereo inset on both sides).
    fn content_w(&self) -> f32 {
        self.eye_width as f32 - 2.0 * self.inset
    }

    fn line_height(&self) -> f32 {
        self.font_px * 1.3
    }

    fn margin(&self) -> f32 {
        (self.font_px * 0.9).round()
    }

    /// The panel's width: to the PV loop's box, at most 48 characters.
    fn panel_w(&self) -> f32 {
        (self.pv_box(0.0).0 - self.margin() * 1.5).min(self.font_px * 48.0)
    }

    /// The breath-phase bar's width.
    fn bar_w(&self) -> f32 {
        self.panel_w() * 0.45
    }

    /// Panel rows: each line shown, as wrapped.
    fn panel_rows(&self) -> usize {
        (0..PANEL_LINES)
            .filter(|&k| self.shown(k))
            .map(|k| self.rows[k])
            .sum()
    }

    /// Top of panel line `k` (below the rows of the lines shown before it).
    fn row_top(&self, k: usize) -> f32 {
        let rows: usize = (0..k)
            .filter(|&j| self.shown(j))
            .map(|j| self.rows[j])
            .sum();
        self.margin() + self.line_height() * rows as f32
    }

    /// Rows of the lobe legend: 0 (not the lobes mode), else its rows and its warning's, as
    /// wrapped.
    fn legend_rows(&self) -> usize {
        [LEGEND, LOBE_WARNING]
            .iter()
            .filter(|&&k| !self.lines[k].is_empty())
            .map(|&k| self.rows[k])
            .sum()
    }

    /// Top of the lobe legend's backdrop of `rows` rows.
    fn legend_top(&self, rows: usize) -> f32 {
        self.height as f32 - self.margin() * 1.5 - self.line_height() * rows as f32
    }

    /// The PV box of an eye whose HUD area starts at `ox`: (x, y, w, h).
    fn pv_box(&self, ox: f32) -> (f32, f32, f32, f32) {
        let w = (self.content_w() * 0.22).clamp(80.0, 320.0);
        let h = w * 0.7;
        let m = self.margin();
        (ox + self.content_w() - m - w, m + self.line_height(), w, h)
    }

    /// Where a body-frame point lands in eye `i` (pixels in the whole target), if in front of it.
    fn project(&self, eye: &EyeUniform, i: u32, p: Vec3) -> Option<(f32, f32)> {
        let m = Mat4::from_cols_array_2d(&eye.view_proj) * Mat4::from_cols_array_2d(&eye.model);
        let c = m * Vec4::new(p.x, p.y, p.z, 1.0);
        if !(c.w > 1e-3 && c.is_finite()) {
            return None;
        }
        let (x, y) = (c.x / c.w, c.y / c.w);
        if !(-1.2..=1.2).contains(&x) || !(-1.2..=1.2).contains(&y) {
            return None;
        }
        Some((
            (i * self.eye_width) as f32 + (x * 0.5 + 0.5) * self.eye_width as f32,
            (0.5 - y * 0.5) * self.height as f32,
        ))
    }

    /// The body-frame points of the anchored labels: R, L beside each lung's outer side, the head
    /// cue above the apices, the feet cue below the bases (each lung's rigid offset applied).
    fn anchors(&self, frame: &EngineFrame) -> [Option<Vec3>; 4] {
        let mut out = [None; 4];
        let (mut top, mut bottom, mut mid) = (f32::NEG_INFINITY, f32::INFINITY, Vec3::ZERO);
        let mut n = 0.0;
        for (k, b) in self.config.lung_boxes.iter().enumerate() {
            let Some((lo, hi)) = *b else {
                continue;
            };
            let off = Vec3::from(frame.lungs[k].offset_mm);
            let off = if off.is_finite() { off } else { Vec3::ZERO };
            let (lo, hi) = (Vec3::from(lo) + off, Vec3::from(hi) + off);
            let c = (lo + hi) * 0.5;
            // +X is the patient's left: the right lung's outer side is its smallest x.
            let outer = if k == ipc_types::LUNG_RIGHT {
                lo.x - 30.0
            } else {
                hi.x + 30.0
            };
            out[k] = Some(Vec3::new(outer, c.y, c.z));
            top = top.max(hi.z);
            bottom = bottom.min(lo.z);
            mid += c;
            n += 1.0;
        }
        if n > 0.0 {
            let mid = mid / n;
            out[2] = Some(Vec3::new(mid.x, mid.y, top + 35.0));
            out[3] = Some(Vec3::new(mid.x, mid.y, bottom - 35.0));
        }
        out
    }

    /// The backdrop of anchored label `k` (R, L, head, feet) centred on `p`: its shaped text with
    /// a little room on each side, one row high.
    fn label_box(&self, k: usize, p: (f32, f32)) -> Rect {
        let block = LABEL_R + k;
        let h = self.buffers[block].metrics().line_height;
        let w = self.widths[block] + self.font_px * 0.6;
        Rect {
            x: p.0 - w * 0.5,
            y: p.1 - h * 0.5,
            w,
            h,
        }
    }

    /// Where this frame's HUD parts go in each eye drawn through `eyes`' cameras (`None` past the
    /// HUD's eyes): the panels, the text blocks, and the anchored labels moved off the panels — a
    /// label projected onto the panel (the head cue at 480 × 360) goes to the nearest clear place.
    pub fn layout(&self, eyes: &[EyeUniform], frame: &EngineFrame) -> [Option<EyeLayout>; 2] {
        let anchors = self.anchors(frame);
        let mut out = [None; 2];
        for (i, slot) in out
            .iter_mut()
            .enumerate()
            .take(self.eyes.min(eyes.len() as u32) as usize)
        {
            *slot = Some(self.eye_layout(&eyes[i], i as u32, &anchors, frame));
        }
        out
    }

    /// The lungs' boxes (moved by their offsets) projected into eye `i`: the bounding rectangle
    /// of their corners; `None` without lungs or when a corner does not project.
    fn lungs_on_screen(&self, eye: &EyeUniform, i: u32, frame: &EngineFrame) -> Option<Rect> {
        let (mut lo, mut hi) = (
            (f32::INFINITY, f32::INFINITY),
            (f32::NEG_INFINITY, f32::NEG_INFINITY),
        );
        let mut any = false;
        for (k, b) in self.config.lung_boxes.iter().enumerate() {
            let Some((a, c)) = *b else { continue };
            let off = Vec3::from(frame.lungs[k].offset_mm);
            let off = if off.is_finite() { off } else { Vec3::ZERO };
            for corner in 0..8 {
                let p = Vec3::new(
                    if corner & 1 == 0 { a[0] } else { c[0] },
                    if corner & 2 == 0 { a[1] } else { c[1] },
                    if corner & 4 == 0 { a[2] } else { c[2] },
                ) + off;
                let (x, y) = self.project(eye, i, p)?;
                lo = (lo.0.min(x), lo.1.min(y));
                hi = (hi.0.max(x), hi.1.max(y));
                any = true;
            }
        }
        any.then_some(Rect {
            x: lo.0,
            y: lo.1,
            w: hi.0 - lo.0,
            h: hi.1 - lo.1,
        })
    }

    /// Text block `k` at `(left, top)` clipped to `clip`: its shaped extent.
    fn text_box(&self, k: usize, left: f32, top: f32, clip: Rect) -> TextBox {
        let lh = self.buffers[k].metrics().line_height;
        TextBox {
            text: Rect {
                x: left,
                y: top,
                w: self.widths[k],
                h: lh * self.rows[k] as f32,
            },
            clip,
        }
    }

    fn eye_layout(
        &self,
        eye: &EyeUniform,
        i: u32,
        anchors: &[Option<Vec3>; 4],
        frame: &EngineFrame,
    ) -> EyeLayout {
        let (lh, m) = (self.line_height(), self.margin());
        let ox = self.eye_origin(i);
        let area = Rect {
            x: (i * self.eye_width) as f32,
            y: 0.0,
            w: self.eye_width as f32,
            h: self.height as f32,
        };
        let panel = Rect {
            x: ox + m * 0.5,
            y: m * 0.5,
            w: self.panel_w(),
            h: lh * self.panel_rows() as f32 + m,
        };
        let (px, py, pw, ph) = self.pv_box(ox);
        let pv = Rect {
            x: px,
            y: py - lh,
            w: pw,
            h: ph + lh,
        };
        let legend_rows = self.legend_rows();
        let legend = (legend_rows > 0).then(|| {
            let w = self.widths[LEGEND].max(self.widths[LOBE_WARNING]) + m;
            Rect {
                x: ox + m * 0.5,
                y: self.legend_top(legend_rows),
                w: w.min(self.content_w() - m),
                h: lh * legend_rows as f32 + m,
            }
        });
        let obstacles = [Some(panel), Some(pv), legend];
        let mut labels = [None; 4];
        for (k, label) in labels.iter_mut().enumerate() {
            *label = anchors[k]
                .and_then(|a| self.project(eye, i, a))
                .and_then(|p| place_label(self.label_box(k, p), &obstacles, area, m * 0.25));
        }
        let mut texts = [None; BLOCKS];
        let bar_w = self.bar_w();
        for (k, slot) in texts.iter_mut().enumerate().take(PANEL_LINES) {
            if self.shown(k) {
                let left = if k == PHASE {
                    ox + m + bar_w + m
                } else {
                    ox + m
                };
                *slot = Some(self.text_box(k, left, self.row_top(k), panel));
            }
        }
        texts[PV_TITLE] = Some(self.text_box(PV_TITLE, px + 4.0, py - lh * 0.9, pv));
        if let Some(legend) = legend {
            // The warning above the legend's row(s), both inside its backdrop.
            let mut top = legend.y + m * 0.5;
            for k in [LOBE_WARNING, LEGEND] {
                if !self.lines[k].is_empty() {
                    texts[k] = Some(self.text_box(k, ox + m, top, legend));
                    top += lh * self.rows[k] as f32;
                }
            }
        }
        if !self.lines[VEIL].is_empty() {
            let band = Rect {
                x: area.x,
                y: self.height as f32 * 0.5 - lh,
                w: area.w,
                h: lh * 2.0,
            };
            let w = self.widths[VEIL];
            let left = area.x + (area.w - w).max(0.0) * 0.5;
            let top = band.y + (band.h - self.buffers[VEIL].metrics().line_height) * 0.5;
            texts[VEIL] = Some(self.text_box(VEIL, left, top, band));
        }
        for (k, label) in labels.iter().enumerate() {
            if let Some(r) = label {
                let block = LABEL_R + k;
                let (cx, cy) = r.centre();
                let lh = self.buffers[block].metrics().line_height;
                let left = cx - self.widths[block] * 0.5;
                texts[block] = Some(self.text_box(block, left, cy - lh * 0.5, *r));
            }
        }
        EyeLayout {
            eye: area,
            panel,
            pv,
            legend,
            labels,
            texts,
            lungs: self.lungs_on_screen(eye, i, frame),
        }
    }

    /// Take `frame` into the PV loop and the trace, and choose what the PV box shows: a site's
    /// box turns to the trace while the source's patient drives its lungs, and back (its title
    /// reshaped only on the change).
    fn record(&mut self, frame: &EngineFrame) {
        self.pv.record(frame);
        if self.config.signal || self.config.remote_site {
            self.trace.record(frame, self.config.tick_hz);
        }
        let shows = text::pv_box_shows(&self.config, frame.state);
        if shows != self.pv_box {
            self.pv_box = shows;
            self.choose_pv_title();
        }
    }

    /// Record the HUD pass for this frame over `target` (the resolved colour target, its eyes side
    /// by side), drawn through `eyes`' cameras.
    pub fn encode(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        encoder: &mut wgpu::CommandEncoder,
        target: &wgpu::TextureView,
        eyes: &[EyeUniform],
        f: &HudFrame,
    ) {
        self.record(f.frame);
        self.update_lines(f);
        self.vertices.clear();
        let lh = self.line_height();
        let m = self.margin();
        let bar_w = self.bar_w();
        let layouts = self.layout(eyes, f.frame);
        for (i, layout) in layouts.iter().enumerate() {
            let Some(layout) = layout else {
                continue;
            };
            let i = i as u32;
            let ox = self.eye_origin(i);
            // Veil text box across the middle.
            if let Some(veil) = layout.texts[VEIL] {
                self.push_rect(veil.clip.tuple(), linear(0, 0, 0, 0.55));
            }
            self.push_rect(layout.panel.tuple(), linear(0, 0, 0, 0.45));
            // The breath-phase bar: inspiration part, expiration part, the current phase.
            let (bx, by, bh) = (ox + m, self.row_top(PHASE) + lh * 0.2, lh * 0.6);
            match text::breath_phase(f.frame) {
                Some((phase, _, split)) => {
                    self.push_rect((bx, by, bar_w * split, bh), linear(40, 90, 120, 0.9));
                    self.push_rect(
                        (bx + bar_w * split, by, bar_w * (1.0 - split), bh),
                        linear(40, 60, 70, 0.9),
                    );
                    self.push_rect((bx, by, bar_w * phase, bh), linear(120, 210, 255, 0.95));
                    self.push_rect(
                        (bx + bar_w * phase - 1.5, by - 2.0, 3.0, bh + 4.0),
                        linear(255, 255, 255, 1.0),
                    );
                }
                None => self.push_rect((bx, by, bar_w, bh), linear(60, 60, 60, 0.9)),
            }
            // The PV loop's box: the loop, or the signal trace in a scene that follows the signal.
            let (px, py, pw, ph) = self.pv_box(ox);
            self.push_rect(layout.pv.tuple(), linear(0, 0, 0, 0.45));
            let frame_color = linear(120, 130, 140, 0.9);
            let corners = [(px, py), (px + pw, py), (px + pw, py + ph), (px, py + ph)];
            for k in 0..4 {
                self.push_line(corners[k], corners[(k + 1) % 4], 1.0, frame_color);
            }
            if self.pv_box != text::PvBox::Loop {
                self.push_trace((px + 4.0, py + 4.0, pw - 8.0, ph - 8.0));
            } else if let Some(scale) = text::PvScale::fit(self.pv.points()) {
                let inner = (px + 4.0, py + 4.0, pw - 8.0, ph - 8.0);
                let mut prev: Option<(f32, f32)> = None;
                for k in 0..text::PV_BINS {
                    let Some(pt) = self.pv.point(k) else { continue };
                    let q = scale.to_px(pt, inner);
                    if let Some(p) = prev {
                        self.push_line(p, q, 2.0, linear(230, 230, 235, 0.9));
                    }
                    prev = Some(q);
                }
                if let Some(c) = self.pv.current {
                    let (cx, cy) = scale.to_px(c, inner);
                    self.push_rect((cx - 4.5, cy - 4.5, 9.0, 9.0), linear(255, 196, 64, 1.0));
                }
            }
            // The lobe legend's panel (bottom left).
            if let Some(legend) = layout.legend {
                self.push_rect(legend.tuple(), linear(0, 0, 0, 0.55));
            }
            // Backdrops under the anchored labels so they read over bright tissue.
            for label in layout.labels.iter().flatten() {
                self.push_rect(label.tuple(), linear(0, 0, 0, 0.5));
            }
        }
        queue.write_buffer(&self.vertex_buffer, 0, bytemuck::cast_slice(&self.vertices));
        let (w, h) = (self.eye_width * self.eyes, self.height);
        self.viewport.update(
            queue,
            Resolution {
                width: w,
                height: h,
            },
        );
        let buffers = &self.buffers;
        let colors = self.colors;
        let areas = layouts
            .iter()
            .flatten()
            .flat_map(|l| l.texts.iter().enumerate())
            .filter_map(|(k, t)| t.map(|t| (k, t)))
            .map(|(k, t)| TextArea {
                buffer: &buffers[k],
                left: t.text.x,
                top: t.text.y,
                scale: 1.0,
                bounds: TextBounds {
                    left: t.clip.x.floor() as i32,
                    top: t.clip.y.floor() as i32,
                    right: (t.clip.x + t.clip.w).ceil() as i32,
                    bottom: (t.clip.y + t.clip.h).ceil() as i32,
                },
                default_color: colors[k],
                custom_glyphs: &[],
            });
        // A glyph that does not fit the atlas is left out of this frame, never a failure.
        let _ = self.text.prepare(
            device,
            queue,
            &mut self.font_system,
            &mut self.atlas,
            &self.viewport,
            areas,
            &mut self.swash,
        );
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("lungdyn hud"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: target,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Load,
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            if !self.vertices.is_empty() {
                pass.set_pipeline(&self.pipeline);
                pass.set_vertex_buffer(0, self.vertex_buffer.slice(..));
                pass.draw(0..self.vertices.len() as u32, 0..1);
            }
            let _ = self.text.render(&self.atlas, &self.viewport, &mut pass);
        }
        self.atlas.trim();
    }
}

#[cfg(test)]
mod tests {
    use super::{place_label, Rect};

    fn r(x: f32, y: f32, w: f32, h: f32) -> Rect {
        Rect { x, y, w, h }
    }

    #[test]
    fn a_label_clear_of_the_panels_stays_where_it_is() {
        let eye = r(0.0, 0.0, 480.0, 360.0);
        let want = r(200.0, 200.0, 60.0, 16.0);
        let panel = Some(r(5.0, 5.0, 350.0, 110.0));
        assert_eq!(
            place_label(want, &[panel, None, None], eye, 2.0),
            Some(want)
        );
    }

    #[test]
    fn a_label_on_a_panel_moves_to_the_nearest_clear_place() {
        let eye = r(0.0, 0.0, 480.0, 360.0);
        let panel = r(5.0, 5.0, 350.0, 110.0);
        let pv = r(364.0, 14.0, 106.0, 88.0);
        // The head cue projected onto the panel's lower edge: moved just below it, not sideways.
        let want = r(210.0, 100.0, 60.0, 16.0);
        let got = place_label(want, &[Some(panel), Some(pv), None], eye, 2.0).unwrap();
        assert_eq!((got.x, got.y), (210.0, 117.0));
        assert!(!got.overlaps(&panel) && !got.overlaps(&pv) && eye.contains(&got));
        // Off the eye's right edge and on the PV box: inside the eye, below the PV box.
        let want = r(450.0, 50.0, 60.0, 16.0);
        let got = place_label(want, &[Some(panel), Some(pv), None], eye, 2.0).unwrap();
        assert_eq!((got.x, got.y), (420.0, 104.0));
        // In the second eye of a stereo pair, the area is that eye's.
        let eye2 = r(480.0, 0.0, 480.0, 360.0);
        let want = r(470.0, 300.0, 60.0, 16.0);
        let got = place_label(want, &[None, None, None], eye2, 2.0).unwrap();
        assert_eq!((got.x, got.y), (480.0, 300.0));
    }

    #[test]
    fn a_label_with_no_room_is_left_out() {
        let eye = r(0.0, 0.0, 100.0, 40.0);
        let want = r(20.0, 10.0, 60.0, 16.0);
        // The panel covers the whole eye.
        let panel = Some(r(0.0, 0.0, 100.0, 40.0));
        assert_eq!(place_label(want, &[panel, None, None], eye, 2.0), None);
        // Wider than the eye, or a non-finite projection.
        assert_eq!(
            place_label(r(0.0, 0.0, 120.0, 16.0), &[None; 3], eye, 2.0),
            None
        );
        assert_eq!(
            place_label(r(f32::NAN, 0.0, 10.0, 16.0), &[None; 3], eye, 2.0),
            None
        );
    }
}
