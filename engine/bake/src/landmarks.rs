//! Landmarks in a stated coordinate frame.
//!
//! lungdyn works in the *body frame*: millimetres, +X towards the patient's left, +Y anterior, +Z
//! superior (head). Imaging data come in other frames: DICOM/ITK physical coordinates are LPS (+X
//! left, +Y posterior, +Z superior), 3D Slicer's are RAS (+X right, +Y anterior, +Z superior), and
//! landmark files such as DIR-Lab's list *voxel indices*, counted from the first column, row and
//! slice of the image — for DIR-Lab from the patient's right, anterior and head (slice 1 is the top
//! of the chest). Read in the wrong frame a fit still "works" and is silently worse (≈ 1.4× for the
//! seed's power law on DIR-Lab, with its Z exponent collapsing to 0), so every reader states its
//! frame, converts explicitly, and the fit checks the result against what breathing does
//! (`motion_models::check_frame`). The body frame is the mirror image of RAS in X (left-handed,
//! `lung_model::frame`): LPS and RAS conversions go through that module's one definition.

use std::path::{Path, PathBuf};

use glam::DVec3;
use thiserror::Error;

/// How the index of a voxel axis runs in the body: which body axis and which way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelAxis {
    /// Body axis (0 X, 1 Y, 2 Z).
    pub body: usize,
    /// +1 when the index grows towards +X/+Y/+Z of the body frame (left, anterior, superior).
    pub sign: f64,
}

/// The three voxel axes, as `R>L,A>P,S>I` (the index grows from the first to the second letter).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelAxes(pub [VoxelAxis; 3]);

impl VoxelAxes {
    /// DIR-Lab's (and standard axial DICOM's) order: columns right → left, rows anterior →
    /// posterior, slices superior → inferior.
    pub const DIRLAB: VoxelAxes = VoxelAxes([
        VoxelAxis { body: 0, sign: 1.0 },
        VoxelAxis {
            body: 1,
            sign: -1.0,
        },
        VoxelAxis {
            body: 2,
            sign: -1.0,
        },
    ]);

    /// The axes as written on the command line.
    pub fn describe(&self) -> String {
        self.0
            .iter()
            .map(|a| {
                let (neg, pos) = [("R", "L"), ("P", "A"), ("I", "S")][a.body];
                if a.sign > 0.0 {
                    format!("{neg}>{pos}")
                } else {
                    format!("{pos}>{neg}")
                }
            })
            .collect::<Vec<_>>()
            .join(",")
    }
}

impl std::str::FromStr for VoxelAxes {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "voxel axes {s:?}: give three directions like R>L,A>P,S>I (the index grows from the first \
                 letter to the second; R/L, A/P, S/I each once)"
            )
        };
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        if parts.len() != 3 {
            return Err(bad());
        }
        let mut axes = [VoxelAxis { body: 0, sign: 1.0 }; 3];
        let mut used = [false; 3];
        for (k, p) in parts.iter().enumerate() {
            let u = p.to_ascii_uppercase();
            let (from, to) = u.split_once('>').ok_or_else(bad)?;
            let (body, sign) = match (from, to) {
                ("R", "L") => (0, 1.0),
                ("L", "R") => (0, -1.0),
                ("P", "A") => (1, 1.0),
                ("A", "P") => (1, -1.0),
                ("I", "S") => (2, 1.0),
                ("S", "I") => (2, -1.0),
                _ => return Err(bad()),
            };
            if used[body] {
                return Err(bad());
            }
            used[body] = true;
            axes[k] = VoxelAxis { body, sign };
        }
        Ok(VoxelAxes(axes))
    }
}

/// The frame of a file's coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Frame {
    /// lungdyn's body frame, mm: +X left, +Y anterior, +Z superior.
    Body,
    /// DICOM/ITK physical coordinates, mm: +X left, +Y posterior, +Z superior.
    Lps,
    /// 3D Slicer coordinates, mm: +X right, +Y anterior, +Z superior.
    Ras,
    /// Voxel indices: `(index − base) × spacing`, each axis running as `axes` says.
    Voxel {
        /// How the three index axes run.
        axes: VoxelAxes,
        /// First index (0 or 1).
        base: u8,
        /// Voxel size along the three index axes, mm.
        spacing: [f64; 3],
    },
}

