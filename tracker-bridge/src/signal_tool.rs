//! A tracked tool on the chest as the respiratory signal (issue 35, `--breathing tool:NAME`): the
//! tool's position in the patient reference's frame, along the patient's anterior axis, in mm (+ =
//! inspiration: the chest wall rises). The patient reference's frame is the patient's RAS frame
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
    /// Samples sent.
    pub sent: u64,
    /// Of those, flagged invalid.
    pub invalid: u64,
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
    /// The signal of the tool named `name` at the bridge's `rate_hz` (its nominal period).
    pub fn new(name: &str, rate_hz: f64) -> Self {
        ToolSignal {
            name: name.to_string(),
            period_ns: (1e9 / rate_hz).round() as u64,
            last_taken_ns: 0,
            describe: format!(
                "the tracked tool {name:?} along the patient reference's anterior axis (mm)"
            ),
            sent: 0,
            invalid: 0,
        }
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
            let value = match (view.chest, view.patient) {
                (Some(chest), Some(patient)) => anterior_mm(&chest, &patient),
                _ => None,
            };
            self.push(block, view.chest_arrival_ns, value);
        } else if view.chest_silent {
            // A loss, said every frame while it lasts.
            self.push(block, now_ns, None);
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
    let q = patient.quat.map(f64::from);
    let rotation = DQuat::from_xyzw(q[0], q[1], q[2], q[3]).normalize();
    let d = DVec3::from(chest.translation_mm.map(f64::from))
        - DVec3::from(patient.translation_mm.map(f64::from));
    let v = (rotation.inverse() * d).dot(ANTERIOR);
    v.is_finite().then_some(v)
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
        let mut s = ToolSignal::new("Chest", 60.0);
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
}
