//! While the engine is down (killed, restarting) the renderer keeps presenting the last frame,
//! flagged stale, and after [`report_flags::ENGINE_DOWN_FRAMES`] stale frames says the engine is
//! down (report flag, violet veil, window title); the first fresh frame clears it. Driven in process
//! through the renderer's session on in-memory ports and a fake clock.

use ipc_types::{report_flags, FrameReport};
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use lungdyn_tests::prepared_scene;
use renderer::gpu::Gpu;
use renderer::process::{Ports, Session, Snapshots};
use renderer::{LungRenderer, RenderLung};
use transport::memory::{Recorder, Scripted};
use transport::FakeClock;

const P: u64 = 16_666_667;

#[test]
fn a_dead_engine_shows_as_its_last_frame_flagged_down_until_it_is_back() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let scene = Scene::load(&prepared_scene("engine-down", "[lungs]\nvertices = 1200\n")).unwrap();
    let lungs = scene.lung_models().unwrap();
    let frame = |tick: u64| lungdyn_tests::engine_frame(&lungs, tick, 1200.0);
    // Two frames, a 20-period outage (the engine restarting), then the resumed stream.
    let clock = FakeClock::at(0);
    let frames = vec![
        (P, frame(1)),
        (2 * P, frame(2)),
        (23 * P, frame(3)),
        (24 * P, frame(4)),
    ];
    let reports = Recorder::<FrameReport>::new(&clock);
    let ports = Ports {
        engine: Box::new(Scripted::new(&clock, frames, 4)),
        tracker: Box::new(Scripted::new(&clock, vec![], 4)),
        report: Box::new(reports.clone()),
    };
    let render: Vec<RenderLung> = lungs.iter().map(RenderLung::from_model).collect();
    let r = LungRenderer::new(&gpu, &scene.render, &render).unwrap();
    let mut session = Session::assemble(
        gpu,
        r,
        &scene,
        &render,
        ports,
        Box::new(clock.clone()),
        Snapshots::default(),
        "engine-down",
    );
    let mut down_seen = Vec::new();
    while session.stats().frames < 40 {
        if session.step(&mut renderer::process::Headless).unwrap() {
            down_seen.push(session.engine_down());
        }
    }
    let r = reports.values();
    let stale = |x: &FrameReport| x.flags & report_flags::STALE_ENGINE != 0;
    let down = |x: &FrameReport| x.flags & report_flags::ENGINE_DOWN != 0;
    // Every period of the outage is presented: the last fresh tick, stale; never a gap.
    let outage: Vec<&FrameReport> = r
        .iter()
        .filter(|x| stale(x) && x.engine_tick == 2)
        .collect();
    assert!(outage.len() >= 19, "{} stale frames", outage.len());
    for w in r.windows(2) {
        let gap = w[1].stamps.renderer_receive_ns - w[0].stamps.renderer_receive_ns;
        assert!(gap <= 2 * P, "a presentation gap of {gap} ns");
    }
    // The first few stale frames are jitter; from ENGINE_DOWN_FRAMES on the frame says "down".
    let first_down = r.iter().position(down).expect("the outage is flagged");
    let first_stale = r.iter().position(stale).unwrap();
    assert_eq!(
        first_down - first_stale,
        report_flags::ENGINE_DOWN_FRAMES as usize - 1
    );
    assert!(r[first_down..]
        .iter()
        .take_while(|x| x.engine_tick == 2)
        .all(down));
    // Back: the resumed ticks are fresh and no longer flagged.
    let back = r.iter().position(|x| x.engine_tick == 3).unwrap();
    assert!(!down(&r[back]) && !stale(&r[back]));
    assert!(!down_seen[back] && down_seen[back - 1]);
}
