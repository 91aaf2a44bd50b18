//! # motion_fit: the direction model's constants from corresponding points (seed §6.4.2)
//!
//! The seed fits `c1..c6` of eq. 6.14–6.16 to a 4D CT (5 % → 40 % tidal volume) by exhaustive search
//! with step 0.01 and checks the same directions, linearly scaled, against a third phase (100 %).
//! Here the data are corresponding points (landmark pairs, or two meshes of the same lung with the
//! same vertex order): `A` at the reference phase, `B` at the fitted phase, optional further phases.
//!
//! Model, per lung and axis (EQUATIONS.md §2.4 with the magnitude carried by the factors): the
//! displacement from `A` to `B` is
//!
//! ```text
//!   δx = s_lat · c1 · x̂^c2,   δy = c3 · ŷ^c4,   δz = −c5 · ẑ^c6          (eq. 6.14–6.16)
//! ```
//!
//! in the body frame (+X patient left, +Y anterior, +Z superior), with x̂ from the mediastinum
//! outwards, ŷ from posterior, ẑ from the apex (normalised in `A`'s bounding box) and `s_lat` the
//! lung's lateral sign. `c1, c3, c5` are in mm at phase `B` and signed (a data set whose motion runs
//! against the seed's axes gets negative factors); only their ratios matter to the kernel's unit
//! directions. Each axis is separable: for a fixed exponent the factor is linear least squares, and
//! the exponent is searched on the seed's 0.01 grid over [0, 8] and then refined by golden section —
//! the exact minimiser of the squared error, which is what the seed's exhaustive search approximates.
//! A further phase `C` is fitted with one factor `k_C` (linearity in volume, seed §6.1):
//! `δ_C ≈ k_C · δ_B(model)`.
//!
//! Residuals are reported in mm (mean and max of |δ − model|) beside the no-motion baseline (mean
//! |δ|): a fit is only useful where its error is well below that baseline.

use glam::DVec3;
use thiserror::Error;

use lung_model::deform::MotionConstants;
use lung_model::mesh::Side;

/// Errors of the motion fit.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum MotionFitError {
    /// A model's equations have no unique solution (too few points for its complexity).
    #[error(
        "the {lung} lung's landmarks do not determine the model (too few, or all in one plane)"
    )]
    Singular {
        /// Lung.
        lung: &'static str,
    },
    /// The point sets differ in length.
    #[error("{what} has {got} points but the reference has {expected}: the sets must correspond point by point")]
    Count {
        /// Which set.
        what: String,
        /// Its size.
        got: usize,
        /// Reference size.
        expected: usize,
    },
    /// Too few points to fit.
    #[error("the {lung} lung has {points} points; at least 8 are needed to fit six constants")]
    TooFew {
        /// Lung.
        lung: &'static str,
        /// Points.
        points: usize,
    },
    /// A coordinate is not finite.
    #[error("{what}: point {index} is not finite")]
    NonFinite {
        /// Which set.
        what: String,
        /// Index.
        index: usize,
    },
    /// The lung is flat along an axis.
    #[error("the {lung} lung's reference points do not span the {axis} axis")]
    Flat {
        /// Lung.
        lung: &'static str,
        /// Axis name.
        axis: &'static str,
    },
    /// The set is one lung and no side was given.
    #[error("the points form one lung (no mid-sagittal gap of at least {gap_mm} mm): say which with --lung left|right")]
    SideNeeded {
        /// Gap threshold.
        gap_mm: f64,
    },
    /// A side was given (the set is one lung), but the set clearly holds both lungs.
    #[error(
        "--lung {side} says the points are one lung, but they look like both: a {gap_mm:.0} mm gap in X \
         parts them into {right} and {left} points, and they span {x_mm:.0} mm from side to side against \
         {y_mm:.0} mm from front to back (one lung is narrower than it is deep; both lungs together are \
         wider): drop --lung to fit each lung, or give one lung's points"
    )]
    TwoLungsForOneSide {
        /// The side given.
        side: &'static str,
        /// The gap between the parts, mm.
        gap_mm: f64,
        /// Points at smaller X (a right lung's side).
        right: usize,
        /// Points at larger X.
        left: usize,
        /// Extent in X (left–right), mm.
        x_mm: f64,
        /// Extent in Y (front–back), mm.
        y_mm: f64,
    },
}

