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
use lung_model::scene::SceneExt;
use lung_model::scene_remote::{RemoteRole, RemoteScene};

/// Options of `lungdyn remote serve`.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// The source engine's instance.
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// The scene whose `[remote]` table gives the settings below (the flags win).
    #[arg(long)]
    pub scene: Option<std::path::PathBuf>,
    /// Zenoh endpoint to listen on (default: the scene's, else tls/0.0.0.0:7447 with --keys and
    /// tcp/127.0.0.1:7447 without, this machine only).
    #[arg(long)]
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to (a router, other peers).
    #[arg(long)]
    pub connect: Vec<String>,
    /// The session's room, mode and lease.
    #[command(flatten)]
    pub session: SessionArgs,
    /// Stop after this many seconds.
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// The shared session's settings both roles take (each defaults to the scene's `[remote]` table).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct SessionArgs {
    /// The shared session's name, every site the same (default: the scene's, else "lungdyn").
    #[arg(long)]
    pub room: Option<String>,
    /// peer, client (through a router) or — `remote serve` only — router (the sites connect to
    /// this machine) (default: the scene's, else peer).
    #[arg(long)]
    pub mode: Option<ZenohMode>,
    /// Link lease, ms (default: the scene's, else 10000).
    #[arg(long)]
    pub lease_ms: Option<u64>,
    /// The room's keys and this machine's identity in them.
    #[command(flatten)]
    pub keys: KeysArgs,
}

/// `--keys DIR --identity NAME`: mutual TLS and sealed packets.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct KeysArgs {
    /// The room's keys (made by `lungdyn remote keys`): mutual TLS on tls/HOST:PORT endpoints and
    /// every packet sealed by its origin (default: the scene's [remote] keys; none: plain TCP, for
    /// a closed lab network only).
    #[arg(long, value_name = "DIR")]
    pub keys: Option<std::path::PathBuf>,
    /// This machine's certificate in the keys (default: the scene's [remote] identity, else the
    /// role: source, site, observer or router).
    #[arg(long, value_name = "NAME")]
    pub identity: Option<String>,
    /// Without keys, allow plain TCP beyond this machine (a listen or connect endpoint that is
    /// not 127.0.0.1, ::1 or localhost): unencrypted, and anyone who reaches the port can listen,
    /// send events and answer clock probes. For a closed lab network only (also the scene's
    /// [remote] insecure_lab_network = true).
    #[arg(long)]
    pub insecure_lab_network: bool,
}

/// Options of `lungdyn remote keys`.
#[derive(Debug, Clone, clap::Args)]
pub struct MakeKeysArgs {
    /// The room the keys are for (every participant's --room).
    #[arg(long)]
    pub room: String,
    /// The folder to write (created; never overwritten).
    #[arg(long, value_name = "DIR")]
    pub out: std::path::PathBuf,
    /// A participant as NAME:ROLE (roles: source, site, observer, router); repeat for each.
    /// Default: source:source, site:site, observer:observer, router:router.
    #[arg(long, value_name = "NAME:ROLE")]
    pub participant: Vec<crate::keys::Participant>,
    /// Days the certificates are valid.
    #[arg(long, default_value_t = crate::keys::DEFAULT_DAYS)]
    pub days: u32,
}

/// Run `lungdyn remote keys`: say what was written and what goes where.
pub fn make_keys(args: &MakeKeysArgs) -> Result<(), RemoteError> {
    let ps = if args.participant.is_empty() {
        crate::keys::default_participants()
    } else {
        args.participant.clone()
    };
    let made = crate::keys::make(&args.room, &args.out, &ps, args.days)
        .map_err(|e| RemoteError::Usage(format!("remote keys: {e}")))?;
    println!(
        "remote keys: room {:?}, {} participant(s), valid {} day(s), in {}",
        args.room,
        ps.len(),
        args.days,
        args.out.display()
    );
    for p in &ps {
        println!("  {:<12} {}", p.name, p.role.name());
    }
    println!(
        "  {} files written (private keys 0600); what goes to which machine: {}",
        made.files.len(),
        args.out.join("README.txt").display()
    );
    println!(
        "  start each with --keys DIR --identity NAME on tls/HOST:PORT endpoints; check with \
         `lungdyn doctor --keys {}`",
        args.out.display()
    );
    Ok(())
}

