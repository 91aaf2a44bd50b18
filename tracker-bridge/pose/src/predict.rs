//! Pose prediction to the display time. A tracker sample is old when its frame is shown (a Polaris
//! Vega's own latency is about 14 ms, then transport, rendering and scan-out), and the head keeps
//! moving: drawing the HMD pose of the sample puts the overlay where the head was. A predictor sees
//! the samples as they arrive and gives the pose at a later time.
//!
//! Three predictors, all pure and allocation-free:
//! - [`Hold`]: the newest sample (no prediction; the baseline);
//! - [`ConstantVelocity`]: linear and angular velocity from the last two samples, extrapolated;
//! - [`AlphaBeta`]: an α-β filter on position (x, v) and on orientation (q, ω, the residual as a
//!   rotation vector), β = α²/(2 − α) (Benedict–Bordner: critically damped for a constant-velocity
//!   target); it smooths the measurement noise that a two-sample difference amplifies.
//!
//! [`evaluate`] replays a recorded sequence: after each sample, predict the pose `lookahead` later
//! and compare with the recorded pose at that time (interpolated between the two samples around
//! it: linear in position, slerp in rotation), giving translation (mm) and rotation (degrees) errors.
//! Which predictor to keep is decided by that measurement (see docs/TRACKERS.md's figures).

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

/// A pose at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedPose {
    /// Time, ns (any monotonic clock).
    pub t_ns: u64,
    /// Orientation.
    pub rotation: UnitQuaternion<f64>,
    /// Position, mm.
    pub position_mm: Vector3<f64>,
}

impl TimedPose {
    /// From the `[x, y, z, w]` quaternion and position of a tracker pose.
    pub fn from_xyzw(t_ns: u64, q: [f32; 4], p: [f32; 3]) -> Self {
        let q = Quaternion::new(
            f64::from(q[3]),
            f64::from(q[0]),
            f64::from(q[1]),
            f64::from(q[2]),
        );
        TimedPose {
            t_ns,
            rotation: UnitQuaternion::from_quaternion(q),
            position_mm: Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])),
        }
    }
}

/// Sees samples in order; predicts the pose at a later time.
pub trait Predictor {
    /// A short name for tables.
    fn name(&self) -> String;
    /// Take the next sample (times increasing).
    fn update(&mut self, s: &TimedPose);
    /// The pose at `t_ns` (not before the newest sample), once a sample was seen.
    fn predict(&self, t_ns: u64) -> Option<TimedPose>;
    /// Forget everything (a gap in the tracking).
    fn reset(&mut self);
}

fn secs(dt_ns: i128) -> f64 {
    dt_ns as f64 * 1e-9
}

/// The newest sample, unchanged.
#[derive(Debug, Clone, Default)]
pub struct Hold {
    last: Option<TimedPose>,
}

impl Predictor for Hold {
    fn name(&self) -> String {
        "none (newest sample)".into()
    }
    fn update(&mut self, s: &TimedPose) {
        self.last = Some(*s);
    }
    fn predict(&self, t_ns: u64) -> Option<TimedPose> {
        self.last.map(|p| TimedPose { t_ns, ..p })
    }
    fn reset(&mut self) {
        self.last = None;
    }
}

/// Velocities from the last two samples.
#[derive(Debug, Clone, Default)]
pub struct ConstantVelocity {
    last: Option<TimedPose>,
    velocity: Vector3<f64>,
    /// Angular velocity, rad/s, world frame (`q(t) = exp(ω t) q₀`).
    omega: Vector3<f64>,
}

impl Predictor for ConstantVelocity {
    fn name(&self) -> String {
        "constant velocity".into()
    }
    fn update(&mut self, s: &TimedPose) {
        if let Some(p) = self.last {
            let dt = secs(s.t_ns as i128 - p.t_ns as i128);
            if dt > 0.0 {
                self.velocity = (s.position_mm - p.position_mm) / dt;
                self.omega = (s.rotation * p.rotation.inverse()).scaled_axis() / dt;
            }
        }
        self.last = Some(*s);
    }
    fn predict(&self, t_ns: u64) -> Option<TimedPose> {
        let p = self.last?;
        let dt = secs(t_ns as i128 - p.t_ns as i128);
        Some(TimedPose {
            t_ns,
            rotation: UnitQuaternion::from_scaled_axis(self.omega * dt) * p.rotation,
            position_mm: p.position_mm + self.velocity * dt,
        })
    }
    fn reset(&mut self) {
        *self = Self::default();
    }
}

