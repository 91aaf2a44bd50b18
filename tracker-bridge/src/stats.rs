//! The bridge's statistics: what was received, what was rejected and why, what was flagged, the
//! link's ups and downs, each tool's rate and latest pose, and the loop's period jitter. Printed at
//! exit, written as JSON with `--stats-json`, and what `lungdyn tracker listen` shows.
//!
//! Counting never allocates: the per-name table's capacity is reserved up front (one entry per
//! tool slot, always; unmapped names up to a cap, the rest counted together), and the jitter
//! histogram is sized up front.

use hdrhistogram::Histogram;
use ipc_types::{tool_status, Pose, MAX_TOOLS};
use serde_json::{json, Map, Value};

use crate::sample::{Event, EventKind, Reject, ToolName};

/// Distinct unmapped tool names tracked one by one; samples for more are counted in
/// [`Stats::other_names`]. The configured tools' entries are on top of these (one per slot), so
/// junk names, however many and in whatever order, never crowd a configured tool out.
pub const NAME_TABLE: usize = 32;

/// One tool name's counters.
#[derive(Debug, Clone, Copy)]
pub struct ToolStats {
    /// The name at the source.
    pub name: ToolName,
    /// The slot it is mapped to, if any.
    pub slot: Option<u8>,
    /// Samples received.
    pub samples: u64,
    /// Samples that became the tool's pose (never for an unmapped name).
    pub accepted: u64,
    /// Samples that repeated a device frame or timestamp already seen, so changed nothing: a
    /// sender whose timestamps do not advance shows here instead of as accepted.
    pub repeats: u64,
    /// Receive time of the first and the latest sample, ns.
    pub first_ns: u64,
    /// See `first_ns`.
    pub last_ns: u64,
    /// The latest accepted pose (the one the tool's slot published).
    pub last_pose: Option<Pose>,
    /// The latest sample's [`tool_status`] bits (validation and device).
    pub last_flags: u32,
    /// The latest sample's RMS error, mm (0 when the device gives none).
    pub last_rms_mm: f32,
}

impl ToolStats {
    /// An entry with nothing counted yet.
    fn new(name: ToolName, slot: Option<u8>) -> Self {
        ToolStats {
            name,
            slot,
            samples: 0,
            accepted: 0,
            repeats: 0,
            first_ns: 0,
            last_ns: 0,
            last_pose: None,
            last_flags: 0,
            last_rms_mm: 0.0,
        }
    }

    /// Samples per second between the first and the latest sample (0 with fewer than two).
    pub fn rate_hz(&self) -> f64 {
        if self.samples < 2 || self.last_ns <= self.first_ns {
            return 0.0;
        }
        (self.samples - 1) as f64 * 1e9 / (self.last_ns - self.first_ns) as f64
    }
}

/// Names of the [`tool_status`] bits, for messages and JSON.
pub const STATUS_NAMES: [(u32, &str); 11] = [
    (tool_status::VALID, "valid"),
    (tool_status::MISSING, "missing"),
    (tool_status::OUT_OF_VOLUME, "out_of_volume"),
    (tool_status::NON_FINITE, "non_finite"),
    (tool_status::PARTIALLY_VISIBLE, "partially_visible"),
    (tool_status::NOT_ROTATION, "not_rotation"),
    (tool_status::HIGH_RMS, "high_rms"),
    (tool_status::FRAME_GAP, "frame_gap"),
    (tool_status::FRAME_REPEAT, "frame_repeat"),
    (tool_status::STALE, "stale"),
    (tool_status::DEVICE_FAULT, "device_fault"),
];

/// The names of the bits set in `status`.
pub fn status_names(status: u32) -> Vec<&'static str> {
    STATUS_NAMES
        .iter()
        .filter(|(bit, _)| status & bit != 0)
        .map(|(_, n)| *n)
        .collect()
}

/// After an arrival, how long the bridge's loop waits at most for the device frame's other tools
/// (sent in messages of their own) before it publishes what it has, ns ([`crate::run`]).
pub const GATHER_NS: u64 = 2_000_000;

