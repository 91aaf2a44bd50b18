//! A site: receive the source's control states, measure the path, run its own engine in step.

use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use control_state::{decode, encode_to_vec, Packet, RemoteEvent};
use engine::runtime::remote::{BreathCache, Prepared};
use engine::runtime::EngineCore;
use ipc_types::EngineFrame;
use transport::clock::now_ns;
use zenoh::Wait;
use zenoh_ext::{AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

use crate::clock::{DelayEstimator, LocalClock, ProbeStamps, RATE_MAX};
use crate::link::{self, Impairment, LinkIn};
use crate::{zerr, Keys, Net, RemoteError};
pub use lung_model::scene_remote::ClockSync;

/// What a site received and did.
#[derive(Debug, Default)]
pub struct SiteCounts {
    /// States taken (decoded, new, usable).
    pub states: AtomicU64,
    /// Packets refused: bytes that are not a packet (checksum, version, ...), or a state the
    /// engine cannot use (the reason is kept in [`Site::last_refusal`]).
    pub refused: AtomicU64,
    /// States already seen (history and live delivery of the same state, a retransmission).
    pub repeated: AtomicU64,
    /// Probe replies taken.
    pub probes: AtomicU64,
    /// When the first was taken (host clock, ns; 0 before): the end of joining.
    pub first_probe_ns: AtomicU64,
    /// States the tick loop applied.
    pub applied: AtomicU64,
    /// Breathing cycles the site breathed on its own prediction because the source's state for
    /// them was late or lost: not there [`late_after_ns`] after the cycle started (the engine
    /// breathes on with the last state's breath until a newer one arrives). A state that comes
    /// within the path's delay, as every state does (it is sent at the cycle start the site
    /// reaches at the same moment), is not counted.
    pub predicted_cycles: AtomicU64,
    /// Disease cycles announced ahead that reached the engine before their start tick (put in at
    /// that tick, as the source does).
    pub announced_in_time: AtomicU64,
    /// Disease cycles whose announcement reached the engine after their start tick (put in at
    /// once; the ticks between showed the previous cycle's breath).
    pub announced_late: AtomicU64,
}

impl SiteCounts {
    /// A probe reply taken: counted, the first one's time kept.
    fn took_probe(&self) {
        if self.probes.fetch_add(1, Ordering::Relaxed) == 0 {
            self.first_probe_ns.store(now_ns(), Ordering::Relaxed);
        }
    }
}

/// The largest step between one source's consecutive states a site takes (a state per breath
/// or change: 2²⁴ is years of a session).
pub const MAX_SEQUENCE_LEAP: u64 = 1 << 24;

/// Where a state `(epoch, sequence)` stands against the newest taken.
enum StateOrder {
    /// Newer (or of a new epoch: a restarted source).
    New,
    /// Already taken (history and live delivery of the same state, a retransmission).
    Repeated,
    /// A leap no source makes: refused, with why.
    Leap(String),
}

fn state_order(newest: Option<(u64, u64)>, key: (u64, u64)) -> StateOrder {
    match newest {
        Some((e, q)) if e == key.0 && q >= key.1 => StateOrder::Repeated,
        // A source numbers its states one by one: a leap no run could make is a forgery (on plain
        // TCP), and taking it would make every real state after it look old.
        Some((e, q)) if e == key.0 && key.1 - q > MAX_SEQUENCE_LEAP => StateOrder::Leap(format!(
            "a state numbered {} after {q}: a leap no source makes (forged?)",
            key.1
        )),
        _ => StateOrder::New,
    }
}

/// Events kept per site (the latest; older ones are dropped from this record only).
pub const EVENTS_KEPT: usize = 256;

/// The path's figures, kept by the link worker, read by the tick loop (atomics: no lock; the
/// offset, its time and its rate are stored one after the other, so a reader may take a new
/// offset with the previous rate: ≤ rate × one probe interval, 2.5 ns at 50 ppm and 50 ms).
#[derive(Debug, Default)]
pub struct PathFigures {
    /// Source clock minus site clock, ns, at [`Self::offset_at_ns`] ([`Self::offset_at`] moves
    /// it to another time with the rate).
    pub offset_ns: AtomicI64,
    /// Where [`Self::offset_ns`] holds (the site's clock), ns.
    pub offset_at_ns: AtomicU64,
    /// The clock rate applied (dθ/dt, f64 bits; 0 until a fit is trusted, [`crate::clock`]).
    pub rate_bits: AtomicU64,
    /// The fitted rate, applied or not (f64 bits), once [`Self::rate_fitted`].
    pub fitted_rate_bits: AtomicU64,
    /// A rate has been fitted.
    pub rate_fitted: AtomicBool,
    /// Rate fits refused as beyond ±[`RATE_MAX`] (not applied).
    pub rates_refused: AtomicU64,
    /// True once a probe came back.
    pub have_offset: AtomicBool,
    /// Smoothed one-way delay, ns.
    pub delay_ns: AtomicU64,
    /// Round-trip variation, ns.
    pub jitter_ns: AtomicU64,
    /// Who answered the last probe (the source's or the relay's id).
    pub answered_by: AtomicU64,
    /// A time relay is present (its liveliness token; a site syncing with the relay only).
    pub relay_present: AtomicBool,
    /// Times the relay went away (the site keeps its last offset meanwhile).
    pub relay_lost: AtomicU64,
}

impl PathFigures {
    /// Add a reply's stamps (answered by `from`) to `estimator` and publish its figures; false
    /// when the stamps are inconsistent (refused by the estimator).
    pub fn take(&self, estimator: &mut DelayEstimator, stamps: ProbeStamps, from: u64) -> bool {
        if !estimator.add(stamps) {
            return false;
        }
        self.answered_by.store(from, Ordering::Relaxed);
        if let Some(o) = estimator.offset() {
            self.offset_ns.store(o.offset_ns, Ordering::Relaxed);
            self.offset_at_ns.store(o.at, Ordering::Relaxed);
            self.rate_bits.store(o.rate.to_bits(), Ordering::Relaxed);
            self.have_offset.store(true, Ordering::Relaxed);
        }
        let rate = estimator.rate();
        if let Some(r) = rate.fitted() {
            self.fitted_rate_bits.store(r.to_bits(), Ordering::Relaxed);
            self.rate_fitted.store(true, Ordering::Relaxed);
        }
        self.rates_refused
            .store(estimator.rates_refused(), Ordering::Relaxed);
        self.delay_ns
            .store(estimator.delay_ns() as u64, Ordering::Relaxed);
        self.jitter_ns
            .store(estimator.jitter_ns() as u64, Ordering::Relaxed);
        true
    }

    /// Source clock minus site clock at `t` (the site's clock), ns: the estimate moved there
    /// with the applied rate; `None` before the first probe came back.
    pub fn offset_at(&self, t: u64) -> Option<i64> {
        self.have_offset.load(Ordering::Relaxed).then(|| {
            crate::clock::Offset {
                at: self.offset_at_ns.load(Ordering::Relaxed),
                offset_ns: self.offset_ns.load(Ordering::Relaxed),
                rate: self.rate(),
            }
            .at(t)
        })
    }

    /// The clock rate applied (dθ/dt; 0 until a fit is trusted).
    pub fn rate(&self) -> f64 {
        f64::from_bits(self.rate_bits.load(Ordering::Relaxed))
    }

    /// The fitted rate, applied or not (`None` before a fit).
    pub fn fitted_rate(&self) -> Option<f64> {
        self.rate_fitted
            .load(Ordering::Relaxed)
            .then(|| f64::from_bits(self.fitted_rate_bits.load(Ordering::Relaxed)))
    }

    /// What to say when the rate's state changed since `last` (updated): applied, or refused as
    /// implausible (`None` otherwise, and for `uncertain`/`unknown`: nothing to act on).
    pub fn rate_news(&self, last: &mut &'static str) -> Option<String> {
        let word = self.rate_word();
        if word == *last {
            return None;
        }
        let was = std::mem::replace(last, word);
        let ppm = self.fitted_rate().unwrap_or(0.0) * 1e6;
        match word {
            "applied" => Some(format!(
                "clock rate against the source {ppm:+.1} ppm: the offset is extrapolated with it"
            )),
            // Said when a rate that was applied is withdrawn, so the log never shows "applied"
            // twice without why.
            "uncertain" | "unknown" => Some(
                "clock rate against the source no longer trusted (too few probes, or its fit's \
                 standard error over 5 ppm): the offset is not extrapolated until it is again"
                    .to_string(),
            )
            .filter(|_| was == "applied"),
            "implausible" => Some(format!(
                "clock rate against the source fitted at {ppm:+.1} ppm, beyond ±{:.0} ppm (no \
                 two quartz clocks differ so much: a stepped clock or a bad peer?): not applied",
                RATE_MAX * 1e6
            )),
            _ => None,
        }
    }

    /// The rate in words, for reports: `applied`, `implausible` (beyond ±500 ppm: not applied),
    /// `uncertain` (fitted, not trusted yet) or `unknown` (too few probes yet).
    pub fn rate_word(&self) -> &'static str {
        match self.fitted_rate() {
            None => "unknown",
            Some(_) if self.rate() != 0.0 => "applied",
            Some(r) if r.abs() > RATE_MAX => "implausible",
            Some(_) => "uncertain",
        }
    }
}

