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
//!   (`DiseaseSceneExt::validate_ventilated`).
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
//!
//! **Pressure control** ([`Control::Pressure`], the recording's majority class or
//! `[pv] waveform_control = "pressure"`): the ventilator holds the recorded airway pressure and the
//! volume follows the lungs. The equation of motion the recording's fit gives (`Paw = V/C + R·flow +
//! P0`, EQUATIONS §1.4) is solved for the volume at the course's compliance `C' = r·C`, `r = Σ tidal
//! of the breathing lungs / delivered` (compliance in proportion to the tidal volume eq. 8.6 gives,
//! as above), with the recorded pressure and the same `R` and `P0` ([`PressureDrive`]): the same
//! pressure into a stiffer system delivers less, though more than `r` of it (the smaller time
//! constant `R·C'` fills the lungs more completely in the inspiratory time). The lungs share the
//! delivered breath in proportion to their compliances (eq. 8.6's proportion again); no pressure
//! limit applies (the pressure is the set one).

use super::{LungBaseline, LungState, NormalBreathing};
use crate::pv::{Boundary, Breathing, PhaseConstants, PvError, Timing};
pub use crate::recording::classify::ControlMode;
use crate::recording::classify::EquationOfMotion;

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

/// What the ventilator of a waveform scene holds fixed.
#[derive(Debug, Clone, PartialEq)]
pub enum Control {
    /// Volume control: the recorded volume is delivered (up to the pressure limit).
    Volume,
    /// Pressure control: the recorded pressure is held; the volume follows the compliance.
    Pressure(Box<PressureDrive>),
}

impl Control {
    /// The mode's name.
    pub fn mode(&self) -> ControlMode {
        match self {
            Control::Volume => ControlMode::Volume,
            Control::Pressure(_) => ControlMode::Pressure,
        }
    }
}

/// A pressure-controlled breath: the airway pressure the ventilator holds at every tick of the cycle
/// and the equation of motion `Paw = V/C + R·flow + P0` fitted to the recording's averaged breath
/// (EQUATIONS §1.4), from which the volume at another compliance follows.
#[derive(Debug, Clone, PartialEq)]
pub struct PressureDrive {
    paw_cmh2o: Vec<f64>,
    eom: EquationOfMotion,
    dt_s: f64,
    /// The model's volume at the recorded compliance, above tick 0, ml (the reference the
    /// recording's departure from the model is measured from).
    model_at_recorded: Vec<f64>,
}

impl PressureDrive {
    /// The drive of `paw_cmh2o` (one cycle, one value a tick at `tick_hz`) with the fitted `eom`.
    /// Refused, with the reason, when the fit is not a passive lung's (`C`, `R` not positive and
    /// finite) or the pressure does not inflate it.
    pub fn new(paw_cmh2o: &[f64], eom: &EquationOfMotion, tick_hz: f64) -> Result<Self, String> {
        let (c, r) = (eom.compliance_ml_per_cmh2o, eom.resistance_cmh2o_s_per_l);
        if !(c.is_finite() && c > 0.0 && r.is_finite() && r > 0.0 && eom.p0_cmh2o.is_finite()) {
            return Err(format!(
                "the equation of motion fitted to the recording's averaged breath gives C = {} \
                 ml/cmH2O, R = {} cmH2O·s/L: not a passive lung, so the volume a held pressure \
                 delivers cannot be modelled (set [pv] waveform_control = \"volume\")",
                crate::plausible::compact(c),
                crate::plausible::compact(r)
            ));
        }
        if paw_cmh2o.len() < 2 || paw_cmh2o.iter().any(|p| !p.is_finite()) || !(tick_hz > 0.0) {
            return Err("the recorded pressure is not a finite cycle of at least 2 ticks".into());
        }
        let mut drive = Self {
            paw_cmh2o: paw_cmh2o.to_vec(),
            eom: *eom,
            dt_s: 1.0 / tick_hz,
            model_at_recorded: Vec::new(),
        };
        drive.model_at_recorded = drive.model_volume(1.0);
        if !(max_of(&drive.model_at_recorded) > 0.0) {
            return Err(
                "the recorded pressure does not inflate the fitted lung (no tidal volume)".into(),
            );
        }
        Ok(drive)
    }

