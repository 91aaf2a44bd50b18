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

#[test]
fn late_frames_give_up_each_step_in_order_and_time_to_spare_takes_them_back() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let scene = Scene::load(&prepared_scene(
        "governor",
        "[lungs]\nvertices = 3000\n[render]\nlook = \"translucent\"\nmsaa = 4\nwidth = 160\nheight = 120\n",
    ))
    .unwrap();
    let lungs = scene.lung_models().unwrap();
    let clock = FakeClock::at(0);
    let n = 900u64;
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
    let steps = r.governor_steps().to_vec();
    let levels = r.lod_triangles().len();
    assert!(levels >= 2, "3000-vertex lungs build coarser draw levels");
    let mut expected = vec![Step::MsaaOff];
    expected.extend(std::iter::repeat_n(Step::CoarserLod, levels - 1));
    expected.push(Step::DrawnOnly);
    expected.push(Step::Opaque);
    assert_eq!(steps, expected, "the ladder of a translucent 4x scene");
    let mut session = Session::assemble(
        gpu,
        r,
        &scene,
        &render,
        ports,
        Box::new(clock.clone()),
        Snapshots::default(),
        "governor",
    );
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
