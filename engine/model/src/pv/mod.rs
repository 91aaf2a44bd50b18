//! # pv: the pressure–volume relation (seed chapter 5), forward model
//!
//! Implements the stable reading of the seed's volume dynamics decided in EQUATIONS.md §1.1:
//!
//! * the damping ("control") function of **eq. 5.11**,
//!   `D_raw(i) = M · Σ_{j=1..N} Σ_{k=1..K} (1 − χ_j · sin^q(i·π / ((k·j)^c · (T + T_ext))))`,
//!   normalised to `[0, 1]` over the phase (§5.3.3);
//! * the Newtonian volume dynamics of **eq. 2.12–2.16** (and 5.1–5.2) in the stable second-order form
//!   `M·v' = F_E − R(t)·v`, `V' = v`, `R = max(0, β0 + β1·D)`, integrated exactly per step for `R`
//!   held at its midpoint (an exponential integrator: unconditionally stable like backward Euler, but
//!   second order) in normalised phase time, `M = F_E = 1`. The printed third-order recurrence is
//!   unstable (EQUATIONS.md §1.1, "Changed (lungdyn)").
//!
//! Each phase is integrated once, ahead of time, on a grid that is an integer multiple of the
//! engine's ticks, so the per-tick cost is one table read ([`Breathing::volume_at`]) and a
//! breathing cycle lasts exactly its configured number of integer ticks.
//!
//! Assumptions: `N` odd and ≥ 3 (so `K = (N−1)/2 ≥ 1`); the phase's normalised volume is mapped onto
//! the boundary values of Table 5.2 (FRC → FRC + TV). Fitting a measured loop is bake-time work
//! (`lung_bake::pv::fit`); [`files`] reads the constants such a fit writes.

pub mod files;

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::pv::{DEFAULT_IE_RATIO, DEFAULT_PRESET, SEED_IE_RATIO};

use thiserror::Error;

/// Substeps of the phase integration per engine tick: keeps the curve (nearly)
/// independent of the tick rate while the table still lands exactly on ticks.
pub const SUBSTEPS_PER_TICK: usize = 16;

/// Most control constants `χ_1..χ_N` a phase may have. The seed uses N = 7 (Table 5.1), and eq.
/// 5.11's `χ` basis is already nearly collinear at 7 (Jacobian condition number 1e9–1e11,
/// EQUATIONS.md §1.2): more constants add no shape, only cost — the control function has
/// `N·(N−1)/2` terms per grid point, so its time and memory grow with N² (1001 constants took 13.8 s
/// and 769 MiB for one simulated breath). 15 is twice the seed's count.
pub const MAX_CONTROL_CONSTANTS: usize = 15;

/// Range of the motor-drive exponent `q` (eq. 5.11), wherever it enters (flags, constants files,
/// scenes). The seed's tables use 2 and 3, Fig. 5.9 varies it around them, and the fit searches
/// 0.5–16 (EQUATIONS.md §1.2); the range is that search widened by 2× each way. Beyond it
/// `sin^q` is a spike (large q) or a step (small q): the curve degenerates without an error.
pub const Q_RANGE: (f64, f64) = (0.25, 32.0);

/// Range of the growth constant `c` (eq. 5.11; EQUATIONS.md §1.3: 1 unless fitted). The fit
/// searches 0.25–4 (§1.2); the range is that widened by 2.5× each way. With `c` of 10 the term
/// `(k·j)^c` already exceeds 1e8 for `k·j = 6`: every higher term is a constant.
pub const C_RANGE: (f64, f64) = (0.1, 10.0);

/// Range of the hysteresis constant `T_ext`, in control-function steps (eq. 5.10: `t = i/(T +
/// T_ext)`). The seed raises it to 10, 20, 30 for Fig. 5.9b with `T = 100`; at 10·T the sine
/// arguments are squeezed into a tenth of their range and the control function is nearly flat, and
/// a huge `T_ext` makes it constant (an error that would blame the χ instead).
pub const T_EXT_RANGE: (f64, f64) = (0.0, 1000.0);

/// `q` within [`Q_RANGE`] ([`PvError::OutOfRange`] otherwise).
pub fn check_q(q: f64) -> Result<(), PvError> {
    check_range(
        "q",
        q,
        Q_RANGE,
        "within 0.25–32: the fit's search, 0.5–16, widened 2×",
    )
}

/// `c` within [`C_RANGE`].
pub fn check_c(c: f64) -> Result<(), PvError> {
    check_range(
        "c",
        c,
        C_RANGE,
        "within 0.1–10: the fit's search, 0.25–4, widened 2.5×",
    )
}

/// `T_ext` within [`T_EXT_RANGE`].
pub fn check_t_ext(t_ext: f64) -> Result<(), PvError> {
    check_range(
        "T_ext",
        t_ext,
        T_EXT_RANGE,
        "within 0–1000 control steps: the seed uses 10–30 with T = 100",
    )
}

/// Control constants of one breathing phase (eq. 5.11) plus the resistance scale of §1.1.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseConstants {
    /// Control constants `χ_1..χ_N` (N odd, ≥ 3).
    pub chi: Vec<f64>,
    /// Motor-drive exponent `q`.
    pub q: f64,
    /// Growth constant `c` (EQUATIONS.md §1.3 Decision: 1 unless fitted).
    pub c: f64,
    /// Hysteresis constant `T_ext`, in control-function steps (0 for normal breathing).
    pub t_ext: f64,
    /// Control-function steps per phase `T` (the seed normalises curves to 100 samples).
    pub t_steps: f64,
    /// Resistance offset `β0` of `R = β0 + β1·D`.
    pub beta0: f64,
    /// Resistance slope `β1` of `R = β0 + β1·D`.
    pub beta1: f64,
}

impl PhaseConstants {
    /// Constants from a table row with the EQUATIONS.md defaults (`c = 1`, `T_ext = 0`, `T = 100`,
    /// `β0 = 30`, `β1 = −30`).
    pub fn from_table(chi: &[f64], q: f64) -> Self {
        Self {
            chi: chi.to_vec(),
            q,
            c: 1.0,
            t_ext: 0.0,
            t_steps: 100.0,
            beta0: 30.0,
            beta1: -30.0,
        }
    }

