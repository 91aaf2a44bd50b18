//! `lungdyn breathing follow FILE`: the three processes run with FILE replayed live as the patient's
//! respiratory signal (the bridge feeds it at its own rate, never ahead of its sample clock), and
//! every frame the renderer drew is held against the recording at the moment it was shown (issue
//! 35's measuring command; `breathing check` is the same question asked offline).
//!
//! Each drawn frame is placed on the recording's own time axis: the bridge names, in every tracker
//! frame, the monotonic time at which the recording's first sample fell
//! ([`ipc_types::SignalBlock::origin_ns`]), and the renderer reports when the frame was shown (the
//! present in a window, else the GPU work done, else the submit). The engine frame it drew says what
//! the engine followed ([`ipc_types::SignalFollowed`]): the volume above FRC it predicted for its own
//! guess of the display time, and the volume the newest sample gave with no prediction — kept side
//! by side from the same run. Both are compared with the recording's hindsight volume at the real
//! display time ([`Trace::truth_at`]: for a ventilator recording each breath's flow integrated on
//! its own; for a one-signal trace, calibrated in hindsight to the same tidal volume the engine
//! calibrates to). Each lung draws its share of the followed volume on its rest volume, so the
//! drawn volume (the CSV's) is that volume's affine image; the run checks that it is
//! ([`FollowReport::drawn_vs_followed_rms_ml`]).

use std::collections::HashMap;
use std::path::PathBuf;

use anyhow::Context;
use ipc_types::{
    report_flags, signal_status, EngineFrame, FrameReport, SignalFollowed, TrackerFrame,
};
use lung_model::breathing::check::{
    read_trace_or_recording, GOAL_IMPROVEMENT, GOAL_PERCENT_OF_TIDAL,
};
use lung_model::breathing::evaluate::{lag, peaks, Trace};
use lung_model::breathing::follow::Calibration;
use serde::Serialize;

use crate::demo::{Run, Watch};
use crate::plot::{self, Panel, Series, DATA, EXHALE, INHALE};
use lung_model::scene::SceneExt;

/// The goal issue 35 sets on the end-inspiration lag, ms (either way).
pub const GOAL_LAG_MS: f64 = 20.0;
/// …on the breaths the lungs follow, % of the recording's.
pub const GOAL_BREATHS_PERCENT: f64 = 98.0;
/// How long the run goes on after the recording's last sample was sent (its last frames shown).
const TAIL_NS: u64 = 1_000_000_000;

/// Options of `lungdyn breathing follow`.
#[derive(Debug, Clone, clap::Args)]
pub struct FollowArgs {
    /// The recording replayed live as the patient's signal: a ventilator recording (the formats
    /// `lungdyn pv recording` reads; its flow integrated), a Varian RPM export (.vxp) or a CSV of
    /// one signal (time_s or time_ms, and amplitude_mm, amplitude_cm, amplitude_au, volume_ml or
    /// volume_L; optional valid 1/0). It plays from its first sample.
    pub file: PathBuf,
    /// Seconds to run once frames flow; by default until the recording's end (the run also ends
    /// there when this is longer).
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// Write every drawn frame as CSV: `display_time_s,volume_ml` — when the frame was shown, in
    /// seconds from the recording's first sample, and the volume of both lungs drawn in it (FRC
    /// included), ml. Written once the run ends (atomically).
    #[arg(long, value_name = "CSV")]
    pub frames_out: Option<PathBuf>,
    /// Cut the signal S seconds into the recording (with --drop-for): a loss, to see the model
    /// carry on under the blue veil and how soon the lungs follow the patient again.
    #[arg(long, value_name = "S", requires = "drop_for")]
    pub drop_at: Option<f64>,
    /// How long --drop-at cuts the signal, seconds.
    #[arg(long, value_name = "S", requires = "drop_at")]
    pub drop_for: Option<f64>,
    /// Predict each frame's volume across a fixed latency, ms, instead of the pipeline's latency as
    /// measured (the scene's [breathing] latency = "measured", by default, takes the median the
    /// bridge reads from the renderer's reports, plus sensor_latency_ms): for comparing horizons.
    #[arg(long, value_name = "MS")]
    pub latency_ms: Option<f64>,
    /// Scene file (TOML): its lungs, PV model (whose tidal volume an amplitude is calibrated to) and
    /// `[breathing]` predictor and latency_ms; the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Folder for the run's files (the kernels baked for the default lungs are kept there).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Plot the recording, the volume followed with and without prediction at each frame's display
    /// time, and where the signal did not drive (PNG; an SVG is written beside it).
    #[arg(long, value_name = "PNG")]
    pub plot: Option<PathBuf>,
    /// Print one JSON object on stdout (the table goes to stdout otherwise).
    #[arg(long)]
    pub json: bool,
    /// Window and display options (headless by default).
    #[command(flatten)]
    pub output: renderer::window::DisplayArgs,
}

/// One frame the renderer drew, as the launcher saw its report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Drawn {
    /// The engine tick it drew.
    pub engine_tick: u64,
    /// When it was shown (present, else GPU done, else submit), CLOCK_MONOTONIC ns.
    pub display_ns: u64,
    /// Both lungs' drawn volume, ml (FRC included).
    pub volume_ml: f64,
    /// [`report_flags`] bits.
    pub flags: u32,
    /// The recording's origin on this clock when the frame was reported (0: none yet).
    pub origin_ns: u64,
}

impl Drawn {
    /// The frame as its report says.
    pub fn of(r: &FrameReport, origin_ns: u64) -> Self {
        Self {
            engine_tick: r.engine_tick,
            display_ns: r.display_ns(),
            volume_ml: f64::from(r.volume_ml[0]) + f64::from(r.volume_ml[1]),
            flags: r.flags,
            origin_ns,
        }
    }

    /// Seconds from the recording's first sample to the frame's display (`None` before the
    /// recording's clock is known).
    pub fn recording_time_ns(&self) -> Option<u64> {
        (self.origin_ns != 0 && self.display_ns >= self.origin_ns)
            .then(|| self.display_ns - self.origin_ns)
    }
}

