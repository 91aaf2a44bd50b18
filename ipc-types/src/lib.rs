//! # ipc-types: the protocol between lungdyn's processes
//!
//! Everything that crosses a process boundary — and everything a recording or a replay stores — is
//! one of the fixed-size, `#[repr(C)]`, pointer-free payloads defined here: [`TrackerFrame`]
//! (tracker-bridge → engine, renderer), [`EngineFrame`] (engine → renderer) and [`FrameReport`]
//! (renderer → launcher, latency harness, tests). They are [`bytemuck::Pod`], so a payload is its
//! bytes: it can be written to a file and read back bit for bit, and any transport that moves bytes
//! can carry it.
//!
//! This crate is only the protocol. How a payload travels (iceoryx2 shared memory, an in-process
//! queue in tests, a recorded file) is the `transport` crate's business; this crate depends on
//! nothing but `bytemuck` (and `serde`, for the names of [`Intervention`] in scene files).
//!
//! Every payload carries [`HopStamps`]: the monotonic time (CLOCK_MONOTONIC, ns, shared by all
//! processes on the host) at which it passed each hop, so the latency harness can attribute every
//! microsecond of the tracker-sample-to-submitted-frame path.
//!
//! ## Layout versioning
//! [`LAYOUT_VERSION`] is written into every payload ([`Message::layout_version`]) and into every
//! payload's type name ([`Message::TYPE_NAME`], `"lungdyn.EngineFrame.v9"`), which the transport
//! hands to iceoryx2: iceoryx2 refuses to open a service whose payload type name, size or alignment
//! differ from the creator's, so a process built from another layout fails at start-up instead of
//! reading garbage; the field in the payload is a second check for peers that bypass the type name.
//! Sizes, alignments and every field offset are pinned by `const` assertions below: a layout change
//! that forgets the version does not compile.
//!
//! Version history: v1 had one breathing state for both lungs; v2 gives each lung its own volume,
//! phase, cycle, rigid offset, deformation coefficients and the identity of the kernel it was
//! computed for ([`LungFrame`]); v3 adds each lung's collapse towards its hilum (a pneumothorax,
//! EQUATIONS.md §4: drawn at `h + (1 − c)(p − h) + s·u + offset`), zero for a healthy lung; v4 adds
//! to each [`FrameReport`] when `present` returned, the present mode and the frame latency (the
//! latency harness's submit-to-present), and the renderer's GPU-done time (capture → GPU done), and
//! what a heads-up display shows of each lung's breath: its PV-model pressure, tidal volume and the
//! ticks of its current cycle and inhalation (so a disease's own rate is shown, not the scene's); v5
//! gives each [`ControlPacket`] its origin (the remote site that raised it, or [`ORIGIN_LOCAL`]); v6
//! adds to each [`TrackerFrame`] the respiratory signal's samples that arrived since the previous one
//! ([`SignalBlock`], issue 35: breathing with the patient); v7 adds to each [`SignalBlock`] a replayed
//! recording's origin on the host's clock, and to each [`EngineFrame`] what the engine followed of
//! the signal ([`SignalFollowed`]: the volume it predicted for the display time, the volume without
//! the prediction, and that display time), so a run can be held against the recording frame by
//! frame (`lungdyn breathing follow`); v8 adds to each [`SignalBlock`] the pipeline's latency as the
//! renderer's reports measured it ([`SignalBlock::pipeline_latency_ns`]), so the engine predicts the
//! signal across the latency measured, and a recording replays the prediction bit for bit, and to
//! each [`SignalFollowed`] the latency the engine predicted across ([`SignalFollowed::latency_ns`]);
//! v9 adds to each [`SignalFollowed`] the patient's typical breath as followed (tidal volume,
//! period, where the breath is and its inspiration's share), so a heads-up display shows the
//! patient's rate, tidal volume and breath phase, not the model's, while the signal drives the
//! lungs.

use core::mem::{align_of, offset_of, size_of};

use bytemuck::{Pod, Zeroable};

/// Version of every payload layout in this crate. Part of each payload's type name.
pub const LAYOUT_VERSION: u32 = 9;

/// Most respiratory-signal samples one [`TrackerFrame`] carries (8 per frame at the bridge's 60 Hz:
/// 480 Hz; a slower source sends one or none per frame, a faster one's rest waits for the next).
pub const MAX_SIGNAL_SAMPLES: usize = 8;

/// Maximum number of tracked tools in one [`TrackerFrame`].
pub const MAX_TOOLS: usize = 4;
/// Capacity for deformation coefficients per lung in an [`EngineFrame`] (force weights of the basis
/// mode, or spherical-harmonic force coefficients: 64 = 8 bands).
pub const MAX_COEFFS: usize = 64;
/// Number of lungs in an [`EngineFrame`]: index [`LUNG_RIGHT`] and [`LUNG_LEFT`].
pub const NUM_LUNGS: usize = 2;
/// Index of the right lung in per-lung arrays.
pub const LUNG_RIGHT: usize = 0;
/// Index of the left lung in per-lung arrays.
pub const LUNG_LEFT: usize = 1;

/// Conventional tool slot of the patient reference (dynamic reference frame on the sternum).
pub const TOOL_PATIENT: usize = 0;
/// Conventional tool slot of the head-mounted display.
pub const TOOL_HMD: usize = 1;
/// Conventional tool slot of a tool on the chest whose motion is the respiratory signal
/// (`--breathing tool:NAME`); unused otherwise.
pub const TOOL_CHEST: usize = 2;

/// A payload of the protocol: plain bytes with a versioned name.
pub trait Message: Pod + core::fmt::Debug + Send + 'static {
    /// Short name used in messages ("EngineFrame").
    const NAME: &'static str;
    /// Versioned type name (`lungdyn.<NAME>.v<LAYOUT_VERSION>`): what the transport registers, so two
    /// builds with different layouts never open each other's streams.
    const TYPE_NAME: &'static str;
    /// The layout version this payload claims (its first field).
    fn layout_version(&self) -> u32;
    /// `Ok` when the payload speaks this build's layout.
    fn check_layout(&self) -> Result<(), LayoutError> {
        check_layout(Self::NAME, self.layout_version())
    }
}

/// Monotonic timestamps (ns) of each hop a sample passed. Zero means "not passed (yet)".
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct HopStamps {
    /// When the tracker captured the sample (for a synthetic source: when it was generated).
    pub capture_ns: u64,
    /// When the tracker-bridge published the tracker frame.
    pub bridge_publish_ns: u64,
    /// When the engine took the tracker frame out of its subscriber.
    pub engine_receive_ns: u64,
    /// When the engine published the engine frame derived from it.
    pub engine_publish_ns: u64,
    /// When the renderer took the engine frame out of its subscriber.
    pub renderer_receive_ns: u64,
    /// When the renderer submitted the GPU work that draws it.
    pub renderer_submit_ns: u64,
}

impl HopStamps {
    /// The hop names, in path order, as used by the latency report.
    pub const NAMES: [&'static str; 6] = [
        "capture",
        "bridge publish",
        "engine receive",
        "engine publish",
        "renderer receive",
        "renderer submit",
    ];

    /// The stamps in path order.
    pub fn as_array(&self) -> [u64; 6] {
        [
            self.capture_ns,
            self.bridge_publish_ns,
            self.engine_receive_ns,
            self.engine_publish_ns,
            self.renderer_receive_ns,
            self.renderer_submit_ns,
        ]
    }

    /// True when every hop is stamped and the stamps never go backwards.
    pub fn is_complete_and_ordered(&self) -> bool {
        let a = self.as_array();
        a.iter().all(|&t| t != 0) && a.windows(2).all(|w| w[0] <= w[1])
    }
}

