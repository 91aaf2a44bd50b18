//! Offscreen rendering on the real wgpu path (lavapipe in CI): fixed states are rendered in every
//! look (opaque tissue, translucent, see-through), as point splats and in the colour modes (the
//! lobes mode in every look), mono and stereo, read back and compared with committed reference images (`tests/reference/*.png`,
//! rendered by lavapipe, 256×192 per eye mono, 192×144 per eye stereo) under each case's stated
//! tolerance. On failure the actual and difference images are written under
//! `target/image-diffs/` (`NAME.actual.png`, `NAME.diff.png`: the per-pixel largest channel
//! difference ×8 in red).
//!
//! Regenerate the references deliberately, after a change meant to alter the picture:
//! `LUNGDYN_BLESS=1 cargo test --release -p lungdyn-tests --test image` (then look at them).

use std::path::PathBuf;
use std::sync::OnceLock;

use lung_model::deform::LungModel;
use lung_model::scene::{ColorMode, DrawMode, Look, RenderScene, Scene};
use renderer::gpu::Gpu;
use renderer::{DrawState, LungRenderer, RenderLung};

/// How far an image may be from its reference: a pixel differs when any channel differs by more
/// than `channel` (out of 255); at most `fraction` of the pixels may differ (rasterisation and
/// blending differences at silhouettes between drivers).
#[derive(Debug, Clone, Copy)]
struct Tolerance {
    channel: u8,
    fraction: f64,
}

/// Opaque and see-through looks and splats: 12/255, 0.5 % of pixels.
const STRICT: Tolerance = Tolerance {
    channel: 12,
    fraction: 0.005,
};
/// The translucent look: half-float accumulation of weights up to 3·10³ rounds differently
/// between drivers; 16/255, 1 % of pixels.
const BLENDED: Tolerance = Tolerance {
    channel: 16,
    fraction: 0.01,
};

fn reference(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("reference")
        .join(name)
}

/// Where failed comparisons leave their images: the workspace's target folder.
fn diff_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target"));
    target.join("image-diffs")
}

/// The default scene's lungs at 4000 vertices each, baked once for every test of this binary.
fn models() -> &'static [LungModel] {
    static MODELS: OnceLock<Vec<LungModel>> = OnceLock::new();
    MODELS.get_or_init(|| {
        let mut scene = Scene::default();
        scene.lungs.vertices = 4000;
        lungdyn_tests::baked_models(&scene)
    })
}

fn render(lungs: &[LungModel]) -> Vec<RenderLung> {
    lungs.iter().map(RenderLung::from_model).collect()
}

/// The deformation scale of mid-inspiration: 250 ml over both lungs.
fn mid_inspiration() -> f32 {
    let lungs = models();
    lungs[0].scale_for_delta(250.0 * lungs[0].start_volume_ml / 2400.0) as f32
}

/// The image tests' view ([`lungdyn_tests::fixed_state`]): the HMD at the patient's right, above
/// the chest.
fn fixed_state(scale: f32) -> DrawState {
    lungdyn_tests::fixed_state(scale, 1.0)
}

/// The render table of a case: mono 256×192, or stereo 2 × 192×144.
fn settings(mode: DrawMode, look: Look, color: ColorMode, stereo: bool) -> RenderScene {
    let (width, height) = if stereo { (192, 144) } else { (256, 192) };
    RenderScene {
        mode,
        look,
        color,
        stereo,
        width,
        height,
        // The references show the look as on a GPU (lavapipe's default is 1).
        msaa: Some(4),
        ..RenderScene::default()
    }
}

/// Render the fixed state at `scale` with `render` and read the image back.
fn draw(gpu: &Gpu, render: &RenderScene, scale: f32) -> image::RgbaImage {
    let r = LungRenderer::new(gpu, render, &self::render(models())).unwrap();
    r.render(gpu, &fixed_state(scale), true);
    r.read_image(gpu).unwrap()
}

