//! Breaths in the signal: turning points found with hysteresis, the end-expiration baseline and
//! its drift, and breaths that are not like the others.
//!
//! The detector sees each grid point once, in order, and keeps only fixed rings. A peak (end of
//! inspiration) is confirmed once the signal has fallen `h` below the highest value since the last
//! trough, a trough (end of expiration) once it has risen `h` above the lowest since the last peak;
//! `h` is a quarter of the typical breath's amplitude (the median of the last regular breaths; in
//! the first seconds, of the range seen so far), and never below four times the signal's
//! point-to-point noise, so a flat or noisy signal does not become a storm of breaths.
//!
//! A completed breath (trough → peak → trough) is *regular* unless it is:
//! * a **sigh**: its amplitude over 1.6 × the typical one (a sigh is about twice a tidal breath;
//!   Bell et al. 2011 measure 2–3×);
//! * a **cough**: its expiration shorter than 0.35 × the typical expiration while at least a third
//!   as deep (an expulsive breath);
//! * **shallow**: under 0.4 × the typical amplitude (a fragment of an irregular breath, or shallow
//!   breathing: five in a row are taken as the new normal);
//!
//! the typical amplitude and period are medians over the last five breaths, coughs left out (one
//! sigh among five moves a median little; leaving sighs out too would bias it low when deep and
//! shallow breaths alternate, as they do in a real RPM trace), and a cough's trough is no
//! end-expiration for the baseline.
//!
//! A **pause** is no turning point for max(2 × the typical period, 3 s): a *breath-hold* when the
//! signal rests more than half a breath above the baseline, an *apnoea* when it rests near the
//! baseline for 10 s or longer (the AASM scoring manual's cessation of airflow ≥ 10 s).
//!
//! The thresholds are this module's (stated here, tested, not the seed's).

use super::{fit_line, median_of, secs, Ring};

/// Hysteresis as a fraction of the typical amplitude.
pub const HYSTERESIS: f64 = 0.25;
/// Amplitude over this × the typical one: a sigh.
pub const SIGH_RATIO: f64 = 1.6;
/// Amplitude under this × the typical one: shallow.
pub const SHALLOW_RATIO: f64 = 0.4;
/// Shallow breaths in a row taken as the new normal (the breathing became shallow).
pub const SHALLOW_RUN: u32 = 5;
/// Expiration shorter than this × the typical one (and deep enough): a cough.
pub const COUGH_EXPIRATION_RATIO: f64 = 0.35;
/// Signal noise multiple the hysteresis never goes below.
pub const NOISE_MULTIPLE: f64 = 4.0;
/// Seconds of signal before the first turning point may be confirmed.
pub const LEARN_S: f64 = 1.5;
/// Shortest pause, s.
pub const PAUSE_MIN_S: f64 = 3.0;
/// An apnoea: a pause near the baseline this long, s (AASM: ≥ 10 s).
pub const APNOEA_S: f64 = 10.0;

/// Before the first breath, the range is taken over blocks of this many seconds (one or two).
pub const RANGE_BLOCK_S: f64 = 6.0;
/// Largest baseline drift followed, typical amplitudes per second (an integrated flow with a
/// sensor offset drifts by a good part of a breath each second; a chest marker by far less).
pub const MAX_DRIFT_AMPLITUDES_PER_S: f64 = 0.1;

/// Regular breaths remembered for the typical amplitude and period.
const TYPICAL: usize = 5;

/// Turns whose value lies within this fraction of the signal's range of its extreme are taken as
/// reaching it (0.5 %: the BioSPPy belt's three cut breaths lie within 0.15 %).
pub const CLIP_BAND: f64 = 0.005;
/// At least this many turns reach the extreme…
pub const CLIP_MIN_BREATHS: usize = 3;
/// …while the other turns on that side spread over at least this fraction of the range (their
/// interquartile range): breaths of unequal depth ending at one value are cut, where breaths of
/// equal depth (a ventilator's, a steady breather's) end together by themselves.
pub const CLIP_SPREAD: f64 = 0.1;
/// Peaks and troughs the live detector judges clipping over (the latest).
pub const CLIP_WINDOW: usize = 16;

/// Whether `v` lies within [`CLIP_BAND`] × `range` of `extreme` (a turn reaching it).
pub fn near_extreme(v: f64, extreme: f64, range: f64) -> bool {
    (v - extreme).abs() <= CLIP_BAND * range
}

