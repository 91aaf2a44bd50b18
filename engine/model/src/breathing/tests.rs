//! Tests of the breathing follower: the grid never reads ahead, the predictors against a known
//! signal, breaths and irregular breaths found, losses, extremes (flat for an hour, huge values,
//! NaN, a sample in the far future) and replay on recordings (the shared real ones said aloud
//! when absent).

use super::detect::{BreathKind, Detector, Pause, Turn};
use super::evaluate::{evaluate, peaks, EvalOptions, Trace};
use super::follow::{Calibration, Follower, FollowerConfig, SignalState};
use super::grid::{Arrival, Grid};
use super::predict::{PredictorKind, SignalPredictor};
use super::{SignalSample, TRACE_START_NS};
use crate::recording::{read_recording, Synthetic};
use proptest::prelude::*;

const MS: u64 = 1_000_000;

fn sample(t_ns: u64, value: f64) -> SignalSample {
    SignalSample {
        t_ns,
        value,
        valid: true,
    }
}

/// A breathing-like signal: 4 s period, `amp` peak to trough, baseline drifting `drift` per s.
fn breathing(t_s: f64, amp: f64, drift: f64) -> f64 {
    let phase = (t_s / 4.0).fract();
    // Inspiration 1.5 s (half a cosine up), expiration 2.5 s (exponential-like fall).
    let v = if phase < 0.375 {
        0.5 * (1.0 - (std::f64::consts::PI * phase / 0.375).cos())
    } else {
        let x = (phase - 0.375) / 0.625;
        ((-4.0 * x).exp() - (-4.0f64).exp()) / (1.0 - (-4.0f64).exp())
    };
    amp * v + drift * t_s
}

fn feed(f: &mut Follower, seconds: f64, rate_hz: f64, signal: impl Fn(f64) -> f64) {
    let n = (seconds * rate_hz) as u64;
    for i in 0..n {
        let t_s = i as f64 / rate_hz;
        f.push(sample(TRACE_START_NS + (t_s * 1e9) as u64, signal(t_s)));
    }
}

#[test]
fn the_grid_interpolates_and_never_reads_ahead_of_the_newest_sample() {
    let mut g = Grid::new(20 * MS, 100 * MS);
    assert_eq!(g.begin(1_000 * MS, 0.0), Arrival::Restarted);
    // A sample 50 ms later on the line v = t(ms): grid points at +20 and +40 only.
    assert_eq!(g.begin(1_050 * MS, 50.0), Arrival::Follows);
    let mut added = 0;
    while g.step() {
        added += 1;
    }
    assert_eq!(added, 2);
    assert_eq!(g.newest_ns(), 1_040 * MS);
    assert!((g.back(0).unwrap() - 40.0).abs() < 1e-12);
    assert!((g.back(1).unwrap() - 20.0).abs() < 1e-12);
    assert_eq!(g.last_sample(), Some((1_050 * MS, 50.0)));
    // A repeat and an older sample are refused; a gap past the limit restarts.
    assert_eq!(g.begin(1_050 * MS, 7.0), Arrival::NotNewer);
    assert_eq!(g.begin(1_010 * MS, 7.0), Arrival::NotNewer);
    assert_eq!(g.begin(1_300 * MS, 9.0), Arrival::Restarted);
    assert_eq!(g.len(), 1);
}

#[test]
fn predictor_names_parse_and_bad_ones_say_what_is_accepted() {
    assert_eq!(PredictorKind::parse("none").unwrap(), PredictorKind::Hold);
    assert_eq!(
        PredictorKind::parse("linear:6").unwrap(),
        PredictorKind::Linear { window: 6 }
    );
    assert_eq!(
        PredictorKind::parse("ar:4:0.99").unwrap(),
        PredictorKind::Ar {
            order: 4,
            lambda: 0.99
        }
    );
    assert_eq!(PredictorKind::parse("ar").unwrap(), PredictorKind::DEFAULT);
    for bad in [
        "", "kalman", "ar:0", "ar:13", "ar:2.5", "ar:4:1.5", "ar:4:nan", "linear:1", "none:3",
    ] {
        let e = PredictorKind::parse(bad).unwrap_err();
        assert!(
            e.contains("predictor") && (e.contains("…") || e.contains("not")),
            "{bad:?}: {e}"
        );
    }
}

/// RMS error of predicting `lead_ms` ahead on the breathing signal at 50 Hz, over 60 s after a
/// 20 s warm-up.
fn prediction_rms(kind: PredictorKind, lead_ms: u64) -> f64 {
    let mut g = Grid::new(20 * MS, 100 * MS);
    let mut p = SignalPredictor::new(kind);
    let (mut sq, mut n) = (0.0, 0);
    for i in 0..4000u64 {
        let t = TRACE_START_NS + i * 20 * MS;
        let v = breathing(i as f64 * 0.02, 500.0, 0.0);
        if g.begin(t, v) == Arrival::Follows {
            while g.step() {
                p.learn(&g);
            }
        }
        if i >= 1000 {
            let target = t + lead_ms * MS;
            let truth = breathing((target - TRACE_START_NS) as f64 * 1e-9, 500.0, 0.0);
            let got = p.predict(&g, target).unwrap();
            assert!(got.value.is_finite());
            sq += (got.value - truth).powi(2);
            n += 1;
        }
    }
    (sq / n as f64).sqrt()
}

