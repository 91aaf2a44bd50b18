//! `lungdyn remote harness`: a source and N sites on loopback, each its own Zenoh session and
//! engine, and the seed's figures: drift = mean |V_site(t) − V_source(t)| / TV per breathing cycle
//! (mean and worst cycle per site), the phase error of each site's schedule, packets per minute,
//! and what per-frame updates would send.
//!
//! Delay, jitter and loss are emulated inside the process, on every packet a session receives
//! (states and probe replies at the sites, probes at the source: both directions), by
//! [`crate::link`]: netem in network namespaces needs `CAP_NET_ADMIN` and veth plumbing per site,
//! which this harness does not do; with an impairment it probes netem once ([`netem_probe`], in a
//! private network namespace) and says in `emulation` precisely why netem is not used. Zenoh itself runs over real TCP on 127.0.0.1 with multicast
//! scouting off.
//!
//! V(t) is what each engine shows at wall time t: the volume of the last tick it stepped by then
//! (both lungs), integrated exactly between the two engines' step times; so the drift includes the OS's lateness in waking each
//! thread, not only the protocol. `drift_percent_mean_scheduled` evaluates the same at each
//! engine's scheduled tick times (the protocol's own error: offset estimate and state timing).

use std::cell::Cell;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use engine::runtime::process::{run_loop, Controls, LoopStats, StateOut};
use engine::runtime::{EngineCore, LungGeometry};
use lung_model::deform::{LungModel, MotionConstants};
use lung_model::mesh::{generate, Side};
use lung_model::scene::Scene;
use serde::Serialize;
use transport::clock::now_ns;
use transport::pacer::PacerConfig;

use crate::link::Impairment;
use crate::measure::Lateness;
use crate::relay::{Relay, RelayCounts};
use crate::site::{ClockSync, Runner, Site};

use crate::source::{EnginePorts, Source};
use crate::{site_id, Keys, Net, RemoteError};

/// Options of `lungdyn remote harness`.
#[derive(Debug, Clone, clap::Args)]
pub struct HarnessArgs {
    /// Sites besides the source.
    #[arg(long, default_value_t = 3)]
    pub sites: usize,
    /// Seconds to run after every site has its first state.
    #[arg(long, default_value_t = 30.0)]
    pub seconds: f64,
    /// Emulated one-way delay, ms.
    #[arg(long, default_value_t = 0.0)]
    pub delay_ms: f64,
    /// Emulated jitter (uniform ±), ms.
    #[arg(long, default_value_t = 0.0)]
    pub jitter_ms: f64,
    /// Emulated loss probability (0..1).
    #[arg(long, default_value_t = 0.0)]
    pub loss: f64,
    /// Breaths per minute of the source's scene (the default scene's 12 otherwise).
    #[arg(long)]
    pub breaths_per_min: Option<f64>,
    /// Sites join as observers (they send no events).
    #[arg(long)]
    pub observer: bool,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Seed of the emulated impairment.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Through a Zenoh router the harness opens in its own process (on 127.0.0.1) with the time
    /// relay beside it: the source and every site are its clients and the sites sync their clocks
    /// with the relay (only the relay probes the source). Without it the sites connect to the
    /// source, peer to peer, and probe it.
    #[arg(long)]
    pub router: bool,
    /// Each site's probe interval, ms (its delay and clock-offset estimate; `remote join` probes
    /// every 500 ms).
    #[arg(long, default_value_t = 50)]
    pub probe_ms: u64,
    /// Test seam, off by default: every site's clock runs at 1 + SKEW_PPM × 10⁻⁶ of the source's,
    /// as a second machine's would (here all share CLOCK_MONOTONIC); the sites fit the rate
    /// (|rate| > 500 ppm is reported, not applied). Each site's offset error and fitted rate are
    /// reported.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub skew_ppm: f64,
    /// Test seam, off by default, with --router: the time relay's clock runs at 1 + PPM × 10⁻⁶
    /// of the source's.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub relay_skew_ppm: f64,
    /// For comparisons: the sites and the relay fit their clock rate but do not apply it (the
    /// offset is the 10 s mean alone, as before the rate fit).
    #[arg(long)]
    pub no_clock_rate: bool,
    /// Run the source in its own process (this executable's hidden `remote harness-source`), so
    /// its CPU time and TCP bytes are its own: the launcher sets it; without it (the library's
    /// tests) the source shares the harness's process and its cost is not reported.
    #[arg(skip)]
    pub source_exe: Option<std::path::PathBuf>,
    /// tls (default): every participant with its own certificate of a room made for this run
    /// (mutual TLS, sealed packets); tcp: plain TCP and plain packets, for the comparison.
    #[arg(long, value_enum, default_value_t = Transport::Tls)]
    pub transport: Transport,
    /// The run's keys (set by the harness for its source process).
    #[arg(long, hide = true)]
    pub keys_dir: Option<std::path::PathBuf>,
}

/// The harness's `--transport`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    /// Mutual TLS with the run's own room keys; every packet sealed.
    Tls,
    /// Plain TCP, plain packets (a closed lab network; the comparison).
    Tcp,
}

/// A room's keys made for one harness run (removed when dropped): the source, the router and
/// one identity per site (`site-K`, observers when `--observer`).
pub struct RunKeys {
    /// The folder.
    pub dir: std::path::PathBuf,
}

impl Drop for RunKeys {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl RunKeys {
    fn make(sites: usize, observer: bool) -> Result<Self, RemoteError> {
        use crate::keys::{Participant, Role};
        let dir = std::env::temp_dir().join(format!(
            "lungdyn-harness-keys-{}-{:x}",
            std::process::id(),
            now_ns()
        ));
        let mut ps = vec![
            Participant {
                name: "source".into(),
                role: Role::Source,
            },
            Participant {
                name: "router".into(),
                role: Role::Router,
            },
        ];
        for k in 1..=sites {
            ps.push(Participant {
                name: format!("site-{k}"),
                role: if observer { Role::Observer } else { Role::Site },
            });
        }
        crate::keys::make("harness", &dir, &ps, 1)
            .map_err(|e| RemoteError::Usage(format!("the harness's keys: {e}")))?;
        Ok(Self { dir })
    }
}

/// `identity`'s keys in `dir` (none: plain TCP).
fn run_room(
    dir: Option<&std::path::Path>,
    identity: &str,
) -> Result<Option<std::sync::Arc<crate::keys::Room>>, RemoteError> {
    dir.map(|d| {
        crate::keys::Room::load(d, identity)
            .map(std::sync::Arc::new)
            .map_err(|e| RemoteError::Usage(format!("the harness's keys: {e}")))
    })
    .transpose()
}

/// Options of the hidden `lungdyn remote harness-source`: the harness's source in its own process.
/// It prints the endpoint sites connect to, waits for `go` on its standard input, runs for
/// `--seconds` (+ 0.5) and prints a [`ChildReport`] as one line of JSON.
#[derive(Debug, Clone, clap::Args)]
pub struct SourceChildArgs {
    /// The harness's options (seconds, breaths, impairment, seed).
    #[command(flatten)]
    pub harness: HarnessArgs,
    /// The router to connect to as a client (none: listen on 127.0.0.1, peer to peer).
    #[arg(long)]
    pub via: Option<String>,
}

/// What a source costs over the measured window.
#[derive(Debug, Clone, Copy, Serialize, serde::Deserialize)]
pub struct SourceCost {
    /// Wall seconds of the window (from `go` to the engine's stop).
    pub wall_s: f64,
    /// CPU seconds (user + system) of the source's process: `getrusage(RUSAGE_SELF)` — its tick
    /// thread, link worker and every Zenoh runtime thread (the process holds only the source).
    pub cpu_s: f64,
    /// CPU seconds of the engine's tick thread alone (`getrusage(RUSAGE_THREAD)`; it also puts
    /// each state to Zenoh, which routes it to each link's queue on this thread).
    pub tick_thread_cpu_s: f64,
    /// Bytes sent over the process's TCP sockets (`TCP_INFO` bytes acknowledged; see
    /// [`crate::measure::tcp_bytes`]): states, probe replies, Zenoh's keep-alives and
    /// declarations.
    pub tcp_bytes_sent: u64,
    /// Bytes received (probes, events, Zenoh's own traffic).
    pub tcp_bytes_received: u64,
    /// Deadlines the source engine's pacer skipped (its tick thread woke more than the catch-up
    /// allowance late): each moves the source's later ticks a period off the schedule a state
    /// carries, for every site, until the next state.
    pub deadlines_skipped: u64,
    /// Probes answered within the window.
    pub probes: u64,
}

/// The source process's result: its stepped ticks (volume as f32 bits), counters and cost.
#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct ChildReport {
    /// (scheduled ns, actual ns, tick, total volume f32 bits, cycle).
    pub recs: Vec<(i128, u64, u64, u32, u32)>,
    /// States published.
    pub states: u64,
    /// State bytes published (once per publish).
    pub state_bytes: u64,
    /// Sites present at the end (liveliness tokens seen).
    pub sites_seen: usize,
    /// The cost.
    pub cost: SourceCost,
}

