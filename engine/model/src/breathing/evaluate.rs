//! A recorded trace replayed as if live, against the volume it holds with hindsight.
//!
//! Frames are shown every `frame_period` from the trace's first sample; the frame shown at τ was
//! computed from the samples captured up to τ − latency (the sensor, bridge, engine and GPU
//! together: the samples a live pipeline had when it drew that frame), predicted to τ. Each frame's
//! volume — predicted, and unpredicted from the same run — is compared with the trace's hindsight
//! volume at τ (interpolated between its samples). Frames before the follower has calibrated, and
//! where the hindsight volume is unknown (outside a complete breath), are not compared.
//!
//! The hindsight volume of a ventilator recording ([`Trace::from_recording`]) is independent of the
//! follower: each breath's flow integrated from its own start and corrected for its own net volume
//! ([`crate::recording::breath_volume`]), while the live signal is the flow integrated once from the
//! recording's start, drifting as a live integrator drifts. Its breaths are the recording's own
//! ([`crate::recording::segment`]).

use super::detect::{BreathKind, Detector, Turn};
use super::follow::Calibration;
use super::follow::{Followed, Follower, FollowerConfig, SampleCounts, SignalState};
use super::trace::{SignalTrace, SignalUnit};
use super::{SignalSample, TRACE_START_NS};
use crate::recording::{breath_volume, segment, Recording, SegmentOptions};

/// A trace and its hindsight volume.
#[derive(Debug, Clone, PartialEq)]
pub struct Trace {
    /// The samples, in capture order.
    pub samples: Vec<SignalSample>,
    /// Hindsight volume above end-expiration at each sample, ml (NaN where unknown).
    pub truth_ml: Vec<f64>,
    /// Complete breaths in the trace (its own count, not the follower's).
    pub breaths: usize,
    /// Each complete breath's end of inspiration (the hindsight volume's highest sample), ns.
    pub end_inspiration_ns: Vec<u64>,
    /// The mean tidal volume of the complete breaths, ml.
    pub tidal_ml: f64,
    /// The source's sample rate, Hz.
    pub rate_hz: f64,
    /// How a live follower turns this signal into ml.
    pub calibration: Calibration,
    /// The median period of the regular breaths the detector found over the whole trace, s (a
    /// one-signal trace's; `None` for a ventilator recording, whose own checks give its rate).
    pub breath_period_s: Option<f64>,
    /// Median fraction of a breath spent rising (inspiring): about 0.3–0.45 in quiet breathing
    /// (I:E 1:1.2–1:2.3); over 0.5 suggests the signal's sign is the wrong way round.
    pub inspiration_fraction: Option<f64>,
    /// A one-signal trace whose breaths end at one value, their depths cut there ([`Clipping`];
    /// `None` when none is seen, and for a ventilator recording).
    pub clipped: Option<Clipping>,
}

pub use super::detect::{CLIP_BAND, CLIP_MIN_BREATHS, CLIP_SPREAD};

/// A one-signal trace that looks clipped: several breaths of unequal depth turn at one value, the
/// signal's highest (inspirations cut: a belt stretched past its sensor's range, a converter's top,
/// a gain set too high) or lowest. Those breaths were deeper than they read, so lungs following
/// them breathe shallower there. Found from the detector's turns over the whole trace.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Clipping {
    /// At the signal's highest value (`true`: inspirations cut) or its lowest (expirations).
    pub at_top: bool,
    /// The value they turn at, in the signal's unit…
    pub value: f64,
    /// …this one's symbol (`mm`, `ml`, `a.u.`).
    pub unit: &'static str,
    /// Seconds from the trace's first sample of each turn at it.
    pub at_s: Vec<f64>,
    /// Turns on that side in all.
    pub turns: usize,
    /// The other turns' interquartile range, fraction of the signal's range.
    pub spread: f64,
}

