//! # ventilated: a disease course on a ventilator's recorded breath (EQUATIONS §4.7)
//!
//! A `[pv] waveform` scene plays a ventilator recording: a passive patient whose breath the
//! ventilator sets. A disease on such a scene keeps everything the course does to the lungs'
//! *shapes* (collapse towards the hilum, drop, mediastinal shift, holds, arrest; eq. 8.1–8.2,
//! 8.10–8.13) and replaces what it does to the *breath*:
//!
//! * **The ventilator delivers the recorded volume.** Under volume control the ventilator imposes
//!   the flow; the equation of motion `Paw = V/C + R·flow + P0` (EQUATIONS §1.4; Bates 2009, ch. 2)
//!   then sets the airway *pressure*, not the volume: a stiffer or smaller lung raises the peak
//!   pressure — the rising airway pressure that is the ventilated patient's sign of a (tension)
//!   pneumothorax (Leigh-Smith & Harris, Emerg Med J 2005;22:8–16; Roberts et al., Ann Surg
//!   2015;261:1068–1078) — while the tidal volume stays the set one. Every breath delivers
//!   `Σ share_i·TV_rec` ml, what the healthy scene's lungs take ([`delivered_ml`]).
//! * **The lungs share it by compliance.** Two lungs in parallel at one airway pressure fill in
//!   proportion to their compliances (Otis et al., J Appl Physiol 1956;8:427–443), and a lung's
//!   compliance is in proportion to its aerated volume (specific compliance; West, *Respiratory
//!   Physiology*, ch. 7). That is the proportion the course's own tidal volumes already have with
//!   α = 0: eq. 8.6 gives the collapsing lung `share·TV·(1 − dV)` (its aerated fraction), the other
//!   lung `share·TV` — so [`deliver`] scales the breathing lungs' tidal volumes by one factor to the
//!   delivered volume, and the collapsing lung's lost share moves to the other lung.
//! * **What a spontaneous breath adds does not apply:** eq. 8.7's α (extra effort) is 0, eq. 8.3–8.5
//!   and the clinical rate (the respiratory centre quickening the breath) are replaced by the
//!   ventilator's rate and I:E (the recording's), eq. 8.8–8.9 (the PV curve's resistance) leave the
//!   delivered volume alone. The scene keys that set them are refused on a waveform scene
//!   (`DiseaseScene::validate_ventilated`).
//! * **The pressure limit.** One factor `k` scales every breathing lung, so every lung's driving
//!   pressure is `k` times the normal one (`ΔP = tidal/C` with `C` in proportion to the course's
//!   tidal volume). A ventilator ends the inspiration at its high-pressure limit (the alarm and
//!   cycling every volume-controlled ventilator has; Tobin, *Principles and Practice of Mechanical
//!   Ventilation*, 3rd ed., 2013, ch. 2), so `k` is capped at [`PRESSURE_LIMIT_FACTOR`]: with a
//!   normal driving pressure of about 10 cmH₂O (500 ml at 50 ml/cmH₂O), PEEP 5 cmH₂O and a limit of
//!   40 cmH₂O, `(40 − 5)/10 = 3.5`. One lung of two collapsing completely needs `k ≈ 2`: the whole
//!   volume is delivered. A lung held by the course (complete collapse, the hyper-expanded lung
//!   while the SVC is closed, arrest) takes none; when the lungs left need more than the limit, less
//!   is delivered ([`deliver`] says how much); when none breathes (arrest), nothing is, and the
//!   lungs are held where the course holds them. A closed pneumothorax that collapses every lung
//!   completely is refused.
//!
//! Each lung then plays the recorded breath (its timing and shape) scaled to its tidal volume
//! ([`lung_breathing`], [`Breathing::rescaled`]). With no disease effect (index 0, before a tension
//! pneumothorax's first air) the factor is exactly 1 and the lungs play the recording bit for bit.

use super::{LungBaseline, LungState, NormalBreathing};
use crate::pv::{Boundary, Breathing, PhaseConstants, PvError, Timing};

/// The normal breathing a disease course starts from: the scene's PV model (`inhale`, `exhale`,
/// `preset`) at its `timing`, or on a waveform scene (`recorded`) the recorded breath's tidal volume
/// on the preset's FRC at its rate and I:E ([`Breathing::timing_at`]; the constants then shape
/// nothing the lungs play: a ventilated lung plays the recording).
pub fn normal_breathing(
    recorded: Option<&Breathing>,
    timing: Timing,
    inhale: PhaseConstants,
    exhale: PhaseConstants,
    preset: Boundary,
) -> NormalBreathing {
    let Some(r) = recorded else {
        return NormalBreathing {
            inhale,
            exhale,
            boundary: preset,
            timing,
        };
    };
    let b = r.boundary();
    NormalBreathing {
        inhale,
        exhale,
        boundary: Boundary {
            frc_ml: b.frc_ml,
            tv_ml: b.tv_ml,
            ..preset
        },
        timing: r.timing_at(timing.tick_hz),
    }
}

