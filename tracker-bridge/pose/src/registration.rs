//! Point-based rigid registration of fiducials (Horn 1987 in its SVD form, Arun et al. 1987 /
//! Umeyama 1991): the rotation `R` and translation `t` that minimise `Σ |R·a_i + t − b_i|²` over
//! corresponding model points `a_i` and tracker points `b_i` — and a judgement of whether that fit
//! can be used at all.
//!
//! With centroids `ā`, `b̄` and `H = Σ (a_i − ā)(b_i − b̄)ᵀ = U Σ Vᵀ`, `R = V · diag(1, 1, d) · Uᵀ`
//! with `d = sign det(V Uᵀ)` (Umeyama's correction, so `R` is a rotation and never a reflection),
//! and `t = b̄ − R ā`. Umeyama's similarity scale from the same SVD,
//! `c = (σ₁ + σ₂ + d·σ₃) / Σ|a_i − ā|²`, is the size of the tracker points relative to the model
//! points; it is reported, and used only to judge units (the calibration written is rigid).
//!
//! # What is refused, and why (each threshold argued)
//!
//! Fiducial localisation error (FLE) is the yardstick: about 0.25–0.5 mm RMS for a tracked pointer
//! tip on an optical tracker, about 1 mm for a fiducial picked in a CT. Fiducials are a few to a
//! few hundred millimetres apart.
//!
//! 1. **Too few** ([`RegistrationError::TooFew`]): under 3 pairs fix no rotation. 3 are accepted with
//!    a warning (they fit almost any rigid motion, so the FRE says little).
//! 2. **Identical or duplicate points** ([`RegistrationError::Duplicate`]): two fiducials of one list
//!    closer than [`MIN_SEPARATION_MM`] (1 mm, about twice the FLE and the size of a fiducial bead)
//!    are one place measured twice — a pointer not moved, a line copied. Exactly identical points
//!    are refused first, before anything else is judged: four identical tracker points once gave a
//!    calibration with an FRE of 75 mm and no warning. Near (not identical) duplicates are judged
//!    after the units, since points in metres read as mm all lie within a millimetre.
//! 3. **Collinear fiducials** ([`RegistrationError::Collinear`]), in either list: with `s₁ ≥ s₂` the
//!    two largest singular values of the centred points, the rotation about the line is fixed only
//!    by the spread across it. By Fitzpatrick, West and Maurer (1998),
//!    `TRE² ≈ FLE²/N · (1 + ⅓ Σ d_k²/f_k²)`: with fiducials spread ±75 mm along a line and
//!    `s₂/s₁ = 0.1` (about 7.5 mm across), a target 100 mm from the line has `d/f ≈ 13`, so
//!    `TRE ≈ 1.9 mm` at FLE 0.5 mm, N = 4 — already the whole error budget of the overlay. Below
//!    [`COLLINEAR_RATIO`] (0.1) the registration is refused; below [`THIN_RATIO`] (0.2) it is warned.
//!    Collinear tracker points used to be fitted and reported as a "reflection" (with a rank-1 `H`
//!    the sign `d` is arbitrary); they are now named for what they are.
//! 4. **A unit or scale mismatch** ([`RegistrationError::Units`], [`RegistrationError::Scale`]): a
//!    rigid body keeps its size, so `c` should be 1 within `FLE/(spread·√N)` (under 1 % for a 25 mm
//!    spread, N ≥ 4). If the similarity fit explains the points (its residual under
//!    [`NO_FIT_FRACTION`] of the tracker points' spread) and `c` is within 10 % of 10, 25.4 or
//!    1000 (or their inverses), the likely units are named ("the tracker points look like cm");
//!    otherwise a scale off by more than [`SCALE_REFUSE`] (5 %: 7.5 mm across a 150 mm lung) is
//!    refused, and one off by more than [`SCALE_WARN`] (2 %, twice the noise) is warned (a CT's
//!    voxel spacing wrong by a few percent does happen).
//! 5. **No rigid fit** ([`RegistrationError::NoRigidFit`]): the FRE RMS is compared with the RMS
//!    distance of the model fiducials from their centroid (the spread). `FRE²/spread²` is the part
//!    of the point layout the rigid fit does not explain: a good registration has FRE ≈ FLE, 1–3 %
//!    of a 30–100 mm spread. Above [`NO_FIT_FRACTION`] (10 %: 3 mm on a tight 30 mm phantom
//!    layout, far beyond any FLE) no rigid fit exists — mismatched pairs, mirrored lists, a wrong
//!    point — and the error says which is likeliest (a reflection, the worst pair).
//! 6. **Warnings** with an accepted fit: FRE RMS above [`FRE_WARN_MM`] (2 mm, above every FLE
//!    above), a point far off the others (a likely mismatched pair), 3 fiducials, thin spread, a
//!    scale off by 2–5 %.
//!
//! Note that a small FRE does not prove a small error at the target (TRE): Fitzpatrick, West and
//! Maurer (1998) show FRE and TRE are uncorrelated; spread the fiducials around the target.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use thiserror::Error;

