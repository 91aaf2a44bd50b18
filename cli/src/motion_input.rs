//! What `lungdyn fit-motion` reads: its arguments, the frame its files are in, and meshes
//! imported into the body frame — shared by its modes (landmarks, surfaces, a breath-hold pair:
//! [`crate::motion_cmd`], [`crate::pair_cmd`]) one way.

use std::path::{Path, PathBuf};

use lung_bake::landmarks::{Frame, VoxelAxes};
use lung_bake::motion_models::ModelKind;
use lung_model::mesh::Side;

/// Options of `lungdyn fit-motion`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "Point files: one `x y z` per line (spaces, tabs or commas; CRLF, blank lines and \
lines starting with # are skipped), the same points in the same order in every file. State the frame: \
--frame body (mm; +X patient left, +Y anterior, +Z superior; the default), lps (DICOM/ITK mm), ras \
(3D Slicer mm), or voxel (indices, with --spacing, --voxel-axes and --index-base). --format dirlab \
reads DIR-Lab landmark files: voxel indices, 1-based, axes R>L,A>P,S>I (slice 1 at the head). A mesh \
(.obj, .ply, .stl) stands for its vertices; two meshes of one lung must share their vertex order. \
Sets covering both lungs are split at the mid-sagittal gap (the lung at larger X is the left one); with \
--lung the set is that one lung and is never split. Coordinates that are all whole numbers >= 0 look like \
voxel indices and need a stated frame.\n\n\
Landmarks: every model (the seed's power law, an affine field, a polynomial, a thin-plate spline \
'rbf') is fitted and cross-validated: in-sample and k-fold held-out errors are printed beside the \
no-motion baseline and the best by held-out error is chosen (--model picks one). The frame is checked \
against what breathing does (the base moves most, downwards on inspiration) and a disagreement is \
said loudly.\n\nExample (DIR-Lab case 1): lungdyn fit-motion --format dirlab --spacing 0.97,0.97,2.5 \
--from Case1_300_T50_xyz.txt --to Case1_300_T00_xyz.txt --out motion.toml --plot fit.png\n\n\
A breath-hold pair (--exhale, --inhale: one patient's exhale and inhale lung masks or surfaces, not \
registered): each lung's inhale surface is aligned by one translation (apex on apex, then the apical \
cap, the top quarter, onto the exhale surface: the apex moves least in breathing), then the applied \
force (a polynomial, --force-degree; the seed's is degree 1) and the directions (a polynomial field, \
--field-degree) are fitted through the bake's own operator so the exhale lung driven to the inhale \
volume lands on the inhale surface. The error printed is that of the kernel `bake --motion` makes \
from the written file, driven to the inhale volume, beside no motion, uniform scaling and a \
cross-validated figure (each part of the surface fitted without itself).\n\n\
Example: lungdyn fit-motion --exhale case_05_exp_mask.nii.gz --inhale case_05_insp_mask.nii.gz \
--axes LPS --lung right --out motion.toml --surfaces-out fit/  then  lungdyn bake --mesh fit/right_exhale.ply \
--frame body --lung right --motion motion.toml --out right.kernel"
)]
pub struct FitMotionArgs {
    /// Points (or mesh) at the reference phase: end-exhalation (FRC).
    #[arg(long, required_unless_present = "exhale", conflicts_with_all = ["exhale", "inhale"])]
    pub from: Option<PathBuf>,
    /// The same points at the phase to fit (e.g. end-inhalation).
    #[arg(long, required_unless_present = "inhale")]
    pub to: Option<PathBuf>,
    /// A breath-hold pair's exhale lung: a lung mask (NIfTI, NRRD, MetaImage, read as `mesh
    /// from-mask` reads it) or a closed surface (.ply, .obj, .stl). With --inhale: the patient's own
    /// motion on the operator (force and direction fields), see below.
    #[arg(long, requires = "inhale", value_name = "MASK|SURFACE")]
    pub exhale: Option<PathBuf>,
    /// The same patient's inhale lung (mask or surface; not registered to the exhale one).
    #[arg(long, requires = "exhale", value_name = "MASK|SURFACE")]
    pub inhale: Option<PathBuf>,
    /// With --exhale/--inhale masks: the voxel axes of the exhale image, replacing its header's (see
    /// `mesh from-mask --help`); also the inhale image's unless --inhale-axes is given.
    #[arg(long, value_name = "XYZ")]
    pub axes: Option<String>,
    /// With --inhale a mask: its voxel axes.
    #[arg(long, value_name = "XYZ")]
    pub inhale_axes: Option<String>,
    /// With --exhale a mask: vertices of the exhale surface the motion is fitted on (bake that
    /// surface: `--surfaces-out` writes it), about.
    #[arg(long, default_value_t = 20_000)]
    pub vertices: usize,
    /// With --exhale/--inhale: total degree of the applied force polynomial (1 is the seed's
    /// linear force), 1-5.
    #[arg(long, default_value_t = 3)]
    pub force_degree: u8,
    /// With --exhale/--inhale: total degree of the direction field polynomial, 1-5 (higher
    /// degrees fit closer in-sample but slide and fold the surface: docs/masks/patient_motion.md).
    #[arg(long, default_value_t = 2)]
    pub field_degree: u8,
    /// With --exhale/--inhale: local terms of the applied force, this many centres on the exhale
    /// surface (8-1000), each reaching 2.5 times their spacing, added to the polynomial where it
    /// cannot follow the breath, held stiff in the first rounds (docs/masks/patient_motion.md);
    /// 0 for the polynomial alone (what the breath-hold population averages).
    #[arg(long, default_value_t = 256)]
    pub force_centres: usize,
    /// With --exhale/--inhale: ridge weight of the local terms (above 0; larger is smoother),
    /// relative to their own normal equations.
    #[arg(long, default_value_t = 0.01)]
    pub force_local_ridge: f64,
    /// With --exhale/--inhale: keep a correspondence only where the surfaces' normals lie within
    /// this many degrees; 180 keeps every one (docs/masks/patient_motion.md).
    #[arg(long, value_name = "DEG", default_value_t = lung_bake::patient_motion::NORMAL_GATE_DEG)]
    pub normal_gate: f64,
    /// With --exhale/--inhale: rounds of the symmetric ICP.
    #[arg(long, default_value_t = 50)]
    pub iterations: usize,
    /// With --exhale/--inhale: write FOLDER/LUNG_exhale.ply (the surface fitted on, to bake),
    /// LUNG_moved.ply (it driven to the inhale volume by the fitted kernel) and
    /// LUNG_inhale_aligned.ply (the target): for an independent check.
    #[arg(long, value_name = "FOLDER")]
    pub surfaces_out: Option<PathBuf>,
    /// Further phases predicted from the fitted field with one scale each (comma-separated files).
    #[arg(long, value_delimiter = ',')]
    pub also: Vec<PathBuf>,
    /// Coordinate frame of the files: body, lps, ras or voxel.
    #[arg(long, value_enum)]
    pub frame: Option<FrameName>,
    /// File format preset: `dirlab` = voxel indices, 1-based, axes R>L,A>P,S>I (needs --spacing).
    #[arg(long, value_enum, default_value_t = PointFormat::Plain)]
    pub format: PointFormat,
    /// Voxel size in mm along the file's three index axes (sx,sy,sz), each 0.1–20: with --frame voxel
    /// or --format dirlab (landmark files only; meshes are in mm).
    #[arg(long, value_delimiter = ',')]
    pub spacing: Vec<f64>,
    /// How the voxel indices run, e.g. R>L,A>P,S>I (the index grows from the first letter to the second).
    #[arg(long)]
    pub voxel_axes: Option<String>,
    /// First voxel index: 0 or 1.
    #[arg(long, value_parser = clap::value_parser!(u8).range(0..=1))]
    pub index_base: Option<u8>,
    /// The points (or meshes) are this one lung: never split at a gap; a warning when their motion
    /// (points) or shape (meshes) says the other lung, a refusal when they clearly hold both lungs:
    /// left or right.
    #[arg(long)]
    pub lung: Option<Side>,
    /// Landmark model: power (the seed's eq. 6.14-6.16), affine, poly, rbf (thin-plate spline), or
    /// auto (fit all, choose the lowest cross-validated error).
    #[arg(long, value_enum, default_value_t = ModelChoice::Auto)]
    pub model: ModelChoice,
    /// Folds of the cross-validation (held-out errors), 2..=20 (with --exhale/--inhale 2..=10).
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u64).range(2..=20))]
    pub folds: u64,
    /// Seed of the fold assignment (the same seed gives the same folds and numbers).
    #[arg(long, default_value_t = 10)]
    pub seed: u64,
    /// Treat two meshes as surfaces without vertex correspondence (automatic when their vertex
    /// counts differ): the model is fitted so the moved reference lies on the target surface.
    #[arg(long)]
    pub surface: bool,
    /// Scene whose [lungs] elasticity, transfer_tolerance and amplitude_smoothing_mm the force fit uses
    /// (mesh input).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Write the constants and the chosen field (TOML, for `lungdyn bake --motion` or a scene's
    /// [lungs] motion).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Draw each model's held-out error per landmark (three views) and their histograms (PNG).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

