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
//! * **Tension pneumothorax**: the course is deterministic in breathing cycles, and the scene's
//!   interventions are timed, so the whole course — every cycle's lung states and PV cycles, each
//!   intervention applied at the first cycle that starts at or after its tick (it shows from that
//!   cycle, [`Tension::intervene`]) — is computed when the engine is built, until arrest with every
//!   intervention past, or [`MAX_COURSE_CYCLES`]. At run time each new cycle of the affected lung moves
//!   the next prepared cycle into both lungs (a move, no allocation); the last state then stays.
//!   Before the onset both lungs breathe normally.
//!
//! Events sent live to a running engine (a control channel) are not built: interventions come from the
//! scene's `[[disease.events]]`. A tumour needs a kernel baked with the tumour region and is refused
//! by the scene loader's caller (`Scene::refuse_unsimulated_disease`).

use lung_model::disease::closed::ClosedPlan;
use lung_model::disease::tension::{EventRecord, Tension};
use lung_model::disease::{DiseaseError, LungBaseline, LungState, NormalBreathing};
use lung_model::mesh::Side;
use lung_model::pv::{Breathing, PhaseConstants, PvError};
use lung_model::scene_disease::{DiseaseSpec, TimedEvent};
use thiserror::Error;

use super::LungBreath;

/// Most tension-pneumothorax cycles prepared (≈ 40 min at 25 breaths/min); the last one's state
/// stays after that.
pub const MAX_COURSE_CYCLES: usize = 1000;

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
    /// Applied once when the engine is built.
    Closed(Vec<LungSetup>),
    /// Tension pneumothorax.
    Tension(TensionRun),
}

/// A prepared tension-pneumothorax course.
#[derive(Debug, Clone)]
pub struct TensionRun {
    affected: Side,
    onset_tick: u64,
    course: Vec<Option<CourseCycle>>,
    next: usize,
    /// The interventions as applied (tick, course cycle, outcome).
    pub events: Vec<EventRecord>,
    /// First course cycle in arrest, if any.
    pub first_arrest: Option<u64>,
}

fn breathing_of(
    side: Side,
    inhale: &PhaseConstants,
    exhale: &PhaseConstants,
    state: &LungState,
    normal: &NormalBreathing,
    share: f64,
    timing: &lung_model::pv::Timing,
) -> Result<Option<Breathing>, DiseaseRunError> {
    state
        .boundary(&normal.boundary, share)
        .map(|b| Breathing::from_constants(inhale, exhale, b, timing))
        .transpose()
        .map_err(|source| DiseaseRunError::Breathing {
            side: side.name(),
            source,
        })
}

