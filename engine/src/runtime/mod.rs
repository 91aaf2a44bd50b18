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
//! Orientation (seed ch. 7, EQUATIONS.md §3.3): in the modes that follow the patient
//! (`basis`, `sh`, `direct`), each tick turns the patient reference pose into gravity in the body
//! frame ([`lung_model::orientation::gravity_in_body`], the scene's `gravity_room`), that into each
//! lung's force weights (exact rotation or the seed's eq. 7.8–7.9 blend, limited where the supine
//! direction model stops expanding the lung), solves the volume cubic of *that* field from the
//! kernel's volume forms, and publishes the coefficients the renderer needs: the four weights
//! (basis, direct) or the `n²` spherical-harmonic force coefficients `F_lm = α·Σ_a w_a·P_a,lm` (sh).
//! A pose that is not a rotation is refused like a missing sample (the last good pose is held and
//! [`engine_state::POSE_INVALID`] set). Per tick and lung: a rotation, 84 multiply-adds for the
//! cubic, at most 12 Newton steps, at most 256 multiply-adds for the SH coefficients.
//!
//! [`process`] is the loop around it.

use glam::DVec3;
use ipc_types::{
    engine_state, fault, lung_flags, EngineFrame, LungFrame, Pose, TrackerFrame, LAYOUT_VERSION,
    NUM_LUNGS, TOOL_PATIENT,
};
use lung_model::deform::modes::{DeformMode, VolumeForms};
use lung_model::deform::{LungModel, VolumeCubic};
use lung_model::kernel::KernelFile;
use lung_model::mesh::Side;
use lung_model::orientation::{gravity_in_body, Orientation, OrientationMethod, SUPINE_GRAVITY};
use lung_model::pv::{Breathing, PvError};
use lung_model::scene::SceneExt;
use lung_model::scene::{LungLoadError, Scene, SceneValueError};
use thiserror::Error;

pub mod disease;
pub mod process;
pub mod remote;
pub mod signal;
pub mod sites;
pub use process::run;

/// What the engine needs of one lung's geometry: its kernel's identity, volume cubic, and for the
/// orientation-following modes the volume forms, orientation model and SH projection.
#[derive(Debug, Clone, PartialEq)]
pub struct LungGeometry {
    /// Which lung.
    pub side: Side,
    /// Identity of the kernel (travels in every frame so a renderer can check it drew the same lung).
    pub kernel_id: u64,
    /// Enclosed volume of `mesh + s·u` as a cubic in `s` (precomputed mode).
    pub cubic: VolumeCubic,
    /// Enclosed volume of the mesh as baked (FRC), ml.
    pub start_volume_ml: f64,
    /// The orientation-following mode's data; `None`: precomputed.
    pub follow: Option<Follow>,
    /// The hilum a collapsing lung retracts towards, mm (found only for a disease scene).
    pub hilum_mm: Option<[f64; 3]>,
    /// The volume range the kernel draws without a fold (`None`: not measured, e.g. a kernel baked
    /// before the bake measured it); a frame outside it carries `lung_flags::PAST_FOLD_FREE`.
    pub fold_free: Option<lung_model::kernel::FoldFreeMeta>,
}

/// What an orientation-following mode needs per tick.
#[derive(Debug, Clone, PartialEq)]
pub struct Follow {
    /// The mode (basis, sh or direct).
    pub mode: DeformMode,
    /// Enclosed volume of the mode's field as forms in the force weights.
    pub forms: VolumeForms,
    /// Pose → force weights.
    pub orientation: Orientation,
    /// SH mode: `α` and the force projection `P` (`4 × n²`, row `a`).
    pub sh: Option<(f64, Vec<f64>)>,
    /// The last gravity (bits) with its weights, limit flag and volume cubic: a patient who has not
    /// moved costs no orientation work (model only what the scene requires).
    pub cache: Option<([u64; 3], [f64; 4], bool, VolumeCubic)>,
}

/// Why a kernel cannot serve an orientation-following mode.
#[derive(Debug, Error)]
pub enum GeometryError {
    /// The kernel lacks the mode's data (the scene loader checks this first).
    #[error("{path}: the kernel has no data for the {mode} mode")]
    Missing {
        /// Kernel.
        path: String,
        /// Mode.
        mode: DeformMode,
    },
    /// A fitted force field baked before the orientation modes drew it.
    #[error(
        "{path}: the kernel's motion is a fitted force field, baked by a lungdyn whose {mode} mode \
         drew eq. 6.18's linear force instead of it; bake it again (or use mode = \"precomputed\")"
    )]
    FittedForceStale {
        /// Kernel.
        path: String,
        /// Mode.
        mode: DeformMode,
    },
}

