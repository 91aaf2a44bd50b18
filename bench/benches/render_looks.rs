//! What each part of the AR picture costs per frame: the default scene's lungs (2 × 10k vertices,
//! baked here as the launcher bakes them) drawn at 800 × 600 mono from a fixed view in every look,
//! with MSAA 4× and off, as triangles and point splats, in each colour mode, and with the
//! heads-up display (its text reshaped every frame, as the volume line changes; the PV loop and
//! the lobes legend drawn) against the same frame without it. Each configuration
//! draws the same frames in interleaved rounds (so a machine shared with other work slows all of
//! them alike); the table gives the median wall time of a frame (deform + draw + wait for the GPU,
//! what the renderer spends) and the median GPU time from timestamp queries where the adapter has
//! them (lavapipe does).
//!
//! Run: `cargo bench -p lungdyn-bench --bench render_looks` (`-- --frames N`, `-- --stereo`,
//! `-- --only WORDS`: the configurations whose name contains WORDS).
//!
//! **Draw levels of detail** (`-- --lod [--vertices N] [--size WxH]`): lungs of N vertices each
//! (default 100k; built-in meshes with a radial stand-in for the baked motion, so no bake is
//! needed: the draw's cost does not depend on the field) drawn small on screen (default 160×120
//! per eye, the view of the image tests from 2.5× as far), at every level fixed, then `lod = "off"`
//! against `"auto"` in mono and stereo: frame time per level, the deformation pass alone and the
//! stereo/mono frame-rate ratio; then each coarser level with the governor's "drawn vertices only"
//! (the deformation pass over that level's vertices alone), and that pass's own time at the
//! coarsest (the column "triangles" gives the vertices moved on the deformation rows).

use glam::{Mat3, Quat, Vec3};
use ipc_types::Pose;
use lung_model::deform::LungModel;
use lung_model::scene::SceneExt;
use lung_model::scene::{ColorMode, DrawMode, Lod, Look, RenderScene, Scene};
use renderer::gpu::Gpu;
use renderer::hud::{Hud, HudConfig, HudFrame};
use renderer::{DrawState, LungRenderer, RenderLung};

/// A breathing engine frame at step `k` of `n` (what the HUD reads): volume, phase and pressure
/// move every frame, so the HUD reshapes its volume line and moves the PV point as when running.
fn engine_frame(k: usize, n: usize) -> ipc_types::EngineFrame {
    use ipc_types::{lung_flags, LUNG_LEFT, LUNG_RIGHT};
    let phase = k as f32 / n.max(1) as f32;
    let mut f = ipc_types::EngineFrame {
        tick: 3600 + k as u64,
        ..Default::default()
    };
    for (slot, v) in [(LUNG_RIGHT, 1300.0), (LUNG_LEFT, 1100.0)] {
        let l = &mut f.lungs[slot];
        l.flags = lung_flags::ACTIVE | lung_flags::INHALING;
        l.volume_ml = v + 250.0 * phase;
        l.tidal_ml = 250.0;
        l.cycle_ticks = 300;
        l.inhale_ticks = 150;
        l.phase = phase;
        l.pressure_cmh2o = 2.0 + 6.0 * phase;
    }
    f
}

fn baked(scene: &Scene) -> Vec<LungModel> {
    scene
        .lungs
        .sides
        .iter()
        .map(|&side| {
            let k = lung_bake::kernel::bake(
                side,
                lung_model::mesh::generate::lung(side, scene.lungs.vertices)
                    .expect("built-in lung"),
                &scene.bake_settings(side).expect("bake settings"),
                &|_| {},
            )
            .expect("bake");
            LungModel::from_unit_displacement(side, k.mesh, k.unit_displacement)
        })
        .collect()
}

/// Patient supine at bed height, the HMD a metre away above the chest at the patient's right
/// (room +Y, as the image tests).
fn state(scale: f32) -> DrawState {
    let supine = Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X));
    let eye = Vec3::new(-250.0, 750.0, 1600.0);
    let forward = (Vec3::new(-30.0, 0.0, 1020.0) - eye).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    DrawState {
        deform_scale: [scale, scale],
        offset_mm: [[0.0; 3]; 2],
        collapse: [0.0; 2],
        hilum_mm: [[0.0; 3]; 2],
        coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
        patient: Pose {
            quat: supine.to_array(),
            translation_mm: [0.0, 0.0, 1120.0],
            _pad: 0,
        },
        hmd: Pose {
            quat: Quat::from_mat3(&Mat3::from_cols(right, up, -forward)).to_array(),
            translation_mm: eye.to_array(),
            _pad: 0,
        },
        pose_warning: Default::default(),
    }
}

