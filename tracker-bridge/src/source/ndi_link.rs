//! NDI combined API over a serial port (Polaris, Aurora: `ndi-serial:/dev/ttyUSB0`) or TCP (Vega:
//! `ndi-tcp:HOST[:8765]`): the session that initialises the tracker and polls it, on a reader
//! thread, over the pure protocol layer in [`crate::ndi`].
//!
//! ## Session
//! 1. Serial: open at 9600 8N1 (the power-up setting); `INIT`; if that gets no `OKAY`, a serial
//!    break, wait for `RESET`, `INIT` again; then `COMM:50000` and switch to 115200 baud.
//!    TCP: `INIT` (the first one may take seconds).
//! 2. Tools: `PHSR:01` → `PHF` each handle waiting to be freed; for each `--ndi-rom FILE`,
//!    `PHRQ:*********1****` → a handle, `PVWR` the file in 64-byte chunks (the tool is then named
//!    by the file's stem); `PHSR:02` → `PINIT` each (repeated until none is left); `PHSR:03` →
//!    `PENA:hhD` each; `TSTART`.
//! 3. Poll at `--ndi-poll-hz` (default the bridge's rate) with `BX:0801` (transforms, port status
//!    and frame numbers, also for tools out of volume); if the tracker does not know `BX`
//!    (`ERROR01`), fall back to `TX:0801` (also forced with `--ndi-tx`).
//! 4. On exit: `TSTOP`, and on a serial port `COMM:00000` so the next session starts at 9600.
//!
//! Tools are named by their port handle as two uppercase hex digits (`0A`), or by their ROM file
//! stem; map them with `--patient-tool 0A --hmd-tool 0B`. Each tool's handle status and port
//! status become device flags: missing, disabled or unoccupied → `MISSING`; out of volume →
//! `OUT_OF_VOLUME`; partially out of volume → `PARTIALLY_VISIBLE`; broken sensor, hardware failure
//! or processing exception → `DEVICE_FAULT`. The per-handle frame number is the sample's device
//! frame (gaps and repeats). A change of the system status is reported; a newly occupied port
//! (a wired tool plugged in) re-runs step 2 as PLUS does.
//!
//! ## Replies belong to polls
//! A tracker answers its commands in order, one reply each. The session keeps at most one poll
//! outstanding on its schedule and matches what comes back with a [`ReplyMatcher`]: a reply that
//! arrives while a newer poll is still owed answers an older one (it came late) and is dropped; a
//! reply that arrives when nothing is owed (a tracker that answers twice) is dropped unless its
//! frame number is newer than the one in use. Dropped replies are counted as `stale_reply`, and
//! the receive time of every sample is taken when its bytes arrive, not when the reply is used —
//! so the bridge is never more than one device sample behind for longer than a poll.
//!
//! ## Faults
//! A reply with a bad CRC or an unexpected layout is rejected and polling goes on; bytes between
//! replies are skipped and counted (`garbage`); a poll without a reply in 250 ms is a `timeout`;
//! five in a row, a write or read error, or a failed set-up drop the link, which is reopened with
//! back-off (an unplugged USB adapter shows as retries until it is back). Nothing is ever buffered
//! beyond [`crate::ndi::DEFAULT_MAX_REPLY`].

use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::time::{Duration, Instant};

use ipc_types::tool_status;
use transport::now_ns;

use crate::ndi::{
    self, AsciiReply, Baud, CommSettings, Command, NdiError, PhsrFilter, RawReply, ReplyReader,
    ToolSample, TrackingPriority,
};
use crate::sample::{Event, EventKind, Input, Reject, Rotation, Sample, ToolName};
use crate::source::{Backoff, Feed, Inbox, Poll, Source, SourceError, SourceOptions};

/// Largest NDI tool definition (virtual SROM) file.
pub const ROM_BYTES: usize = 1024;
/// Reply-option word polled.
pub const POLL_OPTIONS: u16 =
    ndi::reply_options::TRANSFORMS | ndi::reply_options::NOT_NORMALLY_REPORTED;
/// A poll unanswered for this long is a timeout.
pub const POLL_TIMEOUT: Duration = Duration::from_millis(250);
/// Timeouts in a row that drop the link.
pub const MAX_TIMEOUTS: u32 = 5;

/// What to do with one tracking reply ([`ReplyMatcher::reply`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// It answers the newest poll, or carries a newer frame than the one in use: use it.
    Use,
    /// It answers an older poll than one still owed (it came late): drop and count it.
    Late,
    /// Nothing was owed and its frame is not newer (a tracker that answered twice): drop and count.
    Unsolicited,
}

