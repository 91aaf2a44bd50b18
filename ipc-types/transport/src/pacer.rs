//! The pacer: wake on a stream's samples, with an absolute-deadline fallback.
//!
//! The engine ticks when a tracker sample arrives and the renderer draws when an engine frame
//! arrives — input-driven, so a sample becomes output within microseconds instead of waiting for a
//! free-running timer. When the input is late or silent, a deadline (`period + grace` after the last
//! sample, then every `period`, absolute, so it never drifts) keeps the output going. This module is
//! that logic once, over a [`Clock`] and a [`Receive`] port, so it is tested against a fake clock
//! rather than real time.
//!
//! Rules, in order, each time [`Pacer::poll`] runs:
//! 1. wait on the port until the next wake-up time (the deadline, or the end of the minimum spacing
//!    when a sample is being held);
//! 2. a sample that arrived is kept as *pending* (a newer one replaces it: a burst becomes one tick
//!    with the newest sample, the others counted as coalesced);
//! 3. a pending sample drives a tick as soon as `min_spacing` has passed since the previous tick —
//!    an early sample is **held**, never dropped (the old engine loop discarded it and then flagged
//!    the next tick as a deadline fallback);
//! 4. otherwise, once the deadline has passed, a deadline tick runs; if the deadline is more than
//!    `max_catch_up` periods in the past (the process was stopped, the machine suspended, the clock
//!    jumped) the missed deadlines are skipped and counted instead of being replayed as a burst.
//!
//! Each tick has a number ([`Tick::number`]). By default it is how many ticks ran before it. Numbered
//! by the clock ([`PacerConfig::clock_numbered`], the engine's, whose tick number is its breathing
//! clock), it follows the schedule's slots of one period from the start, whatever the input's rate:
//! from 0 the previous number plus one, held within one of the slot the tick is due in — so an input
//! faster than the period (a 120 Hz tracker, a sender that sends each tool in its own message)
//! repeats a number now and then (its extra ticks move the pose, not the breath), and a slower one
//! (a 50 Hz tracker) skips one. No tick waits for it: rule 3 alone decides when ticks run.

use crate::clock::Clock;
use crate::port::{PortError, Receive};

/// Timing of a paced loop, ns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PacerConfig {
    /// Nominal period.
    pub period_ns: u64,
    /// How much later than one period a sample may arrive before the deadline fires.
    pub grace_ns: u64,
    /// Minimum time between two sample-driven ticks (bounds the tick rate whatever the input rate).
    pub min_spacing_ns: u64,
    /// Deadlines further behind than this many periods are skipped, not caught up.
    pub max_catch_up: u64,
    /// Number ticks by the clock's slots, not by count (see the module documentation).
    pub clock_numbered: bool,
}

impl PacerConfig {
    /// The defaults for a loop at `period_ns`: grace a quarter period, minimum spacing half a period,
    /// at most two periods caught up.
    pub fn for_period(period_ns: u64) -> Self {
        let period_ns = period_ns.max(1);
        Self {
            period_ns,
            grace_ns: period_ns / 4,
            min_spacing_ns: period_ns / 2,
            max_catch_up: 2,
            clock_numbered: false,
        }
    }

    /// [`Self::for_period`] with ticks numbered by the clock (the engine's breathing clock).
    pub fn clock_numbered(period_ns: u64) -> Self {
        Self {
            clock_numbered: true,
            ..Self::for_period(period_ns)
        }
    }
}

/// Why a tick runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wake<T> {
    /// A sample arrived (the newest, if several did).
    Sample(T),
    /// No sample before the deadline.
    Deadline,
}

