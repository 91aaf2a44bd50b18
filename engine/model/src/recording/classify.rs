//! What each breath of a ventilator recording is: the equation of motion of a passive lung fitted by
//! least squares, and a class with its reason (EQUATIONS §1.4). `lungdyn pv recording` adds the PV
//! model's fit (`lung_bake::pv::recording`); a `[pv] waveform` scene takes the ventilator's control
//! mode from the classes of its recording's breaths ([`ControlSummary`], EQUATIONS §4.7).
//!
//! The equation of motion of the respiratory system (Bates, *Respiratory Function of the Lung and
//! Chest Wall*, 2009, ch. 2; Iotti & Braschi, *Measurements of Respiratory Mechanics During
//! Mechanical Ventilation*, 1999):
//!
//! ```text
//!     Paw(t) = V(t)/C + R·flow(t) + P0
//! ```
//!
//! holds for a passive lung (no muscle pressure). Its least-squares fit over one breath gives the
//! compliance `C`, the resistance `R` and `P0` (≈ total PEEP); what it leaves unexplained, as a
//! fraction of the breath's pressure swing, measures how far the breath is from passive.
//!
//! Classes (EQUATIONS §1.4):
//! * **artefact**: the recording cuts the breath, its volume does not close (expired and inspired
//!   volumes differ by more than [`super::MAX_IMBALANCE`]), or its tidal volume or rate is implausible;
//! * **patient effort**: airway pressure falls more than [`EFFORT_DIP_CMH2O`] below PEEP (a trigger,
//!   looked for from [`TRIGGER_LEAD_S`] before the breath's flow starts), expiratory flow still runs
//!   when the next breath starts (triggered before the lung emptied),
//!   the oesophageal pressure falls during inspiration, the fitted `C` or `R` is not positive, or the
//!   equation of motion leaves more than [`MAX_PASSIVE_RESIDUAL`] of the swing unexplained;
//! * **passive, pressure-controlled**: airway pressure held within [`PLATEAU_FRACTION`] of the swing
//!   over the last 70 % of inspiration while volume still rises (≥ 5 % of the tidal volume): the PV
//!   model's pressure-driven limb (pressure rising linearly with phase time, §1.1) cannot represent a
//!   flat pressure;
//! * **passive, volume-controlled**: the rest: the ventilator sets the flow and pressure rises with
//!   volume.

use nalgebra::{DMatrix, DVector};

use super::{
    breath_volume, segment, timing, whole_breath, BreathSpan, BreathTiming, Recording,
    SegmentOptions,
};
use crate::plausible::compact;

/// Airway pressure this far below PEEP, cmH2O, is the patient pulling (a trigger effort).
pub const EFFORT_DIP_CMH2O: f64 = 1.0;
/// How long before a breath's flow starts its trigger's pressure dip is looked for, s.
pub const TRIGGER_LEAD_S: f64 = 0.2;
/// Oesophageal pressure falling this far during inspiration, cmH2O, is inspiratory muscle effort
/// (a passive inflation raises it).
pub const EFFORT_PES_DROP_CMH2O: f64 = 1.0;
/// The residual of the equation of motion (RMS, fraction of the pressure swing) above which a breath
/// is not passive.
pub const MAX_PASSIVE_RESIDUAL: f64 = 0.05;
/// Pressure range over the last 70 % of inspiration, as a fraction of the swing, below which the
/// ventilator held the pressure (pressure control).
pub const PLATEAU_FRACTION: f64 = 0.15;

/// What a breath is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BreathClass {
    /// Passive, the ventilator sets the flow.
    PassiveVolumeControlled,
    /// Passive, the ventilator holds the pressure.
    PassivePressureControlled,
    /// The patient breathes (muscle pressure).
    PatientEffort,
    /// Not a whole, clean breath.
    Artefact,
}

impl BreathClass {
    /// Short name for tables.
    pub fn short(self) -> &'static str {
        match self {
            BreathClass::PassiveVolumeControlled => "passive VC",
            BreathClass::PassivePressureControlled => "passive PC",
            BreathClass::PatientEffort => "effort",
            BreathClass::Artefact => "artefact",
        }
    }
}

/// The least-squares fit of `Paw = V/C + R·flow + P0` over one breath.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct EquationOfMotion {
    /// Compliance, ml/cmH2O.
    pub compliance_ml_per_cmh2o: f64,
    /// Resistance, cmH2O·s/L.
    pub resistance_cmh2o_s_per_l: f64,
    /// Pressure at zero volume and flow, cmH2O (≈ total PEEP).
    pub p0_cmh2o: f64,
    /// RMS residual, cmH2O.
    pub residual_rms_cmh2o: f64,
    /// RMS residual as a percentage of the breath's pressure swing (PIP − lowest pressure).
    pub residual_percent: f64,
}

