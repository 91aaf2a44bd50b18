//! `lungdyn export gltf`: one breath of a scene as binary glTF 2.0 (`.glb`), for any glTF viewer, a
//! web page (`<model-viewer>`), Blender, a slide or a headset's own viewer.
//!
//! What the file holds:
//! * each lung as one mesh: the breath's first frame (the start of inspiration) as the base and every
//!   later frame as a morph target (positions only, each frame's difference from the base), and one
//!   animation, `breath`, that steps the weights from frame to frame (linear between neighbours) and
//!   back to the first frame at the breath's period, so a viewer that loops it breathes seamlessly;
//! * the lobes as materials, in the renderer's lobe colours (one primitive per lobe sharing the
//!   lung's vertices; a triangle whose corners lie in two or three lobes is cut between them where
//!   the fissure planes cross its edges, [`LobeSplit`]), or one "lung" material where the kernel has
//!   no lobes;
//! * the tumour, where the scene has one: an ellipsoid of its radii moved along its centre's path
//!   (a translation animation on the same keys);
//! * the scene's figures as metadata (`asset.extras.lungdyn`): the scene, the mode, the breath's
//!   period and rate, each frame's time and each lung's volume, the tumour's motion.
//!
//! The frames are the engine's own: the headless tick function `lungdyn scene run` uses, with a
//! still patient in the scene's posture ([`crate::scene_check::still_patient`]), deformed on the CPU
//! by the renderer's reference (`CpuLung`, plus a collapsing lung's pull towards its hilum as
//! `deform.wgsl` applies it, EQUATIONS.md §4.1), so the file shows what the HMD draws.
//!
//! Units and axes: glTF is metres, +Y up, the asset's front facing +Z, right-handed; the body frame
//! is mm with +X patient left, +Y anterior, +Z superior, left-handed (docs/ARCHITECTURE.md
//! "Registration"). glTF (x, y, z) = body (X, Z, Y) / 1000 ([`body_to_gltf`]): the patient stands
//! facing the viewer, their left on the viewer's right. The map is a reflection, so every triangle's
//! corners are reversed to stay counter-clockwise seen from outside.
//!
//! Each morph target moves the normals too (each frame's normals less the base's), so a viewer shades
//! every frame by its own surface. The targets are quantised (`KHR_mesh_quantization`, required by
//! the file): position differences as 16-bit normalised integers of a metre (a step of 0.03 mm),
//! normal differences as 8-bit ones (a step of 1/127): 12 bytes per vertex and frame, what the
//! positions alone cost as floats. A target whose differences leave −1…1 is written as floats
//! instead (counted in the report). `--float-targets` writes every target as floats, for a reader
//! without the extension (twice the size).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use gltf::json;
use gltf::json::validation::Checked::Valid;
use gltf::json::validation::USize64;
use ipc_types::{EngineFrame, LungFrame, MAX_COEFFS};
use lung_model::mesh::lobes::Lobe;
use lung_model::mesh::Side;
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use renderer::deform::RenderLung;
use serde::Serialize;

/// The glTF extension quantised morph targets need (readers without it must refuse the file, so it
/// is required as well as used).
const QUANTIZATION: &str = "KHR_mesh_quantization";

/// Frames per breath when `--frames` is not given.
pub const DEFAULT_FRAMES: u32 = 24;
/// The most frames a breath may be exported with (morph targets cost a copy of the mesh each).
pub const MAX_FRAMES: u32 = 240;
/// The latest breath `--breath` may ask for (each costs a breath of simulated time).
pub const MAX_BREATH: u32 = 50;
/// The largest file written: past it, fewer frames or vertices are asked for.
pub const MAX_FILE_BYTES: u64 = 1 << 30;
/// Simulated seconds within which the breath asked for must have ended.
const MAX_SIMULATED_S: f64 = 300.0;

/// Options of `lungdyn export gltf`.
#[derive(Debug, Clone, clap::Args)]
pub struct GltfArgs {
    /// Scene file (TOML); the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// The file to write: binary glTF (`.glb`), written atomically (an existing file is replaced
    /// only once the new one is complete).
    #[arg(long, default_value = "out/breath.glb")]
    pub out: PathBuf,
    /// Frames over the breath, 2..=240: the first is the base mesh, each later one a morph target.
    #[arg(long, default_value_t = DEFAULT_FRAMES)]
    pub frames: u32,
    /// Which breath to export, 1..=50, counted from the start of the run (the first starts from
    /// the scene's initial state; the second, the default, is the steady breath).
    #[arg(long, default_value_t = 2)]
    pub breath: u32,
    /// Vertices per generated default lung (overrides the scene's `[lungs] vertices`).
    #[arg(long, value_name = "N")]
    pub vertices: Option<usize>,
    /// The lungs' opacity, 0.05..=1: below 1 they are see-through (glTF's BLEND), so the tumour
    /// inside shows. Default: 0.5 when the scene has a tumour, else 1 (opaque).
    #[arg(long, value_name = "F")]
    pub opacity: Option<f32>,
    /// Folder for the kernels the scene lacks (baked once, as `lungdyn scene prepare` bakes them,
    /// and reused by later runs).
    #[arg(long, default_value = "out/kernels")]
    pub kernels: PathBuf,
    /// Write the morph targets as 32-bit floats, without `KHR_mesh_quantization` (about twice the
    /// file), for a reader that lacks that extension. By default position differences are 16-bit
    /// and normal differences 8-bit normalised integers.
    #[arg(long)]
    pub float_targets: bool,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// How the morph targets were stored, and what quantising them cost.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TargetsExport {
    /// "quantized" (`KHR_mesh_quantization`: position differences 16-bit, normal differences
    /// 8-bit normalised integers) or "float".
    pub encoding: &'static str,
    /// The largest distance between a vertex as written and as computed, over every frame, mm.
    pub position_error_max_mm: f64,
    /// The largest angle between a normal as a viewer rebuilds it (the base's plus the target's,
    /// made unit) and as computed, over every frame, degrees.
    pub normal_error_max_deg: f64,
    /// Targets (positions or normals of one frame) written as floats although quantised was asked
    /// for: a difference outside −1…1.
    pub kept_float: usize,
}

/// Bytes a morph target costs per vertex: position and normal differences.
fn target_bytes(float_targets: bool) -> u64 {
    if float_targets {
        24
    } else {
        12
    }
}

/// About what one lung of `vertices` and `triangles` costs the file over `frames`: its base
/// positions and normals, a morph target per frame, its triangles' indices.
fn lung_bytes(vertices: u64, triangles: u64, frames: u32, float_targets: bool) -> u64 {
    vertices * (24 + target_bytes(float_targets) * u64::from(frames)) + triangles * 12
}

/// What `lungdyn export gltf` wrote.
#[derive(Debug, Clone, Serialize)]
pub struct GltfReport {
    /// The file written.
    pub out: String,
    /// Its size, bytes.
    pub bytes: u64,
    /// The scene exported (its file, or "built-in default").
    pub scene: String,
    /// The deformation mode the frames were computed in.
    pub mode: String,
    /// Frames over the breath (the base and one morph target per later frame).
    pub frames: u32,
    /// Which complete breath of the run.
    pub breath: u32,
    /// The breath's length, s.
    pub period_s: f64,
    /// Per lung.
    pub lungs: Vec<LungExport>,
    /// The tumour's centre, where the scene has one.
    pub tumour: Option<TumourExport>,
    /// The lungs' opacity (1: opaque).
    pub opacity: f32,
    /// The morph targets' storage.
    pub targets: TargetsExport,
    /// Wall-clock seconds (preparing the kernels included).
    pub seconds: f64,
}

/// One lung in the file.
#[derive(Debug, Clone, Serialize)]
pub struct LungExport {
    /// "right" or "left".
    pub side: &'static str,
    /// Vertices.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
    /// The lobes drawn as materials (empty: the kernel has none, one "lung" material).
    pub lobes: Vec<&'static str>,
    /// Smallest and largest volume over the exported frames (the engine's), ml.
    pub volume_ml: [f64; 2],
    /// The largest distance any vertex moves from the first frame, mm.
    pub max_motion_mm: f64,
}

/// The tumour in the file.
#[derive(Debug, Clone, Serialize)]
pub struct TumourExport {
    /// Its lung.
    pub side: &'static str,
    /// Radii, mm (body frame axes).
    pub radii_mm: [f64; 3],
    /// The centre's range of motion per body axis over the exported frames, mm.
    pub motion_mm: [f64; 3],
}