/// What the run watched: every drawn frame, what the engine followed per tick, the recording's
/// clock.
#[derive(Debug, Default)]
pub struct Follow {
    origin_ns: u64,
    /// Times the bridge named another origin (a restarted bridge replays from the start again).
    pub origin_changes: u32,
    ended_at_ns: Option<u64>,
    seen_ended: bool,
    /// The engine's signal part of each tick seen, and its state bits.
    pub engine: HashMap<u64, (SignalFollowed, u32)>,
    /// Every frame reported.
    pub drawn: Vec<Drawn>,
}

impl Follow {
    fn with_capacity(frames: usize) -> Self {
        Self {
            engine: HashMap::with_capacity(frames),
            drawn: Vec::with_capacity(frames),
            ..Self::default()
        }
    }
}

impl Follow {
    /// Frames reported in the pass before the launcher saw the bridge's first origin: the bridge
    /// started before any frame was drawn, so its first origin is theirs.
    fn place_early_frames(&mut self) {
        let first = self.drawn.iter().map(|d| d.origin_ns).find(|&o| o != 0);
        let first = first.unwrap_or(self.origin_ns);
        for d in self.drawn.iter_mut().filter(|d| d.origin_ns == 0) {
            d.origin_ns = first;
        }
    }
}

impl Watch for Follow {
    fn report(&mut self, r: &FrameReport) {
        self.drawn.push(Drawn::of(r, self.origin_ns));
    }
    fn engine_frame(&mut self, f: &EngineFrame) {
        self.engine.insert(f.tick, (f.signal, f.state));
    }
    fn tracker_frame(&mut self, f: &TrackerFrame) {
        let s = &f.signal;
        if s.status & signal_status::CONFIGURED == 0 || s.origin_ns == 0 {
            return;
        }
        if self.origin_ns != 0 && s.origin_ns != self.origin_ns {
            self.origin_changes += 1;
        }
        self.origin_ns = s.origin_ns;
        self.seen_ended = s.status & signal_status::ENDED != 0;
    }
    fn pass(&mut self, run: &mut Run<'_, '_>) -> anyhow::Result<bool> {
        if self.seen_ended && self.ended_at_ns.is_none() {
            self.ended_at_ns = Some(run.now_ns);
        }
        Ok(self
            .ended_at_ns
            .is_none_or(|t| run.now_ns < t.saturating_add(TAIL_NS)))
    }
}

/// A signal loss asked for, and how soon the lungs followed the patient again.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DropReport {
    /// Where the cut began, s into the recording.
    pub at_s: f64,
    /// How long it lasted, s.
    pub for_s: f64,
    /// From the cut's end to the first frame the signal drove again, s (`None`: never again).
    pub resync_s: Option<f64>,
    /// The recording's median breath period, s (the goal: in step again within one breath).
    pub breath_period_s: Option<f64>,
    /// `resync_s` within one breath period: the signal drives the lungs again.
    pub driven_again_within_one_breath: bool,
    /// …and over the breath after that the RMS error is within issue 35's 3 % of tidal: the lungs
    /// are in step with the patient again, not only driven by the signal.
    pub in_step_within_one_breath: bool,
    /// RMS error with prediction over the breath period after the resynchronisation, % of tidal
    /// (whether the lungs are in step again, not only driven again).
    pub rms_error_percent_of_tidal_first_breath_after: Option<f64>,
    /// The same from the breath after that to the end.
    pub rms_error_percent_of_tidal_later: Option<f64>,
}

/// The figures of a run, from its frames (pure: [`figures`]).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Figures {
    /// Frames the renderer drew (every report).
    pub frames_drawn: usize,
    /// Of those, placed on the recording's time axis (the CSV's rows).
    pub frames_on_recording: usize,
    /// Frames the signal drove (the engine was following it).
    pub frames_following: usize,
    /// Frames drawn while the signal was lost, cut, ended or not there yet (the model breathed).
    pub frames_lost: usize,
    /// Frames the model drew while the signal calibrated (neither following nor lost).
    pub frames_calibrating: usize,
    /// Following frames compared with the recording (its hindsight volume known there).
    pub frames_compared: usize,
    /// Following frames whose engine frame the launcher did not see (not compared).
    pub frames_without_engine_frame: usize,
    /// Seconds of the recording played (to the last frame shown).
    pub recording_played_s: f64,
    /// When the signal first drove the lungs, s into the recording.
    pub first_following_s: Option<f64>,
    /// The recording's mean tidal volume, ml.
    pub tidal_ml: f64,
    /// Complete breaths in the part of the recording played.
    pub breaths_in_recording: usize,
    /// Of those, breaths whose end-inspiration the signal-driven lungs drew within ±1 s.
    pub breaths_detected: usize,
    /// The others: each one's end-inspiration, s into the recording (where to look).
    pub breaths_missed_at_s: Vec<f64>,
    /// RMS of followed − recorded volume at display time, ml, with prediction.
    pub rms_error_ml: f64,
    /// The same for the volume with no prediction, same frames.
    pub rms_error_ml_without_prediction: f64,
    /// RMS error, % of the mean tidal volume, with prediction.
    pub rms_error_percent_of_tidal: f64,
    /// The same without prediction.
    pub rms_error_percent_of_tidal_without_prediction: f64,
    /// Drawn end-inspiration minus recorded, mean over matched breaths, ms (positive: late).
    pub lag_ms: Option<f64>,
    /// The same without prediction.
    pub lag_ms_without_prediction: Option<f64>,
    /// `[breathing] latency`: "measured" (the engine predicted across the pipeline's latency the
    /// bridge measured from the renderer's reports) or "fixed" (`latency_ms`).
    pub latency: String,
    /// `[breathing] latency_ms`, ms: what the engine predicted across when fixed, or before the
    /// pipeline's latency was measured.
    pub latency_ms_configured: f64,
    /// What the engine predicted across, ms, median over the compared frames (each engine frame
    /// says its own: `SignalFollowed::latency_ns`).
    pub latency_ms_predicted_median: Option<f64>,
    /// What the frames took from the engine's newest input to their display, ms, median and p99 —
    /// the latency the prediction should cross.
    pub latency_ms_measured_median: Option<f64>,
    /// The same, 99th percentile.
    pub latency_ms_measured_p99: Option<f64>,
    /// RMS of the drawn volume about the best affine image of the followed volume (each lung draws
    /// its share on its rest volume), over following frames past the takeover, ml; near 0 when the
    /// lungs drew what the engine followed.
    pub drawn_vs_followed_rms_ml: Option<f64>,
    /// The loss asked for (`--drop-at`), and the resynchronisation.
    pub drop: Option<DropReport>,
}

