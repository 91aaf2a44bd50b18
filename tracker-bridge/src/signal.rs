//! The respiratory signal (issue 35), a source beside the tracker's: its samples go out in each
//! [`TrackerFrame`]'s [`SignalBlock`] — those that arrived since the previous frame, oldest first,
//! stamped with this host's monotonic clock, invalid ones flagged (value 0), never dropped in
//! silence and never read ahead of the sample clock.
//!
//! | `--breathing` | what it is |
//! |---|---|
//! | `trace:FILE` | a Varian RPM `.vxp`, a CSV trace (`time_s`, `amplitude_mm`, …) or a ventilator recording (as `lungdyn pv recording` reads it; its flow integrated), replayed at its own rate with its own times and valid flags from the run's start |
//!
//! A replayed file feeds samples in time like a device: a sample goes out in the first frame at or
//! after its own time on the run's clock. `--breathing-cut-at S --breathing-cut-for S` withhold the
//! samples of that window (a signal loss, to test one), with the block's `CUT` bit set meanwhile.

use std::path::{Path, PathBuf};

use ipc_types::{signal_status, signal_unit, SignalBlock};
use lung_model::breathing::check::read_trace_or_recording;
use lung_model::breathing::follow::Calibration;
use lung_model::breathing::trace::SignalUnit;
use lung_model::input::ReadLimits;

/// Which signal source, parsed from `--breathing` (or the scene's `[breathing] signal`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SignalSpec {
    /// No signal.
    None,
    /// A file replayed at its own rate.
    Trace(PathBuf),
    /// The signal a replayed tracker recording (`--source replay:FILE`) was made with.
    Recorded,
    /// A live amplitude stream, one sample per UDP datagram ([`crate::signal_udp`]).
    Udp(std::net::SocketAddr),
    /// A tracked tool on the chest, by its name at the source, and the axis it is read along
    /// ([`crate::signal_tool`]).
    Tool(String, crate::signal_tool::AxisChoice),
    /// An amplitude from an OpenIGTLink device, by its name ([`crate::signal_igtl`]).
    Igtl(String),
}

impl SignalSpec {
    /// Parse `trace:FILE`, `udp:[BIND:]PORT` or `recorded`; empty or `none` is no signal.
    pub fn parse(text: &str) -> Result<Self, String> {
        let t = text.trim();
        if t.is_empty() || t.eq_ignore_ascii_case("none") {
            return Ok(SignalSpec::None);
        }
        if t.eq_ignore_ascii_case("recorded") {
            return Ok(SignalSpec::Recorded);
        }
        match t.split_once(':') {
            Some((kind, path)) if kind.eq_ignore_ascii_case("trace") => {
                if path.trim().is_empty() {
                    return Err(format!(
                        "--breathing {text:?}: trace: needs a file (trace:patient.vxp)"
                    ));
                }
                Ok(SignalSpec::Trace(PathBuf::from(path)))
            }
            Some((kind, rest)) if kind.eq_ignore_ascii_case("udp") => {
                crate::signal_udp::parse_bind(rest).map(SignalSpec::Udp)
            }
            Some((kind, name)) if kind.eq_ignore_ascii_case("igtl") => {
                crate::sample::ToolName::new(name.trim())
                    .map(|_| SignalSpec::Igtl(name.trim().to_string()))
                    .map_err(|e| {
                        format!(
                            "--breathing {text:?}: igtl: needs the sending device's name (igtl:Resp): \
                             {e}"
                        )
                    })
            }
            Some((kind, rest)) if kind.eq_ignore_ascii_case("tool") => {
                use crate::signal_tool::AxisChoice;
                let rest = rest.trim();
                let (name, axis) = match rest.rsplit_once(':') {
                    Some((n, a)) if a.trim().eq_ignore_ascii_case("auto") => {
                        (n.trim(), AxisChoice::Auto)
                    }
                    Some((n, a)) if a.trim().eq_ignore_ascii_case("anterior") => {
                        (n.trim(), AxisChoice::Anterior)
                    }
                    Some((_, a)) => {
                        return Err(format!(
                            "--breathing {text:?}: {a:?} is not an axis; tool:NAME reads the chest \
                             tool along the patient reference's anterior axis, tool:NAME:auto along \
                             the axis it moves on (learnt from its first breaths)"
                        ))
                    }
                    None => (rest, AxisChoice::Anterior),
                };
                crate::sample::ToolName::new(name)
                    .map(|_| SignalSpec::Tool(name.to_string(), axis))
                    .map_err(|e| {
                        format!(
                            "--breathing {text:?}: tool: needs the chest tool's name at the source \
                             (tool:Chest, or tool:Chest:auto): {e}"
                        )
                    })
            }
            _ => Err(format!(
                "--breathing {text:?}: not a signal source; use trace:FILE (a Varian RPM .vxp, a CSV \
                 trace, or a ventilator recording), udp:[BIND:]PORT (a live amplitude stream, one \
                 `mm=VALUE` per datagram), tool:NAME[:auto] (a tracked tool on the chest, along the \
                 patient reference's anterior axis, or the axis it moves on), igtl:NAME (an amplitude from the OpenIGTLink device NAME: \
                 SENSOR in mm, ml or no unit, or STRING `mm=VALUE`), recorded (the signal a --source replay:FILE recording \
                 carries) or none"
            )),
        }
    }
}

