//! # disease: the seed's disease states (chapter 8) as pure, deterministic functions
//!
//! Stage: what a disease changes in a lung's breathing and shape, computed once per scene (closed
//! pneumothorax, tumour) or once per breathing cycle (tension pneumothorax), for the engine to apply
//! to its per-lung breathing state at the lung's next cycle start. No clock, no randomness: the same
//! inputs give bit-identical outputs, and the per-cycle path does not allocate.
//!
//! * [`closed`] — closed pneumothorax, **eq. 8.1–8.7**: volume fraction lost `dV = I^0.33`, the drop
//!   `A`, faster breathing `dT`, both lungs' tidal volumes; with [`resistance`] (**eq. 8.8–8.9**) and
//!   [`collapse`] (the affected lung shrunk towards its hilum, exact volume loss).
//! * [`tension`] — tension pneumothorax, **eq. 8.10–8.13**: per-cycle inflow, accumulation to arrest,
//!   mediastinal shift, and the trainee's interventions (needle decompression, occlusive dressing,
//!   chest tube) as a state machine advanced once per cycle.
//! * [`tumour`] — tumour-influenced lung, **eq. 8.14–8.22**: regional expandability, the kernel-row
//!   change with the φ variants, raised resistance, and the tumour centroid's trajectory.
//! * [`ventilated`] — any of these on a ventilator's recorded breath (`[pv] waveform`): the
//!   ventilator delivers the recorded volume and the lungs share it by compliance (EQUATIONS §4.7).
//!
//! Shared here: the seed's closed-pneumothorax relations used by both pneumothorax states
//! ([`volume_fraction_lost`] eq. 8.1, [`drop_for_index`] eq. 8.2, [`phase_times`] eq. 8.3–8.5), the
//! per-lung inputs ([`LungBaseline`], [`NormalBreathing`]) and output ([`LungState`]), and the error
//! type. Every decision where the seed is silent or inconsistent is written next to the code and in
//! docs/EQUATIONS.md §4 ("Decision (lungdyn)", "Changed (lungdyn)").
//!
//! Frame: body frame, mm, +X patient left, +Y anterior, +Z superior; volumes in ml; times in s.

pub mod closed;
pub mod collapse;
pub mod resistance;
pub mod tension;
pub mod tumour;
pub mod ventilated;

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::disease::CourseModel;

use thiserror::Error;

use crate::mesh::{Side, TriMesh};
use crate::pv::{Boundary, PhaseConstants, PvError, Timing};

/// Exponent of eq. 8.1, `dV = I^0.33` (L3554).
pub const DV_EXPONENT: f64 = 0.33;

/// Shortest phase (inhalation or exhalation) a pneumothorax may shorten a phase to, s.
///
/// **Decision (lungdyn):** eq. 8.4–8.5 read literally give non-positive phases for every `I` above
/// about 0.12 (and 0.16 s at the seed's own demo, `I = 0.1`). A phase is clamped to 0.75 s: with I:E
/// 1:1 that is 40 breaths/min, the upper end of the respiratory rates of adult respiratory distress
/// (30–40/min); a clamp is reported in [`PhaseTimes`]. A phase is never lengthened by the clamp (a
/// scene that already breathes faster keeps its phases) and is at least one engine tick.
pub const MIN_PHASE_S: f64 = 0.75;

/// Largest extra effort α (ml) of eq. 8.7: "between (0-2500 millilitres approximately)" (L3613–3616).
pub const ALPHA_MAX_ML: f64 = 2500.0;

/// Seed demo value of α, ml (L3619–3620).
pub const ALPHA_SEED_ML: f64 = 100.0;

/// Dead space as a fraction of the normal tidal volume (clinical model): the anatomic dead space is
/// about 150 ml of a 500 ml breath, `V_D/V_T ≈ 0.3` (West, *Respiratory Physiology: The Essentials*,
/// ch. 2). A fraction rather than 150 ml so that scenes with small tidal volumes stay defined.
pub const DEAD_SPACE_FRACTION: f64 = 0.3;

