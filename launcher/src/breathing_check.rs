//! `lungdyn breathing check FILE`: a respiratory recording replayed as if it were the live signal,
//! through the follower the engine will use (calibration, breath detection, prediction to the
//! display time), against the recording's own hindsight volume — with every predictor beside
//! "none", at each latency asked (issue 35's measurement, offline; the arithmetic is
//! `lung_model::breathing::check`'s, the arguments, the plot and the table are here).

use std::path::PathBuf;

use lung_model::breathing::check::{
    predictors_at, read_trace_or_recording, replay_options, sweep, GoalRow, GOAL_IMPROVEMENT,
    GOAL_PERCENT_OF_TIDAL,
};
use lung_model::breathing::evaluate::{evaluate, frames, EvalOptions, Evaluation, Trace};
use lung_model::breathing::follow::{Calibration, SignalState};
use lung_model::breathing::predict::PredictorKind;
use serde::Serialize;

use crate::plot::{self, Panel, Series, DATA, EXHALE, INHALE};

/// Options of `lungdyn breathing check`.
#[derive(Debug, Clone, clap::Args)]
pub struct CheckArgs {
    /// A respiratory recording: a ventilator's (the formats `lungdyn pv recording` reads: a
    /// Puritan-Bennett 840 raw export, or a CSV naming time, flow and pressure with their units —
    /// its flow integrated from the first sample is the live signal, each breath's own integrated
    /// volume what the lungs should show), a Varian RPM export (.vxp: the marker block's
    /// excursion), or a CSV of one signal (time_s or time_ms, and amplitude_mm, amplitude_cm,
    /// amplitude_au, volume_ml or volume_L; optional valid 1/0; + = inspiration). A one-signal trace
    /// is compared with itself calibrated in hindsight (--tidal-ml).
    pub file: PathBuf,
    /// The tidal volume a one-signal trace's typical breath is calibrated to, ml (the scene's; a
    /// volume trace in ml is used as it is).
    #[arg(long, default_value_t = 500.0, value_name = "ML")]
    pub tidal_ml: f64,
    /// An amplitude's spirometry calibration, ml per mm (per au): the trace is followed from its
    /// first samples at this gain, and compared with itself at the same gain (the scene's
    /// [breathing] ml_per_unit; --tidal-ml is then not used).
    #[arg(long, value_name = "ML")]
    pub ml_per_unit: Option<f64>,
    /// Capture-to-display latencies to replay at, ms (what the sensor, bridge, engine and GPU add
    /// up to; `lungdyn latency` measures the pipeline's part).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "50,100,150",
        value_name = "MS"
    )]
    pub latency_ms: Vec<f64>,
    /// The predictor to report as "with prediction": cycle (the previous breath's course where it
    /// has lately predicted better than the autoregression, compared at the latency replayed),
    /// ar[:ORDER[:LAMBDA]], linear[:WINDOW] or none (every one is measured; this one is the
    /// verdict's).
    #[arg(long, default_value = "cycle", value_name = "NAME")]
    pub predictor: String,
    /// Frame rate of the replayed display, Hz.
    #[arg(long, default_value_t = 60.0, value_name = "HZ")]
    pub frame_rate_hz: f64,
    /// Plot the recording's volume, the volume drawn with and without prediction at the first
    /// latency, and the follower's state (PNG; an SVG is written beside it).
    #[arg(long, value_name = "PNG")]
    pub plot: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input_args: crate::input_args::InputArgs,
}

/// What `lungdyn breathing check` reports.
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    /// The file.
    pub file: String,
    /// What was read.
    pub kind: String,
    /// Samples read.
    pub samples: usize,
    /// Sample rate, Hz.
    pub sample_rate_hz: f64,
    /// Length, s.
    pub duration_s: f64,
    /// Median fraction of a breath spent inspiring (over 0.5: is the sign right?).
    pub inspiration_fraction: Option<f64>,
    /// Complete breaths (the recording's own segmentation).
    pub breaths_in_recording: usize,
    /// Their mean tidal volume, ml.
    pub tidal_ml: f64,
    /// Frames shown per second in the replay.
    pub frame_rate_hz: f64,
    /// The verdict's predictor.
    pub predictor: String,
    /// Every predictor at every latency (the verdict's predictor first at each latency).
    pub results: Vec<Evaluation>,
    /// Per latency: whether the verdict's predictor met issue 35's goal (≤ 3 % and ≥ 2× lower).
    pub goal: Vec<GoalRow>,
    /// RMS error at no latency and without prediction, % of tidal: the live calibration (baseline
    /// and gain from the breaths so far) against the hindsight one (from the whole recording), plus
    /// the newest sample's age — mostly what no prediction can remove. Near 0 on a regular signal;
    /// a belt's irregular breaths raise it. `None` when no frame was compared.
    pub calibration_floor_percent_of_tidal: Option<f64>,
    /// Breaths of unequal depth turning at the signal's highest (or lowest) value: cut by the
    /// sensor's range (`None`: none seen; a ventilator recording is not checked).
    pub clipping: Option<lung_model::breathing::evaluate::Clipping>,
    /// Plots written.
    pub plots: Vec<String>,
}