/// What the signal source did, for the bridge's statistics.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SignalCounts {
    /// Samples sent in frames.
    pub sent: u64,
    /// Of those, flagged invalid.
    pub invalid: u64,
    /// Withheld by `--breathing-cut-at/-for`.
    pub cut: u64,
    /// Frames whose block was full, the rest left for the next frame.
    pub full_blocks: u64,
    /// A live stream's datagrams from hosts not allowed.
    pub refused_senders: u64,
    /// A live stream's datagrams that were not one sample in the stream's unit.
    pub malformed: u64,
    /// A chest tool's valid measurements not sent while its axis was learnt (`tool:NAME:auto`).
    pub learning: u64,
}

/// The bridge's respiratory signal source.
#[derive(Debug)]
pub enum SignalSource {
    /// A file replayed at its own rate.
    Trace(TraceReplay),
    /// A live UDP amplitude stream.
    Udp(crate::signal_udp::UdpSignal),
    /// A tracked tool on the chest.
    Tool(crate::signal_tool::ToolSignal),
    /// An amplitude over OpenIGTLink.
    Igtl(crate::signal_igtl::IgtlSignal),
}

impl SignalSource {
    /// The samples due by `now_ns` into `block`; `tools` is the frame's view of the chest tool and
    /// the patient reference (read by a tool source only).
    pub fn fill(
        &mut self,
        now_ns: u64,
        tools: &crate::signal_tool::ToolView,
        block: &mut SignalBlock,
    ) {
        match self {
            SignalSource::Trace(t) => t.fill(now_ns, block),
            SignalSource::Udp(u) => u.fill(now_ns, block),
            SignalSource::Tool(t) => t.fill(now_ns, tools, block),
            SignalSource::Igtl(s) => s.fill(block),
        }
    }

    /// What it sent and withheld.
    pub fn counts(&self) -> SignalCounts {
        match self {
            SignalSource::Trace(t) => t.counts,
            SignalSource::Udp(u) => Self::stream_counts(&u.counts),
            SignalSource::Igtl(s) => Self::counts_of_igtl(s),
            SignalSource::Tool(t) => SignalCounts {
                sent: t.sent,
                invalid: t.invalid,
                learning: t.learning,
                ..Default::default()
            },
        }
    }

    fn stream_counts(c: &crate::signal_udp::StreamCounts) -> SignalCounts {
        SignalCounts {
            sent: c.sent,
            invalid: c.invalid,
            cut: 0,
            full_blocks: c.full_blocks,
            refused_senders: c.refused_senders,
            malformed: c.malformed,
            learning: 0,
        }
    }

    /// An OpenIGTLink amplitude's counts.
    pub fn counts_of_igtl(s: &crate::signal_igtl::IgtlSignal) -> SignalCounts {
        Self::stream_counts(&s.counts)
    }

    /// What it reads, for messages.
    pub fn describe(&self) -> &str {
        match self {
            SignalSource::Trace(t) => t.describe(),
            SignalSource::Udp(u) => u.describe(),
            SignalSource::Tool(t) => t.describe(),
            SignalSource::Igtl(s) => s.describe(),
        }
    }
}

