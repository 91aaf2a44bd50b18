//! Validation of every sample before it may become a tool's pose: finite numbers, a rotation that
//! is one, inside the tracking volume, an acceptable RMS fit error, and what the device itself said
//! (missing, out of volume, fault). Pure functions of the sample and the limits; no allocation.
//!
//! Frame-number gaps and repeats and staleness need the tool's history and are judged where the
//! history is kept ([`crate::assemble`]).
//!
//! ## The tracking volume
//! Poses are in the tracker's frame. The default for a real tracker is the seed's measurement
//! volume, a cone 1.5 m high with a 0.5 m base radius, placed the way NDI trackers report
//! positions: **apex at the tracker's origin (the camera), axis along the tracker's −Z** (NDI's
//! measurement volumes lie at negative z, in front of the camera). A point `(x, y, z)` is inside
//! when `0 ≤ −z ≤ height` and `√(x² + y²) ≤ radius · (−z) / height`. `--volume` replaces it with
//! another cone (`cone:HEIGHT_MM,RADIUS_MM`), an axis-aligned box
//! (`box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`, mm) or `none`. The synthetic source's poses are in a room
//! frame that no camera cone describes (the HMD walks a 2 m ellipse round the bed), so `auto` means
//! `none` for it and the cone for every device source.

use glam::{Mat3, Quat};
use ipc_types::{tool_status, Pose};

use crate::sample::{Reject, Rotation, Sample};

/// Bits that make a tool not valid (`PARTIALLY_VISIBLE`, `FRAME_GAP` and `FRAME_REPEAT` only warn).
pub const REJECTING: u32 = tool_status::MISSING
    | tool_status::OUT_OF_VOLUME
    | tool_status::NON_FINITE
    | tool_status::NOT_ROTATION
    | tool_status::HIGH_RMS
    | tool_status::STALE
    | tool_status::DEVICE_FAULT;

/// Bits a device may report for a tool ([`Sample::device_flags`]).
pub const DEVICE_BITS: u32 = tool_status::MISSING
    | tool_status::OUT_OF_VOLUME
    | tool_status::PARTIALLY_VISIBLE
    | tool_status::DEVICE_FAULT;

/// Where poses may be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Volume {
    /// No limit.
    Unbounded,
    /// Apex at the origin, axis along −Z (see the module docs).
    Cone {
        /// Height along −Z, mm.
        height_mm: f32,
        /// Base radius at `height_mm`, mm.
        radius_mm: f32,
    },
    /// Axis-aligned box, mm.
    Box {
        /// Smallest corner.
        min_mm: [f32; 3],
        /// Largest corner.
        max_mm: [f32; 3],
    },
}

impl Volume {
    /// The seed's cone: 1.5 m high, 0.5 m radius.
    pub const SEED_CONE: Volume = Volume::Cone {
        height_mm: 1500.0,
        radius_mm: 500.0,
    };

    /// True when `p` (mm) is inside (non-finite points never are).
    pub fn contains(&self, p: [f32; 3]) -> bool {
        if !p.iter().all(|v| v.is_finite()) {
            return false;
        }
        match *self {
            Volume::Unbounded => true,
            Volume::Cone {
                height_mm,
                radius_mm,
            } => {
                let d = -f64::from(p[2]);
                let r = f64::from(p[0]).hypot(f64::from(p[1]));
                (0.0..=f64::from(height_mm)).contains(&d)
                    && r <= f64::from(radius_mm) * d / f64::from(height_mm)
            }
            Volume::Box { min_mm, max_mm } => {
                (0..3).all(|i| (min_mm[i]..=max_mm[i]).contains(&p[i]))
            }
        }
    }

    /// Parse `none`, `cone:H,R` or `box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX` (mm).
    pub fn parse(text: &str) -> Result<Volume, String> {
        let nums = |s: &str, n: usize| -> Result<Vec<f32>, String> {
            let v: Vec<f32> = s
                .split(',')
                .map(|x| {
                    x.trim()
                        .parse::<f32>()
                        .map_err(|_| format!("{x:?} is not a number"))
                })
                .collect::<Result<_, _>>()?;
            if v.len() != n || !v.iter().all(|x| x.is_finite()) {
                return Err(format!("expected {n} finite numbers (mm), got {s:?}"));
            }
            Ok(v)
        };
        let t = text.trim();
        if t.eq_ignore_ascii_case("none") {
            return Ok(Volume::Unbounded);
        }
        if let Some(rest) = t.strip_prefix("cone:") {
            let v = nums(rest, 2)?;
            if !(v[0] > 0.0 && v[1] > 0.0 && v[0] <= 20_000.0 && v[1] <= 20_000.0) {
                return Err(format!(
                    "cone height and radius must be within 0..20000 mm, got {rest:?}"
                ));
            }
            return Ok(Volume::Cone {
                height_mm: v[0],
                radius_mm: v[1],
            });
        }
        if let Some(rest) = t.strip_prefix("box:") {
            let v = nums(rest, 6)?;
            let (min_mm, max_mm) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
            if (0..3).any(|i| min_mm[i] >= max_mm[i]) {
                return Err(format!(
                    "box minimum must be below its maximum on every axis: {rest:?}"
                ));
            }
            return Ok(Volume::Box { min_mm, max_mm });
        }
        Err(format!(
            "{text:?} is not a volume: use none, cone:HEIGHT_MM,RADIUS_MM or \
             box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX"
        ))
    }

