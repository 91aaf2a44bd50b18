//! Where a probe's time goes, each way: the harness's probe exchange (a site's prober thread puts
//! a probe; the source's Zenoh callback stamps it and hands it to a worker, which replies; the
//! site's callback stamps the reply) between two processes on this machine, stamped at more points.
//! All stamps are this host's CLOCK_MONOTONIC, so each leg's one-way time is measured directly
//! (the estimator's offset error is half of up − down).
//!
//! `cargo run --release -p lungdyn-remote --example probe_legs -- [PROBES] [INTERVAL_MS] [MODE]`
//! MODE: `worker` (the source replies from its worker, as `Source` does), `callback` (it replies
//! on Zenoh's callback thread), `busy` (as `worker`, with a thread on each side that keeps a core
//! awake), `express` (as `worker`, both puts `express`: not batched by Zenoh's TX pipeline),
//! `warm` (as `worker`, the site first puts a small packet 1 ms before each probe on a key the
//! source takes with an empty callback: the probe then finds both sides' threads awake). Prints the medians and means of each leg's parts, µs.

use std::io::{BufRead, Write};
use std::sync::mpsc::sync_channel;
use std::time::Duration;

use control_state::{decode, encode_to_vec, Packet};
use transport::clock::now_ns;
use zenoh::Wait;

fn session(listen: &[&str], connect: &[&str]) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    let list = |v: &[&str]| {
        format!(
            "[{}]",
            v.iter()
                .map(|e| format!("{e:?}"))
                .collect::<Vec<_>>()
                .join(",")
        )
    };
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    c.insert_json5("listen/endpoints", &list(listen)).unwrap();
    c.insert_json5("connect/endpoints", &list(connect)).unwrap();
    zenoh::open(c).wait().unwrap()
}

fn busy_thread() {
    std::thread::spawn(|| loop {
        std::hint::spin_loop();
    });
}

/// The source: answer probes; print `id t1 t2 t2_after_put` per probe at the end.
fn source(mode: &str, probes: u64) {
    let s = session(&["tcp/127.0.0.1:0"], &[]);
    let loc = lungdyn_remote::harness::locator(&s).unwrap();
    println!("{loc}");
    std::io::stdout().flush().unwrap();
    if mode == "busy" {
        busy_thread();
    }
    let express = mode == "express";
    let (tx, rx) = sync_channel::<(u64, Vec<u8>)>(1024);
    let (rec_tx, rec_rx) = sync_channel::<(u64, u64, u64, u64)>(100_000);
    let reply = move |s: &zenoh::Session, bytes: &[u8], t1: u64| {
        if let Ok(Packet::Probe {
            from, id, t0_ns, ..
        }) = decode(bytes)
        {
            let t2 = now_ns();
            let b = encode_to_vec(&Packet::ProbeReply {
                from: 1,
                to: from,
                id,
                t0_ns,
                t1_ns: t1,
                t2_ns: t2,
            })
            .unwrap();
            s.put("legs/reply", b).express(express).wait().unwrap();
            let _ = rec_tx.try_send((id, t1, t2, now_ns()));
        }
    };
    let _sub = if mode == "callback" {
        let s2 = s.clone();
        s.declare_subscriber("legs/probe")
            .callback(move |x| {
                let t1 = now_ns();
                reply(&s2, &x.payload().to_bytes(), t1)
            })
            .wait()
            .unwrap()
    } else {
        let s2 = s.clone();
        std::thread::spawn(move || {
            while let Ok((t1, b)) = rx.recv() {
                reply(&s2, &b, t1);
            }
        });
        s.declare_subscriber("legs/probe")
            .callback(move |x| {
                let b = x.payload().to_bytes().into_owned();
                let _ = tx.try_send((now_ns(), b));
            })
            .wait()
            .unwrap()
    };
    let _warm = s
        .declare_subscriber("legs/warm")
        .callback(|_| {})
        .wait()
        .unwrap();
    let mut line = String::new();
    std::io::stdin().lock().read_line(&mut line).unwrap();
    let mut out = std::io::stdout().lock();
    for (id, t1, t2, t2p) in rec_rx.try_iter().take(probes as usize) {
        writeln!(out, "{id} {t1} {t2} {t2p}").unwrap();
    }
}

