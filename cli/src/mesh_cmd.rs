//! `lungdyn mesh generate`: write a generated lung as OBJ or PLY.

use std::path::PathBuf;

use lung_model::mesh::{check, generate, io, Side};
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
}

/// Generate, verify and write.
pub fn run(args: &GenerateArgs) -> anyhow::Result<MeshSummary> {
    let side: Side = args.lung.parse().map_err(anyhow::Error::msg)?;
    io::MeshFormat::from_path(&args.out)?;
    let mesh = generate::lung(side, args.vertices)?;
    check(&mesh)
        .map_err(|e| anyhow::anyhow!("internal error: the generated mesh is invalid: {e}"))?;
    io::write_mesh(&mesh, &args.out)?;
    Ok(MeshSummary {
        path: args.out.display().to_string(),
        lung: side.name().to_string(),
        vertices: mesh.positions.len(),
        triangles: mesh.triangles.len(),
        volume_ml: mesh.enclosed_volume_ml(),
        size_mm: mesh.aabb().size(),
    })
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
    /// Write the welded, repaired mesh (in mm) as .obj or .ply.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
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
}

/// Import, repair what is safe, verify, optionally export.
pub fn check_mesh(args: &CheckArgs) -> anyhow::Result<CheckSummary> {
    let units: lung_bake::import::Units = args.units.parse().map_err(anyhow::Error::msg)?;
    if let Some(out) = &args.out {
        io::MeshFormat::from_path(out)?;
    }
    let imported = lung_bake::import::import(&args.mesh, units)?;
    if let Some(out) = &args.out {
        io::write_mesh(&imported.mesh, out)?;
    }
    Ok(CheckSummary {
        path: args.mesh.display().to_string(),
        vertices: imported.topology.vertices,
        triangles: imported.topology.triangles,
        euler: imported.topology.euler,
        volume_ml: imported.mesh.enclosed_volume_ml(),
        size_mm: imported.mesh.aabb().size(),
        repairs: imported.repairs,
    })
}