/// Two fiducials of one list closer than this (mm) are one place measured twice (item 2 above).
pub const MIN_SEPARATION_MM: f64 = 1.0;
/// Below this `σ₂/σ₁` (either list) the registration is refused as collinear (item 3 above).
pub const COLLINEAR_RATIO: f64 = 0.1;
/// Below this `σ₂/σ₁` (either list) the fiducials are warned about as nearly collinear.
pub const THIN_RATIO: f64 = 0.2;
/// A similarity scale off 1 by more than this fraction is warned about (item 4 above).
pub const SCALE_WARN: f64 = 0.02;
/// A similarity scale off 1 by more than this fraction is refused (item 4 above).
pub const SCALE_REFUSE: f64 = 0.05;
/// FRE RMS above this fraction of the fiducials' RMS spread: no rigid fit (item 5 above).
pub const NO_FIT_FRACTION: f64 = 0.1;
/// FRE RMS above this (mm) is warned about (item 6 above).
pub const FRE_WARN_MM: f64 = 2.0;
/// Units a list of millimetres is confused with: (millimetres per unit, name).
const UNITS: [(f64, &str); 3] = [(10.0, "cm"), (25.4, "inches"), (1000.0, "m")];
/// A scale within this factor of a unit's size names that unit.
const UNIT_MATCH: f64 = 1.1;

