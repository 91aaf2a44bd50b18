//! Breathing with the patient (issue 35; `[breathing] source = "signal"`): the respiratory signal's
//! samples that each tracker frame carries ([`ipc_types::SignalBlock`]) are followed
//! ([`lung_model::breathing::Follower`]: grid, breath detection, calibration, prediction) and turned
//! into the lungs' volume above FRC at the frame's display time; each lung takes its share, as it
//! takes its share of the model's breath.
//!
//! The engine predicts (the renderer draws what it is given): the display time is the newest frame's
//! publish stamp plus the latency, advanced by the tick period on ticks without a frame. The latency
//! is the pipeline's as measured (`[breathing] latency = "measured"`, the default): the bridge reads
//! the renderer's reports and sends the median bridge-publish-to-display time in every tracker frame
//! that carries the signal ([`ipc_types::SignalBlock::pipeline_latency_ns`]), to which the source's
//! own delay (`sensor_latency_ms`) is added; `latency_ms` until the first measurement, and always
//! with `latency = "fixed"`. Every time is a stamp or a figure from the input, never a clock read,
//! so a recorded session (which records the measured latency with the signal) replays bit-exactly;
//! nothing is allocated per tick (the follower's rings are fixed).
//!
//! While the signal calibrates (an amplitude's first regular breaths; a volume's first samples) or
//! is lost (no valid sample for 100 ms
//! or three sample periods), the model breathes, and at the moment the signal is lost the model's
//! cycle is placed where its volume and direction match the signal's last ones, so the lungs carry
//! on without a jump (phase-continuous); when the signal is back and calibrated it takes over again,
//! blended in from the model's breath over [`TAKEOVER_TICKS`].
//!
//! For remote sites (a `[remote]` source following a live signal) the drive keeps the breath the
//! lungs followed, tick by tick, in a buffer allocated once ([`BreathLog`]): at each of the patient's
//! end-expirations the breath just completed is resampled to [`control_state::LIVE_SAMPLES`] points,
//! and the next control state carries it with the new breath's start tick
//! ([`control_state::LiveBreath`]), so every site plays the previous breath from the start of the
//! one in progress and re-aligns at every breath.

use ipc_types::{engine_state, signal_status, signal_unit, TrackerFrame};
use lung_model::breathing::follow::{Calibration, Followed, Follower, FollowerConfig, SignalState};
use lung_model::breathing::SignalSample;
use lung_model::scene::Scene;

use super::{CoreError, LungBreath, LungGeometry};
use lung_model::scene::SceneExt;

use control_state::{Bounded, LiveBreath, LIVE_SAMPLES, MAX_LIVE_TICKS};

/// Sample period assumed before a source states its own, ns (50 Hz).
const PERIOD_BEFORE_KNOWN_NS: u64 = 20_000_000;
/// Shortest and longest sample period followed, ns (1 kHz … 1 Hz: every respiratory source's).
const MIN_PERIOD_NS: u64 = 1_000_000;
const MAX_PERIOD_NS: u64 = 1_000_000_000;
/// Ticks over which the signal takes over from the model (0.5 s at 60 Hz): the drawn volume blends
/// from the model's breath into the patient's instead of jumping.
pub const TAKEOVER_TICKS: u64 = 30;

/// Longest measured latency predicted across, ns (the bridge sends none longer; a frame from
/// elsewhere is bounded here too).
const MAX_MEASURED_LATENCY_NS: u64 = 1_000_000_000;

