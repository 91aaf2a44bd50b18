//! # `[pv]`: the pressure–volume model a scene breathes, or the recording it plays
//!
//! The table and its defaults; the presets, the timing and the recording's checks are
//! `lung_model::pv` and `lung_model::scene`'s.

use serde::{Deserialize, Serialize};

/// `[pv]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PvScene {
    /// Preset name from Table 5.1 (see `lungdyn pv` presets).
    pub preset: String,
    /// Breaths per minute.
    pub breaths_per_min: f64,
    /// I:E ratio as `[I, E]` (default [`crate::pv::DEFAULT_IE_RATIO`], 1:2, quiet breathing;
    /// `[1, 1]` is the seed's, [`crate::pv::SEED_IE_RATIO`]; EQUATIONS §1.1).
    pub ie_ratio: [f64; 2],
    /// A constants file written by `lungdyn pv fit` (relative to the scene file); replaces the
    /// preset's constants and boundary values when given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub constants: Option<std::path::PathBuf>,
    /// A ventilator recording (relative to the scene file; any file `lungdyn pv recording` reads):
    /// the lungs play its measured volume–time curve — its whole, clean breaths averaged into one,
    /// resampled to the tick and looped — above the preset's FRC, at the recording's own rate and
    /// I:E (`breaths_per_min`, `ie_ratio` and the PV constants are not used; no PV model is built).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waveform: Option<std::path::PathBuf>,
    /// What the ventilator of a `[pv] waveform` scene holds fixed when a disease changes the lungs
    /// (EQUATIONS §4.7): `"auto"` (default) the recording's own classification (the majority of its
    /// whole breaths), `"volume"` or `"pressure"` to override it (`scene check` warns when that
    /// contradicts the recording).
    pub waveform_control: WaveformControl,
}

/// `[pv] waveform_control`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WaveformControl {
    /// The recording's classification decides.
    #[default]
    Auto,
    /// Volume control: the recorded volume is delivered (up to the pressure limit).
    Volume,
    /// Pressure control: the recorded pressure is held; the volume follows the compliance.
    Pressure,
}

impl Default for PvScene {
    fn default() -> Self {
        Self {
            preset: crate::pv::DEFAULT_PRESET.to_string(),
            breaths_per_min: 12.0,
            ie_ratio: crate::pv::DEFAULT_IE_RATIO,
            constants: None,
            waveform: None,
            waveform_control: WaveformControl::Auto,
        }
    }
}

/// The default preset of the demo and of scenes that name none.
pub const DEFAULT_PRESET: &str = "venegas-human";

/// The seed's I:E, 1:1: its normal breathing is a 2.5 s inhalation and a 2.5 s exhalation at 12
/// breaths/min (§5.3, Table 5.2). `lung_model::pv::Timing::default` keeps it (the figures checked by hand against
/// the seed); a scene reaches it with `[pv] ie_ratio = [1, 1]`.
pub const SEED_IE_RATIO: [f64; 2] = [1.0, 1.0];

/// The project's default I:E for a scene's `[pv] ie_ratio`, 1:2 (EQUATIONS §1.1, "I:E"): quiet
/// spontaneous breathing spends about a third of the cycle in inspiration (West, *Respiratory
/// Physiology: The Essentials*, 10th ed., 2016, ch. 1: "inspiration ... about one third of the
/// respiratory cycle"; Tobin et al., Chest 1983;84:202–205, normal subjects at rest: `Ti/Ttot` ≈ 0.42,
/// i.e. 1:1.4); a ventilator's default setting is 1:2 (Tobin, *Principles and Practice of Mechanical
/// Ventilation*, 3rd ed., 2013). At 12 breaths/min: 1.67 s in, 3.33 s out.
pub const DEFAULT_IE_RATIO: [f64; 2] = [1.0, 2.0];