#[test]
fn prediction_beats_holding_the_newest_sample_on_a_breathing_signal() {
    let hold = prediction_rms(PredictorKind::Hold, 100);
    let line = prediction_rms(PredictorKind::LINE, 100);
    let ar = prediction_rms(PredictorKind::DEFAULT, 100);
    eprintln!("100 ms ahead, 500 ml breaths: hold {hold:.2} ml, line {line:.2} ml, AR {ar:.2} ml");
    assert!(line < 0.5 * hold, "line {line} hold {hold}");
    assert!(ar < 0.5 * hold, "ar {ar} hold {hold}");
    // Zero lead: every predictor gives the signal.
    assert!(prediction_rms(PredictorKind::DEFAULT, 0) < 1e-9);
}

#[test]
fn breaths_are_counted_and_sighs_and_coughs_named() {
    let mut d = Detector::new();
    let mut kinds = Vec::new();
    // 20 breaths of 4 s at 50 Hz; breath 10 is a sigh (2.2× deep), breath 14 a cough (its
    // expiration squeezed into 0.3 s).
    for i in 0..4000u64 {
        let t_s = i as f64 * 0.02;
        let k = (t_s / 4.0) as u64;
        let phase = (t_s / 4.0).fract();
        let v = match k {
            10 => breathing(t_s, 1100.0, 0.0),
            14 if phase >= 0.375 => {
                let x = ((phase - 0.375) / 0.075).min(1.0);
                500.0 * (1.0 - x)
            }
            _ => breathing(t_s, 500.0, 0.0),
        };
        if let Some(Turn::Trough(_, _, Some(b))) = d.push(TRACE_START_NS + i * 20 * MS, v) {
            kinds.push(b.kind);
        }
    }
    let c = d.counts();
    assert!((17..=19).contains(&c.breaths), "{c:?}");
    assert_eq!(c.sighs, 1, "{kinds:?}");
    assert_eq!(c.coughs, 1, "{kinds:?}");
    assert_eq!(
        kinds.iter().filter(|k| **k == BreathKind::Regular).count() as u64,
        c.breaths - 2
    );
    // The sigh did not move the typical amplitude.
    let a = d.typical_amplitude().unwrap();
    assert!((a - 500.0).abs() < 10.0, "{a}");
    assert!((d.typical_period_s().unwrap() - 4.0).abs() < 0.05);
}

/// The live detector judges clipping over its latest turns, as `breathing check` does over a
/// whole trace: breaths of unequal depth cut at one value are said (at the top, or at the bottom),
/// and allocates nothing to do it; equal breaths, and the same unequal breaths uncut, are not.
#[test]
fn the_detector_says_when_the_latest_breaths_are_cut_at_one_value() {
    let run = |f: &dyn Fn(f64) -> f64| {
        let mut det = Detector::new();
        let mut said = Vec::new();
        for i in 0..(90.0 * 25.0) as u64 {
            let t_s = i as f64 / 25.0;
            let b = (t_s / 4.0).floor();
            let depth = 0.6 + 0.8 * (b * 0.618_034).fract();
            if det
                .push(
                    TRACE_START_NS + i * 40_000_000,
                    f(breathing(t_s, depth, 0.0)),
                )
                .is_some()
            {
                said.push(det.clipped());
            }
        }
        said
    };
    let top = run(&|v| v.min(1.2));
    assert_eq!(top.last(), Some(&Some(true)), "{top:?}");
    assert!(!top.contains(&Some(false)));
    let bottom = run(&|v| (2.0 - v).max(0.8));
    assert_eq!(bottom.last(), Some(&Some(false)), "{bottom:?}");
    assert!(!bottom.contains(&Some(true)));
    assert!(run(&|v| v).iter().all(|c| c.is_none()));
    let mut det = Detector::new();
    for i in 0..(90.0 * 25.0) as u64 {
        let t_s = i as f64 / 25.0;
        det.push(TRACE_START_NS + i * 40_000_000, breathing(t_s, 1.0, 0.0));
        assert_eq!(det.clipped(), None, "{t_s} s");
    }
}

