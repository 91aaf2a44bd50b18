//! # kernel: the kernel file — a baked lung (mesh, operator, motion model) on disk
//!
//! A kernel holds the whole of seed ch. 6 for one lung: the mesh, every Green's-function transfer
//! row (eq. 6.11–6.13), the applied force of eq. 6.18, the elastostatic force `F = Tᵀf` (eq. 6.1),
//! the directions of eq. 6.14–6.16 and the unit displacement `F[i]·d_i` scaled to one unit volume
//! (EQUATIONS §2.4). `lung-bake` computes it and writes it with [`write_file`]; the engine and the
//! renderer map it with [`KernelFile::open`] and never bake. [`KernelFile::id`] identifies its
//! content on the wire (`ipc_types::LungFrame::kernel_id`).
//!
//! ## File format, version 1 (little-endian throughout; every offset a multiple of 64)
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `LUNGDYNK` |
//! | 8 | 4 | format version (u32) = 1 |
//! | 12 | 4 | byte-order mark (u32) `0x0102_0304` as written by a little-endian machine |
//! | 16 | 4 | section count (u32, at most 64) |
//! | 20 | 4 | reserved, 0 |
//! | 24 | 8 | file length in bytes (u64) |
//! | 32 | 8 | xxh3-64 of the section table |
//! | 40 | 8 | xxh3-64 of bytes 0..40 |
//! | 48 | 16 | reserved, 0 |
//! | 64 | 32 × count | section table: kind (u32), element size (u32), offset (u64), length (u64), xxh3-64 of the bytes (u64) |
//!
//! Sections (kind: content): 1 metadata (UTF-8 JSON, [`KernelMeta`]); 2 positions (f32 × 3 per
//! vertex, mm, body frame); 3 triangles (u32 × 3, counter-clockwise from outside); 4 directions
//! (f32 × 3, unit, eq. 6.14–6.16); 5 applied force (f32, eq. 6.18); 6 elastostatic force
//! (f32, `F = Tᵀf`); 7 unit displacement (f32 × 3, mm per unit volume); 8 row offsets (u64,
//! vertices + 1); 9 columns (u32 per non-zero); 10 values (f32 per non-zero, `T[j→i]`);
//! 11 spherical-harmonic transfer coefficients (f32 × bands² per vertex, `T^I_lm` of seed eq. 7.4,
//! present when [`KernelMeta::sh`] is); 12 basis responses (f32 × 4 per vertex, `G_0, G_x, G_y, G_z`
//! of EQUATIONS.md §3.3, present when [`KernelMeta::orientation`] is); 13 lobes (u8 per vertex, the
//! codes of [`crate::mesh::lobes::Lobe`], 0..=5; optional: kernels baked before it existed have none
//! and still load, [`KernelFile::lobes`] then answers `None`). A reader ignores kinds it does
//! not know, so sections can be added without a new version; a change to any existing section's
//! meaning bumps the version.
//!
//! Sections are 64-byte aligned, so a memory-mapped file is used in place ([`KernelFile`]). Every
//! claim of the header is checked against the real file size before anything is read, every
//! section's checksum is verified, and the content is checked (indices in range, offsets monotone,
//! floats finite): a truncated, foreign or corrupted file is refused with a specific
//! [`FormatError`].

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::{
    DEFAULT_AMPLITUDE_SMOOTHING_MM, DEFAULT_SH_BANDS, DEFAULT_TOLERANCE,
};

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use thiserror::Error;
use xxhash_rust::xxh3::{xxh3_64, Xxh3};

use crate::deform::{LungModel, MotionConstants};
use crate::mesh::{Side, TriMesh};
use crate::operator::{Elasticity, Transfer, TransferStats};

/// File magic.
pub const MAGIC: [u8; 8] = *b"LUNGDYNK";
/// Format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
/// Byte-order mark as written by a little-endian machine.
pub const BOM: u32 = 0x0102_0304;
/// Header size, bytes.
pub const HEADER: usize = 64;
/// Section-table entry size, bytes.
pub const ENTRY: usize = 32;
/// Largest coordinate a kernel's positions may have, mm (10 m: a tracker room, not a body).
pub const MAX_COORDINATE_MM: f32 = 1e4;
/// Most sections a file may claim.
pub const MAX_SECTIONS: usize = 64;
/// Alignment of every section, bytes.
pub const ALIGN: u64 = 64;

/// Section kinds.
pub mod section {
    /// Metadata, JSON.
    pub const META: u32 = 1;
    /// Positions, f32 × 3.
    pub const POSITIONS: u32 = 2;
    /// Triangles, u32 × 3.
    pub const TRIANGLES: u32 = 3;
    /// Directions, f32 × 3.
    pub const DIRECTIONS: u32 = 4;
    /// Applied force, f32.
    pub const APPLIED_FORCE: u32 = 5;
    /// Elastostatic force, f32.
    pub const ELASTOSTATIC: u32 = 6;
    /// Unit displacement, f32 × 3.
    pub const UNIT_DISPLACEMENT: u32 = 7;
    /// CSR row offsets, u64.
    pub const ROW_PTR: u32 = 8;
    /// CSR columns, u32.
    pub const COLS: u32 = 9;
    /// CSR values, f32.
    pub const VALS: u32 = 10;
    /// Spherical-harmonic transfer coefficients `T^I_lm`, f32 × bands² per vertex (seed eq. 7.4).
    pub const SH: u32 = 11;
    /// Basis responses `(G_0, G_x, G_y, G_z)`, f32 × 4 per vertex (EQUATIONS.md §3.3).
    pub const BASIS: u32 = 12;
    /// Lobe code per vertex, u8 ([`crate::mesh::lobes::Lobe`]); optional.
    pub const LOBES: u32 = 13;
}

/// What a bake needs besides the mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BakeSettings {
    /// Direction and applied-force constants `c1..c9` (the population preset by default).
    pub motion: MotionConstants,
    /// A displacement field fitted to the patient's landmarks (`lungdyn fit-motion`): when present,
    /// it gives each vertex's direction `d_i` instead of eq. 6.14–6.16 (the applied force and the
    /// operator are unchanged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction_field: Option<crate::deform::field::Field>,
    /// An applied force field fitted to the patient's breath-hold pair (`lungdyn fit-motion
    /// --exhale/--inhale`): when present, the force on each vertex before the operator instead of
    /// `c7..c9`'s linear one (the operator and everything after it are unchanged).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force_field: Option<crate::deform::field::ForceField>,
    /// Regional elasticity.
    pub elasticity: Elasticity,
    /// Pitcher tolerance for a unit force.
    pub tolerance: f64,
    /// Spherical-harmonic bands baked for the SH mode (`n`, `n²` coefficients per vertex; seed: 4);
    /// 0 bakes none. With [`Self::max_error_mm`] this is the most the bake may use.
    #[serde(default = "default_sh_bands")]
    pub sh_bands: u32,
    /// Error budget (mm, RMS displacement against eq. 7.1 at the reference volume over the
    /// orientation set): the bake keeps the fewest bands that meet it (EQUATIONS.md §3.2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_error_mm: Option<f64>,
    /// A tumour region (seed §8.2): the bake changes the transfer rows by eq. 8.14–8.20 before
    /// everything derived from them (EQUATIONS §4.4). Part of the settings, so a kernel names the
    /// tumour it carries and a cached bake is reused only for the same tumour.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tumour: Option<crate::disease::tumour::Tumour>,
    /// Length (mm) over which the elastostatic amplitude is made smooth on the surface
    /// (EQUATIONS.md §2.4, "the deformed surface must not fold"); 0 is the seed's unsmoothed
    /// reading. A kernel written before this key existed was baked unsmoothed, hence 0 when absent.
    #[serde(default)]
    pub amplitude_smoothing_mm: f64,
}

/// Largest smoothing length accepted, mm (a lung is ≈ 100–250 mm across).
pub const MAX_AMPLITUDE_SMOOTHING_MM: f64 = 100.0;

/// A smoothing length is 0 (none) or finite in (0, [`MAX_AMPLITUDE_SMOOTHING_MM`]].
pub fn amplitude_smoothing_ok(length_mm: f64) -> bool {
    length_mm == 0.0 || (length_mm > 0.0 && length_mm <= MAX_AMPLITUDE_SMOOTHING_MM)
}

