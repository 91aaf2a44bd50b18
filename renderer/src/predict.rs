//! The HMD pose predicted to the frame's display time (issue: a tracker sample is ~14 ms old when
//! it leaves a Polaris Vega, and the head keeps moving while the frame is drawn and scanned out).
//!
//! [`HmdPredictor`] feeds each new HMD sample (with its capture time) to a constant-velocity
//! predictor (`tracker_pose::predict::ConstantVelocity`: linear and angular velocity from the last two
//! samples) and gives the pose at `draw time + look-ahead`. Measured on simulated bedside head motion
//! (`lungdyn tracker predict`, docs/TRACKERS.md): at 16 ms the mean error falls from 2.25 mm / 0.37° (newest
//! sample) to 0.29 mm / 0.09°, at 33 ms from 4.59 mm / 0.75° to 0.65 mm / 0.20°; the α-β filters
//! measured worse on that motion. Guards: no extrapolation from a sample older than
//! [`MAX_SAMPLE_AGE_NS`] or across a tracking gap (the newest pose is drawn instead), and a
//! non-finite or non-unit prediction is never drawn. Allocation-free.

use ipc_types::Pose;
use tracker_pose::predict::{ConstantVelocity, Predictor, TimedPose};

/// Samples older than this at draw time (ns) are not extrapolated: a stalled tracker must not fling
/// the view along its last velocity.
pub const MAX_SAMPLE_AGE_NS: u64 = 100_000_000;

/// Largest look-ahead accepted, ms.
pub const MAX_LOOKAHEAD_MS: f64 = 100.0;

/// The HMD pose at display time.
#[derive(Debug, Clone)]
pub struct HmdPredictor {
    predictor: ConstantVelocity,
    lookahead_ns: u64,
    last_frame: u64,
    last_capture_ns: u64,
    newest: Option<Pose>,
    /// Frames drawn with a predicted pose.
    pub predicted_frames: u64,
}

impl HmdPredictor {
    /// Predict `lookahead_ms` past the draw time (0: draw the newest sample).
    pub fn new(lookahead_ms: f64) -> Self {
        Self {
            predictor: ConstantVelocity::default(),
            lookahead_ns: (lookahead_ms.clamp(0.0, MAX_LOOKAHEAD_MS) * 1e6).round() as u64,
            last_frame: 0,
            last_capture_ns: 0,
            newest: None,
            predicted_frames: 0,
        }
    }

    /// A valid HMD sample of tracker frame `frame_number`, captured at `capture_ns`.
    pub fn update(&mut self, frame_number: u64, capture_ns: u64, pose: Pose) {
        if frame_number == self.last_frame && self.newest.is_some() {
            return;
        }
        if capture_ns <= self.last_capture_ns
            || capture_ns - self.last_capture_ns > MAX_SAMPLE_AGE_NS
        {
            // Time went backwards or the tracking had a gap: start again from this sample.
            self.predictor.reset();
        }
        self.predictor.update(&TimedPose::from_xyzw(
            capture_ns,
            pose.quat,
            pose.translation_mm,
        ));
        self.last_frame = frame_number;
        self.last_capture_ns = capture_ns;
        self.newest = Some(pose);
    }

    /// The pose to draw at `now_ns`; `fallback` until a sample arrived.
    pub fn pose_at(&mut self, now_ns: u64, fallback: Pose) -> Pose {
        let Some(newest) = self.newest else {
            return fallback;
        };
        if self.lookahead_ns == 0 || now_ns.saturating_sub(self.last_capture_ns) > MAX_SAMPLE_AGE_NS
        {
            return newest;
        }
        self.predicted(now_ns.max(self.last_capture_ns) + self.lookahead_ns, newest)
    }

    /// The pose to draw for a frame shown at `display_ns` (OpenXR's predicted display time, on the
    /// same clock as the samples): extrapolated to that instant rather than `--predict-ms` past the
    /// draw. The same guards as [`Self::pose_at`]: the newest sample when it is older than
    /// [`MAX_SAMPLE_AGE_NS`] at display time or the look-ahead would exceed [`MAX_LOOKAHEAD_MS`]
    /// (a display time far off is a runtime's mistake, not a reason to fling the view).
    pub fn pose_at_display(&mut self, display_ns: u64, fallback: Pose) -> Pose {
        let Some(newest) = self.newest else {
            return fallback;
        };
        let ahead = display_ns.saturating_sub(self.last_capture_ns);
        if ahead > MAX_SAMPLE_AGE_NS + (MAX_LOOKAHEAD_MS * 1e6) as u64 {
            return newest;
        }
        self.predicted(display_ns.max(self.last_capture_ns), newest)
    }

