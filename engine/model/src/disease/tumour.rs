//! # Tumour-influenced lung (seed §8.2, eq. 8.14–8.22)
//!
//! A tumour lowers the regional alveolar expandability `a(J)` (eq. 8.20), which changes the lung's
//! kernel rows (eq. 8.14–8.19, 8.22), hence the elastostatic force and the unit displacement; the
//! PV resistance rises in both phases (§8.1.3, L3671–3672); and what a radiotherapy planner needs —
//! the tumour centroid's trajectory over the breath and its motion amplitude per axis — is computed
//! from the resulting displacement field ([`TumourTrack`]).
//!
//! ## The seed's equations
//! ```text
//! 8.14  K(J,I) = P_I cos z(J,I) + Q_I sin z(J,I)          8.22  P_I = C_I cos φ_I, Q_I = C_I sin φ_I
//! 8.15  K(J,I) = C_I cos z'(J,I)                          8.16  K(J,I) = D_I / (4π d(J,I))
//! 8.17/18  z'(J,I) = acos(1 / (4π d'(J,I)))               8.19  d'(J,I) = A_I d(J,I) + B_I e(J,I)
//! 8.20  e(J,I) = a(J) − a(I)                              8.21  C_I = D[I] / Σ_J f[J] cos z'(J,I)
//! ```
//! `K(J,I)` is the influence of a force at node `J` on node `I`: entry `(row J, column I)` of the
//! transfer CSR ([`crate::operator::Transfer`], row `j` = catchers of a unit force on `j`).
//!
//! ## Decisions (lungdyn) — the seed's formulas are inconsistent as printed (EQUATIONS §4.4)
//! * **Tumour region** ([`Tumour`]): an ellipsoid, centre in the normalised lung coordinates of
//!   eq. 6.14–6.16 (`x̂` mediastinum → lateral, `ŷ` posterior → anterior, `ẑ` apex → base, each in
//!   [0, 1] over the lung's box), radii in mm along the body axes (a tumour's size is known in mm).
//!   The centre must lie inside the lung surface (winding number).
//! * **Expandability profile** (the seed gives none): `a = 1` in normal lung, `a_t` ([`Tumour::expandability`],
//!   default 0.1: tumour tissue ~10× stiffer than parenchyma) inside the ellipsoid (`ρ ≤ 1`, `ρ` the
//!   ellipsoidal radius), and a C¹ smoothstep from `a_t` back to 1 over `ρ ∈ [1, 1 + falloff]` (the
//!   peritumoral region; default falloff = 1 radius). The kernel's nodes are surface vertices, so a deep
//!   tumour acts on the kernel only through this falloff; the count of vertices with `a < 1` is reported.
//! * **Distance unit** (the seed's `d` has none, and `1/(4πd)` is meaningful only where `4πd = O(1)`):
//!   `d̂ = |p_J − p_I| / ℓ` with `ℓ` the kernel's reach — the mean over rows of the largest distance
//!   from the row's node to a catcher ([`kernel_reach_mm`]). The straight distance stands for the seed's
//!   "piecewise Euclidean" path length (rows are local: a few edges).
//! * **Structural constants** `A_I = 1`, `B_I = B` ([`Tumour::coupling`], default 0.25 reach per unit of
//!   expandability): the seed's two-kernel solve fixes only the ratio `A_I/B_I`, and with `A = 1` a
//!   tumour-free lung (`e = 0`) keeps `d' = d`.
//! * **acos domain:** `1/(4πd') ≤ 1` needs `d' ≥ 1/(4π)`; `d'` (and `d`: the diagonal has `d = 0`) is
//!   clamped to `1/(4π)`, counted ([`RowChange::clamped`]) and, where `B·e` made it `≤ 0`, counted again
//!   ([`RowChange::nonpositive`]).
//! * **How the change enters the baked kernel:** the baked entry is read as `C_I cos z'_0(J,I)` with
//!   `z'_0` the tumour-free angle (the pass's deviations from a pure `1/d` law stay in it), and the tumour
//!   kernel is `C_I cos(z'(J,I) − φ_I)`, i.e. each entry is multiplied by
//!   `g = cos(z' − φ_I)/cos z'_0 = (x′ cos φ_I + √(1 − x′²) sin φ_I)/x_0`, `x = 1/(4π d)`.
//!   With `φ_I = 0` this is `d_0/d'` — eq. 8.16 with the distance stretched or shrunk by the
//!   expandability difference: a node in the tumour receives less from normal neighbours (`e > 0`),
//!   normal nodes receive more from the tumour (`e < 0`, "air flows to the region of least
//!   resistance"). `e = 0` and `φ = 0` leave the entry bit for bit.
//! * **φ sign:** 8.14 with 8.22 is `C_I cos(z − φ_I)`; 8.15 writes `z + φ_I`. lungdyn takes `z − φ_I`:
//!   for `z' ∈ [0, π/2]` and `φ_I ∈ [0, 1]` the entry stays ≥ 0 (with `+` far entries turn negative).
//! * **φ variants** (Fig. 8.6, [`PhiVariant`]): `φ_I` = the normalised distance of node `I` from the
//!   posterior (supporting) surface, `ŷ`, or its square; default none (`φ = 0`). `φ > 0` shifts weight
//!   from near to far entries of a row (a large effect; it is the seed's "steerable" constant).
//! * **eq. 8.21** (`C_I` from a patient's displacements `D[I]`) is the seed's fit to patient data;
//!   [`column_scales_8_21`] provides it for data that have them; a synthetic tumour keeps the baked
//!   `C_I` (refitting to the normal lung's displacements would undo the tumour).
//! * **Resistance:** eq. 8.9 on both phases ([`super::resistance::TUMOUR`]) with
//!   `x = φ_r·min(1, V_tumour/V_lung)` ([`Tumour::resistance_phi`], default the seed's 0.1).
//! * **Centroid trajectory:** the tumour moves with the lung; its centre's displacement is the
//!   mean-value interpolation (Ju, Schaefer & Warren, SIGGRAPH 2005) of the surface's unit
//!   displacement, exact for affine motion, so the centre moves `s·ū` at deformation scale `s`.

use glam::DVec3;
use thiserror::Error;

use super::resistance::{self, ResistanceReport};
use super::{check_range, DiseaseError};
use crate::deform::{normalised_position, LungModel};
use crate::mesh::{Side, TriMesh};
use crate::operator::Transfer;
use crate::pv::PhaseConstants;

/// `1/(4π)`: the smallest normalised distance in the acos domain of eq. 8.17–8.18.
pub const D_MIN: f64 = 1.0 / (4.0 * std::f64::consts::PI);

/// Default expandability inside the tumour (relative to 1 in normal lung).
pub const EXPANDABILITY: f64 = 0.1;
/// Default falloff width, in radii.
pub const FALLOFF: f64 = 1.0;
/// Default structural constant `B` (kernel reaches per unit of expandability).
pub const COUPLING: f64 = 0.25;

