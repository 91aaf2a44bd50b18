//! `lungdyn demo --igtl-serve [PORT]`: the breathing lungs sent to 3D Slicer over OpenIGTLink
//! (issue 38 item 1; docs/SLICER.md). lungdyn is the server Slicer's OpenIGTLinkIF connects to.
//!
//! `lungdyn demo --igtl-connect HOST:PORT` is the other way round: Slicer listens (its
//! OpenIGTLinkIF connector's default type, "Server", port 18944) and lungdyn connects to it, trying
//! again every second until it answers and after it goes.
//!
//! A thread of the launcher, not of the renderer: it subscribes to the engine's stream like any
//! other reader, and at `rate_hz` takes the newest frame, deforms each lung with the renderer's CPU
//! reference (`CpuLung`, the same `h + (1 − c)(p − h) + s·u + o` as `deform.wgsl`), and sends per
//! frame, all with one timestamp:
//!
//! * `POLYDATA` "RightLung" / "LeftLung": the whole mesh (Slicer builds a new model from each
//!   message, so the triangles go every time), points in the patient's RAS frame (mm; the body frame
//!   reflected, `lung_model::frame::BODY_TO_RAS`, and each triangle's corners reversed so that it
//!   stays outward), the lobe code per vertex as the point scalar "Lobe" where the kernel has lobes;
//! * `POLYDATA` "Tumour" (an ellipsoid at its centre) and `TRANSFORM` "TumourCentre" (a translation)
//!   when the scene has a tumour;
//! * `STRING` "BreathState": one JSON object — tick, time, the disease in words, each lung's volume,
//!   phase and collapse.
//!
//! Each client has one frame in flight: sockets are non-blocking, and a client that has not taken
//! the last frame when the next is due misses it (counted, never queued), so a slow Slicer cannot
//! grow memory or hold up anything. Nothing here touches the renderer's deadline except the CPU it
//! uses (measured in docs/SLICER.md). Clients from outside loopback are refused unless the
//! allow-list names them; with an allow-list the port is bound on every interface.

use std::fmt::Write as _;
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;
use ipc_types::{EngineFrame, LungFrame, NUM_LUNGS};
use lung_model::mesh::Side;
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use renderer::RenderLung;
use tracker_bridge::igtl::{Timestamp, Transform};
use tracker_bridge::igtl_polydata::{FixedMesh, PointScalars, Topology};
use tracker_bridge::igtl_send;
use tracker_bridge::source::igtl_server::AllowList;
use transport::{iox, Instance, Receive};

/// As a client, how often a server that is not there is tried, and how long one try waits.
pub const CONNECT_EVERY: Duration = Duration::from_secs(1);
/// (The try runs in the link's own thread.)
pub const CONNECT_WAIT: Duration = Duration::from_millis(250);
/// Clients served at once (a Slicer or two, a recorder); more are refused (closed, and the demo says
/// why).
pub const MAX_CLIENTS: usize = 4;
/// The device names, as Slicer shows its nodes.
pub const RIGHT_LUNG: &str = "RightLung";
/// The left lung's device name.
pub const LEFT_LUNG: &str = "LeftLung";
/// The tumour's mesh.
pub const TUMOUR: &str = "Tumour";
/// The tumour's centre as a translation.
pub const TUMOUR_CENTRE: &str = "TumourCentre";
/// The breath's state (JSON).
pub const BREATH_STATE: &str = "BreathState";
/// The lobe codes' point-scalar name.
pub const LOBE_SCALAR: &str = "Lobe";

/// What the link is asked to do (the scene's `[slicer]` with the command line over it).
#[derive(Debug, Clone)]
pub struct SlicerOptions {
    /// TCP port (served; unused when connecting).
    pub port: u16,
    /// Connect to Slicer's server here (HOST:PORT, as given) instead of serving.
    pub connect: Option<String>,
    /// Frames sent per second.
    pub rate_hz: f64,
    /// Clients besides loopback.
    pub allow: AllowList,
}

impl SlicerOptions {
    /// From the scene's `[slicer]` and the demo's `--igtl-serve[-rate|-allow]`; `None` when off.
    pub fn resolve(
        scene: &Scene,
        serve: Option<Option<u16>>,
        rate_hz: Option<f64>,
        allow: &[String],
        connect: Option<&str>,
    ) -> anyhow::Result<Option<Self>> {
        let s = &scene.slicer;
        let connect = connect.map(str::to_string).or_else(|| s.connect.clone());
        if connect.is_some() && (serve.is_some() || s.serve) {
            anyhow::bail!(
                "--igtl-connect (or [slicer] connect) and --igtl-serve (or [slicer] serve = true) \
                 both asked: lungdyn either listens for Slicer (Slicer's connector a client) or \
                 connects to it (Slicer's connector a server), give one"
            );
        }
        if connect.is_some() && !allow.is_empty() {
            anyhow::bail!(
                "--igtl-serve-allow names who may connect to lungdyn's server; with --igtl-connect \
                 lungdyn connects out, to the host it names"
            );
        }
        if serve.is_none() && !s.serve && connect.is_none() {
            if rate_hz.is_some() || !allow.is_empty() {
                anyhow::bail!(
                    "--igtl-serve-rate and --igtl-serve-allow need --igtl-serve or --igtl-connect \
                     (or [slicer] serve = true in the scene)"
                );
            }
            return Ok(None);
        }
        let port = serve.flatten().unwrap_or(s.port);
        if port == 0 {
            anyhow::bail!("--igtl-serve 0: name the port Slicer connects to (18945 by default)");
        }
        let rate_hz = rate_hz.unwrap_or(s.rate_hz);
        let max = lung_model::scene::slicer::MAX_RATE_HZ;
        if !(rate_hz.is_finite() && (1.0..=max).contains(&rate_hz)) {
            anyhow::bail!(
                "--igtl-serve-rate {rate_hz}: send 1 to {max} meshes per second (Slicer redraws \
                 comfortably at 30)"
            );
        }
        let allow = AllowList::parse_as(
            &[s.allow.clone(), allow.to_vec()].concat(),
            "--igtl-serve-allow",
        )
        .map_err(anyhow::Error::msg)?;
        Ok(Some(Self {
            port,
            connect,
            rate_hz,
            allow,
        }))
    }