fn compare(name: &str, actual: &image::RgbaImage, tolerance: Tolerance) {
    let path = reference(name);
    if std::env::var("LUNGDYN_BLESS").as_deref() == Ok("1") {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        renderer::write_png(actual, &path).unwrap();
        eprintln!("blessed {}", path.display());
        return;
    }
    let expected = image::open(&path)
        .unwrap_or_else(|e| {
            panic!(
                "reference {} unreadable ({e}); create it with LUNGDYN_BLESS=1",
                path.display()
            )
        })
        .to_rgba8();
    assert_eq!(expected.dimensions(), actual.dimensions(), "{name}");
    let mut diff = image::RgbaImage::new(actual.width(), actual.height());
    let mut different = 0usize;
    for (x, y, a) in actual.enumerate_pixels() {
        let e = expected.get_pixel(x, y);
        let d = (0..3).map(|c| a[c].abs_diff(e[c])).max().unwrap();
        if d > tolerance.channel {
            different += 1;
        }
        diff.put_pixel(x, y, image::Rgba([d.saturating_mul(8), 0, 0, 255]));
    }
    let fraction = different as f64 / (actual.width() * actual.height()) as f64;
    if fraction > tolerance.fraction {
        let dir = diff_dir();
        std::fs::create_dir_all(&dir).unwrap();
        let stem = name.trim_end_matches(".png");
        let actual_path = dir.join(format!("{stem}.actual.png"));
        let diff_path = dir.join(format!("{stem}.diff.png"));
        actual.save(&actual_path).unwrap();
        diff.save(&diff_path).unwrap();
        panic!(
            "{name}: {:.3} % of pixels differ by more than {}/255 (allowed {:.3} %); wrote {} and {}",
            100.0 * fraction,
            tolerance.channel,
            100.0 * tolerance.fraction,
            actual_path.display(),
            diff_path.display()
        );
    }
}

/// Render one case mono and stereo at mid-inspiration and compare both with their references.
fn look_case(gpu: &Gpu, name: &str, mode: DrawMode, look: Look, color: ColorMode, t: Tolerance) {
    for stereo in [false, true] {
        let img = draw(gpu, &settings(mode, look, color, stereo), mid_inspiration());
        let eyes = if stereo { "stereo" } else { "mono" };
        compare(&format!("{name}_{eyes}.png"), &img, t);
    }
}

#[test]
fn a_fixed_state_renders_like_the_reference_image() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    look_case(&gpu, "tissue", D::Triangles, L::Opaque, C::Tissue, STRICT);
}

#[test]
fn the_translucent_look_renders_like_its_reference_images() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    look_case(
        &gpu,
        "translucent",
        D::Triangles,
        L::Translucent,
        C::Tissue,
        BLENDED,
    );
}

#[test]
fn the_see_through_look_renders_like_its_reference_images_on_black() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    look_case(
        &gpu,
        "see_through",
        D::Triangles,
        L::SeeThrough,
        C::Tissue,
        STRICT,
    );
    // An additive display shows black as transparent: nothing but the lungs emits light.
    let img = draw(
        &gpu,
        &settings(D::Triangles, L::SeeThrough, C::Tissue, false),
        0.0,
    );
    assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0, 255]);
    let lit = img.pixels().filter(|p| p.0[..3] != [0, 0, 0]).count();
    assert!(lit > 2000, "the lungs emit: {lit} pixels");
}

#[test]
fn point_splats_render_like_their_reference_images() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    look_case(&gpu, "points", D::Points, L::Opaque, C::Tissue, STRICT);
}

#[test]
fn the_colour_modes_render_like_their_reference_images() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    for (name, color) in [
        ("displacement", C::Displacement),
        ("ventilation", C::Ventilation),
    ] {
        let img = draw(
            &gpu,
            &settings(D::Triangles, L::Opaque, color, false),
            mid_inspiration(),
        );
        compare(&format!("{name}_mono.png"), &img, STRICT);
    }
}

/// Lung pixels of an opaque mono image (those unlike the background corner).
fn lung_pixels(img: &image::RgbaImage) -> Vec<[u8; 4]> {
    let background = *img.get_pixel(0, 0);
    img.pixels()
        .filter(|p| **p != background)
        .map(|p| p.0)
        .collect()
}