/// The signal's part of the engine.
#[derive(Debug, Clone)]
pub struct SignalDrive {
    follower: Follower,
    /// The latency predicted across now, ns (the fixed one until a measured one came).
    latency_ns: u64,
    /// Take the pipeline's measured latency from the frames (`latency = "measured"`).
    measured: bool,
    /// The source's own delay added to a measured latency, ns.
    sensor_ns: u64,
    tick_ns: u64,
    /// The scene's tidal volume for an amplitude signal's calibration, ml.
    tidal_ml: f64,
    /// An amplitude's spirometry calibration, ml per unit (`[breathing] ml_per_unit`).
    ml_per_unit: Option<f64>,
    /// The unit and period the follower is configured for (0: none yet).
    unit: u32,
    period_ns: u64,
    /// The time of the newest input, ns, and the tick it came with.
    now_ns: u64,
    now_tick: Option<u64>,
    /// The signal drove the lungs on the previous tick.
    driving: bool,
    /// The tick the signal last took over from the model.
    took_over: u64,
    /// The newest volume and direction the signal gave (the model is placed there on a loss).
    last: Option<(f64, bool)>,
    /// The newest following figures, for reports.
    followed: Option<Followed>,
    source_ended: bool,
    /// The bridge is learning how to read its source (no samples yet, not a loss).
    learning: bool,
    ticks: SignalTicks,
    /// The breaths the lungs followed, for remote sites.
    log: BreathLog,
}

/// The patient's breaths as the lungs followed them (the volume above FRC the signal gave each
/// tick), for remote sites: the ticks since the breath in progress started and the previous whole
/// breath resampled. A breath runs from one end-expiration to the next; each turn (end-expiration,
/// end-inspiration) is confirmed by the follower's own turn (its hysteresis keeps noise, a slow drift
/// and a ventilator's flow steps from making turns) and placed at the lowest or highest volume since
/// the turn before. Allocated once; nothing per tick (a clone allocates its own buffer whole).
#[derive(Debug)]
struct BreathLog {
    /// The volume each tick from the breath in progress's start (or from when following began,
    /// before the first start), at most [`MAX_LIVE_TICKS`].
    ticks: Vec<f32>,
    /// The buffer filled (an apnoea over a minute): the breath in progress is not described.
    overflowed: bool,
    /// Tick of `ticks[0]`, and whether it is a breath's start (`false`: following began there).
    first_tick: u64,
    started: bool,
    /// Whether the follower said the patient inhales on the previous tick (`None`: not following).
    inhaling: Option<bool>,
    /// The lowest volume since the patient began to exhale, and the last tick the volume was
    /// within [`TURN_BAND`] of it (where the patient left it).
    low: (f64, u64),
    /// The highest volume since the breath in progress started, and the last tick within the band
    /// of it; and, once the follower saw the patient expire, that peak.
    high: (f64, u64),
    peak: Option<(u64, f32)>,
    /// The previous whole breath: its samples, how many, its ticks and the tick of its peak (0:
    /// none yet).
    last: [f32; LIVE_SAMPLES],
    last_n: usize,
    last_ticks: u32,
    last_peak: u32,
    last_depth_ml: f64,
    /// Breaths completed while following.
    breaths: u64,
    /// Changes a site must hear of (a breath started, or following stopped).
    generation: u64,
}

/// The highest of `(value, at)` and `volume`, with the last tick the volume was within `band` of
/// it (`tick` when `volume` is; the lowest is the highest of the negated volumes).
fn near_extreme((value, at): (f64, u64), volume: f64, tick: u64, band: f64) -> (f64, u64) {
    let top = value.max(volume);
    (top, if volume >= top - band { tick } else { at })
}

/// How close to a turn's extreme the volume still counts as at it, as a share of the last
/// breath's depth: a turn is placed where the patient left it (the end of a pause or a hold).
const TURN_BAND: f64 = 0.05;

impl Clone for BreathLog {
    fn clone(&self) -> Self {
        // `Vec::clone` keeps the length, not the capacity: the clone's tick would allocate.
        let mut ticks = Vec::with_capacity(MAX_LIVE_TICKS as usize);
        ticks.extend_from_slice(&self.ticks);
        Self {
            ticks,
            overflowed: self.overflowed,
            first_tick: self.first_tick,
            started: self.started,
            inhaling: self.inhaling,
            low: self.low,
            high: self.high,
            peak: self.peak,
            last: self.last,
            last_n: self.last_n,
            last_ticks: self.last_ticks,
            last_peak: self.last_peak,
            last_depth_ml: self.last_depth_ml,
            breaths: self.breaths,
            generation: self.generation,
        }
    }
}

