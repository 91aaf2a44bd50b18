//! Stop requests, latched: SIGTERM, SIGINT and SIGHUP set one flag that no later signal clears.
//!
//! iceoryx2's own signal handling (a node's default `SignalHandlingMode::HandleTerminationRequests`)
//! keeps only the *last* signal it caught, SIGCONT, SIGTSTP and others included, and forgets it once
//! asked. A SIGCONT caught after a SIGTERM replaced the request before the loop looked, and the
//! process ran on until something killed it — and `systemctl stop` sends exactly that, SIGTERM then
//! SIGCONT (so does any stop of a SIGSTOPped process). So every node is created with iceoryx2's
//! handling disabled ([`crate::iox::node`]; no iceoryx2 handler is installed then) and each
//! process's loop asks [`requested`] instead, after [`install`] at its start.
//!
//! The handlers are `signal-hook`'s: each stop signal stores its number into one shared atomic,
//! nothing else does, so a stop once requested stays requested. Signals not listed keep their
//! default action: SIGCONT and SIGCHLD change nothing, SIGTSTP (Ctrl-Z) stops the process and SIGQUIT
//! quits it, as in any other program.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use crate::port::PortError;

/// The signals that ask a process to stop (and are latched).
pub const STOP_SIGNALS: [libc::c_int; 3] = [libc::SIGTERM, libc::SIGINT, libc::SIGHUP];

/// The last stop signal caught (0: none yet). Only the handlers of [`STOP_SIGNALS`] write it.
static REQUEST: OnceLock<Arc<AtomicUsize>> = OnceLock::new();

fn request() -> &'static Arc<AtomicUsize> {
    REQUEST.get_or_init(|| Arc::new(AtomicUsize::new(0)))
}

/// Install the handlers of [`STOP_SIGNALS`] (once per process; later calls do nothing). Call it
/// first thing in a process's run: a stop asked for while it starts is then kept for its loop's
/// first look, where before it the signal's default action ends the process at once.
pub fn install() -> Result<(), PortError> {
    static INSTALLED: Mutex<bool> = Mutex::new(false);
    let mut installed = INSTALLED.lock().unwrap_or_else(|e| e.into_inner());
    if !*installed {
        for sig in STOP_SIGNALS {
            signal_hook::flag::register_usize(sig, Arc::clone(request()), sig as usize).map_err(
                |source| PortError::Signals {
                    signal: sig,
                    source,
                },
            )?;
        }
        *installed = true;
    }
    Ok(())
}

/// The stop signal caught (the last one, when several were), or `None` while none was: one atomic
/// load, no allocation or lock, fit for every pass of a loop.
pub fn signal() -> Option<libc::c_int> {
    match REQUEST.get()?.load(Ordering::Relaxed) {
        0 => None,
        sig => Some(sig as libc::c_int),
    }
}

/// Whether a stop was requested (a stop signal was caught since [`install`]); once true, true for
/// the rest of the process.
pub fn requested() -> bool {
    signal().is_some()
}

/// Sleep up to `period` (a stop signal ends the sleep early); false when a stop was requested,
/// before or during the sleep. Any other signal changes nothing.
pub fn idle(period: std::time::Duration) -> bool {
    if requested() {
        return false;
    }
    crate::clock::sleep_until_ns(crate::clock::now_ns().saturating_add(period.as_nanos() as u64));
    !requested()
}

/// The name of a stop signal, for messages ("SIGTERM").
pub fn name(sig: libc::c_int) -> &'static str {
    match sig {
        libc::SIGTERM => "SIGTERM",
        libc::SIGINT => "SIGINT",
        libc::SIGHUP => "SIGHUP",
        _ => "a signal",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One test (the flag is the process's): a stop signal latches, and SIGCONT, SIGCHLD and another
    /// stop signal after it leave it set.
    #[test]
    fn a_stop_signal_latches_and_no_later_signal_clears_it() {
        assert!(!requested());
        install().unwrap();
        install().unwrap();
        assert!(!requested(), "installing requests nothing");
        // SIGCONT and SIGCHLD before any request: still none (their default actions do nothing
        // to a running process).
        // SAFETY: raise(3) delivers to this thread; the handlers only store to an atomic.
        unsafe {
            libc::raise(libc::SIGCONT);
            libc::raise(libc::SIGCHLD);
        }
        assert!(!requested());
        unsafe { libc::raise(libc::SIGTERM) };
        assert_eq!(signal(), Some(libc::SIGTERM));
        unsafe {
            libc::raise(libc::SIGCONT);
            libc::raise(libc::SIGCHLD);
        }
        assert_eq!(
            signal(),
            Some(libc::SIGTERM),
            "SIGCONT/SIGCHLD clear nothing"
        );
        assert!(requested(), "still requested when asked again");
        unsafe { libc::raise(libc::SIGHUP) };
        assert_eq!(signal(), Some(libc::SIGHUP));
        assert!(requested());
        assert_eq!(name(libc::SIGHUP), "SIGHUP");
    }
}
