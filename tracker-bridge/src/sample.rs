//! What every source hands the bridge: one tool's measurement as the device gave it ([`Sample`]),
//! or something that happened on the link ([`Event`]).
//!
//! A sample is fixed-size and `Copy` (its name is an inline [`ToolName`]), so moving it from a
//! reader thread to the publishing loop, validating it and recording it never allocates. It keeps
//! the rotation in the form the device sent (quaternion or matrix) so that validation checks what
//! was received and a recording replays it bit for bit.

use std::fmt;

/// Capacity of a [`ToolName`], bytes. OpenIGTLink device and TDATA names hold 20; pyigtl's
/// `POSITION` item names (64) are cut to this length.
pub const NAME_CAP: usize = 32;

/// A tool's name as the source knows it: an OpenIGTLink device or element name, an NDI port handle
/// (`"0A"`) or ROM file stem, or `"Patient"`/`"HMD"` for the synthetic source. Printable ASCII,
/// 1..=[`NAME_CAP`] bytes, stored inline.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct ToolName {
    len: u8,
    bytes: [u8; NAME_CAP],
}

impl Default for ToolName {
    fn default() -> Self {
        ToolName {
            len: 0,
            bytes: [0; NAME_CAP],
        }
    }
}

/// A tool name given on the command line or in a configuration that cannot be one.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("tool name {name:?} {reason}: use 1-{NAME_CAP} printable ASCII characters")]
pub struct NameError {
    /// The offending name.
    pub name: String,
    /// What is wrong.
    pub reason: &'static str,
}

impl ToolName {
    /// A checked name (configuration: refuse what would never match).
    pub fn new(name: &str) -> Result<Self, NameError> {
        let err = |reason| NameError {
            name: name.to_string(),
            reason,
        };
        if name.is_empty() {
            return Err(err("is empty"));
        }
        if name.len() > NAME_CAP {
            return Err(err("is too long"));
        }
        if !name.bytes().all(|b| (0x20..=0x7e).contains(&b)) {
            return Err(err("has characters that are not printable ASCII"));
        }
        Ok(Self::from_bytes_lossy(name.as_bytes()))
    }

    /// A name from received bytes: cut at the first NUL and at [`NAME_CAP`], every byte that is
    /// not printable ASCII replaced by `?`. Never fails (an empty result is allowed: it matches no
    /// configured name).
    pub fn from_bytes_lossy(raw: &[u8]) -> Self {
        let raw = raw.split(|&b| b == 0).next().unwrap_or(&[]);
        let mut out = ToolName::default();
        for (dst, &b) in out.bytes.iter_mut().zip(raw) {
            *dst = if (0x20..=0x7e).contains(&b) { b } else { b'?' };
        }
        out.len = raw.len().min(NAME_CAP) as u8;
        out
    }

    /// The name.
    pub fn as_str(&self) -> &str {
        // Only printable ASCII is ever stored.
        std::str::from_utf8(self.as_bytes()).unwrap_or("?")
    }

    /// The name's bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes[..usize::from(self.len).min(NAME_CAP)]
    }

    /// True for the empty name.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Case-insensitive comparison (NDI handles are hex: `0a` and `0A` are one handle; OpenIGTLink
    /// compares type names case-insensitively too).
    pub fn matches(&self, other: &ToolName) -> bool {
        self.as_bytes().eq_ignore_ascii_case(other.as_bytes())
    }
}

impl fmt::Debug for ToolName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.as_str())
    }
}

impl fmt::Display for ToolName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A rotation as the device sent it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rotation {
    /// Quaternion `[x, y, z, w]` (OpenIGTLink POSITION/QTDATA order; NDI's `q0` is `w`).
    Quat([f32; 4]),
    /// Rotation matrix, row-major (`m[row][col]`), as OpenIGTLink TRANSFORM/TDATA carry it.
    Matrix([[f32; 3]; 3]),
    /// The device sent no orientation (a 12-byte OpenIGTLink POSITION): never a valid pose.
    None,
}