/// Most bands a kernel may carry for the run time (`ipc_types::MAX_COEFFS` = 64 = 8²).
pub const MAX_RUNTIME_BANDS: u32 = 8;

fn default_sh_bands() -> u32 {
    DEFAULT_SH_BANDS
}

impl BakeSettings {
    /// The default motion ([`crate::deform::DirectionPreset::default`], the population
    /// constants), the default elasticity field and tolerance.
    pub fn default_for(side: Side) -> Self {
        Self::for_preset(crate::deform::DirectionPreset::default(), side)
    }

    /// [`Self::default_for`] with the motion of `preset`.
    pub fn for_preset(preset: crate::deform::DirectionPreset, side: Side) -> Self {
        let m = crate::deform::preset_motion(preset, side);
        Self {
            motion: m.constants,
            direction_field: m.direction_field,
            force_field: m.force_field,
            elasticity: Elasticity::default(),
            tolerance: DEFAULT_TOLERANCE,
            sh_bands: DEFAULT_SH_BANDS,
            max_error_mm: None,
            tumour: None,
            amplitude_smoothing_mm: DEFAULT_AMPLITUDE_SMOOTHING_MM,
        }
    }
}

/// The enclosed volume of `p + s·u(w)` with `u(w) = Σ_a w_a·U_a` as forms in the weights:
/// `V = v0 + s·Σ_a w_a·L_a + s²·Σ_ab w_a w_b·Q_ab + s³·Σ_abc w_a w_b w_c·C_abc` (mm³), exact for a
/// closed mesh (divergence theorem, the same triple products as `VolumeCubic::of`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeForms {
    /// Volume of the undeformed mesh, mm³.
    pub v0: f64,
    /// Linear form.
    pub l: [f64; 4],
    /// Quadratic form (not symmetrised).
    pub q: [[f64; 4]; 4],
    /// Cubic form (not symmetrised).
    pub c: [[[f64; 4]; 4]; 4],
}

/// What the orientation-dependent modes (direct eq. 7.1 and the exact basis) need beyond the
/// sections: the enclosed volume as forms in the force weights (EQUATIONS.md §3.3), and how well
/// the stored basis reproduces eq. 7.1.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OrientationMeta {
    /// Enclosed volume of `p + s·Σ_a w_a·k·G_a·d` as forms in `w = (w0, wx, wy, wz)`.
    pub volume_forms: VolumeForms,
    /// Largest displacement difference of the basis mode (stored f32 responses) against eq. 7.1
    /// evaluated in f64 from the transfer rows, at the reference volume over the orientation set, mm.
    pub basis_max_error_mm: f64,
    /// Volume change above FRC at which errors are reported, ml.
    pub reference_delta_ml: f64,
    /// Orientations the errors were taken over.
    pub orientations_checked: u32,
    /// The first basis function is the fitted supine force
    /// ([`crate::deform::fitted_supine_force`]) instead of the constant 1: the kernel was baked with a
    /// force field and every orientation mode draws it supine (EQUATIONS.md §3.3, "A fitted supine
    /// force"). Absent (false) in kernels baked before; such a kernel with a force field is refused
    /// by the orientation modes ([`KernelMeta::orientation_predates_fitted_force`]).
    #[serde(default)]
    pub fitted_supine_force: bool,
}

/// The spherical-harmonic form (seed eq. 7.2–7.7, EQUATIONS.md §3.2) as baked.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShMeta {
    /// Bands `n` (`l < n`, `n²` coefficients per vertex).
    pub bands: u32,
    /// Centre of projection (the mesh's volume centroid), mm.
    pub centre_mm: [f64; 3],
    /// Least-squares scale of eq. 7.7 against eq. 7.1.
    pub alpha: f64,
    /// Force projection: `projection[a·n² + k] = Σ_J w_J·x̂_a(J)·Y_k(J)` for `x̂_0 = 1, x̂, ŷ, ẑ`,
    /// so the force coefficients of weights `w` are `F_k = Σ_a w_a·projection[a·n² + k]`.
    pub projection: Vec<f64>,
    /// Enclosed volume of the SH mode's displacement as forms in the weights.
    pub volume_forms: VolumeForms,
    /// RMS displacement error against eq. 7.1 as % of the largest eq. 7.1 displacement.
    pub rms_percent: f64,
    /// RMS displacement error against eq. 7.1, mm.
    pub rms_mm: f64,
    /// Largest displacement error against eq. 7.1, mm.
    pub max_mm: f64,
    /// Largest displacement change the run time's 16-bit storage of the coefficients makes
    /// (EQUATIONS.md §3.2), mm; included in the errors above, which are of what is drawn. Absent
    /// (0) in kernels baked before the run time quantised them.
    #[serde(default)]
    pub quantisation_max_mm: f64,
    /// Vertices touching a triangle whose projection from the centre folds over (or contains it).
    pub foldover_nodes: u64,
    /// The error budget the bands were chosen for, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget_mm: Option<f64>,
    /// With a budget: the RMS error (mm) of each band count tried, from 1 band up to the one kept
    /// (the fewest that meets the budget) or to the most allowed when none does — why the bands
    /// are what they are. Empty without a budget.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub budget_trials_rms_mm: Vec<f64>,
}

impl ShMeta {
    /// Why the kernel has the bands it has, when they were chosen for an error budget: one line a
    /// person can check ("5 bands: the fewest of 1..8 whose RMS error meets the 1 mm budget (4 bands
    /// 1.210 mm, 5 bands 0.930 mm)"), or that none meets it. `None` without a budget.
    pub fn budget_reason(&self) -> Option<String> {
        let budget = self.budget_mm?;
        let tried = |from: usize| {
            self.budget_trials_rms_mm
                .iter()
                .enumerate()
                .skip(from)
                .map(|(i, e)| format!("{} bands {e:.3} mm", i + 1))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let last_two = self.budget_trials_rms_mm.len().saturating_sub(2);
        Some(if self.rms_mm <= budget {
            format!(
                "{} bands: the fewest whose RMS error against eq. 7.1 meets the {budget} mm budget ({})",
                self.bands,
                tried(last_two)
            )
        } else {
            format!(
                "{} bands: NO band count up to {} meets the {budget} mm budget ({}); the exact basis \
                 mode does (the launcher runs it instead)",
                self.bands,
                self.bands,
                tried(last_two)
            )
        })
    }
}

/// Metadata section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KernelMeta {
    /// Which lung.
    pub side: Side,
    /// Length unit of positions and displacements (always "mm").
    pub units: String,
    /// Vertices (mass nodes).
    pub vertices: u64,
    /// Triangles.
    pub triangles: u64,
    /// Edges (spring nodes).
    pub spring_nodes: u64,
    /// Stored transfer non-zeros.
    pub nnz: u64,
    /// xxh3-64 of the input mesh (positions then triangles, little-endian), hex.
    pub mesh_hash: String,
    /// What the bake used.
    pub settings: BakeSettings,
    /// Figures of the transfer computation.
    pub transfer: TransferStats,
    /// Unit volume the unit displacement adds, ml.
    pub unit_volume_ml: f64,
    /// Factor from `F[i]·d_i` to the unit displacement.
    pub force_scale: f64,
    /// Enclosed volume of the mesh, ml.
    pub start_volume_ml: f64,
    /// Software that wrote the file.
    pub written_by: String,
    /// The orientation-dependent modes' data (absent in kernels baked before them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orientation: Option<OrientationMeta>,
    /// The spherical-harmonic mode's data (absent when baked with 0 bands or before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sh: Option<ShMeta>,
    /// The tumour the kernel was baked with, and how its centre moves (seed §8.2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tumour: Option<TumourMeta>,
    /// The volumes the kernel draws without its surface crossing itself (absent in kernels baked
    /// before it was measured).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fold_free: Option<FoldFreeMeta>,
}

