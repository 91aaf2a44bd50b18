//! Sealed packets: every remote packet's origin, role and sequence, signed (issue 37 item 3).
//!
//! TLS protects a link; a packet crosses several (a site → the router → the source), and every
//! participant holding a room certificate may send on any key. So each packet is sealed by its
//! origin with its own Ed25519 key and opened by its receiver against the room's certificates
//! ([`crate::keys::Room`]):
//!
//! ```text
//! "LDS1" | kind u8 | name length u8 | name | sequence u64 LE | payload | Ed25519 signature (64)
//! signed: "lungdyn seal v1" 0 | room | 0 | everything before the signature
//! ```
//!
//! The receiver refuses, and counts by reason with the origin named: bytes that are not sealed,
//! an origin that is not a participant of this room, a bad signature (forged, altered, another
//! room's), a kind the origin's role may not send (a state not from the source, an event from an
//! observer, a clock answer from a site), a sequence already seen or too old (replay), and events
//! beyond a site's rate. Sequences start at the sender's wall-clock time in nanoseconds, so a
//! participant that restarts goes on above its last packet; a window of [`WINDOW`] sequences
//! behind the newest takes packets that were reordered (Zenoh's recovery of a missed state).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::keys::{Role, Room};

/// The seal's magic and version.
pub const MAGIC: [u8; 4] = *b"LDS1";
/// Bytes a seal adds besides the origin's name: magic, kind, name length, sequence, signature.
pub const OVERHEAD: usize = 4 + 1 + 1 + 8 + 64;
/// Sequences behind the newest still taken once (reordering).
pub const WINDOW: u64 = 64;
/// Events a site may send in a burst, and per second after it.
pub const EVENT_BURST: f64 = 20.0;
/// Events per second a site may send on average.
pub const EVENT_RATE: f64 = 5.0;
/// The largest payload sealed or opened.
pub const MAX_PAYLOAD: usize = 64 * 1024;

const DOMAIN: &[u8] = b"lungdyn seal v1\0";

/// What a packet is; each kind has the roles that may send it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Kind {
    /// The source's control state.
    State = 1,
    /// A site's intervention.
    Event = 2,
    /// A clock probe.
    Probe = 3,
    /// A clock probe's answer.
    Reply = 4,
}

impl Kind {
    fn of(b: u8) -> Option<Kind> {
        Some(match b {
            1 => Kind::State,
            2 => Kind::Event,
            3 => Kind::Probe,
            4 => Kind::Reply,
            _ => return None,
        })
    }

    /// The kind's word.
    pub fn name(self) -> &'static str {
        match self {
            Kind::State => "state",
            Kind::Event => "event",
            Kind::Probe => "clock probe",
            Kind::Reply => "clock answer",
        }
    }

    /// Whether `role` may send this kind: states only the source; events only sites; clock
    /// answers the source and the time relay beside the router; probes anyone in the room.
    pub fn allowed(self, role: Role) -> bool {
        match self {
            Kind::State => role == Role::Source,
            Kind::Event => role == Role::Site,
            Kind::Reply => matches!(role, Role::Source | Role::Router),
            Kind::Probe => true,
        }
    }
}

/// Seals this participant's packets.
pub struct Sealer {
    room: Arc<Room>,
    sequence: AtomicU64,
}

fn wall_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

impl Sealer {
    /// A sealer for `room`'s identity; its sequence starts at the wall clock.
    pub fn new(room: Arc<Room>) -> Self {
        Self {
            room,
            sequence: AtomicU64::new(wall_ns()),
        }
    }

    /// `payload` sealed as `kind`.
    pub fn seal(&self, kind: Kind, payload: &[u8]) -> Vec<u8> {
        let seq = self.sequence.fetch_add(1, Ordering::Relaxed);
        self.seal_with(kind, seq, payload)
    }

