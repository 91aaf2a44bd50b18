//! `lungdyn latency`: the latency harness. Runs the three processes (the demo's launcher, through
//! [`crate::demo::Watch`]) and measures every frame from the tracker's capture to the moment its
//! GPU work was done (and, in a window, handed to the presentation engine).
//!
//! A frame's time points, named like an XR compositor's frame pacing:
//!
//! | point      | stamp                                                                   |
//! |------------|-------------------------------------------------------------------------|
//! | capture    | the tracker sample was captured (synthetic: generated)                  |
//! | wake/begin | the renderer woke with the engine frame and began the frame             |
//! | submit     | `Queue::submit` returned                                                |
//! | GPU done   | the wait on the submission's fence returned (CLOCK_MONOTONIC)           |
//! | present    | `Queue::present` returned (`--window` only)                             |
//!
//! Histograms are HdrHistogram with coordinated-omission correction at the 60 Hz frame interval
//! (`record_correct`): a frame that took 50 ms also stands for the two frames that could not start
//! meanwhile. The deadline monitor counts every frame whose capture → GPU done (→ present in a
//! window) exceeded 16.7 ms, and every display slot without a frame, and names the stage that
//! overran its share of the frame the most. Recording a frame never allocates: histograms are
//! bounded and the time series is preallocated.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context};
use hdrhistogram::Histogram;
use ipc_types::FrameReport;
use serde::Serialize;

use crate::demo::Watch;
use crate::stats::{LatencyStats, DEADLINE_NS};

/// Options of `lungdyn latency`.
#[derive(Debug, Clone, clap::Args)]
pub struct LatencyArgs {
    /// Seconds to measure once frames flow (after --warmup).
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Seconds of frames not measured at the start (shader compilation, first-touch page faults,
    /// caches filling).
    #[arg(long, value_name = "S", default_value_t = 1.0)]
    pub warmup: f64,
    /// Scene file (TOML); the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Vertices per generated lung (the scene's `[lungs] vertices` otherwise).
    #[arg(long, value_name = "N")]
    pub mesh: Option<usize>,
    /// Deformation mode (overrides the scene's [lungs] mode): precomputed, basis, sh, direct.
    #[arg(long, value_name = "MODE")]
    pub mode: Option<lung_model::deform::modes::DeformMode>,
    /// Background load while measuring: `cpu:N` busy threads and/or `mem:MiB` of memory touched
    /// over and over, e.g. `--load cpu:2,mem:512`.
    #[arg(long, value_name = "cpu:N,mem:MiB")]
    pub load: Option<String>,
    /// Draw into a window (needs a display) and measure capture → present too.
    #[arg(long)]
    pub window: bool,
    /// Find the largest mesh that holds 60 Hz with zero deadline misses: bisect over the vertex
    /// count with short runs (--sweep-seconds each) between --sweep-min and --sweep-max.
    #[arg(long)]
    pub sweep: bool,
    /// Seconds per sweep run.
    #[arg(long, value_name = "S", default_value_t = 4.0)]
    pub sweep_seconds: f64,
    /// Smallest vertex count the sweep tries.
    #[arg(long, value_name = "N", default_value_t = 2_000)]
    pub sweep_min: usize,
    /// Largest vertex count the sweep tries.
    #[arg(long, value_name = "N", default_value_t = 160_000)]
    pub sweep_max: usize,
    /// Folder for latency.json, latency.md, latency.png/.svg and the baked kernels.
    #[arg(long, default_value = "out/latency")]
    pub out: PathBuf,
    /// Print the JSON result on stdout (the summary goes to stderr).
    #[arg(long)]
    pub json: bool,
    /// Run the three processes SCHED_FIFO with locked memory where permitted (the demo's
    /// --realtime).
    #[arg(long)]
    pub realtime: bool,
    /// Write the Chrome/Perfetto trace (JSON) of every process's stage spans to FILE instead of
    /// <out>/latency.trace.json, where it goes by default (with --sweep: of the final run; open it
    /// in ui.perfetto.dev).
    #[arg(long, value_name = "FILE")]
    pub trace: Option<PathBuf>,
    /// The quality governor (overrides the scene's `[render] governor`): "hold-deadline" draws
    /// less when frames run late, "off" always the scene's quality — measure both back to back to
    /// see what it buys (the report says the quality it settled at). docs/LATENCY.md.
    #[arg(long, value_name = "GOVERNOR")]
    pub governor: Option<lung_model::scene::Governor>,
    /// The governor's accuracy opt-in (overrides the scene's `[render] governor_least_bands`): once
    /// every drawing step is given up, it may also cap the "sh" mode's bands down to N (1..8).
    #[arg(long, value_name = "N")]
    pub governor_least_bands: Option<u32>,
    /// Where the governor starts (overrides the scene's `[render] governor_start`): "remembered"
    /// (the default), where the last run of the same setting on this GPU settled, or "full" — a
    /// heavy scene's first run measures its descent, later ones start where it settled.
    #[arg(long, value_name = "START")]
    pub governor_start: Option<lung_model::scene::GovernorStart>,
    /// Serve the lungs to 3D Slicer while measuring (the demo's --igtl-serve [PORT]; frames are
    /// made only while a client is connected): measure with and without it back to back to see
    /// what the link costs the frame (docs/SLICER.md).
    #[arg(long, value_name = "PORT", num_args = 0..=1)]
    pub igtl_serve: Option<Option<u16>>,
    /// Breathe to a respiratory signal while measuring (the demo's --breathing SOURCE, e.g.
    /// trace:FILE replayed live): the report adds "signal arrival -> GPU done", from the newest
    /// signal sample the engine had for a frame to that frame's GPU completion (docs/BREATHING.md).
    #[arg(long, value_name = "SOURCE")]
    pub breathing: Option<String>,
}

/// `--load`: background work while measuring.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Load {
    /// Busy threads.
    pub cpu_threads: usize,
    /// Memory touched over and over, MiB.
    pub mem_mib: usize,
}

/// Most `cpu:` threads (a spinner per thread; more only measures the scheduler).
pub const MAX_LOAD_THREADS: usize = 256;

impl Load {
    /// Parse `cpu:N,mem:MiB` (either part may be left out, each at most once).
    pub fn parse(s: &str) -> anyhow::Result<Self> {
        let mut load = Load::default();
        let (mut cpu, mut mem) = (false, false);
        for part in s.split(',').map(str::trim) {
            let (key, value) = part.split_once(':').with_context(|| {
                format!(
                    "--load {s:?}: expected cpu:N and/or mem:MiB, e.g. cpu:2,mem:512; got {part:?}"
                )
            })?;
            let n: usize = value.trim().parse().map_err(|_| {
                anyhow::anyhow!("--load {s:?}: {key}:{value:?} is not a whole number")
            })?;
            match key.trim() {
                "cpu" if !cpu => {
                    if n == 0 || n > MAX_LOAD_THREADS {
                        bail!("--load {s:?}: cpu:{n} must be 1..{MAX_LOAD_THREADS} threads");
                    }
                    (cpu, load.cpu_threads) = (true, n);
                }
                "mem" if !mem => {
                    let avail = available_mib();
                    if n == 0 || avail.is_some_and(|a| n > a / 2) {
                        bail!(
                            "--load {s:?}: mem:{n} must be at least 1 MiB and at most half the memory \
                             available ({} MiB)",
                            avail.map_or("unknown".to_string(), |a| (a / 2).to_string())
                        );
                    }
                    (mem, load.mem_mib) = (true, n);
                }
                "cpu" | "mem" => bail!("--load {s:?}: {key} is given twice"),
                other => bail!("--load {s:?}: unknown load {other:?} (cpu:N, mem:MiB)"),
            }
        }
        Ok(load)
    }