#[test]
fn a_held_breath_and_an_apnoea_are_pauses_of_their_kind() {
    let mut d = Detector::new();
    let mut hold_seen = false;
    let mut apnoea_seen = false;
    // 5 breaths, a 12 s breath-hold at full inspiration, 5 breaths, a 14 s apnoea at rest, 5.
    let mut t = 0.0;
    let push = |d: &mut Detector, t: f64, v: f64| {
        d.push(TRACE_START_NS + (t * 1e9) as u64, v);
    };
    while t < 20.0 {
        push(&mut d, t, breathing(t, 500.0, 0.0));
        t += 0.02;
    }
    // Rise to full inspiration then hold.
    let t_hold = t;
    while t < t_hold + 12.0 {
        let x = ((t - t_hold) / 1.0).min(1.0);
        push(&mut d, t, 500.0 * x);
        hold_seen |= d.pause() == Some(Pause::BreathHold);
        t += 0.02;
    }
    let t_back = t;
    while t < t_back + 20.0 {
        let x = (1.0 - (t - t_back) / 1.0).max(0.0);
        let v = if t - t_back < 1.0 {
            500.0 * x
        } else {
            breathing(t - t_back - 1.0, 500.0, 0.0)
        };
        push(&mut d, t, v);
        t += 0.02;
    }
    let t_rest = t;
    while t < t_rest + 14.0 {
        push(&mut d, t, 0.0);
        apnoea_seen |= d.pause() == Some(Pause::Apnoea);
        t += 0.02;
    }
    while t < t_rest + 34.0 {
        push(&mut d, t, breathing(t - t_rest - 14.0, 500.0, 0.0));
        t += 0.02;
    }
    assert!(hold_seen, "{:?}", d.counts());
    assert!(apnoea_seen, "{:?}", d.counts());
    let c = d.counts();
    assert_eq!((c.breath_holds, c.apnoeas), (1, 1), "{c:?}");
    assert_eq!(d.pause(), None);
}

#[test]
fn a_flat_or_noisy_signal_is_no_storm_of_breaths() {
    let mut d = Detector::new();
    for i in 0..50_000u64 {
        d.push(TRACE_START_NS + i * 20 * MS, 3.0);
    }
    assert_eq!(d.counts().breaths, 0);
    // Noise of ±1 unit: a deterministic pseudo-random walk-free sequence.
    let mut d = Detector::new();
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    for i in 0..50_000u64 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let noise = (x % 2001) as f64 / 1000.0 - 1.0;
        d.push(TRACE_START_NS + i * 20 * MS, noise);
    }
    // A few spurious turning points at most in 1000 s of pure noise (hysteresis ≥ 4× the noise).
    assert!(d.counts().breaths < 20, "{:?}", d.counts());
}

fn volume_follower(rate_hz: f64) -> Follower {
    Follower::new(FollowerConfig::at_rate(rate_hz, Calibration::Volume))
}

#[test]
fn a_drifting_volume_is_followed_above_its_moving_baseline() {
    // 500 ml breaths with the integrator drifting 20 ml/s (a leak): the follower reports volume
    // above end-expiration, not the drift.
    let mut f = volume_follower(50.0);
    feed(&mut f, 60.0, 50.0, |t| breathing(t, 500.0, 20.0));
    let now = TRACE_START_NS + 60 * 1_000 * MS - 20 * MS;
    let mut worst: f64 = 0.0;
    for k in 0..40u64 {
        // Look 1 ms … 40 ms ahead of the last sample only (a prediction test elsewhere).
        let g = f.volume_at(now, now + k * MS).unwrap();
        let truth = breathing((now + k * MS - TRACE_START_NS) as f64 * 1e-9, 500.0, 0.0);
        worst = worst.max((g.volume_ml - truth).abs());
        assert_eq!(g.state, SignalState::Following);
    }
    assert!(worst < 25.0, "worst {worst} ml");
}

#[test]
fn auto_calibration_maps_the_typical_breath_to_the_tidal_volume() {
    // A chest marker moving 8 mm per breath; the scene's tidal volume 450 ml.
    let mut f = Follower::new(FollowerConfig::at_rate(
        30.0,
        Calibration::Auto { tidal_ml: 450.0 },
    ));
    feed(&mut f, 40.0, 30.0, |t| breathing(t, 8.0, 0.0));
    let g = f.gain().unwrap();
    assert!((g - 450.0 / 8.0).abs() < 2.0, "gain {g} ml/mm");
}

#[test]
fn a_lost_signal_is_said_within_100_ms_and_the_follower_recovers() {
    let mut f = volume_follower(50.0);
    feed(&mut f, 30.0, 50.0, |t| breathing(t, 500.0, 0.0));
    let last = f.volume_at(TRACE_START_NS + 30_000 * MS, TRACE_START_NS + 30_050 * MS);
    assert_eq!(last.unwrap().state, SignalState::Following);
    let t_last = TRACE_START_NS + 29_980 * MS;
    let at = |ms: u64| {
        f.volume_at(t_last + ms * MS, t_last + ms * MS)
            .unwrap()
            .state
    };
    assert_ne!(at(60), SignalState::Lost);
    assert_eq!(at(101), SignalState::Lost);
    // 5 s later the signal is back: a restart, counted, and following within two breaths.
    for i in 0..600u64 {
        let t_s = 35.0 + i as f64 * 0.02;
        f.push(sample(
            TRACE_START_NS + (t_s * 1e9) as u64,
            breathing(t_s, 500.0, 0.0),
        ));
    }
    assert_eq!(f.samples().restarts, 1);
    let t = TRACE_START_NS + 46_980 * MS;
    assert_eq!(f.volume_at(t, t).unwrap().state, SignalState::Following);
}

