//! # motion_models: direction models fitted to landmarks, compared on held-out points
//!
//! The seed's separable power law (eq. 6.14–6.16) is one model of how a lung's points move between
//! two breathing phases; on public 4DCT landmarks it leaves ≈ 4 mm. This module fits it and two
//! smoother fields per lung — a ridge-regularised polynomial in box coordinates and an anisotropic
//! thin-plate spline with an affine tail (`lung_model::deform::field`) — chooses each field's
//! complexity by *inner* cross-validation, and reports every model's in-sample and k-fold
//! cross-validated error beside the no-motion baseline, so users compare models on points the fit
//! never saw.
//!
//! The recipe and its numbers come from a prototype on the DIR-Lab 4DCT set (10 cases × 300 landmark
//! pairs, end-exhale → end-inhale): power law 4.01 mm CV mean, polynomial 1.71, thin-plate spline with
//! the Z stretch chosen by CV 1.49 (no motion: 8.46). Everything is deterministic: folds come from
//! SplitMix64 + Fisher–Yates with a stated seed, grids are searched in a fixed order and the first
//! strict minimum wins.
//!
//! Decisions: the thin-plate kernel is `φ = −‖S(a − b)‖` (the minus sign makes `+λI` a smoothing
//! term: `−r` is conditionally positive definite of order 1); the two lungs share one configuration,
//! chosen on their pooled held-out error; held-out points are assigned to a lung by the training
//! split's X threshold; every box (normalisation) comes from the training points only.

use glam::DVec3;
use nalgebra::DMatrix;
use serde::Serialize;

use lung_model::deform::field::{box_coords, monomial_values, monomials, seed_coords, Field};
use lung_model::mesh::Side;

use crate::motion_fit::{fit_lung, split_lungs, MotionFitError};

/// SplitMix64: the seeded generator of the fold assignment.
pub fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Fold of each of `n` points for `k`-fold cross-validation: a seeded Fisher–Yates permutation,
/// then `fold[perm[p]] = p % k` (folds differ in size by at most one).
pub fn folds(n: usize, k: usize, seed: u64) -> Vec<usize> {
    let mut state = seed;
    let mut perm: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        let j = (splitmix64(&mut state) % (i as u64 + 1)) as usize;
        perm.swap(i, j);
    }
    let mut fold = vec![0; n];
    for (p, &i) in perm.iter().enumerate() {
        fold[i] = p % k.max(1);
    }
    fold
}

/// A direction model family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// The seed's power law (eq. 6.14–6.16), no hyper-parameters.
    Power,
    /// An affine field (degree-1 polynomial, no smoothing): the simplest smooth baseline.
    Affine,
    /// Polynomial of degree 1..=5 with a ridge term, both chosen by inner CV.
    Poly,
    /// Anisotropic thin-plate spline, Z stretch and smoothing chosen by inner CV ("rbf").
    #[serde(rename = "rbf")]
    Tps,
}

impl ModelKind {
    /// Every kind, in report order.
    pub const ALL: [ModelKind; 4] = [
        ModelKind::Power,
        ModelKind::Affine,
        ModelKind::Poly,
        ModelKind::Tps,
    ];

    /// Its name on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Power => "power",
            ModelKind::Affine => "affine",
            ModelKind::Poly => "poly",
            ModelKind::Tps => "rbf",
        }
    }

    /// The configurations searched, smoothest first.
    pub fn grid(self) -> Vec<Config> {
        match self {
            ModelKind::Power => vec![Config::Power],
            ModelKind::Affine => vec![Config::Poly {
                degree: 1,
                lambda: 0.0,
            }],
            ModelKind::Poly => (1..=5u8)
                .flat_map(|degree| {
                    (0..19).map(move |m| Config::Poly {
                        degree,
                        lambda: 10f64.powf(1.0 - 0.5 * m as f64),
                    })
                })
                .collect(),
            ModelKind::Tps => [1.0, 2.0]
                .into_iter()
                .flat_map(|s_z| {
                    (0..15).map(move |m| Config::Tps {
                        s_z,
                        lambda: 10f64.powf(3.0 - 0.5 * m as f64),
                    })
                })
                .collect(),
        }
    }
}

/// One configuration of a family.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Config {
    /// The power law.
    Power,
    /// A polynomial of `degree` with ridge `lambda` (the constant term is not penalised).
    Poly {
        /// Total degree.
        degree: u8,
        /// Ridge weight (times the number of points).
        lambda: f64,
    },
    /// A thin-plate spline with Z stretch `s_z` and smoothing `lambda` (mm).
    Tps {
        /// Stretch of Z distances.
        s_z: f64,
        /// Smoothing.
        lambda: f64,
    },
}

fn bbox(points: &[DVec3]) -> (DVec3, DVec3) {
    points.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    )
}