/// One site's figures.
#[derive(Debug, Clone, Serialize)]
pub struct SiteReport {
    /// Mean over cycles of the per-cycle mean |ΔV| / TV, %.
    pub drift_percent_mean: f64,
    /// The worst cycle's, %.
    pub drift_percent_worst: f64,
    /// The same at scheduled tick times, %.
    pub drift_percent_mean_scheduled: f64,
    /// Mean |scheduled time of a tick − the source's|, ms.
    pub phase_error_ms_mean: f64,
    /// Largest, ms.
    pub phase_error_ms_worst: f64,
    /// Largest over the run's last 5 s, ms (a clock estimate that settled: the fitted rate).
    pub phase_error_ms_worst_last_5_s: f64,
    /// Ticks stepped.
    pub ticks: usize,
    /// Ticks whose volume differs from the source's at the same tick number (determinism).
    pub ticks_differing: usize,
    /// States applied.
    pub states_applied: u64,
    /// Packets refused.
    pub refused: u64,
    /// Packets dropped by the emulated loss.
    pub lost: u64,
    /// Cycles breathed on the site's own prediction because their state was late (not there one
    /// path delay + 4 jitters + 2 ticks after the cycle's start) or lost.
    pub predicted_cycles: u64,
    /// Smoothed one-way delay, ms.
    pub delay_ms: f64,
    /// Round-trip variation, ms.
    pub jitter_ms: f64,
    /// Estimated clock offset (source − site) at the end, ms (the true one is 0 on one machine
    /// unless the site's clock is skewed: then `clock.offset_error_ms` is the error).
    pub offset_ms: f64,
    /// The clock estimate's error and rate.
    #[serde(flatten)]
    pub clock: ClockFigures,
    /// How late the site's tick thread stepped each tick after its scheduled time.
    pub lateness: Lateness,
    /// How long it took to join.
    #[serde(flatten)]
    pub join: Join,
}

/// A site's time to join the room.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Join {
    /// `Site::open`: the session's link up (TCP, or TLS with both certificates checked), the
    /// subscriptions and the liveliness token declared, ms.
    #[serde(rename = "join_open_ms")]
    pub open_ms: f64,
    /// From the start of the opening to the first clock answer taken (the first probe goes out
    /// on opening); none before the harness's 1 s settling after the last site opened, ms.
    #[serde(rename = "join_first_clock_answer_ms")]
    pub first_clock_answer_ms: Option<f64>,
}

/// A clock estimate's error and rate at the end of a run.
#[derive(Debug, Clone, Serialize)]
pub struct ClockFigures {
    /// The estimated offset minus the true one (the emulated skew's; 0 unskewed) now, ms;
    /// `null` before an offset.
    pub offset_error_ms: Option<f64>,
    /// The fitted clock rate (dθ/dt: the source's clock faster than this one's by it), ppm;
    /// `null` before a fit.
    pub rate_ppm: Option<f64>,
    /// `applied`, `uncertain` (fitted, standard error over 5 ppm: not applied yet),
    /// `implausible` (beyond ±500 ppm: not applied) or `unknown` (too few probes).
    pub rate: &'static str,
    /// Rate fits refused as implausible.
    pub rates_refused: u64,
}

impl ClockFigures {
    /// `path`'s figures now, for a participant on `clock` (the source on the host's).
    pub fn of(path: &crate::site::PathFigures, clock: crate::clock::LocalClock) -> Self {
        let host = now_ns();
        let local = clock.of(host);
        let truth = host as i128 - local as i128;
        Self {
            offset_error_ms: path
                .offset_at(local)
                .map(|o| (o as i128 - truth) as f64 / 1e6),
            rate_ppm: path.fitted_rate().map(|r| r * 1e6),
            rate: path.rate_word(),
            rates_refused: path.rates_refused.load(Ordering::Relaxed),
        }
    }

    /// In words.
    fn words(&self) -> String {
        format!(
            "offset error {}, rate {} ({})",
            self.offset_error_ms
                .map_or("none".to_string(), |e| format!("{e:.3} ms")),
            self.rate_ppm
                .map_or("none".to_string(), |r| format!("{r:.1} ppm")),
            if self.rates_refused > 0 {
                format!("{}, {} fits refused", self.rate, self.rates_refused)
            } else {
                self.rate.to_string()
            }
        )
    }
}

/// The time relay's figures over the measured window (through a router).
#[derive(Debug, Clone, Serialize)]
pub struct RelayReport {
    /// Sites' probes the relay answered per minute (what the source answered peer to peer).
    pub probes_answered_per_minute: f64,
    /// Probes the relay sent to the source per minute (all the source answers: one "site").
    pub probes_to_source_per_minute: f64,
    /// Payload bytes of its replies to the sites per minute (Zenoh's framing not included).
    pub reply_bytes_per_minute: f64,
    /// CPU of the relay's own two threads (link worker, prober; `RUSAGE_THREAD`), % of a core;
    /// Zenoh's threads that route its packets belong to the router's process and are in
    /// `harness_cpu_s`.
    pub threads_cpu_percent: f64,
    /// Sites' probes that came before the relay had an offset (left unanswered), whole run.
    pub unanswered: u64,
    /// The relay's offset estimate to the source at the end, ms (the true one is 0).
    pub offset_ms: Option<f64>,
    /// The relay's smoothed one-way delay to the source, ms.
    pub delay_ms: f64,
    /// Its clock estimate's error and rate.
    #[serde(flatten)]
    pub clock: ClockFigures,
}

