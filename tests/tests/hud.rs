//! The heads-up display on the real wgpu path (lavapipe in CI): the same frame rendered with and
//! without the HUD differs where the HUD's text and shapes are, in every eye, and nowhere the HUD
//! does not draw; the front view used by strips and recordings shows the lungs.

use glam::{Mat3, Quat, Vec3};
use ipc_types::{lung_flags, EngineFrame, Pose, LUNG_LEFT, LUNG_RIGHT};
use lung_model::scene::Scene;
use renderer::gpu::Gpu;
use renderer::hud::{EyeLayout, Hud, HudConfig, HudFrame};
use renderer::{DrawState, LungRenderer, PoseWarning, RenderLung};

fn supine() -> Pose {
    Pose {
        quat: Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X)).to_array(),
        translation_mm: [0.0, 0.0, 1120.0],
        _pad: 0,
    }
}

/// A mid-inspiration engine frame of both lungs (what the HUD reads).
fn engine_frame() -> EngineFrame {
    let mut f = EngineFrame {
        tick: 3720,
        ..Default::default()
    };
    for (k, v) in [(LUNG_RIGHT, 1400.0), (LUNG_LEFT, 1250.0)] {
        let l = &mut f.lungs[k];
        l.flags = lung_flags::ACTIVE | lung_flags::INHALING;
        l.volume_ml = v;
        l.tidal_ml = 250.0;
        l.cycle_ticks = 300;
        l.inhale_ticks = 150;
        l.phase = 0.3;
        l.pressure_cmh2o = 6.0;
    }
    f
}

/// The outcome line the HUD shows in these tests (the example, the longest kind).
const OUTCOME: &str = "needle decompression, left, applied 01:02 — air venting";

/// Render `scene`'s lungs from the front, without and with the HUD; returns both images.
fn render_pair(
    scene: &Scene,
    warning: PoseWarning,
) -> Option<(image::RgbaImage, image::RgbaImage)> {
    render_pair_with(scene, warning, OUTCOME, |_| {})
}

/// As [`render_pair`], showing `outcome` as the intervention's line, with `edit` applied to the
/// lungs before they are uploaded (e.g. a lung without lobe codes).
fn render_pair_with(
    scene: &Scene,
    warning: PoseWarning,
    outcome: &str,
    edit: impl FnOnce(&mut Vec<RenderLung>),
) -> Option<(image::RgbaImage, image::RgbaImage)> {
    render_hud(scene, warning, outcome, edit).map(|(plain, hud, _)| (plain, hud))
}

/// As [`render_pair_with`], with where the HUD put its parts in each eye.
fn render_hud(
    scene: &Scene,
    warning: PoseWarning,
    outcome: &str,
    edit: impl FnOnce(&mut Vec<RenderLung>),
) -> Option<(image::RgbaImage, image::RgbaImage, [Option<EyeLayout>; 2])> {
    render_hud_over(scene, warning, outcome, edit, &[engine_frame()])
}

