//! Is the recording what its header says? A unit or sign that is wrong passes every per-sample
//! range (a kPa column read as cmH2O is a gentle breath, a reversed flow a breath run backwards) and
//! makes a silent wrong answer: a compliance of 519 ml/cmH2O, a PEEP of 52. Before a recording drives
//! the lungs (`[pv] waveform`) or is reported (`lungdyn pv recording`), its whole breaths are checked
//! as a whole — medians, so one cough or one cut breath proves nothing:
//!
//! * median PEEP and PIP within [`PEEP_CMH2O`] and [`PIP_CMH2O`], and the passive breaths' median
//!   compliance within [`COMPLIANCE_ML_PER_CMH2O`]; outside, the other pressure units are tried and
//!   the one that makes all three plausible is named;
//! * the flow's sign: most whole breaths with a negative compliance (volume falls as the ventilator
//!   pushes) while the airway pressure swings at least [`DRIVEN_SWING_CMH2O`] is a flow column with
//!   expiration positive (a patient breathing on CPAP swings ≈ 1 cmH2O and is left alone);
//! * a recorded volume column against the integrated flow: each breath's range over its tidal
//!   volume, median within [`VOLUME_RATIO`] (BTPS/ATPD corrections and leaks stay inside).

use super::classify::{BreathCharacter, BreathClass};
use super::{Format, Recording};
use crate::plausible::{compact, COMPLIANCE_ML_PER_CMH2O, PEEP_CMH2O, PIP_CMH2O};
use crate::units::PRESSURE_UNITS;

/// An airway-pressure swing over a breath, cmH2O, that only a ventilator (or a forced manoeuvre)
/// makes: quiet spontaneous breathing on CPAP swings ≈ 1 cmH2O.
pub const DRIVEN_SWING_CMH2O: f64 = 3.0;

/// The range of a recorded volume column's breath over the flow's integrated tidal volume that is
/// still the same quantity (BTPS against ATPD ≈ 10 %, a leak up to the imbalance an artefact allows).
pub const VOLUME_RATIO: std::ops::RangeInclusive<f64> = 0.5..=2.0;

/// The median of `v` (`None` when empty; `v` holds finite values).
fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// What the breaths of a recording say as a whole (whole breaths only: artefacts left out).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordingFigures {
    /// Whole breaths considered.
    pub breaths: usize,
    /// Median PEEP, cmH2O.
    pub peep_cmh2o: f64,
    /// Median PIP, cmH2O.
    pub pip_cmh2o: f64,
    /// Median compliance of the passive breaths, ml/cmH2O (`None`: no passive breath).
    pub compliance_ml_per_cmh2o: Option<f64>,
    /// Whole breaths whose fitted compliance is negative.
    pub negative_compliance: usize,
    /// Median airway-pressure range over a breath (highest − lowest), cmH2O.
    pub swing_cmh2o: f64,
    /// Median of a recorded volume column's range over a breath against its integrated tidal volume
    /// (`None`: no volume column, or no breath with a tidal volume).
    pub volume_ratio: Option<f64>,
}

/// The figures of `breaths` (every breath of `rec`, characterised); `None` when none is whole.
pub fn figures(rec: &Recording, breaths: &[&BreathCharacter]) -> Option<RecordingFigures> {
    let whole: Vec<&BreathCharacter> = breaths
        .iter()
        .copied()
        .filter(|b| b.class != BreathClass::Artefact)
        .collect();
    let finite = |v: f64| v.is_finite().then_some(v);
    let peep = median(whole.iter().filter_map(|b| finite(b.peep_cmh2o)).collect())?;
    let pip = median(whole.iter().filter_map(|b| finite(b.pip_cmh2o)).collect())?;
    let passive = whole.iter().filter(|b| {
        matches!(
            b.class,
            BreathClass::PassiveVolumeControlled | BreathClass::PassivePressureControlled
        )
    });
    let compliance = median(
        passive
            .filter_map(|b| b.eom.map(|e| e.compliance_ml_per_cmh2o))
            .filter_map(finite)
            .collect(),
    );
    let negative_compliance = whole
        .iter()
        .filter(|b| b.eom.is_some_and(|e| e.compliance_ml_per_cmh2o < 0.0))
        .count();
    let range = |v: &[f64]| {
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
                (lo.min(x), hi.max(x))
            });
        hi - lo
    };
    let swing = median(
        whole
            .iter()
            .map(|b| range(&rec.paw_cmh2o[b.span.start..=b.span.end]))
            .filter_map(finite)
            .collect(),
    )?;
    let volume_ratio = rec.volume_ml.as_ref().and_then(|v| {
        median(
            whole
                .iter()
                .filter(|b| b.timing.tidal_volume_ml > 0.0)
                .map(|b| range(&v[b.span.start..=b.span.end]) / b.timing.tidal_volume_ml)
                .filter_map(finite)
                .collect(),
        )
    });
    Some(RecordingFigures {
        breaths: whole.len(),
        peep_cmh2o: peep,
        pip_cmh2o: pip,
        compliance_ml_per_cmh2o: compliance,
        negative_compliance,
        swing_cmh2o: swing,
        volume_ratio,
    })
}

/// `Ok` when the whole breaths of `rec` (`breaths`: every breath, characterised) look like what its
/// header says; else what is wrong, the likely cause and the fix. A recording without a whole
/// breath passes (there is nothing to judge; the readers refuse it for that on their own).
pub fn check_plausible(rec: &Recording, breaths: &[&BreathCharacter]) -> Result<(), String> {
    let Some(f) = figures(rec, breaths) else {
        return Ok(());
    };
    pressures(rec, &f)?;
    flow_sign(&f)?;
    volume_column(rec, &f)
}

