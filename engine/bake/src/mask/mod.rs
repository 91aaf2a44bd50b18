//! # mask: a patient's lung surface from a CT lung segmentation
//!
//! `label image (NIfTI / NRRD / MetaImage) → this lung's voxels (by the segmenter's label
//! convention, or separated geometrically where one label holds both lungs) → tunnels closed,
//! cavities filled → smooth field → marching tetrahedra → short edges collapsed → relaxed onto the
//! field → volume matched to the mask → the checks every imported lung gets → lobe ids from the
//! lobe labels (or the fissure planes)`, all in lungdyn's body frame (mm, +X left, +Y anterior,
//! +Z superior) through the image's own voxel-to-world transform ([`read`]).
//!
//! **Nothing about the frame is guessed.** A header without an anatomical frame is refused unless
//! `--axes` states the voxel axes; a header that contradicts the anatomy (the base's lowest point
//! anterior, the apex at the bottom, a lung labelled left shaped like a right one, a "right" lung
//! smaller than the left with a lower base) is said, and where the evidence is strong, refused
//! with the `--axes` that would fix it.

pub mod labels;
pub mod morph;
pub mod read;
pub mod surface;
/// Label images made from the built-in lungs, for tests (the `testing` feature).
#[cfg(any(test, feature = "testing"))]
pub mod synthetic;
pub mod volume;

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::DVec3;
use lung_model::mesh::lobes::{self, Lobe};
use lung_model::mesh::{check, Side, TriMesh};
use serde::Serialize;

use labels::{Convention, Meaning};
use morph::Grid;
use volume::{Axes, FrameSource, LabelVolume, VoxelToBody};

