//! # disease: a scene's disease state applied to the lungs' breathing (EQUATIONS.md §4)
//!
//! The disease model itself is `lung_model::disease` (closed pneumothorax eq. 8.1–8.9, tension
//! pneumothorax eq. 8.10–8.13 with interventions). This module turns it into what each lung's
//! [`LungBreath`] does, and keeps the tick free of allocation and of the model's arithmetic:
//!
//! * **Closed pneumothorax** (one or both lungs): a state, not an event — the plan is applied when the
//!   engine is built: each lung breathes its plan's cycle (faster, eq. 8.3–8.5; its own tidal volume,
//!   eq. 8.6–8.7; eq. 8.8–8.9 constants for an affected lung) from its collapsed base volume, collapsed
//!   towards its hilum (`dV` of eq. 8.1 as an exact volume loss) and dropped (eq. 8.2).
//! * **Tension pneumothorax**: deterministic in breathing cycles. The state machine
//!   ([`Tension`]) advances once per cycle of the affected lung; each cycle's lung states and PV
//!   cycles are *prepared one cycle ahead* by [`TensionRun::prepare_ahead`], which the process loop
//!   calls after publishing a frame (where the slack of the tick period is; it allocates the cycle's
//!   tables), and [`DiseaseRun::before_tick`] moves the prepared cycle into both lungs at the tick the
//!   affected lung starts a new cycle (a move: the tick itself never allocates). Interventions — the
//!   scene's `[[disease.events]]` at their time, and a trainee's actions arriving live
//!   ([`TensionRun::intervene_live`], `lungdyn scene event`) — are applied to the state machine when
//!   the next cycle is prepared: an intervention arriving at tick `T` with `S_{k−1} < T ≤ S_k` (cycle
//!   starts) shows from cycle `k + 1`, i.e. within two breaths. The same rule in
//!   `lungdyn scene check` gives the same course. Before the onset both lungs breathe normally.
//!
//! * **Tumour** (seed §8.2): the kernel carries the change of the lung's deformation (baked with the
//!   tumour region; `Scene::lung_kernel` refuses a kernel with another tumour or none); the run
//!   raises the affected lung's PV resistance in both phases ([`TumourRun`]), once, at the start.

use lung_model::disease::closed::ClosedPlan;
use lung_model::disease::tension::{EventRecord, Intervention, Tension};
use lung_model::disease::ventilated::{DeliveryLog, Ventilator};
use lung_model::disease::{DiseaseError, LungBaseline, LungState, NormalBreathing};
use lung_model::mesh::Side;
use lung_model::pv::{Breathing, PhaseConstants, PvError};
use lung_model::scene_disease::{DiseaseSpec, TimedEvent};
use thiserror::Error;

use super::LungBreath;