/// How `φ_I` is set (Fig. 8.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PhiVariant {
    /// `φ_I = 0`: eq. 8.15 reduces to eq. 8.16.
    #[default]
    None,
    /// Fig. 8.6a: the normalised distance from the posterior (supporting) surface, `ŷ`.
    Distance,
    /// Fig. 8.6b: its square, `ŷ²`.
    DistanceSquared,
}

/// Why a tumour cannot be applied.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum TumourError {
    /// The centre is not inside the lung surface.
    #[error("the tumour centre {centre_mm:?} mm is not inside the {side} lung (winding number {winding:.3}); move centre")]
    CentreOutside {
        /// Lung.
        side: &'static str,
        /// Centre, mm.
        centre_mm: [f64; 3],
        /// Generalised winding number of the surface about it (1 inside, 0 outside).
        winding: f64,
    },
    /// Arrays do not belong together.
    #[error("{what}: expected {expected}, got {got}")]
    Shape {
        /// Which array.
        what: &'static str,
        /// Expected length.
        expected: usize,
        /// Length given.
        got: usize,
    },
    /// The kernel has no off-diagonal entries, so it has no reach.
    #[error(
        "the kernel has no entry between distinct nodes: it has no reach to normalise distances by"
    )]
    NoReach,
    /// The mesh is unusable.
    #[error("the lung mesh is empty or not finite")]
    BadMesh,
    /// The point lies on the surface: mean-value coordinates are not defined there.
    #[error("the tumour centre lies on the lung surface")]
    OnSurface,
}

/// A tumour (scene keys in brackets). Serialised into a kernel's bake settings, so a kernel says
/// which tumour it was baked with.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tumour {
    /// Lung (`side`).
    pub side: Side,
    /// Centre in normalised lung coordinates `(x̂, ŷ, ẑ)`, each in [0, 1] (`centre`).
    pub centre: [f64; 3],
    /// Radii along the body X, Y, Z axes, mm (`radii_mm`).
    pub radii_mm: [f64; 3],
    /// Expandability inside, `(0, 1]` (`expandability`).
    pub expandability: f64,
    /// Falloff width in radii, `[0, 10]` (`falloff`).
    pub falloff: f64,
    /// Structural constant `B` of eq. 8.19, `[0, 10]` (`coupling`).
    pub coupling: f64,
    /// `φ_I` variant (`phi_variant`).
    pub phi: PhiVariant,
    /// φ of eq. 8.9 for the raised resistance (`resistance_phi`).
    pub resistance_phi: f64,
}

impl Tumour {
    /// A tumour with the module's defaults.
    pub fn new(side: Side, centre: [f64; 3], radii_mm: [f64; 3]) -> Self {
        Self {
            side,
            centre,
            radii_mm,
            expandability: EXPANDABILITY,
            falloff: FALLOFF,
            coupling: COUPLING,
            phi: PhiVariant::None,
            resistance_phi: resistance::PHI_SEED,
        }
    }

    /// Check every parameter; errors name the scene key.
    pub fn validate(&self) -> Result<(), DiseaseError> {
        for &c in &self.centre {
            check_range(
                "centre",
                c,
                0.0,
                1.0,
                "each within 0..=1 (normalised lung coordinates)",
            )?;
        }
        for &r in &self.radii_mm {
            check_range("radii_mm", r, 0.5, 150.0, "each within 0.5..=150 mm")?;
        }
        check_range(
            "expandability",
            self.expandability,
            f64::MIN_POSITIVE,
            1.0,
            "within (0, 1]",
        )?;
        check_range("falloff", self.falloff, 0.0, 10.0, "within 0..=10 radii")?;
        check_range("coupling", self.coupling, 0.0, 10.0, "within 0..=10")?;
        check_range(
            "resistance_phi",
            self.resistance_phi,
            0.0,
            resistance::PHI_MAX,
            "within 0..=1",
        )?;
        Ok(())
    }

    /// Volume of the ellipsoid, ml.
    pub fn volume_ml(&self) -> f64 {
        4.0 / 3.0 * std::f64::consts::PI * self.radii_mm.iter().product::<f64>() / 1000.0
    }

    /// The centre in the body frame (mm) for `mesh`'s box (inverse of eq. 6.14–6.16's normalisation).
    pub fn centre_mm(&self, mesh: &TriMesh) -> [f64; 3] {
        let bb = mesh.aabb();
        let (lo, hi) = (bb.min.map(|v| v as f64), bb.max.map(|v| v as f64));
        let x = match self.side {
            Side::Left => lo[0] + self.centre[0] * (hi[0] - lo[0]),
            Side::Right => hi[0] - self.centre[0] * (hi[0] - lo[0]),
        };
        [
            x,
            lo[1] + self.centre[1] * (hi[1] - lo[1]),
            hi[2] - self.centre[2] * (hi[2] - lo[2]),
        ]
    }

    /// Expandability `a` at `p` (mm) for a tumour centred at `centre_mm`: the profile of the module's
    /// Decision.
    pub fn expandability_at(&self, p: [f64; 3], centre_mm: [f64; 3]) -> f64 {
        let rho = (0..3)
            .map(|a| ((p[a] - centre_mm[a]) / self.radii_mm[a]).powi(2))
            .sum::<f64>()
            .sqrt();
        if rho <= 1.0 {
            self.expandability
        } else if self.falloff <= 0.0 || rho >= 1.0 + self.falloff {
            1.0
        } else {
            let t = (rho - 1.0) / self.falloff;
            let inside = 1.0 - t * t * (3.0 - 2.0 * t);
            1.0 - (1.0 - self.expandability) * inside
        }
    }

    /// `a(J)` of every vertex of `mesh`.
    pub fn expandability_of(&self, mesh: &TriMesh) -> Vec<f64> {
        let c = self.centre_mm(mesh);
        mesh.positions
            .iter()
            .map(|p| self.expandability_at(p.map(|v| v as f64), c))
            .collect()
    }

    /// The normal constants with the tumour's raised resistance (eq. 8.9 on both phases, `x =
    /// resistance_phi·min(1, V_tumour/lung_volume_ml)`).
    pub fn resistance(
        &self,
        inhale: &PhaseConstants,
        exhale: &PhaseConstants,
        lung_volume_ml: f64,
    ) -> Result<(PhaseConstants, PhaseConstants, [ResistanceReport; 2]), DiseaseError> {
        check_range(
            "lung volume (ml)",
            lung_volume_ml,
            f64::MIN_POSITIVE,
            f64::MAX,
            "> 0",
        )?;
        let x = self.resistance_phi * (self.volume_ml() / lung_volume_ml).min(1.0);
        let (mut i, mut e) = (inhale.clone(), exhale.clone());
        let ri = resistance::phase_into(inhale, resistance::TUMOUR.0, x, &mut i)?;
        let re = resistance::phase_into(exhale, resistance::TUMOUR.1, x, &mut e)?;
        Ok((i, e, [ri, re]))
    }
}

/// `φ_I` of every vertex for `variant` (Fig. 8.6): `ŷ`, `ŷ²` or 0.
pub fn phi_values(mesh: &TriMesh, side: Side, variant: PhiVariant) -> Vec<f64> {
    let bb = mesh.aabb();
    mesh.positions
        .iter()
        .map(|&p| {
            let y = normalised_position(p, &bb, side).y;
            match variant {
                PhiVariant::None => 0.0,
                PhiVariant::Distance => y,
                PhiVariant::DistanceSquared => y * y,
            }
        })
        .collect()
}

