//! `lungdyn bake` and `lungdyn kernel inspect`: a patient lung mesh → a kernel file, and what is in one.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use lung_bake::kernel;
use lung_model::kernel::KernelFile;
use lung_model::mesh::Side;
use lung_model::scene::SceneExt;
use serde::Serialize;

/// Options of `lungdyn bake`.
#[derive(Debug, Clone, clap::Args)]
pub struct BakeArgs {
    /// Lung surface: .obj, .ply or .stl (checked and repaired as by `lungdyn mesh check`).
    #[arg(long)]
    pub mesh: PathBuf,
    /// Which lung the mesh is (sets the direction model's lateral axis): left or right.
    #[arg(long)]
    pub lung: Side,
    /// Unit of the mesh file's coordinates.
    #[arg(long, default_value = "mm", value_parser = ["mm", "cm", "m"])]
    pub units: String,
    /// Keep connected shell N (1 = the largest) of a file holding several.
    #[arg(long, value_name = "N")]
    pub component: Option<usize>,
    /// Frame of the mesh file's coordinates.
    #[command(flatten)]
    pub frame: crate::mesh_cmd::FrameArgs,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input: crate::input_args::InputArgs,
    /// Scene whose [lungs] elasticity, transfer_tolerance and motion are used (defaults otherwise).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Motion constants from `lungdyn fit-motion` (overrides the scene's; the `--directions` preset
    /// otherwise).
    #[arg(long, conflicts_with = "directions")]
    pub motion: Option<PathBuf>,
    /// The motion without a motion file (overrides the scene's `[lungs] directions`): "population"
    /// (diaphragm-driven, matched to DIR-Lab 4DCT on the generated lungs; the default), "breath-hold"
    /// (the population of six real breath-hold pairs' fits: closer on a patient's lung, `lungdyn
    /// patient`'s choice where it does not fold) or "seed" (Table 6.1). See EQUATIONS.md §2.4.
    #[arg(long, value_parser = ["population", "breath-hold", "seed"])]
    pub directions: Option<String>,
    /// Length in mm over which the elastostatic amplitude is made smooth on the surface so the
    /// deformed lung does not fold (overrides the scene's [lungs] amplitude_smoothing_mm; default
    /// 10; 0 = the seed's unsmoothed reading). See EQUATIONS.md §2.4.
    #[arg(long, value_name = "MM")]
    pub smoothing_mm: Option<f64>,
    /// Pitcher tolerance for a unit force (overrides the scene's; default 1e-5). Smaller: more
    /// non-zeros per row, less truncated force, longer bake.
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// Spherical-harmonic bands to store for the "sh" mode (n² coefficients per vertex; 4 = the
    /// seed's 16 coefficients; 0 = none, the basis and precomputed modes need none). Overrides the
    /// scene's [lungs] bands.
    #[arg(long, value_name = "N")]
    pub bands: Option<u32>,
    /// Error budget in mm (RMS displacement against eq. 7.1 at the reference volume over the
    /// orientation set): keep the fewest bands, up to --bands (8 when not given), that meet it.
    #[arg(long, value_name = "MM")]
    pub max_error_mm: Option<f64>,
    /// Output kernel file (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Print one JSON object on stdout (the progress bar stays on stderr).
    #[arg(long)]
    pub json: bool,
}

