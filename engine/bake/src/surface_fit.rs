//! # surface_fit: the motion model fitted to a second-phase *surface* (no correspondences)
//!
//! Two segmentations of one lung at two breathing phases rarely share vertices. The seed (§6.4.2)
//! puts them in correspondence by casting rays along the modelled directions; here the kernel's own
//! model is fitted directly: the reference surface `A` moved by
//!
//! ```text
//!   x_i = A_i + F_i · d_i(c1..c6),   F = w7·Tᵀx̂ + w8·Tᵀŷ + w9·Tᵀẑ        (eq. 6.1, 6.14–6.16, 6.18)
//! ```
//!
//! must lie on the target surface `B`: Levenberg–Marquardt minimises the squared signed distances of
//! the `x_i` to `B` (closest points from a BVH over `B`'s triangles, parry3d) over the exponents
//! `c2, c4, c6`, the direction ratios `c1/c3, c5/c3` (`c3` stays at its Table 6.1 value: a unit
//! direction only sees ratios) and the force weights `w7..w9` (their sum is the phase's scale; the
//! reported `c7..c9` are the weights normalised to sum 1). The start is Table 6.1 scaled so the moved
//! surface encloses `B`'s volume. Further phases get one scale each.
//!
//! A surface distance does not see sliding along the surface, so the residuals are a lower bound of
//! the landmark error; they are reported beside the no-motion baseline (mean distance of `A` to `B`).

use glam::DVec3;
use levenberg_marquardt::LevenbergMarquardt;
use nalgebra::DVector;
use parry3d::query::PointQuery;
use thiserror::Error;

use crate::lsq::{Numeric, ResidualModel};
use crate::motion_fit::{operator_responses, PhaseFit, Residuals};
use lung_model::deform::{direction, MotionConstants};
use lung_model::mesh::{Side, TriMesh};
use lung_model::operator::Elasticity;

/// Errors of the surface fit.
#[derive(Debug, Error)]
pub enum SurfaceFitError {
    /// A surface is unusable.
    #[error("{what}: {message}")]
    Surface {
        /// Which surface.
        what: String,
        /// What is wrong.
        message: String,
    },
    /// The operator could not be built.
    #[error(transparent)]
    Bake(#[from] crate::kernel::BakeError),
}

/// A target surface with a BVH for signed distances.
pub struct Target {
    mesh: parry3d::shape::TriMesh,
}

impl Target {
    /// Index `mesh` (closed, outward wound, mm).
    pub fn new(mesh: &TriMesh, what: &str) -> Result<Self, SurfaceFitError> {
        lung_model::mesh::check(mesh).map_err(|e| SurfaceFitError::Surface {
            what: what.into(),
            message: e.to_string(),
        })?;
        let v = mesh
            .positions
            .iter()
            .map(|p| parry3d::math::Vector::new(p[0], p[1], p[2]))
            .collect();
        let mesh = parry3d::shape::TriMesh::with_flags(
            v,
            mesh.triangles.clone(),
            parry3d::shape::TriMeshFlags::ORIENTED,
        )
        .map_err(|e| SurfaceFitError::Surface {
            what: what.into(),
            message: format!("{e:?}"),
        })?;
        Ok(Self { mesh })
    }

    /// Signed distance of `p` to the surface (negative inside), mm.
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        let q = parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32);
        let proj = self.mesh.project_local_point(q, false);
        let d = (proj.point - q).length() as f64;
        if proj.is_inside {
            -d
        } else {
            d
        }
    }
}

/// What the moved reference must reach at a phase.
#[derive(Clone, Copy)]
pub enum Goal<'a> {
    /// A surface without correspondences: residuals are signed distances to it.
    Surface(&'a Target),
    /// The reference's own vertices at that phase (two meshes with the same vertex order):
    /// residuals are the three coordinate differences.
    Points(&'a [DVec3]),
}

impl Goal<'_> {
    fn push_residuals(&self, i: usize, x: DVec3, out: &mut Vec<f64>) {
        match self {
            Goal::Surface(t) => out.push(t.signed_distance(x)),
            Goal::Points(b) => {
                let d = x - b[i];
                out.extend([d.x, d.y, d.z]);
            }
        }
    }

    /// Error of `x` standing for reference vertex `i`, mm.
    fn error(&self, i: usize, x: DVec3) -> f64 {
        match self {
            Goal::Surface(t) => t.signed_distance(x).abs(),
            Goal::Points(b) => (x - b[i]).length(),
        }
    }

    /// Enclosed volume at this phase, ml (`a` gives the triangles for point goals).
    fn volume_ml(&self, a: &TriMesh) -> f64 {
        match self {
            Goal::Surface(t) => t.mesh_volume_ml(),
            Goal::Points(b) => {
                lung_model::mesh::enclosed_volume_with(&a.triangles, |i| b[i as usize].to_array())
                    / 1000.0
            }
        }
    }
}