/// One compared frame: recording time ns, predicted, unpredicted, recorded (ml).
type Compared = (u64, f64, f64, f64);

/// The figures of `drawn` frames (with the engine's `engine` part of each tick) against `trace`.
/// `first_t_ns` is the trace's first sample time; `latency` the scene's choice and `latency_ns` its
/// `latency_ms`.
pub fn figures(
    trace: &Trace,
    drawn: &[Drawn],
    engine: &HashMap<u64, (SignalFollowed, u32)>,
    (latency, latency_ns): (lung_model::scene::LatencyChoice, u64),
    drop: Option<(f64, f64)>,
) -> (Figures, Vec<Compared>) {
    let first_t = trace.samples.first().map_or(0, |s| s.t_ns);
    let mut f = empty_figures(trace, drawn.len(), latency_ns);
    f.latency = latency.name().into();
    let (mut sq, mut sq_hold) = (0.0, 0.0);
    let mut compared: Vec<Compared> = Vec::with_capacity(drawn.len());
    let mut latencies = Vec::with_capacity(drawn.len());
    let mut predicted = Vec::with_capacity(drawn.len());
    let mut affine = Vec::new();
    let mut played_ns = 0u64;
    // The tick the signal last took over (its volume is blended in from the model's over
    // TAKEOVER_TICKS: not yet the followed volume's image).
    let mut took_over: Option<u64> = None;
    for d in drawn {
        let Some(t) = d.recording_time_ns() else {
            continue;
        };
        f.frames_on_recording += 1;
        played_ns = played_ns.max(t);
        if d.flags & report_flags::SIGNAL_LOST != 0 {
            f.frames_lost += 1;
            took_over = None;
            continue;
        }
        if d.flags & report_flags::SIGNAL_FOLLOWING == 0 {
            f.frames_calibrating += 1;
            took_over = None;
            continue;
        }
        let start = *took_over.get_or_insert(d.engine_tick);
        let blended = d.engine_tick.saturating_sub(start) < engine::runtime::signal::TAKEOVER_TICKS;
        f.frames_following += 1;
        f.first_following_s.get_or_insert(t as f64 * 1e-9);
        let Some(&(s, _)) = engine.get(&d.engine_tick).filter(|e| e.0.display_ns != 0) else {
            f.frames_without_engine_frame += 1;
            continue;
        };
        let (p, h) = (f64::from(s.volume_ml), f64::from(s.unpredicted_ml));
        if !blended {
            affine.push((p, d.volume_ml));
        }
        let input_ns = s.display_ns.saturating_sub(s.latency_ns);
        if d.display_ns >= input_ns {
            latencies.push((d.display_ns - input_ns) as f64 * 1e-6);
        }
        predicted.push(s.latency_ns as f64 * 1e-6);
        if let Some(truth) = trace.truth_at(first_t + t) {
            sq += (p - truth).powi(2);
            sq_hold += (h - truth).powi(2);
            compared.push((t, p, h, truth));
        }
    }
    f.frames_compared = compared.len();
    f.recording_played_s = played_ns as f64 * 1e-9;
    let n = compared.len() as f64;
    let rms = |s: f64| if n > 0.0 { (s / n).sqrt() } else { f64::NAN };
    f.rms_error_ml = rms(sq);
    f.rms_error_ml_without_prediction = rms(sq_hold);
    f.rms_error_percent_of_tidal = 100.0 * f.rms_error_ml / trace.tidal_ml;
    f.rms_error_percent_of_tidal_without_prediction =
        100.0 * f.rms_error_ml_without_prediction / trace.tidal_ml;
    breaths_and_lag(&mut f, trace, &compared, played_ns);
    let at = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v.get(((v.len() as f64 - 1.0) * q).round() as usize)
            .copied()
    };
    f.latency_ms_measured_median = at(&mut latencies, 0.5);
    f.latency_ms_measured_p99 = at(&mut latencies, 0.99);
    f.latency_ms_predicted_median = at(&mut predicted, 0.5);
    f.drawn_vs_followed_rms_ml = affine_residual(&affine);
    f.drop = drop.map(|(at_s, for_s)| drop_report(trace, drawn, &compared, at_s, for_s));
    (f, compared)
}

fn empty_figures(trace: &Trace, frames: usize, latency_ns: u64) -> Figures {
    Figures {
        frames_drawn: frames,
        frames_on_recording: 0,
        frames_following: 0,
        frames_lost: 0,
        frames_calibrating: 0,
        frames_compared: 0,
        frames_without_engine_frame: 0,
        recording_played_s: 0.0,
        first_following_s: None,
        tidal_ml: trace.tidal_ml,
        breaths_in_recording: 0,
        breaths_detected: 0,
        breaths_missed_at_s: Vec::new(),
        rms_error_ml: f64::NAN,
        rms_error_ml_without_prediction: f64::NAN,
        rms_error_percent_of_tidal: f64::NAN,
        rms_error_percent_of_tidal_without_prediction: f64::NAN,
        lag_ms: None,
        lag_ms_without_prediction: None,
        latency: String::new(),
        latency_ms_configured: latency_ns as f64 * 1e-6,
        latency_ms_predicted_median: None,
        latency_ms_measured_median: None,
        latency_ms_measured_p99: None,
        drawn_vs_followed_rms_ml: None,
        drop: None,
    }
}