    /// Where the link goes: the port bound ([`SlicerOptions::bind`]), or Slicer's server's address
    /// resolved — both before anything is baked or started, so a taken port or a host that does
    /// not resolve stops the demo at once.
    pub fn open(&self) -> anyhow::Result<Endpoint> {
        let Some(target) = &self.connect else {
            return self.bind().map(Endpoint::Listen);
        };
        use std::net::ToSocketAddrs as _;
        let addr = target
            .to_socket_addrs()
            .with_context(|| {
                format!(
                    "--igtl-connect {target}: give HOST:PORT of the computer running Slicer and its \
                     OpenIGTLinkIF server's port (18944 by default)"
                )
            })?
            .next()
            .with_context(|| format!("--igtl-connect {target}: the host has no address"))?;
        if addr.port() == 0 {
            anyhow::bail!(
                "--igtl-connect {target}: port 0; Slicer's server listens on 18944 by default"
            );
        }
        Ok(Endpoint::Connect(addr))
    }

    /// Listen (a taken port is an error here, before anything is baked or started).
    pub fn bind(&self) -> anyhow::Result<TcpListener> {
        let bind = self.bind_address();
        let first = TcpListener::bind((bind, self.port));
        // Every interface: dual-stack where the host has IPv6, else IPv4's.
        let (bind, listening) = match first {
            Err(_) if bind == "::" => ("0.0.0.0", TcpListener::bind(("0.0.0.0", self.port))),
            other => (bind, other),
        };
        listening.with_context(|| {
            format!(
                "--igtl-serve: cannot listen on {bind} port {} (another program, or another lungdyn, \
                 has it? 18944 is the tracker's OpenIGTLink port; give another with --igtl-serve PORT)",
                self.port
            )
        })
    }

    /// Loopback only, or every interface (`::`, IPv4 too) when the allow-list names other hosts.
    pub fn bind_address(&self) -> &'static str {
        if self.allow == AllowList::default() {
            "127.0.0.1"
        } else {
            "::"
        }
    }
}

/// Where the link goes ([`SlicerOptions::open`]).
#[derive(Debug)]
pub enum Endpoint {
    /// lungdyn serves on this port; Slicer connects.
    Listen(TcpListener),
    /// lungdyn connects to Slicer's server here.
    Connect(SocketAddr),
}

/// What the link did (the demo's report and JSON).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SlicerReport {
    /// "server" (lungdyn listened) or "client" (lungdyn connected to Slicer's server).
    pub role: String,
    /// The address it listened on, or connected to.
    pub address: String,
    /// Who may connect, in words.
    pub allowed: String,
    /// Frames per second asked for.
    pub rate_hz: f64,
    /// Clients that connected (refused ones not counted).
    pub clients: u64,
    /// Connections refused (not on the allow-list, or too many).
    pub refused: u64,
    /// As a client: tries that found no server listening (one a second while it is away).
    pub connect_failures: u64,
    /// Frames made (each sent to every client that had taken the one before; none is made while
    /// every client is still taking the last).
    pub frames: u64,
    /// Frames a client missed because it had not taken the previous one yet.
    pub dropped: u64,
    /// Bytes written to clients.
    pub bytes: u64,
    /// Clients closed because they took nothing for [`STALLED_AFTER`].
    pub stalled: u64,
    /// Frames that could not be made (skipped; the link went on).
    pub bad_frames: u64,
    /// Why the first of them could not.
    pub first_bad_frame: Option<String>,
    /// Bytes of one frame (meshes, tumour, state), the last made.
    pub frame_bytes: u64,
    /// CPU time (the thread's own) to make one frame (deform, encode, CRC), ms: median, 99th
    /// percentile, largest.
    pub make_ms_p50: f64,
    /// 99th percentile.
    pub make_ms_p99: f64,
    /// Largest.
    pub make_ms_max: f64,
    /// Seconds it ran.
    pub seconds: f64,
    /// Why it stopped early, if it did (the demo goes on without it).
    pub failure: Option<String>,
}

impl SlicerReport {
    /// MB per second to all clients together.
    pub fn mb_per_s(&self) -> f64 {
        if self.seconds > 0.0 {
            self.bytes as f64 / 1e6 / self.seconds
        } else {
            0.0
        }
    }

    /// One paragraph for the demo's summary.
    pub fn text(&self) -> String {
        let on = if self.role == "client" {
            "to Slicer's server at"
        } else {
            "on"
        };
        let mut s = format!(
            "Slicer (OpenIGTLink {on} {}, {} Hz): {} client(s), {} frame(s) made, {} missed by a slow \
             client, {:.1} MB/s ({:.2} MB a frame); making a frame took {:.2} ms of CPU median, {:.2} ms \
             p99, {:.2} ms at most",
            self.address,
            self.rate_hz,
            self.clients,
            self.frames,
            self.dropped,
            self.mb_per_s(),
            self.frame_bytes as f64 / 1e6,
            self.make_ms_p50,
            self.make_ms_p99,
            self.make_ms_max
        );
        if self.refused > 0 {
            let _ = write!(s, "; {} connection(s) refused", self.refused);
        }
        if self.connect_failures > 0 {
            let _ = write!(
                s,
                "; {} connection tries found no server",
                self.connect_failures
            );
        }
        if let Some(f) = &self.failure {
            let _ = write!(s, "; STOPPED: {f}");
        }
        s
    }
}

/// The running server: [`SlicerServer::stop`] ends it and returns its report.
pub struct SlicerServer {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<SlicerReport>>,
    address: SocketAddr,
}

