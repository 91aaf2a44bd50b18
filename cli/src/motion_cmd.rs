//! `lungdyn fit-motion`: direction-model constants from corresponding points or meshes.

use std::path::Path;

use anyhow::Context;
use glam::DVec3;
use lung_bake::landmarks::Frame;
use lung_bake::motion_fit::{self, MotionFit};
use lung_bake::motion_models::{self, ModelReport};
use lung_model::deform::MotionFile;
use lung_model::mesh::Side;
use serde::Serialize;

pub use crate::motion_input::{
    frame_of, FitMotionArgs, FrameName, ModelChoice, PointFormat, VOXEL_SPACING_MM,
};
use crate::motion_input::{import_mesh_in, import_scaled};
pub use crate::motion_report::{PhaseRow, PointsReport};
use lung_model::scene::SceneExt;

/// Read a point file (in `frame`) or a mesh's vertices (mm, `frame` must be body, lps or ras), in
/// the body frame, bounded, sizes checked against lungs.
pub fn read_points(
    path: &Path,
    frame: &Frame,
    input: &crate::input_args::InputArgs,
) -> anyhow::Result<Vec<DVec3>> {
    let pts: Vec<DVec3> = if is_mesh(path) {
        let m = import_mesh_in(path, frame, input)?;
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
        lung_bake::landmarks::read(
            path,
            frame,
            input.limits(lung_model::input::ReadLimits::TABLE),
        )?
    };
    check_spread(path, &pts, matches!(frame, Frame::Voxel { .. }))?;
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

/// Coordinates that are all whole numbers from 0 to 4095 look like CT voxel indices (a CT grid has at
/// most a few thousand voxels per axis; coordinates in mm are almost never all whole and non-negative:
/// the body frame's X changes sign between the lungs). Read as mm they would be fitted into a wrong
/// answer, so without a stated frame they are refused, naming the options for voxels.
fn check_not_voxel_indices(path: &Path, pts: &[DVec3]) -> anyhow::Result<()> {
    if pts.len() < 4 {
        return Ok(());
    }
    let whole = |v: f64| (0.0..4096.0).contains(&v) && v.fract() == 0.0;
    if !pts.iter().all(|p| p.to_array().into_iter().all(whole)) {
        return Ok(());
    }
    let (lo, hi) = pts.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    anyhow::bail!(
        "{}: every coordinate is a whole number from 0 to 4095 (x {}–{}, y {}–{}, z {}–{}), as CT voxel \
         indices are, and no frame was stated (read as mm they would give a wrong answer): for voxel \
         indices pass --frame voxel --spacing sx,sy,sz --voxel-axes AXES --index-base 0|1 (DIR-Lab \
         files: --format dirlab --spacing sx,sy,sz); if they really are mm, say so with --frame body \
         (or lps, ras)",
        path.display(),
        lo.x,
        hi.x,
        lo.y,
        hi.y,
        lo.z,
        hi.z
    )
}

/// Smallest largest-displacement between two phases taken as motion, mm (1 µm: below any imaging
/// resolution, so less is the same phase twice).
const MIN_MOTION_MM: f64 = 1e-3;

/// The two phases must differ: the same points twice fit a motion of zero, written as if measured.
fn check_some_motion(
    from: &[DVec3],
    to: &[DVec3],
    path: &Path,
    args: &FitMotionArgs,
) -> anyhow::Result<()> {
    let largest = from
        .iter()
        .zip(to)
        .map(|(a, b)| a.distance(*b))
        .fold(0.0, f64::max);
    if largest < MIN_MOTION_MM {
        anyhow::bail!(
            "{}: no motion between the phases: every point is where it is in {} (largest displacement {} \
             mm): is it the same phase twice? Give the end-exhale points as --from and the end-inhale \
             points as --to",
            path.display(),
            args.from_path().display(),
            lung_model::plausible::compact(largest)
        );
    }
    Ok(())
}

/// Refuse `--from` and `--to` naming one file (nothing to fit), before reading either.
fn check_distinct_files(args: &FitMotionArgs) -> anyhow::Result<()> {
    let same = match (
        std::fs::canonicalize(args.from_path()),
        std::fs::canonicalize(args.to_path()),
    ) {
        (Ok(a), Ok(b)) => a == b,
        _ => args.from == args.to,
    };
    if same {
        anyhow::bail!(
            "--from and --to are the same file ({}): no motion between the phases can be fitted from one \
             phase; give the end-inhale file as --to",
            args.to_path().display()
        );
    }
    Ok(())
}

/// Warn (stderr) when `side` disagrees with what the evidence says; returns the warning.
fn side_warning(path: &Path, side: Option<Side>, seen: Option<(Side, String)>) -> Option<String> {
    match (side, seen) {
        (Some(given), Some((seen, why))) if given != seen => {
            let w = format!(
                "{}: --lung {} but it looks like a {} lung ({why}): check --lung and the frame (+X = the \
                 patient's left)",
                path.display(),
                given.name(),
                seen.name()
            );
            eprintln!("lungdyn: warning: {w}");
            Some(w)
        }
        _ => None,
    }
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
            "{}: point {} moves {} mm from the reference phase; {}",
            path.display(),
            i + 1,
            if d.is_finite() && d.abs() < 1e7 {
                format!("{d:.1}")
            } else {
                format!("{d:e}")
            },
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
    motion_fit::split_lungs(&pts, side)
        .map_err(|e| anyhow::anyhow!("{}: {e}", what.display()))?
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
    frame: &Frame,
    side: Option<Side>,
    corresponding: bool,
) -> anyhow::Result<MotionFit> {
    use lung_bake::surface_fit::{fit_surface, Goal, Target};
    let scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    let parts_a = lung_parts(a, side, args.from_path())?;
    if side.is_some() {
        // --lung: the mesh is that lung; say so when its geometry says otherwise (as bake and mesh
        // check do).
        for (_, _, m) in &parts_a {
            let e = lung_bake::surface_checks::infer_side(m);
            side_warning(
                args.from_path(),
                side,
                e.side
                    .map(|s| (s, format!("{}; confidence {:.2}", e.reason, e.confidence))),
            );
        }
    }
    let parts_b = lung_parts(b, side, args.to_path())?;
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
            let m = import_scaled(p, frame, &args.input)?;
            if corresponding && (m.positions.len() != a.positions.len() || m.triangles != a.triangles) {
                anyhow::bail!(
                    "{}: its vertices do not match {} (pass --surface to fit all phases as surfaces)",
                    p.display(),
                    args.from_path().display()
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
                    args.from_path().display()
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
                find(&parts_b, *s, args.to_path())?,
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
                scene.lungs.amplitude_smoothing_mm,
            )?
        } else {
            let tb = Target::new(&mb, &args.to_path().display().to_string())?;
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
                scene.lungs.amplitude_smoothing_mm,
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
            None,
        )?;
    }
    Ok(fit)
}