/// Smallest gap in X (mm) taken as the space between the lungs.
pub const MIN_GAP_MM: f64 = 10.0;

/// A set whose X extent (left–right) is at least this many times its Y extent (front–back) is as wide
/// as two lungs side by side: one lung is narrower than it is deep (adult ≈ 10–13 cm wide, 16–20 cm
/// deep; the default lungs 86 × 112 mm), both together ≈ 1.5–2× wider than deep [Gray-2016, ch. 54].
pub const TWO_LUNGS_X_OVER_Y: f64 = 1.2;

/// The largest gap in X between consecutive points (sorted by X) whose middle lies in the middle 80 %
/// of the X range: (gap mm, split position in `order`).
fn central_gap(points: &[DVec3], order: &[usize]) -> (f64, usize) {
    let mut best = (0.0, 0);
    if points.len() >= 2 {
        let (lo, hi) = (points[order[0]].x, points[*order.last().unwrap()].x);
        let range = hi - lo;
        for w in 1..order.len() {
            let gap = points[order[w]].x - points[order[w - 1]].x;
            let mid = 0.5 * (points[order[w]].x + points[order[w - 1]].x);
            if gap > best.0 && mid > lo + 0.1 * range && mid < hi - 0.1 * range {
                best = (gap, w);
            }
        }
    }
    best
}

/// Split `points` (indices) into lungs. Without a side: at the largest gap in X, when it is at least
/// [`MIN_GAP_MM`] and lies in the middle 80 % of the X range (else [`MotionFitError::SideNeeded`]).
/// With a side the set is that one lung, never split (sparse landmarks of one lung have gaps too);
/// a set that clearly holds both lungs — such a gap *and* an X extent of at least
/// [`TWO_LUNGS_X_OVER_Y`] times its Y extent — is refused ([`MotionFitError::TwoLungsForOneSide`]).
/// Returns (side, indices) per lung.
pub fn split_lungs(
    points: &[DVec3],
    side: Option<Side>,
) -> Result<Vec<(Side, Vec<usize>)>, MotionFitError> {
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by(|&a, &b| points[a].x.total_cmp(&points[b].x));
    let (gap, at) = central_gap(points, &order);
    match side {
        None if gap >= MIN_GAP_MM => {
            // +X is the patient's left: the lung at larger X is the left one.
            let (right, left) = order.split_at(at);
            Ok(vec![
                (Side::Right, right.to_vec()),
                (Side::Left, left.to_vec()),
            ])
        }
        None => Err(MotionFitError::SideNeeded { gap_mm: MIN_GAP_MM }),
        Some(s) => {
            let (lo, hi) = points.iter().fold(
                (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
                |(lo, hi), p| (lo.min(*p), hi.max(*p)),
            );
            let size = hi - lo;
            if gap >= MIN_GAP_MM && size.x >= TWO_LUNGS_X_OVER_Y * size.y {
                return Err(MotionFitError::TwoLungsForOneSide {
                    side: s.name(),
                    gap_mm: gap,
                    right: at,
                    left: points.len() - at,
                    x_mm: size.x,
                    y_mm: size.y,
                });
            }
            Ok(vec![(s, order)])
        }
    }
}

/// Which lung a set's motion suggests, when it says so clearly: on inspiration a lung's lateral wall
/// moves outwards (the ribs swing out), so a left lung's points move towards +X on average and a
/// right lung's towards −X (eq. 6.14's lateral term, `side.lateral_sign()`). The direction of the
/// phases comes from the base (it moves down on inspiration); evidence needs a mean X motion of at
/// least 0.5 mm and three standard errors. Returns the side and the numbers behind it.
pub fn side_from_motion(start: &[DVec3], delta: &[DVec3]) -> Option<(Side, String)> {
    let n = start.len().min(delta.len());
    if n < 8 {
        return None;
    }
    let (lo, hi) = start[..n]
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.z), hi.max(p.z))
        });
    let mid = 0.5 * (lo + hi);
    let basal: Vec<f64> = start[..n]
        .iter()
        .zip(delta)
        .filter(|(p, _)| p.z < mid)
        .map(|(_, d)| d.z)
        .collect();
    let basal_dz = basal.iter().sum::<f64>() / basal.len().max(1) as f64;
    if basal_dz == 0.0 || !basal_dz.is_finite() {
        return None;
    }
    // Inspiration: the base moves down; from end-inhale to end-exhale every direction is reversed.
    let towards_inspiration = -basal_dz.signum();
    let dx: Vec<f64> = delta[..n]
        .iter()
        .map(|d| d.x * towards_inspiration)
        .collect();
    let mean = dx.iter().sum::<f64>() / n as f64;
    let var = dx.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let se = (var / n as f64).sqrt();
    if !(mean.abs() >= 0.5 && mean.abs() >= 3.0 * se) {
        return None;
    }
    let side = if mean > 0.0 { Side::Left } else { Side::Right };
    Some((
        side,
        format!(
            "on inspiration the points move towards {} by {:.1} mm on average (± {:.1} mm standard \
             error), as a {} lung's lateral wall does",
            if mean > 0.0 {
                "+X (the patient's left)"
            } else {
                "-X (the patient's right)"
            },
            mean.abs(),
            se,
            side.name()
        ),
    ))
}