/// Lungs of `vertices` each, the built-in meshes with a radial stand-in field (1 mm per 100 mm
/// from the centroid per unit scale).
fn stand_in(vertices: usize) -> Vec<RenderLung> {
    [lung_model::mesh::Side::Right, lung_model::mesh::Side::Left]
        .into_iter()
        .map(|side| {
            let mesh = lung_model::mesh::generate::lung(side, vertices).expect("built-in lung");
            let n = mesh.positions.len() as f32;
            let c = mesh
                .positions
                .iter()
                .fold(Vec3::ZERO, |a, p| a + Vec3::from(*p) / n);
            let u = mesh
                .positions
                .iter()
                .map(|p| ((Vec3::from(*p) - c) * 0.01).to_array())
                .collect();
            RenderLung::from_model(&LungModel::from_unit_displacement(side, mesh, u))
        })
        .collect()
}

/// The draw level study (`--lod`): frame time per level at a small size, and stereo/mono with
/// LOD off and auto.
fn lod_study(gpu: &Gpu, args: &[String], frames: usize) {
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let vertices: usize = value("--vertices")
        .and_then(|s| s.parse().ok())
        .unwrap_or(100_000);
    let (width, height) = value("--size")
        .and_then(|s| {
            let (w, h) = s.split_once('x')?;
            Some((w.parse().ok()?, h.parse().ok()?))
        })
        .unwrap_or((160u32, 120u32));
    eprintln!("building 2 × {vertices} vertex lungs and their draw levels…");
    let lungs = stand_in(vertices);
    let at = |lod, stereo| RenderScene {
        lod,
        stereo,
        width,
        height,
        msaa: Some(1),
        ..RenderScene::default()
    };
    let t = std::time::Instant::now();
    let probe = LungRenderer::new(gpu, &at(Lod::Auto, false), &lungs).expect("upload");
    let load_s = t.elapsed().as_secs_f64();
    let levels = probe.lod_triangles().to_vec();
    drop(probe);
    let mut configs: Vec<(String, RenderScene)> = (0..levels.len())
        .map(|k| (format!("level {k}, mono"), at(Lod::Level(k as u8), false)))
        .collect();
    for stereo in [false, true] {
        for lod in [Lod::Off, Lod::Auto] {
            let eyes = if stereo { "stereo" } else { "mono" };
            configs.push((format!("lod {lod}, {eyes}"), at(lod, stereo)));
        }
    }
    // The governor's "drawn vertices only" at each coarser level: the deformation pass over that
    // level's vertices alone.
    let drawn_from = configs.len();
    for k in 1..levels.len() {
        configs.push((
            format!("level {k}, drawn only"),
            at(Lod::Level(k as u8), false),
        ));
    }
    let renderers: Vec<LungRenderer> = configs
        .iter()
        .enumerate()
        .map(|(i, (_, r))| {
            let mut r = LungRenderer::new(gpu, r, &lungs).expect("upload");
            if i >= drawn_from {
                r.set_quality(renderer::governor::Quality {
                    drawn_only: true,
                    ..renderer::governor::Quality::FULL
                });
            }
            r
        })
        .collect();
    let far = |k: usize| {
        let mut s = state(40.0 * (k as f32 / frames as f32));
        let target = Vec3::new(-30.0, 0.0, 1020.0);
        let eye = Vec3::from(s.hmd.translation_mm);
        s.hmd.translation_mm = (target + (eye - target) * 2.5).to_array();
        s
    };
    let mut wall = vec![Vec::with_capacity(frames); configs.len()];
    let mut gpu_ms = vec![Vec::with_capacity(frames); configs.len()];
    for r in &renderers {
        r.render(gpu, &far(0), false);
    }
    for k in 0..frames {
        for (i, r) in renderers.iter().enumerate() {
            let t = std::time::Instant::now();
            let timing = r.render(gpu, &far(k), false);
            wall[i].push(t.elapsed().as_secs_f64() * 1e3);
            if let Some(ns) = timing.gpu_ns {
                gpu_ms[i].push(ns as f64 / 1e6);
            }
        }
    }
    println!(
        "2 x {vertices} vertices, {width} x {height} per eye, MSAA off, {frames} frames each on {}; \
         levels built at load in {load_s:.2} s; triangles per level (both lungs): {levels:?}",
        gpu.info.name
    );
    println!(
        "{:<24} {:>10} {:>14} {:>12}",
        "configuration", "triangles", "frame p50 ms", "GPU p50 ms"
    );
    let mut p50 = Vec::new();
    for (i, (name, _)) in configs.iter().enumerate() {
        let (f, g) = (median(wall[i].clone()), median(gpu_ms[i].clone()));
        p50.push(f);
        println!(
            "{:<24} {:>10} {:>14.2} {:>12.2}",
            name,
            renderers[i].lod_shown().triangles,
            f,
            g
        );
    }
    // The deformation alone (its compute pass, by timestamps): the floor no level goes under
    // while every vertex is moved; and over the coarsest level's vertices alone.
    let coarsest_drawn = (renderers.len() > drawn_from).then(|| renderers.len() - 1);
    for (label, i) in [
        ("deformation only", Some(0)),
        ("  over the coarsest's", coarsest_drawn),
    ] {
        let Some(i) = i else { continue };
        let deform_ms: Vec<f64> = (0..frames)
            .filter_map(|k| renderers[i].time_deform(gpu, &far(k)))
            .map(|ns| ns as f64 / 1e6)
            .collect();
        if !deform_ms.is_empty() {
            println!(
                "{:<24} {:>10} {:>14} {:>12.2}",
                label,
                renderers[i].vertices_moved(),
                "",
                median(deform_ms)
            );
        }
    }
    let n = levels.len();
    for (k, lod) in ["off", "auto"].iter().enumerate() {
        let (mono, stereo) = (p50[n + k], p50[n + 2 + k]);
        println!(
            "stereo/mono frame rate, lod {lod}: {:.2} (mono {mono:.2} ms, stereo {stereo:.2} ms)",
            mono / stereo
        );
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.iter().any(|a| a == "--list") {
        return;
    }
    let frames = args
        .iter()
        .position(|a| a == "--frames")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(60usize);
    let stereo = args.iter().any(|a| a == "--stereo");
    let only = args
        .iter()
        .position(|a| a == "--only")
        .and_then(|i| args.get(i + 1))
        .cloned();
    let Some(gpu) = Gpu::for_tests() else { return };
    if args.iter().any(|a| a == "--lod") {
        lod_study(&gpu, &args, frames);
        return;
    }
    let scene = Scene::default();
    eprintln!(
        "baking the default lungs ({} vertices each)…",
        scene.lungs.vertices
    );
    let lungs: Vec<RenderLung> = baked(&scene).iter().map(RenderLung::from_model).collect();
    let configs: Vec<(&str, RenderScene, bool)> = [
        (
            "opaque, MSAA off",
            DrawMode::Triangles,
            Look::Opaque,
            ColorMode::Tissue,
            1,
        ),
        (
            "opaque, MSAA 4x",
            DrawMode::Triangles,
            Look::Opaque,
            ColorMode::Tissue,
            4,
        ),
        (
            "translucent, MSAA off",
            DrawMode::Triangles,
            Look::Translucent,
            ColorMode::Tissue,
            1,
        ),
        (
            "translucent, MSAA 4x",
            DrawMode::Triangles,
            Look::Translucent,
            ColorMode::Tissue,
            4,
        ),
        (
            "see-through, MSAA off",
            DrawMode::Triangles,
            Look::SeeThrough,
            ColorMode::Tissue,
            1,
        ),
        (
            "see-through, MSAA 4x",
            DrawMode::Triangles,
            Look::SeeThrough,
            ColorMode::Tissue,
            4,
        ),
        (
            "points, MSAA off",
            DrawMode::Points,
            Look::Opaque,
            ColorMode::Tissue,
            1,
        ),
        (
            "points, MSAA 4x",
            DrawMode::Points,
            Look::Opaque,
            ColorMode::Tissue,
            4,
        ),
        (
            "displacement colour, MSAA off",
            DrawMode::Triangles,
            Look::Opaque,
            ColorMode::Displacement,
            1,
        ),
        (
            "ventilation colour, MSAA off",
            DrawMode::Triangles,
            Look::Opaque,
            ColorMode::Ventilation,
            1,
        ),
    ]
    .into_iter()
    .map(|(name, mode, look, color, msaa)| {
        (
            name,
            RenderScene {
                mode,
                look,
                color,
                msaa: Some(msaa),
                stereo,
                ..scene.render.clone()
            },
            false,
        )
    })
    .collect();
    // The HUD's cost: the lavapipe default (opaque, MSAA off), the lobes colour mode and
    // everything on (translucent, MSAA 4×: the 60 fps goal), each with and without it.
    let mut configs = configs;
    let opaque_off = configs[0].1.clone();
    let everything = configs[3].1.clone();
    let lobes = RenderScene {
        color: ColorMode::Lobes,
        ..opaque_off.clone()
    };
    configs.extend([
        ("opaque + HUD, MSAA off", opaque_off, true),
        ("lobes colour, MSAA off", lobes.clone(), false),
        ("lobes colour + HUD, MSAA off", lobes, true),
        ("translucent + HUD, MSAA 4x", everything, true),
    ]);
    if let Some(only) = &only {
        configs.retain(|(name, _, _)| name.contains(only.as_str()));
    }
    let renderers: Vec<LungRenderer> = configs
        .iter()
        .map(|(_, r, _)| LungRenderer::new(&gpu, r, &lungs).expect("upload"))
        .collect();
    let mut huds: Vec<Option<Hud>> = configs
        .iter()
        .zip(&renderers)
        .map(|((_, r, hud), lr)| {
            hud.then(|| {
                let eyes = if r.stereo { 2 } else { 1 };
                let (w, h) = lr.image_size();
                let scene = Scene {
                    render: r.clone(),
                    ..scene.clone()
                };
                Hud::new(
                    &gpu.device,
                    &gpu.queue,
                    HudConfig::of(&scene, &lungs),
                    w / eyes,
                    h,
                    eyes,
                )
            })
        })
        .collect();
    // CPU time of the HUD's encode (formatting, shaping, glyphon's prepare, its pass recorded),
    // per configuration with a HUD.
    let mut hud_cpu = vec![Vec::with_capacity(frames); configs.len()];
    let draw =
        |r: &LungRenderer, hud: &mut Option<Hud>, s: &DrawState, k: usize, cpu: &mut Vec<f64>| {
            let Some(hud) = hud.as_mut() else {
                return r.render(&gpu, s, false);
            };
            let frame = engine_frame(k, frames);
            let shown = HudFrame {
                frame: &frame,
                tracker: None,
                warning: Default::default(),
                cpu_ns: 2_500_000,
                gpu_ns: Some(11_000_000),
                latency_ns: Some(9_000_000),
                lod: r.lod_shown(),
                governor: None,
                outcome: Some((
                    "needle decompression, left, applied 01:02 — air venting",
                    renderer::hud::text::Standing::Done,
                )),
            };
            r.render_with_overlay(
                &gpu,
                s,
                false,
                |encoder, target, eyes| {
                    let t = std::time::Instant::now();
                    hud.encode(&gpu.device, &gpu.queue, encoder, target, eyes, &shown);
                    cpu.push(t.elapsed().as_secs_f64() * 1e3);
                },
                |_| {},
            )
        };
    let mut wall = vec![Vec::with_capacity(frames); configs.len()];
    let mut gpu_ms = vec![Vec::with_capacity(frames); configs.len()];
    // Warm up every pipeline, then interleave: frame k of every configuration, then frame k + 1.
    for (r, hud) in renderers.iter().zip(huds.iter_mut()) {
        draw(r, hud, &state(0.0), 0, &mut Vec::new());
    }
    for k in 0..frames {
        let s = state(40.0 * (k as f32 / frames as f32));
        for (i, (r, hud)) in renderers.iter().zip(huds.iter_mut()).enumerate() {
            let t = std::time::Instant::now();
            let timing = draw(r, hud, &s, k, &mut hud_cpu[i]);
            wall[i].push(t.elapsed().as_secs_f64() * 1e3);
            if let Some(ns) = timing.gpu_ns {
                gpu_ms[i].push(ns as f64 / 1e6);
            }
        }
    }
    // The deformation alone (its compute pass, from timestamps): the part of every row above
    // that is not drawing.
    let deform_ms: Vec<f64> = (0..frames)
        .filter_map(|k| renderers[0].time_deform(&gpu, &state(40.0 * (k as f32 / frames as f32))))
        .map(|ns| ns as f64 / 1e6)
        .collect();
    let (w, h) = renderers[0].image_size();
    println!(
        "{} x {} ({}), {} frames each on {}",
        w,
        h,
        if stereo { "stereo" } else { "mono" },
        frames,
        gpu.info.name
    );
    println!(
        "{:<32} {:>14} {:>14} {:>14}",
        "configuration", "frame p50 ms", "GPU p50 ms", "HUD CPU p50 ms"
    );
    if !deform_ms.is_empty() {
        println!(
            "{:<32} {:>14} {:>14.2}",
            "deformation only (compute)",
            "",
            median(deform_ms)
        );
    }
    for (i, (name, _, _)) in configs.iter().enumerate() {
        let cpu = if hud_cpu[i].is_empty() {
            String::new()
        } else {
            format!("{:.2}", median(hud_cpu[i].clone()))
        };
        println!(
            "{:<32} {:>14.2} {:>14.2} {:>14}",
            name,
            median(wall[i].clone()),
            median(gpu_ms[i].clone()),
            cpu
        );
    }
}
