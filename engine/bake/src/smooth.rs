//! # smooth: the elastostatic amplitude made smooth at a stated length (EQUATIONS.md §2.4)
//!
//! The pitcher–catcher pass (eq. 6.11–6.13) gives each mass node a share of whatever force reaches
//! it that depends on its own little neighbourhood: its valence, its edge lengths and (through the
//! `Dist ≥ 1 mm` clamp of eq. 6.7) the mesh resolution. So even a smooth applied force gives an
//! elastostatic force `F = Tᵀf` that is rough at the scale of the mesh, and where the base moves
//! 15 mm a few per cent of roughness turns triangles inside out. Real lung motion is smooth at the
//! centimetre scale, so the bake takes out the mesh-scale part of each node's *catch factor*
//! `κ_i = Σ_j T[j→i]` (what node `i` catches of a uniform unit force everywhere):
//!
//! `T'[j→i] = T[j→i] · a_i`, `a_i = (S κ)_i / κ_i`,
//!
//! with `S` an area-weighted Gaussian mean over the surface vertices within the smoothing length `L`
//! (Euclidean distance, `σ = L/2`, cut at `L`). A uniform applied force then gives the smoothed `κ`
//! and any force smooth over a row's reach gives `≈ (Sκ)·f`. Because only the stored transfer
//! changes (a column scaling: same sparsity, same size), every mode that derives from it — the
//! precomputed displacement, the basis responses, the SH coefficients, the direct rows and the
//! tumour (whose eq. 8.14–8.20 factors multiply entries, so they commute with the scaling) — draws
//! the same smoothed lung. `L = 0` keeps the seed's reading (`a_i = 1`).

use rayon::prelude::*;
use thiserror::Error;

use lung_model::mesh::TriMesh;

use crate::operator::Transfer;

/// Errors of the smoothing.
#[derive(Debug, Error, PartialEq)]
pub enum SmoothError {
    /// The length is negative, NaN or absurd.
    #[error("amplitude smoothing length {0} mm: must be 0 (none, the seed's reading) or a finite length up to 100 mm")]
    Length(f64),
    /// A node catches nothing (cannot happen for a transfer of eq. 6.11–6.13, whose every node keeps a share).
    #[error("node {0} catches no force (catch factor {1}); the amplitude cannot be smoothed")]
    NoCatch(usize, f64),
}

/// Check a smoothing length: 0 or finite in (0, [`lung_model::kernel::MAX_AMPLITUDE_SMOOTHING_MM`]].
pub fn check_length(length_mm: f64) -> Result<(), SmoothError> {
    if lung_model::kernel::amplitude_smoothing_ok(length_mm) {
        Ok(())
    } else {
        Err(SmoothError::Length(length_mm))
    }
}

/// Each vertex's area share (a third of its triangles' areas), mm².
pub fn vertex_areas(mesh: &TriMesh) -> Vec<f64> {
    let mut area = vec![0.0f64; mesh.positions.len()];
    for t in &mesh.triangles {
        let p = t.map(|v| glam::DVec3::from(mesh.positions[v as usize].map(|x| x as f64)));
        let a = (p[1] - p[0]).cross(p[2] - p[0]).length() / 6.0;
        for &v in t {
            area[v as usize] += a;
        }
    }
    area
}