/// Load the room's keys: the flag's folder, else the scene's (relative to the scene's folder);
/// the identity from the flag, the scene, else `role`. None without keys.
fn load_room(
    k: &KeysArgs,
    table: Option<&RemoteScene>,
    scene: Option<&std::path::Path>,
    role: &str,
) -> Result<Option<std::sync::Arc<crate::keys::Room>>, RemoteError> {
    let dir = match (&k.keys, table.and_then(|t| t.keys.as_ref())) {
        (Some(d), _) => d.clone(),
        (None, Some(d)) => {
            let base = scene
                .and_then(|s| s.parent())
                .unwrap_or(std::path::Path::new("."));
            base.join(d)
        }
        (None, None) => {
            if k.identity.is_some() {
                return Err(RemoteError::Usage(
                    "--identity without --keys: name the room's keys folder too".into(),
                ));
            }
            return Ok(None);
        }
    };
    let identity = k
        .identity
        .clone()
        .or_else(|| table.and_then(|t| t.identity.clone()))
        .unwrap_or_else(|| role.to_string());
    let room = crate::keys::Room::load(&dir, &identity)
        .map_err(|e| RemoteError::Usage(format!("the room's keys: {e}")))?;
    Ok(Some(std::sync::Arc::new(room)))
}

/// The room a router serves: its keys' when it has them.
fn keys_room(net: &Net, flag: &str) -> String {
    net.auth
        .as_ref()
        .map(|r| r.room.clone())
        .unwrap_or_else(|| flag.to_string())
}

/// Say how this session is protected (start-up): the identity and room, or that it is open.
pub fn say_transport(who: &str, net: &Net) {
    match &net.auth {
        Some(room) => {
            let me = room.identity();
            eprintln!(
                "{who}: mutual TLS as {} ({}) of room {} ({} participants); every packet sealed; \
                 {}",
                me.name,
                me.role.name(),
                room.room,
                room.members.len(),
                if net.acl {
                    "access control by each link's role (states and clock answers only from the \
                     source or router, events only from sites or router)"
                } else {
                    "access control off"
                }
            );
            for w in &room.warnings {
                eprintln!("{who}: keys: {w}");
            }
        }
        None => match lung_model::scene_remote::plain_beyond_loopback(
            net.listen.iter().chain(&net.connect),
        ) {
            None => eprintln!(
                "{who}: PLAIN TCP on this machine only (loopback): unencrypted and \
                 unauthenticated; to reach other machines make the room's keys with `lungdyn \
                 remote keys` and start with --keys"
            ),
            Some(e) => eprintln!(
                "{who}: PLAIN TCP beyond this machine ({e}, --insecure-lab-network): unencrypted \
                 and unauthenticated, anyone who reaches the port can listen, send events and \
                 answer clock probes; for a closed lab network only (make keys with `lungdyn \
                 remote keys` and start with --keys)"
            ),
        },
    }
}

/// The `--mode` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ZenohMode {
    /// Peer to peer.
    Peer,
    /// A router the sites connect to (`remote serve` only).
    Router,
    /// A client of a router.
    Client,
}

impl From<ZenohMode> for lung_model::scene_remote::ZenohMode {
    fn from(m: ZenohMode) -> Self {
        match m {
            ZenohMode::Peer => Self::Peer,
            ZenohMode::Router => Self::Router,
            ZenohMode::Client => Self::Client,
        }
    }
}

/// The `--clock` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ClockSync {
    /// Probe the source (peer to peer; its cost grows with the sites).
    Source,
    /// Probe the time relay beside the router (`lungdyn remote router`).
    Relay,
}

impl From<ClockSync> for lung_model::scene_remote::ClockSync {
    fn from(c: ClockSync) -> Self {
        match c {
            ClockSync::Source => Self::Source,
            ClockSync::Relay => Self::Relay,
        }
    }
}

/// The `[remote]` table of `scene` (none without a scene or table).
fn remote_table(scene: Option<&std::path::Path>) -> Result<Option<RemoteScene>, RemoteError> {
    match scene {
        None => Ok(None),
        Some(p) => Ok(Scene::load(p)?.remote),
    }
}

