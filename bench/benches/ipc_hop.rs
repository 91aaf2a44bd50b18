//! One iceoryx2 hop between two processes: publish → receive, p50/p99/max.
//!
//! The bench re-executes itself as the publisher. The publisher stamps each `TrackerFrame` with
//! CLOCK_MONOTONIC right before `send`, the subscriber with the time it got the sample, in two modes:
//! * `event`: the subscriber sleeps on the iceoryx2 event the publisher signals (the product's path);
//! * `poll`: the subscriber spins on `receive` (the floor of the transport itself).
//!
//! Run: `cargo bench -p lungdyn-bench --bench ipc_hop` (set `HOP_SAMPLES` to change the count).

use std::process::Command;
use std::time::Duration;

use hdrhistogram::Histogram;
use ipc_types::{TrackerFrame, LAYOUT_VERSION};
use transport::clock::{now_ns, sleep_until_ns};
use transport::process::pin_to_core;
use transport::{iox, Instance, Publish, Receive};

const ROLE_ENV: &str = "LUNGDYN_HOP_ROLE";

fn samples() -> u64 {
    std::env::var("HOP_SAMPLES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(20_000)
}

fn publisher(instance: &str, mode: &str) {
    pin_to_core(Some(0), "publisher").ok();
    let services = Instance::new(instance).unwrap();
    let node = iox::node(&services, "hop-pub").unwrap();
    let mut out = services.tracker_outlet(&node).unwrap();
    // Let the subscriber connect before the first sample.
    std::thread::sleep(Duration::from_millis(300));
    // 1 kHz: far below saturation, so each sample sees an idle subscriber (a latency, not a
    // throughput, measurement).
    let period = 1_000_000u64;
    let mut next = now_ns();
    for n in 1..=samples() + 1 {
        next += period;
        sleep_until_ns(next);
        let mut f = TrackerFrame {
            layout_version: LAYOUT_VERSION,
            frame_number: n,
            ..Default::default()
        };
        f.stamps.bridge_publish_ns = now_ns();
        out.publish(&f).unwrap();
    }
    let _ = mode;
    std::thread::sleep(Duration::from_millis(100));
}

fn subscriber(instance: &str, mode: &str) -> Histogram<u64> {
    let services = Instance::new(instance).unwrap();
    let node = iox::node(&services, "hop-sub").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    let exe = std::env::current_exe().unwrap();
    let mut child = Command::new(exe)
        .env(ROLE_ENV, format!("{mode}:{instance}"))
        .spawn()
        .expect("start the publisher process");
    // Publisher on core 0, subscriber on core 1: each hop crosses cores, as between the pinned
    // product processes.
    pin_to_core(Some(1), "subscriber").ok();
    let mut h = Histogram::<u64>::new_with_bounds(1, 10_000_000_000, 3).unwrap();
    let total = samples();
    let deadline = now_ns() + 120_000_000_000;
    while h.len() < total && now_ns() < deadline {
        if mode == "event" {
            inlet.wait_until(now_ns() + 100_000_000).unwrap();
        }
        inlet
            .drain(&mut |f: &TrackerFrame| {
                let got = now_ns();
                if f.frame_number > 1 {
                    let _ = h.record((got - f.stamps.bridge_publish_ns).max(1));
                }
            })
            .unwrap();
    }
    child.wait().unwrap();
    drop(inlet);
    drop(node);
    services.remove_leftovers();
    h
}

fn main() {
    if let Ok(role) = std::env::var(ROLE_ENV) {
        let (mode, instance) = role.split_once(':').unwrap();
        publisher(instance, mode);
        return;
    }
    if std::env::args().any(|a| a == "--list") {
        return; // cargo test --benches asks benches to list themselves
    }
    println!("one iceoryx2 hop across two processes pinned to cores 0 and 1 (publish -> receive), {} samples at 1 kHz", samples());
    println!(
        "{:<8} {:>10} {:>10} {:>10} {:>10}",
        "mode", "p50 us", "p99 us", "p99.9 us", "max us"
    );
    for mode in ["event", "poll"] {
        let instance = format!("hop-{mode}-{}", std::process::id());
        let h = subscriber(&instance, mode);
        let us = |q: f64| h.value_at_quantile(q) as f64 / 1e3;
        println!(
            "{:<8} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
            mode,
            us(0.5),
            us(0.99),
            us(0.999),
            h.max() as f64 / 1e3
        );
    }
}
