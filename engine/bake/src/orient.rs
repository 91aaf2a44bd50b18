//! # orient: what the orientation-following modes need, baked (seed ch. 7, EQUATIONS.md §3)
//!
//! * **Basis responses** `G_a = Tᵀ·x̂_a` for `x̂_0 = 1, x̂, ŷ, ẑ` (EQUATIONS.md §3.3): the operator is
//!   linear, so the elastostatic force of any applied force `f = w0 + w·(x̂, ŷ, ẑ)` is
//!   `D = Σ_a w_a·G_a` exactly ([`Responses`]).
//! * **Volume forms** of each mode's displacement field in the weights
//!   ([`lung_model::deform::modes::VolumeForms`]): the run time solves the volume cubic for any
//!   orientation with 84 multiply-adds.
//! * **Spherical harmonics** (eq. 7.2–7.7, [`ShProjection`]): nodes seen from the mesh's volume
//!   centroid (the seed's "centroid of the lung model", §7.4), quadrature weights of their share of
//!   the sphere, fold-overs detected ([`lung_model::sh`]); per node `T^I_lm = Σ_J T(J, I)·Y_lm(J)`;
//!   the force projection `P_a,lm = Σ_J w_J·x̂_a(J)·Y_lm(J)`, so `F_lm = Σ_a w_a·P_a,lm`; and `α` by
//!   least squares against eq. 7.1 over the orientation set ([`ShProjection::fit`]).
//! * **Errors** are displacements in mm at the reference volume ([`reference_delta_ml`]), each mode's
//!   scale solved from its own forms (what the renderer draws), against eq. 7.1 in f64, over
//!   [`orientation_set`]: 6 cardinal postures and 20 seeded random ones.

use glam::DVec3;
use rayon::prelude::*;
use thiserror::Error;

use lung_model::deform::modes::{ShCoeffs, ShCoeffsError, VolumeForms};
use lung_model::deform::normalised_position;
use lung_model::mesh::{Side, TriMesh};
use lung_model::operator::{Columns, Transfer};
use lung_model::orientation::{
    exact_weights, fitted_weights, ForceWeights, VolumeLimit, DEFAULT_MIN_SLOPE_RATIO,
    SUPINE_GRAVITY,
};
use lung_model::sh;

/// Volume change above FRC at which errors are reported: a tidal breath's share of one lung
/// (about half of 500 ml), at most a quarter of the lung's own volume (tiny test meshes).
pub const REFERENCE_DELTA_ML: f64 = 250.0;

/// The reference volume change for a lung of `start_volume_ml`.
pub fn reference_delta_ml(start_volume_ml: f64) -> f64 {
    REFERENCE_DELTA_ML.min(0.25 * start_volume_ml)
}

/// Seed of the random orientations.
pub const ORIENTATION_SEED: u64 = 7;

/// Gravity directions (body frame, unit) errors are taken over: supine, prone, both lateral
/// decubitus postures, upright and head-down, then 20 uniformly random ones (SplitMix64,
/// [`ORIENTATION_SEED`]).
pub fn orientation_set() -> Vec<DVec3> {
    let mut out = vec![
        SUPINE_GRAVITY,
        -SUPINE_GRAVITY,
        DVec3::X,
        -DVec3::X,
        -DVec3::Z,
        DVec3::Z,
    ];
    let mut state = ORIENTATION_SEED;
    let mut next = || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    while out.len() < 26 {
        let v = DVec3::new(2.0 * next() - 1.0, 2.0 * next() - 1.0, 2.0 * next() - 1.0);
        let l = v.length();
        if l > 0.05 && l <= 1.0 {
            out.push(v / l);
        }
    }
    out
}

