//! The engine's control state for remote sites (seed §8.3; `control-state` crate).
//!
//! A source engine describes its breath with [`EngineCore::control_state`] once per breathing
//! cycle (every change this engine makes takes effect at a lung's cycle start: a disease cycle, an
//! intervention, a rate change). A site's engine is built from its own copy of the scene and
//! driven by those packets: [`Prepared::of`] builds the PV tables a packet names (off the tick:
//! ≈ 20 ms per distinct cycle, cached while the constants stay the same) and
//! [`EngineCore::apply_prepared`] puts them and every lung's state in place (no allocation beyond
//! moving the prepared tables in). Both engines run the same code on the same constants, so the
//! same packets give the same breath, bit for bit, at the same source tick.
//!
//! A disease course changes the breath at a cycle start, from a cycle the source prepares a breath
//! ahead (a trainee's intervention is taken into it). The source announces that prepared cycle in
//! the state it publishes as soon as the cycle is built ([`PendingCycle`], with the tick it starts
//! at), so a site puts it into its lungs at that very tick ([`RemotePending`]) instead of learning
//! of it one network delay after the source's cycle start.
//!
//! A source that follows the patient's live respiratory signal (issue 35) sends the patient's
//! previous breath and the turns of the one in progress with every state, and a state at once at
//! each of the patient's turns ([`LiveBreath`]: a breath's start and its expiration's); a site plays
//! the previous breath from those turns ([`RemoteLive`]) and re-aligns at each. The site's breath is
//! then a prediction at most a breath ahead, not the source's bit for bit: how far it strays is measured
//! (`engine/src/runtime/tests.rs`, `a_site_breathes_with_the_sources_patient`; docs/REMOTE.md).

use control_state::{
    Bounded, ControlState, Disease, LiveBreath, LungState, PendingCycle, PendingLung, PhaseState,
    PvState, RemoteEvent, MAX_EVENTS,
};
use lung_model::mesh::Side;
use lung_model::pv::{Boundary, Breathing, PhaseConstants, PvError, Timing};
use thiserror::Error;

use super::{disease::DiseaseRun, EngineCore, LungBreath};

/// Why a control state cannot be made or used.
#[derive(Debug, Error)]
pub enum RemoteStateError {
    /// A measured waveform has no constants a site could rebuild it from.
    #[error(
        "the {side} lung breathes a measured waveform ([pv] waveform): remote sites need PV \
         constants; use a preset or fitted constants for a shared session"
    )]
    Waveform {
        /// Which lung.
        side: &'static str,
    },
    /// The packet names a lung this site's scene does not simulate.
    #[error(
        "the source simulates the {side} lung but this site's scene does not: start every site \
         on the source's scene"
    )]
    MissingLung {
        /// Which lung.
        side: &'static str,
    },
    /// The packet's constants cannot produce a breath.
    #[error("the source's {side} lung: {source}")]
    Pv {
        /// Which lung.
        side: &'static str,
        /// Why.
        #[source]
        source: PvError,
    },
    /// The boundary values are outside human ranges (a silent wrong answer otherwise).
    #[error("the source's {side} lung: {reason}")]
    Implausible {
        /// Which lung.
        side: &'static str,
        /// Why.
        reason: String,
    },
    /// The site ticks at another rate than the source.
    #[error(
        "the source ticks at {source_hz} Hz, this site at {site_hz} Hz: start the site on the \
         source's scene"
    )]
    TickRate {
        /// Source.
        source_hz: f64,
        /// Site.
        site_hz: f64,
    },
}

fn side_of(code: u8) -> Side {
    if code as usize == ipc_types::LUNG_LEFT {
        Side::Left
    } else {
        Side::Right
    }
}

fn phase_state(p: &PhaseConstants) -> PhaseState {
    PhaseState {
        // lung-model refuses more than MAX_CONTROL_CONSTANTS (15 = control_state::MAX_CHI).
        chi: Bounded::new(p.chi.iter().copied().take(control_state::MAX_CHI).collect())
            .unwrap_or_default(),
        q: p.q,
        c: p.c,
        t_ext: p.t_ext,
        t_steps: p.t_steps,
        beta0: p.beta0,
        beta1: p.beta1,
    }
}