/// Fastest rate the clinical model's respiratory centre reaches, breaths/min: the upper end of the
/// rates of adult respiratory distress (30–40/min), as the seed reading's clamp ([`MIN_PHASE_S`]).
pub const CLINICAL_MAX_RATE_PER_MIN: f64 = 40.0;

/// Clinical model, the rate for a new total tidal volume (both lungs) in place of eq. 8.3–8.5.
///
/// **Changed (lungdyn, issue 25):** eq. 8.3–8.5 shorten both phases by `T·dV` and, clamped, make every
/// pneumothorax of the seed's range breathe at 40/min with I:E 1:1 (≈ 20 l/min at the seed's demo).
/// The respiratory centre holds the arterial CO₂, i.e. the alveolar ventilation
/// `V̇_A = f·(V_T − V_D)` (the alveolar ventilation equation; West ch. 2): the new rate is
/// `f' = f·(V_T − V_D)/(V_T' − V_D)` with `V_D = 0.3·V_T` ([`DEAD_SPACE_FRACTION`]), never slower than
/// normal and at most [`CLINICAL_MAX_RATE_PER_MIN`] (capped, reported as a clamp). The scene's I:E is
/// kept (normal spontaneous breathing is about 1:2; a scene sets it with `[pv] ie_ratio`). A
/// pneumothorax patient is tachypnoeic with a near-normal minute ventilation (BTS pleural disease
/// guideline 2023; Leigh-Smith & Harris, Emerg Med J 2005;22:8–16), not at 20 l/min.
/// `tidal_new_ml == tidal_normal_ml` returns the normal phases exactly (`dt_s = 0`).
pub fn clinical_phase_times(
    normal: &Timing,
    tidal_normal_ml: f64,
    tidal_new_ml: f64,
) -> Result<PhaseTimes, DiseaseError> {
    normal.phase_ticks()?;
    let tv = check_range(
        "tidal volume",
        tidal_normal_ml,
        f64::MIN_POSITIVE,
        crate::plausible::LUNG_VOLUME_ML.hi,
        "within (0, 6000] ml",
    )?;
    let tv_new = check_range(
        "tidal volume",
        tidal_new_ml,
        0.0,
        2.0 * crate::plausible::LUNG_VOLUME_ML.hi,
        "within 0..=12000 ml",
    )?;
    let cycle_s = 60.0 / normal.breaths_per_min;
    let share = normal.ie_inhale / (normal.ie_inhale + normal.ie_exhale);
    let inhale_s = cycle_s * share;
    let exhale_s = cycle_s - inhale_s;
    let dead = DEAD_SPACE_FRACTION * tv;
    let max_rate = CLINICAL_MAX_RATE_PER_MIN.max(normal.breaths_per_min);
    let (rate, capped) = if tv_new >= tv {
        (normal.breaths_per_min, false)
    } else {
        let alveolar_new = tv_new - dead;
        let wanted = normal.breaths_per_min * (tv - dead) / alveolar_new;
        if alveolar_new > 0.0 && wanted <= max_rate {
            (wanted, false)
        } else {
            (max_rate, true)
        }
    };
    let new_cycle = 60.0 / rate;
    let (new_inhale_s, new_exhale_s) = (new_cycle * share, new_cycle - new_cycle * share);
    let dt_s = cycle_s - new_cycle;
    Ok(PhaseTimes {
        cycle_s,
        inhale_s,
        exhale_s,
        dt_s,
        new_inhale_s,
        new_exhale_s,
        raw_inhale_s: new_inhale_s,
        raw_exhale_s: new_exhale_s,
        inhale_clamped: capped,
        exhale_clamped: capped,
        min_phase_s: (60.0 / max_rate) * share.min(1.0 - share),
    })
}

