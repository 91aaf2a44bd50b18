//! The respiratory signal at a later time (the frame's display time).
//!
//! Four predictors, compared on real recordings by [`super::evaluate`] (docs/BREATHING.md):
//! * [`SignalPredictor::Hold`] — the newest sample, unchanged: no prediction, the baseline every
//!   other predictor must beat;
//! * [`SignalPredictor::Linear`] — a least-squares line through the newest grid points,
//!   extrapolated (Sharp et al. 2004's "linear prediction" at its simplest);
//! * [`SignalPredictor::Cycle`] — of the previous breath's course, the autoregression and none,
//!   the one that has lately predicted best at the expected latency;
//! * [`SignalPredictor::Ar`] — an autoregressive model of the signal's velocity (its first
//!   differences on the grid), its coefficients fitted online by recursive least squares with
//!   exponential forgetting, iterated to the horizon. It starts as constant velocity and learns the
//!   breath's curvature; the RLS family is among the predictors Ernst et al. 2013 compared on 304
//!   CyberKnife traces.
//!
//! All three are allocation-free. The autoregression is guarded: a prediction outside the held
//! signal's range widened by half of it (an unstable fit iterated) falls back to the line and
//! says so; its covariance stops growing in a flat signal (a breath-hold: no excitation), so an
//! hour's pause cannot overflow it.

use super::grid::Grid;

/// Largest autoregression order.
pub const MAX_ORDER: usize = 12;
/// Largest number of grid steps iterated (2 s at 50 Hz); beyond it the prediction holds.
pub const MAX_STEPS: usize = 100;
/// Bound on the covariance's trace: above it forgetting stops (no excitation to learn from).
const TRACE_MAX: f64 = 1e8;
/// The covariance a fresh fit starts from (normalised regressors: the differences over their
/// running mean magnitude).
const P0: f64 = 100.0;

/// A prediction and whether the guard replaced it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// Predicted signal, the source's unit.
    pub value: f64,
    /// The autoregression's value was out of range or not finite: this is the line's.
    pub fell_back: bool,
}

/// Which predictor, with its settings (what a scene or a command names).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PredictorKind {
    /// No prediction.
    Hold,
    /// Least-squares line through `window` grid points.
    Linear {
        /// Grid points fitted (≥ 2).
        window: usize,
    },
    /// Of three, the one that has predicted `horizon_ms` ahead best lately (mean squared error over
    /// ≈ 2 s of grid points): the previous breath's course (the lag at which the last second of
    /// signal best matches an earlier stretch, a breath period ago, and the change that followed
    /// there added to now: regular, ventilated breaths), the autoregression (spontaneous breaths
    /// whose timing varies), or none (a noisy signal, where extrapolation amplifies the noise).
    Cycle {
        /// The horizon the two are compared at, ms (the expected capture-to-display latency).
        horizon_ms: u32,
    },
    /// Autoregression of order `order` on the differences, forgetting factor `lambda`.
    Ar {
        /// Order, 1…[`MAX_ORDER`].
        order: usize,
        /// Forgetting factor per grid point, 0.9…1.
        lambda: f64,
    },
}

/// The default autoregression's order and forgetting factor.
const AR_ORDER: usize = 6;
const AR_LAMBDA: f64 = 0.998;

impl PredictorKind {
    /// The measured default (docs/BREATHING.md): order 6, λ = 0.998 (a memory of ≈ 500 grid points,
    /// 10 s at 50 Hz: two or three breaths).
    pub const DEFAULT: PredictorKind = PredictorKind::Ar {
        order: AR_ORDER,
        lambda: AR_LAMBDA,
    };

    /// The line the guard falls back to (and the linear predictor's default): 4 grid points.
    pub const LINE: PredictorKind = PredictorKind::Linear { window: 4 };

