//! # runtime: the engine's tick
//!
//! [`EngineCore`] is the deterministic heart: `step(tick, latest tracker frame)` → [`EngineFrame`],
//! a pure function of its inputs and the scene (no clock, no randomness, no allocation), so a
//! recorded session replays bit-identically. The breathing clock is the integer tick counter
//! (PV volume from [`crate::pv::Breathing::volume_at`]), never an accumulated float time.
//!
//! [`run`] is the process loop around it: it sleeps on the tracker's iceoryx2 event, so a fresh
//! tracker sample is turned into an engine frame immediately (a tick is *driven* by the sample it
//! consumes), and falls back to an absolute deadline (`period + grace`, then every `period`) when the
//! tracker is late or silent, so the lung keeps breathing.

use ipc_types::{
    engine_state, fault, EngineFrame, LungState, Pose, TrackerFrame, LAYOUT_VERSION, TOOL_PATIENT,
};

use crate::deform::LungModel;
use crate::mesh::{generate, Side};
use crate::pv::{self, Breathing};
use crate::scene::Scene;

/// What the engine needs of one lung at run time.
#[derive(Debug, Clone)]
pub struct LungRuntime {
    /// Which lung.
    pub side: Side,
    /// Share of the total PV volume change this lung takes (its FRC volume / total FRC).
    pub share: f64,
    /// The lung's deformation model (its volume cubic is what the tick uses).
    pub model: LungModel,
}

/// The deterministic engine state.
#[derive(Debug, Clone)]
pub struct EngineCore {
    breathing: Breathing,
    lungs: Vec<LungRuntime>,
    staleness_ticks: u64,
    patient_pose: Pose,
    last_good_pose_tick: Option<u64>,
    last_tracker_tick: Option<u64>,
    last_tracker_frame: u64,
}

/// The deformation model of `side` for `scene`: its baked kernel when the scene names one, else the
/// generated lung baked in memory with the scene's settings.
pub fn build_lung(scene: &Scene, side: Side) -> anyhow::Result<LungModel> {
    if let Some(path) = scene.lungs.kernels.get(side) {
        let file = crate::kernel::KernelFile::open(path)?;
        if file.meta().side != side {
            anyhow::bail!(
                "{}: this kernel is of the {} lung, the scene uses it for the {} lung",
                path.display(),
                file.meta().side.name(),
                side.name()
            );
        }
        return Ok(file.lung_model());
    }
    let mesh = generate::lung(side, scene.lungs.vertices)?;
    let kernel = crate::kernel::bake(side, mesh, &scene.bake_settings(side)?, &|_| {})?;
    Ok(LungModel::from_unit_displacement(
        side,
        kernel.mesh,
        kernel.unit_displacement,
    ))
}

