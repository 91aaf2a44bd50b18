//! # runtime: the engine's tick
//!
//! [`EngineCore`] is the deterministic heart: `step(tick, latest tracker frame)` → [`EngineFrame`],
//! a pure function of the scene, the kernels and the sequence of inputs (no clock, no randomness,
//! no allocation), so a recorded session replays bit-identically. The breathing clock is the integer
//! tick counter, never an accumulated float time.
//!
//! Each lung has its own breathing state ([`LungBreath`]): its PV cycle (precomputed per phase from
//! eq. 5.11 and EQUATIONS §1.1, [`Breathing`]), its share of the volume change, a held volume when it
//! does not breathe, and a rigid offset. Today's scenes give both lungs one PV cycle split by their
//! FRC volumes; a disease state changes one lung's state — stop it, shrink it, change its rate from
//! its next cycle — while the other breathes on. Each lung's volume becomes a deformation scale by
//! solving its volume cubic (EQUATIONS §2.4), so the drawn mesh encloses exactly that volume.
//!
//! [`process`] is the loop around it.

use ipc_types::{
    engine_state, fault, lung_flags, EngineFrame, LungFrame, Pose, TrackerFrame, LAYOUT_VERSION,
    NUM_LUNGS, TOOL_PATIENT,
};
use lung_model::deform::{LungModel, VolumeCubic};
use lung_model::mesh::Side;
use lung_model::pv::{Breathing, PvError};
use lung_model::scene::{LungLoadError, Scene, SceneValueError};
use thiserror::Error;

pub mod process;
pub use process::run;

/// What the engine needs of one lung's geometry: its kernel's identity and volume cubic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungGeometry {
    /// Which lung.
    pub side: Side,
    /// Identity of the kernel (travels in every frame so a renderer can check it drew the same lung).
    pub kernel_id: u64,
    /// Enclosed volume of `mesh + s·u` as a cubic in `s`.
    pub cubic: VolumeCubic,
    /// Enclosed volume of the mesh as baked (FRC), ml.
    pub start_volume_ml: f64,
}

impl LungGeometry {
    /// The geometry of a loaded lung model.
    pub fn of(model: &LungModel) -> Self {
        Self {
            side: model.side,
            kernel_id: model.kernel_id,
            cubic: model.cubic,
            start_volume_ml: model.start_volume_ml,
        }
    }

    /// Deformation scale that makes the enclosed volume `start + delta_ml`.
    #[inline]
    pub fn scale_for_delta(&self, delta_ml: f64) -> f64 {
        self.cubic.solve_delta(delta_ml * 1000.0)
    }
}

/// One lung's breathing state.
#[derive(Debug, Clone)]
pub struct LungBreath {
    breathing: Breathing,
    next: Option<Breathing>,
    share: f64,
    held_ml: Option<f64>,
    offset_mm: [f64; 3],
    cycle_start: u64,
    cycle: u32,
    changed_at: Option<u64>,
}

impl LungBreath {
    /// A lung following `breathing`, taking `share` of its volume change above FRC.
    pub fn new(breathing: Breathing, share: f64) -> Self {
        Self {
            breathing,
            next: None,
            share,
            held_ml: None,
            offset_mm: [0.0; 3],
            cycle_start: 0,
            cycle: 0,
            changed_at: None,
        }
    }

    /// The cycle in force.
    pub fn breathing(&self) -> &Breathing {
        &self.breathing
    }

    /// Breathe `next` from the start of this lung's next cycle (a rate or depth change never cuts a
    /// breath short).
    pub fn set_breathing_from_next_cycle(&mut self, next: Breathing) {
        self.next = Some(next);
    }

    /// Stop breathing and hold the lung's volume at `volume_ml` (absolute, ml); `None` resumes.
    pub fn hold(&mut self, volume_ml: Option<f64>) {
        self.held_ml = volume_ml;
    }

