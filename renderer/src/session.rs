//! One renderer session: wake on engine frames, late-latch the HMD pose, draw, report.
//!
//! A [`Session`] paces itself on the engine stream with the same [`Pacer`] the engine uses on the
//! tracker stream: a fresh engine frame is drawn at once, with the newest HMD pose taken from the
//! tracker stream just before the draw (late latching); if the engine is late or gone, the deadline
//! fallback redraws the last frame (flagged stale) so the display never freezes. Each frame's hop
//! stamps and CPU/GPU times go out on the report stream for the latency harness.
//!
//! Every engine frame names, per lung, the kernel it was computed for. A lung whose kernel is not
//! the one this renderer loaded is drawn at rest — never with another lung's displacements — and the
//! frame is flagged [`report_flags::KERNEL_MISMATCH`], counted, and said once on stderr. The same
//! holds for a lung whose coefficients are not of the renderer's deformation mode (an engine started
//! with another scene's `[lungs] mode`).
//!
//! Headless, [`crate::process::run`] drives the session in a loop; with `--window`, [`crate::window`] drives the
//! same session from the window's event loop and presents each frame.

use std::path::PathBuf;

use ipc_types::{
    report_flags, EngineFrame, FrameReport, Message, Pose, TrackerFrame, LAYOUT_VERSION, LUNG_LEFT,
    LUNG_RIGHT, NUM_LUNGS, TOOL_HMD,
};
use lung_model::scene::Scene;
use transport::clock::{Clock, Monotonic};
use transport::iox::{self, IoxNode};
use transport::pacer::{PacerConfig, Wake};
use transport::process::pin_to_core;
use transport::{Instance, Pacer, PortError, Publish, Receive};

use crate::gpu::Gpu;
use crate::{DrawState, LungRenderer};

use crate::options::{HudSwitch, RendererArgs, RendererError, SnapshotView};
use lung_model::scene::SceneExt;

/// The streams a session reads and writes.
pub struct Ports {
    /// Engine frames in.
    pub engine: Box<dyn Receive<EngineFrame>>,
    /// Tracker frames in (for the HMD pose).
    pub tracker: Box<dyn Receive<TrackerFrame>>,
    /// Frame reports out.
    pub report: Box<dyn Publish<FrameReport>>,
}

/// Snapshot options of a session.
#[derive(Debug, Clone, Default)]
pub struct Snapshots {
    /// Engine ticks at or after which to write a PNG.
    pub ticks: Vec<u64>,
    /// Folder for the PNGs.
    pub dir: PathBuf,
    /// Where the snapshots are drawn from.
    pub view: SnapshotView,
    /// Snapshots over one breath, planned when it starts ([`crate::record::BreathPlan`]).
    pub breath: Option<crate::record::BreathPlan>,
}

/// What the session has drawn so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SessionStats {
    /// Frames drawn and reported.
    pub frames: u64,
    /// Frames drawn without a fresh engine frame.
    pub stale_frames: u64,
    /// Frames in which at least one lung's kernel did not match the engine's.
    pub kernel_mismatch_frames: u64,
    /// PNG snapshots written.
    pub snapshots: u32,
    /// Of those, planned ticks whose own frame was not drawn (the renderer skipped it under load):
    /// each took the next drawn frame ([`Session::step`]).
    pub snapshots_substituted: u32,
}

/// One renderer session: its GPU state, its ports and its frame loop state.
pub struct Session {
    /// The GPU.
    pub gpu: Gpu,
    /// The lungs' GPU state and offscreen target.
    pub renderer: LungRenderer,
    instance: String,
    lock: Option<transport::instance::InstanceLock>,
    node: Option<IoxNode>,
    ports: Ports,
    clock: Box<dyn Clock>,
    pacer: Pacer<EngineFrame>,
    stop_at: Option<u64>,
    last: Option<EngineFrame>,
    hmd: Pose,
    predictor: crate::predict::HmdPredictor,
    /// Kernel id of each lung slot as loaded (0: this renderer has no such lung).
    kernel_ids: [u64; NUM_LUNGS],
    kernel_paths: [Option<PathBuf>; NUM_LUNGS],
    /// Coefficient kind and count each slot's frames must carry.
    coeff_shape: [(u32, u32); NUM_LUNGS],
    mismatch_said: bool,
    stats: SessionStats,
    snapshots: Snapshots,
    next_target: usize,
    snapshot_view: Option<Pose>,
    /// A tension pneumothorax scene's control stream and affected lung (the window's keys).
    control: Option<(
        Box<dyn Publish<ipc_types::ControlPacket>>,
        lung_model::mesh::Side,
    )>,
    control_sequence: u64,
    /// The engine's answers to interventions (this window's keys and `lungdyn scene event`).
    replies: Option<Box<dyn Receive<ipc_types::ControlReply>>>,
    /// The heads-up display and whether it is drawn (`--hud`, the H key).
    hud: Option<crate::hud::Hud>,
    hud_on: bool,
    /// What the HUD shows beside the engine frame: the newest tracker frame, the previous frame's
    /// times, the latest intervention's line.
    last_tracker: Option<TrackerFrame>,
    last_timing: (u64, Option<u64>, Option<u64>),
    outcome: String,
    outcome_standing: Option<crate::hud::text::Standing>,
    /// systemd's watchdog, pinged from [`Session::step`] (disabled outside a unit).
    watchdog: transport::notify::Watchdog,
    /// Stale frames in a row, and the time of the last fresh engine frame (the engine-down notice).
    stale_run: u64,
    last_fresh_ns: u64,
    /// The quality governor (`[render] governor = "hold-deadline"`), and whether its floor was said.
    governor: Option<crate::governor::Governor>,
    floor_said: bool,
    /// The accuracy opt-in asked for with nothing to cap, in words, for the start line.
    idle_opt_in: Option<String>,
    /// Where the governor's start is kept (`[render] governor_start = "remembered"`), whether a
    /// file was there, and what the start found, in words for the start line.
    memory: Option<(crate::governor_memory::Memory, bool)>,
    start_note: Option<String>,
}

