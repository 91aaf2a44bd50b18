//! `lungdyn latency`: a short run's JSON has the keys the harness promises and its figures are
//! consistent with each other (never a wall-clock threshold: the machine may be shared).

use lungdyn_tests::{assert_clean_failure, bin};

#[test]
fn a_short_latency_run_reports_capture_to_gpu_done_and_writes_its_report() {
    let out = std::env::temp_dir().join(format!("lungdyn-latency-{}", std::process::id()));
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
            "--out",
        ])
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
    // Each process's period and CPU time.
    let procs = v["processes"].as_array().expect("processes");
    assert_eq!(procs.len(), 3, "{v}");
    for p in procs {
        assert!(p["cpu_s"].as_f64().is_some_and(|c| c > 0.0), "{p}");
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
    let _ = std::fs::remove_dir_all(&out);
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
