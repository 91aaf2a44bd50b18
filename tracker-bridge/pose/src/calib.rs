//! The calibration file `lungdyn register` writes: where the lungs' model frame is relative to the
//! patient reference tool.
//!
//! # Format (TOML, version 2)
//! ```toml
//! format = 2
//! kind = "model-to-reference"
//! # p_reference = R · p_model_ras + t, millimetres. Model frame: the lung meshes' body frame (+X
//! # patient left, +Y anterior, +Z superior) in RAS, i.e. with X negated (p_model_ras = (−x, y, z),
//! # lung_model::frame::body_to_ras): the body frame is left-handed, the reference tool's is not, so
//! # only the RAS points can be moved onto it by a rotation. Reference frame: the patient reference
//! # tool's own frame, as the tracker reports the fiducials relative to it.
//! [transform]
//! rotation_xyzw = [0.0, 0.0, 0.0, 1.0]       # unit quaternion (x, y, z, w)
//! translation_mm = [0.0, -80.0, 0.0]
//! rotation_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]  # the same, row-major (optional; checked)
//! [registration]                               # how it was made (information; optional)
//! fiducials = 6
//! fre_rms_mm = 0.42
//! fre_mm = [0.3, 0.5, 0.4, 0.2, 0.6, 0.4]
//! spread_ratio = 0.61                          # σ₂/σ₁ of the centred model fiducials
//! warnings = []
//! model_points = "model.csv"
//! tracker_points = "tracker.csv"
//! ```
//! **Format 1** (before issue 19) was fitted to the body-frame points as they were, as if that frame
//! were right-handed: for a real patient's fiducials its best rigid fit is a reflection, and the
//! lungs it placed were a mirror image. It is refused with the fix: run `lungdyn register` again
//! with the same point files (the file's `[registration]` names them).
//!
//! Loading checks ([`Calibration::from_toml`], the one validation every reader uses: the renderer,
//! `scene check`, `demo`, `register` reading back what it writes): `format = 2`, the kind; a finite
//! quaternion within 1e-3 of unit length (renormalised); when the matrix is present, every entry
//! finite, the matrix a rotation — orthonormal (`|MᵀM − I|` ≤ [`ROTATION_TOLERANCE`] per entry)
//! with determinant +1 within [`ROTATION_TOLERANCE`] (a reflection, −1, is named) — and the
//! quaternion's rotation within [`ROTATION_TOLERANCE`] (a NaN in the matrix was once accepted);
//! the tolerance 1e-4 passes a matrix written to four decimals (rounding errors ≤ 5e-5) and is
//! 0.006° of rotation, 0.02 mm at 200 mm. A finite translation within [`MAX_TRANSLATION_MM`] (the
//! reference tool sits on the patient or the bed, about 2 m long; more is a unit slip or the
//! camera's frame); the `[registration]` numbers, when present, finite and not negative. Unknown
//! keys are refused (a typo must not be silently ignored). Files above 1 MiB are refused before
//! reading.

use std::path::Path;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::registration::Registration;

/// Largest deviation per entry of a rotation matrix from orthonormal, from determinant +1 and
/// from the quaternion's matrix (see the module doc).
pub const ROTATION_TOLERANCE: f64 = 1e-4;
/// Largest distance of the lungs' model origin from the reference tool, mm (see the module doc).
pub const MAX_TRANSLATION_MM: f64 = 2000.0;

/// Largest calibration or optics file read, bytes.
pub const MAX_FILE: u64 = 1 << 20;

