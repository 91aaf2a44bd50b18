//! `lungdyn patient`: from a patient's CT lung masks to a scene that breathes with this patient's
//! lungs — both surfaces (`mesh from-mask`), both kernels (`bake`, keeping the lobes of the masks),
//! PV constants whose FRC is the exhale masks' lung volume, and a scene naming them, in one folder.

use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::DVec3;
use lung_bake::mask::{self, labels::Convention, volume::Axes, MaskOptions};
use lung_bake::unfitted::Choice;
use lung_model::mesh::{io, Side, TriMesh};
use lung_model::scene::SceneExt;
use serde::Serialize;

/// Options of `lungdyn patient`.
#[derive(Debug, Clone, clap::Args)]
#[command(
    after_help = "Example (a COPDgene breath-hold pair; its headers need --axes LPS, which the
error says when it is left out):
  lungdyn patient --exhale case_05_exp_mask.nii.gz --inhale case_05_insp_mask.nii.gz \\
      --axes LPS --out patient05
  lungdyn demo --scene patient05/scene.toml

OUT receives right.ply, left.ply (the surfaces, with their lobes), right.kernel, left.kernel,
pv.toml (the PV constants with FRC = the exhale lungs' volume), scene.toml and patient.json (what
was made and measured); with --inhale also right_inhale.ply and left_inhale.ply, and each lung's
motion fitted to the breath-hold pair (motion.toml; the kernels are baked with it, and the report
says how far the kernel at the inhale volume lies from the inhale surface beside no motion and
uniform scaling; --motion chooses: auto bakes the fit for each lung whose kernel draws a tidal
breath without a fold, else the breath-hold population of six patients where it draws one, else
the built-in motion; without --inhale, the last two in that order). The lungs are
moved by one translation, the same for both and said in scene.toml, so they sit where the
renderer draws the built-in lungs; their shape, size and relative placement are the patient's."
)]
pub struct PatientArgs {
    /// The exhale (or only) lung label image(s): NIfTI, NRRD or MetaImage, as `mesh from-mask`
    /// reads them (several files: one structure each, on one grid).
    #[arg(long, required = true, num_args = 1.., value_name = "MASK")]
    pub exhale: Vec<PathBuf>,
    /// The inhale label image(s) of the same patient (a breath-hold pair): meshed too, and their
    /// volumes reported beside the exhale ones.
    #[arg(long, num_args = 1.., value_name = "MASK")]
    pub inhale: Vec<PathBuf>,
    /// Output folder (created; an existing scene.toml there is kept unless --force).
    #[arg(long)]
    pub out: PathBuf,
    /// The voxel axes' directions of the exhale image(s), replacing the header's (see `mesh
    /// from-mask --help`); also used for --inhale unless --inhale-axes is given.
    #[arg(long, value_name = "XYZ")]
    pub axes: Option<String>,
    /// The voxel axes of the inhale image(s).
    #[arg(long, value_name = "XYZ")]
    pub inhale_axes: Option<String>,
    /// The label convention (detected when omitted).
    #[arg(long, value_parser = Convention::ALL.map(|c| c.name()))]
    pub convention: Option<String>,
    /// The right lung's label value(s), when the convention does not say.
    #[arg(long, value_delimiter = ',', value_name = "N[,N...]")]
    pub right_label: Option<Vec<u16>>,
    /// The left lung's label value(s), when the convention does not say.
    #[arg(long, value_delimiter = ',', value_name = "N[,N...]")]
    pub left_label: Option<Vec<u16>>,
    /// Vertices per lung, about.
    #[arg(long, default_value_t = 20_000)]
    pub vertices: usize,
    /// The motion baked: "auto" (with --inhale, the motion fitted to this patient's breath-hold
    /// pair, written to OUT/motion.toml, for each lung whose fitted kernel draws a tidal breath
    /// without a fold; else the breath-hold population of six patients where it draws one without
    /// a fold; else the built-in population), "fitted" (always the fit), "breath-hold" (the
    /// breath-hold population, no fit) or "population" (the built-in motion, no fit).
    #[arg(long, value_enum, default_value_t = MotionChoice::Auto)]
    pub motion: MotionChoice,
    /// Keep the image's own coordinates instead of moving the lungs to where the built-in ones
    /// are drawn (for a workstation registered to the CT's frame).
    #[arg(long)]
    pub keep_origin: bool,
    /// Replace an existing scene in OUT.
    #[arg(long)]
    pub force: bool,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Print one JSON object on stdout (also written to OUT/patient.json).
    #[arg(long)]
    pub json: bool,
}