/// Whether PEEP, PIP and the compliance are plausible read with the pressure scaled by `k`.
fn plausible_scaled(f: &RecordingFigures, k: f64) -> bool {
    PEEP_CMH2O.contains(f.peep_cmh2o * k)
        && PIP_CMH2O.contains(f.pip_cmh2o * k)
        && f.compliance_ml_per_cmh2o
            .is_none_or(|c| COMPLIANCE_ML_PER_CMH2O.contains(c / k))
}

/// PEEP, PIP and the passive compliance in their ranges; else the pressure unit that would make
/// them plausible, where one does.
fn pressures(rec: &Recording, f: &RecordingFigures) -> Result<(), String> {
    if plausible_scaled(f, 1.0) {
        return Ok(());
    }
    let column = rec.columns.iter().find(|c| c.quantity == "pressure");
    let (name, unit, factor) = column.map_or(("pressure", "cmH2O", 1.0), |c| {
        (c.column.as_str(), c.unit, c.factor)
    });
    let c_text = |k: f64| {
        f.compliance_ml_per_cmh2o
            .map(|c| format!(", compliance {} ml/cmH2O", compact(c / k)))
            .unwrap_or_default()
    };
    let mut out = format!(
        "the airway pressure is not a breath's: over {} whole breaths the median PEEP is {} \
         cmH2O (plausible {}–{}), PIP {} (plausible {}–{}){} (plausible {}–{}), with the pressure \
         column \"{name}\" read in {unit}",
        f.breaths,
        compact(f.peep_cmh2o),
        PEEP_CMH2O.lo,
        PEEP_CMH2O.hi,
        compact(f.pip_cmh2o),
        PIP_CMH2O.lo,
        PIP_CMH2O.hi,
        c_text(1.0),
        COMPLIANCE_ML_PER_CMH2O.lo,
        COMPLIANCE_ML_PER_CMH2O.hi,
    );
    // The unit that would make every figure plausible: the same numbers read with its factor.
    let other = PRESSURE_UNITS
        .iter()
        .filter(|(_, n, _)| *n != unit)
        .find(|(_, _, g)| plausible_scaled(f, g / factor));
    match (rec.format, other) {
        (Format::Pb840, _) => out.push_str(
            ": a PB-840 export is in cmH2O by definition, so this file is not one (or its pressure \
             is not the airway pressure)",
        ),
        (Format::GenericCsv, Some((_, n, g))) => {
            let k = g / factor;
            out.push_str(&format!(
                "; read in {n} it would be PEEP {}, PIP {}{}: is the column in {n}? Name the unit \
                 in its header (e.g. \"paw_{n}\")",
                compact(f.peep_cmh2o * k),
                compact(f.pip_cmh2o * k),
                c_text(k)
            ));
        }
        (Format::GenericCsv, None) => out.push_str(
            "; no other pressure unit makes it plausible either: is the column the airway pressure, \
             and the flow in the unit its header names?",
        ),
    }
    Err(out)
}

/// Most whole breaths with a negative compliance while the ventilator drives the pressure: the
/// flow's sign is reversed.
fn flow_sign(f: &RecordingFigures) -> Result<(), String> {
    if 2 * f.negative_compliance > f.breaths && f.swing_cmh2o >= DRIVEN_SWING_CMH2O {
        return Err(format!(
            "the flow's sign looks reversed: in {} of {} whole breaths the volume falls while the \
             airway pressure rises (a negative compliance), with the pressure swinging {} cmH2O a \
             breath: inspiration must be positive flow — negate the flow column (or name it so)",
            f.negative_compliance,
            f.breaths,
            compact(f.swing_cmh2o)
        ));
    }
    Ok(())
}

/// A recorded volume column that is the integrated flow's volume (within [`VOLUME_RATIO`]).
fn volume_column(rec: &Recording, f: &RecordingFigures) -> Result<(), String> {
    let Some(ratio) = f.volume_ratio else {
        return Ok(());
    };
    if VOLUME_RATIO.contains(&ratio) {
        return Ok(());
    }
    let column = rec
        .columns
        .iter()
        .find(|c| c.quantity == "volume")
        .map_or("volume", |c| c.column.as_str());
    // (ratio × k ≈ 1, how far apart, the likely cause)
    let causes = [
        (1000.0, "1000 times too small", "the volume column in litres where its header says ml (or the flow in ml/s where it says L/s)"),
        (1.0e-3, "1000 times too large", "the volume column in ml where its header says litres (or the flow in L/s where it says ml/s)"),
        (60.0, "60 times too small", "the flow in L/min where its header says L/s"),
        (1.0 / 60.0, "60 times too large", "the flow in L/s where its header says L/min"),
    ];
    let hint = if ratio < 1e-6 {
        "the column does not change over a breath: is it the volume?".to_string()
    } else {
        causes
            .iter()
            .find(|(k, _, _)| (ratio * k).ln().abs() < 2.0f64.ln())
            .map_or(
                "check both columns' units".to_string(),
                |(_, apart, why)| format!("the column is {apart}: {why}?"),
            )
    };
    Err(format!(
        "the volume column \"{column}\" and the integrated flow disagree: a breath spans {} times \
         the flow's tidal volume in it (median over {} whole breaths; plausible {}–{}): {hint}",
        compact(ratio),
        f.breaths,
        VOLUME_RATIO.start(),
        VOLUME_RATIO.end()
    ))
}
