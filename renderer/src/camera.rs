//! Registration and cameras: patient pose → model matrix, HMD pose → one or two eye views.
//!
//! Frames: the lung meshes are in the body frame (mm, +X left, +Y anterior, +Z superior), which is
//! left-handed; the patient reference (on the sternum) is tracked in the room frame, and its pose
//! (like a calibration) is a rigid transform of the patient's right-handed RAS frame. The model
//! matrix crosses from one to the other through `lung_model::frame::body_to_room` (the reflection
//! `BODY_TO_RAS = diag(−1, 1, 1)`, issue 19): its determinant is −1, so the draw pipelines take
//! clockwise as the front face ([`crate::draw::front_face`]). The HMD pose is a camera looking
//! along its local −Z with +Y up.
//!
//! A [`Rig`] says how the lungs and the eyes are placed:
//! * without a calibration, [`LUNGS_IN_REFERENCE_MM`] places the body-frame origin (the lungs'
//!   centre) relative to the reference, whose axes are taken as the patient's RAS axes; with the
//!   calibration `lungdyn register` writes (the model's RAS frame → patient reference,
//!   `tracker_pose::calib`), the model matrix is `patient_pose · calibration · BODY_TO_RAS`;
//! * without HMD optics, each eye sits ±IPD/2 along the HMD's +X with the scene's symmetric vertical
//!   field of view; with an optics file (`tracker_pose::optics`), each eye's view is
//!   `inverse(hmd_pose · eye_to_hmd)` (the file's offset and rotation) and its projection the
//!   file's asymmetric frustum with its near and far planes, at the file's per-eye resolution.
//!
//! A rig without files draws exactly as before they existed (same matrices, bit for bit).

use std::path::{Path, PathBuf};

use glam::{Mat4, Quat, Vec3, Vec4};
use ipc_types::Pose;
use lung_model::frame::body_to_room;
use lung_model::scene::RenderScene;
use tracker_pose::calib::{Calibration, FileError};
use tracker_pose::optics::Optics;

/// Where the lungs' body-frame origin lies relative to the sternal reference, in the reference's
/// (RAS-aligned) frame: 100 mm posterior and 30 mm inferior to the marker (no lateral offset, so the
/// same numbers in the body frame).
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
    /// Body → room (patient registration; determinant −1, see the module doc).
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

/// The body → room model matrix for a patient reference pose, without a calibration: the pose and
/// the fixed offset place the patient's RAS frame, [`body_to_room`] reflects the body frame into it.
pub fn model_matrix(patient: &Pose) -> Mat4 {
    body_to_room(pose_matrix(patient) * Mat4::from_translation(LUNGS_IN_REFERENCE_MM))
}

/// Eye uniforms for `hmd` (mono: one eye at the HMD; stereo: left then right eye) with the fixed
/// offset, the scene's IPD and vertical field of view: [`Rig::eyes`] of the default rig.
pub fn eyes(
    hmd: &Pose,
    patient: &Pose,
    stereo: bool,
    ipd_mm: f32,
    fov_y_deg: f32,
    aspect: f32,
    splat_mm: f32,
) -> ([EyeUniform; 2], usize) {
    Rig::default().eyes(hmd, patient, stereo, ipd_mm, fov_y_deg, aspect, splat_mm)
}

/// The per-eye image sides the renderer draws, pixels (as `[render] width/height`): the optics
/// file's own limits, checked where every reader loads it (`tracker_pose::optics`).
pub use tracker_pose::optics::{MAX_EYE_PX, MIN_EYE_PX};

/// How the lungs and the eyes are placed: the defaults, or a calibration and HMD optics.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Rig {
    /// The model's RAS frame (the meshes' body frame reflected, mm) → patient reference tool;
    /// `None`: the fixed [`LUNGS_IN_REFERENCE_MM`].
    pub calibration: Option<Mat4>,
    /// The HMD's eyes; `None`: the scene's IPD and vertical field of view.
    pub optics: Option<HmdEyes>,
}

