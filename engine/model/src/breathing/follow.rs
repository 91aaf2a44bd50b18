//! Samples in, the lungs' volume above FRC at a frame's display time out.
//!
//! [`Follower::push`] takes each sample as it arrives (invalid, non-finite, repeated and
//! out-of-order samples are counted and left out; a gap longer than the loss limit restarts the
//! grid and the predictor). [`Follower::volume_at`] gives, for a frame computed at `now` and shown at
//! `display`, the volume `gain · (ŝ(display) − baseline(display))` with ŝ the predicted signal and
//! the baseline the detector's end-expiration level with its drift; beside it the same volume with
//! the newest sample unpredicted (so every frame can report what prediction bought). The volume
//! is kept within −0.5…3 typical tidal volumes (a forced expiration below FRC, a sigh above it;
//! a wild sample is not drawn as a fold), and flagged when it was kept.

use super::detect::{Counts, Detector, Pause};
use super::grid::{Arrival, Grid};
use super::predict::{PredictorKind, SignalPredictor};
use super::{secs, SignalSample};

/// Lowest volume drawn, in typical tidal volumes below the end-expiration baseline.
pub const BELOW_BASELINE_TIDALS: f64 = 0.5;
/// Highest volume drawn, in typical tidal volumes above the baseline.
pub const ABOVE_BASELINE_TIDALS: f64 = 3.0;
/// Regular breaths before an amplitude's calibration ([`Calibration::Auto`]) is trusted. A signal
/// whose gain is known (a volume, a spirometry calibration) needs only its end-expiration baseline,
/// and is followed from its first samples: until its first end-expiration is found, the baseline
/// is the lowest value seen so far ([`super::detect::Detector::baseline_at`]), so a breath in
/// progress when the signal begins is drawn from where it was picked up (a recording that starts
/// at an end-expiration, as a ventilator's breath-aligned export does, exactly). The first
/// end-expiration found may lie above that lowest value (a breath that ends higher than it began:
/// its net volume, or a drift); the baseline moves onto it over [`FIRST_TROUGH_FADE_NS`] instead
/// of stepping. Not after a reconfiguration mid-stream, nor while the source's rate is unknown
/// ([`Follower::wait_for_first_end_expiration`]): a follower restarted mid-breath would take the
/// value it restarts at as its baseline.
pub const CALIBRATION_BREATHS: usize = 2;

/// Over how long the baseline moves from the lowest value seen onto the first end-expiration
/// found, when the signal was followed before it (half a second, as the engine's takeover blend).
pub const FIRST_TROUGH_FADE_NS: u64 = 500_000_000;

/// How the signal's unit becomes ml.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Calibration {
    /// The signal is a volume in ml already (a ventilator's or spirometer's).
    Volume,
    /// The typical breath is `tidal_ml` (the scene's tidal volume): the gain is refitted on every
    /// regular breath from the median of the last five amplitudes.
    Auto {
        /// Tidal volume, ml.
        tidal_ml: f64,
    },
    /// A spirometry calibration: ml per signal unit.
    Fixed {
        /// Gain, ml per unit.
        ml_per_unit: f64,
    },
}

impl Calibration {
    /// An amplitude's: a spirometry calibration's gain when there is one (`ml_per_unit`), else the
    /// gain that makes its typical breath `tidal_ml`.
    pub fn amplitude(ml_per_unit: Option<f64>, tidal_ml: f64) -> Self {
        match ml_per_unit {
            Some(ml_per_unit) => Calibration::Fixed { ml_per_unit },
            None => Calibration::Auto { tidal_ml },
        }
    }
}

/// A follower's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FollowerConfig {
    /// The source's sample period, ns (the grid's).
    pub period_ns: u64,
    /// No sample for this long: the signal is lost (and a longer gap restarts the grid).
    pub lost_after_ns: u64,
    /// The predictor.
    pub predictor: PredictorKind,
    /// The calibration.
    pub calibration: Calibration,
}