fn phase_constants(p: &PhaseState) -> PhaseConstants {
    PhaseConstants {
        chi: p.chi.to_vec(),
        q: p.q,
        c: p.c,
        t_ext: p.t_ext,
        t_steps: p.t_steps,
        beta0: p.beta0,
        beta1: p.beta1,
    }
}

fn pv_state(b: &Breathing, side: Side) -> Result<PvState, RemoteStateError> {
    let s = b
        .source()
        .ok_or(RemoteStateError::Waveform { side: side.name() })?;
    let bd = b.boundary();
    Ok(PvState {
        inhale: phase_state(&s.inhale),
        exhale: phase_state(&s.exhale),
        frc_ml: bd.frc_ml,
        tv_ml: bd.tv_ml,
        rp_cmh2o: bd.rp_cmh2o,
        tp_cmh2o: bd.tp_cmh2o,
        breaths_per_min: s.timing.breaths_per_min,
        ie_inhale: s.timing.ie_inhale,
        ie_exhale: s.timing.ie_exhale,
    })
}

/// Build the breath a [`PvState`] names at `tick_hz` (eq. 5.11 tables; allocates, ≈ 20 ms).
pub fn breathing_of(pv: &PvState, tick_hz: f64, side: Side) -> Result<Breathing, RemoteStateError> {
    let boundary = Boundary {
        frc_ml: pv.frc_ml,
        tv_ml: pv.tv_ml,
        rp_cmh2o: pv.rp_cmh2o,
        tp_cmh2o: pv.tp_cmh2o,
    };
    boundary
        .check_plausible()
        .map_err(|e| RemoteStateError::Implausible {
            side: side.name(),
            reason: e.to_string(),
        })?;
    let timing = Timing {
        tick_hz,
        breaths_per_min: pv.breaths_per_min,
        ie_inhale: pv.ie_inhale,
        ie_exhale: pv.ie_exhale,
    };
    let (i, e) = (phase_constants(&pv.inhale), phase_constants(&pv.exhale));
    for p in [&i, &e] {
        p.validate().map_err(|source| RemoteStateError::Pv {
            side: side.name(),
            source,
        })?;
    }
    Breathing::from_constants(&i, &e, boundary, &timing).map_err(|source| RemoteStateError::Pv {
        side: side.name(),
        source,
    })
}

impl LungBreath {
    fn state(&self, side: Side) -> Result<LungState, RemoteStateError> {
        Ok(LungState {
            side: side.index() as u8,
            pv: pv_state(&self.breathing, side)?,
            next: self.next.as_ref().map(|n| pv_state(n, side)).transpose()?,
            share: self.share,
            held_ml: self.held_ml,
            base_ml: self.base_ml,
            collapse: self.collapse,
            offset_mm: self.offset_mm,
            cycle: self.cycle,
            cycle_start_tick: self.cycle_start,
        })
    }
}

/// Identity of the sender and timing of one state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StateStamp {
    /// Source site id.
    pub source: u64,
    /// Source session.
    pub epoch: u64,
    /// Packet sequence.
    pub sequence: u64,
    /// Ticks per second.
    pub tick_hz: f64,
    /// Source clock at the tick, ns.
    pub source_time_ns: u64,
}

/// A control state with the breaths it names already built (off the tick).
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The packet.
    pub state: ControlState,
    /// Per lung of the packet: the cycle in force and the pending one.
    breaths: Vec<(Breathing, Option<Breathing>)>,
    /// The announced disease cycle, built.
    pending: Option<RemotePending>,
}

/// A source's announced disease cycle on a site's engine: put into the lungs at the first tick
/// stepped at or after `tick` (as the source's disease course does at its cycle start).
#[derive(Debug, Clone)]
pub struct RemotePending {
    /// Source tick it starts at.
    pub tick: u64,
    lungs: Vec<(Side, super::disease::LungChange, Option<Breathing>)>,
}

impl RemotePending {
    /// Put it into `lungs` (no allocation: the PV cycles are moved in).
    pub(crate) fn put_into(&mut self, lungs: &mut [(super::LungGeometry, LungBreath)]) {
        let now = self.tick == 0;
        for (side, change, breathing) in self.lungs.iter_mut() {
            if let Some((_, b)) = lungs.iter_mut().find(|(g, _)| g.side == *side) {
                super::disease::put(b, *change, breathing.take(), now);
            }
        }
    }
}