/// glTF position (m) of a body-frame point (mm): glTF (x, y, z) = body (X, Z, Y) / 1000.
pub fn body_to_gltf(p: [f32; 3]) -> [f32; 3] {
    [p[0] * 1e-3, p[2] * 1e-3, p[1] * 1e-3]
}

/// A body-frame direction as a glTF unit vector (the axes of [`body_to_gltf`], no scaling); +y for
/// a zero or non-finite one.
fn unit_gltf_direction(d: [f32; 3]) -> [f32; 3] {
    let g = [d[0], d[2], d[1]];
    let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        g.map(|v| v / len)
    } else {
        [0.0, 1.0, 0.0]
    }
}

/// One breath's frames as the engine wrote them.
struct Breath {
    /// The frames, evenly spaced over the breath (the first at its start).
    frames: Vec<EngineFrame>,
    /// Each frame's time from the breath's start, s.
    times_s: Vec<f32>,
    /// The breath's length, s.
    period_s: f64,
}

/// `lungdyn export gltf`.
pub fn run(args: &GltfArgs) -> anyhow::Result<GltfReport> {
    let started = Instant::now();
    check_args(args)?;
    let mut scene = Scene::load_or_default(args.scene.as_deref())?;
    if let Some(v) = args.vertices {
        scene.lungs.vertices = v;
        scene.validate()?;
    }
    let origin = args.scene.as_ref().map_or_else(
        || "built-in default".to_string(),
        |p| p.display().to_string(),
    );
    // The generated lungs' size is known before baking them: refuse an oversized file first.
    let generated = scene
        .lungs
        .sides
        .iter()
        .filter(|&&side| scene.lungs.kernels.get(side).is_none())
        .count() as u64;
    let early = generated
        * lung_bytes(
            scene.lungs.vertices as u64,
            0,
            args.frames,
            args.float_targets,
        );
    if early > MAX_FILE_BYTES {
        anyhow::bail!(
            "the file would be more than {:.1} GB ({} frames of {generated} × {} vertices): at most \
             {:.1} GB is written; ask for fewer --frames or --vertices",
            early as f64 / 1e9,
            args.frames,
            scene.lungs.vertices,
            MAX_FILE_BYTES as f64 / 1e9
        );
    }
    let prepared = crate::prepare::prepare(scene, &args.kernels)?;
    let scene = prepared.scene;
    eprintln!(
        "lungdyn: running the scene to its breath {} ({} frames)",
        args.breath, args.frames
    );
    let breath = sample_breath(&scene, args.frames as usize, args.breath)?;
    let mut loaded = Vec::new();
    for &side in &scene.lungs.sides {
        let kernel = scene.lung_kernel(side)?;
        let lung = RenderLung::from_kernel(&kernel, scene.lungs.mode)
            .with_context(|| format!("the {} lung's kernel", side.name()))?;
        loaded.push(lung);
    }
    check_size(&loaded, args.frames, args.float_targets)?;
    let lungs = loaded
        .into_iter()
        .map(|lung| deformed_frames(&lung, &breath.frames).map(|p| (lung, p)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let tumour = tumour_track(&scene, &lungs, &breath.frames)?;
    let name = args.scene.as_ref().and_then(|p| p.file_stem()).map_or_else(
        || "default".to_string(),
        |s| s.to_string_lossy().into_owned(),
    );
    let mut report = GltfReport {
        out: args.out.display().to_string(),
        bytes: 0,
        scene: origin,
        mode: scene.lungs.mode.to_string(),
        frames: args.frames,
        breath: args.breath,
        period_s: breath.period_s,
        lungs: lungs
            .iter()
            .map(|(l, p)| lung_summary(l, p, &breath.frames))
            .collect(),
        tumour: tumour.as_ref().map(|t| t.summary.clone()),
        opacity: args
            .opacity
            .unwrap_or(if tumour.is_some() { 0.5 } else { 1.0 }),
        targets: TargetsExport {
            encoding: if args.float_targets {
                "float"
            } else {
                "quantized"
            },
            ..Default::default()
        },
        seconds: 0.0,
    };
    let glb = build(&name, &mut report, &breath, &lungs, tumour.as_ref())?;
    outfile::write_atomically(&args.out, |w| {
        use std::io::Write;
        w.write_all(&glb)
    })
    .with_context(|| format!("cannot write {}", args.out.display()))?;
    report.bytes = glb.len() as u64;
    report.seconds = (started.elapsed().as_secs_f64() * 1000.0).round() / 1000.0;
    Ok(report)
}

/// Refuse a file past [`MAX_FILE_BYTES`] before computing its frames (each frame after the first
/// costs [`target_bytes`] per vertex; GLB cannot hold more than 4 GiB).
fn check_size(lungs: &[RenderLung], frames: u32, float_targets: bool) -> anyhow::Result<()> {
    let estimate: u64 = lungs
        .iter()
        .map(|l| {
            let (v, t) = (l.lung.len() as u64, l.lung.triangles.len() as u64);
            lung_bytes(v, t, frames, float_targets)
        })
        .sum();
    if estimate > MAX_FILE_BYTES {
        anyhow::bail!(
            "the file would be about {:.1} GB ({frames} frames of {} vertices): at most {:.1} GB is \
             written; ask for fewer --frames or --vertices",
            estimate as f64 / 1e9,
            lungs.iter().map(|l| l.lung.len()).sum::<usize>(),
            MAX_FILE_BYTES as f64 / 1e9
        );
    }
    Ok(())
}

fn check_args(args: &GltfArgs) -> anyhow::Result<()> {
    if !(2..=MAX_FRAMES).contains(&args.frames) {
        anyhow::bail!(
            "--frames {}: give 2 to {MAX_FRAMES} frames over the breath ({DEFAULT_FRAMES} by default; \
             each frame after the first adds a copy of the lungs' positions to the file)",
            args.frames
        );
    }
    if let Some(o) = args.opacity {
        if !(0.05..=1.0).contains(&o) {
            anyhow::bail!(
                "--opacity {o}: give the lungs' opacity from 0.05 (almost clear) to 1 (opaque)"
            );
        }
    }
    if args.breath == 0 || args.breath > MAX_BREATH {
        anyhow::bail!(
            "--breath {}: give 1 to {MAX_BREATH} (breaths are counted from 1, the run's first, which \
             starts from the scene's initial state)",
            args.breath
        );
    }
    let ext = args.out.extension().and_then(|e| e.to_str()).unwrap_or("");
    if !ext.eq_ignore_ascii_case("glb") {
        anyhow::bail!(
            "--out {}: lungdyn writes binary glTF; name the file .glb (one file with its buffers, \
             which every viewer opens)",
            args.out.display()
        );
    }
    crate::outputs::check_writable(args.out.parent().unwrap_or(std::path::Path::new(".")))?;
    Ok(())
}

/// The lung whose breaths the export counts and loops: the first of `[lungs] sides` that the scene's
/// disease leaves alone, else the first (a complete pneumothorax of the first lung holds it still,
/// and its breath was once the one counted: nothing to export although the other lung breathed).
fn reference_lung(scene: &Scene) -> anyhow::Result<lung_model::mesh::Side> {
    let affected = match scene.disease_spec() {
        Ok(Some(d)) => d.affected(),
        _ => Vec::new(),
    };
    let sides = &scene.lungs.sides;
    sides
        .iter()
        .find(|s| !affected.contains(s))
        .or(sides.first())
        .copied()
        .context("the scene has no lungs to export")
}

/// Run `scene` headless to the end of its `breath`-th breath (counted on its [`reference_lung`]: the
/// engine starts a lung at the start of inspiration, so its first breath runs from tick 0 to its first
/// cycle change, each later one from a change to the next) and keep `n` frames evenly spread over it.
fn sample_breath(scene: &Scene, n: usize, breath: u32) -> anyhow::Result<Breath> {
    let hz = scene.engine.tick_hz;
    let reference = reference_lung(scene)?;
    let slot = reference.index();
    let max_ticks = (MAX_SIMULATED_S * hz).round() as u64;
    // Breaths begun so far: the first active frame begins one when it is at the start of
    // inspiration (a run that starts mid-breath waits for the next cycle change).
    let mut begun = 0u32;
    let mut last_cycle: Option<u32> = None;
    let mut kept: Vec<EngineFrame> = Vec::new();
    let mut done = false;
    engine::headless::run_while(
        engine::runtime::EngineCore::new(scene)?,
        max_ticks,
        &mut crate::scene_check::still_patient(scene),
        &mut |_tick, f| {
            let l = &f.lungs[slot];
            if l.is_active() {
                match last_cycle {
                    None if l.phase.abs() < 1e-6 => begun = 1,
                    Some(c) if c != l.cycle => begun += 1,
                    _ => {}
                }
                last_cycle = Some(l.cycle);
            }
            if begun > breath {
                done = true;
                return false;
            }
            if begun == breath {
                kept.push(*f);
            }
            true
        },
    )?;
    let side = reference.name();
    if !done {
        anyhow::bail!(
            "the {side} lung completed {} breath(s) in {MAX_SIMULATED_S} s of simulated time, not the \
             {breath} --breath asks for: an arrested or very slow breath has no breath to export \
             (lungdyn scene run shows the scene's course)",
            begun.saturating_sub(1)
        );
    }
    if kept.len() < n {
        anyhow::bail!(
            "breath {breath} of the {side} lung lasts {} engine ticks, fewer than the {n} --frames asked \
             for: give at most {} frames",
            kept.len(),
            kept.len()
        );
    }
    let held = kept
        .iter()
        .any(|f| f.lungs[slot].flags & ipc_types::lung_flags::HELD != 0);
    let (lo, hi) = kept
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), f| {
            let v = f.lungs[slot].volume_ml;
            (lo.min(v), hi.max(v))
        });
    if held || hi - lo < 1.0 {
        anyhow::bail!(
            "the {side} lung does not breathe in breath {breath} (volume {lo:.0}–{hi:.0} ml{}): \
             nothing to export as a breath",
            if held { ", held" } else { "" }
        );
    }
    let len = kept.len();
    let picks: Vec<usize> = (0..n).map(|i| i * len / n).collect();
    Ok(Breath {
        frames: picks.iter().map(|&i| kept[i]).collect(),
        times_s: picks.iter().map(|&i| (i as f64 / hz) as f32).collect(),
        period_s: len as f64 / hz,
    })
}