/// A file that cannot be used.
#[derive(Debug, Error)]
pub enum FileError {
    /// It could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// It is not a regular file or too large.
    #[error("{path}: {reason}")]
    Unreadable {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// Not valid TOML of the expected shape.
    #[error("{path}: {message}")]
    Syntax {
        /// The file.
        path: String,
        /// The parser's message (with line and column).
        message: String,
    },
    /// A value is out of range or inconsistent.
    #[error("{path}: {field}: {reason}")]
    Invalid {
        /// The file.
        path: String,
        /// The key.
        field: &'static str,
        /// What is wrong and what is expected.
        reason: String,
    },
}

/// Read a small text file: a regular file of at most [`MAX_FILE`] bytes.
pub fn read_small(path: &Path) -> Result<String, FileError> {
    let name = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|source| FileError::Io {
        path: name.clone(),
        source,
    })?;
    if !meta.is_file() {
        return Err(FileError::Unreadable {
            path: name,
            reason: "is not a regular file".into(),
        });
    }
    if meta.len() > MAX_FILE {
        return Err(FileError::Unreadable {
            path: name,
            reason: format!("is {} bytes; at most {MAX_FILE} are read", meta.len()),
        });
    }
    std::fs::read_to_string(path).map_err(|source| FileError::Io { path: name, source })
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibFile {
    format: u32,
    kind: String,
    transform: TransformText,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    registration: Option<RegistrationText>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TransformText {
    rotation_xyzw: [f64; 4],
    translation_mm: [f64; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    rotation_matrix: Option<[[f64; 3]; 3]>,
}

/// How a calibration was made (kept in the file for the record).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegistrationText {
    /// Number of fiducials.
    pub fiducials: usize,
    /// RMS fiducial registration error, mm.
    pub fre_rms_mm: f64,
    /// Per-fiducial error, mm.
    pub fre_mm: Vec<f64>,
    /// σ₂/σ₁ of the centred model fiducials.
    pub spread_ratio: f64,
    /// Warnings given when it was made.
    pub warnings: Vec<String>,
    /// The model points file.
    #[serde(default)]
    pub model_points: String,
    /// The tracker points file.
    #[serde(default)]
    pub tracker_points: String,
}

/// The model → patient reference transform.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Rotation.
    pub rotation: UnitQuaternion<f64>,
    /// Translation, mm.
    pub translation_mm: Vector3<f64>,
    /// How it was made, when known.
    pub registration: Option<RegistrationText>,
}

/// The kind written and accepted.
pub const KIND: &str = "model-to-reference";

/// The format written and accepted (2: the model's points in RAS; see the module doc)."
pub const FORMAT: u32 = 2;

impl Calibration {
    /// From a registration of model fiducials onto fiducials measured in the reference's frame.
    pub fn from_registration(r: &Registration, model_points: &str, tracker_points: &str) -> Self {
        Calibration {
            rotation: r.rotation,
            translation_mm: r.translation_mm,
            registration: Some(RegistrationText {
                fiducials: r.fre_mm.len(),
                fre_rms_mm: r.fre_rms_mm,
                fre_mm: r.fre_mm.clone(),
                spread_ratio: r.spread_ratio(),
                warnings: r.warnings.clone(),
                model_points: model_points.into(),
                tracker_points: tracker_points.into(),
            }),
        }
    }