/// Where a drawn frame goes after the offscreen draw: a window surface, an OpenXR swapchain, or
/// nowhere (headless). A closure `FnMut(&mut CommandEncoder)` is an output that records extra work
/// into the frame and presents nothing.
pub trait FrameOutput {
    /// When the frame will be shown (CLOCK_MONOTONIC, ns), if the output knows (OpenXR's predicted
    /// display time): the HMD pose is predicted to it instead of `--predict-ms` past the draw.
    fn display_time_ns(&mut self) -> Option<u64> {
        None
    }
    /// Record this output's pass into the frame's command buffer (after the draw, same submit).
    fn encode(&mut self, encoder: &mut wgpu::CommandEncoder);
    /// After the submit: present, and return when `present` returned (CLOCK_MONOTONIC, ns);
    /// `None` when nothing was presented this frame.
    fn present(&mut self) -> Option<u64> {
        None
    }
    /// The eyes to draw this frame with, when the output knows them (an OpenXR runtime's views
    /// located for the display time); asked after [`Self::display_time_ns`].
    fn eyes(&mut self) -> Option<crate::camera::HmdEyes> {
        None
    }
    /// The [`ipc_types::present_mode`] code and the frame latency, for the report.
    fn mode(&self) -> (u32, u32) {
        (ipc_types::present_mode::NONE, 0)
    }
}

/// Headless: the frame stays offscreen (snapshots read it back), nothing is presented.
pub struct Headless;

impl FrameOutput for Headless {
    fn encode(&mut self, _: &mut wgpu::CommandEncoder) {}
}

impl<F: FnMut(&mut wgpu::CommandEncoder)> FrameOutput for F {
    fn encode(&mut self, encoder: &mut wgpu::CommandEncoder) {
        self(encoder)
    }
}

/// Keep Mesa quiet on headless machines: without XDG_RUNTIME_DIR its window-system probing prints an
/// alarming but harmless "error:" line. Call before any thread starts.
pub fn quiet_mesa() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        let dir = std::env::temp_dir().join("lungdyn-runtime");
        if std::fs::create_dir_all(&dir).is_ok() {
            std::env::set_var("XDG_RUNTIME_DIR", &dir);
        }
    }
}