impl BreathLog {
    fn new() -> Self {
        Self {
            ticks: Vec::with_capacity(MAX_LIVE_TICKS as usize),
            overflowed: false,
            first_tick: 0,
            started: false,
            inhaling: None,
            low: (f64::INFINITY, 0),
            high: (f64::NEG_INFINITY, 0),
            peak: None,
            last: [0.0; LIVE_SAMPLES],
            last_n: 0,
            last_ticks: 0,
            last_peak: 0,
            last_depth_ml: 0.0,
            breaths: 0,
            generation: 0,
        }
    }

    /// A tick the signal drove at `volume_ml`, the follower saying whether the patient inhales.
    /// The follower's turns (with its hysteresis against noise and a ventilator's flow steps)
    /// confirm each turn; the turn is placed at the extreme since the one before.
    fn take(&mut self, tick: u64, volume_ml: f64, inhaling: bool) {
        if self.ticks.is_empty() && !self.overflowed {
            self.first_tick = tick;
        }
        if self.ticks.len() < MAX_LIVE_TICKS as usize {
            self.ticks.push(volume_ml as f32);
        } else {
            self.overflowed = true;
        }
        let band = self.band_ml();
        let was = self.inhaling.replace(inhaling);
        match (was, inhaling) {
            (Some(false), true) => {
                // End-expiration confirmed: the breath started where the patient left the lowest
                // volume (the end of an expiratory pause, not its drifting start).
                self.start_at(self.low.1);
                self.high = (volume_ml, tick);
            }
            (Some(true), false) => {
                if self.started && self.peak.is_none() && self.high.0.is_finite() {
                    // End-inspiration confirmed: the sites hear of it at once; the expiration
                    // started where the patient left the highest volume (the end of a hold).
                    self.peak = Some((self.high.1, self.high.0 as f32));
                    if self.last_n > 0 {
                        self.generation += 1;
                    }
                }
                self.low = (volume_ml, tick);
            }
            (None, false) => self.low = (volume_ml, tick),
            _ => {}
        }
        // The extremes' values, and the last tick within `band` of them.
        if inhaling && self.peak.is_none() {
            self.high = near_extreme(self.high, volume_ml, tick, band);
        }
        if !inhaling {
            let (low, at) = near_extreme((-self.low.0, self.low.1), -volume_ml, tick, band);
            self.low = (-low, at);
        }
    }

    /// How close to an extreme the volume is still at it, ml: [`TURN_BAND`] of the last breath's
    /// depth (25 ml before one).
    fn band_ml(&self) -> f64 {
        if self.last_depth_ml > 0.0 {
            TURN_BAND * self.last_depth_ml
        } else {
            25.0
        }
    }

    /// A breath started at `trough` (at or before the newest tick): the one before it, from the
    /// last start, is the previous breath.
    fn start_at(&mut self, trough: u64) {
        if self.overflowed {
            // The breath before was over a minute (or following began that long ago): not
            // described, and its trough's tick is no longer in the buffer.
            self.ticks.clear();
            self.overflowed = false;
            self.started = false;
            return;
        }
        let cut = (trough.saturating_sub(self.first_tick) as usize).min(self.ticks.len());
        if self.started && cut >= 2 {
            let samples = cut.min(LIVE_SAMPLES);
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for v in &self.ticks[..cut] {
                lo = lo.min(*v as f64);
                hi = hi.max(*v as f64);
            }
            // Its peak where the patient left the highest volume, as the sites are told.
            let band = self.band_ml();
            let top = self.ticks[..cut]
                .iter()
                .rposition(|&v| v as f64 >= hi - band)
                .unwrap_or(0);
            for (j, out) in self.last[..samples].iter_mut().enumerate() {
                let x = j as f64 * (cut - 1) as f64 / (samples - 1) as f64;
                let k = (x.floor() as usize).min(cut - 2);
                let (a, b) = (self.ticks[k] as f64, self.ticks[k + 1] as f64);
                *out = (a + (b - a) * (x - k as f64)) as f32;
            }
            self.last_n = samples;
            self.last_ticks = cut as u32;
            self.last_peak = top as u32;
            self.last_depth_ml = hi - lo;
            self.breaths += 1;
            self.generation += 1;
        }
        self.ticks.drain(..cut);
        self.first_tick = trough;
        self.started = true;
        self.high = (f64::NEG_INFINITY, trough);
        self.peak = None;
    }

