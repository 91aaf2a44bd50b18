//! Give every lung of a scene a kernel file, once, so every process reads the same lungs.
//!
//! The engine and the renderer never bake. `lungdyn demo` and `lungdyn scene prepare` call
//! [`prepare`]: a lung the scene names no kernel for gets the generated default lung, baked into
//! `<dir>` under a name derived from its resolution and bake settings (reused while they are
//! unchanged and the file verifies); every path becomes absolute and the result is written as
//! `<dir>/scene.resolved.toml`, which the three processes are started with.

use std::path::{Path, PathBuf};

use anyhow::Context;
use lung_model::deform::modes::DeformMode;
use lung_model::kernel::KernelMeta;
use lung_model::mesh::Side;
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use serde::Serialize;

/// A kernel the demo used.
#[derive(Debug, Clone, Serialize)]
pub struct KernelUse {
    /// Lung.
    pub lung: String,
    /// File.
    pub path: String,
    /// Whether it was baked by this run (false: the scene's own or a cached bake).
    pub baked_now: bool,
    /// Bake seconds (0 when reused).
    pub bake_seconds: f64,
    /// Spherical-harmonic bands in the kernel (0: none).
    pub sh_bands: u32,
    /// RMS displacement error of the SH mode against eq. 7.1, mm (when it has bands).
    pub sh_rms_mm: Option<f64>,
    /// Largest displacement error of the basis mode against eq. 7.1, mm (round-off).
    pub basis_max_error_mm: Option<f64>,
    /// With an error budget: the bands kept and why (`ShMeta::budget_reason`).
    pub sh_budget_reason: Option<String>,
}

impl KernelUse {
    fn of(side: Side, path: &Path, baked_now: bool, bake_seconds: f64, meta: &KernelMeta) -> Self {
        Self {
            lung: side.name().into(),
            path: path.display().to_string(),
            baked_now,
            bake_seconds,
            sh_bands: meta.sh.as_ref().map_or(0, |s| s.bands),
            sh_rms_mm: meta.sh.as_ref().map(|s| s.rms_mm),
            basis_max_error_mm: meta.orientation.as_ref().map(|o| o.basis_max_error_mm),
            sh_budget_reason: meta.sh.as_ref().and_then(|s| s.budget_reason()),
        }
    }
}