/// As [`render_hud`], the HUD drawn over `frames` one after another (what it keeps from frame to
/// frame, the PV loop and the signal trace, built up); the image is the last frame's.
fn render_hud_over(
    scene: &Scene,
    warning: PoseWarning,
    outcome: &str,
    edit: impl FnOnce(&mut Vec<RenderLung>),
    frames: &[EngineFrame],
) -> Option<(image::RgbaImage, image::RgbaImage, [Option<EyeLayout>; 2])> {
    let gpu = Gpu::for_tests()?;
    let models = lungdyn_tests::baked_models(scene);
    let mut lungs: Vec<RenderLung> = models.iter().map(RenderLung::from_model).collect();
    edit(&mut lungs);
    let r = LungRenderer::new(&gpu, &scene.render, &lungs).unwrap();
    let patient = supine();
    let (w, h) = r.image_size();
    let eyes = if scene.render.stereo { 2 } else { 1 };
    let mut hud = Hud::new(
        &gpu.device,
        &gpu.queue,
        HudConfig::of(scene, &lungs),
        w / eyes,
        h,
        eyes,
    );
    let state = DrawState {
        deform_scale: [0.0; 2],
        offset_mm: [[0.0; 3]; 2],
        collapse: [0.0; 2],
        hilum_mm: [[0.0; 3]; 2],
        coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
        patient,
        // Framed as strips and recordings are: clear of the HUD.
        hmd: r.front_view_in(&patient, hud.lungs_band()).unwrap(),
        pose_warning: warning,
    };
    r.render(&gpu, &state, true);
    let plain = r.read_image(&gpu).unwrap();
    let shown = |frame| HudFrame {
        frame,
        tracker: None,
        warning,
        cpu_ns: 2_500_000,
        gpu_ns: None,
        latency_ns: Some(9_000_000),
        lod: r.lod_shown(),
        // The longest timing line: the governor gave up everything and is at its floor.
        governor: Some(
            ipc_types::report_flags::quality_bits(true, 2, true)
                | ipc_types::report_flags::GOVERNOR_FLOOR,
        ),
        // "": no intervention sent yet.
        outcome: (!outcome.is_empty()).then_some((outcome, renderer::hud::text::Standing::Done)),
    };
    if let Ok(dir) = std::env::var("LUNGDYN_HUD_TEST_PNG") {
        // For a look at what the test saw.
        let _ = std::fs::create_dir_all(&dir);
        let _ = plain.save(format!("{dir}/plain_{w}x{h}_{}.png", scene.render.stereo));
    }
    let mut layout = [None; 2];
    for frame in frames {
        r.render_with_overlay(
            &gpu,
            &state,
            true,
            |encoder, target, eye_cams| {
                hud.encode(
                    &gpu.device,
                    &gpu.queue,
                    encoder,
                    target,
                    eye_cams,
                    &shown(frame),
                );
                layout = hud.layout(eye_cams, frame);
            },
            |_| {},
        );
    }
    let with_hud = r.read_image(&gpu).unwrap();
    if let Ok(dir) = std::env::var("LUNGDYN_HUD_TEST_PNG") {
        let _ = with_hud.save(format!(
            "{dir}/hud_{}x{}_{}_{warning:?}.png",
            w, h, scene.render.stereo
        ));
    }
    Some((plain, with_hud, layout))
}

/// Pixels of the box `(x0, y0, w, h)` that differ by more than 24/255 in some channel.
fn differing(
    a: &image::RgbaImage,
    b: &image::RgbaImage,
    (x0, y0, w, h): (u32, u32, u32, u32),
) -> usize {
    (x0..x0 + w)
        .flat_map(|x| (y0..y0 + h).map(move |y| (x, y)))
        .filter(|&(x, y)| {
            let (p, q) = (a.get_pixel(x, y), b.get_pixel(x, y));
            (0..3).any(|c| p[c].abs_diff(q[c]) > 24)
        })
        .count()
}

#[test]
fn the_hud_draws_its_panel_and_pv_loop_in_every_eye() {
    for stereo in [false, true] {
        let mut scene = Scene::default();
        scene.lungs.vertices = 2000;
        scene.render.width = 480;
        scene.render.height = 320;
        scene.render.stereo = stereo;
        let Some((plain, hud)) = render_pair(&scene, PoseWarning::None) else {
            return;
        };
        let eyes = if stereo { 2 } else { 1 };
        assert_eq!(plain.dimensions(), (480 * eyes, 320));
        for eye in 0..eyes {
            let ox = eye * 480;
            // The panel: the top-left third of the eye, its text and the phase bar.
            let panel = differing(&plain, &hud, (ox, 0, 160, 100));
            assert!(
                panel > 160 * 100 / 10,
                "stereo {stereo}, eye {eye}: only {panel} panel pixels changed"
            );
            // The PV loop's box at the top right: its frame, its title, and the current point
            // (amber; the frame drawn holds one point of the loop).
            let pv_box = (ox + 480 - 125, 0, 125, 100);
            let pv = differing(&plain, &hud, pv_box);
            assert!(pv > 300, "stereo {stereo}, eye {eye}: PV box {pv} pixels");
            let amber = (pv_box.0..pv_box.0 + pv_box.2)
                .flat_map(|x| (0..pv_box.3).map(move |y| (x, y)))
                .filter(|&(x, y)| {
                    let p = hud.get_pixel(x, y);
                    p[0] > 230 && (150..230).contains(&p[1]) && p[2] < 110
                })
                .count();
            assert!(
                amber >= 40,
                "stereo {stereo}, eye {eye}: current PV point {amber} px"
            );
            // The bottom corners hold neither the panel, the loop nor a label: untouched.
            let corner = differing(&plain, &hud, (ox, 320 - 30, 40, 30))
                + differing(&plain, &hud, (ox + 480 - 40, 320 - 30, 40, 30));
            assert_eq!(
                corner, 0,
                "stereo {stereo}, eye {eye}: the HUD drew outside its places"
            );
        }
        if stereo {
            // The panel floats at a reading depth: the eyes' panels are shifted against each other.
            let row = |x0: u32| {
                (0..200)
                    .map(|x| hud.get_pixel(x0 + x, 20).0)
                    .collect::<Vec<_>>()
            };
            assert_ne!(row(0), row(480), "a stereo HUD needs a disparity");
        }
    }
}

