//! # `[lungs]`: which lungs, their shape, how they are baked and how they deform
//!
//! The table's types and the names the scene file and the command line give them: [`Side`],
//! [`Shape`], [`Elasticity`], [`DirectionPreset`], [`DeformMode`], and the bake's defaults. What each
//! means in physics is `lung-model`'s (it re-exports these under their old paths: `mesh::Side`,
//! `operator::Elasticity`, `deform::modes::DeformMode`...); the checks that need the physics (a kernel
//! against the mode, the motion file) are `lung_model::scene`'s.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Which lung.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    /// The patient's right lung (three lobes, at −X).
    Right,
    /// The patient's left lung (two lobes, cardiac notch, at +X).
    Left,
}

impl Side {
    /// Index into per-lung arrays (`ipc_types::LUNG_RIGHT` / `LUNG_LEFT`).
    pub fn index(self) -> usize {
        match self {
            Side::Right => ipc_types::LUNG_RIGHT,
            Side::Left => ipc_types::LUNG_LEFT,
        }
    }

    /// Unit vector from the mediastinum outwards (lateral), in the body frame's X.
    pub fn lateral_sign(self) -> f32 {
        match self {
            Side::Right => -1.0,
            Side::Left => 1.0,
        }
    }

    /// Name as used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Side::Right => "right",
            Side::Left => "left",
        }
    }
}

impl std::str::FromStr for Side {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "left" => Ok(Side::Left),
            "right" => Ok(Side::Right),
            other => Err(format!("unknown lung {other:?}: use left or right")),
        }
    }
}

/// Which built-in lung shape.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Anatomical lungs (`lung_model::mesh::anatomy`): the default.
    #[default]
    Anatomical,
    /// The smooth teardrop (`lung_model::mesh::teardrop`).
    Teardrop,
}

impl Shape {
    /// Every shape, the default first.
    pub const ALL: [Shape; 2] = [Shape::Anatomical, Shape::Teardrop];

    /// Name as used on the command line and in scenes.
    pub fn name(self) -> &'static str {
        match self {
            Shape::Anatomical => "anatomical",
            Shape::Teardrop => "teardrop",
        }
    }
}

impl std::fmt::Display for Shape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Shape {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Shape::ALL
            .into_iter()
            .find(|shape| shape.name() == s)
            .ok_or_else(|| format!("unknown lung shape {s:?}: use anatomical or teardrop"))
    }
}

/// Regional elasticity: relative Young's modulus over the normalised position (x̂, ŷ, ẑ) of
/// eq. 6.14–6.16 (ẑ apex → base, ŷ posterior → anterior).
///
/// `E(ŷ, ẑ) = (apex + (base − apex)·ẑ) · (1 − dependent·(1 − ŷ))`: stiff at the apex where the
/// alveoli expand least, compliant at the base (diaphragm) where they expand most, and softer again
/// on the gravity-dependent (posterior, for a supine patient) side. The defaults are the prototype of
/// EQUATIONS.md §2.3 (E from 4 at the apex to 1 at the base) with a 30 % dependent softening.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Elasticity {
    /// Relative Young's modulus at the apex (ẑ = 0).
    pub apex: f64,
    /// Relative Young's modulus at the base (ẑ = 1).
    pub base: f64,
    /// Fraction by which `E` drops towards the dependent (posterior) side, in [0, 1).
    pub dependent: f64,
}

impl Default for Elasticity {
    fn default() -> Self {
        Self {
            apex: 4.0,
            base: 1.0,
            dependent: 0.3,
        }
    }
}

impl Elasticity {
    /// A uniform modulus (validation cases, tests).
    pub fn uniform(e: f64) -> Self {
        Self {
            apex: e,
            base: e,
            dependent: 0.0,
        }
    }

    /// Check the field gives a finite, positive modulus everywhere: `apex` and `base` within
    /// [`MODULUS_RANGE`], `dependent` in [0, 1).
    pub fn validate(&self) -> Result<(), ElasticityError> {
        let ok = |v: f64| v.is_finite() && (MODULUS_RANGE.0..=MODULUS_RANGE.1).contains(&v);
        if !ok(self.apex) || !ok(self.base) {
            return Err(ElasticityError::Moduli {
                apex: self.apex,
                base: self.base,
            });
        }
        if !(self.dependent.is_finite() && (0.0..1.0).contains(&self.dependent)) {
            return Err(ElasticityError::Dependent(self.dependent));
        }
        Ok(())
    }
}

