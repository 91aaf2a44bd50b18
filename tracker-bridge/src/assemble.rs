//! From samples to tracker frames: each sample is mapped to its tool slot by name, validated
//! ([`crate::validate`]), checked against the tool's history (device frame-number gaps and
//! repeats), and kept as the tool's latest state; once per tick the slots become one
//! [`TrackerFrame`], with tools that have had no new sample for longer than the staleness bound
//! flagged `STALE` and not valid.
//!
//! A pure state machine: its only inputs are the samples and the tick times it is given, so a
//! recorded session (samples with their receive times, ticks with theirs) assembles into the same
//! frames every time. No allocation after construction.
//!
//! What a slot publishes: the newest sample's pose when it passed every check (`VALID`), else the
//! tool's last good pose (identity before any) with the reasons as bits and `VALID` clear, so a
//! rejected sample's numbers never cross the process boundary.

use ipc_types::{tool_status, Pose, ToolPose, TrackerFrame, LAYOUT_VERSION, MAX_TOOLS};
use serde::{Deserialize, Serialize};

use crate::sample::{Reject, Sample, ToolName};
use crate::stats::Stats;
use crate::validate::{Validation, Volume};

/// How samples become frames: which name goes to which slot, the validation limits, the staleness
/// bound and the rate. Recorded in every recording's header, so a replay assembles the same frames.
#[derive(Debug, Clone, PartialEq)]
pub struct BridgeConfig {
    /// Tick rate, Hz.
    pub rate_hz: f64,
    /// The source name of each slot (slot 0 patient reference, slot 1 HMD); `None`: unused.
    pub slots: [Option<ToolName>; MAX_TOOLS],
    /// Per-sample limits.
    pub validation: Validation,
    /// A tool with no new sample for longer than this is stale, ns.
    pub stale_ns: u64,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        let mut slots = [None; MAX_TOOLS];
        slots[ipc_types::TOOL_PATIENT] = ToolName::new("Patient").ok();
        slots[ipc_types::TOOL_HMD] = ToolName::new("HMD").ok();
        BridgeConfig {
            rate_hz: 60.0,
            slots,
            validation: Validation::default(),
            stale_ns: 50_000_000,
        }
    }
}

/// The serialised form of [`BridgeConfig`] (TOML in recording headers).
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ConfigText {
    rate_hz: f64,
    slots: Vec<String>,
    quat_tolerance: f32,
    matrix_tolerance: f32,
    max_rms_mm: f32,
    volume: String,
    stale_ms: f64,
}

/// A configuration text that cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("bridge configuration: {0}")]
pub struct ConfigError(pub String);

impl BridgeConfig {
    /// The period of the tick, ns.
    pub fn period_ns(&self) -> u64 {
        (1e9 / self.rate_hz).round() as u64
    }

    /// Check every value (what the command line and a recording header both go through).
    pub fn check(&self) -> Result<(), ConfigError> {
        let v = &self.validation;
        if !(self.rate_hz.is_finite() && (1.0..=1000.0).contains(&self.rate_hz)) {
            return Err(ConfigError(format!(
                "rate {} Hz must be within 1..1000",
                self.rate_hz
            )));
        }
        if !(v.quat_tolerance.is_finite() && (0.0..=0.5).contains(&v.quat_tolerance)) {
            return Err(ConfigError(format!(
                "quaternion tolerance {} must be within 0..0.5",
                v.quat_tolerance
            )));
        }
        if !(v.matrix_tolerance.is_finite() && (0.0..=0.5).contains(&v.matrix_tolerance)) {
            return Err(ConfigError(format!(
                "matrix tolerance {} must be within 0..0.5",
                v.matrix_tolerance
            )));
        }
        if !(v.max_rms_mm.is_finite() && v.max_rms_mm > 0.0 && v.max_rms_mm <= 100.0) {
            return Err(ConfigError(format!(
                "RMS threshold {} mm must be within 0..100 mm",
                v.max_rms_mm
            )));
        }
        if !(1_000_000..=10_000_000_000).contains(&self.stale_ns) {
            return Err(ConfigError(format!(
                "staleness bound {} ms must be within 1..10000 ms",
                self.stale_ns as f64 / 1e6
            )));
        }
        for (i, a) in self.slots.iter().enumerate() {
            for b in self.slots.iter().skip(i + 1) {
                if let (Some(a), Some(b)) = (a, b) {
                    if a.matches(b) {
                        return Err(ConfigError(format!(
                            "tool name {a} is given to two slots (patient and HMD must be different tools)"
                        )));
                    }
                }
            }
        }
        Ok(())
    }