/// One tick the loop must run now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tick<T> {
    /// Why.
    pub wake: Wake<T>,
    /// Clock time at which the tick was decided, ns.
    pub at_ns: u64,
    /// The time the tick was due: the deadline it ran for (the schedule, without the OS's lateness
    /// in waking the loop), or `at_ns` for a sample's tick (the sample is the schedule).
    pub due_ns: u64,
    /// Deadlines skipped right before this tick (the loop was stalled or the clock jumped).
    pub skipped: u64,
    /// The tick's number, never lower than the last one's: by count (0, 1, 2, …) or, numbered
    /// by the clock, within one of the slot of the schedule `due_ns` lies in (see the module
    /// documentation).
    pub number: u64,
}

/// What the pacer has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PacerStats {
    /// Ticks driven by a sample.
    pub sample_ticks: u64,
    /// Ticks on the deadline fallback.
    pub deadline_ticks: u64,
    /// Samples replaced by a newer one before they drove a tick.
    pub coalesced: u64,
    /// Samples that arrived within the minimum spacing and were held until it passed.
    pub held: u64,
    /// Deadlines skipped because they were more than `max_catch_up` periods in the past.
    pub skipped_deadlines: u64,
    /// Numbered by the clock: ticks that repeated the last number (the input was faster than
    /// the period).
    pub repeated_numbers: u64,
    /// Numbered by the clock: numbers passed over (the input was slower than the period, or
    /// the loop stalled).
    pub skipped_numbers: u64,
}

/// Wake-on-sample with an absolute-deadline fallback (see the module documentation).
#[derive(Debug, Clone)]
pub struct Pacer<T> {
    cfg: PacerConfig,
    start: u64,
    /// The last tick's number and how many ticks ran.
    last_number: Option<u64>,
    ticks: u64,
    deadline: u64,
    earliest: u64,
    pending: Option<T>,
    held_counted: bool,
    stats: PacerStats,
}

impl<T: Copy> Pacer<T> {
    /// A pacer starting at `start_ns`: the first deadline is one period plus the grace later.
    pub fn new(cfg: PacerConfig, start_ns: u64) -> Self {
        Self {
            cfg,
            start: start_ns,
            last_number: None,
            ticks: 0,
            deadline: start_ns.saturating_add(cfg.period_ns + cfg.grace_ns),
            earliest: start_ns,
            pending: None,
            held_counted: false,
            stats: PacerStats::default(),
        }
    }

    /// The timing in force.
    pub fn config(&self) -> PacerConfig {
        self.cfg
    }

    /// Counters so far.
    pub fn stats(&self) -> PacerStats {
        self.stats
    }

    /// The number of a tick due at `due_ns` (see [`Tick::number`]), counted.
    fn number(&mut self, due_ns: u64) -> u64 {
        let n = if self.cfg.clock_numbered {
            let slot = due_ns.saturating_sub(self.start) / self.cfg.period_ns;
            match self.last_number {
                // The run's first tick is its tick 0 (where a disease's onset or a resumed run
                // starts), whenever it is due.
                None => 0,
                Some(last) => {
                    let n = (last + 1).clamp(slot.saturating_sub(1), slot + 1).max(last);
                    if n == last {
                        self.stats.repeated_numbers += 1;
                    }
                    self.stats.skipped_numbers += n.saturating_sub(last + 1);
                    n
                }
            }
        } else {
            self.ticks
        };
        self.ticks += 1;
        self.last_number = Some(n);
        n
    }

    /// When the next poll will wake at the latest, ns.
    pub fn next_wake_ns(&self) -> u64 {
        if self.pending.is_some() {
            self.earliest
        } else {
            self.deadline
        }
    }

