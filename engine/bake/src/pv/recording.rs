//! What each breath of a ventilator recording is (`lungdyn pv recording`): the equation of motion of
//! a passive lung fitted by least squares and a class with its reason
//! ([`lung_model::recording::classify`], EQUATIONS §1.4, shared with `[pv] waveform` scenes), and
//! the PV model's fit (eq. 5.11, EQUATIONS §1.2) where its form applies: passive volume-controlled
//! breaths (airway pressure against volume).

use lung_model::pv::Phase;
pub use lung_model::recording::classify::{
    fit_equation_of_motion, BreathClass, EquationOfMotion, EFFORT_DIP_CMH2O, EFFORT_PES_DROP_CMH2O,
    MAX_PASSIVE_RESIDUAL, PLATEAU_FRACTION, TRIGGER_LEAD_S,
};
pub use lung_model::recording::MAX_IMBALANCE;
use lung_model::recording::{
    classify::{characterise_breath, BreathCharacter},
    segment, BreathSpan, Recording, SegmentOptions,
};
use rayon::prelude::*;

use super::fit::{fit_curve, CurveFit, FitOptions, PvSample};

/// The PV model's fit of one breath, or why it does not apply.
#[derive(Debug, Clone)]
pub enum PvOutcome {
    /// Fitted (eq. 5.11, both limbs).
    Fitted(Box<CurveFit>),
    /// Not fitted, with the reason.
    NotApplicable(String),
}

/// One breath, characterised: what [`characterise_breath`] finds (its fields read through this
/// report) and the PV model's fit.
#[derive(Debug, Clone)]
pub struct BreathReport {
    /// Timing, pressures, equation of motion, class and reason.
    pub breath: BreathCharacter,
    /// The PV model's fit, or why not.
    pub pv: PvOutcome,
}

impl std::ops::Deref for BreathReport {
    type Target = BreathCharacter;
    fn deref(&self) -> &BreathCharacter {
        &self.breath
    }
}

impl BreathReport {
    /// Expiration time over inspiration time (I:E is 1 : this).
    pub fn ie_ratio(&self) -> f64 {
        self.timing.expiration_s / self.timing.inspiration_s
    }
    /// The PV fit's RMS (worse limb), % of the normalised range, where fitted.
    pub fn pv_rms_percent(&self) -> Option<f64> {
        match &self.pv {
            PvOutcome::Fitted(f) => Some(f.rms_percent),
            PvOutcome::NotApplicable(_) => None,
        }
    }
}

/// Options of [`analyse`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AnalyseOptions {
    /// Segmentation.
    pub segment: SegmentOptions,
    /// The PV fit of passive volume-controlled breaths.
    pub fit: FitOptions,
}

/// Segment a recording and characterise every breath (PV fits in parallel).
pub fn analyse(rec: &Recording, opts: &AnalyseOptions) -> Vec<BreathReport> {
    let spans = segment(rec, &opts.segment);
    spans
        .par_iter()
        .enumerate()
        .map(|(k, span)| characterise(rec, k + 1, span, opts))
        .collect()
}

