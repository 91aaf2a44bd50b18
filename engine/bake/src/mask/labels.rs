//! Which label values are which lung and which lobe: the conventions of the segmenters clinicians
//! use, found from the values present (or named), and `--label` to say it outright.
//!
//! | convention | values | source |
//! |---|---|---|
//! | `lungmask` | 1 right lung, 2 left lung | lungmask (JoHof/lungmask) R231, README "Semantics of output" |
//! | `lungmask-lobes` | 1 left upper, 2 left lower, 3 right upper, 4 right middle, 5 right lower | lungmask LTRCLobes, same README |
//! | `totalsegmentator` | 10 left upper, 11 left lower, 12 right upper, 13 right middle, 14 right lower | TotalSegmentator v2 task "total", `map_to_binary.py` |
//! | `totalsegmentator-v1` | 13 left upper, 14 left lower, 15 right upper, 16 right middle, 17 right lower | TotalSegmentator v1 "total_v1" |
//! | `cip` | region = value & 0xFF: 1 whole lung, 2 right, 3 left, 4 right superior, 5 right middle, 6 right inferior, 7 left superior, 8 left inferior lobe | Chest Imaging Platform, `ChestConventions.xml` (value = type << 8 + region) |
//! | `names` | segment or file names ("lung_upper_lobe_left", "Right lung") | 3D Slicer's .seg.nrrd segment names; TotalSegmentator's per-structure files |
//! | `single` | one value holding both lungs (or one lung): the sides are separated geometrically | COPDgene/VoxelMorph++ masks, thresholded CT |

use lung_model::mesh::lobes::Lobe;
use lung_model::mesh::Side;

/// A label convention.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Convention {
    /// lungmask R231.
    Lungmask,
    /// lungmask LTRCLobes.
    LungmaskLobes,
    /// TotalSegmentator v2 "total".
    TotalSegmentator,
    /// TotalSegmentator v1 "total_v1".
    TotalSegmentatorV1,
    /// Chest Imaging Platform regions.
    Cip,
    /// Segment or file names.
    Names,
    /// One value for the lung tissue, sides separated geometrically.
    Single,
}

impl Convention {
    /// The name on the command line and in the JSON.
    pub fn name(self) -> &'static str {
        match self {
            Convention::Lungmask => "lungmask",
            Convention::LungmaskLobes => "lungmask-lobes",
            Convention::TotalSegmentator => "totalsegmentator",
            Convention::TotalSegmentatorV1 => "totalsegmentator-v1",
            Convention::Cip => "cip",
            Convention::Names => "names",
            Convention::Single => "single",
        }
    }

    /// Every convention.
    pub const ALL: [Convention; 7] = [
        Convention::Lungmask,
        Convention::LungmaskLobes,
        Convention::TotalSegmentator,
        Convention::TotalSegmentatorV1,
        Convention::Cip,
        Convention::Names,
        Convention::Single,
    ];
}

impl std::str::FromStr for Convention {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Convention::ALL
            .into_iter()
            .find(|c| c.name() == s)
            .ok_or_else(|| {
                format!(
                    "unknown label convention {s:?}: use one of {}",
                    Convention::ALL.map(|c| c.name()).join(", ")
                )
            })
    }
}

/// What one label value is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Meaning {
    /// A lobe (hence its side).
    Lobe(Lobe),
    /// A whole lung of one side.
    Lung(Side),
    /// Lung tissue of either or both sides.
    Both,
    /// Not lung.
    Other,
}

fn lobe(side: Side, which: &str) -> Lobe {
    match (side, which) {
        (Side::Right, "upper") => Lobe::RightUpper,
        (Side::Right, "middle") => Lobe::RightMiddle,
        (Side::Right, _) => Lobe::RightLower,
        (Side::Left, "upper") => Lobe::LeftUpper,
        (Side::Left, _) => Lobe::LeftLower,
    }
}

/// What a segment or file name says: "lung_upper_lobe_left", "Right lung", "left lower lobe",
/// "RightSuperiorLobe". `None` for a name that is not a lung's.
pub fn meaning_of_name(name: &str) -> Option<Meaning> {
    let n = name.to_ascii_lowercase();
    let n = n
        .trim_end_matches(".gz")
        .trim_end_matches(".nii")
        .trim_end_matches(".nrrd")
        .trim_end_matches(".mha");
    if !(n.contains("lung") || n.contains("lobe")) {
        return None;
    }
    if n.contains("vessel") || n.contains("airway") || n.contains("trachea") || n.contains("nodule")
    {
        return Some(Meaning::Other);
    }
    let side = match (n.contains("left"), n.contains("right")) {
        (true, false) => Some(Side::Left),
        (false, true) => Some(Side::Right),
        _ => None,
    };
    let which = if n.contains("upper") || n.contains("superior") {
        Some("upper")
    } else if n.contains("middle") {
        Some("middle")
    } else if n.contains("lower") || n.contains("inferior") {
        Some("lower")
    } else {
        None
    };
    Some(match (side, which) {
        (Some(Side::Left), Some("middle")) => Meaning::Other,
        (Some(s), Some(w)) => Meaning::Lobe(lobe(s, w)),
        (Some(s), None) => Meaning::Lung(s),
        (None, _) => Meaning::Both,
    })
}

