//! # Closed pneumothorax (seed §8.1.2–8.1.3, eq. 8.1–8.9)
//!
//! From the pneumothorax index `I ∈ [0, 1]` of each affected lung and the extra effort α (ml):
//!
//! * **eq. 8.1** `dV = I^0.33`, the fraction of the affected lung's volume lost: the lung is shrunk
//!   towards its hilum to lose exactly `dV·V` ([`super::collapse`]);
//! * **eq. 8.2** the drop `A = (100·I − 4.2)/(4.7·2)` cm, applied as a rigid offset of `−10·A` mm in Z
//!   (clamped at 0 for `I < 0.042`; [`super::drop_for_index`]);
//! * **eq. 8.3–8.5** faster breathing `dT = T·dV` off each phase, clamped at [`super::MIN_PHASE_S`]
//!   ([`super::phase_times`]); one timing for both lungs (one respiratory centre), from the largest
//!   `dV` of the affected lungs;
//! * **eq. 8.6** the affected lung's tidal volume `V_new1 = V_old1·(1 − dV)` (the seed's V are tidal
//!   volumes, L3593–3594); at `dV = 1` (`I = 1`) it does not breathe at all and is held;
//! * **eq. 8.7** the unaffected lung's tidal volume `V_new2 = V_old2 + α`;
//! * **eq. 8.8–8.9** the affected lung's control constants ([`super::resistance::PNEUMOTHORAX`]:
//!   more resistive inhalation, less resistive exhalation) with `x = φ·dV`.
//!
//! **Decision (lungdyn), `I = 0`:** no pneumothorax. `dV = 0`, no drop, the normal phases, the normal
//! constants and — because α is "the increase in volume due to the extra effort in breathing" that a
//! pneumothorax causes — no α: the plan is the normal breathing bit for bit (test
//! `pneumothorax_index_zero_is_normal_breathing`). Any `I > 0` applies the full α, as the seed's demo
//! (`I = 0.1`, `α = 100 ml`) does.
//!
//! **Decision (lungdyn), bilateral:** both lungs may be affected, each with its own `I`; there is then
//! no unaffected lung to take α, and an `α ≠ 0` is refused.
//!
//! **Changed (lungdyn, issue 25), `model`:** the above is the seed's reading ([`CourseModel::Seed`]).
//! The default [`CourseModel::Clinical`] (EQUATIONS §4.6) replaces eq. 8.3–8.5 by a rate that keeps
//! the alveolar ventilation with the scene's I:E ([`super::clinical_phase_times`]; West ch. 2; BTS
//! pleural disease guideline 2023) and gives the unaffected lung `α·dV` instead of α: the seed's demo
//! breathes 14.5/min at 6.4 l/min instead of 40/min at 19.7 l/min.
//!
//! Assumptions: the seed's upright patient (the drop is along the body's −Z); the plan is computed
//! once per scene (it allocates its constants), not per tick.

use super::collapse::collapse_for_loss;
use super::resistance::{self, ResistanceReport};
use super::{
    check_range, clinical_phase_times, drop_for_index, phase_times, volume_fraction_lost,
    CourseModel, DiseaseError, LungBaseline, LungState, NormalBreathing, PhaseTimes, VerticalDrop,
    ALPHA_MAX_ML,
};
use crate::mesh::Side;
use crate::pv::{Boundary, Breathing, PhaseConstants, PvError, Timing};

/// A closed pneumothorax of one or both lungs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClosedPneumothorax {
    /// Pneumothorax index per lung, indexed by [`Side::index`]; `None` = the lung is not affected.
    pub index: [Option<f64>; 2],
    /// Extra effort α of eq. 8.7, ml, added to the unaffected lung's tidal volume.
    pub alpha_ml: f64,
    /// Proportionality constant φ of eq. 8.8–8.9 (seed: 0.1).
    pub phi: f64,
    /// Which reading (scene key `model`; default [`CourseModel::Clinical`]).
    pub model: CourseModel,
}

impl ClosedPneumothorax {
    /// One affected lung.
    pub fn unilateral(side: Side, index: f64, alpha_ml: f64, phi: f64) -> Self {
        let mut i = [None, None];
        i[side.index()] = Some(index);
        Self {
            index: i,
            alpha_ml,
            phi,
            model: CourseModel::default(),
        }
    }

