//! `lungdyn demo`: start the three processes, let the lungs breathe, measure, stop cleanly.
//!
//! The launcher re-executes its own binary once per role (`lungdyn tracker-bridge|engine|renderer`),
//! so `cargo run --bin lungdyn` is enough on a fresh clone; each role is a separate OS process
//! talking to the others only through iceoryx2. Children get `PR_SET_PDEATHSIG`, so they die with
//! the launcher even if it is killed. On exit (or Ctrl-C) each child gets SIGINT, then SIGKILL after
//! a grace period; dead-node resources are cleaned and the instance's files are checked to be gone.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use ipc_types::FrameReport;
use transport::{iox, now_ns, Instance, Receive};

use crate::prepare::KernelUse;
use crate::supervise::Children;
use serde::Serialize;

use crate::stats::{HopRow, LatencyStats, DEADLINE_NS};
use lung_model::scene::SceneExt;

/// Frames drawn at one quality (the demo's JSON).
#[derive(Debug, Clone, serde::Serialize)]
pub struct QualityFrames {
    /// "full", or what the governor gave up.
    pub quality: String,
    /// Frames drawn at it.
    pub frames: u64,
}

impl QualityFrames {
    /// "LOD +2 676, LOD +1 16, full 16" (empty: none).
    pub fn list(all: &[QualityFrames]) -> String {
        let at: Vec<String> = all
            .iter()
            .map(|q| format!("{} {}", q.quality, q.frames))
            .collect();
        at.join(", ")
    }
}

/// Frames per quality, most first, in words.
fn quality_frames(seen: &[(u32, u64)]) -> Vec<QualityFrames> {
    let mut v: Vec<QualityFrames> = seen
        .iter()
        .map(|&(q, frames)| QualityFrames {
            quality: ipc_types::report_flags::describe_quality(q),
            frames,
        })
        .collect();
    v.sort_by(|a, b| b.frames.cmp(&a.frames).then(a.quality.cmp(&b.quality)));
    v
}

/// Options of `lungdyn demo`.
#[derive(Debug, Clone, clap::Args)]
pub struct DemoArgs {
    /// Seconds to run once frames flow (the default holds the first second's warm-up, the wait for
    /// the next breath to start and one whole breath at 12/min, so the PNGs are one breath).
    #[arg(long, default_value_t = 12.0)]
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
    /// Pin tracker-bridge, engine and renderer to these three cores, e.g. `--cpus 0,1,1` or
    /// `--cpus 0 1 1` (overrides the scene's `[processes] cpus`).
    // 1..=3 words: clap counts `num_args` before splitting at the commas, so `num_args = 3` refused
    // the comma form; [`check_counts`] asks for exactly three cores after the split.
    #[arg(long, value_delimiter = ',', num_args = 1..=3, value_name = "CORE")]
    pub cpus: Vec<usize>,
    /// Window, fullscreen display and present options (passed to the renderer); closing the window
    /// ends the demo. Headless otherwise.
    #[command(flatten)]
    pub output: renderer::window::DisplayArgs,
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
    /// A shared session's source (the scene's [remote] role = "source"): the room's keys (made by
    /// `lungdyn remote keys`), so `remote serve` beside the engine speaks mutual TLS and seals
    /// every packet; the scene's tcp/ endpoints become tls/ (default: the scene's [remote] keys;
    /// none: plain TCP on this machine only).
    #[arg(long, value_name = "DIR")]
    pub keys: Option<PathBuf>,
    /// This workstation's certificate in --keys (default: the scene's [remote] identity, else
    /// source).
    #[arg(long, value_name = "NAME", requires = "keys")]
    pub identity: Option<String>,
    /// What the lungs breathe to: model (the scene's PV model, its own clock) or the patient's
    /// respiratory signal followed live — trace:FILE (a Varian RPM .vxp, a CSV trace with time_s and
    /// amplitude_mm/volume_ml, or a ventilator recording, replayed at its own rate), udp:[BIND:]PORT
    /// (a live amplitude stream, one `mm=VALUE`, `ml=VALUE` or `au=VALUE` per datagram; senders
    /// off loopback only from the tracker's allow-list), tool:NAME (a tracked tool on the chest:
    /// its rise along the patient reference's anterior axis, with an OpenIGTLink or NDI --tracker;
    /// tool:NAME:auto along the axis it moves on, learnt from its first 12 s),
    /// igtl:NAME (an amplitude from the OpenIGTLink device NAME on an OpenIGTLink --tracker: SENSOR
    /// in mm, ml or no unit, or STRING `mm=VALUE`), or recorded (the signal a --tracker replay:FILE recording was made with, played bit for
    /// bit). The HUD
    /// says "following patient", "calibrating" or "signal lost" (a blue veil: the model carries
    /// on). Default: the scene's [breathing] table (model).
    #[arg(long, value_name = "SOURCE")]
    pub breathing: Option<String>,
    /// Withhold the breathing signal from S seconds into its recording (with --breathing-cut-for):
    /// a signal loss, to see the blue veil, the model carry on and the lungs take the patient's
    /// breath up again.
    #[arg(long, value_name = "S", requires = "breathing_cut_for")]
    pub breathing_cut_at: Option<f64>,
    /// How long --breathing-cut-at withholds the signal, seconds.
    #[arg(long, value_name = "S", requires = "breathing_cut_at")]
    pub breathing_cut_for: Option<f64>,
    /// Predict each frame's volume across this fixed latency, ms, instead of the pipeline's latency
    /// as measured (sets the scene's [breathing] latency = "fixed" and latency_ms; by default the
    /// engine predicts across the median the bridge reads from the renderer's reports, plus
    /// sensor_latency_ms; `lungdyn breathing follow` reports both).
    #[arg(long, value_name = "MS")]
    pub breathing_latency_ms: Option<f64>,
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
    /// A process that dies is restarted (a restarted engine resumes at the tick the stream
    /// expects), at most this many restarts within --restart-window-s; one more ends the run with
    /// an error (0: any death ends the run).
    #[arg(long, value_name = "N", default_value_t = 5)]
    pub max_restarts: u32,
    /// The window of --max-restarts, seconds.
    #[arg(long, value_name = "S", default_value_t = 60.0)]
    pub restart_window_s: f64,
    /// A process that stops answering — no frame from the renderer, engine or tracker-bridge for
    /// this long (stopped with SIGSTOP for good, deadlocked, stuck in a driver) — is killed and
    /// restarted like a dead one, within --max-restarts (0: never; the headset would show a
    /// frozen picture until the run ends). Above the longest pause `lungdyn faults` injects (700
    /// ms), so a process that is only paused comes back by itself.
    #[arg(long, value_name = "S", default_value_t = 1.0)]
    pub hang_after_s: f64,
    /// How the lungs are drawn over the patient (overrides the scene's `[render] look`): "opaque"
    /// (lit tissue; hides what is behind it, a tumour drawn through it), "translucent" (lit tissue
    /// with a fresnel rim, both lungs blended order-independently: the far wall, the other lung and
    /// a tumour show through), "see-through" (for an optical see-through HMD, an additive display
    /// where black is transparent: the lungs emit light, mostly at their outlines, on black).
    #[arg(long, value_name = "LOOK")]
    pub look: Option<lung_model::scene::Look>,
    /// What the lungs' colour shows (overrides the scene's `[render] color`): "tissue" (pink, the
    /// right lung warmer), "displacement" (distance from the rest position: blue 0 → yellow 20 mm),
    /// "ventilation" (local expansion relative to FRC: blue −10 %, white 0, red +30 %), "lobes"
    /// (each lobe its own colour, fissures as dark lines, a legend in the HUD; a lung whose kernel
    /// has no lobe section is drawn grey, and the renderer and HUD say so).
    #[arg(long, value_name = "COLOR")]
    pub color: Option<lung_model::scene::ColorMode>,
    /// Samples per pixel, 4 (multisample anti-aliasing) or 1 (off); overrides the scene's
    /// `[render] msaa`. Default: 4 on a GPU, 1 on a software rasterizer (lavapipe, where 4× costs
    /// 2.3–2.6× the frame: docs/LOOKS.md's render_looks figures).
    #[arg(long, value_name = "N")]
    pub msaa: Option<u32>,
    /// Draw level of detail (overrides the scene's `[render] lod`): "auto" (fewer triangles over
    /// the same deformed vertices when the lungs cover few pixels, chosen per frame), "off" (every
    /// triangle) or a fixed level 0..5 (level k: about 4^-k of the triangles). The HUD's
    /// frame-time line shows the level drawn.
    #[arg(long, value_name = "LOD")]
    pub lod: Option<lung_model::scene::Lod>,
    /// The quality governor (overrides the scene's `[render] governor`): "hold-deadline" (the
    /// default) draws less when frames run late — MSAA off, then coarser draw levels, then only
    /// the drawn level's vertices moved, then the translucent look opaque, never a coarser
    /// deformation unless --governor-least-bands allows it — and takes it back when there is time again, each change said on stderr and
    /// on the HUD; "off" always draws the scene's quality.
    /// docs/LATENCY.md "The governor".
    #[arg(long, value_name = "GOVERNOR")]
    pub governor: Option<lung_model::scene::Governor>,
    /// The governor's accuracy opt-in (overrides the scene's `[render] governor_least_bands`): once
    /// every drawing step is given up and frames are still late, it may also cap the "sh" mode's
    /// spherical-harmonic bands, a band at a time, down to N (1..8); the HUD says "SH<N>". Without
    /// it the deformation's accuracy is never lowered.
    #[arg(long, value_name = "N")]
    pub governor_least_bands: Option<u32>,
    /// Where the governor starts (overrides the scene's `[render] governor_start`): "remembered"
    /// (the default) where the last run of the same lungs and drawing settings on this GPU settled
    /// — kept in the cache folder ($LUNGDYN_CACHE_DIR, else ~/.cache/lungdyn; "off" keeps
    /// nothing) when a run ends after holding one quality for 5 s —, so a heavy scene does not
    /// spend its first frames late stepping down; "full" at the scene's full quality. Either way
    /// it steps up and down as frames allow from there.
    #[arg(long, value_name = "START")]
    pub governor_start: Option<lung_model::scene::GovernorStart>,
    /// Vertices per generated default lung (overrides the scene's `[lungs] vertices`; baked once
    /// into <out>/kernels and reused).
    #[arg(long, value_name = "N")]
    pub vertices: Option<usize>,
    /// Run the three processes SCHED_FIFO with locked memory where permitted (also the scene's
    /// `[processes] realtime`); each says once which capability or limit is missing where not.
    #[arg(long)]
    pub realtime: bool,
    /// Write one Chrome/Perfetto trace (JSON) of every process's stage spans on CLOCK_MONOTONIC to
    /// FILE (open it in ui.perfetto.dev). Off by default.
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// Send the breathing lungs to 3D Slicer over OpenIGTLink while the demo runs: lungdyn listens
    /// on PORT (18945 when none is given; 18944 is the tracker's) and Slicer's OpenIGTLinkIF
    /// connects as a client. Each frame: the meshes "RightLung"/"LeftLung" (RAS, mm, lobe codes as
    /// the point scalar "Lobe"), the tumour, and "BreathState" (JSON). Loopback only unless
    /// --igtl-serve-allow names more. Also the scene's `[slicer]`. docs/SLICER.md.
    #[arg(long, value_name = "PORT", num_args = 0..=1)]
    pub igtl_serve: Option<Option<u16>>,
    /// Meshes sent to Slicer per second, 1 to 60 (default: the scene's `[slicer] rate_hz`, 30).
    #[arg(long, value_name = "HZ")]
    pub igtl_serve_rate: Option<f64>,
    /// Also serve Slicer at ADDR (an address, 10.0.0.5, or a network, 10.0.0.0/24); repeatable.
    /// The port is then bound on every interface, and other hosts are still refused.
    #[arg(long, value_name = "ADDR")]
    pub igtl_serve_allow: Vec<String>,
    /// Send the breathing lungs to a 3D Slicer that listens (its OpenIGTLinkIF connector's default
    /// type, "Server", port 18944): lungdyn connects to HOST:PORT, tries again every second until
    /// it answers and whenever it goes, and sends what --igtl-serve sends. Instead of --igtl-serve
    /// (also the scene's `[slicer] connect`). docs/SLICER.md.
    #[arg(long, value_name = "HOST:PORT")]
    pub igtl_connect: Option<String>,
}