impl Session {
    /// Load the scene's kernels (never baking), upload them to `gpu` and open the iceoryx2 ports.
    pub fn new(args: &RendererArgs, gpu: Gpu) -> Result<Self, RendererError> {
        let run_ns = args.process.run_ns()?;
        check_predict_ms(args.predict_ms)?;
        let instance = Instance::new(&args.process.instance)?;
        let lock = instance.lock("renderer")?;
        // `run` pinned the whole process already; a caller that opens a session itself (tests) is
        // pinned here, its main thread only.
        pin_to_core(args.process.cpu, "renderer")?;
        transport::trace::init("renderer");
        let (scene, rig_files) = args.scene_and_rig()?;
        if args.process.realtime || scene.processes.realtime {
            transport::realtime::apply("renderer");
        }
        let mut snapshots = Snapshots {
            ticks: args.snapshot_ticks.clone(),
            dir: args.snapshot_dir.clone(),
            view: match (args.snapshot_fixed_view, args.snapshot_view) {
                (true, _) => SnapshotView::First,
                (false, v) => v.unwrap_or_default(),
            },
            breath: args
                .snapshot_breath
                .map(|n| crate::record::BreathPlan::new(n, args.snapshot_after_tick)),
        };
        snapshots.ticks.sort_unstable();
        if !snapshots.ticks.is_empty() || snapshots.breath.is_some() {
            std::fs::create_dir_all(&snapshots.dir).map_err(|source| {
                RendererError::SnapshotDir {
                    path: snapshots.dir.clone(),
                    source,
                }
            })?;
        }
        let mut lungs = Vec::new();
        for &side in &scene.lungs.sides {
            let kernel = scene.lung_kernel(side)?;
            lungs.push(crate::RenderLung::from_kernel(&kernel, scene.lungs.mode)?);
        }
        let renderer = LungRenderer::with_rig(&gpu, &scene.render, &rig_files.rig(), &lungs)?;
        let hud_config = crate::hud::HudConfig::of(&scene, &lungs);
        if let Some(which) = hud_config
            .lobes
            .and_then(crate::hud::text::lungs_without_lobes)
        {
            eprintln!(
                "renderer[{}]: warning: colour \"lobes\": no lobe data for the {which} (a kernel \
                 baked before the lobe section existed): drawn grey, as the HUD legend says; bake \
                 the kernel again to see its lobes",
                instance.name()
            );
        }
        let node = iox::node(&instance, "renderer")?;
        let mut engine = instance.engine_inlet(&node)?;
        engine.set_wake(transport::wake::announce(
            "renderer",
            instance.name(),
            "engine frames",
            scene.processes.wake.renderer,
            scene.processes.spin_us,
            args.process.cpu,
            scene.processes.reserved_core(lung_model::scene::RENDERER),
        )?);
        let ports = Ports {
            engine: Box::new(engine),
            tracker: Box::new(instance.tracker_inlet(&node)?),
            report: Box::new(instance.report_outlet(&node)?),
        };
        let mut session = Self::assemble(
            gpu,
            renderer,
            &scene,
            &lungs,
            ports,
            Box::new(Monotonic),
            snapshots,
            instance.name(),
        );
        session.stop_at = run_ns.map(|d| session.clock.now_ns().saturating_add(d));
        session.set_hud(hud_config, args.hud == HudSwitch::On);
        session.predictor = crate::predict::HmdPredictor::new(args.predict_ms);
        if let Some(d) = &scene.disease {
            if d.kind == lung_model::scene_disease::DiseaseKind::TensionPneumothorax {
                if let Some(side) = d.side {
                    session.control = Some((Box::new(instance.control_outlet(&node)?), side));
                }
            }
            // Any disease scene: the outcome of an action sent from anywhere is shown.
            session.replies = Some(Box::new(instance.control_reply_inlet(&node)?));
        }
        if scene.render.governor_start == lung_model::scene::GovernorStart::Remembered {
            if let Some(dir) = crate::lod_cache::dir_from_env() {
                session.start_where_settled(&dir);
            }
        }
        session.node = Some(node);
        session.lock = Some(lock);
        session.watchdog = transport::notify::Watchdog::from_env();
        transport::notify::ready(&format!("renderer[{}]: drawing", instance.name()));
        let (w, h) = session.renderer.image_size();
        eprintln!(
            "renderer[{}]: {} vertices in the {} mode ({:.1} MiB on the GPU), {}x{} {:?}{}, {} look, {} colour, {}x MSAA, {}, {} on {}{}; waiting for engine frames on {:?}",
            instance.name(),
            session.renderer.vertex_count(),
            session.renderer.mode(),
            session.renderer.uploaded_bytes() as f64 / 1048576.0,
            w,
            h,
            scene.render.mode,
            if scene.render.stereo { " stereo" } else { "" },
            scene.render.look,
            scene.render.color,
            session.renderer.samples(),
            session.renderer.describe_lod(),
            session.describe_governor(),
            session.gpu.describe(),
            rig_files.describe(),
            instance.engine()
        );
        Ok(session)
    }

    /// A session over any ports and clock (tests drive it with in-memory ports on a fake clock).
    #[allow(clippy::too_many_arguments)]
    pub fn assemble(
        gpu: Gpu,
        renderer: LungRenderer,
        scene: &Scene,
        lungs: &[crate::RenderLung],
        ports: Ports,
        clock: Box<dyn Clock>,
        snapshots: Snapshots,
        instance: &str,
    ) -> Self {
        let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
        let mut kernel_ids = [0u64; NUM_LUNGS];
        let mut kernel_paths: [Option<PathBuf>; NUM_LUNGS] = Default::default();
        let mut coeff_shape = [(0u32, 0u32); NUM_LUNGS];
        for lung in lungs {
            kernel_ids[lung.side.index()] = lung.kernel_id;
            kernel_paths[lung.side.index()] =
                scene.lungs.kernels.get(lung.side).map(|p| p.to_path_buf());
            coeff_shape[lung.side.index()] =
                (lung.mode().coeff_kind(), lung.lung.coeff_count() as u32);
        }
        let start = clock.now_ns();
        Self {
            gpu,
            renderer,
            instance: instance.to_string(),
            lock: None,
            node: None,
            ports,
            pacer: Pacer::new(PacerConfig::for_period(period_ns), start),
            clock,
            stop_at: None,
            last: None,
            hmd: default_hmd(),
            predictor: crate::predict::HmdPredictor::new(16.7),
            kernel_ids,
            kernel_paths,
            coeff_shape,
            mismatch_said: false,
            stats: SessionStats::default(),
            snapshots,
            next_target: 0,
            snapshot_view: None,
            control: None,
            control_sequence: 0,
            replies: None,
            hud: None,
            hud_on: false,
            last_tracker: None,
            last_timing: (0, None, None),
            outcome: String::new(),
            outcome_standing: None,
            watchdog: transport::notify::Watchdog::every(None),
            stale_run: 0,
            last_fresh_ns: 0,
            governor: None,
            floor_said: false,
            idle_opt_in: None,
            memory: None,
            start_note: None,
        }
        .with_governor(scene, period_ns)
    }

