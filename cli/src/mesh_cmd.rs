//! `lungdyn mesh generate`: write a generated lung as OBJ or PLY.

use std::path::PathBuf;

use lung_model::mesh::{check, generate, io, lobes, Side};
use serde::Serialize;

/// Options of `lungdyn mesh generate`.
#[derive(Debug, Clone, clap::Args)]
pub struct GenerateArgs {
    /// Which lung.
    #[arg(long, value_parser = ["left", "right"])]
    pub lung: String,
    /// Vertices wanted (the generator gives the nearest 6n²+2 at or above; 100 to 4,000,000).
    #[arg(long, default_value_t = 20_000)]
    pub vertices: usize,
    /// Output file, .obj or .ply (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Print one JSON object describing the mesh on stdout.
    #[arg(long)]
    pub json: bool,
    /// Shape: "anatomical" (the built-in lungs the engine uses by default: hilum, cardiac notch and
    /// lingula, domed base, costophrenic recesses: `lung_model::mesh::anatomy`) or "teardrop" (the
    /// earlier smooth shape: `lung_model::mesh::teardrop`).
    #[arg(long, default_value = "anatomical", value_parser = ["anatomical", "teardrop"])]
    pub shape: String,
    /// Write each vertex's lobe colour (OBJ `v x y z r g b`; PLY `red green blue` and a `lobe`
    /// code property) to see the lobes in MeshLab or Blender.
    #[arg(long)]
    pub lobe_colours: bool,
}

/// What was written.
#[derive(Debug, Serialize)]
pub struct MeshSummary {
    /// Output path.
    pub path: String,
    /// Lung side.
    pub lung: String,
    /// Vertex count.
    pub vertices: usize,
    /// Triangle count.
    pub triangles: usize,
    /// Enclosed volume, ml.
    pub volume_ml: f64,
    /// Bounding box size (x, y, z), mm.
    pub size_mm: [f32; 3],
    /// Vertices and surface area per lobe (`lung_model::mesh::lobes`).
    pub lobes: Vec<lobes::LobeSummary>,
}

/// Generate, verify and write.
pub fn run(args: &GenerateArgs) -> anyhow::Result<MeshSummary> {
    let side: Side = args.lung.parse().map_err(anyhow::Error::msg)?;
    io::check_out(&args.out)?;
    let shape: generate::Shape = args.shape.parse().map_err(anyhow::Error::msg)?;
    let mesh = generate::lung_of(shape, side, args.vertices)?;
    check(&mesh)
        .map_err(|e| anyhow::anyhow!("internal error: the generated mesh is invalid: {e}"))?;
    let codes = lobes::classify(side, &mesh);
    if args.lobe_colours {
        io::write_mesh_with_lobes(&mesh, &codes, &args.out)?;
    } else {
        io::write_mesh(&mesh, &args.out)?;
    }
    Ok(MeshSummary {
        path: args.out.display().to_string(),
        lung: side.name().to_string(),
        vertices: mesh.positions.len(),
        triangles: mesh.triangles.len(),
        volume_ml: mesh.enclosed_volume_ml(),
        size_mm: mesh.aabb().size(),
        lobes: lobes::summarise(&mesh, &codes),
    })
}

/// `--frame` of a patient mesh file.
#[derive(Debug, Clone, clap::Args)]
pub struct FrameArgs {
    /// Coordinate frame of the mesh file (all in --units). "body" (the default when not given):
    /// lungdyn's own, +X patient left, +Y anterior, +Z superior — what `lungdyn mesh generate` and
    /// `mesh check --out` write. "lps": DICOM/ITK patient coordinates, +X left, +Y POSTERIOR, +Z
    /// superior — what ITK-SNAP, most DICOM segmentation/RT-structure converters and 3D Slicer's
    /// model export (default since Slicer 4.11) write. "ras": +X RIGHT, +Y anterior, +Z superior —
    /// 3D Slicer's internal frame, NIfTI world coordinates, FreeSurfer. An LPS mesh read as body has
    /// anterior and posterior swapped; the geometry is checked for that (the base's lowest point is
    /// posterior on a real lung; the apex is superior) and, when the frame was not given and the
    /// evidence is strong, the mesh is refused with the fix; with --frame given it is a warning.
    #[arg(long, value_parser = ["body", "lps", "ras"])]
    pub frame: Option<String>,
}