impl SlicerServer {
    /// Load the lungs of the prepared `scene` and start serving `instance`'s engine stream on
    /// `listener` ([`SlicerOptions::bind`]).
    pub fn start(
        instance: &str,
        scene: &Scene,
        options: &SlicerOptions,
        endpoint: Endpoint,
    ) -> anyhow::Result<Self> {
        let (listener, target, address) = match endpoint {
            Endpoint::Listen(listener) => {
                listener.set_nonblocking(true)?;
                let address = listener.local_addr()?;
                (Some(listener), None, address)
            }
            Endpoint::Connect(addr) => (None, Some(addr), addr),
        };
        let frame = FrameMaker::new(scene)?;
        let stop = Arc::new(AtomicBool::new(false));
        let role = if target.is_some() { "client" } else { "server" };
        let report = SlicerReport {
            role: role.to_string(),
            address: address.to_string(),
            allowed: if target.is_some() {
                "none (lungdyn connects out)".to_string()
            } else {
                options.allow.describe()
            },
            rate_hz: options.rate_hz,
            ..SlicerReport::default()
        };
        let (name, opts, flag) = (instance.to_string(), options.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("igtl-serve".into())
            .spawn(move || {
                lower_priority();
                let started = Instant::now();
                let mut serve = match Serve::new(listener, target, opts, frame, report.clone()) {
                    Ok(s) => s,
                    Err(e) => {
                        eprintln!(
                            "lungdyn: the Slicer link did not start: {e:#} (the demo goes on)"
                        );
                        return SlicerReport {
                            failure: Some(format!("{e:#}")),
                            ..report
                        };
                    }
                };
                if let Err(e) = serve.run(&name, &flag) {
                    serve.report.failure = Some(format!("{e:#}"));
                    eprintln!("lungdyn: the Slicer link stopped: {e:#} (the demo goes on)");
                }
                serve.finish(started)
            })?;
        if target.is_some() {
            eprintln!(
                "lungdyn: sending the lungs to 3D Slicer's server at {address} at {} Hz (in Slicer: \
                 OpenIGTLinkIF, a connector of type Server on port {}, active; docs/SLICER.md); \
                 trying every second until it answers",
                options.rate_hz,
                address.port()
            );
        } else {
            eprintln!(
                "lungdyn: serving the lungs to 3D Slicer on {address} at {} Hz (OpenIGTLinkIF: client, \
                 port {}; docs/SLICER.md); clients from {}",
                options.rate_hz,
                address.port(),
                options.allow.describe()
            );
        }
        Ok(Self {
            stop,
            thread: Some(thread),
            address,
        })
    }

    /// The address it listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Stop serving, close every connection, and report.
    pub fn stop(mut self) -> SlicerReport {
        self.stop.store(true, Ordering::Relaxed);
        let joined = self.thread.take().map(JoinHandle::join);
        match joined {
            Some(Ok(report)) => report,
            _ => SlicerReport {
                failure: Some("the Slicer thread panicked: a bug, please report it".into()),
                ..SlicerReport::default()
            },
        }
    }
}

/// A demo that fails before it stops the server still closes the port and its connections.
impl Drop for SlicerServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// One connected client: the bytes of its frame still to write.
struct Client {
    stream: TcpStream,
    peer: SocketAddr,
    pending: Vec<u8>,
    written: usize,
    /// When it last took bytes (or connected).
    progress: Instant,
}

impl Client {
    /// Still taking a frame: bytes of it not yet written, or written but still in this side's
    /// kernel queue (`SIOCOUTQ`: unsent or unacknowledged). The send buffer is held to about one
    /// frame, so at most one frame is ever between lungdyn and the client's own receive buffer.
    fn busy(&self) -> bool {
        self.written < self.pending.len() || unsent_bytes(&self.stream) > 0
    }
}

/// Bytes in the socket's send queue not yet acknowledged by the peer (0 where it cannot be asked).
fn unsent_bytes(stream: &TcpStream) -> usize {
    use std::os::fd::AsRawFd;
    let mut n: libc::c_int = 0;
    // SAFETY: TIOCOUTQ (SIOCOUTQ) on a TCP socket we own writes one int.
    let ok = unsafe { libc::ioctl(stream.as_raw_fd(), libc::TIOCOUTQ, &mut n) } == 0;
    if ok {
        n.max(0) as usize
    } else {
        0
    }
}

/// Holds the kernel's send buffer of `stream` to about `bytes` (Linux doubles what it is given).
fn limit_send_buffer(stream: &TcpStream, bytes: usize) {
    use std::os::fd::AsRawFd;
    let v = libc::c_int::try_from(bytes / 2).unwrap_or(libc::c_int::MAX);
    // SAFETY: SO_SNDBUF takes one int we own.
    unsafe {
        libc::setsockopt(
            stream.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_SNDBUF,
            (&v as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        );
    }
}

/// A client that has taken nothing for this long is closed (its place goes to another).
pub const STALLED_AFTER: Duration = Duration::from_secs(10);
/// Most bytes read from one client per pass (what a client sends is read and dropped).
const READ_PER_PASS: usize = 64 * 1024;
/// Refusals said one by one; after these, once, then only counted.
const REFUSALS_SAID: u64 = 10;

/// Why a connection from `ip` is refused when `clients` are served already (`None`: served).
pub fn refusal(allow: &AllowList, ip: std::net::IpAddr, clients: usize) -> Option<String> {
    if !allow.allows(ip) {
        Some(format!(
            "not on the allow-list ({}); admit it with --igtl-serve-allow {ip}",
            allow.describe()
        ))
    } else if clients >= MAX_CLIENTS {
        Some(format!("{MAX_CLIENTS} clients are served already"))
    } else {
        None
    }
}

struct Serve {
    /// Listening for Slicer, or (`target`) connecting to its server, retried at `next_try`.
    listener: Option<TcpListener>,
    target: Option<SocketAddr>,
    next_try: Instant,
    /// The server's absence said (once each time it goes).
    away_said: bool,
    options: SlicerOptions,
    clients: Vec<Client>,
    frame: FrameMaker,
    /// One worker at the link's priority: the deformation's parallel loops run here, not on the
    /// global pool's workers at normal priority, and its CPU time is this worker's.
    pool: rayon::ThreadPool,
    report: SlicerReport,
    make_us: hdrhistogram::Histogram<u64>,
    stalled_after: Duration,
}

impl Serve {
    fn new(
        listener: Option<TcpListener>,
        target: Option<SocketAddr>,
        options: SlicerOptions,
        frame: FrameMaker,
        report: SlicerReport,
    ) -> anyhow::Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .thread_name(|_| "igtl-deform".into())
            .start_handler(|_| lower_priority())
            .build()?;
        Ok(Self {
            listener,
            target,
            next_try: Instant::now(),
            away_said: false,
            options,
            clients: Vec::new(),
            frame,
            pool,
            report,
            make_us: hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3)?,
            stalled_after: STALLED_AFTER,
        })
    }

    fn run(&mut self, instance: &str, stop: &AtomicBool) -> anyhow::Result<()> {
        let services = Instance::new(instance)?;
        let node = iox::node(&services, "slicer")?;
        let mut engine = services.engine_inlet(&node)?;
        let period = Duration::from_secs_f64(1.0 / self.options.rate_hz);
        let mut next = Instant::now();
        let mut latest: Option<EngineFrame> = None;
        let mut sent_tick = None;
        let mut scratch = vec![0u8; 4096];
        while !stop.load(Ordering::Relaxed) && !transport::stop::requested() {
            self.accept();
            if let Some(f) = engine.take_latest()? {
                latest = Some(f);
            }
            let now = Instant::now();
            if now >= next {
                // Keep the rate's phase; after a long stall start again from now.
                next = if now - next > period {
                    now + period
                } else {
                    next + period
                };
                if let Some(f) = latest.as_ref().filter(|f| Some(f.tick) != sent_tick) {
                    if !self.clients.is_empty() {
                        self.send(f);
                        sent_tick = Some(f.tick);
                    }
                }
            }
            self.flush(&mut scratch);
            self.wait(next);
        }
        Ok(())
    }