    /// The quality governor for `scene` at a frame period of `period_ns`: it holds each frame's
    /// cost to the period less the tracker bridge's and the engine's budgets (what is left once
    /// the renderer's inputs have arrived; 13.7 ms by default), with the steps the renderer built.
    fn with_governor(mut self, scene: &Scene, period_ns: u64) -> Self {
        if scene.render.governor == lung_model::scene::Governor::HoldDeadline {
            let b = &scene.processes.budget_ms;
            let upstream_ns = ((b.tracker_bridge + b.engine) * 1e6) as u64;
            let target = period_ns.saturating_sub(upstream_ns).max(period_ns / 2);
            let steps = self.renderer.governor_steps().to_vec();
            self.idle_opt_in =
                crate::governor::idle_accuracy_opt_in(scene.render.governor_least_bands, &steps);
            self.governor = Some(crate::governor::Governor::new(steps, target));
        }
        self
    }

    /// Start the governor where the last run of these lungs on this adapter settled, kept in
    /// `dir` ([`crate::governor_memory`]), and keep where this run settles there at its end.
    pub fn start_where_settled(&mut self, dir: &std::path::Path) {
        use crate::governor_memory::{Fingerprint, Start};
        let Some(g) = self.governor.as_mut() else {
            return;
        };
        let info = &self.gpu.info;
        let print = Fingerprint {
            adapter: format!(
                "{} ({:?}, {} {}) {:?}",
                info.name, info.backend, info.driver, info.driver_info, info.device_type
            ),
            steps: g.steps(),
            target_ns: g.target_ns(),
            image: self.renderer.image_size(),
            samples: self.renderer.samples(),
            lungs: format!(
                "{}, {} vertices, levels {:?}",
                self.renderer.mode(),
                self.renderer.vertex_count(),
                self.renderer.lod_triangles()
            ),
        };
        let memory = print.memory(dir);
        let start = memory.start(g.steps());
        self.start_note = start.describe(g.steps());
        let existed = !matches!(start, Start::Nothing) || memory.path.exists();
        if let Start::Remembered {
            given_up, bought, ..
        } = &start
        {
            g.start_at(*given_up, bought);
            self.renderer.set_quality(g.quality());
        }
        self.memory = Some((memory, existed));
    }

    /// Hold frames to `target_ns` instead of the scene's (a test's way to make any machine's
    /// frames late, or all of them on time); nothing without a governor.
    pub fn set_governor_target_ns(&mut self, target_ns: u64) {
        if let Some(g) = self.governor.as_mut() {
            g.set_target_ns(target_ns);
        }
    }

    /// The governor in words, for the start line.
    pub fn describe_governor(&self) -> String {
        let mut described = self.describe_steps();
        for note in [&self.idle_opt_in, &self.start_note].into_iter().flatten() {
            described.push_str("; ");
            described.push_str(note);
        }
        described
    }

    /// The governor and the steps it may take, in words.
    fn describe_steps(&self) -> String {
        match &self.governor {
            None => "governor off".to_string(),
            Some(g) if g.steps().is_empty() => format!(
                "governor hold-deadline ({:.1} ms a frame; nothing this scene draws can be given up)",
                g.target_ns() as f64 / 1e6
            ),
            Some(g) => {
                let steps: Vec<&str> = g.steps().iter().map(|s| s.name()).collect();
                format!(
                    "governor hold-deadline ({:.1} ms a frame; may give up, in order: {})",
                    g.target_ns() as f64 / 1e6,
                    steps.join(", ")
                )
            }
        }
    }

    /// Feed the governor the frame that cost `cost_ns` (0: not measured) and apply its change,
    /// saying it on stderr (changes are few: each waits for a window of frames). Returns the
    /// frame's governor bits for its report.
    fn govern(&mut self, cost_ns: u64) -> u32 {
        use crate::governor::Change;
        let Some(g) = self.governor.as_mut() else {
            return 0;
        };
        let drawn = g.quality().report_bits();
        let change = g.observe(cost_ns);
        let floor = g.report_bits() & report_flags::GOVERNOR_FLOOR;
        let target_ms = g.target_ns() as f64 / 1e6;
        let ms = |ns: u64| ns as f64 / 1e6;
        match change {
            None => {}
            Some(Change::Down {
                step,
                quality,
                cost_ns,
            }) => {
                let _span =
                    tracing::info_span!(target: transport::trace::TARGET, "quality down").entered();
                self.renderer.set_quality(quality);
                eprintln!(
                    "renderer[{}]: governor: gives up {} (frames took {:.1} ms, 75th percentile, over the \
                     {target_ms:.1} ms target); drawing with {}",
                    self.instance,
                    step.name(),
                    ms(cost_ns),
                    quality.describe()
                );
            }
            Some(Change::Up {
                step,
                quality,
                cost_ns,
                predicted_ns,
            }) => {
                let _span =
                    tracing::info_span!(target: transport::trace::TARGET, "quality up").entered();
                self.renderer.set_quality(quality);
                eprintln!(
                    "renderer[{}]: governor: {} taken back (frames took {:.1} ms, median; {:.1} ms \
                     predicted with it, within {:.0} % of the {target_ms:.1} ms target); drawing \
                     with {} quality",
                    self.instance,
                    step.name(),
                    ms(cost_ns),
                    ms(predicted_ns),
                    crate::governor::UP_MARGIN * 100.0,
                    quality.describe()
                );
            }
            Some(Change::Floor { cost_ns }) => {
                let _span = tracing::info_span!(target: transport::trace::TARGET, "quality floor")
                    .entered();
                if !self.floor_said {
                    self.floor_said = true;
                    eprintln!(
                        "renderer[{}]: governor: at its floor: with {} the frames still take {:.1} ms \
                         (75th percentile) against its {target_ms:.1} ms target and nothing is left \
                         to give up; frames may miss the deadline (those at the floor are counted \
                         and flagged)",
                        self.instance,
                        g.quality().describe(),
                        ms(cost_ns)
                    );
                }
            }
        }
        drawn | floor
    }