/// How far from its start volume a kernel's lung can be drawn before its surface crosses itself:
/// measured at bake time on the precomputed field `p + s·u` (the lung supine, as the GPU draws it in
/// the precomputed mode): 24 volumes stepping out from the start, the first fold refined to 1/768
/// of each searched span (`lung_bake::folds`). A fitted motion slides the
/// base along the chest wall and may fold a lung within a deep breath (docs/masks/patient_motion.md);
/// the engine marks every frame that draws a lung outside this range
/// (`ipc_types::lung_flags::PAST_FOLD_FREE`), so a fold is never drawn unannounced.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FoldFreeMeta {
    /// Largest volume change above the start volume drawn without a fold, ml
    /// (`searched_above_ml` when none was found up to there).
    pub above_ml: f64,
    /// Largest volume change below the start volume drawn without a fold, ml, as a positive number
    /// (`searched_below_ml` when none was found down to there).
    pub below_ml: f64,
    /// How far above the start volume the search went, ml.
    pub searched_above_ml: f64,
    /// How far below the start volume the search went, ml (positive).
    pub searched_below_ml: f64,
}

impl FoldFreeMeta {
    /// Share of a lung's start volume searched above it: the deepest breath-hold pair shared with
    /// lungdyn (COPDgene case 08) inhales 0.8× its exhale volume; a tidal breath is about 0.2×.
    pub const ABOVE_SHARE: f64 = 1.0;
    /// Share of a lung's start volume searched below it: a quarter (the engine's tests breathe both
    /// lungs down to FRC − 500 ml, about 0.2× a lung's FRC).
    pub const BELOW_SHARE: f64 = 0.25;

    /// Whether a lung drawn `delta_ml` from its start volume lies within the range checked free of
    /// folds (a change past the searched span is outside: not checked).
    #[inline]
    pub fn contains(&self, delta_ml: f64) -> bool {
        delta_ml <= self.above_ml && delta_ml >= -self.below_ml
    }

    /// What a report says of a kernel's range, or of its absence.
    pub fn words(range: Option<&Self>) -> String {
        range.map_or_else(
            || "not measured (baked by an older lungdyn: bake it again to have it)".into(),
            Self::describe,
        )
    }

    /// What a report says of it.
    pub fn describe(&self) -> String {
        let side = |found: f64, searched: f64, sign: char| {
            if found >= searched {
                format!("no fold to {sign}{searched:.0} ml (as far as checked)")
            } else {
                format!("folds past {sign}{found:.0} ml")
            }
        };
        format!(
            "{}; {}",
            side(self.above_ml, self.searched_above_ml, '+'),
            side(self.below_ml, self.searched_below_ml, '-')
        )
    }
}

impl KernelMeta {
    /// A kernel baked with a fitted force field by a lungdyn whose orientation modes drew eq. 6.18's
    /// linear force instead of the fit (before [`OrientationMeta::fitted_supine_force`]): its basis,
    /// SH and direct data describe another motion than its precomputed field. Bake it again.
    pub fn orientation_predates_fitted_force(&self) -> bool {
        self.settings.force_field.is_some()
            && self
                .orientation
                .as_ref()
                .is_some_and(|o| !o.fitted_supine_force)
    }
}

/// What a kernel baked with a tumour records of it ([`KernelMeta::tumour`]): the region, what the
/// kernel change did, and how the tumour centre moves in every deformation mode.
///
/// Every mode's displacement is linear in its per-vertex data, and the centre's displacement is the
/// mean-value interpolation of the surface's (`crate::disease::tumour`, Decisions), so the centre moves by the same
/// linear form with the per-vertex data replaced by their mean-value sums:
/// precomputed `s·Σ_i λ_i u_i`; basis (and direct, eq. 7.1, which the basis reproduces to
/// round-off) `s·Σ_a w_a·Σ_i λ_i G_{i,a} k d_i`; SH (eq. 7.7) `s·Σ_k F_k·Σ_i λ_i T_{i,k} k d_i`.
/// The sums are taken at bake time from the data the run time deforms with: the stored f32 data,
/// and for SH the 16-bit values it holds them as ([`crate::deform::sh_coeffs`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TumourMeta {
    /// The tumour as baked.
    pub tumour: crate::disease::tumour::Tumour,
    /// Centre at rest (FRC), body frame, mm.
    pub centre_mm: [f64; 3],
    /// Volume of the ellipsoid, ml.
    pub volume_ml: f64,
    /// Vertices with expandability below 1.
    pub vertices_affected: u64,
    /// Kernel entries changed by eq. 8.14–8.20.
    pub entries_changed: u64,
    /// Entries whose `d'` was clamped to the acos domain.
    pub entries_clamped: u64,
    /// Of those, entries where `B·e` made `d' ≤ 0`.
    pub entries_nonpositive: u64,
    /// Kernel reach ℓ, mm.
    pub reach_mm: f64,
    /// Smallest and largest entry factor applied.
    pub factor_range: [f64; 2],
    /// How much the tumour changed the surface motion where it reaches (vertices with `a < 1`):
    /// mean and largest `|u − u_normal| / |u_normal|` of the unit displacement, %.
    pub affected_motion_change_percent: [f64; 2],
    /// Centre displacement per unit deformation scale, precomputed mode, mm.
    pub precomputed_mm: [f64; 3],
    /// The same centre in the lung baked without the tumour, mm per unit scale (for comparison).
    pub normal_precomputed_mm: [f64; 3],
    /// Centre displacement per unit scale per force weight `(w0, wx, wy, wz)`: basis and direct modes.
    pub basis_mm: [[f64; 3]; 4],
    /// Centre displacement per unit scale per SH force coefficient (`bands²`; empty without SH).
    #[serde(default)]
    pub sh_mm: Vec<[f64; 3]>,
}

impl TumourMeta {
    /// The centre's position, mm, for deformation scale `scale`, the lung's collapse `collapse`
    /// towards `hilum_mm` and rigid offset (EQUATIONS §4.1: `h + (1 − c)(p − h) + s·u + o`).
    pub fn position_mm(
        &self,
        displacement_mm: [f64; 3],
        scale: f64,
        collapse: f64,
        hilum_mm: [f64; 3],
        offset_mm: [f64; 3],
    ) -> [f64; 3] {
        [0, 1, 2].map(|a| {
            hilum_mm[a]
                + (1.0 - collapse) * (self.centre_mm[a] - hilum_mm[a])
                + scale * displacement_mm[a]
                + offset_mm[a]
        })
    }
}