/// Whether one side's turns `values` (peaks, or troughs) of a signal spanning `range` look cut at
/// `extreme` (its highest, or lowest, value): how many lie within [`CLIP_BAND`] × `range` of it and
/// the others' interquartile range over `range`, when at least [`CLIP_MIN_BREATHS`] do and at least
/// four others spread over [`CLIP_SPREAD`] or more. `scratch` is at least `values.len()` long;
/// nothing is allocated (the live detector runs it on each turn).
pub fn clip_verdict(
    values: &[f64],
    extreme: f64,
    range: f64,
    scratch: &mut [f64],
) -> Option<(usize, f64)> {
    if !(range > 0.0 && range.is_finite() && extreme.is_finite()) || scratch.len() < values.len() {
        return None;
    }
    let near = |v: f64| near_extreme(v, extreme, range);
    let mut others = 0;
    for &v in values.iter().filter(|v| v.is_finite() && !near(**v)) {
        scratch[others] = v;
        others += 1;
    }
    let at = values.iter().filter(|v| near(**v)).count();
    if at < CLIP_MIN_BREATHS || others < 4 {
        return None;
    }
    let o = &mut scratch[..others];
    o.sort_unstable_by(f64::total_cmp);
    let q = |f: f64| o[((others - 1) as f64 * f).round() as usize];
    let spread = (q(0.75) - q(0.25)) / range;
    (spread >= CLIP_SPREAD).then_some((at, spread))
}

/// What a completed breath was.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BreathKind {
    /// Like the ones before.
    #[default]
    Regular,
    /// Much deeper than the typical breath.
    Sigh,
    /// A short, forced expiration.
    Cough,
    /// Under 0.4 × the typical amplitude: a fragment of an irregular breath (its trough is no
    /// end-expiration), or the breathing became shallow.
    Shallow,
}

/// A pause in the breathing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Pause {
    /// No turning point for a while, resting high: the breath is held.
    BreathHold,
    /// Resting near the baseline for 10 s or more.
    Apnoea,
    /// Resting near the baseline, not yet 10 s.
    Resting,
}

/// A turning point just confirmed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Turn {
    /// End of inspiration at (time, value).
    Peak(u64, f64),
    /// End of expiration at (time, value); `Some` when it completed a breath.
    Trough(u64, f64, Option<Breath>),
}

/// A completed breath.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Breath {
    /// Peak minus the trough it started from, signal unit.
    pub amplitude: f64,
    /// Trough to trough, s.
    pub period_s: f64,
    /// What it was.
    pub kind: BreathKind,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Learning the signal's range (no turning point yet).
    Learning,
    /// Rising towards a peak; the highest point since the last trough.
    Rising(u64, f64),
    /// Falling towards a trough; the lowest point since the last peak.
    Falling(u64, f64),
}

/// Whether a breath of `kind` moves the typical figures and the baseline.
fn learns(kind: BreathKind, shallow_run: u32) -> bool {
    match kind {
        BreathKind::Regular | BreathKind::Sigh => true,
        BreathKind::Cough => false,
        BreathKind::Shallow => shallow_run >= SHALLOW_RUN,
    }
}

/// Counts of what was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct Counts {
    /// Completed breaths (all kinds).
    pub breaths: u64,
    /// Sighs.
    pub sighs: u64,
    /// Coughs.
    pub coughs: u64,
    /// Shallow breaths (or fragments of irregular ones).
    pub shallow: u64,
    /// Pauses that became breath-holds.
    pub breath_holds: u64,
    /// Pauses that became apnoeas.
    pub apnoeas: u64,
}

/// The breath detector.
#[derive(Debug, Clone, PartialEq)]
pub struct Detector {
    phase: Phase,
    start_ns: Option<u64>,
    /// Range of the current and the previous [`RANGE_BLOCK_S`] block (before any breath).
    lo: f64,
    hi: f64,
    block: (u64, f64, f64),
    prev: [f64; 2],
    seen: u64,
    noise: f64,
    amplitudes: Ring<f64, TYPICAL>,
    periods: Ring<f64, TYPICAL>,
    expirations: Ring<f64, TYPICAL>,
    troughs: Ring<(u64, f64), TYPICAL>,
    last_trough: Option<(u64, f64)>,
    last_peak: Option<(u64, f64)>,
    /// When the last turning point was confirmed (not when its extreme was: after a held breath
    /// the peak is at the hold's start, its confirmation at its end).
    last_turn_ns: u64,
    last_kind: BreathKind,
    shallow_run: u32,
    pause: Option<Pause>,
    counts: Counts,
    /// The latest peaks' and troughs' values, for [`Self::clipped`].
    peak_values: Ring<f64, CLIP_WINDOW>,
    trough_values: Ring<f64, CLIP_WINDOW>,
    clipped: Option<bool>,
}