/// The volume the ventilator delivers per breath, ml: `Σ share_i·TV` over the simulated lungs (what
/// the healthy waveform scene's lungs take together).
pub fn delivered_ml(lungs: &[LungBaseline], tv_ml: f64) -> f64 {
    lungs.iter().map(|l| l.share * tv_ml).sum()
}

/// Largest factor by which a ventilated breath may raise the driving pressure before the
/// ventilator's high-pressure limit ends the inspiration: `(40 − 5)/10` cmH₂O (limit 40, PEEP 5, a
/// normal driving pressure of 10; module docs). Beyond it less than the recorded volume is delivered.
pub const PRESSURE_LIMIT_FACTOR: f64 = 3.5;

/// Share `delivered_ml` among the lungs of `states` that breathe (not held), in proportion to the
/// tidal volumes the course gave them (their compliances): each breathing lung's `tidal_ml` is
/// multiplied by `k = min(delivered_ml / Σ tidal, PRESSURE_LIMIT_FACTOR)`. Returns `k`: exactly 1
/// when the course took the delivered volume already (nothing is changed), 0 when no lung breathes
/// (nothing is delivered); `k·Σ tidal` is what is delivered. No allocation.
pub fn deliver(states: &mut [LungState], delivered_ml: f64) -> f64 {
    let taken: f64 = states
        .iter()
        .filter(|s| s.held_ml.is_none())
        .map(|s| s.tidal_ml)
        .sum();
    if !(taken > 0.0 && delivered_ml.is_finite() && delivered_ml > 0.0) {
        return 0.0;
    }
    let k = (delivered_ml / taken).min(PRESSURE_LIMIT_FACTOR);
    if k != 1.0 {
        for s in states.iter_mut().filter(|s| s.held_ml.is_none()) {
            s.tidal_ml *= k;
        }
    }
    k
}