/// The basis responses of one lung and what they are combined with.
#[derive(Debug, Clone)]
pub struct Responses {
    /// `(1, x̂, ŷ, ẑ)` per node.
    pub nhat: Vec<[f64; 4]>,
    /// `(G_0, G_x, G_y, G_z)` per node (f64).
    pub g: Vec<[f64; 4]>,
    /// `k·d_i` per node, from the stored f32 directions (what the run time multiplies).
    pub kd: Vec<DVec3>,
    /// Table 6.1-style `(c7, c8, c9)`.
    pub c789: [f64; 3],
    /// Lung.
    pub side: Side,
    /// The volume limit on the weights (set from the exact forms, [`Self::set_limit`]).
    pub limit: Option<VolumeLimit>,
    /// The first basis function is the lung's fitted supine force, not 1
    /// ([`lung_model::orientation::Orientation::with_fitted_supine`]).
    pub fitted: bool,
}

impl Responses {
    /// `G_a = Tᵀ·x̂_a` for a lung with stored directions `directions` and force scale `k`. With
    /// `fitted_supine` (the lung's fitted supine force per vertex,
    /// [`lung_model::deform::fitted_supine_force`]) the first basis function is that force instead of
    /// 1, so the weights [`lung_model::orientation::FITTED_SUPINE`] draw it exactly (EQUATIONS.md §3.3).
    pub fn compute(
        mesh: &TriMesh,
        side: Side,
        transfer: &Transfer,
        directions: &[[f32; 3]],
        k: f64,
        c789: [f64; 3],
        fitted_supine: Option<&[f64]>,
    ) -> Self {
        let bb = mesh.aabb();
        let nhat: Vec<[f64; 4]> = mesh
            .positions
            .iter()
            .enumerate()
            .map(|(i, &p)| {
                let n = normalised_position(p, &bb, side);
                [fitted_supine.map_or(1.0, |f| f[i]), n.x, n.y, n.z]
            })
            .collect();
        let per_axis: Vec<Vec<f64>> = (0..4)
            .into_par_iter()
            .map(|a| {
                let f: Vec<f64> = nhat.iter().map(|n| n[a]).collect();
                transfer.elastostatic(&f)
            })
            .collect();
        let g = (0..nhat.len())
            .map(|i| {
                [
                    per_axis[0][i],
                    per_axis[1][i],
                    per_axis[2][i],
                    per_axis[3][i],
                ]
            })
            .collect();
        let kd = directions
            .iter()
            .map(|d| DVec3::from(d.map(|v| v as f64)) * k)
            .collect();
        Self {
            nhat,
            g,
            kd,
            c789,
            side,
            limit: None,
            fitted: fitted_supine.is_some(),
        }
    }

    /// Limit the weights as the run time does by default ([`DEFAULT_MIN_SLOPE_RATIO`]), from the
    /// exact fields' volume forms.
    pub fn set_limit(&mut self, exact_forms: &VolumeForms) {
        self.limit = Some(VolumeLimit::around(
            exact_forms.l,
            self.weights_unlimited(SUPINE_GRAVITY),
            DEFAULT_MIN_SLOPE_RATIO,
        ));
    }

    /// What the run time makes of `w`, eq. 6.18's weights for a posture: `w` itself, or with a
    /// fitted supine force [`fitted_weights`] (the fitted force plus the posture's change).
    pub fn as_drawn(&self, w: ForceWeights) -> ForceWeights {
        if self.fitted {
            fitted_weights(w, exact_weights(self.c789, self.side, SUPINE_GRAVITY))
        } else {
            w
        }
    }

    fn weights_unlimited(&self, g: DVec3) -> ForceWeights {
        self.as_drawn(exact_weights(self.c789, self.side, g))
    }

    /// Force weights of gravity `g` (exact, EQUATIONS.md §3.3), limited as the run time limits them.
    pub fn weights(&self, g: DVec3) -> ForceWeights {
        let w = self.weights_unlimited(g);
        match &self.limit {
            Some(l) => l.apply(w).0,
            None => w,
        }
    }

    /// `D_i = Σ_a w_a·G_a(i)` (f64).
    pub fn force(&self, w: &ForceWeights) -> Vec<f64> {
        self.g
            .iter()
            .map(|g| w[0] * g[0] + w[1] * g[1] + w[2] * g[2] + w[3] * g[3])
            .collect()
    }