    /// The signal stopped driving (calibrating, lost, ended): what the sites had is void.
    fn stop(&mut self) {
        if self.last_n > 0 && self.started {
            self.generation += 1;
        }
        self.ticks.clear();
        self.overflowed = false;
        self.started = false;
        self.inhaling = None;
        self.last_n = 0;
        self.last_ticks = 0;
    }

    /// The breath for the sites (allocates: call after the tick).
    fn live(&self) -> Option<LiveBreath> {
        if !self.started {
            return None;
        }
        let start_tick = self.first_tick;
        // A value that is not finite is never sent (the packet would be refused): the sites carry
        // on with the model until the next breath.
        if self.last_n < 2 || !self.last[..self.last_n].iter().all(|v| v.is_finite()) {
            return None;
        }
        let ml = self.last[..self.last_n]
            .iter()
            .map(|v| v.clamp(-control_state::MAX_LIVE_ML, control_state::MAX_LIVE_ML))
            .collect();
        Some(LiveBreath {
            start_tick,
            breath: self.breaths,
            peak: self.peak,
            last_ticks: self.last_ticks,
            last_peak: self.last_peak,
            last_ml: Bounded::new(ml)?,
            clipped: false,
        })
    }
}

/// Ticks by what drove the lungs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SignalTicks {
    /// The signal drove them (following, or paused on a breath-hold or apnoea).
    pub following: u64,
    /// The model, while the signal calibrated.
    pub calibrating: u64,
    /// The model, with no signal (lost, ended, none yet).
    pub lost: u64,
}

impl SignalDrive {
    /// The drive for `scene` (`[breathing] source = "signal"`); `model_tidal_ml` is the PV model's
    /// tidal volume (an amplitude's typical breath is calibrated to it unless the table names one).
    pub fn new(scene: &Scene, model_tidal_ml: f64) -> Result<Self, CoreError> {
        let predictor = scene
            .breathing_predictor()
            .map_err(|e| CoreError::Signal(e.to_string()))?;
        let tidal_ml = scene.breathing.tidal_ml.unwrap_or(model_tidal_ml);
        let mut config = FollowerConfig::at_rate(
            1e9 / PERIOD_BEFORE_KNOWN_NS as f64,
            Calibration::Auto { tidal_ml },
        );
        config.predictor = predictor;
        Ok(Self {
            follower: Follower::new(config),
            latency_ns: (scene.breathing.latency_ms * 1e6).round() as u64,
            measured: scene.breathing.latency == lung_model::scene::LatencyChoice::Measured,
            sensor_ns: (scene.breathing.sensor_latency_ms * 1e6).round() as u64,
            tick_ns: (1e9 / scene.engine.tick_hz).round() as u64,
            tidal_ml,
            ml_per_unit: scene.breathing.ml_per_unit,
            unit: signal_unit::NONE,
            period_ns: 0,
            now_ns: 0,
            now_tick: None,
            driving: false,
            took_over: 0,
            last: None,
            followed: None,
            source_ended: false,
            learning: false,
            ticks: SignalTicks::default(),
            log: BreathLog::new(),
        })
    }

    /// The patient's breath for remote sites: the previous whole breath the lungs followed and the
    /// start of the one in progress (`None` while the model breathes, or before a whole breath was
    /// followed), with whether the signal looks clipped now. Allocates: call after the tick.
    pub fn live(&self) -> Option<LiveBreath> {
        let clipped = self.clipped();
        self.log.live().map(|b| LiveBreath { clipped, ..b })
    }

    /// The signal looks clipped now (the follower's verdict).
    fn clipped(&self) -> bool {
        self.followed.is_some_and(|f| f.clipped.is_some())
    }

