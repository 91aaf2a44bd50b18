//! `lungdyn latency`: a short run's JSON has the keys the harness promises and its figures are
//! consistent with each other (never a wall-clock threshold: the machine may be shared).

use lungdyn_tests::{assert_clean_failure, bin};

#[test]
fn a_short_latency_run_reports_capture_to_gpu_done_and_writes_its_report() {
    let out = std::env::temp_dir().join(format!("lungdyn-latency-{}", std::process::id()));
    std::fs::create_dir_all(&out).expect("the output folder");
    let output = std::process::Command::new(bin("lungdyn"))
        .args([
            "latency",
            "--seconds",
            "3",
            "--warmup",
            "0.5",
            "--mesh",
            "1000",
            "--load",
            "cpu:1,mem:8",
            "--json",
            "--trace",
        ])
        .arg(out.join("run.trace.json"))
        .arg("--out")
        .arg(&out)
        .env(
            "WGPU_BACKEND",
            std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()),
        )
        .output()
        .expect("run lungdyn latency");
    let err = String::from_utf8_lossy(&output.stderr);
    if err.contains("no GPU adapter") {
        lungdyn_needs::missing(lungdyn_needs::Need::Gpu, &err);
        return;
    }
    assert!(output.status.success(), "{err}");
    let v: serde_json::Value =
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("JSON: {e}: {err}"));
    let num = |k: &str| {
        v[k].as_f64()
            .unwrap_or_else(|| panic!("{k} missing or not a number: {v}"))
    };
    let frames = num("frames");
    assert!(frames > 0.0, "{v}");
    let submit = num("capture_to_submit_p99_ms");
    let gpu_done = num("capture_to_gpu_done_p99_ms");
    assert!(submit > 0.0 && submit.is_finite(), "{v}");
    assert!(
        gpu_done >= submit,
        "the GPU finishes after the submit: {gpu_done} < {submit}"
    );
    let misses = num("deadline_misses");
    assert_eq!(
        misses,
        num("late_frames") + num("missed_frame_slots"),
        "{v}"
    );
    let charged: f64 = v["deadline_miss_stages"]
        .as_array()
        .expect("deadline_miss_stages")
        .iter()
        .map(|s| s["misses"].as_f64().unwrap())
        .sum();
    assert_eq!(charged, misses, "every miss names a stage: {v}");
    assert!(v["largest_mesh_vertices"].is_null(), "no sweep: {v}");
    assert_eq!(v["mesh_vertices"].as_u64(), Some(1000));
    assert_eq!(v["load"]["cpu_threads"].as_u64(), Some(1));
    // Every hop row is ordered p50 <= p99 <= p99.9 <= max, and the frame's GPU row is there.
    let rows = v["rows"].as_array().expect("rows");
    for r in rows {
        let q: Vec<f64> = ["p50_ms", "p99_ms", "p99_9_ms", "max_ms"]
            .iter()
            .map(|k| r[*k].as_f64().unwrap())
            .collect();
        assert!(q.windows(2).all(|w| w[0] <= w[1]), "{r}");
    }
    assert!(rows.iter().any(|r| r["hop"] == "submit -> GPU done"), "{v}");
    assert!(
        v["signal_arrival_to_gpu_done_p99_ms"].is_null(),
        "no signal: {v}"
    );
    // Each process's period and CPU time.
    let procs = v["processes"].as_array().expect("processes");
    assert_eq!(procs.len(), 3, "{v}");
    for p in procs {
        // /proc counts CPU time in clock ticks (10 ms): a process that idles most of a 3 s run may
        // read 0; the renderer draws every frame and never does.
        let cpu = p["cpu_s"]
            .as_f64()
            .unwrap_or_else(|| panic!("no cpu_s: {p}"));
        assert!(
            cpu >= 0.0 && (cpu > 0.0 || p["process"] != "renderer"),
            "{p}"
        );
        assert!(p["intervals"].as_u64().is_some_and(|n| n > 0), "{p}");
    }
    // The report links the plot, which exists beside it.
    let md = std::fs::read_to_string(out.join("latency.md")).expect("latency.md");
    assert!(md.contains("](latency.png)"), "{md}");
    assert!(md.contains("capture -> GPU done"), "{md}");
    for f in ["latency.png", "latency.svg", "latency.json"] {
        assert!(out.join(f).is_file(), "{f} missing in {}", out.display());
    }
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("latency.json")).unwrap()).unwrap();
    assert_eq!(written["frames"], v["frames"]);
    assert_merged_trace(&out.join("run.trace.json"));
    let _ = std::fs::remove_dir_all(&out);
}

