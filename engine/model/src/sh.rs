//! # sh: real spherical harmonics, quadrature projection and sphere weights (seed ch. 7, eq. 7.2–7.7)
//!
//! Chapter 7 of the seed compresses the Green's-function transfer rows with spherical harmonics:
//! every node is given a direction by projecting it from the lung's centre onto a sphere, the
//! applied force `F` and each node's transfer row `T(·, I)` are expanded in `n²` harmonics, and the
//! per-frame displacement becomes a short dot product (EQUATIONS.md §3.2):
//!
//! ```text
//! F_lm   = Σ_J w_J · F(J) · Y_lm(J)          (force coefficients, eq. 7.3 with quadrature weights)
//! T^I_lm = Σ_J T(J, I) · Y_lm(J)             (transfer coefficients, eq. 7.4, baked offline)
//! D(I)  ≈ α · Σ_{l<n} Σ_m F_lm · T^I_lm      (eq. 7.7)
//! ```
//!
//! This module is the numerical core of that stage, and nothing else: the basis ([`eval_into`],
//! [`Evaluator`]), the basis sampled at a mesh's nodes ([`Basis`]), the projections ([`project`],
//! [`project_sparse`]) and the quadrature weights of scattered node directions, with fold-over
//! detection ([`vertex_sphere_weights`]). Choosing the centre, baking rows and fitting `α` live with
//! the bake. Everything is `f64`; positions arrive as the mesh's `f32` and are widened first.
//!
//! ## What it assumes
//! * Directions are taken from a caller-chosen centre (the seed's §7.4 puts the origin at the lung's
//!   centroid; which centroid is the caller's decision). The radius of the seed's "spherical hull of
//!   large radius" does not matter for a central projection, so none appears here.
//! * The seed assumes the projection is one-to-one ("unique spherical coordinates for all the
//!   nodes", L2969–2973). **Decision (EQUATIONS.md §3.2):** do not assume it — detect and report the
//!   triangles whose projection folds over and the vertices touching them
//!   ([`SphereWeights::foldover_vertices`]); they are where the approximation is weakest.
//! * Band count `n` means `l = 0..n−1`, `n²` coefficients (the seed's "16 coefficients" is `n = 4`;
//!   its own `Σ_{l=0}^{n}` is off by one, see the ch. 7 digest §1.3).
//!
//! ## Decisions, each with its reason
//! * **Real, orthonormal basis.** `∫_{S²} Y_a Y_b dΩ = δ_ab` over the whole sphere (area `4π`), the
//!   "orthonormalised" convention of geodesy/SHTns and of graphics. The seed writes complex
//!   harmonics with conjugates, but its GPU form (16 real numbers per node, 4 vec4 dot products)
//!   is only consistent with a real basis, and eq. 7.6 (`Σ Y_lm Y_l'm'` ≈ δ without a conjugate)
//!   holds only for a real one. With an orthonormal basis the constant `A` of eq. 7.6–7.7 is 1 when
//!   the quadrature is right, so the calibrated `α` measures only band truncation.
//! * **Indexing** `k = l² + l + m`, `m = −l..l`: band `l` occupies `l²..(l+1)²` ([`index`],
//!   [`degree_order`]).
//! * **Real form and phase.** With `Q_l^m(z)` defined below,
//!   `Y_l0 = Q_l^0(z)`, `Y_lm = √2·Q_l^m(z)·Re((x+iy)^m)` and `Y_l,−m = √2·Q_l^m(z)·Im((x+iy)^m)`
//!   for `m > 0` — i.e. `√2·N_lm·P_l^m(cos θ)·cos(mφ)` and `…·sin(mφ)`. **No Condon–Shortley
//!   phase** `(−1)^m`: then `Y_1,−1, Y_10, Y_11 = √(3/4π)·(y, z, x)` and every real harmonic is its
//!   Cartesian polynomial with a positive leading coefficient — the table of Wikipedia's
//!   "Spherical harmonics › Real form" and the convention of real-time graphics (Sloan). The phase
//!   cannot change any result of eq. 7.7: `F_lm` and `T^I_lm` are projected on the same basis, so
//!   a sign flip of one `Y_lm` flips both factors of `F_lm·T^I_lm`. It matters only to anyone who
//!   exchanges coefficients with code built on the other convention (negate the terms of odd `|m|`
//!   to convert).
//! * **Stable recurrences, no poles.** Writing `P̄_l^m = sqrt((2l+1)/(4π)·(l−m)!/(l+m)!)·P_l^m`
//!   (fully normalised, no phase) and `Q_l^m = P̄_l^m / sin^m θ`, the standard three-term
//!   recurrences (Holmes & Featherstone 2002; the form SHTns uses) hold for `Q` unchanged because
//!   they are linear at fixed `m`:
//!   `Q_0^0 = 1/√(4π)`, `Q_m^m = sqrt((2m+1)/(2m))·Q_{m−1}^{m−1}`,
//!   `Q_{m+1}^m = sqrt(2m+3)·z·Q_m^m`,
//!   `Q_l^m = a_lm·(z·Q_{l−1}^m − b_lm·Q_{l−2}^m)` with `a_lm = sqrt((4l²−1)/(l²−m²))`,
//!   `b_lm = sqrt(((l−1)²−m²)/(4(l−1)²−1))`. No factorial is ever formed. The factor
//!   `sin^m θ·(cos mφ, sin mφ) = (Re, Im)(x+iy)^m` comes from the rotation recurrence
//!   `(x+iy)^{m+1} = (x+iy)^m·(x+iy)` — the Chebyshev/rotation recurrence for `cos mφ, sin mφ`
//!   with `sin^m θ` folded in. Nothing divides by `sin θ` and `φ` is never formed, so at the poles
//!   (`x = y = 0`) every `m ≠ 0` term is exactly `0.0` and `Y_l0 = (±1)^l·sqrt((2l+1)/(4π))`;
//!   close to the poles `(x+iy)^m` underflows gracefully to 0 (tests: θ = 1e-300, π − 1e-16).
//!   `Q_l^m` stays below 1e13 for `l < 64`, so the products never overflow (no `∞·0 = NaN`).
//! * **Band limit.** [`MAX_BANDS`] = 64 (`l ≤ 63`), twice what the engine needs. Orthonormality is
//!   measured to `n = 32` (`l = 31`) by exact product quadrature; finiteness, the bound
//!   `|Y_lm| ≤ sqrt((2l+1)/(4π))` and Unsöld's sum are tested to `n = 64`.
//! * **Input directions** need not be unit: they are scaled by their largest component (so neither
//!   1e-310 nor 1e308 over/underflows) and then normalised. **The zero vector, and any direction
//!   with a non-finite component, gives the isotropic answer** — `Y_00 = 1/√(4π)`, every other
//!   term 0 — which is the mean of each `Y_lm` over all directions: a node at the centre "sees" the
//!   sphere uniformly. It is not an error because a single bad node must not stop a bake, but it is
//!   reported: [`Basis::isotropic_nodes`] lists the nodes that got it.
//! * **Quadrature weights, not `sin θ`.** The seed weights eq. 7.3 by `sin θ_J` (L3030): the
//!   Jacobian of a regular θ–φ grid, which ignores how densely scattered nodes cover the sphere,
//!   and then corrects with the constant `A = Σ_J Y²`. Here `w_J` is the node's share of the
//!   sphere's area, so `Σ_J w_J F(J) Y_lm(J) ≈ ∫ F Y_lm dΩ` and `A ≈ 1`. Only the force is
//!   weighted: `Σ_lm F_lm T^I_lm = Σ_K T(K,I)·F_n(K)` where `F_n` is the band-limited force, which
//!   tends to eq. 7.1 as `n` grows — the self-consistent reading of EQUATIONS.md §3.2.
//! * **Vertex weights from the mesh.** Each triangle's vertices, seen from the centre, span a
//!   spherical triangle whose **signed** solid angle comes from the exact Van Oosterom–Strackee
//!   formula `tan(Ω/2) = a·(b×c) / (|a||b||c| + (a·b)|c| + (a·c)|b| + (b·c)|a|)` (evaluated with
//!   `atan2`, so `Ω ∈ (−2π, 2π)` without a branch). A vertex's weight is a third of the signed
//!   solid angles of its incident triangles (the lumped-mass rule on the sphere). Reason for the
//!   sign: for a closed mesh around the centre `Σ Ω = 4π` exactly (it is the winding number), with
//!   or without folds — the sheets of a fold cover their directions `+1 −1 +1` times, so signed
//!   weights still integrate any function of direction consistently and a constant exactly, where
//!   absolute areas would count folded directions three times. [`SphereWeights::covered`]
//!   (`Σ |Ω|`) shows the over-cover.
//! * **Fold-over detection.** A triangle folds over when it is seen from its back: its outward
//!   normal points towards the centre, `a·((b−a)×(c−a)) = a·(b×c) < 0`, which is exactly when its
//!   signed solid angle is negative. Rounding is kept out by a relative tolerance
//!   ([`FOLD_TOLERANCE`]·|a||b||c|): a triangle seen edge-on (within rounding) is not counted. A
//!   triangle that contains the centre (or has a vertex at it) has no defined projection: it is
//!   counted in [`SphereWeights::degenerate_triangles`], given `Ω = 0`, and its vertices are
//!   reported with the fold-overs. Meshes must be wound outwards (as `mesh` checks); an inward-wound
//!   mesh reports every triangle as folded and a total of `−4π`.
//! * **f32 vs f64.** Positions are `f32` (about 7 digits); widening them first and doing every
//!   step in `f64` keeps the basis error at the direction's own error (≈1e-7 relative, so
//!   ≈1e-6 absolute at `l = 15`, measured in the tests) instead of adding rounding of the
//!   recurrences. Store coefficients as `f32` for the GPU only after projection.

