//! # lungdyn-remote: sites breathing in step over Zenoh (seed §8.3)
//!
//! The seed's distributed simulation sends one control packet per breathing cycle (or change) and
//! lets every site drive its own lung from it, with the network delay measured and compensated.
//! Here the packet is the engine's [`control_state::ControlState`]; it travels on
//! [Zenoh](https://zenoh.io) (peer to peer or through a router), in the shape of iceoryx2's
//! Zenoh tunnel: one relay per service, discovery by Zenoh, this crate as the backend.
//!
//! * [`source`]: the source side — publishes each state on an `AdvancedPublisher` with a cache
//!   (a late joiner's `AdvancedSubscriber` gets the current state at once through its history),
//!   answers delay probes, takes sites' events, declares a liveliness token and counts the sites'.
//! * [`site`]: a site — receives states (history + recovery), estimates delay, jitter and clock
//!   offset from probes ([`clock`]), builds the breath a state names off the tick thread and runs
//!   its own [`engine::runtime::EngineCore`] on the source's tick numbers, scheduled so its ticks
//!   fall at the source's times.
//! * [`relay`]: the time relay beside a router: it alone probes the source and answers the
//!   sites' probes in the source's time, so through a router the source's cost does not grow with
//!   the sites.
//! * [`harness`]: a source and N sites on loopback with drift, phase error and packet figures.
//! * [`roles`]: `lungdyn remote serve` / `join` over a running engine's iceoryx2 streams.
//!
//! Zenoh's own runtime threads are not the tick thread: every Zenoh callback only decodes (or
//! copies) and hands over through a bounded channel; building PV tables happens on a worker; the
//! tick loop takes what is ready with `try_recv`.

pub mod acl;
pub mod clock;
pub mod harness;
pub mod keys;
pub mod link;
pub mod measure;
pub mod relay;
pub mod roles;
pub mod seal;
pub mod site;
pub mod source;

use thiserror::Error;