/// `patient --motion`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum MotionChoice {
    /// The fit, else the breath-hold population, each where it draws a tidal breath without a
    /// fold; else the built-in (whose folds are not checked).
    Auto,
    /// The fit, always.
    Fitted,
    /// The breath-hold population of six patients, no fit.
    BreathHold,
    /// The built-in population motion, no fit.
    Population,
}

/// One lung of the patient.
#[derive(Debug, Serialize)]
pub struct PatientLung {
    /// Side.
    pub lung: &'static str,
    /// Surface file.
    pub mesh: String,
    /// Kernel file.
    pub kernel: String,
    /// Vertices.
    pub vertices: usize,
    /// The surface's volume, ml.
    pub volume_ml: f64,
    /// The mask's voxel volume as labelled, ml.
    pub mask_volume_ml: f64,
    /// Tunnels in the mask, and the closing that closed them, mm.
    pub genus_before: i64,
    /// Closing radius, mm.
    pub closing_mm: f64,
    /// Mean distance from the surface's vertices to the mask's boundary, mm.
    pub distance_to_mask_mm: f64,
    /// "labels" or "planes".
    pub lobes_from: &'static str,
    /// How this side was told from the other.
    pub sides_from: &'static str,
    /// Seconds to make the surface and to bake it.
    pub seconds: [f64; 2],
    /// The inhale mask's lung volume, ml (with --inhale).
    pub inhale_volume_ml: Option<f64>,
    /// The motion baked: "fitted to the breath-hold pair", "breath-hold population" or "built-in
    /// population", with why where the first choice folded.
    pub motion: &'static str,
    /// This lung's share of the default scene's tidal breath (by exhale volume), ml.
    pub tidal_share_ml: f64,
    /// Where the breath-hold population was tried: how far above the exhale volume its kernel
    /// draws no fold, ml (to 1/768 of the share; the share itself when it does not fold within it).
    pub breath_hold_fold_free_ml: Option<f64>,
    /// With the fitted motion: the baked kernel driven to the inhale volume against the inhale
    /// surface (MSSD, mm), beside no motion and uniform scaling (`fit-motion` gives held-out
    /// figures too).
    pub motion_mssd_mm: Option<MotionFigures>,
}

/// How far the fitted kernel, and the two baselines, land from the inhale surface (MSSD, mm).
#[derive(Debug, Serialize, Clone, Copy)]
pub struct MotionFigures {
    /// The fitted kernel driven to the inhale volume.
    pub fitted: f64,
    /// Leaving the exhale lung where it is.
    pub no_motion: f64,
    /// Scaling it about its centroid to the inhale volume.
    pub uniform_scaling: f64,
    /// Crossing triangle pairs of the fitted kernel's surface at the inhale volume (0: no fold).
    pub folds_at_inhale: usize,
    /// The largest volume change (ml above FRC) the kernel draws without a fold.
    pub fold_free_ml: f64,
    /// This lung's share of the default breath's tidal volume, ml (the fit is baked by "auto"
    /// only when it draws that without a fold).
    pub tidal_share_ml: f64,
}

/// What `lungdyn patient` made.
#[derive(Debug, Serialize)]
pub struct PatientSummary {
    /// The scene to run.
    pub scene: String,
    /// The exhale masks.
    pub exhale: Vec<String>,
    /// The inhale masks.
    pub inhale: Vec<String>,
    /// Right, then left.
    pub lungs: Vec<PatientLung>,
    /// FRC written to pv.toml: the exhale lungs' volume, ml.
    pub frc_ml: f64,
    /// The inhale lungs' volume, ml (with --inhale).
    pub inhale_ml: Option<f64>,
    /// The translation applied to both lungs (image frame → drawn position), mm.
    pub translation_mm: [f64; 3],
    /// Warnings from reading the masks.
    pub warnings: Vec<String>,
    /// The command that runs it.
    pub run: String,
}