/// A volume (its gain known) drives the lungs from its first samples — before its first
/// end-expiration the baseline is the lowest value seen so far —, unless the range it shows is no
/// plausible breath; an amplitude waits for its gain, two regular breaths.
#[test]
fn a_volume_is_followed_from_its_first_samples_an_amplitude_after_two_breaths() {
    let run = |calibration: Calibration, seconds: f64, signal: &dyn Fn(f64) -> f64| {
        let mut f = Follower::new(FollowerConfig::at_rate(50.0, calibration));
        feed(&mut f, seconds, 50.0, signal);
        f
    };
    let at = |f: &Follower, seconds: f64| {
        let t = TRACE_START_NS + (seconds * 1e9) as u64;
        f.volume_at(t, t).unwrap()
    };
    // Starting at its end-expiration (0 s): followed from the first samples, the breath drawn as
    // the signal above where it began; the first trough (4 s) is confirmed later.
    for calibration in [Calibration::Volume, Calibration::Fixed { ml_per_unit: 2.0 }] {
        let gain = if calibration == Calibration::Volume {
            1.0
        } else {
            2.0
        };
        for seconds in [0.3, 1.0, 1.5, 2.5, 3.9] {
            let f = run(calibration, seconds, &|t| breathing(t, 250.0, 0.0));
            let g = at(&f, seconds);
            assert_eq!(
                g.state,
                SignalState::Following,
                "{calibration:?} at {seconds} s"
            );
            assert_eq!(f.detector().end_expirations(), 0);
            let last = seconds - 0.02;
            let want = gain * breathing(last, 250.0, 0.0);
            assert!(
                (g.unpredicted_ml - want).abs() < 1e-6 && !g.clamped,
                "{calibration:?} at {seconds} s: {} ml against {want} ml",
                g.unpredicted_ml
            );
        }
        let f = run(calibration, 5.0, &|t| breathing(t, 250.0, 0.0));
        assert_eq!(at(&f, 5.0).state, SignalState::Following);
        assert_eq!(f.detector().end_expirations(), 1);
    }
    // Starting half-way up an inspiration: drawn from there (the breath's first half is not
    // seen), 0 ml through the expiration below where it began, and no step when the first
    // end-expiration is confirmed.
    let late = |t: f64| breathing(t + 0.75, 500.0, 0.0);
    let mut f = Follower::new(FollowerConfig::at_rate(50.0, Calibration::Volume));
    let (mut drawn, mut confirmed_at, mut on_the_line) = (Vec::new(), None, 0);
    for i in 0..400u64 {
        let t_s = i as f64 * 0.02;
        let t = TRACE_START_NS + (t_s * 1e9) as u64;
        f.push(sample(t, late(t_s)));
        let g = f.volume_at(t, t).unwrap();
        assert!(i == 0 || g.state == SignalState::Following, "at {t_s} s");
        // Before a breath has been seen, a display 50 ms ahead is predicted by the line through
        // the last four samples (2.5 sample periods on), above the lowest value so far; after,
        // by the scene's predictor.
        let ahead = f.volume_at(t, t + 50 * MS).unwrap();
        if f.detector().end_expirations() == 0 && i >= 4 && !ahead.clamped {
            let y: Vec<f64> = (0..4).map(|k| late(t_s - 0.02 * k as f64)).collect();
            // Least squares through x = 0, −1, −2, −3: mean −1.5, slope from the centred sums.
            let mean = y.iter().sum::<f64>() / 4.0;
            let slope = (0..4)
                .map(|k| (-(k as f64) + 1.5) * (y[k] - mean))
                .sum::<f64>()
                / 5.0;
            let lowest = (0..=i)
                .map(|j| late(j as f64 * 0.02))
                .fold(f64::MAX, f64::min);
            let want = mean + slope * (2.5 + 1.5) - lowest;
            on_the_line += 1;
            assert!(
                (ahead.volume_ml - want).abs() < 1e-6,
                "at {t_s} s: {} ml against the line's {want} ml",
                ahead.volume_ml
            );
        } else if (5.0..5.5).contains(&t_s) {
            // Expiring: 50 ms ahead lies below the newest sample.
            assert!(
                ahead.volume_ml < ahead.unpredicted_ml - 1.0,
                "at {t_s} s: {ahead:?}"
            );
        }
        if confirmed_at.is_none() && f.detector().end_expirations() == 1 {
            confirmed_at = Some(drawn.len());
        }
        drawn.push((t_s, g.unpredicted_ml));
    }
    assert!(
        on_the_line > 100,
        "{on_the_line} frames checked against the line"
    );
    let peak = drawn
        .iter()
        .filter(|d| d.0 < 2.0)
        .map(|d| d.1)
        .fold(f64::MIN, f64::max);
    assert!(
        (peak - 250.0).abs() < 1.0,
        "the first peak drawn: {peak} ml"
    );
    assert!(drawn
        .iter()
        .filter(|d| (2.3..3.2).contains(&d.0))
        .all(|d| d.1.abs() < 1e-9));
    let k = confirmed_at.expect("the first trough confirmed");
    assert!(
        (drawn[k].1 - drawn[k - 1].1).abs() < 30.0,
        "{:?}",
        &drawn[k - 2..k + 2]
    );
    let second_peak = drawn
        .iter()
        .filter(|d| (3.5..6.0).contains(&d.0))
        .map(|d| d.1);
    assert!((second_peak.fold(f64::MIN, f64::max) - 500.0).abs() < 1.0);
    // A flat start, and a first breath of 20 litres, wait for the first end-expiration.
    assert_eq!(
        at(&run(Calibration::Volume, 0.5, &|_| 100.0), 0.5).state,
        SignalState::Calibrating
    );
    let litres = run(Calibration::Volume, 1.0, &|t| breathing(t, 20_000.0, 0.0));
    assert_eq!(at(&litres, 1.0).state, SignalState::Calibrating);
    let auto = Calibration::Auto { tidal_ml: 500.0 };
    let signal = |t: f64| breathing(t, 500.0, 0.0);
    for (seconds, want) in [
        (1.0, SignalState::Calibrating),
        (5.0, SignalState::Calibrating),
        (9.0, SignalState::Calibrating),
        (13.0, SignalState::Following),
    ] {
        assert_eq!(
            at(&run(auto, seconds, &signal), seconds).state,
            want,
            "at {seconds} s"
        );
    }
}

