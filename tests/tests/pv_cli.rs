//! `lungdyn pv`: simulate writes the loop and plots, fit recovers a simulated loop and writes
//! constants a scene can load, bad curves are refused with the file and line.

use std::process::Command;

use lungdyn_tests::{bin, lungdyn};

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("lungdyn-pv-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn simulate_then_fit_round_trips_and_a_scene_uses_the_fit() {
    let csv = tmp("sim.csv");
    let png = tmp("sim.png");
    let (ok, _, err) = lungdyn(&[
        "pv",
        "simulate",
        "--preset",
        "colebatch-human",
        "--samples",
        "60",
        "--out",
        csv.to_str().unwrap(),
        "--plot",
        png.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(png.exists() && png.with_extension("svg").exists());
    let text = std::fs::read_to_string(&csv).unwrap();
    assert!(text.starts_with("phase,t,pressure_cmh2o,volume_ml,damping"));
    assert_eq!(text.lines().count(), 1 + 2 * 60);

    let toml = tmp("fit.toml");
    let (ok, stdout, err) = lungdyn(&[
        "pv",
        "fit",
        "--input",
        csv.to_str().unwrap(),
        "--q",
        "2",
        "--c",
        "1",
        "--out",
        toml.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    // The simulated loop is the model's own curve: the fit reproduces it far inside 1 %.
    assert!(v["rms_percent"].as_f64().unwrap() < 0.05, "{v}");
    for phase in ["inhale", "exhale"] {
        assert!(
            v[phase]["constants"]["chi"].as_array().unwrap().len() == 7,
            "{v}"
        );
        assert!(v[phase]["rms_percent"].as_f64().unwrap() < 0.05);
    }
    assert!((v["boundary"]["frc_ml"].as_f64().unwrap() - 2400.0).abs() < 1e-6);

    // A scene naming the fitted constants runs the engine on them (the launcher bakes its lungs).
    let scene = tmp("scene.toml");
    let resolved = lungdyn_tests::prepared_scene(
        "pvscene",
        &format!(
            "[pv]\nconstants = {:?}\n[lungs]\nvertices = 1000\n",
            tmp("fit.toml").to_str().unwrap()
        ),
    );
    let text = std::fs::read_to_string(&resolved).unwrap();
    assert!(text.contains("fit.toml"), "{text}");
    let out = Command::new(bin("engine"))
        .args([
            "--instance",
            &format!("pvscene-{}", std::process::id()),
            "--seconds",
            "0.3",
            "--scene",
        ])
        .arg(&resolved)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    std::fs::write(&scene, "[pv]\nconstants = \"missing.toml\"\n").unwrap();
    let out = Command::new(bin("engine"))
        .args(["--seconds", "0.1", "--scene"])
        .arg(&scene)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("[pv] constants"));
    let services = transport::Instance::new(&format!("pvscene-{}", std::process::id())).unwrap();
    services.remove_leftovers();
}

#[test]
fn bad_curve_files_are_refused_with_file_and_line() {
    let csv = tmp("bad.csv");
    std::fs::write(&csv, "pressure,volume\n0,2400\n1,NaN\n2,2600\n").unwrap();
    let (ok, _, err) = lungdyn(&["pv", "fit", "--input", csv.to_str().unwrap()]);
    assert!(
        !ok && err.contains("bad.csv: line 3") && err.contains("finite"),
        "{err}"
    );
    std::fs::write(&csv, "pressure,volume\n0,2400\n1,2500\n2,2600\n").unwrap();
    let (ok, _, err) = lungdyn(&["pv", "fit", "--input", csv.to_str().unwrap()]);
    assert!(
        !ok && err.contains("samples; a fit needs at least"),
        "{err}"
    );
    std::fs::write(
        &csv,
        "pressure,volume\n0,2400\n1,2400\n2,2400\n3,2400\n4,2400\n",
    )
    .unwrap();
    let (ok, _, err) = lungdyn(&["pv", "fit", "--input", csv.to_str().unwrap()]);
    assert!(!ok && err.contains("no volume change"), "{err}");
    let (ok, _, err) = lungdyn(&["pv", "fit", "--input", "/nonexistent/curve.csv"]);
    assert!(!ok && err.contains("/nonexistent/curve.csv"), "{err}");
    let (ok, _, err) = lungdyn(&["pv", "simulate", "--preset", "nope", "--out", "/tmp/x.csv"]);
    assert!(!ok && err.contains("unknown PV preset"), "{err}");
    let (ok, _, err) = lungdyn(&[
        "pv",
        "simulate",
        "--chi-inhale",
        "1,2",
        "--out",
        tmp("x.csv").to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("odd number N of control constants"),
        "{err}"
    );
    let (ok, _, err) = lungdyn(&[
        "pv",
        "simulate",
        "--out",
        tmp("y.csv").to_str().unwrap(),
        "--plot",
        tmp("y.jpg").to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("must end in .png"), "{err}");
    assert!(!err.contains("panicked"));
}

/// `lungdyn pv recording` on a recording whose pressure column is in kPa under a cmH2O header
/// (every sample in range; a compliance of ≈ 500 ml/cmH2O) exits non-zero naming the file, the
/// figures and the unit the column is in; the same file with the right header is read.
#[test]
fn a_recording_with_a_mislabelled_pressure_unit_is_refused_with_the_unit_named() {
    let rec = lung_model::recording::Synthetic {
        breaths: 4,
        ..Default::default()
    }
    .recording();
    let write = |name: &str, header: &str| {
        let mut s = format!("time_s,flow_L/s,{header}\n");
        for i in 0..rec.t_s.len() {
            s.push_str(&format!(
                "{},{},{}\n",
                rec.t_s[i],
                rec.flow_lps[i],
                rec.paw_cmh2o[i] / 10.197_162
            ));
        }
        let p = tmp(name);
        std::fs::write(&p, s).unwrap();
        p
    };
    let wrong = write("kpa_as_cmh2o.csv", "paw_cmH2O");
    let (ok, _, err) = lungdyn(&["pv", "recording", wrong.to_str().unwrap()]);
    assert!(!ok, "a kPa column read as cmH2O was accepted");
    assert!(
        err.contains("kpa_as_cmh2o.csv")
            && err.contains("compliance")
            && err.contains("is the column in kPa?"),
        "{err}"
    );
    let right = write("kpa.csv", "paw_kPa");
    let (ok, _, err) = lungdyn(&["pv", "recording", right.to_str().unwrap(), "--json"]);
    assert!(ok, "{err}");
}