/// One axis's fitted power law `δ = factor · t^exponent`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct AxisFit {
    factor: f64,
    exponent: f64,
    sse: f64,
}

/// Least-squares factor for a fixed exponent, and the squared error.
fn axis_sse(t: &[f64], d: &[f64], e: f64) -> (f64, f64) {
    let (mut num, mut den) = (0.0, 0.0);
    for (&ti, &di) in t.iter().zip(d) {
        let b = ti.powf(e);
        num += di * b;
        den += b * b;
    }
    let c = if den > 0.0 { num / den } else { 0.0 };
    let sse = t
        .iter()
        .zip(d)
        .map(|(&ti, &di)| (di - c * ti.powf(e)).powi(2))
        .sum();
    (c, sse)
}

const MAX_EXPONENT: f64 = 8.0;

fn fit_axis(t: &[f64], d: &[f64]) -> AxisFit {
    // The seed's exhaustive grid (step 0.01) ...
    let mut best = (f64::INFINITY, 0.0);
    let steps = (MAX_EXPONENT / 0.01).round() as usize;
    for k in 0..=steps {
        let e = k as f64 * 0.01;
        let (_, sse) = axis_sse(t, d, e);
        if sse < best.0 {
            best = (sse, e);
        }
    }
    // ... then golden section inside the bracket around the best grid point.
    let (mut a, mut b) = ((best.1 - 0.01).max(0.0), (best.1 + 0.01).min(MAX_EXPONENT));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..60 {
        let x1 = b - g * (b - a);
        let x2 = a + g * (b - a);
        if axis_sse(t, d, x1).1 <= axis_sse(t, d, x2).1 {
            b = x2;
        } else {
            a = x1;
        }
    }
    let mut e = 0.5 * (a + b);
    let (mut c, mut sse) = axis_sse(t, d, e);
    if best.0 < sse {
        e = best.1;
        (c, sse) = axis_sse(t, d, e);
    }
    AxisFit {
        factor: c,
        exponent: e,
        sse,
    }
}