impl Clipping {
    /// For a person.
    pub fn describe(&self) -> String {
        let unit = self.unit;
        let times: Vec<String> = self.at_s.iter().map(|t| format!("{t:.1}")).collect();
        let side = if self.at_top { "peaks" } else { "troughs" };
        let sensor = match unit {
            "mm" => "the marker's tracked range",
            "ml" => "the spirometer's or ventilator's range",
            _ if self.at_top => {
                "the sensor's range or its converter (a belt stretched past it, a gain too high)"
            }
            _ => "the sensor's floor or its converter (an offset set too low)",
        };
        format!(
            "the signal looks clipped at {} {unit}, its {} value: {} of its {} {side} lie there \
             (within {:.1} % of its range, at {} s) while the other {side} spread over {:.0} % of \
             it (their interquartile range) — {sensor} likely ends there, so those breaths \
             reached further than they read and the lungs following them breathe shallower there \
             (unless the breaths were held at one level on purpose: a coached breath-hold, a \
             ventilator's set volume)",
            significant(self.value, 5),
            if self.at_top { "highest" } else { "lowest" },
            self.at_s.len(),
            self.turns,
            100.0 * CLIP_BAND,
            times.join(", "),
            100.0 * self.spread,
        )
    }
}

/// `x` to `digits` significant digits, for a person (no float noise such as 0.30000000000000004).
pub(crate) fn significant(x: f64, digits: i32) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let decimals = (digits - 1 - x.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{x:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// [`Clipping`] of the turns `turns` (time ns, value; one side's) of a signal in `unit` spanning
/// `lo..=hi` from `t0_ns`: `top` for peaks.
pub fn clipping(
    turns: &[(u64, f64)],
    (lo, hi): (f64, f64),
    unit: SignalUnit,
    t0_ns: u64,
    top: bool,
) -> Option<Clipping> {
    let range = hi - lo;
    let extreme = if top { hi } else { lo };
    let values: Vec<f64> = turns.iter().map(|(_, v)| *v).collect();
    let mut scratch = vec![0.0; values.len()];
    let (_, spread) = super::detect::clip_verdict(&values, extreme, range, &mut scratch)?;
    let at_s = turns
        .iter()
        .filter(|(_, v)| super::detect::near_extreme(*v, extreme, range))
        .map(|(t, _)| t.saturating_sub(t0_ns) as f64 * 1e-9)
        .collect();
    Some(Clipping {
        at_top: top,
        value: extreme,
        unit: unit.symbol(),
        at_s,
        turns: turns.len(),
        spread,
    })
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.retain(|x| x.is_finite());
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

impl Trace {
    /// A ventilator recording as a live volume source: the flow integrated from its first sample
    /// (ml), and its breaths' hindsight volumes. `None` when it holds no complete breath.
    pub fn from_recording(rec: &Recording) -> Option<Trace> {
        let n = rec.t_s.len();
        if n < 2 {
            return None;
        }
        let t0 = rec.t_s[0];
        let mut samples = Vec::with_capacity(n);
        let mut integrated = 0.0;
        for i in 0..n {
            if i > 0 {
                // As recording::breath_volume integrates: each sample's flow held over its interval.
                integrated += rec.flow_lps[i - 1] * (rec.t_s[i] - rec.t_s[i - 1]) * 1000.0;
            }
            samples.push(SignalSample {
                t_ns: TRACE_START_NS + ((rec.t_s[i] - t0) * 1e9).round() as u64,
                value: integrated,
                valid: true,
            });
        }
        let mut truth_ml = vec![f64::NAN; n];
        let mut ends = Vec::new();
        let mut tidal = Vec::new();
        for span in segment(rec, &SegmentOptions::default()) {
            if !span.complete || span.starts_cut {
                continue;
            }
            let (v, _) = breath_volume(rec, &span);
            let (mut best, mut at) = (f64::NEG_INFINITY, span.start);
            for (j, &x) in v.iter().enumerate() {
                truth_ml[span.start + j] = x;
                if x > best {
                    best = x;
                    at = span.start + j;
                }
            }
            ends.push(samples[at].t_ns);
            tidal.push(best);
        }
        if tidal.is_empty() {
            return None;
        }
        let duration = rec.t_s[n - 1] - t0;
        let fractions = segment(rec, &SegmentOptions::default())
            .iter()
            .filter(|s| s.complete && !s.starts_cut && s.end > s.start)
            .map(|s| {
                (rec.t_s[s.expiration] - rec.t_s[s.start]) / (rec.t_s[s.end] - rec.t_s[s.start])
            })
            .collect();
        Some(Trace {
            samples,
            truth_ml,
            breaths: tidal.len(),
            end_inspiration_ns: ends,
            tidal_ml: tidal.iter().sum::<f64>() / tidal.len() as f64,
            rate_hz: (n - 1) as f64 / duration,
            calibration: Calibration::Volume,
            breath_period_s: None,
            inspiration_fraction: median(fractions),
            clipped: None,
        })
    }

    /// A one-signal trace (a chest marker, an RPM export, a volume) as a live source. Without an
    /// independent volume, its hindsight volume is the signal itself calibrated with the whole
    /// trace known: the baseline interpolated between the end-expirations the detector finds over
    /// all of it (each known only afterwards live), and the gain `calibration` gives: with
    /// [`Calibration::Auto`] the one that makes the median regular breath its `tidal_ml` (a live
    /// follower calibrates the same way, from the breaths seen so far), with [`Calibration::Fixed`]
    /// the spirometry calibration's (a live follower uses it from the start); a volume in ml is
    /// taken as it is, and so is any unit with [`Calibration::Volume`]. `None` with fewer than two
    /// end-expirations.
    pub fn from_signal(t: &SignalTrace, calibration: Calibration) -> Option<Trace> {
        let mut det = Detector::new();
        let mut troughs: Vec<(u64, f64)> = Vec::new();
        let mut peaks: Vec<(u64, f64)> = Vec::new();
        let (mut amplitudes, mut periods) = (Vec::new(), Vec::new());
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for s in t.samples.iter().filter(|s| s.valid) {
            lo = lo.min(s.value);
            hi = hi.max(s.value);
            match det.push(s.t_ns, s.value) {
                Some(Turn::Trough(tt, v, breath)) => {
                    troughs.push((tt, v));
                    if let Some(b) = breath.filter(|b| b.kind == BreathKind::Regular) {
                        amplitudes.push(b.amplitude);
                        periods.push(b.period_s);
                    }
                }
                Some(Turn::Peak(tt, v)) => peaks.push((tt, v)),
                None => {}
            }
        }
        if troughs.len() < 2 {
            return None;
        }
        amplitudes.sort_by(f64::total_cmp);
        let (calibration, gain) = match (t.unit, calibration) {
            (SignalUnit::Ml, _) | (_, Calibration::Volume) => (Calibration::Volume, 1.0),
            (_, Calibration::Fixed { ml_per_unit }) => (calibration, ml_per_unit),
            (_, Calibration::Auto { tidal_ml }) => {
                let median = *amplitudes.get(amplitudes.len() / 2)?;
                if !(median > 0.0) {
                    return None;
                }
                (calibration, tidal_ml / median)
            }
        };
        let mut truth_ml = vec![f64::NAN; t.samples.len()];
        let mut ends = Vec::new();
        let mut tidal = Vec::new();
        let mut k = 0usize;
        let mut best: Option<(f64, u64)> = None;
        for (i, s) in t.samples.iter().enumerate() {
            while k + 1 < troughs.len() && s.t_ns > troughs[k + 1].0 {
                if let Some((v, at)) = best.take() {
                    tidal.push(v);
                    ends.push(at);
                }
                k += 1;
            }
            let ((t0, v0), (t1, v1)) = (troughs[k], troughs[(k + 1).min(troughs.len() - 1)]);
            if s.t_ns < t0 || s.t_ns > t1 || t1 == t0 || !s.valid {
                continue;
            }
            let base = v0 + (v1 - v0) * (s.t_ns - t0) as f64 / (t1 - t0) as f64;
            let v = gain * (s.value - base);
            truth_ml[i] = v;
            if best.is_none_or(|(b, _)| v > b) {
                best = Some((v, s.t_ns));
            }
        }
        if let Some((v, at)) = best {
            tidal.push(v);
            ends.push(at);
        }
        let fractions = ends
            .iter()
            .zip(troughs.windows(2))
            .map(|(&e, w)| (e as i128 - w[0].0 as i128) as f64 / (w[1].0 - w[0].0) as f64)
            .filter(|f| (0.0..=1.0).contains(f))
            .collect();
        Some(Trace {
            samples: t.samples.clone(),
            truth_ml,
            breaths: troughs.len() - 1,
            end_inspiration_ns: ends,
            tidal_ml: tidal.iter().sum::<f64>() / tidal.len() as f64,
            rate_hz: t.rate_hz,
            calibration,
            breath_period_s: median(periods),
            inspiration_fraction: median(fractions),
            clipped: {
                let t0 = t.samples.first().map_or(0, |s| s.t_ns);
                clipping(&peaks, (lo, hi), t.unit, t0, true)
                    .or_else(|| clipping(&troughs, (lo, hi), t.unit, t0, false))
            },
        })
    }

    /// The hindsight volume at `t_ns`, linearly between samples; `None` where unknown.
    pub fn truth_at(&self, t_ns: u64) -> Option<f64> {
        let i = self.samples.partition_point(|s| s.t_ns <= t_ns);
        if i == 0 || i >= self.samples.len() {
            return None;
        }
        // The nearest samples with a hindsight volume on each side: the neighbours themselves when
        // they have one, however far apart (a slow source's samples); across samples without one
        // (flagged invalid) only within the bridge, as the live follower's grid bridges them.
        let has = |k: usize| self.truth_ml[k].is_finite();
        let close = |k: usize| self.samples[k].t_ns.abs_diff(t_ns) <= TRUTH_BRIDGE_NS;
        let a = (0..i)
            .rev()
            .take_while(|&k| k == i - 1 || close(k))
            .find(|&k| has(k))?;
        let b = (i..self.samples.len())
            .take_while(|&k| k == i || close(k))
            .find(|&k| has(k))?;
        let (sa, sb) = (&self.samples[a], &self.samples[b]);
        let (va, vb) = (self.truth_ml[a], self.truth_ml[b]);
        let f = (t_ns - sa.t_ns) as f64 / (sb.t_ns - sa.t_ns) as f64;
        let v = va + (vb - va) * f;
        v.is_finite().then_some(v)
    }
}

/// How far from a frame's display time the hindsight volume is looked for on each side across
/// invalid samples, ns (a longer run of them is a loss the volume is not compared over).
pub const TRUTH_BRIDGE_NS: u64 = 250_000_000;

/// A replay's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalOptions {
    /// Capture to display, ns.
    pub latency_ns: u64,
    /// Frame period, ns (16.67 ms: 60 Hz).
    pub frame_period_ns: u64,
    /// The follower's settings.
    pub follower: FollowerConfig,
}

/// What a replay measured.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Evaluation {
    /// The predictor's name.
    pub predictor: String,
    /// Capture to display, ms.
    pub latency_ms: f64,
    /// Frames shown.
    pub frames: usize,
    /// Frames compared with the hindsight volume.
    pub frames_compared: usize,
    /// Frames while calibrating (not compared).
    pub frames_calibrating: usize,
    /// Frames with the signal lost (not compared).
    pub frames_lost: usize,
    /// Frames whose prediction the guard replaced.
    pub frames_fell_back: usize,
    /// Frames whose volume was kept within the drawn range.
    pub frames_clamped: usize,
    /// The trace's mean tidal volume, ml.
    pub tidal_ml: f64,
    /// RMS of drawn − hindsight volume, ml, predicted.
    pub rms_error_ml: f64,
    /// The same without prediction.
    pub rms_error_ml_without_prediction: f64,
    /// RMS error, % of the mean tidal volume, predicted.
    pub rms_error_percent_of_tidal: f64,
    /// The same without prediction.
    pub rms_error_percent_of_tidal_without_prediction: f64,
    /// Drawn end-inspiration minus the trace's, mean over matched breaths, ms (positive: late).
    pub lag_ms: Option<f64>,
    /// The same without prediction.
    pub lag_ms_without_prediction: Option<f64>,
    /// Breaths whose end-inspiration the drawn volume matched (within ±1 s): what a "breaths
    /// followed" figure counts.
    pub breaths_matched: usize,
    /// The trace's end-inspirations in the part replayed (after the first latency).
    pub breaths_in_recording: usize,
    /// End-inspirations the follower confirmed over the replay, matched or not (it may confirm a
    /// partial last breath, or a turn the trace's hindsight does not count).
    pub breaths_detected: u64,
    /// Irregular breaths and pauses the follower found.
    pub irregular: super::detect::Counts,
    /// What happened to the samples.
    pub samples: SampleCounts,
    /// The largest baseline drift the follower followed, ml per second (an integrated flow with an
    /// offset or a leak; over about a tidal volume per second it cannot be followed live).
    pub largest_drift_ml_per_s: f64,
}

/// Replay `trace` as if live.
pub fn evaluate(trace: &Trace, opts: &EvalOptions) -> Evaluation {
    let Some(first) = trace.samples.first() else {
        return empty(opts, trace);
    };
    let last_ns = trace.samples.last().map_or(first.t_ns, |s| s.t_ns);
    let (mut sq, mut sq_hold, mut compared) = (0.0, 0.0, 0usize);
    let (mut frames, mut calibrating, mut lost, mut fell_back, mut clamped) = (0, 0, 0, 0, 0);
    let mut drawn: Vec<(u64, f64, f64)> = Vec::new();
    let mut drift: f64 = 0.0;
    let follower = replay(trace, opts, |tau, followed, follower| {
        frames += 1;
        let Some(f) = followed else { return };
        drift = drift.max((follower.detector().drift_per_s() * f.gain_ml_per_unit).abs());
        fell_back += usize::from(f.fell_back);
        clamped += usize::from(f.clamped);
        match f.state {
            SignalState::Lost => lost += 1,
            SignalState::Calibrating => calibrating += 1,
            _ => {
                drawn.push((tau, f.volume_ml, f.unpredicted_ml));
                if let Some(truth) = trace.truth_at(tau) {
                    sq += (f.volume_ml - truth).powi(2);
                    sq_hold += (f.unpredicted_ml - truth).powi(2);
                    compared += 1;
                }
            }
        }
    });
    let rms = |s: f64| {
        if compared > 0 {
            (s / compared as f64).sqrt()
        } else {
            f64::NAN
        }
    };
    let (rms_p, rms_h) = (rms(sq), rms(sq_hold));
    let percent = |v: f64| 100.0 * v / trace.tidal_ml;
    let ends_in_play: Vec<u64> = trace
        .end_inspiration_ns
        .iter()
        .copied()
        .filter(|&t| t >= first.t_ns + opts.latency_ns && t <= last_ns)
        .collect();
    let times: Vec<u64> = drawn.iter().map(|d| d.0).collect();
    let pred: Vec<f64> = drawn.iter().map(|d| d.1).collect();
    let hold: Vec<f64> = drawn.iter().map(|d| d.2).collect();
    let h = 0.25 * trace.tidal_ml;
    let (lag_p, matched) = lag(&ends_in_play, &peaks(&times, &pred, h));
    let (lag_h, _) = lag(&ends_in_play, &peaks(&times, &hold, h));
    Evaluation {
        predictor: opts.follower.predictor.describe(),
        latency_ms: opts.latency_ns as f64 * 1e-6,
        frames,
        frames_compared: compared,
        frames_calibrating: calibrating,
        frames_lost: lost,
        frames_fell_back: fell_back,
        frames_clamped: clamped,
        tidal_ml: trace.tidal_ml,
        rms_error_ml: rms_p,
        rms_error_ml_without_prediction: rms_h,
        rms_error_percent_of_tidal: percent(rms_p),
        rms_error_percent_of_tidal_without_prediction: percent(rms_h),
        lag_ms: lag_p,
        lag_ms_without_prediction: lag_h,
        breaths_matched: matched,
        breaths_in_recording: ends_in_play.len(),
        breaths_detected: follower.peaks(),
        irregular: follower.counts(),
        samples: follower.samples(),
        largest_drift_ml_per_s: drift,
    }
}

fn empty(opts: &EvalOptions, trace: &Trace) -> Evaluation {
    Evaluation {
        predictor: opts.follower.predictor.describe(),
        latency_ms: opts.latency_ns as f64 * 1e-6,
        frames: 0,
        frames_compared: 0,
        frames_calibrating: 0,
        frames_lost: 0,
        frames_fell_back: 0,
        frames_clamped: 0,
        tidal_ml: trace.tidal_ml,
        rms_error_ml: f64::NAN,
        rms_error_ml_without_prediction: f64::NAN,
        rms_error_percent_of_tidal: f64::NAN,
        rms_error_percent_of_tidal_without_prediction: f64::NAN,
        lag_ms: None,
        lag_ms_without_prediction: None,
        breaths_matched: 0,
        breaths_in_recording: 0,
        breaths_detected: 0,
        irregular: Default::default(),
        samples: Default::default(),
        largest_drift_ml_per_s: 0.0,
    }
}

/// Times of the maxima of a series, found with hysteresis `h` (a peak is confirmed once the
/// series falls `h` below it, and the next only after it rose `h` above the trough between).
pub fn peaks(times: &[u64], values: &[f64], h: f64) -> Vec<u64> {
    let mut out = Vec::new();
    if !(h > 0.0) {
        return out;
    }
    let mut rising = true;
    let (mut ext_t, mut ext_v) = (0u64, f64::NEG_INFINITY);
    let mut low = f64::INFINITY;
    for (&t, &v) in times.iter().zip(values) {
        if rising {
            if v > ext_v {
                ext_t = t;
                ext_v = v;
            } else if v < ext_v - h && ext_v > low + h {
                out.push(ext_t);
                rising = false;
                low = v;
            }
            low = low.min(v);
        } else if v < low {
            low = v;
        } else if v > low + h {
            rising = true;
            ext_t = t;
            ext_v = v;
        }
    }
    out
}

/// Mean of drawn − recorded end-inspiration over recorded ones with a drawn one within ±1 s, ms;
/// and how many matched.
pub fn lag(recorded: &[u64], drawn: &[u64]) -> (Option<f64>, usize) {
    let mut sum = 0.0;
    let mut n = 0usize;
    for &r in recorded {
        let best = drawn
            .iter()
            .map(|&d| d as i128 - r as i128)
            .min_by_key(|d| d.abs());
        if let Some(d) = best.filter(|d| d.abs() <= 1_000_000_000) {
            sum += d as f64 * 1e-6;
            n += 1;
        }
    }
    ((n > 0).then(|| sum / n as f64), n)
}

/// Replay `trace` through a follower, calling `each(display time, volume, follower)` for every
/// frame from the first sample + latency to the last sample; returns the follower as it ended.
pub fn replay(
    trace: &Trace,
    opts: &EvalOptions,
    mut each: impl FnMut(u64, Option<Followed>, &Follower),
) -> Follower {
    let mut follower = Follower::new(opts.follower);
    let (Some(first), Some(last)) = (trace.samples.first(), trace.samples.last()) else {
        return follower;
    };
    let mut next = 0usize;
    let mut tau = first.t_ns + opts.latency_ns;
    while tau <= last.t_ns {
        let now = tau - opts.latency_ns;
        while next < trace.samples.len() && trace.samples[next].t_ns <= now {
            follower.push(trace.samples[next]);
            next += 1;
        }
        each(tau, follower.volume_at(now, tau), &follower);
        tau += opts.frame_period_ns.max(1);
    }
    follower
}

/// Each frame of a replay, for a picture: (display time from the first sample s, hindsight ml,
/// drawn ml, unpredicted ml, state).
pub fn frames(trace: &Trace, opts: &EvalOptions) -> Vec<(f64, f64, f64, f64, SignalState)> {
    let t0 = trace.samples.first().map_or(0, |s| s.t_ns);
    let mut out = Vec::new();
    replay(trace, opts, |tau, followed, _| {
        if let Some(f) = followed {
            out.push((
                (tau - t0) as f64 * 1e-9,
                trace.truth_at(tau).unwrap_or(f64::NAN),
                f.volume_ml,
                f.unpredicted_ml,
                f.state,
            ));
        }
    });
    out
}
