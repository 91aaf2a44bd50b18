//! Breathing with the patient (issue 35; `[breathing] source = "signal"`): the respiratory signal's
//! samples that each tracker frame carries ([`ipc_types::SignalBlock`]) are followed
//! ([`lung_model::breathing::Follower`]: grid, breath detection, calibration, prediction) and turned
//! into the lungs' volume above FRC at the frame's display time; each lung takes its share, as it
//! takes its share of the model's breath.
//!
//! The engine predicts (the renderer draws what it is given): the display time is the newest frame's
//! publish stamp plus `[breathing] latency_ms`, advanced by the tick period on ticks without a frame.
//! Every time is a stamp from the input, never a clock read, so a recorded session replays
//! bit-exactly; nothing is allocated per tick (the follower's rings are fixed).
//!
//! While the signal calibrates (its first regular breaths) or is lost (no valid sample for 100 ms
//! or three sample periods), the model breathes, and at the moment the signal is lost the model's
//! cycle is placed where its volume and direction match the signal's last ones, so the lungs carry
//! on without a jump (phase-continuous); when the signal is back and calibrated it takes over again,
//! blended in from the model's breath over [`TAKEOVER_TICKS`].

use ipc_types::{engine_state, signal_status, signal_unit, TrackerFrame};
use lung_model::breathing::follow::{Calibration, Followed, Follower, FollowerConfig, SignalState};
use lung_model::breathing::SignalSample;
use lung_model::scene::Scene;

use super::{CoreError, LungBreath, LungGeometry};
use lung_model::scene::SceneExt;

/// Sample period assumed before a source states its own, ns (50 Hz).
const PERIOD_BEFORE_KNOWN_NS: u64 = 20_000_000;
/// Shortest and longest sample period followed, ns (1 kHz … 1 Hz: every respiratory source's).
const MIN_PERIOD_NS: u64 = 1_000_000;
const MAX_PERIOD_NS: u64 = 1_000_000_000;
/// Ticks over which the signal takes over from the model (0.5 s at 60 Hz): the drawn volume blends
/// from the model's breath into the patient's instead of jumping.
pub const TAKEOVER_TICKS: u64 = 30;

/// The signal's part of the engine.
#[derive(Debug, Clone)]
pub struct SignalDrive {
    follower: Follower,
    latency_ns: u64,
    tick_ns: u64,
    /// The scene's tidal volume for an amplitude signal's calibration, ml.
    tidal_ml: f64,
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
    ticks: SignalTicks,
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
            tick_ns: (1e9 / scene.engine.tick_hz).round() as u64,
            tidal_ml,
            unit: signal_unit::NONE,
            period_ns: 0,
            now_ns: 0,
            now_tick: None,
            driving: false,
            took_over: 0,
            last: None,
            followed: None,
            source_ended: false,
            ticks: SignalTicks::default(),
        })
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
        let finite = |v: f64| if v.is_finite() { v as f32 } else { 0.0 };
        match self.followed {
            Some(f) => ipc_types::SignalFollowed {
                display_ns: self.now_ns.saturating_add(self.latency_ns),
                volume_ml: finite(f.volume_ml),
                unpredicted_ml: finite(f.unpredicted_ml),
            },
            None => ipc_types::SignalFollowed::default(),
        }
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
        let (drive, mut bits) = match followed {
            Some(f) => match f.state {
                SignalState::Following => (Some(f), engine_state::SIGNAL_FOLLOWING),
                SignalState::Paused(_) => (
                    Some(f),
                    engine_state::SIGNAL_FOLLOWING | engine_state::SIGNAL_PAUSED,
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
                for (_, breath) in lungs.iter_mut() {
                    breath.driven = Some((f.volume_ml, f.inhaling, w));
                }
                self.driving = true;
            }
            None => {
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
                Calibration::Auto {
                    tidal_ml: self.tidal_ml,
                }
            };
            self.follower.reconfigure(period, calibration);
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
