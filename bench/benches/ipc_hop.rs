//! One iceoryx2 hop between two processes, for each wake strategy, pinned and unpinned: latency
//! (publish → the receiver holding the sample) p50/p99/p99.9/max from HdrHistogram, and the
//! receiver's CPU cost (CPU-seconds of its thread per wall-second, CLOCK_THREAD_CPUTIME_ID).
//!
//! The bench re-executes itself as the publisher. The publisher stamps each `TrackerFrame` with
//! CLOCK_MONOTONIC right before `publish` on an absolute schedule (as the tracker-bridge does); the
//! receiver waits on the product's [`transport::iox::Inlet`] by each [`Wake`] strategy, as the
//! engine's pacer does (`wait_until` a deadline two periods on, then `drain`), and stamps each
//! sample when `drain` hands it over:
//! * `event`: sleeps on the iceoryx2 event the publisher signals;
//! * `spin-then-park`: parks until the next sample is due, spins `HOP_SPIN_US` around it;
//! * `busy-poll`: spins on the subscriber (the floor of the transport itself).
//!
//! "pinned": publisher on core 0, receiver on core 1 (each hop crosses cores, as between the
//! pinned product processes); "unpinned": wherever the scheduler puts them.
//!
//! Run: `cargo bench -p lungdyn-bench --bench ipc_hop`. Environment: `HOP_HZ` (publish rate, default
//! 1000), `HOP_SAMPLES` (per row, default 5000), `HOP_SPIN_US` (default 200), `HOP_MODES` (e.g.
//! `event,busy-poll`), `HOP_PINNING` (`pinned`, `unpinned` or both, default both), `HOP_OUT` (also
//! write the table as markdown to this file, e.g. `docs/latency/ipc_hop.md`).

use std::fmt::Write as _;
use std::process::Command;
use std::time::Duration;

use hdrhistogram::Histogram;
use ipc_types::{TrackerFrame, LAYOUT_VERSION};
use transport::clock::{now_ns, sleep_until_ns};
use transport::process::pin_to_core;
use transport::wake::Wake;
use transport::{iox, Instance, Publish, Receive};

const ROLE_ENV: &str = "LUNGDYN_HOP_ROLE";
/// Samples at the start of each row left out (spin-then-park learns the period from them).
const WARMUP: u64 = 20;

fn env<T: std::str::FromStr>(name: &str, default: T) -> T {
    match std::env::var(name) {
        Ok(s) => s
            .parse()
            .unwrap_or_else(|_| panic!("{name}={s:?} is not a valid value")),
        Err(_) => default,
    }
}

fn period_ns() -> u64 {
    let hz: f64 = env("HOP_HZ", 1000.0);
    assert!(
        hz.is_finite() && (1.0..=100_000.0).contains(&hz),
        "HOP_HZ={hz}: give 1..100000"
    );
    (1e9 / hz).round() as u64
}

fn samples() -> u64 {
    env("HOP_SAMPLES", 5000u64).max(1)
}