/// One lung's positions (body frame, mm) as the renderer draws them for frame `l`:
/// `h + (1 − c)(p − h) + s·u + o` (EQUATIONS.md §4.1), the deformation by `CpuLung`.
fn lung_positions(lung: &mut RenderLung, l: &LungFrame) -> anyhow::Result<Vec<[f32; 3]>> {
    let mut out = vec![[0.0f32; 3]; lung.lung.len()];
    lung_positions_into(lung, l, &mut out)?;
    Ok(out)
}

/// [`lung_positions`] into `out` (one entry per vertex of the lung): `lungdyn demo --igtl-serve`
/// sends these to Slicer every frame, without allocating.
pub fn lung_positions_into(
    lung: &mut RenderLung,
    l: &LungFrame,
    out: &mut [[f32; 3]],
) -> anyhow::Result<()> {
    let side = lung.side.name();
    if !l.is_active() {
        anyhow::bail!("the {side} lung is not active in the engine's frame");
    }
    let n = (l.coeff_count as usize).min(MAX_COEFFS);
    let c = l.collapse;
    let offset = [0, 1, 2].map(|a| l.offset_mm[a] + c * l.hilum_mm[a]);
    lung.lung
        .deform_into(l.deform_scale, &l.coeffs[..n], offset, out)
        .with_context(|| format!("the {side} lung"))?;
    if c != 0.0 {
        for (q, p) in out.iter_mut().zip(&lung.lung.positions) {
            for a in 0..3 {
                q[a] -= c * p[a];
            }
        }
    }
    if let Some(i) = out.iter().position(|q| !q.iter().all(|v| v.is_finite())) {
        anyhow::bail!(
            "the {side} lung's vertex {i} is not finite at volume {} ml (scale {}, collapse {c}): \
             a bug, please report it with the scene",
            l.volume_ml,
            l.deform_scale
        );
    }
    Ok(())
}

/// The tumour's centre (body frame, mm) in frame `l` of its lung, as the renderer places it.
pub fn tumour_centre(
    meta: &lung_model::kernel::TumourMeta,
    mode: lung_model::deform::modes::DeformMode,
    l: &LungFrame,
) -> anyhow::Result<[f64; 3]> {
    let n = (l.coeff_count as usize).min(MAX_COEFFS);
    let d = meta
        .displacement_mm(mode, &l.coeffs[..n])
        .context("the tumour record does not fit the scene's mode; bake the kernel again")?;
    let p = meta.position_mm(
        d,
        l.deform_scale as f64,
        l.collapse as f64,
        l.hilum_mm.map(f64::from),
        l.offset_mm.map(f64::from),
    );
    if !p.iter().all(|v| v.is_finite()) {
        anyhow::bail!("the tumour centre is not finite: a bug, please report it with the scene");
    }
    Ok(p)
}

/// Every frame's positions of `lung` (body frame, mm).
fn deformed_frames(
    lung: &RenderLung,
    frames: &[EngineFrame],
) -> anyhow::Result<Vec<Vec<[f32; 3]>>> {
    let mut lung = lung.clone();
    let slot = lung.side.index();
    frames
        .iter()
        .map(|f| lung_positions(&mut lung, &f.lungs[slot]))
        .collect()
}