    /// As TOML text.
    pub fn to_toml(&self) -> String {
        let c = ConfigText {
            rate_hz: self.rate_hz,
            slots: self
                .slots
                .iter()
                .map(|s| s.map(|n| n.as_str().to_string()).unwrap_or_default())
                .collect(),
            quat_tolerance: self.validation.quat_tolerance,
            matrix_tolerance: self.validation.matrix_tolerance,
            max_rms_mm: self.validation.max_rms_mm,
            volume: self.validation.volume.to_text(),
            stale_ms: self.stale_ns as f64 / 1e6,
        };
        toml::to_string(&c).unwrap_or_default()
    }

    /// From TOML text ([`BridgeConfig::to_toml`]), checked.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let c: ConfigText = toml::from_str(text).map_err(|e| ConfigError(e.to_string()))?;
        if c.slots.len() > MAX_TOOLS {
            return Err(ConfigError(format!(
                "{} slots, at most {MAX_TOOLS}",
                c.slots.len()
            )));
        }
        let mut slots = [None; MAX_TOOLS];
        for (dst, name) in slots.iter_mut().zip(&c.slots) {
            if !name.is_empty() {
                *dst = Some(ToolName::new(name).map_err(|e| ConfigError(e.to_string()))?);
            }
        }
        if !(c.stale_ms.is_finite() && c.stale_ms >= 0.0 && c.stale_ms <= 1e7) {
            return Err(ConfigError(format!(
                "stale_ms {} is out of range",
                c.stale_ms
            )));
        }
        let config = BridgeConfig {
            rate_hz: c.rate_hz,
            slots,
            validation: Validation {
                quat_tolerance: c.quat_tolerance,
                matrix_tolerance: c.matrix_tolerance,
                max_rms_mm: c.max_rms_mm,
                volume: Volume::parse(&c.volume).map_err(ConfigError)?,
            },
            stale_ns: (c.stale_ms * 1e6).round() as u64,
        };
        config.check()?;
        Ok(config)
    }

    /// The slot `name` is mapped to.
    pub fn slot_of(&self, name: &ToolName) -> Option<usize> {
        self.slots
            .iter()
            .position(|s| s.is_some_and(|s| s.matches(name)))
    }

    /// Slots published per frame: up to the last configured one.
    pub fn tool_count(&self) -> usize {
        self.slots
            .iter()
            .rposition(|s| s.is_some())
            .map_or(0, |i| i + 1)
    }
}

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    /// Last good pose, its RMS and tool id.
    good: Option<(Pose, f32, u32)>,
    /// Any sample seen.
    seen: bool,
    /// Receive time of the newest sample that was not a repeat.
    last_new_ns: u64,
    /// Flags of that sample (validation and device).
    newest_flags: u32,
    /// That sample was usable.
    newest_ok: bool,
    /// Its device frame number / timestamp, for gaps and repeats.
    last_frame: Option<u64>,
    last_device_time: u64,
    /// FRAME_GAP / FRAME_REPEAT since the last frame.
    pending: u32,
    tool_id: u32,
    /// A new sample (not a repeat) came since the last frame.
    fresh: bool,
}

/// What became of one sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// It is its tool's pose now.
    Accepted,
    /// It repeats a frame already seen (counted, flagged, nothing else changes).
    Repeat,
    /// It was rejected for this reason (the tool keeps its last good pose).
    Rejected(Reject),
}