    /// `payload` sealed as `kind` with sequence `seq` (the tests' replays).
    pub fn seal_with(&self, kind: Kind, seq: u64, payload: &[u8]) -> Vec<u8> {
        let name = self.room.identity().name.as_bytes();
        let mut out = Vec::with_capacity(OVERHEAD + name.len() + payload.len());
        out.extend_from_slice(&MAGIC);
        out.push(kind as u8);
        out.push(name.len() as u8);
        out.extend_from_slice(name);
        out.extend_from_slice(&seq.to_le_bytes());
        out.extend_from_slice(payload);
        let sig = self.room.sign(&signed(&self.room.room, &out));
        out.extend_from_slice(&sig);
        out
    }
}

fn signed(room: &str, body: &[u8]) -> Vec<u8> {
    let mut m = Vec::with_capacity(DOMAIN.len() + room.len() + 1 + body.len());
    m.extend_from_slice(DOMAIN);
    m.extend_from_slice(room.as_bytes());
    m.push(0);
    m.extend_from_slice(body);
    m
}

/// Why a packet was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// Not a sealed packet (no seal, truncated, an unknown kind, too long).
    Unsealed(String),
    /// An origin that is not a participant of this room.
    Stranger(String),
    /// The signature does not hold: forged, altered, or sealed for another room.
    Forged(String),
    /// The origin's role may not send this kind.
    Role {
        /// The origin.
        origin: String,
        /// Its role.
        role: Role,
        /// What it sent.
        kind: Kind,
    },
    /// A sequence already taken, or too far behind the newest.
    Replay {
        /// The origin.
        origin: String,
        /// The sequence.
        sequence: u64,
    },
    /// More events than a site may send.
    Rate(String),
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::Unsealed(why) => write!(f, "an unsealed packet ({why})"),
            Refusal::Stranger(o) => {
                write!(f, "a packet from {o:?}, not a participant of this room")
            }
            Refusal::Forged(o) => write!(
                f,
                "a packet claiming to be from {o:?} whose signature does not hold (forged, altered \
                 or another room's)"
            ),
            Refusal::Role { origin, role, kind } => write!(
                f,
                "{} {} from {origin:?}, {} {}, which may not send one",
                article(kind.name()),
                kind.name(),
                article(role.name()),
                role.name()
            ),
            Refusal::Replay { origin, sequence } => write!(
                f,
                "a {origin:?} packet replayed or too old (sequence {sequence})"
            ),
            Refusal::Rate(o) => write!(
                f,
                "an event from {o:?} beyond its rate ({EVENT_RATE}/s, bursts of {EVENT_BURST})"
            ),
        }
    }
}

fn article(word: &str) -> &'static str {
    if word.starts_with(['a', 'e', 'i', 'o', 'u']) {
        "an"
    } else {
        "a"
    }
}

/// Refused packets by reason (shared with the role's counters and JSON).
#[derive(Debug, Default)]
pub struct Refusals {
    /// Not sealed (or not a packet at all).
    pub unsealed: AtomicU64,
    /// From an origin not in the room.
    pub stranger: AtomicU64,
    /// Signature failed.
    pub forged: AtomicU64,
    /// A kind the origin's role may not send.
    pub role: AtomicU64,
    /// Replayed or too old.
    pub replay: AtomicU64,
    /// Events beyond the rate.
    pub rate: AtomicU64,
    /// The last refusal, said.
    pub last: Mutex<Option<String>>,
}

impl Refusals {
    /// Every refusal.
    pub fn total(&self) -> u64 {
        [
            &self.unsealed,
            &self.stranger,
            &self.forged,
            &self.role,
            &self.replay,
            &self.rate,
        ]
        .iter()
        .map(|a| a.load(Ordering::Relaxed))
        .sum()
    }

