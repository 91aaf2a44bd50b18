//! Recordings: `--record FILE` on any source writes every sample the loop took, with its receive
//! time, every link event, and every tick; `--source replay:FILE` plays them back through the same
//! assembler, so a recorded session gives the same tracker frames (and so the same engine frames)
//! bit for bit, paced in real time or as fast as possible.
//!
//! # File format, version 1
//! All numbers little-endian; floats are IEEE-754 binary32 stored as their bits (NaN payloads and
//! signed zeros survive). CRC-32 is the IEEE polynomial (reflected 0xEDB88320, init and final XOR
//! 0xFFFFFFFF: the zlib/PNG CRC; `crc32(b"123456789") = 0xCBF43926`).
//!
//! ```text
//! header
//!   0   8  magic  "LDTRREC" 0x1A
//!   8   2  format version (1)
//!   10  2  flags (0; reserved)
//!   12  4  C: length of the configuration text (at most 65536)
//!   16  8  creation time, ns since the Unix epoch (information only)
//!   24  4  D: length of the source description (at most 4096)
//!   28  4  CRC-32 of bytes 0..28, the configuration and the description
//!   32  C  configuration: the bridge's BridgeConfig as TOML (UTF-8): tool names per slot,
//!          validation limits, staleness bound, rate. A replay assembles with it.
//!   32+C D  source description (UTF-8), e.g. "OpenIGTLink server on 0.0.0.0:18944"
//! records, one after another to the end of the file
//!   0   1  kind
//!   1   1  L: payload length, always the kind's fixed length (unknown kinds are skipped by it)
//!   2   L  payload
//!   2+L 4  CRC-32 of kind, L and payload
//! ```
//!
//! | kind | L | payload |
//! |---|---|---|
//! | 1 sample | 120 | receive ns u64 · device time ns u64 · device frame u64 · tool id u32 · device flags u32 · has frame u8 · rotation kind u8 (0 quaternion xyzw, 1 matrix row-major, 2 none) · has RMS u8 · name length u8 · rotation 9×f32 (a quaternion uses the first 4, the rest 0) · translation mm 3×f32 · RMS mm f32 · name 32 bytes (zero-padded) |
//! | 2 tick | 16 | tick time ns u64 (the clock of the receive times) · frame number u64 |
//! | 3 event | 80 | event kind u8 (0 connected, 1 disconnected, 2 retrying, 3 rejected, 4 device status, 5 ignored, 6 note, 7 connection refused or idle one evicted: value 0 or 1; a build older than kind 7 refuses a file that holds it) · reject reason u8 (255 none) · text length u8 · 0 u8 · value u32 · text 72 bytes (UTF-8, cut) |
//! | 4 end | 24 | samples u64 · ticks u64 · events u64 (counts of the records before it) |
//! | 5 signal | 160 | the respiratory signal's block the tick published (issue 35): count u32 (≤ 8) · unit u32 · status u32 · valid mask u32 · period ns u64 · origin ns u64 · 8 × (sample time ns u64 · value f64 bits; finite) — times on the receive times' clock; written only when the run has a signal, before its tick; a build older than kind 5 skips it and replays without the signal |
//! | 6 signal latency | 8 | the pipeline's latency the signal's block carried (layout v8: measured from the renderer's reports, `crate::latency`), ns u64, 1 ns … 1 s; written right after a signal record whose block has one; a build older than kind 6 skips it and replays with the scene's fixed latency |
//!
//! Every record belongs to the tick that follows it: the samples and events a tick took, the
//! signal block it published (and its latency), then the tick. The end record's counts leave signal records out. A clean end is an `end` record whose counts match; a file cut short (a crash, a full disk)
//! ends at its last complete record, which the reader reports as [`RecordError::Truncated`] and a
//! replay plays up to. A record whose CRC fails, a length that does not fit its kind, or bytes
//! after `end` are [`RecordError::Corrupt`].
//!
//! # Bounds
//! The reader never allocates by a length it read: the header's two texts are checked against
//! their limits (and the file's size) before they are read, and records are at most 255 + 6 bytes,
//! read into a buffer on the stack. A proptest feeds it arbitrary and mutated files.

use std::fs::File;
use std::io::{BufReader, BufWriter, ErrorKind, Read, Write};
use std::path::{Path, PathBuf};

use thiserror::Error;

use crate::assemble::{BridgeConfig, ConfigError};
use crate::sample::{Event, EventKind, Reject, Rotation, Sample, ToolName, NAME_CAP};

/// File magic.
pub const MAGIC: [u8; 8] = *b"LDTRREC\x1a";
/// Format version written and read.
pub const VERSION: u16 = 1;
/// Largest configuration text, bytes.
pub const MAX_CONFIG: u32 = 65_536;
/// Largest source description, bytes.
pub const MAX_DESCRIPTION: u32 = 4096;
const FIXED_HEADER: usize = 32;