/// A rigid pose: unit quaternion `(x, y, z, w)` and translation in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct Pose {
    /// Rotation as a unit quaternion, `[x, y, z, w]`.
    pub quat: [f32; 4],
    /// Translation in mm.
    pub translation_mm: [f32; 3],
    /// Explicit padding so the layout has no implicit holes.
    pub _pad: u32,
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    /// No rotation, no translation.
    pub const IDENTITY: Pose = Pose {
        quat: [0.0, 0.0, 0.0, 1.0],
        translation_mm: [0.0; 3],
        _pad: 0,
    };

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.quat
            .iter()
            .chain(self.translation_mm.iter())
            .all(|v| v.is_finite())
    }
}

/// Status bits of a [`ToolPose`].
///
/// [`VALID`](tool_status::VALID) is the only bit a consumer needs: the bridge clears it whenever
/// any other bit but `PARTIALLY_VISIBLE`, `FRAME_GAP` or `FRAME_REPEAT` is set, and then the pose
/// is the tool's last good one (identity before any), never the rejected sample, so no NaN or
/// non-rotation crosses the process boundary. The other bits say why. Bits 5..10 were added
/// without a layout change (the field and its meaning as a bit set are unchanged).
pub mod tool_status {
    /// The pose is valid and may be used.
    pub const VALID: u32 = 1 << 0;
    /// The tool was not seen in this sample.
    pub const MISSING: u32 = 1 << 1;
    /// The tool was outside the tracker's measurement volume.
    pub const OUT_OF_VOLUME: u32 = 1 << 2;
    /// The pose had non-finite components and was rejected by the bridge.
    pub const NON_FINITE: u32 = 1 << 3;
    /// Only some of the tool's markers were seen (pose less accurate).
    pub const PARTIALLY_VISIBLE: u32 = 1 << 4;
    /// The rotation was not one: a quaternion whose norm is off 1 by more than the bridge's
    /// tolerance, a matrix that is not orthonormal with determinant +1, or no orientation at all.
    pub const NOT_ROTATION: u32 = 1 << 5;
    /// The tracker's RMS marker-fit error was above the bridge's threshold.
    pub const HIGH_RMS: u32 = 1 << 6;
    /// The device's frame counter skipped frames since the previous published frame (samples lost
    /// on the way); the pose itself may be good.
    pub const FRAME_GAP: u32 = 1 << 7;
    /// The device's frame counter (or timestamp) repeated or went backwards: no new measurement.
    pub const FRAME_REPEAT: u32 = 1 << 8;
    /// No new sample for longer than the bridge's staleness bound: the pose is the last good one,
    /// not valid any more.
    pub const STALE: u32 = 1 << 9;
    /// The tracker reported a fault for the tool (broken sensor, hardware failure, processing
    /// exception).
    pub const DEVICE_FAULT: u32 = 1 << 10;
}

/// One tool's pose in a tracker sample.
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct ToolPose {
    /// Tracker-assigned tool handle.
    pub tool_id: u32,
    /// [`tool_status`] bits.
    pub status: u32,
    /// Tool pose in the tracker's frame.
    pub pose: Pose,
    /// RMS marker-fit error in mm reported by the tracker.
    pub rms_error_mm: f32,
    /// Explicit padding.
    pub _pad: u32,
}

impl ToolPose {
    /// True when the tool's pose may be used.
    pub fn is_valid(&self) -> bool {
        self.status & tool_status::VALID != 0
    }
}

/// One tracker sample, published by `tracker-bridge` at 60 Hz.
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct TrackerFrame {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// Number of used entries in `tools`.
    pub tool_count: u32,
    /// Frame number, +1 per sample since the bridge started.
    pub frame_number: u64,
    /// Hop timestamps (capture and bridge publish set by the bridge).
    pub stamps: HopStamps,
    /// Tool poses; slot [`TOOL_PATIENT`] is the patient reference, [`TOOL_HMD`] the HMD.
    pub tools: [ToolPose; MAX_TOOLS],
    /// The respiratory signal's samples that arrived since the previous frame (v6).
    pub signal: SignalBlock,
}

/// The unit of a [`SignalBlock`]'s values.
pub mod signal_unit {
    /// No signal source.
    pub const NONE: u32 = 0;
    /// Millimetres of chest (marker) excursion, + = inspiration.
    pub const MM: u32 = 1;
    /// Millilitres (a ventilator's or spirometer's volume).
    pub const ML: u32 = 2;
    /// A device's own amplitude unit, + = inspiration.
    pub const ARBITRARY: u32 = 3;
}

/// Bits of [`SignalBlock::status`].
pub mod signal_status {
    /// The bridge has a respiratory signal source.
    pub const CONFIGURED: u32 = 1 << 0;
    /// The source has ended (a replayed trace reached its end): no more samples will come.
    pub const ENDED: u32 = 1 << 1;
    /// The source is cut on purpose (a loss being tested): samples are withheld.
    pub const CUT: u32 = 1 << 2;
    /// The bridge is learning how to read the source (a chest tool's breathing axis,
    /// `tool:NAME:auto`): its measurements are kept, not sent, until it has. Not a loss.
    pub const LEARNING: u32 = 1 << 3;
}

/// One respiratory-signal sample as its source stamped it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct SignalWire {
    /// Capture time, ns, host monotonic clock.
    pub t_ns: u64,
    /// The value in [`SignalBlock::unit`]; 0 when not valid (never NaN).
    pub value: f64,
}

/// A tracker frame's respiratory-signal samples (issue 35): what arrived since the previous frame,
/// oldest first.
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct SignalBlock {
    /// Samples used in `samples`.
    pub count: u32,
    /// [`signal_unit`] of the values.
    pub unit: u32,
    /// [`signal_status`] bits.
    pub status: u32,
    /// Bit `i` set: sample `i` is valid (its source said so, and it is finite).
    pub valid_mask: u32,
    /// The source's nominal sample period, ns (0 before it is known).
    pub period_ns: u64,
    /// The samples.
    pub samples: [SignalWire; MAX_SIGNAL_SAMPLES],
    /// A replayed recording's clock on this host (layout v7): the monotonic time, ns, at which its
    /// first sample's time fell, so a sample recorded `t` after the first is stamped `origin_ns + t`
    /// (and `lungdyn breathing follow` places every drawn frame on the recording's own time axis).
    /// 0 for a live source, whose stamps are arrival times with no recording behind them.
    pub origin_ns: u64,
    /// The pipeline's latency (layout v8): from the bridge's publish of a tracker frame to the
    /// display of the frame drawn from it, ns — the median of the renderer's latest reports as the
    /// bridge read them ([`FrameReport::display_ns`]); 0 while none is measured (no renderer yet,
    /// or a recording made before v8). An input like the samples: recorded, and replayed as it was,
    /// so the engine's prediction across it stays a pure function of its inputs.
    pub pipeline_latency_ns: u64,
}

impl SignalBlock {
    /// Sample `i` with its validity, when `i < count`.
    pub fn sample(&self, i: usize) -> Option<(SignalWire, bool)> {
        (i < (self.count as usize).min(MAX_SIGNAL_SAMPLES))
            .then(|| (self.samples[i], self.valid_mask & (1 << i) != 0))
    }
}

impl TrackerFrame {
    /// The pose in `slot` when the frame has that tool and it is valid and finite.
    pub fn valid_tool(&self, slot: usize) -> Option<Pose> {
        let tool = self.tools.get(slot)?;
        (slot < self.tool_count as usize && tool.is_valid() && tool.pose.is_finite())
            .then_some(tool.pose)
    }
}

