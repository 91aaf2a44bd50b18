//! The three real processes over iceoryx2: frames flow end to end, in order, with every hop
//! stamped; SIGINT stops them cleanly and nothing of the instance is left in shared memory.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use ipc_types::{now_ns, FrameReport, Inlet, Services};
use lungdyn_tests::{bin, unique_instance};

fn spawn(name: &str, instance: &str, extra: &[&str]) -> Child {
    Command::new(bin(name))
        .args(["--instance", instance, "--seconds", "60"])
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {name}: {e}"))
}

fn interrupt_and_wait(name: &str, child: &mut Child) -> String {
    // SAFETY: signalling our own child.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
    let until = now_ns() + 10_000_000_000;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            assert!(
                status.success(),
                "{name} exited with {status} after SIGINT: {err}"
            );
            return err;
        }
        assert!(
            now_ns() < until,
            "{name} did not stop within 10 s of SIGINT"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn frames_flow_end_to_end_in_order_and_nothing_is_left_behind() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let instance = unique_instance("pipeline");
    let services = Services::new(&instance).unwrap();
    let node = services.node("test").unwrap();
    let reports: Inlet<FrameReport> = Inlet::new(
        &node,
        &services.report(),
        &format!("{}-ready", services.report()),
    )
    .unwrap();
    let scene = std::env::temp_dir().join(format!("{instance}.toml"));
    std::fs::write(&scene, "[lungs]\nvertices = 2000\n").unwrap();
    let scene_arg = scene.to_str().unwrap();
    let mut renderer = spawn("renderer", &instance, &["--scene", scene_arg]);
    let mut engine = spawn("engine", &instance, &["--scene", scene_arg]);
    let mut bridge = spawn("tracker-bridge", &instance, &[]);

    let mut got: Vec<FrameReport> = Vec::new();
    let start = now_ns();
    let mut first: Option<u64> = None;
    while now_ns() - start < 60_000_000_000 {
        reports.drain(|r| got.push(*r)).unwrap();
        if first.is_none() && !got.is_empty() {
            first = Some(now_ns());
        }
        if first.is_some_and(|t| now_ns() - t > 3_000_000_000) {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let bridge_err = interrupt_and_wait("tracker-bridge", &mut bridge);
    let engine_err = interrupt_and_wait("engine", &mut engine);
    let renderer_err = interrupt_and_wait("renderer", &mut renderer);
    reports.drain(|r| got.push(*r)).unwrap();
    drop(reports);
    drop(node);
    std::fs::remove_file(&scene).ok();

    assert!(
        got.len() >= 30,
        "only {} frames in ~3 s\n{bridge_err}\n{engine_err}\n{renderer_err}",
        got.len()
    );
    for w in got.windows(2) {
        assert!(w[1].frame > w[0].frame, "renderer frames out of order");
        assert!(
            w[1].engine_tick >= w[0].engine_tick,
            "engine ticks went backwards"
        );
        assert!(
            w[1].tracker_frame >= w[0].tracker_frame,
            "tracker frames went backwards"
        );
    }
    let fresh: Vec<_> = got
        .iter()
        .filter(|r| r.flags & ipc_types::report_flags::STALE_ENGINE == 0)
        .collect();
    assert!(!fresh.is_empty());
    for r in &fresh {
        assert!(
            r.stamps.is_complete_and_ordered(),
            "hop stamps incomplete or unordered: {:?}",
            r.stamps
        );
        assert!(r.tracker_frame > 0);
        let v = r.volume_ml[0] + r.volume_ml[1];
        assert!((2399.0..=2901.0).contains(&v), "volume {v}");
    }
    assert!(
        engine_err.contains("waiting for tracker frames"),
        "{engine_err}"
    );
    assert!(renderer_err.contains("engine connected"), "{renderer_err}");

    // Every process has exited: remove the instance's persistent segment and check for leftovers.
    services.remove_instance_segment().unwrap();
    let left = services.leftovers();
    assert!(left.is_empty(), "left behind: {left:?}");
}

#[test]
fn a_process_started_alone_waits_and_says_what_for() {
    let instance = unique_instance("alone");
    let out = Command::new(bin("renderer"))
        .args(["--instance", &instance, "--seconds", "1.5"])
        .env(
            "WGPU_BACKEND",
            std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()),
        )
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no GPU adapter") {
        assert_ne!(
            std::env::var("LUNGDYN_REQUIRE_GPU").as_deref(),
            Ok("1"),
            "{err}"
        );
        return;
    }
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("waiting for engine frames on \"lungdyn/"),
        "{err}"
    );
    let out = Command::new(bin("engine"))
        .args(["--instance", &instance, "--seconds", "1"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && err.contains("waiting for tracker frames"),
        "{err}"
    );
    let services = Services::new(&instance).unwrap();
    services.remove_instance_segment().unwrap();
    assert!(services.leftovers().is_empty());
}