    /// Volume forms of fields `U_a(i) = h_a(i)·k·d_i`.
    pub fn forms_of(&self, mesh: &TriMesh, h: &[[f64; 4]]) -> VolumeForms {
        let fields: Vec<Vec<DVec3>> = (0..4)
            .map(|a| h.iter().zip(&self.kd).map(|(h, kd)| *kd * h[a]).collect())
            .collect();
        VolumeForms::of(mesh, [&fields[0], &fields[1], &fields[2], &fields[3]])
    }

    /// The basis responses as stored (f32).
    pub fn stored(&self) -> Vec<[f32; 4]> {
        self.g.iter().map(|g| g.map(|v| v as f32)).collect()
    }
}

/// Displacement error statistics of one approximation against eq. 7.1.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct ErrorStats {
    /// RMS over nodes and orientations, mm.
    pub rms_mm: f64,
    /// Largest, mm.
    pub max_mm: f64,
    /// RMS as % of the largest eq. 7.1 displacement.
    pub rms_percent: f64,
    /// Largest as % of the largest eq. 7.1 displacement.
    pub max_percent: f64,
    /// Largest eq. 7.1 displacement, mm.
    pub max_displacement_mm: f64,
}

/// Accumulates displacement errors over orientations.
#[derive(Debug, Default)]
pub struct ErrorAccumulator {
    sum_sq: f64,
    count: u64,
    max: f64,
    max_ref: f64,
}

impl ErrorAccumulator {
    /// Add one orientation: displacements `s_ref·d_ref(i)·kd_i` against `s·d(i)·kd_i`.
    pub fn add(&mut self, kd: &[DVec3], s_ref: f64, d_ref: &[f64], s: f64, d: &[f64]) {
        for ((kd, r), a) in kd.iter().zip(d_ref).zip(d) {
            let reference = *kd * (s_ref * r);
            let e = (*kd * (s * a) - reference).length();
            self.sum_sq += e * e;
            self.count += 1;
            self.max = self.max.max(e);
            self.max_ref = self.max_ref.max(reference.length());
        }
    }

    /// Add precomputed displacement pairs.
    pub fn add_vectors(&mut self, reference: &[DVec3], approx: &[DVec3]) {
        for (r, a) in reference.iter().zip(approx) {
            let e = (*a - *r).length();
            self.sum_sq += e * e;
            self.count += 1;
            self.max = self.max.max(e);
            self.max_ref = self.max_ref.max(r.length());
        }
    }

    /// The statistics.
    pub fn stats(&self) -> ErrorStats {
        let rms = (self.sum_sq / self.count.max(1) as f64).sqrt();
        let pct = |v: f64| {
            if self.max_ref > 0.0 {
                100.0 * v / self.max_ref
            } else {
                0.0
            }
        };
        ErrorStats {
            rms_mm: rms,
            max_mm: self.max,
            rms_percent: pct(rms),
            max_percent: pct(self.max),
            max_displacement_mm: self.max_ref,
        }
    }
}

/// Why the spherical-harmonic form cannot be baked for a mesh.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ShError {
    /// The centroid is not inside the surface (winding number ≠ 1).
    #[error(
        "the mesh winds {winding} times around its volume centroid, so its nodes have no spherical \
         coordinates from it; bake with --bands 0 and use the basis mode"
    )]
    Winding {
        /// Winding number.
        winding: i64,
    },
    /// Band count out of range.
    #[error("{0} bands: 1 to {max} are supported", max = sh::MAX_BANDS)]
    Bands(usize),
    /// The coefficients cannot be held as the run time holds them (not finite in f32).
    #[error("the spherical-harmonic transfer coefficients cannot be stored: {0}")]
    Held(#[from] ShCoeffsError),
}

/// Volume centroid of a closed mesh (tetrahedra from the origin), mm.
pub fn volume_centroid(mesh: &TriMesh) -> [f64; 3] {
    let mut c = DVec3::ZERO;
    let mut v = 0.0;
    for t in &mesh.triangles {
        let [a, b, d] = t.map(|i| DVec3::from(mesh.positions[i as usize].map(|x| x as f64)));
        let vol = a.dot(b.cross(d));
        c += (a + b + d) * vol;
        v += vol;
    }
    if v != 0.0 {
        (c / (4.0 * v)).to_array()
    } else {
        [0.0; 3]
    }
}

