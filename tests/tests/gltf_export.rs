//! `lungdyn export gltf` judged from outside (issue 38 item 2): one breath of the tumour scene
//! (both lungs with their lobes and the tumour) written as .glb, then
//! * read back with the `gltf` crate's reader (its accessors; the quantised morph targets decoded
//!   here as `KHR_mesh_quantization` defines them, checked against the crate's own reading of the
//!   same breath written with `--float-targets`): every frame rebuilt from the base and its morph
//!   target encloses the volume the engine gave that frame (a wrong target, a lost frame or an
//!   inward winding shows), every frame's normals are that frame's surface's (a target without
//!   normals, or normals of the wrong frame, shows), normals point outward, the right lung on the
//!   patient's right (−x), the
//!   tumour inside it with its ellipsoid's volume; the animation's keys, weights and the tumour's
//!   path read back as a viewer plays them;
//! * judged by the Khronos glTF validator (npm `gltf-validator`): no error, no warning;
//! * shown by Google's `<model-viewer>` in headless Chromium: both lungs in the picture, the right
//!   lung's middle lobe (green) on the viewer's left of the left lung's upper lobe (orange), as a
//!   patient facing the viewer, the tumour showing through the see-through lungs, and at the
//!   breath's largest volume the lungs larger than at its start.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use lungdyn_tests::lungdyn;

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

const FRAMES: usize = 12;

struct Exported {
    glb: PathBuf,
    report: serde_json::Value,
    dir: PathBuf,
}

/// The tumour scene at 2000 vertices per lung, exported once for the tests of this file (its morph
/// targets quantised, the default).
fn exported() -> &'static Exported {
    static ONCE: OnceLock<Exported> = OnceLock::new();
    ONCE.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("lungdyn-gltf-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        export(&dir, "breath.glb", &[])
    })
}

/// The same breath with `--float-targets` (the kernels [`exported`] baked reused).
fn exported_float() -> &'static Exported {
    static ONCE: OnceLock<Exported> = OnceLock::new();
    ONCE.get_or_init(|| export(&exported().dir, "float.glb", &["--float-targets"]))
}

fn export(dir: &Path, file: &str, extra: &[&str]) -> Exported {
    let glb = dir.join(file);
    let scene = workspace_root().join("scenes/tumour_right_lower.toml");
    let frames = FRAMES.to_string();
    let mut args = vec![
        "export",
        "gltf",
        "--scene",
        scene.to_str().unwrap(),
        "--vertices",
        "2000",
        "--frames",
        &frames,
        "--out",
        glb.to_str().unwrap(),
        "--kernels",
    ];
    let kernels = dir.join("kernels");
    args.push(kernels.to_str().unwrap());
    args.push("--json");
    args.extend_from_slice(extra);
    let (ok, out, err) = lungdyn(&args);
    assert!(ok, "export gltf failed: {err}");
    let report: serde_json::Value = serde_json::from_str(out.trim()).expect("--json");
    Exported {
        glb,
        report,
        dir: dir.to_path_buf(),
    }
}

/// An accessor's three-component values as a viewer decodes them: floats as stored, signed
/// normalised integers (`KHR_mesh_quantization`) as max(c / (2^(bits − 1) − 1), −1), element by
/// element at the view's stride.
fn decode_vec3(acc: &gltf::Accessor, blob: &[u8]) -> Vec<[f32; 3]> {
    use gltf::accessor::DataType;
    assert_eq!(acc.dimensions(), gltf::accessor::Dimensions::Vec3);
    let view = acc.view().expect("an accessor with a view");
    let stride = view.stride().unwrap_or(acc.size());
    let start = view.offset() + acc.offset();
    (0..acc.count())
        .map(|i| {
            let e = &blob[start + i * stride..start + i * stride + acc.size()];
            [0, 1, 2].map(|a| match (acc.data_type(), acc.normalized()) {
                (DataType::F32, false) => {
                    f32::from_le_bytes(e[4 * a..4 * a + 4].try_into().unwrap())
                }
                (DataType::I16, true) => {
                    (f32::from(i16::from_le_bytes([e[2 * a], e[2 * a + 1]])) / 32767.0).max(-1.0)
                }
                (DataType::I8, true) => (f32::from(e[a] as i8) / 127.0).max(-1.0),
                other => panic!("a morph target stored as {other:?}, which glTF does not allow"),
            })
        })
        .collect()
}