/// One breath: timing, pressures, equation of motion, class
/// ([`characterise_breath`]), PV fit.
pub fn characterise(
    rec: &Recording,
    index: usize,
    span: &BreathSpan,
    opts: &AnalyseOptions,
) -> BreathReport {
    let c = characterise_breath(rec, index, span, opts.segment.threshold_lps);
    let (class, volume) = (c.class, &c.volume_ml);
    let paw = &rec.paw_cmh2o[span.start..=span.end];
    let pv = if class == BreathClass::PassiveVolumeControlled {
        // The loop ends where the expiratory flow does: the end-expiratory pause (flow within the
        // noise band, pressure at PEEP, volume at its end) carries no PV information, only noise
        // and the drift correction's ramp.
        let flow_end = (span.expiration..=span.end)
            .rev()
            .find(|&i| rec.flow_lps[i] < -opts.segment.threshold_lps)
            .map_or(span.end, |i| (i + 1).min(span.end));
        let samples: Vec<PvSample> = (0..=flow_end - span.start)
            .map(|j| PvSample {
                pressure: paw[j],
                volume: volume[j],
                phase: Some(if span.start + j < span.expiration {
                    Phase::Inhale
                } else {
                    Phase::Exhale
                }),
            })
            .collect();
        match fit_curve(&samples, &opts.fit) {
            Ok(f) if f.rms_percent.is_finite() => PvOutcome::Fitted(Box::new(f)),
            Ok(f) => PvOutcome::NotApplicable(format!(
                "the fit did not converge to a finite error (RMS {})",
                f.rms_percent
            )),
            Err(e) => PvOutcome::NotApplicable(format!("the PV fit refused the loop: {e}")),
        }
    } else {
        PvOutcome::NotApplicable(
            match class {
                BreathClass::PassivePressureControlled => {
                    "pressure is held while volume rises: the PV model's limb drives volume by a \
                     pressure rising with phase time (eq. 5.10–5.11), which a flat pressure cannot \
                     represent; a scene plays such breaths from the recorded volume ([pv] waveform)"
                }
                BreathClass::PatientEffort => {
                    "the airway pressure is not the lungs' driving pressure while the patient's \
                     muscles add their own (it needs the oesophageal pressure)"
                }
                _ => "not a whole, clean breath",
            }
            .to_string(),
        )
    };
    BreathReport { breath: c, pv }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::recording::{Synthetic, SyntheticMode};

    fn quick() -> AnalyseOptions {
        AnalyseOptions {
            fit: FitOptions {
                q: Some(2.0),
                c: Some(1.0),
                ..Default::default()
            },
            ..Default::default()
        }
    }

    #[test]
    fn the_equation_of_motion_recovers_a_passive_lung() {
        for mode in [
            SyntheticMode::Volume { flow_lps: 0.5 },
            SyntheticMode::Pressure {
                above_peep_cmh2o: 12.0,
            },
        ] {
            let rec = Synthetic {
                mode,
                c_ml_per_cmh2o: 40.0,
                r_cmh2o_s_per_l: 12.0,
                peep_cmh2o: 6.0,
                rate_per_min: 12.0,
                ..Default::default()
            }
            .recording();
            let reports = analyse(&rec, &quick());
            assert_eq!(reports.len(), 3);
            for r in &reports {
                let eom = r.eom.expect("fitted");
                // Sampled square waves put the flow steps between samples: within 5 %.
                assert!(
                    (eom.compliance_ml_per_cmh2o - 40.0).abs() < 2.0,
                    "{mode:?}: {eom:?}"
                );
                assert!(
                    (eom.resistance_cmh2o_s_per_l - 12.0).abs() < 0.6,
                    "{mode:?}: {eom:?}"
                );
                assert!(eom.residual_percent < 5.0, "{eom:?}");
                assert!((r.peep_cmh2o - 6.0).abs() < 0.1, "{}", r.peep_cmh2o);
            }
        }
    }

    #[test]
    fn breaths_are_classified_by_what_drives_them() {
        let vc = Synthetic {
            breaths: 2,
            ..Default::default()
        }
        .recording();
        for r in analyse(&vc, &quick()) {
            assert_eq!(
                r.class,
                BreathClass::PassiveVolumeControlled,
                "{}",
                r.reason
            );
            assert!(r.pv_rms_percent().is_some(), "{:?}", r.pv);
        }
        let pc = Synthetic {
            mode: SyntheticMode::Pressure {
                above_peep_cmh2o: 15.0,
            },
            c_ml_per_cmh2o: 30.0,
            r_cmh2o_s_per_l: 8.0,
            peep_cmh2o: 10.0,
            rate_per_min: 20.0,
            breaths: 2,
            ..Default::default()
        }
        .recording();
        for r in analyse(&pc, &quick()) {
            assert_eq!(
                r.class,
                BreathClass::PassivePressureControlled,
                "{}",
                r.reason
            );
            match &r.pv {
                PvOutcome::NotApplicable(why) => assert!(why.contains("flat pressure"), "{why}"),
                PvOutcome::Fitted(_) => panic!("a pressure-controlled breath was fitted"),
            }
        }
        // Patient effort: a trigger dip of 3 cmH2O at the start of the second breath.
        let mut effort = vc.clone();
        let at = effort.vent_breaths[1].0;
        for j in at - 4..at + 2 {
            effort.paw_cmh2o[j] -= 3.0;
        }
        let reports = analyse(&effort, &quick());
        assert_eq!(reports[0].class, BreathClass::PassiveVolumeControlled);
        assert_eq!(reports[1].class, BreathClass::PatientEffort);
        assert!(
            reports[1].reason.contains("below PEEP"),
            "{}",
            reports[1].reason
        );
        // A leak: expiratory flow scaled to half.
        let mut leak = vc.clone();
        leak.flow_lps
            .iter_mut()
            .filter(|f| **f < 0.0)
            .for_each(|f| *f *= 0.5);
        let reports = analyse(&leak, &quick());
        assert!(reports.iter().all(|r| r.class == BreathClass::Artefact));
        assert!(
            reports[0].reason.contains("inspired"),
            "{}",
            reports[0].reason
        );
    }

    #[test]
    fn degenerate_samples_give_no_equation_of_motion() {
        assert!(fit_equation_of_motion(&[0.0; 10], &[0.0; 10], &[5.0; 10]).is_none());
        assert!(fit_equation_of_motion(&[1.0, 2.0], &[0.1, 0.2], &[5.0, 6.0]).is_none());
        let v = [0.0, 100.0, 200.0, 300.0, 200.0, 100.0];
        let f = [0.5, 0.5, 0.5, -0.5, -0.5, -0.5];
        let p: Vec<f64> = v
            .iter()
            .zip(&f)
            .map(|(v, f)| 5.0 + v / 50.0 + 10.0 * f)
            .collect();
        let e = fit_equation_of_motion(&v, &f, &p).unwrap();
        assert!((e.compliance_ml_per_cmh2o - 50.0).abs() < 1e-6);
        assert!((e.resistance_cmh2o_s_per_l - 10.0).abs() < 1e-6);
        assert!(e.residual_percent < 1e-9);
    }
}
