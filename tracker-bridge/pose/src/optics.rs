//! The HMD's optics: where each eye is relative to the HMD's tracked tool, and each eye's
//! projection. The renderer draws each eye with `projection · inverse(hmd_pose · eye_from_hmd)`
//! (`renderer::camera::Rig`).
//!
//! # Format (TOML, version 1)
//! ```toml
//! format = 1
//! [display]                 # per eye
//! width_px = 800
//! height_px = 600
//! horizontal_fov_deg = 70.0 # symmetric frusta; the vertical one follows from the aspect ratio
//! near_mm = 50.0
//! far_mm = 10000.0
//! [eyes]
//! ipd_mm = 64.0             # interpupillary distance
//! # Optional, per eye: the eye's position (mm) and orientation (unit quaternion x, y, z, w) in
//! # the HMD tool's frame, and an asymmetric frustum as half-angles in degrees [left, right, down, up].
//! # Without them: the eyes at (∓ipd/2, 0, 0), looking along the tool's −Z with +Y up, and the
//! # symmetric frustum of the display section.
//! [eyes.left]
//! offset_mm = [-32.0, 0.0, 0.0]
//! rotation_xyzw = [0.0, 0.0, 0.0, 1.0]
//! frustum_deg = [35.0, 35.0, 27.7, 27.7]
//! [eyes.right]
//! offset_mm = [32.0, 0.0, 0.0]
//! ```
//! Every key but `format` may be left out; the defaults are the seed's HMD: 800 × 600 per eye, 70°
//! horizontal field of view, and a 64 mm IPD (the adult mean is 63–64 mm; Dodgson 2004).
//!
//! Loading checks ([`Optics::from_toml`], the one validation every reader uses: `lungdyn hmd check`,
//! `scene check`, `demo`, the renderer); NaN or infinity in any number is refused:
//! - resolution [`MIN_EYE_PX`]..=[`MAX_EYE_PX`] px per eye, what the renderer draws (as
//!   `[render] width/height`);
//! - horizontal field of view 10..170° (`display.horizontal_fov_deg`); every eye's frustum
//!   (given or derived from the display's aspect ratio) [`MIN_FOV_DEG`]..=[`MAX_FOV_DEG`] wide and
//!   high, half-angles −80..80°. The narrowest see-through HMDs show about 14° × 8°; a frustum of
//!   a fraction of a degree (0.001° was once accepted) shows nothing of a 300 mm lung at 1 m (17°)
//!   and draws an empty picture without a word; past 170° the projection's tangents blow up;
//! - [`MIN_NEAR_MM`] ≤ near < far ≤ 100 m, and far/near ≤ [`MAX_FAR_OVER_NEAR`]. The renderer's
//!   depth is a 32-bit float written as `d = f(z − n) / (z(f − n))`, so one depth step at distance
//!   `z` is about `2⁻²⁴ · z² / n`: 0.06 mm at 1 m for near = 1 mm, but 60 m for near = 1e-6 mm
//!   (accepted once: the depth test collapsed and back faces showed through). Nothing can be seen
//!   closer than an HMD's eye relief (about 10 mm) anyway. At far/near = 1e4 the step at the far
//!   plane is 0.06 % of its distance (6 mm at 10 m); the lungs are drawn within arm's reach, so a
//!   1 mm near plane needs no far plane beyond 10 m, and a larger ratio only coarsens the depth;
//! - IPD 40..85 mm (adult IPDs lie within 50–77 mm), eye offsets within 300 mm of the tool,
//!   rotations unit quaternions, and, when both eyes give their offsets, that their distance is
//!   the IPD within 1 mm (a file that says two things is refused). Unknown keys are refused.

use std::path::Path;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::Deserialize;

use crate::calib::{read_small, FileError};

/// Smallest per-eye image side, pixels (the renderer's smallest, as `[render] width/height`).
pub const MIN_EYE_PX: u32 = 16;
/// Largest per-eye image side, pixels (the renderer's largest, as `[render] width/height`).
pub const MAX_EYE_PX: u32 = 8192;
/// Nearest near plane, mm (see the module doc: depth precision).
pub const MIN_NEAR_MM: f64 = 1.0;
/// Largest far/near ratio (see the module doc: depth precision at the far plane).
pub const MAX_FAR_OVER_NEAR: f64 = 1e4;
/// Narrowest frustum, width or height, degrees.
pub const MIN_FOV_DEG: f64 = 5.0;
/// Widest frustum, width or height, degrees.
pub const MAX_FOV_DEG: f64 = 170.0;

