//! `lungdyn fit-motion --exhale E --inhale I`: a breath-hold pair's own motion
//! (`lung_bake::patient_motion`), from masks (read as `mesh from-mask` reads them) or surfaces,
//! written as a motion file `bake --motion` reads. The figure printed is the error of that bake
//! driven to the inhale volume, beside no motion, uniform scaling and a held-out figure.

use std::path::{Path, PathBuf};

use anyhow::Context;
use lung_bake::mask::{self, volume::Axes, MaskOptions};
use lung_bake::patient_motion::{fit_pair, PairFit, PairOptions};
use lung_model::deform::MotionFile;
use lung_model::mesh::{io, Side, TriMesh};
use serde::Serialize;

use crate::motion_input::FitMotionArgs;
use lung_model::scene::SceneExt;

/// One lung of the pair.
#[derive(Debug, Serialize)]
pub struct PairLung {
    /// The fit, its errors and baselines.
    #[serde(flatten)]
    pub fit: PairFit,
    /// Vertices of the exhale surface fitted on.
    pub vertices: usize,
    /// Where each input's surface came from ("mask" or "surface").
    pub exhale_from: &'static str,
    /// Likewise.
    pub inhale_from: &'static str,
    /// The surfaces written (with --surfaces-out): exhale, moved, inhale aligned.
    pub surfaces: Option<[String; 3]>,
    /// Seconds: surfaces, fit.
    pub seconds: [f64; 2],
}

/// What the pair mode did.
#[derive(Debug, Serialize)]
pub struct PairReport {
    /// "pair".
    pub mode: &'static str,
    /// Exhale input.
    pub exhale: String,
    /// Inhale input.
    pub inhale: String,
    /// The lungs fitted.
    pub lungs: Vec<PairLung>,
    /// The motion file written.
    pub out: Option<String>,
    /// Warnings from reading the masks.
    pub warnings: Vec<String>,
}

/// One lung's surface from a mask or a surface file; warnings appended.
fn surface(
    path: &Path,
    side: Side,
    axes: Option<Axes>,
    args: &FitMotionArgs,
    warnings: &mut Vec<String>,
) -> anyhow::Result<(TriMesh, &'static str)> {
    if crate::mask_cmd::is_mask(path) {
        let mut o = MaskOptions::new(side);
        o.vertices = args.vertices;
        o.axes = axes;
        o.limits = args.input.limits(mask::read::MASK_LIMITS);
        let m = mask::mesh_from_mask(&[path.to_path_buf()], &o)
            .with_context(|| format!("{} ({} lung)", path.display(), side.name()))?;
        for w in m.warnings {
            warnings.push(format!("{} ({} lung): {w}", path.display(), side.name()));
        }
        return Ok((m.mesh, "mask"));
    }
    if args.axes.is_some() || args.inhale_axes.is_some() {
        anyhow::bail!(
            "--axes and --inhale-axes state a mask's voxel axes; {} is a surface (mm, --frame)",
            path.display()
        );
    }
    let frame = crate::motion_input::frame_of(args)?;
    let imported = crate::motion_input::import_scaled(path, &frame, &args.input)
        .with_context(|| format!("{}", path.display()))?;
    Ok((imported, "surface"))
}