/// The harness's figures.
#[derive(Debug, Clone, Serialize)]
pub struct HarnessReport {
    /// Sites.
    pub sites: usize,
    /// Seconds measured.
    pub seconds: f64,
    /// Emulated delay, ms.
    pub delay_ms: f64,
    /// Emulated jitter, ms.
    pub jitter_ms: f64,
    /// Emulated loss.
    pub loss: f64,
    /// How the network was emulated and, with an impairment, why not with netem (probed once).
    pub emulation: String,
    /// `tls` (mutual TLS with the run's own room keys, every packet sealed) or `tcp` (plain).
    pub transport: &'static str,
    /// Packets the sites refused because their seal did not hold (0 in a run with no outsider).
    pub refused_seals: u64,
    /// Mean over sites of the time to open a site's session ([`Join::open_ms`]), ms.
    pub join_open_ms_mean: f64,
    /// The slowest site's, ms.
    pub join_open_ms_worst: f64,
    /// The slowest site's first clock answer from the start of its opening; none when a site
    /// had none within the 1 s settling, ms.
    pub join_first_clock_answer_ms_worst: Option<f64>,
    /// Mean over sites of each site's mean drift, %.
    pub drift_percent_mean: f64,
    /// Worst cycle of any site, %.
    pub drift_percent_worst: f64,
    /// Mean drift at scheduled times, %.
    pub drift_percent_mean_scheduled: f64,
    /// Mean phase error, ms.
    pub phase_error_ms_mean: f64,
    /// Worst phase error, ms.
    pub phase_error_ms_worst: f64,
    /// Worst phase error over the last 5 s, ms.
    pub phase_error_ms_worst_last_5_s: f64,
    /// Control packets delivered per minute (states published × sites).
    pub packets_per_minute: f64,
    /// What per-frame updates would deliver (engine frames × sites).
    pub per_frame_packets_per_minute: f64,
    /// Ratio of the two.
    pub reduction: f64,
    /// States published per minute by the source.
    pub states_per_minute: f64,
    /// Bytes of states published per minute (each delivered once per site).
    pub state_bytes_per_minute: f64,
    /// Tidal volume the drift is normalised by, ml.
    pub tidal_volume_ml: f64,
    /// How the sites reach the source.
    pub topology: &'static str,
    /// Probe interval of each site (and of the relay), ms.
    pub probe_ms: u64,
    /// Whom the sites probe for the source's clock.
    pub clock_sync: &'static str,
    /// Emulated rate of each site's clock against the source's, ppm (`--skew-ppm`; 0: none).
    pub skew_ppm: f64,
    /// Emulated rate of the relay's clock against the source's, ppm (`--relay-skew-ppm`).
    pub relay_skew_ppm: f64,
    /// The clock rate was fitted but not applied (`--no-clock-rate`).
    pub no_clock_rate: bool,
    /// The time relay (through a router; `null` peer to peer).
    pub relay: Option<RelayReport>,
    /// Probes the source answered per minute of the window (one reply to each site's each
    /// probe).
    pub probes_per_minute: f64,
    /// Sites the source saw present at the end (their liveliness tokens).
    pub sites_seen_by_source: usize,
    /// How late the source's tick thread stepped each tick after its deadline (a site's drift at
    /// actual step times follows the difference of its lateness and this).
    pub source_lateness: Lateness,
    /// Deadlines the source engine skipped (woken too late to catch up): each shifts its later
    /// ticks a period from the schedule every site follows, until the next state.
    pub source_deadlines_skipped: u64,
    /// The source's own process: CPU seconds over the window (`getrusage(RUSAGE_SELF)`, every
    /// thread of it); `null` when the source shared the harness's process.
    pub source_cpu_s: Option<f64>,
    /// The same per wall second, % of one core.
    pub source_cpu_percent: Option<f64>,
    /// The source's tick thread alone (`getrusage(RUSAGE_THREAD)`), % of one core.
    pub source_tick_thread_cpu_percent: Option<f64>,
    /// Bytes the source's process sent over TCP per minute (every socket; `TCP_INFO`).
    pub source_tcp_bytes_sent_per_minute: Option<f64>,
    /// Bytes it received over TCP per minute.
    pub source_tcp_bytes_received_per_minute: Option<f64>,
    /// CPU seconds of the harness's process over the same window (the sites, the router and,
    /// when not in its own process, the source), for the machine's load.
    pub harness_cpu_s: f64,
    /// The machine's 1-minute load average at the end (`/proc/loadavg`).
    pub load_average_1min: Option<f64>,
    /// Each site.
    pub per_site: Vec<SiteReport>,
}

/// A record of one stepped tick: (scheduled ns, actual ns, tick, total volume, cycle).
pub type Rec = (i128, u64, u64, f32, u32);

/// The generated lungs every harness session runs (no kernels needed: the figures are volumes).
fn lungs() -> (Vec<LungGeometry>, Vec<lung_model::mesh::TriMesh>) {
    [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            let mesh = generate::lung(side, 500).expect("the generated lung");
            let m = LungModel::build(side, mesh.clone(), &MotionConstants::table_6_1(side))
                .expect("the generated lung's model");
            (LungGeometry::of(&m), mesh)
        })
        .unzip()
}

/// An engine for `scene` on the generated lungs, its disease state started (the source's: a site
/// calls [`EngineCore::follow_remote`] on its own).
pub fn scene_core(scene: &Scene) -> Result<EngineCore, RemoteError> {
    let (geometry, meshes) = lungs();
    let mut core = EngineCore::with_geometry(scene, geometry)?;
    core.start_disease(scene, &meshes)?;
    Ok(core)
}

/// The engine every harness session runs: the default scene (at `breaths_per_min` if given).
pub fn harness_core(breaths_per_min: Option<f64>) -> Result<(Scene, EngineCore), RemoteError> {
    let mut scene = Scene::default();
    if let Some(b) = breaths_per_min {
        if !(b.is_finite() && (2.0..=60.0).contains(&b)) {
            return Err(RemoteError::Usage(format!(
                "--breaths-per-min {b}: use 2–60"
            )));
        }
        scene.pv.breaths_per_min = b;
    }
    let core = scene_core(&scene)?;
    Ok((scene, core))
}

/// The locator a session listens on (for a listener on port 0).
pub fn locator(session: &zenoh::Session) -> Result<String, RemoteError> {
    use zenoh::Wait;
    session
        .info()
        .locators()
        .wait()
        .into_iter()
        .map(|l| l.to_string())
        .find(|l| l.starts_with("tcp/") || l.starts_with("tls/"))
        .ok_or_else(|| RemoteError::Usage("the source listens on no tcp or tls locator".into()))
}

/// A tracker that never sends: the source engine ticks on its deadlines (sleeping until each,
/// and keeping the last for the tick's record).
struct NoTracker(Rc<Cell<u64>>);

impl transport::Receive<ipc_types::TrackerFrame> for NoTracker {
    fn wait_until(&mut self, deadline_ns: u64) -> Result<(), transport::PortError> {
        self.0.set(deadline_ns);
        let now = now_ns();
        if deadline_ns > now {
            std::thread::sleep(Duration::from_nanos(deadline_ns - now));
        }
        Ok(())
    }
    fn take_latest(&mut self) -> Result<Option<ipc_types::TrackerFrame>, transport::PortError> {
        Ok(None)
    }
    fn drain(
        &mut self,
        _f: &mut dyn FnMut(&ipc_types::TrackerFrame),
    ) -> Result<usize, transport::PortError> {
        Ok(0)
    }
}

/// Every frame the source engine publishes, as a record; scheduled at the deadline its tick ran
/// for.
struct Records(Vec<Rec>, Rc<Cell<u64>>);

impl transport::Publish<ipc_types::EngineFrame> for Records {
    fn publish(&mut self, f: &ipc_types::EngineFrame) -> Result<(), transport::PortError> {
        let v = f.lungs.iter().map(|l| l.volume_ml).sum::<f32>();
        self.0.push((
            self.1.get() as i128,
            f.stamps.engine_publish_ns,
            f.tick,
            v,
            f.lungs[0].cycle,
        ));
        Ok(())
    }
}

/// Replies to a trainee's actions: nobody in the harness reads them.
struct NoReplies;

impl transport::Publish<ipc_types::ControlReply> for NoReplies {
    fn publish(&mut self, _r: &ipc_types::ControlReply) -> Result<(), transport::PortError> {
        Ok(())
    }
}

/// Run the source engine — the engine process's own loop ([`run_loop`]), on its deadlines, the
/// sites' events coming in and its control states going out over `src` — until `stop`; every
/// tick recorded. `id` is the source's site id, `epoch` its session.
pub fn run_source(
    core: EngineCore,
    hz: f64,
    src: &Source,
    id: u64,
    epoch: u64,
    stop: &AtomicBool,
) -> Result<(Vec<Rec>, LoopStats), RemoteError> {
    run_source_at(core, hz, src, id, epoch, 0, stop)
}

/// [`run_source`] from tick `first` (a restarted source: `core` resumed there with
/// [`EngineCore::resume_at`]).
pub fn run_source_at(
    mut core: EngineCore,
    hz: f64,
    src: &Source,
    id: u64,
    epoch: u64,
    first: u64,
    stop: &AtomicBool,
) -> Result<(Vec<Rec>, LoopStats), RemoteError> {
    let due = Rc::new(Cell::new(0));
    let mut frames = Records(Vec::with_capacity(64 * 1024), due.clone());
    let (mut events, mut states) = (EnginePorts(src), EnginePorts(src));
    let stats = run_loop(
        &mut core,
        &mut NoTracker(due),
        &mut frames,
        Some(Controls {
            inlet: &mut events,
            replies: &mut NoReplies,
            state: Some(StateOut {
                outlet: &mut states,
                source: id,
                epoch,
                tick_hz: hz,
            }),
        }),
        &transport::clock::Monotonic,
        PacerConfig::for_period((1e9 / hz).round() as u64),
        &mut || stop.load(Ordering::Relaxed),
        None,
        first,
    )?;
    Ok((frames.0, stats))
}