/// Tables built lately, reused while a packet's constants stay the same (every healthy cycle).
#[derive(Debug, Default)]
pub struct BreathCache {
    built: Vec<(PvState, Breathing)>,
}

impl BreathCache {
    fn get(&mut self, pv: &PvState, hz: f64, side: Side) -> Result<Breathing, RemoteStateError> {
        if let Some((_, b)) = self.built.iter().find(|(p, _)| p == pv) {
            return Ok(b.clone());
        }
        let b = breathing_of(pv, hz, side)?;
        if self.built.len() >= 4 {
            self.built.remove(0);
        }
        self.built.push((pv.clone(), b.clone()));
        Ok(b)
    }
}

impl Prepared {
    /// Build what `state` needs (allocates; call off the tick).
    pub fn of(state: ControlState, cache: &mut BreathCache) -> Result<Self, RemoteStateError> {
        let mut breaths = Vec::with_capacity(state.lungs.len());
        for l in state.lungs.iter() {
            let side = side_of(l.side);
            let now = cache.get(&l.pv, state.tick_hz, side)?;
            let next = match &l.next {
                Some(n) => Some(cache.get(n, state.tick_hz, side)?),
                None => None,
            };
            breaths.push((now, next));
        }
        let pending = match &state.pending {
            None => None,
            Some(p) => {
                let mut lungs = Vec::with_capacity(p.lungs.len());
                for l in p.lungs.iter() {
                    let side = side_of(l.side);
                    let breathing = match &l.pv {
                        Some(pv) => Some(cache.get(pv, state.tick_hz, side)?),
                        None => None,
                    };
                    let change = super::disease::LungChange {
                        collapse: l.collapse,
                        offset_mm: l.offset_mm,
                        base_ml: l.base_ml,
                        held_ml: l.held_ml,
                    };
                    lungs.push((side, change, breathing));
                }
                Some(RemotePending {
                    tick: p.apply_tick,
                    lungs,
                })
            }
        };
        Ok(Self {
            state,
            breaths,
            pending,
        })
    }
}

/// When a source's control state must go out: a lung started a cycle, the patient's breath moved
/// (a new turn, or the signal no longer driving: a source following a live signal), or a disease
/// cycle was prepared (announced before it starts, so every site puts it in at the same tick). The
/// engine process and [`super::sites::follow`] decide alike. A few compares, no allocation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StateSchedule {
    starts: [u64; ipc_types::NUM_LUNGS],
    pending: Option<u64>,
    live: u64,
}

impl Default for StateSchedule {
    fn default() -> Self {
        Self {
            starts: [u64::MAX; ipc_types::NUM_LUNGS],
            pending: None,
            live: 0,
        }
    }
}

impl StateSchedule {
    /// Whether `core` changed since the last call in a way its sites must hear of now (the first
    /// call always: no cycle start has been sent).
    pub fn changed(&mut self, core: &EngineCore) -> bool {
        let mut changed = false;
        for (k, start) in core.cycle_starts().enumerate().take(self.starts.len()) {
            if self.starts[k] != start {
                self.starts[k] = start;
                changed = true;
            }
        }
        let live = core.live_generation();
        if live != self.live {
            self.live = live;
            changed = true;
        }
        let pending = core.pending_course();
        if pending != self.pending {
            self.pending = pending;
            changed |= pending.is_some();
        }
        changed
    }
}

/// Ticks over which a site's breath moves onto a newly announced patient turn (200 ms at 60 Hz):
/// the difference between the breath it played and the new one fades out instead of jumping.
pub const REALIGN_TICKS: u64 = 12;

/// The patient's breath a site plays (a source following a live signal): the previous breath from
/// the start of the one in progress, each lung its share, as the source's lungs take theirs.
#[derive(Debug, Clone)]
pub struct RemoteLive {
    breath: LiveBreath,
    /// A new breath arrived: re-align on the next tick.
    fresh: bool,
    /// The tick the patient's breath took over from the model here (the same blend as a source's).
    from: Option<u64>,
    /// The difference to fade out after a re-alignment, ml, and the tick it was taken at.
    offset: (f64, u64),
    /// The volume played on the previous tick.
    played: Option<f64>,
    /// Patient breaths taken from the source.
    breaths: u64,
    /// The tick of the newest turn announced (a breath's start or its peak), and how many ticks
    /// after it the site first played it (taken by the engine's counts).
    turn: u64,
    pub(super) heard: Option<u64>,
    /// How long the latest turns took to reach this site, ticks (the newest [`LAGS_KEPT`]; not
    /// the breath the site joined on, whose turn may be long past): a breath the patient started
    /// on rhythm is heard within the longest of them, so a breath predicted on the rhythm waits
    /// that long (and [`control_state::RHYTHM_FADE_TICKS`] more) before it is taken back.
    lags: lung_model::breathing::Ring<u64, LAGS_KEPT>,
    /// The breath joined on was taken (its lag is not kept).
    joined: bool,
}