/// Fit one lung's field with a fixed configuration: `p` start positions, `d` displacements (mm).
pub fn fit_field(
    config: Config,
    side: Side,
    p: &[DVec3],
    d: &[DVec3],
) -> Result<Field, MotionFitError> {
    let (lo, hi) = bbox(p);
    if !((hi - lo).min_element() > 1e-9) {
        return Err(MotionFitError::Flat {
            lung: side.name(),
            axis: "X, Y or Z",
        });
    }
    match config {
        Config::Power => {
            let targets: Vec<DVec3> = p.iter().zip(d).map(|(a, x)| *a + *x).collect();
            let f = fit_lung(side, p, &targets, &[])?;
            let c = f.constants;
            Ok(Field::Power {
                side,
                lo: lo.into(),
                hi: hi.into(),
                c: [c[0], c[1], c[2], c[3], c[4], c[5]],
            })
        }
        Config::Poly { degree, lambda } => {
            let exps = monomials(degree);
            let (g, b) = poly_normal_equations(p, d, lo, hi, &exps);
            let coeffs = ridge_solve(&g, &b, p.len(), lambda)
                .ok_or(MotionFitError::Singular { lung: side.name() })?;
            Ok(Field::Poly {
                lo: lo.into(),
                hi: hi.into(),
                degree,
                coeffs,
            })
        }
        Config::Tps { s_z, lambda } => {
            let (w, a) = tps_solve(p, d, lo, hi, s_z, lambda)
                .ok_or(MotionFitError::Singular { lung: side.name() })?;
            Ok(Field::Tps {
                lo: lo.into(),
                hi: hi.into(),
                s_z,
                centres: p.iter().map(|x| x.to_array()).collect(),
                weights: w,
                affine: a,
            })
        }
    }
}

/// `ΦᵀΦ` and `ΦᵀΔ` of the monomials `exps` at box coordinates.
fn poly_normal_equations(
    p: &[DVec3],
    d: &[DVec3],
    lo: DVec3,
    hi: DVec3,
    exps: &[[u8; 3]],
) -> (DMatrix<f64>, DMatrix<f64>) {
    let m = exps.len();
    let mut g = DMatrix::<f64>::zeros(m, m);
    let mut b = DMatrix::<f64>::zeros(m, 3);
    let mut phi = Vec::with_capacity(m);
    for (x, dx) in p.iter().zip(d) {
        monomial_values(box_coords(*x, lo, hi), exps, &mut phi);
        for r in 0..m {
            for c in 0..m {
                g[(r, c)] += phi[r] * phi[c];
            }
            for k in 0..3 {
                b[(r, k)] += phi[r] * dx[k];
            }
        }
    }
    (g, b)
}

/// `(G + λ·n·D) C = B` with `D = diag(0, 1, …, 1)` (constant unpenalised), by Cholesky; `None` when
/// the system is singular (too few points for the degree without smoothing).
fn ridge_solve(g: &DMatrix<f64>, b: &DMatrix<f64>, n: usize, lambda: f64) -> Option<Vec<[f64; 3]>> {
    let m = g.nrows();
    let mut a = g.clone();
    for i in 1..m {
        a[(i, i)] += lambda * n as f64;
    }
    let sol = a.cholesky()?.solve(b);
    let out: Vec<[f64; 3]> = (0..m)
        .map(|r| [sol[(r, 0)], sol[(r, 1)], sol[(r, 2)]])
        .collect();
    out.iter().flatten().all(|v| v.is_finite()).then_some(out)
}

/// Solve the spline's saddle system `[K + λI, T; Tᵀ, 0][W; A] = [Δ; 0]` by LU.
#[allow(clippy::type_complexity)]
fn tps_solve(
    p: &[DVec3],
    d: &[DVec3],
    lo: DVec3,
    hi: DVec3,
    s_z: f64,
    lambda: f64,
) -> Option<(Vec<[f64; 3]>, [[f64; 3]; 4])> {
    let n = p.len();
    let s = DVec3::new(1.0, 1.0, s_z);
    let mut a = DMatrix::<f64>::zeros(n + 4, n + 4);
    let mut rhs = DMatrix::<f64>::zeros(n + 4, 3);
    for i in 0..n {
        for j in 0..n {
            a[(i, j)] = -((p[i] - p[j]) * s).length();
        }
        a[(i, i)] += lambda;
        let u = box_coords(p[i], lo, hi);
        let t = [1.0, u.x, u.y, u.z];
        for (k, v) in t.iter().enumerate() {
            a[(i, n + k)] = *v;
            a[(n + k, i)] = *v;
        }
        for k in 0..3 {
            rhs[(i, k)] = d[i][k];
        }
    }
    let sol = a.lu().solve(&rhs)?;
    if !sol.iter().all(|v| v.is_finite()) {
        return None;
    }
    let w = (0..n)
        .map(|i| [sol[(i, 0)], sol[(i, 1)], sol[(i, 2)]])
        .collect();
    let t = |k: usize| [sol[(n + k, 0)], sol[(n + k, 1)], sol[(n + k, 2)]];
    Some((w, [t(0), t(1), t(2), t(3)]))
}

/// One lung's training data.
#[derive(Debug, Clone)]
pub struct LungData {
    /// Which lung.
    pub side: Side,
    /// Start positions, mm.
    pub start: Vec<DVec3>,
    /// Displacements to the fitted phase, mm.
    pub delta: Vec<DVec3>,
}