/// A session's settings: the flags, else the scene's `[remote]` table, else the defaults; checked
/// as the table is (a site's router mode is refused there).
fn settings(
    table: Option<RemoteScene>,
    role: RemoteRole,
    listen: &[String],
    connect: &[String],
    session: &SessionArgs,
    clock: Option<ClockSync>,
    scene: Option<&std::path::Path>,
    identity: crate::keys::Role,
) -> Result<(RemoteScene, Net, Keys), RemoteError> {
    let auth = load_room(&session.keys, table.as_ref(), scene, identity.name())?;
    if let Some(room) = &auth {
        let me = room.identity();
        if me.role != identity {
            return Err(RemoteError::Usage(format!(
                "--identity {}: its certificate is a {}'s, and this runs the {} (use the {}'s \
                 identity, or make one with `lungdyn remote keys --participant NAME:{}`)",
                me.name,
                me.role.name(),
                identity.name(),
                identity.name(),
                identity.name()
            )));
        }
    }
    let mut r = table.unwrap_or(RemoteScene {
        role,
        room: "lungdyn".into(),
        listen: None,
        connect: Vec::new(),
        mode: lung_model::scene_remote::ZenohMode::Peer,
        lease_ms: lung_model::scene_remote::DEFAULT_LEASE_MS,
        site_id: None,
        clock: None,
        keys: None,
        identity: None,
        insecure_lab_network: false,
    });
    if let Some(room) = &auth {
        // With keys the default endpoint is TLS's; the room is the keys' unless named.
        if r.listen.is_none() && role == RemoteRole::Source && listen.is_empty() {
            r.listen = Some(vec![
                lung_model::scene_remote::DEFAULT_LISTEN_TLS.to_string()
            ]);
        }
        if session.room.is_none() && r.room == "lungdyn" {
            r.room = room.room.clone();
        }
        if r.room != room.room {
            return Err(RemoteError::Usage(format!(
                "room {:?}, but the keys are room {:?}'s: use --room {} (or the keys made for {:?})",
                r.room, room.room, room.room, r.room
            )));
        }
    }
    if !listen.is_empty() {
        r.listen = Some(listen.to_vec());
    }
    if !connect.is_empty() {
        r.connect = connect.to_vec();
    }
    if let Some(room) = &session.room {
        r.room = room.clone();
    }
    if let Some(m) = session.mode {
        r.mode = m.into();
    }
    if let Some(l) = session.lease_ms {
        r.lease_ms = l;
    }
    if let Some(c) = clock {
        r.clock = Some(c.into());
    }
    r.validate().map_err(|e| {
        RemoteError::Usage(format!(
            "remote settings: {e} (on the command line: --listen, --connect, --room, --mode, \
             --lease-ms, --clock)"
        ))
    })?;
    if session.keys.insecure_lab_network {
        r.insecure_lab_network = true;
    }
    if auth.is_none() && !r.insecure_lab_network {
        if let Some(e) =
            lung_model::scene_remote::plain_beyond_loopback(r.listen().iter().chain(&r.connect))
        {
            return Err(RemoteError::Usage(format!(
                "endpoint {e:?}: plain TCP beyond this machine is unencrypted and open to anyone \
                 who reaches the port; make the room's keys (`lungdyn remote keys --room {} --out \
                 DIR`) and use --keys DIR with tls/HOST:PORT endpoints, or, on a closed lab network \
                 only, add --insecure-lab-network (scene: [remote] insecure_lab_network = true)",
                r.room
            )));
        }
    }
    let net = Net::of(&r).with_keys(auth);
    let keys = Keys::new(&r.room)?;
    Ok((r, net, keys))
}