    /// Changes to [`Self::live`] so far (a new breath, following stopped, or the clipping verdict
    /// changed): a source publishes a control state when it moves.
    pub fn live_generation(&self) -> u64 {
        2 * self.log.generation + u64::from(self.clipped())
    }

    /// The follower (its detector, counts and settings).
    pub fn follower(&self) -> &Follower {
        &self.follower
    }

    /// The newest following figures (`None` before the first sample).
    pub fn followed(&self) -> Option<Followed> {
        self.followed
    }

    /// The bridge said its source ended (a replayed trace reached its end).
    pub fn source_ended(&self) -> bool {
        self.source_ended
    }

    /// What this tick followed, for the engine frame ([`ipc_types::SignalFollowed`]): the display
    /// time predicted for, and the volume with and without the prediction (0 where none; a value
    /// that is not finite is never written).
    pub fn wire(&self) -> ipc_types::SignalFollowed {
        let finite = |v: f64| {
            let x = v as f32;
            if x.is_finite() {
                x
            } else {
                0.0
            }
        };
        // The patient's typical breath and where it is at the display time: all or nothing (a
        // display pairs them).
        let display_ns = self.now_ns.saturating_add(self.latency_ns);
        let (tidal, period, phase, split) = match (
            self.typical_tidal_ml(),
            self.follower.detector().phase_at(display_ns),
        ) {
            (Some(v), Some((p, phase, split))) if finite(v) > 0.0 && finite(p) > 0.0 => {
                (finite(v), finite(p), finite(phase), finite(split))
            }
            _ => (0.0, 0.0, 0.0, 0.0),
        };
        match self.followed {
            Some(f) => ipc_types::SignalFollowed {
                display_ns,
                volume_ml: finite(f.volume_ml),
                unpredicted_ml: finite(f.unpredicted_ml),
                latency_ns: self.latency_ns,
                tidal_ml: tidal,
                period_s: period,
                phase,
                inhale_fraction: split,
            },
            None => ipc_types::SignalFollowed::default(),
        }
    }

    /// The patient's typical tidal volume as followed (the gain in use times the typical breath's
    /// amplitude), ml; `None` while either is unknown.
    fn typical_tidal_ml(&self) -> Option<f64> {
        let f = &self.follower;
        let v = f.gain()? * f.detector().typical_amplitude()?;
        (v.is_finite() && v > 0.0).then_some(v)
    }

    /// Ticks so far by what drove the lungs.
    pub fn ticks(&self) -> SignalTicks {
        self.ticks
    }

