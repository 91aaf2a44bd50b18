//! The source side of a shared session: publish control states, answer probes, take events.
//!
//! Peer to peer the source answers every site's probes; through a router the sites probe the
//! time relay beside it ([`crate::relay`]) and only the relay probes the source. A source that is
//! itself the router (`--mode router`) also answers on the relay's key (it is where the router
//! runs).

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;

use control_state::{decode, encode_to_vec, Packet, RemoteEvent};
use zenoh::Wait;
use zenoh_ext::{AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use crate::link::{self, Impairment, LinkIn};
use crate::seal::{Guard, Kind};
use crate::{zerr, Keys, Net, RemoteError};

/// What the source did.
#[derive(Debug, Default)]
pub struct SourceCounts {
    /// Control states published.
    pub states: AtomicU64,
    /// Bytes of control states published (payload, once per publish).
    pub state_bytes: AtomicU64,
    /// Probes answered.
    pub probes: AtomicU64,
    /// Events taken from sites.
    pub events: AtomicU64,
    /// Packets refused (bad bytes, a state from another source, a seal that does not hold: the
    /// reasons in [`Source::guard`]'s refusals).
    pub refused: AtomicU64,
    /// States the engine handed over that Zenoh would not put (the session closing).
    pub put_failures: AtomicU64,
}

/// A source's Zenoh side.
pub struct Source {
    session: zenoh::Session,
    publisher: zenoh_ext::AdvancedPublisher<'static>,
    _probes: zenoh::pubsub::Subscriber<()>,
    /// The probers' warm-up packets (and the relay's key's, as its own relay in router mode).
    _warm: Vec<zenoh::pubsub::Subscriber<()>>,
    /// In router mode the source is also the time relay (its own clock, offset 0).
    _relay: Option<(
        zenoh::pubsub::Subscriber<()>,
        zenoh::liveliness::LivelinessToken,
    )>,
    _events: zenoh::pubsub::Subscriber<()>,
    _presence: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
    _link: LinkIn,
    events: std::sync::Mutex<Receiver<RemoteEvent>>,
    sites: Arc<AtomicUsize>,
    /// Counters.
    pub counts: Arc<SourceCounts>,
    /// Seals the states and answers; counts the packets whose seal did not hold, by reason.
    pub guard: Guard,
}

impl Source {
    /// Open the source `id` of `keys`' room on `net`; incoming probes and events pass `imp`.
    pub fn open(net: &Net, keys: &Keys, id: u64, imp: Impairment) -> Result<Self, RemoteError> {
        let session = net.open()?;
        let publisher = session
            .declare_publisher(keys.state())
            // A late joiner's history query gets the latest state at once.
            .cache(CacheConfig::default().max_samples(1))
            // Sites detect a missed state and ask the cache for it.
            .sample_miss_detection(
                MissDetectionConfig::default().heartbeat(std::time::Duration::from_millis(500)),
            )
            .publisher_detection()
            .wait()
            .map_err(zerr("declare the state publisher"))?;
        let counts = Arc::new(SourceCounts::default());
        let (etx, events) = sync_channel(256);
        let (c, s2, k2) = (counts.clone(), session.clone(), keys.clone());
        let guard = net.guard();
        let (g2, mut inbox) = (guard.clone(), guard.inbox());
        // Probes and events: opened and decoded on the link worker, never on Zenoh's threads.
        let link = link::start("remote-source-in", imp, move |bytes, at| {
            let Some((_, payload)) = inbox.open(&bytes, at, &[Kind::Probe, Kind::Event]) else {
                c.refused.fetch_add(1, Ordering::Relaxed);
                return;
            };
            match decode(payload) {
                Ok(Packet::Probe {
                    from,
                    to,
                    id: pid,
                    t0_ns,
                }) if to == id || to == 0 => {
                    let reply = Packet::ProbeReply {
                        from: id,
                        to: from,
                        id: pid,
                        t0_ns,
                        t1_ns: at,
                        t2_ns: imp.clock.now(),
                    };
                    if let Ok(b) = encode_to_vec(&reply) {
                        if s2
                            .put(k2.reply(from), g2.wrap(Kind::Reply, b))
                            .wait()
                            .is_ok()
                        {
                            c.probes.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                Ok(Packet::Event(e)) => {
                    c.events.fetch_add(1, Ordering::Relaxed);
                    let _ = etx.try_send(e);
                }
                Ok(Packet::Probe { .. }) => {}
                Ok(_) | Err(_) => {
                    c.refused.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
        let l1 = link.clone();
        let probes = session
            .declare_subscriber(keys.probe())
            .callback(move |s| l1.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the probe subscriber"))?;
        // Warm-up packets only wake Zenoh's threads: taken and dropped there.
        let mut warm = vec![session
            .declare_subscriber(keys.warm())
            .callback(|_| {})
            .wait()
            .map_err(zerr("declare the warm-up subscriber"))?];
        if net.mode == "router" {
            warm.push(
                session
                    .declare_subscriber(keys.relay_warm())
                    .callback(|_| {})
                    .wait()
                    .map_err(zerr("declare the relay's warm-up subscriber"))?,
            );
        }
        // A source that is the router is also the sites' time relay: the relay's answer in the
        // source's time is its own answer.
        let relay = if net.mode == "router" {
            let l = link.clone();
            let sub = session
                .declare_subscriber(keys.relay_probe())
                .callback(move |s| l.push(s.payload().to_bytes().into_owned()))
                .wait()
                .map_err(zerr("declare the relay probe subscriber"))?;
            let token = session
                .liveliness()
                .declare_token(keys.relay_presence())
                .wait()
                .map_err(zerr("declare the relay's liveliness token"))?;
            Some((sub, token))
        } else {
            None
        };
        let l2 = link.clone();
        let ev = session
            .declare_subscriber(keys.event())
            .callback(move |s| l2.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the event subscriber"))?;
        let sites = Arc::new(AtomicUsize::new(0));
        let s3 = sites.clone();
        let presence = session
            .liveliness()
            .declare_subscriber(keys.presence_all())
            .history(true)
            .callback(move |s| match s.kind() {
                zenoh::sample::SampleKind::Put => {
                    s3.fetch_add(1, Ordering::Relaxed);
                }
                zenoh::sample::SampleKind::Delete => {
                    let _ = s3.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |n| {
                        Some(n.saturating_sub(1))
                    });
                }
            })
            .wait()
            .map_err(zerr("declare the presence subscriber"))?;
        let token = session
            .liveliness()
            .declare_token(keys.source_presence())
            .wait()
            .map_err(zerr("declare the source's liveliness token"))?;
        Ok(Self {
            session,
            publisher,
            _probes: probes,
            _warm: warm,
            _relay: relay,
            _events: ev,
            _presence: presence,
            _token: token,
            _link: link,
            events: std::sync::Mutex::new(events),
            sites,
            counts,
            guard,
        })
    }

    /// Publish one encoded state (bytes as [`control_state::encode`] wrote them).
    pub fn publish(&self, bytes: &[u8]) -> Result<(), RemoteError> {
        self.publisher
            .put(self.guard.wrap(Kind::State, bytes.to_vec()))
            .wait()
            .map_err(zerr("publish a control state"))?;
        self.counts.states.fetch_add(1, Ordering::Relaxed);
        self.counts
            .state_bytes
            .fetch_add(bytes.len() as u64, Ordering::Relaxed);
        Ok(())
    }

    /// Events sent by sites since the last call.
    pub fn take_events(&self) -> Vec<RemoteEvent> {
        let mut v = Vec::new();
        self.drain_events(&mut |e| v.push(*e));
        v
    }

    /// Hand each event sent by sites since the last call to `f` (no allocation); how many.
    pub fn drain_events(&self, f: &mut dyn FnMut(&RemoteEvent)) -> usize {
        let Ok(rx) = self.events.lock() else {
            return 0;
        };
        let mut n = 0;
        for e in rx.try_iter() {
            f(&e);
            n += 1;
        }
        n
    }

    /// Packets the link handed to the worker, and those dropped because it was behind.
    pub fn link_counts(&self) -> &Arc<link::LinkCounts> {
        self._link.counts()
    }

    /// Sites present now (their liveliness tokens).
    pub fn sites(&self) -> usize {
        self.sites.load(Ordering::Relaxed)
    }

    /// The Zenoh session (to close it).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }
}

/// A site's event as the engine's control packet: its origin (the site) and the site's own
/// sequence, so the engine takes a repeat once and announces it with both.
pub fn control_packet(e: &RemoteEvent) -> ipc_types::ControlPacket {
    ipc_types::ControlPacket {
        layout_version: ipc_types::LAYOUT_VERSION,
        kind: e.kind,
        lung: e.lung,
        _pad: 0,
        sequence: e.sequence,
        origin: e.origin,
    }
}

/// The source engine's ports on Zenoh, for [`engine::runtime::process::run_loop`] run in the
/// same process as the Zenoh session (the harness, the tests): the sites' events come in as
/// control packets, the engine's states go out on the publisher.
pub struct EnginePorts<'a>(pub &'a Source);

impl transport::Receive<ipc_types::ControlPacket> for EnginePorts<'_> {
    fn wait_until(&mut self, _deadline_ns: u64) -> Result<(), transport::PortError> {
        Ok(())
    }
    fn take_latest(&mut self) -> Result<Option<ipc_types::ControlPacket>, transport::PortError> {
        let mut last = None;
        self.0.drain_events(&mut |e| last = Some(control_packet(e)));
        Ok(last)
    }
    fn drain(
        &mut self,
        f: &mut dyn FnMut(&ipc_types::ControlPacket),
    ) -> Result<usize, transport::PortError> {
        Ok(self.0.drain_events(&mut |e| f(&control_packet(e))))
    }
}

impl transport::Publish<control_state::ControlStateFrame> for EnginePorts<'_> {
    fn publish(
        &mut self,
        frame: &control_state::ControlStateFrame,
    ) -> Result<(), transport::PortError> {
        // A failed put is counted (the session is closing); the engine keeps ticking.
        if self.0.publish(frame.encoded()).is_err() {
            self.0.counts.put_failures.fetch_add(1, Ordering::Relaxed);
        }
        Ok(())
    }
}