impl Default for Detector {
    fn default() -> Self {
        Self::new()
    }
}

impl Detector {
    /// A detector that has seen nothing.
    pub fn new() -> Self {
        Self {
            phase: Phase::Learning,
            start_ns: None,
            lo: f64::INFINITY,
            hi: f64::NEG_INFINITY,
            block: (0, f64::INFINITY, f64::NEG_INFINITY),
            prev: [0.0; 2],
            seen: 0,
            noise: 0.0,
            amplitudes: Ring::default(),
            periods: Ring::default(),
            expirations: Ring::default(),
            troughs: Ring::default(),
            last_trough: None,
            last_peak: None,
            last_turn_ns: 0,
            last_kind: BreathKind::Regular,
            shallow_run: 0,
            pause: None,
            counts: Counts::default(),
            peak_values: Ring::default(),
            trough_values: Ring::default(),
            clipped: None,
        }
    }

    /// Whether the latest breaths look cut by the sensor's range ([`clip_verdict`] over the last
    /// [`CLIP_WINDOW`] peaks and troughs, their range the highest peak to the lowest trough):
    /// `Some(true)` at the top (inspirations cut: the breaths were deeper than they read),
    /// `Some(false)` at the bottom, `None` when not. Judged at each turn; allocates nothing.
    pub fn clipped(&self) -> Option<bool> {
        self.clipped
    }

    fn judge_clipping(&mut self) {
        let (mut peaks, mut troughs, mut scratch) =
            ([0.0; CLIP_WINDOW], [0.0; CLIP_WINDOW], [0.0; CLIP_WINDOW]);
        let np = self.peak_values.copy_into(&mut peaks);
        let nt = self.trough_values.copy_into(&mut troughs);
        let (peaks, troughs) = (&peaks[..np], &troughs[..nt]);
        let hi = peaks.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let lo = troughs.iter().copied().fold(f64::INFINITY, f64::min);
        let range = hi - lo;
        self.clipped = if clip_verdict(peaks, hi, range, &mut scratch).is_some() {
            Some(true)
        } else if clip_verdict(troughs, lo, range, &mut scratch).is_some() {
            Some(false)
        } else {
            None
        };
    }

    /// The typical amplitude (median of the last five breaths, coughs left out); before the first
    /// breath, the range seen lately.
    pub fn typical_amplitude(&self) -> Option<f64> {
        let mut buf = [0.0; TYPICAL];
        let n = self.amplitudes.copy_into(&mut buf);
        median_of(&buf[..n]).or_else(|| (self.hi > self.lo).then_some(self.hi - self.lo))
    }

    /// The typical trough-to-trough period (median of the last five breaths, coughs left out), s.
    pub fn typical_period_s(&self) -> Option<f64> {
        let mut buf = [0.0; TYPICAL];
        let n = self.periods.copy_into(&mut buf);
        median_of(&buf[..n])
    }

    /// The typical expiration (peak to the next trough, median of the last five breaths, coughs
    /// left out), s.
    pub fn typical_expiration_s(&self) -> Option<f64> {
        let mut buf = [0.0; TYPICAL];
        let n = self.expirations.copy_into(&mut buf);
        median_of(&buf[..n])
    }

    /// Where the breath under way is at `t_ns`: the typical period (s), the time since the last
    /// end-expiration over it (kept below 1 when the breath runs long), and the typical
    /// inspiration's share of a breath; `None` before a typical breath is known.
    pub fn phase_at(&self, t_ns: u64) -> Option<(f64, f64, f64)> {
        let period = self.typical_period_s().filter(|p| *p > 0.0)?;
        let expiration = self.typical_expiration_s()?;
        let (trough, _) = self.last_trough?;
        let since = secs(t_ns as i128 - trough as i128).max(0.0);
        let phase = (since / period).min(0.999);
        let split = (1.0 - expiration / period).clamp(0.0, 1.0);
        (phase.is_finite() && split.is_finite()).then_some((period, phase, split))
    }

    /// End-expirations behind the baseline (up to five; kept across a loss).
    pub fn end_expirations(&self) -> usize {
        self.troughs.len()
    }

    /// Breaths behind the typical figures (up to five).
    pub fn regular_breaths(&self) -> usize {
        self.amplitudes.len()
    }