/// Run a site until `stop`; every stepped tick recorded (on the host's clock: a site's emulated
/// skewed clock, [`Runner::clock`], is moved back, so the records compare with the source's).
pub fn run_site(mut runner: Runner, stop: &AtomicBool) -> Result<Vec<Rec>, RemoteError> {
    let mut recs = Vec::new();
    let clock = runner.clock();
    while !stop.load(Ordering::Relaxed) {
        let now = clock.now();
        if let Some(k) = runner.poll(now)? {
            let v = runner.frame.lungs.iter().map(|l| l.volume_ml).sum::<f32>();
            let sched = clock.host(runner.time_of(k).unwrap_or(now as i128));
            recs.push((sched, now_ns(), k, v, runner.frame.lungs[0].cycle));
        }
        let wake = runner
            .next_wake()
            .map(|t| clock.host_span(t - clock.now() as i128))
            .unwrap_or(1_000_000)
            .clamp(0, 2_000_000);
        std::thread::sleep(Duration::from_nanos(wake as u64));
    }
    Ok(recs)
}

/// How late the records' ticks were stepped after their scheduled times.
fn lateness(recs: &[Rec]) -> Lateness {
    Lateness::of(recs.iter().map(|r| (r.0, r.1 as i128)))
}

/// Per-cycle drift of `site` against `source` over `[from, to)`: (mean over cycles, worst cycle),
/// %. Each engine shows the volume of the last tick it stepped (at its actual or, with `sched`,
/// its scheduled time) until its next, so |V_site(t) − V_source(t)| is piecewise constant and
/// its mean over each of the source's cycles is integrated exactly, segment by segment between
/// the two lists' step times. (Sampling it on a 1 ms grid, as the harness did before, aliases: the
/// 60 Hz period is 50/3 ms, so the grid meets the ticks at only three phases, and two engines a
/// fraction of a millisecond apart measured either 0 or ≈ 0.016 % depending on whether a phase fell
/// between their step times.)
fn drift(source: &[Rec], site: &[Rec], from: i128, to: i128, tv: f64, sched: bool) -> (f64, f64) {
    let time = |r: &Rec| if sched { r.0 } else { r.1 as i128 };
    // The records shown at `t`: the last at or before it in each list (both sorted by `time`).
    let (mut i, mut j) = (
        source.partition_point(|r| time(r) <= from),
        site.partition_point(|r| time(r) <= from),
    );
    // (source's cycle, ∫|ΔV|/TV dt in %·ns, ns with both shown).
    let mut cycles: Vec<(u32, f64, f64)> = Vec::new();
    let mut t = from;
    while t < to {
        let next = [source.get(i), site.get(j)]
            .into_iter()
            .flatten()
            .map(time)
            .fold(to, i128::min);
        if let (Some(a), Some(b)) = (i.checked_sub(1), j.checked_sub(1)) {
            let (a, b) = (&source[a], &site[b]);
            let dt = (next - t) as f64;
            let d = (a.3 as f64 - b.3 as f64).abs() / tv * 100.0;
            match cycles.last_mut() {
                Some(c) if c.0 == a.4 => {
                    c.1 += d * dt;
                    c.2 += dt;
                }
                _ => cycles.push((a.4, d * dt, dt)),
            }
        }
        t = next;
        while source.get(i).is_some_and(|r| time(r) <= t) {
            i += 1;
        }
        while site.get(j).is_some_and(|r| time(r) <= t) {
            j += 1;
        }
    }
    let per: Vec<f64> = cycles
        .iter()
        .filter(|c| c.2 > 0.0)
        .map(|c| c.1 / c.2)
        .collect();
    let mean = per.iter().sum::<f64>() / per.len().max(1) as f64;
    (mean, per.iter().copied().fold(0.0, f64::max))
}

/// The harness's link lease, ms (a lost peer is seen fast).
const LEASE_MS: u64 = 2000;

/// A session on 127.0.0.1: `mode` listening on a free port (`via` none) or connecting to `via`;
/// TLS and sealed packets with `auth`.
fn local_net(
    mode: &'static str,
    via: Option<&str>,
    auth: Option<std::sync::Arc<crate::keys::Room>>,
) -> Net {
    let proto = if auth.is_some() { "tls" } else { "tcp" };
    Net {
        listen: match via {
            None => vec![format!("{proto}/127.0.0.1:0")],
            Some(_) => Vec::new(),
        },
        connect: via.map(|v| vec![v.to_string()]).unwrap_or_default(),
        lease_ms: LEASE_MS,
        mode,
        auth,
        acl: true,
    }
}

/// The source's session: a peer listening on 127.0.0.1, or a client of the router `via`.
fn source_net(via: Option<&str>, auth: Option<std::sync::Arc<crate::keys::Room>>) -> Net {
    local_net(if via.is_some() { "client" } else { "peer" }, via, auth)
}

/// Check the harness's options; the emulated impairment.
fn check(args: &HarnessArgs) -> Result<Impairment, RemoteError> {
    if args.sites == 0 || args.sites > 64 {
        return Err(RemoteError::Usage(format!(
            "--sites {}: use 1–64",
            args.sites
        )));
    }
    if !(args.seconds.is_finite() && args.seconds > 0.0 && args.seconds <= 3600.0) {
        return Err(RemoteError::Usage(format!(
            "--seconds {}: use more than 0 and at most 3600",
            args.seconds
        )));
    }
    if !(1..=10_000).contains(&args.probe_ms) {
        return Err(RemoteError::Usage(format!(
            "--probe-ms {}: use 1–10000",
            args.probe_ms
        )));
    }
    crate::clock::LocalClock::skewed(args.skew_ppm, 0)
        .map_err(|e| RemoteError::Usage(format!("--skew-ppm {e}")))?;
    crate::clock::LocalClock::skewed(args.relay_skew_ppm, 0)
        .map_err(|e| RemoteError::Usage(format!("--relay-skew-ppm {e}")))?;
    if args.relay_skew_ppm != 0.0 && !args.router {
        return Err(RemoteError::Usage(
            "--relay-skew-ppm needs --router (the time relay runs beside the router)".into(),
        ));
    }
    let imp = Impairment {
        delay_ms: args.delay_ms,
        jitter_ms: args.jitter_ms,
        loss: args.loss,
        seed: args.seed,
        clock: crate::clock::LocalClock::default(),
        no_rate: args.no_clock_rate,
    };
    imp.check().map_err(RemoteError::Usage)?;
    Ok(imp)
}

/// Run the source engine for `seconds` (+ 0.5) from now and measure what its process and tick
/// thread spent and its sockets carried meanwhile.
fn timed_source(
    core: EngineCore,
    hz: f64,
    src: &Source,
    id: u64,
    seconds: f64,
    stop: &AtomicBool,
) -> Result<(Vec<Rec>, SourceCost), RemoteError> {
    use crate::measure::{cpu_s, tcp_bytes, Who};
    let probes0 = src.counts.probes.load(Ordering::Relaxed);
    let (t0, p0, th0, b0) = (
        now_ns(),
        cpu_s(Who::Process),
        cpu_s(Who::Thread),
        tcp_bytes(),
    );
    let recs = std::thread::scope(|s| {
        let stopper = s.spawn(move || {
            let end = now_ns() + ((seconds + 0.5) * 1e9) as u64;
            while !stop.load(Ordering::Relaxed) && now_ns() < end {
                std::thread::sleep(Duration::from_millis(20));
            }
            stop.store(true, Ordering::Relaxed);
        });
        let r = run_source(core, hz, src, id, now_ns(), stop);
        stop.store(true, Ordering::Relaxed);
        let _ = stopper.join();
        r
    })?;
    let (recs, stats) = recs;
    let (sent, received) = match (b0, tcp_bytes()) {
        (Some(a), Some(b)) => b.since(&a),
        _ => (0, 0),
    };
    let cost = SourceCost {
        wall_s: (now_ns() - t0) as f64 / 1e9,
        cpu_s: cpu_s(Who::Process) - p0,
        tick_thread_cpu_s: cpu_s(Who::Thread) - th0,
        tcp_bytes_sent: sent,
        tcp_bytes_received: received,
        deadlines_skipped: stats.pacer.skipped_deadlines,
        probes: src.counts.probes.load(Ordering::Relaxed) - probes0,
    };
    Ok((recs, cost))
}

