//! `lungdyn mesh from-mask` through the real binary: a two-lung label image made here (the built-in
//! lungs voxelised and written as NIfTI-1 by `lung_bake::mask::synthetic`) becomes a
//! right lung that `mesh check` accepts and `bake` bakes with the mesh's own lobes; bad inputs are
//! refused with a non-zero exit, no panic, a message naming the problem and no output written (an
//! existing file at `--out` left as it was); `--help` names the formats, `--axes` and the body
//! frame.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use glam::DVec3;
use lung_bake::mask::synthetic::{both_lungs, in_file_order, nifti, Body};
use lung_bake::mask::volume::Axes;
use lung_model::mesh::{anatomy, lobes, Side, TriMesh};
use lungdyn_tests::bin;

/// The keys `--json` must print.
const KEYS: [&str; 12] = [
    "vertices",
    "volume_ml",
    "mask_volume_ml",
    "genus_before",
    "genus_after",
    "lobes_from",
    "distance_to_mask",
    "frame",
    "labels_used",
    "convention",
    "sides_from",
    "warnings",
];

/// Vertices asked of from-mask (small, so bake is quick).
const VERTICES: &str = "2000";

/// A fresh folder for one test, removed by `Tmp::drop` when the test passed.
struct Tmp(PathBuf);