    /// Take this tick's input, decide what drives each lung, and return the state bits. A lung
    /// driven by the signal gets its volume change above FRC; the model's lungs get none, and on
    /// the tick the signal is lost each lung's model cycle is placed at the signal's last volume
    /// and direction.
    pub(super) fn tick(
        &mut self,
        tick: u64,
        input: Option<&TrackerFrame>,
        lungs: &mut [(LungGeometry, LungBreath)],
    ) -> u32 {
        match input {
            Some(frame) => {
                self.take(&frame.signal);
                // The pipeline's latency as measured (0: none yet; a bridge bounds it to 1 s).
                let measured = frame.signal.pipeline_latency_ns;
                if self.measured && measured != 0 {
                    self.latency_ns = measured
                        .min(MAX_MEASURED_LATENCY_NS)
                        .saturating_add(self.sensor_ns);
                }
                let stamp = frame.stamps.bridge_publish_ns.max(frame.stamps.capture_ns);
                // The frame's own time (never backwards: a frame stamped before an estimate made
                // on a tick without one keeps the estimate).
                self.now_ns = stamp.max(self.now_ns);
            }
            None => self.now_ns = self.advanced_to(tick),
        }
        self.now_tick = Some(tick);
        let followed = self
            .follower
            .volume_at(self.now_ns, self.now_ns.saturating_add(self.latency_ns));
        self.followed = followed;
        let clipped = |f: &Followed| {
            if f.clipped.is_some() {
                engine_state::SIGNAL_CLIPPED
            } else {
                0
            }
        };
        let (drive, mut bits) = match followed {
            Some(f) => match f.state {
                SignalState::Following => (Some(f), engine_state::SIGNAL_FOLLOWING | clipped(&f)),
                SignalState::Paused(_) => (
                    Some(f),
                    engine_state::SIGNAL_FOLLOWING | engine_state::SIGNAL_PAUSED | clipped(&f),
                ),
                SignalState::Calibrating => (None, engine_state::SIGNAL_CALIBRATING),
                SignalState::Lost => (None, engine_state::SIGNAL_LOST),
            },
            None => (None, engine_state::SIGNAL_LOST),
        };
        match drive {
            Some(f) => {
                if !self.driving {
                    self.took_over = tick;
                }
                let w = ((tick - self.took_over + 1) as f64 / TAKEOVER_TICKS as f64).min(1.0);
                self.last = Some((f.volume_ml, f.inhaling));
                self.log.take(tick, f.volume_ml, f.inhaling);
                for (_, breath) in lungs.iter_mut() {
                    breath.driven = Some((f.volume_ml, f.inhaling, w));
                }
                self.driving = true;
            }
            None => {
                self.log.stop();
                for (_, breath) in lungs.iter_mut() {
                    breath.driven = None;
                    if self.driving {
                        if let Some((volume_ml, inhaling)) = self.last {
                            breath.resume_model_at(tick, volume_ml, inhaling);
                        }
                    }
                }
                self.driving = false;
            }
        }
        if self.unit == signal_unit::NONE {
            bits |= engine_state::SIGNAL_LOST;
            bits &= !engine_state::SIGNAL_CALIBRATING;
        }
        if self.learning && bits & engine_state::SIGNAL_FOLLOWING == 0 {
            // The bridge learns how to read its source (a chest tool's axis): calibrating, not
            // lost (no veil), and said as such.
            bits = engine_state::SIGNAL_CALIBRATING | engine_state::SIGNAL_LEARNING;
        }
        if bits & engine_state::SIGNAL_FOLLOWING != 0 {
            self.ticks.following += 1;
        } else if bits & engine_state::SIGNAL_CALIBRATING != 0 {
            self.ticks.calibrating += 1;
        } else {
            self.ticks.lost += 1;
        }
        bits
    }

    /// The clock at `tick` from the newest input's time and the tick period.
    fn advanced_to(&self, tick: u64) -> u64 {
        match self.now_tick {
            Some(t) => self
                .now_ns
                .saturating_add(tick.saturating_sub(t).saturating_mul(self.tick_ns)),
            None => self.now_ns,
        }
    }

