//! The loop every source shares: wait for the next slot of the schedule (an absolute deadline,
//! `next += period`, so the rate never drifts; overruns skip slots instead of bursting), take what
//! the source received, validate and assemble it, record it, publish one frame.
//!
//! Written against [`Pace`] (time and sleeping), [`Source`] and [`Publish`], so tests drive it on a
//! fake clock with in-memory ports. Per tick it does not allocate (the source's samples are
//! fixed-size, the recorder writes into a buffer, the frame is reused).

use std::sync::atomic::{AtomicBool, Ordering};

use ipc_types::TrackerFrame;
use transport::{FakeClock, Publish};

use crate::assemble::Assembler;
use crate::record::RecordWriter;
use crate::sample::{Event, EventKind, Input};
use crate::source::{Poll, Source};
use crate::stats::fnv1a;
use crate::BridgeError;

/// Time and sleeping, for the loop.
pub trait Pace {
    /// Monotonic now, ns.
    fn now_ns(&self) -> u64;
    /// Sleep until `deadline_ns` (absolute; returns at once when it has passed).
    fn sleep_until(&self, deadline_ns: u64);
}

/// The host's monotonic clock.
#[derive(Debug, Clone, Copy, Default)]
pub struct RealTime;

impl Pace for RealTime {
    fn now_ns(&self) -> u64 {
        transport::now_ns()
    }
    fn sleep_until(&self, deadline_ns: u64) {
        transport::clock::sleep_until_ns(deadline_ns);
    }
}

impl Pace for FakeClock {
    fn now_ns(&self) -> u64 {
        transport::Clock::now_ns(self)
    }
    fn sleep_until(&self, deadline_ns: u64) {
        if deadline_ns > transport::Clock::now_ns(self) {
            self.set(deadline_ns);
        }
    }
}

/// Prints source events for a person without flooding: the first few of each kind, then one line
/// with how many were not shown, at most every ten seconds.
#[derive(Debug)]
pub struct Reporter {
    prefix: String,
    shown: [u32; 16],
    hidden: [u64; 16],
    last_summary_ns: u64,
    quiet: bool,
}

impl Reporter {
    /// Lines go to stderr as `prefix: text`; `quiet` shows nothing.
    pub fn new(prefix: impl Into<String>, quiet: bool) -> Self {
        Reporter {
            prefix: prefix.into(),
            shown: [0; 16],
            hidden: [0; 16],
            last_summary_ns: 0,
            quiet,
        }
    }

    fn key(e: &Event) -> usize {
        match (e.kind, e.reason) {
            (EventKind::Rejected, Some(r)) => (7 + r as usize).min(15),
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
                self.hidden = [0; 16];
            }
        }
    }
}

/// Ask the loop to stop on SIGINT/SIGTERM without iceoryx2 (the listening command): returns the
/// flag the signal handler sets.
pub fn stop_on_signals() -> &'static AtomicBool {
    static STOP: AtomicBool = AtomicBool::new(false);
    extern "C" fn on_signal(_: libc::c_int) {
        STOP.store(true, Ordering::Relaxed);
    }
    // SAFETY: installs an async-signal-safe handler (one atomic store) for two signals.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
    &STOP
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
/// loop goes on. `report` sees every event.
pub fn run_loop(
    source: &mut dyn Source,
    asm: &mut Assembler,
    outlet: &mut dyn Publish<TrackerFrame>,
    recorder: &mut Option<RecordWriter>,
    pace: &dyn Pace,
    should_stop: &mut dyn FnMut(u64) -> bool,
    report: &mut dyn FnMut(&Event, u64),
) -> Result<Ended, BridgeError> {
    let period = asm.config().period_ns();
    let paced = source.paced();
    let mut frame = TrackerFrame::default();
    let mut next = pace.now_ns();
    loop {
        if should_stop(pace.now_ns()) {
            return Ok(Ended::Stopped);
        }
        if paced {
            pace.sleep_until(next);
        }
        let now = pace.now_ns();
        if paced {
            asm.stats
                .jitter
                .saturating_record(now.saturating_sub(next).max(1));
        }
        let mut record_error: Option<std::io::Error> = None;
        let poll = {
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
                    stats_sink.ingest(s);
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
        match poll {
            Poll::End => return Ok(Ended::SourceEnded),
            Poll::Tick { at_ns } => {
                asm.frame(at_ns, &mut frame);
                if let Some(r) = recorder.as_mut() {
                    if let Err(e) = r.tick(at_ns, frame.frame_number) {
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
                frame.stamps.bridge_publish_ns = pace.now_ns().max(frame.stamps.capture_ns);
                outlet.publish(&frame)?;
            }
        }
        if let Some(e) = record_error {
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
        if paced {
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