    fn count(&self, r: &Refusal) {
        let a = match r {
            Refusal::Unsealed(_) => &self.unsealed,
            Refusal::Stranger(_) => &self.stranger,
            Refusal::Forged(_) => &self.forged,
            Refusal::Role { .. } => &self.role,
            Refusal::Replay { .. } => &self.replay,
            Refusal::Rate(_) => &self.rate,
        };
        a.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut g) = self.last.lock() {
            *g = Some(r.to_string());
        }
    }

    /// The counts as JSON (`{"unsealed":…, …, "last": "…"}`).
    pub fn json(&self) -> serde_json::Value {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        serde_json::json!({
            "total": self.total(),
            "unsealed": l(&self.unsealed),
            "stranger": l(&self.stranger),
            "forged": l(&self.forged),
            "role": l(&self.role),
            "replay": l(&self.replay),
            "rate": l(&self.rate),
            "last": self.last.lock().ok().and_then(|g| g.clone()),
        })
    }
}

/// The newest sequence from one origin and kind, and which of the [`WINDOW`] before it were taken.
#[derive(Debug, Clone, Copy)]
struct Window {
    newest: u64,
    seen: u64,
}

impl Window {
    /// Take `seq` once: newer than the newest, or within the window and not seen.
    fn take(&mut self, seq: u64) -> bool {
        if seq > self.newest {
            let shift = seq - self.newest;
            self.seen = if shift >= 64 { 0 } else { self.seen << shift };
            // Bit 0 is the newest itself.
            self.seen |= 1;
            self.newest = seq;
            return true;
        }
        let back = self.newest - seq;
        if back >= WINDOW {
            return false;
        }
        let bit = 1u64 << back;
        if self.seen & bit != 0 {
            return false;
        }
        self.seen |= bit;
        true
    }
}

/// Opens packets against a room's certificates (one per receiving worker: not shared).
pub struct Opener {
    room: Arc<Room>,
    windows: HashMap<(usize, Kind), Window>,
    /// Per site: tokens left and when they were counted (ns).
    buckets: HashMap<usize, (f64, u64)>,
    /// The counts.
    pub refusals: Arc<Refusals>,
}

/// An opened packet.
#[derive(Debug)]
pub struct Opened<'a> {
    /// Who sealed it.
    pub origin: &'a str,
    /// Its role.
    pub role: Role,
    /// What it is.
    pub kind: Kind,
    /// The payload.
    pub payload: &'a [u8],
}

impl Opener {
    /// An opener for `room`, counting into `refusals`.
    pub fn new(room: Arc<Room>, refusals: Arc<Refusals>) -> Self {
        Self {
            room,
            windows: HashMap::new(),
            buckets: HashMap::new(),
            refusals,
        }
    }

