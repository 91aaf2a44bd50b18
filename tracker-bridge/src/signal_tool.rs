//! A tracked tool on the chest as the respiratory signal (issue 35, `--breathing tool:NAME`): the
//! tool's position in the patient reference's frame, along the patient's anterior axis, in mm (+ =
//! inspiration: the chest wall rises). With `tool:NAME:auto` the axis is the one the tool itself
//! moves on, learnt from its first [`LEARN_S`] seconds ([`AxisLearner`]), for a reference not
//! mounted on the patient's RAS frame; no sample is sent while it is learnt. The patient reference's frame is the patient's RAS frame
//! (the pose the renderer registers the lungs with), so the patient's own motion on the table —
//! the reference and the chest tool moving together — is not breathing, and the axis is anatomical
//! wherever the tracker stands.
//!
//! The tool is tracked like any other (slot [`ipc_types::TOOL_CHEST`]: validation, staleness, gaps
//! and repeats). Each new measurement of the chest tool gives one sample stamped with its arrival
//! time; a measurement while the chest tool or the reference is not valid is sent flagged invalid
//! (value 0); a chest tool silent past the staleness bound sends one invalid sample per frame, so a
//! loss is seen by the engine as a loss and never as a held value. Nothing is allocated per frame.

use glam::{DQuat, DVec3};
use ipc_types::{signal_status, signal_unit, Pose, SignalBlock};

/// The patient's anterior axis in the patient reference's (RAS) frame.
pub const ANTERIOR: DVec3 = DVec3::new(0.0, 1.0, 0.0);

/// The chest tool's signal: what it last took and what it sent.
#[derive(Debug, Clone)]
pub struct ToolSignal {
    name: String,
    period_ns: u64,
    last_taken_ns: u64,
    describe: String,
    /// The axis learnt so far (`:auto`), and the learner (`None` along the anterior axis).
    learnt: Option<LearntAxis>,
    learner: Option<AxisLearner>,
    /// Samples sent.
    pub sent: u64,
    /// Of those, flagged invalid.
    pub invalid: u64,
    /// Valid measurements not sent while the axis was learnt.
    pub learning: u64,
}

/// One frame's view of the two tools: the chest tool's newest measurement (its arrival time and
/// whether the frame marks it valid and not stale) and the patient reference's pose when valid.
#[derive(Debug, Clone, Copy)]
pub struct ToolView {
    /// Arrival time of the chest tool's newest measurement, ns; 0 when never seen.
    pub chest_arrival_ns: u64,
    /// The chest tool's pose, when valid and not stale in this frame.
    pub chest: Option<Pose>,
    /// The patient reference's pose, when valid and not stale in this frame.
    pub patient: Option<Pose>,
    /// The chest tool is stale (silent past the staleness bound) or was never seen.
    pub chest_silent: bool,
}

impl ToolSignal {
    /// The signal of the tool named `name` at the bridge's `rate_hz` (its nominal period), read
    /// along `axis`.
    pub fn new(name: &str, rate_hz: f64, axis: AxisChoice) -> Self {
        let describe = match axis {
            AxisChoice::Anterior => {
                format!(
                    "the tracked tool {name:?} along the patient reference's anterior axis (mm)"
                )
            }
            AxisChoice::Auto => format!(
                "the tracked tool {name:?} along the axis it moves on, learnt from its first \
                 {LEARN_S:.0} s (mm)"
            ),
        };
        ToolSignal {
            name: name.to_string(),
            period_ns: (1e9 / rate_hz).round() as u64,
            last_taken_ns: 0,
            describe,
            learnt: None,
            learner: (axis == AxisChoice::Auto).then(AxisLearner::default),
            sent: 0,
            invalid: 0,
            learning: 0,
        }
    }

    /// The axis learnt from the tool's motion (`:auto`), once it is.
    pub fn learnt(&self) -> Option<LearntAxis> {
        self.learnt
    }

    /// The tool's name at the source.
    pub fn tool_name(&self) -> &str {
        &self.name
    }

