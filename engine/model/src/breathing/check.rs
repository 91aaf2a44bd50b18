//! Issue 35's measurement on one file: a recording (a ventilator's, or one respiratory signal)
//! read as a [`Trace`], then replayed at each latency with every predictor beside "none", and the
//! verdict's predictor held against the goal (`lungdyn breathing check` prints it).

use std::path::Path;

use super::evaluate::{evaluate, EvalOptions, Evaluation, Trace};
use super::follow::{Calibration, FollowerConfig};
use super::predict::PredictorKind;
use super::trace::{looks_like_trace, parse_trace, SignalUnit, TraceError, TraceFormat};
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

    /// A chest trace (mm) read as a recording to compare with: its hindsight volume is calibrated
    /// to the scene's tidal volume, or by a spirometry calibration's gain when there is one (as the
    /// live follower calibrates), and a volume trace in ml is taken as it is either way.
    #[test]
    fn a_one_signal_traces_reference_is_calibrated_as_the_follower_is() {
        let mut csv = String::from("time_s,amplitude_mm\n");
        for k in 0..750 {
            let t = k as f64 * 0.04;
            let v = 4.0 * (1.0 - (std::f64::consts::TAU * t / 3.0).cos());
            csv += &format!("{t:.3},{v:.5}\n");
        }
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
        let ml = csv.replace("amplitude_mm", "volume_ml");
        let as_is = read_trace_or_recording(
            path,
            ml.as_bytes(),
            Calibration::Fixed { ml_per_unit: 60.0 },
        )
        .unwrap();
        assert!(
            (as_is.trace.tidal_ml - 8.0).abs() < 0.1,
            "{}",
            as_is.trace.tidal_ml
        );
        assert_eq!(as_is.trace.calibration, Calibration::Volume);
    }
}
