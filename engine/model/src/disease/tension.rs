//! # Tension pneumothorax with the trainee's interventions (seed §8.1.4, eq. 8.10–8.13)
//!
//! A state machine advanced once per breathing cycle ([`Tension::advance`]), deterministic in cycles:
//! no clock, no randomness, no allocation. Interventions ([`Tension::intervene`]) change its state at
//! once and show from the next cycle; each returns an [`EventRecord`] with the tick it arrived at.
//!
//! ## The seed's model (L3677–3811)
//! * **eq. 8.10** in cycle `t` since onset, `V_p^t = V_p·e^{−τt}` ml of air enter the pleural space;
//!   it accumulates in `dV_sum` (here `pleural_air_ml`, `P`);
//! * **eq. 8.3–8.6 with `dV_t`** the affected lung breathes faster and shallower, and its shape
//!   changes as for a closed pneumothorax, "until the affected lung collapses";
//! * at **`V1max`** "the affected lung cannot inhale or exhale"; further air presses on the heart and
//!   the superior vena cava (SVC): the mediastinum shifts by **eq. 8.11–8.13**
//!   `q = V/(bX·bY·bZ)`, `dX = dV_t/(q·bY·bZ)`; at a shift of **β = 18 mm** (the SVC's diameter) the SVC
//!   closes, the unaffected lung hyper-expands to **`V2max`**, and both lungs are in arrest.
//!
//! ## Decisions (lungdyn) where the seed is silent (EQUATIONS §4.3)
//! * **Timing.** The air of cycle `t`'s inhalation is accounted at the start of cycle `t + 1`:
//!   [`TensionCycle`] for cycle `t` shows `P_t = Σ_{k<t} V_p·e^{−τk}` (cycle 0, the onset, is normal).
//! * **What `dV_t` is.** The seed uses `dV_t` as a fraction in eq. 8.3–8.6 and as a volume in eq. 8.12.
//!   For eq. 8.3–8.6 it is the way to `V1max`, `dV_t = min(1, P/V1max)`: tidal volume
//!   `(1 − dV_t)` of normal reaches 0 exactly when the seed says the lung "cannot inhale or exhale",
//!   and the breathing quickens with it. The shape loses `min(P, V1max)` ml (pleural air displaces
//!   lung 1:1 until `V1max`) by the collapse towards the hilum, and drops by eq. 8.2's `A` of the
//!   equivalent index `I = (loss/V)^{1/0.33}` (eq. 8.1 inverted). In eq. 8.12 `dV_t` is the air
//!   volume, and only air beyond `V1max` moves the mediastinum (before, it takes the lung's place):
//!   the shift is cumulative, `X = (P − V1max)⁺·1000/(q·k1²·bY·bZ)` mm with the box of the collapsed
//!   lung (`k1 = (1 − V1max/V)^{1/3}`; `q` is unchanged by the collapse, a similarity).
//!   The affected lung moves by `X` towards the mediastinum (the seed's "displacement of the bounding
//!   box of the affected lung towards the mediastinum"); the unaffected lung is not moved (the seed
//!   does not move it); `shift_mm` is reported for the renderer.
//! * **Arrest.** The SVC is closed while `X ≥ β`. Each cycle with the SVC closed brings the unaffected
//!   lung `1/N_h` of the way from the top of its breath to `V2max` (held, not breathing), `N_h` =
//!   [`TensionParams::hyperexpansion_cycles`]; arrest when it is there. In arrest nobody breathes, so
//!   no more air enters. The mechanics is reversible: decompression that brings `X` below β reopens
//!   the SVC, the unaffected lung comes back over `N_h` cycles and breathing resumes (whether a real
//!   patient would survive is not modelled).
//! * **`V1max`, `V2max`, `V_p`, `τ`** are not given by the seed; defaults: [`V1MAX_FRACTION`] of the
//!   affected lung's volume, `V2max` = the unaffected lung's end-inspiratory volume with α (the seed's
//!   Fig. 8.3: "the right lung is at a volume of Vmax"), [`INFLOW_ML`] and [`TAU_PER_CYCLE`] chosen
//!   for a training time scale (see their docs).
//! * **Interventions** ([`Intervention`]): a *needle decompression* stops the accumulation and vents
//!   the pleural air linearly over [`NEEDLE_VENT_CYCLES`] cycles down to [`NEEDLE_RESIDUAL`] of what
//!   it found (a needle converts a tension into a simple pneumothorax; ATLS follows it with a chest
//!   tube); a *chest tube* stops the accumulation and drains [`CHEST_TUBE_ML_PER_CYCLE`] per cycle to
//!   zero; an *occlusive dressing* stops the inflow of an open (sucking) chest-wall wound
//!   ([`LeakSource::Wound`]) and does nothing for a leak from the lung itself. An intervention on the
//!   other side has no effect ([`Outcome::WrongSide`]).
//!
//! ## The clinical model (default; EQUATIONS §4.6, issue 25)
//! [`TensionParams::model`] = [`CourseModel::Seed`] is everything above. [`CourseModel::Clinical`]
//! changes, each with its source: the pleural air is shared from the onset between the lung and the
//! mediastinum by compliance (a tension pneumothorax is a positive pleural pressure, not a completely
//! collapsed lung: Leigh-Smith & Harris, Emerg Med J 2005;22:8–16; Pulse's compliant pleural
//! cavity), so the shift starts with the first air and the SVC closes while the lung still
//! breathes; a needle opens the pleural space to the air and the tension vents with a one-cycle time
//! constant (Pulse's needle: a low resistance to the environment; ATLS); the unaffected lung takes
//! `α·dV_t`, not α, and the rate keeps the alveolar ventilation ([`super::clinical_phase_times`]).

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::disease::LeakSource;

use super::collapse::collapse_for_loss;
use super::resistance;
use super::{
    check_range, clinical_phase_times, drop_for_index, equivalent_index, phase_times, CourseModel,
    DiseaseError, LungBaseline, LungState, PhaseTimes, VerticalDrop, ALPHA_MAX_ML, ALPHA_SEED_ML,
};
use crate::mesh::Side;
use crate::pv::{Boundary, PhaseConstants, Timing};

/// Cardiovascular factor β, mm: the mean diameter of the vena cava (seed L3807–3809).
pub const BETA_SEED_MM: f64 = 18.0;

/// Default `V1max` as a fraction of the affected lung's volume. **Decision (lungdyn):** a completely
/// collapsed lung is an airless mass at the hilum; it keeps 20 % of its FRC volume here so that the
/// collapsed shape and its box (eq. 8.13 divides by it) stay finite.
pub const V1MAX_FRACTION: f64 = 0.8;

/// Largest `V1max` as a fraction of the affected lung's volume (eq. 8.13 needs the collapsed box > 0).
pub const V1MAX_FRACTION_MAX: f64 = 0.95;

/// Default `V_p`, ml per cycle. **Decision (lungdyn), training time scale:** with
/// [`TAU_PER_CYCLE`] the untreated default left lung reaches arrest in cycle 217, 7.3 minutes at the
/// quickened rate (test `default_course_reaches_arrest_in_minutes`; EQUATIONS §4.3) — the minutes of a
/// patient on positive-pressure ventilation rather than the hours of one breathing unassisted
/// (Roberts et al., Ann Surg 2015;261:1068–1078; Leigh-Smith & Harris, Emerg Med J 2005;22:8–16),
/// inside "death can come within 30 minutes" of issue 13 and with time for a trainee to act. 5 ml is
/// 1 % of a 500 ml tidal volume per breath. Slower courses: lower `v_p_ml`/`tau`.
pub const INFLOW_ML: f64 = 5.0;

/// Default `τ`, per cycle: the inflow halves in about 700 cycles (the trans-pulmonary pressure range
/// falls slowly; seed L3689–3691).
pub const TAU_PER_CYCLE: f64 = 0.001;

/// Default cycles a needle decompression takes to vent (Decision: about half a minute at 20–40/min).
pub const NEEDLE_VENT_CYCLES: u32 = 10;

/// Default share of the pleural air a needle leaves (Decision: a simple pneumothorax remains).
pub const NEEDLE_RESIDUAL: f64 = 0.25;

/// Default chest-tube drainage, ml per cycle (Decision: ~1 l in 20 cycles).
pub const CHEST_TUBE_ML_PER_CYCLE: f64 = 50.0;

/// Default cycles from the SVC's closure to `V2max` and arrest (Decision: a few breaths).
pub const HYPEREXPANSION_CYCLES: u32 = 5;

/// Clinical model: compliance of both lungs together, ml/cmH₂O (about 0.2 l/cmH₂O; West,
/// *Respiratory Physiology: The Essentials*, ch. 7). The affected lung's is its share of it.
pub const LUNG_COMPLIANCE_ML_PER_CMH2O: f64 = 200.0;

/// Clinical model: default compliance of the mediastinum (with the hemidiaphragm) against the
/// pleural air, ml/cmH₂O (`mediastinal_compliance_ml_per_cmh2o`). **Decision (lungdyn), training
/// calibration:** with it the default left lung's SVC closes (β = 18 mm) at a pleural pressure of
/// about +5 cmH₂O with the lung about two thirds of the way to `V1max` — a tension pneumothorax is a
/// positive pleural pressure, not a completely collapsed lung (Leigh-Smith & Harris 2005); no
/// measured value exists.
pub const MEDIASTINAL_COMPLIANCE_ML_PER_CMH2O: f64 = 10.0;