    /// The equation of motion's fit.
    pub fn eom(&self) -> &EquationOfMotion {
        &self.eom
    }

    /// The periodic volume, ml above its value at tick 0, of `R·dV/dt + V/C' = Paw(t) − P0` with
    /// `C' = ratio·C` over one cycle: per tick exactly (each tick's pressure held over its
    /// interval, the exponential step of the linear equation), the start chosen so the cycle closes. All zero for
    /// `ratio ≤ 0`. Allocates: call when a cycle is prepared.
    pub fn model_volume(&self, ratio: f64) -> Vec<f64> {
        let n = self.paw_cmh2o.len();
        let c = ratio * self.eom.compliance_ml_per_cmh2o;
        if !(c > 0.0 && c.is_finite()) {
            return vec![0.0; n];
        }
        let tau = self.eom.resistance_cmh2o_s_per_l * c / 1000.0;
        let a = (-self.dt_s / tau).exp();
        // Each tick's pressure held to the next tick, as the recording's volume holds each sample's
        // flow over its interval (EQUATIONS §1.4); a mean of the two ends would smear the
        // ventilator's step at the start of inspiration back into the end of expiration.
        let target = |k: usize| c * (self.paw_cmh2o[k] - self.eom.p0_cmh2o);
        // One cycle from V = 0 gives V_N = a^N·V_0 + b; the periodic start is b / (1 − a^N).
        let (mut v, mut an) = (0.0, 1.0);
        for k in 0..n {
            let t = target(k);
            v = t + (v - t) * a;
            an *= a;
        }
        let v0 = if an < 1.0 { v / (1.0 - an) } else { 0.0 };
        let mut out = Vec::with_capacity(n);
        let mut v = v0;
        for k in 0..n {
            out.push(v - v0);
            let t = target(k);
            v = t + (v - t) * a;
        }
        out
    }

    /// The system's breath when its compliance is `ratio` times the recording's: the model's volume
    /// at `ratio` plus the recording's own departure from the model at the recorded compliance,
    /// scaled with the model's tidal volume (so the breath tends to nothing as the compliance does).
    /// `ratio == 1` is `recorded` itself, bit for bit. Allocates: call when a cycle is prepared.
    pub fn respond(&self, recorded: &Breathing, ratio: f64) -> Result<Breathing, PvError> {
        if ratio == 1.0 {
            return Ok(recorded.clone());
        }
        let frc = recorded.boundary().frc_ml;
        let model = self.model_volume(ratio);
        let g = max_of(&model) / max_of(&self.model_at_recorded);
        let above: Vec<f64> = model
            .iter()
            .zip(&self.model_at_recorded)
            .enumerate()
            .map(|(k, (m, m1))| m + g * (recorded.volume_at(k as u64) - frc - m1))
            .collect();
        if above.len() != recorded.cycle_ticks() as usize {
            return Err(PvError::BadTiming {
                name: "ticks of the recorded pressure",
                value: above.len() as f64,
            });
        }
        Breathing::from_volume_table(&above, recorded.inhale_ticks(), frc)
    }
}

fn max_of(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
}

/// The ventilator of a waveform scene: the recorded breath, the volume it delivers to the simulated
/// lungs ([`delivered_ml`]) and what it holds fixed.
#[derive(Debug, Clone)]
pub struct Ventilator {
    /// The recorded breath (the scene's breathing before any disease).
    pub recorded: Breathing,
    /// `Σ share_i·TV` of the simulated lungs, ml.
    pub delivered_ml: f64,
    /// Volume or pressure control.
    pub control: Control,
}