const KIND_SAMPLE: u8 = 1;
const KIND_TICK: u8 = 2;
const KIND_EVENT: u8 = 3;
const KIND_END: u8 = 4;
const KIND_SIGNAL: u8 = 5;
const KIND_SIGNAL_LATENCY: u8 = 6;
const LEN_SAMPLE: usize = 120;
const LEN_TICK: usize = 16;
const LEN_EVENT: usize = 80;
const LEN_END: usize = 24;
const LEN_SIGNAL: usize = 32 + 16 * ipc_types::MAX_SIGNAL_SAMPLES;
const LEN_SIGNAL_LATENCY: usize = 8;
const EVENT_TEXT: usize = 72;

const fn crc_table() -> [u32; 256] {
    let mut t = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

static CRC_TABLE: [u32; 256] = crc_table();

/// Continue a CRC-32 over `data` (start with `0xFFFF_FFFF`, finish with `!crc`).
fn crc32_update(mut crc: u32, data: &[u8]) -> u32 {
    for &b in data {
        crc = CRC_TABLE[((crc ^ u32::from(b)) & 0xFF) as usize] ^ (crc >> 8);
    }
    crc
}

/// CRC-32 (IEEE) of `data`.
pub fn crc32(data: &[u8]) -> u32 {
    !crc32_update(0xFFFF_FFFF, data)
}

/// What went wrong with a recording.
#[derive(Debug, Error)]
pub enum RecordError {
    /// Reading or writing the file failed.
    #[error("recording {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// `--record` names something that is not a regular file.
    #[error("--record {0}")]
    Target(#[from] outfile::WriteError),
    /// `--record` names a file that exists.
    #[error("recording {path} exists: choose another name or remove it (a recording is never overwritten)")]
    Exists {
        /// The file.
        path: PathBuf,
    },
    /// The file does not start with the magic.
    #[error("{path} is not a lungdyn tracker recording (no LDTRREC header)")]
    NotARecording {
        /// The file.
        path: PathBuf,
    },
    /// A version this build does not read.
    #[error("{path} is a version-{found} recording; this build reads version {VERSION}")]
    Version {
        /// The file.
        path: PathBuf,
        /// Its version.
        found: u16,
    },
    /// The header is damaged or claims more than its limits.
    #[error("recording {path}: header {reason}")]
    Header {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The recorded configuration cannot be used.
    #[error("recording {path}: {source}")]
    Config {
        /// The file.
        path: PathBuf,
        /// Why.
        source: ConfigError,
    },
    /// A record is damaged.
    #[error("recording {path}: record at byte {offset} is corrupt: {reason}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// Where the record starts.
        offset: u64,
        /// What is wrong.
        reason: String,
    },
    /// The file ends without its end record (the recording was cut short).
    #[error("recording {path} ends at byte {offset} without its end record (cut short after {records} complete records)")]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Where it ends.
        offset: u64,
        /// Complete records before.
        records: u64,
    },
}

/// A recording's header.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordHeader {
    /// Format version.
    pub version: u16,
    /// When it was made, ns since the Unix epoch.
    pub created_unix_ns: u64,
    /// The bridge configuration it was made with.
    pub config: BridgeConfig,
    /// The source it was made from.
    pub source: String,
}

/// One record.
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    /// A sample the loop took.
    Sample(Sample),
    /// A tick: the frame built from everything before it.
    Tick {
        /// Tick time, ns (the receive times' clock).
        at_ns: u64,
        /// Frame number published.
        frame_number: u64,
    },
    /// A link event.
    Event(Event),
    /// The respiratory signal's block the next tick published (times on the receive clock).
    Signal(ipc_types::SignalBlock),
    /// The pipeline's latency the signal block before it carried, ns
    /// ([`ipc_types::SignalBlock::pipeline_latency_ns`]).
    SignalLatency(u64),
    /// The clean end.
    End {
        /// Samples recorded.
        samples: u64,
        /// Ticks recorded.
        ticks: u64,
        /// Events recorded.
        events: u64,
    },
}

fn encode_signal(b: &ipc_types::SignalBlock, p: &mut [u8; LEN_SIGNAL]) {
    put_u32(p, 0, b.count);
    put_u32(p, 4, b.unit);
    put_u32(p, 8, b.status);
    put_u32(p, 12, b.valid_mask);
    put_u64(p, 16, b.period_ns);
    put_u64(p, 24, b.origin_ns);
    for (i, s) in b.samples.iter().enumerate() {
        put_u64(p, 32 + 16 * i, s.t_ns);
        put_u64(p, 40 + 16 * i, s.value.to_bits());
    }
}

fn decode_signal(p: &[u8]) -> Result<ipc_types::SignalBlock, String> {
    let mut b = ipc_types::SignalBlock {
        count: get_u32(p, 0),
        unit: get_u32(p, 4),
        status: get_u32(p, 8),
        valid_mask: get_u32(p, 12),
        period_ns: get_u64(p, 16),
        origin_ns: get_u64(p, 24),
        ..Default::default()
    };
    if b.count as usize > ipc_types::MAX_SIGNAL_SAMPLES {
        return Err(format!(
            "a signal block of {} samples (at most {})",
            b.count,
            ipc_types::MAX_SIGNAL_SAMPLES
        ));
    }
    for (i, s) in b.samples.iter_mut().enumerate() {
        s.t_ns = get_u64(p, 32 + 16 * i);
        s.value = f64::from_bits(get_u64(p, 40 + 16 * i));
        if !s.value.is_finite() {
            return Err(format!("a signal sample {i} that is not finite"));
        }
    }
    Ok(b)
}