fn lung_summary(lung: &RenderLung, frames: &[Vec<[f32; 3]>], engine: &[EngineFrame]) -> LungExport {
    let slot = lung.side.index();
    let volumes = engine.iter().map(|f| f.lungs[slot].volume_ml as f64);
    let lo = volumes.clone().fold(f64::INFINITY, f64::min);
    let hi = volumes.fold(f64::NEG_INFINITY, f64::max);
    let base = &frames[0];
    let moved = frames
        .iter()
        .flat_map(|f| f.iter().zip(base).map(|(p, q)| dist(*p, *q)))
        .fold(0.0f64, f64::max);
    LungExport {
        side: lung.side.name(),
        vertices: lung.lung.len(),
        triangles: lung.lung.triangles.len(),
        // The lobes its vertices are in, in code order (the lobes `LobeSplit` makes a primitive of),
        // without cutting the mesh a second time for their names.
        lobes: lung.lobe_codes().map_or_else(Vec::new, |codes| {
            let present: std::collections::BTreeSet<u8> = codes.iter().copied().collect();
            present
                .into_iter()
                .map(|c| Lobe::from_code(c).unwrap_or(Lobe::Unknown).name())
                .collect()
        }),
        volume_ml: [r3(lo), r3(hi)],
        max_motion_mm: r3(moved),
    }
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3)
        .map(|k| ((a[k] - b[k]) as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn r3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// A vertex the lobe cut adds: a point of an edge, `(1 − t)·a + t·b` (`a < b`), or a triangle's
/// centre, the mean of its corners.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Added {
    Edge(u32, u32, f32),
    Centre(u32, u32, u32),
}

/// The lung's triangles by lobe, with every triangle whose corners lie in two or three lobes cut
/// between them: on each edge whose ends lie in two lobes (where the fissure plane between those
/// lobes crosses it, [`fissure_cut`], else its midpoint) and at its centre where all three differ,
/// each piece given to the lobe of the corners it holds. The boundary then runs across the
/// triangles as the renderer draws it (`draw.wgsl` finds a fragment's lobe from the same planes),
/// where giving each whole triangle to one lobe made a triangle-wide zig-zag. A cut point is an
/// added vertex, a fixed blend of two or three of the mesh's, and so it is in every frame
/// ([`Self::extend`]): a morph target moves it exactly as the surface it lies on, the pieces are
/// coplanar with the triangle they cut (same volume, same winding) and an edge's cut point is
/// shared by both its triangles (the surface stays closed).
struct LobeSplit {
    /// Vertices after the mesh's own, in the order their indices were given.
    added: Vec<Added>,
    /// The triangles of each lobe (`None`: the kernel has no lobe codes, every triangle), in code
    /// order, indexing the mesh's vertices then [`Self::added`].
    groups: Vec<(Option<Lobe>, Vec<[u32; 3]>)>,
}

impl LobeSplit {
    fn of(lung: &RenderLung) -> Self {
        let codes = lung.lobe_codes();
        let at = codes.map(|c| fissure_cut(lung.side, &lung.lung.positions, c));
        Self::cut(&lung.lung.triangles, lung.lung.len(), codes, |a, b| {
            at.as_ref().map_or(0.5, |f| f(a, b))
        })
    }

    /// The cut of `triangles` over `n` vertices of lobe codes `codes` (one per vertex), an edge
    /// `a < b` between two lobes cut at `(1 − t)·a + t·b`, `t = at(a, b)`.
    fn cut(
        triangles: &[[u32; 3]],
        n: usize,
        codes: Option<&[u8]>,
        at: impl Fn(u32, u32) -> f32,
    ) -> Self {
        let Some(codes) = codes else {
            return Self {
                added: Vec::new(),
                groups: vec![(None, triangles.to_vec())],
            };
        };
        let mut added = Vec::new();
        // Each cut edge's added vertex, by the edge (shared by the two triangles on it).
        let mut cuts = std::collections::HashMap::new();
        let mut by_code: std::collections::BTreeMap<u8, Vec<[u32; 3]>> = Default::default();
        let add = |a: Added, added: &mut Vec<Added>| -> u32 {
            added.push(a);
            (n + added.len() - 1) as u32
        };
        for &t in triangles {
            let c = t.map(|v| codes[v as usize]);
            if c[0] == c[1] && c[1] == c[2] {
                by_code.entry(c[0]).or_default().push(t);
                continue;
            }
            let mut cut_on = |a: u32, b: u32, added: &mut Vec<Added>| -> u32 {
                let (lo, hi) = (a.min(b), a.max(b));
                *cuts
                    .entry((lo, hi))
                    .or_insert_with(|| add(Added::Edge(lo, hi, at(lo, hi)), added))
            };
            if c[0] != c[1] && c[1] != c[2] && c[0] != c[2] {
                // Three lobes: each corner's piece, (corner, its next edge's cut, centre, its
                // previous edge's cut), counter-clockwise as the triangle.
                let m = [0, 1, 2].map(|k| cut_on(t[k], t[(k + 1) % 3], &mut added));
                let g = add(Added::Centre(t[0], t[1], t[2]), &mut added);
                for k in 0..3 {
                    let piece = by_code.entry(c[k]).or_default();
                    piece.push([t[k], m[k], g]);
                    piece.push([t[k], g, m[(k + 2) % 3]]);
                }
                continue;
            }
            // Two lobes: turned so that corners 0 and 1 share one and corner 2 is alone.
            let r = if c[0] == c[1] {
                0
            } else if c[1] == c[2] {
                1
            } else {
                2
            };
            let [a, b, o] = [t[r], t[(r + 1) % 3], t[(r + 2) % 3]];
            let (ca, co) = (codes[a as usize], codes[o as usize]);
            let mb = cut_on(b, o, &mut added);
            let ma = cut_on(o, a, &mut added);
            let pair = by_code.entry(ca).or_default();
            pair.push([a, b, mb]);
            pair.push([a, mb, ma]);
            by_code.entry(co).or_default().push([mb, o, ma]);
        }
        let groups = by_code
            .into_iter()
            .map(|(code, tris)| (Some(Lobe::from_code(code).unwrap_or(Lobe::Unknown)), tris))
            .collect();
        Self { added, groups }
    }

    /// `v` (one value per mesh vertex) with the added vertices' blends after it.
    fn extend(&self, v: &[[f32; 3]]) -> Vec<[f32; 3]> {
        let blend = |w: &[(u32, f64)]| {
            let s = w.iter().fold([0.0f64; 3], |s, &(i, w)| {
                let p = v[i as usize];
                [0, 1, 2].map(|a| s[a] + w * p[a] as f64)
            });
            s.map(|x| x as f32)
        };
        let mut out = Vec::with_capacity(v.len() + self.added.len());
        out.extend_from_slice(v);
        out.extend(self.added.iter().map(|a| match *a {
            Added::Edge(p, q, t) => blend(&[(p, 1.0 - t as f64), (q, t as f64)]),
            Added::Centre(p, q, r) => blend(&[(p, 1.0 / 3.0), (q, 1.0 / 3.0), (r, 1.0 / 3.0)]),
        }));
        out
    }
}

/// Where an edge between two lobes is cut: `t` along it from its first vertex to its second, at the
/// fissure plane that separates those lobes (the oblique one from a lower lobe, the horizontal one
/// between the right upper and middle lobes), with the signed distances the renderer draws by
/// (`lobes::fissure_distances` of the rest mesh), kept within the middle 80 % of the edge so no
/// piece is a sliver. Where the plane does not separate the two ends (lobe codes from a labelmap
/// rather than from the planes, or an unknown lobe): the midpoint.
fn fissure_cut(side: Side, rest: &[[f32; 3]], codes: &[u8]) -> impl Fn(u32, u32) -> f32 {
    let d = lung_model::mesh::lobes::fissure_distances(side, rest);
    let codes = codes.to_vec();
    move |a: u32, b: u32| {
        let (ca, cb) = (codes[a as usize], codes[b as usize]);
        let lower = [Lobe::RightLower.code(), Lobe::LeftLower.code()];
        let plane = if lower.contains(&ca) != lower.contains(&cb) {
            0
        } else if [ca, cb].contains(&Lobe::RightUpper.code())
            && [ca, cb].contains(&Lobe::RightMiddle.code())
        {
            1
        } else {
            return 0.5;
        };
        let (da, db) = (d[a as usize][plane], d[b as usize][plane]);
        if da * db < 0.0 {
            (da / (da - db)).clamp(0.1, 0.9) as f32
        } else {
            0.5
        }
    }
}

/// The tumour's ellipsoid and its centre per frame (body frame, mm).
struct TumourTrack {
    /// Its lung's slot.
    side: Side,
    radii_mm: [f64; 3],
    centres_mm: Vec<[f64; 3]>,
    summary: TumourExport,
}

fn tumour_track(
    scene: &Scene,
    lungs: &[(RenderLung, Vec<Vec<[f32; 3]>>)],
    frames: &[EngineFrame],
) -> anyhow::Result<Option<TumourTrack>> {
    let Some(t) = scene.tumour() else {
        return Ok(None);
    };
    let Some((lung, _)) = lungs.iter().find(|(l, _)| l.side == t.side) else {
        return Ok(None);
    };
    let meta = lung.tumour.as_ref().with_context(|| {
        format!(
            "the {} lung's kernel has no tumour record (baked before lungdyn recorded it); bake it again",
            t.side.name()
        )
    })?;
    let mut centres = Vec::with_capacity(frames.len());
    for f in frames {
        centres.push(tumour_centre(
            meta,
            scene.lungs.mode,
            &f.lungs[t.side.index()],
        )?);
    }
    let motion = [0, 1, 2].map(|a| {
        let (lo, hi) = centres
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), c| {
                (lo.min(c[a]), hi.max(c[a]))
            });
        r3(hi - lo)
    });
    Ok(Some(TumourTrack {
        side: t.side,
        radii_mm: t.radii_mm,
        centres_mm: centres,
        summary: TumourExport {
            side: t.side.name(),
            radii_mm: t.radii_mm,
            motion_mm: motion,
        },
    }))
}

/// The glTF document and its one binary buffer as they are assembled.
struct Doc {
    root: json::Root,
    bin: Vec<u8>,
    /// Whether a quantised accessor was written (the file then requires `KHR_mesh_quantization`).
    quantized: bool,
}

impl Doc {
    fn new() -> Self {
        Doc {
            root: json::Root::default(),
            bin: Vec::new(),
            quantized: false,
        }
    }