/// Errors reading or writing a kernel file.
#[derive(Debug, Error)]
pub enum KernelError {
    /// Reading or writing failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Writing refused or failed (a target that is not a regular file, an OS error).
    #[error(transparent)]
    Write(#[from] outfile::WriteError),
    /// Not a regular file.
    #[error(transparent)]
    Input(crate::input::InputError),
    /// The file is not a usable kernel.
    #[error("{}: {source}", path.display())]
    Invalid {
        /// File.
        path: PathBuf,
        /// What is wrong.
        source: FormatError,
    },
}

/// Why a byte image is not a valid kernel.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum FormatError {
    /// Shorter than a header.
    #[error("truncated or empty: {len} bytes, a kernel header needs {HEADER}")]
    TooShort {
        /// Bytes present.
        len: u64,
    },
    /// Not our magic.
    #[error("not a lungdyn kernel file (wrong magic; expected LUNGDYNK)")]
    Magic,
    /// Another format version.
    #[error("kernel format version {found}; this lungdyn reads version {FORMAT_VERSION}: bake the mesh again")]
    Version {
        /// Version in the file.
        found: u32,
    },
    /// Byte-order mark wrong.
    #[error("byte-order mark is wrong: the file is corrupted or was not written by lungdyn")]
    ByteOrder,
    /// Header checksum wrong.
    #[error("header checksum mismatch: the file is corrupted")]
    HeaderChecksum,
    /// Too many sections claimed.
    #[error("header claims {count} sections (at most {MAX_SECTIONS})")]
    SectionCount {
        /// Sections claimed.
        count: usize,
    },
    /// The file length differs from the header's claim.
    #[error("truncated or padded: the header says {claimed} bytes, the file has {actual}")]
    Length {
        /// Length in the header.
        claimed: u64,
        /// Real length.
        actual: u64,
    },
    /// The section table runs past the end.
    #[error("truncated: the section table runs past the end of the file")]
    TableTruncated,
    /// Section table checksum wrong.
    #[error("section table checksum mismatch: the file is corrupted")]
    TableChecksum,
    /// A section runs past the end.
    #[error("section {index} (kind {kind}) runs past the end of the file")]
    SectionPastEnd {
        /// Table index.
        index: usize,
        /// Section kind.
        kind: u32,
    },
    /// A section is unaligned or overlaps the table.
    #[error("section {index} (kind {kind}) is misplaced at offset {offset}")]
    SectionMisplaced {
        /// Table index.
        index: usize,
        /// Section kind.
        kind: u32,
        /// Offset claimed.
        offset: u64,
    },
    /// A section's length is not a whole number of elements.
    #[error(
        "section {index} (kind {kind}): length {len} is not a multiple of its element size {elem}"
    )]
    SectionElement {
        /// Table index.
        index: usize,
        /// Section kind.
        kind: u32,
        /// Length, bytes.
        len: u64,
        /// Element size, bytes.
        elem: u32,
    },
    /// A section's checksum is wrong.
    #[error("section {index} (kind {kind}) checksum mismatch: the file is corrupted")]
    SectionChecksum {
        /// Table index.
        index: usize,
        /// Section kind.
        kind: u32,
    },
    /// A section kind appears twice.
    #[error("section kind {kind} appears twice")]
    DuplicateSection {
        /// Section kind.
        kind: u32,
    },
    /// A required section is missing.
    #[error("required section kind {kind} is missing")]
    MissingSection {
        /// Section kind.
        kind: u32,
    },
    /// A section has the wrong element size.
    #[error("section kind {kind} has element size {found}, expected {expected}")]
    ElementSize {
        /// Section kind.
        kind: u32,
        /// Element size in the file.
        found: u32,
        /// Element size expected.
        expected: u32,
    },
    /// The metadata JSON does not parse as [`KernelMeta`].
    #[error("metadata: {0}")]
    Metadata(String),
    /// Lengths are not in millimetres.
    #[error("metadata: units {found:?}, expected \"mm\"")]
    Units {
        /// Units in the file.
        found: String,
    },
    /// A section's element count disagrees with the metadata.
    #[error("section kind {kind} holds {found} elements, the metadata implies {expected}")]
    ElementCount {
        /// Section kind.
        kind: u32,
        /// Elements present.
        found: u64,
        /// Elements implied.
        expected: u64,
    },
    /// A position is beyond any body (more than [`MAX_COORDINATE_MM`] from the origin on an axis).
    #[error("positions: coordinate {index} = {value:e} mm is beyond any body (|x| ≤ {MAX_COORDINATE_MM:e} mm); was the mesh in another unit?")]
    PositionRange {
        /// Index of the float.
        index: usize,
        /// Its value.
        value: f32,
    },
    /// A float is NaN or infinite.
    #[error("{what}: value {index} is not finite")]
    NonFinite {
        /// Which section.
        what: &'static str,
        /// Index of the float.
        index: usize,
    },
    /// A triangle references a vertex that does not exist.
    #[error("triangle {triangle} references a vertex out of range")]
    TriangleIndex {
        /// Triangle index.
        triangle: usize,
    },
    /// A lobe code is not one of 0..=5.
    #[error("vertex {vertex} has lobe code {code}; codes are 0 (unknown) to 5 (left lower)")]
    LobeCode {
        /// Vertex index.
        vertex: usize,
        /// The code found.
        code: u8,
    },
    /// A transfer column references a vertex that does not exist.
    #[error("a transfer column references a vertex out of range")]
    ColumnIndex,
    /// Row offsets decrease.
    #[error("transfer row offsets are not monotone at row {row}")]
    RowOffsets {
        /// Row.
        row: usize,
    },
    /// Row offsets do not end at the non-zero count.
    #[error("transfer row offsets end at {last}, the metadata says {nnz} non-zeros")]
    RowEnd {
        /// Last offset.
        last: u64,
        /// Non-zeros in the metadata.
        nnz: u64,
    },
}

/// xxh3-64 of a mesh (positions then triangles, little-endian bytes).
pub fn mesh_hash(mesh: &TriMesh) -> u64 {
    let mut h = Xxh3::new();
    h.update(bytemuck::cast_slice(&mesh.positions));
    h.update(bytemuck::cast_slice(&mesh.triangles));
    h.digest()
}

/// One section to write: kind, element size, bytes.
pub type SectionData<'a> = (u32, u32, &'a [u8]);

/// Write a kernel file atomically (temporary sibling, then rename): the metadata section, then
/// `sections` in order, each 64-byte aligned, with every checksum. Returns the file length.
pub fn write_file(
    path: &Path,
    meta: &KernelMeta,
    sections: &[SectionData<'_>],
) -> Result<u64, KernelError> {
    let meta = serde_json::to_vec_pretty(meta).map_err(|e| KernelError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    })?;
    let mut all: Vec<SectionData<'_>> = vec![(section::META, 1, &meta)];
    all.extend_from_slice(sections);
    let sections = all;
    let count = sections.len();
    let mut offset = align((HEADER + ENTRY * count) as u64);
    let mut table = Vec::with_capacity(ENTRY * count);
    for (kind, elem, bytes) in &sections {
        table.extend_from_slice(&kind.to_le_bytes());
        table.extend_from_slice(&elem.to_le_bytes());
        table.extend_from_slice(&offset.to_le_bytes());
        table.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        table.extend_from_slice(&xxh3_64(bytes).to_le_bytes());
        offset = align(offset + bytes.len() as u64);
    }
    let file_len = offset;
    let mut header = [0u8; HEADER];
    header[0..8].copy_from_slice(&MAGIC);
    header[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
    header[12..16].copy_from_slice(&BOM.to_le_bytes());
    header[16..20].copy_from_slice(&(count as u32).to_le_bytes());
    header[24..32].copy_from_slice(&file_len.to_le_bytes());
    header[32..40].copy_from_slice(&xxh3_64(&table).to_le_bytes());
    let head_sum = xxh3_64(&header[0..40]);
    header[40..48].copy_from_slice(&head_sum.to_le_bytes());
    outfile::write_atomically(path, |w| {
        use std::io::Write;
        let mut at = 0u64;
        let pad_to = |w: &mut std::io::BufWriter<std::fs::File>, at: &mut u64, to: u64| {
            let zeros = [0u8; 64];
            while *at < to {
                let n = ((to - *at) as usize).min(64);
                w.write_all(&zeros[..n])?;
                *at += n as u64;
            }
            std::io::Result::Ok(())
        };
        w.write_all(&header)?;
        w.write_all(&table)?;
        at += (HEADER + table.len()) as u64;
        for (_, _, bytes) in &sections {
            let to = align(at);
            pad_to(w, &mut at, to)?;
            w.write_all(bytes)?;
            at += bytes.len() as u64;
        }
        pad_to(w, &mut at, file_len)
    })
    .map_err(KernelError::Write)?;
    Ok(file_len)
}

fn align(v: u64) -> u64 {
    v.div_ceil(ALIGN) * ALIGN
}

/// A kernel file, memory-mapped and verified; accessors borrow the mapping.
///
/// [`KernelFile::open`] verifies every section before returning. [`KernelFile::open_lazy`] (the
/// run-time processes) verifies the header, the section table, the metadata and the sections every
/// deformation mode reads (positions, triangles, directions, unit displacement) at once, and every
/// other section (the transfer rows, the spherical-harmonic and basis coefficients, the forces) the
/// first time it is asked for: a precomputed-mode run never reads, let alone checks, the transfer
/// rows, which are most of the file. [`KernelFile::bytes_verified`] counts what was checked.
pub struct KernelFile {
    path: PathBuf,
    map: memmap2::Mmap,
    id: u64,
    meta: KernelMeta,
    sections: Vec<Section>,
    checked: Vec<std::sync::OnceLock<Result<(), FormatError>>>,
    verified_bytes: std::sync::atomic::AtomicU64,
}

impl std::fmt::Debug for KernelFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KernelFile")
            .field("path", &self.path)
            .field("meta", &self.meta)
            .finish()
    }
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// A section as the table describes it: kind, element size, byte offset, byte length, checksum.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Section {
    /// Section kind ([`section`]).
    pub kind: u32,
    /// Element size, bytes.
    pub elem: u32,
    /// Byte offset in the file.
    pub offset: usize,
    /// Byte length.
    pub len: usize,
    /// xxh3-64 of the bytes, as the table claims.
    pub checksum: u64,
}