fn put_u64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}
fn put_u32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}
fn get_u64(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}
fn get_u32(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}
fn get_f32(b: &[u8], at: usize) -> f32 {
    f32::from_bits(get_u32(b, at))
}

/// Encode a sample's payload.
fn encode_sample(s: &Sample, p: &mut [u8; LEN_SAMPLE]) {
    p.fill(0);
    put_u64(p, 0, s.receive_ns);
    put_u64(p, 8, s.device_time_ns);
    put_u64(p, 16, s.device_frame.unwrap_or(0));
    put_u32(p, 24, s.tool_id);
    put_u32(p, 28, s.device_flags);
    p[32] = u8::from(s.device_frame.is_some());
    let mut rot = [0f32; 9];
    p[33] = match s.rotation {
        Rotation::Quat(q) => {
            rot[..4].copy_from_slice(&q);
            0
        }
        Rotation::Matrix(m) => {
            for (i, v) in m.iter().flatten().enumerate() {
                rot[i] = *v;
            }
            1
        }
        Rotation::None => 2,
    };
    p[34] = u8::from(s.rms_error_mm.is_some());
    let name = s.name.as_bytes();
    p[35] = name.len() as u8;
    for (i, v) in rot.iter().enumerate() {
        put_u32(p, 36 + 4 * i, v.to_bits());
    }
    for (i, v) in s.translation_mm.iter().enumerate() {
        put_u32(p, 72 + 4 * i, v.to_bits());
    }
    put_u32(p, 84, s.rms_error_mm.unwrap_or(0.0).to_bits());
    p[88..88 + name.len()].copy_from_slice(name);
}

fn decode_sample(p: &[u8]) -> Result<Sample, String> {
    let flag = |i: usize, what: &str| match p[i] {
        0 => Ok(false),
        1 => Ok(true),
        v => Err(format!("{what} flag is {v}, not 0 or 1")),
    };
    let has_frame = flag(32, "has-frame")?;
    let has_rms = flag(34, "has-RMS")?;
    let name_len = usize::from(p[35]);
    if name_len > NAME_CAP {
        return Err(format!("name length {name_len} above {NAME_CAP}"));
    }
    let rot: Vec<f32> = (0..9).map(|i| get_f32(p, 36 + 4 * i)).collect();
    let rotation = match p[33] {
        0 => Rotation::Quat([rot[0], rot[1], rot[2], rot[3]]),
        1 => Rotation::Matrix([
            [rot[0], rot[1], rot[2]],
            [rot[3], rot[4], rot[5]],
            [rot[6], rot[7], rot[8]],
        ]),
        2 => Rotation::None,
        k => return Err(format!("rotation kind {k} is not 0, 1 or 2")),
    };
    let name_bytes = &p[88..88 + name_len];
    if !name_bytes.iter().all(|b| (0x20..=0x7e).contains(b)) {
        return Err("tool name is not printable ASCII".into());
    }
    Ok(Sample {
        receive_ns: get_u64(p, 0),
        device_time_ns: get_u64(p, 8),
        device_frame: has_frame.then(|| get_u64(p, 16)),
        tool_id: get_u32(p, 24),
        device_flags: get_u32(p, 28),
        name: ToolName::from_bytes_lossy(name_bytes),
        rotation,
        translation_mm: [get_f32(p, 72), get_f32(p, 76), get_f32(p, 80)],
        rms_error_mm: has_rms.then(|| get_f32(p, 84)),
    })
}

fn event_kind(k: u8) -> Option<EventKind> {
    Some(match k {
        0 => EventKind::Connected,
        1 => EventKind::Disconnected,
        2 => EventKind::Retrying,
        3 => EventKind::Rejected,
        4 => EventKind::DeviceStatus,
        5 => EventKind::Ignored,
        6 => EventKind::Note,
        7 => EventKind::ConnectionRefused,
        _ => return None,
    })
}

fn encode_event(e: &Event, p: &mut [u8; LEN_EVENT]) {
    p.fill(0);
    p[0] = e.kind as u8;
    p[1] = e.reason.map_or(255, |r| r as u8);
    let mut n = e.text.len().min(EVENT_TEXT);
    while !e.text.is_char_boundary(n) {
        n -= 1;
    }
    p[2] = n as u8;
    put_u32(p, 4, e.value);
    p[8..8 + n].copy_from_slice(&e.text.as_bytes()[..n]);
}