/// The shared state machine of every source: samples in, one frame per tick out.
#[derive(Debug)]
pub struct Assembler {
    config: BridgeConfig,
    slots: [Slot; MAX_TOOLS],
    frame_number: u64,
    /// The run's counters.
    pub stats: Stats,
    /// The respiratory signal, when there is one (`--breathing`).
    signal: Option<crate::signal::SignalSource>,
}

impl Assembler {
    /// An assembler with no history.
    pub fn new(config: BridgeConfig) -> Self {
        Assembler {
            config,
            slots: [Slot::default(); MAX_TOOLS],
            frame_number: 0,
            stats: Stats::new(),
            signal: None,
        }
    }

    /// Send this respiratory signal in every frame's signal block from now on.
    pub fn set_signal(&mut self, signal: impl Into<crate::signal::SignalSource>) {
        let signal = signal.into();
        self.stats.signal = Some(signal.counts());
        self.signal = Some(signal);
    }

    /// The respiratory signal, when there is one.
    pub fn signal(&self) -> Option<&crate::signal::SignalSource> {
        self.signal.as_ref()
    }

    /// The signal's samples due by `now_ns` (the run's clock) into `out` (an empty block without a
    /// signal).
    /// `tools` are the tools of the frame just built ([`Self::frame`]): a chest tool's signal reads
    /// them.
    pub fn fill_signal(
        &mut self,
        now_ns: u64,
        tools: &[ToolPose; MAX_TOOLS],
        out: &mut ipc_types::SignalBlock,
    ) {
        let usable = |t: &ToolPose| {
            (t.is_valid() && t.status & tool_status::STALE == 0 && t.pose.is_finite())
                .then_some(t.pose)
        };
        let chest = &tools[ipc_types::TOOL_CHEST];
        let slot = &self.slots[ipc_types::TOOL_CHEST];
        let view = crate::signal_tool::ToolView {
            chest_arrival_ns: if slot.seen {
                slot.last_new_ns.max(1)
            } else {
                0
            },
            chest: usable(chest),
            patient: usable(&tools[ipc_types::TOOL_PATIENT]),
            chest_silent: !slot.seen || chest.status & tool_status::STALE != 0,
        };
        match &mut self.signal {
            Some(s) => {
                s.fill(now_ns, &view, out);
                self.stats.signal = Some(s.counts());
                if let crate::signal::SignalSource::Tool(t) = s {
                    self.stats.chest_axis = t.learnt();
                }
            }
            None => *out = Default::default(),
        }
    }

    /// A reading (OpenIGTLink `SENSOR` or `STRING`) for an OpenIGTLink amplitude signal: true when
    /// it is the signal's device's (queued for the next frame, or refused and counted), false when
    /// there is no such signal or it is another device's.
    pub fn take_reading(&mut self, r: &crate::sample::Reading) -> bool {
        match &mut self.signal {
            Some(crate::signal::SignalSource::Igtl(s)) => {
                let mine = s.take(r);
                self.stats.signal = Some(crate::signal::SignalSource::counts_of_igtl(s));
                mine
            }
            _ => false,
        }
    }

    /// Publish `b`, the block a replayed recording carries for this tick, into `out`, counting
    /// its samples as a live signal's are (the bridge's summary and JSON say what was played).
    pub fn replay_signal(&mut self, b: &ipc_types::SignalBlock, out: &mut ipc_types::SignalBlock) {
        *out = *b;
        let c = self.stats.signal.get_or_insert_with(Default::default);
        let n = (b.count as usize).min(ipc_types::MAX_SIGNAL_SAMPLES);
        c.sent += n as u64;
        c.invalid += (0..n).filter(|&i| b.valid_mask & (1 << i) == 0).count() as u64;
        if n == ipc_types::MAX_SIGNAL_SAMPLES {
            c.full_blocks += 1;
        }
    }