/// Summed held-out 3D errors of every configuration of `grid` on one training/held-out split.
/// Polynomials share one Gram matrix per split (lower degrees are its leading blocks) and splines one
/// kernel matrix per stretch, so a whole grid costs little more than one fit per λ.
#[allow(clippy::too_many_arguments)]
fn held_out_errors(
    kind: ModelKind,
    grid: &[Config],
    side: Side,
    tp: &[DVec3],
    td: &[DVec3],
    hp: &[DVec3],
    hd: &[DVec3],
    sum: &mut [f64],
) {
    let (lo, hi) = bbox(tp);
    match kind {
        ModelKind::Poly if (hi - lo).min_element() > 1e-9 => {
            poly_held_out(grid, tp, td, hp, hd, (lo, hi), sum)
        }
        ModelKind::Tps if (hi - lo).min_element() > 1e-9 && tp.len() > 8 => {
            tps_held_out(grid, tp, td, hp, hd, (lo, hi), sum)
        }
        _ => {
            for (g, cfg) in grid.iter().enumerate() {
                let err = match fit_field(*cfg, side, tp, td) {
                    Ok(field) => hp
                        .iter()
                        .zip(hd)
                        .map(|(x, dx)| (field.displacement(*x) - *dx).length())
                        .sum::<f64>(),
                    Err(_) => f64::INFINITY,
                };
                add_error(sum, g, err);
            }
        }
    }
}

/// Add a fold's held-out error to configuration `g`'s sum (a non-finite one makes it infinite).
fn add_error(sum: &mut [f64], g: usize, err: f64) {
    sum[g] += if err.is_finite() { err } else { f64::INFINITY };
}

/// [`held_out_errors`] for the polynomial grid: one Gram matrix of degree 5 per split, each degree
/// its leading block.
fn poly_held_out(
    grid: &[Config],
    tp: &[DVec3],
    td: &[DVec3],
    hp: &[DVec3],
    hd: &[DVec3],
    (lo, hi): (DVec3, DVec3),
    sum: &mut [f64],
) {
    let exps = monomials(5);
    let (g5, b5) = poly_normal_equations(tp, td, lo, hi, &exps);
    let mut phi = Vec::new();
    let test: Vec<Vec<f64>> = hp
        .iter()
        .map(|x| {
            monomial_values(box_coords(*x, lo, hi), &exps, &mut phi);
            phi.clone()
        })
        .collect();
    for (g, cfg) in grid.iter().enumerate() {
        let Config::Poly { degree, lambda } = *cfg else {
            continue;
        };
        let m = monomials(degree).len();
        let sub = g5.view((0, 0), (m, m)).into_owned();
        let rhs = b5.view((0, 0), (m, 3)).into_owned();
        let err = match ridge_solve(&sub, &rhs, tp.len(), lambda) {
            Some(c) => test
                .iter()
                .zip(hd)
                .map(|(v, d)| {
                    let pred: DVec3 = (0..m).map(|r| DVec3::from(c[r]) * v[r]).sum();
                    (pred - *d).length()
                })
                .sum(),
            None => f64::INFINITY,
        };
        add_error(sum, g, err);
    }
}

/// [`held_out_errors`] for the thin-plate spline grid: every smoothing value at once from one
/// eigendecomposition per stretch.
fn tps_held_out(
    grid: &[Config],
    tp: &[DVec3],
    td: &[DVec3],
    hp: &[DVec3],
    hd: &[DVec3],
    (lo, hi): (DVec3, DVec3),
    sum: &mut [f64],
) {
    // All smoothing values at once (as the prototype does): with T = Q1·R and P = I − Q1Q1ᵀ,
    // the weights live in the complement of T's columns, where K is positive definite
    // (−r is conditionally positive definite). One eigendecomposition of P·K·P per stretch,
    // then each λ costs O(n²): W = Σ v_i (v_iᵀΔ)/(e_i + λ) over the complement,
    // A = R⁻¹Q1ᵀ(Δ − (K + λI)W).
    let n = tp.len();
    let mut t = DMatrix::<f64>::zeros(n, 4);
    let mut delta = DMatrix::<f64>::zeros(n, 3);
    for i in 0..n {
        let u = box_coords(tp[i], lo, hi);
        for (k, v) in [1.0, u.x, u.y, u.z].into_iter().enumerate() {
            t[(i, k)] = v;
        }
        for k in 0..3 {
            delta[(i, k)] = td[i][k];
        }
    }
    // Full orthonormal basis: QR of [T | I] puts span(T) in the first four columns of Q and
    // its complement in the rest, so the weights' constraint Tᵀ W = 0 holds by construction.
    let mut ti = DMatrix::<f64>::zeros(n, n + 4);
    ti.view_mut((0, 0), (n, 4)).copy_from(&t);
    ti.view_mut((0, 4), (n, n)).fill_with_identity();
    let q = ti.qr().q();
    let q1 = q.columns(0, 4).into_owned();
    let q2 = q.columns(4, n - 4).into_owned();
    let r = q1.transpose() * &t;
    let Some(r_inv) = r.try_inverse() else {
        for (g, cfg) in grid.iter().enumerate() {
            if matches!(cfg, Config::Tps { .. }) {
                add_error(sum, g, f64::INFINITY);
            }
        }
        return;
    };
    let test_t: Vec<[f64; 4]> = hp
        .iter()
        .map(|x| {
            let u = box_coords(*x, lo, hi);
            [1.0, u.x, u.y, u.z]
        })
        .collect();
    for s_z in [1.0, 2.0] {
        let sc = DVec3::new(1.0, 1.0, s_z);
        let k = DMatrix::<f64>::from_fn(n, n, |i, j| -((tp[i] - tp[j]) * sc).length());
        let kte = DMatrix::<f64>::from_fn(hp.len(), n, |i, j| -((hp[i] - tp[j]) * sc).length());
        let mut sm = q2.transpose() * &k * &q2;
        sm = (&sm + sm.transpose()) * 0.5;
        let eig = nalgebra::SymmetricEigen::new(sm);
        // Weights W = Q2·V·diag(1/(e + λ))·Vᵀ·Q2ᵀ·Δ.
        let basis = &q2 * &eig.eigenvectors;
        let z = basis.transpose() * &delta;
        for (g, cfg) in grid.iter().enumerate() {
            let Config::Tps { s_z: gs, lambda } = *cfg else {
                continue;
            };
            if gs != s_z {
                continue;
            }
            let mut scaled = z.clone();
            let mut ok = true;
            for c in 0..n - 4 {
                let den = eig.eigenvalues[c] + lambda;
                if !(den > 0.0) {
                    ok = false;
                    break;
                }
                for qq in 0..3 {
                    scaled[(c, qq)] /= den;
                }
            }
            if !ok {
                add_error(sum, g, f64::INFINITY);
                continue;
            }
            let w = &basis * scaled;
            let resid = &delta - (&k * &w + &w * lambda);
            let a = &r_inv * (q1.transpose() * resid);
            let pred = &kte * &w;
            let err: f64 = (0..hp.len())
                .map(|i| {
                    let mut d = DVec3::new(pred[(i, 0)], pred[(i, 1)], pred[(i, 2)]);
                    for (qq, tv) in test_t[i].iter().enumerate() {
                        d += DVec3::new(a[(qq, 0)], a[(qq, 1)], a[(qq, 2)]) * *tv;
                    }
                    (d - hd[i]).length()
                })
                .sum();
            add_error(sum, g, err);
        }
    }
}

