//! Where samples come from: one module per source, all behind the [`Source`] trait, chosen by a
//! URI-like argument ([`SourceSpec`]):
//!
//! | `--source` | module | what it is |
//! |---|---|---|
//! | `synthetic` | [`synthetic`] | the built-in supine patient and walking HMD |
//! | `igtl-client:HOST[:PORT]` | [`igtl_client`] | connects to a PLUS server or 3D Slicer (port 18944) |
//! | `igtl-server[:BIND[:PORT]]` | [`igtl_server`] | listens; several senders at once (0.0.0.0:18944) |
//! | `ndi-serial:/dev/ttyUSB0` | [`ndi_link`] | NDI Polaris/Aurora on a serial port |
//! | `ndi-tcp:HOST[:PORT]` | [`ndi_link`] | NDI Vega over TCP (port 8765) |
//! | `replay:FILE` | [`replay`] | a recording ([`crate::record`]), paced or as fast as possible |
//!
//! Network and serial sources run their link on a reader thread that decodes, reconnects with
//! back-off and hands [`Input`]s over a bounded queue ([`Inbox`]), each sample stamped with the
//! time its bytes arrived; the publishing loop ([`crate::run`]) waits on the queue and takes
//! whatever arrived as soon as it arrives. Samples are fixed-size,
//! so the queue never allocates after start-up; when it is full the newest input is dropped and
//! counted (`queue_full`).

pub mod igtl_client;
pub mod igtl_owners;
pub mod igtl_server;
pub mod ndi_link;
pub mod replay;
pub mod synthetic;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use thiserror::Error;

use crate::assemble::BridgeConfig;
use crate::sample::{Event, Input, Reject};

/// What the loop does with this tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Poll {
    /// Build and publish a frame, judging staleness at `at_ns` (the source's clock: now for a live
    /// source, the recorded tick time for a replay).
    Tick {
        /// Time of the tick, ns.
        at_ns: u64,
    },
    /// The source has nothing more (a replay reached its end): stop.
    End,
}

/// A tracker source.
pub trait Source {
    /// What it reads, for messages (`OpenIGTLink server on 0.0.0.0:18944`).
    fn describe(&self) -> String;

    /// Hand every input received since the previous call to `sink`, oldest first, without
    /// blocking; then say what this tick is.
    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError>;

    /// Wait until an input is waiting or `deadline_ns` (on `pace`'s clock) has passed; true when
    /// an input is waiting — the loop then takes it and publishes on arrival. Sources whose
    /// samples are made on the tick (synthetic, replay) sleep until the deadline and return false:
    /// they keep the absolute-deadline schedule.
    fn wait(&mut self, pace: &dyn transport::Clock, deadline_ns: u64) -> bool {
        pace.sleep_until(deadline_ns);
        false
    }

    /// False when the loop should not wait for its schedule (a replay as fast as possible).
    fn paced(&self) -> bool {
        true
    }

    /// The configuration a recording was made with (a replay assembles with it, so it reproduces
    /// the recorded frames whatever the command line says).
    fn recorded_config(&self) -> Option<&BridgeConfig> {
        None
    }

    /// The respiratory signal's block recorded with the tick the last `poll` returned (a replay
    /// of a recording made with a signal), taken once; the loop publishes it in place of the
    /// run's own signal.
    fn recorded_signal(&mut self) -> Option<ipc_types::SignalBlock> {
        None
    }
}