/// What a ventilated breath delivers under a disease course (one cycle).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Delivery {
    /// The ventilator's control mode.
    pub control: ControlMode,
    /// Factor the breathing lungs' course tidal volumes were multiplied by.
    pub factor: f64,
    /// The breathing lungs' compliance against the recording's (Σ course tidal / delivered).
    pub compliance_ratio: f64,
    /// Volume delivered to the simulated lungs per breath, ml.
    pub delivered_ml: f64,
    /// `delivered_ml` against the recorded volume (1: the recording's).
    pub fraction: f64,
    /// Volume control: the pressure limit ([`PRESSURE_LIMIT_FACTOR`]) ended the inspiration early.
    pub pressure_capped: bool,
}

impl Ventilator {
    /// Share this cycle's breath among the lungs of `states` that breathe (their `tidal_ml`, from
    /// the course, are their compliances; they are replaced by what each takes). Returns what is
    /// delivered and, under pressure control with a changed compliance, the system's breath the
    /// lungs then play ([`PressureDrive::respond`]; `None`: the recording). Allocates only under
    /// pressure control: call when a cycle is prepared, never per tick.
    pub fn deliver(
        &self,
        states: &mut [LungState],
    ) -> Result<(Delivery, Option<Breathing>), PvError> {
        let taken: f64 = states
            .iter()
            .filter(|s| s.held_ml.is_none())
            .map(|s| s.tidal_ml)
            .sum();
        let ratio = if self.delivered_ml > 0.0 {
            taken / self.delivered_ml
        } else {
            0.0
        };
        let (factor, breath) = match &self.control {
            Control::Volume => (deliver(states, self.delivered_ml), None),
            Control::Pressure(drive) if ratio > 0.0 && ratio.is_finite() => {
                let b = drive.respond(&self.recorded, ratio)?;
                let f = b.boundary().tv_ml / self.recorded.boundary().tv_ml;
                let k = f / ratio;
                if k != 1.0 {
                    for s in states.iter_mut().filter(|s| s.held_ml.is_none()) {
                        s.tidal_ml *= k;
                    }
                }
                (k, (ratio != 1.0).then_some(b))
            }
            Control::Pressure(_) => (0.0, None),
        };
        let delivered: f64 = states
            .iter()
            .filter(|s| s.held_ml.is_none())
            .map(|s| s.tidal_ml)
            .sum();
        Ok((
            Delivery {
                control: self.control.mode(),
                factor,
                compliance_ratio: ratio,
                delivered_ml: delivered,
                fraction: if self.delivered_ml > 0.0 {
                    delivered / self.delivered_ml
                } else {
                    0.0
                },
                pressure_capped: matches!(self.control, Control::Volume)
                    && factor == PRESSURE_LIMIT_FACTOR,
            },
            breath,
        ))
    }

    /// The breath a lung in `state` plays in a cycle whose system breath is `breath` (`None`: the
    /// recording) and the TV it is scaled to; `None` when the lung is held or takes nothing.
    pub fn lung_table(
        &self,
        breath: Option<&Breathing>,
        state: &LungState,
        share: f64,
    ) -> Option<(Breathing, f64)> {
        let r = breath.unwrap_or(&self.recorded);
        state
            .boundary(&r.boundary(), share)
            .map(|b| (r.clone(), b.tv_ml))
    }
}

/// The deliveries of a course, cycle by cycle, summarised (no allocation).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DeliveryLog {
    /// The ventilator's control mode.
    pub control: ControlMode,
    /// Cycles delivered.
    pub cycles: u64,
    /// Smallest delivered fraction of a cycle in which a lung breathed.
    pub lowest_fraction: Option<f64>,
    /// Cycles in which the pressure limit capped the volume (volume control).
    pub pressure_capped_cycles: u64,
    /// The last cycle's delivery.
    pub last: Option<Delivery>,
}

impl DeliveryLog {
    /// An empty log.
    pub fn new(control: ControlMode) -> Self {
        Self {
            control,
            cycles: 0,
            lowest_fraction: None,
            pressure_capped_cycles: 0,
            last: None,
        }
    }

