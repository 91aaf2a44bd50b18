//! The renderer process: wake on engine frames, late-latch the HMD pose, draw, report.
//!
//! It sleeps on the engine's iceoryx2 event; a fresh engine frame is drawn at once, with the newest
//! HMD pose taken from the tracker stream just before the draw (late latching). If the engine is late
//! or gone, the deadline fallback redraws the last frame (flagged stale) so the display never freezes.
//! Each frame's hop stamps and CPU/GPU times go out on the report service for the latency harness.

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
    /// Instance name shared by the three processes of one run.
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Scene file (TOML); the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Pin this process to CPU core N.
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted).
    #[arg(long)]
    pub seconds: Option<f64>,
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
}

/// Run the renderer until terminated (or `--seconds` elapse).
pub fn run(args: &RendererArgs) -> anyhow::Result<()> {
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        // Mesa's window-system probing prints a scary "error: XDG_RUNTIME_DIR is invalid" line on
        // headless machines; a private runtime folder keeps it quiet. Done before any thread starts.
        let dir = std::env::temp_dir().join("lungdyn-runtime");
        if std::fs::create_dir_all(&dir).is_ok() {
            std::env::set_var("XDG_RUNTIME_DIR", &dir);
        }
    }
    let scene = engine::scene::Scene::load_or_default(args.scene.as_deref())?;
    let services = Services::new(&args.instance)?;
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
    let gpu = Gpu::new()?;
    let renderer = LungRenderer::new(&gpu, &scene.render, &lungs);
    ipc_types::pin_to_core(args.cpu, "renderer")?;
    let node = services.node("renderer")?;
    let engine_in: Inlet<EngineFrame> =
        Inlet::new(&node, &services.engine(), &services.engine_event())?;
    let tracker_in: Inlet<TrackerFrame> =
        Inlet::new(&node, &services.tracker(), &services.tracker_event())?;
    // The report stream has no consumer that waits on an event, but Outlet keeps one code path.
    let report_out: Outlet<FrameReport> = Outlet::new(
        &node,
        &services.report(),
        &format!("{}-ready", services.report()),
    )?;

    let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
    let grace_ns = period_ns / 4;
    let start = now_ns();
    let stop_at = args.seconds.map(|s| start + (s * 1e9) as u64);
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
    let mut last: Option<EngineFrame> = None;
    let mut hmd = default_hmd();
    let mut deadline = start + period_ns + grace_ns;
    let mut frame_no: u64 = 0;
    let mut next_target = 0usize;
    let mut written: u32 = 0;
    let mut snapshot_view: Option<Pose> = None;
    loop {
        if termination_requested(&node) || stop_at.is_some_and(|t| now_ns() >= t) {
            break;
        }
        engine_in.wait_until(deadline);
        let fresh = engine_in.take_latest()?;
        let now = now_ns();
        if fresh.is_none() && now < deadline {
            continue;
        }
        let mut flags = 0u32;
        let mut frame = match (fresh, last) {
            (Some(f), _) => {
                ipc_types::check_layout("EngineFrame", f.layout_version)?;
                if last.is_none() {
                    eprintln!(
                        "renderer[{}]: engine connected (tick {})",
                        services.instance, f.tick
                    );
                }
                deadline = now + period_ns + grace_ns;
                f
            }
            (None, Some(f)) => {
                flags |= report_flags::STALE_ENGINE;
                deadline += period_ns;
                f
            }
            (None, None) => {
                deadline += period_ns;
                continue;
            }
        };
        frame.stamps.renderer_receive_ns = now;
        // Late latch: the freshest HMD pose at draw time.
        if let Some(t) = tracker_in.take_latest()? {
            let tool = &t.tools[TOOL_HMD];
            if t.tool_count as usize > TOOL_HMD && tool.is_valid() && tool.pose.is_finite() {
                hmd = tool.pose;
            }
        }
        let capture = next_target < targets.len() && frame.tick >= targets[next_target];
        if capture {
            flags |= report_flags::SNAPSHOT;
        }
        let mut view = hmd;
        if capture && args.snapshot_fixed_view {
            view = *snapshot_view.get_or_insert(hmd);
        }
        let state = DrawState {
            deform_scale: [
                frame.lungs[LUNG_RIGHT].deform_scale,
                frame.lungs[LUNG_LEFT].deform_scale,
            ],
            patient: frame.patient_pose,
            hmd: view,
        };
        let timing = renderer.render(&gpu, &state, capture);
        frame.stamps.renderer_submit_ns = timing.submit_ns;
        if timing.gpu_ns.is_some() {
            flags |= report_flags::GPU_TIMED;
        }
        frame_no += 1;
        report_out.publish(FrameReport {
            layout_version: LAYOUT_VERSION,
            flags,
            frame: frame_no,
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
            while next_target < targets.len() && frame.tick >= targets[next_target] {
                next_target += 1;
            }
            let img = renderer
                .read_image(&gpu)
                .ok_or_else(|| anyhow::anyhow!("could not read the frame back"))?;
            let total = frame.lungs[LUNG_RIGHT].volume_ml + frame.lungs[LUNG_LEFT].volume_ml;
            let path = args.snapshot_dir.join(format!(
                "lungs_{:02}_tick{:05}_{:04.0}ml.png",
                written, frame.tick, total
            ));
            crate::write_png(&img, &path)?;
            written += 1;
        }
        last = Some(frame);
    }
    eprintln!(
        "renderer[{}]: stopped after {frame_no} frames, {written} snapshots",
        services.instance
    );
    Ok(())
}

/// The HMD pose used until the tracker reports one: standing at the patient's right side.
fn default_hmd() -> Pose {
    let p = Pose {
        quat: [0.0; 4],
        translation_mm: [0.0, -1300.0, 1650.0],
        _pad: 0,
    };
    let eye = glam::Vec3::from(p.translation_mm);
    let target = glam::Vec3::new(0.0, 0.0, 1040.0);
    let forward = (target - eye).normalize();
    let right = forward.cross(glam::Vec3::Z).normalize();
    let up = right.cross(forward);
    let q = glam::Quat::from_mat3(&glam::Mat3::from_cols(right, up, -forward));
    Pose {
        quat: q.to_array(),
        ..p
    }
}
