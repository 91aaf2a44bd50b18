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
//!   from the row's node to a catcher (`lung_bake::tumour::kernel_reach_mm`). The straight distance stands for the seed's
//!   "piecewise Euclidean" path length (rows are local: a few edges).
//! * **Structural constants** `A_I = 1`, `B_I = B` ([`Tumour::coupling`], default 0.25 reach per unit of
//!   expandability): the seed's two-kernel solve fixes only the ratio `A_I/B_I`, and with `A = 1` a
//!   tumour-free lung (`e = 0`) keeps `d' = d`.
//! * **acos domain:** `1/(4πd') ≤ 1` needs `d' ≥ 1/(4π)`; `d'` (and `d`: the diagonal has `d = 0`) is
//!   clamped to `1/(4π)`, counted (`lung_bake::tumour::RowChange::clamped`) and, where `B·e` made it `≤ 0`, counted again
//!   (`RowChange::nonpositive`).
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
//!   `lung_bake::tumour::column_scales_8_21` provides it for data that have them; a synthetic tumour keeps the baked
//!   `C_I` (refitting to the normal lung's displacements would undo the tumour).
//! * **Resistance:** eq. 8.9 on both phases ([`super::resistance::TUMOUR`]) with
//!   `x = φ_r·min(1, V_tumour/V_lung)` ([`Tumour::resistance_phi`], default the seed's 0.1).
//! * **Centroid trajectory:** the tumour moves with the lung; its centre's displacement is the
//!   mean-value interpolation (Ju, Schaefer & Warren, SIGGRAPH 2005) of the surface's unit
//!   displacement, exact for affine motion, so the centre moves `s·ū` at deformation scale `s`.

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::disease::PhiVariant;

use glam::DVec3;
use thiserror::Error;

use super::resistance::{self, ResistanceReport};
use super::{check_range, DiseaseError};
use crate::mesh::{Side, TriMesh};
use crate::pv::PhaseConstants;

/// Default expandability inside the tumour (relative to 1 in normal lung).
pub const EXPANDABILITY: f64 = 0.1;
/// Default falloff width, in radii.
pub const FALLOFF: f64 = 1.0;
/// Default structural constant `B` (kernel reaches per unit of expandability).
pub const COUPLING: f64 = 0.25;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

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
}