/// The breaths of the part played, those the drawn lungs followed, and the end-inspiration lag
/// with and without prediction (the offline check's peak finder and matching, ±1 s).
fn breaths_and_lag(f: &mut Figures, trace: &Trace, compared: &[Compared], played_ns: u64) {
    let first_t = trace.samples.first().map_or(0, |s| s.t_ns);
    let ends: Vec<u64> = trace
        .end_inspiration_ns
        .iter()
        .copied()
        .filter(|&t| t >= first_t && t - first_t <= played_ns)
        .collect();
    let times: Vec<u64> = compared.iter().map(|c| first_t + c.0).collect();
    let pred: Vec<f64> = compared.iter().map(|c| c.1).collect();
    let hold: Vec<f64> = compared.iter().map(|c| c.2).collect();
    let h = 0.25 * trace.tidal_ml;
    let drawn = peaks(&times, &pred, h);
    let (lag_p, matched) = lag(&ends, &drawn);
    let (lag_h, _) = lag(&ends, &peaks(&times, &hold, h));
    f.breaths_in_recording = ends.len();
    f.breaths_detected = matched;
    // The same ±1 s as `lag`'s matching.
    f.breaths_missed_at_s = ends
        .iter()
        .filter(|&&r| !drawn.iter().any(|&d| d.abs_diff(r) <= 1_000_000_000))
        .map(|&r| (r - first_t) as f64 * 1e-9)
        .collect();
    f.lag_ms = lag_p;
    f.lag_ms_without_prediction = lag_h;
}

/// RMS residual of `(followed, drawn)` about their least-squares line, ml (`None` under 10 points).
fn affine_residual(points: &[(f64, f64)]) -> Option<f64> {
    if points.len() < 10 {
        return None;
    }
    let n = points.len() as f64;
    let (sx, sy) = points
        .iter()
        .fold((0.0, 0.0), |a, p| (a.0 + p.0, a.1 + p.1));
    let (mx, my) = (sx / n, sy / n);
    let (sxx, sxy) = points.iter().fold((0.0, 0.0), |a, p| {
        (a.0 + (p.0 - mx).powi(2), a.1 + (p.0 - mx) * (p.1 - my))
    });
    let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let ss: f64 = points
        .iter()
        .map(|p| (p.1 - my - slope * (p.0 - mx)).powi(2))
        .sum();
    Some((ss / n).sqrt())
}

fn drop_report(
    trace: &Trace,
    drawn: &[Drawn],
    compared: &[Compared],
    at_s: f64,
    for_s: f64,
) -> DropReport {
    let end_ns = ((at_s + for_s) * 1e9).round() as u64;
    let resync_s = drawn
        .iter()
        .filter(|d| d.flags & report_flags::SIGNAL_FOLLOWING != 0)
        .filter_map(|d| d.recording_time_ns())
        .find(|&t| t >= end_ns)
        .map(|t| (t - end_ns) as f64 * 1e-9);
    let mut periods: Vec<f64> = trace
        .end_inspiration_ns
        .windows(2)
        .map(|w| (w[1] - w[0]) as f64 * 1e-9)
        .collect();
    periods.sort_by(f64::total_cmp);
    let breath_period_s = periods.get(periods.len() / 2).copied();
    let rms_in = |from_s: f64, to_s: f64| {
        let e: Vec<f64> = compared
            .iter()
            .filter(|c| (from_s..to_s).contains(&(c.0 as f64 * 1e-9)))
            .map(|c| (c.1 - c.3).powi(2))
            .collect();
        (!e.is_empty())
            .then(|| 100.0 * (e.iter().sum::<f64>() / e.len() as f64).sqrt() / trace.tidal_ml)
    };
    let (first, later) = match (resync_s, breath_period_s) {
        (Some(r), Some(p)) => {
            let from = at_s + for_s + r;
            (rms_in(from, from + p), rms_in(from + p, f64::INFINITY))
        }
        _ => (None, None),
    };
    DropReport {
        at_s,
        for_s,
        resync_s,
        breath_period_s,
        driven_again_within_one_breath: matches!((resync_s, breath_period_s), (Some(r), Some(p)) if r <= p),
        in_step_within_one_breath: matches!((resync_s, breath_period_s), (Some(r), Some(p)) if r <= p)
            && first.is_some_and(|e| e <= GOAL_PERCENT_OF_TIDAL),
        rms_error_percent_of_tidal_first_breath_after: first,
        rms_error_percent_of_tidal_later: later,
    }
}

/// Issue 35's goals against a run's figures.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Goals {
    /// RMS ≤ 3 % of tidal with prediction.
    pub rms_within_3_percent: bool,
    /// …and at least 2× lower than without.
    pub prediction_halves_the_error: bool,
    /// |lag| ≤ 20 ms.
    pub lag_within_20_ms: bool,
    /// ≥ 98 % of the breaths followed.
    pub breaths_98_percent: bool,
    /// After the loss asked for, in step again within one breath — driven by the signal, and the
    /// breath after within 3 % of tidal (`None`: no loss asked for).
    pub resync_within_one_breath: Option<bool>,
}

impl Goals {
    /// The goals of `f`.
    pub fn of(f: &Figures) -> Self {
        Self {
            rms_within_3_percent: f.rms_error_percent_of_tidal <= GOAL_PERCENT_OF_TIDAL,
            prediction_halves_the_error: f.rms_error_ml_without_prediction
                >= GOAL_IMPROVEMENT * f.rms_error_ml,
            lag_within_20_ms: f.lag_ms.is_some_and(|l| l.abs() <= GOAL_LAG_MS),
            breaths_98_percent: f.breaths_in_recording > 0
                && 100.0 * f.breaths_detected as f64
                    >= GOAL_BREATHS_PERCENT * f.breaths_in_recording as f64,
            resync_within_one_breath: f.drop.as_ref().map(|d| d.in_step_within_one_breath),
        }
    }
}

/// What `lungdyn breathing follow` reports.
#[derive(Debug, Serialize)]
pub struct FollowReport {
    /// The recording.
    pub file: String,
    /// What it was read as.
    pub kind: String,
    /// Breaths of unequal depth turning at the signal's highest (or lowest) value: cut by the
    /// sensor's range (`None`: none seen; a ventilator recording is not checked).
    pub clipping: Option<lung_model::breathing::evaluate::Clipping>,
    /// Its length, s.
    pub duration_s: f64,
    /// The scene run (`built-in default` without --scene).
    pub scene: String,
    /// The predictor the engine ran (`[breathing] predictor`).
    pub predictor: String,
    /// The figures.
    #[serde(flatten)]
    pub figures: Figures,
    /// The goals.
    pub goals: Goals,
    /// Times the bridge replayed the recording from its start again (a restarted bridge).
    pub replay_restarts: u32,
    /// The CSV written, the plots.
    pub frames_out: Option<String>,
    /// The plots written (PNG, SVG).
    pub plots: Vec<String>,
    /// The run itself, as `lungdyn demo --json` reports it (frame rate, deadline misses, the
    /// frames the signal drove and those it did not).
    pub run: crate::demo::DemoReport,
}

