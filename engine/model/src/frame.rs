//! # frame: the body frame's handedness, and the one reflection at the body ↔ room boundary
//!
//! The model's data (meshes, kernels, landmarks, the physics' normalised axes) live in the **body
//! frame**, millimetres: **+X patient left, +Y anterior, +Z superior**. Physically that frame is
//! *left-handed*: patient-left × anterior points inferior, not superior. Every other frame a point
//! meets on its way to a person's eyes is right-handed and physical: the patient's anatomical frame
//! **RAS** (+X patient right, +Y anterior, +Z superior: 3D Slicer's, NIfTI's), DICOM/ITK's **LPS**
//! (+X left, +Y posterior, +Z superior), the patient reference tool's, the tracker's room, the HMD's
//! eyes.
//!
//! **Decision (lungdyn, issue 19).** The data frame stays as it is (changing it would flip every
//! lateral sign in the physics, the meshes, the kernels and their fixtures); the reflection is made
//! explicit and single-sourced here, at the body ↔ room boundary:
//!
//! * `p_ras = BODY_TO_RAS · p_body`, `BODY_TO_RAS = diag(−1, 1, 1)` ([`body_to_ras`],
//!   [`ras_to_body`]; it is its own inverse);
//! * a tracked patient pose (`ipc_types::Pose` of the patient reference) and a calibration
//!   (`lungdyn register`) are **rigid transforms of the right-handed RAS frame** into the room (or the
//!   reference tool): `body → room = pose · BODY_TO_RAS` ([`body_to_room`]). The renderer's model
//!   matrix, the engine's gravity in the body frame ([`crate::orientation::gravity_in_body`]) and
//!   the registration's fit all cross the boundary through this module;
//! * `body → room` therefore has determinant −1 ([`BODY_TO_RAS_DETERMINANT`]): a triangle wound
//!   counter-clockwise seen from outside in the body frame is clockwise seen from outside in the room,
//!   so the renderer takes its front face from that sign; normals transform by the same matrix (an
//!   orthogonal matrix is its own inverse transpose), so an outward normal stays outward.
//!
//! Imported data are converted into the body frame axis by axis: RAS by [`ras_to_body`], LPS by
//! [`lps_to_body`] (LPS → RAS negates X and Y). Those conversions are the same numbers as before
//! the reflection was named: they always were correct; what was wrong was treating body → room as
//! a rotation.

use glam::{DMat3, DVec3, Mat3, Mat4, Quat, Vec3};

/// Body → RAS (and RAS → body): negate X, the lateral axis.
pub const BODY_TO_RAS: DMat3 = DMat3::from_cols(
    DVec3::new(-1.0, 0.0, 0.0),
    DVec3::new(0.0, 1.0, 0.0),
    DVec3::new(0.0, 0.0, 1.0),
);

/// Determinant of [`BODY_TO_RAS`], hence of every body → room transform: the body frame is
/// left-handed.
pub const BODY_TO_RAS_DETERMINANT: f64 = -1.0;

/// [`BODY_TO_RAS`] in f32, as the renderer's homogeneous matrices use it.
pub const BODY_TO_RAS_F32: Mat3 = Mat3::from_cols(
    Vec3::new(-1.0, 0.0, 0.0),
    Vec3::new(0.0, 1.0, 0.0),
    Vec3::new(0.0, 0.0, 1.0),
);

/// A body-frame point or direction in RAS: [`BODY_TO_RAS`] applied as the sign change it is (no
/// multiply-adds: exactly `−x`, and an infinite Y or Z cannot turn X into NaN).
pub fn body_to_ras(p: DVec3) -> DVec3 {
    DVec3::new(-p.x, p.y, p.z)
}

/// A RAS point or direction in the body frame (the same sign change).
pub fn ras_to_body(p: DVec3) -> DVec3 {
    body_to_ras(p)
}

/// An LPS (DICOM/ITK) point or direction in the body frame: LPS → RAS negates X and Y, then
/// [`ras_to_body`] (together: Y negated).
pub fn lps_to_body(p: DVec3) -> DVec3 {
    ras_to_body(DVec3::new(-p.x, -p.y, p.z))
}

/// A body-frame point or direction in LPS (the inverse of [`lps_to_body`]).
pub fn body_to_lps(p: DVec3) -> DVec3 {
    let r = body_to_ras(p);
    DVec3::new(-r.x, -r.y, r.z)
}

/// `[f32; 3]` form of [`ras_to_body`] (mesh vertices).
pub fn ras_to_body_f32(p: [f32; 3]) -> [f32; 3] {
    [-p[0], p[1], p[2]]
}

