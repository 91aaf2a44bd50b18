//! The loop every source shares: wait for the next slot of the schedule (an absolute deadline,
//! `next += period`, so the rate never drifts; overruns skip slots instead of bursting), take what
//! the source received, validate and assemble it, record it, publish one frame.
//!
//! A device source (a reader thread behind an [`crate::source::Inbox`]) also ends the wait when a
//! sample arrives: the loop takes everything queued and publishes at once, so a tracker's sample
//! never waits for the bridge's own tick; the schedule then only keeps frames going (stale-flagged)
//! when the device falls silent, its next slot 1.5 periods after the last arrival. Arrivals closer
//! than [`MIN_ARRIVAL_SPACING_NS`] are gathered into one frame, which bounds the publish rate
//! whatever a sender does. A sender that sends each tool in its own message (pyigtl, PLUS, 3D
//! Slicer) completes a device frame message by message: after an arrival the loop waits at most
//! [`GATHER_NS`] for every live configured tool to have a new sample
//! ([`Assembler::frame_complete`]), so one device frame is one published frame with all its tools
//! (before: 75–87 frames a second from a 60 Hz sender of three tools, each new in one tool only);
//! the end of that wait is not a slot of the schedule. The synthetic source and replays make their
//! samples on the tick and keep the absolute-deadline schedule.
//!
//! Written against [`transport::Clock`] (time and sleeping), [`Source`] and [`Publish`], so tests drive it on a
//! fake clock with in-memory ports. Per tick it does not allocate (the source's samples are
//! fixed-size, the recorder writes into a buffer, the frame is reused).

use ipc_types::TrackerFrame;
use transport::{Clock, Publish};

use crate::assemble::{Assembler, Outcome};
use crate::record::RecordWriter;
use crate::sample::{Event, EventKind, Input};
use crate::source::{Poll, Source};
use crate::stats::fnv1a;
use crate::BridgeError;

/// Arrival-driven frames are at least this far apart (≤ 4 kHz, whatever the sender's rate), ns.
pub const MIN_ARRIVAL_SPACING_NS: u64 = 250_000;

pub use crate::stats::GATHER_NS;

/// Gathering a device frame's tools sent in messages of their own (see the module documentation).
#[derive(Debug, Default)]
struct Gather {
    /// Until when, once an arrival started it.
    until: Option<u64>,
    /// The frame was held back at least once.
    held: bool,
}

impl Gather {
    /// The loop's wait ends at the schedule's slot or the gather window's end.
    fn deadline(&self, next: u64) -> u64 {
        self.until.map_or(next, |g| g.min(next))
    }

    /// Whether to hold the frame back now: new samples came (or a gather is on), the schedule's
    /// slot has not come, the window (from `started`) is open and a live tool has no new sample.
    fn hold(&mut self, asm: &Assembler, samples: u64, due: bool, started: u64, now: u64) -> bool {
        let hold = !due
            && (samples > 0 || self.until.is_some())
            && now < *self.until.get_or_insert(started + GATHER_NS)
            && !asm.frame_complete(now);
        self.held |= hold;
        hold
    }

    /// A frame is published: count it when it was held back, and end the gather.
    fn published(&mut self, asm: &mut Assembler, now: u64) {
        if let (Some(until), true) = (self.until.take(), self.held) {
            asm.stats.gathered_frames += 1;
            asm.stats.gather_timeouts += u64::from(now >= until);
        }
        self.held = false;
    }
}

/// The [`Reporter`]'s first key for a rejection reason: one past the last [`EventKind`].
const FIRST_REASON_KEY: usize = EventKind::ConnectionRefused as usize + 1;

/// The [`Reporter`]'s counters: every event kind, then every rejection reason.
const KEYS: usize = FIRST_REASON_KEY + crate::sample::Reject::ALL.len();

/// Prints source events for a person without flooding: the first few of each kind, then one line
/// with how many were not shown, at most every ten seconds.
#[derive(Debug)]
pub struct Reporter {
    prefix: String,
    shown: [u32; KEYS],
    hidden: [u64; KEYS],
    last_summary_ns: u64,
    quiet: bool,
}