/// Matches tracking replies to polls for a device that answers in order, one reply per command
/// (see the module docs). Pure bookkeeping: the session tells it what it sent and what came back.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplyMatcher {
    owed: u32,
    last_frame: Option<u32>,
    /// The reply used last repeated the frame in use (a duplicate taken as an answer, or a tracker
    /// polled faster than its camera): counted as stale if a newer unsolicited reply follows.
    suspect: bool,
    timeouts_in_row: u32,
}

impl ReplyMatcher {
    /// A poll was sent.
    pub fn sent(&mut self) {
        self.owed = (self.owed + 1).min(MAX_TIMEOUTS + 1);
    }

    /// Polls sent and not answered yet.
    pub fn owed(&self) -> u32 {
        self.owed
    }

    /// The newest poll got no reply by its deadline. Its reply may still come (late, then dropped
    /// as [`Verdict::Late`] when the next poll's reply follows it); after a second timeout in a
    /// row the polls are taken as lost, so a reply that never comes cannot shift every later
    /// reply onto the wrong poll.
    pub fn timed_out(&mut self) {
        self.timeouts_in_row += 1;
        if self.timeouts_in_row >= 2 {
            self.owed = 0;
        }
    }

    /// A reply came back with the device frame `frame` (the newest of its tools; `None` when it
    /// carries none: an error reply, a bad CRC). Returns what to do with it and how many replies
    /// to count as stale (0 or 1) besides a dropped one.
    pub fn reply(&mut self, frame: Option<u32>) -> (Verdict, u64) {
        let answers = self.owed > 0;
        self.owed = self.owed.saturating_sub(1);
        let newer = match (frame, self.last_frame) {
            (Some(f), Some(l)) => (f.wrapping_sub(l) as i32) > 0,
            (Some(_), None) => true,
            (None, _) => false,
        };
        if self.owed > 0 {
            return (Verdict::Late, 0);
        }
        if !answers && !newer {
            return (Verdict::Unsolicited, 0);
        }
        // A newer frame arriving unasked shows that the previous answer was a duplicate.
        let stale = u64::from(!answers && self.suspect);
        self.timeouts_in_row = 0;
        self.suspect = answers && frame.is_some() && !newer && self.last_frame.is_some();
        if newer {
            self.last_frame = frame;
        }
        (Verdict::Use, stale)
    }

    /// Start over (the tracker was set up again; nothing is owed).
    pub fn reset(&mut self) {
        *self = ReplyMatcher {
            last_frame: self.last_frame,
            ..Default::default()
        };
    }
}

/// A byte link to an NDI tracker.
pub trait Link: Send {
    /// Write every byte.
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()>;
    /// Read what is there, waiting at most the timeout (`TimedOut`/`WouldBlock` then).
    fn recv(&mut self, buf: &mut [u8]) -> std::io::Result<usize>;
    /// Set the read timeout.
    fn set_timeout(&mut self, d: Duration) -> std::io::Result<()>;
    /// True for a serial port (baud changes and breaks apply).
    fn is_serial(&self) -> bool;
    /// Serial: hold a break for `d` (the tracker resets to 9600 8N1 and answers `RESET`).
    fn send_break(&mut self, _d: Duration) -> std::io::Result<()> {
        Ok(())
    }
    /// Serial: change the host's baud rate.
    fn set_baud(&mut self, _baud: u32) -> std::io::Result<()> {
        Ok(())
    }
    /// Drop unread input.
    fn discard_input(&mut self) {}
}

/// A serial port.
pub struct SerialLink(Box<dyn serialport::SerialPort>);

impl SerialLink {
    /// Open `path` at 9600 8N1, no handshake (the tracker's power-up setting).
    pub fn open(path: &str) -> Result<Self, serialport::Error> {
        let port = serialport::new(path, 9600)
            .data_bits(serialport::DataBits::Eight)
            .parity(serialport::Parity::None)
            .stop_bits(serialport::StopBits::One)
            .flow_control(serialport::FlowControl::None)
            .timeout(Duration::from_millis(100))
            .open()?;
        Ok(SerialLink(port))
    }
}

impl Link for SerialLink {
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.0.write_all(bytes)?;
        self.0.flush()
    }
    fn recv(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.0.read(buf)
    }
    fn set_timeout(&mut self, d: Duration) -> std::io::Result<()> {
        self.0.set_timeout(d).map_err(std::io::Error::from)
    }
    fn is_serial(&self) -> bool {
        true
    }
    fn send_break(&mut self, d: Duration) -> std::io::Result<()> {
        self.0.set_break().map_err(std::io::Error::from)?;
        std::thread::sleep(d);
        self.0.clear_break().map_err(std::io::Error::from)
    }
    fn set_baud(&mut self, baud: u32) -> std::io::Result<()> {
        self.0.set_baud_rate(baud).map_err(std::io::Error::from)
    }
    fn discard_input(&mut self) {
        let _ = self.0.clear(serialport::ClearBuffer::Input);
    }
}