/// The merged trace is one Chrome trace: every process named, complete ("X") spans from all three
/// processes with their pid and tid, on one clock (CLOCK_MONOTONIC microseconds).
fn assert_merged_trace(path: &std::path::Path) {
    let text = std::fs::read_to_string(path).expect("the merged trace");
    let v: serde_json::Value = serde_json::from_str(&text).expect("the trace is JSON");
    let events = v["traceEvents"].as_array().expect("traceEvents");
    let mut names = std::collections::HashMap::new();
    for e in events.iter().filter(|e| e["ph"] == "M") {
        names.insert(
            e["pid"].as_u64().unwrap(),
            e["args"]["name"].as_str().unwrap().to_string(),
        );
    }
    let mut roles: Vec<&str> = names.values().map(String::as_str).collect();
    roles.sort_unstable();
    assert_eq!(roles, ["engine", "renderer", "tracker-bridge"], "{names:?}");
    let mut spans_of = std::collections::HashMap::<&str, Vec<&str>>::new();
    for e in events.iter().filter(|e| e["ph"] == "X") {
        let pid = e["pid"].as_u64().expect("pid");
        assert!(e["tid"].as_u64().is_some_and(|t| t > 0), "{e}");
        let ts = e["ts"].as_f64().expect("ts");
        let dur = e["dur"].as_f64().expect("dur");
        assert!(ts > 0.0 && dur >= 0.0, "{e}");
        let role = names
            .get(&pid)
            .unwrap_or_else(|| panic!("span of an unnamed pid: {e}"));
        spans_of
            .entry(role.as_str())
            .or_default()
            .push(e["name"].as_str().unwrap());
    }
    for (role, span) in [
        ("tracker-bridge", "poll source"),
        ("engine", "tick"),
        ("renderer", "GPU wait"),
    ] {
        let spans = spans_of
            .get(role)
            .unwrap_or_else(|| panic!("no spans of the {role}"));
        assert!(
            spans.contains(&span),
            "{role}: no {span:?} span in {spans:?}"
        );
    }
}

/// With a breathing signal (`--breathing trace:FILE`, replayed live) the harness measures from the
/// newest sample's arrival to the GPU done of the frame made with it (issue 35), beside capture ->
/// GPU done: a sample arrives at most a sample period before the tracker frame that carries it.
#[test]
fn a_run_with_a_breathing_signal_measures_signal_arrival_to_gpu_done() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let out = std::env::temp_dir().join(format!("lungdyn-latency-signal-{}", std::process::id()));
    std::fs::create_dir_all(&out).expect("the output folder");
    // A 20 s chest trace at 25 Hz, 3 s breaths (synthetic, written for the test).
    let trace = out.join("trace.csv");
    let mut csv = String::from("time_s,amplitude_mm\n");
    for k in 0..500 {
        let t = k as f64 * 0.04;
        let v = 4.0 * (1.0 - (2.0 * std::f64::consts::PI * t / 3.0).cos());
        csv += &format!("{t:.3},{v:.4}\n");
    }
    std::fs::write(&trace, csv).unwrap();
    let output = std::process::Command::new(bin("lungdyn"))
        .args([
            "latency",
            "--seconds",
            "4",
            "--warmup",
            "0.5",
            "--mesh",
            "1000",
            "--json",
        ])
        .arg("--breathing")
        .arg(format!("trace:{}", trace.display()))
        .arg("--out")
        .arg(&out)
        .output()
        .expect("run lungdyn latency");
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{err}");
    let v: serde_json::Value =
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("JSON: {e}: {err}"));
    let p50 = v["signal_arrival_to_gpu_done_p50_ms"]
        .as_f64()
        .unwrap_or_else(|| panic!("the signal row: {v}"));
    let p99 = v["signal_arrival_to_gpu_done_p99_ms"].as_f64().unwrap();
    assert!(p50 > 0.0 && p50 <= p99 && p99 < 5_000.0, "{v}");
    let row = v["rows"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["hop"] == "signal arrival -> GPU done")
        .unwrap_or_else(|| panic!("the row: {v}"))
        .clone();
    let frames = v["frames"].as_u64().unwrap();
    let unmatched = v["signal_frames_unmatched"].as_u64().unwrap();
    assert!(unmatched < frames / 2, "most frames matched: {v}");
    assert!(row["count"].as_u64().unwrap() > 0, "{row}");
    let md = std::fs::read_to_string(out.join("latency.md")).expect("latency.md");
    assert!(md.contains("signal arrival -> GPU done"), "{md}");
}

#[test]
fn bad_latency_arguments_fail_before_any_work() {
    assert_clean_failure(&["latency", "--load", "cpu:0"], "cpu:0 must be 1..256");
    assert_clean_failure(&["latency", "--mesh", "5"], "--mesh");
    assert_clean_failure(&["latency", "--seconds=-1"], "--seconds -1");
    assert_clean_failure(
        &[
            "latency",
            "--sweep",
            "--sweep-min",
            "9000",
            "--sweep-max",
            "8000",
        ],
        "--sweep-min 9000 must be below --sweep-max 8000",
    );
}

/// In a window the frame's last time point is its present: capture -> present is measured, after
/// GPU done, and its own hop row is there.
#[test]
fn a_windowed_run_measures_capture_to_present() {
    if renderer::gpu::Gpu::for_tests().is_none() || !lungdyn_tests::xvfb_available() {
        return;
    }
    let out = std::env::temp_dir().join(format!("lungdyn-latency-window-{}", std::process::id()));
    let output = std::process::Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1024x768x24"])
        .arg(bin("lungdyn"))
        .args([
            "latency",
            "--window",
            "--seconds",
            "2",
            "--warmup",
            "0.5",
            "--mesh",
            "1000",
            "--json",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("run xvfb-run lungdyn latency --window");
    let err = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{err}");
    let v: serde_json::Value =
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("JSON: {e}: {err}"));
    assert_eq!(v["window"], true, "{v}");
    let present = v["capture_to_present_p99_ms"]
        .as_f64()
        .unwrap_or_else(|| panic!("no capture_to_present_p99_ms: {v}"));
    let gpu_done = v["capture_to_gpu_done_p99_ms"].as_f64().unwrap();
    assert!(
        present >= gpu_done,
        "present {present} before GPU done {gpu_done}"
    );
    let rows = v["rows"].as_array().unwrap();
    assert!(
        rows.iter().any(|r| r["hop"] == "GPU done -> present"),
        "{v}"
    );
    let _ = std::fs::remove_dir_all(&out);
}