    /// Sleep until `next`, a client can take more or sends something, or a new one knocks (at most
    /// 5 ms, so a stop request is seen soon).
    fn wait(&self, next: Instant) {
        use std::os::fd::AsRawFd;
        let idle = libc::pollfd {
            fd: -1,
            events: 0,
            revents: 0,
        };
        let mut fds = [idle; MAX_CLIENTS + 1];
        if let Some(listener) = &self.listener {
            fds[0] = libc::pollfd {
                fd: listener.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
        }
        for (slot, c) in fds[1..].iter_mut().zip(&self.clients) {
            let out = if c.written < c.pending.len() {
                libc::POLLOUT
            } else {
                0
            };
            *slot = libc::pollfd {
                fd: c.stream.as_raw_fd(),
                events: libc::POLLIN | out,
                revents: 0,
            };
        }
        let ms = next
            .saturating_duration_since(Instant::now())
            .min(Duration::from_millis(5))
            .as_millis() as libc::c_int;
        // SAFETY: pollfds we own, their count, a timeout in ms.
        unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, ms) };
    }

    fn accept(&mut self) {
        if let Some(addr) = self.target {
            self.connect(addr);
            return;
        }
        loop {
            let Some(accepted) = self.listener.as_ref().map(TcpListener::accept) else {
                return;
            };
            match accepted {
                Ok((stream, peer)) => {
                    if let Some(why) = refusal(&self.options.allow, peer.ip(), self.clients.len()) {
                        self.report.refused += 1;
                        if self.report.refused <= REFUSALS_SAID {
                            eprintln!("lungdyn: Slicer link: refused {peer}: {why}");
                        } else if self.report.refused == REFUSALS_SAID + 1 {
                            eprintln!(
                                "lungdyn: Slicer link: more connections refused; from now on only \
                                 counted (the report says how many)"
                            );
                        }
                        continue;
                    }
                    if self.add(stream, peer) {
                        eprintln!("lungdyn: Slicer link: {peer} connected");
                    }
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                // A connection reset before it was taken, out of descriptors: try again later.
                Err(_) => return,
            }
        }
    }

    /// A connection to serve (accepted, or made to Slicer's server); false when it cannot be set up.
    fn add(&mut self, stream: TcpStream, peer: SocketAddr) -> bool {
        if stream.set_nonblocking(true).is_err() {
            return false;
        }
        let _ = stream.set_nodelay(true);
        limit_send_buffer(&stream, self.frame.bytes.len().max(1 << 20));
        self.report.clients += 1;
        self.clients.push(Client {
            stream,
            peer,
            pending: Vec::new(),
            written: 0,
            progress: Instant::now(),
        });
        true
    }

    /// As a client: connect to Slicer's server at `addr` when not connected, at most once a
    /// second (the wait bounded to [`CONNECT_WAIT`], in this thread only); the first failure in a
    /// row is said, the rest counted.
    fn connect(&mut self, addr: SocketAddr) {
        let now = Instant::now();
        if !self.clients.is_empty() || now < self.next_try {
            return;
        }
        self.next_try = now + CONNECT_EVERY;
        match TcpStream::connect_timeout(&addr, CONNECT_WAIT) {
            Ok(stream) => {
                if self.add(stream, addr) {
                    self.away_said = false;
                    eprintln!("lungdyn: Slicer link: connected to Slicer's server at {addr}");
                }
            }
            Err(e) => {
                self.report.connect_failures += 1;
                if !self.away_said {
                    self.away_said = true;
                    eprintln!(
                        "lungdyn: Slicer link: no server at {addr} ({e}); trying every second (in \
                         Slicer: OpenIGTLinkIF, a connector of type Server on port {}, active)",
                        addr.port()
                    );
                }
            }
        }
    }

    /// Make frame `f` and hand it to every client that has taken the previous one. A frame that
    /// cannot be made (a lung the engine runs with another kernel, a non-finite vertex) is skipped
    /// and counted; the link goes on.
    fn send(&mut self, f: &EngineFrame) {
        // No client can take it: each misses it, and it is not made.
        if self.clients.iter().all(Client::busy) {
            self.report.dropped += self.clients.len() as u64;
            return;
        }
        let (pool, frame) = (&self.pool, &mut self.frame);
        let (made, cpu_ns) = pool.install(|| {
            let t0 = thread_cpu_ns();
            let made = frame.make(f);
            (made, thread_cpu_ns().saturating_sub(t0))
        });
        if let Err(e) = made {
            self.report.bad_frames += 1;
            if self.report.bad_frames == 1 {
                eprintln!(
                    "lungdyn: Slicer link: frame of tick {} not sent: {e:#}",
                    f.tick
                );
                self.report.first_bad_frame = Some(format!("tick {}: {e:#}", f.tick));
            }
            return;
        }
        let _ = self.make_us.record((cpu_ns / 1000).max(1));
        self.report.frames += 1;
        self.report.frame_bytes = self.frame.bytes.len() as u64;
        for c in &mut self.clients {
            if c.busy() {
                self.report.dropped += 1;
                continue;
            }
            c.pending.clear();
            c.pending.extend_from_slice(&self.frame.bytes);
            c.written = 0;
        }
    }

    /// Write what each client can take now; read and drop what it sends (Slicer's own messages,
    /// which are not asked for); close clients that closed, failed, or took nothing for
    /// [`STALLED_AFTER`].
    fn flush(&mut self, scratch: &mut [u8]) {
        let report = &mut self.report;
        let stalled_after = self.stalled_after;
        self.clients.retain_mut(|c| {
            let mut read = 0;
            while read < READ_PER_PASS {
                match c.stream.read(scratch) {
                    Ok(0) => {
                        eprintln!("lungdyn: Slicer link: {} disconnected", c.peer);
                        return false;
                    }
                    Ok(n) => read += n,
                    Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                    Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                    Err(e) => {
                        eprintln!("lungdyn: Slicer link: {} dropped: {e}", c.peer);
                        return false;
                    }
                }
            }
            while c.written < c.pending.len() {
                match c.stream.write(&c.pending[c.written..]) {
                    Ok(0) => return false,
                    Ok(n) => {
                        c.written += n;
                        c.progress = Instant::now();
                        report.bytes += n as u64;
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                    Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                    Err(e) => {
                        eprintln!("lungdyn: Slicer link: {} dropped: {e}", c.peer);
                        return false;
                    }
                }
            }
            if c.busy() && c.progress.elapsed() > stalled_after {
                report.stalled += 1;
                eprintln!(
                    "lungdyn: Slicer link: {} took nothing for {} s: closed",
                    c.peer,
                    stalled_after.as_secs()
                );
                return false;
            }
            if !c.busy() {
                c.progress = Instant::now();
            }
            true
        });
    }

    fn finish(mut self, started: Instant) -> SlicerReport {
        self.clients.clear();
        let h = &self.make_us;
        let ms = |us: u64| us as f64 / 1000.0;
        if !h.is_empty() {
            self.report.make_ms_p50 = ms(h.value_at_quantile(0.5));
            self.report.make_ms_p99 = ms(h.value_at_quantile(0.99));
            self.report.make_ms_max = ms(h.max());
        }
        self.report.seconds = (started.elapsed().as_secs_f64() * 1000.0).round() / 1000.0;
        self.report
    }
}

/// One lung as it is sent: its mesh's triangles (reversed, RAS) and lobe codes encoded and CRC'd
/// once, the deformed positions' buffer.
struct SentLung {
    lung: RenderLung,
    device: &'static str,
    mesh: FixedMesh,
    positions: Vec<[f32; 3]>,
}

/// The tumour as it is sent: the unit sphere scaled to its radii, moved to its centre each frame.
struct SentTumour {
    slot: usize,
    meta: lung_model::kernel::TumourMeta,
    shape: Vec<[f32; 3]>,
    mesh: FixedMesh,
    positions: Vec<[f32; 3]>,
}

/// Makes one frame's messages into a reused buffer.
pub struct FrameMaker {
    lungs: Vec<SentLung>,
    tumour: Option<SentTumour>,
    mode: lung_model::deform::modes::DeformMode,
    tick_hz: f64,
    disease: Option<(String, Option<usize>)>,
    disease_text: String,
    state: Vec<u8>,
    /// The frame's bytes: every message, back to back.
    pub bytes: Vec<u8>,
}

/// Body frame (+X left, +Y anterior, +Z superior; left-handed) → the patient's RAS frame:
/// `lung_model::frame::BODY_TO_RAS = diag(−1, 1, 1)`.
pub use lung_model::frame::body_to_ras_f32 as body_to_ras;

/// Triangles as Slicer gets them: corners reversed (the reflection to RAS turns a counter-clockwise
/// triangle clockwise; reversed, it faces outward again).
pub fn ras_triangles(triangles: &[[u32; 3]]) -> Vec<[u32; 3]> {
    triangles.iter().map(|&[a, b, c]| [a, c, b]).collect()
}

impl FrameMaker {
    /// The lungs (and tumour) of the prepared `scene`, read from their kernels.
    pub fn new(scene: &Scene) -> anyhow::Result<Self> {
        let mut lungs = Vec::new();
        for &side in &scene.lungs.sides {
            let kernel = scene.lung_kernel(side)?;
            let lung = RenderLung::from_kernel(&kernel, scene.lungs.mode)
                .with_context(|| format!("the {} lung's kernel", side.name()))?;
            let n = lung.lung.len();
            let topology = Topology::triangles(&ras_triangles(&lung.lung.triangles), n)
                .with_context(|| format!("the {} lung's mesh", side.name()))?;
            let lobes: Option<Vec<f32>> = lung
                .lobe_codes()
                .map(|c| c.iter().map(|&v| f32::from(v)).collect());
            let lobes = lobes.as_deref().map(|values| PointScalars {
                name: LOBE_SCALAR,
                components: 1,
                values,
            });
            let mesh = FixedMesh::new(&topology, lobes.as_slice())
                .with_context(|| format!("the {} lung's mesh and lobe codes", side.name()))?;
            lungs.push(SentLung {
                device: if side == Side::Right {
                    RIGHT_LUNG
                } else {
                    LEFT_LUNG
                },
                lung,
                mesh,
                positions: vec![[0.0; 3]; n],
            });
        }
        let tumour = match scene.tumour() {
            None => None,
            Some(t) => {
                let Some(l) = lungs.iter().find(|l| l.lung.side == t.side) else {
                    anyhow::bail!("the tumour's lung ({}) is not in the scene", t.side.name());
                };
                let meta = l.lung.tumour.clone().with_context(|| {
                    format!(
                        "the {} lung's kernel has no tumour record (baked before lungdyn recorded \
                         it); bake it again",
                        t.side.name()
                    )
                })?;
                let (unit, tris) = renderer::tumour::unit_sphere();
                // The kernel's tumour, as the renderer draws it.
                let r = meta.tumour.radii_mm;
                let shape: Vec<[f32; 3]> = unit
                    .iter()
                    .map(|p| [0, 1, 2].map(|a| p[a] * r[a] as f32))
                    .collect();
                let topology = Topology::triangles(&ras_triangles(&tris), shape.len())?;
                Some(SentTumour {
                    slot: t.side.index(),
                    meta,
                    positions: vec![[0.0; 3]; shape.len()],
                    shape,
                    mesh: FixedMesh::new(&topology, &[]).context("the tumour's mesh")?,
                })
            }
        };
        let disease = renderer::hud::HudConfig::of(scene, &[]).disease;
        Ok(Self {
            lungs,
            tumour,
            mode: scene.lungs.mode,
            tick_hz: scene.engine.tick_hz,
            disease,
            disease_text: String::new(),
            state: Vec::new(),
            bytes: Vec::new(),
        })
    }

    /// Every message of frame `f` into [`Self::bytes`].
    pub fn make(&mut self, f: &EngineFrame) -> anyhow::Result<()> {
        self.bytes.clear();
        let ts = Timestamp::from_unix_ns(unix_ns());
        for l in &mut self.lungs {
            let Some(lf) = drawn(&f.lungs[l.lung.side.index()], &l.lung)? else {
                continue;
            };
            crate::export::lung_positions_into(&mut l.lung, &lf, &mut l.positions)?;
            for p in &mut l.positions {
                *p = body_to_ras(*p);
            }
            igtl_send::fixed_polydata(&mut self.bytes, l.device, ts, &l.positions, &l.mesh)?;
        }
        let mut centre = None;
        if let Some(t) = &mut self.tumour {
            let lf = f.lungs[t.slot];
            let lung = self.lungs.iter().find(|l| l.lung.side.index() == t.slot);
            let lf = match lung {
                Some(l) => drawn(&lf, &l.lung)?,
                None => None,
            };
            if let Some(lf) = lf {
                let c = crate::export::tumour_centre(&t.meta, self.mode, &lf)?;
                let c = body_to_ras(c.map(|v| v as f32));
                for (q, p) in t.positions.iter_mut().zip(&t.shape) {
                    *q = body_to_ras(*p);
                    for a in 0..3 {
                        q[a] += c[a];
                    }
                }
                igtl_send::fixed_polydata(&mut self.bytes, TUMOUR, ts, &t.positions, &t.mesh)?;
                let tf = Transform {
                    translation_mm: c,
                    ..Transform::IDENTITY
                };
                igtl_send::transform(&mut self.bytes, TUMOUR_CENTRE, ts, &tf)?;
                centre = Some(c);
            }
        }
        self.state_json(f, centre);
        let text = std::str::from_utf8(&self.state).context("the state text is not UTF-8")?;
        igtl_send::string(&mut self.bytes, BREATH_STATE, ts, text)?;
        Ok(())
    }

    /// The breath's state as one JSON object into `self.state` (no allocation once grown).
    fn state_json(&mut self, f: &EngineFrame, tumour: Option<[f32; 3]>) {
        let s = &mut self.state;
        s.clear();
        let disease = self.disease.as_ref().map(|(k, side)| (k.as_str(), *side));
        renderer::hud::text::disease_line(&mut self.disease_text, disease, f);
        let fault = match f.fault {
            ipc_types::fault::NONE => "none",
            ipc_types::fault::TRACKER_LOST => "tracker lost",
            ipc_types::fault::NON_FINITE_VOLUME => "non-finite volume held",
            _ => "unknown",
        };
        let _ = write!(
            s,
            "{{\"tick\":{},\"time_s\":{:.3},\"fault\":\"{fault}\",\"disease\":",
            f.tick,
            f.tick as f64 / self.tick_hz
        );
        let _ = serde_json::to_writer(&mut *s, self.disease_text.as_str());
        let _ = write!(s, ",\"lungs\":[");
        let mut first = true;
        for (k, l) in f.lungs.iter().enumerate().take(NUM_LUNGS) {
            if !l.is_active() {
                continue;
            }
            if !first {
                s.push(b',');
            }
            first = false;
            lung_json(s, k, l);
        }
        s.push(b']');
        if let Some(c) = tumour {
            let _ = write!(
                s,
                ",\"tumour_ras_mm\":[{:.2},{:.2},{:.2}]",
                c[0], c[1], c[2]
            );
        }
        s.push(b'}');
    }
}

/// Frame `l` as the renderer would draw it for `lung` (`renderer::session`'s checks): `None` for an
/// inactive slot; an error when the engine runs the lung with another kernel (an engine restarted on
/// another scene: the mesh held here is not the one it deforms); a collapse outside [0, 1] or a
/// non-finite hilum is not applied.
fn drawn(l: &LungFrame, lung: &RenderLung) -> anyhow::Result<Option<LungFrame>> {
    if !l.is_active() {
        return Ok(None);
    }
    if lung.kernel_id != 0 && l.kernel_id != lung.kernel_id {
        anyhow::bail!(
            "the engine runs the {} lung with kernel {:016x}, the link loaded {:016x}",
            lung.side.name(),
            l.kernel_id,
            lung.kernel_id
        );
    }
    let mut l = *l;
    if !((0.0..=1.0).contains(&l.collapse) && l.hilum_mm.iter().all(|v| v.is_finite())) {
        l.collapse = 0.0;
        l.hilum_mm = [0.0; 3];
    }
    Ok(Some(l))
}

fn lung_json(s: &mut Vec<u8>, slot: usize, l: &LungFrame) {
    let side = if slot == Side::Right.index() {
        "right"
    } else {
        "left"
    };
    let inhaling = l.flags & ipc_types::lung_flags::INHALING != 0;
    let held = l.flags & ipc_types::lung_flags::HELD != 0;
    let num = |v: f32| if v.is_finite() { v } else { 0.0 };
    let _ = write!(
        s,
        "{{\"side\":\"{side}\",\"volume_ml\":{:.1},\"phase\":{:.3},\"cycle\":{},\"inhaling\":{inhaling},\
         \"held\":{held},\"collapse\":{:.3}}}",
        num(l.volume_ml),
        num(l.phase),
        l.cycle,
        num(l.collapse)
    );
}

/// The link's thread yields to the run's processes: nice 10 (one tenth of a nice-0 thread's share
/// when the cores are busy). A loaded machine then sends Slicer fewer frames rather than draw fewer
/// (measured in docs/SLICER.md). Where the nice value cannot be set, the thread runs as it is.
fn lower_priority() {
    // SAFETY: gettid has no arguments; setpriority on one thread id (Linux: per-thread nice).
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, LINK_NICE);
    }
}