    /// Parse `none`, `linear`, `linear:W`, `ar`, `ar:ORDER` or `ar:ORDER:LAMBDA`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let mut parts = s.trim().split(':');
        let head = parts.next().unwrap_or("").to_ascii_lowercase();
        let rest: Vec<&str> = parts.collect();
        let num = |i: usize, what: &str| -> Result<Option<f64>, String> {
            rest.get(i)
                .map(|v| {
                    v.trim()
                        .parse::<f64>()
                        .ok()
                        .filter(|x| x.is_finite())
                        .ok_or_else(|| format!("predictor {s:?}: {what} {v:?} is not a number"))
                })
                .transpose()
        };
        let kind = match head.as_str() {
            "none" | "hold" if rest.is_empty() => PredictorKind::Hold,
            "cycle" if rest.len() <= 1 => {
                let h = num(0, "horizon")?.unwrap_or(100.0);
                if !(0.0..=2000.0).contains(&h) || h.fract() != 0.0 {
                    return Err(format!(
                        "predictor {s:?}: the horizon is a whole number of ms, 0…2000"
                    ));
                }
                PredictorKind::Cycle {
                    horizon_ms: h as u32,
                }
            }
            "linear" if rest.len() <= 1 => {
                let w = num(0, "window")?.unwrap_or(4.0);
                if !(2.0..=64.0).contains(&w) || w.fract() != 0.0 {
                    return Err(format!(
                        "predictor {s:?}: the line's window is a whole number of grid points, 2…64"
                    ));
                }
                PredictorKind::Linear { window: w as usize }
            }
            "ar" if rest.len() <= 2 => {
                let PredictorKind::Ar {
                    order: o0,
                    lambda: l0,
                } = Self::DEFAULT
                else {
                    unreachable!("the default is an autoregression")
                };
                let order = num(0, "order")?.unwrap_or(o0 as f64);
                let lambda = num(1, "forgetting factor")?.unwrap_or(l0);
                if !(1.0..=MAX_ORDER as f64).contains(&order) || order.fract() != 0.0 {
                    return Err(format!(
                        "predictor {s:?}: the order is a whole number, 1…{MAX_ORDER}"
                    ));
                }
                if !(0.9..=1.0).contains(&lambda) {
                    return Err(format!(
                        "predictor {s:?}: the forgetting factor is 0.9…1 (1: never forget)"
                    ));
                }
                PredictorKind::Ar {
                    order: order as usize,
                    lambda,
                }
            }
            _ => {
                return Err(format!(
                    "predictor {s:?} is not one of none, linear[:WINDOW], ar[:ORDER[:LAMBDA]], cycle[:HORIZON_MS]"
                ))
            }
        };
        Ok(kind)
    }

    /// A short name for tables.
    pub fn describe(self) -> String {
        match self {
            PredictorKind::Hold => "none (newest sample)".into(),
            PredictorKind::Linear { window } => format!("linear ({window} points)"),
            PredictorKind::Cycle { horizon_ms } => {
                format!("best lately at {horizon_ms} ms: cycle, AR or none")
            }
            PredictorKind::Ar { order, lambda } => {
                format!("autoregressive RLS (order {order}, lambda {lambda})")
            }
        }
    }
}

/// A predictor's state.
#[derive(Debug, Clone, PartialEq)]
pub enum SignalPredictor {
    /// See [`PredictorKind::Hold`].
    Hold,
    /// See [`PredictorKind::Linear`].
    Linear {
        /// Grid points fitted.
        window: usize,
    },
    /// See [`PredictorKind::Ar`].
    Ar(Box<ArRls>),
    /// See [`PredictorKind::Cycle`].
    Cycle(Box<CycleMatch>),
}

