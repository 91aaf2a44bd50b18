//! A synthetic optical tracker: a supine patient with slow, bounded orientation drift and an HMD
//! worn by someone walking around the bed at head height, looking at the patient's chest.
//!
//! Tracker (room) frame, millimetres: +Z up, the bed's long axis along +X (the patient's head at
//! +X), bed surface at z = 900 mm. The patient reference sits on the sternum; its pose is a rotation
//! of the patient's right-handed anatomical frame RAS (+X patient right, +Y anterior, +Z superior)
//! into the room: supine, RAS +X, +Y, +Z are room +Y, +Z, +X — the patient's right at room +Y,
//! their left at room −Y. The lung meshes' body frame (+X patient left) is the mirror of RAS in X
//! (`lung_model::frame::BODY_TO_RAS`): body +X is room −Y when supine.
//! Camera convention of the HMD pose: looks along its local −Z with +Y up (right-handed).
//!
//! A sample is a pure function of its frame number, so a synthetic session is exactly repeatable.

use glam::{Mat3, Quat, Vec3};
use ipc_types::{
    tool_status, HopStamps, Pose, ToolPose, TrackerFrame, LAYOUT_VERSION, TOOL_HMD, TOOL_PATIENT,
};

/// Sternum (patient reference) position at rest, room frame, mm.
pub const STERNUM_MM: Vec3 = Vec3::new(0.0, 0.0, 1120.0);
/// Height of the HMD wearer's eyes, mm.
pub const HEAD_HEIGHT_MM: f32 = 1600.0;

/// Parameters of the synthetic scene.
#[derive(Debug, Clone, Copy)]
pub struct Synthetic {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Peak patient rotation drift about each axis, degrees.
    pub drift_deg: f32,
    /// Seconds per walk around the bed.
    pub walk_period_s: f32,
    /// Roll sweep amplitude about the bed's long axis (room X), degrees (0: none).
    pub roll_deg: f32,
    /// Pitch sweep amplitude about the bed's cross axis (room Y), degrees (0: none).
    pub pitch_deg: f32,
    /// Seconds per roll/pitch sweep.
    pub sweep_period_s: f32,
    /// The patient's posture (a fixed turn before the drift and the sweeps).
    pub posture: Posture,
}

/// A patient's posture on the bed: the scene's `[tracker] posture`, the bridge's `--posture`.
pub use lungdyn_scene::tracker::Posture;

/// The room-frame turn of a posture from supine (head at +X, +Z up): sitting turns the head up
/// about the bed's cross axis, prone rolls 180° about its long axis, the lateral postures roll 90°
/// (left-lateral puts the patient's left side, room −Y when supine, down: +90° about room X).
pub fn posture_turn(posture: Posture) -> Quat {
    use std::f32::consts::{FRAC_PI_2, PI};
    match posture {
        Posture::Supine => Quat::IDENTITY,
        Posture::Sitting => Quat::from_rotation_y(-FRAC_PI_2),
        Posture::Prone => Quat::from_rotation_x(PI),
        Posture::LeftLateral => Quat::from_rotation_x(FRAC_PI_2),
        Posture::RightLateral => Quat::from_rotation_x(-FRAC_PI_2),
    }
}

impl Default for Synthetic {
    fn default() -> Self {
        Self {
            rate_hz: 60.0,
            drift_deg: 3.0,
            walk_period_s: 40.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            sweep_period_s: 20.0,
            posture: Posture::Supine,
        }
    }
}

/// Supine orientation: the RAS → room rotation (patient right → room Y, anterior → room Z (up),
/// superior → room X). Not the body frame's: body → room is this times `BODY_TO_RAS`.
pub fn supine() -> Quat {
    Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X))
}

/// A camera pose at `eye` looking at `target` with room +Z up, as a camera → room rotation.
pub fn look_at(eye: Vec3, target: Vec3) -> Quat {
    let forward = (target - eye).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    Quat::from_mat3(&Mat3::from_cols(right, up, -forward)).normalize()
}

fn pose(q: Quat, t: Vec3) -> Pose {
    Pose {
        quat: q.to_array(),
        translation_mm: t.to_array(),
        _pad: 0,
    }
}