/// Most landmarks per lung the spline's inner CV uses (see [`select`]).
pub const SELECT_MAX: usize = 200;

/// Choose a configuration of `kind` by `k`-fold inner CV over `lungs` pooled (held-out mean 3D error;
/// first strict minimum in grid order, the grid running smoothest first). Returns the configuration
/// and its inner-CV mean error (NaN for a family without choices).
pub fn select(kind: ModelKind, lungs: &[LungData], k: usize, seed: u64) -> (Config, f64) {
    let grid = kind.grid();
    if grid.len() == 1 {
        return (grid[0], f64::NAN);
    }
    let mut sum = vec![0.0f64; grid.len()];
    let mut count = 0usize;
    for full in lungs {
        // The spline's choice is made on at most SELECT_MAX landmarks per lung (a seeded subset):
        // its cost grows with the cube of the points, and 150–200 landmarks per lung pin the
        // smoothing as well as more do. The chosen configuration is then fitted to all of them.
        let subset;
        let lung = if kind == ModelKind::Tps && full.start.len() > SELECT_MAX {
            let mut state = seed ^ 0x5eed;
            let mut idx: Vec<usize> = (0..full.start.len()).collect();
            for i in (1..idx.len()).rev() {
                let j = (splitmix64(&mut state) % (i as u64 + 1)) as usize;
                idx.swap(i, j);
            }
            idx.truncate(SELECT_MAX);
            idx.sort_unstable();
            subset = LungData {
                side: full.side,
                start: idx.iter().map(|&i| full.start[i]).collect(),
                delta: idx.iter().map(|&i| full.delta[i]).collect(),
            };
            &subset
        } else {
            full
        };
        let n = lung.start.len();
        let fold = folds(n, k, seed);
        for f in 0..k {
            let (mut tp, mut td, mut hp, mut hd) = (vec![], vec![], vec![], vec![]);
            for i in 0..n {
                if fold[i] == f {
                    hp.push(lung.start[i]);
                    hd.push(lung.delta[i]);
                } else {
                    tp.push(lung.start[i]);
                    td.push(lung.delta[i]);
                }
            }
            if hp.is_empty() || tp.len() < 8 {
                continue;
            }
            count += hp.len();
            held_out_errors(kind, &grid, lung.side, &tp, &td, &hp, &hd, &mut sum);
        }
    }
    let mut best = (0usize, f64::INFINITY);
    for (g, &s) in sum.iter().enumerate() {
        if s < best.1 {
            best = (g, s);
        }
    }
    (grid[best.0], best.1 / count.max(1) as f64)
}

/// A model of a whole point set: the lung split and one field per lung.
#[derive(Debug, Clone, PartialEq)]
pub struct SetModel {
    /// X threshold between the lungs (`x < threshold` → right), when both are present.
    pub threshold_x: Option<f64>,
    /// Per lung, the field.
    pub lungs: Vec<(Side, Field)>,
    /// The configuration used for both lungs.
    pub config: Config,
}

impl SetModel {
    /// The lung a start position belongs to.
    pub fn side_of(&self, p: DVec3) -> Side {
        match self.threshold_x {
            Some(t) if p.x < t => Side::Right,
            Some(_) => Side::Left,
            None => self.lungs[0].0,
        }
    }