    fn is_empty(&self) -> bool {
        self.cpu_threads == 0 && self.mem_mib == 0
    }
}

/// MemAvailable from /proc/meminfo, MiB.
fn available_mib() -> Option<usize> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: usize = line.split_ascii_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024)
}

/// Background load threads; stopped (and joined) on drop.
struct LoadThreads {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl LoadThreads {
    fn start(load: Load) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let mut threads = Vec::new();
        for _ in 0..load.cpu_threads {
            let stop = stop.clone();
            threads.push(std::thread::spawn(move || {
                let mut x = 0x9e37_79b9_7f4a_7c15u64;
                while !stop.load(Ordering::Relaxed) {
                    for _ in 0..10_000 {
                        x = std::hint::black_box(x.rotate_left(5) ^ x.wrapping_mul(3));
                    }
                }
            }));
        }
        if load.mem_mib > 0 {
            let stop = stop.clone();
            let bytes = load.mem_mib << 20;
            threads.push(std::thread::spawn(move || {
                let mut buf = vec![0u8; bytes];
                let mut pass = 0u8;
                while !stop.load(Ordering::Relaxed) {
                    pass = pass.wrapping_add(1);
                    // One write per page: every page stays resident and is dirtied each pass.
                    for i in (0..buf.len()).step_by(4096) {
                        buf[i] = pass;
                        if i % (64 << 20) == 0 && stop.load(Ordering::Relaxed) {
                            break;
                        }
                    }
                    std::hint::black_box(&buf);
                }
            }));
        }
        LoadThreads { stop, threads }
    }
}

impl Drop for LoadThreads {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// The frame's time points in path order: the six hop stamps, GPU done, present.
const POINTS: usize = 8;
const GPU_DONE: usize = 6;
const PRESENT: usize = 7;

/// Rows measured: (label, from point, to point).
const ROWS: [(&str, usize, usize); 11] = [
    ("tracker capture -> bridge publish", 0, 1),
    ("bridge publish -> engine receive", 1, 2),
    ("engine receive -> engine publish", 2, 3),
    ("engine publish -> renderer wake", 3, 4),
    ("renderer wake -> submit", 4, 5),
    ("submit -> GPU done", 5, GPU_DONE),
    ("GPU done -> present", GPU_DONE, PRESENT),
    ("capture -> submit", 0, 5),
    ("capture -> GPU done", 0, GPU_DONE),
    ("capture -> present", 0, PRESENT),
    ("renderer wake -> GPU done", 4, GPU_DONE),
];
/// The row a breathing signal adds (after [`ROWS`]).
const SIGNAL_ROW: &str = "signal arrival -> GPU done";
const ROW_SUBMIT: usize = 7;
const ROW_GPU_DONE: usize = 8;
const ROW_PRESENT: usize = 9;

/// The deadline monitor's stages: (name, the first [`ROWS`] entries they are).
const STAGES: [&str; 7] = [
    "tracker-bridge",
    "IPC bridge -> engine",
    "engine",
    "IPC engine -> renderer",
    "renderer CPU",
    "GPU",
    "present",
];
/// Share of the frame an IPC hop may take (wake included), ms.
pub const IPC_BUDGET_MS: f64 = 0.5;
/// Share of the frame handing it to the presentation engine may take (`--window`), ms.
pub const PRESENT_BUDGET_MS: f64 = 1.0;
/// The stage named for a display slot that passed without any frame.
const NO_FRAME: &str = "no frame in a display slot";

/// Each stage's share of the 16.7 ms frame, ns: the scene's process budgets, the IPC and present
/// shares, and what is left for the GPU.
fn stage_budgets(b: &lung_model::scene::ProcessBudgets, window: bool) -> [u64; 7] {
    let present = if window { PRESENT_BUDGET_MS } else { 0.0 };
    let cpu = b.tracker_bridge + b.engine + b.renderer + 2.0 * IPC_BUDGET_MS + present;
    let gpu = (lung_model::scene::FRAME_DEADLINE_MS - cpu).max(0.0);
    [
        b.tracker_bridge,
        IPC_BUDGET_MS,
        b.engine,
        IPC_BUDGET_MS,
        b.renderer,
        gpu,
        present,
    ]
    .map(|ms| (ms * 1e6) as u64)
}

/// The stage that overran its share the most in a frame's stage times (ns); `present` only counts
/// when measured.
fn overran_stage(times: &[u64; 7], budgets: &[u64; 7]) -> usize {
    (0..7)
        .max_by_key(|&i| times[i] as i128 - budgets[i] as i128)
        .unwrap_or(5)
}

/// Per-process period jitter: the interval between consecutive outputs against the nominal period.
struct Period {
    nominal_ns: u64,
    jitter: Histogram<u64>,
    last: Option<(u64, u64)>,
}

impl Period {
    fn new(nominal_ns: u64) -> Self {
        Period {
            nominal_ns,
            jitter: histogram(),
            last: None,
        }
    }

    /// Output `seq` at `at_ns`: only consecutive outputs give an interval.
    fn record(&mut self, seq: u64, at_ns: u64) {
        if at_ns == 0 {
            return;
        }
        if let Some((s, t)) = self.last {
            if seq == s + 1 && at_ns >= t {
                let _ = self
                    .jitter
                    .record((at_ns - t).abs_diff(self.nominal_ns).max(1));
            }
            if seq <= s {
                return;
            }
        }
        self.last = Some((seq, at_ns));
    }
}

fn histogram() -> Histogram<u64> {
    // 1 ns .. 60 s at 3 significant digits: recording never allocates.
    Histogram::new_with_bounds(1, 60_000_000_000, 3).expect("static bounds are valid")
}

/// One point of the time series (ms since the first frame; latencies in ms, NaN when absent).
#[derive(Debug, Clone, Copy)]
struct SeriesPoint {
    t_s: f32,
    submit_ms: f32,
    gpu_done_ms: f32,
    present_ms: f32,
}

/// The launcher-side recorder of one run.
pub struct Recorder {
    rows: Vec<Histogram<u64>>,
    schedule: LatencyStats,
    budgets: [u64; 7],
    window: bool,
    late_frames: u64,
    stage_misses: [u64; 7],
    no_gpu_done: u64,
    periods: [Period; 3],
    series: Vec<SeriesPoint>,
    series_dropped: u64,
    first_capture_ns: Option<u64>,
    load: Load,
    load_threads: Option<LoadThreads>,
    started_ns: Option<u64>,
    warmup_ns: u64,
    warmup_frames: u64,
    frames: u64,
    launcher_cpu_start_s: f64,
    cpu: Vec<ProcessCpu>,
    stages: Vec<transport::trace::StageSummary>,
    signal: SignalArrivals,
}

/// Where the breathing signal's newest sample had arrived by each tracker frame, for the row
/// "signal arrival -> GPU done": a fixed ring indexed by tracker frame number (the launcher sees
/// most tracker frames; a frame it missed is not measured, and counted).
struct SignalArrivals {
    /// (tracker frame number, the newest sample's arrival by then, ns).
    ring: Vec<(u64, u64)>,
    newest_ns: u64,
    hist: Histogram<u64>,
    unmatched: u64,
}

const SIGNAL_RING: usize = 512;

impl SignalArrivals {
    fn new() -> Self {
        Self {
            ring: vec![(u64::MAX, 0); SIGNAL_RING],
            newest_ns: 0,
            hist: histogram(),
            unmatched: 0,
        }
    }