/// Options of `lungdyn remote join`.
#[derive(Debug, Clone, clap::Args)]
pub struct JoinArgs {
    /// The source's (or a router's) Zenoh endpoint, tcp/HOST:7447 (default: the scene's `[remote]
    /// connect`).
    #[arg(long)]
    pub connect: Vec<String>,
    /// This site's instance (its renderer attaches to it).
    #[arg(long, default_value = "site")]
    pub instance: String,
    /// The scene (the source's, with its kernels: `lungdyn scene prepare`).
    #[arg(long)]
    pub scene: Option<std::path::PathBuf>,
    /// Watch only: send no events (also the scene's `[remote] role = "observer"`).
    #[arg(long)]
    pub observer: bool,
    /// The session's room, mode (not router: a site joins one) and lease.
    #[command(flatten)]
    pub session: SessionArgs,
    /// Whom the site probes for the source's clock: relay (the time relay `lungdyn remote router`
    /// runs beside the router; needs --mode client) or source (default: the scene's `[remote]
    /// clock`, else relay in client mode and source peer to peer).
    #[arg(long)]
    pub clock: Option<ClockSync>,
    /// Stop after this many seconds.
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// Options of `lungdyn remote router`: a Zenoh router for a classroom and the time relay beside
/// it (the source and the sites connect to it as clients).
#[derive(Debug, Clone, clap::Args)]
pub struct RouterArgs {
    /// Zenoh endpoint to listen on (default: tls/0.0.0.0:7447 with --keys, else tcp/127.0.0.1:7447,
    /// this machine only).
    #[arg(long)]
    pub listen: Vec<String>,
    /// The shared session's name (the source's and the sites' `--room`).
    #[arg(long, default_value = "lungdyn")]
    pub room: String,
    /// Link lease, ms.
    #[arg(long, default_value_t = lung_model::scene_remote::DEFAULT_LEASE_MS)]
    pub lease_ms: u64,
    /// How often the relay probes the source, ms (the source answers only these).
    #[arg(long, default_value_t = 100)]
    pub probe_ms: u64,
    /// The room's keys and the router's identity in them (default identity: router).
    #[command(flatten)]
    pub keys: KeysArgs,
    /// Stop after this many seconds.
    #[arg(long)]
    pub seconds: Option<f64>,
}

/// How often `remote join` probes: the relay every 100 ms (the probes do not reach the source),
/// the source every 500 ms (each site's probes are the source's cost).
fn join_probe_ms(clock: lung_model::scene_remote::ClockSync) -> u64 {
    match clock {
        lung_model::scene_remote::ClockSync::Relay => 100,
        lung_model::scene_remote::ClockSync::Source => 500,
    }
}

fn deadline(seconds: Option<f64>) -> Result<Option<u64>, RemoteError> {
    match seconds {
        None => Ok(None),
        Some(s) if s.is_finite() && s > 0.0 && s < 1e7 => Ok(Some(now_ns() + (s * 1e9) as u64)),
        Some(s) => Err(RemoteError::Usage(format!(
            "--seconds {s}: use a positive number of seconds below 10000000 (about 116 days; leave \
             it out to run until stopped)"
        ))),
    }
}

/// Run `lungdyn remote serve`.
pub fn serve(args: &ServeArgs) -> Result<(), RemoteError> {
    transport::stop::install()?;
    let until = deadline(args.seconds)?;
    let table = remote_table(args.scene.as_deref())?;
    if let Some(t) = table.as_ref().filter(|t| t.role != RemoteRole::Source) {
        return Err(RemoteError::Usage(format!(
            "the scene's [remote] role is {:?}, not \"source\": a site runs `lungdyn remote join \
             --scene …`",
            t.role
        )));
    }
    let (remote, net, keys) = settings(
        table,
        RemoteRole::Source,
        &args.listen,
        &args.connect,
        &args.session,
        None,
        args.scene.as_deref(),
        crate::keys::Role::Source,
    )?;
    net.config()?;
    say_transport("remote serve", &net);
    let instance = Instance::new(&args.instance)?;
    let node = iox::node(&instance, "remote-serve")?;
    let mut states = instance.control_state_inlet(&node)?;
    let mut control = instance.control_outlet(&node)?;
    let id = remote.site_id().unwrap_or_else(|| site_id(0));
    let source = Source::open(&net, &keys, id, Impairment::default())?;
    let _acl = crate::acl::Watch::start(
        &net,
        source.session(),
        &format!("remote serve[{}]", instance.name()),
    );
    let how = if net.mode == "client" {
        format!(
            "through the router {:?}: sites join with lungdyn remote join --mode client --connect \
             ROUTER --room {}",
            net.connect, remote.room
        )
    } else {
        format!(
            "on {:?}: sites join with lungdyn remote join --connect {}/THIS_HOST:PORT --room {}",
            net.listen,
            net.transport_word(),
            remote.room
        )
    };
    eprintln!(
        "remote serve[{}]: relaying {} to zenoh key {} as a {} {how}",
        instance.name(),
        instance.control_state(),
        keys.state(),
        net.mode,
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
                "remote serve[{}]: {} on the {} lung from site {:016x} (its #{}) handed to the \
                 engine",
                instance.name(),
                ipc_types::kind_words(e.kind),
                ipc_types::lung_words(e.lung),
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
         refused{}",
        instance.name(),
        c.states.load(Ordering::Relaxed),
        c.state_bytes.load(Ordering::Relaxed),
        c.probes.load(Ordering::Relaxed),
        c.events.load(Ordering::Relaxed),
        refused + c.refused.load(Ordering::Relaxed),
        crate::acl::closing_words(&net, source.session())
    );
    Ok(())
}

/// What `remote join` says about the time relay (a site syncing with it only).
struct RelayWatch {
    started: u64,
    present: bool,
    lost: u64,
    warned: bool,
}

/// How long a site waits for the relay's first answer before it says none came, ns.
const RELAY_WAIT_NS: u64 = 5_000_000_000;

impl RelayWatch {
    fn new(now: u64) -> Self {
        Self {
            started: now,
            present: false,
            lost: 0,
            warned: false,
        }
    }