impl Tmp {
    fn new(tag: &str) -> Self {
        let d =
            std::env::temp_dir().join(format!("lungdyn-from-mask-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        Tmp(d)
    }
    fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
    fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.path(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

impl Drop for Tmp {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            std::fs::remove_dir_all(&self.0).ok();
        }
    }
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// One run of the binary.
struct Run {
    code: Option<i32>,
    stdout: String,
    stderr: String,
}

fn lungdyn(args: &[&str]) -> Run {
    let out = Command::new(bin("lungdyn"))
        .args(args)
        .output()
        .expect("run lungdyn");
    Run {
        code: out.status.code(),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// `lungdyn mesh from-mask` with `args`, expected to fail: a non-zero exit that is not a panic
/// (101) nor a signal, no "panicked" on stderr, every one of `words` in stderr, and nothing at
/// `out` afterwards.
fn refused(case: &str, args: &[&str], out: &Path, words: &[&str]) -> String {
    let mut full = vec!["mesh", "from-mask"];
    full.extend_from_slice(args);
    refused_command(case, &full, out, words)
}

/// [`refused`] for any `lungdyn` command line `full`.
fn refused_command(case: &str, full: &[&str], out: &Path, words: &[&str]) -> String {
    let r = lungdyn(full);
    assert!(
        matches!(r.code, Some(c) if c != 0 && c != 101),
        "{case}: exit {:?} (want non-zero, not 101, not a signal)\nargs {full:?}\nstdout: {}\nstderr: {}",
        r.code,
        r.stdout,
        r.stderr
    );
    assert!(
        !r.stderr.contains("panicked"),
        "{case}: panicked: {}",
        r.stderr
    );
    for w in words {
        assert!(
            r.stderr.contains(w),
            "{case}: stderr lacks {w:?}:\n{}",
            r.stderr
        );
    }
    eprintln!("{case}: {}", r.stderr.trim());
    assert!(
        !out.exists(),
        "{case}: {} was written by a failed run",
        out.display()
    );
    r.stderr
}

// ---- Label volumes voxelised from the built-in lungs: lung_bake::mask::synthetic (the one copy
// ---- lung-bake's own mask tests use too).

const SPACING: [f64; 3] = [2.5, 2.5, 2.5];

/// Both lungs as one label (1), RAS voxel axes under an RAS sform: the bytes of a good .nii.
fn single_label_nii() -> &'static [u8] {
    static BYTES: OnceLock<Vec<u8>> = OnceLock::new();
    BYTES.get_or_init(|| {
        let body = both_lungs(SPACING, |_| 1, |_| 1).0;
        let (d, rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
        nifti(&body, Some(rows), &d)
    })
}

/// Both lungs with lungmask LTRCLobes labels (1 LUL, 2 LLL, 3 RUL, 4 RML, 5 RLL).
fn lobes_body() -> &'static Body {
    static BODY: OnceLock<Body> = OnceLock::new();
    BODY.get_or_init(|| {
        let r = anatomy::lung(Side::Right, 4000).unwrap();
        let l = anatomy::lung(Side::Left, 4000).unwrap();
        let fr = lobes::Fissures::adult(Side::Right);
        let fl = lobes::Fissures::adult(Side::Left);
        let (rb, lb) = (r.aabb(), l.aabb());
        let code = |side: Side, bb: &lung_model::mesh::Aabb, f: &lobes::Fissures, p: DVec3| match f
            .lobe_at(side, lobes::normalise(side, bb, p.to_array()))
        {
            lobes::Lobe::LeftUpper => 1u16,
            lobes::Lobe::LeftLower => 2,
            lobes::Lobe::RightUpper => 3,
            lobes::Lobe::RightMiddle => 4,
            _ => 5,
        };
        both_lungs(
            SPACING,
            |p| code(Side::Right, &rb, &fr, p),
            |p| code(Side::Left, &lb, &fl, p),
        )
        .0
    })
}

// ---- The tests.

#[test]
fn from_mask_makes_a_right_lung_that_mesh_check_accepts_and_bake_bakes_with_its_lobes() {
    let tmp = Tmp::new("ok");
    let nii = tmp.write("lungs.nii", single_label_nii());
    let ply = tmp.path("right.ply");
    let r = lungdyn(&[
        "mesh",
        "from-mask",
        s(&nii),
        "--lung",
        "right",
        "--vertices",
        VERTICES,
        "--out",
        s(&ply),
        "--json",
    ]);
    assert_eq!(r.code, Some(0), "from-mask failed: {}", r.stderr);
    assert!(!r.stderr.contains("panicked"), "{}", r.stderr);
    // One JSON object on stdout.
    let v: serde_json::Value = serde_json::from_str(r.stdout.trim())
        .unwrap_or_else(|e| panic!("stdout is not one JSON object ({e}): {:?}", r.stdout));
    let obj = v.as_object().expect("a JSON object");
    for key in KEYS {
        assert!(obj.contains_key(key), "--json lacks {key:?}: {v}");
    }
    let n = v["vertices"].as_u64().unwrap();
    assert!(
        (1000..=3000).contains(&n),
        "{n} vertices for {VERTICES} asked"
    );
    assert_eq!(v["genus_after"].as_i64(), Some(0), "{v}");
    assert_eq!(v["convention"].as_str(), Some("single"), "{v}");
    assert_eq!(v["sides_from"].as_str(), Some("components"), "{v}");
    assert_eq!(v["labels_used"], serde_json::json!([1]), "{v}");
    assert!(v["warnings"].is_array(), "{v}");
    let vol = v["volume_ml"].as_f64().unwrap();
    let mask_vol = v["mask_volume_ml"].as_f64().unwrap();
    assert!(
        vol > 500.0 && (vol / mask_vol - 1.0).abs() < 0.1,
        "surface {vol} ml vs mask {mask_vol} ml"
    );
    assert!(ply.is_file(), "{} not written", ply.display());

    // mesh check accepts it as a right lung.
    let c = lungdyn(&[
        "mesh",
        "check",
        "--mesh",
        s(&ply),
        "--lung",
        "right",
        "--json",
    ]);
    assert_eq!(c.code, Some(0), "mesh check refused it: {}", c.stderr);
    let cv: serde_json::Value = serde_json::from_str(c.stdout.trim())
        .unwrap_or_else(|e| panic!("mesh check --json ({e}): {:?}", c.stdout));
    assert_eq!(cv["euler"].as_i64(), Some(2), "{cv}");

    // bake takes the lobes from the PLY.
    let kernel = tmp.path("right.kernel");
    let b = lungdyn(&[
        "bake",
        "--mesh",
        s(&ply),
        "--lung",
        "right",
        "--out",
        s(&kernel),
        "--json",
    ]);
    assert_eq!(b.code, Some(0), "bake failed: {}", b.stderr);
    let bv: serde_json::Value = serde_json::from_str(b.stdout.trim())
        .unwrap_or_else(|e| panic!("bake --json ({e}): {:?}", b.stdout));
    assert_eq!(bv["lobes_from"].as_str(), Some("mesh"), "{bv}");
    assert!(kernel.is_file());
}

#[test]
fn unreadable_or_unknown_files_are_refused_without_output() {
    let tmp = Tmp::new("files");
    let good = single_label_nii();
    let out = tmp.path("unreadable.ply");
    let run = |case: &str, mask: &Path, words: &[&str]| {
        refused(
            case,
            &[
                s(mask),
                "--lung",
                "right",
                "--vertices",
                VERTICES,
                "--out",
                s(&out),
            ],
            &out,
            words,
        );
    };
    let missing = tmp.path("no-such-mask.nii");
    run(
        "missing file",
        &missing,
        &["no-such-mask.nii", "No such file"],
    );
    let folder = tmp.path("a-folder.nii");
    std::fs::create_dir_all(&folder).unwrap();
    run("a folder", &folder, &["a-folder.nii", "folder"]);
    let txt = tmp.write("lungs.txt", good);
    run(
        "unknown extension",
        &txt,
        &["lungs.txt", "unknown label image format"],
    );
    let cut = tmp.write("cut.nii", &good[..good.len() / 2]);
    run("truncated .nii", &cut, &["cut.nii", "cut short"]);
    // Header alone, cut inside it.
    let short = tmp.write("short.nii", &good[..200]);
    run("header cut short", &short, &["short.nii", "NIfTI"]);
}

#[test]
fn a_nifti_without_sform_or_qform_is_refused_naming_axes() {
    let tmp = Tmp::new("plain");
    let body = both_lungs(SPACING, |_| 1, |_| 1).0;
    let (d, _) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let plain = tmp.write("plain.nii", &nifti(&body, None, &d));
    let out = tmp.path("plain.ply");
    refused(
        "no sform/qform",
        &[
            s(&plain),
            "--lung",
            "right",
            "--vertices",
            VERTICES,
            "--out",
            s(&out),
        ],
        &out,
        &["plain.nii", "neither an sform nor a qform", "--axes"],
    );
}

#[test]
fn bad_options_are_refused_naming_the_option() {
    let tmp = Tmp::new("opts");
    let nii = tmp.write("opts.nii", single_label_nii());
    let out = tmp.path("opts.ply");
    let base = |extra: &[&'static str]| -> Vec<String> {
        let mut a: Vec<String> = vec![s(&nii).into(), "--lung".into(), "right".into()];
        a.extend(extra.iter().map(|x| x.to_string()));
        a
    };
    let go = |case: &str, args: Vec<String>, out: &Path, words: &[&str]| {
        let a: Vec<&str> = args.iter().map(String::as_str).collect();
        refused(case, &a, out, words);
    };
    let with_out = |mut a: Vec<String>, o: &Path| {
        a.push("--out".into());
        a.push(s(o).into());
        a
    };
    go(
        "--axes XYZ",
        with_out(base(&["--axes", "XYZ", "--vertices", VERTICES]), &out),
        &out,
        &["--axes", "XYZ"],
    );
    go(
        "--label absent",
        with_out(base(&["--label", "7", "--vertices", VERTICES]), &out),
        &out,
        &["--label 7", "no voxel holds 7"],
    );
    go(
        "--vertices 5",
        with_out(base(&["--vertices", "5"]), &out),
        &out,
        &["--vertices 5", "100 to 4,000,000"],
    );
    let stl = tmp.path("opts.stl");
    go(
        "--out .stl",
        with_out(base(&["--vertices", VERTICES]), &stl),
        &stl,
        &["opts.stl", "unknown mesh format"],
    );
}

#[test]
fn a_label_of_the_other_lungs_lobe_is_refused() {
    let tmp = Tmp::new("lobes");
    let body = lobes_body();
    let (d, rows) = in_file_order(body, Axes::RAS, Axes::RAS);
    let nii = tmp.write("lobes.nii", &nifti(body, Some(rows), &d));
    let out = tmp.path("lobes-wrong.ply");
    refused(
        "--label 1 for the right lung (lungmask-lobes)",
        &[
            s(&nii),
            "--lung",
            "right",
            "--label",
            "1",
            "--vertices",
            VERTICES,
            "--out",
            s(&out),
        ],
        &out,
        &["--label 1", "left upper", "not a lobe of the right lung"],
    );
    // The same with the convention named.
    refused(
        "--label 1 --convention lungmask-lobes",
        &[
            s(&nii),
            "--lung",
            "right",
            "--convention",
            "lungmask-lobes",
            "--label",
            "1",
            "--vertices",
            VERTICES,
            "--out",
            s(&out),
        ],
        &out,
        &["--label 1", "left upper", "not a lobe of the right lung"],
    );
}

/// LPS-ordered voxels under an identity (RAS) sform: both lungs, lobe labels. Refused with
/// `--axes LPS`; with `--axes LPS` it is made. An existing file at `--out` survives the refusal.
#[test]
fn a_lying_header_is_refused_with_the_axes_that_fix_it_and_does_not_clobber_out() {
    let tmp = Tmp::new("lying");
    let body = lobes_body();
    let (d_lps, _) = in_file_order(body, Axes::LPS, Axes::LPS);
    let mut lying = [[0.0; 4]; 3];
    for a in 0..3 {
        lying[a][a] = SPACING[a];
    }
    let nii = tmp.write("lying.nii", &nifti(body, Some(lying), &d_lps));
    let out = tmp.path("lying.ply");
    refused(
        "lying header",
        &[
            s(&nii),
            "--lung",
            "left",
            "--vertices",
            VERTICES,
            "--out",
            s(&out),
        ],
        &out,
        &["lying.nii", "--axes LPS"],
    );

    // A sentinel at --out is left as it was by the same refusal.
    const SENTINEL: &[u8] = b"lungdyn from-mask test: this file must not change\n";
    let sentinel = tmp.path("sentinel.ply");
    std::fs::write(&sentinel, SENTINEL).unwrap();
    let r = lungdyn(&[
        "mesh",
        "from-mask",
        s(&nii),
        "--lung",
        "left",
        "--vertices",
        VERTICES,
        "--out",
        s(&sentinel),
    ]);
    assert!(
        matches!(r.code, Some(c) if c != 0 && c != 101) && !r.stderr.contains("panicked"),
        "exit {:?}: {}",
        r.code,
        r.stderr
    );
    assert_eq!(
        std::fs::read(&sentinel).unwrap(),
        SENTINEL,
        "a failed from-mask changed the file at --out"
    );
    // And by an early refusal (a label absent).
    let r = lungdyn(&[
        "mesh",
        "from-mask",
        s(&nii),
        "--lung",
        "left",
        "--label",
        "9",
        "--vertices",
        VERTICES,
        "--out",
        s(&sentinel),
    ]);
    assert!(
        matches!(r.code, Some(c) if c != 0 && c != 101) && r.stderr.contains("--label 9"),
        "exit {:?}: {}",
        r.code,
        r.stderr
    );
    assert_eq!(std::fs::read(&sentinel).unwrap(), SENTINEL);

    // One label for both lungs under the same lying header, the right lung asked: refused too,
    // naming the same axes (the sides told apart by geometry, the half turn seen from the sizes).
    let single = both_lungs(SPACING, |_| 1, |_| 1).0;
    let (d_single, _) = in_file_order(&single, Axes::LPS, Axes::LPS);
    let nii_single = tmp.write("lying-single.nii", &nifti(&single, Some(lying), &d_single));
    let out_single = tmp.path("lying-single.ply");
    refused(
        "lying header, one label",
        &[
            s(&nii_single),
            "--lung",
            "right",
            "--vertices",
            VERTICES,
            "--out",
            s(&out_single),
        ],
        &out_single,
        &["lying-single.nii", "--axes LPS"],
    );

    // With the axes stated it is made, the override reported.
    let fixed = tmp.path("lying-fixed.ply");
    let r = lungdyn(&[
        "mesh",
        "from-mask",
        s(&nii),
        "--lung",
        "left",
        "--axes",
        "LPS",
        "--vertices",
        VERTICES,
        "--out",
        s(&fixed),
        "--json",
    ]);
    assert_eq!(r.code, Some(0), "--axes LPS: {}", r.stderr);
    let v: serde_json::Value = serde_json::from_str(r.stdout.trim()).unwrap();
    assert_eq!(v["frame"]["axes_override"].as_str(), Some("LPS"), "{v}");
    assert_eq!(v["lobes_from"].as_str(), Some("labels"), "{v}");
    assert_eq!(v["labels_used"], serde_json::json!([1, 2]), "{v}");
    assert!(fixed.is_file());
}

#[test]
fn help_names_the_formats_axes_and_the_body_frame() {
    let r = lungdyn(&["mesh", "from-mask", "--help"]);
    assert_eq!(r.code, Some(0), "{}", r.stderr);
    for w in ["NIfTI", "NRRD", "--axes", "body frame"] {
        assert!(r.stdout.contains(w), "--help lacks {w:?}:\n{}", r.stdout);
    }
}

/// `lungdyn patient`: a lobe-labelled two-lung mask becomes a folder whose scene `scene check`
/// accepts, whose kernels carry the masks' lobes, whose PV constants' FRC is the two surfaces'
/// volume, and which is not overwritten by a second run without --force.
#[test]
fn patient_makes_a_scene_that_scene_check_accepts_with_frc_from_the_masks() {
    let tmp = Tmp::new("patient");
    let body = lobes_body();
    let (d, rows) = in_file_order(body, Axes::RAS, Axes::RAS);
    let nii = tmp.write("lobes.nii", &nifti(body, Some(rows), &d));
    let out = tmp.path("patient");
    let r = lungdyn(&[
        "patient",
        "--exhale",
        s(&nii),
        "--vertices",
        "2000",
        "--out",
        s(&out),
        "--json",
    ]);
    assert_eq!(r.code, Some(0), "stderr: {}", r.stderr);
    let j: serde_json::Value = serde_json::from_str(r.stdout.trim()).expect("one JSON object");
    let lungs = j["lungs"].as_array().expect("lungs");
    assert_eq!(lungs.len(), 2);
    let mut total = 0.0;
    for (l, name) in lungs.iter().zip(["right", "left"]) {
        assert_eq!(l["lung"], name);
        assert_eq!(l["lobes_from"], "labels", "{l}");
        total += l["volume_ml"].as_f64().unwrap();
        // Without a pair: the breath-hold population, unless it folds within the lung's tidal
        // share; the kernel carries the motion the report names, and where it is the population,
        // the kernel driven to that share draws no fold (`kernel export`, then `mesh check`).
        let k = lung_model::kernel::KernelFile::open(&out.join(format!("{name}.kernel"))).unwrap();
        let breath_hold = k.meta().settings.direction_field.is_some();
        let share = l["tidal_share_ml"].as_f64().unwrap();
        let free = l["breath_hold_fold_free_ml"]
            .as_f64()
            .expect("the population was tried");
        assert!(share > 50.0 && share < 450.0, "{l}");
        let want = if breath_hold {
            assert_eq!(free, share, "{l}");
            let drawn = tmp.path(&format!("{name}_tidal.ply"));
            let kernel = out.join(format!("{name}.kernel"));
            let e = lungdyn(&[
                "kernel",
                "export",
                s(&kernel),
                "--delta-ml",
                &format!("{share}"),
                "--out",
                s(&drawn),
            ]);
            assert_eq!(e.code, Some(0), "{}", e.stderr);
            let c = lungdyn(&["mesh", "check", "--mesh", s(&drawn), "--frame", "body"]);
            assert_eq!(
                c.code,
                Some(0),
                "the population drawn at its share: {}",
                c.stderr
            );
            "breath-hold population"
        } else {
            assert!(free < share, "{l}");
            "built-in population (the breath-hold population folds within a tidal breath)"
        };
        assert_eq!(l["motion"], want, "{l}");
    }
    eprintln!(
        "without a pair: {:?}",
        lungs
            .iter()
            .map(|l| (&l["motion"], &l["breath_hold_fold_free_ml"]))
            .collect::<Vec<_>>()
    );
    let frc = j["frc_ml"].as_f64().unwrap();
    assert!(
        (frc - total).abs() < 1e-6,
        "FRC {frc} vs the lungs' {total}"
    );
    // The PV constants file says the same FRC.
    let pv = std::fs::read_to_string(out.join("pv.toml")).unwrap();
    let written: toml::Value = toml::from_str(&pv).unwrap();
    let frc_file = written["boundary"]["frc_ml"].as_float().unwrap();
    assert!(
        (frc_file - frc).abs() < 1e-6,
        "pv.toml FRC {frc_file} vs {frc}"
    );
    // scene check accepts the scene as written (the kernels are opened and checked there).
    let scene = out.join("scene.toml");
    let c = lungdyn(&["scene", "check", s(&scene)]);
    assert_eq!(c.code, Some(0), "scene check: {}\n{}", c.stdout, c.stderr);
    // The kernels keep the masks' lobes: the right one holds right lobes only, all three.
    let kernel = lung_model::kernel::KernelFile::open(&out.join("right.kernel")).unwrap();
    let codes = kernel
        .lobes()
        .unwrap()
        .expect("the kernel has lobes")
        .to_vec();
    for code in [1u8, 2, 3] {
        assert!(codes.contains(&code), "right lobe {code} missing");
    }
    assert!(
        codes.iter().all(|c| (1..=3).contains(c)),
        "a right kernel with another lobe"
    );
    // With an inhale mask (the same voxels under a header with larger spacing: the lungs 19 % larger),
    // each lung's motion is fitted to the pair, written, and baked into the kernels.
    let mut big = rows;
    for row in big.iter_mut() {
        for (c, f) in [1.05, 1.05, 1.08].iter().enumerate() {
            row[c] *= f;
        }
    }
    let inhale = tmp.write("lobes_inhale.nii", &nifti(body, Some(big), &d));
    let out2 = tmp.path("patient_pair");
    let r = lungdyn(&[
        "patient",
        "--exhale",
        s(&nii),
        "--inhale",
        s(&inhale),
        "--vertices",
        "2000",
        "--out",
        s(&out2),
        "--json",
    ]);
    assert_eq!(r.code, Some(0), "stderr: {}", r.stderr);
    let j: serde_json::Value = serde_json::from_str(r.stdout.trim()).expect("one JSON object");
    // "auto": each lung gets the fit unless its kernel folds before the lung's share of a tidal
    // breath; the kernel says which it was baked with.
    for l in j["lungs"].as_array().unwrap() {
        let m = &l["motion_mssd_mm"];
        assert!(
            m["fitted"].as_f64().unwrap() < m["no_motion"].as_f64().unwrap(),
            "{l}"
        );
        // No fold found up to the pair's own inspiration counts, whatever the share (a fold that
        // comes and goes below a clean inhale does not: the scan finds it).
        let (v, inhale) = (
            l["volume_ml"].as_f64().unwrap(),
            l["inhale_volume_ml"].as_f64(),
        );
        let pair = inhale.unwrap() - v;
        let keeps = m["fold_free_ml"].as_f64().unwrap()
            >= m["tidal_share_ml"].as_f64().unwrap().min(pair) - 1e-6 * v;
        let name = l["lung"].as_str().unwrap();
        let k = lung_model::kernel::KernelFile::open(&out2.join(format!("{name}.kernel"))).unwrap();
        // Where the fit folds: the breath-hold population, else the built-in (no force field).
        let side: Side = name.parse().unwrap();
        let preset = lung_model::deform::DirectionPreset::BreathHold;
        let population = lung_model::kernel::BakeSettings::for_preset(preset, side).force_field;
        let baked = &k.meta().settings.force_field;
        let want = match (keeps, baked.is_some(), *baked == population) {
            (true, true, false) => "fitted to the breath-hold pair",
            (false, true, true) => {
                "breath-hold population (the fitted motion folds within a tidal breath)"
            }
            (false, false, _) => {
                "built-in population (the fitted motion and the breath-hold population fold \
                 within a tidal breath)"
            }
            other => panic!("{name}: the kernel's motion {other:?} does not match {l}"),
        };
        assert_eq!(l["motion"], want, "{name}: {l}");
    }
    let motion = std::fs::read_to_string(out2.join("motion.toml")).unwrap();
    assert!(
        motion.contains("[right_force]") && motion.contains("[left_field]"),
        "{motion}"
    );
    // --motion fitted bakes the fit whatever it draws.
    let out3 = tmp.path("patient_fitted");
    let r = lungdyn(&[
        "patient",
        "--exhale",
        s(&nii),
        "--inhale",
        s(&inhale),
        "--vertices",
        "2000",
        "--motion",
        "fitted",
        "--out",
        s(&out3),
    ]);
    assert_eq!(r.code, Some(0), "stderr: {}", r.stderr);
    for name in ["right", "left"] {
        let k = lung_model::kernel::KernelFile::open(&out3.join(format!("{name}.kernel"))).unwrap();
        assert!(k.meta().settings.force_field.is_some(), "{name}");
    }
    let c = lungdyn(&["scene", "check", s(&out2.join("scene.toml"))]);
    assert_eq!(c.code, Some(0), "scene check: {}\n{}", c.stdout, c.stderr);
    // A second run does not overwrite it.
    let again = lungdyn(&[
        "patient",
        "--exhale",
        s(&nii),
        "--vertices",
        "2000",
        "--out",
        s(&out),
    ]);
    assert!(
        matches!(again.code, Some(c) if c != 0 && c != 101),
        "{:?}",
        again.code
    );
    assert!(again.stderr.contains("--force"), "{}", again.stderr);
    // --motion fitted without a pair to fit is refused, nothing written.
    let out4 = tmp.path("patient_fitted_alone");
    let alone = [
        "patient",
        "--exhale",
        s(&nii),
        "--motion",
        "fitted",
        "--out",
        s(&out4),
    ];
    let words = ["--motion fitted needs --inhale"];
    refused_command(
        "--motion fitted alone",
        &alone,
        &out4.join("scene.toml"),
        &words,
    );
}

/// `fit-motion --exhale/--inhale` on a known breath (surfaces): the error it reports is the error of
/// the kernel `bake --motion` makes from the file it wrote, driven (`kernel export`) to the inhale
/// volume — measured here again from those files; bad pairs are refused without output.
#[test]
fn fit_motion_on_a_pair_reports_what_the_bake_of_its_file_draws() {
    let tmp = Tmp::new("pair");
    let exhale = anatomy::lung(Side::Right, 2500).unwrap();
    let top = exhale
        .positions
        .iter()
        .map(|p| p[2])
        .fold(f32::MIN, f32::max) as f64;
    let bottom = exhale
        .positions
        .iter()
        .map(|p| p[2])
        .fold(f32::MAX, f32::min) as f64;
    let inhale = TriMesh {
        positions: exhale
            .positions
            .iter()
            .map(|p| {
                let x = DVec3::from(p.map(|v| v as f64));
                let t = (top - x.z) / (top - bottom);
                (x + t * t * DVec3::new(-3.0, 5.0, -20.0) + DVec3::new(2.0, 1.0, 30.0))
                    .as_vec3()
                    .to_array()
            })
            .collect(),
        triangles: exhale.triangles.clone(),
    };
    let (e, i) = (tmp.path("exhale.ply"), tmp.path("inhale.ply"));
    lung_model::mesh::io::write_mesh(&exhale, &e).unwrap();
    lung_model::mesh::io::write_mesh(&inhale, &i).unwrap();
    // The force with its local terms (the default, 256 centres) and the polynomial alone
    // (`--force-centres 0`): either way the figure printed is the figure the bake of the written
    // file draws.
    let variants: [&[&str]; 2] = [&[], &["--force-centres", "0"]];
    for (v, extra) in variants.into_iter().enumerate() {
        let (motion, dir) = (
            tmp.path(&format!("motion{v}.toml")),
            tmp.path(&format!("fit{v}")),
        );
        let mut args = vec![
            "fit-motion",
            "--exhale",
            s(&e),
            "--inhale",
            s(&i),
            "--lung",
            "right",
            "--iterations",
            "20",
            "--folds",
            "3",
            "--out",
            s(&motion),
            "--surfaces-out",
            s(&dir),
            "--json",
        ];
        args.extend(extra);
        let r = lungdyn(&args);
        assert_eq!(r.code, Some(0), "{}", r.stderr);
        let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        let lung = &j["lungs"][0];
        let reported = lung["in_sample"]["mssd_mm"].as_f64().unwrap();
        let (none, held) = (
            lung["no_motion"]["mssd_mm"].as_f64().unwrap(),
            lung["cross_validated"]["mssd_mm"].as_f64().unwrap(),
        );
        assert!(reported < 0.5 * none && held.is_finite(), "{lung}");
        // With local terms, the file carries them (and the bake below must draw them).
        let centres = lung["force"]["centres"].as_array().map_or(0, |c| c.len());
        assert_eq!(centres, if extra.is_empty() { 256 } else { 0 }, "{extra:?}");
        // What a user does with the file: bake the surface the fit used, drive it to the inhale volume.
        let kernel = tmp.path(&format!("right{v}.kernel"));
        let b = lungdyn(&[
            "bake",
            "--mesh",
            s(&dir.join("right_exhale.ply")),
            "--lung",
            "right",
            "--motion",
            s(&motion),
            "--out",
            s(&kernel),
        ]);
        assert_eq!(b.code, Some(0), "{}", b.stderr);
        let dv = lung["inhale_ml"].as_f64().unwrap() - lung["exhale_ml"].as_f64().unwrap();
        let drawn = tmp.path(&format!("drawn{v}.ply"));
        let x = lungdyn(&[
            "kernel",
            "export",
            s(&kernel),
            "--delta-ml",
            &format!("{dv}"),
            "--out",
            s(&drawn),
        ]);
        assert_eq!(x.code, Some(0), "{}", x.stderr);
        let read = |p: &Path| {
            lung_bake::import::import(p, lung_bake::import::Units::Mm)
                .unwrap()
                .mesh
        };
        let again = lung_bake::patient_motion::surface_distance(
            &read(&drawn),
            &read(&dir.join("right_inhale_aligned.ply")),
        )
        .unwrap();
        assert!(
            (again.mssd_mm - reported).abs() < 0.01,
            "{extra:?}: fit-motion reported {reported} mm; its bake, exported at +{dv:.1} ml, lies {} mm",
            again.mssd_mm
        );
    }
    // Refused, nothing written: the pair the wrong way round; one file twice; a landmark option.
    for (case, args, words) in [
        (
            "reversed",
            vec!["--exhale", s(&i), "--inhale", s(&e)],
            vec!["not larger"],
        ),
        (
            "same file",
            vec!["--exhale", s(&e), "--inhale", s(&e)],
            vec!["same file"],
        ),
        (
            "plot",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--plot", "x.png"],
            vec!["--plot"],
        ),
        (
            "degree",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--force-degree", "9"],
            vec!["--force-degree"],
        ),
        (
            "centres",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--force-centres", "5"],
            vec!["--force-centres 5", "8 to 1000"],
        ),
        (
            "local ridge",
            vec![
                "--exhale",
                s(&e),
                "--inhale",
                s(&i),
                "--force-local-ridge",
                "0",
            ],
            vec!["--force-local-ridge 0"],
        ),
        (
            "folds",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--folds", "12"],
            vec!["--folds 12"],
        ),
        (
            "iterations",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--iterations", "0"],
            vec!["--iterations 0"],
        ),
        (
            "vertices",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--vertices", "10"],
            vec!["--vertices 10"],
        ),
        (
            "axes on a surface",
            vec!["--exhale", s(&e), "--inhale", s(&i), "--axes", "LPS"],
            vec!["--axes", "surface"],
        ),
        (
            "exhale missing",
            vec!["--exhale", "/nonexistent/e.ply", "--inhale", s(&i)],
            vec!["/nonexistent/e.ply"],
        ),
    ] {
        let out = tmp.path(&format!("{}.toml", case.replace(' ', "_")));
        let mut full = vec!["fit-motion", "--lung", "right", "--out", s(&out)];
        full.extend(args);
        let r = lungdyn(&full);
        assert!(
            matches!(r.code, Some(c) if c != 0 && c != 101),
            "{case}: {:?} {}",
            r.code,
            r.stderr
        );
        for w in words {
            assert!(r.stderr.contains(w), "{case}: {}", r.stderr);
        }
        assert!(!out.exists(), "{case}: wrote {}", out.display());
    }
}