/// Why a remote session failed.
#[derive(Debug, Error)]
pub enum RemoteError {
    /// Zenoh refused a configuration or an operation.
    #[error("zenoh: {what}: {message}")]
    Zenoh {
        /// What was being done.
        what: String,
        /// Zenoh's error.
        message: String,
    },
    /// A bad option.
    #[error("{0}")]
    Usage(String),
    /// The engine could not be built or driven (boxed: the engine's error is large).
    #[error(transparent)]
    Core(Box<engine::runtime::CoreError>),
    /// A control state could not be made or used.
    #[error(transparent)]
    State(#[from] engine::runtime::remote::RemoteStateError),
    /// A local stream failed.
    #[error(transparent)]
    Port(#[from] transport::PortError),
    /// The scene could not be loaded.
    #[error(transparent)]
    Scene(Box<lung_model::scene::SceneError>),
    /// A site's run ended without applying one state from the source.
    #[error("remote join: no state from the source at {connect} was applied: {why}")]
    NoState {
        /// Where the site connected.
        connect: String,
        /// What was heard, and what to check.
        why: String,
    },
    /// The source engine's loop stopped with an error.
    #[error(transparent)]
    Engine(Box<engine::runtime::process::EngineError>),
}

impl From<engine::runtime::process::EngineError> for RemoteError {
    fn from(e: engine::runtime::process::EngineError) -> Self {
        Self::Engine(Box::new(e))
    }
}

impl From<engine::runtime::CoreError> for RemoteError {
    fn from(e: engine::runtime::CoreError) -> Self {
        Self::Core(Box::new(e))
    }
}

impl From<lung_model::scene::SceneError> for RemoteError {
    fn from(e: lung_model::scene::SceneError) -> Self {
        Self::Scene(Box::new(e))
    }
}

/// Wrap a Zenoh error with what was being done.
pub(crate) fn zerr<E: std::fmt::Display>(what: impl Into<String>) -> impl FnOnce(E) -> RemoteError {
    let what = what.into();
    move |e| RemoteError::Zenoh {
        what,
        message: e.to_string(),
    }
}

/// Key expressions of one shared session (`room`).
#[derive(Debug, Clone)]
pub struct Keys {
    room: String,
}

impl Keys {
    /// The keys of `room` (letters, digits, `-`, `_` only: Zenoh's wildcards and separators are
    /// refused).
    pub fn new(room: &str) -> Result<Self, RemoteError> {
        if room.is_empty()
            || room.len() > 64
            || !room
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(RemoteError::Usage(format!(
                "room {room:?}: use 1–64 letters, digits, '-' or '_'"
            )));
        }
        Ok(Self {
            room: room.to_string(),
        })
    }
    /// The source's control states.
    pub fn state(&self) -> String {
        format!("lungdyn/{}/state", self.room)
    }
    /// Events sent by sites to the source.
    pub fn event(&self) -> String {
        format!("lungdyn/{}/event", self.room)
    }
    /// Delay probes to the source.
    pub fn probe(&self) -> String {
        format!("lungdyn/{}/probe", self.room)
    }
    /// A warm-up packet a prober puts [`site::WARM_UP_MS`] before each probe to the source (the
    /// source takes it with an empty callback): the probe then finds both ends' threads awake.
    pub fn warm(&self) -> String {
        format!("lungdyn/{}/warm", self.room)
    }
    /// The same before each probe to the time relay.
    pub fn relay_warm(&self) -> String {
        format!("lungdyn/{}/relay/warm", self.room)
    }
    /// Delay probes to the time relay beside the router ([`relay`]).
    pub fn relay_probe(&self) -> String {
        format!("lungdyn/{}/relay/probe", self.room)
    }
    /// The time relay's presence.
    pub fn relay_presence(&self) -> String {
        format!("lungdyn/{}/relay/alive", self.room)
    }
    /// Probe replies to `site`.
    pub fn reply(&self, site: u64) -> String {
        format!("lungdyn/{}/reply/{site:016x}", self.room)
    }
    /// A site's liveliness token.
    pub fn presence(&self, site: u64) -> String {
        format!("lungdyn/{}/site/{site:016x}", self.room)
    }
    /// Every site's presence.
    pub fn presence_all(&self) -> String {
        format!("lungdyn/{}/site/*", self.room)
    }
    /// The source's presence.
    pub fn source_presence(&self) -> String {
        format!("lungdyn/{}/source", self.room)
    }
}

/// How a Zenoh session is reached.
#[derive(Debug, Clone)]
pub struct Net {
    /// Endpoints to listen on (`tcp/0.0.0.0:7447`).
    pub listen: Vec<String>,
    /// Endpoints to connect to (`tcp/HOST:7447`).
    pub connect: Vec<String>,
    /// Link lease, ms (a lost peer is seen within it).
    pub lease_ms: u64,
    /// `peer`, `router` (the others connect to this session) or `client` (through a router).
    pub mode: &'static str,
    /// The room's keys as this participant (`--keys DIR --identity NAME`): TLS with mutual
    /// authentication on `tls/` endpoints, and every packet sealed ([`seal`]). None: plain TCP
    /// and plain packets, for a closed lab network only.
    pub auth: Option<std::sync::Arc<keys::Room>>,
    /// With keys, Zenoh's access control by the role in each link's certificate ([`acl`]), the
    /// wall before the seals. Off only to test the seals alone.
    pub acl: bool,
}

impl Net {
    /// A peer listening on `listen` and connecting to `connect`, multicast scouting off.
    pub fn peer(listen: &[String], connect: &[String]) -> Self {
        Self {
            listen: listen.to_vec(),
            connect: connect.to_vec(),
            lease_ms: 10_000,
            mode: "peer",
            auth: None,
            acl: true,
        }
    }

    /// The same session with `room`'s keys.
    pub fn with_keys(mut self, room: Option<std::sync::Arc<keys::Room>>) -> Self {
        self.auth = room;
        self
    }

    /// This participant's seal and opener ([`seal::Guard`]).
    pub fn guard(&self) -> seal::Guard {
        seal::Guard::new(self.auth.clone())
    }

    /// How this session is protected, in words (start-up lines, JSON's `transport`).
    pub fn transport_word(&self) -> &'static str {
        if self.auth.is_some() {
            "tls"
        } else {
            "tcp"
        }
    }

    /// The session a scene's `[remote]` table (already validated) describes: its endpoints, lease
    /// and mode (`router`: this machine is the router the others connect to).
    pub fn of(r: &lung_model::scene_remote::RemoteScene) -> Self {
        Self {
            listen: r.listen(),
            connect: r.connect.clone(),
            lease_ms: r.lease_ms,
            mode: r.mode.name(),
            auth: None,
            acl: true,
        }
    }

