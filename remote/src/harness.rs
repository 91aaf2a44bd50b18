//! `lungdyn remote harness`: a source and N sites on loopback, each its own Zenoh session and
//! engine, and the seed's figures: drift = mean |V_site(t) − V_source(t)| / TV per breathing cycle
//! (mean and worst cycle per site), the phase error of each site's schedule, packets per minute,
//! and what per-frame updates would send.
//!
//! Delay, jitter and loss are emulated inside the process, on every packet a session receives
//! (states and probe replies at the sites, probes at the source: both directions), by
//! [`crate::link`]: netem in network namespaces needs `CAP_NET_ADMIN` and veth plumbing per site,
//! which this harness does not do. Zenoh itself runs over real TCP on 127.0.0.1 with multicast
//! scouting off.
//!
//! V(t) is what each engine shows at wall time t: the volume of the last tick it stepped by then
//! (both lungs), sampled every millisecond; so the drift includes the OS's lateness in waking each
//! thread, not only the protocol. `drift_percent_mean_scheduled` evaluates the same at each
//! engine's scheduled tick times (the protocol's own error: offset estimate and state timing).

use std::cell::Cell;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
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
use crate::site::{Runner, Site};

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
    /// Cycles started before their state arrived.
    pub predicted_cycles: u64,
    /// Smoothed one-way delay, ms.
    pub delay_ms: f64,
    /// Round-trip variation, ms.
    pub jitter_ms: f64,
    /// Estimated clock offset, ms (the true one is 0: one machine, one clock).
    pub offset_ms: f64,
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
    /// How the network was emulated.
    pub emulation: &'static str,
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
        .find(|l| l.starts_with("tcp/"))
        .ok_or_else(|| RemoteError::Usage("the source listens on no tcp locator".into()))
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

/// Run a site until `stop`; every stepped tick recorded.
pub fn run_site(mut runner: Runner, stop: &AtomicBool) -> Result<Vec<Rec>, RemoteError> {
    let mut recs = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        let now = now_ns();
        if let Some(k) = runner.poll(now)? {
            let v = runner.frame.lungs.iter().map(|l| l.volume_ml).sum::<f32>();
            let sched = runner.time_of(k).unwrap_or(now as i128);
            recs.push((sched, now_ns(), k, v, runner.frame.lungs[0].cycle));
        }
        let wake = runner
            .next_wake()
            .map(|t| t - now_ns() as i128)
            .unwrap_or(1_000_000)
            .clamp(0, 2_000_000);
        std::thread::sleep(Duration::from_nanos(wake as u64));
    }
    Ok(recs)
}

/// Volume shown at `t` by a record list sorted by the chosen time: the last record at or before.
fn shown_at(recs: &[Rec], t: i128, sched: bool) -> Option<&Rec> {
    let time = |r: &Rec| if sched { r.0 } else { r.1 as i128 };
    let i = recs.partition_point(|r| time(r) <= t);
    (i > 0).then(|| &recs[i - 1])
}

/// Per-cycle drift of `site` against `source` over `[from, to)` sampled every ms: (mean over
/// cycles, worst cycle), %.
fn drift(source: &[Rec], site: &[Rec], from: i128, to: i128, tv: f64, sched: bool) -> (f64, f64) {
    let mut cycles: Vec<(u32, f64, u64)> = Vec::new();
    let mut t = from;
    while t < to {
        if let (Some(a), Some(b)) = (shown_at(source, t, sched), shown_at(site, t, sched)) {
            let d = (a.3 as f64 - b.3 as f64).abs() / tv * 100.0;
            match cycles.last_mut() {
                Some(c) if c.0 == a.4 => {
                    c.1 += d;
                    c.2 += 1;
                }
                _ => cycles.push((a.4, d, 1)),
            }
        }
        t += 1_000_000;
    }
    let per: Vec<f64> = cycles.iter().map(|c| c.1 / c.2 as f64).collect();
    let mean = per.iter().sum::<f64>() / per.len().max(1) as f64;
    (mean, per.iter().copied().fold(0.0, f64::max))
}