/// The eyes of an HMD optics file, as matrices.
///
/// Mono (one image, `[render] stereo = false`) draws from a cyclopean eye: midway between the two
/// eyes' positions, halfway (slerp) between their orientations, with the mean of their frustum
/// tangents. For the usual mirror-image eyes (left eye wider to the left, right eye wider to the
/// right) that is a symmetric frustum of the same angular size as each eye, so the per-eye pixel
/// grid keeps its aspect and the image is centred between the eyes, where a bystander or a
/// recording expects it; the left eye's own frustum would look off-centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HmdEyes {
    /// Left and right eye → HMD tool frame (the file's offset and rotation).
    pub eye_to_hmd: [Mat4; 2],
    /// Left and right eye projection: the file's frustum, near and far, in wgpu clip space (Y up,
    /// depth 0 at near .. 1 at far, the convention of glam's `rh::proj::directx`).
    pub projection: [Mat4; 2],
    /// The mono (cyclopean) eye → HMD tool frame.
    pub mono_to_hmd: Mat4,
    /// The mono eye's projection.
    pub mono_projection: Mat4,
    /// Pixels per eye, horizontally.
    pub width: u32,
    /// Pixels per eye, vertically.
    pub height: u32,
}

/// A rotation (unit quaternion x, y, z, w) as f32, renormalised after the narrowing.
fn quat_f32([x, y, z, w]: [f64; 4]) -> Quat {
    Quat::from_xyzw(x as f32, y as f32, z as f32, w as f32).normalize()
}

fn vec_f32([x, y, z]: [f64; 3]) -> Vec3 {
    Vec3::new(x as f32, y as f32, z as f32)
}

/// `(rotation, position)` of a `tracker_pose` rigid transform (nalgebra, f64) in glam f32.
macro_rules! rigid {
    ($rotation:expr, $translation:expr) => {{
        let q = $rotation.quaternion();
        let t = $translation;
        (quat_f32([q.i, q.j, q.k, q.w]), vec_f32([t.x, t.y, t.z]))
    }};
}

impl HmdEyes {
    /// The matrices of a loaded (checked) optics file.
    pub fn from_optics(o: &Optics) -> Self {
        let [l, r] = &o.eyes;
        Self::from_eyes(
            [
                rigid!(l.rotation, l.offset_mm),
                rigid!(r.rotation, r.offset_mm),
            ],
            [l.frustum_tan, r.frustum_tan],
            o.near_mm,
            o.far_mm,
            o.width_px,
            o.height_px,
        )
    }

    /// From each eye's rotation and position in the HMD tool frame (mm) and frustum tangents
    /// `[left, right, down, up]` (an optics file's, or an OpenXR runtime's views), the mono eye
    /// derived as above.
    pub fn from_eyes(
        eyes: [(Quat, Vec3); 2],
        frustum_tan: [[f64; 4]; 2],
        near_mm: f64,
        far_mm: f64,
        width: u32,
        height: u32,
    ) -> Self {
        let [(ql, pl), (mut qr, pr)] = eyes;
        let eye_to_hmd = [
            Mat4::from_rotation_translation(ql, pl),
            Mat4::from_rotation_translation(qr, pr),
        ];
        let mid = (pl + pr) * 0.5;
        if ql.dot(qr) < 0.0 {
            qr = -qr;
        }
        let mono_rotation = ql.slerp(qr, 0.5).normalize();
        let [l, r] = frustum_tan;
        let mono_tan = std::array::from_fn(|k| 0.5 * (l[k] + r[k]));
        let projection = |t| {
            Mat4::from_cols_array_2d(&tracker_pose::optics::frustum_projection(
                t, near_mm, far_mm,
            ))
        };
        HmdEyes {
            eye_to_hmd,
            projection: [projection(l), projection(r)],
            mono_to_hmd: Mat4::from_rotation_translation(mono_rotation, mid),
            mono_projection: projection(mono_tan),
            width,
            height,
        }
    }
}

/// The model-RAS → reference matrix of a loaded (checked) calibration.
pub fn calibration_matrix(c: &Calibration) -> Mat4 {
    let (q, t) = rigid!(c.rotation, c.translation_mm);
    Mat4::from_rotation_translation(q, t)
}

impl Rig {
    /// The body → room model matrix for a patient reference pose (determinant −1).
    pub fn model(&self, patient: &Pose) -> Mat4 {
        match &self.calibration {
            Some(c) => body_to_room(pose_matrix(patient) * *c),
            None => model_matrix(patient),
        }
    }