/// Each morph target of `prim` as (position differences, normal differences), decoded.
fn morph_targets(prim: &gltf::Primitive, blob: &[u8]) -> Vec<(Vec<[f32; 3]>, Vec<[f32; 3]>)> {
    prim.morph_targets()
        .map(|t| {
            let p = t.positions().expect("a target moves the positions");
            let n = t.normals().expect("a target moves the normals");
            (decode_vec3(&p, blob), decode_vec3(&n, blob))
        })
        .collect()
}

/// The file as the `gltf` crate's reader sees it (its own GLB parsing; its validation too where the
/// file needs no extension: the crate does not know `KHR_mesh_quantization`, which the Khronos
/// validator below checks).
fn read(path: &Path) -> gltf::Gltf {
    let bytes = std::fs::read(path).unwrap();
    let file = gltf::Gltf::from_slice_without_validation(&bytes).expect("the gltf crate reads it");
    let required: Vec<&str> = file.extensions_required().collect();
    if required.is_empty() {
        gltf::Gltf::from_slice(&bytes).expect("the gltf crate validates the file")
    } else {
        assert_eq!(
            required,
            ["KHR_mesh_quantization"],
            "extensions the file requires"
        );
        file
    }
}

/// `asset.extras`, where the export puts the scene's figures.
fn asset_extras(file: &gltf::Gltf) -> serde_json::Value {
    let raw = file
        .document
        .as_json()
        .asset
        .extras
        .as_ref()
        .expect("asset extras");
    serde_json::from_str(raw.get()).unwrap()
}

/// Enclosed volume of a closed triangle mesh, in the units cubed (positive: wound outward).
fn signed_volume(p: &[[f32; 3]], tris: &[[u32; 3]]) -> f64 {
    lung_model::mesh::enclosed_volume_with(tris, |i| p[i as usize].map(f64::from))
}