/// A first breath that ends above where it began (here the integrator drifts 10 ml/s: 40 ml over
/// the 4 s breath): the baseline moves from the lowest value seen onto the first end-expiration
/// over half a second instead of stepping 40 ml in a frame.
#[test]
fn the_first_end_expiration_found_moves_the_baseline_without_a_step() {
    // Shown at once, and 100 ms and 600 ms after the newest sample (a latency: the fade runs on
    // the samples' clock).
    for lead_ms in [0u64, 100, 600] {
        first_trough_without_a_step(lead_ms);
    }
}

fn first_trough_without_a_step(lead_ms: u64) {
    let mut f = volume_follower(50.0);
    let mut drawn: Vec<(f64, f64, usize)> = Vec::new();
    for i in 0..400u64 {
        let t_s = i as f64 * 0.02;
        let t = TRACE_START_NS + (t_s * 1e9) as u64;
        f.push(sample(t, breathing(t_s, 500.0, 10.0)));
        let g = f.volume_at(t, t + lead_ms * MS).unwrap();
        // Calibrating only until the first samples span 5 ml (the smallest plausible breath).
        assert!(t_s < 0.3 || g.state == SignalState::Following, "at {t_s} s");
        drawn.push((t_s, g.unpredicted_ml, f.detector().end_expirations()));
    }
    let k = drawn
        .iter()
        .position(|d| d.2 == 1)
        .expect("the first trough");
    let jump = |a: usize, b: usize| drawn[b].1 - drawn[a].1;
    // The signal rises about 10 ml a frame there; a 40 ml baseline step would drop it by 30.
    let worst = (k - 3..k + 25)
        .map(|j| jump(j - 1, j))
        .fold(f64::MAX, f64::min);
    assert!(
        worst > 0.0,
        "shown {lead_ms} ms ahead, the drawn volume fell by {:.1} ml in a frame at {:.2} s",
        -worst,
        drawn[k].0
    );
    // Half a second later the baseline is the end-expiration itself (the drift after it aside).
    let later = &drawn[k + 30];
    let want = breathing(later.0, 500.0, 0.0) + 10.0 * (later.0 - 4.0);
    assert!(
        (later.1 - want).abs() < 3.0,
        "shown {lead_ms} ms ahead: {later:?} against {want:.1} ml"
    );
}

/// A reconfiguration once samples were taken (a device's rate became known), or a source whose
/// rate is not known yet: a signal whose gain is known waits for its first end-expiration, as a
/// follower restarted mid-breath would otherwise take wherever it restarted as its baseline.
#[test]
fn a_follower_restarted_mid_stream_waits_for_its_first_end_expiration() {
    let mut f = volume_follower(50.0);
    feed(&mut f, 1.0, 50.0, |t| breathing(t, 500.0, 0.0));
    let at = |f: &Follower, s: f64| {
        let t = TRACE_START_NS + (s * 1e9) as u64;
        f.volume_at(t, t).unwrap().state
    };
    assert_eq!(at(&f, 0.98), SignalState::Following);
    f.reconfigure(20 * MS, Calibration::Volume);
    for i in 50..400u64 {
        let t_s = i as f64 * 0.02;
        f.push(sample(
            TRACE_START_NS + (t_s * 1e9) as u64,
            breathing(t_s, 500.0, 0.0),
        ));
        let want = if f.detector().end_expirations() == 0 {
            SignalState::Calibrating
        } else {
            SignalState::Following
        };
        assert_eq!(at(&f, t_s), want, "at {t_s} s");
    }
    assert_eq!(f.detector().end_expirations(), 1);
    // Configured before its first sample: from the first samples, unless told to wait.
    let mut fresh = volume_follower(50.0);
    fresh.reconfigure(40 * MS, Calibration::Volume);
    feed(&mut fresh, 1.0, 25.0, |t| breathing(t, 500.0, 0.0));
    assert_eq!(at(&fresh, 0.96), SignalState::Following);
    // Lost for half a second before its first end-expiration, and back mid-breath: waits too.
    let mut lost = volume_follower(50.0);
    feed(&mut lost, 1.0, 50.0, |t| breathing(t, 500.0, 0.0));
    for i in 75..150u64 {
        let t_s = i as f64 * 0.02;
        lost.push(sample(
            TRACE_START_NS + (t_s * 1e9) as u64,
            breathing(t_s, 500.0, 0.0),
        ));
    }
    assert_eq!(lost.samples().restarts, 1);
    assert_eq!(lost.detector().end_expirations(), 0);
    assert_eq!(at(&lost, 2.98), SignalState::Calibrating);
    let mut waiting = volume_follower(50.0);
    waiting.wait_for_first_end_expiration();
    feed(&mut waiting, 1.0, 50.0, |t| breathing(t, 500.0, 0.0));
    assert_eq!(at(&waiting, 0.98), SignalState::Calibrating);
}

