//! Issue 35's measurement on one file: a recording (a ventilator's, or one respiratory signal)
//! read as a [`Trace`], then replayed at each latency with every predictor beside "none", and the
//! verdict's predictor held against the goal (`lungdyn breathing check` prints it).

use std::path::Path;

use super::evaluate::{evaluate, EvalOptions, Evaluation, Trace};
use super::follow::{Calibration, FollowerConfig};
use super::predict::PredictorKind;
use super::trace::{looks_like_trace, parse_trace, SignalUnit, TraceError, TraceFormat};
use crate::plausible;
use crate::recording::{checks, classify, parse_recording, SegmentOptions};

/// The goal issue 35 sets: RMS error at display time ≤ 3 % of the tidal volume with prediction…
pub const GOAL_PERCENT_OF_TIDAL: f64 = 3.0;
/// …and at least this many times lower than without.
pub const GOAL_IMPROVEMENT: f64 = 2.0;

/// One latency's verdict.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GoalRow {
    /// Latency, ms.
    pub latency_ms: f64,
    /// With prediction, % of tidal.
    pub percent_of_tidal: f64,
    /// Without, % of tidal.
    pub percent_of_tidal_without_prediction: f64,
    /// Without ÷ with.
    pub improvement: f64,
    /// Both goals met.
    pub met: bool,
}

/// A file read as a respiratory signal.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadTrace {
    /// The live signal and its hindsight volume.
    pub trace: Trace,
    /// What the file was read as, for a person.
    pub kind: String,
    /// The unit of the trace's samples (ml for a ventilator recording's integrated flow).
    pub unit: SignalUnit,
}

/// A file's bytes as a trace, and what it was read as. A one-signal trace (RPM `.vxp`, a CSV of one
/// signal) is calibrated in hindsight by `calibration` (the scene's tidal volume, or a spirometry
/// calibration's gain: [`Trace::from_signal`]); a ventilator recording is checked for its
/// units and its flow's sign first (a recording in the wrong unit would be "followed" perfectly
/// into nonsense), and its flow integrated.
pub fn read_trace_or_recording(
    path: &Path,
    bytes: &[u8],
    calibration: Calibration,
) -> Result<ReadTrace, TraceError> {
    let whole = |message: String| TraceError::Parse {
        path: path.to_path_buf(),
        line: 0,
        message,
    };
    let at_line = |(line, message): (u64, String)| TraceError::Parse {
        path: path.to_path_buf(),
        line,
        message,
    };
    if looks_like_trace(bytes) {
        let signal = parse_trace(bytes).map_err(at_line)?;
        let kind = format!(
            "{} trace of {} ({} invalid samples{})",
            match signal.format {
                TraceFormat::Vxp => "Varian RPM",
                TraceFormat::Csv => "CSV",
            },
            signal.unit.symbol(),
            signal.invalid,
            if signal.format == TraceFormat::Vxp {
                format!(", {} flagged non-periodic", signal.non_periodic)
            } else {
                String::new()
            }
        );
        let trace = Trace::from_signal(&signal, calibration).ok_or_else(|| {
            whole(
                "fewer than two end-expirations found: no breathing to follow in this signal"
                    .into(),
            )
        })?;
        plausible(&trace, signal.unit).map_err(whole)?;
        return Ok(ReadTrace {
            trace,
            kind,
            unit: signal.unit,
        });
    }
    let rec = parse_recording(bytes).map_err(at_line)?;
    let characters = classify::characterise_all(&rec, &SegmentOptions::default());
    checks::check_plausible(&rec, &characters.iter().collect::<Vec<_>>())
        .map_err(|e| whole(e.to_string()))?;
    let trace = Trace::from_recording(&rec).ok_or_else(|| {
        whole(
            "no complete breath (inspiration and a whole expiration): nothing to follow or \
             compare with"
                .into(),
        )
    })?;
    let kind = format!(
        "ventilator recording ({}), flow integrated",
        rec.format.describe()
    );
    Ok(ReadTrace {
        trace,
        kind,
        unit: SignalUnit::Ml,
    })
}