/// One tool's measurement, as received.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// When the bridge received it: CLOCK_MONOTONIC ns (for a replay: the recorded time).
    pub receive_ns: u64,
    /// The device's own timestamp, ns since the Unix epoch (OpenIGTLink header); 0 when none.
    pub device_time_ns: u64,
    /// The device's frame counter (NDI frame number, synthetic frame); `None` when it has none.
    pub device_frame: Option<u64>,
    /// The tool's name at the source.
    pub name: ToolName,
    /// The device's id for the tool (NDI port handle; 0 when none).
    pub tool_id: u32,
    /// Orientation.
    pub rotation: Rotation,
    /// Position, mm, in the tracker's frame.
    pub translation_mm: [f32; 3],
    /// RMS marker-fit error, mm, when the device reports one.
    pub rms_error_mm: Option<f32>,
    /// What the device itself said of the tool, as [`ipc_types::tool_status`] bits: `MISSING`,
    /// `OUT_OF_VOLUME`, `PARTIALLY_VISIBLE`, `DEVICE_FAULT` (never `VALID`).
    pub device_flags: u32,
}

impl Sample {
    /// A sample with a quaternion pose and nothing else known (tests, synthetic sources).
    pub fn quat(receive_ns: u64, name: ToolName, quat: [f32; 4], translation_mm: [f32; 3]) -> Self {
        Sample {
            receive_ns,
            device_time_ns: 0,
            device_frame: None,
            name,
            tool_id: 0,
            rotation: Rotation::Quat(quat),
            translation_mm,
            rms_error_mm: None,
            device_flags: 0,
        }
    }
}

/// Why a received message or sample never became a tool's pose. The names (`as_str`) are the keys
/// of the statistics' `rejected` object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
pub enum Reject {
    /// A checksum did not match (OpenIGTLink CRC-64, NDI CRC16).
    Crc = 0,
    /// A message with a checksum that matched but a body that is not what its type says.
    Malformed = 1,
    /// A message announced a body above the size limit (the connection is dropped).
    Oversized = 2,
    /// Bytes that are not the protocol (bad header version, bytes between NDI replies).
    Garbage = 3,
    /// The link closed in the middle of a message.
    Truncated = 4,
    /// The tracker answered with an error.
    DeviceError = 5,
    /// The tracker did not answer in time.
    Timeout = 6,
    /// The reader produced samples faster than the loop took them; the oldest were dropped.
    QueueFull = 7,
    /// A sample for a name that no tool slot is mapped to.
    Unmapped = 8,
    /// NaN or infinity in the pose or RMS.
    NonFinite = 9,
    /// Not a rotation (non-unit quaternion, non-orthonormal matrix or determinant not +1, none).
    NotRotation = 10,
    /// Outside the tracking volume (the bridge's or the device's).
    OutOfVolume = 11,
    /// The tracker did not see the tool.
    Missing = 12,
    /// RMS fit error above the threshold.
    HighRms = 13,
    /// The tracker reported a fault for the tool.
    DeviceFault = 14,
    /// A tracker reply that answered an earlier poll (it came late) or no poll (the tracker
    /// answered twice): dropped, so the bridge never falls behind the device.
    StaleReply = 15,
    /// A second OpenIGTLink sender streaming a tool another sender streams: the first keeps it
    /// until it is quiet for [`crate::source::igtl_owners::TAKEOVER_AFTER`] or gone.
    CompetingSender = 16,
}

impl Reject {
    /// Every reason, in order.
    pub const ALL: [Reject; 17] = [
        Reject::Crc,
        Reject::Malformed,
        Reject::Oversized,
        Reject::Garbage,
        Reject::Truncated,
        Reject::DeviceError,
        Reject::Timeout,
        Reject::QueueFull,
        Reject::Unmapped,
        Reject::NonFinite,
        Reject::NotRotation,
        Reject::OutOfVolume,
        Reject::Missing,
        Reject::HighRms,
        Reject::DeviceFault,
        Reject::StaleReply,
        Reject::CompetingSender,
    ];

    /// The reason's key in statistics and JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Reject::Crc => "crc",
            Reject::Malformed => "malformed",
            Reject::Oversized => "oversized",
            Reject::Garbage => "garbage",
            Reject::Truncated => "truncated",
            Reject::DeviceError => "device_error",
            Reject::Timeout => "timeout",
            Reject::QueueFull => "queue_full",
            Reject::Unmapped => "unmapped",
            Reject::NonFinite => "non_finite",
            Reject::NotRotation => "not_rotation",
            Reject::OutOfVolume => "out_of_volume",
            Reject::Missing => "missing",
            Reject::HighRms => "high_rms",
            Reject::DeviceFault => "device_fault",
            Reject::StaleReply => "stale_reply",
            Reject::CompetingSender => "competing_sender",
        }
    }

    /// The reason with code `c` (recordings store the code).
    pub fn from_code(c: u8) -> Option<Reject> {
        Reject::ALL.get(usize::from(c)).copied()
    }
}