fn mask_options(args: &PatientArgs, side: Side, axes: Option<Axes>) -> anyhow::Result<MaskOptions> {
    let mut o = MaskOptions::new(side);
    o.vertices = args.vertices;
    o.axes = axes;
    o.limits = args.input.limits(mask::read::MASK_LIMITS);
    o.convention = crate::mask_cmd::parsed(args.convention.as_deref())?;
    o.labels = match side {
        Side::Right => args.right_label.clone(),
        Side::Left => args.left_label.clone(),
    };
    Ok(o)
}

fn translate(mesh: &mut TriMesh, t: DVec3) {
    for p in &mut mesh.positions {
        *p = [
            (p[0] as f64 + t.x) as f32,
            (p[1] as f64 + t.y) as f32,
            (p[2] as f64 + t.z) as f32,
        ];
    }
}

/// The centre of the joint bounding box of `meshes`.
fn joint_centre<'a>(meshes: impl IntoIterator<Item = &'a TriMesh>) -> DVec3 {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for m in meshes {
        let b = m.aabb();
        lo = lo.min(DVec3::from(b.min.map(|v| v as f64)));
        hi = hi.max(DVec3::from(b.max.map(|v| v as f64)));
    }
    (lo + hi) * 0.5
}

/// Bake one lung keeping its lobes, with the motion fitted to its pair where there is one, else the
/// motion `unfitted` chooses for its tidal share (ml); seconds taken, and the motion chosen.
fn bake_lung(
    side: Side,
    m: &mask::FromMask,
    kernel_path: &Path,
    fit: Option<&lung_bake::patient_motion::PairFit>,
    unfitted: (Choice, f64),
) -> anyhow::Result<(f64, Option<(lung_bake::unfitted::Baked, Option<f64>)>)> {
    eprintln!(
        "lungdyn: baking the {} lung ({} vertices) into {}",
        side.name(),
        m.mesh.positions.len(),
        kernel_path.display()
    );
    let t = std::time::Instant::now();
    let bar = crate::prepare::rows_bar(m.mesh.positions.len(), crate::prepare::ROWS_BAR);
    let rows = |rows: usize| bar.inc(rows as u64);
    let what = || format!("baking the {} lung", side.name());
    let (mut kernel, baked) = if let Some(f) = fit {
        let mut settings = lung_model::kernel::BakeSettings::default_for(side);
        settings.force_field = Some(f.force.clone());
        settings.direction_field = Some(f.direction.clone());
        let kernel = lung_bake::kernel::bake(side, m.mesh.clone(), &settings, &rows);
        (kernel.with_context(what)?, None)
    } else {
        // Each step said starts a bake (the built-in one after the breath-hold one that folded).
        let say = |s: &str| {
            bar.suspend(|| eprintln!("lungdyn: {s}"));
            bar.set_position(0);
        };
        let u = lung_bake::unfitted::bake(side, &m.mesh, unfitted.1, unfitted.0, &rows, &say);
        let u = u.with_context(what)?;
        (u.kernel, Some((u.motion, u.breath_hold_fold_free_ml)))
    };
    bar.finish_and_clear();
    kernel.lobes = Some(m.lobes.clone());
    kernel.write(kernel_path)?;
    Ok((t.elapsed().as_secs_f64(), baked))
}

