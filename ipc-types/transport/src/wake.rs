//! Wake strategies: how a receiver ([`crate::iox::Inlet`]) waits for its next sample.
//!
//! * [`Wake::Event`] sleeps on the stream's iceoryx2 event until the producer signals it: no CPU
//!   while waiting, and the kernel's wake-up (tens of µs, more on a busy machine) is the hop.
//! * [`Wake::BusyPoll`] spins on the subscriber until a sample is there or the deadline passes: the
//!   transport's floor (a few µs) for a whole core, so only on a core the scene reserves for the
//!   process ([`choose`] refuses it anywhere else; `auto` picks it only where that core is also
//!   isolated from other tasks, `isolcpus`, since the scheduler otherwise time-slices the spinning
//!   thread with them and the hop waits out their slices: milliseconds).
//! * [`Wake::SpinThenPark`] learns when samples arrive (the last arrival plus the stream's measured
//!   period, [`Arrivals`]) and parks on the event (precisely: `ppoll`, timer slack 1 µs) until
//!   `3/4 spin` before the next one is due, spins at most `spin` around it, then parks on the event
//!   until the deadline. A periodic stream's sample
//!   lands in the window and is taken at busy-poll latency for `spin / period` of a core (1.2 % at
//!   60 Hz and 200 µs); a sample outside it wakes the park as the event strategy would. The spin is
//!   bounded: one window per due sample, however often the caller waits.
//!
//! None of them allocates or locks (iceoryx2's `ipc::Service` ports are single-threaded: their guard
//! is not a mutex); the event is drained before spinning, so wake-ups the spin made unnecessary do
//! not pile up in the listener.

use lungdyn_scene::wake::WakeMode;
use thiserror::Error;

/// How an [`crate::iox::Inlet`] waits (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Wake {
    /// Sleep on the event.
    #[default]
    Event,
    /// Park until the next sample is due, spin `spin_ns` around it, park again.
    SpinThenPark {
        /// The spin window, ns.
        spin_ns: u64,
    },
    /// Spin until a sample or the deadline.
    BusyPoll,
}

impl Wake {
    /// The strategy's scene name.
    pub fn mode(self) -> WakeMode {
        match self {
            Wake::Event => WakeMode::Event,
            Wake::SpinThenPark { .. } => WakeMode::SpinThenPark,
            Wake::BusyPoll => WakeMode::BusyPoll,
        }
    }
}

impl std::fmt::Display for Wake {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Wake::SpinThenPark { spin_ns } => {
                write!(f, "spin-then-park ({} µs window)", spin_ns / 1000)
            }
            w => f.write_str(w.mode().name()),
        }
    }
}

/// With `auto`, spin-then-park from this many cores on (below it, the three processes and the
/// GPU driver's threads already contend for the cores and a spin would take time from them).
pub const SPIN_MIN_CORES: usize = 4;

/// The strategy a process runs, and the one line that says why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Choice {
    /// The strategy.
    pub wake: Wake,
    /// "busy-poll (auto: core 2 is reserved for it by [processes] cpus)", ...
    pub line: String,
}

/// What a process knows when it chooses: the scene's wish and where it runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Placement {
    /// The core the process is pinned to (`--cpu`).
    pub pinned: Option<usize>,
    /// The core the scene's `[processes] cpus` gives this process alone (none when unpinned or
    /// shared with another lungdyn process).
    pub reserved: Option<usize>,
    /// Cores the machine has online.
    pub cores: usize,
    /// Whether the process's own core is isolated from other tasks (`isolcpus`): without it the
    /// scheduler shares the core with whatever else runs, and a busy-poll loses its slices to them.
    pub isolated: bool,
}

impl Placement {
    /// The core the process runs on alone: pinned where the scene reserves a core for it.
    pub fn own_core(&self) -> Option<usize> {
        self.reserved.filter(|&r| self.pinned == Some(r))
    }
}

