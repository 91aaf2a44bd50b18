//! `lungdyn fit-motion`: direction-model constants from corresponding points or meshes.

use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::DVec3;
use lung_bake::motion_fit::{self, MotionFit};
use lung_model::deform::MotionFile;
use lung_model::mesh::Side;

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
    /// Treat two meshes as surfaces without vertex correspondence (automatic when their vertex
    /// counts differ): the model is fitted so the moved reference lies on the target surface.
    #[arg(long)]
    pub surface: bool,
    /// Scene whose [lungs] elasticity and transfer_tolerance the force fit uses (mesh input).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Write the constants (TOML, for `lungdyn bake --motion` or a scene's [lungs] motion).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Read a point file or a mesh's vertices, in mm (bounded reading; sizes checked against lungs).
pub fn read_points(
    path: &Path,
    spacing: Option<[f64; 3]>,
    input: &crate::input_args::InputArgs,
) -> anyhow::Result<Vec<DVec3>> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let raw: Vec<DVec3> = if matches!(ext.as_deref(), Some("obj" | "ply" | "stl")) {
        let m = lung_bake::import::import_with(
            path,
            &lung_bake::import::ImportOptions {
                units: lung_bake::import::Units::Mm,
                limits: input.limits(lung_model::input::ReadLimits::MESH),
                shells: lung_bake::import::Shells::All,
                one_lung: false,
            },
        )?;
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
        let text = lung_model::input::read_text_bounded(
            path,
            input.limits(lung_model::input::ReadLimits::TABLE),
        )?;
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
    let pts: Vec<DVec3> = match spacing {
        Some(s) => raw.into_iter().map(|p| p * DVec3::from(s)).collect(),
        None => raw,
    };
    check_spread(path, &pts, spacing.is_some())?;
    Ok(pts)
}