impl From<crate::signal_tool::ToolSignal> for SignalSource {
    fn from(t: crate::signal_tool::ToolSignal) -> Self {
        SignalSource::Tool(t)
    }
}

impl From<crate::signal_igtl::IgtlSignal> for SignalSource {
    fn from(s: crate::signal_igtl::IgtlSignal) -> Self {
        SignalSource::Igtl(s)
    }
}

impl From<TraceReplay> for SignalSource {
    fn from(t: TraceReplay) -> Self {
        SignalSource::Trace(t)
    }
}

impl From<crate::signal_udp::UdpSignal> for SignalSource {
    fn from(u: crate::signal_udp::UdpSignal) -> Self {
        SignalSource::Udp(u)
    }
}

/// A file replayed as a live respiratory signal.
#[derive(Debug, Clone)]
pub struct TraceReplay {
    /// `(time since the first sample, ns; value; valid)`.
    samples: Vec<(u64, f64, bool)>,
    unit: u32,
    period_ns: u64,
    start_ns: Option<u64>,
    next: usize,
    cut: Option<(u64, u64)>,
    describe: String,
    /// What was sent and withheld.
    pub counts: SignalCounts,
    warning: Option<String>,
}

/// Why a signal source cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SignalError {
    /// The `--breathing` text or a cut option.
    #[error("{0}")]
    Spec(String),
    /// The file could not be read as a signal.
    #[error("--breathing: {0}")]
    Read(String),
}

/// Move a block's sample times (and a recording's origin) by `by_ns`: a replayed block's times
/// from the recording's clock to this run's, as a replayed sample's capture time is moved.
pub fn shift(b: &mut ipc_types::SignalBlock, by_ns: i128) {
    let moved = |t: u64| (i128::from(t) + by_ns).clamp(1, i128::from(u64::MAX)) as u64;
    let n = (b.count as usize).min(ipc_types::MAX_SIGNAL_SAMPLES);
    for s in &mut b.samples[..n] {
        s.t_ns = moved(s.t_ns);
    }
    if b.origin_ns != 0 {
        b.origin_ns = moved(b.origin_ns);
    }
}

/// A cut's window, checked: it starts at 0 s or later and lasts more than 0 s, within a week.
pub fn check_cut(at_s: f64, for_s: f64) -> Result<(), SignalError> {
    if !(at_s.is_finite()
        && at_s >= 0.0
        && for_s.is_finite()
        && for_s > 0.0
        && at_s + for_s <= 604_800.0)
    {
        return Err(SignalError::Spec(format!(
            "--breathing-cut-at {at_s} --breathing-cut-for {for_s}: a cut starts at 0 s or later and \
             lasts more than 0 s (within a week)"
        )));
    }
    Ok(())
}

impl TraceReplay {
    /// Read `path` (within the input limits a table has) as a live signal.
    pub fn open(path: &Path) -> Result<Self, SignalError> {
        let bytes = lung_model::input::read_bounded(path, ReadLimits::TABLE)
            .map_err(|e| SignalError::Read(e.to_string()))?;
        // The tidal volume only shapes the hindsight volume this reader also makes; the engine
        // calibrates the live samples itself.
        let read = read_trace_or_recording(path, &bytes, Calibration::Auto { tidal_ml: 500.0 })
            .map_err(|e| SignalError::Read(e.to_string()))?;
        let samples = &read.trace.samples;
        let first = samples.first().map_or(0, |s| s.t_ns);
        let unit = match read.unit {
            SignalUnit::Mm => signal_unit::MM,
            SignalUnit::Ml => signal_unit::ML,
            SignalUnit::Arbitrary => signal_unit::ARBITRARY,
        };
        let rate = read.trace.rate_hz;
        Ok(Self {
            samples: samples
                .iter()
                .map(|s| (s.t_ns - first, s.value, s.valid && s.value.is_finite()))
                .collect(),
            unit,
            period_ns: if rate.is_finite() && rate > 0.0 {
                (1e9 / rate).round() as u64
            } else {
                0
            },
            start_ns: None,
            next: 0,
            cut: None,
            describe: format!(
                "{} from {} ({:.1} Hz, {:.0} s)",
                read.kind,
                path.display(),
                rate,
                samples.last().map_or(0, |s| s.t_ns - first) as f64 * 1e-9
            ),
            counts: SignalCounts::default(),
            warning: read.trace.clipped.as_ref().map(|c| c.describe()),
        })
    }

