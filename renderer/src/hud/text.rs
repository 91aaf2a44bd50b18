//! The heads-up display's words and numbers, apart from any GPU: what each line says, the PV loop
//! it traces and how that loop is scaled into its box. Everything here is a pure function of the
//! frames the renderer already receives (engine frames, tracker frames, the engine's control
//! replies) and is unit-tested; [`super::Hud`] only draws it.
//!
//! Formatting writes into `String`s the HUD keeps from frame to frame (`clear` then `write!`), so a
//! frame allocates nothing once the lines have reached their longest.

use std::fmt::Write;

use lung_model::mesh::lobes::Lobe;

use ipc_types::{
    tool_status, ControlReply, EngineFrame, Intervention, TrackerFrame, LUNG_LEFT, LUNG_RIGHT,
    NUM_LUNGS,
};

/// `mm:ss` of an engine tick (the time since the engine started, as the trainee's clock):
/// "01:02". Hours roll into the minutes ("75:00"); a non-positive or non-finite rate gives "--:--".
pub struct Clock {
    /// Engine tick.
    pub tick: u64,
    /// Engine ticks per second.
    pub tick_hz: f64,
}

impl core::fmt::Display for Clock {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        if !(self.tick_hz.is_finite() && self.tick_hz > 0.0) {
            return f.write_str("--:--");
        }
        let s = (self.tick as f64 / self.tick_hz).floor() as u64;
        write!(f, "{:02}:{:02}", s / 60, s % 60)
    }
}

/// An intervention's name in words ("needle decompression").
pub fn kind_words(kind: Intervention) -> &'static str {
    match kind {
        Intervention::NeedleDecompression => "needle decompression",
        Intervention::OcclusiveDressing => "occlusive dressing",
        Intervention::ChestTube => "chest tube",
    }
}

/// A lung slot in words.
pub fn lung_words(lung: u32) -> &'static str {
    match lung as usize {
        LUNG_RIGHT => "right",
        LUNG_LEFT => "left",
        _ => "affected side",
    }
}

/// How an intervention stands, for colouring its line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Standing {
    /// Sent, no answer yet (or received, waiting for the breath that applies it).
    Pending,
    /// Applied and it changed the course.
    Done,
    /// Applied without effect, ignored or refused.
    Failed,
}

/// One line for the engine's latest answer to an intervention, with the engine time it refers to:
/// "needle decompression, left, applied 01:02 — air venting"; "chest tube, right, wrong side
/// 01:05 — the pneumothorax is on the other side"; "chest tube, left, received 00:40 — applied
/// with the next breath". Returns how it stands.
pub fn outcome_line(
    out: &mut String,
    kind: Intervention,
    r: &ControlReply,
    tick_hz: f64,
) -> Standing {
    out.clear();
    let at = Clock {
        tick: r.tick,
        tick_hz,
    };
    let (word, standing) = match r.status {
        ipc_types::REPLY_RECEIVED => ("received", Standing::Pending),
        ipc_types::REPLY_APPLIED => match r.outcome {
            ipc_types::OUTCOME_APPLIED => ("applied", Standing::Done),
            ipc_types::OUTCOME_WRONG_SIDE => ("wrong side", Standing::Failed),
            ipc_types::OUTCOME_ALREADY_APPLIED => ("already in place", Standing::Failed),
            ipc_types::OUTCOME_NO_EFFECT => ("no effect", Standing::Failed),
            _ => ("unknown outcome", Standing::Failed),
        },
        ipc_types::REPLY_IGNORED => ("ignored", Standing::Failed),
        ipc_types::REPLY_REFUSED => ("refused", Standing::Failed),
        _ => ("unknown answer", Standing::Failed),
    };
    let _ = write!(
        out,
        "{}, {}, {word} {at}",
        kind_words(kind),
        lung_words(r.lung)
    );
    let text = r.text();
    if r.status == ipc_types::REPLY_RECEIVED && text.is_empty() {
        out.push_str(" — applied with the next breath");
    } else if !text.is_empty() {
        let _ = write!(out, " — {text}");
    }
    standing
}

/// The line for an intervention sent from the window that the engine has not answered yet.
pub fn sent_line(out: &mut String, kind: Intervention, lung: u32) {
    out.clear();
    let _ = write!(
        out,
        "{}, {}, sent — waiting for the engine",
        kind_words(kind),
        lung_words(lung)
    );
}

/// Breaths per minute of a cycle of `cycle_ticks` engine ticks; `None` for an empty slot or a bad
/// rate.
pub fn rate_per_min(cycle_ticks: u32, tick_hz: f64) -> Option<f64> {
    (cycle_ticks > 0 && tick_hz.is_finite() && tick_hz > 0.0)
        .then(|| 60.0 * tick_hz / cycle_ticks as f64)
}

/// The lung whose breath the HUD follows (the phase bar, the rate, the PV loop): the first active
/// lung that breathes, else the first active one.
pub fn breathing_lung(frame: &EngineFrame) -> Option<usize> {
    let active = |k: usize| frame.lungs[k].is_active();
    let breathes = |k: usize| active(k) && frame.lungs[k].flags & ipc_types::lung_flags::HELD == 0;
    (0..NUM_LUNGS)
        .find(|&k| breathes(k))
        .or_else(|| (0..NUM_LUNGS).find(|&k| active(k)))
}

/// Total volume, total tidal volume (ml) and the followed lung's rate: "V 2650 ml  TV 500 ml
/// 12 /min" (29 characters: one row of the compact HUD's panel at 320 px). While the patient's
/// signal drives the lungs, the tidal volume and the rate are the patient's typical breath as
/// followed (the model's would be another breath than the one drawn).
pub fn volume_line(out: &mut String, frame: &EngineFrame, tick_hz: f64) {
    out.clear();
    let (mut v, mut tv) = (0.0f64, 0.0f64);
    for l in frame.lungs.iter().filter(|l| l.is_active()) {
        v += l.volume_ml as f64;
        tv += l.tidal_ml as f64;
    }
    let s = &frame.signal;
    let following = frame.state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0;
    if following && s.tidal_ml > 0.0 && s.tidal_ml.is_finite() {
        tv = s.tidal_ml as f64;
    }
    let _ = write!(out, "V {v:4.0} ml  TV {tv:3.0} ml");
    let patient_rate =
        (following && s.period_s > 0.0 && s.period_s.is_finite()).then(|| 60.0 / s.period_s as f64);
    match patient_rate.or_else(|| {
        breathing_lung(frame).and_then(|k| rate_per_min(frame.lungs[k].cycle_ticks, tick_hz))
    }) {
        Some(r) => {
            let _ = write!(out, "  {r:2.0} /min");
        }
        None => out.push_str("  -- /min"),
    }
}

/// Where the followed lung is in its breath: the fraction of the cycle done, `[0, 1)`, whether it
/// inhales, and the fraction of the cycle that is inhalation; `None` when no lung breathes. While
/// the patient's signal drives the lungs, the patient's breath as followed (layout v9).
pub fn breath_phase(frame: &EngineFrame) -> Option<(f32, bool, f32)> {
    let k = breathing_lung(frame)?;
    let l = &frame.lungs[k];
    if l.flags & ipc_types::lung_flags::HELD != 0 || l.cycle_ticks == 0 || !l.phase.is_finite() {
        return None;
    }
    // While the patient's signal drives the lungs: the patient's breath, not the model's clock.
    let s = &frame.signal;
    if frame.state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0
        && s.period_s > 0.0
        && (0.0..1.0).contains(&s.phase)
        && (0.0..=1.0).contains(&s.inhale_fraction)
    {
        let inhaling = l.flags & ipc_types::lung_flags::INHALING != 0;
        return Some((s.phase, inhaling, s.inhale_fraction));
    }
    let split = (l.inhale_ticks as f32 / l.cycle_ticks as f32).clamp(0.0, 1.0);
    Some((
        l.phase.clamp(0.0, 1.0),
        l.flags & ipc_types::lung_flags::INHALING != 0,
        split,
    ))
}