impl FitMotionArgs {
    /// `--from` (required unless --exhale, which takes another path through `run`).
    pub fn from_path(&self) -> &Path {
        self.from.as_deref().unwrap_or(Path::new(""))
    }

    /// `--to`.
    pub fn to_path(&self) -> &Path {
        self.to.as_deref().unwrap_or(Path::new(""))
    }
}

/// `--frame`: the frame the files state (voxel details come from --spacing, --voxel-axes,
/// --index-base or --format dirlab).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FrameName {
    /// lungdyn's body frame, mm.
    Body,
    /// DICOM/ITK, mm.
    Lps,
    /// 3D Slicer, mm.
    Ras,
    /// Voxel indices.
    Voxel,
}

/// `--format`: how a landmark file is laid out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PointFormat {
    /// `x y z` per line in the stated frame.
    Plain,
    /// DIR-Lab: voxel indices, 1-based, axes R>L,A>P,S>I.
    Dirlab,
}

/// `--model`: one landmark model (the seed's power law is always fitted beside it, as the
/// baseline), or all of them with the lowest cross-validated error chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelChoice {
    /// The seed's power law (eq. 6.14–6.16).
    Power,
    /// An affine field.
    Affine,
    /// A polynomial (degree and ridge by inner CV).
    Poly,
    /// A thin-plate spline.
    Rbf,
    /// Every model; the lowest held-out error is chosen.
    Auto,
}