/// Why a mask could not become a lung surface.
#[derive(Debug, thiserror::Error)]
pub enum MaskError {
    /// Unreadable file, or not within the input limits.
    #[error(transparent)]
    Input(#[from] lung_model::input::InputError),
    /// Not a label image lungdyn reads, or a header it will not trust.
    #[error("{}: {message}", path.display())]
    Format {
        /// Path.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The labels do not give this lung.
    #[error("{}: {message}", path.display())]
    Labels {
        /// Path.
        path: PathBuf,
        /// What is wrong and what to pass.
        message: String,
    },
    /// The surface could not be made or is not a lung's.
    #[error("{}: {message}", path.display())]
    Surface {
        /// Path.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Largest padded box of one lung, voxels (≈ 5 GiB of work arrays at the most).
pub const MAX_CROP_VOXELS: usize = 200_000_000;

/// How to make the surface.
#[derive(Debug, Clone)]
pub struct MaskOptions {
    /// Which lung.
    pub side: Side,
    /// The label values that are this lung or its lobes (`--label`); found from the convention
    /// when `None`.
    pub labels: Option<Vec<u16>>,
    /// The label convention (`--convention`); detected when `None`.
    pub convention: Option<Convention>,
    /// Vertices wanted (about: the surface's spacing is chosen for it).
    pub vertices: usize,
    /// The voxel axes' directions, replacing the header's (`--axes`).
    pub axes: Option<Axes>,
    /// Keep tunnels (vessels, airways through the mask) instead of closing them.
    pub keep_tunnels: bool,
    /// Gaussian σ of the smoothing, mm (`None`: 0.75 × the largest voxel spacing, at least 0.6).
    pub smoothing_mm: Option<f64>,
    /// Input limits.
    pub limits: lung_model::input::ReadLimits,
}

impl MaskOptions {
    /// Defaults for `side`: conventions detected, 20k vertices, tunnels closed.
    pub fn new(side: Side) -> Self {
        Self {
            side,
            labels: None,
            convention: None,
            vertices: 20_000,
            axes: None,
            keep_tunnels: false,
            smoothing_mm: None,
            limits: read::MASK_LIMITS,
        }
    }
}

/// Distances from the surface's vertices to the mask's staircase boundary, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Distances {
    /// Mean, mm.
    pub mean_mm: f64,
    /// 95th percentile, mm.
    pub p95_mm: f64,
    /// Largest, mm.
    pub max_mm: f64,
    /// Mean over the geometric mean voxel spacing.
    pub mean_voxels: f64,
}

/// What [`mesh_from_mask`] made and how.
#[derive(Debug, Clone)]
pub struct FromMask {
    /// The surface, mm, body frame.
    pub mesh: TriMesh,
    /// A lobe code per vertex ([`lung_model::mesh::lobes`]).
    pub lobes: Vec<u8>,
    /// Where the lobe codes came from: "labels" (the image's lobe labels) or "planes" (the fissure
    /// planes over the bounding box).
    pub lobes_from: &'static str,
    /// The image's frame.
    pub frame: FrameSource,
    /// The label convention used.
    pub convention: Convention,
    /// Why (detected from what, or given).
    pub convention_reason: String,
    /// The label values taken as this lung.
    pub labels_used: Vec<u16>,
    /// How this lung was told from the other: "labels", "components" (two separate bodies),
    /// "split at contact" (one body eroded apart and grown back) or "one lung in the image".
    pub sides_from: &'static str,
    /// Voxel volume of this lung's mask as labelled (after separating sides), ml.
    pub mask_volume_ml: f64,
    /// Voxel volume after closing tunnels and filling cavities (the surface's target), ml.
    pub closed_volume_ml: f64,
    /// Genus of the mask's boundary as it came (tunnels through it: vessels, airways).
    pub genus_before: i64,
    /// Genus of the surface made.
    pub genus_after: i64,
    /// Radius of the closing that closed the tunnels, mm (0: none needed or asked).
    pub closing_mm: f64,
    /// Cavities (enclosed holes) filled.
    pub cavities_filled: usize,
    /// Voxels in pieces apart from the lung's main body, dropped.
    pub voxels_dropped: usize,
    /// Gaussian σ of the smoothing, mm.
    pub smoothing_mm: f64,
    /// Grid step of the isosurface, mm.
    pub grid_step_mm: f64,
    /// Distances from the vertices to the mask's boundary.
    pub distance_to_mask: Distances,
    /// Geometry's side and orientation findings, one line each.
    pub side_reason: String,
    /// What the geometry says about anterior/posterior and superior/inferior.
    pub orientation_reason: String,
    /// Things to look at (a header that looks mirrored, notes of the reader).
    pub warnings: Vec<String>,
    /// Seconds spent per stage.
    pub seconds: Vec<(&'static str, f64)>,
}

/// Read one label image, or several binary ones (one structure per file, as TotalSegmentator
/// writes them) combined into one: file `n` becomes label `n` (1-based), named by its file name.
pub fn read_masks(paths: &[PathBuf], opts: &MaskOptions) -> Result<LabelVolume, MaskError> {
    let first = paths.first().ok_or_else(|| MaskError::Labels {
        path: PathBuf::new(),
        message: "no mask file given".into(),
    })?;
    let mut volume = read::read_labels(first, opts.limits, opts.axes)?;
    if paths.len() == 1 {
        return Ok(volume);
    }
    let name_of = |p: &Path| {
        p.file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default()
    };
    let binary = |v: &LabelVolume, p: &Path| -> Result<(), MaskError> {
        let h = v.histogram();
        if h.len() > 1 {
            return Err(MaskError::Labels {
                path: p.to_path_buf(),
                message: format!(
                    "given with other files, each file must hold one structure (values 0 and one \
                     other), but it holds {} values",
                    h.len()
                ),
            });
        }
        Ok(())
    };
    binary(&volume, first)?;
    for l in &mut volume.labels {
        if *l != 0 {
            *l = 1;
        }
    }
    volume.names = vec![(1, name_of(first))];
    for (n, path) in paths.iter().enumerate().skip(1) {
        let other = read::read_labels(path, opts.limits, opts.axes)?;
        binary(&other, path)?;
        let same_grid = other.dims == volume.dims
            && (other.to_body.linear - volume.to_body.linear)
                .to_cols_array()
                .iter()
                .all(|d| d.abs() < 1e-3)
            && (other.to_body.origin - volume.to_body.origin)
                .abs()
                .max_element()
                < 1e-2;
        if !same_grid {
            return Err(MaskError::Labels {
                path: path.clone(),
                message: format!(
                    "its grid ({:?} voxels, origin {:.2?} mm) is not {}'s ({:?}, {:.2?}): masks given \
                     together must come from one image",
                    other.dims,
                    other.to_body.origin.to_array(),
                    first.display(),
                    volume.dims,
                    volume.to_body.origin.to_array()
                ),
            });
        }
        let value = (n + 1) as u16;
        for (dst, &src) in volume.labels.iter_mut().zip(&other.labels) {
            if src != 0 {
                *dst = value;
            }
        }
        volume.names.push((value, name_of(path)));
    }
    Ok(volume)
}

/// The label values chosen for one lung and what each value means.
struct Chosen {
    convention: Convention,
    reason: String,
    /// The values taken as this lung.
    selected: Vec<u16>,
    /// Every value present and its meaning.
    meanings: Vec<(u16, Meaning)>,
    /// Every selected value is this lung's by its label (else the side is told geometrically).
    by_label: bool,
}

impl Chosen {
    fn meaning(&self, v: u16) -> Meaning {
        self.meanings
            .iter()
            .find(|&&(x, _)| x == v)
            .map_or(Meaning::Other, |&(_, m)| m)
    }
}

fn is_side(m: Meaning, side: Side) -> bool {
    match m {
        Meaning::Lobe(l) => l.side() == Some(side),
        Meaning::Lung(s) => s == side,
        _ => false,
    }
}

fn list(values: &[u16]) -> String {
    values
        .iter()
        .map(|v| v.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Which values are `opts.side`'s lung: the convention given or detected, `--label` checked
/// against it.
fn choose_labels(volume: &LabelVolume, opts: &MaskOptions) -> Result<Chosen, String> {
    let histogram = volume.histogram();
    let (convention, reason) = match (opts.convention, &opts.labels) {
        (Some(c), _) => (c, "given (--convention)".to_string()),
        (None, Some(_)) => labels::detect(&histogram, &volume.names).unwrap_or((
            Convention::Single,
            "--label given; no convention matched".into(),
        )),
        (None, None) => labels::detect(&histogram, &volume.names)?,
    };
    let present: Vec<u16> = histogram.iter().map(|&(v, _)| v).collect();
    let meanings: Vec<(u16, Meaning)> = present
        .iter()
        .map(|&v| {
            let m = if opts.labels.is_some() && convention == Convention::Single {
                Meaning::Both
            } else {
                labels::meaning(convention, v, &volume.names)
            };
            (v, m)
        })
        .collect();
    let meaning = |v: u16| {
        meanings
            .iter()
            .find(|&&(x, _)| x == v)
            .map_or(Meaning::Other, |&(_, m)| m)
    };
    let side = opts.side;
    let selected: Vec<u16> = match &opts.labels {
        Some(given) => {
            for &v in given {
                if !present.contains(&v) {
                    return Err(format!(
                        "--label {v}: no voxel holds {v}; the values present are {}",
                        list(&present)
                    ));
                }
                match meaning(v) {
                    Meaning::Lobe(l) if l.side() != Some(side) => {
                        return Err(format!(
                            "--label {v} is the {} lobe under the {} convention, not a lobe of the \
                             {} lung",
                            l.name(),
                            convention.name(),
                            side.name()
                        ))
                    }
                    Meaning::Lung(s) if s != side => {
                        return Err(format!(
                            "--label {v} is the {} lung under the {} convention, not the {}",
                            s.name(),
                            convention.name(),
                            side.name()
                        ))
                    }
                    _ => {}
                }
            }
            given.clone()
        }
        None => {
            let own: Vec<u16> = present
                .iter()
                .copied()
                .filter(|&v| is_side(meaning(v), side))
                .collect();
            if own.is_empty() {
                present
                    .iter()
                    .copied()
                    .filter(|&v| meaning(v) == Meaning::Both)
                    .collect()
            } else {
                own
            }
        }
    };
    if selected.is_empty() {
        return Err(format!(
            "no label is the {} lung under the {} convention ({reason}); values present: {}. Name \
             its values with --label",
            side.name(),
            convention.name(),
            list(&present)
        ));
    }
    let by_label = selected.iter().all(|&v| is_side(meaning(v), side));
    Ok(Chosen {
        convention,
        reason,
        selected,
        meanings,
        by_label,
    })
}

/// `sides_from` where one label holds one body: the image holds one lung.
const ONE_LUNG: &str = "one lung in the image";

/// The image's extent along the body's X, mm (its eight corners).
fn image_x_extent(volume: &LabelVolume) -> Option<f64> {
    let [nx, ny, nz] = volume.dims.map(|d| d.saturating_sub(1) as f64);
    let xs: Vec<f64> = (0..8)
        .map(|m| {
            let c = DVec3::new(
                if m & 1 == 1 { nx } else { 0.0 },
                if m & 2 == 2 { ny } else { 0.0 },
                if m & 4 == 4 { nz } else { 0.0 },
            );
            volume.to_body.apply(c).x
        })
        .collect();
    let lo = xs.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    (hi > lo).then_some(hi - lo)
}

/// One lung's voxels, told from the other's.
struct Separated {
    grid: Grid,
    sides_from: &'static str,
    /// Voxels in pieces apart from both lungs.
    stray: usize,
    /// (right, left) where both lungs were seen.
    both: Option<(LungStats, LungStats)>,
}

/// `grid` holds lung tissue of either side (one label for both): the two lungs by their
/// components, or split where they touch; the one on `side` (+X is the patient's left).
fn separate_sides(grid: Grid, to_body: &VoxelToBody, voxel_ml: f64, side: Side) -> Separated {
    let lateral = |idx: usize| {
        let [nx, ny, _] = grid.dims;
        to_body
            .apply(DVec3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            ))
            .x
    };
    let (id, sizes) = morph::components(&grid, true);
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    order.sort_by_key(|&c| std::cmp::Reverse(sizes[c]));
    let total: usize = sizes.iter().sum();
    let mut sides_from = ONE_LUNG;
    let mut stray = 0;
    let parts: Option<[Grid; 2]> = if order.len() >= 2 && sizes[order[1]] * 100 >= total * 15 {
        sides_from = "components";
        stray = total - sizes[order[0]] - sizes[order[1]];
        let part = |c: usize| Grid {
            on: id.iter().map(|&x| x == c as u32 + 1).collect(),
            ..grid.clone()
        };
        Some([part(order[0]), part(order[1])])
    } else {
        let split = morph::split_two(&grid, lateral, 60.0);
        if split.is_some() {
            sides_from = "split at contact";
        }
        split
    };
    let Some([a, b]) = parts else {
        return Separated {
            grid,
            sides_from,
            stray,
            both: None,
        };
    };
    let centre = |g: &Grid| {
        let (mut s, mut n) = (0.0, 0usize);
        for (idx, &on) in g.on.iter().enumerate() {
            if on {
                s += lateral(idx);
                n += 1;
            }
        }
        s / n.max(1) as f64
    };
    let (left, right) = if centre(&a) > centre(&b) {
        (a, b)
    } else {
        (b, a)
    };
    let both = Some((
        part_stats(&right, to_body, voxel_ml),
        part_stats(&left, to_body, voxel_ml),
    ));
    Separated {
        grid: if side == Side::Left { left } else { right },
        sides_from,
        stray,
        both,
    }
}

/// The surface of one lung's voxels, its tunnels closed.
struct Closed {
    made: Extracted,
    grid: Grid,
    closing_mm: f64,
    filled: usize,
    volume_ml: f64,
    genus: i64,
}

/// Tunnels closed by the smallest closing that leaves the *surface* (not only the voxels) of
/// genus 0 — the smoothing can also bridge a narrow groove into a new handle, which a closing of
/// the groove prevents — and the surface made.
fn close_and_extract(
    as_labelled: &Grid,
    genus_as_labelled: i64,
    to_body: VoxelToBody,
    voxel_ml: f64,
    sigma: f64,
    opts: &MaskOptions,
) -> Result<Option<Closed>, MaskError> {
    let min_spacing = as_labelled
        .spacing
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min);
    let radii: Vec<f64> = [0.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0]
        .into_iter()
        .filter(|&r| r == 0.0 || r >= min_spacing)
        .collect();
    // The dilation's distance transform is the same for every radius: made once, when a closing
    // is first needed.
    let mut to_in: Option<Vec<f64>> = None;
    for (attempt, &r) in radii.iter().enumerate() {
        let mut filled = 0;
        let g = if r > 0.0 {
            let to_in = to_in.get_or_insert_with(|| morph::distance_sq(as_labelled, true));
            let mut g = morph::close_with(as_labelled, to_in, r);
            filled = morph::fill_cavities(&mut g).0;
            morph::keep_largest(&mut g);
            g
        } else {
            as_labelled.clone()
        };
        // (No closing: the genus is the caller's, already measured.)
        let genus = if r > 0.0 {
            morph::genus(&g)
        } else {
            genus_as_labelled
        };
        if !opts.keep_tunnels && r < *radii.last().unwrap_or(&0.0) && genus != 0 {
            continue;
        }
        let volume_ml = g.count() as f64 * voxel_ml;
        let last = attempt + 1 == radii.len();
        let need_genus_0 = !opts.keep_tunnels && !last;
        if let Some(made) = extract(&g, to_body, sigma, opts.vertices, volume_ml, need_genus_0)? {
            let genus = (2 - made.euler) / 2;
            return Ok(Some(Closed {
                made,
                grid: g,
                closing_mm: r,
                filled,
                volume_ml,
                genus,
            }));
        }
    }
    Ok(None)
}

/// What the anatomy says of the frame's three axes.
struct Verdict {
    flip_lr: bool,
    flip_ap: bool,
    flip_si: bool,
    /// Strong enough to refuse without --axes.
    strong: bool,
    findings: Vec<String>,
    warnings: Vec<String>,
    reason: String,
}

/// The image's frame judged from both lungs' voxels (one verdict, whichever lung is asked).
fn image_verdict(right: LungStats, left: LungStats, header_axes: Axes) -> Verdict {
    use crate::surface_checks::{AP_SWAP_WARN, UPSIDE_DOWN_REFUSE, UPSIDE_DOWN_WARN};
    let mut warnings = Vec::new();
    let mut findings = Vec::new();
    let mut strong = false;
    let taper = (right.taper + left.taper) / 2.0;
    let share = right.volume_ml / (right.volume_ml + left.volume_ml);
    // Each A/P cue votes +1 (anterior and posterior look swapped), −1 (they look as the
    // frame states) or 0 (too weak, or the two lungs disagree).
    let vote = |a: f64, b: f64, dead: f64| {
        let mean = (a + b) / 2.0;
        if a > 0.0 && b > 0.0 && mean > dead {
            1
        } else if a < 0.0 && b < 0.0 && mean < -dead {
            -1
        } else {
            0
        }
    };
    let base_vote = vote(right.base_offset, left.base_offset, AP_SWAP_WARN);
    let bulk_vote = -vote(right.bulk, left.bulk, 0.1);
    let ap_votes = base_vote + bulk_vote;
    let smaller_right = share < 0.5;
    // A half turn about the long axis (an LPS image under an RAS header, or the reverse)
    // swaps anterior with posterior and left with right, and no lung's shape shows the
    // second: the frame's right lung the smaller (a right lung is 53–56 % of both) is
    // its sign. Both A/P cues swapped, or one swapped and the other silent or outvoted
    // by the sizes, decide it.
    let half_turn = smaller_right && ap_votes >= 0 && (base_vote > 0 || bulk_vote > 0);
    let flip_ap = ap_votes >= 2 || half_turn || ap_votes == 1;
    let flip_lr = half_turn;
    let flip_si = taper > UPSIDE_DOWN_WARN && right.taper > 0.0 && left.taper > 0.0;
    let numbers = format!(
        "both lungs' voxels (right / left): base (lowest 5 % slab) {:+.2} / {:+.2} of the \
         lung's depth from its centroid along +Y (a lung's lowest point is posterior, so \
         negative), posterior-to-anterior bulk ln {:+.2} / {:+.2} (a lung is deeper \
         posteriorly, so positive), taper {:+.2} / {:+.2} (negative = narrower at +Z); \
         the frame's right lung {:.0} % of both ({:.0} against {:.0} ml; usually 53–56 %)",
        right.base_offset,
        left.base_offset,
        right.bulk,
        left.bulk,
        right.taper,
        left.taper,
        100.0 * share,
        right.volume_ml,
        left.volume_ml
    );
    if flip_ap {
        strong |= ap_votes >= 2 || half_turn;
        findings.push(format!(
            "{} — +Y looks posterior, not anterior{} ({numbers})",
            match (base_vote, bulk_vote) {
                (1, 1) => "both lungs' lowest parts lie towards +Y and their bulk towards −Y",
                (1, _) => "both lungs' lowest parts lie towards +Y",
                _ => "both lungs' bulk lies towards −Y",
            },
            if half_turn {
                ", and the lung the frame calls right is the smaller: together a half \
                 turn about the long axis, which swaps left and right too"
            } else {
                ""
            }
        ));
    }
    if flip_si {
        strong |= taper > UPSIDE_DOWN_REFUSE;
        findings.push(format!(
            "both lungs are wider at +Z than at −Z, but a lung narrows towards the apex: \
             +Z looks inferior ({numbers})"
        ));
    }
    let lower_by = left.lowest_mm - right.lowest_mm;
    if !flip_ap && share < 0.47 && lower_by > 5.0 {
        warnings.push(format!(
            "in the image's frame the right lung is the smaller ({:.0} % of both lungs, \
             {:.0} ml against {:.0} ml) and its base {:.0} mm lower than the left's; a \
             right lung is usually the larger (53–56 %) with the higher base. If the \
             image's left-right axis is mirrored (a header written with the wrong \
             directions), pass --axes {}",
            100.0 * share,
            right.volume_ml,
            left.volume_ml,
            lower_by,
            fixed_axes(header_axes, true, false, false).code()
        ));
    }
    let reason = if findings.is_empty() {
        format!("anterior, posterior, superior and inferior look as the frame states: {numbers}")
    } else {
        numbers
    };
    Verdict {
        flip_lr,
        flip_ap,
        flip_si,
        strong,
        findings,
        warnings,
        reason,
    }
}

/// One lung's surface judged alone (the image holds no other lung to weigh it against).
fn surface_verdict(mesh: &TriMesh) -> Verdict {
    let orientation = crate::surface_checks::infer_orientation(mesh);
    let (flip_ap, flip_si) = (
        orientation.anterior_posterior_swapped,
        orientation.upside_down,
    );
    let mut findings = Vec::new();
    if flip_ap || flip_si {
        findings.push(format!(
            "lies {} ({})",
            if flip_ap {
                "with anterior and posterior swapped"
            } else {
                "upside down"
            },
            orientation.reason
        ));
    }
    Verdict {
        flip_lr: false,
        flip_ap,
        flip_si,
        strong: (flip_ap || flip_si) && orientation.strong,
        findings,
        warnings: Vec::new(),
        reason: orientation.reason,
    }
}

/// Where the image holds one lung only: how far its centre lies from the image's centre along
/// the body's X, as a share of the image's X extent (negative: towards the patient's right).
#[derive(Debug, Clone, Copy)]
struct OneLung {
    offset: f64,
}

/// One lung in the image, one label: which lung it is comes from its shape (its concave,
/// mediastinal face) and where it lies in the image, never from what was asked — the other side
/// is refused; a weak or disagreeing verdict is a warning.
fn one_lung_side(
    one: OneLung,
    side: Side,
    side_evidence: &crate::surface_checks::SideEvidence,
    header_axes: Axes,
    warnings: &mut Vec<String>,
) -> Result<(), String> {
    let confident = side_evidence.confidence >= crate::surface_checks::SIDE_MISMATCH_CONFIDENCE;
    // One lung in the image, one label: which lung it is comes from its shape (its concave,
    // mediastinal face) and where it lies in the image, never from what was asked.
    let by_place = if one.offset.abs() >= 0.1 {
        Some(if one.offset < 0.0 {
            Side::Right
        } else {
            Side::Left
        })
    } else {
        None
    };
    let by_shape = side_evidence.side.filter(|_| confident);
    let seen = by_shape.or(by_place);
    let place = format!(
        "its centre lies {:.0} % of the image's width to the patient's {} of the image's centre",
        100.0 * one.offset.abs(),
        if one.offset < 0.0 { "right" } else { "left" }
    );
    match seen {
        Some(seen) if seen != side => {
            return Err(format!(
                "--lung {asked}: the image holds one lung, and it is the {seen} lung (its shape: \
                 {}; {place}). Ask for --lung {seen}; if the image's left-right axis is \
                 mirrored, pass --axes {}",
                side_evidence.reason,
                fixed_axes(header_axes, true, false, false).code(),
                asked = side.name(),
                seen = seen.name(),
            ));
        }
        Some(_) if by_shape.is_some() && by_place.is_some_and(|p| p != side) => {
            warnings.push(format!(
                "the image holds one lung: its shape is a {} lung's ({}), but {place}; check \
                 the image's left-right axis",
                side.name(),
                side_evidence.reason
            ));
        }
        Some(_) => {}
        None => warnings.push(format!(
            "the image holds one lung, and neither its shape ({}) nor its place ({place}) \
             says which: it was meshed as the {} lung because you asked so; check it",
            side_evidence.reason,
            side.name()
        )),
    }
    Ok(())
}

/// Where the one lung of a one-lung image lies, from the image's centre along the body's X.
fn one_lung_place(volume: &LabelVolume, mesh: &TriMesh) -> OneLung {
    let [nx, ny, nz] = volume.dims;
    let centre = mesh.positions.iter().map(|p| p[0] as f64).sum::<f64>()
        / mesh.positions.len().max(1) as f64;
    let mid = volume
        .to_body
        .apply(DVec3::new(
            (nx as f64 - 1.0) / 2.0,
            (ny as f64 - 1.0) / 2.0,
            (nz as f64 - 1.0) / 2.0,
        ))
        .x;
    let extent = image_x_extent(volume).unwrap_or(1.0).max(1e-9);
    OneLung {
        offset: (centre - mid) / extent,
    }
}

/// What the anatomy says against the image's frame: `Err` with the `--axes` that answers all of
/// it where the evidence is strong and no `--axes` was given, else the warnings to report.
///
/// Where the image holds both lungs the frame is judged **once for the image**, from both lungs'
/// voxels (their bases, their tapers, their sizes), so the verdict is the same whichever lung is
/// asked; two independent cues that agree (both bases anterior and the frame's right lung the
/// smaller: a half turn about the long axis) are enough to refuse. A lung's own surface is asked
/// only where the image holds that lung alone, and for the side where labels name it.
fn frame_findings(
    mesh: &TriMesh,
    volume: &LabelVolume,
    side: Side,
    by_label: bool,
    both: Option<(LungStats, LungStats)>,
    one_lung: Option<OneLung>,
    axes_given: bool,
) -> Result<(Vec<String>, String, String), String> {
    use crate::surface_checks::SIDE_MISMATCH_CONFIDENCE;
    let side_evidence = crate::surface_checks::infer_side(mesh);
    let header_axes = Axes(volume.to_body.voxel_axes().0);
    let Verdict {
        mut flip_lr,
        flip_ap,
        flip_si,
        mut strong,
        mut findings,
        mut warnings,
        reason: orientation_reason,
    } = match both {
        Some((right, left)) => image_verdict(right, left, header_axes),
        None => surface_verdict(mesh),
    };
    let confident = side_evidence.confidence >= SIDE_MISMATCH_CONFIDENCE;
    if let Some(seen) = side_evidence.side.filter(|_| confident) {
        if by_label && seen != side && !flip_lr {
            flip_lr = true;
            strong = true;
            findings.push(format!(
                "the labels say {} lung but its shape is a {} lung's ({}): the left-right axis looks \
                 mirrored",
                side.name(),
                seen.name(),
                side_evidence.reason
            ));
        }
    }
    if let Some(one) = one_lung {
        one_lung_side(one, side, &side_evidence, header_axes, &mut warnings)?;
    }
    if !findings.is_empty() {
        let fix = fixed_axes(header_axes, flip_lr, flip_ap, flip_si);
        let w = format!(
            "in the image's frame ({}, voxel axes {}) the {} lung: {}. If the header is wrong, pass \
             --axes {} (the voxel axes as they really are)",
            volume.frame.from,
            header_axes.code(),
            side.name(),
            findings.join("; and "),
            fix.code()
        );
        if strong && !axes_given {
            return Err(w);
        }
        warnings.push(w);
    }
    Ok((warnings, side_evidence.reason, orientation_reason))
}

/// Both lungs by label, where the image has both (right, left): their sizes and bases, where a
/// mirrored or turned left-right axis shows.
fn labelled_pair(
    volume: &LabelVolume,
    chosen: &Chosen,
    side: Side,
) -> Option<(LungStats, LungStats)> {
    if !chosen.by_label {
        return None;
    }
    let other_side = if side == Side::Left {
        Side::Right
    } else {
        Side::Left
    };
    let other: Vec<u16> = chosen
        .meanings
        .iter()
        .filter(|&&(_, m)| is_side(m, other_side))
        .map(|&(v, _)| v)
        .collect();
    if other.is_empty() {
        return None;
    }
    let ours = lung_stats(volume, |l| chosen.selected.contains(&l));
    let theirs = lung_stats(volume, |l| other.contains(&l));
    Some(if side == Side::Right {
        (ours, theirs)
    } else {
        (theirs, ours)
    })
}

/// [`crop`] of the `selected` values, refused when the box is larger than lungdyn meshes (the
/// work arrays cost up to ~25 bytes a voxel: distance transforms in f64).
fn crop_checked(
    volume: &LabelVolume,
    selected: &[u16],
    margin_mm: f64,
) -> Result<(Grid, VoxelToBody), String> {
    let (grid, to_body) = crop(volume, |l| selected.contains(&l), margin_mm)
        .ok_or_else(|| "the selected labels hold no voxel".to_string())?;
    if grid.on.len() > MAX_CROP_VOXELS {
        let spacing = volume.to_body.spacing();
        return Err(format!(
            "this lung's box is {}×{}×{} voxels at {:.3} × {:.3} × {:.3} mm, more than lungdyn \
             meshes ({} million): resample the mask to a coarser grid (0.5–2 mm is plenty for a \
             lung surface) and try again",
            grid.dims[0],
            grid.dims[1],
            grid.dims[2],
            spacing[0],
            spacing[1],
            spacing[2],
            MAX_CROP_VOXELS / 1_000_000
        ));
    }
    Ok((grid, to_body))
}

/// Make `opts.side`'s lung surface from the label image(s) at `paths`.
pub fn mesh_from_mask(paths: &[PathBuf], opts: &MaskOptions) -> Result<FromMask, MaskError> {
    let path = paths.first().cloned().unwrap_or_default();
    let labels_err = |message: String| MaskError::Labels {
        path: path.clone(),
        message,
    };
    let surface_err = |message: String| MaskError::Surface {
        path: path.clone(),
        message,
    };
    let mut seconds = Vec::new();
    let mut clock = Instant::now();
    let mut lap = |name: &'static str, seconds: &mut Vec<(&'static str, f64)>| {
        seconds.push((name, clock.elapsed().as_secs_f64()));
        clock = Instant::now();
    };
    if !(100..=4_000_000).contains(&opts.vertices) {
        return Err(labels_err(format!(
            "--vertices {}: give 100 to 4,000,000",
            opts.vertices
        )));
    }
    let volume = read_masks(paths, opts)?;
    lap("read", &mut seconds);
    let mut warnings = volume.notes.clone();
    let side = opts.side;
    let chosen = choose_labels(&volume, opts).map_err(labels_err)?;
    let both_lungs = labelled_pair(&volume, &chosen, side);

    // This lung's voxels on a padded crop.
    let spacing = volume.to_body.spacing();
    let sigma = opts
        .smoothing_mm
        .unwrap_or((0.75 * spacing.iter().cloned().fold(0.0, f64::max)).max(0.6));
    if !(0.0..=10.0).contains(&sigma) {
        return Err(labels_err(format!("--smooth {sigma} mm: give 0 to 10 mm")));
    }
    let (grid, crop_to_body) =
        crop_checked(&volume, &chosen.selected, 14.0 + 3.0 * sigma).map_err(labels_err)?;
    let separated = if chosen.by_label {
        Separated {
            grid,
            sides_from: "labels",
            stray: 0,
            both: None,
        }
    } else {
        separate_sides(grid, &crop_to_body, volume.voxel_ml(), side)
    };
    let both_lungs = both_lungs.or(separated.both);
    let mut grid = separated.grid;
    lap("select", &mut seconds);
    let voxels_dropped = morph::keep_largest(&mut grid) + separated.stray;
    let mask_volume_ml = grid.count() as f64 * volume.voxel_ml();
    let (cavities_filled, _) = morph::fill_cavities(&mut grid);
    let genus_before = morph::genus(&grid);
    let closed = close_and_extract(
        &grid,
        genus_before,
        crop_to_body,
        volume.voxel_ml(),
        sigma,
        opts,
    )?
    .ok_or_else(|| surface_err("internal error: no surface was made".into()))?;
    let Extracted {
        mesh, h, crossing, ..
    } = closed.made;
    lap("surface", &mut seconds);
    if closed.genus != 0 && !opts.keep_tunnels {
        return Err(surface_err(format!(
            "the {} lung's surface keeps {} tunnel(s) after a closing of {} mm: look at the mask (a \
             lung fused with the airways or the other lung?), or pass --keep-tunnels",
            side.name(),
            closed.genus,
            closed.closing_mm
        )));
    }
    if crossing > 0 {
        return Err(surface_err(format!(
            "the surface made from the mask intersects itself ({crossing} crossing pairs left after \
             untangling): the mask has parts thinner than the smoothing; try a smaller --smooth or \
             more --vertices"
        )));
    }
    crate::import::check_size(&mesh, crate::import::Units::Mm, true)
        .map_err(|e| surface_err(format!("{e}")))?;
    let one_lung = (separated.sides_from == ONE_LUNG).then(|| one_lung_place(&volume, &mesh));
    let (frame_warnings, side_reason, orientation_reason) = frame_findings(
        &mesh,
        &volume,
        side,
        chosen.by_label,
        both_lungs,
        one_lung,
        opts.axes.is_some(),
    )
    .map_err(surface_err)?;
    warnings.extend(frame_warnings);
    lap("check", &mut seconds);

    // Lobes.
    let lobe_codes: Vec<(u16, u8)> = chosen
        .selected
        .iter()
        .filter_map(|&v| match chosen.meaning(v) {
            Meaning::Lobe(l) => Some((v, l.code())),
            _ => None,
        })
        .collect();
    let (lobes, lobes_from) = if lobe_codes.len() >= 2 {
        (
            lobes_from_labels(&mesh, &volume, &lobe_codes, side),
            "labels",
        )
    } else {
        (lobes::classify(side, &mesh), "planes")
    };
    let distance_to_mask = distances(&mesh, &closed.grid, &crop_to_body);
    lap("lobes and distances", &mut seconds);
    Ok(FromMask {
        mesh,
        lobes,
        lobes_from,
        frame: volume.frame.clone(),
        convention: chosen.convention,
        convention_reason: chosen.reason,
        labels_used: chosen.selected,
        sides_from: separated.sides_from,
        mask_volume_ml,
        closed_volume_ml: closed.volume_ml,
        genus_before,
        genus_after: closed.genus,
        closing_mm: closed.closing_mm,
        cavities_filled: cavities_filled + closed.filled,
        voxels_dropped,
        smoothing_mm: sigma,
        grid_step_mm: h,
        distance_to_mask,
        side_reason,
        orientation_reason,
        warnings,
        seconds,
    })
}

/// A surface made from one voxel set.
struct Extracted {
    mesh: TriMesh,
    /// Grid step, mm.
    h: f64,
    /// Euler characteristic.
    euler: i64,
    /// Crossing triangle pairs left.
    crossing: usize,
}

/// The surface of `g` (a crop with voxel → body `to_body`): smoothed field, marching tetrahedra at
/// the step that gives about `vertices`, short edges collapsed, slivers flipped, relaxed onto the
/// field, untangled, volume matched to `volume_ml`.
fn extract(
    g: &Grid,
    to_body: VoxelToBody,
    sigma: f64,
    vertices: usize,
    volume_ml: f64,
    need_genus_0: bool,
) -> Result<Option<Extracted>, MaskError> {
    let field = surface::Field::blurred(g.dims, &g.on, to_body, sigma);
    let spacing = to_body.spacing();
    let area_estimate = staircase_area(g) / 1.5;
    let mut h = (4.0 * area_estimate / vertices as f64)
        .sqrt()
        .clamp(0.15, 12.0);
    // The level whose surface encloses the mask's volume (the blur moves the 0.5 level inwards
    // where the surface is convex): a secant search on marching tetrahedra's own volume. Taking
    // the volume by the level keeps the surface a level set, which never crosses itself; an
    // offset along the normals afterwards can, where the lung is thin.
    let target_mm3 = volume_ml * 1000.0;
    // The grid last sampled, kept while the level is searched on it.
    let mut nodes: Option<surface::Nodes> = None;
    let volume_at = |nodes: &mut Option<surface::Nodes>, iso: f64, h: f64| {
        marching_tetrahedra_kept(&field, nodes, iso, spacing.map(|s| h / s)).enclosed_volume_mm3()
    };
    // The grid is never coarser than twice the smoothing: a sheet of lung thinner than the grid
    // step (an anterior border, a costophrenic recess) would be punctured by the piecewise-linear
    // level set, and each puncture is a false tunnel. Fewer vertices than that grid gives are had
    // by collapsing short edges (a decimation) instead of by a coarser grid.
    let min_spacing = spacing.iter().cloned().fold(f64::INFINITY, f64::min);
    let mut h_grid_max = (2.0 * sigma).max(spacing.iter().cloned().fold(0.0, f64::max));
    let mut h_vol = h.min(h_grid_max);
    let mut iso = 0.5;
    let mut first = marching_tetrahedra_kept(&field, &mut nodes, iso, spacing.map(|s| h_vol / s));
    if need_genus_0 && !genus_0(&first) {
        // A handle at the first grid is almost always kept by the search's grids (the same
        // field, at the same level): the next closing is tried at once instead of after the
        // whole search — except where a finer grid may lose it (`finer_without_handle`).
        let Some((hf, m)) = finer_without_handle(&field, iso, h, h_grid_max, min_spacing) else {
            return Ok(None);
        };
        h_grid_max = hf;
        h_vol = hf;
        first = m;
    }
    let mut v0 = first.enclosed_volume_mm3();
    let mut iso_prev = if v0 < target_mm3 { 0.45 } else { 0.55 };
    let mut v_prev = volume_at(&mut nodes, iso_prev, h_vol);
    for _ in 0..4 {
        if (v0 / target_mm3 - 1.0).abs() < 2e-4 || v0 == v_prev {
            break;
        }
        let next = (iso + (target_mm3 - v0) * (iso - iso_prev) / (v0 - v_prev)).clamp(0.2, 0.8);
        iso_prev = iso;
        v_prev = v0;
        iso = next;
        v0 = volume_at(&mut nodes, iso, h_vol);
    }
    // The spacing `h` is searched for the vertex count asked: the count falls as h grows (about
    // as 1/h² on the grid, faster in the decimation, whose collapse length joins the grid's at
    // h_grid_max), so a few steps by √ratio, then halving the bracket in log h; the closest is kept.
    let mut fine: Option<TriMesh> = None;
    let mut best: Option<(f64, TriMesh, f64)> = None;
    let (mut below, mut above): (Option<f64>, Option<f64>) = (None, None); // h with too many / too few
    for _round in 0..8 {
        let mut candidate = if h <= h_grid_max {
            marching_tetrahedra_kept(&field, &mut nodes, iso, spacing.map(|s| h / s))
        } else {
            fine.get_or_insert_with(|| {
                marching_tetrahedra_kept(&field, &mut nodes, iso, spacing.map(|s| h_grid_max / s))
            })
            .clone()
        };
        let length = if h <= h_grid_max {
            0.35 * h
        } else {
            0.35 * h * (h / h_grid_max).sqrt()
        };
        surface::collapse_short_edges(&mut candidate, length);
        let n = candidate.positions.len();
        if n == 0 {
            break;
        }
        let ratio = n as f64 / vertices as f64;
        let miss = ratio.ln().abs();
        if best.as_ref().is_none_or(|(m, _, _)| miss < *m) {
            best = Some((miss, candidate, h));
        }
        if (0.95..=1.05).contains(&ratio) {
            break;
        }
        if ratio > 1.0 {
            below = Some(below.map_or(h, |b: f64| b.max(h)));
        } else {
            above = Some(above.map_or(h, |a: f64| a.min(h)));
        }
        h = match (below, above) {
            (Some(lo), Some(hi)) => (lo * hi).sqrt(),
            _ => h * ratio.sqrt().clamp(0.5, 2.0),
        };
    }
    let Some((_, mut mesh, h_used)) = best else {
        return Err(MaskError::Surface {
            path: PathBuf::new(),
            message: "the mask gives no surface at the level of its volume".into(),
        });
    };
    let h = h_used;
    drop(nodes);
    let internal = |e: String| MaskError::Surface {
        path: PathBuf::new(),
        message: format!(
            "internal error: the surface made from the mask is not a closed manifold ({e}); please \
             report it with the mask"
        ),
    };
    let euler = check(&mesh).map_err(|e| internal(e.to_string()))?.euler;
    if need_genus_0 && euler != 2 {
        return Ok(None);
    }
    let crossing = flipped_and_relaxed(&mut mesh, &field, iso);
    let topology = check(&mesh).map_err(|e| internal(e.to_string()))?;
    Ok(Some(Extracted {
        mesh,
        h,
        euler: topology.euler,
        crossing,
    }))
}

/// `mesh` (as extracted and collapsed) with its slivers flipped and relaxed onto `field`'s level
/// `iso` as far as it stays free of crossings; returns the crossing pairs left (0 but where
/// untangling failed at every relaxation, down to none).
fn flipped_and_relaxed(mesh: &mut TriMesh, field: &surface::Field, iso: f64) -> usize {
    // Slivers marching tetrahedra cut along its grid flipped into better triangles first: the
    // relaxation moves vertices but never changes which are joined. (Flipping again after the
    // relaxation, with a second collapse, was tried on 2026-12-07: fewer slivers, but one more of
    // the 12 COPDgene lungs folded within its tidal breath at 20 000 vertices.)
    let unflipped = mesh.clone();
    let flips = surface::flip_edges(mesh, 4);
    // Relaxed as far as the surface stays free of crossings; where untangling cannot undo what
    // the relaxation did, a gentler relaxation is taken instead, down to none. A flip only
    // re-triangulates a nearly flat quad, but on a coarse surface "nearly flat" is a fraction of a
    // long edge, and across a thin sheet that can cross the other side (the one-lung MetaImage mask
    // at 3 000 vertices: 49 crossing pairs): then the surface as extracted, whose triangles are a
    // level set's and never cross (the collapses are checked), is relaxed instead.
    let flipped = mesh.clone();
    let mut crossing = usize::MAX;
    // Without a flip the unflipped surface is the same: nothing to fall back to.
    let fallback: &[TriMesh] = if flips > 0 {
        std::slice::from_ref(&unflipped)
    } else {
        &[]
    };
    for (start, iterations) in [(&flipped, 8), (&flipped, 3), (&flipped, 0)]
        .into_iter()
        .chain(fallback.iter().flat_map(|m| [(m, 8), (m, 3), (m, 0)]))
    {
        *mesh = start.clone();
        surface::relax_onto(mesh, field, iso, iterations);
        crossing = surface::untangle(mesh, field, iso, 4);
        if crossing == 0 {
            break;
        }
    }
    crossing
}

/// [`surface::marching_tetrahedra`] of `field` at `iso` on the grid of `step` voxels, the grid's
/// samples taken from `nodes` when it holds that grid and kept there otherwise (the same surface,
/// without sampling the field again for each level tried on one grid).
fn marching_tetrahedra_kept(
    field: &surface::Field,
    nodes: &mut Option<surface::Nodes>,
    iso: f64,
    step: [f64; 3],
) -> TriMesh {
    let kept = match nodes.take() {
        Some(k) if k.step() == step => k,
        _ => surface::Nodes::sample(field, step),
    };
    let mesh = surface::marching_tetrahedra_at(field, &kept, iso);
    *nodes = Some(kept);
    mesh
}

/// Marching tetrahedra's surface is closed, so E = 3F/2 and χ = V − F/2: genus 0 is χ = 2.
fn genus_0(m: &TriMesh) -> bool {
    m.positions.len() as i64 - m.triangles.len() as i64 / 2 == 2
}

/// Where the count asked is had by decimating the finest grid (`h` > `h_grid_max`), a finer grid
/// may not puncture the thin sheet that made a handle: the first finer grid (÷1.5, ÷2.25, not
/// below half a voxel) whose surface has none, with that surface.
fn finer_without_handle(
    field: &surface::Field,
    iso: f64,
    h: f64,
    h_grid_max: f64,
    min_spacing: f64,
) -> Option<(f64, TriMesh)> {
    if h <= h_grid_max {
        return None;
    }
    let spacing = field.to_body.spacing();
    for f in [1.5, 2.25] {
        let hf = h_grid_max / f;
        if hf < 0.5 * min_spacing {
            break;
        }
        let m = surface::marching_tetrahedra(field, iso, spacing.map(|s| hf / s));
        if genus_0(&m) {
            return Some((hf, m));
        }
    }
    None
}

/// `axes` with its L/R, A/P and S/I letters reversed as asked.
fn fixed_axes(axes: Axes, lr: bool, ap: bool, si: bool) -> Axes {
    use volume::Dir::*;
    let mut out = axes;
    for d in &mut out.0 {
        *d = match *d {
            L if lr => R,
            R if lr => L,
            A if ap => P,
            P if ap => A,
            S if si => I,
            I if si => S,
            x => x,
        };
    }
    out
}

/// One lung's voxels as the frame check needs them: volume (ml), lowest body-frame Z (mm), and the
/// same two shape measures [`crate::surface_checks::infer_orientation`] takes from a surface,
/// here from the voxel centres, so both lungs of an image can be weighed before either is meshed.
#[derive(Debug, Clone, Copy)]
struct LungStats {
    volume_ml: f64,
    lowest_mm: f64,
    /// (mean Y of the lowest 5 % slab − centroid Y) / Y extent: negative on a lung in the body
    /// frame (its lowest point is the posterior costophrenic recess).
    base_offset: f64,
    /// (X·Y box area of the top 15 % slab − that of the bottom one) / their sum: negative on a lung
    /// in the body frame (it narrows towards the apex).
    taper: f64,
    /// ln(voxels in the posterior third of the Y extent / voxels in the anterior third): positive
    /// on a lung in the body frame (deep posteriorly beside the spine, thin towards the anterior
    /// junction: 1.17–6.2 on all 24 shared COPDgene lungs). A second A/P cue beside the base, which
    /// a flat, emphysematous diaphragm can mislead.
    bulk: f64,
}

/// [`LungStats`] of the voxels at `points` (body frame, mm), each `voxel_ml`.
fn stats_of(points: &[DVec3], voxel_ml: f64) -> LungStats {
    use crate::surface_checks::{ORIENTATION_BASE_SLAB_REL, ORIENTATION_TAPER_SLAB_REL};
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    let mut sum = DVec3::ZERO;
    for p in points {
        lo = lo.min(*p);
        hi = hi.max(*p);
        sum += *p;
    }
    let n = points.len().max(1) as f64;
    let centroid = sum / n;
    let extent = hi - lo;
    let base_slab = ORIENTATION_BASE_SLAB_REL * extent.z;
    let (mut base_y, mut base_n) = (0.0, 0usize);
    let taper_slab = ORIENTATION_TAPER_SLAB_REL * extent.z;
    let mut boxes = [[DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)]; 2];
    for p in points {
        if p.z <= lo.z + base_slab {
            base_y += p.y;
            base_n += 1;
        }
        for (b, inside) in [(0, p.z <= lo.z + taper_slab), (1, p.z >= hi.z - taper_slab)] {
            if inside {
                boxes[b][0] = boxes[b][0].min(*p);
                boxes[b][1] = boxes[b][1].max(*p);
            }
        }
    }
    let area = |b: [DVec3; 2]| {
        let d = b[1] - b[0];
        if d.x >= 0.0 {
            (d.x + 1e-9) * (d.y + 1e-9)
        } else {
            0.0
        }
    };
    let (bottom, top) = (area(boxes[0]), area(boxes[1]));
    let (mut posterior, mut anterior) = (0usize, 0usize);
    for p in points {
        let t = (p.y - lo.y) / extent.y.max(1e-9);
        if t < 1.0 / 3.0 {
            posterior += 1;
        } else if t > 2.0 / 3.0 {
            anterior += 1;
        }
    }
    LungStats {
        bulk: ((posterior as f64 + 1.0) / (anterior as f64 + 1.0)).ln(),
        volume_ml: points.len() as f64 * voxel_ml,
        lowest_mm: lo.z,
        base_offset: if base_n > 0 && extent.y > 0.0 {
            (base_y / base_n as f64 - centroid.y) / extent.y
        } else {
            0.0
        },
        taper: if top + bottom > 0.0 {
            (top - bottom) / (top + bottom)
        } else {
            0.0
        },
    }
}

fn lung_stats(volume: &LabelVolume, pick: impl Fn(u16) -> bool) -> LungStats {
    let [nx, ny, _] = volume.dims;
    let points: Vec<DVec3> = volume
        .labels
        .iter()
        .enumerate()
        .filter(|&(_, &l)| l != 0 && pick(l))
        .map(|(idx, _)| {
            volume.to_body.apply(DVec3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            ))
        })
        .collect();
    stats_of(&points, volume.voxel_ml())
}

fn part_stats(g: &Grid, to_body: &VoxelToBody, voxel_ml: f64) -> LungStats {
    let [nx, ny, _] = g.dims;
    let points: Vec<DVec3> =
        g.on.iter()
            .enumerate()
            .filter(|&(_, &on)| on)
            .map(|(idx, _)| {
                to_body.apply(DVec3::new(
                    (idx % nx) as f64,
                    ((idx / nx) % ny) as f64,
                    (idx / (nx * ny)) as f64,
                ))
            })
            .collect();
    stats_of(&points, voxel_ml)
}

/// The selected voxels on a crop padded by `margin_mm` (which may reach outside the image: outside
/// is background), and the crop's voxel → body transform.
fn crop(
    volume: &LabelVolume,
    pick: impl Fn(u16) -> bool,
    margin_mm: f64,
) -> Option<(Grid, VoxelToBody)> {
    let [nx, ny, nz] = volume.dims;
    let mut lo = [usize::MAX; 3];
    let mut hi = [0usize; 3];
    let mut any = false;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let l = volume.labels[volume.index(i, j, k)];
                if l != 0 && pick(l) {
                    any = true;
                    for (a, v) in [i, j, k].into_iter().enumerate() {
                        lo[a] = lo[a].min(v);
                        hi[a] = hi[a].max(v);
                    }
                }
            }
        }
    }
    if !any {
        return None;
    }
    let spacing = volume.to_body.spacing();
    let pad: [isize; 3] = [0, 1, 2].map(|a| (margin_mm / spacing[a]).ceil() as isize + 2);
    let start: [isize; 3] = [0, 1, 2].map(|a| lo[a] as isize - pad[a]);
    let dims: [usize; 3] = [0, 1, 2].map(|a| hi[a] - lo[a] + 1 + 2 * pad[a] as usize);
    let mut grid = Grid::new(dims, spacing);
    for k in lo[2]..=hi[2] {
        for j in lo[1]..=hi[1] {
            for i in lo[0]..=hi[0] {
                let l = volume.labels[volume.index(i, j, k)];
                if l != 0 && pick(l) {
                    let g = grid.at(
                        (i as isize - start[0]) as usize,
                        (j as isize - start[1]) as usize,
                        (k as isize - start[2]) as usize,
                    );
                    grid.on[g] = true;
                }
            }
        }
    }
    let to_body = VoxelToBody {
        linear: volume.to_body.linear,
        origin: volume.to_body.apply(DVec3::new(
            start[0] as f64,
            start[1] as f64,
            start[2] as f64,
        )),
    };
    Some((grid, to_body))
}