/// What `patient` reports of one lung.
fn lung_summary(
    side: Side,
    m: &mask::FromMask,
    paths: [PathBuf; 2],
    seconds: [f64; 2],
    inhale_volume_ml: Option<f64>,
    fit: Option<&lung_bake::patient_motion::PairFit>,
) -> PatientLung {
    PatientLung {
        lung: side.name(),
        mesh: paths[0].display().to_string(),
        kernel: paths[1].display().to_string(),
        vertices: m.mesh.positions.len(),
        volume_ml: m.mesh.enclosed_volume_ml(),
        mask_volume_ml: m.mask_volume_ml,
        genus_before: m.genus_before,
        closing_mm: m.closing_mm,
        distance_to_mask_mm: m.distance_to_mask.mean_mm,
        lobes_from: m.lobes_from,
        sides_from: m.sides_from,
        seconds,
        inhale_volume_ml,
        motion: match fit {
            Some(f) if f.options.force_centres < lung_bake::patient_motion::PairOptions::default().force_centres => "fitted, the polynomial force alone (with local terms it folded within a tidal breath)",
            Some(_) => "fitted to the breath-hold pair",
            None => "built-in population",
        },
        tidal_share_ml: 0.0,
        breath_hold_fold_free_ml: None,
        motion_mssd_mm: fit.map(|f| MotionFigures {
            fitted: f.in_sample.mssd_mm,
            no_motion: f.no_motion.mssd_mm,
            uniform_scaling: f.uniform_scaling.mssd_mm,
            folds_at_inhale: f.folds_at_inhale,
            fold_free_ml: f.fold_free_ml,
            tidal_share_ml: 0.0,
        }),
    }
}

/// With an inhale pair (and without --motion population or breath-hold): each lung's motion fitted to it
/// (`lung_bake::patient_motion`, no held-out folds here: `fit-motion` measures those), written to
/// OUT/motion.toml.
fn fit_motion(
    args: &PatientArgs,
    made: &[(Side, mask::FromMask, f64)],
    inhale: &[(Side, TriMesh, Vec<u8>)],
    share: &dyn Fn(&TriMesh) -> f64,
) -> anyhow::Result<Vec<crate::pair_cmd::PairLung>> {
    let no_fit = matches!(
        args.motion,
        MotionChoice::Population | MotionChoice::BreathHold
    );
    if inhale.is_empty() || no_fit {
        return Ok(Vec::new());
    }
    let opts = lung_bake::patient_motion::PairOptions {
        folds: 0,
        ..Default::default()
    };
    let mut lungs = Vec::new();
    for (side, m, _) in made {
        let Some((_, target, _)) = inhale.iter().find(|(s, _, _)| s == side) else {
            continue;
        };
        let t = std::time::Instant::now();
        let name = side.name();
        let settings = lung_model::kernel::BakeSettings::default_for(*side);
        // "auto" asks for a fit that draws this lung's tidal breath without a fold.
        let breath_ml = (args.motion == MotionChoice::Auto).then(|| share(&m.mesh));
        let fit = lung_bake::patient_motion::fit_pair_for_breath(
            *side,
            &m.mesh,
            target,
            &settings,
            &opts,
            breath_ml.unwrap_or(0.0),
            &|stage| eprintln!("lungdyn: {name} lung's motion: {stage}"),
        )
        .with_context(|| format!("fitting the {name} lung's motion to the breath-hold pair"))?;
        lungs.push(crate::pair_cmd::PairLung {
            vertices: m.mesh.positions.len(),
            fit,
            exhale_from: "mask",
            inhale_from: "mask",
            surfaces: None,
            seconds: [0.0, t.elapsed().as_secs_f64()],
        });
    }
    crate::pair_cmd::write(
        &args.out.join("motion.toml"),
        &args.exhale[0],
        &args.inhale[0],
        &lungs,
    )?;
    Ok(lungs)
}