/// Why a disease state cannot be computed; each names the parameter at fault by its scene key.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DiseaseError {
    /// A parameter is NaN, infinite or outside its range.
    #[error("{name} = {value} is out of range (must be {range})")]
    OutOfRange {
        /// Scene key of the parameter.
        name: &'static str,
        /// Its value.
        value: f64,
        /// The valid range, in words.
        range: &'static str,
    },
    /// A parameter does not apply to this configuration.
    #[error("{name}: {reason}")]
    NotApplicable {
        /// Scene key.
        name: &'static str,
        /// Why.
        reason: &'static str,
    },
    /// The disease names a lung the scene does not simulate.
    #[error(
        "the disease affects the {side} lung, which the scene does not simulate ([lungs] sides)"
    )]
    MissingLung {
        /// "left" or "right".
        side: &'static str,
    },
    /// A lung's baseline is unusable.
    #[error("the {side} lung's {what} = {value} must be finite and > 0")]
    BadBaseline {
        /// "left" or "right".
        side: &'static str,
        /// Which quantity.
        what: &'static str,
        /// Its value.
        value: f64,
    },
    /// The control constants cannot be changed (eq. 8.8–8.9).
    #[error("eq. 8.8-8.9: {0}")]
    Resistance(#[from] resistance::ResistanceError),
    /// The collapse cannot be computed.
    #[error("collapse: {0}")]
    Collapse(#[from] collapse::CollapseError),
    /// The normal breathing cannot be used.
    #[error("normal breathing: {0}")]
    Pv(#[from] PvError),
    /// The tumour cannot be placed or applied.
    #[error("tumour: {0}")]
    Tumour(#[from] tumour::TumourError),
}

/// `Ok(v)` if `v` is finite and within `[lo, hi]`, else [`DiseaseError::OutOfRange`] (also the
/// bake's check of its tumour constants).
pub fn check_range(
    name: &'static str,
    v: f64,
    lo: f64,
    hi: f64,
    range: &'static str,
) -> Result<f64, DiseaseError> {
    if v.is_finite() && lo <= v && v <= hi {
        Ok(v)
    } else {
        Err(DiseaseError::OutOfRange {
            name,
            value: v,
            range,
        })
    }
}

/// Eq. 8.1: the fraction of the affected lung's volume lost for pneumothorax index `I ∈ [0, 1]`,
/// `dV = I^0.33` (exactly 0 at `I = 0`, 1 at `I = 1`).
pub fn volume_fraction_lost(index: f64) -> Result<f64, DiseaseError> {
    let i = check_range("index", index, 0.0, 1.0, "within 0..=1")?;
    Ok(i.powf(DV_EXPONENT))
}

/// The index whose eq. 8.1 loss is `dv ∈ [0, 1]`: `I = dV^{1/0.33}` (used to give a tension
/// pneumothorax's current collapse the closed pneumothorax's drop, eq. 8.2).
pub fn equivalent_index(dv: f64) -> f64 {
    dv.clamp(0.0, 1.0).powf(1.0 / DV_EXPONENT)
}

/// The drop of eq. 8.2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerticalDrop {
    /// `A = (100·I − 4.2)/(4.7·2)` as the seed writes it, cm (negative for `I < 0.042`).
    pub raw_cm: f64,
    /// The drop applied, mm, `≥ 0`: `10·max(A, 0)`.
    pub drop_mm: f64,
    /// `A < 0` was clamped to 0.
    pub clamped: bool,
}

/// Eq. 8.2, the vertical drop of the affected lung from the apex.
///
/// **Decision (lungdyn), unit:** the seed gives none. `4.2` and `4.7` are the regression of Collins
/// et al. (AJR 1995;165:1127–1130), `%PTX = 4.2 + 4.7·(A + B + C)` with `A, B, C` the interpleural
/// distances on an erect radiograph in **cm** (not Rhea et al. 1982, whose method is a nomogram of
/// the average distance). So `(100·I − 4.2)/4.7` is
/// a length in cm for `I` as a fraction, and `A` (half of it) is in cm. The drop is `10·A` mm along
/// −Z (the seed's upright patient; body frame). `A < 0` (`I < 0.042`, where the regression meets no
/// separation) is clamped to 0 and reported.
pub fn drop_for_index(index: f64) -> VerticalDrop {
    let raw_cm = (index * 100.0 - 4.2) / (4.7 * 2.0);
    if raw_cm > 0.0 {
        VerticalDrop {
            raw_cm,
            drop_mm: 10.0 * raw_cm,
            clamped: false,
        }
    } else {
        VerticalDrop {
            raw_cm,
            drop_mm: 0.0,
            clamped: raw_cm < 0.0,
        }
    }
}

/// The phase times of eq. 8.3–8.5 and what the clamp did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhaseTimes {
    /// `T`, the normal breathing cycle, s (eq. 8.3: "the normal time taken for one breathing cycle").
    pub cycle_s: f64,
    /// Normal inhalation `T_i`, s.
    pub inhale_s: f64,
    /// Normal exhalation `T_e`, s.
    pub exhale_s: f64,
    /// `dT = T·dV`, s.
    pub dt_s: f64,
    /// `T'_i = T_i − dT` after the clamp, s.
    pub new_inhale_s: f64,
    /// `T'_e = T_e − dT` after the clamp, s.
    pub new_exhale_s: f64,
    /// `T_i − dT` as the seed computes it (may be ≤ 0), s.
    pub raw_inhale_s: f64,
    /// `T_e − dT` as the seed computes it, s.
    pub raw_exhale_s: f64,
    /// The inhalation was clamped.
    pub inhale_clamped: bool,
    /// The exhalation was clamped.
    pub exhale_clamped: bool,
    /// The clamp used, s: `min(normal phase, max(MIN_PHASE_S, one tick))`.
    pub min_phase_s: f64,
}

impl PhaseTimes {
    /// The engine timing that plays these phases (`normal`'s tick rate). `dT = 0` returns `normal`
    /// itself, so `I = 0` is normal breathing bit for bit.
    pub fn timing(&self, normal: &Timing) -> Timing {
        if self.dt_s == 0.0 {
            return *normal;
        }
        Timing {
            tick_hz: normal.tick_hz,
            breaths_per_min: 60.0 / (self.new_inhale_s + self.new_exhale_s),
            ie_inhale: self.new_inhale_s,
            ie_exhale: self.new_exhale_s,
        }
    }

    /// Breaths per minute of the new phases.
    pub fn breaths_per_min(&self) -> f64 {
        60.0 / (self.new_inhale_s + self.new_exhale_s)
    }
}

/// Eq. 8.3–8.5 for the volume fraction `dv` and the scene's normal timing.
///
/// **Decision (lungdyn):** `T` is the normal *cycle* (60/bpm; the seed's "12 breathing cycles per
/// minute" gives T = 5 s, L3547), `T_i`, `T_e` its I:E split; `dT` is subtracted from each phase as
/// written, then each is clamped to `min(normal phase, max(MIN_PHASE_S, 1 tick))`.
pub fn phase_times(normal: &Timing, dv: f64) -> Result<PhaseTimes, DiseaseError> {
    let dv = check_range("dV", dv, 0.0, 1.0, "within 0..=1")?;
    normal.phase_ticks()?;
    let cycle_s = 60.0 / normal.breaths_per_min;
    let share = normal.ie_inhale / (normal.ie_inhale + normal.ie_exhale);
    let inhale_s = cycle_s * share;
    let exhale_s = cycle_s - inhale_s;
    let dt_s = cycle_s * dv;
    let tick = 1.0 / normal.tick_hz;
    let clamp = |normal_phase: f64, raw: f64| {
        let min = normal_phase.min(MIN_PHASE_S.max(tick));
        if raw < min {
            (min, true)
        } else {
            (raw, false)
        }
    };
    let (raw_inhale_s, raw_exhale_s) = (inhale_s - dt_s, exhale_s - dt_s);
    let (new_inhale_s, inhale_clamped) = clamp(inhale_s, raw_inhale_s);
    let (new_exhale_s, exhale_clamped) = clamp(exhale_s, raw_exhale_s);
    Ok(PhaseTimes {
        cycle_s,
        inhale_s,
        exhale_s,
        dt_s,
        new_inhale_s,
        new_exhale_s,
        raw_inhale_s,
        raw_exhale_s,
        inhale_clamped,
        exhale_clamped,
        min_phase_s: inhale_s.min(exhale_s).min(MIN_PHASE_S.max(tick)),
    })
}

/// The scene's normal breathing, which every disease state changes.
#[derive(Debug, Clone, PartialEq)]
pub struct NormalBreathing {
    /// Inhalation constants.
    pub inhale: PhaseConstants,
    /// Exhalation constants.
    pub exhale: PhaseConstants,
    /// Boundary values (FRC, TV of both lungs together).
    pub boundary: Boundary,
    /// Timing.
    pub timing: Timing,
}

/// What a disease state needs of one lung: its volume, its share of the PV volume change, its box
/// (eq. 8.11–8.13) and its hilum (the collapse).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungBaseline {
    /// Which lung.
    pub side: Side,
    /// Enclosed volume at FRC, ml (the engine's `start_volume_ml`).
    pub start_volume_ml: f64,
    /// Share of the PV volume change above FRC (the engine's `share`, FRC-volume proportional).
    pub share: f64,
    /// Bounding box size `(bX, bY, bZ)`, mm.
    pub box_mm: [f64; 3],
    /// Hilum ([`collapse::hilum`]), mm.
    pub hilum_mm: [f64; 3],
    /// Lowest Z of the lung (its base), mm.
    pub base_z_mm: f64,
}