    /// The file text, with a comment saying what the numbers mean.
    pub fn to_toml(&self) -> String {
        let q = self.rotation.quaternion();
        let m = self.rotation.to_rotation_matrix();
        let m = m.matrix();
        let file = CalibFile {
            format: FORMAT,
            kind: KIND.into(),
            transform: TransformText {
                rotation_xyzw: [q.i, q.j, q.k, q.w],
                translation_mm: [
                    self.translation_mm.x,
                    self.translation_mm.y,
                    self.translation_mm.z,
                ],
                rotation_matrix: Some(std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))),
            },
            registration: self.registration.clone(),
        };
        format!(
            "# lungdyn calibration (format 2): the lungs' model frame in the patient reference tool's frame.\n\
             # p_reference = R * p_model_ras + t, millimetres; p_model_ras = the meshes' body-frame point (+X\n\
             # left, +Y anterior, +Z superior) with X negated (RAS). Written by `lungdyn register`; see\n\
             # tracker-bridge/pose/src/calib.rs.\n{}",
            toml::to_string(&file).unwrap_or_default()
        )
    }

    /// Parse and check a calibration text (`path` names it in errors).
    pub fn from_toml(text: &str, path: &str) -> Result<Self, FileError> {
        let f: CalibFile = toml::from_str(text).map_err(|e| FileError::Syntax {
            path: path.into(),
            message: e.to_string(),
        })?;
        let invalid = |field, reason: String| FileError::Invalid {
            path: path.into(),
            field,
            reason,
        };
        if f.format == 1 {
            return Err(invalid(
                "format",
                "1 is the format fitted to the mirrored body frame before issue 19's fix (its lungs \
                 were drawn as a mirror image of the patient): run `lungdyn register` again with the \
                 same point files to write format 2"
                    .into(),
            ));
        }
        if f.format != FORMAT {
            return Err(invalid(
                "format",
                format!(
                    "{} is not {FORMAT}, the only version this build reads",
                    f.format
                ),
            ));
        }
        if f.kind != KIND {
            return Err(invalid("kind", format!("{:?} is not {KIND:?}", f.kind)));
        }
        let [x, y, z, w] = f.transform.rotation_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let n = q.norm();
        if !(n.is_finite() && (n - 1.0).abs() <= 1e-3) {
            return Err(invalid(
                "transform.rotation_xyzw",
                format!("|q| = {n}: not a unit quaternion (x, y, z, w)"),
            ));
        }
        let rotation = UnitQuaternion::from_quaternion(q);
        let t = Vector3::from(f.transform.translation_mm);
        if !(t.iter().all(|v| v.is_finite()) && t.norm() <= MAX_TRANSLATION_MM) {
            return Err(invalid(
                "transform.translation_mm",
                format!(
                    "{:?} is not a finite offset within {MAX_TRANSLATION_MM} mm of the reference \
                     tool (millimetres expected; the tool is on the patient or the bed)",
                    f.transform.translation_mm
                ),
            ));
        }
        if let Some(m) = f.transform.rotation_matrix {
            check_rotation_matrix(&m, &rotation)
                .map_err(|reason| invalid("transform.rotation_matrix", reason))?;
        }
        if let Some(r) = &f.registration {
            let numbers = [r.fre_rms_mm, r.spread_ratio]
                .into_iter()
                .chain(r.fre_mm.iter().copied());
            if let Some(bad) = numbers.into_iter().find(|v| !(v.is_finite() && *v >= 0.0)) {
                return Err(invalid(
                    "registration",
                    format!("{bad} is not a finite, non-negative number (fre_rms_mm, fre_mm, spread_ratio)"),
                ));
            }
        }
        Ok(Calibration {
            rotation,
            translation_mm: t,
            registration: f.registration,
        })
    }

    /// Read and check a calibration file.
    pub fn load(path: &Path) -> Result<Self, FileError> {
        Self::from_toml(&read_small(path)?, &path.display().to_string())
    }

    /// Apply to a model point in RAS (the body-frame point with X negated), mm.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let b = self.rotation * Vector3::from(p) + self.translation_mm;
        [b.x, b.y, b.z]
    }
}