fn decode_event(p: &[u8]) -> Result<Event, String> {
    let kind = event_kind(p[0]).ok_or_else(|| format!("event kind {} unknown", p[0]))?;
    let reason = match p[1] {
        255 => None,
        c => Some(Reject::from_code(c).ok_or_else(|| format!("reject reason {c} unknown"))?),
    };
    let n = usize::from(p[2]);
    if n > EVENT_TEXT || p[3] != 0 {
        return Err("event text length or padding invalid".into());
    }
    Ok(Event {
        kind,
        reason,
        value: get_u32(p, 4),
        text: String::from_utf8_lossy(&p[8..8 + n]).into_owned(),
    })
}

/// Writes a recording as the loop runs. Write errors stop recording (reported once), never the
/// bridge.
pub struct RecordWriter {
    w: BufWriter<File>,
    path: PathBuf,
    samples: u64,
    ticks: u64,
    events: u64,
    buf: [u8; 2 + 255 + 4],
}

impl std::fmt::Debug for RecordWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RecordWriter({})", self.path.display())
    }
}

impl RecordWriter {
    /// Create `path` (never overwriting) and write the header.
    pub fn create(path: &Path, config: &BridgeConfig, source: &str) -> Result<Self, RecordError> {
        let io = |source| RecordError::Io {
            path: path.to_path_buf(),
            source,
        };
        // A device, FIFO, socket or folder is named as such (not "exists"); see outfile.
        outfile::check(path)?;
        let file = match File::options().write(true).create_new(true).open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == ErrorKind::AlreadyExists => {
                return Err(RecordError::Exists {
                    path: path.to_path_buf(),
                })
            }
            Err(e) => return Err(io(e)),
        };
        let config_text = config.to_toml();
        let mut desc = source.as_bytes();
        desc = &desc[..desc.len().min(MAX_DESCRIPTION as usize)];
        let mut head = [0u8; FIXED_HEADER];
        head[..8].copy_from_slice(&MAGIC);
        head[8..10].copy_from_slice(&VERSION.to_le_bytes());
        put_u32(&mut head, 12, config_text.len() as u32);
        let created = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
        put_u64(&mut head, 16, created);
        put_u32(&mut head, 24, desc.len() as u32);
        let crc = !crc32_update(
            crc32_update(
                crc32_update(0xFFFF_FFFF, &head[..28]),
                config_text.as_bytes(),
            ),
            desc,
        );
        put_u32(&mut head, 28, crc);
        let mut w = BufWriter::with_capacity(64 * 1024, file);
        w.write_all(&head).map_err(io)?;
        w.write_all(config_text.as_bytes()).map_err(io)?;
        w.write_all(desc).map_err(io)?;
        Ok(RecordWriter {
            w,
            path: path.to_path_buf(),
            samples: 0,
            ticks: 0,
            events: 0,
            buf: [0; 2 + 255 + 4],
        })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn put(&mut self, kind: u8, payload: &[u8]) -> std::io::Result<()> {
        let n = payload.len();
        self.buf[0] = kind;
        self.buf[1] = n as u8;
        self.buf[2..2 + n].copy_from_slice(payload);
        let crc = crc32(&self.buf[..2 + n]);
        self.buf[2 + n..6 + n].copy_from_slice(&crc.to_le_bytes());
        self.w.write_all(&self.buf[..6 + n])
    }

    /// Record a sample.
    pub fn sample(&mut self, s: &Sample) -> std::io::Result<()> {
        let mut p = [0u8; LEN_SAMPLE];
        encode_sample(s, &mut p);
        self.samples += 1;
        self.put(KIND_SAMPLE, &p)
    }

    /// Record an event.
    pub fn event(&mut self, e: &Event) -> std::io::Result<()> {
        let mut p = [0u8; LEN_EVENT];
        encode_event(e, &mut p);
        self.events += 1;
        self.put(KIND_EVENT, &p)
    }

    /// Record the respiratory signal's block of the tick about to be recorded (and the latency it
    /// carries, when one was measured).
    pub fn signal(&mut self, b: &ipc_types::SignalBlock) -> std::io::Result<()> {
        let mut p = [0u8; LEN_SIGNAL];
        encode_signal(b, &mut p);
        self.put(KIND_SIGNAL, &p)?;
        if b.pipeline_latency_ns != 0 {
            self.put(KIND_SIGNAL_LATENCY, &b.pipeline_latency_ns.to_le_bytes())?;
        }
        Ok(())
    }

    /// Record a tick (flushed to the OS once a second at 60 Hz, so a crash loses at most that).
    pub fn tick(&mut self, at_ns: u64, frame_number: u64) -> std::io::Result<()> {
        let mut p = [0u8; LEN_TICK];
        put_u64(&mut p, 0, at_ns);
        put_u64(&mut p, 8, frame_number);
        self.ticks += 1;
        self.put(KIND_TICK, &p)?;
        if self.ticks.is_multiple_of(60) {
            self.w.flush()?;
        }
        Ok(())
    }

    /// Write the end record and sync the file.
    pub fn finish(mut self) -> Result<PathBuf, RecordError> {
        let mut p = [0u8; LEN_END];
        put_u64(&mut p, 0, self.samples);
        put_u64(&mut p, 8, self.ticks);
        put_u64(&mut p, 16, self.events);
        let path = self.path.clone();
        let io = |source| RecordError::Io {
            path: path.clone(),
            source,
        };
        self.put(KIND_END, &p).map_err(io)?;
        let file = self.w.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        Ok(path)
    }
}