    /// What it reads, for messages.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// The frame's sample (at most one) into `block`.
    pub fn fill(&mut self, now_ns: u64, view: &ToolView, block: &mut SignalBlock) {
        *block = SignalBlock {
            status: signal_status::CONFIGURED,
            unit: signal_unit::MM,
            period_ns: self.period_ns,
            ..Default::default()
        };
        let fresh = view.chest_arrival_ns != 0 && view.chest_arrival_ns != self.last_taken_ns;
        if fresh && !view.chest_silent {
            self.last_taken_ns = view.chest_arrival_ns;
            let relative = match (view.chest, view.patient) {
                (Some(chest), Some(patient)) => relative_mm(&chest, &patient),
                _ => None,
            };
            match (relative, self.axis()) {
                (Some(r), Some(axis)) => self.push(block, view.chest_arrival_ns, Some(r.dot(axis))),
                (Some(r), None) => self.learn(view.chest_arrival_ns, r),
                (None, _) => self.push(block, view.chest_arrival_ns, None),
            }
        } else if view.chest_silent {
            // A loss, said every frame while it lasts.
            self.push(block, now_ns, None);
        }
        if self.axis().is_none() {
            // Still learning the axis: the engine says so rather than "lost".
            block.status |= signal_status::LEARNING;
        }
    }

    /// The axis samples are read along: the anterior axis, the learnt one, or none yet.
    fn axis(&self) -> Option<DVec3> {
        match (&self.learner, &self.learnt) {
            (None, _) => Some(ANTERIOR),
            (Some(_), Some(a)) => Some(DVec3::from(a.axis)),
            (Some(_), None) => None,
        }
    }

    /// A valid measurement while the axis is learnt: kept, not sent; the axis, or why a window
    /// gave none, said once on stderr (at a window's end: every 12 s at most; nothing is
    /// allocated otherwise, the window's buffer being allocated once).
    fn learn(&mut self, t_ns: u64, relative: DVec3) {
        self.learning += 1;
        let Some(learner) = self.learner.as_mut() else {
            return;
        };
        let before = learner.unclear_windows;
        if let Some(a) = learner.push(t_ns, relative) {
            eprintln!(
                "tracker-bridge: chest tool {:?}: {}",
                self.name,
                a.describe()
            );
            self.learnt = Some(a);
        } else if learner.unclear_windows != before {
            if let Some(why) = &learner.unclear {
                eprintln!(
                    "tracker-bridge: chest tool {:?}: no breathing axis from its last {LEARN_S:.0} s: \
                     {why}; learning again",
                    self.name
                );
            }
        }
    }

    fn push(&mut self, block: &mut SignalBlock, t_ns: u64, value: Option<f64>) {
        crate::signal_udp::push_sample(block, t_ns, value.unwrap_or(0.0), value.is_some());
        self.sent += 1;
        self.invalid += u64::from(value.is_none());
    }
}

/// The chest tool's position relative to the patient reference, in the reference's frame, along
/// [`ANTERIOR`], mm; `None` when not finite.
pub fn anterior_mm(chest: &Pose, patient: &Pose) -> Option<f64> {
    relative_mm(chest, patient).map(|r| r.dot(ANTERIOR))
}

/// The chest tool's position relative to the patient reference, in the reference's frame, mm;
/// `None` when not finite.
pub fn relative_mm(chest: &Pose, patient: &Pose) -> Option<DVec3> {
    let q = patient.quat.map(f64::from);
    let rotation = DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize();
    let d = DVec3::from(chest.translation_mm.map(f64::from))
        - DVec3::from(patient.translation_mm.map(f64::from));
    let v = rotation.inverse() * d;
    v.is_finite().then_some(v)
}

/// Which way the chest tool's breathing is read (`tool:NAME[:anterior|auto]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum AxisChoice {
    /// Along the patient reference's anterior axis ([`ANTERIOR`]): the reference is mounted on the
    /// patient's RAS frame (the default).
    #[default]
    Anterior,
    /// Along the axis the tool itself moves on, learnt from its first [`LEARN_S`] seconds of
    /// motion ([`AxisLearner`]): a reference mounted any way.
    Auto,
}

impl AxisChoice {
    /// The suffix of the source string (`""` for the default, `":auto"`).
    pub fn suffix(self) -> &'static str {
        match self {
            AxisChoice::Anterior => "",
            AxisChoice::Auto => ":auto",
        }
    }
}

/// Seconds of the chest tool's valid measurements an axis is learnt from: two breaths at ten a
/// minute.
pub const LEARN_S: f64 = 12.0;
/// Most measurements kept while learning (34 s at 120 Hz), allocated once.
pub const LEARN_CAPACITY: usize = 4096;
/// Least RMS motion along the axis, mm: a chest that barely moves has no axis to learn.
pub const MIN_ALONG_MM: f64 = 0.5;
/// Least ratio of the RMS motion along the axis to the largest across it: breathing moves a chest
/// wall on one line; a tool that wanders as much across has no breathing axis.
pub const MIN_RATIO: f64 = 3.0;
/// Least |skewness| of the motion along the axis for its sign to be read from the breath's shape
/// (the pause at end-expiration puts most samples near it and a tail towards inspiration).
pub const MIN_SKEW: f64 = 0.3;

