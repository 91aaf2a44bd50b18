//! A live one-dimensional respiratory signal over UDP (`--breathing udp:[BIND:]PORT`, issue 35
//! item 1): a belt, a spirometer or a camera-based tracker's PC sends one sample per datagram.
//!
//! # Wire format (ours: there is no common one for a bare amplitude)
//! One datagram, one sample, UTF-8 text: `UNIT=VALUE`, optionally followed by a newline.
//! `UNIT` is `mm` (chest or abdomen displacement), `ml` (volume) or `au` (arbitrary units);
//! `VALUE` a decimal number. `UNIT=` with no value, or a value that is not finite, is a sample the
//! sender marks invalid: it is sent on flagged invalid, never held silently. Every sample of a
//! stream keeps the unit of the first; a datagram in another unit is refused and counted, as are
//! datagrams that are not one `UNIT=VALUE` line, and datagrams from hosts not allowed.
//!
//! # The tracker's rules
//! Each sample is stamped on arrival (the host's monotonic clock, when the bridge took it from the
//! socket, at most one frame late), so nothing reads ahead of it. The nominal period is the mean of
//! the last 16 arrival intervals (the frame-quantised stamps of a 25 Hz sender alternate 33 and
//! 50 ms), to the millisecond, held until the mean moves by more than a fifth: the engine
//! re-calibrates its follower when the period changes, so a jittering figure would restart it
//! every frame. Until the first sample the block's unit is none (the engine waits). The socket binds 127.0.0.1 unless told otherwise, and senders off
//! loopback are served only when the tracker's allow-list names them (`--igtl-allow`, `[tracker]
//! allow`): the hosts the scene names.

use std::net::{SocketAddr, UdpSocket};

use ipc_types::{signal_status, signal_unit, SignalBlock, SignalWire, MAX_SIGNAL_SAMPLES};

use crate::allow::AllowList;

/// The largest datagram read; a longer one is cut by the kernel and refused as malformed.
const DATAGRAM: usize = 512;
/// Arrival intervals kept for the period.
const INTERVALS: usize = 16;

/// A UDP amplitude stream.
#[derive(Debug)]
pub struct UdpSignal {
    socket: UdpSocket,
    allow: AllowList,
    stream: AmplitudeStream,
    describe: String,
    buf: [u8; DATAGRAM],
    /// What was sent and refused.
    pub counts: StreamCounts,
}

/// What a live amplitude stream sent and refused.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StreamCounts {
    /// Samples sent in frames.
    pub sent: u64,
    /// Of those, flagged invalid by their sender.
    pub invalid: u64,
    /// Frames whose block was full, the rest left for the next frame.
    pub full_blocks: u64,
    /// Datagrams from hosts not allowed.
    pub refused_senders: u64,
    /// Messages that were not one sample in the stream's unit.
    pub malformed: u64,
}

/// A live amplitude stream's unit (held to its first sample's) and period (from its arrivals),
/// shared by the UDP and OpenIGTLink streams.
#[derive(Debug, Default)]
pub(crate) struct AmplitudeStream {
    unit: Option<u32>,
    intervals: [u64; INTERVALS],
    n_intervals: usize,
    period_ns: u64,
    last_arrival: Option<u64>,
}

impl AmplitudeStream {
    /// A sample in `unit` that arrived at `t_ns` (`value` `None`: its sender marked it invalid)
    /// into `block`, counted; false when its unit is not the stream's (refused, counted
    /// malformed). The caller checks that the block has room.
    pub(crate) fn take(
        &mut self,
        block: &mut SignalBlock,
        counts: &mut StreamCounts,
        t_ns: u64,
        unit: u32,
        value: Option<f64>,
    ) -> bool {
        if *self.unit.get_or_insert(unit) != unit {
            counts.malformed += 1;
            return false;
        }
        self.arrived(t_ns);
        push_sample(block, t_ns, value.unwrap_or(0.0), value.is_some());
        counts.invalid += u64::from(value.is_none());
        counts.sent += 1;
        true
    }