/// After a 5 s loss the follower is in step again within one breath: the baseline's drift is not
/// extrapolated across the gap (here the integrator's offset was zeroed during it, as a
/// ventilator's auto-zero does), and no breath is made of the turning points on either side.
#[test]
fn after_a_loss_the_follower_is_in_step_within_one_breath() {
    let mut f = volume_follower(50.0);
    let (gap_from, gap_to) = (20.5, 25.5);
    let signal = |t: f64| breathing(t, 500.0, 0.0) + 10.0 * t.min(gap_from);
    let mut errors: Vec<(f64, f64)> = Vec::new();
    for i in 0..(40 * 50) {
        let t_s = i as f64 * 0.02;
        if (gap_from..gap_to).contains(&t_s) {
            continue;
        }
        let t = TRACE_START_NS + (t_s * 1e9) as u64;
        f.push(sample(t, signal(t_s)));
        if t_s >= gap_to {
            let v = f.volume_at(t, t).unwrap();
            assert_eq!(v.state, SignalState::Following, "{t_s} s");
            errors.push((t_s, v.unpredicted_ml - breathing(t_s, 500.0, 0.0)));
        }
    }
    assert_eq!(f.samples().restarts, 1);
    let rms = |from: f64, to: f64| {
        let e: Vec<f64> = errors
            .iter()
            .filter(|e| (from..to).contains(&e.0))
            .map(|e| e.1 * e.1)
            .collect();
        (e.iter().sum::<f64>() / e.len() as f64).sqrt()
    };
    // The first breath after the gap (to its end-expiration at 28 s): the baseline held where it
    // was; from the next, the new end-expiration: within 3 % of the tidal volume.
    let (first, next) = (rms(gap_to, 28.0), rms(28.5, 40.0));
    assert!(first < 0.1 * 500.0, "{first:.1} ml");
    assert!(
        next < 0.03 * 500.0,
        "{next:.1} ml (first breath {first:.1} ml)"
    );
    assert!(
        f.detector().typical_period_s().unwrap() < 4.5,
        "no breath spans the gap"
    );
}

#[test]
fn bad_samples_are_counted_and_never_reach_the_volume() {
    let mut f = volume_follower(50.0);
    feed(&mut f, 20.0, 50.0, |t| breathing(t, 500.0, 0.0));
    let t = TRACE_START_NS + 20_000 * MS;
    f.push(sample(t, f64::NAN));
    f.push(sample(t, f64::INFINITY));
    f.push(SignalSample {
        t_ns: t,
        value: 10.0,
        valid: false,
    });
    f.push(sample(t - 500 * MS, 10.0));
    let s = f.samples();
    assert_eq!((s.invalid, s.not_newer), (3, 1));
    let g = f.volume_at(t, t + 50 * MS).unwrap();
    assert!(g.volume_ml.is_finite() && g.unpredicted_ml.is_finite());
    // A wild value is drawn within −0.5…3 tidal volumes, flagged.
    f.push(sample(t + 20 * MS, 1e300));
    let g = f.volume_at(t + 20 * MS, t + 60 * MS).unwrap();
    assert!(g.volume_ml.is_finite() && g.clamped, "{g:?}");
    assert!(g.volume_ml <= 3.0 * 500.0 + 1.0);
    // A sample stamped in the far future restarts the grid; the next real one is refused as older,
    // and the signal is said lost (its newest sample is not "now").
    f.push(sample(u64::MAX, 1.0));
    f.push(sample(t + 40 * MS, 1.0));
    assert_eq!(f.samples().not_newer, 2);
}