#[test]
fn the_colour_fields_are_zero_at_rest_and_grow_with_the_breath() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    let scene = |color| settings(D::Triangles, L::Opaque, color, false);
    // Displacement at rest: all dark blue; at full inspiration some of the lungs moved ≥ 10 mm
    // (green-yellow: red and green over blue).
    let rest = lung_pixels(&draw(&gpu, &scene(C::Displacement), 0.0));
    assert!(rest.len() > 2000);
    let bluish = rest.iter().filter(|p| p[2] > p[0] && p[2] >= p[1]).count();
    assert!(
        bluish * 100 >= rest.len() * 95,
        "{bluish} of {}",
        rest.len()
    );
    let full = lung_pixels(&draw(
        &gpu,
        &scene(C::Displacement),
        4.0 * mid_inspiration(),
    ));
    let moved = full.iter().filter(|p| p[1] > p[2] + 20).count();
    assert!(moved * 20 > full.len(), "{moved} of {} moved", full.len());
    // Ventilation at rest: no expansion anywhere, grey (channels within the lighting's tint); with
    // the breath, expanding regions turn red.
    let rest = lung_pixels(&draw(&gpu, &scene(C::Ventilation), 0.0));
    let grey = rest
        .iter()
        .filter(|p| p[0].abs_diff(p[2]) < 40 && p[0].abs_diff(p[1]) < 40)
        .count();
    assert!(grey * 100 >= rest.len() * 90, "{grey} of {}", rest.len());
    let full = lung_pixels(&draw(&gpu, &scene(C::Ventilation), 4.0 * mid_inspiration()));
    let red = full.iter().filter(|p| p[0] > p[2] + 40).count();
    assert!(red * 10 > full.len(), "{red} of {} red", full.len());
}

#[test]
fn msaa_smooths_the_silhouette_and_can_be_turned_off() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    let mut off = settings(D::Triangles, L::Opaque, C::Tissue, false);
    off.msaa = Some(1);
    let on = settings(D::Triangles, L::Opaque, C::Tissue, false);
    let (a, b) = (draw(&gpu, &off, 0.0), draw(&gpu, &on, 0.0));
    // The same picture away from the edges; different (blended) along the silhouette.
    let differing = a.pixels().zip(b.pixels()).filter(|(p, q)| p != q).count();
    let total = (a.width() * a.height()) as usize;
    assert!(differing > 100, "MSAA changed {differing} pixels");
    assert!(differing * 4 < total, "MSAA changed {differing} of {total}");
}

#[test]
fn stereo_point_splats_draw_both_eyes_from_one_deformation() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let mut scene = Scene::default();
    scene.lungs.vertices = 4000;
    scene.render.width = 160;
    scene.render.height = 120;
    scene.render.stereo = true;
    scene.render.mode = DrawMode::Points;
    let r = LungRenderer::new(&gpu, &scene.render, &render(models())).unwrap();
    assert_eq!(r.image_size(), (320, 120));
    r.render(&gpu, &fixed_state(0.0), true);
    let img = r.read_image(&gpu).unwrap();
    let background = *img.get_pixel(0, 0);
    let lit = |x0: u32| {
        (x0..x0 + 160)
            .flat_map(|x| (0..120).map(move |y| (x, y)))
            .filter(|&(x, y)| *img.get_pixel(x, y) != background)
            .count()
    };
    let (left, right) = (lit(0), lit(160));
    assert!(
        left > 500 && right > 500,
        "both eyes show the lungs: {left} / {right} pixels"
    );
    // The eyes are IPD apart: the images are similar but not identical.
    let same = (0..160)
        .flat_map(|x| (0..120).map(move |y| (x, y)))
        .filter(|&(x, y)| img.get_pixel(x, y) == img.get_pixel(x + 160, y))
        .count();
    assert!(same < 160 * 120, "stereo eyes must differ");
}

#[test]
fn the_gpu_deformation_matches_the_cpu_reference() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let mut scene = Scene::default();
    scene.render.width = 64;
    scene.render.height = 64;
    let lungs = models();
    let r = LungRenderer::new(&gpu, &scene.render, &render(lungs)).unwrap();
    for (scale_r, scale_l) in [
        (0.0f32, 0.0f32),
        (37.5, 12.25),
        (150.0, 140.0),
        (-20.0, 400.0),
    ] {
        let mut state = fixed_state(0.0);
        state.deform_scale = [scale_r, scale_l];
        r.render(&gpu, &state, false);
        let gpu_out = r.read_deformed(&gpu).unwrap();
        let mut offset = 0;
        let mut worst = 0.0f32;
        for lung in lungs {
            let s = state.deform_scale[lung.side.index()];
            let mut cpu = vec![[0.0f32; 3]; lung.mesh.positions.len()];
            lung.deform_into(s, &mut cpu);
            for (i, c) in cpu.iter().enumerate() {
                let g = gpu_out[offset + i];
                assert!(g.iter().all(|v| v.is_finite()));
                assert_eq!(g[3], lung.side.index() as f32);
                for a in 0..3 {
                    worst = worst.max((g[a] - c[a]).abs());
                }
            }
            offset += cpu.len();
        }
        // The GPU may fuse the multiply-add; the CPU rounds twice: ≤ 1 ulp of ~200 mm.
        assert!(
            worst <= 1e-4,
            "scales ({scale_r}, {scale_l}): max |gpu - cpu| = {worst} mm"
        );
    }
}