    fn tracker_frame(&mut self, f: &ipc_types::TrackerFrame) {
        for i in 0..f.signal.count as usize {
            if let Some((s, true)) = f.signal.sample(i) {
                self.newest_ns = self.newest_ns.max(s.t_ns);
            }
        }
        if self.newest_ns > 0 {
            self.ring[(f.frame_number % SIGNAL_RING as u64) as usize] =
                (f.frame_number, self.newest_ns);
        }
    }

    /// A drawn frame made from `tracker_frame`, its GPU work done at `gpu_done_ns`.
    fn drawn(&mut self, tracker_frame: u64, gpu_done_ns: u64) {
        if self.newest_ns == 0 {
            return;
        }
        match self.ring[(tracker_frame % SIGNAL_RING as u64) as usize] {
            (n, t) if n == tracker_frame && gpu_done_ns >= t => {
                let _ = self
                    .hist
                    .record_correct((gpu_done_ns - t).max(1), DEADLINE_NS);
            }
            _ => self.unmatched += 1,
        }
    }
}

/// One child's CPU use over the run.
#[derive(Debug, Clone, Serialize)]
pub struct ProcessCpu {
    /// Role.
    pub process: String,
    /// User + system CPU seconds from start to the end of the measurement (bake-free: the children
    /// load kernels, never bake).
    pub cpu_s: f64,
}

impl Recorder {
    /// A recorder for `seconds` of frames at `tick_hz` after `warmup` seconds, against `budgets`.
    pub fn new(
        warmup: f64,
        seconds: f64,
        tick_hz: f64,
        bridge_hz: f64,
        budgets: &lung_model::scene::ProcessBudgets,
        window: bool,
        load: Load,
    ) -> Self {
        let frames = (seconds * tick_hz.max(60.0) * 1.5) as usize + 600;
        let tick_ns = (1e9 / tick_hz) as u64;
        Recorder {
            rows: ROWS.iter().map(|_| histogram()).collect(),
            schedule: LatencyStats::new(),
            budgets: stage_budgets(budgets, window),
            window,
            late_frames: 0,
            stage_misses: [0; 7],
            no_gpu_done: 0,
            periods: [
                Period::new((1e9 / bridge_hz) as u64),
                Period::new(tick_ns),
                Period::new(tick_ns),
            ],
            series: Vec::with_capacity(frames),
            series_dropped: 0,
            first_capture_ns: None,
            load,
            load_threads: None,
            started_ns: None,
            warmup_ns: (warmup * 1e9) as u64,
            warmup_frames: 0,
            frames: 0,
            launcher_cpu_start_s: 0.0,
            cpu: Vec::new(),
            stages: Vec::new(),
            signal: SignalArrivals::new(),
        }
    }
}

impl Watch for Recorder {
    fn report(&mut self, r: &FrameReport) {
        if self.started_ns.is_none() {
            // Frames flow: the warm-up (and the background load) starts now.
            self.started_ns = Some(transport::now_ns());
            self.launcher_cpu_start_s = crate::launch::thread_cpu_s();
            if !self.load.is_empty() {
                self.load_threads = Some(LoadThreads::start(self.load));
            }
        }
        if self.warmup_ns > 0 {
            let since = self
                .started_ns
                .map_or(0, |t| transport::now_ns().saturating_sub(t));
            if since < self.warmup_ns {
                self.warmup_frames += 1;
                return;
            }
        }
        self.frames += 1;
        self.schedule.record(r);
        let s = &r.stamps;
        if !s.is_complete_and_ordered() {
            return;
        }
        let h = s.as_array();
        let p: [u64; POINTS] = [
            h[0],
            h[1],
            h[2],
            h[3],
            h[4],
            h[5],
            r.gpu_done_ns,
            r.present_ns,
        ];
        self.periods[0].record(r.tracker_frame, s.bridge_publish_ns);
        self.periods[1].record(r.engine_tick, s.engine_publish_ns);
        self.periods[2].record(r.frame, s.renderer_submit_ns);
        let interval = DEADLINE_NS;
        for (hist, &(_, a, b)) in self.rows.iter_mut().zip(ROWS.iter()) {
            if p[a] != 0 && p[b] >= p[a] {
                let _ = hist.record_correct((p[b] - p[a]).max(1), interval);
            }
        }
        let gpu_ok = p[GPU_DONE] >= p[5];
        if !gpu_ok {
            self.no_gpu_done += 1;
        } else {
            self.signal.drawn(r.tracker_frame, p[GPU_DONE]);
        }
        // The frame is done when its GPU work is (in a window: when it is presented).
        let end = if self.window && p[PRESENT] >= p[GPU_DONE] && gpu_ok {
            p[PRESENT]
        } else if gpu_ok {
            p[GPU_DONE]
        } else {
            p[5]
        };
        if end - p[0] > DEADLINE_NS {
            self.late_frames += 1;
            let d = |a: usize, b: usize| p[b].saturating_sub(p[a]);
            let times = [
                d(0, 1),
                d(1, 2),
                d(2, 3),
                d(3, 4),
                d(4, 5),
                if gpu_ok { d(5, GPU_DONE) } else { 0 },
                if self.window && p[PRESENT] != 0 {
                    d(GPU_DONE, PRESENT)
                } else {
                    0
                },
            ];
            self.stage_misses[overran_stage(&times, &self.budgets)] += 1;
        }
        let t0 = *self.first_capture_ns.get_or_insert(p[0]);
        if self.series.len() < self.series.capacity() {
            let ms = |a: usize, b: usize| {
                if p[a] != 0 && p[b] >= p[a] {
                    (p[b] - p[a]) as f32 / 1e6
                } else {
                    f32::NAN
                }
            };
            self.series.push(SeriesPoint {
                t_s: p[0].saturating_sub(t0) as f32 / 1e9,
                submit_ms: ms(0, 5),
                gpu_done_ms: ms(0, GPU_DONE),
                present_ms: ms(0, PRESENT),
            });
        } else {
            self.series_dropped += 1;
        }
    }

    fn stages(&mut self, stages: &[transport::trace::StageSummary]) {
        self.stages = stages.to_vec();
    }

    fn tracker_frame(&mut self, f: &ipc_types::TrackerFrame) {
        self.signal.tracker_frame(f);
    }