    /// The text [`Volume::parse`] reads back.
    pub fn to_text(&self) -> String {
        match self {
            Volume::Unbounded => "none".into(),
            Volume::Cone {
                height_mm,
                radius_mm,
            } => format!("cone:{height_mm},{radius_mm}"),
            Volume::Box { min_mm, max_mm } => format!(
                "box:{},{},{},{},{},{}",
                min_mm[0], min_mm[1], min_mm[2], max_mm[0], max_mm[1], max_mm[2]
            ),
        }
    }
}

/// Limits every sample is checked against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Validation {
    /// Largest accepted `| |q| − 1 |` of a quaternion.
    pub quat_tolerance: f32,
    /// Largest accepted entry of `RᵀR − I` and `|det R − 1|` of a matrix.
    pub matrix_tolerance: f32,
    /// RMS fit errors above this (mm) make the sample not valid.
    pub max_rms_mm: f32,
    /// Where poses may be.
    pub volume: Volume,
}

impl Default for Validation {
    fn default() -> Self {
        Validation {
            quat_tolerance: 1e-3,
            matrix_tolerance: 1e-3,
            max_rms_mm: 1.0,
            volume: Volume::SEED_CONE,
        }
    }
}

/// The outcome of checking one sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Verdict {
    /// [`tool_status`] bits found (never `VALID`): device bits plus the checks that failed.
    pub flags: u32,
    /// The most basic reason the sample is not usable, when it is not.
    pub reason: Option<Reject>,
    /// The pose to publish (unit quaternion), when the sample is usable.
    pub pose: Option<Pose>,
    /// The RMS error to publish (0 when the device gives none).
    pub rms_error_mm: f32,
}

/// A quaternion whose squared norm is this close to 1 is passed on bit for bit (float rounding of
/// a normalised quaternion); others within the tolerance are renormalised.
const UNIT_BY_ROUNDING: f64 = 1e-5;

impl Validation {
    /// Check a sample. The order of reasons (device said missing, device fault, non-finite, not a
    /// rotation, outside the volume, RMS) decides which one a rejected sample is counted under;
    /// `flags` holds all that apply.
    pub fn check(&self, s: &Sample) -> Verdict {
        let mut flags = s.device_flags & DEVICE_BITS;
        let rms = s.rms_error_mm.unwrap_or(0.0);
        let finite = s.translation_mm.iter().all(|v| v.is_finite())
            && rms.is_finite()
            && match s.rotation {
                Rotation::Quat(q) => q.iter().all(|v| v.is_finite()),
                Rotation::Matrix(m) => m.iter().flatten().all(|v| v.is_finite()),
                Rotation::None => true,
            };
        if !finite {
            flags |= tool_status::NON_FINITE;
        }
        let quat = if finite {
            self.rotation(&s.rotation)
        } else {
            None
        };
        if finite && quat.is_none() {
            flags |= tool_status::NOT_ROTATION;
        }
        if finite && flags & tool_status::MISSING == 0 && !self.volume.contains(s.translation_mm) {
            flags |= tool_status::OUT_OF_VOLUME;
        }
        if finite && rms > self.max_rms_mm {
            flags |= tool_status::HIGH_RMS;
        }
        let reason = if flags & tool_status::MISSING != 0 {
            Some(Reject::Missing)
        } else if flags & tool_status::DEVICE_FAULT != 0 {
            Some(Reject::DeviceFault)
        } else if flags & tool_status::NON_FINITE != 0 {
            Some(Reject::NonFinite)
        } else if flags & tool_status::NOT_ROTATION != 0 {
            Some(Reject::NotRotation)
        } else if flags & tool_status::OUT_OF_VOLUME != 0 {
            Some(Reject::OutOfVolume)
        } else if flags & tool_status::HIGH_RMS != 0 {
            Some(Reject::HighRms)
        } else {
            None
        };
        let pose = match (reason, quat) {
            (None, Some(q)) => Some(Pose {
                quat: q,
                translation_mm: s.translation_mm,
                _pad: 0,
            }),
            _ => None,
        };
        Verdict {
            flags,
            reason,
            pose,
            rms_error_mm: if rms.is_finite() { rms } else { 0.0 },
        }
    }