    /// Both lungs affected (no α: there is no unaffected lung).
    pub fn bilateral(left: f64, right: f64, phi: f64) -> Self {
        let mut i = [None, None];
        i[Side::Left.index()] = Some(left);
        i[Side::Right.index()] = Some(right);
        Self {
            index: i,
            alpha_ml: 0.0,
            phi,
            model: CourseModel::default(),
        }
    }

    /// The same pneumothorax under `model`.
    pub fn with_model(self, model: CourseModel) -> Self {
        Self { model, ..self }
    }

    /// The index of `side`, if affected.
    pub fn index_of(&self, side: Side) -> Option<f64> {
        self.index[side.index()]
    }

    /// Check every parameter; errors name the scene key.
    pub fn validate(&self) -> Result<(), DiseaseError> {
        let mut affected = 0;
        for side in [Side::Right, Side::Left] {
            if let Some(i) = self.index_of(side) {
                let name = match side {
                    Side::Left => "index_left",
                    Side::Right => "index_right",
                };
                check_range(name, i, 0.0, 1.0, "within 0..=1")?;
                affected += 1;
            }
        }
        if affected == 0 {
            return Err(DiseaseError::NotApplicable {
                name: "index",
                reason: "a closed pneumothorax needs at least one affected lung",
            });
        }
        check_range(
            "alpha_ml",
            self.alpha_ml,
            0.0,
            ALPHA_MAX_ML,
            "within 0..=2500 ml (seed L3613-3616)",
        )?;
        if affected == 2 && self.alpha_ml != 0.0 {
            return Err(DiseaseError::NotApplicable {
                name: "alpha_ml",
                reason: "both lungs are affected: there is no unaffected lung to take the extra effort (eq. 8.7)",
            });
        }
        check_range(
            "phi",
            self.phi,
            0.0,
            resistance::PHI_MAX,
            "within 0..=1 (seed: 0.1)",
        )?;
        Ok(())
    }

    /// The plan for the lungs the scene simulates (`lungs`, any order; each affected lung must be
    /// among them) from the scene's normal breathing.
    pub fn plan(
        &self,
        normal: &NormalBreathing,
        lungs: &[LungBaseline],
    ) -> Result<ClosedPlan, DiseaseError> {
        self.validate()?;
        for side in [Side::Right, Side::Left] {
            if self.index_of(side).is_some() && !lungs.iter().any(|l| l.side == side) {
                return Err(DiseaseError::MissingLung { side: side.name() });
            }
        }
        let mut dv_max = 0.0f64;
        let mut any_pneumothorax = false;
        for side in [Side::Right, Side::Left] {
            if let Some(i) = self.index_of(side) {
                dv_max = dv_max.max(volume_fraction_lost(i)?);
                any_pneumothorax |= i > 0.0;
            }
        }
        let seed_times = phase_times(&normal.timing, dv_max)?;
        let tv = normal.boundary.tv_ml;
        // α of eq. 8.7: the seed adds it in full for any I > 0; the clinical model in proportion to
        // the volume lost (EQUATIONS §4.6 (c)).
        let alpha = match self.model {
            CourseModel::Seed => self.alpha_ml,
            CourseModel::Clinical => self.alpha_ml * dv_max,
        };
        let mut out = Vec::with_capacity(lungs.len());
        for lung in lungs {
            lung.validate()?;
            let plan = match self.index_of(lung.side) {
                Some(index) => self.affected_lung(normal, lung, index)?,
                None => {
                    let alpha = if any_pneumothorax { alpha } else { 0.0 };
                    unaffected_lung(normal, lung, alpha)
                }
            };
            out.push(plan);
        }
        let times = match self.model {
            CourseModel::Seed => seed_times,
            CourseModel::Clinical => {
                let total: f64 = out.iter().map(|l| l.state.tidal_ml).sum();
                let normal_total: f64 = lungs.iter().map(|l| l.share * tv).sum();
                if any_pneumothorax {
                    clinical_phase_times(&normal.timing, normal_total, total)?
                } else {
                    seed_times
                }
            }
        };
        let timing = times.timing(&normal.timing);
        Ok(ClosedPlan {
            times,
            timing,
            lungs: out,
        })
    }

