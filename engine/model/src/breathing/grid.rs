//! The samples on a uniform grid at the source's own period.
//!
//! Sources deliver at 25–50 Hz with jitter (an RPM export's timestamps, a ventilator's 50 Hz, a
//! tracker's 60 Hz), and the predictors and the breath detector want evenly spaced values. Each
//! sample adds the grid points between the previous sample and itself, linearly interpolated; a
//! grid point is never placed after the newest sample (nothing reads ahead of the sample clock).
//! A sample at or before the previous one is refused (a repeat or a reordering), and a gap longer
//! than `max_gap_ns` restarts the grid at the new sample: a loss is not bridged by a straight line.

use super::Ring;

/// Grid points kept: 1024 (20 s at 50 Hz, 41 s at 25 Hz): the previous-cycle predictor searches
/// back 12 s, the others read a few points, the prediction guard the range.
pub const GRID_LEN: usize = 1024;

/// What [`Grid::begin`] made of a sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrival {
    /// The sample follows the previous one: step the grid with [`Grid::step`].
    Follows,
    /// The first sample, or the first after a gap longer than the limit: the grid starts again
    /// with this one point.
    Restarted,
    /// At or before the previous sample's time: refused.
    NotNewer,
}

/// Uniformly resampled signal.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    period_ns: u64,
    max_gap_ns: u64,
    values: Ring<f64, GRID_LEN>,
    newest_ns: u64,
    last: Option<(u64, f64)>,
    pending: Option<(u64, f64)>,
}

impl Grid {
    /// A grid at `period_ns` (> 0) that restarts after gaps longer than `max_gap_ns`.
    pub fn new(period_ns: u64, max_gap_ns: u64) -> Self {
        Self {
            period_ns: period_ns.max(1),
            max_gap_ns,
            values: Ring::default(),
            newest_ns: 0,
            last: None,
            pending: None,
        }
    }

    /// The grid period, ns.
    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// Begin taking sample `(t_ns, v)`; after [`Arrival::Follows`] call [`Grid::step`] until it
    /// returns false (each `true` is one new grid point the caller may learn from).
    pub fn begin(&mut self, t_ns: u64, v: f64) -> Arrival {
        match self.last {
            Some((t0, _)) if t_ns <= t0 => Arrival::NotNewer,
            Some((t0, _)) if t_ns - t0 <= self.max_gap_ns => {
                self.pending = Some((t_ns, v));
                Arrival::Follows
            }
            _ => {
                self.values.clear();
                self.values.push(v);
                self.newest_ns = t_ns;
                self.last = Some((t_ns, v));
                self.pending = None;
                Arrival::Restarted
            }
        }
    }

    /// Add the next grid point towards the pending sample; false when none is due (the pending
    /// sample then becomes the newest raw sample).
    pub fn step(&mut self) -> bool {
        let (Some((t1, v1)), Some((t0, v0))) = (self.pending, self.last) else {
            return false;
        };
        let next = self.newest_ns.saturating_add(self.period_ns);
        if next > t1 {
            self.last = Some((t1, v1));
            self.pending = None;
            return false;
        }
        let f = (next - t0) as f64 / (t1 - t0) as f64;
        self.values.push(v0 + (v1 - v0) * f);
        self.newest_ns = next;
        true
    }

    /// Forget everything.
    pub fn reset(&mut self) {
        *self = Self::new(self.period_ns, self.max_gap_ns);
    }

    /// Grid points held.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// No grid point yet.
    pub fn is_empty(&self) -> bool {
        self.values.len() == 0
    }

    /// The `k`-th newest grid value (0: the newest).
    pub fn back(&self, k: usize) -> Option<f64> {
        self.values.back(k)
    }

    /// Time of the newest grid point, ns.
    pub fn newest_ns(&self) -> u64 {
        self.newest_ns
    }

    /// The newest raw sample (time, value).
    pub fn last_sample(&self) -> Option<(u64, f64)> {
        self.last
    }

    /// Smallest and largest grid value held.
    pub fn range(&self) -> Option<(f64, f64)> {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for k in 0..self.values.len() {
            let v = self.values.back(k).expect("k < len");
            lo = lo.min(v);
            hi = hi.max(v);
        }
        (lo <= hi).then_some((lo, hi))
    }
}
