//! Time: the host's monotonic clock, and a fake one for tests.
//!
//! Every hop stamp and deadline in lungdyn is CLOCK_MONOTONIC nanoseconds, comparable across the
//! processes of one host. Loops that wait take a [`Clock`], so their deadline logic can be driven
//! by a [`FakeClock`] in tests instead of real time.

use std::cell::Cell;
use std::rc::Rc;

/// Monotonic nanoseconds, and sleeping on them: the one time trait every loop is written
/// against (the engine's and renderer's pacing, the bridge's schedule), so tests drive each on a
/// [`FakeClock`].
pub trait Clock {
    /// Now, ns.
    fn now_ns(&self) -> u64;
    /// Sleep until `deadline_ns` (absolute; returns at once when it has passed). A fake clock
    /// jumps there.
    fn sleep_until(&self, deadline_ns: u64);
}

/// The host's CLOCK_MONOTONIC.
#[derive(Debug, Clone, Copy, Default)]
pub struct Monotonic;

impl Clock for Monotonic {
    fn now_ns(&self) -> u64 {
        now_ns()
    }
    fn sleep_until(&self, deadline_ns: u64) {
        sleep_until_ns(deadline_ns);
    }
}

/// Monotonic time in nanoseconds (CLOCK_MONOTONIC), comparable across processes on one host.
#[inline]
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleep until the monotonic clock reaches `deadline_ns` (absolute), so periodic loops never drift;
/// returns early when a signal arrives.
pub fn sleep_until_ns(deadline_ns: u64) {
    let ts = libc::timespec {
        tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: plain syscall with a valid timespec. A signal (EINTR) ends the sleep early on
    // purpose, so the caller's loop sees a termination request promptly.
    unsafe {
        libc::clock_nanosleep(
            libc::CLOCK_MONOTONIC,
            libc::TIMER_ABSTIME,
            &ts,
            core::ptr::null_mut(),
        )
    };
}

/// A clock that moves only when told to: the test double for every waiting loop. Clones share
/// the same time, so a test ports and the loop under test see one clock.
#[derive(Debug, Clone, Default)]
pub struct FakeClock {
    now: Rc<Cell<u64>>,
}

impl FakeClock {
    /// A clock reading `start_ns`.
    pub fn at(start_ns: u64) -> Self {
        Self {
            now: Rc::new(Cell::new(start_ns)),
        }
    }

    /// Set the time (may jump forwards by any amount; never backwards, like CLOCK_MONOTONIC).
    pub fn set(&self, ns: u64) {
        assert!(ns >= self.now.get(), "a monotonic clock never goes back");
        self.now.set(ns);
    }

    /// Advance by `ns`.
    pub fn advance(&self, ns: u64) {
        self.now.set(self.now.get() + ns);
    }
}

impl Clock for FakeClock {
    fn now_ns(&self) -> u64 {
        self.now.get()
    }
    fn sleep_until(&self, deadline_ns: u64) {
        if deadline_ns > self.now.get() {
            self.now.set(deadline_ns);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_monotonic_clock_advances() {
        let a = now_ns();
        let b = Monotonic.now_ns();
        assert!(b >= a && a > 0);
    }

    #[test]
    fn fake_clock_clones_share_one_time() {
        let a = FakeClock::at(5);
        let b = a.clone();
        b.advance(10);
        assert_eq!(a.now_ns(), 15);
        a.set(100);
        assert_eq!(b.now_ns(), 100);
    }
}