/// Run the harness.
pub fn run(args: &HarnessArgs) -> Result<HarnessReport, RemoteError> {
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
    let imp = Impairment {
        delay_ms: args.delay_ms,
        jitter_ms: args.jitter_ms,
        loss: args.loss,
        seed: args.seed,
    };
    imp.check().map_err(RemoteError::Usage)?;
    let (scene, core) = harness_core(args.breaths_per_min)?;
    let hz = scene.engine.tick_hz;
    let (_, site_core) = harness_core(None)?;
    let tv = core
        .lung(Side::Right)
        .map(|l| l.breathing().boundary().tv_ml)
        .unwrap_or(500.0);
    let keys = Keys::new("harness")?;
    let mut net = Net::peer(&["tcp/127.0.0.1:0".to_string()], &[]);
    net.lease_ms = 2000;
    let source_id = site_id(0);
    let source = Source::open(&net, &keys, source_id, imp)?;
    let endpoint = locator(source.session())?;
    let site_net = {
        let mut n = Net::peer(&[], &[endpoint]);
        n.lease_ms = 2000;
        n
    };
    let mut sites = Vec::new();
    for k in 0..args.sites {
        let mut i = imp;
        i.seed = args.seed.wrapping_add(k as u64 + 1);
        sites.push(Site::open(
            &site_net,
            &keys,
            site_id(k as u64 + 1),
            args.observer,
            i,
            50,
        )?);
    }
    // Let the probes measure the path before the first state.
    std::thread::sleep(Duration::from_millis(1000));
    let stop = Arc::new(AtomicBool::new(false));
    let epoch = now_ns();
    let recs: Mutex<Vec<(usize, Vec<Rec>)>> = Mutex::new(Vec::new());
    let result: Mutex<Option<RemoteError>> = Mutex::new(None);
    let source_recs = std::thread::scope(|s| {
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
        let stopper = {
            let stop = stop.clone();
            let secs = args.seconds;
            s.spawn(move || {
                std::thread::sleep(Duration::from_secs_f64(secs + 0.5));
                stop.store(true, Ordering::Relaxed);
            })
        };
        let r = run_source(core.clone(), hz, &source, source_id, epoch, &stop);
        stop.store(true, Ordering::Relaxed);
        let _ = stopper.join();
        r.map(|(recs, _)| recs)
    })?;
    if let Some(e) = result.lock().expect("result").take() {
        return Err(e);
    }
    let mut per_site = Vec::new();
    let mut recs = recs.into_inner().expect("records");
    recs.sort_by_key(|(k, _)| *k);
    let end = source_recs.last().map_or(0, |r| r.1 as i128);
    let sched_of = |k: u64| source_recs.get(k as usize).map(|r| r.0);
    for (k, r) in &recs {
        let site = &sites[*k];
        let from = r.first().map_or(end, |x| x.1 as i128);
        let (mean, worst) = drift(&source_recs, r, from, end, tv, false);
        let (mean_s, _) = drift(&source_recs, r, from, end, tv, true);
        let phase: Vec<f64> = r
            .iter()
            .filter_map(|x| sched_of(x.2).map(|s| (x.0 - s).abs() as f64 / 1e6))
            .collect();
        let differing = r
            .iter()
            .filter(|x| {
                source_recs
                    .get(x.2 as usize)
                    .is_some_and(|s| s.3.to_bits() != x.3.to_bits())
            })
            .count();
        let c = &site.counts;
        per_site.push(SiteReport {
            drift_percent_mean: mean,
            drift_percent_worst: worst,
            drift_percent_mean_scheduled: mean_s,
            phase_error_ms_mean: phase.iter().sum::<f64>() / phase.len().max(1) as f64,
            phase_error_ms_worst: phase.iter().copied().fold(0.0, f64::max),
            ticks: r.len(),
            ticks_differing: differing,
            states_applied: c.applied.load(Ordering::Relaxed),
            refused: c.refused.load(Ordering::Relaxed),
            lost: site.link_counts().lost.load(Ordering::Relaxed),
            predicted_cycles: c.predicted_cycles.load(Ordering::Relaxed),
            delay_ms: site.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6,
            jitter_ms: site.path.jitter_ns.load(Ordering::Relaxed) as f64 / 1e6,
            offset_ms: site.path.offset_ns.load(Ordering::Relaxed) as f64 / 1e6,
        });
    }
    let minutes = source_recs.len() as f64 / hz / 60.0;
    let states = source.counts.states.load(Ordering::Relaxed) as f64;
    let n = args.sites as f64;
    let mean = |f: fn(&SiteReport) -> f64| {
        per_site.iter().map(f).sum::<f64>() / per_site.len().max(1) as f64
    };
    let max = |f: fn(&SiteReport) -> f64| per_site.iter().map(f).fold(0.0, f64::max);
    let packets = states * n / minutes;
    let per_frame = source_recs.len() as f64 * n / minutes;
    Ok(HarnessReport {
        sites: args.sites,
        seconds: minutes * 60.0,
        delay_ms: args.delay_ms,
        jitter_ms: args.jitter_ms,
        loss: args.loss,
        emulation: if imp == Impairment::default() || (imp.delay_ms == 0.0 && imp.loss == 0.0) {
            "none: real TCP on 127.0.0.1"
        } else {
            "in-process on every received packet (both directions); netem not used"
        },
        drift_percent_mean: mean(|s| s.drift_percent_mean),
        drift_percent_worst: max(|s| s.drift_percent_worst),
        drift_percent_mean_scheduled: mean(|s| s.drift_percent_mean_scheduled),
        phase_error_ms_mean: mean(|s| s.phase_error_ms_mean),
        phase_error_ms_worst: max(|s| s.phase_error_ms_worst),
        packets_per_minute: packets,
        per_frame_packets_per_minute: per_frame,
        reduction: per_frame / packets.max(f64::MIN_POSITIVE),
        states_per_minute: states / minutes,
        state_bytes_per_minute: source.counts.state_bytes.load(Ordering::Relaxed) as f64 / minutes,
        tidal_volume_ml: tv,
        per_site,
    })
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
        "phase error: mean {:.3} ms, worst {:.3} ms",
        r.phase_error_ms_mean, r.phase_error_ms_worst
    );
    println!(
        "packets: {:.1}/min per-cycle control states vs {:.0}/min per-frame updates ({:.0}× fewer); \
         {:.0} state bytes/min from the source",
        r.packets_per_minute, r.per_frame_packets_per_minute, r.reduction, r.state_bytes_per_minute
    );
    for (k, s) in r.per_site.iter().enumerate() {
        println!(
            "  site {k}: drift {:.5} % (worst {:.5} %), phase {:.3} ms, {} ticks ({} differ from \
             the source's), {} states, {} lost, {} refused, {} predicted cycles, delay {:.2} ms, \
             jitter {:.2} ms, offset {:.3} ms",
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
            s.offset_ms
        );
    }
}