    /// Say when the relay comes, goes, or has not answered [`RELAY_WAIT_NS`] after the start.
    fn say(&mut self, instance: &Instance, site: &Site, now: u64) {
        if site.clock != lung_model::scene_remote::ClockSync::Relay {
            return;
        }
        let p = &site.path;
        let (present, lost) = (
            p.relay_present.load(Ordering::Relaxed),
            p.relay_lost.load(Ordering::Relaxed),
        );
        let offset_ms = p.offset_ns.load(Ordering::Relaxed) as f64 / 1e6;
        if lost > self.lost {
            eprintln!(
                "remote join[{}]: the time relay is gone: keeping the last clock offset ({offset_ms:.3} \
                 ms; it ages at the two clocks' rate difference) until it is back",
                instance.name()
            );
        }
        if present && !self.present {
            eprintln!(
                "remote join[{}]: time relay present: clock sync through it (the source answers \
                 only the relay)",
                instance.name()
            );
        }
        (self.present, self.lost) = (present, lost);
        if !self.warned
            && !p.have_offset.load(Ordering::Relaxed)
            && now.saturating_sub(self.started) > RELAY_WAIT_NS
        {
            self.warned = true;
            eprintln!(
                "remote join[{}]: no clock answer {} s after joining: {}. Through a router the \
                 sites sync with the time relay `lungdyn remote router` runs on the router's host \
                 (a stock zenohd cannot answer); behind a stock router join with --clock source",
                instance.name(),
                RELAY_WAIT_NS / 1_000_000_000,
                if present {
                    "the relay is present but has no offset to the source yet (is the source \
                     connected to the router?)"
                } else {
                    "no time relay is present"
                }
            );
        }
    }
}

/// Run `lungdyn remote router`: a Zenoh router and the time relay in this process.
pub fn router(args: &RouterArgs) -> Result<(), RemoteError> {
    transport::stop::install()?;
    let until = deadline(args.seconds)?;
    if !(1..=10_000).contains(&args.probe_ms) {
        return Err(RemoteError::Usage(format!(
            "--probe-ms {}: use 1–10000",
            args.probe_ms
        )));
    }
    // The router's settings are checked as a router source's `[remote]` table.
    let (_, net, keys) = settings(
        None,
        RemoteRole::Source,
        &args.listen,
        &[],
        &SessionArgs {
            // The default room gives way to the keys' room.
            room: (args.room != "lungdyn").then(|| args.room.clone()),
            mode: Some(ZenohMode::Router),
            lease_ms: Some(args.lease_ms),
            keys: args.keys.clone(),
        },
        None,
        None,
        crate::keys::Role::Router,
    )?;
    say_transport("remote router", &net);
    let session = net.open()?;
    let _acl = crate::acl::Watch::start(&net, &session, "remote router");
    let relay = crate::relay::Relay::open(
        &session,
        &keys,
        site_id(0),
        Impairment::default(),
        args.probe_ms,
        net.guard(),
    )?;
    let (proto, room) = (net.transport_word(), keys_room(&net, &args.room));
    let keys_flags = if net.auth.is_some() {
        " --keys DIR --identity NAME"
    } else {
        ""
    };
    eprintln!(
        "remote router: a Zenoh router on {:?} with the time relay for room {room} (the source runs \
         `lungdyn remote serve --mode client --connect {proto}/THIS_HOST:PORT --room \
         {room}{keys_flags}`, each site `lungdyn remote join --mode client --connect \
         {proto}/THIS_HOST:PORT --room {room}{keys_flags}`)",
        net.listen
    );
    let mut synced = false;
    let mut rate_word = "unknown";
    let mut last_reply = (0u64, now_ns());
    let mut silent = false;
    while transport::stop::idle(Duration::from_millis(100)) && until.is_none_or(|t| now_ns() < t) {
        let c = &relay.counts;
        if let (Some(o), true, false) = (relay.offset_ns(), relay.answering(), synced) {
            synced = true;
            eprintln!(
                "remote router: clock relay in step with the source (offset {:.3} ms, delay {:.2} \
                 ms): answering the sites' probes",
                o as f64 / 1e6,
                relay.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6
            );
        }
        if let Some(news) = relay.path.rate_news(&mut rate_word) {
            eprintln!("remote router: {news}");
        }
        let replies = c.source_replies.load(Ordering::Relaxed);
        let now = now_ns();
        if replies != last_reply.0 {
            if silent {
                eprintln!("remote router: the source answers the relay again");
            }
            (last_reply, silent) = ((replies, now), false);
        } else if !silent && now - last_reply.1 > 5_000_000_000 {
            silent = true;
            eprintln!(
                "remote router: no answer from the source for 5 s{}",
                if synced {
                    ": the relay answers the sites with its last offset to it"
                } else {
                    ": the sites' probes wait (start `lungdyn remote serve --mode client \
                     --connect` to this router)"
                }
            );
        }
    }
    let c = &relay.counts;
    eprintln!(
        "remote router: relay sent {} probes to the source ({} answered); answered {} site \
         probes, {} before it had {} source replies, {} refused{}",
        c.probes_to_source.load(Ordering::Relaxed),
        c.source_replies.load(Ordering::Relaxed),
        c.answered.load(Ordering::Relaxed),
        c.unanswered.load(Ordering::Relaxed),
        crate::relay::MIN_REPLIES,
        c.refused.load(Ordering::Relaxed),
        crate::acl::closing_words(&net, &session)
    );
    Ok(())
}

/// Run `lungdyn remote join`.
pub fn join(args: &JoinArgs) -> Result<(), RemoteError> {
    transport::stop::install()?;
    let until = deadline(args.seconds)?;
    let table = remote_table(args.scene.as_deref())?;
    let role = join_role(args, table.as_ref())?;
    let observer = role == RemoteRole::Observer;
    // Endpoints are checked before anything is loaded or opened.
    let (remote, net, keys) = settings(
        table,
        role,
        &[],
        &args.connect,
        &args.session,
        args.clock,
        args.scene.as_deref(),
        if observer {
            crate::keys::Role::Observer
        } else {
            crate::keys::Role::Site
        },
    )?;
    let clock = remote.clock();
    net.config()?;
    say_transport("remote join", &net);
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
    let mut local = LocalEvents::default();
    let site = Site::open(
        &net,
        &keys,
        remote.site_id().unwrap_or_else(|| site_id(0)),
        observer,
        Impairment::default(),
        join_probe_ms(clock),
        clock,
    )?;
    eprintln!(
        "remote join[{}]: site {:016x}{} waiting for the source's state on {:?}; clock sync with \
         the {}",
        instance.name(),
        site.id,
        if observer { " (observer)" } else { "" },
        net.connect,
        match clock {
            lung_model::scene_remote::ClockSync::Relay => "time relay beside the router",
            lung_model::scene_remote::ClockSync::Source => "source",
        }
    );
    let _acl = crate::acl::Watch::start(
        &net,
        site.session(),
        &format!("remote join[{}]", instance.name()),
    );
    let mut relay_watch = RelayWatch::new(now_ns());
    let mut runner = site
        .runner(core, hz)
        .ok_or_else(|| RemoteError::Usage("the site's runner was taken".into()))?;
    let mut first = true;
    let mut rate_word = "unknown";
    let mut patient = PatientWatch::default();
    while !transport::stop::requested() && until.is_none_or(|t| now_ns() < t) {
        let now = now_ns();
        if runner.poll(now)?.is_some() {
            patient.see(&instance, runner.core());
            if first {
                first = false;
                eprintln!(
                    "remote join[{}]: in step with the source (delay {:.2} ms, offset {:.3} ms)",
                    instance.name(),
                    site.path.delay_ns.load(Ordering::Relaxed) as f64 / 1e6,
                    site.path.offset_at(now).unwrap_or(0) as f64 / 1e6
                );
            }
            runner.frame.stamps.engine_receive_ns = now;
            runner.frame.stamps.engine_publish_ns = now_ns();
            outlet.publish(&runner.frame)?;
        }
        relay_watch.say(&instance, &site, now);
        if let Some(news) = site.path.rate_news(&mut rate_word) {
            eprintln!("remote join[{}]: {news}", instance.name());
        }
        local.tell_announced(&instance, &site, &mut replies)?;
        let tick = runner.last_tick().unwrap_or(0);
        local.forward(&instance, &site, tick, &mut control, &mut replies)?;
        let wake = runner
            .next_wake()
            .map(|t| t - now_ns() as i128)
            .unwrap_or(2_000_000)
            .clamp(0, 2_000_000);
        std::thread::sleep(Duration::from_nanos(wake as u64));
    }
    say_join_counts(&instance, &site, &net);
    patient.say(&instance, runner.core(), hz);
    // A site that never breathed the source's breath did not do its job: say why, exit non-zero.
    let c = &site.counts;
    let applied = c.applied.load(Ordering::Relaxed);
    let heard = applied + c.repeated.load(Ordering::Relaxed) + c.refused.load(Ordering::Relaxed);
    if applied == 0 {
        return Err(RemoteError::NoState {
            connect: net.connect.join(", "),
            why: if heard == 0 {
                "nothing came from the source: is `lungdyn remote serve` (or a source's `lungdyn \
                 demo`) running there, in the same --room, and does the network let the port \
                 through?"
                    .into()
            } else {
                format!(
                    "{heard} state(s) came and none could be applied (refused or repeated; the last \
                     refusal is above)"
                )
            },
        });
    }
    Ok(())
}

/// The role a joining engine takes: the scene's (`site` or `observer`) or `--observer`; a
/// source's scene is refused.
fn join_role(args: &JoinArgs, table: Option<&RemoteScene>) -> Result<RemoteRole, RemoteError> {
    if let Some(t) = table.filter(|t| t.role == RemoteRole::Source) {
        return Err(RemoteError::Usage(format!(
            "the scene's [remote] role is {:?}: the source runs `lungdyn remote serve` (or `lungdyn \
             demo`); a site's scene says role = \"site\" or \"observer\"",
            t.role
        )));
    }
    let observer = args.observer || table.is_some_and(|t| t.role == RemoteRole::Observer);
    Ok(if observer {
        RemoteRole::Observer
    } else {
        RemoteRole::Site
    })
}

/// The events this site's own senders (`lungdyn scene event`) gave it: sent to the source and
/// answered as by an engine — received when sent, applied when the source announces it.
#[derive(Default)]
struct LocalEvents {
    /// Sent to the source and not yet announced by it (its number there, the packet): the last 64.
    sent: Vec<(u64, ControlPacket)>,
    /// How many of the source's announced events were told already.
    told: usize,
}

impl LocalEvents {
    /// Each event the source announced, once: who raised it and the cycle every site applies it;
    /// one of ours is answered "applied".
    fn tell_announced(
        &mut self,
        instance: &Instance,
        site: &Site,
        replies: &mut dyn Publish<ControlReply>,
    ) -> Result<(), RemoteError> {
        let mut announced = Vec::new();
        if let Ok(seen) = site.events.lock() {
            announced.extend(seen.iter().skip(self.told).copied());
            self.told = seen.len();
        }
        for e in &announced {
            eprintln!(
                "remote join[{}]: {} on the {} lung from {} (its #{}) applies at the source's \
                 breathing cycle {} (tick {}), the disease course's cycle {}",
                instance.name(),
                ipc_types::kind_words(e.kind),
                ipc_types::lung_words(e.lung),
                if e.origin == site.id {
                    "this site".to_string()
                } else {
                    format!("site {:016x}", e.origin)
                },
                e.sequence,
                e.apply_cycle,
                e.apply_tick,
                e.course_cycle
            );
            let Some(k) = self
                .sent
                .iter()
                .position(|(n, _)| e.origin == site.id && *n == e.sequence)
            else {
                continue;
            };
            let (_, p) = self.sent.remove(k);
            let mut r = ControlReply {
                status: ipc_types::REPLY_APPLIED,
                sequence: p.sequence,
                tick: e.apply_tick,
                // The disease course's cycle, as the source's engine answers (not the breathing
                // cycle `apply_cycle`).
                cycle: e.course_cycle,
                kind: e.kind,
                lung: e.lung,
                outcome: e.outcome,
                ..Default::default()
            };
            r.set_text(&["applied by the source; every site switches at that tick"]);
            replies.publish(&r)?;
        }
        Ok(())
    }