fn stats(name: &str, mut v: Vec<f64>) {
    v.sort_by(f64::total_cmp);
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    println!(
        "{name:>34}: median {:8.1} µs, mean {:8.1} µs, p10 {:8.1}, p90 {:8.1}",
        v[v.len() / 2],
        mean,
        v[v.len() / 10],
        v[v.len() * 9 / 10]
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.get(1).map(String::as_str) == Some("source") {
        return source(&a[2], a[3].parse().unwrap());
    }
    let probes: u64 = a.get(1).map_or(400, |v| v.parse().unwrap());
    let every: u64 = a.get(2).map_or(50, |v| v.parse().unwrap());
    let mode = a.get(3).cloned().unwrap_or_else(|| "worker".into());
    let mut child = std::process::Command::new(&a[0])
        .args(["source", &mode, &probes.to_string()])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut loc = String::new();
    out.read_line(&mut loc).unwrap();
    let s = session(&[], &[loc.trim()]);
    if mode == "busy" {
        busy_thread();
    }
    let (tx, rx) = sync_channel::<(u64, u64)>(100_000);
    let _sub = s
        .declare_subscriber("legs/reply")
        .callback(move |x| {
            let t3 = now_ns();
            if let Ok(Packet::ProbeReply { id, .. }) = decode(&x.payload().to_bytes()) {
                let _ = tx.try_send((id, t3));
            }
        })
        .wait()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1000));
    let mut sent = Vec::new();
    for id in 0..probes {
        if mode == "warm" {
            s.put("legs/warm", vec![0u8]).wait().unwrap();
            std::thread::sleep(Duration::from_millis(1));
        }
        let t0 = now_ns();
        let b = encode_to_vec(&Packet::Probe {
            from: 2,
            to: 0,
            id,
            t0_ns: t0,
        })
        .unwrap();
        s.put("legs/probe", b)
            .express(mode == "express")
            .wait()
            .unwrap();
        sent.push((t0, now_ns()));
        std::thread::sleep(Duration::from_millis(every));
    }
    std::thread::sleep(Duration::from_millis(200));
    writeln!(child.stdin.as_mut().unwrap(), "go").unwrap();
    let got: std::collections::HashMap<u64, u64> = rx.try_iter().collect();
    let (mut put_up, mut wire_up, mut up, mut put_down, mut wire_down, mut down, mut theta) =
        Default::default();
    let f = |v: &mut Vec<f64>, x: i64| v.push(x as f64 / 1e3);
    for l in out.lines() {
        let l = l.unwrap();
        let v: Vec<u64> = l.split(' ').map(|x| x.parse().unwrap()).collect();
        let (id, t1, t2, t2p) = (v[0], v[1], v[2], v[3]);
        let (Some(&(t0, t0p)), Some(&t3)) = (sent.get(id as usize), got.get(&id)) else {
            continue;
        };
        let (t0, t0p, t1, t2, t2p, t3) = (
            t0 as i64, t0p as i64, t1 as i64, t2 as i64, t2p as i64, t3 as i64,
        );
        f(&mut put_up, t0p - t0);
        f(&mut wire_up, t1 - t0p);
        f(&mut up, t1 - t0);
        f(&mut put_down, t2p - t2);
        f(&mut wire_down, t3 - t2p);
        f(&mut down, t3 - t2);
        f(&mut theta, ((t1 - t0) - (t3 - t2)) / 2);
    }
    let _ = child.wait();
    println!(
        "{} probes every {every} ms, source replies from its {mode}",
        up.len()
    );
    stats("up: t0 → put returned", put_up);
    stats("up: put returned → source callback", wire_up);
    stats("up: t1 − t0", up);
    stats("down: t2 → put returned", put_down);
    stats("down: put returned → site callback", wire_down);
    stats("down: t3 − t2", down);
    stats("NTP offset (true 0)", theta);
}