/// `lungdyn remote harness-source`: the harness's source in this process (see
/// [`SourceChildArgs`]).
pub fn source_child(args: &SourceChildArgs) -> Result<(), RemoteError> {
    use std::io::{BufRead, Write};
    let h = &args.harness;
    let imp = check(h)?;
    let (scene, core) = harness_core(h.breaths_per_min)?;
    let keys = Keys::new("harness")?;
    let id = site_id(0);
    let auth = run_room(h.keys_dir.as_deref(), "source")?;
    let source = Source::open(&source_net(args.via.as_deref(), auth), &keys, id, imp)?;
    let endpoint = match &args.via {
        Some(v) => v.clone(),
        None => locator(source.session())?,
    };
    let io = |e: std::io::Error| RemoteError::Usage(format!("harness source: {e}"));
    let mut out = std::io::stdout().lock();
    writeln!(out, "{endpoint}").map_err(io)?;
    out.flush().map_err(io)?;
    let mut line = String::new();
    std::io::stdin().lock().read_line(&mut line).map_err(io)?;
    if line.trim() != "go" {
        return Err(RemoteError::Usage(format!(
            "harness source: expected \"go\" on standard input, got {line:?}"
        )));
    }
    let stop = AtomicBool::new(false);
    let (recs, cost) = timed_source(core, scene.engine.tick_hz, &source, id, h.seconds, &stop)?;
    let c = &source.counts;
    let report = ChildReport {
        recs: recs
            .iter()
            .map(|r| (r.0, r.1, r.2, r.3.to_bits(), r.4))
            .collect(),
        states: c.states.load(Ordering::Relaxed),
        state_bytes: c.state_bytes.load(Ordering::Relaxed),
        sites_seen: source.sites(),
        cost,
    };
    let json = serde_json::to_string(&report).map_err(|e| RemoteError::Usage(e.to_string()))?;
    writeln!(out, "{json}").map_err(io)?;
    out.flush().map_err(io)
}

/// The source in its own process; killed if the harness fails before it ends.
struct ChildSource {
    child: std::process::Child,
    stdout: std::io::BufReader<std::process::ChildStdout>,
    endpoint: String,
}

impl Drop for ChildSource {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}

impl ChildSource {
    fn spawn(
        exe: &std::path::Path,
        args: &HarnessArgs,
        via: Option<&str>,
    ) -> Result<Self, RemoteError> {
        use std::io::BufRead;
        let mut cmd = std::process::Command::new(exe);
        cmd.args(["remote", "harness-source", "--sites"])
            .arg(args.sites.to_string())
            .arg("--seconds")
            .arg(args.seconds.to_string())
            .arg("--delay-ms")
            .arg(args.delay_ms.to_string())
            .arg("--jitter-ms")
            .arg(args.jitter_ms.to_string())
            .arg("--loss")
            .arg(args.loss.to_string())
            .arg("--seed")
            .arg(args.seed.to_string())
            .arg("--probe-ms")
            .arg(args.probe_ms.to_string());
        if let Some(b) = args.breaths_per_min {
            cmd.arg("--breaths-per-min").arg(b.to_string());
        }
        if let Some(v) = via {
            cmd.arg("--via").arg(v);
        }
        if let Some(d) = &args.keys_dir {
            cmd.arg("--keys-dir").arg(d);
        }
        if args.observer {
            cmd.arg("--observer");
        }
        let io = |e: std::io::Error| {
            RemoteError::Usage(format!("the source process ({}): {e}", exe.display()))
        };
        let mut child = cmd
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .map_err(io)?;
        let stdout = child.stdout.take().expect("piped stdout");
        let mut me = Self {
            child,
            stdout: std::io::BufReader::new(stdout),
            endpoint: String::new(),
        };
        let mut line = String::new();
        me.stdout.read_line(&mut line).map_err(io)?;
        if !(line.trim().starts_with("tcp/") || line.trim().starts_with("tls/")) {
            return Err(RemoteError::Usage(format!(
                "the source process did not start (it printed {line:?}; its error is above)"
            )));
        }
        me.endpoint = line.trim().to_string();
        Ok(me)
    }

    /// Start its engine and wait for its report.
    fn run(&mut self) -> Result<ChildReport, RemoteError> {
        use std::io::{BufRead, Write};
        let io = |e: std::io::Error| RemoteError::Usage(format!("the source process: {e}"));
        let stdin = self.child.stdin.as_mut().expect("piped stdin");
        stdin.write_all(b"go\n").map_err(io)?;
        stdin.flush().map_err(io)?;
        let mut line = String::new();
        self.stdout.read_line(&mut line).map_err(io)?;
        serde_json::from_str(&line).map_err(|e| {
            RemoteError::Usage(format!(
                "the source process's report ({e}): {:?}",
                line.chars().take(200).collect::<String>()
            ))
        })
    }
}

/// The source: in the harness's process or its own.
enum SourceSide {
    Here(Box<Source>),
    Own(ChildSource),
}

/// What the source did, wherever it ran.
struct SourceOutcome {
    recs: Vec<Rec>,
    states: u64,
    state_bytes: u64,
    probes: u64,
    sites_seen: usize,
    deadlines_skipped: u64,
    cost: Option<SourceCost>,
}

impl SourceOutcome {
    /// A source in the harness's process: its counts; its cost is the sites' too, so none.
    fn here(src: &Source, recs: Vec<Rec>, cost: SourceCost) -> Self {
        let c = &src.counts;
        SourceOutcome {
            recs,
            states: c.states.load(Ordering::Relaxed),
            state_bytes: c.state_bytes.load(Ordering::Relaxed),
            probes: cost.probes,
            sites_seen: src.sites(),
            deadlines_skipped: cost.deadlines_skipped,
            // Its process is the sites' too: not the source's own cost.
            cost: None,
        }
    }

    /// A source in its own process: what it reported, its cost included.
    fn own(c: ChildReport) -> Self {
        SourceOutcome {
            recs: c
                .recs
                .iter()
                .map(|r| (r.0, r.1, r.2, f32::from_bits(r.3), r.4))
                .collect(),
            states: c.states,
            state_bytes: c.state_bytes,
            probes: c.cost.probes,
            sites_seen: c.sites_seen,
            deadlines_skipped: c.cost.deadlines_skipped,
            cost: Some(c.cost),
        }
    }
}

/// The relay's counters at the start of the measured window.
#[derive(Debug, Clone, Copy)]
struct Snapshot {
    at: u64,
    answered: u64,
    to_source: u64,
    bytes: u64,
    cpu_s: f64,
}

impl Snapshot {
    fn of(c: &RelayCounts, at: u64) -> Self {
        Self {
            at,
            answered: c.answered.load(Ordering::Relaxed),
            to_source: c.probes_to_source.load(Ordering::Relaxed),
            bytes: c.reply_bytes.load(Ordering::Relaxed),
            cpu_s: c.threads_cpu_s(),
        }
    }

    /// The relay's figures from this snapshot to `end`.
    fn report(self, r: &Relay, end: u64) -> RelayReport {
        let b = Snapshot::of(&r.counts, end);
        let wall_s = (end.saturating_sub(self.at) as f64 / 1e9).max(1e-9);
        let per_minute = |a: u64, b: u64| b.saturating_sub(a) as f64 / wall_s * 60.0;
        RelayReport {
            probes_answered_per_minute: per_minute(self.answered, b.answered),
            probes_to_source_per_minute: per_minute(self.to_source, b.to_source),
            reply_bytes_per_minute: per_minute(self.bytes, b.bytes),
            threads_cpu_percent: (b.cpu_s - self.cpu_s).max(0.0) / wall_s * 100.0,
            unanswered: r.counts.unanswered.load(Ordering::Relaxed),
            offset_ms: r.offset_ns().map(|o| o as f64 / 1e6),
            delay_ms: r.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6,
            clock: ClockFigures::of(&r.path, r.clock),
        }
    }
}

/// Why the harness does not use netem here: `tc qdisc add dev lo root netem delay 1ms` run once
/// in a private network namespace (`unshare --net`: nothing on this machine changes, the namespace
/// ends with the command), its outcome in words.
pub fn netem_probe() -> String {
    let out = std::process::Command::new("unshare")
        .args([
            "--net", "tc", "qdisc", "add", "dev", "lo", "root", "netem", "delay", "1ms",
        ])
        .stdin(std::process::Stdio::null())
        .output();
    netem_reason(out.map(|o| {
        (
            o.status.success(),
            String::from_utf8_lossy(&o.stderr).into(),
        )
    }))
}