impl Synthetic {
    /// Patient reference pose at time `t` seconds: supine with bounded drift (incommensurate periods
    /// so the motion never repeats exactly within a session, amplitude ≤ `drift_deg` per axis),
    /// turned by the roll and pitch sweeps (`roll_deg·sin(2πt/T)` about the bed's long axis, then
    /// `pitch_deg·cos(2πt/T)` about its cross axis).
    pub fn patient_pose(&self, t: f32) -> Pose {
        let a = self.drift_deg.to_radians();
        let tau = std::f32::consts::TAU;
        let phase = tau * t / self.sweep_period_s;
        let sweep = Quat::from_rotation_y(self.pitch_deg.to_radians() * phase.cos())
            * Quat::from_rotation_x(self.roll_deg.to_radians() * phase.sin());
        let drift = sweep
            * Quat::from_rotation_z(a * (tau * t / 23.0).sin())
            * Quat::from_rotation_x(0.7 * a * (tau * t / 31.0).sin())
            * Quat::from_rotation_y(0.5 * a * (tau * t / 37.0).sin());
        let shift = Vec3::new(
            4.0 * (tau * t / 29.0).sin(),
            3.0 * (tau * t / 41.0).sin(),
            0.0,
        );
        pose(
            (drift * posture_turn(self.posture) * supine()).normalize(),
            STERNUM_MM + shift,
        )
    }

    /// HMD pose at time `t`: walking an ellipse around the bed at head height, facing the chest
    /// (a point 80 mm below the sternum reference, where the lungs are).
    pub fn hmd_pose(&self, t: f32) -> Pose {
        let angle = std::f32::consts::TAU * t / self.walk_period_s - std::f32::consts::FRAC_PI_2;
        let eye = Vec3::new(1000.0 * angle.cos(), 750.0 * angle.sin(), HEAD_HEIGHT_MM);
        let target = STERNUM_MM - Vec3::new(0.0, 0.0, 80.0);
        pose(look_at(eye, target), eye)
    }

    /// The tracker frame with number `n` (its time is `n / rate`), capture stamp `capture_ns`.
    pub fn frame(&self, n: u64, capture_ns: u64) -> TrackerFrame {
        let t = (n as f64 / self.rate_hz) as f32;
        let mut tools = [ToolPose::default(); ipc_types::MAX_TOOLS];
        tools[TOOL_PATIENT] = ToolPose {
            tool_id: 1,
            status: tool_status::VALID,
            pose: self.patient_pose(t),
            rms_error_mm: 0.25,
            _pad: 0,
        };
        tools[TOOL_HMD] = ToolPose {
            tool_id: 2,
            status: tool_status::VALID,
            pose: self.hmd_pose(t),
            rms_error_mm: 0.35,
            _pad: 0,
        };
        TrackerFrame {
            layout_version: LAYOUT_VERSION,
            tool_count: 2,
            frame_number: n,
            stamps: HopStamps {
                capture_ns,
                ..HopStamps::default()
            },
            tools,
            signal: Default::default(),
        }
    }
}