#[test]
fn an_hour_of_flat_signal_keeps_every_number_finite() {
    let mut f = volume_follower(50.0);
    feed(&mut f, 20.0, 50.0, |t| breathing(t, 500.0, 0.0));
    // One hour at a constant level (a ventilator disconnected, a held breath), then breathing.
    let start = 20.0;
    for i in 0..(3600 * 50) as u64 {
        f.push(sample(
            TRACE_START_NS + ((start + i as f64 * 0.02) * 1e9) as u64,
            123.0,
        ));
    }
    let t = TRACE_START_NS + ((start + 3600.0) * 1e9) as u64;
    let g = f.volume_at(t, t + 80 * MS).unwrap();
    assert!(g.volume_ml.is_finite(), "{g:?}");
    assert!(matches!(g.state, SignalState::Paused(_)), "{g:?}");
    feed(&mut f, 0.0, 50.0, |_| 0.0);
    for i in 0..(30 * 50) as u64 {
        let t_s = start + 3600.0 + 0.02 + i as f64 * 0.02;
        f.push(sample(
            TRACE_START_NS + (t_s * 1e9) as u64,
            123.0 + breathing(t_s, 500.0, 0.0),
        ));
    }
    let t = TRACE_START_NS + ((start + 3629.9) * 1e9) as u64;
    let g = f.volume_at(t, t + 80 * MS).unwrap();
    assert!(g.volume_ml.is_finite() && !g.fell_back, "{g:?}");
    assert_eq!(g.state, SignalState::Following);
}

#[test]
fn the_same_samples_give_bit_identical_volumes() {
    let run = || {
        let mut f = volume_follower(30.0);
        feed(&mut f, 30.0, 30.0, |t| {
            breathing(t, 7.5, 0.1) + (t * 13.0).sin() * 0.05
        });
        let t = TRACE_START_NS + 29_990 * MS;
        (f.volume_at(t, t + 70 * MS).unwrap(), f)
    };
    let (a, fa) = run();
    let (b, fb) = run();
    assert_eq!(a.volume_ml.to_bits(), b.volume_ml.to_bits());
    assert_eq!(fa, fb);
}

#[test]
fn peaks_are_found_with_hysteresis() {
    let times: Vec<u64> = (0..1000).map(|i| i * 20 * MS).collect();
    let values: Vec<f64> = (0..1000)
        .map(|i| breathing(i as f64 * 0.02, 500.0, 0.0))
        .collect();
    let p = peaks(&times, &values, 125.0);
    assert_eq!(p.len(), 5);
    // The breathing signal peaks 1.5 s into each 4 s breath.
    assert!((p[0] as f64 * 1e-9 - 1.5).abs() < 0.021, "{p:?}");
    assert!(peaks(&times, &values, 0.0).is_empty());
}

fn replay_options(latency_ms: u64, predictor: PredictorKind, rate_hz: f64) -> EvalOptions {
    let mut follower = FollowerConfig::at_rate(rate_hz, Calibration::Volume);
    follower.predictor = predictor;
    EvalOptions {
        latency_ns: latency_ms * MS,
        frame_period_ns: 16_666_667,
        follower,
    }
}

#[test]
fn a_synthetic_ventilator_recording_replays_with_prediction_ahead_of_none() {
    let rec = Synthetic {
        breaths: 20,
        ..Synthetic::default()
    }
    .recording();
    let trace = Trace::from_recording(&rec).unwrap();
    assert!((trace.tidal_ml - 500.0).abs() < 1.0, "{}", trace.tidal_ml);
    let e = evaluate(
        &trace,
        &replay_options(100, PredictorKind::DEFAULT, trace.rate_hz),
    );
    eprintln!("{e:#?}");
    assert!(e.frames_compared > 1000);
    assert!(e.rms_error_ml < e.rms_error_ml_without_prediction, "{e:?}");
    // The volume is drawn about 100 ms late without prediction.
    let late = e.lag_ms_without_prediction.unwrap();
    assert!((late - 100.0).abs() < 25.0, "{late}");
    assert!(e.breaths_matched >= e.breaths_in_recording - 1, "{e:?}");
}