    /// Open `bytes` (arrived at `now_ns` on a monotonic clock); a refusal is counted.
    pub fn open<'a>(&mut self, bytes: &'a [u8], now_ns: u64) -> Result<Opened<'a>, Refusal> {
        let r = self.check(bytes, now_ns);
        if let Err(e) = &r {
            self.refusals.count(e);
        }
        r
    }

    fn check<'a>(&mut self, bytes: &'a [u8], now_ns: u64) -> Result<Opened<'a>, Refusal> {
        let unsealed = |why: &str| Refusal::Unsealed(why.to_string());
        if bytes.len() < OVERHEAD || bytes[..4] != MAGIC {
            return Err(unsealed(if bytes.len() >= 4 && bytes[..4] == MAGIC {
                "truncated"
            } else {
                "no seal: a participant without the room's keys, or plain TCP's packets"
            }));
        }
        if bytes.len() > OVERHEAD + 255 + MAX_PAYLOAD {
            return Err(unsealed("longer than any packet"));
        }
        let kind = Kind::of(bytes[4]).ok_or_else(|| unsealed("an unknown kind"))?;
        let name_len = bytes[5] as usize;
        let body_end = bytes.len() - 64;
        if 6 + name_len + 8 > body_end {
            return Err(unsealed("truncated"));
        }
        let name = std::str::from_utf8(&bytes[6..6 + name_len])
            .map_err(|_| unsealed("an origin that is not text"))?;
        let Some(who) = self.room.members.iter().position(|m| m.name == name) else {
            return Err(Refusal::Stranger(name.escape_debug().to_string()));
        };
        let member = &self.room.members[who];
        let key =
            ring::signature::UnparsedPublicKey::new(&ring::signature::ED25519, &member.public_key);
        key.verify(
            &signed(&self.room.room, &bytes[..body_end]),
            &bytes[body_end..],
        )
        .map_err(|_| Refusal::Forged(name.to_string()))?;
        if !kind.allowed(member.role) {
            return Err(Refusal::Role {
                origin: name.to_string(),
                role: member.role,
                kind,
            });
        }
        let at = 6 + name_len;
        let mut s = [0u8; 8];
        s.copy_from_slice(&bytes[at..at + 8]);
        let seq = u64::from_le_bytes(s);
        let w = self.windows.entry((who, kind)).or_insert(Window {
            newest: seq,
            seen: 0,
        });
        if !w.take(seq) {
            return Err(Refusal::Replay {
                origin: name.to_string(),
                sequence: seq,
            });
        }
        if kind == Kind::Event {
            let b = self.buckets.entry(who).or_insert((EVENT_BURST, now_ns));
            let dt = now_ns.saturating_sub(b.1) as f64 / 1e9;
            b.0 = (b.0 + dt * EVENT_RATE).min(EVENT_BURST);
            b.1 = now_ns;
            if b.0 < 1.0 {
                return Err(Refusal::Rate(name.to_string()));
            }
            b.0 -= 1.0;
        }
        Ok(Opened {
            origin: name,
            role: member.role,
            kind,
            payload: &bytes[at + 8..body_end],
        })
    }
}

/// A participant's two ends: seal what it sends, open what it receives — or, with no keys (a
/// closed lab network on plain TCP), pass packets as they are.
#[derive(Clone)]
pub struct Guard {
    sealer: Option<Arc<Sealer>>,
    room: Option<Arc<Room>>,
    /// Refused packets (also counted where there are no keys: bytes that are not a packet).
    pub refusals: Arc<Refusals>,
}

impl Guard {
    /// The guard of `room` (none: plain packets).
    pub fn new(room: Option<Arc<Room>>) -> Self {
        Self {
            sealer: room.clone().map(|r| Arc::new(Sealer::new(r))),
            room,
            refusals: Arc::new(Refusals::default()),
        }
    }

    /// Whether packets are sealed.
    pub fn sealed(&self) -> bool {
        self.sealer.is_some()
    }

    /// The bytes to send for `payload` of `kind`.
    pub fn wrap(&self, kind: Kind, payload: Vec<u8>) -> Vec<u8> {
        match &self.sealer {
            Some(s) => s.seal(kind, &payload),
            None => payload,
        }
    }

    /// A receiving end (one per worker thread).
    pub fn inbox(&self) -> Inbox {
        Inbox {
            opener: self
                .room
                .clone()
                .map(|r| Opener::new(r, self.refusals.clone())),
        }
    }
}

/// A receiving worker's end of a [`Guard`].
pub struct Inbox {
    opener: Option<Opener>,
}