/// Residual figures, mm.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct Residuals {
    /// Mean |δ − model|.
    pub mean_error_mm: f64,
    /// Max |δ − model|.
    pub max_error_mm: f64,
    /// RMS |δ − model|.
    pub rms_error_mm: f64,
    /// No-motion baseline: mean |δ|.
    pub baseline_mean_mm: f64,
}

fn residuals(delta: &[DVec3], model: &[DVec3]) -> Residuals {
    let n = delta.len().max(1) as f64;
    let mut r = Residuals::default();
    let mut sq = 0.0;
    for (d, m) in delta.iter().zip(model) {
        let e = (*d - *m).length();
        r.mean_error_mm += e;
        r.max_error_mm = r.max_error_mm.max(e);
        sq += e * e;
        r.baseline_mean_mm += d.length();
    }
    r.mean_error_mm /= n;
    r.baseline_mean_mm /= n;
    r.rms_error_mm = (sq / n).sqrt();
    r
}

/// A further phase fitted by one scale.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PhaseFit {
    /// `k_C`: displacement at this phase / displacement at phase B.
    pub scale: f64,
    /// Residuals at this phase.
    #[serde(flatten)]
    pub residuals: Residuals,
}

/// The fit of one lung.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LungFit {
    /// Which lung.
    pub lung: Side,
    /// Points of this lung.
    pub points: usize,
    /// `c1..c9` (points mode: c1, c3, c5 in mm at phase B and c7..c9 Table 6.1; mesh and surface
    /// modes: the kernel's constants, c7..c9 fitted through the operator).
    pub constants: [f64; 9],
    /// Residuals at phase B.
    #[serde(flatten)]
    pub residuals: Residuals,
    /// Further phases, in the order given.
    pub also: Vec<PhaseFit>,
    /// Indices of this lung's points in the input sets.
    #[serde(skip)]
    pub indices: Vec<usize>,
}

impl LungFit {
    /// The constants as [`MotionConstants`].
    pub fn motion(&self) -> MotionConstants {
        MotionConstants { c: self.constants }
    }
}

/// Normalised coordinates (x̂, ŷ, ẑ) of `p` in the box `lo..hi` with the seed's origins.
fn normalised(p: DVec3, lo: DVec3, hi: DVec3, side: Side) -> DVec3 {
    let u = (p - lo) / (hi - lo);
    let u = u.clamp(DVec3::ZERO, DVec3::ONE);
    DVec3::new(
        match side {
            Side::Left => u.x,
            Side::Right => 1.0 - u.x,
        },
        u.y,
        1.0 - u.z,
    )
}

/// Model displacement of a lung with constants `c` at normalised position `n` (body frame, mm).
pub fn model_displacement(n: DVec3, c: &[f64; 9], side: Side) -> DVec3 {
    DVec3::new(
        side.lateral_sign() as f64 * c[0] * n.x.powf(c[1]),
        c[2] * n.y.powf(c[3]),
        -c[4] * n.z.powf(c[5]),
    )
}

