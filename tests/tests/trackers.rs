//! Trackers end to end: a recorded session replays into the same tracker frames and so the same
//! engine frames bit for bit (in process, and through `lungdyn tracker listen` as processes); the
//! bridge process publishes what an OpenIGTLink sender sends; `lungdyn demo --tracker` drives the
//! engine and renderer from a device source; `lungdyn register`, `tracker simulate`, `tracker
//! predict` and `hmd check` do what docs/TRACKERS.md says, and refuse bad input with one clear message.

use std::io::Write;
use std::net::TcpStream;
use std::time::Duration;

use engine::runtime::{EngineCore, LungGeometry};
use ipc_types::{EngineFrame, TrackerFrame, TOOL_HMD, TOOL_PATIENT};
use lung_model::deform::LungModel;
use lung_model::scene::SceneExt;
use lungdyn_tests::{assert_clean_failure, bin, lungdyn, unique_instance};
use tracker_bridge::assemble::Assembler;
use tracker_bridge::igtl::{Body, Message, QtDataElement, Timestamp};
use tracker_bridge::record::RecordWriter;
use tracker_bridge::run::run_loop;
use tracker_bridge::source::replay::Replay;
use tracker_bridge::source::synthetic::SyntheticSource;
use tracker_bridge::source::Source;
use transport::memory::Recorder;
use transport::{iox, FakeClock, Instance, Receive};

fn tmp(name: &str) -> std::path::PathBuf {
    let p = std::env::temp_dir().join(format!("lungdyn-trackers-{}-{name}", std::process::id()));
    let _ = std::fs::remove_file(&p);
    p
}

fn frames_of(
    source: &mut dyn Source,
    clock: &FakeClock,
    ticks: u64,
    record: Option<&std::path::Path>,
) -> Vec<TrackerFrame> {
    let config = source.recorded_config().cloned().unwrap_or_else(|| {
        let mut c = tracker_bridge::assemble::BridgeConfig::default();
        c.validation.volume = tracker_bridge::validate::Volume::Unbounded;
        c
    });
    let mut recorder =
        record.map(|p| RecordWriter::create(p, &config, &source.describe()).unwrap());
    let mut asm = Assembler::new(config);
    let mut out = Recorder::new(clock);
    let mut n = 0;
    run_loop(
        source,
        &mut asm,
        &mut out,
        &mut recorder,
        clock,
        &mut |_| {
            n += 1;
            n > ticks
        },
        &mut |_, _| {},
        &mut || 0,
    )
    .unwrap();
    if let Some(r) = recorder {
        r.finish().unwrap();
    }
    out.values()
}