/// Give every lung of `scene` a kernel file: lungs without one get the generated default lung, baked
/// into `dir` under a name derived from its resolution and bake settings, or reused from an earlier
/// run when that file exists and verifies. All paths in `scene` become absolute.
pub fn ensure_kernels(
    scene: &mut lung_model::scene::Scene,
    dir: &Path,
) -> anyhow::Result<Vec<KernelUse>> {
    let absolute = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    if let Some(c) = &scene.pv.constants {
        scene.pv.constants = Some(absolute(c));
    }
    if let Some(m) = &scene.lungs.motion {
        scene.lungs.motion = Some(absolute(m));
    }
    if let Some(c) = &scene.render.calibration {
        scene.render.calibration = Some(absolute(c));
    }
    if let Some(h) = &scene.render.hmd {
        scene.render.hmd = Some(absolute(h));
    }
    // The calibration and HMD optics files are read by the renderer: check them here, before any
    // bake, so a bad one is refused by the launcher rather than by the renderer after the launch.
    renderer::camera::RigFiles::load(&scene.render, None, None)?;
    let mut used = Vec::new();
    for side in scene.lungs.sides.clone() {
        if let Some(k) = scene.lungs.kernels.get(side) {
            let k = absolute(k);
            scene.lungs.kernels.set(side, k.clone());
            // The scene's own kernel: verified now (every section), the right lung, and what the
            // mode needs — so a bad kernel is refused here, not by the engine after the launch.
            let opened = lung_model::kernel::KernelFile::open(&k)?;
            if scene.render.color == lung_model::scene::ColorMode::Lobes
                && opened.lobes()?.is_none()
            {
                eprintln!(
                    "lungdyn: warning: [render] color = \"lobes\", but {} (the {} lung) has no \
                     lobe section (baked before lobes existed): that lung is drawn grey, as the \
                     HUD legend says; bake it again to see its lobes",
                    k.display(),
                    side.name()
                );
            }
            // (The error budget is settled below, for every lung at once.)
            let file = check_named_kernel(scene, side)?;
            used.push(KernelUse::of(side, &k, false, 0.0, file.meta()));
            continue;
        }
        let mut settings = scene.bake_settings(side)?;
        // Model only what the scene requires: spherical harmonics only for the sh mode (with a
        // budget, up to 8 bands and the fewest that meet it).
        // (`bake_settings` holds the error-budget rule shared with `lungdyn bake`.)
        if scene.lungs.mode != DeformMode::Sh {
            settings.sh_bands = 0;
            settings.max_error_mm = None;
        }
        let key = xxhash_rust::xxh3::xxh3_64(
            format!(
                "{}:{}:{}:{}",
                scene.lungs.shape,
                scene.lungs.vertices,
                serde_json::to_string(&settings)?,
                lung_model::kernel::FORMAT_VERSION
            )
            .as_bytes(),
        );
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let path = absolute(&dir.join(format!(
            "default_{}_{}_{}_{key:016x}.kernel",
            side.name(),
            scene.lungs.shape,
            scene.lungs.vertices
        )));
        let reusable = lung_model::kernel::KernelFile::open(&path)
            .map(|f| {
                f.meta().side == side
                    && f.meta().settings == settings
                    && !f.meta().orientation_predates_fitted_force()
                    // Baked before the bake measured where the lung folds: baked again, so the
                    // engine can say when a frame draws it past that.
                    && f.meta().fold_free.is_some()
            })
            .unwrap_or(false);
        let mut meta = None;
        let mut seconds = 0.0;
        if !reusable {
            let t = std::time::Instant::now();
            eprintln!(
                "lungdyn: baking the default {} lung ({}, {} vertices) into {}",
                side.name(),
                scene.lungs.shape,
                scene.lungs.vertices,
                path.display()
            );
            let mesh =
                lung_model::mesh::generate::lung_of(scene.lungs.shape, side, scene.lungs.vertices)?;
            let bar = rows_bar(mesh.positions.len(), ROWS_BAR);
            let kernel =
                lung_bake::kernel::bake(side, mesh, &settings, &|rows| bar.inc(rows as u64))?;
            bar.finish_and_clear();
            kernel.write(&path)?;
            seconds = t.elapsed().as_secs_f64();
            meta = Some(kernel.meta);
        }
        let meta = match meta {
            Some(m) => m,
            None => lung_model::kernel::KernelFile::open_lazy(&path)?
                .meta()
                .clone(),
        };
        used.push(KernelUse::of(side, &path, !reusable, seconds, &meta));
        scene.lungs.kernels.set(side, path);
    }
    // An error budget the spherical harmonics cannot meet: the force is linear in the box
    // coordinates, so the exact basis mode serves it (EQUATIONS.md §3.2).
    if let (DeformMode::Sh, Some(budget)) = (scene.lungs.mode, scene.lungs.max_error_mm) {
        let missed: Vec<String> = used
            .iter()
            .filter(|u| u.sh_rms_mm.is_some_and(|e| e > budget))
            .map(|u| {
                format!(
                    "{} lung {:.3} mm with {} bands",
                    u.lung,
                    u.sh_rms_mm.unwrap_or(f64::NAN),
                    u.sh_bands
                )
            })
            .collect();
        if !missed.is_empty() {
            eprintln!(
                "lungdyn: the spherical harmonics cannot meet max_error_mm = {budget} ({}); running \
                 the exact \"basis\" mode instead (error {:.1e} mm)",
                missed.join(", "),
                used.iter()
                    .filter_map(|u| u.basis_max_error_mm)
                    .fold(0.0, f64::max)
            );
            scene.lungs.mode = DeformMode::Basis;
        }
    }
    // The resolved scene must load in every process: check it here.
    for side in scene.lungs.sides.clone() {
        scene.lung_kernel(side)?;
    }
    Ok(used)
}

