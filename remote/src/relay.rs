//! The time relay beside a Zenoh router: clock sync that does not load the source.
//!
//! Peer to peer each site probes the source ([`crate::clock`]), so the source answers every
//! site's every probe and its cost grows with the sites. Through a router the relay runs in the
//! router's process (`lungdyn remote router`, or the harness's router): it alone probes the source
//! (as a site does) and keeps its own offset θ_rs = source clock − relay clock; it answers the
//! sites' probes (on [`crate::Keys::relay_probe`]) with its receive and send stamps moved into the
//! source's time, `t1 + θ_rs` and `t2 + θ_rs`. A site's NTP estimate on such a reply is then
//! θ_sr + θ_rs = source clock − site clock, with no change to the site's estimator or the wire
//! format: its offset to the relay plus the relay's offset to the source.
//!
//! **Error budget**: the two estimates' errors add. Each is the mean over the quickest half of the
//! last 10 s of probes of half the path's asymmetry ([`crate::clock`]); under 20 ± 5 ms each way
//! on both legs the harness measured 0.16 ms on one leg; independent errors add as √2 of one leg
//! in the mean, at worst twice. The clocks' rate difference: a mean over the last 10 s of probes
//! trails a drifting offset by rate × ≈ 5 s (50 ppm: 0.25 ms), the relay's and then the site's
//! mean over the relay's replies — ≈ 0.5 ms at 50 ppm between machines without a rate estimate.
//! Both estimators fit the rate ([`crate::clock`]) and extrapolate their offsets to the moment
//! they are used, the relay's answers carrying its offset of that moment; what is left is the
//! fitted rate's error × ≈ 5 s per leg (its standard error is at most 5 ppm when applied: ≤ 25
//! µs a leg; measured with an emulated skew, `lungdyn remote harness --skew-ppm`, docs/REMOTE.md).
//!
//! Why not Zenoh's timestamps: a router stamps a sample with its hybrid logical clock on the way
//! through, which gives every site the same *order*, but a single stamp of a one-way trip is
//! offset + delay together; separating them needs a round trip with both ends' stamps (the four
//! stamps of a probe), which a stock router does not answer. Hence a relay session beside it.
//!
//! The relay answers nothing before its first [`MIN_REPLIES`] replies from the source (its first
//! [`BURST`] probes go every [`BURST_MS`]); a site's probes then go unanswered (counted here) and
//! the site waits, as it waits for the source peer to peer.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use control_state::{decode, encode_to_vec, Packet};
use zenoh::Wait;

use crate::clock::{DelayEstimator, LocalClock, ProbeStamps};
use crate::link::{self, Impairment, LinkIn};
use crate::measure::{cpu_s, Who};
use crate::site::{PathFigures, Prober};
use crate::{zerr, Keys, RemoteError};

/// The relay's first probes to the source go this often (ms, or its interval if shorter) ...
pub const BURST_MS: u64 = 20;
/// ... this many of them: a sound offset within a second of starting, whatever the interval.
pub const BURST: u64 = 16;
/// The relay answers the sites once it has this many replies from the source: each reply a site
/// takes carries the relay's offset of that moment and stays in the site's 10 s window, so an
/// offset from one or two probes (the first ones through a fresh route are the slowest) would
/// skew the sites' estimates for 10 s (measured: 2 ms of phase at 3 of 10 sites before this).
pub const MIN_REPLIES: u64 = 8;

/// What the relay did.
#[derive(Debug, Default)]
pub struct RelayCounts {
    /// Probes the relay sent to the source.
    pub probes_to_source: AtomicU64,
    /// The source's replies taken.
    pub source_replies: AtomicU64,
    /// Sites' probes answered (in the source's time).
    pub answered: AtomicU64,
    /// Sites' probes left unanswered: they came before the relay had [`MIN_REPLIES`] replies from
    /// the source.
    pub unanswered: AtomicU64,
    /// Payload bytes of the replies sent to sites.
    pub reply_bytes: AtomicU64,
    /// Packets refused (bad bytes, a packet that is not a probe or a reply to the relay).
    pub refused: AtomicU64,
    /// CPU time of the relay's link worker (it answers every probe), ns, as of its last packet.
    pub worker_cpu_ns: AtomicU64,
    /// CPU time of the relay's prober thread, ns, as of its last probe.
    pub prober_cpu_ns: AtomicU64,
}