/// Fit the equation of motion to samples of volume (ml), flow (L/s) and airway pressure (cmH2O).
/// `None` when the samples cannot determine it (fewer than 4, or no volume or flow change).
pub fn fit_equation_of_motion(
    v_ml: &[f64],
    flow_lps: &[f64],
    p: &[f64],
) -> Option<EquationOfMotion> {
    let n = v_ml.len();
    if n < 4 || flow_lps.len() != n || p.len() != n {
        return None;
    }
    // Columns scaled to order 1 (V in L) so the SVD's tolerance is meaningful.
    let a = DMatrix::from_fn(n, 3, |i, j| match j {
        0 => v_ml[i] / 1000.0,
        1 => flow_lps[i],
        _ => 1.0,
    });
    let b = DVector::from_column_slice(p);
    let svd = a.clone().svd(true, true);
    let s = &svd.singular_values;
    let (hi, lo) = (s.max(), s.min());
    if !(lo > 1e-9 * hi) {
        return None;
    }
    let x = svd.solve(&b, 1e-12 * hi).ok()?;
    let r = &a * &x - &b;
    let rms = (r.norm_squared() / n as f64).sqrt();
    let (p_lo, p_hi) = p
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let swing = p_hi - p_lo;
    let eom = EquationOfMotion {
        compliance_ml_per_cmh2o: 1000.0 / x[0],
        resistance_cmh2o_s_per_l: x[1],
        p0_cmh2o: x[2],
        residual_rms_cmh2o: rms,
        residual_percent: if swing > 0.0 {
            100.0 * rms / swing
        } else {
            f64::INFINITY
        },
    };
    [
        eom.compliance_ml_per_cmh2o,
        eom.resistance_cmh2o_s_per_l,
        eom.p0_cmh2o,
        eom.residual_rms_cmh2o,
    ]
    .iter()
    .all(|v| v.is_finite())
    .then_some(eom)
}

/// One breath, characterised: timing, pressures, equation of motion, class (without the PV model's
/// fit, which `lung_bake::pv::recording` adds to passive volume-controlled breaths).
#[derive(Debug, Clone)]
pub struct BreathCharacter {
    /// 1-based index in the recording.
    pub index: usize,
    /// The ventilator's breath number (PB-840 `S:<n>` of the `BS` the breath starts in).
    pub vent_breath: Option<u64>,
    /// Samples.
    pub span: BreathSpan,
    /// Timing and volumes.
    pub timing: BreathTiming,
    /// Drift-corrected volume above the start, ml, per sample of the span.
    pub volume_ml: Vec<f64>,
    /// Peak inspiratory pressure, cmH2O.
    pub pip_cmh2o: f64,
    /// End-expiratory pressure (mean of the 0.1 s before the next breath), cmH2O.
    pub peep_cmh2o: f64,
    /// The equation of motion, where it could be fitted.
    pub eom: Option<EquationOfMotion>,
    /// Class.
    pub class: BreathClass,
    /// Why this class.
    pub reason: String,
    /// A whole breath whose ventilator held the pressure over the last 70 % of inspiration while
    /// the volume rose (pressure control), whether passive or with patient effort; false for
    /// artefacts and breaths whose pressure rises with volume (volume control).
    pub pressure_held: bool,
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// One breath: timing, pressures, equation of motion, class. `threshold_lps`: the segmentation's
/// flow threshold ([`SegmentOptions::threshold_lps`]).
pub fn characterise_breath(
    rec: &Recording,
    index: usize,
    span: &BreathSpan,
    threshold_lps: f64,
) -> BreathCharacter {
    let (volume, net) = breath_volume(rec, span);
    let tm = timing(rec, span, &volume, net);
    let range = span.start..=span.end;
    let paw = &rec.paw_cmh2o[range.clone()];
    let flow = &rec.flow_lps[range];
    let n = paw.len();
    let dt = if n > 1 {
        tm.duration_s / (n - 1) as f64
    } else {
        1.0
    };
    // The last sample is the next breath's first: PEEP is read over the 0.1 s before it.
    let tail = ((0.1 / dt).round() as usize).clamp(1, n.saturating_sub(1).max(1));
    let pip = paw.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let peep = mean(&paw[n.saturating_sub(1 + tail)..n.saturating_sub(1).max(1)]);
    let vent_breath = rec
        .vent_breaths
        .iter()
        .take_while(|(at, _)| *at <= span.start)
        .last()
        .map(|b| b.1);
    let eom = fit_equation_of_motion(&volume, flow, paw);
    let (class, reason, pressure_held) = classify(
        rec,
        span,
        &tm,
        &volume,
        paw,
        pip,
        peep,
        eom.as_ref(),
        threshold_lps,
    );
    BreathCharacter {
        index,
        vent_breath,
        span: *span,
        timing: tm,
        volume_ml: volume,
        pip_cmh2o: pip,
        peep_cmh2o: peep,
        eom,
        class,
        reason,
        pressure_held,
    }
}

/// Every breath of a recording, characterised (in order).
pub fn characterise_all(rec: &Recording, opts: &SegmentOptions) -> Vec<BreathCharacter> {
    segment(rec, opts)
        .iter()
        .enumerate()
        .map(|(k, span)| characterise_breath(rec, k + 1, span, opts.threshold_lps))
        .collect()
}

/// How a ventilator drove the breaths of a recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlMode {
    /// The ventilator sets the flow (and so the volume); the airway pressure follows the lungs.
    Volume,
    /// The ventilator holds the airway pressure; the volume follows the lungs.
    Pressure,
}