/// Sections every deformation mode reads: verified when a kernel is opened, even lazily.
pub const CORE_SECTIONS: [u32; 4] = [
    section::POSITIONS,
    section::TRIANGLES,
    section::DIRECTIONS,
    section::UNIT_DISPLACEMENT,
];

/// Why a byte image is not a valid kernel (no path; [`KernelFile::open`] adds it): the layout and
/// then every section.
pub fn verify_bytes(b: &[u8]) -> Result<(KernelMeta, Vec<Section>), FormatError> {
    let (meta, sections) = verify_layout(b)?;
    for (index, s) in sections.iter().enumerate() {
        verify_section(b, index, s, &meta)?;
    }
    Ok((meta, sections))
}

/// Element size and count a known section must have under `meta`; `None` for kinds this build does
/// not know (ignored).
fn expected_shape(kind: u32, meta: &KernelMeta) -> Option<(u32, u64)> {
    let v = meta.vertices;
    Some(match kind {
        section::META => return None,
        section::POSITIONS | section::DIRECTIONS | section::UNIT_DISPLACEMENT => (12, v),
        section::TRIANGLES => (12, meta.triangles),
        section::APPLIED_FORCE | section::ELASTOSTATIC => (4, v),
        section::ROW_PTR => (8, v.saturating_add(1)),
        section::COLS | section::VALS => (4, meta.nnz),
        section::SH => {
            let n = meta.sh.as_ref().map_or(0, |s| s.bands as u64);
            (4, v.saturating_mul(n * n))
        }
        section::BASIS => (16, v),
        section::LOBES => (1, v),
        _ => return None,
    })
}

/// The header, the section table, the metadata and the shape of every known section (sizes and
/// counts against the metadata) — everything but the other sections' bytes.
pub fn verify_layout(b: &[u8]) -> Result<(KernelMeta, Vec<Section>), FormatError> {
    let (count, table_end) = verify_header(b)?;
    let sections = section_table(b, count, table_end)?;
    let meta = read_meta(b, &sections)?;
    check_meta(&meta)?;
    check_shapes(&sections, &meta)?;
    Ok((meta, sections))
}

/// The header (magic, version, byte order, checksum, length) and the section table's checksum:
/// the section count and where the table ends.
fn verify_header(b: &[u8]) -> Result<(usize, usize), FormatError> {
    if b.len() < HEADER {
        return Err(FormatError::TooShort {
            len: b.len() as u64,
        });
    }
    if b[0..8] != MAGIC {
        return Err(FormatError::Magic);
    }
    let version = u32_at(b, 8);
    if version != FORMAT_VERSION {
        return Err(FormatError::Version { found: version });
    }
    if u32_at(b, 12) != BOM {
        return Err(FormatError::ByteOrder);
    }
    if xxh3_64(&b[0..40]) != u64_at(b, 40) {
        return Err(FormatError::HeaderChecksum);
    }
    let count = u32_at(b, 16) as usize;
    if count > MAX_SECTIONS {
        return Err(FormatError::SectionCount { count });
    }
    let file_len = u64_at(b, 24);
    if file_len != b.len() as u64 {
        return Err(FormatError::Length {
            claimed: file_len,
            actual: b.len() as u64,
        });
    }
    let table_end = HEADER + ENTRY * count;
    if table_end > b.len() {
        return Err(FormatError::TableTruncated);
    }
    let table = &b[HEADER..table_end];
    if xxh3_64(table) != u64_at(b, 32) {
        return Err(FormatError::TableChecksum);
    }
    Ok((count, table_end))
}

/// The section table's entries: each inside the file, aligned after the table, a whole number of
/// elements, no kind twice.
fn section_table(b: &[u8], count: usize, table_end: usize) -> Result<Vec<Section>, FormatError> {
    let table = &b[HEADER..table_end];
    let mut sections: Vec<Section> = Vec::with_capacity(count);
    for s in 0..count {
        let e = &table[s * ENTRY..(s + 1) * ENTRY];
        let (kind, elem) = (u32_at(e, 0), u32_at(e, 4));
        let (offset, len, checksum) = (u64_at(e, 8), u64_at(e, 16), u64_at(e, 24));
        let end = offset
            .checked_add(len)
            .filter(|&end| end <= b.len() as u64)
            .ok_or(FormatError::SectionPastEnd { index: s, kind })?;
        let _ = end;
        if offset % ALIGN != 0 || offset < table_end as u64 {
            return Err(FormatError::SectionMisplaced {
                index: s,
                kind,
                offset,
            });
        }
        if elem == 0 || len % elem as u64 != 0 {
            return Err(FormatError::SectionElement {
                index: s,
                kind,
                len,
                elem,
            });
        }
        if sections.iter().any(|x| x.kind == kind) {
            return Err(FormatError::DuplicateSection { kind });
        }
        sections.push(Section {
            kind,
            elem,
            offset: offset as usize,
            len: len as usize,
            checksum,
        });
    }
    Ok(sections)
}

/// The metadata section, checksummed and parsed.
fn read_meta(b: &[u8], sections: &[Section]) -> Result<KernelMeta, FormatError> {
    let (meta_index, meta_section) = sections
        .iter()
        .enumerate()
        .find(|(_, s)| s.kind == section::META)
        .ok_or(FormatError::MissingSection {
            kind: section::META,
        })?;
    if meta_section.elem != 1 {
        return Err(FormatError::ElementSize {
            kind: section::META,
            found: meta_section.elem,
            expected: 1,
        });
    }
    let meta_bytes = &b[meta_section.offset..meta_section.offset + meta_section.len];
    if xxh3_64(meta_bytes) != meta_section.checksum {
        return Err(FormatError::SectionChecksum {
            index: meta_index,
            kind: section::META,
        });
    }
    let meta: KernelMeta =
        serde_json::from_slice(meta_bytes).map_err(|e| FormatError::Metadata(e.to_string()))?;
    Ok(meta)
}

/// The metadata's values: units mm, positive finite volumes and scale, well-formed SH and
/// orientation records.
fn check_meta(meta: &KernelMeta) -> Result<(), FormatError> {
    if meta.units != "mm" {
        return Err(FormatError::Units {
            found: meta.units.clone(),
        });
    }
    for (name, v) in [
        ("unit_volume_ml", meta.unit_volume_ml),
        ("start_volume_ml", meta.start_volume_ml),
        ("force_scale", meta.force_scale),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(FormatError::Metadata(format!(
                "{name} = {v:e} must be a finite positive number"
            )));
        }
    }
    if let Some(f) = &meta.fold_free {
        let (a, b, sa, sb) = (
            f.above_ml,
            f.below_ml,
            f.searched_above_ml,
            f.searched_below_ml,
        );
        if ![a, b, sa, sb].iter().all(|v| v.is_finite() && *v >= 0.0) || a > sa || b > sb {
            return Err(FormatError::Metadata(format!(
                "fold_free = +{a:e} / -{b:e} ml (searched +{sa:e} / -{sb:e}) must be finite, not \
                 negative, and within the spans searched"
            )));
        }
    }
    if let Some(sh) = &meta.sh {
        if sh.bands == 0 || sh.bands as usize > crate::sh::MAX_BANDS {
            return Err(FormatError::Metadata(format!(
                "sh.bands = {} (1 to {})",
                sh.bands,
                crate::sh::MAX_BANDS
            )));
        }
        let n2 = (sh.bands * sh.bands) as usize;
        if sh.projection.len() != 4 * n2 || !sh.projection.iter().all(|v| v.is_finite()) {
            return Err(FormatError::Metadata(format!(
                "sh.projection must hold 4 × {n2} finite numbers"
            )));
        }
        if !sh.alpha.is_finite() || !sh.volume_forms.is_finite() {
            return Err(FormatError::Metadata(
                "sh.alpha and sh.volume_forms must be finite".into(),
            ));
        }
    }
    if let Some(o) = &meta.orientation {
        if !o.volume_forms.is_finite() {
            return Err(FormatError::Metadata(
                "orientation.volume_forms must be finite".into(),
            ));
        }
    }
    Ok(())
}