fn check_args(a: &CheckArgs) -> anyhow::Result<PredictorKind> {
    if a.latency_ms.is_empty() {
        anyhow::bail!("--latency-ms: give at least one latency, e.g. --latency-ms 100");
    }
    for &l in &a.latency_ms {
        if !(0.0..=2000.0).contains(&l) {
            anyhow::bail!(
                "--latency-ms {l}: a capture-to-display latency is 0…2000 ms (the pipeline's is tens of ms)"
            );
        }
    }
    if !(a.frame_rate_hz.is_finite() && (1.0..=1000.0).contains(&a.frame_rate_hz)) {
        anyhow::bail!(
            "--frame-rate-hz {}: 1…1000 Hz (an HMD shows 60–120)",
            a.frame_rate_hz
        );
    }
    if !(a.tidal_ml.is_finite() && (50.0..=3000.0).contains(&a.tidal_ml)) {
        anyhow::bail!(
            "--tidal-ml {}: an adult's tidal volume is 300–800 ml, a child's from 50 (50…3000 accepted)",
            a.tidal_ml
        );
    }
    if let Some(g) = a.ml_per_unit {
        if let Err(why) = lung_model::scene::check_ml_per_unit(g) {
            anyhow::bail!("--ml-per-unit {}: {why}", lung_model::plausible::compact(g));
        }
    }
    if let Some(p) = &a.plot {
        plot::check_path(p)?;
    }
    PredictorKind::parse(&a.predictor).map_err(|e| anyhow::anyhow!("--predictor: {e}"))
}

/// Run `lungdyn breathing check`.
pub fn check(a: &CheckArgs) -> anyhow::Result<CheckReport> {
    let chosen = check_args(a)?;
    let bytes = lung_model::input::read_bounded(
        &a.file,
        a.input_args.limits(lung_model::input::ReadLimits::TABLE),
    )?;
    let calibration = Calibration::amplitude(a.ml_per_unit, a.tidal_ml);
    let read = read_trace_or_recording(&a.file, &bytes, calibration)?;
    let (trace, kind) = (read.trace, read.kind);
    let (results, goal) = sweep(&trace, chosen, &a.latency_ms, a.frame_rate_hz);
    if let Some(e) = results.iter().find(|e| e.frames_compared == 0) {
        anyhow::bail!(
            "{}: at {} ms no drawn frame could be compared with the recording ({} frames: {} \
             calibrating, {} lost) — the follower never followed it: too few regular breaths, or \
             too many invalid samples, to calibrate on",
            a.file.display(),
            e.latency_ms,
            e.frames,
            e.frames_calibrating,
            e.frames_lost
        );
    }
    let plots = match &a.plot {
        Some(png) => {
            let first = a.latency_ms[0];
            let shown = replay_options(
                &trace,
                first,
                a.frame_rate_hz,
                predictors_at(chosen, first)[0],
            );
            plot::render(png, &panels(&trace, &shown))?
                .commit()?
                .iter()
                .map(|p| p.display().to_string())
                .collect()
        }
        None => Vec::new(),
    };
    let floor = evaluate(
        &trace,
        &replay_options(&trace, 0.0, a.frame_rate_hz, PredictorKind::Hold),
    );
    let n = trace.samples.len();
    let span_ns = trace.samples[n - 1].t_ns - trace.samples[0].t_ns;
    Ok(CheckReport {
        file: a.file.display().to_string(),
        kind,
        samples: n,
        sample_rate_hz: trace.rate_hz,
        duration_s: span_ns as f64 * 1e-9,
        inspiration_fraction: trace.inspiration_fraction,
        clipping: trace.clipped.clone(),
        breaths_in_recording: trace.breaths,
        tidal_ml: trace.tidal_ml,
        frame_rate_hz: a.frame_rate_hz,
        predictor: match chosen {
            PredictorKind::Cycle { .. } => {
                "the best lately of previous cycle, autoregression and none, at the latency replayed".into()
            }
            k => k.describe(),
        },
        results,
        goal,
        calibration_floor_percent_of_tidal: (floor.frames_compared > 0)
            .then_some(floor.rms_error_percent_of_tidal),
        plots,
    })
}