impl ControlMode {
    /// Name as the scene and the reports write it.
    pub fn name(self) -> &'static str {
        match self {
            ControlMode::Volume => "volume",
            ControlMode::Pressure => "pressure",
        }
    }
}

/// The classes of a recording's breaths and the control mode they show: pressure control when the
/// whole breaths (not artefacts) that hold their pressure while the volume rises are the majority,
/// volume control otherwise (a tie included: the reading of EQUATIONS §4.7 before this summary).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct ControlSummary {
    /// Whole breaths whose pressure is held while the volume rises (passive or effort).
    pub pressure_held: usize,
    /// Whole breaths whose pressure rises with the volume.
    pub pressure_rising: usize,
    /// Passive volume-controlled breaths.
    pub passive_volume_controlled: usize,
    /// Passive pressure-controlled breaths.
    pub passive_pressure_controlled: usize,
    /// Breaths with patient effort.
    pub patient_effort: usize,
    /// Artefacts (not counted in the majority).
    pub artefacts: usize,
}

impl ControlSummary {
    /// Count `breaths`.
    pub fn of(breaths: &[BreathCharacter]) -> Self {
        let mut s = Self::default();
        for b in breaths {
            match b.class {
                BreathClass::Artefact => s.artefacts += 1,
                BreathClass::PassiveVolumeControlled => s.passive_volume_controlled += 1,
                BreathClass::PassivePressureControlled => s.passive_pressure_controlled += 1,
                BreathClass::PatientEffort => s.patient_effort += 1,
            }
            if b.class != BreathClass::Artefact {
                if b.pressure_held {
                    s.pressure_held += 1;
                } else {
                    s.pressure_rising += 1;
                }
            }
        }
        s
    }

    /// The majority's control mode.
    pub fn mode(&self) -> ControlMode {
        if self.pressure_held > self.pressure_rising {
            ControlMode::Pressure
        } else {
            ControlMode::Volume
        }
    }

    /// One line: the mode and the counts it comes from.
    pub fn describe(&self) -> String {
        let whole = self.pressure_held + self.pressure_rising;
        let (n, what) = match self.mode() {
            ControlMode::Pressure => (
                self.pressure_held,
                "hold their pressure while the volume rises",
            ),
            ControlMode::Volume => (self.pressure_rising, "raise their pressure with the volume"),
        };
        format!(
            "{} control: {n} of {whole} whole breaths {what} ({} passive VC, {} passive PC, {} with \
             patient effort; {} artefacts not counted)",
            self.mode().name(),
            self.passive_volume_controlled,
            self.passive_pressure_controlled,
            self.patient_effort,
            self.artefacts
        )
    }
}