impl RelayCounts {
    /// CPU seconds of the relay's own two threads (Zenoh's runtime threads, which route its
    /// packets, are the hosting process's and not included).
    pub fn threads_cpu_s(&self) -> f64 {
        (self.worker_cpu_ns.load(Ordering::Relaxed) + self.prober_cpu_ns.load(Ordering::Relaxed))
            as f64
            / 1e9
    }
}

/// The stamps of a reply to a site's probe received at `at` and answered at `now` (the relay's
/// clock), moved into the source's time by `offset_ns` (source − relay).
pub fn in_source_time(at: u64, now: u64, offset_ns: i64) -> (u64, u64) {
    let shift = |t: u64| (t as i128 + offset_ns as i128).clamp(0, u64::MAX as i128) as u64;
    (shift(at), shift(now))
}

/// A time relay on a session (the router's).
pub struct Relay {
    /// The relay's id (the source's replies are addressed to it).
    pub id: u64,
    _probes: zenoh::pubsub::Subscriber<()>,
    _replies: zenoh::pubsub::Subscriber<()>,
    _warm: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
    _link: LinkIn,
    stop: Arc<AtomicBool>,
    /// Counters.
    pub counts: Arc<RelayCounts>,
    /// The relay's path to the source: delay, jitter, offset (source − relay), rate.
    pub path: Arc<PathFigures>,
    /// The relay's clock (the host's unless emulated skewed).
    pub clock: LocalClock,
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl Relay {
    /// Run a relay `id` for `keys`' room on `session` (the router's): probe the source every
    /// `probe_ms`, answer the sites' probes; incoming packets pass `imp`.
    pub fn open(
        session: &zenoh::Session,
        keys: &Keys,
        id: u64,
        imp: Impairment,
        probe_ms: u64,
        guard: crate::seal::Guard,
    ) -> Result<Self, RemoteError> {
        let counts = Arc::new(RelayCounts::default());
        let path = Arc::new(PathFigures::default());
        let (c, p, s2, k2) = (counts.clone(), path.clone(), session.clone(), keys.clone());
        let mut estimator = if imp.no_rate {
            DelayEstimator::without_rate()
        } else {
            DelayEstimator::default()
        };
        let (g2, mut inbox) = (guard.clone(), guard.inbox());
        let link = link::start(&format!("remote-relay-{id:x}"), imp, move |bytes, at| {
            use crate::seal::Kind;
            let Some((_, payload)) = inbox.open(&bytes, at, &[Kind::Reply, Kind::Probe]) else {
                c.refused.fetch_add(1, Ordering::Relaxed);
                return;
            };
            match decode(payload) {
                Ok(ref packet @ Packet::ProbeReply { to, .. }) if to == id => {
                    let Some((from, stamps)) = ProbeStamps::of_reply(packet, id, at) else {
                        return;
                    };
                    if p.take(&mut estimator, stamps, from) {
                        c.source_replies.fetch_add(1, Ordering::Relaxed);
                    } else {
                        c.refused.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Ok(Packet::Probe {
                    from,
                    id: pid,
                    t0_ns,
                    ..
                }) if from != id => {
                    if c.source_replies.load(Ordering::Relaxed) < MIN_REPLIES {
                        c.unanswered.fetch_add(1, Ordering::Relaxed);
                    } else {
                        // The offset moved to this moment with the fitted rate: a site's
                        // estimate on the reply is then as current as the relay's.
                        let (t1_ns, t2_ns) =
                            in_source_time(at, imp.clock.now(), p.offset_at(at).unwrap_or(0));
                        let reply = Packet::ProbeReply {
                            from: id,
                            to: from,
                            id: pid,
                            t0_ns,
                            t1_ns,
                            t2_ns,
                        };
                        if let Ok(b) = encode_to_vec(&reply) {
                            let b = g2.wrap(Kind::Reply, b);
                            let n = b.len() as u64;
                            if s2.put(k2.reply(from), b).wait().is_ok() {
                                c.answered.fetch_add(1, Ordering::Relaxed);
                                c.reply_bytes.fetch_add(n, Ordering::Relaxed);
                            }
                        }
                    }
                }
                Ok(_) | Err(_) => {
                    c.refused.fetch_add(1, Ordering::Relaxed);
                }
            }
            c.worker_cpu_ns
                .store((cpu_s(Who::Thread) * 1e9) as u64, Ordering::Relaxed);
        });
        let l1 = link.clone();
        let probes = session
            .declare_subscriber(keys.relay_probe())
            .callback(move |s| l1.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the relay's probe subscriber"))?;
        let l2 = link.clone();
        let replies = session
            .declare_subscriber(keys.reply(id))
            .callback(move |s| l2.push(s.payload().to_bytes().into_owned()))
            .wait()
            .map_err(zerr("declare the relay's reply subscriber"))?;
        // The sites' warm-up packets: taken and dropped on Zenoh's thread (they only wake it).
        let warm = session
            .declare_subscriber(keys.relay_warm())
            .callback(|_| {})
            .wait()
            .map_err(zerr("declare the relay's warm-up subscriber"))?;
        let token = session
            .liveliness()
            .declare_token(keys.relay_presence())
            .wait()
            .map_err(zerr("declare the relay's liveliness token"))?;
        let stop = Arc::new(AtomicBool::new(false));
        let c3 = counts.clone();
        Prober {
            name: format!("remote-relay-probe-{id:x}"),
            guard,
            session: session.clone(),
            key: keys.probe(),
            warm: keys.warm(),
            id,
            clock: imp.clock,
        }
        .start(
            move |n| {
                if n < BURST {
                    probe_ms.min(BURST_MS)
                } else {
                    probe_ms
                }
            },
            stop.clone(),
            move |sent| {
                if sent {
                    c3.probes_to_source.fetch_add(1, Ordering::Relaxed);
                }
                c3.prober_cpu_ns
                    .store((cpu_s(Who::Thread) * 1e9) as u64, Ordering::Relaxed);
            },
        )
        .map_err(|e| RemoteError::Usage(format!("start the relay's prober: {e}")))?;
        Ok(Self {
            id,
            _probes: probes,
            _replies: replies,
            _warm: warm,
            _token: token,
            _link: link,
            stop,
            counts,
            path,
            clock: imp.clock,
        })
    }

    /// Whether the relay answers the sites' probes: it has [`MIN_REPLIES`] replies from the source.
    pub fn answering(&self) -> bool {
        self.counts.source_replies.load(Ordering::Relaxed) >= MIN_REPLIES
    }

    /// The relay's offset to the source (source − relay) now, ns, once it has one (from the
    /// first reply on; the sites are answered only once it is [`Self::answering`]).
    pub fn offset_ns(&self) -> Option<i64> {
        self.path.offset_at(self.clock.now())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A site 3 ms behind the relay, the relay 1 s behind the source, 2 ms each way between site
    /// and relay: the site's NTP estimate on the relay's reply is the sum, 1.003 s, exactly.
    #[test]
    fn a_reply_in_source_time_gives_the_site_its_offset_to_the_source() {
        let theta_sr: i64 = 3_000_000; // relay − site
        let theta_rs: i64 = 1_000_000_000; // source − relay
        let t0 = 50_000_000_000u64; // site clock
        let at = (t0 as i64 + 2_000_000 + theta_sr) as u64; // relay clock
        let now = at + 40_000;
        let (t1, t2) = in_source_time(at, now, theta_rs);
        let t3 = (now as i64 - theta_sr) as u64 + 2_000_000; // site clock
        let p = ProbeStamps { t0, t1, t2, t3 };
        assert_eq!(p.offset_ns(), theta_sr + theta_rs);
        assert_eq!(p.rtt_ns(), Some(4_000_000));
        // Extremes clamp instead of wrapping.
        assert_eq!(in_source_time(5, 6, -10), (0, 0));
        assert_eq!(
            in_source_time(u64::MAX - 1, u64::MAX, 10),
            (u64::MAX, u64::MAX)
        );
    }
}