impl Frame {
    /// Body-frame position of coordinates `c` given in this frame.
    pub fn to_body(&self, c: [f64; 3]) -> DVec3 {
        match self {
            Frame::Body => DVec3::from(c),
            // The one conversion of each (lung_model::frame): the same body point as before the
            // body ↔ room reflection was named (issue 19).
            Frame::Lps => lung_model::frame::lps_to_body(DVec3::from(c)),
            Frame::Ras => lung_model::frame::ras_to_body(DVec3::from(c)),
            Frame::Voxel {
                axes,
                base,
                spacing,
            } => {
                let mut out = [0.0; 3];
                for k in 0..3 {
                    out[axes.0[k].body] = axes.0[k].sign * (c[k] - *base as f64) * spacing[k];
                }
                DVec3::from(out)
            }
        }
    }

    /// A name for reports and JSON ("body", "lps", "ras", "voxel").
    pub fn name(&self) -> &'static str {
        match self {
            Frame::Body => "body",
            Frame::Lps => "lps",
            Frame::Ras => "ras",
            Frame::Voxel { .. } => "voxel",
        }
    }

    /// One line saying how coordinates were read.
    pub fn describe(&self) -> String {
        match self {
            Frame::Body => "body frame, mm (+X left, +Y anterior, +Z superior)".into(),
            Frame::Lps => "LPS, mm (converted: Y negated)".into(),
            Frame::Ras => "RAS, mm (converted: X negated)".into(),
            Frame::Voxel {
                axes,
                base,
                spacing,
            } => format!(
                "voxel indices ({base}-based), axes {}, spacing {} x {} x {} mm",
                axes.describe(),
                spacing[0],
                spacing[1],
                spacing[2]
            ),
        }
    }
}