/// A TCP connection (Vega). Reads wait with `ppoll` (a high-resolution timer) rather than
/// `SO_RCVTIMEO`, which rounds up to the kernel's tick (up to 4 ms late): the session reads the
/// link right up to its next poll slot.
pub struct TcpLink {
    stream: TcpStream,
    timeout: Duration,
}

impl TcpLink {
    /// Connect to `host:port`.
    pub fn connect(host: &str, port: u16) -> std::io::Result<Self> {
        let stream = crate::source::igtl_client::connect(host, port, Duration::from_secs(2))?;
        stream.set_nodelay(true)?;
        Ok(TcpLink {
            stream,
            timeout: Duration::from_millis(100),
        })
    }
}

/// Wait until `fd` is readable or `timeout` passes; false on timeout.
fn readable(fd: libc::c_int, timeout: Duration) -> std::io::Result<bool> {
    let mut pfd = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: timeout.as_secs().min(i32::MAX as u64) as libc::time_t,
        tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
    };
    // SAFETY: one valid pollfd for an open socket; a valid timespec; no signal mask change.
    match unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) } {
        0 => Ok(false),
        n if n > 0 => Ok(true),
        _ => Err(std::io::Error::last_os_error()),
    }
}

impl Link for TcpLink {
    fn send(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.stream.write_all(bytes)
    }
    fn recv(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::os::fd::AsRawFd;
        if !readable(self.stream.as_raw_fd(), self.timeout)? {
            return Err(std::io::Error::new(
                ErrorKind::TimedOut,
                "no bytes within the timeout",
            ));
        }
        match self.stream.read(buf) {
            Ok(0) => Err(std::io::Error::new(
                ErrorKind::UnexpectedEof,
                "the tracker closed the connection",
            )),
            r => r,
        }
    }
    fn set_timeout(&mut self, d: Duration) -> std::io::Result<()> {
        self.timeout = d;
        Ok(())
    }
    fn is_serial(&self) -> bool {
        false
    }
}

/// Why a session step failed.
#[derive(Debug)]
enum SessionError {
    Io(std::io::Error),
    Timeout(String),
    Ndi(String, NdiError),
    Stopped,
}

impl std::fmt::Display for SessionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SessionError::Io(e) => write!(f, "link error: {e}"),
            SessionError::Timeout(c) => write!(f, "no reply to {c}"),
            SessionError::Ndi(c, e) => write!(f, "{c}: {e}"),
            SessionError::Stopped => write!(f, "stopped"),
        }
    }
}

/// One tool definition to load.
#[derive(Debug, Clone)]
pub struct Rom {
    /// The tool's name (the file stem).
    pub name: ToolName,
    /// The file's bytes, zero-padded to [`ROM_BYTES`].
    pub bytes: Vec<u8>,
}

/// Read and check a ROM file (at most [`ROM_BYTES`], never more read).
pub fn load_rom(path: &Path) -> Result<Rom, SourceError> {
    let err = |reason: String| SourceError::Rom {
        path: path.to_path_buf(),
        reason,
    };
    let meta = std::fs::metadata(path).map_err(|e| err(e.to_string()))?;
    if !meta.is_file() {
        return Err(err("is not a regular file".into()));
    }
    if meta.len() == 0 || meta.len() > ROM_BYTES as u64 {
        return Err(err(format!(
            "is {} bytes; an NDI tool definition has 1..={ROM_BYTES}",
            meta.len()
        )));
    }
    let mut bytes = Vec::with_capacity(ROM_BYTES);
    std::fs::File::open(path)
        .and_then(|f| f.take(ROM_BYTES as u64).read_to_end(&mut bytes))
        .map_err(|e| err(e.to_string()))?;
    bytes.resize(ROM_BYTES, 0);
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .ok_or_else(|| err("has no usable file name to name the tool by".into()))?;
    let name = ToolName::new(stem).map_err(|e| err(e.to_string()))?;
    Ok(Rom { name, bytes })
}

/// The polling state of [`Session::track`].
struct Polling {
    use_tx: bool,
    matcher: ReplyMatcher,
}

struct Session<'a> {
    link: &'a mut dyn Link,
    reader: ReplyReader,
    /// Replies framed but not taken yet, each with the time its last bytes arrived.
    ready: std::collections::VecDeque<(RawReply, u64)>,
    feed: &'a Feed,
    skipped_reported: u64,
    names: Box<[Option<ToolName>; 256]>,
    last_system: Option<u16>,
}

impl<'a> Session<'a> {
    fn new(link: &'a mut dyn Link, feed: &'a Feed) -> Self {
        Session {
            link,
            reader: ReplyReader::new(),
            ready: Default::default(),
            feed,
            skipped_reported: 0,
            names: Box::new([None; 256]),
            last_system: None,
        }
    }

