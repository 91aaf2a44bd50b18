//! The quality governor (`[render] governor = "hold-deadline"`, the default; docs/LATENCY.md "The
//! governor"): when the renderer's frames take longer than its share of the 16.7 ms frame, it draws
//! less — one step at a time, in a fixed order — and takes the steps back when there is time again.
//!
//! **The order** ([`ladder`]), cheapest loss first, each step only where the scene has something to
//! give up: multisampling off (4× → 1×), then the draw level of detail one level coarser at a time
//! (the same deformed vertices under fewer triangles: [`crate::lod`]), then the deformation pass
//! limited to the vertices the drawn level uses, their normals from its triangles ("drawn vertices
//! only": a coarse level references a few percent of the vertices, and moving all of them was most
//! of a coarse frame's GPU time on lavapipe), then the translucent look drawn opaque (its two extra
//! passes over half-float targets). The deformation's accuracy — its mode, its bands, the position
//! of every vertex drawn — is not touched by these: each drawn vertex is where the full pass puts
//! it, bit for bit, and what changes is what is drawn and how it is shaded. **Accuracy steps** come
//! only where the scene opts in (`[render] governor_least_bands = N`) and only after every drawing
//! step: the spherical-harmonic mode capped one band at a time down to N bands (its force
//! coefficients past N² dropped; the cost in mm per band is measured in docs/LATENCY.md). A render-scale step
//! (fewer pixels) is not among them: on the software rasteriser this project is measured on, the
//! frame's cost does not follow its pixels (the default lungs at 800 × 600 and 200 × 150: 23.3 and
//! 22.0 ms, `render_looks -- --lod`), and it wants an upscaling pass and a HUD drawn after it.
//!
//! **What it measures**: each frame's cost from the renderer's wake to the wait on its GPU fence
//! returning (the CPU's encode and the GPU's work: what must fit), against a target — the frame's
//! deadline less the tracker bridge's and the engine's budgets (`[processes.budget_ms]`; 13.7 ms by
//! default), the time left to the renderer once its inputs have arrived.
//!
//! **When it moves** (frames, not clock time: a run's decisions follow from its frame costs alone):
//! - down one step when the 75th percentile of the last [`DOWN_WINDOW`] frames is over the target,
//!   or sooner, after [`FAST_FRAMES`], when each of those took over [`FAR_OVER`] times the target
//!   (a heavy scene's start: the descent took 16 frames a step, each of them late);
//!   the first [`SETTLE`] frames after any change are not counted (a new pipeline's first use);
//! - at the last step and still over: at its floor, said once ([`Change::Floor`]) and flagged on
//!   every such frame ([`ipc_types::report_flags::GOVERNOR_FLOOR`]);
//! - up one step after at least [`HOLD_FRAMES`] frames at the present step, when the median of the
//!   last [`UP_WINDOW`] frames times what that step bought when it was taken (the median before it
//!   over the median after it) is at most [`UP_MARGIN`] of the target — a frame predicted to fit
//!   with room to spare, so a cost near the target does not swing between two steps;
//! - a step taken back that has to be given up again within [`RELAPSE_FRAMES`] doubles the hold
//!   before the next try (up to [`MAX_HOLD_FRAMES`], a minute at 60 Hz), and a step kept for
//!   [`RELAPSE_FRAMES`] resets it.
//!
//! Nothing here allocates after [`Governor::new`]; a frame's decision sorts a copy of at most
//! [`UP_WINDOW`] costs on the stack.

use lung_model::scene::{DrawMode, Look, RenderScene};

/// One thing the governor can give up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// Multisampling off (the scene's 4× drawn with one sample per pixel).
    MsaaOff,
    /// The draw level one coarser than the level of detail chooses (again for each such step).
    CoarserLod,
    /// Only the drawn level's vertices deformed, their normals from its triangles.
    DrawnOnly,
    /// The translucent look drawn opaque.
    Opaque,
    /// The spherical-harmonic deformation capped at this many bands (an accuracy step: only where
    /// the scene allows it, `[render] governor_least_bands`, after every drawing step).
    ShBands(u8),
}