/// Bits of [`EngineFrame::state`].
pub mod engine_state {
    /// The tick used a fresh tracker frame (woken by its arrival).
    pub const TRACKER_FRESH: u32 = 1 << 0;
    /// No tracker frame arrived before the tick deadline: the tick ran on the deadline fallback.
    pub const DEADLINE_FALLBACK: u32 = 1 << 1;
    /// The patient pose is held from an earlier sample (tracker flagged it or it was missing).
    pub const PATIENT_POSE_HELD: u32 = 1 << 2;
    /// The patient pose has been held longer than the allowed staleness.
    pub const PATIENT_POSE_STALE: u32 = 1 << 3;
    /// The first active lung is inhaling (per-lung phase: [`super::lung_flags::INHALING`]).
    pub const INHALING: u32 = 1 << 4;
    /// No tracker sample has been seen yet.
    pub const NO_TRACKER_YET: u32 = 1 << 5;
    /// The patient pose is not a rotation (NaN, not unit): the force follows the last good
    /// gravity direction (supine before any).
    pub const POSE_INVALID: u32 = 1 << 6;
    /// The orientation is where the supine-fitted direction model barely expands a lung: its
    /// force weights were limited towards supine (`lung_model::orientation::VolumeLimit`).
    pub const ORIENTATION_LIMITED: u32 = 1 << 7;
    /// The scene breathes with the patient's signal (`[breathing] source = "signal"`), and these
    /// volumes are the signal's (following, or paused on a breath-hold or apnoea).
    pub const SIGNAL_FOLLOWING: u32 = 1 << 8;
    /// The signal is being calibrated (an amplitude's first regular breaths; a signal whose gain
    /// is known, until its first samples span a plausible breath): the model breathes meanwhile.
    pub const SIGNAL_CALIBRATING: u32 = 1 << 9;
    /// No valid signal sample within the loss limit (or none yet): the model breathes, carried on
    /// from the signal's last volume and phase.
    pub const SIGNAL_LOST: u32 = 1 << 10;
    /// The signal shows no breath lately (a breath-hold, an apnoea, a pause): its volume is drawn.
    pub const SIGNAL_PAUSED: u32 = 1 << 11;
    /// With [`SIGNAL_CALIBRATING`]: the bridge is still learning how to read its source (a chest
    /// tool's breathing axis, `tool:NAME:auto`, over its first 12 s) and sends no samples yet; the
    /// model breathes. Not a loss: no veil.
    pub const SIGNAL_LEARNING: u32 = 1 << 12;
    /// With [`SIGNAL_FOLLOWING`]: the latest breaths look cut by the sensor's range (several of
    /// unequal depth ending at one value, the signal's highest or lowest): the patient breathed
    /// deeper than the signal reads, so the lungs drawn from it breathe shallower.
    pub const SIGNAL_CLIPPED: u32 = 1 << 13;
}

/// Bits of [`LungFrame::flags`].
pub mod lung_flags {
    /// The lung is simulated in the current scene (clear: the slot is empty, draw nothing).
    pub const ACTIVE: u32 = 1 << 0;
    /// The lung is inhaling (clear: exhaling or not breathing).
    pub const INHALING: u32 = 1 << 1;
    /// The lung does not breathe: its volume is held (a collapsed or arrested lung).
    pub const HELD: u32 = 1 << 2;
    /// The lung's breathing changed at the start of this tick's cycle (rate, depth or constants).
    pub const CYCLE_CHANGED: u32 = 1 << 3;
    /// The lung is drawn outside the volume range its kernel was checked free of folds at bake time
    /// (`KernelMeta::fold_free`): its surface may cross itself.
    pub const PAST_FOLD_FREE: u32 = 1 << 4;
}

/// What [`LungFrame::coeffs`] hold.
pub mod coeff_kind {
    /// No coefficients: the lung deforms by `p + s·u` (precomputed mode).
    pub const NONE: u32 = 0;
    /// Applied-force weights `(w0, wx, wy, wz)` of the exact basis mode (EQUATIONS §3.3).
    pub const FORCE_WEIGHTS: u32 = 1;
    /// Spherical-harmonic force coefficients `F_lm`, `l < n`, `n²` values (eq. 7.2).
    pub const SH_FORCE: u32 = 2;
}

/// One lung's state in an [`EngineFrame`]: enough for a renderer to deform this lung alone, and to
/// check that it deforms the lung the engine computed.
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct LungFrame {
    /// Identity of the kernel this state is for (the kernel file's header checksum; 0 when the slot
    /// is empty). A renderer that loaded another kernel for this lung must not apply the state.
    pub kernel_id: u64,
    /// Lung volume, ml.
    pub volume_ml: f32,
    /// Scale applied to the lung's unit displacement field this tick.
    pub deform_scale: f32,
    /// Position in the lung's current breathing cycle, `[0, 1)` (0 = start of an inhalation).
    pub phase: f32,
    /// Breathing cycles this lung has completed since the engine started.
    pub cycle: u32,
    /// Rigid offset of the whole lung in the body frame, mm (mediastinal shift, a dropped lung).
    pub offset_mm: [f32; 3],
    /// [`lung_flags`] bits.
    pub flags: u32,
    /// What `coeffs` hold ([`coeff_kind`]).
    pub coeff_kind: u32,
    /// Number of used entries of `coeffs`.
    pub coeff_count: u32,
    /// Deformation coefficients of this tick (fixed capacity, [`MAX_COEFFS`]).
    pub coeffs: [f32; MAX_COEFFS],
    /// Collapse towards the hilum, `c ∈ [0, 1]` (0: none): the lung is drawn at
    /// `h + (1 − c)(p − h) + s·u + offset_mm` (EQUATIONS.md §4.1; `deform_scale` is solved on the
    /// collapsed lung's volume cubic).
    pub collapse: f32,
    /// The hilum `h` the lung collapses towards, body frame, mm (0 when `collapse` is 0).
    pub hilum_mm: [f32; 3],
    /// The PV model's driving pressure at this tick, cmH2O (EQUATIONS.md §1.1: RP → TP linearly in
    /// the inhalation's phase time, back to RP in the exhalation's; RP while the lung is held). With
    /// `volume_ml` it is the point on the lung's PV loop.
    pub pressure_cmh2o: f32,
    /// This lung's tidal volume in its current cycle, ml (its share of the cycle's TV; 0 while the
    /// lung is held).
    pub tidal_ml: f32,
    /// Ticks of this lung's current breathing cycle (its rate is `60 · tick_hz / cycle_ticks`
    /// breaths/min; 0 for an empty slot).
    pub cycle_ticks: u32,
    /// Ticks of the current cycle's inhalation (`phase < inhale_ticks / cycle_ticks`: inhaling).
    pub inhale_ticks: u32,
}

impl Default for LungFrame {
    fn default() -> Self {
        Self::zeroed()
    }
}

impl LungFrame {
    /// True when the lung is simulated in the current scene.
    pub fn is_active(&self) -> bool {
        self.flags & lung_flags::ACTIVE != 0
    }
}

/// One engine tick's output, published by `engine` every tick.
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct EngineFrame {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// [`engine_state`] bits.
    pub state: u32,
    /// Fault word: 0 when healthy, else a [`fault`] code.
    pub fault: u32,
    /// Explicit padding.
    pub _pad: u32,
    /// Integer tick counter since the engine started.
    pub tick: u64,
    /// `frame_number` of the tracker frame this tick used (0 when none yet).
    pub tracker_frame: u64,
    /// Hop timestamps, inherited from the tracker frame and extended by the engine.
    pub stamps: HopStamps,
    /// Patient reference pose used for registration (held when the tracker flagged it).
    pub patient_pose: Pose,
    /// Per-lung state, indexed by [`LUNG_RIGHT`] and [`LUNG_LEFT`].
    pub lungs: [LungFrame; NUM_LUNGS],
    /// What the engine followed of the patient's respiratory signal this tick (layout v7); zero
    /// when the scene breathes with the model or no sample has come yet.
    pub signal: SignalFollowed,
}