/// An α-β filter on position and orientation.
#[derive(Debug, Clone)]
pub struct AlphaBeta {
    /// Position and orientation gain, 0 < α ≤ 1 (1: trust each sample fully).
    pub alpha: f64,
    /// Velocity gain; [`AlphaBeta::new`] sets β = α²/(2 − α).
    pub beta: f64,
    state: Option<(
        u64,
        Vector3<f64>,
        Vector3<f64>,
        UnitQuaternion<f64>,
        Vector3<f64>,
    )>,
}

impl AlphaBeta {
    /// A filter with gain `alpha` and the critically damped `beta`.
    pub fn new(alpha: f64) -> Self {
        let alpha = alpha.clamp(1e-3, 1.0);
        AlphaBeta {
            alpha,
            beta: alpha * alpha / (2.0 - alpha),
            state: None,
        }
    }
}

impl Predictor for AlphaBeta {
    fn name(&self) -> String {
        format!("alpha-beta (alpha {:.2})", self.alpha)
    }
    fn update(&mut self, s: &TimedPose) {
        let Some((t0, x, v, q, w)) = self.state else {
            self.state = Some((
                s.t_ns,
                s.position_mm,
                Vector3::zeros(),
                s.rotation,
                Vector3::zeros(),
            ));
            return;
        };
        let dt = secs(s.t_ns as i128 - t0 as i128);
        if dt <= 0.0 {
            return;
        }
        let x_pred = x + v * dt;
        let q_pred = UnitQuaternion::from_scaled_axis(w * dt) * q;
        let rx = s.position_mm - x_pred;
        let rq = (s.rotation * q_pred.inverse()).scaled_axis();
        self.state = Some((
            s.t_ns,
            x_pred + rx * self.alpha,
            v + rx * (self.beta / dt),
            UnitQuaternion::from_scaled_axis(rq * self.alpha) * q_pred,
            w + rq * (self.beta / dt),
        ));
    }
    fn predict(&self, t_ns: u64) -> Option<TimedPose> {
        let (t0, x, v, q, w) = self.state?;
        let dt = secs(t_ns as i128 - t0 as i128);
        Some(TimedPose {
            t_ns,
            rotation: UnitQuaternion::from_scaled_axis(w * dt) * q,
            position_mm: x + v * dt,
        })
    }
    fn reset(&mut self) {
        self.state = None;
    }
}

/// Error statistics of one predictor at one look-ahead.
#[derive(Debug, Clone, PartialEq)]
pub struct Errors {
    /// Predictions compared.
    pub n: usize,
    /// Translation error, mm: mean, median, 95th, 99th percentile, maximum.
    pub translation_mm: Summary,
    /// Rotation error, degrees: the same.
    pub rotation_deg: Summary,
}

