//! The three real processes over iceoryx2: what a run produced is checked, not how fast it was —
//! every frame valid and finite, nothing lost between what the renderer says it drew and what we
//! received, hop stamps complete, the lungs of one kernel on both sides, SIGINT stops everything
//! cleanly and nothing of the instance is left in shared memory.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use ipc_types::{report_flags, FrameReport, LAYOUT_VERSION};
use lungdyn_tests::{bin, prepared_scene, renderer_frames, unique_instance};
use transport::{iox, now_ns, Instance, Receive};

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

/// SIGINT to `child`, then wait for its clean exit, calling `meanwhile` as it is awaited (a
/// reader of the reports keeps draining them: the renderer goes on drawing while the others stop);
/// its stderr (empty where the caller reads it itself).
fn interrupt_and_wait(name: &str, child: &mut Child, meanwhile: &mut dyn FnMut()) -> String {
    // SAFETY: signalling our own child.
    unsafe { libc::kill(child.id() as libc::pid_t, libc::SIGINT) };
    let until = now_ns() + 10_000_000_000;
    loop {
        meanwhile();
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            if let Some(mut e) = child.stderr.take() {
                e.read_to_string(&mut err).unwrap();
            }
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

/// The number in "`<role>`[..]: stopped after N ..." of a process's stderr.
fn stopped_after(stderr: &str, role: &str) -> u64 {
    stderr
        .lines()
        .find(|l| l.starts_with(&format!("{role}[")) && l.contains("stopped after"))
        .and_then(|l| {
            l.split("stopped after ")
                .nth(1)?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .unwrap_or_else(|| panic!("{role} did not say how much it did: {stderr}"))
}

/// Run the three processes on `engine_scene` / `renderer_scene` for about `seconds` of frames.
struct Run {
    reports: Vec<FrameReport>,
    bridge_err: String,
    engine_err: String,
    renderer_err: String,
}

fn run(tag: &str, engine_scene: &str, renderer_scene: &str, seconds: u64) -> Option<Run> {
    run_with(tag, engine_scene, renderer_scene, seconds, |_| {})
}

/// [`run`], calling `during(renderer_pid)` once the first frame has arrived; the `seconds` of
/// frames are counted from its return (frames drawn after it are what it is checked by).
fn run_with(
    tag: &str,
    engine_scene: &str,
    renderer_scene: &str,
    seconds: u64,
    during: impl FnOnce(u32),
) -> Option<Run> {
    renderer::gpu::Gpu::for_tests()?;
    let instance = unique_instance(tag);
    let services = Instance::new(&instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut inlet = services.report_inlet(&node).unwrap();
    let mut renderer = spawn("renderer", &instance, &["--scene", renderer_scene]);
    let mut engine = spawn("engine", &instance, &["--scene", engine_scene]);
    let mut bridge = spawn("tracker-bridge", &instance, &[]);
    let mut reports: Vec<FrameReport> = Vec::new();
    let start = now_ns();
    let mut first: Option<u64> = None;
    let mut during = Some(during);
    while now_ns() - start < 60_000_000_000 {
        inlet
            .drain(&mut |r: &FrameReport| reports.push(*r))
            .unwrap();
        if first.is_none() && !reports.is_empty() {
            first = Some(now_ns());
            if let Some(f) = during.take() {
                f(renderer.id());
                inlet
                    .drain(&mut |r: &FrameReport| reports.push(*r))
                    .unwrap();
                first = Some(now_ns());
            }
        }
        if first.is_some_and(|t| now_ns() - t > seconds * 1_000_000_000) {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    // The renderer draws on (stale frames) while the bridge and the engine stop: its reports are
    // drained meanwhile, so none overflows the stream's buffer however long the stops take.
    let mut drain = || {
        inlet
            .drain(&mut |r: &FrameReport| reports.push(*r))
            .unwrap();
    };
    let bridge_err = interrupt_and_wait("tracker-bridge", &mut bridge, &mut drain);
    let engine_err = interrupt_and_wait("engine", &mut engine, &mut drain);
    let renderer_err = interrupt_and_wait("renderer", &mut renderer, &mut drain);
    inlet
        .drain(&mut |r: &FrameReport| reports.push(*r))
        .unwrap();
    drop(inlet);
    drop(node);
    // Every process has exited: only iceoryx2's node counter may remain, and then nothing.
    let cleanup = services.remove_leftovers();
    assert!(
        cleanup.unexpected.is_empty(),
        "left behind by the processes: {:?}",
        cleanup.unexpected
    );
    assert!(services.leftovers().is_empty());
    assert!(
        !reports.is_empty(),
        "no frame in 60 s\n{bridge_err}\n{engine_err}\n{renderer_err}"
    );
    Some(Run {
        reports,
        bridge_err,
        engine_err,
        renderer_err,
    })
}

#[test]
fn frames_flow_end_to_end_complete_valid_and_accounted_for() {
    let scene = prepared_scene("pipeline", "[lungs]\nvertices = 2000\n");
    let scene = scene.to_str().unwrap();
    let Some(r) = run("pipeline", scene, scene, 2) else {
        return;
    };
    let ctx = format!("{}\n{}\n{}", r.bridge_err, r.engine_err, r.renderer_err);
    // Nothing lost between the renderer and us: frames 1..=N, N as the renderer counted them.
    let drawn = renderer_frames(&r.renderer_err).unwrap_or_else(|| panic!("{ctx}"));
    assert_eq!(r.reports.len() as u64, drawn, "{ctx}");
    for (k, rep) in r.reports.iter().enumerate() {
        assert_eq!(rep.frame, k as u64 + 1, "report {k} out of sequence");
        assert_eq!(rep.layout_version, LAYOUT_VERSION);
        assert_eq!(
            rep.flags & report_flags::KERNEL_MISMATCH,
            0,
            "same scene, same kernels"
        );
        let v = rep.volume_ml[0] + rep.volume_ml[1];
        assert!(
            v.is_finite() && (2399.0..=2901.0).contains(&v),
            "frame {}: volume {v}",
            rep.frame
        );
    }
    for w in r.reports.windows(2) {
        assert!(
            w[1].engine_tick >= w[0].engine_tick,
            "engine ticks went backwards"
        );
        assert!(
            w[1].tracker_frame >= w[0].tracker_frame,
            "tracker frames went backwards"
        );
    }
    // Fresh frames carry every hop, in order; every engine tick drawn was published by the engine.
    let fresh: Vec<_> = r
        .reports
        .iter()
        .filter(|x| x.flags & report_flags::STALE_ENGINE == 0)
        .collect();
    assert!(!fresh.is_empty(), "{ctx}");
    for rep in &fresh {
        assert!(rep.stamps.is_complete_and_ordered(), "{:?}", rep.stamps);
        assert!(rep.tracker_frame > 0);
    }
    let ticks = stopped_after(&r.engine_err, "engine");
    let last_tick = r.reports.last().unwrap().engine_tick;
    assert!(
        last_tick < ticks,
        "drew tick {last_tick}, the engine ran {ticks}: {ctx}"
    );
    let tracker_frames = stopped_after(&r.bridge_err, "tracker-bridge");
    assert!(r.reports.last().unwrap().tracker_frame <= tracker_frames);
    assert!(r.engine_err.contains("tracker connected"), "{ctx}");
    assert!(r.renderer_err.contains("engine connected"), "{ctx}");
    assert!(
        r.renderer_err.contains(", 0 with a kernel mismatch"),
        "{ctx}"
    );
}

/// The scene's wake strategies reach the processes: each says the one it runs in its start-up
/// line, and frames flow with every hop stamped (busy-poll needs a reserved core: the transport's
/// own test covers it, and the bad-input cases its refusals).
#[test]
fn the_scenes_wake_strategies_run_and_are_said_at_start_up() {
    let scene = prepared_scene(
        "pipeline-wake",
        "[lungs]\nvertices = 1500\n[processes]\nspin_us = 150\nwake = { engine = \"spin-then-park\", renderer = \"event\" }\n",
    );
    let scene = scene.to_str().unwrap();
    let Some(r) = run("pipeline-wake", scene, scene, 2) else {
        return;
    };
    let ctx = format!("{}\n{}\n{}", r.bridge_err, r.engine_err, r.renderer_err);
    assert!(
        r.engine_err.contains(
            "waits for tracker frames by spin-then-park (150 µs window) (the scene's [processes] wake)"
        ),
        "{ctx}"
    );
    assert!(
        r.renderer_err
            .contains("waits for engine frames by event (the scene's [processes] wake)"),
        "{ctx}"
    );
    let fresh = r
        .reports
        .iter()
        .filter(|x| x.flags & report_flags::STALE_ENGINE == 0)
        .inspect(|rep| assert!(rep.stamps.is_complete_and_ordered(), "{:?}", rep.stamps))
        .count();
    assert!(fresh > 0, "{ctx}");
    // The engine ticked on tracker samples, not only on its deadline fallback.
    let on_samples: u64 = r
        .engine_err
        .split(" on a tracker sample")
        .next()
        .and_then(|head| head.rsplit('(').next())
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("the engine did not count its sample ticks: {ctx}"));
    assert!(on_samples > 0, "{ctx}");
}

/// Two different kernels: the engine computes the lungs of one bake, the renderer loaded another.
/// Every frame is flagged, the renderer says so once and counts it, and no displacement of one
/// kernel is drawn on the other's vertices (the in-process test in `kernel_identity.rs` reads the
/// deformed vertices back; here the processes are real).
#[test]
fn a_renderer_with_other_kernels_flags_every_frame_and_says_why() {
    let a = prepared_scene("mismatch-a", "[lungs]\nvertices = 1500\n");
    let b = prepared_scene("mismatch-b", "[lungs]\nvertices = 2500\n");
    let Some(r) = run("mismatch", a.to_str().unwrap(), b.to_str().unwrap(), 1) else {
        return;
    };
    let fresh: Vec<_> = r
        .reports
        .iter()
        .filter(|x| x.flags & report_flags::STALE_ENGINE == 0)
        .collect();
    assert!(!fresh.is_empty());
    for rep in &fresh {
        assert_ne!(
            rep.flags & report_flags::KERNEL_MISMATCH,
            0,
            "frame {}",
            rep.frame
        );
    }
    let warnings = r.renderer_err.matches("drawing that lung at rest").count();
    assert_eq!(warnings, 1, "said once: {}", r.renderer_err);
    assert!(
        r.renderer_err.contains("lungdyn scene prepare"),
        "{}",
        r.renderer_err
    );
    let mismatched: u64 = r
        .renderer_err
        .split("frames (")
        .nth(1)
        .and_then(|s| s.split(" with a kernel mismatch").next())
        .and_then(|s| s.rsplit(", ").next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{}", r.renderer_err));
    let flagged = r
        .reports
        .iter()
        .filter(|x| x.flags & report_flags::KERNEL_MISMATCH != 0)
        .count() as u64;
    assert_eq!(
        mismatched, flagged,
        "the renderer's count matches the flagged reports"
    );
}

/// A renderer frozen for two seconds (SIGSTOP) draws nothing meanwhile; measured only on drawn
/// frames that is invisible. Against the schedule it must show as ~120 late tracker samples and a
/// worst case of about two seconds.
#[test]
fn a_frozen_renderer_shows_as_missed_deadlines_not_as_nothing() {
    let scene = prepared_scene(
        "freeze",
        "[lungs]\nvertices = 1000\n[render]\nwidth = 160\nheight = 120\n",
    );
    let scene = scene.to_str().unwrap();
    let Some(r) = run_with("freeze", scene, scene, 1, |pid| {
        std::thread::sleep(Duration::from_millis(300));
        // SAFETY: signalling our own child.
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGSTOP) };
        std::thread::sleep(Duration::from_secs(2));
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGCONT) };
    }) else {
        return;
    };
    let mut stats = lungdyn::stats::LatencyStats::new();
    for rep in &r.reports {
        stats.record(rep);
    }
    let worst = stats.sample_latency().max_ms;
    assert!(
        stats.sample_deadline_misses >= 100,
        "{} late samples, worst {worst} ms",
        stats.sample_deadline_misses
    );
    assert!((1800.0..4000.0).contains(&worst), "worst {worst} ms");
    assert!(
        stats.missed_frame_slots >= 100,
        "{}",
        stats.missed_frame_slots
    );
}

#[test]
fn a_second_run_with_the_same_instance_is_refused_and_touches_nothing() {
    let instance = unique_instance("twice");
    let scene = prepared_scene("twice", "[lungs]\nvertices = 1000\n");
    let mut first = Command::new(bin("engine"))
        .args(["--instance", &instance, "--seconds", "20", "--scene"])
        .arg(&scene)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the first one is up (it prints its waiting line, its ports open), however long a
    // cold, loaded machine takes: a fixed pause let the second start before the first held the
    // instance. Its stderr is read on a thread meanwhile, and to its end after it stops.
    let (lines, up) = std::sync::mpsc::channel();
    let stderr = first.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        use std::io::BufRead;
        let mut all = String::new();
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let _ = lines.send(line.contains("waiting for tracker frames"));
            all += &line;
            all.push('\n');
        }
        all
    });
    let waiting = std::time::Instant::now();
    loop {
        match up.recv_timeout(Duration::from_secs(120).saturating_sub(waiting.elapsed())) {
            Ok(true) => break,
            Ok(false) => {}
            Err(e) => panic!("the first engine never said it waits for tracker frames: {e}"),
        }
    }
    let out = Command::new(bin("engine"))
        .args(["--instance", &instance, "--seconds", "1", "--scene"])
        .arg(&scene)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("is already running") && err.contains(&format!("process {}", first.id())),
        "{err}"
    );
    // The first is unharmed: its streams still exist and it stops cleanly.
    let services = Instance::new(&instance).unwrap();
    assert!(
        !services.leftovers().is_empty(),
        "the first run's shared memory is still there"
    );
    interrupt_and_wait("engine", &mut first, &mut || {});
    let first_err = reader.join().unwrap();
    assert!(first_err.contains("stopped after"), "{first_err}");
    assert!(services.remove_leftovers().unexpected.is_empty());
    // Two launchers: while one holds the instance (here: this test), a demo with the same name is
    // refused before it bakes, writes or removes anything.
    let held = services.lock("launcher").unwrap();
    let out_dir = std::env::temp_dir().join(format!("{instance}-out"));
    let (ok, _, err) = lungdyn_tests::lungdyn(&[
        "demo",
        "--instance",
        &instance,
        "--seconds",
        "1",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("is already running"), "{err}");
    assert!(
        err.contains(&format!("process {}", std::process::id())),
        "{err}"
    );
    assert!(
        !out_dir.exists(),
        "the refused demo wrote {}",
        out_dir.display()
    );
    drop(held);
}