/// What an [`Event`] reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum EventKind {
    /// A link came up (`text`: the peer or device).
    Connected = 0,
    /// A link went down (`text`: why).
    Disconnected = 1,
    /// Connecting failed; the next try is in `value` ms (`text`: why).
    Retrying = 2,
    /// Messages or samples were rejected (`value`: how many, `reason`; `text`: the first
    /// message's detail).
    Rejected = 3,
    /// The device reported its state (`value`: OpenIGTLink STATUS code or NDI system status
    /// bits; `text`: what it said).
    DeviceStatus = 4,
    /// A message type the bridge does not use arrived (`value`: how many; `text`: its type).
    Ignored = 5,
    /// Anything else worth a line (`text`).
    Note = 6,
    /// The OpenIGTLink server had every sender slot taken when a new connection came: `value` 0,
    /// the newcomer was refused (every connection had sent within the eviction window); 1, the
    /// idlest connection was closed to make room for it (`text`: who and why). Its own kind, not
    /// a [`EventKind::Note`], so the statistics count it (a Note's `value` carries other data).
    ConnectionRefused = 7,
}

/// Something that happened on a source's link. Rare by construction (connection changes, errors,
/// rejected messages), so it may carry text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Event {
    /// What happened.
    pub kind: EventKind,
    /// For [`EventKind::Rejected`]: why.
    pub reason: Option<Reject>,
    /// A count or code (see [`EventKind`]).
    pub value: u32,
    /// Details for a person.
    pub text: String,
}

impl Event {
    /// An event without a reason.
    pub fn new(kind: EventKind, value: u32, text: impl Into<String>) -> Self {
        Event {
            kind,
            reason: None,
            value,
            text: text.into(),
        }
    }

    /// `count` messages rejected for `reason`.
    pub fn rejected(reason: Reject, count: u32, text: impl Into<String>) -> Self {
        Event {
            kind: EventKind::Rejected,
            reason: Some(reason),
            value: count,
            text: text.into(),
        }
    }
}

/// What a source hands the loop.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    /// A tool's measurement.
    Sample(Sample),
    /// Something that happened on the link.
    Event(Event),
    /// A one-dimensional reading (an OpenIGTLink `SENSOR` or `STRING`): a respiratory amplitude
    /// when its device is the one `--breathing igtl:NAME` names.
    Reading(Reading),
}

/// A one-dimensional reading as it came, stamped on arrival.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    /// When the bridge received it: CLOCK_MONOTONIC ns.
    pub receive_ns: u64,
    /// The sender's device name.
    pub name: ToolName,
    /// Its unit (`ipc_types::signal_unit::MM`, `ML` or `ARBITRARY`) and value in that unit
    /// (`None`: not a finite number, or marked invalid by its sender), or why it is no amplitude.
    pub value: Result<(u32, Option<f64>), NotAmplitude>,
}

/// Why a reading is no respiratory amplitude.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotAmplitude {
    /// A `SENSOR` whose unit is neither a length, a volume nor none (the packed unit).
    Unit(u64),
    /// A `SENSOR` with other than one value.
    Values(usize),
    /// A `STRING` that is not one `UNIT=VALUE` (mm, ml, au) in ASCII or UTF-8.
    Text,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_checked_on_configuration_and_sanitised_on_receipt() {
        assert!(ToolName::new("").is_err());
        assert!(ToolName::new(&"x".repeat(33)).is_err());
        assert!(ToolName::new("tab\there").is_err());
        let n = ToolName::new("Patient").unwrap();
        assert_eq!(n.as_str(), "Patient");
        let r = ToolName::from_bytes_lossy(b"pat\xffient\0garbage");
        assert_eq!(r.as_str(), "pat?ient");
        let long = ToolName::from_bytes_lossy(&[b'a'; 64]);
        assert_eq!(long.as_bytes().len(), NAME_CAP);
        assert!(ToolName::new("0a")
            .unwrap()
            .matches(&ToolName::new("0A").unwrap()));
        assert!(!ToolName::new("0A")
            .unwrap()
            .matches(&ToolName::new("0B").unwrap()));
    }

    #[test]
    fn reject_codes_round_trip() {
        for (i, r) in Reject::ALL.iter().enumerate() {
            assert_eq!(*r as usize, i);
            assert_eq!(Reject::from_code(i as u8), Some(*r));
        }
        assert_eq!(Reject::from_code(200), None);
    }
}
