//! # lungdyn-scene: the scene schema, every table of it
//!
//! A scene file (TOML, `docs/SCENES.md`) describes one run. This crate owns its schema: every
//! table's types, their defaults (`Scene::default()` is the default scene, mirrored by
//! `scenes/default.toml`) and the checks that need no physics. Unknown keys are errors: a misspelt
//! key must not silently fall back to a default in a clinical tool.
//! * [`pv`] — `[pv]`: the pressure–volume preset and timing, or a ventilator recording to play;
//! * [`engine`] — `[engine]`: the tick, pose staleness, gravity and the orientation method;
//! * [`lungs`] — `[lungs]`: which lungs, their shape, kernels, motion and deformation mode (and the
//!   names of that vocabulary: [`lungs::Side`], [`lungs::DeformMode`]...);
//! * [`disease`] — `[disease]`: a disease state and its interventions;
//! * [`tracker`] — `[tracker]`: where poses come from and the synthetic patient's posture; the
//!   tracker-bridge reads it from the scene file itself ([`read_table`]), nothing re-stringified;
//! * [`processes`] — `[processes]`: cores, per-process budgets, real-time scheduling and each
//!   receiver's [`wake::WakeMode`];
//! * [`render`] — `[render]`: how the renderer draws;
//! * [`remote`] — `[remote]`: this machine's part in a shared session;
//! * [`breathing`] — `[breathing]`: the scene's model or the patient's signal; the bridge reads its
//!   `signal` (where the samples come from) itself;
//! * [`slicer`] — `[slicer]`: the lungs sent to 3D Slicer;
//! * [`wake`] — the wake strategies' names, shared by the scene and the transport.
//!
//! The physics tables' checks call the physics (a preset's constants, the PV timing, a disease
//! against the lungs' shapes, a kernel against the mode) and live in `lung-model`:
//! `lung_model::scene::SceneExt` reads, validates and resolves a [`Scene`]
//! (`lung_model::scene::Scene` is this one, re-exported). The tables a process reads for itself
//! ([`tracker`], [`processes`], [`render`], [`remote`], [`breathing`], [`slicer`]) are checked here, by
//! each table's `validate`; each check's message names its table and key.

pub mod breathing;
pub mod disease;
pub mod engine;
pub mod lungs;
pub mod processes;
pub mod pv;
pub mod remote;
pub mod render;
pub mod slicer;
pub mod tracker;
pub mod wake;

use std::io::Read;
use std::path::{Path, PathBuf};

pub use processes::FRAME_DEADLINE_MS;
use serde::{Deserialize, Serialize};

use breathing::BreathingScene;
use engine::EngineScene;
use lungs::LungsScene;
use processes::ProcessesScene;
use pv::PvScene;
use render::RenderScene;
use slicer::SlicerScene;
use tracker::TrackerScene;

/// A complete scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
#[derive(Default)]
pub struct Scene {
    /// Pressure–volume model.
    pub pv: PvScene,
    /// Engine timing.
    pub engine: EngineScene,
    /// Lung geometry.
    pub lungs: LungsScene,
    /// Rendering.
    pub render: RenderScene,
    /// Disease state (`[disease]`, [`crate::disease`]); none for normal breathing.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disease: Option<crate::disease::DiseaseScene>,
    /// Where the patient and HMD poses come from.
    pub tracker: TrackerScene,
    /// Where each process runs and what it may spend per tracker sample.
    pub processes: ProcessesScene,
    /// This machine's part in a shared session (`[remote]`, [`crate::remote`]); none alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub remote: Option<crate::remote::RemoteScene>,
    /// What the lungs breathe to: the PV model, or the patient's signal (`[breathing]`).
    pub breathing: BreathingScene,
    /// The lungs sent to 3D Slicer over OpenIGTLink during a demo (`[slicer]`; off by default).
    pub slicer: SlicerScene,
}