    /// Pixels of one eye's image: the optics file's, else `[render] width/height`.
    pub fn eye_size(&self, settings: &RenderScene) -> (u32, u32) {
        match &self.optics {
            Some(o) => (o.width, o.height),
            None => (settings.width, settings.height),
        }
    }

    /// Eye uniforms for `hmd` (mono: one eye; stereo: left then right eye). Without optics the eyes
    /// sit ±`ipd_mm`/2 along the HMD's +X with a symmetric `fov_y_deg` and `aspect`; with optics
    /// those three are not used.
    #[allow(clippy::too_many_arguments)]
    pub fn eyes(
        &self,
        hmd: &Pose,
        patient: &Pose,
        stereo: bool,
        ipd_mm: f32,
        fov_y_deg: f32,
        aspect: f32,
        splat_mm: f32,
    ) -> ([EyeUniform; 2], usize) {
        let head = pose_matrix(hmd);
        let model = self.model(patient);
        let mut views = [(Mat4::IDENTITY, Mat4::IDENTITY); 2];
        let n = if stereo { 2 } else { 1 };
        match &self.optics {
            None => {
                // wgpu clip space: Y up, depth in [0, 1] — the "directx" convention of glam's
                // camera module.
                let proj = glam::camera::rh::proj::directx::perspective(
                    fov_y_deg.to_radians(),
                    aspect,
                    NEAR_MM,
                    FAR_MM,
                );
                let offsets: &[f32] = if stereo { &[-0.5, 0.5] } else { &[0.0] };
                for (v, &side) in views.iter_mut().zip(offsets) {
                    *v = (
                        head * Mat4::from_translation(Vec3::new(side * ipd_mm, 0.0, 0.0)),
                        proj,
                    );
                }
            }
            Some(o) if stereo => {
                for (i, v) in views.iter_mut().enumerate() {
                    *v = (head * o.eye_to_hmd[i], o.projection[i]);
                }
            }
            Some(o) => views[0] = (head * o.mono_to_hmd, o.mono_projection),
        }
        let mut out = [EyeUniform::zeroed(); 2];
        for (slot, &(eye_to_room, proj)) in out.iter_mut().zip(&views[..n]) {
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
        (out, n)
    }
}

/// A calibration or optics file the renderer cannot use; each names the key or flag that named it.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    /// The file is missing, unreadable or invalid (the loader's message names the file and field).
    #[error("{key}: {source}")]
    File {
        /// `[render] calibration`, `--calibration`, `[render] hmd` or `--hmd`.
        key: &'static str,
        /// The loader's error.
        source: FileError,
    },
}