    /// Check the constants can produce a curve; every failure names the offending constant. `q`,
    /// `c` and `T_ext` must lie in [`Q_RANGE`], [`C_RANGE`] and [`T_EXT_RANGE`], and there are at
    /// most [`MAX_CONTROL_CONSTANTS`] `χ`.
    pub fn validate(&self) -> Result<(), PvError> {
        let n = self.chi.len();
        if n < 3 || n.is_multiple_of(2) || n > MAX_CONTROL_CONSTANTS {
            return Err(PvError::BadConstantCount { n });
        }
        let named = [
            ("q", self.q),
            ("c", self.c),
            ("T_ext", self.t_ext),
            ("T", self.t_steps),
            ("beta0", self.beta0),
            ("beta1", self.beta1),
        ];
        for (i, &v) in self.chi.iter().enumerate() {
            if !v.is_finite() {
                return Err(PvError::NonFinite {
                    name: format!("chi_{}", i + 1),
                    value: v,
                });
            }
        }
        for (name, v) in named {
            if !v.is_finite() {
                return Err(PvError::NonFinite {
                    name: name.to_string(),
                    value: v,
                });
            }
        }
        check_q(self.q)?;
        check_c(self.c)?;
        check_t_ext(self.t_ext)?;
        if self.t_steps < 1.0 {
            return Err(PvError::OutOfRange {
                name: "T",
                value: self.t_steps,
                range: ">= 1",
            });
        }
        Ok(())
    }

    /// Raw control function of eq. 5.11 at normalised phase time `t ∈ [0, 1]` (M = 1); the step
    /// index of the seed is `i = t·T`.
    pub fn control_raw(&self, t: f64) -> f64 {
        let n = self.chi.len();
        let k_max = (n - 1) / 2;
        let i = t * self.t_steps;
        let denom_base = self.t_steps + self.t_ext;
        let mut sum = 0.0;
        for (j0, &chi) in self.chi.iter().enumerate() {
            let j = (j0 + 1) as f64;
            for k in 1..=k_max {
                let arg = i * std::f64::consts::PI / ((k as f64 * j).powf(self.c) * denom_base);
                // arg ∈ [0, π] for c > 0, so sin ≥ 0; the clamp keeps powf off tiny negatives.
                sum += 1.0 - chi * arg.sin().max(0.0).powf(self.q);
            }
        }
        sum
    }
}

/// `Ok` when `value` is within `range` (inclusive), else [`PvError::OutOfRange`] naming `name` and
/// describing the range as `text`.
pub fn check_range(
    name: &'static str,
    value: f64,
    range: (f64, f64),
    text: &'static str,
) -> Result<(), PvError> {
    if !value.is_finite() {
        return Err(PvError::NonFinite {
            name: name.to_string(),
            value,
        });
    }
    if value < range.0 || value > range.1 {
        return Err(PvError::OutOfRange {
            name,
            value,
            range: text,
        });
    }
    Ok(())
}

/// Boundary values of a PV curve (Table 5.2).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Boundary {
    /// Functional residual capacity, ml (volume at the start of inhalation).
    pub frc_ml: f64,
    /// Tidal volume, ml.
    pub tv_ml: f64,
    /// Resting pressure, cmH2O.
    pub rp_cmh2o: f64,
    /// Top (end-inspiratory) pressure, cmH2O.
    pub tp_cmh2o: f64,
}

impl Boundary {
    /// Check the boundary values against human ranges ([`crate::plausible`]): FRC, tidal volume,
    /// each pressure, and a top pressure above the resting one by a plausible swing.
    pub fn check_plausible(&self) -> Result<(), crate::plausible::Implausible> {
        use crate::plausible::{FRC_ML, PRESSURE_CMH2O, PRESSURE_SWING_CMH2O, TIDAL_VOLUME_ML};
        FRC_ML.check(self.frc_ml, None)?;
        TIDAL_VOLUME_ML.check(self.tv_ml, None)?;
        PRESSURE_CMH2O.check(self.rp_cmh2o, None)?;
        PRESSURE_CMH2O.check(self.tp_cmh2o, None)?;
        PRESSURE_SWING_CMH2O.check(
            self.tp_cmh2o - self.rp_cmh2o,
            Some("the top pressure (TP) must exceed the resting pressure (RP)".into()),
        )
    }

    /// Table 5.2, human subjects.
    pub const HUMAN: Boundary = Boundary {
        frc_ml: 2400.0,
        tv_ml: 500.0,
        rp_cmh2o: 0.0,
        tp_cmh2o: 10.0,
    };
    /// Table 5.2, sheep.
    pub const SHEEP: Boundary = Boundary {
        frc_ml: 2400.0,
        tv_ml: 500.0,
        rp_cmh2o: 0.0,
        tp_cmh2o: 40.0,
    };
}

/// A named set of constants for both phases and its boundary values.
#[derive(Debug, Clone, PartialEq)]
pub struct Preset {
    /// Name used on the command line and in scenes.
    pub name: &'static str,
    /// Where the constants come from.
    pub source: &'static str,
    /// Inhalation constants.
    pub inhale: PhaseConstants,
    /// Exhalation constants.
    pub exhale: PhaseConstants,
    /// Boundary values.
    pub boundary: Boundary,
}

/// Names of the presets of Table 5.1 (EQUATIONS.md §1.3).
pub const PRESET_NAMES: [&str; 8] = [
    "takeuchi-sheep",
    "takeuchi-sheep-high-pressure",
    "colebatch-human",
    "venegas-human",
    "subject-1",
    "subject-2",
    "subject-3",
    "subject-4",
];

/// Look up a preset of Table 5.1 by name.
pub fn preset(name: &str) -> Result<Preset, PvError> {
    let same = |name, source, chi: &[f64], q, boundary| Preset {
        name,
        source,
        inhale: PhaseConstants::from_table(chi, q),
        exhale: PhaseConstants::from_table(chi, q),
        boundary,
    };
    let subject = |name, second: f64, third: f64| {
        same(
            name,
            "Table 5.1, subjects 1-4",
            &[2.0, second, third, 0.2, 0.15, 0.1, 0.08],
            3.0,
            Boundary::HUMAN,
        )
    };
    Ok(match name {
        "takeuchi-sheep" => same(
            "takeuchi-sheep",
            "Table 5.1, Takeuchi sheep (Fig. 5.5a)",
            &[1.2, 0.9, 0.5, 0.3, 0.2, 0.1, 0.05],
            2.0,
            Boundary::SHEEP,
        ),
        "takeuchi-sheep-high-pressure" => Preset {
            name: "takeuchi-sheep-high-pressure",
            source: "Table 5.1, Takeuchi sheep, high pressure",
            inhale: PhaseConstants::from_table(&[1.2, 0.3, 0.2, 0.1, 0.1, 0.1, 0.05], 2.0),
            exhale: PhaseConstants::from_table(&[1.2, 1.2, 1.2, 1.0, 0.7, 0.5, 0.3], 2.0),
            boundary: Boundary::SHEEP,
        },
        "colebatch-human" => same(
            "colebatch-human",
            "Table 5.1, Colebatch human",
            &[0.65, 0.32, 0.14, 0.023, 0.045, 0.037, 0.031],
            2.0,
            Boundary::HUMAN,
        ),
        "venegas-human" => same(
            "venegas-human",
            "Table 5.1, Venegas human",
            &[0.57, 0.46, 0.40, 0.35, 0.31, 0.30, 0.29],
            2.0,
            Boundary::HUMAN,
        ),
        "subject-1" => subject("subject-1", 1.2, 0.2),
        "subject-2" => subject("subject-2", 1.18, 0.17),
        "subject-3" => subject("subject-3", 1.23, 0.2),
        "subject-4" => subject("subject-4", 1.15, 0.2),
        other => {
            return Err(PvError::UnknownPreset {
                name: other.to_string(),
            })
        }
    })
}