    fn report_garbage(&mut self) {
        let skipped = self.reader.skipped_bytes();
        if skipped > self.skipped_reported {
            let n = skipped - self.skipped_reported;
            self.skipped_reported = skipped;
            self.feed.event(Event::rejected(
                Reject::Garbage,
                1,
                format!("{n} bytes between replies skipped"),
            ));
        }
    }

    /// The next reply and when its bytes arrived (CLOCK_MONOTONIC ns, taken as the read returns),
    /// waiting at most `timeout`.
    fn reply(&mut self, what: &str, timeout: Duration) -> Result<(RawReply, u64), SessionError> {
        let until = Instant::now() + timeout;
        let mut buf = [0u8; 4096];
        loop {
            if let Some(r) = self.ready.pop_front() {
                return Ok(r);
            }
            if self.feed.stopping() {
                return Err(SessionError::Stopped);
            }
            let now = Instant::now();
            if now >= until {
                return Err(SessionError::Timeout(what.to_string()));
            }
            self.link
                .set_timeout(
                    (until - now)
                        .min(Duration::from_millis(50))
                        .max(Duration::from_millis(1)),
                )
                .map_err(SessionError::Io)?;
            match self.link.recv(&mut buf) {
                Ok(n) => {
                    let receive_ns = now_ns();
                    let replies = self.reader.push(buf.get(..n).unwrap_or(&[]));
                    self.ready
                        .extend(replies.into_iter().map(|r| (r, receive_ns)));
                    self.report_garbage();
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(SessionError::Io(e)),
            }
        }
    }

    fn send(&mut self, cmd: &Command) -> Result<String, SessionError> {
        let bytes = cmd
            .encode()
            .map_err(|e| SessionError::Ndi(cmd.name().to_string(), e))?;
        self.link.send(&bytes).map_err(SessionError::Io)?;
        Ok(cmd.name().to_string())
    }

    /// Send `cmd` (after dropping any stale input) and read its ASCII reply.
    fn ascii(&mut self, cmd: &Command, timeout: Duration) -> Result<AsciiReply, SessionError> {
        self.ready.clear();
        self.link.discard_input();
        let name = self.send(cmd)?;
        let (r, _) = self.reply(&name, timeout)?;
        ndi::parse_ascii_reply(r.bytes()).map_err(|e| SessionError::Ndi(name, e))
    }

    fn expect_ok(&mut self, cmd: &Command, timeout: Duration) -> Result<(), SessionError> {
        let name = cmd.name().to_string();
        match self.ascii(cmd, timeout)? {
            r if r.is_success() => Ok(()),
            other => Err(SessionError::Ndi(
                name,
                NdiError::UnexpectedReply {
                    expected: "OKAY",
                    got: format!("{other:?}"),
                },
            )),
        }
    }

    fn phsr(&mut self, filter: PhsrFilter) -> Result<Vec<ndi::PhsrEntry>, SessionError> {
        self.ready.clear();
        self.link.discard_input();
        let name = self.send(&Command::Phsr(filter))?;
        let (r, _) = self.reply(&name, Duration::from_secs(1))?;
        ndi::parse_phsr_reply(r.bytes()).map_err(|e| SessionError::Ndi(name, e))
    }

    fn init(&mut self) -> Result<(), SessionError> {
        if self.link.is_serial() {
            self.link.set_baud(9600).map_err(SessionError::Io)?;
            if self
                .expect_ok(&Command::Init, Duration::from_secs(1))
                .is_err()
            {
                self.feed.event(Event::new(
                    EventKind::Note,
                    0,
                    "no OKAY to INIT at 9600 baud: resetting the tracker with a serial break",
                ));
                self.link
                    .send_break(Duration::from_millis(500))
                    .map_err(SessionError::Io)?;
                self.reader.clear();
                self.ready.clear();
                let until = Instant::now() + Duration::from_secs(5);
                loop {
                    let left = until.saturating_duration_since(Instant::now());
                    let (r, _) = self.reply("a serial break (RESET)", left)?;
                    if matches!(ndi::parse_ascii_reply(r.bytes()), Ok(AsciiReply::Reset)) {
                        break;
                    }
                }
                std::thread::sleep(Duration::from_millis(100));
                self.expect_ok(&Command::Init, Duration::from_secs(5))?;
            }
            self.expect_ok(
                &Command::Comm(CommSettings::new_8n1(Baud::B115200)),
                Duration::from_secs(1),
            )?;
            std::thread::sleep(Duration::from_millis(100));
            self.link.set_baud(115_200).map_err(SessionError::Io)?;
            std::thread::sleep(Duration::from_millis(100));
        } else {
            self.expect_ok(&Command::Init, Duration::from_secs(6))?;
        }
        Ok(())
    }

    fn tools(&mut self, roms: &[Rom]) -> Result<(), SessionError> {
        for e in self.phsr(PhsrFilter::ToBeFreed)? {
            self.expect_ok(&Command::Phf(e.handle), Duration::from_secs(1))?;
        }
        for rom in roms {
            let reply = self.ascii(
                &Command::Raw("PHRQ:*********1****".into()),
                Duration::from_secs(1),
            )?;
            let AsciiReply::Data(text) = reply else {
                return Err(SessionError::Timeout(
                    "PHRQ (no handle in the reply)".into(),
                ));
            };
            let handle = u8::from_str_radix(text.trim(), 16)
                .ok()
                .filter(|&h| h != 0 && text.trim().len() == 2)
                .ok_or_else(|| {
                    SessionError::Timeout(format!("PHRQ (reply {text:?} is not a handle)"))
                })?;
            for (k, chunk) in rom.bytes.chunks(64).enumerate() {
                let hex: String = chunk.iter().map(|b| format!("{b:02X}")).collect();
                let cmd = Command::Raw(format!("PVWR:{handle:02X}{:04X}{hex}", k * 64));
                self.expect_ok(&cmd, Duration::from_secs(1))?;
            }
            self.names[usize::from(handle)] = Some(rom.name);
        }
        for _ in 0..5 {
            let pending = self.phsr(PhsrFilter::NeedInit)?;
            if pending.is_empty() {
                break;
            }
            for e in pending {
                if let Err(err) = self.expect_ok(&Command::Pinit(e.handle), Duration::from_secs(3))
                {
                    self.feed.event(Event::new(
                        EventKind::Note,
                        u32::from(e.handle),
                        format!("port handle {:02X} did not initialise: {err}", e.handle),
                    ));
                }
            }
        }
        for e in self.phsr(PhsrFilter::NeedEnable)? {
            self.expect_ok(
                &Command::Pena {
                    handle: e.handle,
                    priority: TrackingPriority::Dynamic,
                },
                Duration::from_secs(1),
            )?;
        }
        let enabled = self.phsr(PhsrFilter::Enabled).unwrap_or_default();
        let names: Vec<String> = enabled
            .iter()
            .map(|e| self.name(e.handle).to_string())
            .collect();
        self.feed.event(Event::new(
            EventKind::Note,
            enabled.len() as u32,
            format!(
                "NDI tools enabled: {}",
                if names.is_empty() {
                    "none".into()
                } else {
                    names.join(", ")
                }
            ),
        ));
        Ok(())
    }

    fn name(&self, handle: u8) -> ToolName {
        self.names[usize::from(handle)].unwrap_or_else(|| {
            let hex = [
                b"0123456789ABCDEF"[usize::from(handle >> 4)],
                b"0123456789ABCDEF"[usize::from(handle & 15)],
            ];
            ToolName::from_bytes_lossy(&hex)
        })
    }

    fn sample(&self, t: &ToolSample, receive_ns: u64) -> Sample {
        sample_of(t, self.name(t.handle), receive_ns)
    }

    /// Poll until stopped or the link is lost; `Ok` means asked to stop.
    ///
    /// One poll is sent per slot of the schedule and waited for until its reply or
    /// [`POLL_TIMEOUT`]; between polls the link is still read, and every reply received is matched
    /// before the next poll is sent, so a duplicate or late reply is matched (and dropped) when it
    /// arrives instead of being taken as the next poll's answer.
    fn track(&mut self, roms: &[Rom], use_tx: bool, poll_hz: f64) -> Result<(), SessionError> {
        let period = Duration::from_secs_f64(1.0 / poll_hz);
        let mut next = Instant::now();
        let mut timeouts = 0u32;
        let mut poll = Polling {
            use_tx,
            matcher: ReplyMatcher::default(),
        };
        loop {
            if self.feed.stopping() {
                return Ok(());
            }
            // Until the next slot: take what arrives (nothing is owed, so only duplicates or
            // replies to a poll that timed out can come); the last moment is slept precisely.
            loop {
                let left = next.saturating_duration_since(Instant::now());
                if left < Duration::from_millis(2) {
                    std::thread::sleep(left);
                    break;
                }
                match self.reply("", left - Duration::from_millis(1)) {
                    Ok((r, at)) => self.handle(&r, at, &mut poll, roms)?,
                    Err(SessionError::Timeout(_)) => {}
                    Err(e) => return Err(e),
                }
            }
            next += period;
            if next + period < Instant::now() {
                next = Instant::now() + period;
            }
            // Replies already received cannot answer the poll about to be sent: match them now. A
            // duplicate read together with its first copy stays queued, and when the slot was
            // already due (a bridge behind its schedule on a loaded machine, or polling faster than
            // the wait above can read) it was taken as the next poll's answer, a repeated frame.
            while let Some((r, at)) = self.ready.pop_front() {
                self.handle(&r, at, &mut poll, roms)?;
            }
            let cmd = if poll.use_tx {
                Command::Tx(POLL_OPTIONS)
            } else {
                Command::Bx(POLL_OPTIONS)
            };
            let name = self.send(&cmd)?;
            poll.matcher.sent();
            let deadline = Instant::now() + POLL_TIMEOUT;
            loop {
                let left = deadline.saturating_duration_since(Instant::now());
                match self.reply(&name, left) {
                    Ok((r, at)) => {
                        self.handle(&r, at, &mut poll, roms)?;
                        if poll.matcher.owed() == 0 {
                            timeouts = 0;
                            break;
                        }
                    }
                    Err(SessionError::Timeout(_)) => {
                        timeouts += 1;
                        poll.matcher.timed_out();
                        self.feed.event(Event::rejected(
                            Reject::Timeout,
                            1,
                            format!("no reply to {name} within {} ms", POLL_TIMEOUT.as_millis()),
                        ));
                        if timeouts >= MAX_TIMEOUTS {
                            return Err(SessionError::Timeout(format!(
                                "{MAX_TIMEOUTS} polls in a row"
                            )));
                        }
                        break;
                    }
                    Err(e) => return Err(e),
                }
            }
        }
    }

    /// One reply to a poll, received at `receive_ns`: parsed, matched to its poll, and its samples
    /// handed over (or it is dropped and counted).
    fn handle(
        &mut self,
        reply: &RawReply,
        receive_ns: u64,
        poll: &mut Polling,
        roms: &[Rom],
    ) -> Result<(), SessionError> {
        let name = if poll.use_tx { "TX" } else { "BX" };
        let parsed = match reply {
            RawReply::Binary(b) => ndi::parse_bx_reply(b, POLL_OPTIONS),
            RawReply::Ascii(b) if poll.use_tx => ndi::parse_tx_reply(b, POLL_OPTIONS),
            RawReply::Ascii(b) => match ndi::parse_ascii_reply(b) {
                Err(NdiError::Device { code: 0x01, .. }) => {
                    poll.matcher.reply(None);
                    poll.use_tx = true;
                    self.feed.event(Event::new(
                        EventKind::Note,
                        0,
                        "the tracker does not know BX: polling with TX from now on",
                    ));
                    return Ok(());
                }
                Err(e) => Err(e),
                Ok(other) => Err(NdiError::UnexpectedReply {
                    expected: "tracking data",
                    got: format!("{other:?}"),
                }),
            },
        };
        let r = match parsed {
            Ok(r) => r,
            Err(e) => {
                poll.matcher.reply(None);
                let reason = match e {
                    NdiError::Crc { .. } => Reject::Crc,
                    NdiError::Device { .. } => Reject::DeviceError,
                    _ => Reject::Malformed,
                };
                self.feed
                    .event(Event::rejected(reason, 1, format!("{name} reply: {e}")));
                return Ok(());
            }
        };
        let frame = r.tools.iter().map(|t| t.frame).max();
        let (verdict, stale) = poll.matcher.reply(frame);
        let dropped = stale + u64::from(verdict != Verdict::Use);
        if dropped > 0 {
            self.feed.event(Event::rejected(
                Reject::StaleReply,
                dropped as u32,
                match verdict {
                    Verdict::Late => format!(
                        "a {name} reply that answered an earlier poll (it came late) was dropped"
                    ),
                    _ => format!(
                        "a {name} reply nobody asked for (the tracker answered twice) was dropped"
                    ),
                },
            ));
        }
        if verdict != Verdict::Use {
            return Ok(());
        }
        {
            let _batch = self.feed.batch();
            for t in &r.tools {
                self.feed.send(Input::Sample(self.sample(t, receive_ns)));
            }
        }
        let raw = r.system_status.raw;
        if self.last_system != Some(raw) && (raw != 0 || self.last_system.is_some()) {
            self.feed.event(Event::new(
                EventKind::DeviceStatus,
                u32::from(raw),
                format!("NDI system status {raw:04X}"),
            ));
        }
        self.last_system = Some(raw);
        if r.system_status.port_occupied {
            self.feed.event(Event::new(
                EventKind::Note,
                0,
                "a tool was plugged in: setting up the tools again",
            ));
            self.expect_ok(&Command::Tstop, Duration::from_secs(1))?;
            self.tools(roms)?;
            self.expect_ok(&Command::Tstart, Duration::from_secs(2))?;
            poll.matcher.reset();
        }
        Ok(())
    }

    fn shutdown(&mut self) {
        let _ = self.expect_ok(&Command::Tstop, Duration::from_millis(500));
        if self.link.is_serial()
            && self
                .expect_ok(
                    &Command::Comm(CommSettings::POWER_ON),
                    Duration::from_millis(500),
                )
                .is_ok()
        {
            std::thread::sleep(Duration::from_millis(100));
            let _ = self.link.set_baud(9600);
        }
    }
}

fn session(
    link: &mut dyn Link,
    feed: &Feed,
    roms: &[Rom],
    use_tx: bool,
    poll_hz: f64,
) -> Result<(), SessionError> {
    let mut s = Session::new(link, feed);
    s.init()?;
    s.tools(roms)?;
    s.expect_ok(&Command::Tstart, Duration::from_secs(2))?;
    feed.event(Event::new(EventKind::Note, 0, "NDI tracking started"));
    let r = s.track(roms, use_tx, poll_hz);
    if matches!(r, Ok(()) | Err(SessionError::Stopped)) {
        s.shutdown();
    }
    r
}

/// The sample of one tool of a `BX`/`TX` reply: handle status and port status become device flags
/// (see the module docs), the per-handle frame number the device frame, NDI's `[q0, qx, qy, qz]`
/// the `[x, y, z, w]` quaternion.
pub fn sample_of(t: &ToolSample, name: ToolName, receive_ns: u64) -> Sample {
    let p = &t.port_status;
    let mut flags = 0;
    let has_pose = t.has_pose();
    if !has_pose {
        flags |= tool_status::MISSING;
    }
    if p.out_of_volume {
        flags |= tool_status::OUT_OF_VOLUME;
    }
    if p.partially_out_of_volume {
        flags |= tool_status::PARTIALLY_VISIBLE;
    }
    if p.sensor_broken || p.hardware_failure || p.processing_exception {
        flags |= tool_status::DEVICE_FAULT;
    }
    let [w, x, y, z] = t.quat;
    Sample {
        receive_ns,
        device_time_ns: 0,
        device_frame: (t.frame != 0 || has_pose).then_some(u64::from(t.frame)),
        name,
        tool_id: u32::from(t.handle),
        rotation: if has_pose {
            Rotation::Quat([x, y, z, w])
        } else {
            Rotation::None
        },
        translation_mm: if has_pose { t.translation_mm } else { [0.0; 3] },
        rms_error_mm: has_pose.then_some(t.rms_error_mm),
        device_flags: flags,
    }
}

/// How to open the link, again after each loss.
#[derive(Debug, Clone)]
enum Target {
    Serial(String),
    Tcp(String, u16),
}

impl Target {
    fn open(&self) -> Result<Box<dyn Link>, String> {
        match self {
            Target::Serial(p) => SerialLink::open(p)
                .map(|l| Box::new(l) as Box<dyn Link>)
                .map_err(|e| format!("cannot open {p}: {e}")),
            Target::Tcp(h, port) => TcpLink::connect(h, *port)
                .map(|l| Box::new(l) as Box<dyn Link>)
                .map_err(|e| format!("cannot connect to {h}:{port}: {e}")),
        }
    }