    /// Share of the PV volume change above FRC this lung takes.
    pub fn set_share(&mut self, share: f64) {
        self.share = share;
    }

    /// Rigid offset of the whole lung, body frame, mm.
    pub fn set_offset_mm(&mut self, offset_mm: [f64; 3]) {
        self.offset_mm = offset_mm;
    }

    /// Advance the cycle bookkeeping to `tick`; returns the tick within the current cycle.
    fn local_tick(&mut self, tick: u64) -> u64 {
        let mut local = tick.saturating_sub(self.cycle_start);
        let ct = self.breathing.cycle_ticks() as u64;
        if local >= ct {
            // The cycle that started at `cycle_start` is over: a pending change takes effect at
            // the boundary, later whole cycles of the new breathing are skipped arithmetically.
            self.cycle_start += ct;
            self.cycle = self.cycle.wrapping_add(1);
            if let Some(n) = self.next.take() {
                self.breathing = n;
                self.changed_at = Some(self.cycle_start);
            }
            local = tick.saturating_sub(self.cycle_start);
            let ct = self.breathing.cycle_ticks() as u64;
            let whole = local / ct;
            self.cycle_start += whole * ct;
            self.cycle = self.cycle.wrapping_add(whole as u32);
            local -= whole * ct;
        }
        local
    }

    /// Volume change above this lung's FRC volume at `local` (ml), and whether it is inhaling.
    fn delta_at(&self, local: u64) -> (f64, bool) {
        let b = &self.breathing;
        let delta = (b.volume_at(local) - b.boundary().frc_ml) * self.share;
        (delta, local < b.inhale_ticks() as u64)
    }
}