/// Why a source could not start or stopped.
#[derive(Debug, Error)]
pub enum SourceError {
    /// The `--source` text names no source.
    #[error(
        "--source {text:?}: {reason}; use synthetic, igtl-client:HOST[:PORT], \
         igtl-server[:BIND[:PORT]], ndi-serial:DEVICE, ndi-tcp:HOST[:PORT] or replay:FILE"
    )]
    BadSpec {
        /// What was given.
        text: String,
        /// What is wrong.
        reason: String,
    },
    /// A listening socket could not be opened.
    #[error("cannot listen on {addr}: {source} (is another bridge or Slicer using the port?)")]
    Bind {
        /// The address.
        addr: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// A ROM file for an NDI tool could not be used.
    #[error("NDI tool definition {path}: {reason}")]
    Rom {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The recording could not be read.
    #[error(transparent)]
    Recording(#[from] crate::record::RecordError),
    /// A source option is out of range.
    #[error("{0}")]
    Option(String),
}

/// Which source, parsed from `--source`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SourceSpec {
    /// The synthetic patient and HMD.
    Synthetic,
    /// OpenIGTLink client of `host:port`.
    IgtlClient {
        /// Host name or address.
        host: String,
        /// TCP port.
        port: u16,
    },
    /// OpenIGTLink server on `bind:port`.
    IgtlServer {
        /// Address to bind.
        bind: String,
        /// TCP port (0: any free port).
        port: u16,
    },
    /// NDI combined API on a serial device.
    NdiSerial {
        /// Device path.
        path: String,
    },
    /// NDI combined API over TCP.
    NdiTcp {
        /// Host name or address.
        host: String,
        /// TCP port.
        port: u16,
    },
    /// A recording.
    Replay {
        /// The file.
        path: PathBuf,
    },
}

fn host_port(text: &str, rest: &str, default_port: u16) -> Result<(String, u16), SourceError> {
    let bad = |reason: &str| SourceError::BadSpec {
        text: text.to_string(),
        reason: reason.to_string(),
    };
    let (host, port) = if let Some(r) = rest.strip_prefix('[') {
        let (h, after) = r
            .split_once(']')
            .ok_or_else(|| bad("unclosed [ in an IPv6 address"))?;
        match after.strip_prefix(':') {
            Some(p) => (h.to_string(), Some(p)),
            None if after.is_empty() => (h.to_string(), None),
            None => return Err(bad("unexpected text after ]")),
        }
    } else {
        match rest.rsplit_once(':') {
            Some((h, p)) if !h.contains(':') => (h.to_string(), Some(p)),
            Some(_) => return Err(bad("put an IPv6 address in brackets: [::1]:18944")),
            None => (rest.to_string(), None),
        }
    };
    let port = match port {
        Some(p) => p
            .parse::<u16>()
            .map_err(|_| bad(&format!("port {p:?} is not a number within 0..65535")))?,
        None => default_port,
    };
    Ok((host, port))
}

impl SourceSpec {
    /// Parse `--source`.
    pub fn parse(text: &str) -> Result<SourceSpec, SourceError> {
        let bad = |reason: &str| SourceError::BadSpec {
            text: text.to_string(),
            reason: reason.to_string(),
        };
        let t = text.trim();
        let (kind, rest) = t.split_once(':').unwrap_or((t, ""));
        match kind {
            "synthetic" if rest.is_empty() => Ok(SourceSpec::Synthetic),
            "igtl-client" => {
                if rest.is_empty() {
                    return Err(bad("name the server: igtl-client:HOST[:PORT]"));
                }
                let (host, port) = host_port(text, rest, crate::igtl::DEFAULT_PORT)?;
                if host.is_empty() || port == 0 {
                    return Err(bad("a client needs a host and a non-zero port"));
                }
                Ok(SourceSpec::IgtlClient { host, port })
            }
            "igtl-server" => {
                let (bind, port) = if rest.is_empty() {
                    ("0.0.0.0".to_string(), crate::igtl::DEFAULT_PORT)
                } else {
                    host_port(text, rest, crate::igtl::DEFAULT_PORT)?
                };
                let bind = if bind.is_empty() {
                    "0.0.0.0".to_string()
                } else {
                    bind
                };
                Ok(SourceSpec::IgtlServer { bind, port })
            }
            "ndi-serial" => {
                if rest.is_empty() {
                    return Err(bad("name the serial device: ndi-serial:/dev/ttyUSB0"));
                }
                Ok(SourceSpec::NdiSerial {
                    path: rest.to_string(),
                })
            }
            "ndi-tcp" => {
                if rest.is_empty() {
                    return Err(bad("name the tracker: ndi-tcp:HOST[:PORT]"));
                }
                let (host, port) = host_port(text, rest, crate::ndi::VEGA_TCP_PORT)?;
                if host.is_empty() || port == 0 {
                    return Err(bad("ndi-tcp needs a host and a non-zero port"));
                }
                Ok(SourceSpec::NdiTcp { host, port })
            }
            "replay" => {
                if rest.is_empty() {
                    return Err(bad("name the recording: replay:FILE"));
                }
                Ok(SourceSpec::Replay {
                    path: PathBuf::from(rest),
                })
            }
            _ => Err(bad("unknown source")),
        }
    }

    /// True for sources that measure in a tracker's frame (the default volume applies).
    pub fn is_device(&self) -> bool {
        !matches!(self, SourceSpec::Synthetic | SourceSpec::Replay { .. })
    }
}

/// Delay between connection attempts: 100 ms, doubling to 5 s; back to 100 ms after a
/// connection that delivered data.
#[derive(Debug, Clone, Copy)]
pub struct Backoff {
    next: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Backoff { next: Self::MIN }
    }
}

