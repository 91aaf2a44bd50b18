//! `lungdyn demo`: start the three processes, let the lungs breathe, measure, stop cleanly.
//!
//! The launcher re-executes its own binary once per role (`lungdyn tracker-bridge|engine|renderer`),
//! so `cargo run --bin lungdyn` is enough on a fresh clone; each role is a separate OS process
//! talking to the others only through iceoryx2. Children get `PR_SET_PDEATHSIG`, so they die with
//! the launcher even if it is killed. On exit (or Ctrl-C) each child gets SIGINT, then SIGKILL after
//! a grace period; dead-node resources are cleaned and the instance's files are checked to be gone.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context};
use ipc_types::FrameReport;
use transport::{iox, now_ns, Instance, Receive};

use crate::prepare::KernelUse;
use serde::Serialize;

use crate::stats::{HopRow, LatencyStats, DEADLINE_NS};

/// Options of `lungdyn demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Seconds to run once frames flow.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Folder for the PNG frames (created if missing).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// PNG frames to write, spread over one whole breath at the breath's own rate, from the front
    /// of the patient with the HUD (0 for none; at most 240); they make the breath strip.
    #[arg(long, default_value_t = 6)]
    pub snapshots: u32,
    /// Record one whole breath (the same frames as the strip, more of them) as an animation: a
    /// `.gif`, or an `.mp4` when ffmpeg is on PATH. The strip then uses --snapshots of its frames.
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
    /// Frames of the --record animation over the breath (2 to 240).
    #[arg(long, value_name = "N", default_value_t = 36)]
    pub record_frames: u32,
    /// The heads-up display in the window and the PNGs: on or off (the window's H key toggles it).
    #[arg(long, value_name = "ON|OFF", default_value = "on")]
    pub hud: renderer::process::HudSwitch,
    /// Take the snapshots over the breath that starts after this many seconds (default: after the
    /// first second), e.g. to see a tension pneumothorax well into its course.
    #[arg(long, value_name = "S")]
    pub snapshot_at_s: Option<f64>,
    /// Scene file (TOML); the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Instance name (service and shared-memory names derive from it); `demo-<pid>` by default. The
    /// demo prints it at start; `lungdyn instances` lists running ones, `lungdyn scene event NAME …`
    /// acts on one.
    #[arg(long)]
    pub instance: Option<String>,
    /// Print one JSON object with the results on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
    /// Pin tracker-bridge, engine and renderer to these three cores, e.g. `--cpus 0,1,1` (overrides
    /// the scene's `[processes] cpus`).
    #[arg(long, value_delimiter = ',', num_args = 3)]
    pub cpus: Vec<usize>,
    /// Show the frames in a window (needs a display); closing it ends the demo. Headless otherwise.
    #[arg(long)]
    pub window: bool,
    /// With --window: present on the display's vertical blank.
    #[arg(long, requires = "window")]
    pub vsync: bool,
    /// Seconds to wait for the first frame before giving up.
    #[arg(long, default_value_t = 60.0)]
    pub startup_timeout: f64,
    /// Draw the HMD pose predicted this many ms past the draw time (the renderer's --predict-ms;
    /// 0 draws the newest sample).
    #[arg(long, value_name = "MS", default_value_t = 16.7)]
    pub predict_ms: f64,
    /// Tracker source for the bridge (its --source): synthetic, igtl-client:HOST[:PORT],
    /// igtl-server[:BIND[:PORT]], ndi-serial:DEVICE, ndi-tcp:HOST[:PORT], replay:FILE. Default: the
    /// scene's [tracker] source (synthetic).
    #[arg(long, value_name = "URI")]
    pub tracker: Option<String>,
    /// Deformation mode (overrides the scene's [lungs] mode): "precomputed" (one baked field,
    /// supine only, 3 MACs per vertex), "basis" (exact for any orientation, 4 MACs), "sh" (eq. 7.7
    /// with the scene's bands), "direct" (eq. 7.1 every frame, the accuracy reference).
    #[arg(long, value_name = "MODE")]
    pub mode: Option<lung_model::deform::modes::DeformMode>,
    /// Roll the synthetic patient about the bed's long axis, sweeping ±DEG (90: onto each side,
    /// 180: over to prone): in the orientation modes the breath follows gravity.
    #[arg(long, value_name = "DEG", default_value_t = 0.0)]
    pub roll_deg: f32,
    /// Pitch the synthetic patient head-up/head-down, sweeping ±DEG (90: sitting up).
    #[arg(long, value_name = "DEG", default_value_t = 0.0)]
    pub pitch_deg: f32,
    /// Seconds per roll/pitch sweep.
    #[arg(long, value_name = "S", default_value_t = 20.0)]
    pub sweep_period_s: f32,
    /// Calibration file (`lungdyn register`: the lungs' model frame on the patient reference);
    /// overrides the scene's `[render] calibration`. Without either, the renderer places the lungs
    /// at a fixed offset from the reference.
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// HMD optics file (`lungdyn hmd check FILE`: per-eye offsets, frusta, resolution); overrides
    /// the scene's `[render] hmd` and its ipd_mm, fov_y_deg, width and height.
    #[arg(long, value_name = "FILE")]
    pub hmd: Option<PathBuf>,
}