/// Result of a surface fit for one lung.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SurfaceFit {
    /// `c1..c9` (c7..c9 normalised to sum 1).
    pub constants: [f64; 9],
    /// Sum of the force weights: the scale of phase B.
    pub scale: f64,
    /// Distances of the moved reference to B (`baseline_mean_mm`: of the unmoved reference).
    pub residuals: Residuals,
    /// Further phases: one scale each (relative to phase B) and their distances.
    pub also: Vec<PhaseFit>,
    /// Mean non-zeros per transfer row of the operator used.
    pub mean_row_nnz: f64,
    /// Surface points used in the fit (a subsample of large meshes; residuals use all).
    pub fit_points: usize,
}

/// Points used in the Levenberg–Marquardt fit at most (every k-th vertex beyond that).
pub const MAX_FIT_POINTS: usize = 4000;

struct Model<'a> {
    side: Side,
    a: &'a [DVec3],
    norm: &'a [DVec3],
    g: &'a [Vec<f64>],
    c3: f64,
}

impl Model<'_> {
    /// Parameters: [c1, c2, c4, c5, c6, w7, w8, w9] with exponents as squares (kept ≥ 0).
    fn constants(&self, p: &DVector<f64>) -> ([f64; 9], [f64; 3]) {
        (
            [
                p[0],
                p[1] * p[1],
                self.c3,
                p[2] * p[2],
                p[3],
                p[4] * p[4],
                0.0,
                0.0,
                0.0,
            ],
            [p[5], p[6], p[7]],
        )
    }

    fn moved(&self, i: usize, c: &[f64; 9], w: &[f64; 3]) -> DVec3 {
        let d = direction(self.norm[i], &MotionConstants { c: *c }, self.side);
        let f = w[0] * self.g[0][i] + w[1] * self.g[1][i] + w[2] * self.g[2][i];
        self.a[i] + d * f
    }
}

struct Problem<'a> {
    model: Model<'a>,
    target: Goal<'a>,
    sample: Vec<usize>,
}

impl Problem<'_> {
    fn residuals_at(&self, p: &DVector<f64>) -> DVector<f64> {
        let (c, w) = self.model.constants(p);
        let mut out = Vec::with_capacity(self.sample.len() * 3);
        for &i in &self.sample {
            self.target
                .push_residuals(i, self.model.moved(i, &c, &w), &mut out);
        }
        DVector::from_vec(out)
    }
}

impl ResidualModel for Problem<'_> {
    fn residuals_at(&self, p: &DVector<f64>) -> DVector<f64> {
        Problem::residuals_at(self, p)
    }

    /// Steps of 1e-4 relative stay above the f32 distance queries' noise.
    fn step(&self, v: f64) -> f64 {
        1e-4 * v.abs().max(1e-2)
    }
}

fn distance_residuals(dist: impl Iterator<Item = f64>, baseline: f64) -> Residuals {
    let (mut n, mut sum, mut sq, mut max) = (0usize, 0.0, 0.0, 0.0f64);
    for d in dist {
        n += 1;
        sum += d.abs();
        sq += d * d;
        max = max.max(d.abs());
    }
    let n = n.max(1) as f64;
    Residuals {
        mean_error_mm: sum / n,
        max_error_mm: max,
        rms_error_mm: (sq / n).sqrt(),
        baseline_mean_mm: baseline,
    }
}