    /// The Zenoh configuration: explicit endpoints, no multicast scouting, the lease.
    pub fn config(&self) -> Result<zenoh::Config, RemoteError> {
        let want = if self.auth.is_some() { "tls/" } else { "tcp/" };
        for e in self.listen.iter().chain(&self.connect) {
            if !e.starts_with(want) {
                return Err(RemoteError::Usage(if self.auth.is_some() {
                    format!(
                        "endpoint {e:?}: with the room's keys (--keys) the endpoints are \
                         tls/HOST:PORT (e.g. tls/192.168.1.10:7447)"
                    )
                } else if e.starts_with("tls/") {
                    format!(
                        "endpoint {e:?}: TLS needs the room's keys: --keys DIR --identity NAME \
                         (make them with `lungdyn remote keys --room ROOM --out DIR`)"
                    )
                } else {
                    format!(
                        "endpoint {e:?}: use tls/HOST:PORT with the room's keys, or tcp/HOST:PORT \
                         on a closed lab network (e.g. tls/192.168.1.10:7447)"
                    )
                }));
            }
        }
        let mut c = zenoh::Config::default();
        let json = |v: &[String]| {
            let quoted: Vec<String> = v.iter().map(|e| format!("{e:?}")).collect();
            format!("[{}]", quoted.join(","))
        };
        let set = |c: &mut zenoh::Config, k: &str, v: &str| {
            c.insert_json5(k, v)
                .map_err(zerr(format!("config {k} = {v}")))
        };
        set(&mut c, "mode", &format!("{:?}", self.mode))?;
        set(&mut c, "scouting/multicast/enabled", "false")?;
        set(&mut c, "listen/endpoints", &json(&self.listen))?;
        set(&mut c, "connect/endpoints", &json(&self.connect))?;
        set(
            &mut c,
            "transport/link/tx/lease",
            &self.lease_ms.to_string(),
        )?;
        set(&mut c, "transport/link/tx/keep_alive", "4")?;
        // Opening returns once the configured endpoints are connected and their declarations
        // heard, without also waiting up to Zenoh's 500 ms scouting delay for peers learnt by
        // gossip (a room's sites do not connect to each other): a site joined peer to peer in
        // about 500 ms, now in a few (docs/REMOTE.md, the time to join).
        set(&mut c, "open/return_conditions/connect_scouted", "false")?;
        if let Some(room) = &self.auth {
            let path = |p: &std::path::Path| format!("{:?}", p.display().to_string());
            let t = &room.tls;
            set(
                &mut c,
                "transport/link/tls/root_ca_certificate",
                &path(&t.authority),
            )?;
            for side in ["listen", "connect"] {
                set(
                    &mut c,
                    &format!("transport/link/tls/{side}_certificate"),
                    &path(&t.certificate),
                )?;
                set(
                    &mut c,
                    &format!("transport/link/tls/{side}_private_key"),
                    &path(&t.key),
                )?;
            }
            // Both ends present a certificate of the room's authority.
            set(&mut c, "transport/link/tls/enable_mtls", "true")?;
            // Participants are reached by address, not by a name in their certificate; who they
            // are is the room's authority's word, and every packet is sealed by its origin.
            set(&mut c, "transport/link/tls/verify_name_on_connect", "false")?;
            // An expired certificate ends the link, not only the next handshake.
            set(
                &mut c,
                "transport/link/tls/close_link_on_expiration",
                "true",
            )?;
            if self.acl {
                let table = acl::config(room)?.to_string();
                set(&mut c, "access_control", &table)?;
                // Its drops are read from this session's own admin space (acl::refusals); the
                // table above refuses the admin space to every other participant.
                set(&mut c, "adminspace/enabled", "true")?;
            }
        }
        Ok(c)
    }

    /// Open a session.
    pub fn open(&self) -> Result<zenoh::Session, RemoteError> {
        use zenoh::Wait;
        zenoh::open(self.config()?)
            .wait()
            .map_err(zerr("open a session"))
    }
}

/// A site id: the low 48 bits of `now_ns` and 16 bits of the process id (as
/// [`ipc_types::control_sequence`]), plus `k` for several sites in one process.
pub fn site_id(k: u64) -> u64 {
    ipc_types::control_sequence(std::process::id(), transport::clock::now_ns())
        .wrapping_add(k.wrapping_mul(0x9e37_79b9_7f4a_7c15))
}