/// Counters of one bridge run.
#[derive(Debug, Clone)]
pub struct Stats {
    /// Tracker frames built (published).
    pub frames: u64,
    /// Schedule slots skipped because the loop overran.
    pub ticks_skipped: u64,
    /// Frames held back to gather a device frame's tools sent in messages of their own, and of
    /// those the ones published when the gather window ran out (a tool slower than the others, or
    /// late) ([`GATHER_NS`]).
    pub gathered_frames: u64,
    /// See `gathered_frames`.
    pub gather_timeouts: u64,
    /// Samples received from the source.
    pub samples: u64,
    /// Samples that became a tool's pose.
    pub accepted: u64,
    /// Messages or samples rejected, by [`Reject`] code.
    pub rejected: [u64; Reject::ALL.len()],
    /// Times a device frame counter skipped ahead.
    pub frame_gaps: u64,
    /// Device frames skipped in total.
    pub frames_lost: u64,
    /// Samples whose device frame counter or timestamp repeated or went backwards.
    pub frame_repeats: u64,
    /// Tool slots published stale (one per tool per frame).
    pub stale: u64,
    /// Tool slots published with no sample ever received for them.
    pub never_seen: u64,
    /// Samples the device reported as partially visible (used, flagged).
    pub partially_visible: u64,
    /// Links that came up.
    pub connects: u64,
    /// Links that went down.
    pub disconnects: u64,
    /// Failed connection attempts (each followed by a back-off).
    pub retries: u64,
    /// Messages of types the bridge does not use.
    pub ignored: u64,
    /// Of those, readings (SENSOR, STRING) of a device that is not the respiratory signal's: the
    /// first is said, the rest counted (they may come every frame).
    pub ignored_readings: u64,
    /// Device status reports.
    pub device_status: u64,
    /// Per-name counters: one entry per configured slot that has had a sample (named as the
    /// source first spelt it), then unmapped names, at most [`NAME_TABLE`] of them.
    pub tools: Vec<ToolStats>,
    /// Samples for unmapped names that found no room in the table (names beyond
    /// [`NAME_TABLE`]); every unmapped sample is also in `rejected.unmapped`.
    pub other_names: u64,
    /// Connections refused because every sender slot was taken by a recent one
    /// ([`EventKind::ConnectionRefused`] with value 0).
    pub refused_connections: u64,
    /// Idle connections closed to make room for a new one (value 1).
    pub evicted_idle_connections: u64,
    /// Lateness of each tick against its schedule slot, ns.
    pub jitter: Histogram<u64>,
    /// FNV-1a 64 digest of every published frame's bytes with its hop stamps zeroed: equal digests
    /// mean equal frames (a replay proves itself with it).
    pub frames_digest: u64,
    /// The respiratory signal's counts, when there is one.
    pub signal: Option<crate::signal::SignalCounts>,
    /// The chest tool's breathing axis learnt from its motion (`tool:NAME:auto`), once it is.
    pub chest_axis: Option<crate::signal_tool::LearntAxis>,
}

/// FNV-1a 64 offset basis.
pub const FNV_START: u64 = 0xcbf2_9ce4_8422_2325;