impl SignalPredictor {
    /// A fresh predictor of `kind`.
    pub fn new(kind: PredictorKind) -> Self {
        match kind {
            PredictorKind::Hold => SignalPredictor::Hold,
            PredictorKind::Linear { window } => SignalPredictor::Linear {
                window: window.clamp(2, 64),
            },
            PredictorKind::Ar { order, lambda } => {
                SignalPredictor::Ar(Box::new(ArRls::new(order, lambda)))
            }
            PredictorKind::Cycle { horizon_ms } => {
                SignalPredictor::Cycle(Box::new(CycleMatch::new(horizon_ms)))
            }
        }
    }

    /// A grid point was added (the grid's newest).
    pub fn learn(&mut self, grid: &Grid) {
        match self {
            SignalPredictor::Ar(ar) => ar.learn(grid),
            SignalPredictor::Cycle(c) => c.learn(grid),
            _ => {}
        }
    }

    /// The signal at `t_ns` (not before the newest grid point), `None` before any sample.
    pub fn predict(&self, grid: &Grid, t_ns: u64) -> Option<Prediction> {
        let plain = |value| Prediction {
            value,
            fell_back: false,
        };
        match self {
            SignalPredictor::Hold => grid.last_sample().map(|(_, v)| plain(v)),
            SignalPredictor::Linear { window } => line(grid, *window, t_ns).map(plain),
            SignalPredictor::Ar(ar) => ar.predict(grid, t_ns),
            SignalPredictor::Cycle(c) => c.predict(grid, t_ns),
        }
    }

    /// Forget what was learnt (a restart of the grid).
    pub fn reset(&mut self) {
        match self {
            SignalPredictor::Ar(ar) => **ar = ArRls::new(ar.order, ar.lambda),
            SignalPredictor::Cycle(c) => **c = CycleMatch::new(c.horizon_ms),
            _ => {}
        }
    }
}

/// Steps from the newest grid point to `t_ns`, ≥ 0.
fn steps_to(grid: &Grid, t_ns: u64) -> f64 {
    (t_ns.saturating_sub(grid.newest_ns())) as f64 / grid.period_ns() as f64
}

/// A least-squares line through the newest `window` grid points, at `t_ns`.
pub(super) fn line(grid: &Grid, window: usize, t_ns: u64) -> Option<f64> {
    let m = window.min(grid.len());
    if m == 0 {
        return None;
    }
    let newest = grid.back(0)?;
    if m == 1 {
        return Some(newest);
    }
    // x = −k for the k-th newest point.
    let points = (0..m).filter_map(|k| grid.back(k).map(|y| (-(k as f64), y)));
    let Some((slope, intercept)) = super::fit_line(points) else {
        return Some(newest);
    };
    let v = intercept + slope * steps_to(grid, t_ns);
    Some(if v.is_finite() { v } else { newest })
}

/// An autoregressive model of the grid's first differences, fitted by recursive least squares.
#[derive(Debug, Clone, PartialEq)]
pub struct ArRls {
    order: usize,
    lambda: f64,
    /// Coefficients: `d_k ≈ Σ a_i d_{k−i}`, i = 1…order.
    a: [f64; MAX_ORDER],
    /// Inverse correlation matrix (order × order used).
    p: [[f64; MAX_ORDER]; MAX_ORDER],
    /// Running mean magnitude of the differences (the regressors' scale).
    scale: f64,
    /// Grid points learnt from.
    learnt: u64,
}

impl ArRls {
    /// A fresh fit: constant velocity (`a₁ = 1`).
    pub fn new(order: usize, lambda: f64) -> Self {
        let order = order.clamp(1, MAX_ORDER);
        let mut p = [[0.0; MAX_ORDER]; MAX_ORDER];
        for (i, row) in p.iter_mut().enumerate().take(order) {
            row[i] = P0;
        }
        let mut a = [0.0; MAX_ORDER];
        a[0] = 1.0;
        Self {
            order,
            lambda: if lambda.is_finite() {
                lambda.clamp(0.9, 1.0)
            } else {
                1.0
            },
            a,
            p,
            scale: 0.0,
            learnt: 0,
        }
    }