impl LungGeometry {
    /// The geometry of a loaded lung model (precomputed mode).
    pub fn of(model: &LungModel) -> Self {
        Self {
            side: model.side,
            kernel_id: model.kernel_id,
            cubic: model.cubic,
            start_volume_ml: model.start_volume_ml,
            follow: None,
            hilum_mm: None,
            fold_free: None,
        }
    }

    /// The geometry of `kernel` for `mode`: only the metadata and the core sections are read.
    /// `method` and `min_slope_ratio` are the scene's orientation model (`[engine] orientation`,
    /// `min_slope_ratio`; EQUATIONS.md §3.3).
    pub fn from_kernel(
        kernel: &KernelFile,
        mode: DeformMode,
        method: OrientationMethod,
        min_slope_ratio: f64,
    ) -> Result<Self, GeometryError> {
        let meta = kernel.meta();
        let u64s: Vec<DVec3> = kernel
            .unit_displacement()
            .iter()
            .map(|u| DVec3::from(u.map(|v| v as f64)))
            .collect();
        let cubic = VolumeCubic::of(&kernel.mesh(), &u64s);
        let missing = || GeometryError::Missing {
            path: kernel.path().display().to_string(),
            mode,
        };
        let follow = match mode {
            DeformMode::Precomputed => None,
            _ => {
                let o = meta.orientation.as_ref().ok_or_else(missing)?;
                if meta.orientation_predates_fitted_force() {
                    return Err(GeometryError::FittedForceStale {
                        path: kernel.path().display().to_string(),
                        mode,
                    });
                }
                let c = &meta.settings.motion.c;
                let orientation = Orientation::new(
                    method,
                    [c[6], c[7], c[8]],
                    meta.side,
                    Some(o.volume_forms.l),
                    min_slope_ratio,
                );
                // A fitted supine force is the first basis function (EQUATIONS.md §3.3).
                let orientation = if o.fitted_supine_force {
                    orientation.with_fitted_supine()
                } else {
                    orientation
                };
                let (forms, sh) = if mode == DeformMode::Sh {
                    let sh = meta.sh.as_ref().ok_or_else(missing)?;
                    (
                        sh.volume_forms.clone(),
                        Some((sh.alpha, sh.projection.clone())),
                    )
                } else {
                    (o.volume_forms.clone(), None)
                };
                Some(Follow {
                    mode,
                    forms,
                    orientation,
                    sh,
                    cache: None,
                })
            }
        };
        Ok(Self {
            side: meta.side,
            kernel_id: kernel.id(),
            cubic,
            start_volume_ml: cubic.coeffs[0] / 1000.0,
            follow,
            hilum_mm: None,
            fold_free: meta.fold_free,
        })
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
    base_ml: Option<f64>,
    collapse: f64,
    cycle_start: u64,
    cycle: u32,
    changed_at: Option<u64>,
    /// This tick's volume change above FRC from the patient's signal (whole patient, before the
    /// share), whether it is inhaling, and its weight against the model's (rising from 0 to 1 over
    /// [`signal::TAKEOVER_TICKS`] when the signal takes over); `None`: the model's cycle ([`signal`]).
    driven: Option<(f64, bool, f64)>,
    /// The tidal volume (whole patient) of the breath the lung started with: the healthy breath a
    /// disease's cycles are measured against when the patient's signal drives the lung
    /// ([`Self::tidal_fraction`]).
    healthy_tv_ml: f64,
    /// What this lung's share of the patient's signal is multiplied by this tick (exactly 1 while
    /// every lung breathes its healthy breath; [`share_signal`]).
    signal_factor: f64,
}

impl LungBreath {
    /// A lung following `breathing`, taking `share` of its volume change above FRC.
    pub fn new(breathing: Breathing, share: f64) -> Self {
        Self {
            healthy_tv_ml: breathing.boundary().tv_ml,
            signal_factor: 1.0,
            breathing,
            next: None,
            share,
            held_ml: None,
            offset_mm: [0.0; 3],
            base_ml: None,
            collapse: 0.0,
            cycle_start: 0,
            cycle: 0,
            changed_at: None,
            driven: None,
        }
    }