/// Most `--snapshots`: one per 60 Hz display frame of a 4-second breath (15 breaths/min). More are
/// frames of one breath closer together than the renderer draws them, and every one is a PNG of the
/// window's size written to disk (a billion asked for ran a run to 16 GiB before this limit).
pub const MAX_SNAPSHOTS: u32 = 240;

/// Check the demo's count and core options before any work (nothing is baked, started or written
/// for a bad one): `--snapshots` at most [`MAX_SNAPSHOTS`], every `--cpus` core one this process may
/// run on.
pub fn check_counts(args: &DemoArgs) -> anyhow::Result<()> {
    if args.snapshots > MAX_SNAPSHOTS {
        bail!(
            "--snapshots {}: at most {MAX_SNAPSHOTS} PNG frames over one breath (one per display frame \
             of a 4 s breath at 60 Hz)",
            args.snapshots
        );
    }
    if let Some(at) = args.snapshot_at_s {
        if !(at.is_finite() && at >= 0.0 && at < args.seconds) {
            bail!(
                "--snapshot-at-s {}: must be a number of seconds from 0 to below --seconds {}",
                lung_model::plausible::compact(at),
                args.seconds
            );
        }
    }
    check_cpus(&args.cpus, "--cpus")
}

/// Every core of `cpus` one this process may run on (`what` names where they came from).
fn check_cpus(cpus: &[usize], what: &str) -> anyhow::Result<()> {
    if !cpus.is_empty() {
        let allowed = allowed_cpus();
        for (role, &core) in ["tracker-bridge", "engine", "renderer"].iter().zip(cpus) {
            if let Some(allowed) = &allowed {
                if !allowed.contains(&core) {
                    bail!(
                        "{what}: core {core} for the {role} is not one this process may run on (cores {})",
                        allowed
                            .iter()
                            .map(|c| c.to_string())
                            .collect::<Vec<_>>()
                            .join(", ")
                    );
                }
            }
        }
    }
    Ok(())
}

/// The cores this process may run on (`None` when the system does not say).
fn allowed_cpus() -> Option<Vec<usize>> {
    // SAFETY: sched_getaffinity fills a zeroed cpu_set_t of the size we pass; CPU_ISSET only reads it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return None;
        }
        Some(
            (0..libc::CPU_SETSIZE as usize)
                .filter(|&c| libc::CPU_ISSET(c, &set))
                .collect(),
        )
    }
}

/// The demo's machine-readable result.
#[derive(Debug, Serialize)]
pub struct DemoReport {
    /// Frames the renderer drew and reported.
    pub frames_rendered: u64,
    /// Tracker samples first shown more than 16.7 ms after capture, against the 60 Hz schedule —
    /// drawn or not, so a stalled process shows up here (coordinated-omission corrected).
    pub deadline_misses: u64,
    /// Tracker samples on the schedule while frames flowed.
    pub tracker_samples: u64,
    /// Worst tracker-sample-to-display latency against the schedule, ms (a stall's length).
    pub worst_case_ms: f64,
    /// 99th percentile of the same, ms.
    pub schedule_p99_ms: f64,
    /// Display slots (60 Hz) in which no frame at all was submitted.
    pub missed_frame_slots: u64,
    /// Drawn frames whose own end-to-end latency exceeded 16.7 ms.
    pub late_frames: u64,
    /// End-to-end (tracker capture → renderer submit) median, ms.
    pub end_to_end_p50_ms: f64,
    /// End-to-end 99th percentile, ms.
    pub end_to_end_p99_ms: f64,
    /// End-to-end maximum, ms.
    pub end_to_end_max_ms: f64,
    /// PNG frames written.
    pub pngs: Vec<String>,
    /// The breath's frames side by side plus a motion panel (absent with fewer than two PNGs).
    pub strip: Option<String>,
    /// The `--record` animation of one breath.
    pub recording: Option<String>,
    /// Per-hop rows.
    pub hops: Vec<HopRow>,
    /// Each process's per-sample time against the scene's `[processes] budget_ms`.
    pub budgets: Vec<crate::stats::BudgetRow>,
    /// Cores the three processes were pinned to (empty: not pinned).
    pub cpus: Vec<usize>,
    /// Seconds measured.
    pub seconds: f64,
    /// Frames per second drawn.
    pub fps: f64,
    /// Frames drawn without a fresh engine frame.
    pub stale_frames: u64,
    /// Frames drawn with the patient pose held by the engine (tinted amber on screen).
    pub patient_pose_held_frames: u64,
    /// Of those, frames whose held pose was stale or never arrived (tinted red on screen).
    pub patient_pose_stale_frames: u64,
    /// Engine ticks never drawn.
    pub skipped_ticks: u64,
    /// Reports lost between renderer and launcher.
    pub lost_reports: u64,
    /// Frames with incomplete or unordered hop stamps.
    pub bad_stamps: u64,
    /// Frames drawn before the first tracker sample reached the engine (no latency to measure).
    pub untracked_frames: u64,
    /// Summed lung volume range drawn, ml.
    pub volume_min_ml: f32,
    /// Summed lung volume range drawn, ml.
    pub volume_max_ml: f32,
    /// Instance files iceoryx2 left behind after shutdown, then removed by the launcher (should be 0).
    pub leftover_files: usize,
    /// Instance files still present after the launcher's removal (must be 0).
    pub remaining_files: usize,
    /// Kernel files the lungs ran from (baked now or reused).
    pub kernels: Vec<KernelUse>,
    /// The instance name used.
    pub instance: String,
    /// Deformation mode the lungs ran in.
    pub mode: String,
    /// The calibration file the renderer placed the lungs by (none: the fixed offset).
    pub calibration: Option<String>,
    /// The HMD optics file the renderer drew the eyes from (none: the scene's IPD and field of view).
    pub hmd: Option<String>,
}