/// A scene that breathes with the patient's signal shows, in the PV loop's box, the last ten seconds
/// of the lungs' volume (white) and the patient's measured volume (blue, only while it drives the
/// lungs), its title saying which is which; a scene that breathes with the model shows no blue
/// there. (The trace's points, gaps and scale: `renderer::hud::text`'s unit test.)
#[test]
fn a_scene_breathing_with_the_signal_shows_its_trace_in_the_pv_box() {
    let blue_in = |img: &image::RgbaImage, (x0, y0, w, h): (u32, u32, u32, u32)| {
        (x0..x0 + w)
            .flat_map(|x| (y0..y0 + h).map(move |y| (x, y)))
            .filter(|&(x, y)| {
                let p = img.get_pixel(x, y);
                p[2] > 200 && p[1] > 150 && p[0] < 150
            })
            .count()
    };
    // Six seconds at 60 Hz: one breath of 5 s, the signal driving it from the second second.
    let frames: Vec<EngineFrame> = (0..360u64)
        .map(|tick| {
            let mut f = engine_frame();
            f.tick = tick;
            let breath = (tick as f32 / 300.0 * std::f32::consts::TAU).sin();
            f.lungs[LUNG_RIGHT].volume_ml = 1400.0 + 150.0 * breath;
            f.lungs[LUNG_LEFT].volume_ml = 1250.0 + 130.0 * breath;
            if tick >= 120 {
                f.state = ipc_types::engine_state::SIGNAL_FOLLOWING;
                f.signal.display_ns = 1 + tick;
                f.signal.volume_ml = 280.0 * breath;
                // The newest sample, 30 ml behind what the prediction drew.
                f.signal.unpredicted_ml = 280.0 * breath - 30.0;
            }
            f
        })
        .collect();
    for signal in [true, false] {
        let mut scene = Scene::default();
        scene.lungs.vertices = 2000;
        scene.render.width = 960;
        scene.render.height = 540;
        if signal {
            scene.breathing.source = lung_model::scene::BreathSource::Signal;
        }
        let Some((plain, hud, layout)) =
            render_hud_over(&scene, PoseWarning::None, "", |_| {}, &frames)
        else {
            return;
        };
        let pv = layout[0].expect("one eye").pv;
        let pv_box = (pv.x as u32, pv.y as u32, pv.w as u32, pv.h as u32);
        let blue = blue_in(&hud, pv_box);
        assert_eq!(
            blue_in(&plain, pv_box),
            0,
            "no blue lung pixels under the box"
        );
        if signal {
            // Four seconds of the measured line, two pixels wide, across about 40 % of the box.
            assert!(
                blue as f32 > pv.w * 0.3,
                "signal scene: {blue} blue pixels in the PV box {pv:?}"
            );
        } else {
            assert_eq!(blue, 0, "a model scene draws no patient line");
        }
    }
}

#[test]
fn a_stale_pose_veil_carries_its_words() {
    let mut scene = Scene::default();
    scene.lungs.vertices = 2000;
    scene.render.width = 480;
    scene.render.height = 320;
    let Some((plain, hud)) = render_pair(&scene, PoseWarning::Stale) else {
        return;
    };
    // The middle band across the eye, where the veil text is.
    let band = differing(&plain, &hud, (0, 150, 480, 20));
    assert!(band > 480 * 20 / 5, "veil text band: {band} pixels changed");
}