#[test]
fn the_exported_breath_reads_back_with_the_engines_volumes_and_the_patients_anatomy() {
    let e = exported();
    let file = read(&e.glb);
    let doc = &file.document;
    let blob = file.blob.as_deref().expect("the .glb's binary chunk");
    let meta = &e.report;
    let extras = asset_extras(&file);
    let lungdyn = &extras["lungdyn"];
    let anim = doc.animations().next().expect("one animation");
    assert_eq!(anim.name(), Some("breath"));
    let mut centroids = Vec::new();
    for node in doc
        .nodes()
        .filter(|n| n.name().is_some_and(|s| s.ends_with("lung")))
    {
        let side = node.name().unwrap().split(' ').next().unwrap().to_string();
        let mesh = node.mesh().unwrap();
        let mut tris: Vec<[u32; 3]> = Vec::new();
        let mut base: Vec<[f32; 3]> = Vec::new();
        let mut normals: Vec<[f32; 3]> = Vec::new();
        let mut targets: Vec<Vec<[f32; 3]>> = Vec::new();
        for prim in mesh.primitives() {
            let r = prim.reader(|b| (b.index() == 0).then_some(blob));
            let idx: Vec<u32> = r.read_indices().unwrap().into_u32().collect();
            tris.extend(idx.chunks(3).map(|c| [c[0], c[1], c[2]]));
            base = r.read_positions().unwrap().collect();
            normals = r.read_normals().unwrap().collect();
            targets = morph_targets(&prim, blob)
                .into_iter()
                .map(|(p, _)| p)
                .collect();
        }
        assert_eq!(
            targets.len(),
            FRAMES - 1,
            "{side}: a target per frame after the first"
        );
        let volumes = lungdyn["volume_ml"][&side].as_array().unwrap();
        for k in 0..FRAMES {
            let p: Vec<[f32; 3]> = if k == 0 {
                base.clone()
            } else {
                base.iter()
                    .zip(&targets[k - 1])
                    .map(|(b, d)| [b[0] + d[0], b[1] + d[1], b[2] + d[2]])
                    .collect()
            };
            // m³ → ml.
            let v = signed_volume(&p, &tris) * 1e6;
            let engine = volumes[k].as_f64().unwrap();
            assert!(
                (v - engine).abs() < 0.01 * engine,
                "{side} lung, frame {k}: the file's mesh encloses {v:.1} ml, the engine gave {engine} ml"
            );
        }
        let c0 = base.iter().fold([0.0f64; 3], |s, p| {
            [0, 1, 2].map(|a| s[a] + p[a] as f64 / base.len() as f64)
        });
        let outward = base
            .iter()
            .zip(&normals)
            .filter(|(p, n)| {
                (0..3)
                    .map(|a| (p[a] as f64 - c0[a]) * n[a] as f64)
                    .sum::<f64>()
                    > 0.0
            })
            .count();
        assert!(
            outward as f64 > 0.9 * base.len() as f64,
            "{side} lung: only {outward} of {} normals point away from the centre",
            base.len()
        );
        let c = base.iter().fold([0.0f64; 3], |s, p| {
            [0, 1, 2].map(|a| s[a] + p[a] as f64 / base.len() as f64)
        });
        centroids.push((side, c, base));
    }
    assert_eq!(centroids.len(), 2, "both lungs");
    for (side, c, _) in &centroids {
        // glTF +x is the patient's left (a patient facing the viewer).
        let expected = if side == "right" { -1.0 } else { 1.0 };
        assert!(
            c[0] * expected > 0.02,
            "{side} lung's centre at x = {:.3} m",
            c[0]
        );
    }
    // The tumour sits in the right lower lobe: inside the right lung's box, in its lower half; its
    // mesh is wound outward and encloses its ellipsoid's volume (the 12-ring sphere a little less).
    let tumour = doc
        .nodes()
        .find(|n| n.name().is_some_and(|s| s.starts_with("tumour")))
        .expect("a tumour node");
    let t = tumour.transform().decomposed().0;
    let (_, _, right) = centroids.iter().find(|(s, _, _)| s == "right").unwrap();
    let (lo, hi) = right
        .iter()
        .fold(([f32::MAX; 3], [f32::MIN; 3]), |(lo, hi), p| {
            (
                [0, 1, 2].map(|a| lo[a].min(p[a])),
                [0, 1, 2].map(|a| hi[a].max(p[a])),
            )
        });
    assert!(
        (0..3).all(|a| t[a] > lo[a] && t[a] < hi[a]) && t[1] < 0.5 * (lo[1] + hi[1]),
        "tumour at {t:?} m, right lung within {lo:?}..{hi:?}"
    );
    let prim = tumour.mesh().unwrap().primitives().next().unwrap();
    let r = prim.reader(|b| (b.index() == 0).then_some(blob));
    let p: Vec<[f32; 3]> = r.read_positions().unwrap().collect();
    let idx: Vec<u32> = r.read_indices().unwrap().into_u32().collect();
    let tris: Vec<[u32; 3]> = idx.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    let radii: Vec<f64> = meta["tumour"]["radii_mm"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let ellipsoid_ml = 4.0 / 3.0 * std::f64::consts::PI * radii.iter().product::<f64>() / 1000.0;
    let v = signed_volume(&p, &tris) * 1e6;
    assert!(
        v > 0.95 * ellipsoid_ml && v < ellipsoid_ml,
        "the tumour mesh encloses {v:.2} ml, its ellipsoid {ellipsoid_ml:.2} ml"
    );
    check_animation(&doc, blob, lungdyn, meta);
}

/// The lungs' nodes of a file: (side, positions, normals, triangles of every lobe, decoded morph
/// targets).
type LungRead = (
    String,
    Vec<[f32; 3]>,
    Vec<[f32; 3]>,
    Vec<[u32; 3]>,
    Vec<(Vec<[f32; 3]>, Vec<[f32; 3]>)>,
);

fn lungs_of(file: &gltf::Gltf) -> Vec<LungRead> {
    let blob = file.blob.as_deref().expect("the .glb's binary chunk");
    file.document
        .nodes()
        .filter(|n| n.name().is_some_and(|s| s.ends_with("lung")))
        .map(|node| {
            let side = node.name().unwrap().split(' ').next().unwrap().to_string();
            let prims: Vec<_> = node.mesh().unwrap().primitives().collect();
            let r = prims[0].reader(|b| (b.index() == 0).then_some(blob));
            let base: Vec<[f32; 3]> = r.read_positions().unwrap().collect();
            let normals: Vec<[f32; 3]> = r.read_normals().unwrap().collect();
            let mut tris = Vec::new();
            for prim in &prims {
                let r = prim.reader(|b| (b.index() == 0).then_some(blob));
                let idx: Vec<u32> = r.read_indices().unwrap().into_u32().collect();
                tris.extend(idx.chunks(3).map(|c| [c[0], c[1], c[2]]));
            }
            (side, base, normals, tris, morph_targets(&prims[0], blob))
        })
        .collect()
}

fn unit(v: [f32; 3]) -> [f64; 3] {
    let v = v.map(f64::from);
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|x| x / l)
}

fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f64 {
    let (a, b) = (unit(a), unit(b));
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Area-weighted vertex normals of a triangle mesh.
fn surface_normals(p: &[[f32; 3]], tris: &[[u32; 3]]) -> Vec<[f32; 3]> {
    let mut n = vec![[0.0f32; 3]; p.len()];
    for t in tris {
        let [a, b, c] = t.map(|i| p[i as usize]);
        let (u, v) = (
            [0, 1, 2].map(|k| b[k] - a[k]),
            [0, 1, 2].map(|k| c[k] - a[k]),
        );
        let x = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for &i in t {
            for k in 0..3 {
                n[i as usize][k] += x[k];
            }
        }
    }
    n
}

/// Every frame is shaded by its own surface: the normals a viewer rebuilds at frame k (the base's
/// plus target k's, made unit) against the area-weighted normals of frame k's own triangles in the
/// file. The first frame's normals against the same surfaces show what a file without normal
/// targets is off by; at the frame that moves most the file's own must be at most half that.
#[test]
fn every_frame_is_shaded_by_its_own_surfaces_normals() {
    let file = read(&exported().glb);
    for (side, base, normals, tris, targets) in lungs_of(&file) {
        assert_eq!(
            targets.len(),
            FRAMES - 1,
            "{side}: a target per later frame"
        );
        let mut worst = (0.0f32, 0.0f64, 0.0f64, 0);
        for (k, (dp, dn)) in targets.iter().enumerate() {
            let p: Vec<[f32; 3]> = base
                .iter()
                .zip(dp)
                .map(|(b, d)| [0, 1, 2].map(|a| b[a] + d[a]))
                .collect();
            let geo = surface_normals(&p, &tris);
            let mean = |n: &dyn Fn(usize) -> [f32; 3]| {
                (0..p.len()).map(|i| angle_deg(n(i), geo[i])).sum::<f64>() / p.len() as f64
            };
            let own = mean(&|i| [0, 1, 2].map(|a| normals[i][a] + dn[i][a]));
            let first = mean(&|i| normals[i]);
            eprintln!("{side} lung, frame {}: its normals {own:.3}° from its surface's, the first frame's {first:.3}°", k + 1);
            assert!(
                own < 2.0,
                "{side} lung, frame {}: its normals lie {own:.2}° (mean) from its surface's",
                k + 1
            );
            let moved = dp
                .iter()
                .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
                .fold(0.0f32, f32::max);
            if moved > worst.0 {
                worst = (moved, own, first, k + 1);
            }
        }
        let (moved, own, first, k) = worst;
        assert!(
            own < 0.5 * first,
            "{side} lung, frame {k} (moves up to {:.1} mm): its normals lie {own:.3}° from its \
             surface's, the first frame's {first:.3}°: the targets do not turn the normals",
            moved * 1e3
        );
    }
}

/// The quantised targets are the float ones (the `gltf` crate's own reading of the breath written
/// with `--float-targets`, the file validated by the crate) within half a step of their integers:
/// this checks the decoding above as much as the export; the quantised file is about half the size
/// and says what quantising cost.
#[test]
fn quantised_targets_are_the_float_ones_within_half_a_step_at_about_half_the_size() {
    let (q, f) = (exported(), exported_float());
    let float = read(&f.glb);
    assert_eq!(
        float.extensions_required().count(),
        0,
        "--float-targets needs no extension"
    );
    let blob = float.blob.as_deref().unwrap();
    let ours = lungs_of(&read(&q.glb));
    for node in float
        .document
        .nodes()
        .filter(|n| n.name().is_some_and(|s| s.ends_with("lung")))
    {
        let side = node.name().unwrap().split(' ').next().unwrap();
        let prim = node.mesh().unwrap().primitives().next().unwrap();
        let r = prim.reader(|b| (b.index() == 0).then_some(blob));
        let theirs: Vec<(Vec<[f32; 3]>, Vec<[f32; 3]>)> = r
            .read_morph_targets()
            .map(|(p, n, _)| (p.unwrap().collect(), n.unwrap().collect()))
            .collect();
        let (.., targets) = ours.iter().find(|l| l.0 == side).expect("the same lung");
        assert_eq!(theirs.len(), targets.len(), "{side}: targets");
        for (k, ((fp, fnn), (qp, qn))) in theirs.iter().zip(targets).enumerate() {
            for (what, a, b, step) in [
                ("position", fp, qp, 1.0 / 32767.0),
                ("normal", fnn, qn, 1.0 / 127.0),
            ] {
                let off = a
                    .iter()
                    .zip(b)
                    .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs()))
                    .fold(0.0f32, f32::max);
                assert!(
                    off <= 0.5 * step + 1e-6,
                    "{side} lung, target {k}: a {what} difference {off:e} off the float one (half \
                     a step {:e})",
                    0.5 * step
                );
            }
        }
    }
    let t = &q.report["targets"];
    assert_eq!(t["encoding"], "quantized", "{t}");
    assert_eq!(t["kept_float"], 0, "{t}");
    assert!(t["position_error_max_mm"].as_f64().unwrap() < 0.03, "{t}");
    assert!(t["normal_error_max_deg"].as_f64().unwrap() < 1.0, "{t}");
    assert_eq!(f.report["targets"]["encoding"], "float");
    let (qb, fb) = (
        q.report["bytes"].as_f64().unwrap(),
        f.report["bytes"].as_f64().unwrap(),
    );
    assert!(qb < 0.65 * fb, "quantised {qb} bytes, float {fb}");
}