impl EngineCore {
    /// Build the engine for `scene`: precompute the breathing cycle and each active lung's model.
    pub fn new(scene: &Scene) -> anyhow::Result<Self> {
        let (inhale, exhale, boundary) = scene.pv_model()?;
        let breathing = Breathing::from_constants(&inhale, &exhale, boundary, &scene.timing())?;
        let frc = breathing.boundary().frc_ml;
        let lungs = scene
            .lungs
            .sides
            .iter()
            .map(|&side| {
                let model = build_lung(scene, side)?;
                Ok(LungRuntime {
                    side,
                    share: model.start_volume_ml / frc,
                    model,
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Self::from_parts(
            breathing,
            lungs,
            scene.engine.pose_staleness_ticks as u64,
        ))
    }

    /// Assemble from precomputed parts (tests, benchmarks).
    pub fn from_parts(breathing: Breathing, lungs: Vec<LungRuntime>, staleness_ticks: u64) -> Self {
        Self {
            breathing,
            lungs,
            staleness_ticks,
            patient_pose: Pose::IDENTITY,
            last_good_pose_tick: None,
            last_tracker_tick: None,
            last_tracker_frame: 0,
        }
    }

    /// The precomputed breathing cycle.
    pub fn breathing(&self) -> &Breathing {
        &self.breathing
    }

    /// The active lungs.
    pub fn lungs(&self) -> &[LungRuntime] {
        &self.lungs
    }

    /// One tick. `input` is the latest tracker frame if one arrived since the previous tick.
    /// Writes every field of `out` except the engine's own hop stamps (set by the process loop).
    pub fn step(&mut self, tick: u64, input: Option<&TrackerFrame>, out: &mut EngineFrame) {
        let mut state = 0u32;
        let mut fault_word = fault::NONE;
        match input {
            Some(frame) => {
                state |= engine_state::TRACKER_FRESH;
                self.last_tracker_tick = Some(tick);
                self.last_tracker_frame = frame.frame_number;
                out.stamps = frame.stamps;
                let patient = &frame.tools[TOOL_PATIENT];
                if frame.tool_count as usize > TOOL_PATIENT
                    && patient.is_valid()
                    && patient.pose.is_finite()
                {
                    self.patient_pose = patient.pose;
                    self.last_good_pose_tick = Some(tick);
                }
            }
            None => state |= engine_state::DEADLINE_FALLBACK,
        }
        match self.last_tracker_tick {
            None => state |= engine_state::NO_TRACKER_YET,
            Some(t) if tick - t > self.staleness_ticks => fault_word = fault::TRACKER_LOST,
            _ => {}
        }
        match self.last_good_pose_tick {
            Some(t) if t == tick => {}
            Some(t) => {
                state |= engine_state::PATIENT_POSE_HELD;
                if tick - t > self.staleness_ticks {
                    state |= engine_state::PATIENT_POSE_STALE;
                }
            }
            None => state |= engine_state::PATIENT_POSE_HELD | engine_state::PATIENT_POSE_STALE,
        }
        if self.breathing.phase_at(tick) == pv::Phase::Inhale {
            state |= engine_state::INHALING;
        }
        let total = self.breathing.volume_at(tick);
        let delta_total = total - self.breathing.boundary().frc_ml;
        out.lungs = [LungState::default(); ipc_types::NUM_LUNGS];
        for lung in &self.lungs {
            let slot = &mut out.lungs[lung.side.index()];
            let delta = delta_total * lung.share;
            let scale = lung.model.scale_for_delta(delta);
            if scale.is_finite() {
                slot.volume_ml = (lung.model.start_volume_ml + delta) as f32;
                slot.deform_scale = scale as f32;
            } else {
                // Unreachable for validated scenes; a NaN must never reach a frame.
                fault_word = fault::NON_FINITE_VOLUME;
                slot.volume_ml = lung.model.start_volume_ml as f32;
                slot.deform_scale = 0.0;
            }
            slot.active = 1;
        }
        out.layout_version = LAYOUT_VERSION;
        out.state = state;
        out.fault = fault_word;
        out.cycle_ticks = self.breathing.cycle_ticks();
        out.tick = tick;
        out.tracker_frame = self.last_tracker_frame;
        out.patient_pose = self.patient_pose;
    }
}

pub mod process;
pub use process::run;

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::{tool_status, ToolPose};

    fn frame(n: u64, patient_valid: bool) -> TrackerFrame {
        let mut f = TrackerFrame {
            layout_version: LAYOUT_VERSION,
            tool_count: 2,
            frame_number: n,
            ..Default::default()
        };
        f.stamps.capture_ns = 1000 + n;
        f.tools[TOOL_PATIENT] = ToolPose {
            tool_id: 1,
            status: if patient_valid {
                tool_status::VALID
            } else {
                tool_status::MISSING
            },
            pose: Pose {
                quat: [0.0, 0.0, (n as f32 * 0.01).sin(), 1.0],
                translation_mm: [n as f32, 0.0, 900.0],
                _pad: 0,
            },
            rms_error_mm: 0.2,
            _pad: 0,
        };
        f
    }

    fn small_scene() -> Scene {
        let mut s = Scene::default();
        s.lungs.vertices = 1000;
        s
    }

    /// A recorded input sequence with gaps (deadline-fallback ticks) and bad patient samples.
    fn replay(core: &mut EngineCore) -> Vec<EngineFrame> {
        let mut out = Vec::new();
        for tick in 0..900u64 {
            let input = match tick % 37 {
                5 | 6 => None,
                9 => Some(frame(tick, false)),
                _ => Some(frame(tick, true)),
            };
            let mut f = EngineFrame::default();
            core.step(tick, input.as_ref(), &mut f);
            out.push(f);
        }
        out
    }

    fn bits(f: &EngineFrame) -> Vec<u32> {
        let mut v = vec![
            f.state,
            f.fault,
            f.cycle_ticks,
            f.tick as u32,
            f.tracker_frame as u32,
        ];
        v.extend(
            f.patient_pose
                .quat
                .iter()
                .chain(&f.patient_pose.translation_mm)
                .map(|x| x.to_bits()),
        );
        for l in &f.lungs {
            v.extend([l.volume_ml.to_bits(), l.deform_scale.to_bits(), l.active]);
        }
        v
    }

    #[test]
    fn same_inputs_replay_bitwise_identically() {
        let scene = small_scene();
        let a = replay(&mut EngineCore::new(&scene).unwrap());
        let b = replay(&mut EngineCore::new(&scene).unwrap());
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(bits(x), bits(y), "tick {}", x.tick);
        }
        // A committed digest pins the reference run across builds and machines.
        let digest = a
            .iter()
            .flat_map(bits)
            .fold(0xcbf2_9ce4_8422_2325_u64, |h, w| {
                (h ^ w as u64).wrapping_mul(0x0000_0100_0000_01b3)
            });
        assert_eq!(
            digest, REFERENCE_DIGEST,
            "reference run changed: digest {digest:#018x}"
        );
    }

    /// FNV-1a over [`bits`] of the 900-tick reference replay at 1000 vertices per lung.
    const REFERENCE_DIGEST: u64 = 0xd9cf7a77d6c0942c;

    #[test]
    fn missing_samples_hold_the_pose_and_flag_it() {
        let mut core = EngineCore::new(&small_scene()).unwrap();
        let mut f = EngineFrame::default();
        core.step(0, None, &mut f);
        assert_ne!(f.state & engine_state::NO_TRACKER_YET, 0);
        core.step(1, Some(&frame(1, true)), &mut f);
        let good = f.patient_pose;
        assert_eq!(f.state & engine_state::PATIENT_POSE_HELD, 0);
        core.step(2, Some(&frame(2, false)), &mut f);
        assert_eq!(f.patient_pose, good);
        assert_ne!(f.state & engine_state::PATIENT_POSE_HELD, 0);
        for t in 3..40 {
            core.step(t, None, &mut f);
        }
        assert_ne!(f.state & engine_state::PATIENT_POSE_STALE, 0);
        assert_eq!(f.fault, fault::TRACKER_LOST);
        assert_eq!(f.patient_pose, good);
    }

    #[test]
    fn lung_volumes_follow_the_pv_model_and_stay_finite() {
        let mut core = EngineCore::new(&small_scene()).unwrap();
        let mut f = EngineFrame::default();
        for tick in 0..600 {
            core.step(tick, None, &mut f);
            let total: f32 = f.lungs.iter().map(|l| l.volume_ml).sum();
            let expect = core.breathing().volume_at(tick) as f32;
            assert!(
                (total - expect).abs() < 0.01 * expect / 100.0 + 0.5,
                "tick {tick}: {total} vs {expect}"
            );
            for l in &f.lungs {
                assert!(
                    l.volume_ml.is_finite() && l.deform_scale.is_finite() && l.deform_scale >= 0.0
                );
            }
        }
    }
}