/// Pleural pressure at FRC below atmospheric, cmH₂O (−3 to −5 cmH₂O; Levitzky, *Pulmonary
/// Physiology*, as quoted by the Pulse Respiratory Methodology): the clinical model's pleural air at
/// atmospheric pressure — what a needle leaves — is the air at this rise.
pub const PLEURAL_RECOIL_CMH2O: f64 = 5.0;

/// Clinical model: default time constant of a needle's venting, cycles (`needle_tau_cycles`).
/// **Changed (lungdyn, issue 25):** Pulse (Kitware; `Respiratory.cpp`, the `PleuralToEnvironment`
/// path) models the needle as a flow resistance of half the airway's from the pleural space to the
/// environment, i.e. a time constant `R·C` of a fraction of a second; clinically "a rush of air" and
/// improvement within a minute (ATLS). One cycle (63 % of the tension gone after the first breath,
/// 95 % after three) is the conservative reading.
pub const NEEDLE_TAU_CYCLES: f64 = 1.0;

/// Clinical model: default share of the mediastinal displacement that comes out of the other lung
/// (`contralateral_compression`). **Changed (lungdyn, issue 25):** the shifted mediastinum
/// compresses the contralateral lung (Leigh-Smith & Harris, Emerg Med J 2005;22:8–16; Jain et al.,
/// "Understanding and managing tension pneumothorax", JIACM 2008;9:42–50, which Pulse's Respiratory
/// Methodology cites for the shift). The mediastinal volume `M = C_m·p` is the mediastinum's and
/// the affected hemidiaphragm's displacement together; how it splits between the two is not
/// measured: half (a training calibration). 0 is the earlier reading (the other lung keeps its
/// volume until the SVC closes).
pub const CONTRALATERAL_COMPRESSION: f64 = 0.5;

/// Largest fraction of the other lung's volume the compression may take (as [`V1MAX_FRACTION`] for
/// the affected lung: a compressed lung keeps 20 % and its box stays finite).
pub const CONTRALATERAL_MAX_LOSS: f64 = V1MAX_FRACTION;

/// Longest course [`Tension::cycles_to_arrest`] looks at, cycles.
pub const ARREST_SEARCH_CYCLES: u64 = 10_000_000;

/// A trainee's intervention: the protocol's enum, which also holds its scene names and wire codes.
pub use ipc_types::Intervention;

/// What an intervention did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// It changed the course.
    Applied,
    /// It was done on the unaffected side: no effect.
    WrongSide,
    /// The same intervention is already in place.
    AlreadyApplied,
    /// It does not act on this pneumothorax (why).
    NoEffect(&'static str),
}

impl Outcome {
    /// The outcome in words for a trainee: what happened ("applied", "no effect", "no change") and
    /// what it does to the course (§4.3: a needle vents the pleural air, a chest tube drains it, a
    /// dressing seals the wound's one-way valve).
    pub fn words(&self, kind: Intervention) -> (&'static str, &'static str) {
        match self {
            Outcome::Applied => (
                "applied",
                match kind {
                    Intervention::NeedleDecompression => "air venting",
                    Intervention::ChestTube => "the pleural air drains",
                    Intervention::OcclusiveDressing => "the wound is sealed: no more air enters",
                },
            ),
            Outcome::WrongSide => ("no effect", "the pneumothorax is on the other side"),
            Outcome::AlreadyApplied => ("no change", "it is already in place"),
            Outcome::NoEffect(why) => ("no effect", why),
        }
    }
}

/// An intervention as recorded for the run's output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EventRecord {
    /// Engine tick it arrived at.
    pub tick: u64,
    /// First cycle (since onset) whose state reflects it.
    pub cycle: u64,
    /// What was done.
    pub kind: Intervention,
    /// On which side.
    pub side: Side,
    /// What it did.
    pub outcome: Outcome,
}

/// Parameters of a tension pneumothorax (scene keys in brackets).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TensionParams {
    /// Affected lung (`side`).
    pub side: Side,
    /// Where the air comes from (`source`).
    pub source: LeakSource,
    /// `V_p` of eq. 8.10, ml in the first cycle (`v_p_ml`).
    pub inflow_ml: f64,
    /// `τ` of eq. 8.10, per cycle (`tau`).
    pub tau: f64,
    /// `V1max`, ml of pleural air at which the affected lung stops (`v1_max_ml`); `None`:
    /// [`V1MAX_FRACTION`] of its volume.
    pub v1_max_ml: Option<f64>,
    /// `V2max`, ml, the unaffected lung's volume in arrest (`v2_max_ml`); `None`: the top of its
    /// breath with α.
    pub v2_max_ml: Option<f64>,
    /// β, mm of mediastinal shift that closes the SVC (`beta_mm`).
    pub beta_mm: f64,
    /// α of eq. 8.7 for the unaffected lung while air is present (`alpha_ml`).
    pub alpha_ml: f64,
    /// φ of eq. 8.8–8.9 (`phi`).
    pub phi: f64,
    /// Cycles a needle vents over (`needle_vent_cycles`).
    pub needle_vent_cycles: u32,
    /// Share of the pleural air a needle leaves (`needle_residual`).
    pub needle_residual: f64,
    /// Chest-tube drainage per cycle, ml (`chest_tube_ml_per_cycle`).
    pub chest_tube_ml_per_cycle: f64,
    /// Cycles from the SVC's closure to arrest (`hyperexpansion_cycles`).
    pub hyperexpansion_cycles: u32,
    /// Which reading (`model`; default [`CourseModel::Clinical`]).
    pub model: CourseModel,
    /// Clinical: the mediastinum's compliance, ml/cmH₂O (`mediastinal_compliance_ml_per_cmh2o`).
    pub mediastinal_compliance_ml_per_cmh2o: f64,
    /// Clinical: the needle's venting time constant, cycles (`needle_tau_cycles`).
    pub needle_tau_cycles: f64,
    /// Clinical: the share of the mediastinal displacement taken from the other lung, 0..=1
    /// (`contralateral_compression`; 0: the other lung is not compressed).
    pub contralateral_compression: f64,
}

impl TensionParams {
    /// The defaults of this module for `side`.
    pub fn new(side: Side) -> Self {
        Self {
            side,
            source: LeakSource::Lung,
            inflow_ml: INFLOW_ML,
            tau: TAU_PER_CYCLE,
            v1_max_ml: None,
            v2_max_ml: None,
            beta_mm: BETA_SEED_MM,
            alpha_ml: ALPHA_SEED_ML,
            phi: super::resistance::PHI_SEED,
            needle_vent_cycles: NEEDLE_VENT_CYCLES,
            needle_residual: NEEDLE_RESIDUAL,
            chest_tube_ml_per_cycle: CHEST_TUBE_ML_PER_CYCLE,
            hyperexpansion_cycles: HYPEREXPANSION_CYCLES,
            model: CourseModel::default(),
            mediastinal_compliance_ml_per_cmh2o: MEDIASTINAL_COMPLIANCE_ML_PER_CMH2O,
            needle_tau_cycles: NEEDLE_TAU_CYCLES,
            contralateral_compression: CONTRALATERAL_COMPRESSION,
        }
    }

    /// The same parameters under `model`.
    pub fn with_model(self, model: CourseModel) -> Self {
        Self { model, ..self }
    }

    /// Check the parameters that do not depend on the lungs; errors name the scene key.
    pub fn validate(&self) -> Result<(), DiseaseError> {
        check_range(
            "v_p_ml",
            self.inflow_ml,
            f64::MIN_POSITIVE,
            1000.0,
            "within (0, 1000] ml per cycle",
        )?;
        check_range("tau", self.tau, 0.0, 10.0, "within 0..=10 per cycle")?;
        check_range(
            "beta_mm",
            self.beta_mm,
            f64::MIN_POSITIVE,
            100.0,
            "within (0, 100] mm (seed: 18)",
        )?;
        check_range(
            "alpha_ml",
            self.alpha_ml,
            0.0,
            ALPHA_MAX_ML,
            "within 0..=2500 ml",
        )?;
        check_range(
            "phi",
            self.phi,
            0.0,
            super::resistance::PHI_MAX,
            "within 0..=1 (seed: 0.1)",
        )?;
        check_range(
            "needle_residual",
            self.needle_residual,
            0.0,
            1.0,
            "within 0..=1",
        )?;
        check_range(
            "chest_tube_ml_per_cycle",
            self.chest_tube_ml_per_cycle,
            f64::MIN_POSITIVE,
            5000.0,
            "within (0, 5000] ml",
        )?;
        check_range(
            "needle_vent_cycles",
            self.needle_vent_cycles as f64,
            1.0,
            10_000.0,
            "within 1..=10000",
        )?;
        check_range(
            "hyperexpansion_cycles",
            self.hyperexpansion_cycles as f64,
            0.0,
            10_000.0,
            "within 0..=10000",
        )?;
        check_range(
            "mediastinal_compliance_ml_per_cmh2o",
            self.mediastinal_compliance_ml_per_cmh2o,
            0.1,
            1000.0,
            "within [0.1, 1000] ml/cmH2O",
        )?;
        check_range(
            "needle_tau_cycles",
            self.needle_tau_cycles,
            0.01,
            1000.0,
            "within [0.01, 1000] cycles",
        )?;
        check_range(
            "contralateral_compression",
            self.contralateral_compression,
            0.0,
            1.0,
            "within 0..=1 (the share of the mediastinal displacement taken from the other lung)",
        )?;
        Ok(())
    }
}

/// Needle venting in progress.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Vent {
    /// Seed reading: linear, down to a share of what the needle found.
    Linear { per_cycle_ml: f64, floor_ml: f64 },
    /// Clinical: towards the air at atmospheric pleural pressure, keeping `keep` of the difference
    /// per cycle (`e^{−1/τ}`).
    Exponential { keep: f64, floor_ml: f64 },
}

