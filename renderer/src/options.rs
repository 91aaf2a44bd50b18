//! The renderer process's options (`lungdyn renderer`, the `renderer` binary) and its errors:
//! what [`crate::session`], [`crate::window`] and [`crate::xr_runtime`] are started with.

use std::path::PathBuf;

use lung_model::scene::{LungLoadError, Scene, SceneError};
use outfile::WriteError;
use thiserror::Error;
use transport::process::{ArgError, PinError, ProcessArgs};
use transport::PortError;

use crate::gpu::GpuError;
use lung_model::scene::SceneExt;

/// Command-line options of the `renderer` process.
#[derive(Debug, Clone, clap::Args)]
pub struct RendererArgs {
    /// Instance, scene, pinning and run time.
    #[command(flatten)]
    pub process: ProcessArgs,
    /// Write a PNG of the first frame at or after each of these engine ticks (comma-separated).
    #[arg(long, value_delimiter = ',', value_name = "TICKS")]
    pub snapshot_ticks: Vec<u64>,
    /// Folder for the PNG snapshots.
    #[arg(long, value_name = "DIR", default_value = ".")]
    pub snapshot_dir: PathBuf,
    /// Draw every snapshot frame from the HMD pose of the first one, so the frames of a breath are
    /// comparable (the walking HMD would otherwise change the view more than the breath does).
    /// Same as `--snapshot-view first`.
    #[arg(long, conflicts_with = "snapshot_view")]
    pub snapshot_fixed_view: bool,
    /// Window, fullscreen display and present options.
    #[command(flatten)]
    pub output: crate::display::DisplayArgs,
    /// Each eye's size when drawing for an OpenXR runtime (its recommended image size): the scene
    /// is drawn in stereo at this size per eye.
    #[arg(skip)]
    pub xr_eye_size: Option<(u32, u32)>,
    /// The OpenXR runtime's environment blend mode: on an additive display the look is made
    /// see-through (black background; see [`crate::xr::look_for_blend`]).
    #[arg(skip)]
    pub xr_blend: Option<crate::xr::BlendMode>,
    /// The display's size when fullscreen (set by the window once it knows the display): the
    /// offscreen image is made this size, each eye half its width in stereo.
    #[arg(skip)]
    pub screen_size: Option<(u32, u32)>,
    /// The viewpoint of the snapshots: `hmd` (where the HMD is at each), `first` (the first
    /// snapshot's HMD pose for all), `front` (the front of the patient, head up, the lungs filling
    /// about half the image: one fixed viewpoint for strips and recordings).
    #[arg(long, value_name = "VIEW", value_enum)]
    pub snapshot_view: Option<SnapshotView>,
    /// Write a PNG at N frames over one whole breath: the first breath of the followed lung (the
    /// first that breathes) starting at or after `--snapshot-after-tick`, at that breath's own rate
    /// as the engine runs it (a disease's faster breathing gives one breath, not part of several).
    /// 1 to 240.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=240))]
    pub snapshot_breath: Option<u32>,
    /// With --snapshot-breath: the engine tick from which to wait for a breath's start.
    #[arg(
        long,
        value_name = "TICK",
        default_value_t = 0,
        requires = "snapshot_breath"
    )]
    pub snapshot_after_tick: u64,
    /// Draw the HMD pose predicted this many ms past the draw time (constant linear and angular
    /// velocity from the last two samples; ~ one display frame of scan-out): 0 draws the newest
    /// sample. At most 100.
    #[arg(long, value_name = "MS", default_value_t = 16.7)]
    pub predict_ms: f64,
    /// Calibration file (`lungdyn register`: the lungs' model frame on the patient reference);
    /// overrides the scene's `[render] calibration`. Without either, the lungs sit at a fixed
    /// offset from the reference.
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// HMD optics file (`lungdyn hmd check FILE`): each eye's offset, rotation, frustum and the
    /// per-eye resolution; overrides the scene's `[render] hmd` (and its ipd_mm, fov_y_deg, width
    /// and height).
    #[arg(long, value_name = "FILE")]
    pub hmd: Option<PathBuf>,
    /// The heads-up display (volumes, rate, breath phase, PV loop, disease, outcomes, tracker
    /// health, timing; R/L and head/feet labels) in every eye and in the PNGs: on or off. The
    /// window's H key toggles it.
    #[arg(long, value_name = "ON|OFF", default_value = "on")]
    pub hud: HudSwitch,
}

/// `--snapshot-view`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum SnapshotView {
    /// The HMD pose of each frame.
    #[default]
    Hmd,
    /// The first snapshot's HMD pose, for all.
    First,
    /// The front of the patient.
    Front,
}

/// `--hud on|off`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum HudSwitch {
    /// Draw the heads-up display.
    On,
    /// Draw the lungs alone.
    Off,
}

