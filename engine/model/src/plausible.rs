//! Physical plausibility of every input: the ranges a lung can have, and what it means to be outside.
//!
//! A wrong unit is the most common way a bad input becomes a silent wrong answer: a mesh in metres
//! read as millimetres is a lung of 0.25 mm; a kPa column read as cmH2O is a loop a tenth as wide;
//! millilitres declared as litres make an FRC of 2,400,000 ml. Every command checks what it reads
//! against the [`Limit`]s here — generous enough for a neonate and for a tall adult at total lung
//! capacity (and for the sheep of the seed's Table 5.1, whose lungs are of human size) — and a value
//! outside one is refused with the likely cause and the flag that fixes it.
//!
//! Sources of the ranges (each [`Limit`] names its own):
//! * [ATS/ERS-2005] Wanger J et al., "Standardisation of the measurement of lung volumes", Eur Respir J
//!   2005;26:511–522 — FRC, TLC, tidal volume definitions.
//! * [Quanjer-1993] Quanjer PH et al., "Lung volumes and forced ventilatory flows", Eur Respir J
//!   1993;6 Suppl 16:5–40 — adult reference values (TLC up to ≈ 9 L in tall men, FRC ≈ 2–4.5 L).
//! * [Stocks-1995] Stocks J, Quanjer PH, "Reference values for residual volume, functional residual
//!   capacity and total lung capacity", Eur Respir J 1995;8:492–506 — infants: FRC ≈ 25–30 ml/kg.
//! * [ATS/ERS-2002] ATS/ERS Statement on respiratory muscle testing, Am J Respir Crit Care Med
//!   2002;166:518–624 — maximal inspiratory/expiratory mouth pressures ≈ −150…+250 cmH2O.
//! * [ARDSNet-2000] The ARDS Network, "Ventilation with lower tidal volumes ...", N Engl J Med
//!   2000;342:1301–1308 — plateau pressure ≤ 30 cmH2O; [ARDSNet-2004] Brower RG et al., "Higher versus
//!   lower positive end-expiratory pressures ...", N Engl J Med 2004;351:327–336 — PEEP up to 24 cmH2O.
//! * [Bates-2009] Bates JHT, *Lung Mechanics*, Cambridge 2009, ch. 2 — compliance of the lungs and the
//!   respiratory system, adult and neonate.
//! * [Gray-2016] Standring S (ed.), Gray's Anatomy, 41st ed., 2016, ch. 54 (pleura, lungs) — adult lung
//!   height ≈ 20–30 cm; the default lungs of `mesh::generate` are 230/240 mm.

use thiserror::Error;

/// A documented range of one physical quantity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limit {
    /// What the value is ("one lung's volume").
    pub what: &'static str,
    /// Smallest plausible value.
    pub lo: f64,
    /// Largest plausible value.
    pub hi: f64,
    /// Unit of `lo` and `hi`.
    pub unit: &'static str,
    /// Where the range comes from.
    pub source: &'static str,
}

impl Limit {
    /// Whether `v` is finite and inside the range.
    pub fn contains(&self, v: f64) -> bool {
        v.is_finite() && self.lo <= v && v <= self.hi
    }

    /// `Ok` when `v` is plausible, else an error carrying `hint` (the likely cause and the fix).
    pub fn check(&self, v: f64, hint: Option<String>) -> Result<(), Implausible> {
        if self.contains(v) {
            Ok(())
        } else {
            Err(Implausible {
                limit: *self,
                value: v,
                hint,
            })
        }
    }
}