impl LungBaseline {
    /// The baseline of `mesh` (a lung of `side`) taking `share` of the PV volume change.
    pub fn of(mesh: &TriMesh, side: Side, share: f64) -> Result<Self, DiseaseError> {
        let hilum = collapse::hilum(mesh, side)?;
        let bb = mesh.aabb();
        let size = bb.size().map(|v| v as f64);
        let b = Self {
            side,
            start_volume_ml: mesh.enclosed_volume_ml(),
            share,
            box_mm: size,
            hilum_mm: hilum.position_mm,
            base_z_mm: bb.min[2] as f64,
        };
        b.validate()?;
        Ok(b)
    }

    /// Check every quantity is finite and positive.
    pub fn validate(&self) -> Result<(), DiseaseError> {
        let side = self.side.name();
        for (what, value) in [
            ("volume (ml)", self.start_volume_ml),
            ("share", self.share),
            ("box X (mm)", self.box_mm[0]),
            ("box Y (mm)", self.box_mm[1]),
            ("box Z (mm)", self.box_mm[2]),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(DiseaseError::BadBaseline { side, what, value });
            }
        }
        if !(self.hilum_mm.iter().all(|v| v.is_finite()) && self.base_z_mm.is_finite()) {
            return Err(DiseaseError::BadBaseline {
                side,
                what: "hilum/base position",
                value: f64::NAN,
            });
        }
        Ok(())
    }

    /// Fill fraction of eq. 8.11, `q = V/(bX·bY·bZ)` (unchanged by the collapse: a similarity scales
    /// the volume by `k³` and the box by `k`).
    pub fn fill_fraction(&self) -> f64 {
        self.start_volume_ml * 1000.0 / (self.box_mm[0] * self.box_mm[1] * self.box_mm[2])
    }
}