fn write_motion(
    out: &Path,
    fit: &MotionFit,
    args: &FitMotionArgs,
    how: &str,
    chosen: Option<(&PointsReport, &ModelReport)>,
) -> anyhow::Result<()> {
    let mut file = MotionFile {
        format: if chosen.is_some() { 2 } else { 1 },
        left: None,
        right: None,
        frame: None,
        chosen: None,
        cv_mean_error_mm: None,
        left_field: None,
        right_field: None,
        left_force: None,
        right_force: None,
    };
    for l in &fit.lungs {
        match l.lung {
            Side::Left => file.left = Some(l.motion()),
            Side::Right => file.right = Some(l.motion()),
        }
    }
    if let Some((report, model)) = chosen {
        file.frame = Some(report.frame_description.clone());
        file.chosen = Some(model.model.name().to_string());
        file.cv_mean_error_mm = Some(model.cv.mean_mm);
        for (side, field) in &model.fit.lungs {
            match side {
                Side::Left => file.left_field = Some(field.clone()),
                Side::Right => file.right_field = Some(field.clone()),
            }
        }
    }
    let text = format!(
        "# lungdyn motion constants (fit-motion from {} to {}, {} mode); {how}.\n\
         # Use: lungdyn bake --motion this.toml\n{}",
        args.from_path().display(),
        args.to_path().display(),
        fit.mode,
        toml::to_string(&file)?
    );
    outfile::write_atomically(out, |w| {
        use std::io::Write;
        w.write_all(text.as_bytes())
    })?;
    Ok(())
}