    /// This lung's breath now against the healthy one it started with: its cycle's tidal volume
    /// over the healthy tidal volume (exactly 1 for a healthy lung), 0 for a held lung (it takes no
    /// breath); 1 where either is not a usable volume.
    fn tidal_fraction(&self) -> f64 {
        if self.held_ml.is_some() {
            return 0.0;
        }
        let tv = self.breathing.boundary().tv_ml;
        if self.healthy_tv_ml > 0.0 && tv.is_finite() && tv >= 0.0 {
            tv / self.healthy_tv_ml
        } else {
            1.0
        }
    }

    /// Carry on with the model from where the signal left the lungs: place the cycle at the tick
    /// whose volume change above FRC is nearest `volume_ml` on the same branch (inhaling or
    /// exhaling), so the volume does not jump. One pass over the cycle's ticks, nothing allocated.
    pub fn resume_model_at(&mut self, tick: u64, volume_ml: f64, inhaling: bool) {
        let b = &self.breathing;
        let (ct, it) = (b.cycle_ticks() as u64, b.inhale_ticks() as u64);
        let frc = b.boundary().frc_ml;
        let (from, to) = if inhaling { (0, it) } else { (it, ct) };
        let mut best = (f64::INFINITY, from);
        for local in from..to.max(from + 1).min(ct) {
            let d = (b.volume_at(local) - frc - volume_ml).abs();
            if d < best.0 {
                best = (d, local);
            }
        }
        let local = best.1;
        // A cycle cannot start before tick 0: early on, the nearest start is tick 0's.
        self.cycle_start = tick.saturating_sub(local);
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

    /// Volume at the start of an inhalation, ml (`None`: the lung's own FRC volume): a collapsed
    /// lung breathes from less, a hyper-expanded one from more (EQUATIONS.md §4).
    pub fn set_base_volume_ml(&mut self, base_ml: Option<f64>) {
        self.base_ml = base_ml;
    }

    /// Collapse towards the hilum, `c ∈ [0, 1]` (EQUATIONS.md §4.1; 0: none).
    pub fn set_collapse(&mut self, collapse: f64) {
        self.collapse = collapse.clamp(0.0, 1.0);
    }

    /// Breathing cycles completed.
    pub fn cycle(&self) -> u32 {
        self.cycle
    }

    /// Held volume, if the lung does not breathe.
    pub fn held_ml(&self) -> Option<f64> {
        self.held_ml
    }

    /// Collapse towards the hilum.
    pub fn collapse(&self) -> f64 {
        self.collapse
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
    /// The `[breathing]` signal cannot be followed as configured.
    #[error("[breathing] {0}")]
    Signal(String),
    /// A kernel cannot serve the scene's mode.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// The scene's disease state cannot be run on these lungs.
    #[error("the scene's [disease]: {0}")]
    Disease(#[from] disease::DiseaseRunError),
    /// The scene's `[disease]` table does not fit its lungs.
    #[error("the scene's {0}")]
    DiseaseScene(#[from] lung_model::scene_disease::DiseaseSceneError),
}

/// What one lung's tick says about the frame's state.
struct LungTick {
    /// The lung is on its inhaling branch.
    inhaling: bool,
    /// The pose lay outside the fitted orientations (weights clamped).
    orientation_limited: bool,
    /// The volume, scale or coefficients were not finite: the lung was drawn at rest instead.
    non_finite: bool,
}

/// How the patient's signal is shared between the lungs this tick (issue 35 item 4, EQUATIONS.md
/// §4.7's decision for a recorded breath, applied to a live one): the signal is the volume the
/// patient breathes, and the lungs share it by compliance — each its share times its breath's
/// tidal fraction ([`LungBreath::tidal_fraction`]), normalised so the lungs together still take the
/// whole signal. A collapsing lung's part of the breath moves to the other lung; a held lung takes
/// none. While every lung breathes its healthy breath the factor is exactly 1 (frames bit for bit
/// as before). A few multiplies, no allocation.
fn share_signal(lungs: &mut [(LungGeometry, LungBreath)]) {
    if lungs.iter().all(|(_, b)| b.tidal_fraction() == 1.0) {
        for (_, b) in lungs.iter_mut() {
            b.signal_factor = 1.0;
        }
        return;
    }
    let total: f64 = lungs
        .iter()
        .map(|(_, b)| b.share * b.tidal_fraction())
        .sum();
    for (_, b) in lungs.iter_mut() {
        b.signal_factor = if total > 0.0 && total.is_finite() {
            b.tidal_fraction() / total
        } else {
            1.0
        };
    }
}

/// One lung's part of a tick: its volume on its breath (or held), the breathing scale solved for
/// that volume (on the collapsed cubic for a collapsed lung), the force coefficients for the
/// patient's gravity, and what a heads-up display shows of the breath, all written into `slot`.
/// No allocation.
fn lung_tick(
    geometry: &mut LungGeometry,
    breath: &mut LungBreath,
    tick: u64,
    gravity: DVec3,
    slot: &mut LungFrame,
    counts: &mut StageCounts,
) -> LungTick {
    let local = breath.local_tick(tick);
    let ct = breath.breathing.cycle_ticks();
    let mut flags = lung_flags::ACTIVE;
    let volume = match breath.held_ml {
        Some(v) => {
            flags |= lung_flags::HELD;
            v
        }
        None => {
            let (delta, inhaling) = match breath.driven {
                Some((volume_ml, inhaling, w)) if w >= 1.0 => {
                    (volume_ml * breath.share * breath.signal_factor, inhaling)
                }
                Some((volume_ml, inhaling, w)) => {
                    // The signal taking over: blended from the model's breath, no jump.
                    let (model, _) = breath.delta_at(local);
                    let driven = volume_ml * breath.share * breath.signal_factor;
                    (w * driven + (1.0 - w) * model, inhaling)
                }
                None => breath.delta_at(local),
            };
            if inhaling {
                flags |= lung_flags::INHALING;
            }
            breath.base_ml.unwrap_or(geometry.start_volume_ml) + delta
        }
    };
    if breath.changed_at == Some(tick) {
        flags |= lung_flags::CYCLE_CHANGED;
    }
    let delta_mm3 = (volume - geometry.start_volume_ml) * 1000.0;
    // Past the range the kernel was checked free of folds (a collapsing lung is drawn on another
    // field): said in the frame, so a crossed surface is never drawn unannounced.
    if breath.collapse == 0.0
        && volume.is_finite()
        && geometry
            .fold_free
            .is_some_and(|f| !f.contains(volume - geometry.start_volume_ml))
    {
        flags |= lung_flags::PAST_FOLD_FREE;
    }
    // A collapsed lung (EQUATIONS.md §4.1): its breathing scale is solved on the collapsed
    // cubic for the volume above the collapsed lung's own (exactly the healthy solve at 0).
    let collapse = breath.collapse;
    let solve = |cubic: &VolumeCubic| {
        if collapse == 0.0 {
            cubic.solve_delta(delta_mm3)
        } else {
            let k = 1.0 - collapse;
            let collapsed_ml = geometry.start_volume_ml * k * k * k;
            lung_model::disease::scale_on_collapsed(cubic, collapse, volume - collapsed_ml)
        }
    };
    let mut orientation_limited = false;
    let scale = match &mut geometry.follow {
        None => solve(&geometry.cubic),
        Some(follow) => {
            let (cubic, limited) = follow.coefficients(gravity, slot, counts);
            orientation_limited = limited;
            solve(&cubic)
        }
    };
    let coeffs_finite = slot.coeffs.iter().all(|c| c.is_finite());
    let non_finite = !(scale.is_finite() && volume.is_finite() && coeffs_finite);
    if !non_finite {
        slot.volume_ml = volume as f32;
        slot.deform_scale = scale as f32;
    } else {
        // Unreachable for validated scenes and kernels; a NaN must never reach a frame.
        slot.volume_ml = geometry.start_volume_ml as f32;
        slot.deform_scale = 0.0;
        slot.coeffs = [0.0; ipc_types::MAX_COEFFS];
    }
    slot.kernel_id = geometry.kernel_id;
    slot.phase = (local as f64 / ct as f64) as f32;
    slot.cycle = breath.cycle;
    slot.offset_mm = breath.offset_mm.map(|v| v as f32);
    if collapse != 0.0 {
        slot.collapse = collapse as f32;
        slot.hilum_mm = geometry.hilum_mm.unwrap_or_default().map(|v| v as f32);
    }
    // What a heads-up display shows of this lung's breath (no effect on the motion).
    let b = &breath.breathing;
    slot.cycle_ticks = ct;
    slot.inhale_ticks = b.inhale_ticks();
    slot.pressure_cmh2o = match breath.held_ml {
        Some(_) => b.boundary().rp_cmh2o as f32,
        None => b.pressure_at(local) as f32,
    };
    slot.tidal_ml = match breath.held_ml {
        Some(_) => 0.0,
        None => (b.boundary().tv_ml * breath.share) as f32,
    };
    slot.flags = flags;
    LungTick {
        inhaling: flags & lung_flags::INHALING != 0,
        orientation_limited,
        non_finite,
    }
}

impl Follow {
    /// The force weights for `gravity` (cached while the patient has not moved) written into
    /// `slot` as the mode's coefficients (the four weights, or their SH projection), with the
    /// volume cubic for those weights and whether the weights were limited.
    fn coefficients(
        &mut self,
        gravity: DVec3,
        slot: &mut LungFrame,
        counts: &mut StageCounts,
    ) -> (VolumeCubic, bool) {
        let key = gravity.to_array().map(f64::to_bits);
        let (w, limited, cubic) = match &self.cache {
            Some((k, w, limited, cubic)) if *k == key => (*w, *limited, *cubic),
            _ => {
                let (w, limited) = self.orientation.weights(gravity);
                let cubic = self.forms.cubic(&w);
                self.cache = Some((key, w, limited, cubic));
                counts.orientation_evaluations += 1;
                (w, limited, cubic)
            }
        };
        slot.coeff_kind = self.mode.coeff_kind();
        match &self.sh {
            None => {
                slot.coeff_count = 4;
                for (c, w) in slot.coeffs.iter_mut().zip(w) {
                    *c = w as f32;
                }
            }
            Some((alpha, p)) => {
                counts.sh_projections += 1;
                let n2 = p.len() / 4;
                slot.coeff_count = n2 as u32;
                for (k, c) in slot.coeffs.iter_mut().take(n2).enumerate() {
                    let f = w[0] * p[k]
                        + w[1] * p[n2 + k]
                        + w[2] * p[2 * n2 + k]
                        + w[3] * p[3 * n2 + k];
                    *c = (alpha * f) as f32;
                }
            }
        }
        (cubic, limited)
    }
}

/// How often each stage of the tick did its work (`lungdyn scene run --json`): what a scene does
/// not need is never computed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct StageCounts {
    /// Ticks stepped.
    pub ticks: u64,
    /// Pose → force weights evaluations (orientation modes; only when gravity changed).
    pub orientation_evaluations: u64,
    /// Per-lung volume → scale solves.
    pub volume_solves: u64,
    /// SH force coefficient projections (sh mode).
    pub sh_projections: u64,
    /// Disease cycles moved into the lungs.
    pub disease_cycles: u64,
    /// PV models evaluated (eq. 5.11 tables built from constants); 0 for a `[pv] waveform` scene.
    pub pv_models_built: u64,
}

/// What became of a live intervention.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LiveAction {
    /// Queued: applied when the next cycle is prepared.
    Queued,
    /// Dropped: too many actions within one breath.
    QueueFull,
    /// The scene has no tension pneumothorax to act on.
    NoTension,
}

/// The deterministic engine state.
#[derive(Debug, Clone)]
pub struct EngineCore {
    lungs: Vec<(LungGeometry, LungBreath)>,
    staleness_ticks: u64,
    gravity_room: DVec3,
    gravity_body: DVec3,
    pose_invalid: bool,
    patient_pose: Pose,
    last_good_pose_tick: Option<u64>,
    last_tracker_tick: Option<u64>,
    last_tracker_frame: u64,
    disease: Option<disease::DiseaseRun>,
    /// A remote source's announced disease cycle (a site's engine): put into the lungs at its tick.
    remote_pending: Option<remote::RemotePending>,
    /// The last one put in, freed off the tick (by the next state applied).
    remote_spent: Option<remote::RemotePending>,
    /// The patient's signal, when the scene breathes with it (`[breathing] source = "signal"`).
    signal: Option<signal::SignalDrive>,
    /// The patient's breath a remote source follows (a site's engine, issue 35): played each tick.
    remote_live: Option<remote::RemoteLive>,
    /// How late the patient's turns reached this site.
    turn_lag: remote::TurnLag,
    counts: StageCounts,
}

impl EngineCore {
    /// How often each stage did its work so far.
    pub fn stage_counts(&self) -> StageCounts {
        let mut c = self.counts;
        if let Some(disease::DiseaseRun::Tension(run)) = &self.disease {
            c.disease_cycles = run.cycles_run;
        }
        c
    }

    /// Build the engine for `scene`: precompute the breathing cycle and load each lung's kernel
    /// (never baking: a lung without a kernel is an error that says how to get one).
    pub fn new(scene: &Scene) -> Result<Self, CoreError> {
        let mut lungs = Vec::new();
        let mut meshes = Vec::new();
        for &side in &scene.lungs.sides {
            let kernel = scene.lung_kernel(side)?;
            lungs.push(LungGeometry::from_kernel(
                &kernel,
                scene.lungs.mode,
                scene.engine.orientation,
                scene.engine.min_slope_ratio,
            )?);
            // Only a disease scene needs the surfaces (the hilum, the box): model only what the
            // scene requires.
            if scene.disease.is_some() {
                meshes.push(kernel.mesh());
            }
        }
        let mut core = Self::with_geometry(scene, lungs)?;
        if scene.disease.is_some() {
            core.start_disease(scene, &meshes)?;
        }
        Ok(core)
    }

    /// Prepare the scene's disease state on these lungs (`meshes` in the scene's lung order) and
    /// apply what holds from the start (EQUATIONS.md §4; [`disease`]).
    pub fn start_disease(
        &mut self,
        scene: &Scene,
        meshes: &[lung_model::mesh::TriMesh],
    ) -> Result<(), CoreError> {
        let Some(spec) = scene.disease_spec()? else {
            return Ok(());
        };
        let (inhale, exhale, boundary) = scene.pv_model().map_err(CoreError::Pv)?;
        // A waveform scene's course runs on the ventilator's recorded breath, which every lung
        // plays before the disease (EQUATIONS §4.7).
        let recorded = match (&scene.pv.waveform, self.lungs.first()) {
            (Some(_), Some((_, breath))) => Some(breath.breathing.clone()),
            _ => None,
        };
        let normal = lung_model::disease::ventilated::normal_breathing(
            recorded.as_ref(),
            scene.timing(),
            inhale,
            exhale,
            boundary,
        );
        let mut baselines = Vec::new();
        for ((geometry, breath), mesh) in self.lungs.iter_mut().zip(meshes) {
            let b = lung_model::disease::LungBaseline::of(mesh, geometry.side, breath.share)
                .map_err(disease::DiseaseRunError::from)?;
            geometry.hilum_mm = Some(b.hilum_mm);
            baselines.push(b);
        }
        let ventilator = scene
            .ventilator(&baselines)
            .map_err(CoreError::Pv)?
            .map(|(v, _)| v);
        let mut run =
            disease::DiseaseRun::prepare(&spec, &normal, &baselines, ventilator.as_ref())?;
        if let disease::DiseaseRun::Closed(setups, _) = &mut run {
            for setup in setups.iter_mut() {
                if let Some((_, breath)) = self.lungs.iter_mut().find(|(g, _)| g.side == setup.side)
                {
                    disease::apply(setup, breath, true);
                }
            }
        }
        if let disease::DiseaseRun::Tumour(t) = &mut run {
            if let (Some((_, breath)), Some(b)) = (
                self.lungs.iter_mut().find(|(g, _)| g.side == t.side),
                t.breathing.take(),
            ) {
                breath.breathing = b;
            }
        }
        self.disease = Some(run);
        Ok(())
    }

    /// Drive this engine from a remote source's control states only: drop its own disease course
    /// (the states carry the source's; the hilum found for it stays for a collapsing lung) and its
    /// own respiratory signal (the states carry the source's patient's breath).
    pub fn follow_remote(&mut self) {
        self.disease = None;
        // A site breathes with the source's patient through the states; a signal of its own (a
        // site scene with `[breathing] source = "signal"`) has no input here and would say "lost".
        self.signal = None;
    }

    /// The disease state being run, if any.
    pub fn disease(&self) -> Option<&disease::DiseaseRun> {
        self.disease.as_ref()
    }

    /// The disease state being run, to read what happened (interventions applied).
    pub fn disease_mut(&mut self) -> Option<&mut disease::DiseaseRun> {
        self.disease.as_mut()
    }

    /// Prepare the disease state's next cycle (allocates; call after a frame is published, never in
    /// the tick). Nothing to do without a disease state.
    pub fn prepare_ahead(&mut self) -> Result<(), CoreError> {
        match &mut self.disease {
            Some(d) => Ok(d.prepare_ahead()?),
            None => Ok(()),
        }
    }

    /// The disease state's next cycle to build, if one is to be prepared (cheap; the build is
    /// [`disease::Recipe::build`], for a worker thread).
    pub fn next_recipe(&mut self) -> Result<Option<disease::Recipe>, CoreError> {
        match &mut self.disease {
            Some(d) => Ok(d.next_recipe()?),
            None => Ok(None),
        }
    }

    /// Hand over a cycle built from [`Self::next_recipe`].
    pub fn deliver(&mut self, cycle: disease::CourseCycle) {
        if let Some(d) = &mut self.disease {
            d.deliver(cycle);
        }
    }

    /// Whether the tick `tick` starts a disease cycle whose preparation was requested but not yet
    /// delivered: the caller waits for it before stepping (determinism over thread timing).
    pub fn due_undelivered(&self, tick: u64) -> bool {
        self.disease
            .as_ref()
            .is_some_and(|d| d.due_undelivered(tick, &self.lungs))
    }

    /// Bring a fresh core to where an uninterrupted run stands just before `tick`, so that
    /// `step(tick, ..)` and every later step show the breath an uninterrupted run shows there: the
    /// resume of a restarted engine (`engine --start-tick`). A healthy core needs nothing: its
    /// breath is a function of the tick alone ([`LungBreath::local_tick`] skips whole cycles
    /// arithmetically). A disease state evolves cycle by cycle, so its ticks `0..tick` are replayed
    /// without tracker input, each cycle built in place as [`Self::prepare_ahead`] does (≈ 40 ms a
    /// breath). What the replay cannot know: a trainee's live interventions sent to the engine that
    /// died (scene-timed events replay). Tracker-derived state (pose, staleness) starts afresh and
    /// is flagged as such until the first sample arrives, one tick later.
    pub fn resume_at(&mut self, tick: u64) -> Result<(), CoreError> {
        if self.disease.is_none() {
            return Ok(());
        }
        let mut scratch = EngineFrame::default();
        for t in 0..tick {
            self.step(t, None, &mut scratch);
            self.prepare_ahead()?;
        }
        Ok(())
    }

    /// A trainee's action arriving at `tick` (a live intervention). What became of it:
    /// [`LiveAction`].
    pub fn intervene(
        &mut self,
        tick: u64,
        kind: lung_model::disease::tension::Intervention,
        side: Side,
    ) -> LiveAction {
        self.intervene_tagged(tick, kind, side, 0)
    }

    /// [`Self::intervene`] with the sender's `tag` (its sequence number), which comes back with
    /// the applied event from [`disease::TensionRun::take_new_events`].
    pub fn intervene_tagged(
        &mut self,
        tick: u64,
        kind: lung_model::disease::tension::Intervention,
        side: Side,
        tag: u64,
    ) -> LiveAction {
        match &mut self.disease {
            Some(disease::DiseaseRun::Tension(run)) => {
                if run.intervene_live(tick, kind, side, tag) {
                    LiveAction::Queued
                } else {
                    LiveAction::QueueFull
                }
            }
            _ => LiveAction::NoTension,
        }
    }

    /// The side of the scene's tension pneumothorax (where a live action without a side goes);
    /// `None` without one.
    pub fn tension_side(&self) -> Option<Side> {
        match &self.disease {
            Some(disease::DiseaseRun::Tension(run)) => Some(run.affected()),
            _ => None,
        }
    }

    /// Build from a scene and lung geometries already loaded (tests, benchmarks, tools that hold
    /// the lung models): today's behaviour, both lungs on the scene's PV cycle split by FRC volume.
    pub fn with_geometry(scene: &Scene, lungs: Vec<LungGeometry>) -> Result<Self, CoreError> {
        let mut counts = StageCounts::default();
        // A waveform scene plays the recording above the preset's FRC; no PV model is built.
        let breathing = match scene.waveform_breathing().map_err(CoreError::Pv)? {
            Some(b) => b,
            None => {
                let (inhale, exhale, boundary) = scene.pv_model().map_err(CoreError::Pv)?;
                counts.pv_models_built += 1;
                Breathing::from_constants(&inhale, &exhale, boundary, &scene.timing())
                    .map_err(CoreError::Breathing)?
            }
        };
        let frc = breathing.boundary().frc_ml;
        let signal = match scene.breathing.source {
            lung_model::scene::BreathSource::Signal => {
                Some(signal::SignalDrive::new(scene, breathing.boundary().tv_ml)?)
            }
            lung_model::scene::BreathSource::Model => None,
        };
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
            gravity_room: DVec3::from(scene.engine.gravity_room).normalize(),
            gravity_body: SUPINE_GRAVITY,
            pose_invalid: false,
            patient_pose: Pose::IDENTITY,
            last_good_pose_tick: None,
            last_tracker_tick: None,
            last_tracker_frame: 0,
            disease: None,
            remote_pending: None,
            remote_spent: None,
            signal,
            remote_live: None,
            turn_lag: remote::TurnLag::default(),
            counts,
        })
    }