impl FollowerConfig {
    /// A source at `rate_hz` with the default predictor, lost after 100 ms (the HUD's veil goal) or
    /// three sample periods if longer.
    pub fn at_rate(rate_hz: f64, calibration: Calibration) -> Self {
        let period_ns = if rate_hz.is_finite() && rate_hz > 0.0 {
            (1e9 / rate_hz).round().max(1.0) as u64
        } else {
            20_000_000
        };
        Self {
            period_ns,
            lost_after_ns: (3 * period_ns).max(100_000_000),
            predictor: PredictorKind::DEFAULT,
            calibration,
        }
    }
}

/// Where the following stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SignalState {
    /// An amplitude's calibration: no end-expiration found yet, or fewer than
    /// [`CALIBRATION_BREATHS`] regular breaths (since the start). A signal whose gain is known:
    /// before its first end-expiration, while the range it has shown is no plausible breath
    /// ([`crate::plausible::TIDAL_VOLUME_ML`], calibrated).
    Calibrating,
    /// Following the patient.
    Following,
    /// No turning point for a while (see [`Pause`]).
    Paused(Pause),
    /// No valid sample within the loss limit.
    Lost,
}

impl SignalState {
    /// Words for a display.
    pub fn describe(self) -> &'static str {
        match self {
            SignalState::Calibrating => "calibrating",
            SignalState::Following => "following patient",
            SignalState::Paused(Pause::BreathHold) => "breath-hold",
            SignalState::Paused(Pause::Apnoea) => "apnoea",
            SignalState::Paused(Pause::Resting) => "pause",
            SignalState::Lost => "signal lost",
        }
    }
}

/// The volume for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Followed {
    /// Volume above the end-expiration baseline at the display time, ml (predicted; before the
    /// first end-expiration by a line through the last four grid points: the predictor has seen
    /// no breath yet).
    pub volume_ml: f64,
    /// The same from the newest sample, not predicted, ml.
    pub unpredicted_ml: f64,
    /// Where the following stands.
    pub state: SignalState,
    /// Inspiration under way.
    pub inhaling: bool,
    /// The latest breaths look cut by the sensor's range: `Some(true)` at the top (the patient's
    /// inspirations were deeper than the signal reads), `Some(false)` at the bottom
    /// ([`super::detect::Detector::clipped`]).
    pub clipped: Option<bool>,
    /// The volume was kept within the drawn range.
    pub clamped: bool,
    /// The predictor's guard replaced its value with the line's.
    pub fell_back: bool,
    /// ml per signal unit in use.
    pub gain_ml_per_unit: f64,
    /// Display time minus the newest sample's time, s (what was predicted across).
    pub lead_s: f64,
}

/// Samples the follower left out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct SampleCounts {
    /// Samples taken.
    pub used: u64,
    /// Flagged invalid by the source, or not finite.
    pub invalid: u64,
    /// At or before the previous sample's time (a repeat or a reordering).
    pub not_newer: u64,
    /// Gaps longer than the loss limit (each restarts the grid and the predictor).
    pub restarts: u64,
}

/// The follower.
#[derive(Debug, Clone, PartialEq)]
pub struct Follower {
    config: FollowerConfig,
    grid: Grid,
    predictor: SignalPredictor,
    detector: Detector,
    samples: SampleCounts,
    peaks: u64,
    /// A known gain may drive before the first end-expiration (see [`CALIBRATION_BREATHS`]).
    from_first_samples: bool,
    /// When the first end-expiration was found after following from the first samples, and how
    /// far above the lowest value seen it lay (faded out over [`FIRST_TROUGH_FADE_NS`]).
    first_trough_step: Option<(u64, f64)>,
}

impl Follower {
    /// A follower that has seen nothing.
    pub fn new(config: FollowerConfig) -> Self {
        Self {
            grid: Grid::new(config.period_ns, config.lost_after_ns),
            predictor: SignalPredictor::new(config.predictor),
            detector: Detector::new(),
            samples: SampleCounts::default(),
            peaks: 0,
            from_first_samples: true,
            first_trough_step: None,
            config,
        }
    }