    /// The end-expiration level at `t_ns`: the last regular trough, moved by the drift the last
    /// troughs show (a least-squares slope over up to five, once there are two; its size kept
    /// below [`MAX_DRIFT_AMPLITUDES_PER_S`]). Before any trough, the lowest value seen lately.
    pub fn baseline_at(&self, t_ns: u64) -> Option<f64> {
        let Some((t_last, v_last)) = self.troughs.back(0) else {
            return self.lo.is_finite().then_some(self.lo);
        };
        let n = self.troughs.len();
        if n < 2 {
            return Some(v_last);
        }
        let points = (0..n)
            .filter_map(|k| self.troughs.back(k))
            .map(|(t, v)| (secs(t as i128 - t_last as i128), v));
        let Some((slope, _)) = fit_line(points) else {
            return Some(v_last);
        };
        let limit = MAX_DRIFT_AMPLITUDES_PER_S * self.typical_amplitude().unwrap_or(0.0);
        let slope = slope.clamp(-limit, limit);
        // The drift is followed up to a typical breath past the last trough (the next trough is
        // due by then): beyond, and across a gap in the signal, it is held, not extrapolated for
        // the gap's length.
        let horizon = self.typical_period_s().unwrap_or(PAUSE_MIN_S);
        let ahead = secs(t_ns as i128 - t_last as i128).clamp(0.0, horizon);
        let v = v_last + slope * ahead;
        Some(if v.is_finite() { v } else { v_last })
    }

    /// The baseline's drift, signal units per second (0 before two troughs).
    pub fn drift_per_s(&self) -> f64 {
        match self.troughs.back(0) {
            Some((t, v)) if self.troughs.len() >= 2 => {
                self.baseline_at(t + 1_000_000_000).map_or(0.0, |b| b - v)
            }
            _ => 0.0,
        }
    }

    /// Whether the signal is rising (inspiration) since the last trough.
    pub fn inhaling(&self) -> bool {
        matches!(self.phase, Phase::Rising(..))
    }

    /// The pause under way, if any.
    pub fn pause(&self) -> Option<Pause> {
        self.pause
    }

    /// What the last completed breath was.
    pub fn last_kind(&self) -> BreathKind {
        self.last_kind
    }

    /// What was found so far.
    pub fn counts(&self) -> Counts {
        self.counts
    }

    /// The hysteresis now.
    fn threshold(&self) -> f64 {
        let a = self.typical_amplitude().unwrap_or(0.0);
        (HYSTERESIS * a).max(NOISE_MULTIPLE * self.noise)
    }

    /// Forget the signal (its grid restarted after a loss) but keep what breaths look like and
    /// where the end-expiration baseline was: no breath spans the gap (its last peak and trough
    /// are forgotten), and the signal's range is learnt again before the first turning point.
    pub fn restart(&mut self) {
        self.phase = Phase::Learning;
        self.start_ns = None;
        self.seen = 0;
        self.pause = None;
        self.last_peak = None;
        self.last_trough = None;
        self.lo = f64::INFINITY;
        self.hi = f64::NEG_INFINITY;
        self.block = (0, f64::INFINITY, f64::NEG_INFINITY);
    }

    /// Take the next grid point; returns the turning point it confirmed, if any.
    pub fn push(&mut self, t_ns: u64, v: f64) -> Option<Turn> {
        if !v.is_finite() {
            return None;
        }
        let start = *self.start_ns.get_or_insert(t_ns);
        if self.seen >= 2 {
            let second = (v - 2.0 * self.prev[0] + self.prev[1]).abs();
            self.noise += (second - self.noise) / 50.0;
        }
        self.prev = [v, self.prev[0]];
        self.seen += 1;
        if self.amplitudes.len() == 0 || self.phase == Phase::Learning {
            self.see_range(t_ns, v);
        }
        let h = self.threshold();
        let turn = match self.phase {
            Phase::Learning => {
                if secs(t_ns as i128 - start as i128) >= LEARN_S && h > 0.0 {
                    self.last_turn_ns = t_ns;
                    self.phase = if v - self.lo < self.hi - v {
                        Phase::Falling(t_ns, v)
                    } else {
                        Phase::Rising(t_ns, v)
                    };
                }
                None
            }
            Phase::Rising(tm, m) => {
                if v > m {
                    self.phase = Phase::Rising(t_ns, v);
                    None
                } else if h > 0.0 && v < m - h {
                    self.phase = Phase::Falling(t_ns, v);
                    self.last_turn_ns = t_ns;
                    Some(self.peak(tm, m))
                } else {
                    None
                }
            }
            Phase::Falling(tm, m) => {
                if v < m {
                    self.phase = Phase::Falling(t_ns, v);
                    None
                } else if h > 0.0 && v > m + h {
                    self.phase = Phase::Rising(t_ns, v);
                    self.last_turn_ns = t_ns;
                    Some(self.trough(tm, m))
                } else {
                    None
                }
            }
        };
        self.watch_pause(t_ns, v);
        turn
    }