    /// The patient's signal and its follower, when the scene breathes with it.
    pub fn signal(&self) -> Option<&signal::SignalDrive> {
        self.signal.as_ref()
    }

    /// The active lungs' geometry.
    pub fn geometry(&self) -> impl Iterator<Item = &LungGeometry> {
        self.lungs.iter().map(|(g, _)| g)
    }

    /// Each lung's current cycle start tick, in the scene's lung order.
    pub fn cycle_starts(&self) -> impl Iterator<Item = u64> + '_ {
        self.lungs.iter().map(|(_, b)| b.cycle_start)
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
        let (mut state, mut fault_word) = self.take_tracker(tick, input, out);
        let gravity = self.gravity_body;
        self.counts.ticks += 1;
        self.counts.volume_solves += self.lungs.len() as u64;
        if let Some(d) = &mut self.disease {
            d.before_tick(tick, &mut self.lungs);
        }
        out.signal = ipc_types::SignalFollowed::default();
        if let Some(drive) = &mut self.signal {
            state |= drive.tick(tick, input, &mut self.lungs);
            out.signal = drive.wire();
        }
        if let Some(live) = &mut self.remote_live {
            state |= live.tick(tick, &mut self.lungs);
            if let Some(lag) = live.heard.take() {
                self.turn_lag.add(lag);
            }
        }
        if self.remote_pending.as_ref().is_some_and(|p| tick >= p.tick) {
            if let Some(mut p) = self.remote_pending.take() {
                p.put_into(&mut self.lungs);
                self.remote_spent = Some(p);
            }
        }
        // With a breath from the patient (the signal, or a source's), each lung's cycle advanced
        // first (as its tick would: a change pending for the cycle that starts now takes effect),
        // so the signal is shared by the breaths this tick draws; nothing to share otherwise.
        if self.lungs.iter().any(|(_, b)| b.driven.is_some()) {
            for (_, b) in self.lungs.iter_mut() {
                b.local_tick(tick);
            }
            share_signal(&mut self.lungs);
        }
        out.lungs = [LungFrame::default(); NUM_LUNGS];
        for (k, (geometry, breath)) in self.lungs.iter_mut().enumerate() {
            let slot = &mut out.lungs[geometry.side.index()];
            let lung = lung_tick(geometry, breath, tick, gravity, slot, &mut self.counts);
            if k == 0 && lung.inhaling {
                state |= engine_state::INHALING;
            }
            if lung.orientation_limited {
                state |= engine_state::ORIENTATION_LIMITED;
            }
            if lung.non_finite {
                fault_word = fault::NON_FINITE_VOLUME;
            }
        }
        out.layout_version = LAYOUT_VERSION;
        out.state = state;
        out.fault = fault_word;
        out._pad = 0;
        out.tick = tick;
        out.tracker_frame = self.last_tracker_frame;
        out.patient_pose = self.patient_pose;
    }