/// Turn lags a site keeps to judge when a breath predicted on the patient's rhythm is overdue (a
/// lag from a lost and resent state leaves them after this many turns: four breaths).
pub const LAGS_KEPT: usize = 8;

/// A site's patience before the first turn is heard after joining: 2 s at 60 Hz (a second's
/// network delay and the source's confirmation of a turn).
const FIRST_PATIENCE_TICKS: u64 = 120;

/// How late the patient's turns reached a site: from the tick of the turn at the source (where the
/// patient's volume was lowest or highest) to the site's first tick playing it — the source's
/// confirmation of the turn (its follower's hysteresis) plus the network and the site's schedule.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TurnLag {
    /// Turns heard.
    pub turns: u64,
    /// The sum of their lags, ticks.
    pub sum_ticks: u64,
    /// The largest, ticks.
    pub max_ticks: u64,
}

impl TurnLag {
    pub(super) fn add(&mut self, ticks: u64) {
        self.turns += 1;
        self.sum_ticks += ticks;
        self.max_ticks = self.max_ticks.max(ticks);
    }

    /// The mean lag, ms, at `tick_hz` (`None` before a turn).
    pub fn mean_ms(&self, tick_hz: f64) -> Option<f64> {
        (self.turns > 0).then(|| self.sum_ticks as f64 / self.turns as f64 * 1e3 / tick_hz)
    }
}

impl RemoteLive {
    fn new(breath: LiveBreath) -> Self {
        Self {
            fresh: true,
            from: None,
            offset: (0.0, 0),
            played: None,
            breaths: 1,
            turn: Self::turn_of(&breath),
            heard: None,
            lags: Default::default(),
            joined: false,
            breath,
        }
    }

    /// The newest turn a breath announces: its peak once expiring, else its start.
    fn turn_of(b: &LiveBreath) -> u64 {
        b.peak.map_or(b.start_tick, |(t, _)| t)
    }

    /// The patient breaths taken from the source so far.
    pub fn breaths(&self) -> u64 {
        self.breaths
    }

    /// Drive every lung with the patient's breath at `tick`; the state bits. No allocation.
    pub(super) fn tick(
        &mut self,
        tick: u64,
        lungs: &mut [(super::LungGeometry, LungBreath)],
    ) -> u32 {
        let fresh = std::mem::take(&mut self.fresh);
        if fresh {
            let late = tick.saturating_sub(self.turn);
            // The breath joined on is no measure of the lag (its turn may be long past).
            if std::mem::replace(&mut self.joined, true) {
                self.lags.push(late);
            }
            self.heard = Some(late);
        }
        let slowest = (0..LAGS_KEPT)
            .filter_map(|k| self.lags.back(k))
            .max()
            .unwrap_or(FIRST_PATIENCE_TICKS);
        let patience = slowest.saturating_add(control_state::RHYTHM_FADE_TICKS);
        let (v, inhaling) = self.breath.volume_on_rhythm(tick, patience);
        if fresh {
            self.offset = (self.played.map_or(0.0, |p| p - v), tick);
        }
        let fade = 1.0 - (tick.saturating_sub(self.offset.1) as f64 / REALIGN_TICKS as f64);
        let volume = v + self.offset.0 * fade.clamp(0.0, 1.0);
        let from = *self.from.get_or_insert(tick);
        let w = ((tick.saturating_sub(from) + 1) as f64 / super::signal::TAKEOVER_TICKS as f64)
            .min(1.0);
        for (_, b) in lungs.iter_mut() {
            b.driven = Some((volume, inhaling, w));
        }
        self.played = Some(volume);
        use ipc_types::engine_state::{SIGNAL_CLIPPED, SIGNAL_FOLLOWING};
        let clipped = if self.breath.clipped {
            SIGNAL_CLIPPED
        } else {
            0
        };
        SIGNAL_FOLLOWING | clipped
    }
}