/// Why a scene's disease state cannot be run.
#[derive(Debug, Error)]
pub enum DiseaseRunError {
    /// The disease model refused the scene's lungs or constants.
    #[error("the disease model: {0}")]
    Model(#[from] DiseaseError),
    /// A lung's changed PV cycle cannot be precomputed.
    #[error("the {side} lung's PV cycle under the disease state: {source}")]
    Breathing {
        /// Which lung.
        side: &'static str,
        /// Why.
        source: PvError,
    },
    /// The kind is not run by the engine.
    #[error("[disease] kind {0} is not run by the engine")]
    NotRun(&'static str),
    /// The thread that builds disease cycles stopped.
    #[error("the disease worker thread stopped")]
    WorkerGone,
}

/// What one lung does from one cycle on.
#[derive(Debug, Clone)]
pub struct LungSetup {
    /// Which lung.
    pub side: Side,
    /// The lung's state (collapse, base volume, tidal volume, hold, offset).
    pub state: LungState,
    /// Its PV cycle (`None` when held).
    pub breathing: Option<Breathing>,
}

/// One prepared cycle of a tension pneumothorax.
#[derive(Debug, Clone)]
pub struct CourseCycle {
    /// The course's cycle number (0 = the onset).
    pub cycle: u64,
    /// The lungs' setups.
    pub lungs: Vec<LungSetup>,
    /// Arrest in this cycle.
    pub arrest: bool,
    /// Pleural air, ml.
    pub pleural_air_ml: f64,
}

/// A disease state being run.
#[derive(Debug, Clone)]
pub enum DiseaseRun {
    /// Applied once when the engine is built; on a ventilated scene with what the ventilator
    /// delivers (EQUATIONS §4.7).
    Closed(Vec<LungSetup>, Option<DeliveryLog>),
    /// Tension pneumothorax (boxed: its run is by far the largest variant; the box is allocated
    /// once, when the scene is built, and the tick only reads through it).
    Tension(Box<TensionRun>),
    /// Tumour-influenced lung: applied once when the engine is built.
    Tumour(Box<TumourRun>),
}

/// A tumour-influenced lung (seed §8.2): its kernel change is in the kernel (baked with the tumour
/// region, `lungdyn bake`/`scene prepare`); what the run adds is the raised resistance of both
/// phases (eq. 8.9 with `x = φ_r·min(1, V_tumour/V_lung)`, §8.1.3) on the affected lung's PV
/// cycle. The other lung breathes normally.
#[derive(Debug, Clone)]
pub struct TumourRun {
    /// The affected lung.
    pub side: Side,
    /// Its PV cycle with the raised resistance (moved into the lung when the engine is built);
    /// `None` on a ventilated scene (the lung plays the recorded breath).
    pub breathing: Option<Breathing>,
    /// The changed constants, inhale and exhale.
    pub constants: (PhaseConstants, PhaseConstants),
    /// What eq. 8.9 did to each phase.
    pub resistance: [lung_model::disease::resistance::ResistanceReport; 2],
}

/// A tension pneumothorax being run, one cycle prepared ahead.
#[derive(Debug, Clone)]
pub struct TensionRun {
    tension: Tension,
    normal: NormalBreathing,
    shares: Vec<(Side, f64)>,
    affected: Side,
    onset_tick: u64,
    timed: Vec<TimedEvent>,
    next_timed: usize,
    /// Live actions waiting for the next preparation: arrival tick, kind, side, sender's tag.
    live: Vec<(u64, Intervention, Side, u64)>,
    prepared: Option<CourseCycle>,
    spent: Option<CourseCycle>,
    started: bool,
    last_start: u64,
    /// The last course cycle moved into the lungs and the tick it started at.
    last_course: Option<(u64, u64)>,
    inhale: PhaseConstants,
    exhale: PhaseConstants,
    /// The ventilator of a `[pv] waveform` scene (its recorded breath, the volume it delivers, its
    /// control mode; EQUATIONS §4.7), instead of PV cycles.
    ventilator: Option<Ventilator>,
    /// What the ventilator delivered, cycle by cycle (`None` without one).
    pub delivery: Option<DeliveryLog>,
    /// Cycles moved into the lungs so far.
    pub cycles_run: u64,
    requested: bool,
    /// The interventions as applied (arrival tick, cycle, outcome), in order.
    pub events: Vec<EventRecord>,
    /// The sender's tag of each of [`Self::events`] (0: a timed event of the scene).
    event_tags: Vec<u64>,
    /// Events reported by [`TensionRun::take_new_events`] so far.
    reported: usize,
    /// First course cycle in arrest, if any.
    pub first_arrest: Option<u64>,
}

/// Live actions queued between two preparations (more are refused, not queued, and the sender is
/// told): room for every one of the transport's senders at once, each with one action in flight.
pub const MAX_QUEUED_ACTIONS: usize = 64;

/// What a lung's cycle is built from.
#[derive(Debug, Clone)]
pub enum LungTable {
    /// A PV cycle (eq. 5.11) from these constants, boundary values and timing.
    Pv(
        PhaseConstants,
        PhaseConstants,
        lung_model::pv::Boundary,
        lung_model::pv::Timing,
    ),
    /// The ventilator's recorded breath scaled to this tidal volume (TV, ml; EQUATIONS §4.7).
    Recorded(Breathing, f64),
}

/// One lung's part of a [`Recipe`].
#[derive(Debug, Clone)]
pub struct LungRecipe {
    /// The lung's state.
    pub state: LungState,
    /// Its cycle's inputs (`None` when held).
    pub pv: Option<LungTable>,
}

/// Everything needed to build one prepared cycle (the expensive part: the PV cycles).
#[derive(Debug, Clone)]
pub struct Recipe {
    /// The course's cycle number.
    pub cycle: u64,
    /// Arrest in this cycle.
    pub arrest: bool,
    /// Pleural air, ml.
    pub pleural_air_ml: f64,
    /// The lungs.
    pub lungs: Vec<LungRecipe>,
}

impl Recipe {
    /// Build the cycle's PV tables (allocates; ≈ 20 ms per lung on the 2-core VM).
    pub fn build(self) -> Result<CourseCycle, DiseaseRunError> {
        let mut lungs = Vec::with_capacity(self.lungs.len());
        for l in self.lungs {
            let breathing = match l.pv {
                Some(LungTable::Pv(i, e, b, t)) => Some(Breathing::from_constants(&i, &e, b, &t)),
                Some(LungTable::Recorded(r, tv)) => Some(r.rescaled(tv)),
                None => None,
            }
            .transpose()
            .map_err(|source| DiseaseRunError::Breathing {
                side: l.state.side.name(),
                source,
            })?;
            lungs.push(LungSetup {
                side: l.state.side,
                state: l.state,
                breathing,
            });
        }
        Ok(CourseCycle {
            cycle: self.cycle,
            lungs,
            arrest: self.arrest,
            pleural_air_ml: self.pleural_air_ml,
        })
    }
}

impl DiseaseRun {
    /// Prepare `spec` for lungs with `baselines` (the scene's order) breathing `normal`, with the
    /// engine's tick rate. `ventilator`: that of a `[pv] waveform` scene, whose breath the lungs
    /// share instead of PV cycles (`normal` from
    /// [`lung_model::disease::ventilated::normal_breathing`]; EQUATIONS §4.7).
    pub fn prepare(
        spec: &DiseaseSpec,
        normal: &NormalBreathing,
        baselines: &[LungBaseline],
        ventilator: Option<&Ventilator>,
    ) -> Result<Self, DiseaseRunError> {
        match spec {
            DiseaseSpec::Closed(c) => {
                let mut plan: ClosedPlan = c.plan(normal, baselines)?;
                let mut log = None;
                let mut breath = None;
                if let Some(v) = ventilator {
                    let mut states: Vec<LungState> = plan.lungs.iter().map(|l| l.state).collect();
                    let (d, b) =
                        v.deliver(&mut states)
                            .map_err(|source| DiseaseRunError::Breathing {
                                side: "ventilated",
                                source,
                            })?;
                    let mut l = DeliveryLog::new(d.control);
                    l.record(&d);
                    log = Some(l);
                    breath = b;
                    for (l, s) in plan.lungs.iter_mut().zip(states) {
                        l.state = s;
                    }
                }
                let mut lungs = Vec::new();
                for l in &plan.lungs {
                    let share = baselines
                        .iter()
                        .find(|b| b.side == l.side)
                        .map_or(1.0, |b| b.share);
                    let breathing = match ventilator {
                        Some(v) => v
                            .lung_table(breath.as_ref(), &l.state, share)
                            .map(|(r, tv)| r.rescaled(tv)),
                        None => l.breathing(&plan.timing),
                    }
                    .transpose()
                    .map_err(|source| DiseaseRunError::Breathing {
                        side: l.side.name(),
                        source,
                    })?;
                    lungs.push(LungSetup {
                        side: l.side,
                        state: l.state,
                        breathing,
                    });
                }
                Ok(DiseaseRun::Closed(lungs, log))
            }
            DiseaseSpec::Tension {
                params,
                onset_s,
                events,
            } => Ok(DiseaseRun::Tension(Box::new(TensionRun::prepare(
                *params, *onset_s, events, normal, baselines, ventilator,
            )?))),
            DiseaseSpec::Tumour(t) => {
                let lung = baselines.iter().find(|b| b.side == t.side).ok_or(
                    DiseaseError::MissingLung {
                        side: t.side.name(),
                    },
                )?;
                let (i, e, resistance) =
                    t.resistance(&normal.inhale, &normal.exhale, lung.start_volume_ml)?;
                // A ventilated lung plays the recorded breath: the resistance raises the airway
                // pressure, not the delivered volume (EQUATIONS §4.7); the kernel carries the tumour.
                let breathing = match ventilator {
                    Some(_) => None,
                    None => Some(
                        Breathing::from_constants(&i, &e, normal.boundary, &normal.timing)
                            .map_err(|source| DiseaseRunError::Breathing {
                                side: t.side.name(),
                                source,
                            })?,
                    ),
                };
                Ok(DiseaseRun::Tumour(Box::new(TumourRun {
                    side: t.side,
                    breathing,
                    constants: (i, e),
                    resistance,
                })))
            }
        }
    }
}

impl TensionRun {
    fn prepare(
        params: lung_model::disease::tension::TensionParams,
        onset_s: f64,
        events: &[TimedEvent],
        normal: &NormalBreathing,
        baselines: &[LungBaseline],
        ventilator: Option<&Ventilator>,
    ) -> Result<Self, DiseaseRunError> {
        let affected =
            *baselines
                .iter()
                .find(|b| b.side == params.side)
                .ok_or(DiseaseError::MissingLung {
                    side: params.side.name(),
                })?;
        let other = baselines.iter().find(|b| b.side != params.side).copied();
        let tension = Tension::new(params, normal.timing, normal.boundary, affected, other)?;
        tension.check_constants(&normal.inhale, &normal.exhale)?;
        let mut timed = events.to_vec();
        timed.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
        let mut run = Self {
            tension,
            normal: normal.clone(),
            shares: baselines.iter().map(|b| (b.side, b.share)).collect(),
            affected: params.side,
            onset_tick: (onset_s * normal.timing.tick_hz).round() as u64,
            timed,
            next_timed: 0,
            live: Vec::with_capacity(MAX_QUEUED_ACTIONS),
            prepared: None,
            spent: None,
            started: false,
            last_start: 0,
            last_course: None,
            inhale: normal.inhale.clone(),
            exhale: normal.exhale.clone(),
            ventilator: ventilator.cloned(),
            delivery: ventilator.map(|v| DeliveryLog::new(v.control.mode())),
            cycles_run: 0,
            requested: false,
            events: Vec::with_capacity(64),
            event_tags: Vec::with_capacity(64),
            reported: 0,
            first_arrest: None,
        };
        run.prepare_ahead()?;
        Ok(run)
    }

    /// Queue a trainee's action that arrived at `tick`; it is applied when the next cycle is
    /// prepared, and [`Self::take_new_events`] reports it with `tag` (the sender's sequence
    /// number). `false` when the queue is full (the action is dropped and the caller says so).
    pub fn intervene_live(&mut self, tick: u64, kind: Intervention, side: Side, tag: u64) -> bool {
        if self.live.len() >= MAX_QUEUED_ACTIONS {
            return false;
        }
        self.live.push((tick, kind, side, tag));
        true
    }

    /// The work of preparing the next cycle, split so the expensive part can run on another
    /// thread: the state machine's step is taken here (the interventions due — timed ones at or
    /// before the last cycle start, every queued live one — then one cycle; cheap), the PV cycles are
    /// built by [`Recipe::build`]. `None` when a cycle is prepared or already requested.
    pub fn next_recipe(&mut self) -> Result<Option<Recipe>, DiseaseRunError> {
        self.spent = None;
        if self.prepared.is_some() || self.requested {
            return Ok(None);
        }
        let tick_hz = self.normal.timing.tick_hz;
        if self.started {
            while let Some(e) = self.timed.get(self.next_timed) {
                if e.tick(tick_hz) > self.last_start {
                    break;
                }
                let r = self.tension.intervene(e.kind, e.side, e.tick(tick_hz));
                self.events.push(r);
                self.event_tags.push(0);
                self.next_timed += 1;
            }
            for (tick, kind, side, tag) in self.live.drain(..) {
                let r = self.tension.intervene(kind, side, tick);
                self.events.push(r);
                self.event_tags.push(tag);
            }
        }
        let c = self.tension.advance();
        let mut states = [Some(c.affected), c.unaffected];
        let mut breath = None;
        if let Some(v) = &self.ventilator {
            let mut breathing: Vec<LungState> = states.iter().flatten().copied().collect();
            let (d, b) =
                v.deliver(&mut breathing)
                    .map_err(|source| DiseaseRunError::Breathing {
                        side: "ventilated",
                        source,
                    })?;
            if let Some(log) = &mut self.delivery {
                log.record(&d);
            }
            breath = b;
            for (s, d) in states.iter_mut().flatten().zip(breathing) {
                *s = d;
            }
        }
        let mut lungs = Vec::with_capacity(2);
        for state in states.into_iter().flatten() {
            let share = self
                .shares
                .iter()
                .find(|(s, _)| *s == state.side)
                .map(|&(_, s)| s)
                .expect("the course's lungs are the scene's");
            let normal = &self.normal;
            if let Some(v) = &self.ventilator {
                lungs.push(LungRecipe {
                    state,
                    pv: v
                        .lung_table(breath.as_ref(), &state, share)
                        .map(|(r, tv)| LungTable::Recorded(r, tv)),
                });
                continue;
            }
            let (inhale, exhale) = if state.side == self.affected {
                self.tension.constants_into(
                    state.resistance_dv,
                    (&normal.inhale, &normal.exhale),
                    (&mut self.inhale, &mut self.exhale),
                )?;
                (self.inhale.clone(), self.exhale.clone())
            } else {
                (normal.inhale.clone(), normal.exhale.clone())
            };
            lungs.push(LungRecipe {
                state,
                pv: state
                    .boundary(&normal.boundary, share)
                    .map(|b| LungTable::Pv(inhale, exhale, b, c.timing)),
            });
        }
        self.first_arrest = self.tension.first_arrest();
        self.requested = true;
        Ok(Some(Recipe {
            cycle: c.cycle,
            arrest: c.arrest,
            pleural_air_ml: c.pleural_air_ml,
            lungs,
        }))
    }

    /// Hand over the cycle built from the last [`Self::next_recipe`].
    pub fn deliver(&mut self, cycle: CourseCycle) {
        self.prepared = Some(cycle);
        self.requested = false;
    }

    /// Prepare the next cycle here and now if it is not ready (tests, tools; the engine process
    /// builds it on a worker thread instead).
    pub fn prepare_ahead(&mut self) -> Result<(), DiseaseRunError> {
        if let Some(r) = self.next_recipe()? {
            let c = r.build()?;
            self.deliver(c);
        }
        Ok(())
    }

    /// Whether a new cycle of the affected lung starts at `tick` with its preparation requested but
    /// not delivered (the caller must deliver it before the tick, or the lungs would keep their
    /// state and the run would depend on thread timing).
    pub fn due_undelivered(&self, tick: u64, lungs: &[(super::LungGeometry, LungBreath)]) -> bool {
        self.requested && self.prepared.is_none() && self.cycle_starts(tick, lungs)
    }

    fn cycle_starts(&self, tick: u64, lungs: &[(super::LungGeometry, LungBreath)]) -> bool {
        if tick < self.onset_tick {
            return false;
        }
        let Some((_, b)) = lungs.iter().find(|(g, _)| g.side == self.affected) else {
            return false;
        };
        tick == 0 || tick.saturating_sub(b.cycle_start) >= b.breathing.cycle_ticks() as u64
    }

    /// Interventions applied since the last call (for the process's one line and reply per
    /// action), each with its sender's tag (0: a timed event of the scene).
    pub fn take_new_events(&mut self) -> impl Iterator<Item = (&EventRecord, u64)> + '_ {
        let from = self.reported;
        self.reported = self.events.len();
        self.events[from..]
            .iter()
            .zip(self.event_tags[from..].iter().copied())
    }

    /// The affected lung.
    pub fn affected(&self) -> Side {
        self.affected
    }

    /// The cycle prepared and not yet moved into the lungs, and the tick it will be moved in at:
    /// the affected lung's next cycle start at or after the onset (what [`Self::cycle_starts`]
    /// answers true for, given the lungs as stepped so far). What a source announces to its sites
    /// ahead of that tick.
    pub fn pending(
        &self,
        lungs: &[(super::LungGeometry, LungBreath)],
    ) -> Option<(&CourseCycle, u64)> {
        let c = self.prepared.as_ref()?;
        if !self.started && self.onset_tick == 0 {
            return Some((c, 0));
        }
        let (_, b) = lungs.iter().find(|(g, _)| g.side == self.affected)?;
        let ct = (b.breathing.cycle_ticks() as u64).max(1);
        let mut at = b.cycle_start + ct;
        if at < self.onset_tick {
            at += (self.onset_tick - at).div_ceil(ct) * ct;
        }
        Some((c, at))
    }

    /// The last course cycle moved into the lungs and the tick it started at.
    pub fn last_course(&self) -> Option<(u64, u64)> {
        self.last_course
    }
}

/// One lung's cycle-start change without its PV cycle: what [`put`] sets at once.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungChange {
    /// Collapse towards the hilum.
    pub collapse: f64,
    /// Rigid offset, body frame, mm.
    pub offset_mm: [f64; 3],
    /// Volume at the start of an inhalation, ml.
    pub base_ml: f64,
    /// Held volume, ml, when the lung stops breathing.
    pub held_ml: Option<f64>,
}

