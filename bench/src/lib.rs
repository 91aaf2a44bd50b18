//! Benchmarks live in `benches/`: `cargo bench -p lungdyn-bench --bench ipc_hop` (one iceoryx2 hop
//! across two processes) and `--bench engine_tick` (criterion: PV tick, engine step, CPU deform).