/// The file read and the options checked, before anything starts.
struct Checked {
    trace: Trace,
    kind: String,
    scene: lung_model::scene::Scene,
}

fn check_args(a: &FollowArgs) -> anyhow::Result<Checked> {
    if let Some(s) = a.seconds {
        if !(s.is_finite() && s > 0.0 && s <= transport::process::MAX_SECONDS) {
            anyhow::bail!(
                "--seconds {}: a positive number of seconds, at most {} (one week)",
                lung_model::plausible::compact(s),
                transport::process::MAX_SECONDS
            );
        }
    }
    // The bridge reads the recording again when it starts: a pipe or device would be empty then.
    if a.file.exists() && !a.file.is_file() {
        anyhow::bail!(
            "the recording {}: not a regular file (a pipe, device or folder); breathing follow \
             replays a file, which the tracker bridge reads again when it starts",
            a.file.display()
        );
    }
    let scene = lung_model::scene::Scene::load_or_default(a.scene.as_deref())?;
    let tidal_ml = match (scene.breathing.tidal_ml, scene.pv_waveform()?) {
        (Some(t), _) => t,
        (None, Some(w)) => w.tidal_volume_ml,
        (None, None) => scene.pv_model()?.2.tv_ml,
    };
    let bytes = lung_model::input::read_bounded(&a.file, lung_model::input::ReadLimits::TABLE)
        .with_context(|| format!("the recording {}", a.file.display()))?;
    // The recording's hindsight volume is calibrated as the engine calibrates it live: by the
    // scene's spirometry calibration when it has one, else to its tidal volume.
    let calibration = Calibration::amplitude(scene.breathing.ml_per_unit, tidal_ml);
    let read = read_trace_or_recording(&a.file, &bytes, calibration)?;
    let duration_s = duration_s(&read.trace);
    let mut scene = scene;
    if let Some(ms) = a.latency_ms {
        scene.breathing.latency_ms = ms;
        scene.breathing.latency = lung_model::scene::LatencyChoice::Fixed;
        scene
            .validate()
            .map_err(|e| anyhow::anyhow!("--latency-ms {ms}: {e}"))?;
    }
    if let (Some(at), Some(dur)) = (a.drop_at, a.drop_for) {
        tracker_bridge::signal::check_cut(at, dur).map_err(|e| {
            anyhow::anyhow!("{}", e.to_string().replace("--breathing-cut", "--drop"))
        })?;
        if at >= duration_s {
            anyhow::bail!(
                "--drop-at {at}: the recording is {duration_s:.1} s long; cut it within that"
            );
        }
    }
    // Outputs are written when the run ends: anything that would refuse them refuses now.
    for (flag, p) in [("--frames-out", &a.frames_out), ("--plot", &a.plot)] {
        let Some(p) = p else { continue };
        let folder = p.parent().filter(|f| !f.as_os_str().is_empty());
        if folder.is_some_and(|f| !f.is_dir()) {
            anyhow::bail!(
                "{flag} {}: the folder {} does not exist (nothing is written until the run ends)",
                p.display(),
                folder.map_or(String::new(), |f| f.display().to_string())
            );
        }
    }
    if let Some(p) = &a.frames_out {
        outfile::check(p).with_context(|| format!("--frames-out {}", p.display()))?;
    }
    if let Some(p) = &a.plot {
        plot::check_path(p)?;
    }
    Ok(Checked {
        trace: read.trace,
        kind: read.kind,
        scene,
    })
}

fn duration_s(trace: &Trace) -> f64 {
    match (trace.samples.first(), trace.samples.last()) {
        (Some(a), Some(b)) => (b.t_ns - a.t_ns) as f64 * 1e-9,
        _ => 0.0,
    }
}

/// The demo's arguments for the run.
fn demo_args(a: &FollowArgs, duration_s: f64) -> anyhow::Result<crate::demo::DemoArgs> {
    let mut demo = crate::demo::DemoArgs::defaults();
    let file = std::path::absolute(&a.file)
        .with_context(|| format!("the recording {}", a.file.display()))?;
    // Frames flow a few seconds after the replay starts (processes, kernels): the run ends at the
    // recording's end anyway, so the default leaves room for the slowest start.
    demo.seconds = a.seconds.unwrap_or(duration_s + 60.0);
    demo.out = a.out.clone();
    demo.snapshots = 0;
    demo.scene = a.scene.clone();
    demo.json = a.json;
    demo.output = a.output.clone();
    demo.breathing = Some(format!("trace:{}", file.display()));
    demo.breathing_cut_at = a.drop_at;
    demo.breathing_cut_for = a.drop_for;
    demo.breathing_latency_ms = a.latency_ms;
    Ok(demo)
}

/// Run `lungdyn breathing follow`.
pub fn follow(a: &FollowArgs) -> anyhow::Result<FollowReport> {
    let c = check_args(a)?;
    let duration = duration_s(&c.trace);
    let demo = demo_args(a, duration)?;
    let latency = (
        c.scene.breathing.latency,
        (c.scene.breathing.latency_ms * 1e6).round() as u64,
    );
    let frames = ((demo.seconds.min(duration + 60.0)) * 120.0) as usize + 1024;
    let mut watch = Follow::with_capacity(frames);
    let run = crate::demo::run_watched(&demo, &mut watch)?;
    watch.place_early_frames();
    let drop = a.drop_at.zip(a.drop_for);
    let (figures, compared) = figures(&c.trace, &watch.drawn, &watch.engine, latency, drop);
    let frames_out = match &a.frames_out {
        Some(p) => Some(write_frames(p, &watch.drawn)?),
        None => None,
    };
    let plots = match &a.plot {
        Some(png) => plot::render(png, &panels(&c.trace, &watch.drawn, &compared))?
            .commit()?
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        None => Vec::new(),
    };
    Ok(FollowReport {
        file: a.file.display().to_string(),
        kind: c.kind,
        clipping: c.trace.clipped.clone(),
        duration_s: duration,
        scene: a
            .scene
            .as_ref()
            .map_or_else(|| "built-in default".into(), |p| p.display().to_string()),
        predictor: c.scene.breathing.predictor.clone(),
        goals: Goals::of(&figures),
        figures,
        replay_restarts: watch.origin_changes,
        frames_out,
        plots,
        run,
    })
}