/// The real ICU recordings (../shared/data/ventilator) replayed live: prediction must beat none.
/// The figures printed are those docs/BREATHING.md quotes (`lungdyn breathing check` measures
/// them too). Said aloud when the data is absent.
#[test]
fn the_real_ventilator_recordings_are_followed_better_with_prediction() {
    let root =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/ventilator");
    if !root.exists() {
        eprintln!(
            "SKIPPED (said aloud): {} is absent: the follower was not replayed on real recordings",
            root.display()
        );
        return;
    }
    // The ARDS patient and the third example: prediction must beat none. The COPD recording's
    // flow holds seconds of −30 L/min between breaths (its name: "neg-flows"): integrated live it
    // falls by litres per breath, which no live baseline follows; its figures are printed, and the
    // follower must not claim it: it finds fewer breaths than the recording holds.
    for (name, must_beat) in [
        ("ventmap_ards-alone.csv", true),
        ("ventmap_ards-with-copd-and-neg-flows.csv", false),
        ("ventmap_jimmy-example-data.csv", true),
    ] {
        let rec = read_recording(&root.join(name), crate::input::ReadLimits::TABLE).unwrap();
        let trace = Trace::from_recording(&rec).unwrap();
        for latency in [0, 50, 100] {
            let e = evaluate(
                &trace,
                &replay_options(latency, PredictorKind::DEFAULT, trace.rate_hz),
            );
            let line = evaluate(
                &trace,
                &replay_options(latency, PredictorKind::LINE, trace.rate_hz),
            );
            let cycle = evaluate(
                &trace,
                &replay_options(
                    latency,
                    PredictorKind::Cycle {
                        horizon_ms: latency as u32,
                    },
                    trace.rate_hz,
                ),
            );
            eprintln!(
                "{name} {latency} ms: AR {:.2} % cycle {:.2} % (lag {:?}) line {:.2} % none {:.2} % of tidal {:.0} ml; lag {:?} / {:?} ms; breaths {}/{}; drift {:.0} ml/s",
                e.rms_error_percent_of_tidal,
                cycle.rms_error_percent_of_tidal,
                cycle.lag_ms,
                line.rms_error_percent_of_tidal,
                e.rms_error_percent_of_tidal_without_prediction,
                e.tidal_ml,
                e.lag_ms,
                e.lag_ms_without_prediction,
                e.breaths_matched,
                e.breaths_in_recording,
                e.largest_drift_ml_per_s,
            );
            assert!(e.rms_error_ml.is_finite(), "{name}: {e:?}");
            if must_beat {
                assert!(e.frames_compared > 100, "{name}: {e:?}");
                // With no latency there is nothing to predict: the two agree within 1 %.
                let slack = if latency == 0 { 1.01 } else { 1.0 };
                assert!(
                    e.rms_error_ml < slack * e.rms_error_ml_without_prediction,
                    "{name} {latency} ms: {e:?}"
                );
            } else {
                assert!(
                    (e.breaths_detected as usize) < e.breaths_in_recording,
                    "{name}: {e:?}"
                );
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Whatever arrives — jittered, repeated, reordered, huge, tiny, invalid — every volume is
    /// finite and within the drawn range.
    #[test]
    fn any_samples_give_finite_volumes_within_range(
        steps in prop::collection::vec(
            (0u64..60_000_000, prop_oneof![
                -1e3f64..1e3,
                -1e12f64..1e12,
                Just(0.0),
                Just(f64::NAN),
                -1e-9f64..1e-9,
            ], any::<bool>()),
            1..600,
        ),
        lead_ms in 0u64..500,
    ) {
        let mut f = volume_follower(50.0);
        let mut t = TRACE_START_NS;
        for (dt, v, valid) in steps {
            t += dt;
            f.push(SignalSample { t_ns: t, value: v, valid });
            if let Some(g) = f.volume_at(t, t + lead_ms * MS) {
                prop_assert!(g.volume_ml.is_finite() && g.unpredicted_ml.is_finite(), "{g:?}");
                let tidal = g.gain_ml_per_unit * f.detector().typical_amplitude().unwrap_or(0.0);
                prop_assert!(g.volume_ml <= 3.0 * tidal + 1e-6 * tidal.abs() + 1e-9, "{g:?} {tidal}");
                prop_assert!(g.volume_ml >= -0.5 * tidal - 1e-6 * tidal.abs() - 1e-9, "{g:?} {tidal}");
            }
        }
    }
}

#[test]
fn csv_trace_headers_name_their_units_as_every_table_reader_does() {
    use super::trace::{parse_trace, SignalUnit};
    let table = |header: &str, time_scale: f64| {
        let mut s = format!("{header}\n");
        for i in 0..500 {
            let t = i as f64 * 0.04;
            s += &format!("{},{:.6}\n", t * time_scale, (t * 1.3).sin());
        }
        s
    };
    for (header, time_scale, unit, factor) in [
        ("time_s,amplitude_mm", 1.0, SignalUnit::Mm, 1.0),
        ("t (s),Amplitude (cm)", 1.0, SignalUnit::Mm, 10.0),
        ("Time [ms],excursion_mm", 1000.0, SignalUnit::Mm, 1.0),
        ("time_s,signal (a.u.)", 1.0, SignalUnit::Arbitrary, 1.0),
        ("time_s,amplitude_au", 1.0, SignalUnit::Arbitrary, 1.0),
        ("time_s,volume_L", 1.0, SignalUnit::Ml, 1000.0),
        ("time_s,Volume (ml)", 1.0, SignalUnit::Ml, 1.0),
    ] {
        let t = parse_trace(table(header, time_scale).as_bytes())
            .unwrap_or_else(|e| panic!("{header}: {e:?}"));
        assert_eq!(t.unit, unit, "{header}");
        let want = (10.0f64 * 0.04 * 1.3).sin() * factor;
        assert!(
            (t.samples[10].value - want).abs() < 1e-4 * factor,
            "{header}: {:?}",
            t.samples[10]
        );
        assert!((t.rate_hz - 25.0).abs() < 0.1, "{header}: {} Hz", t.rate_hz);
    }
    for header in [
        "time,amplitude_mm",
        "time_s,amplitude",
        "time_s,volume_kg",
        "time_s,pressure_cmH2O",
    ] {
        let e = parse_trace(table(header, 1.0).as_bytes()).expect_err(header);
        assert!(e.1.contains("unit"), "{header}: {e:?}");
    }
}
