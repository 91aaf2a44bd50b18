//! The renderer process: wake on engine frames, late-latch the HMD pose, draw, report.
//!
//! A [`Session`] sleeps on the engine's iceoryx2 event; a fresh engine frame is drawn at once, with
//! the newest HMD pose taken from the tracker stream just before the draw (late latching). If the
//! engine is late or gone, the deadline fallback redraws the last frame (flagged stale) so the
//! display never freezes. Each frame's hop stamps and CPU/GPU times go out on the report service for
//! the latency harness. Headless, [`run`] drives the session in a loop; with `--window`,
//! [`crate::window`] drives the same session from the window's event loop and presents each frame.

use std::path::PathBuf;

use ipc_types::{
    now_ns, report_flags, termination_requested, EngineFrame, FrameReport, Inlet, Outlet, Pose,
    Services, TrackerFrame, LAYOUT_VERSION, LUNG_LEFT, LUNG_RIGHT, TOOL_HMD,
};

use crate::gpu::Gpu;
use crate::{DrawState, LungRenderer};

/// Command-line options of the `renderer` process.
#[derive(Debug, Clone, clap::Args)]
pub struct RendererArgs {
    /// Instance, scene, pinning and run time.
    #[command(flatten)]
    pub process: engine::runtime::process::ProcessArgs,
    /// Write a PNG of the first frame at or after each of these engine ticks (comma-separated).
    #[arg(long, value_delimiter = ',', value_name = "TICKS")]
    pub snapshot_ticks: Vec<u64>,
    /// Folder for the PNG snapshots.
    #[arg(long, value_name = "DIR", default_value = ".")]
    pub snapshot_dir: PathBuf,
    /// Draw every snapshot frame from the HMD pose of the first one, so the frames of a breath are
    /// comparable (the walking HMD would otherwise change the view more than the breath does).
    #[arg(long)]
    pub snapshot_fixed_view: bool,
    /// Show the frames in a window (needs a display, e.g. DISPLAY on X11); headless otherwise.
    #[arg(long)]
    pub window: bool,
    /// With --window: wait for the display's vertical blank when presenting (adds up to a refresh
    /// period of latency; off by default, frames are paced by the engine).
    #[arg(long, requires = "window")]
    pub vsync: bool,
}

/// One renderer session: its GPU state, its ports and its frame loop state.
pub struct Session {
    /// The GPU.
    pub gpu: Gpu,
    /// The lungs' GPU state and offscreen target.
    pub renderer: LungRenderer,
    args: RendererArgs,
    services: Services,
    node: iceoryx2::prelude::Node<iceoryx2::prelude::ipc::Service>,
    engine_in: Inlet<EngineFrame>,
    tracker_in: Inlet<TrackerFrame>,
    report_out: Outlet<FrameReport>,
    period_ns: u64,
    grace_ns: u64,
    deadline: u64,
    stop_at: Option<u64>,
    last: Option<EngineFrame>,
    hmd: Pose,
    frame_no: u64,
    targets: Vec<u64>,
    next_target: usize,
    written: u32,
    snapshot_view: Option<Pose>,
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
    /// Load the scene, build the lungs, upload them to `gpu` and open the ports.
    pub fn new(args: &RendererArgs, gpu: Gpu) -> anyhow::Result<Self> {
        let scene = engine::scene::Scene::load_or_default(args.process.scene.as_deref())?;
        let services = Services::new(&args.process.instance)?;
        let mut targets = args.snapshot_ticks.clone();
        targets.sort_unstable();
        if !targets.is_empty() {
            std::fs::create_dir_all(&args.snapshot_dir).map_err(|e| {
                anyhow::anyhow!(
                    "cannot create the snapshot folder {}: {e}",
                    args.snapshot_dir.display()
                )
            })?;
        }
        let lungs = scene
            .lungs
            .sides
            .iter()
            .map(|&side| engine::runtime::build_lung(&scene, side))
            .collect::<anyhow::Result<Vec<_>>>()?;
        let renderer = LungRenderer::new(&gpu, &scene.render, &lungs);
        ipc_types::pin_to_core(args.process.cpu, "renderer")?;
        let node = services.node("renderer")?;
        let engine_in = Inlet::new(&node, &services.engine(), &services.engine_event())?;
        let tracker_in = Inlet::new(&node, &services.tracker(), &services.tracker_event())?;
        // The report stream has no consumer that waits on an event, but Outlet keeps one code path.
        let report_out = Outlet::new(
            &node,
            &services.report(),
            &format!("{}-ready", services.report()),
        )?;
        let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
        let start = now_ns();
        let (w, h) = renderer.image_size();
        eprintln!(
            "renderer[{}]: {} vertices, {}x{} {:?}{} on {}; waiting for engine frames on {:?}",
            services.instance,
            renderer.vertex_count(),
            w,
            h,
            scene.render.mode,
            if scene.render.stereo { " stereo" } else { "" },
            gpu.describe(),
            services.engine()
        );
        Ok(Self {
            gpu,
            renderer,
            args: args.clone(),
            services,
            node,
            engine_in,
            tracker_in,
            report_out,
            period_ns,
            grace_ns: period_ns / 4,
            deadline: start + period_ns + period_ns / 4,
            stop_at: args.process.stop_at(start),
            last: None,
            hmd: default_hmd(),
            frame_no: 0,
            targets,
            next_target: 0,
            written: 0,
            snapshot_view: None,
        })
    }