impl EngineCore {
    /// The patient's breath this site plays, when its source follows a live signal.
    pub fn remote_live(&self) -> Option<&RemoteLive> {
        self.remote_live.as_ref()
    }

    /// How late the patient's turns reached this site so far (a site of a source following a live
    /// signal; nothing otherwise).
    pub fn patient_turn_lag(&self) -> TurnLag {
        self.turn_lag
    }

    /// Changes to what a source tells its sites of the patient's breath (a new breath, or the
    /// signal no longer driving): the process publishes a state when it moves. 0 without a signal.
    pub fn live_generation(&self) -> u64 {
        self.signal.as_ref().map_or(0, |s| s.live_generation())
    }

    /// The patient's breath from a site's state: a new one re-aligns, the same one carries on,
    /// none hands the lungs back to the model (the state's cycles say where it is).
    fn take_live(&mut self, live: Option<LiveBreath>) {
        match (live, &mut self.remote_live) {
            (Some(b), Some(r)) => {
                let new_breath = (b.breath, b.start_tick) != (r.breath.breath, r.breath.start_tick);
                if new_breath || b.peak != r.breath.peak {
                    r.breaths += u64::from(new_breath);
                    r.turn = RemoteLive::turn_of(&b);
                    r.breath = b;
                    r.fresh = true;
                } else {
                    // The same breath: only what the source says of its signal may have changed.
                    r.breath.clipped = b.clipped;
                }
            }
            (Some(b), None) => self.remote_live = Some(RemoteLive::new(b)),
            (None, _) => {
                if self.remote_live.take().is_some() {
                    for (_, b) in self.lungs.iter_mut() {
                        b.driven = None;
                    }
                }
            }
        }
    }

    /// The control state at `tick` (call at a cycle start or after a change; allocates the
    /// constants' vectors, so after the tick's publish). `events` are the latest interventions.
    pub fn control_state(
        &self,
        tick: u64,
        stamp: StateStamp,
        events: &[RemoteEvent],
    ) -> Result<ControlState, RemoteStateError> {
        let mut lungs = Bounded::default();
        for (g, b) in &self.lungs {
            lungs.push(b.state(g.side)?);
        }
        let disease = match &self.disease {
            None => Disease::None,
            Some(DiseaseRun::Closed(setups, _)) => Disease::ClosedPneumothorax {
                side: setups.first().map_or(0, |s| s.side.index() as u8),
            },
            Some(DiseaseRun::Tension(run)) => Disease::TensionPneumothorax {
                side: run.affected().index() as u8,
                cycles_run: run.cycles_run,
            },
            Some(DiseaseRun::Tumour(t)) => Disease::Tumour {
                side: t.side.index() as u8,
            },
        };
        let first = events.len().saturating_sub(MAX_EVENTS);
        let pending = self.pending_cycle()?;
        Ok(ControlState {
            source: stamp.source,
            epoch: stamp.epoch,
            sequence: stamp.sequence,
            tick,
            tick_hz: stamp.tick_hz,
            source_time_ns: stamp.source_time_ns,
            cycle: self.lungs.first().map_or(0, |(_, b)| b.cycle as u64),
            gravity_body: self.gravity_body.to_array(),
            disease,
            lungs,
            live: self.signal.as_ref().and_then(|s| s.live()),
            events: Bounded::new(events[first..].to_vec()).unwrap_or_default(),
            pending,
        })
    }

    /// The disease cycle prepared and not yet started, with the tick and breathing cycle it starts
    /// at (`None` without one: healthy lungs, a closed pneumothorax, a cycle still being built).
    pub fn pending_cycle(&self) -> Result<Option<PendingCycle>, RemoteStateError> {
        let Some(super::disease::DiseaseRun::Tension(run)) = &self.disease else {
            return Ok(None);
        };
        let Some((c, apply_tick)) = run.pending(&self.lungs) else {
            return Ok(None);
        };
        let mut lungs = Bounded::default();
        for l in &c.lungs {
            lungs.push(PendingLung {
                side: l.side.index() as u8,
                pv: l
                    .breathing
                    .as_ref()
                    .map(|b| pv_state(b, l.side))
                    .transpose()?,
                collapse: l.state.collapse,
                offset_mm: l.state.offset_mm,
                base_ml: l.state.base_volume_ml,
                held_ml: l.state.held_ml,
            });
        }
        Ok(Some(PendingCycle {
            apply_tick,
            apply_cycle: self.cycle_at(apply_tick),
            course_cycle: c.cycle,
            lungs,
        }))
    }

