//! # Breathing resistance: the control-constant changes of eq. 8.8–8.9
//!
//! Seed §8.1.3: the control constants `C_0..C_{N−1}` of a phase (our `χ_1..χ_N`, EQUATIONS §1.1) form
//! a converging sequence; "multiplying every parameter with its exponent … divided by the exponent
//! of the first parameter" changes the rate of convergence one way (eq. 8.8), "multiplying every
//! parameter with its logarithm and dividing it by the logarithm of the first parameter" the other
//! (eq. 8.9). With `x = φ·dV` (φ the seed's proportionality constant, 0.1 for pneumothorax; `dV` the
//! volume fraction of eq. 8.1):
//!
//! ```text
//! eq. 8.8 (exponent):  d_i = C_i · e^{C_i·x} / e^{C_0·x}
//! eq. 8.9 (logarithm): e_i = C_i · ln(C_i·x) / ln(C_0·x)
//! ```
//!
//! **Decision (lungdyn), leading factor `C_i`, not `C_0`:** the extraction prints `C_0 ×` in front of
//! both; the seed's prose ("multiplying every parameter with …") and the requirement that `dV = 0` is
//! normal breathing both say `C_i` (with `C_0` every constant tends to `C_0`, a flat sequence that no
//! longer converges). With `C_i`: `d_i = C_i` exactly at `x = 0`, and `e_i → C_i` as `x → 0`.
//!
//! Singular cases, each decided here and tested:
//! * `x = 0` (`dV = 0` or `φ = 0`): both transforms are the identity (eq. 8.9's `ln 0 / ln 0` is
//!   replaced by its limit 1) — the constants come back bit for bit.
//! * eq. 8.9's denominator `ln(C_0·x)` is 0 at `C_0·x = 1` and changes sign beyond: the transform is
//!   defined for `0 < C_0·x < 1` only; outside it is [`ResistanceError::LogSingular`].
//! * `C_i·x ≥ 1` for `i ≥ 1` flips the sign of `e_i`: [`ResistanceError::LogDomain`].
//! * `C_i = 0`: `e_i = 0` (the limit of `C·ln(C·x)` as `C → 0`). `C_i < 0` (fitted constants may be
//!   negative): the odd extension `e_i = C_i·ln(|C_i|·x)/ln(C_0·x)`, continuous through 0; counted in
//!   [`ResistanceReport::negative_constants`].
//! * eq. 8.8 is evaluated as `C_i·e^{(C_i − C_0)·x}` (the same number without two overflowing
//!   exponentials); a result that is not finite is [`ResistanceError::NonFinite`].

use thiserror::Error;

use crate::pv::PhaseConstants;

/// The seed's proportionality constant φ for pneumothorax (L3666–3667: "set to 0.1").
pub const PHI_SEED: f64 = 0.1;

/// Largest φ a scene may set (a documented bound: with φ = 1 and dV = 1, eq. 8.9 already needs every
/// |χ| < 1).
pub const PHI_MAX: f64 = 1.0;

/// Which of the seed's two changes of the control constants.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transform {
    /// Eq. 8.8, `d_i = C_i·e^{C_i x}/e^{C_0 x}`: faster convergence, less resistive breathing.
    Exponent,
    /// Eq. 8.9, `e_i = C_i·ln(C_i x)/ln(C_0 x)`: slower convergence, more resistive breathing.
    Logarithm,
}

/// What a change of the control constants did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ResistanceReport {
    /// `x = φ·dV` used.
    pub x: f64,
    /// `x = 0`: the constants were copied unchanged.
    pub identity: bool,
    /// Constants `< 0` for which eq. 8.9's odd extension was used.
    pub negative_constants: u32,
}

/// Why the constants cannot be changed.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ResistanceError {
    /// `x = φ·dV` is negative or not finite.
    #[error("phi·dV = {x} must be finite and >= 0")]
    BadX {
        /// The product given.
        x: f64,
    },
    /// Eq. 8.9's denominator `ln(C_0·φ·dV)` is zero or changes sign.
    #[error("eq. 8.9 is singular: chi_1·phi·dV = {c0x} must lie in (0, 1) (ln of it is the denominator); lower phi")]
    LogSingular {
        /// `C_0·x`.
        c0x: f64,
    },
    /// `C_i·φ·dV ≥ 1` for a later constant: `ln` changes sign and so would `e_i`.
    #[error("eq. 8.9: chi_{index}·phi·dV = {cx} must be below 1; lower phi")]
    LogDomain {
        /// 1-based index of the constant (χ numbering).
        index: usize,
        /// `|C_i|·x`.
        cx: f64,
    },
    /// A changed constant is not finite.
    #[error("eq. {eq}: the changed chi_{index} is not finite; lower phi")]
    NonFinite {
        /// "8.8" or "8.9".
        eq: &'static str,
        /// 1-based index.
        index: usize,
    },
    /// No constants.
    #[error("no control constants to change")]
    Empty,
}