/// The required sections present, and the shape of every known one against the metadata.
fn check_shapes(sections: &[Section], meta: &KernelMeta) -> Result<(), FormatError> {
    // Required sections, and the shape of every known one.
    let required = [
        section::POSITIONS,
        section::TRIANGLES,
        section::DIRECTIONS,
        section::APPLIED_FORCE,
        section::ELASTOSTATIC,
        section::UNIT_DISPLACEMENT,
        section::ROW_PTR,
        section::COLS,
        section::VALS,
    ];
    for kind in required {
        if !sections.iter().any(|s| s.kind == kind) {
            return Err(FormatError::MissingSection { kind });
        }
    }
    for (kind, present) in [
        (section::SH, meta.sh.is_some()),
        (section::BASIS, meta.orientation.is_some()),
    ] {
        if present && !sections.iter().any(|s| s.kind == kind) {
            return Err(FormatError::MissingSection { kind });
        }
    }
    for s in sections {
        if let Some((elem, n)) = expected_shape(s.kind, meta) {
            if s.elem != elem {
                return Err(FormatError::ElementSize {
                    kind: s.kind,
                    found: s.elem,
                    expected: elem,
                });
            }
            let got = s.len as u64 / elem as u64;
            if got != n {
                return Err(FormatError::ElementCount {
                    kind: s.kind,
                    found: got,
                    expected: n,
                });
            }
        }
    }
    Ok(())
}

/// One section's checksum and content (floats finite, indices in range, offsets monotone), given
/// a layout [`verify_layout`] accepted.
pub fn verify_section(
    b: &[u8],
    index: usize,
    s: &Section,
    meta: &KernelMeta,
) -> Result<(), FormatError> {
    let bytes = &b[s.offset..s.offset + s.len];
    if xxh3_64(bytes) != s.checksum {
        return Err(FormatError::SectionChecksum {
            index,
            kind: s.kind,
        });
    }
    let floats = |what: &'static str| -> Result<(), FormatError> {
        match bytes
            .chunks_exact(4)
            .position(|c| !f32::from_le_bytes(c.try_into().unwrap()).is_finite())
        {
            Some(i) => Err(FormatError::NonFinite { what, index: i }),
            None => Ok(()),
        }
    };
    let v = meta.vertices as usize;
    match s.kind {
        section::POSITIONS => {
            floats("positions")?;
            match bytes
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                .enumerate()
                .find(|(_, v)| v.abs() > MAX_COORDINATE_MM)
            {
                Some((index, value)) => Err(FormatError::PositionRange { index, value }),
                None => Ok(()),
            }
        }
        section::DIRECTIONS => floats("directions"),
        section::APPLIED_FORCE => floats("applied force"),
        section::ELASTOSTATIC => floats("elastostatic force"),
        section::UNIT_DISPLACEMENT => floats("unit displacement"),
        section::VALS => floats("transfer values"),
        section::SH => floats("spherical-harmonic transfer coefficients"),
        section::BASIS => floats("basis responses"),
        section::TRIANGLES => match bytes
            .chunks_exact(4)
            .position(|c| u32::from_le_bytes(c.try_into().unwrap()) as usize >= v)
        {
            Some(t) => Err(FormatError::TriangleIndex { triangle: t / 3 }),
            None => Ok(()),
        },
        section::COLS => {
            if bytes
                .chunks_exact(4)
                .any(|c| u32::from_le_bytes(c.try_into().unwrap()) as usize >= v)
            {
                Err(FormatError::ColumnIndex)
            } else {
                Ok(())
            }
        }
        section::LOBES => match bytes.iter().position(|&c| c > 5) {
            Some(vertex) => Err(FormatError::LobeCode {
                vertex,
                code: bytes[vertex],
            }),
            None => Ok(()),
        },
        section::ROW_PTR => {
            let mut last = 0u64;
            for (i, c) in bytes.chunks_exact(8).enumerate() {
                let p = u64::from_le_bytes(c.try_into().unwrap());
                if (i == 0 && p != 0) || p < last {
                    return Err(FormatError::RowOffsets { row: i });
                }
                last = p;
            }
            if last != meta.nnz {
                return Err(FormatError::RowEnd {
                    last,
                    nnz: meta.nnz,
                });
            }
            Ok(())
        }
        _ => Ok(()),
    }
}

impl KernelFile {
    /// Map `path` and verify every section.
    pub fn open(path: &Path) -> Result<Self, KernelError> {
        let f = Self::open_lazy(path)?;
        for i in 0..f.sections.len() {
            f.check(i)?;
        }
        Ok(f)
    }

    /// Map `path`, verify the layout, the metadata and [`CORE_SECTIONS`]; every other section is
    /// verified the first time it is read.
    pub fn open_lazy(path: &Path) -> Result<Self, KernelError> {
        let io = |source| KernelError::Io {
            path: path.to_path_buf(),
            source,
        };
        // The type first, from the path: opening a FIFO with no writer would block for ever.
        let meta = std::fs::metadata(path).map_err(io)?;
        if !meta.is_file() {
            // A device or pipe cannot be a kernel (and must not be mapped or read without bound).
            return Err(KernelError::Input(crate::input::InputError::NotRegular {
                path: path.to_path_buf(),
                kind: if meta.is_dir() {
                    "folder"
                } else {
                    "special file"
                },
            }));
        }
        let file = std::fs::File::open(path).map_err(io)?;
        let meta = file.metadata().map_err(io)?;
        if !meta.is_file() {
            // Replaced between the two looks.
            return Err(KernelError::Input(crate::input::InputError::NotRegular {
                path: path.to_path_buf(),
                kind: "special file",
            }));
        }
        let len = meta.len();
        let invalid = |source: FormatError| KernelError::Invalid {
            path: path.to_path_buf(),
            source,
        };
        if len < HEADER as u64 {
            return Err(invalid(FormatError::TooShort { len }));
        }
        // SAFETY: the mapping is read-only; lungdyn writes kernels atomically (new file + rename),
        // so a kernel is never modified in place while mapped.
        let map = unsafe { memmap2::Mmap::map(&file) }.map_err(io)?;
        let (meta, sections) = verify_layout(&map).map_err(invalid)?;
        let checked = sections
            .iter()
            .map(|_| std::sync::OnceLock::new())
            .collect();
        let f = Self {
            path: path.to_path_buf(),
            id: u64_at(&map, 40),
            map,
            meta,
            sections,
            checked,
            verified_bytes: std::sync::atomic::AtomicU64::new(0),
        };
        for kind in CORE_SECTIONS {
            f.section(kind)?;
        }
        Ok(f)
    }

    /// Verify section `index` once; later calls return the first answer.
    fn check(&self, index: usize) -> Result<(), KernelError> {
        self.checked[index]
            .get_or_init(|| {
                let s = &self.sections[index];
                self.verified_bytes
                    .fetch_add(s.len as u64, std::sync::atomic::Ordering::Relaxed);
                verify_section(&self.map, index, s, &self.meta)
            })
            .clone()
            .map_err(|source| KernelError::Invalid {
                path: self.path.clone(),
                source,
            })
    }

    /// The bytes of section `kind`, verified.
    fn section(&self, kind: u32) -> Result<&[u8], KernelError> {
        let index = self
            .sections
            .iter()
            .position(|s| s.kind == kind)
            .ok_or_else(|| KernelError::Invalid {
                path: self.path.clone(),
                source: FormatError::MissingSection { kind },
            })?;
        self.check(index)?;
        let s = &self.sections[index];
        Ok(&self.map[s.offset..s.offset + s.len])
    }

    fn slice<T: bytemuck::AnyBitPattern>(&self, kind: u32) -> Result<&[T], KernelError> {
        // Sections are 64-byte aligned within a page-aligned mapping.
        Ok(bytemuck::cast_slice(self.section(kind)?))
    }

    fn core<T: bytemuck::AnyBitPattern>(&self, kind: u32) -> &[T] {
        self.slice(kind)
            .expect("core sections are verified when the kernel is opened")
    }