    /// The disease course's cycle prepared and not yet started (cheap: no allocation).
    pub fn pending_course(&self) -> Option<u64> {
        match &self.disease {
            Some(super::disease::DiseaseRun::Tension(run)) => {
                run.pending(&self.lungs).map(|(c, _)| c.cycle)
            }
            _ => None,
        }
    }

    /// The breathing cycle (as [`ControlState::cycle`] counts: the first lung's) that a cycle start
    /// at `tick` begins, from the lungs as stepped so far.
    pub fn cycle_at(&self, tick: u64) -> u64 {
        self.lungs.first().map_or(0, |(_, b)| {
            let ct = (b.breathing.cycle_ticks() as u64).max(1);
            b.cycle as u64 + tick.saturating_sub(b.cycle_start) / ct
        })
    }

    /// The source tick and breathing cycle from which the disease course's cycle `course` shows:
    /// the prepared one's, or, once it is in the lungs, the tick it started at (`None` for a cycle
    /// neither prepared nor started yet, or without a tension pneumothorax).
    pub fn course_cycle_start(&self, course: u64) -> Option<(u64, u64)> {
        let Some(super::disease::DiseaseRun::Tension(run)) = &self.disease else {
            return None;
        };
        if let Some((c, at)) = run.pending(&self.lungs) {
            if c.cycle == course {
                return Some((at, self.cycle_at(at)));
            }
        }
        let (last, at) = run.last_course()?;
        (course <= last).then(|| {
            // Started already (a cycle waited for at its start tick): counted back from the first
            // lung's current cycle.
            let cycle = self.lungs.first().map_or(0, |(_, b)| {
                let ct = (b.breathing.cycle_ticks() as u64).max(1);
                (b.cycle as u64).saturating_sub(b.cycle_start.saturating_sub(at).div_ceil(ct))
            });
            (at, cycle)
        })
    }