/// Range of the relative Young's moduli `apex` and `base`. Only their ratio shapes the operator (the
/// defaults are 4 and 1, EQUATIONS.md §2.3); regional lung compliance varies a few times from apex to
/// base, so 0.01–100 is ample. Outside it the apex-to-base ramp loses the modulus to rounding (apex
/// 1e308 and base 1 give a modulus of exactly 0 at the base).
pub const MODULUS_RANGE: (f64, f64) = (0.01, 100.0);

/// The elasticity field is unusable.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ElasticityError {
    /// A modulus is not finite and within [`MODULUS_RANGE`].
    #[error(
        "apex = {} and base = {} must each be within 0.01–100 (relative Young's moduli: only their \
         ratio matters; the default is apex 4, base 1)",
        crate::compact(*.apex),
        crate::compact(*.base)
    )]
    Moduli {
        /// Modulus at the apex.
        apex: f64,
        /// Modulus at the base.
        base: f64,
    },
    /// The dependent softening is outside [0, 1).
    #[error("dependent = {} must be in [0, 1)", crate::compact(*.0))]
    Dependent(f64),
}

/// Which motion a bake uses without a motion file (scene `[lungs] directions`, `lungdyn bake
/// --directions`). EQUATIONS.md §2.4.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "&'static str")]
pub enum DirectionPreset {
    /// `lung_model::deform::MotionConstants::population`: diaphragm-driven constants matched to DIR-Lab 4DCT
    /// landmarks (the default).
    #[default]
    Population,
    /// The population of six real breath-hold pairs: the mean of each COPDgene pair's `fit-motion
    /// --exhale/--inhale` fit (a direction field and an applied force field), made scale-free
    /// (`lung_model::deform::BREATH_HOLD_POPULATION`). Held out by patient it lands 1.8–3.1× closer to the real inhale
    /// surface than no motion or uniform scaling on 12 of 12 lungs, where the default is worse than no
    /// motion on 8 (docs/masks/population_motion_table.md, breath_hold_baselines.md); not yet the
    /// default: the generated right lung folds beyond its share of FRC + 750 ml (EQUATIONS.md §2.4).
    BreathHold,
    /// `lung_model::deform::MotionConstants::table_6_1`: the seed's Table 6.1 (gravity-driven, mostly anterior).
    Seed,
}

impl DirectionPreset {
    /// Every preset, in the order they are listed.
    pub const ALL: [DirectionPreset; 3] = [
        DirectionPreset::Population,
        DirectionPreset::BreathHold,
        DirectionPreset::Seed,
    ];

    /// Its name in scenes and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            DirectionPreset::Population => "population",
            DirectionPreset::BreathHold => "breath-hold",
            DirectionPreset::Seed => "seed",
        }
    }
}

impl From<DirectionPreset> for &'static str {
    fn from(p: DirectionPreset) -> Self {
        p.name()
    }
}

impl TryFrom<String> for DirectionPreset {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl std::str::FromStr for DirectionPreset {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                format!("directions \"{s}\": expected \"population\" (diaphragm-driven, the default), \"breath-hold\" (six patients' breath-hold pairs) or \"seed\" (Table 6.1)")
            })
    }
}

/// How the lungs deform (scene `[lungs] mode`, `lungdyn demo --mode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeformMode {
    /// `p + s·u`: one baked field, the supine orientation (3 MACs per vertex).
    Precomputed,
    /// Eq. 7.1 every frame over the stored transfer rows: the accuracy reference.
    Direct,
    /// Eq. 7.7 with the kernel's SH bands.
    Sh,
    /// The exact basis responses (4 MACs per vertex).
    Basis,
}

impl DeformMode {
    /// Every mode, cheapest-to-load first.
    pub const ALL: [DeformMode; 4] = [
        DeformMode::Precomputed,
        DeformMode::Basis,
        DeformMode::Sh,
        DeformMode::Direct,
    ];

    /// The scene/CLI name.
    pub fn name(self) -> &'static str {
        match self {
            DeformMode::Precomputed => "precomputed",
            DeformMode::Direct => "direct",
            DeformMode::Sh => "sh",
            DeformMode::Basis => "basis",
        }
    }

    /// Whether the deformation follows the patient's orientation.
    pub fn follows_orientation(self) -> bool {
        self != DeformMode::Precomputed
    }

    /// What a frame's coefficients hold in this mode ([`ipc_types::coeff_kind`]).
    pub fn coeff_kind(self) -> u32 {
        match self {
            DeformMode::Precomputed => ipc_types::coeff_kind::NONE,
            DeformMode::Direct | DeformMode::Basis => ipc_types::coeff_kind::FORCE_WEIGHTS,
            DeformMode::Sh => ipc_types::coeff_kind::SH_FORCE,
        }
    }
}

impl std::fmt::Display for DeformMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for DeformMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        DeformMode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown mode {s:?} (precomputed, direct, sh, basis)"))
    }
}