/// The disease state in words, from the scene's `[disease]` (its kind and side) and what the
/// frame shows of each lung: "tension pneumothorax, left: lung 62 % collapsed, not breathing".
/// Without a disease: "healthy lungs". A lung drawn past its kernel's fold-free volume is named in
/// capitals after it.
pub fn disease_line(out: &mut String, disease: Option<(&str, Option<usize>)>, frame: &EngineFrame) {
    out.clear();
    lungs_state(out, disease, frame);
    // A lung drawn outside the range its kernel was checked free of folds at bake time.
    for (k, l) in frame.lungs.iter().enumerate() {
        if l.is_active() && l.flags & ipc_types::lung_flags::PAST_FOLD_FREE != 0 {
            let _ = write!(
                out,
                " · {} LUNG PAST ITS FOLD-FREE VOLUME",
                if k == ipc_types::LUNG_LEFT {
                    "LEFT"
                } else {
                    "RIGHT"
                }
            );
        }
    }
}

/// Whether a lung is drawn past its kernel's fold-free volume (the disease line says so in amber).
pub fn past_fold_free(frame: &EngineFrame) -> bool {
    frame
        .lungs
        .iter()
        .any(|l| l.is_active() && l.flags & ipc_types::lung_flags::PAST_FOLD_FREE != 0)
}

fn lungs_state(out: &mut String, disease: Option<(&str, Option<usize>)>, frame: &EngineFrame) {
    let Some((kind, side)) = disease else {
        out.push_str("healthy lungs");
        return;
    };
    out.push_str(kind);
    let mut sep = match side {
        Some(k) => {
            let _ = write!(out, ", {}", lung_words(k as u32));
            ": "
        }
        None => ": ",
    };
    for (k, l) in frame.lungs.iter().enumerate() {
        if !l.is_active() || side.is_some_and(|s| s != k) {
            continue;
        }
        let held = l.flags & ipc_types::lung_flags::HELD != 0;
        if l.collapse <= 0.0 && !held {
            continue;
        }
        out.push_str(sep);
        sep = "; ";
        if side.is_none() {
            let _ = write!(out, "{} ", lung_words(k as u32));
        }
        if l.collapse > 0.0 && l.collapse.is_finite() {
            let _ = write!(out, "lung {:.0} % collapsed", l.collapse * 100.0);
            if held {
                out.push_str(", ");
            }
        }
        if held {
            out.push_str("not breathing");
        }
    }
}

/// One tool's tracker status in a word.
pub fn tool_words(status: u32) -> &'static str {
    use tool_status as t;
    // The reason the bridge gives, most serious first; VALID only when nothing else is set.
    for (bit, word) in [
        (t::DEVICE_FAULT, "fault"),
        (t::NON_FINITE, "bad pose"),
        (t::NOT_ROTATION, "bad pose"),
        (t::STALE, "stale"),
        (t::MISSING, "not seen"),
        (t::OUT_OF_VOLUME, "out of volume"),
        (t::HIGH_RMS, "high error"),
    ] {
        if status & bit != 0 {
            return word;
        }
    }
    if status & t::VALID == 0 {
        "invalid"
    } else if status & t::PARTIALLY_VISIBLE != 0 {
        "partly seen"
    } else {
        "ok"
    }
}

/// The name of a tool slot.
pub fn tool_name(slot: usize) -> &'static str {
    match slot {
        ipc_types::TOOL_PATIENT => "patient",
        ipc_types::TOOL_HMD => "HMD",
        2 => "tool 3",
        _ => "tool 4",
    }
}

/// Tracker health per tool: "tracker: patient ok · HMD not seen"; "tracker: no samples" before any.
/// Returns whether every tool is ok.
pub fn tracker_line(out: &mut String, tracker: Option<&TrackerFrame>) -> bool {
    out.clear();
    out.push_str("tracker:");
    let Some(t) = tracker else {
        out.push_str(" no samples");
        return false;
    };
    let n = (t.tool_count as usize).min(ipc_types::MAX_TOOLS);
    if n == 0 {
        out.push_str(" no tools");
        return false;
    }
    let mut all_ok = true;
    for (slot, tool) in t.tools[..n].iter().enumerate() {
        let w = tool_words(tool.status);
        all_ok &= w == "ok";
        let _ = write!(
            out,
            "{}{} {w}",
            if slot == 0 { " " } else { " · " },
            tool_name(slot)
        );
    }
    all_ok
}

/// Frame time and end-to-end latency (tracker capture → frame submitted) of the last frame:
/// "frame 3.1 ms (GPU 1.2 ms) · latency 11.8 ms"; with what the quality governor gave up
/// ([`governor_words`]).
pub fn timing_line(
    out: &mut String,
    cpu_ns: u64,
    gpu_ns: Option<u64>,
    lod: &crate::lod::Shown,
    governor: Option<u32>,
    latency_ns: Option<u64>,
) {
    out.clear();
    let _ = write!(out, "frame {:.1} ms", cpu_ns as f64 / 1e6);
    if let Some(g) = gpu_ns {
        let _ = write!(out, " (GPU {:.1} ms)", g as f64 / 1e6);
    }
    // The draw level: "LOD 1/3" (auto: level 1 of 0..3), "LOD 2 fixed", "LOD off" (every
    // triangle, no levels built).
    let _ = match (lod.auto, lod.coarsest) {
        (true, c) if c > 0 => write!(out, " · LOD {}/{c}", lod.level),
        (false, c) if c > 0 || lod.level > 0 => write!(out, " · LOD {} fixed", lod.level),
        _ => write!(out, " · LOD off"),
    };
    if let Some(bits) = governor {
        governor_words(out, bits);
    }
    match latency_ns {
        Some(l) => {
            let _ = write!(out, " · latency {:.1} ms", l as f64 / 1e6);
        }
        None => out.push_str(" · latency --"),
    }
}

/// What the HUD's PV box shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PvBox {
    /// The model's PV loop.
    Loop,
    /// The last 10 s of the lungs' volume and the patient's measured volume (a scene breathing
    /// with the signal).
    Signal,
    /// The last 10 s of the lungs' volume at a remote site while the source's patient drives them
    /// (the patient's samples stay at the source: the lungs' line alone).
    SitePatient,
}

impl PvBox {
    /// The box's titles, longest first (the longest that fits is shown).
    pub fn titles(self) -> &'static [&'static str] {
        match self {
            PvBox::Signal => &[
                "last 10 s: lungs white, patient blue",
                "10 s: lungs white, patient blue",
                "lungs white, patient blue",
                "10 s trace",
                "trace",
            ],
            PvBox::SitePatient => &[
                "last 10 s: lungs, breathing with the source's patient",
                "10 s: lungs with the source's patient",
                "lungs with the source's patient",
                "10 s trace",
                "trace",
            ],
            PvBox::Loop => &[
                "PV loop  P → cmH2O, V ↑ ml",
                "PV  P → cmH2O, V ↑ ml",
                "PV  P→cmH2O V↑ml",
                "PV  P→ V↑",
                "PV",
            ],
        }
    }
}

/// What the PV box shows for a frame of engine `state` in a scene of `config`: the signal's trace
/// in a scene that follows the signal; at a remote site, the lungs' trace while the source's
/// patient drives them (`SIGNAL_FOLLOWING` or `SIGNAL_PAUSED`), the model's PV loop otherwise (its
/// pressure is the model's, so beside the patient's volume it would draw a loop no one breathed).
pub fn pv_box_shows(config: &super::HudConfig, state: u32) -> PvBox {
    use ipc_types::engine_state as e;
    if config.signal {
        PvBox::Signal
    } else if config.remote_site && state & (e::SIGNAL_FOLLOWING | e::SIGNAL_PAUSED) != 0 {
        PvBox::SitePatient
    } else {
        PvBox::Loop
    }
}