/// One cycle of the course: what the engine applies to both lungs and reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TensionCycle {
    /// Cycle since onset (0 = the onset cycle).
    pub cycle: u64,
    /// Air that entered during the previous cycle (eq. 8.10), ml.
    pub inflow_ml: f64,
    /// Pleural air `P = dV_sum`, ml.
    pub pleural_air_ml: f64,
    /// `dV_t` of eq. 8.3–8.6, `min(1, P/V1max)`.
    pub dv: f64,
    /// Fraction of the affected lung's volume lost, `min(P, V1max)/V`.
    pub loss_fraction: f64,
    /// Eq. 8.2 drop of the equivalent index.
    pub drop: VerticalDrop,
    /// Mediastinal shift `X` (eq. 8.11–8.13, cumulative), mm.
    pub shift_mm: f64,
    /// `X ≥ β`.
    pub svc_closed: bool,
    /// Both lungs in arrest.
    pub arrest: bool,
    /// Eq. 8.3–8.5 with `dV_t`.
    pub times: PhaseTimes,
    /// The timing both lungs breathe at this cycle.
    pub timing: Timing,
    /// The affected lung.
    pub affected: LungState,
    /// The unaffected lung, if simulated.
    pub unaffected: Option<LungState>,
}

impl TensionCycle {
    /// The state of `side`, if simulated.
    pub fn lung(&self, side: Side) -> Option<&LungState> {
        if self.affected.side == side {
            Some(&self.affected)
        } else {
            self.unaffected.as_ref().filter(|l| l.side == side)
        }
    }
}

/// A tension pneumothorax course (state machine, one [`Tension::advance`] per breathing cycle).
#[derive(Debug, Clone, PartialEq)]
pub struct Tension {
    params: TensionParams,
    normal_timing: Timing,
    normal_boundary: Boundary,
    affected: LungBaseline,
    unaffected: Option<LungBaseline>,
    v1_max_ml: f64,
    v2_max_ml: f64,
    shift_mm_per_ml: f64,
    /// Clinical: the affected lung's compliance, ml/cmH₂O (its share of
    /// [`LUNG_COMPLIANCE_ML_PER_CMH2O`]).
    lung_compliance: f64,
    /// Clinical: pleural air at atmospheric pressure, ml (what a needle leaves).
    atmospheric_air_ml: f64,
    /// Clinical: pleural air at which the SVC closes, ml.
    clinical_svc_air_ml: f64,
    // State.
    next_cycle: u64,
    pleural_ml: f64,
    inflow_open: bool,
    vent: Option<Vent>,
    draining: bool,
    dressed: bool,
    hyper: u32,
    arrested: bool,
    first_arrest: Option<u64>,
}

impl Tension {
    /// A course of `params` for the `affected` lung (and the `unaffected` one if simulated), from the
    /// scene's normal timing and boundary values. Checks every parameter against the lungs.
    pub fn new(
        params: TensionParams,
        normal_timing: Timing,
        normal_boundary: Boundary,
        affected: LungBaseline,
        unaffected: Option<LungBaseline>,
    ) -> Result<Self, DiseaseError> {
        params.validate()?;
        normal_timing.phase_ticks()?;
        affected.validate()?;
        if affected.side != params.side {
            return Err(DiseaseError::MissingLung {
                side: params.side.name(),
            });
        }
        if let Some(u) = &unaffected {
            u.validate()?;
            if u.side == affected.side {
                return Err(DiseaseError::NotApplicable {
                    name: "side",
                    reason: "the unaffected lung must be the other lung",
                });
            }
        }
        let v_aff = affected.start_volume_ml;
        let v1_max_ml = match params.v1_max_ml {
            Some(v) => check_range(
                "v1_max_ml",
                v,
                f64::MIN_POSITIVE,
                V1MAX_FRACTION_MAX * v_aff,
                "within (0, 0.95 × the affected lung's volume] ml",
            )?,
            None => V1MAX_FRACTION * v_aff,
        };
        let v2_max_ml = match (&unaffected, params.v2_max_ml) {
            (Some(u), v2) => {
                let top = u.start_volume_ml + u.share * normal_boundary.tv_ml + params.alpha_ml;
                match v2 {
                    Some(v) => check_range(
                        "v2_max_ml",
                        v,
                        top,
                        crate::plausible::LUNG_VOLUME_ML.hi,
                        "at least the unaffected lung's end-inspiratory volume with alpha, at most 6000 ml",
                    )?,
                    None => top,
                }
            }
            (None, Some(_)) => {
                return Err(DiseaseError::NotApplicable {
                    name: "v2_max_ml",
                    reason: "the scene does not simulate the unaffected lung",
                })
            }
            (None, None) => 0.0,
        };
        // eq. 8.11–8.13 on the lung collapsed to V1max: q is unchanged by the similarity, the box's
        // Y·Z face scales by k1².
        let k1 = (1.0 - v1_max_ml / v_aff).cbrt();
        let q = affected.fill_fraction();
        let shift_mm_per_ml = 1000.0 / (q * k1 * k1 * affected.box_mm[1] * affected.box_mm[2]);
        if !(shift_mm_per_ml.is_finite() && shift_mm_per_ml > 0.0) {
            return Err(DiseaseError::BadBaseline {
                side: affected.side.name(),
                what: "collapsed box face (eq. 8.13)",
                value: shift_mm_per_ml,
            });
        }
        let mut m = Self {
            params,
            normal_timing,
            normal_boundary,
            affected,
            unaffected,
            v1_max_ml,
            v2_max_ml,
            shift_mm_per_ml,
            lung_compliance: affected.share.min(1.0) * LUNG_COMPLIANCE_ML_PER_CMH2O,
            atmospheric_air_ml: 0.0,
            clinical_svc_air_ml: 0.0,
            next_cycle: 0,
            pleural_ml: 0.0,
            inflow_open: true,
            vent: None,
            draining: false,
            dressed: false,
            hyper: 0,
            arrested: false,
            first_arrest: None,
        };
        let recoil = PLEURAL_RECOIL_CMH2O;
        m.atmospheric_air_ml = m.lung_displaced_ml(recoil) + m.mediastinal_ml(recoil);
        m.clinical_svc_air_ml = m.clinical_svc_air();
        Ok(m)
    }

    /// Clinical: the volume the affected lung has given up at a pleural pressure `rise` cmH₂O above
    /// its FRC value, `D = V1max·(1 − e^{−C_L·rise/V1max})`: compliance `C_L` at first, stiffening
    /// as it empties towards `V1max` (an emptied lung's compliance falls: West ch. 7).
    fn lung_displaced_ml(&self, rise: f64) -> f64 {
        let v1 = self.v1_max_ml;
        v1 * -(-self.lung_compliance * rise / v1).exp_m1()
    }

    /// Clinical: the volume the mediastinum (with the hemidiaphragm) has moved at `rise`, `C_m·rise`.
    fn mediastinal_ml(&self, rise: f64) -> f64 {
        self.params.mediastinal_compliance_ml_per_cmh2o * rise
    }