/// Default smoothing length of the elastostatic amplitude, mm (EQUATIONS.md §2.4).
pub const DEFAULT_AMPLITUDE_SMOOTHING_MM: f64 = 10.0;

/// Bands baked by default (the seed's 16 coefficients).
pub const DEFAULT_SH_BANDS: u32 = 4;

/// Default pitcher tolerance for a unit force (see `docs/EQUATIONS.md` §2.3 for what it gives).
pub const DEFAULT_TOLERANCE: f64 = 1e-5;

/// `[lungs]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LungsScene {
    /// Which lungs the scene simulates and draws.
    pub sides: Vec<Side>,
    /// Vertices per generated default lung (what the launcher bakes for a lung without a kernel).
    pub vertices: usize,
    /// Shape of the generated lungs (a lung with a kernel ignores it): "anatomical" (the default:
    /// lobes, hilum, cardiac notch, domed base; `lung_model::mesh::anatomy`) or "teardrop" (the earlier smooth
    /// shape; `mesh::teardrop`).
    pub shape: crate::lungs::Shape,
    /// Regional elasticity of the operator (`[lungs.elasticity]`: apex, base, dependent).
    pub elasticity: crate::lungs::Elasticity,
    /// Pitcher tolerance of the transfer pass for a unit force.
    pub transfer_tolerance: f64,
    /// Motion constants written by `lungdyn fit-motion` (relative to the scene file); the
    /// `directions` preset when absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub motion: Option<std::path::PathBuf>,
    /// The motion without a motion file: "population" (diaphragm-driven constants matched to 4DCT;
    /// the default), "breath-hold" (the population of six breath-hold pairs) or "seed" (Table 6.1).
    /// EQUATIONS.md §2.4.
    pub directions: crate::lungs::DirectionPreset,
    /// Length (mm) over which the bake makes the elastostatic amplitude smooth on the surface, so the
    /// deformed lungs do not fold (EQUATIONS.md §2.4); 0 is the seed's unsmoothed reading.
    pub amplitude_smoothing_mm: f64,
    /// How the lungs deform (EQUATIONS.md §3): "precomputed" (one baked field, supine, 3 MACs per
    /// vertex), "basis" (exact for any orientation, 4 MACs), "sh" (eq. 7.7 with `bands` bands),
    /// "direct" (eq. 7.1 every frame, the accuracy reference). Only what the mode needs is loaded.
    pub mode: crate::lungs::DeformMode,
    /// Spherical-harmonic bands a bake stores (n² coefficients per vertex, 1..8; the seed's 16
    /// coefficients are 4 bands).
    pub bands: u32,
    /// Error budget, mm (RMS displacement against eq. 7.1): the bake keeps the fewest bands that meet
    /// it; with `mode` left at its default, the launcher picks the cheapest orientation-following mode
    /// that meets it (the exact basis, whose error is round-off).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_error_mm: Option<f64>,
    /// Baked kernels (`lungdyn bake`), relative to the scene file: `[lungs.kernels] left = "l.kernel"`.
    /// The engine and renderer processes need one per lung; the launcher (`lungdyn demo`,
    /// `lungdyn scene prepare`) bakes the generated default lung for a lung without one, once.
    pub kernels: KernelPaths,
}

/// `[lungs.kernels]` table.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KernelPaths {
    /// Left lung kernel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub left: Option<std::path::PathBuf>,
    /// Right lung kernel.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub right: Option<std::path::PathBuf>,
}

impl KernelPaths {
    /// The kernel of `side`, if any.
    pub fn get(&self, side: Side) -> Option<&std::path::Path> {
        match side {
            Side::Left => self.left.as_deref(),
            Side::Right => self.right.as_deref(),
        }
    }

    /// Set the kernel of `side`.
    pub fn set(&mut self, side: Side, path: std::path::PathBuf) {
        match side {
            Side::Left => self.left = Some(path),
            Side::Right => self.right = Some(path),
        }
    }
}

impl Default for LungsScene {
    fn default() -> Self {
        Self {
            sides: vec![Side::Right, Side::Left],
            vertices: 10_000,
            shape: crate::lungs::Shape::Anatomical,
            elasticity: crate::lungs::Elasticity::default(),
            transfer_tolerance: crate::lungs::DEFAULT_TOLERANCE,
            motion: None,
            directions: crate::lungs::DirectionPreset::Population,
            amplitude_smoothing_mm: crate::lungs::DEFAULT_AMPLITUDE_SMOOTHING_MM,
            mode: crate::lungs::DeformMode::Basis,
            bands: crate::lungs::DEFAULT_SH_BANDS,
            max_error_mm: None,
            kernels: KernelPaths::default(),
        }
    }
}