/// Why no registration could be computed, or why the one computed must not be used.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum RegistrationError {
    /// Fewer than three pairs.
    #[error("{0} point pairs: a rigid registration needs at least 3 (4 or more to see an error)")]
    TooFew(usize),
    /// The lists differ in length.
    #[error("{model} model points but {tracker} tracker points: every fiducial needs both")]
    CountMismatch {
        /// Model points.
        model: usize,
        /// Tracker points.
        tracker: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("point {index} ({which}) has a coordinate that is not a finite number")]
    NonFinite {
        /// Zero-based index.
        index: usize,
        /// "model" or "tracker".
        which: &'static str,
    },
    /// Two fiducials of one list are (nearly) the same place.
    #[error(
        "{which} points {} and {} are {}: one place measured twice (distinct fiducials are at \
         least {MIN_SEPARATION_MM} mm apart); measure each fiducial at its own place",
        first + 1,
        second + 1,
        if *distance_mm == 0.0 { "identical".to_string() } else { format!("{distance_mm:.3} mm apart") }
    )]
    Duplicate {
        /// "model" or "tracker".
        which: &'static str,
        /// Zero-based index of the first.
        first: usize,
        /// Zero-based index of the second.
        second: usize,
        /// Their distance, mm.
        distance_mm: f64,
    },
    /// The points of one list lie on (or near) one line: the rotation about it is not determined.
    #[error(
        "the {which} fiducials are {} (spread across their line {:.2} % of the spread along it; \
         refused below {:.0} %): the rotation about that line is not determined and the error away \
         from the fiducials would be large; use fiducials that span a plane or a volume",
        if *ratio < 1e-6 { "collinear" } else { "nearly collinear" },
        100.0 * ratio,
        100.0 * COLLINEAR_RATIO
    )]
    Collinear {
        /// "model" or "tracker".
        which: &'static str,
        /// σ₂/σ₁.
        ratio: f64,
    },
    /// The lists differ in size by a factor that names a unit.
    #[error(
        "the tracker points are {scale:.4} times the size of the model points: {guess}; give both \
         lists in mm"
    )]
    Units {
        /// Umeyama's similarity scale (tracker / model).
        scale: f64,
        /// The likely units, e.g. "the tracker points look like cm".
        guess: String,
    },
    /// The lists differ in size by more than measurement error allows, and no unit explains it.
    #[error(
        "the tracker points are {scale:.4} times the size of the model points (refused beyond ±{:.0} %): \
         a rigid body keeps its size — a wrong CT voxel spacing, or a scaled mesh?",
        100.0 * SCALE_REFUSE
    )]
    Scale {
        /// Umeyama's similarity scale (tracker / model).
        scale: f64,
    },
    /// The best rigid fit leaves errors comparable to the fiducials' spread.
    #[error(
        "no rigid fit: FRE RMS {fre_rms_mm:.2} mm is {:.0} % of the fiducials' spread ({spread_mm:.1} mm \
         RMS from their centroid; refused above {:.0} %): {hint}",
        100.0 * fre_rms_mm / spread_mm,
        100.0 * NO_FIT_FRACTION
    )]
    NoRigidFit {
        /// FRE RMS of the best rigid fit, mm.
        fre_rms_mm: f64,
        /// RMS distance of the model fiducials from their centroid, mm.
        spread_mm: f64,
        /// The likeliest cause.
        hint: String,
    },
}

/// A rigid registration and how good it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// Rotation, model → tracker.
    pub rotation: UnitQuaternion<f64>,
    /// Translation, mm: `b = R a + t`.
    pub translation_mm: Vector3<f64>,
    /// Fiducial registration error of every pair, mm.
    pub fre_mm: Vec<f64>,
    /// RMS of `fre_mm`, mm.
    pub fre_rms_mm: f64,
    /// Singular values of the centred model points, mm, largest first.
    pub singular_values: [f64; 3],
    /// `σ₂/σ₁` of the centred tracker points.
    pub tracker_spread_ratio: f64,
    /// RMS distance of the model fiducials from their centroid, mm.
    pub spread_mm: f64,
    /// Umeyama's similarity scale, tracker / model (1 for a rigid body in one unit).
    pub scale: f64,
    /// Human-readable warnings (thin spread, large FRE, scale, outliers, 3 fiducials).
    pub warnings: Vec<String>,
}

impl Registration {
    /// `σ₂/σ₁` of the centred model points (0: collinear, 1: round spread in a plane or volume).
    pub fn spread_ratio(&self) -> f64 {
        ratio(&self.singular_values)
    }

    /// Apply to a model point.
    pub fn apply(&self, a: [f64; 3]) -> [f64; 3] {
        let b = self.rotation * Vector3::from(a) + self.translation_mm;
        [b.x, b.y, b.z]
    }
}

fn ratio(sv: &[f64; 3]) -> f64 {
    if sv[0] > 0.0 {
        sv[1] / sv[0]
    } else {
        0.0
    }
}

/// Centroid, singular values of the centred points (largest first) and their sum of squares.
fn spread(p: &[Vector3<f64>]) -> (Vector3<f64>, [f64; 3], f64) {
    let c = p.iter().sum::<Vector3<f64>>() / p.len() as f64;
    let scatter: Matrix3<f64> = p.iter().map(|q| (q - c) * (q - c).transpose()).sum();
    let mut ev: Vec<f64> = scatter
        .symmetric_eigenvalues()
        .iter()
        .map(|&l| l.max(0.0).sqrt())
        .collect();
    ev.sort_by(|x, y| y.total_cmp(x));
    let ss = p.iter().map(|q| (q - c).norm_squared()).sum();
    (c, [ev[0], ev[1], ev[2]], ss)
}

