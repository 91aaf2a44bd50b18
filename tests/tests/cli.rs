//! The command line: clear errors and non-zero exits for bad input, never a panic; the demo and
//! `mesh generate` produce what they promise.

use std::process::Command;

use lungdyn_tests::{assert_clean_failure, bin, lungdyn};

#[test]
fn bad_arguments_give_one_clear_message_and_a_non_zero_exit() {
    assert_clean_failure(&["demo", "--bogus"], "unexpected argument '--bogus'");
    assert_clean_failure(&["demo", "--seconds=-3"], "--seconds -3");
    assert_clean_failure(&["demo", "--seconds", "nan"], "--seconds NaN");
    assert_clean_failure(
        &["demo", "--out", "/proc/lungdyn-no"],
        "--out /proc/lungdyn-no",
    );
    assert_clean_failure(
        &["demo", "--scene", "/nonexistent/scene.toml"],
        "cannot read scene",
    );
    assert_clean_failure(&["demo", "--instance", "bad/name"], "instance name");
    // `--cpus` takes the comma form its --help shows as well as three words: both reach the core
    // check (clap once refused the comma form with "3 values required").
    assert_clean_failure(&["demo", "--cpus", "4096,0,0"], "core 4096");
    assert_clean_failure(&["demo", "--cpus", "0", "4096", "0"], "core 4096");
    assert_clean_failure(&["demo", "--cpus", "0,1"], "needs three cores");
    assert_clean_failure(&["demo", "--cpus", "0,1,1,1"], "needs three cores");
    assert_clean_failure(&["demo", "--cpus", "0,,1"], "--cpus");
    assert_clean_failure(
        &["mesh", "generate", "--lung", "middle", "--out", "x.obj"],
        "middle",
    );
    assert_clean_failure(
        &[
            "mesh",
            "generate",
            "--lung",
            "left",
            "--vertices",
            "3",
            "--out",
            "/tmp/x.obj",
        ],
        "out of range",
    );
    assert_clean_failure(
        &["mesh", "generate", "--lung", "left", "--out", "/tmp/x.stl"],
        "must end in .obj or .ply",
    );
    assert_clean_failure(
        &[
            "mesh",
            "generate",
            "--lung",
            "left",
            "--out",
            "/nonexistent-dir/x.obj",
        ],
        "cannot write",
    );
    assert_clean_failure(
        &["engine", "--scene", "/nonexistent.toml"],
        "cannot read scene",
    );
    assert_clean_failure(&["engine", "--cpu", "4096"], "cannot pin to CPU core 4096");
}

#[test]
fn a_bad_scene_is_refused_naming_the_key() {
    let path = std::env::temp_dir().join(format!("lungdyn-bad-scene-{}.toml", std::process::id()));
    std::fs::write(&path, "[render]\nstereo = true\nwidht = 3\n").unwrap();
    assert_clean_failure(&["demo", "--scene", path.to_str().unwrap()], "widht");
    std::fs::remove_file(path).ok();
}

#[test]
fn mesh_generate_writes_a_closed_lung_of_the_requested_size() {
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-mesh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("right.ply");
    let (ok, stdout, err) = lungdyn(&[
        "mesh",
        "generate",
        "--lung",
        "right",
        "--vertices",
        "1000",
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert!(v["vertices"].as_u64().unwrap() >= 1000);
    assert!((v["volume_ml"].as_f64().unwrap() - 1300.0).abs() < 0.01);
    assert!(out.exists());
    std::fs::remove_dir_all(dir).ok();
}

/// The lowest-numbered core this process may run on.
fn first_allowed_core() -> usize {
    // SAFETY: sched_getaffinity fills a zeroed cpu_set_t of the size passed; CPU_ISSET only reads it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        assert_eq!(
            libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set),
            0
        );
        (0..libc::CPU_SETSIZE as usize)
            .find(|&c| libc::CPU_ISSET(c, &set))
            .expect("some core")
    }
}

/// The cores this process may run on.
fn allowed_cores() -> Vec<usize> {
    // SAFETY: as in `first_allowed_core`.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        assert_eq!(
            libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set),
            0
        );
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| libc::CPU_ISSET(c, &set))
            .collect()
    }
}