    /// The plan of a lung with a pneumothorax of `index`: its volume lost (eq. 8.1), collapse and
    /// drop (eq. 8.2), tidal volume shrunk in proportion (eq. 8.6), held when wholly collapsed, and
    /// its phases' control constants raised by φ·ΔV (eq. 8.8–8.9).
    fn affected_lung(
        &self,
        normal: &NormalBreathing,
        lung: &LungBaseline,
        index: f64,
    ) -> Result<LungPlan, DiseaseError> {
        let tv = normal.boundary.tv_ml;
        let dv = volume_fraction_lost(index)?;
        let drop = drop_for_index(index);
        let collapse = collapse_for_loss(dv)?;
        let base = lung.start_volume_ml * (1.0 - dv);
        let tv_new = tv * (1.0 - dv);
        let held = dv >= 1.0;
        let (inhale, exhale, reports) = if dv == 0.0 {
            (
                normal.inhale.clone(),
                normal.exhale.clone(),
                identity_reports(),
            )
        } else {
            let x = self.phi * dv;
            let (t_in, t_ex) = resistance::PNEUMOTHORAX;
            let mut i = normal.inhale.clone();
            let mut e = normal.exhale.clone();
            let ri = resistance::phase_into(&normal.inhale, t_in, x, &mut i)?;
            let re = resistance::phase_into(&normal.exhale, t_ex, x, &mut e)?;
            (i, e, (ri, re))
        };
        Ok(LungPlan {
            side: lung.side,
            index: Some(index),
            dv,
            drop: Some(drop),
            state: LungState {
                side: lung.side,
                collapse,
                base_volume_ml: base,
                tidal_ml: if held { 0.0 } else { lung.share * tv_new },
                held_ml: held.then_some(base),
                offset_mm: [
                    0.0,
                    0.0,
                    if drop.drop_mm > 0.0 {
                        -drop.drop_mm
                    } else {
                        0.0
                    },
                ],
                resistance_dv: dv,
            },
            boundary: (!held).then_some(Boundary {
                tv_ml: tv_new,
                ..normal.boundary
            }),
            inhale,
            exhale,
            resistance: reports,
            base_lift_mm: collapse * (lung.hilum_mm[2] - lung.base_z_mm),
        })
    }
}

/// Both phases' resistance reports of a lung whose resistance is not changed.
fn identity_reports() -> (ResistanceReport, ResistanceReport) {
    let identity = || ResistanceReport {
        identity: true,
        ..Default::default()
    };
    (identity(), identity())
}

/// The plan of a lung without a pneumothorax: normal breathing, its tidal volume raised by the
/// compensation `alpha_ml` (eq. 8.7; 0 when no lung has a pneumothorax).
fn unaffected_lung(normal: &NormalBreathing, lung: &LungBaseline, alpha_ml: f64) -> LungPlan {
    let tv = normal.boundary.tv_ml;
    let tv_new = if alpha_ml == 0.0 {
        tv
    } else {
        tv + alpha_ml / lung.share
    };
    LungPlan {
        side: lung.side,
        index: None,
        dv: 0.0,
        drop: None,
        state: LungState {
            tidal_ml: lung.share * tv + alpha_ml,
            ..LungState::normal(lung, &normal.boundary)
        },
        boundary: Some(Boundary {
            tv_ml: tv_new,
            ..normal.boundary
        }),
        inhale: normal.inhale.clone(),
        exhale: normal.exhale.clone(),
        resistance: identity_reports(),
        base_lift_mm: 0.0,
    }
}

/// The closed pneumothorax's changes to every simulated lung.
#[derive(Debug, Clone, PartialEq)]
pub struct ClosedPlan {
    /// Eq. 8.3–8.5 for the largest `dV`, with the clamp's report.
    pub times: PhaseTimes,
    /// The timing both lungs breathe at (the normal timing itself when `dT = 0`).
    pub timing: Timing,
    /// One plan per simulated lung, in the order given.
    pub lungs: Vec<LungPlan>,
}

impl ClosedPlan {
    /// The plan of `side`, if simulated.
    pub fn lung(&self, side: Side) -> Option<&LungPlan> {
        self.lungs.iter().find(|l| l.side == side)
    }
}