/// Eq. 5.11 precomputed on a phase grid for fixed `c`, `T`, `T_ext`, `N`: the control function is
/// linear in `χ`, `D_raw = M·(N·K − Σ_j χ_j·B_j)` with `B_j(t) = Σ_k sin^q(t·T·π / ((k·j)^c (T + T_ext)))`,
/// and `sin^q = exp(q·ln sin)`. Keeping `ln sin` (per `c`) and `B_j` (per `q`) makes re-evaluating the
/// curve for new `χ` or `β` (every fit iteration) a dot product per grid point.
#[derive(Debug, Clone)]
pub struct ControlBasis {
    n: usize,
    k_max: usize,
    steps: usize,
    key: (f64, f64, f64),
    q: f64,
    /// `ln sin` of every (point, j, k); points on the half-step grid `t = i / (2·steps)`.
    log_sin: Vec<f64>,
    /// `B_j` of every (point, j).
    basis: Vec<f64>,
}

impl ControlBasis {
    /// Terms for `N = n` constants, growth `c`, `T` and `T_ext`, on `steps` steps per phase.
    pub fn new(n: usize, steps: usize, c: f64, t_steps: f64, t_ext: f64) -> Self {
        let k_max = (n - 1) / 2;
        let points = 2 * steps + 1;
        let mut log_sin = Vec::with_capacity(points * n * k_max);
        for i in 0..points {
            let t = i as f64 / (2 * steps) as f64;
            for j in 1..=n {
                for k in 1..=k_max {
                    let arg = t * t_steps * std::f64::consts::PI
                        / (((k * j) as f64).powf(c) * (t_steps + t_ext));
                    // arg ∈ [0, π] for c > 0: sin ≥ 0; ln 0 = −∞ gives sin^q = 0 exactly.
                    log_sin.push(arg.sin().max(0.0).ln());
                }
            }
        }
        Self {
            n,
            k_max,
            steps,
            key: (c, t_steps, t_ext),
            q: f64::NAN,
            log_sin,
            basis: vec![0.0; points * n],
        }
    }

    /// Whether this basis serves `constants` at `steps` (up to `q`, which [`Self::set_q`] updates).
    pub fn serves(&self, constants: &PhaseConstants, steps: usize) -> bool {
        self.steps == steps
            && self.n == constants.chi.len()
            && self.key == (constants.c, constants.t_steps, constants.t_ext)
    }

    /// Recompute `B_j` for exponent `q` (no-op when unchanged).
    pub fn set_q(&mut self, q: f64) {
        if q.to_bits() == self.q.to_bits() {
            return;
        }
        self.q = q;
        let kk = self.k_max;
        for (b, terms) in self.basis.iter_mut().zip(self.log_sin.chunks_exact(kk)) {
            *b = terms.iter().map(|&l| (q * l).exp()).sum();
        }
    }

    /// Normalised control function `(at, mid)`: `at[i] = D(i/steps)`, `mid[i] = D((i + ½)/steps)`,
    /// normalised over both together (EQUATIONS.md §1.1 Decision).
    pub fn control(&self, chi: &[f64]) -> Result<(Vec<f64>, Vec<f64>), PvError> {
        let nk = (self.n * self.k_max) as f64;
        let raw: Vec<f64> = self
            .basis
            .chunks_exact(self.n)
            .map(|b| nk - b.iter().zip(chi).map(|(b, c)| b * c).sum::<f64>())
            .collect();
        let (lo, hi) = raw
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &d| {
                (lo.min(d), hi.max(d))
            });
        if !(lo.is_finite() && hi.is_finite() && (hi - lo).is_finite()) {
            return Err(PvError::NonFiniteControl);
        }
        if hi - lo <= 1e-12 * hi.abs().max(1.0) {
            return Err(PvError::DegenerateControl);
        }
        let norm = |d: &f64| (d - lo) / (hi - lo);
        Ok((
            raw.iter().step_by(2).map(norm).collect(),
            raw.iter().skip(1).step_by(2).map(norm).collect(),
        ))
    }

    /// The phase's normalised volume curve (see [`phase_curve`]) for `constants` (their `c`, `T`,
    /// `T_ext`, `N` must be this basis's: [`Self::serves`]).
    pub fn phase_curve(&mut self, constants: &PhaseConstants) -> Result<Vec<f64>, PvError> {
        constants.validate()?;
        self.set_q(constants.q);
        let (_, mid) = self.control(&constants.chi)?;
        integrate_phase(&mid, constants.beta0, constants.beta1)
    }
}

/// The normalised control function of eq. 5.11 over one phase: `(at, mid)` with `at[i] = D(i/steps)`
/// (`steps + 1` values) and `mid[i] = D((i + ½)/steps)` (`steps` values). Normalised to [0, 1] over
/// both grids together (EQUATIONS.md §1.1 Decision); a constant or overflowing `D_raw` is an error.
pub fn control_curve(
    constants: &PhaseConstants,
    steps: usize,
) -> Result<(Vec<f64>, Vec<f64>), PvError> {
    constants.validate()?;
    if steps == 0 {
        return Err(PvError::OutOfRange {
            name: "steps",
            value: 0.0,
            range: ">= 1",
        });
    }
    let mut basis = ControlBasis::new(
        constants.chi.len(),
        steps,
        constants.c,
        constants.t_steps,
        constants.t_ext,
    );
    basis.set_q(constants.q);
    basis.control(&constants.chi)
}

/// Normalised volume of one phase at `steps + 1` equally spaced phase times `t = i/steps`,
/// from 0 (start) to 1 (end), monotonically non-decreasing.
///
/// Control function eq. 5.11 (normalised, EQUATIONS.md §1.1 Decision); dynamics eq. 2.12–2.16 in the
/// stable form `v' = F_E − R(t)·v` of EQUATIONS.md §1.1 (M = F_E = 1). **Changed (lungdyn):** each
/// step is integrated exactly for `R` held at its midpoint value (exponential integrator) instead of
/// by backward Euler: just as stable (any `R ≥ 0`, any step) but second-order, so the curve a fit
/// evaluates at a few hundred steps is the curve the engine plays at 16 substeps per tick.
pub fn phase_curve(constants: &PhaseConstants, steps: usize) -> Result<Vec<f64>, PvError> {
    let (_, mid) = control_curve(constants, steps)?;
    integrate_phase(&mid, constants.beta0, constants.beta1)
}