    /// Send a trainee's intervention on the tension pneumothorax's side to the engine; `None` when
    /// the scene has none, else the lung it was sent for.
    pub fn send_action(
        &mut self,
        kind: ipc_types::Intervention,
    ) -> Result<Option<lung_model::mesh::Side>, RendererError> {
        let Some((outlet, side)) = self.control.as_mut() else {
            return Ok(None);
        };
        self.control_sequence += 1;
        let packet = ipc_types::ControlPacket {
            layout_version: LAYOUT_VERSION,
            kind: kind.code(),
            lung: side.index() as u32,
            _pad: 0,
            origin: ipc_types::ORIGIN_LOCAL,
            // Unique among the engine's senders (it takes a repeated number as one action).
            sequence: ipc_types::control_sequence(
                std::process::id(),
                self.clock.now_ns().wrapping_add(self.control_sequence),
            ),
        };
        outlet.publish(&packet)?;
        crate::hud::text::sent_line(&mut self.outcome, kind, side.index() as u32);
        self.outcome_standing = Some(crate::hud::text::Standing::Pending);
        Ok(Some(*side))
    }

    /// Give the session a heads-up display for `config` (drawn when `on`).
    pub fn set_hud(&mut self, config: crate::hud::HudConfig, on: bool) {
        let (w, h) = self.renderer.image_size();
        let eyes = if self.renderer.is_stereo() { 2 } else { 1 };
        self.hud = Some(crate::hud::Hud::new(
            &self.gpu.device,
            &self.gpu.queue,
            config,
            w / eyes,
            h,
            eyes,
        ));
        self.hud_on = on;
    }

    /// Turn the heads-up display on or off (the window's H key); returns whether it is now on.
    pub fn toggle_hud(&mut self) -> bool {
        self.hud_on = !self.hud_on && self.hud.is_some();
        self.hud_on
    }

    /// The engine's answers that arrived: the latest becomes the HUD's outcome line (and is said
    /// on stderr once, in words).
    fn read_replies(&mut self) -> Result<(), RendererError> {
        let Some(replies) = self.replies.as_mut() else {
            return Ok(());
        };
        let mut latest: Option<ipc_types::ControlReply> = None;
        replies.drain(&mut |r: &ipc_types::ControlReply| {
            if r.check_layout().is_ok() {
                latest = Some(*r);
            }
        })?;
        if let Some(r) = latest {
            let tick_hz = self.hud.as_ref().map_or(60.0, |h| h.config().tick_hz);
            match ipc_types::Intervention::from_code(r.kind) {
                Some(kind) => {
                    let standing =
                        crate::hud::text::outcome_line(&mut self.outcome, kind, &r, tick_hz);
                    self.outcome_standing = Some(standing);
                }
                None => {
                    self.outcome.clear();
                    self.outcome
                        .push_str("an intervention this build does not know: ");
                    self.outcome.push_str(&r.text());
                    self.outcome_standing = Some(crate::hud::text::Standing::Failed);
                }
            }
            eprintln!("renderer[{}]: {}", self.instance, self.outcome);
        }
        Ok(())
    }

    /// True when the process was asked to stop or its time is up.
    pub fn should_stop(&self) -> bool {
        transport::stop::requested() || self.stop_at.is_some_and(|t| self.clock.now_ns() >= t)
    }

    /// Whether the engine is down: no engine frame for
    /// [`ipc_types::report_flags::ENGINE_DOWN_FRAMES`] frames (the window title says so).
    pub fn engine_down(&self) -> bool {
        self.stale_run >= report_flags::ENGINE_DOWN_FRAMES
    }

    /// What the session has drawn so far.
    pub fn stats(&self) -> SessionStats {
        self.stats
    }

