//! A label image in memory: integer labels on a voxel grid, and where each voxel is in the body
//! frame (mm), from the file's own header (never guessed).

use glam::{DMat3, DVec3};

/// The anatomical direction a world or voxel axis points to (its positive end).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dir {
    /// Patient left.
    L,
    /// Patient right.
    R,
    /// Anterior.
    A,
    /// Posterior.
    P,
    /// Superior.
    S,
    /// Inferior.
    I,
}

impl Dir {
    /// This direction as a body-frame unit vector (+X left, +Y anterior, +Z superior).
    pub fn body(self) -> DVec3 {
        match self {
            Dir::L => DVec3::X,
            Dir::R => -DVec3::X,
            Dir::A => DVec3::Y,
            Dir::P => -DVec3::Y,
            Dir::S => DVec3::Z,
            Dir::I => -DVec3::Z,
        }
    }

    /// The letter.
    pub fn letter(self) -> char {
        match self {
            Dir::L => 'L',
            Dir::R => 'R',
            Dir::A => 'A',
            Dir::P => 'P',
            Dir::S => 'S',
            Dir::I => 'I',
        }
    }

    /// The direction a body-frame vector points to most.
    pub fn nearest(v: DVec3) -> Dir {
        let a = v.abs();
        if a.x >= a.y && a.x >= a.z {
            if v.x >= 0.0 {
                Dir::L
            } else {
                Dir::R
            }
        } else if a.y >= a.z {
            if v.y >= 0.0 {
                Dir::A
            } else {
                Dir::P
            }
        } else if v.z >= 0.0 {
            Dir::S
        } else {
            Dir::I
        }
    }

    fn from_letter(c: char) -> Option<Dir> {
        Some(match c.to_ascii_uppercase() {
            'L' => Dir::L,
            'R' => Dir::R,
            'A' => Dir::A,
            'P' => Dir::P,
            'S' => Dir::S,
            'I' => Dir::I,
            _ => return None,
        })
    }
}

/// Three axis codes such as `RAS` or `LPS`: where each axis's positive end points.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Axes(pub [Dir; 3]);

impl Axes {
    /// RAS: NIfTI's world, 3D Slicer's.
    pub const RAS: Axes = Axes([Dir::R, Dir::A, Dir::S]);
    /// LPS: DICOM's and ITK's world (MetaImage, most NRRD files).
    pub const LPS: Axes = Axes([Dir::L, Dir::P, Dir::S]);

    /// The matrix taking coordinates along these axes to the body frame.
    pub fn to_body(self) -> DMat3 {
        DMat3::from_cols(self.0[0].body(), self.0[1].body(), self.0[2].body())
    }

    /// The codes as text ("RAS").
    pub fn code(self) -> String {
        self.0.iter().map(|d| d.letter()).collect()
    }
}

impl std::str::FromStr for Axes {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let letters: Vec<char> = s.chars().collect();
        let bad = || {
            format!(
                "axis codes {s:?}: give three letters, one of L/R, one of A/P and one of S/I \
                 (e.g. RAS, LPS, LAS), each the direction its axis's positive end points to"
            )
        };
        if letters.len() != 3 {
            return Err(bad());
        }
        let d: Vec<Dir> = letters
            .iter()
            .map(|&c| Dir::from_letter(c))
            .collect::<Option<_>>()
            .ok_or_else(bad)?;
        let group = |d: Dir| match d {
            Dir::L | Dir::R => 0,
            Dir::A | Dir::P => 1,
            Dir::S | Dir::I => 2,
        };
        let mut seen = [false; 3];
        for &x in &d {
            if std::mem::replace(&mut seen[group(x)], true) {
                return Err(bad());
            }
        }
        Ok(Axes([d[0], d[1], d[2]]))
    }
}

/// Voxel index → body-frame position (mm): `p = linear · [i, j, k] + origin`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelToBody {
    /// Columns: the body-frame step (mm) of one voxel along each index axis.
    pub linear: DMat3,
    /// The body-frame position of voxel (0, 0, 0)'s centre, mm.
    pub origin: DVec3,
}

impl VoxelToBody {
    /// The body-frame position of (fractional) voxel index `ijk`.
    pub fn apply(&self, ijk: DVec3) -> DVec3 {
        self.linear * ijk + self.origin
    }

    /// Voxel spacing along each index axis, mm.
    pub fn spacing(&self) -> [f64; 3] {
        [
            self.linear.x_axis.length(),
            self.linear.y_axis.length(),
            self.linear.z_axis.length(),
        ]
    }