#[test]
fn the_front_view_shows_both_lungs_below_the_hud() {
    let mut scene = Scene::default();
    scene.lungs.vertices = 2000;
    scene.render.width = 320;
    scene.render.height = 240;
    let Some((plain, _)) = render_pair(&scene, PoseWarning::None) else {
        return;
    };
    let background = *plain.get_pixel(0, 0);
    let lit: Vec<(u32, u32)> = plain
        .enumerate_pixels()
        .filter(|(_, _, p)| **p != background)
        .map(|(x, y, _)| (x, y))
        .collect();
    // The front view frames the lungs' box at 55 % of the image height (renderer::record::
    // FRONT_VIEW_FILL); the anatomical lungs' silhouette (tapered apices, the mediastinal gap, the
    // left cardiac notch) covered 9.8 % of the image at the earlier 50 %, so the box was framed
    // larger rather than this check lowered: the lungs must be framed, not specks (under a tenth
    // fails).
    assert!(
        lit.len() > 320 * 240 / 10,
        "the lungs fill part of the image: {}",
        lit.len()
    );
    let (x0, x1) = (
        lit.iter().map(|p| p.0).min().unwrap(),
        lit.iter().map(|p| p.0).max().unwrap(),
    );
    let cy = lit.iter().map(|p| p.1 as f64).sum::<f64>() / lit.len() as f64;
    // Centred left-right, in the lower part of the image, not cut off at the sides.
    assert!(x0 > 5 && x1 < 315, "lungs span {x0}..{x1}");
    assert!((x0 + x1) / 2 > 120 && (x0 + x1) / 2 < 200, "{x0}..{x1}");
    assert!(cy > 120.0, "the lungs sit below the middle: {cy}");
}

/// Pixels of the box `(x0, y0, w, h)` of `hud` within 6/255 of the sRGB colour `c` that are not
/// so in `plain` (what the HUD drew in that colour).
fn drawn_in(
    plain: &image::RgbaImage,
    hud: &image::RgbaImage,
    c: [u8; 3],
    (x0, y0, w, h): (u32, u32, u32, u32),
) -> usize {
    let near = |p: &image::Rgba<u8>| (0..3).all(|k| p[k].abs_diff(c[k]) <= 6);
    (x0..x0 + w)
        .flat_map(|x| (y0..y0 + h).map(move |y| (x, y)))
        .filter(|&(x, y)| near(hud.get_pixel(x, y)) && !near(plain.get_pixel(x, y)))
        .count()
}

#[test]
fn the_lobes_colour_mode_has_a_legend_that_names_a_lung_without_lobe_data() {
    use lung_model::mesh::lobes::{Lobe, ALL};
    let mut scene = Scene::default();
    scene.lungs.vertices = 2000;
    scene.render.width = 480;
    scene.render.height = 360;
    scene.render.color = lung_model::scene::ColorMode::Lobes;
    let legend_box = (0, 360 - 70, 300, 70);
    let Some((plain, hud)) = render_pair(&scene, PoseWarning::None) else {
        return;
    };
    // Every lobe's square in its colour, bottom left; no grey square, no warning.
    for lobe in ALL {
        let n = drawn_in(&plain, &hud, lobe.colour(), legend_box);
        assert!(n >= 12, "{lobe}: {n} legend pixels");
    }
    // (White text's antialiased edges pass through grey: counted to compare with below.)
    let grey_text = drawn_in(&plain, &hud, Lobe::Unknown.colour(), legend_box);
    let amber = [255, 196, 64];
    assert_eq!(drawn_in(&plain, &hud, amber, legend_box), 0);
    // The left lung's kernel without lobes: its lobes leave the legend, a grey square and an
    // amber warning say so.
    let Some((plain, hud)) = render_pair_with(&scene, PoseWarning::None, OUTCOME, |lungs| {
        for l in lungs.iter_mut() {
            if l.side == lung_model::mesh::Side::Left {
                l.lobes = None;
            }
        }
    }) else {
        return;
    };
    for lobe in ALL {
        let n = drawn_in(&plain, &hud, lobe.colour(), legend_box);
        if lobe.side() == Some(lung_model::mesh::Side::Left) {
            assert_eq!(n, 0, "{lobe} is not in the legend");
        } else {
            assert!(n >= 12, "{lobe}: {n} legend pixels");
        }
    }
    let grey = drawn_in(&plain, &hud, Lobe::Unknown.colour(), legend_box);
    assert!(
        grey >= grey_text + 20,
        "grey square: {grey} pixels ({grey_text} without)"
    );
    let warning = drawn_in(&plain, &hud, amber, legend_box);
    assert!(warning >= 40, "amber warning: {warning} pixels");
    // The tissue colour mode has no legend: its bottom left stays as drawn.
    scene.render.color = lung_model::scene::ColorMode::Tissue;
    let Some((plain, hud)) = render_pair(&scene, PoseWarning::None) else {
        return;
    };
    assert_eq!(differing(&plain, &hud, (0, 360 - 40, 60, 40)), 0);
}

