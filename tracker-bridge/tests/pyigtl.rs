//! Interoperability with pyigtl (`pip install pyigtl`), a real OpenIGTLink peer: a Python sender
//! streams TRANSFORM and POSITION at 60 Hz to the bridge's server, and the bridge, as a client,
//! reads a pyigtl server; every message arrives in order with exactly the values sent. A message
//! with a bad CRC is rejected and counted, and the stream goes on after it.
//!
//! A missing python3 with pyigtl fails the test naming the fix (`./run test` installs it into
//! `target/pyenv`), unless `LUNGDYN_SKIP_PYIGTL=1` opts out: then it is skipped, said aloud and counted.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::record::{Record, RecordReader, RecordWriter};
use tracker_bridge::sample::{Reject, Rotation, Sample};
use tracker_bridge::source::igtl_client::IgtlClient;
use tracker_bridge::source::igtl_server::IgtlServer;
use tracker_bridge::source::{Source, SourceOptions};
use tracker_bridge::testing::run_source;
use transport::Monotonic;

const SCRIPT: &str = r#"
import sys, time, json, math, socket
import numpy as np, pyigtl

def values(k):
    a = math.radians(3.0 * k)
    c, s = math.cos(a), math.sin(a)
    m = np.array([[c, -s, 0, 10.0 + k], [s, c, 0, -20.0 - 0.5 * k],
                  [0, 0, 1, -1000.0 + 0.25 * k], [0, 0, 0, 1]], dtype=np.float32)
    pos = np.array([float(k), 2.0 * k, -900.0 - k], dtype=np.float32)
    h = math.radians(2.0 * k) / 2
    quat = np.array([0.0, math.sin(h), 0.0, math.cos(h)], dtype=np.float32)
    return m, pos, quat

def emit(k, m, pos, quat):
    print(json.dumps({"k": k, "m": [float(v) for v in m[:3, :].flatten()],
                      "pos": [float(v) for v in pos], "quat": [float(v) for v in quat]}), flush=True)

def wait_connected(peer):
    t = time.time()
    while not peer.is_connected():
        if time.time() - t > 20:
            sys.exit("no connection")
        time.sleep(0.01)

def stream(peer, n):
    period, nxt, t0 = 1.0 / 60.0, time.perf_counter(), time.time()
    for k in range(n):
        m, pos, quat = values(k)
        peer.send_message(pyigtl.TransformMessage(m, timestamp=t0 + k * period, device_name="Patient"), wait=True)
        peer.send_message(pyigtl.PositionMessage(pos, quat, timestamp=t0 + k * period, device_name="HMD"), wait=True)
        emit(k, m, pos, quat)
        nxt += period
        time.sleep(max(0.0, nxt - time.perf_counter()))

mode, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
if mode == "sender":
    peer = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    wait_connected(peer)
    stream(peer, n)
    # A message with a bad CRC, then a good one on the same connection.
    raw = socket.create_connection(("127.0.0.1", port))
    bad = bytearray(pyigtl.TransformMessage(values(0)[0], timestamp=1.0, device_name="Patient").pack())
    bad[50] ^= 0xFF
    raw.sendall(bytes(bad))
    after = np.eye(4, dtype=np.float32)
    after[:3, 3] = [1.0, 2.0, -1000.0]
    raw.sendall(pyigtl.TransformMessage(after, timestamp=2.0, device_name="After").pack())
    time.sleep(0.5)
    raw.close()
    peer.stop()
else:
    peer = pyigtl.OpenIGTLinkServer(port=port, local_server=True)
    wait_connected(peer)
    time.sleep(0.1)
    stream(peer, n)
    time.sleep(0.5)
    peer.stop()
print("done", flush=True)
"#;

const N: usize = 60;

/// The python with pyigtl and the peer script written for it, or `None` on an explicit opt-out
/// (`lungdyn_needs`: a missing peer is otherwise a failure naming the fix).
fn python() -> Option<(PathBuf, PathBuf)> {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let py = lungdyn_needs::pyigtl_python(&root)?;
    let path = std::env::temp_dir().join(format!("lungdyn-pyigtl-{}.py", std::process::id()));
    std::fs::write(&path, SCRIPT).unwrap();
    Some((py, path))
}

#[derive(Debug)]
struct Sent {
    m: [f32; 12],
    pos: [f32; 3],
    quat: [f32; 4],
}

fn floats<const K: usize>(v: &serde_json::Value) -> [f32; K] {
    let a = v.as_array().unwrap();
    assert_eq!(a.len(), K);
    std::array::from_fn(|i| a[i].as_f64().unwrap() as f32)
}

