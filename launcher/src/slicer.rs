//! `lungdyn demo --igtl-serve [PORT]`: the breathing lungs sent to 3D Slicer over OpenIGTLink
//! (issue 38 item 1; docs/SLICER.md). lungdyn is the server Slicer's OpenIGTLinkIF connects to.
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
use renderer::RenderLung;
use tracker_bridge::igtl::{Timestamp, Transform};
use tracker_bridge::igtl_polydata::{PointScalars, Topology};
use tracker_bridge::igtl_send;
use tracker_bridge::source::igtl_server::AllowList;
use transport::{iox, Instance, Receive};

/// Clients served at once (a Slicer or two, a recorder); more are refused and told why.
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

/// What the server is asked to do (the scene's `[slicer]` with the command line over it).
#[derive(Debug, Clone)]
pub struct SlicerOptions {
    /// TCP port.
    pub port: u16,
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
    ) -> anyhow::Result<Option<Self>> {
        let s = &scene.slicer;
        if serve.is_none() && !s.serve {
            if rate_hz.is_some() || !allow.is_empty() {
                anyhow::bail!(
                    "--igtl-serve-rate and --igtl-serve-allow need --igtl-serve (or [slicer] serve = \
                     true in the scene)"
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
            rate_hz,
            allow,
        }))
    }

    /// Listen (a taken port is an error here, before anything is baked or started).
    pub fn bind(&self) -> anyhow::Result<TcpListener> {
        let bind = self.bind_address();
        TcpListener::bind((bind, self.port)).with_context(|| {
            format!(
                "--igtl-serve: cannot listen on {bind}:{} (another program, or another lungdyn, has \
                 it? 18944 is the tracker's OpenIGTLink port; give another with --igtl-serve PORT)",
                self.port
            )
        })
    }

    /// Loopback only, or every interface when the allow-list names other hosts.
    pub fn bind_address(&self) -> &'static str {
        if self.allow == AllowList::default() {
            "127.0.0.1"
        } else {
            "0.0.0.0"
        }
    }
}