    /// Predicted displacement at start position `p`.
    pub fn displacement(&self, p: DVec3) -> DVec3 {
        let side = self.side_of(p);
        self.lungs
            .iter()
            .find(|(s, _)| *s == side)
            .map(|(_, f)| f.displacement(p))
            .unwrap_or(DVec3::ZERO)
    }
}

/// Split a set into lungs (at the mid-sagittal gap, else `side`) and say where the split is.
pub fn split(
    start: &[DVec3],
    delta: &[DVec3],
    side: Option<Side>,
) -> Result<(Option<f64>, Vec<LungData>, Vec<Vec<usize>>), MotionFitError> {
    let parts = split_lungs(start, side)?;
    let threshold = if parts.len() == 2 {
        let max_r = parts[0]
            .1
            .iter()
            .map(|&i| start[i].x)
            .fold(f64::MIN, f64::max);
        let min_l = parts[1]
            .1
            .iter()
            .map(|&i| start[i].x)
            .fold(f64::MAX, f64::min);
        Some(0.5 * (max_r + min_l))
    } else {
        None
    };
    let lungs = parts
        .iter()
        .map(|(s, idx)| LungData {
            side: *s,
            start: idx.iter().map(|&i| start[i]).collect(),
            delta: idx.iter().map(|&i| delta[i]).collect(),
        })
        .collect();
    Ok((threshold, lungs, parts.into_iter().map(|p| p.1).collect()))
}

/// Fit `kind` to a whole set: split, choose the configuration by inner CV (seed `seed`), fit each lung.
pub fn fit_set(
    kind: ModelKind,
    start: &[DVec3],
    delta: &[DVec3],
    side: Option<Side>,
    k: usize,
    seed: u64,
) -> Result<SetModel, MotionFitError> {
    let (threshold_x, lungs, _) = split(start, delta, side)?;
    for l in &lungs {
        if l.start.len() < 8 {
            return Err(MotionFitError::TooFew {
                lung: l.side.name(),
                points: l.start.len(),
            });
        }
    }
    let (config, _) = select(kind, &lungs, k, seed);
    let fields = lungs
        .iter()
        .map(|l| Ok((l.side, fit_field(config, l.side, &l.start, &l.delta)?)))
        .collect::<Result<Vec<_>, MotionFitError>>()?;
    Ok(SetModel {
        threshold_x,
        lungs: fields,
        config,
    })
}

/// Errors of a set of predictions, mm.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Errors {
    /// Mean |predicted − measured|.
    pub mean_mm: f64,
    /// Largest.
    pub max_mm: f64,
    /// Root mean square.
    pub rms_mm: f64,
    /// Points.
    pub points: usize,
}

impl Errors {
    /// From per-point errors.
    pub fn of(e: &[f64]) -> Self {
        let n = e.len().max(1) as f64;
        Self {
            mean_mm: e.iter().sum::<f64>() / n,
            max_mm: e.iter().copied().fold(0.0, f64::max),
            rms_mm: (e.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
            points: e.len(),
        }
    }
}

/// What one model did on a set: in-sample and cross-validated, per lung and over all points.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModelReport {
    /// The family.
    pub model: ModelKind,
    /// The configuration the full fit chose.
    pub config: Config,
    /// In-sample errors of the full fit.
    pub in_sample: Errors,
    /// Held-out errors of the outer k-fold CV (every point predicted by a fit that never saw it).
    pub cv: Errors,
    /// Per lung: (side, in-sample, CV).
    pub lungs: Vec<LungReport>,
    /// Numbers stored by the full fit (both lungs).
    pub parameters: usize,
    /// Wall time of the CV and the full fit, s.
    pub seconds: f64,
    /// The full fit.
    #[serde(skip)]
    pub fit: SetModel,
    /// Held-out error of each point (input order).
    #[serde(skip)]
    pub cv_point_errors: Vec<f64>,
}

/// One lung's figures in a [`ModelReport`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LungReport {
    /// Which lung.
    pub lung: Side,
    /// In-sample errors.
    pub in_sample: Errors,
    /// Cross-validated errors.
    pub cv: Errors,
}

/// Fit `kind` to `start → start + delta` and cross-validate it: outer `k` folds over all points
/// (seed `seed`), inner CV seed `seed + 1 + fold` for each outer fold and `seed + 1000` for the full
/// fit. Deterministic.
pub fn evaluate(
    kind: ModelKind,
    start: &[DVec3],
    delta: &[DVec3],
    side: Option<Side>,
    k: usize,
    seed: u64,
) -> Result<ModelReport, MotionFitError> {
    let t0 = std::time::Instant::now();
    let n = start.len();
    let fold = folds(n, k, seed);
    let mut cv = vec![f64::NAN; n];
    for f in 0..k {
        let train: Vec<usize> = (0..n).filter(|&i| fold[i] != f).collect();
        let test: Vec<usize> = (0..n).filter(|&i| fold[i] == f).collect();
        if test.is_empty() {
            continue;
        }
        let pick = |set: &[DVec3], idx: &[usize]| idx.iter().map(|&i| set[i]).collect::<Vec<_>>();
        let model = fit_set(
            kind,
            &pick(start, &train),
            &pick(delta, &train),
            side,
            k,
            seed + 1 + f as u64,
        )?;
        for &i in &test {
            cv[i] = (model.displacement(start[i]) - delta[i]).length();
        }
    }
    let full = fit_set(kind, start, delta, side, k, seed + 1000)?;
    let ins: Vec<f64> = (0..n)
        .map(|i| (full.displacement(start[i]) - delta[i]).length())
        .collect();
    let lungs = full
        .lungs
        .iter()
        .map(|(s, _)| {
            let idx: Vec<usize> = (0..n).filter(|&i| full.side_of(start[i]) == *s).collect();
            LungReport {
                lung: *s,
                in_sample: Errors::of(&idx.iter().map(|&i| ins[i]).collect::<Vec<_>>()),
                cv: Errors::of(&idx.iter().map(|&i| cv[i]).collect::<Vec<_>>()),
            }
        })
        .collect();
    Ok(ModelReport {
        model: kind,
        config: full.config,
        in_sample: Errors::of(&ins),
        cv: Errors::of(&cv),
        lungs,
        parameters: full.lungs.iter().map(|(_, f)| f.parameters()).sum(),
        seconds: t0.elapsed().as_secs_f64(),
        fit: full,
        cv_point_errors: cv,
    })
}