/// Check every option and output before any work.
fn check(args: &FitMotionArgs) -> anyhow::Result<(PathBuf, PathBuf, PairOptions)> {
    let exhale = args.exhale.clone().unwrap_or_default();
    let inhale = args.inhale.clone().unwrap_or_default();
    let canonical = |p: &PathBuf| std::fs::canonicalize(p).unwrap_or_else(|_| p.clone());
    if canonical(&exhale) == canonical(&inhale) {
        anyhow::bail!(
            "--exhale and --inhale are the same file ({}): a breath-hold pair is two scans",
            exhale.display()
        );
    }
    for (flag, given) in [
        ("--also", !args.also.is_empty()),
        ("--plot", args.plot.is_some()),
        ("--surface", args.surface),
        ("--spacing", !args.spacing.is_empty()),
    ] {
        if given {
            anyhow::bail!("{flag} belongs to --from/--to (landmarks or meshes), not to a breath-hold pair (--exhale/--inhale)");
        }
    }
    if !(1_000..=200_000).contains(&args.vertices) {
        anyhow::bail!("--vertices {}: give 1,000 to 200,000", args.vertices);
    }
    if !(2..=10).contains(&args.folds) {
        anyhow::bail!(
            "--folds {} with --exhale/--inhale: give 2 to 10",
            args.folds
        );
    }
    let mut outputs = Vec::new();
    if let Some(path) = &args.out {
        outputs.push(crate::outputs::Output {
            flag: "--out",
            path,
            extensions: &["toml"],
        });
    }
    crate::outputs::check_all(&outputs, &[])?;
    if let Some(dir) = &args.surfaces_out {
        if dir.exists() && !dir.is_dir() {
            anyhow::bail!("--surfaces-out {}: not a folder", dir.display());
        }
    }
    let opts = PairOptions {
        force_degree: args.force_degree,
        field_degree: args.field_degree,
        force_centres: args.force_centres,
        force_local_ridge: args.force_local_ridge,
        normal_gate_deg: args.normal_gate,
        iterations: args.iterations,
        folds: args.folds as usize,
        seed: args.seed,
        ..PairOptions::default()
    };
    opts.validate()?;
    Ok((exhale, inhale, opts))
}

/// Fit each lung asked (both without --lung), write the motion file.
pub fn run(args: &FitMotionArgs) -> anyhow::Result<PairReport> {
    let (exhale, inhale, opts) = check(args)?;
    let ax = crate::mask_cmd::axes("--axes", &args.axes)?;
    let inhale_ax = crate::mask_cmd::axes("--inhale-axes", &args.inhale_axes)?.or(ax);
    let scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    let sides = match args.lung {
        Some(s) => vec![s],
        None => vec![Side::Right, Side::Left],
    };
    let mut warnings = Vec::new();
    let mut lungs = Vec::new();
    for side in sides {
        let clock = std::time::Instant::now();
        eprintln!(
            "lungdyn: {} lung: the exhale and inhale surfaces",
            side.name()
        );
        let (e, exhale_from) = surface(&exhale, side, ax, args, &mut warnings)?;
        let (i, inhale_from) = surface(&inhale, side, inhale_ax, args, &mut warnings)?;
        let made = clock.elapsed().as_secs_f64();
        let settings = scene.bake_settings(side)?;
        let name = side.name();
        let fit = fit_pair(side, &e, &i, &settings, &opts, &|stage| {
            eprintln!("lungdyn: {name} lung: {stage}")
        })?;
        let surfaces = match &args.surfaces_out {
            Some(dir) => {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("--surfaces-out {}", dir.display()))?;
                let paths = ["exhale", "moved", "inhale_aligned"]
                    .map(|w| dir.join(format!("{name}_{w}.ply")));
                io::write_mesh(&e, &paths[0])?;
                io::write_mesh(&fit.moved, &paths[1])?;
                io::write_mesh(&fit.inhale_aligned, &paths[2])?;
                Some(paths.map(|p| p.display().to_string()))
            }
            None => None,
        };
        lungs.push(PairLung {
            vertices: e.positions.len(),
            fit,
            exhale_from,
            inhale_from,
            surfaces,
            seconds: [made, clock.elapsed().as_secs_f64() - made],
        });
    }
    if let Some(out) = &args.out {
        write(out, &exhale, &inhale, &lungs)?;
    }
    Ok(PairReport {
        mode: "pair",
        exhale: exhale.display().to_string(),
        inhale: inhale.display().to_string(),
        lungs,
        out: args.out.as_ref().map(|p| p.display().to_string()),
        warnings,
    })
}