fn publisher(instance: &str, pinned: bool) {
    if pinned {
        pin_to_core(Some(0), "publisher").expect("pin the publisher to core 0");
    }
    let services = Instance::new(instance).unwrap();
    let node = iox::node(&services, "hop-pub").unwrap();
    let mut out = services.tracker_outlet(&node).unwrap();
    // Let the subscriber connect before the first sample.
    while out.subscribers() == 0 {
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(100));
    // Far below saturation (1 kHz by default), so each sample meets a waiting receiver: a latency,
    // not a throughput, measurement.
    let period = period_ns();
    let mut next = now_ns();
    for n in 1..=samples() + WARMUP {
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
    std::thread::sleep(Duration::from_millis(100));
}

/// One row: the latency histogram, the receiver's CPU-seconds per wall-second, samples lost.
struct Row {
    h: Histogram<u64>,
    cpu_per_s: f64,
    lost: u64,
}

fn receiver(instance: &str, wake: Wake, pinned: bool) -> Row {
    let services = Instance::new(instance).unwrap();
    let node = iox::node(&services, "hop-sub").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    inlet.set_wake(wake);
    let exe = std::env::current_exe().unwrap();
    let mut child = Command::new(exe)
        .env(
            ROLE_ENV,
            format!("{}:{instance}", if pinned { "pinned" } else { "free" }),
        )
        .spawn()
        .expect("start the publisher process");
    if pinned {
        pin_to_core(Some(1), "receiver").expect("pin the receiver to core 1");
    }
    let mut h = Histogram::<u64>::new_with_bounds(1, 10_000_000_000, 3).unwrap();
    let total = samples() + WARMUP;
    let period = period_ns();
    let give_up = now_ns() + 120_000_000_000 + total * period * 2;
    let (mut last, mut received) = (0u64, 0u64);
    let (mut cpu0, mut wall0) = (0.0, 0u64);
    while last < total && now_ns() < give_up {
        inlet.wait_until(now_ns() + 2 * period).unwrap();
        inlet
            .drain(&mut |f: &TrackerFrame| {
                let got = now_ns();
                last = f.frame_number;
                if f.frame_number >= WARMUP && wall0 == 0 {
                    cpu0 = thread_cpu_s();
                    wall0 = got;
                }
                if f.frame_number > WARMUP {
                    received += 1;
                    let _ = h.record((got - f.stamps.bridge_publish_ns).max(1));
                }
            })
            .unwrap();
    }
    let wall = (now_ns() - wall0) as f64 / 1e9;
    let cpu_per_s = (thread_cpu_s() - cpu0) / wall;
    child.wait().unwrap();
    drop(inlet);
    drop(node);
    services.remove_leftovers();
    Row {
        h,
        cpu_per_s,
        lost: samples() - received.min(samples()),
    }
}

/// How late `wait_until` returns when nothing arrives (the engine's deadline tick while the
/// tracker is silent): `DEADLINE_WAITS` waits for a deadline `DEADLINE_US` away, each overshoot
/// (return time − deadline, ns; 1 when on time or early) recorded.
fn overshoot(instance: &str, wake: Wake) -> Histogram<u64> {
    let services = Instance::new(instance).unwrap();
    let node = iox::node(&services, "hop-idle").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    inlet.set_wake(wake);
    let mut h = Histogram::<u64>::new_with_bounds(1, 10_000_000_000, 3).unwrap();
    let away = env("HOP_DEADLINE_US", 2_000u64) * 1_000;
    for _ in 0..env("HOP_DEADLINE_WAITS", 300u64) {
        let deadline = now_ns() + away;
        inlet.wait_until(deadline).unwrap();
        let _ = h.record(now_ns().saturating_sub(deadline).max(1));
    }
    drop(inlet);
    drop(node);
    services.remove_leftovers();
    h
}

/// The calling thread's allowed cores, to give back after a pinned row (the next row's publisher
/// inherits them, and an unpinned row must not stay on core 1).
fn affinity() -> libc::cpu_set_t {
    // SAFETY: sched_getaffinity fills the zeroed set of the size we pass.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set);
        set
    }
}

fn set_affinity(set: &libc::cpu_set_t) {
    // SAFETY: sched_setaffinity reads the set we pass; the calling thread only.
    let rc = unsafe { libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), set) };
    assert_eq!(rc, 0, "cannot restore the receiver's cores");
}

/// The calling thread's CPU time, seconds (CLOCK_THREAD_CPUTIME_ID: the scheduler's own runtime
/// in ns; getrusage's tick-sampled times miss a spin that is phase-locked to the publisher).
fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) } != 0 {
        return f64::NAN;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 / 1e9
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "?".into())
}