impl Backoff {
    /// First delay.
    pub const MIN: Duration = Duration::from_millis(100);
    /// Largest delay.
    pub const MAX: Duration = Duration::from_secs(5);

    /// The delay to wait now; the next one doubles.
    pub fn next_delay(&mut self) -> Duration {
        let d = self.next;
        self.next = (self.next * 2).min(Self::MAX);
        d
    }

    /// Start over (the link worked).
    pub fn reset(&mut self) {
        self.next = Self::MIN;
    }
}

/// Inputs waiting in the queue at most.
pub const QUEUE: usize = 4096;

/// The reader thread's end of the queue.
#[derive(Debug, Clone)]
pub struct Feed {
    tx: SyncSender<Input>,
    stop: Arc<AtomicBool>,
    dropped: Arc<AtomicU64>,
    /// Readers in the middle of handing over the inputs of one read ([`Feed::batch`]).
    busy: Arc<AtomicU32>,
}

/// While it lives, the inputs being sent belong together (the messages of one read, the tools of
/// one reply): the loop waits for the rest before it publishes, so they make one frame.
#[derive(Debug)]
pub struct Batch<'a>(&'a AtomicU32);

impl Drop for Batch<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Release);
    }
}

/// How long [`Inbox::drain`] waits at most for a reader to finish a batch.
pub const BATCH_WAIT: Duration = Duration::from_micros(100);

impl Feed {
    /// Hand one input to the loop; a full queue drops it (counted, reported as `queue_full`).
    pub fn send(&self, input: Input) {
        match self.tx.try_send(input) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Disconnected(_)) => self.stop.store(true, Ordering::Relaxed),
        }
    }

    /// Mark the inputs sent until the guard drops as one batch.
    pub fn batch(&self) -> Batch<'_> {
        self.busy.fetch_add(1, Ordering::Acquire);
        Batch(&self.busy)
    }

    /// An event.
    pub fn event(&self, e: Event) {
        self.send(Input::Event(e));
    }

    /// True once the source is being dropped: the thread should end.
    pub fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Sleep `d` in short steps; false when asked to stop meanwhile.
    pub fn sleep(&self, d: Duration) -> bool {
        let until = std::time::Instant::now() + d;
        while !self.stopping() {
            let now = std::time::Instant::now();
            if now >= until {
                return true;
            }
            std::thread::sleep((until - now).min(Duration::from_millis(20)));
        }
        false
    }
}

/// The loop's end of the queue; stops and joins the reader threads when dropped.
#[derive(Debug)]
pub struct Inbox {
    rx: Receiver<Input>,
    /// The input [`Inbox::wait`] took off the queue, handed over first by the next drain.
    held: Option<Input>,
    feed: Feed,
    threads: Vec<JoinHandle<()>>,
}

impl Inbox {
    /// A queue of [`QUEUE`] inputs.
    pub fn new() -> Self {
        let (tx, rx) = sync_channel(QUEUE);
        Inbox {
            rx,
            held: None,
            feed: Feed {
                tx,
                stop: Arc::new(AtomicBool::new(false)),
                dropped: Arc::new(AtomicU64::new(0)),
                busy: Arc::new(AtomicU32::new(0)),
            },
            threads: Vec::new(),
        }
    }

