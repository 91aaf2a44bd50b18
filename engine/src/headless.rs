//! The engine's tick function run without processes, shared memory or a GPU: the scene (its kernels
//! prepared: this crate never bakes) stepped for a number of ticks as fast as it runs, fed by the
//! caller's tracker frames, each frame handed back, and a per-lung summary of what the renderer would
//! have drawn. `lungdyn scene run` is its front (`lungdyn_launcher::scene_check`), which prepares the
//! kernels, supplies a still patient in the scene's posture and reports.
//!
//! The frames are the ones the engine process would publish for the same inputs (the same
//! [`EngineCore::step`] and [`EngineCore::prepare_ahead`], in the same order).

use ipc_types::{EngineFrame, TrackerFrame, NUM_LUNGS};
use lung_model::scene::Scene;

use crate::runtime::{CoreError, EngineCore};

/// One lung's breathing over a headless run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungSummary {
    /// Smallest and largest volume over the run, ml (infinite when the lung was never active).
    pub volume_range_ml: (f64, f64),
    /// The last complete breath: its smallest and largest volume (ml) and its length in ticks.
    pub last_breath: Option<(f64, f64, u64)>,
}

impl LungSummary {
    const EMPTY: LungSummary = LungSummary {
        volume_range_ml: (f64::INFINITY, f64::NEG_INFINITY),
        last_breath: None,
    };

    /// Tidal volume (ml) and rate (breaths per minute) of the last complete breath at `tick_hz`;
    /// without one, the run's volume range and no rate.
    pub fn tidal_and_rate(&self, tick_hz: f64) -> (f64, Option<f64>) {
        match self.last_breath {
            Some((lo, hi, len)) if len > 0 => (hi - lo, Some(60.0 * tick_hz / len as f64)),
            _ => (self.volume_range_ml.1 - self.volume_range_ml.0, None),
        }
    }
}

/// What a headless run leaves: the core (its stage counts, its disease course), the last frame and
/// each lung's summary.
pub struct HeadlessRun {
    /// The engine core after the last tick.
    pub core: EngineCore,
    /// The last frame it wrote.
    pub last: EngineFrame,
    /// Per lung slot (`Side::index`).
    pub lungs: [LungSummary; NUM_LUNGS],
    /// Frames in which an active lung's volume or deformation scale was not finite (a bug if not 0).
    pub non_finite_frames: u64,
}

/// Step `scene` for `ticks` ticks: tick `t`'s input is `input(t)`, and `on_frame(t, &frame)` sees
/// each frame as written. The scene must name a kernel for every lung (`lungdyn scene prepare`).
pub fn run(
    scene: &Scene,
    ticks: u64,
    input: &mut dyn FnMut(u64) -> TrackerFrame,
    on_frame: &mut dyn FnMut(u64, &EngineFrame),
) -> Result<HeadlessRun, CoreError> {
    run_core(EngineCore::new(scene)?, ticks, input, on_frame)
}

/// [`run`] on a core already made (e.g. over geometry in memory, as the tests make it).
pub fn run_core(
    core: EngineCore,
    ticks: u64,
    input: &mut dyn FnMut(u64) -> TrackerFrame,
    on_frame: &mut dyn FnMut(u64, &EngineFrame),
) -> Result<HeadlessRun, CoreError> {
    run_while(core, ticks, input, &mut |tick, f| {
        on_frame(tick, f);
        true
    })
}

/// [`run_core`] for at most `ticks` ticks, stopping after the first frame for which `on_frame`
/// returns `false` (`lungdyn export gltf` stops once it has the breath it wants).
pub fn run_while(
    mut core: EngineCore,
    ticks: u64,
    input: &mut dyn FnMut(u64) -> TrackerFrame,
    on_frame: &mut dyn FnMut(u64, &EngineFrame) -> bool,
) -> Result<HeadlessRun, CoreError> {
    let mut f = EngineFrame::default();
    let mut lungs = [LungSummary::EMPTY; NUM_LUNGS];
    // The breath in progress per lung: its volume range and the tick it started; its cycle number.
    let mut current = [(f64::INFINITY, f64::NEG_INFINITY, 0u64); NUM_LUNGS];
    let mut cycle = [0u32; NUM_LUNGS];
    let mut non_finite_frames = 0u64;
    for tick in 0..ticks {
        let frame_in = input(tick);
        core.step(tick, Some(&frame_in), &mut f);
        let go_on = on_frame(tick, &f);
        for (k, l) in f.lungs.iter().enumerate() {
            if !l.is_active() {
                continue;
            }
            let v = l.volume_ml as f64;
            if !(v.is_finite() && l.deform_scale.is_finite()) {
                non_finite_frames += 1;
            }
            let s = &mut lungs[k];
            s.volume_range_ml = (s.volume_range_ml.0.min(v), s.volume_range_ml.1.max(v));
            let c = &mut current[k];
            if l.cycle != cycle[k] {
                s.last_breath = Some((c.0, c.1, tick - c.2));
                *c = (f64::INFINITY, f64::NEG_INFINITY, tick);
                cycle[k] = l.cycle;
            }
            *c = (c.0.min(v), c.1.max(v), c.2);
        }
        if !go_on {
            break;
        }
        core.prepare_ahead()?;
    }
    Ok(HeadlessRun {
        core,
        last: f,
        lungs,
        non_finite_frames,
    })
}
