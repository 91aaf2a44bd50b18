//! One frame of `lungdyn demo --igtl-serve` (issue 38; docs/SLICER.md): both lungs of the built-in
//! default scene (2 × ~10k vertices, basis mode) deformed by the CPU reference, reflected to RAS,
//! encoded as POLYDATA with their lobe codes and the BreathState STRING, every body CRC'd — the whole
//! of what the link does per sent frame, against the goal of ≤ 2 ms CPU. It runs as the link runs
//! it, in a pool of one thread (so wall time here is CPU time). Then the tumour scene's frame (its
//! ellipsoid and TRANSFORM added), and the CRC-64 alone over 1 MB.
//!
//! `cargo bench -p lungdyn-bench --bench slicer_frame` (bakes the default lungs once into
//! target/bench-slicer-kernels).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use lungdyn_launcher::slicer::FrameMaker;

fn kernels() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/bench-slicer-kernels")
}

/// The prepared scene and its engine frame at `tick` (a still supine patient).
fn frame_of(scene: Scene, tick: u64) -> (Scene, ipc_types::EngineFrame) {
    let scene = lungdyn_launcher::prepare::prepare(scene, &kernels())
        .expect("bake the bench's lungs")
        .scene;
    let mut frame = None;
    engine::headless::run_while(
        engine::runtime::EngineCore::new(&scene).expect("the scene's engine"),
        tick + 1,
        &mut lungdyn_launcher::scene_check::still_patient(&scene),
        &mut |_, f| {
            frame = Some(*f);
            true
        },
    )
    .expect("run the engine");
    (scene, frame.expect("a frame"))
}

fn slicer_frame(c: &mut Criterion) {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a pool of one thread");
    let (scene, f) = frame_of(Scene::default(), 150);
    let mut maker = FrameMaker::new(&scene).expect("the default lungs");
    maker.make(&f).expect("a frame");
    let mut g = c.benchmark_group("slicer frame");
    g.throughput(Throughput::Bytes(maker.bytes.len() as u64));
    eprintln!(
        "slicer frame: {} bytes for 2 lungs of {} vertices",
        maker.bytes.len(),
        scene.lungs.vertices
    );
    g.bench_function(
        "default lungs (deform, RAS, POLYDATA ×2, STRING, CRC)",
        |b| b.iter(|| one.install(|| maker.make(std::hint::black_box(&f)).expect("a frame"))),
    );
    let tumour = Scene::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/tumour_right_lower.toml"),
    )
    .expect("the tumour scene");
    let (scene, f) = frame_of(tumour, 150);
    let mut maker = FrameMaker::new(&scene).expect("the tumour scene's lungs");
    maker.make(&f).expect("a frame");
    g.bench_function("tumour scene (+ ellipsoid, TRANSFORM)", |b| {
        b.iter(|| one.install(|| maker.make(std::hint::black_box(&f)).expect("a frame")))
    });
    let mb = vec![0x5au8; 1 << 20];
    g.throughput(Throughput::Bytes(mb.len() as u64));
    g.bench_function("CRC-64 of 1 MiB", |b| {
        b.iter(|| tracker_bridge::igtl::crc64(std::hint::black_box(&mb)))
    });
    g.finish();
}

criterion_group!(benches, slicer_frame);
criterion_main!(benches);