/// How a child ended: its status, or why it could not be collected (then it counts as gone too).
#[derive(Debug, Clone)]
enum Ended {
    Status(std::process::ExitStatus),
    Unknown(String),
}

impl std::fmt::Display for Ended {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Ended::Status(s) => write!(f, "{s}"),
            Ended::Unknown(e) => write!(f, "status unknown: {e}"),
        }
    }
}

/// One child process of the demo, signalled only through its handle.
///
/// A pid may be signalled only while the child is known not to be reaped: once `try_wait`/`wait`
/// has collected its status the kernel may hand the pid to an unrelated process. Only this handle
/// reaps the child (nobody else waits on it and SIGCHLD keeps its default), so a `try_wait` that
/// finds it still running guarantees the pid is ours until the next wait — a child that dies in
/// between stays a zombie holding the pid. Once it has ended, the child is never signalled again.
struct Proc {
    role: &'static str,
    child: Child,
    ended: Option<Ended>,
}

impl Proc {
    fn new(role: &'static str, child: Child) -> Self {
        Proc {
            role,
            child,
            ended: None,
        }
    }

    /// How the child ended, collecting its status (and so reaping it) if it has exited.
    fn poll(&mut self) -> Option<&Ended> {
        if self.ended.is_none() {
            self.ended = match self.child.try_wait() {
                Ok(s) => s.map(Ended::Status),
                // ECHILD: something else reaped it, so the pid is not ours any more either.
                Err(e) => Some(Ended::Unknown(e.to_string())),
            };
        }
        self.ended.as_ref()
    }

    /// Send `sig` if the child is still un-reaped; false (and nothing sent) once it has ended.
    fn signal(&mut self, sig: libc::c_int) -> bool {
        if self.poll().is_some() {
            return false;
        }
        // SAFETY: `poll` just found the child un-reaped, and only this handle reaps it, so the pid
        // still names our child (at worst a zombie); kill(2) has no memory-safety preconditions.
        unsafe { libc::kill(self.child.id() as libc::pid_t, sig) == 0 }
    }

    /// SIGKILL (through the handle, which refuses a reaped child) and reap.
    fn kill_and_reap(&mut self) {
        if self.poll().is_none() {
            let _ = self.child.kill();
            self.ended = Some(match self.child.wait() {
                Ok(s) => Ended::Status(s),
                Err(e) => Ended::Unknown(e.to_string()),
            });
        }
    }
}

struct Children {
    procs: Vec<Proc>,
}

impl Children {
    fn spawn(exe: &Path, role: &'static str, args: &[String]) -> anyhow::Result<Proc> {
        let mut cmd = Command::new(exe);
        cmd.arg(role)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        // SAFETY: prctl is async-signal-safe; it only arms a signal for when the parent dies.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        let child = cmd
            .spawn()
            .with_context(|| format!("cannot start the {role} process ({})", exe.display()))?;
        Ok(Proc::new(role, child))
    }

    /// The first child that exited, with its status.
    fn exited(&mut self) -> Option<(&'static str, Ended)> {
        self.procs
            .iter_mut()
            .find_map(|p| p.poll().cloned().map(|e| (p.role, e)))
    }