/// Apply `transform` with `x = φ·dV` to the constants `c`, writing into `out` (cleared first; no
/// allocation when `out` has the capacity).
pub fn transform_into(
    c: &[f64],
    transform: Transform,
    x: f64,
    out: &mut Vec<f64>,
) -> Result<ResistanceReport, ResistanceError> {
    if !(x.is_finite() && x >= 0.0) {
        return Err(ResistanceError::BadX { x });
    }
    let Some(&c0) = c.first() else {
        return Err(ResistanceError::Empty);
    };
    out.clear();
    let mut report = ResistanceReport {
        x,
        ..Default::default()
    };
    if x == 0.0 {
        // dV = 0 (or φ = 0) is normal breathing: eq. 8.8 is exactly the identity, eq. 8.9's limit is.
        out.extend_from_slice(c);
        report.identity = true;
        return Ok(report);
    }
    match transform {
        Transform::Exponent => {
            for (i, &ci) in c.iter().enumerate() {
                // eq. 8.8, C_i reading: C_i·e^{C_i x}/e^{C_0 x} = C_i·e^{(C_i − C_0) x}.
                let d = ci * ((ci - c0) * x).exp();
                if !d.is_finite() {
                    return Err(ResistanceError::NonFinite {
                        eq: "8.8",
                        index: i + 1,
                    });
                }
                out.push(d);
            }
        }
        Transform::Logarithm => {
            let c0x = c0 * x;
            if !(c0x > 0.0 && c0x < 1.0) {
                return Err(ResistanceError::LogSingular { c0x });
            }
            let den = c0x.ln();
            for (i, &ci) in c.iter().enumerate() {
                let cx = ci.abs() * x;
                if cx >= 1.0 {
                    return Err(ResistanceError::LogDomain { index: i + 1, cx });
                }
                let e = if i == 0 {
                    // ln(C_0 x)/ln(C_0 x) = 1 exactly: the first constant is kept, as the seed intends.
                    ci
                } else if ci == 0.0 || cx == 0.0 {
                    // lim_{C→0} C·ln(C·x) = 0 (also C·x underflowing to 0).
                    0.0
                } else {
                    if ci < 0.0 {
                        report.negative_constants += 1;
                    }
                    ci * cx.ln() / den
                };
                if !e.is_finite() {
                    return Err(ResistanceError::NonFinite {
                        eq: "8.9",
                        index: i + 1,
                    });
                }
                out.push(e);
            }
        }
    }
    Ok(report)
}

/// Copy `base` into `out` with its control constants changed by `transform` at `x = φ·dV` (every
/// other constant kept). No allocation when `out.chi` has the capacity (the per-cycle path).
pub fn phase_into(
    base: &PhaseConstants,
    transform: Transform,
    x: f64,
    out: &mut PhaseConstants,
) -> Result<ResistanceReport, ResistanceError> {
    let report = transform_into(&base.chi, transform, x, &mut out.chi)?;
    out.q = base.q;
    out.c = base.c;
    out.t_ext = base.t_ext;
    out.t_steps = base.t_steps;
    out.beta0 = base.beta0;
    out.beta1 = base.beta1;
    Ok(report)
}

/// The changed constants of both phases (allocating; see [`phase_into`] for the per-cycle path).
pub fn phases(
    inhale: &PhaseConstants,
    exhale: &PhaseConstants,
    transforms: (Transform, Transform),
    x: f64,
) -> Result<(PhaseConstants, PhaseConstants), ResistanceError> {
    let (mut i, mut e) = (inhale.clone(), exhale.clone());
    phase_into(inhale, transforms.0, x, &mut i)?;
    phase_into(exhale, transforms.1, x, &mut e)?;
    Ok((i, e))
}

/// Pneumothorax, `(inhalation, exhalation)`: "an increased resistance to breathing … during
/// inhalation, and decrease resistance during exhalation" (L3669–3670). **Decision (lungdyn):** eq. 8.9
/// (slower convergence, "more resistive" in the seed's prose, L3642–3647, and measurably later filling
/// in lungdyn's PV reading) on the inhalation constants, eq. 8.8 on the exhalation constants. The
/// seed's "let d_i and e_i be the modified constants respectively" pairs them the other way round; that
/// one word loses against the prose, the physiology of §8.1.1 and the measurement (EQUATIONS §4.2).
pub const PNEUMOTHORAX: (Transform, Transform) = (Transform::Logarithm, Transform::Exponent);