    /// Per-lung scale, offset and coefficients to draw; a lung whose kernel or coefficients do not
    /// match what this renderer loaded is drawn at rest (scale 0). Returns whether any mismatched.
    fn lungs_to_draw(&mut self, frame: &EngineFrame, state: &mut DrawState) -> bool {
        state.deform_scale = [0.0; 2];
        state.offset_mm = [[0.0; 3]; 2];
        state.collapse = [0.0; 2];
        state.hilum_mm = [[0.0; 3]; 2];
        let mut mismatch = false;
        for slot in 0..NUM_LUNGS {
            let lung = &frame.lungs[slot];
            let loaded = self.kernel_ids[slot];
            let engine_id = if lung.is_active() { lung.kernel_id } else { 0 };
            let (kind, count) = self.coeff_shape[slot];
            let shape_ok = loaded == 0 || (lung.coeff_kind == kind && lung.coeff_count == count);
            if engine_id == loaded && shape_ok {
                if loaded != 0 {
                    state.deform_scale[slot] = lung.deform_scale;
                    state.offset_mm[slot] = lung.offset_mm;
                    state.coeffs[slot] = lung.coeffs;
                    // A collapse outside [0, 1] or a non-finite hilum is never drawn.
                    let h_ok = lung.hilum_mm.iter().all(|v| v.is_finite());
                    if (0.0..=1.0).contains(&lung.collapse) && h_ok {
                        state.collapse[slot] = lung.collapse;
                        state.hilum_mm[slot] = lung.hilum_mm;
                    }
                }
                continue;
            }
            mismatch = true;
            if !self.mismatch_said {
                self.mismatch_said = true;
                let name = if slot == LUNG_LEFT { "left" } else { "right" };
                let ours = match &self.kernel_paths[slot] {
                    Some(p) => format!("kernel {loaded:016x} ({})", p.display()),
                    None => "no kernel for it".to_string(),
                };
                let theirs = if engine_id == 0 {
                    "not simulated".to_string()
                } else if engine_id != loaded {
                    format!("kernel {engine_id:016x}")
                } else {
                    format!(
                        "sent with {} coefficients of kind {} (this renderer's mode needs {count} of kind {kind})",
                        lung.coeff_count, lung.coeff_kind
                    )
                };
                eprintln!(
                    "renderer[{}]: warning: the engine's {name} lung is {theirs} but this renderer loaded \
                     {ours}; drawing that lung at rest. Start the engine and the renderer with the \
                     same scene (`lungdyn scene prepare` writes one).",
                    self.instance,
                );
            }
        }
        mismatch
    }

    /// Wait for the next engine frame (or the deadline) and draw it, recording `output`'s pass (the
    /// window's present pass) into the frame and presenting it after the submit; the frame's report
    /// goes out after the present, with the time it returned. Returns whether a frame was drawn.
    pub fn step(&mut self, output: &mut impl FrameOutput) -> Result<bool, RendererError> {
        // Every pass of the frame loop: a hung draw or present stops the pings.
        self.watchdog.ping(self.clock.now_ns());
        let Some(tick) = self
            .pacer
            .poll(self.clock.as_ref(), self.ports.engine.as_mut())?
        else {
            return Ok(false);
        };
        let Some((mut frame, mut flags)) = self.take_engine_frame(&tick)? else {
            return Ok(false);
        };
        let now = tick.at_ns;
        frame.stamps.renderer_receive_ns = now;
        self.latch_hmd()?;
        let mut state = self.draw_state(&frame, &mut flags);
        let capture = self.plan_capture(&frame);
        if capture {
            flags |= report_flags::SNAPSHOT;
        }
        state.hmd = self.view(output, now, capture, &state);
        self.read_replies()?;
        // The governor's clock: the real one, whatever clock paces the session (tests' fake ones).
        let started_ns = transport::now_ns();
        let timing = self.draw(output, &frame, &state, capture);
        flags |= self.govern(timing.gpu_done_ns.saturating_sub(started_ns));
        frame.stamps.renderer_submit_ns = timing.submit_ns;
        let present_ns = output.present().unwrap_or(0);
        let (present_mode, frame_latency) = output.mode();
        self.last_timing = (
            timing.submit_ns.saturating_sub(now),
            timing.gpu_ns,
            (frame.stamps.capture_ns != 0)
                .then(|| timing.submit_ns.saturating_sub(frame.stamps.capture_ns)),
        );
        if timing.gpu_ns.is_some() {
            flags |= report_flags::GPU_TIMED;
        }
        self.stats.frames += 1;
        let report = FrameReport {
            layout_version: LAYOUT_VERSION,
            flags,
            frame: self.stats.frames,
            engine_tick: frame.tick,
            tracker_frame: frame.tracker_frame,
            stamps: frame.stamps,
            cpu_frame_ns: timing.submit_ns.saturating_sub(now),
            gpu_frame_ns: timing.gpu_ns.unwrap_or(0),
            gpu_done_ns: timing.gpu_done_ns,
            volume_ml: [
                frame.lungs[LUNG_RIGHT].volume_ml,
                frame.lungs[LUNG_LEFT].volume_ml,
            ],
            present_ns,
            present_mode,
            frame_latency,
        };
        self.ports.report.publish(&report)?;
        if capture {
            self.write_snapshots(&frame)?;
        }
        self.last = Some(frame);
        Ok(true)
    }

    /// The frame to draw for this wake: the engine's new one, or (at a deadline with none) its
    /// last one flagged stale; `None` before the engine's first frame. Says on stderr when the
    /// engine connects, goes quiet and comes back.
    fn take_engine_frame(
        &mut self,
        tick: &transport::pacer::Tick<EngineFrame>,
    ) -> Result<Option<(EngineFrame, u32)>, RendererError> {
        let mut flags = 0u32;
        let frame = match (tick.wake, self.last) {
            (Wake::Sample(f), _) => {
                f.check_layout().map_err(PortError::from)?;
                if self.last.is_none() {
                    eprintln!(
                        "renderer[{}]: engine connected (tick {})",
                        self.instance, f.tick
                    );
                } else if self.engine_down() {
                    eprintln!(
                        "renderer[{}]: engine back after {:.0} ms without frames (tick {})",
                        self.instance,
                        tick.at_ns.saturating_sub(self.last_fresh_ns) as f64 / 1e6,
                        f.tick
                    );
                }
                self.stale_run = 0;
                self.last_fresh_ns = tick.at_ns;
                f
            }
            (Wake::Deadline, Some(f)) => {
                flags |= report_flags::STALE_ENGINE;
                self.stats.stale_frames += 1;
                self.stale_run += 1;
                if self.stale_run == report_flags::ENGINE_DOWN_FRAMES {
                    eprintln!(
                        "renderer[{}]: no engine frame since tick {}: the engine is restarting or \
                         stopped; presenting its last frame, flagged stale",
                        self.instance, f.tick
                    );
                }
                f
            }
            (Wake::Deadline, None) => return Ok(None),
        };
        Ok(Some((frame, flags)))
    }