/// Area of the voxel faces between inside and outside, mm².
fn staircase_area(g: &Grid) -> f64 {
    let [nx, ny, nz] = g.dims;
    let s = g.spacing;
    let face = [s[1] * s[2], s[0] * s[2], s[0] * s[1]];
    let mut area = 0.0;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let on = g.on[g.at(i, j, k)];
                if i + 1 < nx && on != g.on[g.at(i + 1, j, k)] {
                    area += face[0];
                }
                if j + 1 < ny && on != g.on[g.at(i, j + 1, k)] {
                    area += face[1];
                }
                if k + 1 < nz && on != g.on[g.at(i, j, k + 1)] {
                    area += face[2];
                }
            }
        }
    }
    area
}

/// Distance from each vertex to the nearest voxel face between inside and outside of `g` (the
/// staircase boundary), searched within 4 voxels, in mm (voxel axes taken as orthogonal).
fn distances(mesh: &TriMesh, g: &Grid, to_body: &VoxelToBody) -> Distances {
    let inverse = to_body.linear.inverse();
    let s = g.spacing;
    let [nx, ny, nz] = g.dims;
    let on = |i: isize, j: isize, k: isize| {
        i >= 0
            && j >= 0
            && k >= 0
            && (i as usize) < nx
            && (j as usize) < ny
            && (k as usize) < nz
            && g.on[g.at(i as usize, j as usize, k as usize)]
    };
    let mut d: Vec<f64> = mesh
        .positions
        .iter()
        .map(|q| {
            let u = inverse * (DVec3::from(q.map(|v| v as f64)) - to_body.origin);
            let c = u.round();
            let (ci, cj, ck) = (c.x as isize, c.y as isize, c.z as isize);
            let mut best = f64::INFINITY;
            for r in [2isize, 4] {
                for k in ck - r..=ck + r {
                    for j in cj - r..=cj + r {
                        for i in ci - r..=ci + r {
                            let here = on(i, j, k);
                            // Faces towards +x, +y, +z of voxel (i, j, k).
                            for axis in 0..3 {
                                let (a, b, c2) = match axis {
                                    0 => (i + 1, j, k),
                                    1 => (i, j + 1, k),
                                    _ => (i, j, k + 1),
                                };
                                if here == on(a, b, c2) {
                                    continue;
                                }
                                // The face: centre at the voxel's centre + half a step along axis.
                                let mut centre = DVec3::new(i as f64, j as f64, k as f64);
                                centre[axis] += 0.5;
                                let delta = u - centre;
                                let mut dist2 = 0.0;
                                for e in 0..3 {
                                    let along = if e == axis {
                                        delta[e].abs()
                                    } else {
                                        (delta[e].abs() - 0.5).max(0.0)
                                    };
                                    dist2 += (along * s[e]).powi(2);
                                }
                                best = best.min(dist2);
                            }
                        }
                    }
                }
                if best.is_finite() {
                    break;
                }
            }
            best.sqrt()
        })
        .collect();
    let n = d.len().max(1) as f64;
    let mean = d.iter().filter(|v| v.is_finite()).sum::<f64>() / n;
    d.sort_by(|a, b| a.total_cmp(b));
    let p95 = d
        .get(((d.len() as f64 * 0.95) as usize).min(d.len().saturating_sub(1)))
        .copied()
        .unwrap_or(0.0);
    let max = d.last().copied().unwrap_or(0.0);
    let voxel = (s[0] * s[1] * s[2]).cbrt();
    Distances {
        mean_mm: mean,
        p95_mm: p95,
        max_mm: max,
        mean_voxels: mean / voxel,
    }
}