/// A long intervention outcome is wrapped inside the panel at 480 px wide and below, never
/// clipped at the panel's edge: its green text (a "done" outcome) stays left of the panel's right
/// edge and spans more than one row.
#[test]
fn a_long_outcome_line_wraps_inside_the_panel_at_480_px_and_below() {
    let long = "chest tube, right, already in place 01:05 — the pneumothorax is on the other side";
    for (w, h, outcome) in [
        (480u32, 360u32, OUTCOME),
        (480, 360, long),
        (320, 240, long),
    ] {
        let mut scene = Scene::default();
        scene.lungs.vertices = 2000;
        scene.render.width = w;
        scene.render.height = h;
        let Some((plain, hud, layout)) = render_hud(&scene, PoseWarning::None, outcome, |_| {})
        else {
            return;
        };
        // The panel's geometry as the HUD laid it out (renderer/src/hud): the panel and the PV
        // box, font h/40 px (at least 11, 10 in the compact HUD below 400 × 300).
        let e = layout[0].unwrap();
        let font = (h as f32 / 40.0).clamp(if h < 300 { 10.0 } else { 11.0 }, 40.0);
        let m = (font * 0.9).round();
        let pv_x = e.pv.x;
        let panel_right = e.panel.x + e.panel.w;
        // The outcome is the panel's fourth row (below the disease line, green too when none).
        let outcome_top = m + font * 1.3 * 3.0 - 1.0;
        let green: Vec<(u32, u32)> = hud
            .enumerate_pixels()
            .filter(|&(x, y, p)| {
                (x as f32) < pv_x
                    && y as f32 >= outcome_top
                    && p[1] > 150
                    && p[1] as i32 > p[0] as i32 + 60
                    && p[1] as i32 > p[2] as i32 + 40
                    && plain.get_pixel(x, y) != p
            })
            .map(|(x, y, _)| (x, y))
            .collect();
        assert!(green.len() > 100, "{w}x{h}: {} outcome pixels", green.len());
        let &(rx, ry) = green.iter().max_by_key(|p| p.0).unwrap();
        let right = rx as f32;
        assert!(
            right < panel_right - 3.0,
            "{w}x{h} {outcome:?}: text reaches x = {right} (y {ry}, {:?}), the panel ends at \
             {panel_right}",
            hud.get_pixel(rx, ry)
        );
        let (top, bottom) = (
            green.iter().map(|p| p.1).min().unwrap(),
            green.iter().map(|p| p.1).max().unwrap(),
        );
        assert!(
            (bottom - top) as f32 > 1.5 * font * 1.3,
            "{w}x{h} {outcome:?}: one row ({top}..{bottom}), not wrapped"
        );
    }
}

/// Render the front view with the HUD at each of `sizes`, mono and stereo, in tissue and lobes
/// colour, and call `check` with where it was (for messages), the image without the HUD, each
/// eye's layout and the colour mode; `false` when there is no GPU (nothing checked).
fn at_every_size(
    sizes: &[(u32, u32)],
    check: impl FnMut(&str, &image::RgbaImage, &EyeLayout, lung_model::scene::ColorMode),
) -> bool {
    at_every_size_showing(sizes, OUTCOME, check)
}