/// The patient's respiratory signal as the engine followed it on one tick (issue 35), whole patient
/// (before each lung's share), whether or not it drove the lungs: [`engine_state`]'s
/// `SIGNAL_FOLLOWING` says whether it did. Never NaN (0 when there is nothing to say).
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct SignalFollowed {
    /// The display time the engine predicted for (CLOCK_MONOTONIC, ns): the newest input's time
    /// plus [`Self::latency_ns`]; 0 when nothing was followed.
    pub display_ns: u64,
    /// The volume above FRC predicted for `display_ns`, ml: what drives the lungs.
    pub volume_ml: f32,
    /// The volume above FRC from the newest sample with no prediction, ml: the baseline a
    /// predictor must beat, kept from the same run.
    pub unpredicted_ml: f32,
    /// The latency predicted across, ns (layout v8): the pipeline's as measured plus
    /// `[breathing] sensor_latency_ms`, or `latency_ms` (fixed, or before a measurement); 0 when
    /// nothing was followed.
    pub latency_ns: u64,
    /// The patient's typical breath as drawn, ml, whole patient (layout v9): the calibrated median
    /// of the last regular breaths — with an amplitude's automatic calibration the volume it is
    /// calibrated to, with a spirometry gain or a volume signal the patient's own; 0 while it or
    /// the period is unknown.
    pub tidal_ml: f32,
    /// The patient's typical breath period as followed (median of the last regular breaths), s
    /// (layout v9); 0 while it or the tidal volume is unknown.
    pub period_s: f32,
    /// Where the patient's breath is at `display_ns`: the time since the last end-expiration over
    /// the typical period, `[0, 1)` (layout v9); 0 while the period is unknown.
    pub phase: f32,
    /// The patient's typical inspiration as a share of the breath, `[0, 1]` (layout v9); 0 while
    /// unknown.
    pub inhale_fraction: f32,
}

impl Default for EngineFrame {
    fn default() -> Self {
        Self::zeroed()
    }
}

/// Fault codes of [`EngineFrame::fault`].
pub mod fault {
    /// Healthy.
    pub const NONE: u32 = 0;
    /// The tracker has been silent for longer than the staleness bound.
    pub const TRACKER_LOST: u32 = 1;
    /// The PV model produced a non-finite value and the engine held the last good volume.
    pub const NON_FINITE_VOLUME: u32 = 2;
}

/// Bits of [`FrameReport::flags`].
pub mod report_flags {
    /// This frame also wrote a PNG snapshot (its CPU time includes the readback).
    pub const SNAPSHOT: u32 = 1 << 0;
    /// GPU time was measured with timestamp queries.
    pub const GPU_TIMED: u32 = 1 << 1;
    /// The renderer drew without a fresh engine frame (deadline fallback).
    pub const STALE_ENGINE: u32 = 1 << 2;
    /// The engine frame was computed for another kernel than the renderer loaded for at least one
    /// lung; that lung was drawn at rest instead of with foreign displacements.
    pub const KERNEL_MISMATCH: u32 = 1 << 3;
    /// The engine held the last good patient pose for this frame (samples missing or rejected):
    /// the lungs are drawn where the patient was, and the frame says so (tinted background).
    pub const PATIENT_POSE_HELD: u32 = 1 << 4;
    /// The held pose is older than the scene's `pose_staleness_ticks`, or no patient sample ever
    /// arrived: the overlay's placement is not to be trusted (red-tinted background).
    pub const PATIENT_POSE_STALE: u32 = 1 << 5;
    /// No engine frame for [`ENGINE_DOWN_FRAMES`] frame periods or more: the engine is restarting
    /// (or stopped); the last frame is presented, stale, under a violet veil that says so.
    pub const ENGINE_DOWN: u32 = 1 << 6;
    /// The patient's respiratory signal drove the lungs drawn (the engine's `SIGNAL_FOLLOWING`).
    pub const SIGNAL_FOLLOWING: u32 = 1 << 7;
    /// The scene follows a signal and it was lost: the model breathed, under the blue veil (the
    /// engine's `SIGNAL_LOST`).
    pub const SIGNAL_LOST: u32 = 1 << 8;
    /// The renderer's quality governor has given up every step it may and the frames are still
    /// over its target: the deadline is not held (`renderer::governor`).
    pub const GOVERNOR_FLOOR: u32 = 1 << 9;
    /// Drawn with multisampling off by the governor (the scene asked for 4×).
    pub const QUALITY_MSAA_OFF: u32 = 1 << 10;
    /// Drawn opaque by the governor (the scene's look is translucent).
    pub const QUALITY_OPAQUE: u32 = 1 << 11;
    /// Drawn with only the drawn level's vertices deformed, their normals from its triangles, by
    /// the governor (every drawn vertex's position is the full pass's; `renderer::governor`).
    pub const QUALITY_DRAWN_ONLY: u32 = 1 << 12;
    /// The signal driving the lungs drawn looks clipped by its sensor's range (the engine's
    /// `SIGNAL_CLIPPED`): the patient's breaths were deeper than drawn.
    pub const SIGNAL_CLIPPED: u32 = 1 << 13;
    /// A lung was drawn outside the volume range its kernel was checked free of folds at bake time
    /// (the engine's `lung_flags::PAST_FOLD_FREE`): its surface may cross itself.
    pub const PAST_FOLD_FREE: u32 = 1 << 14;
    /// Bits 16..18: draw levels coarser than the level of detail chose, by the governor (0..7).
    pub const QUALITY_LOD_SHIFT: u32 = 16;
    /// The mask of [`QUALITY_LOD_SHIFT`]'s bits.
    pub const QUALITY_LOD_MASK: u32 = 0x7 << QUALITY_LOD_SHIFT;
    /// Bits 19..22: the spherical-harmonic bands the deformation was capped at by the governor,
    /// 1..8 (0: not capped) — an accuracy step, taken only where the scene allows it
    /// (`[render] governor_least_bands`; `renderer::governor`).
    pub const QUALITY_SH_SHIFT: u32 = 19;
    /// The mask of [`QUALITY_SH_SHIFT`]'s bits.
    pub const QUALITY_SH_MASK: u32 = 0xf << QUALITY_SH_SHIFT;
    /// Every bit that says the governor drew below the scene's quality.
    pub const QUALITY_LOWERED: u32 =
        QUALITY_MSAA_OFF | QUALITY_OPAQUE | QUALITY_DRAWN_ONLY | QUALITY_LOD_MASK | QUALITY_SH_MASK;

    /// The bits of a frame deformed with its spherical harmonics capped at `bands` (0: not).
    pub const fn sh_cap_bits(bands: u8) -> u32 {
        let b = if bands > 8 { 8 } else { bands as u32 };
        b << QUALITY_SH_SHIFT
    }

    /// The bits of a frame drawn with multisampling off, `lod_bias` levels coarser (at most 7)
    /// and opaque instead of translucent.
    pub const fn quality_bits(msaa_off: bool, lod_bias: u8, opaque: bool) -> u32 {
        let lod = if lod_bias > 7 { 7 } else { lod_bias as u32 };
        (if msaa_off { QUALITY_MSAA_OFF } else { 0 })
            | (if opaque { QUALITY_OPAQUE } else { 0 })
            | (lod << QUALITY_LOD_SHIFT)
    }