    /// A sending end for a reader thread.
    pub fn feed(&self) -> Feed {
        self.feed.clone()
    }

    /// Keep a thread to join on drop.
    pub fn adopt(&mut self, t: JoinHandle<()>) {
        self.threads.push(t);
    }

    /// Block until an input is queued or the monotonic clock reaches `deadline_ns`; true when one
    /// is (it stays queued for [`Inbox::drain`]).
    pub fn wait(&mut self, deadline_ns: u64) -> bool {
        if self.held.is_some() {
            return true;
        }
        let left = deadline_ns.saturating_sub(transport::now_ns());
        let got = if left == 0 {
            self.rx.try_recv().ok()
        } else {
            self.rx.recv_timeout(Duration::from_nanos(left)).ok()
        };
        self.held = got;
        self.held.is_some()
    }

    /// Everything queued, oldest first (bounded: at most what was queued when it started). A
    /// reader in the middle of a batch is given up to [`BATCH_WAIT`] to finish it first.
    pub fn drain(&mut self, sink: &mut dyn FnMut(&Input)) {
        if self.feed.busy.load(Ordering::Acquire) > 0 {
            let until = std::time::Instant::now() + BATCH_WAIT;
            while self.feed.busy.load(Ordering::Acquire) > 0 && std::time::Instant::now() < until {
                std::thread::yield_now();
            }
        }
        if let Some(i) = self.held.take() {
            sink(&i);
        }
        for _ in 0..QUEUE {
            match self.rx.try_recv() {
                Ok(i) => sink(&i),
                Err(_) => break,
            }
        }
        let lost = self.feed.dropped.swap(0, Ordering::Relaxed);
        if lost > 0 {
            sink(&Input::Event(Event::rejected(
                Reject::QueueFull,
                lost.min(u64::from(u32::MAX)) as u32,
                "the source produced inputs faster than the loop took them",
            )));
        }
    }
}