/// How far a trace's mean calibrated breath may lie from the tidal volume an amplitude's automatic
/// calibration makes its median breath (×¼…×4): beyond, its breaths differ too much in size to be
/// one patient's breathing at one gain.
pub const AUTO_MEAN_OVER_MEDIAN: std::ops::RangeInclusive<f64> = 0.25..=4.0;

/// A one-signal trace that is breathing: its regular breaths' median period within the project's
/// breathing rates ([`plausible::BREATHS_PER_MIN`]) and, calibrated, its mean breath within its
/// tidal volumes ([`plausible::TIDAL_VOLUME_ML`]; with an amplitude's automatic calibration, within
/// [`AUTO_MEAN_OVER_MEDIAN`] of the volume it is calibrated to). Figures computed on a 3 Hz
/// vibration or on a volume 1000× off look like any others, so such a trace is refused with what
/// looks wrong.
pub fn plausible(trace: &Trace, unit: SignalUnit) -> Result<(), String> {
    let (rate, tv) = (plausible::BREATHS_PER_MIN, plausible::TIDAL_VOLUME_ML);
    if let Some(p) = trace.breath_period_s.filter(|p| *p > 0.0) {
        let per_min = 60.0 / p;
        if !rate.contains(per_min) {
            return Err(format!(
                "its regular breaths come every {p:.2} s (median): {per_min:.1} a minute, where \
                 breathing is {}–{} (breath-holds and pauses are not counted as breaths) — is this \
                 a respiratory signal, and is its time column in the unit it names?",
                rate.lo, rate.hi
            ));
        }
    }
    let tidal = trace.tidal_ml;
    if !tidal.is_finite() {
        return Err(
            "no breath's volume could be computed: its values are too large or too small to \
             calibrate (rescale them), or invalid between its end-expirations"
                .into(),
        );
    }
    let why = match (unit, trace.calibration) {
        (_, Calibration::Auto { tidal_ml }) => {
            let ratio = tidal / tidal_ml;
            if AUTO_MEAN_OVER_MEDIAN.contains(&ratio) {
                return Ok(());
            }
            return Err(format!(
                "its median breath is calibrated to {} ml and its breaths average {} ml ({}×): \
                 they differ too much in size to be one patient's breathing at one gain (is the \
                 device's gain changing?)",
                plausible::compact(tidal_ml),
                plausible::compact(tidal),
                plausible::compact(ratio)
            ));
        }
        _ if tv.contains(tidal) => return Ok(()),
        (SignalUnit::Ml, _) | (_, Calibration::Volume) => {
            "is the volume column's unit right? ml under volume_L reads 1000× too large, litres \
             under volume_ml 1000× too small"
                .to_string()
        }
        (_, Calibration::Fixed { ml_per_unit }) => format!(
            "is the spirometry calibration ({} ml per {}) for this signal's unit?",
            plausible::compact(ml_per_unit),
            unit.symbol()
        ),
    };
    Err(format!(
        "its breaths average {} ml, where a tidal volume is {}–{} ml: {why}",
        plausible::compact(tidal),
        tv.lo,
        tv.hi
    ))
}

/// The predictors replayed at `latency_ms`: `chosen` first, then the previous cycle's, the
/// autoregression, the line and none (each once); the previous-cycle predictor compares its
/// candidates at the latency replayed.
pub fn predictors_at(chosen: PredictorKind, latency_ms: f64) -> Vec<PredictorKind> {
    let at = |k: PredictorKind| match k {
        PredictorKind::Cycle { .. } => PredictorKind::Cycle {
            horizon_ms: latency_ms.round() as u32,
        },
        k => k,
    };
    let mut kinds = vec![at(chosen)];
    for k in [
        PredictorKind::Cycle { horizon_ms: 0 },
        PredictorKind::DEFAULT,
        PredictorKind::LINE,
        PredictorKind::Hold,
    ] {
        if !kinds.contains(&at(k)) {
            kinds.push(at(k));
        }
    }
    kinds
}

