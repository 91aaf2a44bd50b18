//! # `[engine]`: the engine's tick, its pose staleness, gravity and how a posture becomes a force
//!
//! The table and its defaults; what the orientation methods compute is `lung_model::orientation`.

use serde::{Deserialize, Serialize};

/// `[engine]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EngineScene {
    /// Tick rate, Hz.
    pub tick_hz: f64,
    /// Ticks the patient pose may be held before it is reported stale.
    pub pose_staleness_ticks: u32,
    /// Gravity ("down") in the tracker's room frame, unit vector: the synthetic tracker's room has
    /// +Z up. A real tracker's camera frame is mounted however it is: state it.
    pub gravity_room: [f64; 3],
    /// How the patient's pose becomes the applied force (EQUATIONS.md §3.3): "exact" (the rotated
    /// weights), "seed" (eq. 7.8–7.9's blend, for comparison), or "fixed" (always supine).
    pub orientation: crate::engine::OrientationMethod,
    /// Where the supine model ends (EQUATIONS.md §3.3): a turned patient's force weights are moved
    /// towards supine until the field's volume slope is at least this fraction of the supine one.
    /// Default 0.8 (no posture folds the default lungs to FRC + 1500 ml); 0.5 was lungdyn's earlier
    /// value; 0 is no limit (the seed's eq. 7.8–7.9 limit nothing).
    pub min_slope_ratio: f64,
}

impl Default for EngineScene {
    fn default() -> Self {
        Self {
            tick_hz: 60.0,
            pose_staleness_ticks: 30,
            gravity_room: [0.0, 0.0, -1.0],
            orientation: crate::engine::OrientationMethod::Exact,
            min_slope_ratio: crate::engine::DEFAULT_MIN_SLOPE_RATIO,
        }
    }
}

/// How the engine turns the patient's pose into force weights (scene `[engine] orientation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OrientationMethod {
    /// The patient is taken as supine whatever the tracker says (Table 6.1's force).
    Fixed,
    /// The exact rotation of the weights (EQUATIONS.md §3.3).
    Exact,
    /// The seed's eq. 7.8–7.9 blend of 12 precomputed orientations (for comparison).
    Seed,
}

/// Smallest volume slope, as a fraction of the supine one, the weights may give by default
/// (`lung_model::orientation::VolumeLimit`, scene `[engine] min_slope_ratio`). EQUATIONS.md §3.3:
/// at 0.8 no posture of the bake's orientation set folds either default lung from FRC − 500 to FRC + 1500 ml (1000 and 10k
/// vertices) and the largest vertex move stays within 1.7× the supine one; at the earlier 0.5 the
/// turned breath moved up to 3.2× as far and folded the surface beyond FRC + 500 ml.
pub const DEFAULT_MIN_SLOPE_RATIO: f64 = 0.8;