    /// The tracker's part of a tick: take the frame's patient pose (a pose that is not a rotation
    /// is refused like a missing sample), copy its stamps into `out`, and say how fresh the
    /// tracker and the pose are (the state bits, and `TRACKER_LOST` past the staleness limit).
    fn take_tracker(
        &mut self,
        tick: u64,
        input: Option<&TrackerFrame>,
        out: &mut EngineFrame,
    ) -> (u32, u32) {
        let mut state = 0u32;
        let mut fault_word = fault::NONE;
        match input {
            Some(frame) => {
                state |= engine_state::TRACKER_FRESH;
                self.last_tracker_tick = Some(tick);
                self.last_tracker_frame = frame.frame_number;
                out.stamps = frame.stamps;
                if let Some(pose) = frame.valid_tool(TOOL_PATIENT) {
                    // A pose that is not a rotation is refused like a missing sample: it would
                    // shear the registration and has no gravity direction.
                    match gravity_in_body(pose.quat, self.gravity_room) {
                        Ok(g) => {
                            self.patient_pose = pose;
                            self.gravity_body = g;
                            self.last_good_pose_tick = Some(tick);
                            self.pose_invalid = false;
                        }
                        Err(_) => self.pose_invalid = true,
                    }
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
        if self.pose_invalid {
            state |= engine_state::POSE_INVALID;
        }
        (state, fault_word)
    }
}

/// A core over the generated default lungs at 500 vertices with Table 6.1's motion (no bake): the
/// unit tests' engine where the kernel's exact data does not matter.
#[cfg(test)]
pub(crate) fn generated_core(scene: &Scene) -> EngineCore {
    let lungs = [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            let m = LungModel::build(
                side,
                lung_model::mesh::generate::lung(side, 500).unwrap(),
                &lung_model::deform::MotionConstants::table_6_1(side),
            )
            .unwrap();
            LungGeometry::of(&m)
        })
        .collect();
    EngineCore::with_geometry(scene, lungs).unwrap()
}

#[cfg(test)]
mod tests;