use std::f64::consts::PI;

/// Largest number of bands (`l = 0..MAX_BANDS−1`) an [`Evaluator`] accepts.
pub const MAX_BANDS: usize = 64;

/// Relative tolerance on the triple product `a·(b×c)` (scaled by `|a||b||c|`) below which a
/// projected triangle counts as seen edge-on rather than folded over or containing the centre.
pub const FOLD_TOLERANCE: f64 = 64.0 * f64::EPSILON;

/// Coefficient index of degree `l` and order `m` (`−l ≤ m ≤ l`): `k = l² + l + m`.
///
/// # Panics
/// If `|m| > l`.
pub fn index(l: usize, m: isize) -> usize {
    assert!(
        m.unsigned_abs() <= l,
        "spherical harmonic order m = {m} outside −{l}..{l}"
    );
    (l * l + l).wrapping_add_signed(m)
}

/// Degree and order `(l, m)` of coefficient index `k` (the inverse of [`index`]).
pub fn degree_order(k: usize) -> (usize, isize) {
    let mut l = (k as f64).sqrt() as usize;
    // Guard the float square root at perfect squares.
    while l * l > k {
        l -= 1;
    }
    while (l + 1) * (l + 1) <= k {
        l += 1;
    }
    (l, k as isize - (l * l + l) as isize)
}

/// Number of coefficients of `n_bands` bands: `n_bands²`.
pub fn n_coeffs(n_bands: usize) -> usize {
    n_bands * n_bands
}

/// Evaluate every real orthonormal harmonic `Y_lm`, `l < n_bands`, for one direction into
/// `out[0..n_bands²]` (index `k = l² + l + m`).
///
/// `dir` need not be unit length; it is normalised here. The zero vector and directions with a
/// non-finite component give the isotropic answer (`Y_00 = 1/√(4π)`, all else 0; see the module
/// doc). This builds an [`Evaluator`] (a small allocation); evaluate many directions with one
/// [`Evaluator`] or a [`Basis`].
///
/// # Panics
/// If `n_bands > MAX_BANDS` or `out.len() < n_bands²`.
pub fn eval_into(dir: [f64; 3], n_bands: usize, out: &mut [f64]) {
    Evaluator::new(n_bands).eval_into(dir, out);
}

/// Unit direction of `dir`, or `None` for the zero vector and non-finite input.
fn unit(dir: [f64; 3]) -> Option<[f64; 3]> {
    if !dir.iter().all(|c| c.is_finite()) {
        return None;
    }
    let scale = dir[0].abs().max(dir[1].abs()).max(dir[2].abs());
    if !(scale > 0.0) {
        return None;
    }
    let [x, y, z] = dir.map(|c| c / scale);
    let r = (x * x + y * y + z * z).sqrt(); // in [1, √3]
    Some([x / r, y / r, z / r])
}

/// The recurrence constants of `n` bands, computed once: evaluates all `n²` harmonics of a
/// direction with `O(n²)` multiply-adds and no square roots.
#[derive(Debug, Clone)]
pub struct Evaluator {
    n_bands: usize,
    /// `a_lm` at `l² + l + m` (m ≥ 0); for `l = m` the diagonal step `sqrt((2m+1)/(2m))`, for
    /// `l = m + 1` the first step `sqrt(2m+3)`.
    a: Vec<f64>,
    /// `b_lm` at `l² + l + m` (m ≥ 0, `l ≥ m + 2`).
    b: Vec<f64>,
}