/// Fit one lung: `a`, `b` and each of `also` are that lung's points (same order).
pub fn fit_lung(
    side: Side,
    a: &[DVec3],
    b: &[DVec3],
    also: &[Vec<DVec3>],
) -> Result<LungFit, MotionFitError> {
    if a.len() < 8 {
        return Err(MotionFitError::TooFew {
            lung: side.name(),
            points: a.len(),
        });
    }
    let lo = a.iter().fold(DVec3::splat(f64::INFINITY), |m, p| m.min(*p));
    let hi = a
        .iter()
        .fold(DVec3::splat(f64::NEG_INFINITY), |m, p| m.max(*p));
    for (k, axis) in ["X", "Y", "Z"].into_iter().enumerate() {
        if !(hi[k] - lo[k] > 1e-9) {
            return Err(MotionFitError::Flat {
                lung: side.name(),
                axis,
            });
        }
    }
    let n: Vec<DVec3> = a.iter().map(|&p| normalised(p, lo, hi, side)).collect();
    let delta: Vec<DVec3> = a.iter().zip(b).map(|(p, q)| *q - *p).collect();
    // Body-frame components mapped onto the seed's positive axes: lateral, anterior, towards base.
    let lat = side.lateral_sign() as f64;
    let t = |k: usize| n.iter().map(|v| v[k]).collect::<Vec<_>>();
    let fx = fit_axis(&t(0), &delta.iter().map(|d| lat * d.x).collect::<Vec<_>>());
    let fy = fit_axis(&t(1), &delta.iter().map(|d| d.y).collect::<Vec<_>>());
    let fz = fit_axis(&t(2), &delta.iter().map(|d| -d.z).collect::<Vec<_>>());
    let defaults = MotionConstants::table_6_1(side).c;
    let constants = [
        fx.factor,
        fx.exponent,
        fy.factor,
        fy.exponent,
        fz.factor,
        fz.exponent,
        defaults[6],
        defaults[7],
        defaults[8],
    ];
    let model: Vec<DVec3> = n
        .iter()
        .map(|&v| model_displacement(v, &constants, side))
        .collect();
    let residuals_b = residuals(&delta, &model);
    let also = also
        .iter()
        .map(|c| {
            let d: Vec<DVec3> = a.iter().zip(c).map(|(p, q)| *q - *p).collect();
            let (num, den) = d.iter().zip(&model).fold((0.0, 0.0), |(nu, de), (x, m)| {
                (nu + x.dot(*m), de + m.dot(*m))
            });
            let scale = if den > 0.0 { num / den } else { 0.0 };
            let scaled: Vec<DVec3> = model.iter().map(|m| *m * scale).collect();
            PhaseFit {
                scale,
                residuals: residuals(&d, &scaled),
            }
        })
        .collect();
    Ok(LungFit {
        lung: side,
        points: a.len(),
        constants,
        residuals: residuals_b,
        also,
        indices: Vec::new(),
    })
}

/// The whole fit: per lung and over all points.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MotionFit {
    /// "points" (corresponding points, the point-wise power law), "mesh" (two meshes with the same
    /// vertices, the kernel's model through the operator, point-to-point residuals) or "surface" (a
    /// second-phase surface without correspondences: residuals are distances to that surface).
    pub mode: &'static str,
    /// Over all points at phase B.
    #[serde(flatten)]
    pub residuals: Residuals,
    /// Over all points at each further phase.
    pub also: Vec<Residuals>,
    /// Per lung.
    pub lungs: Vec<LungFit>,
}

/// Fit point sets `a → b` (and further phases), splitting them into lungs at the mid-sagittal gap.
pub fn fit(
    a: &[DVec3],
    b: &[DVec3],
    also: &[(String, Vec<DVec3>)],
    side: Option<Side>,
) -> Result<MotionFit, MotionFitError> {
    let check = |what: &str, set: &[DVec3]| {
        if set.len() != a.len() {
            return Err(MotionFitError::Count {
                what: what.to_string(),
                got: set.len(),
                expected: a.len(),
            });
        }
        match set.iter().position(|p| !p.is_finite()) {
            Some(index) => Err(MotionFitError::NonFinite {
                what: what.to_string(),
                index,
            }),
            None => Ok(()),
        }
    };
    check("the reference set", a)?;
    check("the target set", b)?;
    for (name, set) in also {
        check(name, set)?;
    }
    let mut lungs = Vec::new();
    for (s, idx) in split_lungs(a, side)? {
        let pick = |set: &[DVec3]| idx.iter().map(|&i| set[i]).collect::<Vec<_>>();
        let extra: Vec<Vec<DVec3>> = also.iter().map(|(_, set)| pick(set)).collect();
        let mut f = fit_lung(s, &pick(a), &pick(b), &extra)?;
        f.indices = idx.clone();
        lungs.push(f);
    }
    Ok(MotionFit::from_lungs("points", also.len(), lungs))
}

