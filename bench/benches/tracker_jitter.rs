//! The bridge's period jitter against its 60 Hz schedule with each source: the shared loop runs in
//! real time for a while per source and publishes on iceoryx2, while a peer feeds the source at its
//! own 60 Hz (an OpenIGTLink sender or server thread, the simulated NDI tracker over TCP and on a
//! pty, a recording). Reported per source: how late each tick woke after its schedule slot
//! (p50/p99/max) and how far each publish-to-publish interval was from 16.667 ms (p99, max); and
//! for the device sources, capture -> bridge publish of every new sample (its receive time, taken
//! by the reader thread as the bytes arrive, to the publish: the bridge's own work, p50/p99/max)
//! and, for the OpenIGTLink senders, sender write -> bridge publish (loopback delivery included).
//!
//! Run: `cargo bench -p lungdyn-bench --bench tracker_jitter` (`TRACKER_JITTER_SECONDS`, default 10
//! per source).

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use hdrhistogram::Histogram;
use ipc_types::{TrackerFrame, MAX_TOOLS};
use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::igtl::{Body, Message, QtDataElement, Timestamp};
use tracker_bridge::ndi_sim::{SimDevice, SimTool};
use tracker_bridge::run::run_loop;
use tracker_bridge::sample::ToolName;
use tracker_bridge::source::igtl_client::IgtlClient;
use tracker_bridge::source::igtl_server::IgtlServer;
use tracker_bridge::source::ndi_link::NdiSource;
use tracker_bridge::source::replay::Replay;
use tracker_bridge::source::synthetic::SyntheticSource;
use tracker_bridge::source::{Source, SourceOptions};
use transport::{iox, now_ns, Instance, PortError, Publish};

const PERIOD: u64 = 16_666_667;

/// When the OpenIGTLink sender wrote message `k` (ns), for sender write -> publish.
type Written = Arc<Mutex<Vec<u64>>>;

struct Timed<P> {
    inner: P,
    last: Option<u64>,
    interval_error: Histogram<u64>,
    last_capture: u64,
    capture_to_publish: Histogram<u64>,
    written: Option<Written>,
    write_to_publish: Histogram<u64>,
}

impl<P: Publish<TrackerFrame>> Publish<TrackerFrame> for Timed<P> {
    fn publish(&mut self, f: &TrackerFrame) -> Result<(), PortError> {
        self.inner.publish(f)?;
        let t = f.stamps.bridge_publish_ns;
        if let Some(l) = self.last {
            let _ = self.interval_error.record((t - l).abs_diff(PERIOD).max(1));
        }
        self.last = Some(t);
        // A new sample (not a frame repeating the last one while the device is silent).
        if f.stamps.capture_ns != self.last_capture {
            self.last_capture = f.stamps.capture_ns;
            let _ = self
                .capture_to_publish
                .record(t.saturating_sub(f.stamps.capture_ns).max(1));
            if let Some(w) = &self.written {
                // The sender put k/100 in the patient's x.
                let k = (f.tools[0].pose.translation_mm[0] * 100.0).round() as usize;
                if let Some(&at) = w.lock().unwrap().get(k) {
                    let _ = self.write_to_publish.record(t.saturating_sub(at).max(1));
                }
            }
        }
        Ok(())
    }
}

fn qtdata(k: u32) -> Vec<u8> {
    let e = |name: &str, z: f32| QtDataElement {
        name: name.into(),
        instrument_type: 2,
        position_mm: [k as f32 * 0.01, 2.0, z],
        quaternion: [0.0, 0.0, 0.0, 1.0],
    };
    Message::new(
        "Tracker",
        // One device timestamp per message, a period apart (a repeated one is not a new sample).
        Timestamp::from_unix_ns(1_700_000_000_000_000_000 + u64::from(k) * PERIOD),
        Body::QtData(vec![e("Patient", -1000.0), e("HMD", -900.0)]),
    )
    .encode()
    .unwrap()
}

/// Write a 60 Hz OpenIGTLink stream to `s` until `stop`, logging when each message was written.
fn stream(mut s: TcpStream, stop: &AtomicBool, written: &Written) {
    let mut next = now_ns();
    let mut k = 0;
    while !stop.load(Ordering::Relaxed) {
        next += PERIOD;
        transport::clock::sleep_until_ns(next);
        k += 1;
        let m = qtdata(k);
        {
            // Logged before the write: the bridge may publish before write_all returns.
            let mut w = written.lock().unwrap();
            w.resize(k as usize, 0);
            w.push(now_ns());
        }
        if s.write_all(&m).is_err() {
            return;
        }
    }
}

fn serve_ndi(l: TcpListener, stop: Arc<AtomicBool>) {
    let dev = Arc::new(Mutex::new(SimDevice::new(vec![
        SimTool::at(0x0A, [10.0, -20.0, -1000.0]),
        SimTool::at(0x0B, [0.0, 30.0, -900.0]),
    ])));
    l.set_nonblocking(true).unwrap();
    while !stop.load(Ordering::Relaxed) {
        let Ok((mut s, _)) = l.accept() else {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        };
        s.set_nonblocking(false).unwrap();
        s.set_nodelay(true).unwrap();
        s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
        let mut buf = [0u8; 4096];
        while !stop.load(Ordering::Relaxed) {
            match s.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => {
                    let r = dev.lock().unwrap().receive(&buf[..n]);
                    if s.write_all(&r).is_err() {
                        break;
                    }
                }
                Err(_) => {}
            }
        }
    }
}