fn panels(trace: &Trace, opts: &EvalOptions) -> Vec<Panel> {
    let f = frames(trace, opts);
    let end = f.last().map_or(0.0, |x| x.0);
    let ms = opts.latency_ns as f64 * 1e-6;
    // The whole trace, and its last 20 s close up (where breaths can be told apart).
    let panel = |title: String, from: f64| {
        let pick = |g: fn(&(f64, f64, f64, f64, SignalState)) -> f64| -> Vec<(f64, f64)> {
            f.iter()
                .filter(|x| x.0 >= from)
                .map(|x| (x.0, g(x)))
                .filter(|p| p.1.is_finite())
                .collect()
        };
        let line = |label: &str, points, color, markers| Series {
            label: label.into(),
            points,
            color,
            markers,
        };
        let not_following: Vec<(f64, f64)> = f
            .iter()
            .filter(|x| x.0 >= from && !matches!(x.4, SignalState::Following))
            .map(|x| (x.0, 0.0))
            .collect();
        Panel {
            title,
            x_label: "time from the first sample, s".into(),
            y_label: "volume above end-expiration, ml".into(),
            series: vec![
                line("recording (hindsight)", pick(|x| x.1), DATA, false),
                line("drawn, predicted", pick(|x| x.2), INHALE, false),
                line("drawn, not predicted", pick(|x| x.3), EXHALE, false),
                line(
                    "not following (calibrating, paused, lost)",
                    not_following,
                    plotters::style::RGBColor(200, 40, 40),
                    true,
                ),
            ],
        }
    };
    vec![
        panel(format!("shown {ms:.0} ms after capture, whole trace"), 0.0),
        panel("the last 20 s".into(), (end - 20.0).max(0.0)),
    ]
}

/// The report as a table.
pub fn check_text(r: &CheckReport) -> String {
    let mut s = format!(
        "{}: {}, {} samples at {:.1} Hz ({:.1} s), {} complete breaths, mean tidal volume {:.0} ml\n\
         replayed as the live signal, shown at {:.0} frames per second\n",
        r.file,
        r.kind,
        r.samples,
        r.sample_rate_hz,
        r.duration_s,
        r.breaths_in_recording,
        r.tidal_ml,
        r.frame_rate_hz
    );
    if let Some(c) = &r.clipping {
        s += &format!("WARNING: {}\n", c.describe());
    }
    if let Some(f) = r.inspiration_fraction {
        s += &format!("inspiration {:.0} % of a breath (median)", 100.0 * f);
        s += if f > 0.5 {
            ": LONGER than expiration — is + inspiration? (RPM's raw amplitude falls on inspiration; lungdyn negates it)\n"
        } else {
            "\n"
        };
    }
    s += "\nlatency   predictor                                             RMS ml  % tidal  lag ms  breaths matched  fell back\n";
    for e in &r.results {
        s += &format!(
            "{:>5.0} ms  {:<52} {:>7.1} {:>7.2}  {:>6}  {:>7}/{:<7}  {:>5}\n",
            e.latency_ms,
            e.predictor,
            e.rms_error_ml,
            e.rms_error_percent_of_tidal,
            e.lag_ms.map_or("-".into(), |l| format!("{l:.0}")),
            e.breaths_matched,
            e.breaths_in_recording,
            e.frames_fell_back,
        );
    }
    if let Some(e) = r.results.first() {
        s += &format!(
            "(each row's 'none' figure from the same run: {:.2} % of tidal at {:.0} ms; frames compared {}, calibrating {}, lost {})\n",
            e.rms_error_percent_of_tidal_without_prediction,
            e.latency_ms,
            e.frames_compared,
            e.frames_calibrating,
            e.frames_lost
        );
    }
    if let Some(floor) = r.calibration_floor_percent_of_tidal {
        s += &format!(
            "at 0 ms without prediction: {floor:.2} % of tidal — the live calibration (baseline and \
             gain from the breaths so far) against the hindsight one (the whole recording), and the \
             newest sample's age (half a sample period on average): prediction removes little of \
             this part{}\n",
            if floor > GOAL_PERCENT_OF_TIDAL {
                format!(
                    "; over the goal's {GOAL_PERCENT_OF_TIDAL} % by itself: irregular breaths or a \
                     drifting baseline (the plot shows where)"
                )
            } else {
                String::new()
            }
        );
    }
    s += &format!(
        "\ngoal (issue 35): RMS ≤ {GOAL_PERCENT_OF_TIDAL} % of tidal with prediction and ≥ {GOAL_IMPROVEMENT}× lower than without — {}:\n",
        r.predictor
    );
    for g in &r.goal {
        s += &format!(
            "{:>5.0} ms: {:.2} % against {:.2} % without ({}× lower): {}\n",
            g.latency_ms,
            g.percent_of_tidal,
            g.percent_of_tidal_without_prediction,
            if g.improvement > 1000.0 {
                "over 1000".to_string()
            } else {
                format!("{:.1}", g.improvement)
            },
            if g.met { "met" } else { "NOT met" }
        );
    }
    for p in &r.plots {
        s += &format!("wrote {p}\n");
    }
    s
}
