//! `lungdyn remote serve` and `lungdyn remote join`: the bridge between an instance's iceoryx2
//! streams and a Zenoh session (iceoryx2's Zenoh tunnel shape: one relay per service).
//!
//! * `serve` runs beside the source's engine (the HMD workstation): it relays the engine's
//!   control-state stream to Zenoh unchanged (decoding each to refuse and count a bad one), answers
//!   the sites' probes, and hands a site's event to the engine as a [`ipc_types::ControlPacket`]
//!   (the engine answers and applies it at its next disease cycle; the states that follow carry
//!   the result to every site at the same cycle).
//! * `join` is a site's engine: it runs the site's own [`engine::runtime::EngineCore`] (its scene's
//!   kernels; the disease course is the source's, carried by the states) driven by the received
//!   states, in step with the source, and publishes its frames on the site's own instance so a
//!   renderer there draws them (`lungdyn renderer --instance SITE --scene SCENE`). Unless
//!   `--observer`, a trainee's action sent to the site's instance (`lungdyn scene event
//!   --instance SITE`) is forwarded to the source.

use std::sync::atomic::Ordering;
use std::time::Duration;

use control_state::{decode, Packet};
use engine::runtime::EngineCore;
use ipc_types::{ControlPacket, ControlReply, Message};
use lung_model::scene::Scene;
use transport::clock::now_ns;
use transport::{iox, Instance, Publish, Receive};

use crate::link::Impairment;
use crate::site::Site;
use crate::source::Source;
use crate::{site_id, Keys, Net, RemoteError};

/// Options of `lungdyn remote serve`.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// The source engine's instance.
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Zenoh endpoint to listen on.
    #[arg(long, default_value = "tcp/0.0.0.0:7447")]
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to (a router, other peers).
    #[arg(long)]
    pub connect: Vec<String>,
    /// The shared session's name (every site uses the same).
    #[arg(long, default_value = "lungdyn")]
    pub room: String,
    /// Stop after this many seconds.
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// Options of `lungdyn remote join`.
#[derive(Debug, Clone, clap::Args)]
pub struct JoinArgs {
    /// The source's Zenoh endpoint (tcp/HOST:7447).
    #[arg(long, required = true)]
    pub connect: Vec<String>,
    /// This site's instance (its renderer attaches to it).
    #[arg(long, default_value = "site")]
    pub instance: String,
    /// The scene (the source's, with its kernels: `lungdyn scene prepare`).
    #[arg(long)]
    pub scene: Option<std::path::PathBuf>,
    /// Watch only: send no events.
    #[arg(long)]
    pub observer: bool,
    /// The shared session's name.
    #[arg(long, default_value = "lungdyn")]
    pub room: String,
    /// Stop after this many seconds.
    #[arg(long)]
    pub seconds: Option<f64>,
}

fn deadline(seconds: Option<f64>) -> Result<Option<u64>, RemoteError> {
    match seconds {
        None => Ok(None),
        Some(s) if s.is_finite() && s > 0.0 && s < 1e7 => Ok(Some(now_ns() + (s * 1e9) as u64)),
        Some(s) => Err(RemoteError::Usage(format!(
            "--seconds {s}: use a positive number of seconds"
        ))),
    }
}

/// Run `lungdyn remote serve`.
pub fn serve(args: &ServeArgs) -> Result<(), RemoteError> {
    transport::stop::install()?;
    let until = deadline(args.seconds)?;
    let keys = Keys::new(&args.room)?;
    let net = Net::peer(&args.listen, &args.connect);
    net.config()?;
    let instance = Instance::new(&args.instance)?;
    let node = iox::node(&instance, "remote-serve")?;
    let mut states = instance.control_state_inlet(&node)?;
    let mut control = instance.control_outlet(&node)?;
    let id = site_id(0);
    let source = Source::open(&net, &keys, id, Impairment::default())?;
    eprintln!(
        "remote serve[{}]: relaying {} to zenoh key {} on {:?} (sites join with lungdyn remote \
         join --connect tcp/THIS_HOST:PORT --room {})",
        instance.name(),
        instance.control_state(),
        keys.state(),
        args.listen,
        args.room
    );
    let (mut refused, mut sites) = (0u64, 0usize);
    while transport::stop::idle(Duration::from_millis(5)) && until.is_none_or(|t| now_ns() < t) {
        let mut failed = None;
        states.drain(&mut |f| {
            if f.check_layout().is_err() {
                refused += 1;
                return;
            }
            match decode(f.encoded()) {
                Ok(Packet::State(_)) => {
                    if let Err(e) = source.publish(f.encoded()) {
                        failed = Some(e);
                    }
                }
                Ok(_) | Err(_) => refused += 1,
            }
        })?;
        if let Some(e) = failed {
            return Err(e);
        }
        for e in source.take_events() {
            // The engine takes (origin, sequence) once and announces the event with both.
            control.publish(&crate::source::control_packet(&e))?;
            eprintln!(
                "remote serve[{}]: event kind {} on lung {} from site {:016x} (its #{}) handed \
                 to the engine",
                instance.name(),
                e.kind,
                e.lung,
                e.origin,
                e.sequence
            );
        }
        let n = source.sites();
        if n != sites {
            eprintln!("remote serve[{}]: {n} site(s) present", instance.name());
            sites = n;
        }
    }
    let c = &source.counts;
    eprintln!(
        "remote serve[{}]: {} states ({} bytes) published, {} probes answered, {} events, {} \
         refused",
        instance.name(),
        c.states.load(Ordering::Relaxed),
        c.state_bytes.load(Ordering::Relaxed),
        c.probes.load(Ordering::Relaxed),
        c.events.load(Ordering::Relaxed),
        refused + c.refused.load(Ordering::Relaxed)
    );
    Ok(())
}