/// [`netem_probe`]'s words for the probe's outcome: (succeeded, its standard error), or why it
/// could not run.
pub fn netem_reason(out: std::io::Result<(bool, String)>) -> String {
    let probe = "probed with `unshare --net tc qdisc add dev lo root netem delay 1ms`";
    match out {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            format!("`unshare` (util-linux) is not installed, so netem could not be probed ({e})")
        }
        Err(e) => format!("the netem probe could not run ({probe}): {e}"),
        Ok((true, _)) => format!(
            "netem works on this machine ({probe}), but the harness has no per-site network \
             namespace and veth path: emulated in-process instead"
        ),
        Ok((false, err)) => {
            let first = err.lines().next().unwrap_or("").trim().to_string();
            if err.contains("qdisc kind is unknown") {
                format!("this kernel has no sch_netem qdisc ({probe}: \"{first}\")")
            } else if err.contains("Operation not permitted") || err.contains("EPERM") {
                format!(
                    "not permitted to make a network namespace or add a qdisc (needs \
                     CAP_SYS_ADMIN and CAP_NET_ADMIN; {probe}: \"{first}\")"
                )
            } else if err.contains("No such file or directory") || err.contains("failed to execute")
            {
                format!("`tc` (iproute2) is not installed ({probe}: \"{first}\")")
            } else {
                format!("the netem probe failed ({probe}: \"{first}\")")
            }
        }
    }
}

/// Run the harness.
pub fn run(args: &HarnessArgs) -> Result<HarnessReport, RemoteError> {
    let imp = check(args)?;
    let (scene, core) = harness_core(args.breaths_per_min)?;
    let hz = scene.engine.tick_hz;
    let (_, site_core) = harness_core(None)?;
    let tv = core
        .lung(Side::Right)
        .map(|l| l.breathing().boundary().tv_ml)
        .unwrap_or(500.0);
    let keys = Keys::new("harness")?;
    // Every participant's own certificate of a room made for this run (removed at the end).
    let run_keys = match args.transport {
        Transport::Tls => Some(RunKeys::make(args.sites, args.observer)?),
        Transport::Tcp => None,
    };
    let mut args = args.clone();
    args.keys_dir = run_keys.as_ref().map(|k| k.dir.clone());
    let args = &args;
    let kd = args.keys_dir.as_deref();
    // The emulated clocks (equal to the host's now, then running at their rates).
    let epoch = now_ns();
    let skewed = |ppm: f64| {
        crate::clock::LocalClock::skewed(ppm, epoch).map_err(|e| RemoteError::Usage(e.to_string()))
    };
    let (site_clock, relay_clock) = (skewed(args.skew_ppm)?, skewed(args.relay_skew_ppm)?);
    // A router in this process: everyone else is its client.
    let router = if args.router {
        Some(local_net("router", None, run_room(kd, "router")?).open()?)
    } else {
        None
    };
    let via = router.as_ref().map(locator).transpose()?;
    // The time relay beside the router, in its process: it probes the source as a site would.
    let relay = match &router {
        Some(r) => {
            let mut i = imp;
            i.seed = args.seed.wrapping_add(0x7e1a);
            i.clock = relay_clock;
            let guard = crate::seal::Guard::new(run_room(kd, "router")?);
            Some(Relay::open(
                r,
                &keys,
                site_id(1000),
                i,
                args.probe_ms,
                guard,
            )?)
        }
        None => None,
    };
    let clock = if relay.is_some() {
        ClockSync::Relay
    } else {
        ClockSync::Source
    };
    let source_id = site_id(0);
    let side = match &args.source_exe {
        None => SourceSide::Here(Box::new(Source::open(
            &source_net(via.as_deref(), run_room(kd, "source")?),
            &keys,
            source_id,
            imp,
        )?)),
        Some(exe) => SourceSide::Own(ChildSource::spawn(exe, args, via.as_deref())?),
    };
    let endpoint = match (&via, &side) {
        (Some(v), _) => v.clone(),
        (None, SourceSide::Here(s)) => locator(s.session())?,
        (None, SourceSide::Own(c)) => c.endpoint.clone(),
    };
    let (sites, joins) = open_sites(
        args,
        imp,
        site_clock,
        &endpoint,
        via.is_some(),
        kd,
        &keys,
        clock,
    )?;
    // Let the probes measure the path before the first state.
    std::thread::sleep(Duration::from_millis(1000));
    let first_answer = first_answers(&sites, &joins);
    let stop = AtomicBool::new(false);
    let recs: Mutex<Vec<(usize, Vec<Rec>)>> = Mutex::new(Vec::new());
    let result: Mutex<Option<RemoteError>> = Mutex::new(None);
    let harness_cpu0 = crate::measure::cpu_s(crate::measure::Who::Process);
    let relay0 = relay.as_ref().map(|r| Snapshot::of(&r.counts, now_ns()));
    let mut side = side;
    let outcome = std::thread::scope(|s| {
        for (k, site) in sites.iter().enumerate() {
            let (stop, recs, result) = (&stop, &recs, &result);
            // The site's own engine, from the default scene: the packets make it breathe the
            // source's breath.
            let runner = site
                .runner(site_core.clone(), hz)
                .expect("a new site's runner");
            s.spawn(move || match run_site(runner, stop) {
                Ok(r) => recs.lock().expect("records").push((k, r)),
                Err(e) => *result.lock().expect("result") = Some(e),
            });
        }
        let r = match &mut side {
            SourceSide::Here(src) => {
                timed_source(core.clone(), hz, src, source_id, args.seconds, &stop)
                    .map(|(recs, cost)| SourceOutcome::here(src, recs, cost))
            }
            SourceSide::Own(child) => child.run().map(SourceOutcome::own),
        };
        stop.store(true, Ordering::Relaxed);
        r
    })?;
    let harness_cpu_s = crate::measure::cpu_s(crate::measure::Who::Process) - harness_cpu0;
    let relay_report = match (&relay, relay0) {
        (Some(r), Some(a)) => Some(a.report(r, now_ns())),
        _ => None,
    };
    drop(side);
    if let Some(e) = result.lock().expect("result").take() {
        return Err(e);
    }
    let source_recs = &outcome.recs;
    let mut recs = recs.into_inner().expect("records");
    recs.sort_by_key(|(k, _)| *k);
    let per_site: Vec<SiteReport> = recs
        .iter()
        .map(|(k, r)| {
            let join = Join {
                open_ms: joins[*k].1,
                first_clock_answer_ms: first_answer[*k],
            };
            site_report(&sites[*k], r, source_recs, tv, join)
        })
        .collect();
    Ok(harness_report(
        args,
        &imp,
        clock,
        hz,
        tv,
        &outcome,
        per_site,
        relay_report,
        harness_cpu_s,
        sites.iter().map(|s| s.guard.refusals.total()).sum(),
    ))
}

/// Open the harness's `args.sites` sites on `endpoint` (clients of the router when `routed`), each
/// with its own seed; with each, when it began to open and how long its opening took (the link's
/// handshake, the subscriptions, the liveliness token): the time to join.
#[allow(clippy::too_many_arguments)]
fn open_sites(
    args: &HarnessArgs,
    imp: Impairment,
    site_clock: crate::clock::LocalClock,
    endpoint: &str,
    routed: bool,
    kd: Option<&std::path::Path>,
    keys: &Keys,
    clock: ClockSync,
) -> Result<(Vec<Site>, Vec<(u64, f64)>), RemoteError> {
    let mut sites = Vec::new();
    let mut joins: Vec<(u64, f64)> = Vec::new();
    for k in 0..args.sites {
        let mut i = imp;
        i.seed = args.seed.wrapping_add(k as u64 + 1);
        i.clock = site_clock;
        let site_net = local_net(
            if routed { "client" } else { "peer" },
            Some(endpoint),
            run_room(kd, &format!("site-{}", k + 1))?,
        );
        let began = now_ns();
        sites.push(Site::open(
            &site_net,
            keys,
            site_id(k as u64 + 1),
            args.observer,
            i,
            args.probe_ms,
            clock,
        )?);
        joins.push((began, (now_ns() - began) as f64 / 1e6));
    }
    Ok((sites, joins))
}