    /// Section bytes checksummed and checked so far (a precomputed-mode run stays at the core
    /// sections' size).
    pub fn bytes_verified(&self) -> u64 {
        self.verified_bytes
            .load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Whether the section of `kind` has been verified (read) yet.
    pub fn is_verified(&self, kind: u32) -> bool {
        self.sections
            .iter()
            .position(|s| s.kind == kind)
            .is_some_and(|i| self.checked[i].get().is_some())
    }

    /// The section table.
    pub fn sections(&self) -> &[Section] {
        &self.sections
    }

    /// The kernel's identity: the header checksum, which covers the section table and through it
    /// every section's checksum, so two files share an id only when their content is identical.
    /// Travels as `ipc_types::LungFrame::kernel_id`.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// The file this kernel was mapped from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Metadata.
    pub fn meta(&self) -> &KernelMeta {
        &self.meta
    }

    /// File size in bytes.
    pub fn len_bytes(&self) -> usize {
        self.map.len()
    }

    /// Positions, mm.
    pub fn positions(&self) -> &[[f32; 3]] {
        self.core(section::POSITIONS)
    }
    /// Triangles.
    pub fn triangles(&self) -> &[[u32; 3]] {
        self.core(section::TRIANGLES)
    }
    /// Unit directions.
    pub fn directions(&self) -> &[[f32; 3]] {
        self.core(section::DIRECTIONS)
    }
    /// Unit displacement.
    pub fn unit_displacement(&self) -> &[[f32; 3]] {
        self.core(section::UNIT_DISPLACEMENT)
    }
    /// Applied force (eq. 6.18), verified on first use.
    pub fn applied_force(&self) -> Result<&[f32], KernelError> {
        self.slice(section::APPLIED_FORCE)
    }
    /// Elastostatic force, verified on first use.
    pub fn elastostatic(&self) -> Result<&[f32], KernelError> {
        self.slice(section::ELASTOSTATIC)
    }
    /// CSR row offsets, verified on first use.
    pub fn row_ptr(&self) -> Result<&[u64], KernelError> {
        self.slice(section::ROW_PTR)
    }
    /// CSR columns, verified on first use.
    pub fn cols(&self) -> Result<&[u32], KernelError> {
        self.slice(section::COLS)
    }
    /// CSR values, verified on first use.
    pub fn vals(&self) -> Result<&[f32], KernelError> {
        self.slice(section::VALS)
    }
    /// Spherical-harmonic transfer coefficients `T^I_lm` (`bands²` per vertex, row-major), if the
    /// kernel has them; verified on first use.
    pub fn sh_coefficients(&self) -> Result<Option<&[f32]>, KernelError> {
        if self.meta.sh.is_none() {
            return Ok(None);
        }
        self.slice(section::SH).map(Some)
    }
    /// Basis responses `(G_0, G_x, G_y, G_z)` per vertex (EQUATIONS.md §3.3), if the kernel has them;
    /// verified on first use.
    pub fn basis_responses(&self) -> Result<Option<&[[f32; 4]]>, KernelError> {
        if self.meta.orientation.is_none() {
            return Ok(None);
        }
        self.slice(section::BASIS).map(Some)
    }

    /// Lobe code per vertex ([`crate::mesh::lobes::Lobe`]), if the kernel has the section (kernels
    /// baked before it existed do not); verified on first use.
    pub fn lobes(&self) -> Result<Option<&[u8]>, KernelError> {
        if !self.sections.iter().any(|s| s.kind == section::LOBES) {
            return Ok(None);
        }
        self.slice(section::LOBES).map(Some)
    }

    /// The mesh (copied out of the mapping).
    pub fn mesh(&self) -> TriMesh {
        TriMesh {
            positions: self.positions().to_vec(),
            triangles: self.triangles().to_vec(),
        }
    }

    /// The run-time deformation model of this lung (carrying this kernel's [`Self::id`]).
    pub fn lung_model(&self) -> LungModel {
        let mut m = LungModel::from_unit_displacement(
            self.meta.side,
            self.mesh(),
            self.unit_displacement().to_vec(),
        );
        m.kernel_id = self.id;
        m
    }

    /// The transfer rows (copied out of the mapping), verified on first use.
    pub fn transfer(&self) -> Result<Transfer, KernelError> {
        Ok(Transfer {
            n: self.meta.vertices as usize,
            row_ptr: self.row_ptr()?.to_vec(),
            cols: self.cols()?.to_vec(),
            vals: self.vals()?.to_vec(),
            stats: self.meta.transfer,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fold-free range holds its boundaries (a lung exactly at either end is within it) and
    /// nothing past them, a non-finite change included; its words say which side was searched out.
    #[test]
    fn a_fold_free_range_holds_its_boundaries_and_nothing_past_them() {
        let r = FoldFreeMeta {
            above_ml: 300.0,
            below_ml: 20.0,
            searched_above_ml: 1000.0,
            searched_below_ml: 20.0,
        };
        for (delta, inside) in [
            (0.0, true),
            (300.0, true),
            (300.001, false),
            (-20.0, true),
            (-20.001, false),
            (f64::NAN, false),
            (f64::INFINITY, false),
        ] {
            assert_eq!(r.contains(delta), inside, "{delta}");
        }
        assert_eq!(
            r.describe(),
            "folds past +300 ml; no fold to -20 ml (as far as checked)"
        );
        assert!(FoldFreeMeta::words(None).starts_with("not measured"));
    }

    /// A kernel whose recorded fold-free range is not a range (non-finite, negative, past the span
    /// searched) is refused naming it; a sound one, and none, are read.
    #[test]
    fn a_kernel_with_a_broken_fold_free_range_is_refused() {
        let path = std::env::temp_dir().join(format!("lungdyn-ff-{}.kernel", std::process::id()));
        tetra_kernel(&path, 1.0);
        let mut meta = KernelFile::open(&path).unwrap().meta().clone();
        let _ = std::fs::remove_file(&path);
        assert!(check_meta(&meta).is_ok());
        let good = FoldFreeMeta {
            above_ml: 10.0,
            below_ml: 2.0,
            searched_above_ml: 10.0,
            searched_below_ml: 5.0,
        };
        meta.fold_free = Some(good);
        assert!(check_meta(&meta).is_ok());
        for bad in [
            FoldFreeMeta {
                above_ml: f64::NAN,
                ..good
            },
            FoldFreeMeta {
                below_ml: -1.0,
                ..good
            },
            FoldFreeMeta {
                searched_below_ml: f64::INFINITY,
                ..good
            },
            FoldFreeMeta {
                above_ml: 11.0,
                ..good
            },
            FoldFreeMeta {
                below_ml: 6.0,
                ..good
            },
        ] {
            meta.fold_free = Some(bad);
            let e = check_meta(&meta).unwrap_err().to_string();
            assert!(e.contains("fold_free"), "{e}");
        }
    }

    /// The smallest valid kernel: a tetrahedron whose transfer rows keep all force at home.
    fn tetra_kernel(path: &Path, scale: f32) -> u64 {
        let positions: Vec<[f32; 3]> = vec![
            [0.0; 3],
            [100.0 * scale, 0.0, 0.0],
            [0.0, 100.0 * scale, 0.0],
            [0.0, 0.0, 100.0 * scale],
        ];
        let triangles: Vec<[u32; 3]> = vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        let dirs: Vec<[f32; 3]> = vec![[0.0, 0.0, 1.0]; 4];
        let force = vec![1.0f32; 4];
        let unit: Vec<[f32; 3]> = vec![[0.0, 0.0, 0.1]; 4];
        let row_ptr: Vec<u64> = vec![0, 1, 2, 3, 4];
        let cols: Vec<u32> = vec![0, 1, 2, 3];
        let vals = vec![1.0f32; 4];
        let mesh = TriMesh {
            positions: positions.clone(),
            triangles: triangles.clone(),
        };
        let meta = KernelMeta {
            side: Side::Left,
            units: "mm".into(),
            vertices: 4,
            triangles: 4,
            spring_nodes: 6,
            nnz: 4,
            mesh_hash: format!("{:016x}", mesh_hash(&mesh)),
            settings: BakeSettings::default_for(Side::Left),
            transfer: TransferStats::default(),
            unit_volume_ml: 1.5,
            force_scale: 1.0,
            start_volume_ml: mesh.enclosed_volume_ml(),
            written_by: "test".into(),
            orientation: None,
            sh: None,
            tumour: None,
            fold_free: None,
        };
        write_file(
            path,
            &meta,
            &[
                (section::POSITIONS, 12, bytemuck::cast_slice(&positions)),
                (section::TRIANGLES, 12, bytemuck::cast_slice(&triangles)),
                (section::DIRECTIONS, 12, bytemuck::cast_slice(&dirs)),
                (section::APPLIED_FORCE, 4, bytemuck::cast_slice(&force)),
                (section::ELASTOSTATIC, 4, bytemuck::cast_slice(&force)),
                (section::UNIT_DISPLACEMENT, 12, bytemuck::cast_slice(&unit)),
                (section::ROW_PTR, 8, bytemuck::cast_slice(&row_ptr)),
                (section::COLS, 4, bytemuck::cast_slice(&cols)),
                (section::VALS, 4, bytemuck::cast_slice(&vals)),
            ],
        )
        .unwrap()
    }

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lungdyn-kernel-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn a_written_kernel_maps_back_with_every_section() {
        let path = tmp("tetra.kernel");
        let len = tetra_kernel(&path, 1.0);
        let f = KernelFile::open(&path).unwrap();
        assert_eq!(f.len_bytes() as u64, len);
        assert_eq!(len % ALIGN, 0);
        assert_eq!(f.positions()[1], [100.0, 0.0, 0.0]);
        assert_eq!(f.triangles().len(), 4);
        assert_eq!(f.row_ptr().unwrap(), &[0, 1, 2, 3, 4]);
        assert_eq!(f.transfer().unwrap().row(2), (&[2u32][..], &[1.0f32][..]));
        let m = f.lung_model();
        assert_eq!(m.side, Side::Left);
        assert!((m.start_volume_ml - 1e6 / 6.0 / 1000.0).abs() < 1e-9);
    }

    #[test]
    fn a_lazy_open_checks_only_the_core_until_more_is_read() {
        let path = tmp("lazy.kernel");
        tetra_kernel(&path, 1.0);
        let f = KernelFile::open_lazy(&path).unwrap();
        let core: u64 = f
            .sections()
            .iter()
            .filter(|s| CORE_SECTIONS.contains(&s.kind))
            .map(|s| s.len as u64)
            .sum();
        assert_eq!(f.bytes_verified(), core);
        assert!(!f.is_verified(section::VALS) && !f.is_verified(section::COLS));
        f.transfer().unwrap();
        assert!(f.is_verified(section::VALS));
        assert!(f.bytes_verified() > core);
        // A corrupted transfer section: a lazy open still works (a precomputed run never reads
        // it), reading it is refused, a full open is refused.
        let mut bytes = std::fs::read(&path).unwrap();
        let vals = f
            .sections()
            .iter()
            .find(|s| s.kind == section::VALS)
            .unwrap();
        bytes[vals.offset] ^= 0x40;
        let bad = tmp("lazy-bad.kernel");
        std::fs::write(&bad, &bytes).unwrap();
        let lazy = KernelFile::open_lazy(&bad).unwrap();
        assert_eq!(
            lazy.id(),
            f.id(),
            "the id is the header's: same table, same id"
        );
        let e = lazy.vals().unwrap_err().to_string();
        assert!(e.contains("checksum") && e.contains("lazy-bad"), "{e}");
        assert!(KernelFile::open(&bad).is_err());
        // Core corruption is refused at once.
        let pos = f
            .sections()
            .iter()
            .find(|s| s.kind == section::POSITIONS)
            .unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[pos.offset] ^= 0x40;
        std::fs::write(&bad, &bytes).unwrap();
        assert!(KernelFile::open_lazy(&bad).is_err());
    }

    #[test]
    fn a_fifo_is_refused_without_blocking() {
        let p = tmp("fifo.kernel");
        let _ = std::fs::remove_file(&p);
        let status = std::process::Command::new("mkfifo").arg(&p).status();
        if !status.map(|s| s.success()).unwrap_or(false) {
            return; // no mkfifo on this system: nothing to test
        }
        let e = KernelFile::open(&p).unwrap_err();
        assert!(matches!(e, KernelError::Input(_)), "{e:?}");
    }

    #[test]
    fn the_kernel_id_follows_the_content() {
        let (a, b, c) = (tmp("id-a.kernel"), tmp("id-b.kernel"), tmp("id-c.kernel"));
        tetra_kernel(&a, 1.0);
        tetra_kernel(&b, 1.0);
        tetra_kernel(&c, 1.5);
        let (a, b, c) = (
            KernelFile::open(&a).unwrap(),
            KernelFile::open(&b).unwrap(),
            KernelFile::open(&c).unwrap(),
        );
        assert_eq!(a.id(), b.id(), "same content, same id");
        assert_ne!(a.id(), c.id(), "other mesh, other id");
        assert_ne!(a.id(), 0);
    }

    #[test]
    fn truncated_foreign_and_corrupted_files_are_refused() {
        let path = tmp("good.kernel");
        tetra_kernel(&path, 1.0);
        let good = std::fs::read(&path).unwrap();
        assert!(verify_bytes(&good).is_ok());
        let flip = |at: usize| {
            let mut b = good.clone();
            b[at] ^= 0x10;
            b
        };
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            ("empty", vec![], "empty"),
            ("short", good[..40].to_vec(), "truncated"),
            ("truncated", good[..good.len() - 64].to_vec(), "truncated"),
            (
                "foreign",
                b"solid lung\nfacet normal 0 0 1\n".repeat(4),
                "magic",
            ),
            ("bit flip in values", flip(good.len() - 64 + 2), "checksum"),
            ("bit flip in header", flip(24), "checksum"),
            (
                "version",
                {
                    let mut b = good.clone();
                    b[8] = 9;
                    b
                },
                "version",
            ),
        ];
        for (name, bytes, needle) in cases {
            let err = verify_bytes(&bytes).expect_err(name).to_string();
            assert!(err.contains(needle), "{name}: {err}");
            let p = tmp(&format!("{}.kernel", name.replace(' ', "_")));
            std::fs::write(&p, &bytes).unwrap();
            let e = KernelFile::open(&p).unwrap_err();
            assert!(matches!(e, KernelError::Invalid { .. }), "{name}: {e:?}");
            let e = e.to_string();
            assert!(e.contains(p.file_name().unwrap().to_str().unwrap()), "{e}");
        }
        assert!(matches!(
            KernelFile::open(&tmp("does-not-exist.kernel")),
            Err(KernelError::Io { .. })
        ));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(256))]
        #[test]
        fn the_reader_never_panics_on_arbitrary_bytes(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..512)) {
            let _ = verify_bytes(&bytes);
        }

        #[test]
        fn the_reader_never_panics_on_mutated_kernels(at in 0usize..4096, val in proptest::prelude::any::<u8>(), cut in 0usize..4096) {
            let mut b = GOOD.with(|g| g.clone());
            let at = at % b.len();
            b[at] = val;
            b.truncate(b.len() - cut.min(b.len()));
            let _ = verify_bytes(&b);
        }

        #[test]
        fn the_reader_never_panics_on_mutated_resealed_kernels(at in 0usize..1_000_000, val in proptest::prelude::any::<u8>()) {
            // Mutate, then recompute every checksum so the content checks (not the checksums) are hit.
            let mut b = GOOD.with(|g| g.clone());
            let at = at % b.len();
            b[at] = val;
            reseal(&mut b);
            let _ = verify_bytes(&b);
        }
    }

    /// Recompute section, table and header checksums where the table can be read.
    fn reseal(b: &mut [u8]) {
        let count = (u32_at(b, 16) as usize).min(MAX_SECTIONS);
        let table_end = HEADER + ENTRY * count;
        if table_end > b.len() {
            return;
        }
        for s in 0..count {
            let e = HEADER + s * ENTRY;
            let (offset, len) = (u64_at(b, e + 8) as usize, u64_at(b, e + 16) as usize);
            if let Some(end) = offset.checked_add(len).filter(|&end| end <= b.len()) {
                let sum = xxh3_64(&b[offset..end]);
                b[e + 24..e + 32].copy_from_slice(&sum.to_le_bytes());
            }
        }
        let t = xxh3_64(&b[HEADER..table_end]);
        b[32..40].copy_from_slice(&t.to_le_bytes());
        let h = xxh3_64(&b[0..40]);
        b[40..48].copy_from_slice(&h.to_le_bytes());
    }

    thread_local! {
        static GOOD: Vec<u8> = {
            let p = tmp(&format!("fuzz-{:?}.kernel", std::thread::current().id()));
            tetra_kernel(&p, 1.0);
            std::fs::read(p).unwrap()
        };
    }
}