    /// Wait once on `rx` and decide: `Some(tick)` when the loop must run a tick now, `None` when it
    /// woke without one (a held sample, a spurious wake-up) and should check its stop condition and
    /// poll again. Never allocates.
    pub fn poll(
        &mut self,
        clock: &dyn Clock,
        rx: &mut dyn Receive<T>,
    ) -> Result<Option<Tick<T>>, PortError> {
        rx.wait_until(self.next_wake_ns())?;
        let mut newest = None;
        let arrived = rx.drain(&mut |s| newest = Some(*s))? as u64;
        if let Some(sample) = newest {
            let replaced = u64::from(self.pending.replace(sample).is_some());
            self.stats.coalesced += arrived - 1 + replaced;
        }
        let now = clock.now_ns();
        if let Some(sample) = self.pending {
            if now < self.earliest {
                if !self.held_counted {
                    self.stats.held += 1;
                    self.held_counted = true;
                }
                return Ok(None);
            }
            self.pending = None;
            self.held_counted = false;
            self.earliest = now + self.cfg.min_spacing_ns;
            self.deadline = now + self.cfg.period_ns + self.cfg.grace_ns;
            self.stats.sample_ticks += 1;
            return Ok(Some(Tick {
                wake: Wake::Sample(sample),
                at_ns: now,
                due_ns: now,
                skipped: 0,
                number: self.number(now),
            }));
        }
        if now < self.deadline {
            return Ok(None);
        }
        let behind = (now - self.deadline) / self.cfg.period_ns;
        let skipped = if behind >= self.cfg.max_catch_up {
            self.deadline += behind * self.cfg.period_ns;
            self.stats.skipped_deadlines += behind;
            behind
        } else {
            0
        };
        let due_ns = self.deadline;
        self.deadline += self.cfg.period_ns;
        self.earliest = now + self.cfg.min_spacing_ns;
        self.stats.deadline_ticks += 1;
        Ok(Some(Tick {
            wake: Wake::Deadline,
            at_ns: now,
            due_ns,
            skipped,
            number: self.number(due_ns),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::FakeClock;
    use crate::memory::Scripted;

    const P: u64 = 16_666_667;

    /// Run the pacer until `until_ns`, returning every tick.
    fn run(
        clock: &FakeClock,
        src: &mut Scripted<u32>,
        pacer: &mut Pacer<u32>,
        until_ns: u64,
    ) -> Vec<Tick<u32>> {
        let mut ticks = Vec::new();
        let mut polls = 0;
        while clock.now_ns() < until_ns {
            if let Some(t) = pacer.poll(clock, src).unwrap() {
                ticks.push(t);
            }
            polls += 1;
            assert!(polls < 1_000_000, "the pacer stopped making progress");
        }
        ticks
    }

    fn samples(ticks: &[Tick<u32>]) -> Vec<u32> {
        ticks
            .iter()
            .filter_map(|t| match t.wake {
                Wake::Sample(s) => Some(s),
                Wake::Deadline => None,
            })
            .collect()
    }

    #[test]
    fn on_time_samples_each_drive_one_tick_at_their_arrival() {
        let clock = FakeClock::at(1_000);
        let arrivals: Vec<(u64, u32)> = (1..=20).map(|k| (1_000 + k * P, k as u32)).collect();
        let mut src = Scripted::new(&clock, arrivals.clone(), 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 1_000);
        let ticks = run(&clock, &mut src, &mut pacer, 1_000 + 20 * P);
        assert_eq!(samples(&ticks), (1..=20).collect::<Vec<_>>());
        for (t, (at, _)) in ticks.iter().zip(&arrivals) {
            assert_eq!(t.at_ns, *at, "driven by the sample, not a timer");
        }
        assert_eq!(pacer.stats().deadline_ticks, 0);
    }

    /// A deadline tick decided late (the loop woke late) is still due at its deadline: what a
    /// remote site schedules by, free of this host's wake-up lateness.
    #[test]
    fn a_late_deadline_tick_is_due_at_its_deadline() {
        let clock = FakeClock::at(0);
        let mut src = Scripted::<u32>::new(&clock, vec![], 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let first = P + P / 4;
        clock.set(first + 300_000);
        let t = pacer.poll(&clock, &mut src).unwrap().unwrap();
        assert_eq!((t.at_ns, t.due_ns), (first + 300_000, first));
        clock.set(first + P + 50_000);
        let t = pacer.poll(&clock, &mut src).unwrap().unwrap();
        assert_eq!((t.at_ns, t.due_ns), (first + P + 50_000, first + P));
    }

    /// Regression: the engine loop used to take an early tracker sample out of its subscriber and
    /// then `continue`, losing it; the next tick ran on the deadline fallback, flagged as if the
    /// tracker had been late. A tracker whose rhythm shifts by 0.3 periods then lost *every*
    /// sample: each arrived < ½ period after a fallback tick. (The old rule — drop a sample taken
    /// within half a period of the last tick — ported into `poll` makes this test fail: samples
    /// 2..4 never appear and three deadline ticks do.)
    #[test]
    fn an_early_sample_is_held_until_the_minimum_spacing_not_dropped() {
        let clock = FakeClock::at(0);
        let arrivals = vec![
            (P, 1u32),
            (13 * P / 10, 2),
            (23 * P / 10, 3),
            (33 * P / 10, 4),
        ];
        let mut src = Scripted::new(&clock, arrivals, 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let ticks = run(&clock, &mut src, &mut pacer, 33 * P / 10);
        assert_eq!(samples(&ticks), vec![1, 2, 3, 4], "{ticks:?}");
        assert_eq!(pacer.stats().deadline_ticks, 0, "{ticks:?}");
        assert_eq!(pacer.stats().held, 1);
        assert_eq!(
            ticks[1].at_ns,
            P + P / 2,
            "held exactly until the spacing passed"
        );
        assert_eq!(ticks[2].at_ns, 23 * P / 10, "then on time again");
    }

    /// A sample that arrives just after a deadline tick (the tracker was late) still drives the
    /// next tick; the late tracker shows as one deadline tick, nothing is lost.
    #[test]
    fn a_late_sample_right_after_a_deadline_tick_is_still_used() {
        let clock = FakeClock::at(0);
        let arrivals = vec![
            (P, 1u32),
            (2 * P, 2),
            (33 * P / 10, 3),
            (4 * P, 4),
            (5 * P, 5),
        ];
        let mut src = Scripted::new(&clock, arrivals, 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let ticks = run(&clock, &mut src, &mut pacer, 5 * P);
        assert_eq!(samples(&ticks), vec![1, 2, 3, 4, 5], "{ticks:?}");
        assert_eq!(pacer.stats().deadline_ticks, 1, "{ticks:?}");
        assert_eq!(ticks[2].wake, Wake::Deadline);
        assert_eq!(ticks[2].at_ns, 3 * P + P / 4);
        assert_eq!(
            ticks[3].at_ns,
            3 * P + P / 4 + P / 2,
            "sample 3 held, then used"
        );
    }

    #[test]
    fn a_silent_source_ticks_on_absolute_deadlines_without_drift() {
        let clock = FakeClock::at(500);
        let mut src = Scripted::<u32>::new(&clock, vec![], 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 500);
        let ticks = run(&clock, &mut src, &mut pacer, 500 + P + P / 4 + 999 * P);
        assert!(ticks.iter().all(|t| t.wake == Wake::Deadline));
        for (k, t) in ticks.iter().enumerate() {
            assert_eq!(t.at_ns, 500 + P + P / 4 + k as u64 * P, "tick {k}");
        }
        assert_eq!(ticks.len(), 1000);
    }

    #[test]
    fn a_burst_becomes_one_tick_with_the_newest_sample() {
        let clock = FakeClock::at(0);
        let arrivals: Vec<(u64, u32)> = (0..4).map(|i| (P, i)).collect();
        let mut src = Scripted::new(&clock, arrivals, 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let ticks = run(&clock, &mut src, &mut pacer, P);
        assert_eq!(samples(&ticks), vec![3]);
        assert_eq!(pacer.stats().coalesced, 3);
        // A sample arriving right after, within the spacing, is held, then used; never lost.
        let mut src = Scripted::new(&clock, vec![(P + 10, 7), (P + 20, 8)], 4);
        let ticks = run(&clock, &mut src, &mut pacer, 2 * P);
        assert_eq!(samples(&ticks), vec![8]);
        assert_eq!(pacer.stats().coalesced, 4);
    }

    #[test]
    fn a_clock_jump_skips_the_missed_deadlines_instead_of_bursting() {
        let clock = FakeClock::at(0);
        let mut src = Scripted::<u32>::new(&clock, vec![], 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let before = run(&clock, &mut src, &mut pacer, 5 * P);
        assert_eq!(before.len(), 5, "{before:?}");
        // The machine sleeps for ten seconds.
        clock.advance(10_000_000_000);
        let jump_at = clock.now_ns();
        let t = loop {
            if let Some(t) = pacer.poll(&clock, &mut src).unwrap() {
                break t;
            }
        };
        assert_eq!(t.at_ns, jump_at, "one tick at once");
        assert!((598..=601).contains(&t.skipped), "{}", t.skipped);
        let next = loop {
            if let Some(t) = pacer.poll(&clock, &mut src).unwrap() {
                break t;
            }
        };
        assert_eq!(next.skipped, 0);
        assert!(
            next.at_ns > jump_at && next.at_ns <= jump_at + P,
            "then the rhythm resumes"
        );
        assert_eq!(pacer.stats().skipped_deadlines, t.skipped);
    }

    #[test]
    fn a_short_stall_is_caught_up_tick_by_tick() {
        let clock = FakeClock::at(0);
        let mut src = Scripted::<u32>::new(&clock, vec![], 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        run(&clock, &mut src, &mut pacer, 2 * P);
        clock.advance(P + P / 3); // one missed period: within max_catch_up
        let ticks = run(&clock, &mut src, &mut pacer, clock.now_ns() + 1);
        assert!(ticks.iter().all(|t| t.skipped == 0), "{ticks:?}");
        assert_eq!(pacer.stats().skipped_deadlines, 0);
    }

    #[test]
    fn the_source_resuming_after_silence_drives_ticks_again() {
        let clock = FakeClock::at(0);
        let arrivals = vec![(P, 1u32), (10 * P, 2), (11 * P, 3)];
        let mut src = Scripted::new(&clock, arrivals, 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let ticks = run(&clock, &mut src, &mut pacer, 11 * P);
        assert_eq!(samples(&ticks), vec![1, 2, 3]);
        // Deadlines at 1P + 1.25P, then every P until sample 2 arrives at 10P.
        let deadlines: Vec<u64> = ticks
            .iter()
            .filter(|t| t.wake == Wake::Deadline)
            .map(|t| t.at_ns)
            .collect();
        assert_eq!(deadlines.first(), Some(&(2 * P + P / 4)));
        assert!(deadlines.iter().all(|&d| d < 10 * P));
        assert_eq!(deadlines.len(), 8, "{deadlines:?}");
    }

    /// Arrivals at `hz` from `first_ns` for `seconds`, each jittered by up to ±`jitter_ns`
    /// (a fixed pattern), numbered from 1.
    fn arrivals_at(hz: f64, first_ns: u64, seconds: f64, jitter_ns: u64) -> Vec<(u64, u32)> {
        let n = (hz * seconds) as u64;
        (0..n)
            .map(|k| {
                let t = first_ns + (k as f64 * 1e9 / hz) as u64;
                let j = (k * 7919 % 2001) as i64 - 1000; // -1000..=1000, deterministic
                let t = (t as i64 + j * jitter_ns as i64 / 1000).max(1) as u64;
                (t, k as u32 + 1)
            })
            .collect()
    }

    /// The engine's breathing clock: whatever the tracker's rate (and a sender that sends each
    /// tool in its own message looks like a faster one), the tick numbers stay within one of the
    /// clock's slot, never go back, and no tick waits for them. Before numbering by the clock the
    /// engine counted its ticks: an 87 Hz input breathed 1.45x fast, a 50 Hz one 0.83x slow.
    #[test]
    fn ticks_numbered_by_the_clock_follow_it_whatever_the_input_rate() {
        for hz in [25.0, 40.0, 50.0, 59.9, 60.0, 60.1, 87.0, 120.0] {
            for (first, jitter) in [(3 * P / 10, 0), (P - 20_000, 300_000), (10, 1_500_000)] {
                let clock = FakeClock::at(0);
                let arrivals = arrivals_at(hz, first, 10.0, jitter);
                let mut src = Scripted::new(&clock, arrivals.clone(), 4);
                let mut pacer = Pacer::new(PacerConfig::clock_numbered(P), 0);
                let ticks = run(&clock, &mut src, &mut pacer, 10_000_000_000);
                let what = format!("{hz} Hz, first {first}, jitter {jitter}");
                let mut last = 0;
                for t in &ticks {
                    let slot = t.due_ns / P;
                    assert!(
                        t.number + 1 >= slot && t.number <= slot + 1,
                        "{what}: tick {} due in slot {slot}",
                        t.number
                    );
                    assert!(t.number >= last, "{what}: {} after {last}", t.number);
                    last = t.number;
                }
                // The breath's clock at the end is the wall clock's, within a tick.
                assert!((598..=601).contains(&last), "{what}: last {last}");
                // Every sample drove a tick at its arrival or, when it came within half a
                // period of the tick before, when that spacing passed: nothing waited for a number.
                let arrived: std::collections::HashMap<u32, u64> =
                    arrivals.iter().map(|&(t, k)| (k, t)).collect();
                for w in ticks.windows(2) {
                    if let Wake::Sample(k) = w[1].wake {
                        let spaced = w[0].at_ns + P / 2;
                        assert_eq!(w[1].at_ns, arrived[&k].max(spaced), "{what}: sample {k}");
                    }
                }
                let st = pacer.stats();
                if hz > 61.0 {
                    assert!(st.repeated_numbers > 0, "{what}: {st:?}");
                }
                if hz < 59.0 && hz > 41.0 {
                    assert!(st.skipped_numbers > 0, "{what}: {st:?}");
                }
            }
        }
    }

    #[test]
    fn ticks_not_numbered_by_the_clock_are_counted() {
        let clock = FakeClock::at(0);
        let mut src = Scripted::new(&clock, arrivals_at(120.0, P / 3, 1.0, 0), 4);
        let mut pacer = Pacer::new(PacerConfig::for_period(P), 0);
        let ticks = run(&clock, &mut src, &mut pacer, 1_000_000_000);
        assert!(ticks.len() > 100, "{}", ticks.len());
        for (k, t) in ticks.iter().enumerate() {
            assert_eq!(t.number, k as u64);
        }
        assert_eq!(pacer.stats().repeated_numbers, 0);
    }

    #[test]
    fn after_a_stall_the_clock_numbered_ticks_jump_to_the_clock() {
        let clock = FakeClock::at(0);
        let mut src = Scripted::<u32>::new(&clock, vec![], 4);
        let mut pacer = Pacer::new(PacerConfig::clock_numbered(P), 0);
        let before = run(&clock, &mut src, &mut pacer, 5 * P);
        let numbers: Vec<u64> = before.iter().map(|t| t.number).collect();
        assert_eq!(numbers, [0, 1, 2, 3, 4], "the first is 0, due in slot 1");
        clock.advance(10_000_000_000);
        let t = loop {
            if let Some(t) = pacer.poll(&clock, &mut src).unwrap() {
                break t;
            }
        };
        assert_eq!(t.number.abs_diff(t.due_ns / P), 1, "{t:?}");
        assert!(t.number > 600, "{t:?}");
        assert_eq!(pacer.stats().skipped_numbers, t.number - 5);
    }
}