    /// Add one cycle.
    pub fn record(&mut self, d: &Delivery) {
        self.cycles += 1;
        if d.delivered_ml > 0.0 {
            self.lowest_fraction = Some(
                self.lowest_fraction
                    .map_or(d.fraction, |f| f.min(d.fraction)),
            );
        }
        self.pressure_capped_cycles += d.pressure_capped as u64;
        self.last = Some(*d);
    }
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

    /// A passive lung on a pressure-controlled ventilator at 15 /min, Ti 1 s (no exhalation valve:
    /// the pressure is PEEP throughout expiration, so the equation of motion holds exactly),
    /// averaged at 60 Hz. The synthetic breaths each start from FRC: `R·C` up to 0.6 s keeps what
    /// the 3 s expiration leaves below 1 %.
    fn pc_recording(c: f64, r: f64) -> (crate::recording::Waveform, Breathing) {
        use crate::recording::{average_breath, SegmentOptions, Synthetic, SyntheticMode};
        let rec = Synthetic {
            mode: SyntheticMode::Pressure {
                above_peep_cmh2o: 12.0,
            },
            c_ml_per_cmh2o: c,
            r_cmh2o_s_per_l: r,
            r_valve_cmh2o_s_per_l: 0.0,
            peep_cmh2o: 5.0,
            rate_per_min: 15.0,
            ti_s: 1.0,
            breaths: 3,
            dt_s: 0.02,
        }
        .recording();
        let w = average_breath(&rec, &SegmentOptions::default(), 60.0).unwrap();
        let b = Breathing::from_volume_table(&w.volume_ml, w.inhale_ticks, 2400.0).unwrap();
        (w, b)
    }

    /// The periodic tidal volume of a square pressure wave (ΔP for `ti`, 0 for `te`) into a lung of
    /// time constant `tau`, per ml/cmH2O·cmH2O of `C·ΔP`: `(1 − a)(1 − b)/(1 − ab)`,
    /// `a = e^(−ti/τ)`, `b = e^(−te/τ)`.
    fn square_wave_fill(tau: f64, ti: f64, te: f64) -> f64 {
        let (a, b) = ((-ti / tau).exp(), (-te / tau).exp());
        (1.0 - a) * (1.0 - b) / (1.0 - a * b)
    }

    #[test]
    fn pressure_control_follows_the_equation_of_motion() {
        // τ = R·C = 0.6 s against Ti = 1 s: the lung is not filled, so a stiffer lung fills
        // relatively more (its τ is shorter) and the delivered fraction exceeds the compliance's.
        let (w, recorded) = pc_recording(50.0, 12.0);
        assert_eq!(
            w.control.mode(),
            ControlMode::Pressure,
            "{}",
            w.control.describe()
        );
        let eom = w.eom.expect("fitted");
        assert!(
            (eom.compliance_ml_per_cmh2o / 50.0 - 1.0).abs() < 0.05,
            "{eom:?}"
        );
        assert!(
            (eom.resistance_cmh2o_s_per_l / 12.0 - 1.0).abs() < 0.05,
            "{eom:?}"
        );
        let drive = PressureDrive::new(&w.paw_cmh2o, &eom, 60.0).unwrap();
        // The recorded compliance: the recording, bit for bit.
        let same = drive.respond(&recorded, 1.0).unwrap();
        for t in 0..recorded.cycle_ticks() as u64 {
            assert_eq!(same.volume_at(t).to_bits(), recorded.volume_at(t).to_bits());
        }
        let tau = 50.0 * 12.0 / 1000.0;
        let healthy = square_wave_fill(tau, 1.0, 3.0);
        let mut last = 0.0;
        for ratio in [0.1, 0.25, 0.5, 0.75, 0.9] {
            let b = drive.respond(&recorded, ratio).unwrap();
            let f = b.boundary().tv_ml / recorded.boundary().tv_ml;
            let want = ratio * square_wave_fill(ratio * tau, 1.0, 3.0) / healthy;
            assert!(
                (f / want - 1.0).abs() < 0.03,
                "ratio {ratio}: {f} against {want}"
            );
            assert!(f > ratio && f < 1.0 && f > last, "ratio {ratio}: {f}");
            last = f;
            // The same ticks, the same FRC, no NaN.
            assert_eq!(b.cycle_ticks(), recorded.cycle_ticks());
            assert_eq!(b.boundary().frc_ml, 2400.0);
            assert!((0..b.cycle_ticks() as u64).all(|t| b.volume_at(t).is_finite()));
        }
        // No compliance: nothing is delivered; a fit that is no passive lung is refused.
        assert!(drive.model_volume(0.0).iter().all(|&v| v == 0.0));
        for (c, r) in [
            (-5.0, 10.0),
            (50.0, 0.0),
            (f64::NAN, 10.0),
            (50.0, f64::INFINITY),
        ] {
            let bad = EquationOfMotion {
                compliance_ml_per_cmh2o: c,
                resistance_cmh2o_s_per_l: r,
                ..eom
            };
            let e = PressureDrive::new(&w.paw_cmh2o, &bad, 60.0).unwrap_err();
            assert!(e.contains("waveform_control"), "{e}");
        }
        assert!(PressureDrive::new(&[10.0], &eom, 60.0).is_err());
        assert!(PressureDrive::new(&[10.0, f64::NAN], &eom, 60.0).is_err());
    }