/// The breathing axis learnt from the chest tool's own motion, in the patient reference's frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LearntAxis {
    /// Unit axis, + = inspiration.
    pub axis: [f64; 3],
    /// Its angle to the reference's anterior axis, degrees.
    pub from_anterior_deg: f64,
    /// RMS motion along it and the largest across it, mm.
    pub along_mm: f64,
    /// The largest RMS motion across it, mm.
    pub across_mm: f64,
    /// Skewness of the motion along it (positive: a tail towards inspiration).
    pub skewness: f64,
    /// Which way is inspiration was read from the breath's shape (`true`) or, the shape being
    /// too symmetric, from the reference's anterior axis (`false`).
    pub sign_from_shape: bool,
    /// Measurements and seconds it was learnt from.
    pub samples: usize,
    /// Seconds.
    pub seconds: f64,
}

impl LearntAxis {
    /// In words, for the bridge's line.
    pub fn describe(&self) -> String {
        let a = self.axis;
        format!(
            "axis ({:.3}, {:.3}, {:.3}) in the reference's frame, {:.0}° from its anterior axis, learnt \
             from {} measurements over {:.1} s (RMS {:.2} mm along it, {:.2} mm across); inspiration \
             is + {}",
            a[0],
            a[1],
            a[2],
            self.from_anterior_deg,
            self.samples,
            self.seconds,
            self.along_mm,
            self.across_mm,
            if self.sign_from_shape {
                format!("by the breath's shape (skewness {:+.2})", self.skewness)
            } else {
                format!(
                    "towards the reference's anterior axis (the breath's shape is too symmetric to \
                     tell: skewness {:+.2})",
                    self.skewness
                )
            }
        )
    }
}

/// Learns the chest tool's breathing axis from its positions relative to the reference.
#[derive(Debug, Clone)]
pub struct AxisLearner {
    points: Vec<DVec3>,
    first_ns: u64,
    /// Why the last window gave no axis.
    pub unclear: Option<String>,
    /// Windows that gave no axis.
    pub unclear_windows: u32,
}

impl Default for AxisLearner {
    fn default() -> Self {
        Self {
            points: Vec::with_capacity(LEARN_CAPACITY),
            first_ns: 0,
            unclear: None,
            unclear_windows: 0,
        }
    }
}

impl AxisLearner {
    /// One valid measurement `p` (the chest in the reference's frame, mm) at `t_ns`: the axis once
    /// [`LEARN_S`] seconds (or [`LEARN_CAPACITY`] measurements) are in and it is clear; a window
    /// that gives none is said ([`Self::unclear`]) and learning starts again.
    pub fn push(&mut self, t_ns: u64, p: DVec3) -> Option<LearntAxis> {
        if self.points.is_empty() {
            self.first_ns = t_ns;
        }
        self.points.push(p);
        let seconds = t_ns.saturating_sub(self.first_ns) as f64 / 1e9;
        if seconds < LEARN_S && self.points.len() < LEARN_CAPACITY {
            return None;
        }
        let result = axis_of(&self.points, seconds);
        self.points.clear();
        match result {
            Ok(a) => Some(a),
            Err(why) => {
                self.unclear = Some(why);
                self.unclear_windows += 1;
                None
            }
        }
    }
}