/// Volume of one lung (mesh, kernel): a neonate's lung at FRC to an adult's at TLC.
pub const LUNG_VOLUME_ML: Limit = Limit {
    what: "one lung's volume",
    lo: 20.0,
    hi: 6000.0,
    unit: "ml",
    source:
        "neonate FRC ≈ 25–30 ml/kg [Stocks-1995] to adult TLC ≤ 9 L for both lungs [Quanjer-1993]",
};
/// Both lungs' volume (a PV curve's volumes, FRC + tidal volume).
pub const LUNGS_VOLUME_ML: Limit = Limit {
    what: "lung volume",
    lo: 40.0,
    hi: 10_000.0,
    unit: "ml",
    source: "neonate FRC [Stocks-1995] to adult TLC ≈ 9 L [Quanjer-1993]",
};
/// Functional residual capacity of both lungs.
pub const FRC_ML: Limit = Limit {
    what: "FRC",
    lo: 40.0,
    hi: 8000.0,
    unit: "ml",
    source: "neonate ≈ 80 ml [Stocks-1995] to large adult ≈ 6 L [Quanjer-1993]",
};
/// Tidal volume (one breath's volume change), from a neonate to an exercising adult.
pub const TIDAL_VOLUME_ML: Limit = Limit {
    what: "tidal volume",
    lo: 5.0,
    hi: 5000.0,
    unit: "ml",
    source: "neonate ≈ 15–25 ml to vital capacity ≈ 5 L [ATS/ERS-2005, Quanjer-1993]",
};
/// Any airway, oesophageal or transpulmonary pressure of a PV curve.
pub const PRESSURE_CMH2O: Limit = Limit {
    what: "pressure",
    lo: -200.0,
    hi: 250.0,
    unit: "cmH2O",
    source: "maximal inspiratory/expiratory pressures [ATS/ERS-2002]",
};
/// The pressure range a PV loop spans (end-inspiratory minus end-expiratory).
pub const PRESSURE_SWING_CMH2O: Limit = Limit {
    what: "pressure range of the loop",
    lo: 0.5,
    hi: 200.0,
    unit: "cmH2O",
    source: "quiet tidal transpulmonary swing ≈ 5 cmH2O to maximal efforts [ATS/ERS-2002]",
};
/// The largest side of one lung's bounding box.
pub const LUNG_EXTENT_MM: Limit = Limit {
    what: "lung size (largest side of its bounding box)",
    lo: 30.0,
    hi: 450.0,
    unit: "mm",
    source: "neonate ≈ 40 mm to adult ≈ 300 mm at TLC [Gray-2016]",
};
/// The spread (largest side of the bounding box) of a set of lung landmarks.
pub const LANDMARK_SPREAD_MM: Limit = Limit {
    what: "spread of the landmarks (largest side of their bounding box)",
    lo: 10.0,
    hi: 600.0,
    unit: "mm",
    source: "both adult lungs span ≈ 300 mm [Gray-2016]",
};
/// How far one landmark moves between two breathing phases.
pub const LANDMARK_MOTION_MM: Limit = Limit {
    what: "landmark displacement between phases",
    lo: 0.0,
    hi: 120.0,
    unit: "mm",
    source: "diaphragm excursion ≤ 100 mm at vital capacity breathing [Gray-2016]",
};
/// Airflow at the airway opening (a ventilator's flow sensor), + inspiration.
pub const FLOW_LPS: Limit = Limit {
    what: "airflow",
    lo: -15.0,
    hi: 15.0,
    unit: "L/s",
    source: "adult peak expiratory flow ≤ ≈ 12 L/s [Quanjer-1993]; ventilator peak flows ≤ ≈ 3 L/s",
};
/// Breathing rate.
pub const BREATHS_PER_MIN: Limit = Limit {
    what: "breathing rate",
    lo: 2.0,
    hi: 150.0,
    unit: "breaths/min",
    source: "slow deep breathing ≈ 4/min to neonatal tachypnoea ≈ 100/min",
};

/// End-expiratory airway pressure of a recording (the median over its whole breaths).
pub const PEEP_CMH2O: Limit = Limit {
    what: "end-expiratory pressure (PEEP)",
    lo: -2.0,
    hi: 30.0,
    unit: "cmH2O",
    source:
        "0 breathing room air (−2 for a sensor's offset) to the ARDS Network's highest PEEP, 24 \
             cmH2O [ARDSNet-2004]",
};
/// Peak airway pressure of a recording (the median over its whole breaths: one cough is not a
/// recording's PIP).
pub const PIP_CMH2O: Limit = Limit {
    what: "peak inspiratory pressure (PIP)",
    lo: -2.0,
    hi: 80.0,
    unit: "cmH2O",
    source:
        "≈ 0 breathing room air to a ventilator's high-pressure limit (PB-840: settable to 100 \
             cmH2O; lung-protective plateaus ≤ 30 [ARDSNet-2000])",
};
/// Compliance of the respiratory system from the equation of motion of passive breaths.
pub const COMPLIANCE_ML_PER_CMH2O: Limit = Limit {
    what: "compliance",
    lo: 0.5,
    hi: 250.0,
    unit: "ml/cmH2O",
    source:
        "a preterm neonate ≈ 0.5–1 to a healthy adult's lungs ≈ 200 (respiratory system ≈ 100) \
             [Bates-2009]",
};

/// A value outside its documented range (a non-finite one is said to be no number at all, never
/// printed as a quantity like "NaN ml").
#[derive(Debug, Clone, PartialEq, Error)]
#[error("{}{} {}–{} {} ({}){}", .limit.what, value_text(.limit, *.value), .limit.lo, .limit.hi, .limit.unit, .limit.source, hint_text(.hint))]
pub struct Implausible {
    /// The range violated.
    pub limit: Limit,
    /// The value found.
    pub value: f64,
    /// The likely cause and the flag that fixes it.
    pub hint: Option<String>,
}