    /// The ventilator of `recorded` for lungs of shares 0.55 / 0.45 under `control`.
    fn ventilator(recorded: &Breathing, control: Control) -> Ventilator {
        let tv = recorded.boundary().tv_ml;
        Ventilator {
            recorded: recorded.clone(),
            delivered_ml: 0.55 * tv + 0.45 * tv,
            control,
        }
    }

    fn two_lungs(tv: f64, dv: f64, held: bool) -> [LungState; 2] {
        [
            state(Side::Right, 0.55 * tv, None),
            state(
                Side::Left,
                0.45 * tv * (1.0 - dv),
                (held || dv == 1.0).then_some(100.0),
            ),
        ]
    }

    #[test]
    fn under_a_pneumothorax_pressure_control_delivers_less_and_volume_control_the_same() {
        let (w, recorded) = pc_recording(50.0, 12.0);
        let tv = recorded.boundary().tv_ml;
        let drive = PressureDrive::new(&w.paw_cmh2o, &w.eom.unwrap(), 60.0).unwrap();
        let pc = ventilator(&recorded, Control::Pressure(Box::new(drive)));
        let vc = ventilator(&recorded, Control::Volume);
        // Healthy: both deliver the recording unchanged (factor 1, no new breath).
        for v in [&pc, &vc] {
            let mut s = two_lungs(tv, 0.0, false);
            let before = s;
            let (d, b) = v.deliver(&mut s).unwrap();
            assert_eq!((d.factor, d.fraction, d.compliance_ratio), (1.0, 1.0, 1.0));
            assert!(b.is_none() && s == before && !d.pressure_capped);
        }
        // dV = 0.6 of the left lung: compliance 0.55 + 0.45·0.4 = 0.73 of the recording's.
        let mut s = two_lungs(tv, 0.6, false);
        let (d, b) = vc.deliver(&mut s).unwrap();
        assert!((d.fraction - 1.0).abs() < 1e-12 && b.is_none());
        assert!((s[0].tidal_ml + s[1].tidal_ml - tv).abs() < 1e-9);
        let mut s = two_lungs(tv, 0.6, false);
        let (d, b) = pc.deliver(&mut s).unwrap();
        let b = b.expect("a changed breath");
        assert!((d.compliance_ratio - 0.73).abs() < 1e-12);
        assert!(d.fraction > 0.73 && d.fraction < 0.95, "{d:?}");
        let total = s[0].tidal_ml + s[1].tidal_ml;
        assert!((total - d.fraction * tv).abs() < 1e-9 * tv);
        assert!((b.boundary().tv_ml - d.fraction * tv).abs() < 1e-9 * tv);
        // The lungs keep eq. 8.6's proportion (compliance): 0.55 against 0.45·0.4.
        assert!((s[1].tidal_ml / s[0].tidal_ml - 0.45 * 0.4 / 0.55).abs() < 1e-12);
        // Each lung plays the changed breath scaled to its share.
        let (table, tv_left) = pc.lung_table(Some(&b), &s[1], 0.45).unwrap();
        assert_eq!(table.boundary().tv_ml, b.boundary().tv_ml);
        assert!((tv_left * 0.45 - s[1].tidal_ml).abs() < 1e-9);
        // The left lung held (complete collapse): volume control gives the right lung everything;
        // pressure control only its own compliance's worth (and a little more: its τ is shorter).
        let mut s = two_lungs(tv, 1.0, true);
        let (d, _) = vc.deliver(&mut s).unwrap();
        assert!((s[0].tidal_ml - tv).abs() < 1e-9 && !d.pressure_capped);
        let mut s = two_lungs(tv, 1.0, true);
        let (d, _) = pc.deliver(&mut s).unwrap();
        assert!(d.fraction > 0.55 && d.fraction < 0.8, "{d:?}");
        // Nobody breathes: nothing delivered, no NaN.
        let mut s = two_lungs(tv, 1.0, true);
        s[0].held_ml = Some(1300.0);
        s[0].tidal_ml = 0.0;
        for v in [&pc, &vc] {
            let (d, b) = v.deliver(&mut s.clone()).unwrap();
            assert_eq!((d.delivered_ml, d.fraction), (0.0, 0.0));
            assert!(b.is_none());
        }
        // The pressure limit: a small lung left under volume control gets at most 3.5 times its own.
        let mut s = two_lungs(tv, 0.9, false);
        s[0].held_ml = Some(1300.0);
        s[0].tidal_ml = 0.0;
        let (d, _) = vc.deliver(&mut s).unwrap();
        assert!(d.pressure_capped && d.factor == PRESSURE_LIMIT_FACTOR);
        assert!((d.fraction - 3.5 * 0.045).abs() < 1e-12, "{d:?}");
        let mut log = DeliveryLog::new(ControlMode::Volume);
        log.record(&d);
        assert_eq!((log.cycles, log.pressure_capped_cycles), (1, 1));
        assert_eq!(log.lowest_fraction, Some(d.fraction));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]
        /// Pressure control, any passive lung, any collapse of one lung of two, held or not: what the
        /// lungs take adds up to the delivered fraction of the recorded volume, which lies between
        /// the compliance's fraction and the whole; every tidal volume and every tick is finite.
        #[test]
        fn pressure_control_delivers_between_the_compliance_and_the_recording(
            c in 15.0f64..60.0, r in 4.0f64..10.0, dv in 0.0f64..=1.0, held in any::<bool>(),
        ) {
            let (w, recorded) = pc_recording(c, r);
            let tv = recorded.boundary().tv_ml;
            let drive = PressureDrive::new(&w.paw_cmh2o, &w.eom.unwrap(), 60.0).unwrap();
            let pc = ventilator(&recorded, Control::Pressure(Box::new(drive)));
            let mut s = two_lungs(tv, dv, held);
            let (d, b) = pc.deliver(&mut s).unwrap();
            let total: f64 = s.iter().filter(|l| l.held_ml.is_none()).map(|l| l.tidal_ml).sum();
            prop_assert!((total - d.delivered_ml).abs() <= 1e-9 * tv);
            prop_assert!((d.delivered_ml - d.fraction * tv).abs() <= 1e-9 * tv);
            prop_assert!(d.fraction >= d.compliance_ratio * (1.0 - 0.02), "{:?}", d);
            prop_assert!(d.fraction <= 1.0 + 1e-9, "{:?}", d);
            for l in &s {
                prop_assert!(l.tidal_ml.is_finite() && l.tidal_ml >= 0.0);
            }
            if let Some(b) = b {
                prop_assert!((0..b.cycle_ticks() as u64).all(|t| b.volume_at(t).is_finite()));
            }
        }
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