impl Inbox {
    /// The payload of `bytes` if it opens as one of `kinds` (with no keys: `bytes` as they are);
    /// a refusal is counted and `None` returned. The origin's name comes with it when sealed.
    pub fn open<'a>(
        &mut self,
        bytes: &'a [u8],
        now_ns: u64,
        kinds: &[Kind],
    ) -> Option<(Option<&'a str>, &'a [u8])> {
        match &mut self.opener {
            None => Some((None, bytes)),
            Some(o) => match o.open(bytes, now_ns) {
                Ok(p) if kinds.contains(&p.kind) => Some((Some(p.origin), p.payload)),
                Ok(p) => {
                    o.refusals.count(&Refusal::Unsealed(format!(
                        "a {} on another packet's key",
                        p.kind.name()
                    )));
                    None
                }
                Err(_) => None,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::keys;

    fn room(tag: &str) -> (std::path::PathBuf, impl Fn(&str) -> Arc<Room>) {
        let d = std::env::temp_dir().join(format!("lungdyn-seal-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        keys::make("ward", &d, &keys::default_participants(), 365).unwrap();
        let d2 = d.clone();
        (d, move |who: &str| Arc::new(Room::load(&d2, who).unwrap()))
    }

    #[test]
    fn a_sealed_packet_opens_once_and_every_forgery_is_refused_by_reason() {
        let (d, load) = room("forge");
        let source = Sealer::new(load("source"));
        let site = Sealer::new(load("site"));
        let observer = Sealer::new(load("observer"));
        let router = Sealer::new(load("router"));
        let refusals = Arc::new(Refusals::default());
        let mut at_site = Opener::new(load("site"), refusals.clone());
        let p = source.seal(Kind::State, b"breath");
        let o = at_site.open(&p, 0).unwrap();
        assert_eq!(
            (o.origin, o.kind, o.payload),
            ("source", Kind::State, &b"breath"[..])
        );
        // The same packet again: a replay.
        assert!(matches!(at_site.open(&p, 0), Err(Refusal::Replay { .. })));
        // One bit flipped anywhere: the signature fails (or the origin is no one).
        for i in [0usize, 4, 6, 12, 20, p.len() - 1] {
            let mut q = p.clone();
            q[i] ^= 0x10;
            assert!(at_site.open(&q, 0).is_err(), "bit flipped at {i}");
        }
        // A site, an observer or the router sending a state; an observer an event; a site a
        // clock answer.
        for (s, k) in [
            (&site, Kind::State),
            (&observer, Kind::State),
            (&router, Kind::State),
            (&observer, Kind::Event),
            (&site, Kind::Reply),
        ] {
            let e = at_site.open(&s.seal(k, b"x"), 0).unwrap_err();
            assert!(matches!(e, Refusal::Role { .. }), "{e}");
        }
        // The router's clock answer is taken (the time relay).
        assert!(at_site.open(&router.seal(Kind::Reply, b"t"), 0).is_ok());
        // Not sealed, truncated, a huge sequence forged without the key.
        assert!(matches!(
            at_site.open(b"LDCS plain", 0),
            Err(Refusal::Unsealed(_))
        ));
        assert!(matches!(
            at_site.open(&p[..30], 0),
            Err(Refusal::Unsealed(_))
        ));
        let mut far = source.seal_with(Kind::State, 1 << 62, b"breath");
        let n = far.len();
        far[n - 64..].copy_from_slice(&[0u8; 64]);
        assert!(matches!(at_site.open(&far, 0), Err(Refusal::Forged(_))));
        // The source's next real state is still taken.
        assert!(at_site.open(&source.seal(Kind::State, b"next"), 0).is_ok());
        assert_eq!(refusals.forged.load(Ordering::Relaxed) >= 2, true);
        assert_eq!(refusals.role.load(Ordering::Relaxed), 5);
        assert_eq!(refusals.replay.load(Ordering::Relaxed), 1);
        assert!(refusals.last.lock().unwrap().is_some());
        std::fs::remove_dir_all(d).unwrap();
    }

    #[test]
    fn another_rooms_participant_of_the_same_name_is_refused_as_forged() {
        let (d, load) = room("other-a");
        let (d2, load2) = room("other-b");
        let theirs = Sealer::new(load2("source"));
        let mut ours = Opener::new(load("site"), Arc::default());
        assert!(matches!(
            ours.open(&theirs.seal(Kind::State, b"x"), 0),
            Err(Refusal::Forged(_))
        ));
        for d in [d, d2] {
            std::fs::remove_dir_all(d).unwrap();
        }
    }

    #[test]
    fn reordered_packets_are_taken_once_within_the_window_and_old_ones_refused() {
        let mut w = Window {
            newest: 99,
            seen: 0,
        };
        assert!(w.take(100));
        assert!(w.take(103));
        assert!(w.take(101), "reordered, within the window");
        assert!(!w.take(101), "twice");
        assert!(!w.take(100), "twice");
        assert!(w.take(102));
        assert!(w.take(103 + 200));
        assert!(!w.take(103), "far behind the newest");
        assert!(w.take(103 + 200 - 63));
        assert!(!w.take(103 + 200 - 64));
        // The extremes of u64 do not overflow.
        let mut w = Window {
            newest: u64::MAX - 1,
            seen: 0,
        };
        assert!(w.take(u64::MAX));
        assert!(!w.take(0));
    }

    #[test]
    fn a_sites_events_beyond_its_rate_are_refused_and_it_recovers() {
        let (d, load) = room("rate");
        let site = Sealer::new(load("site"));
        let mut at_source = Opener::new(load("source"), Arc::default());
        let taken = (0..100)
            .filter(|_| at_source.open(&site.seal(Kind::Event, b"e"), 0).is_ok())
            .count();
        assert_eq!(taken, EVENT_BURST as usize);
        assert_eq!(at_source.refusals.rate.load(Ordering::Relaxed), 80);
        // One second later, five more.
        let later = (0..10)
            .filter(|_| {
                at_source
                    .open(&site.seal(Kind::Event, b"e"), 1_000_000_000)
                    .is_ok()
            })
            .count();
        assert_eq!(later, EVENT_RATE as usize);
        std::fs::remove_dir_all(d).unwrap();
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(256))]
        /// Any bytes, and any truncation or one-byte change of a real sealed packet, neither
        /// panic nor open (only the packet as sealed opens), and every refusal is counted.
        #[test]
        fn no_bytes_but_the_sealed_ones_open(
            junk in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..300),
            cut in 0usize..200,
            at in 0usize..200,
            flip in 1u8..=255,
        ) {
            let (d, load) = shared_room();
            let source = Sealer::new(load("source"));
            let mut at_site = Opener::new(load("site"), Arc::default());
            proptest::prop_assert!(at_site.open(&junk, 0).is_err());
            let p = source.seal(Kind::State, b"a state's bytes");
            let cut = cut % p.len();
            proptest::prop_assert!(at_site.open(&p[..cut], 0).is_err());
            let mut q = p.clone();
            q[at % p.len()] ^= flip;
            proptest::prop_assert!(at_site.open(&q, 0).is_err());
            proptest::prop_assert!(at_site.open(&p, 0).is_ok());
            proptest::prop_assert_eq!(at_site.refusals.total(), 3);
            let _ = d;
        }
    }

    /// One room for every proptest case (making keys per case would be most of the test's time).
    fn shared_room() -> (std::path::PathBuf, impl Fn(&str) -> Arc<Room>) {
        static MADE: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
        let d = MADE
            .get_or_init(|| {
                let d =
                    std::env::temp_dir().join(format!("lungdyn-seal-prop-{}", std::process::id()));
                let _ = std::fs::remove_dir_all(&d);
                keys::make("ward", &d, &keys::default_participants(), 365).unwrap();
                d
            })
            .clone();
        let d2 = d.clone();
        (d, move |who: &str| Arc::new(Room::load(&d2, who).unwrap()))
    }

    #[test]
    fn without_keys_the_guard_passes_packets_as_they_are() {
        let g = Guard::new(None);
        assert!(!g.sealed());
        assert_eq!(g.wrap(Kind::State, vec![1, 2]), vec![1, 2]);
        let mut i = g.inbox();
        assert_eq!(i.open(&[1, 2], 0, &[Kind::State]).unwrap().1, &[1, 2]);
    }
}