/// Each vertex's lobe: the lobe label of the nearest voxel holding one of `codes` (value, lobe
/// code), searched within 6 voxels; a vertex with none that near takes the fissure planes' lobe.
fn lobes_from_labels(
    mesh: &TriMesh,
    volume: &LabelVolume,
    codes: &[(u16, u8)],
    side: Side,
) -> Vec<u8> {
    let planes = lobes::classify(side, mesh);
    let inverse = volume.to_body.linear.inverse();
    let s = volume.to_body.spacing();
    let [nx, ny, nz] = volume.dims;
    let code_of = |l: u16| codes.iter().find(|&&(v, _)| v == l).map(|&(_, c)| c);
    mesh.positions
        .iter()
        .enumerate()
        .map(|(vi, q)| {
            let u = inverse * (DVec3::from(q.map(|v| v as f64)) - volume.to_body.origin);
            let c = u.round();
            let mut best = (f64::INFINITY, 0u8);
            for r in [2isize, 4, 6] {
                for k in c.z as isize - r..=c.z as isize + r {
                    for j in c.y as isize - r..=c.y as isize + r {
                        for i in c.x as isize - r..=c.x as isize + r {
                            if i < 0
                                || j < 0
                                || k < 0
                                || i as usize >= nx
                                || j as usize >= ny
                                || k as usize >= nz
                            {
                                continue;
                            }
                            let Some(code) = code_of(
                                volume.labels[volume.index(i as usize, j as usize, k as usize)],
                            ) else {
                                continue;
                            };
                            let d2 = ((i as f64 - u.x) * s[0]).powi(2)
                                + ((j as f64 - u.y) * s[1]).powi(2)
                                + ((k as f64 - u.z) * s[2]).powi(2);
                            if d2 < best.0 {
                                best = (d2, code);
                            }
                        }
                    }
                }
                if best.0.is_finite() {
                    break;
                }
            }
            if best.1 == 0 {
                planes[vi]
            } else {
                best.1
            }
        })
        .collect()
}

/// The lobes a code list holds, for the report.
pub fn lobe_name(code: u8) -> &'static str {
    Lobe::from_code(code).unwrap_or(Lobe::Unknown).name()
}
