//! Benchmarks live in `benches/`: `cargo bench -p lungdyn-bench --bench ipc_hop` (one iceoryx2 hop
//! across two processes), `--bench engine_tick` (criterion: PV tick, engine step, CPU deform),
//! `--bench tracker_sample` (criterion: one tracker message parsed, validated, assembled and
//! published) and `--bench tracker_jitter` (the bridge's period jitter with each source).