/// `[f32; 3]` form of [`body_to_ras`] (mesh vertices sent to 3D Slicer).
pub fn body_to_ras_f32(p: [f32; 3]) -> [f32; 3] {
    [-p[0], p[1], p[2]]
}

/// `[f32; 3]` form of [`lps_to_body`] (mesh vertices).
pub fn lps_to_body_f32(p: [f32; 3]) -> [f32; 3] {
    ras_to_body_f32([-p[0], -p[1], p[2]])
}

/// The body → room matrix of a rigid RAS → room transform (`rotation`, `translation`, e.g. a
/// tracked pose times a calibration): `rigid · BODY_TO_RAS`. Its determinant is
/// [`BODY_TO_RAS_DETERMINANT`].
pub fn body_to_room(ras_to_room: Mat4) -> Mat4 {
    ras_to_room * Mat4::from_mat3(BODY_TO_RAS_F32)
}

/// A body-frame direction in the room for a patient pose (RAS → room rotation).
pub fn body_dir_to_room(pose: Quat, v: Vec3) -> Vec3 {
    pose * Vec3::from(ras_to_body_f32(v.to_array()))
}

/// A room direction in the body frame for a patient pose (RAS → room rotation, unit): the
/// inverse of [`body_dir_to_room`].
pub fn room_dir_to_body(pose: glam::DQuat, v: DVec3) -> DVec3 {
    ras_to_body(pose.inverse() * v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_body_frame_is_left_handed_and_body_to_room_is_a_reflection() {
        // Patient-left × anterior = inferior in the body frame's own coordinates, read physically:
        // in RAS, left (−X) × anterior (+Y) = −Z, inferior.
        let left = body_to_ras(DVec3::X);
        let anterior = body_to_ras(DVec3::Y);
        let superior = body_to_ras(DVec3::Z);
        assert_eq!(left, DVec3::new(-1.0, 0.0, 0.0));
        assert!((left.cross(anterior) + superior).length() < 1e-15);
        assert_eq!(BODY_TO_RAS.determinant(), BODY_TO_RAS_DETERMINANT);
        assert_eq!(
            BODY_TO_RAS_F32.determinant() as f64,
            BODY_TO_RAS_DETERMINANT
        );
        // Any rigid RAS → room transform gives body → room with determinant −1: a rotation alone
        // (the old model matrix) would be +1 and show a mirror-image patient.
        for q in [
            Quat::IDENTITY,
            Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X)),
            Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.2, 2.0),
        ] {
            let m = body_to_room(Mat4::from_rotation_translation(q, Vec3::new(1.0, 2.0, 3.0)));
            assert!((m.determinant() + 1.0).abs() < 1e-5, "{}", m.determinant());
            let v = Vec3::new(0.2, -0.7, 0.4);
            assert!((m.transform_vector3(v) - body_dir_to_room(q, v)).length() < 1e-6);
            let back = room_dir_to_body(q.as_dquat(), body_dir_to_room(q, v).as_dvec3());
            assert!((back - v.as_dvec3()).length() < 1e-6);
        }
    }

    #[test]
    fn imported_frames_land_on_the_same_body_point() {
        // A point 80 mm to the patient's left, 20 mm anterior, 150 mm superior of the origin:
        // body (80, 20, 150); RAS (−80, 20, 150); LPS (80, −20, 150).
        let body = DVec3::new(80.0, 20.0, 150.0);
        assert_eq!(ras_to_body(DVec3::new(-80.0, 20.0, 150.0)), body);
        assert_eq!(lps_to_body(DVec3::new(80.0, -20.0, 150.0)), body);
        assert_eq!(body_to_lps(body), DVec3::new(80.0, -20.0, 150.0));
        assert_eq!(body_to_ras(ras_to_body(body)), body);
        assert_eq!(ras_to_body_f32([-80.0, 20.0, 150.0]), [80.0, 20.0, 150.0]);
        assert_eq!(lps_to_body_f32([80.0, -20.0, 150.0]), [80.0, 20.0, 150.0]);
        // The functions are the matrix, exactly.
        for p in [body, DVec3::new(-0.5, 1e30, -3.0), DVec3::ZERO] {
            assert_eq!(body_to_ras(p), BODY_TO_RAS * p);
            assert_eq!(
                Vec3::from(ras_to_body_f32(p.as_vec3().to_array())),
                BODY_TO_RAS_F32 * p.as_vec3()
            );
        }
        // A sign change: an infinite coordinate stays in its own axis.
        let far = body_to_ras(DVec3::new(1.0, f64::INFINITY, 0.0));
        assert_eq!(far.x, -1.0);
    }
}