/// What `value` means under `convention` (`names` from the file, for [`Convention::Names`]).
pub fn meaning(convention: Convention, value: u16, names: &[(u16, String)]) -> Meaning {
    use Lobe::*;
    match convention {
        Convention::Lungmask => match value {
            1 => Meaning::Lung(Side::Right),
            2 => Meaning::Lung(Side::Left),
            _ => Meaning::Other,
        },
        Convention::LungmaskLobes => match value {
            1 => Meaning::Lobe(LeftUpper),
            2 => Meaning::Lobe(LeftLower),
            3 => Meaning::Lobe(RightUpper),
            4 => Meaning::Lobe(RightMiddle),
            5 => Meaning::Lobe(RightLower),
            _ => Meaning::Other,
        },
        Convention::TotalSegmentator | Convention::TotalSegmentatorV1 => {
            let base = if convention == Convention::TotalSegmentator {
                10
            } else {
                13
            };
            match value.checked_sub(base) {
                Some(0) => Meaning::Lobe(LeftUpper),
                Some(1) => Meaning::Lobe(LeftLower),
                Some(2) => Meaning::Lobe(RightUpper),
                Some(3) => Meaning::Lobe(RightMiddle),
                Some(4) => Meaning::Lobe(RightLower),
                _ => Meaning::Other,
            }
        }
        Convention::Cip => match value & 0xFF {
            1 => Meaning::Both,
            2 => Meaning::Lung(Side::Right),
            3 => Meaning::Lung(Side::Left),
            4 => Meaning::Lobe(RightUpper),
            5 => Meaning::Lobe(RightMiddle),
            6 => Meaning::Lobe(RightLower),
            7 => Meaning::Lobe(LeftUpper),
            8 => Meaning::Lobe(LeftLower),
            _ => Meaning::Other,
        },
        Convention::Names => names
            .iter()
            .find(|(v, _)| *v == value)
            .and_then(|(_, n)| meaning_of_name(n))
            .unwrap_or(Meaning::Other),
        Convention::Single => {
            if value != 0 {
                Meaning::Both
            } else {
                Meaning::Other
            }
        }
    }
}

/// The convention the values present (`histogram`: value, voxels) and names suggest, with why.
pub fn detect(
    histogram: &[(u16, usize)],
    names: &[(u16, String)],
) -> Result<(Convention, String), String> {
    let values: Vec<u16> = histogram.iter().map(|&(v, _)| v).collect();
    let listed = || {
        let mut s: Vec<String> = values.iter().take(12).map(|v| v.to_string()).collect();
        if values.len() > 12 {
            s.push(format!("… ({} values)", values.len()));
        }
        s.join(", ")
    };
    if values.is_empty() {
        return Err("the image holds no labelled voxel (every voxel is 0)".into());
    }
    let named: Vec<&(u16, String)> = names
        .iter()
        .filter(|(v, n)| {
            values.contains(v) && meaning_of_name(n).is_some_and(|m| m != Meaning::Other)
        })
        .collect();
    if !named.is_empty() {
        return Ok((
            Convention::Names,
            format!(
                "segment names: {}",
                named
                    .iter()
                    .map(|(v, n)| format!("{v} = {n:?}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    let within = |set: &[u16]| values.iter().all(|v| set.contains(v));
    if values.len() == 1 {
        let v = values[0];
        let cip_region = v > 255 && (1..=8).contains(&(v & 0xFF));
        if !cip_region {
            return Ok((
                Convention::Single,
                format!("one label value ({v}) holds the lung tissue"),
            ));
        }
    }
    if within(&[1, 2]) {
        return Ok((
            Convention::Lungmask,
            "values 1 and 2: lungmask R231 (1 right, 2 left)".into(),
        ));
    }
    if within(&[1, 2, 3, 4, 5]) && values.len() >= 3 {
        return Ok((
            Convention::LungmaskLobes,
            format!("values {}: lungmask LTRCLobes (1–2 left upper/lower, 3–5 right upper/middle/lower)", listed()),
        ));
    }
    let regions: Vec<u16> = values.iter().map(|v| v & 0xFF).collect();
    if regions.iter().all(|r| (1..=8).contains(r))
        && (values.iter().any(|&v| v > 255) || within(&[2, 3, 4, 5, 6, 7, 8]))
    {
        return Ok((
            Convention::Cip,
            format!("values {}: Chest Imaging Platform regions (2 right, 3 left, 4–8 lobes; value = type·256 + region)", listed()),
        ));
    }
    let ts = (10..=14).filter(|v| values.contains(v)).count();
    if ts >= 2 && (values.len() > 5 || within(&[10, 11, 12, 13, 14])) {
        return Ok((
            Convention::TotalSegmentator,
            format!("values {}: TotalSegmentator v2 'total' (10–11 left upper/lower, 12–14 right upper/middle/lower lobes)", listed()),
        ));
    }
    Err(format!(
        "the label values present ({}) match no convention lungdyn knows: name the lung's values with \
         --label (e.g. --label 3 or --label 4,5,6 for its lobes) or the convention with --convention \
         ({})",
        listed(),
        Convention::ALL.map(|c| c.name()).join(", ")
    ))
}
