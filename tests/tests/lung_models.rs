//! Patient lung models end to end through the command line: a mesh bakes into a kernel that
//! `kernel inspect` verifies and the demo renders breathing; `fit-motion` turns corresponding points
//! into constants `bake --motion` uses; bad files fail clearly.

use std::path::{Path, PathBuf};

use glam::DVec3;
use lungdyn_tests::{assert_clean_failure as run_err, lungdyn, unique_instance};

fn workdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lungdyn-models-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn json(out: &str) -> serde_json::Value {
    serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("not JSON ({e}): {out}"))
}

fn run_ok(args: &[&str]) -> String {
    let (ok, out, err) = lungdyn(args);
    assert!(ok, "{args:?} failed: {err}");
    assert!(!err.contains("panicked"), "{err}");
    out
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn a_patient_mesh_bakes_into_a_kernel_that_the_demo_renders() {
    let d = workdir("bake");
    let mesh = d.join("patient_left.ply");
    let g = json(&run_ok(&[
        "mesh",
        "generate",
        "--lung",
        "left",
        "--vertices",
        "3000",
        "--out",
        s(&mesh),
        "--json",
    ]));
    let generated = g["vertices"].as_u64().unwrap();
    assert!(generated >= 3000, "{g}");
    let kernel = d.join("patient_left.kernel");
    let b = json(&run_ok(&[
        "bake",
        "--mesh",
        s(&mesh),
        "--lung",
        "left",
        "--out",
        s(&kernel),
        "--json",
    ]));
    assert_eq!(
        b["vertices"].as_u64(),
        Some(generated),
        "the bake keeps every vertex"
    );
    assert!(b["mean_row_nnz"].as_f64().unwrap() > 10.0, "{b}");
    let trunc = b["truncated_force"].as_f64().unwrap();
    assert!(trunc > 0.0 && trunc < 1e-2, "{b}");
    assert!(b["conservation_error_max"].as_f64().unwrap() < 1e-9);
    assert!(b["seconds"].as_f64().unwrap() > 0.0);

    let i = json(&run_ok(&["kernel", "inspect", s(&kernel), "--json"]));
    assert_eq!(i["meta"]["side"], "left");
    assert_eq!(i["meta"]["vertices"].as_u64(), Some(generated));
    assert_eq!(i["meta"]["nnz"], b["nnz"]);
    let text = run_ok(&["kernel", "inspect", s(&kernel)]);
    assert!(text.contains("checksums OK"), "{text}");
    // The volumes the bake checked free of folds travel in the kernel; both commands say them.
    let ff = &b["fold_free"];
    assert_eq!(i["meta"]["fold_free"], *ff);
    let (above, searched) = (ff["above_ml"].as_f64(), ff["searched_above_ml"].as_f64());
    assert!(above.unwrap() > 0.0 && above <= searched, "{b}");
    assert!(ff["below_ml"].as_f64().unwrap() > 0.0, "{b}");
    assert!(
        text.contains("fold-free (supine, precomputed field): "),
        "{text}"
    );
    let png = d.join("kernel.png");
    run_ok(&["kernel", "inspect", s(&kernel), "--plot", s(&png)]);
    let img = image::open(&png).expect("the kernel picture is a PNG");
    assert!(img.width() >= 1000 && img.height() >= 500);
    run_err(
        &[
            "kernel",
            "inspect",
            s(&kernel),
            "--plot",
            s(&d.join("k.jpg")),
        ],
        ".png",
    );

    // The deformed state at +250 ml, exported as a mesh, encloses exactly that much more.
    let deformed = d.join("left_plus250.obj");
    let e = json(&run_ok(&[
        "kernel",
        "export",
        s(&kernel),
        "--delta-ml",
        "250",
        "--out",
        s(&deformed),
        "--json",
    ]));
    let got = e["volume_ml"].as_f64().unwrap() - e["start_volume_ml"].as_f64().unwrap();
    assert!((got - 250.0).abs() < 0.1, "{e}");
    assert!(e["max_displacement_mm"].as_f64().unwrap() > 1.0);
    // At +250 ml the generated left lung's linear field folds the surface near the base (a few
    // crossing triangle pairs): reported, and `mesh check` would refuse to bake it. A smaller change
    // does not fold and round-trips through `mesh check`.
    assert!(e["self_intersections"].is_u64(), "{e}");
    let small = d.join("left_plus100.obj");
    let e = json(&run_ok(&[
        "kernel",
        "export",
        s(&kernel),
        "--delta-ml",
        "100",
        "--out",
        s(&small),
        "--json",
    ]));
    assert_eq!(e["self_intersections"].as_u64(), Some(0), "{e}");
    let c = json(&run_ok(&["mesh", "check", "--mesh", s(&small), "--json"]));
    assert!((c["volume_ml"].as_f64().unwrap() - e["volume_ml"].as_f64().unwrap()).abs() < 0.5);
    run_err(
        &[
            "kernel",
            "export",
            s(&kernel),
            "--delta-ml",
            "nan",
            "--out",
            s(&deformed),
        ],
        "--delta-ml",
    );

    // A scene that runs the patient's left lung from its kernel; the demo must draw it breathing.
    let scene = d.join("patient.toml");
    std::fs::write(
        &scene,
        "[lungs]\nsides = [\"left\"]\n[lungs.kernels]\nleft = \"patient_left.kernel\"\n",
    )
    .unwrap();
    let out = d.join("out");
    let inst = unique_instance("kernel");
    let r = json(&run_ok(&[
        "demo",
        "--seconds",
        "2",
        "--snapshots",
        "0",
        "--scene",
        s(&scene),
        "--out",
        s(&out),
        "--instance",
        &inst,
        "--json",
    ]));
    lungdyn_tests::assert_demo_report_is_consistent(&r, "");
    assert_eq!(r["kernels"][0]["baked_now"], false);
    assert!(r["kernels"][0]["path"]
        .as_str()
        .unwrap()
        .ends_with("patient_left.kernel"));
    assert!(r["volume_max_ml"].as_f64().unwrap() > r["volume_min_ml"].as_f64().unwrap());
    assert_eq!(r["remaining_files"].as_u64(), Some(0));

    // Using the left kernel for the right lung is refused, by name.
    std::fs::write(
        d.join("wrong.toml"),
        "[lungs]\nsides = [\"right\"]\n[lungs.kernels]\nright = \"patient_left.kernel\"\n",
    )
    .unwrap();
    let inst = unique_instance("wrong");
    run_err(
        &[
            "demo",
            "--seconds",
            "1",
            "--snapshots",
            "0",
            "--scene",
            s(&d.join("wrong.toml")),
            "--out",
            s(&out),
            "--instance",
            &inst,
            "--startup-timeout",
            "20",
        ],
        "kernel is of the left lung",
    );
}

#[test]
fn bad_meshes_kernels_and_options_fail_clearly() {
    let d = workdir("bad");
    let garbage = d.join("garbage.obj");
    std::fs::write(&garbage, b"\x00\x01binary junk\xff\xfe").unwrap();
    let out = d.join("x.kernel");
    run_err(
        &[
            "bake",
            "--mesh",
            s(&garbage),
            "--lung",
            "left",
            "--out",
            s(&out),
        ],
        "garbage.obj",
    );
    run_err(
        &[
            "bake",
            "--mesh",
            "/nonexistent.stl",
            "--lung",
            "left",
            "--out",
            s(&out),
        ],
        "nonexistent.stl",
    );
    let mesh = d.join("m.obj");
    run_ok(&[
        "mesh",
        "generate",
        "--lung",
        "right",
        "--vertices",
        "200",
        "--out",
        s(&mesh),
    ]);
    run_err(
        &[
            "bake",
            "--mesh",
            s(&mesh),
            "--lung",
            "right",
            "--out",
            s(&d.join("x.bin")),
        ],
        ".kernel",
    );
    run_err(
        &[
            "bake",
            "--mesh",
            s(&mesh),
            "--lung",
            "right",
            "--tolerance",
            "0",
            "--out",
            s(&out),
        ],
        "--tolerance 0",
    );
    assert!(!out.exists(), "a failed bake must not leave a file");

    run_ok(&[
        "bake",
        "--mesh",
        s(&mesh),
        "--lung",
        "right",
        "--out",
        s(&out),
    ]);
    let mut bytes = std::fs::read(&out).unwrap();
    let good = bytes.clone();
    let n = bytes.len();
    bytes[n - 100] ^= 0x40;
    let bad = d.join("flipped.kernel");
    std::fs::write(&bad, &bytes).unwrap();
    run_err(&["kernel", "inspect", s(&bad)], "checksum mismatch");
    let cut = d.join("cut.kernel");
    std::fs::write(&cut, &good[..n / 2]).unwrap();
    run_err(&["kernel", "inspect", s(&cut)], "truncated");
    run_err(&["kernel", "inspect", s(&mesh)], "not a lungdyn kernel");
    let empty = d.join("empty.kernel");
    std::fs::write(&empty, b"").unwrap();
    run_err(&["kernel", "inspect", s(&empty)], "empty");
    // Bake over an existing kernel fails → the old file is untouched.
    run_err(
        &[
            "bake",
            "--mesh",
            s(&garbage),
            "--lung",
            "right",
            "--out",
            s(&out),
        ],
        "garbage.obj",
    );
    assert_eq!(std::fs::read(&out).unwrap(), good);
}

/// Points of a generated lung moved by a known direction model (body frame, mm).
fn known_motion(
    side: lung_model::mesh::Side,
    n: usize,
    c: &[f64; 9],
    scale: f64,
) -> (Vec<DVec3>, Vec<DVec3>) {
    let a: Vec<DVec3> = lung_model::mesh::generate::lung(side, n)
        .unwrap()
        .positions
        .iter()
        .map(|p| DVec3::from(p.map(|v| v as f64)))
        .collect();
    let lo = a.iter().fold(DVec3::splat(f64::INFINITY), |m, p| m.min(*p));
    let hi = a
        .iter()
        .fold(DVec3::splat(f64::NEG_INFINITY), |m, p| m.max(*p));
    let b = a
        .iter()
        .map(|&p| {
            let u = (p - lo) / (hi - lo);
            let x = match side {
                lung_model::mesh::Side::Left => u.x,
                lung_model::mesh::Side::Right => 1.0 - u.x,
            };
            let nrm = DVec3::new(x, u.y, 1.0 - u.z);
            p + scale * lung_bake::motion_fit::model_displacement(nrm, c, side)
        })
        .collect();
    (a, b)
}

fn write_points(path: &Path, pts: &[DVec3], spacing: [f64; 3]) {
    let mut t = String::from("# x y z\n");
    for p in pts {
        t += &format!(
            "{} {} {}\n",
            // Voxel indices start at 0: shift the lungs into positive indices (fits are translation
            // invariant, so the constants do not change).
            p.x / spacing[0] + 500.0,
            p.y / spacing[1] + 500.0,
            p.z / spacing[2] + 500.0
        );
    }
    std::fs::write(path, t).unwrap();
}

#[test]
fn fit_motion_recovers_known_constants_and_its_output_bakes() {
    use lung_model::mesh::Side;
    let d = workdir("fit");
    let truth = [2.0, 0.6, 5.0, 0.5, 12.0, 2.0, 0.01, 0.95, 0.07];
    let (ra, rb) = known_motion(Side::Right, 600, &truth, 1.0);
    let (la, lb) = known_motion(Side::Left, 600, &truth, 1.0);
    let (_, rc) = known_motion(Side::Right, 600, &truth, 2.0);
    let (_, lc) = known_motion(Side::Left, 600, &truth, 2.0);
    let cat = |x: &[DVec3], y: &[DVec3]| x.iter().chain(y).copied().collect::<Vec<_>>();
    let spacing = [0.8, 0.8, 2.5];
    write_points(&d.join("a.txt"), &cat(&ra, &la), spacing);
    write_points(&d.join("b.txt"), &cat(&rb, &lb), spacing);
    write_points(&d.join("c.txt"), &cat(&rc, &lc), spacing);
    let motion = d.join("motion.toml");
    let f = json(&run_ok(&[
        "fit-motion",
        "--from",
        s(&d.join("a.txt")),
        "--to",
        s(&d.join("b.txt")),
        "--also",
        s(&d.join("c.txt")),
        "--frame",
        "voxel",
        "--voxel-axes",
        "R>L,P>A,I>S",
        "--index-base",
        "0",
        "--spacing",
        "0.8,0.8,2.5",
        "--out",
        s(&motion),
        "--json",
    ]));
    assert_eq!(f["chosen"], "power", "the truth is a power law: {f}");
    // Held out, points outside the training box are clamped: not exact, but far inside the noise.
    assert!(f["cv_mean_error_mm"].as_f64().unwrap() < 0.01, "{f}");
    assert!(f["frame_warning"].is_null(), "{f}");
    let names: Vec<&str> = f["models"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["model"].as_str().unwrap())
        .collect();
    assert_eq!(names, vec!["power", "affine", "poly", "rbf"]);
    assert!(f["mean_error_mm"].as_f64().unwrap() < 1e-3, "{f}");
    assert!(f["max_error_mm"].as_f64().unwrap() < 1e-2, "{f}");
    assert!(f["baseline_mean_mm"].as_f64().unwrap() > 2.0, "{f}");
    assert!(
        f["also"][0]["mean_error_mm"].as_f64().unwrap() < 1e-3,
        "{f}"
    );
    let lungs = f["lungs"].as_array().unwrap();
    assert_eq!(lungs.len(), 2);
    for l in lungs {
        let c: Vec<f64> = l["constants"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        for k in 0..6 {
            assert!(
                (c[k] - truth[k]).abs() < 1e-3,
                "{}: c{} = {}",
                l["lung"],
                k + 1,
                c[k]
            );
        }
        assert!((l["also"][0]["scale"].as_f64().unwrap() - 2.0).abs() < 1e-6);
    }
    // The written constants bake.
    let mesh = d.join("l.obj");
    run_ok(&[
        "mesh",
        "generate",
        "--lung",
        "left",
        "--vertices",
        "500",
        "--out",
        s(&mesh),
    ]);
    let k = json(&run_ok(&[
        "bake",
        "--mesh",
        s(&mesh),
        "--lung",
        "left",
        "--motion",
        s(&motion),
        "--out",
        s(&d.join("l.kernel")),
        "--json",
    ]));
    assert!(k["vertices"].as_u64().unwrap() > 0);
    let i = json(&run_ok(&[
        "kernel",
        "inspect",
        s(&d.join("l.kernel")),
        "--json",
    ]));
    let c1 = i["meta"]["settings"]["motion"]["c"][0].as_f64().unwrap();
    assert!((c1 - 2.0).abs() < 1e-3, "{c1}");

    // Bad point files, each against the good reference (the same file as both phases is refused as
    // such before it is read), with what must be said.
    for (name, text, needle) in [
        ("short.txt", "1 2 3\n4 5 6\n", "must correspond"),
        ("nan.txt", "1 2 3\n4 x 6\n", "nan.txt:2"),
        ("two.txt", "1 2\n", "three numbers"),
        ("empty.txt", "# nothing\n", "no points"),
    ] {
        let bad = d.join(name);
        std::fs::write(&bad, text).unwrap();
        run_err(
            &["fit-motion", "--from", s(&d.join("a.txt")), "--to", s(&bad)],
            needle,
        );
    }
    // One lung's points at both phases: which lung must be said.
    write_points(&d.join("one.txt"), &la, [1.0; 3]);
    write_points(&d.join("one_b.txt"), &lb, [1.0; 3]);
    run_err(
        &[
            "fit-motion",
            "--from",
            s(&d.join("one.txt")),
            "--to",
            s(&d.join("one_b.txt")),
        ],
        "--lung",
    );
    run_err(
        &[
            "fit-motion",
            "--from",
            s(&d.join("a.txt")),
            "--to",
            s(&d.join("b.txt")),
            "--spacing",
            "1,0,1",
        ],
        "--spacing",
    );
    // Voxel indices without saying how they run are refused, not read in a guessed frame.
    run_err(
        &[
            "fit-motion",
            "--from",
            s(&d.join("a.txt")),
            "--to",
            s(&d.join("b.txt")),
            "--spacing",
            "0.8,0.8,2.5",
        ],
        "--frame voxel",
    );
}

/// The same motion written in every frame lungdyn reads gives the same fit, to round-off; read in
/// a frame whose Z runs the wrong way it gives a loud frame warning.
#[test]
fn one_motion_in_every_frame_gives_the_same_constants_and_a_wrong_frame_is_said() {
    use lung_model::mesh::Side;
    let d = workdir("frames");
    let truth = [2.0, 0.6, 5.0, 0.5, 12.0, 2.0, 0.01, 0.95, 0.07];
    let (ra, rb) = known_motion(Side::Right, 600, &truth, 1.0);
    let (la, lb) = known_motion(Side::Left, 600, &truth, 1.0);
    let a: Vec<DVec3> = ra.iter().chain(&la).copied().collect();
    let b: Vec<DVec3> = rb.iter().chain(&lb).copied().collect();
    let spacing = DVec3::new(0.97, 0.97, 2.5);
    let write = |name: &str, pts: &[DVec3], f: &dyn Fn(DVec3) -> DVec3| {
        let mut t = String::new();
        for p in pts {
            let q = f(*p);
            t += &format!("{}\t{}\t{}\r\n", q.x, q.y, q.z);
        }
        std::fs::write(d.join(name), t).unwrap();
    };
    // DIR-Lab voxels: 1-based, columns right → left, rows anterior → posterior, slices downwards.
    let voxel = |p: DVec3| {
        DVec3::new(
            p.x / spacing.x + 300.0,
            -p.y / spacing.y + 300.0,
            -p.z / spacing.z + 300.0,
        )
    };
    let frames: Vec<(&str, Vec<&str>, Box<dyn Fn(DVec3) -> DVec3>)> = vec![
        ("body", vec![], Box::new(|p| p)),
        (
            "lps",
            vec!["--frame", "lps"],
            Box::new(|p: DVec3| DVec3::new(p.x, -p.y, p.z)),
        ),
        (
            "ras",
            vec!["--frame", "ras"],
            Box::new(|p: DVec3| DVec3::new(-p.x, p.y, p.z)),
        ),
        (
            "dirlab",
            vec!["--format", "dirlab", "--spacing", "0.97,0.97,2.5"],
            Box::new(voxel),
        ),
    ];
    let mut constants: Vec<Vec<f64>> = Vec::new();
    for (name, flags, f) in &frames {
        write(&format!("{name}_a.txt"), &a, f);
        write(&format!("{name}_b.txt"), &b, f);
        let from = d.join(format!("{name}_a.txt"));
        let to = d.join(format!("{name}_b.txt"));
        let mut args = vec![
            "fit-motion",
            "--from",
            s(&from),
            "--to",
            s(&to),
            "--model",
            "power",
            "--json",
        ];
        args.extend(flags.iter().copied());
        let r = json(&run_ok(&args));
        assert!(r["frame_warning"].is_null(), "{name}: {r}");
        let c: Vec<f64> = r["lungs"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|l| {
                l["constants"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
            })
            .collect();
        constants.push(c);
    }
    for c in &constants[1..] {
        for (x, y) in c.iter().zip(&constants[0]) {
            assert!(
                (x - y).abs() < 1e-6 * (1.0 + y.abs()),
                "{c:?} vs {:?}",
                constants[0]
            );
        }
    }
    // The DIR-Lab files read as if slices ran upwards: Z is reversed, the fit still runs, and says so.
    let r = json(&run_ok(&[
        "fit-motion",
        "--from",
        s(&d.join("dirlab_a.txt")),
        "--to",
        s(&d.join("dirlab_b.txt")),
        "--frame",
        "voxel",
        "--voxel-axes",
        "R>L,A>P,I>S",
        "--index-base",
        "1",
        "--spacing",
        "0.97,0.97,2.5",
        "--json",
    ]));
    let w = r["frame_warning"]
        .as_str()
        .unwrap_or_else(|| panic!("no warning: {r}"));
    assert!(w.contains("reversed"), "{w}");
    assert!(r["frame_check"]["rho_z"].as_f64().unwrap() > 0.0);
}

/// A generated `lung` at `vertices`, baked with motion constants `c`, and its surface exported at each
/// (volume change in ml, file name): the reference mesh and the phases.
fn kernel_phases(
    d: &Path,
    lung: &str,
    vertices: usize,
    c: [f64; 9],
    deltas: &[(&str, &str)],
) -> (PathBuf, Vec<PathBuf>) {
    let mesh = d.join(format!("{lung}_{vertices}.ply"));
    let n = vertices.to_string();
    run_ok(&[
        "mesh",
        "generate",
        "--lung",
        lung,
        "--vertices",
        &n,
        "--out",
        s(&mesh),
    ]);
    let m = d.join(format!("{lung}_motion.toml"));
    std::fs::write(&m, format!("format = 1\n[{lung}]\nc = {c:?}\n")).unwrap();
    let k = d.join(format!("{lung}_{vertices}.kernel"));
    run_ok(&[
        "bake",
        "--mesh",
        s(&mesh),
        "--lung",
        lung,
        "--motion",
        s(&m),
        "--out",
        s(&k),
    ]);
    let phases = deltas
        .iter()
        .map(|(dv, name)| {
            let p = d.join(name);
            run_ok(&["kernel", "export", s(&k), "--delta-ml", dv, "--out", s(&p)]);
            p
        })
        .collect();
    (mesh, phases)
}

#[test]
fn two_meshes_with_the_same_vertices_give_the_whole_kernel_model_back() {
    // Phase B is the kernel's own deformation with known constants; fit-motion on the two meshes
    // fits the kernel's model through the operator and recovers all nine.
    let d = workdir("meshes");
    let (a, phases) = kernel_phases(
        &d,
        "left",
        2000,
        [0.09, 0.23, 0.4, 0.5, 0.1, 2.3, 0.2, 0.5, 0.3],
        &[("300", "b.obj")],
    );
    let b = &phases[0];
    let out = d.join("fitted.toml");
    let f = json(&run_ok(&[
        "fit-motion",
        "--from",
        s(&a),
        "--to",
        s(b),
        "--lung",
        "left",
        "--out",
        s(&out),
        "--json",
    ]));
    let l = &f["lungs"][0];
    let c: Vec<f64> = l["constants"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    // Same vertices at both phases: the kernel's whole model comes back, every constant.
    assert_eq!(f["mode"], "mesh");
    for (k, want) in [0.09, 0.23, 0.4, 0.5, 0.1, 2.3, 0.2, 0.5, 0.3]
        .iter()
        .enumerate()
    {
        assert!(
            (c[k] - want).abs() < 5e-3,
            "c{} = {} (want {want})",
            k + 1,
            c[k]
        );
    }
    assert!(l["mean_error_mm"].as_f64().unwrap() < 0.01, "{l}");
    assert!(l["baseline_mean_mm"].as_f64().unwrap() > 5.0, "{l}");
    assert!(std::fs::read_to_string(&out)
        .unwrap()
        .contains("fitted through the operator"));
}

#[test]
fn a_second_phase_surface_without_correspondences_is_fitted() {
    // The reference is a coarse segmentation, the targets a finer one moved by a kernel with known
    // constants (+300 ml, +450 ml): different vertices, so surface mode is chosen by itself.
    let d = workdir("surface");
    let (_, phases) = kernel_phases(
        &d,
        "right",
        6000,
        [0.12, 0.3, 0.4, 0.6, 0.15, 1.8, 0.1, 0.8, 0.1],
        &[("300", "b.ply"), ("450", "c.obj")],
    );
    let (b, c) = (&phases[0], &phases[1]);
    let a = d.join("a.obj");
    run_ok(&[
        "mesh",
        "generate",
        "--lung",
        "right",
        "--vertices",
        "1500",
        "--out",
        s(&a),
    ]);
    let out = d.join("fitted.toml");
    let f = json(&run_ok(&[
        "fit-motion",
        "--from",
        s(&a),
        "--to",
        s(b),
        "--also",
        s(c),
        "--lung",
        "right",
        "--out",
        s(&out),
        "--json",
    ]));
    assert_eq!(f["mode"], "surface");
    let base = f["baseline_mean_mm"].as_f64().unwrap();
    assert!(base > 3.0, "{f}");
    assert!(f["mean_error_mm"].as_f64().unwrap() < 0.1 * base, "{f}");
    let also = &f["lungs"][0]["also"][0];
    assert!(
        also["mean_error_mm"].as_f64().unwrap() < 0.1 * also["baseline_mean_mm"].as_f64().unwrap(),
        "{f}"
    );
    assert!((also["scale"].as_f64().unwrap() - 1.5).abs() < 0.1, "{f}");
    // A surface distance does not see motion along the surface, so the constants are not unique
    // (EQUATIONS §2.4); what is checked is that they reproduce the surfaces, and that they bake.
    let ka = d.join("a.kernel");
    run_ok(&[
        "bake",
        "--mesh",
        s(&a),
        "--lung",
        "right",
        "--motion",
        s(&out),
        "--out",
        s(&ka),
    ]);
    assert!(std::fs::read_to_string(&out)
        .unwrap()
        .contains("surface mode"));
    run_err(
        &[
            "fit-motion",
            "--from",
            s(&d.join("x.txt")),
            "--to",
            s(b),
            "--surface",
        ],
        "two meshes",
    );
}