/// A wake strategy the process cannot run where it is.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum WakeError {
    /// busy-poll, but not on a core the scene reserves for this process.
    #[error(
        "{role}: [processes] wake = \"busy-poll\" needs the process pinned to a core [processes] cpus \
         reserves for it alone, but {where_}; pin it there (`--cpu N`, as `lungdyn demo` does) or use \
         \"spin-then-park\""
    )]
    BusyPollWithoutCore {
        /// Process role.
        role: String,
        /// Where it runs instead, in words.
        where_: String,
    },
}

/// Cores online on this machine (not this process's affinity, which pinning narrows to one).
pub fn machine_cores() -> usize {
    // SAFETY: sysconf has no preconditions.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_ONLN) };
    usize::try_from(n).unwrap_or(1).max(1)
}

/// Resolve the scene's `asked` mode for process `role` at `at`: `auto` becomes busy-poll on the
/// process's own isolated core, spin-then-park on its own core otherwise or from
/// [`SPIN_MIN_CORES`] cores, the event otherwise; an explicit busy-poll off a reserved core is
/// refused (on one that is not isolated it runs, with a warning in the line).
pub fn choose(
    role: &str,
    asked: WakeMode,
    spin_us: u32,
    at: Placement,
) -> Result<Choice, WakeError> {
    let spin = Wake::SpinThenPark {
        spin_ns: u64::from(spin_us.max(1)) * 1000,
    };
    let (wake, why) = match asked {
        WakeMode::Event => (Wake::Event, "the scene's [processes] wake".to_string()),
        WakeMode::SpinThenPark => (spin, "the scene's [processes] wake".to_string()),
        WakeMode::BusyPoll => match at.own_core() {
            Some(c) if at.isolated => (
                Wake::BusyPoll,
                format!("the scene's [processes] wake, on core {c} reserved for it and isolated"),
            ),
            Some(c) => (
                Wake::BusyPoll,
                format!(
                    "the scene's [processes] wake, on core {c} reserved for it; warning: core {c} \
                     is not isolated (isolcpus), other tasks still get slices of it and the hop \
                     waits for them; `lungdyn doctor` says how to isolate it"
                ),
            ),
            None => {
                let where_ = match (at.pinned, at.reserved) {
                    (_, None) => "the scene's cpus reserve no core for it alone".to_string(),
                    (None, Some(r)) => format!("it is not pinned (the scene reserves core {r})"),
                    (Some(p), Some(r)) => {
                        format!("it is pinned to core {p}, the scene reserves core {r}")
                    }
                };
                return Err(WakeError::BusyPollWithoutCore {
                    role: role.to_string(),
                    where_,
                });
            }
        },
        WakeMode::Auto => match at.own_core() {
            Some(c) if at.isolated => (
                Wake::BusyPoll,
                format!("auto: core {c} is reserved for it by [processes] cpus and isolated"),
            ),
            Some(c) => (
                spin,
                format!(
                    "auto: core {c} is reserved for it by [processes] cpus but not isolated \
                     (isolcpus); busy-poll on an isolated one"
                ),
            ),
            None if at.cores >= SPIN_MIN_CORES => (
                spin,
                format!(
                    "auto: {} cores, none reserved for it; busy-poll on a core [processes] cpus \
                     reserves",
                    at.cores
                ),
            ),
            None => (
                Wake::Event,
                format!(
                    "auto: {} core{}, none reserved for it; spin-then-park from {SPIN_MIN_CORES} \
                     cores, busy-poll on a core [processes] cpus reserves",
                    at.cores,
                    if at.cores == 1 { "" } else { "s" }
                ),
            ),
        },
    };
    Ok(Choice {
        wake,
        line: format!("{wake} ({why})"),
    })
}

/// [`choose`] for process `role` of `instance` on this machine's cores, and say the choice on stderr
/// in one line ("engine[demo-1]: waits for tracker frames by event (auto: 2 cores, ...)").
pub fn announce(
    role: &str,
    instance: &str,
    what: &str,
    asked: WakeMode,
    spin_us: u32,
    pinned: Option<usize>,
    reserved: Option<usize>,
) -> Result<Wake, WakeError> {
    let at = Placement {
        pinned,
        reserved,
        cores: machine_cores(),
        isolated: pinned.is_some_and(|c| crate::process::isolated_cores().contains(&c)),
    };
    let c = choose(role, asked, spin_us, at)?;
    crate::process::say(&format!(
        "{role}[{instance}]: waits for {what} by {}",
        c.line
    ));
    Ok(c.wake)
}