    /// A frame's quality in words from its flags: "full", or what the governor gave up ("MSAA off,
    /// LOD +2, drawn vertices only, opaque look, SH at 2 bands").
    pub fn describe_quality(flags: u32) -> String {
        let mut s = String::new();
        let _ = write_quality(&mut s, flags);
        s
    }

    /// [`describe_quality`] into `w`, allocating nothing (the HUD's per-frame line).
    pub fn write_quality(w: &mut impl core::fmt::Write, flags: u32) -> core::fmt::Result {
        let lod = (flags & QUALITY_LOD_MASK) >> QUALITY_LOD_SHIFT;
        let mut sep = "";
        if flags & QUALITY_MSAA_OFF != 0 {
            w.write_str("MSAA off")?;
            sep = ", ";
        }
        if lod > 0 {
            write!(w, "{sep}LOD +{lod}")?;
            sep = ", ";
        }
        if flags & QUALITY_DRAWN_ONLY != 0 {
            write!(w, "{sep}drawn vertices only")?;
            sep = ", ";
        }
        if flags & QUALITY_OPAQUE != 0 {
            write!(w, "{sep}opaque look")?;
            sep = ", ";
        }
        let bands = (flags & QUALITY_SH_MASK) >> QUALITY_SH_SHIFT;
        if bands > 0 {
            write!(
                w,
                "{sep}SH at {bands} band{}",
                if bands == 1 { "" } else { "s" }
            )?;
            sep = ", ";
        }
        if sep.is_empty() {
            w.write_str("full")?;
        }
        Ok(())
    }

    /// Stale frames in a row after which the renderer says the engine is down (100 ms at 60 Hz:
    /// longer than any jitter of a running engine, short next to a restart).
    pub const ENGINE_DOWN_FRAMES: u64 = 6;
}

/// The renderer's per-frame report, consumed by the launcher's latency harness and by tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Pod, Zeroable)]
#[repr(C)]
pub struct FrameReport {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// [`report_flags`] bits.
    pub flags: u32,
    /// Renderer frame counter.
    pub frame: u64,
    /// Engine tick drawn.
    pub engine_tick: u64,
    /// Tracker frame number behind the engine tick.
    pub tracker_frame: u64,
    /// All hop stamps of the drawn frame.
    pub stamps: HopStamps,
    /// CPU time of the frame (receive → submit), ns.
    pub cpu_frame_ns: u64,
    /// GPU time of the frame's passes from timestamp queries, ns (0 when unsupported).
    pub gpu_frame_ns: u64,
    /// Lung volumes drawn, ml (right, left).
    pub volume_ml: [f32; NUM_LUNGS],
    /// When `present` returned for this frame (CLOCK_MONOTONIC, ns); 0 when nothing was presented
    /// (headless, or the surface gave no image this frame). `present_ns - stamps.renderer_submit_ns`
    /// is the frame's submit-to-present time.
    pub present_ns: u64,
    /// How the frame was presented: a [`present_mode`] code.
    pub present_mode: u32,
    /// The surface's `desired_maximum_frame_latency` (frames queued ahead); 0 when not presented
    /// to a surface.
    pub frame_latency: u32,
    /// When the renderer saw the frame's GPU work complete (CLOCK_MONOTONIC, ns): the wait on the
    /// submission's fence returned (`Device::poll` with the submission index). 0: not observed.
    pub gpu_done_ns: u64,
}

impl FrameReport {
    /// When the frame was shown, CLOCK_MONOTONIC ns: its present (in a window), else when its GPU
    /// work was seen done, else its submit (a time before the submit is not taken).
    pub fn display_ns(&self) -> u64 {
        let submit = self.stamps.renderer_submit_ns;
        if self.present_ns != 0 && self.present_ns >= submit {
            self.present_ns
        } else if self.gpu_done_ns != 0 && self.gpu_done_ns >= submit {
            self.gpu_done_ns
        } else {
            submit
        }
    }
}

/// [`FrameReport::present_mode`]: how a frame reached the display.
pub mod present_mode {
    /// Not presented (headless: the frame stays offscreen).
    pub const NONE: u32 = 0;
    /// FIFO: waits for vertical blank, never tears (up to a refresh of latency).
    pub const FIFO: u32 = 1;
    /// Mailbox: the newest frame replaces a queued one at vertical blank, no tearing.
    pub const MAILBOX: u32 = 2;
    /// Immediate: shown at once, may tear.
    pub const IMMEDIATE: u32 = 3;
    /// FIFO relaxed: FIFO, but a late frame is shown at once (may tear).
    pub const FIFO_RELAXED: u32 = 4;
    /// An OpenXR swapchain (the runtime's compositor paces it).
    pub const OPENXR: u32 = 5;

    /// The code's name, as the demo report writes it.
    pub fn name(code: u32) -> &'static str {
        match code {
            NONE => "none",
            FIFO => "fifo",
            MAILBOX => "mailbox",
            IMMEDIATE => "immediate",
            FIFO_RELAXED => "fifo-relaxed",
            OPENXR => "openxr",
            _ => "unknown",
        }
    }
}

/// A trainee's action sent to a running engine (`lungdyn scene event`, a key in the window): an
/// intervention on one lung. The engine applies it at its next disease cycle and reports it with its
/// tick (EQUATIONS.md §4.3).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct ControlPacket {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// [`Intervention::code`].
    pub kind: u32,
    /// Lung slot ([`LUNG_RIGHT`], [`LUNG_LEFT`]), or [`LUNG_AFFECTED`]: the pneumothorax's side.
    pub lung: u32,
    /// Explicit padding.
    pub _pad: u32,
    /// Sender's sequence number ([`control_sequence`]; a repeated number from the same origin is
    /// one action, not two). The engine's [`ControlReply`]s carry it back.
    pub sequence: u64,
    /// Where the action was raised: [`ORIGIN_LOCAL`] for a sender on this host (`lungdyn scene
    /// event`, the window's keys), otherwise the remote site's id (`lungdyn remote serve` hands a
    /// site's event to the source engine with it). The engine announces each action to every site
    /// with its origin and sequence and the cycle it applies at.
    pub origin: u64,
}

/// [`ControlPacket::origin`] of an action raised on the engine's own host.
pub const ORIGIN_LOCAL: u64 = 0;

/// [`ControlPacket::lung`] meaning "the side of the scene's pneumothorax": the engine resolves it and
/// its [`ControlReply::lung`] names the side it acted on.
pub const LUNG_AFFECTED: u32 = u32::MAX;

/// A [`ControlPacket::lung`] (or [`ControlReply::lung`]) in words: "right", "left", "affected"
/// ([`LUNG_AFFECTED`], before the engine resolves it) or "an unknown side".
pub fn lung_words(lung: u32) -> &'static str {
    match lung as usize {
        LUNG_RIGHT => "right",
        LUNG_LEFT => "left",
        _ if lung == LUNG_AFFECTED => "affected",
        _ => "an unknown side",
    }
}

/// A [`ControlPacket::kind`] code in words: the intervention's name (`needle-decompression`, ...),
/// or "an unknown action" for a code this layout does not define.
pub fn kind_words(code: u32) -> &'static str {
    Intervention::from_code(code).map_or("an unknown action", Intervention::name)
}

/// A sequence number for a [`ControlPacket`] that no other sender of the host uses at the same
/// time: the low 48 bits of the send time (ns; they repeat after 3.2 days) and the low 16 bits of
/// the sender's process id. The engine replies with it, so each sender picks out its own answers.
pub fn control_sequence(pid: u32, now_ns: u64) -> u64 {
    (now_ns & 0x0000_ffff_ffff_ffff) | (u64::from(pid & 0xffff) << 48)
}