/// Integrate `v' = 1 − R·v`, `V' = v` over one phase with `R = max(0, β0 + β1·D)` held at each step's
/// midpoint value `mid[i]`, exactly per step; returns `V` normalised to end at 1.
fn integrate_phase(mid: &[f64], beta0: f64, beta1: f64) -> Result<Vec<f64>, PvError> {
    let h = 1.0 / mid.len() as f64;
    let mut volume = Vec::with_capacity(mid.len() + 1);
    let (mut v, mut vol) = (0.0_f64, 0.0_f64);
    volume.push(0.0);
    for &d in mid {
        let r = (beta0 + beta1 * d).max(0.0);
        let rh = r * h;
        if rh < 1e-9 {
            // R ≈ 0: free acceleration over the step.
            vol += h * v + 0.5 * h * h;
            v += h;
        } else {
            // Exact: v(τ) = 1/R + (v0 − 1/R)·e^(−Rτ), integrated over the step for the volume.
            let decay = (-rh).exp();
            let v_inf = 1.0 / r;
            // ≥ 0 exactly (v stays between v0 ≥ 0 and 1/R); rounding can make it −1e−20 near v = 1/R.
            vol += (h * v_inf + (v - v_inf) * (1.0 - decay) / r).max(0.0);
            v = v_inf + (v - v_inf) * decay;
        }
        volume.push(vol);
    }
    let end = vol;
    if !(end.is_finite() && end > 0.0) {
        return Err(PvError::DegenerateControl);
    }
    for x in &mut volume {
        *x /= end;
    }
    Ok(volume)
}

/// Range of each part of an I:E ratio `[I, E]` (the parts are relative: 1:2 and 0.5:1 are one ratio;
/// the range keeps them ordinary numbers).
pub const IE_PART_RANGE: (f64, f64) = (0.1, 10.0);

/// Range of the ratio I/E: from 1:5 (obstructive disease, prolonged expiration) to 4:1 (inverse-ratio
/// ventilation); spontaneous breathing is about 1:2 and the seed's default 1:1 (Tobin MJ, Principles and
/// Practice of Mechanical Ventilation, 3rd ed., 2013: I:E settings 1:1 to 1:4, inverse ratio to 4:1).
pub const IE_RATIO_RANGE: (f64, f64) = (0.2, 4.0);

/// Timing of the breathing cycle.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Timing {
    /// Engine ticks per second.
    pub tick_hz: f64,
    /// Breaths per minute.
    pub breaths_per_min: f64,
    /// Inspiratory share of the I:E ratio (I in I:E).
    pub ie_inhale: f64,
    /// Expiratory share of the I:E ratio (E in I:E).
    pub ie_exhale: f64,
}

impl Default for Timing {
    /// 60 Hz, 12 breaths/min, I:E = 1:1 ([`SEED_IE_RATIO`], the seed's 2.5 s phases): the seed's
    /// timing, which the by-hand checks of chapter 8 use. A scene's default I:E is
    /// [`DEFAULT_IE_RATIO`] (1:2).
    fn default() -> Self {
        Self {
            tick_hz: 60.0,
            breaths_per_min: 12.0,
            ie_inhale: 1.0,
            ie_exhale: 1.0,
        }
    }
}

impl Timing {
    /// Integer ticks of (inhalation, exhalation). Each phase gets at least one tick.
    pub fn phase_ticks(&self) -> Result<(u32, u32), PvError> {
        let (i, e) = (self.ie_inhale, self.ie_exhale);
        let part = |v: f64| v.is_finite() && (IE_PART_RANGE.0..=IE_PART_RANGE.1).contains(&v);
        if !(part(i) && part(e) && (IE_RATIO_RANGE.0..=IE_RATIO_RANGE.1).contains(&(i / e))) {
            return Err(PvError::IeRatio {
                inhale: i,
                exhale: e,
            });
        }
        for (name, v) in [
            ("tick rate", self.tick_hz),
            ("breathing rate", self.breaths_per_min),
            ("I share of I:E", self.ie_inhale),
            ("E share of I:E", self.ie_exhale),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(PvError::BadTiming { name, value: v });
            }
        }
        let cycle = (self.tick_hz * 60.0 / self.breaths_per_min).round();
        if !(2.0..=1.0e8).contains(&cycle) {
            return Err(PvError::BadTiming {
                name: "ticks per breath",
                value: cycle,
            });
        }
        let cycle = cycle as u32;
        let inhale =
            ((cycle as f64) * self.ie_inhale / (self.ie_inhale + self.ie_exhale)).round() as u32;
        let inhale = inhale.clamp(1, cycle - 1);
        Ok((inhale, cycle - inhale))
    }
}

/// Breathing phase.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Inhalation.
    Inhale,
    /// Exhalation.
    Exhale,
}

/// A precomputed breathing cycle: the volume at every tick of one cycle.
#[derive(Debug, Clone)]
pub struct Breathing {
    inhale_ticks: u32,
    cycle_ticks: u32,
    /// Volume (ml) at tick `k` of the cycle, `k ∈ 0..cycle_ticks`.
    volume_ml: Vec<f64>,
    boundary: Boundary,
    /// The constants and timing the table was built from (`None` for a measured waveform): what a
    /// remote site needs to build the same table (seed §8.3's control packet).
    source: Option<std::sync::Arc<BreathingSource>>,
}

/// What a [`Breathing`] built by [`Breathing::from_constants`] was built from.
#[derive(Debug, Clone, PartialEq)]
pub struct BreathingSource {
    /// Inhalation constants.
    pub inhale: PhaseConstants,
    /// Exhalation constants.
    pub exhale: PhaseConstants,
    /// Timing.
    pub timing: Timing,
}

impl Breathing {
    /// Precompute one cycle of `preset` at `timing`.
    pub fn new(preset: &Preset, timing: &Timing) -> Result<Self, PvError> {
        Self::from_constants(&preset.inhale, &preset.exhale, preset.boundary, timing)
    }