impl Evaluator {
    /// Precompute the recurrence constants of `n_bands` bands.
    ///
    /// # Panics
    /// If `n_bands > MAX_BANDS`.
    pub fn new(n_bands: usize) -> Self {
        assert!(
            n_bands <= MAX_BANDS,
            "{n_bands} spherical-harmonic bands requested, at most {MAX_BANDS} supported"
        );
        let n = n_coeffs(n_bands);
        let mut a = vec![0.0; n];
        let mut b = vec![0.0; n];
        for m in 0..n_bands {
            let mf = m as f64;
            let k = m * m + 2 * m;
            a[k] = if m == 0 {
                1.0
            } else {
                ((2.0 * mf + 1.0) / (2.0 * mf)).sqrt()
            };
            if m + 1 < n_bands {
                let l = m + 1;
                a[l * l + l + m] = (2.0 * mf + 3.0).sqrt();
            }
            for l in m + 2..n_bands {
                let lf = l as f64;
                let k = l * l + l + m;
                a[k] = ((4.0 * lf * lf - 1.0) / (lf * lf - mf * mf)).sqrt();
                let l1 = lf - 1.0;
                b[k] = ((l1 * l1 - mf * mf) / (4.0 * l1 * l1 - 1.0)).sqrt();
            }
        }
        Self { n_bands, a, b }
    }

    /// Number of bands.
    pub fn n_bands(&self) -> usize {
        self.n_bands
    }

    /// Number of coefficients, `n_bands²`.
    pub fn n_coeffs(&self) -> usize {
        n_coeffs(self.n_bands)
    }

    /// Evaluate all harmonics of `dir` into `out[0..n_coeffs]` (see [`eval_into`]). Returns `false`
    /// when `dir` had no direction (zero or non-finite) and the isotropic answer was written.
    ///
    /// # Panics
    /// If `out.len() < n_coeffs`.
    pub fn eval_into(&self, dir: [f64; 3], out: &mut [f64]) -> bool {
        let n = self.n_bands;
        let nc = n_coeffs(n);
        assert!(
            out.len() >= nc,
            "output slice holds {} values, {} bands need {nc}",
            out.len(),
            n
        );
        let out = &mut out[..nc];
        if n == 0 {
            return true;
        }
        let y00 = 0.5 / PI.sqrt();
        let Some([x, y, z]) = unit(dir) else {
            out.fill(0.0);
            out[0] = y00;
            return false;
        };
        let sqrt2 = std::f64::consts::SQRT_2;
        // Running Q_m^m and (x + iy)^m.
        let mut qmm = y00;
        let (mut cm, mut sm) = (1.0f64, 0.0f64);
        for m in 0..n {
            if m > 0 {
                qmm *= self.a[m * m + 2 * m];
                let c = cm * x - sm * y;
                sm = cm * y + sm * x;
                cm = c;
            }
            let (rc, rs) = if m == 0 {
                (1.0, 0.0)
            } else {
                (sqrt2 * cm, sqrt2 * sm)
            };
            let mut q2 = 0.0; // Q_{l−2}^m
            let mut q1 = qmm; // Q_{l−1}^m, starting at Q_m^m
            for l in m..n {
                let k = l * l + l;
                let q = if l == m {
                    qmm
                } else if l == m + 1 {
                    self.a[k + m] * z * qmm
                } else {
                    self.a[k + m] * (z * q1 - self.b[k + m] * q2)
                };
                if l > m {
                    q2 = q1;
                    q1 = q;
                }
                if m == 0 {
                    out[k] = q;
                } else {
                    out[k + m] = q * rc;
                    out[k - m] = q * rs;
                }
            }
        }
        true
    }
}

/// The basis sampled at `n_nodes` node directions: `n_nodes × n_bands²` values, row-major (row `j`
/// = every `Y_lm` of node `j`), computed once and reused by every projection.
#[derive(Debug, Clone)]
pub struct Basis {
    n_bands: usize,
    n_nodes: usize,
    values: Vec<f64>,
    isotropic: Vec<u32>,
}

impl Basis {
    /// Sample `n_bands` bands at each of `directions` (need not be unit; see [`eval_into`]).
    ///
    /// # Panics
    /// If `n_bands > MAX_BANDS` or there are more than `u32::MAX` directions.
    pub fn new(directions: &[[f64; 3]], n_bands: usize) -> Self {
        Self::build(directions.len(), n_bands, |j| directions[j])
    }

    /// Sample `n_bands` bands at the directions of `positions` seen from `centre` (positions
    /// widened to `f64` before the centre is subtracted).
    ///
    /// # Panics
    /// As [`Basis::new`].
    pub fn from_positions(centre: [f64; 3], positions: &[[f32; 3]], n_bands: usize) -> Self {
        Self::build(positions.len(), n_bands, |j| {
            let p = positions[j];
            [
                p[0] as f64 - centre[0],
                p[1] as f64 - centre[1],
                p[2] as f64 - centre[2],
            ]
        })
    }

    fn build(n_nodes: usize, n_bands: usize, dir: impl Fn(usize) -> [f64; 3]) -> Self {
        assert!(
            u32::try_from(n_nodes).is_ok(),
            "{n_nodes} nodes do not fit u32 node indices"
        );
        let ev = Evaluator::new(n_bands);
        let nc = ev.n_coeffs();
        let mut values = vec![0.0; n_nodes * nc];
        let mut isotropic = Vec::new();
        if nc > 0 {
            for (j, row) in values.chunks_exact_mut(nc).enumerate() {
                if !ev.eval_into(dir(j), row) {
                    isotropic.push(j as u32);
                }
            }
        }
        Self {
            n_bands,
            n_nodes,
            values,
            isotropic,
        }
    }

    /// Number of bands.
    pub fn n_bands(&self) -> usize {
        self.n_bands
    }

    /// Number of coefficients per node, `n_bands²`.
    pub fn n_coeffs(&self) -> usize {
        n_coeffs(self.n_bands)
    }

    /// Number of nodes.
    pub fn n_nodes(&self) -> usize {
        self.n_nodes
    }

    /// All values, row-major: `values()[j·n_coeffs + k] = Y_k(node j)`.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Every `Y_k` of node `j`.
    ///
    /// # Panics
    /// If `j ≥ n_nodes`.
    pub fn row(&self, j: usize) -> &[f64] {
        let nc = self.n_coeffs();
        &self.values[j * nc..(j + 1) * nc]
    }