impl DiseaseRun {
    /// Prepare `spec` for lungs with `baselines` (the scene's order) breathing `normal`, with the
    /// engine's tick rate.
    pub fn prepare(
        spec: &DiseaseSpec,
        normal: &NormalBreathing,
        baselines: &[LungBaseline],
    ) -> Result<Self, DiseaseRunError> {
        match spec {
            DiseaseSpec::Closed(c) => {
                let plan: ClosedPlan = c.plan(normal, baselines)?;
                let mut lungs = Vec::new();
                for l in &plan.lungs {
                    let breathing = l
                        .breathing(&plan.timing)
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
                Ok(DiseaseRun::Closed(lungs))
            }
            DiseaseSpec::Tension {
                params,
                onset_s,
                events,
            } => Ok(DiseaseRun::Tension(TensionRun::prepare(
                *params, *onset_s, events, normal, baselines,
            )?)),
            DiseaseSpec::Tumour(_) => Err(DiseaseRunError::NotRun("tumour")),
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
    ) -> Result<Self, DiseaseRunError> {
        let affected = *baselines
            .iter()
            .find(|b| b.side == params.side)
            .ok_or(DiseaseError::MissingLung {
                side: params.side.name(),
            })?;
        let other = baselines.iter().find(|b| b.side != params.side).copied();
        let mut t = Tension::new(params, normal.timing, normal.boundary, affected, other)?;
        t.check_constants(&normal.inhale, &normal.exhale)?;
        let tick_hz = normal.timing.tick_hz;
        let onset_tick = (onset_s * tick_hz).round() as u64;
        let normal_ticks = {
            let (i, e) = normal.timing.phase_ticks().map_err(DiseaseError::from)?;
            i as u64 + e as u64
        };
        // The affected lung's first cycle at or after the onset starts on a multiple of the normal
        // cycle (both lungs breathe normally until then).
        let mut tick = onset_tick.div_ceil(normal_ticks) * normal_ticks;
        let mut cycle_ticks = normal_ticks;
        let mut pending: Vec<TimedEvent> = events.to_vec();
        pending.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
        let mut pending = pending.into_iter().peekable();
        let mut records = Vec::new();
        let mut course = Vec::new();
        let (mut inh, mut exh) = (normal.inhale.clone(), normal.exhale.clone());
        while course.len() < MAX_COURSE_CYCLES {
            while let Some(e) = pending.peek() {
                let at = e.tick(tick_hz);
                if at > tick {
                    break;
                }
                records.push(t.intervene(e.kind, e.side, at));
                pending.next();
            }
            let c = t.advance();
            let mut lungs = Vec::new();
            for state in std::iter::once(c.affected).chain(c.unaffected) {
                let base = baselines
                    .iter()
                    .find(|b| b.side == state.side)
                    .expect("the course's lungs are the scene's");
                let (i, e) = if state.side == params.side {
                    t.constants_into(
                        state.resistance_dv,
                        (&normal.inhale, &normal.exhale),
                        (&mut inh, &mut exh),
                    )?;
                    (&inh, &exh)
                } else {
                    (&normal.inhale, &normal.exhale)
                };
                let breathing =
                    breathing_of(state.side, i, e, &state, normal, base.share, &c.timing)?;
                lungs.push(LungSetup {
                    side: state.side,
                    state,
                    breathing,
                });
            }
            // The affected lung's cycle length in force (a held lung keeps the last one).
            if let Some(b) = lungs
                .iter()
                .find(|l| l.side == params.side)
                .and_then(|l| l.breathing.as_ref())
            {
                cycle_ticks = b.cycle_ticks() as u64;
            }
            course.push(Some(CourseCycle {
                cycle: c.cycle,
                lungs,
                arrest: c.arrest,
                pleural_air_ml: c.pleural_air_ml,
            }));
            tick += cycle_ticks;
            if c.arrest && pending.peek().is_none() {
                break;
            }
        }
        Ok(Self {
            affected: params.side,
            onset_tick,
            course,
            next: 0,
            events: records,
            first_arrest: t.first_arrest(),
        })
    }

    /// Cycles prepared.
    pub fn cycles(&self) -> usize {
        self.course.len()
    }
}

/// Put `setup` into `breath`: from now (`now = true`, at build time) or from the lung's cycle that
/// starts this tick.
pub fn apply(setup: &mut LungSetup, breath: &mut LungBreath, now: bool) {
    let s = &setup.state;
    breath.set_collapse(s.collapse);
    breath.set_offset_mm(s.offset_mm);
    breath.set_base_volume_ml(Some(s.base_volume_ml));
    breath.hold(s.held_ml);
    if let Some(b) = setup.breathing.take() {
        if now {
            breath.breathing = b;
        } else {
            breath.set_breathing_from_next_cycle(b);
        }
    }
}

impl DiseaseRun {
    /// Before a tick: at the start of each new cycle of the affected lung after the onset, move the
    /// course's next cycle into the lungs. No allocation.
    pub fn before_tick(&mut self, tick: u64, lungs: &mut [(super::LungGeometry, LungBreath)]) {
        let DiseaseRun::Tension(run) = self else {
            return;
        };
        if tick < run.onset_tick || run.next >= run.course.len() {
            return;
        }
        let Some(affected) = lungs.iter().find(|(g, _)| g.side == run.affected) else {
            return;
        };
        let b = &affected.1;
        // A new cycle of the affected lung starts at this tick (what `local_tick` rolls over to),
        // or the course starts with the run.
        let starts = tick == 0
            || tick.saturating_sub(b.cycle_start) >= b.breathing.cycle_ticks() as u64;
        if !starts {
            return;
        }
        if let Some(mut cycle) = run.course[run.next].take() {
            for setup in cycle.lungs.iter_mut() {
                if let Some((_, breath)) = lungs.iter_mut().find(|(g, _)| g.side == setup.side) {
                    apply(setup, breath, tick == 0);
                }
            }
            // Dropping the emptied cycle frees only its small lung list: keep it to free later.
            run.course[run.next] = Some(cycle);
        }
        run.next += 1;
    }
}