impl RendererArgs {
    /// The scene and the calibration and optics files this renderer draws with, loaded and
    /// checked (before any GPU work: a bad file is refused at once).
    // RendererError is large in every function that returns it (its scene and file errors carry
    // their paths); boxing it here alone would not change that.
    #[allow(clippy::result_large_err)]
    pub fn scene_and_rig(&self) -> Result<(Scene, crate::camera::RigFiles), RendererError> {
        let mut scene = Scene::load_or_default(self.process.scene.as_deref())?;
        if let Some((w, h)) = self.xr_eye_size {
            scene.render.stereo = true;
            scene.render.width = w.max(1);
            scene.render.height = h.max(1);
        }
        if let Some(blend) = self.xr_blend {
            scene.render.look = crate::xr::look_for_blend(blend, scene.render.look);
        }
        if let Some((w, h)) = self.screen_size {
            let eyes = if scene.render.stereo { 2 } else { 1 };
            scene.render.width = (w / eyes).max(1);
            scene.render.height = h.max(1);
        }
        let files = crate::camera::RigFiles::load(
            &scene.render,
            self.calibration.as_deref(),
            self.hmd.as_deref(),
        )?;
        Ok((scene, files))
    }
}

/// Why the renderer stopped with an error.
#[derive(Debug, Error)]
pub enum RendererError {
    /// A bad command-line option.
    #[error(transparent)]
    Args(#[from] ArgError),
    /// The scene could not be loaded.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// A calibration or HMD optics file is unusable.
    #[error(transparent)]
    Rig(#[from] crate::camera::RigError),
    /// The prediction look-ahead is out of range.
    #[error("--predict-ms {0} must be within 0..100 ms (0 draws the newest HMD sample)")]
    PredictMs(f64),
    /// A lung's kernel could not be loaded.
    #[error(transparent)]
    Lung(#[from] LungLoadError),
    /// A lung's kernel lacks its mode's data or a section failed verification.
    #[error(transparent)]
    Mode(#[from] lung_model::deform::modes::ModeLoadError),
    /// The lungs do not fit the GPU.
    #[error(transparent)]
    Upload(#[from] crate::UploadError),
    /// No usable GPU.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// Pinning failed.
    #[error(transparent)]
    Pin(#[from] PinError),
    /// A stream failed.
    #[error(transparent)]
    Port(#[from] PortError),
    /// The scene's wake strategy cannot run where the renderer runs.
    #[error(transparent)]
    Wake(#[from] transport::wake::WakeError),
    /// The snapshot folder could not be created.
    #[error("cannot create the snapshot folder {}: {source}", path.display())]
    SnapshotDir {
        /// Folder.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// A frame could not be read back for a snapshot.
    #[error("could not read frame {frame} back from the GPU for a snapshot")]
    Readback {
        /// Renderer frame.
        frame: u64,
    },
    /// A snapshot could not be written.
    #[error(transparent)]
    Snapshot(#[from] WriteError),
    /// No display for `--window`.
    #[error("--window needs a display, but none could be opened ({source}); set DISPLAY or run headless")]
    NoDisplay {
        /// winit's reason.
        source: winit::error::EventLoopError,
    },
    /// The window could not be created.
    #[error("cannot open a window: {source}")]
    Window {
        /// winit's reason.
        source: winit::error::OsError,
    },
    /// The adapter cannot present to the window.
    #[error("the GPU adapter {adapter} cannot present to this window")]
    CannotPresent {
        /// Adapter name.
        adapter: String,
    },
    /// `--fullscreen` on a display server that lists no monitors.
    #[error("--fullscreen: the display server lists no monitors (check `xrandr --query`)")]
    NoMonitors,
    /// `--display NAME` names no monitor.
    #[error("--display {name}: no display of that name; the displays are: {monitors}")]
    UnknownDisplay {
        /// The name asked for.
        name: String,
        /// The monitors there are, one `INDEX: NAME WxH` each.
        monitors: String,
    },
    /// `--display INDEX` is past the list.
    #[error("--display {index}: there are only {count} display(s), 0 to {}: {monitors}", count - 1)]
    DisplayIndex {
        /// The index asked for.
        index: usize,
        /// How many monitors there are (at least one).
        count: usize,
        /// The monitors there are.
        monitors: String,
    },
    /// `--present-mode` names a mode the surface does not offer.
    #[error("--present-mode {wanted}: this surface offers only {supported} (`latency` picks the best of them)")]
    PresentMode {
        /// The mode asked for.
        wanted: String,
        /// The modes the surface offers.
        supported: String,
    },
    /// `--xr` could not start or the runtime stopped it.
    #[error("--xr: {0}")]
    Xr(String),
    /// The window's event loop failed.
    #[error("the window's event loop failed: {source}")]
    EventLoop {
        /// winit's reason.
        source: winit::error::EventLoopError,
    },
}