    /// Start again with a source of another period or calibration (a device's rate or unit
    /// became known), keeping the predictor's kind: in place, nothing allocated (the engine's tick
    /// may call it). Once samples were taken, a signal whose gain is known then waits for its
    /// first end-expiration again (restarted mid-breath, the lowest value seen would be wherever
    /// it restarted).
    pub fn reconfigure(&mut self, period_ns: u64, calibration: Calibration) {
        self.from_first_samples = self.samples.used == 0;
        self.first_trough_step = None;
        self.config.period_ns = period_ns.max(1);
        self.config.lost_after_ns = self.config.period_ns.saturating_mul(3).max(100_000_000);
        self.config.calibration = calibration;
        self.grid = Grid::new(self.config.period_ns, self.config.lost_after_ns);
        self.predictor.reset();
        self.detector = Detector::new();
        self.samples = SampleCounts::default();
        self.peaks = 0;
    }

    /// Drive from the first end-expiration, not from the first samples (the source's rate is not
    /// known yet: the follower will be reconfigured once it is).
    pub fn wait_for_first_end_expiration(&mut self) {
        self.from_first_samples = false;
    }

    /// The settings.
    pub fn config(&self) -> &FollowerConfig {
        &self.config
    }

    /// The breath detector (typical amplitude and period, counts).
    pub fn detector(&self) -> &Detector {
        &self.detector
    }

    /// What happened to the samples.
    pub fn samples(&self) -> SampleCounts {
        self.samples
    }

    /// End-inspiration peaks confirmed.
    pub fn peaks(&self) -> u64 {
        self.peaks
    }

    /// Breaths found (see [`Detector::counts`]).
    pub fn counts(&self) -> Counts {
        self.detector.counts()
    }

    /// Take one sample as it arrives.
    pub fn push(&mut self, s: SignalSample) {
        if !s.valid || !s.value.is_finite() {
            self.samples.invalid += 1;
            return;
        }
        match self.grid.begin(s.t_ns, s.value) {
            Arrival::NotNewer => {
                self.samples.not_newer += 1;
                return;
            }
            Arrival::Restarted => {
                if self.samples.used > 0 {
                    self.samples.restarts += 1;
                    if self.detector.end_expirations() == 0 {
                        // Lost before a breath was seen: back mid-breath, the lowest value seen
                        // would be wherever the signal came back.
                        self.from_first_samples = false;
                    }
                }
                self.predictor.reset();
                self.detector.restart();
                self.see(s.t_ns, s.value);
            }
            Arrival::Follows => {
                while self.grid.step() {
                    self.predictor.learn(&self.grid);
                    let (t, v) = (
                        self.grid.newest_ns(),
                        self.grid.back(0).expect("just added"),
                    );
                    self.see(t, v);
                }
            }
        }
        self.samples.used += 1;
    }

    fn see(&mut self, t_ns: u64, v: f64) {
        let lowest = (self.detector.end_expirations() == 0 && self.calibrated())
            .then(|| self.detector.baseline_at(t_ns))
            .flatten();
        match self.detector.push(t_ns, v) {
            Some(super::detect::Turn::Peak(..)) => self.peaks += 1,
            Some(super::detect::Turn::Trough(..)) => {
                if let (Some(lo), Some(b)) = (lowest, self.detector.baseline_at(t_ns)) {
                    let step = b - lo;
                    self.first_trough_step =
                        (step.is_finite() && step != 0.0 && self.detector.end_expirations() == 1)
                            .then_some((t_ns, step));
                }
            }
            None => {}
        }
    }