/// The spherical-harmonic projection of one lung up to `n_max` bands (eq. 7.2–7.4).
#[derive(Debug, Clone)]
pub struct ShProjection {
    /// Bands computed.
    pub n_max: usize,
    /// Centre of projection, mm.
    pub centre: [f64; 3],
    /// Quadrature weights and fold-overs.
    pub weights: sh::SphereWeights,
    /// Nodes that got the isotropic answer (at the centre).
    pub isotropic_nodes: usize,
    /// `T^I_k` per node, `n_max²` each, row-major.
    pub t: Vec<f64>,
    /// `P[a·n_max² + k]`.
    pub projection: Vec<f64>,
}

/// One band count fitted: `α`, its fields and errors.
#[derive(Debug, Clone)]
pub struct ShFit {
    /// Bands.
    pub n: usize,
    /// Least-squares scale against eq. 7.1.
    pub alpha: f64,
    /// `H_a(i) = α·Σ_k P_ak·T^i_k`: the SH mode's response to each weight.
    pub h: Vec<[f64; 4]>,
    /// Volume forms of the SH mode.
    pub forms: VolumeForms,
    /// Errors against eq. 7.1, of the coefficients as drawn (quantised, [`ShProjection::quantised`]).
    pub error: ErrorStats,
    /// Largest displacement difference between the drawn (quantised) coefficients and the f64
    /// projection, same `α` and scale, over the orientations, mm: the quantisation's share.
    pub quantisation_max_mm: f64,
}

impl ShProjection {
    /// Project `mesh`'s transfer columns on `n_max` bands from its volume centroid.
    pub fn compute(
        mesh: &TriMesh,
        columns: &Columns,
        nhat: &[[f64; 4]],
        n_max: usize,
    ) -> Result<Self, ShError> {
        if n_max == 0 || n_max > sh::MAX_BANDS {
            return Err(ShError::Bands(n_max));
        }
        let centre = volume_centroid(mesh);
        let weights = sh::vertex_sphere_weights(centre, &mesh.positions, &mesh.triangles);
        if weights.winding() != 1 {
            return Err(ShError::Winding {
                winding: weights.winding(),
            });
        }
        let basis = sh::Basis::from_positions(centre, &mesh.positions, n_max);
        let nc = basis.n_coeffs();
        let mut t = vec![0.0; mesh.positions.len() * nc];
        t.par_chunks_mut(nc).enumerate().for_each(|(i, row)| {
            let (src, vals) = columns.column(i);
            for (&j, &v) in src.iter().zip(vals) {
                basis.accumulate(j as usize, v as f64, row);
            }
        });
        // What a kernel stores is f32: a coefficient beyond its range would be stored as infinite
        // and could not be held at run time; refuse it here rather than panic later.
        if let Some((index, &v)) = t
            .iter()
            .enumerate()
            .find(|(_, v)| !(**v as f32).is_finite())
        {
            return Err(ShError::Held(ShCoeffsError::NotFinite {
                index,
                value: v as f32,
            }));
        }
        let mut projection = vec![0.0; 4 * nc];
        for a in 0..4 {
            let values: Vec<f64> = nhat.iter().map(|n| n[a]).collect();
            sh::project(
                &values,
                &basis,
                &weights.weights,
                &mut projection[a * nc..(a + 1) * nc],
            );
        }
        Ok(Self {
            n_max,
            centre,
            isotropic_nodes: basis.isotropic_nodes().len(),
            weights,
            t,
            projection,
        })
    }

    /// `H_a(i) = Σ_{k<n²} P_ak·T^i_k` for `n ≤ n_max` bands (before `α`), from the f64 projection.
    pub fn responses(&self, n: usize) -> Vec<[f64; 4]> {
        let nc_max = self.n_max * self.n_max;
        self.t
            .par_chunks(nc_max)
            .map(|row| self.response_of(n, |k| row[k]))
            .collect()
    }