/// `v` for a message: up to three decimals within 1e-3..1e7, else in exponent form (`1e308`, not
/// 309 digits).
pub fn compact(v: f64) -> String {
    fmt(v)
}

fn fmt(v: f64) -> String {
    // One rule for every message, the scene tables' checks included.
    lungdyn_scene::compact(v)
}

fn value_text(limit: &Limit, v: f64) -> String {
    if v.is_finite() {
        format!(
            " = {} {} is outside the plausible range",
            fmt(v),
            limit.unit
        )
    } else {
        format!(" is {v}, not a finite number: the plausible range is")
    }
}

fn hint_text(h: &Option<String>) -> String {
    h.as_ref().map(|h| format!(": {h}")).unwrap_or_default()
}

/// The likely unit mistake behind a lung whose largest side is `extent` in the unit `given`
/// ("mm", "cm" or "m"), as a hint naming the flag.
pub fn length_unit_hint(extent_in_given: f64, given: &str) -> Option<String> {
    let mm_per = match given {
        "m" => 1000.0,
        "cm" => 10.0,
        _ => 1.0,
    };
    let raw = extent_in_given / mm_per; // the number as written in the file
    let candidates = [("m", 1000.0), ("cm", 10.0), ("mm", 1.0)];
    candidates
        .iter()
        .filter(|(u, _)| *u != given)
        .find(|(_, f)| LUNG_EXTENT_MM.contains(raw * f))
        .map(|(u, f)| {
            format!(
                "read as {given} it is {} mm; read as {u} it would be {} mm: the file looks like {u} — pass --units {u}",
                fmt(extent_in_given),
                fmt(raw * f)
            )
        })
}

/// The likely unit mistake behind lung volumes `v_ml` read as `given` ("ml" or "l").
pub fn volume_unit_hint(v_ml: f64, given: &str) -> Option<String> {
    match given {
        "l" if LUNGS_VOLUME_ML.contains(v_ml / 1000.0) => Some(
            "read as litres the volumes are far too large; as millilitres they are plausible: drop \
             --volume-unit l (or name the column volume_ml)"
                .into(),
        ),
        "ml" if LUNGS_VOLUME_ML.contains(v_ml * 1000.0) => Some(
            "read as millilitres the volumes are far too small; as litres they are plausible: pass \
             --volume-unit l (or name the column volume_L)"
                .into(),
        ),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lung_in_metres_read_as_millimetres_names_the_flag() {
        // A 250 mm lung written in metres: 0.25.
        let h = length_unit_hint(0.25, "mm").unwrap();
        assert!(h.contains("--units m"), "{h}");
        let h = length_unit_hint(25.0, "mm").unwrap();
        assert!(h.contains("--units cm"), "{h}");
        // Millimetres read as metres: 250 m.
        let h = length_unit_hint(250_000.0, "m").unwrap();
        assert!(h.contains("--units mm"), "{h}");
        assert_eq!(
            length_unit_hint(1e38, "mm"),
            None,
            "no unit makes it plausible"
        );
        assert!(LUNG_EXTENT_MM.contains(230.0));
    }

    #[test]
    fn millilitres_declared_as_litres_are_caught_both_ways() {
        assert!(volume_unit_hint(2_400_000.0, "l")
            .unwrap()
            .contains("drop --volume-unit l"));
        assert!(volume_unit_hint(2.4, "ml")
            .unwrap()
            .contains("--volume-unit l"));
        assert_eq!(volume_unit_hint(2400.0, "ml"), None);
    }

    #[test]
    fn the_message_names_value_range_source_and_fix() {
        let e = FRC_ML
            .check(-200.0, Some("pass --frc".into()))
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("FRC = -200 ml is outside the plausible range 40–8000 ml"),
            "{e}"
        );
        assert!(e.contains("Quanjer") && e.ends_with(": pass --frc"), "{e}");
        let e = TIDAL_VOLUME_ML.check(f64::INFINITY, None).unwrap_err();
        assert!(e.to_string().contains("inf"), "{e}");
        // Never a non-finite quantity ("inf ml", "NaN ml"): the value is no number of ml at all.
        for v in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let e = FRC_ML.check(v, None).unwrap_err().to_string();
            assert!(
                !e.contains(" ml is") && !e.contains("NaN ml") && !e.contains("inf ml"),
                "{e}"
            );
            assert!(
                e.starts_with("FRC is ") && e.contains("not a finite number"),
                "{e}"
            );
        }
        assert_eq!(compact(-1e308), "-1e308");
        assert_eq!(compact(0.0), "0");
        assert!(TIDAL_VOLUME_ML.check(f64::NAN, None).is_err());
        assert!(FRC_ML.check(2400.0, None).is_ok());
    }
}