    /// Whether the signal can drive the lungs: an amplitude's once its baseline is found and its
    /// gain is known from [`CALIBRATION_BREATHS`] regular breaths; a signal whose gain is known
    /// (see [`CALIBRATION_BREATHS`]) from its first end-expiration, and before it while the range
    /// it has shown, calibrated, lies within a tidal volume's plausible range (a flat start, or
    /// a first second that swings by litres, waits for the first breath).
    pub fn calibrated(&self) -> bool {
        let found = self.detector.end_expirations() > 0;
        match self.config.calibration {
            Calibration::Auto { .. } => {
                found && self.detector.regular_breaths() >= CALIBRATION_BREATHS
            }
            Calibration::Volume | Calibration::Fixed { .. } => {
                found
                    || self.from_first_samples
                        && match (self.gain(), self.detector.typical_amplitude()) {
                            (Some(g), Some(a)) => crate::plausible::TIDAL_VOLUME_ML.contains(g * a),
                            _ => false,
                        }
            }
        }
    }

    /// ml per signal unit now, when known.
    pub fn gain(&self) -> Option<f64> {
        match self.config.calibration {
            Calibration::Volume => Some(1.0),
            Calibration::Fixed { ml_per_unit } => Some(ml_per_unit),
            Calibration::Auto { tidal_ml } => {
                let a = self.detector.typical_amplitude()?;
                let g = tidal_ml / a;
                (a > 0.0 && g.is_finite()).then_some(g)
            }
        }
    }

    /// The volume for a frame computed at `now_ns` and shown at `display_ns`; `None` before the
    /// first sample.
    pub fn volume_at(&self, now_ns: u64, display_ns: u64) -> Option<Followed> {
        let (t_last, v_last) = self.grid.last_sample()?;
        let state = if now_ns.saturating_sub(t_last) > self.config.lost_after_ns {
            SignalState::Lost
        } else if let Some(p) = self.detector.pause() {
            SignalState::Paused(p)
        } else if !self.calibrated() {
            SignalState::Calibrating
        } else {
            SignalState::Following
        };
        let display_ns = display_ns.max(self.grid.newest_ns());
        let prediction = self.predictor.predict(&self.grid, display_ns)?;
        let mut baseline = self.detector.baseline_at(display_ns).unwrap_or(v_last);
        if let Some((at, step)) = self.first_trough_step {
            // On the samples' clock, not the display's (a display one latency ahead would start
            // the fade that far in: at a 500 ms latency, the whole step at once).
            let left = 1.0 - (t_last.saturating_sub(at) as f64 / FIRST_TROUGH_FADE_NS as f64);
            baseline -= step * left.clamp(0.0, 1.0);
        }
        let gain = self.gain().unwrap_or(0.0);
        let tidal = gain * self.detector.typical_amplitude().unwrap_or(0.0);
        let keep = |v: f64| -> (f64, bool) {
            if !(tidal > 0.0) || !v.is_finite() {
                return (0.0, v != 0.0);
            }
            let lo = -BELOW_BASELINE_TIDALS * tidal;
            let hi = ABOVE_BASELINE_TIDALS * tidal;
            let k = v.clamp(lo, hi);
            (k, k != v)
        };
        // Before the first end-expiration the predictor has seen no turn of a breath: its first
        // forecast across one (an autoregression fitted to an inspiration alone) can land a
        // tidal volume off — on an ICU recording, −34 ml for 493 ml, for one frame. Until a
        // breath has been seen, the line through the last four grid points predicts (the
        // predictor's own fallback; no prediction stays none).
        let (predicted, fell_back) = match self.config.predictor {
            _ if self.detector.end_expirations() > 0 => (prediction.value, prediction.fell_back),
            PredictorKind::Hold => (v_last, false),
            _ => (
                super::predict::line(&self.grid, 4, display_ns).unwrap_or(v_last),
                false,
            ),
        };
        let (volume_ml, clamped) = keep(gain * (predicted - baseline));
        let (unpredicted_ml, _) = keep(gain * (v_last - baseline));
        Some(Followed {
            volume_ml,
            unpredicted_ml,
            state,
            inhaling: self.detector.inhaling(),
            clipped: self.detector.clipped(),
            clamped,
            fell_back,
            gain_ml_per_unit: gain,
            lead_s: secs(display_ns as i128 - t_last as i128),
        })
    }
}
