//! # scene: what the physics makes of a scene
//!
//! The scene file's schema — every table's types, defaults and the checks that need no physics — is
//! `lungdyn-scene`'s ([`Scene`] is its, re-exported here with every table so that callers name them
//! from one place). This module is the half that needs the physics, as [`SceneExt`]: reading a scene
//! file within limits (with the scenes beside a mistyped path), checking the physics tables' values
//! against the models (a preset that exists, a timing that gives a cycle, a disease against the lungs'
//! shapes, files that exist), and resolving a scene into what runs: the lungs' run-time models from
//! their kernels, the PV model or recording it breathes, its disease and its bake settings. Every field
//! has a default (`Scene::default()`, mirrored by `scenes/default.toml`), so an empty file is the
//! default scene; unknown keys are errors.

pub use lungdyn_scene::engine::EngineScene;
pub use lungdyn_scene::lungs::{KernelPaths, LungsScene};
pub use lungdyn_scene::pv::{PvScene, WaveformControl};
pub use lungdyn_scene::Scene;

use std::path::Path;

use serde::Serialize;

use crate::mesh::Side;
use crate::scene_disease::DiseaseSceneExt;
// The tables a process reads for itself, re-exported beside the physics tables above.
pub use lungdyn_scene::breathing::{
    check_ml_per_unit, BreathSource, BreathingScene, LatencyChoice,
};
pub use lungdyn_scene::processes::*;
pub use lungdyn_scene::render::*;
pub use lungdyn_scene::slicer::{self, SlicerScene};
pub use lungdyn_scene::tracker::*;
pub use lungdyn_scene::wake::WakeMode;
pub use lungdyn_scene::TableError;

/// The control mode a `[pv] waveform` scene's ventilator runs in, and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ControlChoice {
    /// The mode.
    pub mode: crate::recording::classify::ControlMode,
    /// `"recording"` (the majority of its breaths) or `"scene"` (`[pv] waveform_control`).
    pub set_by: &'static str,
    /// What the recording's breaths show.
    pub recording: String,
    /// The scene's choice contradicts the recording's classification.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

/// Why a scene file could not be read, without repeating its path (the message names it once).
fn read_reason(e: &crate::input::InputError) -> String {
    match e {
        crate::input::InputError::Open { source, .. } => source.to_string(),
        other => other.to_string(),
    }
}

/// Most scene files [`missing_scene_hint`] lists.
const HINT_SCENES: usize = 8;

/// For a scene path that does not exist, what a typo's fix needs: the `.toml` files in the folder
/// it points into, closest to the name given first (edit distance; `scenes/` holds the shipped
/// scenes), or that the folder does not exist either. Empty for any other read error.
fn missing_scene_hint(path: &Path, e: &crate::input::InputError) -> String {
    let crate::input::InputError::Open { source, .. } = e else {
        return String::new();
    };
    if source.kind() != std::io::ErrorKind::NotFound {
        return String::new();
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return format!(" (the folder {} does not exist either)", dir.display());
    };
    let mut names: Vec<String> = entries
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".toml"))
        .collect();
    if names.is_empty() {
        return format!(" (no .toml file in {})", dir.display());
    }
    let wanted = path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    names.sort_by_cached_key(|n| (strsim::levenshtein(&wanted, n), n.clone()));
    let more = names.len().saturating_sub(HINT_SCENES);
    names.truncate(HINT_SCENES);
    let more = if more > 0 {
        format!(" and {more} more")
    } else {
        String::new()
    };
    format!(
        "; the scenes in {}, closest first: {}{more}",
        dir.display(),
        names.join(", ")
    )
}

/// Errors loading a scene.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read within the limits.
    #[error("cannot read scene {path}: {}{hint}", read_reason(.why))]
    Read {
        /// Path.
        path: String,
        /// Why (not an error `source`: the message already says it without repeating the path).
        why: crate::input::InputError,
        /// For a path that does not exist: the scenes beside it ([`missing_scene_hint`]).
        hint: String,
    },
    /// The TOML is malformed or has unknown keys.
    #[error("scene {path} is invalid: {message}")]
    Parse {
        /// Path.
        path: String,
        /// Parser message (with line and column).
        message: String,
    },
    /// A value is out of range or a file it names is unusable.
    #[error("scene {path}: {source}")]
    Invalid {
        /// Path.
        path: String,
        /// What is wrong.
        source: SceneValueError,
    },
}