/// Run the loop on `source`, recording, until the Python peer has printed `done` and exited.
fn exchange(
    source: &mut dyn Source,
    mut child: Child,
    tag: &str,
) -> (Vec<Sent>, Vec<Sample>, Assembler) {
    let stdout = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
            .collect::<Vec<String>>()
    });
    let path =
        std::env::temp_dir().join(format!("lungdyn-pyigtl-{}-{tag}.ldtr", std::process::id()));
    let _ = std::fs::remove_file(&path);
    let config = BridgeConfig::default();
    let mut recorder = Some(RecordWriter::create(&path, &config, &source.describe()).unwrap());
    let start = Instant::now();
    let mut exited_at: Option<Instant> = None;
    let run = run_source(
        source,
        config,
        &Monotonic,
        &mut recorder,
        &mut || {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "pyigtl exchange took too long"
            );
            if exited_at.is_none() && child.try_wait().unwrap().is_some() {
                exited_at = Some(Instant::now());
            }
            exited_at.is_some_and(|t| t.elapsed() > Duration::from_millis(300))
        },
        "pyigtl test",
    )
    .unwrap();
    recorder.take().unwrap().finish().unwrap();
    let status = child.wait().unwrap();
    let lines = reader.join().unwrap();
    assert!(status.success(), "the Python peer failed: {lines:?}");
    assert_eq!(lines.last().map(String::as_str), Some("done"));
    let sent: Vec<Sent> = lines[..lines.len() - 1]
        .iter()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            Sent {
                m: floats(&v["m"]),
                pos: floats(&v["pos"]),
                quat: floats(&v["quat"]),
            }
        })
        .collect();
    let mut r = RecordReader::open(&path).unwrap();
    let mut got = Vec::new();
    while let Some(rec) = r.next_record().unwrap() {
        if let Record::Sample(s) = rec {
            got.push(s);
        }
    }
    let _ = std::fs::remove_file(&path);
    (sent, got, run.assembler)
}

fn check_exact(sent: &[Sent], got: &[Sample]) {
    assert_eq!(sent.len(), N);
    let patient: Vec<&Sample> = got
        .iter()
        .filter(|s| s.name.as_str() == "Patient")
        .collect();
    let hmd: Vec<&Sample> = got.iter().filter(|s| s.name.as_str() == "HMD").collect();
    assert_eq!(patient.len(), N, "every TRANSFORM arrived once");
    assert_eq!(hmd.len(), N, "every POSITION arrived once");
    for (k, (s, (p, h))) in sent.iter().zip(patient.iter().zip(&hmd)).enumerate() {
        // The matrix in the rows Python built it in: rotation 3x3 and translation column.
        let Rotation::Matrix(r) = p.rotation else {
            panic!("TRANSFORM {k} is not a matrix")
        };
        for row in 0..3 {
            assert_eq!(
                r[row],
                [s.m[4 * row], s.m[4 * row + 1], s.m[4 * row + 2]],
                "TRANSFORM {k} row {row}"
            );
            assert_eq!(p.translation_mm[row], s.m[4 * row + 3], "TRANSFORM {k}");
        }
        assert_eq!(h.translation_mm, s.pos, "POSITION {k}");
        assert_eq!(h.rotation, Rotation::Quat(s.quat), "POSITION {k}");
        assert!(
            p.device_time_ns > 0 && h.device_time_ns > 0,
            "timestamps carried"
        );
    }
    // In order: receive times and device times never go backwards per tool.
    for w in patient.windows(2) {
        assert!(w[0].receive_ns <= w[1].receive_ns && w[0].device_time_ns < w[1].device_time_ns);
    }
}

#[test]
fn a_pyigtl_sender_streams_to_the_bridge_server_exactly_and_a_bad_crc_is_counted() {
    let Some((py, script)) = python() else { return };
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let port = server.local_addr().port();
    let child = Command::new(&py)
        .arg(&script)
        .args(["sender", &port.to_string(), &N.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let (sent, got, asm) = exchange(&mut server, child, "sender");
    check_exact(&sent, &got);
    assert_eq!(
        asm.stats.rejected_for(Reject::Crc),
        1,
        "{}",
        asm.stats.text()
    );
    assert!(
        got.iter().any(|s| s.name.as_str() == "After"),
        "the stream went on after the bad CRC"
    );
    let hmd = asm
        .stats
        .tools
        .iter()
        .find(|t| t.name.as_str() == "HMD")
        .unwrap();
    assert!(
        (40.0..80.0).contains(&hmd.rate_hz()),
        "about 60 Hz: {}",
        hmd.rate_hz()
    );
}

#[test]
fn the_bridge_as_client_of_a_pyigtl_server_receives_every_message_exactly() {
    let Some((py, script)) = python() else { return };
    let port = lungdyn_needs::free_local_port();
    let child = Command::new(&py)
        .arg(&script)
        .args(["server", &port.to_string(), &N.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut client = IgtlClient::start("127.0.0.1".into(), port, &SourceOptions::default());
    let (sent, got, asm) = exchange(&mut client, child, "server");
    check_exact(&sent, &got);
    assert_eq!(asm.stats.rejected_total(), 0, "{}", asm.stats.text());
}