    /// The range over the last one or two blocks of [`RANGE_BLOCK_S`]: a drifting signal (a flow
    /// integrated with an offset) does not widen it for ever.
    fn see_range(&mut self, t_ns: u64, v: f64) {
        let (start, blo, bhi) = self.block;
        if self.block.1 > self.block.2 || secs(t_ns as i128 - start as i128) >= RANGE_BLOCK_S {
            // A new block: the range is the finished block's and the new one's.
            self.lo = blo.min(v);
            self.hi = bhi.max(v);
            self.block = (t_ns, v, v);
        } else {
            self.block = (start, blo.min(v), bhi.max(v));
            self.lo = self.lo.min(v);
            self.hi = self.hi.max(v);
        }
    }

    fn peak(&mut self, t: u64, v: f64) -> Turn {
        self.last_peak = Some((t, v));
        self.end_pause();
        self.peak_values.push(v);
        self.judge_clipping();
        Turn::Peak(t, v)
    }

    fn trough(&mut self, t: u64, v: f64) -> Turn {
        self.end_pause();
        self.trough_values.push(v);
        self.judge_clipping();
        let breath = match (self.last_trough, self.last_peak) {
            (Some((t0, v0)), Some((tp, vp))) if t0 < tp && tp < t => {
                let amplitude = vp - v0;
                let period_s = secs(t as i128 - t0 as i128);
                let expiration_s = secs(t as i128 - tp as i128);
                let kind = self.classify(amplitude, expiration_s);
                self.counts.breaths += 1;
                match kind {
                    BreathKind::Sigh => self.counts.sighs += 1,
                    BreathKind::Cough => self.counts.coughs += 1,
                    BreathKind::Shallow => self.counts.shallow += 1,
                    BreathKind::Regular => {}
                }
                // A median of five is moved little by one sigh among them; leaving sighs out would
                // bias it low when deep and shallow breaths alternate. A cough's are left out, and
                // a shallow breath's unless the breathing stays shallow: fragments of an irregular
                // breath would otherwise shrink the typical amplitude, and with it the hysteresis,
                // until every wiggle is a breath.
                self.shallow_run = if kind == BreathKind::Shallow {
                    self.shallow_run + 1
                } else {
                    0
                };
                if learns(kind, self.shallow_run) {
                    self.amplitudes.push(amplitude);
                    self.periods.push(period_s);
                    self.expirations.push(expiration_s);
                }
                self.last_kind = kind;
                Some(Breath {
                    amplitude,
                    period_s,
                    kind,
                })
            }
            _ => None,
        };
        if breath.is_none_or(|b| learns(b.kind, self.shallow_run)) {
            self.troughs.push((t, v));
        }
        self.last_trough = Some((t, v));
        Turn::Trough(t, v, breath)
    }

    fn classify(&self, amplitude: f64, expiration_s: f64) -> BreathKind {
        if self.amplitudes.len() < 2 {
            return BreathKind::Regular;
        }
        let a = self.typical_amplitude().unwrap_or(amplitude);
        let mut buf = [0.0; TYPICAL];
        let n = self.expirations.copy_into(&mut buf);
        let e = median_of(&buf[..n]).unwrap_or(expiration_s);
        if amplitude < SHALLOW_RATIO * a {
            BreathKind::Shallow
        } else if amplitude > SIGH_RATIO * a {
            BreathKind::Sigh
        } else if expiration_s < COUGH_EXPIRATION_RATIO * e && amplitude > a / 3.0 {
            BreathKind::Cough
        } else {
            BreathKind::Regular
        }
    }

    fn end_pause(&mut self) {
        match self.pause.take() {
            Some(Pause::BreathHold) => self.counts.breath_holds += 1,
            Some(Pause::Apnoea) => self.counts.apnoeas += 1,
            _ => {}
        }
    }

    fn watch_pause(&mut self, t_ns: u64, v: f64) {
        if matches!(self.phase, Phase::Learning) {
            return;
        }
        let still_s = secs(t_ns as i128 - self.last_turn_ns as i128);
        let limit = self
            .typical_period_s()
            .map_or(PAUSE_MIN_S, |p| (2.0 * p).max(PAUSE_MIN_S));
        if still_s < limit {
            return;
        }
        let a = self.typical_amplitude().unwrap_or(0.0);
        let base = self.baseline_at(t_ns).unwrap_or(v);
        self.pause = Some(if v - base > 0.5 * a {
            Pause::BreathHold
        } else if still_s >= APNOEA_S {
            Pause::Apnoea
        } else {
            Pause::Resting
        });
    }
}