impl DemoArgs {
    /// `lungdyn demo`'s options parsed from `argv` (its first item the program's name), for
    /// commands that run the demo with some of them set (fault rounds, tests).
    pub fn from_args<I, T>(argv: I) -> Result<Self, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        use clap::Parser;
        #[derive(Parser)]
        struct Demo {
            #[command(flatten)]
            demo: DemoArgs,
        }
        Ok(Demo::try_parse_from(argv)?.demo)
    }

    /// The demo's defaults, as `lungdyn demo` with no options has them (the latency harness and
    /// `breathing follow` set a few of them).
    pub fn defaults() -> Self {
        Self::from_args(["demo"]).expect("the demo's defaults parse")
    }
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
    if let Some(v) = args.vertices {
        crate::launch::check_vertices(v).context("--vertices")?;
    }
    crate::launch::check_trace(args.trace.as_deref())?;
    if !args.cpus.is_empty() && args.cpus.len() != 3 {
        bail!(
            "--cpus {}: needs three cores, one each for tracker-bridge, engine and renderer \
             (e.g. --cpus 0,1,1 or --cpus 0 1 1); got {}",
            args.cpus
                .iter()
                .map(|c| c.to_string())
                .collect::<Vec<_>>()
                .join(","),
            args.cpus.len()
        );
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
    /// Frames of the breath (recording and strip) whose planned tick was not drawn (the renderer
    /// skipped it under load) and that show the next drawn frame instead.
    pub substituted_frames: usize,
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
    /// How frames reached the display: `mailbox`, `immediate`, `fifo`, `fifo-relaxed`, `openxr`;
    /// `none` headless.
    pub present_mode: String,
    /// The surface's `desired_maximum_frame_latency` (0 headless).
    pub frame_latency: u32,
    /// Frames that reached the display (`present` returned).
    pub presented_frames: u64,
    /// Per presented frame, renderer submit → `present` returned (CLOCK_MONOTONIC): median, 99th
    /// percentile and maximum, ms (0 headless).
    pub submit_to_present_p50_ms: f64,
    /// See `submit_to_present_p50_ms`.
    pub submit_to_present_p99_ms: f64,
    /// See `submit_to_present_p50_ms`.
    pub submit_to_present_max_ms: f64,
    /// Frames drawn without a fresh engine frame.
    pub stale_frames: u64,
    /// Frames drawn with the patient pose held by the engine (tinted amber on screen).
    pub patient_pose_held_frames: u64,
    /// Of those, frames whose held pose was stale or never arrived (tinted red on screen).
    pub patient_pose_stale_frames: u64,
    /// Frames whose lungs the patient's respiratory signal drove (`--breathing`; 0 otherwise).
    pub signal_following_frames: u64,
    /// Frames drawn while the followed signal was lost, ended or not yet there: the model breathed,
    /// under the blue veil.
    pub signal_lost_frames: u64,
    /// Of the frames the signal drove, those whose signal looked clipped by its sensor's range (the
    /// HUD said "SIGNAL LOOKS CLIPPED": the patient's breaths were deeper than drawn).
    pub signal_clipped_frames: u64,
    /// Frames that drew a lung outside the volume range its kernel was checked free of folds at
    /// bake time (`kernel inspect` gives the range; the HUD said "PAST ITS FOLD-FREE VOLUME").
    pub past_fold_free_frames: u64,
    /// Seconds from the command's start to the first frame drawn (bake, start-up and the draw
    /// levels included); null when none was drawn.
    pub first_frame_s: Option<f64>,
    /// The quality governor (`[render] governor`, `--governor`): "hold-deadline" or "off".
    pub governor: String,
    /// Frames the governor drew below the scene's quality.
    pub lowered_frames: u64,
    /// Frames drawn with every step the governor may take given up and still over its target: the
    /// deadline was not held by drawing less.
    pub governor_floor_frames: u64,
    /// Times the quality drawn changed between frames.
    pub quality_changes: u64,
    /// The quality of the last frame: "full", or what the governor gave up ("LOD +2").
    pub final_quality: String,
    /// Where the governor started (`[render] governor_start`): "remembered" or "full".
    pub governor_start: String,
    /// The quality of the first frame: not "full" where the governor started where an earlier run
    /// of the same setting settled.
    pub first_quality: String,
    /// Frames drawn at each quality, most frames first.
    pub quality_frames: Vec<QualityFrames>,
    /// Engine ticks never drawn.
    pub skipped_ticks: u64,
    /// Reports lost between renderer and launcher.
    pub lost_reports: u64,
    /// Frames with incomplete or unordered hop stamps.
    pub bad_stamps: u64,
    /// Frames drawn before the first tracker sample reached the engine (no latency to measure).
    pub untracked_frames: u64,
    /// Frames whose tracker sample number jumped further ahead than the clock allows (a corrupted
    /// or foreign tracker frame), left out of the schedule.
    pub implausible_samples: u64,
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
    /// The look drawn (`[render] look`).
    pub look: String,
    /// The colour mode drawn (`[render] color`).
    pub color: String,
    /// Samples per pixel the scene asks for (`[render] msaa`; null: the adapter's default, which
    /// the renderer's start line names).
    pub msaa: Option<u32>,
    /// The draw level of detail the scene asks for (`[render] lod`: auto, off or a level).
    pub lod: String,
    /// The calibration file the renderer placed the lungs by (none: the fixed offset).
    pub calibration: Option<String>,
    /// The HMD optics file the renderer drew the eyes from (none: the scene's IPD and field of view).
    pub hmd: Option<String>,
    /// Processes restarted after they died or stopped answering.
    pub restarts: usize,
    /// Of those, processes that stopped answering (no frame for --hang-after-s), killed and
    /// restarted.
    pub hung_restarts: usize,
    /// Each restart: the process, how it ended, when, what was cleaned, the time to a fresh frame.
    pub restart_log: Vec<crate::supervise::Restart>,
    /// The launcher's own stalls (stopped, or starved of CPU) longer than half of --hang-after-s:
    /// the children's silence meanwhile is not held against them. Reports published meanwhile wait
    /// in the launcher's 512-report buffer (8.5 s at 60 Hz); any beyond it count in lost_reports.
    pub launcher_stalls: u64,
    /// The longest the launcher went between two looks at its processes, ms.
    pub launcher_max_gap_ms: f64,
    /// Restarted engines whose first frame did not show the breath an uninterrupted run shows at
    /// that tick (must be 0).
    pub phase_errors: u64,
    /// Why the run ended: "completed", "interrupted", or the failure.
    pub ended: String,
    /// Set when the run failed (the launcher exits non-zero after printing this report).
    pub failure: Option<String>,
    /// Files of dead earlier instances (a killed launcher's) removed at start.
    pub swept_files: usize,
    /// What the link to 3D Slicer did (`--igtl-serve`; null when off).
    pub slicer: Option<crate::slicer::SlicerReport>,
}