    /// Clinical: the pleural pressure rise (cmH₂O) that holds `air` ml, solving
    /// `air = D(rise) + C_m·rise` (strictly increasing) by bisection: 80 halvings of
    /// `[0, air/C_m]`, a fixed count, so the result is a pure function of `air`.
    fn clinical_rise(&self, air: f64) -> f64 {
        if !(air > 0.0) {
            return 0.0;
        }
        let (mut lo, mut hi) = (
            0.0f64,
            air / self.params.mediastinal_compliance_ml_per_cmh2o,
        );
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if self.lung_displaced_ml(mid) + self.mediastinal_ml(mid) < air {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    }

    /// Clinical: (lung displaced ml, mediastinal ml, shift mm, rise cmH₂O) for `air` ml of pleural
    /// air. The shift is eq. 8.12–8.13 on the mediastinal volume with the box of the lung as it is
    /// now: `X = M·1000/(q·k²·bY·bZ)`, `k = (1 − D/V)^{1/3}`.
    fn clinical_partition(&self, air: f64) -> (f64, f64, f64, f64) {
        let rise = self.clinical_rise(air);
        let displaced = self.lung_displaced_ml(rise).min(air).max(0.0);
        let mediastinal = (air - displaced).max(0.0);
        let v = self.affected.start_volume_ml;
        let k = (1.0 - displaced / v).max(0.0).cbrt();
        let face = self.affected.fill_fraction()
            * k
            * k
            * self.affected.box_mm[1]
            * self.affected.box_mm[2];
        (displaced, mediastinal, mediastinal * 1000.0 / face, rise)
    }

    /// Clinical: the volume the other lung loses to the shifted mediastinum, ml:
    /// `contralateral_compression·M`, at most [`CONTRALATERAL_MAX_LOSS`] of its volume (0 without
    /// the other lung).
    fn compressed_ml(&self, mediastinal: f64) -> f64 {
        let Some(u) = &self.unaffected else {
            return 0.0;
        };
        (self.params.contralateral_compression * mediastinal)
            .clamp(0.0, CONTRALATERAL_MAX_LOSS * u.start_volume_ml)
    }

    /// Clinical: the air at which the shift reaches β (the shift grows with the air), by bisection.
    fn clinical_svc_air(&self) -> f64 {
        let beta = self.params.beta_mm;
        let mut hi = self.v1_max_ml.max(1.0);
        while self.clinical_partition(hi).2 < beta && hi < 1.0e9 {
            hi *= 2.0;
        }
        let mut lo = 0.0;
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if self.clinical_partition(mid).2 < beta {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        hi
    }

    /// Clinical: pleural air at atmospheric pressure, ml (what a needle leaves; 0 in the seed
    /// reading, whose needle leaves [`TensionParams::needle_residual`] of what it found).
    pub fn atmospheric_air_ml(&self) -> f64 {
        match self.params.model {
            CourseModel::Seed => 0.0,
            CourseModel::Clinical => self.atmospheric_air_ml,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &TensionParams {
        &self.params
    }

    /// `V1max` in force, ml.
    pub fn v1_max_ml(&self) -> f64 {
        self.v1_max_ml
    }

    /// `V2max` in force, ml (0 without an unaffected lung).
    pub fn v2_max_ml(&self) -> f64 {
        self.v2_max_ml
    }

    /// Mediastinal shift per ml of air beyond `V1max` (eq. 8.13 on the collapsed box), mm/ml.
    pub fn shift_mm_per_ml(&self) -> f64 {
        self.shift_mm_per_ml
    }

    /// Pleural air at which the SVC closes, ml: seed `V1max + β/shift_mm_per_ml`; clinical the air
    /// whose mediastinal share shifts by β.
    pub fn svc_closing_air_ml(&self) -> f64 {
        match self.params.model {
            CourseModel::Seed => self.v1_max_ml + self.params.beta_mm / self.shift_mm_per_ml,
            CourseModel::Clinical => self.clinical_svc_air_ml,
        }
    }

    /// The cycle the next [`Self::advance`] computes.
    pub fn next_cycle(&self) -> u64 {
        self.next_cycle
    }

    /// First cycle in arrest so far.
    pub fn first_arrest(&self) -> Option<u64> {
        self.first_arrest
    }

    /// Apply an intervention arriving at engine tick `tick`; it shows from the next cycle.
    pub fn intervene(&mut self, kind: Intervention, side: Side, tick: u64) -> EventRecord {
        let outcome = if side != self.params.side {
            Outcome::WrongSide
        } else {
            match kind {
                Intervention::NeedleDecompression => {
                    if self.draining {
                        Outcome::NoEffect("a chest tube already drains this side")
                    } else if self.vent.is_some() {
                        Outcome::AlreadyApplied
                    } else {
                        self.inflow_open = false;
                        self.vent = Some(match self.params.model {
                            CourseModel::Seed => {
                                let floor_ml = self.params.needle_residual * self.pleural_ml;
                                Vent::Linear {
                                    per_cycle_ml: (self.pleural_ml - floor_ml)
                                        / self.params.needle_vent_cycles as f64,
                                    floor_ml,
                                }
                            }
                            CourseModel::Clinical => Vent::Exponential {
                                keep: (-1.0 / self.params.needle_tau_cycles).exp(),
                                floor_ml: self.atmospheric_air_ml,
                            },
                        });
                        Outcome::Applied
                    }
                }
                Intervention::ChestTube => {
                    if self.draining {
                        Outcome::AlreadyApplied
                    } else {
                        self.inflow_open = false;
                        self.draining = true;
                        self.vent = None;
                        Outcome::Applied
                    }
                }
                Intervention::OcclusiveDressing => match self.params.source {
                    LeakSource::Lung => Outcome::NoEffect(
                        "the air leaks from the lung: a dressing seals a chest-wall wound only",
                    ),
                    LeakSource::Wound if self.dressed => Outcome::AlreadyApplied,
                    LeakSource::Wound => {
                        self.dressed = true;
                        self.inflow_open = false;
                        Outcome::Applied
                    }
                },
            }
        };
        EventRecord {
            tick,
            cycle: self.next_cycle,
            kind,
            side,
            outcome,
        }
    }

    /// The pleural air's change into cycle `t` (> 0): the inhalation of cycle t − 1 lets air in
    /// while the leak is open (none in arrest: no breathing then), a chest tube drains it, a vent
    /// lets it out. Returns the air that came in.
    fn move_air(&mut self, t: u64) -> f64 {
        let p = &self.params;
        let mut inflow_ml = 0.0;
        if self.inflow_open && !self.arrested {
            inflow_ml = p.inflow_ml * (-p.tau * (t - 1) as f64).exp();
            self.pleural_ml += inflow_ml;
        }
        if self.draining {
            self.pleural_ml = (self.pleural_ml - p.chest_tube_ml_per_cycle).max(0.0);
            return inflow_ml;
        }
        match self.vent {
            Some(Vent::Linear {
                per_cycle_ml,
                floor_ml,
            }) if self.pleural_ml > floor_ml => {
                self.pleural_ml = (self.pleural_ml - per_cycle_ml).max(floor_ml);
            }
            Some(Vent::Linear { .. }) => {}
            // The needle opens the pleural space to the atmosphere: the air goes to its volume at
            // atmospheric pressure, out under tension, in below it (Pulse's PleuralToEnvironment
            // path is a resistor: flow either way).
            Some(Vent::Exponential { keep, floor_ml }) => {
                self.pleural_ml = floor_ml + (self.pleural_ml - floor_ml) * keep;
            }
            None => {}
        }
        inflow_ml
    }

    /// Hyperexpansion of the other lung while the vena cava is closed (up over
    /// `hyperexpansion_cycles`, down again when it opens); arrest when it is closed and the
    /// hyperexpansion complete. Returns whether cycle `t` is in arrest.
    fn track_hyperexpansion(&mut self, svc_closed: bool, t: u64) -> bool {
        let n_h = self.params.hyperexpansion_cycles;
        self.hyper = if svc_closed {
            (self.hyper + 1).min(n_h)
        } else {
            self.hyper.saturating_sub(1)
        };
        let arrest = svc_closed && self.hyper >= n_h;
        self.arrested = arrest;
        if arrest && self.first_arrest.is_none() {
            self.first_arrest = Some(t);
        }
        arrest
    }

    /// The cycle's phase times: the seed's from `dv` (eq. 8.4–8.6); the clinical model's from the
    /// tidal volume still breathing (`breathing_tidal_ml`, both lungs) against the normal one.
    /// Cannot fail here (the normal timing was checked in new(), dv ∈ [0, 1], the tidal volumes
    /// are finite and ≥ 0); all zero if it did.
    fn cycle_times(&self, dv: f64, air: f64, breathing_tidal_ml: f64) -> PhaseTimes {
        let tv = self.normal_boundary.tv_ml;
        match self.params.model {
            CourseModel::Seed => phase_times(&self.normal_timing, dv),
            CourseModel::Clinical => {
                let normal_total =
                    self.affected.share * tv + self.unaffected.map_or(0.0, |u| u.share * tv);
                if air > 0.0 {
                    clinical_phase_times(&self.normal_timing, normal_total, breathing_tidal_ml)
                } else {
                    phase_times(&self.normal_timing, 0.0)
                }
            }
        }
        .unwrap_or(PhaseTimes {
            cycle_s: 0.0,
            inhale_s: 0.0,
            exhale_s: 0.0,
            dt_s: 0.0,
            new_inhale_s: 0.0,
            new_exhale_s: 0.0,
            raw_inhale_s: 0.0,
            raw_exhale_s: 0.0,
            inhale_clamped: false,
            exhale_clamped: false,
            min_phase_s: 0.0,
        })
    }

    /// Advance to the next breathing cycle and return its state. No allocation.
    pub fn advance(&mut self) -> TensionCycle {
        let t = self.next_cycle;
        let inflow_ml = if t > 0 { self.move_air(t) } else { 0.0 };
        let p = &self.params;
        let air = self.pleural_ml;
        let v_aff = self.affected.start_volume_ml;
        let (displaced, shift_mm, compressed) = match p.model {
            // Air takes the lung's place 1:1 up to V1max; only air beyond it moves the mediastinum;
            // the other lung is not compressed (the seed moves only the affected box).
            CourseModel::Seed => (
                air.min(self.v1_max_ml),
                (air - self.v1_max_ml).max(0.0) * self.shift_mm_per_ml,
                0.0,
            ),
            // Shared by compliance from the onset (EQUATIONS §4.6 (a)); a share of the mediastinal
            // displacement comes out of the other lung (§4.6 (f)).
            CourseModel::Clinical => {
                let (d, m, x, _) = self.clinical_partition(air);
                (d, x, self.compressed_ml(m))
            }
        };
        let loss_fraction = (displaced / v_aff).clamp(0.0, 1.0);
        let dv = match p.model {
            CourseModel::Seed => (air / self.v1_max_ml).clamp(0.0, 1.0),
            CourseModel::Clinical => (displaced / self.v1_max_ml).clamp(0.0, 1.0),
        };
        let svc_closed = shift_mm >= self.params.beta_mm;
        let arrest = self.track_hyperexpansion(svc_closed, t);
        let p = &self.params;
        let n_h = p.hyperexpansion_cycles;
        let tv = self.normal_boundary.tv_ml;
        let stopped = dv >= 1.0 || arrest;
        // α of eq. 8.7: the seed adds it in full as soon as there is air; the clinical model in
        // proportion to the way to V1max (EQUATIONS §4.6 (c)).
        let alpha = match p.model {
            CourseModel::Seed if air > 0.0 => p.alpha_ml,
            CourseModel::Seed => 0.0,
            CourseModel::Clinical => p.alpha_ml * dv,
        };
        let affected_tidal = if stopped {
            0.0
        } else {
            self.affected.share * tv * (1.0 - dv)
        };
        // The compressed other lung: its aerated volume, and with it its compliance (specific
        // compliance; West ch. 7) and tidal volume, fall in proportion.
        let aerated = self
            .unaffected
            .map_or(1.0, |u| 1.0 - compressed / u.start_volume_ml);
        let unaffected_tidal = self.unaffected.map(|u| {
            let t = u.share * tv + alpha;
            if compressed > 0.0 {
                t * aerated
            } else {
                t
            }
        });
        let unaffected_base = self.unaffected.map_or(0.0, |u| u.start_volume_ml) - compressed;
        let unaffected_held = self.unaffected.and(if n_h == 0 {
            svc_closed.then_some(self.v2_max_ml)
        } else if self.hyper > 0 {
            let top = unaffected_base + unaffected_tidal.unwrap_or(0.0);
            Some(top + (self.v2_max_ml - top) * self.hyper as f64 / n_h as f64)
        } else {
            None
        });
        let breathing_tidal = affected_tidal
            + if unaffected_held.is_some() {
                0.0
            } else {
                unaffected_tidal.unwrap_or(0.0)
            };
        let times = self.cycle_times(dv, air, breathing_tidal);
        let timing = times.timing(&self.normal_timing);
        let drop = drop_for_index(equivalent_index(loss_fraction));
        let collapse = collapse_for_loss(loss_fraction).unwrap_or(0.0);
        let base = v_aff - displaced;
        let lateral = self.affected.side.lateral_sign() as f64;
        let affected = LungState {
            side: self.affected.side,
            collapse,
            base_volume_ml: base,
            tidal_ml: affected_tidal,
            held_ml: stopped.then_some(base),
            offset_mm: [
                if shift_mm > 0.0 {
                    -lateral * shift_mm
                } else {
                    0.0
                },
                0.0,
                if drop.drop_mm > 0.0 {
                    -drop.drop_mm
                } else {
                    0.0
                },
            ],
            resistance_dv: dv,
        };
        let unaffected = self.unaffected.map(|u| {
            let held = unaffected_held;
            // Compressed by the mediastinum: shrunk towards its hilum by the volume lost and moved
            // with the shift (in the affected lung's direction) so that its lateral wall stays near
            // the chest wall (the similarity moves it by (1 − k) of the box's width).
            let (collapse, offset_x) = if compressed > 0.0 {
                let c = collapse_for_loss(1.0 - aerated).unwrap_or(0.0);
                (c, -lateral * c * u.box_mm[0])
            } else {
                (0.0, 0.0)
            };
            LungState {
                side: u.side,
                collapse,
                base_volume_ml: unaffected_base,
                tidal_ml: if held.is_some() {
                    0.0
                } else {
                    unaffected_tidal.unwrap_or(0.0)
                },
                held_ml: held,
                offset_mm: [offset_x, 0.0, 0.0],
                resistance_dv: 0.0,
            }
        });
        self.next_cycle = t + 1;
        TensionCycle {
            cycle: t,
            inflow_ml,
            pleural_air_ml: air,
            dv,
            loss_fraction,
            drop,
            shift_mm,
            svc_closed,
            arrest,
            times,
            timing,
            affected,
            unaffected,
        }
    }

    /// Check once (at scene start) that eq. 8.8–8.9 apply to the normal constants over the whole
    /// course: `x = φ·dV_t` runs from 0 to `φ`, and both the domain of eq. 8.9 (`|χ_i|·x < 1`,
    /// `χ_1·x > 0`) and the finiteness of eq. 8.8 are hardest at `x = φ`.
    pub fn check_constants(
        &self,
        inhale: &PhaseConstants,
        exhale: &PhaseConstants,
    ) -> Result<(), DiseaseError> {
        let (mut i, mut e) = (inhale.clone(), exhale.clone());
        self.constants_into(1.0, (inhale, exhale), (&mut i, &mut e))
    }

    /// The affected lung's constants for a cycle with `dV_t = dv` ([`TensionCycle::dv`]): eq. 8.9
    /// on the inhalation, eq. 8.8 on the exhalation ([`resistance::PNEUMOTHORAX`]), `x = φ·dv`, written
    /// into `out` (no allocation when its `chi` have the capacity: the per-cycle path).
    pub fn constants_into(
        &self,
        dv: f64,
        normal: (&PhaseConstants, &PhaseConstants),
        out: (&mut PhaseConstants, &mut PhaseConstants),
    ) -> Result<(), DiseaseError> {
        let x = self.params.phi * dv.clamp(0.0, 1.0);
        let (t_in, t_ex) = resistance::PNEUMOTHORAX;
        resistance::phase_into(normal.0, t_in, x, out.0)?;
        resistance::phase_into(normal.1, t_ex, x, out.1)?;
        Ok(())
    }

    /// The same course from its onset, without interventions.
    pub fn untreated(&self) -> Self {
        Self {
            next_cycle: 0,
            pleural_ml: 0.0,
            inflow_open: true,
            vent: None,
            draining: false,
            dressed: false,
            hyper: 0,
            arrested: false,
            first_arrest: None,
            ..self.clone()
        }
    }

    /// The first cycle in arrest of the untreated course, `None` when the inflow can never reach
    /// the SVC's closure (`V_p/(1 − e^{−τ}) ≤` [`Self::svc_closing_air_ml`]) or not within
    /// [`ARREST_SEARCH_CYCLES`]. Runs the same accumulation as [`Self::advance`], so it is exact.
    pub fn cycles_to_arrest(&self) -> Option<u64> {
        let p = &self.params;
        let target = self.svc_closing_air_ml();
        let estimate = if p.tau == 0.0 {
            (target / p.inflow_ml).ceil()
        } else {
            let total = p.inflow_ml / (1.0 - (-p.tau).exp());
            if !(total > target) {
                return None;
            }
            (-(1.0 - target / total).ln() / p.tau).ceil()
        };
        let limit = estimate + p.hyperexpansion_cycles as f64 + 4.0;
        if !(limit <= ARREST_SEARCH_CYCLES as f64) {
            return None;
        }
        let mut m = self.untreated();
        for _ in 0..=(limit as u64) {
            if m.advance().arrest {
                return m.first_arrest;
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pv::{preset, DEFAULT_PRESET};
    use proptest::prelude::*;

    /// A box-shaped affected lung for hand computation: 1000 ml in a 100 × 100 × 200 mm box
    /// (q = 1 000 000 / 2 000 000 = 0.5), share 0.5; the right lung 1300 ml, share 0.5.
    fn lungs() -> (LungBaseline, LungBaseline) {
        let left = LungBaseline {
            side: Side::Left,
            start_volume_ml: 1000.0,
            share: 0.5,
            box_mm: [100.0, 100.0, 200.0],
            hilum_mm: [30.0, 0.0, 0.0],
            base_z_mm: -100.0,
        };
        let right = LungBaseline {
            side: Side::Right,
            start_volume_ml: 1300.0,
            ..left
        };
        (left, right)
    }

    fn course(p: TensionParams) -> Tension {
        let (l, r) = lungs();
        Tension::new(
            p,
            Timing::default(),
            preset(DEFAULT_PRESET).unwrap().boundary,
            l,
            Some(r),
        )
        .unwrap()
    }

    /// EQUATIONS §4.6 (f): the other lung loses `contralateral_compression` of the mediastinal
    /// volume `M = C_m·p` (its base volume, its collapse towards its hilum, its tidal volume in
    /// proportion to what stays aerated) and moves with the shift; 0 is the earlier course bit for
    /// bit; the seed reading never compresses; bounded and finite at any air.
    #[test]
    fn the_shifted_mediastinum_compresses_the_other_lung() {
        let clinical = |c: f64, inflow: f64| {
            course(TensionParams {
                inflow_ml: inflow,
                tau: 0.0,
                contralateral_compression: c,
                ..TensionParams::new(Side::Left)
            })
        };
        let (mut none, mut half, mut all) = (
            clinical(0.0, 20.0),
            clinical(0.5, 20.0),
            clinical(1.0, 20.0),
        );
        let right_v = lungs().1.start_volume_ml;
        for _ in 0..60 {
            let (a, b, c) = (none.advance(), half.advance(), all.advance());
            // The affected lung and the shift do not depend on the compression.
            assert_eq!(a.affected, b.affected);
            assert_eq!((a.shift_mm, a.dv), (c.shift_mm, c.dv));
            let (ua, ub, uc) = (
                a.unaffected.unwrap(),
                b.unaffected.unwrap(),
                c.unaffected.unwrap(),
            );
            assert_eq!(
                (ua.base_volume_ml, ua.collapse, ua.offset_mm),
                (right_v, 0.0, [0.0; 3])
            );
            // By hand: M = air − D(p) (the partition), the right lung loses c·M.
            let (_, m, _, _) = half.clinical_partition(b.pleural_air_ml);
            assert!(
                (right_v - ub.base_volume_ml - 0.5 * m).abs() < 1e-9,
                "{ub:?}"
            );
            assert!((right_v - uc.base_volume_ml - m).abs() < 1e-9, "{uc:?}");
            if m > 0.0 && ua.held_ml.is_none() {
                assert!(uc.base_volume_ml < ub.base_volume_ml);
                assert!(uc.tidal_ml < ub.tidal_ml && ub.tidal_ml < ua.tidal_ml);
                let aerated = ub.base_volume_ml / right_v;
                assert!((ub.tidal_ml - ua.tidal_ml * aerated).abs() < 1e-9);
                // The collapse takes exactly the volume lost: k³ = aerated.
                let k = 1.0 - ub.collapse;
                assert!((k * k * k - aerated).abs() < 1e-9);
                // Moved with the shift: the affected (left) lung moves towards −X, so does it.
                assert!(ub.offset_mm[0] < 0.0 && b.affected.offset_mm[0] < 0.0);
            }
        }
        // The seed reading never compresses the other lung, whatever the key says.
        let mut seed = course(TensionParams {
            contralateral_compression: 1.0,
            ..hand(100.0, 0.0)
        });
        for _ in 0..30 {
            let u = seed.advance().unaffected.unwrap();
            assert_eq!((u.base_volume_ml, u.collapse), (right_v, 0.0));
        }
        // A litre a cycle for an hour of cycles: bounded by CONTRALATERAL_MAX_LOSS, finite.
        let mut huge = clinical(1.0, 1000.0);
        for _ in 0..2000 {
            let u = huge.advance().unaffected.unwrap();
            assert!(u.base_volume_ml >= (1.0 - CONTRALATERAL_MAX_LOSS) * right_v - 1e-9);
            assert!((0.0..=1.0).contains(&u.collapse) && u.offset_mm[0].is_finite());
            assert!(u.tidal_ml.is_finite() && u.tidal_ml >= 0.0);
            assert!(u.held_ml.is_none_or(|h| h.is_finite()));
        }
        for bad in [-0.1, 1.5, f64::NAN] {
            let p = TensionParams {
                contralateral_compression: bad,
                ..TensionParams::new(Side::Left)
            };
            assert!(matches!(
                p.validate(),
                Err(DiseaseError::OutOfRange {
                    name: "contralateral_compression",
                    ..
                })
            ));
        }
    }

    /// V1max = 875 ml: the collapsed lung keeps 125 ml = 1/8, so k1 = 1/2 and the collapsed box's
    /// Y·Z face is 100·200/4 = 5000 mm²; q·face = 2500 mm², 1 ml = 1000 mm³ → 0.4 mm per ml;
    /// β = 18 mm ↔ 45 ml beyond V1max: the SVC closes at P ≥ 920 ml.
    fn hand(inflow_ml: f64, tau: f64) -> TensionParams {
        TensionParams {
            inflow_ml,
            tau,
            v1_max_ml: Some(875.0),
            model: CourseModel::Seed,
            ..TensionParams::new(Side::Left)
        }
    }

    #[test]
    fn arrest_comes_at_the_hand_computed_cycle() {
        // τ = 0, V_p = 100 ml: P_t = 100·t. P_9 = 900 < 920 (X = 25·0.4 = 10 mm < 18), P_10 = 1000
        // (X = 125·0.4 = 50 mm ≥ 18): the SVC closes in cycle 10; N_h = 5 → arrest in cycle 14.
        let mut m = course(hand(100.0, 0.0));
        assert!((m.shift_mm_per_ml() - 0.4).abs() < 1e-12);
        assert!((m.svc_closing_air_ml() - 920.0).abs() < 1e-9);
        assert_eq!(m.cycles_to_arrest(), Some(14));
        let cycles: Vec<TensionCycle> = (0..20).map(|_| m.advance()).collect();
        assert_eq!(cycles[9].pleural_air_ml, 900.0);
        assert!((cycles[9].shift_mm - 10.0).abs() < 1e-9 && !cycles[9].svc_closed);
        assert!(cycles[10].svc_closed && (cycles[10].shift_mm - 50.0).abs() < 1e-9);
        assert!(!cycles[13].arrest && cycles[14].arrest);
        assert_eq!(m.first_arrest(), Some(14));
        // In arrest no air enters: P stays at 1400 ml (cycles 1..=14 each added 100 ml).
        assert_eq!(cycles[19].pleural_air_ml, 1400.0);
        assert_eq!(cycles[19].inflow_ml, 0.0);
        // τ = ln 2, V_p = 500 ml: P_t = 1000·(1 − 2^{−t}): P_3 = 875, P_4 = 937.5 ≥ 920 → SVC in
        // cycle 4, arrest in cycle 8.
        let m = course(hand(500.0, std::f64::consts::LN_2));
        assert_eq!(m.cycles_to_arrest(), Some(8));
        // τ = ln 2, V_p = 400 ml: P_∞ = 800 ml < 920: never.
        assert_eq!(
            course(hand(400.0, std::f64::consts::LN_2)).cycles_to_arrest(),
            None
        );
    }

    #[test]
    fn the_course_states_by_hand() {
        // τ = 0, V_p = 100 ml, cycle 5: P = 500 ml, dV_t = 500/875 = 0.571429; loss 500/1000 = 0.5;
        // collapse c = 1 − 0.5^{1/3} = 0.206299; equivalent I = 0.5^{1/0.33} = 0.122346,
        // A = (12.2346 − 4.2)/9.4 = 0.854744 cm → drop 8.54744 mm; tidal left = 250·(1 − 0.571429)
        // = 107.142857 ml; right = share 0.5·500 + α 100 = 350 ml; dT = 5·0.571429 = 2.857 s
        // → both phases clamped to 0.75 s.
        let mut m = course(hand(100.0, 0.0));
        let c = (0..=5).map(|_| m.advance()).last().unwrap();
        assert_eq!(c.cycle, 5);
        assert_eq!(c.pleural_air_ml, 500.0);
        assert!((c.dv - 0.571_429).abs() < 1e-6);
        assert!((c.affected.collapse - 0.206_299).abs() < 1e-6);
        assert!((c.drop.drop_mm - 8.553_39).abs() < 1e-4, "{:?}", c.drop);
        assert!((c.affected.tidal_ml - 107.142_857).abs() < 1e-6);
        assert_eq!(c.affected.base_volume_ml, 500.0);
        assert_eq!(c.unaffected.unwrap().tidal_ml, 350.0);
        assert!(c.times.inhale_clamped && c.timing.breaths_per_min == 40.0);
        // Cycle 0 is the onset: normal breathing exactly.
        let first = course(hand(100.0, 0.0)).advance();
        assert_eq!(first.timing, Timing::default());
        assert_eq!(first.affected.offset_mm.map(f64::to_bits), [0u64; 3]);
        assert_eq!(first.affected.tidal_ml, 250.0);
        assert_eq!(first.unaffected.unwrap().tidal_ml, 250.0);
        // Cycle 9 (P = 900 ≥ V1max): the affected lung is held at 125 ml, shifted 10 mm medially
        // (−X for the left lung).
        let c9 = (0..10).map(|_| m.advance()).nth(3).unwrap();
        assert_eq!(c9.cycle, 9);
        assert_eq!(c9.affected.held_ml, Some(125.0));
        assert!((c9.affected.offset_mm[0] + 10.0).abs() < 1e-9);
    }

    #[test]
    fn same_course_and_events_are_bitwise_identical() {
        let run = || {
            let mut m = course(TensionParams::new(Side::Left));
            let mut out = Vec::new();
            for t in 0..600u64 {
                if t == 250 {
                    out.push(format!(
                        "{:?}",
                        m.intervene(Intervention::NeedleDecompression, Side::Left, t * 90)
                    ));
                }
                if t == 400 {
                    out.push(format!(
                        "{:?}",
                        m.intervene(Intervention::ChestTube, Side::Left, t * 90)
                    ));
                }
                let c = m.advance();
                out.push(format!(
                    "{} {} {} {:?} {:?}",
                    c.pleural_air_ml.to_bits(),
                    c.shift_mm.to_bits(),
                    c.timing.breaths_per_min.to_bits(),
                    c.affected.offset_mm.map(f64::to_bits),
                    c.unaffected.map(|u| u.held_ml.map(f64::to_bits))
                ));
            }
            out
        };
        assert_eq!(run(), run());
    }

    #[test]
    fn air_accumulates_monotonically_until_treated() {
        let mut m = course(TensionParams::new(Side::Left));
        let mut last = -1.0;
        for _ in 0..2000 {
            let c = m.advance();
            assert!(c.pleural_air_ml >= last && c.inflow_ml >= 0.0);
            last = c.pleural_air_ml;
        }
    }

    #[test]
    fn needle_decompression_reverses_arrest_and_the_chest_tube_restores_normal_breathing() {
        let mut m = course(hand(100.0, 0.0));
        let mut c = m.advance();
        while !c.arrest {
            c = m.advance();
        }
        assert_eq!(c.cycle, 14);
        // P = 1400 ml; the needle vents to 25 % = 350 ml over 10 cycles: −105 ml per cycle.
        let rec = m.intervene(Intervention::NeedleDecompression, Side::Left, 12_345);
        assert_eq!(
            (rec.outcome, rec.cycle, rec.tick),
            (Outcome::Applied, 15, 12_345)
        );
        let vented: Vec<TensionCycle> = (0..12).map(|_| m.advance()).collect();
        assert_eq!(vented[0].pleural_air_ml, 1295.0);
        assert_eq!(vented[0].inflow_ml, 0.0);
        // 1400 − 105·k ≥ 920 while k ≤ 4: the SVC reopens at k = 5 (P = 875, X = 0).
        assert!(vented[3].svc_closed && !vented[4].svc_closed);
        // Arrest clears with the SVC; the right lung comes back over N_h = 5 cycles.
        assert!(!vented[4].arrest);
        assert!(vented[4].unaffected.unwrap().held_ml.is_some());
        assert!(vented[10].unaffected.unwrap().held_ml.is_none());
        assert!((vented[9].pleural_air_ml - 350.0).abs() < 1e-9);
        assert!((vented[11].pleural_air_ml - 350.0).abs() < 1e-9);
        // The left lung breathes again: dV = 350/875 = 0.4, tidal 250·0.6 = 150 ml.
        assert!((vented[11].affected.tidal_ml - 150.0).abs() < 1e-9);
        // A second needle does nothing; the wrong side does nothing; the chest tube drains the rest.
        assert_eq!(
            m.intervene(Intervention::NeedleDecompression, Side::Left, 1)
                .outcome,
            Outcome::AlreadyApplied
        );
        assert_eq!(
            m.intervene(Intervention::ChestTube, Side::Right, 2).outcome,
            Outcome::WrongSide
        );
        assert_eq!(
            m.intervene(Intervention::ChestTube, Side::Left, 3).outcome,
            Outcome::Applied
        );
        let drained: Vec<TensionCycle> = (0..8).map(|_| m.advance()).collect();
        // 350 ml at 50 ml per cycle: empty after 7 cycles, then exactly normal breathing.
        assert_eq!(drained[6].pleural_air_ml, 0.0);
        let last = drained[7];
        assert_eq!(last.timing, Timing::default());
        assert_eq!(last.affected.collapse, 0.0);
        assert_eq!(last.affected.tidal_ml, 250.0);
        assert_eq!(last.unaffected.unwrap().tidal_ml, 250.0);
    }

    #[test]
    fn the_affected_constants_follow_dv_and_are_checked_once() {
        let p = preset(DEFAULT_PRESET).unwrap();
        let m = course(hand(100.0, 0.0));
        m.check_constants(&p.inhale, &p.exhale).unwrap();
        let (mut i, mut e) = (p.inhale.clone(), p.exhale.clone());
        m.constants_into(0.0, (&p.inhale, &p.exhale), (&mut i, &mut e))
            .unwrap();
        assert_eq!((&i, &e), (&p.inhale, &p.exhale));
        // dV_t = 0.5, φ = 0.1: x = 0.05; venegas χ_2 = 0.46 on inhalation (eq. 8.9):
        // 0.46·ln(0.023)/ln(0.0285) = 0.46·(−3.772261)/(−3.557851) = 0.487721.
        m.constants_into(0.5, (&p.inhale, &p.exhale), (&mut i, &mut e))
            .unwrap();
        assert!((i.chi[1] - 0.487_721).abs() < 1e-6, "{}", i.chi[1]);
        // Constants for which eq. 8.9 is singular within the course are refused at the start.
        let big = PhaseConstants::from_table(&[12.0, 1.0, 0.5], 2.0);
        assert!(matches!(
            m.check_constants(&big, &p.exhale),
            Err(DiseaseError::Resistance(_))
        ));
    }

    #[test]
    fn an_occlusive_dressing_stops_only_a_wound() {
        let mut lung = course(TensionParams::new(Side::Left));
        let r = lung.intervene(Intervention::OcclusiveDressing, Side::Left, 0);
        assert!(matches!(r.outcome, Outcome::NoEffect(_)));
        let mut wound = course(TensionParams {
            source: LeakSource::Wound,
            ..TensionParams::new(Side::Left)
        });
        for _ in 0..50 {
            wound.advance();
        }
        assert_eq!(
            wound
                .intervene(Intervention::OcclusiveDressing, Side::Left, 7)
                .outcome,
            Outcome::Applied
        );
        let held = wound.advance().pleural_air_ml;
        // The wound is sealed: no more air, and none leaves either (the tension stays).
        for _ in 0..100 {
            assert_eq!(wound.advance().pleural_air_ml, held);
        }
        assert_eq!(
            wound
                .intervene(Intervention::OcclusiveDressing, Side::Left, 8)
                .outcome,
            Outcome::AlreadyApplied
        );
    }

    #[test]
    fn every_parameter_edge_is_a_named_error() {
        let (l, r) = lungs();
        let b = preset(DEFAULT_PRESET).unwrap().boundary;
        let build = |p: TensionParams| Tension::new(p, Timing::default(), b, l, Some(r));
        let base = TensionParams::new(Side::Left);
        let cases: Vec<(TensionParams, &str)> = vec![
            (
                TensionParams {
                    inflow_ml: 0.0,
                    ..base
                },
                "v_p_ml",
            ),
            (
                TensionParams {
                    inflow_ml: f64::NAN,
                    ..base
                },
                "v_p_ml",
            ),
            (TensionParams { tau: -0.1, ..base }, "tau"),
            (
                TensionParams {
                    tau: f64::INFINITY,
                    ..base
                },
                "tau",
            ),
            (
                TensionParams {
                    beta_mm: 0.0,
                    ..base
                },
                "beta_mm",
            ),
            (
                TensionParams {
                    alpha_ml: 3000.0,
                    ..base
                },
                "alpha_ml",
            ),
            (TensionParams { phi: -0.1, ..base }, "phi"),
            (
                TensionParams {
                    needle_residual: 1.5,
                    ..base
                },
                "needle_residual",
            ),
            (
                TensionParams {
                    needle_vent_cycles: 0,
                    ..base
                },
                "needle_vent_cycles",
            ),
            (
                TensionParams {
                    chest_tube_ml_per_cycle: 0.0,
                    ..base
                },
                "chest_tube_ml_per_cycle",
            ),
            (
                TensionParams {
                    v1_max_ml: Some(960.0),
                    ..base
                },
                "v1_max_ml",
            ),
            (
                TensionParams {
                    v1_max_ml: Some(0.0),
                    ..base
                },
                "v1_max_ml",
            ),
            (
                TensionParams {
                    v2_max_ml: Some(1000.0),
                    ..base
                },
                "v2_max_ml",
            ),
            (
                TensionParams {
                    v2_max_ml: Some(7000.0),
                    ..base
                },
                "v2_max_ml",
            ),
        ];
        for (p, key) in cases {
            let e = build(p).unwrap_err().to_string();
            assert!(e.contains(key), "{key}: {e}");
        }
        let e = Tension::new(
            TensionParams::new(Side::Right),
            Timing::default(),
            b,
            l,
            Some(r),
        )
        .unwrap_err();
        assert_eq!(e, DiseaseError::MissingLung { side: "right" });
        let e = Tension::new(
            TensionParams {
                v2_max_ml: Some(3000.0),
                ..base
            },
            Timing::default(),
            b,
            l,
            None,
        )
        .unwrap_err();
        assert!(e.to_string().contains("v2_max_ml"));
        // The extremes that are allowed give a finite course.
        for p in [
            TensionParams {
                inflow_ml: 1000.0,
                tau: 0.0,
                hyperexpansion_cycles: 0,
                ..base
            },
            TensionParams {
                inflow_ml: 1e-300,
                tau: 10.0,
                ..base
            },
            TensionParams {
                v1_max_ml: Some(950.0),
                beta_mm: 100.0,
                ..base
            },
            TensionParams {
                needle_residual: 1.0,
                alpha_ml: 2500.0,
                phi: 1.0,
                ..base
            },
        ] {
            let mut m = build(p).unwrap();
            m.intervene(Intervention::NeedleDecompression, Side::Left, 0);
            for _ in 0..500 {
                finite(&m.advance());
            }
        }
    }

    fn finite(c: &TensionCycle) {
        let mut v = vec![
            c.pleural_air_ml,
            c.dv,
            c.loss_fraction,
            c.shift_mm,
            c.timing.breaths_per_min,
            c.drop.drop_mm,
        ];
        for l in std::iter::once(&c.affected).chain(c.unaffected.as_ref()) {
            v.extend([
                l.collapse,
                l.base_volume_ml,
                l.tidal_ml,
                l.held_ml.unwrap_or(0.0),
            ]);
            v.extend(l.offset_mm);
        }
        assert!(v.iter().all(|x| x.is_finite()), "{c:?}");
    }

    /// The generated default lungs (left 1100/2400 of the PV change, right 1300/2400) and a course
    /// of `params` on them.
    fn default_course(params: TensionParams) -> Tension {
        let base = |side, share| {
            let mesh = crate::mesh::generate::lung(side, 4000).unwrap();
            LungBaseline::of(&mesh, side, share).unwrap()
        };
        Tension::new(
            params,
            Timing::default(),
            preset(DEFAULT_PRESET).unwrap().boundary,
            base(Side::Left, 1100.0 / 2400.0),
            Some(base(Side::Right, 1300.0 / 2400.0)),
        )
        .unwrap()
    }

    /// (cycles to arrest, minutes to arrest, the first cycle with the SVC closed and its state).
    fn untreated_figures(m: &Tension) -> (u64, f64, TensionCycle) {
        let cycles = m.cycles_to_arrest().unwrap();
        let mut run = m.untreated();
        let mut seconds = 0.0;
        let mut first_svc = None;
        for _ in 0..=cycles {
            let c = run.advance();
            seconds += 60.0 / c.timing.breaths_per_min;
            if c.svc_closed && first_svc.is_none() {
                first_svc = Some(c);
            }
        }
        (cycles, seconds / 60.0, first_svc.unwrap())
    }

    #[test]
    fn default_course_reaches_arrest_in_minutes() {
        //! Pins the defaults' time scale (EQUATIONS §4.3, §4.6) on the generated default left lung,
        //! for both readings; the seed's figure is the one documented before issue 25.
        for model in [CourseModel::Seed, CourseModel::Clinical] {
            let m = default_course(TensionParams::new(Side::Left).with_model(model));
            let (cycles, minutes, svc) = untreated_figures(&m);
            eprintln!(
                "default left course ({}): V1max {:.0} ml, shift {:.3} mm/ml, SVC closing air \
                 {:.1} ml; SVC closes in cycle {} at {:.1} ml (lung {:.1} % of the way to V1max), \
                 arrest in cycle {cycles}, {minutes:.2} min",
                model.name(),
                m.v1_max_ml(),
                m.shift_mm_per_ml(),
                m.svc_closing_air_ml(),
                svc.cycle,
                svc.pleural_air_ml,
                100.0 * svc.dv,
            );
            assert!((100..2000).contains(&cycles));
            assert!(minutes > 2.0 && minutes < 30.0);
            if model == CourseModel::Seed {
                assert_eq!(cycles, 216);
                assert_eq!(svc.dv, 1.0);
            }
        }
    }

    #[test]
    fn the_clinical_mediastinum_moves_before_the_lung_has_collapsed() {
        //! Issue 25 (a): the shift grows from the first air (shared by compliance) and the SVC
        //! closes while the lung still breathes (Leigh-Smith & Harris 2005: tension is a positive
        //! pleural pressure, not a completely collapsed lung).
        let m = default_course(TensionParams::new(Side::Left));
        let (_, _, svc) = untreated_figures(&m);
        assert!(svc.dv < 0.9 && svc.affected.tidal_ml > 0.0, "{svc:?}");
        let mut run = m.untreated();
        let (mut last_x, mut last_c, mut last_p) = (-1.0, -1.0, -1.0);
        for t in 0..400 {
            let c = run.advance();
            finite(&c);
            if t >= 1 {
                assert!(
                    c.shift_mm > 0.0,
                    "cycle {t}: no shift with {} ml",
                    c.pleural_air_ml
                );
            }
            assert!(c.shift_mm >= last_x && c.affected.collapse >= last_c);
            assert!(c.pleural_air_ml >= last_p && c.dv <= 1.0);
            // The air is exactly the lung's loss plus the mediastinum's share.
            let displaced = c.loss_fraction * m.affected.start_volume_ml;
            assert!(displaced <= c.pleural_air_ml + 1e-9);
            (last_x, last_c, last_p) = (c.shift_mm, c.affected.collapse, c.pleural_air_ml);
        }
    }

    #[test]
    fn a_clinical_needle_relieves_the_tension_within_three_breaths() {
        //! Issue 25 (b): Pulse's needle is a low-resistance path from the pleural space to the
        //! environment; here it vents with a one-cycle time constant to the air at atmospheric
        //! pressure. The seed reading vents 10 % of the way per cycle.
        for model in [CourseModel::Clinical, CourseModel::Seed] {
            let mut m = default_course(TensionParams::new(Side::Left).with_model(model));
            let mut c = m.advance();
            while !c.arrest {
                c = m.advance();
            }
            let rec = m.intervene(Intervention::NeedleDecompression, Side::Left, 0);
            assert_eq!(rec.outcome, Outcome::Applied);
            let after: Vec<TensionCycle> = (0..12).map(|_| m.advance()).collect();
            let relieved = after.iter().position(|c| !c.svc_closed).unwrap();
            let breathing = after
                .iter()
                .position(|c| c.unaffected.unwrap().held_ml.is_none())
                .unwrap();
            eprintln!(
                "{}: needle at {:.1} ml, {:.1} mm: SVC open after {} cycles, both lungs breathe \
                 after {} cycles; 3 cycles on: {:.1} ml, {:.2} mm",
                model.name(),
                c.pleural_air_ml,
                c.shift_mm,
                relieved + 1,
                breathing + 1,
                after[2].pleural_air_ml,
                after[2].shift_mm
            );
            match model {
                CourseModel::Clinical => {
                    assert_eq!(relieved, 0, "the first cycle after the needle");
                    // 95 % of the way to the atmospheric air in three cycles (e^{−3} = 0.0498).
                    let floor = m.atmospheric_air_ml();
                    let excess0 = c.pleural_air_ml - floor;
                    assert!(after[2].pleural_air_ml - floor <= 0.05 * excess0);
                    assert!(after[2].shift_mm < 0.5 * m.params().beta_mm);
                    assert!(after
                        .windows(2)
                        .all(|w| w[1].pleural_air_ml <= w[0].pleural_air_ml));
                    assert!(after[11].affected.tidal_ml > 0.0);
                }
                // 7.5 % of what it found per cycle: 77.5 % is still there three cycles on.
                CourseModel::Seed => {
                    assert!((after[2].pleural_air_ml - 0.775 * c.pleural_air_ml).abs() < 1e-9)
                }
            }
        }
        // A needle into a pneumothorax below atmospheric pressure lets air in up to it (the path
        // is open both ways), and no further.
        let mut m = default_course(TensionParams::new(Side::Left));
        for _ in 0..5 {
            m.advance();
        }
        m.intervene(Intervention::NeedleDecompression, Side::Left, 0);
        let floor = m.atmospheric_air_ml();
        let mut last = 0.0;
        for _ in 0..40 {
            let c = m.advance();
            assert!(c.pleural_air_ml >= last && c.pleural_air_ml <= floor + 1e-9);
            last = c.pleural_air_ml;
        }
        assert!(floor - last < 1e-6 * floor);
    }

    #[test]
    fn the_clinical_onset_adds_no_more_tidal_volume_than_its_air_explains() {
        //! Issue 25 (c): α grows with the way to V1max, so 5 ml of air at onset changes the
        //! unaffected lung's tidal volume by α·dV (≪ 5 ml), not by α = 100 ml.
        for model in [CourseModel::Clinical, CourseModel::Seed] {
            let mut m = default_course(TensionParams::new(Side::Left).with_model(model));
            let c0 = m.advance();
            let c1 = m.advance();
            let jump = c1.unaffected.unwrap().tidal_ml - c0.unaffected.unwrap().tidal_ml;
            let lost = c0.affected.tidal_ml - c1.affected.tidal_ml;
            eprintln!(
                "{}: onset {:.1} ml of air: unaffected tidal {:.3} -> {:.3} ml (+{jump:.3}), \
                 affected {:.3} -> {:.3} ml",
                model.name(),
                c1.pleural_air_ml,
                c0.unaffected.unwrap().tidal_ml,
                c1.unaffected.unwrap().tidal_ml,
                c0.affected.tidal_ml,
                c1.affected.tidal_ml
            );
            match model {
                CourseModel::Clinical => {
                    assert!(jump >= 0.0 && jump <= c1.pleural_air_ml, "{jump}");
                    assert!(lost >= 0.0 && lost <= c1.pleural_air_ml);
                    // Both lungs together breathe no more than before.
                    let total =
                        |c: &TensionCycle| c.affected.tidal_ml + c.unaffected.unwrap().tidal_ml;
                    assert!(total(&c1) <= total(&c0));
                }
                CourseModel::Seed => assert_eq!(jump, 100.0),
            }
        }
    }

    #[test]
    fn clinical_parameter_edges_are_named_errors_and_extremes_stay_finite() {
        let (l, r) = lungs();
        let b = preset(DEFAULT_PRESET).unwrap().boundary;
        let base = TensionParams::new(Side::Left);
        for (p, key) in [
            (
                TensionParams {
                    mediastinal_compliance_ml_per_cmh2o: 0.0,
                    ..base
                },
                "mediastinal_compliance_ml_per_cmh2o",
            ),
            (
                TensionParams {
                    mediastinal_compliance_ml_per_cmh2o: f64::NAN,
                    ..base
                },
                "mediastinal_compliance_ml_per_cmh2o",
            ),
            (
                TensionParams {
                    needle_tau_cycles: 0.0,
                    ..base
                },
                "needle_tau_cycles",
            ),
            (
                TensionParams {
                    needle_tau_cycles: f64::INFINITY,
                    ..base
                },
                "needle_tau_cycles",
            ),
        ] {
            let e = Tension::new(p, Timing::default(), b, l, Some(r))
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{key}: {e}");
        }
        for p in [
            TensionParams {
                mediastinal_compliance_ml_per_cmh2o: 0.1,
                inflow_ml: 1000.0,
                tau: 0.0,
                ..base
            },
            TensionParams {
                mediastinal_compliance_ml_per_cmh2o: 1000.0,
                needle_tau_cycles: 0.01,
                inflow_ml: 1e-300,
                ..base
            },
            TensionParams {
                needle_tau_cycles: 1000.0,
                v1_max_ml: Some(950.0),
                beta_mm: 100.0,
                ..base
            },
        ] {
            let mut m = Tension::new(p, Timing::default(), b, l, Some(r)).unwrap();
            assert!(m.svc_closing_air_ml().is_finite() && m.atmospheric_air_ml().is_finite());
            for t in 0..3000 {
                if t == 1500 {
                    m.intervene(Intervention::NeedleDecompression, Side::Left, t);
                }
                let c = m.advance();
                finite(&c);
                assert!(c.affected.collapse <= 1.0 && c.dv <= 1.0);
            }
        }
    }

    proptest! {
        #[test]
        fn hours_of_cycles_stay_finite_and_bounded(
            inflow in 0.1f64..200.0,
            tau in 0.0f64..0.05,
            n_h in 0u32..20,
            seed_model in proptest::bool::ANY,
            events in proptest::collection::vec((0u64..36_000, 0usize..3, proptest::bool::ANY), 0..6),
        ) {
            // 10 hours at 60 breaths/min, random interventions on either side.
            let model = if seed_model { CourseModel::Seed } else { CourseModel::Clinical };
            let mut m = course(TensionParams { inflow_ml: inflow, tau, hyperexpansion_cycles: n_h, model, ..TensionParams::new(Side::Left) });
            let bound = m.svc_closing_air_ml() + (n_h as f64 + 2.0) * inflow;
            let kinds = [Intervention::NeedleDecompression, Intervention::OcclusiveDressing, Intervention::ChestTube];
            for t in 0..36_000u64 {
                for &(at, k, left) in &events {
                    if at == t {
                        m.intervene(kinds[k], if left { Side::Left } else { Side::Right }, t);
                    }
                }
                let c = m.advance();
                finite(&c);
                prop_assert!(c.pleural_air_ml <= bound, "{} > {}", c.pleural_air_ml, bound);
                prop_assert!(c.affected.collapse >= 0.0 && c.affected.collapse <= 1.0);
            }
        }
    }
}