    fn predicted(&mut self, at_ns: u64, newest: Pose) -> Pose {
        let Some(p) = self.predictor.predict(at_ns) else {
            return newest;
        };
        let q = p.rotation.quaternion();
        let quat = [q.i as f32, q.j as f32, q.k as f32, q.w as f32];
        let translation_mm = [
            p.position_mm.x as f32,
            p.position_mm.y as f32,
            p.position_mm.z as f32,
        ];
        let norm = quat.iter().map(|v| v * v).sum::<f32>().sqrt();
        if !(quat.iter().chain(&translation_mm).all(|v| v.is_finite()) && (norm - 1.0).abs() < 1e-3)
        {
            return newest;
        }
        self.predicted_frames += 1;
        Pose {
            quat,
            translation_mm,
            _pad: 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f32, yaw: f32) -> Pose {
        let (s, c) = (yaw * 0.5).sin_cos();
        Pose {
            quat: [0.0, 0.0, s, c],
            translation_mm: [x, 0.0, 900.0],
            _pad: 0,
        }
    }

    #[test]
    fn steady_motion_is_extrapolated_to_the_display_time() {
        let mut p = HmdPredictor::new(16.0);
        // 100 mm/s along x and 0.5 rad/s of yaw, sampled at 60 Hz.
        let dt = 16_666_667u64;
        for k in 0..10u64 {
            let t = 1_000_000_000 + k * dt;
            let s = t as f32 * 1e-9 - 1.0;
            p.update(k + 1, t, pose(100.0 * s, 0.5 * s));
        }
        let last = 1_000_000_000 + 9 * dt;
        let drawn = p.pose_at(last + 2_000_000, pose(0.0, 0.0));
        // At last + 2 ms + 16 ms: x = 100 mm/s · (9·dt + 18 ms).
        let s = (9 * dt + 18_000_000) as f32 * 1e-9;
        let want = pose(100.0 * s, 0.5 * s);
        assert!(
            (drawn.translation_mm[0] - want.translation_mm[0]).abs() < 0.01,
            "{drawn:?}"
        );
        for a in 0..4 {
            assert!(
                (drawn.quat[a] - want.quat[a]).abs() < 1e-4,
                "{drawn:?} vs {want:?}"
            );
        }
        assert_eq!(p.predicted_frames, 1);
    }

    #[test]
    fn a_runtimes_display_time_is_the_instant_predicted_to() {
        let dt = 16_666_667u64;
        let sample = |k: u64| {
            let s = (1_000_000_000 + k * dt) as f32 * 1e-9 - 1.0;
            pose(100.0 * s, 0.5 * s)
        };
        let feed = |p: &mut HmdPredictor| {
            for k in 0..10u64 {
                p.update(k + 1, 1_000_000_000 + k * dt, sample(k));
            }
        };
        let last = 1_000_000_000 + 9 * dt;
        let (mut a, mut b) = (HmdPredictor::new(16.0), HmdPredictor::new(16.0));
        feed(&mut a);
        feed(&mut b);
        // Shown 18 ms after the last sample: the same pose as drawing 2 ms after it with 16 ms ahead.
        let at_display = a.pose_at_display(last + 18_000_000, pose(0.0, 0.0));
        assert_eq!(at_display, b.pose_at(last + 2_000_000, pose(0.0, 0.0)));
        assert_ne!(at_display, sample(9));
        // A display time seconds away (a runtime's bad clock) draws the newest sample.
        assert_eq!(
            a.pose_at_display(last + 5_000_000_000, pose(0.0, 0.0)),
            sample(9)
        );
        // Before any sample: the fallback.
        let mut none = HmdPredictor::new(16.0);
        assert_eq!(none.pose_at_display(last, pose(1.0, 0.0)), pose(1.0, 0.0));
    }

    #[test]
    fn a_stale_or_gapped_tracker_is_not_extrapolated() {
        let mut p = HmdPredictor::new(16.0);
        assert_eq!(p.pose_at(5, pose(1.0, 0.0)), pose(1.0, 0.0));
        p.update(1, 1_000_000_000, pose(0.0, 0.0));
        p.update(2, 1_016_000_000, pose(10.0, 0.0));
        // 200 ms later without a sample: the newest pose, not a 2 m fling.
        assert_eq!(p.pose_at(1_216_000_000, pose(0.0, 0.0)), pose(10.0, 0.0));
        // A gap restarts the velocity from the next two samples.
        p.update(3, 2_000_000_000, pose(500.0, 0.0));
        let drawn = p.pose_at(2_001_000_000, pose(0.0, 0.0));
        assert_eq!(drawn.translation_mm[0], 500.0);
        // Look-ahead 0: the newest sample.
        let mut p = HmdPredictor::new(0.0);
        p.update(1, 1_000, pose(3.0, 0.0));
        p.update(2, 2_000, pose(4.0, 0.0));
        assert_eq!(p.pose_at(2_500, pose(0.0, 0.0)), pose(4.0, 0.0));
    }
}