/// A value of the `[processes]` or `[render]` table that parses but cannot be used; each names its
/// table and key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TableError {
    /// Image size out of range.
    #[error("[render] width/height {width}x{height} must be within 16..8192")]
    ImageSize {
        /// Width of one eye.
        width: u32,
        /// Height.
        height: u32,
    },
    /// Field of view out of range.
    #[error("[render] fov_y_deg = {0} must be within 1..170")]
    FieldOfView(f32),
    /// An MSAA sample count the renderer does not offer.
    #[error("[render] msaa = {0}: give 4 (anti-aliased) or 1 (off)")]
    Msaa(u32),
    /// A least band count the spherical harmonics do not have.
    #[error(
        "[render] governor_least_bands = {0}: give the fewest spherical-harmonic bands the governor \
         may deform with, 1..8 (leave it out to never lower the deformation's accuracy)"
    )]
    LeastBands(u32),
    /// IPD or splat size out of range.
    #[error(
        "[render] ipd_mm = {ipd_mm} must be within 0..200 and splat_mm = {splat_mm} within 0..100"
    )]
    EyeOrSplat {
        /// IPD given.
        ipd_mm: f32,
        /// Splat size given.
        splat_mm: f32,
    },
    /// `[processes] cpus` is not three cores.
    #[error(
        "[processes] cpus = {0:?}: give three cores (tracker-bridge, engine, renderer), or none"
    )]
    ProcessCpus(Vec<usize>),
    /// A budget is out of range, or together they exceed the frame deadline.
    #[error("[processes] budget_ms: {0}")]
    ProcessBudget(String),
    /// A wake strategy the cores cannot hold, or a spin window out of range.
    #[error("[processes] {0}")]
    ProcessWake(String),
    /// A `[breathing]` value out of range.
    #[error("[breathing] {0}")]
    Breathing(String),
    /// A `[slicer]` value out of range.
    #[error("[slicer] {0}")]
    Slicer(String),
}

/// A number as every check's message prints it: three decimals at most within 1e-3..1e7, else in
/// exponent form (`1e308`, not 309 digits). The one implementation: `lung_model::plausible::compact`
/// is this.
pub fn compact(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    if v.is_finite() && v.abs() >= 1e-3 && v.abs() < 1e7 {
        format!("{}", (v * 1000.0).round() / 1000.0)
    } else {
        format!("{v:e}")
    }
}

/// The largest scene file [`read_table`] reads (a scene is a few kilobytes; `lung-model` allows the
/// same).
pub const MAX_SCENE_BYTES: u64 = 4 << 20;

/// Why one table could not be read from a scene file.
#[derive(Debug, thiserror::Error)]
pub enum ReadTableError {
    /// The file could not be opened or read.
    #[error("cannot read scene {}: {why}", path.display())]
    Read {
        /// The scene file.
        path: PathBuf,
        /// What went wrong.
        why: String,
    },
    /// The file is not TOML.
    #[error("scene {} is not valid TOML: {why}", path.display())]
    Toml {
        /// The scene file.
        path: PathBuf,
        /// The parser's message (line and column).
        why: String,
    },
    /// The table is there but one of its values cannot be used.
    #[error("scene {}: [{table}] {why}", path.display())]
    Table {
        /// The scene file.
        path: PathBuf,
        /// The table's name.
        table: String,
        /// The message (the key and what it expected).
        why: String,
    },
}

/// Read table `name` of the scene file at `path` as `T` (`T::default()` when the file has no such
/// table). The other tables are not this reader's business and are not looked at beyond parsing the
/// file as TOML; the launcher has checked the whole scene. The file must be a regular file of at most
/// [`MAX_SCENE_BYTES`] (a FIFO or a device named as a scene is refused, never waited on).
pub fn read_table<T>(path: &Path, name: &str) -> Result<T, ReadTableError>
where
    T: serde::de::DeserializeOwned + Default,
{
    let read = |why: String| ReadTableError::Read {
        path: path.to_path_buf(),
        why,
    };
    let meta = std::fs::metadata(path).map_err(|e| read(e.to_string()))?;
    if !meta.is_file() {
        return Err(read("not a regular file".into()));
    }
    if meta.len() > MAX_SCENE_BYTES {
        return Err(read(format!(
            "{} bytes, more than the {} a scene may have",
            meta.len(),
            MAX_SCENE_BYTES
        )));
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_SCENE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| read(e.to_string()))?;
    if bytes.len() as u64 > MAX_SCENE_BYTES {
        return Err(read(format!(
            "more than the {MAX_SCENE_BYTES} bytes a scene may have"
        )));
    }
    let text = String::from_utf8(bytes).map_err(|e| read(format!("not UTF-8 ({e})")))?;
    table_of(&text, name).map_err(|e| match e {
        TableOf::Toml(why) => ReadTableError::Toml {
            path: path.to_path_buf(),
            why,
        },
        TableOf::Table(why) => ReadTableError::Table {
            path: path.to_path_buf(),
            table: name.to_string(),
            why,
        },
    })
}