    /// Drive this (site) engine from a source's state: each lung breathes the source's cycle,
    /// share, held/base volume, collapse and offset, its cycle aligned to the source's tick
    /// numbers; gravity is the source's. `site_hz` is this site's tick rate. No allocation (the
    /// prepared tables are moved in).
    pub fn apply_prepared(
        &mut self,
        mut p: Prepared,
        site_hz: f64,
    ) -> Result<(), RemoteStateError> {
        // The cycle put in last is freed here, off the tick it was put in at.
        self.remote_spent = None;
        let hz = p.state.tick_hz;
        if hz != site_hz {
            return Err(RemoteStateError::TickRate {
                source_hz: hz,
                site_hz,
            });
        }
        for l in p.state.lungs.iter() {
            let side = side_of(l.side);
            if self.lung(side).is_none() {
                return Err(RemoteStateError::MissingLung { side: side.name() });
            }
        }
        for (l, (now, next)) in p.state.lungs.iter().zip(p.breaths) {
            let Some(b) = self.lung_mut(side_of(l.side)) else {
                continue;
            };
            b.breathing = now;
            b.next = next;
            b.share = l.share;
            b.held_ml = l.held_ml;
            b.base_ml = l.base_ml;
            b.collapse = l.collapse.clamp(0.0, 1.0);
            b.offset_mm = l.offset_mm;
            b.cycle = l.cycle;
            b.cycle_start = l.cycle_start_tick;
        }
        let g = glam::DVec3::from(p.state.gravity_body);
        if g.is_finite() && g.length() > 0.0 {
            self.gravity_body = g.normalize();
        }
        // The state is the source's whole word: a cycle it no longer announces is not pending.
        self.remote_pending = p.pending;
        self.take_live(p.state.live.take());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use control_state::{decode, encode_to_vec, Packet};
    use ipc_types::EngineFrame;
    use lung_model::scene::Scene;

    fn core(scene: &Scene) -> EngineCore {
        crate::runtime::generated_core(scene)
    }

    fn stamp(tick: u64) -> StateStamp {
        StateStamp {
            source: 7,
            epoch: 1,
            sequence: tick,
            tick_hz: 60.0,
            source_time_ns: tick * 16_666_667,
        }
    }

    /// Through the wire: encode, decode, prepare.
    fn over_the_wire(s: ControlState, cache: &mut BreathCache) -> Prepared {
        let Packet::State(s) = decode(&encode_to_vec(&Packet::State(s)).unwrap()).unwrap() else {
            panic!("not a state")
        };
        Prepared::of(s, cache).unwrap()
    }

    /// A site whose own scene breathes differently (20 breaths/min, another TV), joining late at
    /// tick 400 with the source's last packet, then fed each cycle's packet, shows the source's
    /// breath bit for bit at every tick (the same packets give the same breath).
    #[test]
    fn a_late_site_driven_by_packets_breathes_the_sources_breath_bit_for_bit() {
        let mut source_scene = Scene::default();
        source_scene.pv.breaths_per_min = 14.0;
        let mut source = core(&source_scene);
        let mut site_scene = Scene::default();
        site_scene.pv.breaths_per_min = 20.0;
        let mut site = core(&site_scene);
        let (mut a, mut b) = (EngineFrame::default(), EngineFrame::default());
        let mut cache = BreathCache::default();
        let mut last = None;
        let mut starts = [u64::MAX; 2];
        let mut compared = 0;
        for tick in 0..1200u64 {
            source.step(tick, None, &mut a);
            let now: Vec<u64> = source.cycle_starts().collect();
            if now[..] != starts[..] {
                starts.copy_from_slice(&now);
                last = Some(source.control_state(tick, stamp(tick), &[]).unwrap());
                if tick >= 400 {
                    let p = over_the_wire(last.clone().unwrap(), &mut cache);
                    site.apply_prepared(p, 60.0).unwrap();
                }
            }
            if tick == 400 {
                // Late join: the latest state the source published (a cycle start before 400).
                let p = over_the_wire(last.clone().unwrap(), &mut cache);
                site.apply_prepared(p, 60.0).unwrap();
            }
            if tick >= 400 {
                site.step(tick, None, &mut b);
                for k in 0..2 {
                    assert_eq!(
                        a.lungs[k].volume_ml.to_bits(),
                        b.lungs[k].volume_ml.to_bits(),
                        "tick {tick} lung {k}"
                    );
                    assert_eq!(
                        a.lungs[k].deform_scale.to_bits(),
                        b.lungs[k].deform_scale.to_bits()
                    );
                    assert_eq!(a.lungs[k].phase.to_bits(), b.lungs[k].phase.to_bits());
                    assert_eq!(a.lungs[k].cycle, b.lungs[k].cycle);
                }
                compared += 1;
            }
        }
        assert_eq!(compared, 800);
        // 14 breaths/min at 60 Hz: a packet every 257 ticks.
        assert_eq!(source.cycle_ticks(), 257);
    }

    #[test]
    fn a_packet_the_site_cannot_use_is_refused_with_the_reason() {
        let scene = Scene::default();
        let source = core(&scene);
        let mut cache = BreathCache::default();
        let s = source.control_state(0, stamp(0), &[]).unwrap();
        let mut site = core(&scene);
        let e = site
            .apply_prepared(Prepared::of(s.clone(), &mut cache).unwrap(), 90.0)
            .unwrap_err();
        assert!(e.to_string().contains("60 Hz, this site at 90 Hz"), "{e}");
        // An implausible tidal volume (finite, so the codec passes it) is the engine's to refuse.
        let mut bad = s.clone();
        for l in [0, 1] {
            let mut lungs = bad.lungs.to_vec();
            lungs[l].pv.tv_ml = 1e6;
            bad.lungs = Bounded::new(lungs).unwrap();
        }
        let e = Prepared::of(bad, &mut cache).unwrap_err();
        assert!(e.to_string().contains("right lung"), "{e}");
        // A site simulating one lung refuses a packet naming the other.
        let mut one = core(&scene);
        one.lungs.truncate(1);
        let e = one
            .apply_prepared(Prepared::of(s, &mut cache).unwrap(), 60.0)
            .unwrap_err();
        assert!(e.to_string().contains("left lung"), "{e}");
    }
}