/// Write pv.toml (the default preset's curves with this patient's FRC) and the scene naming it
/// and the kernels; then load the scene and check both kernels as the processes will.
fn write_scene(
    args: &PatientArgs,
    scene_path: &Path,
    frc_ml: f64,
    volumes: [f64; 2],
    translation: DVec3,
    lungs: &[PatientLung],
) -> anyhow::Result<()> {
    // PV constants: the default preset's curve with this patient's FRC.
    let preset = lung_model::pv::preset(lung_model::pv::DEFAULT_PRESET)?;
    let mut boundary = preset.boundary;
    boundary.frc_ml = frc_ml;
    boundary.check_plausible().map_err(|e| {
        anyhow::anyhow!("the exhale lungs' volume ({frc_ml:.0} ml) is not a plausible FRC: {e}")
    })?;
    let pv = lung_model::pv::files::PvConstantsFile {
        format: lung_model::pv::files::CONSTANTS_FORMAT,
        source: format!(
            "lungdyn patient: the {} preset's curves, FRC = the exhale masks' lung volume ({})",
            preset.name,
            names(&args.exhale).join(" ")
        ),
        boundary,
        inhale: preset.inhale,
        exhale: preset.exhale,
    };
    pv.save(&args.out.join("pv.toml"))?;
    let scene_text = format!(
        "# A patient's lungs, made by `lungdyn patient` from {exhale}{inhale}.\n\
         # FRC {frc_ml:.0} ml = the exhale lungs' volume (right {r:.0} ml, left {l:.0} ml); the\n\
         # breath is the {preset} preset's curve with that FRC (pv.toml). Both lungs were moved by\n\
         # ({tx:.1}, {ty:.1}, {tz:.1}) mm from the image's frame (body frame: +X left, +Y anterior,\n\
         # +Z superior) so they sit where the built-in lungs are drawn.\n\
         # {motion}\n\
         # Run: lungdyn demo --scene {scene}\n\
         [pv]\n\
         constants = \"pv.toml\"\n\n\
         [lungs.kernels]\n\
         right = \"right.kernel\"\n\
         left = \"left.kernel\"\n",
        exhale = names(&args.exhale).join(" "),
        inhale = if args.inhale.is_empty() {
            String::new()
        } else {
            format!(" (inhale: {})", names(&args.inhale).join(" "))
        },
        r = volumes[0],
        l = volumes[1],
        preset = preset.name,
        tx = translation.x,
        ty = translation.y,
        tz = translation.z,
        scene = scene_path.display(),
        motion = format!(
            "Motion baked: right lung {}, left lung {} (the fit, where there is one: motion.toml).",
            lungs[0].motion, lungs[1].motion
        ),
    );
    outfile::write_atomically(&scene_path, |w| {
        use std::io::Write;
        w.write_all(scene_text.as_bytes())
    })?;
    // What the engine and renderer will check at start: the scene and both kernels.
    let scene = lung_model::scene::Scene::load(&scene_path)?;
    for side in [Side::Right, Side::Left] {
        crate::prepare::check_named_kernel(&scene, side).with_context(|| {
            format!(
                "the {} lung's kernel in {}",
                side.name(),
                scene_path.display()
            )
        })?;
    }
    Ok(())
}