    /// The block's unit and period after a frame's samples (`counts`: a full block is counted).
    pub(crate) fn finish(&self, block: &mut SignalBlock, counts: &mut StreamCounts) {
        if block.count as usize == MAX_SIGNAL_SAMPLES {
            counts.full_blocks += 1;
        }
        block.unit = self.unit.unwrap_or(signal_unit::NONE);
        block.period_ns = self.period_ns;
    }

    fn arrived(&mut self, now_ns: u64) {
        if let Some(last) = self.last_arrival {
            let d = now_ns.saturating_sub(last);
            // Samples taken in one frame arrived together: not an interval of the sender's.
            if d > 0 {
                self.intervals[self.n_intervals % INTERVALS] = d;
                self.n_intervals += 1;
            }
        }
        self.last_arrival = Some(now_ns);
        let n = self.n_intervals.min(INTERVALS);
        if n >= 8 {
            let mean = self.intervals[..n].iter().sum::<u64>() / n as u64;
            let held = self.period_ns;
            if held == 0 || mean.abs_diff(held) * 5 > held {
                self.period_ns = (mean + 500_000) / 1_000_000 * 1_000_000;
            }
        }
    }
}

/// Append a sample to `block` (`valid`: its value is used, else 0 is sent flagged invalid);
/// false when the block is full.
pub(crate) fn push_sample(block: &mut SignalBlock, t_ns: u64, value: f64, valid: bool) -> bool {
    let i = block.count as usize;
    if i >= MAX_SIGNAL_SAMPLES {
        return false;
    }
    block.samples[i] = SignalWire {
        t_ns,
        value: if valid { value } else { 0.0 },
    };
    if valid {
        block.valid_mask |= 1 << i;
    }
    block.count += 1;
    true
}

/// Parse the `udp:` spec's rest, `[BIND:]PORT` (an IPv6 bind in brackets).
pub fn parse_bind(rest: &str) -> Result<SocketAddr, String> {
    let rest = rest.trim();
    let with_bind = if rest.parse::<u16>().is_ok() {
        format!("127.0.0.1:{rest}")
    } else {
        rest.to_string()
    };
    with_bind.parse::<SocketAddr>().map_err(|_| {
        format!(
            "--breathing udp:{rest}: use udp:PORT (127.0.0.1) or udp:ADDRESS:PORT (udp:0.0.0.0:5005, \
             udp:[::]:5005), a port 0–65535"
        )
    })
}

impl UdpSignal {
    /// Bind `addr` (non-blocking); senders off loopback must be in `allow`.
    pub fn bind(addr: SocketAddr, allow: AllowList) -> Result<Self, String> {
        let socket = UdpSocket::bind(addr).map_err(|e| {
            format!(
                "--breathing udp:{addr}: cannot listen there ({e}); is another program on that \
                 port, or is the address not this machine's?"
            )
        })?;
        socket
            .set_nonblocking(true)
            .map_err(|e| format!("--breathing udp:{addr}: {e}"))?;
        let local = socket.local_addr().unwrap_or(addr);
        Ok(Self {
            describe: format!(
                "UDP amplitude stream on {local} (one `mm=VALUE`, `ml=VALUE` or `au=VALUE` per \
                 datagram; senders: {})",
                allow.describe()
            ),
            socket,
            allow,
            stream: AmplitudeStream::default(),
            buf: [0; DATAGRAM],
            counts: StreamCounts::default(),
        })
    }