/// What a bake did.
#[derive(Debug, Serialize)]
pub struct BakeSummary {
    /// Output path.
    pub path: String,
    /// Lung.
    pub lung: String,
    /// Vertices (mass nodes).
    pub vertices: u64,
    /// Spring nodes (edges).
    pub spring_nodes: u64,
    /// Stored transfer non-zeros.
    pub nnz: u64,
    /// Mean non-zeros per transfer row.
    pub mean_row_nnz: f64,
    /// Largest row.
    pub max_row_nnz: u64,
    /// Mean force per unit row left in pitchers below the tolerance.
    pub truncated_force: f64,
    /// Largest truncated force of a row.
    pub truncated_force_max: f64,
    /// Mean share of a row's force caught by mass nodes.
    pub mass_caught: f64,
    /// Worst |caught + truncated − applied| of a row.
    pub conservation_error_max: f64,
    /// Tolerance used.
    pub tolerance: f64,
    /// Enclosed volume of the mesh, ml.
    pub volume_ml: f64,
    /// Largest unit displacement, mm per unit volume.
    pub max_unit_displacement_mm: f64,
    /// Kernel file size, bytes.
    pub file_bytes: u64,
    /// Wall time of import + bake + write, seconds.
    pub seconds: f64,
    /// Peak resident memory of this process, MiB (Linux VmHWM; 0 when unknown).
    pub peak_rss_mib: f64,
    /// The warning when `--lung` disagrees with the geometry.
    pub side_warning: Option<String>,
    /// The warning when the mesh's anterior/posterior or superior/inferior look flipped.
    pub frame_warning: Option<String>,
    /// Where the kernel's lobe codes came from: "mesh" (the file's own `lobe` property, e.g. from
    /// the patient's lobe labels by `mesh from-mask`) or "planes" (the fissure planes).
    pub lobes_from: &'static str,
    /// Spherical-harmonic bands stored (0: none).
    pub sh_bands: u32,
    /// Least-squares scale of eq. 7.7 against eq. 7.1.
    pub alpha: Option<f64>,
    /// RMS displacement error of the SH mode against eq. 7.1, % of the largest displacement.
    pub sh_rms_percent: Option<f64>,
    /// RMS displacement error of the SH mode against eq. 7.1, mm.
    pub sh_rms_mm: Option<f64>,
    /// Largest displacement error of the SH mode against eq. 7.1, mm.
    pub sh_max_mm: Option<f64>,
    /// Largest displacement change from holding the SH coefficients in 16 bits at run time, mm
    /// (included in the errors above, which are of what is drawn).
    pub sh_quantisation_max_mm: Option<f64>,
    /// The error budget, when one was given, and whether the stored bands meet it.
    pub sh_budget_mm: Option<f64>,
    /// Whether the budget was met (absent without one).
    pub sh_budget_met: Option<bool>,
    /// Which bands were kept for the budget and why (absent without one).
    pub sh_budget_reason: Option<String>,
    /// Vertices touching a triangle whose projection from the centroid folds over.
    pub foldover_nodes: u64,
    /// Largest displacement difference of the basis mode against eq. 7.1 (round-off), mm.
    pub basis_max_error_mm: f64,
    /// Volume change above FRC at which the errors are taken, ml.
    pub reference_delta_ml: f64,
    /// Orientations the errors are taken over.
    pub orientations: u32,
    /// The tumour baked in (`--scene` with a `[disease] kind = "tumour"` on this lung): what the
    /// kernel change did and the centre's motion per unit scale.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tumour: Option<lung_model::kernel::TumourMeta>,
    /// The volumes the kernel draws without its surface crossing itself (the engine marks frames
    /// drawn outside them).
    pub fold_free: Option<lung_model::kernel::FoldFreeMeta>,
}

/// Peak resident set size of this process in MiB (Linux), 0 elsewhere.
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map(|kb| kb / 1024.0)
        .unwrap_or(0.0)
}