/// `Err` with the reason unless `m` (row-major) is finite, a rotation within
/// [`ROTATION_TOLERANCE`] and `q`'s rotation within it.
fn check_rotation_matrix(m: &[[f64; 3]; 3], q: &UnitQuaternion<f64>) -> Result<(), String> {
    if let Some(v) = m.iter().flatten().find(|v| !v.is_finite()) {
        return Err(format!("{v} is not a finite number"));
    }
    let mm = nalgebra::Matrix3::from_fn(|i, j| m[i][j]);
    let off = (mm.transpose() * mm - nalgebra::Matrix3::identity())
        .abs()
        .max();
    if off > ROTATION_TOLERANCE {
        return Err(format!(
            "not orthonormal: MᵀM differs from the identity by up to {off:.2e} (at most \
             {ROTATION_TOLERANCE:.0e})"
        ));
    }
    let det = mm.determinant();
    if (det - 1.0).abs() > ROTATION_TOLERANCE {
        return Err(format!(
            "determinant {det:.6}, not +1{}",
            if det < 0.0 {
                ": a reflection (a left-handed frame), not a rotation"
            } else {
                ""
            }
        ));
    }
    let worst = (mm - q.to_rotation_matrix().matrix()).abs().max();
    if worst > ROTATION_TOLERANCE {
        return Err(format!(
            "differs from rotation_xyzw by up to {worst:.2e}: the file was edited inconsistently"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_calibration_round_trips_through_its_file() {
        let c = Calibration {
            rotation: UnitQuaternion::from_euler_angles(0.1, 0.2, -0.3),
            translation_mm: Vector3::new(1.5, -80.0, 12.25),
            registration: None,
        };
        let text = c.to_toml();
        assert!(text.starts_with("# lungdyn calibration"));
        let back = Calibration::from_toml(&text, "c.toml").unwrap();
        assert!(back.rotation.angle_to(&c.rotation) < 1e-12);
        assert_eq!(back.translation_mm, c.translation_mm);
    }

    #[test]
    fn bad_files_are_refused_with_the_key_named() {
        let good = Calibration {
            rotation: UnitQuaternion::identity(),
            translation_mm: Vector3::zeros(),
            registration: None,
        }
        .to_toml();
        let cases = [
            (good.replace("format = 2", "format = 3"), "format"),
            (good.replace("format = 2", "format = 1"), "run `lungdyn register` again"),
            (
                good.replace("model-to-reference", "reference-to-model"),
                "kind",
            ),
            (
                good.replace(
                    "rotation_xyzw = [0.0, 0.0, 0.0, 1.0]",
                    "rotation_xyzw = [0.0, 0.0, 0.0, 2.0]",
                ),
                "rotation_xyzw",
            ),
            (
                good.replace(
                    "translation_mm = [0.0, 0.0, 0.0]",
                    "translation_mm = [0.0, 0.0, 9000.0]",
                ),
                "translation_mm",
            ),
            (
                good.replace("[1.0, 0.0, 0.0]", "[0.0, 1.0, 0.0]"),
                "rotation_matrix",
            ),
            (format!("{good}\nextra = 1\n"), "unknown field"),
            (
                format!("{good}\n[registration]\nfiducials = 4\nfre_rms_mm = nan\nfre_mm = [0.1]\nspread_ratio = 0.5\nwarnings = []\n"),
                "not a finite, non-negative number",
            ),
            // Issue 18's probe: a NaN in the matrix was accepted.
            (
                good.replace("[1.0, 0.0, 0.0]", "[nan, 0.0, 0.0]"),
                "NaN is not a finite number",
            ),
            (
                good.replace("[0.0, 0.0, 1.0]]", "[0.0, 0.0, -1.0]]"),
                "a reflection",
            ),
            (
                good.replace("[1.0, 0.0, 0.0]", "[1.01, 0.0, 0.0]"),
                "not orthonormal",
            ),
            (
                good.replace(
                    "rotation_xyzw = [0.0, 0.0, 0.0, 1.0]",
                    "rotation_xyzw = [nan, 0.0, 0.0, 1.0]",
                ),
                "rotation_xyzw",
            ),
            (
                good.replace(
                    "translation_mm = [0.0, 0.0, 0.0]",
                    "translation_mm = [0.0, inf, 0.0]",
                ),
                "translation_mm",
            ),
            (
                good.replace(
                    "translation_mm = [0.0, 0.0, 0.0]",
                    "translation_mm = [0.0, 2500.0, 0.0]",
                ),
                "within 2000 mm",
            ),
            ("format = ".to_string(), "c.toml"),
        ];
        for (text, needle) in cases {
            let e = Calibration::from_toml(&text, "c.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
    }
}