    /// Where it listens.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.socket.local_addr().ok()
    }

    /// What it reads, for messages.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// Take the datagrams waiting by `now_ns` into `block` (at most [`MAX_SIGNAL_SAMPLES`]; the
    /// rest wait for the next frame), each stamped `now_ns`, its arrival as the bridge saw it.
    pub fn fill(&mut self, now_ns: u64, block: &mut SignalBlock) {
        *block = SignalBlock {
            status: signal_status::CONFIGURED,
            ..Default::default()
        };
        while (block.count as usize) < MAX_SIGNAL_SAMPLES {
            let (n, from) = match self.socket.recv_from(&mut self.buf) {
                Ok(got) => got,
                // Nothing waiting (or a transient error: the next frame reads again).
                Err(_) => break,
            };
            if !self.allow.allows(from.ip()) {
                self.counts.refused_senders += 1;
                continue;
            }
            let Some((unit, value)) = parse_datagram(&self.buf[..n]) else {
                self.counts.malformed += 1;
                continue;
            };
            self.stream
                .take(block, &mut self.counts, now_ns, unit, value);
        }
        self.stream.finish(block, &mut self.counts);
    }
}

/// `UNIT=VALUE` (an optional trailing newline): the unit, and the value when it is a finite
/// number (`None`: the sender marks the sample invalid). `None` for anything else.
pub(crate) fn parse_datagram(bytes: &[u8]) -> Option<(u32, Option<f64>)> {
    let text = std::str::from_utf8(bytes).ok()?;
    let line = text
        .strip_suffix("\r\n")
        .or_else(|| text.strip_suffix('\n'))
        .unwrap_or(text);
    if line.contains(['\n', '\r']) {
        return None;
    }
    let (unit, value) = line.split_once('=')?;
    let unit = match unit.trim() {
        "mm" => signal_unit::MM,
        "ml" => signal_unit::ML,
        "au" => signal_unit::ARBITRARY,
        _ => return None,
    };
    let value = value.trim();
    if value.is_empty() {
        return Some((unit, None));
    }
    let v = value.parse::<f64>().ok()?;
    Some((unit, v.is_finite().then_some(v)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn stream() -> (UdpSignal, UdpSocket) {
        let s = UdpSignal::bind("127.0.0.1:0".parse().unwrap(), AllowList::default()).unwrap();
        let sender = UdpSocket::bind("127.0.0.1:0").unwrap();
        sender.connect(s.local_addr().unwrap()).unwrap();
        (s, sender)
    }

    /// Fill until `n` samples came (the datagrams are on loopback: they arrive at once).
    fn take(s: &mut UdpSignal, now: u64) -> SignalBlock {
        let mut b = SignalBlock::default();
        for _ in 0..200 {
            s.fill(now, &mut b);
            if b.count > 0 {
                return b;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        b
    }

    #[test]
    fn samples_are_stamped_on_arrival_flagged_when_invalid_and_junk_is_counted() {
        let (mut s, tx) = stream();
        for d in [
            "mm=12.5\n",
            "mm=",
            "mm=nan",
            "ml=400",     // another unit: refused
            "mm=1\nmm=2", // two samples: refused
            "cmH2O=3",    // not a unit
            "mm=twelve",  // not a number
        ] {
            tx.send(d.as_bytes()).unwrap();
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
        let b = take(&mut s, 5_000);
        assert_eq!(b.count, 3, "{b:?}");
        assert_eq!(b.unit, signal_unit::MM);
        assert_eq!(b.valid_mask, 0b001);
        assert_eq!(b.samples[0].value, 12.5);
        assert!(b.samples[..3]
            .iter()
            .all(|w| w.t_ns == 5_000 && w.value.is_finite()));
        assert_eq!(b.status, signal_status::CONFIGURED);
        assert_eq!(
            (s.counts.sent, s.counts.invalid, s.counts.malformed),
            (3, 2, 4)
        );
        // Nothing more waiting: an empty block, still configured.
        let mut e = SignalBlock::default();
        s.fill(6_000, &mut e);
        assert_eq!((e.count, e.status), (0, signal_status::CONFIGURED));
        // Before any sample the unit is none: the engine waits.
        let (mut fresh, _tx) = stream();
        fresh.fill(1, &mut e);
        assert_eq!((e.unit, e.period_ns), (signal_unit::NONE, 0));
    }

    #[test]
    fn the_period_is_the_mean_arrival_interval_held_while_it_holds() {
        let (mut s, tx) = stream();
        let mut b = SignalBlock::default();
        for k in 0..10u64 {
            tx.send(b"au=0.5").unwrap();
            std::thread::sleep(std::time::Duration::from_millis(2));
            // One frame per sample, 40 ms apart on the bridge's clock (one late at 55 ms).
            let t = k * 40_000_000 + if k == 5 { 15_000_000 } else { 0 };
            for _ in 0..100 {
                s.fill(t, &mut b);
                if b.count == 1 {
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            assert_eq!(b.count, 1, "sample {k}");
        }
        assert_eq!(b.period_ns, 40_000_000);
        assert_eq!(b.unit, signal_unit::ARBITRARY);
        // Frame-quantised arrivals of a 25 Hz sender (33 and 50 ms alternating) keep it.
        let mut t = 10 * 40_000_000;
        for k in 0..16u64 {
            t += if k % 2 == 0 { 33_333_333 } else { 50_000_000 };
            tx.send(b"au=0.5").unwrap();
            std::thread::sleep(std::time::Duration::from_millis(2));
            for _ in 0..100 {
                s.fill(t, &mut b);
                if b.count == 1 {
                    break;
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            assert_eq!(b.period_ns, 40_000_000, "arrival {k}");
        }
    }

    #[test]
    fn a_sender_off_the_allow_list_is_refused_and_counted() {
        // Listen on every address, allow only a network this machine is not on; send from this
        // machine's own non-loopback address when it has one (else only loopback is tried).
        let own = UdpSocket::bind("0.0.0.0:0")
            .and_then(|u| u.connect("192.0.2.1:9").map(|()| u))
            .and_then(|u| u.local_addr())
            .map(|a| a.ip())
            .ok()
            .filter(|ip| !ip.is_loopback() && !ip.is_unspecified());
        let Some(ip) = own else {
            eprintln!("no non-loopback address here: the refusal is not tried");
            return;
        };
        // A documentation network this machine is not on.
        let net = ["198.51.100.0/24", "203.0.113.0/24"]
            .into_iter()
            .find(|n| !n.parse::<ipnet::IpNet>().unwrap().contains(&ip))
            .unwrap();
        let allow = AllowList::parse_as(&[net.into()], "--igtl-allow").unwrap();
        let mut s = UdpSignal::bind("0.0.0.0:0".parse().unwrap(), allow).unwrap();
        let port = s.local_addr().unwrap().port();
        let tx = UdpSocket::bind((ip, 0)).unwrap();
        tx.send_to(b"mm=1", (ip, port)).unwrap();
        let loop_tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        loop_tx.send_to(b"mm=2", ("127.0.0.1", port)).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        let b = take(&mut s, 1);
        assert_eq!(
            (b.count, b.samples[0].value),
            (1, 2.0),
            "only loopback's sample"
        );
        assert_eq!(s.counts.refused_senders, 1);
    }

    #[test]
    fn the_bind_spec_takes_a_port_or_an_address_and_port() {
        assert_eq!(
            parse_bind("5005").unwrap(),
            "127.0.0.1:5005".parse().unwrap()
        );
        assert_eq!(
            parse_bind("0.0.0.0:5005").unwrap(),
            "0.0.0.0:5005".parse().unwrap()
        );
        assert_eq!(
            parse_bind("[::]:5005").unwrap(),
            "[::]:5005".parse().unwrap()
        );
        for bad in ["", "70000", "host:5005", "5005:", "::5005"] {
            let e = parse_bind(bad).unwrap_err();
            assert!(e.contains("udp:PORT"), "{bad}: {e}");
        }
    }

    proptest! {
        #[test]
        fn any_datagram_parses_to_a_finite_value_or_nothing(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            if let Some((_, Some(v))) = parse_datagram(&bytes) {
                prop_assert!(v.is_finite());
            }
        }
    }
}