    /// The configuration.
    pub fn config(&self) -> &BridgeConfig {
        &self.config
    }

    /// Take one sample: map, validate, check its frame number against the tool's history.
    ///
    /// The per-name counters are updated from what became of the sample, after it was judged: a
    /// repeat is counted as a repeat, not as accepted, and an unmapped name is never accepted, so
    /// the tools' `accepted` add up to [`Stats::accepted`] and each tool's `last_pose` is one that
    /// was published.
    pub fn ingest(&mut self, s: &Sample) -> Outcome {
        self.stats.samples += 1;
        let slot_index = self.config.slot_of(&s.name);
        let verdict = self.config.validation.check(s);
        let outcome = match slot_index {
            Some(i) => self.judge(i, s, &verdict),
            None => {
                self.stats.reject(Reject::Unmapped, 1);
                Outcome::Rejected(Reject::Unmapped)
            }
        };
        if let Some(t) = self.stats.tool_mut(&s.name, slot_index.map(|i| i as u8)) {
            if t.samples == 0 {
                t.first_ns = s.receive_ns;
            }
            t.samples += 1;
            t.last_ns = s.receive_ns;
            t.last_flags = verdict.flags;
            t.last_rms_mm = verdict.rms_error_mm;
            match outcome {
                Outcome::Accepted => {
                    t.accepted += 1;
                    t.last_pose = verdict.pose;
                }
                Outcome::Repeat => {
                    t.repeats += 1;
                    t.last_flags |= tool_status::FRAME_REPEAT;
                }
                Outcome::Rejected(_) => {}
            }
        }
        outcome
    }

    /// What becomes of a sample mapped to slot `i` that validation judged `verdict`: a repeat of
    /// a device frame already seen, the slot's new pose, or rejected (counted here).
    fn judge(&mut self, i: usize, s: &Sample, verdict: &crate::validate::Verdict) -> Outcome {
        let slot = &mut self.slots[i];
        // Gaps and repeats: the device frame counter when there is one, else its timestamp.
        let mut repeat = false;
        if let Some(f) = s.device_frame {
            if let Some(prev) = slot.last_frame {
                if f <= prev {
                    repeat = true;
                } else if f > prev + 1 {
                    slot.pending |= tool_status::FRAME_GAP;
                    self.stats.frame_gaps += 1;
                    self.stats.frames_lost += f - prev - 1;
                }
            }
            // A counter that went backwards (device restarted) continues from where it is now.
            slot.last_frame = Some(f);
        } else if s.device_time_ns != 0 {
            repeat = slot.last_device_time != 0 && s.device_time_ns <= slot.last_device_time;
            slot.last_device_time = s.device_time_ns;
        }
        if repeat {
            slot.pending |= tool_status::FRAME_REPEAT;
            self.stats.frame_repeats += 1;
            return Outcome::Repeat;
        }
        slot.seen = true;
        slot.fresh = true;
        slot.last_new_ns = s.receive_ns;
        slot.newest_flags = verdict.flags;
        slot.newest_ok = verdict.pose.is_some();
        slot.tool_id = s.tool_id;
        if verdict.flags & tool_status::PARTIALLY_VISIBLE != 0 {
            self.stats.partially_visible += 1;
        }
        match (verdict.pose, verdict.reason) {
            (Some(p), _) => {
                slot.good = Some((p, verdict.rms_error_mm, s.tool_id));
                self.stats.accepted += 1;
                Outcome::Accepted
            }
            (None, reason) => {
                let r = reason.unwrap_or(Reject::Malformed);
                self.stats.reject(r, 1);
                Outcome::Rejected(r)
            }
        }
    }