/// Whether the recording at `path` carries a respiratory signal: a signal record among its first
/// 600 ticks (a run with a signal records one before every tick that has samples or a status).
pub fn carries_signal(path: &Path) -> Result<bool, RecordError> {
    let mut r = RecordReader::open(path)?;
    let mut ticks = 0;
    loop {
        match r.next_record() {
            Ok(Some(Record::Signal(_))) => return Ok(true),
            Ok(Some(Record::Tick { .. })) => {
                ticks += 1;
                if ticks >= 600 {
                    return Ok(false);
                }
            }
            Ok(Some(_)) => {}
            Ok(None) | Err(RecordError::Truncated { .. }) => return Ok(false),
            Err(e) => return Err(e),
        }
    }
}

/// Reads a recording record by record; never allocates by a length read from the file.
#[derive(Debug)]
pub struct RecordReader<R: Read> {
    r: R,
    path: PathBuf,
    /// The header.
    pub header: RecordHeader,
    offset: u64,
    records: u64,
    counts: [u64; 3],
    ended: bool,
}

/// Read up to `buf.len()` bytes; returns how many (less only at the end of the input).
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

impl RecordReader<BufReader<File>> {
    /// Open a recording file (a regular file only).
    pub fn open(path: &Path) -> Result<Self, RecordError> {
        let io = |source| RecordError::Io {
            path: path.to_path_buf(),
            source,
        };
        let meta = std::fs::metadata(path).map_err(io)?;
        if !meta.is_file() {
            return Err(RecordError::Header {
                path: path.to_path_buf(),
                reason: "names something that is not a regular file".into(),
            });
        }
        let f = File::open(path).map_err(io)?;
        Self::new(BufReader::new(f), path, Some(meta.len()))
    }
}

impl<R: Read> RecordReader<R> {
    /// Read the header from `r`; `size` (when known) bounds the header's texts further.
    pub fn new(mut r: R, path: &Path, size: Option<u64>) -> Result<Self, RecordError> {
        let path = path.to_path_buf();
        let io = |source| RecordError::Io {
            path: path.clone(),
            source,
        };
        let header_err = |reason: String| RecordError::Header {
            path: path.clone(),
            reason,
        };
        let mut head = [0u8; FIXED_HEADER];
        let n = read_full(&mut r, &mut head).map_err(io)?;
        if n < 8 || head[..8] != MAGIC {
            return Err(RecordError::NotARecording { path });
        }
        if n < FIXED_HEADER {
            return Err(header_err(format!(
                "is {n} bytes, shorter than its {FIXED_HEADER}"
            )));
        }
        let version = u16::from_le_bytes([head[8], head[9]]);
        if version != VERSION {
            return Err(RecordError::Version {
                path,
                found: version,
            });
        }
        let config_len = get_u32(&head, 12);
        let desc_len = get_u32(&head, 24);
        if config_len > MAX_CONFIG || desc_len > MAX_DESCRIPTION {
            return Err(header_err(format!(
                "claims a {config_len}-byte configuration and a {desc_len}-byte description (limits {MAX_CONFIG} and {MAX_DESCRIPTION})"
            )));
        }
        let texts = u64::from(config_len) + u64::from(desc_len);
        if size.is_some_and(|s| s < FIXED_HEADER as u64 + texts) {
            return Err(header_err("claims more bytes than the file has".into()));
        }
        // Bounded by the checks above (at most 68 KiB).
        let mut config = vec![0u8; config_len as usize];
        let mut desc = vec![0u8; desc_len as usize];
        if read_full(&mut r, &mut config).map_err(io)? < config.len()
            || read_full(&mut r, &mut desc).map_err(io)? < desc.len()
        {
            return Err(header_err("ends inside its texts".into()));
        }
        let crc = !crc32_update(
            crc32_update(crc32_update(0xFFFF_FFFF, &head[..28]), &config),
            &desc,
        );
        if crc != get_u32(&head, 28) {
            return Err(header_err(
                "CRC does not match (the file is damaged)".into(),
            ));
        }
        let text = std::str::from_utf8(&config)
            .map_err(|_| header_err("configuration is not UTF-8".into()))?;
        let config = BridgeConfig::from_toml(text).map_err(|source| RecordError::Config {
            path: path.clone(),
            source,
        })?;
        let header = RecordHeader {
            version,
            created_unix_ns: get_u64(&head, 16),
            config,
            source: String::from_utf8_lossy(&desc).into_owned(),
        };
        Ok(RecordReader {
            r,
            path,
            header,
            offset: FIXED_HEADER as u64 + texts,
            records: 0,
            counts: [0; 3],
            ended: false,
        })
    }

    fn corrupt(&self, offset: u64, reason: impl Into<String>) -> RecordError {
        RecordError::Corrupt {
            path: self.path.clone(),
            offset,
            reason: reason.into(),
        }
    }