/// The `breath` animation as a viewer plays it: its keys are the frames' times and the period; each
/// lung's weights show frame k at key k (frame 0, the base, at the first and the last key); the
/// tumour's path moves it down (glTF −y) by the report's superior–inferior motion.
fn check_animation(
    doc: &gltf::Document,
    blob: &[u8],
    lungdyn: &serde_json::Value,
    meta: &serde_json::Value,
) {
    let anim = doc.animations().next().expect("one animation");
    let mut expected_keys: Vec<f32> = lungdyn["frame_times_s"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap() as f32)
        .collect();
    expected_keys.push(meta["period_s"].as_f64().unwrap() as f32);
    let mut lungs_seen = 0;
    let mut tumour_path: Vec<[f32; 3]> = Vec::new();
    for channel in anim.channels() {
        let r = channel.reader(|b| (b.index() == 0).then_some(blob));
        let keys: Vec<f32> = r.read_inputs().unwrap().collect();
        assert_eq!(keys, expected_keys, "the animation's key times");
        match r.read_outputs().unwrap() {
            gltf::animation::util::ReadOutputs::MorphTargetWeights(w) => {
                let w: Vec<f32> = w.into_f32().collect();
                let t = FRAMES - 1;
                assert_eq!(w.len(), keys.len() * t);
                for (k, row) in w.chunks(t).enumerate() {
                    let shown: Vec<usize> = (0..t).filter(|&i| row[i] != 0.0).collect();
                    let expected = if k == 0 || k == FRAMES {
                        vec![]
                    } else {
                        vec![k - 1]
                    };
                    assert_eq!(shown, expected, "key {k}'s weights {row:?}");
                    assert!(shown.iter().all(|&i| row[i] == 1.0), "key {k}: {row:?}");
                }
                lungs_seen += 1;
            }
            gltf::animation::util::ReadOutputs::Translations(p) => tumour_path = p.collect(),
            _ => panic!("an animation channel of another kind"),
        }
    }
    assert_eq!(lungs_seen, 2, "a weights channel per lung");
    assert_eq!(tumour_path.len(), expected_keys.len(), "the tumour's path");
    assert_eq!(
        tumour_path[0], tumour_path[FRAMES],
        "the path closes the loop"
    );
    let ys: Vec<f64> = tumour_path.iter().map(|p| p[1] as f64 * 1000.0).collect();
    let (lo, hi) = ys
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &y| (l.min(y), h.max(y)));
    let si = meta["tumour"]["motion_mm"][2].as_f64().unwrap();
    assert!(
        si > 1.0 && ((hi - lo) - si).abs() < 0.01,
        "the path spans {:.3} mm superior-inferior, the report {si} mm",
        hi - lo
    );
    // Inspiration takes it down: lowest in the frames of largest volume, not at the start.
    let lowest = (0..FRAMES)
        .min_by(|&a, &b| ys[a].total_cmp(&ys[b]))
        .unwrap();
    assert!(
        lowest > 0,
        "the tumour is lowest at the breath's start: {ys:?}"
    );
}