/// Why a landmark file could not be read.
#[derive(Debug, Error)]
pub enum LandmarkError {
    /// Not readable within the limits.
    #[error(transparent)]
    Input(#[from] lung_model::input::InputError),
    /// A line is not three numbers.
    #[error("{}:{line}: expected three numbers `x y z` (separated by spaces, tabs or commas), found {found}", path.display())]
    Fields {
        /// File.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// What was found.
        found: String,
    },
    /// A field is not a finite number.
    #[error("{}:{line}: {field:?} is not a finite number", path.display())]
    Number {
        /// File.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The field.
        field: String,
    },
    /// A voxel index below the first index of the stated base.
    #[error("{}:{line}: index {value} is below {base}, the first index of a {base}-based file: check --index-base", path.display())]
    Index {
        /// File.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The index.
        value: f64,
        /// The stated base.
        base: u8,
    },
    /// No points at all.
    #[error("{}: no points", path.display())]
    Empty {
        /// File.
        path: PathBuf,
    },
}

/// Parse point text: one point per line, three numbers separated by spaces, tabs or commas (CRLF,
/// blank lines and `#` comments tolerated). Coordinates as written (no frame applied).
pub fn parse(path: &Path, text: &str) -> Result<Vec<[f64; 3]>, LandmarkError> {
    let mut pts = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if fields.len() != 3 {
            return Err(LandmarkError::Fields {
                path: path.to_path_buf(),
                line: i + 1,
                found: format!("{} fields", fields.len()),
            });
        }
        let mut p = [0.0; 3];
        for (k, f) in fields.iter().enumerate() {
            p[k] = f
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| LandmarkError::Number {
                    path: path.to_path_buf(),
                    line: i + 1,
                    field: f.to_string(),
                })?;
        }
        pts.push(p);
    }
    if pts.is_empty() {
        return Err(LandmarkError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(pts)
}

/// Read a landmark file in `frame` (bounded) and convert it to the body frame.
pub fn read(
    path: &Path,
    frame: &Frame,
    limits: lung_model::input::ReadLimits,
) -> Result<Vec<DVec3>, LandmarkError> {
    let text = lung_model::input::read_text_bounded(path, limits)?;
    let raw = parse(path, &text)?;
    if let Frame::Voxel { base, .. } = frame {
        // Lines are counted again for the message: the n-th point is not the n-th line.
        let mut n = 0;
        for (i, l) in text.lines().enumerate() {
            let l = l.trim();
            if l.is_empty() || l.starts_with('#') {
                continue;
            }
            if let Some(v) = raw[n].iter().find(|v| **v < *base as f64) {
                return Err(LandmarkError::Index {
                    path: path.to_path_buf(),
                    line: i + 1,
                    value: *v,
                    base: *base,
                });
            }
            n += 1;
        }
    }
    Ok(raw.into_iter().map(|c| frame.to_body(c)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxel_axes_parse_print_and_refuse_nonsense() {
        let a: VoxelAxes = "R>L,A>P,S>I".parse().unwrap();
        assert_eq!(a, VoxelAxes::DIRLAB);
        assert_eq!(a.describe(), "R>L,A>P,S>I");
        let b: VoxelAxes = "s>i, l>r, p>a".parse().unwrap();
        assert_eq!(b.describe(), "S>I,L>R,P>A");
        for bad in ["R>L,A>P", "R>L,R>L,S>I", "R>A,A>P,S>I", "RL,AP,SI", ""] {
            assert!(bad.parse::<VoxelAxes>().is_err(), "{bad}");
        }
    }

    #[test]
    fn one_motion_in_every_frame_gives_one_body_position() {
        // A point 10 mm left, 20 mm anterior, 30 mm superior of the origin.
        let body = DVec3::new(10.0, 20.0, 30.0);
        assert_eq!(Frame::Body.to_body([10.0, 20.0, 30.0]), body);
        assert_eq!(Frame::Lps.to_body([10.0, -20.0, 30.0]), body);
        assert_eq!(Frame::Ras.to_body([-10.0, 20.0, 30.0]), body);
        // DIR-Lab voxel (1-based, 2 mm voxels, 5 mm slices): column 6 → +10 mm left, row −9 → +20 mm
        // anterior (rows grow posteriorly), slice −5 → +30 mm superior (slices grow downwards).
        let dirlab = Frame::Voxel {
            axes: VoxelAxes::DIRLAB,
            base: 1,
            spacing: [2.0, 2.0, 5.0],
        };
        assert_eq!(dirlab.to_body([6.0, -9.0, -5.0]), body);
        // A permuted voxel layout (slices first).
        let perm = Frame::Voxel {
            axes: "I>S,R>L,P>A".parse().unwrap(),
            base: 0,
            spacing: [5.0, 2.0, 2.0],
        };
        assert_eq!(perm.to_body([6.0, 5.0, 10.0]), body);
    }

    #[test]
    fn dirlab_style_text_parses_with_tabs_crlf_and_commas() {
        let p = Path::new("x.txt");
        let pts = parse(p, "88\t104\t55\r\n 89 105 56\t\r\n\r\n90,106,57\n").unwrap();
        assert_eq!(
            pts,
            vec![
                [88.0, 104.0, 55.0],
                [89.0, 105.0, 56.0],
                [90.0, 106.0, 57.0]
            ]
        );
        let e = parse(p, "1 2 3\n1 2\n").unwrap_err().to_string();
        assert!(e.contains("x.txt:2") && e.contains("2 fields"), "{e}");
        let e = parse(p, "1 nan 3\n").unwrap_err().to_string();
        assert!(e.contains("\"nan\""), "{e}");
        assert!(parse(p, "# only a comment\n").is_err());
    }

    #[test]
    fn an_index_below_the_base_is_refused() {
        let dir = std::env::temp_dir().join(format!("lungdyn-landmarks-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("zero.txt");
        std::fs::write(&f, "1 1 1\n0 4 5\n").unwrap();
        let frame = Frame::Voxel {
            axes: VoxelAxes::DIRLAB,
            base: 1,
            spacing: [1.0; 3],
        };
        let e = read(&f, &frame, lung_model::input::ReadLimits::TABLE)
            .unwrap_err()
            .to_string();
        assert!(e.contains(":2:") && e.contains("--index-base"), "{e}");
    }
}