impl From<&LungState> for LungChange {
    fn from(s: &LungState) -> Self {
        Self {
            collapse: s.collapse,
            offset_mm: s.offset_mm,
            base_ml: s.base_volume_ml,
            held_ml: s.held_ml,
        }
    }
}

/// Put one lung's cycle-start change into `breath` (the disease course's, or a remote source's
/// announcement of it): collapse, offset, base volume and hold at once, the PV cycle `breathing`
/// from now (`now = true`) or from the lung's cycle that starts this tick.
pub fn put(breath: &mut LungBreath, s: LungChange, breathing: Option<Breathing>, now: bool) {
    breath.set_collapse(s.collapse);
    breath.set_offset_mm(s.offset_mm);
    breath.set_base_volume_ml(Some(s.base_ml));
    breath.hold(s.held_ml);
    if let Some(b) = breathing {
        if now {
            breath.breathing = b;
        } else {
            breath.set_breathing_from_next_cycle(b);
        }
    }
}

/// Put `setup` into `breath`: from now (`now = true`, at build time) or from the lung's cycle that
/// starts this tick.
pub fn apply(setup: &mut LungSetup, breath: &mut LungBreath, now: bool) {
    put(
        breath,
        LungChange::from(&setup.state),
        setup.breathing.take(),
        now,
    );
}

