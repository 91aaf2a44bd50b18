//! The rig's files as JSON: a calibration (`lungdyn register`, `lungdyn scene check`) and an HMD optics
//! file (`lungdyn hmd check`, `lungdyn scene check`), one shape wherever they are shown.

use std::path::Path;

use serde_json::{json, Value};
use tracker_pose::calib::Calibration;
use tracker_pose::optics::Optics;

/// What a calibration's model points are (JSON `model_frame`; `lungdyn register` documents the frame).
pub const MODEL_FRAME: &str =
    "ras: the body-frame points with X negated (lung_model::frame::body_to_ras)";

/// An optics file as `lungdyn hmd check --json` shows it (also in `lungdyn scene check`).
pub fn optics_json(file: Option<&Path>, o: &Optics) -> Value {
    let eyes: Vec<Value> = (0..2)
        .map(|i| {
            let e = &o.eyes[i];
            let q = e.rotation.quaternion();
            json!({
                "eye": if i == 0 { "left" } else { "right" },
                "offset_mm": [e.offset_mm.x, e.offset_mm.y, e.offset_mm.z],
                "rotation_xyzw": [q.i, q.j, q.k, q.w],
                "horizontal_fov_deg": o.horizontal_fov_deg(i),
                "vertical_fov_deg": o.vertical_fov_deg(i),
                "projection_col_major": o.projection(i),
            })
        })
        .collect();
    json!({
        "file": file.map(|p| p.display().to_string()),
        "width_px": o.width_px,
        "height_px": o.height_px,
        "ipd_mm": o.ipd_mm,
        "near_mm": o.near_mm,
        "far_mm": o.far_mm,
        "eyes": eyes,
    })
}

/// A calibration as `lungdyn scene check` shows it.
pub fn calibration_json(file: &Path, c: &Calibration) -> Value {
    let q = c.rotation.quaternion();
    let t = c.translation_mm;
    json!({
        "file": file.display().to_string(),
        "rotation_xyzw": [q.i, q.j, q.k, q.w],
        "rotation_deg": c.rotation.angle().to_degrees(),
        "model_frame": MODEL_FRAME,
        "translation_mm": [t.x, t.y, t.z],
        "fre_rms_mm": c.registration.as_ref().map(|r| r.fre_rms_mm),
        "fiducials": c.registration.as_ref().map(|r| r.fiducials),
    })
}