    /// The coefficients fitted so far.
    pub fn coefficients(&self) -> &[f64] {
        &self.a[..self.order]
    }

    /// Grid points learnt from.
    pub fn learnt(&self) -> u64 {
        self.learnt
    }

    /// The newest `order + 1` differences, newest first, when the grid holds them.
    fn differences(&self, grid: &Grid) -> Option<[f64; MAX_ORDER + 1]> {
        if grid.len() < self.order + 2 {
            return None;
        }
        let mut d = [0.0; MAX_ORDER + 1];
        for (i, di) in d.iter_mut().enumerate().take(self.order + 1) {
            *di = grid.back(i)? - grid.back(i + 1)?;
        }
        Some(d)
    }

    // Indices as in the RLS update (P, φ, k): clearer than iterator chains over rows and columns.
    #[allow(clippy::needless_range_loop)]
    fn learn(&mut self, grid: &Grid) {
        let Some(d) = self.differences(grid) else {
            return;
        };
        let n = self.order;
        // The regressors' scale: a running mean of |d| over ≈ 200 grid points.
        let mag = d[0].abs();
        self.scale = if self.learnt == 0 {
            mag
        } else {
            self.scale + (mag - self.scale) / 200.0
        };
        self.learnt += 1;
        if !(self.scale > 1e-300) || !self.scale.is_finite() {
            return;
        }
        let inv = 1.0 / self.scale;
        let mut phi = [0.0; MAX_ORDER];
        for i in 0..n {
            phi[i] = d[i + 1] * inv;
        }
        let y = d[0] * inv;
        let mut pphi = [0.0; MAX_ORDER];
        for i in 0..n {
            pphi[i] = (0..n).map(|j| self.p[i][j] * phi[j]).sum();
        }
        let denom = self.lambda + (0..n).map(|i| phi[i] * pphi[i]).sum::<f64>();
        let err = y - (0..n).map(|i| self.a[i] * phi[i]).sum::<f64>();
        if !(denom > 0.0) || !denom.is_finite() || !err.is_finite() {
            *self = Self::new(self.order, self.lambda);
            return;
        }
        let trace: f64 = (0..n).map(|i| self.p[i][i]).sum();
        // No forgetting while the covariance is already large (a flat signal teaches nothing).
        let forget = if trace > TRACE_MAX { 1.0 } else { self.lambda };
        for i in 0..n {
            let k = pphi[i] / denom;
            self.a[i] += k * err;
            for j in 0..n {
                self.p[i][j] = (self.p[i][j] - k * pphi[j]) / forget;
            }
        }
        // Keep P symmetric against rounding.
        for i in 0..n {
            for j in 0..i {
                let m = 0.5 * (self.p[i][j] + self.p[j][i]);
                self.p[i][j] = m;
                self.p[j][i] = m;
            }
        }
        if self.a[..n].iter().any(|a| !a.is_finite()) {
            *self = Self::new(self.order, self.lambda);
        }
    }

    fn predict(&self, grid: &Grid, t_ns: u64) -> Option<Prediction> {
        let newest = grid.back(0)?;
        let fallback = |fell_back| line(grid, 4, t_ns).map(|value| Prediction { value, fell_back });
        let Some(d) = self.differences(grid) else {
            return fallback(false);
        };
        let f = steps_to(grid, t_ns);
        if f == 0.0 {
            return Some(Prediction {
                value: newest,
                fell_back: false,
            });
        }
        let n = self.order;
        let mut hist = [0.0; MAX_ORDER];
        hist[..n].copy_from_slice(&d[..n]);
        let steps = (f.ceil() as usize).min(MAX_STEPS);
        let (mut before, mut x) = (newest, newest);
        for _ in 0..steps {
            let next: f64 = (0..n).map(|i| self.a[i] * hist[i]).sum();
            hist.copy_within(0..n - 1, 1);
            hist[0] = next;
            before = x;
            x += next;
        }
        let frac = (f - (steps as f64 - 1.0)).clamp(0.0, 1.0);
        let value = before + (x - before) * frac;
        let (lo, hi) = grid.range()?;
        let spread = 0.5 * (hi - lo);
        if !value.is_finite() || value < lo - spread || value > hi + spread {
            return fallback(true);
        }
        Some(Prediction {
            value,
            fell_back: false,
        })
    }
}

