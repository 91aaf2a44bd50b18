//! Kernel identity on the wire: every engine frame names, per lung, the kernel it was computed for;
//! a renderer that loaded another kernel draws that lung at rest — never one lung's displacements on
//! another's vertices — flags the frame and counts it. Driven in process through the renderer's
//! session on in-memory ports and a fake clock, with the deformed vertices read back from the GPU.

use ipc_types::{
    lung_flags, report_flags, EngineFrame, FrameReport, LAYOUT_VERSION, LUNG_LEFT, LUNG_RIGHT,
};
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use lungdyn_tests::prepared_scene;
use renderer::gpu::Gpu;
use renderer::process::{Ports, Session, Snapshots};
use renderer::{LungRenderer, RenderLung};
use transport::memory::{Recorder, Scripted};
use transport::FakeClock;

const P: u64 = 16_666_667;

fn frame(tick: u64, ids: [u64; 2], scale: f32) -> EngineFrame {
    let mut f = EngineFrame {
        layout_version: LAYOUT_VERSION,
        tick,
        ..Default::default()
    };
    for (slot, id) in [LUNG_RIGHT, LUNG_LEFT].into_iter().zip(ids) {
        f.lungs[slot].kernel_id = id;
        f.lungs[slot].flags = lung_flags::ACTIVE;
        f.lungs[slot].deform_scale = scale;
        f.lungs[slot].volume_ml = 1200.0;
    }
    f
}

#[test]
fn a_lung_of_another_kernel_is_drawn_at_rest_and_flagged() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let a = Scene::load(&prepared_scene("kid-a", "[lungs]\nvertices = 1200\n")).unwrap();
    let b = Scene::load(&prepared_scene("kid-b", "[lungs]\nvertices = 1800\n")).unwrap();
    let lungs_a = a.lung_models().unwrap();
    let lungs_b = b.lung_models().unwrap();
    let ids = |l: &[lung_model::deform::LungModel]| [l[0].kernel_id, l[1].kernel_id];
    let (ids_a, ids_b) = (ids(&lungs_a), ids(&lungs_b));
    assert!(ids_a.iter().chain(&ids_b).all(|&i| i != 0));
    assert_ne!(ids_a, ids_b, "two different bakes, two identities");
    assert_eq!(lungs_b[0].side.index(), LUNG_RIGHT);

    // The renderer loads B. The engine sends A's lungs, then B's right lung with A's left lung,
    // then B's lungs.
    let clock = FakeClock::at(0);
    let frames = vec![
        (P, frame(1, ids_a, 40.0)),
        (2 * P, frame(2, [ids_b[0], ids_a[1]], 40.0)),
        (3 * P, frame(3, ids_b, 40.0)),
    ];
    let reports = Recorder::<FrameReport>::new(&clock);
    let ports = Ports {
        engine: Box::new(Scripted::new(&clock, frames, 4)),
        tracker: Box::new(Scripted::new(&clock, vec![], 4)),
        report: Box::new(reports.clone()),
    };
    let render_b: Vec<RenderLung> = lungs_b.iter().map(RenderLung::from_model).collect();
    let r = LungRenderer::new(&gpu, &b.render, &render_b).unwrap();
    let mut session = Session::assemble(
        gpu,
        r,
        &b,
        &render_b,
        ports,
        Box::new(clock.clone()),
        Snapshots::default(),
        "kernel-identity",
    );
    let rest: Vec<[f32; 3]> = lungs_b
        .iter()
        .flat_map(|l| l.mesh.positions.iter().copied())
        .collect();
    let right_len = lungs_b[0].mesh.positions.len();
    let mut drawn = Vec::new();
    while drawn.len() < 3 {
        if session.step(&mut renderer::process::Headless).unwrap() {
            let v = session.renderer.read_deformed(&session.gpu).unwrap();
            drawn.push(v);
        }
    }
    let moved = |v: &[[f32; 4]], range: std::ops::Range<usize>| {
        range
            .map(|i| {
                (0..3)
                    .map(|c| (v[i][c] - rest[i][c]).abs())
                    .fold(0.0f32, f32::max)
            })
            .fold(0.0f32, f32::max)
    };
    let (right, left) = (0..right_len, right_len..rest.len());
    // Frame 1: both lungs foreign: both at rest, exactly.
    assert_eq!(moved(&drawn[0], right.clone()), 0.0);
    assert_eq!(moved(&drawn[0], left.clone()), 0.0);
    // Frame 2: the right lung is ours and moves; the left one stays at rest.
    assert!(moved(&drawn[1], right.clone()) > 1.0);
    assert_eq!(moved(&drawn[1], left.clone()), 0.0);
    // Frame 3: both ours.
    assert!(moved(&drawn[2], left) > 1.0);
    let flags: Vec<bool> = reports
        .values()
        .iter()
        .map(|r| r.flags & report_flags::KERNEL_MISMATCH != 0)
        .collect();
    assert_eq!(flags, vec![true, true, false]);
    assert_eq!(session.stats().kernel_mismatch_frames, 2);
    assert_eq!(session.stats().frames, 3);
}

#[test]
fn a_lung_the_engine_does_not_simulate_is_not_drawn_with_stale_state() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let b = Scene::load(&prepared_scene("kid-c", "[lungs]\nvertices = 1000\n")).unwrap();
    let lungs = b.lung_models().unwrap();
    let clock = FakeClock::at(0);
    // The engine simulates only the right lung (the left slot is empty).
    let mut f = frame(1, [lungs[0].kernel_id, 0], 30.0);
    f.lungs[LUNG_LEFT] = Default::default();
    let reports = Recorder::<FrameReport>::new(&clock);
    let ports = Ports {
        engine: Box::new(Scripted::new(&clock, vec![(P, f)], 4)),
        tracker: Box::new(Scripted::new(&clock, vec![], 4)),
        report: Box::new(reports.clone()),
    };
    let render: Vec<RenderLung> = lungs.iter().map(RenderLung::from_model).collect();
    let r = LungRenderer::new(&gpu, &b.render, &render).unwrap();
    let mut session = Session::assemble(
        gpu,
        r,
        &b,
        &render,
        ports,
        Box::new(clock),
        Snapshots::default(),
        "kernel-identity-2",
    );
    while !session.step(&mut renderer::process::Headless).unwrap() {}
    assert_ne!(reports.values()[0].flags & report_flags::KERNEL_MISMATCH, 0);
}