/// The snapshot ticks of a run too short for one whole breath: `count` spread evenly from the
/// warm-up (at most a third of the run) to the run's end; empty when a whole breath fits after the
/// warm-up even if its start is a cycle away (then the renderer plans one breath), or `count` is 0.
pub fn partial_breath_ticks(
    count: u32,
    run_ticks: u64,
    warmup_ticks: u64,
    cycle_ticks: u64,
) -> Vec<u64> {
    if count == 0 || warmup_ticks + 2 * cycle_ticks <= run_ticks {
        return Vec::new();
    }
    let start = warmup_ticks.min(run_ticks / 3);
    let span = run_ticks.saturating_sub(start).max(1);
    (0..count as u64)
        .map(|k| start + k * span / count as u64)
        .collect()
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

/// What a [`Watch`] sees of a running demo on each pass of the launcher's loop.
pub struct Run<'r, 'a> {
    /// The run's processes and their restarts (signal one through `supervisor.children`).
    pub supervisor: &'r mut crate::supervise::Supervisor<'a>,
    /// The run's instance.
    pub services: &'r Instance,
    /// The resolved scene the processes run.
    pub scene: &'r lung_model::scene::Scene,
    /// The engine tick last published.
    pub last_tick: Option<u64>,
    /// When the first frame reached the launcher.
    pub first_frame_ns: Option<u64>,
    /// Now (the pass's time).
    pub now_ns: u64,
}

/// Something that watches (and may act on) a running demo from inside the launcher's loop — the
/// fault injector of `lungdyn faults`. Every method has a do-nothing default.
pub trait Watch {
    /// A frame report from the renderer, as it reaches the launcher.
    fn report(&mut self, _r: &FrameReport) {}
    /// An engine frame, as it reaches the launcher.
    fn engine_frame(&mut self, _f: &ipc_types::EngineFrame) {}
    /// A tracker frame, as it reaches the launcher (the stream keeps only the newest few: a
    /// watcher may miss some).
    fn tracker_frame(&mut self, _f: &ipc_types::TrackerFrame) {}
    /// Once per pass, after dead processes were restarted. `Ok(false)` ends the run now (as
    /// completed); an error ends it as a failure.
    fn pass(&mut self, _run: &mut Run<'_, '_>) -> anyhow::Result<bool> {
        Ok(true)
    }
    /// The children (role, pid), still running, just before they are asked to stop.
    fn before_stop(&mut self, _children: &[(&'static str, u32)]) {}
    /// With `--trace`: every process's stage timers over the whole run, once they have stopped.
    fn stages(&mut self, _stages: &[transport::trace::StageSummary]) {}
}

/// The plain demo watches nothing.
impl Watch for () {}

/// Run the demo; returns the report (the caller prints it).
pub fn run(args: &DemoArgs) -> anyhow::Result<DemoReport> {
    run_watched(args, &mut ())
}

/// Run the demo with `watch` looking on (see [`Watch`]); returns the report.
pub fn run_watched(args: &DemoArgs, watch: &mut dyn Watch) -> anyhow::Result<DemoReport> {
    let started_ns = now_ns();
    // SIGTERM, SIGINT and SIGHUP stop the run (latched: a SIGCONT after them changes nothing).
    transport::stop::install()?;
    // Validate: every argument checked before anything is written.
    let checked = validate(args)?;
    let Resolved { scene, launch } = resolve_scene(args)?;
    let slicer = crate::slicer::SlicerOptions::resolve(
        &scene,
        args.igtl_serve,
        args.igtl_serve_rate,
        &args.igtl_serve_allow,
        args.igtl_connect.as_deref(),
    )?
    .map(|o| o.open().map(|l| (o, l)))
    .transpose()?;
    let instance = args
        .instance
        .clone()
        .unwrap_or_else(|| format!("demo-{}", std::process::id()));
    let services = Instance::new(&instance)?;
    // One launcher per instance: a second run with this name is refused here, before it writes or
    // removes anything (its cleanup would otherwise delete the first run's shared memory).
    let _lock = services.lock("launcher")?;
    // What a killed launcher (or process) of an earlier run left behind goes first.
    let swept = Instance::sweep_dead().len();
    if swept > 0 {
        eprintln!("lungdyn: removed {swept} files of earlier runs that are no longer running");
    }
    eprintln!(
        "lungdyn: instance {instance} (`lungdyn instances` lists running ones; `lungdyn scene event \
         {instance} …` acts on this one)"
    );
    crate::outputs::check_writable(&args.out)?;
    // Prepare: every lung runs from a kernel file: the scene's own, or the generated default baked
    // once into <out>/kernels (reused while the scene's mesh and bake settings are unchanged); all
    // three processes read the same resolved scene.
    let prepared = crate::prepare::prepare(scene, &args.out.join("kernels"))?;
    let (scene, kernels) = (prepared.scene, prepared.kernels);
    let plan = SnapshotPlan::new(args, &scene, checked.record.is_some());
    // Slicer's link (bound before the bake) serves the engine's frames from its own thread.
    let slicer = match slicer {
        Some((o, listener)) => Some(crate::slicer::SlicerServer::start(
            &instance, &scene, &o, listener,
        )?),
        None => None,
    };

    // Subscribe to the reports before anything can publish them.
    let node = iox::node(&services, "launcher")?;
    let mut ports = LauncherPorts {
        reports: services.report_inlet(&node)?,
        // The engine tick last published (a restarted engine resumes at the next one, a restarted
        // renderer takes only the snapshots still ahead).
        engine: services.engine_inlet(&node)?,
        // The bridge's frames, read only as its sign of life (it publishes on its schedule even
        // while its device is silent).
        tracker: services.tracker_inlet(&node)?,
    };
    // Snapshots already in --out, with their modification times: a file this run writes again (the
    // same command run twice into one folder names the same ticks) counts as this run's.
    let existing = Existing::of(&args.out);
    let trace_dir = match &args.trace {
        Some(_) => Some(crate::launch::start_trace(&args.out, &instance)?),
        None => None,
    };
    // Spawn: one role table, each role's arguments and how it is started again.
    let roles = Roles::new(args, &scene, &launch, &instance, &plan, &prepared.path)?;
    let mut supervisor = crate::supervise::Supervisor::new(
        checked.intensity,
        Box::new(|| transport::iox::remove_dead_nodes(&services).map_err(anyhow::Error::from)),
    )
    .with_liveness(checked.liveness);
    roles.start(&mut supervisor)?;
    // Watch, until the run's time is up, it fails or it is stopped.
    let mut w = Watching::new(&scene, !args.json);
    w.run(
        args,
        &mut supervisor,
        &mut ports,
        &roles.last_tick,
        &services,
        &scene,
        watch,
    );
    // Stop, clean, report.
    let end_ns = now_ns();
    let measured_s = w
        .first_frame_ns
        .map(|t0| (end_ns - t0) as f64 / 1e9)
        .unwrap_or(0.0);
    let slicer = slicer.map(crate::slicer::SlicerServer::stop);
    watch.before_stop(&supervisor.children.pids());
    let killed = supervisor.children.stop(Duration::from_secs(5));
    let _ = ports.reports.drain(&mut |r: &FrameReport| {
        w.stats.record(r);
        watch.report(r);
    });
    // Whatever never reached a frame by the end (a renderer stopped for good) is missed.
    w.stats.finish(end_ns);
    let restart_log = supervisor.restarts.clone();
    let stalls = supervisor.stalls;
    drop(supervisor);
    drop(ports);
    node.try_cleanup_dead_nodes();
    drop(node);
    let (leftovers, remaining) = remove_leftovers(&services);
    if !killed.is_empty() {
        eprintln!("lungdyn: warning: had to kill {killed:?} after SIGINT");
    }
    if let (Some(dir), Some(file)) = (&trace_dir, &args.trace) {
        let stages = crate::launch::finish_trace(dir, file)?;
        watch.stages(&stages);
    }
    if w.interrupted && w.stats.frames == 0 && w.failure.is_none() {
        w.failure = Some("interrupted before any frame was drawn".to_string());
    }
    if let Some(t) = w.resumed_at {
        w.failure.get_or_insert(format!(
            "the restarted engine never published its resume tick {t}"
        ));
    }
    let pictures = pictures(args, &existing, checked.record, &plan, &mut w.failure);
    let first_frame_s = w
        .first_frame_ns
        .map(|t| t.saturating_sub(started_ns) as f64 / 1e9);
    Ok(report(Ended {
        first_frame_s,
        w,
        scene: &scene,
        cpus: launch.cpus,
        measured_s,
        pictures,
        restart_log,
        stalls,
        leftovers: leftovers.len(),
        remaining,
        kernels,
        instance,
        swept,
        slicer,
    }))
}

/// What [`validate`] found: the recording's format, the restart limits.
struct Checked {
    record: Option<crate::record::RecordFormat>,
    intensity: crate::supervise::Intensity,
    liveness: Option<crate::supervise::Liveness>,
}

/// Every argument checked before anything is written or started.
fn validate(args: &DemoArgs) -> anyhow::Result<Checked> {
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
    let intensity = crate::supervise::Intensity::checked(args.max_restarts, args.restart_window_s)?;
    let liveness = crate::supervise::Liveness::checked(args.hang_after_s, args.startup_timeout)?;
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
    if args.output.shown()
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
    Ok(Checked {
        record,
        intensity,
        liveness,
    })
}

/// The scene the processes run, with the command line's overrides, and how they are started.
struct Resolved {
    scene: lung_model::scene::Scene,
    launch: Launch,
}

/// What the processes are started with besides the scene.
struct Launch {
    /// Cores of tracker-bridge, engine, renderer (empty: not pinned).
    cpus: Vec<usize>,
}

/// The GPU adapter found, the scene loaded and overridden by the command line, checked.
fn resolve_scene(args: &DemoArgs) -> anyhow::Result<Resolved> {
    // The renderer needs a GPU adapter: find out now, in the first second, rather than after
    // baking the lungs (a fresh machine without a Vulkan driver is the common case). The error names
    // the package and `./run demo`, which installs it.
    ensure_runtime_dir();
    let adapter = renderer::gpu::probe_adapter()?;
    eprintln!("lungdyn: GPU adapter {adapter}");
    let mut loaded = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    if let Some(mode) = args.mode {
        loaded.lungs.mode = mode;
    }
    if let Some(look) = args.look {
        loaded.render.look = look;
    }
    if let Some(color) = args.color {
        loaded.render.color = color;
    }
    if let Some(n) = args.msaa {
        if !lung_model::scene::MSAA_SAMPLES.contains(&n) {
            anyhow::bail!("--msaa {n}: give 4 (anti-aliased) or 1 (off)");
        }
        loaded.render.msaa = Some(n);
    }
    if let Some(lod) = args.lod {
        loaded.render.lod = lod;
    }
    if let Some(g) = args.governor {
        loaded.render.governor = g;
    }
    if let Some(start) = args.governor_start {
        loaded.render.governor_start = start;
    }
    if let Some(n) = args.governor_least_bands {
        loaded.render.governor_least_bands = Some(n);
        loaded
            .render
            .validate()
            .map_err(|e| anyhow::anyhow!("--governor-least-bands {n}: {e}"))?;
    }
    if let Some(v) = args.vertices {
        loaded.lungs.vertices = v;
    }
    loaded.processes.realtime |= args.realtime;
    let cpus = if args.cpus.is_empty() {
        check_cpus(&loaded.processes.cpus, "[processes] cpus")?;
        loaded.processes.cpus.clone()
    } else {
        // The resolved scene carries the cores the processes run on: a process reads from it which
        // core is its own (busy-poll needs one; `auto` busy-polls on it).
        loaded.processes.cpus = args.cpus.clone();
        loaded
            .validate()
            .map_err(|e| anyhow::anyhow!("the scene with --cpus {:?}: {e}", args.cpus))?;
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
    // The bridge reads its source and posture from the resolved scene's [tracker] table itself.
    if let Some(t) = &args.tracker {
        loaded.tracker.source = t.clone();
    }
    tracker_bridge::source::SourceSpec::parse(&loaded.tracker.source)?;
    if let Some(dir) = &args.keys {
        use_keys(&mut loaded, dir, args.identity.as_deref())?;
    }
    // The engine follows the signal the bridge reads, both from the resolved scene's [breathing].
    if let Some(b) = &args.breathing {
        match breathing_override(b)? {
            None => loaded.breathing.source = lung_model::scene::BreathSource::Model,
            Some(signal) => {
                loaded.breathing.source = lung_model::scene::BreathSource::Signal;
                loaded.breathing.signal = signal;
            }
        }
        loaded
            .validate()
            .map_err(|e| anyhow::anyhow!("the scene with --breathing {b}: {e}"))?;
        recorded_signal_check(&loaded.tracker.source, &loaded.breathing.signal)?;
    }
    if let Some(ms) = args.breathing_latency_ms {
        require_signal(&loaded, &format!("--breathing-latency-ms {ms}"), "predict")?;
        loaded.breathing.latency_ms = ms;
        loaded.breathing.latency = lung_model::scene::LatencyChoice::Fixed;
        loaded
            .validate()
            .map_err(|e| anyhow::anyhow!("--breathing-latency-ms {ms}: {e}"))?;
    }
    if let (Some(at), Some(dur)) = (args.breathing_cut_at, args.breathing_cut_for) {
        tracker_bridge::signal::check_cut(at, dur)?;
        require_signal(&loaded, &format!("--breathing-cut-at {at}"), "cut")?;
    }
    if (args.roll_deg > 0.0 || args.pitch_deg > 0.0) && !loaded.lungs.mode.follows_orientation() {
        eprintln!(
            "lungdyn: note: the {} mode keeps the supine breath whatever the patient's orientation; \
             use --mode basis (or sh, direct) to see the breath follow the turns",
            loaded.lungs.mode
        );
    }
    Ok(Resolved {
        scene: loaded,
        launch: Launch { cpus },
    })
}

/// When the renderer writes the run's pictures.
struct SnapshotPlan {
    tick_hz: f64,
    /// The first tick a breath's frames may be planned from (the first second is warm-up).
    warmup_ticks: u64,
    /// Frames of the breath (the strip's, or the recording's).
    breath_frames: u32,
    /// A run too short for a whole breath: the ticks its snapshots are spread over.
    spread_ticks: Vec<u64>,
}

impl SnapshotPlan {
    fn new(args: &DemoArgs, scene: &lung_model::scene::Scene, recording: bool) -> Self {
        let tick_hz = scene.engine.tick_hz;
        // (--snapshot-at-s was checked with the other counts, before anything was written.)
        let warmup_ticks = args.snapshot_at_s.map_or(tick_hz as u64, |at| {
            ((at * tick_hz) as u64).max(tick_hz as u64)
        });
        // The renderer plans the frames when the breath starts, at that breath's own rate (a
        // disease may breathe faster than the scene's [pv] rate), from the front of the patient.
        let breath_frames = if recording {
            args.record_frames.max(args.snapshots)
        } else {
            args.snapshots
        };
        // A run too short to hold a whole breath after the warm-up (waiting for the next cycle
        // start can take a cycle) still gets its snapshots: spread over what the run has, from the
        // same front view, and it says so (a strip of part of a breath). A recording always wants
        // a whole breath.
        // A waveform scene breathes at its recording's rate, not [pv] breaths_per_min (read
        // already when the scene was resolved, so it reads again here).
        let cycle_s = 60.0
            / scene
                .pv_waveform()
                .ok()
                .flatten()
                .map_or(scene.pv.breaths_per_min, |w| w.rate_per_min);
        let spread_ticks = partial_breath_ticks(
            if recording { 0 } else { breath_frames },
            (args.seconds * tick_hz) as u64,
            warmup_ticks,
            (cycle_s * tick_hz).round().max(1.0) as u64,
        );
        if !spread_ticks.is_empty() {
            eprintln!(
                "demo: {} s is too short for one whole breath after the first second (a cycle is \
                 {:.1} s); the {breath_frames} snapshots are spread over the run, part of a breath \
                 — run --seconds {:.0} or more for a strip of one whole breath",
                args.seconds,
                cycle_s,
                (warmup_ticks as f64 / tick_hz + 2.0 * cycle_s).ceil()
            );
        }
        Self {
            tick_hz,
            warmup_ticks,
            breath_frames,
            spread_ticks,
        }
    }
}

/// The launcher's subscriptions: what it measures, and each process's sign of life.
struct LauncherPorts {
    reports: transport::iox::Inlet<FrameReport>,
    engine: transport::iox::Inlet<ipc_types::EngineFrame>,
    tracker: transport::iox::Inlet<ipc_types::TrackerFrame>,
}

/// The PNGs in --out before the run, with their modification times.
struct Existing(std::collections::HashMap<PathBuf, Option<std::time::SystemTime>>);

impl Existing {
    fn of(dir: &Path) -> Self {
        Self(
            list_pngs(dir)
                .into_iter()
                .map(|p| {
                    let t = modified(&p);
                    (p, t)
                })
                .collect(),
        )
    }

    /// Written by this run: new, or written again.
    fn written_now(&self, p: &Path) -> bool {
        self.0
            .get(p)
            .is_none_or(|&t| t.is_none() || modified(p) != t)
    }
}

fn modified(p: &Path) -> Option<std::time::SystemTime> {
    std::fs::metadata(p).and_then(|m| m.modified()).ok()
}

/// The role table: each process's command line, and how it is started again after a death.
struct Roles<'p> {
    exe: PathBuf,
    renderer: Vec<String>,
    engine: Vec<String>,
    bridge: Vec<String>,
    /// `remote serve`'s, when the scene's [remote] role is source.
    remote: Option<Vec<String>>,
    plan: &'p SnapshotPlan,
    out_dir: String,
    /// The engine tick last published (set by the watch loop).
    last_tick: std::cell::Cell<Option<u64>>,
}

impl<'p> Roles<'p> {
    fn new(
        args: &DemoArgs,
        scene: &lung_model::scene::Scene,
        launch: &Launch,
        instance: &str,
        plan: &'p SnapshotPlan,
        resolved_scene: &Path,
    ) -> anyhow::Result<Self> {
        let exe = std::env::current_exe()
            .context("cannot find the lungdyn executable to start the processes")?;
        let mut common = vec!["--instance".to_string(), instance.to_string()];
        // Children outlive a stuck launcher by at most this long.
        let child_seconds = (args.seconds + args.startup_timeout + 30.0)
            .min(transport::process::MAX_SECONDS)
            .to_string();
        common.extend(["--seconds".to_string(), child_seconds]);
        if scene.processes.realtime {
            common.push("--realtime".to_string());
        }
        let with_scene = |mut v: Vec<String>| {
            v.extend(["--scene".to_string(), resolved_scene.display().to_string()]);
            v
        };
        let cpu = |i: usize| {
            launch
                .cpus
                .get(i)
                .map(|c| vec!["--cpu".to_string(), c.to_string()])
                .unwrap_or_default()
        };
        let mut renderer = with_scene([common.clone(), cpu(2)].concat());
        let hud = match args.hud {
            renderer::process::HudSwitch::On => "on",
            renderer::process::HudSwitch::Off => "off",
        };
        renderer.extend([
            "--predict-ms".into(),
            args.predict_ms.to_string(),
            "--hud".into(),
            hud.into(),
        ]);
        renderer.extend(args.output.to_args());
        let engine = with_scene([common.clone(), cpu(1)].concat());
        // A scene whose [remote] role is "source" shares this engine with remote sites.
        let remote = scene
            .remote
            .as_ref()
            .is_some_and(|r| r.role == lung_model::scene_remote::RemoteRole::Source)
            .then(|| {
                let plain: Vec<String> = common
                    .iter()
                    .filter(|a| *a != "--realtime")
                    .cloned()
                    .collect();
                with_scene([vec!["serve".to_string()], plain].concat())
            });
        let bridge = with_scene(
            [
                common,
                cpu(0),
                vec![
                    "--roll-deg".to_string(),
                    args.roll_deg.to_string(),
                    "--pitch-deg".to_string(),
                    args.pitch_deg.to_string(),
                    "--sweep-period-s".to_string(),
                    args.sweep_period_s.to_string(),
                ],
                match (args.breathing_cut_at, args.breathing_cut_for) {
                    (Some(at), Some(dur)) => vec![
                        "--breathing-cut-at".to_string(),
                        at.to_string(),
                        "--breathing-cut-for".to_string(),
                        dur.to_string(),
                    ],
                    _ => Vec::new(),
                },
            ]
            .concat(),
        );
        Ok(Self {
            exe,
            renderer,
            engine,
            bridge,
            remote,
            plan,
            out_dir: args.out.display().to_string(),
            last_tick: std::cell::Cell::new(None),
        })
    }

    /// The renderer's arguments now: a restarted one takes only the snapshots still ahead, and
    /// plans its breath after the last tick shown (a strip across a restart can hold frames of
    /// two breaths).
    fn renderer_args(&self) -> Vec<String> {
        let mut a = self.renderer.clone();
        let last = self.last_tick.get();
        let plan = self.plan;
        let (key, value) = if !plan.spread_ticks.is_empty() {
            let ahead: Vec<String> = plan
                .spread_ticks
                .iter()
                .filter(|&&t| last.is_none_or(|l| t > l))
                .map(|t| t.to_string())
                .collect();
            if ahead.is_empty() {
                return a;
            }
            ("--snapshot-ticks", ahead.join(","))
        } else if plan.breath_frames > 0 {
            a.extend([
                "--snapshot-breath".to_string(),
                plan.breath_frames.to_string(),
            ]);
            let after = last.map_or(plan.warmup_ticks, |l| plan.warmup_ticks.max(l + 1));
            ("--snapshot-after-tick", after.to_string())
        } else {
            return a;
        };
        a.extend([
            key.to_string(),
            value,
            "--snapshot-view".to_string(),
            "front".to_string(),
            "--snapshot-dir".to_string(),
            self.out_dir.clone(),
        ]);
        a
    }

    /// Start every role under `supervisor`, each watched by its stream but `remote serve`.
    fn start<'s>(
        &'s self,
        supervisor: &mut crate::supervise::Supervisor<'s>,
    ) -> anyhow::Result<()> {
        let exe = &self.exe;
        supervisor.start(
            "renderer",
            Box::new(move || Children::spawn(exe, "renderer", &self.renderer_args())),
        )?;
        supervisor.start(
            "engine",
            Box::new(move || {
                let mut a = self.engine.clone();
                if let Some(t) = self.last_tick.get() {
                    a.extend(["--start-tick".to_string(), (t + 1).to_string()]);
                }
                Children::spawn(exe, "engine", &a)
            }),
        )?;
        // `remote serve` runs beside the engine, supervised like the other processes (restarted if
        // it dies; a restarted one takes the engine's current state from its stream's history).
        if let Some(serve) = &self.remote {
            eprintln!(
                "lungdyn: the scene's [remote] role is source: starting `lungdyn remote serve` \
                 (sites join with `lungdyn remote join --scene SITE_SCENE`)"
            );
            supervisor.start(
                "remote",
                Box::new(move || Children::spawn(exe, "remote", serve)),
            )?;
        }
        supervisor.start(
            "tracker-bridge",
            Box::new(move || Children::spawn(exe, "tracker-bridge", &self.bridge)),
        )?;
        for role in ["renderer", "engine", "tracker-bridge"] {
            supervisor.watch(role);
        }
        Ok(())
    }
}

/// The watch loop's state: what it measured and how the run is ending.
struct Watching {
    stats: LatencyStats,
    first_frame_ns: Option<u64>,
    interrupted: bool,
    failure: Option<String>,
    /// A process that finished its work (the end of a replay).
    finished: Option<&'static str>,
    /// A restarted engine's first tick, checked against the deterministic expectation.
    resumed_at: Option<u64>,
    /// The sample shown when the tracker-bridge died, and the one shown last.
    bridge_died_at: Option<u64>,
    last_sample: u64,
    phase: crate::supervise::PhaseCheck,
    last_progress: u64,
    show_progress: bool,
}

impl Watching {
    fn new(scene: &lung_model::scene::Scene, text: bool) -> Self {
        Self {
            stats: LatencyStats::new(),
            first_frame_ns: None,
            interrupted: false,
            failure: None,
            finished: None,
            resumed_at: None,
            bridge_died_at: None,
            last_sample: 0,
            phase: crate::supervise::PhaseCheck::new(scene),
            last_progress: 0,
            show_progress: text && std::io::IsTerminal::is_terminal(&std::io::stderr()),
        }
    }

    /// Pass after pass, every 5 ms, until the run ends.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &mut self,
        args: &DemoArgs,
        supervisor: &mut crate::supervise::Supervisor<'_>,
        ports: &mut LauncherPorts,
        last_tick: &std::cell::Cell<Option<u64>>,
        services: &Instance,
        scene: &lung_model::scene::Scene,
        watch: &mut dyn Watch,
    ) {
        let started = now_ns();
        loop {
            if !transport::stop::idle(Duration::from_millis(5)) {
                self.interrupted = true;
                eprintln!(
                    "lungdyn: interrupted ({}), stopping the processes",
                    transport::stop::signal().map_or("a stop signal", transport::stop::name)
                );
                break;
            }
            let now = match self.drain(supervisor, ports, last_tick, watch) {
                Ok(now) => now,
                Err(e) => {
                    self.failure = Some(format!("{e:#}"));
                    break;
                }
            };
            if !self.supervise(supervisor, last_tick.get()) {
                break;
            }
            let mut view = Run {
                supervisor: &mut *supervisor,
                services,
                scene,
                last_tick: last_tick.get(),
                first_frame_ns: self.first_frame_ns,
                now_ns: now,
            };
            match watch.pass(&mut view) {
                Ok(true) => {}
                Ok(false) => break,
                Err(e) => {
                    self.failure = Some(format!("{e:#}"));
                    break;
                }
            }
            if !self.on_time(args, started, now) {
                break;
            }
        }
        if self.show_progress && self.last_progress > 0 {
            eprintln!();
        }
    }

    /// Take every report and frame queued: measure, note each process's sign of life, check a
    /// resumed engine's breath. Returns the pass's time.
    fn drain(
        &mut self,
        supervisor: &mut crate::supervise::Supervisor<'_>,
        ports: &mut LauncherPorts,
        last_tick: &std::cell::Cell<Option<u64>>,
        watch: &mut dyn Watch,
    ) -> anyhow::Result<u64> {
        // Recovered: a frame from a live engine, showing a sample of the live bridge.
        let mut fresh = false;
        let (mut renderer_beat, mut engine_beat, mut bridge_beat) = (None, None, None);
        ports.reports.drain(&mut |r: &FrameReport| {
            if self.first_frame_ns.is_none() {
                self.first_frame_ns = Some(now_ns());
            }
            renderer_beat = Some(r.stamps.renderer_submit_ns.max(r.present_ns));
            let new_sample = self.bridge_died_at.is_none_or(|f| r.tracker_frame != f);
            if r.flags & ipc_types::report_flags::STALE_ENGINE == 0 && new_sample {
                fresh = true;
                self.bridge_died_at = None;
            }
            self.last_sample = r.tracker_frame;
            self.stats.record(r);
            watch.report(r);
        })?;
        let now = now_ns();
        ports.engine.drain(&mut |f: &ipc_types::EngineFrame| {
            engine_beat = Some(f.stamps.engine_publish_ns);
            if self.resumed_at == Some(f.tick) {
                self.resumed_at = None;
                self.phase.check(f);
            }
            last_tick.set(Some(f.tick));
            watch.engine_frame(f);
        })?;
        ports.tracker.drain(&mut |f: &ipc_types::TrackerFrame| {
            bridge_beat = Some(f.stamps.bridge_publish_ns);
            watch.tracker_frame(f);
        })?;
        for (role, beat) in [
            ("renderer", renderer_beat),
            ("engine", engine_beat),
            ("tracker-bridge", bridge_beat),
        ] {
            if let Some(published) = beat {
                supervisor.beat(role, published, now);
            }
        }
        if self.first_frame_ns.is_some() {
            supervisor.pipeline_running();
        }
        if fresh && supervisor.recovering() {
            supervisor.recovered(now);
        }
        Ok(now)
    }

    /// Restart what died or hung; false when the run ends (a process finished its work, or the
    /// restarts went past the limit).
    fn supervise(
        &mut self,
        supervisor: &mut crate::supervise::Supervisor<'_>,
        last_tick: Option<u64>,
    ) -> bool {
        if let Some(role) = supervisor.finished() {
            // A replay shorter than --seconds ends the run cleanly (it is not looped: the
            // recording's samples would jump back in time); the report covers what was played.
            eprintln!("lungdyn: the {role} finished (its source ended); stopping the run");
            self.finished = Some(role);
            return false;
        }
        let restarted = match supervisor.check() {
            Err(e) => {
                self.failure = Some(format!("{e:#}"));
                return false;
            }
            Ok(restarted) => restarted,
        };
        for role in restarted {
            let r = supervisor.restarts.last().expect("just restarted");
            let how = if r.hung {
                r.ended.clone()
            } else {
                format!("died ({})", r.ended)
            };
            if role == "engine" {
                self.resumed_at = last_tick.map(|t| t + 1);
                eprintln!(
                    "lungdyn: the engine process {how}; restarted, resuming at tick {}",
                    self.resumed_at.unwrap_or(0)
                );
            } else {
                eprintln!("lungdyn: the {role} process {how}; restarted");
            }
            if role == "tracker-bridge" {
                self.bridge_died_at = Some(self.last_sample);
            }
            self.stats.restarted(role);
        }
        true
    }

    /// The run's clock: false when its time is up, or the pipeline never started; the progress
    /// line at a terminal.
    fn on_time(&mut self, args: &DemoArgs, started: u64, now: u64) -> bool {
        match self.first_frame_ns {
            None if now - started > (args.startup_timeout * 1e9) as u64 => {
                self.failure = Some(format!(
                    "no frame reached the renderer within {} s: the pipeline did not start",
                    args.startup_timeout
                ));
                false
            }
            Some(t0) if now - t0 >= (args.seconds * 1e9) as u64 => false,
            Some(t0) if self.show_progress && (now - t0) / 1_000_000_000 > self.last_progress => {
                self.last_progress = (now - t0) / 1_000_000_000;
                eprint!(
                    "\rlungdyn: {:>4} s / {} s, {} frames",
                    self.last_progress, args.seconds, self.stats.frames
                );
                true
            }
            _ => true,
        }
    }
}

/// Every process of the instance has exited and the prefix is the instance's own: remove its
/// files. iceoryx2's node counter is expected; anything else a process failed to clean up is worth
/// saying. Returns (the unexpected files removed, the files still there).
fn remove_leftovers(services: &Instance) -> (Vec<PathBuf>, usize) {
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
    (cleanup.unexpected, services.leftovers().len())
}

/// The run's pictures: its PNGs in breath order, the recording, the strip.
struct Pictures {
    pngs: Vec<String>,
    substituted_frames: usize,
    recording: Option<String>,
    strip: Option<String>,
}

/// Gather the PNGs this run wrote, encode the recording and the strip; a failure of either is the
/// run's failure (the first one kept).
fn pictures(
    args: &DemoArgs,
    existing: &Existing,
    record: Option<crate::record::RecordFormat>,
    plan: &SnapshotPlan,
    failure: &mut Option<String>,
) -> Pictures {
    let mut frames: Vec<PathBuf> = list_pngs(&args.out)
        .into_iter()
        .filter(|p| existing.written_now(p))
        .collect();
    // In breath order (the engine tick in each name; the index alone sorts 100 before 11).
    frames.sort_by_key(|p| (crate::record::tick_of(p), p.clone()));
    let pngs: Vec<String> = frames.iter().map(|p| p.display().to_string()).collect();
    let substituted_frames = crate::record::substituted(&frames);
    if substituted_frames > 0 {
        eprintln!(
            "lungdyn: {substituted_frames} of the breath's {} frames were not drawn at their planned \
             tick (the renderer skipped it under load) and show the next drawn frame instead",
            frames.len()
        );
    }
    let recording = match (record, &args.record) {
        (Some(_), Some(path)) if frames.len() < plan.breath_frames as usize => {
            failure.get_or_insert(format!(
                "--record {}: the run ended after {} of the breath's {} frames; run longer \
                 (--seconds) so a whole breath fits after the first second",
                path.display(),
                frames.len(),
                plan.breath_frames
            ));
            None
        }
        (Some(format), Some(path)) => {
            let ticks: Vec<u64> = frames
                .iter()
                .map(|p| crate::record::tick_of(p).unwrap_or(0))
                .collect();
            let delays = crate::record::frame_delays_ms(&ticks, plan.tick_hz);
            match crate::record::write(format, &frames, &delays, path) {
                Ok(()) => Some(path.display().to_string()),
                Err(e) => {
                    failure.get_or_insert(format!("{e:#}"));
                    None
                }
            }
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
    let strip = match crate::strip::breath_strip(&strip_frames, &args.out.join("breath_strip.png"))
    {
        Ok(s) => s.map(|p| p.display().to_string()),
        Err(e) => {
            failure.get_or_insert(format!("{e:#}"));
            None
        }
    };
    Pictures {
        pngs,
        substituted_frames,
        recording,
        strip,
    }
}

/// Everything the report is made of, once the processes are gone.
struct Ended<'s> {
    first_frame_s: Option<f64>,
    w: Watching,
    scene: &'s lung_model::scene::Scene,
    cpus: Vec<usize>,
    measured_s: f64,
    pictures: Pictures,
    restart_log: Vec<crate::supervise::Restart>,
    stalls: crate::supervise::Stalls,
    leftovers: usize,
    remaining: usize,
    kernels: Vec<KernelUse>,
    instance: String,
    swept: usize,
    slicer: Option<crate::slicer::SlicerReport>,
}

/// The run's report.
fn report(e: Ended<'_>) -> DemoReport {
    let (stats, scene) = (&e.w.stats, e.scene);
    let e2e = stats.end_to_end();
    let sched = stats.sample_latency();
    let to_present = stats.submit_to_present();
    let (present_code, frame_latency) = stats
        .present_mode
        .unwrap_or((ipc_types::present_mode::NONE, 0));
    let b = scene.processes.budget_ms;
    let (volume_min_ml, volume_max_ml) = if stats.frames > 0 {
        stats.volume_range
    } else {
        (0.0, 0.0)
    };
    DemoReport {
        first_frame_s: e.first_frame_s,
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
        pngs: e.pictures.pngs,
        strip: e.pictures.strip,
        recording: e.pictures.recording,
        substituted_frames: e.pictures.substituted_frames,
        hops: stats.rows(),
        budgets: vec![
            stats.budget_row("tracker-bridge", 0, b.tracker_bridge),
            stats.budget_row("engine", 2, b.engine),
            stats.budget_row("renderer", 4, b.renderer),
        ],
        cpus: e.cpus,
        seconds: e.measured_s,
        fps: if e.measured_s > 0.0 {
            stats.frames as f64 / e.measured_s
        } else {
            0.0
        },
        present_mode: ipc_types::present_mode::name(present_code).to_string(),
        frame_latency,
        presented_frames: stats.presented_frames,
        submit_to_present_p50_ms: to_present.p50_ms,
        submit_to_present_p99_ms: to_present.p99_ms,
        submit_to_present_max_ms: to_present.max_ms,
        stale_frames: stats.stale_frames,
        patient_pose_held_frames: stats.pose_held_frames,
        patient_pose_stale_frames: stats.pose_stale_frames,
        signal_following_frames: stats.signal_following_frames,
        signal_lost_frames: stats.signal_lost_frames,
        signal_clipped_frames: stats.signal_clipped_frames,
        past_fold_free_frames: stats.past_fold_free_frames,
        governor: scene.render.governor.name().to_string(),
        lowered_frames: stats
            .quality_frames
            .iter()
            .filter(|(q, _)| *q != 0)
            .map(|(_, n)| n)
            .sum(),
        governor_floor_frames: stats.governor_floor_frames,
        quality_changes: stats.quality_changes,
        final_quality: ipc_types::report_flags::describe_quality(stats.last_quality),
        governor_start: scene.render.governor_start.name().to_string(),
        first_quality: ipc_types::report_flags::describe_quality(stats.first_quality),
        quality_frames: quality_frames(&stats.quality_frames),
        skipped_ticks: stats.skipped_ticks,
        lost_reports: stats.lost_reports,
        bad_stamps: stats.bad_stamps,
        untracked_frames: stats.untracked_frames,
        implausible_samples: stats.implausible_samples,
        volume_min_ml,
        volume_max_ml,
        leftover_files: e.leftovers,
        remaining_files: e.remaining,
        kernels: e.kernels,
        instance: e.instance,
        mode: scene.lungs.mode.name().to_string(),
        look: scene.render.look.name().to_string(),
        color: scene.render.color.name().to_string(),
        msaa: scene.render.msaa,
        lod: scene.render.lod.to_string(),
        calibration: scene
            .render
            .calibration
            .as_ref()
            .map(|p| p.display().to_string()),
        hmd: scene.render.hmd.as_ref().map(|p| p.display().to_string()),
        restarts: e.restart_log.len(),
        hung_restarts: e.restart_log.iter().filter(|r| r.hung).count(),
        restart_log: e.restart_log,
        launcher_stalls: e.stalls.count,
        launcher_max_gap_ms: e.stalls.max_gap_ms,
        phase_errors: e.w.phase.errors,
        ended: match (&e.w.failure, e.w.interrupted, e.w.finished) {
            (Some(f), _, _) => f.clone(),
            (None, true, _) => "interrupted".to_string(),
            (None, false, Some(role)) => format!(
                "the {role} finished before --seconds (its source ended: the end of the replay)"
            ),
            (None, false, None) => "completed".to_string(),
        },
        failure: e.w.failure,
        swept_files: e.swept,
        slicer: e.slicer,
    }
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
/// The table's lines on restarts and the launcher's own stalls (none when there were none).
fn restart_lines(s: &mut String, r: &DemoReport) {
    use std::fmt::Write;
    if r.restarts > 0 {
        let _ = writeln!(
            *s,
            "RESTARTS {}: {}; breathing-phase errors after engine restarts: {}",
            r.restarts,
            r.restart_log
                .iter()
                .map(|x| format!(
                    "{} at {:.1} s ({}), {}",
                    x.role,
                    x.at_s,
                    x.ended,
                    x.recover_ms
                        .map_or("never recovered".to_string(), |m| format!(
                            "fresh frames again after {m:.0} ms"
                        ))
                ))
                .collect::<Vec<_>>()
                .join("; "),
            r.phase_errors
        );
    }
    if r.launcher_stalls > 0 {
        let _ = writeln!(
            *s,
            "LAUNCHER STALLED {} times (longest {:.0} ms between two looks at its processes: it was \
             stopped or starved of CPU); their silence meanwhile was not counted as a hang",
            r.launcher_stalls, r.launcher_max_gap_ms
        );
    }
}

/// The table's line on the quality governor, when it drew anything below the scene's quality.
fn governor_line(s: &mut String, r: &DemoReport) {
    use std::fmt::Write as _;
    if r.lowered_frames + r.governor_floor_frames > 0 {
        let _ = writeln!(
            s,
            "quality governor: {} of {} frames drawn with less ({}; {} change(s), the first frame \
             {}, the last {}){}",
            r.lowered_frames,
            r.frames_rendered,
            QualityFrames::list(&r.quality_frames),
            r.quality_changes,
            r.first_quality,
            r.final_quality,
            if r.governor_floor_frames > 0 {
                format!(
                    "; DEADLINE NOT HELD in {} frames with everything given up",
                    r.governor_floor_frames
                )
            } else {
                String::new()
            }
        );
    }
}

/// The table's lines on what the frames showed beside the lungs: a held patient pose, the
/// patient's signal, a lung past its fold-free volume.
fn state_lines(s: &mut String, r: &DemoReport) {
    use std::fmt::Write as _;
    if r.patient_pose_held_frames > 0 {
        let _ = writeln!(
            s,
            "PATIENT POSE HELD in {} of {} frames ({} of them stale: no patient sample in time, or \
             none yet) — drawn over a tinted background, amber held, red stale",
            r.patient_pose_held_frames, r.frames_rendered, r.patient_pose_stale_frames
        );
    }
    if r.signal_following_frames + r.signal_lost_frames > 0 {
        let _ = writeln!(
            s,
            "breathing: the patient's signal drove {} of {} frames; in {} it was lost, ended or not \
             yet there (the model breathed, under a blue veil); the rest calibrated it (a chest \
             tool's axis being learnt included)",
            r.signal_following_frames, r.frames_rendered, r.signal_lost_frames
        );
        if r.signal_clipped_frames > 0 {
            let _ = writeln!(
                s,
                "SIGNAL LOOKED CLIPPED in {} of the frames it drove: several breaths of unequal \
                 depth ended at one value — the patient's breaths may have been deeper than drawn \
                 (the sensor's range, or breaths held at one level on purpose)",
                r.signal_clipped_frames
            );
        }
    }
    if r.past_fold_free_frames > 0 {
        let _ = writeln!(
            s,
            "PAST THE FOLD-FREE VOLUME in {} of {} frames: a lung was drawn outside the volume range \
             its kernel was checked free of folds at bake time, and its surface may have crossed \
             itself (`lungdyn kernel inspect KERNEL` gives the range)",
            r.past_fold_free_frames, r.frames_rendered
        );
    }
}

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
    if r.presented_frames > 0 {
        let _ = writeln!(
            s,
            "presented {} frames ({} mode, frame latency {}); submit to present p50 {:.3} ms, p99 {:.3} ms",
            r.presented_frames,
            r.present_mode,
            r.frame_latency,
            r.submit_to_present_p50_ms,
            r.submit_to_present_p99_ms
        );
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
    state_lines(&mut s, r);
    governor_line(&mut s, r);
    if let Some(sl) = &r.slicer {
        let _ = writeln!(s, "{}", sl.text());
    }
    let _ = writeln!(
        s,
        "stale frames {}, engine ticks not drawn {}, reports lost {}, shm files left by iceoryx2 {} (remaining {})",
        r.stale_frames, r.skipped_ticks, r.lost_reports, r.leftover_files, r.remaining_files
    );
    if r.implausible_samples > 0 {
        let _ = writeln!(
            s,
            "IMPLAUSIBLE TRACKER SAMPLE NUMBERS in {} frames (further ahead than the clock allows: \
             a corrupted or foreign tracker frame), left out of the schedule",
            r.implausible_samples
        );
    }
    restart_lines(&mut s, r);
    let _ = writeln!(s, "run ended: {}", r.ended);
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
    if r.substituted_frames > 0 {
        let _ = writeln!(
            s,
            "{} frames of the breath show the next drawn frame (their planned tick was skipped \
             under load)",
            r.substituted_frames
        );
    }
    if let Some(strip) = &r.strip {
        let _ = writeln!(s, "breath strip (frames + motion panel: green = newly covered at end-inspiration, red = vacated): {strip}");
    }
    s
}

/// A signal option (`flag`, as given) refused when the scene breathes with the model: there is no
/// signal to `what`.
fn require_signal(scene: &lung_model::scene::Scene, flag: &str, what: &str) -> anyhow::Result<()> {
    if scene.breathing.source != lung_model::scene::BreathSource::Signal {
        anyhow::bail!(
            "{flag}: there is no breathing signal to {what}; follow one with --breathing \
             trace:FILE (or the scene's [breathing] source = \"signal\")"
        );
    }
    Ok(())
}

/// `--keys DIR [--identity NAME]`: the source's room keys into the resolved scene's [remote]
/// table (absolute: the processes run elsewhere), loaded now so a wrong folder, identity or role
/// is refused before anything starts.
fn use_keys(
    loaded: &mut lung_model::scene::Scene,
    dir: &Path,
    identity: Option<&str>,
) -> anyhow::Result<()> {
    let Some(r) = loaded
        .remote
        .as_mut()
        .filter(|r| r.role == lung_model::scene_remote::RemoteRole::Source)
    else {
        anyhow::bail!(
            "--keys {}: this scene shares no session (its [remote] role is not \"source\"); run a \
             source scene (scenes/remote_source.toml), or join one with `lungdyn remote join --keys`",
            dir.display()
        );
    };
    let abs =
        std::path::absolute(dir).map_err(|e| anyhow::anyhow!("--keys {}: {e}", dir.display()))?;
    let name = identity
        .map(str::to_string)
        .or_else(|| r.identity.clone())
        .unwrap_or_else(|| "source".into());
    let room = lungdyn_remote::keys::Room::load(&abs, &name)
        .map_err(|e| anyhow::anyhow!("--keys {}: {e}", dir.display()))?;
    if room.identity().role != lungdyn_remote::keys::Role::Source {
        anyhow::bail!(
            "--identity {name}: its certificate is a {}'s, and the demo's engine is the source \
             (use the source's identity, or make one with `lungdyn remote keys --participant \
             NAME:source`)",
            room.identity().role.name()
        );
    }
    r.keys = Some(abs.display().to_string());
    r.identity = Some(name);
    // With keys the endpoints are TLS's: the scene's plain ones are moved over, and said.
    let to_tls = |v: &mut Vec<String>| {
        for e in v.iter_mut().filter(|e| e.starts_with("tcp/")) {
            let tls = e.replacen("tcp/", "tls/", 1);
            eprintln!("lungdyn: --keys: the scene's {e} becomes {tls}");
            *e = tls;
        }
    };
    if let Some(listen) = r.listen.as_mut() {
        to_tls(listen);
    }
    to_tls(&mut r.connect);
    Ok(())
}

/// `--breathing recorded` needs `--tracker replay:FILE` whose recording carries a signal, and a
/// recording that carries one refuses another signal beside it: the bridge's rule
/// ([`tracker_bridge::check_recorded_signal`]), said here before any process starts.
fn recorded_signal_check(tracker: &str, signal: &str) -> anyhow::Result<()> {
    let spec =
        tracker_bridge::signal::SignalSpec::parse(signal).map_err(|e| anyhow::anyhow!("{e}"))?;
    let source = tracker_bridge::source::SourceSpec::parse(tracker)?;
    tracker_bridge::check_recorded_signal(&spec, &source, "--tracker", "model")?;
    Ok(())
}

/// `--breathing`: `model` (`None`), or a signal source with its file made absolute and checked
/// (the processes run elsewhere than this shell's folder).
fn breathing_override(text: &str) -> anyhow::Result<Option<String>> {
    use tracker_bridge::signal::SignalSpec;
    if text.trim().eq_ignore_ascii_case("model") {
        return Ok(None);
    }
    match SignalSpec::parse(text).map_err(|e| anyhow::anyhow!("{e}; or model"))? {
        SignalSpec::None => Ok(None),
        // The bridge checks the replayed recording carries one (before anything starts below).
        SignalSpec::Recorded => Ok(Some("recorded".into())),
        // Bound by the bridge (a taken port fails it at start-up, named).
        SignalSpec::Udp(addr) => Ok(Some(format!("udp:{addr}"))),
        // Tracked by the bridge beside the patient reference (its name checked there).
        SignalSpec::Tool(name, axis) => Ok(Some(format!("tool:{name}{}", axis.suffix()))),
        // Read by the bridge from its OpenIGTLink link (the source checked with the tracker's).
        SignalSpec::Igtl(name) => Ok(Some(format!("igtl:{name}"))),
        SignalSpec::Trace(path) => {
            let abs = std::path::absolute(&path)
                .map_err(|e| anyhow::anyhow!("--breathing trace:{}: {e}", path.display()))?;
            if !abs.is_file() {
                anyhow::bail!(
                    "--breathing trace:{}: no such file (a Varian RPM .vxp, a CSV trace or a \
                     ventilator recording)",
                    path.display()
                );
            }
            // Read now: a file the bridge cannot follow is refused before anything starts.
            let replay = tracker_bridge::signal::TraceReplay::open(&abs)?;
            eprintln!("lungdyn: breathing signal: {}", replay.describe());
            Ok(Some(format!("trace:{}", abs.display())))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `lungdyn demo ARGS…`'s arguments.
    fn args(a: &[&str]) -> DemoArgs {
        DemoArgs::from_args(std::iter::once("demo").chain(a.iter().copied())).unwrap()
    }

    #[test]
    fn a_hang_time_out_of_range_is_refused_before_any_work() {
        for bad in ["0.01", "-1", "1e9", "NaN"] {
            // (An --out nothing could write to: the refusal comes before it is tried.)
            let flag = format!("--hang-after-s={bad}");
            let e = run(&args(&[&flag, "--out", "/proc/lungdyn-no"])).unwrap_err();
            let msg = format!("{e:#}");
            assert!(
                msg.contains("--hang-after-s") && msg.contains("or 0"),
                "{bad}: {msg}"
            );
        }
    }

    #[test]
    fn counts_and_cores_are_checked_before_any_work() {
        assert!(check_counts(&args(&[])).is_ok());
        // 3 s at 60 Hz, 12/min (300-tick cycles): spread from the first second, increasing.
        assert_eq!(partial_breath_ticks(3, 180, 60, 300), vec![60, 100, 140]);
        // 11 s holds the wait for a cycle start and a whole breath: the renderer plans it.
        assert!(partial_breath_ticks(3, 660, 60, 300).is_empty());
        assert!(partial_breath_ticks(0, 180, 60, 300).is_empty());
        // Shorter than the warm-up: still inside the run.
        assert!(partial_breath_ticks(4, 30, 60, 300).iter().all(|&t| t < 30));
        assert!(check_counts(&args(&["--snapshots", "240"])).is_ok());
        let e = check_counts(&args(&["--snapshots", "1000000000"])).unwrap_err();
        assert!(e.to_string().contains("--snapshots 1000000000"), "{e}");
        let e = check_counts(&args(&["--cpus", "4096", "0", "0"])).unwrap_err();
        assert!(e.to_string().contains("core 4096"), "{e}");
        let first = allowed_cpus().unwrap()[0].to_string();
        assert!(check_counts(&args(&["--cpus", &first, &first, &first])).is_ok());
        // The comma form its --help shows gives the same three cores as the spaced one.
        let comma = args(&["--cpus", &format!("{first},{first},{first}")]);
        assert_eq!(comma.cpus, args(&["--cpus", &first, &first, &first]).cpus);
        assert!(check_counts(&comma).is_ok());
        let e = check_counts(&args(&["--cpus", "4096,0,0"])).unwrap_err();
        assert!(e.to_string().contains("core 4096"), "{e}");
        for short_or_long in [&["0,1"][..], &["0,1,1,1"], &["0", "1,1,1"], &["0"]] {
            let mut a = vec!["--cpus"];
            a.extend_from_slice(short_or_long);
            let e = check_counts(&args(&a)).unwrap_err();
            assert!(e.to_string().contains("needs three cores"), "{a:?}: {e}");
        }
    }

    #[test]
    fn keys_go_into_a_source_scene_with_tls_endpoints_and_a_wrong_role_is_refused() {
        let dir = std::env::temp_dir().join(format!("lungdyn-demo-keys-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        lungdyn_remote::keys::make(
            "ward",
            &dir,
            &lungdyn_remote::keys::default_participants(),
            10,
        )
        .unwrap();
        let scene = |role: &str| -> lung_model::scene::Scene {
            toml::from_str(&format!(
                "[remote]\nrole = \"{role}\"\nroom = \"ward\"\nlisten = [\"tcp/127.0.0.1:7447\"]\n\
                 connect = [\"tcp/127.0.0.1:7448\"]\n"
            ))
            .unwrap()
        };
        let mut s = scene("source");
        use_keys(&mut s, &dir, None).unwrap();
        let r = s.remote.as_ref().unwrap();
        assert_eq!(r.keys.as_deref(), Some(dir.display().to_string().as_str()));
        assert_eq!(r.identity.as_deref(), Some("source"));
        assert_eq!(r.listen, Some(vec!["tls/127.0.0.1:7447".to_string()]));
        assert_eq!(r.connect, vec!["tls/127.0.0.1:7448".to_string()]);
        let e = use_keys(&mut scene("source"), &dir, Some("site")).unwrap_err();
        assert!(format!("{e:#}").contains("a site's"), "{e:#}");
        let e = use_keys(&mut scene("site"), &dir, None).unwrap_err();
        assert!(format!("{e:#}").contains("shares no session"), "{e:#}");
        let e = use_keys(&mut scene("source"), &dir.join("nothing"), None).unwrap_err();
        assert!(format!("{e:#}").contains("lungdyn remote keys"), "{e:#}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_unwritable_out_folder_is_a_clear_error() {
        let e =
            crate::outputs::check_writable(Path::new("/proc/lungdyn-cannot-exist")).unwrap_err();
        assert!(
            format!("{e:#}").contains("--out /proc/lungdyn-cannot-exist"),
            "{e:#}"
        );
    }
}