/// The CSV of every frame placed on the recording's time axis, written atomically.
fn write_frames(path: &std::path::Path, drawn: &[Drawn]) -> anyhow::Result<String> {
    use std::io::Write;
    outfile::write_atomically(path, |w| {
        writeln!(w, "display_time_s,volume_ml")?;
        for d in drawn {
            if let Some(t) = d.recording_time_ns() {
                writeln!(w, "{:.6},{:.2}", t as f64 * 1e-9, d.volume_ml)?;
            }
        }
        Ok(())
    })
    .with_context(|| format!("--frames-out {}", path.display()))?;
    Ok(path.display().to_string())
}

fn panels(trace: &Trace, drawn: &[Drawn], compared: &[Compared]) -> Vec<Panel> {
    let first_t = trace.samples.first().map_or(0, |s| s.t_ns);
    let end = compared.last().map_or(0.0, |c| c.0 as f64 * 1e-9);
    let secs = |t: u64| t as f64 * 1e-9;
    // The not-following marks above the breaths, clear of the legend.
    let top = 1.1
        * trace
            .truth_ml
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
    let line = |label: &str, points, color, markers| Series {
        label: label.into(),
        points,
        color,
        markers,
    };
    // A line per stretch the signal drove (none drawn across a loss); one legend entry per kind.
    let runs = |label: &str, from: f64, g: fn(&Compared) -> f64, color| -> Vec<Series> {
        let mut runs: Vec<Vec<(f64, f64)>> = Vec::new();
        let mut last = f64::NEG_INFINITY;
        for c in compared.iter().filter(|c| secs(c.0) >= from) {
            if runs.is_empty() || secs(c.0) - last > 0.25 {
                runs.push(Vec::new());
            }
            last = secs(c.0);
            runs.last_mut().expect("pushed").push((secs(c.0), g(c)));
        }
        runs.into_iter()
            .enumerate()
            .map(|(i, points)| line(if i == 0 { label } else { "" }, points, color, false))
            .collect()
    };
    let panel = |title: String, from: f64| {
        let recording: Vec<(f64, f64)> = trace
            .samples
            .iter()
            .zip(&trace.truth_ml)
            .map(|(s, &v)| (secs(s.t_ns - first_t), v))
            .filter(|p| p.0 >= from && p.0 <= end.max(from) && p.1.is_finite())
            .collect();
        let not_following: Vec<(f64, f64)> = drawn
            .iter()
            .filter(|d| d.flags & report_flags::SIGNAL_FOLLOWING == 0)
            .filter_map(|d| d.recording_time_ns())
            .map(secs)
            .filter(|&t| t >= from && t <= end.max(from))
            .map(|t| (t, top))
            .collect();
        Panel {
            title,
            x_label: "display time from the recording's first sample, s".into(),
            y_label: "volume above end-expiration, ml".into(),
            series: [
                vec![line("recording (hindsight)", recording, DATA, false)],
                runs("drawn, predicted", from, |c| c.1, INHALE),
                runs("drawn, not predicted (same run)", from, |c| c.2, EXHALE),
                vec![line(
                    "the signal did not drive (calibrating, lost)",
                    not_following,
                    plotters::style::RGBColor(200, 40, 40),
                    true,
                )],
            ]
            .into_iter()
            .flatten()
            .collect(),
        }
    };
    vec![
        panel("every frame drawn, live".into(), 0.0),
        panel("the last 20 s".into(), (end - 20.0).max(0.0)),
    ]
}

/// The RMS line of the text report, or why there is none (no frame compared: the figures would be
/// NaN).
fn rms_line(f: &Figures) -> String {
    if f.frames_compared == 0 {
        return format!(
            "RMS error at display time: none — no drawn frame was compared with the recording \
             (following {}, calibrating {}, lost {}): too few breaths to calibrate on before the \
             run ended, or the signal never drove the lungs",
            f.frames_following, f.frames_calibrating, f.frames_lost
        );
    }
    format!(
        "RMS error at display time: {:.1} ml = {:.2} % of tidal ({:.0} ml) with prediction, {:.1} \
         ml = {:.2} % without ({} frames compared)",
        f.rms_error_ml,
        f.rms_error_percent_of_tidal,
        f.tidal_ml,
        f.rms_error_ml_without_prediction,
        f.rms_error_percent_of_tidal_without_prediction,
        f.frames_compared
    )
}