    /// Precompute one cycle from explicit constants.
    pub fn from_constants(
        inhale: &PhaseConstants,
        exhale: &PhaseConstants,
        boundary: Boundary,
        timing: &Timing,
    ) -> Result<Self, PvError> {
        if !(boundary.frc_ml.is_finite()
            && boundary.tv_ml.is_finite()
            && boundary.frc_ml > 0.0
            && boundary.tv_ml > 0.0)
        {
            return Err(PvError::BadBoundary {
                frc_ml: boundary.frc_ml,
                tv_ml: boundary.tv_ml,
            });
        }
        let (ti, te) = timing.phase_ticks()?;
        let up = phase_curve(inhale, ti as usize * SUBSTEPS_PER_TICK)?;
        let down = phase_curve(exhale, te as usize * SUBSTEPS_PER_TICK)?;
        let mut volume_ml = Vec::with_capacity((ti + te) as usize);
        for k in 0..ti as usize {
            volume_ml.push(boundary.frc_ml + boundary.tv_ml * up[k * SUBSTEPS_PER_TICK]);
        }
        for k in 0..te as usize {
            volume_ml.push(boundary.frc_ml + boundary.tv_ml * (1.0 - down[k * SUBSTEPS_PER_TICK]));
        }
        Ok(Self {
            inhale_ticks: ti,
            cycle_ticks: ti + te,
            volume_ml,
            boundary,
            source: Some(std::sync::Arc::new(BreathingSource {
                inhale: inhale.clone(),
                exhale: exhale.clone(),
                timing: *timing,
            })),
        })
    }

    /// A cycle given tick by tick (a measured waveform, [`crate::recording::Waveform`]): `above_frc_ml`
    /// is the volume above FRC at every tick of one cycle, the first `inhale_ticks` the inhalation.
    /// No PV model is evaluated. The boundary's TV is the cycle's largest volume above FRC.
    pub fn from_volume_table(
        above_frc_ml: &[f64],
        inhale_ticks: u32,
        frc_ml: f64,
    ) -> Result<Self, PvError> {
        let cycle = above_frc_ml.len();
        let tv = above_frc_ml
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        if !(frc_ml.is_finite() && frc_ml > 0.0 && tv.is_finite() && tv > 0.0)
            || above_frc_ml
                .iter()
                .any(|v| !v.is_finite() || frc_ml + v <= 0.0)
        {
            return Err(PvError::BadBoundary { frc_ml, tv_ml: tv });
        }
        if cycle < 2 || cycle > u32::MAX as usize || !(1..cycle as u32).contains(&inhale_ticks) {
            return Err(PvError::BadTiming {
                name: "ticks per breath of the waveform",
                value: cycle as f64,
            });
        }
        Ok(Self {
            inhale_ticks,
            cycle_ticks: cycle as u32,
            volume_ml: above_frc_ml.iter().map(|v| frc_ml + v).collect(),
            boundary: Boundary {
                frc_ml,
                tv_ml: tv,
                ..Boundary::HUMAN
            },
            source: None,
        })
    }

    /// The same cycle (timing, shape) with its volume above FRC scaled to a tidal volume of `tv_ml`
    /// (`volume = FRC + (v − FRC)·tv_ml/TV`): a ventilated lung's share of a recorded breath
    /// (EQUATIONS §4.7). `tv_ml` equal to this cycle's TV returns it unchanged, bit for bit.
    /// Allocates: call when a cycle is prepared, never per tick.
    pub fn rescaled(&self, tv_ml: f64) -> Result<Self, PvError> {
        let b = self.boundary;
        if tv_ml == b.tv_ml {
            return Ok(self.clone());
        }
        if !(tv_ml.is_finite() && tv_ml > 0.0) {
            return Err(PvError::BadBoundary {
                frc_ml: b.frc_ml,
                tv_ml,
            });
        }
        let k = tv_ml / b.tv_ml;
        Ok(Self {
            volume_ml: self
                .volume_ml
                .iter()
                .map(|v| b.frc_ml + (v - b.frc_ml) * k)
                .collect(),
            boundary: Boundary { tv_ml, ..b },
            ..self.clone()
        })
    }

    /// The timing of this cycle at `tick_hz` (a recorded breath's rate and I:E, for the disease
    /// courses): [`Timing::phase_ticks`] gives back [`Self::cycle_ticks`] and, where the I:E lies in
    /// [`IE_RATIO_RANGE`], [`Self::inhale_ticks`] exactly; outside it the nearest ratio allowed (the
    /// cycle itself still plays its own ticks).
    pub fn timing_at(&self, tick_hz: f64) -> Timing {
        let (ti, ct) = (self.inhale_ticks as f64, self.cycle_ticks as f64);
        Timing {
            tick_hz,
            breaths_per_min: tick_hz * 60.0 / ct,
            ie_inhale: (ti / (ct - ti)).clamp(IE_RATIO_RANGE.0, IE_RATIO_RANGE.1),
            ie_exhale: 1.0,
        }
    }

    /// The constants and timing this cycle was built from; `None` for a measured waveform.
    pub fn source(&self) -> Option<&BreathingSource> {
        self.source.as_deref()
    }

    /// Ticks per breathing cycle.
    pub fn cycle_ticks(&self) -> u32 {
        self.cycle_ticks
    }

    /// Ticks of the inhalation phase.
    pub fn inhale_ticks(&self) -> u32 {
        self.inhale_ticks
    }

    /// Boundary values in force.
    pub fn boundary(&self) -> Boundary {
        self.boundary
    }

    /// Volume (ml) at integer tick `tick` since the start of an inhalation. O(1), no allocation.
    #[inline]
    pub fn volume_at(&self, tick: u64) -> f64 {
        self.volume_ml[(tick % self.cycle_ticks as u64) as usize]
    }

    /// The driving pressure (cmH2O) at integer tick `tick` since the start of an inhalation:
    /// EQUATIONS.md §1.1, RP → TP linearly in the inhalation's phase time `t = k/T_i`, then
    /// `1 − s` of the swing in the exhalation's (`s = k/T_e`), on the same ticks as
    /// [`Self::volume_at`] (together: the point on the PV loop). O(1), no allocation.
    #[inline]
    pub fn pressure_at(&self, tick: u64) -> f64 {
        let b = &self.boundary;
        let local = tick % self.cycle_ticks as u64;
        let (ti, te) = (
            self.inhale_ticks as u64,
            (self.cycle_ticks - self.inhale_ticks) as u64,
        );
        let x = if local < ti {
            local as f64 / ti as f64
        } else {
            1.0 - (local - ti) as f64 / te as f64
        };
        b.rp_cmh2o + (b.tp_cmh2o - b.rp_cmh2o) * x
    }

    /// Phase at integer tick `tick`.
    #[inline]
    pub fn phase_at(&self, tick: u64) -> Phase {
        if tick % (self.cycle_ticks as u64) < self.inhale_ticks as u64 {
            Phase::Inhale
        } else {
            Phase::Exhale
        }
    }
}