/// One lung's state for a breathing cycle, as the engine applies it to its `LungBreath`.
///
/// Drawn positions: `h + (1 − collapse)·(p − h) + s·u + offset_mm` (`h` the hilum, `u` the kernel's
/// unit displacement); the volume cubic in `s` is [`collapse::collapsed_cubic`] of the kernel's.
/// Volume: `base_volume_ml + tidal_ml·v(t)` with `v(t) ∈ [0, 1]` the normalised PV curve; a held lung
/// stays at `held_ml`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungState {
    /// Which lung.
    pub side: Side,
    /// Collapse towards the hilum, `c ∈ [0, 1]` (0: none).
    pub collapse: f64,
    /// Volume at the start of an inhalation (after the collapse or hyper-expansion), ml.
    pub base_volume_ml: f64,
    /// Tidal volume of this lung, ml (0 when held).
    pub tidal_ml: f64,
    /// `Some(v)`: the lung does not breathe and is drawn at `v` ml.
    pub held_ml: Option<f64>,
    /// Rigid offset (drop, mediastinal shift), body frame, mm.
    pub offset_mm: [f64; 3],
    /// Volume fraction `dV` that eq. 8.8–8.9 use for this lung (0: normal constants).
    pub resistance_dv: f64,
}

impl LungState {
    /// The unchanged state of a normally breathing lung.
    pub fn normal(baseline: &LungBaseline, boundary: &Boundary) -> Self {
        Self {
            side: baseline.side,
            collapse: 0.0,
            base_volume_ml: baseline.start_volume_ml,
            tidal_ml: baseline.share * boundary.tv_ml,
            held_ml: None,
            offset_mm: [0.0; 3],
            resistance_dv: 0.0,
        }
    }