/// The kernel `scene` names for `side`, opened and checked as the processes check it (the right
/// lung, the scene's tumour, what the scene's mode needs), leaving out the error budget: against a
/// budget the harmonics miss, [`prepare`] runs the exact basis mode instead of refusing.
pub fn check_named_kernel(
    scene: &Scene,
    side: Side,
) -> anyhow::Result<lung_model::kernel::KernelFile> {
    let mut unbudgeted = scene.clone();
    unbudgeted.lungs.max_error_mm = None;
    Ok(unbudgeted.lung_kernel(side)?)
}

/// A scene whose every lung has a kernel, written where the processes can read it.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The resolved scene (absolute paths, a kernel per lung).
    pub scene: Scene,
    /// Where it was written.
    pub path: PathBuf,
    /// The kernels it uses.
    pub kernels: Vec<KernelUse>,
}

/// Bake what `scene` lacks into `dir` and write `dir/scene.resolved.toml` atomically.
pub fn prepare(scene: Scene, dir: &Path) -> anyhow::Result<Prepared> {
    prepare_carrying(scene, dir, None).map(|(p, _)| p)
}

/// One file a scene names, copied beside the prepared scene.
#[derive(Debug, Clone, Serialize)]
pub struct Carried {
    /// The scene's key (`[pv] waveform`, `[tracker] source`, …).
    pub key: String,
    /// Where it was.
    pub from: String,
    /// Where the prepared scene now names it.
    pub to: String,
}

/// [`prepare`], and with `carry`, every file the scene names that lies outside `dir` (PV
/// constants, the ventilator waveform, the motion file, its own kernels, the calibration, the HMD
/// optics, a replayed tracker recording) copied into `carry`, atomically, and named there by the
/// written scene: an installed scene that keeps working when the folder it came from is gone.
pub fn prepare_carrying(
    mut scene: Scene,
    dir: &Path,
    carry: Option<&Path>,
) -> anyhow::Result<(Prepared, Vec<Carried>)> {
    // Say where, before writing: the default folder is ./out, which a person may not expect.
    eprintln!(
        "lungdyn: kernels and the resolved scene go to {} (--out chooses; --kernels for export)",
        std::path::absolute(dir)
            .unwrap_or_else(|_| dir.to_path_buf())
            .display()
    );
    let kernels = ensure_kernels(&mut scene, dir)?;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let carried = match carry {
        Some(to) => carry_files(&mut scene, dir, to)?,
        None => Vec::new(),
    };
    let path = std::path::absolute(dir.join("scene.resolved.toml"))
        .unwrap_or_else(|_| dir.join("scene.resolved.toml"));
    let text = toml::to_string(&scene).context("the resolved scene does not serialise")?;
    outfile::write_atomically(&path, |w| {
        use std::io::Write;
        w.write_all(b"# Written by lungdyn: every lung has a kernel; start the engine and the renderer with --scene <this file>\n")?;
        w.write_all(text.as_bytes())
    })?;
    Ok((
        Prepared {
            scene,
            path,
            kernels,
        },
        carried,
    ))
}