    fn describe(&self) -> String {
        match self {
            Target::Serial(p) => format!("NDI tracker on serial port {p}"),
            Target::Tcp(h, p) => format!("NDI tracker at {h}:{p}"),
        }
    }
}

fn link_thread(target: &Target, feed: &Feed, roms: &[Rom], use_tx: bool, poll_hz: f64) {
    let mut backoff = Backoff::default();
    while !feed.stopping() {
        match target.open() {
            Ok(mut link) => {
                feed.event(Event::new(
                    EventKind::Connected,
                    0,
                    format!("opened {}", target.describe()),
                ));
                match session(link.as_mut(), feed, roms, use_tx, poll_hz) {
                    Ok(()) | Err(SessionError::Stopped) => return,
                    Err(e) => {
                        feed.event(Event::new(
                            EventKind::Disconnected,
                            0,
                            format!("{}: {e}", target.describe()),
                        ));
                    }
                }
                let d = backoff.next_delay();
                if !feed.sleep(d) {
                    return;
                }
            }
            Err(why) => {
                let d = backoff.next_delay();
                feed.event(Event::new(
                    EventKind::Retrying,
                    d.as_millis() as u32,
                    format!("{why}; retrying in {} ms", d.as_millis()),
                ));
                if !feed.sleep(d) {
                    return;
                }
            }
        }
    }
}

/// The NDI source (serial or TCP).
#[derive(Debug)]
pub struct NdiSource {
    inbox: Inbox,
    what: String,
}

impl NdiSource {
    fn start(target: Target, options: &SourceOptions) -> Result<Self, SourceError> {
        let roms = options
            .ndi_roms
            .iter()
            .map(|p| load_rom(p))
            .collect::<Result<Vec<_>, _>>()?;
        if !(options.ndi_poll_hz.is_finite() && (1.0..=1000.0).contains(&options.ndi_poll_hz)) {
            return Err(SourceError::Option(format!(
                "--ndi-poll-hz {} must be within 1..1000",
                options.ndi_poll_hz
            )));
        }
        let mut inbox = Inbox::new();
        let feed = inbox.feed();
        let what = target.describe();
        let (use_tx, hz) = (options.ndi_tx, options.ndi_poll_hz);
        let t = std::thread::Builder::new()
            .name("ndi-link".into())
            .spawn(move || link_thread(&target, &feed, &roms, use_tx, hz))
            .expect("spawning a thread");
        inbox.adopt(t);
        Ok(NdiSource { inbox, what })
    }