    /// A buffer view over `bytes` (appended at a 4-byte boundary), with `stride` bytes between
    /// elements where they are padded.
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
        stride: Option<usize>,
    ) -> json::Index<json::buffer::View> {
        while self.bin.len() % 4 != 0 {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: json::Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: stride.map(json::buffer::Stride),
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    }

    /// An accessor of `count` elements of `type_` over a new view of `bytes`; `normalized` gives
    /// the padded elements' stride of normalised integers.
    #[allow(clippy::too_many_arguments)]
    fn accessor(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
        count: usize,
        component: json::accessor::ComponentType,
        type_: json::accessor::Type,
        bounds: Option<(serde_json::Value, serde_json::Value)>,
        normalized: Option<usize>,
        name: &str,
    ) -> json::Index<json::Accessor> {
        let view = self.view(bytes, target, normalized);
        let (min, max) = bounds.map_or((None, None), |(a, b)| (Some(a), Some(b)));
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(type_),
            min,
            max,
            name: Some(name.to_string()),
            normalized: normalized.is_some(),
            sparse: None,
        })
    }

    /// Three-component floats (with the bounds glTF requires of positions when `bounded`).
    fn vec3(
        &mut self,
        v: &[[f32; 3]],
        vertex: bool,
        bounded: bool,
        name: &str,
    ) -> json::Index<json::Accessor> {
        let bytes: Vec<u8> = v.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
        let bounds = bounded.then(|| {
            let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
            for p in v {
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
            }
            (serde_json::json!(lo), serde_json::json!(hi))
        });
        let target = vertex.then_some(json::buffer::Target::ArrayBuffer);
        self.accessor(
            &bytes,
            target,
            v.len(),
            json::accessor::ComponentType::F32,
            json::accessor::Type::Vec3,
            bounds,
            None,
            name,
        )
    }

    /// Morph-target differences as signed normalised integers (`KHR_mesh_quantization`): 16-bit
    /// (`wide`: elements of 8 bytes, 2 of them padding, a step of 1/32767) or 8-bit (4 bytes, 1
    /// padding, a step of 1/127), each element on 4 bytes as glTF asks of vertex attributes; the
    /// bounds, where asked, the stored integers (glTF's min and max are never normalised). Returns
    /// the accessor and the values a viewer decodes, or None where a difference lies outside −1…1
    /// (or is not finite), which normalised integers cannot hold.
    fn vec3_normalized(
        &mut self,
        v: &[[f32; 3]],
        wide: bool,
        bounded: bool,
        name: &str,
    ) -> Option<(json::Index<json::Accessor>, Vec<[f32; 3]>)> {
        if v.iter().flatten().any(|x| !x.is_finite() || x.abs() > 1.0) {
            return None;
        }
        let scale = if wide { 32767.0f32 } else { 127.0 };
        let q: Vec<[i16; 3]> = v
            .iter()
            .map(|p| p.map(|x| (x * scale).round().clamp(-scale, scale) as i16))
            .collect();
        let decoded = q
            .iter()
            .map(|c| c.map(|k| (f32::from(k) / scale).max(-1.0)))
            .collect();
        let (stride, component) = if wide {
            (8, json::accessor::ComponentType::I16)
        } else {
            (4, json::accessor::ComponentType::I8)
        };
        let mut bytes = Vec::with_capacity(v.len() * stride);
        for c in &q {
            for &k in c {
                if wide {
                    bytes.extend_from_slice(&k.to_le_bytes());
                } else {
                    bytes.push(k as i8 as u8);
                }
            }
            let used = if wide { 6 } else { 3 };
            bytes.resize(bytes.len() + stride - used, 0);
        }
        let bounds = bounded.then(|| {
            let lo = [0, 1, 2].map(|a| q.iter().map(|c| c[a]).min().unwrap_or(0));
            let hi = [0, 1, 2].map(|a| q.iter().map(|c| c[a]).max().unwrap_or(0));
            (serde_json::json!(lo), serde_json::json!(hi))
        });
        self.quantized = true;
        let acc = self.accessor(
            &bytes,
            Some(json::buffer::Target::ArrayBuffer),
            v.len(),
            component,
            json::accessor::Type::Vec3,
            bounds,
            Some(stride),
            name,
        );
        Some((acc, decoded))
    }

    /// Scalar floats (an animation's key times carry their bounds).
    fn scalars(&mut self, v: &[f32], bounded: bool, name: &str) -> json::Index<json::Accessor> {
        let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        let bounds = bounded.then(|| {
            let lo = v.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = v.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            (serde_json::json!([lo]), serde_json::json!([hi]))
        });
        self.accessor(
            &bytes,
            None,
            v.len(),
            json::accessor::ComponentType::F32,
            json::accessor::Type::Scalar,
            bounds,
            None,
            name,
        )
    }

    /// Triangle indices, corners reversed (the body → glTF map is a reflection), 16-bit where the
    /// vertices allow.
    fn indices(
        &mut self,
        tris: &[[u32; 3]],
        vertices: usize,
        name: &str,
    ) -> json::Index<json::Accessor> {
        let flat = tris.iter().flat_map(|t| [t[0], t[2], t[1]]);
        let (bytes, component): (Vec<u8>, _) = if vertices <= u16::MAX as usize {
            (
                flat.flat_map(|i| (i as u16).to_le_bytes()).collect(),
                json::accessor::ComponentType::U16,
            )
        } else {
            (
                flat.flat_map(u32::to_le_bytes).collect(),
                json::accessor::ComponentType::U32,
            )
        };
        let target = Some(json::buffer::Target::ElementArrayBuffer);
        self.accessor(
            &bytes,
            target,
            tris.len() * 3,
            component,
            json::accessor::Type::Scalar,
            None,
            None,
            name,
        )
    }

    /// A material of an sRGB colour (converted to glTF's linear base colour factor), blended at
    /// `opacity` below 1.
    fn material(&mut self, name: &str, srgb: [u8; 3], opacity: f32) -> json::Index<json::Material> {
        let lin = renderer::draw::srgb_to_linear;
        self.root.push(json::Material {
            name: Some(name.to_string()),
            pbr_metallic_roughness: json::material::PbrMetallicRoughness {
                base_color_factor: json::material::PbrBaseColorFactor([
                    lin(srgb[0]),
                    lin(srgb[1]),
                    lin(srgb[2]),
                    opacity,
                ]),
                metallic_factor: json::material::StrengthFactor(0.0),
                roughness_factor: json::material::StrengthFactor(0.55),
                ..Default::default()
            },
            alpha_mode: Valid(if opacity < 1.0 {
                json::material::AlphaMode::Blend
            } else {
                json::material::AlphaMode::Opaque
            }),
            ..Default::default()
        })
    }
}

fn extras(v: &serde_json::Value) -> anyhow::Result<json::Extras> {
    Ok(Some(serde_json::value::to_raw_value(v)?))
}

fn node(name: &str) -> json::Node {
    json::Node {
        name: Some(name.to_string()),
        ..Default::default()
    }
}