/// Make the surfaces, kernels, PV constants and scene.
pub fn run(args: &PatientArgs) -> anyhow::Result<PatientSummary> {
    let scene_path = args.out.join("scene.toml");
    if scene_path.exists() && !args.force {
        anyhow::bail!(
            "{} exists: choose another --out, or pass --force to replace it",
            scene_path.display()
        );
    }
    if args.motion == MotionChoice::Fitted && args.inhale.is_empty() {
        anyhow::bail!("--motion fitted needs --inhale: a breath-hold pair to fit the motion to");
    }
    if !(1_000..=400_000).contains(&args.vertices) {
        anyhow::bail!(
            "--vertices {}: give 1,000 to 400,000 per lung",
            args.vertices
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let exhale_axes = crate::mask_cmd::axes("--axes", &args.axes)?;
    let inhale_axes = crate::mask_cmd::axes("--inhale-axes", &args.inhale_axes)?.or(exhale_axes);
    let mut warnings = Vec::new();
    let mut made = Vec::new();
    for side in [Side::Right, Side::Left] {
        eprintln!(
            "lungdyn: the {} lung's surface from {} …",
            side.name(),
            args.exhale[0].display()
        );
        let t = std::time::Instant::now();
        let m = mask::mesh_from_mask(&args.exhale, &mask_options(args, side, exhale_axes)?)?;
        warnings.extend(
            m.warnings
                .iter()
                .map(|w| format!("exhale {}: {w}", side.name())),
        );
        made.push((side, m, t.elapsed().as_secs_f64()));
    }
    let mut inhale_meshes = inhale_surfaces(args, inhale_axes, &mut warnings)?;
    let inhale_volumes: Vec<f64> = inhale_meshes
        .iter()
        .map(|(_, m, _)| m.enclosed_volume_ml())
        .collect();
    // One translation for both lungs (and the inhale ones, each pair about its own centre: the
    // two scans are not registered to each other).
    let translation = if args.keep_origin {
        DVec3::ZERO
    } else {
        builtin_centre()? - joint_centre(made.iter().map(|(_, m, _)| &m.mesh))
    };
    for (_, m, _) in &mut made {
        translate(&mut m.mesh, translation);
    }
    if !inhale_meshes.is_empty() && !args.keep_origin {
        let t = builtin_centre()? - joint_centre(inhale_meshes.iter().map(|(_, m, _)| m));
        for (_, m, _) in &mut inhale_meshes {
            translate(m, t);
        }
    }
    for (side, mesh, lobes) in &inhale_meshes {
        io::write_mesh_with_lobes(
            mesh,
            lobes,
            &args.out.join(format!("{}_inhale.ply", side.name())),
        )?;
    }
    // A lung's share of the default breath's tidal volume: where the fitted kernel folds before
    // it (a fold on screen at every breath), "auto" bakes the breath-hold population, or the
    // built-in motion where that folds too.
    let tv_ml = lung_model::pv::preset(lung_model::pv::DEFAULT_PRESET)?
        .boundary
        .tv_ml;
    let exhale_total: f64 = made
        .iter()
        .map(|(_, m, _)| m.mesh.enclosed_volume_ml())
        .sum();
    let share = |m: &TriMesh| tv_ml * m.enclosed_volume_ml() / exhale_total;
    let fits = fit_motion(args, &made, &inhale_meshes, &share)?;
    let mut lungs = Vec::new();
    for (k, (side, m, mesh_seconds)) in made.iter().enumerate() {
        let mesh_path = args.out.join(format!("{}.ply", side.name()));
        io::write_mesh_with_lobes(&m.mesh, &m.lobes, &mesh_path)?;
        let kernel_path = args.out.join(format!("{}.kernel", side.name()));
        let fit = fits.iter().find(|l| l.fit.side == *side).map(|l| &l.fit);
        let tidal_share_ml = share(&m.mesh);
        let used = fit.filter(|f| {
            args.motion == MotionChoice::Fitted
                || lung_bake::patient_motion::draws_breath(f, tidal_share_ml)
        });
        let unfitted = match args.motion {
            MotionChoice::Population => Choice::Builtin,
            MotionChoice::BreathHold => Choice::BreathHold,
            _ => Choice::Auto,
        };
        let (bake_seconds, baked) =
            bake_lung(*side, m, &kernel_path, used, (unfitted, tidal_share_ml))?;
        let mut lung = lung_summary(
            *side,
            m,
            [mesh_path, kernel_path],
            [*mesh_seconds, bake_seconds],
            inhale_volumes.get(k).copied(),
            fit,
        );
        lung.tidal_share_ml = tidal_share_ml;
        if let Some((b, free)) = baked {
            lung.motion = b.describe(fit.is_some());
            lung.breath_hold_fold_free_ml = free;
        }
        if let Some(f) = lung.motion_mssd_mm.as_mut() {
            f.tidal_share_ml = tidal_share_ml;
        }
        lungs.push(lung);
    }
    let frc_ml: f64 = lungs.iter().map(|l| l.volume_ml).sum();
    write_scene(
        args,
        &scene_path,
        frc_ml,
        [lungs[0].volume_ml, lungs[1].volume_ml],
        translation,
        &lungs,
    )?;
    let summary = PatientSummary {
        scene: scene_path.display().to_string(),
        exhale: names(&args.exhale),
        inhale: names(&args.inhale),
        lungs,
        frc_ml,
        inhale_ml: (!inhale_volumes.is_empty()).then(|| inhale_volumes.iter().sum()),
        translation_mm: translation.to_array(),
        warnings,
        run: format!("lungdyn demo --scene {}", scene_path.display()),
    };
    let json = serde_json::to_string_pretty(&summary)?;
    outfile::write_atomically(&args.out.join("patient.json"), |w| {
        use std::io::Write;
        w.write_all(json.as_bytes())
    })?;
    Ok(summary)
}

/// The paths as text.
fn names(paths: &[PathBuf]) -> Vec<String> {
    paths.iter().map(|p| p.display().to_string()).collect()
}

/// Both lungs' inhale surfaces (none without --inhale), their warnings added to `warnings`.
fn inhale_surfaces(
    args: &PatientArgs,
    axes: Option<Axes>,
    warnings: &mut Vec<String>,
) -> anyhow::Result<Vec<(Side, lung_model::mesh::TriMesh, Vec<u8>)>> {
    let mut meshes = Vec::new();
    if args.inhale.is_empty() {
        return Ok(meshes);
    }
    for side in [Side::Right, Side::Left] {
        eprintln!(
            "lungdyn: the {} lung's inhale surface from {} …",
            side.name(),
            args.inhale[0].display()
        );
        let m = mask::mesh_from_mask(&args.inhale, &mask_options(args, side, axes)?)?;
        warnings.extend(
            m.warnings
                .iter()
                .map(|w| format!("inhale {}: {w}", side.name())),
        );
        meshes.push((side, m.mesh, m.lobes));
    }
    Ok(meshes)
}

/// The joint centre of the built-in lungs: where the renderer draws lungs.
fn builtin_centre() -> anyhow::Result<DVec3> {
    Ok(joint_centre(&[
        lung_model::mesh::anatomy::lung(Side::Right, 2_000)?,
        lung_model::mesh::anatomy::lung(Side::Left, 2_000)?,
    ]))
}

/// The summary for a person.
pub fn text(s: &PatientSummary) -> String {
    let mut out = String::new();
    for l in &s.lungs {
        out.push_str(&format!(
            "{} lung: {} vertices, {:.0} ml (mask {:.0} ml){}, {} tunnel(s) closed at {} mm, {:.2} mm from the mask's boundary, lobes from {}, sides from {}; surface {:.1} s, bake {:.1} s\n",
            l.lung,
            l.vertices,
            l.volume_ml,
            l.mask_volume_ml,
            l.inhale_volume_ml.map_or(String::new(), |v| format!(", inhale {v:.0} ml")),
            l.genus_before,
            l.closing_mm,
            l.distance_to_mask_mm,
            l.lobes_from,
            l.sides_from,
            l.seconds[0],
            l.seconds[1],
        ));
        if let Some(m) = &l.motion_mssd_mm {
            out.push_str(&format!(
                "  motion fitted to the breath-hold pair: the kernel at the inhale volume lies {:.2} mm (MSSD) \
                 from the inhale surface; no motion {:.2} mm, uniform scaling {:.2} mm\n",
                m.fitted, m.no_motion, m.uniform_scaling
            ));
            if m.folds_at_inhale > 0 {
                out.push_str(&format!(
                    "  WARNING: that kernel folds the surface at the inhale volume ({} crossing triangle pairs); \
                     it draws no fold up to {:+.0} ml above FRC (this lung's share of a tidal breath is \
                     about {:.0} ml)\n",
                    m.folds_at_inhale, m.fold_free_ml, m.tidal_share_ml
                ));
            }
        }
        out.push_str(&format!("  motion baked: {}\n", l.motion));
    }
    out.push_str(&format!(
        "FRC {:.0} ml (the exhale lungs){}; lungs moved by ({:.1}, {:.1}, {:.1}) mm\nwrote {}\nrun it: {}\n",
        s.frc_ml,
        s.inhale_ml.map_or(String::new(), |v| format!(", inhale {v:.0} ml (a breath-hold pair: {:.0} ml apart)", v - s.frc_ml)),
        s.translation_mm[0],
        s.translation_mm[1],
        s.translation_mm[2],
        s.scene,
        s.run
    ));
    out
}
