//! The draw level of detail on the real wgpu path (lavapipe in CI): the default framings draw every
//! triangle (the image tests' pictures are the full mesh's), lungs that cover few pixels draw a
//! coarser level in both eyes alike, the level follows the viewing distance without flickering,
//! and a coarser level's picture differs from the full mesh's only at a few silhouette pixels.

use std::sync::OnceLock;

use lung_model::deform::LungModel;
use lung_model::scene::{Lod, RenderScene, Scene};
use lungdyn_tests::fixed_state;
use renderer::gpu::Gpu;
use renderer::{LungRenderer, RenderLung};

/// The default scene's lungs (2 × 10k vertices), baked once for every test of this binary.
fn models() -> &'static [LungModel] {
    static MODELS: OnceLock<Vec<LungModel>> = OnceLock::new();
    MODELS.get_or_init(|| lungdyn_tests::baked_models(&Scene::default()))
}

/// The image tests' lungs (2 × 4000 vertices).
fn image_test_models() -> &'static [LungModel] {
    static MODELS: OnceLock<Vec<LungModel>> = OnceLock::new();
    MODELS.get_or_init(|| {
        let mut scene = Scene::default();
        scene.lungs.vertices = 4000;
        lungdyn_tests::baked_models(&scene)
    })
}

fn renderer(gpu: &Gpu, render: &RenderScene) -> LungRenderer {
    renderer_of(gpu, render, models())
}

fn renderer_of(gpu: &Gpu, render: &RenderScene, models: &[LungModel]) -> LungRenderer {
    let lungs: Vec<RenderLung> = models.iter().map(RenderLung::from_model).collect();
    LungRenderer::new(gpu, render, &lungs).unwrap()
}

fn sized(width: u32, height: u32, stereo: bool, lod: Lod) -> RenderScene {
    RenderScene {
        width,
        height,
        stereo,
        lod,
        msaa: Some(1),
        ..RenderScene::default()
    }
}

/// Pixels that differ by more than 24/255 in some channel.
fn differing(a: &image::RgbaImage, b: &image::RgbaImage) -> usize {
    a.pixels()
        .zip(b.pixels())
        .filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > 24))
        .count()
}

/// The scene's default lungs and image (2 × 10k vertices, 800 × 600) from the image tests' view and
/// from the front view of strips and recordings, and the image tests' lungs and sizes (2 × 4000
/// vertices; 256 × 192 mono, 2 × 192 × 144 stereo), draw level 0 under `lod = "auto"`: the same
/// picture, to the bit, as `lod = "off"` (so the reference images are the full mesh's).
#[test]
fn the_default_framings_draw_every_triangle() {
    let Some(gpu) = Gpu::for_tests() else { return };
    for (w, h, stereo, models) in [
        (800, 600, false, models()),
        (256, 192, false, image_test_models()),
        (192, 144, true, image_test_models()),
    ] {
        let auto = renderer_of(&gpu, &sized(w, h, stereo, Lod::Auto), models);
        let off = renderer_of(&gpu, &sized(w, h, stereo, Lod::Off), models);
        assert!(
            auto.lod_triangles().len() >= 3,
            "{:?}",
            auto.lod_triangles()
        );
        assert_eq!(off.lod_triangles().len(), 1);
        let fixed = fixed_state(0.0, 1.0);
        let front = fixed_state(0.0, 1.0).patient;
        let front = renderer::DrawState {
            hmd: auto.front_view(&front).unwrap(),
            ..fixed
        };
        // The front view of strips and recordings at the default size; the image tests' view at
        // every size.
        let views = [("image tests' view", fixed), ("front view", front)];
        for (view, state) in &views[..if w == 800 { 2 } else { 1 }] {
            let state = *state;
            auto.render(&gpu, &state, true);
            off.render(&gpu, &state, true);
            let shown = auto.lod_shown();
            assert_eq!(shown.level, 0, "{w}x{h} stereo {stereo}, {view}: {shown:?}");
            assert!(shown.auto && shown.coarsest >= 2, "{shown:?}");
            assert_eq!(shown.triangles, auto.lod_triangles()[0]);
            assert_eq!(
                auto.read_image(&gpu).unwrap(),
                off.read_image(&gpu).unwrap(),
                "{w}x{h} stereo {stereo}, {view}"
            );
        }
    }
}

