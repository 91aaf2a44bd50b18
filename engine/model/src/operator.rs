//! # operator: the Green's-function transfer operator as the run time holds it (seed eq. 6.1, 7.1)
//!
//! The transfer (Green's function) matrix `T` of eq. 6.1 — row `j` = the mass-node catchers of a unit
//! force on node `j` after the pitcher–catcher pass (eq. 6.11–6.13) — stored as compressed sparse rows
//! ([`Transfer`]), its transpose for gathering eq. 7.1 per node ([`Columns::apply_into`]), the
//! regional [`Elasticity`] field that shaped it, and the figures of its computation
//! ([`TransferStats`]). Building `T` (node graph, eq. 6.7, the pass itself) is bake time and lives
//! in `lung-bake`'s `operator`.

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::{Elasticity, ElasticityError, MODULUS_RANGE};

use glam::DVec3;
use rayon::prelude::*;

/// Relative Young's modulus of `e` at normalised position `n` (eq. 6.14–6.16's ẑ and ŷ; the field's
/// form is [`Elasticity`]'s).
pub fn youngs_modulus(e: &Elasticity, n: DVec3) -> f64 {
    (e.apex + (e.base - e.apex) * n.z) * (1.0 - e.dependent * (1.0 - n.y))
}

/// Order in which pitchers are emptied. Both run eq. 6.11–6.13 to the same fixed point; they differ
/// only in the order of pitches and hence in what is left below the tolerance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Schedule {
    /// The seed's order: always the node (mass or spring) with the largest pitcher.
    LargestFirst,
    /// Mass nodes only in the queue, keyed by their pitcher when queued (one entry per node, not one
    /// per increase); a spring node (exactly two neighbours, no displayed catcher of its own) is
    /// pitched the moment it receives force. Far fewer heap operations; the default
    /// (EQUATIONS.md §2.3, "Changed (lungdyn)").
    SpringsForward,
}

/// Figures of a transfer computation.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct TransferStats {
    /// Pitcher tolerance (absolute, for a unit applied force).
    pub tolerance: f64,
    /// Order of pitches.
    pub schedule: Option<Schedule>,
    /// Mean non-zeros (mass nodes) per row.
    pub mean_row_nnz: f64,
    /// Largest row.
    pub max_row_nnz: u64,
    /// Mean share of a row's unit force caught by mass nodes.
    pub mass_caught_mean: f64,
    /// Mean share caught by spring nodes.
    pub spring_caught_mean: f64,
    /// Mean truncated force per row (left in pitchers below the tolerance).
    pub truncated_force_mean: f64,
    /// Largest truncated force of any row.
    pub truncated_force_max: f64,
    /// Largest |caught + truncated − applied| of any row.
    pub conservation_error_max: f64,
    /// Mean pitches per row.
    pub mean_pitches: f64,
}

/// The transfer (Green's function) matrix: row `j` = mass-node catchers of a unit force on `j`,
/// compressed sparse rows, f32 values (what is stored and evaluated).
#[derive(Debug, Clone, PartialEq)]
pub struct Transfer {
    /// Mass nodes (rows = columns).
    pub n: usize,
    /// Row offsets, `n + 1` entries.
    pub row_ptr: Vec<u64>,
    /// Column (mass node) of each non-zero.
    pub cols: Vec<u32>,
    /// `T[j→i]` of each non-zero.
    pub vals: Vec<f32>,
    /// Figures of the computation.
    pub stats: TransferStats,
}

impl Transfer {
    /// Row `j`: (columns, values).
    pub fn row(&self, j: usize) -> (&[u32], &[f32]) {
        let r = self.row_ptr[j] as usize..self.row_ptr[j + 1] as usize;
        (&self.cols[r.clone()], &self.vals[r])
    }

    /// Number of stored non-zeros.
    pub fn nnz(&self) -> usize {
        self.cols.len()
    }

    /// Elastostatic force of eq. 6.1, `F[i] = Σ_j f[j]·T[j→i]`, in f64 (bake time).
    pub fn elastostatic(&self, f: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.n];
        for (j, &fj) in f.iter().enumerate().take(self.n) {
            if fj == 0.0 {
                continue;
            }
            let (c, v) = self.row(j);
            for (&i, &t) in c.iter().zip(v) {
                out[i as usize] += fj * t as f64;
            }
        }
        out
    }

    /// The transpose as CSR (row `i` lists `T[j→i]` over `j`), for gathering eq. 7.1 per node.
    pub fn transposed(&self) -> Columns {
        let mut ptr = vec![0u64; self.n + 1];
        for &c in &self.cols {
            ptr[c as usize + 1] += 1;
        }
        for i in 0..self.n {
            ptr[i + 1] += ptr[i];
        }
        let mut fill = ptr.clone();
        let mut src = vec![0u32; self.cols.len()];
        let mut vals = vec![0f32; self.cols.len()];
        for j in 0..self.n {
            let (c, v) = self.row(j);
            for (&i, &t) in c.iter().zip(v) {
                let at = fill[i as usize] as usize;
                src[at] = j as u32;
                vals[at] = t;
                fill[i as usize] += 1;
            }
        }
        Columns { ptr, src, vals }
    }
}