/// The breath a lung in `state` plays: `recorded` scaled so that its `share` of it is the lung's
/// tidal volume; `None` when the lung is held or takes nothing.
pub fn lung_breathing(
    state: &LungState,
    recorded: &Breathing,
    share: f64,
) -> Option<Result<Breathing, PvError>> {
    state
        .boundary(&recorded.boundary(), share)
        .map(|b| recorded.rescaled(b.tv_ml))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Side;
    use proptest::prelude::*;

    fn recorded() -> Breathing {
        // 500 ml over 12 ticks in, 24 out (a 1:2 breath at 60 Hz would be longer; the shape is
        // what matters here).
        let mut v: Vec<f64> = (0..12).map(|k| 500.0 * k as f64 / 12.0).collect();
        v.extend((0..24).map(|k| 500.0 * (1.0 - k as f64 / 24.0)));
        Breathing::from_volume_table(&v, 12, 2400.0).unwrap()
    }

    fn state(side: Side, tidal: f64, held: Option<f64>) -> LungState {
        LungState {
            side,
            collapse: 0.0,
            base_volume_ml: 1000.0,
            tidal_ml: tidal,
            held_ml: held,
            offset_mm: [0.0; 3],
            resistance_dv: 0.0,
        }
    }

    #[test]
    fn the_recorded_timing_comes_back_in_ticks() {
        let r = recorded();
        let t = r.timing_at(60.0);
        assert_eq!(t.phase_ticks().unwrap(), (12, 24));
        // An I:E beyond the allowed range keeps the cycle and takes the nearest ratio.
        let v: Vec<f64> = (0..40).map(|k| if k == 1 { 10.0 } else { 5.0 }).collect();
        let narrow = Breathing::from_volume_table(&v, 1, 2400.0).unwrap();
        let (i, e) = narrow.timing_at(60.0).phase_ticks().unwrap();
        assert_eq!(i + e, 40);
    }

    #[test]
    fn the_delivered_volume_moves_from_the_collapsing_lung_to_the_other() {
        // Shares 0.5/0.5 of 500 ml; the left lung loses dV = 0.4 (eq. 8.6: 150 ml instead of 250).
        let mut s = [
            state(Side::Right, 250.0, None),
            state(Side::Left, 250.0 * 0.6, None),
        ];
        let k = deliver(&mut s, 500.0);
        assert!((k - 1.25).abs() < 1e-15);
        assert!((s[0].tidal_ml - 312.5).abs() < 1e-12 && (s[1].tidal_ml - 187.5).abs() < 1e-12);
        // Nothing changed: the factor is 1 exactly and the states are untouched, bit for bit.
        let mut same = [
            state(Side::Right, 0.5 * 500.0, None),
            state(Side::Left, 0.5 * 500.0, None),
        ];
        let before = same;
        assert_eq!(deliver(&mut same, 0.5 * 500.0 + 0.5 * 500.0), 1.0);
        assert_eq!(same, before);
        // Complete collapse (held): the other lung takes everything.
        let mut s = [
            state(Side::Right, 250.0, None),
            state(Side::Left, 0.0, Some(220.0)),
        ];
        assert_eq!(deliver(&mut s, 500.0), 2.0);
        assert_eq!((s[0].tidal_ml, s[1].tidal_ml), (500.0, 0.0));
        // The lung left is small (a 29 %-aerated lung while the other is held): the pressure limit
        // caps the factor, and 3.5 × 72.5 ml is delivered, not 500 ml.
        let mut s = [
            state(Side::Right, 0.0, Some(1500.0)),
            state(Side::Left, 72.5, None),
        ];
        assert_eq!(deliver(&mut s, 500.0), PRESSURE_LIMIT_FACTOR);
        assert_eq!(s[1].tidal_ml, 3.5 * 72.5);
        // Nobody breathes (arrest): nothing is delivered, nothing changes, no NaN.
        let mut s = [
            state(Side::Right, 0.0, Some(1500.0)),
            state(Side::Left, 0.0, Some(220.0)),
        ];
        assert_eq!(deliver(&mut s, 500.0), 0.0);
        assert!(s.iter().all(|l| l.tidal_ml == 0.0));
        // Degenerate delivered volumes change nothing.
        for bad in [f64::NAN, f64::INFINITY, 0.0, -5.0] {
            let mut s = [state(Side::Right, 250.0, None)];
            assert_eq!(deliver(&mut s, bad), 0.0);
            assert_eq!(s[0].tidal_ml, 250.0);
        }
    }

    #[test]
    fn a_lung_plays_the_recording_scaled_to_its_share() {
        let r = recorded();
        let s = state(Side::Left, 0.5 * 500.0, None);
        // Its own share of the recorded TV: the recording itself, bit for bit.
        let same = lung_breathing(&s, &r, 0.5).unwrap().unwrap();
        for t in 0..36 {
            assert_eq!(same.volume_at(t).to_bits(), r.volume_at(t).to_bits());
        }
        // 100 ml at share 0.5: TV 200 ml, 0.4 of every tick's volume above FRC, same ticks.
        let s = state(Side::Left, 100.0, None);
        let b = lung_breathing(&s, &r, 0.5).unwrap().unwrap();
        assert_eq!((b.cycle_ticks(), b.inhale_ticks()), (36, 12));
        for t in 0..36 {
            let want = 2400.0 + 0.4 * (r.volume_at(t) - 2400.0);
            assert!((b.volume_at(t) - want).abs() < 1e-9);
        }
        assert!(lung_breathing(&state(Side::Left, 0.0, Some(5.0)), &r, 0.5).is_none());
        assert!(lung_breathing(&state(Side::Left, 0.0, None), &r, 0.5).is_none());
        assert!(r.rescaled(f64::NAN).is_err() && r.rescaled(0.0).is_err());
    }

    proptest! {
        /// For any two lungs and any collapse, the breathing lungs' tidal volumes add up to the
        /// delivered volume (to rounding) unless the pressure limit caps it, every one stays
        /// finite, ≥ 0 and within it.
        #[test]
        fn the_delivered_volume_is_conserved(
            share_r in 0.05f64..1.0, share_l in 0.05f64..1.0, dv in 0.0f64..=1.0,
            tv in 1.0f64..3000.0, held in any::<bool>(),
        ) {
            let mut s = [
                state(Side::Right, share_r * tv, None),
                state(Side::Left, share_l * tv * (1.0 - dv), (held || dv == 1.0).then_some(100.0)),
            ];
            let delivered = share_r * tv + share_l * tv;
            let k = deliver(&mut s, delivered);
            prop_assert!((1.0 - 1e-12..=PRESSURE_LIMIT_FACTOR).contains(&k));
            let total: f64 = s.iter().filter(|l| l.held_ml.is_none()).map(|l| l.tidal_ml).sum();
            if k < PRESSURE_LIMIT_FACTOR {
                prop_assert!((total - delivered).abs() <= 1e-9 * delivered);
            } else {
                prop_assert!(total <= delivered * (1.0 + 1e-12));
            }
            for l in &s {
                prop_assert!(l.tidal_ml.is_finite() && l.tidal_ml >= 0.0);
                prop_assert!(l.tidal_ml <= delivered * (1.0 + 1e-12));
            }
        }
    }
}