/// The calibration and optics files a renderer uses, loaded and checked.
#[derive(Debug, Clone, Default)]
pub struct RigFiles {
    /// The calibration, where from, and the key or flag that named it.
    pub calibration: Option<(PathBuf, &'static str, Calibration)>,
    /// The optics, where from, and the key or flag that named it.
    pub optics: Option<(PathBuf, &'static str, Optics)>,
}

impl RigFiles {
    /// Load the files of `render` (`[render] calibration`, `[render] hmd`; paths as the scene
    /// resolved them), each replaced by its flag when given (`--calibration`, `--hmd`).
    pub fn load(
        render: &RenderScene,
        calibration_flag: Option<&Path>,
        hmd_flag: Option<&Path>,
    ) -> Result<Self, RigError> {
        let pick = |flag: Option<&Path>, scene: &Option<PathBuf>, fk, sk| match flag {
            Some(p) => Some((p.to_path_buf(), fk)),
            None => scene.as_ref().map(|p| (p.clone(), sk)),
        };
        let calibration = match pick(
            calibration_flag,
            &render.calibration,
            "--calibration",
            "[render] calibration",
        ) {
            Some((path, key)) => {
                let c =
                    Calibration::load(&path).map_err(|source| RigError::File { key, source })?;
                Some((path, key, c))
            }
            None => None,
        };
        let optics = match pick(hmd_flag, &render.hmd, "--hmd", "[render] hmd") {
            Some((path, key)) => {
                let o = Optics::load(&path).map_err(|source| RigError::File { key, source })?;
                Some((path, key, o))
            }
            None => None,
        };
        Ok(Self {
            calibration,
            optics,
        })
    }

    /// The matrices.
    pub fn rig(&self) -> Rig {
        Rig {
            calibration: self
                .calibration
                .as_ref()
                .map(|(_, _, c)| calibration_matrix(c)),
            optics: self
                .optics
                .as_ref()
                .map(|(_, _, o)| HmdEyes::from_optics(o)),
        }
    }

    /// What the files change, for a log line; empty without files.
    pub fn describe(&self) -> String {
        let mut s = String::new();
        if let Some((p, key, c)) = &self.calibration {
            let t = c.translation_mm;
            s += &format!(
                "; lungs placed by the calibration {} ({key}: model -> reference, {:.1} deg, [{:.1}, {:.1}, {:.1}] mm)",
                p.display(),
                c.rotation.angle().to_degrees(),
                t.x,
                t.y,
                t.z
            );
        }
        if let Some((p, key, o)) = &self.optics {
            s += &format!(
                "; eyes from the HMD optics {} ({key}): {}x{} px per eye from the file (overrides [render] width/height), \
                 IPD {} mm, frusta {:.1}x{:.1} deg, near {} mm, far {} mm (overrides [render] ipd_mm and fov_y_deg)",
                p.display(),
                o.width_px,
                o.height_px,
                o.ipd_mm,
                o.horizontal_fov_deg(0),
                o.vertical_fov_deg(0),
                o.near_mm,
                o.far_mm
            );
        }
        s
    }
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
        // Nor through a calibrated rig with optics, mono or stereo.
        let rig = Rig {
            calibration: Some(calibration_matrix(&calibration(
                [0.0, 0.0, 0.3826834, 0.9238795],
                [10.0, -80.0, 5.0],
            ))),
            optics: Some(HmdEyes::from_optics(&asymmetric_optics())),
        };
        for stereo in [false, true] {
            let (e, n) = rig.eyes(&bad, &bad, stereo, 63.0, 30.0, 1.0, 2.0);
            for u in &e[..n] {
                let m = [u.view_proj, u.model];
                assert!(m.iter().flatten().flatten().all(|v| v.is_finite()), "{u:?}");
                assert!(u.eye_pos.iter().all(|v| v.is_finite()), "{u:?}");
            }
        }
    }

    /// Issue 19: the body frame is left-handed, so body → room is a reflection (determinant −1)
    /// for every pose, with or without a calibration; a rotation (+1, the old model matrix) showed
    /// a mirror-image patient. The patient's left (body +X) of the synthetic supine patient (head
    /// at room +X, face up) is room −Y.
    #[test]
    fn body_to_room_reflects_the_left_handed_body_frame() {
        let supine = Quat::from_mat3(&glam::Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X));
        let patient = Pose {
            quat: supine.to_array(),
            translation_mm: [0.0, 0.0, 1120.0],
            _pad: 0,
        };
        let calibrated = Rig {
            calibration: Some(calibration_matrix(&calibration(
                [0.0, 0.0, 0.3826834, 0.9238795],
                [10.0, -80.0, 5.0],
            ))),
            optics: None,
        };
        for rig in [Rig::default(), calibrated] {
            let m = rig.model(&patient);
            assert!((m.determinant() + 1.0).abs() < 1e-4, "{}", m.determinant());
            assert_eq!(
                crate::draw::front_face(m.determinant() as f64),
                wgpu::FrontFace::Cw
            );
        }
        let left = model_matrix(&patient).transform_vector3(Vec3::X);
        assert!((left - Vec3::NEG_Y).length() < 1e-6, "{left}");
        assert_eq!(crate::draw::front_face(1.0), wgpu::FrontFace::Ccw);
    }

    /// A pose of a camera at `eye` looking at `target` with +Z up.
    fn look_at(eye: Vec3, target: Vec3) -> Pose {
        let forward = (target - eye).normalize();
        let right = forward.cross(Vec3::Z).normalize();
        let up = right.cross(forward);
        let q = Quat::from_mat3(&glam::Mat3::from_cols(right, up, -forward));
        Pose {
            quat: q.to_array(),
            translation_mm: eye.to_array(),
            _pad: 0,
        }
    }

    fn calibration(xyzw: [f64; 4], t: [f64; 3]) -> Calibration {
        Calibration::from_toml(
            &format!(
                "format = 2\nkind = \"model-to-reference\"\n[transform]\nrotation_xyzw = {xyzw:?}\ntranslation_mm = {t:?}\n"
            ),
            "c.toml",
        )
        .unwrap()
    }