fn main() {
    if let Ok(role) = std::env::var(ROLE_ENV) {
        let (pinning, instance) = role.split_once(':').unwrap();
        publisher(instance, pinning == "pinned");
        return;
    }
    if std::env::args().any(|a| a == "--list") {
        return; // cargo test --benches asks benches to list themselves
    }
    let spin_us: u64 = env("HOP_SPIN_US", 200);
    let all = [
        Wake::Event,
        Wake::SpinThenPark {
            spin_ns: spin_us * 1000,
        },
        Wake::BusyPoll,
    ];
    let modes: Vec<Wake> = match std::env::var("HOP_MODES") {
        Ok(list) => list
            .split(',')
            .map(|m| {
                *all.iter()
                    .find(|w| w.mode().name() == m.trim())
                    .unwrap_or_else(|| {
                        panic!("HOP_MODES: {m:?} is not event, spin-then-park or busy-poll")
                    })
            })
            .collect(),
        Err(_) => all.to_vec(),
    };
    let pinnings: Vec<bool> = match std::env::var("HOP_PINNING").as_deref() {
        Ok("pinned") => vec![true],
        Ok("unpinned") => vec![false],
        _ => vec![true, false],
    };
    let cores = transport::wake::machine_cores();
    let isolated = transport::process::isolated_cores();
    let hz = 1e9 / period_ns() as f64;
    let load_before = loadavg();
    let head = format!(
        "one iceoryx2 hop across two processes (publish -> the receiver holds the sample), {} \
         samples per row at {hz:.0} Hz; {} ({cores} cores, isolated: {}); load average before: {load_before}",
        samples(),
        cpu_model(),
        if isolated.is_empty() {
            "none".to_string()
        } else {
            format!("{isolated:?}")
        }
    );
    println!("{head}");
    let mut md = String::new();
    let cols =
        "| strategy | cores | p50 µs | p99 µs | p99.9 µs | max µs | receiver CPU s/s | lost |";
    let _ = writeln!(md, "{cols}\n|---|---|---:|---:|---:|---:|---:|---:|");
    println!(
        "{:<30} {:<9} {:>9} {:>9} {:>9} {:>9} {:>9} {:>5}",
        "strategy", "cores", "p50 us", "p99 us", "p99.9 us", "max us", "CPU s/s", "lost"
    );
    let free = affinity();
    for &pinned in &pinnings {
        for &wake in &modes {
            set_affinity(&free);
            let instance = format!(
                "hop-{}-{}-{}",
                wake.mode().name(),
                if pinned { "p" } else { "u" },
                std::process::id()
            );
            let r = receiver(&instance, wake, pinned);
            let us = |q: f64| r.h.value_at_quantile(q) as f64 / 1e3;
            let cores = if pinned { "0 -> 1" } else { "unpinned" };
            println!(
                "{:<30} {:<9} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.3} {:>5}",
                wake.to_string(),
                cores,
                us(0.5),
                us(0.99),
                us(0.999),
                r.h.max() as f64 / 1e3,
                r.cpu_per_s,
                r.lost
            );
            let _ = writeln!(
                md,
                "| {wake} | {cores} | {:.1} | {:.1} | {:.1} | {:.1} | {:.3} | {} |",
                us(0.5),
                us(0.99),
                us(0.999),
                r.h.max() as f64 / 1e3,
                r.cpu_per_s,
                r.lost
            );
        }
    }
    // Deadlines with nothing arriving: how late each strategy wakes (unpinned).
    set_affinity(&free);
    let away_us: u64 = env("HOP_DEADLINE_US", 2_000);
    let _ = writeln!(
        md,
        "\nA deadline {away_us} µs away with nothing arriving (the engine's deadline tick while the \
         tracker is silent), unpinned: how late `wait_until` returns.\n\n\
         | strategy | p50 µs late | p99 µs late | max µs late |\n|---|---:|---:|---:|"
    );
    println!("deadline {away_us} us away, nothing arriving: how late wait_until returns");
    for &wake in &modes {
        let instance = format!("hop-idle-{}-{}", wake.mode().name(), std::process::id());
        let h = overshoot(&instance, wake);
        let us = |q: f64| h.value_at_quantile(q) as f64 / 1e3;
        println!(
            "{:<30} late p50 {:>9.1} us  p99 {:>9.1} us  max {:>9.1} us",
            wake.to_string(),
            us(0.5),
            us(0.99),
            h.max() as f64 / 1e3
        );
        let _ = writeln!(
            md,
            "| {wake} | {:.1} | {:.1} | {:.1} |",
            us(0.5),
            us(0.99),
            h.max() as f64 / 1e3
        );
    }
    let load_after = loadavg();
    println!("load average after: {load_after}");
    if let Ok(path) = std::env::var("HOP_OUT") {
        let text = format!(
            "<!-- written by `cargo bench -p lungdyn-bench --bench ipc_hop` (bench/benches/ipc_hop.rs) -->\n\
             {head}; after: {load_after}.\n\n{md}"
        );
        std::fs::write(&path, text).unwrap_or_else(|e| panic!("HOP_OUT={path}: {e}"));
        println!("written: {path}");
    }
}