    /// The site's own senders' packets, each sent to the source and answered (received, or
    /// ignored with the reason); `tick` is the site's last tick.
    fn forward(
        &mut self,
        instance: &Instance,
        site: &Site,
        tick: u64,
        control: &mut dyn Receive<ControlPacket>,
        replies: &mut dyn Publish<ControlReply>,
    ) -> Result<(), RemoteError> {
        let mut events = Vec::new();
        control.drain(&mut |p: &ControlPacket| events.push(*p))?;
        for p in events {
            let mut r = ControlReply {
                sequence: p.sequence,
                tick,
                kind: p.kind,
                lung: p.lung,
                ..Default::default()
            };
            match site.send_event(p.kind, p.lung) {
                Ok(n) => {
                    eprintln!(
                        "remote join[{}]: {} on the {} lung sent to the source (#{n})",
                        instance.name(),
                        ipc_types::kind_words(p.kind),
                        ipc_types::lung_words(p.lung)
                    );
                    r.status = ipc_types::REPLY_RECEIVED;
                    r.set_text(&["sent to the source; it applies it at a cycle it announces"]);
                    if self.sent.len() == 64 {
                        self.sent.remove(0);
                    }
                    self.sent.push((n, p));
                }
                Err(e) => {
                    eprintln!("remote join[{}]: {e}", instance.name());
                    r.status = ipc_types::REPLY_IGNORED;
                    r.set_text(&["ignored: ", &e.to_string()]);
                }
            }
            replies.publish(&r)?;
        }
        Ok(())
    }
}

/// Whether a joined site plays the source's patient's breath (a source following a live signal),
/// said when it starts and stops, and the breaths taken.
#[derive(Default)]
struct PatientWatch {
    following: bool,
    /// Breaths of the spans ended, and of the one under way.
    breaths: u64,
    span: u64,
}

impl PatientWatch {
    fn see(&mut self, instance: &Instance, core: &engine::runtime::EngineCore) {
        let live = core.remote_live().map(|l| l.breaths());
        if live.is_some() != self.following {
            self.following = live.is_some();
            self.breaths += std::mem::take(&mut self.span);
            eprintln!(
                "remote join[{}]: {}",
                instance.name(),
                if self.following {
                    "breathing with the source's patient (the source follows a live respiratory \
                     signal): each breath plays the patient's previous one from the patient's last \
                     turn and, until the patient's next breath is heard, starts the next one on the \
                     patient's rhythm"
                } else {
                    "the source's model breathes (its patient's signal is calibrating or lost)"
                }
            );
        }
        self.span = live.unwrap_or(self.span);
    }