/// When a periodic stream's samples arrive, learned from the arrivals themselves (no assumption of
/// the producer's rate): the period is an average of the intervals near it, so a lost sample (a
/// double interval) or a burst does not move it; four intervals in a row far from it (the producer
/// changed its rate) replace it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Arrivals {
    last_ns: u64,
    period_ns: u64,
    off_band: u32,
    spun_due_ns: u64,
}

/// Where to spin for the next sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// When the next sample is due, ns.
    pub due_ns: u64,
    /// Start spinning, ns.
    pub from_ns: u64,
    /// Stop spinning, ns.
    pub until_ns: u64,
}

impl Arrivals {
    /// A sample arrived at `at_ns`.
    pub fn observe(&mut self, at_ns: u64) {
        if self.last_ns != 0 && at_ns > self.last_ns {
            let dt = at_ns - self.last_ns;
            let p = self.period_ns;
            if p == 0 || self.off_band >= 3 {
                self.period_ns = dt;
                self.off_band = 0;
            } else if dt >= p / 2 && dt <= p + p / 2 {
                // An exponential average with weight 1/8: jitter moves it little.
                self.period_ns = p - p / 8 + dt / 8;
                self.off_band = 0;
            } else {
                self.off_band += 1;
            }
        }
        self.last_ns = at_ns;
    }

    /// The measured period, ns (0 until two samples arrived).
    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// The window of `spin_ns` around the next due sample, three quarters of it before: an arrival
    /// taken from a park is noted a wake-up late, so the due time leans late, and the park that
    /// starts the window may itself wake late by the timer's slack. `None` until the period is
    /// known, and once that sample's window was spun ([`Self::spun`]).
    pub fn window(&self, spin_ns: u64) -> Option<Window> {
        if self.period_ns == 0 {
            return None;
        }
        let due_ns = self.last_ns + self.period_ns;
        (due_ns != self.spun_due_ns).then(|| Window {
            due_ns,
            from_ns: due_ns.saturating_sub(spin_ns - spin_ns / 4),
            until_ns: due_ns + spin_ns / 4,
        })
    }