/// The `.glb` bytes: the lungs, the tumour, the breath's animation and the metadata.
fn build(
    name: &str,
    report: &mut GltfReport,
    breath: &Breath,
    lungs: &[(RenderLung, Vec<Vec<[f32; 3]>>)],
    tumour: Option<&TumourTrack>,
) -> anyhow::Result<Vec<u8>> {
    let mut doc = Doc::new();
    // Key times: each frame, then the breath's end showing the first frame again (seamless loop).
    let mut keys = breath.times_s.clone();
    keys.push(breath.period_s as f32);
    let input = doc.scalars(&keys, true, "breath key times (s)");
    let mut animation = json::Animation {
        extensions: None,
        extras: Default::default(),
        channels: Vec::new(),
        name: Some("breath".to_string()),
        samplers: Vec::new(),
    };
    let mut children = Vec::new();
    let float_targets = report.targets.encoding == "float";
    for (lung, frames) in lungs {
        let n = lung_node(
            &mut doc,
            lung,
            frames,
            breath,
            report.opacity,
            (input, float_targets),
            &mut animation,
            &mut report.targets,
        )?;
        children.push(n);
    }
    let t = &mut report.targets;
    t.position_error_max_mm = (t.position_error_max_mm * 1e4).ceil() / 1e4;
    t.normal_error_max_deg = (t.normal_error_max_deg * 1e3).ceil() / 1e3;
    if doc.quantized {
        doc.root.extensions_used = vec![QUANTIZATION.to_string()];
        doc.root.extensions_required = vec![QUANTIZATION.to_string()];
    }
    if let Some(t) = tumour {
        children.push(tumour_node(&mut doc, t, input, &mut animation));
    }
    doc.root.animations.push(animation);
    let mut top = node(&format!("lungdyn: {name}"));
    top.children = Some(children);
    let top = doc.root.push(top);
    let scene = doc.root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: Some(name.to_string()),
        nodes: vec![top],
    });
    doc.root.scene = Some(scene);
    doc.root.asset = json::Asset {
        copyright: None,
        extensions: None,
        extras: extras(&metadata(name, report, breath, lungs))?,
        generator: Some(format!(
            "lungdyn {} (export gltf)",
            env!("CARGO_PKG_VERSION")
        )),
        min_version: None,
        version: "2.0".to_string(),
    };
    while doc.bin.len() % 4 != 0 {
        doc.bin.push(0);
    }
    doc.root.buffers.push(json::Buffer {
        byte_length: USize64::from(doc.bin.len()),
        name: None,
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let json = json::serialize::to_vec(&doc.root)?;
    let glb = gltf::binary::Glb {
        header: gltf::binary::Header {
            magic: *b"glTF",
            version: 2,
            length: 0, // computed by `to_vec`
        },
        json: json.into(),
        bin: Some(doc.bin.into()),
    };
    Ok(glb.to_vec()?)
}

/// One lung: its mesh (base, normals, one morph target per later frame, a primitive per lobe), its
/// node, and its weights' channel in `animation` (on the key times `keys.0`; `keys.1`: every target
/// as floats). What quantising cost is added to `cost`.
#[allow(clippy::too_many_arguments)]
fn lung_node(
    doc: &mut Doc,
    lung: &RenderLung,
    frames: &[Vec<[f32; 3]>],
    breath: &Breath,
    opacity: f32,
    keys: (json::Index<json::Accessor>, bool),
    animation: &mut json::Animation,
    cost: &mut TargetsExport,
) -> anyhow::Result<json::Index<json::Node>> {
    let (input, float_targets) = keys;
    let side = lung.side.name();
    let split = LobeSplit::of(lung);
    let base: Vec<[f32; 3]> = split
        .extend(&frames[0])
        .into_iter()
        .map(body_to_gltf)
        .collect();
    // Each frame's unit normals in glTF's axes; an added vertex's: the mean of its corners', made
    // unit again.
    let mut scratch = vec![[0.0f32; 3]; lung.lung.len()];
    let mut normals_of = |f: &[[f32; 3]]| -> Vec<[f32; 3]> {
        lung.lung.normals_into(f, &mut scratch);
        split
            .extend(&scratch)
            .into_iter()
            .map(unit_gltf_direction)
            .collect()
    };
    let normals = normals_of(&frames[0]);
    let position = doc.vec3(&base, true, true, &format!("{side} lung: first frame (m)"));
    let normal = doc.vec3(&normals, true, false, &format!("{side} lung: normals"));
    let mut targets = Vec::new();
    let mut target_names = Vec::new();
    for (k, f) in frames.iter().enumerate().skip(1) {
        let delta: Vec<[f32; 3]> = split
            .extend(f)
            .iter()
            .zip(&base)
            .map(|(&p, b)| {
                let g = body_to_gltf(p);
                [g[0] - b[0], g[1] - b[1], g[2] - b[2]]
            })
            .collect();
        let frame_normals = normals_of(f);
        let turn: Vec<[f32; 3]> = frame_normals
            .iter()
            .zip(&normals)
            .map(|(n, n0)| [n[0] - n0[0], n[1] - n0[1], n[2] - n0[2]])
            .collect();
        let name = format!(
            "frame {} of {}, {:.2} s, {:.0} ml",
            k + 1,
            frames.len(),
            breath.times_s[k],
            breath.frames[k].lungs[lung.side.index()].volume_ml
        );
        let positions = target(
            doc,
            &delta,
            (true, float_targets),
            cost,
            &format!("{side} lung: {name}"),
        );
        let turned = target(
            doc,
            &turn,
            (false, float_targets),
            cost,
            &format!("{side} lung: {name}, normals"),
        );
        for (i, d) in positions.1.iter().enumerate() {
            let e = (0..3)
                .map(|a| (d[a] - delta[i][a]).powi(2))
                .sum::<f32>()
                .sqrt();
            cost.position_error_max_mm = cost.position_error_max_mm.max(f64::from(e) * 1e3);
        }
        for (i, d) in turned.1.iter().enumerate() {
            let rebuilt = [0, 1, 2].map(|a| normals[i][a] + d[a]);
            let angle = angle_deg(rebuilt, frame_normals[i]);
            cost.normal_error_max_deg = cost.normal_error_max_deg.max(angle);
        }
        targets.push(json::mesh::MorphTarget {
            positions: Some(positions.0),
            normals: Some(turned.0),
            tangents: None,
        });
        target_names.push(name);
    }
    let mut primitives = Vec::new();
    for (lobe, tris) in split.groups {
        let (label, colour) = match lobe {
            Some(l) => (format!("{l}"), l.colour()),
            None => (format!("{side} lung"), Lobe::Unknown.colour()),
        };
        let material = doc.material(&label, colour, opacity);
        let indices = doc.indices(&tris, base.len(), &format!("{label}: triangles"));
        let mut attributes = std::collections::BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), position);
        attributes.insert(Valid(json::mesh::Semantic::Normals), normal);
        primitives.push(json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: Some(targets.clone()),
        });
    }
    let mesh = doc.root.push(json::Mesh {
        extensions: None,
        extras: extras(&serde_json::json!({ "targetNames": target_names }))?,
        name: Some(format!("{side} lung")),
        primitives,
        weights: Some(vec![0.0; targets.len()]),
    });
    let mut n = node(&format!("{side} lung"));
    n.mesh = Some(mesh);
    let n = doc.root.push(n);
    // Key k shows frame k: weight 1 on its target (frame 0 is the base: all 0); the last key the
    // first frame again.
    let t = targets.len();
    let mut weights = vec![0.0f32; (frames.len() + 1) * t];
    for k in 1..frames.len() {
        weights[k * t + (k - 1)] = 1.0;
    }
    let output = doc.scalars(&weights, false, &format!("{side} lung: weights per key"));
    push_channel(
        animation,
        input,
        output,
        n,
        json::animation::Property::MorphTargetWeights,
    );
    Ok(n)
}

/// One morph target's differences (`kind.0`: positions, bounded and 16-bit; else normals, 8-bit):
/// quantised unless `kind.1` asks for floats or a difference leaves −1…1 (then counted in
/// `cost.kept_float`). Returns the accessor and the values a viewer decodes.
fn target(
    doc: &mut Doc,
    v: &[[f32; 3]],
    kind: (bool, bool),
    cost: &mut TargetsExport,
    name: &str,
) -> (json::Index<json::Accessor>, Vec<[f32; 3]>) {
    let (positions, float_targets) = kind;
    if !float_targets {
        if let Some(q) = doc.vec3_normalized(v, positions, positions, name) {
            return q;
        }
        cost.kept_float += 1;
    }
    (doc.vec3(v, true, positions, name), v.to_vec())
}

/// The angle between two directions (neither need be unit), degrees; 0 where either is zero.
fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
    let a = a.map(f64::from);
    let b = b.map(f64::from);
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cross = [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ];
    let sin = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
    if sin == 0.0 && dot == 0.0 {
        0.0
    } else {
        sin.atan2(dot).to_degrees()
    }
}

fn push_channel(
    animation: &mut json::Animation,
    input: json::Index<json::Accessor>,
    output: json::Index<json::Accessor>,
    node: json::Index<json::Node>,
    path: json::animation::Property,
) {
    let sampler = json::Index::new(animation.samplers.len() as u32);
    animation.samplers.push(json::animation::Sampler {
        extensions: None,
        extras: Default::default(),
        input,
        interpolation: Valid(json::animation::Interpolation::Linear),
        output,
    });
    animation.channels.push(json::animation::Channel {
        sampler,
        target: json::animation::Target {
            extensions: None,
            extras: Default::default(),
            node,
            path: Valid(path),
        },
        extensions: None,
        extras: Default::default(),
    });
}

/// The tumour: an ellipsoid of its radii about its node's origin, the node moved along the centre's
/// path on the breath's keys.
fn tumour_node(
    doc: &mut Doc,
    t: &TumourTrack,
    input: json::Index<json::Accessor>,
    animation: &mut json::Animation,
) -> json::Index<json::Node> {
    let (unit, tris) = renderer::tumour::unit_sphere();
    let r = t.radii_mm.map(|v| v as f32);
    let p: Vec<[f32; 3]> = unit
        .iter()
        .map(|u| body_to_gltf([u[0] * r[0], u[1] * r[1], u[2] * r[2]]))
        .collect();
    let normals: Vec<[f32; 3]> = unit
        .iter()
        // An ellipsoid's normal: the unit sphere's divided by the radii, normalised.
        .map(|u| unit_gltf_direction([u[0] / r[0], u[1] / r[1], u[2] / r[2]]))
        .collect();
    let position = doc.vec3(&p, true, true, "tumour: ellipsoid (m)");
    let normal = doc.vec3(&normals, true, false, "tumour: normals");
    let indices = doc.indices(&tris, p.len(), "tumour: triangles");
    let material = doc.material("tumour", [140, 235, 30], 1.0);
    let mut attributes = std::collections::BTreeMap::new();
    attributes.insert(Valid(json::mesh::Semantic::Positions), position);
    attributes.insert(Valid(json::mesh::Semantic::Normals), normal);
    let mesh = doc.root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        name: Some("tumour".to_string()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });
    let centre = |c: &[f64; 3]| body_to_gltf(c.map(|v| v as f32));
    let mut n = node(&format!("tumour ({} lung)", t.side.name()));
    n.mesh = Some(mesh);
    n.translation = Some(centre(&t.centres_mm[0]));
    let n = doc.root.push(n);
    let mut path: Vec<[f32; 3]> = t.centres_mm.iter().map(centre).collect();
    path.push(path[0]);
    let output = doc.vec3(&path, false, false, "tumour: centre per key (m)");
    push_channel(
        animation,
        input,
        output,
        n,
        json::animation::Property::Translation,
    );
    n
}