/// Point-weighted pooling of per-lung residuals.
fn pool(items: Vec<(Residuals, usize)>) -> Residuals {
    let total: usize = items.iter().map(|x| x.1).sum::<usize>().max(1);
    let mut r = Residuals::default();
    let mut sq = 0.0;
    for (x, n) in items {
        let w = n as f64 / total as f64;
        r.mean_error_mm += w * x.mean_error_mm;
        r.baseline_mean_mm += w * x.baseline_mean_mm;
        r.max_error_mm = r.max_error_mm.max(x.max_error_mm);
        sq += w * x.rms_error_mm * x.rms_error_mm;
    }
    r.rms_error_mm = sq.sqrt();
    r
}

impl MotionFit {
    /// Pool per-lung fits (each with `also` further phases).
    pub fn from_lungs(mode: &'static str, also: usize, lungs: Vec<LungFit>) -> Self {
        let residuals = pool(lungs.iter().map(|l| (l.residuals, l.points)).collect());
        let also = (0..also)
            .map(|k| {
                pool(
                    lungs
                        .iter()
                        .map(|l| (l.also[k].residuals, l.points))
                        .collect(),
                )
            })
            .collect();
        Self {
            mode,
            residuals,
            also,
            lungs,
        }
    }
}

/// Responses of the operator to the three coordinate fields: `G_a = Tᵀ x̂_a` (a = x̂, ŷ, ẑ), so the
/// elastostatic force of `f = c7·x̂ + c8·ŷ + c9·ẑ` is `c7·G_x + c8·G_y + c9·G_z` (eq. 6.1 is linear).
/// Also returns the normalised positions and the mean non-zeros per transfer row. The transfer is
/// the bake's: its amplitude smoothed over `smoothing_mm` (EQUATIONS.md §2.4).
pub(crate) type Responses = (Vec<DVec3>, Vec<Vec<f64>>, f64);