#[allow(clippy::too_many_arguments)]
fn classify(
    rec: &Recording,
    span: &BreathSpan,
    tm: &BreathTiming,
    volume: &[f64],
    paw: &[f64],
    pip: f64,
    peep: f64,
    eom: Option<&EquationOfMotion>,
    threshold_lps: f64,
) -> (BreathClass, String, bool) {
    use BreathClass::*;
    if let Err(why) = whole_breath(span, tm) {
        return (Artefact, why, false);
    }
    let lowest = paw.iter().copied().fold(f64::INFINITY, f64::min);
    // The ventilation mode, from the pressure over the last 70 % of inspiration against the swing
    // and the volume gained there: said in every passive or effort reason.
    let ni = span.expiration - span.start;
    let from = span.start + (3 * ni) / 10;
    let late = &rec.paw_cmh2o[from..span.expiration.max(from + 1)];
    let (lo, hi) = late
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
            (l.min(v), h.max(v))
        });
    let swing = (pip - lowest).max(1e-9);
    let gained = volume[span.expiration - span.start] - volume[from - span.start];
    let pressure_held = hi - lo <= PLATEAU_FRACTION * swing && gained >= 0.05 * tm.tidal_volume_ml;
    let mode = if pressure_held {
        format!(
            "pressure held within {}–{} cmH2O ({} % of the {} cmH2O swing) over the last 70 % of \
             inspiration while volume rose {} ml",
            compact(lo),
            compact(hi),
            compact(100.0 * (hi - lo) / swing),
            compact(swing),
            compact(gained)
        )
    } else {
        format!(
            "pressure rises with volume ({} → {} cmH2O over the last 70 % of inspiration): the \
             ventilator sets the flow",
            compact(late[0]),
            compact(hi)
        )
    };
    let effort = |why: String| (PatientEffort, format!("{why}; {mode}"), pressure_held);
    // A trigger's dip comes just before the flow it starts: the window runs from 0.2 s before this
    // breath's start to 0.2 s before its end (that last part is the next breath's trigger).
    let dt = tm.duration_s / (span.end - span.start).max(1) as f64;
    let lead = ((TRIGGER_LEAD_S / dt).round() as usize).min(span.end - span.start);
    let window = &rec.paw_cmh2o[span.start.saturating_sub(lead)..=span.end - lead];
    let dip = window.iter().copied().fold(f64::INFINITY, f64::min);
    let reference = peep.min(paw[0]);
    if dip < reference - EFFORT_DIP_CMH2O {
        return effort(format!(
            "airway pressure falls to {} cmH2O, {} cmH2O below PEEP: the patient pulls (trigger or \
             sustained effort)",
            compact(dip),
            compact(reference - dip)
        ));
    }
    // Expiratory flow still running when the next breath starts: the patient triggered it before
    // the lung emptied (or breathed out actively); the loop is cut short.
    let last_flow = rec.flow_lps[span.end.saturating_sub(1).max(span.expiration)];
    if span.end + 1 < rec.flow_lps.len() && last_flow < -threshold_lps {
        return effort(format!(
            "expiratory flow is still {} L/min when the next breath starts: the patient triggers \
             it before the lung has emptied (or breathes out actively)",
            compact(last_flow * 60.0)
        ));
    }
    let insp = span.start..=span.expiration;
    if let Some(pes) = &rec.pes_cmh2o {
        let p0 = pes[span.start];
        let low = pes[insp].iter().copied().fold(f64::INFINITY, f64::min);
        if low < p0 - EFFORT_PES_DROP_CMH2O {
            return effort(format!(
                "oesophageal pressure falls {} cmH2O during inspiration (a passive inflation raises \
                 it): inspiratory muscle effort",
                compact(p0 - low)
            ));
        }
    }
    let Some(eom) = eom else {
        return (
            Artefact,
            "the equation of motion cannot be fitted (no volume or flow change)".into(),
            false,
        );
    };
    if !(eom.compliance_ml_per_cmh2o > 0.0 && eom.resistance_cmh2o_s_per_l > 0.0) {
        return effort(format!(
            "the equation of motion fits C = {} ml/cmH2O, R = {} cmH2O·s/L: not a passive lung (a \
             muscle pressure or an artefact drives it)",
            compact(eom.compliance_ml_per_cmh2o),
            compact(eom.resistance_cmh2o_s_per_l)
        ));
    }
    if eom.residual_percent > 100.0 * MAX_PASSIVE_RESIDUAL {
        return effort(format!(
            "the equation of motion of a passive lung leaves {} % of the pressure swing unexplained \
             (more than {} %): a muscle pressure (or an artefact) acts",
            compact(eom.residual_percent),
            100.0 * MAX_PASSIVE_RESIDUAL
        ));
    }
    let class = if pressure_held {
        PassivePressureControlled
    } else {
        PassiveVolumeControlled
    };
    (
        class,
        format!(
            "{mode}; the equation of motion leaves {} %",
            compact(eom.residual_percent)
        ),
        pressure_held,
    )
}