impl Step {
    /// In words, for the start line and the change lines.
    pub fn name(self) -> &'static str {
        match self {
            Step::MsaaOff => "MSAA off",
            Step::CoarserLod => "LOD +1",
            Step::DrawnOnly => "drawn vertices only",
            Step::Opaque => "opaque look",
            Step::ShBands(1) => "SH at 1 band",
            Step::ShBands(2) => "SH at 2 bands",
            Step::ShBands(3) => "SH at 3 bands",
            Step::ShBands(4) => "SH at 4 bands",
            Step::ShBands(5) => "SH at 5 bands",
            Step::ShBands(6) => "SH at 6 bands",
            Step::ShBands(7) => "SH at 7 bands",
            // Never built (a cap is 1..7, below a kernel's most bands, 8).
            Step::ShBands(_) => "SH capped",
        }
    }
}

/// What a frame is drawn with below the scene's own quality: the sum of the steps taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Quality {
    /// Multisampling dropped.
    pub msaa_off: bool,
    /// Draw levels coarser than the chosen one.
    pub lod_bias: u8,
    /// Only the drawn level's vertices deformed, normals from its triangles.
    pub drawn_only: bool,
    /// The translucent look drawn opaque.
    pub opaque: bool,
    /// The spherical harmonics capped at this many bands (0: not capped).
    pub sh_bands: u8,
}

impl Quality {
    /// The scene's own quality: nothing given up.
    pub const FULL: Quality = Quality {
        msaa_off: false,
        lod_bias: 0,
        drawn_only: false,
        opaque: false,
        sh_bands: 0,
    };

    /// With the first `taken` of `steps` given up.
    pub fn of(steps: &[Step], taken: usize) -> Self {
        let mut q = Quality::FULL;
        for s in &steps[..taken.min(steps.len())] {
            match s {
                Step::MsaaOff => q.msaa_off = true,
                Step::CoarserLod => q.lod_bias = q.lod_bias.saturating_add(1),
                Step::DrawnOnly => q.drawn_only = true,
                Step::Opaque => q.opaque = true,
                Step::ShBands(b) => q.sh_bands = *b,
            }
        }
        q
    }

    /// The frame report's bits for it ([`ipc_types::report_flags::quality_bits`]).
    pub fn report_bits(self) -> u32 {
        let drawn = if self.drawn_only {
            ipc_types::report_flags::QUALITY_DRAWN_ONLY
        } else {
            0
        };
        ipc_types::report_flags::quality_bits(self.msaa_off, self.lod_bias, self.opaque)
            | drawn
            | ipc_types::report_flags::sh_cap_bits(self.sh_bands)
    }

    /// "full", or what is given up: "MSAA off, LOD +2, drawn vertices only, opaque look".
    pub fn describe(self) -> String {
        ipc_types::report_flags::describe_quality(self.report_bits())
    }
}

/// The steps a scene can give up, in the governor's order: `samples` the scene draws with,
/// `coarser_levels` the draw levels built beyond every triangle (0 with `lod = "off"` or splats),
/// `sh_bands` the most spherical-harmonic bands a lung deforms with (0: not the "sh" mode) — a
/// band at a time down to `[render] governor_least_bands` where the scene allows it, last.
pub fn ladder(
    settings: &RenderScene,
    samples: u32,
    coarser_levels: usize,
    sh_bands: u32,
) -> Vec<Step> {
    let mut steps = Vec::new();
    if samples > 1 {
        steps.push(Step::MsaaOff);
    }
    if settings.mode == DrawMode::Triangles && coarser_levels > 0 {
        steps.extend(std::iter::repeat_n(
            Step::CoarserLod,
            coarser_levels.min(MAX_LOD_STEPS),
        ));
        steps.push(Step::DrawnOnly);
    }
    if settings.look == Look::Translucent {
        steps.push(Step::Opaque);
    }
    if let Some(least) = settings.governor_least_bands {
        let top = sh_bands.min(MAX_SH_BANDS);
        steps.extend((least.max(1)..top).rev().map(|b| Step::ShBands(b as u8)));
    }
    steps
}

/// What the start line says of an accuracy opt-in that has nothing to give up (`least`: the
/// scene's `governor_least_bands`; `steps`: the ladder built): only the "sh" mode's bands above the
/// least can be capped, so a scene in another mode, or with no more bands, is told so rather than
/// left to think the opt-in acts. `None` where it acts or was not asked for.
pub fn idle_accuracy_opt_in(least: Option<u32>, steps: &[Step]) -> Option<String> {
    let least = least?;
    if steps.iter().any(|s| matches!(s, Step::ShBands(_))) {
        return None;
    }
    Some(format!(
        "governor_least_bands = {least} has nothing to cap: only the \"sh\" mode's bands above \
         {least} can be given up, and these lungs have none"
    ))
}

/// Most spherical-harmonic bands a kernel holds (so at most 7 band steps).
pub const MAX_SH_BANDS: u32 = 8;