fn measure(
    name: &str,
    source: &mut dyn Source,
    config: BridgeConfig,
    seconds: f64,
    instance: &Instance,
    node: &iox::IoxNode,
    written: Option<Written>,
) {
    let outlet = instance.tracker_outlet(node).unwrap();
    let histogram = || Histogram::new_with_bounds(1, 10_000_000_000, 3).unwrap();
    let mut timed = Timed {
        inner: outlet,
        last: None,
        interval_error: histogram(),
        last_capture: 0,
        capture_to_publish: histogram(),
        written,
        write_to_publish: histogram(),
    };
    let mut asm = Assembler::new(config);
    let stop_at = now_ns() + (seconds * 1e9) as u64;
    run_loop(
        source,
        &mut asm,
        &mut timed,
        &mut None,
        &transport::Monotonic,
        &mut |now| now >= stop_at,
        &mut |_, _| {},
        &mut || 0,
    )
    .unwrap();
    let s = &asm.stats;
    let us = |h: &Histogram<u64>, q: f64| h.value_at_quantile(q) as f64 / 1000.0;
    let valid = s.accepted;
    println!(
        "{name:<24} {:>6} frames {:>7} samples ({:>5} rejected)  wake late p50 {:>7.1} us p99 {:>8.1} us max {:>8.1} us | interval error p99 {:>8.1} us max {:>8.1} us",
        s.frames,
        valid,
        s.rejected_total(),
        us(&s.jitter, 0.5),
        us(&s.jitter, 0.99),
        s.jitter.max() as f64 / 1000.0,
        us(&timed.interval_error, 0.99),
        timed.interval_error.max() as f64 / 1000.0,
    );
    let row = |what: &str, h: &Histogram<u64>| {
        if !h.is_empty() {
            println!(
                "{:<24} {what}: {} samples, p50 {:>7.1} us p99 {:>7.1} us max {:>8.1} us",
                "",
                h.len(),
                us(h, 0.5),
                us(h, 0.99),
                h.max() as f64 / 1000.0
            );
        }
    };
    if source_is_device(name) {
        row("capture -> bridge publish", &timed.capture_to_publish);
        row("sender write -> bridge publish", &timed.write_to_publish);
    }
}

fn source_is_device(name: &str) -> bool {
    name.starts_with("igtl") || name.starts_with("ndi")
}

fn main() {
    let seconds: f64 = std::env::var("TRACKER_JITTER_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10.0);
    let instance = Instance::new(&format!("bench-jitter-{}", std::process::id())).unwrap();
    let node = iox::node(&instance, "bench").unwrap();
    let config = BridgeConfig::default();
    let mut ndi_config = BridgeConfig::default();
    let mut slots = [None; MAX_TOOLS];
    slots[0] = ToolName::new("0A").ok();
    slots[1] = ToolName::new("0B").ok();
    ndi_config.slots = slots;
    println!("bridge period jitter against the 60 Hz schedule, {seconds} s per source, publishing on iceoryx2");

    let mut synthetic = SyntheticSource::new(Default::default());
    let mut synthetic_config = config.clone();
    synthetic_config.validation.volume = tracker_bridge::validate::Volume::Unbounded;
    measure(
        "synthetic",
        &mut synthetic,
        synthetic_config.clone(),
        seconds,
        &instance,
        &node,
        None,
    );

    let stop = Arc::new(AtomicBool::new(false));
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let written = Written::default();
    let sender = {
        let (stop, written) = (stop.clone(), written.clone());
        std::thread::spawn(move || stream(TcpStream::connect(addr).unwrap(), &stop, &written))
    };
    measure(
        "igtl-server (60 Hz)",
        &mut server,
        config.clone(),
        seconds,
        &instance,
        &node,
        Some(written),
    );
    stop.store(true, Ordering::Relaxed);
    sender.join().unwrap();
    drop(server);

    let stop = Arc::new(AtomicBool::new(false));
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    let written = Written::default();
    let peer = {
        let (stop, written) = (stop.clone(), written.clone());
        std::thread::spawn(move || {
            let (s, _) = l.accept().unwrap();
            stream(s, &stop, &written)
        })
    };
    let mut client = IgtlClient::start("127.0.0.1".into(), port, &SourceOptions::default());
    measure(
        "igtl-client (60 Hz)",
        &mut client,
        config.clone(),
        seconds,
        &instance,
        &node,
        Some(written),
    );
    stop.store(true, Ordering::Relaxed);
    peer.join().unwrap();
    drop(client);

    let stop = Arc::new(AtomicBool::new(false));
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    let sim = {
        let stop = stop.clone();
        std::thread::spawn(move || serve_ndi(l, stop))
    };
    let mut ndi = NdiSource::tcp("127.0.0.1", port, &SourceOptions::default()).unwrap();
    measure(
        "ndi-tcp (simulated)",
        &mut ndi,
        ndi_config.clone(),
        seconds,
        &instance,
        &node,
        None,
    );
    drop(ndi);
    stop.store(true, Ordering::Relaxed);
    sim.join().unwrap();

    let path = std::env::temp_dir().join(format!("lungdyn-jitter-{}.ldtr", std::process::id()));
    let _ = std::fs::remove_file(&path);
    tracker_bridge::head_motion::write(
        &path,
        &tracker_bridge::head_motion::HeadMotion {
            seconds: seconds + 1.0,
            ..Default::default()
        },
    )
    .unwrap();
    let mut replay = Replay::open(&path, true).unwrap();
    let rc = replay.recorded_config().cloned().unwrap();
    measure(
        "replay (paced)",
        &mut replay,
        rc,
        seconds,
        &instance,
        &node,
        None,
    );
    let _ = std::fs::remove_file(&path);
    drop(node);
    instance.remove_leftovers();
}