/// The principal axis of `points` (a window of `seconds`), signed towards inspiration, or why
/// there is none.
pub fn axis_of(points: &[DVec3], seconds: f64) -> Result<LearntAxis, String> {
    let n = points.len() as f64;
    if points.len() < 8 {
        return Err(format!("{} measurements in {seconds:.1} s", points.len()));
    }
    let mean = points.iter().fold(DVec3::ZERO, |s, p| s + *p) / n;
    let mut c = nalgebra::Matrix3::<f64>::zeros();
    for p in points {
        let d = nalgebra::Vector3::new(p.x - mean.x, p.y - mean.y, p.z - mean.z);
        c += d * d.transpose();
    }
    c /= n;
    let eig = nalgebra::SymmetricEigen::new(c);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let along = eig.eigenvalues[order[0]].max(0.0).sqrt();
    let across = eig.eigenvalues[order[1]].max(0.0).sqrt();
    if !(along.is_finite() && across.is_finite()) {
        return Err("positions that are not finite".to_string());
    }
    if along < MIN_ALONG_MM {
        return Err(format!(
            "the chest tool moved {along:.2} mm RMS in {seconds:.1} s (at least {MIN_ALONG_MM} mm \
             needed): is it on the chest, and is the patient breathing?"
        ));
    }
    if along < MIN_RATIO * across {
        return Err(format!(
            "the chest tool's motion is not along one line ({along:.2} mm RMS along its main axis, \
             {across:.2} mm across; at least {MIN_RATIO}× needed): is it loose, or is the patient \
             moving relative to the reference?"
        ));
    }
    let e = eig.eigenvectors.column(order[0]);
    let mut axis = DVec3::new(e[0], e[1], e[2]).normalize();
    let m3 = points
        .iter()
        .map(|p| (*p - mean).dot(axis).powi(3))
        .sum::<f64>()
        / n;
    let mut skewness = m3 / along.powi(3);
    let sign_from_shape = skewness.abs() >= MIN_SKEW;
    let flip = if sign_from_shape {
        skewness < 0.0
    } else {
        axis.dot(ANTERIOR) < 0.0
    };
    if flip {
        axis = -axis;
        skewness = -skewness;
    }
    Ok(LearntAxis {
        axis: axis.to_array(),
        from_anterior_deg: axis.dot(ANTERIOR).clamp(-1.0, 1.0).acos().to_degrees(),
        along_mm: along,
        across_mm: across,
        skewness,
        sign_from_shape,
        samples: points.len(),
        seconds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(quat: DQuat, t: DVec3) -> Pose {
        Pose {
            quat: quat.to_array().map(|v| v as f32),
            translation_mm: t.to_array().map(|v| v as f32),
            _pad: 0,
        }
    }

    /// The value is the chest's rise along the patient's anterior axis whatever the patient's pose
    /// in the room: the same chest offset in the reference's frame gives the same value with the
    /// patient turned and moved, and moving both tools together changes nothing.
    #[test]
    fn the_value_is_along_the_patients_anterior_axis_wherever_the_patient_lies() {
        let offset = DVec3::new(20.0, 7.5, -40.0); // 7.5 mm anterior of the reference
        for (turn, at) in [
            (DQuat::IDENTITY, DVec3::ZERO),
            (
                DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
                DVec3::new(100.0, -50.0, 900.0),
            ),
            (
                DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0),
                DVec3::new(-300.0, 20.0, 1500.0),
            ),
        ] {
            let patient = pose(turn, at);
            let chest = pose(turn, at + turn * offset);
            let v = anterior_mm(&chest, &patient).unwrap();
            assert!((v - 7.5).abs() < 1e-3, "{v}");
        }
        let bad = pose(DQuat::IDENTITY, DVec3::new(f64::NAN, 0.0, 0.0));
        assert_eq!(anterior_mm(&bad, &pose(DQuat::IDENTITY, DVec3::ZERO)), None);
    }

    /// One sample per new chest measurement, stamped with its arrival; a repeat of the same
    /// measurement gives none; without the reference it is flagged invalid (value 0); a silent
    /// chest tool gives one invalid sample per frame. Unit mm, period the bridge's.
    #[test]
    fn each_measurement_is_one_sample_and_a_loss_is_flagged_never_held() {
        let mut s = ToolSignal::new("Chest", 60.0, AxisChoice::Anterior);
        let patient = pose(DQuat::IDENTITY, DVec3::ZERO);
        let chest = pose(DQuat::IDENTITY, DVec3::new(0.0, 3.0, 0.0));
        let mut b = SignalBlock::default();
        let view = |arrival, chest, patient, silent| ToolView {
            chest_arrival_ns: arrival,
            chest,
            patient,
            chest_silent: silent,
        };
        s.fill(1_000, &view(900, Some(chest), Some(patient), false), &mut b);
        assert_eq!((b.count, b.unit, b.valid_mask), (1, signal_unit::MM, 1));
        assert_eq!(b.period_ns, 16_666_667);
        assert_eq!((b.samples[0].t_ns, b.samples[0].value), (900, 3.0));
        // The same measurement again: nothing new.
        s.fill(2_000, &view(900, Some(chest), Some(patient), false), &mut b);
        assert_eq!(b.count, 0);
        assert_ne!(b.status & signal_status::CONFIGURED, 0);
        // A new measurement without the reference: flagged.
        s.fill(3_000, &view(2_900, Some(chest), None, false), &mut b);
        assert_eq!((b.count, b.valid_mask, b.samples[0].value), (1, 0, 0.0));
        // Silent: one flagged sample per frame, stamped with the frame's time.
        for now in [4_000, 5_000] {
            s.fill(now, &view(2_900, None, Some(patient), true), &mut b);
            assert_eq!((b.count, b.valid_mask, b.samples[0].t_ns), (1, 0, now));
        }
        assert_eq!((s.sent, s.invalid), (4, 3));
    }

    /// A breathing chest (`cos⁴`-shaped rise with a pause at end-expiration, 7 mm at 15 breaths a
    /// minute, 0.1 mm of tracker noise) on `axis` in the reference's frame, as the reference's
    /// frame sees it, sampled at 60 Hz for `seconds`: (time ns, position mm).
    fn chest_motion(axis: DVec3, seconds: f64, shape: fn(f64) -> f64) -> Vec<(u64, DVec3)> {
        use rand::{RngExt, SeedableRng};
        let mut r = rand_xorshift::XorShiftRng::seed_from_u64(7);
        let across = axis.any_orthonormal_vector();
        let across2 = axis.cross(across);
        (0..(seconds * 60.0) as usize)
            .map(|k| {
                let t = k as f64 / 60.0;
                let rise = 7.0 * shape(t / 4.0);
                let noise = DVec3::new(
                    r.random_range(-0.17..0.17),
                    r.random_range(-0.17..0.17),
                    r.random_range(-0.17..0.17),
                );
                let sway = 0.3 * (t * 0.7).sin() * across + 0.2 * (t * 1.3).cos() * across2;
                let p = DVec3::new(40.0, 90.0, -120.0) + rise * axis + sway + noise;
                ((1e9 * t) as u64 + 1_000, p)
            })
            .collect()
    }

    /// Lujan's breathing shape: 1 at end-inspiration, a long pause near 0 at end-expiration.
    fn lujan(cycle: f64) -> f64 {
        (std::f64::consts::PI * cycle).sin().powi(4)
    }

    /// A symmetric breath (no pause): its sign cannot be read from its shape.
    fn sine(cycle: f64) -> f64 {
        0.5 - 0.5 * (2.0 * std::f64::consts::PI * cycle).cos()
    }

    /// The axis a reference mounted any way sees: learnt within 2° of the true one, inspiration
    /// towards +, from the breath's shape whichever way the axis points; the rise along it then
    /// follows the true rise.
    #[test]
    fn the_axis_is_learnt_from_the_tools_own_motion_with_inspiration_positive() {
        for truth in [
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::new(0.6, -0.3, 0.74).normalize(),
            DVec3::new(-0.2, -0.9, -0.3).normalize(),
        ] {
            let motion = chest_motion(truth, 14.0, lujan);
            let mut learner = AxisLearner::default();
            let learnt = motion
                .iter()
                .find_map(|&(t, p)| learner.push(t, p))
                .expect("an axis within 14 s");
            let axis = DVec3::from(learnt.axis);
            let angle = axis.dot(truth).clamp(-1.0, 1.0).acos().to_degrees();
            assert!(angle < 2.0, "{truth}: {angle}° off ({learnt:?})");
            assert!(
                learnt.sign_from_shape && learnt.skewness > MIN_SKEW,
                "{learnt:?}"
            );
            assert!((learnt.seconds - LEARN_S).abs() < 0.1, "{}", learnt.seconds);
            let want = truth.dot(ANTERIOR).clamp(-1.0, 1.0).acos().to_degrees();
            assert!((learnt.from_anterior_deg - want).abs() < 2.0);
        }
    }

    /// A symmetric breath's sign comes from the reference's anterior axis, and says so; a chest
    /// that does not move, or moves as much across as along, gives no axis and says why.
    #[test]
    fn an_unclear_motion_gives_no_axis_and_says_why() {
        let truth = DVec3::new(0.3, 0.9, 0.2).normalize();
        let motion = chest_motion(-truth, 14.0, sine);
        let mut learner = AxisLearner::default();
        let learnt = motion
            .iter()
            .find_map(|&(t, p)| learner.push(t, p))
            .unwrap();
        assert!(!learnt.sign_from_shape, "{learnt:?}");
        assert!(DVec3::from(learnt.axis).dot(truth) > 0.99, "{learnt:?}");
        assert!(learnt.describe().contains("too symmetric"));
        // Still: 0.1 mm of noise only.
        let still: Vec<DVec3> = chest_motion(truth, 14.0, |_| 0.0)
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let why = axis_of(&still, 14.0).unwrap_err();
        assert!(why.contains("is the patient breathing"), "{why}");
        // As much across as along: a loose tool.
        let loose: Vec<DVec3> = (0..840)
            .map(|k| {
                let t = k as f64 / 60.0;
                DVec3::new(3.0 * (t * 1.1).sin(), 3.0 * (t * 1.7).cos(), 0.0)
            })
            .collect();
        let why = axis_of(&loose, 14.0).unwrap_err();
        assert!(why.contains("not along one line"), "{why}");
        // The learner starts again after an unclear window and says why.
        let mut learner = AxisLearner::default();
        for (k, p) in loose.iter().enumerate() {
            assert!(learner.push(1_000 + k as u64 * 16_666_667, *p).is_none());
        }
        assert!(learner
            .unclear
            .as_deref()
            .unwrap()
            .contains("not along one line"));
    }

    /// `tool:NAME:auto` through the signal: no sample while the axis is learnt (the engine's model
    /// breathes meanwhile), then each measurement's rise along the learnt axis; a loss is still
    /// flagged while learning.
    #[test]
    fn an_auto_axis_withholds_samples_while_it_learns_then_sends_the_rise_along_it() {
        let truth = DVec3::new(0.6, -0.3, 0.74).normalize();
        let turn = DQuat::from_euler(glam::EulerRot::XYZ, 0.4, -0.8, 1.9);
        let at = DVec3::new(-200.0, 40.0, 1100.0);
        let patient = pose(turn, at);
        let mut s = ToolSignal::new("Chest", 60.0, AxisChoice::Auto);
        let mut b = SignalBlock::default();
        let mut sent = Vec::new();
        let mut learning_frames = 0;
        let motion = chest_motion(truth, 20.0, lujan);
        for (k, &(t, p)) in motion.iter().enumerate() {
            let view = ToolView {
                chest_arrival_ns: t,
                chest: Some(pose(turn, at + turn * p)),
                patient: Some(patient),
                chest_silent: false,
            };
            s.fill(t + 500, &view, &mut b);
            // Every frame before the axis is learnt says so (the engine shows "learning", not a
            // loss); none after.
            if b.status & signal_status::LEARNING != 0 {
                assert!(sent.is_empty() && b.count == 0, "frame {k}");
                learning_frames += 1;
            }
            if b.count == 1 {
                assert_eq!(b.valid_mask, 1);
                sent.push((k, b.samples[0].value));
            }
        }
        let learnt = s.learnt().expect("learnt");
        let first = sent[0].0;
        assert!(
            (first as f64 / 60.0 - LEARN_S).abs() < 0.1,
            "first sample at {first}"
        );
        assert_eq!(s.learning as usize, first);
        // (The frame whose measurement completes the window sends nothing and is no longer
        // learning: the axis is known at its end.)
        assert_eq!(learning_frames, first - 1);
        // Along the learnt axis: the true rise plus a constant (the tool's offset).
        let offset = sent
            .iter()
            .map(|&(k, v)| v - motion[k].1.dot(truth))
            .sum::<f64>()
            / sent.len() as f64;
        for &(k, v) in &sent {
            let want = motion[k].1.dot(truth) + offset;
            assert!((v - want).abs() < 0.3, "sample {k}: {v} against {want}");
        }
        assert!(DVec3::from(learnt.axis).dot(truth) > 0.999);
        // A silent tool while learning is a loss, flagged.
        let mut s = ToolSignal::new("Chest", 60.0, AxisChoice::Auto);
        let view = ToolView {
            chest_arrival_ns: 0,
            chest: None,
            patient: Some(patient),
            chest_silent: true,
        };
        s.fill(1_000, &view, &mut b);
        assert_eq!((b.count, b.valid_mask), (1, 0));
        assert_ne!(b.status & signal_status::LEARNING, 0);
        // The anterior axis needs no learning.
        let mut s = ToolSignal::new("Chest", 60.0, AxisChoice::Anterior);
        s.fill(1_000, &view, &mut b);
        assert_eq!(b.status & signal_status::LEARNING, 0);
    }
}