    /// True when the process was asked to stop or its time is up.
    pub fn should_stop(&self) -> bool {
        termination_requested(&self.node) || self.stop_at.is_some_and(|t| now_ns() >= t)
    }

    /// Wait for the next engine frame (or the deadline) and draw it, recording `extra` (the
    /// window's present pass) into the frame. Returns whether a frame was drawn.
    pub fn step(&mut self, extra: impl FnOnce(&mut wgpu::CommandEncoder)) -> anyhow::Result<bool> {
        self.engine_in.wait_until(self.deadline);
        let fresh = self.engine_in.take_latest()?;
        let now = now_ns();
        if fresh.is_none() && now < self.deadline {
            return Ok(false);
        }
        let mut flags = 0u32;
        let mut frame = match (fresh, self.last) {
            (Some(f), _) => {
                ipc_types::check_layout("EngineFrame", f.layout_version)?;
                if self.last.is_none() {
                    eprintln!(
                        "renderer[{}]: engine connected (tick {})",
                        self.services.instance, f.tick
                    );
                }
                self.deadline = now + self.period_ns + self.grace_ns;
                f
            }
            (None, Some(f)) => {
                flags |= report_flags::STALE_ENGINE;
                self.deadline += self.period_ns;
                f
            }
            (None, None) => {
                self.deadline += self.period_ns;
                return Ok(false);
            }
        };
        frame.stamps.renderer_receive_ns = now;
        // Late latch: the freshest HMD pose at draw time.
        if let Some(t) = self.tracker_in.take_latest()? {
            let tool = &t.tools[TOOL_HMD];
            if t.tool_count as usize > TOOL_HMD && tool.is_valid() && tool.pose.is_finite() {
                self.hmd = tool.pose;
            }
        }
        let targets = &self.targets;
        let capture = self.next_target < targets.len() && frame.tick >= targets[self.next_target];
        if capture {
            flags |= report_flags::SNAPSHOT;
        }
        let mut view = self.hmd;
        if capture && self.args.snapshot_fixed_view {
            view = *self.snapshot_view.get_or_insert(self.hmd);
        }
        let state = DrawState {
            deform_scale: [
                frame.lungs[LUNG_RIGHT].deform_scale,
                frame.lungs[LUNG_LEFT].deform_scale,
            ],
            patient: frame.patient_pose,
            hmd: view,
        };
        let timing = self.renderer.render_with(&self.gpu, &state, capture, extra);
        frame.stamps.renderer_submit_ns = timing.submit_ns;
        if timing.gpu_ns.is_some() {
            flags |= report_flags::GPU_TIMED;
        }
        self.frame_no += 1;
        self.report_out.publish(FrameReport {
            layout_version: LAYOUT_VERSION,
            flags,
            frame: self.frame_no,
            engine_tick: frame.tick,
            tracker_frame: frame.tracker_frame,
            stamps: frame.stamps,
            cpu_frame_ns: timing.submit_ns.saturating_sub(now),
            gpu_frame_ns: timing.gpu_ns.unwrap_or(0),
            volume_ml: [
                frame.lungs[LUNG_RIGHT].volume_ml,
                frame.lungs[LUNG_LEFT].volume_ml,
            ],
        })?;
        if capture {
            while self.next_target < self.targets.len()
                && frame.tick >= self.targets[self.next_target]
            {
                self.next_target += 1;
            }
            self.write_snapshot(&frame)?;
        }
        self.last = Some(frame);
        Ok(true)
    }

    fn write_snapshot(&mut self, frame: &EngineFrame) -> anyhow::Result<()> {
        let img = self
            .renderer
            .read_image(&self.gpu)
            .ok_or_else(|| anyhow::anyhow!("could not read the frame back from the GPU"))?;
        let total = frame.lungs[LUNG_RIGHT].volume_ml + frame.lungs[LUNG_LEFT].volume_ml;
        let path = self.args.snapshot_dir.join(format!(
            "lungs_{:02}_tick{:05}_{:04.0}ml.png",
            self.written, frame.tick, total
        ));
        crate::write_png(&img, &path)?;
        self.written += 1;
        Ok(())
    }

    /// Say goodbye on stderr.
    pub fn finish(&self) {
        eprintln!(
            "renderer[{}]: stopped after {} frames, {} snapshots",
            self.services.instance, self.frame_no, self.written
        );
    }
}

/// Run the renderer until terminated (or `--seconds` elapse): headless, or in a window.
pub fn run(args: &RendererArgs) -> anyhow::Result<()> {
    quiet_mesa();
    if args.window {
        return crate::window::run(args);
    }
    let mut session = Session::new(args, Gpu::new()?)?;
    while !session.should_stop() {
        session.step(|_| {})?;
    }
    session.finish();
    Ok(())
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