    /// The window of the sample due at `due_ns` was spun: the next wait parks.
    pub fn spun(&mut self, due_ns: u64) {
        self.spun_due_ns = due_ns;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: u64 = 16_666_667;

    fn at(pinned: Option<usize>, reserved: Option<usize>, cores: usize) -> Placement {
        Placement {
            pinned,
            reserved,
            cores,
            isolated: true,
        }
    }

    #[test]
    fn auto_busy_polls_only_on_a_reserved_isolated_core_and_spins_only_with_cores_to_spare() {
        let c = choose("engine", WakeMode::Auto, 200, at(Some(2), Some(2), 2)).unwrap();
        assert_eq!(c.wake, Wake::BusyPoll);
        assert!(c.line.contains("core 2 is reserved"), "{}", c.line);
        // Reserved but shared with the scheduler's other tasks: a bounded spin, not a whole core.
        let shared = Placement {
            isolated: false,
            ..at(Some(2), Some(2), 2)
        };
        let c = choose("engine", WakeMode::Auto, 200, shared).unwrap();
        assert_eq!(c.wake, Wake::SpinThenPark { spin_ns: 200_000 });
        assert!(c.line.contains("but not isolated"), "{}", c.line);
        // Asked for explicitly it runs, with a warning in its line.
        let c = choose("engine", WakeMode::BusyPoll, 200, shared).unwrap();
        assert_eq!(c.wake, Wake::BusyPoll);
        assert!(
            c.line.contains("warning: core 2 is not isolated"),
            "{}",
            c.line
        );
        // Reserved by the scene but the process runs elsewhere (or nowhere in particular).
        for p in [
            at(None, Some(2), 2),
            at(Some(1), Some(2), 2),
            at(Some(1), None, 2),
        ] {
            let c = choose("engine", WakeMode::Auto, 200, p).unwrap();
            assert_eq!(c.wake, Wake::Event, "{p:?}");
            assert!(c.line.starts_with("event (auto: 2 cores"), "{}", c.line);
        }
        let c = choose("engine", WakeMode::Auto, 200, at(None, None, 1)).unwrap();
        assert!(c.line.contains("auto: 1 core,"), "{}", c.line);
        let c = choose("renderer", WakeMode::Auto, 150, at(None, None, 8)).unwrap();
        assert_eq!(c.wake, Wake::SpinThenPark { spin_ns: 150_000 });
        assert_eq!(
            c.line,
            "spin-then-park (150 µs window) (auto: 8 cores, none reserved for it; busy-poll on a \
             core [processes] cpus reserves)"
        );
    }

    #[test]
    fn an_explicit_strategy_is_kept_and_busy_poll_off_its_core_is_refused() {
        let p = at(None, None, 2);
        assert_eq!(
            choose("engine", WakeMode::Event, 200, p).unwrap().wake,
            Wake::Event
        );
        assert_eq!(
            choose("engine", WakeMode::SpinThenPark, 200, p)
                .unwrap()
                .wake,
            Wake::SpinThenPark { spin_ns: 200_000 }
        );
        assert_eq!(
            choose("engine", WakeMode::BusyPoll, 200, at(Some(3), Some(3), 4))
                .unwrap()
                .wake,
            Wake::BusyPoll
        );
        for (p, needle) in [
            (at(None, None, 8), "reserve no core for it alone"),
            (
                at(None, Some(3), 8),
                "it is not pinned (the scene reserves core 3)",
            ),
            (
                at(Some(1), Some(3), 8),
                "pinned to core 1, the scene reserves core 3",
            ),
        ] {
            let e = choose("renderer", WakeMode::BusyPoll, 200, p)
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with("renderer: [processes] wake = \"busy-poll\""),
                "{e}"
            );
            assert!(e.contains(needle), "{e}");
        }
    }

    #[test]
    fn arrivals_learn_the_period_and_ignore_gaps_and_bursts() {
        let mut a = Arrivals::default();
        assert_eq!(a.window(200_000), None, "nothing known yet");
        a.observe(1_000);
        assert_eq!(a.window(200_000), None, "one sample: no period");
        for k in 1..=20u64 {
            // ±30 µs of jitter around a 60 Hz schedule.
            let jitter = if k % 2 == 0 { 30_000 } else { 0 };
            a.observe(1_000 + k * P + jitter);
        }
        let p = a.period_ns();
        assert!(p.abs_diff(P) < 30_000, "{p}");
        // A lost sample (a double interval) and a burst (a tiny one) leave the period alone.
        let last = 1_000 + 20 * P;
        a.observe(last + 2 * P);
        a.observe(last + 2 * P + 1_000);
        assert_eq!(a.period_ns(), p);
        // The window is on the next due sample, three quarters before it, bounded by the spin.
        let w = a.window(200_000).unwrap();
        assert_eq!(w.due_ns, last + 2 * P + 1_000 + p);
        assert_eq!(
            (w.from_ns, w.until_ns),
            (w.due_ns - 150_000, w.due_ns + 50_000)
        );
        // Spun once: no second window for the same sample.
        a.spun(w.due_ns);
        assert_eq!(a.window(200_000), None);
        // The producer halves its rate: four long intervals in a row re-learn the period.
        let mut t = last + 2 * P + 1_000;
        for _ in 0..4 {
            t += 2 * P;
            a.observe(t);
        }
        assert_eq!(a.period_ns(), 2 * P);
        assert_eq!(
            a.window(1).unwrap().due_ns,
            t + 2 * P,
            "a new sample: a new window"
        );
    }
}