/// Fit one lung: reference surface `a` (phase A), goal `b` at the fitted phase, further phases
/// `also`.
pub fn fit_surface(
    side: Side,
    a: &TriMesh,
    b: Goal,
    also: &[Goal],
    elasticity: &Elasticity,
    tolerance: f64,
    smoothing_mm: f64,
) -> Result<SurfaceFit, SurfaceFitError> {
    let (norm, g, mean_row_nnz) = operator_responses(side, a, elasticity, tolerance, smoothing_mm)?;
    let pts: Vec<DVec3> = a
        .positions
        .iter()
        .map(|p| DVec3::from(p.map(|v| v as f64)))
        .collect();
    let table = MotionConstants::table_6_1(side).c;
    let model = Model {
        side,
        a: &pts,
        norm: &norm,
        g: &g,
        c3: table[2],
    };
    // Start: Table 6.1 with the force scaled by the volume change, via the kernel's own unit field.
    let f: Vec<f64> = (0..pts.len())
        .map(|i| table[6] * g[0][i] + table[7] * g[1][i] + table[8] * g[2][i])
        .collect();
    let (unit, _, force_scale) = lung_model::deform::LungModel::from_force(
        side,
        a.clone(),
        &MotionConstants { c: table },
        &f,
    )
    .map_err(crate::kernel::BakeError::from)?;
    let dv_ml = b.volume_ml(a) - unit.start_volume_ml;
    let s0 = unit.scale_for_delta(dv_ml) * force_scale;
    let start = DVector::from_vec(vec![
        table[0],
        table[1].sqrt(),
        table[3].sqrt(),
        table[4],
        table[5].sqrt(),
        table[6] * s0,
        table[7] * s0,
        table[8] * s0,
    ]);
    let stride = pts.len().div_ceil(MAX_FIT_POINTS).max(1);
    let sample: Vec<usize> = (0..pts.len()).step_by(stride).collect();
    let fit_points = sample.len();
    let problem = Numeric {
        model: Problem {
            model,
            target: b,
            sample,
        },
        p: start,
    };
    let (problem, _report) = LevenbergMarquardt::new()
        .with_patience(40)
        .minimize(problem);
    let (mut c, w) = problem.model.model.constants(&problem.p);
    let model = problem.model.model;
    let baseline = (0..pts.len()).map(|i| b.error(i, pts[i])).sum::<f64>() / pts.len() as f64;
    let residuals = distance_residuals(
        (0..pts.len()).map(|i| b.error(i, model.moved(i, &c, &w))),
        baseline,
    );
    // Further phases: one scale k on the whole displacement, by golden section on the mean squared
    // distance over the subsample.
    let also = also
        .iter()
        .map(|t| {
            let cost = |k: f64| {
                let wk = [w[0] * k, w[1] * k, w[2] * k];
                (0..pts.len())
                    .step_by(stride)
                    .map(|i| t.error(i, model.moved(i, &c, &wk)).powi(2))
                    .sum::<f64>()
            };
            let (mut lo, mut hi) = (0.0, 4.0);
            let gr = 0.5 * (5f64.sqrt() - 1.0);
            for _ in 0..50 {
                let (x1, x2) = (hi - gr * (hi - lo), lo + gr * (hi - lo));
                if cost(x1) <= cost(x2) {
                    hi = x2;
                } else {
                    lo = x1;
                }
            }
            let k = 0.5 * (lo + hi);
            let wk = [w[0] * k, w[1] * k, w[2] * k];
            let base = (0..pts.len()).map(|i| t.error(i, pts[i])).sum::<f64>() / pts.len() as f64;
            PhaseFit {
                scale: k,
                residuals: distance_residuals(
                    (0..pts.len()).map(|i| t.error(i, model.moved(i, &c, &wk))),
                    base,
                ),
            }
        })
        .collect();
    let scale = w[0] + w[1] + w[2];
    let norm_by = if scale.abs() > 1e-300 { scale } else { 1.0 };
    c[6] = w[0] / norm_by;
    c[7] = w[1] / norm_by;
    c[8] = w[2] / norm_by;
    Ok(SurfaceFit {
        constants: c,
        scale,
        residuals,
        also,
        mean_row_nnz,
        fit_points,
    })
}