/// Errors of the PV model; each names the constant or input at fault.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum PvError {
    /// N must be odd, at least 3 (K = (N−1)/2 ≥ 1) and at most [`MAX_CONTROL_CONSTANTS`].
    #[error(
        "the control function needs an odd number N of control constants (chi), from 3 to \
         {MAX_CONTROL_CONSTANTS}, got {n} (the seed uses 7)"
    )]
    BadConstantCount {
        /// Number given.
        n: usize,
    },
    /// A constant is NaN or infinite.
    #[error("constant {name} is not finite ({value})")]
    NonFinite {
        /// Constant name.
        name: String,
        /// Its value.
        value: f64,
    },
    /// A constant is outside its valid range.
    #[error("constant {name} = {} is out of range (must be {range})", crate::plausible::compact(*.value))]
    OutOfRange {
        /// Constant name.
        name: &'static str,
        /// Its value.
        value: f64,
        /// The valid range.
        range: &'static str,
    },
    /// The control function is constant over the phase (e.g. all χ = 0), so it cannot be normalised.
    #[error("the control function is constant over the phase (all control constants zero?): it cannot be normalised to [0, 1]")]
    DegenerateControl,
    /// The control function overflows (constants too large to evaluate in f64).
    #[error(
        "the control function is not finite over the phase: the control constants are too large"
    )]
    NonFiniteControl,
    /// A timing parameter is invalid.
    #[error(
        "{name} must be a positive finite number giving at least 2 ticks per breath, got {value}"
    )]
    BadTiming {
        /// Parameter name.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// The I:E ratio is outside [`IE_PART_RANGE`] / [`IE_RATIO_RANGE`].
    #[error(
        "ie_ratio = [{}, {}] (I:E) is not a breathing I:E ratio: each part must be within 0.1–10 and I/E \
         within 1:5 (obstructive disease) to 4:1 (inverse-ratio ventilation); spontaneous breathing is \
         about [1, 2]",
        crate::plausible::compact(*.inhale),
        crate::plausible::compact(*.exhale)
    )]
    IeRatio {
        /// I.
        inhale: f64,
        /// E.
        exhale: f64,
    },
    /// Boundary values are invalid.
    #[error("boundary values need FRC > 0 and TV > 0 (got FRC {frc_ml} ml, TV {tv_ml} ml)")]
    BadBoundary {
        /// FRC given.
        frc_ml: f64,
        /// TV given.
        tv_ml: f64,
    },
    /// No preset of that name.
    #[error("unknown PV preset {name:?}; known presets: {}", PRESET_NAMES.join(", "))]
    UnknownPreset {
        /// Name given.
        name: String,
    },
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn default_breathing() -> Breathing {
        Breathing::new(&preset(DEFAULT_PRESET).unwrap(), &Timing::default()).unwrap()
    }

    #[test]
    fn twelve_breaths_per_minute_at_60_hz_is_300_ticks() {
        let b = default_breathing();
        assert_eq!(b.cycle_ticks(), 300);
        assert_eq!(b.inhale_ticks(), 150);
    }

    #[test]
    fn pressure_rises_rp_to_tp_in_inhalation_and_falls_back_in_exhalation() {
        for name in PRESET_NAMES {
            let p = preset(name).unwrap();
            let b = Breathing::new(&p, &Timing::default()).unwrap();
            let (rp, tp) = (p.boundary.rp_cmh2o, p.boundary.tp_cmh2o);
            let (ti, ct) = (b.inhale_ticks() as u64, b.cycle_ticks() as u64);
            // The loop's corners: RP at the start of inhalation, TP at its end, RP again one
            // cycle later.
            assert_eq!(b.pressure_at(0), rp, "{name}");
            assert_eq!(b.pressure_at(ti), tp, "{name}");
            assert_eq!(b.pressure_at(ct), rp, "{name}");
            let mut last = rp;
            for tick in 1..ct {
                let x = b.pressure_at(tick);
                assert!(
                    x.is_finite() && (rp..=tp).contains(&x),
                    "{name} {tick}: {x}"
                );
                if tick <= ti {
                    assert!(x > last, "{name} {tick}: pressure must rise while inhaling");
                } else {
                    assert!(x < last, "{name} {tick}: pressure must fall while exhaling");
                }
                last = x;
            }
        }
    }

    #[test]
    fn volume_stays_within_frc_and_frc_plus_tv_for_every_preset() {
        for name in PRESET_NAMES {
            let p = preset(name).unwrap();
            let b = Breathing::new(&p, &Timing::default()).unwrap();
            for tick in 0..b.cycle_ticks() as u64 * 2 {
                let v = b.volume_at(tick);
                assert!(v.is_finite(), "{name} tick {tick}");
                assert!(
                    v >= p.boundary.frc_ml - 1e-9
                        && v <= p.boundary.frc_ml + p.boundary.tv_ml + 1e-9,
                    "{name} {v}"
                );
            }
        }
    }

    #[test]
    fn cycle_starts_at_frc_and_peaks_at_end_of_inhalation() {
        let b = default_breathing();
        assert_eq!(b.volume_at(0), 2400.0);
        assert!((b.volume_at(150) - 2900.0).abs() < 1e-9);
        assert_eq!(b.phase_at(149), Phase::Inhale);
        assert_eq!(b.phase_at(150), Phase::Exhale);
        assert_eq!(b.phase_at(300), Phase::Inhale);
    }

    #[test]
    fn a_breathing_cycle_lasts_exactly_its_configured_ticks() {
        for (hz, bpm) in [(60.0, 12.0), (66.66, 12.0), (90.0, 15.0), (60.0, 7.0)] {
            let t = Timing {
                tick_hz: hz,
                breaths_per_min: bpm,
                ..Timing::default()
            };
            let b = Breathing::new(&preset("colebatch-human").unwrap(), &t).unwrap();
            let n = b.cycle_ticks() as u64;
            assert_eq!(n, (hz * 60.0 / bpm).round() as u64);
            // Exactly periodic, and FRC is reached exactly at every cycle start and nowhere else.
            for tick in 0..3 * n {
                assert_eq!(b.volume_at(tick).to_bits(), b.volume_at(tick + n).to_bits());
                let at_frc = b.volume_at(tick) == b.boundary().frc_ml;
                assert_eq!(at_frc, tick % n == 0, "tick {tick}");
            }
        }
    }

    #[test]
    fn volume_is_continuous_across_phase_changes() {
        for name in PRESET_NAMES {
            let b = Breathing::new(&preset(name).unwrap(), &Timing::default()).unwrap();
            let n = b.cycle_ticks() as u64;
            let step = |t: u64| (b.volume_at(t + 1) - b.volume_at(t)).abs();
            let max_inside = (1..n - 1)
                .filter(|&t| t != b.inhale_ticks() as u64 - 1)
                .map(step)
                .fold(0.0, f64::max);
            // The steps straddling the inhale→exhale and exhale→inhale changes are no larger than the
            // largest step inside a phase: the curve has no jump at a phase change.
            let across_peak = step(b.inhale_ticks() as u64 - 1);
            let across_cycle = step(n - 1);
            assert!(
                across_peak <= max_inside + 1e-9,
                "{name}: {across_peak} > {max_inside}"
            );
            assert!(
                across_cycle <= max_inside + 1e-9,
                "{name}: {across_cycle} > {max_inside}"
            );
        }
    }

    #[test]
    fn larger_q_makes_the_inhalation_limb_more_sigmoidal() {
        // Fig. 5.9 trend, the acceptance test of the §1.1 reading: with larger q the limb starts
        // slower (less volume gained in the first fifth of the phase).
        let base = PhaseConstants::from_table(&[0.57, 0.46, 0.40, 0.35, 0.31, 0.30, 0.29], 1.0);
        let early = |q: f64| phase_curve(&PhaseConstants { q, ..base.clone() }, 100).unwrap()[20];
        assert!(early(4.0) < early(1.0), "{} !< {}", early(4.0), early(1.0));
    }

    #[test]
    fn the_cached_basis_reproduces_eq_5_11_term_by_term() {
        let k = PhaseConstants {
            c: 1.3,
            t_ext: 20.0,
            q: 2.7,
            ..PhaseConstants::from_table(&[0.65, 0.32, 0.14, 0.023, 0.045, 0.037, 0.031], 2.0)
        };
        let (at, _) = control_curve(&k, 50).unwrap();
        let raw: Vec<f64> = (0..=100).map(|i| k.control_raw(i as f64 / 100.0)).collect();
        let (lo, hi) = raw
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &d| {
                (l.min(d), h.max(d))
            });
        for i in 0..=50 {
            assert!(
                (at[i] - (raw[2 * i] - lo) / (hi - lo)).abs() < 1e-12,
                "t = {}",
                i as f64 / 50.0
            );
        }
    }

    /// Loop area between the normalised limbs (inhale V(t) against P = t, exhale 1 − V(s) against
    /// P = 1 − s) for a preset with `T_ext` applied to both phases.
    fn loop_area(name: &str, t_ext: f64) -> f64 {
        let p = preset(name).unwrap();
        let up = phase_curve(&PhaseConstants { t_ext, ..p.inhale }, 400).unwrap();
        let down = phase_curve(&PhaseConstants { t_ext, ..p.exhale }, 400).unwrap();
        (0..=400)
            .map(|i| (up[i] - (1.0 - down[400 - i])).abs())
            .sum::<f64>()
            / 400.0
    }

    #[test]
    fn t_ext_changes_the_loop_width_measured_against_fig_5_9() {
        //! Pins a measured discrepancy, not the seed's claim: Fig. 5.9 shows larger T_ext widening
        //! the hysteresis; in the §1.1 reading with the default resistance (β0 = 30, β1 = −30) it
        //! narrows the loop for every Table 5.1 preset (see EQUATIONS.md §1.1, "Measured"). The
        //! test fails if that changes, so the docs and this test move together.
        for name in PRESET_NAMES {
            let (a0, a50, a100) = (
                loop_area(name, 0.0),
                loop_area(name, 50.0),
                loop_area(name, 100.0),
            );
            eprintln!("{name}: loop area T_ext 0/50/100 = {a0:.4} / {a50:.4} / {a100:.4}");
            assert!(a100 < a0, "{name}: {a0} -> {a100}");
        }
    }

    #[test]
    fn all_zero_constants_are_a_typed_error_not_nan() {
        let c = PhaseConstants::from_table(&[0.0; 7], 2.0);
        assert_eq!(phase_curve(&c, 100), Err(PvError::DegenerateControl));
    }

    #[test]
    fn invalid_constants_are_named_in_the_error() {
        let mut c = PhaseConstants::from_table(&[1.0; 6], 2.0);
        assert_eq!(c.validate(), Err(PvError::BadConstantCount { n: 6 }));
        c.chi.push(f64::NAN);
        assert!(c.validate().unwrap_err().to_string().contains("chi_7"));
        let c = PhaseConstants {
            q: 0.0,
            ..PhaseConstants::from_table(&[1.0; 7], 2.0)
        };
        assert!(c.validate().unwrap_err().to_string().contains("q = 0"));
        assert!(preset("nope")
            .unwrap_err()
            .to_string()
            .contains("venegas-human"));
        let t = Timing {
            breaths_per_min: 0.0,
            ..Timing::default()
        };
        assert!(matches!(t.phase_ticks(), Err(PvError::BadTiming { .. })));
    }

    #[test]
    fn control_constants_outside_their_documented_ranges_are_refused_by_name() {
        let base = PhaseConstants::from_table(&[0.57, 0.46, 0.40, 0.35, 0.31, 0.30, 0.29], 2.0);
        for (k, words) in [
            (
                PhaseConstants {
                    q: 1e308,
                    ..base.clone()
                },
                "q = 1e308",
            ),
            (
                PhaseConstants {
                    q: 0.1,
                    ..base.clone()
                },
                "q = 0.1",
            ),
            (
                PhaseConstants {
                    c: 1e308,
                    ..base.clone()
                },
                "c = 1e308",
            ),
            (
                PhaseConstants {
                    c: -1e308,
                    ..base.clone()
                },
                "c = -1e308",
            ),
            (
                PhaseConstants {
                    t_ext: 1e308,
                    ..base.clone()
                },
                "T_ext = 1e308",
            ),
            (
                PhaseConstants {
                    t_ext: -1.0,
                    ..base.clone()
                },
                "T_ext = -1",
            ),
        ] {
            let e = k.validate().unwrap_err().to_string();
            assert!(e.contains(words) && e.contains("out of range"), "{e}");
            assert!(phase_curve(&k, 100).is_err());
        }
        // The ends of every range are valid.
        for k in [
            PhaseConstants {
                q: Q_RANGE.0,
                c: C_RANGE.1,
                t_ext: T_EXT_RANGE.1,
                ..base.clone()
            },
            PhaseConstants {
                q: Q_RANGE.1,
                c: C_RANGE.0,
                t_ext: T_EXT_RANGE.0,
                ..base.clone()
            },
        ] {
            assert_eq!(k.validate(), Ok(()));
        }
        // At most MAX_CONTROL_CONSTANTS: 1001 constants are refused before any work.
        let many = PhaseConstants::from_table(&[0.1; 1001], 2.0);
        let e = many.validate().unwrap_err();
        assert_eq!(e, PvError::BadConstantCount { n: 1001 });
        assert!(e.to_string().contains("from 3 to 15"), "{e}");
        let most = PhaseConstants::from_table(&[0.1; MAX_CONTROL_CONSTANTS], 2.0);
        assert!(phase_curve(&most, 100).is_ok());
    }

    #[test]
    fn twenty_four_hours_at_60_hz_stay_periodic_and_bounded() {
        let b = default_breathing();
        let day = 24 * 3600 * 60_u64;
        let n = b.cycle_ticks() as u64;
        for tick in (day - 2 * n)..day {
            let v = b.volume_at(tick);
            assert_eq!(v.to_bits(), b.volume_at(tick % n).to_bits());
            assert!((2400.0..=2900.0).contains(&v));
        }
        assert_eq!(b.volume_at(day - day % n), 2400.0);
    }

    #[test]
    fn extreme_constants_give_a_finite_curve_or_a_typed_error() {
        let base = PhaseConstants::from_table(&[0.57, 0.46, 0.40, 0.35, 0.31, 0.30, 0.29], 2.0);
        let mut cases: Vec<PhaseConstants> = Vec::new();
        for q in [1.0, 2.0, 6.0, 12.0] {
            for t_ext in [0.0, 1.0, 100.0] {
                for c in [0.5, 1.0, 3.0] {
                    for t_steps in [10.0, 100.0, 10_000.0] {
                        cases.push(PhaseConstants {
                            q,
                            t_ext,
                            c,
                            t_steps,
                            ..base.clone()
                        });
                    }
                }
            }
        }
        for n in [3usize, 5, 9, 15] {
            cases.push(PhaseConstants {
                chi: vec![0.3; n],
                ..base.clone()
            });
            cases.push(PhaseConstants {
                chi: (0..n).map(|j| 1.0 / (j + 1) as f64).collect(),
                ..base.clone()
            });
        }
        for chi in [
            [0.0; 7],
            [1.0; 7],
            [-1.0; 7],
            [1e6; 7],
            [1e300; 7],
            [-1e300; 7],
            [1e-300; 7],
        ] {
            cases.push(PhaseConstants {
                chi: chi.to_vec(),
                ..base.clone()
            });
        }
        for (b0, b1) in [
            (0.0, 0.0),
            (1e6, -1e6),
            (-30.0, 0.0),
            (1e-9, 0.0),
            (1e300, 0.0),
        ] {
            cases.push(PhaseConstants {
                beta0: b0,
                beta1: b1,
                ..base.clone()
            });
        }
        for k in &cases {
            for steps in [1usize, 10, 1000] {
                match phase_curve(k, steps) {
                    Ok(c) => {
                        assert!(
                            c.iter()
                                .all(|v| v.is_finite() && (0.0..=1.0 + 1e-12).contains(v)),
                            "{k:?}"
                        );
                        assert!(c.windows(2).all(|w| w[1] >= w[0]));
                    }
                    Err(e) => assert!(
                        matches!(e, PvError::DegenerateControl | PvError::NonFiniteControl),
                        "{k:?}: unexpected {e}"
                    ),
                }
            }
        }
    }

    #[test]
    fn one_and_sixty_breaths_per_minute_keep_exact_integer_cycles() {
        let p = preset(DEFAULT_PRESET).unwrap();
        for (bpm, cycle) in [(1.0, 3600u32), (60.0, 60)] {
            let b = Breathing::new(
                &p,
                &Timing {
                    breaths_per_min: bpm,
                    ..Timing::default()
                },
            )
            .unwrap();
            assert_eq!(b.cycle_ticks(), cycle);
            for tick in 0..2 * cycle as u64 {
                let v = b.volume_at(tick);
                assert!(v.is_finite() && (2400.0..=2900.0).contains(&v));
            }
        }
        // Faster than the tick rate can resolve: a typed error, not a zero-length phase.
        let t = Timing {
            breaths_per_min: 3600.0,
            ..Timing::default()
        };
        assert!(matches!(
            Breathing::new(&p, &t),
            Err(PvError::BadTiming { .. })
        ));
    }

    #[test]
    fn an_ie_ratio_outside_breathing_is_refused_by_its_key() {
        let t = |i: f64, e: f64| Timing {
            ie_inhale: i,
            ie_exhale: e,
            ..Timing::default()
        };
        for (i, e) in [(1.0, 2.0), (1.0, 1.0), (4.0, 1.0), (1.0, 5.0), (0.5, 1.0)] {
            assert!(t(i, e).phase_ticks().is_ok(), "{i}:{e}");
        }
        for (i, e) in [
            (1e308, 1e-308),
            (0.0, 1.0),
            (-1.0, 1.0),
            (f64::NAN, 1.0),
            (5.0, 1.0),
            (1.0, 6.0),
            (20.0, 20.0),
        ] {
            let err = t(i, e).phase_ticks().unwrap_err();
            assert!(matches!(err, PvError::IeRatio { .. }), "{i}:{e}: {err}");
            assert!(err.to_string().starts_with("ie_ratio = ["), "{err}");
        }
        assert!(PvError::IeRatio {
            inhale: 1e308,
            exhale: 1e-308
        }
        .to_string()
        .contains("[1e308, 1e-308]"));
    }

    proptest! {
        #[test]
        fn random_valid_constants_give_bounded_monotone_curves(
            chi in proptest::collection::vec(-3.0f64..3.0, 7),
            q in 1.0f64..12.0,
            c in 0.5f64..3.0,
            t_ext in 0.0f64..100.0,
            steps in 10usize..2000,
        ) {
            let k = PhaseConstants { chi, q, c, t_ext, ..PhaseConstants::from_table(&[0.0; 7], 2.0) };
            match phase_curve(&k, steps) {
                Ok(curve) => {
                    prop_assert_eq!(curve.len(), steps + 1);
                    prop_assert_eq!(curve[0], 0.0);
                    prop_assert!((curve[steps] - 1.0).abs() < 1e-12);
                    for w in curve.windows(2) {
                        prop_assert!(w[1].is_finite() && w[1] >= w[0] && w[1] <= 1.0 + 1e-12);
                    }
                }
                Err(e) => prop_assert_eq!(e, PvError::DegenerateControl),
            }
        }

        #[test]
        fn the_curve_is_nearly_independent_of_the_step_count(
            chi in proptest::collection::vec(0.0f64..2.0, 7),
            q in 1.0f64..6.0,
            beta0 in 0.0f64..60.0,
            beta1 in -60.0f64..0.0,
        ) {
            // A fit evaluates ~400 steps per phase; the engine plays 16 substeps per tick (2400 at
            // 60 Hz, 12 breaths/min). The two curves must agree far inside the 1 % fit target.
            let k = PhaseConstants { chi, q, beta0, beta1, ..PhaseConstants::from_table(&[0.0; 7], 2.0) };
            if let (Ok(coarse), Ok(fine)) = (phase_curve(&k, 400), phase_curve(&k, 2400)) {
                for i in 0..=400 {
                    prop_assert!((coarse[i] - fine[i * 6]).abs() < 1e-3, "t = {}: {} vs {}", i as f64 / 400.0, coarse[i], fine[i * 6]);
                }
            }
        }
    }
}