impl DiseaseRun {
    /// Before a tick: at the start of each new cycle of the affected lung after the onset, move the
    /// prepared cycle into the lungs. No allocation (a cycle not prepared in time leaves the lungs as
    /// they are: the process loop prepares one after every frame).
    pub fn before_tick(&mut self, tick: u64, lungs: &mut [(super::LungGeometry, LungBreath)]) {
        let DiseaseRun::Tension(run) = self else {
            return;
        };
        if !run.cycle_starts(tick, lungs) {
            return;
        }
        let Some(mut cycle) = run.prepared.take() else {
            return;
        };
        for setup in cycle.lungs.iter_mut() {
            if let Some((_, breath)) = lungs.iter_mut().find(|(g, _)| g.side == setup.side) {
                apply(setup, breath, tick == 0);
            }
        }
        // Freed by the next preparation, not in the tick.
        run.last_course = Some((cycle.cycle, tick));
        run.spent = Some(cycle);
        run.started = true;
        run.last_start = tick;
        run.cycles_run += 1;
    }

    /// See [`TensionRun::next_recipe`]; `None` for a closed pneumothorax.
    pub fn next_recipe(&mut self) -> Result<Option<Recipe>, DiseaseRunError> {
        match self {
            DiseaseRun::Tension(run) => run.next_recipe(),
            DiseaseRun::Closed(..) | DiseaseRun::Tumour(_) => Ok(None),
        }
    }