    fn before_stop(&mut self, children: &[(&'static str, u32)]) {
        self.load_threads = None;
        self.cpu = children
            .iter()
            .filter_map(|&(role, pid)| {
                crate::launch::process_cpu_s(pid).map(|cpu_s| ProcessCpu {
                    process: role.to_string(),
                    cpu_s,
                })
            })
            .collect();
        let launcher = crate::launch::thread_cpu_s() - self.launcher_cpu_start_s;
        self.cpu.push(ProcessCpu {
            process: "launcher (measuring thread, while frames flowed)".to_string(),
            cpu_s: launcher.max(0.0),
        });
    }
}

/// One latency row.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// What is measured.
    pub hop: String,
    /// Samples (coordinated-omission corrected: includes the synthetic samples).
    pub count: u64,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// 99.9th percentile, ms.
    pub p99_9_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

impl Row {
    fn of(name: &str, h: &Histogram<u64>) -> Self {
        let ms = |q: f64| {
            if h.is_empty() {
                0.0
            } else {
                h.value_at_quantile(q) as f64 / 1e6
            }
        };
        Row {
            hop: name.to_string(),
            count: h.len(),
            p50_ms: ms(0.5),
            p99_ms: ms(0.99),
            p99_9_ms: ms(0.999),
            max_ms: if h.is_empty() {
                0.0
            } else {
                h.max() as f64 / 1e6
            },
        }
    }
}

/// One process's pacing and CPU use.
#[derive(Debug, Clone, Serialize)]
pub struct ProcessRow {
    /// Process.
    pub process: String,
    /// What its period is measured on.
    pub measured_on: String,
    /// Nominal period, ms.
    pub period_ms: f64,
    /// |interval − period| between consecutive outputs: median, ms.
    pub jitter_p50_ms: f64,
    /// 99th percentile, ms.
    pub jitter_p99_ms: f64,
    /// Maximum, ms.
    pub jitter_max_ms: f64,
    /// Consecutive pairs measured.
    pub intervals: u64,
    /// CPU seconds used (user + system), from start to the end of the measurement.
    pub cpu_s: Option<f64>,
}

/// Deadline misses charged to one stage.
#[derive(Debug, Clone, Serialize)]
pub struct StageMisses {
    /// Stage.
    pub stage: String,
    /// Its share of the frame, ms.
    pub budget_ms: f64,
    /// Misses in which it overran its share the most.
    pub misses: u64,
}

/// The result of one measured run.
#[derive(Debug, Clone, Serialize)]
pub struct LatencyReport {
    /// What the link to 3D Slicer did (`--igtl-serve`; null when off).
    pub slicer: Option<crate::slicer::SlicerReport>,
    /// Frames drawn and reported after the warm-up.
    pub frames: u64,
    /// Frames of the warm-up (not measured).
    pub warmup_frames: u64,
    /// Seconds measured (after the warm-up).
    pub seconds: f64,
    /// Capture → submit, 99th percentile (coordinated-omission corrected), ms.
    pub capture_to_submit_p99_ms: f64,
    /// Capture → GPU done, 99th percentile (coordinated-omission corrected), ms.
    pub capture_to_gpu_done_p99_ms: f64,
    /// Capture → present, 99th percentile, ms (`--window` only).
    pub capture_to_present_p99_ms: Option<f64>,
    /// Late frames (capture → GPU done, or → present in a window, over 16.7 ms) plus display
    /// slots that passed without a frame.
    pub deadline_misses: u64,
    /// Of those, drawn frames over the deadline.
    pub late_frames: u64,
    /// Of those, display slots without a frame.
    pub missed_frame_slots: u64,
    /// Misses by the stage that overran its share the most.
    pub deadline_miss_stages: Vec<StageMisses>,
    /// Tracker samples shown more than 16.7 ms after capture on the 60 Hz schedule, drawn or not
    /// (the demo's view; to submit).
    pub schedule_misses: u64,
    /// Frames whose GPU completion was not observed.
    pub frames_without_gpu_done: u64,
    /// Frames with incomplete or unordered stamps (not measured).
    pub bad_stamps: u64,
    /// Per hop and end to end.
    pub rows: Vec<Row>,
    /// Per process: period jitter and CPU time.
    pub processes: Vec<ProcessRow>,
    /// Per process and stage: the stage timers (the processes' spans).
    pub stages: Vec<transport::trace::StageSummary>,
    /// The launcher's measuring thread's CPU time, s.
    pub launcher_cpu_s: f64,
    /// Vertices per generated lung.
    pub mesh_vertices: usize,
    /// Deformation mode.
    pub mode: String,
    /// Background load.
    pub load: Load,
    /// Measured in a window (capture → present).
    pub window: bool,
    /// The processes were asked to run SCHED_FIFO with locked memory (`--realtime` or the scene);
    /// their stderr says whether they could.
    pub realtime: bool,
    /// Frames beyond the preallocated time series (not plotted; still in the histograms).
    pub series_dropped: u64,
    /// The quality governor: "hold-deadline" or "off".
    pub governor: String,
    /// The quality of the last frame: "full", or what the governor gave up ("LOD +2").
    pub final_quality: String,
    /// Where the governor started (`[render] governor_start`): "remembered" or "full".
    pub governor_start: String,
    /// The quality of the first frame (not "full" where it started where an earlier run settled).
    pub first_quality: String,
    /// Frames drawn at each quality over the whole run (warm-up included), most first.
    pub quality_frames: Vec<crate::demo::QualityFrames>,
    /// Times the quality changed, over the whole run.
    pub quality_changes: u64,
    /// Frames with every governor step given up and still over its target, over the whole run.
    pub governor_floor_frames: u64,
    /// With a breathing signal (`--breathing`): the newest signal sample's arrival → the GPU done
    /// of the frame made with it, 99th percentile (coordinated-omission corrected), ms; null
    /// without a signal.
    pub signal_arrival_to_gpu_done_p99_ms: Option<f64>,
    /// The same, median, ms.
    pub signal_arrival_to_gpu_done_p50_ms: Option<f64>,
    /// Drawn frames whose tracker frame the launcher did not see (not in the signal row).
    pub signal_frames_unmatched: u64,
}

/// A sweep's result.
#[derive(Debug, Clone, Serialize)]
pub struct SweepTrial {
    /// Vertices per lung.
    pub vertices: usize,
    /// Frames drawn.
    pub frames: u64,
    /// Deadline misses.
    pub deadline_misses: u64,
    /// Capture → GPU done p99, ms.
    pub capture_to_gpu_done_p99_ms: f64,
    /// Held 60 Hz with zero misses.
    pub holds: bool,
}

/// What `lungdyn latency` writes as JSON.
#[derive(Debug, Clone, Serialize)]
pub struct LatencyOutput {
    /// The measured run (at the sweep's largest mesh with `--sweep`).
    #[serde(flatten)]
    pub run: LatencyReport,
    /// `--sweep`: the largest vertex count per lung that held 60 Hz with zero misses (`None`: not
    /// even the smallest tried).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub largest_mesh_vertices: Option<Option<usize>>,
    /// `--sweep`: every run, in the order tried.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub sweep: Vec<SweepTrial>,
    /// The GPU adapter.
    pub adapter: String,
    /// Files written.
    pub json_path: String,
    /// The markdown report.
    pub report_path: String,
    /// The plot (PNG; an SVG beside it).
    pub plot_path: String,
}

fn check_args(args: &LatencyArgs) -> anyhow::Result<Load> {
    if !(args.warmup.is_finite() && (0.0..=600.0).contains(&args.warmup)) {
        bail!(
            "--warmup {} must be within 0..600 seconds",
            lung_model::plausible::compact(args.warmup)
        );
    }
    for (flag, s) in [
        ("--seconds", args.seconds),
        ("--sweep-seconds", args.sweep_seconds),
    ] {
        if !(s.is_finite() && s > 0.0 && s <= transport::process::MAX_SECONDS) {
            bail!(
                "{flag} {} must be a positive number of seconds, at most {} (one week)",
                lung_model::plausible::compact(s),
                transport::process::MAX_SECONDS
            );
        }
    }
    if let Some(m) = args.mesh {
        crate::launch::check_vertices(m).context("--mesh")?;
    }
    if args.sweep {
        crate::launch::check_vertices(args.sweep_min).context("--sweep-min")?;
        crate::launch::check_vertices(args.sweep_max).context("--sweep-max")?;
        if args.sweep_min >= args.sweep_max {
            bail!(
                "--sweep-min {} must be below --sweep-max {}",
                args.sweep_min,
                args.sweep_max
            );
        }
        if args.mesh.is_some() {
            bail!("--mesh and --sweep: the sweep chooses the mesh; give one or the other");
        }
    }
    crate::launch::check_trace(args.trace.as_deref())?;
    args.load
        .as_deref()
        .map_or(Ok(Load::default()), Load::parse)
}

/// Measure one run at `vertices` (the scene's own when `None`) for `seconds`.
fn measure(
    args: &LatencyArgs,
    vertices: Option<usize>,
    seconds: f64,
    load: Load,
    trace: Option<&Path>,
) -> anyhow::Result<(LatencyReport, Vec<SeriesPoint>)> {
    // The demo's defaults for everything the harness does not set.
    let mut demo = crate::demo::DemoArgs::defaults();
    demo.seconds = seconds + args.warmup;
    demo.out = args.out.clone();
    demo.snapshots = 0;
    demo.scene = args.scene.clone();
    demo.mode = args.mode;
    demo.output.window = args.window;
    demo.vertices = vertices;
    demo.json = true;
    demo.realtime = args.realtime;
    demo.governor = args.governor;
    demo.governor_least_bands = args.governor_least_bands;
    demo.governor_start = args.governor_start;
    demo.igtl_serve = args.igtl_serve;
    demo.breathing = args.breathing.clone();
    // The stage timers come with the spans: always on here, into --out unless --trace names a file.
    demo.trace = Some(trace.map_or_else(|| args.out.join("latency.trace.json"), Path::to_path_buf));
    let mut scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    if let Some(m) = args.mode {
        scene.lungs.mode = m;
    }
    let mesh_vertices = vertices.unwrap_or(scene.lungs.vertices);
    // The launcher leaves the bridge at its default rate.
    let bridge_hz = tracker_bridge::SourceArgs::default().rate_hz;
    let mut rec = Recorder::new(
        args.warmup,
        seconds,
        scene.engine.tick_hz,
        bridge_hz,
        &scene.processes.budget_ms,
        args.window,
        load,
    );
    let demo_report = crate::demo::run_watched(&demo, &mut rec)?;
    Ok(rec.finish(
        &demo_report,
        mesh_vertices,
        scene.lungs.mode.name(),
        args.realtime || scene.processes.realtime,
        bridge_hz,
        scene.engine.tick_hz,
    ))
}

impl Recorder {
    fn finish(
        mut self,
        demo: &crate::demo::DemoReport,
        mesh_vertices: usize,
        mode: &str,
        realtime: bool,
        bridge_hz: f64,
        tick_hz: f64,
    ) -> (LatencyReport, Vec<SeriesPoint>) {
        self.load_threads = None;
        let mut rows: Vec<Row> = ROWS
            .iter()
            .zip(&self.rows)
            .filter(|(_, h)| !h.is_empty())
            .map(|(&(name, _, _), h)| Row::of(name, h))
            .collect();
        let signal = (!self.signal.hist.is_empty()).then(|| Row::of(SIGNAL_ROW, &self.signal.hist));
        rows.extend(signal.clone());
        let p99 = |i: usize| Row::of(ROWS[i].0, &self.rows[i]).p99_ms;
        let cpu_of = |role: &str| self.cpu.iter().find(|c| c.process == role).map(|c| c.cpu_s);
        let processes = [
            (
                "tracker-bridge",
                "bridge publish of consecutive tracker frames",
                bridge_hz,
            ),
            (
                "engine",
                "engine publish of consecutive drawn ticks",
                tick_hz,
            ),
            ("renderer", "submit of consecutive frames", tick_hz),
        ]
        .iter()
        .zip(&self.periods)
        .map(|(&(process, on, hz), p)| {
            let r = Row::of(process, &p.jitter);
            ProcessRow {
                process: process.to_string(),
                measured_on: on.to_string(),
                period_ms: 1e3 / hz,
                jitter_p50_ms: r.p50_ms,
                jitter_p99_ms: r.p99_ms,
                jitter_max_ms: r.max_ms,
                intervals: r.count,
                cpu_s: cpu_of(process),
            }
        })
        .collect();
        let slots = self.schedule.missed_frame_slots;
        let mut stages: Vec<StageMisses> = STAGES
            .iter()
            .zip(self.stage_misses)
            .zip(self.budgets)
            .filter(|((_, n), _)| *n > 0)
            .map(|((s, n), b)| StageMisses {
                stage: s.to_string(),
                budget_ms: b as f64 / 1e6,
                misses: n,
            })
            .collect();
        if slots > 0 {
            stages.push(StageMisses {
                stage: NO_FRAME.to_string(),
                budget_ms: DEADLINE_NS as f64 / 1e6,
                misses: slots,
            });
        }
        let report = LatencyReport {
            slicer: demo.slicer.clone(),
            frames: self.frames,
            warmup_frames: self.warmup_frames,
            seconds: (demo.seconds - self.warmup_ns as f64 / 1e9).max(0.0),
            capture_to_submit_p99_ms: p99(ROW_SUBMIT),
            capture_to_gpu_done_p99_ms: p99(ROW_GPU_DONE),
            capture_to_present_p99_ms: (self.window && !self.rows[ROW_PRESENT].is_empty())
                .then(|| p99(ROW_PRESENT)),
            deadline_misses: self.late_frames + slots,
            late_frames: self.late_frames,
            missed_frame_slots: slots,
            deadline_miss_stages: stages,
            schedule_misses: self.schedule.sample_deadline_misses,
            frames_without_gpu_done: self.no_gpu_done,
            bad_stamps: self.schedule.bad_stamps,
            rows,
            processes,
            stages: self.stages,
            launcher_cpu_s: self
                .cpu
                .iter()
                .find(|c| c.process.starts_with("launcher"))
                .map_or(0.0, |c| c.cpu_s),
            mesh_vertices,
            mode: mode.to_string(),
            load: self.load,
            window: self.window,
            realtime,
            series_dropped: self.series_dropped,
            governor: demo.governor.clone(),
            final_quality: demo.final_quality.clone(),
            governor_start: demo.governor_start.clone(),
            first_quality: demo.first_quality.clone(),
            quality_frames: demo.quality_frames.clone(),
            quality_changes: demo.quality_changes,
            governor_floor_frames: demo.governor_floor_frames,
            signal_arrival_to_gpu_done_p99_ms: signal.as_ref().map(|r| r.p99_ms),
            signal_arrival_to_gpu_done_p50_ms: signal.as_ref().map(|r| r.p50_ms),
            signal_frames_unmatched: self.signal.unmatched,
        };
        (report, self.series)
    }
}

/// Run the harness; writes latency.json, latency.md and latency.png/.svg into `--out`.
pub fn run(args: &LatencyArgs) -> anyhow::Result<LatencyOutput> {
    let load = check_args(args)?;
    crate::outputs::check_writable(&args.out)?;
    let json_path = args.out.join("latency.json");
    let md_path = args.out.join("latency.md");
    let png_path = args.out.join("latency.png");
    for p in [&json_path, &md_path, &png_path] {
        outfile::check(p).with_context(|| format!("--out: cannot write {}", p.display()))?;
    }
    let adapter = renderer::gpu::probe_adapter()?.to_string();
    let mut sweep = Vec::new();
    let mut largest = None;
    let (run, series) = if args.sweep {
        let mut try_mesh = |v: usize| -> anyhow::Result<bool> {
            eprintln!(
                "lungdyn latency: sweep: {v} vertices per lung, {} s",
                args.sweep_seconds
            );
            let (r, _) = measure(args, Some(v), args.sweep_seconds, load, None)?;
            let holds = r.frames > 0 && r.deadline_misses == 0;
            eprintln!(
                "lungdyn latency: sweep: {v} vertices: {} frames, {} misses, capture -> GPU done p99 {:.2} ms: {}",
                r.frames,
                r.deadline_misses,
                r.capture_to_gpu_done_p99_ms,
                if holds { "holds" } else { "misses" }
            );
            sweep.push(SweepTrial {
                vertices: v,
                frames: r.frames,
                deadline_misses: r.deadline_misses,
                capture_to_gpu_done_p99_ms: r.capture_to_gpu_done_p99_ms,
                holds,
            });
            Ok(holds)
        };
        let (mut lo, mut hi) = (args.sweep_min, args.sweep_max);
        let found = if try_mesh(lo)? {
            if try_mesh(hi)? {
                Some(hi)
            } else {
                // Bisect on a log scale until the bracket is within 15 %.
                while hi as f64 / lo as f64 > 1.15 {
                    let mid = ((lo as f64 * hi as f64).sqrt() as usize).clamp(lo + 1, hi - 1);
                    if try_mesh(mid)? {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                Some(lo)
            }
        } else {
            None
        };
        largest = Some(found);
        // The full-length run at the mesh found (the smallest tried when none held).
        measure(
            args,
            Some(found.unwrap_or(args.sweep_min)),
            args.seconds,
            load,
            args.trace.as_deref(),
        )?
    } else {
        measure(args, args.mesh, args.seconds, load, args.trace.as_deref())?
    };
    let out = LatencyOutput {
        run,
        largest_mesh_vertices: largest,
        sweep,
        adapter,
        json_path: json_path.display().to_string(),
        report_path: md_path.display().to_string(),
        plot_path: png_path.display().to_string(),
    };
    write_plot(&png_path, &out.run, &series)?;
    let md = markdown(&out);
    outfile::write_atomically(&md_path, |w| w.write_all(md.as_bytes()))
        .with_context(|| format!("cannot write {}", md_path.display()))?;
    let json = serde_json::to_string_pretty(&out)?;
    outfile::write_atomically(&json_path, |w| w.write_all(json.as_bytes()))
        .with_context(|| format!("cannot write {}", json_path.display()))?;
    Ok(out)
}

use lung_model::scene::SceneExt;
use std::io::Write;

fn write_plot(png: &Path, r: &LatencyReport, series: &[SeriesPoint]) -> anyhow::Result<()> {
    use crate::plot::{Panel, Series};
    use plotters::style::RGBColor;
    let deadline = DEADLINE_NS as f64 / 1e6;
    let t_end = series.last().map_or(1.0, |p| p.t_s as f64);
    let line = |label: &str, f: fn(&SeriesPoint) -> f32, color: RGBColor| Series {
        label: label.to_string(),
        points: series
            .iter()
            .filter(|p| f(p).is_finite())
            .map(|p| (p.t_s as f64, f(p) as f64))
            .collect(),
        color,
        markers: false,
    };
    let deadline_line = |x1: f64| Series {
        label: "16.7 ms deadline".to_string(),
        points: vec![(0.0, deadline), (x1, deadline)],
        color: RGBColor(200, 30, 30),
        markers: false,
    };
    // The measured time points, each with its label and colour: the same in both panels.
    type Measured = (&'static str, fn(&SeriesPoint) -> f32, RGBColor);
    let mut measured: Vec<Measured> = vec![
        ("capture -> submit", |p| p.submit_ms, crate::plot::INHALE),
        (
            "capture -> GPU done",
            |p| p.gpu_done_ms,
            crate::plot::EXHALE,
        ),
    ];
    if r.window {
        measured.push((
            "capture -> present",
            |p| p.present_ms,
            RGBColor(40, 160, 60),
        ));
    }
    let mut over_time: Vec<Series> = measured.iter().map(|&(l, f, c)| line(l, f, c)).collect();
    over_time.push(deadline_line(t_end));
    // Percentile distribution: latency against "nines" (-log10(1 - q)), as HdrHistogram plots it.
    let quantiles: Vec<f64> = (0..=40)
        .map(|i| 1.0 - 10f64.powf(-(i as f64) / 10.0))
        .collect();
    let dist = |label: &str, f: fn(&SeriesPoint) -> f32, color: RGBColor| {
        let mut v: Vec<f64> = series
            .iter()
            .map(|p| f(p) as f64)
            .filter(|x| x.is_finite())
            .collect();
        v.sort_by(f64::total_cmp);
        Series {
            label: label.to_string(),
            points: if v.is_empty() {
                Vec::new()
            } else {
                quantiles
                    .iter()
                    .filter(|&&q| (1.0 - q) * v.len() as f64 >= 1.0 || q == 0.0)
                    .map(|&q| {
                        let i = ((q * v.len() as f64) as usize).min(v.len() - 1);
                        (-(1.0 - q).log10(), v[i])
                    })
                    .collect()
            },
            color,
            markers: false,
        }
    };
    let mut percentiles: Vec<Series> = measured.iter().map(|&(l, f, c)| dist(l, f, c)).collect();
    let x_max = percentiles
        .iter()
        .flat_map(|s| s.points.last().map(|p| p.0))
        .fold(1.0, f64::max);
    percentiles.push(deadline_line(x_max));
    crate::plot::write(
        png,
        &[
            Panel {
                title: format!("Latency per frame ({} frames)", series.len()),
                x_label: "time since the first frame, s".to_string(),
                y_label: "ms".to_string(),
                series: over_time,
            },
            Panel {
                title: "Percentile distribution (drawn frames)".to_string(),
                x_label: "nines: 1 = p90, 2 = p99, 3 = p99.9".to_string(),
                y_label: "ms".to_string(),
                series: percentiles,
            },
        ],
    )?;
    Ok(())
}

/// The report's line on the quality governor: the frames at each quality, its changes, its floor.
fn governor_line(r: &LatencyReport) -> String {
    let at = crate::demo::QualityFrames::list(&r.quality_frames);
    format!(
        "Quality governor: {} (started {}, the first frame at {} quality); frames at each quality \
         over the whole run: {}; {} change(s); the last frame drawn with {} quality{}.\n",
        r.governor,
        r.governor_start,
        r.first_quality,
        if at.is_empty() { "none" } else { at.as_str() },
        r.quality_changes,
        r.final_quality,
        if r.governor_floor_frames > 0 {
            format!(
                "; **{} frames with everything given up still over the deadline**",
                r.governor_floor_frames
            )
        } else {
            String::new()
        }
    )
}

/// The markdown report.
pub fn markdown(o: &LatencyOutput) -> String {
    use std::fmt::Write;
    let r = &o.run;
    let mut s = String::new();
    let _ = writeln!(s, "# lungdyn latency report\n");
    let _ = writeln!(
        s,
        "{} frames in {:.1} s (after {} warm-up frames) on {}; {} vertices per lung, {} mode{}{}.\n",
        r.frames,
        r.seconds,
        r.warmup_frames,
        o.adapter,
        r.mesh_vertices,
        r.mode,
        match (r.window, r.realtime) {
            (true, true) => ", in a window, real-time settings asked for",
            (true, false) => ", in a window",
            (false, true) => ", headless, real-time settings asked for",
            (false, false) => ", headless",
        },
        if r.load.cpu_threads > 0 || r.load.mem_mib > 0 {
            format!(
                ", under load ({} busy threads, {} MiB touched)",
                r.load.cpu_threads, r.load.mem_mib
            )
        } else {
            String::new()
        }
    );
    let png = Path::new(&o.plot_path)
        .file_name()
        .map_or(String::new(), |n| n.to_string_lossy().into_owned());
    let _ = writeln!(
        s,
        "![latency over time and percentile distribution]({png})\n"
    );
    let _ = writeln!(
        s,
        "Time points: capture (tracker), wake (renderer woke with the engine frame), submit \
         (`Queue::submit` returned), GPU done (the wait on the submission's fence returned), present \
         (`Queue::present` returned; `--window`). HdrHistogram, coordinated-omission corrected at the \
         60 Hz interval.\n"
    );
    let _ = writeln!(
        s,
        "| hop | samples | p50 ms | p99 ms | p99.9 ms | max ms |\n|---|---:|---:|---:|---:|---:|"
    );
    for row in &r.rows {
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.3} | {:.3} |",
            row.hop, row.count, row.p50_ms, row.p99_ms, row.p99_9_ms, row.max_ms
        );
    }
    let _ = writeln!(
        s,
        "\n**Deadline misses: {}** ({} frames over 16.7 ms from capture to GPU done{}, {} display \
         slots without a frame); tracker samples late on the 60 Hz schedule (to submit): {}.\n",
        r.deadline_misses,
        r.late_frames,
        if r.window { " / present" } else { "" },
        r.missed_frame_slots,
        r.schedule_misses
    );
    let _ = writeln!(s, "{}", governor_line(r));
    if !r.deadline_miss_stages.is_empty() {
        let _ = writeln!(
            s,
            "| stage that overran its share the most | share ms | misses |\n|---|---:|---:|"
        );
        for m in &r.deadline_miss_stages {
            let _ = writeln!(s, "| {} | {:.2} | {} |", m.stage, m.budget_ms, m.misses);
        }
        s.push('\n');
    }
    let _ = writeln!(
        s,
        "| process | period ms | jitter p50 ms | p99 ms | max ms | intervals | CPU s | measured on |\n|---|---:|---:|---:|---:|---:|---:|---|"
    );
    for p in &r.processes {
        let _ = writeln!(
            s,
            "| {} | {:.2} | {:.3} | {:.3} | {:.3} | {} | {} | {} |",
            p.process,
            p.period_ms,
            p.jitter_p50_ms,
            p.jitter_p99_ms,
            p.jitter_max_ms,
            p.intervals,
            p.cpu_s.map_or("-".to_string(), |c| format!("{c:.2}")),
            p.measured_on
        );
    }
    if !r.stages.is_empty() {
        let _ = writeln!(
            s,
            "\n| process | stage (span) | count | total ms | p50 ms | p99 ms | max ms |\n|---|---|---:|---:|---:|---:|---:|"
        );
        for t in &r.stages {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {:.1} | {:.3} | {:.3} | {:.3} |",
                t.process, t.stage, t.count, t.total_ms, t.p50_ms, t.p99_ms, t.max_ms
            );
        }
    }
    let _ = writeln!(
        s,
        "\nThe launcher's measuring thread used {:.2} s of CPU.",
        r.launcher_cpu_s
    );
    if let Some(largest) = o.largest_mesh_vertices {
        let _ = writeln!(
            s,
            "\n## Sweep\n\nLargest mesh holding 60 Hz with zero misses: **{}**.\n\n| vertices per lung | frames | misses | capture -> GPU done p99 ms | holds |\n|---:|---:|---:|---:|---|",
            largest.map_or("none (not even the smallest tried)".to_string(), |v| format!("{v} vertices per lung"))
        );
        for t in &o.sweep {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {:.2} | {} |",
                t.vertices,
                t.frames,
                t.deadline_misses,
                t.capture_to_gpu_done_p99_ms,
                if t.holds { "yes" } else { "no" }
            );
        }
    }
    s
}

/// The short summary printed after a run.
pub fn summary(o: &LatencyOutput) -> String {
    let r = &o.run;
    let mut s = format!(
        "lungdyn latency: {} frames in {:.1} s, {} vertices per lung ({} mode): capture -> submit p99 \
         {:.2} ms, capture -> GPU done p99 {:.2} ms{}, {} deadline misses; governor {}, last frame \
         at {} quality\n",
        r.frames,
        r.seconds,
        r.mesh_vertices,
        r.mode,
        r.capture_to_submit_p99_ms,
        r.capture_to_gpu_done_p99_ms,
        r.capture_to_present_p99_ms
            .map_or(String::new(), |p| format!(", capture -> present p99 {p:.2} ms")),
        r.deadline_misses,
        r.governor,
        r.final_quality
    );
    if let Some(sl) = &r.slicer {
        s.push_str(&sl.text());
        s.push('\n');
    }
    if let (Some(p50), Some(p99)) = (
        r.signal_arrival_to_gpu_done_p50_ms,
        r.signal_arrival_to_gpu_done_p99_ms,
    ) {
        s.push_str(&format!(
            "breathing signal: its newest sample's arrival -> GPU done median {p50:.2} ms, p99 \
             {p99:.2} ms ({} frames not matched to their tracker frame)\n",
            r.signal_frames_unmatched
        ));
    }
    if let Some(l) = o.largest_mesh_vertices {
        s.push_str(&format!(
            "largest mesh holding 60 Hz with zero misses: {}\n",
            l.map_or("none".to_string(), |v| v.to_string())
        ));
    }
    s.push_str(&format!(
        "report {} (plot {}, JSON {})\n",
        o.report_path, o.plot_path, o.json_path
    ));
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::HopStamps;

    /// The signal row: each drawn frame is measured from the newest valid sample that had arrived by
    /// its tracker frame (a frame without samples carries the newest before it); an invalid sample
    /// is not an arrival; a drawn frame whose tracker frame was not seen is counted, not measured.
    #[test]
    fn the_signal_row_measures_from_the_newest_sample_by_each_tracker_frame() {
        let mut a = SignalArrivals::new();
        let frame = |n: u64, samples: &[(u64, bool)]| {
            let mut f = ipc_types::TrackerFrame::default();
            f.frame_number = n;
            f.signal.count = samples.len() as u32;
            for (i, &(t, valid)) in samples.iter().enumerate() {
                f.signal.samples[i].t_ns = t;
                if valid {
                    f.signal.valid_mask |= 1 << i;
                }
            }
            f
        };
        // No signal yet: nothing measured, nothing counted.
        a.tracker_frame(&frame(1, &[]));
        a.drawn(1, 50_000_000);
        assert!(a.hist.is_empty() && a.unmatched == 0);
        a.tracker_frame(&frame(2, &[(100_000_000, true), (120_000_000, true)]));
        a.tracker_frame(&frame(3, &[]));
        a.tracker_frame(&frame(4, &[(150_000_000, false)]));
        a.drawn(2, 130_000_000); // 10 ms after the sample at 120 ms
        a.drawn(3, 135_000_000); // frame 3 carried none: still from 120 ms
        a.drawn(4, 160_000_000); // the sample at 150 ms was invalid: from 120 ms
        a.drawn(9, 170_000_000); // never seen
        assert_eq!(a.unmatched, 1);
        // Three frames, and the 40 ms one corrected for coordinated omission (one more at 23.3 ms).
        assert_eq!(a.hist.len(), 4);
        assert!((a.hist.min() as f64 - 10e6).abs() < 1e4, "{}", a.hist.min());
        assert!((a.hist.max() as f64 - 40e6).abs() < 1e5, "{}", a.hist.max());
        // The ring wraps: frame 2 + 512 replaces frame 2.
        a.tracker_frame(&frame(2 + SIGNAL_RING as u64, &[(200_000_000, true)]));
        a.drawn(2, 210_000_000);
        assert_eq!(a.unmatched, 2);
    }

    #[test]
    fn load_specs_parse_and_bad_ones_say_why() {
        assert_eq!(
            Load::parse("cpu:2,mem:16").unwrap(),
            Load {
                cpu_threads: 2,
                mem_mib: 16
            }
        );
        assert_eq!(Load::parse("cpu:1").unwrap().cpu_threads, 1);
        for (bad, says) in [
            ("cpu", "expected cpu:N"),
            ("cpu:x", "not a whole number"),
            ("cpu:0", "1..256"),
            ("cpu:1,cpu:2", "twice"),
            ("gpu:1", "unknown load"),
            ("mem:0", "at least 1 MiB"),
            ("mem:99999999999", "half the memory"),
        ] {
            let e = Load::parse(bad).unwrap_err().to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    fn frame(n: u64, gpu_ms: f64) -> FrameReport {
        let p = DEADLINE_NS;
        let c = 1_000_000_000 + n * p;
        let submit = c + 3_000_000;
        FrameReport {
            frame: n,
            engine_tick: n,
            tracker_frame: n,
            stamps: HopStamps {
                capture_ns: c,
                bridge_publish_ns: c + 100_000,
                engine_receive_ns: c + 200_000,
                engine_publish_ns: c + 1_000_000,
                renderer_receive_ns: c + 1_100_000,
                renderer_submit_ns: submit,
            },
            gpu_done_ns: submit + (gpu_ms * 1e6) as u64,
            ..Default::default()
        }
    }

    /// A frame whose GPU work ran long is a miss charged to the GPU, and the 60 Hz correction adds
    /// the frames it held up to the histogram.
    #[test]
    fn a_slow_gpu_frame_is_a_miss_charged_to_the_gpu() {
        let budgets = lung_model::scene::ProcessBudgets::default();
        let mut rec = Recorder::new(0.0, 10.0, 60.0, 60.0, &budgets, false, Load::default());
        for n in 1..=100 {
            rec.report(&frame(n, if n == 50 { 60.0 } else { 5.0 }));
        }
        assert_eq!(rec.late_frames, 1);
        assert_eq!(rec.stage_misses[5], 1, "{:?}", rec.stage_misses);
        let gpu_done = Row::of("", &rec.rows[ROW_GPU_DONE]);
        let submit = Row::of("", &rec.rows[ROW_SUBMIT]);
        assert!(gpu_done.p50_ms > submit.p50_ms);
        assert!((gpu_done.max_ms - 63.0).abs() < 0.1, "{}", gpu_done.max_ms);
        // 63 ms at a 16.7 ms interval also stands for the frames that would have waited 46 and
        // 30 ms (HdrHistogram adds value − k·interval while it is at least one interval).
        assert_eq!(rec.rows[ROW_GPU_DONE].len(), 102);
        assert_eq!(rec.rows[ROW_SUBMIT].len(), 100);
        // Consecutive frames exactly one period apart: no jitter.
        assert_eq!(rec.periods[0].jitter.max(), 1);
        assert_eq!(rec.series.len(), 100);
    }

    #[test]
    fn the_stage_named_is_the_one_furthest_over_its_share() {
        let b = stage_budgets(&lung_model::scene::ProcessBudgets::default(), false);
        // The engine took 5 ms of its 2: 3 over; the GPU 4 ms of its 2.67: less over.
        let t = [100_000, 50_000, 5_000_000, 50_000, 8_000_000, 4_000_000, 0];
        assert_eq!(STAGES[overran_stage(&t, &b)], "engine");
        assert_eq!(b[6], 0, "no present share headless");
        assert_eq!(b.iter().sum::<u64>(), 16_666_666);
    }

    #[test]
    fn arguments_are_checked_before_any_work() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            l: LatencyArgs,
        }
        let args =
            |a: &[&str]| Cli::parse_from(std::iter::once("latency").chain(a.iter().copied())).l;
        assert!(check_args(&args(&[])).is_ok());
        for (bad, says) in [
            (&["--seconds", "0"][..], "--seconds 0"),
            (&["--warmup", "nan"][..], "--warmup NaN"),
            (&["--mesh", "5"][..], "--mesh"),
            (
                &["--sweep", "--sweep-min", "5000", "--sweep-max", "4000"][..],
                "below",
            ),
            (&["--sweep", "--mesh", "5000"][..], "--mesh and --sweep"),
            (&["--load", "cpu:-1"][..], "--load"),
        ] {
            let e = format!("{:#}", check_args(&args(bad)).unwrap_err());
            assert!(e.contains(says), "{bad:?}: {e}");
        }
    }
}