    /// Whether the device's frame is complete at `now_ns`: every configured tool that is live (seen,
    /// its newest sample within the staleness bound) has a new sample since the last frame. A
    /// sender that sends each tool in its own message (pyigtl, PLUS, 3D Slicer) completes a frame
    /// message by message; the loop gathers them into one frame (see [`crate::run`]).
    pub fn frame_complete(&self, now_ns: u64) -> bool {
        let count = self.config.tool_count();
        self.slots
            .iter()
            .zip(self.config.slots.iter())
            .take(count)
            .all(|(slot, name)| {
                name.is_none()
                    || !slot.seen
                    || slot.fresh
                    || now_ns.saturating_sub(slot.last_new_ns) > self.config.stale_ns
            })
    }

    /// Build the frame of the tick at `at_ns` (the same clock as the samples' receive times):
    /// frame number +1, every configured slot's state, `capture_ns` = the newest sample's receive
    /// time, at most `at_ns` (the tick time before any). A tool is stale when its newest sample is
    /// more than the staleness bound away from the tick on either side. `bridge_publish_ns` is
    /// left 0 for the loop to stamp.
    pub fn frame(&mut self, at_ns: u64, out: &mut TrackerFrame) {
        self.frame_number += 1;
        self.stats.frames += 1;
        let count = self.config.tool_count();
        let mut capture = 0u64;
        out.layout_version = LAYOUT_VERSION;
        out.tool_count = count as u32;
        out.frame_number = self.frame_number;
        out.stamps = Default::default();
        out.tools = [ToolPose::default(); MAX_TOOLS];
        for (i, (slot, tool)) in self
            .slots
            .iter_mut()
            .zip(out.tools.iter_mut())
            .enumerate()
            .take(count)
        {
            if self.config.slots[i].is_none() {
                continue;
            }
            let mut status = slot.pending;
            slot.pending = 0;
            slot.fresh = false;
            if !slot.seen {
                status |= tool_status::MISSING;
                self.stats.never_seen += 1;
            } else {
                // A receive time after the tick is a reader thread's stamp taken a few µs after
                // the loop read its clock; one further ahead than the staleness bound (a damaged
                // recording, a clock that jumped) gives no age, so it goes stale like a silent
                // tool instead of looking fresh for ever. The capture stamp never leads the tick.
                capture = capture.max(slot.last_new_ns.min(at_ns));
                status |= slot.newest_flags;
                if at_ns.abs_diff(slot.last_new_ns) > self.config.stale_ns {
                    status |= tool_status::STALE;
                    self.stats.stale += 1;
                }
            }
            if slot.seen && slot.newest_ok && status & crate::validate::REJECTING == 0 {
                status |= tool_status::VALID;
            }
            let (pose, rms, id) = slot.good.unwrap_or((Pose::IDENTITY, 0.0, slot.tool_id));
            *tool = ToolPose {
                tool_id: id,
                status,
                pose,
                rms_error_mm: rms,
                _pad: 0,
            };
        }
        out.stamps.capture_ns = if capture == 0 { at_ns } else { capture };
    }

