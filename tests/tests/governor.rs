//! The quality governor through the renderer's session, on whatever GPU the tests get: its target
//! set below any real frame makes every frame late, so it gives up each step of a translucent,
//! multisampled scene in order — multisampling, the draw levels, the drawn vertices only, the
//! look — drawing each (a variant built at start: no validation error, no pipeline compiled
//! mid-run), flags every frame's report with what it gave up and, with nothing left, its floor;
//! its target set far above any frame gives everything back. Driven in process on in-memory ports and a fake clock.

use ipc_types::{report_flags as rf, FrameReport};
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use lungdyn_tests::prepared_scene;
use renderer::governor::{Quality, Step};
use renderer::gpu::Gpu;
use renderer::process::{Ports, Session, Snapshots};
use renderer::{LungRenderer, RenderLung};
use transport::memory::{Recorder, Scripted};
use transport::FakeClock;

const P: u64 = 16_666_667;

/// A translucent, multisampled scene of 3000-vertex lungs, its session on in-memory ports fed `n`
/// engine frames on a fake clock, and the recorder of its frame reports (`tag`: the test's own
/// folder; tests run side by side).
fn translucent_session(gpu: Gpu, n: u64, tag: &str) -> (Session, Recorder<FrameReport>) {
    let scene = Scene::load(&prepared_scene(
        tag,
        "[lungs]\nvertices = 3000\n[render]\nlook = \"translucent\"\nmsaa = 4\nwidth = 160\nheight = 120\n",
    ))
    .unwrap();
    let lungs = scene.lung_models().unwrap();
    let clock = FakeClock::at(0);
    let frames = (1..=n)
        .map(|t| {
            (
                t * P,
                lungdyn_tests::engine_frame(&lungs, t, 1200.0 + (t % 50) as f32),
            )
        })
        .collect();
    let reports = Recorder::<FrameReport>::new(&clock);
    let ports = Ports {
        engine: Box::new(Scripted::new(&clock, frames, 4)),
        tracker: Box::new(Scripted::new(&clock, vec![], 4)),
        report: Box::new(reports.clone()),
    };
    let render: Vec<RenderLung> = lungs.iter().map(RenderLung::from_model).collect();
    let r = LungRenderer::new(&gpu, &scene.render, &render).unwrap();
    let session = Session::assemble(
        gpu,
        r,
        &scene,
        &render,
        ports,
        Box::new(clock.clone()),
        Snapshots::default(),
        "governor",
    );
    (session, reports)
}

#[test]
fn late_frames_give_up_each_step_in_order_and_time_to_spare_takes_them_back() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let n = 900u64;
    let (mut session, reports) = translucent_session(gpu, n, "governor");
    let steps = session.renderer.governor_steps().to_vec();
    let levels = session.renderer.lod_triangles().len();
    assert!(levels >= 2, "3000-vertex lungs build coarser draw levels");
    let mut expected = vec![Step::MsaaOff];
    expected.extend(std::iter::repeat_n(Step::CoarserLod, levels - 1));
    expected.push(Step::DrawnOnly);
    expected.push(Step::Opaque);
    assert_eq!(steps, expected, "the ladder of a translucent 4x scene");
    // Every frame late: all the way down.
    session.set_governor_target_ns(1);
    while session.stats().frames < 200 {
        session.step(&mut renderer::process::Headless).unwrap();
    }
    let late = reports.values();
    let quality = |r: &FrameReport| r.flags & rf::QUALITY_LOWERED;
    let mut seen: Vec<u32> = Vec::new();
    for r in &late {
        if seen.last() != Some(&quality(r)) {
            seen.push(quality(r));
        }
    }
    let order: Vec<u32> = (0..=steps.len())
        .map(|k| Quality::of(&steps, k).report_bits())
        .collect();
    assert_eq!(
        seen, order,
        "each step in turn, none skipped, none taken back"
    );
    assert!(
        late.last().unwrap().flags & rf::GOVERNOR_FLOOR != 0,
        "with everything given up and still late: the floor"
    );
    assert_eq!(
        session.renderer.lod_shown().level as usize,
        levels - 1,
        "drawn at the coarsest level"
    );
    assert_eq!(session.renderer.samples(), 1);
    assert_eq!(session.renderer.scene_samples(), 4);
    // Time to spare: everything back, one step at a time.
    session.set_governor_target_ns(u64::MAX / 4);
    while session.stats().frames < n - 10 {
        session.step(&mut renderer::process::Headless).unwrap();
    }
    let spare = reports.values().split_off(late.len());
    let last = spare.last().unwrap();
    assert_eq!(quality(last), 0, "full quality again");
    assert_eq!(last.flags & rf::GOVERNOR_FLOOR, 0);
    let mut back: Vec<u32> = Vec::new();
    for r in &spare {
        if back.last() != Some(&quality(r)) {
            back.push(quality(r));
        }
    }
    let mut reversed = order.clone();
    reversed.reverse();
    assert_eq!(back, reversed, "taken back in the reverse order");
    assert_eq!(session.renderer.samples(), 4);
}