/// `Tᵀ` in CSR: for each node `i`, the `(j, T[j→i])` that feed it (eq. 7.1 gathers).
#[derive(Debug, Clone, PartialEq)]
pub struct Columns {
    ptr: Vec<u64>,
    src: Vec<u32>,
    vals: Vec<f32>,
}

impl Columns {
    /// Set subnormal values to zero (see `CpuLung::new`).
    pub fn flush_subnormals(&mut self) {
        for x in self.vals.iter_mut().filter(|x| x.is_subnormal()) {
            *x = 0.0;
        }
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.ptr.len().saturating_sub(1)
    }

    /// No nodes.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Node `i`'s feeders: `(j, T[j→i])` as two slices.
    pub fn column(&self, i: usize) -> (&[u32], &[f32]) {
        let r = self.ptr[i] as usize..self.ptr[i + 1] as usize;
        (&self.src[r.clone()], &self.vals[r])
    }

    /// Raw arrays `(ptr, src, vals)` (GPU upload).
    pub fn raw(&self) -> (&[u64], &[u32], &[f32]) {
        (&self.ptr, &self.src, &self.vals)
    }

    /// Eq. 7.1, `out[i] = Σ_j f[j]·T[j→i]`, f32, parallel over nodes; no allocation.
    pub fn apply_into(&self, f: &[f32], out: &mut [f32]) {
        out.par_chunks_mut(4096).enumerate().for_each(|(c, chunk)| {
            let base = c * 4096;
            for (k, o) in chunk.iter_mut().enumerate() {
                let i = base + k;
                let r = self.ptr[i] as usize..self.ptr[i + 1] as usize;
                let mut acc = 0.0f32;
                for (&j, &t) in self.src[r.clone()].iter().zip(&self.vals[r]) {
                    acc += f[j as usize] * t;
                }
                *o = acc;
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> Transfer {
        // Three nodes: row 0 sends 0.5 to itself and 0.5 to node 2; row 1 keeps all; row 2 sends
        // 0.25 to node 0.
        Transfer {
            n: 3,
            row_ptr: vec![0, 2, 3, 4],
            cols: vec![0, 2, 1, 0],
            vals: vec![0.5, 0.5, 1.0, 0.25],
            stats: TransferStats::default(),
        }
    }

    #[test]
    fn the_gather_of_eq_7_1_equals_the_scatter_of_eq_6_1() {
        let t = tiny();
        let f = [2.0f64, 3.0, 4.0];
        let scatter = t.elastostatic(&f);
        assert_eq!(scatter, vec![2.0 * 0.5 + 4.0 * 0.25, 3.0, 2.0 * 0.5]);
        let mut gather = [0f32; 3];
        t.transposed().apply_into(&f.map(|v| v as f32), &mut gather);
        for (g, s) in gather.iter().zip(&scatter) {
            assert!((*g as f64 - s).abs() < 1e-6, "{gather:?} vs {scatter:?}");
        }
    }

    #[test]
    fn elasticity_out_of_range_is_a_typed_error() {
        assert!(Elasticity::default().validate().is_ok());
        let bad = Elasticity {
            apex: 0.0,
            ..Default::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(ElasticityError::Moduli { .. })
        ));
        let bad = Elasticity {
            dependent: 1.0,
            ..Default::default()
        };
        assert_eq!(bad.validate(), Err(ElasticityError::Dependent(1.0)));
        // A modulus of 1e308 would cancel to 0 in the apex-to-base ramp: refused by its name.
        let bad = Elasticity {
            apex: 1e308,
            ..Default::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("apex = 1e308") && e.contains("0.01–100"), "{e}");
        for ok in [MODULUS_RANGE.0, MODULUS_RANGE.1] {
            assert!(Elasticity::uniform(ok).validate().is_ok());
        }
        let e = Elasticity::default();
        assert_eq!(
            youngs_modulus(&e, DVec3::new(0.5, 1.0, 0.0)),
            4.0,
            "apex, anterior"
        );
        assert_eq!(youngs_modulus(&e, DVec3::new(0.5, 1.0, 1.0)), 1.0, "base");
    }
}