/// Run `lungdyn remote join`.
pub fn join(args: &JoinArgs) -> Result<(), RemoteError> {
    transport::stop::install()?;
    let until = deadline(args.seconds)?;
    let keys = Keys::new(&args.room)?;
    // Endpoints are checked before anything is loaded or opened.
    let net = Net::peer(&[], &args.connect);
    net.config()?;
    let instance = Instance::new(&args.instance)?;
    let _lock = instance.lock("engine")?;
    let scene = Scene::load_or_default(args.scene.as_deref())?;
    let mut core = EngineCore::new(&scene)?;
    core.follow_remote();
    let hz = scene.engine.tick_hz;
    let node = iox::node(&instance, "engine")?;
    let mut outlet = instance.engine_outlet(&node)?;
    let mut control = instance.control_inlet(&node)?;
    // A sender on the site (`lungdyn scene event`) is answered as by an engine: received when sent
    // to the source, applied when the source announces it (with its tick, cycle and outcome).
    let mut replies = instance.control_reply_outlet(&node)?;
    let mut sent: Vec<(u64, ControlPacket)> = Vec::new();
    let site = Site::open(
        &net,
        &keys,
        site_id(0),
        args.observer,
        Impairment::default(),
        500,
    )?;
    eprintln!(
        "remote join[{}]: site {:016x}{} waiting for the source's state on {:?}",
        instance.name(),
        site.id,
        if args.observer { " (observer)" } else { "" },
        args.connect
    );
    let mut runner = site
        .runner(core, hz)
        .ok_or_else(|| RemoteError::Usage("the site's runner was taken".into()))?;
    let mut first = true;
    let mut told = 0usize;
    while !transport::stop::requested() && until.is_none_or(|t| now_ns() < t) {
        let now = now_ns();
        if runner.poll(now)?.is_some() {
            if first {
                first = false;
                eprintln!(
                    "remote join[{}]: in step with the source (delay {:.2} ms, offset {:.3} ms)",
                    instance.name(),
                    site.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6,
                    site.path.offset_ns.load(Ordering::Relaxed) as f64 / 1e6
                );
            }
            runner.frame.stamps.engine_receive_ns = now;
            runner.frame.stamps.engine_publish_ns = now_ns();
            outlet.publish(&runner.frame)?;
        }
        // Each event the source announced, once: who raised it and the cycle every site applies it.
        let mut announced = Vec::new();
        if let Ok(seen) = site.events.lock() {
            announced.extend(seen.iter().skip(told).copied());
            told = seen.len();
        }
        {
            for e in &announced {
                eprintln!(
                    "remote join[{}]: event kind {} on lung {} from {} (its #{}) applies at the \
                     source's cycle {} (tick {})",
                    instance.name(),
                    e.kind,
                    e.lung,
                    if e.origin == site.id {
                        "this site".to_string()
                    } else {
                        format!("site {:016x}", e.origin)
                    },
                    e.sequence,
                    e.apply_cycle,
                    e.apply_tick
                );
                let Some(k) = sent
                    .iter()
                    .position(|(n, _)| e.origin == site.id && *n == e.sequence)
                else {
                    continue;
                };
                let (_, p) = sent.remove(k);
                let mut r = ControlReply {
                    status: ipc_types::REPLY_APPLIED,
                    sequence: p.sequence,
                    tick: e.apply_tick,
                    cycle: e.apply_cycle,
                    kind: e.kind,
                    lung: e.lung,
                    outcome: e.outcome,
                    ..Default::default()
                };
                r.set_text(&["applied by the source; every site switches at that tick"]);
                replies.publish(&r)?;
            }
        }
        let mut events = Vec::new();
        control.drain(&mut |p: &ControlPacket| events.push(*p))?;
        for p in events {
            let mut r = ControlReply {
                sequence: p.sequence,
                tick: runner.last_tick().unwrap_or(0),
                kind: p.kind,
                lung: p.lung,
                ..Default::default()
            };
            match site.send_event(p.kind, p.lung) {
                Ok(n) => {
                    eprintln!(
                        "remote join[{}]: event kind {} sent to the source (#{n})",
                        instance.name(),
                        p.kind
                    );
                    r.status = ipc_types::REPLY_RECEIVED;
                    r.set_text(&["sent to the source; it applies it at a cycle it announces"]);
                    if sent.len() == 64 {
                        sent.remove(0);
                    }
                    sent.push((n, p));
                }
                Err(e) => {
                    eprintln!("remote join[{}]: {e}", instance.name());
                    r.status = ipc_types::REPLY_IGNORED;
                    r.set_text(&["ignored: ", &e.to_string()]);
                }
            }
            replies.publish(&r)?;
        }
        let wake = runner
            .next_wake()
            .map(|t| t - now_ns() as i128)
            .unwrap_or(2_000_000)
            .clamp(0, 2_000_000);
        std::thread::sleep(Duration::from_nanos(wake as u64));
    }
    let c = &site.counts;
    eprintln!(
        "remote join[{}]: {} disease cycle(s) announced in time, {} late",
        instance.name(),
        c.announced_in_time.load(Ordering::Relaxed),
        c.announced_late.load(Ordering::Relaxed)
    );
    eprintln!(
        "remote join[{}]: {} states applied, {} repeated, {} refused{}, {} cycles started before \
         their state",
        instance.name(),
        c.applied.load(Ordering::Relaxed),
        c.repeated.load(Ordering::Relaxed),
        c.refused.load(Ordering::Relaxed),
        site.last_refusal
            .lock()
            .ok()
            .and_then(|g| g.clone())
            .map(|w| format!(" (last: {w})"))
            .unwrap_or_default(),
        c.predicted_cycles.load(Ordering::Relaxed)
    );
    Ok(())
}