/// One eye.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Eye {
    /// Eye position in the HMD tool's frame, mm.
    pub offset_mm: Vector3<f64>,
    /// Eye orientation in the HMD tool's frame (the eye looks along its −Z, +Y up).
    pub rotation: UnitQuaternion<f64>,
    /// Frustum tangents `[left, right, down, up]` (tan of the half-angles; left and down positive
    /// when the frustum extends that way).
    pub frustum_tan: [f64; 4],
}

/// The HMD's optics.
#[derive(Debug, Clone, PartialEq)]
pub struct Optics {
    /// Pixels per eye, horizontally.
    pub width_px: u32,
    /// Pixels per eye, vertically.
    pub height_px: u32,
    /// Near clipping distance, mm.
    pub near_mm: f64,
    /// Far clipping distance, mm.
    pub far_mm: f64,
    /// Interpupillary distance, mm.
    pub ipd_mm: f64,
    /// Left and right eye.
    pub eyes: [Eye; 2],
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    format: u32,
    #[serde(default)]
    display: DisplayText,
    #[serde(default)]
    eyes: EyesText,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct DisplayText {
    width_px: i64,
    height_px: i64,
    horizontal_fov_deg: f64,
    near_mm: f64,
    far_mm: f64,
}

impl Default for DisplayText {
    fn default() -> Self {
        DisplayText {
            width_px: 800,
            height_px: 600,
            horizontal_fov_deg: 70.0,
            near_mm: 50.0,
            far_mm: 10_000.0,
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct EyesText {
    ipd_mm: f64,
    left: EyeText,
    right: EyeText,
}

impl Default for EyesText {
    fn default() -> Self {
        EyesText {
            ipd_mm: 64.0,
            left: EyeText::default(),
            right: EyeText::default(),
        }
    }
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct EyeText {
    offset_mm: Option<[f64; 3]>,
    rotation_xyzw: Option<[f64; 4]>,
    frustum_deg: Option<[f64; 4]>,
}

impl Default for Optics {
    fn default() -> Self {
        Self::from_toml("format = 1", "built-in").expect("the defaults are valid")
    }
}

/// The display's size, field of view and depth range, each in the range the renderer draws.
fn check_display(d: &DisplayText, path: &str) -> Result<(), FileError> {
    let invalid = |field, reason: String| FileError::Invalid {
        path: path.into(),
        field,
        reason,
    };
    for (field, v) in [
        ("display.width_px", d.width_px),
        ("display.height_px", d.height_px),
    ] {
        if !(i64::from(MIN_EYE_PX)..=i64::from(MAX_EYE_PX)).contains(&v) {
            return Err(invalid(
                field,
                format!(
                    "{v} px is outside {MIN_EYE_PX}..={MAX_EYE_PX}, the per-eye sizes the \
                     renderer draws"
                ),
            ));
        }
    }
    if !(d.horizontal_fov_deg.is_finite() && (10.0..=170.0).contains(&d.horizontal_fov_deg)) {
        return Err(invalid(
            "display.horizontal_fov_deg",
            format!("{} is outside 10..170 degrees", d.horizontal_fov_deg),
        ));
    }
    if !(d.near_mm.is_finite()
        && d.far_mm.is_finite()
        && d.near_mm >= MIN_NEAR_MM
        && d.near_mm < d.far_mm
        && d.far_mm <= 100_000.0)
    {
        return Err(invalid(
            "display.near_mm/far_mm",
            format!(
                "need {MIN_NEAR_MM} <= near < far <= 100000 mm, got {:?} and {:?} (a near plane \
                 under {MIN_NEAR_MM} mm collapses the depth test: one depth step at 1 m would \
                 be {:.3e} mm)",
                d.near_mm,
                d.far_mm,
                depth_step_mm(d.near_mm, 1000.0)
            ),
        ));
    }
    if d.far_mm / d.near_mm > MAX_FAR_OVER_NEAR {
        return Err(invalid(
            "display.near_mm/far_mm",
            format!(
                "far/near = {:.3e} is above {MAX_FAR_OVER_NEAR:.0e}: the depth steps at the far \
                 plane would be {:.1} mm; raise near_mm or lower far_mm",
                d.far_mm / d.near_mm,
                depth_step_mm(d.near_mm, d.far_mm)
            ),
        ));
    }
    Ok(())
}

impl Optics {
    /// Parse and check an optics text (`path` names it in errors).
    pub fn from_toml(text: &str, path: &str) -> Result<Self, FileError> {
        let f: File = toml::from_str(text).map_err(|e| FileError::Syntax {
            path: path.into(),
            message: e.to_string(),
        })?;
        let invalid = |field, reason: String| FileError::Invalid {
            path: path.into(),
            field,
            reason,
        };
        if f.format != 1 {
            return Err(invalid(
                "format",
                format!("{} is not 1, the only version this build reads", f.format),
            ));
        }
        let d = &f.display;
        check_display(d, path)?;
        let ipd = f.eyes.ipd_mm;
        if !(ipd.is_finite() && (40.0..=85.0).contains(&ipd)) {
            return Err(invalid(
                "eyes.ipd_mm",
                format!("{ipd} is outside 40..85 mm (adult IPDs are 50-77 mm; is it in cm or m?)"),
            ));
        }
        let tan_h = (d.horizontal_fov_deg.to_radians() / 2.0).tan();
        let tan_v = tan_h * d.height_px as f64 / d.width_px as f64;
        let eye = |e: &EyeText, sign: f64, side: &'static str| -> Result<Eye, FileError> {
            let offset = e.offset_mm.unwrap_or([sign * ipd / 2.0, 0.0, 0.0]);
            let o = Vector3::from(offset);
            if !(o.iter().all(|v| v.is_finite()) && o.norm() <= 300.0) {
                return Err(invalid(
                    side_field(side, "offset_mm"),
                    format!("{offset:?} is not within 300 mm of the tool"),
                ));
            }
            let rotation = match e.rotation_xyzw {
                None => UnitQuaternion::identity(),
                Some([x, y, z, w]) => {
                    let q = Quaternion::new(w, x, y, z);
                    if !(q.norm().is_finite() && (q.norm() - 1.0).abs() <= 1e-3) {
                        return Err(invalid(
                            side_field(side, "rotation_xyzw"),
                            format!("|q| = {}: not a unit quaternion", q.norm()),
                        ));
                    }
                    UnitQuaternion::from_quaternion(q)
                }
            };
            let frustum_tan = match e.frustum_deg {
                None => [tan_h, tan_h, tan_v, tan_v],
                Some(a) => {
                    if !a
                        .iter()
                        .all(|v| v.is_finite() && (-80.0..=80.0).contains(v))
                    {
                        return Err(invalid(
                            side_field(side, "frustum_deg"),
                            format!("{a:?}: half-angles [left, right, down, up] must be within -80..80 degrees"),
                        ));
                    }
                    a.map(|v| v.to_radians().tan())
                }
            };
            let [l, r, dn, up] = frustum_tan.map(f64::atan);
            for (what, extent) in [
                ("wide", (l + r).to_degrees()),
                ("high", (dn + up).to_degrees()),
            ] {
                if !(MIN_FOV_DEG..=MAX_FOV_DEG).contains(&extent) {
                    let key = if e.frustum_deg.is_some() {
                        side_field(side, "frustum_deg")
                    } else {
                        "display (width_px, height_px, horizontal_fov_deg)"
                    };
                    return Err(invalid(
                        key,
                        format!(
                            "the {side} eye's frustum is {extent:.4} degrees {what}, outside \
                             {MIN_FOV_DEG}..{MAX_FOV_DEG}: a lung would not fit in it (or the \
                             projection blows up)"
                        ),
                    ));
                }
            }
            Ok(Eye {
                offset_mm: o,
                rotation,
                frustum_tan,
            })
        };
        let left = eye(&f.eyes.left, -1.0, "left")?;
        let right = eye(&f.eyes.right, 1.0, "right")?;
        if f.eyes.left.offset_mm.is_some() && f.eyes.right.offset_mm.is_some() {
            let apart = (left.offset_mm - right.offset_mm).norm();
            if (apart - ipd).abs() > 1.0 {
                return Err(invalid(
                    "eyes.left/right.offset_mm",
                    format!("the eyes are {apart:.1} mm apart but ipd_mm = {ipd}: the file says two things"),
                ));
            }
        }
        Ok(Optics {
            width_px: d.width_px as u32,
            height_px: d.height_px as u32,
            near_mm: d.near_mm,
            far_mm: d.far_mm,
            ipd_mm: ipd,
            eyes: [left, right],
        })
    }

    /// Read and check an optics file.
    pub fn load(path: &Path) -> Result<Self, FileError> {
        Self::from_toml(&read_small(path)?, &path.display().to_string())
    }

    /// Horizontal field of view of an eye, degrees.
    pub fn horizontal_fov_deg(&self, eye: usize) -> f64 {
        let t = self.eyes[eye].frustum_tan;
        (t[0].atan() + t[1].atan()).to_degrees()
    }

    /// Vertical field of view of an eye, degrees.
    pub fn vertical_fov_deg(&self, eye: usize) -> f64 {
        let t = self.eyes[eye].frustum_tan;
        (t[2].atan() + t[3].atan()).to_degrees()
    }

    /// The projection of an eye, column-major 4×4 (`m[col][row]`), right-handed view space looking
    /// along −Z, clip depth 0 (near) .. 1 (far) as wgpu and Vulkan use it.
    pub fn projection(&self, eye: usize) -> [[f32; 4]; 4] {
        frustum_projection(self.eyes[eye].frustum_tan, self.near_mm, self.far_mm)
    }
}

/// The projection of an asymmetric frustum with tangents `[left, right, down, up]` measured
/// outwards from the view direction, column-major 4×4 (`m[col][row]`), right-handed view space
/// looking along −Z, clip depth 0 (`near_mm`) .. 1 (`far_mm`) as wgpu and Vulkan use it (an optics
/// file's eye, or an OpenXR runtime's `XrFovf`).
pub fn frustum_projection(tan: [f64; 4], near_mm: f64, far_mm: f64) -> [[f32; 4]; 4] {
    let [l, r, d, u] = tan;
    let (n, f) = (near_mm, far_mm);
    // x_ndc = (2 x / (-z) - (r - l)) / (r + l) with tangents l, r measured outwards.
    let sx = 2.0 / (l + r);
    let sy = 2.0 / (d + u);
    let ox = (r - l) / (l + r);
    let oy = (u - d) / (d + u);
    let a = f / (n - f);
    let b = n * f / (n - f);
    [
        [sx as f32, 0.0, 0.0, 0.0],
        [0.0, sy as f32, 0.0, 0.0],
        [ox as f32, oy as f32, a as f32, -1.0],
        [0.0, 0.0, b as f32, 0.0],
    ]
}

/// One step of the 32-bit float depth buffer at distance `z_mm`, mm, for a near plane `near_mm`
/// (`2⁻²⁴ · z² / n`; see the module doc).
fn depth_step_mm(near_mm: f64, z_mm: f64) -> f64 {
    (-24f64).exp2() * z_mm * z_mm / near_mm
}

fn side_field(side: &str, key: &str) -> &'static str {
    match (side, key) {
        ("left", "offset_mm") => "eyes.left.offset_mm",
        ("left", "rotation_xyzw") => "eyes.left.rotation_xyzw",
        ("left", _) => "eyes.left.frustum_deg",
        (_, "offset_mm") => "eyes.right.offset_mm",
        (_, "rotation_xyzw") => "eyes.right.rotation_xyzw",
        _ => "eyes.right.frustum_deg",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn project(p: &[[f32; 4]; 4], v: [f32; 3]) -> [f32; 3] {
        let x = [v[0], v[1], v[2], 1.0];
        let c: Vec<f32> = (0..4)
            .map(|r| (0..4).map(|k| p[k][r] * x[k]).sum())
            .collect();
        [c[0] / c[3], c[1] / c[3], c[2] / c[3]]
    }

    #[test]
    fn the_defaults_are_the_seed_hmd() {
        let o = Optics::default();
        assert_eq!((o.width_px, o.height_px), (800, 600));
        assert!((o.horizontal_fov_deg(0) - 70.0).abs() < 1e-9);
        // tan(v/2) = tan(35°) · 600/800 → 55.4° vertical.
        assert!((o.vertical_fov_deg(1) - 55.41).abs() < 0.01);
        assert_eq!(o.eyes[0].offset_mm, Vector3::new(-32.0, 0.0, 0.0));
        assert_eq!(o.eyes[1].offset_mm, Vector3::new(32.0, 0.0, 0.0));
        let p = o.projection(0);
        let edge = project(&p, [(35f32).to_radians().tan() * 1000.0, 0.0, -1000.0]);
        assert!((edge[0] - 1.0).abs() < 1e-5, "{edge:?}");
        assert!(
            project(&p, [0.0, 0.0, -50.0])[2].abs() < 1e-5,
            "near plane at depth 0"
        );
        assert!(
            (project(&p, [0.0, 0.0, -10_000.0])[2] - 1.0).abs() < 1e-5,
            "far plane at depth 1"
        );
    }

    #[test]
    fn an_asymmetric_frustum_and_offsets_are_read() {
        let text = "format = 1\n[eyes]\nipd_mm = 60\n[eyes.left]\noffset_mm = [-30, 10, 5]\nfrustum_deg = [40, 30, 25, 30]\n[eyes.right]\noffset_mm = [30, 10, 5]\n";
        let o = Optics::from_toml(text, "hmd.toml").unwrap();
        assert!((o.horizontal_fov_deg(0) - 70.0).abs() < 1e-9);
        let p = o.projection(0);
        let left_edge = project(&p, [-(40f32).to_radians().tan() * 500.0, 0.0, -500.0]);
        assert!((left_edge[0] + 1.0).abs() < 1e-5);
    }

    #[test]
    fn the_limits_themselves_are_accepted() {
        let text = format!(
            "format = 1\n[display]\nwidth_px = {MIN_EYE_PX}\nheight_px = {MIN_EYE_PX}\n\
             near_mm = {MIN_NEAR_MM}\nfar_mm = {}\n[eyes.left]\nfrustum_deg = [2.5, 2.5, 2.5, 2.5]\n\
             [eyes.right]\nfrustum_deg = [80, 5, 80, -0.01]\n",
            MIN_NEAR_MM * MAX_FAR_OVER_NEAR
        );
        let o = Optics::from_toml(&text, "hmd.toml").unwrap();
        assert!((o.horizontal_fov_deg(0) - MIN_FOV_DEG).abs() < 1e-9);
        let p = o.projection(1);
        assert!(p.iter().flatten().all(|v| v.is_finite()));
        let big =
            format!("format = 1\n[display]\nwidth_px = {MAX_EYE_PX}\nheight_px = {MAX_EYE_PX}\n");
        assert!(Optics::from_toml(&big, "hmd.toml").is_ok());
    }

    #[test]
    fn bad_files_are_refused_with_the_key_named() {
        let cases = [
            ("format = 2", "format"),
            ("format = 1\n[display]\nwidth_px = 0", "width_px"),
            ("format = 1\n[display]\nhorizontal_fov_deg = 200", "horizontal_fov_deg"),
            ("format = 1\n[display]\nnear_mm = 100\nfar_mm = 50", "near_mm"),
            ("format = 1\n[eyes]\nipd_mm = 6.4", "in cm or m"),
            ("format = 1\n[eyes.left]\noffset_mm = [-40, 0, 0]\n[eyes.right]\noffset_mm = [40, 0, 0]", "two things"),
            ("format = 1\n[eyes.left]\nrotation_xyzw = [0, 0, 0, 3]", "rotation_xyzw"),
            ("format = 1\n[eyes.right]\nfrustum_deg = [-40, 30, 20, 20]", "frustum_deg"),
            ("format = 1\n[display]\nfov = 70", "unknown field"),
            // Issue 18's probe: each was accepted, and the picture collapsed or came out empty.
            ("format = 1\n[display]\nnear_mm = 1e-6", "collapses the depth test"),
            ("format = 1\n[display]\nnear_mm = 5e-324", "near_mm"),
            ("format = 1\n[display]\nnear_mm = 0.5", "near_mm"),
            ("format = 1\n[display]\nnear_mm = nan", "near_mm"),
            ("format = 1\n[display]\nnear_mm = 1\nfar_mm = 100000", "far/near"),
            ("format = 1\n[eyes.left]\nfrustum_deg = [0.0005, 0.0005, 20, 20]", "0.0010 degrees wide"),
            ("format = 1\n[eyes.right]\nfrustum_deg = [30, 30, 1, 1]", "degrees high"),
            ("format = 1\n[eyes.right]\nfrustum_deg = [30, 30, nan, 20]", "frustum_deg"),
            ("format = 1\n[eyes.left]\noffset_mm = [inf, 0, 0]", "offset_mm"),
            ("format = 1\n[eyes.left]\nrotation_xyzw = [nan, 0, 0, 1]", "rotation_xyzw"),
            ("format = 1\n[eyes]\nipd_mm = nan", "ipd_mm"),
            ("format = 1\n[display]\nhorizontal_fov_deg = inf", "horizontal_fov_deg"),
            ("format = 1\n[display]\nwidth_px = 15", "16..=8192"),
            ("format = 1\n[display]\nheight_px = 8193", "16..=8192"),
            ("format = 1\n[display]\nwidth_px = 16384", "16..=8192"),
            // A 16 × 8192 display with symmetric frusta: 70° wide but over 170° high.
            ("format = 1\n[display]\nwidth_px = 16\nheight_px = 8192", "degrees high"),
        ];
        for (text, needle) in cases {
            let e = Optics::from_toml(text, "hmd.toml").unwrap_err().to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
    }
}
