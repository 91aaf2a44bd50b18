//! `lungdyn register`: the lungs' model frame onto the patient reference from fiducials, written as
//! a calibration file (`tracker_pose::calib`); and `lungdyn hmd check`: load and show an HMD optics
//! file (`tracker_pose::optics`).
//!
//! Point files are text: one fiducial per line as `x y z` or `label x y z` (separated by commas,
//! semicolons, spaces or tabs), millimetres; `#` starts a comment; one header line is allowed. The
//! model points are in the lung meshes' body frame, the tracker points in the patient reference
//! tool's frame (a tracked pointer's tip relative to the reference, as PLUS and 3D Slicer give it).
//! When both files label every point, fiducials are paired by label, else by order.
//!
//! The body frame (+X patient left, +Y anterior, +Z superior) is left-handed and the tool's frame is
//! not: no rotation moves a real patient's body-frame fiducials onto their tracked positions, only
//! a reflection does. The model points are therefore taken to RAS first
//! (`lung_model::frame::body_to_ras`, X negated, issue 19) and the rigid fit is RAS → reference;
//! the calibration (format 2) says so, and the renderer reflects the body frame back at the same
//! boundary. A tracker list that is the mirror image of the model's still fits best as a
//! reflection and is refused.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use lung_model::input::{read_text_bounded, ReadLimits};
use serde_json::{json, Value};
use tracker_pose::calib::Calibration;
use tracker_pose::optics::Optics;
use tracker_pose::registration::{register, COLLINEAR_RATIO, THIN_RATIO};

use crate::input_args::InputArgs;
pub use lungdyn_launcher::rig_json::{calibration_json, optics_json, MODEL_FRAME};

/// Most fiducials read from one file.
pub const MAX_POINTS: usize = 10_000;

/// Options of `lungdyn register`.
#[derive(Debug, Clone, clap::Args)]
pub struct RegisterArgs {
    /// Fiducials in the model (body) frame, mm (+X patient left, +Y anterior, +Z superior).
    #[arg(long, value_name = "FILE")]
    pub model_points: PathBuf,
    /// The same fiducials measured in the patient reference tool's frame, mm.
    #[arg(long, value_name = "FILE")]
    pub tracker_points: PathBuf,
    /// The calibration file to write (TOML; replaced atomically).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
    /// Input limits.
    #[command(flatten)]
    pub input: InputArgs,
}

/// Fiducials of one file.
#[derive(Debug, Clone, PartialEq)]
pub struct Points {
    /// Labels, when every point has one.
    pub labels: Option<Vec<String>>,
    /// Coordinates, mm.
    pub points: Vec<[f64; 3]>,
}

/// Parse a point file's text.
pub fn parse_points(text: &str, path: &Path) -> anyhow::Result<Points> {
    let mut labels = Vec::new();
    let mut points = Vec::new();
    let mut labelled: Option<bool> = None;
    let mut header_seen = false;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let fields: Vec<&str> = line
            .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
            .filter(|f| !f.is_empty())
            .collect();
        let nums: Vec<Option<f64>> = fields.iter().map(|f| f.parse::<f64>().ok()).collect();
        let (label, xyz) = match fields.len() {
            3 if nums.iter().all(Option::is_some) => (None, [nums[0], nums[1], nums[2]]),
            4 if nums[1..].iter().all(Option::is_some) => {
                (Some(fields[0].to_string()), [nums[1], nums[2], nums[3]])
            }
            _ if points.is_empty() && !header_seen && nums.iter().any(Option::is_none) => {
                header_seen = true;
                continue;
            }
            _ => bail!(
                "{}:{}: {line:?} is not a fiducial: write `x y z` or `label x y z` in mm",
                path.display(),
                i + 1
            ),
        };
        let xyz = xyz.map(|v| v.unwrap_or(f64::NAN));
        if !xyz.iter().all(|v| v.is_finite() && v.abs() <= 1e5) {
            bail!(
                "{}:{}: coordinates {xyz:?} must be finite and within 100 m (mm expected)",
                path.display(),
                i + 1
            );
        }
        match (labelled, label.is_some()) {
            (Some(a), b) if a != b => bail!(
                "{}:{}: some fiducials have labels and some do not: label all or none",
                path.display(),
                i + 1
            ),
            _ => labelled = Some(label.is_some()),
        }
        if let Some(l) = label {
            if labels.contains(&l) {
                bail!("{}:{}: label {l:?} is used twice", path.display(), i + 1);
            }
            labels.push(l);
        }
        points.push(xyz);
        if points.len() > MAX_POINTS {
            bail!("{} has more than {MAX_POINTS} fiducials", path.display());
        }
    }
    Ok(Points {
        labels: (labelled == Some(true)).then_some(labels),
        points,
    })
}