/// The landmarks must span a lung-sized region: points in metres span 0.3 "mm".
fn check_spread(path: &Path, pts: &[DVec3], voxels: bool) -> anyhow::Result<()> {
    use lung_model::plausible::LANDMARK_SPREAD_MM;
    // Too few points to judge a spread (the fit refuses too few points itself).
    if pts.len() < 4 {
        return Ok(());
    }
    let (lo, hi) = pts.iter().fold(
        (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let spread = (hi - lo).max_element();
    let hint = if voxels {
        Some("check --spacing (mm per voxel along x, y, z)".to_string())
    } else if LANDMARK_SPREAD_MM.contains(spread * 1000.0) {
        Some("the coordinates look like metres: convert them to mm (lungdyn reads mm)".into())
    } else if LANDMARK_SPREAD_MM.contains(spread * 10.0) {
        Some("the coordinates look like centimetres: convert them to mm (lungdyn reads mm)".into())
    } else if spread < 1000.0 {
        Some("voxel indices? pass --spacing sx,sy,sz".into())
    } else {
        None
    };
    LANDMARK_SPREAD_MM
        .check(spread, hint)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// Corresponding points must not move further than a lung can between two phases.
fn check_motion(from: &[DVec3], to: &[DVec3], path: &Path) -> anyhow::Result<()> {
    use lung_model::plausible::LANDMARK_MOTION_MM;
    if let Some((i, d)) = from
        .iter()
        .zip(to)
        .map(|(a, b)| a.distance(*b))
        .enumerate()
        .find(|(_, d)| !LANDMARK_MOTION_MM.contains(*d))
    {
        anyhow::bail!(
            "{}: point {} moves {d:.1} mm from the reference phase; {}",
            path.display(),
            i + 1,
            LANDMARK_MOTION_MM
                .check(
                    d,
                    Some("are the two files in the same order, frame and unit?".into())
                )
                .unwrap_err()
        );
    }
    Ok(())
}

fn is_mesh(p: &Path) -> bool {
    matches!(
        p.extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref(),
        Some("obj" | "ply" | "stl")
    )
}

/// The closed surface made of the triangles whose vertices are all in `keep` (reindexed), scaled.
fn sub_mesh(
    mesh: &lung_model::mesh::TriMesh,
    keep: &[usize],
    scale: [f64; 3],
) -> anyhow::Result<lung_model::mesh::TriMesh> {
    let mut map = vec![u32::MAX; mesh.positions.len()];
    let mut positions = Vec::with_capacity(keep.len());
    for &i in keep {
        map[i] = positions.len() as u32;
        let p = mesh.positions[i];
        positions.push([
            (p[0] as f64 * scale[0]) as f32,
            (p[1] as f64 * scale[1]) as f32,
            (p[2] as f64 * scale[2]) as f32,
        ]);
    }
    let triangles: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .filter(|t| t.iter().all(|&v| map[v as usize] != u32::MAX))
        .map(|t| t.map(|v| map[v as usize]))
        .collect();
    let sub = lung_model::mesh::TriMesh {
        positions,
        triangles,
    };
    lung_model::mesh::check(&sub)?;
    Ok(sub)
}

fn import_scaled(
    path: &Path,
    spacing: Option<[f64; 3]>,
    input: &crate::input_args::InputArgs,
) -> anyhow::Result<lung_model::mesh::TriMesh> {
    let mut m = lung_bake::import::import_with(
        path,
        &lung_bake::import::ImportOptions {
            units: lung_bake::import::Units::Mm,
            limits: input.limits(lung_model::input::ReadLimits::MESH),
            shells: lung_bake::import::Shells::All,
            one_lung: false,
        },
    )?
    .mesh;
    if let Some(s) = spacing {
        for p in &mut m.positions {
            for k in 0..3 {
                p[k] = (p[k] as f64 * s[k]) as f32;
            }
        }
    }
    Ok(m)
}

fn lung_parts(
    mesh: &lung_model::mesh::TriMesh,
    side: Option<Side>,
    what: &Path,
) -> anyhow::Result<Vec<(Side, Vec<usize>, lung_model::mesh::TriMesh)>> {
    let pts: Vec<DVec3> = mesh
        .positions
        .iter()
        .map(|p| DVec3::from(p.map(|v| v as f64)))
        .collect();
    motion_fit::split_lungs(&pts, side)?
        .into_iter()
        .map(|(s, idx)| {
            let sub = sub_mesh(mesh, &idx, [1.0; 3]).with_context(|| {
                format!(
                    "{}: the {} lung's part of the mesh",
                    what.display(),
                    s.name()
                )
            })?;
            Ok((s, idx, sub))
        })
        .collect()
}

/// Surface mode: fit each lung of `a` to the matching lung of `b` (and of each `--also` mesh).
fn run_surface(
    args: &FitMotionArgs,
    a: &lung_model::mesh::TriMesh,
    b: &lung_model::mesh::TriMesh,
    spacing: Option<[f64; 3]>,
    side: Option<Side>,
    corresponding: bool,
) -> anyhow::Result<MotionFit> {
    use lung_bake::surface_fit::{fit_surface, Goal, Target};
    let scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    let parts_a = lung_parts(a, side, &args.from)?;
    let parts_b = lung_parts(b, side, &args.to)?;
    let also = args
        .also
        .iter()
        .map(|p| {
            if !is_mesh(p) {
                anyhow::bail!(
                    "{}: with two meshes, --also must be meshes too",
                    p.display()
                );
            }
            let m = import_scaled(p, spacing, &args.input)?;
            if corresponding && (m.positions.len() != a.positions.len() || m.triangles != a.triangles) {
                anyhow::bail!(
                    "{}: its vertices do not match {} (pass --surface to fit all phases as surfaces)",
                    p.display(),
                    args.from.display()
                );
            }
            let parts = lung_parts(&m, side, p)?;
            Ok((p, m, parts))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let find = |parts: &[(Side, Vec<usize>, lung_model::mesh::TriMesh)], s: Side, what: &Path| {
        parts
            .iter()
            .find(|(x, _, _)| *x == s)
            .map(|(_, _, m)| m.clone())
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: has no {} lung, but {} has one",
                    what.display(),
                    s.name(),
                    args.from.display()
                )
            })
    };
    let mut lungs = Vec::new();
    for (s, idx, ma) in &parts_a {
        // Corresponding meshes are cut with the reference's own vertex sets, so indices still match.
        let (mb, mc) = if corresponding {
            (
                sub_mesh(b, idx, [1.0; 3])?,
                also.iter()
                    .map(|(_, m, _)| sub_mesh(m, idx, [1.0; 3]))
                    .collect::<anyhow::Result<Vec<_>>>()?,
            )
        } else {
            (
                find(&parts_b, *s, &args.to)?,
                also.iter()
                    .map(|(p, _, parts)| find(parts, *s, p))
                    .collect::<anyhow::Result<Vec<_>>>()?,
            )
        };
        let f = if corresponding {
            // Same vertices and triangles at every phase: point-to-point goals.
            let pts = |m: &lung_model::mesh::TriMesh| -> Vec<DVec3> {
                m.positions
                    .iter()
                    .map(|p| DVec3::from(p.map(|v| v as f64)))
                    .collect()
            };
            let (pb, pc): (Vec<DVec3>, Vec<Vec<DVec3>>) = (pts(&mb), mc.iter().map(pts).collect());
            let goals: Vec<Goal> = pc.iter().map(|p| Goal::Points(p)).collect();
            fit_surface(
                *s,
                ma,
                Goal::Points(&pb),
                &goals,
                &scene.lungs.elasticity,
                scene.lungs.transfer_tolerance,
            )?
        } else {
            let tb = Target::new(&mb, &args.to.display().to_string())?;
            let tc = also
                .iter()
                .zip(&mc)
                .map(|((p, _, _), m)| Target::new(m, &p.display().to_string()).map_err(Into::into))
                .collect::<anyhow::Result<Vec<_>>>()?;
            let goals: Vec<Goal> = tc.iter().map(Goal::Surface).collect();
            fit_surface(
                *s,
                ma,
                Goal::Surface(&tb),
                &goals,
                &scene.lungs.elasticity,
                scene.lungs.transfer_tolerance,
            )?
        };
        lungs.push(motion_fit::LungFit {
            lung: *s,
            points: ma.positions.len(),
            constants: f.constants,
            residuals: f.residuals,
            also: f.also,
            indices: Vec::new(),
        });
    }
    let mode = if corresponding { "mesh" } else { "surface" };
    let fit = MotionFit::from_lungs(mode, args.also.len(), lungs);
    if let Some(out) = &args.out {
        write_motion(
            out,
            &fit,
            args,
            "c1..c9 of the kernel's model, fitted through the operator",
        )?;
    }
    Ok(fit)
}

fn write_motion(
    out: &Path,
    fit: &MotionFit,
    args: &FitMotionArgs,
    how: &str,
) -> anyhow::Result<()> {
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
        "# lungdyn motion constants (fit-motion from {} to {}, {} mode); {how}.\n\
         # Use: lungdyn bake --motion this.toml\n{}",
        args.from.display(),
        args.to.display(),
        fit.mode,
        toml::to_string(&file)?
    );
    lung_model::mesh::io::write_atomically(out, |w| {
        use std::io::Write;
        w.write_all(text.as_bytes())
    })?;
    Ok(())
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
    if is_mesh(&args.from) && is_mesh(&args.to) {
        let ma = import_scaled(&args.from, spacing, &args.input)?;
        let mb = import_scaled(&args.to, spacing, &args.input)?;
        let same_vertices =
            ma.positions.len() == mb.positions.len() && ma.triangles == mb.triangles;
        return run_surface(
            args,
            &ma,
            &mb,
            spacing,
            side,
            same_vertices && !args.surface,
        );
    } else if args.surface {
        anyhow::bail!("--surface needs two meshes (.obj, .ply, .stl) for --from and --to");
    }
    let a = read_points(&args.from, spacing, &args.input)?;
    let b = read_points(&args.to, spacing, &args.input)?;
    if a.len() == b.len() {
        check_motion(&a, &b, &args.to)?;
    }
    let also = args
        .also
        .iter()
        .map(|p| {
            let pts = read_points(p, spacing, &args.input)?;
            if pts.len() == a.len() {
                check_motion(&a, &pts, p)?;
            }
            Ok((p.display().to_string(), pts))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let fit = motion_fit::fit(&a, &b, &also, side)?;
    if let Some(out) = &args.out {
        write_motion(
            out,
            &fit,
            args,
            "c1, c3, c5 in mm at the fitted phase; c7..c9 are Table 6.1 (not fitted from points)",
        )?;
    }
    Ok(fit)
}

/// Human-readable report.
pub fn text(f: &MotionFit, args: &FitMotionArgs) -> String {
    let mut s = String::new();
    match f.mode {
        "surface" => s += "surface mode: errors are distances of the moved reference to the target surface\n",
        "mesh" => s += "mesh mode: the kernel's model fitted through the operator; errors are point to point\n",
        _ => {}
    }
    for l in &f.lungs {
        let c = &l.constants;
        let force = if f.mode != "points" {
            "fitted"
        } else {
            "Table 6.1"
        };
        s += &format!(
            "{} lung, {} points: c1 {:.4} c2 {:.3} c3 {:.4} c4 {:.3} c5 {:.4} c6 {:.3}; c7 {:.3} c8 {:.3} c9 {:.3} ({force})\n  \
             error mean {:.2} mm, max {:.2} mm, rms {:.2} mm (no-motion baseline {:.2} mm)\n",
            l.lung.name(),
            l.points,
            c[0],
            c[1],
            c[2],
            c[3],
            c[4],
            c[5],
            c[6],
            c[7],
            c[8],
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