/// No silent skips: run one of this binary's GPU tests again in a child with the Vulkan loader
/// pointed at no driver (`VK_ICD_FILENAMES`, what a machine without lavapipe looks like). Without
/// an opt-out it must fail naming the package; with `LUNGDYN_SKIP_GPU=1` it passes, says SKIPPED past
/// the harness's capture and logs one line in the skip log that `./run test` counts.
#[test]
fn without_a_vulkan_driver_a_gpu_test_fails_naming_the_package_unless_skipped_aloud() {
    let exe = std::env::current_exe().unwrap();
    let log = std::env::temp_dir().join(format!("lungdyn-skiplog-{}.log", std::process::id()));
    let _ = std::fs::remove_file(&log);
    let run = |skip: bool| {
        let mut c = std::process::Command::new(&exe);
        c.args([
            "--exact",
            "a_fixed_state_renders_like_the_reference_image",
            "--test-threads",
            "1",
        ])
        .env("VK_ICD_FILENAMES", "/nonexistent/lungdyn-no-driver.json")
        .env("VK_DRIVER_FILES", "/nonexistent/lungdyn-no-driver.json")
        .env("LUNGDYN_SKIP_LOG", &log)
        .env_remove("LUNGDYN_REQUIRE_GPU")
        .env_remove("LUNGDYN_SKIP_ALL");
        if skip {
            c.env("LUNGDYN_SKIP_GPU", "1");
        } else {
            c.env_remove("LUNGDYN_SKIP_GPU");
        }
        let out = c.output().unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        (out.status.success(), text)
    };
    let (ok, text) = run(false);
    assert!(!ok, "a GPU test without a driver must fail: {text}");
    assert!(
        text.contains("mesa-vulkan-drivers") && text.contains("LUNGDYN_SKIP_GPU=1"),
        "{text}"
    );
    assert!(!log.exists(), "a failure is not a skip");
    let (ok, text) = run(true);
    assert!(ok, "opted out: {text}");
    assert!(text.contains("SKIPPED"), "said aloud: {text}");
    let logged = std::fs::read_to_string(&log).unwrap();
    assert_eq!(logged.lines().count(), 1, "{logged}");
    assert!(
        logged.contains("a_fixed_state_renders_like_the_reference_image"),
        "{logged}"
    );
    std::fs::remove_file(&log).ok();
}

/// The lobes colour mode in every look: each lobe its own colour from the lobe codes a bake
/// writes, fissures as lines where lobes meet (dark on tissue, light on the see-through look).
#[test]
fn the_lobes_colour_mode_renders_like_its_reference_images_in_every_look() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    look_case(&gpu, "lobes", D::Triangles, L::Opaque, C::Lobes, STRICT);
    for (name, mode, look, t) in [
        ("lobes_translucent", D::Triangles, L::Translucent, BLENDED),
        ("lobes_see_through", D::Triangles, L::SeeThrough, STRICT),
        ("lobes_points", D::Points, L::Opaque, STRICT),
    ] {
        let img = draw(
            &gpu,
            &settings(mode, look, C::Lobes, false),
            mid_inspiration(),
        );
        compare(&format!("{name}_mono.png"), &img, t);
    }
}

/// Handedness (issue 19), from the pixels: in an anterior snapshot (the front view strips and
/// recordings use, of a supine patient, head up) the patient's right lung — its three lobes'
/// colours — is on the viewer's left, the left lung on the viewer's right, as a clinician facing
/// the patient and an anterior radiograph show them. With body → room taken as a rotation (before
/// the fix) the two were swapped: a mirror-image patient.
#[test]
fn the_patients_right_lung_is_on_the_viewers_left_in_an_anterior_snapshot() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let scene = settings(DrawMode::Triangles, Look::Opaque, ColorMode::Lobes, false);
    let r = LungRenderer::new(&gpu, &scene, &render(models())).unwrap();
    let mut state = fixed_state(mid_inspiration());
    state.hmd = r.front_view(&state.patient).unwrap();
    r.render(&gpu, &state, true);
    let img = r.read_image(&gpu).unwrap();
    let (mut sum, mut n) = ([0.0f64; 2], [0usize; 2]);
    for (x, _, p) in img.enumerate_pixels() {
        if let Some(side) = nearest_lobe(p.0).and_then(|l| l.side()) {
            sum[side.index()] += x as f64;
            n[side.index()] += 1;
        }
    }
    let (right, left) = (ipc_types::LUNG_RIGHT, ipc_types::LUNG_LEFT);
    assert!(n[right] > 1000 && n[left] > 1000, "lobe pixels {n:?}");
    let mean = |k: usize| sum[k] / n[k] as f64;
    let w = img.width() as f64;
    assert!(
        mean(right) < 0.45 * w && mean(left) > 0.55 * w,
        "right-lung pixels centred at x = {:.0}, left at {:.0} of {w}",
        mean(right),
        mean(left)
    );
}

