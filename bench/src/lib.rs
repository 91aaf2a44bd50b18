//! Benchmarks live in `benches/`: `cargo bench -p lungdyn-bench --bench ipc_hop` (one iceoryx2 hop
//! across two processes), `--bench engine_tick` (criterion: PV tick, engine step, CPU deform),
//! `--bench tracker_sample` (criterion: one tracker message parsed, validated, assembled and
//! published), `--bench tracker_jitter` (the bridge's period jitter with each source), `--bench
//! operator` and `--bench modes_cpu` (one-shot tables of the deformation passes).

/// Median seconds of `f` over `runs` runs, after one warm-up run (the one-shot benches' timer).
pub fn median(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..runs.max(1))
        .map(|_| {
            let s = std::time::Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}