/// Options of `lungdyn mesh check`.
#[derive(Debug, Clone, clap::Args)]
pub struct CheckArgs {
    /// Mesh file: .obj, .ply or .stl (ASCII or binary).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Unit of the file's coordinates.
    #[arg(long, default_value = "mm", value_parser = ["mm", "cm", "m"])]
    pub units: String,
    /// Which lung the file should be: checked against the geometry (its concave medial surface faces
    /// the midline), with a warning when they disagree.
    #[arg(long, value_parser = ["left", "right"])]
    pub lung: Option<String>,
    /// Keep connected shell N (1 = the largest by volume) of a file holding several; without it a
    /// file of more than one shell is refused.
    #[arg(long, value_name = "N")]
    pub component: Option<usize>,
    /// Frame of the file's coordinates.
    #[command(flatten)]
    pub frame: FrameArgs,
    /// Write the welded, repaired mesh (in mm, body frame) as .obj or .ply.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Import a single-lung surface with the common options (`--units`, `--component`, `--frame`,
/// input limits), and compare the geometry's side with `lung` when given: returns the import, a
/// warning when they disagree, and a warning when anterior/posterior or superior/inferior look
/// flipped (both also printed on stderr). Refuses a mesh whose frame was not stated and whose
/// geometry strongly says it is flipped (`lung_bake::surface_checks` module doc, *Frame*).
pub fn import_lung(
    mesh: &std::path::Path,
    units: &str,
    component: Option<usize>,
    frame: &FrameArgs,
    input: &crate::input_args::InputArgs,
    lung: Option<Side>,
) -> anyhow::Result<(lung_bake::import::Imported, Option<String>, Option<String>)> {
    use lung_bake::import::{ImportOptions, MeshFrame, Shells};
    let units: lung_bake::import::Units = units.parse().map_err(anyhow::Error::msg)?;
    let stated: Option<MeshFrame> = crate::mask_cmd::parsed(frame.frame.as_deref())?;
    let imported = lung_bake::import::import_with(
        mesh,
        &ImportOptions {
            units,
            limits: input.limits(lung_model::input::ReadLimits::MESH),
            shells: component.map_or(Shells::One, Shells::Pick),
            one_lung: true,
            frame: stated.unwrap_or_default(),
        },
    )?;
    let frame_warning = match &imported.orientation {
        Some(o) if o.anterior_posterior_swapped || o.upside_down => {
            let name = stated.unwrap_or_default().name();
            if stated.is_none() && o.strong {
                anyhow::bail!(
                    "{}: read in the body frame (no --frame given), {}. State the file's frame: \
                     --frame lps for a DICOM/ITK export, --frame ras for 3D Slicer/NIfTI \
                     coordinates, or --frame body to keep it as it is (then this is only a warning)",
                    mesh.display(),
                    o.reason
                );
            }
            let fix = if o.anterior_posterior_swapped {
                ap_swap_fix(stated.unwrap_or_default())
            } else {
                ""
            };
            let w = format!(
                "{}: read with --frame {name}, {}{fix}",
                mesh.display(),
                o.reason
            );
            eprintln!("lungdyn: warning: {w}");
            Some(w)
        }
        _ => None,
    };
    let evidence = imported.side.as_ref();
    let warning = match (lung, evidence.and_then(|e| e.side)) {
        (Some(given), Some(seen)) if given != seen => {
            let e = evidence.expect("side seen");
            let w = format!(
                "{}: --lung {} but the geometry looks like a {} lung ({}; confidence {:.2}): check the file \
                 and its coordinate frame (+X = patient left)",
                mesh.display(),
                given.name(),
                seen.name(),
                e.reason,
                e.confidence
            );
            eprintln!("lungdyn: warning: {w}");
            Some(w)
        }
        _ => None,
    };
    Ok((imported, warning, frame_warning))
}

/// The fix for a mesh whose anterior and posterior look swapped after reading it in `frame`: the
/// frame whose +Y is the other way round (an LPS file read as body or RAS, or a body/RAS file read
/// as LPS).
fn ap_swap_fix(frame: lung_bake::import::MeshFrame) -> &'static str {
    use lung_bake::import::MeshFrame;
    match frame {
        MeshFrame::Body | MeshFrame::Ras => {
            ". If it is a DICOM/ITK export (+Y posterior), read it with --frame lps"
        }
        MeshFrame::Lps => {
            ". If its +Y is anterior, read it with --frame body (or --frame ras when its +X is the \
             patient's right)"
        }
    }
}