/// Import, bake, write.
pub fn bake(args: &BakeArgs) -> anyhow::Result<BakeSummary> {
    let start = Instant::now();
    let side = args.lung;
    if args.out.extension().and_then(|e| e.to_str()) != Some("kernel") {
        anyhow::bail!("{}: the output must end in .kernel", args.out.display());
    }
    // A device, FIFO or folder is refused now, not after the bake.
    outfile::check(&args.out)?;
    let settings = settings(args)?;
    let (imported, side_warning, frame_warning) = crate::mesh_cmd::import_lung(
        &args.mesh,
        &args.units,
        args.component,
        &args.frame,
        &args.input,
        Some(side),
    )?;
    // The mesh's own lobes (a PLY's `lobe` property) are kept, when they are all this lung's.
    let own_lobes = imported.lobes.clone();
    if let Some(codes) = &own_lobes {
        use lung_model::mesh::lobes::Lobe;
        if let Some((i, &c)) = codes
            .iter()
            .enumerate()
            .find(|&(_, &c)| c != 0 && Lobe::from_code(c).and_then(|l| l.side()) != Some(side))
        {
            anyhow::bail!(
                "{}: vertex {i} carries lobe code {c} ({}), not a lobe of the {} lung: is --lung right?",
                args.mesh.display(),
                Lobe::from_code(c).map_or("unknown", |l| l.name()),
                side.name()
            );
        }
    }
    let template = "baking {msg} [{bar:40}] {pos}/{len} rows, {per_sec}, eta {eta}";
    let bar = crate::prepare::rows_bar(imported.mesh.positions.len(), template);
    bar.set_message(format!("{} lung", side.name()));
    let mut k = kernel::bake(side, imported.mesh, &settings, &|rows| bar.inc(rows as u64))
        .with_context(|| format!("baking {}", args.mesh.display()))?;
    let lobes_from = if own_lobes.is_some() {
        "mesh"
    } else {
        "planes"
    };
    k.lobes = own_lobes;
    bar.finish_and_clear();
    let file_bytes = k.write(&args.out)?;
    let max_u = k
        .unit_displacement
        .iter()
        .map(|u| (u[0] as f64).hypot(u[1] as f64).hypot(u[2] as f64))
        .fold(0.0, f64::max);
    let s = &k.meta.transfer;
    let sh = k.meta.sh.as_ref();
    let orientation = k.meta.orientation.as_ref();
    Ok(BakeSummary {
        path: args.out.display().to_string(),
        lung: side.name().into(),
        vertices: k.meta.vertices,
        spring_nodes: k.meta.spring_nodes,
        nnz: k.meta.nnz,
        mean_row_nnz: s.mean_row_nnz,
        max_row_nnz: s.max_row_nnz,
        truncated_force: s.truncated_force_mean,
        truncated_force_max: s.truncated_force_max,
        mass_caught: s.mass_caught_mean,
        conservation_error_max: s.conservation_error_max,
        tolerance: s.tolerance,
        volume_ml: k.meta.start_volume_ml,
        max_unit_displacement_mm: max_u,
        file_bytes,
        seconds: start.elapsed().as_secs_f64(),
        peak_rss_mib: peak_rss_mib(),
        side_warning,
        frame_warning,
        lobes_from,
        sh_bands: sh.map_or(0, |s| s.bands),
        alpha: sh.map(|s| s.alpha),
        sh_rms_percent: sh.map(|s| s.rms_percent),
        sh_rms_mm: sh.map(|s| s.rms_mm),
        sh_max_mm: sh.map(|s| s.max_mm),
        sh_quantisation_max_mm: sh.map(|s| s.quantisation_max_mm),
        sh_budget_mm: sh.and_then(|s| s.budget_mm),
        sh_budget_met: sh.and_then(|s| s.budget_mm.map(|b| s.rms_mm <= b)),
        sh_budget_reason: sh.and_then(|s| s.budget_reason()),
        foldover_nodes: sh.map_or(0, |s| s.foldover_nodes),
        basis_max_error_mm: orientation.map_or(0.0, |o| o.basis_max_error_mm),
        reference_delta_ml: orientation.map_or(0.0, |o| o.reference_delta_ml),
        orientations: orientation.map_or(0, |o| o.orientations_checked),
        tumour: k.meta.tumour.clone(),
        fold_free: k.meta.fold_free,
    })
}

