//! # Bake-time tumour kernel change (seed §8.2, eq. 8.14–8.22)
//!
//! What [`crate::kernel::bake`] does to a lung's transfer rows when the scene has a tumour: eq.
//! 8.14–8.20, 8.22 on the kernel in CSR ([`modify_rows`], normalised by the kernel's reach
//! [`kernel_reach_mm`]), the `φ_I` variants of Fig. 8.6 ([`phi_values`]), eq. 8.21's column scales
//! for data that have displacements ([`column_scales_8_21`]), and the mean-value sums the kernel
//! records for the centre's motion ([`weighted_rows`]). The tumour itself (its parameters, its
//! expandability profile, its resistance, where its centre is and how it moves) is the run time's
//! ([`lung_model::disease::tumour`]), and the modelling decisions are written there and in
//! EQUATIONS.md §4.4.

use lung_model::deform::normalised_position;
use lung_model::disease::tumour::{PhiVariant, TumourError};
use lung_model::disease::{check_range, DiseaseError};
use lung_model::mesh::{Side, TriMesh};

/// `1/(4π)`: the smallest normalised distance in the acos domain of eq. 8.17–8.18.
pub const D_MIN: f64 = 1.0 / (4.0 * std::f64::consts::PI);

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
    use lung_model::mesh::generate;

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