/// The lobe whose colour (`Lobe::colour`, as drawn: chromaticity, whatever the shading) is nearest
/// a lung pixel's, if one is near (within 0.06 in r/(r+g+b), g/(r+g+b)).
fn nearest_lobe(p: [u8; 4]) -> Option<lung_model::mesh::lobes::Lobe> {
    let chroma = |c: [f32; 3]| {
        let s = c[0] + c[1] + c[2];
        (s > 0.0).then(|| [c[0] / s, c[1] / s])
    };
    let lin = |c: u8| renderer::draw::srgb_to_linear(c);
    let q = chroma([lin(p[0]), lin(p[1]), lin(p[2])])?;
    lung_model::mesh::lobes::ALL
        .into_iter()
        .map(|l| {
            let c = chroma(l.colour().map(lin)).unwrap();
            (l, (c[0] - q[0]).hypot(c[1] - q[1]))
        })
        .filter(|&(_, d)| d < 0.06)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(l, _)| l)
}

#[test]
fn lobes_show_in_their_colours_with_fissures_and_a_lung_without_lobe_data_shows_grey() {
    let Some(gpu) = Gpu::for_tests() else { return };
    use {ColorMode as C, DrawMode as D, Look as L};
    let scene = settings(D::Triangles, L::Opaque, C::Lobes, false);
    let supine = fixed_state(0.0).patient;
    let draw_front = |lungs: &[RenderLung]| {
        let r = LungRenderer::new(&gpu, &scene, lungs).unwrap();
        let mut state = fixed_state(mid_inspiration());
        state.hmd = r.front_view(&supine).unwrap();
        r.render(&gpu, &state, true);
        r.read_image(&gpu).unwrap()
    };
    // From the front, every lobe shows in its own colour, and fissures are drawn as dark lines.
    let img = draw_front(&render(models()));
    let lung = lung_pixels(&img);
    assert!(lung.len() > 4000, "{} lung pixels", lung.len());
    let mut counts = std::collections::HashMap::new();
    for p in &lung {
        if let Some(l) = nearest_lobe(*p) {
            *counts.entry(l).or_insert(0usize) += 1;
        }
    }
    for lobe in lung_model::mesh::lobes::ALL {
        let n = counts.get(&lobe).copied().unwrap_or(0);
        assert!(n * 200 > lung.len(), "{lobe}: {n} of {} pixels", lung.len());
    }
    let dark = |p: &&[u8; 4]| p[..3].iter().all(|&c| c < 40);
    let fissure = lung.iter().filter(dark).count();
    assert!(fissure > 40, "{fissure} fissure pixels");
    // The left lung without lobe codes (a kernel baked before the lobe section): grey, no
    // fissure, never a lobe's colour; the right lung keeps its lobes.
    let mut lungs = render(models());
    let left = lungs
        .iter_mut()
        .find(|l| l.side == lung_model::mesh::Side::Left)
        .unwrap();
    left.lobes = None;
    let img = draw_front(&lungs);
    let lung = lung_pixels(&img);
    let grey = |p: &&[u8; 4]| p[0].abs_diff(p[2]) < 40 && p[0].abs_diff(p[1]) < 40 && p[0] > 40;
    let greys = lung.iter().filter(grey).count();
    assert!(greys > 1000, "{greys} grey pixels of {}", lung.len());
    let lobes: Vec<_> = lung.iter().filter_map(|p| nearest_lobe(*p)).collect();
    let left_lobes = lobes
        .iter()
        .filter(|l| l.side() == Some(lung_model::mesh::Side::Left))
        .count();
    assert!(
        left_lobes * 200 < lung.len(),
        "{left_lobes} left-lobe pixels"
    );
    let right_lobes = lobes.len() - left_lobes;
    assert!(right_lobes > 1000, "{right_lobes} right-lobe pixels");
}