/// Where a run settled is where the next one starts (`[render] governor_start = "remembered"`,
/// `renderer::governor_memory`): a session whose every frame is late gives everything up, holds
/// its floor past the settling frames and keeps it at its end; the next session of the same
/// setting draws its first frame there, with no change; a folder with nothing kept starts at full
/// quality.
#[test]
fn the_next_run_starts_where_the_last_one_settled() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let dir = std::env::temp_dir().join(format!("lungdyn-governor-kept-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let n = 600u64;
    let (mut first, reports) = translucent_session(gpu, n, "governor-start");
    let steps = first.renderer.governor_steps().to_vec();
    first.set_governor_target_ns(1);
    first.start_where_settled(&dir);
    assert_eq!(reports.values().len(), 0);
    while first.stats().frames < n - 10 {
        first.step(&mut renderer::process::Headless).unwrap();
    }
    let late = reports.values();
    let quality = |r: &FrameReport| r.flags & rf::QUALITY_LOWERED;
    let floor = Quality::of(&steps, steps.len()).report_bits();
    assert_eq!(
        quality(&late[0]),
        0,
        "nothing kept: the first run starts at full quality"
    );
    assert_eq!(quality(late.last().unwrap()), floor);
    first.finish();
    let kept: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(kept.len(), 1, "one file kept: {kept:?}");
    let text = std::fs::read_to_string(&kept[0]).unwrap();
    assert!(
        text.contains(&format!("\"given_up\": {}", steps.len())),
        "{text}"
    );

    let Some(gpu) = Gpu::for_tests() else { return };
    let (mut second, reports) = translucent_session(gpu, 60, "governor-start");
    second.set_governor_target_ns(1);
    second.start_where_settled(&dir);
    assert!(
        second
            .describe_governor()
            .contains("where the last run of these lungs on this adapter settled"),
        "{}",
        second.describe_governor()
    );
    while second.stats().frames < 40 {
        second.step(&mut renderer::process::Headless).unwrap();
    }
    let drawn = reports.values();
    assert!(
        drawn.iter().all(|r| quality(r) == floor),
        "every frame at the kept quality, from the first"
    );
    assert_eq!(second.renderer.samples(), 1, "MSAA off from the start");

    // Another folder, nothing kept: full quality.
    let Some(gpu) = Gpu::for_tests() else { return };
    let (mut third, reports) = translucent_session(gpu, 20, "governor-start");
    third.set_governor_target_ns(1);
    third.start_where_settled(&dir.join("elsewhere"));
    third.step(&mut renderer::process::Headless).unwrap();
    assert_eq!(quality(&reports.values()[0]), 0);
    let _ = std::fs::remove_dir_all(&dir);
}