impl Reporter {
    /// Lines go to stderr as `prefix: text`; `quiet` shows nothing.
    pub fn new(prefix: impl Into<String>, quiet: bool) -> Self {
        Reporter {
            prefix: prefix.into(),
            shown: [0; KEYS],
            hidden: [0; KEYS],
            last_summary_ns: 0,
            quiet,
        }
    }

    /// Each kind of event its own counter, and each reason of a rejection its own: the kinds
    /// first (0..=7), the rejections after them, so no kind shares a limit with a reason.
    fn key(e: &Event) -> usize {
        match (e.kind, e.reason) {
            (EventKind::Rejected, Some(r)) => (FIRST_REASON_KEY + r as usize).min(KEYS - 1),
            (k, _) => k as usize,
        }
    }

    /// Show (or count) one event.
    pub fn event(&mut self, e: &Event, now_ns: u64) {
        if self.quiet {
            return;
        }
        let k = Self::key(e);
        // Connections coming and going are always worth a line; repeated errors are not.
        let always = matches!(e.kind, EventKind::Connected | EventKind::Disconnected);
        if always || self.shown[k] < 5 {
            self.shown[k] += 1;
            let what = match (e.kind, e.reason) {
                (EventKind::Rejected, Some(r)) => format!("rejected ({}): ", r.as_str()),
                (EventKind::Retrying, _) => String::new(),
                (EventKind::Ignored, _) => "ignored: ".into(),
                (EventKind::DeviceStatus, _) => "device: ".into(),
                _ => String::new(),
            };
            eprintln!("{}: {what}{}", self.prefix, e.text);
        } else {
            self.hidden[k] += 1;
        }
        if now_ns.saturating_sub(self.last_summary_ns) > 10_000_000_000 {
            self.last_summary_ns = now_ns;
            let n: u64 = self.hidden.iter().sum();
            if n > 0 {
                eprintln!(
                    "{}: {n} more such messages (counted in the statistics)",
                    self.prefix
                );
                self.hidden = [0; KEYS];
            }
        }
    }
}

/// What the loop did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ended {
    /// `should_stop` said so.
    Stopped,
    /// The source ended (a replay reached its end).
    SourceEnded,
}

