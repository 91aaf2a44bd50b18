//! Per-tick and per-frame CPU costs: the PV table read, the whole engine step (PV + the volume
//! cubic solve per lung), and the CPU reference of the deformation at several mesh sizes.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use engine::runtime::{EngineCore, LungGeometry};
use ipc_types::{EngineFrame, TrackerFrame};
use lung_model::deform::{LungModel, MotionConstants};
use lung_model::mesh::{generate, Side};
use lung_model::pv::{preset, Breathing, Timing, DEFAULT_PRESET};
use lung_model::scene::Scene;

fn pv_tick(c: &mut Criterion) {
    let b = Breathing::new(&preset(DEFAULT_PRESET).unwrap(), &Timing::default()).unwrap();
    let mut tick = 0u64;
    c.bench_function("pv volume_at (per tick)", |bench| {
        bench.iter(|| {
            tick = tick.wrapping_add(1);
            std::hint::black_box(b.volume_at(std::hint::black_box(tick)))
        })
    });
    c.bench_function("pv precompute one cycle (per scene change)", |bench| {
        bench.iter(|| Breathing::new(&preset(DEFAULT_PRESET).unwrap(), &Timing::default()).unwrap())
    });
}

fn engine_step(c: &mut Criterion) {
    let lungs = [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            let k = lung_bake::kernel::bake(
                side,
                generate::lung(side, 2000).unwrap(),
                &lung_bake::kernel::BakeSettings::default_for(side),
                &|_| {},
            )
            .unwrap();
            LungGeometry::of(&LungModel::from_unit_displacement(
                side,
                k.mesh,
                k.unit_displacement,
            ))
        })
        .collect();
    let mut core = EngineCore::with_geometry(&Scene::default(), lungs).unwrap();
    let input = TrackerFrame::default();
    let mut out = EngineFrame::default();
    let mut tick = 0u64;
    c.bench_function("engine step (2 lungs, per tick)", |bench| {
        bench.iter(|| {
            tick += 1;
            core.step(tick, Some(&input), &mut out);
            std::hint::black_box(&out);
        })
    });
}

fn cpu_deform(c: &mut Criterion) {
    let mut group = c.benchmark_group("cpu deform p + s*u (reference of the GPU pass)");
    for n in [10_000usize, 100_000, 400_000] {
        let model = LungModel::build(
            Side::Left,
            generate::lung(Side::Left, n).unwrap(),
            &MotionConstants::table_6_1(Side::Left),
        )
        .unwrap();
        let mut out = vec![[0.0f32; 3]; model.mesh.positions.len()];
        group.throughput(Throughput::Elements(model.mesh.positions.len() as u64));
        group.bench_with_input(BenchmarkId::from_parameter(n), &n, |bench, _| {
            bench.iter(|| model.deform_into(std::hint::black_box(123.0), &mut out))
        });
    }
    group.finish();
}

criterion_group!(benches, pv_tick, engine_step, cpu_deform);
criterion_main!(benches);