#[test]
fn a_process_started_alone_waits_and_says_what_for() {
    let instance = unique_instance("alone");
    let scene = prepared_scene("alone", "[lungs]\nvertices = 1000\n");
    let out = Command::new(bin("renderer"))
        .args(["--instance", &instance, "--seconds", "1.5", "--scene"])
        .arg(&scene)
        .env(
            "WGPU_BACKEND",
            std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()),
        )
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    if err.contains("no GPU adapter") {
        lungdyn_needs::missing(lungdyn_needs::Need::Gpu, &err);
    } else {
        assert!(out.status.success(), "{err}");
        assert!(
            err.contains("waiting for engine frames on \"lungdyn/"),
            "{err}"
        );
        assert_eq!(
            renderer_frames(&err),
            Some(0),
            "nothing to draw without an engine: {err}"
        );
    }
    let out = Command::new(bin("engine"))
        .args(["--instance", &instance, "--seconds", "1", "--scene"])
        .arg(&scene)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && err.contains("waiting for tracker frames"),
        "{err}"
    );
    // Alone, every tick ran on the deadline: about 60 in a second, none on a sample.
    assert!(err.contains("0 on a tracker sample"), "{err}");
    let services = Instance::new(&instance).unwrap();
    assert!(services.remove_leftovers().unexpected.is_empty());
    assert!(services.leftovers().is_empty());
}