/// Most draw-level steps (the report's bits hold a bias up to 7).
pub const MAX_LOD_STEPS: usize = 7;
/// Frames after a change not counted (the new pipelines' first use, the targets' first touch).
pub const SETTLE: u32 = 4;
/// Frames whose 75th percentile decides a step down.
pub const DOWN_WINDOW: usize = 12;
/// Frames that decide a step down when each of them is [`FAR_OVER`] times the target or more.
pub const FAST_FRAMES: usize = 4;
/// How far over the target frames must all be for [`FAST_FRAMES`] of them to decide.
pub const FAR_OVER: f64 = 1.5;
/// Frames whose median decides a step up.
pub const UP_WINDOW: usize = 60;
/// Least frames at a step before one is taken back.
pub const HOLD_FRAMES: u32 = 90;
/// Longest hold, after steps taken back and given up again.
pub const MAX_HOLD_FRAMES: u32 = 3600;
/// A step given up again within this many frames of being taken back doubles the hold.
pub const RELAPSE_FRAMES: u32 = 300;
/// A step is taken back when the frame is predicted to take at most this share of the target.
pub const UP_MARGIN: f64 = 0.8;

/// A change the governor made (or its floor reached), for the caller to apply and say.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Change {
    /// One more step given up: `step`, now drawing at `quality`; the frames' 75th percentile that
    /// decided it, ns.
    Down {
        step: Step,
        quality: Quality,
        cost_ns: u64,
    },
    /// One step taken back: `step`, now drawing at `quality`; the median that decided it and the
    /// frame predicted with the step back, ns.
    Up {
        step: Step,
        quality: Quality,
        cost_ns: u64,
        predicted_ns: u64,
    },
    /// Every step given up and the frames still over the target (75th percentile, ns).
    Floor { cost_ns: u64 },
}

/// The governor's state over a run.
#[derive(Debug, Clone)]
pub struct Governor {
    steps: Vec<Step>,
    taken: usize,
    target_ns: u64,
    /// The newest frame costs since the last change (a ring of `UP_WINDOW`).
    ring: [u64; UP_WINDOW],
    len: usize,
    next: usize,
    /// Frames since the last change (counted ones and settling ones).
    since_change: u32,
    /// Per step k: the 75th percentile that gave it up, and the median of the first full window
    /// after (0: not yet measured) — what the step bought.
    before: [u64; MAX_STEPS],
    after: [u64; MAX_STEPS],
    hold: u32,
    /// Frames since the last step taken back (`u32::MAX`: none yet).
    since_up: u32,
    at_floor: bool,
    /// Changes made, and frames at the floor.
    pub changes: u32,
    pub floor_frames: u64,
}

/// Most steps a ladder can have (MSAA, the draw levels, drawn vertices only, the look, the bands).
const MAX_STEPS: usize = 3 + MAX_LOD_STEPS + MAX_SH_BANDS as usize - 1;

impl Governor {
    /// A governor over `steps` (from [`ladder`]) holding frames to `target_ns`.
    pub fn new(steps: Vec<Step>, target_ns: u64) -> Self {
        let mut steps = steps;
        steps.truncate(MAX_STEPS);
        Self {
            steps,
            taken: 0,
            target_ns: target_ns.max(1),
            ring: [0; UP_WINDOW],
            len: 0,
            next: 0,
            since_change: 0,
            before: [0; MAX_STEPS],
            after: [0; MAX_STEPS],
            hold: HOLD_FRAMES,
            since_up: u32::MAX,
            at_floor: false,
            changes: 0,
            floor_frames: 0,
        }
    }

    /// The steps it may take, in order.
    pub fn steps(&self) -> &[Step] {
        &self.steps
    }

    /// The frame cost it holds to, ns.
    pub fn target_ns(&self) -> u64 {
        self.target_ns
    }

    /// Hold frames to `target_ns` from the next frame on.
    pub fn set_target_ns(&mut self, target_ns: u64) {
        self.target_ns = target_ns.max(1);
    }

    /// The quality frames are drawn at now.
    pub fn quality(&self) -> Quality {
        Quality::of(&self.steps, self.taken)
    }

    /// Steps given up now.
    pub fn taken(&self) -> usize {
        self.taken
    }

    /// The report's bits for frames drawn now: the quality and, at the floor,
    /// [`ipc_types::report_flags::GOVERNOR_FLOOR`].
    pub fn report_bits(&self) -> u32 {
        let floor = if self.at_floor {
            ipc_types::report_flags::GOVERNOR_FLOOR
        } else {
            0
        };
        self.quality().report_bits() | floor
    }