    /// Eyes 60 mm apart, 10 mm above and 5 mm behind the tool, the right eye turned 2° inwards;
    /// mirror-image asymmetric frusta (tangents differ on every side).
    fn asymmetric_optics() -> Optics {
        Optics::from_toml(
            "format = 1\n[display]\nwidth_px = 320\nheight_px = 200\nnear_mm = 40\nfar_mm = 8000\n\
             [eyes]\nipd_mm = 60\n\
             [eyes.left]\noffset_mm = [-30, 10, 5]\nfrustum_deg = [40, 30, 25, 32]\n\
             [eyes.right]\noffset_mm = [30, 10, 5]\nrotation_xyzw = [0, 0.0174524, 0, 0.9998477]\n\
             frustum_deg = [30, 40, 25, 32]\n",
            "hmd.toml",
        )
        .unwrap()
    }

    fn ndc(view_proj: &[[f32; 4]; 4], p: Vec3) -> Vec3 {
        let c = Mat4::from_cols_array_2d(view_proj) * p.extend(1.0);
        c.truncate() / c.w
    }

    #[test]
    fn a_calibration_equal_to_the_fixed_offset_draws_exactly_the_default() {
        let t = LUNGS_IN_REFERENCE_MM;
        let c = calibration([0.0, 0.0, 0.0, 1.0], [t.x as f64, t.y as f64, t.z as f64]);
        let rig = Rig {
            calibration: Some(calibration_matrix(&c)),
            optics: None,
        };
        let patient = look_at(Vec3::new(20.0, -30.0, 1100.0), Vec3::new(0.0, 400.0, 900.0));
        let hmd = look_at(
            Vec3::new(-250.0, -750.0, 1600.0),
            Vec3::new(-30.0, 0.0, 1020.0),
        );
        assert_eq!(rig.model(&patient), model_matrix(&patient));
        for stereo in [false, true] {
            assert_eq!(
                rig.eyes(&hmd, &patient, stereo, 63.0, 30.0, 4.0 / 3.0, 2.5),
                eyes(&hmd, &patient, stereo, 63.0, 30.0, 4.0 / 3.0, 2.5),
            );
        }
        // And a rig without files is the default, whatever the scene's size.
        let scene = RenderScene::default();
        assert_eq!(Rig::default().eye_size(&scene), (scene.width, scene.height));
    }

    #[test]
    fn a_calibrated_model_point_projects_where_the_calibration_and_pose_put_it() {
        // 45° about the model's Z, then (10, -80, 5) mm, on a patient lying turned in the room.
        let c = calibration([0.0, 0.0, 0.3826834, 0.9238795], [10.0, -80.0, 5.0]);
        let rig = Rig {
            calibration: Some(calibration_matrix(&c)),
            optics: None,
        };
        let patient = look_at(
            Vec3::new(100.0, 50.0, 1000.0),
            Vec3::new(400.0, 80.0, 700.0),
        );
        let p_model = [30.0, 40.0, -20.0];
        // The calibration moves the model's RAS point: the body point with X negated.
        let p_ras = lung_model::frame::body_to_ras(glam::DVec3::from(p_model)).to_array();
        let in_reference = Vec3::from(c.apply(p_ras).map(|v| v as f32));
        let expected = pose_matrix(&patient).transform_point3(in_reference);
        let got = rig
            .model(&patient)
            .transform_point3(Vec3::from(p_model.map(|v| v as f32)));
        assert!((got - expected).length() < 1e-3, "{got} vs {expected}");
        // p_reference = R p_ras + t by hand: R rotates (−30, 40) by 45°.
        let s = std::f32::consts::FRAC_1_SQRT_2;
        let by_hand = Vec3::new(s * (-30.0 - 40.0) + 10.0, s * (-30.0 + 40.0) - 80.0, -15.0);
        assert!((in_reference - by_hand).length() < 1e-3, "{in_reference}");
        // An HMD looking at it sees it at the image centre.
        let hmd = look_at(expected + Vec3::new(300.0, -1200.0, 600.0), expected);
        let (e, _) = rig.eyes(&hmd, &patient, false, 63.0, 30.0, 4.0 / 3.0, 2.0);
        let model = Mat4::from_cols_array_2d(&e[0].model);
        let q = ndc(
            &e[0].view_proj,
            model.transform_point3(Vec3::from(p_model.map(|v| v as f32))),
        );
        assert!(
            q.x.abs() < 1e-4 && q.y.abs() < 1e-4 && q.z > 0.0 && q.z < 1.0,
            "{q}"
        );
    }