#[test]
fn the_processes_never_bake_and_say_how_to_get_kernels() {
    for role in ["engine", "renderer"] {
        let out = Command::new(bin(role))
            .args(["--instance", &unique_instance("nobake"), "--seconds", "1"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        if role == "renderer" && err.contains("no GPU adapter") {
            lungdyn_needs::missing(lungdyn_needs::Need::Gpu, &err);
            continue;
        }
        assert!(!out.status.success(), "{role}: {err}");
        assert!(
            err.contains("no kernel for the right lung") && err.contains("lungdyn scene prepare"),
            "{role}: {err}"
        );
        assert!(!err.contains("panicked"), "{role}: {err}");
    }
}

#[test]
fn seconds_must_be_finite_positive_and_bounded_in_every_process() {
    for role in ["engine", "renderer", "tracker-bridge"] {
        for bad in ["1e30", "-1", "0", "nan", "inf"] {
            let out = Command::new(bin(role))
                .args([
                    "--instance",
                    &unique_instance("secs"),
                    &format!("--seconds={bad}"),
                ])
                .output()
                .unwrap();
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(!out.status.success(), "{role} --seconds={bad}: {err}");
            assert!(err.contains("--seconds"), "{role} --seconds={bad}: {err}");
            assert!(!err.contains("panicked"), "{role}: {err}");
        }
    }
}