    /// Whether every step is given up and frames are still over the target.
    pub fn at_floor(&self) -> bool {
        self.at_floor
    }

    /// The frames before the next one may take a step back (the hold, doubled after relapses).
    pub fn hold(&self) -> u32 {
        self.hold
    }

    /// One drawn frame's cost (wake → GPU done, ns; 0: not measured, ignored): the change to make
    /// before the next frame, if any.
    pub fn observe(&mut self, cost_ns: u64) -> Option<Change> {
        self.since_change = self.since_change.saturating_add(1);
        self.since_up = self.since_up.saturating_add(1);
        // The step last taken back was kept (no change since): the hold is back to its least.
        if self.since_up == RELAPSE_FRAMES && self.since_change >= RELAPSE_FRAMES {
            self.hold = HOLD_FRAMES;
        }
        if self.at_floor {
            self.floor_frames += 1;
        }
        if cost_ns == 0 || self.since_change <= SETTLE {
            return None;
        }
        self.ring[self.next] = cost_ns;
        self.next = (self.next + 1) % UP_WINDOW;
        self.len = (self.len + 1).min(UP_WINDOW);
        if self.len < DOWN_WINDOW {
            // Far over: when every one of the first FAST_FRAMES counted frames took more than
            // FAR_OVER times the target, no window's vote is needed (a heavy scene's start).
            if self.len >= FAST_FRAMES {
                let least = self.quantile(FAST_FRAMES, 0.0);
                if least as f64 > FAR_OVER * self.target_ns as f64 {
                    if self.taken > 0 && self.after[self.taken - 1] == 0 {
                        self.after[self.taken - 1] = self.quantile(FAST_FRAMES, 0.5);
                    }
                    return self.down(self.quantile(FAST_FRAMES, 0.75));
                }
            }
            return None;
        }
        let recent = self.quantile(DOWN_WINDOW, 0.75);
        if self.taken > 0 && self.len == DOWN_WINDOW && self.after[self.taken - 1] == 0 {
            self.after[self.taken - 1] = self.quantile(DOWN_WINDOW, 0.5);
        }
        if recent > self.target_ns {
            return self.down(recent);
        }
        self.at_floor = false;
        self.up()
    }

    fn down(&mut self, recent: u64) -> Option<Change> {
        if self.taken == self.steps.len() {
            if self.at_floor {
                return None;
            }
            self.at_floor = true;
            return Some(Change::Floor { cost_ns: recent });
        }
        if self.since_up < RELAPSE_FRAMES {
            self.hold = self.hold.saturating_mul(2).min(MAX_HOLD_FRAMES);
        }
        let k = self.taken;
        self.before[k] = recent;
        self.after[k] = 0;
        self.taken += 1;
        self.changed();
        Some(Change::Down {
            step: self.steps[k],
            quality: self.quality(),
            cost_ns: recent,
        })
    }

    fn up(&mut self) -> Option<Change> {
        if self.taken == 0 || self.since_change < self.hold || self.len < UP_WINDOW {
            return None;
        }
        let k = self.taken - 1;
        let median = self.quantile(UP_WINDOW, 0.5);
        // What the step bought when it was given up (never taken as a gain below 1: a step that
        // bought nothing is predicted to cost nothing back).
        let bought = if self.after[k] > 0 {
            (self.before[k] as f64 / self.after[k] as f64).max(1.0)
        } else {
            1.0
        };
        let predicted = (median as f64 * bought) as u64;
        if predicted as f64 > UP_MARGIN * self.target_ns as f64 {
            return None;
        }
        self.taken = k;
        self.since_up = 0;
        self.changed();
        Some(Change::Up {
            step: self.steps[k],
            quality: self.quality(),
            cost_ns: median,
            predicted_ns: predicted,
        })
    }

    /// Start with the first `taken` steps given up (where an earlier run settled:
    /// [`crate::governor_memory`]), each having bought `bought[k]` (its frames' cost before it over
    /// after it, ≥ 1), so taking one back is predicted as though this run had given it up. Called
    /// before the first frame; `taken` past the ladder is held to it, a missing or unusable gain
    /// is taken as 1 (a step predicted to cost nothing back). Not counted as a change.
    pub fn start_at(&mut self, taken: usize, bought: &[f64]) {
        self.taken = taken.min(self.steps.len());
        for k in 0..self.taken {
            let gain = bought
                .get(k)
                .copied()
                .filter(|g| g.is_finite() && *g >= 1.0)
                .unwrap_or(1.0);
            // Only the ratio is read ([`Governor::up`]).
            self.after[k] = 1_000_000;
            self.before[k] = (gain.min(1000.0) * 1e6) as u64;
        }
        self.len = 0;
        self.next = 0;
        self.since_change = 0;
    }