    /// Boundary values that give this lung `tidal_ml` with its `share` (`TV = tidal/share`); `None`
    /// when the lung is held (a PV cycle needs TV > 0).
    pub fn boundary(&self, normal: &Boundary, share: f64) -> Option<Boundary> {
        if self.held_ml.is_some() || !(self.tidal_ml > 0.0) {
            return None;
        }
        let tv_ml = if self.tidal_ml == share * normal.tv_ml {
            normal.tv_ml
        } else {
            self.tidal_ml / share
        };
        Some(Boundary { tv_ml, ..*normal })
    }
}

/// Deformation scale `s` of the breathing field on a collapsed lung for a volume `delta_ml` above its
/// collapsed base volume: solves [`collapse::collapsed_cubic`]; 0 when the lung has collapsed into its
/// hilum (`collapse = 1`: no breathing field left) or the solve is not finite.
pub fn scale_on_collapsed(cubic: &crate::deform::VolumeCubic, collapse: f64, delta_ml: f64) -> f64 {
    let c = collapse::collapsed_cubic(cubic, collapse);
    if !(c.coeffs[1] > 0.0) {
        return 0.0;
    }
    let s = c.solve_delta(delta_ml * 1000.0);
    if s.is_finite() {
        s
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eq_8_1_by_hand() {
        // dV = I^0.33 = e^{0.33·ln I}.
        let cases = [
            (0.0, 0.0),
            (1e-9, 0.001_071_5), // e^{0.33·(−20.723266)} = e^{−6.838678} = 0.00107152
            (0.042, 0.351_295),  // e^{0.33·(−3.170086)} = e^{−1.046128} = 0.351295
            (0.1, 0.467_735),    // 10^{−0.33} = 0.467735
            (0.2, 0.587_949),    // e^{0.33·(−1.609438)} = e^{−0.531114} = 0.587949
            (0.5, 0.795_536),    // e^{0.33·(−0.693147)} = e^{−0.228739} = 0.795536
            (1.0, 1.0),
        ];
        for (i, want) in cases {
            let dv = volume_fraction_lost(i).unwrap();
            assert!((dv - want).abs() < 1e-6, "I = {i}: {dv} vs {want}");
        }
        assert_eq!(
            volume_fraction_lost(0.0).unwrap().to_bits(),
            0.0f64.to_bits()
        );
        for bad in [-1e-12, 1.000_001, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                volume_fraction_lost(bad),
                Err(DiseaseError::OutOfRange { name: "index", .. })
            ));
        }
        assert!((equivalent_index(0.467_735_141_287_198_2) - 0.1).abs() < 1e-12);
    }

    #[test]
    fn eq_8_2_by_hand() {
        // A = (100·I − 4.2)/9.4 cm; drop = 10·A mm.
        let d = drop_for_index(0.0); // (0 − 4.2)/9.4 = −0.446809 cm → clamped
        assert!(d.clamped && d.drop_mm == 0.0 && (d.raw_cm + 0.446_809).abs() < 1e-6);
        assert!(drop_for_index(1e-9).clamped);
        // I = 0.042: 100·0.042 = 4.2 (to rounding) → A = 0 (±1e-16), no drop.
        let d = drop_for_index(0.042);
        assert!(d.raw_cm.abs() < 1e-15 && d.drop_mm < 1e-14, "{d:?}");
        for (i, mm) in [
            (0.1, 6.170_213),   // 5.8/9.4 = 0.6170213 cm
            (0.2, 16.808_511),  // 15.8/9.4 = 1.6808511 cm
            (0.5, 48.723_404),  // 45.8/9.4 = 4.8723404 cm
            (1.0, 101.914_894), // 95.8/9.4 = 10.1914894 cm
        ] {
            let d = drop_for_index(i);
            assert!(
                !d.clamped && (d.drop_mm - mm).abs() < 1e-5,
                "I = {i}: {d:?}"
            );
        }
    }

    #[test]
    fn eq_8_3_to_8_5_by_hand_with_the_clamp() {
        // T = 5 s (12/min), T_i = T_e = 2.5 s, clamp 0.75 s.
        let t = Timing::default();
        let p = phase_times(&t, 0.0).unwrap();
        assert_eq!((p.dt_s, p.new_inhale_s, p.new_exhale_s), (0.0, 2.5, 2.5));
        assert_eq!(p.timing(&t), t);
        // I = 1e-9: dT = 5·0.00107152 = 0.0053576 → T' = 2.4946424 s each, 12.0258/min.
        let p = phase_times(&t, 1e-9f64.powf(0.33)).unwrap();
        assert!((p.new_inhale_s - 2.494_642_4).abs() < 1e-6 && !p.inhale_clamped);
        // I = 0.042: dT = 5·0.351295 = 1.756476 → T'_i = 0.743524 s < 0.75: clamped.
        let p = phase_times(&t, 0.042f64.powf(0.33)).unwrap();
        assert!((p.raw_inhale_s - 0.743_524).abs() < 1e-6);
        assert!(p.inhale_clamped && p.exhale_clamped && p.new_inhale_s == 0.75);
        // I = 0.1: dT = 2.338676 → raw 0.161324 s (the seed's own demo) → clamped; 40/min.
        let p = phase_times(&t, 0.1f64.powf(0.33)).unwrap();
        assert!((p.raw_inhale_s - 0.161_324).abs() < 1e-6 && p.inhale_clamped);
        assert_eq!(p.breaths_per_min(), 40.0);
        let timing = p.timing(&t);
        assert_eq!(timing.phase_ticks().unwrap(), (45, 45));
        // I = 1: dT = 5 s → raw −2.5 s → clamped.
        let p = phase_times(&t, 1.0).unwrap();
        assert_eq!(p.raw_inhale_s, -2.5);
        assert_eq!((p.new_inhale_s, p.new_exhale_s), (0.75, 0.75));
        // A scene already faster than the clamp keeps its phases; a 1 Hz tick makes the clamp 1 s.
        let fast = Timing {
            breaths_per_min: 60.0,
            ..t
        };
        let p = phase_times(&fast, 1.0).unwrap();
        assert_eq!((p.new_inhale_s, p.new_exhale_s), (0.5, 0.5));
        let slow_tick = Timing { tick_hz: 1.0, ..t };
        let p = phase_times(&slow_tick, 1.0).unwrap();
        assert_eq!(p.new_inhale_s, 1.0);
        assert!(phase_times(&t, 1.5).is_err());
    }
}