/// How long before each probe its prober puts a warm-up packet, ms. A probe sent on a path idle
/// since the last one (50–500 ms) found the sender's Zenoh TX thread and the receiver's RX thread
/// asleep, while the reply left on the answerer's just-woken threads: on this VM the way up took
/// 190 µs against 80 µs down, an offset error of +56 µs (+63 µs every 200 ms, +5 µs every 1 ms;
/// `remote/examples/probe_legs.rs`). A 1-byte packet 1 ms ahead wakes both ends: +2.6 µs.
pub const WARM_UP_MS: u64 = 1;

/// A prober: a thread `name` putting probes from `id` on `key` of `session`, stamped on `clock`,
/// each [`WARM_UP_MS`] after a 1-byte packet on `warm`.
pub(crate) struct Prober {
    pub name: String,
    /// Seals each probe.
    pub guard: crate::seal::Guard,
    pub session: zenoh::Session,
    pub key: String,
    pub warm: String,
    pub id: u64,
    pub clock: LocalClock,
}

impl Prober {
    /// Start it: probe `n` followed by a pause of `interval_ms(n)`, until `stop`; `after(sent)`
    /// runs on it after each.
    pub fn start(
        self,
        interval_ms: impl Fn(u64) -> u64 + Send + 'static,
        stop: Arc<AtomicBool>,
        mut after: impl FnMut(bool) + Send + 'static,
    ) -> std::io::Result<()> {
        let Prober {
            name,
            guard,
            session,
            key,
            warm,
            id,
            clock,
        } = self;
        std::thread::Builder::new().name(name).spawn(move || {
            let mut n = 0u64;
            while !stop.load(Ordering::Relaxed) {
                let _ = session.put(&warm, vec![0u8]).wait();
                std::thread::sleep(Duration::from_millis(WARM_UP_MS));
                let probe = Packet::Probe {
                    from: id,
                    to: 0,
                    id: n,
                    t0_ns: clock.now(),
                };
                let sent = encode_to_vec(&probe).is_ok_and(|b| {
                    session
                        .put(&key, guard.wrap(crate::seal::Kind::Probe, b))
                        .wait()
                        .is_ok()
                });
                after(sent);
                std::thread::sleep(Duration::from_millis(
                    interval_ms(n).saturating_sub(WARM_UP_MS).max(1),
                ));
                n += 1;
            }
        })?;
        Ok(())
    }
}