fn dist(positions: &[[f32; 3]], a: usize, b: usize) -> f64 {
    let (p, q) = (positions[a], positions[b]);
    (0..3)
        .map(|k| (p[k] as f64 - q[k] as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn check_csr(n: usize, row_ptr: &[u64], cols: &[u32], vals_len: usize) -> Result<(), TumourError> {
    if row_ptr.len() != n + 1 {
        return Err(TumourError::Shape {
            what: "row_ptr (vertices + 1)",
            expected: n + 1,
            got: row_ptr.len(),
        });
    }
    let nnz = cols.len();
    if vals_len != nnz || row_ptr[n] as usize != nnz {
        return Err(TumourError::Shape {
            what: "vals / row_ptr end (non-zeros)",
            expected: nnz,
            got: vals_len.min(row_ptr[n] as usize),
        });
    }
    if row_ptr.windows(2).any(|w| w[0] > w[1]) {
        return Err(TumourError::Shape {
            what: "row_ptr (non-decreasing)",
            expected: nnz,
            got: 0,
        });
    }
    if let Some(&c) = cols.iter().find(|&&c| c as usize >= n) {
        return Err(TumourError::Shape {
            what: "cols (a column beyond the vertices)",
            expected: n,
            got: c as usize,
        });
    }
    Ok(())
}

/// The kernel's reach ℓ, mm: the mean over rows of the largest distance from the row's node to one
/// of its catchers (rows with only their own node left out).
pub fn kernel_reach_mm(
    positions: &[[f32; 3]],
    row_ptr: &[u64],
    cols: &[u32],
) -> Result<f64, TumourError> {
    check_csr(positions.len(), row_ptr, cols, cols.len())?;
    let (mut sum, mut rows) = (0.0, 0usize);
    for j in 0..positions.len() {
        let r = row_ptr[j] as usize..row_ptr[j + 1] as usize;
        let far = cols[r]
            .iter()
            .map(|&i| dist(positions, j, i as usize))
            .fold(0.0, f64::max);
        if far > 0.0 {
            sum += far;
            rows += 1;
        }
    }
    if rows == 0 {
        return Err(TumourError::NoReach);
    }
    Ok(sum / rows as f64)
}

/// What [`modify_rows`] did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RowChange {
    /// Entries visited.
    pub entries: u64,
    /// Entries whose value changed (`e ≠ 0` or `φ ≠ 0`).
    pub changed: u64,
    /// Entries whose `d'` was below `1/(4π)` and clamped to it (the acos domain).
    pub clamped: u64,
    /// Of those, entries where `B·e` made `d' ≤ 0`.
    pub nonpositive: u64,
    /// Reach ℓ used, mm.
    pub reach_mm: f64,
    /// Smallest factor `g` applied.
    pub min_factor: f64,
    /// Largest factor `g` applied.
    pub max_factor: f64,
}

/// The factor `g` of one entry (module Decision): `d` and `d'` in reaches, `phi` = `φ_I`.
fn factor(d: f64, d_new: f64, phi: f64) -> f64 {
    let x0 = 1.0 / (4.0 * std::f64::consts::PI * d.max(D_MIN));
    let x1 = 1.0 / (4.0 * std::f64::consts::PI * d_new.max(D_MIN));
    if phi == 0.0 {
        x1 / x0
    } else {
        (x1 * phi.cos() + (1.0 - x1 * x1).max(0.0).sqrt() * phi.sin()) / x0
    }
}

/// Eq. 8.14–8.20, 8.22 on a kernel in CSR (`row_ptr`, `cols`, `vals` as in
/// [`crate::operator::Transfer`]; entry `(row J, column I)` = `K(J,I)`): writes the tumour kernel into
/// `out` (same layout; no allocation), given `a(J)` per node, `φ_I` per node, the structural constant
/// `coupling` (`B`) and the reach ℓ (`reach_mm`, [`kernel_reach_mm`]).
#[allow(clippy::too_many_arguments)]
pub fn modify_rows(
    positions: &[[f32; 3]],
    row_ptr: &[u64],
    cols: &[u32],
    vals: &[f32],
    a: &[f64],
    phi: &[f64],
    coupling: f64,
    reach_mm: f64,
    out: &mut [f32],
) -> Result<RowChange, DiseaseError> {
    let n = positions.len();
    check_csr(n, row_ptr, cols, vals.len())?;
    for (what, got) in [("a (per vertex)", a.len()), ("phi (per vertex)", phi.len())] {
        if got != n {
            return Err(TumourError::Shape {
                what,
                expected: n,
                got,
            }
            .into());
        }
    }
    if out.len() != vals.len() {
        return Err(TumourError::Shape {
            what: "out (non-zeros)",
            expected: vals.len(),
            got: out.len(),
        }
        .into());
    }
    check_range("coupling", coupling, 0.0, 10.0, "within 0..=10")?;
    check_range("reach (mm)", reach_mm, f64::MIN_POSITIVE, f64::MAX, "> 0")?;
    if let Some(v) = a.iter().chain(phi).find(|v| !v.is_finite()) {
        return Err(DiseaseError::OutOfRange {
            name: "a / phi",
            value: *v,
            range: "finite",
        });
    }
    let mut change = RowChange {
        reach_mm,
        min_factor: 1.0,
        max_factor: 1.0,
        ..Default::default()
    };
    for j in 0..n {
        let r = row_ptr[j] as usize..row_ptr[j + 1] as usize;
        for ((&i, &v), o) in cols[r.clone()]
            .iter()
            .zip(&vals[r.clone()])
            .zip(&mut out[r])
        {
            let i = i as usize;
            change.entries += 1;
            let e = a[j] - a[i];
            let phi_i = phi[i];
            if e == 0.0 && phi_i == 0.0 {
                *o = v;
                continue;
            }
            let d = dist(positions, j, i) / reach_mm;
            let d_new = d + coupling * e;
            if d_new < D_MIN {
                change.clamped += 1;
                if d_new <= 0.0 {
                    change.nonpositive += 1;
                }
            }
            let g = factor(d, d_new, phi_i);
            change.changed += 1;
            change.min_factor = change.min_factor.min(g);
            change.max_factor = change.max_factor.max(g);
            *o = (v as f64 * g) as f32;
        }
    }
    Ok(change)
}

/// Eq. 8.21 for data that have displacements: per node `I`, `C_I = D[I] / Σ_J f[J]·K(J,I)` — the
/// scale that makes the kernel reproduce the displacement magnitude `target[I]` under the force `f`.
/// Writes the scales into `out` (length = nodes); nodes whose sum is 0 (nothing reaches them) keep
/// scale 1 and are counted (returned).
pub fn column_scales_8_21(
    row_ptr: &[u64],
    cols: &[u32],
    vals: &[f32],
    f: &[f64],
    target: &[f64],
    out: &mut [f64],
) -> Result<u64, TumourError> {
    let n = f.len();
    check_csr(n, row_ptr, cols, vals.len())?;
    for (what, got) in [("target", target.len()), ("out", out.len())] {
        if got != n {
            return Err(TumourError::Shape {
                what,
                expected: n,
                got,
            });
        }
    }
    out.fill(0.0);
    for j in 0..n {
        let r = row_ptr[j] as usize..row_ptr[j + 1] as usize;
        for (&i, &v) in cols[r.clone()].iter().zip(&vals[r]) {
            out[i as usize] += f[j] * v as f64;
        }
    }
    let mut singular = 0;
    for (o, &t) in out.iter_mut().zip(target) {
        let s = t / *o;
        if *o == 0.0 || !s.is_finite() {
            *o = 1.0;
            singular += 1;
        } else {
            *o = s;
        }
    }
    Ok(singular)
}

/// Generalised winding number of `mesh` about `x` (1 inside a closed outward surface, 0 outside):
/// the solid angles of its triangles (Van Oosterom & Strackee 1983) over 4π.
pub fn winding_number(mesh: &TriMesh, x: [f64; 3]) -> f64 {
    let x = DVec3::from(x);
    let mut omega = 0.0;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| DVec3::from(mesh.positions[i as usize].map(|v| v as f64)) - x);
        let (la, lb, lc) = (a.length(), b.length(), c.length());
        let num = a.dot(b.cross(c));
        let den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
        omega += 2.0 * num.atan2(den);
    }
    omega / (4.0 * std::f64::consts::PI)
}

