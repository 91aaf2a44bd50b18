//! The hand-over from Zenoh's threads to a worker, with an optional emulated impairment.
//!
//! A Zenoh callback copies the payload and its arrival time into a bounded channel (never
//! blocking Zenoh: a full channel drops and counts). The worker delivers each packet to its
//! handler at `arrival + delay ± jitter` (uniform), dropping a share `loss` first — the harness's
//! network emulation when netem in network namespaces is not used (see `harness`).

use std::collections::BinaryHeap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::time::Duration;

use rand::{RngExt, SeedableRng};
use rand_xorshift::XorShiftRng;
use transport::clock::now_ns;

use crate::clock::LocalClock;

/// An emulated path: one-way delay, uniform jitter, loss probability.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Impairment {
    /// Mean one-way delay, ms.
    pub delay_ms: f64,
    /// Jitter: the delay is uniform in `delay ± jitter`, ms.
    pub jitter_ms: f64,
    /// Probability a packet is lost, 0..1.
    pub loss: f64,
    /// Seed of the emulation's random numbers.
    pub seed: u64,
    /// The receiving participant's clock: the host's, or (the harness's `--skew-ppm`, tests) one
    /// running at 1 + r. The handler's arrival stamps are on it; the participant stamps with it.
    pub clock: LocalClock,
    /// Compare with the estimator before: fit the clock rate but never apply it (the harness's
    /// `--no-clock-rate`).
    pub no_rate: bool,
}

impl Impairment {
    /// Check the values (finite, non-negative, jitter ≤ delay, loss < 1).
    pub fn check(&self) -> Result<(), String> {
        let ok = |v: f64| v.is_finite() && v >= 0.0;
        if !(ok(self.delay_ms) && ok(self.jitter_ms) && self.delay_ms <= 60_000.0) {
            return Err(format!(
                "--delay-ms {} / --jitter-ms {}: use finite values from 0 to 60000 ms",
                self.delay_ms, self.jitter_ms
            ));
        }
        if self.jitter_ms > self.delay_ms {
            return Err(format!(
                "--jitter-ms {} exceeds --delay-ms {}: a packet cannot arrive before it is sent",
                self.jitter_ms, self.delay_ms
            ));
        }
        if !(self.loss.is_finite() && (0.0..1.0).contains(&self.loss)) {
            return Err(format!(
                "--loss {}: use a probability from 0 to below 1",
                self.loss
            ));
        }
        Ok(())
    }

    /// No delay, jitter or loss (the clock aside).
    fn none(&self) -> bool {
        self.delay_ms == 0.0 && self.jitter_ms == 0.0 && self.loss == 0.0
    }
}

/// What a link did.
#[derive(Debug, Default)]
pub struct LinkCounts {
    /// Packets Zenoh handed over.
    pub arrived: AtomicU64,
    /// Dropped because the worker was behind (channel full).
    pub overflow: AtomicU64,
    /// Dropped by the emulated loss.
    pub lost: AtomicU64,
    /// Delivered to the handler.
    pub delivered: AtomicU64,
}

/// The Zenoh side of a link: hand a payload over.
#[derive(Clone)]
pub struct LinkIn {
    tx: SyncSender<(u64, Vec<u8>)>,
    counts: Arc<LinkCounts>,
}