impl Default for Inbox {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for Inbox {
    fn drop(&mut self) {
        self.feed.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// Options of the sources beyond the URI (defaults suit PLUS, Slicer, pyigtl and a Polaris).
#[derive(Debug, Clone)]
pub struct SourceOptions {
    /// OpenIGTLink decoding limits.
    pub igtl_limits: crate::igtl::Limits,
    /// An OpenIGTLink connection with no message for this long is dropped.
    pub igtl_idle_timeout: Duration,
    /// Component order of pyigtl `POSITION` quaternions.
    pub pyigtl_quat_order: crate::igtl::QuatOrder,
    /// NDI passive tool definitions (ROM files) to load; the tool is named by the file stem.
    pub ndi_roms: Vec<PathBuf>,
    /// Poll NDI trackers with `TX` instead of `BX`.
    pub ndi_tx: bool,
    /// NDI polling rate, Hz.
    pub ndi_poll_hz: f64,
    /// Replay without waiting for the schedule.
    pub as_fast_as_possible: bool,
    /// The synthetic source's parameters.
    pub synthetic: crate::synthetic::Synthetic,
    /// The OpenIGTLink server's senders: loopback and these (`--igtl-allow`).
    pub igtl_allow: igtl_server::AllowList,
}

impl Default for SourceOptions {
    fn default() -> Self {
        SourceOptions {
            igtl_limits: crate::igtl::Limits::default(),
            igtl_idle_timeout: igtl_client::IDLE_TIMEOUT,
            pyigtl_quat_order: crate::igtl::QuatOrder::Xyzw,
            ndi_roms: Vec::new(),
            ndi_tx: false,
            ndi_poll_hz: 60.0,
            as_fast_as_possible: false,
            synthetic: crate::synthetic::Synthetic::default(),
            igtl_allow: igtl_server::AllowList::default(),
        }
    }
}

/// Open the source `spec` names (listening sockets are bound here, so a busy port fails at once;
/// connections to peers are made by the reader thread, with back-off).
pub fn open(spec: &SourceSpec, options: &SourceOptions) -> Result<Box<dyn Source>, SourceError> {
    Ok(match spec {
        SourceSpec::Synthetic => Box::new(synthetic::SyntheticSource::new(options.synthetic)),
        SourceSpec::IgtlClient { host, port } => {
            Box::new(igtl_client::IgtlClient::start(host.clone(), *port, options))
        }
        SourceSpec::IgtlServer { bind, port } => {
            Box::new(igtl_server::IgtlServer::bind(bind, *port, options)?)
        }
        SourceSpec::NdiSerial { path } => Box::new(ndi_link::NdiSource::serial(path, options)?),
        SourceSpec::NdiTcp { host, port } => {
            Box::new(ndi_link::NdiSource::tcp(host, *port, options)?)
        }
        SourceSpec::Replay { path } => {
            Box::new(replay::Replay::open(path, !options.as_fast_as_possible)?)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_uris_parse_with_their_default_ports() {
        assert_eq!(
            SourceSpec::parse("synthetic").unwrap(),
            SourceSpec::Synthetic
        );
        assert_eq!(
            SourceSpec::parse("igtl-client:plus.local").unwrap(),
            SourceSpec::IgtlClient {
                host: "plus.local".into(),
                port: 18944
            }
        );
        assert_eq!(
            SourceSpec::parse("igtl-client:10.0.0.2:18945").unwrap(),
            SourceSpec::IgtlClient {
                host: "10.0.0.2".into(),
                port: 18945
            }
        );
        assert_eq!(
            SourceSpec::parse("igtl-server:0.0.0.0:18944").unwrap(),
            SourceSpec::IgtlServer {
                bind: "0.0.0.0".into(),
                port: 18944
            }
        );
        assert_eq!(
            SourceSpec::parse("igtl-server").unwrap(),
            SourceSpec::IgtlServer {
                bind: "0.0.0.0".into(),
                port: 18944
            }
        );
        assert_eq!(
            SourceSpec::parse("igtl-server:127.0.0.1").unwrap(),
            SourceSpec::IgtlServer {
                bind: "127.0.0.1".into(),
                port: 18944
            }
        );
        assert_eq!(
            SourceSpec::parse("igtl-server:[::1]:5000").unwrap(),
            SourceSpec::IgtlServer {
                bind: "::1".into(),
                port: 5000
            }
        );
        assert_eq!(
            SourceSpec::parse("ndi-serial:/dev/ttyUSB0").unwrap(),
            SourceSpec::NdiSerial {
                path: "/dev/ttyUSB0".into()
            }
        );
        assert_eq!(
            SourceSpec::parse("ndi-tcp:vega").unwrap(),
            SourceSpec::NdiTcp {
                host: "vega".into(),
                port: 8765
            }
        );
        assert_eq!(
            SourceSpec::parse("replay:/tmp/a b.ldtr").unwrap(),
            SourceSpec::Replay {
                path: "/tmp/a b.ldtr".into()
            }
        );
        for bad in [
            "",
            "polaris",
            "synthetic:x",
            "igtl-client",
            "igtl-client:h:99999",
            "igtl-client:h:0",
            "ndi-tcp:",
            "replay:",
            "igtl-server:::1:5",
            "igtl-client:[::1",
        ] {
            let e = SourceSpec::parse(bad).unwrap_err().to_string();
            assert!(e.contains("use synthetic"), "{bad:?}: {e}");
        }
    }

    #[test]
    fn backoff_doubles_to_its_ceiling_and_resets() {
        let mut b = Backoff::default();
        let d: Vec<u64> = (0..8).map(|_| b.next_delay().as_millis() as u64).collect();
        assert_eq!(d, [100, 200, 400, 800, 1600, 3200, 5000, 5000]);
        b.reset();
        assert_eq!(b.next_delay().as_millis(), 100);
    }

    #[test]
    fn a_full_queue_drops_and_reports_how_many() {
        let mut inbox = Inbox::new();
        let feed = inbox.feed();
        for _ in 0..QUEUE + 5 {
            feed.event(Event::new(crate::sample::EventKind::Note, 0, ""));
        }
        let mut n = 0;
        let mut lost = 0;
        inbox.drain(&mut |i| match i {
            Input::Event(e) if e.reason == Some(Reject::QueueFull) => lost += e.value,
            _ => n += 1,
        });
        assert_eq!((n, lost), (QUEUE, 5));
    }
}