/// Extend an FNV-1a 64 digest by `bytes`.
pub fn fnv1a(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl Default for Stats {
    fn default() -> Self {
        Self::new()
    }
}

impl Stats {
    /// Empty counters.
    pub fn new() -> Self {
        Stats {
            frames: 0,
            ticks_skipped: 0,
            gathered_frames: 0,
            gather_timeouts: 0,
            samples: 0,
            accepted: 0,
            rejected: [0; Reject::ALL.len()],
            frame_gaps: 0,
            frames_lost: 0,
            frame_repeats: 0,
            stale: 0,
            never_seen: 0,
            partially_visible: 0,
            connects: 0,
            disconnects: 0,
            retries: 0,
            ignored: 0,
            ignored_readings: 0,
            device_status: 0,
            // Every entry there can ever be, so the per-sample path never reallocates.
            tools: Vec::with_capacity(NAME_TABLE + MAX_TOOLS),
            other_names: 0,
            refused_connections: 0,
            evicted_idle_connections: 0,
            // 1 µs resolution would hide nothing of interest; 1 ns .. 10 s at 3 digits.
            jitter: Histogram::new_with_bounds(1, 10_000_000_000, 3)
                .expect("static histogram bounds are valid"),
            frames_digest: FNV_START,
            signal: None,
            chest_axis: None,
        }
    }

    /// Count `n` rejections for `reason`.
    pub fn reject(&mut self, reason: Reject, n: u64) {
        self.rejected[reason as usize] = self.rejected[reason as usize].saturating_add(n);
    }

    /// Total rejections.
    pub fn rejected_total(&self) -> u64 {
        self.rejected.iter().sum()
    }

    /// The rejections for `reason`.
    pub fn rejected_for(&self, reason: Reject) -> u64 {
        self.rejected[reason as usize]
    }

    /// The entry of a sample named `name` and mapped to `slot`, created when there is room. A
    /// mapped sample's entry is its slot's (whatever the spelling: slots match names without
    /// regard to case) and always has room; an unmapped name's is its own, while fewer than
    /// [`NAME_TABLE`] unmapped names have one (else the sample is counted in `other_names`).
    pub fn tool_mut(&mut self, name: &ToolName, slot: Option<u8>) -> Option<&mut ToolStats> {
        let found = match slot {
            Some(k) => self.tools.iter().position(|t| t.slot == Some(k)),
            None => self
                .tools
                .iter()
                .position(|t| t.slot.is_none() && t.name == *name),
        };
        let i = match found {
            Some(i) => i,
            None => {
                let room = match slot {
                    Some(k) => usize::from(k) < MAX_TOOLS,
                    None => self.tools.iter().filter(|t| t.slot.is_none()).count() < NAME_TABLE,
                };
                if !room {
                    self.other_names += 1;
                    return None;
                }
                self.tools.push(ToolStats::new(*name, slot));
                self.tools.len() - 1
            }
        };
        self.tools.get_mut(i)
    }

    /// Count an event from the source.
    pub fn event(&mut self, e: &Event) {
        match e.kind {
            EventKind::Connected => self.connects += 1,
            EventKind::Disconnected => self.disconnects += 1,
            EventKind::Retrying => self.retries += 1,
            EventKind::Rejected => {
                if let Some(r) = e.reason {
                    self.reject(r, u64::from(e.value.max(1)));
                }
            }
            EventKind::Ignored => self.ignored += u64::from(e.value.max(1)),
            EventKind::DeviceStatus => self.device_status += 1,
            EventKind::ConnectionRefused => {
                if e.value == 1 {
                    self.evicted_idle_connections += 1;
                } else {
                    self.refused_connections += 1;
                }
            }
            EventKind::Note => {}
        }
    }

    /// Tick lateness percentile, µs.
    pub fn jitter_us(&self, quantile: f64) -> f64 {
        if self.jitter.is_empty() {
            return 0.0;
        }
        self.jitter.value_at_quantile(quantile) as f64 / 1000.0
    }

    /// Everything as one JSON object: `frames`, `samples`, `accepted`, `rejected` (by reason),
    /// `flagged`, `link` (with the refused and evicted connections), `tools` (name, slot, frames,
    /// accepted, repeats, rate, last pose as position mm + quaternion xyzw, flags), `other_names`,
    /// `jitter_us`, `frames_digest`.
    pub fn to_json(&self) -> Value {
        let mut rejected = Map::new();
        for r in Reject::ALL {
            rejected.insert(r.as_str().into(), json!(self.rejected_for(r)));
        }
        let tools: Vec<Value> = self
            .tools
            .iter()
            .map(|t| {
                json!({
                    "name": t.name.as_str(),
                    "slot": t.slot,
                    "frames": t.samples,
                    "accepted": t.accepted,
                    "repeats": t.repeats,
                    "rate_hz": t.rate_hz(),
                    "last_pose": t.last_pose.map(|p| json!({
                        "position_mm": p.translation_mm,
                        "quaternion_xyzw": p.quat,
                    })),
                    "last_rms_mm": t.last_rms_mm,
                    "flags": status_names(t.last_flags),
                })
            })
            .collect();
        json!({
            "frames": self.frames,
            "ticks_skipped": self.ticks_skipped,
            "gathered_frames": self.gathered_frames,
            "gather_timeouts": self.gather_timeouts,
            "samples": self.samples,
            "accepted": self.accepted,
            "rejected_total": self.rejected_total(),
            "rejected": rejected,
            "flagged": {
                "frame_gaps": self.frame_gaps,
                "frames_lost": self.frames_lost,
                "frame_repeats": self.frame_repeats,
                "stale": self.stale,
                "never_seen": self.never_seen,
                "partially_visible": self.partially_visible,
            },
            "link": {
                "connects": self.connects,
                "disconnects": self.disconnects,
                "retries": self.retries,
                "ignored_messages": self.ignored,
                "ignored_readings": self.ignored_readings,
                "device_status_reports": self.device_status,
                "refused_connections": self.refused_connections,
                "evicted_idle_connections": self.evicted_idle_connections,
            },
            "tools": tools,
            "other_names": self.other_names,
            "jitter_us": {
                "p50": self.jitter_us(0.5),
                "p99": self.jitter_us(0.99),
                "max": if self.jitter.is_empty() { 0.0 } else { self.jitter.max() as f64 / 1000.0 },
            },
            "frames_digest": format!("{:016x}", self.frames_digest),
            "signal": self.signal.map(|c| json!({
                "samples_sent": c.sent,
                "invalid": c.invalid,
                "withheld_by_cut": c.cut,
                "full_blocks": c.full_blocks,
                "refused_senders": c.refused_senders,
                "malformed": c.malformed,
                "withheld_while_learning_axis": c.learning,
            })),
            "chest_axis": self.chest_axis,
        })
    }

    /// A few lines for a person (what the bridge prints at exit).
    pub fn text(&self) -> String {
        let mut s = format!(
            "{} frames, {} samples ({} accepted, {} rejected), {} ticks skipped, tick lateness p50 {:.0} us p99 {:.0} us\n",
            self.frames,
            self.samples,
            self.accepted,
            self.rejected_total(),
            self.ticks_skipped,
            self.jitter_us(0.5),
            self.jitter_us(0.99),
        );
        if self.gathered_frames > 0 {
            s += &format!(
                "  {} frames gathered from a device frame's messages ({} published when the {} ms \
                 window ran out, a tool slower or later than the others)\n",
                self.gathered_frames,
                self.gather_timeouts,
                GATHER_NS as f64 / 1e6
            );
        }
        let reasons: Vec<String> = Reject::ALL
            .iter()
            .filter(|r| self.rejected_for(**r) > 0)
            .map(|r| format!("{} {}", r.as_str(), self.rejected_for(*r)))
            .collect();
        if !reasons.is_empty() {
            s += &format!("  rejected: {}\n", reasons.join(", "));
        }
        s += &format!(
            "  flagged: {} frame gaps ({} frames lost), {} repeats, {} stale tool-frames, {} never seen, {} partially visible\n",
            self.frame_gaps, self.frames_lost, self.frame_repeats, self.stale, self.never_seen, self.partially_visible
        );
        s += &format!(
            "  link: {} connects, {} disconnects, {} retries, {} ignored messages, {} refused connections, {} idle connections closed to make room\n",
            self.connects,
            self.disconnects,
            self.retries,
            self.ignored,
            self.refused_connections,
            self.evicted_idle_connections
        );
        for t in &self.tools {
            let slot = match t.slot {
                Some(0) => "patient".to_string(),
                Some(1) => "hmd".to_string(),
                Some(2) => "chest".to_string(),
                Some(k) => format!("slot {k}"),
                None => "unmapped".to_string(),
            };
            let pose = match t.last_pose {
                Some(p) => format!(
                    "({:.1}, {:.1}, {:.1}) mm q({:.4}, {:.4}, {:.4}, {:.4})",
                    p.translation_mm[0],
                    p.translation_mm[1],
                    p.translation_mm[2],
                    p.quat[0],
                    p.quat[1],
                    p.quat[2],
                    p.quat[3]
                ),
                None => "no good pose".into(),
            };
            s += &format!(
                "  {:<20} {:<9} {:>7} samples ({} accepted, {} repeats) {:>6.1} Hz  {}  [{}]\n",
                t.name.as_str(),
                slot,
                t.samples,
                t.accepted,
                t.repeats,
                t.rate_hz(),
                pose,
                if t.last_flags == 0 {
                    "ok".to_string()
                } else {
                    status_names(t.last_flags).join(",")
                }
            );
        }
        if let Some(c) = self.signal {
            s += &format!(
                "  breathing signal: {} samples sent ({} flagged invalid), {} withheld by the cut, {} frames with a full block\n",
                c.sent, c.invalid, c.cut, c.full_blocks
            );
            if c.learning > 0 {
                s += &format!(
                    "  breathing signal: {} chest-tool measurement(s) withheld while its axis was learnt\n",
                    c.learning
                );
            }
            if let Some(a) = &self.chest_axis {
                s += &format!("  chest tool's {}\n", a.describe());
            }
            if c.refused_senders + c.malformed > 0 {
                s += &format!(
                    "  breathing signal refused: {} datagram(s) from hosts not allowed, {} not one sample in the stream's unit\n",
                    c.refused_senders, c.malformed
                );
            }
        }
        s
    }
}