/// `asset.extras.lungdyn`: what a reader of the file needs to know of it.
fn metadata(
    name: &str,
    report: &GltfReport,
    breath: &Breath,
    lungs: &[(RenderLung, Vec<Vec<[f32; 3]>>)],
) -> serde_json::Value {
    let volumes: serde_json::Map<String, serde_json::Value> = lungs
        .iter()
        .map(|(l, _)| {
            let v: Vec<f64> = breath
                .frames
                .iter()
                .map(|f| (f.lungs[l.side.index()].volume_ml as f64 * 10.0).round() / 10.0)
                .collect();
            (l.side.name().to_string(), serde_json::json!(v))
        })
        .collect();
    serde_json::json!({
        "lungdyn": {
            "scene": name,
            "scene_file": report.scene,
            "mode": report.mode,
            "breath": report.breath,
            "frames": report.frames,
            "period_s": r3(report.period_s),
            "breaths_per_min": r3(60.0 / report.period_s),
            "frame_times_s": breath.times_s,
            "volume_ml": volumes,
            "lungs": report.lungs,
            "tumour": report.tumour,
            "opacity": report.opacity,
            "targets": report.targets,
            "frame": "glTF metres: +X patient left, +Y superior, +Z anterior (lungdyn's body frame \
                      (X, Y, Z) mm → glTF (X, Z, Y) / 1000)",
            "animation": "'breath': key 0 shows frame 0 (the base mesh, every weight 0), key k > 0 \
                          frame k (weight 1 on morph target k - 1), the last key frame 0 again; \
                          linear between keys; each target moves positions and normals",
        }
    })
}