/// Run until `should_stop(now)` or the source ends. Every sample and event goes to the recorder
/// (when there is one) before the assembler; a recording that fails is reported and dropped, the
/// loop goes on. `report` sees every event. `latency` gives the pipeline's latency as measured now
/// (ns, 0 while unknown: [`crate::latency::LatencyMeter`]); a frame that carries the respiratory
/// signal carries it too, and it is recorded with the signal (a replay gives the recorded one).
#[allow(clippy::too_many_arguments)]
pub fn run_loop(
    source: &mut dyn Source,
    asm: &mut Assembler,
    outlet: &mut dyn Publish<TrackerFrame>,
    recorder: &mut Option<RecordWriter>,
    pace: &dyn Clock,
    should_stop: &mut dyn FnMut(u64) -> bool,
    report: &mut dyn FnMut(&Event, u64),
    latency: &mut dyn FnMut() -> u64,
) -> Result<Ended, BridgeError> {
    let period = asm.config().period_ns();
    let paced = source.paced();
    let mut frame = TrackerFrame::default();
    let mut next = pace.now_ns();
    let mut last_publish = 0u64;
    // Gathering a device frame's tools until then (see the module documentation).
    let mut gather = Gather::default();
    loop {
        if should_stop(pace.now_ns()) {
            return Ok(Ended::Stopped);
        }
        // A device's sample ends the wait (published on arrival); else the schedule's slot.
        let arrived = {
            let _wait = tracing::info_span!(target: transport::trace::TARGET, "wait").entered();
            paced && source.wait(pace, gather.deadline(next))
        };
        // Woken by the gather window's end, not by the schedule.
        let gather_wake = !arrived && gather.until.is_some();
        if arrived && pace.now_ns() < last_publish + MIN_ARRIVAL_SPACING_NS {
            pace.sleep_until(last_publish + MIN_ARRIVAL_SPACING_NS);
        }
        let now = pace.now_ns();
        // The schedule's slot has come (also when inputs arrived: a flood of link events must not
        // hold back the frames that say a silent tool is stale).
        let due = paced && now >= next;
        if paced && !arrived && !gather_wake {
            asm.stats
                .jitter
                .saturating_record(now.saturating_sub(next).max(1));
        }
        let mut samples = 0u64;
        let mut record_error: Option<std::io::Error> = None;
        let poll = {
            let _poll =
                tracing::info_span!(target: transport::trace::TARGET, "poll source").entered();
            let stats_sink = &mut *asm;
            let rec = &mut *recorder;
            let report = &mut *report;
            source.poll(now, &mut |input| match input {
                Input::Sample(s) => {
                    if let Some(r) = rec.as_mut() {
                        if let Err(e) = r.sample(s) {
                            record_error.get_or_insert(e);
                        }
                    }
                    // A repeat of a device frame already seen changes no pose: no frame for it.
                    if stats_sink.ingest(s) != Outcome::Repeat {
                        samples += 1;
                    }
                }
                // An amplitude for the respiratory signal (not recorded as it came: the frame's
                // signal block is); another device's reading is ignored, as any other message is.
                Input::Reading(reading) => {
                    if stats_sink.take_reading(reading) {
                        samples += 1;
                    } else if let Err(err) = ignore_reading(reading, rec, stats_sink, report, now) {
                        record_error.get_or_insert(err);
                    }
                }
                Input::Event(e) => {
                    if let Some(r) = rec.as_mut() {
                        if let Err(err) = r.event(e) {
                            record_error.get_or_insert(err);
                        }
                    }
                    stats_sink.stats.event(e);
                    report(e, now);
                }
            })?
        };
        let quiet = arrived && samples == 0 && !due && gather.until.is_none();
        // A device frame's tools still coming, each in its own message: wait for them (bounded).
        let gathering = paced && !quiet && gather.hold(asm, samples, due, now, pace.now_ns());
        match poll {
            Poll::End => return Ok(Ended::SourceEnded),
            // Only link events or repeats arrived (a connection, a rejected message): no frame.
            Poll::Tick { .. } if quiet || gathering => {}
            Poll::Tick { at_ns } => {
                gather.published(asm, pace.now_ns());
                let _publish =
                    tracing::info_span!(target: transport::trace::TARGET, "assemble + publish")
                        .entered();
                asm.frame(at_ns, &mut frame);
                // The respiratory signal on the run's clock (a replayed trace plays in real time),
                // or the one a replayed recording carries, on the recording's clock until moved
                // below (the digest sees it as recorded).
                let replayed = source.recorded_signal();
                match &replayed {
                    Some(b) => asm.replay_signal(b, &mut frame.signal),
                    None => {
                        asm.fill_signal(now, &frame.tools, &mut frame.signal);
                        if frame.signal != ipc_types::SignalBlock::default() {
                            frame.signal.pipeline_latency_ns = latency();
                        }
                    }
                }
                if let Some(r) = recorder.as_mut() {
                    let mut put = || -> std::io::Result<()> {
                        // The signal's block before its tick, when the run has a signal.
                        if frame.signal != ipc_types::SignalBlock::default() {
                            r.signal(&frame.signal)?;
                        }
                        r.tick(at_ns, frame.frame_number)
                    };
                    if let Err(e) = put() {
                        record_error.get_or_insert(e);
                    }
                }
                let capture = frame.stamps.capture_ns;
                frame.stamps = Default::default();
                asm.stats.frames_digest =
                    fnv1a(asm.stats.frames_digest, bytemuck::bytes_of(&frame));
                // The stamps are this run's times: a replayed sample is as old at its tick as it
                // was when recorded.
                frame.stamps.capture_ns = now.saturating_sub(at_ns.saturating_sub(capture)).max(1);
                if replayed.is_some() {
                    crate::signal::shift(&mut frame.signal, i128::from(now) - i128::from(at_ns));
                }
                frame.stamps.bridge_publish_ns = pace.now_ns().max(frame.stamps.capture_ns);
                outlet.publish(&frame)?;
                last_publish = frame.stamps.bridge_publish_ns;
            }
        }
        if let Some(e) = record_error {
            stop_recording(recorder, &e, report, now);
        }
        if arrived && samples > 0 {
            next = pace.now_ns() + period + period / 2;
        } else if paced && (due || (!arrived && !gather_wake)) {
            next += period;
            let now = pace.now_ns();
            if now > next + period {
                let missed = (now - next) / period;
                asm.stats.ticks_skipped += missed;
                next += missed * period;
            }
        }
    }
}

