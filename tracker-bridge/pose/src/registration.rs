//! Point-based rigid registration of fiducials (Horn 1987 in its SVD form, Arun et al. 1987 /
//! Umeyama 1991 without scale): the rotation `R` and translation `t` that minimise
//! `Σ |R·a_i + t − b_i|²` over corresponding model points `a_i` and tracker points `b_i`.
//!
//! With centroids `ā`, `b̄` and `H = Σ (a_i − ā)(b_i − b̄)ᵀ = U Σ Vᵀ`, `R = V · diag(1, 1, d) · Uᵀ`
//! with `d = sign det(V Uᵀ)` (Umeyama's correction, so `R` is a rotation and never a reflection),
//! and `t = b̄ − R ā`.
//!
//! Reported with the fit: the fiducial registration error of every point `|R a_i + t − b_i|` and
//! their RMS (FRE); the singular values of the centred model points, whose ratio `σ₂/σ₁` says how
//! far the fiducials are from a line (near 0: the rotation about that line is not determined, and
//! a warning says so); whether the unconstrained optimum was a reflection (the point lists may be
//! mirrored: left and right swapped); points whose error is far above the RMS (a likely mismatched
//! pair).
//!
//! Note that a small FRE does not prove a small error at the target (TRE): Fitzpatrick, West and
//! Maurer (1998) show FRE and TRE are uncorrelated; spread the fiducials around the target.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use thiserror::Error;

/// Below this `σ₂/σ₁` the fiducials are reported as nearly collinear.
pub const COLLINEAR_RATIO: f64 = 0.1;
/// Below this `σ₂/σ₁` (or with all points at one place) the registration is refused.
pub const DEGENERATE_RATIO: f64 = 1e-6;

/// Why no registration could be computed.
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
    /// The points lie on one line (or at one place): the rotation is not determined.
    #[error(
        "the model fiducials are collinear (spread across their line {ratio:.2e} of the spread along it): \
         the rotation about that line is not determined; use fiducials that span a plane or a volume"
    )]
    Degenerate {
        /// σ₂/σ₁.
        ratio: f64,
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
    /// Human-readable warnings (collinear, reflection, outliers).
    pub warnings: Vec<String>,
}

impl Registration {
    /// `σ₂/σ₁` of the centred model points (0: collinear, 1: round spread in a plane or volume).
    pub fn spread_ratio(&self) -> f64 {
        if self.singular_values[0] > 0.0 {
            self.singular_values[1] / self.singular_values[0]
        } else {
            0.0
        }
    }

    /// Apply to a model point.
    pub fn apply(&self, a: [f64; 3]) -> [f64; 3] {
        let b = self.rotation * Vector3::from(a) + self.translation_mm;
        [b.x, b.y, b.z]
    }
}

/// Register `model` onto `tracker` (pairs by index).
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
    let ca = a.iter().sum::<Vector3<f64>>() / n as f64;
    let cb = b.iter().sum::<Vector3<f64>>() / n as f64;
    // Spread of the model points: singular values of the centred n×3 matrix = sqrt of the
    // eigenvalues of its scatter matrix.
    let scatter: Matrix3<f64> = a.iter().map(|p| (p - ca) * (p - ca).transpose()).sum();
    let mut ev: Vec<f64> = scatter
        .symmetric_eigenvalues()
        .iter()
        .map(|&l| l.max(0.0).sqrt())
        .collect();
    ev.sort_by(|x, y| y.total_cmp(x));
    let singular_values = [ev[0], ev[1], ev[2]];
    let ratio = if ev[0] > 0.0 { ev[1] / ev[0] } else { 0.0 };
    if ratio < DEGENERATE_RATIO {
        return Err(RegistrationError::Degenerate { ratio });
    }
    let h: Matrix3<f64> = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (p - ca) * (q - cb).transpose())
        .sum();
    let svd = h.svd(true, true);
    let (u, v_t) = (svd.u.expect("computed"), svd.v_t.expect("computed"));
    let v = v_t.transpose();
    let d = (v * u.transpose()).determinant();
    let mut warnings = Vec::new();
    let fix = if d < 0.0 {
        warnings.push(
            "the best unconstrained fit was a reflection: are the point lists mirrored (left and right \
             swapped, or one list in a left-handed frame)? The rotation given is the best proper one."
                .to_string(),
        );
        Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0))
    } else {
        Matrix3::identity()
    };
    let r = v * fix * u.transpose();
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let translation_mm = cb - rotation * ca;
    let fre_mm: Vec<f64> = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (rotation * p + translation_mm - q).norm())
        .collect();
    let fre_rms_mm = (fre_mm.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt();
    if ratio < COLLINEAR_RATIO {
        warnings.push(format!(
            "the model fiducials are nearly collinear (spread across their line is {:.1} % of the \
             spread along it): rotation about that line is poorly determined, and the error away from \
             the fiducials can be much larger than the FRE; add fiducials off that line",
            100.0 * ratio
        ));
    }
    if n == 3 {
        warnings.push(
            "3 fiducials fit any rigid motion almost exactly: the FRE says little; use 4 or more"
                .into(),
        );
    }
    // One bad pair inflates the RMS too (its error is at most √n times the RMS), so each point is
    // compared with the RMS of the others.
    let sum2: f64 = fre_mm.iter().map(|e| e * e).sum();
    for (i, e) in fre_mm.iter().enumerate() {
        let others = ((sum2 - e * e).max(0.0) / (n - 1) as f64).sqrt();
        if n >= 4 && *e > 1.0 && *e > 3.0 * others {
            warnings.push(format!(
                "point {} fits {e:.2} mm off, over 3 times the RMS of the others ({others:.2} mm): \
                 check that it is paired with the right fiducial",
                i + 1
            ));
        }
    }
    Ok(Registration {
        rotation,
        translation_mm,
        fre_mm,
        fre_rms_mm,
        singular_values,
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
    fn collinear_fiducials_are_refused_and_nearly_collinear_ones_warned() {
        let line: Vec<[f64; 3]> = (0..5).map(|i| [i as f64 * 10.0, 0.0, 0.0]).collect();
        assert!(matches!(
            register(&line, &line),
            Err(RegistrationError::Degenerate { .. })
        ));
        let mut near = line.clone();
        near[2][1] = 2.0;
        let r = register(&near, &near).unwrap();
        assert!(r.spread_ratio() < COLLINEAR_RATIO);
        assert!(
            r.warnings.iter().any(|w| w.contains("nearly collinear")),
            "{:?}",
            r.warnings
        );
    }

    #[test]
    fn a_mirrored_list_is_fitted_by_a_rotation_and_warned_about() {
        let mirrored: Vec<[f64; 3]> = cube().iter().map(|p| [-p[0], p[1], p[2]]).collect();
        let r = register(&cube(), &mirrored).unwrap();
        assert!(r.warnings.iter().any(|w| w.contains("reflection")));
        assert!((r.rotation.to_rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-12);
        assert!(r.fre_rms_mm > 1.0);
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
        let mut w = cube();
        w[4] = [500.0, 500.0, 500.0];
        let r = register(&cube(), &w).unwrap();
        assert!(
            r.warnings.iter().any(|x| x.contains("point 5")),
            "{:?}",
            r.warnings
        );
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
        }
    }
}