    /// The next record; `Ok(None)` after the end record. A file cut short gives
    /// [`RecordError::Truncated`].
    pub fn next_record(&mut self) -> Result<Option<Record>, RecordError> {
        loop {
            if let Some(r) = self.one_record()? {
                return Ok(r);
            }
        }
    }

    /// One record: `Some(r)` as `next_record` returns it, `None` for a skipped unknown kind.
    fn one_record(&mut self) -> Result<Option<Option<Record>>, RecordError> {
        let start = self.offset;
        let mut buf = [0u8; 2 + 255 + 4];
        let n = read_full(&mut self.r, &mut buf[..2]).map_err(|source| RecordError::Io {
            path: self.path.clone(),
            source,
        })?;
        if self.ended {
            return if n == 0 {
                Ok(Some(None))
            } else {
                Err(self.corrupt(start, "bytes after the end record"))
            };
        }
        let truncated = |s: &Self| RecordError::Truncated {
            path: s.path.clone(),
            offset: start,
            records: s.records,
        };
        if n < 2 {
            return Err(truncated(self));
        }
        let (kind, len) = (buf[0], usize::from(buf[1]));
        let expected = match kind {
            KIND_SAMPLE => Some(LEN_SAMPLE),
            KIND_TICK => Some(LEN_TICK),
            KIND_EVENT => Some(LEN_EVENT),
            KIND_END => Some(LEN_END),
            KIND_SIGNAL => Some(LEN_SIGNAL),
            KIND_SIGNAL_LATENCY => Some(LEN_SIGNAL_LATENCY),
            _ => None,
        };
        if expected.is_some_and(|e| e != len) {
            return Err(self.corrupt(start, format!("kind {kind} with length {len}")));
        }
        let got =
            read_full(&mut self.r, &mut buf[2..2 + len + 4]).map_err(|source| RecordError::Io {
                path: self.path.clone(),
                source,
            })?;
        if got < len + 4 {
            return Err(truncated(self));
        }
        let crc = get_u32(&buf, 2 + len);
        if crc != crc32(&buf[..2 + len]) {
            return Err(self.corrupt(start, "CRC does not match"));
        }
        self.offset += (2 + len + 4) as u64;
        let p = &buf[2..2 + len];
        let record = match kind {
            KIND_SAMPLE => {
                self.counts[0] += 1;
                Record::Sample(decode_sample(p).map_err(|e| self.corrupt(start, e))?)
            }
            KIND_TICK => {
                self.counts[1] += 1;
                Record::Tick {
                    at_ns: get_u64(p, 0),
                    frame_number: get_u64(p, 8),
                }
            }
            KIND_EVENT => {
                self.counts[2] += 1;
                Record::Event(decode_event(p).map_err(|e| self.corrupt(start, e))?)
            }
            KIND_SIGNAL => Record::Signal(decode_signal(p).map_err(|e| self.corrupt(start, e))?),
            KIND_SIGNAL_LATENCY => {
                let ns = get_u64(p, 0);
                if !(1..=crate::latency::MAX_LATENCY_NS).contains(&ns) {
                    return Err(
                        self.corrupt(start, format!("a signal latency of {ns} ns (1 ns … 1 s)"))
                    );
                }
                Record::SignalLatency(ns)
            }
            KIND_END => {
                let (samples, ticks, events) = (get_u64(p, 0), get_u64(p, 8), get_u64(p, 16));
                if [samples, ticks, events] != self.counts {
                    return Err(self.corrupt(
                        start,
                        format!(
                            "end record counts {samples}/{ticks}/{events} but the file holds {}/{}/{}",
                            self.counts[0], self.counts[1], self.counts[2]
                        ),
                    ));
                }
                self.ended = true;
                Record::End {
                    samples,
                    ticks,
                    events,
                }
            }
            // A kind from a later minor revision: skipped (its CRC checked).
            _ => return Ok(None),
        };
        self.records += 1;
        Ok(Some(Some(record)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tmp(name: &str) -> PathBuf {
        let p = std::env::temp_dir().join(format!("lungdyn-rec-{}-{name}", std::process::id()));
        let _ = std::fs::remove_file(&p);
        p
    }

    fn samples() -> Vec<Sample> {
        let n = ToolName::new("Patient").unwrap();
        vec![
            Sample::quat(
                5,
                n,
                [0.0, -0.0, f32::from_bits(0x7fc0_0001), 1.0],
                [1.5, -2.25, 1e-30],
            ),
            Sample {
                device_time_ns: 99,
                device_frame: Some(u64::MAX),
                tool_id: 0x0A,
                rotation: Rotation::Matrix([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]),
                rms_error_mm: Some(0.125),
                device_flags: 0x12,
                ..Sample::quat(6, ToolName::new("0A").unwrap(), [0.0; 4], [0.0; 3])
            },
            Sample {
                rotation: Rotation::None,
                name: ToolName::from_bytes_lossy(&[b'x'; 32]),
                ..Sample::quat(7, n, [0.0; 4], [f32::INFINITY, 0.0, 0.0])
            },
        ]
    }

    fn bits(s: &Sample) -> Vec<u8> {
        let mut p = [0u8; LEN_SAMPLE];
        encode_sample(s, &mut p);
        p.to_vec()
    }

    #[test]
    fn crc32_matches_the_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn a_recording_reads_back_bit_for_bit() {
        let path = tmp("roundtrip");
        let config = BridgeConfig::default();
        let mut w = RecordWriter::create(&path, &config, "test source").unwrap();
        for s in samples() {
            w.sample(&s).unwrap();
        }
        let e = Event::rejected(Reject::Crc, 3, "é".repeat(50));
        w.event(&e).unwrap();
        w.tick(1000, 1).unwrap();
        w.finish().unwrap();
        let mut r = RecordReader::open(&path).unwrap();
        assert_eq!(r.header.config, config);
        assert_eq!(r.header.source, "test source");
        for s in samples() {
            match r.next_record().unwrap() {
                Some(Record::Sample(back)) => assert_eq!(bits(&back), bits(&s), "{s:?}"),
                other => panic!("{other:?}"),
            }
        }
        match r.next_record().unwrap() {
            Some(Record::Event(back)) => {
                assert_eq!(back.reason, Some(Reject::Crc));
                assert_eq!(back.value, 3);
                assert!(back.text.len() <= 72 && back.text.chars().all(|c| c == 'é'));
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            r.next_record().unwrap(),
            Some(Record::Tick {
                at_ns: 1000,
                frame_number: 1
            })
        );
        assert!(matches!(
            r.next_record().unwrap(),
            Some(Record::End {
                samples: 3,
                ticks: 1,
                events: 1
            })
        ));
        assert_eq!(r.next_record().unwrap(), None);
        assert!(matches!(
            RecordWriter::create(&path, &config, "again"),
            Err(RecordError::Exists { .. })
        ));
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn a_signal_block_reads_back_bit_for_bit_and_a_damaged_one_is_refused() {
        let path = tmp("signal");
        let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "with signal").unwrap();
        let mut b = ipc_types::SignalBlock {
            count: 3,
            unit: ipc_types::signal_unit::ML,
            status: 0x5,
            valid_mask: 0b101,
            period_ns: 40_000_000,
            origin_ns: 123_456_789,
            ..Default::default()
        };
        for (i, v) in [412.5, -0.0, f64::MIN_POSITIVE].into_iter().enumerate() {
            b.samples[i] = ipc_types::SignalWire {
                t_ns: 1_000 + i as u64,
                value: v,
            };
        }
        w.signal(&b).unwrap();
        w.tick(2000, 7).unwrap();
        w.finish().unwrap();
        let mut r = RecordReader::open(&path).unwrap();
        match r.next_record().unwrap() {
            Some(Record::Signal(back)) => {
                assert_eq!(bytemuck::bytes_of(&back), bytemuck::bytes_of(&b))
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            r.next_record().unwrap(),
            Some(Record::Tick { .. })
        ));
        // The end record's counts leave the signal out.
        assert!(matches!(
            r.next_record().unwrap(),
            Some(Record::End {
                samples: 0,
                ticks: 1,
                events: 0
            })
        ));
        let _ = std::fs::remove_file(&path);
        // More samples than a block holds, and a value that is not finite: refused, by name.
        for (damage, word) in [
            (ipc_types::SignalBlock { count: 9, ..b }, "9 samples"),
            (
                {
                    let mut d = b;
                    d.samples[7].value = f64::NAN;
                    d
                },
                "not finite",
            ),
        ] {
            let path = tmp("signal-bad");
            let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "bad").unwrap();
            w.signal(&damage).unwrap();
            w.finish().unwrap();
            let mut r = RecordReader::open(&path).unwrap();
            match r.next_record() {
                Err(e @ RecordError::Corrupt { .. }) => {
                    assert!(e.to_string().contains(word), "{e}")
                }
                other => panic!("{other:?}"),
            }
            let _ = std::fs::remove_file(&path);
        }
    }

    #[test]
    fn a_measured_latency_follows_its_signal_block_and_one_out_of_range_is_refused() {
        let path = tmp("signal-latency");
        let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "latency").unwrap();
        let b = ipc_types::SignalBlock {
            count: 1,
            unit: ipc_types::signal_unit::ML,
            valid_mask: 1,
            period_ns: 40_000_000,
            pipeline_latency_ns: 9_123_456,
            ..Default::default()
        };
        w.signal(&b).unwrap();
        w.tick(2000, 1).unwrap();
        // None measured yet: no latency record.
        w.signal(&ipc_types::SignalBlock {
            pipeline_latency_ns: 0,
            ..b
        })
        .unwrap();
        w.tick(3000, 2).unwrap();
        w.finish().unwrap();
        let mut r = RecordReader::open(&path).unwrap();
        let kinds: Vec<Record> = std::iter::from_fn(|| r.next_record().unwrap()).collect();
        assert!(matches!(kinds[0], Record::Signal(s) if s.pipeline_latency_ns == 0));
        assert_eq!(kinds[1], Record::SignalLatency(9_123_456));
        assert!(matches!(
            kinds[2],
            Record::Tick {
                frame_number: 1,
                ..
            }
        ));
        assert!(matches!(kinds[3], Record::Signal(_)));
        assert!(matches!(
            kinds[4],
            Record::Tick {
                frame_number: 2,
                ..
            }
        ));
        let _ = std::fs::remove_file(&path);
        for (ns, word) in [
            (0u64, "latency of 0 ns"),
            (1_000_000_001, "latency of 1000000001 ns"),
        ] {
            let path = tmp("signal-latency-bad");
            let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "bad").unwrap();
            w.put(KIND_SIGNAL_LATENCY, &ns.to_le_bytes()).unwrap();
            w.finish().unwrap();
            match RecordReader::open(&path).unwrap().next_record() {
                Err(e @ RecordError::Corrupt { .. }) => {
                    assert!(e.to_string().contains(word), "{e}")
                }
                other => panic!("{other:?}"),
            }
            let _ = std::fs::remove_file(&path);
        }
    }

    #[test]
    fn a_connection_refused_event_reads_back() {
        let path = tmp("refused");
        let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "server").unwrap();
        let events = [
            Event::new(EventKind::ConnectionRefused, 0, "refused 127.0.0.1:5"),
            Event::new(EventKind::ConnectionRefused, 1, "closing 127.0.0.1:6"),
        ];
        for e in &events {
            w.event(e).unwrap();
        }
        w.tick(1000, 1).unwrap();
        w.finish().unwrap();
        let mut r = RecordReader::open(&path).unwrap();
        for e in &events {
            assert_eq!(r.next_record().unwrap(), Some(Record::Event(e.clone())));
        }
        let _ = std::fs::remove_file(&path);
    }