/// Mean-value coordinates of `x` with respect to the closed triangle surface `mesh` (Ju, Schaefer &
/// Warren 2005, their robust evaluation): weights summing to 1 that reproduce every affine function
/// of the vertices exactly. Allocates the weight vector (set-up, not per tick).
pub fn mean_value_weights(mesh: &TriMesh, x: [f64; 3]) -> Result<Vec<f64>, TumourError> {
    if mesh.positions.is_empty() || mesh.triangles.is_empty() {
        return Err(TumourError::BadMesh);
    }
    let x = DVec3::from(x);
    let n = mesh.positions.len();
    let mut d = vec![0.0; n];
    let mut u = vec![DVec3::ZERO; n];
    let scale = mesh
        .aabb()
        .size()
        .iter()
        .fold(0.0f64, |m, &s| m.max(s as f64));
    let eps = 1e-12 * scale.max(1.0);
    for (k, p) in mesh.positions.iter().enumerate() {
        let v = DVec3::from(p.map(|c| c as f64)) - x;
        if !v.is_finite() {
            return Err(TumourError::BadMesh);
        }
        d[k] = v.length();
        if d[k] < eps {
            let mut w = vec![0.0; n];
            w[k] = 1.0;
            return Ok(w);
        }
        u[k] = v / d[k];
    }
    let mut w = vec![0.0; n];
    let angle_eps = 1e-12;
    for t in &mesh.triangles {
        let idx = t.map(|i| i as usize);
        let l = [0, 1, 2].map(|k| (u[idx[(k + 1) % 3]] - u[idx[(k + 2) % 3]]).length());
        let theta = l.map(|l| 2.0 * (l / 2.0).min(1.0).asin());
        let h = 0.5 * (theta[0] + theta[1] + theta[2]);
        if std::f64::consts::PI - h < angle_eps {
            // x lies on this triangle: mean-value coordinates are not defined on the surface.
            return Err(TumourError::OnSurface);
        }
        let c = [0, 1, 2].map(|k| {
            2.0 * h.sin() * (h - theta[k]).sin()
                / (theta[(k + 1) % 3].sin() * theta[(k + 2) % 3].sin())
                - 1.0
        });
        let sign = u[idx[0]].dot(u[idx[1]].cross(u[idx[2]])).signum();
        let s = c.map(|c| sign * (1.0 - c * c).max(0.0).sqrt());
        if s.iter().any(|s| s.abs() <= angle_eps) {
            // x on the triangle's plane, outside it: no contribution.
            continue;
        }
        for k in 0..3 {
            let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
            w[idx[k]] += (theta[k] - c[k1] * theta[k2] - c[k2] * theta[k1])
                / (d[idx[k]] * theta[k1].sin() * s[k2]);
        }
    }
    let total: f64 = w.iter().sum();
    if !(total.is_finite() && total != 0.0) {
        return Err(TumourError::BadMesh);
    }
    for v in &mut w {
        *v /= total;
    }
    Ok(w)
}

/// The tumour centre's motion: `centre + s·ū + offset` at deformation scale `s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TumourTrack {
    /// Centre at rest (the mesh's FRC), body frame, mm.
    pub centre_mm: [f64; 3],
    /// Displacement of the centre per unit of deformation scale, mm (mean-value interpolation of the
    /// unit displacement field).
    pub unit_displacement_mm: [f64; 3],
}

impl TumourTrack {
    /// The track of the point `centre_mm` inside `mesh` moving with `unit_displacement` (per vertex).
    pub fn new(
        mesh: &TriMesh,
        unit_displacement: &[[f32; 3]],
        centre_mm: [f64; 3],
    ) -> Result<Self, TumourError> {
        if unit_displacement.len() != mesh.positions.len() {
            return Err(TumourError::Shape {
                what: "unit displacement (per vertex)",
                expected: mesh.positions.len(),
                got: unit_displacement.len(),
            });
        }
        let w = mean_value_weights(mesh, centre_mm)?;
        let mut u = [0.0f64; 3];
        for (wk, d) in w.iter().zip(unit_displacement) {
            for a in 0..3 {
                u[a] += wk * d[a] as f64;
            }
        }
        if !u.iter().all(|v| v.is_finite()) {
            return Err(TumourError::BadMesh);
        }
        Ok(Self {
            centre_mm,
            unit_displacement_mm: u,
        })
    }

    /// Position at deformation scale `scale` with the lung's rigid `offset_mm`, mm.
    pub fn position_mm(&self, scale: f64, offset_mm: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| self.centre_mm[a] + scale * self.unit_displacement_mm[a] + offset_mm[a])
    }

    /// Positions at each scale of `scales` (one per tick of a cycle), appended to `out` after clearing
    /// it (no allocation when `out` has the capacity).
    pub fn trajectory_into(&self, scales: &[f64], out: &mut Vec<[f64; 3]>) {
        out.clear();
        out.extend(scales.iter().map(|&s| self.position_mm(s, [0.0; 3])));
    }

    /// Motion amplitude per axis (max − min of the position over `scales`), mm.
    pub fn amplitude_mm(&self, scales: &[f64]) -> [f64; 3] {
        let (lo, hi) = scales
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &s| {
                (l.min(s), h.max(s))
            });
        if !(lo.is_finite() && hi.is_finite()) {
            return [0.0; 3];
        }
        self.unit_displacement_mm.map(|u| (u * (hi - lo)).abs())
    }
}