    /// The unit quaternion `[x, y, z, w]` of a rotation, or `None` when it is not one.
    pub fn rotation(&self, r: &Rotation) -> Option<[f32; 4]> {
        match *r {
            Rotation::None => None,
            Rotation::Quat(q) => {
                let n2: f64 = q.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
                let n = n2.sqrt();
                if !((n - 1.0).abs() <= f64::from(self.quat_tolerance)) {
                    return None;
                }
                if (n2 - 1.0).abs() <= UNIT_BY_ROUNDING {
                    Some(q)
                } else {
                    Some(q.map(|v| (f64::from(v) / n) as f32))
                }
            }
            Rotation::Matrix(m) => {
                let tol = f64::from(self.matrix_tolerance);
                let e = |r: usize, c: usize| f64::from(m[r][c]);
                for i in 0..3 {
                    for j in 0..3 {
                        // (RᵀR)_ij = Σ_k R_ki R_kj
                        let dot: f64 = (0..3).map(|k| e(k, i) * e(k, j)).sum();
                        let want = if i == j { 1.0 } else { 0.0 };
                        if !((dot - want).abs() <= tol) {
                            return None;
                        }
                    }
                }
                let det = e(0, 0) * (e(1, 1) * e(2, 2) - e(1, 2) * e(2, 1))
                    - e(0, 1) * (e(1, 0) * e(2, 2) - e(1, 2) * e(2, 0))
                    + e(0, 2) * (e(1, 0) * e(2, 1) - e(1, 1) * e(2, 0));
                if !((det - 1.0).abs() <= tol) {
                    return None;
                }
                let cols = Mat3::from_cols(
                    [m[0][0], m[1][0], m[2][0]].into(),
                    [m[0][1], m[1][1], m[2][1]].into(),
                    [m[0][2], m[1][2], m[2][2]].into(),
                );
                let q = Quat::from_mat3(&cols);
                let q = if q.is_normalized() { q } else { q.normalize() };
                Some(q.to_array())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::ToolName;

    fn sample(rotation: Rotation, t: [f32; 3]) -> Sample {
        Sample {
            rotation,
            ..Sample::quat(1, ToolName::new("T").unwrap(), [0.0, 0.0, 0.0, 1.0], t)
        }
    }

    const INSIDE: [f32; 3] = [10.0, -20.0, -1000.0];

    #[test]
    fn a_good_sample_passes_with_its_exact_values() {
        let v = Validation::default();
        let q = Quat::from_rotation_y(0.3).to_array();
        let out = v.check(&sample(Rotation::Quat(q), INSIDE));
        assert_eq!(out.reason, None);
        assert_eq!(out.flags, 0);
        assert_eq!(out.pose.unwrap().quat, q, "bit for bit");
        assert_eq!(out.pose.unwrap().translation_mm, INSIDE);
    }

    #[test]
    fn non_finite_values_anywhere_are_rejected() {
        let v = Validation::default();
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let out = v.check(&sample(Rotation::Quat([0.0, 0.0, bad, 1.0]), INSIDE));
            assert_eq!(out.reason, Some(Reject::NonFinite));
            assert!(out.pose.is_none());
            let out = v.check(&sample(
                Rotation::Quat([0.0, 0.0, 0.0, 1.0]),
                [0.0, bad, -900.0],
            ));
            assert_eq!(out.reason, Some(Reject::NonFinite));
            let mut s = sample(Rotation::Quat([0.0, 0.0, 0.0, 1.0]), INSIDE);
            s.rms_error_mm = Some(bad);
            assert_eq!(v.check(&s).reason, Some(Reject::NonFinite));
            let mut m = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            m[1][2] = bad;
            assert_eq!(
                v.check(&sample(Rotation::Matrix(m), INSIDE)).reason,
                Some(Reject::NonFinite)
            );
        }
    }

    #[test]
    fn quaternions_off_unit_length_are_renormalised_within_tolerance_and_refused_beyond() {
        let v = Validation::default();
        let near = v.check(&sample(Rotation::Quat([0.0, 0.0, 0.0, 1.0005]), INSIDE));
        assert_eq!(near.reason, None);
        assert_eq!(near.pose.unwrap().quat, [0.0, 0.0, 0.0, 1.0]);
        let far = v.check(&sample(Rotation::Quat([0.0, 0.0, 0.0, 1.01]), INSIDE));
        assert_eq!(far.reason, Some(Reject::NotRotation));
        assert_ne!(far.flags & tool_status::NOT_ROTATION, 0);
        let zero = v.check(&sample(Rotation::Quat([0.0; 4]), INSIDE));
        assert_eq!(zero.reason, Some(Reject::NotRotation));
        let none = v.check(&sample(Rotation::None, INSIDE));
        assert_eq!(none.reason, Some(Reject::NotRotation));
    }

    #[test]
    fn matrices_must_be_proper_rotations() {
        let v = Validation::default();
        let r = Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.2, -0.4, 1.1));
        let rows = |m: Mat3| {
            let c = m.to_cols_array_2d();
            [
                [c[0][0], c[1][0], c[2][0]],
                [c[0][1], c[1][1], c[2][1]],
                [c[0][2], c[1][2], c[2][2]],
            ]
        };
        let good = v.check(&sample(Rotation::Matrix(rows(r)), INSIDE));
        assert_eq!(good.reason, None);
        let q = Quat::from_array(good.pose.unwrap().quat);
        assert!(q.dot(Quat::from_mat3(&r)).abs() > 1.0 - 1e-6);
        // A reflection is orthonormal but has determinant −1.
        let mirror = v.check(&sample(
            Rotation::Matrix(rows(r * Mat3::from_diagonal([1.0, 1.0, -1.0].into()))),
            INSIDE,
        ));
        assert_eq!(mirror.reason, Some(Reject::NotRotation));
        // A scaled matrix (a transform with scale) is not orthonormal.
        let scaled = v.check(&sample(Rotation::Matrix(rows(r * 1.01)), INSIDE));
        assert_eq!(scaled.reason, Some(Reject::NotRotation));
        // A sheared one neither.
        let mut m = rows(r);
        m[0][1] += 0.01;
        assert_eq!(
            v.check(&sample(Rotation::Matrix(m), INSIDE)).reason,
            Some(Reject::NotRotation)
        );
    }