impl ModelChoice {
    /// The models fitted, in report order; the one asked for (not `auto`) is last.
    pub fn kinds(self) -> Vec<ModelKind> {
        let asked = match self {
            ModelChoice::Auto => return ModelKind::ALL.to_vec(),
            ModelChoice::Power => return vec![ModelKind::Power],
            ModelChoice::Affine => ModelKind::Affine,
            ModelChoice::Poly => ModelKind::Poly,
            ModelChoice::Rbf => ModelKind::Tps,
        };
        vec![ModelKind::Power, asked]
    }
}

/// Plausible CT voxel sizes, mm: clinical CT has 0.3–1 mm pixels and 0.5–5 mm slices (4DCT often
/// 2.5–3 mm); the range is that widened to 0.1–20 mm. A spacing outside it is a typo or a unit
/// mistake (metres, or a count), and it would only turn into a lung of an impossible size later.
pub const VOXEL_SPACING_MM: (f64, f64) = (0.1, 20.0);

/// The frame the options state.
pub fn frame_of(args: &FitMotionArgs) -> anyhow::Result<Frame> {
    let spacing = match args.spacing.as_slice() {
        [] => None,
        [x, y, z] => {
            let (lo, hi) = VOXEL_SPACING_MM;
            if ![x, y, z]
                .iter()
                .all(|v| v.is_finite() && (lo..=hi).contains(*v))
            {
                let c = lung_model::plausible::compact;
                anyhow::bail!(
                    "--spacing {},{},{}: each must be a CT voxel size in mm within {lo}–{hi} (clinical CT \
                     has 0.3–1 mm pixels and 0.5–5 mm slices; DIR-Lab case 1 is 0.97,0.97,2.5)",
                    c(*x),
                    c(*y),
                    c(*z)
                );
            }
            Some([*x, *y, *z])
        }
        _ => anyhow::bail!("--spacing needs three numbers sx,sy,sz"),
    };
    let dirlab = args.format == PointFormat::Dirlab;
    let frame = args
        .frame
        .unwrap_or(if dirlab || args.voxel_axes.is_some() {
            FrameName::Voxel
        } else {
            FrameName::Body
        });
    if dirlab && frame != FrameName::Voxel {
        let name = clap::ValueEnum::to_possible_value(&frame).expect("every frame has a name");
        anyhow::bail!(
            "--format dirlab files hold voxel indices: drop --frame {}",
            name.get_name()
        );
    }
    let mm = |f: Frame| {
        if spacing.is_some() || args.voxel_axes.is_some() || args.index_base.is_some() {
            anyhow::bail!(
                "--spacing, --voxel-axes and --index-base describe voxel indices: add --frame voxel \
                 (or --format dirlab), or drop them for coordinates in mm"
            );
        }
        Ok(f)
    };
    match frame {
        FrameName::Voxel => {
            let spacing = spacing.ok_or_else(|| {
                anyhow::anyhow!(
                    "voxel indices need --spacing sx,sy,sz (mm per voxel along the file's three axes; \
                     for DIR-Lab see the case's image header, e.g. 0.97,0.97,2.5 for case 1)"
                )
            })?;
            let axes = match (&args.voxel_axes, dirlab) {
                (Some(a), _) => a.parse::<VoxelAxes>().map_err(anyhow::Error::msg)?,
                (None, true) => VoxelAxes::DIRLAB,
                (None, false) => anyhow::bail!(
                    "--frame voxel needs --voxel-axes (how the indices run in the patient, e.g. R>L,A>P,S>I \
                     for axial DICOM order), or --format dirlab"
                ),
            };
            let base = match (args.index_base, dirlab) {
                (Some(b), _) => b,
                (None, true) => 1,
                (None, false) => anyhow::bail!(
                    "--frame voxel needs --index-base 0 or 1 (whether the first voxel is numbered 0 or 1)"
                ),
            };
            Ok(Frame::Voxel {
                axes,
                base,
                spacing,
            })
        }
        FrameName::Body => mm(Frame::Body),
        FrameName::Lps => mm(Frame::Lps),
        FrameName::Ras => mm(Frame::Ras),
    }
}