/// A lung with a tumour: its changed deformation and the tumour's track.
#[derive(Debug, Clone)]
pub struct TumourLung {
    /// The lung model with the tumour's unit displacement (normalised to the unit volume, EQUATIONS
    /// §2.4, so the lung still breathes its tidal volume).
    pub model: LungModel,
    /// `a(J)` per vertex.
    pub expandability: Vec<f64>,
    /// Vertices with `a < 1`.
    pub vertices_affected: usize,
    /// What the kernel change did.
    pub change: RowChange,
    /// The tumour centre's track on the changed field.
    pub track: TumourTrack,
    /// The track the same centre would have in the normal lung (for comparison).
    pub normal_track: TumourTrack,
}

/// Apply `tumour` to a lung: `mesh`, its transfer rows, the unit directions `d_i` and the applied
/// force `f` (as stored in a kernel file). Set-up work (allocates).
pub fn tumour_lung(
    tumour: &Tumour,
    mesh: TriMesh,
    transfer: &Transfer,
    directions: &[[f32; 3]],
    applied_force: &[f32],
) -> Result<TumourLung, DiseaseError> {
    tumour.validate()?;
    let n = mesh.positions.len();
    if mesh.triangles.is_empty() || mesh.positions.iter().flatten().any(|v| !v.is_finite()) {
        return Err(TumourError::BadMesh.into());
    }
    for (what, got) in [
        ("transfer rows (vertices)", transfer.n),
        ("directions (per vertex)", directions.len()),
        ("applied force (per vertex)", applied_force.len()),
    ] {
        if got != n {
            return Err(TumourError::Shape {
                what,
                expected: n,
                got,
            }
            .into());
        }
    }
    let centre_mm = tumour.centre_mm(&mesh);
    let winding = winding_number(&mesh, centre_mm);
    if !(winding > 0.5) {
        return Err(TumourError::CentreOutside {
            side: tumour.side.name(),
            centre_mm,
            winding,
        }
        .into());
    }
    let a = tumour.expandability_of(&mesh);
    let phi = phi_values(&mesh, tumour.side, tumour.phi);
    let reach = kernel_reach_mm(&mesh.positions, &transfer.row_ptr, &transfer.cols)?;
    let mut changed = transfer.clone();
    let change = modify_rows(
        &mesh.positions,
        &transfer.row_ptr,
        &transfer.cols,
        &transfer.vals,
        &a,
        &phi,
        tumour.coupling,
        reach,
        &mut changed.vals,
    )?;
    let f: Vec<f64> = applied_force.iter().map(|&v| v as f64).collect();
    let dirs: Vec<DVec3> = directions
        .iter()
        .map(|d| DVec3::from(d.map(|v| v as f64)))
        .collect();
    let normal_force = transfer.elastostatic(&f);
    let (normal, _, _) = LungModel::from_force_and_directions(
        tumour.side,
        mesh.clone(),
        dirs.clone(),
        &normal_force,
    )
    .map_err(|_| TumourError::BadMesh)?;
    let force = changed.elastostatic(&f);
    let (model, _, _) = LungModel::from_force_and_directions(tumour.side, mesh, dirs, &force)
        .map_err(|_| TumourError::BadMesh)?;
    let track = TumourTrack::new(&model.mesh, &model.unit_displacement, centre_mm)?;
    let normal_track = TumourTrack::new(&normal.mesh, &normal.unit_displacement, centre_mm)?;
    Ok(TumourLung {
        vertices_affected: a.iter().filter(|&&v| v < 1.0).count(),
        model,
        expandability: a,
        change,
        track,
        normal_track,
    })
}

/// What a kernel baked with a tumour records of it (`KernelMeta::tumour`): the region, what the
/// kernel change did, and how the tumour centre moves in every deformation mode.
///
/// Every mode's displacement is linear in its per-vertex data, and the centre's displacement is the
/// mean-value interpolation of the surface's (module Decisions), so the centre moves by the same
/// linear form with the per-vertex data replaced by their mean-value sums:
/// precomputed `s·Σ_i λ_i u_i`; basis (and direct, eq. 7.1, which the basis reproduces to
/// round-off) `s·Σ_a w_a·Σ_i λ_i G_{i,a} k d_i`; SH (eq. 7.7) `s·Σ_k F_k·Σ_i λ_i T_{i,k} k d_i`.
/// The sums are taken at bake time from the data the run time deforms with: the stored f32 data,
/// and for SH the 16-bit values it holds them as ([`crate::deform::sh_coeffs`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TumourMeta {
    /// The tumour as baked.
    pub tumour: Tumour,
    /// Centre at rest (FRC), body frame, mm.
    pub centre_mm: [f64; 3],
    /// Volume of the ellipsoid, ml.
    pub volume_ml: f64,
    /// Vertices with expandability below 1.
    pub vertices_affected: u64,
    /// Kernel entries changed by eq. 8.14–8.20.
    pub entries_changed: u64,
    /// Entries whose `d'` was clamped to the acos domain.
    pub entries_clamped: u64,
    /// Of those, entries where `B·e` made `d' ≤ 0`.
    pub entries_nonpositive: u64,
    /// Kernel reach ℓ, mm.
    pub reach_mm: f64,
    /// Smallest and largest entry factor applied.
    pub factor_range: [f64; 2],
    /// How much the tumour changed the surface motion where it reaches (vertices with `a < 1`):
    /// mean and largest `|u − u_normal| / |u_normal|` of the unit displacement, %.
    pub affected_motion_change_percent: [f64; 2],
    /// Centre displacement per unit deformation scale, precomputed mode, mm.
    pub precomputed_mm: [f64; 3],
    /// The same centre in the lung baked without the tumour, mm per unit scale (for comparison).
    pub normal_precomputed_mm: [f64; 3],
    /// Centre displacement per unit scale per force weight `(w0, wx, wy, wz)`: basis and direct modes.
    pub basis_mm: [[f64; 3]; 4],
    /// Centre displacement per unit scale per SH force coefficient (`bands²`; empty without SH).
    #[serde(default)]
    pub sh_mm: Vec<[f64; 3]>,
}

impl TumourMeta {
    /// The centre's displacement per unit deformation scale in `mode` with the frame's
    /// coefficients (none for precomputed, 4 weights for basis/direct, `bands²` for SH); `None`
    /// when the coefficients do not fit the mode.
    pub fn displacement_mm(
        &self,
        mode: crate::deform::modes::DeformMode,
        coeffs: &[f32],
    ) -> Option<[f64; 3]> {
        use crate::deform::modes::DeformMode as M;
        let rows: &[[f64; 3]] = match mode {
            M::Precomputed => return Some(self.precomputed_mm),
            M::Basis | M::Direct => &self.basis_mm,
            M::Sh => &self.sh_mm,
        };
        if rows.is_empty() || coeffs.len() != rows.len() {
            return None;
        }
        let mut d = [0.0; 3];
        for (r, &c) in rows.iter().zip(coeffs) {
            for a in 0..3 {
                d[a] += c as f64 * r[a];
            }
        }
        Some(d)
    }