/// Shortest breath period searched, s.
pub const CYCLE_MIN_S: f64 = 1.2;
/// Longest breath period searched, s (a slow breath; the grid holds more).
pub const CYCLE_MAX_S: f64 = 12.0;
/// Signal matched, s.
pub const CYCLE_WINDOW_S: f64 = 1.0;
/// A match is used when its squared error is under this fraction of the window's own variation.
pub const CYCLE_MATCH: f64 = 0.02;
/// Grid points between full searches (between them only lags near the last are tried).
const FULL_SEARCH_EVERY: u32 = 25;

/// Predictions remembered for scoring (the horizon in grid steps is at most this).
const SCORED: usize = 128;
/// Grid points the recent errors are averaged over (≈ 10 s at 50 Hz: two or three breaths).
const SCORE_MEMORY: f64 = 100.0;

/// What the previous-cycle predictor uses now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CycleChoice {
    /// The previous breath's course.
    Cycle,
    /// The autoregression.
    Autoregression,
    /// No prediction (a noisy signal, where extrapolating amplifies the noise).
    Hold,
}

/// The previous-cycle predictor's state.
#[derive(Debug, Clone, PartialEq)]
pub struct CycleMatch {
    horizon_ms: u32,
    /// The matched lag, grid steps, and its relative error.
    matched: Option<(usize, f64)>,
    since_full: u32,
    fallback: ArRls,
    /// (cycle's, autoregression's, none's) predictions for the grid point `horizon` steps after
    /// each point, newest last.
    scored: super::Ring<(f64, f64, f64), SCORED>,
    /// Recent mean squared errors (cycle, autoregression, none) at the horizon.
    errors: (f64, f64, f64),
}

/// The grid value `k` steps back, `k` fractional (linear between points).
fn back_at(grid: &Grid, k: f64) -> Option<f64> {
    let i = k.floor();
    let f = k - i;
    let a = grid.back(i as usize)?;
    if f == 0.0 {
        return Some(a);
    }
    let b = grid.back(i as usize + 1)?;
    Some(a + (b - a) * f)
}

impl CycleMatch {
    /// A fresh predictor comparing its two at `horizon_ms`.
    pub fn new(horizon_ms: u32) -> Self {
        Self {
            horizon_ms,
            matched: None,
            since_full: FULL_SEARCH_EVERY,
            fallback: ArRls::new(AR_ORDER, AR_LAMBDA),
            scored: super::Ring::default(),
            errors: (f64::INFINITY, 0.0, f64::INFINITY),
        }
    }

    /// Which of the three is in use: the one with the least recent error at the horizon (the
    /// previous cycle only while one matches).
    pub fn choice(&self) -> CycleChoice {
        let (c, a, h) = self.errors;
        if self.matched().is_some() && c < a && c < h {
            CycleChoice::Cycle
        } else if h < a {
            CycleChoice::Hold
        } else {
            CycleChoice::Autoregression
        }
    }

    /// The lag matched and its relative squared error, when one is good enough to use.
    pub fn matched(&self) -> Option<(usize, f64)> {
        self.matched.filter(|m| m.1 < CYCLE_MATCH)
    }

    fn learn(&mut self, grid: &Grid) {
        self.fallback.learn(grid);
        self.search(grid);
        self.score(grid);
    }