/// The report as text.
pub fn follow_text(r: &FollowReport) -> String {
    let f = &r.figures;
    let yes = |b: bool| if b { "met" } else { "NOT met" };
    let opt = |v: Option<f64>, unit: &str| v.map_or("-".to_string(), |x| format!("{x:.1} {unit}"));
    let mut s = format!(
        "{}: {} ({:.1} s), followed live by the scene {} (predictor {})\n\
         frames drawn {}, on the recording's clock {}: following {}, calibrating {}, lost {}; \
         first following at {}\n\
         recording played {:.1} s; breaths {} of {} followed (end-inspiration drawn within 1 s){}\n\
         {}\n\
         end-inspiration lag: {} with prediction, {} without\n\
         latency (newest input to display): predicted across {} ({}), measured median {}, p99 {}\n",
        r.file,
        r.kind,
        r.duration_s,
        r.scene,
        r.predictor,
        f.frames_drawn,
        f.frames_on_recording,
        f.frames_following,
        f.frames_calibrating,
        f.frames_lost,
        opt(f.first_following_s, "s"),
        f.recording_played_s,
        f.breaths_detected,
        f.breaths_in_recording,
        if f.breaths_missed_at_s.is_empty() {
            String::new()
        } else {
            format!(
                "; missed the end-inspiration at {} s",
                f.breaths_missed_at_s
                    .iter()
                    .map(|t| format!("{t:.1}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        },
        rms_line(f),
        opt(f.lag_ms, "ms"),
        opt(f.lag_ms_without_prediction, "ms"),
        opt(f.latency_ms_predicted_median, "ms"),
        if f.latency == "measured" {
            format!(
                "the pipeline's as measured; {:.0} ms before a measurement",
                f.latency_ms_configured
            )
        } else {
            "fixed: latency_ms".to_string()
        },
        opt(f.latency_ms_measured_median, "ms"),
        opt(f.latency_ms_measured_p99, "ms"),
    );
    if let Some(d) = &f.drop {
        s.push_str(&format!(
            "signal cut at {:.1} s for {:.1} s: following again {} after (breath period {}); RMS \
             error over the breath after {}, later {}\n",
            d.at_s,
            d.for_s,
            opt(d.resync_s, "s"),
            opt(d.breath_period_s, "s"),
            opt(d.rms_error_percent_of_tidal_first_breath_after, "%"),
            opt(d.rms_error_percent_of_tidal_later, "%"),
        ));
    }
    let g = &r.goals;
    s.push_str(&format!(
        "goals: RMS <= 3 % {}; prediction >= 2x better {}; |lag| <= 20 ms {}; breaths >= 98 % {}{}\n",
        yes(g.rms_within_3_percent),
        yes(g.prediction_halves_the_error),
        yes(g.lag_within_20_ms),
        yes(g.breaths_98_percent),
        g.resync_within_one_breath
            .map_or(String::new(), |b| format!("; in step within a breath after the cut {}", yes(b))),
    ));
    s.push_str(&format!(
        "run: {:.1} fps, {} deadline misses{}\n",
        r.run.fps,
        r.run.deadline_misses,
        if r.replay_restarts > 0 {
            format!(
                "; the bridge restarted and replayed the recording from its start {} time(s)",
                r.replay_restarts
            )
        } else {
            String::new()
        }
    ));
    if let Some(c) = &r.clipping {
        s.push_str(&format!("WARNING: {}\n", c.describe()));
    }
    for p in r.frames_out.iter().chain(&r.plots) {
        s.push_str(&format!("wrote {p}\n"));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::HopStamps;
    use lung_model::breathing::SignalSample;
    use lung_model::scene::LatencyChoice;

    /// The latency the test runs predicted across: a fixed 50 ms.
    const FIXED_50: (LatencyChoice, u64) = (LatencyChoice::Fixed, 50 * MS);

    const MS: u64 = 1_000_000;
    /// Where the bridge's replay began on the host clock in these tests.
    const ORIGIN: u64 = 50_000 * MS;

    /// 60 s of 4 s breaths (1.5 s in, 2.5 s out), 500 ml, sampled at 25 Hz from t = 1 s.
    fn trace() -> Trace {
        let volume = |t: f64| {
            let p = t % 4.0;
            if p < 1.5 {
                250.0 * (1.0 - (std::f64::consts::PI * p / 1.5).cos())
            } else {
                250.0 * (1.0 + (std::f64::consts::PI * (p - 1.5) / 2.5).cos())
            }
        };
        let first = lung_model::breathing::TRACE_START_NS;
        let samples: Vec<SignalSample> = (0..1500u64)
            .map(|k| SignalSample {
                t_ns: first + k * 40 * MS,
                value: volume(k as f64 * 0.04),
                valid: true,
            })
            .collect();
        Trace {
            truth_ml: samples.iter().map(|s| s.value).collect(),
            samples,
            breaths: 15,
            end_inspiration_ns: (0..15u64)
                .map(|b| first + b * 4000 * MS + 1500 * MS)
                .collect(),
            tidal_ml: 500.0,
            rate_hz: 25.0,
            calibration: Calibration::Volume,
            breath_period_s: None,
            inspiration_fraction: Some(0.375),
            clipped: None,
        }
    }

    /// Frames every 1/60 s shown `shown_after` after the engine's newest input, following from
    /// `from_s`, the engine predicting perfectly and its unpredicted volume `hold` late; drawn as
    /// 2400 ml + 0.9 × the followed volume; the signal lost in `lost`.
    fn run(
        tr: &Trace,
        from_s: f64,
        hold_ns: u64,
        lost: Option<(f64, f64)>,
    ) -> (Vec<Drawn>, HashMap<u64, (SignalFollowed, u32)>) {
        let at = |t_ns: u64| tr.truth_at(tr.samples[0].t_ns + t_ns).unwrap_or(0.0);
        let (mut drawn, mut engine) = (Vec::new(), HashMap::new());
        for tick in 1..3540u64 {
            let t = tick * 16_666_667;
            let secs = t as f64 * 1e-9;
            let display = ORIGIN + t;
            let mut flags = 0;
            if lost.is_some_and(|(a, b)| secs >= a && secs < b) {
                flags |= report_flags::SIGNAL_LOST;
            } else if secs >= from_s {
                flags |= report_flags::SIGNAL_FOLLOWING;
            }
            let (p, h) = (at(t), at(t.saturating_sub(hold_ns)));
            let r = FrameReport {
                engine_tick: tick,
                flags,
                volume_ml: [(1200.0 + 0.45 * p) as f32, (1200.0 + 0.45 * p) as f32],
                gpu_done_ns: display,
                stamps: HopStamps {
                    renderer_submit_ns: display - 2 * MS,
                    ..Default::default()
                },
                ..Default::default()
            };
            drawn.push(Drawn::of(&r, ORIGIN));
            let s = SignalFollowed {
                display_ns: display + 10 * MS,
                volume_ml: p as f32,
                unpredicted_ml: h as f32,
                latency_ns: 50 * MS,
                ..Default::default()
            };
            engine.insert(tick, (s, 0));
        }
        (drawn, engine)
    }

    #[test]
    fn a_perfect_prediction_scores_zero_and_the_held_sample_scores_its_lag() {
        let tr = trace();
        let (drawn, engine) = run(&tr, 8.0, 100 * MS, None);
        let (f, compared) = figures(&tr, &drawn, &engine, FIXED_50, None);
        assert_eq!(f.frames_drawn, drawn.len());
        assert_eq!(f.frames_on_recording, drawn.len());
        assert!(
            f.frames_calibrating > 400 && f.frames_following > 2500,
            "{f:?}"
        );
        assert_eq!(f.frames_compared, compared.len());
        // f32 round-off only.
        assert!(f.rms_error_ml < 0.05, "{f:?}");
        // 100 ms behind on a 500 ml breath rising over 1.5 s: tens of ml.
        assert!(
            f.rms_error_ml_without_prediction > 20.0 && f.rms_error_ml_without_prediction < 80.0,
            "{f:?}"
        );
        let lag = f.lag_ms.unwrap();
        assert!(lag.abs() < 20.0, "predicted lag {lag}");
        let hold = f.lag_ms_without_prediction.unwrap();
        assert!((hold - 100.0).abs() < 20.0, "held sample's lag {hold}");
        // The breaths of the part played: the first two fell in the calibration.
        assert_eq!(f.breaths_in_recording, 15);
        assert_eq!(f.breaths_detected, 13, "{f:?}");
        // ... and the report says which: the two before the signal first drove the lungs.
        assert_eq!(f.breaths_missed_at_s.len(), 2, "{f:?}");
        let first = f.first_following_s.unwrap();
        assert!(f.breaths_missed_at_s.iter().all(|&t| t < first), "{f:?}");
        // Newest input = display_ns − 50 ms = shown − 40 ms.
        assert!((f.latency_ms_measured_median.unwrap() - 40.0).abs() < 0.01);
        // ... whatever the horizon each engine frame says it predicted across (here 50 ms).
        assert_eq!(f.latency_ms_predicted_median, Some(50.0));
        assert_eq!(f.latency, "fixed");
        assert!(f.drawn_vs_followed_rms_ml.unwrap() < 0.01);
        let g = Goals::of(&f);
        assert!(g.rms_within_3_percent && g.prediction_halves_the_error && g.lag_within_20_ms);
        assert!(!g.breaths_98_percent, "13 of 15 is under 98 %");
        assert_eq!(g.resync_within_one_breath, None);
    }

    #[test]
    fn a_loss_is_timed_from_the_cut_to_the_first_frame_the_signal_drives_again() {
        let tr = trace();
        let (drawn, engine) = run(&tr, 8.0, 0, Some((20.0, 26.5)));
        let (f, _) = figures(&tr, &drawn, &engine, FIXED_50, Some((20.0, 5.0)));
        let d = f.drop.clone().unwrap();
        assert!((d.resync_s.unwrap() - 1.5).abs() < 0.02, "{d:?}");
        assert!((d.breath_period_s.unwrap() - 4.0).abs() < 1e-9);
        assert!(d.driven_again_within_one_breath && d.in_step_within_one_breath);
        assert!(d.rms_error_percent_of_tidal_first_breath_after.unwrap() < 0.01);
        assert!(f.frames_lost > 350, "{f:?}");
        // A cut the lungs never recover from.
        let (drawn, engine) = run(&tr, 8.0, 0, Some((20.0, 99.0)));
        let (f, _) = figures(&tr, &drawn, &engine, FIXED_50, Some((20.0, 5.0)));
        assert_eq!(f.drop.as_ref().unwrap().resync_s, None);
        assert_eq!(Goals::of(&f).resync_within_one_breath, Some(false));
    }

    #[test]
    fn frames_without_a_clock_or_an_engine_frame_are_counted_not_compared() {
        let tr = trace();
        let (mut drawn, mut engine) = run(&tr, 8.0, 0, None);
        for d in drawn.iter_mut().take(100) {
            d.origin_ns = 0;
        }
        for tick in 1000..1100 {
            engine.remove(&tick);
        }
        let (f, _) = figures(&tr, &drawn, &engine, FIXED_50, None);
        assert_eq!(f.frames_on_recording, drawn.len() - 100);
        assert_eq!(f.frames_without_engine_frame, 100);
        // Nothing followed: every figure says so, none is a made-up number.
        let (f, c) = figures(&tr, &drawn[..200], &engine, FIXED_50, None);
        assert!(c.is_empty() && f.rms_error_ml.is_nan() && f.lag_ms.is_none());
        assert_eq!(f.breaths_detected, 0);
        // …and the text says why there is no error figure rather than printing NaN.
        let line = rms_line(&f);
        assert!(
            line.contains("none — no drawn frame was compared") && !line.contains("NaN"),
            "{line}"
        );
        let g = Goals::of(&f);
        assert!(!g.rms_within_3_percent && !g.lag_within_20_ms && !g.breaths_98_percent);
    }

    #[test]
    fn the_frames_csv_is_the_issues_two_columns_on_the_recordings_clock() {
        let tr = trace();
        let (mut drawn, _) = run(&tr, 8.0, 0, None);
        drawn.truncate(5);
        drawn[0].origin_ns = 0;
        let dir = std::env::temp_dir().join(format!("lungdyn-follow-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("frames.csv");
        write_frames(&p, &drawn).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "display_time_s,volume_ml");
        assert_eq!(
            lines.len(),
            5,
            "the frame with no clock is left out: {text}"
        );
        assert!(lines[1].starts_with("0.033333,2400."), "{text}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_display_time_is_the_present_else_the_gpu_done_else_the_submit() {
        let mut r = FrameReport::default();
        r.stamps.renderer_submit_ns = 100;
        assert_eq!(Drawn::of(&r, 1).display_ns, 100);
        r.gpu_done_ns = 150;
        assert_eq!(Drawn::of(&r, 1).display_ns, 150);
        r.present_ns = 170;
        assert_eq!(Drawn::of(&r, 1).display_ns, 170);
        // A stamp before the submit is not a display time.
        r.present_ns = 50;
        assert_eq!(Drawn::of(&r, 1).display_ns, 150);
        assert_eq!(Drawn::of(&r, 0).recording_time_ns(), None);
        assert_eq!(Drawn::of(&r, 200).recording_time_ns(), None);
        assert_eq!(Drawn::of(&r, 100).recording_time_ns(), Some(50));
    }
}