/// As [`at_every_size`], with `outcome` as the intervention's line ("": none sent).
fn at_every_size_showing(
    sizes: &[(u32, u32)],
    outcome: &str,
    mut check: impl FnMut(&str, &image::RgbaImage, &EyeLayout, lung_model::scene::ColorMode),
) -> bool {
    for &(w, h) in sizes {
        for stereo in [false, true] {
            for color in [
                lung_model::scene::ColorMode::Tissue,
                lung_model::scene::ColorMode::Lobes,
            ] {
                let mut scene = Scene::default();
                scene.lungs.vertices = 2000;
                scene.render.width = w;
                scene.render.height = h;
                scene.render.stereo = stereo;
                scene.render.color = color;
                let Some((plain, _, layout)) =
                    render_hud(&scene, PoseWarning::None, outcome, |_| {})
                else {
                    return false;
                };
                let eyes = if stereo { 2 } else { 1 };
                assert_eq!(layout.iter().flatten().count(), eyes);
                for (i, e) in layout.iter().flatten().enumerate() {
                    let at = format!("{w}x{h} {color:?} stereo {stereo} eye {i}");
                    check(&at, &plain, e, color);
                }
            }
        }
    }
    true
}

/// The anchored labels (R, L, the head and feet cues) never cover the panel, the PV loop or the
/// lobe legend, and stay inside their eye, mono and stereo, from 320 × 240 up: at 480 × 360 the
/// head cue's anchor above the apices projects onto the panel, so it is moved beside or below it.
/// Every label whose anchor is on screen is still shown (there is room for each at these sizes).
#[test]
fn anchored_labels_never_overlap_the_panels() {
    let sizes = [(320u32, 240u32), (480, 360), (640, 480), (1280, 720)];
    at_every_size(&sizes, |at, _, e, color| {
        assert_eq!(
            e.legend.is_some(),
            color == lung_model::scene::ColorMode::Lobes
        );
        // The front view shows both lungs: all four labels have room.
        for (k, name) in ["R", "L", "head", "feet"].iter().enumerate() {
            let label = e.labels[k].unwrap_or_else(|| panic!("{at}: no {name}"));
            assert!(
                e.eye.contains(&label),
                "{at}: {name} {label:?} leaves the eye"
            );
            for (part, r) in [
                ("panel", Some(e.panel)),
                ("PV loop", Some(e.pv)),
                ("legend", e.legend),
            ] {
                if let Some(r) = r {
                    assert!(
                        !label.overlaps(&r),
                        "{at}: {name} {label:?} overlaps the {part} {r:?}"
                    );
                }
            }
        }
    });
}

/// At every size from 320 × 240 to 1920 × 1080, mono and stereo, in tissue and lobes colour (with
/// the legend): every text block the HUD draws lies wholly inside what it is clipped to, so no
/// text is cut off (the PV loop's title ran past its box and the eye's edge at 480 px and 1920 px
/// wide, the right eye's panel past the eye's left edge in stereo); every part lies inside its
/// eye; and the lungs, framed as strips and recordings frame them, are clear of the panel, the PV
/// loop and the legend — neither their projected box nor any lung pixel lies under them (at
/// 320 × 240 the panel covered the apices). The same with an unusually long outcome (many wrapped
/// rows at every size: it once grew the panel over the apices), which is cut to its reserved rows.
#[test]
fn the_hud_fits_every_size_without_clipped_text_or_covering_the_lungs() {
    let sizes = [
        (320u32, 240u32),
        (480, 360),
        (640, 480),
        (960, 540),
        (1280, 720),
        (1920, 1080),
    ];
    for outcome in [OUTCOME, LONG_OUTCOME] {
        hud_fits(&sizes, outcome);
    }
}

/// An outcome of many rows wherever it wraps (the reply of a tension scene's chest tube with its
/// reasons, said in full).
const LONG_OUTCOME: &str = "chest tube, left, applied 01:02 — air and blood draining, the lung \
    re-expanding over the next breaths; the tension is relieved, mediastinal shift resolving, \
    venous return recovering; keep the drain below the chest and watch for a persistent air leak";