/// What `mesh check` found.
#[derive(Debug, Serialize)]
pub struct CheckSummary {
    /// Input path.
    pub path: String,
    /// Vertices after welding.
    pub vertices: usize,
    /// Triangles after repairs.
    pub triangles: usize,
    /// Euler characteristic (2: closed sphere-like surface).
    pub euler: i64,
    /// Enclosed volume, ml.
    pub volume_ml: f64,
    /// Bounding box size, mm.
    pub size_mm: [f32; 3],
    /// Repairs applied.
    pub repairs: lung_bake::import::Repairs,
    /// Connected shells in the file.
    pub shells: usize,
    /// Which lung the geometry looks like ("left", "right" or null when it cannot tell).
    pub geometry_side: Option<String>,
    /// Why (the evidence).
    pub geometry_side_reason: String,
    /// The warning when `--lung` disagrees with the geometry.
    pub side_warning: Option<String>,
    /// The frame the coordinates were read in ("body", "lps", "ras"; the mesh is reported in body).
    pub frame: String,
    /// What the geometry says about anterior/posterior and superior/inferior.
    pub orientation_reason: String,
    /// The warning when anterior/posterior or superior/inferior look flipped.
    pub frame_warning: Option<String>,
    /// Where `--out` wrote the repaired mesh (mm, body frame); `null` without `--out`.
    pub out: Option<String>,
    /// Vertices and surface area per lobe, from the fissure planes in normalised lung coordinates
    /// (`lung_model::mesh::lobes`) for `--lung`, else the side the geometry shows; empty when
    /// neither is known.
    pub lobes: Vec<lobes::LobeSummary>,
}

/// Import, repair what is safe, verify, optionally export.
pub fn check_mesh(args: &CheckArgs) -> anyhow::Result<CheckSummary> {
    if let Some(out) = &args.out {
        io::check_out(out)?;
    }
    let lung = crate::mask_cmd::parsed::<Side>(args.lung.as_deref())?;
    let (imported, side_warning, frame_warning) = import_lung(
        &args.mesh,
        &args.units,
        args.component,
        &args.frame,
        &args.input,
        lung,
    )?;
    if let Some(out) = &args.out {
        io::write_mesh(&imported.mesh, out)?;
    }
    let lobe_side = lung.or(imported.side.as_ref().and_then(|e| e.side));
    let lobes = lobe_side.map_or_else(Vec::new, |side| {
        lobes::summarise(&imported.mesh, &lobes::classify(side, &imported.mesh))
    });
    Ok(CheckSummary {
        path: args.mesh.display().to_string(),
        vertices: imported.topology.vertices,
        triangles: imported.topology.triangles,
        euler: imported.topology.euler,
        volume_ml: imported.mesh.enclosed_volume_ml(),
        size_mm: imported.mesh.aabb().size(),
        repairs: imported.repairs,
        shells: imported.shells,
        geometry_side: imported
            .side
            .as_ref()
            .and_then(|e| e.side)
            .map(|s| s.name().to_string()),
        geometry_side_reason: imported
            .side
            .as_ref()
            .map(|e| e.reason.clone())
            .unwrap_or_default(),
        side_warning,
        frame: args.frame.frame.clone().unwrap_or_else(|| "body".into()),
        orientation_reason: imported
            .orientation
            .as_ref()
            .map(|o| o.reason.clone())
            .unwrap_or_default(),
        frame_warning,
        out: args.out.as_ref().map(|p| p.display().to_string()),
        lobes,
    })
}