/// The replay's options: shown `latency_ms` after capture at `frame_rate_hz`, followed with
/// `predictor` at the trace's own rate and calibration.
pub fn replay_options(
    trace: &Trace,
    latency_ms: f64,
    frame_rate_hz: f64,
    predictor: PredictorKind,
) -> EvalOptions {
    let mut follower = FollowerConfig::at_rate(trace.rate_hz, trace.calibration);
    follower.predictor = predictor;
    EvalOptions {
        latency_ns: (latency_ms * 1e6).round() as u64,
        frame_period_ns: (1e9 / frame_rate_hz).round() as u64,
        follower,
    }
}

/// Every predictor ([`predictors_at`]) at every latency, and per latency the verdict on `chosen`.
pub fn sweep(
    trace: &Trace,
    chosen: PredictorKind,
    latencies_ms: &[f64],
    frame_rate_hz: f64,
) -> (Vec<Evaluation>, Vec<GoalRow>) {
    let mut results = Vec::new();
    let mut goal = Vec::new();
    for &l in latencies_ms {
        for (i, k) in predictors_at(chosen, l).into_iter().enumerate() {
            let e = evaluate(trace, &replay_options(trace, l, frame_rate_hz, k));
            if i == 0 {
                let improvement = e.rms_error_ml_without_prediction / e.rms_error_ml;
                goal.push(GoalRow {
                    latency_ms: l,
                    percent_of_tidal: e.rms_error_percent_of_tidal,
                    percent_of_tidal_without_prediction: e
                        .rms_error_percent_of_tidal_without_prediction,
                    improvement,
                    met: e.rms_error_percent_of_tidal <= GOAL_PERCENT_OF_TIDAL
                        && improvement >= GOAL_IMPROVEMENT,
                });
            }
            results.push(e);
        }
    }
    (results, goal)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 30 s of `scale × 4·(1 − cos)` breaths every `period_s` at 25 Hz, under `column`.
    fn sine_csv(column: &str, scale: f64, period_s: f64) -> String {
        let mut csv = format!("time_s,{column}\n");
        for k in 0..750 {
            let t = k as f64 * 0.04;
            let v = scale * 4.0 * (1.0 - (std::f64::consts::TAU * t / period_s).cos());
            csv += &format!("{t:.3},{v:.5}\n");
        }
        csv
    }

    /// 60 s of breaths every 3 s at 25 Hz whose depths differ (0.6–1.4 × 4 mm, a golden-ratio
    /// sequence), each value through `f`.
    fn unequal_breaths(f: impl Fn(f64) -> f64) -> String {
        breaths_varying(0.8, f)
    }

    /// As [`unequal_breaths`], the depths (1 − `vary`/2 … 1 + `vary`/2) × 4 mm.
    fn breaths_varying(vary: f64, f: impl Fn(f64) -> f64) -> String {
        let mut csv = String::from("time_s,amplitude_mm\n");
        for k in 0..1500 {
            let t = k as f64 * 0.04;
            let b = (t / 3.0).floor();
            let depth = 4.0 * (1.0 - vary / 2.0 + vary * (b * 0.618_034).fract());
            let v = depth * 0.5 * (1.0 - (std::f64::consts::TAU * t / 3.0).cos());
            csv += &format!("{t:.3},{:.5}\n", f(v));
        }
        csv
    }

    /// Breaths of unequal depth that all end at one value were cut there (the BioSPPy belt's top):
    /// said, at the top or the bottom; the same breaths uncut, and breaths of equal depth (which
    /// end together by themselves), are not called clipped.
    #[test]
    fn breaths_cut_at_the_sensors_range_are_said_and_others_are_not() {
        let path = Path::new("t.csv");
        let auto = Calibration::Auto { tidal_ml: 500.0 };
        let clipped = |csv: String| {
            read_trace_or_recording(path, csv.as_bytes(), auto)
                .unwrap()
                .trace
                .clipped
        };
        let top = clipped(unequal_breaths(|v| v.min(4.8))).expect("cut at 4.8 mm");
        assert!(top.at_top && top.value == 4.8, "{top:?}");
        assert!(top.at_s.len() >= 3 && top.at_s.len() < top.turns, "{top:?}");
        let said = top.describe();
        assert!(
            said.contains("clipped at 4.8 mm, its highest")
                && said.contains("marker's tracked range")
                && said.contains("shallower"),
            "{said}"
        );
        assert_eq!(super::super::evaluate::significant(0.1 + 0.2, 5), "0.3");
        assert_eq!(super::super::evaluate::significant(4087.68, 5), "4087.7");
        assert_eq!(clipped(unequal_breaths(|v| v)), None);
        // The mirror image (inspiration falling), cut at its lowest value.
        let bottom = clipped(unequal_breaths(|v| (6.0 - v).max(1.2))).expect("cut at 1.2 mm");
        assert!(!bottom.at_top && bottom.value == 1.2, "{bottom:?}");
        assert_eq!(clipped(sine_csv("amplitude_mm", 1.0, 4.0)), None);
        // Breaths within 2 % of each other: several end within 0.5 % of the highest by
        // themselves, and the others as close: steady breathing, not a cut.
        assert_eq!(clipped(breaths_varying(0.02, |v| v)), None);
    }

    /// A sample flagged invalid has no hindsight volume; the frames beside it are still compared
    /// with the volume across it (every other sample invalid: as many frames compared as with
    /// every sample valid, within a few), as the live follower's grid bridges it.
    #[test]
    fn frames_beside_invalid_samples_are_still_compared() {
        let path = Path::new("t.csv");
        let auto = Calibration::Auto { tidal_ml: 500.0 };
        let valid = sine_csv("amplitude_mm", 1.0, 4.0);
        let alternate: String = valid
            .lines()
            .enumerate()
            .map(|(i, l)| match i {
                0 => format!("{l},valid\n"),
                _ => format!("{l},{}\n", i % 2),
            })
            .collect();
        let compared = |csv: &str| {
            let t = read_trace_or_recording(path, csv.as_bytes(), auto)
                .unwrap()
                .trace;
            evaluate(&t, &replay_options(&t, 50.0, 60.0, PredictorKind::Hold)).frames_compared
        };
        let (all, half) = (compared(&valid), compared(&alternate));
        assert!(all > 800, "{all}");
        assert!(half + 60 >= all, "{half} of {all}");
        // A slow source's neighbours are 500 ms apart, all valid: every frame between them is
        // compared (the bridge's limit is for stepping over invalid samples only).
        let mut slow = String::from("time_s,amplitude_mm\n");
        for k in 0..60 {
            let t = k as f64 * 0.5;
            let v = 4.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos());
            slow += &format!("{t:.3},{v:.5}\n");
        }
        let slow = compared(&slow);
        assert!(slow + 90 >= all, "{slow} of {all} at 2 Hz");
    }

    /// What is not breathing is refused naming what looks wrong, not measured: a vibration, breaths
    /// a minute long, a volume 1000× off either way, a spirometry gain for another unit.
    #[test]
    fn a_trace_that_is_not_breathing_is_refused_with_what_looks_wrong() {
        let path = Path::new("t.csv");
        let auto = Calibration::Auto { tidal_ml: 500.0 };
        let refused =
            |csv: String, c: Calibration| match read_trace_or_recording(path, csv.as_bytes(), c) {
                Ok(r) => panic!("accepted: {} ml", r.trace.tidal_ml),
                Err(e) => e.to_string(),
            };
        let fast = refused(sine_csv("amplitude_mm", 1.0, 0.25), auto);
        assert!(
            fast.contains("a minute, where breathing is 2–150")
                && fast.contains("respiratory signal"),
            "{fast}"
        );
        let mut slow = String::from("time_s,amplitude_mm\n");
        for k in 0..3000 {
            let t = k as f64 * 0.2;
            slow += &format!(
                "{t:.3},{:.5}\n",
                4.0 * (1.0 - (std::f64::consts::TAU * t / 40.0).cos())
            );
        }
        let slow = refused(slow, auto);
        assert!(slow.contains("1.5 a minute"), "{slow}");
        let litres = refused(sine_csv("volume_L", 50.0, 3.0), auto);
        assert!(
            litres.contains("average 399824.57 ml") && litres.contains("volume_L"),
            "{litres}"
        );
        let ml = refused(sine_csv("volume_ml", 0.05, 3.0), auto);
        assert!(
            ml.contains("average 0.4 ml") && ml.contains("1000× too small"),
            "{ml}"
        );
        let gain = refused(
            sine_csv("amplitude_mm", 1.0, 3.0),
            Calibration::Fixed { ml_per_unit: 1e-6 },
        );
        assert!(gain.contains("1e-6 ml per mm"), "{gain}");
        // An amplitude whose breaths grow a hundredfold over the trace: no one gain calibrates it.
        let mut growing = String::from("time_s,amplitude_mm\n");
        for k in 0..750 {
            let t = k as f64 * 0.04;
            let v = 10f64.powf(2.0 * t / 30.0) * (1.0 - (std::f64::consts::TAU * t / 3.0).cos());
            growing += &format!("{t:.3},{v:.5}\n");
        }
        let growing = refused(growing, auto);
        assert!(
            growing.contains("calibrated to 500 ml") && growing.contains("differ too much"),
            "{growing}"
        );
        // An infant's 30 ml breaths at 40 a minute, as a volume: breathing, accepted.
        read_trace_or_recording(path, sine_csv("volume_ml", 3.75, 1.5).as_bytes(), auto).unwrap();
        // Breathing at 20 a minute, 400 ml: accepted.
        read_trace_or_recording(path, sine_csv("volume_ml", 50.0, 3.0).as_bytes(), auto).unwrap();
    }

    /// A chest trace (mm) read as a recording to compare with: its hindsight volume is calibrated
    /// to the scene's tidal volume, or by a spirometry calibration's gain when there is one (as the
    /// live follower calibrates), and a volume trace in ml is taken as it is either way.
    #[test]
    fn a_one_signal_traces_reference_is_calibrated_as_the_follower_is() {
        let csv = sine_csv("amplitude_mm", 1.0, 3.0);
        let path = Path::new("chest.csv");
        let read = |c: Calibration| read_trace_or_recording(path, csv.as_bytes(), c).unwrap();
        let auto = read(Calibration::Auto { tidal_ml: 500.0 });
        assert!(
            (auto.trace.tidal_ml - 500.0).abs() < 5.0,
            "{}",
            auto.trace.tidal_ml
        );
        let spiro = read(Calibration::Fixed { ml_per_unit: 60.0 });
        // 8 mm breaths at 60 ml/mm.
        assert!(
            (spiro.trace.tidal_ml - 480.0).abs() < 5.0,
            "{}",
            spiro.trace.tidal_ml
        );
        assert_eq!(
            spiro.trace.calibration,
            Calibration::Fixed { ml_per_unit: 60.0 }
        );
        let ml = sine_csv("volume_ml", 50.0, 3.0);
        let as_is = read_trace_or_recording(
            path,
            ml.as_bytes(),
            Calibration::Fixed { ml_per_unit: 60.0 },
        )
        .unwrap();
        assert!(
            (as_is.trace.tidal_ml - 400.0).abs() < 5.0,
            "{}",
            as_is.trace.tidal_ml
        );
        assert_eq!(as_is.trace.calibration, Calibration::Volume);
    }
}