    /// What looks wrong in the file though it can be followed (a signal clipped by its sensor's
    /// range), for the person starting the run.
    pub fn warning(&self) -> Option<&str> {
        self.warning.as_deref()
    }

    /// Withhold the samples from `at_s` to `at_s + for_s` after the start (a loss, to test one).
    pub fn cut(&mut self, at_s: f64, for_s: f64) -> Result<(), SignalError> {
        check_cut(at_s, for_s)?;
        self.cut = Some(((at_s * 1e9) as u64, ((at_s + for_s) * 1e9) as u64));
        Ok(())
    }

    /// What it replays, for messages.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// Put the samples due by `now_ns` into `block` (at most [`MAX_SIGNAL_SAMPLES`]; the rest wait
    /// for the next frame). The first call starts the replay's clock.
    pub fn fill(&mut self, now_ns: u64, block: &mut SignalBlock) {
        let start = *self.start_ns.get_or_insert(now_ns);
        *block = SignalBlock {
            unit: self.unit,
            status: signal_status::CONFIGURED,
            period_ns: self.period_ns,
            origin_ns: start,
            ..Default::default()
        };
        let since = now_ns.saturating_sub(start);
        let in_cut = |t: u64, cut: Option<(u64, u64)>| cut.is_some_and(|(a, b)| t >= a && t < b);
        while let Some(&(t, value, valid)) = self.samples.get(self.next) {
            if t > since {
                break;
            }
            if in_cut(t, self.cut) {
                self.counts.cut += 1;
                self.next += 1;
                continue;
            }
            if !crate::signal_udp::push_sample(block, start.saturating_add(t), value, valid) {
                self.counts.full_blocks += 1;
                break;
            }
            self.counts.invalid += u64::from(!valid);
            self.counts.sent += 1;
            self.next += 1;
        }
        if in_cut(since, self.cut) {
            block.status |= signal_status::CUT;
        }
        if self.next >= self.samples.len() {
            block.status |= signal_status::ENDED;
        }
    }