/// Every thread of process `pid`: (name, the kernel's `Cpus_allowed_list`).
fn thread_affinities(pid: u32) -> Vec<(String, String)> {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return Vec::new();
    };
    tasks
        .flatten()
        .filter_map(|t| {
            let name = std::fs::read_to_string(t.path().join("comm")).ok()?;
            let status = std::fs::read_to_string(t.path().join("status")).ok()?;
            let list = status
                .lines()
                .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))?;
            Some((name.trim().to_string(), list.trim().to_string()))
        })
        .collect()
}

/// Each pinned process keeps every one of its threads on its core — the renderer's driver's too (lavapipe's
/// `llvmpipe-N` rasterisers, wgpu's and the window system's): the renderer pins itself before the
/// GPU opens, and threads inherit their creator's affinity. (Pinned after the GPU opened, only its
/// main thread was on the core and lavapipe's threads ran on every core, the engine's included.)
#[test]
fn every_pinned_process_keeps_all_its_threads_on_its_core_the_renderers_driver_too() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let cores = allowed_cores();
    assert!(
        cores.len() >= 2,
        "this test needs two cores to tell a pinned thread from an unpinned one; it may run on {cores:?}"
    );
    let (other, mine) = (cores[0], cores[1]);
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-pin-{}", std::process::id()));
    let scene = dir.with_extension("toml");
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 2000\n[render]\nwidth = 320\nheight = 240\n",
    )
    .unwrap();
    let instance = format!("pin{}", std::process::id());
    let mut demo = Command::new(bin("lungdyn"))
        .args([
            "demo",
            "--seconds",
            "8",
            "--snapshots",
            "1",
            "--instance",
            &instance,
        ])
        .args(["--cpus", &format!("{other},{other},{mine}")])
        .arg("--out")
        .arg(&dir)
        .arg("--scene")
        .arg(&scene)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Each role is the demo's child whose command line names it.
    let child = |demo: u32, role: &[u8]| -> Option<u32> {
        let children =
            std::fs::read_to_string(format!("/proc/{demo}/task/{demo}/children")).ok()?;
        children
            .split_whitespace()
            .filter_map(|c| c.parse().ok())
            .find(|c: &u32| {
                std::fs::read(format!("/proc/{c}/cmdline"))
                    .map(|l| l.split(|b| *b == 0).any(|a| a == role))
                    .unwrap_or(false)
            })
    };
    let roles: [(&[u8], usize); 3] = [
        (b"tracker-bridge", other),
        (b"engine", other),
        (b"renderer", mine),
    ];
    // Sample each role's threads while it runs; the latest sample with the most threads is kept (the
    // GPU's threads exist once the renderer's first frames are drawn). The latest, not the first: a
    // process sampled between its exec and its own pin_to_core still has the launcher's affinity
    // (CI caught the engine so, its one thread on 0-1), and a later sample of as many threads
    // shows it after pinning.
    let mut widest: [Vec<(String, String)>; 3] = Default::default();
    let start = std::time::Instant::now();
    while demo.try_wait().unwrap().is_none() && start.elapsed().as_secs() < 120 {
        for ((role, _), seen) in roles.iter().zip(&mut widest) {
            if let Some(pid) = child(demo.id(), role) {
                let threads = thread_affinities(pid);
                if threads.len() >= seen.len() {
                    *seen = threads;
                }
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let out = demo.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    for ((role, core), seen) in roles.iter().zip(&widest) {
        let role = String::from_utf8_lossy(role);
        assert!(!seen.is_empty(), "the {role} process was never seen");
        // Mesa's shader disk-cache writer (`disk$N`) is the one thread that widens its own affinity
        // on purpose: Mesa starts it with UTIL_QUEUE_INIT_SET_FULL_THREAD_AFFINITY at its lowest
        // priority (src/util/disk_cache_os.c), so it neither inherits nor competes with a pinned
        // core's work.
        let wrong: Vec<_> = seen
            .iter()
            .filter(|(name, list)| *list != core.to_string() && !name.contains(":disk$"))
            .collect();
        assert!(
            wrong.is_empty(),
            "{role} pinned to core {core}: threads allowed elsewhere {wrong:?} (all: {seen:?})"
        );
    }
    assert!(
        widest[2].len() >= 2,
        "the renderer was seen with only {} threads (before its GPU opened?): {:?}",
        widest[2].len(),
        widest[2]
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
}

#[test]
fn the_demo_prints_json_with_frames_latency_and_pngs() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-demo-{}", std::process::id()));
    let scene = dir.with_extension("toml");
    std::fs::write(&scene, "[lungs]\nvertices = 2000\n[render]\nwidth = 320\nheight = 240\nstereo = true\nmode = \"points\"\n")
        .unwrap();
    // Pinned with the comma form of --cpus (the first core this test may run on, for all three).
    let core = first_allowed_core();
    let cpus = format!("{core},{core},{core}");
    let (ok, stdout, err) = lungdyn(&[
        "demo",
        "--seconds",
        "3",
        "--snapshots",
        "3",
        "--json",
        "--cpus",
        &cpus,
        "--out",
        dir.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value =
        serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    lungdyn_tests::assert_demo_report_is_consistent(&v, &err);
    assert_eq!(v["cpus"], serde_json::json!([core, core, core]), "{v}");
    for key in [
        "deadline_misses",
        "end_to_end_p50_ms",
        "end_to_end_p99_ms",
        "end_to_end_max_ms",
    ] {
        assert!(v[key].is_number(), "{key} missing: {v}");
    }
    let p50 = v["end_to_end_p50_ms"].as_f64().unwrap();
    assert!(p50 > 0.0 && p50 <= v["end_to_end_max_ms"].as_f64().unwrap());
    // The first frame came after the start, and within the run.
    let first = v["first_frame_s"].as_f64().unwrap();
    assert!(first > 0.0 && first < 60.0, "{v}");
    // The governor's account: every frame at some quality, and the last one's named.
    assert_eq!(v["governor"], "hold-deadline", "{v}");
    let at_quality: u64 = v["quality_frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|q| q["frames"].as_u64().unwrap())
        .sum();
    assert_eq!(at_quality, v["frames_rendered"].as_u64().unwrap(), "{v}");
    assert!(v["final_quality"].is_string(), "{v}");
    assert_eq!(v["governor_start"], "remembered", "{v}");
    let first_quality = v["first_quality"].as_str().unwrap();
    assert!(
        v["quality_frames"]
            .as_array()
            .unwrap()
            .iter()
            .any(|q| q["quality"] == first_quality),
        "the first frame's quality is one frames were drawn at: {v}"
    );
    let pngs = v["pngs"].as_array().unwrap();
    assert_eq!(pngs.len(), 3, "{v}");
    for p in pngs {
        let img = image::open(p.as_str().unwrap()).unwrap();
        assert_eq!(
            (img.width(), img.height()),
            (640, 240),
            "stereo: two 320-wide eyes"
        );
    }
    assert_eq!(
        v["leftover_files"].as_u64(),
        Some(0),
        "no process left files behind"
    );
    assert_eq!(v["remaining_files"].as_u64(), Some(0));
    assert!(std::path::Path::new(v["strip"].as_str().unwrap()).exists());
    assert!(
        err.contains("end to end"),
        "the table goes to stderr with --json: {err}"
    );
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
}

#[test]
fn the_demo_shows_frames_in_a_window_when_a_display_exists() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    if !lungdyn_tests::xvfb_available() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-window-{}", std::process::id()));
    let scene = dir.with_extension("toml");
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 2000\n[render]\nwidth = 320\nheight = 240\n",
    )
    .unwrap();
    let out = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1024x768x24"])
        .arg(bin("lungdyn"))
        .args([
            "demo",
            "--window",
            "--seconds",
            "2",
            "--snapshots",
            "2",
            "--json",
            "--out",
        ])
        .arg(&dir)
        .arg("--scene")
        .arg(&scene)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let v: serde_json::Value =
        serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    lungdyn_tests::assert_demo_report_is_consistent(&v, &stderr);
    assert_eq!(v["pngs"].as_array().unwrap().len(), 2);
    assert_eq!(v["remaining_files"].as_u64(), Some(0));
    // Presented, in the mode chosen for latency (Xvfb offers no mailbox; lavapipe's X11 surface
    // presents immediately), with one frame queued at most.
    assert!(v["presented_frames"].as_u64().unwrap() >= 1, "{v}");
    assert!(
        ["mailbox", "immediate"].contains(&v["present_mode"].as_str().unwrap()),
        "{v}"
    );
    assert_eq!(v["frame_latency"], 1, "{v}");
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_file(&scene).ok();
}

#[test]
fn window_without_a_display_is_refused_up_front() {
    let out = Command::new(bin("lungdyn"))
        .args(["demo", "--window", "--seconds", "1"])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--window needs a display"), "{err}");
}

#[test]
fn mesh_check_imports_repairs_and_refuses_with_one_clear_message() {
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-check-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let obj = dir.join("left.obj");
    let (ok, _, err) = lungdyn(&[
        "mesh",
        "generate",
        "--lung",
        "left",
        "--vertices",
        "1000",
        "--out",
        obj.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let ply = dir.join("left_mm.ply");
    let (ok, stdout, err) = lungdyn(&[
        "mesh",
        "check",
        "--mesh",
        obj.to_str().unwrap(),
        "--out",
        ply.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["euler"].as_i64(), Some(2));
    assert!((v["volume_ml"].as_f64().unwrap() - 1100.0).abs() < 0.01);
    assert!(ply.exists());
    let (ok, _, err) = lungdyn(&[
        "mesh",
        "check",
        "--mesh",
        dir.join("missing.stl").to_str().unwrap(),
    ]);
    assert!(!ok);
    assert_eq!(
        err.matches("No such file").count(),
        1,
        "the OS error appears once: {err}"
    );
    std::fs::write(
        dir.join("open.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\n",
    )
    .unwrap();
    let (ok, _, err) = lungdyn(&[
        "mesh",
        "check",
        "--mesh",
        dir.join("open.obj").to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("open.obj") && err.contains("open boundary edges"),
        "{err}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// `lungdyn doctor --json` on this machine: every check, each with a status, what it saw and a fix;
/// exit 2 exactly when one is missing (a script can gate the service on it).
#[test]
fn doctor_json_lists_every_check_with_a_status_and_a_fix() {
    let out = Command::new(bin("lungdyn"))
        .args(["doctor", "--json"])
        .output()
        .expect("run lungdyn doctor");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("doctor --json is not JSON ({e}): {stderr}"));
    let checks = v["checks"].as_array().expect("a checks list");
    let names: Vec<&str> = checks.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, lungdyn::doctor::CHECKS);
    let mut missing = false;
    for c in checks {
        let status = c["status"].as_str().unwrap();
        assert!(["ok", "warning", "missing"].contains(&status), "{c}");
        missing |= status == "missing";
        for key in ["detail", "fix"] {
            assert!(
                c[key].as_str().is_some_and(|s| !s.trim().is_empty()),
                "{key} of {c}"
            );
        }
    }
    assert_eq!(
        out.status.code(),
        Some(if missing { 2 } else { 0 }),
        "{stderr}"
    );
}

/// A copy of an OBJ lung with every vertex mapped by `f` (a reflection) and the winding flipped
/// so it stays outward: what a tool writing that frame would have written.
fn reflected_obj(text: &str, f: impl Fn(f64, f64, f64) -> (f64, f64, f64)) -> String {
    let mut out = String::new();
    for line in text.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.first() {
            Some(&"v") => {
                let c: Vec<f64> = w[1..4].iter().map(|x| x.parse().unwrap()).collect();
                let (x, y, z) = f(c[0], c[1], c[2]);
                out += &format!("v {x} {y} {z}\n");
            }
            Some(&"f") => out += &format!("f {} {} {}\n", w[1], w[3], w[2]),
            _ => {}
        }
    }
    out
}

/// A reader that closes the pipe before a printing command writes (`lungdyn pv presets | head`, the
/// reader already gone) ends it quietly, without `println!`'s EPIPE panic and its backtrace.
#[test]
fn a_printing_command_whose_reader_is_gone_ends_without_a_panic() {
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenes/tension_pneumothorax.toml"
    );
    for args in [&["pv", "presets"][..], &["scene", "check", scene][..]] {
        let mut child = Command::new(bin("lungdyn"))
            .args(args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

/// `mesh check --frame lps|ras` on an LPS (Y negated) or RAS (X negated) copy of a generated lung
/// gives the body-frame original's volume, size and side, without a frame warning; the LPS copy
/// read without `--frame` is refused naming `--frame lps` (anterior and posterior would swap), the
/// RAS copy read as body is seen as the other lung.
#[test]
fn mesh_check_frame_lps_and_ras_give_the_body_frame_lung() {
    let dir = std::env::temp_dir().join(format!("lungdyn-cli-frame-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (side, other) in [("left", "right"), ("right", "left")] {
        let body = dir.join(format!("{side}.obj"));
        let (ok, _, err) = lungdyn(&[
            "mesh",
            "generate",
            "--lung",
            side,
            "--vertices",
            "2000",
            "--out",
            body.to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
        let check = |path: &std::path::Path, extra: &[&str]| {
            let mut args = vec!["mesh", "check", "--mesh", path.to_str().unwrap(), "--json"];
            args.extend_from_slice(extra);
            let (ok, stdout, err) = lungdyn(&args);
            (ok, stdout, err)
        };
        let (ok, stdout, err) = check(&body, &[]);
        assert!(ok && !err.contains("warning"), "{side} body: {err}");
        let original: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(original["geometry_side"], side, "{side}");
        assert!(original["frame_warning"].is_null(), "{side}: {original}");
        assert_eq!(original["frame"], "body");

        let text = std::fs::read_to_string(&body).unwrap();
        let lps = dir.join(format!("{side}_lps.obj"));
        std::fs::write(&lps, reflected_obj(&text, |x, y, z| (x, -y, z))).unwrap();
        let ras = dir.join(format!("{side}_ras.obj"));
        std::fs::write(&ras, reflected_obj(&text, |x, y, z| (-x, y, z))).unwrap();
        for (copy, frame) in [(&lps, "lps"), (&ras, "ras")] {
            let (ok, stdout, err) = check(copy, &["--frame", frame, "--lung", side]);
            assert!(ok && !err.contains("warning"), "{side} {frame}: {err}");
            let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
            let what = format!("{side} --frame {frame}");
            let vol = v["volume_ml"].as_f64().unwrap();
            let vol0 = original["volume_ml"].as_f64().unwrap();
            assert!((vol - vol0).abs() < 1e-6 * vol0, "{what}: {vol} vs {vol0}");
            assert_eq!(v["size_mm"], original["size_mm"], "{what}");
            assert_eq!(v["geometry_side"], side, "{what}");
            assert_eq!(
                v["repairs"], original["repairs"],
                "{what}: not flipped inside out"
            );
            assert!(v["frame_warning"].is_null(), "{what}: {v}");
            assert_eq!(v["frame"], frame);
        }
        // Without --frame: the LPS copy is refused with the fix ...
        let (ok, _, err) = check(&lps, &[]);
        assert!(!ok, "{side}: an LPS copy read as body must be refused");
        assert!(
            err.contains("--frame lps") && err.contains("POSTERIOR"),
            "{side}: {err}"
        );
        // ... and the RAS copy looks like the other lung.
        let (ok, stdout, _) = check(&ras, &[]);
        assert!(ok);
        let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(v["geometry_side"], other, "{side} RAS read as body");
        // The body-frame original read with --frame lps: warned about, with --frame body as the
        // fix (not the --frame lps it was read with).
        let (ok, stdout, err) = check(&body, &["--frame", "lps"]);
        assert!(ok, "{side}: {err}");
        let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        let w = v["frame_warning"]
            .as_str()
            .unwrap_or_else(|| panic!("{side}: a body lung read as LPS must be warned about: {v}"));
        assert!(
            w.contains("--frame body") && !w.contains("read it with --frame lps"),
            "{side}: {w}"
        );
    }
    std::fs::remove_dir_all(dir).ok();
}