    /// Score the predictions made `horizon` steps ago against the point just added, and predict
    /// from here for the point `horizon` steps on.
    fn score(&mut self, grid: &Grid) {
        let h = ((f64::from(self.horizon_ms) * 1e6 / grid.period_ns() as f64).round() as usize)
            .clamp(1, SCORED - 1);
        let x = grid.back(0).expect("a point was just added");
        if self.scored.len() >= h {
            let (c, a, n) = self.scored.back(h - 1).expect("len ≥ h");
            let (ec, ea, en) = ((c - x).powi(2), (a - x).powi(2), (n - x).powi(2));
            if ec.is_finite() && ea.is_finite() && en.is_finite() {
                let (oc, oa, on) = self.errors;
                let step = |o: f64, e: f64| o + (e - o) / SCORE_MEMORY;
                self.errors = if oc.is_finite() {
                    (step(oc, ec), step(oa, ea), step(on, en))
                } else {
                    (ec, ea, en)
                };
            }
        }
        let t = grid.newest_ns() + h as u64 * grid.period_ns();
        let ar = self.fallback.predict(grid, t).map_or(x, |p| p.value);
        let cycle = self.cycle_at(grid, t).unwrap_or(ar);
        self.scored.push((cycle, ar, x));
    }

    fn search(&mut self, grid: &Grid) {
        let per_s = 1e9 / grid.period_ns() as f64;
        let w = (CYCLE_WINDOW_S * per_s).round().max(2.0) as usize;
        let lo = (CYCLE_MIN_S * per_s).round() as usize;
        let hi = ((CYCLE_MAX_S * per_s).round() as usize).min(grid.len().saturating_sub(w + 1));
        if hi <= lo {
            self.matched = None;
            return;
        }
        let x0 = grid.back(0).expect("a point was just added");
        let mut own = 0.0;
        for j in 0..w {
            own += (grid.back(j).expect("j < len") - x0).powi(2);
        }
        if !(own > 0.0) {
            self.matched = None;
            return;
        }
        let cost = |lag: usize| -> f64 {
            let xl = grid.back(lag).expect("lag < len");
            let mut c = 0.0;
            for j in 0..w {
                let a = grid.back(j).expect("j < len") - x0;
                let b = grid.back(j + lag).expect("j + lag < len") - xl;
                c += (a - b) * (a - b);
            }
            c
        };
        self.since_full += 1;
        let (from, to) = match self.matched {
            Some((lag, _)) if self.since_full < FULL_SEARCH_EVERY => {
                (lag.saturating_sub(3).max(lo), (lag + 3).min(hi))
            }
            _ => {
                self.since_full = 0;
                (lo, hi)
            }
        };
        let mut best: Option<(usize, f64)> = None;
        for lag in from..=to {
            let c = cost(lag);
            if best.is_none_or(|b| c < b.1) {
                best = Some((lag, c));
            }
        }
        self.matched = best.map(|(lag, c)| (lag, c / own));
    }

    /// The previous cycle's prediction for `t_ns`, when a cycle matched.
    fn cycle_at(&self, grid: &Grid, t_ns: u64) -> Option<f64> {
        let (lag, _) = self.matched()?;
        let f = steps_to(grid, t_ns);
        let lag = lag as f64;
        if f >= lag {
            return None;
        }
        let v = grid.back(0)? + back_at(grid, lag - f)? - grid.back(lag as usize)?;
        v.is_finite().then_some(v)
    }

    fn predict(&self, grid: &Grid, t_ns: u64) -> Option<Prediction> {
        let plain = |value| Prediction {
            value,
            fell_back: false,
        };
        match self.choice() {
            CycleChoice::Cycle => match self.cycle_at(grid, t_ns) {
                Some(v) => Some(plain(v)),
                None => self.fallback.predict(grid, t_ns),
            },
            CycleChoice::Hold => grid.last_sample().map(|(_, v)| plain(v)),
            CycleChoice::Autoregression => self.fallback.predict(grid, t_ns),
        }
    }
}