/// The governor's part of the timing line, short so the line keeps to one row: nothing at full
/// quality; " · less: AA LOD+2 VTX OIT SH2" for what it gave up (multisampling, draw levels, the
/// vertices of other levels not moved, the translucent look, the spherical harmonics capped at 2
/// bands — an accuracy step the scene allowed), "LATE" instead of "less" at its
/// floor (everything given up, frames still over target).
fn governor_words(out: &mut String, bits: u32) {
    use ipc_types::report_flags as r;
    let floor = bits & r::GOVERNOR_FLOOR != 0;
    if bits & r::QUALITY_LOWERED == 0 && !floor {
        return;
    }
    out.push_str(if floor { " · LATE:" } else { " · less:" });
    if bits & r::QUALITY_MSAA_OFF != 0 {
        out.push_str(" AA");
    }
    let lod = (bits & r::QUALITY_LOD_MASK) >> r::QUALITY_LOD_SHIFT;
    if lod > 0 {
        let _ = write!(out, " LOD+{lod}");
    }
    if bits & r::QUALITY_DRAWN_ONLY != 0 {
        out.push_str(" VTX");
    }
    if bits & r::QUALITY_OPAQUE != 0 {
        out.push_str(" OIT");
    }
    let bands = (bits & r::QUALITY_SH_MASK) >> r::QUALITY_SH_SHIFT;
    if bands > 0 {
        let _ = write!(out, " SH{bands}");
    }
    if bits & r::QUALITY_LOWERED == 0 {
        out.push_str(" nothing to give up");
    }
}

/// The key help line (the window's keys; `interventions`: the scene has a tension pneumothorax).
pub fn key_help(interventions: bool) -> &'static str {
    if interventions {
        "keys: H hud · N needle decompression · C chest tube · O occlusive dressing"
    } else {
        "keys: H hud"
    }
}

/// The lobes colour mode's legend entries: (lobe, abbreviation) of each lung shown with its lobe
/// codes (`lungs`, per slot: `None` not loaded, `Some(has_lobe_codes)`), right lung first.
pub fn lobe_legend(lungs: [Option<bool>; ipc_types::NUM_LUNGS]) -> Vec<(Lobe, &'static str)> {
    let mut out = Vec::new();
    if lungs[ipc_types::LUNG_RIGHT] == Some(true) {
        out.extend([
            (Lobe::RightUpper, "RUL"),
            (Lobe::RightMiddle, "RML"),
            (Lobe::RightLower, "RLL"),
        ]);
    }
    if lungs[ipc_types::LUNG_LEFT] == Some(true) {
        out.extend([(Lobe::LeftUpper, "LUL"), (Lobe::LeftLower, "LLL")]);
    }
    out
}

/// The lungs loaded without lobe codes, in words ("right lung", "both lungs"), if any.
pub fn lungs_without_lobes(lungs: [Option<bool>; ipc_types::NUM_LUNGS]) -> Option<&'static str> {
    match (
        lungs[ipc_types::LUNG_RIGHT] == Some(false),
        lungs[ipc_types::LUNG_LEFT] == Some(false),
    ) {
        (true, true) => Some("both lungs"),
        (true, false) => Some("right lung"),
        (false, true) => Some("left lung"),
        (false, false) => None,
    }
}

/// The HUD's warning for lungs without lobe codes in the lobes colour mode (short enough for a
/// 480 px eye), if any.
pub fn lobe_warning(lungs: [Option<bool>; ipc_types::NUM_LUNGS]) -> Option<String> {
    lungs_without_lobes(lungs).map(|which| format!("NO LOBE DATA: {which} grey (old kernel)"))
}

/// The words on the held/stale veil.
pub fn veil_words(warning: crate::PoseWarning) -> Option<&'static str> {
    match warning {
        crate::PoseWarning::None => None,
        crate::PoseWarning::Held => Some("PATIENT POSE HELD — placement may lag the patient"),
        crate::PoseWarning::Stale => {
            Some("PATIENT POSE STALE — do not trust where the lungs are drawn")
        }
        crate::PoseWarning::EngineDown => {
            Some("ENGINE RESTARTING — last frame shown, the breath is frozen")
        }
        crate::PoseWarning::SignalLost => {
            Some("BREATHING SIGNAL LOST — the model breathes, not the patient")
        }
    }
}

/// The breath's phase in words and, when the scene breathes with the patient's signal, what drives
/// it: "inspiration · following patient, predicted 9 ms ahead" (the latency the engine predicted
/// the breath across), "expiration · model (signal lost)". Allocates nothing once `out` has room.
pub fn phase_line(out: &mut String, frame: &EngineFrame) {
    use ipc_types::engine_state as e;
    out.clear();
    let signal = frame.state
        & (e::SIGNAL_FOLLOWING | e::SIGNAL_CALIBRATING | e::SIGNAL_LOST | e::SIGNAL_PAUSED);
    let paused = signal & e::SIGNAL_PAUSED != 0;
    out.push_str(match breath_phase(frame) {
        _ if paused => "pause",
        Some((_, true, _)) => "inspiration",
        Some((_, false, _)) => "expiration",
        None => "not breathing",
    });
    if signal == 0 {
        return;
    }
    if signal & e::SIGNAL_FOLLOWING != 0 {
        out.push_str(" · following patient");
        let ms = (frame.signal.latency_ns as f64 * 1e-6).round();
        if frame.signal.latency_ns != 0 {
            let _ = write!(out, ", predicted {ms:.0} ms ahead");
        }
        if frame.state & e::SIGNAL_CLIPPED != 0 {
            // The sensor's range cuts the breaths: what is drawn is shallower than the patient.
            out.push_str(" · SIGNAL LOOKS CLIPPED: breaths may be deeper than drawn");
        }
        return;
    }
    out.push_str(if frame.state & e::SIGNAL_LEARNING != 0 {
        " · model (learning the chest's axis)"
    } else if signal & e::SIGNAL_CALIBRATING != 0 {
        " · model (calibrating signal)"
    } else {
        " · model (signal lost)"
    });
}

/// Phase bins of the traced PV loop: one point per bin of the followed lung's cycle.
pub const PV_BINS: usize = 96;

/// The PV loop of the followed lung's current breathing (pressure, total volume), one point per
/// phase bin, filled as frames arrive; it starts again when the cycle's length changes (a new
/// rate from a disease or an intervention).
#[derive(Debug, Clone)]
pub struct PvTrace {
    points: [(f32, f32); PV_BINS],
    filled: [bool; PV_BINS],
    cycle_ticks: u32,
    /// The newest point.
    pub current: Option<(f32, f32)>,
}

impl Default for PvTrace {
    fn default() -> Self {
        Self {
            points: [(0.0, 0.0); PV_BINS],
            filled: [false; PV_BINS],
            cycle_ticks: 0,
            current: None,
        }
    }
}

impl PvTrace {
    /// Record the frame's point (pressure of the followed lung, volume of both); a non-finite one
    /// is left out.
    pub fn record(&mut self, frame: &EngineFrame) {
        let Some(k) = breathing_lung(frame) else {
            self.current = None;
            return;
        };
        let l = &frame.lungs[k];
        let v: f32 = frame
            .lungs
            .iter()
            .filter(|l| l.is_active())
            .map(|l| l.volume_ml)
            .sum();
        let p = l.pressure_cmh2o;
        if !(p.is_finite() && v.is_finite() && l.phase.is_finite()) {
            return;
        }
        if l.cycle_ticks != self.cycle_ticks {
            *self = Self {
                cycle_ticks: l.cycle_ticks,
                ..Self::default()
            };
        }
        let bin = ((l.phase.clamp(0.0, 1.0) * PV_BINS as f32) as usize).min(PV_BINS - 1);
        self.points[bin] = (p, v);
        self.filled[bin] = true;
        self.current = Some((p, v));
    }

    /// The point of phase bin `k`, if one was recorded.
    pub fn point(&self, k: usize) -> Option<(f32, f32)> {
        (*self.filled.get(k)?).then(|| self.points[k])
    }

    /// The recorded points in phase order.
    pub fn points(&self) -> impl Iterator<Item = (f32, f32)> + '_ {
        self.points
            .iter()
            .zip(&self.filled)
            .filter(|(_, f)| **f)
            .map(|(p, _)| *p)
    }
}

/// How a PV loop maps into its box: pressure on x, volume on y (up), each axis over the loop's
/// range with a margin; an axis whose range is empty (a held lung) is centred.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PvScale {
    /// Pressure range shown, cmH2O.
    pub p: (f32, f32),
    /// Volume range shown, ml.
    pub v: (f32, f32),
}