/// The link thread's nice value.
pub const LINK_NICE: libc::c_int = 10;

/// CPU time of the calling thread, ns (what making a frame costs, whatever else the cores run).
fn thread_cpu_ns() -> u64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid clock id and a timespec we own.
    let ok = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0;
    if ok {
        t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
    } else {
        0
    }
}

fn unix_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::deform::modes::DeformMode;

    #[test]
    fn the_body_frame_reaches_slicer_as_ras_with_triangles_reversed() {
        // +X is the patient's left in the body frame; in RAS the patient's left is −R.
        assert_eq!(body_to_ras([10.0, 20.0, 30.0]), [-10.0, 20.0, 30.0]);
        assert_eq!(ras_triangles(&[[0, 1, 2]]), vec![[0, 2, 1]]);
    }

    #[test]
    fn options_come_from_the_scene_with_the_command_line_over_them() {
        let mut scene = Scene::default();
        assert!(SlicerOptions::resolve(&scene, None, None, &[], None)
            .unwrap()
            .is_none());
        let e = SlicerOptions::resolve(&scene, None, Some(10.0), &[], None).unwrap_err();
        assert!(e.to_string().contains("need --igtl-serve"), "{e}");
        let o = SlicerOptions::resolve(&scene, Some(None), None, &[], None)
            .unwrap()
            .unwrap();
        assert_eq!(
            (o.port, o.rate_hz, o.bind_address()),
            (18945, 30.0, "127.0.0.1")
        );
        scene.slicer.serve = true;
        scene.slicer.port = 20000;
        let o = SlicerOptions::resolve(&scene, None, Some(5.0), &["10.0.0.0/24".into()], None)
            .unwrap()
            .unwrap();
        assert_eq!((o.port, o.rate_hz, o.bind_address()), (20000, 5.0, "::"));
        let o = SlicerOptions::resolve(&scene, Some(Some(20001)), None, &[], None)
            .unwrap()
            .unwrap();
        assert_eq!(o.port, 20001);
        // A taken port is named, with the way out.
        let held = TcpListener::bind("127.0.0.1:0").unwrap();
        let taken = SlicerOptions {
            port: held.local_addr().unwrap().port(),
            ..o.clone()
        };
        let e = format!("{:#}", taken.bind().unwrap_err());
        assert!(
            e.contains("cannot listen on 127.0.0.1 port") && e.contains("--igtl-serve PORT"),
            "{e}"
        );
        for (serve, rate, allow, words) in [
            (Some(Some(0)), None, vec![], "--igtl-serve 0"),
            (Some(None), Some(0.0), vec![], "--igtl-serve-rate 0"),
            (Some(None), Some(f64::NAN), vec![], "--igtl-serve-rate NaN"),
            (Some(None), Some(500.0), vec![], "--igtl-serve-rate 500"),
            (
                Some(None),
                None,
                vec!["0.0.0.0/0".to_string()],
                "admits every host",
            ),
            (
                Some(None),
                None,
                vec!["slicer.local".to_string()],
                "--igtl-serve-allow",
            ),
        ] {
            let e = SlicerOptions::resolve(&scene, serve, rate, &allow, None)
                .unwrap_err()
                .to_string();
            assert!(e.contains(words), "{words}: {e}");
        }
        // Connecting to Slicer's server instead: not beside serving, nor with an allow-list; the
        // host resolved (or refused naming what to give) before anything starts.
        scene.slicer.serve = false;
        let o = SlicerOptions::resolve(&scene, None, None, &[], Some("127.0.0.1:18944"))
            .unwrap()
            .unwrap();
        assert!(matches!(o.open().unwrap(), Endpoint::Connect(a) if a.port() == 18944));
        for (serve, allow, connect, words) in [
            (Some(None), vec![], "127.0.0.1:18944", "give one"),
            (
                None,
                vec!["10.0.0.5".to_string()],
                "127.0.0.1:18944",
                "connects out",
            ),
        ] {
            let e = SlicerOptions::resolve(&scene, serve, None, &allow, Some(connect))
                .unwrap_err()
                .to_string();
            assert!(e.contains(words), "{words}: {e}");
        }
        for (connect, words) in [
            ("slicer-host", "HOST:PORT"),
            ("127.0.0.1:0", "port 0"),
            (
                "no-such-host.invalid:18944",
                "--igtl-connect no-such-host.invalid:18944",
            ),
        ] {
            let o = SlicerOptions::resolve(&scene, None, None, &[], Some(connect))
                .unwrap()
                .unwrap();
            let e = format!("{:#}", o.open().unwrap_err());
            assert!(e.contains(words), "{connect}: {e}");
        }
    }

    /// As a client of Slicer's server: no server yet is tried once a second and counted, never an
    /// error; once one listens the link connects and the server receives whole frames, the
    /// first of them the right lung's POLYDATA; when the server goes the link says so and connects
    /// again when it is back.
    #[test]
    fn as_a_client_it_connects_to_slicers_server_when_there_and_again_after_it_goes() {
        let (scene, frames, dir) = small(DeformMode::Precomputed, "client");
        let maker = FrameMaker::new(&scene).unwrap();
        // A port nobody listens on: bind one, note it, close it.
        let addr = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let options = SlicerOptions {
            port: addr.port(),
            connect: Some(addr.to_string()),
            rate_hz: 30.0,
            allow: AllowList::default(),
        };
        let mut serve =
            Serve::new(None, Some(addr), options, maker, SlicerReport::default()).unwrap();
        serve.accept();
        serve.accept();
        assert_eq!(
            (serve.report.connect_failures, serve.clients.len()),
            (1, 0),
            "one try a second: {:?}",
            serve.report
        );
        let slicer = TcpListener::bind(addr).unwrap();
        let mut scratch = vec![0u8; 4096];
        for round in 0..2 {
            serve.next_try = Instant::now();
            serve.accept();
            assert_eq!(serve.clients.len(), 1, "round {round}: {:?}", serve.report);
            let (mut got, _) = slicer.accept().unwrap();
            serve.send(&frames[60 + round]);
            let want = serve.frame.bytes.clone();
            let until = Instant::now() + Duration::from_secs(5);
            while serve.clients.iter().any(|c| c.written < c.pending.len())
                && Instant::now() < until
            {
                serve.flush(&mut scratch);
            }
            let mut bytes = vec![0u8; want.len()];
            got.read_exact(&mut bytes).unwrap();
            assert!(bytes == want, "round {round}: the frame as served");
            // An OpenIGTLink v1/v2 header: type at 2..14, device name at 14..34.
            assert_eq!(&bytes[2..10], b"POLYDATA");
            assert_eq!(&bytes[14..23], b"RightLung");
            drop(got);
            let until = Instant::now() + Duration::from_secs(5);
            while !serve.clients.is_empty() && Instant::now() < until {
                serve.flush(&mut scratch);
                std::thread::sleep(Duration::from_millis(2));
            }
            assert!(serve.clients.is_empty(), "the server's close is seen");
        }
        assert_eq!(serve.report.clients, 2, "{:?}", serve.report);
        let _ = std::fs::remove_dir_all(dir);
    }

    /// The built-in lungs at 1200 vertices in `mode`, prepared into a folder of their own, and the
    /// engine's first 200 frames (a still patient).
    fn small(mode: DeformMode, tag: &str) -> (Scene, Vec<EngineFrame>, std::path::PathBuf) {
        let dir = std::env::temp_dir().join(format!(
            "lungdyn-slicer-{}-{tag}-{}",
            std::process::id(),
            mode.name()
        ));
        let mut scene = Scene::default();
        scene.lungs.vertices = 1200;
        scene.lungs.mode = mode;
        let scene = crate::prepare::prepare(scene, &dir).unwrap().scene;
        let mut frames = Vec::new();
        engine::headless::run_while(
            engine::runtime::EngineCore::new(&scene).unwrap(),
            200,
            &mut crate::scene_check::still_patient(&scene),
            &mut |_, f| {
                frames.push(*f);
                true
            },
        )
        .unwrap();
        (scene, frames, dir)
    }

    fn be32(b: &[u8], at: usize) -> u32 {
        u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
    }

    /// Points and triangles of the POLYDATA message at `at` (read from the bytes, not by our encoder).
    fn mesh_at(b: &[u8], at: usize) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        let c = at + HEADER_SIZE;
        let (n, polys) = (be32(b, c) as usize, be32(b, c + 20) as usize);
        let p0 = c + 40;
        let pts = (0..n)
            .map(|i| [0, 1, 2].map(|a| f32::from_bits(be32(b, p0 + 12 * i + 4 * a))))
            .collect();
        let t0 = p0 + 12 * n;
        let tris = (0..polys)
            .map(|k| {
                assert_eq!(be32(b, t0 + 16 * k), 3);
                [1, 2, 3].map(|j| be32(b, t0 + 16 * k + 4 * j))
            })
            .collect();
        (pts, tris)
    }

    use tracker_bridge::igtl::HEADER_SIZE;

    /// In every deformation mode, a frame is both lungs then the state: every message decodes with
    /// our reader; every point is the CPU reference's for that frame, reflected to RAS; the meshes
    /// enclose a positive volume in RAS (the corners' reversal keeps them outward) close to the
    /// engine's; the state holds the tick and the engine's volumes.
    #[test]
    fn in_every_mode_a_frame_is_both_lungs_then_the_state_with_the_cpu_references_points() {
        use tracker_bridge::igtl::{Limits, Message};
        for mode in DeformMode::ALL {
            let (scene, frames, dir) = small(mode, "modes");
            let mut maker = FrameMaker::new(&scene).unwrap();
            let f = frames[150];
            maker.make(&f).unwrap();
            let limits = Limits {
                max_body_bytes: 64 << 20,
                ..Limits::default()
            };
            let (mut at, mut seen) = (0, Vec::new());
            while at < maker.bytes.len() {
                let (m, n) = Message::decode(&maker.bytes[at..], &limits).unwrap();
                seen.push((m.device_name.clone(), m.body.type_name().to_string(), at));
                at += n;
            }
            let names: Vec<(&str, &str)> = seen
                .iter()
                .map(|(a, b, _)| (a.as_str(), b.as_str()))
                .collect();
            assert_eq!(
                names,
                [
                    (RIGHT_LUNG, "POLYDATA"),
                    (LEFT_LUNG, "POLYDATA"),
                    (BREATH_STATE, "STRING")
                ],
                "{mode:?}"
            );
            for (k, lung) in maker.lungs.iter().enumerate() {
                let mut l = lung.lung.clone();
                let mut expect = vec![[0.0; 3]; l.lung.len()];
                let lf = &f.lungs[l.side.index()];
                crate::export::lung_positions_into(&mut l, lf, &mut expect).unwrap();
                let (pts, tris) = mesh_at(&maker.bytes, seen[k].2);
                let ras: Vec<[f32; 3]> = expect.iter().map(|&p| body_to_ras(p)).collect();
                assert!(
                    pts == ras,
                    "{mode:?} {}: every point the reference's",
                    l.side.name()
                );
                let v = lung_model::mesh::enclosed_volume_with(&tris, |i| {
                    pts[i as usize].map(f64::from)
                }) / 1000.0;
                assert!(
                    v > 0.0 && (v - f64::from(lf.volume_ml)).abs() < 0.1 * f64::from(lf.volume_ml),
                    "{mode:?} {}: {v} ml enclosed, outward, near the engine's {}",
                    l.side.name(),
                    lf.volume_ml
                );
            }
            let state_start = maker.bytes.len() - maker.state.len();
            let v: serde_json::Value = serde_json::from_slice(&maker.bytes[state_start..]).unwrap();
            assert_eq!(v["tick"], f.tick);
            assert_eq!(
                (v["disease"].as_str(), v["fault"].as_str()),
                (Some("healthy lungs"), Some("none"))
            );
            let vol = v["lungs"][0]["volume_ml"].as_f64().unwrap();
            assert!((vol - f64::from(f.lungs[0].volume_ml)).abs() < 0.06);
            // A frame of a lung the engine runs with another kernel is refused, not sent wrong.
            let mut other = f;
            other.lungs[0].kernel_id ^= 1;
            let e = maker.make(&other).unwrap_err().to_string();
            assert!(
                e.contains("another kernel") || e.contains("with kernel"),
                "{e}"
            );
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    #[test]
    fn hosts_off_the_allow_list_and_a_fifth_client_are_refused_with_the_reason() {
        let ip = |s: &str| s.parse::<std::net::IpAddr>().unwrap();
        let allow = AllowList::parse_as(&["10.0.0.0/24".into()], "--igtl-serve-allow").unwrap();
        assert_eq!(refusal(&allow, ip("127.0.0.1"), 0), None);
        assert_eq!(refusal(&allow, ip("::ffff:10.0.0.9"), 3), None);
        let e = refusal(&allow, ip("10.0.1.9"), 0).unwrap();
        assert!(
            e.contains("--igtl-serve-allow 10.0.1.9") && e.contains("10.0.0.0/24"),
            "{e}"
        );
        let e = refusal(&allow, ip("127.0.0.1"), MAX_CLIENTS).unwrap();
        assert!(e.contains("clients are served already"), "{e}");
    }

    /// A client that never reads: it takes what the socket buffers hold, then misses frames
    /// (counted, none kept beyond the one it was given), and is closed once it has taken nothing for
    /// the stall limit; a client that reads gets whole frames meanwhile.
    #[test]
    fn a_client_that_does_not_read_misses_frames_then_is_closed_and_nothing_piles_up() {
        let (scene, frames, dir) = small(DeformMode::Precomputed, "deaf");
        let maker = FrameMaker::new(&scene).unwrap();
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let options = SlicerOptions {
            port: addr.port(),
            connect: None,
            rate_hz: 30.0,
            allow: AllowList::default(),
        };
        let mut serve = Serve::new(
            Some(listener),
            None,
            options,
            maker,
            SlicerReport::default(),
        )
        .unwrap();
        serve.stalled_after = Duration::from_millis(400);
        let _deaf = TcpStream::connect(addr).unwrap();
        let reader = std::thread::spawn(move || {
            let mut s = TcpStream::connect(addr).unwrap();
            let mut all = Vec::new();
            let _ = s.read_to_end(&mut all);
            all
        });
        let until = Instant::now() + Duration::from_secs(5);
        while serve.clients.len() < 2 && Instant::now() < until {
            serve.accept();
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(serve.clients.len(), 2);
        let mut scratch = vec![0u8; 4096];
        let sends = 150;
        for k in 0..sends {
            serve.send(&frames[50 + k % 150]);
            for _ in 0..3 {
                serve.flush(&mut scratch);
                std::thread::sleep(Duration::from_millis(1));
            }
            let most = serve.frame.bytes.len();
            assert!(serve.clients.iter().all(|c| c.pending.len() <= most));
        }
        let frame_bytes = serve.frame.bytes.len() as u64;
        assert!(serve.report.dropped > 0, "{:?}", serve.report);
        assert!(
            serve.report.dropped < sends as u64 + 10,
            "the reading client misses few: {:?}",
            serve.report
        );
        std::thread::sleep(Duration::from_millis(500));
        serve.flush(&mut scratch);
        // The reading client's last frame goes out whole before the link stops.
        let until = Instant::now() + Duration::from_secs(5);
        while serve.clients.iter().any(|c| c.written < c.pending.len()) && Instant::now() < until {
            serve.flush(&mut scratch);
            std::thread::sleep(Duration::from_millis(1));
        }
        assert_eq!(
            (serve.report.stalled, serve.clients.len()),
            (1, 1),
            "{:?}",
            serve.report
        );
        let report = serve.finish(Instant::now());
        let got = reader.join().unwrap();
        assert!(
            got.len() as u64 >= frame_bytes,
            "the reading client got whole frames"
        );
        let mut at = 0;
        let limits = tracker_bridge::igtl::Limits {
            max_body_bytes: 64 << 20,
            ..Default::default()
        };
        while at < got.len() {
            let (_, n) = tracker_bridge::igtl::Message::decode(&got[at..], &limits).unwrap();
            at += n;
        }
        assert_eq!(at, got.len(), "only whole messages");
        assert_eq!(report.bad_frames, 0);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