    /// Late latch: the freshest HMD pose at draw time (and the tracker frame the HUD shows).
    fn latch_hmd(&mut self) -> Result<(), RendererError> {
        if let Some(t) = self.ports.tracker.take_latest()? {
            self.last_tracker = Some(t);
            if let Some(pose) = t.valid_tool(TOOL_HMD) {
                self.hmd = pose;
                self.predictor
                    .update(t.frame_number, t.stamps.capture_ns, pose);
            }
        }
        Ok(())
    }

    /// What the GPU draws of `frame`: the lungs' deformation and the poses, with the warning
    /// the engine's state calls for (flags for the report added to `flags`).
    fn draw_state(&mut self, frame: &EngineFrame, flags: &mut u32) -> DrawState {
        let mut state = DrawState {
            deform_scale: [0.0; 2],
            offset_mm: [[0.0; 3]; 2],
            collapse: [0.0; 2],
            hilum_mm: [[0.0; 3]; 2],
            coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
            patient: frame.patient_pose,
            hmd: self.hmd,
            pose_warning: crate::PoseWarning::of_engine_state(frame.state),
        };
        if frame.state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0 {
            *flags |= report_flags::SIGNAL_FOLLOWING;
        }
        if frame.state & ipc_types::engine_state::SIGNAL_LOST != 0 {
            *flags |= report_flags::SIGNAL_LOST;
        }
        if frame.state & ipc_types::engine_state::SIGNAL_CLIPPED != 0 {
            *flags |= report_flags::SIGNAL_CLIPPED;
        }
        if crate::hud::text::past_fold_free(frame) {
            *flags |= report_flags::PAST_FOLD_FREE;
        }
        if self.engine_down() {
            *flags |= report_flags::ENGINE_DOWN;
            state.pose_warning = crate::PoseWarning::EngineDown;
        }
        match state.pose_warning {
            crate::PoseWarning::None
            | crate::PoseWarning::EngineDown
            | crate::PoseWarning::SignalLost => {}
            crate::PoseWarning::Held => *flags |= report_flags::PATIENT_POSE_HELD,
            crate::PoseWarning::Stale => {
                *flags |= report_flags::PATIENT_POSE_HELD | report_flags::PATIENT_POSE_STALE
            }
        }
        if self.lungs_to_draw(frame, &mut state) {
            *flags |= report_flags::KERNEL_MISMATCH;
            self.stats.kernel_mismatch_frames += 1;
        }
        state
    }

    /// Whether this frame is a snapshot's (the breath's snapshot ticks planned once, from the
    /// first frames that show the breath).
    fn plan_capture(&mut self, frame: &EngineFrame) -> bool {
        if let Some(plan) = self.snapshots.breath.as_mut() {
            if let Some(ticks) = plan.observe(frame) {
                // Planned once per run (the only allocation of the plan).
                self.snapshots.ticks.extend(ticks);
                self.snapshots.ticks.sort_unstable();
                self.snapshots.breath = None;
            }
        }
        let targets = &self.snapshots.ticks;
        self.next_target < targets.len() && frame.tick >= targets[self.next_target]
    }

    /// The viewpoint to draw from: where the head will be when the frame is shown (predict.rs);
    /// the snapshots of a breath keep the first frame's view (or the front view).
    fn view(
        &mut self,
        output: &mut impl FrameOutput,
        now: u64,
        capture: bool,
        state: &DrawState,
    ) -> Pose {
        let mut view = match output.display_time_ns() {
            Some(t) => self.predictor.pose_at_display(t, self.hmd),
            None => self.predictor.pose_at(now, self.hmd),
        };
        if let Some(eyes) = output.eyes() {
            self.renderer.set_eyes(eyes);
        }
        if capture {
            match self.snapshots.view {
                SnapshotView::Hmd => {}
                SnapshotView::First => view = *self.snapshot_view.get_or_insert(self.hmd),
                SnapshotView::Front => {
                    // The lungs framed clear of the HUD, whether or not it is shown now (the H
                    // key does not move the strip's viewpoint).
                    let band = self
                        .hud
                        .as_ref()
                        .map_or(crate::record::FRONT_VIEW_BAND, |h| h.lungs_band());
                    if let Some(pose) = self.renderer.front_view_in(&state.patient, band) {
                        view = pose;
                    }
                }
            }
        }
        view
    }