impl PvScale {
    /// The scale that shows every point (non-finite ones are ignored); `None` without points.
    pub fn fit(points: impl Iterator<Item = (f32, f32)>) -> Option<Self> {
        let mut r: Option<((f32, f32), (f32, f32))> = None;
        for (p, v) in points.filter(|(p, v)| p.is_finite() && v.is_finite()) {
            let ((p0, p1), (v0, v1)) = r.unwrap_or(((p, p), (v, v)));
            r = Some(((p0.min(p), p1.max(p)), (v0.min(v), v1.max(v))));
        }
        let (p, v) = r?;
        let pad = |(a, b): (f32, f32), least: f32| {
            let m = ((b - a) * 0.08).max(least);
            (a - m, b + m)
        };
        // At least ±0.5 cmH2O and ±10 ml: a held lung's single point sits in the middle.
        Some(Self {
            p: pad(p, 0.5),
            v: pad(v, 10.0),
        })
    }

    /// Where `(p, v)` lies in a box at `(x, y)` of size `(w, h)` pixels (y down), clamped into it.
    pub fn to_px(&self, (p, v): (f32, f32), (x, y, w, h): (f32, f32, f32, f32)) -> (f32, f32) {
        let u = ((p - self.p.0) / (self.p.1 - self.p.0)).clamp(0.0, 1.0);
        let t = ((v - self.v.0) / (self.v.1 - self.v.0)).clamp(0.0, 1.0);
        let (u, t) = (
            if u.is_finite() { u } else { 0.5 },
            if t.is_finite() { t } else { 0.5 },
        );
        (x + u * w, y + (1.0 - t) * h)
    }
}

/// Seconds of breathing the signal trace shows.
pub const TRACE_SECONDS: f64 = 10.0;

/// Points of the signal trace: one every twelfth of a second over [`TRACE_SECONDS`].
pub const TRACE_POINTS: usize = 120;

/// One point of the [`SignalTrace`], both lungs together, ml.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TracePoint {
    /// The volume the lungs were drawn at (`None`: no frame in this twelfth of a second — a stall
    /// shows as a gap, never as a line drawn through it).
    pub drawn_ml: Option<f32>,
    /// The patient's measured volume on the same scale — the newest sample's, before prediction —
    /// while the signal drives the lungs (following, or paused on a breath-hold); `None` while the
    /// model breathes (calibrating, lost) or in a scene that breathes with the model.
    pub measured_ml: Option<f32>,
}

/// The last [`TRACE_SECONDS`] of the breath as drawn, beside the patient's signal (issue 35): the
/// HUD's box shows it instead of the PV loop when the scene breathes with the patient's signal, so
/// whoever looks sees whether the lungs follow the patient, and when they do not.
///
/// The measured volume is put on the drawn volume's scale through the engine's own figures: with
/// both lungs breathing freely the lungs are drawn at FRC plus the predicted volume
/// ([`ipc_types::SignalFollowed::volume_ml`]; each lung takes its share of it, the shares making
/// the whole), so `drawn − predicted + unpredicted` is FRC plus the newest sample's volume and the
/// gap between the two lines is what the prediction moved the lungs ahead. A pneumothorax keeps
/// that: since 2026-12-06 a held or collapsing lung's part of the signal moves to the other lung
/// (the engine's `share_signal`, EQUATIONS.md §4.7), so the lungs still take it whole, on bases the
/// course moves at its cycle starts (both lines step together). Only with every lung held (an
/// arrest) do the lungs take none of it: there the measured line is left out rather than drawn on
/// a wrong scale. (The half second in which the signal takes over from the model
/// blends the two, so the lines part there.) Points are kept by the frame's engine
/// tick (one per twelfth of a second of the engine's clock, a repeated frame adds nothing), in a
/// fixed ring: recording allocates nothing.
#[derive(Debug, Clone)]
pub struct SignalTrace {
    points: [TracePoint; TRACE_POINTS],
    /// Points recorded, at most [`TRACE_POINTS`].
    len: usize,
    /// Where the next point goes.
    next: usize,
    /// The slot (twelfth of a second of engine time) of the newest point.
    slot: Option<u64>,
    /// The newest frame's tick (a tick that goes back starts a fresh trace, even within a slot).
    tick: u64,
}

impl Default for SignalTrace {
    fn default() -> Self {
        Self {
            points: [TracePoint::default(); TRACE_POINTS],
            len: 0,
            next: 0,
            slot: None,
            tick: 0,
        }
    }
}

impl SignalTrace {
    /// Record frame `frame` of an engine ticking at `tick_hz`: a new point when its tick is in a new
    /// slot, gaps for slots no frame came in (at most the whole trace), a fresh trace when the tick
    /// went back (a restarted run). A non-finite volume is left out.
    pub fn record(&mut self, frame: &EngineFrame, tick_hz: f64) {
        use ipc_types::engine_state as e;
        let per_slot = tick_hz * TRACE_SECONDS / TRACE_POINTS as f64;
        if !(per_slot.is_finite() && per_slot > 0.0) {
            return;
        }
        let slot = (frame.tick as f64 / per_slot).floor() as u64;
        if frame.tick < self.tick {
            *self = Self::default();
        }
        self.tick = frame.tick;
        match self.slot {
            Some(s) if slot == s => return,
            Some(s) if slot < s => *self = Self::default(),
            Some(s) => {
                for _ in 0..(slot - s - 1).min(TRACE_POINTS as u64) {
                    self.push(TracePoint::default());
                }
            }
            None => {}
        }
        self.slot = Some(slot);
        let active = frame.lungs.iter().filter(|l| l.is_active());
        let drawn: f32 = active.map(|l| l.volume_ml).sum();
        let drawn = drawn.is_finite().then_some(drawn);
        // A lung breathing: the lungs together take the whole of the signal's volume (a held or
        // collapsing lung's part moves to the other, the engine's `share_signal`).
        let whole = frame
            .lungs
            .iter()
            .any(|l| l.is_active() && l.flags & ipc_types::lung_flags::HELD == 0);
        let following = frame.state & (e::SIGNAL_FOLLOWING | e::SIGNAL_PAUSED) != 0
            && frame.signal.display_ns != 0
            && whole;
        let measured = drawn
            .filter(|_| following)
            .map(|d| d - frame.signal.volume_ml + frame.signal.unpredicted_ml)
            .filter(|m| m.is_finite());
        self.push(TracePoint {
            drawn_ml: drawn,
            measured_ml: measured,
        });
    }

    fn push(&mut self, p: TracePoint) {
        self.points[self.next] = p;
        self.next = (self.next + 1) % TRACE_POINTS;
        self.len = (self.len + 1).min(TRACE_POINTS);
    }

    /// The points, oldest first, each with its place on the time axis (0 the oldest slot the
    /// trace can hold, [`TRACE_POINTS`]` − 1` the newest): a young trace fills from the right.
    pub fn points(&self) -> impl Iterator<Item = (usize, TracePoint)> + '_ {
        (TRACE_POINTS - self.len..TRACE_POINTS).filter_map(move |k| Some((k, self.point(k)?)))
    }

    /// The point at place `k` of the time axis (as [`Self::points`] numbers them), if recorded.
    pub fn point(&self, k: usize) -> Option<TracePoint> {
        let empty = TRACE_POINTS - self.len;
        let age = k.checked_sub(empty).filter(|&a| a < self.len)?;
        let first = (self.next + TRACE_POINTS - self.len) % TRACE_POINTS;
        Some(self.points[(first + age) % TRACE_POINTS])
    }

    /// The volume range shown: every drawn and measured volume with an 8 % margin, at least ±25 ml
    /// (a held breath is a line in the middle); `None` without a volume.
    pub fn range(&self) -> Option<(f32, f32)> {
        let mut r: Option<(f32, f32)> = None;
        for (_, p) in self.points() {
            for v in [p.drawn_ml, p.measured_ml].into_iter().flatten() {
                let (lo, hi) = r.unwrap_or((v, v));
                r = Some((lo.min(v), hi.max(v)));
            }
        }
        let (lo, hi) = r?;
        let m = ((hi - lo) * 0.08).max(25.0);
        Some((lo - m, hi + m))
    }

    /// Where point `(k, volume)` lies in the box `(x, y, w, h)` over `range`.
    pub fn to_px(
        k: usize,
        volume_ml: f32,
        (lo, hi): (f32, f32),
        (x, y, w, h): (f32, f32, f32, f32),
    ) -> (f32, f32) {
        let u = k as f32 / (TRACE_POINTS - 1) as f32;
        let t = ((volume_ml - lo) / (hi - lo)).clamp(0.0, 1.0);
        let t = if t.is_finite() { t } else { 0.5 };
        (x + u * w, y + (1.0 - t) * h)
    }
}

