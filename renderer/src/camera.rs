//! Registration and cameras: patient pose → model matrix, HMD pose → one or two eye views.
//!
//! Frames: the lung meshes are in the body frame (mm, +X left, +Y anterior, +Z superior); the
//! patient reference (on the sternum) is tracked in the room frame. [`LUNGS_IN_REFERENCE_MM`] places
//! the body-frame origin (the lungs' centre) relative to that reference. The HMD pose is a camera
//! looking along its local −Z with +Y up; each eye sits ±IPD/2 along the HMD's +X.

use glam::{Mat4, Quat, Vec3, Vec4};
use ipc_types::Pose;

/// Where the lungs' body-frame origin lies relative to the sternal reference, in the body frame:
/// 100 mm posterior and 30 mm inferior to the marker.
pub const LUNGS_IN_REFERENCE_MM: Vec3 = Vec3::new(0.0, -100.0, -30.0);
/// Near and far clip planes, mm.
pub const NEAR_MM: f32 = 50.0;
/// Far clip plane, mm.
pub const FAR_MM: f32 = 20_000.0;

/// The uniform block of `draw.wgsl`'s `Eye`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct EyeUniform {
    /// Projection × view.
    pub view_proj: [[f32; 4]; 4],
    /// Body → room (patient registration).
    pub model: [[f32; 4]; 4],
    /// Eye position in the room frame.
    pub eye_pos: [f32; 4],
    /// Camera right axis; w = splat radius (mm).
    pub cam_right: [f32; 4],
    /// Camera up axis.
    pub cam_up: [f32; 4],
}

/// A pose as a rigid transform; a non-finite or zero quaternion falls back to identity rotation
/// (the bridge flags such samples; this keeps a bad value from ever reaching a frame).
pub fn pose_matrix(p: &Pose) -> Mat4 {
    let q = Quat::from_array(p.quat);
    let q = if q.is_finite() && q.length_squared() > 1e-12 {
        q.normalize()
    } else {
        Quat::IDENTITY
    };
    let t = Vec3::from(p.translation_mm);
    let t = if t.is_finite() { t } else { Vec3::ZERO };
    Mat4::from_rotation_translation(q, t)
}

/// The body → room model matrix for a patient reference pose.
pub fn model_matrix(patient: &Pose) -> Mat4 {
    pose_matrix(patient) * Mat4::from_translation(LUNGS_IN_REFERENCE_MM)
}

/// Eye uniforms for `hmd` (mono: one eye at the HMD; stereo: left then right eye).
pub fn eyes(
    hmd: &Pose,
    patient: &Pose,
    stereo: bool,
    ipd_mm: f32,
    fov_y_deg: f32,
    aspect: f32,
    splat_mm: f32,
) -> ([EyeUniform; 2], usize) {
    let head = pose_matrix(hmd);
    let model = model_matrix(patient);
    // wgpu clip space: Y up, depth in [0, 1] — the "directx" convention of glam's camera module.
    let proj = glam::camera::rh::proj::directx::perspective(
        fov_y_deg.to_radians(),
        aspect,
        NEAR_MM,
        FAR_MM,
    );
    let offsets: &[f32] = if stereo { &[-0.5, 0.5] } else { &[0.0] };
    let mut out = [EyeUniform::zeroed(); 2];
    for (slot, &side) in out.iter_mut().zip(offsets) {
        let eye_to_room = head * Mat4::from_translation(Vec3::new(side * ipd_mm, 0.0, 0.0));
        let view = eye_to_room.inverse();
        let right = eye_to_room.transform_vector3(Vec3::X).normalize();
        let up = eye_to_room.transform_vector3(Vec3::Y).normalize();
        *slot = EyeUniform {
            view_proj: (proj * view).to_cols_array_2d(),
            model: model.to_cols_array_2d(),
            eye_pos: eye_to_room.w_axis.to_array(),
            cam_right: right.extend(0.5 * splat_mm).to_array(),
            cam_up: Vec4::from((up, 0.0)).to_array(),
        };
    }
    (out, offsets.len())
}

use bytemuck::Zeroable;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lungs_project_to_the_image_centre_when_the_hmd_looks_at_them() {
        let patient = Pose {
            quat: [0.0, 0.0, 0.0, 1.0],
            translation_mm: [0.0, 0.0, 1000.0],
            _pad: 0,
        };
        let lungs_room = model_matrix(&patient).transform_point3(Vec3::ZERO);
        let eye = lungs_room + Vec3::new(0.0, -1500.0, 500.0);
        let forward = (lungs_room - eye).normalize();
        let right = forward.cross(Vec3::Z).normalize();
        let up = right.cross(forward);
        let q = Quat::from_mat3(&glam::Mat3::from_cols(right, up, -forward));
        let hmd = Pose {
            quat: q.to_array(),
            translation_mm: eye.to_array(),
            _pad: 0,
        };
        let (e, n) = eyes(&hmd, &patient, false, 63.0, 40.0, 4.0 / 3.0, 2.0);
        assert_eq!(n, 1);
        let clip = Mat4::from_cols_array_2d(&e[0].view_proj) * lungs_room.extend(1.0);
        let ndc = clip.truncate() / clip.w;
        assert!(
            ndc.x.abs() < 1e-4 && ndc.y.abs() < 1e-4 && ndc.z > 0.0 && ndc.z < 1.0,
            "{ndc}"
        );
        // Stereo eyes sit IPD apart along the HMD's right axis.
        let (s, n) = eyes(&hmd, &patient, true, 63.0, 40.0, 4.0 / 3.0, 2.0);
        assert_eq!(n, 2);
        let gap = Vec4::from(s[1].eye_pos) - Vec4::from(s[0].eye_pos);
        assert!((gap.truncate().length() - 63.0).abs() < 1e-3);
        assert!(gap.truncate().normalize().dot(right) > 0.9999);
    }

    #[test]
    fn non_finite_poses_never_reach_the_matrices() {
        let bad = Pose {
            quat: [f32::NAN, 0.0, 0.0, 1.0],
            translation_mm: [f32::INFINITY, 0.0, 0.0],
            _pad: 0,
        };
        assert!(pose_matrix(&bad).is_finite());
    }
}