    /// A tracker on the serial device `path`.
    pub fn serial(path: &str, options: &SourceOptions) -> Result<Self, SourceError> {
        Self::start(Target::Serial(path.to_string()), options)
    }

    /// A tracker at `host:port` over TCP.
    pub fn tcp(host: &str, port: u16, options: &SourceOptions) -> Result<Self, SourceError> {
        Self::start(Target::Tcp(host.to_string(), port), options)
    }
}

impl Source for NdiSource {
    fn describe(&self) -> String {
        self.what.clone()
    }

    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        self.inbox.drain(sink);
        Ok(Poll::Tick { at_ns: now_ns })
    }

    fn wait(&mut self, _pace: &dyn transport::Clock, deadline_ns: u64) -> bool {
        // A reader thread on the host's clock: publish on arrival.
        self.inbox.wait(deadline_ns)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use Verdict::{Late, Unsolicited, Use};

    #[test]
    fn a_tracker_that_answers_twice_has_every_second_reply_dropped() {
        let mut m = ReplyMatcher::default();
        for f in 1..=50u32 {
            m.sent();
            assert_eq!(m.reply(Some(f)), (Use, 0));
            assert_eq!(m.owed(), 0);
            assert_eq!(m.reply(Some(f)), (Unsolicited, 0), "the copy of frame {f}");
        }
    }

    #[test]
    fn a_copy_taken_for_the_next_answer_is_counted_when_the_real_answer_follows() {
        let mut m = ReplyMatcher::default();
        m.sent();
        assert_eq!(m.reply(Some(1)), (Use, 0));
        m.sent();
        // The copy of frame 1 arrives after the next poll went out: it looks like the answer
        // (the same pose again; the assembler flags it a repeat) ...
        assert_eq!(m.reply(Some(1)), (Use, 0));
        // ... and the real answer, newer, is used too, the copy counted as stale.
        assert_eq!(m.reply(Some(2)), (Use, 1));
        m.sent();
        assert_eq!(m.reply(Some(3)), (Use, 0));
    }

    #[test]
    fn a_late_reply_is_dropped_when_the_next_polls_reply_follows_it() {
        let mut m = ReplyMatcher::default();
        m.sent();
        assert_eq!(m.reply(Some(10)), (Use, 0));
        m.sent();
        m.timed_out(); // frame 11 is 300 ms late
        m.sent();
        assert_eq!(m.reply(Some(11)), (Late, 0));
        assert_eq!(m.reply(Some(12)), (Use, 0));
        assert_eq!(m.owed(), 0);
        m.sent();
        assert_eq!(m.reply(Some(13)), (Use, 0), "back in step");
    }

    #[test]
    fn a_lost_reply_does_not_shift_every_later_reply() {
        let mut m = ReplyMatcher::default();
        m.sent();
        m.timed_out(); // never answered
        m.sent();
        assert_eq!(m.reply(Some(5)), (Late, 0), "taken for the lost poll's");
        m.timed_out(); // a second timeout in a row: the polls are taken as lost
        m.sent();
        assert_eq!(m.reply(Some(6)), (Use, 0));
        m.sent();
        assert_eq!(m.reply(Some(7)), (Use, 0));
    }

    #[test]
    fn a_tracker_polled_faster_than_its_camera_repeats_frames_and_is_not_dropped() {
        let mut m = ReplyMatcher::default();
        for f in [1u32, 1, 2, 2, 3] {
            m.sent();
            assert_eq!(m.reply(Some(f)).0, Use);
        }
        // Error replies and bad CRCs answer their poll without a frame.
        m.sent();
        assert_eq!(m.reply(None), (Use, 0));
        assert_eq!(m.owed(), 0);
        // A frame counter that wraps is still newer.
        let mut w = ReplyMatcher::default();
        w.sent();
        w.reply(Some(u32::MAX));
        assert_eq!(w.reply(Some(0)), (Use, 0), "unasked but newer");
        assert_eq!(w.reply(Some(u32::MAX)), (Unsolicited, 0));
    }
}