/// `S v`: at each vertex the area-weighted Gaussian mean (`σ = L/2`, cut at `L`) of `values` over the
/// vertices within Euclidean distance `L`. `L = 0` returns the values unchanged.
pub fn surface_mean(mesh: &TriMesh, values: &[f64], length_mm: f64) -> Vec<f64> {
    if length_mm == 0.0 || mesh.positions.is_empty() {
        return values.to_vec();
    }
    let area = vertex_areas(mesh);
    let bb = mesh.aabb();
    // Cells at least `length_mm` wide (the ±1-cell search then covers the reach) and at most 128
    // per axis: a reach far below the lung's size (0.1 mm on a 250 mm lung) would otherwise ask
    // for 2500³ cells (a proptest case once took 24 GB and the OOM killer).
    let extent = (0..3)
        .map(|a| (bb.max[a] - bb.min[a]) as f64)
        .fold(0.0f64, f64::max);
    let cell = length_mm.max(extent / 128.0);
    let dims: [usize; 3] =
        [0, 1, 2].map(|a| (((bb.max[a] - bb.min[a]) as f64 / cell).floor() as usize + 1).max(1));
    let cell_of = |p: [f32; 3]| -> [usize; 3] {
        [0, 1, 2].map(|a| (((p[a] - bb.min[a]) as f64 / cell) as usize).min(dims[a] - 1))
    };
    let index = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
    // Vertices sorted by cell (counting sort).
    let ncell = dims[0] * dims[1] * dims[2];
    let mut start = vec![0usize; ncell + 1];
    let cells: Vec<usize> = mesh.positions.iter().map(|&p| index(cell_of(p))).collect();
    for &c in &cells {
        start[c + 1] += 1;
    }
    for c in 0..ncell {
        start[c + 1] += start[c];
    }
    let mut fill = start.clone();
    let mut order = vec![0u32; cells.len()];
    for (v, &c) in cells.iter().enumerate() {
        order[fill[c]] = v as u32;
        fill[c] += 1;
    }
    let inv_two_sigma2 = 1.0 / (2.0 * (length_mm / 2.0).powi(2));
    let l2 = length_mm * length_mm;
    mesh.positions
        .par_iter()
        .enumerate()
        .map(|(i, &p)| {
            let c = cell_of(p);
            let (mut num, mut den) = (0.0f64, 0.0f64);
            let range = |a: usize| c[a].saturating_sub(1)..=(c[a] + 1).min(dims[a] - 1);
            for z in range(2) {
                for y in range(1) {
                    for x in range(0) {
                        let k = index([x, y, z]);
                        for &v in &order[start[k]..start[k + 1]] {
                            let q = mesh.positions[v as usize];
                            let d2: f64 = (0..3).map(|a| ((q[a] - p[a]) as f64).powi(2)).sum();
                            if d2 <= l2 {
                                let w = area[v as usize] * (-d2 * inv_two_sigma2).exp();
                                num += w * values[v as usize];
                                den += w;
                            }
                        }
                    }
                }
            }
            // The vertex itself is always within reach; a mesh of zero-area triangles has den = 0.
            if den > 0.0 {
                num / den
            } else {
                values[i]
            }
        })
        .collect()
}

/// Each node's catch factor `κ_i = Σ_j T[j→i]`.
pub fn catch_factor(transfer: &Transfer) -> Vec<f64> {
    transfer.elastostatic(&vec![1.0; transfer.n])
}