impl LinkIn {
    /// Hand `bytes` (arrived now) to the worker; never blocks.
    pub fn push(&self, bytes: Vec<u8>) {
        self.counts.arrived.fetch_add(1, Ordering::Relaxed);
        match self.tx.try_send((now_ns(), bytes)) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.counts.overflow.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// The link's counters.
    pub fn counts(&self) -> &Arc<LinkCounts> {
        &self.counts
    }
}

/// Start a link's worker thread `name`: `handler(bytes, delivered_at_ns)` runs on it for every
/// packet, after the impairment (the time on `imp.clock`). The worker ends when every [`LinkIn`] is dropped.
pub fn start<F>(name: &str, imp: Impairment, mut handler: F) -> LinkIn
where
    F: FnMut(Vec<u8>, u64) + Send + 'static,
{
    let (tx, rx) = sync_channel::<(u64, Vec<u8>)>(1024);
    let counts = Arc::new(LinkCounts::default());
    let c = counts.clone();
    std::thread::Builder::new()
        .name(name.to_string())
        .spawn(move || run(rx, imp, &c, &mut handler))
        .expect("spawn a link worker");
    LinkIn { tx, counts }
}

fn run<F: FnMut(Vec<u8>, u64)>(
    rx: Receiver<(u64, Vec<u8>)>,
    imp: Impairment,
    counts: &LinkCounts,
    handler: &mut F,
) {
    let mut rng = XorShiftRng::seed_from_u64(imp.seed ^ 0x5eed);
    // Min-heap on delivery time (then arrival order).
    let mut held: BinaryHeap<core::cmp::Reverse<(u64, u64, Vec<u8>)>> = BinaryHeap::new();
    let mut order = 0u64;
    loop {
        let now = now_ns();
        while held.peek().is_some_and(|r| r.0 .0 <= now) {
            if let Some(core::cmp::Reverse((at, _, bytes))) = held.pop() {
                counts.delivered.fetch_add(1, Ordering::Relaxed);
                handler(bytes, imp.clock.of(at.max(now)));
            }
        }
        let wait = held
            .peek()
            .map(|r| Duration::from_nanos(r.0 .0.saturating_sub(now)))
            .unwrap_or(Duration::from_millis(100));
        match rx.recv_timeout(wait) {
            Ok((at, bytes)) => {
                if imp.none() {
                    counts.delivered.fetch_add(1, Ordering::Relaxed);
                    handler(bytes, imp.clock.of(at));
                    continue;
                }
                if imp.loss > 0.0 && rng.random::<f64>() < imp.loss {
                    counts.lost.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let j = if imp.jitter_ms > 0.0 {
                    rng.random_range(-imp.jitter_ms..=imp.jitter_ms)
                } else {
                    0.0
                };
                let d = ((imp.delay_ms + j) * 1e6).max(0.0) as u64;
                order += 1;
                held.push(core::cmp::Reverse((at + d, order, bytes)));
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => {
                if held.is_empty() {
                    return;
                }
                std::thread::sleep(wait);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn delay_jitter_and_loss_are_applied() {
        let got = Arc::new(Mutex::new(Vec::new()));
        let g = got.clone();
        let imp = Impairment {
            delay_ms: 20.0,
            jitter_ms: 5.0,
            loss: 0.1,
            seed: 1,
            ..Default::default()
        };
        imp.check().unwrap();
        let link = start("test-link", imp, move |b, at| {
            g.lock().unwrap().push((b[0], at));
        });
        let mut sent = Vec::new();
        for k in 0..200u8 {
            sent.push(now_ns());
            link.push(vec![k]);
            std::thread::sleep(Duration::from_micros(500));
        }
        std::thread::sleep(Duration::from_millis(150));
        let got = got.lock().unwrap();
        let lost = link.counts().lost.load(Ordering::Relaxed) as usize;
        assert_eq!(got.len() + lost, 200);
        assert!((5..=40).contains(&lost), "{lost} of 200 lost at 10 %");
        let mut delays: Vec<f64> = got
            .iter()
            .map(|(k, at)| (*at - sent[*k as usize]) as f64 / 1e6)
            .collect();
        for (d, (k, _)) in delays.iter().zip(got.iter()) {
            // Never early; late only by the scheduler (a loaded 2-core machine stalled one packet
            // 51 ms once, so no packet's lateness is held against a wall clock here).
            assert!(*d >= 14.9 && *d < 1000.0, "packet {k}: {d} ms");
        }
        // The delay and jitter as set (20 ± 5 ms): the median, which one stall does not move.
        delays.sort_by(f64::total_cmp);
        let median = delays[delays.len() / 2];
        assert!((17.0..=30.0).contains(&median), "median delay {median} ms");
    }

    #[test]
    fn bad_impairments_are_refused_with_the_option_named() {
        for (imp, word) in [
            (
                Impairment {
                    delay_ms: f64::NAN,
                    ..Default::default()
                },
                "--delay-ms",
            ),
            (
                Impairment {
                    delay_ms: 5.0,
                    jitter_ms: 6.0,
                    ..Default::default()
                },
                "exceeds",
            ),
            (
                Impairment {
                    loss: 1.0,
                    ..Default::default()
                },
                "--loss",
            ),
            (
                Impairment {
                    loss: -0.1,
                    ..Default::default()
                },
                "--loss",
            ),
        ] {
            let e = imp.check().unwrap_err();
            assert!(e.contains(word), "{e}");
        }
    }
}