/// Spearman rank correlation of `a` and `b` (average ranks for ties).
pub fn spearman(a: &[f64], b: &[f64]) -> f64 {
    fn ranks(v: &[f64]) -> Vec<f64> {
        let mut idx: Vec<usize> = (0..v.len()).collect();
        idx.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
        let mut r = vec![0.0; v.len()];
        let mut i = 0;
        while i < idx.len() {
            let mut j = i;
            while j + 1 < idx.len() && v[idx[j + 1]] == v[idx[i]] {
                j += 1;
            }
            for k in i..=j {
                r[idx[k]] = 0.5 * (i + j) as f64;
            }
            i = j + 1;
        }
        r
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len() as f64;
    let (ma, mb) = (ra.iter().sum::<f64>() / n, rb.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
}

/// What the motion says about the stated frame and phase order.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameCheck {
    /// Spearman ρ between Z (superior) and displacement size, averaged over the lungs: breathing moves
    /// the base most, so it is negative in a correct frame (−0.48 or lower on every DIR-Lab case).
    pub rho_z: f64,
    /// Mean Z displacement of each lung's basal half, mm: negative when the start phase is
    /// end-exhale and the target inhale (the diaphragm descends).
    pub basal_dz_mm: f64,
    /// A warning for the user, when the data disagree with the stated frame or phase order.
    pub warning: Option<String>,
}

/// Check the stated frame and phase order against what breathing does.
pub fn check_frame(lungs: &[LungData]) -> FrameCheck {
    let mut rho = 0.0;
    let mut dz = 0.0;
    for l in lungs {
        let z: Vec<f64> = l.start.iter().map(|p| p.z).collect();
        let m: Vec<f64> = l.delta.iter().map(|d| d.length()).collect();
        rho += spearman(&z, &m);
        let (lo, hi) = bbox(&l.start);
        let mid = 0.5 * (lo.z + hi.z);
        let basal: Vec<f64> = l
            .start
            .iter()
            .zip(&l.delta)
            .filter(|(p, _)| p.z < mid)
            .map(|(_, d)| d.z)
            .collect();
        dz += basal.iter().sum::<f64>() / basal.len().max(1) as f64;
    }
    let n = lungs.len().max(1) as f64;
    let (rho_z, basal_dz_mm) = (rho / n, dz / n);
    let warning = if rho_z > 0.0 {
        Some(format!(
            "the motion grows towards the apex (Spearman rho = {rho_z:+.2} between Z and displacement size): \
             breathing moves the base most, so the Z axis (superior) of the stated frame looks reversed — \
             check --frame / --voxel-axes (DIR-Lab files count slices from the head down: --format dirlab)"
        ))
    } else if basal_dz_mm > 0.0 {
        Some(format!(
            "the lung bases move up by {basal_dz_mm:.1} mm on average: the start phase looks like end-inhale \
             and the target like end-exhale — the reference phase (--from) should be end-exhale (FRC)"
        ))
    } else {
        None
    };
    FrameCheck {
        rho_z,
        basal_dz_mm,
        warning,
    }
}

/// A further phase predicted by one scale of the fitted field (linearity in volume, seed §6.1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PhaseReport {
    /// The scale fitted on all points: displacement at this phase / at the fitted phase.
    pub scale: f64,
    /// In-sample errors of the scaled field.
    pub in_sample: Errors,
    /// Held-out errors: field and scale fitted on the other folds.
    pub cv: Errors,
    /// No-motion baseline at this phase.
    pub baseline_mm: f64,
}

fn best_scale(model: &SetModel, start: &[DVec3], delta: &[DVec3]) -> f64 {
    let (num, den) = start
        .iter()
        .zip(delta)
        .fold((0.0, 0.0), |(nu, de), (p, d)| {
            let m = model.displacement(*p);
            (nu + d.dot(m), de + m.dot(m))
        });
    if den > 0.0 {
        num / den
    } else {
        0.0
    }
}