/// [`ControlReply::status`]: the engine took the action; it is applied when the next disease cycle
/// is prepared (a second reply, [`REPLY_APPLIED`], follows).
pub const REPLY_RECEIVED: u32 = 1;
/// [`ControlReply::status`]: the action was applied to the disease state; [`ControlReply::outcome`]
/// says what it did, from [`ControlReply::cycle`] on.
pub const REPLY_APPLIED: u32 = 2;
/// [`ControlReply::status`]: the engine cannot use the action (no tension pneumothorax in the scene,
/// an unknown kind or lung); the text says why. Final.
pub const REPLY_IGNORED: u32 = 3;
/// [`ControlReply::status`]: the engine is over capacity (too many actions wait for the next
/// breath); nothing was done, send it again later. Final.
pub const REPLY_REFUSED: u32 = 4;

/// [`ControlReply::outcome`]: it changed the course.
pub const OUTCOME_APPLIED: u32 = 1;
/// [`ControlReply::outcome`]: done on the unaffected side, no effect.
pub const OUTCOME_WRONG_SIDE: u32 = 2;
/// [`ControlReply::outcome`]: the same intervention is already in place.
pub const OUTCOME_ALREADY_APPLIED: u32 = 3;
/// [`ControlReply::outcome`]: it does not act on this pneumothorax (the text says why).
pub const OUTCOME_NO_EFFECT: u32 = 4;

/// Bytes of [`ControlReply::text`].
pub const REPLY_TEXT_BYTES: usize = 128;

/// The engine's answer to one [`ControlPacket`] (engine → every sender; each keeps those with its
/// [`ControlPacket::sequence`]): first [`REPLY_RECEIVED`] (or a final [`REPLY_IGNORED`] /
/// [`REPLY_REFUSED`]), then [`REPLY_APPLIED`] with the outcome and the cycle it shows from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct ControlReply {
    /// [`LAYOUT_VERSION`] of the engine.
    pub layout_version: u32,
    /// [`REPLY_RECEIVED`], [`REPLY_APPLIED`], [`REPLY_IGNORED`] or [`REPLY_REFUSED`].
    pub status: u32,
    /// The [`ControlPacket::sequence`] answered.
    pub sequence: u64,
    /// Engine tick the action arrived at.
    pub tick: u64,
    /// First disease-course cycle (counted from the onset: what `lungdyn scene event` and the
    /// engine call the "disease cycle") whose state reflects it ([`REPLY_APPLIED`] only). Not a
    /// breathing cycle ([`LungFrame::cycle`] counts those; a remote event's `apply_cycle` too): a
    /// joined site's reply carries the source's course cycle, as the source's engine would.
    pub cycle: u64,
    /// [`ControlPacket::kind`] as received.
    pub kind: u32,
    /// The lung acted on ([`LUNG_RIGHT`], [`LUNG_LEFT`]; the packet's lung when unusable).
    pub lung: u32,
    /// [`OUTCOME_APPLIED`], ... ([`REPLY_APPLIED`] only; 0 otherwise).
    pub outcome: u32,
    /// Bytes of [`Self::text`] used.
    pub text_len: u32,
    /// UTF-8 words: what the outcome does ("air venting") or why the action was ignored/refused.
    pub text: [u8; REPLY_TEXT_BYTES],
}

impl Default for ControlReply {
    fn default() -> Self {
        Self {
            layout_version: LAYOUT_VERSION,
            ..Zeroable::zeroed()
        }
    }
}

impl ControlReply {
    /// Set [`Self::text`] to the pieces joined, cut at a character boundary to fit (no allocation:
    /// the engine calls this on its tick).
    pub fn set_text(&mut self, pieces: &[&str]) {
        let mut n = 0;
        'pieces: for piece in pieces {
            for c in piece.chars() {
                let mut buf = [0u8; 4];
                let b = c.encode_utf8(&mut buf).as_bytes();
                if n + b.len() > REPLY_TEXT_BYTES {
                    break 'pieces;
                }
                self.text[n..n + b.len()].copy_from_slice(b);
                n += b.len();
            }
        }
        self.text[n..].fill(0);
        self.text_len = n as u32;
    }

    /// [`Self::text`] as a string (an invalid length or bytes from a faulty peer read as
    /// replacement characters, never a panic).
    pub fn text(&self) -> std::borrow::Cow<'_, str> {
        let n = (self.text_len as usize).min(REPLY_TEXT_BYTES);
        String::from_utf8_lossy(&self.text[..n])
    }
}

/// A trainee's intervention on a tension pneumothorax (EQUATIONS.md §4.3), as named in scenes and
/// on the command line (`needle-decompression`, ...) and as coded in [`ControlPacket::kind`]. This
/// enum is the only place either mapping is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
#[repr(u32)]
pub enum Intervention {
    /// Needle decompression of the affected side.
    NeedleDecompression = 1,
    /// Occlusive dressing of an open chest wound.
    OcclusiveDressing = 2,
    /// Chest tube (tube thoracostomy).
    ChestTube = 3,
}

impl Intervention {
    /// Every intervention, in code order.
    pub const ALL: [Intervention; 3] = [
        Intervention::NeedleDecompression,
        Intervention::OcclusiveDressing,
        Intervention::ChestTube,
    ];

    /// The code carried in [`ControlPacket::kind`].
    pub const fn code(self) -> u32 {
        self as u32
    }

    /// The intervention of a [`ControlPacket::kind`] code; `None` for a code this layout does not
    /// define (such a packet is reported and ignored, never applied).
    pub fn from_code(code: u32) -> Option<Intervention> {
        Intervention::ALL.into_iter().find(|k| k.code() == code)
    }

    /// Name as in scenes and on the command line (the serde name too).
    pub const fn name(self) -> &'static str {
        match self {
            Intervention::NeedleDecompression => "needle-decompression",
            Intervention::OcclusiveDressing => "occlusive-dressing",
            Intervention::ChestTube => "chest-tube",
        }
    }
}

impl core::fmt::Display for Intervention {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not an [`Intervention`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownIntervention(pub String);

impl core::fmt::Display for UnknownIntervention {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{:?} is not an intervention: ", self.0)?;
        for (i, k) in Intervention::ALL.iter().enumerate() {
            let sep = match i {
                0 => "",
                i if i + 1 == Intervention::ALL.len() => " or ",
                _ => ", ",
            };
            write!(f, "{sep}{k}")?;
        }
        Ok(())
    }
}

impl std::error::Error for UnknownIntervention {}

impl core::str::FromStr for Intervention {
    type Err = UnknownIntervention;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Intervention::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| UnknownIntervention(s.to_string()))
    }
}