/// Tumour (seed L3671–3672, "increased resistance … during both the inhalation and exhalation", no
/// formula): the "more resistive" transform (eq. 8.9; test
/// `the_logarithm_slows_and_the_exponent_speeds_every_preset_limb`) on both phases.
pub const TUMOUR: (Transform, Transform) = (Transform::Logarithm, Transform::Logarithm);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pv::{phase_curve, preset, PRESET_NAMES};
    use proptest::prelude::*;

    const SUBJECT_1: [f64; 7] = [2.0, 1.2, 0.2, 0.2, 0.15, 0.1, 0.08];

    #[test]
    fn x_zero_returns_the_constants_bit_for_bit() {
        for t in [Transform::Exponent, Transform::Logarithm] {
            let mut out = Vec::new();
            let r = transform_into(&SUBJECT_1, t, 0.0, &mut out).unwrap();
            assert!(r.identity);
            assert_eq!(
                out.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                SUBJECT_1.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn seed_demo_values_by_hand() {
        // Subject-1 constants, φ = 0.1, I = 0.1: dV = 0.1^0.33 = 10^-0.33 = 0.467735…,
        // x = φ·dV = 0.0467735.
        let x = 0.1 * 0.1f64.powf(0.33);
        assert!((x - 0.046_773_5).abs() < 1e-7);
        let mut d = Vec::new();
        transform_into(&SUBJECT_1, Transform::Exponent, x, &mut d).unwrap();
        // d_1 = C_1 = 2.0; d_2 = 1.2·e^{(1.2 − 2)·0.0467735} = 1.2·e^{−0.0374188} = 1.2·0.963273 = 1.155927;
        // d_3 = 0.2·e^{(0.2 − 2)·0.0467735} = 0.2·e^{−0.0841923} = 0.2·0.919254 = 0.183851;
        // d_7 = 0.08·e^{−1.92·0.0467735} = 0.08·e^{−0.0898051} = 0.08·0.914111 = 0.073129.
        for (i, want) in [(0, 2.0), (1, 1.155_927), (2, 0.183_851), (6, 0.073_129)] {
            assert!(
                (d[i] - want).abs() < 2e-6,
                "d_{} = {} vs {want}",
                i + 1,
                d[i]
            );
        }
        let mut e = Vec::new();
        transform_into(&SUBJECT_1, Transform::Logarithm, x, &mut e).unwrap();
        // ln(C_0 x) = ln(0.0935470) = −2.369291.
        // e_2 = 1.2·ln(1.2·0.0467735)/(−2.369291) = 1.2·ln(0.0561282)/(−2.369291)
        //     = 1.2·(−2.880117)/(−2.369291) = 1.458723;
        // e_3 = 0.2·ln(0.00935470)/(−2.369291) = 0.2·(−4.671876)/(−2.369291) = 0.394369;
        // e_7 = 0.08·ln(0.00374188)/(−2.369291) = 0.08·(−5.588167)/(−2.369291) = 0.188687.
        for (i, want) in [(0, 2.0), (1, 1.458_723), (2, 0.394_369), (6, 0.188_687)] {
            assert!(
                (e[i] - want).abs() < 2e-6,
                "e_{} = {} vs {want}",
                i + 1,
                e[i]
            );
        }
    }

    #[test]
    fn small_x_tends_to_the_normal_constants() {
        // eq. 8.9's ratio of logarithms → 1 as x → 0, but only logarithmically slowly.
        let mut e = Vec::new();
        transform_into(&SUBJECT_1, Transform::Logarithm, 1e-300, &mut e).unwrap();
        for (a, b) in e.iter().zip(SUBJECT_1) {
            assert!((a - b).abs() < 0.02 * b, "{a} vs {b}");
        }
    }

    #[test]
    fn the_singular_denominator_and_the_log_domain_are_typed_errors() {
        let mut out = Vec::new();
        // C_0·x = 1: ln(1) = 0 in eq. 8.9's denominator.
        assert!(matches!(
            transform_into(&[2.0, 1.0, 0.5], Transform::Logarithm, 0.5, &mut out),
            Err(ResistanceError::LogSingular { c0x }) if c0x == 1.0
        ));
        assert!(matches!(
            transform_into(&[-1.0, 1.0, 0.5], Transform::Logarithm, 0.1, &mut out),
            Err(ResistanceError::LogSingular { .. })
        ));
        assert!(matches!(
            transform_into(&[0.5, 30.0, 0.5], Transform::Logarithm, 0.1, &mut out),
            Err(ResistanceError::LogDomain { index: 2, .. })
        ));
        assert!(matches!(
            transform_into(&[1.0, 1.0, 1.0], Transform::Exponent, f64::NAN, &mut out),
            Err(ResistanceError::BadX { .. })
        ));
        assert!(matches!(
            transform_into(&[], Transform::Exponent, 0.1, &mut out),
            Err(ResistanceError::Empty)
        ));
        assert!(matches!(
            transform_into(&[0.0, 1e300, 1.0], Transform::Exponent, 0.5, &mut out),
            Err(ResistanceError::NonFinite {
                eq: "8.8",
                index: 2
            })
        ));
    }

    #[test]
    fn zero_and_negative_constants_use_the_limit_and_the_odd_extension() {
        let mut e = Vec::new();
        let r = transform_into(&[2.0, 0.0, -0.2, 0.2], Transform::Logarithm, 0.05, &mut e).unwrap();
        assert_eq!(e[1], 0.0);
        assert_eq!(e[2], -e[3]);
        assert_eq!(r.negative_constants, 1);
    }

    /// Mean normalised volume over the phase (lower = the limb fills later = "more resistive") and
    /// the largest difference from `base`'s curve.
    fn filling(k: &PhaseConstants, base: &PhaseConstants) -> (f64, f64) {
        let (c, b) = (
            phase_curve(k, 400).unwrap(),
            phase_curve(base, 400).unwrap(),
        );
        let mean = c.iter().sum::<f64>() / c.len() as f64;
        let max = c
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        (mean, max)
    }

    #[test]
    fn the_logarithm_slows_and_the_exponent_speeds_every_preset_limb() {
        //! Measures what eq. 8.8 and 8.9 do in lungdyn's PV reading (EQUATIONS §1.1) at the seed's
        //! demo (φ = 0.1, I = 0.1: x = 0.0468) and at x = 0.3: the mean normalised volume of each
        //! limb (lower = fills later = "more resistive") and the largest change of the curve. Pins
        //! EQUATIONS §4.2 "Measured (lungdyn)": eq. 8.9 lowers the mean for every preset (more
        //! resistive), eq. 8.8 raises it or leaves it (less resistive) — as the seed's prose says — and
        //! both change the curve by less than 1.5 % of the normalised range at the demo (5 % at 0.3).
        for (x, limit) in [(0.1 * 0.1f64.powf(0.33), 0.015), (0.3, 0.05)] {
            for name in PRESET_NAMES {
                let p = preset(name).unwrap();
                for (limb, base) in [("inhale", &p.inhale), ("exhale", &p.exhale)] {
                    let (m0, _) = filling(base, base);
                    let mut k = base.clone();
                    phase_into(base, Transform::Exponent, x, &mut k).unwrap();
                    let (m_exp, max_exp) = filling(&k, base);
                    phase_into(base, Transform::Logarithm, x, &mut k).unwrap();
                    let (m_log, max_log) = filling(&k, base);
                    eprintln!(
                        "x = {x:.4} {name} {limb}: mean V normal {m0:.4}, eq. 8.8 {m_exp:.4} \
                         (max change {max_exp:.4}), eq. 8.9 {m_log:.4} (max change {max_log:.4})"
                    );
                    assert!(m_log < m0 && m_exp > m0 - 1e-4, "{name} {limb} x = {x}");
                    assert!(max_exp < limit && max_log < limit, "{name} {limb} x = {x}");
                }
            }
        }
    }

    proptest! {
        #[test]
        fn changed_constants_are_finite_or_a_typed_error(
            chi in proptest::collection::vec(-3.0f64..3.0, 1..9),
            x in 0.0f64..1.0,
        ) {
            for t in [Transform::Exponent, Transform::Logarithm] {
                let mut out = Vec::new();
                match transform_into(&chi, t, x, &mut out) {
                    Ok(_) => {
                        prop_assert_eq!(out.len(), chi.len());
                        prop_assert!(out.iter().all(|v| v.is_finite()));
                        prop_assert_eq!(out[0].to_bits(), chi[0].to_bits());
                    }
                    Err(e) => {
                        let expected = matches!(e, ResistanceError::LogSingular { .. } | ResistanceError::LogDomain { .. });
                        prop_assert!(expected, "unexpected {}", e);
                    }
                }
            }
        }
    }
}