/// A site's Zenoh side.
pub struct Site {
    /// This site's id.
    pub id: u64,
    /// An observer never sends events.
    pub observer: bool,
    session: zenoh::Session,
    keys: Keys,
    /// Seals this site's probes and events; counts the packets whose seal did not hold.
    pub guard: crate::seal::Guard,
    _states: zenoh_ext::AdvancedSubscriber<()>,
    _replies: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
    _relay: Option<zenoh::pubsub::Subscriber<()>>,
    /// Whom this site probes for the source's clock.
    pub clock: ClockSync,
    /// This site's own clock (the host's unless emulated skewed).
    pub own_clock: LocalClock,
    link: LinkIn,
    prepared: Mutex<Option<Receiver<Prepared>>>,
    stop: Arc<AtomicBool>,
    /// Counters.
    pub counts: Arc<SiteCounts>,
    /// Delay, jitter, offset.
    pub path: Arc<PathFigures>,
    /// Why the last refused packet was refused.
    pub last_refusal: Arc<Mutex<Option<String>>>,
    /// Events the source announced (any site's, this one's included), each once, with the tick
    /// and cycle it applies at.
    pub events: Arc<Mutex<Vec<RemoteEvent>>>,
    event_sequence: AtomicU64,
}

impl Drop for Site {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl Site {
    /// Join `keys`' room on `net` as site `id`; incoming packets pass `imp`; a probe every
    /// `probe_ms` to `clock`: the source, or the time relay beside the router
    /// ([`crate::relay`]: the replies are in the source's time, the estimator is the same). When
    /// the relay goes away the site keeps its last offset (it stops changing; two machines'
    /// clocks part at their rate difference, tens of µs a second), says so in
    /// [`PathFigures::relay_present`] and [`PathFigures::relay_lost`], and takes the relay's
    /// answers again when it is back; it does not fall back to probing the source, which would
    /// put the per-site cost back on the source when the classroom's router host is in trouble.
    pub fn open(
        net: &Net,
        keys: &Keys,
        id: u64,
        observer: bool,
        imp: Impairment,
        probe_ms: u64,
        clock: ClockSync,
    ) -> Result<Self, RemoteError> {
        let session = net.open()?;
        let counts = Arc::new(SiteCounts::default());
        let path = Arc::new(PathFigures::default());
        let last_refusal = Arc::new(Mutex::new(None));
        let (ptx, prepared) = sync_channel::<Prepared>(8);
        let (c, p, r) = (counts.clone(), path.clone(), last_refusal.clone());
        let events = Arc::new(Mutex::new(Vec::new()));
        let ev = events.clone();
        let mut cache = BreathCache::default();
        let mut estimator = if imp.no_rate {
            DelayEstimator::without_rate()
        } else {
            DelayEstimator::default()
        };
        let mut newest: Option<(u64, u64)> = None;
        let refuse = move |r: &Mutex<Option<String>>, c: &SiteCounts, why: String| {
            c.refused.fetch_add(1, Ordering::Relaxed);
            if let Ok(mut g) = r.lock() {
                *g = Some(why);
            }
        };
        let guard = net.guard();
        let (mut inbox, refusals) = (guard.inbox(), guard.refusals.clone());
        let link = link::start(&format!("remote-site-{id:x}"), imp, move |bytes, at| {
            use crate::seal::Kind;
            let Some((_, payload)) = inbox.open(&bytes, at, &[Kind::State, Kind::Reply]) else {
                let why = refusals.last.lock().ok().and_then(|g| g.clone());
                refuse(&r, &c, why.unwrap_or_else(|| "a packet refused".into()));
                return;
            };
            match decode(payload) {
                Ok(Packet::State(s)) => {
                    // A restarted source has a new epoch: its states are taken from then on.
                    let key = (s.epoch, s.sequence);
                    match state_order(newest, key) {
                        StateOrder::New => {}
                        StateOrder::Repeated => {
                            c.repeated.fetch_add(1, Ordering::Relaxed);
                            return;
                        }
                        StateOrder::Leap(why) => return refuse(&r, &c, why),
                    }
                    if !s.events.is_empty() {
                        if let Ok(mut seen) = ev.lock() {
                            for e in s.events.iter() {
                                if !seen.iter().any(|o: &RemoteEvent| {
                                    (o.origin, o.sequence) == (e.origin, e.sequence)
                                }) {
                                    if seen.len() == EVENTS_KEPT {
                                        seen.remove(0);
                                    }
                                    seen.push(*e);
                                }
                            }
                        }
                    }
                    match Prepared::of(s, &mut cache) {
                        Ok(prep) => {
                            newest = Some(key);
                            c.states.fetch_add(1, Ordering::Relaxed);
                            let _ = ptx.try_send(prep);
                        }
                        Err(e) => refuse(&r, &c, e.to_string()),
                    }
                }
                Ok(ref packet @ Packet::ProbeReply { to, .. }) if to == id => {
                    let Some((from, stamps)) = ProbeStamps::of_reply(packet, id, at) else {
                        return;
                    };
                    if p.take(&mut estimator, stamps, from) {
                        c.took_probe();
                    }
                }
                Ok(_) => {}
                Err(e) => refuse(&r, &c, e.to_string()),
            }
        });
        let l1 = link.clone();
        let states = session
            .declare_subscriber(keys.state())
            // The publisher's cache answers at once: a late joiner has the current state.
            .history(HistoryConfig::default().detect_late_publishers())
            // A missed state (sequence gap, heartbeat) is asked for again.
            .recovery(RecoveryConfig::default().heartbeat())
            .subscriber_detection()
            .callback(move |s| l1.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the state subscriber"))?;
        let l2 = link.clone();
        let replies = session
            .declare_subscriber(keys.reply(id))
            .callback(move |s| l2.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the probe-reply subscriber"))?;
        let token = session
            .liveliness()
            .declare_token(keys.presence(id))
            .wait()
            .map_err(zerr("declare the site's liveliness token"))?;
        let relay = match clock {
            ClockSync::Source => None,
            ClockSync::Relay => Some(relay_presence(&session, keys, &path)?),
        };
        let (probe_key, warm) = match clock {
            ClockSync::Source => (keys.probe(), keys.warm()),
            ClockSync::Relay => (keys.relay_probe(), keys.relay_warm()),
        };
        let stop = Arc::new(AtomicBool::new(false));
        Prober {
            name: format!("remote-probe-{id:x}"),
            guard: guard.clone(),
            session: session.clone(),
            key: probe_key,
            warm,
            id,
            clock: imp.clock,
        }
        .start(move |_| probe_ms, stop.clone(), |_| {})
        .map_err(|e| RemoteError::Usage(format!("start the site's prober: {e}")))?;
        Ok(Self {
            id,
            observer,
            session,
            keys: keys.clone(),
            guard,
            _states: states,
            _replies: replies,
            _token: token,
            _relay: relay,
            clock,
            own_clock: imp.clock,
            link,
            prepared: Mutex::new(Some(prepared)),
            stop,
            counts,
            path,
            last_refusal,
            events,
            event_sequence: AtomicU64::new(1),
        })
    }

    /// Send an intervention to the source (refused for an observer).
    pub fn send_event(&self, kind: u32, lung: u32) -> Result<u64, RemoteError> {
        if self.observer {
            return Err(RemoteError::Usage(
                "an observer site does not send events (join without --observer)".into(),
            ));
        }
        let sequence = self.event_sequence.fetch_add(1, Ordering::Relaxed);
        let b = encode_to_vec(&Packet::Event(RemoteEvent {
            origin: self.id,
            sequence,
            kind,
            lung,
            apply_cycle: 0,
            apply_tick: 0,
            course_cycle: 0,
            outcome: 0,
        }))
        .map_err(|e| RemoteError::Usage(e.to_string()))?;
        self.session
            .put(
                self.keys.event(),
                self.guard.wrap(crate::seal::Kind::Event, b),
            )
            .wait()
            .map_err(zerr("send an event"))?;
        Ok(sequence)
    }

    /// This site's Zenoh session.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// The engine runner fed by this site's states (once: `None` after the first call).
    pub fn runner(&self, core: EngineCore, hz: f64) -> Option<Runner> {
        let rx = self.prepared.lock().ok()?.take()?;
        Some(Runner::new(
            core,
            hz,
            rx,
            self.path.clone(),
            self.counts.clone(),
            self.own_clock,
        ))
    }

    /// Packets the link handed to the worker, lost to emulation, and overflowed.
    pub fn link_counts(&self) -> &Arc<link::LinkCounts> {
        self.link.counts()
    }
}

/// How long after a cycle's start its state counts as late, ns: the smoothed one-way delay, four
/// times the round-trip variation (RFC 6298's margin) and two ticks (the source publishes after
/// stepping the cycle's first tick; the site's link worker builds the state's breath).
pub fn late_after_ns(delay_ns: u64, jitter_ns: u64, period_ns: f64) -> i128 {
    delay_ns as i128 + 4 * jitter_ns as i128 + (2.0 * period_ns).round() as i128
}

/// A site's engine in step with the source: ticks numbered as the source's, each at the local
/// time the source's schedule (moved by the clock offset) gives it.
pub struct Runner {
    core: EngineCore,
    hz: f64,
    period_ns: f64,
    rx: Receiver<Prepared>,
    path: Arc<PathFigures>,
    counts: Arc<SiteCounts>,
    clock: LocalClock,
    /// (source tick, local time of that tick, ns, the source's tick period on the local clock:
    /// `period / (1 + rate)`, the source's clock running `rate` faster than ours).
    anchor: Option<(u64, i128, f64)>,
    last_tick: Option<u64>,
    state_cycle: u64,
    predicted_upto: u64,
    /// The cycle the site is in ahead of the newest state, and the local time it began.
    ahead: Option<(u64, i128)>,
    /// Start tick of the last announced cycle counted.
    announced: Option<u64>,
    /// The latest frame.
    pub frame: EngineFrame,
}

impl Runner {
    /// A runner at `hz` that has seen no state yet, fed by `rx`.
    fn new(
        core: EngineCore,
        hz: f64,
        rx: Receiver<Prepared>,
        path: Arc<PathFigures>,
        counts: Arc<SiteCounts>,
        clock: LocalClock,
    ) -> Self {
        Runner {
            core,
            hz,
            period_ns: 1e9 / hz,
            rx,
            path,
            counts,
            clock,
            anchor: None,
            last_tick: None,
            state_cycle: 0,
            predicted_upto: 0,
            ahead: None,
            announced: None,
            frame: EngineFrame::default(),
        }
    }

    /// Apply every state ready at `now` (the site's clock; no blocking: the tables were built on
    /// the link worker). The state's source time is moved onto the site's clock with the offset
    /// of now (a state is a path delay old: the offset moves by rate × delay meanwhile, 1 ns at
    /// 50 ppm and 20 ms).
    fn take(&mut self, now: u64) -> Result<(), RemoteError> {
        while let Ok(p) = self.rx.try_recv() {
            let offset = self.path.offset_at(now).unwrap_or(0) as i128;
            let rate = self.path.rate();
            if let Some(pending) = p
                .state
                .pending
                .as_ref()
                .filter(|c| self.announced != Some(c.apply_tick))
            {
                self.announced = Some(pending.apply_tick);
                let late = self.last_tick.is_some_and(|l| l >= pending.apply_tick);
                let n = if late {
                    &self.counts.announced_late
                } else {
                    &self.counts.announced_in_time
                };
                n.fetch_add(1, Ordering::Relaxed);
            }
            self.anchor = Some((
                p.state.tick,
                p.state.source_time_ns as i128 - offset,
                self.period_ns / (1.0 + rate),
            ));
            self.state_cycle = p.state.cycle;
            self.core.apply_prepared(p, self.hz)?;
            self.counts.applied.fetch_add(1, Ordering::Relaxed);
        }
        Ok(())
    }

    /// Local time (ns, the site's clock) source tick `k` is scheduled at; `None` before the first
    /// state.
    pub fn time_of(&self, k: u64) -> Option<i128> {
        self.anchor
            .map(|(a, t, period)| t + ((k as f64 - a as f64) * period).round() as i128)
    }

    /// The site's clock (the host's unless emulated skewed): [`Self::poll`]'s `now` and
    /// [`Self::time_of`] are on it.
    pub fn clock(&self) -> LocalClock {
        self.clock
    }

    /// The next tick's local time (to sleep until), `None` before the first state.
    pub fn next_wake(&self) -> Option<i128> {
        let k = self.last_tick.map_or(self.anchor?.0, |t| t + 1);
        self.time_of(k)
    }

    /// Take ready states and, when a tick is due at `now` (the site's clock, [`Self::clock`]),
    /// step the newest due tick; returns it.
    pub fn poll(&mut self, now: u64) -> Result<Option<u64>, RemoteError> {
        self.take(now)?;
        let Some((a, t, period)) = self.anchor else {
            return Ok(None);
        };
        let since = now as i128 - t;
        let steps = (since as f64 / period).floor() as i128;
        let k = a as i128 + steps;
        if k < 0 || self.last_tick.is_some_and(|l| k as u64 <= l) {
            return Ok(None);
        }
        let k = k as u64;
        self.core.step(k, None, &mut self.frame);
        self.last_tick = Some(k);
        self.count_prediction(k);
        Ok(Some(k))
    }

    /// After stepping tick `k`: count the cycle the site is in once its state is late (the site
    /// started it at the source's cycle start; the state leaves the source then and should be
    /// here one path delay later, give or take the jitter).
    fn count_prediction(&mut self, k: u64) {
        let cycle = self.frame.lungs.iter().map(|l| l.cycle).max().unwrap_or(0) as u64;
        if cycle <= self.state_cycle {
            self.ahead = None;
            return;
        }
        let at = self.time_of(k).unwrap_or(0);
        let began = match self.ahead {
            Some((c, t)) if c == cycle => t,
            _ => {
                self.ahead = Some((cycle, at));
                at
            }
        };
        let late = late_after_ns(
            self.path.delay_ns.load(Ordering::Relaxed),
            self.path.jitter_ns.load(Ordering::Relaxed),
            self.period_ns,
        );
        if cycle > self.predicted_upto && at - began >= late {
            self.predicted_upto = cycle;
            self.counts.predicted_cycles.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// The last source tick stepped.
    pub fn last_tick(&self) -> Option<u64> {
        self.last_tick
    }

    /// The engine.
    pub fn core(&self) -> &EngineCore {
        &self.core
    }
}

/// Watch the relay's presence (a site that takes its clock from the relay): present, or lost
/// (counted).
fn relay_presence(
    session: &zenoh::Session,
    keys: &Keys,
    path: &Arc<PathFigures>,
) -> Result<zenoh::pubsub::Subscriber<()>, RemoteError> {
    let p = path.clone();
    session
        .liveliness()
        .declare_subscriber(keys.relay_presence())
        .history(true)
        .callback(move |s| match s.kind() {
            zenoh::sample::SampleKind::Put => {
                p.relay_present.store(true, Ordering::Relaxed);
            }
            zenoh::sample::SampleKind::Delete => {
                p.relay_present.store(false, Ordering::Relaxed);
                p.relay_lost.fetch_add(1, Ordering::Relaxed);
            }
        })
        .wait()
        .map_err(zerr("declare the relay presence subscriber"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use engine::runtime::remote::StateStamp;

    /// A site fed a 30 breaths/min source's states (one at each 2 s cycle start) on a simulated
    /// clock: cycle 1's state arrives 1 ms after its start (on time), cycle 2's ten ticks late,
    /// cycle 3's never (lost). Only the late and the lost cycles count as predicted, once each.
    #[test]
    fn only_cycles_whose_state_is_late_or_lost_count_as_predicted() {
        let (scene, mut source) = crate::harness::harness_core(Some(30.0)).unwrap();
        let hz = scene.engine.tick_hz;
        let period = 1e9 / hz;
        let mut site_core = source.clone();
        site_core.follow_remote();
        let (tx, rx) = sync_channel::<Prepared>(8);
        let counts = Arc::new(SiteCounts::default());
        let mut runner = Runner::new(
            site_core,
            hz,
            rx,
            Arc::new(PathFigures::default()),
            counts.clone(),
            LocalClock::default(),
        );
        let t0 = 1_000_000_000u64;
        let time = |k: u64| t0 + (k as f64 * period).round() as u64;
        let mut cache = BreathCache::default();
        let mut frame = EngineFrame::default();
        let mut starts: Vec<u64> = Vec::new();
        // (delivery time, state) for each cycle start.
        let mut queue: Vec<(u64, Prepared)> = Vec::new();
        let ticks = 4 * 120;
        for k in 0..ticks {
            source.step(k, None, &mut frame);
            let now: Vec<u64> = source.cycle_starts().collect();
            if now == starts {
                continue;
            }
            starts = now;
            let stamp = StateStamp {
                source: 1,
                epoch: 1,
                sequence: queue.len() as u64,
                tick_hz: hz,
                source_time_ns: time(k),
            };
            let state = source.control_state(k, stamp, &[]).unwrap();
            let cycle = state.cycle;
            let deliver = match cycle {
                0 | 1 => time(k) + 1_000_000,
                2 => time(k + 10),
                _ => continue,
            };
            queue.push((deliver, Prepared::of(state, &mut cache).unwrap()));
        }
        assert_eq!(queue.len(), 3, "states of cycles 0, 1 and 2 (3 is lost)");
        let mut now = t0;
        while now < time(ticks) {
            while queue.first().is_some_and(|(at, _)| *at <= now) {
                tx.send(queue.remove(0).1).unwrap();
            }
            runner.poll(now).unwrap();
            now += 1_000_000;
        }
        assert_eq!(runner.last_tick(), Some(ticks - 1));
        assert_eq!(counts.applied.load(Ordering::Relaxed), 3);
        assert_eq!(counts.predicted_cycles.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn a_states_order_takes_new_ones_counts_repeats_and_refuses_a_leap() {
        assert!(matches!(state_order(None, (1, 1 << 62)), StateOrder::New));
        assert!(matches!(state_order(Some((1, 5)), (1, 6)), StateOrder::New));
        assert!(matches!(
            state_order(Some((1, 5)), (1, 5)),
            StateOrder::Repeated
        ));
        assert!(matches!(
            state_order(Some((1, 5)), (1, 4)),
            StateOrder::Repeated
        ));
        assert!(matches!(state_order(Some((1, 5)), (2, 0)), StateOrder::New));
        assert!(matches!(
            state_order(Some((1, 5)), (1, 1 << 62)),
            StateOrder::Leap(w) if w.contains("leap")
        ));
        assert!(matches!(
            state_order(Some((1, 5)), (1, 5 + MAX_SEQUENCE_LEAP)),
            StateOrder::New
        ));
    }

    #[test]
    fn the_lateness_allowance_is_delay_four_jitters_and_two_ticks() {
        assert_eq!(late_after_ns(0, 0, 16_666_666.7), 33_333_333);
        assert_eq!(
            late_after_ns(20_000_000, 5_000_000, 16_666_666.7),
            20_000_000 + 20_000_000 + 33_333_333
        );
    }

    /// A site whose clock runs 200 ppm fast (its offset to the source falls at dθ/dt =
    /// −r / (1 + r)): a state anchors the source's tick at its source time minus the offset of
    /// that moment, and the source's later ticks come a period / (1 + rate) apart on the site's
    /// clock — 10 s of ticks 2 ms longer than on the source's, not the 60 Hz period itself.
    #[test]
    fn with_a_fitted_rate_the_sources_ticks_are_spaced_on_the_sites_clock() {
        let (scene, mut source) = crate::harness::harness_core(Some(12.0)).unwrap();
        let hz = scene.engine.tick_hz;
        let mut site_core = source.clone();
        site_core.follow_remote();
        let (tx, rx) = sync_channel::<Prepared>(8);
        let path = Arc::new(PathFigures::default());
        let rate: f64 = -200e-6 / (1.0 + 200e-6);
        let (t0, theta) = (5_000_000_000u64, -3_000_000i64);
        path.offset_ns.store(theta, Ordering::Relaxed);
        path.offset_at_ns.store(t0, Ordering::Relaxed);
        path.rate_bits.store(rate.to_bits(), Ordering::Relaxed);
        path.have_offset.store(true, Ordering::Relaxed);
        let mut runner = Runner::new(
            site_core,
            hz,
            rx,
            path.clone(),
            Arc::new(SiteCounts::default()),
            LocalClock::default(),
        );
        let mut frame = EngineFrame::default();
        source.step(0, None, &mut frame);
        let stamp = StateStamp {
            source: 1,
            epoch: 1,
            sequence: 0,
            tick_hz: hz,
            source_time_ns: 20_000_000_000,
        };
        let state = source.control_state(0, stamp, &[]).unwrap();
        tx.send(Prepared::of(state, &mut BreathCache::default()).unwrap())
            .unwrap();
        // Taken 10 s after the offset's time: the offset moved by rate × 10 s = −2 ms.
        let now = t0 + 10_000_000_000;
        assert_eq!(path.offset_at(now), Some(theta - 2_000_000 + 400));
        runner.poll(now).unwrap();
        let anchor = 20_000_000_000i128 - path.offset_at(now).unwrap() as i128;
        assert_eq!(runner.time_of(0), Some(anchor));
        let ticks = (10.0 * hz) as u64;
        let spaced = runner.time_of(ticks).unwrap() - anchor;
        let want = 10e9 * (1.0 + 200e-6);
        assert!(
            (spaced as f64 - want).abs() < 2.0,
            "{spaced} against {want}"
        );
        // No rate: the source's period itself.
        path.rate_bits.store(0f64.to_bits(), Ordering::Relaxed);
        assert_eq!(path.offset_at(now), Some(theta));
    }
}