impl Message for ControlPacket {
    const NAME: &'static str = "ControlPacket";
    const TYPE_NAME: &'static str = "lungdyn.ControlPacket.v9";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}

impl Message for ControlReply {
    const NAME: &'static str = "ControlReply";
    const TYPE_NAME: &'static str = "lungdyn.ControlReply.v9";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}

const VERSION_SUFFIX: &str = ".v9";
const _: () = assert!(
    LAYOUT_VERSION == 9,
    "bump VERSION_SUFFIX with LAYOUT_VERSION"
);

impl Message for TrackerFrame {
    const NAME: &'static str = "TrackerFrame";
    const TYPE_NAME: &'static str = "lungdyn.TrackerFrame.v9";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}
impl Message for EngineFrame {
    const NAME: &'static str = "EngineFrame";
    const TYPE_NAME: &'static str = "lungdyn.EngineFrame.v9";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}
impl Message for FrameReport {
    const NAME: &'static str = "FrameReport";
    const TYPE_NAME: &'static str = "lungdyn.FrameReport.v9";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}

const fn ends_with(s: &str, suffix: &str) -> bool {
    let (s, x) = (s.as_bytes(), suffix.as_bytes());
    if x.len() > s.len() {
        return false;
    }
    let mut i = 0;
    while i < x.len() {
        if s[s.len() - x.len() + i] != x[i] {
            return false;
        }
        i += 1;
    }
    true
}

// The layout, pinned at compile time: a change to any payload must change these lines (and
// LAYOUT_VERSION with them).
const _: () = {
    assert!(ends_with(TrackerFrame::TYPE_NAME, VERSION_SUFFIX));
    assert!(ends_with(EngineFrame::TYPE_NAME, VERSION_SUFFIX));
    assert!(ends_with(FrameReport::TYPE_NAME, VERSION_SUFFIX));
    assert!(ends_with(ControlPacket::TYPE_NAME, VERSION_SUFFIX));
    assert!(size_of::<ControlPacket>() == 32 && align_of::<ControlPacket>() == 8);
    assert!(offset_of!(ControlPacket, kind) == 4);
    assert!(offset_of!(ControlPacket, lung) == 8);
    assert!(offset_of!(ControlPacket, sequence) == 16);
    assert!(offset_of!(ControlPacket, origin) == 24);
    assert!(ends_with(ControlReply::TYPE_NAME, VERSION_SUFFIX));
    assert!(size_of::<ControlReply>() == 48 + REPLY_TEXT_BYTES && align_of::<ControlReply>() == 8);
    assert!(offset_of!(ControlReply, status) == 4);
    assert!(offset_of!(ControlReply, sequence) == 8);
    assert!(offset_of!(ControlReply, tick) == 16);
    assert!(offset_of!(ControlReply, cycle) == 24);
    assert!(offset_of!(ControlReply, kind) == 32);
    assert!(offset_of!(ControlReply, lung) == 36);
    assert!(offset_of!(ControlReply, outcome) == 40);
    assert!(offset_of!(ControlReply, text_len) == 44);
    assert!(offset_of!(ControlReply, text) == 48);

    assert!(size_of::<HopStamps>() == 48 && align_of::<HopStamps>() == 8);
    assert!(offset_of!(HopStamps, capture_ns) == 0);
    assert!(offset_of!(HopStamps, bridge_publish_ns) == 8);
    assert!(offset_of!(HopStamps, engine_receive_ns) == 16);
    assert!(offset_of!(HopStamps, engine_publish_ns) == 24);
    assert!(offset_of!(HopStamps, renderer_receive_ns) == 32);
    assert!(offset_of!(HopStamps, renderer_submit_ns) == 40);

    assert!(size_of::<Pose>() == 32 && align_of::<Pose>() == 4);
    assert!(offset_of!(Pose, quat) == 0);
    assert!(offset_of!(Pose, translation_mm) == 16);
    assert!(offset_of!(Pose, _pad) == 28);

    assert!(size_of::<ToolPose>() == 48 && align_of::<ToolPose>() == 4);
    assert!(offset_of!(ToolPose, tool_id) == 0);
    assert!(offset_of!(ToolPose, status) == 4);
    assert!(offset_of!(ToolPose, pose) == 8);
    assert!(offset_of!(ToolPose, rms_error_mm) == 40);
    assert!(offset_of!(ToolPose, _pad) == 44);

    assert!(size_of::<SignalWire>() == 16 && align_of::<SignalWire>() == 8);
    assert!(offset_of!(SignalWire, t_ns) == 0);
    assert!(offset_of!(SignalWire, value) == 8);
    assert!(
        size_of::<SignalBlock>() == 40 + 16 * MAX_SIGNAL_SAMPLES && align_of::<SignalBlock>() == 8
    );
    assert!(offset_of!(SignalBlock, count) == 0);
    assert!(offset_of!(SignalBlock, unit) == 4);
    assert!(offset_of!(SignalBlock, status) == 8);
    assert!(offset_of!(SignalBlock, valid_mask) == 12);
    assert!(offset_of!(SignalBlock, period_ns) == 16);
    assert!(offset_of!(SignalBlock, samples) == 24);
    assert!(offset_of!(SignalBlock, origin_ns) == 24 + 16 * MAX_SIGNAL_SAMPLES);
    assert!(offset_of!(SignalBlock, pipeline_latency_ns) == 32 + 16 * MAX_SIGNAL_SAMPLES);

    assert!(
        size_of::<TrackerFrame>() == 256 + 40 + 16 * MAX_SIGNAL_SAMPLES
            && align_of::<TrackerFrame>() == 8
    );
    assert!(offset_of!(TrackerFrame, layout_version) == 0);
    assert!(offset_of!(TrackerFrame, tool_count) == 4);
    assert!(offset_of!(TrackerFrame, frame_number) == 8);
    assert!(offset_of!(TrackerFrame, stamps) == 16);
    assert!(offset_of!(TrackerFrame, tools) == 64);
    assert!(offset_of!(TrackerFrame, signal) == 256);

    assert!(size_of::<LungFrame>() == 80 + 4 * MAX_COEFFS && align_of::<LungFrame>() == 8);
    assert!(offset_of!(LungFrame, kernel_id) == 0);
    assert!(offset_of!(LungFrame, volume_ml) == 8);
    assert!(offset_of!(LungFrame, deform_scale) == 12);
    assert!(offset_of!(LungFrame, phase) == 16);
    assert!(offset_of!(LungFrame, cycle) == 20);
    assert!(offset_of!(LungFrame, offset_mm) == 24);
    assert!(offset_of!(LungFrame, flags) == 36);
    assert!(offset_of!(LungFrame, coeff_kind) == 40);
    assert!(offset_of!(LungFrame, coeff_count) == 44);
    assert!(offset_of!(LungFrame, coeffs) == 48);
    assert!(offset_of!(LungFrame, collapse) == 48 + 4 * MAX_COEFFS);
    assert!(offset_of!(LungFrame, hilum_mm) == 52 + 4 * MAX_COEFFS);
    assert!(offset_of!(LungFrame, pressure_cmh2o) == 64 + 4 * MAX_COEFFS);
    assert!(offset_of!(LungFrame, tidal_ml) == 68 + 4 * MAX_COEFFS);
    assert!(offset_of!(LungFrame, cycle_ticks) == 72 + 4 * MAX_COEFFS);
    assert!(offset_of!(LungFrame, inhale_ticks) == 76 + 4 * MAX_COEFFS);

    assert!(size_of::<SignalFollowed>() == 40 && align_of::<SignalFollowed>() == 8);
    assert!(offset_of!(SignalFollowed, display_ns) == 0);
    assert!(offset_of!(SignalFollowed, volume_ml) == 8);
    assert!(offset_of!(SignalFollowed, unpredicted_ml) == 12);
    assert!(offset_of!(SignalFollowed, latency_ns) == 16);
    assert!(offset_of!(SignalFollowed, tidal_ml) == 24);
    assert!(offset_of!(SignalFollowed, period_s) == 28);
    assert!(offset_of!(SignalFollowed, phase) == 32);
    assert!(offset_of!(SignalFollowed, inhale_fraction) == 36);

    assert!(size_of::<EngineFrame>() == 824 && align_of::<EngineFrame>() == 8);
    assert!(offset_of!(EngineFrame, layout_version) == 0);
    assert!(offset_of!(EngineFrame, state) == 4);
    assert!(offset_of!(EngineFrame, fault) == 8);
    assert!(offset_of!(EngineFrame, _pad) == 12);
    assert!(offset_of!(EngineFrame, tick) == 16);
    assert!(offset_of!(EngineFrame, tracker_frame) == 24);
    assert!(offset_of!(EngineFrame, stamps) == 32);
    assert!(offset_of!(EngineFrame, patient_pose) == 80);
    assert!(offset_of!(EngineFrame, lungs) == 112);
    assert!(offset_of!(EngineFrame, signal) == 784);

    assert!(size_of::<FrameReport>() == 128 && align_of::<FrameReport>() == 8);
    assert!(offset_of!(FrameReport, layout_version) == 0);
    assert!(offset_of!(FrameReport, flags) == 4);
    assert!(offset_of!(FrameReport, frame) == 8);
    assert!(offset_of!(FrameReport, engine_tick) == 16);
    assert!(offset_of!(FrameReport, tracker_frame) == 24);
    assert!(offset_of!(FrameReport, stamps) == 32);
    assert!(offset_of!(FrameReport, cpu_frame_ns) == 80);
    assert!(offset_of!(FrameReport, gpu_frame_ns) == 88);
    assert!(offset_of!(FrameReport, volume_ml) == 96);
    assert!(offset_of!(FrameReport, present_ns) == 104);
    assert!(offset_of!(FrameReport, present_mode) == 112);
    assert!(offset_of!(FrameReport, frame_latency) == 116);
    assert!(offset_of!(FrameReport, gpu_done_ns) == 120);
};

/// A received payload claims another layout version than this build speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LayoutError {
    /// Payload type.
    pub payload: &'static str,
    /// What the payload says.
    pub theirs: u32,
    /// What we speak.
    pub ours: u32,
}

impl core::fmt::Display for LayoutError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "received a {} with layout v{}, but this process speaks layout v{}: rebuild all lungdyn \
             processes from one version",
            self.payload, self.theirs, self.ours
        )
    }
}

impl std::error::Error for LayoutError {}

/// Check the layout version a received payload claims.
pub fn check_layout(payload: &'static str, theirs: u32) -> Result<(), LayoutError> {
    if theirs == LAYOUT_VERSION {
        Ok(())
    } else {
        Err(LayoutError {
            payload,
            theirs,
            ours: LAYOUT_VERSION,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_intervention_round_trips_through_its_code_and_name() {
        // Exhaustive: a new variant fails to compile here until it is placed in ALL.
        let index = |k: Intervention| match k {
            Intervention::NeedleDecompression => 0,
            Intervention::OcclusiveDressing => 1,
            Intervention::ChestTube => 2,
        };
        for (i, k) in Intervention::ALL.into_iter().enumerate() {
            assert_eq!(index(k), i);
            assert_eq!(Intervention::from_code(k.code()), Some(k));
            assert_eq!(k.name().parse::<Intervention>(), Ok(k));
            assert_eq!(k.to_string(), k.name());
        }
        // The wire codes are the protocol: pinned.
        let codes: Vec<u32> = Intervention::ALL.iter().map(|k| k.code()).collect();
        assert_eq!(codes, [1, 2, 3]);
    }

    #[test]
    fn reply_text_is_cut_at_a_character_boundary_and_read_back_safely() {
        let mut r = ControlReply::default();
        r.set_text(&["applied", " — ", "air venting"]);
        assert_eq!(r.text(), "applied — air venting");
        // 127 ASCII bytes then a 3-byte dash: the dash does not fit and is left out whole.
        let long = "x".repeat(REPLY_TEXT_BYTES - 1);
        r.set_text(&[&long, "—", "tail"]);
        assert_eq!(r.text(), long);
        assert!(r.text[REPLY_TEXT_BYTES - 1] == 0);
        r.set_text(&[]);
        assert_eq!(r.text(), "");
        // A peer's nonsense length or bytes are read, not trusted.
        r.text_len = u32::MAX;
        r.text = [0xff; REPLY_TEXT_BYTES];
        assert_eq!(r.text().chars().count(), REPLY_TEXT_BYTES);
    }

    #[test]
    fn control_sequences_differ_by_sender_and_by_time() {
        let a = control_sequence(1234, 5_000_000_000);
        assert_ne!(a, control_sequence(1235, 5_000_000_000));
        assert_ne!(a, control_sequence(1234, 5_000_000_001));
        assert_eq!(a >> 48, 1234);
    }

    #[test]
    fn unknown_intervention_codes_and_names_are_refused() {
        for code in [0, 4, 5, 0x100, u32::MAX] {
            assert_eq!(Intervention::from_code(code), None, "{code}");
        }
        for name in ["", "chest tube", "Chest-Tube", "needle", "chest-tube "] {
            let e = name.parse::<Intervention>().unwrap_err();
            assert_eq!(
                e.to_string(),
                format!(
                    "{name:?} is not an intervention: needle-decompression, occlusive-dressing \
                     or chest-tube"
                )
            );
        }
    }

    #[test]
    fn stamps_order_check_rejects_gaps_and_reversals() {
        let mut s = HopStamps {
            capture_ns: 1,
            bridge_publish_ns: 2,
            engine_receive_ns: 3,
            engine_publish_ns: 4,
            renderer_receive_ns: 5,
            renderer_submit_ns: 6,
        };
        assert!(s.is_complete_and_ordered());
        s.engine_publish_ns = 0;
        assert!(!s.is_complete_and_ordered());
        s.engine_publish_ns = 2;
        assert!(!s.is_complete_and_ordered());
    }

    #[test]
    fn payloads_round_trip_through_their_bytes() {
        let mut f = EngineFrame {
            layout_version: LAYOUT_VERSION,
            tick: 77,
            ..Default::default()
        };
        f.lungs[LUNG_LEFT].coeffs[63] = -1.5;
        f.lungs[LUNG_LEFT].kernel_id = 0xdead_beef_0123_4567;
        f.lungs[LUNG_RIGHT].offset_mm = [1.0, -2.0, 3.5];
        let bytes = bytemuck::bytes_of(&f).to_vec();
        assert_eq!(bytes.len(), 824);
        let back: EngineFrame = bytemuck::pod_read_unaligned(&bytes);
        assert_eq!(back, f);
        // Little-endian on every supported host: the kernel id sits at byte 112 + 336 (left lung).
        assert_eq!(
            u64::from_le_bytes(bytes[448..456].try_into().unwrap()),
            0xdead_beef_0123_4567
        );
    }

    #[test]
    fn a_payload_of_another_layout_is_refused_by_name() {
        let f = EngineFrame {
            layout_version: LAYOUT_VERSION + 1,
            ..Default::default()
        };
        let e = f.check_layout().unwrap_err();
        assert_eq!(e.theirs, LAYOUT_VERSION + 1);
        assert!(
            e.to_string()
                .contains(&format!("EngineFrame with layout v{}", LAYOUT_VERSION + 1)),
            "{e}"
        );
        assert!(TrackerFrame {
            layout_version: LAYOUT_VERSION,
            ..Default::default()
        }
        .check_layout()
        .is_ok());
    }

    #[test]
    fn a_tool_is_used_only_when_present_valid_and_finite() {
        let mut f = TrackerFrame {
            tool_count: 1,
            ..Default::default()
        };
        f.tools[TOOL_PATIENT].status = tool_status::VALID;
        assert!(f.valid_tool(TOOL_PATIENT).is_some());
        assert!(f.valid_tool(TOOL_HMD).is_none(), "slot beyond tool_count");
        assert!(f.valid_tool(99).is_none());
        f.tools[TOOL_PATIENT].pose.quat[0] = f32::NAN;
        assert!(f.valid_tool(TOOL_PATIENT).is_none());
    }
}
