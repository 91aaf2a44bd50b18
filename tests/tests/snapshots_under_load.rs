//! Snapshots planned at engine ticks (a breath's recording and strip) when the renderer skips
//! engine frames under load: every planned tick still gets a PNG, the next drawn frame standing in
//! for a tick whose own frame was not drawn, named by its planned tick (so the animation keeps the
//! breath's pace) with the tick drawn, and counted. Driven in process through the renderer's
//! session on in-memory ports and a fake clock.

use ipc_types::FrameReport;
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
fn a_planned_tick_the_renderer_skipped_takes_the_next_drawn_frame() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let scene = Scene::load(&prepared_scene("under-load", "[lungs]\nvertices = 1200\n")).unwrap();
    let lungs = scene.lung_models().unwrap();
    let frame = |tick: u64| lungdyn_tests::engine_frame(&lungs, tick, 1200.0 + tick as f32);
    // The engine's ticks as the loaded renderer drew them: 4, 5, 8 and 9 never drawn (a newer
    // frame had replaced them when the renderer came round).
    let drawn = [1u64, 2, 3, 6, 7, 10, 11];
    let clock = FakeClock::at(0);
    let frames = drawn
        .iter()
        .enumerate()
        .map(|(k, &t)| ((k as u64 + 1) * P, frame(t)))
        .collect();
    let reports = Recorder::<FrameReport>::new(&clock);
    let ports = Ports {
        engine: Box::new(Scripted::new(&clock, frames, 4)),
        tracker: Box::new(Scripted::new(&clock, vec![], 4)),
        report: Box::new(reports.clone()),
    };
    let dir = std::env::temp_dir().join(format!("lungdyn-under-load-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let render: Vec<RenderLung> = lungs.iter().map(RenderLung::from_model).collect();
    let r = LungRenderer::new(&gpu, &scene.render, &render).unwrap();
    let planned = vec![2u64, 4, 5, 8, 10];
    let mut session = Session::assemble(
        gpu,
        r,
        &scene,
        &render,
        ports,
        Box::new(clock.clone()),
        Snapshots {
            ticks: planned.clone(),
            dir: dir.clone(),
            ..Default::default()
        },
        "under-load",
    );
    while session.stats().frames < drawn.len() as u64 + 2 {
        session.step(&mut renderer::process::Headless).unwrap();
    }
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    // Every planned tick has its frame: 4 and 5 from tick 6, 8 from tick 10.
    assert_eq!(
        names,
        [
            "lungs_00_tick00002_2404ml.png",
            "lungs_01_tick00004_2412ml_drawn00006.png",
            "lungs_02_tick00005_2412ml_drawn00006.png",
            "lungs_03_tick00008_2420ml_drawn00010.png",
            "lungs_04_tick00010_2420ml.png",
        ]
    );
    assert_eq!(session.stats().snapshots, 5);
    assert_eq!(session.stats().snapshots_substituted, 3);
    // The substitutes are the drawn frame itself.
    let read = |n: &str| std::fs::read(dir.join(n)).unwrap();
    assert_eq!(
        read("lungs_01_tick00004_2412ml_drawn00006.png"),
        read("lungs_02_tick00005_2412ml_drawn00006.png")
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// The same `demo --record` twice into one `--out`: the second run writes the same snapshot names
/// again and must count them as its own (it reported "0 of the breath's frames" and failed, because
/// the names were already there before it started).
#[test]
fn recording_twice_into_one_folder_records_both_times() {
    if Gpu::for_tests().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-record-twice-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // One breath a second, so a 3 s run holds the first second and a whole breath.
    let scene = dir.join("fast.toml");
    std::fs::write(
        &scene,
        "[pv]\nbreaths_per_min = 60.0\n[lungs]\nvertices = 1200\n[render]\nwidth = 160\nheight = 120\n",
    )
    .unwrap();
    let gif = dir.join("breath.gif");
    for run in 1..=2 {
        let (ok, out, err) = lungdyn_tests::lungdyn(&[
            "demo",
            "--scene",
            scene.to_str().unwrap(),
            "--seconds",
            "3",
            "--record",
            gif.to_str().unwrap(),
            "--record-frames",
            "4",
            "--out",
            dir.to_str().unwrap(),
        ]);
        assert!(ok, "run {run}: {out}\n{err}");
        assert!(
            out.contains("recording of one breath"),
            "run {run}: {out}\n{err}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