    /// Nodes whose direction was the zero vector or non-finite (a node at the centre): they got the
    /// isotropic answer. Ascending.
    pub fn isotropic_nodes(&self) -> &[u32] {
        &self.isotropic
    }

    /// `out[k] += scale · Y_k(node j)` for every `k`.
    ///
    /// # Panics
    /// If `j ≥ n_nodes` or `out.len() != n_coeffs`.
    pub fn accumulate(&self, j: usize, scale: f64, out: &mut [f64]) {
        let row = self.row(j);
        assert_eq!(out.len(), row.len(), "coefficient slice length");
        for (o, y) in out.iter_mut().zip(row) {
            *o += scale * y;
        }
    }

    /// The band-limited function `Σ_k coeffs[k]·Y_k` at node `j`.
    ///
    /// # Panics
    /// If `j ≥ n_nodes` or `coeffs.len() != n_coeffs`.
    pub fn synthesize(&self, coeffs: &[f64], j: usize) -> f64 {
        let row = self.row(j);
        assert_eq!(coeffs.len(), row.len(), "coefficient slice length");
        coeffs.iter().zip(row).map(|(c, y)| c * y).sum()
    }

    /// [`Basis::synthesize`] at every node into `out[0..n_nodes]`.
    ///
    /// # Panics
    /// If `coeffs.len() != n_coeffs` or `out.len() != n_nodes`.
    pub fn synthesize_into(&self, coeffs: &[f64], out: &mut [f64]) {
        assert_eq!(out.len(), self.n_nodes, "value slice length");
        for (j, o) in out.iter_mut().enumerate() {
            *o = self.synthesize(coeffs, j);
        }
    }
}

/// Quadrature projection (eq. 7.3 with area weights): `out[k] = Σ_J weights[J]·values[J]·Y_k(J)`,
/// approximating `∫ F·Y_k dΩ`. `out` is overwritten.
///
/// # Panics
/// If `values` or `weights` does not have one entry per node of `basis`, or `out.len()` is not
/// `basis.n_coeffs()`.
pub fn project(values: &[f64], basis: &Basis, weights: &[f64], out: &mut [f64]) {
    assert_eq!(values.len(), basis.n_nodes(), "one value per node");
    assert_eq!(weights.len(), basis.n_nodes(), "one weight per node");
    assert_eq!(out.len(), basis.n_coeffs(), "coefficient slice length");
    out.fill(0.0);
    for (j, (v, w)) in values.iter().zip(weights).enumerate() {
        let s = v * w;
        if s != 0.0 {
            basis.accumulate(j, s, out);
        }
    }
}

/// Unweighted projection of a sparse node vector (eq. 7.4's `T^I_lm = Σ_J T(J, I)·Y_lm(J)` for a
/// stored transfer column): `out[k] = Σ_i values[i]·Y_k(nodes[i])`. `out` is overwritten. Multiply
/// `values` by weights first for a weighted projection.
///
/// # Panics
/// If `nodes` and `values` differ in length, a node is out of range, or `out.len()` is not
/// `basis.n_coeffs()`.
pub fn project_sparse(basis: &Basis, nodes: &[u32], values: &[f64], out: &mut [f64]) {
    assert_eq!(nodes.len(), values.len(), "one value per listed node");
    assert_eq!(out.len(), basis.n_coeffs(), "coefficient slice length");
    out.fill(0.0);
    for (&j, &v) in nodes.iter().zip(values) {
        basis.accumulate(j as usize, v, out);
    }
}

/// Per-vertex quadrature weights of a mesh projected from a centre onto the unit sphere, and what
/// the projection does wrong ([`vertex_sphere_weights`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SphereWeights {
    /// Per vertex: a third of the signed solid angles of its incident triangles (sr). Vertices in
    /// no triangle get 0. May be negative inside folds.
    pub weights: Vec<f64>,
    /// `Σ weights` = the signed solid angle of the whole mesh: `4π × winding number` for a closed
    /// mesh (`4π` when the centre is inside an outward-wound mesh, 0 when it is outside).
    pub total: f64,
    /// `Σ |Ω|` over the triangles: `4π` when the projection is one-to-one, more where it folds.
    pub covered: f64,
    /// Triangles seen from their back from the centre (signed solid angle < 0, the triple product
    /// below `−FOLD_TOLERANCE·|a||b||c|`): fold-overs.
    pub foldover_triangles: usize,
    /// Triangles containing the centre or with a vertex at it: no projection, given `Ω = 0`.
    pub degenerate_triangles: usize,
    /// Triangles with a vertex index out of range: skipped.
    pub invalid_triangles: usize,
    /// Vertices touching a fold-over or degenerate triangle, ascending, each once.
    pub foldover_vertices: Vec<u32>,
    /// Vertices whose weight is negative (they sit on a fold's reversed sheet).
    pub negative_weights: usize,
}

impl SphereWeights {
    /// Winding number of the mesh around the centre, `round(total / 4π)`.
    pub fn winding(&self) -> i64 {
        (self.total / (4.0 * PI)).round() as i64
    }

    /// The projection is one-to-one onto the whole sphere: no fold-over, degenerate or invalid
    /// triangle, and the signed total is `4π` (within 1e-9 relative).
    pub fn is_one_to_one(&self) -> bool {
        self.foldover_triangles == 0
            && self.degenerate_triangles == 0
            && self.invalid_triangles == 0
            && (self.total - 4.0 * PI).abs() <= 1e-9 * 4.0 * PI
    }
}