    /// The centre's position, mm, for deformation scale `scale`, the lung's collapse `collapse`
    /// towards `hilum_mm` and rigid offset (EQUATIONS §4.1: `h + (1 − c)(p − h) + s·u + o`).
    pub fn position_mm(
        &self,
        displacement_mm: [f64; 3],
        scale: f64,
        collapse: f64,
        hilum_mm: [f64; 3],
        offset_mm: [f64; 3],
    ) -> [f64; 3] {
        [0, 1, 2].map(|a| {
            hilum_mm[a]
                + (1.0 - collapse) * (self.centre_mm[a] - hilum_mm[a])
                + scale * displacement_mm[a]
                + offset_mm[a]
        })
    }
}

/// Mean-value sums of per-vertex data times `k·d_i` (the [`TumourMeta`] rows): `out[c] = Σ_i λ_i
/// data[i·stride + c]·kd_i` for each of the `stride` columns.
pub fn weighted_rows(
    weights: &[f64],
    data: &[f32],
    stride: usize,
    kd: &[[f32; 3]],
) -> Vec<[f64; 3]> {
    let mut out = vec![[0.0f64; 3]; stride];
    for (i, (&l, kd)) in weights.iter().zip(kd).enumerate() {
        if l == 0.0 {
            continue;
        }
        for (c, o) in out.iter_mut().enumerate() {
            let v = l * data[i * stride + c] as f64;
            for a in 0..3 {
                o[a] += v * kd[a] as f64;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deform::{direction, MotionConstants};
    use crate::mesh::generate;
    use crate::operator::TransferStats;

    #[test]
    fn the_expandability_profile_by_hand() {
        let t = Tumour::new(Side::Right, [0.5; 3], [10.0, 20.0, 30.0]);
        let c = [0.0; 3];
        assert_eq!(t.expandability_at([0.0; 3], c), 0.1);
        assert_eq!(t.expandability_at([10.0, 0.0, 0.0], c), 0.1); // ρ = 1: inside
                                                                  // ρ = 1.5, falloff 1: t = 0.5, smoothstep 0.5 → a = 1 − 0.9·0.5 = 0.55.
        assert!((t.expandability_at([0.0, 30.0, 0.0], c) - 0.55).abs() < 1e-12);
        // ρ = 1.25: t = 0.25, 1 − t²(3 − 2t) = 1 − 0.0625·2.5 = 0.84375 → a = 1 − 0.9·0.84375 = 0.240625.
        assert!((t.expandability_at([0.0, 0.0, 37.5], c) - 0.240_625).abs() < 1e-12);
        assert_eq!(t.expandability_at([0.0, 0.0, 60.0], c), 1.0); // ρ = 2
                                                                  // V = 4/3·π·10·20·30 mm³ = 25132.74 mm³ = 25.13274 ml.
        assert!((t.volume_ml() - 25.132_74).abs() < 1e-5);
    }

    /// Three nodes on a line 10 mm apart; row 0 = (0: 0.5, 1: 0.3, 2: 0.2), row 1 = (0: 0.4, 1: 0.6),
    /// row 2 = (2: 0.7, 0: 0.3). Largest row distances 20, 10, 20 → reach 50/3 = 16.6667 mm.
    fn line() -> (Vec<[f32; 3]>, Vec<u64>, Vec<u32>, Vec<f32>) {
        (
            vec![[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [20.0, 0.0, 0.0]],
            vec![0, 3, 5, 7],
            vec![0, 1, 2, 0, 1, 2, 0],
            vec![0.5, 0.3, 0.2, 0.4, 0.6, 0.7, 0.3],
        )
    }

    #[test]
    fn the_kernel_change_by_hand() {
        let (p, rp, cols, vals) = line();
        let reach = kernel_reach_mm(&p, &rp, &cols).unwrap();
        assert!((reach - 50.0 / 3.0).abs() < 1e-12);
        // Node 0 in the tumour (a = 0.1), B = 0.25, φ = 0.
        let a = [0.1, 1.0, 1.0];
        let mut out = vec![0.0f32; vals.len()];
        let ch = modify_rows(&p, &rp, &cols, &vals, &a, &[0.0; 3], 0.25, reach, &mut out).unwrap();
        // (0→0): e = 0: unchanged.
        assert_eq!(out[0], 0.5);
        // (0→1): d = 10/16.6667 = 0.6, e = 0.1 − 1 = −0.9, d' = 0.6 − 0.225 = 0.375, g = 0.6/0.375
        //        = 1.6 → 0.48 (the tumour node's force reaches its normal neighbour more).
        assert!((out[1] - 0.48).abs() < 1e-6);
        // (0→2): d = 1.2, d' = 0.975, g = 1.230769 → 0.246154.
        assert!((out[2] - 0.246_154).abs() < 1e-6);
        // (1→0): e = +0.9, d' = 0.825, g = 0.727273 → 0.290909 (the tumour node receives less).
        assert!((out[3] - 0.290_909).abs() < 1e-6);
        assert_eq!((out[4], out[5]), (0.6, 0.7));
        assert_eq!((ch.entries, ch.changed, ch.clamped), (7, 4, 0));
        // B = 1: (0→1) d' = 0.6 − 0.9 = −0.3 ≤ 0 → clamped to 1/(4π): g = 4π·0.6 = 7.539822.
        let ch = modify_rows(&p, &rp, &cols, &vals, &a, &[0.0; 3], 1.0, reach, &mut out).unwrap();
        assert!((out[1] as f64 - 0.3 * 7.539_822).abs() < 1e-5);
        // Only (0→1) leaves the domain: (0→2) has d' = 1.2 − 0.9 = 0.3 ≥ 1/(4π) = 0.0796, and (1→0),
        // (2→0) have e = +0.9.
        assert_eq!((ch.clamped, ch.nonpositive), (1, 1));
    }

    #[test]
    fn the_phi_variant_by_hand() {
        let (p, rp, cols, vals) = line();
        let reach = 50.0 / 3.0;
        let mut out = vec![0.0f32; vals.len()];
        // φ = 0.5 at node 1 only, no tumour: (0→1) has x = 1/(4π·0.6) = 0.132629,
        // g = (x·cos 0.5 + √(1 − x²)·sin 0.5)/x = 0.877583 + 0.991166·0.479426/0.132629 = 4.460432.
        modify_rows(
            &p,
            &rp,
            &cols,
            &vals,
            &[1.0; 3],
            &[0.0, 0.5, 0.0],
            0.25,
            reach,
            &mut out,
        )
        .unwrap();
        assert!((out[1] as f64 - 0.3 * 4.460_432).abs() < 1e-5);
        // (1→1): d = 0 → clamped x = 1 on both sides: g = cos 0.5 = 0.877583.
        assert!((out[4] as f64 - 0.6 * 0.877_583).abs() < 1e-6);
        assert_eq!(out[0], 0.5);
    }

    #[test]
    fn no_tumour_and_no_phi_leave_the_kernel_bit_for_bit() {
        let (p, rp, cols, vals) = line();
        let mut out = vec![0.0f32; vals.len()];
        let ch = modify_rows(
            &p, &rp, &cols, &vals, &[1.0; 3], &[0.0; 3], 0.25, 16.0, &mut out,
        )
        .unwrap();
        assert_eq!(out, vals);
        assert_eq!(ch.changed, 0);
        // Shapes that do not fit are typed errors.
        assert!(modify_rows(
            &p,
            &rp[..3],
            &cols,
            &vals,
            &[1.0; 3],
            &[0.0; 3],
            0.25,
            16.0,
            &mut out
        )
        .is_err());
        assert!(
            modify_rows(&p, &rp, &cols, &vals, &[1.0; 2], &[0.0; 3], 0.25, 16.0, &mut out).is_err()
        );
        assert!(modify_rows(
            &p,
            &rp,
            &cols,
            &vals,
            &[f64::NAN; 3],
            &[0.0; 3],
            0.25,
            16.0,
            &mut out
        )
        .is_err());
        assert!(
            modify_rows(&p, &rp, &cols, &vals, &[1.0; 3], &[0.0; 3], -1.0, 16.0, &mut out).is_err()
        );
        assert!(kernel_reach_mm(&p, &[0, 1, 2, 3], &[0, 1, 2]).is_err());
    }

    #[test]
    fn eq_8_21_scales_reproduce_the_target() {
        let (_, rp, cols, vals) = line();
        let f = [1.0, 2.0, 0.0];
        // Column sums Σ_J f[J]·K(J,I): I=0: 1·0.5 + 2·0.4 = 1.3; I=1: 1·0.3 + 2·0.6 = 1.5; I=2: 0.2.
        let mut s = [0.0; 3];
        let singular = column_scales_8_21(&rp, &cols, &vals, &f, &[2.6, 3.0, 0.1], &mut s).unwrap();
        assert_eq!(singular, 0);
        assert!(
            (s[0] - 2.0).abs() < 1e-6 && (s[1] - 2.0).abs() < 1e-6 && (s[2] - 0.5).abs() < 1e-6
        );
        let singular = column_scales_8_21(&rp, &cols, &vals, &[0.0; 3], &[1.0; 3], &mut s).unwrap();
        assert_eq!((singular, s), (3, [1.0; 3]));
    }

    #[test]
    fn mean_value_coordinates_reproduce_affine_fields_inside_a_lung() {
        let mesh = generate::lung(Side::Left, 3000).unwrap();
        let affine = |p: [f64; 3]| {
            [
                2.0 + 0.3 * p[0] - 0.1 * p[1] + 0.05 * p[2],
                -1.0 + 0.2 * p[1],
                0.7 * p[0] - 0.4 * p[2],
            ]
        };
        let field: Vec<[f32; 3]> = mesh
            .positions
            .iter()
            .map(|p| affine(p.map(|v| v as f64)).map(|v| v as f32))
            .collect();
        let t = Tumour::new(Side::Left, [0.5, 0.5, 0.5], [10.0; 3]);
        for centre in [[0.5, 0.5, 0.5], [0.6, 0.3, 0.8], [0.5, 0.6, 0.2]] {
            let c = Tumour { centre, ..t }.centre_mm(&mesh);
            assert!((winding_number(&mesh, c) - 1.0).abs() < 1e-9);
            let track = TumourTrack::new(&mesh, &field, c).unwrap();
            let want = affine(c);
            for (got, want) in track.unit_displacement_mm.iter().zip(want) {
                assert!(
                    (got - want).abs() < 1e-4 * (1.0 + want.abs()),
                    "{centre:?}: {got} vs {want}"
                );
            }
        }
        let bb = mesh.aabb();
        let outside = [bb.max[0] as f64 + 50.0, 0.0, 0.0];
        assert!(winding_number(&mesh, outside).abs() < 1e-9);
    }

    #[test]
    fn trajectory_and_amplitude_by_hand() {
        let track = TumourTrack {
            centre_mm: [1.0, 2.0, 3.0],
            unit_displacement_mm: [0.1, -0.2, 0.5],
        };
        let scales = [0.0, 10.0, 20.0, 5.0];
        let mut out = Vec::with_capacity(4);
        track.trajectory_into(&scales, &mut out);
        assert_eq!(out[2], [1.0 + 2.0, 2.0 - 4.0, 3.0 + 10.0]);
        // Amplitude = |u|·(20 − 0): (2, 4, 10) mm.
        assert_eq!(track.amplitude_mm(&scales), [2.0, 4.0, 10.0]);
        assert_eq!(track.amplitude_mm(&[]), [0.0; 3]);
    }

    /// A synthetic kernel on `mesh`: each vertex keeps 0.4 and gives 0.6 to its one-ring, shared by
    /// inverse distance (stands in for a baked pass in this crate, which has no pass).
    fn ring_kernel(mesh: &TriMesh) -> Transfer {
        let n = mesh.positions.len();
        let mut nb: Vec<Vec<u32>> = vec![Vec::new(); n];
        for t in &mesh.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if !nb[a as usize].contains(&b) {
                    nb[a as usize].push(b);
                    nb[b as usize].push(a);
                }
            }
        }
        let (mut row_ptr, mut cols, mut vals) = (vec![0u64], Vec::new(), Vec::new());
        for (j, ring) in nb.iter_mut().enumerate() {
            ring.sort_unstable();
            let w: Vec<f64> = ring
                .iter()
                .map(|&i| 1.0 / dist(&mesh.positions, j, i as usize))
                .collect();
            let total: f64 = w.iter().sum();
            cols.push(j as u32);
            vals.push(0.4f32);
            for (&i, wi) in ring.iter().zip(&w) {
                cols.push(i);
                vals.push((0.6 * wi / total) as f32);
            }
            row_ptr.push(cols.len() as u64);
        }
        Transfer {
            n,
            row_ptr,
            cols,
            vals,
            stats: TransferStats::default(),
        }
    }

    fn lung_inputs(side: Side) -> (TriMesh, Transfer, Vec<[f32; 3]>, Vec<f32>) {
        let mesh = generate::lung(side, 3000).unwrap();
        let k = MotionConstants::table_6_1(side);
        let bb = mesh.aabb();
        let dirs = mesh
            .positions
            .iter()
            .map(|&p| {
                direction(normalised_position(p, &bb, side), &k, side)
                    .as_vec3()
                    .to_array()
            })
            .collect();
        let f = mesh
            .positions
            .iter()
            .map(|&p| crate::deform::applied_force(normalised_position(p, &bb, side), &k) as f32)
            .collect();
        let t = ring_kernel(&mesh);
        (mesh, t, dirs, f)
    }

    #[test]
    fn a_tumour_stiffens_its_region_and_the_lower_lobe_moves_most() {
        let side = Side::Right;
        let (mesh, t, dirs, f) = lung_inputs(side);
        // A lateral tumour near the base touching the costal surface, 25 mm radius.
        let tumour = Tumour::new(side, [0.75, 0.5, 0.75], [25.0; 3]);
        let lung = tumour_lung(&tumour, mesh.clone(), &t, &dirs, &f).unwrap();
        assert!(lung.vertices_affected > 0 && lung.change.changed > 0);
        // Vertices inside the tumour move less relative to the lung than before.
        let normal = LungModel::from_force_and_directions(
            side,
            mesh.clone(),
            dirs.iter()
                .map(|d| DVec3::from(d.map(|v| v as f64)))
                .collect(),
            &t.elastostatic(&f.iter().map(|&v| v as f64).collect::<Vec<_>>()),
        )
        .unwrap()
        .0;
        let mag = |u: &[f32; 3]| (u[0] as f64).hypot(u[1] as f64).hypot(u[2] as f64);
        let mean = |m: &LungModel, inside: bool| {
            let v: Vec<f64> = m
                .unit_displacement
                .iter()
                .zip(&lung.expandability)
                .filter(|(_, &a)| (a < 0.2) == inside)
                .map(|(u, _)| mag(u))
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        let ratio_n = mean(&normal, true) / mean(&normal, false);
        let mut ratios = vec![ratio_n, mean(&lung.model, true) / mean(&lung.model, false)];
        for coupling in [0.5, 1.0, 2.0] {
            let l =
                tumour_lung(&Tumour { coupling, ..tumour }, mesh.clone(), &t, &dirs, &f).unwrap();
            ratios.push(mean(&l.model, true) / mean(&l.model, false));
        }
        // Measured (EQUATIONS §4.4): normal 0.8795; B = 0.25, 0.5, 1, 2: 0.8764, 0.8736, 0.8682, 0.8580
        // — the tumour region moves less, more so with B, but only through its boundary (e = 0 inside).
        eprintln!("tumour region / rest, mean unit displacement: normal, B = 0.25, 0.5, 1, 2: {ratios:.4?}");
        assert!(ratios.windows(2).all(|w| w[1] < w[0]), "{ratios:?}");
        // Same unit volume either way (the lung still breathes its tidal volume).
        assert!(
            (lung.model.cubic.volume(1.0)
                - lung.model.cubic.coeffs[0]
                - crate::deform::UNIT_VOLUME_ML * 1000.0)
                .abs()
                < 1e-6 * 1000.0
        );
        // A lower-lobe tumour moves more along Z than an upper-lobe one (clinically: lower-lobe
        // tumours move most), both finite.
        let upper = Tumour::new(side, [0.5, 0.5, 0.2], [15.0; 3]);
        let lower = Tumour::new(side, [0.5, 0.5, 0.8], [15.0; 3]);
        let scales: Vec<f64> = (0..=100).map(|k| k as f64 * 1.5).collect();
        let amp = |tm: &Tumour| {
            let l = tumour_lung(tm, mesh.clone(), &t, &dirs, &f).unwrap();
            l.track.amplitude_mm(&scales)
        };
        let (au, al) = (amp(&upper), amp(&lower));
        eprintln!("amplitude upper {au:?} mm, lower {al:?} mm (s from 0 to 150)");
        assert!(al[2] > au[2] && au.iter().chain(&al).all(|v| v.is_finite()));
    }

    #[test]
    fn a_tumour_free_kernel_gives_the_normal_field_bit_for_bit() {
        let side = Side::Left;
        let (mesh, t, dirs, f) = lung_inputs(side);
        // Expandability 1 inside: no change anywhere.
        let tumour = Tumour {
            expandability: 1.0,
            ..Tumour::new(side, [0.5, 0.5, 0.5], [20.0; 3])
        };
        let lung = tumour_lung(&tumour, mesh, &t, &dirs, &f).unwrap();
        assert_eq!(lung.change.changed, 0);
        assert_eq!(lung.track, lung.normal_track);
    }

    #[test]
    fn a_centre_outside_the_lung_and_bad_keys_are_named_errors() {
        let side = Side::Left;
        let (mesh, t, dirs, f) = lung_inputs(side);
        // The box corner (medial, posterior, apex) is outside the rounded lung.
        let e = tumour_lung(
            &Tumour::new(side, [0.0, 0.0, 0.0], [5.0; 3]),
            mesh.clone(),
            &t,
            &dirs,
            &f,
        )
        .unwrap_err();
        assert!(
            matches!(e, DiseaseError::Tumour(TumourError::CentreOutside { .. })),
            "{e}"
        );
        for (tm, key) in [
            (Tumour::new(side, [1.5, 0.5, 0.5], [5.0; 3]), "centre"),
            (Tumour::new(side, [0.5, 0.5, 0.5], [0.0; 3]), "radii_mm"),
            (
                Tumour {
                    expandability: 0.0,
                    ..Tumour::new(side, [0.5; 3], [5.0; 3])
                },
                "expandability",
            ),
            (
                Tumour {
                    falloff: -1.0,
                    ..Tumour::new(side, [0.5; 3], [5.0; 3])
                },
                "falloff",
            ),
            (
                Tumour {
                    coupling: f64::NAN,
                    ..Tumour::new(side, [0.5; 3], [5.0; 3])
                },
                "coupling",
            ),
            (
                Tumour {
                    resistance_phi: 2.0,
                    ..Tumour::new(side, [0.5; 3], [5.0; 3])
                },
                "resistance_phi",
            ),
        ] {
            let e = tumour_lung(&tm, mesh.clone(), &t, &dirs, &f)
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{key}: {e}");
        }
        let e = tumour_lung(
            &Tumour::new(side, [0.5; 3], [5.0; 3]),
            mesh,
            &t,
            &dirs[1..],
            &f,
        )
        .unwrap_err();
        assert!(e.to_string().contains("directions"), "{e}");
    }

    #[test]
    fn raised_resistance_uses_eq_8_9_on_both_phases_by_the_tumour_volume() {
        let p = crate::pv::preset("subject-1").unwrap();
        let t = Tumour::new(Side::Right, [0.5; 3], [20.0; 3]);
        // V_t = 4/3·π·8000 mm³ = 33.5103 ml; x = 0.1·33.5103/1300 = 0.00257772.
        let (i, e, r) = t.resistance(&p.inhale, &p.exhale, 1300.0).unwrap();
        assert!((r[0].x - 0.002_577_72).abs() < 1e-8);
        // χ_2: 1.2·ln(1.2·0.00257772)/ln(2·0.00257772) = 1.2·(−5.778530)/(−5.267704) = 1.316368.
        assert!((i.chi[1] - 1.316_368).abs() < 1e-5, "{}", i.chi[1]);
        assert_eq!(i.chi, e.chi);
        // φ_r = 0: the normal constants.
        let (i, _, _) = Tumour {
            resistance_phi: 0.0,
            ..t
        }
        .resistance(&p.inhale, &p.exhale, 1300.0)
        .unwrap();
        assert_eq!(i, p.inhale);
    }

    #[test]
    fn phi_variants_follow_the_posterior_distance() {
        let mesh = generate::lung(Side::Right, 1000).unwrap();
        let d = phi_values(&mesh, Side::Right, PhiVariant::Distance);
        let d2 = phi_values(&mesh, Side::Right, PhiVariant::DistanceSquared);
        let z = phi_values(&mesh, Side::Right, PhiVariant::None);
        let bb = mesh.aabb();
        for k in 0..mesh.positions.len() {
            let y = (mesh.positions[k][1] - bb.min[1]) as f64 / (bb.max[1] - bb.min[1]) as f64;
            assert!((d[k] - y).abs() < 1e-6 && (d2[k] - y * y).abs() < 1e-6 && z[k] == 0.0);
        }
    }
}