/// A scene value that parses but cannot be used; each names its key.
#[derive(Debug, thiserror::Error)]
pub enum SceneValueError {
    /// The PV preset does not exist.
    #[error("[pv] preset: {0}")]
    Preset(#[source] crate::pv::PvError),
    /// Breathing rate, I:E or tick rate give no usable cycle.
    #[error("[pv]/[engine] timing: {0}")]
    Timing(#[source] crate::pv::PvError),
    /// A value outside human ranges.
    #[error("[pv] breaths_per_min: {0}")]
    Implausible(#[source] crate::plausible::Implausible),
    /// The tick rate is out of range.
    #[error("[engine] tick_hz = {0} must be within 1..1000")]
    TickRate(f64),
    /// No lungs.
    #[error("[lungs] sides must name at least one lung (\"left\", \"right\")")]
    NoLungs,
    /// A lung twice.
    #[error("[lungs] sides lists a lung twice")]
    DuplicateLung,
    /// Generated-lung resolution out of range.
    #[error("[lungs] vertices = {0} must be within {min}..{max}", min = crate::mesh::generate::MIN_VERTICES, max = crate::mesh::generate::MAX_VERTICES)]
    Vertices(usize),
    /// The elasticity field is unusable.
    #[error("[lungs.elasticity]: {0}")]
    Elasticity(#[source] crate::operator::ElasticityError),
    /// The transfer tolerance is out of range.
    #[error("[lungs] transfer_tolerance = {0} must be within 1e-9..0.5; 1e-5 is the default")]
    Tolerance(f64),
    /// The amplitude smoothing length is out of range.
    #[error("[lungs] amplitude_smoothing_mm = {0} must be 0 (the seed's unsmoothed reading) or within 0..{max} mm; {def} is the default", max = crate::kernel::MAX_AMPLITUDE_SMOOTHING_MM, def = crate::kernel::DEFAULT_AMPLITUDE_SMOOTHING_MM)]
    AmplitudeSmoothing(f64),
    /// Gravity is not a unit vector.
    #[error("[engine] gravity_room = {0:?} must be a finite unit vector (the room's \"down\"; [0, 0, -1] when the tracker's +Z is up)")]
    Gravity([f64; 3]),
    /// The orientation limit's ratio is out of range.
    #[error("[engine] min_slope_ratio = {0} must be within 0..1 (0: no limit, the seed's reading; {def} is the default)", def = crate::orientation::DEFAULT_MIN_SLOPE_RATIO)]
    MinSlopeRatio(f64),
    /// Band count out of range.
    #[error("[lungs] bands = {0} must be within 1..{max} (n² ≤ 64 coefficients travel per lung per frame)", max = crate::kernel::MAX_RUNTIME_BANDS)]
    Bands(u32),
    /// Error budget out of range.
    #[error("[lungs] max_error_mm = {0} must be a positive number of millimetres up to 50")]
    ErrorBudget(f64),
    /// A `[processes]` or `[render]` value out of range (`lungdyn_scene`'s checks; the message
    /// names the table and key).
    #[error(transparent)]
    Table(#[from] TableError),
    /// The `[remote]` table cannot be used.
    #[error("[remote] {0}")]
    Remote(String),
    /// The PV constants file named by `[pv] constants` is unusable.
    #[error("[pv] constants: {0}")]
    Constants(#[source] crate::pv::files::PvFileError),
    /// The recording named by `[pv] waveform` is unusable, or combined with what it replaces.
    #[error("[pv] waveform: {0}")]
    Waveform(String),
    /// A key that a `[pv] waveform` scene does not use, set beside one.
    #[error(
        "[pv] {0} is set beside [pv] waveform, which plays the recording's own rate and I:E: drop it \
         (or drop the waveform to breathe the PV model at that {0})"
    )]
    BesideWaveform(&'static str),
    /// A key that applies only to a `[pv] waveform` scene, without one.
    #[error("[pv] {0} is set but [pv] waveform is not: it applies only to a scene that plays a recording")]
    WithoutWaveform(&'static str),
    /// The motion constants file named by `[lungs] motion` is unusable.
    #[error("[lungs] motion: {0}")]
    Motion(#[source] crate::deform::MotionFileError),
    /// The `[disease]` table is unusable (the message names its table and key: no prefix here).
    #[error(transparent)]
    Disease(crate::scene_disease::DiseaseSceneError),
    /// A file named by `[render] calibration` or `[render] hmd` does not exist or is not a regular
    /// file (its content is checked by the renderer's loader, `renderer::camera::RigFiles`).
    #[error("[render] {key}: {} {problem} ({hint})", path.display())]
    RenderFile {
        /// "calibration" or "hmd".
        key: &'static str,
        /// Resolved path.
        path: std::path::PathBuf,
        /// "does not exist" or "is not a regular file".
        problem: &'static str,
        /// What the file is and how to get one.
        hint: &'static str,
    },
    /// A kernel named by `[lungs.kernels]` does not exist.
    #[error("[lungs.kernels] {side}: {} does not exist (bake it with `lungdyn bake`)", path.display())]
    MissingKernel {
        /// "left" or "right".
        side: &'static str,
        /// Resolved path.
        path: std::path::PathBuf,
    },
}

/// Why a lung of a scene could not be loaded by a run-time process.
#[derive(Debug, thiserror::Error)]
pub enum LungLoadError {
    /// The scene names no kernel for a lung it simulates.
    #[error(
        "the scene names no kernel for the {side} lung: the engine and renderer never bake; bake one \
         with `lungdyn bake --lung {side} ...` and name it in [lungs.kernels], or let the launcher do it \
         (`lungdyn scene prepare [SCENE] --out DIR` writes DIR/kernels/scene.resolved.toml; `lungdyn demo` \
         does the same and starts the processes)"
    )]
    NoKernel {
        /// "left" or "right".
        side: &'static str,
    },
    /// The kernel file is unusable.
    #[error(transparent)]
    Kernel(#[from] crate::kernel::KernelError),
    /// The kernel's lung is not of a plausible size.
    #[error("{}: {source}", path.display())]
    Implausible {
        /// Kernel file.
        path: std::path::PathBuf,
        /// The value out of range.
        source: crate::plausible::Implausible,
    },
    /// The kernel lacks what the scene's deformation mode needs.
    #[error("{}: the scene's mode is \"{mode}\" but this kernel has no {missing}; bake it again with this lungdyn ({hint}) or choose another [lungs] mode", path.display())]
    ModeNeeds {
        /// Kernel file.
        path: std::path::PathBuf,
        /// The scene's mode.
        mode: crate::deform::modes::DeformMode,
        /// What is missing.
        missing: &'static str,
        /// How to get it.
        hint: &'static str,
    },
    /// The kernel's spherical harmonics do not meet the scene's error budget.
    #[error("{}: the spherical harmonics reach {reached_mm:.3} mm RMS with {bands} bands, the scene's budget is max_error_mm = {budget_mm}; the \"basis\" mode is exact for this force (`lungdyn scene prepare` switches to it)", path.display())]
    BudgetNotMet {
        /// Kernel file.
        path: std::path::PathBuf,
        /// Bands in the kernel.
        bands: u32,
        /// RMS error reached, mm.
        reached_mm: f64,
        /// The scene's budget, mm.
        budget_mm: f64,
    },
    /// The kernel is of the other lung.
    #[error("{}: this kernel is of the {kernel} lung, the scene uses it for the {scene} lung", path.display())]
    WrongSide {
        /// Kernel file.
        path: std::path::PathBuf,
        /// Side in the kernel.
        kernel: &'static str,
        /// Side in the scene.
        scene: &'static str,
    },
    /// The kernel carries another tumour than the scene (or one where the scene has none, or none
    /// where the scene has one): its breathing would silently be the wrong lung's.
    #[error(
        "{}: the kernel was baked {kernel} but the scene's {side} lung has {scene}; bake it with \
         `lungdyn bake --scene <this scene>`, or leave [lungs] kernels out and let lungdyn bake it",
        path.display()
    )]
    TumourMismatch {
        /// Kernel file.
        path: std::path::PathBuf,
        /// Which lung.
        side: &'static str,
        /// What the kernel has.
        kernel: String,
        /// What the scene has.
        scene: String,
    },
}

fn describe_tumour(t: Option<&crate::disease::tumour::Tumour>, baked: bool) -> String {
    match t {
        None if baked => "without a tumour".into(),
        None => "no tumour".into(),
        Some(t) => format!(
            "{}a tumour at centre {:?} with radii {:?} mm",
            if baked { "with " } else { "" },
            t.centre,
            t.radii_mm
        ),
    }
}

/// What the physics makes of a [`Scene`] (the schema is `lungdyn-scene`'s): reading and checking a
/// scene file, the lungs' run-time models, the PV model or recording it breathes, its disease and its
/// bake. `use lung_model::scene::SceneExt` brings these to `Scene` (`Scene::load(path)`,
/// `scene.pv_model(..)`) as they were before the schema had its own crate.
pub trait SceneExt: Sized {
    /// The run-time model of `side` from its kernel (memory-mapped, verified); a run-time process
    /// never bakes, so a scene without a kernel for `side` is an error that says how to get one.
    fn lung(&self, side: Side) -> Result<crate::deform::LungModel, LungLoadError>;

    /// The kernel of `side`, mapped lazily ([`crate::kernel::KernelFile::open_lazy`]: the sections
    /// the scene's mode does not read are never checked or paged in) and checked: plausible size,
    /// the right lung, and what the scene's `[lungs] mode` needs.
    fn lung_kernel(&self, side: Side) -> Result<crate::kernel::KernelFile, LungLoadError>;

    /// Every lung the scene simulates, in scene order.
    fn lung_models(&self) -> Result<Vec<crate::deform::LungModel>, LungLoadError>;

    /// Load a scene from a TOML file and validate it.
    fn load(path: &Path) -> Result<Self, SceneError>;

    /// Parse and validate scene TOML; `origin` names it in errors.
    fn parse(text: &str, origin: &str) -> Result<Self, SceneError>;

    /// How the scene at `path` (or the built-in default) is named in messages.
    fn origin(path: Option<&Path>) -> String;

    /// Load `path` if given, else the default scene.
    fn load_or_default(path: Option<&Path>) -> Result<Self, SceneError>;

    /// Range checks that serde cannot express.
    fn validate(&self) -> Result<(), SceneValueError>;

    /// The `[breathing]` predictor, its horizon the table's latency.
    fn breathing_predictor(&self) -> Result<crate::breathing::predict::PredictorKind, TableError>;

    /// The PV constants and boundary values of this scene: the fitted file if named, else the preset.
    fn pv_model(
        &self,
    ) -> Result<
        (
            crate::pv::PhaseConstants,
            crate::pv::PhaseConstants,
            crate::pv::Boundary,
        ),
        SceneValueError,
    >;

    /// The breathing of a `[pv] waveform` scene, read from its recording (`None` without one).
    /// Reads the file (bounded): call at load time.
    fn pv_waveform(&self) -> Result<Option<crate::recording::Waveform>, SceneValueError>;

    /// The scene's disease state, validated against its lungs (`None` without `[disease]`). On a
    /// `[pv] waveform` scene the course runs on the ventilator's recorded breath
    /// ([`crate::scene_disease::DiseaseSceneExt::validate_ventilated`], EQUATIONS §4.7).
    fn disease_spec(
        &self,
    ) -> Result<Option<crate::scene_disease::DiseaseSpec>, crate::scene_disease::DiseaseSceneError>;

    /// The breathing cycle of a `[pv] waveform` scene: its averaged breath above the preset's FRC
    /// (`None` without a waveform: the PV model gives the cycle). Reads the recording: call at load
    /// time.
    fn waveform_breathing(&self) -> Result<Option<crate::pv::Breathing>, SceneValueError>;

    /// The control mode of a `[pv] waveform` scene's ventilator (`None` without a waveform): the
    /// recording's majority class unless `[pv] waveform_control` overrides it, with a warning when the
    /// override contradicts the recording (EQUATIONS §4.7). Pressure control plays the averaged
    /// breath's equation of motion, which only passive breaths give: on a recording with none (every
    /// breath the patient's effort, as under pressure support) `"pressure"` is refused and `"auto"`
    /// plays volume control, saying why.
    fn waveform_control(
        w: &crate::recording::Waveform,
        set: WaveformControl,
    ) -> Result<ControlChoice, SceneValueError>;

    /// The ventilator of a `[pv] waveform` scene whose simulated lungs are `baselines` (`None`
    /// without a waveform): the recorded breath, the volume it delivers to them and its control
    /// ([`Self::waveform_control`]; pressure control needs a passive equation of motion of the
    /// averaged breath). Reads the recording: call at load time.
    fn ventilator(
        &self,
        baselines: &[crate::disease::LungBaseline],
    ) -> Result<Option<(crate::disease::ventilated::Ventilator, ControlChoice)>, SceneValueError>;

    /// The bake settings of `side` in this scene (motion file or the `directions` preset,
    /// elasticity, tolerance).
    fn bake_settings(
        &self,
        side: Side,
    ) -> Result<crate::kernel::BakeSettings, crate::deform::MotionFileError>;

    /// The scene's tumour, if its `[disease]` is one (validated when the scene was loaded).
    fn tumour(&self) -> Option<crate::disease::tumour::Tumour>;

    /// Breathing timing of this scene.
    fn timing(&self) -> crate::pv::Timing;
}

impl SceneExt for Scene {
    fn lung(&self, side: Side) -> Result<crate::deform::LungModel, LungLoadError> {
        Ok(self.lung_kernel(side)?.lung_model())
    }

    fn lung_kernel(&self, side: Side) -> Result<crate::kernel::KernelFile, LungLoadError> {
        use crate::deform::modes::DeformMode;
        let path = self
            .lungs
            .kernels
            .get(side)
            .ok_or(LungLoadError::NoKernel { side: side.name() })?;
        let file = crate::kernel::KernelFile::open_lazy(path)?;
        crate::plausible::LUNG_VOLUME_ML
            .check(
                file.meta().start_volume_ml,
                Some("the kernel was baked from a mesh in the wrong unit? bake it again with the right --units".into()),
            )
            .map_err(|source| LungLoadError::Implausible {
                path: path.to_path_buf(),
                source,
            })?;
        if file.meta().side != side {
            return Err(LungLoadError::WrongSide {
                path: path.to_path_buf(),
                kernel: file.meta().side.name(),
                scene: side.name(),
            });
        }
        let wanted = self.tumour().filter(|t| t.side == side);
        if file.meta().settings.tumour != wanted {
            return Err(LungLoadError::TumourMismatch {
                path: path.to_path_buf(),
                side: side.name(),
                kernel: describe_tumour(file.meta().settings.tumour.as_ref(), true),
                scene: describe_tumour(wanted.as_ref(), false),
            });
        }
        let mode = self.lungs.mode;
        let needs = |missing, hint| LungLoadError::ModeNeeds {
            path: path.to_path_buf(),
            mode,
            missing,
            hint,
        };
        if mode.follows_orientation() && file.meta().orientation.is_none() {
            return Err(needs(
                "basis responses (baked before the orientation modes)",
                "`lungdyn bake`",
            ));
        }
        if mode.follows_orientation() && file.meta().orientation_predates_fitted_force() {
            return Err(needs(
                "basis responses of its fitted force (baked when the orientation modes drew eq. \
                 6.18's linear force instead of the fit)",
                "`lungdyn bake` (or mode = \"precomputed\")",
            ));
        }
        if mode == DeformMode::Sh {
            let sh = file.meta().sh.as_ref().ok_or_else(|| {
                needs(
                    "spherical-harmonic coefficients",
                    "`lungdyn bake --bands N`, N = 1..8",
                )
            })?;
            if sh.bands > crate::kernel::MAX_RUNTIME_BANDS {
                return Err(needs(
                    "spherical harmonics within 8 bands (64 coefficients per frame)",
                    "`lungdyn bake --bands N`, N = 1..8",
                ));
            }
            if let Some(budget) = self.lungs.max_error_mm {
                if sh.rms_mm > budget {
                    return Err(LungLoadError::BudgetNotMet {
                        path: path.to_path_buf(),
                        bands: sh.bands,
                        reached_mm: sh.rms_mm,
                        budget_mm: budget,
                    });
                }
            }
        }
        Ok(file)
    }

    fn lung_models(&self) -> Result<Vec<crate::deform::LungModel>, LungLoadError> {
        self.lungs.sides.iter().map(|&s| self.lung(s)).collect()
    }

    fn load(path: &Path) -> Result<Self, SceneError> {
        let p = path.display().to_string();
        let invalid = |source| SceneError::Invalid {
            path: p.clone(),
            source,
        };
        let text = crate::input::read_text_bounded(path, crate::input::ReadLimits::CONFIG)
            .map_err(|why| SceneError::Read {
                path: p.clone(),
                hint: missing_scene_hint(path, &why),
                why,
            })?;
        let mut scene = Self::parse(&text, &p)?;
        // Files a scene names are relative to the scene file, so a scene and its patient files
        // travel together.
        let base = path.parent().unwrap_or(Path::new("."));
        if let Some(c) = &scene.pv.constants {
            let resolved = base.join(c);
            crate::pv::files::PvConstantsFile::load(&resolved)
                .map_err(|e| invalid(SceneValueError::Constants(e)))?;
            scene.pv.constants = Some(resolved);
        }
        if let Some(w) = &scene.pv.waveform {
            let resolved = base.join(w);
            scene.pv.waveform = Some(resolved);
            if let Some(w) = scene.pv_waveform().map_err(invalid)? {
                // A control the recording cannot give is refused when the scene is read.
                Self::waveform_control(&w, scene.pv.waveform_control).map_err(invalid)?;
            }
        }
        if let Some(m) = &scene.lungs.motion {
            let resolved = base.join(m);
            crate::deform::MotionFile::load(&resolved)
                .map_err(|e| invalid(SceneValueError::Motion(e)))?;
            scene.lungs.motion = Some(resolved);
        }
        for side in [Side::Left, Side::Right] {
            if let Some(k) = scene.lungs.kernels.get(side) {
                let resolved = base.join(k);
                if !resolved.is_file() {
                    return Err(invalid(SceneValueError::MissingKernel {
                        side: side.name(),
                        path: resolved,
                    }));
                }
                scene.lungs.kernels.set(side, resolved);
            }
        }
        // The breathing signal's file (`[breathing] signal = "trace:FILE"`): the bridge reads it.
        if let Some(resolved) =
            lungdyn_scene::breathing::trace_relative_to(&scene.breathing.signal, base)
        {
            if !resolved.is_file() {
                return Err(invalid(SceneValueError::Table(TableError::Breathing(
                    format!(
                        "signal = {:?}: {} is not a file (a path relative to the scene file)",
                        scene.breathing.signal,
                        resolved.display()
                    ),
                ))));
            }
            scene.breathing.signal = format!("trace:{}", resolved.display());
        }
        // The calibration and HMD optics files must exist here; their content is checked where they
        // are read (the renderer, `lungdyn scene check`, the launcher), as lung-model does not know
        // tracker files.
        for (key, file, hint) in [
            (
                "calibration",
                &mut scene.render.calibration,
                "a calibration written by `lungdyn register`",
            ),
            (
                "hmd",
                &mut scene.render.hmd,
                "an HMD optics file; `lungdyn hmd check FILE` shows one",
            ),
        ] {
            if let Some(f) = file.as_ref() {
                let resolved = base.join(f);
                let problem = match std::fs::metadata(&resolved) {
                    Err(_) => Some("does not exist"),
                    Ok(m) if !m.is_file() => Some("is not a regular file"),
                    Ok(_) => None,
                };
                if let Some(problem) = problem {
                    return Err(invalid(SceneValueError::RenderFile {
                        key,
                        path: resolved,
                        problem,
                        hint,
                    }));
                }
                *file = Some(resolved);
            }
        }
        Ok(scene)
    }

    fn parse(text: &str, origin: &str) -> Result<Self, SceneError> {
        let scene: Scene = toml::from_str(text).map_err(|e| SceneError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        scene.validate().map_err(|source| SceneError::Invalid {
            path: origin.to_string(),
            source,
        })?;
        Ok(scene)
    }

    fn origin(path: Option<&Path>) -> String {
        path.map_or_else(
            || "(built-in default)".to_string(),
            |p| p.display().to_string(),
        )
    }

    fn load_or_default(path: Option<&Path>) -> Result<Self, SceneError> {
        match path {
            Some(p) => Self::load(p),
            None => Ok(Self::default()),
        }
    }

    fn validate(&self) -> Result<(), SceneValueError> {
        use SceneValueError as E;
        crate::pv::preset(&self.pv.preset).map_err(E::Preset)?;
        crate::plausible::BREATHS_PER_MIN
            .check(self.pv.breaths_per_min, None)
            .map_err(E::Implausible)?;
        self.timing().phase_ticks().map_err(E::Timing)?;
        if !(1.0..=1000.0).contains(&self.engine.tick_hz) {
            return Err(E::TickRate(self.engine.tick_hz));
        }
        if self.pv.waveform.is_none() && self.pv.waveform_control != WaveformControl::Auto {
            return Err(E::WithoutWaveform("waveform_control"));
        }
        // A recording plays its own rate and I:E: a rate or I:E set beside it would be ignored
        // without a word. (One set to the default value cannot be told from one left out, and
        // changes nothing either way.)
        if self.pv.waveform.is_some() {
            let default = PvScene::default();
            if self.pv.breaths_per_min != default.breaths_per_min {
                return Err(E::BesideWaveform("breaths_per_min"));
            }
            if self.pv.ie_ratio != default.ie_ratio {
                return Err(E::BesideWaveform("ie_ratio"));
            }
        }
        if self.lungs.sides.is_empty() {
            return Err(E::NoLungs);
        }
        let mut seen = self.lungs.sides.clone();
        seen.sort_by_key(|s| s.index());
        seen.dedup();
        if seen.len() != self.lungs.sides.len() {
            return Err(E::DuplicateLung);
        }
        if !(crate::mesh::generate::MIN_VERTICES..=crate::mesh::generate::MAX_VERTICES)
            .contains(&self.lungs.vertices)
        {
            return Err(E::Vertices(self.lungs.vertices));
        }
        self.lungs.elasticity.validate().map_err(E::Elasticity)?;
        let t = self.lungs.transfer_tolerance;
        if !(t.is_finite() && (1e-9..=0.5).contains(&t)) {
            return Err(E::Tolerance(t));
        }
        if !crate::kernel::amplitude_smoothing_ok(self.lungs.amplitude_smoothing_mm) {
            return Err(E::AmplitudeSmoothing(self.lungs.amplitude_smoothing_mm));
        }
        let g = self.engine.gravity_room;
        let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
        if !(g.iter().all(|v| v.is_finite()) && (len - 1.0).abs() <= 1e-3) {
            return Err(E::Gravity(g));
        }
        if !crate::orientation::min_slope_ratio_ok(self.engine.min_slope_ratio) {
            return Err(E::MinSlopeRatio(self.engine.min_slope_ratio));
        }
        if !(1..=crate::kernel::MAX_RUNTIME_BANDS).contains(&self.lungs.bands) {
            return Err(E::Bands(self.lungs.bands));
        }
        if let Some(e) = self.lungs.max_error_mm {
            if !(e.is_finite() && e > 0.0 && e <= 50.0) {
                return Err(E::ErrorBudget(e));
            }
        }
        self.disease_spec().map_err(E::Disease)?;
        if let Some(r) = &self.remote {
            r.validate().map_err(E::Remote)?;
        }
        self.processes.validate()?;
        self.render.validate()?;
        self.breathing.validate()?;
        self.breathing_predictor()?;
        self.slicer.validate()?;
        Ok(())
    }

    fn breathing_predictor(&self) -> Result<crate::breathing::predict::PredictorKind, TableError> {
        use crate::breathing::predict::PredictorKind;
        match PredictorKind::parse(&self.breathing.predictor) {
            Ok(PredictorKind::Cycle { .. }) => Ok(PredictorKind::Cycle {
                horizon_ms: self.breathing.latency_ms.round() as u32,
            }),
            Ok(k) => Ok(k),
            Err(e) => Err(TableError::Breathing(format!("predictor: {e}"))),
        }
    }

    fn pv_model(
        &self,
    ) -> Result<
        (
            crate::pv::PhaseConstants,
            crate::pv::PhaseConstants,
            crate::pv::Boundary,
        ),
        SceneValueError,
    > {
        match &self.pv.constants {
            Some(path) => {
                let f = crate::pv::files::PvConstantsFile::load(path)
                    .map_err(SceneValueError::Constants)?;
                Ok((f.inhale, f.exhale, f.boundary))
            }
            None => {
                let p = crate::pv::preset(&self.pv.preset).map_err(SceneValueError::Preset)?;
                Ok((p.inhale, p.exhale, p.boundary))
            }
        }
    }

    fn pv_waveform(&self) -> Result<Option<crate::recording::Waveform>, SceneValueError> {
        let Some(path) = &self.pv.waveform else {
            return Ok(None);
        };
        if self.pv.constants.is_some() {
            return Err(SceneValueError::Waveform(
                "a scene plays a recording or a PV model, not both: drop [pv] constants".into(),
            ));
        }
        let rec = crate::recording::read_recording(path, crate::input::ReadLimits::TABLE)
            .map_err(|e| SceneValueError::Waveform(e.to_string()))?;
        crate::recording::average_breath(
            &rec,
            &crate::recording::SegmentOptions::default(),
            self.engine.tick_hz,
        )
        .map(Some)
        .map_err(|e| SceneValueError::Waveform(format!("{}: {e}", path.display())))
    }

    fn disease_spec(
        &self,
    ) -> Result<Option<crate::scene_disease::DiseaseSpec>, crate::scene_disease::DiseaseSceneError>
    {
        let Some(d) = &self.disease else {
            return Ok(None);
        };
        let sides = &self.lungs.sides;
        match self.pv.waveform {
            Some(_) => d.validate_ventilated(sides, self.lungs.shape),
            None => d.validate(sides, self.lungs.shape),
        }
        .map(Some)
    }

    fn waveform_breathing(&self) -> Result<Option<crate::pv::Breathing>, SceneValueError> {
        let Some(w) = self.pv_waveform()? else {
            return Ok(None);
        };
        breathing_of(self, &w).map(Some)
    }

    fn waveform_control(
        w: &crate::recording::Waveform,
        set: WaveformControl,
    ) -> Result<ControlChoice, SceneValueError> {
        use crate::recording::classify::ControlMode;
        let found = w.control.mode();
        let recording = w.control.describe();
        let passive = w.control.passive_volume_controlled + w.control.passive_pressure_controlled;
        let no_passive = |why: &str| {
            format!(
                "{why}: none of the recording's whole breaths is passive ({recording}), so its airway \
                 pressure is not what drives the volume and no equation of motion can be fitted to it"
            )
        };
        let (mode, set_by) = match set {
            WaveformControl::Pressure if passive == 0 => {
                return Err(SceneValueError::Waveform(no_passive(
                    "waveform_control = \"pressure\" needs passive breaths; use \"volume\"",
                )))
            }
            WaveformControl::Auto if passive == 0 && found == ControlMode::Pressure => {
                return Ok(ControlChoice {
                    mode: ControlMode::Volume,
                    set_by: "recording",
                    warning: Some(no_passive(
                        "the recording's breaths hold their pressure, but a disease is played as \
                         volume control",
                    )),
                    recording,
                });
            }
            WaveformControl::Auto => (found, "recording"),
            WaveformControl::Volume => (ControlMode::Volume, "scene"),
            WaveformControl::Pressure => (ControlMode::Pressure, "scene"),
        };
        let warning = (mode != found).then(|| {
            format!(
                "[pv] waveform_control = \"{}\" contradicts the recording's classification ({recording}): \
                 a disease is played as if the ventilator held the {}",
                mode.name(),
                match mode {
                    ControlMode::Volume => "volume",
                    ControlMode::Pressure => "pressure",
                }
            )
        });
        Ok(ControlChoice {
            mode,
            set_by,
            recording,
            warning,
        })
    }

    fn ventilator(
        &self,
        baselines: &[crate::disease::LungBaseline],
    ) -> Result<Option<(crate::disease::ventilated::Ventilator, ControlChoice)>, SceneValueError>
    {
        use crate::disease::ventilated::{delivered_ml, Control, PressureDrive, Ventilator};
        let Some(w) = self.pv_waveform()? else {
            return Ok(None);
        };
        let recorded = breathing_of(self, &w)?;
        let choice = Self::waveform_control(&w, self.pv.waveform_control)?;
        let control = match choice.mode {
            crate::recording::classify::ControlMode::Volume => Control::Volume,
            crate::recording::classify::ControlMode::Pressure => {
                let eom = w.eom.as_ref().ok_or_else(|| {
                    SceneValueError::Waveform(
                        "pressure control needs the equation of motion of the recording's averaged \
                         breath, which cannot be fitted (no volume or flow change)"
                            .into(),
                    )
                })?;
                Control::Pressure(Box::new(
                    PressureDrive::new(&w.paw_cmh2o, eom, self.engine.tick_hz)
                        .map_err(SceneValueError::Waveform)?,
                ))
            }
        };
        let delivered = delivered_ml(baselines, recorded.boundary().tv_ml);
        Ok(Some((
            Ventilator {
                recorded,
                delivered_ml: delivered,
                control,
            },
            choice,
        )))
    }

    fn bake_settings(
        &self,
        side: Side,
    ) -> Result<crate::kernel::BakeSettings, crate::deform::MotionFileError> {
        let (motion, direction_field, force_field) = match &self.lungs.motion {
            Some(path) => {
                let f = crate::deform::MotionFile::load(path)?;
                (
                    f.for_side(side),
                    f.field_for_side(side).cloned(),
                    f.force_for_side(side).cloned(),
                )
            }
            None => {
                let m = crate::deform::preset_motion(self.lungs.directions, side);
                (m.constants, m.direction_field, m.force_field)
            }
        };
        Ok(crate::kernel::BakeSettings {
            motion,
            direction_field,
            force_field,
            elasticity: self.lungs.elasticity,
            tolerance: self.lungs.transfer_tolerance,
            // The one error-budget rule: with a budget the bake keeps the fewest bands, from 1 up to
            // the run time's most, that meet it (lung_bake::kernel::bake); without one, the scene's
            // band count. `scene prepare`, `bake --scene` and `bake --max-error-mm` all start here.
            sh_bands: if self.lungs.max_error_mm.is_some() {
                crate::kernel::MAX_RUNTIME_BANDS
            } else {
                self.lungs.bands
            },
            max_error_mm: self.lungs.max_error_mm,
            tumour: self.tumour().filter(|t| t.side == side),
            amplitude_smoothing_mm: self.lungs.amplitude_smoothing_mm,
        })
    }

    fn tumour(&self) -> Option<crate::disease::tumour::Tumour> {
        match self.disease.as_ref()?.resolve(self.lungs.shape).ok()? {
            crate::scene_disease::DiseaseSpec::Tumour(t) => Some(t),
            _ => None,
        }
    }

    fn timing(&self) -> crate::pv::Timing {
        crate::pv::Timing {
            tick_hz: self.engine.tick_hz,
            breaths_per_min: self.pv.breaths_per_min,
            ie_inhale: self.pv.ie_ratio[0],
            ie_exhale: self.pv.ie_ratio[1],
        }
    }
}

/// The breathing cycle that plays `w` above the preset's FRC.
fn breathing_of(
    this: &Scene,
    w: &crate::recording::Waveform,
) -> Result<crate::pv::Breathing, SceneValueError> {
    let frc = crate::pv::preset(&this.pv.preset)
        .map_err(SceneValueError::Preset)?
        .boundary
        .frc_ml;
    crate::pv::Breathing::from_volume_table(&w.volume_ml, w.inhale_ticks, frc)
        .map_err(|e| SceneValueError::Waveform(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn processes_take_three_cores_and_budgets_that_fit_the_frame() {
        let ok = Scene::parse(
            "[processes]\ncpus = [0, 1, 1]\n[processes.budget_ms]\ntracker_bridge = 0.5\nengine = 1.5\nrenderer = 12.0\n",
            "s.toml",
        )
        .unwrap();
        assert_eq!(ok.processes.cpus, vec![0, 1, 1]);
        assert_eq!(ok.processes.budget_ms.renderer, 12.0);
        // The defaults fit the 16.7 ms frame with room for the transport.
        let d = ProcessBudgets::default();
        assert!(d.tracker_bridge + d.engine + d.renderer < FRAME_DEADLINE_MS);
        for (text, needle) in [
            ("[processes]\ncpus = [0, 1]\n", "give three cores"),
            (
                "[processes.budget_ms]\nengine = 0\n",
                "engine = 0 must be within",
            ),
            ("[processes.budget_ms]\nrenderer = -1\n", "renderer = -1"),
            (
                "[processes.budget_ms]\nrenderer = 16.0\n",
                "sum to 19.00 ms",
            ),
            ("[processes.budget_ms]\nengine = nan\n", "engine = NaN"),
            ("[processes]\ncpu = [0, 1, 1]\n", "cpu"),
            ("[processes.budget_ms]\ngpu = 1.0\n", "gpu"),
        ] {
            let e = Scene::parse(text, "s.toml").unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }

    #[test]
    fn wake_takes_one_strategy_for_both_or_a_table_and_busy_poll_needs_a_core_of_its_own() {
        let one = Scene::parse("[processes]\nwake = \"event\"\n", "s.toml").unwrap();
        assert_eq!(one.processes.wake, ProcessWake::both(WakeMode::Event));
        let each = Scene::parse(
            "[processes]\ncpus = [0, 1, 2]\nspin_us = 50\nwake = { engine = \"busy-poll\", renderer = \"spin-then-park\" }\n",
            "s.toml",
        )
        .unwrap();
        assert_eq!(each.processes.wake.engine, WakeMode::BusyPoll);
        assert_eq!(each.processes.wake.renderer, WakeMode::SpinThenPark);
        assert_eq!(each.processes.spin_us, 50);
        let half = Scene::parse("[processes.wake]\nrenderer = \"event\"\n", "s.toml").unwrap();
        assert_eq!(half.processes.wake.engine, WakeMode::Auto);
        assert_eq!(half.processes.wake.renderer, WakeMode::Event);
        assert_eq!(
            Scene::default().processes.wake,
            ProcessWake::both(WakeMode::Auto)
        );
        // The resolved scene the launcher writes reads back the same.
        let text = toml::to_string(&each).unwrap();
        assert_eq!(Scene::parse(&text, "resolved.toml").unwrap(), each);
        assert_eq!(each.processes.reserved_core(1), Some(1));
        let shared = Scene::parse("[processes]\ncpus = [0, 1, 1]\n", "s.toml").unwrap();
        assert_eq!(shared.processes.reserved_core(0), Some(0));
        assert_eq!(shared.processes.reserved_core(1), None);
        assert_eq!(Scene::default().processes.reserved_core(1), None);
        for (text, needle) in [
            ("[processes]\nwake = \"busy_poll\"\n", "\"busy_poll\" is not a wake strategy"),
            ("[processes]\nwake = \"\"\n", "is not a wake strategy"),
            ("[processes]\nwake = 3\n", "a wake strategy"),
            ("[processes]\nwake = [\"event\"]\n", "a wake strategy"),
            ("[processes.wake]\ntracker-bridge = \"event\"\n", "tracker-bridge"),
            ("[processes.wake]\nengine = \"fast\"\n", "fast"),
            (
                "[processes]\nwake = \"busy-poll\"\n",
                "wake: engine = \"busy-poll\" spins a whole core: it needs a core of its own, and [processes] cpus gives none",
            ),
            (
                "[processes]\ncpus = [0, 1, 1]\nwake = { renderer = \"busy-poll\" }\n",
                "gives the renderer core 1, shared with the engine",
            ),
            (
                "[processes]\ncpus = [1, 1, 1]\nwake = { engine = \"busy-poll\" }\n",
                "shared with the tracker-bridge and renderer",
            ),
            ("[processes]\nspin_us = 0\n", "spin_us = 0 must be within 1..2000"),
            ("[processes]\nspin_us = 2001\n", "spin_us = 2001"),
            ("[processes]\nspin_us = -5\n", "spin_us"),
        ] {
            let e = Scene::parse(text, "s.toml").unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }

    /// `[engine] min_slope_ratio` (EQUATIONS.md §3.3): 0 (no limit, the seed's reading) to 1;
    /// anything else is refused by name with the range.
    #[test]
    fn the_orientation_limit_ratio_is_checked() {
        for ok in ["0", "0.5", "0.8", "1"] {
            let s = Scene::parse(&format!("[engine]\nmin_slope_ratio = {ok}\n"), "s.toml").unwrap();
            assert_eq!(s.engine.min_slope_ratio, ok.parse::<f64>().unwrap());
        }
        for bad in ["1.5", "-0.1", "nan", "inf"] {
            let e = Scene::parse(&format!("[engine]\nmin_slope_ratio = {bad}\n"), "s.toml")
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("min_slope_ratio") && e.contains("0..1"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn the_committed_default_scene_is_the_built_in_default() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/default.toml");
        assert_eq!(Scene::load(&path).unwrap(), Scene::default());
        assert_eq!(Scene::parse("", "empty").unwrap(), Scene::default());
    }

    #[test]
    fn a_scene_path_that_does_not_exist_lists_the_scenes_beside_it() {
        let dir = std::env::temp_dir().join(format!("lungdyn-scene-typo-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in ["tension_pneumothorax.toml", "default.toml", "notes.txt"] {
            std::fs::write(dir.join(name), "").unwrap();
        }
        let typo = dir.join("tension_pneumothrax.toml");
        let e = Scene::load(&typo).unwrap_err().to_string();
        assert!(e.starts_with("cannot read scene"), "{e}");
        assert!(
            e.contains("the scenes in") && e.contains("tension_pneumothorax.toml, default.toml"),
            "{e}"
        );
        assert!(!e.contains("notes.txt"), "{e}");
        assert_eq!(
            e.matches("tension_pneumothrax").count(),
            1,
            "the path once: {e}"
        );
        let e = Scene::load(&dir.join("no-such-folder/s.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("does not exist either"), "{e}");
        // A file that exists but cannot be read as a scene gets no list.
        std::fs::create_dir_all(dir.join("folder.toml")).unwrap();
        let e = Scene::load(&dir.join("folder.toml"))
            .unwrap_err()
            .to_string();
        assert!(!e.contains("the scenes in"), "{e}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn kernel_and_motion_paths_resolve_relative_to_the_scene_and_must_exist() {
        let dir = std::env::temp_dir().join(format!("lungdyn-scene-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scene = dir.join("s.toml");
        std::fs::write(&scene, "[lungs.kernels]\nleft = \"missing.kernel\"\n").unwrap();
        let e = Scene::load(&scene).unwrap_err().to_string();
        assert!(
            e.contains("missing.kernel") && e.contains("lungdyn bake"),
            "{e}"
        );
        std::fs::write(dir.join("l.kernel"), b"x").unwrap();
        std::fs::write(&scene, "[lungs.kernels]\nleft = \"l.kernel\"\n").unwrap();
        let s = Scene::load(&scene).unwrap();
        assert_eq!(
            s.lungs.kernels.get(Side::Left),
            Some(dir.join("l.kernel").as_path())
        );
        std::fs::write(&scene, "[lungs]\nmotion = \"m.toml\"\n").unwrap();
        std::fs::write(dir.join("m.toml"), "format = 3\n").unwrap();
        let e = Scene::load(&scene).unwrap_err().to_string();
        assert!(e.contains("format 3"), "{e}");
        std::fs::write(
            dir.join("m.toml"),
            "format = 1\n[left]\nc = [1.0, 0.5, 2.0, 0.5, 3.0, 2.0, 0.01, 0.95, 0.07]\n",
        )
        .unwrap();
        let s = Scene::load(&scene).unwrap();
        assert_eq!(s.bake_settings(Side::Left).unwrap().motion.c[0], 1.0);
        assert_eq!(
            s.bake_settings(Side::Right).unwrap().motion,
            crate::deform::MotionConstants::table_6_1(Side::Right)
        );
    }

    #[test]
    fn render_calibration_and_hmd_paths_resolve_relative_to_the_scene_and_must_be_files() {
        let dir = std::env::temp_dir().join(format!("lungdyn-scene-render-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("patient")).unwrap();
        let scene = dir.join("s.toml");
        std::fs::write(dir.join("patient/calib.toml"), "format = 1\n").unwrap();
        std::fs::write(dir.join("hmd.toml"), "format = 1\n").unwrap();
        std::fs::write(
            &scene,
            "[render]\ncalibration = \"patient/calib.toml\"\nhmd = \"hmd.toml\"\n",
        )
        .unwrap();
        let s = Scene::load(&scene).unwrap();
        assert_eq!(s.render.calibration, Some(dir.join("patient/calib.toml")));
        assert_eq!(s.render.hmd, Some(dir.join("hmd.toml")));
        // Absent keys stay absent and are not written back.
        let d = Scene::parse("", "empty").unwrap();
        assert_eq!((d.render.calibration, d.render.hmd), (None, None));
        let text = toml::to_string(&Scene::default()).unwrap();
        assert!(
            !text.contains("calibration") && !text.contains("hmd"),
            "{text}"
        );
        // A written scene with the keys reads back the same.
        let back = Scene::parse(&toml::to_string(&s).unwrap(), "back").unwrap();
        assert_eq!(back, s);
        std::fs::write(&scene, "[render]\ncalibration = \"none.toml\"\n").unwrap();
        let e = Scene::load(&scene).unwrap_err().to_string();
        assert!(
            e.contains("[render] calibration")
                && e.contains("none.toml")
                && e.contains("does not exist"),
            "{e}"
        );
        std::fs::write(&scene, "[render]\nhmd = \"patient\"\n").unwrap();
        let e = Scene::load(&scene).unwrap_err().to_string();
        assert!(
            e.contains("[render] hmd") && e.contains("is not a regular file"),
            "{e}"
        );
        for bad in [
            "[render]\ncalibratoin = \"c.toml\"\n",
            "[render]\nhmd_file = \"h.toml\"\n",
            "[render.hmd]\nipd_mm = 64\n",
        ] {
            let e = Scene::parse(bad, "s.toml").unwrap_err().to_string();
            assert!(e.contains("s.toml"), "{bad}: {e}");
        }
        let e = Scene::parse("[render]\ncalibratoin = \"c.toml\"\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("calibratoin"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn bad_scenes_are_refused_with_the_key_named() {
        let e = Scene::parse("[pv]\npresett = \"x\"\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("presett"), "{e}");
        let e = Scene::parse("[pv]\npreset = \"nope\"\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown PV preset"), "{e}");
        let e = Scene::parse("[lungs]\nvertices = 5\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("vertices"), "{e}");
        let e = Scene::parse("[lungs]\nsides = [\"left\", \"left\"]\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("twice"), "{e}");
        let e = Scene::parse("[lungs.elasticity]\napex = 0\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("[lungs.elasticity]"), "{e}");
        let e = Scene::parse("[lungs]\ntransfer_tolerance = 2\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("transfer_tolerance"), "{e}");
        for bad in ["-1", "nan", "inf", "1e3"] {
            let e = Scene::parse(
                &format!("[lungs]\namplitude_smoothing_mm = {bad}\n"),
                "s.toml",
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains("amplitude_smoothing_mm"), "{bad}: {e}");
        }
        let e = Scene::parse("[lungs.kernels]\nmiddle = \"m.kernel\"\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("middle"), "{e}");
        let e = Scene::parse("[render]\nmode = \"voxels\"\n", "s.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains("voxels"), "{e}");
    }

    #[test]
    fn render_look_colour_and_msaa_parse_by_name_and_refuse_others() {
        let s = Scene::parse(
            "[render]\nlook = \"see-through\"\ncolor = \"ventilation\"\nmsaa = 1\n",
            "s.toml",
        )
        .unwrap();
        assert_eq!(
            (s.render.look, s.render.color, s.render.msaa),
            (Look::SeeThrough, ColorMode::Ventilation, Some(1))
        );
        let d = Scene::default().render;
        assert_eq!(
            (d.look, d.color, d.msaa),
            (Look::Opaque, ColorMode::Tissue, None)
        );
        for look in Look::ALL {
            assert_eq!(look.name().parse::<Look>().unwrap(), look);
        }
        for c in ColorMode::ALL {
            assert_eq!(c.name().parse::<ColorMode>().unwrap(), c);
        }
        let e = "glass".parse::<Look>().unwrap_err();
        assert!(e.contains("glass") && e.contains("see-through"), "{e}");
        assert_eq!("lobes".parse::<ColorMode>(), Ok(ColorMode::Lobes));
        for bad in ["lobe", "Lobes", " lobes", ""] {
            let e = bad.parse::<ColorMode>().unwrap_err();
            assert!(
                e.contains("lobes") && e.contains("ventilation"),
                "{bad:?}: {e}"
            );
        }
        for bad in [
            "look = \"glass\"",
            "color = \"lobe\"",
            "color = \"LOBES\"",
            "look = 1",
        ] {
            let e = Scene::parse(&format!("[render]\n{bad}\n"), "s.toml")
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("look") || e.contains("color") || e.contains("glass"),
                "{bad}: {e}"
            );
        }
        for n in [0u32, 2, 3, 8, 16] {
            let mut s = Scene::default();
            s.render.msaa = Some(n);
            let e = s.validate().unwrap_err().to_string();
            assert!(e.contains("msaa") && e.contains(&n.to_string()), "{e}");
        }
    }

    #[test]
    fn render_lod_parses_auto_off_and_levels_and_refuses_others() {
        assert_eq!(Scene::default().render.lod, Lod::Auto);
        for (text, lod) in [
            ("\"auto\"", Lod::Auto),
            ("\"off\"", Lod::Off),
            ("0", Lod::Level(0)),
            ("3", Lod::Level(3)),
            ("5", Lod::Level(5)),
            ("\"2\"", Lod::Level(2)),
        ] {
            let s = Scene::parse(&format!("[render]\nlod = {text}\n"), "s.toml").unwrap();
            assert_eq!(s.render.lod, lod, "{text}");
            // The resolved scene the launcher hands the renderer reads back the same.
            let back = Scene::parse(&toml::to_string(&s).unwrap(), "s.toml").unwrap();
            assert_eq!(back.render.lod, lod, "{text}");
            assert_eq!(lod.to_string().parse::<Lod>(), Ok(lod));
        }
        for bad in [
            "\"fast\"", "\"Auto\"", "\"\"", "6", "-1", "300", "1.5", "true", "[1]",
        ] {
            let e = Scene::parse(&format!("[render]\nlod = {bad}\n"), "s.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains("lod") && e.contains("auto"), "{bad}: {e}");
        }
        for bad in ["fast", "6", "-1", "+1", "", " 1"] {
            let e = bad.parse::<Lod>().unwrap_err();
            assert!(e.contains("auto") && e.contains("off"), "{bad:?}: {e}");
        }
    }

    #[test]
    fn render_governor_is_hold_deadline_by_default_and_refuses_other_words() {
        assert_eq!(Scene::default().render.governor, Governor::HoldDeadline);
        for g in Governor::ALL {
            let s = Scene::parse(&format!("[render]\ngovernor = \"{g}\"\n"), "s.toml").unwrap();
            assert_eq!(s.render.governor, g);
            // The resolved scene the launcher hands the renderer reads back the same.
            let back = Scene::parse(&toml::to_string(&s).unwrap(), "s.toml").unwrap();
            assert_eq!(back.render.governor, g);
            assert_eq!(g.to_string().parse::<Governor>(), Ok(g));
        }
        for bad in ["\"fast\"", "\"Off\"", "\"\"", "true", "1"] {
            let e = Scene::parse(&format!("[render]\ngovernor = {bad}\n"), "s.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains("governor"), "{bad}: {e}");
        }
        let e = "on".parse::<Governor>().unwrap_err();
        assert!(e.contains("hold-deadline") && e.contains("off"), "{e}");
    }

    /// Where the governor starts: "remembered" by default (and then not written into a resolved
    /// scene), "full" read and written back, other words refused naming the key and the choices.
    #[test]
    fn governor_start_is_remembered_by_default_and_refuses_other_words() {
        assert_eq!(
            Scene::default().render.governor_start,
            GovernorStart::Remembered
        );
        assert!(!toml::to_string(&Scene::default())
            .unwrap()
            .contains("governor_start"));
        for g in GovernorStart::ALL {
            let s =
                Scene::parse(&format!("[render]\ngovernor_start = \"{g}\"\n"), "s.toml").unwrap();
            assert_eq!(s.render.governor_start, g);
            let back = Scene::parse(&toml::to_string(&s).unwrap(), "s.toml").unwrap();
            assert_eq!(back.render.governor_start, g);
            assert_eq!(g.to_string().parse::<GovernorStart>(), Ok(g));
        }
        for bad in ["\"last\"", "\"Full\"", "\"\"", "true", "0"] {
            let e = Scene::parse(&format!("[render]\ngovernor_start = {bad}\n"), "s.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains("governor_start"), "{bad}: {e}");
        }
        let e = "fresh".parse::<GovernorStart>().unwrap_err();
        assert!(e.contains("remembered") && e.contains("full"), "{e}");
    }

    /// The governor's accuracy opt-in: unset by default (accuracy never lowered), 1..8 read and
    /// written back, anything else refused naming the key.
    #[test]
    fn governor_least_bands_is_unset_by_default_and_refuses_what_is_not_a_band_count() {
        assert_eq!(Scene::default().render.governor_least_bands, None);
        assert!(!toml::to_string(&Scene::default())
            .unwrap()
            .contains("governor_least_bands"));
        for n in [1u32, 2, 8] {
            let s =
                Scene::parse(&format!("[render]\ngovernor_least_bands = {n}\n"), "s.toml").unwrap();
            assert_eq!(s.render.governor_least_bands, Some(n));
            let back = Scene::parse(&toml::to_string(&s).unwrap(), "s.toml").unwrap();
            assert_eq!(back.render.governor_least_bands, Some(n));
        }
        for bad in ["0", "9", "-1", "2.5", "\"2\"", "true"] {
            let e = Scene::parse(
                &format!("[render]\ngovernor_least_bands = {bad}\n"),
                "s.toml",
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains("governor_least_bands"), "{bad}: {e}");
        }
    }

    /// A recording plays its own rate and I:E: a rate or an I:E set beside it is refused naming
    /// the key (it would be ignored without a word); the defaults a resolved scene writes back
    /// still parse.
    #[test]
    fn a_rate_or_an_ie_ratio_beside_a_waveform_is_refused() {
        for (key, value) in [("breaths_per_min", "20"), ("ie_ratio", "[1, 1]")] {
            let e = Scene::parse(
                &format!("[pv]\nwaveform = \"r.csv\"\n{key} = {value}\n"),
                "s.toml",
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains(key) && e.contains("beside [pv] waveform"), "{e}");
        }
        let mut resolved = Scene::default();
        resolved.pv.waveform = Some("r.csv".into());
        Scene::parse(&toml::to_string(&resolved).unwrap(), "s.toml").unwrap();
    }

    /// Pressure control plays the averaged breath's equation of motion, which only passive breaths
    /// give: on a pressure-support-like recording (the ventilator holds the pressure, every breath
    /// triggered by the patient) `"pressure"` is refused when the scene is read, `"auto"` plays
    /// volume control with a warning, `"volume"` plays.
    #[test]
    fn pressure_control_needs_passive_breaths_in_the_recording() {
        use crate::recording::classify::ControlMode;
        use crate::recording::{Synthetic, SyntheticMode};
        let dir = std::env::temp_dir().join(format!("lungdyn-scene-effort-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut rec = Synthetic {
            mode: SyntheticMode::Pressure {
                above_peep_cmh2o: 15.0,
            },
            breaths: 6,
            ..Default::default()
        }
        .recording();
        // A trigger dip of 3 cmH2O 0.18–0.12 s before every breath (inside the trigger's 0.2 s,
        // before the 0.1 s the previous breath's PEEP is read over); the file starts in the first
        // breath's expiration (that cut breath is an artefact), so no breath is passive.
        let starts: Vec<usize> = rec.vent_breaths.iter().map(|b| b.0).collect();
        for &at in &starts[1..] {
            for j in at - 9..at - 5 {
                rec.paw_cmh2o[j] -= 3.0;
            }
        }
        let mut csv = String::from("time_s,flow_L/s,paw_cmH2O\n");
        for i in starts[1] - 10..rec.t_s.len() {
            csv.push_str(&format!(
                "{},{},{}\n",
                rec.t_s[i], rec.flow_lps[i], rec.paw_cmh2o[i]
            ));
        }
        std::fs::write(dir.join("effort.csv"), csv).unwrap();
        let scene = |control: &str| {
            let p = dir.join(format!("{control}.toml"));
            std::fs::write(
                &p,
                format!("[pv]\nwaveform = \"effort.csv\"\nwaveform_control = \"{control}\"\n"),
            )
            .unwrap();
            Scene::load(&p)
        };
        let auto = scene("auto").unwrap();
        let w = auto.pv_waveform().unwrap().unwrap();
        let c = &w.control;
        assert_eq!(
            c.passive_volume_controlled + c.passive_pressure_controlled,
            0,
            "{}",
            c.describe()
        );
        assert_eq!(c.mode(), ControlMode::Pressure, "{}", c.describe());
        let choice = Scene::waveform_control(&w, WaveformControl::Auto).unwrap();
        assert_eq!(choice.mode, ControlMode::Volume);
        assert!(choice.warning.unwrap().contains("volume control"));
        let e = scene("pressure").unwrap_err().to_string();
        assert!(
            e.contains("needs passive breaths") && e.contains("use \"volume\""),
            "{e}"
        );
        scene("volume").unwrap();
        std::fs::remove_dir_all(&dir).ok();
    }
}