/// Pair the two lists (by label when both have labels): model points, tracker points, labels.
pub fn pair(
    model: &Points,
    tracker: &Points,
) -> anyhow::Result<(Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<String>)> {
    match (&model.labels, &tracker.labels) {
        (Some(ml), Some(tl)) => {
            let mut b = Vec::new();
            for l in ml {
                let i = tl.iter().position(|x| x == l).with_context(|| {
                    format!("model fiducial {l:?} has no tracker point with that label")
                })?;
                b.push(tracker.points[i]);
            }
            if let Some(extra) = tl.iter().find(|l| !ml.contains(l)) {
                bail!("tracker fiducial {extra:?} has no model point with that label");
            }
            Ok((model.points.clone(), b, ml.clone()))
        }
        _ => {
            let labels = model
                .labels
                .clone()
                .or_else(|| tracker.labels.clone())
                .unwrap_or_else(|| (1..=model.points.len()).map(|i| i.to_string()).collect());
            Ok((model.points.clone(), tracker.points.clone(), labels))
        }
    }
}

/// Run `lungdyn register`; the result as JSON.
pub fn run(args: &RegisterArgs) -> anyhow::Result<Value> {
    let limits = args.input.limits(ReadLimits::TABLE);
    let read =
        |p: &Path| -> anyhow::Result<Points> { parse_points(&read_text_bounded(p, limits)?, p) };
    let model = read(&args.model_points)?;
    let tracker = read(&args.tracker_points)?;
    let (a, b, labels) = pair(&model, &tracker)?;
    // Body frame → RAS: the only frame a rotation can move onto the tool's (see the module doc).
    let a: Vec<[f64; 3]> = a
        .iter()
        .map(|p| lung_model::frame::body_to_ras(glam::DVec3::from(*p)).to_array())
        .collect();
    // Refused (non-zero exit, nothing written) when no usable rigid fit exists: duplicates,
    // collinear fiducials, a unit or scale mismatch, an FRE against the spread (see
    // tracker_pose::registration).
    let r = register(&a, &b).context("registration refused; nothing was written")?;
    for w in &r.warnings {
        eprintln!("lungdyn: warning: {w}");
    }
    let calib = Calibration::from_registration(
        &r,
        &args.model_points.display().to_string(),
        &args.tracker_points.display().to_string(),
    );
    let text = calib.to_toml();
    // Check what is written reads back before replacing anything.
    Calibration::from_toml(&text, "the new calibration")
        .context("the calibration does not read back")?;
    outfile::write_atomically(&args.out, |w| w.write_all(text.as_bytes()))?;
    let q = r.rotation.quaternion();
    let m = r.rotation.to_rotation_matrix();
    Ok(json!({
        "out": args.out.display().to_string(),
        "fiducials": a.len(),
        "paired_by": if model.labels.is_some() && tracker.labels.is_some() { "label" } else { "order" },
        "model_frame": MODEL_FRAME,
        "rotation_xyzw": [q.i, q.j, q.k, q.w],
        "rotation_matrix": (0..3).map(|i| (0..3).map(|j| m.matrix()[(i, j)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
        "translation_mm": [r.translation_mm.x, r.translation_mm.y, r.translation_mm.z],
        "fre_rms_mm": r.fre_rms_mm,
        "fre_mm": labels.iter().zip(&r.fre_mm).map(|(l, e)| json!({"label": l, "fre_mm": e})).collect::<Vec<_>>(),
        "singular_values_mm": r.singular_values,
        "spread_ratio": r.spread_ratio(),
        "tracker_spread_ratio": r.tracker_spread_ratio,
        "spread_mm": r.spread_mm,
        "scale": r.scale,
        "warnings": r.warnings,
    }))
}

/// What `lungdyn register` prints.
pub fn text(v: &Value) -> String {
    let mut s = format!(
        "registered {} fiducials (paired by {}): FRE RMS {:.3} mm\n",
        v["fiducials"],
        v["paired_by"].as_str().unwrap_or(""),
        v["fre_rms_mm"].as_f64().unwrap_or(0.0)
    );
    for p in v["fre_mm"].as_array().into_iter().flatten() {
        s += &format!(
            "  {:<12} FRE {:>8.3} mm\n",
            p["label"].as_str().unwrap_or(""),
            p["fre_mm"].as_f64().unwrap_or(0.0)
        );
    }
    let f = |k: &str| -> Vec<String> {
        v[k].as_array()
            .into_iter()
            .flatten()
            .map(|x| format!("{:.6}", x.as_f64().unwrap_or(0.0)))
            .collect()
    };
    s += &format!(
        "model (RAS: body X negated) -> reference: rotation (x y z w) [{}], translation [{}] mm\n",
        f("rotation_xyzw").join(", "),
        f("translation_mm").join(", ")
    );
    s += &format!(
        "fiducial spread: {:.1} mm RMS from the centroid; sigma2/sigma1 = {:.3} model, {:.3} tracker \
         (refused below {COLLINEAR_RATIO}, warned below {THIN_RATIO}); size tracker/model {:.4}\n",
        v["spread_mm"].as_f64().unwrap_or(0.0),
        v["spread_ratio"].as_f64().unwrap_or(0.0),
        v["tracker_spread_ratio"].as_f64().unwrap_or(0.0),
        v["scale"].as_f64().unwrap_or(0.0)
    );
    for w in v["warnings"].as_array().into_iter().flatten() {
        s += &format!("warning: {}\n", w.as_str().unwrap_or(""));
    }
    s += &format!("wrote {}\n", v["out"].as_str().unwrap_or(""));
    s
}

/// Options of `lungdyn hmd check`.
#[derive(Debug, Clone, clap::Args)]
pub struct HmdArgs {
    /// The HMD optics file (the seed's HMD when omitted: 800x600 per eye, 70 degrees, 64 mm IPD).
    pub file: Option<PathBuf>,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Run `lungdyn hmd check`.
pub fn hmd(args: &HmdArgs) -> anyhow::Result<Value> {
    let o = match &args.file {
        Some(p) => Optics::load(p)?,
        None => Optics::default(),
    };
    Ok(optics_json(args.file.as_deref(), &o))
}

/// What `lungdyn hmd check` prints.
pub fn hmd_text(v: &Value) -> String {
    let mut s = format!(
        "{}: {} x {} px per eye, IPD {} mm, near {} mm, far {} mm\n",
        v["file"].as_str().unwrap_or("built-in seed HMD"),
        v["width_px"],
        v["height_px"],
        v["ipd_mm"],
        v["near_mm"],
        v["far_mm"]
    );
    for e in v["eyes"].as_array().into_iter().flatten() {
        s += &format!(
            "  {:<5} eye at {} mm in the HMD tool frame, field of view {:.1} x {:.1} degrees\n",
            e["eye"].as_str().unwrap_or(""),
            e["offset_mm"],
            e["horizontal_fov_deg"].as_f64().unwrap_or(0.0),
            e["vertical_fov_deg"].as_f64().unwrap_or(0.0)
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_files_parse_with_labels_headers_and_comments() {
        let p = parse_points(
            "name,x,y,z\n# comment\nA, 1, 2, 3\nB;4;5;6 # trailing\n\nC 7 8 9\n",
            Path::new("a.csv"),
        )
        .unwrap();
        assert_eq!(
            p.labels.as_deref(),
            Some(&["A".to_string(), "B".into(), "C".into()][..])
        );
        assert_eq!(
            p.points,
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]
        );
        let q = parse_points("1 2 3\n4 5 6\n", Path::new("b.txt")).unwrap();
        assert_eq!(q.labels, None);
        for bad in [
            "1 2\n",
            "A 1 2 3\n4 5 6\n",
            "1 2 nan\n",
            "A 1 2 3\nA 4 5 6\n",
            "1 2 3\nx y z\n",
        ] {
            assert!(parse_points(bad, Path::new("c.txt")).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn labelled_lists_pair_by_label_in_any_order() {
        let a = parse_points("A 0 0 0\nB 1 0 0\nC 0 1 0\n", Path::new("a")).unwrap();
        let b = parse_points("C 5 6 7\nA 1 1 1\nB 2 2 2\n", Path::new("b")).unwrap();
        let (_, t, l) = pair(&a, &b).unwrap();
        assert_eq!(t, vec![[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [5.0, 6.0, 7.0]]);
        assert_eq!(l, ["A", "B", "C"]);
        let c = parse_points("A 1 1 1\nB 2 2 2\nD 5 6 7\n", Path::new("c")).unwrap();
        assert!(pair(&a, &c).is_err());
    }
}