/// The parts of the HUD inside their eyes, no text clipped and the lungs clear, at `sizes` with
/// `outcome` shown; the outcome takes at most its reserved rows.
fn hud_fits(sizes: &[(u32, u32)], outcome: &str) {
    at_every_size_showing(sizes, outcome, |at, plain, e, _| {
        let row = e.texts[0].expect("the volume line").text.h;
        let outcome_box = e.texts[renderer::hud::OUTCOME_BLOCK].expect("the outcome line");
        assert!(
            outcome_box.text.h <= row * renderer::hud::OUTCOME_RESERVED_ROWS as f32 + 0.5,
            "{at}: the outcome takes {} px, rows of {row} px",
            outcome_box.text.h
        );
        let background = *plain.get_pixel(0, 0);
        let parts = [
            ("panel", Some(e.panel)),
            ("PV loop", Some(e.pv)),
            ("legend", e.legend),
        ];
        for (part, r) in parts {
            if let Some(r) = r {
                assert!(e.eye.contains(&r), "{at}: the {part} {r:?} leaves the eye");
            }
        }
        let mut drawn = 0;
        for (k, t) in e.texts.iter().enumerate() {
            let Some(t) = t else { continue };
            drawn += 1;
            // Half a pixel for the rounding of glyph positions.
            let text = renderer::hud::Rect {
                x: t.text.x + 0.5,
                y: t.text.y + 0.5,
                w: (t.text.w - 1.0).max(0.0),
                h: (t.text.h - 1.0).max(0.0),
            };
            assert!(
                t.text.w > 0.0 && t.clip.contains(&text),
                "{at}: text block {k} {:?} is clipped by {:?}",
                t.text,
                t.clip
            );
            assert!(
                e.eye.contains(&t.clip),
                "{at}: block {k} {:?} leaves the eye",
                t.clip
            );
        }
        // The panel's lines (four in the compact HUD at 320 × 240), the PV title, the
        // labels, and the legend in the lobes mode.
        assert!(drawn >= 9, "{at}: {drawn} text blocks");
        let lungs = e
            .lungs
            .unwrap_or_else(|| panic!("{at}: the lungs are off screen"));
        assert!(
            e.eye.contains(&lungs),
            "{at}: lungs {lungs:?} leave the eye"
        );
        for (part, r) in parts {
            let Some(r) = r else { continue };
            assert!(
                !lungs.overlaps(&r),
                "{at}: lungs {lungs:?} under the {part} {r:?}"
            );
            let under = (r.x.floor() as u32..(r.x + r.w).ceil() as u32)
                .flat_map(|x| (r.y.floor() as u32..(r.y + r.h).ceil() as u32).map(move |y| (x, y)))
                .filter(|&(x, y)| x < plain.width() && y < plain.height())
                .filter(|&(x, y)| *plain.get_pixel(x, y) != background)
                .count();
            assert_eq!(under, 0, "{at}: {under} lung pixels under the {part} {r:?}");
        }
    });
}

/// Before any intervention is sent the panel has no outcome row (it showed an empty one between
/// the disease and the tracker lines); the lungs' framing stays where it is when one arrives (the
/// band keeps the outcome's reserved rows), so the picture does not jump.
#[test]
fn no_outcome_row_before_an_intervention_is_sent() {
    let mut scene = Scene::default();
    scene.lungs.vertices = 2000;
    scene.render.width = 640;
    scene.render.height = 480;
    let eye = |outcome| {
        render_hud(&scene, PoseWarning::None, outcome, |_| {}).map(|(_, _, l)| l[0].unwrap())
    };
    let (Some(none), Some(sent)) = (eye(""), eye(OUTCOME)) else {
        return;
    };
    let k = renderer::hud::OUTCOME_BLOCK;
    assert!(none.texts[k].is_none(), "{:?}", none.texts[k]);
    let outcome = sent.texts[k].expect("the outcome line once sent");
    // The lines after the outcome move up into its place, and the panel shrinks by as much: the
    // outcome's rows (its text's height, to the glyphs' rounding).
    let (a, b) = (none.texts[k + 1].unwrap(), sent.texts[k + 1].unwrap());
    let shift = b.text.y - a.text.y;
    assert!(
        (sent.panel.h - none.panel.h - shift).abs() < 0.5 && shift >= outcome.text.h - 0.5,
        "the panel without the outcome {:?}, with {:?}; the next line moved {shift} px for {} px \
         of outcome",
        none.panel,
        sent.panel,
        outcome.text.h
    );
    assert_eq!(none.lungs, sent.lungs, "the lungs' framing");
}