/// The closest pair of points closer than `limit_mm` (zero-based indices, distance), if any.
fn closest_pair(p: &[Vector3<f64>], limit_mm: f64) -> Option<(usize, usize, f64)> {
    let mut best: Option<(usize, usize, f64)> = None;
    for i in 0..p.len() {
        for j in i + 1..p.len() {
            let d = (p[i] - p[j]).norm();
            if d <= limit_mm && best.is_none_or(|(_, _, b)| d < b) {
                best = Some((i, j, d));
            }
        }
    }
    best
}

/// The units a similarity scale (tracker / model) suggests, if it is near one.
fn unit_guess(scale: f64) -> Option<String> {
    UNITS.iter().find_map(|&(mm, name)| {
        let near = |x: f64| x > 0.0 && x.ln().abs() < UNIT_MATCH.ln();
        if near(scale * mm) {
            Some(format!(
                "the tracker points look like {name} (the model points are mm)"
            ))
        } else if near(scale / mm) {
            Some(format!(
                "the model points look like {name} (the tracker points are mm)"
            ))
        } else {
            None
        }
    })
}

/// Register `model` onto `tracker` (pairs by index) and judge the result (see the module doc).
pub fn register(
    model: &[[f64; 3]],
    tracker: &[[f64; 3]],
) -> Result<Registration, RegistrationError> {
    if model.len() != tracker.len() {
        return Err(RegistrationError::CountMismatch {
            model: model.len(),
            tracker: tracker.len(),
        });
    }
    let n = model.len();
    if n < 3 {
        return Err(RegistrationError::TooFew(n));
    }
    for (which, pts) in [("model", model), ("tracker", tracker)] {
        if let Some(index) = pts.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(RegistrationError::NonFinite { index, which });
        }
    }
    let a: Vec<Vector3<f64>> = model.iter().map(|p| Vector3::from(*p)).collect();
    let b: Vec<Vector3<f64>> = tracker.iter().map(|p| Vector3::from(*p)).collect();
    let lists = [("model", &a), ("tracker", &b)];
    // 2. Identical points, before anything is judged from a spread they collapse.
    for (which, p) in lists {
        if let Some((first, second, _)) = closest_pair(p, 0.0) {
            return Err(RegistrationError::Duplicate {
                which,
                first,
                second,
                distance_mm: 0.0,
            });
        }
    }
    // 3. Collinear lists (the ratio is free of units).
    let (ca, sv_a, ss_a) = spread(&a);
    let (cb, sv_b, ss_b) = spread(&b);
    for (which, sv) in [("model", &sv_a), ("tracker", &sv_b)] {
        let ratio = ratio(sv);
        if ratio < COLLINEAR_RATIO {
            return Err(RegistrationError::Collinear { which, ratio });
        }
    }
    let h: Matrix3<f64> = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (p - ca) * (q - cb).transpose())
        .sum();
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("computed"), svd.v_t.expect("computed"));
    let v = v_t.transpose();
    let d = if (v * u.transpose()).determinant() < 0.0 {
        -1.0
    } else {
        1.0
    };
    // nalgebra sorts the singular values, largest first: the sign goes on the smallest.
    let sigma = svd.singular_values;
    let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let translation_mm = cb - rotation * ca;
    let fre_mm: Vec<f64> = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (rotation * p + translation_mm - q).norm())
        .collect();
    let sum2: f64 = fre_mm.iter().map(|e| e * e).sum();
    let fre_rms_mm = (sum2 / n as f64).sqrt();
    let spread_mm = (ss_a / n as f64).sqrt();
    // 4. Units and scale: Umeyama's c, trusted only where the similarity fit explains the points.
    let scale = (sigma[0] + sigma[1] + d * sigma[2]) / ss_a;
    let similar_rms = {
        let t = cb - rotation * ca * scale;
        let e2: f64 = a
            .iter()
            .zip(&b)
            .map(|(p, q)| (rotation * p * scale + t - q).norm_squared())
            .sum();
        (e2 / n as f64).sqrt()
    };
    let similar_fits = similar_rms <= NO_FIT_FRACTION * (ss_b / n as f64).sqrt();
    let mut warnings = Vec::new();
    if similar_fits && (scale - 1.0).abs() > SCALE_REFUSE {
        return Err(match unit_guess(scale) {
            Some(guess) => RegistrationError::Units { scale, guess },
            None => RegistrationError::Scale { scale },
        });
    }
    // Near duplicates, now that both lists are known to be in mm.
    for (which, p) in lists {
        if let Some((first, second, distance_mm)) = closest_pair(p, MIN_SEPARATION_MM) {
            return Err(RegistrationError::Duplicate {
                which,
                first,
                second,
                distance_mm,
            });
        }
    }
    // One bad pair inflates the RMS too (its error is at most √n times the RMS), so each point is
    // compared with the RMS of the others.
    let others = |e: f64| ((sum2 - e * e).max(0.0) / (n - 1) as f64).sqrt();
    let worst = fre_mm
        .iter()
        .enumerate()
        .max_by(|x, y| x.1.total_cmp(y.1))
        .map(|(i, e)| (i, *e))
        .unwrap_or((0, 0.0));
    // 5. No rigid fit.
    if fre_rms_mm > NO_FIT_FRACTION * spread_mm {
        let hint = if d < 0.0 && sigma[2] > COLLINEAR_RATIO * sigma[0] {
            "the best fit of these points was a reflection: are the lists mirrored (left and right \
             swapped, or one list in a left-handed frame), or are fiducials paired in the wrong order?"
                .to_string()
        } else if n >= 4 && worst.1 > 3.0 * others(worst.1) {
            format!(
                "point {} fits {:.1} mm off, over 3 times the RMS of the others ({:.1} mm): is it \
                 paired with the right fiducial?",
                worst.0 + 1,
                worst.1,
                others(worst.1)
            )
        } else {
            "the two lists do not describe the same rigid layout: are the fiducials paired in the \
             same order (or labelled), and are both lists of the same fiducials?"
                .to_string()
        };
        return Err(RegistrationError::NoRigidFit {
            fre_rms_mm,
            spread_mm,
            hint,
        });
    }
    // 6. Warnings with an accepted fit.
    if fre_rms_mm > FRE_WARN_MM {
        warnings.push(format!(
            "FRE RMS {fre_rms_mm:.2} mm is above {FRE_WARN_MM} mm (fiducial localisation error is \
             0.25-1 mm): check the worst points and the pairing"
        ));
    }
    if (scale - 1.0).abs() > SCALE_WARN {
        warnings.push(format!(
            "the tracker points are {scale:.4} times the size of the model points (more than \
             ±{:.0} %, beyond measurement noise): a CT voxel spacing or mesh scale slightly wrong?",
            100.0 * SCALE_WARN
        ));
    }
    for (which, sv) in [("model", &sv_a), ("tracker", &sv_b)] {
        let ratio = ratio(sv);
        if ratio < THIN_RATIO {
            warnings.push(format!(
                "the {which} fiducials are nearly collinear (spread across their line is {:.1} % of \
                 the spread along it): rotation about that line is poorly determined, and the error \
                 away from the fiducials can be much larger than the FRE; add fiducials off that line",
                100.0 * ratio
            ));
        }
    }
    if n == 3 {
        warnings.push(
            "3 fiducials fit any rigid motion almost exactly: the FRE says little; use 4 or more"
                .into(),
        );
    }
    for (i, e) in fre_mm.iter().enumerate() {
        if n >= 4 && *e > 1.0 && *e > 3.0 * others(*e) {
            warnings.push(format!(
                "point {} fits {e:.2} mm off, over 3 times the RMS of the others ({:.2} mm): \
                 check that it is paired with the right fiducial",
                i + 1,
                others(*e)
            ));
        }
    }
    Ok(Registration {
        rotation,
        translation_mm,
        fre_mm,
        fre_rms_mm,
        singular_values: sv_a,
        tracker_spread_ratio: ratio(&sv_b),
        spread_mm,
        scale,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn cube() -> Vec<[f64; 3]> {
        vec![
            [0.0, 0.0, 0.0],
            [100.0, 0.0, 0.0],
            [0.0, 80.0, 0.0],
            [0.0, 0.0, 60.0],
            [100.0, 80.0, 20.0],
            [30.0, 10.0, 60.0],
        ]
    }

    fn moved(pts: &[[f64; 3]], q: UnitQuaternion<f64>, t: Vector3<f64>) -> Vec<[f64; 3]> {
        pts.iter()
            .map(|p| {
                let b = q * Vector3::from(*p) + t;
                [b.x, b.y, b.z]
            })
            .collect()
    }

    #[test]
    fn an_exact_rigid_motion_is_recovered_with_zero_fre() {
        let q = UnitQuaternion::from_euler_angles(0.3, -1.2, 2.5);
        let t = Vector3::new(12.0, -300.0, -1100.0);
        let r = register(&cube(), &moved(&cube(), q, t)).unwrap();
        assert!(r.rotation.angle_to(&q) < 1e-12);
        assert!((r.translation_mm - t).norm() < 1e-9);
        assert!(r.fre_rms_mm < 1e-9);
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    }

    #[test]
    fn the_fre_is_the_residual_of_noisy_points() {
        let mut b = moved(&cube(), UnitQuaternion::identity(), Vector3::zeros());
        b[0][0] += 1.0;
        let r = register(&cube(), &b).unwrap();
        assert!(r.fre_rms_mm > 0.1 && r.fre_rms_mm < 1.0);
        let rms = (r.fre_mm.iter().map(|e| e * e).sum::<f64>() / 6.0).sqrt();
        assert!((rms - r.fre_rms_mm).abs() < 1e-12);
        assert!(r.fre_mm[0] == r.fre_mm.iter().cloned().fold(0.0, f64::max));
    }

    #[test]
    fn collinear_fiducials_are_refused_and_thin_ones_warned() {
        let line: Vec<[f64; 3]> = (0..5).map(|i| [i as f64 * 10.0, 0.0, 0.0]).collect();
        assert!(matches!(
            register(&line, &line),
            Err(RegistrationError::Collinear { which: "model", ratio }) if ratio < 1e-6
        ));
        let mut near = line.clone();
        near[2][1] = 2.0;
        let e = register(&near, &near).unwrap_err();
        assert!(
            matches!(e, RegistrationError::Collinear { which: "model", ratio } if ratio > 0.0 && ratio < COLLINEAR_RATIO),
            "{e}"
        );
        assert!(e.to_string().contains("nearly collinear"), "{e}");
        // Across the line 15 % of along it: accepted with a warning.
        let mut thin = line.clone();
        thin[1][1] = 5.0;
        thin[3][1] = -5.0;
        let r = register(&thin, &thin).unwrap();
        assert!(r.spread_ratio() > COLLINEAR_RATIO && r.spread_ratio() < THIN_RATIO);
        assert!(
            r.warnings
                .iter()
                .any(|w| w.contains("model fiducials are nearly collinear")),
            "{:?}",
            r.warnings
        );
    }

    #[test]
    fn a_mirrored_list_is_refused_naming_the_reflection() {
        let mirrored: Vec<[f64; 3]> = cube().iter().map(|p| [-p[0], p[1], p[2]]).collect();
        let e = register(&cube(), &mirrored).unwrap_err();
        assert!(matches!(e, RegistrationError::NoRigidFit { .. }), "{e}");
        assert!(e.to_string().contains("reflection"), "{e}");
    }

    #[test]
    fn bad_inputs_are_named() {
        assert_eq!(
            register(&cube()[..2], &cube()[..2]),
            Err(RegistrationError::TooFew(2))
        );
        assert!(matches!(
            register(&cube(), &cube()[..5]),
            Err(RegistrationError::CountMismatch { .. })
        ));
        let mut b = cube();
        b[3][1] = f64::NAN;
        assert_eq!(
            register(&cube(), &b),
            Err(RegistrationError::NonFinite {
                index: 3,
                which: "tracker"
            })
        );
        // One pair 5 mm off: accepted, that point named.
        let mut w = cube();
        w[4][0] += 5.0;
        let r = register(&cube(), &w).unwrap();
        assert!(
            r.warnings.iter().any(|x| x.contains("point 5")),
            "{:?}",
            r.warnings
        );
        // One pair wildly off: no rigid fit, that point named.
        w[4] = [500.0, 500.0, 500.0];
        let e = register(&cube(), &w).unwrap_err();
        assert!(matches!(e, RegistrationError::NoRigidFit { .. }), "{e}");
        assert!(e.to_string().contains("point 5"), "{e}");
    }

    // The hostile probe's cases (issue 18): each was written with exit 0 and no (or the wrong) warning.
    fn four() -> Vec<[f64; 3]> {
        cube()[..4].to_vec()
    }

    #[test]
    fn four_identical_tracker_points_are_refused_as_duplicates() {
        let same = vec![[10.0, 20.0, 30.0]; 4];
        let e = register(&four(), &same).unwrap_err();
        assert_eq!(
            e,
            RegistrationError::Duplicate {
                which: "tracker",
                first: 0,
                second: 1,
                distance_mm: 0.0
            }
        );
        assert!(
            e.to_string()
                .contains("tracker points 1 and 2 are identical"),
            "{e}"
        );
        // Two model points 0.4 mm apart: the same fiducial twice.
        let mut m = cube();
        m[5] = [0.4, 0.0, 0.0];
        let e = register(&m, &m).unwrap_err();
        assert!(
            matches!(e, RegistrationError::Duplicate { which: "model", first: 0, second: 5, distance_mm } if (distance_mm - 0.4).abs() < 1e-12),
            "{e}"
        );
    }

    #[test]
    fn tracker_points_in_cm_read_as_mm_are_named() {
        let q = UnitQuaternion::from_euler_angles(0.2, 0.1, -0.4);
        let t = Vector3::new(10.0, -80.0, 5.0);
        let cm: Vec<[f64; 3]> = moved(&cube(), q, t)
            .iter()
            .map(|p| p.map(|v| v / 10.0))
            .collect();
        let e = register(&cube(), &cm).unwrap_err();
        assert!(
            matches!(e, RegistrationError::Units { scale, .. } if (scale - 0.1).abs() < 1e-9),
            "{e}"
        );
        assert!(
            e.to_string().contains("the tracker points look like cm"),
            "{e}"
        );
        for (k, words) in [
            (0.001, "tracker points look like m "),
            (1.0 / 25.4, "tracker points look like inches"),
            (10.0, "model points look like cm"),
            (1000.0, "model points look like m "),
        ] {
            let b: Vec<[f64; 3]> = moved(&cube(), q, t)
                .iter()
                .map(|p| p.map(|v| v * k))
                .collect();
            let e = register(&cube(), &b).unwrap_err().to_string();
            assert!(e.contains(words), "{k}: {e}");
        }
        // 20 % too large names no unit; 3 % is a warning.
        let b: Vec<[f64; 3]> = cube().iter().map(|p| p.map(|v| v * 1.2)).collect();
        assert!(matches!(
            register(&cube(), &b),
            Err(RegistrationError::Scale { scale }) if (scale - 1.2).abs() < 1e-9
        ));
        let b: Vec<[f64; 3]> = cube().iter().map(|p| p.map(|v| v * 1.03)).collect();
        let r = register(&cube(), &b).unwrap();
        assert!((r.scale - 1.03).abs() < 1e-9);
        assert!(
            r.warnings
                .iter()
                .any(|w| w.contains("1.0300 times the size")),
            "{:?}",
            r.warnings
        );
    }

    #[test]
    fn collinear_tracker_points_are_refused_as_collinear_not_a_reflection() {
        let line: Vec<[f64; 3]> = (0..4).map(|i| [0.0, i as f64 * 40.0, 7.0]).collect();
        let e = register(&four(), &line).unwrap_err();
        assert!(
            matches!(
                e,
                RegistrationError::Collinear {
                    which: "tracker",
                    ..
                }
            ),
            "{e}"
        );
        let text = e.to_string();
        assert!(text.contains("tracker fiducials are collinear"), "{text}");
        assert!(!text.contains("reflection"), "{text}");
    }

    #[test]
    fn a_good_registration_passes_with_its_numbers() {
        // The battery's fixture: five fiducials, the model 80 mm posterior of the reference.
        let model = [
            [0.0, 0.0, 0.0],
            [100.0, 0.0, 0.0],
            [0.0, 120.0, 0.0],
            [0.0, 0.0, 90.0],
            [60.0, 40.0, 30.0],
        ];
        let tracker: Vec<[f64; 3]> = model.iter().map(|p| [p[0], p[1] - 80.0, p[2]]).collect();
        let r = register(&model, &tracker).unwrap();
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        assert!(r.fre_rms_mm < 1e-9);
        assert!(r.rotation.angle() < 1e-12);
        assert!((r.translation_mm - Vector3::new(0.0, -80.0, 0.0)).norm() < 1e-9);
        assert!((r.scale - 1.0).abs() < 1e-12);
        // RMS distance from the centroid (32, 32, 24): sqrt of the mean of |a - c|².
        let c = [32.0, 32.0, 24.0];
        let ss: f64 = model
            .iter()
            .map(|p| (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f64>())
            .sum();
        assert!((r.spread_mm - (ss / 5.0).sqrt()).abs() < 1e-9);
    }

    proptest! {
        #[test]
        fn any_rigid_motion_of_a_spread_set_is_recovered(
            ax in -3.2f64..3.2, ay in -1.5f64..1.5, az in -3.2f64..3.2,
            tx in -2000f64..2000.0, ty in -2000f64..2000.0, tz in -2000f64..2000.0,
        ) {
            let q = UnitQuaternion::from_euler_angles(ax, ay, az);
            let t = Vector3::new(tx, ty, tz);
            let r = register(&cube(), &moved(&cube(), q, t)).unwrap();
            prop_assert!(r.rotation.angle_to(&q) < 1e-9);
            prop_assert!((r.translation_mm - t).norm() < 1e-6);
            prop_assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        }

        #[test]
        fn noise_within_the_localisation_error_is_accepted_and_a_scale_beyond_5_percent_is_not(
            ax in -3.2f64..3.2, ay in -1.5f64..1.5, az in -3.2f64..3.2,
            noise in proptest::collection::vec(-0.5f64..0.5, 18),
            scale in 0.5f64..2.0,
        ) {
            let q = UnitQuaternion::from_euler_angles(ax, ay, az);
            let t = Vector3::new(5.0, -700.0, 40.0);
            let mut b = moved(&cube(), q, t);
            for (k, e) in noise.iter().enumerate() {
                b[k / 3][k % 3] += e;
            }
            let r = register(&cube(), &b).unwrap();
            prop_assert!(r.fre_rms_mm < 0.9 && (r.scale - 1.0).abs() < SCALE_WARN);
            let scaled: Vec<[f64; 3]> = b.iter().map(|p| p.map(|v| v * scale)).collect();
            match register(&cube(), &scaled) {
                Ok(r) => prop_assert!((r.scale - 1.0).abs() <= SCALE_REFUSE + 0.01, "{}", r.scale),
                Err(e) => prop_assert!(
                    (scale - 1.0).abs() > SCALE_REFUSE - 0.01
                        && matches!(e, RegistrationError::Scale { .. } | RegistrationError::NoRigidFit { .. }),
                    "{scale}: {e}"
                ),
            }
        }
    }
}