#[test]
fn the_khronos_validator_finds_no_error_and_no_warning() {
    let root = workspace_root();
    let Some(modules) = lungdyn_needs::node_modules(
        &root,
        &["gltf-validator"],
        lungdyn_needs::Need::GltfValidator,
    ) else {
        return;
    };
    let e = exported();
    let out = Command::new("node")
        .arg(root.join("tests/peers/gltf_validate.mjs"))
        .arg(&modules)
        .arg(&e.glb)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let issues = &v["issues"];
    let fixture = format!(
        "validator {}: {} errors, {} warnings, {} infos, {} hints; messages: {}",
        v["validatorVersion"],
        issues["numErrors"],
        issues["numWarnings"],
        issues["numInfos"],
        issues["numHints"],
        issues["messages"]
    );
    eprintln!("{fixture}");
    assert_eq!(issues["numErrors"], 0, "{fixture}");
    assert_eq!(issues["numWarnings"], 0, "{fixture}");
    assert_eq!(v["info"]["animationCount"], 1, "{v}");
    // The file judged is the quantised one: the validator checks the extension's types too.
    assert_eq!(
        v["info"]["extensionsRequired"],
        serde_json::json!(["KHR_mesh_quantization"]),
        "{v}"
    );
}

/// What a screenshot shows, by colour.
#[derive(Debug, Clone, Copy, Default)]
struct Shot {
    /// Pixels of any lung (coloured, not the white page).
    lung: usize,
    /// The right lung's middle lobe (green, pale): count and mean x.
    green: (usize, f64),
    /// The left lung's upper lobe (orange): count and mean x.
    orange: (usize, f64),
    /// The tumour (saturated yellow-green): count and mean y.
    tumour: (usize, f64),
}