pub(crate) fn import_scaled(
    path: &Path,
    frame: &Frame,
    input: &crate::input_args::InputArgs,
) -> anyhow::Result<lung_model::mesh::TriMesh> {
    Ok(import_mesh_in(path, frame, input)?.mesh)
}

/// Import a mesh of one or both lungs given in `frame` (mm), converted to the body frame by the
/// importer (lung_model::frame) before its repairs and checks, wound outwards, as `mesh check
/// --frame` and `bake --frame` do. Voxel indices are refused: a mesh holds millimetres.
pub(crate) fn import_mesh_in(
    path: &Path,
    frame: &Frame,
    input: &crate::input_args::InputArgs,
) -> anyhow::Result<lung_bake::import::Imported> {
    use lung_bake::import::MeshFrame;
    let frame = match frame {
        Frame::Body => MeshFrame::Body,
        Frame::Lps => MeshFrame::Lps,
        Frame::Ras => MeshFrame::Ras,
        Frame::Voxel { .. } => anyhow::bail!(
            "{}: a mesh holds coordinates in mm, not voxel indices: use --frame body, lps or ras",
            path.display()
        ),
    };
    Ok(lung_bake::import::import_with(
        path,
        &lung_bake::import::ImportOptions {
            units: lung_bake::import::Units::Mm,
            limits: input.limits(lung_model::input::ReadLimits::MESH),
            shells: lung_bake::import::Shells::All,
            one_lung: false,
            frame,
        },
    )?)
}