    fn say(&self, instance: &Instance, core: &engine::runtime::EngineCore, hz: f64) {
        let breaths = self.breaths + self.span;
        if breaths == 0 {
            return;
        }
        let lag = core.patient_turn_lag();
        eprintln!(
            "remote join[{}]: {breaths} of the patient's breaths taken from the source; its turns \
             reached this site {:.0} ms after they happened there on average, {:.0} ms at most ({} \
             turns: the source's confirmation, the network, this site's schedule; `lungdyn \
             breathing sites FILE` measures how far a site strays at each network delay)",
            instance.name(),
            lag.mean_ms(hz).unwrap_or(f64::NAN),
            lag.max_ticks as f64 * 1e3 / hz,
            lag.turns
        );
    }
}

/// A joined site's closing counts on stderr: disease cycles announced in time or late, states
/// applied, repeated and refused, cycles breathed on prediction.
fn say_join_counts(instance: &Instance, site: &Site, net: &Net) {
    let c = &site.counts;
    eprintln!(
        "remote join[{}]: {} disease cycle(s) announced in time, {} late",
        instance.name(),
        c.announced_in_time.load(Ordering::Relaxed),
        c.announced_late.load(Ordering::Relaxed)
    );
    eprintln!(
        "remote join[{}]: {} states applied, {} repeated, {} refused{}, {} cycle(s) breathed on \
         prediction (their state late or lost){}",
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
        c.predicted_cycles.load(Ordering::Relaxed),
        crate::acl::closing_words(net, site.session())
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::keys::Role;

    #[test]
    fn an_identity_of_another_role_and_a_room_of_another_name_are_refused() {
        let d = std::env::temp_dir().join(format!("lungdyn-roles-keys-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        crate::keys::make("ward", &d, &crate::keys::default_participants(), 10).unwrap();
        let connect = ["tls/127.0.0.1:7447".to_string()];
        let with = |identity: &str, room: Option<&str>| SessionArgs {
            room: room.map(str::to_string),
            keys: KeysArgs {
                keys: Some(d.clone()),
                identity: Some(identity.into()),
                ..Default::default()
            },
            ..Default::default()
        };
        let run = |s: &SessionArgs| {
            settings(
                None,
                RemoteRole::Site,
                &[],
                &connect,
                s,
                None,
                None,
                Role::Site,
            )
        };
        let (r, net, _) = run(&with("site", None)).unwrap();
        assert_eq!((r.room.as_str(), net.transport_word()), ("ward", "tls"));
        let e = run(&with("observer", None)).unwrap_err().to_string();
        assert!(
            e.contains("observer's") && e.contains("runs the site"),
            "{e}"
        );
        let e = run(&with("site", Some("other"))).unwrap_err().to_string();
        assert!(e.contains("--room ward"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }

    fn session(mode: ZenohMode) -> SessionArgs {
        SessionArgs {
            mode: Some(mode),
            lease_ms: Some(2000),
            ..Default::default()
        }
    }

    /// One set of session flags for both roles: the source may be the router, a site may not
    /// (a clear error naming what to do instead); a site joins a router as a client.
    #[test]
    fn router_mode_is_the_sources_and_a_site_is_told_to_join_as_a_client() {
        let listen = ["tcp/127.0.0.1:7447".to_string()];
        let (r, net, _) = settings(
            None,
            RemoteRole::Source,
            &listen,
            &[],
            &session(ZenohMode::Router),
            None,
            None,
            Role::Source,
        )
        .unwrap();
        assert_eq!(
            (r.mode.name(), net.mode, net.lease_ms),
            ("router", "router", 2000)
        );
        for role in [RemoteRole::Site, RemoteRole::Observer] {
            let e = settings(
                None,
                role,
                &[],
                &listen,
                &session(ZenohMode::Router),
                None,
                None,
                Role::Site,
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.contains("remote serve --mode router")
                    && e.contains("client")
                    && e.contains("--mode"),
                "{e}"
            );
            let (r, net, _) = settings(
                None,
                role,
                &[],
                &listen,
                &session(ZenohMode::Client),
                None,
                None,
                Role::Site,
            )
            .unwrap();
            assert_eq!(net.mode, "client");
            // Through a router a site syncs with the relay unless told otherwise.
            assert_eq!(r.clock(), lung_model::scene_remote::ClockSync::Relay);
            let (r, _, _) = settings(
                None,
                role,
                &[],
                &listen,
                &session(ZenohMode::Client),
                Some(ClockSync::Source),
                None,
                Role::Site,
            )
            .unwrap();
            assert_eq!(r.clock(), lung_model::scene_remote::ClockSync::Source);
            let e = settings(
                None,
                role,
                &[],
                &listen,
                &session(ZenohMode::Peer),
                Some(ClockSync::Relay),
                None,
                Role::Site,
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.contains("needs mode = \"client\"") && e.contains("--clock"),
                "{e}"
            );
        }
    }
}