fn read_shot(path: &Path) -> Shot {
    let img = image::open(path).unwrap().to_rgb8();
    let mut s = Shot::default();
    let add = |acc: &mut (usize, f64), v: u32| {
        acc.0 += 1;
        acc.1 += v as f64;
    };
    for (x, y, p) in img.enumerate_pixels() {
        let [r, g, b] = p.0.map(|c| c as f64 / 255.0);
        let (max, min) = (r.max(g).max(b), r.min(g).min(b));
        let sat = if max > 0.0 { (max - min) / max } else { 0.0 };
        if max - min < 0.04 || sat < 0.08 {
            continue; // the white page, greys
        }
        s.lung += 1;
        let hue = if max == r {
            60.0 * ((g - b) / (max - min)).rem_euclid(6.0)
        } else if max == g {
            60.0 * ((b - r) / (max - min) + 2.0)
        } else {
            60.0 * ((r - g) / (max - min) + 4.0)
        };
        if sat > 0.5 && (70.0..=110.0).contains(&hue) {
            add(&mut s.tumour, y);
        } else if (100.0..=150.0).contains(&hue) {
            add(&mut s.green, x);
        } else if (25.0..=60.0).contains(&hue) {
            add(&mut s.orange, x);
        }
    }
    for acc in [&mut s.green, &mut s.orange, &mut s.tumour] {
        acc.1 /= acc.0.max(1) as f64;
    }
    s
}

#[test]
fn model_viewer_in_chromium_shows_both_lungs_breathing_the_right_way_round() {
    let root = workspace_root();
    let Some(modules) = lungdyn_needs::node_modules(
        &root,
        &["playwright-core", "@google/model-viewer"],
        lungdyn_needs::Need::Browser,
    ) else {
        return;
    };
    let Some(chromium) = lungdyn_needs::chromium() else {
        return;
    };
    let e = exported();
    let extras = &e.report;
    // The breath's start, and the frame of the right lung's largest volume.
    let meta = asset_extras(&read(&e.glb));
    let vols: Vec<f64> = meta["lungdyn"]["volume_ml"]["right"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let top = (0..vols.len())
        .max_by(|&a, &b| vols[a].total_cmp(&vols[b]))
        .unwrap();
    let t_top = meta["lungdyn"]["frame_times_s"][top].as_f64().unwrap();
    let prefix = e.dir.join("shot");
    let out = Command::new("node")
        .arg(root.join("tests/peers/gltf_view.mjs"))
        .arg(&modules)
        .arg(&chromium)
        .arg(&e.glb)
        .arg(&prefix)
        .args(["0", &format!("{t_top}")])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["loaded"], true, "model-viewer did not load the file: {v}");
    assert_eq!(v["animations"][0], "breath", "{v}");
    let period = extras["period_s"].as_f64().unwrap();
    assert!(
        (v["duration_s"].as_f64().unwrap() - period).abs() < 0.01,
        "the viewer's animation lasts {} s, the breath {period} s",
        v["duration_s"]
    );
    let start = read_shot(&PathBuf::from(format!("{}_0.png", prefix.display())));
    let full = read_shot(&PathBuf::from(format!("{}_1.png", prefix.display())));
    eprintln!(
        "screenshots: start {start:?}, largest volume {full:?}; in {}",
        e.dir.display()
    );
    for (what, s) in [("start", start), ("largest volume", full)] {
        assert!(
            s.lung > 20_000,
            "{what}: only {} lung pixels of 480000",
            s.lung
        );
        assert!(
            s.green.0 > 500 && s.orange.0 > 500,
            "{what}: both lungs' lobes in view: {s:?}"
        );
        assert!(
            s.green.1 < 400.0 && s.orange.1 > 400.0,
            "{what}: the right lung (green middle lobe, mean x {:.0}) must be on the viewer's left \
             and the left lung (orange upper lobe, {:.0}) on the right: {s:?}",
            s.green.1,
            s.orange.1
        );
        assert!(
            s.tumour.0 > 100,
            "{what}: the tumour shows through the lungs: {s:?}"
        );
    }
    assert!(
        full.lung as f64 > 1.01 * start.lung as f64,
        "the lungs at their largest volume cover {} px, at the start {} px: no breath seen",
        full.lung,
        start.lung
    );
}