    /// SIGINT everyone still running, wait up to `grace`, SIGKILL stragglers. Returns roles that
    /// had to be killed.
    fn stop(&mut self, grace: Duration) -> Vec<&'static str> {
        for p in &mut self.procs {
            p.signal(libc::SIGINT);
        }
        let until = now_ns() + grace.as_nanos() as u64;
        let mut killed = Vec::new();
        for p in &mut self.procs {
            while p.poll().is_none() {
                if now_ns() >= until {
                    p.kill_and_reap();
                    killed.push(p.role);
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        killed
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        for p in &mut self.procs {
            p.kill_and_reap();
        }
    }
}

/// The synthetic source's posture for a scene's (the bridge does not depend on the lung model, so
/// each crate has its enum; this match is where they meet, checked by the compiler).
pub fn bridge_posture(p: lung_model::scene::Posture) -> tracker_bridge::synthetic::Posture {
    use lung_model::scene::Posture as S;
    use tracker_bridge::synthetic::Posture as B;
    match p {
        S::Supine => B::Supine,
        S::Sitting => B::Sitting,
        S::Prone => B::Prone,
        S::LeftLateral => B::LeftLateral,
        S::RightLateral => B::RightLateral,
    }
}

/// Check `dir` can take our PNGs: create it, write and remove a probe file.
pub fn check_writable(dir: &Path) -> anyhow::Result<()> {
    if let Ok(meta) = std::fs::metadata(dir) {
        if !meta.is_dir() {
            use std::os::unix::fs::FileTypeExt;
            let t = meta.file_type();
            let what = if t.is_char_device() {
                "a character device"
            } else if t.is_block_device() {
                "a block device"
            } else if t.is_fifo() {
                "a FIFO (named pipe)"
            } else if t.is_socket() {
                "a socket"
            } else {
                "a file"
            };
            bail!(
                "--out {}: exists and is {what}, not a folder: give a folder to write into",
                dir.display()
            );
        }
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("--out {}: cannot create the folder", dir.display()))?;
    let probe = dir.join(format!(".lungdyn-write-probe-{}", std::process::id()));
    std::fs::write(&probe, b"probe")
        .with_context(|| format!("--out {}: the folder is not writable", dir.display()))?;
    std::fs::remove_file(&probe).ok();
    Ok(())
}

/// Mesa's window-system probe prints "XDG_RUNTIME_DIR is invalid or not set" from every process when
/// the variable is missing (a root shell, a service): give the launcher and its children a private
/// one (mode 0700, per user) instead of that noise.
fn ensure_runtime_dir() {
    let valid = std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| Path::new(&d).is_dir());
    if valid {
        return;
    }
    use std::os::unix::fs::DirBuilderExt;
    // SAFETY: getuid cannot fail and has no preconditions.
    let uid = unsafe { libc::getuid() };
    let dir = std::env::temp_dir().join(format!("lungdyn-runtime-{uid}"));
    let made = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let ours = std::fs::symlink_metadata(&dir).is_ok_and(|m| {
        use std::os::unix::fs::MetadataExt;
        m.is_dir() && m.uid() == uid && m.mode() & 0o077 == 0
    });
    if (made.is_ok() || dir.is_dir()) && ours {
        // Set before any thread or child exists (the launcher is single-threaded here).
        std::env::set_var("XDG_RUNTIME_DIR", &dir);
    }
}

/// Run the demo; returns the report (the caller prints it).
pub fn run(args: &DemoArgs) -> anyhow::Result<DemoReport> {
    let s = args.seconds;
    if !(s.is_finite() && s > 0.0 && s <= transport::process::MAX_SECONDS) {
        bail!(
            "--seconds {} must be a positive number of seconds, at most {} (one week)",
            lung_model::plausible::compact(s),
            transport::process::MAX_SECONDS
        );
    }
    transport::process::run_ns(Some(args.seconds))?;
    if !(args.startup_timeout.is_finite()
        && args.startup_timeout > 0.0
        && args.startup_timeout <= 3600.0)
    {
        bail!(
            "--startup-timeout {} must be a positive number of seconds, at most 3600",
            lung_model::plausible::compact(args.startup_timeout)
        );
    }
    check_counts(args)?;
    let record = args
        .record
        .as_deref()
        .map(|p| crate::record::check(p, args.record_frames))
        .transpose()?;
    if !(args.predict_ms.is_finite() && (0.0..=100.0).contains(&args.predict_ms)) {
        bail!(
            "--predict-ms {} must be within 0..100 ms (0 draws the newest HMD sample)",
            args.predict_ms
        );
    }
    if args.window
        && std::env::var_os("DISPLAY").is_none()
        && std::env::var_os("WAYLAND_DISPLAY").is_none()
    {
        bail!(
            "--window needs a display, but DISPLAY is not set: run it on the workstation's desktop, \
             under xvfb-run, or without --window (headless)"
        );
    }
    if let Some(t) = &args.tracker {
        tracker_bridge::source::SourceSpec::parse(t)?;
    }
    let ok_deg = |v: f32| v.is_finite() && (0.0..=180.0).contains(&v);
    if !(ok_deg(args.roll_deg) && ok_deg(args.pitch_deg)) {
        bail!(
            "--roll-deg {} / --pitch-deg {} must be within 0..180 degrees",
            args.roll_deg,
            args.pitch_deg
        );
    }
    if !(args.sweep_period_s.is_finite() && (1.0..=3600.0).contains(&args.sweep_period_s)) {
        bail!(
            "--sweep-period-s {} must be within 1..3600 seconds",
            args.sweep_period_s
        );
    }
    // The renderer needs a GPU adapter: find out now, in the first second, rather than after
    // baking the lungs (a fresh machine without a Vulkan driver is the common case). The error names
    // the package and `./run demo`, which installs it.
    ensure_runtime_dir();
    let adapter = renderer::gpu::probe_adapter()?;
    eprintln!("lungdyn: GPU adapter {adapter}");
    // Every argument is checked before anything is written (kernels are baked below).
    let mut loaded = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    if let Some(mode) = args.mode {
        loaded.lungs.mode = mode;
    }
    let cpus = if args.cpus.is_empty() {
        check_cpus(&loaded.processes.cpus, "[processes] cpus")?;
        loaded.processes.cpus.clone()
    } else {
        args.cpus.clone()
    };
    // The renderer's calibration and optics files (a flag replaces the scene's): checked now, and
    // carried to the renderer in the resolved scene.
    renderer::camera::RigFiles::load(
        &loaded.render,
        args.calibration.as_deref(),
        args.hmd.as_deref(),
    )?;
    if let Some(c) = &args.calibration {
        loaded.render.calibration = Some(c.clone());
    }
    if let Some(h) = &args.hmd {
        loaded.render.hmd = Some(h.clone());
    }
    let tracker_source = args
        .tracker
        .clone()
        .unwrap_or_else(|| loaded.tracker.source.clone());
    tracker_bridge::source::SourceSpec::parse(&tracker_source)?;
    let posture = bridge_posture(loaded.tracker.posture);
    let posture = clap::ValueEnum::to_possible_value(&posture)
        .expect("every posture has a name")
        .get_name()
        .to_string();
    if (args.roll_deg > 0.0 || args.pitch_deg > 0.0) && !loaded.lungs.mode.follows_orientation() {
        eprintln!(
            "lungdyn: note: the {} mode keeps the supine breath whatever the patient's orientation; \
             use --mode basis (or sh, direct) to see the breath follow the turns",
            loaded.lungs.mode
        );
    }
    let instance = args
        .instance
        .clone()
        .unwrap_or_else(|| format!("demo-{}", std::process::id()));
    let services = Instance::new(&instance)?;
    // One launcher per instance: a second run with this name is refused here, before it writes or
    // removes anything (its cleanup would otherwise delete the first run's shared memory).
    let _lock = services.lock("launcher")?;
    eprintln!(
        "lungdyn: instance {instance} (`lungdyn instances` lists running ones; `lungdyn scene event \
         {instance} …` acts on this one)"
    );
    check_writable(&args.out)?;
    // Every lung runs from a kernel file: the scene's own, or the generated default baked once into
    // <out>/kernels (reused while the scene's mesh and bake settings are unchanged); all three
    // processes read the same resolved scene.
    let prepared = crate::prepare::prepare(loaded, &args.out.join("kernels"))?;
    let (scene, kernels, resolved_scene) = (prepared.scene, prepared.kernels, prepared.path);
    let tick_hz = scene.engine.tick_hz;
    // (--snapshot-at-s was checked with the other counts, before anything was written.)
    let warmup_ticks = args.snapshot_at_s.map_or(tick_hz as u64, |at| {
        ((at * tick_hz) as u64).max(tick_hz as u64)
    });
    // The renderer plans the frames when the breath starts, at that breath's own rate (a disease
    // may breathe faster than the scene's [pv] rate), from the front of the patient.
    let breath_frames = match record {
        Some(_) => args.record_frames.max(args.snapshots),
        None => args.snapshots,
    };

    // Subscribe to the reports before anything can publish them.
    let node = iox::node(&services, "launcher")?;
    let mut reports = services.report_inlet(&node)?;

    let exe = std::env::current_exe()
        .context("cannot find the lungdyn executable to start the processes")?;
    let mut common = vec!["--instance".to_string(), instance.clone()];
    // Children outlive a stuck launcher by at most this long.
    let child_seconds = (args.seconds + args.startup_timeout + 30.0)
        .min(transport::process::MAX_SECONDS)
        .to_string();
    common.extend(["--seconds".to_string(), child_seconds]);
    let with_scene = |mut v: Vec<String>| {
        v.extend(["--scene".to_string(), resolved_scene.display().to_string()]);
        v
    };
    let cpu = |i: usize| {
        cpus.get(i)
            .map(|c| vec!["--cpu".to_string(), c.to_string()])
            .unwrap_or_default()
    };
    let mut renderer_args = with_scene([common.clone(), cpu(2)].concat());
    renderer_args.push("--predict-ms".into());
    renderer_args.push(args.predict_ms.to_string());
    renderer_args.push("--hud".into());
    renderer_args.push(
        match args.hud {
            renderer::process::HudSwitch::On => "on",
            renderer::process::HudSwitch::Off => "off",
        }
        .into(),
    );
    if breath_frames > 0 {
        renderer_args.extend([
            "--snapshot-breath".to_string(),
            breath_frames.to_string(),
            "--snapshot-after-tick".to_string(),
            warmup_ticks.to_string(),
            "--snapshot-view".to_string(),
            "front".to_string(),
            "--snapshot-dir".to_string(),
            args.out.display().to_string(),
        ]);
    }
    if args.window {
        renderer_args.push("--window".into());
        if args.vsync {
            renderer_args.push("--vsync".into());
        }
    }
    let existing: std::collections::HashSet<PathBuf> = list_pngs(&args.out).into_iter().collect();
    let mut children = Children { procs: Vec::new() };
    children
        .procs
        .push(Children::spawn(&exe, "renderer", &renderer_args)?);
    children.procs.push(Children::spawn(
        &exe,
        "engine",
        &with_scene([common.clone(), cpu(1)].concat()),
    )?);
    let sweep = vec![
        "--roll-deg".to_string(),
        args.roll_deg.to_string(),
        "--pitch-deg".to_string(),
        args.pitch_deg.to_string(),
        "--sweep-period-s".to_string(),
        args.sweep_period_s.to_string(),
    ];
    children.procs.push(Children::spawn(
        &exe,
        "tracker-bridge",
        &[
            common.clone(),
            cpu(0),
            sweep,
            vec![
                "--source".to_string(),
                tracker_source.clone(),
                "--posture".to_string(),
                posture.to_string(),
            ],
        ]
        .concat(),
    )?);

    let mut stats = LatencyStats::new();
    let started = now_ns();
    let mut first_frame_ns: Option<u64> = None;
    let mut interrupted = false;
    let mut failure: Option<String> = None;
    let mut last_progress = 0u64;
    let show_progress = !args.json && std::io::IsTerminal::is_terminal(&std::io::stderr());
    loop {
        if !iox::idle(&node, Duration::from_millis(5)) {
            interrupted = true;
            eprintln!("lungdyn: interrupted, stopping the processes");
            break;
        }
        reports.drain(&mut |r: &FrameReport| {
            if first_frame_ns.is_none() {
                first_frame_ns = Some(now_ns());
            }
            stats.record(r);
        })?;
        let now = now_ns();
        if let Some((role, status)) = children.exited() {
            failure = Some(format!(
                "the {role} process exited early ({status}); see its message above"
            ));
            break;
        }
        match first_frame_ns {
            None if now - started > (args.startup_timeout * 1e9) as u64 => {
                failure = Some(format!(
                    "no frame reached the renderer within {} s: the pipeline did not start",
                    args.startup_timeout
                ));
                break;
            }
            Some(t0) if now - t0 >= (args.seconds * 1e9) as u64 => break,
            Some(t0) if show_progress && (now - t0) / 1_000_000_000 > last_progress => {
                last_progress = (now - t0) / 1_000_000_000;
                eprint!(
                    "\rlungdyn: {last_progress:>4} s / {} s, {} frames",
                    args.seconds, stats.frames
                );
            }
            _ => {}
        }
    }
    if show_progress && last_progress > 0 {
        eprintln!();
    }
    let measured_s = first_frame_ns
        .map(|t0| (now_ns() - t0) as f64 / 1e9)
        .unwrap_or(0.0);
    let killed = children.stop(Duration::from_secs(5));
    let _ = reports.drain(&mut |r: &FrameReport| stats.record(r));
    drop(reports);
    node.try_cleanup_dead_nodes();
    drop(node);
    // Every process of the instance has exited and the prefix is the instance's own: remove its
    // files. iceoryx2's node counter is expected; anything else a process failed to clean up is
    // worth saying.
    let cleanup = services.remove_leftovers();
    if !cleanup.unexpected.is_empty() {
        eprintln!(
            "lungdyn: warning: {} files of this run were left behind and have been removed:",
            cleanup.unexpected.len()
        );
        for f in &cleanup.unexpected {
            eprintln!("  {}", f.display());
        }
    }
    let leftovers = cleanup.unexpected;
    let remaining = services.leftovers().len();
    if !killed.is_empty() {
        eprintln!("lungdyn: warning: had to kill {killed:?} after SIGINT");
    }
    if let Some(f) = failure {
        bail!(f);
    }
    let mut frames: Vec<PathBuf> = list_pngs(&args.out)
        .into_iter()
        .filter(|p| !existing.contains(p))
        .collect();
    // In breath order (the engine tick in each name; the index alone sorts 100 before 11).
    frames.sort_by_key(|p| (crate::record::tick_of(p), p.clone()));
    let pngs: Vec<String> = frames.iter().map(|p| p.display().to_string()).collect();
    let recording = match (record, &args.record) {
        (Some(format), Some(path)) => {
            if frames.len() < breath_frames as usize {
                bail!(
                    "--record {}: the run ended after {} of the breath's {breath_frames} frames;                      run longer (--seconds) so a whole breath fits after the first second",
                    path.display(),
                    frames.len()
                );
            }
            let ticks: Vec<u64> = frames
                .iter()
                .map(|p| crate::record::tick_of(p).unwrap_or(0))
                .collect();
            let delays = crate::record::frame_delays_ms(&ticks, tick_hz);
            crate::record::write(format, &frames, &delays, path)?;
            Some(path.display().to_string())
        }
        _ => None,
    };
    let strip_frames: Vec<PathBuf> = match record {
        Some(_) => crate::record::spread(frames.len(), args.snapshots as usize)
            .into_iter()
            .map(|k| frames[k].clone())
            .collect(),
        None => frames,
    };
    let strip = crate::strip::breath_strip(&strip_frames, &args.out.join("breath_strip.png"))?
        .map(|p| p.display().to_string());
    if interrupted && stats.frames == 0 {
        bail!("interrupted before any frame was drawn");
    }
    let e2e = stats.end_to_end();
    let sched = stats.sample_latency();
    Ok(DemoReport {
        frames_rendered: stats.frames,
        deadline_misses: stats.sample_deadline_misses,
        tracker_samples: stats.tracker_samples,
        worst_case_ms: sched.max_ms,
        schedule_p99_ms: sched.p99_ms,
        missed_frame_slots: stats.missed_frame_slots,
        late_frames: stats.deadline_misses,
        end_to_end_p50_ms: e2e.p50_ms,
        end_to_end_p99_ms: e2e.p99_ms,
        end_to_end_max_ms: e2e.max_ms,
        pngs,
        strip,
        recording,
        hops: stats.rows(),
        budgets: {
            let b = scene.processes.budget_ms;
            vec![
                stats.budget_row("tracker-bridge", 0, b.tracker_bridge),
                stats.budget_row("engine", 2, b.engine),
                stats.budget_row("renderer", 4, b.renderer),
            ]
        },
        cpus: cpus.clone(),
        seconds: measured_s,
        fps: if measured_s > 0.0 {
            stats.frames as f64 / measured_s
        } else {
            0.0
        },
        stale_frames: stats.stale_frames,
        patient_pose_held_frames: stats.pose_held_frames,
        patient_pose_stale_frames: stats.pose_stale_frames,
        skipped_ticks: stats.skipped_ticks,
        lost_reports: stats.lost_reports,
        bad_stamps: stats.bad_stamps,
        untracked_frames: stats.untracked_frames,
        volume_min_ml: if stats.frames > 0 {
            stats.volume_range.0
        } else {
            0.0
        },
        volume_max_ml: if stats.frames > 0 {
            stats.volume_range.1
        } else {
            0.0
        },
        leftover_files: leftovers.len(),
        remaining_files: remaining,
        kernels,
        instance,
        mode: scene.lungs.mode.name().to_string(),
        calibration: scene
            .render
            .calibration
            .as_ref()
            .map(|p| p.display().to_string()),
        hmd: scene.render.hmd.as_ref().map(|p| p.display().to_string()),
    })
}

fn list_pngs(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .map(|e| e.path())
                .filter(|p| {
                    p.extension().is_some_and(|e| e == "png")
                        && p.file_name()
                            .is_some_and(|n| n.to_string_lossy().starts_with("lungs_"))
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The human-readable latency table.
pub fn table(r: &DemoReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "lungdyn demo: {} frames in {:.1} s ({:.1} fps), lung volume {:.0}-{:.0} ml, {} mode",
        r.frames_rendered, r.seconds, r.fps, r.volume_min_ml, r.volume_max_ml, r.mode
    );
    if let Some(c) = &r.calibration {
        let _ = writeln!(s, "lungs placed by the calibration {c}");
    }
    if let Some(h) = &r.hmd {
        let _ = writeln!(s, "eyes drawn from the HMD optics {h}");
    }
    let _ = writeln!(
        s,
        "{:<42} {:>8} {:>9} {:>9} {:>9}",
        "hop", "frames", "p50 ms", "p99 ms", "max ms"
    );
    for h in &r.hops {
        let _ = writeln!(
            s,
            "{:<42} {:>8} {:>9.3} {:>9.3} {:>9.3}",
            h.hop, h.count, h.p50_ms, h.p99_ms, h.max_ms
        );
    }
    let pct = if r.tracker_samples > 0 {
        100.0 * r.deadline_misses as f64 / r.tracker_samples as f64
    } else {
        0.0
    };
    let _ = writeln!(
        s,
        "deadline misses (tracker samples shown > {:.1} ms after capture, on the 60 Hz schedule, drawn or \
         not): {} of {} ({:.2} %), worst {:.1} ms; display slots without a frame: {}; drawn frames over the \
         deadline: {}",
        DEADLINE_NS as f64 / 1e6,
        r.deadline_misses,
        r.tracker_samples,
        pct,
        r.worst_case_ms,
        r.missed_frame_slots,
        r.late_frames
    );
    let _ = writeln!(
        s,
        "per-process budgets (p99 / max against the scene's [processes] budget_ms{}): {}",
        if r.cpus.is_empty() {
            ", not pinned".to_string()
        } else {
            format!(", pinned to cores {:?}", r.cpus)
        },
        r.budgets
            .iter()
            .map(|b| format!(
                "{} {:.3} / {:.3} of {} ms{}",
                b.process,
                b.p99_ms,
                b.max_ms,
                b.budget_ms,
                if b.over_budget > 0 {
                    format!(" ({} of {} samples OVER)", b.over_budget, b.samples)
                } else {
                    String::new()
                }
            ))
            .collect::<Vec<_>>()
            .join("; ")
    );
    if r.patient_pose_held_frames > 0 {
        let _ = writeln!(
            s,
            "PATIENT POSE HELD in {} of {} frames ({} of them stale: no patient sample in time, or \
             none yet) — drawn over a tinted background, amber held, red stale",
            r.patient_pose_held_frames, r.frames_rendered, r.patient_pose_stale_frames
        );
    }
    let _ = writeln!(
        s,
        "stale frames {}, engine ticks not drawn {}, reports lost {}, shm files left by iceoryx2 {} (remaining {})",
        r.stale_frames, r.skipped_ticks, r.lost_reports, r.leftover_files, r.remaining_files
    );
    if r.pngs.is_empty() {
        let _ = writeln!(s, "PNG frames: none");
    } else {
        let _ = writeln!(s, "PNG frames across one breath:");
        for p in &r.pngs {
            let _ = writeln!(s, "  {p}");
        }
    }
    if let Some(rec) = &r.recording {
        let _ = writeln!(s, "recording of one breath (front view, HUD): {rec}");
    }
    if let Some(strip) = &r.strip {
        let _ = writeln!(s, "breath strip (frames + motion panel: green = newly covered at end-inspiration, red = vacated): {strip}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `sh -c script` with SIGINT at its default (whatever the test runner inherited), stdout
    /// piped; returns once the script has printed its first line (so its traps are in place).
    fn sh(role: &'static str, script: &str) -> Proc {
        use std::io::BufRead;
        use std::os::unix::process::CommandExt;
        let mut cmd = Command::new("sh");
        cmd.args(["-c", script]).stdout(Stdio::piped());
        // SAFETY: signal(2) is async-signal-safe.
        unsafe {
            cmd.pre_exec(|| {
                libc::signal(libc::SIGINT, libc::SIG_DFL);
                Ok(())
            });
        }
        let mut child = cmd.spawn().unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        assert_eq!(line.trim(), "ready", "{role}");
        Proc::new(role, child)
    }

    fn code(e: &Ended) -> Option<i32> {
        match e {
            Ended::Status(s) => s.code(),
            Ended::Unknown(_) => None,
        }
    }

    fn signal_of(e: &Ended) -> Option<i32> {
        use std::os::unix::process::ExitStatusExt;
        match e {
            Ended::Status(s) => s.signal(),
            Ended::Unknown(_) => None,
        }
    }

    #[test]
    fn a_scenes_posture_is_the_bridges_posture_of_the_same_name() {
        use clap::ValueEnum;
        use lung_model::scene::Posture as S;
        for p in [
            S::Supine,
            S::Sitting,
            S::Prone,
            S::LeftLateral,
            S::RightLateral,
        ] {
            let b = bridge_posture(p);
            assert_eq!(b.to_possible_value().unwrap().get_name(), p.name());
        }
    }

    #[test]
    fn a_reaped_child_is_never_signalled_again() {
        let mut children = Children {
            procs: vec![sh("quits", "echo ready; exit 3")],
        };
        let (role, ended) = loop {
            if let Some(e) = children.exited() {
                break e;
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        assert_eq!((role, code(&ended)), ("quits", Some(3)));
        // Reaped: its pid may belong to someone else now, so nothing is sent to it.
        assert!(!children.procs[0].signal(libc::SIGINT));
        assert!(children.stop(Duration::from_millis(50)).is_empty());
        assert_eq!(code(children.procs[0].poll().unwrap()), Some(3));
    }

    #[test]
    fn stop_interrupts_then_kills_only_stragglers() {
        let mut children = Children {
            procs: vec![
                sh("polite", "echo ready; exec sleep 30"),
                sh("stubborn", "trap '' INT; echo ready; exec sleep 30"),
            ],
        };
        assert!(children.exited().is_none());
        let killed = children.stop(Duration::from_millis(300));
        assert_eq!(killed, vec!["stubborn"]);
        assert_eq!(
            signal_of(children.procs[0].poll().unwrap()),
            Some(libc::SIGINT)
        );
        assert_eq!(
            signal_of(children.procs[1].poll().unwrap()),
            Some(libc::SIGKILL)
        );
        // Both reaped: a second stop sends nothing and kills nothing.
        assert!(!children.procs[0].signal(libc::SIGTERM));
        assert!(children.stop(Duration::from_millis(10)).is_empty());
    }

    #[test]
    fn counts_and_cores_are_checked_before_any_work() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            demo: DemoArgs,
        }
        let args =
            |a: &[&str]| Cli::parse_from(std::iter::once("demo").chain(a.iter().copied())).demo;
        assert!(check_counts(&args(&[])).is_ok());
        assert!(check_counts(&args(&["--snapshots", "240"])).is_ok());
        let e = check_counts(&args(&["--snapshots", "1000000000"])).unwrap_err();
        assert!(e.to_string().contains("--snapshots 1000000000"), "{e}");
        let e = check_counts(&args(&["--cpus", "4096", "0", "0"])).unwrap_err();
        assert!(e.to_string().contains("core 4096"), "{e}");
        let first = allowed_cpus().unwrap()[0].to_string();
        assert!(check_counts(&args(&["--cpus", &first, &first, &first])).is_ok());
    }

    #[test]
    fn an_unwritable_out_folder_is_a_clear_error() {
        let e = check_writable(Path::new("/proc/lungdyn-cannot-exist")).unwrap_err();
        assert!(
            format!("{e:#}").contains("--out /proc/lungdyn-cannot-exist"),
            "{e:#}"
        );
    }
}