/// What the server did (the demo's report and JSON).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SlicerReport {
    /// The address it listened on.
    pub address: String,
    /// Who may connect, in words.
    pub allowed: String,
    /// Frames per second asked for.
    pub rate_hz: f64,
    /// Clients that connected (refused ones not counted).
    pub clients: u64,
    /// Connections refused (not on the allow-list, or too many).
    pub refused: u64,
    /// Frames made (each sent to every client that had taken the one before; none is made while
    /// every client is still taking the last).
    pub frames: u64,
    /// Frames a client missed because it had not taken the previous one yet.
    pub dropped: u64,
    /// Bytes written to clients.
    pub bytes: u64,
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
        let mut s = format!(
            "Slicer (OpenIGTLink on {}, {} Hz): {} client(s), {} frame(s) made, {} missed by a slow \
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
        listener: TcpListener,
    ) -> anyhow::Result<Self> {
        listener.set_nonblocking(true)?;
        let address = listener.local_addr()?;
        let frame = FrameMaker::new(scene)?;
        let stop = Arc::new(AtomicBool::new(false));
        let report = SlicerReport {
            address: address.to_string(),
            allowed: options.allow.describe(),
            rate_hz: options.rate_hz,
            ..SlicerReport::default()
        };
        let (name, opts, flag) = (instance.to_string(), options.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("igtl-serve".into())
            .spawn(move || {
                lower_priority();
                let mut serve = Serve {
                    listener,
                    options: opts,
                    clients: Vec::new(),
                    frame,
                    report,
                    make_us: hdrhistogram::Histogram::new(3).expect("3 significant figures"),
                };
                let started = Instant::now();
                if let Err(e) = serve.run(&name, &flag) {
                    serve.report.failure = Some(format!("{e:#}"));
                    eprintln!("lungdyn: the Slicer link stopped: {e:#} (the demo goes on)");
                }
                serve.finish(started)
            })?;
        eprintln!(
            "lungdyn: serving the lungs to 3D Slicer on {address} at {} Hz (OpenIGTLinkIF: client, \
             port {}; docs/SLICER.md); clients from {}",
            options.rate_hz,
            address.port(),
            options.allow.describe()
        );
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
}

struct Serve {
    listener: TcpListener,
    options: SlicerOptions,
    clients: Vec<Client>,
    frame: FrameMaker,
    report: SlicerReport,
    make_us: hdrhistogram::Histogram<u64>,
}

impl Serve {
    fn run(&mut self, instance: &str, stop: &AtomicBool) -> anyhow::Result<()> {
        let services = Instance::new(instance)?;
        let node = iox::node(&services, "slicer")?;
        let mut engine = services.engine_inlet(&node)?;
        let period = Duration::from_secs_f64(1.0 / self.options.rate_hz);
        let mut next = Instant::now();
        let mut latest: Option<EngineFrame> = None;
        let mut sent_tick = None;
        let mut scratch = [0u8; 4096];
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
                        self.send(f)?;
                        sent_tick = Some(f.tick);
                    }
                }
            }
            self.flush(&mut scratch);
            let busy = self.clients.iter().any(|c| c.written < c.pending.len());
            let wait = next.saturating_duration_since(Instant::now());
            std::thread::sleep(if busy {
                wait.min(Duration::from_millis(1))
            } else {
                wait.min(Duration::from_millis(5))
            });
        }
        Ok(())
    }

    fn accept(&mut self) {
        loop {
            match self.listener.accept() {
                Ok((stream, peer)) => {
                    let why = if !self.options.allow.allows(peer.ip()) {
                        Some(format!(
                            "not on the allow-list ({}); admit it with --igtl-serve-allow {}",
                            self.options.allow.describe(),
                            peer.ip()
                        ))
                    } else if self.clients.len() >= MAX_CLIENTS {
                        Some(format!("{MAX_CLIENTS} clients are served already"))
                    } else {
                        None
                    };
                    if let Some(why) = why {
                        self.report.refused += 1;
                        // Once per refusal is bounded by the accept rate; a flood says so once.
                        if self.report.refused <= 10 {
                            eprintln!("lungdyn: Slicer link: refused {peer}: {why}");
                        }
                        continue;
                    }
                    if stream.set_nonblocking(true).is_err() {
                        continue;
                    }
                    let _ = stream.set_nodelay(true);
                    self.report.clients += 1;
                    eprintln!("lungdyn: Slicer link: {peer} connected");
                    self.clients.push(Client {
                        stream,
                        peer,
                        pending: Vec::new(),
                        written: 0,
                    });
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                // A connection reset before it was taken, out of descriptors: try again later.
                Err(_) => return,
            }
        }
    }

    /// Make frame `f` and hand it to every client that has taken the previous one.
    fn send(&mut self, f: &EngineFrame) -> anyhow::Result<()> {
        // No client can take it: each misses it, and it is not made.
        if self.clients.iter().all(|c| c.written < c.pending.len()) {
            self.report.dropped += self.clients.len() as u64;
            return Ok(());
        }
        let t0 = thread_cpu_ns();
        self.frame.make(f)?;
        let us = thread_cpu_ns().saturating_sub(t0) / 1000;
        let _ = self.make_us.record(us.max(1));
        self.report.frames += 1;
        self.report.frame_bytes = self.frame.bytes.len() as u64;
        for c in &mut self.clients {
            if c.written < c.pending.len() {
                self.report.dropped += 1;
                continue;
            }
            c.pending.clear();
            c.pending.extend_from_slice(&self.frame.bytes);
            c.written = 0;
        }
        Ok(())
    }

    /// Write what each client can take now; read and drop what it sends (Slicer's own messages,
    /// which are not asked for); drop clients that closed.
    fn flush(&mut self, scratch: &mut [u8]) {
        let report = &mut self.report;
        self.clients.retain_mut(|c| {
            loop {
                match c.stream.read(scratch) {
                    Ok(0) => {
                        eprintln!("lungdyn: Slicer link: {} disconnected", c.peer);
                        return false;
                    }
                    Ok(_) => continue,
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
            true
        });
    }

    fn finish(mut self, started: Instant) -> SlicerReport {
        self.clients.clear();
        let h = &self.make_us;
        let ms = |us: u64| (us as f64 / 1000.0 * 1000.0).round() / 1000.0;
        if !h.is_empty() {
            self.report.make_ms_p50 = ms(h.value_at_quantile(0.5));
            self.report.make_ms_p99 = ms(h.value_at_quantile(0.99));
            self.report.make_ms_max = ms(h.max());
        }
        self.report.seconds = (started.elapsed().as_secs_f64() * 1000.0).round() / 1000.0;
        self.report
    }
}

/// One lung as it is sent: its mesh's triangles (reversed, RAS) encoded once, the deformed
/// positions' buffer, the lobe codes.
struct SentLung {
    lung: RenderLung,
    device: &'static str,
    topology: Topology,
    positions: Vec<[f32; 3]>,
    lobes: Option<Vec<f32>>,
}

/// The tumour as it is sent: the unit sphere scaled to its radii, moved to its centre each frame.
struct SentTumour {
    slot: usize,
    meta: lung_model::kernel::TumourMeta,
    shape: Vec<[f32; 3]>,
    topology: Topology,
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
pub fn body_to_ras(p: [f32; 3]) -> [f32; 3] {
    [-p[0], p[1], p[2]]
}

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
            let lobes = lung
                .lobe_codes()
                .map(|c| c.iter().map(|&v| f32::from(v)).collect());
            lungs.push(SentLung {
                device: if side == Side::Right {
                    RIGHT_LUNG
                } else {
                    LEFT_LUNG
                },
                lung,
                topology,
                positions: vec![[0.0; 3]; n],
                lobes,
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
                let r = t.radii_mm;
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
                    topology,
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
            let lf = &f.lungs[l.lung.side.index()];
            if !lf.is_active() {
                continue;
            }
            crate::export::lung_positions_into(&mut l.lung, lf, &mut l.positions)?;
            for p in &mut l.positions {
                *p = body_to_ras(*p);
            }
            let lobes = l.lobes.as_deref().map(|values| PointScalars {
                name: LOBE_SCALAR,
                components: 1,
                values,
            });
            igtl_send::polydata(
                &mut self.bytes,
                l.device,
                ts,
                &l.positions,
                &l.topology,
                lobes.as_slice(),
            )?;
        }
        let mut centre = None;
        if let Some(t) = &mut self.tumour {
            let lf = &f.lungs[t.slot];
            if lf.is_active() {
                let c = crate::export::tumour_centre(&t.meta, self.mode, lf)?;
                let c = body_to_ras(c.map(|v| v as f32));
                for (q, p) in t.positions.iter_mut().zip(&t.shape) {
                    *q = body_to_ras(*p);
                    for a in 0..3 {
                        q[a] += c[a];
                    }
                }
                igtl_send::polydata(&mut self.bytes, TUMOUR, ts, &t.positions, &t.topology, &[])?;
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
        let _ = write!(
            s,
            "{{\"tick\":{},\"time_s\":{:.3},\"disease\":",
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

    #[test]
    fn the_body_frame_reaches_slicer_as_ras_with_triangles_reversed() {
        // +X is the patient's left in the body frame; in RAS the patient's left is −R.
        assert_eq!(body_to_ras([10.0, 20.0, 30.0]), [-10.0, 20.0, 30.0]);
        assert_eq!(ras_triangles(&[[0, 1, 2]]), vec![[0, 2, 1]]);
    }

    #[test]
    fn options_come_from_the_scene_with_the_command_line_over_them() {
        let mut scene = Scene::default();
        assert!(SlicerOptions::resolve(&scene, None, None, &[])
            .unwrap()
            .is_none());
        let e = SlicerOptions::resolve(&scene, None, Some(10.0), &[]).unwrap_err();
        assert!(e.to_string().contains("need --igtl-serve"), "{e}");
        let o = SlicerOptions::resolve(&scene, Some(None), None, &[])
            .unwrap()
            .unwrap();
        assert_eq!(
            (o.port, o.rate_hz, o.bind_address()),
            (18945, 30.0, "127.0.0.1")
        );
        scene.slicer.serve = true;
        scene.slicer.port = 20000;
        let o = SlicerOptions::resolve(&scene, None, Some(5.0), &["10.0.0.0/24".into()])
            .unwrap()
            .unwrap();
        assert_eq!(
            (o.port, o.rate_hz, o.bind_address()),
            (20000, 5.0, "0.0.0.0")
        );
        let o = SlicerOptions::resolve(&scene, Some(Some(20001)), None, &[])
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
            e.contains("cannot listen on 127.0.0.1:") && e.contains("--igtl-serve PORT"),
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
            let e = SlicerOptions::resolve(&scene, serve, rate, &allow)
                .unwrap_err()
                .to_string();
            assert!(e.contains(words), "{words}: {e}");
        }
    }

    /// The frame of the built-in lungs: both meshes with their lobes, then the state; every message
    /// decodes (our reader) and the points are the CPU reference's, reflected.
    #[test]
    fn a_frame_is_both_lungs_then_the_state_and_its_points_are_the_cpu_references() {
        use tracker_bridge::igtl::{Limits, Message};
        let dir = std::env::temp_dir().join(format!("lungdyn-slicer-{}", std::process::id()));
        let mut scene = Scene::default();
        scene.lungs.vertices = 1200;
        let prepared = crate::prepare::prepare(scene, &dir).unwrap();
        let scene = prepared.scene;
        let mut maker = FrameMaker::new(&scene).unwrap();
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
        let f = frames[150];
        maker.make(&f).unwrap();
        let limits = Limits {
            max_body_bytes: 64 << 20,
            ..Limits::default()
        };
        let mut at = 0;
        let mut names = Vec::new();
        while at < maker.bytes.len() {
            let (m, n) = Message::decode(&maker.bytes[at..], &limits).unwrap();
            names.push((m.device_name.clone(), m.body.type_name().to_string()));
            at += n;
        }
        let names: Vec<(&str, &str)> = names
            .iter()
            .map(|(a, b)| (a.as_str(), b.as_str()))
            .collect();
        assert_eq!(
            names,
            [
                (RIGHT_LUNG, "POLYDATA"),
                (LEFT_LUNG, "POLYDATA"),
                (BREATH_STATE, "STRING")
            ]
        );
        // The right lung's first point, read from the bytes: header 58 + counts 40.
        let mut lung = maker.lungs[0].lung.clone();
        let mut expect = vec![[0.0; 3]; lung.lung.len()];
        crate::export::lung_positions_into(&mut lung, &f.lungs[0], &mut expect).unwrap();
        let p = &maker.bytes[98..110];
        let got: Vec<f32> = p
            .chunks(4)
            .map(|c| f32::from_be_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        assert_eq!(got, body_to_ras(expect[0]).to_vec());
        let state_start = maker.bytes.len() - maker.state.len();
        let v: serde_json::Value = serde_json::from_slice(&maker.bytes[state_start..]).unwrap();
        assert_eq!(v["tick"], f.tick);
        assert_eq!(v["disease"], "healthy lungs");
        assert_eq!(v["lungs"].as_array().unwrap().len(), 2);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