    /// What each step given up now bought when it was given up (cost before over after; 1 where
    /// not yet measured), for the next run ([`Governor::start_at`]).
    pub fn bought(&self) -> Vec<f64> {
        (0..self.taken)
            .map(|k| {
                if self.after[k] > 0 && self.before[k] > 0 {
                    (self.before[k] as f64 / self.after[k] as f64).max(1.0)
                } else {
                    1.0
                }
            })
            .collect()
    }

    /// Frames drawn since the last change (or the start).
    pub fn frames_since_change(&self) -> u32 {
        self.since_change
    }

    fn changed(&mut self) {
        self.len = 0;
        self.next = 0;
        self.since_change = 0;
        self.at_floor = false;
        self.changes += 1;
    }

    /// The `q` quantile (nearest rank) of the newest `n` costs.
    fn quantile(&self, n: usize, q: f64) -> u64 {
        let n = n.min(self.len);
        let mut window = [0u64; UP_WINDOW];
        for (i, w) in window[..n].iter_mut().enumerate() {
            *w = self.ring[(self.next + UP_WINDOW - 1 - i) % UP_WINDOW];
        }
        let window = &mut window[..n];
        window.sort_unstable();
        let rank = ((q * n as f64).ceil() as usize).clamp(1, n);
        window[rank - 1]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::scene::Lod;

    const MS: u64 = 1_000_000;

    /// A frame's cost at `quality` on a made-up GPU: `base` ms, MSAA 4× doubling it, each coarser
    /// level taking off `lod_ms`, the translucent look adding `oit_ms`.
    fn cost(q: Quality, base: f64, lod_ms: f64, oit_ms: f64) -> u64 {
        let mut c = base - lod_ms * q.lod_bias as f64;
        if !q.opaque {
            c += oit_ms;
        }
        if !q.msaa_off {
            c *= 2.0;
        }
        (c.max(0.5) * MS as f64) as u64
    }

    fn translucent_msaa() -> Vec<Step> {
        let scene = RenderScene {
            look: Look::Translucent,
            ..Default::default()
        };
        ladder(&scene, 4, 2, 0)
    }

    /// Accuracy steps only where the scene opts in, only for the bands the lungs have, after
    /// every drawing step, a band at a time down to the least allowed.
    #[test]
    fn bands_are_given_up_last_and_only_where_the_scene_allows_it() {
        let mut scene = RenderScene::default();
        assert_eq!(ladder(&scene, 1, 1, 6), [Step::CoarserLod, Step::DrawnOnly]);
        scene.governor_least_bands = Some(3);
        assert_eq!(
            ladder(&scene, 1, 1, 6),
            [
                Step::CoarserLod,
                Step::DrawnOnly,
                Step::ShBands(5),
                Step::ShBands(4),
                Step::ShBands(3)
            ]
        );
        // Not the "sh" mode, or no more bands than the least: nothing to cap.
        assert_eq!(ladder(&scene, 1, 1, 0), [Step::CoarserLod, Step::DrawnOnly]);
        assert_eq!(ladder(&scene, 1, 1, 3), [Step::CoarserLod, Step::DrawnOnly]);
        scene.governor_least_bands = Some(1);
        scene.look = Look::Translucent;
        let all = ladder(&scene, 4, MAX_LOD_STEPS, 8);
        assert_eq!(all.len(), MAX_STEPS, "the longest ladder fits");
        assert_eq!(all.last(), Some(&Step::ShBands(1)));
        let q = Quality::of(&all, all.len());
        assert_eq!(q.sh_bands, 1);
        assert_eq!(
            q.describe(),
            "MSAA off, LOD +7, drawn vertices only, opaque look, SH at 1 band"
        );
        let q = Quality::of(&all, all.len() - 5);
        assert_eq!(q.sh_bands, 6);
        assert_eq!(Step::ShBands(6).name(), "SH at 6 bands");
        assert_eq!(Quality::of(&all, 9).sh_bands, 0, "drawing steps only");
        // A governor over the longest ladder takes every step.
        let mut g = Governor::new(all.clone(), MS);
        for _ in 0..(all.len() + 1) * 40 {
            g.observe(10 * MS);
        }
        assert_eq!(g.taken(), all.len());
        assert!(g.at_floor());
    }

    #[test]
    fn an_accuracy_opt_in_with_nothing_to_cap_is_said() {
        assert_eq!(idle_accuracy_opt_in(None, &[Step::CoarserLod]), None);
        assert_eq!(
            idle_accuracy_opt_in(
                Some(2),
                &[Step::DrawnOnly, Step::ShBands(3), Step::ShBands(2)]
            ),
            None
        );
        let said = idle_accuracy_opt_in(Some(2), &[Step::CoarserLod, Step::DrawnOnly]).unwrap();
        assert!(
            said.contains("governor_least_bands = 2") && said.contains("\"sh\""),
            "{said}"
        );
    }

    #[test]
    fn the_ladder_has_only_what_the_scene_can_give_up_in_order() {
        let opaque = RenderScene::default();
        assert_eq!(
            ladder(&opaque, 1, 2, 0),
            [Step::CoarserLod, Step::CoarserLod, Step::DrawnOnly]
        );
        assert_eq!(
            translucent_msaa(),
            [
                Step::MsaaOff,
                Step::CoarserLod,
                Step::CoarserLod,
                Step::DrawnOnly,
                Step::Opaque
            ]
        );
        // No coarser level built (`lod = "off"`, or meshes too small): nothing to limit the
        // deformation to.
        assert!(ladder(&opaque, 1, 0, 0).is_empty());
        let points = RenderScene {
            mode: DrawMode::Points,
            lod: Lod::Off,
            ..Default::default()
        };
        assert_eq!(ladder(&points, 4, 0, 0), [Step::MsaaOff]);
        assert!(ladder(&points, 1, 0, 0).is_empty());
        // A see-through look is never made opaque (black is the world on an additive display).
        let see = RenderScene {
            look: Look::SeeThrough,
            ..Default::default()
        };
        assert_eq!(ladder(&see, 1, 1, 0), [Step::CoarserLod, Step::DrawnOnly]);
    }

    #[test]
    fn quality_sums_the_steps_taken() {
        let steps = translucent_msaa();
        assert_eq!(Quality::of(&steps, 0), Quality::FULL);
        assert_eq!(
            Quality::of(&steps, 3),
            Quality {
                msaa_off: true,
                lod_bias: 2,
                drawn_only: false,
                opaque: false,
                sh_bands: 0
            }
        );
        assert_eq!(
            Quality::of(&steps, 4).describe(),
            "MSAA off, LOD +2, drawn vertices only"
        );
        assert_eq!(
            Quality::of(&steps, 99).describe(),
            "MSAA off, LOD +2, drawn vertices only, opaque look"
        );
        assert_eq!(Quality::FULL.describe(), "full");
    }

    /// Frames through `g` at `frame_cost(quality, frame)`; the qualities drawn, one per frame.
    fn run(
        g: &mut Governor,
        frames: usize,
        frame_cost: impl Fn(Quality, usize) -> u64,
    ) -> Vec<Quality> {
        (0..frames)
            .map(|f| {
                let q = g.quality();
                g.observe(frame_cost(q, f));
                q
            })
            .collect()
    }

    #[test]
    fn over_the_target_it_steps_down_until_the_frame_fits_and_stays() {
        let mut g = Governor::new(translucent_msaa(), 13 * MS);
        // 6 ms opaque, OIT +2, coarser levels -1.5 each; MSAA doubles: 16 ms at full quality.
        let drawn = run(&mut g, 600, |q, _| cost(q, 6.0, 1.5, 2.0));
        // MSAA off (8 ms) fits: one step, then nothing more for 10 s of frames.
        assert_eq!(g.taken(), 1);
        assert_eq!(g.changes, 1);
        assert!(!g.at_floor());
        assert_eq!(drawn[0], Quality::FULL);
        // It took no longer than a window and the settling frames to decide.
        let first_down = drawn.iter().position(|q| *q != Quality::FULL).unwrap();
        assert!(
            first_down <= SETTLE as usize + DOWN_WINDOW + 1,
            "{first_down}"
        );
    }

    /// Frames far over the target step down after FAST_FRAMES counted frames, not a whole
    /// window; frames a little over (or far over only now and then) still wait for the window.
    #[test]
    fn far_over_the_target_it_steps_down_without_waiting_for_a_window() {
        let steps = vec![Step::CoarserLod; 5];
        // A heavy scene: 48 ms at full quality, each level half the cost, against 13.7 ms.
        let heavy = |q: Quality, _| (48.0 * MS as f64 * 0.5f64.powi(q.lod_bias.into())) as u64;
        let mut g = Governor::new(steps.clone(), 13_700_000);
        let drawn = run(&mut g, 200, heavy);
        let settled = drawn.iter().position(|q| q.lod_bias == 2).unwrap();
        // 48 and 24 ms are far over (> 20.55 ms): two fast steps; 12 ms fits.
        assert_eq!(g.taken(), 2);
        assert_eq!(
            settled,
            2 * (SETTLE as usize + FAST_FRAMES),
            "frames to settle"
        );
        // What each fast step bought is known, so taking one back is judged as before: at 12 ms
        // the step back predicts 24 ms and stays given up.
        assert!(run(&mut g, 600, heavy).iter().all(|q| q.lod_bias == 2));
        // A little over (1.2×): the window decides, as before.
        let mut g = Governor::new(steps.clone(), 10 * MS);
        let drawn = run(&mut g, 40, |_, _| 12 * MS);
        let first = drawn.iter().position(|q| q.lod_bias > 0).unwrap();
        assert_eq!(first, SETTLE as usize + DOWN_WINDOW);
        // Far over now and then (one frame in four at 3×): the window decides.
        let mut g = Governor::new(steps, 10 * MS);
        let drawn = run(
            &mut g,
            40,
            |_, f| if f % 4 == 0 { 30 * MS } else { 12 * MS },
        );
        let first = drawn.iter().position(|q| q.lod_bias > 0).unwrap();
        assert_eq!(first, SETTLE as usize + DOWN_WINDOW);
    }

    #[test]
    fn when_nothing_is_left_to_give_up_it_says_so_once_and_counts_the_frames() {
        let mut g = Governor::new(vec![Step::CoarserLod], 10 * MS);
        let mut floors = 0;
        for _ in 0..300 {
            let q = g.quality();
            if let Some(Change::Floor { cost_ns }) = g.observe(cost(q, 30.0, 1.0, 0.0)) {
                assert!(cost_ns > 10 * MS);
                floors += 1;
            }
        }
        assert_eq!(floors, 1);
        assert!(g.at_floor());
        assert_eq!(g.taken(), 1);
        assert!(g.floor_frames > 250, "{}", g.floor_frames);
    }

    #[test]
    fn a_load_that_passes_gives_the_quality_back() {
        let mut g = Governor::new(translucent_msaa(), 13 * MS);
        // Ten seconds of a machine loaded 3× (every step taken), then unloaded.
        let drawn = run(&mut g, 1800, |q, f| {
            let c = cost(q, 6.0, 1.5, 2.0);
            if f < 600 {
                c * 3
            } else {
                c
            }
        });
        assert_eq!(
            drawn[599].describe(),
            "MSAA off, LOD +2, drawn vertices only, opaque look"
        );
        // Back to what fits unloaded (MSAA off alone: 8 ms; full is 16 ms, over the target).
        assert_eq!(g.quality(), Quality::of(&translucent_msaa(), 1));
        // Never the full quality, which does not fit: no swing into it and back.
        assert!(drawn[600..].iter().all(|q| *q != Quality::FULL));
    }

    #[test]
    fn a_cost_at_the_edge_does_not_swing_between_two_steps() {
        // Full quality costs just over the target, one step just under it: noise around both.
        let mut g = Governor::new(vec![Step::CoarserLod], 10 * MS);
        let drawn = run(&mut g, 3600, |q, f| {
            // ±0.5 ms, scattered over the frames (7919 is prime to 1000).
            let jitter = (f as i64 * 7919 % 1000) * 1000 - 500_000;
            let base = if q.lod_bias == 0 {
                10_400_000
            } else {
                9_000_000
            };
            (base + jitter) as u64
        });
        let changes = drawn.windows(2).filter(|w| w[0] != w[1]).count();
        assert!(changes <= 3, "{changes} changes in a minute of frames");
        assert_eq!(g.taken(), 1);
    }

    #[test]
    fn a_step_taken_back_that_does_not_fit_is_given_up_again_and_not_soon_retried() {
        // Under load the coarser level bought little (12 → 11 ms); the load goes, the coarser
        // level draws in 3 ms, the full one still takes 12: one try, given up again, not retried.
        let mut g = Governor::new(vec![Step::CoarserLod], 10 * MS);
        let drawn = run(&mut g, 3600, |q, f| match (q.lod_bias, f < 600) {
            (0, _) => 12 * MS,
            (_, true) => 11 * MS,
            (_, false) => 3 * MS,
        });
        let tries = drawn
            .windows(2)
            .filter(|w| w[0].lod_bias == 1 && w[1].lod_bias == 0)
            .count();
        assert_eq!(
            tries, 1,
            "the try measured what the step buys: 4x, 12 ms, over"
        );
        assert_eq!(g.taken(), 1);
        // The relapse doubled the hold and it stays doubled: the step was not kept.
        assert_eq!(g.hold(), 2 * HOLD_FRAMES);
    }

    #[test]
    fn a_step_kept_after_it_was_taken_back_resets_the_hold() {
        let mut g = Governor::new(vec![Step::CoarserLod], 10 * MS);
        // Loaded (everything 12 ms, the step bought nothing), then a try that relapses (the full
        // quality 12 ms, the coarser 3), then the machine quiet (both halved): kept.
        run(&mut g, 2400, |q, f| match (q.lod_bias, f) {
            (_, f) if f < 600 => 12 * MS,
            (0, f) if f < 900 => 12 * MS,
            (_, f) if f < 900 => 3 * MS,
            (0, _) => 6 * MS,
            (_, _) => 3 * MS / 2,
        });
        assert_eq!(g.taken(), 0);
        assert_eq!(g.hold(), HOLD_FRAMES);
    }

    #[test]
    fn unmeasured_frames_and_settling_frames_do_not_count() {
        let mut g = Governor::new(vec![Step::CoarserLod], 10 * MS);
        for _ in 0..1000 {
            assert_eq!(g.observe(0), None);
        }
        assert_eq!(g.taken(), 0);
        // One huge frame among fast ones is not a reason to step down (75th percentile).
        for f in 0..200 {
            g.observe(if f == 50 { 500 * MS } else { 2 * MS });
        }
        assert_eq!(g.taken(), 0);
    }

    #[test]
    fn no_steps_means_nothing_to_do_but_say_the_floor() {
        let mut g = Governor::new(Vec::new(), 10 * MS);
        let changes: Vec<_> = (0..100).filter_map(|_| g.observe(20 * MS)).collect();
        assert_eq!(changes.len(), 1);
        assert!(matches!(changes[0], Change::Floor { .. }));
        assert_eq!(g.quality(), Quality::FULL);
    }

    /// A run started where the last one settled draws at that quality from its first frame, takes
    /// a step back only when the frame is predicted to fit with that step's remembered gain (the
    /// same frames with no gain remembered step up), and hands the gains on unchanged.
    #[test]
    fn a_remembered_start_draws_there_and_steps_back_by_the_remembered_gains() {
        let steps = vec![Step::MsaaOff, Step::CoarserLod];
        let mut g = Governor::new(steps.clone(), 10 * MS);
        g.start_at(2, &[2.0, 1.5]);
        assert_eq!(g.taken(), 2);
        assert_eq!(g.quality(), Quality::of(&steps, 2));
        assert_eq!(g.changes, 0, "the start is not a change");
        assert_eq!(g.bought(), vec![2.0, 1.5]);
        // 6 ms frames: with the level back, 9 ms predicted — over 80 % of the target: stay.
        for _ in 0..2000 {
            assert_eq!(g.observe(6 * MS), None);
        }
        // With no gain remembered the same frames are predicted to fit: a step back.
        let mut blind = Governor::new(steps.clone(), 10 * MS);
        blind.start_at(2, &[]);
        assert_eq!(blind.bought(), vec![1.0, 1.0]);
        let first = (1..=2000).find_map(|f| blind.observe(6 * MS).map(|c| (f, c)));
        assert!(
            matches!(first, Some((f, Change::Up { step: Step::CoarserLod, .. })) if f >= HOLD_FRAMES),
            "{first:?}"
        );
        // 4.5 ms frames: 6.75 ms predicted — back, after the hold; the next step by its own gain,
        // 9 ms predicted, over 80 % of the target: kept.
        let ups: Vec<u32> = (1..=2000u32)
            .filter(|_| matches!(g.observe(9 * MS / 2), Some(Change::Up { .. })))
            .collect();
        assert_eq!(ups.len(), 1, "{ups:?}");
        assert_eq!(g.taken(), 1);
        // Past the ladder, and gains that are not gains, are held to what can be.
        let mut odd = Governor::new(steps, 10 * MS);
        odd.start_at(9, &[f64::NAN, 0.5, 3.0]);
        assert_eq!(odd.taken(), 2);
        assert_eq!(odd.bought(), vec![1.0, 1.0]);
    }
}
