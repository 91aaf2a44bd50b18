//! `lungdyn mesh from-mask`: a patient's lung surface (and lobes) from a CT lung segmentation
//! (`lung_bake::mask`).

use std::path::Path;
use std::path::PathBuf;

use lung_bake::mask::{self, labels::Convention, volume::Axes, MaskOptions};
use lung_model::mesh::{io, lobes, Side};
use serde::Serialize;

/// Options of `lungdyn mesh from-mask`.
#[derive(Debug, Clone, clap::Args)]
#[command(after_help = "Examples:
  lungdyn mesh from-mask lungs.nii.gz --lung right --out right.ply
  lungdyn mesh from-mask seg.seg.nrrd --lung left --vertices 100000 --out left.ply --json
  lungdyn mesh from-mask lung_upper_lobe_left.nii.gz lung_lower_lobe_left.nii.gz --lung left --out left.ply

The surface is written in lungdyn's body frame (mm; +X patient left, +Y anterior, +Z superior),
taken from the image's own header; a PLY keeps each vertex's lobe (a `lobe` property) for
`lungdyn bake`, an OBJ carries the lobes as vertex colours to look at.")]
pub struct FromMaskArgs {
    /// The label image: NIfTI (.nii, .nii.gz), NRRD (.nrrd, 3D Slicer's .seg.nrrd) or MetaImage
    /// (.mha). Several files: one binary structure each, on one grid (TotalSegmentator's
    /// lung_upper_lobe_left.nii.gz ... ), named by their file names. DICOM SEG: convert it first.
    #[arg(required = true, value_name = "MASK")]
    pub masks: Vec<PathBuf>,
    /// Which lung.
    #[arg(long, value_parser = ["left", "right"])]
    pub lung: String,
    /// The label value(s) that are this lung or its lobes, comma-separated (e.g. 3, or 4,5,6).
    /// Found from the convention when omitted.
    #[arg(long, value_delimiter = ',', value_name = "N[,N...]")]
    pub label: Option<Vec<u16>>,
    /// The segmenter's label convention; detected from the values (and segment names) present when
    /// omitted: lungmask (1 right, 2 left), lungmask-lobes (LTRCLobes 1-5), totalsegmentator (v2
    /// 'total': 10-14 the lobes), totalsegmentator-v1 (13-17), cip (Chest Imaging Platform
    /// regions), names (segment or file names), single (one value for the lungs; the sides are
    /// separated geometrically, also where they touch).
    #[arg(long, value_parser = Convention::ALL.map(|c| c.name()))]
    pub convention: Option<String>,
    /// Vertices wanted, about (the surface's spacing is chosen for it; 100 to 4,000,000).
    #[arg(long, default_value_t = 20_000)]
    pub vertices: usize,
    /// The directions of the image's voxel axes (three letters, e.g. LPS, RAS, LAS), replacing
    /// the header's: for a file whose header has no anatomical frame, or whose frame contradicts
    /// the anatomy (then the error names the axes to pass). Spacing stays the header's.
    #[arg(long, value_name = "XYZ")]
    pub axes: Option<String>,
    /// Keep tunnels through the mask (vessels, airways) instead of closing them (the surface then
    /// has genus > 0, which `bake` refuses).
    #[arg(long)]
    pub keep_tunnels: bool,
    /// Gaussian smoothing of the mask before the surface is taken, σ in mm (default 0.75 × the
    /// largest voxel spacing: the staircase averaged out, the lung's shape kept).
    #[arg(long, value_name = "MM")]
    pub smooth: Option<f64>,
    /// Output file, .ply (keeps the lobes for `bake`) or .obj (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What `mesh from-mask` made; `mesh check`'s keys and the mask's.
#[derive(Debug, Serialize)]
pub struct FromMaskSummary {
    /// The mask file(s).
    pub path: String,
    /// Where the surface was written.
    pub out: String,
    /// Lung side.
    pub lung: String,
    /// Vertices.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
    /// Euler characteristic (2: closed, sphere-like).
    pub euler: i64,
    /// The surface's enclosed volume, ml.
    pub volume_ml: f64,
    /// Bounding box size, mm.
    pub size_mm: [f32; 3],
    /// Which lung the geometry looks like.
    pub geometry_side: Option<String>,
    /// Why.
    pub geometry_side_reason: String,
    /// The frame the image stated ("body" output).
    pub frame: mask::volume::FrameSource,
    /// What the geometry says about anterior/posterior and superior/inferior.
    pub orientation_reason: String,
    /// The lung's voxel volume as labelled, ml.
    pub mask_volume_ml: f64,
    /// After tunnels closed and cavities filled (the surface's target volume), ml.
    pub closed_mask_volume_ml: f64,
    /// The label values taken as this lung.
    pub labels_used: Vec<u16>,
    /// The label convention.
    pub convention: String,
    /// Why that convention.
    pub convention_reason: String,
    /// How this lung was told from the other.
    pub sides_from: String,
    /// Genus of the mask's boundary as it came (tunnels: vessels, airways).
    pub genus_before: i64,
    /// Genus of the surface.
    pub genus_after: i64,
    /// Radius of the closing that closed the tunnels, mm.
    pub closing_mm: f64,
    /// Cavities filled.
    pub cavities_filled: usize,
    /// Voxels in separate pieces, dropped.
    pub voxels_dropped: usize,
    /// Smoothing σ, mm.
    pub smoothing_mm: f64,
    /// Isosurface grid step, mm.
    pub grid_step_mm: f64,
    /// Distances from the vertices to the mask's staircase boundary.
    pub distance_to_mask: mask::Distances,
    /// Where the lobes came from: "labels" or "planes".
    pub lobes_from: String,
    /// Vertices and area per lobe.
    pub lobes: Vec<lobes::LobeSummary>,
    /// Things to look at.
    pub warnings: Vec<String>,
    /// Seconds per stage.
    pub seconds: Vec<(String, f64)>,
}

/// Read, make the surface, write it.
pub fn run(args: &FromMaskArgs) -> anyhow::Result<FromMaskSummary> {
    let side: Side = args.lung.parse().map_err(anyhow::Error::msg)?;
    io::check_out(&args.out)?;
    let mut opts = MaskOptions::new(side);
    opts.labels = args.label.clone();
    opts.convention = parsed(args.convention.as_deref())?;
    opts.vertices = args.vertices;
    opts.axes = axes("--axes", &args.axes)?;
    opts.keep_tunnels = args.keep_tunnels;
    opts.smoothing_mm = args.smooth;
    opts.limits = args.input.limits(mask::read::MASK_LIMITS);
    let made = mask::mesh_from_mask(&args.masks, &opts)?;
    io::write_mesh_with_lobes(&made.mesh, &made.lobes, &args.out)?;
    for w in &made.warnings {
        eprintln!("lungdyn: warning: {w}");
    }
    let side_seen = lung_bake::surface_checks::infer_side(&made.mesh);
    let topology = lung_model::mesh::check(&made.mesh)?;
    Ok(FromMaskSummary {
        path: args
            .masks
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(" "),
        out: args.out.display().to_string(),
        lung: side.name().to_string(),
        vertices: topology.vertices,
        triangles: topology.triangles,
        euler: topology.euler,
        volume_ml: made.mesh.enclosed_volume_ml(),
        size_mm: made.mesh.aabb().size(),
        geometry_side: side_seen.side.map(|s| s.name().to_string()),
        geometry_side_reason: made.side_reason.clone(),
        frame: made.frame.clone(),
        orientation_reason: made.orientation_reason.clone(),
        mask_volume_ml: made.mask_volume_ml,
        closed_mask_volume_ml: made.closed_volume_ml,
        labels_used: made.labels_used.clone(),
        convention: made.convention.name().to_string(),
        convention_reason: made.convention_reason.clone(),
        sides_from: made.sides_from.to_string(),
        genus_before: made.genus_before,
        genus_after: made.genus_after,
        closing_mm: made.closing_mm,
        cavities_filled: made.cavities_filled,
        voxels_dropped: made.voxels_dropped,
        smoothing_mm: made.smoothing_mm,
        grid_step_mm: made.grid_step_mm,
        distance_to_mask: made.distance_to_mask,
        lobes_from: made.lobes_from.to_string(),
        lobes: lobes::summarise(&made.mesh, &made.lobes),
        warnings: made.warnings.clone(),
        seconds: made
            .seconds
            .iter()
            .map(|(n, s)| (n.to_string(), *s))
            .collect(),
    })
}

/// The summary for a person.
pub fn text(s: &FromMaskSummary) -> String {
    let d = &s.distance_to_mask;
    let lobes: Vec<String> = s
        .lobes
        .iter()
        .map(|l| format!("{} {}", l.name, l.vertices))
        .collect();
    format!(
        "wrote {}: the {} lung from {}, {} vertices, {} triangles, closed 2-manifold, genus {} (mask: {}), {:.1} ml (mask {:.1} ml as labelled, {:.1} ml closed)\n\
         frame: {} {} ({}), voxel axes {}, spacing {:.3} x {:.3} x {:.3} mm; written in the body frame (+X left, +Y anterior, +Z superior)\n\
         labels: {:?} ({}: {}); sides from {}\n\
         surface: smoothing σ {:.2} mm, grid {:.2} mm, tunnels closed at {} mm, {} cavities filled; vertices to the mask's boundary mean {:.2} mm ({:.2} voxel), p95 {:.2} mm, max {:.2} mm\n\
         lobes from {}: {}\n\
         geometry: {}\n",
        s.out,
        s.lung,
        s.path,
        s.vertices,
        s.triangles,
        s.genus_after,
        if s.genus_before == 0 { "genus 0".to_string() } else { format!("{} tunnel(s)", s.genus_before) },
        s.volume_ml,
        s.mask_volume_ml,
        s.closed_mask_volume_ml,
        s.frame.format,
        s.frame.from,
        s.frame.world,
        s.frame.axes_override.clone().map_or(s.frame.voxel_axes.clone(), |a| format!("{a} (--axes; header {})", s.frame.voxel_axes)),
        s.frame.spacing_mm[0],
        s.frame.spacing_mm[1],
        s.frame.spacing_mm[2],
        s.labels_used,
        s.convention,
        s.convention_reason,
        s.sides_from,
        s.smoothing_mm,
        s.grid_step_mm,
        s.closing_mm,
        s.cavities_filled,
        d.mean_mm,
        d.mean_voxels,
        d.p95_mm,
        d.max_mm,
        s.lobes_from,
        lobes.join(", "),
        s.geometry_side_reason,
    )
}
/// Whether `path` looks like a label image `lungdyn patient` and `fit-motion --exhale/--inhale` read.
pub fn is_mask(path: &Path) -> bool {
    mask::read::Format::of(path).is_some()
}

/// An option's text parsed, its parser's message the error.
pub(crate) fn parsed<T: std::str::FromStr>(s: Option<&str>) -> anyhow::Result<Option<T>>
where
    T::Err: std::fmt::Display + std::fmt::Debug + Send + Sync + 'static,
{
    s.map(str::parse).transpose().map_err(anyhow::Error::msg)
}

/// `--axes`-style option `flag` parsed (also `fit-motion`'s and `patient`'s).
pub(crate) fn axes(flag: &str, s: &Option<String>) -> anyhow::Result<Option<Axes>> {
    s.as_deref()
        .map(str::parse::<Axes>)
        .transpose()
        .map_err(|e| anyhow::anyhow!("{flag}: {e}"))
}