/// Copy every file `scene` names outside `keep` into `to` (named `<key>-<file name>`) and name the
/// copy in `scene`.
fn carry_files(scene: &mut Scene, keep: &Path, to: &Path) -> anyhow::Result<Vec<Carried>> {
    let keep = std::path::absolute(keep)?;
    let mut carried = Vec::new();
    let mut copy = |key: &str, tag: &str, from: &Path| -> anyhow::Result<PathBuf> {
        let from = std::path::absolute(from)?;
        if from.starts_with(&keep) {
            return Ok(from);
        }
        let name = from
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "file".into());
        let dest = std::path::absolute(to.join(format!("{tag}-{name}")))?;
        let bytes = std::fs::read(&from)
            .with_context(|| format!("{key} {}: cannot read it to install", from.display()))?;
        std::fs::create_dir_all(to).with_context(|| format!("cannot create {}", to.display()))?;
        outfile::write_atomically(&dest, |w| std::io::Write::write_all(w, &bytes))?;
        carried.push(Carried {
            key: key.to_string(),
            from: from.display().to_string(),
            to: dest.display().to_string(),
        });
        Ok(dest)
    };
    let fields: [(&str, &str, &mut Option<PathBuf>); 5] = [
        ("[pv] constants", "pv-constants", &mut scene.pv.constants),
        ("[pv] waveform", "pv-waveform", &mut scene.pv.waveform),
        ("[lungs] motion", "lungs-motion", &mut scene.lungs.motion),
        (
            "[render] calibration",
            "render-calibration",
            &mut scene.render.calibration,
        ),
        ("[render] hmd", "render-hmd", &mut scene.render.hmd),
    ];
    for (key, tag, field) in fields {
        if let Some(f) = field.as_ref() {
            *field = Some(copy(key, tag, f)?);
        }
    }
    for side in [Side::Left, Side::Right] {
        if let Some(k) = scene.lungs.kernels.get(side).map(Path::to_path_buf) {
            let key = format!("[lungs.kernels] {}", side.name());
            let tag = format!("kernel-{}", side.name());
            scene.lungs.kernels.set(side, copy(&key, &tag, &k)?);
        }
    }
    if let tracker_bridge::source::SourceSpec::Replay { path } =
        tracker_bridge::source::SourceSpec::parse(&scene.tracker.source)?
    {
        let copied = copy("[tracker] source", "tracker-replay", &path)?;
        scene.tracker.source = format!("replay:{}", copied.display());
    }
    Ok(carried)
}

/// Options of `lungdyn scene prepare`.
#[derive(Debug, Clone, clap::Args)]
pub struct PrepareArgs {
    /// Scene file (TOML); the built-in default scene when omitted.
    pub scene: Option<PathBuf>,
    /// Folder for the baked kernels and the resolved scene (`<out>/kernels/scene.resolved.toml`).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Print one JSON object (`scene`, `kernels`) on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What `lungdyn scene prepare` did.
#[derive(Debug, Serialize)]
pub struct PrepareReport {
    /// The resolved scene to start the processes with.
    pub scene: String,
    /// The kernels it uses.
    pub kernels: Vec<KernelUse>,
    /// The deformation mode the processes will run (the scene's, or "basis" where an error budget
    /// could not be met with spherical harmonics).
    pub mode: String,
}

/// `scene prepare`'s text.
pub fn text(p: &PrepareReport) -> String {
    let mut t = String::new();
    for k in &p.kernels {
        t.push_str(&format!(
            "{} lung: {}{}\n",
            k.lung,
            k.path,
            if k.baked_now {
                format!(" (baked now, {:.1} s)", k.bake_seconds)
            } else {
                String::new()
            }
        ));
        match (&k.sh_budget_reason, k.sh_bands) {
            (Some(r), _) => t.push_str(&format!("  sh mode, {r}\n")),
            (None, 0) => {}
            (None, n) => t.push_str(&format!(
                "  sh mode, {n} bands (the scene's), RMS error {:.3} mm\n",
                k.sh_rms_mm.unwrap_or(f64::NAN)
            )),
        }
    }
    t.push_str(&format!("mode: {}\n", p.mode));
    t.push_str(&format!(
        "wrote {}: start the engine and the renderer with --scene {}\n",
        p.scene, p.scene
    ));
    t
}

/// `lungdyn scene prepare`.
pub fn run(args: &PrepareArgs) -> anyhow::Result<PrepareReport> {
    let scene = Scene::load_or_default(args.scene.as_deref())?;
    crate::outputs::check_writable(&args.out)?;
    let p = prepare(scene, &args.out.join("kernels"))?;
    Ok(PrepareReport {
        scene: p.path.display().to_string(),
        kernels: p.kernels,
        mode: p.scene.lungs.mode.to_string(),
    })
}

/// How a bake's progress is drawn: its transfer rows done of all, and the time left.
pub const ROWS_BAR: &str = "  [{bar:40}] {pos}/{len} rows, eta {eta}";

/// A progress bar over a bake's `rows` transfer rows, drawn with `template` (indicatif's).
pub fn rows_bar(rows: usize, template: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(rows as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(template)
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar
}