enum TableOf {
    Toml(String),
    Table(String),
}

fn table_of<T>(text: &str, name: &str) -> Result<T, TableOf>
where
    T: serde::de::DeserializeOwned + Default,
{
    let mut doc: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| TableOf::Toml(e.to_string().trim_end().to_string()))?;
    match doc.remove(name) {
        None => Ok(T::default()),
        Some(toml::Value::Table(t)) => t
            .try_into()
            .map_err(|e: toml::de::Error| TableOf::Table(e.message().trim_end().to_string())),
        Some(other) => Err(TableOf::Table(format!(
            "is a {}, not a table",
            other.type_str()
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tracker::{Posture, TrackerScene};

    #[test]
    fn a_table_is_read_alone_and_defaults_when_absent() {
        let t: TrackerScene = table_of(
            "[pv]\npreset = \"anything: not this reader's\"\n[tracker]\nposture = \"prone\"\n",
            "tracker",
        )
        .ok()
        .unwrap();
        assert_eq!(t.posture, Posture::Prone);
        assert_eq!(t.source, "synthetic");
        let t: TrackerScene = table_of("[render]\nwidth = 3\n", "tracker").ok().unwrap();
        assert_eq!(t, TrackerScene::default());
    }

    #[test]
    fn bad_tables_name_the_key() {
        let e = |text: &str| match table_of::<TrackerScene>(text, "tracker") {
            Err(TableOf::Table(m)) | Err(TableOf::Toml(m)) => m,
            Ok(t) => panic!("accepted {t:?}"),
        };
        assert!(e("[tracker]\nposture = \"standing\"\n").contains("standing"));
        assert!(e("[tracker]\nsorce = \"synthetic\"\n").contains("sorce"));
        assert!(e("tracker = 3\n").contains("not a table"));
        assert!(e("[tracker\n").contains("line 1"), "{}", e("[tracker\n"));
    }

    #[test]
    fn read_table_refuses_what_is_not_a_small_regular_file() {
        let dir = std::env::temp_dir().join(format!("lungdyn-scene-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = read_table::<TrackerScene>(&dir, "tracker").unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
        let missing = dir.join("missing.toml");
        let e = read_table::<TrackerScene>(&missing, "tracker").unwrap_err();
        assert!(e.to_string().contains("missing.toml"), "{e}");
        let big = dir.join("big.toml");
        std::fs::write(&big, vec![b'#'; MAX_SCENE_BYTES as usize + 1]).unwrap();
        let e = read_table::<TrackerScene>(&big, "tracker").unwrap_err();
        assert!(e.to_string().contains("more than"), "{e}");
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, b"[tracker]\nposture = \"upside-down\"\n").unwrap();
        let e = read_table::<TrackerScene>(&bad, "tracker").unwrap_err();
        assert!(
            e.to_string().contains("[tracker]") && e.to_string().contains("bad.toml"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn compact_prints_three_decimals_or_an_exponent() {
        assert_eq!(compact(0.0), "0");
        assert_eq!(compact(2.5), "2.5");
        assert_eq!(compact(1.23456), "1.235");
        assert_eq!(compact(f64::INFINITY), "inf");
        assert_eq!(compact(1e-9), "1e-9");
    }
}