/// Text of the report.
pub fn text(r: &GltfReport) -> String {
    let mut s = format!(
        "wrote {} ({:.2} MB): one breath of {} ({} mode), breath {} of the run, {} frames over {:.2} s \
         ({:.1} breaths/min)\n",
        r.out,
        r.bytes as f64 / 1e6,
        r.scene,
        r.mode,
        r.breath,
        r.frames,
        r.period_s,
        60.0 / r.period_s
    );
    for l in &r.lungs {
        s += &format!(
            "  {} lung: {} vertices, {} triangles, {} ml → {} ml, moves up to {:.1} mm; {}\n",
            l.side,
            l.vertices,
            l.triangles,
            l.volume_ml[0].round(),
            l.volume_ml[1].round(),
            l.max_motion_mm,
            if l.lobes.is_empty() {
                "no lobes in the kernel (one material)".to_string()
            } else {
                format!("lobes: {}", l.lobes.join(", "))
            }
        );
    }
    if let Some(t) = &r.tumour {
        s += &format!(
            "  tumour in the {} lung: radii {:?} mm, its centre moves {:.1} / {:.1} / {:.1} mm \
             (left-right / anterior-posterior / superior-inferior)\n",
            t.side, t.radii_mm, t.motion_mm[0], t.motion_mm[1], t.motion_mm[2]
        );
    }
    let t = &r.targets;
    s += &if t.encoding == "float" {
        "  morph targets (positions and normals) as 32-bit floats\n".to_string()
    } else {
        format!(
            "  morph targets quantised (KHR_mesh_quantization: position differences 16-bit, normal \
             differences 8-bit): vertices within {:.3} mm, normals within {:.2}° of the engine's{}; \
             --float-targets for a viewer without the extension\n",
            t.position_error_max_mm,
            t.normal_error_max_deg,
            if t.kept_float > 0 {
                format!(" ({} targets kept as floats: differences past ±1)", t.kept_float)
            } else {
                String::new()
            }
        )
    };
    if r.opacity < 1.0 {
        s += &format!(
            "  the lungs are see-through (opacity {}; --opacity 1 for opaque)\n",
            r.opacity
        );
    }
    s += &format!(
        "  open it in any glTF viewer (its animation 'breath' loops the breath), e.g. drop it on \
         https://gltf-viewer.donmccurdy.com or Blender (File > Import > glTF 2.0); took {:.1} s\n",
        r.seconds
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The breath is counted on a lung the disease leaves alone: a complete pneumothorax of the
    /// first lung listed no longer leaves nothing to export.
    #[test]
    fn the_breath_is_counted_on_a_lung_the_disease_leaves_alone() {
        let scene = |text: &str| Scene::parse(text, "test").expect("a valid scene");
        let sides = "[lungs]\nsides = [\"right\", \"left\"]\n";
        let side = |text: String| reference_lung(&scene(&text)).unwrap();
        use lung_model::mesh::Side;
        assert_eq!(side(sides.to_string()), Side::Right);
        let closed = |s: &str| {
            format!(
                "{sides}[disease]\nkind = \"closed-pneumothorax\"\nside = \"{s}\"\nindex = 1.0\n"
            )
        };
        assert_eq!(side(closed("right")), Side::Left);
        assert_eq!(side(closed("left")), Side::Right);
        let both = format!(
            "{sides}[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\nindex_right = 0.2\n"
        );
        assert_eq!(side(both), Side::Right, "both affected: the first listed");
    }

    /// Twice the area vector of triangle `t` of `p` (its normal times twice its area).
    fn area_vector(p: &[[f32; 3]], t: [u32; 3]) -> [f64; 3] {
        let [a, b, c] = t.map(|i| p[i as usize].map(|v| v as f64));
        let (u, v) = (
            [0, 1, 2].map(|k| b[k] - a[k]),
            [0, 1, 2].map(|k| c[k] - a[k]),
        );
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    }

    /// One triangle cut between two lobes and between three: the pieces cover it exactly (their
    /// area vectors sum to its own, so none is flipped or missing), each piece holds one or two of
    /// its corners and is their lobe, and the cut points are the edges' midpoints and centre.
    #[test]
    fn a_triangle_in_two_or_three_lobes_is_cut_at_its_midpoints_into_pieces_that_cover_it() {
        let p = [[0.0f32, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 1.0]];
        let t = [0u32, 1, 2];
        let whole = area_vector(&p, t);
        for codes in [[1u8, 1, 2], [1, 2, 1], [2, 1, 1], [1, 2, 3], [3, 1, 2]] {
            let split = LobeSplit::cut(&[t], 3, Some(&codes), |_, _| 0.5);
            let all = split.extend(&p);
            let mut sum = [0.0f64; 3];
            for (lobe, tris) in &split.groups {
                let code = lobe.unwrap().code();
                for &piece in tris {
                    let a = area_vector(&all, piece);
                    sum = [0, 1, 2].map(|k| sum[k] + a[k]);
                    let dot: f64 = (0..3).map(|k| a[k] * whole[k]).sum();
                    assert!(dot > 0.0, "{codes:?}: piece {piece:?} is flipped");
                    let own: Vec<u32> = piece.iter().copied().filter(|&v| v < 3).collect();
                    assert!(!own.is_empty(), "{codes:?}: {piece:?} holds no corner");
                    for v in own {
                        assert_eq!(codes[v as usize], code, "{codes:?}: {piece:?}");
                    }
                }
            }
            for k in 0..3 {
                assert!(
                    (sum[k] - whole[k]).abs() < 1e-9,
                    "{codes:?}: {sum:?} vs {whole:?}"
                );
            }
            let three = codes[0] != codes[1] && codes[1] != codes[2] && codes[0] != codes[2];
            assert_eq!(split.added.len(), if three { 4 } else { 2 }, "{codes:?}");
            assert!(split.added.iter().all(|a| match *a {
                Added::Edge(i, j, t) => i < j && j < 3 && t == 0.5,
                Added::Centre(..) => three,
            }));
        }
        // One lobe, or no lobe codes: nothing is cut.
        assert!(LobeSplit::cut(&[t], 3, Some(&[2, 2, 2]), |_, _| 0.5)
            .added
            .is_empty());
        let plain = LobeSplit::cut(&[t], 3, None, |_, _| 0.5);
        assert_eq!(plain.groups, vec![(None, vec![t])]);
    }

    /// The built-in lungs with their lobes, cut: still one closed surface (every edge between
    /// exactly two pieces, once each way), enclosing the volume it did (the pieces are coplanar
    /// with what they cut), each lobe's pieces hold only that lobe's vertices, and the cut points are
    /// one per boundary edge, each once, and the centres of triangles in three lobes.
    #[test]
    fn the_built_in_lungs_cut_by_lobe_stay_closed_and_keep_their_volume() {
        use lung_model::mesh::{anatomy, lobes};
        for side in [Side::Right, Side::Left] {
            let mesh = anatomy::lung(side, 4000).unwrap();
            let codes = lobes::classify(side, &mesh);
            let at = fissure_cut(side, &mesh.positions, &codes);
            let split = LobeSplit::cut(&mesh.triangles, mesh.positions.len(), Some(&codes), &at);
            let p = split.extend(&mesh.positions);
            let tris: Vec<[u32; 3]> = split.groups.iter().flat_map(|(_, t)| t.clone()).collect();
            let mut directed = std::collections::HashMap::new();
            for t in &tris {
                for k in 0..3 {
                    *directed.entry((t[k], t[(k + 1) % 3])).or_insert(0u32) += 1;
                }
            }
            for (&(a, b), &n) in &directed {
                assert_eq!(n, 1, "{side:?}: edge {a}->{b} used {n} times");
                assert_eq!(
                    directed.get(&(b, a)),
                    Some(&1),
                    "{side:?}: edge {a}-{b} open"
                );
            }
            let before = mesh.enclosed_volume_ml();
            let after =
                lung_model::mesh::enclosed_volume_with(&tris, |i| p[i as usize].map(|v| v as f64))
                    / 1000.0;
            assert!(
                (after - before).abs() < 1e-6 * before,
                "{side:?}: {after} vs {before} ml"
            );
            let n = mesh.positions.len() as u32;
            for (lobe, pieces) in &split.groups {
                let code = lobe.unwrap().code();
                for t in pieces {
                    for &v in t.iter().filter(|&&v| v < n) {
                        assert_eq!(codes[v as usize], code, "{side:?}: {t:?} in {lobe:?}");
                    }
                }
            }
            let lobes_here = split.groups.len();
            assert_eq!(lobes_here, if side == Side::Right { 3 } else { 2 });
            // A cut point per edge between two lobes, and one per triangle in three.
            let mut crossing = std::collections::HashSet::new();
            let mut three = 0;
            for t in &mesh.triangles {
                let c = t.map(|v| codes[v as usize]);
                three += usize::from(c[0] != c[1] && c[1] != c[2] && c[0] != c[2]);
                for k in 0..3 {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    if codes[a as usize] != codes[b as usize] {
                        crossing.insert((a.min(b), a.max(b)));
                    }
                }
            }
            assert_eq!(split.added.len(), crossing.len() + three, "{side:?}");
            // The codes came from the fissure planes, so every edge is cut where a plane crosses
            // it (the renderer's boundary), unless that is within a tenth of an end.
            let bb = mesh.aabb();
            let fissures = lobes::Fissures::adult(side);
            let (mut on_plane, mut edges) = (0, 0);
            for (k, a) in split.added.iter().enumerate() {
                if let Added::Edge(i, j, t) = *a {
                    edges += 1;
                    let q = p[mesh.positions.len() + k].map(|v| v as f64);
                    let d = fissures.signed(lobes::normalise(side, &bb, q));
                    let (ci, cj) = (codes[i as usize], codes[j as usize]);
                    let plane = usize::from(ci != 3 && cj != 3 && ci != 5 && cj != 5);
                    if t > 0.1 && t < 0.9 {
                        assert!(d[plane].abs() < 1e-5, "{side:?}: cut {i}-{j} at {t}: {d:?}");
                        on_plane += 1;
                    }
                }
            }
            eprintln!("{side:?}: {on_plane} of {edges} edge cuts on their plane");
            assert!(
                on_plane * 10 >= edges * 7,
                "{side:?}: {on_plane} of {edges}"
            );
        }
    }

    #[test]
    fn the_body_frame_maps_onto_gltf_with_the_patient_facing_the_viewer() {
        // Patient left (+X) stays +x; superior (+Z) becomes up (+y); anterior (+Y) the front (+z).
        assert_eq!(body_to_gltf([1000.0, 0.0, 0.0]), [1.0, 0.0, 0.0]);
        assert_eq!(body_to_gltf([0.0, 0.0, 1000.0]), [0.0, 1.0, 0.0]);
        assert_eq!(body_to_gltf([0.0, 1000.0, 0.0]), [0.0, 0.0, 1.0]);
    }

    #[test]
    fn indices_are_16_bit_up_to_65535_vertices_then_32_bit_with_the_corners_reversed() {
        let tris = [[0u32, 1, 65_535], [2, 3, 4]];
        for (vertices, size, kind) in [
            (65_535usize, 2usize, json::accessor::ComponentType::U16),
            (70_000, 4, json::accessor::ComponentType::U32),
        ] {
            let mut doc = Doc::new();
            let a = doc.indices(&tris, vertices, "t");
            let acc = &doc.root.accessors[a.value()];
            assert_eq!(acc.count.0, 6);
            match &acc.component_type {
                Valid(json::accessor::GenericComponentType(k)) => assert_eq!(*k, kind),
                other => panic!("{other:?}"),
            }
            assert_eq!(doc.bin.len(), 6 * size);
            let read = |i: usize| {
                let b = &doc.bin[i * size..(i + 1) * size];
                b.iter().rev().fold(0u32, |v, &x| (v << 8) | x as u32)
            };
            let v: Vec<u32> = (0..6).map(read).collect();
            assert_eq!(v, [0, 65_535, 1, 2, 4, 3]);
        }
    }

    #[test]
    fn position_bounds_are_the_datas_own_and_every_view_starts_on_four_bytes() {
        let mut doc = Doc::new();
        doc.indices(&[[0, 1, 2]], 3, "odd: 6 bytes");
        let a = doc.vec3(&[[1.0, -2.0, 0.5], [-1.0, 3.0, 0.25]], true, true, "p");
        let acc = &doc.root.accessors[a.value()];
        assert_eq!(acc.min, Some(serde_json::json!([-1.0, -2.0, 0.25])));
        assert_eq!(acc.max, Some(serde_json::json!([1.0, 3.0, 0.5])));
        for v in &doc.root.buffer_views {
            assert_eq!(v.byte_offset.map_or(0, |o| o.0) % 4, 0);
        }
    }

    /// Quantised differences: each element padded to 4 or 8 bytes (the view's stride says so), the
    /// integers rounded to nearest and decoded within half a step, the bounds the stored integers;
    /// a difference past ±1 or not finite is refused (the caller writes floats), and nothing is
    /// written for it.
    #[test]
    fn quantised_differences_are_padded_rounded_and_bounded_by_their_integers() {
        let mut doc = Doc::new();
        let v = [[0.5, -1.0, 1.0], [0.001, -0.0042, 0.0]];
        for (wide, stride, scale) in [(true, 8usize, 32767.0f32), (false, 4, 127.0)] {
            let start = doc.bin.len().next_multiple_of(4);
            let (a, decoded) = doc.vec3_normalized(&v, wide, true, "d").unwrap();
            let acc = &doc.root.accessors[a.value()];
            assert!(acc.normalized);
            let view = &doc.root.buffer_views[acc.buffer_view.unwrap().value()];
            assert_eq!(view.byte_stride.map(|s| s.0), Some(stride));
            assert_eq!(view.byte_length.0 as usize, 2 * stride);
            let s = scale as i64;
            let (lo, hi) = (
                (0.0042 * scale).round() as i64,
                (0.001 * scale).round() as i64,
            );
            assert_eq!(acc.min, Some(serde_json::json!([hi, -s, 0])));
            assert_eq!(acc.max, Some(serde_json::json!([s / 2 + 1, -lo, s])));
            for (d, x) in decoded.iter().flatten().zip(v.iter().flatten()) {
                assert!((d - x).abs() <= 0.5 / scale + 1e-7, "{d} for {x}");
            }
            // The second element starts a stride after the first, its padding zero.
            let second = &doc.bin[start + stride..start + 2 * stride];
            assert!(second[stride - if wide { 2 } else { 1 }..]
                .iter()
                .all(|&b| b == 0));
        }
        assert!(doc.quantized);
        let views = doc.root.buffer_views.len();
        assert!(doc
            .vec3_normalized(&[[1.01, 0.0, 0.0]], true, true, "past one")
            .is_none());
        assert!(doc
            .vec3_normalized(&[[f32::NAN, 0.0, 0.0]], false, false, "nan")
            .is_none());
        assert_eq!(
            doc.root.buffer_views.len(),
            views,
            "nothing written for a refused target"
        );
    }
}