    /// The number the next frame will carry, minus one.
    pub fn frame_number(&self) -> u64 {
        self.frame_number
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::{Rotation, ToolName};
    use crate::validate::Volume;

    fn config() -> BridgeConfig {
        BridgeConfig {
            validation: Validation {
                volume: Volume::Unbounded,
                ..Validation::default()
            },
            ..BridgeConfig::default()
        }
    }

    fn s(name: &str, t: u64, frame: Option<u64>, x: f32) -> Sample {
        Sample {
            device_frame: frame,
            rms_error_mm: Some(0.2),
            tool_id: 7,
            ..Sample::quat(
                t,
                ToolName::new(name).unwrap(),
                [0.0, 0.0, 0.0, 1.0],
                [x, 0.0, -1000.0],
            )
        }
    }

    const MS: u64 = 1_000_000;

    #[test]
    fn samples_land_in_their_slots_by_name_and_unknown_names_are_counted() {
        let mut a = Assembler::new(config());
        assert_eq!(
            a.ingest(&s("hmd", 1, None, 2.0)),
            Outcome::Accepted,
            "case-insensitive"
        );
        assert_eq!(a.ingest(&s("Patient", 2, None, 1.0)), Outcome::Accepted);
        assert_eq!(
            a.ingest(&s("Pointer", 3, None, 9.0)),
            Outcome::Rejected(Reject::Unmapped)
        );
        let mut f = TrackerFrame::default();
        a.frame(5, &mut f);
        assert_eq!(f.tool_count, 2);
        assert_eq!(f.frame_number, 1);
        assert_eq!(f.tools[0].status, tool_status::VALID);
        assert_eq!(f.tools[0].pose.translation_mm[0], 1.0);
        assert_eq!(f.tools[1].pose.translation_mm[0], 2.0);
        assert_eq!(f.tools[0].tool_id, 7);
        assert_eq!(f.stamps.capture_ns, 2, "the newest sample's receive time");
        assert_eq!(a.stats.rejected_for(Reject::Unmapped), 1);
        assert_eq!(a.stats.tools.len(), 3);
    }

    #[test]
    fn a_configured_tool_keeps_its_entry_whatever_junk_names_came_first() {
        use crate::stats::NAME_TABLE;
        let mut a = Assembler::new(config());
        let capacity = a.stats.tools.capacity();
        assert!(capacity >= NAME_TABLE + MAX_TOOLS);
        for k in 0..40u64 {
            a.ingest(&s(&format!("junk{k}"), k, None, 0.0));
        }
        // The configured name in any case: one entry, the slot's, named as first spelt.
        for (k, name) in ["Patient", "PATIENT", "patient"].iter().enumerate() {
            assert_eq!(
                a.ingest(&s(name, 100 + k as u64, None, 1.0)),
                Outcome::Accepted
            );
        }
        let patient: Vec<_> = a.stats.tools.iter().filter(|t| t.slot == Some(0)).collect();
        assert_eq!(patient.len(), 1, "{:?}", a.stats.tools);
        assert_eq!(
            (
                patient[0].name.as_str(),
                patient[0].samples,
                patient[0].accepted
            ),
            ("Patient", 3, 3)
        );
        assert_eq!(a.stats.other_names, 40 - NAME_TABLE as u64);
        assert_eq!(a.stats.rejected_for(Reject::Unmapped), 40);
        // More junk still finds no room; the other configured tool still does.
        a.ingest(&s("junk99", 200, None, 0.0));
        a.ingest(&s("HMD", 201, None, 2.0));
        assert_eq!(a.stats.other_names, 40 - NAME_TABLE as u64 + 1);
        assert_eq!(a.stats.tools.len(), NAME_TABLE + 2);
        assert_eq!(a.stats.tools.capacity(), capacity, "never reallocated");
        let json = a.stats.to_json();
        let names: Vec<&str> = json["tools"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|t| t["name"].as_str())
            .collect();
        assert!(
            names.contains(&"Patient") && names.contains(&"HMD"),
            "{names:?}"
        );
    }

    #[test]
    fn a_constant_device_timestamp_counts_as_repeats_not_as_accepted() {
        let mut a = Assembler::new(config());
        for k in 0..70u64 {
            let out = a.ingest(&Sample {
                device_time_ns: 100,
                ..s("Patient", k * MS, None, k as f32 + 1.0)
            });
            let expected = if k == 0 {
                Outcome::Accepted
            } else {
                Outcome::Repeat
            };
            assert_eq!(out, expected, "sample {k}");
        }
        assert_eq!(
            a.ingest(&s("Pointer", 71 * MS, None, 5.0)),
            Outcome::Rejected(Reject::Unmapped)
        );
        let tool = |name: &str| {
            *a.stats
                .tools
                .iter()
                .find(|t| t.name.as_str() == name)
                .unwrap()
        };
        let p = tool("Patient");
        assert_eq!((p.samples, p.accepted, p.repeats), (70, 1, 69));
        assert_eq!(
            p.last_pose.unwrap().translation_mm[0],
            1.0,
            "the pose published, not the last repeat's"
        );
        assert_ne!(p.last_flags & tool_status::FRAME_REPEAT, 0);
        let pointer = tool("Pointer");
        assert_eq!(
            (pointer.samples, pointer.accepted, pointer.last_pose),
            (1, 0, None),
            "an unmapped name is never accepted"
        );
        assert_eq!((a.stats.accepted, a.stats.frame_repeats), (1, 69));
        let sum: u64 = a.stats.tools.iter().map(|t| t.accepted).sum();
        assert_eq!(sum, a.stats.accepted);
        let json = a.stats.to_json();
        let patient = json["tools"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["name"] == "Patient")
            .unwrap()
            .clone();
        assert_eq!(
            (patient["accepted"].as_u64(), patient["repeats"].as_u64()),
            (Some(1), Some(69))
        );
    }

    #[test]
    fn a_tool_never_seen_is_missing_and_a_silent_one_goes_stale() {
        let mut a = Assembler::new(config());
        a.ingest(&s("Patient", 0, None, 1.0));
        let mut f = TrackerFrame::default();
        a.frame(10 * MS, &mut f);
        assert!(f.tools[0].is_valid());
        assert_eq!(f.tools[1].status, tool_status::MISSING);
        assert_eq!(f.tools[1].pose, Pose::IDENTITY);
        a.frame(50 * MS, &mut f);
        assert!(f.tools[0].is_valid(), "exactly at the bound is still fresh");
        a.frame(51 * MS, &mut f);
        assert!(!f.tools[0].is_valid());
        assert_eq!(f.tools[0].status, tool_status::STALE);
        assert_eq!(
            f.tools[0].pose.translation_mm[0], 1.0,
            "the last good pose is kept"
        );
        a.ingest(&s("Patient", 60 * MS, None, 3.0));
        a.frame(61 * MS, &mut f);
        assert_eq!(
            f.tools[0].status,
            tool_status::VALID,
            "a new sample heals it"
        );
        assert_eq!(a.stats.stale, 1);
    }

    #[test]
    fn a_sample_stamped_far_after_its_tick_goes_stale_and_never_leads_the_capture_stamp() {
        let mut a = Assembler::new(config());
        let mut f = TrackerFrame::default();
        a.ingest(&s("Patient", u64::MAX, None, 1.0));
        for at in [10 * MS, 11 * MS] {
            a.frame(at, &mut f);
            assert_ne!(f.tools[0].status & tool_status::STALE, 0, "at {at}");
            assert!(!f.tools[0].is_valid());
            assert!(f.stamps.capture_ns <= at, "{}", f.stamps.capture_ns);
        }
        // A real sample repairs the slot.
        a.ingest(&s("Patient", 20 * MS, None, 2.0));
        a.frame(20 * MS, &mut f);
        assert_eq!(f.tools[0].status, tool_status::VALID);
        // A reader thread's stamp a little after the loop read its clock is fresh, and the
        // capture stamp is the tick's.
        a.ingest(&s("Patient", 30 * MS + 100_000, None, 3.0));
        a.frame(30 * MS, &mut f);
        assert_eq!(f.tools[0].status, tool_status::VALID);
        assert_eq!(f.stamps.capture_ns, 30 * MS);
        // Exactly the bound ahead is still fresh; beyond it, stale.
        a.ingest(&s("Patient", 40 * MS + 50 * MS, None, 4.0));
        a.frame(40 * MS, &mut f);
        assert_eq!(f.tools[0].status, tool_status::VALID);
        a.ingest(&s("Patient", 100 * MS + 50 * MS + 1, None, 5.0));
        a.frame(100 * MS, &mut f);
        assert_eq!(f.tools[0].status, tool_status::STALE);
        assert_eq!(a.stats.stale, 3);
    }

    #[test]
    fn a_bad_sample_never_reaches_the_frame() {
        let mut a = Assembler::new(config());
        a.ingest(&s("Patient", 0, None, 1.0));
        let mut bad = s("Patient", 1, None, f32::NAN);
        bad.rotation = Rotation::Quat([0.0, 0.0, 0.0, 1.0]);
        assert_eq!(a.ingest(&bad), Outcome::Rejected(Reject::NonFinite));
        let mut f = TrackerFrame::default();
        a.frame(2, &mut f);
        assert!(!f.tools[0].is_valid());
        assert_eq!(f.tools[0].status, tool_status::NON_FINITE);
        assert_eq!(f.tools[0].pose.translation_mm[0], 1.0);
        assert!(f.tools.iter().all(|t| t.pose.is_finite()));
    }

    #[test]
    fn device_frame_gaps_and_repeats_are_flagged_once_and_counted() {
        let mut a = Assembler::new(config());
        let mut f = TrackerFrame::default();
        a.ingest(&s("Patient", 0, Some(10), 1.0));
        a.ingest(&s("Patient", 1, Some(11), 1.0));
        a.frame(2, &mut f);
        assert_eq!(f.tools[0].status, tool_status::VALID);
        assert_eq!(a.ingest(&s("Patient", 3, Some(15), 1.0)), Outcome::Accepted);
        a.frame(4, &mut f);
        assert_eq!(
            f.tools[0].status,
            tool_status::VALID | tool_status::FRAME_GAP
        );
        assert_eq!((a.stats.frame_gaps, a.stats.frames_lost), (1, 3));
        assert_eq!(a.ingest(&s("Patient", 5, Some(15), 9.0)), Outcome::Repeat);
        a.frame(6, &mut f);
        assert_eq!(
            f.tools[0].status,
            tool_status::VALID | tool_status::FRAME_REPEAT
        );
        assert_eq!(
            f.tools[0].pose.translation_mm[0], 1.0,
            "a repeat changes nothing"
        );
        a.frame(7, &mut f);
        assert_eq!(
            f.tools[0].status,
            tool_status::VALID,
            "flags last one frame"
        );
        // Repeats by timestamp when there is no counter.
        a.ingest(&Sample {
            device_time_ns: 100,
            ..s("HMD", 8, None, 1.0)
        });
        assert_eq!(
            a.ingest(&Sample {
                device_time_ns: 100,
                ..s("HMD", 9, None, 1.0)
            }),
            Outcome::Repeat
        );
        assert_eq!(
            a.ingest(&Sample {
                device_time_ns: 90,
                ..s("HMD", 9, None, 1.0)
            }),
            Outcome::Repeat
        );
        assert_eq!(
            a.ingest(&Sample {
                device_time_ns: 101,
                ..s("HMD", 9, None, 1.0)
            }),
            Outcome::Accepted
        );
        assert_eq!(a.stats.frame_repeats, 3);
    }

    #[test]
    fn repeats_alone_do_not_keep_a_tool_fresh() {
        let mut a = Assembler::new(config());
        let mut f = TrackerFrame::default();
        a.ingest(&s("Patient", 0, Some(1), 1.0));
        for k in 1..10 {
            a.ingest(&s("Patient", k * 10 * MS, Some(1), 1.0));
        }
        a.frame(90 * MS, &mut f);
        assert_ne!(f.tools[0].status & tool_status::STALE, 0);
        assert!(!f.tools[0].is_valid());
    }

    #[test]
    fn configurations_round_trip_through_toml_and_bad_ones_are_refused() {
        let c = BridgeConfig {
            stale_ns: 75_000_000,
            ..BridgeConfig::default()
        };
        let back = BridgeConfig::from_toml(&c.to_toml()).unwrap();
        assert_eq!(back, c);
        let mut same = BridgeConfig::default();
        same.slots[1] = ToolName::new("patient").ok();
        assert!(same.check().is_err(), "one tool in two slots");
        assert!(BridgeConfig::from_toml("rate_hz = 60").is_err());
        assert!(BridgeConfig::from_toml(&c.to_toml().replace("60.0", "0.0")).is_err());
    }
}