/// One lung's closed-pneumothorax plan: what the engine applies from the lung's next cycle.
#[derive(Debug, Clone, PartialEq)]
pub struct LungPlan {
    /// Which lung.
    pub side: Side,
    /// Its pneumothorax index (`None`: unaffected).
    pub index: Option<f64>,
    /// Eq. 8.1 volume fraction lost (0 for an unaffected lung).
    pub dv: f64,
    /// Eq. 8.2 drop with its clamp (`None` for an unaffected lung).
    pub drop: Option<VerticalDrop>,
    /// Collapse, volumes, hold, offset.
    pub state: LungState,
    /// Boundary values whose TV gives this lung its tidal volume with its share (FRC, pressures
    /// unchanged); `None` when the lung is held (`dV = 1`).
    pub boundary: Option<Boundary>,
    /// Inhalation constants (eq. 8.9 for an affected lung, the normal ones otherwise).
    pub inhale: PhaseConstants,
    /// Exhalation constants (eq. 8.8 for an affected lung).
    pub exhale: PhaseConstants,
    /// What eq. 8.8–8.9 did (inhalation, exhalation).
    pub resistance: (ResistanceReport, ResistanceReport),
    /// How far the collapse towards the hilum raised the lung's base, mm (the seed's drop "so that
    /// it sits on the diaphragm" is eq. 8.2's `A`; this is the gap the collapse itself opens, for
    /// reports and the renderer).
    pub base_lift_mm: f64,
}

