//! `lungdyn fit-motion`: direction-model constants from corresponding points or meshes.

use std::path::{Path, PathBuf};

use anyhow::Context;
use engine::deform::MotionFile;
use engine::mesh::Side;
use engine::motion_fit::{self, MotionFit};
use glam::DVec3;

/// Options of `lungdyn fit-motion`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "Point files: one `x y z` per line (whitespace-separated; blank lines and \
lines starting with # are skipped), the same points in the same order in every file. Coordinates \
are in the body frame: +X patient left, +Y anterior, +Z superior; millimetres, or voxel indices \
with --spacing. A mesh (.obj, .ply, .stl) stands for its vertices; two meshes of one lung must \
share their vertex order. Sets covering both lungs are split at the mid-sagittal gap (the lung at \
larger X is the left one).\n\nExample: lungdyn fit-motion --from exhale.txt --to mid.txt --also \
inhale.txt --spacing 0.97,0.97,2.5 --out motion.toml"
)]
pub struct FitMotionArgs {
    /// Points (or mesh) at the reference phase, e.g. end-exhalation.
    #[arg(long)]
    pub from: PathBuf,
    /// The same points at the phase to fit.
    #[arg(long)]
    pub to: PathBuf,
    /// Further phases checked with one volume scale each (comma-separated files).
    #[arg(long, value_delimiter = ',')]
    pub also: Vec<PathBuf>,
    /// Voxel spacing in mm (sx,sy,sz): the files hold voxel indices.
    #[arg(long, value_delimiter = ',')]
    pub spacing: Vec<f64>,
    /// Which lung, when the points are one lung (no mid-sagittal gap).
    #[arg(long, value_parser = ["left", "right"])]
    pub lung: Option<String>,
    /// Write the constants (TOML, for `lungdyn bake --motion` or a scene's [lungs] motion).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Read a point file or a mesh's vertices, in mm.
pub fn read_points(path: &Path, spacing: Option<[f64; 3]>) -> anyhow::Result<Vec<DVec3>> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let raw: Vec<DVec3> = if matches!(ext.as_deref(), Some("obj" | "ply" | "stl")) {
        let m = engine::mesh::import::import(path, engine::mesh::import::Units::Mm)?;
        if m.repairs.welded_vertices > 0 || m.repairs.unused_vertices > 0 {
            anyhow::bail!(
                "{}: the mesh needed vertex repairs (welded {}, unused {}), so its vertex order no longer \
                 matches the other phase: export both phases without duplicate or unused vertices",
                path.display(),
                m.repairs.welded_vertices,
                m.repairs.unused_vertices
            );
        }
        m.mesh
            .positions
            .iter()
            .map(|p| DVec3::from(p.map(|v| v as f64)))
            .collect()
    } else {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let mut pts = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let v: Vec<&str> = line.split_whitespace().collect();
            if v.len() != 3 {
                anyhow::bail!(
                    "{}:{}: expected three numbers `x y z`, found {} fields",
                    path.display(),
                    i + 1,
                    v.len()
                );
            }
            let mut p = [0.0; 3];
            for (k, f) in v.iter().enumerate() {
                p[k] = f
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| {
                        anyhow::anyhow!(
                            "{}:{}: {f:?} is not a finite number",
                            path.display(),
                            i + 1
                        )
                    })?;
            }
            pts.push(DVec3::from(p));
        }
        if pts.is_empty() {
            anyhow::bail!("{}: no points", path.display());
        }
        pts
    };
    Ok(match spacing {
        Some(s) => raw.into_iter().map(|p| p * DVec3::from(s)).collect(),
        None => raw,
    })
}

/// Read, fit, optionally write.
pub fn run(args: &FitMotionArgs) -> anyhow::Result<MotionFit> {
    let spacing = match args.spacing.as_slice() {
        [] => None,
        [x, y, z] => {
            if ![x, y, z].iter().all(|v| v.is_finite() && **v > 0.0) {
                anyhow::bail!("--spacing {x},{y},{z}: each must be a positive number of mm");
            }
            Some([*x, *y, *z])
        }
        _ => anyhow::bail!("--spacing needs three numbers sx,sy,sz"),
    };
    let side: Option<Side> = args
        .lung
        .as_deref()
        .map(|s| s.parse().map_err(anyhow::Error::msg))
        .transpose()?;
    let a = read_points(&args.from, spacing)?;
    let b = read_points(&args.to, spacing)?;
    let also = args
        .also
        .iter()
        .map(|p| Ok((p.display().to_string(), read_points(p, spacing)?)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let fit = motion_fit::fit(&a, &b, &also, side)?;
    if let Some(out) = &args.out {
        let mut file = MotionFile {
            format: 1,
            left: None,
            right: None,
        };
        for l in &fit.lungs {
            match l.lung {
                Side::Left => file.left = Some(l.motion()),
                Side::Right => file.right = Some(l.motion()),
            }
        }
        let text = format!(
            "# lungdyn motion constants (fit-motion from {} to {}); c1, c3, c5 in mm at the fitted phase,\n\
             # c7..c9 are Table 6.1 (not fitted from points). Use: lungdyn bake --motion this.toml\n{}",
            args.from.display(),
            args.to.display(),
            toml::to_string(&file)?
        );
        engine::mesh::io::write_atomically(out, |w| {
            use std::io::Write;
            w.write_all(text.as_bytes())
        })?;
    }
    Ok(fit)
}

/// Human-readable report.
pub fn text(f: &MotionFit, args: &FitMotionArgs) -> String {
    let mut s = String::new();
    for l in &f.lungs {
        let c = &l.constants;
        s += &format!(
            "{} lung, {} points: c1 {:.4} c2 {:.3} c3 {:.4} c4 {:.3} c5 {:.4} c6 {:.3}\n  \
             error mean {:.2} mm, max {:.2} mm, rms {:.2} mm (no-motion baseline {:.2} mm)\n",
            l.lung.name(),
            l.points,
            c[0],
            c[1],
            c[2],
            c[3],
            c[4],
            c[5],
            l.residuals.mean_error_mm,
            l.residuals.max_error_mm,
            l.residuals.rms_error_mm,
            l.residuals.baseline_mean_mm
        );
        for (p, path) in l.also.iter().zip(&args.also) {
            s += &format!(
                "  {}: scale {:.3}, error mean {:.2} mm, max {:.2} mm (baseline {:.2} mm)\n",
                path.display(),
                p.scale,
                p.residuals.mean_error_mm,
                p.residuals.max_error_mm,
                p.residuals.baseline_mean_mm
            );
        }
    }
    s += &format!(
        "all points: error mean {:.2} mm, max {:.2} mm (baseline {:.2} mm)\n",
        f.residuals.mean_error_mm, f.residuals.max_error_mm, f.residuals.baseline_mean_mm
    );
    if let Some(out) = &args.out {
        s += &format!("wrote {}\n", out.display());
    }
    s
}