    /// [`Self::responses`] from the values the run time holds ([`Self::quantised`]): what is drawn.
    pub fn drawn_responses(&self, n: usize) -> Vec<[f64; 4]> {
        let q = self.quantised(n);
        (0..q.vertices())
            .into_par_iter()
            .map(|i| self.response_of(n, |k| q.value(i, k)))
            .collect()
    }

    fn response_of(&self, n: usize, t: impl Fn(usize) -> f64) -> [f64; 4] {
        let nc_max = self.n_max * self.n_max;
        std::array::from_fn(|a| {
            let p = &self.projection[a * nc_max..a * nc_max + n * n];
            p.iter().enumerate().map(|(k, p)| t(k) * p).sum()
        })
    }

    /// The `n`-band coefficients as the run time holds them: the kernel's f32 values
    /// ([`Self::stored`]) quantised to 16 bits per coefficient (EQUATIONS.md §3.2, run-time storage).
    ///
    /// # Panics
    /// If `n` is 0 or more than 8 bands (a frame's 64 coefficients; the bake and the trade study
    /// check this first). The values are finite in f32 ([`Self::compute`] refuses others).
    pub fn quantised(&self, n: usize) -> ShCoeffs {
        ShCoeffs::quantise(n * n, &self.stored(n)).expect("1 to 8 bands of finite values")
    }

    /// The SH transfer coefficients truncated to `n` bands, f32 (what a kernel stores).
    pub fn stored(&self, n: usize) -> Vec<f32> {
        let nc_max = self.n_max * self.n_max;
        self.t
            .chunks(nc_max)
            .flat_map(|row| row[..n * n].iter().map(|&v| v as f32))
            .collect()
    }

    /// The force projection truncated to `n` bands (`4 × n²`, row `a`).
    pub fn projection(&self, n: usize) -> Vec<f64> {
        let nc_max = self.n_max * self.n_max;
        (0..4)
            .flat_map(|a| {
                self.projection[a * nc_max..a * nc_max + n * n]
                    .iter()
                    .copied()
            })
            .collect()
    }

    /// Fit `α` for `n` bands against eq. 7.1 over `orientations` and measure the displacement
    /// error at `delta_ml` (each mode's scale from its own forms).
    pub fn fit(
        &self,
        n: usize,
        mesh: &TriMesh,
        responses: &Responses,
        exact_forms: &VolumeForms,
        orientations: &[DVec3],
        delta_ml: f64,
    ) -> ShFit {
        // α, the forms and the errors are those of what the run time draws: the quantised values.
        let raw = self.drawn_responses(n);
        let exact = self.responses(n);
        // α = Σ D_sh·D / Σ D_sh² over nodes and orientations.
        let (mut num, mut den) = (0.0, 0.0);
        for &g in orientations {
            let w = responses.weights(g);
            for (h, ge) in raw.iter().zip(&responses.g) {
                let d_sh = w[0] * h[0] + w[1] * h[1] + w[2] * h[2] + w[3] * h[3];
                let d = w[0] * ge[0] + w[1] * ge[1] + w[2] * ge[2] + w[3] * ge[3];
                num += d_sh * d;
                den += d_sh * d_sh;
            }
        }
        let alpha = if den > 0.0 && num.is_finite() {
            num / den
        } else {
            1.0
        };
        let h: Vec<[f64; 4]> = raw.iter().map(|h| h.map(|v| v * alpha)).collect();
        let forms = responses.forms_of(mesh, &h);
        let mut acc = ErrorAccumulator::default();
        let mut quantisation = ErrorAccumulator::default();
        let delta_mm3 = delta_ml * 1000.0;
        let dot =
            |w: &ForceWeights, h: &[f64; 4]| w[0] * h[0] + w[1] * h[1] + w[2] * h[2] + w[3] * h[3];
        for &g in orientations {
            let w = responses.weights(g);
            let s_ref = exact_forms.cubic(&w).solve_delta(delta_mm3);
            let s_sh = forms.cubic(&w).solve_delta(delta_mm3);
            let d_ref = responses.force(&w);
            let d_sh: Vec<f64> = h.iter().map(|h| dot(&w, h)).collect();
            let d_exact: Vec<f64> = exact.iter().map(|h| alpha * dot(&w, h)).collect();
            acc.add(&responses.kd, s_ref, &d_ref, s_sh, &d_sh);
            quantisation.add(&responses.kd, s_sh, &d_exact, s_sh, &d_sh);
        }
        ShFit {
            n,
            alpha,
            h,
            forms,
            error: acc.stats(),
            quantisation_max_mm: quantisation.stats().max_mm,
        }
    }
}