/// Mean, median, 95th and 99th percentile, maximum.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Summary {
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl Summary {
    /// Of a set of values (sorts them).
    pub fn of(v: &mut [f64]) -> Summary {
        if v.is_empty() {
            return Summary::default();
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Summary {
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p50: q(0.5),
            p95: q(0.95),
            p99: q(0.99),
            max: v[v.len() - 1],
        }
    }
}

/// The recorded pose at `t_ns`, interpolated between the samples around it (`None` outside the
/// sequence or across a gap longer than `max_gap_ns`).
pub fn pose_at(samples: &[TimedPose], t_ns: u64, max_gap_ns: u64) -> Option<TimedPose> {
    let i = samples.partition_point(|s| s.t_ns < t_ns);
    let b = samples.get(i)?;
    if b.t_ns == t_ns {
        return Some(*b);
    }
    let a = samples.get(i.checked_sub(1)?)?;
    if b.t_ns - a.t_ns > max_gap_ns {
        return None;
    }
    let f = (t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64;
    Some(TimedPose {
        t_ns,
        rotation: a.rotation.slerp(&b.rotation, f),
        position_mm: a.position_mm.lerp(&b.position_mm, f),
    })
}

/// Replay `samples` (times increasing) through `p`: after each, predict `lookahead_ns` ahead and
/// compare with the recorded pose then. A gap longer than `max_gap_ns` resets the predictor.
pub fn evaluate(
    samples: &[TimedPose],
    p: &mut dyn Predictor,
    lookahead_ns: u64,
    max_gap_ns: u64,
) -> Errors {
    p.reset();
    let (mut dt, mut dr) = (Vec::new(), Vec::new());
    let mut prev: Option<u64> = None;
    for s in samples {
        if prev.is_some_and(|t| s.t_ns.saturating_sub(t) > max_gap_ns || s.t_ns <= t) {
            p.reset();
        }
        prev = Some(s.t_ns);
        p.update(s);
        let target = s.t_ns + lookahead_ns;
        let (Some(truth), Some(guess)) = (pose_at(samples, target, max_gap_ns), p.predict(target))
        else {
            continue;
        };
        dt.push((guess.position_mm - truth.position_mm).norm());
        dr.push(guess.rotation.angle_to(&truth.rotation).to_degrees());
    }
    Errors {
        n: dt.len(),
        translation_mm: Summary::of(&mut dt),
        rotation_deg: Summary::of(&mut dr),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: u64 = 16_666_667;

    /// A head turning at 90°/s about Z while moving at 0.5 m/s along X.
    fn linear_motion(n: u64) -> Vec<TimedPose> {
        (0..n)
            .map(|k| {
                let t = k as f64 * P as f64 * 1e-9;
                TimedPose {
                    t_ns: k * P,
                    rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, (90f64 * t).to_radians()),
                    position_mm: Vector3::new(500.0 * t, 0.0, 1600.0),
                }
            })
            .collect()
    }

    #[test]
    fn constant_velocity_predicts_constant_motion_exactly_and_hold_lags_it() {
        let s = linear_motion(120);
        let hold = evaluate(&s, &mut Hold::default(), 2 * P, 50_000_000);
        let cv = evaluate(&s, &mut ConstantVelocity::default(), 2 * P, 50_000_000);
        assert_eq!(hold.n, 118);
        // 33 ms of 0.5 m/s and 90°/s.
        assert!((hold.translation_mm.mean - 16.67).abs() < 0.01, "{hold:?}");
        assert!((hold.rotation_deg.max - 3.0).abs() < 0.01);
        // Exact from the second sample on (the first has no velocity yet: it holds).
        assert!(
            cv.translation_mm.p99 < 1e-6 && cv.rotation_deg.p99 < 1e-6,
            "{cv:?}"
        );
        assert!((cv.translation_mm.max - hold.translation_mm.max).abs() < 1e-9);
    }

    #[test]
    fn alpha_beta_converges_on_constant_motion() {
        let s = linear_motion(600);
        let mut ab = AlphaBeta::new(0.5);
        let mut worst_late = 0.0f64;
        for (k, x) in s.iter().enumerate() {
            ab.update(x);
            if k >= 300 && k + 1 < s.len() {
                let p = ab.predict(x.t_ns + P).unwrap();
                worst_late = worst_late
                    .max((p.position_mm - s[k + 1].position_mm).norm())
                    .max(p.rotation.angle_to(&s[k + 1].rotation).to_degrees());
            }
        }
        assert!(
            worst_late < 1e-6,
            "after its transient it tracks constant velocity: {worst_late}"
        );
    }

    #[test]
    fn interpolation_and_gaps() {
        let s = linear_motion(3);
        let mid = pose_at(&s, P / 2, 50_000_000).unwrap();
        assert!((mid.position_mm.x - 500.0 * (P / 2) as f64 * 1e-9).abs() < 1e-9);
        assert!(pose_at(&s, 10 * P, 50_000_000).is_none());
        assert!(
            pose_at(&s, P / 2, P / 2).is_none(),
            "gap longer than allowed"
        );
    }
}