/// Horizontal disparity (pixels, one eye's shift) that puts a screen-space HUD at `depth_mm` in a
/// parallel stereo pair: half of `f·IPD/depth` with the focal length in pixels from the vertical
/// field of view. The left eye's HUD moves right by it, the right eye's left.
pub fn half_disparity_px(eye_height_px: u32, fov_y_deg: f32, ipd_mm: f32, depth_mm: f32) -> f32 {
    let f = eye_height_px as f32 * 0.5 / (fov_y_deg.to_radians() * 0.5).tan();
    let d = 0.5 * f * ipd_mm / depth_mm;
    if d.is_finite() {
        d
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The PV box: the signal's trace in a scene following the signal; at a remote site the lungs'
    /// trace while the source's patient drives them and the PV loop otherwise; the loop elsewhere,
    /// whatever the frame says. The shipped site scene is a site.
    #[test]
    fn a_site_shows_the_lungs_trace_while_the_sources_patient_drives_them() {
        use ipc_types::engine_state as e;
        use lung_model::scene::SceneExt;
        let scene = |text: &str| lung_model::scene::Scene::parse(text, "s.toml").unwrap();
        let site = scene(include_str!("../../../scenes/remote_site.toml"));
        let site = crate::hud::HudConfig::of(&site, &[]);
        assert!(site.remote_site && !site.signal);
        assert_eq!(pv_box_shows(&site, 0), PvBox::Loop);
        assert_eq!(pv_box_shows(&site, e::SIGNAL_FOLLOWING), PvBox::SitePatient);
        assert_eq!(pv_box_shows(&site, e::SIGNAL_PAUSED), PvBox::SitePatient);
        assert_eq!(pv_box_shows(&site, e::SIGNAL_LOST), PvBox::Loop);
        let plain = crate::hud::HudConfig::of(&lung_model::scene::Scene::default(), &[]);
        assert!(!plain.remote_site);
        assert_eq!(pv_box_shows(&plain, e::SIGNAL_FOLLOWING), PvBox::Loop);
        let signal = scene("[breathing]\nsource = \"signal\"\nsignal = \"trace:t.csv\"\n");
        let signal = crate::hud::HudConfig::of(&signal, &[]);
        assert_eq!(pv_box_shows(&signal, 0), PvBox::Signal);
        // Each box has its own titles, the shortest a word.
        for b in [PvBox::Loop, PvBox::Signal, PvBox::SitePatient] {
            assert!(b.titles().len() >= 3 && b.titles().last().unwrap().len() <= 5);
        }
        assert!(PvBox::SitePatient.titles()[0].contains("source's patient"));
    }
    use ipc_types::{lung_flags, LungFrame, ToolPose};

    fn reply(status: u32, outcome: u32, tick: u64, lung: u32, text: &str) -> ControlReply {
        let mut r = ControlReply {
            status,
            outcome,
            tick,
            lung,
            ..Default::default()
        };
        r.set_text(&[text]);
        r
    }

    #[test]
    fn the_lobe_legend_names_the_lobes_of_lungs_with_codes_and_warns_of_the_others() {
        let both = [Some(true), Some(true)];
        let names: Vec<&str> = lobe_legend(both).iter().map(|e| e.1).collect();
        assert_eq!(names, ["RUL", "RML", "RLL", "LUL", "LLL"]);
        for (lobe, abbreviation) in lobe_legend(both) {
            let parsed: Lobe = abbreviation.parse().unwrap();
            assert_eq!(parsed, lobe);
        }
        assert_eq!(lungs_without_lobes(both), None);
        assert_eq!(lobe_warning(both), None);
        // Only the right lung loaded, with codes.
        assert_eq!(lobe_legend([Some(true), None]).len(), 3);
        assert_eq!(lobe_warning([Some(true), None]), None);
        // The left lung's kernel has none.
        let left_old = [Some(true), Some(false)];
        assert_eq!(lobe_legend(left_old).len(), 3);
        assert_eq!(lungs_without_lobes(left_old), Some("left lung"));
        let w = lobe_warning(left_old).unwrap();
        assert!(w.contains("left lung") && w.contains("grey"), "{w}");
        assert_eq!(
            lungs_without_lobes([Some(false), Some(false)]),
            Some("both lungs")
        );
        assert!(lobe_legend([Some(false), Some(false)]).is_empty());
        assert_eq!(lungs_without_lobes([Some(false), None]), Some("right lung"));
        // Short enough for a 480 px eye at the HUD's smallest font (11 px, 0.6 em a character).
        for lungs in [[Some(false), Some(false)], [Some(false), Some(true)]] {
            let w = lobe_warning(lungs).unwrap();
            assert!(w.chars().count() as f32 * 11.0 * 0.6 < 440.0, "{w}");
        }
    }

    #[test]
    fn clock_is_minutes_and_seconds_of_engine_time() {
        let c = |tick, tick_hz| Clock { tick, tick_hz }.to_string();
        assert_eq!(c(0, 60.0), "00:00");
        assert_eq!(c(3720, 60.0), "01:02");
        assert_eq!(c(3779, 60.0), "01:02", "seconds are floored, not rounded");
        assert_eq!(c(60 * 60 * 75, 60.0), "75:00");
        assert_eq!(c(100, 0.0), "--:--");
        assert_eq!(c(100, f64::NAN), "--:--");
        // The largest tick does not overflow: 2^64 / 60 s.
        assert_eq!(c(u64::MAX, 60.0), "5124095576030430:56");
    }

    #[test]
    fn outcomes_read_as_words_with_their_time() {
        let mut s = String::new();
        let k = Intervention::NeedleDecompression;
        let r = reply(
            ipc_types::REPLY_APPLIED,
            ipc_types::OUTCOME_APPLIED,
            3720,
            LUNG_LEFT as u32,
            "air venting",
        );
        assert_eq!(outcome_line(&mut s, k, &r, 60.0), Standing::Done);
        assert_eq!(s, "needle decompression, left, applied 01:02 — air venting");
        let r = reply(
            ipc_types::REPLY_APPLIED,
            ipc_types::OUTCOME_WRONG_SIDE,
            3900,
            LUNG_RIGHT as u32,
            "the pneumothorax is on the other side",
        );
        assert_eq!(
            outcome_line(&mut s, Intervention::ChestTube, &r, 60.0),
            Standing::Failed
        );
        assert_eq!(
            s,
            "chest tube, right, wrong side 01:05 — the pneumothorax is on the other side"
        );
        let r = reply(ipc_types::REPLY_RECEIVED, 0, 2400, LUNG_LEFT as u32, "");
        assert_eq!(
            outcome_line(&mut s, Intervention::OcclusiveDressing, &r, 60.0),
            Standing::Pending
        );
        assert_eq!(
            s,
            "occlusive dressing, left, received 00:40 — applied with the next breath"
        );
        let r = reply(
            ipc_types::REPLY_IGNORED,
            0,
            60,
            u32::MAX,
            "no tension pneumothorax",
        );
        assert_eq!(outcome_line(&mut s, k, &r, 60.0), Standing::Failed);
        assert_eq!(
            s,
            "needle decompression, affected side, ignored 00:01 — no tension pneumothorax"
        );
        // A status or outcome from a newer build is said, not mistaken for success.
        let r = reply(99, 0, 0, 0, "");
        assert_eq!(outcome_line(&mut s, k, &r, 60.0), Standing::Failed);
        assert!(s.contains("unknown answer"), "{s}");
        let r = reply(ipc_types::REPLY_APPLIED, 77, 0, 0, "");
        assert_eq!(outcome_line(&mut s, k, &r, 60.0), Standing::Failed);
        assert!(s.contains("unknown outcome"), "{s}");
        sent_line(&mut s, k, LUNG_LEFT as u32);
        assert_eq!(
            s,
            "needle decompression, left, sent — waiting for the engine"
        );
    }

    fn lung(volume: f32, tidal: f32, ct: u32, ti: u32, phase: f32, flags: u32) -> LungFrame {
        LungFrame {
            volume_ml: volume,
            tidal_ml: tidal,
            cycle_ticks: ct,
            inhale_ticks: ti,
            phase,
            flags: lung_flags::ACTIVE | flags,
            pressure_cmh2o: 5.0,
            ..Default::default()
        }
    }

    #[test]
    fn volume_rate_and_phase_follow_the_breathing_lung() {
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.25, lung_flags::INHALING);
        f.lungs[LUNG_LEFT] = lung(1250.0, 230.0, 300, 150, 0.25, lung_flags::INHALING);
        let mut s = String::new();
        volume_line(&mut s, &f, 60.0);
        assert_eq!(s, "V 2650 ml  TV 500 ml  12 /min");
        assert_eq!(breath_phase(&f), Some((0.25, true, 0.5)));
        // A held right lung (tension): the left one's 40 /min is the rate shown.
        f.lungs[LUNG_RIGHT] = lung(900.0, 0.0, 300, 150, 0.0, lung_flags::HELD);
        f.lungs[LUNG_LEFT] = lung(1300.0, 420.0, 90, 30, 0.6, 0);
        assert_eq!(breathing_lung(&f), Some(LUNG_LEFT));
        volume_line(&mut s, &f, 60.0);
        assert_eq!(s, "V 2200 ml  TV 420 ml  40 /min");
        assert_eq!(breath_phase(&f), Some((0.6, false, 1.0 / 3.0)));
        // Both held: no phase, the rate of the first.
        f.lungs[LUNG_LEFT].flags |= lung_flags::HELD;
        assert_eq!(breath_phase(&f), None);
        // No lung at all.
        let empty = EngineFrame::default();
        volume_line(&mut s, &empty, 60.0);
        assert_eq!(s, "V    0 ml  TV   0 ml  -- /min");
        assert_eq!(breath_phase(&empty), None);
        assert_eq!(rate_per_min(0, 60.0), None);
    }

    /// While the patient's signal drives the lungs, the line gives the patient's typical breath as
    /// followed (20 /min, 450 ml), not the model's (12 /min, 500 ml); while it calibrates, or
    /// before the follower knows a breath, the model's.
    #[test]
    fn the_patients_rate_and_tidal_volume_are_shown_while_following() {
        use ipc_types::engine_state as e;
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.25, lung_flags::INHALING);
        f.lungs[LUNG_LEFT] = lung(1250.0, 230.0, 300, 150, 0.25, lung_flags::INHALING);
        f.signal.tidal_ml = 450.0;
        f.signal.period_s = 3.0;
        let mut s = String::new();
        f.state = e::SIGNAL_FOLLOWING;
        volume_line(&mut s, &f, 60.0);
        assert_eq!(s, "V 2650 ml  TV 450 ml  20 /min");
        // The phase bar: the patient's breath, 70 % through, inspiration 40 % of it (the model's
        // is 25 % through a breath half inspiration).
        f.signal.phase = 0.7;
        f.signal.inhale_fraction = 0.4;
        assert_eq!(breath_phase(&f), Some((0.7, true, 0.4)));
        f.state = e::SIGNAL_CALIBRATING;
        assert_eq!(breath_phase(&f), Some((0.25, true, 0.5)));
        volume_line(&mut s, &f, 60.0);
        assert_eq!(s, "V 2650 ml  TV 500 ml  12 /min");
        f.state = e::SIGNAL_FOLLOWING;
        f.signal = ipc_types::SignalFollowed::default();
        volume_line(&mut s, &f, 60.0);
        assert_eq!(s, "V 2650 ml  TV 500 ml  12 /min");
        assert_eq!(rate_per_min(300, 0.0), None);
    }

    #[test]
    fn disease_state_in_words() {
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.0, 0);
        f.lungs[LUNG_LEFT] = lung(600.0, 0.0, 300, 150, 0.0, lung_flags::HELD);
        f.lungs[LUNG_LEFT].collapse = 0.62;
        let mut s = String::new();
        disease_line(&mut s, None, &f);
        assert_eq!(s, "healthy lungs");
        disease_line(&mut s, Some(("tension pneumothorax", Some(LUNG_LEFT))), &f);
        assert_eq!(
            s,
            "tension pneumothorax, left: lung 62 % collapsed, not breathing"
        );
        f.lungs[LUNG_RIGHT].collapse = 0.1;
        disease_line(&mut s, Some(("bilateral pneumothorax", None)), &f);
        assert_eq!(
            s,
            "bilateral pneumothorax: right lung 10 % collapsed; left lung 62 % collapsed, not breathing"
        );
        // Before onset nothing is collapsed: the kind alone.
        let healthy = {
            let mut g = f;
            g.lungs[LUNG_LEFT] = lung(1250.0, 230.0, 300, 150, 0.0, 0);
            g.lungs[LUNG_RIGHT].collapse = 0.0;
            g
        };
        disease_line(
            &mut s,
            Some(("tension pneumothorax", Some(LUNG_LEFT))),
            &healthy,
        );
        assert_eq!(s, "tension pneumothorax, left");
    }

    /// A lung drawn past its kernel's fold-free volume is named after the lungs' state; the rest
    /// of the line is unchanged, and an inactive slot is never named.
    #[test]
    fn a_lung_past_its_fold_free_volume_is_named() {
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.0, lung_flags::PAST_FOLD_FREE);
        f.lungs[LUNG_LEFT] = lung(1250.0, 230.0, 300, 150, 0.0, 0);
        let mut s = String::new();
        assert!(past_fold_free(&f));
        disease_line(&mut s, None, &f);
        assert_eq!(s, "healthy lungs · RIGHT LUNG PAST ITS FOLD-FREE VOLUME");
        f.lungs[LUNG_LEFT].flags |= lung_flags::PAST_FOLD_FREE;
        f.lungs[LUNG_LEFT].collapse = 0.2;
        disease_line(&mut s, Some(("closed pneumothorax", Some(LUNG_LEFT))), &f);
        assert_eq!(
            s,
            "closed pneumothorax, left: lung 20 % collapsed · RIGHT LUNG PAST ITS FOLD-FREE VOLUME · \
             LEFT LUNG PAST ITS FOLD-FREE VOLUME"
        );
        f.lungs[LUNG_RIGHT].flags = 0;
        f.lungs[LUNG_LEFT] = LungFrame {
            flags: lung_flags::PAST_FOLD_FREE,
            ..LungFrame::default()
        };
        assert!(!past_fold_free(&f));
        disease_line(&mut s, None, &f);
        assert_eq!(s, "healthy lungs");
    }

    #[test]
    fn tracker_health_names_each_tool() {
        let mut s = String::new();
        assert!(!tracker_line(&mut s, None));
        assert_eq!(s, "tracker: no samples");
        let mut t = TrackerFrame {
            tool_count: 2,
            ..Default::default()
        };
        t.tools[0] = ToolPose {
            status: tool_status::VALID,
            ..Default::default()
        };
        t.tools[1] = ToolPose {
            status: tool_status::MISSING,
            ..Default::default()
        };
        assert!(!tracker_line(&mut s, Some(&t)));
        assert_eq!(s, "tracker: patient ok · HMD not seen");
        t.tools[1].status = tool_status::VALID | tool_status::PARTIALLY_VISIBLE;
        assert!(!tracker_line(&mut s, Some(&t)));
        assert_eq!(s, "tracker: patient ok · HMD partly seen");
        t.tools[1].status = tool_status::VALID | tool_status::FRAME_GAP;
        assert!(tracker_line(&mut s, Some(&t)));
        // A count beyond the array is read as the array.
        t.tool_count = 99;
        tracker_line(&mut s, Some(&t));
        assert_eq!(s.matches(" · ").count(), ipc_types::MAX_TOOLS - 1, "{s}");
        assert_eq!(tool_words(tool_status::STALE), "stale");
        assert_eq!(tool_words(0), "invalid");
        assert_eq!(
            tool_words(tool_status::VALID | tool_status::DEVICE_FAULT),
            "fault"
        );
    }

    #[test]
    fn timing_line_says_frame_time_and_latency() {
        let mut s = String::new();
        use crate::lod::Shown;
        let auto = Shown {
            level: 1,
            coarsest: 3,
            triangles: 10_000,
            auto: true,
        };
        timing_line(
            &mut s,
            3_140_000,
            Some(1_200_000),
            &auto,
            None,
            Some(11_850_000),
        );
        assert_eq!(s, "frame 3.1 ms (GPU 1.2 ms) · LOD 1/3 · latency 11.8 ms");
        timing_line(&mut s, 0, None, &Shown::default(), None, None);
        assert_eq!(s, "frame 0.0 ms · LOD off · latency --");
        let fixed = Shown {
            level: 2,
            coarsest: 2,
            auto: false,
            ..auto
        };
        timing_line(&mut s, 0, None, &fixed, None, None);
        assert_eq!(s, "frame 0.0 ms · LOD 2 fixed · latency --");
        // Auto on a mesh too small for levels: every triangle.
        let small = Shown {
            level: 0,
            coarsest: 0,
            ..auto
        };
        timing_line(&mut s, 0, None, &small, None, None);
        assert_eq!(s, "frame 0.0 ms · LOD off · latency --");
        // The governor: nothing given up says nothing; what it gave up and its floor are said.
        timing_line(&mut s, 0, None, &auto, Some(0), None);
        assert_eq!(s, "frame 0.0 ms · LOD 1/3 · latency --");
        let lowered = ipc_types::report_flags::quality_bits(true, 2, false);
        timing_line(&mut s, 0, None, &auto, Some(lowered), None);
        assert_eq!(s, "frame 0.0 ms · LOD 1/3 · less: AA LOD+2 · latency --");
        let floor = lowered | ipc_types::report_flags::GOVERNOR_FLOOR;
        timing_line(&mut s, 0, None, &auto, Some(floor), None);
        assert_eq!(s, "frame 0.0 ms · LOD 1/3 · LATE: AA LOD+2 · latency --");
        let all = ipc_types::report_flags::quality_bits(true, 1, true)
            | ipc_types::report_flags::QUALITY_DRAWN_ONLY;
        timing_line(&mut s, 0, None, &auto, Some(all), None);
        assert_eq!(
            s,
            "frame 0.0 ms · LOD 1/3 · less: AA LOD+1 VTX OIT · latency --"
        );
        let capped = all | ipc_types::report_flags::sh_cap_bits(2);
        timing_line(&mut s, 0, None, &auto, Some(capped), None);
        assert_eq!(
            s,
            "frame 0.0 ms · LOD 1/3 · less: AA LOD+1 VTX OIT SH2 · latency --"
        );
        // At the floor with nothing to give up (a scene with no steps).
        let none = ipc_types::report_flags::GOVERNOR_FLOOR;
        timing_line(&mut s, 0, None, &auto, Some(none), None);
        assert_eq!(
            s,
            "frame 0.0 ms · LOD 1/3 · LATE: nothing to give up · latency --"
        );
    }

    #[test]
    fn pv_scale_fits_the_loop_and_centres_a_single_point() {
        let loop_pts = [(0.0, 2400.0), (10.0, 2900.0), (5.0, 2700.0)];
        let s = PvScale::fit(loop_pts.into_iter()).unwrap();
        let r = (100.0, 50.0, 200.0, 100.0);
        // The corners of the loop lie inside the box, the margin on every side.
        let (x0, y0) = s.to_px((0.0, 2400.0), r);
        let (x1, y1) = s.to_px((10.0, 2900.0), r);
        assert!(
            x0 > 100.0 && x0 < 120.0 && y0 < 150.0 && y0 > 140.0,
            "{x0} {y0}"
        );
        assert!(
            x1 < 300.0 && x1 > 280.0 && y1 > 50.0 && y1 < 60.0,
            "{x1} {y1}"
        );
        // Volume goes up the screen, pressure to the right.
        assert!(y1 < y0 && x1 > x0);
        // Out-of-range points are clamped to the box.
        assert_eq!(s.to_px((-1e9, 1e9), r), (100.0, 50.0));
        // A held lung: one point, in the middle.
        let one = PvScale::fit([(3.0, 2000.0)].into_iter()).unwrap();
        assert_eq!(one.to_px((3.0, 2000.0), r), (200.0, 100.0));
        // Nothing (or nothing finite) to fit.
        assert!(PvScale::fit(std::iter::empty()).is_none());
        assert!(PvScale::fit([(f32::NAN, 1.0), (1.0, f32::INFINITY)].into_iter()).is_none());
        // A NaN point never leaves the box.
        let (x, y) = s.to_px((f32::NAN, f32::NAN), r);
        assert!((100.0..=300.0).contains(&x) && (50.0..=150.0).contains(&y));
    }

    #[test]
    fn pv_trace_follows_phase_and_restarts_on_a_new_rate() {
        let mut t = PvTrace::default();
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.0, lung_flags::INHALING);
        for k in 0..300 {
            f.lungs[LUNG_RIGHT].phase = k as f32 / 300.0;
            f.lungs[LUNG_RIGHT].pressure_cmh2o = k as f32 / 30.0;
            t.record(&f);
        }
        assert_eq!(t.points().count(), PV_BINS);
        assert_eq!(t.current, Some((299.0 / 30.0, 1400.0)));
        // The points come in phase order: pressure rising here.
        let p: Vec<f32> = t.points().map(|p| p.0).collect();
        assert!(p.windows(2).all(|w| w[0] < w[1]));
        // A non-finite pressure is left out.
        f.lungs[LUNG_RIGHT].pressure_cmh2o = f32::NAN;
        t.record(&f);
        assert_eq!(t.current, Some((299.0 / 30.0, 1400.0)));
        // A new cycle length starts a new loop.
        f.lungs[LUNG_RIGHT].cycle_ticks = 90;
        f.lungs[LUNG_RIGHT].pressure_cmh2o = 1.0;
        f.lungs[LUNG_RIGHT].phase = 0.5;
        t.record(&f);
        assert_eq!(t.points().count(), 1);
    }

    #[test]
    fn hud_disparity_puts_it_at_a_comfortable_depth() {
        // 720 px high, 60° field, 64 mm IPD, 1.75 m: f = 623.5 px, f·IPD/Z = 22.8 px in all.
        let d = half_disparity_px(720, 60.0, 64.0, 1750.0);
        assert!((d - 11.40).abs() < 0.01, "{d}");
        assert_eq!(half_disparity_px(720, 60.0, 64.0, 0.0), 0.0);
        assert_eq!(half_disparity_px(720, 60.0, 0.0, 1750.0), 0.0);
    }

    #[test]
    fn the_phase_line_says_what_drives_the_breath() {
        use ipc_types::engine_state as e;
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1400.0, 270.0, 300, 150, 0.25, lung_flags::INHALING);
        let mut s = String::new();
        phase_line(&mut s, &f);
        assert_eq!(s, "inspiration", "a model scene says no more");
        f.signal.latency_ns = 9_400_000;
        for (state, want) in [
            (
                e::SIGNAL_FOLLOWING,
                "inspiration · following patient, predicted 9 ms ahead",
            ),
            (
                e::SIGNAL_FOLLOWING | e::SIGNAL_PAUSED,
                "pause · following patient, predicted 9 ms ahead",
            ),
            (
                e::SIGNAL_FOLLOWING | e::SIGNAL_CLIPPED,
                "inspiration · following patient, predicted 9 ms ahead · SIGNAL LOOKS CLIPPED: \
                 breaths may be deeper than drawn",
            ),
            (
                e::SIGNAL_CALIBRATING,
                "inspiration · model (calibrating signal)",
            ),
            (e::SIGNAL_LOST, "inspiration · model (signal lost)"),
            (
                e::SIGNAL_CALIBRATING | e::SIGNAL_LEARNING,
                "inspiration · model (learning the chest's axis)",
            ),
        ] {
            f.state = state;
            phase_line(&mut s, &f);
            assert_eq!(s, want);
        }
        // Nothing said of a latency the frame does not carry.
        f.state = e::SIGNAL_FOLLOWING;
        f.signal.latency_ns = 0;
        phase_line(&mut s, &f);
        assert_eq!(s, "inspiration · following patient");
        assert_eq!(
            crate::PoseWarning::of_engine_state(e::SIGNAL_CALIBRATING | e::SIGNAL_LEARNING),
            crate::PoseWarning::None,
            "learning a chest's axis is no loss: no veil"
        );
        assert_eq!(
            crate::PoseWarning::of_engine_state(e::SIGNAL_LOST),
            crate::PoseWarning::SignalLost
        );
        assert_eq!(
            crate::PoseWarning::of_engine_state(e::SIGNAL_LOST | e::PATIENT_POSE_STALE),
            crate::PoseWarning::Stale,
            "a stale pose is the graver warning"
        );
    }

    #[test]
    fn veil_words_name_the_pose_state() {
        assert_eq!(veil_words(crate::PoseWarning::None), None);
        assert!(veil_words(crate::PoseWarning::Held)
            .unwrap()
            .contains("HELD"));
        assert!(veil_words(crate::PoseWarning::Stale)
            .unwrap()
            .contains("STALE"));
        assert!(veil_words(crate::PoseWarning::SignalLost)
            .unwrap()
            .contains("SIGNAL LOST"));
        assert!(key_help(true).contains("N needle"));
        assert!(!key_help(false).contains("N needle"));
    }

    /// The trace keeps one point per twelfth of a second of engine time (a repeated frame adds
    /// nothing), the measured line only while the signal drives the lungs, on the drawn volume's
    /// scale; a stall leaves gaps, a run that starts again a fresh trace; the ring holds the last
    /// ten seconds, oldest first, and a NaN never reaches a point.
    #[test]
    fn the_signal_trace_keeps_ten_seconds_of_the_drawn_and_measured_breath() {
        use ipc_types::engine_state as e;
        let mut t = SignalTrace::default();
        assert_eq!(t.range(), None);
        let mut f = EngineFrame::default();
        f.lungs[LUNG_RIGHT] = lung(1300.0, 270.0, 300, 150, 0.0, lung_flags::INHALING);
        f.lungs[LUNG_LEFT] = lung(1100.0, 230.0, 300, 150, 0.0, lung_flags::INHALING);
        // Calibrating: the model breathes, no measured point.
        f.state = e::SIGNAL_CALIBRATING;
        f.signal.display_ns = 5;
        for tick in 0..10 {
            f.tick = tick;
            t.record(&f, 60.0);
        }
        let pts: Vec<_> = t.points().collect();
        assert_eq!(
            pts.len(),
            2,
            "ticks 0..10 at 60 Hz are two twelfths of a second"
        );
        assert_eq!(pts[1].0, TRACE_POINTS - 1, "the newest on the right");
        assert_eq!(pts[1].1.drawn_ml, Some(2400.0));
        assert_eq!(pts[1].1.measured_ml, None);
        assert_eq!(t.point(TRACE_POINTS - 1), Some(pts[1].1));
        assert_eq!(t.point(TRACE_POINTS - 3), None);
        assert_eq!(t.point(TRACE_POINTS), None);
        // Following: drawn at FRC + the predicted 300 ml; the newest sample said 280 ml.
        f.state = e::SIGNAL_FOLLOWING;
        f.signal.volume_ml = 300.0;
        f.signal.unpredicted_ml = 280.0;
        f.tick = 10;
        t.record(&f, 60.0);
        let newest = t.points().last().unwrap().1;
        assert_eq!(newest.measured_ml, Some(2380.0));
        // A held or collapsed lung, or one lung alone: the lungs still take the whole signal (the
        // other lung takes a held or collapsing one's part), so the measured point stays; every
        // lung held (an arrest) takes none of it: no measured point.
        let edits: [(fn(&mut EngineFrame), bool); 4] = [
            (|f| f.lungs[LUNG_LEFT].flags |= lung_flags::HELD, true),
            (|f| f.lungs[LUNG_RIGHT].collapse = 0.2, true),
            (|f| f.lungs[LUNG_LEFT] = LungFrame::default(), true),
            (
                |f| {
                    for l in &mut f.lungs {
                        l.flags |= lung_flags::HELD;
                    }
                },
                false,
            ),
        ];
        for (k, (edit, measured)) in edits.into_iter().enumerate() {
            let mut g = f;
            edit(&mut g);
            let mut u = SignalTrace::default();
            u.record(&g, 60.0);
            let p = u.points().last().unwrap().1;
            let drawn = p.drawn_ml.expect("a drawn point");
            let want = measured.then_some(drawn - g.signal.volume_ml + g.signal.unpredicted_ml);
            assert_eq!(p.measured_ml, want, "case {k}");
        }
        // A repeated frame adds nothing; a stall of 65 ticks (slots 3..=14) leaves twelve gaps.
        t.record(&f, 60.0);
        assert_eq!(t.points().count(), 3);
        f.tick = 75;
        t.record(&f, 60.0);
        let pts: Vec<_> = t.points().collect();
        assert_eq!(pts.len(), 3 + 12 + 1);
        assert_eq!(pts.iter().filter(|(_, p)| p.drawn_ml.is_none()).count(), 12);
        // The range holds both lines with a margin.
        let (lo, hi) = t.range().unwrap();
        assert!(lo < 2380.0 && hi > 2400.0 && hi - lo >= 50.0);
        // A NaN volume is no point; a lost signal no measured point.
        f.lungs[LUNG_LEFT].volume_ml = f32::NAN;
        f.tick = 80;
        t.record(&f, 60.0);
        assert_eq!(t.points().last().unwrap().1, TracePoint::default());
        f.lungs[LUNG_LEFT].volume_ml = 1100.0;
        f.state = e::SIGNAL_LOST;
        f.tick = 85;
        t.record(&f, 60.0);
        assert_eq!(t.points().last().unwrap().1.measured_ml, None);
        // Long runs keep the last ten seconds, oldest first.
        for tick in 90..2000u64 {
            f.tick = tick;
            f.lungs[LUNG_RIGHT].volume_ml = tick as f32;
            t.record(&f, 60.0);
        }
        let pts: Vec<_> = t.points().collect();
        assert_eq!(pts.len(), TRACE_POINTS);
        assert!(pts.windows(2).all(|w| w[0].0 + 1 == w[1].0));
        let drawn: Vec<f32> = pts.iter().filter_map(|(_, p)| p.drawn_ml).collect();
        assert!(drawn.windows(2).all(|w| w[0] < w[1]), "oldest first");
        assert_eq!(*drawn.last().unwrap(), 1995.0 + 1100.0);
        // A run that starts again (its tick went back) starts a fresh trace, even within a slot.
        f.tick = 3;
        t.record(&f, 60.0);
        assert_eq!(t.points().count(), 1);
        f.tick = 4;
        t.record(&f, 60.0);
        f.tick = 2;
        f.lungs[LUNG_RIGHT].volume_ml = 777.0;
        t.record(&f, 60.0);
        assert_eq!(t.points().count(), 1);
        assert_eq!(t.points().last().unwrap().1.drawn_ml, Some(777.0 + 1100.0));
        // A box maps the oldest slot to its left edge and the newest to its right.
        let b = (10.0, 20.0, 119.0, 50.0);
        assert_eq!(SignalTrace::to_px(0, 0.0, (0.0, 10.0), b), (10.0, 70.0));
        assert_eq!(
            SignalTrace::to_px(TRACE_POINTS - 1, 10.0, (0.0, 10.0), b),
            (129.0, 20.0)
        );
    }
}