    #[test]
    fn the_optics_projection_is_wgpus_clip_space() {
        // The seed HMD: symmetric, 70° horizontal at 800x600.
        let o = Optics::default();
        let mine = Mat4::from_cols_array_2d(&o.projection(0));
        let glams = glam::camera::rh::proj::directx::perspective(
            (o.vertical_fov_deg(0) as f32).to_radians(),
            800.0 / 600.0,
            o.near_mm as f32,
            o.far_mm as f32,
        );
        for (a, b) in mine.to_cols_array().iter().zip(glams.to_cols_array()) {
            assert!(
                (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                "{mine} vs {glams}"
            );
        }
    }

    #[test]
    fn optics_eyes_sit_at_their_offsets_and_their_frusta_fill_the_image() {
        let o = asymmetric_optics();
        let rig = Rig {
            calibration: None,
            optics: Some(HmdEyes::from_optics(&o)),
        };
        assert_eq!(rig.eye_size(&RenderScene::default()), (320, 200));
        let patient = look_at(Vec3::new(0.0, 0.0, 1000.0), Vec3::new(0.0, 500.0, 1000.0));
        let hmd = look_at(
            Vec3::new(-200.0, -900.0, 1500.0),
            Vec3::new(0.0, 0.0, 1000.0),
        );
        let head = pose_matrix(&hmd);
        // The scene's IPD and field of view are not used with optics.
        let (s, n) = rig.eyes(&hmd, &patient, true, 99.0, 10.0, 3.0, 2.0);
        assert_eq!(n, 2);
        for (i, eye) in o.eyes.iter().enumerate() {
            let off = eye.offset_mm;
            let offset = Vec3::new(off.x as f32, off.y as f32, off.z as f32);
            let at = Vec4::from(s[i].eye_pos).truncate();
            assert!(
                (at - head.transform_point3(offset)).length() < 1e-3,
                "eye {i}: {at}"
            );
            // Points on the eye's frustum edges, in the eye's own frame, reach NDC ±1; near and far
            // reach depth 0 and 1.
            let eye_to_room = head * rig.optics.unwrap().eye_to_hmd[i];
            let [l, r, d, u] = eye.frustum_tan.map(|v| v as f32);
            let z = 700.0;
            let cases = [
                (Vec3::new(-l * z, 0.0, -z), 0, -1.0),
                (Vec3::new(r * z, 0.0, -z), 0, 1.0),
                (Vec3::new(0.0, -d * z, -z), 1, -1.0),
                (Vec3::new(0.0, u * z, -z), 1, 1.0),
                (Vec3::new(0.0, 0.0, -40.0), 2, 0.0),
                (Vec3::new(0.0, 0.0, -8000.0), 2, 1.0),
            ];
            for (p, axis, want) in cases {
                let q = ndc(&s[i].view_proj, eye_to_room.transform_point3(p));
                assert!((q[axis] - want).abs() < 1e-4, "eye {i} {p}: {q}");
            }
        }
        // The eyes are the IPD apart along the HMD's right axis.
        let gap = Vec4::from(s[1].eye_pos).truncate() - Vec4::from(s[0].eye_pos).truncate();
        assert!((gap.length() - 60.0).abs() < 1e-3, "{gap}");
        assert!(gap.normalize().dot(head.transform_vector3(Vec3::X)) > 0.9999);
        // Mono: midway between the eyes, a symmetric frustum of the mean tangents (the centre of
        // the image straight ahead of it).
        let (m, n) = rig.eyes(&hmd, &patient, false, 99.0, 10.0, 3.0, 2.0);
        assert_eq!(n, 1);
        let mid = head.transform_point3(Vec3::new(0.0, 10.0, 5.0));
        assert!((Vec4::from(m[0].eye_pos).truncate() - mid).length() < 1e-3);
        let mono_to_room = head * rig.optics.unwrap().mono_to_hmd;
        let centre = ndc(
            &m[0].view_proj,
            mono_to_room.transform_point3(Vec3::new(0.0, 0.0, -900.0)),
        );
        let tan = |a: f32, b: f32| 0.5 * (a.to_radians().tan() + b.to_radians().tan());
        let half_h = tan(40.0, 30.0);
        let edge = ndc(
            &m[0].view_proj,
            mono_to_room.transform_point3(Vec3::new(half_h * 900.0, 0.0, -900.0)),
        );
        assert!(
            centre.x.abs() < 1e-4 && (edge.x - 1.0).abs() < 1e-4,
            "{centre} {edge}"
        );
        let up = ndc(
            &m[0].view_proj,
            mono_to_room.transform_point3(Vec3::new(0.0, tan(32.0, 32.0) * 900.0, -900.0)),
        );
        assert!((up.y - 1.0).abs() < 1e-4, "{up}");
    }

    #[test]
    fn rig_files_are_loaded_with_the_key_or_flag_named_and_flags_win() {
        let dir = std::env::temp_dir().join(format!("lungdyn-rig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good_c = dir.join("calib.toml");
        std::fs::write(
            &good_c,
            "format = 2\nkind = \"model-to-reference\"\n[transform]\nrotation_xyzw = [0, 0, 0, 1]\ntranslation_mm = [0, -80, 0]\n",
        )
        .unwrap();
        let good_h = dir.join("hmd.toml");
        std::fs::write(
            &good_h,
            "format = 1\n[display]\nwidth_px = 160\nheight_px = 120\n",
        )
        .unwrap();
        let garbage = dir.join("garbage.toml");
        std::fs::write(&garbage, "this is not a calibration\n").unwrap();
        let ipd500 = dir.join("ipd500.toml");
        std::fs::write(&ipd500, "format = 1\n[eyes]\nipd_mm = 500\n").unwrap();
        let tiny = dir.join("tiny.toml");
        std::fs::write(&tiny, "format = 1\n[display]\nwidth_px = 8\n").unwrap();
        let missing = dir.join("missing.toml");
        let scene = RenderScene {
            calibration: Some(good_c.clone()),
            hmd: Some(good_h.clone()),
            ..RenderScene::default()
        };
        let f = RigFiles::load(&scene, None, None).unwrap();
        assert_eq!(f.calibration.as_ref().unwrap().1, "[render] calibration");
        assert_eq!(f.optics.as_ref().unwrap().1, "[render] hmd");
        assert_eq!(f.rig().eye_size(&scene), (160, 120));
        let d = f.describe();
        assert!(
            d.contains("calib.toml") && d.contains("160x120 px per eye from the file"),
            "{d}"
        );
        // A flag replaces the scene's file.
        let f = RigFiles::load(&scene, Some(&good_c), None).unwrap();
        assert_eq!(f.calibration.as_ref().unwrap().1, "--calibration");
        assert!(RigFiles::load(&RenderScene::default(), None, None)
            .unwrap()
            .describe()
            .is_empty());
        let err = |c: Option<&Path>, h: Option<&Path>, s: &RenderScene| {
            RigFiles::load(s, c, h).unwrap_err().to_string()
        };
        let e = err(Some(&missing), None, &scene);
        assert!(
            e.starts_with("--calibration: ") && e.contains("missing.toml"),
            "{e}"
        );
        let e = err(Some(&garbage), None, &scene);
        assert!(
            e.contains("--calibration") && e.contains("garbage.toml"),
            "{e}"
        );
        let e = err(None, Some(&ipd500), &scene);
        assert!(e.contains("--hmd") && e.contains("eyes.ipd_mm"), "{e}");
        let in_scene = RenderScene {
            hmd: Some(ipd500.clone()),
            ..RenderScene::default()
        };
        let e = err(None, None, &in_scene);
        assert!(
            e.starts_with("[render] hmd: ") && e.contains("ipd500.toml"),
            "{e}"
        );
        let e = err(None, Some(&dir), &scene);
        assert!(
            e.contains("--hmd") && e.contains("not a regular file"),
            "{e}"
        );
        let e = err(None, Some(&tiny), &scene);
        assert!(
            e.contains("--hmd")
                && e.contains("display.width_px")
                && e.contains("8 px is outside 16..=8192"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }
}