/// The bake settings: the scene's for this lung, with the command line's overrides, each checked.
fn settings(args: &BakeArgs) -> anyhow::Result<lung_bake::kernel::BakeSettings> {
    let side = args.lung;
    let scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    let mut settings = scene.bake_settings(side)?;
    if let Some(d) = &args.directions {
        let preset: lung_model::deform::DirectionPreset = d.parse().map_err(anyhow::Error::msg)?;
        let m = lung_model::deform::preset_motion(preset, side);
        settings.motion = m.constants;
        settings.direction_field = m.direction_field;
        settings.force_field = m.force_field;
    }
    if let Some(m) = &args.motion {
        let f = lung_model::deform::MotionFile::load(m)?;
        settings.motion = f.for_side(side);
        settings.direction_field = f.field_for_side(side).cloned();
        settings.force_field = f.force_for_side(side).cloned();
    }
    if let Some(l) = args.smoothing_mm {
        if !lung_model::kernel::amplitude_smoothing_ok(l) {
            anyhow::bail!(
                "--smoothing-mm {l} must be 0 (the seed's unsmoothed reading) or a length within 0..{} mm ({} is the default)",
                lung_model::kernel::MAX_AMPLITUDE_SMOOTHING_MM,
                lung_model::kernel::DEFAULT_AMPLITUDE_SMOOTHING_MM
            );
        }
        settings.amplitude_smoothing_mm = l;
    }
    if let Some(t) = args.tolerance {
        if !(t.is_finite() && (1e-9..=0.5).contains(&t)) {
            anyhow::bail!(
                "--tolerance {t} must be within 1e-9..0.5 (1e-5 is the default; 1e-6 doubles the bake time, \
                 smaller values take far longer)"
            );
        }
        settings.tolerance = t;
    }
    if let Some(e) = args.max_error_mm {
        if !(e.is_finite() && e > 0.0 && e <= 50.0) {
            anyhow::bail!("--max-error-mm {e} must be a positive number of millimetres up to 50");
        }
        settings.max_error_mm = Some(e);
        settings.sh_bands = lung_model::kernel::MAX_RUNTIME_BANDS;
    }
    if let Some(b) = args.bands {
        if b > lung_model::kernel::MAX_RUNTIME_BANDS {
            anyhow::bail!(
                "--bands {b}: 0 (none) to {} (64 coefficients per lung travel in every engine frame)",
                lung_model::kernel::MAX_RUNTIME_BANDS
            );
        }
        if b == 0 && args.max_error_mm.is_some() {
            anyhow::bail!(
                "--max-error-mm chooses a band count: it needs --bands ≥ 1 (or none: up to 8)"
            );
        }
        settings.sh_bands = b;
    }
    Ok(settings)
}

/// Human-readable bake report.
pub fn bake_text(b: &BakeSummary) -> String {
    format!(
        "wrote {} ({:.1} MiB): {} lung, {} vertices + {} spring nodes, {:.1} ml\n\
         transfer: {} non-zeros, {:.1} per row (max {}), tolerance {:e}\n\
         force per unit row: {:.1} % caught by mass nodes, truncated {:.2e} mean / {:.2e} max, conservation error {:.1e}\n\
         largest unit displacement {:.3} mm per {:.2} ml; {:.1} s, peak memory {:.0} MiB\n\
         fold-free (supine, precomputed field): {}\n\
         orientation (errors against eq. 7.1 at +{:.0} ml over {} orientations): basis mode {:.1e} mm (exact);\n{}",
        b.path,
        b.file_bytes as f64 / 1048576.0,
        b.lung,
        b.vertices,
        b.spring_nodes,
        b.volume_ml,
        b.nnz,
        b.mean_row_nnz,
        b.max_row_nnz,
        b.tolerance,
        100.0 * b.mass_caught,
        b.truncated_force,
        b.truncated_force_max,
        b.conservation_error_max,
        b.max_unit_displacement_mm,
        lung_model::deform::UNIT_VOLUME_ML,
        b.seconds,
        b.peak_rss_mib,
        lung_model::kernel::FoldFreeMeta::words(b.fold_free.as_ref()),
        b.reference_delta_ml,
        b.orientations,
        b.basis_max_error_mm,
        match (b.sh_bands, b.alpha, b.sh_rms_mm, b.sh_rms_percent, b.sh_max_mm) {
            (0, ..) => "  no spherical harmonics stored (--bands 0): the sh mode is unavailable\n".to_string(),
            (n, Some(alpha), Some(rms), Some(pct), Some(max)) => format!(
                "  sh mode, {n} bands ({} coefficients): alpha {alpha:.4}, RMS {rms:.3} mm ({pct:.2} % of the largest displacement), max {max:.3} mm (16-bit storage's share at most {:.4} mm); {} fold-over nodes{}\n",
                n * n,
                b.sh_quantisation_max_mm.unwrap_or(0.0),
                b.foldover_nodes,
                b.sh_budget_reason
                    .as_ref()
                    .map(|r| format!("\n  error budget: {r}"))
                    .unwrap_or_default()
            ),
            _ => String::new(),
        }
    )
}