impl LungPlan {
    /// The breathing cycle this lung plays from its next cycle (`None` when held).
    pub fn breathing(&self, timing: &Timing) -> Option<Result<Breathing, PvError>> {
        self.boundary
            .map(|b| Breathing::from_constants(&self.inhale, &self.exhale, b, timing))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pv::{preset, DEFAULT_PRESET};
    use proptest::prelude::*;

    fn normal() -> NormalBreathing {
        let p = preset(DEFAULT_PRESET).unwrap();
        NormalBreathing {
            inhale: p.inhale,
            exhale: p.exhale,
            boundary: p.boundary,
            timing: Timing::default(),
        }
    }

    /// Two synthetic lungs: left 1100 ml, right 1300 ml, each half of the PV change (tidal 250 ml),
    /// hilum 120 mm above the base.
    fn lungs() -> [LungBaseline; 2] {
        let l = |side, v| LungBaseline {
            side,
            start_volume_ml: v,
            share: 0.5,
            box_mm: [100.0, 150.0, 240.0],
            hilum_mm: [0.0, 0.0, 120.0],
            base_z_mm: 0.0,
        };
        [l(Side::Right, 1300.0), l(Side::Left, 1100.0)]
    }

    #[test]
    fn pneumothorax_index_zero_is_normal_breathing() {
        let n = normal();
        let plan = ClosedPneumothorax::unilateral(Side::Left, 0.0, 100.0, 0.1)
            .plan(&n, &lungs())
            .unwrap();
        assert_eq!(plan.timing, n.timing);
        let reference =
            Breathing::from_constants(&n.inhale, &n.exhale, n.boundary, &n.timing).unwrap();
        for (lp, base) in plan.lungs.iter().zip(lungs()) {
            assert_eq!(
                lp.state,
                LungState::normal(&base, &n.boundary),
                "{:?}",
                lp.side
            );
            assert_eq!(lp.state.offset_mm.map(f64::to_bits), [0u64; 3]);
            assert_eq!(lp.inhale, n.inhale);
            assert_eq!(lp.exhale, n.exhale);
            assert_eq!(lp.boundary, Some(n.boundary));
            let b = lp.breathing(&plan.timing).unwrap().unwrap();
            assert_eq!(b.cycle_ticks(), reference.cycle_ticks());
            for tick in 0..reference.cycle_ticks() as u64 {
                assert_eq!(
                    b.volume_at(tick).to_bits(),
                    reference.volume_at(tick).to_bits()
                );
            }
        }
    }

    #[test]
    fn the_seven_indices_by_hand() {
        // Left lung 1100 ml affected, right 1300 ml unaffected, share 0.5 each, TV 500 ml (tidal
        // 250 ml per lung), α = 100 ml, φ = 0.1, T = 5 s, T_i = T_e = 2.5 s, clamp 0.75 s.
        // Columns: I, dV = I^0.33, drop mm = 10·max(0, (100 I − 4.2)/9.4), affected tidal = 250(1 − dV),
        // base = 1100(1 − dV), collapse c = 1 − (1 − dV)^{1/3}, new inhalation phase (s).
        let rows: [(f64, f64, f64, f64, f64, f64, f64); 7] = [
            (0.0, 0.0, 0.0, 250.0, 1100.0, 0.0, 2.5),
            // dV = 0.0010715; 250·0.9989285 = 249.73212; 1100·0.9989285 = 1098.82133;
            // c = 1 − 0.9989285^{1/3} = 0.00035730; T' = 2.5 − 5·0.0010715 = 2.4946424.
            (
                1e-9,
                0.001_071_5,
                0.0,
                249.732_12,
                1_098.821_33,
                0.000_357_30,
                2.494_642_4,
            ),
            // dV = 0.351295; A = 0 (100·0.042 = 4.2); 250·0.648705 = 162.17619; 1100·0.648705 = 713.57524;
            // c = 1 − 0.648705^{1/3} = 1 − 0.865663 = 0.134337; raw T' = 0.743524 → clamped 0.75.
            (
                0.042, 0.351_295, 0.0, 162.176_19, 713.575_24, 0.134_337, 0.75,
            ),
            // dV = 0.467735; A = 5.8/9.4 = 0.617021 cm; 250·0.532265 = 133.06621; 1100·0.532265 = 585.49134;
            // c = 0.189582; raw T' = 0.161324 → 0.75 (40 breaths/min).
            (
                0.1, 0.467_735, 6.170_213, 133.066_21, 585.491_34, 0.189_582, 0.75,
            ),
            // dV = 0.587949; A = 15.8/9.4 = 1.680851 cm; 250·0.412051 = 103.01267; 1100·0.412051 = 453.25574;
            // c = 1 − 0.412051^{1/3} = 1 − 0.744132 = 0.255868.
            (
                0.2, 0.587_949, 16.808_511, 103.012_67, 453.255_74, 0.255_868, 0.75,
            ),
            // dV = 0.795536; A = 45.8/9.4 = 4.872340 cm; 250·0.204464 = 51.11588; 1100·0.204464 = 224.90987;
            // c = 1 − 0.204464^{1/3} = 1 − 0.589122 = 0.410878.
            (
                0.5, 0.795_536, 48.723_404, 51.115_88, 224.909_87, 0.410_878, 0.75,
            ),
            // dV = 1: A = 95.8/9.4 = 10.191489 cm; no tidal volume (held), base 0, collapse 1.
            (1.0, 1.0, 101.914_894, 0.0, 0.0, 1.0, 0.75),
        ];
        let n = normal();
        for (i, dv, drop, tidal, base, c, ti) in rows {
            let plan = ClosedPneumothorax::unilateral(Side::Left, i, 100.0, 0.1)
                .with_model(CourseModel::Seed)
                .plan(&n, &lungs())
                .unwrap();
            let l = plan.lung(Side::Left).unwrap();
            let close = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol;
            assert!(close(l.dv, dv, 1e-6), "I {i}: dV {}", l.dv);
            assert!(
                close(-l.state.offset_mm[2], drop, 1e-5),
                "I {i}: drop {:?}",
                l.state.offset_mm
            );
            assert!(
                close(l.state.tidal_ml, tidal, 1e-4),
                "I {i}: tidal {}",
                l.state.tidal_ml
            );
            assert!(
                close(l.state.base_volume_ml, base, 1e-4),
                "I {i}: base {}",
                l.state.base_volume_ml
            );
            assert!(
                close(l.state.collapse, c, 1e-6),
                "I {i}: c {}",
                l.state.collapse
            );
            assert!(
                close(plan.times.new_inhale_s, ti, 1e-6),
                "I {i}: T'_i {}",
                plan.times.new_inhale_s
            );
            assert_eq!(l.state.held_ml.is_some(), i == 1.0);
            // The unaffected right lung: tidal 250 + α = 350 ml whenever I > 0 (eq. 8.7).
            let r = plan.lung(Side::Right).unwrap();
            let want = if i > 0.0 { 350.0 } else { 250.0 };
            assert!(
                close(r.state.tidal_ml, want, 1e-9),
                "I {i}: right tidal {}",
                r.state.tidal_ml
            );
            assert!(close(0.5 * r.boundary.unwrap().tv_ml, want, 1e-9));
            // Everything the engine gets is finite, and every breathing lung has a playable cycle.
            for lp in &plan.lungs {
                assert!(lp.state.offset_mm.iter().all(|v| v.is_finite()));
                if let Some(b) = lp.breathing(&plan.timing) {
                    b.unwrap();
                }
            }
        }
    }

    #[test]
    fn the_seed_demo_changes_the_constants_by_eq_8_8_and_8_9() {
        let n = normal();
        let plan = ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1)
            .plan(&n, &lungs())
            .unwrap();
        let l = plan.lung(Side::Left).unwrap();
        // Venegas χ_1 = 0.57, χ_2 = 0.46, x = 0.1·0.467735 = 0.0467735.
        // Inhalation (eq. 8.9): 0.46·ln(0.46·0.0467735)/ln(0.57·0.0467735)
        //   = 0.46·ln(0.0215158)/ln(0.0266609) = 0.46·(−3.838967)/(−3.624557) = 0.487211.
        assert!(
            (l.inhale.chi[1] - 0.487_211).abs() < 1e-6,
            "{}",
            l.inhale.chi[1]
        );
        // Exhalation (eq. 8.8): 0.46·e^{(0.46 − 0.57)·0.0467735} = 0.46·e^{−0.00514509} = 0.457639.
        assert!(
            (l.exhale.chi[1] - 0.457_639).abs() < 1e-6,
            "{}",
            l.exhale.chi[1]
        );
        assert_eq!(l.inhale.chi[0], 0.57);
        assert_eq!(plan.lung(Side::Right).unwrap().inhale, n.inhale);
        assert!((l.base_lift_mm - 0.189_582 * 120.0).abs() < 1e-3);
    }