/// Write the motion file of `lungs` (a breath-hold pair's fits) atomically.
pub fn write(out: &Path, exhale: &Path, inhale: &Path, lungs: &[PairLung]) -> anyhow::Result<()> {
    let mut file = MotionFile {
        format: 2,
        left: None,
        right: None,
        frame: Some("body (lungdyn's frame, from the exhale image)".into()),
        chosen: Some("pair".into()),
        cv_mean_error_mm: None,
        left_field: None,
        right_field: None,
        left_force: None,
        right_force: None,
    };
    let mut notes = String::new();
    for l in lungs {
        let f = &l.fit;
        match f.side {
            Side::Left => {
                file.left_field = Some(f.direction.clone());
                file.left_force = Some(f.force.clone());
            }
            Side::Right => {
                file.right_field = Some(f.direction.clone());
                file.right_force = Some(f.force.clone());
            }
        }
        notes += &format!(
            "# {} lung ({} exhale vertices): in-sample MSSD {:.2} mm, held-out {}, no motion {:.2} mm, \
             uniform scaling {:.2} mm\n",
            f.side.name(),
            l.vertices,
            f.in_sample.mssd_mm,
            f.cross_validated
                .map_or("not measured".into(), |c| format!("{:.2} mm", c.mssd_mm)),
            f.no_motion.mssd_mm,
            f.uniform_scaling.mssd_mm
        );
    }
    file.cv_mean_error_mm = lungs
        .iter()
        .filter_map(|l| l.fit.cross_validated.map(|c| c.mssd_mm))
        .reduce(f64::max);
    let text = format!(
        "# lungdyn motion (fit-motion, a breath-hold pair: {} → {}).\n# Use: lungdyn bake --mesh \
         EXHALE_SURFACE --frame body --lung L --motion this.toml (the exhale surface the fit used: --surfaces-out writes it; `lungdyn patient` bakes its own)\n\
         {notes}{}",
        exhale.display(),
        inhale.display(),
        toml::to_string(&file)?
    );
    outfile::write_atomically(out, |w| {
        use std::io::Write;
        w.write_all(text.as_bytes())
    })?;
    Ok(())
}

/// The human-readable report.
pub fn text(r: &PairReport) -> String {
    let mut s = String::new();
    for w in &r.warnings {
        s += &format!("WARNING: {w}\n");
    }
    s += "breath-hold pair: errors are mean symmetric surface distances (MSSD) between the exhale lung \
          driven to the inhale volume and the inhale surface, after the alignment\n";
    for l in &r.lungs {
        let f = &l.fit;
        let a = &f.alignment;
        s += &format!(
            "{} lung: {:.0} ml → {:.0} ml ({:+.0} ml), {} vertices; inhale moved by ({:+.1}, {:+.1}, \
             {:+.1}) mm (apical cap {:.0} mm deep, {:.2} mm from the exhale surface)\n",
            f.side.name(),
            f.exhale_ml,
            f.inhale_ml,
            f.inhale_ml - f.exhale_ml,
            l.vertices,
            a.translation_mm[0],
            a.translation_mm[1],
            a.translation_mm[2],
            a.cap_depth_mm,
            a.cap_residual_mm
        );
        let row = |name: &str, d: &lung_bake::patient_motion::SurfaceDistance| {
            format!(
                "  {name:<34} MSSD {:5.2} mm  (exhale→inhale {:.2}, inhale→exhale {:.2}, p95 {:.2}, max {:.1})\n",
                d.mssd_mm, d.exhale_to_inhale_mm, d.inhale_to_exhale_mm, d.p95_mm, d.max_mm
            )
        };
        s += &row("no motion", &f.no_motion);
        s += &row("uniform scaling to the volume", &f.uniform_scaling);
        s += &row("fitted kernel (in-sample)", &f.in_sample);
        if let Some(c) = &f.cross_validated {
            s += &row(&format!("fitted, held out ({} folds)", f.options.folds), c);
        }
        s += &format!(
            "  displacement at the inhale volume: median {:.1} mm, 99th percentile {:.1} mm, largest {:.1} mm\n",
            f.displacement_mm[0], f.displacement_mm[1], f.displacement_mm[2]
        );
        if f.folds_at_inhale > 0 {
            s += &format!(
                "  WARNING: the fitted kernel folds the surface at the inhale volume ({} crossing triangle \
                 pairs): a surface pair cannot see sliding within the surface and the fit slid part of it \
                 (largest displacement {:.0} mm); the fold shows on screen near end-inspiration — try a \
                 lower --field-degree, or keep the population motion; it draws no fold up to \
                 {:+.0} ml (a tidal breath is ~250 ml a lung)\n",
                f.folds_at_inhale, f.displacement_mm[2], f.fold_free_ml
            );
        }
        s += &format!(
            "  surfaces {:.1} s, fit {:.1} s\n",
            l.seconds[0], l.seconds[1]
        );
    }
    if let Some(o) = &r.out {
        s += &format!("wrote {o}\n");
    }
    s
}
