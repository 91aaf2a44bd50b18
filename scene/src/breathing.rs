//! The `[breathing]` table: what the lungs breathe to — the scene's own PV model, or the patient's
//! respiratory signal followed live (issue 35; docs/BREATHING.md). The tracker-bridge reads `signal`
//! (where the samples come from) from the scene file itself; the engine reads the rest through
//! `lung_model::scene::SceneExt` (`breathing_predictor`), which also checks `predictor` (its names are
//! the follower's).
//!
//! ```toml
//! [breathing]
//! source = "signal"                 # "model" (default): the PV model's own breaths
//! signal = "trace:patient.vxp"      # the bridge's signal source (`lungdyn demo --breathing`)
//! predictor = "cycle"               # none, linear[:N], ar[:ORDER[:LAMBDA]], cycle
//! latency = "measured"              # predict across the pipeline's latency as measured ("fixed": latency_ms)
//! latency_ms = 50                   # capture → display until measured (always, when "fixed")
//! sensor_latency_ms = 0             # the source's own delay before the bridge, added to the measured
//! # tidal_ml = 500                  # an amplitude's typical breath; default: the PV model's
//! # ml_per_unit = 48                # an amplitude's spirometry calibration, ml per mm (per au)
//! ```

use serde::{Deserialize, Serialize};

use crate::TableError;

/// What the lungs breathe to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BreathSource {
    /// The scene's PV model (`[pv]`): its own clock.
    #[default]
    Model,
    /// The patient's respiratory signal (`signal`), calibrated to volume and predicted to the
    /// display time; the model breathes while the signal calibrates or is lost, carried on from the
    /// signal's last volume and phase.
    Signal,
}

impl BreathSource {
    /// The name in scenes.
    pub fn name(self) -> &'static str {
        match self {
            BreathSource::Model => "model",
            BreathSource::Signal => "signal",
        }
    }
}

/// Which latency the breath is predicted across.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LatencyChoice {
    /// The pipeline's latency as the renderer's reports measure it (bridge publish → display, the
    /// median of the latest frames, carried to the engine in each tracker frame) plus
    /// `sensor_latency_ms`; `latency_ms` until the first measurement and where nothing measures it
    /// (no renderer: `breathing check`, `breathing sites`).
    #[default]
    Measured,
    /// `latency_ms`, always.
    Fixed,
}

impl LatencyChoice {
    /// The name in scenes and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LatencyChoice::Measured => "measured",
            LatencyChoice::Fixed => "fixed",
        }
    }
}

/// The predictor a scene gets by default: the previous breath's course where it has lately
/// predicted better than the autoregression, compared at the latency (measured in docs/BREATHING.md).
pub const DEFAULT_PREDICTOR: &str = "cycle";
/// Capture-to-display latency predicted across by default, ms: the sensor's tens of ms and the
/// pipeline's two to three frames (`lungdyn latency` measures the pipeline's part).
pub const DEFAULT_LATENCY_MS: f64 = 50.0;

/// `[breathing]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BreathingScene {
    /// `model` or `signal`.
    pub source: BreathSource,
    /// The signal's source at the bridge: `trace:FILE` (a Varian RPM `.vxp`, a CSV trace, or a
    /// ventilator recording as `lungdyn pv recording` reads it, replayed at its own rate from the
    /// run's start), `udp:[BIND:]PORT` (a live amplitude stream), `tool:NAME[:auto]` (a tracked tool
    /// on the chest, along the reference's anterior axis or the axis it moves on), `igtl:NAME` (an amplitude from an OpenIGTLink device) or `recorded` (the signal
    /// a replayed tracker recording carries); empty: none. `lungdyn demo --breathing` overrides it.
    pub signal: String,
    /// The predictor's name (`lungdyn breathing check --predictor` takes the same).
    pub predictor: String,
    /// `measured` (default) or `fixed`: see [`LatencyChoice`].
    pub latency: LatencyChoice,
    /// Capture-to-display latency the volume is predicted across, ms: always with `latency =
    /// "fixed"`, and until the pipeline's latency is measured with `"measured"`.
    pub latency_ms: f64,
    /// The source's own delay from the chest's movement to the sample's arrival at the bridge, ms
    /// (a sensor's filter, a network): added to the measured latency (a replayed file has none).
    pub sensor_latency_ms: f64,
    /// The volume an amplitude signal's typical breath is calibrated to, ml; default the PV model's
    /// tidal volume. A signal in ml is taken as it is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tidal_ml: Option<f64>,
    /// An amplitude signal's calibration against a spirometer: ml breathed per mm of the chest
    /// marker's excursion (per unit of an `au` signal). With it the amplitude drives the lungs from
    /// its first samples at this gain (its baseline the lowest value so far until its first
    /// end-expiration), instead of after two regular breaths at the gain that
    /// makes its typical breath `tidal_ml`; the patient's own tidal volume is then drawn, whatever
    /// the scene's. A signal in ml is used as it is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ml_per_unit: Option<f64>,
}

impl Default for BreathingScene {
    fn default() -> Self {
        Self {
            source: BreathSource::Model,
            signal: String::new(),
            predictor: DEFAULT_PREDICTOR.into(),
            latency: LatencyChoice::Measured,
            latency_ms: DEFAULT_LATENCY_MS,
            sensor_latency_ms: 0.0,
            tidal_ml: None,
            ml_per_unit: None,
        }
    }
}

