//! What `lungdyn fit-motion` reports for landmarks: the models fitted and cross-validated, the
//! frame's check, the phases predicted — read by its text ([`crate::motion_cmd`]) and its plot
//! ([`crate::motion_plot`]), one way each.

use lung_bake::motion_fit;
use lung_bake::motion_models::{self, ModelReport, PhaseReport};
use serde::Serialize;

/// A further phase in the points report.
#[derive(Debug, Serialize)]
pub struct PhaseRow {
    /// The file.
    pub file: String,
    /// The chosen model's prediction with one scale.
    #[serde(flatten)]
    pub report: PhaseReport,
    /// In-sample mean error (compatibility with the power-law report).
    pub mean_error_mm: f64,
}

/// What `fit-motion` reports for landmarks.
#[derive(Debug, Serialize)]
pub struct PointsReport {
    /// "points".
    pub mode: &'static str,
    /// The frame the files were read in ("body", "lps", "ras", "voxel").
    pub frame: &'static str,
    /// How the coordinates were read.
    pub frame_description: String,
    /// What the motion says about the frame.
    pub frame_check: motion_models::FrameCheck,
    /// A warning when the data disagree with the stated frame or phase order.
    pub frame_warning: Option<String>,
    /// A warning when the motion disagrees with `--lung`.
    pub side_warning: Option<String>,
    /// Mean landmark displacement (the no-motion error), mm.
    pub baseline_mean_mm: f64,
    /// Folds of the cross-validation and their seed.
    pub folds: u64,
    /// Seed of the folds.
    pub seed: u64,
    /// Every model fitted, with in-sample and cross-validated errors.
    pub models: Vec<ModelReport>,
    /// The model chosen (lowest held-out mean error, or `--model`).
    pub chosen: &'static str,
    /// The chosen model's held-out mean error, mm.
    pub cv_mean_error_mm: f64,
    /// The chosen model's held-out max error, mm.
    pub cv_max_error_mm: f64,
    /// The chosen model's in-sample mean error, mm.
    pub mean_error_mm: f64,
    /// The chosen model's in-sample max error, mm.
    pub max_error_mm: f64,
    /// The chosen model's in-sample RMS error, mm.
    pub rms_error_mm: f64,
    /// Further phases predicted by the chosen field with one scale.
    pub also: Vec<PhaseRow>,
    /// Per lung: the seed's power-law constants (what `bake` uses besides the field).
    pub lungs: Vec<motion_fit::LungFit>,
}
