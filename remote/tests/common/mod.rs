//! Helpers shared by the remote crate's loopback and hostile tests.

use std::time::{Duration, Instant};

/// Wait (up to 30 s: slow starts on a loaded machine) until `ok`.
pub fn wait_for(what: &str, ok: impl Fn() -> bool) {
    let began = Instant::now();
    while !ok() {
        assert!(
            began.elapsed() < Duration::from_secs(30),
            "timed out waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}