    #[test]
    fn the_seed_cone_has_its_apex_at_the_camera_and_opens_along_minus_z() {
        let c = Volume::SEED_CONE;
        assert!(c.contains([0.0, 0.0, -1.0]));
        assert!(c.contains([0.0, 0.0, -1500.0]));
        assert!(!c.contains([0.0, 0.0, -1500.1]), "beyond the height");
        assert!(!c.contains([0.0, 0.0, 10.0]), "behind the camera");
        assert!(c.contains([499.0, 0.0, -1500.0]));
        assert!(
            !c.contains([300.0, 300.0, -1200.0]),
            "outside the radius at that depth"
        );
        assert!(c.contains([0.0, 330.0, -1000.0]));
        assert!(!c.contains([0.0, 340.0, -1000.0]));
        let v = Validation::default();
        let out = v.check(&sample(
            Rotation::Quat([0.0, 0.0, 0.0, 1.0]),
            [0.0, 0.0, 100.0],
        ));
        assert_eq!(out.reason, Some(Reject::OutOfVolume));
    }

    #[test]
    fn volumes_parse_and_print_back() {
        for text in ["none", "cone:1500,500", "box:-1,-2,-3,4,5,6"] {
            let v = Volume::parse(text).unwrap();
            assert_eq!(Volume::parse(&v.to_text()).unwrap(), v);
        }
        assert!(Volume::parse("cone:0,5").is_err());
        assert!(Volume::parse("cone:1500").is_err());
        assert!(Volume::parse("box:1,1,1,0,2,2").is_err());
        assert!(Volume::parse("sphere:3").is_err());
        assert!(Volume::parse("cone:nan,4").is_err());
    }

    #[test]
    fn rms_above_the_threshold_and_device_reports_reject() {
        let v = Validation::default();
        let mut s = sample(Rotation::Quat([0.0, 0.0, 0.0, 1.0]), INSIDE);
        s.rms_error_mm = Some(1.5);
        assert_eq!(v.check(&s).reason, Some(Reject::HighRms));
        s.rms_error_mm = Some(0.2);
        s.device_flags = tool_status::PARTIALLY_VISIBLE;
        let partial = v.check(&s);
        assert_eq!(partial.reason, None, "partially visible only warns");
        assert_eq!(partial.flags, tool_status::PARTIALLY_VISIBLE);
        s.device_flags = tool_status::MISSING;
        assert_eq!(v.check(&s).reason, Some(Reject::Missing));
        s.device_flags = tool_status::OUT_OF_VOLUME;
        assert_eq!(v.check(&s).reason, Some(Reject::OutOfVolume));
        s.device_flags = tool_status::DEVICE_FAULT | tool_status::VALID;
        let f = v.check(&s);
        assert_eq!(f.reason, Some(Reject::DeviceFault));
        assert_eq!(
            f.flags & tool_status::VALID,
            0,
            "a device cannot claim VALID"
        );
    }
}