impl Target {
    /// Enclosed volume of the target, ml.
    pub fn mesh_volume_ml(&self) -> f64 {
        let v = self.mesh.vertices();
        let t = self.mesh.indices();
        lung_model::mesh::enclosed_volume_with(t, |i| {
            let p = v[i as usize];
            [p.x as f64, p.y as f64, p.z as f64]
        }) / 1000.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernel::{bake, BakeSettings};
    use lung_model::mesh::generate;

    #[test]
    fn a_surface_made_by_known_constants_gives_them_back() {
        let side = Side::Left;
        let a = generate::lung(side, 1500).unwrap();
        let mut settings = BakeSettings::default_for(side);
        settings.motion.c = [0.12, 0.3, 0.4, 0.6, 0.15, 1.8, 0.1, 0.8, 0.1];
        let k = bake(side, a.clone(), &settings, &|_| {}).unwrap();
        let m = lung_model::deform::LungModel::from_unit_displacement(
            side,
            a.clone(),
            k.unit_displacement.clone(),
        );
        let moved = |dv: f64| {
            let mut out = vec![[0.0f32; 3]; a.positions.len()];
            m.deform_into(m.scale_for_delta(dv) as f32, &mut out);
            // A different tessellation of B would be realistic; the same vertices moved is the
            // strictest check that the model is recovered.
            TriMesh {
                positions: out,
                triangles: a.triangles.clone(),
            }
        };
        let b = Target::new(&moved(300.0), "B").unwrap();
        let c = Target::new(&moved(450.0), "C").unwrap();
        let f = fit_surface(
            side,
            &a,
            Goal::Surface(&b),
            &[Goal::Surface(&c)],
            &settings.elasticity,
            settings.tolerance,
            settings.amplitude_smoothing_mm,
        )
        .unwrap();
        assert!(f.residuals.baseline_mean_mm > 5.0);
        for (k, want) in settings.motion.c.iter().enumerate() {
            assert!(
                (f.constants[k] - want).abs() < 1e-3,
                "c{} = {}",
                k + 1,
                f.constants[k]
            );
        }
        assert!(
            f.residuals.mean_error_mm < 0.05 * f.residuals.baseline_mean_mm,
            "{:?}",
            f.residuals
        );
        assert!((f.also[0].scale - 1.5).abs() < 0.1, "{:?}", f.also);
        assert!(f.also[0].residuals.mean_error_mm < 0.1 * f.also[0].residuals.baseline_mean_mm);
    }

    #[test]
    fn the_same_vertices_at_the_other_phase_give_every_constant_back() {
        let side = Side::Right;
        let a = generate::lung(side, 1200).unwrap();
        let mut settings = BakeSettings::default_for(side);
        settings.motion.c = [0.2, 0.4, 0.39, 0.5, 0.1, 2.5, 0.2, 0.5, 0.3];
        let k = bake(side, a.clone(), &settings, &|_| {}).unwrap();
        let b: Vec<DVec3> = a
            .positions
            .iter()
            .zip(&k.unit_displacement)
            .map(|(p, u)| {
                DVec3::from(p.map(|v| v as f64)) + 150.0 * DVec3::from(u.map(|v| v as f64))
            })
            .collect();
        let f = fit_surface(
            side,
            &a,
            Goal::Points(&b),
            &[],
            &settings.elasticity,
            settings.tolerance,
            settings.amplitude_smoothing_mm,
        )
        .unwrap();
        for (k, want) in settings.motion.c.iter().enumerate() {
            assert!(
                (f.constants[k] - want).abs() < 1e-3,
                "c{} = {}",
                k + 1,
                f.constants[k]
            );
        }
        assert!(f.residuals.max_error_mm < 1e-3, "{:?}", f.residuals);
    }

    #[test]
    fn distances_are_signed() {
        let a = generate::lung(Side::Right, 500).unwrap();
        let t = Target::new(&a, "A").unwrap();
        let bb = a.aabb();
        let centre = DVec3::new(
            0.5 * (bb.min[0] + bb.max[0]) as f64,
            0.5 * (bb.min[1] + bb.max[1]) as f64,
            0.5 * (bb.min[2] + bb.max[2]) as f64,
        );
        assert!(t.signed_distance(centre) < 0.0);
        assert!(t.signed_distance(centre + DVec3::new(0.0, 0.0, 1000.0)) > 800.0);
        assert!((t.mesh_volume_ml() - a.enclosed_volume_ml()).abs() < 0.1);
    }
}