/// Lungs far away in a small stereo image draw a coarser level, in both eyes alike (one level per
/// frame); the picture differs from the full mesh's at under 3 % of the lungs' pixels (silhouette
/// pixels: the level's surface is within about a millimetre of the full one).
#[test]
fn small_lungs_draw_a_coarser_level_that_looks_the_same() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let auto = renderer(&gpu, &sized(160, 120, true, Lod::Auto));
    let off = renderer(&gpu, &sized(160, 120, true, Lod::Off));
    let far = fixed_state(0.0, 2.5);
    auto.render(&gpu, &far, true);
    let shown = auto.lod_shown();
    assert!(shown.level >= 1, "{shown:?}");
    assert_eq!(shown.triangles, auto.lod_triangles()[shown.level as usize]);
    let coarse = auto.read_image(&gpu).unwrap();
    off.render(&gpu, &far, true);
    let full = off.read_image(&gpu).unwrap();
    // The lungs' pixels: those not the background in the full picture.
    let background = full.get_pixel(0, 0).0;
    let lungs = full
        .pixels()
        .filter(|p| p.0.iter().zip(background).any(|(x, y)| x.abs_diff(y) > 24))
        .count();
    assert!(lungs > 500, "the lungs are on screen: {lungs} px");
    let diff = differing(&coarse, &full);
    assert!(
        (diff as f64) < 0.03 * lungs as f64,
        "level {}: {diff} of {lungs} lung pixels differ",
        shown.level
    );
    // Each eye shows its lungs at the coarse level: the right eye's half differs from the left's
    // only by the eye's offset, so both have about as many lung pixels.
    let half = |x0: u32| {
        (x0..x0 + 160)
            .flat_map(|x| (0..120).map(move |y| (x, y)))
            .filter(|&(x, y)| {
                coarse
                    .get_pixel(x, y)
                    .0
                    .iter()
                    .zip(background)
                    .any(|(a, b)| a.abs_diff(b) > 24)
            })
            .count() as f64
    };
    let (l, r) = (half(0), half(160));
    assert!((l - r).abs() < 0.15 * l.max(r), "eyes: {l} and {r} px");
}

/// Walking away from the patient and back: the level never gets finer while walking away nor
/// coarser while coming back, reaches the coarsest far away and level 0 near; swaying ±2 % about
/// every distance at which it switched never changes it (hysteresis).
#[test]
fn the_level_follows_the_distance_without_flickering() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let r = renderer(&gpu, &sized(320, 240, false, Lod::Auto));
    let coarsest = r.lod_triangles().len() - 1;
    let distances: Vec<f32> = (0..40).map(|k| 0.8 * 1.1f32.powi(k)).collect();
    let level_at = |d: f32| {
        r.render(&gpu, &fixed_state(0.0, d), false);
        r.lod_shown().level as usize
    };
    let mut switches = Vec::new();
    let mut last = level_at(distances[0]);
    assert_eq!(last, 0, "near: every triangle");
    for &d in &distances[1..] {
        let l = level_at(d);
        assert!(l >= last, "walking away at {d}: {last} → {l}");
        if l != last {
            switches.push(d);
        }
        last = l;
    }
    assert_eq!(last, coarsest, "far away: the coarsest level");
    assert!(!switches.is_empty());
    for &d in distances.iter().rev() {
        let l = level_at(d);
        assert!(l <= last, "coming back at {d}: {last} → {l}");
        last = l;
    }
    assert_eq!(last, 0);
    for &d in &switches {
        let settled = level_at(d);
        for k in 0..20 {
            let sway = if k % 2 == 0 { 1.02 } else { 0.98 };
            assert_eq!(level_at(d * sway), settled, "swaying about {d}");
        }
    }
}

/// A fixed level is drawn whatever the size (a level past the meshes' coarsest draws their
/// coarsest); `lod = 0` and `"off"` draw every triangle.
#[test]
fn a_fixed_level_is_drawn_at_every_size() {
    let Some(gpu) = Gpu::for_tests() else { return };
    for (lod, want) in [(Lod::Level(0), 0), (Lod::Level(1), 1), (Lod::Level(5), 2)] {
        let r = renderer(&gpu, &sized(320, 240, false, lod));
        for d in [0.8, 5.0] {
            r.render(&gpu, &fixed_state(0.0, d), false);
            let s = r.lod_shown();
            assert_eq!(
                s.level as usize,
                want.min(r.lod_triangles().len() - 1),
                "{lod}"
            );
            assert!(!s.auto);
        }
    }
}