/// Each site's first clock answer, ms from when it began to open (`joins`); none yet.
fn first_answers(sites: &[Site], joins: &[(u64, f64)]) -> Vec<Option<f64>> {
    sites
        .iter()
        .zip(joins)
        .map(|(site, (began, _))| {
            let at = site.counts.first_probe_ns.load(Ordering::Relaxed);
            (at > 0).then(|| at.saturating_sub(*began) as f64 / 1e6)
        })
        .collect()
}

/// One site's figures against the source's record: drift of the volume (against the source's
/// tick and its schedule), phase error, ticks that differ bit for bit, the site's counts and its
/// path and clock.
fn site_report(site: &Site, r: &[Rec], source_recs: &[Rec], tv: f64, join: Join) -> SiteReport {
    let end = source_recs.last().map_or(0, |r| r.1 as i128);
    // The source's record of tick `k`, found by its tick number rather than assumed at place `k`
    // (the same today: the source records every tick from 0, a skipped deadline shifting when a
    // tick runs, not its number; found so whatever tick a source starts from).
    let source_tick = |k: u64| {
        source_recs
            .binary_search_by_key(&k, |r| r.2)
            .ok()
            .map(|i| &source_recs[i])
    };
    let sched_of = |k: u64| source_tick(k).map(|r| r.0);
    let from = r.first().map_or(end, |x| x.1 as i128);
    let (mean, worst) = drift(source_recs, r, from, end, tv, false);
    let (mean_s, _) = drift(source_recs, r, from, end, tv, true);
    let phase: Vec<(i128, f64)> = r
        .iter()
        .filter_map(|x| sched_of(x.2).map(|s| (s, (x.0 - s).abs() as f64 / 1e6)))
        .collect();
    let last_5_s = phase
        .iter()
        .filter(|p| p.0 >= end - 5_000_000_000)
        .map(|p| p.1)
        .fold(0.0, f64::max);
    let phase: Vec<f64> = phase.into_iter().map(|p| p.1).collect();
    let differing = r
        .iter()
        .filter(|x| source_tick(x.2).is_some_and(|s| s.3.to_bits() != x.3.to_bits()))
        .count();
    let c = &site.counts;
    SiteReport {
        drift_percent_mean: mean,
        drift_percent_worst: worst,
        drift_percent_mean_scheduled: mean_s,
        phase_error_ms_mean: phase.iter().sum::<f64>() / phase.len().max(1) as f64,
        phase_error_ms_worst: phase.iter().copied().fold(0.0, f64::max),
        phase_error_ms_worst_last_5_s: last_5_s,
        ticks: r.len(),
        ticks_differing: differing,
        states_applied: c.applied.load(Ordering::Relaxed),
        refused: c.refused.load(Ordering::Relaxed),
        lost: site.link_counts().lost.load(Ordering::Relaxed),
        predicted_cycles: c.predicted_cycles.load(Ordering::Relaxed),
        delay_ms: site.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6,
        jitter_ms: site.path.jitter_ns.load(Ordering::Relaxed) as f64 / 1e6,
        offset_ms: site.path.offset_at(site.own_clock.now()).unwrap_or(0) as f64 / 1e6,
        clock: ClockFigures::of(&site.path, site.own_clock),
        lateness: lateness(r),
        join,
    }
}

/// The run's report: the sites' figures averaged (or their worst), the traffic per minute, the
/// source's own cost (when it ran in its own process) and how the run was set up.
#[allow(clippy::too_many_arguments)]
fn harness_report(
    args: &HarnessArgs,
    imp: &Impairment,
    clock: ClockSync,
    hz: f64,
    tv: f64,
    outcome: &SourceOutcome,
    per_site: Vec<SiteReport>,
    relay_report: Option<RelayReport>,
    harness_cpu_s: f64,
    refused_seals: u64,
) -> HarnessReport {
    let minutes = outcome.recs.len() as f64 / hz / 60.0;
    let states = outcome.states as f64;
    let n = args.sites as f64;
    let mean = |f: fn(&SiteReport) -> f64| {
        per_site.iter().map(f).sum::<f64>() / per_site.len().max(1) as f64
    };
    let max = |f: fn(&SiteReport) -> f64| per_site.iter().map(f).fold(0.0, f64::max);
    let packets = states * n / minutes;
    let per_frame = outcome.recs.len() as f64 * n / minutes;
    let cost = outcome.cost;
    let per_minute = |f: fn(&SourceCost) -> f64| cost.map(|c| f(&c) / c.wall_s * 60.0);
    HarnessReport {
        sites: args.sites,
        seconds: minutes * 60.0,
        delay_ms: args.delay_ms,
        jitter_ms: args.jitter_ms,
        loss: args.loss,
        emulation: if imp.delay_ms == 0.0 && imp.loss == 0.0 {
            "none: real TCP on 127.0.0.1".to_string()
        } else {
            format!(
                "in-process on every received packet (both directions); netem not used: {}",
                netem_probe()
            )
        },
        transport: match args.transport {
            Transport::Tls => "tls",
            Transport::Tcp => "tcp",
        },
        refused_seals,
        join_open_ms_mean: mean(|s| s.join.open_ms),
        join_open_ms_worst: max(|s| s.join.open_ms),
        join_first_clock_answer_ms_worst: per_site
            .iter()
            .map(|s| s.join.first_clock_answer_ms)
            .try_fold(0.0, |w: f64, a| a.map(|a| w.max(a))),
        drift_percent_mean: mean(|s| s.drift_percent_mean),
        drift_percent_worst: max(|s| s.drift_percent_worst),
        drift_percent_mean_scheduled: mean(|s| s.drift_percent_mean_scheduled),
        phase_error_ms_mean: mean(|s| s.phase_error_ms_mean),
        phase_error_ms_worst: max(|s| s.phase_error_ms_worst),
        phase_error_ms_worst_last_5_s: max(|s| s.phase_error_ms_worst_last_5_s),
        packets_per_minute: packets,
        per_frame_packets_per_minute: per_frame,
        reduction: per_frame / packets.max(f64::MIN_POSITIVE),
        states_per_minute: states / minutes,
        state_bytes_per_minute: outcome.state_bytes as f64 / minutes,
        tidal_volume_ml: tv,
        topology: if args.router {
            "router: the source and every site are clients of a Zenoh router in the harness's \
             process"
        } else {
            "peer to peer: every site connects to the source"
        },
        probe_ms: args.probe_ms,
        skew_ppm: args.skew_ppm,
        relay_skew_ppm: args.relay_skew_ppm,
        no_clock_rate: args.no_clock_rate,
        clock_sync: match clock {
            ClockSync::Relay => {
                "relay: each site probes the time relay beside the router; only the relay probes \
                 the source"
            }
            ClockSync::Source => "source: each site probes the source",
        },
        relay: relay_report,
        probes_per_minute: outcome.probes as f64 / minutes,
        sites_seen_by_source: outcome.sites_seen,
        source_lateness: lateness(&outcome.recs),
        source_deadlines_skipped: outcome.deadlines_skipped,
        source_cpu_s: cost.map(|c| c.cpu_s),
        source_cpu_percent: per_minute(|c| c.cpu_s).map(|v| v / 60.0 * 100.0),
        source_tick_thread_cpu_percent: per_minute(|c| c.tick_thread_cpu_s)
            .map(|v| v / 60.0 * 100.0),
        source_tcp_bytes_sent_per_minute: per_minute(|c| c.tcp_bytes_sent as f64),
        source_tcp_bytes_received_per_minute: per_minute(|c| c.tcp_bytes_received as f64),
        harness_cpu_s,
        load_average_1min: crate::measure::load_average(),
        per_site,
    }
}

/// A lateness summary in words.
fn lateness_words(l: &Lateness) -> String {
    format!(
        "mean {:.3} ms, p50 {:.3}, p90 {:.3}, p99 {:.3}, max {:.3} ms",
        l.mean_ms, l.p50_ms, l.p90_ms, l.p99_ms, l.max_ms
    )
}

