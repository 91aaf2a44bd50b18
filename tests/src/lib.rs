//! Helpers shared by the workspace-level tests.

use lung_model::scene::SceneExt;
use std::path::PathBuf;

/// The folder holding the workspace's built binaries (`target/<profile>`), derived from the test
/// executable's own path (`target/<profile>/deps/<test>`).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    exe.parent()
        .and_then(|p| p.parent())
        .expect("target/<profile>/deps layout")
        .to_path_buf()
}

/// Path of workspace binary `name`; panics with a fix if it has not been built.
pub fn bin(name: &str) -> PathBuf {
    let p = bin_dir().join(name);
    assert!(
        p.exists(),
        "{} is missing: run the tests with `cargo test --workspace` so every binary is built",
        p.display()
    );
    p
}

/// A unique instance name for one test.
pub fn unique_instance(tag: &str) -> String {
    format!(
        "t-{tag}-{}-{}",
        std::process::id(),
        transport::now_ns() % 1_000_000
    )
}

/// Run the `lungdyn` binary with `args`: (success, stdout, stderr).
pub fn lungdyn(args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(bin("lungdyn"))
        .args(args)
        .output()
        .expect("run lungdyn");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Run `lungdyn args`, expecting a non-zero exit whose stderr contains `needle` and no panic.
pub fn assert_clean_failure(args: &[&str], needle: &str) {
    let (ok, _, err) = lungdyn(args);
    assert!(!ok, "{args:?} should fail");
    assert!(
        err.contains(needle),
        "{args:?}: expected {needle:?} in: {err}"
    );
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
}

/// A scene file made from `toml` in a fresh folder, prepared by `lungdyn scene prepare` (every lung
/// baked into a kernel once): returns the resolved scene the processes can be started with.
pub fn prepared_scene(tag: &str, toml: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungdyn-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp folder");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, toml).expect("write scene");
    let (ok, out, err) = lungdyn(&[
        "scene",
        "prepare",
        scene.to_str().expect("utf-8 path"),
        "--out",
        dir.to_str().expect("utf-8 path"),
        "--json",
    ]);
    assert!(ok, "scene prepare failed: {err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).expect("prepare --json");
    PathBuf::from(v["scene"].as_str().expect("scene path"))
}

/// The frame count a renderer printed when it stopped ("renderer[..]: stopped after N frames").
pub fn renderer_frames(stderr: &str) -> Option<u64> {
    stderr
        .lines()
        .filter(|l| l.starts_with("renderer[") && l.contains("stopped after"))
        .find_map(|l| {
            l.split("stopped after ")
                .nth(1)?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
}

/// The lungs of `scene` baked in memory exactly as the launcher bakes them (no kernel file: their
/// kernel id is 0).
pub fn baked_models(scene: &lung_model::scene::Scene) -> Vec<lung_model::deform::LungModel> {
    scene
        .lungs
        .sides
        .iter()
        .map(|&side| {
            let k = lung_bake::kernel::bake(
                side,
                lung_model::mesh::generate::lung_of(scene.lungs.shape, side, scene.lungs.vertices)
                    .expect("generated lung"),
                &scene.bake_settings(side).expect("bake settings"),
                &|_| {},
            )
            .expect("bake");
            lung_model::deform::LungModel::from_unit_displacement(side, k.mesh, k.unit_displacement)
        })
        .collect()
}

/// The image tests' fixed view at deformation scale `scale`: patient supine at bed height, the HMD
/// at the patient's right, above the chest, `distance` times its usual distance from the point it
/// looks at (1: the image tests' framing). The supine pose is RAS → room (head at room +X, face up),
/// so the patient's right is room +Y (issue 19: before the body frame's reflection was applied the
/// eye sat at −Y, which drew the mirror image of this view from the patient's then apparent right).
pub fn fixed_state(scale: f32, distance: f32) -> renderer::DrawState {
    use glam::{Mat3, Quat, Vec3};
    let supine = Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X));
    let patient = ipc_types::Pose {
        quat: supine.to_array(),
        translation_mm: [0.0, 0.0, 1120.0],
        _pad: 0,
    };
    let target = Vec3::new(-30.0, 0.0, 1020.0);
    let eye = target + (Vec3::new(-250.0, 750.0, 1600.0) - target) * distance;
    let forward = (target - eye).normalize();
    let right = forward.cross(Vec3::Z).normalize();
    let up = right.cross(forward);
    let q = Quat::from_mat3(&Mat3::from_cols(right, up, -forward));
    renderer::DrawState {
        deform_scale: [scale, scale],
        offset_mm: [[0.0; 3]; 2],
        collapse: [0.0; 2],
        hilum_mm: [[0.0; 3]; 2],
        coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
        patient,
        hmd: ipc_types::Pose {
            quat: q.to_array(),
            translation_mm: eye.to_array(),
            _pad: 0,
        },
        pose_warning: Default::default(),
    }
}

/// What a `lungdyn demo --json` report must say of any run, fast or slow: frames were drawn, none
/// were lost or had broken hop stamps, the rates and ranges agree with the counts, nothing of the
/// instance is left in shared memory, and — given the launcher's stderr — the renderer's own count
/// of the frames it drew equals the frames the launcher received.
pub fn assert_demo_report_is_consistent(v: &serde_json::Value, stderr: &str) {
    let n = |k: &str| {
        v[k].as_f64()
            .unwrap_or_else(|| panic!("{k} missing or not a number: {v}"))
    };
    let frames = n("frames_rendered");
    assert!(frames >= 1.0, "no frame drawn: {v}");
    assert_eq!(n("lost_reports"), 0.0, "{v}");
    assert_eq!(n("bad_stamps"), 0.0, "{v}");
    assert_eq!(n("leftover_files"), 0.0, "{v}");
    assert_eq!(n("remaining_files"), 0.0, "{v}");
    let (fps, secs) = (n("fps"), n("seconds"));
    assert!(
        secs > 0.0 && (fps * secs - frames).abs() <= 1.0 + 1e-6 * frames,
        "{v}"
    );
    // Deadline misses count tracker samples on the schedule (drawn or not), not drawn frames.
    assert!(
        n("deadline_misses") <= n("tracker_samples") && n("stale_frames") <= frames,
        "{v}"
    );
    // Frames drawn on a held patient pose are counted, stale ones among them.
    assert!(
        n("patient_pose_stale_frames") <= n("patient_pose_held_frames")
            && n("patient_pose_held_frames") <= frames,
        "{v}"
    );
    let (lo, hi) = (n("volume_min_ml"), n("volume_max_ml"));
    assert!(
        lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= hi,
        "{v}"
    );
    let (p50, p99, max) = (
        n("end_to_end_p50_ms"),
        n("end_to_end_p99_ms"),
        n("end_to_end_max_ms"),
    );
    assert!(0.0 < p50 && p50 <= p99 && p99 <= max, "{v}");
    // Frames presented to a display are drawn frames, timed submit → present in order.
    assert!(n("presented_frames") <= frames, "{v}");
    let (s50, s99, smax) = (
        n("submit_to_present_p50_ms"),
        n("submit_to_present_p99_ms"),
        n("submit_to_present_max_ms"),
    );
    assert!(0.0 <= s50 && s50 <= s99 && s99 <= smax, "{v}");
    if n("presented_frames") == 0.0 {
        assert_eq!(v["present_mode"], "none", "{v}");
    }
    if !stderr.is_empty() {
        let drawn = renderer_frames(stderr)
            .unwrap_or_else(|| panic!("the renderer did not report its frames: {stderr}"));
        assert_eq!(
            drawn as f64, frames,
            "launcher received every frame drawn: {stderr}"
        );
    }
}

/// `scene` with every lung baked in process (as the launcher bakes them) into kernel files under a
/// fresh folder named by `tag`, named in `[lungs.kernels]`.
pub fn scene_with_kernels(
    mut scene: lung_model::scene::Scene,
    tag: &str,
) -> lung_model::scene::Scene {
    let dir = std::env::temp_dir().join(format!("lungdyn-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp folder");
    for side in scene.lungs.sides.clone() {
        let path = dir.join(format!("{}.kernel", side.name()));
        lung_bake::kernel::bake(
            side,
            lung_model::mesh::generate::lung(side, scene.lungs.vertices).expect("generated lung"),
            &scene.bake_settings(side).expect("bake settings"),
            &|_| {},
        )
        .expect("bake")
        .write(&path)
        .expect("write kernel");
        scene.lungs.kernels.set(side, path);
    }
    scene
}

/// Whether `xvfb-run` can give a windowed test a display. Without it the test fails naming the
/// package, unless `LUNGDYN_SKIP_DISPLAY=1` (then it is skipped, said aloud and counted).
pub fn xvfb_available() -> bool {
    lungdyn_needs::display()
}

/// An engine frame at `tick` for `lungs` (a scene's lung models, in `[lungs] sides` order): each
/// lung active with its kernel id and `volume_ml` in its side's entry ([`ipc_types::LUNG_RIGHT`],
/// [`ipc_types::LUNG_LEFT`]) whatever the order, as the engine publishes it — for driving a
/// renderer session on in-memory ports.
pub fn engine_frame(
    lungs: &[lung_model::deform::LungModel],
    tick: u64,
    volume_ml: f32,
) -> ipc_types::EngineFrame {
    let mut f = ipc_types::EngineFrame {
        layout_version: ipc_types::LAYOUT_VERSION,
        tick,
        ..Default::default()
    };
    for l in lungs {
        let entry = &mut f.lungs[l.side.index()];
        entry.kernel_id = l.kernel_id;
        entry.flags = ipc_types::lung_flags::ACTIVE;
        entry.volume_ml = volume_ml;
    }
    f
}

#[cfg(test)]
mod tests {
    use ipc_types::{lung_flags, LUNG_LEFT, LUNG_RIGHT};
    use lung_model::scene::SceneExt;

    /// Each lung's kernel id, flags and volume land in its side's entry for either `[lungs] sides`
    /// order, and a lung the scene leaves out stays inactive (slot order once put the flags of a
    /// left-only scene on the right lung's entry).
    #[test]
    fn engine_frame_fills_each_lungs_own_side_in_either_order() {
        for sides in [
            "[\"left\", \"right\"]",
            "[\"right\", \"left\"]",
            "[\"left\"]",
            "[\"right\"]",
        ] {
            let scene = lung_model::scene::Scene::parse(
                &format!("[lungs]\nsides = {sides}\nvertices = 100\n"),
                "test",
            )
            .unwrap();
            let mut lungs = crate::baked_models(&scene);
            for l in &mut lungs {
                l.kernel_id = 100 + l.side.index() as u64;
            }
            let f = crate::engine_frame(&lungs, 7, 1234.0);
            assert_eq!(f.tick, 7);
            for (index, side) in [
                (LUNG_RIGHT, lung_model::mesh::Side::Right),
                (LUNG_LEFT, lung_model::mesh::Side::Left),
            ] {
                let e = &f.lungs[index];
                if scene.lungs.sides.contains(&side) {
                    assert_eq!(
                        (e.kernel_id, e.flags, e.volume_ml),
                        (100 + index as u64, lung_flags::ACTIVE, 1234.0),
                        "sides = {sides}: {side:?}"
                    );
                } else {
                    assert_eq!(
                        (e.kernel_id, e.flags, e.volume_ml),
                        (0, 0, 0.0),
                        "sides = {sides}: {side:?} is not simulated"
                    );
                }
            }
        }
    }
}