/// What `fit-motion` did.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum Outcome {
    /// Landmarks: every model, cross-validated.
    Points(Box<PointsReport>),
    /// Meshes or surfaces: the kernel's own model through the operator.
    Kernel(MotionFit),
    /// A breath-hold pair: the patient's force and direction fields.
    Pair(Box<crate::pair_cmd::PairReport>),
}

/// Read, fit, optionally write.
pub fn run(args: &FitMotionArgs) -> anyhow::Result<Outcome> {
    if args.exhale.is_some() {
        return Ok(Outcome::Pair(Box::new(crate::pair_cmd::run(args)?)));
    }
    let meshes = std::iter::once(args.from_path())
        .chain(std::iter::once(args.to_path()))
        .chain(args.also.iter().map(|p| p.as_path()))
        .any(is_mesh);
    if meshes && !args.spacing.is_empty() {
        anyhow::bail!(
            "--spacing applies to voxel landmark files only; a mesh (.obj, .ply, .stl) holds coordinates \
             in mm, which --spacing must not rescale: drop --spacing"
        );
    }
    let frame = frame_of(args)?;
    let side: Option<Side> = args.lung;
    check_distinct_files(args)?;
    check_outputs(args)?;
    if is_mesh(args.from_path()) && is_mesh(args.to_path()) {
        return Ok(Outcome::Kernel(run_meshes(args, &frame, side)?));
    } else if args.surface {
        anyhow::bail!("--surface needs two meshes (.obj, .ply, .stl) for --from and --to");
    }
    let a = read_points(args.from_path(), &frame, &args.input)?;
    let b = read_points(args.to_path(), &frame, &args.input)?;
    let stated = args.frame.is_some()
        || args.format == PointFormat::Dirlab
        || args.voxel_axes.is_some()
        || args.index_base.is_some();
    if !stated {
        for (path, pts) in [(args.from_path(), &a), (args.to_path(), &b)] {
            if !is_mesh(path) {
                check_not_voxel_indices(path, pts)?;
            }
        }
    }
    if a.len() == b.len() {
        check_motion(&a, &b, args.to_path())?;
        check_some_motion(&a, &b, args.to_path(), args)?;
    }
    let also = args
        .also
        .iter()
        .map(|p| {
            let pts = read_points(p, &frame, &args.input)?;
            if pts.len() == a.len() {
                check_motion(&a, &pts, p)?;
            }
            Ok((p.display().to_string(), pts))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    // --lung: the set is that one lung (refused, naming the file, when it clearly holds both).
    if side.is_some() {
        motion_fit::split_lungs(&a, side)
            .map_err(|e| anyhow::anyhow!("{}: {e}", args.from_path().display()))?;
    }
    // The seed's power law with its per-lung constants (what a kernel's c1..c9 are)...
    let power = motion_fit::fit(&a, &b, &also, side)?;
    // ... and every model, cross-validated.
    let delta: Vec<DVec3> = a.iter().zip(&b).map(|(p, q)| *q - *p).collect();
    let (_, lungs, _) = motion_models::split(&a, &delta, side)?;
    // --lung: the set is that lung; say so when its motion says otherwise.
    let side_warning = side_warning(
        args.from_path(),
        side,
        motion_fit::side_from_motion(&a, &delta),
    );
    let frame_check = motion_models::check_frame(&lungs);
    if let Some(w) = &frame_check.warning {
        eprintln!("lungdyn: WARNING: {w}");
    }
    let k = args.folds as usize;
    let kinds = args.model.kinds();
    let models = kinds
        .iter()
        .map(|&kind| motion_models::evaluate(kind, &a, &delta, side, k, args.seed))
        .collect::<Result<Vec<_>, _>>()?;
    let chosen = if args.model == ModelChoice::Auto {
        models
            .iter()
            .min_by(|x, y| x.cv.mean_mm.total_cmp(&y.cv.mean_mm))
            .expect("at least one model")
    } else {
        models.last().expect("the asked model")
    };
    let phases = predicted_phases(&also, chosen, &a, &delta, side, args)?;
    let report = PointsReport {
        mode: "points",
        frame: frame.name(),
        frame_description: frame.describe(),
        frame_warning: frame_check.warning.clone(),
        side_warning,
        frame_check,
        baseline_mean_mm: power.residuals.baseline_mean_mm,
        folds: args.folds,
        seed: args.seed,
        chosen: chosen.model.name(),
        cv_mean_error_mm: chosen.cv.mean_mm,
        cv_max_error_mm: chosen.cv.max_mm,
        mean_error_mm: chosen.in_sample.mean_mm,
        max_error_mm: chosen.in_sample.max_mm,
        rms_error_mm: chosen.in_sample.rms_mm,
        also: phases,
        lungs: power.lungs.clone(),
        models: Vec::new(),
    };
    let chosen_index = models
        .iter()
        .position(|m| m.model == chosen.model)
        .expect("chosen is one of them");
    let report = PointsReport { models, ..report };
    if let Some(png) = &args.plot {
        crate::motion_plot::write(png, &a, &report)?;
    }
    if let Some(out) = &args.out {
        write_motion(
            out,
            &power,
            args,
            "c1, c3, c5 in mm at the fitted phase; c7..c9 are Table 6.1 (not fitted from points); \
             [left_field]/[right_field] is the model chosen by cross-validation (the kernel's directions)",
            Some((&report, &report.models[chosen_index])),
        )?;
    }
    Ok(Outcome::Points(Box::new(report)))
}

/// Every output of `fit-motion` checked before any work.
fn check_outputs(args: &FitMotionArgs) -> anyhow::Result<()> {
    let mut outputs = Vec::new();
    if let Some(path) = &args.out {
        outputs.push(crate::outputs::Output {
            flag: "--out",
            path,
            extensions: &[],
        });
    }
    if let Some(path) = &args.plot {
        outputs.push(crate::outputs::Output {
            flag: "--plot",
            path,
            extensions: &["png"],
        });
    }
    crate::outputs::check_all(&outputs, &[])
}

/// Two meshes: the kernel's own model through the operator (corresponding vertices when they
/// share their vertex order and `--surface` is not asked, else surface to surface).
fn run_meshes(
    args: &FitMotionArgs,
    frame: &Frame,
    side: Option<Side>,
) -> anyhow::Result<MotionFit> {
    let ma = import_scaled(args.from_path(), frame, &args.input)?;
    let mb = import_scaled(args.to_path(), frame, &args.input)?;
    let same_vertices = ma.positions.len() == mb.positions.len() && ma.triangles == mb.triangles;
    if same_vertices {
        let pts = |m: &lung_model::mesh::TriMesh| -> Vec<DVec3> {
            m.positions
                .iter()
                .map(|p| DVec3::from(p.map(|v| v as f64)))
                .collect()
        };
        check_some_motion(&pts(&ma), &pts(&mb), args.to_path(), args)?;
    }
    run_surface(args, &ma, &mb, frame, side, same_vertices && !args.surface)
}

/// The chosen model's prediction of each further phase (`--also`) with one scale.
fn predicted_phases(
    also: &[(String, Vec<DVec3>)],
    chosen: &ModelReport,
    a: &[DVec3],
    delta: &[DVec3],
    side: Option<Side>,
    args: &FitMotionArgs,
) -> anyhow::Result<Vec<PhaseRow>> {
    also.iter()
        .map(|(name, c)| {
            let dc: Vec<DVec3> = a.iter().zip(c).map(|(p, q)| *q - *p).collect();
            let r = motion_models::evaluate_phase(
                chosen.model,
                &chosen.fit,
                a,
                delta,
                &dc,
                side,
                args.folds as usize,
                args.seed,
            )?;
            Ok(PhaseRow {
                file: name.clone(),
                mean_error_mm: r.in_sample.mean_mm,
                report: r,
            })
        })
        .collect()
}

/// Human-readable report.
pub fn text(outcome: &Outcome, args: &FitMotionArgs) -> String {
    match outcome {
        Outcome::Kernel(f) => kernel_text(f, args),
        Outcome::Points(r) => points_text(r, args),
        Outcome::Pair(r) => crate::pair_cmd::text(r),
    }
}

fn points_text(r: &PointsReport, args: &FitMotionArgs) -> String {
    let mut s = format!("frame: {}\n", r.frame_description);
    if let Some(w) = &r.frame_warning {
        s += &format!("WARNING: {w}\n");
    }
    if let Some(w) = &r.side_warning {
        s += &format!("WARNING: {w}\n");
    }
    s += &format!(
        "{} points; no-motion baseline {:.2} mm; {}-fold cross-validation (seed {})\n",
        r.lungs.iter().map(|l| l.points).sum::<usize>(),
        r.baseline_mean_mm,
        r.folds,
        r.seed
    );
    s += &format!(
        "{:<8} {:>14} {:>14} {:>13} {:>11} {:>8}  configuration\n",
        "model", "in-sample mm", "held-out mm", "held-out max", "parameters", "seconds"
    );
    for m in &r.models {
        let cfg = match m.config {
            motion_models::Config::Power => "eq. 6.14-6.16".to_string(),
            motion_models::Config::Poly { degree, lambda } => {
                format!("degree {degree}, ridge {lambda:.1e}")
            }
            motion_models::Config::Tps { s_z, lambda } => {
                format!("Z stretch {s_z}, smoothing {lambda:.1e} mm")
            }
        };
        s += &format!(
            "{:<8} {:>14.3} {:>14.3} {:>13.2} {:>11} {:>8.2}  {cfg}{}\n",
            m.model.name(),
            m.in_sample.mean_mm,
            m.cv.mean_mm,
            m.cv.max_mm,
            m.parameters,
            m.seconds,
            if m.model.name() == r.chosen {
                "  <- chosen"
            } else {
                ""
            }
        );
    }
    for l in &r.lungs {
        let c = &l.constants;
        s += &format!(
            "{} lung, {} points, power law: {}\n",
            l.lung.name(),
            l.points,
            power_law(c)
        );
    }
    for p in &r.also {
        s += &format!(
            "{}: scale {:.3}, in-sample {:.2} mm, held-out {:.2} mm (baseline {:.2} mm)\n",
            p.file,
            p.report.scale,
            p.report.in_sample.mean_mm,
            p.report.cv.mean_mm,
            p.report.baseline_mm
        );
    }
    if let Some(out) = &args.out {
        s += &format!("wrote {} (model {})\n", out.display(), r.chosen);
    }
    if let Some(p) = &args.plot {
        s += &format!("plot {}\n", p.display());
    }
    s
}

/// The power law's `c1 … c6` as the reports print them.
fn power_law(c: &[f64]) -> String {
    let [c1, c2, c3, c4, c5, c6] = [c[0], c[1], c[2], c[3], c[4], c[5]];
    format!("c1 {c1:.4} c2 {c2:.3} c3 {c3:.4} c4 {c4:.3} c5 {c5:.4} c6 {c6:.3}")
}

/// Human-readable report of the kernel-model (mesh and surface) modes.
fn kernel_text(f: &MotionFit, args: &FitMotionArgs) -> String {
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
            "{} lung, {} points: {}; c7 {:.3} c8 {:.3} c9 {:.3} ({force})\n  \
             error mean {:.2} mm, max {:.2} mm, rms {:.2} mm (no-motion baseline {:.2} mm)\n",
            l.lung.name(),
            l.points,
            power_law(c),
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
