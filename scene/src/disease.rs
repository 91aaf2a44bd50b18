//! # `[disease]`: a disease state and its interventions, as the scene file states them
//!
//! The table's types only: which keys each kind uses, their ranges and the lobe a tumour sits in are
//! checked by `lung_model::scene_disease` (it needs the lungs' shapes and the course models), which
//! turns the table into a `DiseaseSpec`.

use serde::{Deserialize, Serialize};

use crate::lungs::Side;
use ipc_types::Intervention;

/// Most events a scene may list (fixed capacity).
pub const MAX_EVENTS: usize = 1000;

/// Latest time an event or onset may name, s (≈ 116 days: far beyond any run, finite ticks).
pub const MAX_TIME_S: f64 = 1.0e7;

/// `[disease] kind`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DiseaseKind {
    /// Closed pneumothorax of one lung (eq. 8.1–8.9).
    ClosedPneumothorax,
    /// Tension pneumothorax of one lung with interventions (eq. 8.10–8.13).
    TensionPneumothorax,
    /// Closed pneumothorax of both lungs.
    BilateralPneumothorax,
    /// Tumour-influenced lung (eq. 8.14–8.22).
    Tumour,
}

impl DiseaseKind {
    /// Name as in scenes.
    pub fn name(self) -> &'static str {
        match self {
            DiseaseKind::ClosedPneumothorax => "closed-pneumothorax",
            DiseaseKind::TensionPneumothorax => "tension-pneumothorax",
            DiseaseKind::BilateralPneumothorax => "bilateral-pneumothorax",
            DiseaseKind::Tumour => "tumour",
        }
    }
}

/// The `[disease]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiseaseScene {
    /// Which disease state.
    pub kind: DiseaseKind,
    /// Affected lung (closed, tension, tumour).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub side: Option<Side>,
    /// Pneumothorax index `I ∈ [0, 1]` (closed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index: Option<f64>,
    /// Left lung's index (bilateral).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index_left: Option<f64>,
    /// Right lung's index (bilateral).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index_right: Option<f64>,
    /// Extra effort α of eq. 8.7, ml (closed, tension; default 100, the seed's demo).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_ml: Option<f64>,
    /// φ of eq. 8.8–8.9 (closed, bilateral, tension; default 0.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phi: Option<f64>,
    /// Onset of the tension pneumothorax, s from the scene's start (default 0).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub onset_s: Option<f64>,
    /// Where the air comes from, "lung" or "wound" (tension; default lung).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<LeakSource>,
    /// `V_p` of eq. 8.10, ml in the first cycle (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v_p_ml: Option<f64>,
    /// `τ` of eq. 8.10, per cycle (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tau: Option<f64>,
    /// `V1max`, ml (tension; default 0.8 × the affected lung's volume).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v1_max_ml: Option<f64>,
    /// `V2max`, ml (tension; default the unaffected lung's end-inspiratory volume with α).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v2_max_ml: Option<f64>,
    /// β, mm (tension; default 18, the seed's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beta_mm: Option<f64>,
    /// Cycles a needle decompression vents over (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub needle_vent_cycles: Option<u32>,
    /// Share of the pleural air a needle leaves (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub needle_residual: Option<f64>,
    /// Chest-tube drainage, ml per cycle (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chest_tube_ml_per_cycle: Option<f64>,
    /// Cycles from the SVC's closure to arrest (tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hyperexpansion_cycles: Option<u32>,
    /// Which reading of chapter 8: "clinical" (default, EQUATIONS §4.6) or "seed" (the seed's
    /// literal reading, §4.1–4.3) (closed, bilateral, tension).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<CourseModel>,
    /// Compliance of the mediastinum, ml/cmH₂O (tension, clinical model).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mediastinal_compliance_ml_per_cmh2o: Option<f64>,
    /// Time constant of a needle's venting, cycles (tension, clinical model).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub needle_tau_cycles: Option<f64>,
    /// Share of the mediastinal displacement taken from the other lung, 0..=1 (tension, clinical
    /// model; default 0.5; 0: the other lung is not compressed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contralateral_compression: Option<f64>,
    /// `[disease.tumour]` (tumour).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tumour: Option<TumourScene>,
    /// `[[disease.events]]` (tension).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub events: Vec<EventScene>,
}

/// `[disease.tumour]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TumourScene {
    /// Centre in normalised lung coordinates `[x̂, ŷ, ẑ]` (mediastinum → lateral, posterior →
    /// anterior, apex → base), each in [0, 1]. Optional when `lobe` is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub centre: Option<[f64; 3]>,
    /// The lobe the tumour is in ("right lower", "left upper", or "RLL"...; `mesh::lobes`): without
    /// `centre`, the centre is a point well inside that lobe of the scene's `[lungs] shape` (a lung
    /// with its own kernel gets that shape's point, in its own bounding box); with it, the centre
    /// must lie in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lobe: Option<String>,
    /// Radii along the body X, Y, Z axes, mm.
    pub radii_mm: [f64; 3],
    /// Expandability inside the tumour, (0, 1] (default 0.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub expandability: Option<f64>,
    /// Falloff width in radii (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub falloff: Option<f64>,
    /// Structural constant `B` of eq. 8.19 (default 0.25).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coupling: Option<f64>,
    /// `φ_I` variant: "none", "distance", "distance-squared" (default none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phi_variant: Option<PhiVariant>,
    /// φ of eq. 8.9 for the raised resistance (default 0.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resistance_phi: Option<f64>,
}

/// `[[disease.events]]`: an intervention at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventScene {
    /// Time from the scene's start, s.
    pub at_s: f64,
    /// What is done.
    pub kind: Intervention,
    /// On which side.
    pub side: Side,
}

/// Where the air comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LeakSource {
    /// A leak from the lung (closed tension pneumothorax): a dressing cannot stop it.
    Lung,
    /// An open (sucking) chest-wall wound acting as a one-way valve: an occlusive dressing stops it.
    Wound,
}

/// Which reading of chapter 8 a disease course follows (scene key `model`).
///
/// * [`CourseModel::Seed`] — the seed's literal reading of eq. 8.1–8.13 with lungdyn's decisions of
///   EQUATIONS §4.1–4.3 (the clamp of eq. 8.3–8.5 at 40 breaths/min, I:E 1:1 there; α added in full for
///   any pneumothorax; the mediastinum moves only after complete collapse; a needle vents linearly).
/// * [`CourseModel::Clinical`] (default) — the changes of EQUATIONS §4.6 (issue 25), each with its
///   source: the rate keeps the alveolar ventilation (`lung_model::disease::clinical_phase_times`), α grows with the
///   collapse, the pleural air is shared between the lung and the mediastinum by compliance from the
///   onset, and a needle vents the tension within a few breaths (`lung_model::disease::tension`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CourseModel {
    /// The seed's literal reading (the figures of EQUATIONS §4.1–4.3).
    Seed,
    /// The clinical course of EQUATIONS §4.6.
    #[default]
    Clinical,
}

impl CourseModel {
    /// Name as in scenes.
    pub fn name(self) -> &'static str {
        match self {
            CourseModel::Seed => "seed",
            CourseModel::Clinical => "clinical",
        }
    }
}

/// How `φ_I` is set (Fig. 8.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PhiVariant {
    /// `φ_I = 0`: eq. 8.15 reduces to eq. 8.16.
    #[default]
    None,
    /// Fig. 8.6a: the normalised distance from the posterior (supporting) surface, `ŷ`.
    Distance,
    /// Fig. 8.6b: its square, `ŷ²`.
    DistanceSquared,
}