    /// The anatomical direction of each index axis ("the voxel axes"), e.g. LPS.
    pub fn voxel_axes(&self) -> Axes {
        Axes([
            Dir::nearest(self.linear.x_axis),
            Dir::nearest(self.linear.y_axis),
            Dir::nearest(self.linear.z_axis),
        ])
    }

    /// Determinant sign: +1 for a right-handed voxel grid in RAS (-1 in the body frame).
    pub fn determinant(&self) -> f64 {
        self.linear.determinant()
    }

    /// The same grid with its voxel axes re-declared as `axes` (spacing and the origin's distance
    /// from the grid kept): what `--axes` does when a header's directions are wrong.
    pub fn with_axes(&self, axes: Axes) -> VoxelToBody {
        let s = self.spacing();
        let linear = DMat3::from_cols(
            axes.0[0].body() * s[0],
            axes.0[1].body() * s[1],
            axes.0[2].body() * s[2],
        );
        VoxelToBody {
            linear,
            origin: self.origin,
        }
    }
}

/// Where a volume's frame came from, for the report.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FrameSource {
    /// The file format ("NIfTI-1", "NRRD", "MetaImage").
    pub format: &'static str,
    /// Which header fields gave the frame ("sform (code 2, aligned)", "space directions, LPS").
    pub from: String,
    /// The world frame of the header ("RAS", "LPS", ...).
    pub world: String,
    /// Spacing along each voxel axis, mm.
    pub spacing_mm: [f64; 3],
    /// The anatomical direction of each voxel axis per the header ("LPS").
    pub voxel_axes: String,
    /// The voxel axes used instead, when `--axes` overrode the header.
    pub axes_override: Option<String>,
}

/// A label image: `labels[i + nx·(j + ny·k)]` for voxel `(i, j, k)`.
#[derive(Debug, Clone)]
pub struct LabelVolume {
    /// Voxels along each index axis.
    pub dims: [usize; 3],
    /// Label values (0 = background), x fastest.
    pub labels: Vec<u16>,
    /// Voxel → body frame.
    pub to_body: VoxelToBody,
    /// Where the frame came from.
    pub frame: FrameSource,
    /// Segment names by label value, where the file names them (3D Slicer's .seg.nrrd), and names
    /// of the files the labels came from (one binary file per structure, as TotalSegmentator writes).
    pub names: Vec<(u16, String)>,
    /// Things the header left unsaid or said oddly, for the report.
    pub notes: Vec<String>,
}

impl LabelVolume {
    /// Linear index of voxel (i, j, k).
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Volume of one voxel, ml.
    pub fn voxel_ml(&self) -> f64 {
        self.to_body.linear.determinant().abs() / 1000.0
    }

    /// Distinct nonzero labels and their voxel counts, ascending by value.
    pub fn histogram(&self) -> Vec<(u16, usize)> {
        let mut counts = vec![0usize; 1 << 16];
        for &l in &self.labels {
            counts[l as usize] += 1;
        }
        counts
            .iter()
            .enumerate()
            .skip(1)
            .filter(|(_, &c)| c > 0)
            .map(|(v, &c)| (v as u16, c))
            .collect()
    }
}

/// Checks every reader makes of a grid: dimensions, spacing in mm, a finite, invertible frame.
pub(crate) fn check_grid(dims: [usize; 3], to_body: &VoxelToBody) -> Result<(), String> {
    if dims.contains(&0) {
        return Err(format!("the image has no voxels (sizes {dims:?})"));
    }
    if dims.iter().any(|&d| d > 8192) || dims.iter().product::<usize>() > 1 << 31 {
        return Err(format!(
            "the image is {}×{}×{} voxels: more than lungdyn reads (8192 per axis, 2^31 in all)",
            dims[0], dims[1], dims[2]
        ));
    }
    let s = to_body.spacing();
    let finite = s.iter().all(|v| v.is_finite())
        && to_body.origin.is_finite()
        && to_body.linear.determinant().is_finite();
    if !finite {
        return Err("the header's voxel-to-world transform holds a NaN or an infinity".into());
    }
    if let Some(a) = (0..3).find(|&a| !(s[a] >= 0.05 && s[a] <= 20.0)) {
        return Err(format!(
            "voxel spacing {:.6} mm along axis {a} is not a CT's (0.05–20 mm): is the header's unit \
             right (metres or micrometres stated as mm)?",
            s[a]
        ));
    }
    let det = to_body.linear.determinant().abs();
    if !(det > 0.1 * s[0] * s[1] * s[2]) {
        return Err(
            "the header's voxel axes are (nearly) parallel: its voxel-to-world transform cannot be \
             inverted"
                .into(),
        );
    }
    Ok(())
}