/// Scale the transfer's columns so each node's catch factor becomes its surface mean over
/// `length_mm` (module doc); returns the factors `a_i` applied (all 1 for `length_mm = 0`).
pub fn smooth_amplitude(
    transfer: &mut Transfer,
    mesh: &TriMesh,
    length_mm: f64,
) -> Result<Vec<f64>, SmoothError> {
    check_length(length_mm)?;
    if length_mm == 0.0 {
        return Ok(vec![1.0; transfer.n]);
    }
    let kappa = catch_factor(transfer);
    if let Some((i, &k)) = kappa.iter().enumerate().find(|(_, &k)| !(k > 0.0)) {
        return Err(SmoothError::NoCatch(i, k));
    }
    let smooth = surface_mean(mesh, &kappa, length_mm);
    let a: Vec<f64> = smooth.iter().zip(&kappa).map(|(s, k)| s / k).collect();
    for (v, &c) in transfer.vals.iter_mut().zip(&transfer.cols) {
        *v = (*v as f64 * a[c as usize]) as f32;
    }
    Ok(a)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::operator::{compute_transfer, NodeGraph, Schedule};
    use lung_model::deform::normalised_position;
    use lung_model::mesh::{generate, Side};
    use lung_model::operator::Elasticity;
    use proptest::prelude::*;

    fn transfer_of(mesh: &TriMesh) -> Transfer {
        let bb = mesh.aabb();
        let g = NodeGraph::from_mesh(mesh, &Elasticity::default(), |p| {
            normalised_position(p, &bb, Side::Left)
        })
        .unwrap();
        compute_transfer(&g, 1e-5, Schedule::SpringsForward, &|_| {}).unwrap()
    }

    /// A reach far below the lung's size keeps the search grid bounded (once 2500³ cells): the
    /// mean is then each vertex's own value where no neighbour is that close.
    #[test]
    fn a_tiny_reach_stays_bounded_and_is_a_mean() {
        let mesh = generate::lung(Side::Right, 2000).unwrap();
        let v: Vec<f64> = (0..mesh.positions.len()).map(|i| (i % 7) as f64).collect();
        let m = surface_mean(&mesh, &v, 1e-3);
        assert_eq!(m.len(), v.len());
        assert!(m.iter().zip(&v).all(|(a, b)| (a - b).abs() < 1e-12));
    }

    #[test]
    fn bad_lengths_are_refused_and_zero_keeps_the_seed_reading() {
        for l in [-1.0, f64::NAN, f64::INFINITY, 100.5, -1e-300] {
            assert!(check_length(l).is_err(), "{l}");
        }
        let mesh = generate::lung(Side::Left, 600).unwrap();
        let t = transfer_of(&mesh);
        let mut same = t.clone();
        assert!(smooth_amplitude(&mut same, &mesh, 0.0)
            .unwrap()
            .iter()
            .all(|&a| a == 1.0));
        assert_eq!(same, t, "bit for bit");
        let mut bad = t.clone();
        assert!(smooth_amplitude(&mut bad, &mesh, f64::NAN).is_err());
        assert_eq!(bad, t, "nothing changed on a refusal");
    }

    /// After smoothing, each node's catch factor is the surface mean of the old one (the module's
    /// definition), it varies less between neighbours, and its area-weighted total is kept within
    /// the edge effect of the mean.
    #[test]
    fn the_catch_factor_becomes_its_surface_mean() {
        // (mean jump along an edge: the large-scale trend of `E` is kept, the mesh-scale part goes)
        let mesh = generate::lung(Side::Left, 2_000).unwrap();
        let mut t = transfer_of(&mesh);
        let before = catch_factor(&t);
        let want = surface_mean(&mesh, &before, 10.0);
        let a = smooth_amplitude(&mut t, &mesh, 10.0).unwrap();
        let after = catch_factor(&t);
        for i in 0..after.len() {
            assert!((after[i] - want[i]).abs() <= 1e-5 * want[i], "node {i}");
            assert!(a[i].is_finite() && a[i] > 0.0);
        }
        let edges = crate::operator::mesh_edges(&mesh);
        let jump = |k: &[f64]| {
            edges
                .iter()
                .map(|e| (k[e[0] as usize] - k[e[1] as usize]).abs())
                .sum::<f64>()
                / edges.len() as f64
        };
        assert!(
            jump(&after) < 0.5 * jump(&before),
            "{} vs {}",
            jump(&after),
            jump(&before)
        );
        let area = vertex_areas(&mesh);
        let total = |k: &[f64]| k.iter().zip(&area).map(|(k, a)| k * a).sum::<f64>();
        assert!((total(&after) / total(&before) - 1.0).abs() < 0.02);
    }

    proptest! {
        /// A surface mean is a weighted mean: constants stay, and every value stays within the
        /// range of the input, for any length.
        #[test]
        fn a_surface_mean_is_a_mean(c in -1e6f64..1e6, length in 0.1f64..100.0, seed in 0u64..1000) {
            let mesh = generate::lung(Side::Right, 300).unwrap();
            let flat = surface_mean(&mesh, &vec![c; mesh.positions.len()], length);
            prop_assert!(flat.iter().all(|v| (v - c).abs() <= 1e-9 * c.abs().max(1.0)));
            let v: Vec<f64> = (0..mesh.positions.len())
                .map(|i| ((i as u64 * 2654435761 + seed) % 1000) as f64)
                .collect();
            let (lo, hi) = (v.iter().cloned().fold(f64::MAX, f64::min), v.iter().cloned().fold(f64::MIN, f64::max));
            for m in surface_mean(&mesh, &v, length) {
                prop_assert!(m >= lo - 1e-9 && m <= hi + 1e-9);
            }
        }
    }
}