/// The engine over a tracker stream, with the hop stamps (this run's times) cleared.
fn engine_frames(frames: &[TrackerFrame]) -> Vec<EngineFrame> {
    let scene = lung_model::scene::Scene::default();
    let geometry: Vec<LungGeometry> = [lung_model::mesh::Side::Right, lung_model::mesh::Side::Left]
        .into_iter()
        .map(|side| {
            let k = lung_bake::kernel::bake(
                side,
                lung_model::mesh::generate::lung(side, 800).unwrap(),
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
    let mut core = EngineCore::with_geometry(&scene, geometry).unwrap();
    frames
        .iter()
        .enumerate()
        .map(|(tick, f)| {
            let input = TrackerFrame {
                stamps: Default::default(),
                ..*f
            };
            let mut out = EngineFrame::default();
            core.step(tick as u64, Some(&input), &mut out);
            out
        })
        .collect()
}

#[test]
fn a_recorded_session_replays_into_the_same_tracker_and_engine_frames() {
    let path = tmp("engine.ldtr");
    let live = frames_of(
        &mut SyntheticSource::new(Default::default()),
        &FakeClock::at(3_000_000_000),
        300,
        Some(&path),
    );
    let mut replay = Replay::open(&path, false).unwrap();
    let again = frames_of(&mut replay, &FakeClock::at(90_000_000_000), u64::MAX, None);
    assert_eq!(live.len(), again.len());
    for (a, b) in live.iter().zip(&again) {
        let (a, b) = (
            TrackerFrame {
                stamps: Default::default(),
                ..*a
            },
            TrackerFrame {
                stamps: Default::default(),
                ..*b
            },
        );
        assert_eq!(
            bytemuck::bytes_of(&a),
            bytemuck::bytes_of(&b),
            "tracker frame {}",
            a.frame_number
        );
    }
    let (x, y) = (engine_frames(&live), engine_frames(&again));
    for (a, b) in x.iter().zip(&y) {
        assert_eq!(
            bytemuck::bytes_of(a),
            bytemuck::bytes_of(b),
            "engine tick {}",
            a.tick
        );
    }
    // The engine used every sample's patient pose (none was held).
    assert!(x
        .iter()
        .all(|f| f.state & ipc_types::engine_state::PATIENT_POSE_HELD == 0));
    let _ = std::fs::remove_file(&path);
}

#[test]
fn listen_records_and_a_replay_through_the_command_gives_the_same_frames_digest() {
    let path = tmp("listen.ldtr");
    let p = path.to_str().unwrap();
    let (ok, out, err) = lungdyn(&[
        "tracker",
        "listen",
        "--source",
        "synthetic",
        "--seconds",
        "1",
        "--record",
        p,
        "--json",
    ]);
    assert!(ok, "{err}");
    let live: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert!(live["frames"].as_u64().unwrap() >= 50, "{live}");
    assert_eq!(live["rejected_total"], 0);
    let tools = live["tools"].as_array().unwrap();
    assert_eq!(tools.len(), 2);
    for t in tools {
        assert!(t["frames"].as_u64().unwrap() >= 50);
        assert_eq!(t["last_pose"]["position_mm"].as_array().unwrap().len(), 3);
        assert_eq!(
            t["last_pose"]["quaternion_xyzw"].as_array().unwrap().len(),
            4
        );
        assert!((t["rate_hz"].as_f64().unwrap() - 60.0).abs() < 3.0);
    }
    for fast in [true, false] {
        let src = format!("replay:{p}");
        let mut args = vec!["tracker", "listen", "--source", &src, "--json"];
        if fast {
            args.push("--as-fast-as-possible");
        }
        let (ok, out, err) = lungdyn(&args);
        assert!(ok, "{err}");
        let back: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        assert_eq!(back["frames"], live["frames"]);
        assert_eq!(
            back["frames_digest"], live["frames_digest"],
            "bit for bit (fast {fast})"
        );
    }
    // A damaged recording is refused with the place named, never replayed.
    let mut bytes = std::fs::read(&path).unwrap();
    let n = bytes.len();
    bytes[n - 100] ^= 0x40;
    let bad = tmp("bad.ldtr");
    std::fs::write(&bad, bytes).unwrap();
    assert_clean_failure(
        &[
            "tracker",
            "listen",
            "--source",
            &format!("replay:{}", bad.display()),
        ],
        "is corrupt",
    );
    assert_clean_failure(
        &[
            "tracker",
            "listen",
            "--source",
            "synthetic",
            "--record",
            p,
            "--seconds",
            "1",
        ],
        "exists",
    );
    for f in [&path, &bad] {
        let _ = std::fs::remove_file(f);
    }
}

#[test]
fn a_udp_amplitude_stream_is_heard_recorded_and_replayed_with_its_signal() {
    // A breathing belt's PC on this machine: 25 Hz, one `mm=VALUE` per datagram, one sample it
    // marks invalid and one junk datagram, for 3.5 s (the listener hears 2 s of it).
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let sender = std::thread::spawn(move || {
        let tx = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        for k in 0..88u32 {
            let t = f64::from(k) * 0.04;
            let d = match k {
                40 => "mm=".to_string(),
                41 => "mm=1;2".to_string(),
                _ => format!(
                    "mm={:.3}",
                    3.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos())
                ),
            };
            let _ = tx.send_to(d.as_bytes(), ("127.0.0.1", port));
            std::thread::sleep(Duration::from_millis(40));
        }
    });
    let path = tmp("udp-signal.ldtr");
    let p = path.to_str().unwrap();
    let spec = format!("udp:{port}");
    let (ok, out, err) = lungdyn(&[
        "tracker",
        "listen",
        "--source",
        "synthetic",
        "--breathing",
        &spec,
        "--seconds",
        "2",
        "--record",
        p,
        "--json",
    ]);
    sender.join().unwrap();
    assert!(ok, "{err}");
    let live: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let signal = &live["signal"];
    assert!(signal["samples_sent"].as_u64().unwrap() >= 30, "{signal}");
    assert_eq!(signal["invalid"], 1, "{signal}");
    assert_eq!(signal["malformed"], 1, "{signal}");
    assert_eq!(signal["refused_senders"], 0, "{signal}");
    // The recording plays the stream back: the same frames, signal included, bit for bit.
    let src = format!("replay:{p}");
    let (ok, out, err) = lungdyn(&[
        "tracker",
        "listen",
        "--source",
        &src,
        "--breathing",
        "recorded",
        "--json",
        "--as-fast-as-possible",
    ]);
    assert!(ok, "{err}");
    let back: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(back["frames_digest"], live["frames_digest"]);
    assert_eq!(back["signal"]["samples_sent"], signal["samples_sent"]);
    assert_eq!(back["signal"]["invalid"], signal["invalid"]);
    let _ = std::fs::remove_file(&path);
}

fn qtdata(k: u32) -> Vec<u8> {
    let e = |name: &str, p: [f32; 3], q: [f32; 4]| QtDataElement {
        name: name.into(),
        instrument_type: 2,
        position_mm: p,
        quaternion: q,
    };
    // Inside the seed's cone: the patient 1.2 m in front of the camera, the HMD 0.7 m, looking at it
    // (a camera looking along −Z is the identity rotation).
    Message::new(
        "Tracker",
        Timestamp::from_parts(1_700_000_000, k * 1000),
        Body::QtData(vec![
            e(
                "Patient",
                [k as f32 * 0.1, 0.0, -1200.0],
                [0.0, 0.0, 0.0, 1.0],
            ),
            e("HMD", [0.0, 100.0, -700.0], [0.0, 0.0, 0.0, 1.0]),
        ]),
    )
    .encode()
    .unwrap()
}

/// Stream QTDATA to `port` at 60 Hz for `seconds` from connecting (as soon as the server listens:
/// the seconds do not run while a slow bridge starts).
fn sender(port: u16, seconds: f64) -> std::thread::JoinHandle<u32> {
    std::thread::spawn(move || {
        let waiting = std::time::Instant::now();
        let mut s = loop {
            match TcpStream::connect(("127.0.0.1", port)) {
                Ok(s) => break s,
                Err(_) if waiting.elapsed() < Duration::from_secs(120) => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                Err(e) => panic!("the bridge never listened on {port}: {e}"),
            }
        };
        let start = std::time::Instant::now();
        let mut k = 0;
        while start.elapsed().as_secs_f64() < seconds {
            k += 1;
            if s.write_all(&qtdata(k)).is_err() {
                break;
            }
            std::thread::sleep(Duration::from_micros(16_667));
        }
        k
    })
}

#[test]
fn the_bridge_process_publishes_what_an_openigtlink_sender_sends() {
    let instance = unique_instance("igtl");
    let port = lungdyn_needs::free_local_port();
    let bridge = std::process::Command::new(bin("tracker-bridge"))
        .args([
            "--instance",
            &instance,
            "--seconds",
            "30",
            "--source",
            &format!("igtl-server:127.0.0.1:{port}"),
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let services = Instance::new(&instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    let send = sender(port, 2.0);
    let mut frames = Vec::new();
    let start = std::time::Instant::now();
    while !send.is_finished() && start.elapsed() < Duration::from_secs(60) {
        inlet
            .drain(&mut |f: &TrackerFrame| frames.push(*f))
            .unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let sent = send.join().unwrap();
    // SAFETY: signalling our own child.
    unsafe { libc::kill(bridge.id() as libc::pid_t, libc::SIGINT) };
    let out = bridge.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(sent > 60);
    let valid: Vec<&TrackerFrame> = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].is_valid() && f.tools[TOOL_HMD].is_valid())
        .collect();
    assert!(
        valid.len() > 60,
        "{} valid of {} frames: {err}",
        valid.len(),
        frames.len()
    );
    for f in &valid {
        let x = f.tools[TOOL_PATIENT].pose.translation_mm[0];
        assert!(
            (x * 10.0).round() >= 1.0
                && f.tools[TOOL_HMD].pose.translation_mm == [0.0, 100.0, -700.0]
        );
        assert!(f.stamps.capture_ns > 0 && f.stamps.capture_ns <= f.stamps.bridge_publish_ns);
    }
    assert!(
        err.contains("sender 127.0.0.1:") && err.contains("connected"),
        "{err}"
    );
    assert!(err.contains("0 rejected"), "{err}");
    drop(inlet);
    drop(node);
    services.remove_leftovers();
}

/// The chest's rise in mm at sender frame `k` (60 Hz): 5 mm + 4 mm at 15 breaths a minute.
fn chest_rise_mm(k: u32) -> f64 {
    5.0 + 4.0 * (2.0 * std::f64::consts::PI * k as f64 / 240.0).sin()
}

/// QTDATA of a patient reference turned 30° about the camera's Y and tilted 10°, drifting, the
/// HMD, and — for `k < chest_until` — a chest tool
/// [`chest_rise_mm`] anterior of the reference (and 60 mm cranial of it, 20 mm to the left).
fn qtdata_with_chest(k: u32, chest_until: u32) -> Vec<u8> {
    use glam::{DQuat, DVec3};
    let e = |name: &str, p: DVec3, q: DQuat| QtDataElement {
        name: name.into(),
        instrument_type: 2,
        position_mm: p.to_array().map(|v| v as f32),
        quaternion: q.to_array().map(|v| v as f32),
    };
    // RAS → camera: anterior up (the camera's +Y), turned 30° about it and tilted 10°.
    let q = DQuat::from_rotation_y(30f64.to_radians()) * DQuat::from_rotation_z(10f64.to_radians());
    let at = DVec3::new(k as f64 * 0.05, 0.0, -1200.0);
    let mut tools = vec![
        e("Patient", at, q),
        e("HMD", DVec3::new(0.0, 100.0, -700.0), DQuat::IDENTITY),
    ];
    if k < chest_until {
        let offset = DVec3::new(-20.0, chest_rise_mm(k), 60.0);
        tools.push(e("Chest", at + q * offset, q));
    }
    Message::new(
        "Tracker",
        Timestamp::from_parts(1_700_000_000, k * 1000),
        Body::QtData(tools),
    )
    .encode()
    .unwrap()
}

/// A tracked tool on the chest is the respiratory signal (`--breathing tool:Chest`): each of its
/// measurements is one sample in the frame's signal block, in mm along the patient reference's
/// anterior axis (the reference turned 30° and drifting: neither is breathing), equal to the sent
/// rise; the tool has its own slot; when the tool stops coming the samples are flagged invalid,
/// never held.
#[test]
fn a_chest_tool_is_the_respiratory_signal_along_the_patients_anterior_axis() {
    let instance = unique_instance("chest");
    let port = lungdyn_needs::free_local_port();
    let bridge = std::process::Command::new(bin("tracker-bridge"))
        .args([
            "--instance",
            &instance,
            "--seconds",
            "30",
            "--source",
            &format!("igtl-server:127.0.0.1:{port}"),
            "--breathing",
            "tool:Chest",
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let services = Instance::new(&instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    let send = std::thread::spawn(move || {
        let waiting = std::time::Instant::now();
        let mut s = loop {
            match TcpStream::connect(("127.0.0.1", port)) {
                Ok(s) => break s,
                Err(_) if waiting.elapsed() < Duration::from_secs(120) => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                Err(e) => panic!("the bridge never listened on {port}: {e}"),
            }
        };
        // 4 s with the chest tool, then 1 s without it.
        for k in 1..=300u32 {
            if s.write_all(&qtdata_with_chest(k, 240)).is_err() {
                break;
            }
            std::thread::sleep(Duration::from_micros(16_667));
        }
    });
    let mut frames = Vec::new();
    let start = std::time::Instant::now();
    while !send.is_finished() && start.elapsed() < Duration::from_secs(60) {
        inlet
            .drain(&mut |f: &TrackerFrame| frames.push(*f))
            .unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    send.join().unwrap();
    std::thread::sleep(Duration::from_millis(200));
    inlet
        .drain(&mut |f: &TrackerFrame| frames.push(*f))
        .unwrap();
    // SAFETY: signalling our own child.
    unsafe { libc::kill(bridge.id() as libc::pid_t, libc::SIGINT) };
    let out = bridge.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let samples: Vec<(f64, bool)> = frames
        .iter()
        .flat_map(|f| (0..f.signal.count as usize).map(move |i| f.signal.sample(i).unwrap()))
        .map(|(w, valid)| (w.value, valid))
        .collect();
    assert!(frames
        .iter()
        .all(|f| f.signal.status & ipc_types::signal_status::CONFIGURED != 0));
    assert!(frames
        .iter()
        .filter(|f| f.signal.count > 0)
        .all(|f| f.signal.unit == ipc_types::signal_unit::MM));
    let valid: Vec<f64> = samples.iter().filter(|s| s.1).map(|s| s.0).collect();
    assert!(valid.len() > 150, "{} valid samples: {err}", valid.len());
    // Every value is a sent rise (f32 poses: within 0.01 mm), and the breath's range is seen.
    for v in &valid {
        assert!(
            (1..240u32).any(|k| (chest_rise_mm(k) - v).abs() < 0.01),
            "{v} mm is no rise that was sent"
        );
    }
    let (lo, hi) = valid
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(*v), h.max(*v))
        });
    assert!(lo < 1.5 && hi > 8.5, "range {lo}..{hi}");
    // The chest tool in its own slot while it came; then flagged samples, none valid after them.
    assert!(frames
        .iter()
        .any(|f| f.tools[ipc_types::TOOL_CHEST].is_valid()));
    let last_valid = samples.iter().rposition(|s| s.1).unwrap();
    let flagged = samples.len() - last_valid - 1;
    assert!(
        flagged > 30,
        "{flagged} flagged after the chest tool went: {err}"
    );
    drop(inlet);
    drop(node);
    services.remove_leftovers();
}

/// A respiratory amplitude over OpenIGTLink (`--breathing igtl:Resp`) from pyigtl, an outside
/// sender (`tests/peers/amplitude_sender.py`: STRING `mm=VALUE` from "Resp", k/10 mm for k = 1..90
/// at 30 Hz, "Other"'s `mm=99` every tenth frame, a Patient pose, then `mm=` marked invalid): every
/// sent value reaches a frame's signal block once, in order, in mm, stamped when the bridge took
/// it (never before the frame that carries it); the other device's never; the invalid one flagged.
#[test]
fn an_amplitude_over_openigtlink_from_pyigtl_is_the_respiratory_signal() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let Some(python) = lungdyn_needs::pyigtl_python(&root) else {
        return;
    };
    let instance = unique_instance("igtl-amplitude");
    let port = lungdyn_needs::free_local_port();
    let bridge = std::process::Command::new(bin("tracker-bridge"))
        .args([
            "--instance",
            &instance,
            "--seconds",
            "60",
            "--source",
            &format!("igtl-server:127.0.0.1:{port}"),
            "--breathing",
            "igtl:Resp",
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let services = Instance::new(&instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut inlet = services.tracker_inlet(&node).unwrap();
    let n = 90;
    let mut sender = std::process::Command::new(&python)
        .arg(root.join("tests/peers/amplitude_sender.py"))
        .args([port.to_string(), n.to_string()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut frames = Vec::new();
    let start = std::time::Instant::now();
    while sender.try_wait().unwrap().is_none() && start.elapsed() < Duration::from_secs(90) {
        inlet
            .drain(&mut |f: &TrackerFrame| frames.push(*f))
            .unwrap();
        std::thread::sleep(Duration::from_millis(5));
    }
    let (sent_ok, said) = sender.wait_with_output_timeout();
    std::thread::sleep(Duration::from_millis(200));
    inlet
        .drain(&mut |f: &TrackerFrame| frames.push(*f))
        .unwrap();
    // SAFETY: signalling our own child.
    unsafe { libc::kill(bridge.id() as libc::pid_t, libc::SIGINT) };
    let out = bridge.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(sent_ok, "the pyigtl sender failed: {said}\nbridge: {err}");
    assert!(out.status.success(), "{err}");
    let mut samples = Vec::new();
    for f in &frames {
        assert_ne!(f.signal.status & ipc_types::signal_status::CONFIGURED, 0);
        for i in 0..f.signal.count as usize {
            let (w, valid) = f.signal.sample(i).unwrap();
            assert!(
                w.t_ns <= f.stamps.bridge_publish_ns,
                "a sample stamped after its frame"
            );
            assert_eq!(f.signal.unit, ipc_types::signal_unit::MM);
            samples.push((w.t_ns, w.value, valid));
        }
    }
    let valid: Vec<f64> = samples.iter().filter(|s| s.2).map(|s| s.1).collect();
    let want: Vec<f64> = (1..=n).map(|k| f64::from(k) / 10.0).collect();
    assert_eq!(valid.len(), want.len(), "{valid:?}\n{err}");
    for (v, w) in valid.iter().zip(&want) {
        assert!((v - w).abs() < 1e-9, "{v} mm where {w} mm was sent");
    }
    assert!(
        samples.windows(2).all(|w| w[0].0 <= w[1].0),
        "stamps in order"
    );
    let last = samples.last().unwrap();
    assert!(!last.2, "the sender's `mm=` is flagged invalid: {last:?}");
    assert_eq!(
        samples.len(),
        n as usize + 1,
        "Other's 99s are not the signal"
    );
    assert!(
        err.contains("OpenIGTLink amplitude from device \"Resp\""),
        "{err}"
    );
    drop(inlet);
    drop(node);
    services.remove_leftovers();
}

/// A small, quick scene for demos driven by a device source, written next to `dir`.
fn small_demo_scene(dir: &std::path::Path) -> std::path::PathBuf {
    let scene = dir.with_extension("toml");
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 1500\n[render]\nwidth = 160\nheight = 120\n",
    )
    .unwrap();
    scene
}

#[test]
fn the_demo_runs_on_a_device_source() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-trackers-demo-{}", std::process::id()));
    let scene = small_demo_scene(&dir);
    let port = lungdyn_needs::free_local_port();
    let send = sender(port, 60.0);
    let (ok, stdout, err) = demo_json(
        &dir,
        &scene,
        2,
        0,
        &["--tracker", &format!("igtl-server:127.0.0.1:{port}")],
    );
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    lungdyn_tests::assert_demo_report_is_consistent(&v, &err);
    assert!(err.contains("OpenIGTLink server on 127.0.0.1"), "{err}");
    let patient_line = err
        .lines()
        .find(|l| l.contains("Patient") && l.contains("patient"))
        .unwrap_or_default();
    assert!(
        patient_line.contains("Hz"),
        "the bridge counted the sender's patient samples: {err}"
    );
    drop(send); // the sender ends when the bridge is gone
    assert_clean_failure(&["demo", "--tracker", "polaris"], "--source \"polaris\"");
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
}

/// A bridge that never receives a patient sample: the engine holds (no) pose and flags it stale,
/// the renderer tints the view red and reports every such frame, and the demo says so.
#[test]
fn without_patient_samples_every_frame_says_the_pose_is_stale_on_screen_and_in_the_report() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-trackers-stale-{}", std::process::id()));
    let scene = small_demo_scene(&dir);
    // An OpenIGTLink server nobody sends to.
    let port = lungdyn_needs::free_local_port();
    let (ok, stdout, err) = demo_json(
        &dir,
        &scene,
        2,
        1,
        &["--tracker", &format!("igtl-server:127.0.0.1:{port}")],
    );
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let frames = v["frames_rendered"].as_u64().unwrap();
    assert!(frames > 0, "{v}");
    assert_eq!(v["patient_pose_held_frames"].as_u64(), Some(frames), "{v}");
    assert_eq!(v["patient_pose_stale_frames"].as_u64(), Some(frames), "{v}");
    assert!(err.contains("PATIENT POSE HELD"), "{err}");
    // On screen: the corner of the snapshot is the stale tint (sRGB of linear 0.22, 0.01, 0.01).
    let png = v["pngs"][0].as_str().unwrap();
    let img = image::open(png).unwrap().to_rgb8();
    let c = img.get_pixel(0, 0);
    assert!(
        c[0] > 100 && c[1] < 40 && c[2] < 40,
        "corner {c:?} of {png}"
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
}

#[test]
fn register_writes_a_calibration_with_fiducial_errors_and_refuses_collinear_points() {
    let model = tmp("model.csv");
    let tracker = tmp("tracker.csv");
    let out = tmp("calib.toml");
    // A known motion of the patient's RAS frame (the body-frame points with X negated: issue 19,
    // lung_model::frame): 90° about Z, then (10, -80, 5) mm; 0.3 mm of error on one tracker point.
    // RAS (−x, y, z) turned 90° about Z is (−y, −x, z).
    let pts = [
        ("A", [0.0, 0.0, 0.0]),
        ("B", [120.0, 0.0, 0.0]),
        ("C", [0.0, 90.0, 0.0]),
        ("D", [30.0, 40.0, 70.0]),
        ("E", [90.0, 80.0, 40.0]),
    ];
    let mut m = String::from("label,x,y,z\n");
    let mut t = String::from("# tracker, in the reference's frame\n");
    for (i, (l, p)) in pts.iter().enumerate() {
        m += &format!("{l},{},{},{}\n", p[0], p[1], p[2]);
        let q = [
            -p[1] + 10.0 + if i == 3 { 0.3 } else { 0.0 },
            -p[0] - 80.0,
            p[2] + 5.0,
        ];
        // Tracker list in another order: paired by label.
        t = format!("{l} {} {} {}\n", q[0], q[1], q[2]) + &t;
    }
    std::fs::write(&model, m).unwrap();
    std::fs::write(&tracker, t).unwrap();
    let args = [
        "register",
        "--model-points",
        model.to_str().unwrap(),
        "--tracker-points",
        tracker.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    let (ok, text, err) = lungdyn(&args);
    assert!(ok, "{err}");
    assert!(
        text.contains("registered 5 fiducials (paired by label)"),
        "{text}"
    );
    let mut json_args = args.to_vec();
    json_args.push("--json");
    let (ok, stdout, err) = lungdyn(&json_args);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let fre = v["fre_rms_mm"].as_f64().unwrap();
    assert!(fre > 0.01 && fre < 0.3, "{v}");
    let worst = v["fre_mm"]
        .as_array()
        .unwrap()
        .iter()
        .max_by(|a, b| {
            a["fre_mm"]
                .as_f64()
                .unwrap()
                .total_cmp(&b["fre_mm"].as_f64().unwrap())
        })
        .unwrap();
    assert_eq!(worst["label"], "D");
    assert!(v["model_frame"].as_str().unwrap().starts_with("ras"), "{v}");
    let c = tracker_pose::calib::Calibration::load(&out).unwrap();
    // Model point B (120 mm to the patient's left) is RAS (−120, 0, 0): turned, (0, −120, 0).
    let b = c.apply(lung_model::frame::body_to_ras(glam::DVec3::new(120.0, 0.0, 0.0)).to_array());
    assert!(
        (b[0] - 10.0).abs() < 0.2 && (b[1] + 200.0).abs() < 0.2 && (b[2] - 5.0).abs() < 0.2,
        "{b:?}"
    );
    // The same fiducials as the body frame's numbers turned as if the frame were right-handed
    // (how the tracker points were made before issue 19's fix): a mirror image of a real patient,
    // whose best fit is a reflection, refused; nothing written.
    let before = std::fs::read(&out).unwrap();
    let mirrored: String = pts
        .iter()
        .map(|(l, p)| format!("{l} {} {} {}\n", -p[1] + 10.0, p[0] - 80.0, p[2] + 5.0))
        .collect();
    std::fs::write(&tracker, mirrored).unwrap();
    assert_clean_failure(&args, "reflection");
    assert_eq!(std::fs::read(&out).unwrap(), before);
    // Nearly collinear fiducials (across the line 0.5 % of along it): refused, nothing written.
    let before = std::fs::read(&out).unwrap();
    std::fs::write(&model, "0 0 0\n50 0.5 0\n100 0 0\n150 0.2 1\n").unwrap();
    std::fs::write(&tracker, "0 0 0\n50 0.5 0\n100 0 0\n150 0.2 1\n").unwrap();
    assert_clean_failure(&args, "model fiducials are nearly collinear");
    assert_eq!(std::fs::read(&out).unwrap(), before);
    // Refusals.
    std::fs::write(&tracker, "0 0 0\n1 1 1\n").unwrap();
    assert_clean_failure(&args, "4 model points but 2 tracker points");
    std::fs::write(&tracker, "0 0 0\n1 1 nope\n").unwrap();
    assert_clean_failure(&args, "is not a fiducial");
    for f in [&model, &tracker, &out] {
        let _ = std::fs::remove_file(f);
    }
}

#[test]
fn prediction_on_simulated_head_motion_beats_holding_the_sample() {
    let rec = tmp("head.ldtr");
    let (ok, _, err) = lungdyn(&[
        "tracker",
        "simulate",
        "--out",
        rec.to_str().unwrap(),
        "--seconds",
        "20",
        "--seed",
        "3",
    ]);
    assert!(ok, "{err}");
    let (ok, stdout, err) = lungdyn(&[
        "tracker",
        "predict",
        "--recording",
        rec.to_str().unwrap(),
        "--lookahead-ms",
        "16,33",
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["tool"], "HMD");
    let find = |la: f64, method: &str| {
        v["results"]
            .as_array()
            .unwrap()
            .iter()
            .find(|r| {
                r["lookahead_ms"].as_f64() == Some(la)
                    && r["method"].as_str().unwrap().starts_with(method)
            })
            .unwrap_or_else(|| panic!("{la} {method}: {v}"))
            .clone()
    };
    for la in [16.0, 33.0] {
        let none = find(la, "none");
        let cv = find(la, "constant velocity");
        let mean = |r: &serde_json::Value, k: &str| r[k]["mean"].as_f64().unwrap();
        assert!(
            mean(&cv, "rotation_deg") < mean(&none, "rotation_deg") / 2.0,
            "{la} ms: {v}"
        );
        assert!(
            mean(&cv, "translation_mm") < mean(&none, "translation_mm"),
            "{la} ms: {v}"
        );
    }
    let (ok, text, _) = lungdyn(&["tracker", "predict", "--recording", rec.to_str().unwrap()]);
    assert!(ok && text.contains("alpha-beta"), "{text}");
    assert_clean_failure(
        &[
            "tracker",
            "predict",
            "--recording",
            rec.to_str().unwrap(),
            "--tool",
            "Pointer",
        ],
        "valid samples of tool Pointer",
    );
    assert_clean_failure(
        &["tracker", "simulate", "--out", rec.to_str().unwrap()],
        "exists",
    );
    let _ = std::fs::remove_file(&rec);
}

#[test]
fn hmd_check_shows_the_seed_hmd_and_refuses_a_bad_file() {
    let (ok, stdout, err) = lungdyn(&["hmd", "check", "--json"]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(
        (v["width_px"].as_u64(), v["height_px"].as_u64()),
        (Some(800), Some(600))
    );
    assert!((v["eyes"][0]["horizontal_fov_deg"].as_f64().unwrap() - 70.0).abs() < 1e-9);
    let f = tmp("hmd.toml");
    std::fs::write(&f, "format = 1\n[eyes]\nipd_mm = 0.064\n").unwrap();
    assert_clean_failure(&["hmd", "check", f.to_str().unwrap()], "eyes.ipd_mm");
    let _ = std::fs::remove_file(&f);
}

/// A calibration 80 mm posterior of the reference, turned 10° about the body's long axis, and an HMD
/// with small mirror-image asymmetric eyes, in `dir`.
fn calibration_and_hmd(dir: &std::path::Path) -> (std::path::PathBuf, std::path::PathBuf) {
    std::fs::create_dir_all(dir).unwrap();
    let calib = dir.join("calib.toml");
    std::fs::write(
        &calib,
        "format = 2\nkind = \"model-to-reference\"\n[transform]\n\
         rotation_xyzw = [0.0, 0.0, 0.0871557, 0.9961947]\ntranslation_mm = [0.0, -80.0, -20.0]\n",
    )
    .unwrap();
    let hmd = dir.join("hmd.toml");
    std::fs::write(
        &hmd,
        "format = 1\n[display]\nwidth_px = 144\nheight_px = 96\n[eyes]\nipd_mm = 62\n\
         [eyes.left]\noffset_mm = [-31, 0, 0]\nfrustum_deg = [36, 30, 24, 24]\n\
         [eyes.right]\noffset_mm = [31, 0, 0]\nfrustum_deg = [30, 36, 24, 24]\n",
    )
    .unwrap();
    (calib, hmd)
}

#[test]
fn scene_check_loads_and_reports_the_calibration_and_hmd_files() {
    let dir = tmp("scene-render-files");
    let (_, _) = calibration_and_hmd(&dir);
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 1500\n[render]\ncalibration = \"calib.toml\"\nhmd = \"hmd.toml\"\n",
    )
    .unwrap();
    let (ok, stdout, err) = lungdyn(&["scene", "check", scene.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let c = &v["render"]["calibration"];
    assert_eq!(c["file"].as_str(), dir.join("calib.toml").to_str());
    assert!(
        (c["rotation_deg"].as_f64().unwrap() - 10.0).abs() < 1e-3,
        "{c}"
    );
    assert_eq!(c["translation_mm"][1].as_f64(), Some(-80.0));
    let h = &v["render"]["hmd"];
    assert_eq!(h["file"].as_str(), dir.join("hmd.toml").to_str());
    assert_eq!(
        (h["width_px"].as_u64(), h["ipd_mm"].as_f64()),
        (Some(144), Some(62.0))
    );
    assert!((h["eyes"][0]["horizontal_fov_deg"].as_f64().unwrap() - 66.0).abs() < 1e-9);
    let (ok, text, err) = lungdyn(&["scene", "check", scene.to_str().unwrap()]);
    assert!(ok, "{err}");
    assert!(
        text.contains("calibration: ")
            && text.contains("HMD optics: ")
            && text.contains("144 x 96 px per eye"),
        "{text}"
    );
    // Without the keys, the text says what is used instead.
    std::fs::write(&scene, "[lungs]\nvertices = 1500\n").unwrap();
    let (ok, text, _) = lungdyn(&["scene", "check", scene.to_str().unwrap()]);
    assert!(
        ok && text.contains("calibration: none") && text.contains("HMD optics: none"),
        "{text}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_demo_draws_with_a_calibration_and_hmd_optics() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = tmp("demo-calibrated");
    let (calib, hmd) = calibration_and_hmd(&dir);
    let scene = dir.join("scene.toml");
    // Stereo, and a [render] size the optics file must override.
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 1500\n[render]\nstereo = true\nwidth = 400\nheight = 300\n",
    )
    .unwrap();
    let out = dir.join("out");
    let (ok, stdout, err) = demo_json(
        &out,
        &scene,
        2,
        2,
        &[
            "--calibration",
            calib.to_str().unwrap(),
            "--hmd",
            hmd.to_str().unwrap(),
        ],
    );
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    lungdyn_tests::assert_demo_report_is_consistent(&v, &err);
    assert_eq!(v["calibration"].as_str(), calib.to_str());
    assert_eq!(v["hmd"].as_str(), hmd.to_str());
    let start = err
        .lines()
        .find(|l| l.starts_with("renderer[") && l.contains("waiting for engine frames"))
        .unwrap_or_default();
    assert!(
        start.contains("288x96")
            && start.contains("lungs placed by the calibration")
            && start.contains(calib.to_str().unwrap())
            && start.contains(hmd.to_str().unwrap())
            && start.contains("144x96 px per eye from the file (overrides [render] width/height)"),
        "{err}"
    );
    // (The launcher hands the files to the renderer in the resolved scene, as [render] keys.)
    // The snapshots have the optics' size (both eyes side by side), and the lungs are in them.
    let pngs = v["pngs"].as_array().unwrap();
    assert_eq!(pngs.len(), 2, "{v}");
    for p in pngs {
        let img = image::open(p.as_str().unwrap()).unwrap().to_rgba8();
        assert_eq!(img.dimensions(), (288, 96));
        for eye in 0..2 {
            let lit = (eye * 144..(eye + 1) * 144)
                .flat_map(|x| (0..96).map(move |y| (x, y)))
                .filter(|&(x, y)| img.get_pixel(x, y).0[..3].iter().any(|&c| c > 40))
                .count();
            assert!(lit > 50, "eye {eye} of {p}: {lit} lit pixels");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `lungdyn demo --seconds S --snapshots N --json --out DIR --scene SCENE` and `extra`: the tests'
/// demo runs, which differ in their length, snapshots and what they connect to.
fn demo_json(
    out: &std::path::Path,
    scene: &std::path::Path,
    seconds: u32,
    snapshots: u32,
    extra: &[&str],
) -> (bool, String, String) {
    let (seconds, snapshots) = (seconds.to_string(), snapshots.to_string());
    let mut args = vec![
        "demo",
        "--seconds",
        &seconds,
        "--snapshots",
        &snapshots,
        "--json",
        "--out",
        out.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    lungdyn(&args)
}

/// A 15 s chest trace (3 s breaths, 25 Hz) written for the test: synthetic, not patient data.
fn breathing_trace(path: &std::path::Path) {
    let mut s = String::from("time_s,amplitude_mm,valid\n");
    for k in 0..600 {
        let t = k as f64 * 0.04;
        let phase = (t / 3.0).fract();
        let depth = 8.0 * (1.0 + 0.05 * ((t / 3.0).floor() * 1.7).sin());
        let v = depth * 0.5 * (1.0 - (2.0 * std::f64::consts::PI * phase).cos());
        s += &format!("{t:.3},{v:.4},1\n");
    }
    std::fs::write(path, s).unwrap();
}

/// `lungdyn breathing follow FILE` (issue 35): the three processes with a 24 s trace replayed live
/// by the bridge; the engine follows it (calibrates, then the signal drives the lungs), loses it
/// in a 2 s cut (the model carries on under the blue veil) and takes it up again, and says the
/// signal is lost when the trace ends. Every drawn frame comes out on the trace's own clock (the
/// CSV), and the figures hold the followed volume against the trace at each frame's display time
/// (docs/BREATHING.md).
#[test]
fn breathing_follow_replays_a_trace_live_and_holds_every_drawn_frame_against_it() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-trackers-breath-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = small_demo_scene(&dir);
    let trace = dir.with_extension("csv");
    breathing_trace(&trace);
    let frames = dir.join("frames.csv");
    let (ok, stdout, err) = lungdyn(&[
        "breathing",
        "follow",
        trace.to_str().unwrap(),
        "--json",
        "--out",
        dir.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
        "--drop-at",
        "15",
        "--drop-for",
        "2",
        "--frames-out",
        frames.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    lungdyn_tests::assert_demo_report_is_consistent(&v["run"], &err);
    assert!(err.contains("breathing signal: CSV trace of mm"), "{err}");
    let engine = err
        .lines()
        .find(|l| l.contains("engine[") && l.contains("breathing signal:"))
        .unwrap_or_else(|| panic!("the engine's breathing line: {err}"));
    let number_before = |words: &str| -> u64 {
        let at = engine
            .find(words)
            .unwrap_or_else(|| panic!("{words:?} in {engine}"));
        engine[..at]
            .split_whitespace()
            .last()
            .and_then(|w| w.trim_start_matches('(').parse().ok())
            .unwrap_or_else(|| panic!("a number before {words:?} in {engine}"))
    };
    // 600 samples, 50 of them in the cut.
    assert!(number_before("samples used") >= 500, "{engine}");
    assert!(number_before("breaths (") >= 3, "{engine}");
    assert!(
        engine.contains("signal lost (the source ended)"),
        "{engine}"
    );
    let run = &v["run"];
    let (drawn, followed, lost) = (
        run["frames_rendered"].as_u64().unwrap(),
        run["signal_following_frames"].as_u64().unwrap(),
        run["signal_lost_frames"].as_u64().unwrap(),
    );
    assert!(followed >= drawn / 10, "{followed} of {drawn} frames: {v}");
    assert!(lost > 0 && lost < drawn, "{lost} of {drawn}: {v}");
    assert_eq!(
        run["signal_clipped_frames"].as_u64(),
        Some(0),
        "a trace of breaths not cut by a sensor's range: {v}"
    );
    // The figures: the trace's own numbers, and the run's, consistent with each other.
    let n = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k}: {v}"));
    assert_eq!(n("frames_drawn") as u64, drawn);
    assert!(
        n("frames_following") > 0.0 && n("frames_compared") > 0.0,
        "{v}"
    );
    assert!(n("frames_lost") > 0.0, "the cut and the end: {v}");
    assert!(n("breaths_in_recording") >= 6.0, "{v}");
    assert!(n("breaths_detected") >= 1.0, "{v}");
    let rms = n("rms_error_percent_of_tidal");
    assert!(rms.is_finite() && rms > 0.0 && rms < 60.0, "{v}");
    assert!(
        n("rms_error_percent_of_tidal_without_prediction").is_finite(),
        "{v}"
    );
    let latency = n("latency_ms_measured_median");
    assert!(latency > 0.0 && latency < 2000.0, "{v}");
    // The engine predicted across the pipeline's latency as the bridge measured it from the
    // renderer's reports (the scene's default), not the fixed 50 ms: what it predicted across and
    // what the frames took are the same latency, each frame's a median of the frames before it.
    assert_eq!(v["latency"], "measured", "{v}");
    let predicted = n("latency_ms_predicted_median");
    assert!(
        predicted > 0.0 && (predicted - latency).abs() <= 0.5 * latency + 10.0,
        "predicted across {predicted} ms, the frames took {latency} ms: {v}"
    );
    assert!(
        err.contains("pipeline latency (bridge publish → display) from")
            && err.contains("sent to the engine"),
        "the bridge says what it measured: {err}"
    );
    assert!(
        n("drawn_vs_followed_rms_ml") < 5.0,
        "the lungs drew what the engine followed: {v}"
    );
    assert!(
        n("recording_played_s") > 20.0 && n("recording_played_s") < 30.0,
        "{v}"
    );
    let cut = &v["drop"];
    assert_eq!(cut["at_s"].as_f64(), Some(15.0));
    assert!(
        cut["resync_s"].as_f64().is_some_and(|s| s < 6.0),
        "following again after the cut: {v}"
    );
    assert!(v["goals"]["rms_within_3_percent"].is_boolean(), "{v}");
    // Every frame on the trace's clock, in order, its volume both lungs' (FRC included).
    let csv = std::fs::read_to_string(&frames).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("display_time_s,volume_ml"));
    let rows: Vec<(f64, f64)> = lines
        .map(|l| {
            let (t, ml) = l.split_once(',').unwrap();
            (t.parse().unwrap(), ml.parse().unwrap())
        })
        .collect();
    assert_eq!(rows.len() as f64, n("frames_on_recording"));
    assert!(
        rows.windows(2).all(|w| w[1].0 >= w[0].0),
        "in display order"
    );
    assert!(
        rows.iter()
            .all(|r| r.0 >= 0.0 && r.0 < 30.0 && r.1 > 500.0 && r.1 < 9000.0),
        "{csv}"
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
    std::fs::remove_file(&trace).ok();
}

/// `lungdyn demo --igtl-connect HOST:PORT`: lungdyn connects to Slicer's server (here the test's
/// listener, as Slicer's OpenIGTLinkIF connector of type Server would listen) and sends what
/// `--igtl-serve` sends, each frame the two lungs' POLYDATA then the state; the report names the
/// role. (What the frames hold is checked against the CPU reference in the test below and in
/// `lungdyn-launcher`'s `slicer` tests: the bytes are the same frame maker's.)
#[test]
fn the_demo_connects_to_slicers_server_with_igtl_connect() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = tmp("slicer-connect");
    let scene_path = dir.with_extension("toml");
    std::fs::write(
        &scene_path,
        "[lungs]\nvertices = 1500\n[render]\nwidth = 160\nheight = 120\n",
    )
    .unwrap();
    let slicer = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = slicer.local_addr().unwrap().port();
    slicer.set_nonblocking(true).unwrap();
    let reader = std::thread::spawn(move || -> Result<Vec<(String, String)>, String> {
        use std::io::Read;
        let until = std::time::Instant::now() + Duration::from_secs(180);
        let mut s = loop {
            match slicer.accept() {
                Ok((s, _)) => break s,
                Err(_) if std::time::Instant::now() < until => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                Err(e) => return Err(format!("lungdyn never connected: {e}")),
            }
        };
        s.set_nonblocking(false).map_err(|e| e.to_string())?;
        s.set_read_timeout(Some(Duration::from_secs(30)))
            .map_err(|e| e.to_string())?;
        let mut got = Vec::new();
        let text = |b: &[u8]| {
            String::from_utf8_lossy(b)
                .trim_end_matches('\0')
                .to_string()
        };
        loop {
            let mut head = [0u8; 58];
            s.read_exact(&mut head).map_err(|e| e.to_string())?;
            let size = u64::from_be_bytes(head[42..50].try_into().unwrap());
            let mut body = vec![0u8; size as usize];
            s.read_exact(&mut body).map_err(|e| e.to_string())?;
            got.push((text(&head[2..14]), text(&head[14..34])));
            if got.last().unwrap().1 == "BreathState" {
                return Ok(got);
            }
        }
    });
    let target = format!("127.0.0.1:{port}");
    let (ok, stdout, err) = demo_json(&dir, &scene_path, 5, 0, &["--igtl-connect", &target]);
    assert!(ok, "{err}");
    let first = reader
        .join()
        .unwrap()
        .unwrap_or_else(|e| panic!("{e}\ndemo: {err}"));
    let pair = |t: &str, d: &str| (t.to_string(), d.to_string());
    assert_eq!(
        first,
        [
            pair("POLYDATA", "RightLung"),
            pair("POLYDATA", "LeftLung"),
            pair("STRING", "BreathState")
        ],
        "the first frame"
    );
    assert!(
        err.contains(&format!(
            "sending the lungs to 3D Slicer's server at {target}"
        )) && err.contains("connected to Slicer's server"),
        "{err}"
    );
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let s = &v["slicer"];
    assert_eq!(
        (&s["role"], &s["clients"]),
        (&"client".into(), &1.into()),
        "{s}"
    );
    assert!(s["frames"].as_u64().unwrap() >= 1, "{s}");
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene_path).ok();
}

/// `lungdyn demo --igtl-serve` (issue 38): lungdyn as the OpenIGTLink server 3D Slicer connects to.
/// pyigtl, as the client (its own receive loop, then its header parser, CRC and message classes on
/// an ordered capture; POLYDATA's unpack mended in `tests/peers/slicer_client.py`), receives each
/// frame as RightLung, LeftLung, Tumour (POLYDATA), TumourCentre (TRANSFORM) and BreathState
/// (STRING) with one timestamp; the points equal the renderer's CPU reference for the frame's tick
/// (the engine run headless to it), reflected to RAS, to 1 µm; the triangles are the mesh's with
/// their corners reversed; the lobe codes come as the point scalar "Lobe". The scene deforms in the
/// precomputed mode: the demo's synthetic patient drifts ±3° (which the orientation modes follow,
/// so its frames are not the headless still patient's); the orientation modes' frames are checked
/// against the CPU reference in `lungdyn-launcher`'s `slicer` tests.
#[test]
fn slicer_receives_the_breathing_lungs_and_the_tumour_over_openigtlink() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    // `bench/igtl_reference.sh` names a client built on the OpenIGTLink C++ library (3D Slicer's
    // own) here; otherwise pyigtl is the client.
    let reference_client = std::env::var_os("LUNGDYN_IGTL_REFERENCE_CLIENT");
    let client_cmd = match &reference_client {
        Some(exe) => std::process::Command::new(exe),
        None => {
            let Some(python) = lungdyn_needs::pyigtl_python(&root) else {
                return;
            };
            let mut c = std::process::Command::new(python);
            c.arg(root.join("tests/peers/slicer_client.py"));
            c
        }
    };
    let dir = tmp("slicer");
    let scene_path = dir.with_extension("toml");
    std::fs::write(
        &scene_path,
        "[lungs]\nvertices = 1500\nmode = \"precomputed\"\n[render]\nwidth = 160\nheight = 120\n\
         [disease]\nkind = \"tumour\"\nside = \"right\"\n[disease.tumour]\nlobe = \"right lower\"\nradii_mm = [12.0, 10.0, 15.0]\n",
    )
    .unwrap();
    let port = lungdyn_needs::free_local_port();
    let capture = dir.with_extension("json");
    let frames = 30;
    let mut client_cmd = client_cmd;
    let mut client = client_cmd
        .args([port.to_string(), frames.to_string()])
        .arg(&capture)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let (ok, stdout, err) = demo_json(
        &dir,
        &scene_path,
        8,
        0,
        &["--igtl-serve", &port.to_string()],
    );
    let peer = client.wait_with_output_timeout();
    assert!(ok, "{err}");
    assert!(peer.0, "the pyigtl client failed: {}\ndemo: {err}", peer.1);
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let s = &v["slicer"];
    assert!(s["failure"].is_null(), "{s}");
    assert!(s["frames"].as_u64().unwrap() >= frames, "{s}");
    assert_eq!(
        (&s["refused"], &s["bad_frames"], &s["stalled"]),
        (&0.into(), &0.into(), &0.into()),
        "{s}"
    );
    assert!(
        err.contains(&format!(
            "serving the lungs to 3D Slicer on 127.0.0.1:{port}"
        )),
        "{err}"
    );
    assert!(
        err.contains("Slicer (OpenIGTLink on"),
        "the summary says what was sent: {err}"
    );

    let got: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&capture).unwrap()).unwrap();
    let pyigtl = reference_client.is_none();
    let phase1 = &got["pyigtl_client"];
    if pyigtl {
        assert_eq!(phase1["BreathState"], "STRING", "{phase1}\ndemo: {err}");
        assert_eq!(phase1["RightLung"], "POLYDATA", "{phase1}");
    } else {
        assert_eq!(got["client"], "OpenIGTLink C++ library", "{got}");
        eprintln!("slicer test: the client is the OpenIGTLink C++ library's (LUNGDYN_IGTL_REFERENCE_CLIENT)");
    }
    assert_eq!(
        got["crc_errors"], 0,
        "the client's CRC-64 agrees with every header"
    );
    let captured = got["frames"].as_array().unwrap();
    assert_eq!(captured.len() as u64, frames);
    let order = [
        "RightLung",
        "LeftLung",
        "Tumour",
        "TumourCentre",
        "BreathState",
    ];
    let mut last_tick = None;
    for f in captured {
        let names: Vec<&str> = f["order"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d.as_str().unwrap())
            .collect();
        assert_eq!(names, order, "{}", f["types"]);
        let ts: Vec<f64> = f["timestamps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t.as_f64().unwrap())
            .collect();
        assert!(
            ts.iter().all(|&t| t == ts[0] && t > 1.6e9),
            "one wall-clock timestamp a frame: {ts:?}"
        );
        let tick = f["tick"].as_u64().unwrap();
        assert!(last_tick.is_none_or(|t| tick > t), "frames in tick order");
        last_tick = Some(tick);
    }

    // The reference: the same kernels (the demo baked them into --out/kernels), the engine run
    // headless to each kept tick, the renderer's CPU deformation, reflected to RAS.
    let scene = lung_model::scene::Scene::load(&scene_path).unwrap();
    let scene = lungdyn::prepare::prepare(scene, &dir.join("kernels"))
        .unwrap()
        .scene;
    let kept: Vec<&serde_json::Value> = captured
        .iter()
        .filter(|f| f.get("messages").is_some())
        .collect();
    let ticks: Vec<u64> = kept.iter().map(|f| f["tick"].as_u64().unwrap()).collect();
    let mut reference = std::collections::HashMap::new();
    engine::headless::run_while(
        EngineCore::new(&scene).unwrap(),
        ticks.iter().max().unwrap() + 2,
        &mut lungdyn::scene_check::still_patient(&scene),
        &mut |_, f| {
            if ticks.contains(&f.tick) {
                reference.insert(f.tick, *f);
            }
            true
        },
    )
    .unwrap();
    let first_right = kept[0]["messages"]["RightLung"]["points"]
        .as_array()
        .unwrap()
        .len() as u64;
    if pyigtl {
        assert_eq!(
            phase1["RightLung_points"].as_u64(),
            Some(first_right / 3),
            "pyigtl's own receive loop unpacked the whole mesh: {phase1}"
        );
    }
    let mut worst = 0.0f32;
    for (k, f) in kept.iter().enumerate() {
        let e = &reference[&f["tick"].as_u64().unwrap()];
        let m = &f["messages"];
        for &side in &scene.lungs.sides {
            let device = if side == lung_model::mesh::Side::Right {
                "RightLung"
            } else {
                "LeftLung"
            };
            let mut lung = renderer::RenderLung::from_kernel(
                &scene.lung_kernel(side).unwrap(),
                scene.lungs.mode,
            )
            .unwrap();
            let mut body = vec![[0.0f32; 3]; lung.lung.len()];
            lungdyn::export::lung_positions_into(&mut lung, &e.lungs[side.index()], &mut body)
                .unwrap();
            let msg = &m[device];
            if pyigtl {
                // (pyigtl's mended unpack says how far it read; the C++ library reads by the
                // counts and does not say: there the points, cells and attributes below are
                // what a body of the wrong length would break.)
                assert_eq!(
                    msg["consumed"], msg["content_length"],
                    "{device}: every byte read"
                );
            }
            let pts: Vec<f32> = msg["points"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect();
            assert_eq!(pts.len(), body.len() * 3, "{device}");
            for (i, p) in body.iter().enumerate() {
                let ras = lungdyn::slicer::body_to_ras(*p);
                for a in 0..3 {
                    worst = worst.max((pts[3 * i + a] - ras[a]).abs());
                }
            }
            assert_eq!(
                msg["polygon_count"].as_u64().unwrap() as usize,
                lung.lung.triangles.len()
            );
            if k == 0 {
                let polys: Vec<u32> = msg["polygons"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|x| x.as_u64().unwrap() as u32)
                    .collect();
                let expect: Vec<u32> = lungdyn::slicer::ras_triangles(&lung.lung.triangles)
                    .iter()
                    .flat_map(|t| [3, t[0], t[1], t[2]])
                    .collect();
                // Outward in RAS: the received triangles enclose a positive volume, the engine's.
                let tris: Vec<[u32; 3]> = polys.chunks(4).map(|c| [c[1], c[2], c[3]]).collect();
                let ml = lung_model::mesh::enclosed_volume_with(&tris, |i| {
                    [0, 1, 2].map(|a| f64::from(pts[3 * i as usize + a]))
                }) / 1000.0;
                let engine_ml = f64::from(e.lungs[side.index()].volume_ml);
                assert!(
                    ml > 0.0 && (ml - engine_ml).abs() < 0.1 * engine_ml,
                    "{device}: {ml} ml vs the engine's {engine_ml}"
                );
                assert!(
                    polys == expect,
                    "{device}: the mesh's triangles, corners reversed"
                );
            }
            let attrs = msg["attributes"].as_array().unwrap();
            let codes = lung.lobe_codes().expect("generated lungs have lobes");
            assert_eq!(attrs.len(), 1, "{device}");
            assert_eq!(
                (
                    attrs[0]["name"].as_str(),
                    attrs[0]["type"].as_u64(),
                    attrs[0]["components"].as_u64()
                ),
                (Some("Lobe"), Some(0), Some(1))
            );
            let lobes: Vec<u8> = attrs[0]["data"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as u8)
                .collect();
            assert_eq!(lobes, codes, "{device}: lobe codes per vertex");
        }
        // The tumour: its centre as the TRANSFORM's translation, its mesh around it.
        let t = scene.tumour().unwrap();
        let lung = renderer::RenderLung::from_kernel(
            &scene.lung_kernel(t.side).unwrap(),
            scene.lungs.mode,
        )
        .unwrap();
        let c = lungdyn::export::tumour_centre(
            lung.tumour.as_ref().unwrap(),
            scene.lungs.mode,
            &e.lungs[t.side.index()],
        )
        .unwrap();
        let c = lungdyn::slicer::body_to_ras(c.map(|v| v as f32));
        let mat: Vec<f64> = m["TumourCentre"]["matrix"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        for a in 0..3 {
            assert!(
                (mat[4 * a + 3] as f32 - c[a]).abs() < 1e-3,
                "tumour centre {mat:?} vs {c:?}"
            );
            assert!(
                (mat[5 * a] - 1.0).abs() < 1e-9,
                "a pure translation: {mat:?}"
            );
        }
        let tp: Vec<f64> = m["Tumour"]["points"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let n = tp.len() / 3;
        for a in 0..3 {
            let (lo, hi) = (0..n)
                .map(|i| tp[3 * i + a])
                .fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(v), h.max(v)));
            assert!(
                ((hi + lo) / 2.0 - c[a] as f64).abs() < 0.05,
                "the ellipsoid sits on its centre"
            );
            assert!(
                (hi - lo - 2.0 * t.radii_mm[a]).abs() < 0.05,
                "its radii: {} vs {:?}",
                hi - lo,
                t.radii_mm
            );
        }
        let state: serde_json::Value =
            serde_json::from_str(m["BreathState"]["string"].as_str().unwrap()).unwrap();
        assert_eq!(state["disease"].as_str().unwrap(), "tumour, right");
        for l in state["lungs"].as_array().unwrap() {
            let slot = if l["side"] == "right" { 0 } else { 1 };
            let vol = l["volume_ml"].as_f64().unwrap();
            assert!(
                (vol - e.lungs[slot].volume_ml as f64).abs() < 0.06,
                "{l} vs {}",
                e.lungs[slot].volume_ml
            );
        }
    }
    eprintln!(
        "Slicer link: {} frames captured by {}, {} checked whole; largest difference from the CPU \
         reference {worst:e} mm; {}",
        captured.len(),
        if pyigtl {
            "pyigtl"
        } else {
            "the OpenIGTLink C++ library"
        },
        kept.len(),
        s
    );
    assert!(
        worst <= 1e-3,
        "points within 1 µm of the CPU reference: {worst} mm"
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene_path).ok();
    std::fs::remove_file(&capture).ok();
}

/// A child's exit and its stderr, waiting at most two minutes (then killed).
trait WaitTimeout {
    fn wait_with_output_timeout(&mut self) -> (bool, String);
}

impl WaitTimeout for std::process::Child {
    fn wait_with_output_timeout(&mut self) -> (bool, String) {
        let until = std::time::Instant::now() + Duration::from_secs(120);
        let status = loop {
            if let Some(s) = self.try_wait().unwrap() {
                break Some(s);
            }
            if std::time::Instant::now() > until {
                let _ = self.kill();
                let _ = self.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        let mut err = String::new();
        if let Some(mut e) = self.stderr.take() {
            use std::io::Read;
            let _ = e.read_to_string(&mut err);
        }
        (status.is_some_and(|s| s.success()), err)
    }
}