/// Gravity in the body frame for the synthetic patient at `t`, as the engine computes it.
#[cfg(test)]
fn gravity_in_body_of(s: &Synthetic, t: f32) -> glam::DVec3 {
    let down = glam::DVec3::new(0.0, 0.0, -1.0);
    lung_model::orientation::gravity_in_body(s.patient_pose(t).quat, down).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patient_drift_is_slow_and_bounded() {
        let s = Synthetic::default();
        let rest = supine();
        let mut prev = Quat::from_array(s.patient_pose(0.0).quat);
        for i in 0..(600 * 60) {
            let q = Quat::from_array(s.patient_pose(i as f32 / 60.0).quat);
            assert!(q.is_normalized());
            assert!(q.angle_between(rest).to_degrees() <= 3.0 * 1.9, "bounded");
            // Small-angle form (2·asin|v| of the relative rotation): acos-based angles are too
            // coarse in f32 for per-frame steps of hundredths of a degree.
            let step_deg = (2.0 * (q * prev.inverse()).xyz().length().asin()).to_degrees();
            assert!(
                step_deg < 0.05,
                "slow: {step_deg} degrees in one 60 Hz frame"
            );
            prev = q;
        }
    }

    #[test]
    fn the_sweeps_turn_the_patient_onto_its_side_and_upright() {
        let s = Synthetic {
            drift_deg: 0.0,
            roll_deg: 90.0,
            pitch_deg: 90.0,
            sweep_period_s: 20.0,
            ..Default::default()
        };
        let gravity_in_body = |t: f32| gravity_in_body_of(&s, t);
        // t = 0: pitch 90° (roll 0): gravity along the body's long axis (sitting up / head down).
        assert!(
            gravity_in_body(0.0).z.abs() > 0.999,
            "{}",
            gravity_in_body(0.0)
        );
        // t = T/4: roll 90°, pitch 0: gravity across the body (lying on one side).
        assert!(
            gravity_in_body(5.0).x.abs() > 0.999,
            "{}",
            gravity_in_body(5.0)
        );
        // t = T/2: pitch −90°: the other end up.
        assert!(gravity_in_body(10.0).z * gravity_in_body(0.0).z < -0.99);
        // Without sweeps the patient stays supine: gravity towards the back.
        let still = Synthetic {
            drift_deg: 0.0,
            ..Default::default()
        };
        let g = gravity_in_body_of(&still, 7.0);
        assert!((g - glam::DVec3::new(0.0, -1.0, 0.0)).length() < 1e-6);
    }

    #[test]
    fn the_hmd_walks_around_the_bed_at_head_height_facing_the_patient() {
        let s = Synthetic::default();
        for i in 0..40 {
            let p = s.hmd_pose(i as f32);
            let eye = Vec3::from(p.translation_mm);
            assert!((eye.z - HEAD_HEIGHT_MM).abs() < 1e-3);
            assert!(eye.truncate().length() > 700.0, "stays off the bed");
            let forward = Quat::from_array(p.quat) * Vec3::NEG_Z;
            let to_chest = (STERNUM_MM - Vec3::new(0.0, 0.0, 80.0) - eye).normalize();
            assert!(forward.dot(to_chest) > 0.9999);
        }
    }

    #[test]
    fn a_sample_is_taken_at_its_frame_number_over_the_rate() {
        let at_60 = Synthetic::default();
        let at_120 = Synthetic {
            rate_hz: 120.0,
            ..Default::default()
        };
        // Frame 30 at 60 Hz and frame 60 at 120 Hz are both t = 0.5 s: the same poses.
        assert_eq!(at_60.frame(30, 5).tools, at_120.frame(60, 9).tools);
        // One frame later the patient and the HMD have moved.
        let (a, b) = (at_60.frame(30, 0), at_60.frame(31, 0));
        assert_ne!(a.tools[TOOL_HMD].pose, b.tools[TOOL_HMD].pose);
        assert_ne!(a.tools[TOOL_PATIENT].pose, b.tools[TOOL_PATIENT].pose);
        assert_eq!(b.frame_number, 31);
        assert_eq!(b.stamps.capture_ns, 0);
        assert!(b.tools[..2].iter().all(|t| t.status == tool_status::VALID));
    }
}

#[cfg(test)]
mod posture_tests {
    use super::*;

    /// Body axes in the room for each posture (body → room through the boundary reflection,
    /// `lung_model::frame`): sitting puts the feet (body −Z) down, prone the front (body +Y) down,
    /// left-lateral the patient's left (body +X) down, so the engine's gravity makes the left lung
    /// dependent. Before issue 19's fix left-lateral turned room +Y down, which is the patient's
    /// right side of a supine patient with the head at +X and the face up.
    #[test]
    fn each_posture_turns_the_body_as_named() {
        let still = |posture| Synthetic {
            drift_deg: 0.0,
            posture,
            ..Default::default()
        };
        let body_down = |p: Posture, v: Vec3| {
            let q = Quat::from_array(still(p).patient_pose(0.0).quat);
            (lung_model::frame::body_dir_to_room(q, v) - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-5
        };
        assert!(body_down(Posture::Supine, Vec3::new(0.0, -1.0, 0.0)));
        assert!(body_down(Posture::Sitting, Vec3::new(0.0, 0.0, -1.0)));
        assert!(body_down(Posture::Prone, Vec3::new(0.0, 1.0, 0.0)));
        assert!(body_down(Posture::LeftLateral, Vec3::new(1.0, 0.0, 0.0)));
        assert!(body_down(Posture::RightLateral, Vec3::new(-1.0, 0.0, 0.0)));
        // The engine's gravity, from the published pose: the dependent side is the one named.
        let g = |p: Posture| gravity_in_body_of(&still(p), 0.0);
        assert!((g(Posture::LeftLateral) - glam::DVec3::X).length() < 1e-6);
        assert!((g(Posture::RightLateral) + glam::DVec3::X).length() < 1e-6);
        assert!((g(Posture::Prone) - glam::DVec3::Y).length() < 1e-6);
        use clap::ValueEnum;
        let names: Vec<String> = Posture::value_variants()
            .iter()
            .map(|p| p.to_possible_value().unwrap().get_name().to_string())
            .collect();
        assert_eq!(
            names,
            [
                "supine",
                "sitting",
                "prone",
                "left-lateral",
                "right-lateral"
            ]
        );
        // The command line's names are the scene's (one type, one set of names).
        assert_eq!(names, Posture::ALL.map(|p| p.name()));
        for (name, p) in names.iter().zip(Posture::value_variants()) {
            assert_eq!(Posture::from_str(name, false), Ok(*p));
        }
        assert!(Posture::from_str("standing", false).is_err());
    }
}