/// Largest displacement difference of the basis mode as the run time evaluates it (f32 responses,
/// f32 directions, f32 weights and scale) against eq. 7.1 evaluated in f64 directly from the rows
/// (`D = Tᵀf` with `f(J) = w0 + w·n̂(J)`), at `delta_ml`, over `orientations`. Round-off by
/// construction; this measures it.
pub fn basis_error(
    transfer: &Transfer,
    responses: &Responses,
    stored: &[[f32; 4]],
    directions: &[[f32; 3]],
    k: f64,
    forms: &VolumeForms,
    orientations: &[DVec3],
    delta_ml: f64,
) -> ErrorStats {
    let mut acc = ErrorAccumulator::default();
    for &g in orientations {
        let w = responses.weights(g);
        let f: Vec<f64> = responses
            .nhat
            .iter()
            .map(|n| w[0] * n[0] + w[1] * n[1] + w[2] * n[2] + w[3] * n[3])
            .collect();
        let d_ref = transfer.elastostatic(&f);
        let s = forms.cubic(&w).solve_delta(delta_ml * 1000.0);
        let reference: Vec<DVec3> = d_ref
            .iter()
            .zip(&responses.kd)
            .map(|(d, kd)| *kd * (s * d))
            .collect();
        let (s32, w32, k32) = (s as f32, w.map(|v| v as f32), k as f32);
        let approx: Vec<DVec3> = stored
            .iter()
            .zip(directions)
            .map(|(g, d)| {
                let dd = w32[0] * g[0] + w32[1] * g[1] + w32[2] * g[2] + w32[3] * g[3];
                let amount = s32 * dd;
                DVec3::new(
                    (amount * (d[0] * k32)) as f64,
                    (amount * (d[1] * k32)) as f64,
                    (amount * (d[2] * k32)) as f64,
                )
            })
            .collect();
        acc.add_vectors(&reference, &approx);
    }
    acc.stats()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::{bake, BakeSettings};
    use lung_model::mesh::generate;

    #[test]
    fn the_orientation_set_is_unit_and_deterministic() {
        let a = orientation_set();
        assert_eq!(a.len(), 26);
        assert!(a.iter().all(|g| (g.length() - 1.0).abs() < 1e-12));
        assert_eq!(a, orientation_set());
    }

    #[test]
    fn basis_responses_reproduce_the_supine_elastostatic_force() {
        let side = Side::Left;
        let k = bake(
            side,
            generate::lung(side, 600).unwrap(),
            &BakeSettings::default_for(side),
            &|_| {},
        )
        .unwrap();
        let r = k.responses();
        let d = r.force(&r.weights(SUPINE_GRAVITY));
        for (a, b) in d.iter().zip(&k.elastostatic) {
            assert!(
                (a - *b as f64).abs() <= 1e-5 * a.abs().max(1e-3),
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn a_lung_that_is_not_star_shaped_reports_its_fold_overs_and_stays_finite() {
        // Dent the lateral face towards the centroid: the rim of the dent is seen from its back.
        let side = Side::Left;
        let mut mesh = generate::lung(side, 2000).unwrap();
        let c = DVec3::from(volume_centroid(&mesh));
        let axis = DVec3::X;
        for p in &mut mesh.positions {
            let v = DVec3::from(p.map(|x| x as f64)) - c;
            let cos = v.normalize().dot(axis);
            if cos > 0.8 {
                let q = c + v * (1.0 - 0.85 * (cos - 0.8) / 0.2);
                *p = q.as_vec3().to_array();
            }
        }
        let k = bake(side, mesh, &BakeSettings::default_for(side), &|_| {}).unwrap();
        let sh = k.meta.sh.as_ref().unwrap();
        assert!(sh.foldover_nodes > 0, "the dent folds the projection");
        assert!(sh.rms_mm.is_finite() && sh.max_mm.is_finite() && sh.alpha.is_finite());
        assert!(k.sh.as_ref().unwrap().iter().all(|v| v.is_finite()));
    }

    #[test]
    fn more_bands_than_a_frame_carries_are_refused_and_zero_bands_bake_none() {
        let side = Side::Left;
        let mut s = BakeSettings::default_for(side);
        s.sh_bands = 16;
        let e = bake(side, generate::lung(side, 300).unwrap(), &s, &|_| {}).unwrap_err();
        assert!(e.to_string().contains("0 (none) to 8"), "{e}");
        s.sh_bands = 0;
        let k = bake(side, generate::lung(side, 300).unwrap(), &s, &|_| {}).unwrap();
        assert!(k.sh.is_none() && k.meta.sh.is_none());
        assert!(k.meta.orientation.as_ref().unwrap().basis_max_error_mm < 1e-3);
        // One band: the constant harmonic only, still finite.
        s.sh_bands = 1;
        let k = bake(side, generate::lung(side, 300).unwrap(), &s, &|_| {}).unwrap();
        assert_eq!(k.meta.sh.as_ref().unwrap().bands, 1);
        assert!(k.meta.sh.as_ref().unwrap().rms_mm.is_finite());
    }

    #[test]
    fn sh_error_falls_with_bands_and_alpha_is_near_one() {
        let side = Side::Right;
        let k = bake(
            side,
            generate::lung(side, 1500).unwrap(),
            &BakeSettings::default_for(side),
            &|_| {},
        )
        .unwrap();
        let r = k.responses();
        let forms = r.forms_of(&k.mesh, &r.g);
        let mut r = r;
        r.set_limit(&forms);
        let proj = ShProjection::compute(&k.mesh, &k.transfer.transposed(), &r.nhat, 8).unwrap();
        assert!((proj.weights.total - 4.0 * std::f64::consts::PI).abs() < 1e-9);
        let o = orientation_set();
        let errs: Vec<f64> = [1, 2, 4, 8]
            .iter()
            .map(|&n| proj.fit(n, &k.mesh, &r, &forms, &o, 200.0).error.rms_mm)
            .collect();
        assert!(errs.iter().all(|e| e.is_finite()));
        assert!(errs[3] < errs[0], "{errs:?}");
        let f4 = proj.fit(4, &k.mesh, &r, &forms, &o, 200.0);
        assert!((0.5..2.0).contains(&f4.alpha), "alpha {}", f4.alpha);
        // The run time's 16-bit storage: a share of the error that exists (not 0: it is measured)
        // and is far below the truncation's, at every band count, 1 and 8 included.
        for n in [1, 4, 8] {
            let f = proj.fit(n, &k.mesh, &r, &forms, &o, 200.0);
            let max_disp = f.error.max_displacement_mm;
            assert!(
                f.quantisation_max_mm > 0.0 && f.quantisation_max_mm < 1e-3 * max_disp,
                "{n} bands: quantisation {} mm of {max_disp} mm",
                f.quantisation_max_mm
            );
            assert!(
                f.quantisation_max_mm < 0.01 * f.error.max_mm,
                "{n} bands: {f:?}"
            );
            // The fit's responses are those of the held values (not of the f64 projection).
            let q = proj.quantised(n);
            let exact = proj.responses(n);
            let i = k.mesh.positions.len() / 3;
            let mut differs = false;
            for a in 0..4 {
                let want: f64 = (0..n * n)
                    .map(|kk| q.value(i, kk) * proj.projection(n)[a * n * n + kk])
                    .sum::<f64>()
                    * f.alpha;
                assert!(
                    (f.h[i][a] - want).abs() <= 1e-12 * want.abs().max(1e-9),
                    "{n} bands, weight {a}: {} vs {want}",
                    f.h[i][a]
                );
                differs |= f.h[i][a] != exact[i][a] * f.alpha;
            }
            assert!(
                differs,
                "{n} bands: the held values differ from the f64 ones somewhere"
            );
        }
    }
}