/// Predict a further phase (`delta_c`) from the field of `kind` fitted on `delta` with one scale.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_phase(
    kind: ModelKind,
    full: &SetModel,
    start: &[DVec3],
    delta: &[DVec3],
    delta_c: &[DVec3],
    side: Option<Side>,
    k: usize,
    seed: u64,
) -> Result<PhaseReport, MotionFitError> {
    let n = start.len();
    let fold = folds(n, k, seed);
    let mut cv = vec![f64::NAN; n];
    for f in 0..k {
        let train: Vec<usize> = (0..n).filter(|&i| fold[i] != f).collect();
        let pick = |set: &[DVec3]| train.iter().map(|&i| set[i]).collect::<Vec<_>>();
        let (ts, td, tc) = (pick(start), pick(delta), pick(delta_c));
        let model = fit_set(kind, &ts, &td, side, k, seed + 1 + f as u64)?;
        let s = best_scale(&model, &ts, &tc);
        for i in (0..n).filter(|&i| fold[i] == f) {
            cv[i] = (model.displacement(start[i]) * s - delta_c[i]).length();
        }
    }
    let scale = best_scale(full, start, delta_c);
    let ins: Vec<f64> = (0..n)
        .map(|i| (full.displacement(start[i]) * scale - delta_c[i]).length())
        .collect();
    Ok(PhaseReport {
        scale,
        in_sample: Errors::of(&ins),
        cv: Errors::of(&cv),
        baseline_mm: delta_c.iter().map(|d| d.length()).sum::<f64>() / n.max(1) as f64,
    })
}

/// The seed's normalised coordinates of a power field's lung (re-exported for callers that plot).
pub fn seed_position(p: DVec3, lo: DVec3, hi: DVec3, side: Side) -> DVec3 {
    seed_coords(p, lo, hi, side)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folds_match_the_reference_generator() {
        let mut s = 10u64;
        assert_eq!(splitmix64(&mut s), 0x0887_12be_8a58_2fca);
        assert_eq!(splitmix64(&mut s), 0xbbff_7c59_6e26_ce46);
        assert_eq!(splitmix64(&mut s), 0x2187_6e7a_2aec_4a3d);
        assert_eq!(folds(10, 5, 1), vec![1, 3, 1, 0, 0, 4, 2, 3, 2, 4]);
        let f = folds(300, 5, 10);
        assert_eq!(
            f[..30],
            [
                4, 1, 4, 0, 2, 2, 4, 0, 1, 2, 3, 1, 0, 1, 3, 2, 2, 2, 1, 1, 3, 2, 4, 3, 3, 4, 1, 1,
                2, 1
            ]
        );
        for k in 0..5 {
            assert_eq!(f.iter().filter(|&&x| x == k).count(), 60);
        }
    }

    /// Two synthetic lungs on a jittered grid moving by a smooth, non-separable field plus noise.
    fn synthetic(noise_mm: f64, seed: u64) -> (Vec<DVec3>, Vec<DVec3>) {
        let mut state = seed;
        let mut unit = || (splitmix64(&mut state) >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        let mut start = Vec::new();
        let mut delta = Vec::new();
        for (x0, side) in [(-110.0, -1.0), (40.0, 1.0)] {
            for _ in 0..150 {
                let p = DVec3::new(
                    x0 + 70.0 * (unit() + 0.5),
                    -60.0 + 120.0 * (unit() + 0.5),
                    -120.0 + 200.0 * (unit() + 0.5),
                );
                // Base (low Z) moves most, down; posterior moves more; a little lateral swing.
                let t = (p.z + 120.0) / 200.0;
                let d = DVec3::new(
                    side * 2.0 * (1.0 - t) * (1.0 + 0.3 * (p.y / 60.0)),
                    1.5 * (1.0 - t) + 0.5 * (p.x / 100.0).sin(),
                    -14.0 * (1.0 - t).powf(1.6) * (1.2 - 0.4 * (p.y / 60.0)),
                );
                start.push(p);
                delta.push(d + DVec3::new(unit(), unit(), unit()) * (2.0 * noise_mm));
            }
        }
        (start, delta)
    }

    #[test]
    fn smooth_fields_beat_the_power_law_on_held_out_points() {
        let (start, delta) = synthetic(0.3, 7);
        let report = |k| evaluate(k, &start, &delta, None, 5, 10).unwrap();
        let power = report(ModelKind::Power);
        let poly = report(ModelKind::Poly);
        let tps = report(ModelKind::Tps);
        let baseline = delta.iter().map(|d| d.length()).sum::<f64>() / delta.len() as f64;
        for r in [&power, &poly, &tps] {
            assert!(r.cv.mean_mm < baseline, "{r:?}");
            assert!(
                r.cv.mean_mm >= r.in_sample.mean_mm * 0.9,
                "held out is not better than in sample"
            );
            assert_eq!(r.lungs.len(), 2);
        }
        assert!(
            tps.cv.mean_mm < 0.8 * power.cv.mean_mm,
            "tps {} power {}",
            tps.cv.mean_mm,
            power.cv.mean_mm
        );
        assert!(poly.cv.mean_mm < power.cv.mean_mm);
        // Deterministic: the same call gives the same numbers to the bit.
        let again = report(ModelKind::Tps);
        assert_eq!(again.cv.mean_mm.to_bits(), tps.cv.mean_mm.to_bits());
        assert_eq!(again.config, tps.config);
    }

    #[test]
    fn a_spline_without_smoothing_interpolates_its_landmarks() {
        let (start, delta) = synthetic(0.0, 3);
        let f = fit_field(
            Config::Tps {
                s_z: 2.0,
                lambda: 0.0,
            },
            Side::Left,
            &start[150..],
            &delta[150..],
        )
        .unwrap();
        for (p, d) in start[150..].iter().zip(&delta[150..]) {
            assert!((f.displacement(*p) - *d).length() < 1e-6);
        }
        assert!(f.validate().is_ok());
    }

    #[test]
    fn an_exact_affine_motion_is_recovered_by_every_smooth_model() {
        let (start, _) = synthetic(0.0, 5);
        let delta: Vec<DVec3> = start
            .iter()
            .map(|p| DVec3::new(0.01 * p.x, -0.02 * p.z + 1.0, 0.05 * p.y - 3.0))
            .collect();
        for kind in [ModelKind::Affine, ModelKind::Poly, ModelKind::Tps] {
            let r = evaluate(kind, &start, &delta, None, 5, 10).unwrap();
            assert!(r.cv.mean_mm < 1e-3, "{kind:?}: {}", r.cv.mean_mm);
        }
    }

    #[test]
    fn a_reversed_z_axis_is_flagged_and_the_right_one_is_not() {
        let (start, delta) = synthetic(0.3, 9);
        let (_, lungs, _) = split(&start, &delta, None).unwrap();
        let ok = check_frame(&lungs);
        assert!(ok.rho_z < -0.3 && ok.warning.is_none(), "{ok:?}");
        let flip = |v: &DVec3| DVec3::new(v.x, v.y, -v.z);
        let fs: Vec<DVec3> = start.iter().map(flip).collect();
        let fd: Vec<DVec3> = delta.iter().map(flip).collect();
        let (_, lungs, _) = split(&fs, &fd, None).unwrap();
        let bad = check_frame(&lungs);
        assert!(bad.rho_z > 0.3, "{bad:?}");
        assert!(bad.warning.unwrap().contains("reversed"));
        // Phases swapped: the base moves up.
        let back: Vec<DVec3> = delta.iter().map(|d| -*d).collect();
        let (_, lungs, _) = split(&start, &back, None).unwrap();
        assert!(check_frame(&lungs).warning.unwrap().contains("end-exhale"));
    }

    #[test]
    fn a_further_phase_is_predicted_by_one_scale() {
        let (start, delta) = synthetic(0.2, 11);
        let half: Vec<DVec3> = delta.iter().map(|d| *d * 0.5).collect();
        let full = fit_set(ModelKind::Tps, &start, &delta, None, 5, 1010).unwrap();
        let r = evaluate_phase(ModelKind::Tps, &full, &start, &delta, &half, None, 5, 10).unwrap();
        assert!((r.scale - 0.5).abs() < 0.02, "{r:?}");
        assert!(r.cv.mean_mm < 0.5 * r.baseline_mm, "{r:?}");
    }

    #[test]
    fn too_few_points_and_flat_sets_are_typed_errors() {
        let p = vec![DVec3::ZERO; 5];
        assert!(matches!(
            fit_set(ModelKind::Tps, &p, &p, Some(Side::Left), 5, 1),
            Err(MotionFitError::TooFew { .. })
        ));
        let flat: Vec<DVec3> = (0..20)
            .map(|i| DVec3::new(i as f64, 0.0, i as f64))
            .collect();
        assert!(fit_field(Config::Power, Side::Left, &flat, &flat).is_err());
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]), -1.0);
    }
}