/// Signed solid angle of the triangle `(a, b, c)` (vectors from the centre) by Van Oosterom and
/// Strackee (1983), positive when the triangle winds counter-clockwise seen from the centre's
/// outside, i.e. its normal `(b−a)×(c−a)` points away from the centre. Returns `None` when the
/// triangle contains the centre or has a vertex at it (no projection).
pub fn signed_solid_angle(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Option<f64> {
    solid_angle(a, b, c).map(|(omega, _)| omega)
}

/// The signed solid angle and whether the triangle is clearly seen from its back (triple product
/// below `−FOLD_TOLERANCE·|a||b||c|`); `None` when it has no projection.
fn solid_angle(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Option<(f64, bool)> {
    let dot = |u: [f64; 3], v: [f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let cross = |u: [f64; 3], v: [f64; 3]| {
        [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ]
    };
    let (la, lb, lc) = (dot(a, a).sqrt(), dot(b, b).sqrt(), dot(c, c).sqrt());
    let scale = la * lb * lc;
    if !(scale > 0.0) || !scale.is_finite() {
        return None;
    }
    let num = dot(a, cross(b, c));
    let den = scale + dot(a, b) * lc + dot(a, c) * lb + dot(b, c) * la;
    let tol = FOLD_TOLERANCE * scale;
    if num.abs() <= tol && den <= tol {
        // Seen edge-on with the centre on the triangle (or on an edge): Ω → ±2π, undefined.
        return None;
    }
    Some((2.0 * num.atan2(den), num < -tol))
}

/// Quadrature weights of a triangle mesh's vertices as directions from `centre`, with fold-over
/// detection (see the module doc for the scheme and its reasons).
///
/// Each triangle's signed solid angle (Van Oosterom–Strackee, [`signed_solid_angle`]) is shared
/// equally by its three vertices. For a closed, outward-wound mesh around the centre the weights
/// sum to `4π`; a triangle seen from its back (normal towards the centre) is a fold-over, counted
/// with its vertices in [`SphereWeights::foldover_vertices`]. Never panics: out-of-range triangles
/// are skipped and counted.
pub fn vertex_sphere_weights(
    centre: [f64; 3],
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
) -> SphereWeights {
    let rel = |p: [f32; 3]| {
        [
            p[0] as f64 - centre[0],
            p[1] as f64 - centre[1],
            p[2] as f64 - centre[2],
        ]
    };
    let nv = positions.len();
    let mut weights = vec![0.0; nv];
    let mut flagged = vec![false; nv];
    let (mut total, mut covered) = (0.0, 0.0);
    let (mut folds, mut degenerate, mut invalid) = (0usize, 0usize, 0usize);
    for t in triangles {
        if t.iter().any(|&i| i as usize >= nv) {
            invalid += 1;
            continue;
        }
        let [a, b, c] = t.map(|i| rel(positions[i as usize]));
        let omega = match solid_angle(a, b, c) {
            Some((o, reversed)) => {
                if reversed {
                    folds += 1;
                    t.iter().for_each(|&i| flagged[i as usize] = true);
                }
                o
            }
            None => {
                degenerate += 1;
                t.iter().for_each(|&i| flagged[i as usize] = true);
                0.0
            }
        };
        total += omega;
        covered += omega.abs();
        for &i in t {
            weights[i as usize] += omega / 3.0;
        }
    }
    let foldover_vertices = (0..nv as u32).filter(|&i| flagged[i as usize]).collect();
    let negative_weights = weights.iter().filter(|&&w| w < 0.0).count();
    SphereWeights {
        weights,
        total,
        covered,
        foldover_triangles: folds,
        degenerate_triangles: degenerate,
        invalid_triangles: invalid,
        foldover_vertices,
        negative_weights,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    const FOUR_PI: f64 = 4.0 * PI;

    /// SplitMix64: deterministic test randomness without crates.
    struct Rng(u64);
    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let u = self.uniform().max(1e-300);
            let v = self.uniform();
            (-2.0 * u.ln()).sqrt() * (2.0 * PI * v).cos()
        }
        fn direction(&mut self) -> [f64; 3] {
            loop {
                let d = [self.normal(), self.normal(), self.normal()];
                let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if r > 1e-3 {
                    return d.map(|c| c / r);
                }
            }
        }
    }

    fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
        a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    }

    fn eval(dir: [f64; 3], n: usize) -> Vec<f64> {
        let mut out = vec![f64::NAN; n * n];
        eval_into(dir, n, &mut out);
        out
    }

    /// Gauss–Legendre nodes and weights on [−1, 1] (Newton on P_n).
    fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
        let (mut xs, mut ws) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for i in 0..n {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let kf = k as f64;
                    let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-16 {
                    break;
                }
            }
            xs.push(x);
            ws.push(2.0 / ((1.0 - x * x) * dp * dp));
        }
        (xs, ws)
    }

    /// A product grid (Gauss–Legendre in cos θ × uniform φ) that integrates every product of two
    /// harmonics of `n` bands exactly: `n + 1` latitudes, `2n + 2` longitudes.
    fn product_grid(n: usize) -> (Vec<[f64; 3]>, Vec<f64>) {
        let (zs, wz) = gauss_legendre(n + 1);
        let nphi = 2 * n + 2;
        let (mut dirs, mut ws) = (Vec::new(), Vec::new());
        for (z, w) in zs.iter().zip(&wz) {
            let s = (1.0 - z * z).sqrt();
            for j in 0..nphi {
                let phi = 2.0 * PI * j as f64 / nphi as f64;
                dirs.push([s * phi.cos(), s * phi.sin(), *z]);
                ws.push(w * 2.0 * PI / nphi as f64);
            }
        }
        (dirs, ws)
    }

    /// Max |<Y_a, Y_b> − δ_ab| over all pairs, by a quadrature rule.
    fn max_gram_error(basis: &Basis, weights: &[f64]) -> f64 {
        let (nc, np) = (basis.n_coeffs(), basis.n_nodes());
        // Column-major copy with sqrt(w) folded in for contiguous dot products (weights ≥ 0 here).
        let mut cols = vec![0.0; nc * np];
        for j in 0..np {
            let sw = weights[j].sqrt();
            for (k, y) in basis.row(j).iter().enumerate() {
                cols[k * np + j] = y * sw;
            }
        }
        let mut worst = 0.0f64;
        for a in 0..nc {
            let ca = &cols[a * np..(a + 1) * np];
            for b in a..nc {
                let cb = &cols[b * np..(b + 1) * np];
                let g: f64 = ca.iter().zip(cb).map(|(u, v)| u * v).sum();
                let e = (g - if a == b { 1.0 } else { 0.0 }).abs();
                worst = worst.max(e);
            }
        }
        worst
    }

    fn legendre(l: usize, x: f64) -> f64 {
        let (mut p0, mut p1) = (1.0, x);
        if l == 0 {
            return 1.0;
        }
        for k in 2..=l {
            let kf = k as f64;
            let p2 = ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf;
            p0 = p1;
            p1 = p2;
        }
        p1
    }

    /// Icosphere: the icosahedron subdivided `level` times, vertices on the unit sphere, triangles
    /// wound counter-clockwise seen from outside.
    fn icosphere(level: usize) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let t = (1.0 + 5f64.sqrt()) / 2.0;
        let mut v: Vec<[f64; 3]> = [
            [-1.0, t, 0.0],
            [1.0, t, 0.0],
            [-1.0, -t, 0.0],
            [1.0, -t, 0.0],
            [0.0, -1.0, t],
            [0.0, 1.0, t],
            [0.0, -1.0, -t],
            [0.0, 1.0, -t],
            [t, 0.0, -1.0],
            [t, 0.0, 1.0],
            [-t, 0.0, -1.0],
            [-t, 0.0, 1.0],
        ]
        .iter()
        .map(|p| {
            let r = dot(*p, *p).sqrt();
            p.map(|c| c / r)
        })
        .collect();
        let mut f: Vec<[u32; 3]> = vec![
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ];
        for _ in 0..level {
            let mut cache: HashMap<(u32, u32), u32> = HashMap::new();
            let mut mid = |i: u32, j: u32, v: &mut Vec<[f64; 3]>| {
                let key = (i.min(j), i.max(j));
                *cache.entry(key).or_insert_with(|| {
                    let (a, b) = (v[i as usize], v[j as usize]);
                    let m = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
                    let r = dot(m, m).sqrt();
                    v.push(m.map(|c| c / r));
                    (v.len() - 1) as u32
                })
            };
            let mut g = Vec::with_capacity(f.len() * 4);
            for [a, b, c] in f {
                let ab = mid(a, b, &mut v);
                let bc = mid(b, c, &mut v);
                let ca = mid(c, a, &mut v);
                g.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
            }
            f = g;
        }
        (v, f)
    }

    fn to_f32(v: &[[f64; 3]]) -> Vec<[f32; 3]> {
        v.iter().map(|p| p.map(|c| c as f32)).collect()
    }

    #[test]
    fn index_and_degree_order_are_inverse() {
        for k in 0..MAX_BANDS * MAX_BANDS {
            let (l, m) = degree_order(k);
            assert!(m.unsigned_abs() <= l);
            assert_eq!(index(l, m), k);
        }
        assert_eq!(index(0, 0), 0);
        assert_eq!(index(1, -1), 1);
        assert_eq!(index(3, 3), 15);
    }

    #[test]
    fn low_orders_match_the_cartesian_table_without_condon_shortley_phase() {
        let mut rng = Rng(1);
        for _ in 0..100 {
            let d = rng.direction();
            let [x, y, z] = d;
            let y_ = eval([3.0 * x, 3.0 * y, 3.0 * z], 4); // not unit: normalised inside
            let c1 = (3.0 / FOUR_PI).sqrt();
            let c2 = 0.5 * (15.0 / PI).sqrt();
            let expect = [
                0.5 / PI.sqrt(),
                c1 * y,
                c1 * z,
                c1 * x,
                c2 * x * y,
                c2 * y * z,
                0.25 * (5.0 / PI).sqrt() * (3.0 * z * z - 1.0),
                c2 * x * z,
                0.25 * (15.0 / PI).sqrt() * (x * x - y * y),
                0.25 * (35.0 / (2.0 * PI)).sqrt() * y * (3.0 * x * x - y * y),
                0.5 * (105.0 / PI).sqrt() * x * y * z,
                0.25 * (21.0 / (2.0 * PI)).sqrt() * y * (5.0 * z * z - 1.0),
                0.25 * (7.0 / PI).sqrt() * z * (5.0 * z * z - 3.0),
                0.25 * (21.0 / (2.0 * PI)).sqrt() * x * (5.0 * z * z - 1.0),
                0.25 * (105.0 / PI).sqrt() * z * (x * x - y * y),
                0.25 * (35.0 / (2.0 * PI)).sqrt() * x * (x * x - 3.0 * y * y),
            ];
            for (k, (a, b)) in y_.iter().zip(expect).enumerate() {
                assert!((a - b).abs() < 1e-14, "k = {k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn orthonormal_by_exact_product_quadrature_at_16_and_32_bands() {
        for (n, tol) in [(4, 1e-13), (16, 1e-12), (32, 1e-12)] {
            let (dirs, w) = product_grid(n);
            let basis = Basis::new(&dirs, n);
            let err = max_gram_error(&basis, &w);
            eprintln!(
                "orthonormality n = {n}: max |<Y_a,Y_b> − δ_ab| = {err:.3e} ({} nodes)",
                dirs.len()
            );
            assert!(err < tol, "n = {n}: {err}");
        }
    }

    #[test]
    fn pole_values_are_exact_and_finite() {
        for n in [16, 32, MAX_BANDS] {
            for (dir, sign) in [([0.0, 0.0, 1.0], 1.0), ([0.0, 0.0, -2.5], -1.0)] {
                let y = eval(dir, n);
                let mut worst = 0.0f64;
                for (k, v) in y.iter().enumerate() {
                    let (l, m) = degree_order(k);
                    assert!(v.is_finite());
                    if m == 0 {
                        let expect = sign_pow(sign, l) * ((2 * l + 1) as f64 / FOUR_PI).sqrt();
                        worst = worst.max(((v - expect) / expect).abs());
                    } else {
                        assert_eq!(*v, 0.0, "l = {l}, m = {m} at the pole");
                    }
                }
                assert!(worst < 1e-13, "n = {n}: relative pole error {worst}");
            }
        }
    }

    fn sign_pow(sign: f64, l: usize) -> f64 {
        if sign < 0.0 && l % 2 == 1 {
            -1.0
        } else {
            1.0
        }
    }

    #[test]
    fn directions_extremely_close_to_the_poles_are_finite_and_continuous() {
        let n = 32;
        let north = eval([0.0, 0.0, 1.0], n);
        let south = eval([0.0, 0.0, -1.0], n);
        let cases = [
            ([1e-300, 0.0, 1.0], &north),
            ([1e-300, -1e-300, 1.0], &north),
            ([(PI - 1e-16).sin(), 0.0, (PI - 1e-16).cos()], &south),
            ([1e-16, 1e-16, -1.0], &south),
            ([5e-324, 0.0, -1e-300], &south), // subnormal x, tiny z
        ];
        for (dir, pole) in cases {
            let y = eval(dir, n);
            for (k, (a, b)) in y.iter().zip(pole.iter()).enumerate() {
                assert!(a.is_finite(), "{dir:?} k = {k}");
                assert!((a - b).abs() < 1e-12, "{dir:?} k = {k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn degenerate_directions_give_the_isotropic_answer() {
        let ev = Evaluator::new(8);
        let mut y = vec![f64::NAN; 64];
        for dir in [
            [0.0, 0.0, 0.0],
            [-0.0, 0.0, -0.0],
            [f64::NAN, 1.0, 0.0],
            [f64::INFINITY, 0.0, 0.0],
        ] {
            assert!(!ev.eval_into(dir, &mut y));
            assert_eq!(y[0], 0.5 / PI.sqrt());
            assert!(y[1..].iter().all(|&v| v == 0.0));
        }
        // Huge and subnormal scales are still directions.
        let unit_ = eval([0.6, 0.0, 0.8], 8);
        for s in [1e308, 1e-310] {
            assert!(ev.eval_into([0.6 * s, 0.0, 0.8 * s], &mut y));
            for (a, b) in y.iter().zip(&unit_) {
                assert!((a - b).abs() < 1e-13);
            }
        }
        let basis = Basis::new(&[[1.0, 0.0, 0.0], [0.0; 3], [0.0, 1.0, 0.0]], 3);
        assert_eq!(basis.isotropic_nodes(), &[1]);
    }

    #[test]
    fn addition_theorem_holds_to_l_31() {
        let n = 32;
        let mut rng = Rng(7);
        let mut worst = 0.0f64;
        for _ in 0..200 {
            let (a, b) = (rng.direction(), rng.direction());
            let (ya, yb) = (eval(a, n), eval(b, n));
            let c = dot(a, b);
            for l in 0..n {
                let s: f64 = (l * l..(l + 1) * (l + 1)).map(|k| ya[k] * yb[k]).sum();
                let expect = (2 * l + 1) as f64 / FOUR_PI * legendre(l, c);
                worst = worst.max((s - expect).abs());
            }
        }
        eprintln!("addition theorem, l ≤ 31: max error {worst:.3e}");
        assert!(worst < 1e-12, "{worst}");
    }

    #[test]
    fn values_stay_within_their_bound_up_to_the_band_limit() {
        let mut rng = Rng(11);
        for n in [32, MAX_BANDS] {
            let mut dirs: Vec<[f64; 3]> = (0..2000).map(|_| rng.direction()).collect();
            // Plus near-polar and equatorial directions, where m = l and m = 0 peak.
            for e in [1e-3, 1e-8, 0.0] {
                dirs.push([e, 0.3 * e, 1.0]);
                dirs.push([1.0, e, 0.0]);
            }
            let mut worst_unsold = 0.0f64;
            for d in dirs {
                let y = eval(d, n);
                for l in 0..n {
                    let bound = ((2 * l + 1) as f64 / FOUR_PI).sqrt();
                    let band = &y[l * l..(l + 1) * (l + 1)];
                    let mut s = 0.0;
                    for &v in band {
                        assert!(v.is_finite() && v.abs() <= bound * (1.0 + 1e-12), "l = {l}");
                        s += v * v;
                    }
                    // Unsöld: Σ_m Y_lm² = (2l+1)/(4π).
                    worst_unsold = worst_unsold.max((s / (bound * bound) - 1.0).abs());
                }
            }
            eprintln!("Unsöld's sum, n = {n}: max relative error {worst_unsold:.3e}");
            assert!(worst_unsold < 1e-12, "n = {n}: {worst_unsold}");
        }
    }

    /// Rotation matrix of a random unit quaternion.
    fn random_rotation(rng: &mut Rng) -> [[f64; 3]; 3] {
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let r = (q.iter().map(|c| c * c).sum::<f64>()).sqrt();
        let [w, x, y, z] = q.map(|c| c / r);
        [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ]
    }

    fn rotate(r: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
        [dot(r[0], v), dot(r[1], v), dot(r[2], v)]
    }

    #[test]
    fn band_power_is_rotation_invariant() {
        let n = 16;
        let mut rng = Rng(3);
        let coeffs: Vec<f64> = (0..n * n).map(|_| rng.normal()).collect();
        let (dirs, w) = product_grid(n);
        let basis = Basis::new(&dirs, n);
        let ev = Evaluator::new(n);
        let mut y = vec![0.0; n * n];
        let mut worst = 0.0f64;
        for _ in 0..5 {
            let r = random_rotation(&mut rng);
            // g(x) = f(R x), sampled on the grid, projected back.
            let g: Vec<f64> = dirs
                .iter()
                .map(|d| {
                    ev.eval_into(rotate(&r, *d), &mut y);
                    coeffs.iter().zip(&y).map(|(c, v)| c * v).sum()
                })
                .collect();
            let mut gc = vec![0.0; n * n];
            project(&g, &basis, &w, &mut gc);
            for l in 0..n {
                let band = l * l..(l + 1) * (l + 1);
                let p0: f64 = coeffs[band.clone()].iter().map(|c| c * c).sum();
                let p1: f64 = gc[band].iter().map(|c| c * c).sum();
                worst = worst.max((p1 - p0).abs() / p0);
            }
        }
        eprintln!("band power under rotation: max relative change {worst:.3e}");
        assert!(worst < 1e-11, "{worst}");
    }

    #[test]
    fn projection_recovers_band_limited_coefficients() {
        for n in [4, 16, 32] {
            let mut rng = Rng(5 + n as u64);
            let coeffs: Vec<f64> = (0..n * n).map(|_| rng.normal()).collect();
            let (dirs, w) = product_grid(n);
            let basis = Basis::new(&dirs, n);
            let mut f = vec![0.0; dirs.len()];
            basis.synthesize_into(&coeffs, &mut f);
            let mut back = vec![0.0; n * n];
            project(&f, &basis, &w, &mut back);
            let err = coeffs
                .iter()
                .zip(&back)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            eprintln!("projection round trip n = {n}: max coefficient error {err:.3e}");
            assert!(err < 1e-11, "n = {n}: {err}");
            // The sparse (unweighted) projection agrees with the dense one on weighted values.
            let nodes: Vec<u32> = (0..dirs.len() as u32).step_by(7).collect();
            let vals: Vec<f64> = nodes
                .iter()
                .map(|&j| f[j as usize] * w[j as usize])
                .collect();
            let mut sparse = vec![0.0; n * n];
            project_sparse(&basis, &nodes, &vals, &mut sparse);
            let mut masked = f.clone();
            for (j, v) in masked.iter_mut().enumerate() {
                if j % 7 != 0 {
                    *v = 0.0;
                }
            }
            project(&masked, &basis, &w, &mut back);
            for (a, b) in sparse.iter().zip(&back) {
                assert!((a - b).abs() < 1e-13);
            }
        }
    }

    #[test]
    #[should_panic(expected = "one weight per node")]
    fn project_refuses_mismatched_weights() {
        let basis = Basis::new(&[[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], 2);
        let mut out = vec![0.0; 4];
        project(&[1.0, 2.0], &basis, &[1.0], &mut out);
    }

    #[test]
    fn icosphere_weights_sum_to_four_pi_without_folds() {
        for level in [0, 3, 5] {
            let (v, f) = icosphere(level);
            let centre = [0.01, -0.02, 0.03]; // off-centre: still star-shaped (convex)
            let sw = vertex_sphere_weights(centre, &to_f32(&v), &f);
            assert!(
                (sw.total - FOUR_PI).abs() < 1e-9,
                "level {level}: {}",
                sw.total
            );
            assert!((sw.covered - FOUR_PI).abs() < 1e-9);
            assert_eq!(sw.foldover_triangles, 0);
            assert!(sw.foldover_vertices.is_empty());
            assert_eq!(sw.degenerate_triangles, 0);
            assert_eq!(sw.negative_weights, 0);
            assert_eq!(sw.winding(), 1);
            assert!(sw.is_one_to_one());
            assert!(sw.weights.iter().all(|&w| w > 0.0));
        }
    }

    #[test]
    fn icosphere_vertex_weights_make_a_usable_quadrature() {
        // Measured, not exact: the lumped vertex rule on scattered nodes.
        let (v, f) = icosphere(5); // 10,242 vertices
        let sw = vertex_sphere_weights([0.0; 3], &to_f32(&v), &f);
        let basis = Basis::from_positions([0.0; 3], &to_f32(&v), 4);
        let err4 = max_gram_error(&basis, &sw.weights);
        let basis16 = Basis::from_positions([0.0; 3], &to_f32(&v), 16);
        let err16 = max_gram_error(&basis16, &sw.weights);
        eprintln!(
            "icosphere level 5 vertex weights: orthonormality error n = 4: {err4:.3e}, n = 16: {err16:.3e}"
        );
        assert!(err4 < 1e-3, "{err4}");
        assert!(err16 < 1e-2, "{err16}");
    }

    #[test]
    fn dumbbell_seen_from_its_neck_folds_over() {
        // A sphere stretched along z and pinched at the waist: the lobes' faces towards the neck
        // are seen from their backs from the centre of the neck.
        let (v, f) = icosphere(5);
        let shaped: Vec<[f64; 3]> = v
            .iter()
            .map(|&[x, y, z]| {
                let g = 1.0 - 0.9 * (-(z / 0.12) * (z / 0.12)).exp();
                [g * x, g * y, 3.0 * z]
            })
            .collect();
        let sw = vertex_sphere_weights([0.0; 3], &to_f32(&shaped), &f);
        eprintln!(
            "dumbbell: {} fold-over triangles, {} vertices, {} negative weights, total/4π = {:.12}, covered/4π = {:.4}",
            sw.foldover_triangles,
            sw.foldover_vertices.len(),
            sw.negative_weights,
            sw.total / FOUR_PI,
            sw.covered / FOUR_PI
        );
        assert!(sw.foldover_triangles > 0);
        assert!(!sw.foldover_vertices.is_empty());
        assert!(sw.covered > FOUR_PI * (1.0 + 1e-3));
        // Folds cancel in the signed total: still exactly one turn.
        assert!((sw.total - FOUR_PI).abs() < 1e-9);
        assert!(!sw.is_one_to_one());
        // Every flagged vertex touches a reversed triangle.
        let mut touching = vec![false; shaped.len()];
        for t in &f {
            let [a, b, c] = t.map(|i| shaped[i as usize].map(|c| c as f32 as f64));
            if solid_angle(a, b, c).unwrap().1 {
                t.iter().for_each(|&i| touching[i as usize] = true);
            }
        }
        let expect: Vec<u32> = (0..shaped.len() as u32)
            .filter(|&i| touching[i as usize])
            .collect();
        assert_eq!(sw.foldover_vertices, expect);
    }

    #[test]
    fn centre_outside_the_mesh_folds_and_winds_zero_times() {
        let (v, f) = icosphere(3);
        let sw = vertex_sphere_weights([3.0, 0.0, 0.0], &to_f32(&v), &f);
        assert!(sw.total.abs() < 1e-9, "{}", sw.total);
        assert_eq!(sw.winding(), 0);
        assert!(sw.foldover_triangles > f.len() / 3);
        assert!(!sw.is_one_to_one());
        // Inward winding reads as everything folded.
        let flipped: Vec<[u32; 3]> = f.iter().map(|&[a, b, c]| [a, c, b]).collect();
        let sw = vertex_sphere_weights([0.0; 3], &to_f32(&v), &flipped);
        assert_eq!(sw.foldover_triangles, flipped.len());
        assert_eq!(sw.winding(), -1);
    }

    #[test]
    fn degenerate_and_invalid_triangles_are_counted_not_fatal() {
        let p: Vec<[f32; 3]> = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [-1.0, -1.0, 0.0],
        ];
        // Triangle 0 has a vertex at the centre; triangle 1 contains the centre in its plane;
        // triangle 2 indexes past the end.
        let t = vec![[0, 1, 2], [1, 2, 3], [1, 2, 9]];
        let sw = vertex_sphere_weights([0.0; 3], &p, &t);
        assert_eq!(sw.degenerate_triangles, 2);
        assert_eq!(sw.invalid_triangles, 1);
        assert_eq!(sw.foldover_vertices, vec![0, 1, 2, 3]);
        assert!(sw.weights.iter().all(|w| w.is_finite()));
        // Edge-on but not through the centre: Ω = 0, not a fold.
        let omega = signed_solid_angle([1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 1.0, 0.0]).unwrap();
        assert_eq!(omega, 0.0);
        // An octant is 4π/8.
        let octant = signed_solid_angle([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]).unwrap();
        assert!((octant - PI / 2.0).abs() < 1e-15);
    }

    #[test]
    fn f32_positions_cost_only_their_own_precision() {
        // The basis at f32-rounded directions vs exact ones: the error is the direction's
        // (≈6e-8), amplified by the gradient of Y (∝ l), not the recurrence's rounding.
        let (v, _) = icosphere(4);
        let n = 16;
        let scale = [120.0, 80.0, 200.0]; // lung-sized ellipsoid, mm
        let centre = [10.0, -30.0, 150.0];
        let (mut worst, mut worst_unit) = (0.0f64, 0.0f64);
        for p in &v {
            let exact = [0, 1, 2].map(|i| p[i] * scale[i]);
            let pos32 = [0, 1, 2].map(|i| (exact[i] + centre[i]) as f32);
            let b32 = Basis::from_positions(centre, &[pos32], n);
            let y64 = eval(exact, n);
            for (a, b) in b32.row(0).iter().zip(&y64) {
                worst = worst.max((a - b).abs());
            }
            // f64 throughout: rounding only.
            let y64b = eval(exact.map(|c| c * 3.0), n);
            for (a, b) in y64b.iter().zip(&y64) {
                worst_unit = worst_unit.max((a - b).abs());
            }
        }
        eprintln!("f32 positions, n = 16: max |ΔY| = {worst:.3e} (f64 rescaled: {worst_unit:.3e})");
        assert!(worst < 1e-4, "{worst}");
        assert!(worst_unit < 1e-13, "{worst_unit}");
    }
}