    #[test]
    fn bad_parameters_name_their_key() {
        let n = normal();
        let err = |c: ClosedPneumothorax| c.plan(&n, &lungs()).unwrap_err().to_string();
        assert!(
            err(ClosedPneumothorax::unilateral(Side::Left, 1.5, 100.0, 0.1)).contains("index_left")
        );
        assert!(err(ClosedPneumothorax::unilateral(
            Side::Left,
            f64::NAN,
            100.0,
            0.1
        ))
        .contains("index_left"));
        assert!(
            err(ClosedPneumothorax::unilateral(Side::Left, 0.1, -1.0, 0.1)).contains("alpha_ml")
        );
        assert!(
            err(ClosedPneumothorax::unilateral(Side::Left, 0.1, 3000.0, 0.1)).contains("alpha_ml")
        );
        assert!(err(ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 2.0)).contains("phi"));
        let mut both = ClosedPneumothorax::bilateral(0.1, 0.2, 0.1);
        both.alpha_ml = 50.0;
        assert!(err(both).contains("alpha_ml"));
        let only_right = [lungs()[0]];
        let e = ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1)
            .plan(&n, &only_right)
            .unwrap_err();
        assert_eq!(e, DiseaseError::MissingLung { side: "left" });
        // φ so large that eq. 8.9's denominator is singular for these constants: a typed error.
        let k = NormalBreathing {
            inhale: PhaseConstants::from_table(&[20.0, 1.0, 0.5], 2.0),
            ..n.clone()
        };
        let e = ClosedPneumothorax::unilateral(Side::Left, 1.0, 0.0, 0.05)
            .plan(&k, &lungs())
            .unwrap_err();
        assert!(matches!(e, DiseaseError::Resistance(_)), "{e}");
    }

    #[test]
    fn bilateral_pneumothorax_changes_both_lungs_and_times_by_the_larger_dv() {
        let n = normal();
        let plan = ClosedPneumothorax::bilateral(0.01, 0.001, 0.1)
            .with_model(CourseModel::Seed)
            .plan(&n, &lungs())
            .unwrap();
        let (l, r) = (
            plan.lung(Side::Left).unwrap(),
            plan.lung(Side::Right).unwrap(),
        );
        // dV left = 0.01^0.33 = 0.218776, right = 0.001^0.33 = 0.102329; dT = 5·0.218776 = 1.093881.
        assert!((l.dv - 0.218_776).abs() < 1e-6 && (r.dv - 0.102_329).abs() < 1e-6);
        assert!((plan.times.new_inhale_s - (2.5 - 1.093_881)).abs() < 1e-6);
        assert!(l.state.collapse > r.state.collapse && r.state.collapse > 0.0);
    }

    #[test]
    fn the_clinical_course_keeps_the_alveolar_ventilation_by_hand() {
        // I = 0.1: dV = 0.467735; left tidal 250·0.532265 = 133.066209; right 250 + α·dV =
        // 250 + 46.773514 = 296.773514; total 429.839723 ml. V_D = 0.3·500 = 150 ml:
        // f' = 12·350/279.839723 = 15.008591 /min; minute ventilation 6.45130 l/min (seed: 40/min,
        // 483.066 ml, 19.32 l/min).
        let n = normal();
        let plan = ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1)
            .plan(&n, &lungs())
            .unwrap();
        let (l, r) = (
            plan.lung(Side::Left).unwrap(),
            plan.lung(Side::Right).unwrap(),
        );
        assert!((l.state.tidal_ml - 133.066_209).abs() < 1e-5);
        assert!(
            (r.state.tidal_ml - 296.773_514).abs() < 1e-5,
            "{}",
            r.state.tidal_ml
        );
        let f = plan.timing.breaths_per_min;
        assert!((f - 15.008_591).abs() < 1e-5, "{f}");
        let minute = f * (l.state.tidal_ml + r.state.tidal_ml) / 1000.0;
        assert!((minute - 6.451_30).abs() < 1e-4, "{minute}");
        assert!(!plan.times.inhale_clamped);
        // The scene's I:E is kept: 1:1 here, 1:2 with a 1:2 scene.
        assert_eq!(plan.timing.ie_inhale, plan.timing.ie_exhale);
        let one_two = NormalBreathing {
            timing: Timing {
                ie_inhale: 1.0,
                ie_exhale: 2.0,
                ..Timing::default()
            },
            ..n.clone()
        };
        let p2 = ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1)
            .plan(&one_two, &lungs())
            .unwrap();
        assert!((p2.timing.ie_exhale / p2.timing.ie_inhale - 2.0).abs() < 1e-12);
        assert!((p2.timing.breaths_per_min - 15.008_591).abs() < 1e-5);
        // I = 1: the left lung is held; right 350 ml; f' = 12·350/200 = 21 /min.
        let p1 = ClosedPneumothorax::unilateral(Side::Left, 1.0, 100.0, 0.1)
            .plan(&n, &lungs())
            .unwrap();
        assert!((p1.timing.breaths_per_min - 21.0).abs() < 1e-9);
        // Bilateral I = 1 on both: no tidal volume left, the rate is capped at 40/min (reported).
        let both = ClosedPneumothorax::bilateral(1.0, 1.0, 0.1)
            .plan(&n, &lungs())
            .unwrap();
        assert!(both.times.inhale_clamped && both.timing.breaths_per_min == 40.0);
        // The seed reading of the same demo, for the record: 40/min, I:E 1:1.
        let seed = ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1)
            .with_model(CourseModel::Seed)
            .plan(&n, &lungs())
            .unwrap();
        assert_eq!(seed.timing.breaths_per_min, 40.0);
        assert_eq!(seed.lung(Side::Right).unwrap().state.tidal_ml, 350.0);
    }

    proptest! {
        #[test]
        fn a_larger_index_never_breathes_slower_or_deeper(a in 0.0f64..=1.0, b in 0.0f64..=1.0) {
            let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
            let n = normal();
            let p = |i| ClosedPneumothorax::unilateral(Side::Left, i, 100.0, 0.1).plan(&n, &lungs()).unwrap();
            let (pl, ph) = (p(lo), p(hi));
            let (l, h) = (pl.lung(Side::Left).unwrap(), ph.lung(Side::Left).unwrap());
            prop_assert!(h.dv >= l.dv && h.state.collapse >= l.state.collapse);
            prop_assert!(h.state.tidal_ml <= l.state.tidal_ml);
            prop_assert!(h.state.offset_mm[2] <= l.state.offset_mm[2]);
            prop_assert!(ph.times.breaths_per_min() >= pl.times.breaths_per_min());
            prop_assert!(h.inhale.chi.iter().chain(&h.exhale.chi).all(|v| v.is_finite()));
        }
    }
}