/// Options of `lungdyn kernel inspect`.
#[derive(Debug, Clone, clap::Args)]
pub struct InspectArgs {
    /// Kernel file.
    pub file: PathBuf,
    /// Also draw the kernel (PNG): unit displacement and two transfer rows (near base and apex).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What `kernel inspect` reports.
#[derive(Debug, Serialize)]
pub struct InspectSummary {
    /// Path.
    pub path: String,
    /// File size.
    pub file_bytes: u64,
    /// Format version.
    pub format: u32,
    /// The metadata section.
    pub meta: kernel::KernelMeta,
    /// Set when the kernel's surface looks like the other lung than the side it was baked as (the
    /// bake warned too; a kernel keeps the side it was told).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub side_warning: Option<String>,
}

/// Open (verifying every checksum) and summarise.
pub fn inspect(args: &InspectArgs) -> anyhow::Result<InspectSummary> {
    let f = KernelFile::open(&args.file)?;
    if let Some(png) = &args.plot {
        if png.extension().and_then(|e| e.to_str()) != Some("png") {
            anyhow::bail!("--plot {}: the picture must be a .png", png.display());
        }
        crate::kernel_plot::write(&f, png)
            .with_context(|| format!("cannot draw {}", png.display()))?;
    }
    // Say it again on every inspect: the bake's warning scrolled past once, the kernel stays.
    let baked = f.meta().side;
    let evidence = lung_bake::surface_checks::infer_side(&f.mesh());
    let side_warning = match evidence.side {
        Some(seen) if seen != baked => {
            let w = format!(
                "{}: baked as the {} lung but its surface looks like a {} lung ({}; confidence {:.2}): \
                 bake it again with the right --lung, or check the mesh's frame (+X = patient left)",
                args.file.display(),
                baked.name(),
                seen.name(),
                evidence.reason,
                evidence.confidence
            );
            eprintln!("lungdyn: warning: {w}");
            Some(w)
        }
        _ => None,
    };
    Ok(InspectSummary {
        path: args.file.display().to_string(),
        file_bytes: f.len_bytes() as u64,
        format: lung_model::kernel::FORMAT_VERSION,
        meta: f.meta().clone(),
        side_warning,
    })
}

/// Human-readable inspect report.
pub fn inspect_text(i: &InspectSummary) -> String {
    let m = &i.meta;
    let c = &m.settings.motion.c;
    let e = &m.settings.elasticity;
    format!(
        "{}: lungdyn kernel format {}, {:.1} MiB, checksums OK\n\
         {} lung, {} vertices, {} triangles, {} spring nodes, {:.1} ml, units {}\n\
         mesh hash {}\n\
         transfer: {} non-zeros ({:.1} per row, max {}), tolerance {:e}, truncated {:.2e} mean / {:.2e} max\n\
         motion c1..c9 = {:?}\n\
         elasticity: apex {} base {} dependent {}\n\
         unit volume {:.3} ml, written by {}\n\
         fold-free (supine, precomputed field): {}\n",
        i.path,
        i.format,
        i.file_bytes as f64 / 1048576.0,
        m.side.name(),
        m.vertices,
        m.triangles,
        m.spring_nodes,
        m.start_volume_ml,
        m.units,
        m.mesh_hash,
        m.nnz,
        m.transfer.mean_row_nnz,
        m.transfer.max_row_nnz,
        m.transfer.tolerance,
        m.transfer.truncated_force_mean,
        m.transfer.truncated_force_max,
        c,
        e.apex,
        e.base,
        e.dependent,
        m.unit_volume_ml,
        m.written_by,
        lung_model::kernel::FoldFreeMeta::words(m.fold_free.as_ref())
    )
}

/// Options of `lungdyn kernel export`.
#[derive(Debug, Clone, clap::Args)]
pub struct ExportArgs {
    /// Kernel file.
    pub file: PathBuf,
    /// Volume above the start (FRC) volume, ml; the surface is deformed so its enclosed volume
    /// grows by exactly this much (EQUATIONS.md §2.4). Negative deflates.
    #[arg(long, allow_negative_numbers = true)]
    pub delta_ml: f64,
    /// Output mesh, .obj or .ply (written atomically).
    #[arg(long)]
    pub out: PathBuf,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What `kernel export` wrote.
#[derive(Debug, Serialize)]
pub struct ExportSummary {
    /// Output.
    pub path: String,
    /// Requested volume change, ml.
    pub delta_ml: f64,
    /// Enclosed volume of the written mesh, ml.
    pub volume_ml: f64,
    /// Start volume, ml.
    pub start_volume_ml: f64,
    /// Deformation scale applied to the unit displacement.
    pub scale: f64,
    /// Largest vertex displacement, mm.
    pub max_displacement_mm: f64,
    /// Self-intersecting triangle pairs of the deformed surface (counted up to 16): the linear model
    /// `p + s·u` folds the surface where neighbouring vertices move very differently.
    pub self_intersections: usize,
}

/// Deform a kernel's lung to `start + delta` and write the surface.
pub fn export(args: &ExportArgs) -> anyhow::Result<ExportSummary> {
    if !(args.delta_ml.is_finite() && args.delta_ml.abs() <= 10_000.0) {
        anyhow::bail!(
            "--delta-ml {} must be a volume within ±10000 ml",
            args.delta_ml
        );
    }
    lung_model::mesh::io::check_out(&args.out)?;
    let f = KernelFile::open(&args.file)?;
    lung_model::plausible::LUNG_VOLUME_ML.check(
        f.meta().start_volume_ml,
        Some("the kernel was baked from a mesh in the wrong unit? bake it again with the right --units".into()),
    )?;
    let model = f.lung_model();
    if args.delta_ml < -0.9 * model.start_volume_ml {
        anyhow::bail!(
            "--delta-ml {} would empty the lung (start volume {:.1} ml)",
            args.delta_ml,
            model.start_volume_ml
        );
    }
    let scale = model.scale_for_delta(args.delta_ml);
    let mut out = vec![[0.0f32; 3]; model.mesh.positions.len()];
    model.deform_into(scale as f32, &mut out);
    let max_d = out
        .iter()
        .zip(&model.mesh.positions)
        .map(|(a, b)| {
            let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
            ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) as f64).sqrt()
        })
        .fold(0.0, f64::max);
    let mesh = lung_model::mesh::TriMesh {
        positions: out,
        triangles: model.mesh.triangles.clone(),
    };
    if let Err(e) = lung_model::mesh::check(&mesh) {
        anyhow::bail!(
            "at {:+} ml the deformed surface is no longer valid ({e}): the linear model does not reach that far",
            args.delta_ml
        );
    }
    // The volume cubic must have reached the target; anything else is a kernel in the wrong unit or
    // a change beyond the model's range, never something to write.
    let reached = mesh.enclosed_volume_ml() - model.start_volume_ml;
    if !(reached.is_finite() && (reached - args.delta_ml).abs() <= 0.5 + 1e-3 * args.delta_ml.abs())
    {
        anyhow::bail!(
            "the deformed lung changes by {reached:+.1} ml instead of {:+} ml: this kernel cannot reach that volume",
            args.delta_ml
        );
    }
    lung_model::plausible::LUNG_VOLUME_ML.check(
        mesh.enclosed_volume_ml(),
        Some("--delta-ml takes the lung outside human volumes".into()),
    )?;
    let folds = lung_bake::surface_checks::self_intersections(&mesh, 16);
    if let Some((a, b)) = folds.first {
        eprintln!(
            "lungdyn: warning: at {:+} ml the deformed surface intersects itself ({} crossing pair(s), first \
             triangles {a} and {b}): the linear model folds it there (`lungdyn kernel inspect` gives the range the bake found free of folds)",
            args.delta_ml, folds.count
        );
    }
    lung_model::mesh::io::write_mesh(&mesh, &args.out)?;
    Ok(ExportSummary {
        self_intersections: folds.count,
        path: args.out.display().to_string(),
        delta_ml: args.delta_ml,
        volume_ml: mesh.enclosed_volume_ml(),
        start_volume_ml: model.start_volume_ml,
        scale,
        max_displacement_mm: max_d,
    })
}