pub(crate) fn operator_responses(
    side: Side,
    mesh: &lung_model::mesh::TriMesh,
    elasticity: &lung_model::operator::Elasticity,
    tolerance: f64,
    smoothing_mm: f64,
) -> Result<Responses, crate::kernel::BakeError> {
    use crate::operator::{compute_transfer, NodeGraph, Schedule};
    use lung_model::deform::normalised_position;
    lung_model::mesh::check(mesh)?;
    let bb = mesh.aabb();
    let norm: Vec<DVec3> = mesh
        .positions
        .iter()
        .map(|&p| normalised_position(p, &bb, side))
        .collect();
    let graph = NodeGraph::from_mesh(mesh, elasticity, |p| normalised_position(p, &bb, side))?;
    let mut t = compute_transfer(&graph, tolerance, Schedule::SpringsForward, &|_| {})?;
    crate::smooth::smooth_amplitude(&mut t, mesh, smoothing_mm)?;
    let g: Vec<Vec<f64>> = (0..3)
        .map(|a| t.elastostatic(&norm.iter().map(|n| n[a]).collect::<Vec<_>>()))
        .collect();
    Ok((norm, g, t.stats.mean_row_nnz))
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::generate;

    fn lung_points(side: Side, n: usize) -> Vec<DVec3> {
        generate::lung(side, n)
            .unwrap()
            .positions
            .iter()
            .map(|p| DVec3::from(p.map(|v| v as f64)))
            .collect()
    }

    fn move_points(a: &[DVec3], side: Side, c: &[f64; 9], scale: f64) -> Vec<DVec3> {
        let lo = a.iter().fold(DVec3::splat(f64::INFINITY), |m, p| m.min(*p));
        let hi = a
            .iter()
            .fold(DVec3::splat(f64::NEG_INFINITY), |m, p| m.max(*p));
        a.iter()
            .map(|&p| p + scale * model_displacement(normalised(p, lo, hi, side), c, side))
            .collect()
    }

    /// A small deterministic noise source (xorshift), mm.
    fn noise(seed: &mut u64, sigma: f64) -> DVec3 {
        let mut g = || {
            // Sum of 4 uniforms ≈ Gaussian.
            let mut s = 0.0;
            for _ in 0..4 {
                *seed ^= *seed << 13;
                *seed ^= *seed >> 7;
                *seed ^= *seed << 17;
                s += (*seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
            }
            s * sigma * (3.0f64).sqrt()
        };
        DVec3::new(g(), g(), g())
    }

    const TRUTH: [f64; 9] = [3.0, 0.8, 6.5, 0.5, 14.0, 2.2, 0.01, 0.95, 0.07];

    #[test]
    fn a_given_side_means_one_lung_and_both_lungs_are_refused_for_one_side() {
        let right = lung_points(Side::Right, 800);
        let left = lung_points(Side::Left, 800);
        // Sparse landmarks of one lung (every 23rd vertex) have gaps of 10 mm and more in X: with
        // --lung they stay one lung.
        let sparse: Vec<DVec3> = left.iter().step_by(23).copied().collect();
        let parts = split_lungs(&sparse, Some(Side::Left)).unwrap();
        assert_eq!(parts.len(), 1);
        assert_eq!((parts[0].0, parts[0].1.len()), (Side::Left, sparse.len()));
        // Both lungs with one side: refused, naming --lung.
        let both: Vec<DVec3> = right.iter().chain(&left).copied().collect();
        let e = split_lungs(&both, Some(Side::Left)).unwrap_err();
        assert!(
            matches!(
                e,
                MotionFitError::TwoLungsForOneSide { right: r, left: l, .. }
                    if r == right.len() && l == left.len()
            ),
            "{e}"
        );
        assert!(e.to_string().contains("--lung left"), "{e}");
        // Without a side both lungs are still split at the gap.
        assert_eq!(split_lungs(&both, None).unwrap().len(), 2);
    }

    #[test]
    fn the_lateral_motion_tells_the_side() {
        for side in [Side::Left, Side::Right] {
            let a = lung_points(side, 400);
            let b = move_points(&a, side, &TRUTH, 1.0);
            let d: Vec<DVec3> = a.iter().zip(&b).map(|(p, q)| *q - *p).collect();
            let (seen, why) = side_from_motion(&a, &d).unwrap();
            assert_eq!(seen, side, "{why}");
            // The phases reversed (inhale to exhale): still the same lung.
            let back: Vec<DVec3> = d.iter().map(|v| -*v).collect();
            assert_eq!(side_from_motion(&b, &back).unwrap().0, side);
        }
        // No lateral motion: no claim.
        let a = lung_points(Side::Left, 400);
        let d: Vec<DVec3> = a.iter().map(|_| DVec3::new(0.0, 0.0, -5.0)).collect();
        assert_eq!(side_from_motion(&a, &d), None);
    }

    #[test]
    fn known_constants_are_recovered_exactly_on_both_lungs() {
        let right = lung_points(Side::Right, 800);
        let left = lung_points(Side::Left, 800);
        let a: Vec<DVec3> = right.iter().chain(&left).copied().collect();
        let mut b = move_points(&right, Side::Right, &TRUTH, 1.0);
        b.extend(move_points(&left, Side::Left, &TRUTH, 1.0));
        let mut c = move_points(&right, Side::Right, &TRUTH, 2.5);
        c.extend(move_points(&left, Side::Left, &TRUTH, 2.5));
        let f = fit(&a, &b, &[("C".into(), c)], None).unwrap();
        assert_eq!(f.lungs.len(), 2);
        for l in &f.lungs {
            for k in 0..6 {
                assert!(
                    (l.constants[k] - TRUTH[k]).abs() < 1e-6,
                    "{:?} c{}: {}",
                    l.lung,
                    k + 1,
                    l.constants[k]
                );
            }
            assert!(l.residuals.max_error_mm < 1e-6);
            assert!((l.also[0].scale - 2.5).abs() < 1e-9);
        }
        assert!(f.residuals.baseline_mean_mm > 1.0);
        assert!(f.also[0].max_error_mm < 1e-5);
    }

    #[test]
    fn noisy_landmarks_give_errors_near_the_noise_and_constants_near_the_truth() {
        let a = lung_points(Side::Left, 4000);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let b: Vec<DVec3> = move_points(&a, Side::Left, &TRUTH, 1.0)
            .into_iter()
            .map(|p| p + noise(&mut seed, 1.0))
            .collect();
        let f = fit(&a, &b, &[], Some(Side::Left)).unwrap();
        let l = &f.lungs[0];
        eprintln!(
            "1 mm noise per axis, {} points: mean {:.2} mm, max {:.2} mm, baseline {:.2} mm, c = {:?}",
            l.points, l.residuals.mean_error_mm, l.residuals.max_error_mm, l.residuals.baseline_mean_mm, &l.constants[..6]
        );
        // 1 mm per axis noise → mean |e| ≈ 1.6 mm (chi with 3 dof); the fit must not do worse.
        assert!(l.residuals.mean_error_mm < 1.8, "{:?}", l.residuals);
        assert!(l.residuals.baseline_mean_mm > 4.0);
        for k in [0, 2, 4] {
            assert!(
                (l.constants[k] - TRUTH[k]).abs() < 0.1 * TRUTH[k] + 0.3,
                "c{}: {}",
                k + 1,
                l.constants[k]
            );
        }
        assert!(
            (l.constants[5] - TRUTH[5]).abs() < 0.2,
            "c6 {}",
            l.constants[5]
        );
    }

    #[test]
    fn reversed_motion_gives_negative_factors() {
        let a = lung_points(Side::Right, 500);
        let mut t = TRUTH;
        t[2] = -4.0;
        let b = move_points(&a, Side::Right, &t, 1.0);
        let f = fit(&a, &b, &[], Some(Side::Right)).unwrap();
        assert!((f.lungs[0].constants[2] + 4.0).abs() < 1e-6);
    }

    #[test]
    fn one_lung_without_a_side_and_mismatched_sets_are_refused() {
        // A lung's surface sampled densely enough that no X gap of MIN_GAP_MM lies inside it: at
        // 218 vertices (about 17 mm apart) the anatomical lung's thin anterior border, jutting
        // medially, leaves a gap of more than 10 mm between its few medial vertices and the rest —
        // the sparse-landmark case `split_lungs` documents, which needs `--lung`.
        let a = lung_points(Side::Left, 2000);
        assert!(matches!(
            fit(&a, &a, &[], None),
            Err(MotionFitError::SideNeeded { .. })
        ));
        assert!(matches!(
            fit(&a, &a[..10], &[], Some(Side::Left)),
            Err(MotionFitError::Count { got: 10, .. })
        ));
        let mut bad = a.clone();
        bad[3].y = f64::NAN;
        assert!(matches!(
            fit(&a, &bad, &[], Some(Side::Left)),
            Err(MotionFitError::NonFinite { index: 3, .. })
        ));
        let flat: Vec<DVec3> = (0..20)
            .map(|i| DVec3::new(i as f64, 0.0, (i * i) as f64))
            .collect();
        assert!(matches!(
            fit(&flat, &flat, &[], Some(Side::Left)),
            Err(MotionFitError::Flat { axis: "Y", .. })
        ));
        assert!(matches!(
            fit(&a[..5], &a[..5], &[], Some(Side::Left)),
            Err(MotionFitError::TooFew { .. })
        ));
    }

    #[test]
    fn no_motion_fits_zero_factors() {
        let a = lung_points(Side::Left, 300);
        let f = fit(&a, &a, &[], Some(Side::Left)).unwrap();
        assert_eq!(f.residuals.max_error_mm, 0.0);
        assert_eq!(f.residuals.baseline_mean_mm, 0.0);
        for k in [0, 2, 4] {
            assert_eq!(f.lungs[0].constants[k], 0.0);
        }
    }
}