    /// A small recording's bytes, made once (tests run in parallel; one file, one writer).
    fn file_bytes() -> Vec<u8> {
        static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
        BYTES
            .get_or_init(|| {
                let path = tmp("bytes");
                let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "src").unwrap();
                for (k, s) in samples().iter().enumerate() {
                    w.sample(s).unwrap();
                    w.tick(k as u64, k as u64 + 1).unwrap();
                }
                w.finish().unwrap();
                let b = std::fs::read(&path).unwrap();
                let _ = std::fs::remove_file(&path);
                b
            })
            .clone()
    }

    fn read_all(bytes: &[u8]) -> Result<usize, RecordError> {
        let mut r = RecordReader::new(bytes, Path::new("mem"), Some(bytes.len() as u64))?;
        let mut n = 0;
        while r.next_record()?.is_some() {
            n += 1;
        }
        Ok(n)
    }

    #[test]
    fn damage_is_found_and_named() {
        let good = file_bytes();
        assert_eq!(read_all(&good).unwrap(), 7);
        // Cut anywhere inside the records: truncated, never a panic or a wrong record.
        let header_len = good.len() - (7 * 6 + 3 * LEN_SAMPLE + 3 * LEN_TICK + LEN_END);
        for cut in header_len..good.len() {
            match read_all(&good[..cut]) {
                Err(RecordError::Truncated { .. }) => {}
                other => panic!("cut at {cut}: {other:?}"),
            }
        }
        // Flip any bit after the header: corrupt (or, in a length byte, corrupt or truncated).
        for i in (header_len..good.len()).step_by(7) {
            let mut b = good.clone();
            b[i] ^= 0x10;
            assert!(
                matches!(
                    read_all(&b),
                    Err(RecordError::Corrupt { .. } | RecordError::Truncated { .. })
                ),
                "bit flip at {i}"
            );
        }
        let mut b = good.clone();
        b.push(0);
        assert!(matches!(read_all(&b), Err(RecordError::Corrupt { .. })));
        let mut b = good.clone();
        b[40] ^= 1;
        assert!(matches!(
            read_all(&b),
            Err(RecordError::Header { .. } | RecordError::Config { .. })
        ));
        let mut b = good.clone();
        b[8] = 2;
        assert!(matches!(
            read_all(&b),
            Err(RecordError::Version { found: 2, .. })
        ));
        assert!(matches!(
            read_all(b"not a recording at all"),
            Err(RecordError::NotARecording { .. })
        ));
        // A header that claims a huge configuration is refused before anything is allocated.
        let mut b = good.clone();
        b[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(read_all(&b), Err(RecordError::Header { .. })));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        #[test]
        fn the_reader_survives_arbitrary_bytes(tail in proptest::collection::vec(any::<u8>(), 0..600)) {
            let good = file_bytes();
            let mut b = good[..40].to_vec();
            b.extend_from_slice(&tail);
            let _ = read_all(&b);
            let mut c = MAGIC.to_vec();
            c.extend_from_slice(&tail);
            let _ = read_all(&c);
        }

        #[test]
        fn the_reader_survives_mutated_recordings(
            edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
            cut in any::<usize>(),
        ) {
            let mut b = file_bytes();
            for (i, v) in edits {
                let i = i % b.len();
                b[i] = v;
            }
            let cut = cut % (b.len() + 1);
            let _ = read_all(&b[..cut]);
        }
    }
}