/// The report in words.
pub fn print(r: &HarnessReport) {
    println!(
        "remote harness: source + {} site(s), {:.1} s, emulated delay {} ms ± {} ms, loss {} ({})",
        r.sites, r.seconds, r.delay_ms, r.jitter_ms, r.loss, r.emulation
    );
    println!(
        "drift per cycle (mean |V_site − V_source| / TV, TV {:.0} ml): mean {:.5} %, worst cycle \
         {:.5} %; at scheduled tick times {:.5} %",
        r.tidal_volume_ml,
        r.drift_percent_mean,
        r.drift_percent_worst,
        r.drift_percent_mean_scheduled
    );
    println!(
        "phase error: mean {:.3} ms, worst {:.3} ms (over the last 5 s {:.3} ms)",
        r.phase_error_ms_mean, r.phase_error_ms_worst, r.phase_error_ms_worst_last_5_s
    );
    println!(
        "packets: {:.1}/min per-cycle control states vs {:.0}/min per-frame updates ({:.0}× fewer); \
         {:.0} state bytes/min from the source",
        r.packets_per_minute, r.per_frame_packets_per_minute, r.reduction, r.state_bytes_per_minute
    );
    println!(
        "topology: {}; the source saw {} site(s); {:.0} probes/min answered (every {} ms per \
         site); {} deadline(s) skipped by the source engine",
        r.topology,
        r.sites_seen_by_source,
        r.probes_per_minute,
        r.probe_ms,
        r.source_deadlines_skipped
    );
    println!(
        "clock sync: {}{}",
        r.clock_sync,
        if r.no_clock_rate {
            " (--no-clock-rate: the rate is fitted, not applied)"
        } else {
            ""
        }
    );
    if r.skew_ppm != 0.0 || r.relay_skew_ppm != 0.0 {
        println!(
            "emulated clock skew against the source: sites {} ppm, relay {} ppm",
            r.skew_ppm, r.relay_skew_ppm
        );
    }
    println!(
        "joining ({}): a site's session open in {:.1} ms mean, {:.1} ms worst; its first clock \
         answer {}",
        r.transport,
        r.join_open_ms_mean,
        r.join_open_ms_worst,
        r.join_first_clock_answer_ms_worst.map_or(
            "missing for a site after the 1 s settling".to_string(),
            |w| format!("within {w:.1} ms of its start")
        )
    );
    println!(
        "step lateness (actual − scheduled): source {}",
        lateness_words(&r.source_lateness)
    );
    if let Some(x) = &r.relay {
        println!(
            "time relay: answered {:.0} site probes/min ({:.0} reply bytes/min), sent {:.0} \
             probes/min to the source, its threads {:.3} % of a core, {} probe(s) before it \
             answered (8 source replies); its offset to the source {}, delay {:.2} ms; {}",
            x.probes_answered_per_minute,
            x.reply_bytes_per_minute,
            x.probes_to_source_per_minute,
            x.threads_cpu_percent,
            x.unanswered,
            x.offset_ms
                .map_or("none".to_string(), |o| format!("{o:.3} ms")),
            x.delay_ms,
            x.clock.words()
        );
    }
    match (r.source_cpu_percent, r.source_tcp_bytes_sent_per_minute) {
        (Some(cpu), Some(sent)) => println!(
            "source process: CPU {cpu:.2} % of a core (tick thread {:.2} %), TCP {sent:.0} bytes/min \
             sent, {:.0} received",
            r.source_tick_thread_cpu_percent.unwrap_or(0.0),
            r.source_tcp_bytes_received_per_minute.unwrap_or(0.0)
        ),
        _ => println!("source cost: not measured (the source shared the harness's process)"),
    }
    println!(
        "harness process (sites{}): {:.2} CPU s; load average {}",
        if r.topology.starts_with("router") {
            ", router"
        } else {
            ""
        },
        r.harness_cpu_s,
        r.load_average_1min
            .map_or("unknown".to_string(), |l| format!("{l:.2}"))
    );
    for (k, s) in r.per_site.iter().enumerate() {
        println!(
            "  site {k}: drift {:.5} % (worst {:.5} %), phase {:.3} ms, {} ticks ({} differ from \
             the source's), {} states, {} lost, {} refused, {} predicted cycles, delay {:.2} ms, \
             jitter {:.2} ms, offset {:.3} ms ({}); step lateness {}",
            s.drift_percent_mean,
            s.drift_percent_worst,
            s.phase_error_ms_mean,
            s.ticks,
            s.ticks_differing,
            s.states_applied,
            s.lost,
            s.refused,
            s.predicted_cycles,
            s.delay_ms,
            s.jitter_ms,
            s.offset_ms,
            s.clock.words(),
            lateness_words(&s.lateness)
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ticks at 60 Hz from 1 s on breathing a triangle wave of 0 → 500 ml → 0 over `n` ticks
    /// (cycle k / n), each stepped `late` ns after its scheduled time.
    fn triangle(n: u64, cycles: u64, late: i128) -> Vec<Rec> {
        (0..n * cycles)
            .map(|k| {
                let sched = 1_000_000_000 + (k as f64 * 1e9 / 60.0).round() as i128;
                let p = k % n;
                let v = 500.0 * (p.min(n - p) as f32) / (n / 2) as f32;
                (sched, (sched + late) as u64, k, v, (k / n) as u32)
            })
            .collect()
    }

    /// A site stepping the source's volumes δ later shows the previous tick's for δ of each tick:
    /// over a cycle Σ|ΔV| = 2 TV, so the drift is 2 δ / cycle length, at every δ. The 1 ms grid
    /// the harness sampled before met the 50/3 ms ticks at three phases only: started at the
    /// source's step time, as here, it measured 0.0133 % for δ = 10 µs (the true 0.0004 %), and
    /// started just after the site's step it measured 0 — the same two engines, 0 or ≈ 0.013 %.
    #[test]
    fn drift_is_the_exact_mean_of_the_volume_difference_whatever_the_ticks_phase() {
        let (n, cycles) = (300u64, 4u64);
        let cycle_ns = n as f64 * 1e9 / 60.0;
        let source = triangle(n, cycles, 100_000);
        let from = source[0].1 as i128;
        let to = source.last().unwrap().1 as i128;
        for delta_us in [10i128, 50, 85, 150, 400] {
            let site = triangle(n, cycles, 100_000 + delta_us * 1000);
            let (mean, worst) = drift(&source, &site, from, to, 500.0, false);
            let want = 2.0 * (delta_us * 1000) as f64 / cycle_ns * 100.0;
            assert!(
                (mean - want).abs() < 1e-3 * want && (worst - want).abs() < 1e-3 * want,
                "δ = {delta_us} µs: drift {mean} % (worst {worst} %), want {want} %"
            );
            // A site as much early drifts as much; at the scheduled times (both on time) none.
            let early = triangle(n, cycles, 100_000 - delta_us * 1000);
            let (m, _) = drift(&source, &early, from, to, 500.0, false);
            assert!(
                (m - want).abs() < 1e-3 * want,
                "early by {delta_us} µs: {m} %"
            );
            assert_eq!(drift(&source, &site, from, to, 500.0, true), (0.0, 0.0));
        }
    }

    /// Each outcome of the netem probe is named precisely (the words `tc` and `unshare` print).
    #[test]
    fn the_netem_probe_says_why_netem_is_not_used() {
        let said = |ok: bool, err: &str| netem_reason(Ok((ok, err.to_string())));
        let e = said(false, "Error: Specified qdisc kind is unknown.\n");
        assert!(
            e.contains("no sch_netem") && e.contains("Specified qdisc kind is unknown"),
            "{e}"
        );
        let e = said(false, "unshare: unshare failed: Operation not permitted\n");
        assert!(
            e.contains("not permitted") && e.contains("CAP_NET_ADMIN"),
            "{e}"
        );
        let e = said(
            false,
            "unshare: failed to execute tc: No such file or directory\n",
        );
        assert!(e.contains("`tc` (iproute2) is not installed"), "{e}");
        let e = said(true, "");
        assert!(e.contains("netem works") && e.contains("in-process"), "{e}");
        let e = said(false, "RTNETLINK answers: Invalid argument\n");
        assert!(
            e.contains("failed") && e.contains("Invalid argument"),
            "{e}"
        );
        let e = netem_reason(Err(std::io::Error::from(std::io::ErrorKind::NotFound)));
        assert!(e.contains("`unshare` (util-linux) is not installed"), "{e}");
    }
}
