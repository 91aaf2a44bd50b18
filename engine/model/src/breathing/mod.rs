//! Breathing with the patient (issue 35): a live respiratory signal — a chest marker's excursion,
//! an amplitude stream, a ventilator's volume — turned into the lungs' volume above FRC at the
//! moment a frame is shown.
//!
//! The seed placed its models over the patient simulator by hand and left "their dynamic
//! registration" to future work (§7.5); nothing here is the seed's. The pieces, each pure,
//! deterministic and free of allocation per sample (fixed rings; the engine's tick may call them):
//! * [`grid`] — the samples, stamped by their source, resampled onto a uniform grid at the source's
//!   own period (a gap longer than the loss limit restarts it: nothing is interpolated across a loss);
//! * [`predict`] — the signal at a later time: [`predict::SignalPredictor::Hold`] (no prediction,
//!   the baseline), a least-squares line, and an autoregressive model of the signal's velocity
//!   fitted online by recursive least squares (the family Ernst et al. 2013 and Sharp et al. 2004
//!   compare for respiratory motion; the choice is measured, see docs/BREATHING.md);
//! * [`detect`] — breaths found with hysteresis on the signal, the end-expiration baseline and its
//!   drift, and irregular breaths (sigh, cough, breath-hold, apnoea) flagged and kept out of the
//!   calibration;
//! * [`follow`] — the three together: samples in, `volume_at(now, display)` out, with the state a
//!   head-up display shows (calibrating, following, paused, lost);
//! * [`check`] — one file read as a trace and replayed at each latency with every predictor;
//! * [`evaluate`] — a recorded trace replayed as if live against its own hindsight volume: RMS error
//!   with and without prediction, end-inspiration lag, breaths detected.
//!
//! Times are nanoseconds on the host's monotonic clock (the tracker bridge's stamps); values are
//! in the signal's own unit until [`follow::Calibration`] turns them into ml.

pub mod check;
pub mod detect;
pub mod evaluate;
pub mod follow;
pub mod grid;
pub mod predict;
#[cfg(test)]
mod tests;
pub mod trace;

pub use follow::{Calibration, Followed, Follower, FollowerConfig, SignalState};
pub use predict::SignalPredictor;

/// One respiratory signal sample as its source stamped it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SignalSample {
    /// Capture time, ns, host monotonic clock.
    pub t_ns: u64,
    /// The signal, in its source's unit (mm of chest excursion, ml, a device's amplitude unit).
    pub value: f64,
    /// The source said the sample is good (an RPM valid flag, a tool's VALID bit).
    pub valid: bool,
}

/// Where a recorded trace's time starts on the replay clock: 1 s, so no stamp is 0.
pub const TRACE_START_NS: u64 = 1_000_000_000;

/// Nanoseconds to seconds.
pub(crate) fn secs(ns: i128) -> f64 {
    ns as f64 * 1e-9
}

/// The least-squares line through `points` (x, y): `(slope, intercept at x = 0)`; `None` where the
/// x do not spread (fewer than two distinct).
pub(crate) fn fit_line(points: impl Iterator<Item = (f64, f64)>) -> Option<(f64, f64)> {
    let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (x, y) in points {
        n += 1.0;
        sx += x;
        sy += y;
        sxx += x * x;
        sxy += x * y;
    }
    let den = n * sxx - sx * sx;
    if !(den > 0.0) {
        return None;
    }
    let slope = (n * sxy - sx * sy) / den;
    Some((slope, (sy - slope * sx) / n))
}

/// Median of up to a few values (copied: the rings are small), `None` when empty.
pub(crate) fn median_of(values: &[f64]) -> Option<f64> {
    let mut buf = [0.0f64; 16];
    let n = values.len().min(buf.len());
    if n == 0 {
        return None;
    }
    buf[..n].copy_from_slice(&values[..n]);
    let s = &mut buf[..n];
    s.sort_by(f64::total_cmp);
    Some(if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    })
}

/// A fixed ring of the last `N` values, oldest first when read (allocation-free: the detector's
/// typical breaths, a remote site's turn lags).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ring<T: Copy + Default, const N: usize> {
    items: [T; N],
    len: usize,
    head: usize,
}

impl<T: Copy + Default, const N: usize> Default for Ring<T, N> {
    fn default() -> Self {
        Self {
            items: [T::default(); N],
            len: 0,
            head: 0,
        }
    }
}

impl<T: Copy + Default, const N: usize> Ring<T, N> {
    /// Keep `v`, dropping the oldest when full.
    pub fn push(&mut self, v: T) {
        self.items[self.head] = v;
        self.head = (self.head + 1) % N;
        self.len = (self.len + 1).min(N);
    }
    /// Values kept (at most `N`).
    pub fn len(&self) -> usize {
        self.len
    }
    /// None kept yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// `k`-th newest (0: the newest).
    pub fn back(&self, k: usize) -> Option<T> {
        (k < self.len).then(|| self.items[(self.head + N - 1 - k) % N])
    }
    /// Copy out, oldest first, into `out` (at least `N` long); returns the count.
    pub(crate) fn copy_into(&self, out: &mut [T]) -> usize {
        for k in 0..self.len {
            out[self.len - 1 - k] = self.back(k).expect("k < len");
        }
        self.len
    }
    pub(crate) fn clear(&mut self) {
        self.len = 0;
        self.head = 0;
    }
}