    /// What the ventilator of a `[pv] waveform` scene delivered (`None` without one; EQUATIONS
    /// §4.7).
    pub fn delivery(&self) -> Option<DeliveryLog> {
        match self {
            DiseaseRun::Closed(_, log) => *log,
            DiseaseRun::Tension(run) => run.delivery,
            DiseaseRun::Tumour(_) => None,
        }
    }

    /// See [`TensionRun::deliver`].
    pub fn deliver(&mut self, cycle: CourseCycle) {
        if let DiseaseRun::Tension(run) = self {
            run.deliver(cycle);
        }
    }

    /// See [`TensionRun::due_undelivered`].
    pub fn due_undelivered(&self, tick: u64, lungs: &[(super::LungGeometry, LungBreath)]) -> bool {
        match self {
            DiseaseRun::Tension(run) => run.due_undelivered(tick, lungs),
            DiseaseRun::Closed(..) | DiseaseRun::Tumour(_) => false,
        }
    }

    /// Prepare what the next cycle needs (see [`TensionRun::prepare_ahead`]); nothing for a closed
    /// pneumothorax.
    pub fn prepare_ahead(&mut self) -> Result<(), DiseaseRunError> {
        match self {
            DiseaseRun::Tension(run) => run.prepare_ahead(),
            DiseaseRun::Closed(..) | DiseaseRun::Tumour(_) => Ok(()),
        }
    }
}