    /// The block's samples into the follower (reconfigured, in place, when the source's unit or
    /// period first shows or changes).
    fn take(&mut self, block: &ipc_types::SignalBlock) {
        if block.status & signal_status::CONFIGURED == 0 {
            return;
        }
        self.source_ended = block.status & signal_status::ENDED != 0;
        self.learning = block.status & signal_status::LEARNING != 0;
        // A unit the protocol does not name, or a period no respiratory source has (a foreign or
        // damaged frame), is not followed: the block's samples are left out.
        let unit = block.unit;
        if !matches!(
            unit,
            signal_unit::MM | signal_unit::ML | signal_unit::ARBITRARY
        ) {
            return;
        }
        let period = match block.period_ns {
            0 => PERIOD_BEFORE_KNOWN_NS,
            p if (MIN_PERIOD_NS..=MAX_PERIOD_NS).contains(&p) => p,
            _ => return,
        };
        if unit != self.unit || period != self.period_ns {
            let calibration = if unit == signal_unit::ML {
                Calibration::Volume
            } else {
                Calibration::amplitude(self.ml_per_unit, self.tidal_ml)
            };
            self.follower.reconfigure(period, calibration);
            if block.period_ns == 0 {
                // Reconfigured again once the rate is known: drive from the first
                // end-expiration, not from samples on a grid of a guessed period.
                self.follower.wait_for_first_end_expiration();
            }
            self.unit = unit;
            self.period_ns = period;
        }
        for i in 0..ipc_types::MAX_SIGNAL_SAMPLES {
            let Some((s, valid)) = block.sample(i) else {
                break;
            };
            self.follower.push(SignalSample {
                t_ns: s.t_ns,
                value: s.value,
                valid,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ventilator-like breath of `period` ticks: `rise` ticks of inspiration to 500 ml, `hold`
    /// ticks held there, a fall to 0 over `fall` ticks, then a pause at 0 (drifting up 0.2 ml a
    /// tick); the follower's turns `lag` ticks after the patient's.
    fn breath(k: u64, period: u64, hold: u64) -> (f64, bool) {
        let (rise, fall) = (40, 60);
        let t = k % period;
        // The rise starts where the drifting pause ended: the pause's lowest is at its start.
        let base = 0.2 * (period - rise - hold - fall) as f64;
        if t < rise {
            (base + (500.0 - base) * t as f64 / rise as f64, true)
        } else if t < rise + hold {
            (500.0, true)
        } else if t < rise + hold + fall {
            (
                500.0 * (1.0 - (t - rise - hold) as f64 / fall as f64),
                false,
            )
        } else {
            (0.2 * (t - rise - hold - fall) as f64, false)
        }
    }

    fn run(log: &mut BreathLog, from: u64, to: u64, period: u64, hold: u64, lag: u64) {
        for k in from..to {
            let (v, _) = breath(k, period, hold);
            let (_, inhaling) = breath(k.saturating_sub(lag), period, hold);
            log.take(k, v, inhaling);
        }
    }

    /// Each turn is placed where the patient left the extreme — the end of the pause (not its
    /// drifting start), the end of the hold — and the breath described is the previous one whole.
    #[test]
    fn turns_are_placed_where_the_patient_left_the_extreme() {
        let mut log = BreathLog::new();
        // Breaths of 240 ticks with a 30-tick hold; the follower's turns 8 ticks late.
        run(&mut log, 0, 240 * 3 + 100, 240, 30, 8);
        let live = log.live().expect("a whole breath");
        assert_eq!(live.last_ticks, 240);
        // The pause drifts up 0.2 ml a tick (28 ml over it, past the 25 ml band: 5 % of 500): the
        // start is placed where the volume left the band — at the breath's start, within the
        // band's 2 ticks of this rise — not 140 ticks earlier where the pause began.
        assert!(live.start_tick.abs_diff(720) <= 2, "{live:?}");
        // The previous breath's peak at the end of its hold (tick 70 of it; the band is 3 ticks of
        // this fall), this one's announced there too.
        assert!(live.last_peak.abs_diff(70) <= 3, "{live:?}");
        assert!(live
            .peak
            .is_some_and(|(t, v)| t.abs_diff(790) <= 3 && v == 500.0));
        assert_eq!(live.breath, 2);
    }

    /// A breath over a minute (an apnoea) is not described, and the one after it is, whole and in
    /// place; a stop voids what the sites had.
    #[test]
    fn an_apnoea_over_a_minute_is_not_described_and_the_next_breath_is() {
        let mut log = BreathLog::new();
        run(&mut log, 0, 500, 240, 30, 8);
        let before = log.live().expect("a whole breath").breath;
        // An apnoea: the volume at 0 for 70 s, the follower exhaling.
        for k in 500..500 + 70 * 60 {
            log.take(k, 0.0, false);
        }
        let resume = 500 + 70 * 60;
        // Breaths again, starting at `resume`.
        for k in resume..resume + 240 * 3 {
            let (v, _) = breath(k - resume, 240, 30);
            let (_, inhaling) = breath((k - resume).saturating_sub(8), 240, 30);
            log.take(k, v, inhaling);
        }
        let live = log.live().expect("described again");
        assert_eq!(live.last_ticks, 240, "{live:?}");
        assert!(live.start_tick.abs_diff(resume + 480) <= 2, "{live:?}");
        assert!(live.breath > before);
        let generation = log.generation;
        log.stop();
        assert!(log.live().is_none());
        assert!(log.generation > generation, "the sites hear of it");
    }
}