/// A recording that failed is reported and dropped; the loop goes on.
fn stop_recording(
    recorder: &mut Option<RecordWriter>,
    e: &std::io::Error,
    report: &mut dyn FnMut(&Event, u64),
    now: u64,
) {
    let path = recorder
        .as_ref()
        .map(|r| r.path().display().to_string())
        .unwrap_or_default();
    *recorder = None;
    report(
        &Event::new(
            EventKind::Note,
            0,
            format!("recording to {path} failed and stopped: {e}"),
        ),
        now,
    );
}

/// Another device's reading (or one without an OpenIGTLink signal): ignored, as any message the
/// bridge does not use is, and counted. Such readings may come every frame and this is the loop's
/// thread: only the first is said and recorded (an event's text allocates), the rest counted.
fn ignore_reading(
    reading: &crate::sample::Reading,
    recorder: &mut Option<RecordWriter>,
    asm: &mut Assembler,
    report: &mut dyn FnMut(&Event, u64),
    now: u64,
) -> std::io::Result<()> {
    asm.stats.ignored_readings += 1;
    if asm.stats.ignored_readings > 1 {
        asm.stats.ignored += 1;
        return Ok(());
    }
    let e = Event::new(
        EventKind::Ignored,
        1,
        format!(
            "a reading (SENSOR or STRING) from {:?}: not the signal's device (the next ones \
             only counted)",
            reading.name.as_str()
        ),
    );
    asm.stats.event(&e);
    report(&e, now);
    match recorder.as_mut() {
        Some(r) => r.event(&e),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::assemble::BridgeConfig;
    use crate::sample::{Sample, ToolName};
    use crate::source::SourceError;
    use crate::validate::Volume;
    use transport::memory::Recorder;
    use transport::FakeClock;

    /// A device source on a fake clock: inputs arrive at scripted times.
    struct Scripted {
        arrivals: std::collections::VecDeque<(u64, Input)>,
        /// Time each poll takes (on the loop's clock).
        clock: FakeClock,
        poll_cost_ns: u64,
    }

    impl Source for Scripted {
        fn describe(&self) -> String {
            "scripted".into()
        }
        fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
            while self.arrivals.front().is_some_and(|(t, _)| *t <= now_ns) {
                if let Some((_, i)) = self.arrivals.pop_front() {
                    sink(&i);
                }
            }
            self.clock.advance(self.poll_cost_ns);
            Ok(Poll::Tick { at_ns: now_ns })
        }
        fn wait(&mut self, pace: &dyn Clock, deadline_ns: u64) -> bool {
            match self.arrivals.front() {
                // Already queued: at once, whatever the deadline (as `Inbox::wait`).
                Some(&(t, _)) if t <= pace.now_ns() => true,
                Some(&(t, _)) if t < deadline_ns => {
                    pace.sleep_until(t);
                    true
                }
                _ => {
                    pace.sleep_until(deadline_ns);
                    false
                }
            }
        }
    }

    const MS: u64 = 1_000_000;
    const P: u64 = 16_666_667;

    fn sample(at: u64, x: f32) -> (u64, Input) {
        let name = ToolName::new("Patient").unwrap();
        (
            at,
            Input::Sample(Sample::quat(
                at,
                name,
                [0.0, 0.0, 0.0, 1.0],
                [x, 0.0, -1000.0],
            )),
        )
    }

    /// (publish time, capture stamp, patient x) of every frame until `until_ns`.
    fn run(arrivals: Vec<(u64, Input)>, until_ns: u64) -> Vec<(u64, u64, f32)> {
        run_costing(arrivals, until_ns, 0)
    }

    fn run_costing(
        arrivals: Vec<(u64, Input)>,
        until_ns: u64,
        poll_cost_ns: u64,
    ) -> Vec<(u64, u64, f32)> {
        frames_stats_of(arrivals, until_ns, poll_cost_ns)
            .0
            .iter()
            .map(|f: &TrackerFrame| {
                (
                    f.stamps.bridge_publish_ns,
                    f.stamps.capture_ns,
                    f.tools[0].pose.translation_mm[0],
                )
            })
            .collect()
    }

    #[test]
    fn every_event_kind_and_rejection_reason_has_its_own_reporter_limit() {
        use crate::sample::Reject;
        let kinds = [
            EventKind::Connected,
            EventKind::Disconnected,
            EventKind::Retrying,
            EventKind::DeviceStatus,
            EventKind::Ignored,
            EventKind::Note,
            EventKind::ConnectionRefused,
        ];
        let mut keys: Vec<usize> = kinds
            .iter()
            .map(|&k| Reporter::key(&crate::sample::Event::new(k, 0, "")))
            .collect();
        keys.extend(
            Reject::ALL
                .iter()
                .map(|&r| Reporter::key(&crate::sample::Event::rejected(r, 1, ""))),
        );
        let n = keys.len();
        assert!(keys.iter().all(|&k| k < KEYS), "{keys:?}");
        keys.sort_unstable();
        keys.dedup();
        assert_eq!(keys.len(), n, "two share a key");
    }

    #[test]
    fn a_device_sample_is_published_when_it_arrives_and_the_schedule_only_fills_silence() {
        let t = [10 * MS, 10 * MS + P, 10 * MS + 2 * P];
        let frames = run(
            vec![
                sample(t[0], 1.0),
                (
                    12 * MS,
                    Input::Event(crate::sample::Event::new(EventKind::Note, 0, "a note")),
                ),
                sample(t[1], 2.0),
                sample(t[2], 3.0),
            ],
            120 * MS,
        );
        let heartbeat = t[2] + P + P / 2;
        let expected = [
            (1, 0.0),
            (t[0], 1.0),
            (t[1], 2.0),
            (t[2], 3.0),
            (heartbeat, 3.0),
            (heartbeat + P, 3.0),
            (heartbeat + 2 * P, 3.0),
        ];
        let got: Vec<(u64, f32)> = frames.iter().take(7).map(|&(at, _, x)| (at, x)).collect();
        assert_eq!(
            got, expected,
            "no frame for the note, none waiting for a tick"
        );
        for (&(at, capture, _), &arrival) in frames[1..4].iter().zip(&t) {
            assert_eq!(
                (at, capture),
                (arrival, arrival),
                "capture -> publish is the work alone"
            );
        }
    }

    #[test]
    fn a_flood_of_link_events_does_not_hold_back_the_schedule() {
        let note = |at| {
            (
                at,
                Input::Event(crate::sample::Event::new(EventKind::Note, 0, "garbage")),
            )
        };
        // An event every 0.5 ms, each taking the loop 0.6 ms: one is always waiting.
        let mut arrivals = vec![sample(MS, 1.0)];
        arrivals.extend((1..200).map(|k| note(MS + k * MS / 2)));
        let frames = run_costing(arrivals, 90 * MS, 600_000);
        let at: Vec<u64> = frames.iter().skip(1).take(4).map(|f| f.0).collect();
        assert_eq!(at.len(), 4, "frames: {frames:?}");
        assert_eq!(at[0], MS + 600_000, "the sample, after its poll");
        // Each slot's frame comes within one poll of its slot.
        let first = at[0] + P + P / 2;
        for (k, &t) in at[1..].iter().enumerate() {
            let slot = first + k as u64 * P;
            assert!(
                (slot..slot + 2 * 600_000).contains(&t),
                "frame {k} at {t}, slot {slot}"
            );
        }
    }

    #[test]
    fn a_repeated_device_frame_is_no_reason_to_publish() {
        let with_frame = |(at, i): (u64, Input), n: u64| match i {
            Input::Sample(s) => (
                at,
                Input::Sample(Sample {
                    device_frame: Some(n),
                    ..s
                }),
            ),
            other => (at, other),
        };
        let frames = run(
            vec![
                with_frame(sample(10 * MS, 1.0), 7),
                with_frame(sample(20 * MS, 1.0), 7),
            ],
            30 * MS,
        );
        let at: Vec<u64> = frames.iter().skip(1).take(2).map(|f| f.0).collect();
        assert_eq!(
            at,
            [10 * MS, 10 * MS + P + P / 2],
            "the repeat at 20 ms made none"
        );
    }

    #[test]
    fn arrivals_closer_than_the_minimum_spacing_make_one_frame() {
        let frames = run(
            vec![
                sample(10 * MS, 1.0),
                sample(10 * MS + 100_000, 2.0),
                sample(10 * MS + 200_000, 3.0),
            ],
            20 * MS,
        );
        let got: Vec<(u64, u64, f32)> = frames.into_iter().skip(1).take(2).collect();
        assert_eq!(
            got,
            [
                (10 * MS, 10 * MS, 1.0),
                (10 * MS + MIN_ARRIVAL_SPACING_NS, 10 * MS + 200_000, 3.0),
            ]
        );
    }

    fn tool_sample(at: u64, name: &str, x: f32) -> (u64, Input) {
        (
            at,
            Input::Sample(Sample::quat(
                at,
                ToolName::new(name).unwrap(),
                [0.0, 0.0, 0.0, 1.0],
                [x, 0.0, -1000.0],
            )),
        )
    }

    /// Every frame published until `until_ns`.
    fn frames_of(arrivals: Vec<(u64, Input)>, until_ns: u64) -> Vec<TrackerFrame> {
        frames_stats_of(arrivals, until_ns, 0).0
    }

    /// Every frame published until `until_ns`, each poll taking `poll_cost_ns`, and the counters.
    fn frames_stats_of(
        arrivals: Vec<(u64, Input)>,
        until_ns: u64,
        poll_cost_ns: u64,
    ) -> (Vec<TrackerFrame>, crate::stats::Stats) {
        let clock = FakeClock::at(0);
        let mut source = Scripted {
            arrivals: arrivals.into(),
            clock: clock.clone(),
            poll_cost_ns,
        };
        let mut config = BridgeConfig::default();
        config.validation.volume = Volume::Unbounded;
        let mut asm = Assembler::new(config);
        let mut out = Recorder::new(&clock);
        run_loop(
            &mut source,
            &mut asm,
            &mut out,
            &mut None,
            &clock,
            &mut |now| now >= until_ns,
            &mut |_, _| {},
            &mut || 0,
        )
        .unwrap();
        (out.values(), asm.stats.clone())
    }

    fn x(f: &TrackerFrame, slot: usize) -> f32 {
        f.tools[slot].pose.translation_mm[0]
    }

    /// pyigtl, PLUS and Slicer send each tool in its own message: the patient reference, then the
    /// HMD 0.3 ms later. One device frame is one published frame with both tools new, published
    /// when the last came (before: two frames, the first with the HMD a frame old). (The first
    /// device frame, before the HMD was ever seen, goes out as it comes.)
    #[test]
    fn a_device_frame_sent_tool_by_tool_is_one_frame_with_every_tool() {
        use ipc_types::{TOOL_HMD, TOOL_PATIENT};
        let t = |k: u64| 10 * MS + k * P;
        let mut arrivals = Vec::new();
        for k in 0..5u64 {
            arrivals.push(tool_sample(t(k), "Patient", k as f32));
            arrivals.push(tool_sample(t(k) + 300_000, "HMD", 10.0 + k as f32));
        }
        let frames = frames_of(arrivals, t(4) + P);
        let got: Vec<(u64, f32, f32)> = frames
            .iter()
            // From the second device frame to the last (the schedule's heartbeat after it left out).
            .filter(|f| (t(1)..t(5)).contains(&f.stamps.bridge_publish_ns))
            .map(|f| {
                (
                    f.stamps.bridge_publish_ns,
                    x(f, TOOL_PATIENT),
                    x(f, TOOL_HMD),
                )
            })
            .collect();
        let want: Vec<(u64, f32, f32)> = (1..5u64)
            .map(|k| (t(k) + 300_000, k as f32, 10.0 + k as f32))
            .collect();
        assert_eq!(got, want);
    }

    /// A tool slower than the others (an HMD at 30 Hz beside a 60 Hz reference) holds a frame
    /// back at most [`GATHER_NS`]; a tool gone silent past the staleness bound holds back none.
    #[test]
    fn a_slower_or_silent_tool_holds_a_frame_back_at_most_the_gather_window() {
        use ipc_types::TOOL_PATIENT;
        let t = |k: u64| 10 * MS + k * P;
        let mut arrivals = Vec::new();
        for k in 0..12u64 {
            arrivals.push(tool_sample(t(k), "Patient", k as f32));
            // The HMD at 30 Hz for four frames, then silent.
            if k % 2 == 0 && k < 4 {
                arrivals.push(tool_sample(t(k) + 100_000, "HMD", 0.0));
            }
        }
        let (frames, stats) = frames_stats_of(arrivals, t(11) + P, 0);
        // Frames 1, 3, 4, 5 waited the window out; the start-up's HMD-only frame waited too.
        assert_eq!(
            (stats.gathered_frames, stats.gather_timeouts),
            (6, 5),
            "{stats:?}"
        );
        let at: Vec<(f32, u64)> = frames
            .iter()
            .filter(|f| (t(1)..t(12)).contains(&f.stamps.bridge_publish_ns))
            .map(|f| (x(f, TOOL_PATIENT), f.stamps.bridge_publish_ns))
            .collect();
        assert_eq!(at.len(), 11, "one frame per reference sample: {at:?}");
        for (k, &(xk, published)) in at.iter().enumerate() {
            let k = k as u64 + 1;
            assert_eq!(xk, k as f32);
            let late = published - t(k);
            match k {
                2 => assert_eq!(late, 100_000, "frame {k}: complete with the HMD"),
                // Waiting for an HMD that comes every other frame, then until it is stale (50 ms).
                1 | 3 | 4 | 5 => assert_eq!(late, GATHER_NS, "frame {k}"),
                _ => assert_eq!(late, 0, "frame {k}: the HMD is stale, nothing to wait for"),
            }
        }
    }

    /// The end of a gather window is not a slot of the schedule: after a frame published when the
    /// window ran out, a device gone silent still gets its heartbeat 1.5 periods after its last
    /// sample (it came a period later when the window's end counted as a slot).
    #[test]
    fn the_gather_windows_end_does_not_move_the_schedule() {
        let t0 = 10 * MS;
        let t1 = t0 + P;
        let frames = frames_of(
            vec![
                tool_sample(t0, "Patient", 0.0),
                tool_sample(t0 + 100_000, "HMD", 0.0),
                tool_sample(t1, "Patient", 1.0),
            ],
            t1 + 2 * P,
        );
        let at: Vec<u64> = frames
            .iter()
            .map(|f| f.stamps.bridge_publish_ns)
            .filter(|&t| t >= t1)
            .collect();
        assert_eq!(at[0], t1 + GATHER_NS, "held for the HMD: {at:?}");
        assert_eq!(at[1], t1 + P + P / 2, "then the heartbeat on time: {at:?}");
    }
}