    /// Every sample has been sent (or withheld).
    pub fn ended(&self) -> bool {
        self.next >= self.samples.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::MAX_SIGNAL_SAMPLES;

    fn replay_of(samples: Vec<(u64, f64, bool)>) -> TraceReplay {
        TraceReplay {
            samples,
            unit: signal_unit::MM,
            period_ns: 40_000_000,
            start_ns: None,
            next: 0,
            cut: None,
            describe: String::new(),
            counts: SignalCounts::default(),
            warning: None,
        }
    }

    #[test]
    fn the_spec_names_a_trace_or_none_and_says_what_else_it_takes() {
        assert_eq!(SignalSpec::parse("").unwrap(), SignalSpec::None);
        assert_eq!(SignalSpec::parse("none").unwrap(), SignalSpec::None);
        assert_eq!(
            SignalSpec::parse("trace:/tmp/a b.vxp").unwrap(),
            SignalSpec::Trace("/tmp/a b.vxp".into())
        );
        assert_eq!(
            SignalSpec::parse("udp:5000").unwrap(),
            SignalSpec::Udp("127.0.0.1:5000".parse().unwrap())
        );
        assert_eq!(SignalSpec::parse("recorded").unwrap(), SignalSpec::Recorded);
        let e = SignalSpec::parse("serial:/dev/ttyUSB0").unwrap_err();
        assert!(
            e.contains("trace:FILE") && e.contains("udp:[BIND:]PORT") && e.contains("serial:"),
            "{e}"
        );
        assert!(SignalSpec::parse("udp:99999")
            .unwrap_err()
            .contains("udp:PORT"));
        assert!(SignalSpec::parse("trace:")
            .unwrap_err()
            .contains("needs a file"));
        use crate::signal_tool::AxisChoice;
        for (text, name, axis) in [
            ("tool:Chest", "Chest", AxisChoice::Anterior),
            ("tool:Chest:anterior", "Chest", AxisChoice::Anterior),
            ("tool: Chest : AUTO ", "Chest", AxisChoice::Auto),
        ] {
            assert_eq!(
                SignalSpec::parse(text).unwrap(),
                SignalSpec::Tool(name.into(), axis),
                "{text}"
            );
        }
        let e = SignalSpec::parse("tool:Chest:sideways").unwrap_err();
        assert!(
            e.contains("not an axis") && e.contains("tool:NAME:auto"),
            "{e}"
        );
        assert!(SignalSpec::parse("tool::auto")
            .unwrap_err()
            .contains("tool:Chest:auto"));
    }

    #[test]
    fn a_replay_never_sends_a_sample_before_its_time_and_keeps_the_rest_for_later() {
        // 25 Hz for 2 s, every fifth sample invalid.
        let samples: Vec<_> = (0..50u64)
            .map(|i| (i * 40_000_000, i as f64, i % 5 != 4))
            .collect();
        let mut r = replay_of(samples);
        let t0 = 1_000_000_000u64;
        let mut block = SignalBlock::default();
        let mut sent = Vec::new();
        let mut now = t0;
        while !r.ended() {
            r.fill(now, &mut block);
            assert_eq!(block.unit, signal_unit::MM);
            assert_eq!(block.period_ns, 40_000_000);
            assert_eq!(
                block.origin_ns, t0,
                "every block names where the recording's first sample fell on this clock"
            );
            for i in 0..block.count as usize {
                let (s, valid) = block.sample(i).unwrap();
                assert!(s.t_ns <= now, "a sample at {} went out at {now}", s.t_ns);
                assert!(now - s.t_ns < 16_666_667 + 1, "sent as soon as due");
                let index = (s.t_ns - t0) / 40_000_000;
                assert_eq!(valid, index % 5 != 4, "sample {index}");
                if !valid {
                    assert_eq!(
                        s.value, 0.0,
                        "an invalid sample's value is 0, never its number"
                    );
                }
                sent.push(s.t_ns);
            }
            now += 16_666_667;
        }
        assert_eq!(sent.len(), 50);
        assert!(sent.windows(2).all(|w| w[1] - w[0] == 40_000_000));
        assert_eq!(r.counts.invalid, 10);
        assert!(block.status & signal_status::ENDED != 0);
        // A frame late by 0.5 s: the 8 oldest due go out, the rest in the next frame, in order.
        let mut r = replay_of((0..50u64).map(|i| (i * 40_000_000, 1.0, true)).collect());
        r.fill(t0, &mut block);
        assert_eq!(block.count, 1);
        r.fill(t0 + 500_000_000, &mut block);
        assert_eq!(block.count as usize, MAX_SIGNAL_SAMPLES);
        assert_eq!(r.counts.full_blocks, 1);
        let last = block.samples[MAX_SIGNAL_SAMPLES - 1].t_ns;
        r.fill(t0 + 516_000_000, &mut block);
        assert_eq!(block.samples[0].t_ns, last + 40_000_000);
    }

    #[test]
    fn a_cut_withholds_its_window_and_says_so() {
        let mut r = replay_of((0..100u64).map(|i| (i * 40_000_000, 1.0, true)).collect());
        r.cut(1.0, 1.0).unwrap();
        let mut block = SignalBlock::default();
        let mut cut_frames = 0;
        let mut now = 0u64;
        let mut times = Vec::new();
        while !r.ended() {
            r.fill(now, &mut block);
            if block.status & signal_status::CUT != 0 {
                cut_frames += 1;
            }
            times.extend((0..block.count as usize).map(|i| block.samples[i].t_ns));
            now += 16_666_667;
        }
        assert_eq!(r.counts.cut, 25);
        assert_eq!(times.len(), 75);
        assert!(times
            .iter()
            .all(|&t| !(1_000_000_000..2_000_000_000).contains(&t)));
        assert!((59..=61).contains(&cut_frames), "{cut_frames}");
        for (at, dur) in [(-1.0, 1.0), (0.0, 0.0), (f64::NAN, 1.0), (1.0, 1e9)] {
            assert!(r.cut(at, dur).is_err(), "{at} {dur}");
        }
    }
}