    /// Draws the frame (with the HUD over it when it is on) and encodes the output's own work.
    fn draw(
        &mut self,
        output: &mut impl FrameOutput,
        frame: &EngineFrame,
        state: &DrawState,
        capture: bool,
    ) -> crate::FrameTiming {
        let hud_on = self.hud_on;
        let _draw = tracing::info_span!(target: transport::trace::TARGET, "draw").entered();
        match self.hud.as_mut().filter(|_| hud_on) {
            Some(hud) => {
                let (cpu_ns, gpu_ns, latency_ns) = self.last_timing;
                let shown = crate::hud::HudFrame {
                    frame,
                    tracker: self.last_tracker.as_ref(),
                    warning: state.pose_warning,
                    cpu_ns,
                    gpu_ns,
                    latency_ns,
                    lod: self.renderer.lod_shown(),
                    governor: self.governor.as_ref().map(|g| g.report_bits()),
                    outcome: self.outcome_standing.map(|s| (self.outcome.as_str(), s)),
                };
                let gpu = &self.gpu;
                self.renderer.render_with_overlay(
                    gpu,
                    state,
                    capture,
                    |encoder, target, eyes| {
                        hud.encode(&gpu.device, &gpu.queue, encoder, target, eyes, &shown)
                    },
                    |e| output.encode(e),
                )
            }
            None => self
                .renderer
                .render_with(&self.gpu, state, capture, |e| output.encode(e)),
        }
    }

    /// Every planned tick this frame reaches gets a snapshot: a tick whose own frame was skipped
    /// (the renderer under load took a newer engine frame) takes this, the next drawn frame, so a
    /// breath's recording keeps all its planned frames.
    fn write_snapshots(&mut self, frame: &EngineFrame) -> Result<(), RendererError> {
        let img = self
            .renderer
            .read_image(&self.gpu)
            .ok_or(RendererError::Readback {
                frame: self.stats.frames,
            })?;
        while self.next_target < self.snapshots.ticks.len()
            && frame.tick >= self.snapshots.ticks[self.next_target]
        {
            let planned = self.snapshots.ticks[self.next_target];
            self.next_target += 1;
            // The same tick planned twice (a short breath over many frames) is one frame.
            if self.next_target < self.snapshots.ticks.len()
                && self.snapshots.ticks[self.next_target] == planned
            {
                continue;
            }
            self.write_snapshot(frame, planned, &img)?;
        }
        Ok(())
    }

    /// Write `img`, the drawn `frame`, as the snapshot planned for engine tick `planned`:
    /// `lungs_NN_tickPLANNED_VOLml.png`, or, when the frame drawn is a later one (the planned
    /// tick's own was skipped), `lungs_NN_tickPLANNED_VOLml_drawnTICK.png`.
    fn write_snapshot(
        &mut self,
        frame: &EngineFrame,
        planned: u64,
        img: &image::RgbaImage,
    ) -> Result<(), RendererError> {
        let total = frame.lungs[LUNG_RIGHT].volume_ml + frame.lungs[LUNG_LEFT].volume_ml;
        let mut name = format!(
            "lungs_{:02}_tick{:05}_{:04.0}ml",
            self.stats.snapshots, planned, total
        );
        if frame.tick != planned {
            name.push_str(&format!("_drawn{:05}", frame.tick));
            self.stats.snapshots_substituted += 1;
        }
        let path = self.snapshots.dir.join(name + ".png");
        crate::write_png(img, &path)?;
        self.stats.snapshots += 1;
        Ok(())
    }

    /// Say goodbye on stderr.
    pub fn finish(&self) {
        transport::trace::flush();
        let s = &self.stats;
        transport::process::say(&format!(
            "renderer[{}]: stopped after {} frames ({} stale, {} with a kernel mismatch), {} snapshots \
             ({} of them the next drawn frame for a planned tick skipped under load), {} drawn \
             with the HMD pose predicted to display time",
            self.instance,
            s.frames,
            s.stale_frames,
            s.kernel_mismatch_frames,
            s.snapshots,
            s.snapshots_substituted,
            self.predictor.predicted_frames
        ));
        if let Some(g) = &self.governor {
            transport::process::say(&format!(
                "renderer[{}]: governor: {} change(s), drawing with {} quality at the end, {} frame(s) \
                     at its floor (every step given up, still over {:.1} ms)",
                self.instance,
                g.changes,
                g.quality().describe(),
                g.floor_frames,
                g.target_ns() as f64 / 1e6
            ));
            if let Some((memory, existed)) = &self.memory {
                transport::process::say(&format!(
                    "renderer[{}]: governor: {}",
                    self.instance,
                    memory.keep(g, self.stats.frames, *existed).describe()
                ));
            }
        }
    }
}

pub(crate) fn check_predict_ms(ms: f64) -> Result<(), RendererError> {
    if ms.is_finite() && (0.0..=crate::predict::MAX_LOOKAHEAD_MS).contains(&ms) {
        Ok(())
    } else {
        Err(RendererError::PredictMs(ms))
    }
}

/// The HMD pose used until the tracker reports one: standing at the patient's right side.
fn default_hmd() -> Pose {
    let eye = glam::Vec3::new(0.0, -1300.0, 1650.0);
    let target = glam::Vec3::new(0.0, 0.0, 1040.0);
    let forward = (target - eye).normalize();
    let right = forward.cross(glam::Vec3::Z).normalize();
    let up = right.cross(forward);
    let q = glam::Quat::from_mat3(&glam::Mat3::from_cols(right, up, -forward));
    Pose {
        quat: q.to_array(),
        translation_mm: eye.to_array(),
        _pad: 0,
    }
}