impl BreathingScene {
    /// Range checks (the predictor's grammar is checked where it is parsed, in `lung-model`).
    pub fn validate(&self) -> Result<(), TableError> {
        let bad = |why: String| Err(TableError::Breathing(why));
        if self.source == BreathSource::Signal && self.signal.trim().is_empty() {
            return bad(
                "source = \"signal\" needs signal = \"trace:FILE\" (or lungdyn demo --breathing trace:FILE)"
                    .into(),
            );
        }
        if !(self.latency_ms.is_finite() && (0.0..=2000.0).contains(&self.latency_ms)) {
            return bad(format!(
                "latency_ms = {}: a capture-to-display latency is 0..2000 ms (the pipeline's is tens of ms)",
                crate::compact(self.latency_ms)
            ));
        }
        if !(self.sensor_latency_ms.is_finite() && (0.0..=1000.0).contains(&self.sensor_latency_ms))
        {
            return bad(format!(
                "sensor_latency_ms = {}: a source's own delay is 0..1000 ms (a marker camera's or a belt's is tens of ms)",
                crate::compact(self.sensor_latency_ms)
            ));
        }
        if let Some(g) = self.ml_per_unit {
            if let Err(why) = check_ml_per_unit(g) {
                return bad(format!("ml_per_unit = {}: {why}", crate::compact(g)));
            }
        }
        if let Some(t) = self.tidal_ml {
            if !(t.is_finite() && (50.0..=3000.0).contains(&t)) {
                return bad(format!(
                    "tidal_ml = {}: an adult's tidal volume is 300-800 ml, a child's from 50 (50..3000 accepted)",
                    crate::compact(t)
                ));
            }
        }
        Ok(())
    }
}

/// A spirometry calibration's gain in range (`[breathing] ml_per_unit`, `lungdyn breathing check
/// --ml-per-unit`): `Err` says what the value is and the range, for the caller to name its key.
pub fn check_ml_per_unit(g: f64) -> Result<(), &'static str> {
    if g.is_finite() && g > 0.0 && g <= 1e5 {
        Ok(())
    } else {
        Err(
            "a spirometry calibration is ml breathed per mm of the marker's excursion (tens: 500 \
             ml over 10 mm is 50), above 0 and at most 1e5",
        )
    }
}

/// The file of a `trace:FILE` signal, relative to `base` (a scene's folder) when it is relative;
/// `None` for any other signal.
pub fn trace_relative_to(signal: &str, base: &std::path::Path) -> Option<std::path::PathBuf> {
    let (kind, path) = signal.trim().split_once(':')?;
    (kind.eq_ignore_ascii_case("trace") && !path.trim().is_empty()).then(|| base.join(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_is_the_model_and_a_signal_scene_names_its_source() {
        let d = BreathingScene::default();
        assert_eq!(d.source, BreathSource::Model);
        assert!(d.validate().is_ok());
        let t: BreathingScene =
            toml::from_str("source = \"signal\"\nsignal = \"trace:a.vxp\"\nlatency_ms = 80\n")
                .unwrap();
        assert_eq!(t.source, BreathSource::Signal);
        assert_eq!(t.latency_ms, 80.0);
        assert_eq!(t.latency, LatencyChoice::Measured, "measured by default");
        assert_eq!(t.sensor_latency_ms, 0.0);
        assert_eq!(t.predictor, DEFAULT_PREDICTOR);
        let f: BreathingScene =
            toml::from_str("latency = \"fixed\"\nsensor_latency_ms = 30\n").unwrap();
        assert_eq!(
            (f.latency, f.sensor_latency_ms),
            (LatencyChoice::Fixed, 30.0)
        );
        assert!(f.validate().is_ok());
        assert!(toml::from_str::<BreathingScene>("latency = \"learnt\"\n").is_err());
        assert!(t.validate().is_ok());
        for (text, words) in [
            ("source = \"signal\"\n", "needs signal"),
            ("latency_ms = -1\n", "latency_ms = -1"),
            ("latency_ms = 1e9\n", "latency_ms = 1e9"),
            ("sensor_latency_ms = -5\n", "sensor_latency_ms = -5"),
            ("sensor_latency_ms = 2000\n", "sensor_latency_ms = 2000"),
            ("ml_per_unit = 0\n", "ml_per_unit = 0"),
            ("ml_per_unit = -48\n", "ml_per_unit = -48"),
            ("ml_per_unit = 1e9\n", "ml_per_unit = 1e9"),
            ("tidal_ml = 5\n", "tidal_ml = 5"),
        ] {
            let t: BreathingScene = toml::from_str(text).unwrap();
            let e = t.validate().unwrap_err().to_string();
            assert!(
                e.starts_with("[breathing] ") && e.contains(words),
                "{text}: {e}"
            );
        }
        assert!(toml::from_str::<BreathingScene>("source = \"patient\"\n").is_err());
        assert!(toml::from_str::<BreathingScene>("signl = \"x\"\n").is_err());
    }

    #[test]
    fn a_trace_path_is_relative_to_the_scene() {
        let base = std::path::Path::new("/scenes");
        assert_eq!(
            trace_relative_to("trace:p/a.vxp", base),
            Some("/scenes/p/a.vxp".into())
        );
        assert_eq!(
            trace_relative_to("trace:/abs/a.csv", base),
            Some("/abs/a.csv".into())
        );
        assert_eq!(trace_relative_to("none", base), None);
        assert_eq!(trace_relative_to("trace:", base), None);
    }
}