#[cfg(test)]
mod fast_path {
    use super::*;

    /// The all-λ eigen path of the inner CV must give the same held-out errors as solving each
    /// configuration's saddle system directly.
    #[test]
    fn the_fast_spline_cv_equals_direct_solves() {
        let mut state = 3u64;
        let mut unit = || (splitmix64(&mut state) >> 11) as f64 / (1u64 << 53) as f64;
        let pts: Vec<DVec3> = (0..90)
            .map(|_| DVec3::new(60.0 * unit(), 100.0 * unit(), 180.0 * unit()))
            .collect();
        let d: Vec<DVec3> = pts
            .iter()
            .map(|p| {
                DVec3::new(
                    (p.y / 30.0).sin(),
                    0.01 * p.x,
                    -8.0 * (1.0 - p.z / 180.0).powi(2),
                ) + DVec3::splat(unit() - 0.5)
            })
            .collect();
        let (tp, td, hp, hd) = (&pts[..70], &d[..70], &pts[70..], &d[70..]);
        let grid = ModelKind::Tps.grid();
        let mut fast = vec![0.0; grid.len()];
        held_out_errors(ModelKind::Tps, &grid, Side::Left, tp, td, hp, hd, &mut fast);
        for (g, cfg) in grid.iter().enumerate() {
            let f = fit_field(*cfg, Side::Left, tp, td).unwrap();
            let direct: f64 = hp
                .iter()
                .zip(hd)
                .map(|(x, y)| (f.displacement(*x) - *y).length())
                .sum();
            assert!(
                (fast[g] - direct).abs() < 1e-6 * (1.0 + direct),
                "{cfg:?}: fast {} direct {direct}",
                fast[g]
            );
        }
    }
}
