//! systemd service notifications (`sd_notify(3)` through the `sd-notify` crate): READY=1 once a
//! process's ports are open, WATCHDOG=1 from the loop that would hang.
//!
//! Under a unit with `Type=notify` and `WatchdogSec=`, systemd sets `NOTIFY_SOCKET`, `WATCHDOG_USEC`
//! and `WATCHDOG_PID`; a process that stops pinging for `WatchdogSec` is killed (SIGABRT) and, with
//! `Restart=on-failure`, started again. Outside systemd every call here is a no-op.
//!
//! [`Watchdog::ping`] is called every tick or frame: it compares the time with its next deadline and
//! only every `WatchdogSec / 2` sends a datagram (the crate formats the message and opens a socket for
//! it, so that one call allocates — twice a `WatchdogSec`, never per tick). A send that fails (systemd
//! gone) is not retried until the next deadline and never stops the loop.

/// The watchdog pinger of one process loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Watchdog {
    /// Ping interval (half the watchdog timeout), ns; `None`: no watchdog asked for.
    every_ns: Option<u64>,
    next_ns: u64,
}

impl Watchdog {
    /// The watchdog systemd asked this process for (`WATCHDOG_USEC`, when `WATCHDOG_PID` is unset or
    /// this process): pings every half of it. Disabled otherwise.
    pub fn from_env() -> Self {
        Self::every(sd_notify::watchdog_enabled().map(|d| d.as_nanos() as u64 / 2))
    }

    /// A watchdog pinging every `every_ns` (at least 1 ns), or none.
    pub fn every(every_ns: Option<u64>) -> Self {
        Self {
            every_ns: every_ns.map(|e| e.max(1)),
            next_ns: 0,
        }
    }

    /// Whether pings are sent.
    pub fn enabled(&self) -> bool {
        self.every_ns.is_some()
    }

    /// Call from the loop each tick: sends WATCHDOG=1 when the interval has passed since the last
    /// one (the first call sends at once). Returns whether it sent.
    #[inline]
    pub fn ping(&mut self, now_ns: u64) -> bool {
        match self.every_ns {
            Some(every) if now_ns >= self.next_ns => {
                self.next_ns = now_ns.saturating_add(every);
                let _ = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]);
                true
            }
            _ => false,
        }
    }
}

/// Tell systemd the process is ready (its ports are open) with a one-line status (`systemctl status`
/// shows it). A no-op outside systemd; a failure to send is reported on stderr once, not fatal.
pub fn ready(status: &str) {
    if let Err(e) = sd_notify::notify(&[
        sd_notify::NotifyState::Ready,
        sd_notify::NotifyState::Status(status),
    ]) {
        eprintln!("lungdyn: cannot notify systemd of readiness ({e}); the unit will time out");
    }
}

/// Tell systemd the process is stopping (a clean exit, not a hang).
pub fn stopping() {
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pings_only_once_per_interval_and_never_without_a_watchdog() {
        let mut w = Watchdog::every(Some(100));
        assert!(w.enabled());
        assert!(w.ping(5), "the first call pings");
        assert!(!w.ping(6));
        assert!(!w.ping(104));
        assert!(w.ping(105));
        assert!(!w.ping(204));
        // A loop that stalled past several intervals pings once when it resumes.
        assert!(w.ping(10_000));
        assert!(!w.ping(10_001));
        assert!(w.ping(u64::MAX), "no overflow at the end of time");
        let mut off = Watchdog::every(None);
        assert!(!off.enabled());
        assert!(!off.ping(0) && !off.ping(u64::MAX));
        assert!(Watchdog::every(Some(0)).ping(0));
    }
}