/// Why the engine could not be built for a scene.
#[derive(Debug, Error)]
pub enum CoreError {
    /// The scene's PV model cannot be used.
    #[error("the scene's PV model: {0}")]
    Pv(#[source] SceneValueError),
    /// The breathing cycle cannot be precomputed.
    #[error("the breathing cycle: {0}")]
    Breathing(#[source] PvError),
    /// A lung could not be loaded.
    #[error(transparent)]
    Lung(#[from] LungLoadError),
}

/// The deterministic engine state.
#[derive(Debug, Clone)]
pub struct EngineCore {
    lungs: Vec<(LungGeometry, LungBreath)>,
    staleness_ticks: u64,
    patient_pose: Pose,
    last_good_pose_tick: Option<u64>,
    last_tracker_tick: Option<u64>,
    last_tracker_frame: u64,
}

impl EngineCore {
    /// Build the engine for `scene`: precompute the breathing cycle and load each lung's kernel
    /// (never baking: a lung without a kernel is an error that says how to get one).
    pub fn new(scene: &Scene) -> Result<Self, CoreError> {
        let lungs = scene
            .lung_models()?
            .iter()
            .map(LungGeometry::of)
            .collect::<Vec<_>>();
        Self::with_geometry(scene, lungs)
    }

    /// Build from a scene and lung geometries already loaded (tests, benchmarks, tools that hold
    /// the lung models): today's behaviour, both lungs on the scene's PV cycle split by FRC volume.
    pub fn with_geometry(scene: &Scene, lungs: Vec<LungGeometry>) -> Result<Self, CoreError> {
        let (inhale, exhale, boundary) = scene.pv_model().map_err(CoreError::Pv)?;
        let breathing = Breathing::from_constants(&inhale, &exhale, boundary, &scene.timing())
            .map_err(CoreError::Breathing)?;
        let frc = breathing.boundary().frc_ml;
        let lungs = lungs
            .into_iter()
            .map(|g| {
                let share = g.start_volume_ml / frc;
                (g, LungBreath::new(breathing.clone(), share))
            })
            .collect();
        Ok(Self {
            lungs,
            staleness_ticks: scene.engine.pose_staleness_ticks as u64,
            patient_pose: Pose::IDENTITY,
            last_good_pose_tick: None,
            last_tracker_tick: None,
            last_tracker_frame: 0,
        })
    }

    /// The active lungs' geometry.
    pub fn geometry(&self) -> impl Iterator<Item = &LungGeometry> {
        self.lungs.iter().map(|(g, _)| g)
    }

    /// Number of active lungs.
    pub fn lung_count(&self) -> usize {
        self.lungs.len()
    }

    /// The breathing state of `side`, if the scene simulates it.
    pub fn lung(&self, side: Side) -> Option<&LungBreath> {
        self.lungs
            .iter()
            .find(|(g, _)| g.side == side)
            .map(|l| &l.1)
    }

    /// The breathing state of `side` to change it (disease states, interventions).
    pub fn lung_mut(&mut self, side: Side) -> Option<&mut LungBreath> {
        self.lungs
            .iter_mut()
            .find(|(g, _)| g.side == side)
            .map(|l| &mut l.1)
    }

    /// Ticks per breathing cycle of the first lung (for reports and snapshot planning).
    pub fn cycle_ticks(&self) -> u32 {
        self.lungs
            .first()
            .map(|(_, b)| b.breathing.cycle_ticks())
            .unwrap_or(0)
    }

    /// One tick. `input` is the latest tracker frame if one arrived since the previous tick; ticks
    /// must not go backwards. Writes every field of `out` except the engine's own hop stamps (set
    /// by the process loop). No allocation.
    pub fn step(&mut self, tick: u64, input: Option<&TrackerFrame>, out: &mut EngineFrame) {
        let mut state = 0u32;
        let mut fault_word = fault::NONE;
        match input {
            Some(frame) => {
                state |= engine_state::TRACKER_FRESH;
                self.last_tracker_tick = Some(tick);
                self.last_tracker_frame = frame.frame_number;
                out.stamps = frame.stamps;
                if let Some(pose) = frame.valid_tool(TOOL_PATIENT) {
                    self.patient_pose = pose;
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
        out.lungs = [LungFrame::default(); NUM_LUNGS];
        for (k, (geometry, breath)) in self.lungs.iter_mut().enumerate() {
            let local = breath.local_tick(tick);
            let ct = breath.breathing.cycle_ticks();
            let slot = &mut out.lungs[geometry.side.index()];
            let mut flags = lung_flags::ACTIVE;
            let volume = match breath.held_ml {
                Some(v) => {
                    flags |= lung_flags::HELD;
                    v
                }
                None => {
                    let (delta, inhaling) = breath.delta_at(local);
                    if inhaling {
                        flags |= lung_flags::INHALING;
                    }
                    geometry.start_volume_ml + delta
                }
            };
            if breath.changed_at == Some(tick) {
                flags |= lung_flags::CYCLE_CHANGED;
            }
            if k == 0 && flags & lung_flags::INHALING != 0 {
                state |= engine_state::INHALING;
            }
            let scale = geometry.scale_for_delta(volume - geometry.start_volume_ml);
            if scale.is_finite() && volume.is_finite() {
                slot.volume_ml = volume as f32;
                slot.deform_scale = scale as f32;
            } else {
                // Unreachable for validated scenes; a NaN must never reach a frame.
                fault_word = fault::NON_FINITE_VOLUME;
                slot.volume_ml = geometry.start_volume_ml as f32;
                slot.deform_scale = 0.0;
            }
            slot.kernel_id = geometry.kernel_id;
            slot.phase = (local as f64 / ct as f64) as f32;
            slot.cycle = breath.cycle;
            slot.offset_mm = breath.offset_mm.map(|v| v as f32);
            slot.flags = flags;
        }
        out.layout_version = LAYOUT_VERSION;
        out.state = state;
        out.fault = fault_word;
        out._pad = 0;
        out.tick = tick;
        out.tracker_frame = self.last_tracker_frame;
        out.patient_pose = self.patient_pose;
    }
}

#[cfg(test)]
mod tests;
