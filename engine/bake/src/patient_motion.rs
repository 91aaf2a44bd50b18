//! # patient_motion: a breath-hold pair's motion, fitted on the chapter-6 operator
//!
//! A patient's exhale and inhale lung surfaces (two breath-hold CTs, not registered to each other)
//! give the motion that patient's lung makes between the two volumes. The seed's motion (eq.
//! 6.14–6.16, 6.18) has nine constants: a linear applied force and a separable power law of directions.
//! On the shared COPDgene pairs that cannot hold a real lung even in-sample (issue 34: 6.5 mm on a
//! right lung where leaving it still gave 6.3 mm), so this fit gives the same pipeline the freedom
//! the data need and nothing else:
//!
//! * **the applied force** `f(x)` is a polynomial of total degree ≤ `force_degree` in the lung's box
//!   coordinates (the seed's is the degree-1 case) plus `force_centres` local terms (compactly
//!   supported bumps centred on the exhale surface, [`ForceField::centres`]), turned into the
//!   elastostatic force by the same Green's-function operator the bake uses (`F = T·f`, seed §6.3,
//!   eq. 6.9–6.13);
//! * **the directions** `d(x)` come from a smooth displacement field (a polynomial of degree
//!   `field_degree`, [`Field::Poly`]), normalised, as `fit-motion` already gives the bake;
//! * the vertex moves by `s·F_i·d_i`, `s` set by the volume — exactly the kernel's unit displacement,
//!   driven to the inhale volume.
//!
//! **Alignment (argued).** The two scans are not registered: the patient lay down twice. One
//! translation per lung puts the inhale apex on the exhale apex, then a trimmed, translation-only
//! ICP fits the inhale apical cap (the top quarter of the exhale lung's height) onto the exhale
//! surface. The apex moves least in breathing (the base and the front move most), so the cap
//! carries the patient's repositioning and little of the breath; a rotation is not fitted because
//! on these pairs a rotating ICP tilted the lungs 0.9–6.4° to fit the breath itself
//! (docs/masks/breath_hold_baselines.md).
//!
//! **The fit.** Symmetric non-rigid ICP: each round moves the exhale surface by the current model,
//! pairs every moved vertex with its closest inhale point and every inhale vertex with its closest
//! moved point (so no part of the inhale surface is ignored), refits the direction field to the
//! paired displacements and the force coefficients to their magnitudes along the directions (ridge
//! least squares through the operator's columns). Start: uniform scaling to the inhale volume. The
//! local terms' ridge is annealed ([`local_stiffness`]): stiff while the closest points are still far
//! from where each vertex belongs, free once they have settled.
//!
//! **Held-out error.** The exhale surface is cut into patches (farthest-point seeds, nearest-seed
//! regions, [`PATCHES_PER_FOLD`] per fold); the patches are dealt into folds by a seeded shuffle;
//! each fold is fitted without its
//! patches' vertices and without the inhale points nearest to them, then measured there only. Every
//! vertex is held out once; the figure is the symmetric mean over the held-out parts.
//!
//! Everything is deterministic (fixed seeds, fixed iteration counts, sums in index order).

use glam::DVec3;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;
use thiserror::Error;

use lung_model::deform::field::{
    box_coords, monomial_values, monomials, wendland, Field, ForceField, MAX_LOCAL_TERMS,
};
use lung_model::deform::LungModel;
use lung_model::kernel::BakeSettings;
use lung_model::mesh::{Side, TriMesh};

use crate::folds::at_volume;
use crate::mask::surface::{neighbour_rows, points};
use crate::motion_models::{fit_field, folds, Config};
use crate::operator::{compute_transfer, NodeGraph, Schedule};

/// How the pair is fitted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PairOptions {
    /// Total degree of the applied force polynomial (1 = the seed's linear force), 1..=5.
    pub force_degree: u8,
    /// Total degree of the direction field polynomial, 1..=5.
    pub field_degree: u8,
    /// Local terms of the applied force ([`ForceField::centres`]): this many centres on the exhale
    /// surface (farthest-point samples), each reaching [`LOCAL_REACH`] times their spacing; 0 for the
    /// polynomial alone.
    pub force_centres: usize,
    /// Ridge weight of the local terms, times the mean diagonal of their normal equations.
    pub force_local_ridge: f64,
    /// Ridge weight of the direction field (times the number of points).
    pub field_ridge: f64,
    /// Normal compatibility of the ICP's correspondences, degrees: a pull is kept only where the
    /// moved surface's normal and the target's lie within this angle (180 keeps every pull).
    pub normal_gate_deg: f64,
    /// ICP rounds.
    pub iterations: usize,
    /// Folds of the held-out error (0: none), 2..=10 otherwise.
    pub folds: usize,
    /// Seed of the patches' deal into folds.
    pub seed: u64,
    /// Apical cap for the alignment, as a share of the exhale lung's height.
    pub cap_fraction: f64,
}

impl Default for PairOptions {
    fn default() -> Self {
        Self {
            force_degree: 3,
            field_degree: 2,
            force_centres: 256,
            force_local_ridge: 0.01,
            field_ridge: 1e-6,
            normal_gate_deg: NORMAL_GATE_DEG,
            iterations: 50,
            folds: 5,
            seed: 34,
            cap_fraction: 0.25,
        }
    }
}

impl PairOptions {
    /// Every option in its range, or the one that is not, named as `fit-motion`'s flag with its value.
    pub fn validate(&self) -> Result<(), PairFitError> {
        let bad = |m: String| Err(PairFitError::Option(m));
        for (flag, d) in [
            ("--force-degree", self.force_degree),
            ("--field-degree", self.field_degree),
        ] {
            if !(1..=5).contains(&d) {
                return bad(format!("{flag} {d}: give 1 to 5"));
            }
        }
        if self.force_centres != 0 && !(8..=MAX_LOCAL_TERMS).contains(&self.force_centres) {
            return bad(format!(
                "--force-centres {}: give 0 (the polynomial force alone) or 8 to 1000",
                self.force_centres
            ));
        }
        if !(self.force_local_ridge.is_finite() && self.force_local_ridge > 0.0) {
            return bad(format!(
                "--force-local-ridge {}: give a finite number above 0 (larger is smoother)",
                self.force_local_ridge
            ));
        }
        if !(MIN_NORMAL_GATE_DEG..=180.0).contains(&self.normal_gate_deg) {
            return bad(format!(
                "--normal-gate {}: give 10 to 180 degrees (180 keeps every correspondence; a \
                 narrower gate drops nearly every one and leaves the fit at uniform scaling)",
                self.normal_gate_deg
            ));
        }
        if !(1..=200).contains(&self.iterations) {
            return bad(format!("--iterations {}: give 1 to 200", self.iterations));
        }
        if self.folds == 1 || self.folds > 10 {
            return bad(format!("--folds {}: give 0 (none) or 2 to 10", self.folds));
        }
        Ok(())
    }
}

/// What went wrong.
#[derive(Debug, Error)]
pub enum PairFitError {
    /// A surface is not a closed lung surface.
    #[error("the {what} surface: {message}")]
    Surface {
        /// Which.
        what: &'static str,
        /// Why.
        message: String,
    },
    /// An option is out of range.
    #[error("{0}")]
    Option(String),
    /// The inhale lung is not larger than the exhale one.
    #[error(
        "the inhale surface ({inhale_ml:.0} ml) is not larger than the exhale one ({exhale_ml:.0} \
         ml): is it the same phase twice, or are --exhale and --inhale the other way round?"
    )]
    NotInhaled {
        /// Exhale volume, ml.
        exhale_ml: f64,
        /// Inhale volume, ml.
        inhale_ml: f64,
    },
    /// The operator could not be built or the model does not expand.
    #[error(transparent)]
    Bake(#[from] crate::kernel::BakeError),
    /// A least-squares system was singular.
    #[error("the {0} fit is singular: too few points for its degree")]
    Singular(&'static str),
}

/// The rigid (translation-only) alignment of the inhale surface onto the exhale one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Alignment {
    /// Added to every inhale point, mm.
    pub translation_mm: [f64; 3],
    /// The apex-on-apex start, mm.
    pub apex_translation_mm: [f64; 3],
    /// Cap depth, mm.
    pub cap_depth_mm: f64,
    /// Inhale vertices in the cap.
    pub cap_points: usize,
    /// Mean distance of the aligned cap to the exhale surface (the trimmed 90 %), mm.
    pub cap_residual_mm: f64,
}

/// Distances between a moved surface and the target, area-weighted means over vertices.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SurfaceDistance {
    /// Mean symmetric surface distance, mm: the mean of the two directed means.
    pub mssd_mm: f64,
    /// Moved exhale surface → inhale surface, mm.
    pub exhale_to_inhale_mm: f64,
    /// Inhale surface → moved exhale surface, mm.
    pub inhale_to_exhale_mm: f64,
    /// 95th percentile of all vertex distances (both directions), mm.
    pub p95_mm: f64,
    /// Largest, mm (symmetric Hausdorff over vertices).
    pub max_mm: f64,
}

/// One lung's fit.
#[derive(Debug, Clone, Serialize)]
pub struct PairFit {
    /// Which lung.
    pub side: Side,
    /// The applied force field (what `bake` uses with the direction field).
    pub force: ForceField,
    /// The direction field.
    pub direction: Field,
    /// The inhale surface's alignment.
    pub alignment: Alignment,
    /// Exhale surface volume, ml.
    pub exhale_ml: f64,
    /// Inhale surface volume, ml.
    pub inhale_ml: f64,
    /// The fitted kernel driven to the inhale volume, against the aligned inhale surface.
    pub in_sample: SurfaceDistance,
    /// The same, each part of the surface fitted without itself (None with `folds` 0).
    pub cross_validated: Option<SurfaceDistance>,
    /// Leaving the exhale surface where it is.
    pub no_motion: SurfaceDistance,
    /// Scaling the exhale surface about its volume centroid to the inhale volume.
    pub uniform_scaling: SurfaceDistance,
    /// Crossing triangle pairs of the fitted kernel's surface at the inhale volume (0: no fold; at
    /// most 100,000 counted). A surface pair cannot see sliding within the surface, and the fit
    /// may slide parts of it far enough to fold it: said, never hidden.
    pub folds_at_inhale: usize,
    /// The volume change above the exhale volume (ml, to 1/768 of the pair's) up to which the fitted
    /// kernel was found to draw no fold ([`crate::folds::fold_free_share`]): the pair's whole change
    /// when none was found.
    pub fold_free_ml: f64,
    /// Vertex displacement at the inhale volume, mm: median, 99th percentile, largest (the real
    /// motion is a few centimetres at the base; far more is sliding the surface pair cannot see).
    pub displacement_mm: [f64; 3],
    /// The options used.
    pub options: PairOptions,
    /// The exhale surface driven to the inhale volume by the fitted kernel (what a bake draws).
    #[serde(skip)]
    pub moved: TriMesh,
    /// The aligned inhale surface (the target the errors are measured against).
    #[serde(skip)]
    pub inhale_aligned: TriMesh,
}

/// A closed surface indexed for closest points.
struct Surface {
    mesh: parry3d::shape::TriMesh,
    tris: Vec<[u32; 3]>,
    p: Vec<DVec3>,
    /// Unit normals: per triangle, and per vertex (area-weighted).
    tri_n: Vec<DVec3>,
    vert_n: Vec<DVec3>,
}

impl Surface {
    fn new(p: &[DVec3], tris: &[[u32; 3]]) -> Option<Self> {
        let v = p
            .iter()
            .map(|q| parry3d::math::Vector::new(q.x as f32, q.y as f32, q.z as f32))
            .collect();
        let mesh = parry3d::shape::TriMesh::new(v, tris.to_vec()).ok()?;
        let tri_n = crate::mask::surface::triangle_normals(p, tris);
        let vert_n = crate::mask::surface::vertex_normals(p, tris);
        Some(Self {
            mesh,
            tris: tris.to_vec(),
            p: p.to_vec(),
            tri_n,
            vert_n,
        })
    }

    /// The closest surface point to `q`, the vertex of its triangle nearest to it, and the
    /// triangle's normal.
    fn closest(&self, q: DVec3) -> (DVec3, u32, DVec3) {
        use parry3d::query::PointQueryWithLocation;
        let x = parry3d::math::Vector::new(q.x as f32, q.y as f32, q.z as f32);
        let (proj, (tri, _)) = self.mesh.project_local_point_and_get_location(x, false);
        let c = DVec3::new(
            proj.point.x as f64,
            proj.point.y as f64,
            proj.point.z as f64,
        );
        let t = self.tris[tri as usize];
        let near = *t
            .iter()
            .min_by(|a, b| {
                (self.p[**a as usize] - c)
                    .length_squared()
                    .total_cmp(&(self.p[**b as usize] - c).length_squared())
            })
            .unwrap_or(&t[0]);
        (c, near, self.tri_n[tri as usize])
    }
}

/// A third of each incident triangle's area, per vertex, mm².
fn vertex_areas(p: &[DVec3], tris: &[[u32; 3]]) -> Vec<f64> {
    let mut a = vec![0.0; p.len()];
    for t in tris {
        let [x, y, z] = t.map(|v| p[v as usize]);
        let area = 0.5 * (y - x).cross(z - x).length();
        for &v in t {
            a[v as usize] += area / 3.0;
        }
    }
    a
}

fn volume_ml(p: &[DVec3], tris: &[[u32; 3]]) -> f64 {
    lung_model::mesh::enclosed_volume_with(tris, |i| p[i as usize].to_array()) / 1000.0
}

/// Centroid of the volume a closed surface encloses (signed tetrahedra from the origin).
fn volume_centroid(p: &[DVec3], tris: &[[u32; 3]]) -> DVec3 {
    let (mut six_v, mut moment) = (0.0, DVec3::ZERO);
    for t in tris {
        let [a, b, c] = t.map(|v| p[v as usize]);
        let v6 = a.dot(b.cross(c));
        six_v += v6;
        moment += v6 * (a + b + c);
    }
    moment / (4.0 * six_v)
}

/// Translation of the inhale surface onto the exhale one: apex on apex, then a trimmed,
/// translation-only ICP of the inhale apical cap onto the exhale surface.
pub fn align(exhale: &TriMesh, inhale: &TriMesh, cap_fraction: f64) -> Option<Alignment> {
    let (pe, pi) = (points(exhale), points(inhale));
    let target = Surface::new(&pe, &exhale.triangles)?;
    let top = |p: &[DVec3]| {
        p.iter()
            .copied()
            .max_by(|a, b| a.z.total_cmp(&b.z))
            .unwrap_or(DVec3::ZERO)
    };
    let height = pe.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max)
        - pe.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
    let depth = cap_fraction * height;
    let apex_i = top(&pi);
    let cap: Vec<DVec3> = pi
        .iter()
        .copied()
        .filter(|p| p.z >= apex_i.z - depth)
        .collect();
    let apex_t = top(&pe) - apex_i;
    let mut t = apex_t;
    let mut residual = 0.0;
    for _ in 0..100 {
        let mut r: Vec<(f64, DVec3)> = cap
            .iter()
            .map(|&q| {
                let (c, _, _) = target.closest(q + t);
                let d = c - (q + t);
                (d.length(), d)
            })
            .collect();
        r.sort_by(|a, b| a.0.total_cmp(&b.0));
        let keep = &r[..(r.len() * 9 / 10).max(1)];
        let step = keep.iter().map(|x| x.1).sum::<DVec3>() / keep.len() as f64;
        residual = keep.iter().map(|x| x.0).sum::<f64>() / keep.len() as f64;
        t += step;
        if step.length() < 1e-4 {
            break;
        }
    }
    Some(Alignment {
        translation_mm: t.to_array(),
        apex_translation_mm: apex_t.to_array(),
        cap_depth_mm: depth,
        cap_points: cap.len(),
        cap_residual_mm: residual,
    })
}

/// Distances between the surface (`moved`, `tris`) and `target`, over the vertices `keep_moved`
/// of the moved surface and `keep_target` of the target (area-weighted means).
fn distances(
    moved: &[DVec3],
    tris: &[[u32; 3]],
    target: &Surface,
    keep_moved: &dyn Fn(usize) -> bool,
    keep_target: &dyn Fn(usize) -> bool,
) -> Option<(f64, f64, f64, f64, Vec<f64>)> {
    let moved_surface = Surface::new(moved, tris)?;
    let am = vertex_areas(moved, tris);
    let at = vertex_areas(&target.p, &target.tris);
    let (mut fw, mut fa, mut rw, mut ra) = (0.0, 0.0, 0.0, 0.0);
    let mut all = Vec::new();
    for (i, &q) in moved.iter().enumerate() {
        if keep_moved(i) {
            let d = (target.closest(q).0 - q).length();
            fw += am[i] * d;
            fa += am[i];
            all.push(d);
        }
    }
    for (j, &v) in target.p.iter().enumerate() {
        if keep_target(j) {
            let d = (moved_surface.closest(v).0 - v).length();
            rw += at[j] * d;
            ra += at[j];
            all.push(d);
        }
    }
    Some((fw, fa, rw, ra, all))
}

fn summarise(fw: f64, fa: f64, rw: f64, ra: f64, mut all: Vec<f64>) -> SurfaceDistance {
    all.sort_by(|a, b| a.total_cmp(b));
    let forward = fw / fa.max(1e-300);
    let reverse = rw / ra.max(1e-300);
    SurfaceDistance {
        mssd_mm: 0.5 * (forward + reverse),
        exhale_to_inhale_mm: forward,
        inhale_to_exhale_mm: reverse,
        p95_mm: all
            .get(((all.len() as f64 * 0.95) as usize).min(all.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0),
        max_mm: all.last().copied().unwrap_or(0.0),
    }
}

/// Whole-surface distances.
fn distance(moved: &[DVec3], tris: &[[u32; 3]], target: &Surface) -> SurfaceDistance {
    match distances(moved, tris, target, &|_| true, &|_| true) {
        Some((fw, fa, rw, ra, all)) => summarise(fw, fa, rw, ra, all),
        None => SurfaceDistance {
            mssd_mm: f64::INFINITY,
            exhale_to_inhale_mm: f64::INFINITY,
            inhale_to_exhale_mm: f64::INFINITY,
            p95_mm: f64::INFINITY,
            max_mm: f64::INFINITY,
        },
    }
}

/// The exhale lung with its operator: what every round of the fit needs.
struct Problem<'a> {
    side: Side,
    mesh: &'a TriMesh,
    p: Vec<DVec3>,
    /// `T·m_k` for each monomial `m_k` of the force degree (box coordinates), one column each,
    /// then `T·ψ_j` for each local term's centre.
    columns: Vec<Vec<f64>>,
    /// The local terms' centres (mm, exhale frame) and reach.
    local: Local,
    lo: DVec3,
    hi: DVec3,
    target: &'a Surface,
    inhale_ml: f64,
    /// Per inhale vertex, the exhale vertex it lies nearest to (for the folds).
    owner: Vec<u32>,
    opts: PairOptions,
}

/// One fitted model: force coefficients and direction field.
struct Model {
    theta: Vec<f64>,
    field: Field,
}

impl Problem<'_> {
    /// Per-vertex elastostatic force `F = Σ θ_k T·m_k`.
    fn force(&self, theta: &[f64]) -> Vec<f64> {
        (0..self.p.len())
            .map(|i| theta.iter().zip(&self.columns).map(|(t, c)| t * c[i]).sum())
            .collect()
    }

    /// The model's directions at the exhale vertices (the field evaluated in place).
    fn directions(&self, field: &Field) -> Vec<DVec3> {
        self.p
            .iter()
            .map(|&x| {
                let d = field.displacement(x);
                let l = d.length();
                if l > 1e-300 && l.is_finite() {
                    d / l
                } else {
                    DVec3::ZERO
                }
            })
            .collect()
    }

    /// The exhale vertices driven to the inhale volume by a kernel with these forces and
    /// directions (the bake's own normalisation and volume cubic).
    fn driven(&self, force: &[f64], dirs: Vec<DVec3>) -> Result<Vec<DVec3>, PairFitError> {
        let model = self.model(force, dirs)?;
        Ok(at_volume(&model, self.inhale_ml - model.start_volume_ml))
    }

    /// The kernel's model for these forces and directions (the bake's normalisation).
    fn model(&self, force: &[f64], dirs: Vec<DVec3>) -> Result<LungModel, PairFitError> {
        let (model, _, _) =
            LungModel::from_force_and_directions(self.side, self.mesh.clone(), dirs, force)
                .map_err(crate::kernel::BakeError::from)?;
        Ok(model)
    }

    /// Fit on the exhale vertices with `train[i]` (and the inhale vertices they own).
    fn fit(&self, train: &[bool]) -> Result<Model, PairFitError> {
        let n = self.p.len();
        let tris = &self.mesh.triangles;
        let e_ml = volume_ml(&self.p, tris);
        let centre = self.p.iter().sum::<DVec3>() / n as f64;
        let k = (self.inhale_ml / e_ml).cbrt() - 1.0;
        let mut u: Vec<DVec3> = self.p.iter().map(|&x| k * (x - centre)).collect();
        let mut model = None;
        // Every training vertex pulls itself, so the force's rows are the training vertices in
        // every round: its normal equations are built once (and factored once per stiffness).
        let mut system = self.force_system((0..n).filter(|&i| train[i]).collect());
        let adj = neighbour_rows(n, tris);
        for round in 0..self.opts.iterations {
            system.stiffen(local_stiffness(round, self.opts.iterations))?;
            let q: Vec<DVec3> = self.p.iter().zip(&u).map(|(a, b)| *a + *b).collect();
            let moved = Surface::new(&q, tris).ok_or(PairFitError::Singular("surface"))?;
            let pull = pulls(
                &moved,
                (self.target, &self.owner),
                train,
                self.opts.normal_gate_deg,
                &adj,
            );
            let (mut at, mut goal) = (Vec::new(), Vec::new());
            for i in (0..n).filter(|&i| train[i]) {
                at.push(self.p[i]);
                goal.push(u[i] + pull[i]);
            }
            let field = fit_field(
                Config::Poly {
                    degree: self.opts.field_degree,
                    lambda: self.opts.field_ridge,
                },
                self.side,
                &at,
                &goal,
            )
            .map_err(|_| PairFitError::Singular("direction field"))?;
            let dirs = self.directions(&field);
            debug_assert_eq!(goal.len(), system.idx.len());
            let magnitude: Vec<f64> = system
                .idx
                .iter()
                .zip(&goal)
                .map(|(&i, g)| dirs[i].dot(*g))
                .collect();
            let theta = self.solve_force(&system, &magnitude)?;
            let force = self.force(&theta);
            u = (0..n).map(|i| force[i] * dirs[i]).collect();
            model = Some(Model { theta, field });
        }
        model.ok_or(PairFitError::Option("--iterations 0: give 1 to 200".into()))
    }

    /// The normal equations of `min Σ_i ((Σ_k θ_k C_k)_i − m_i)² + λ‖θ‖²` over the rows `idx`, to
    /// be factored by [`ForceSystem::stiffen`]: a vanishing ridge on every coefficient (1e-9 of the
    /// mean diagonal), and `force_local_ridge` times their own mean diagonal on the local terms'.
    fn force_system(&self, idx: Vec<usize>) -> ForceSystem {
        let first_local = self.columns.len() - self.local.centres.len();
        let kk = self.columns.len();
        let mut a = DMatrix::<f64>::zeros(kk, kk);
        for &i in &idx {
            for x in 0..kk {
                let cx = self.columns[x][i];
                for y in 0..kk {
                    a[(x, y)] += cx * self.columns[y][i];
                }
            }
        }
        let trace = (0..kk).map(|x| a[(x, x)]).sum::<f64>() / kk as f64;
        for x in 0..kk {
            a[(x, x)] += 1e-9 * trace;
        }
        let local_mean =
            (first_local..kk).map(|x| a[(x, x)]).sum::<f64>() / (kk - first_local).max(1) as f64;
        ForceSystem {
            idx,
            chol: None,
            gram: a,
            first_local,
            local_ridge: self.opts.force_local_ridge * local_mean,
            stiffness: f64::NAN,
        }
    }

    /// The force coefficients for the magnitudes `m` wanted at the system's rows.
    fn solve_force(&self, system: &ForceSystem, m: &[f64]) -> Result<Vec<f64>, PairFitError> {
        let kk = self.columns.len();
        let mut b = DVector::<f64>::zeros(kk);
        for (r, &i) in system.idx.iter().enumerate() {
            for x in 0..kk {
                b[x] += self.columns[x][i] * m[r];
            }
        }
        let theta = system
            .chol
            .as_ref()
            .ok_or(PairFitError::Singular("force"))?
            .solve(&b);
        theta
            .iter()
            .all(|v| v.is_finite())
            .then(|| theta.iter().copied().collect())
            .ok_or(PairFitError::Singular("force"))
    }
}

/// The force's normal equations over a fit's rows, factored with the local terms' ridge times a
/// stiffness.
struct ForceSystem {
    idx: Vec<usize>,
    chol: Option<nalgebra::Cholesky<f64, nalgebra::Dyn>>,
    /// The normal equations before the local terms' ridge.
    gram: DMatrix<f64>,
    first_local: usize,
    /// The local terms' ridge at stiffness 1.
    local_ridge: f64,
    stiffness: f64,
}

impl ForceSystem {
    /// Refactor with the local terms' ridge times `stiffness` (nothing to do without local terms or
    /// when it is the one in use).
    fn stiffen(&mut self, stiffness: f64) -> Result<(), PairFitError> {
        if stiffness == self.stiffness
            || (self.chol.is_some() && self.first_local == self.gram.ncols())
        {
            return Ok(());
        }
        let mut a = self.gram.clone();
        for x in self.first_local..a.ncols() {
            a[(x, x)] += stiffness * self.local_ridge;
        }
        self.chol = Some(a.cholesky().ok_or(PairFitError::Singular("force"))?);
        self.stiffness = stiffness;
        Ok(())
    }
}

/// The cosine below which two normals are incompatible (none at 180°).
fn gate_cos(normal_gate_deg: f64) -> f64 {
    if normal_gate_deg >= 180.0 {
        f64::NEG_INFINITY
    } else {
        normal_gate_deg.to_radians().cos()
    }
}

/// One round's pull on each training vertex of the `moved` surface (zero elsewhere): the mean of
/// its own pull to its closest target point and of the pulls of the target vertices that find it
/// nearest (the symmetric ICP), each kept only where the two surfaces' normals there lie within
/// `normal_gate_deg` (normal compatibility, Rusinkiewicz & Levoy 2001, as in Amberg et al. 2007's
/// non-rigid ICP). At a deep breath the base moves centimetres: the closest point of a vertex on
/// the posterior wall is then on the inhale diaphragm, whose normal points down where the wall's
/// points back, and following it slides the wall down past the recess, overtaking the base (the
/// folds). A training vertex left without a compatible pull takes the mean of its neighbours'
/// pulls, ring by ring, rather than being held where it is.
fn pulls(
    moved: &Surface,
    (target, owner): (&Surface, &[u32]),
    train: &[bool],
    normal_gate_deg: f64,
    adj: &(Vec<usize>, Vec<u32>),
) -> Vec<DVec3> {
    let n = moved.p.len();
    let gate = gate_cos(normal_gate_deg);
    let mut pull = vec![DVec3::ZERO; n];
    let mut count = vec![0.0f64; n];
    for i in (0..n).filter(|&i| train[i]) {
        let (c, _, normal) = target.closest(moved.p[i]);
        if moved.vert_n[i].dot(normal) >= gate {
            pull[i] += c - moved.p[i];
            count[i] += 1.0;
        }
    }
    for (j, &v) in target.p.iter().enumerate() {
        if !train[owner[j] as usize] {
            continue;
        }
        let (c, near, normal) = moved.closest(v);
        if train[near as usize] && target.vert_n[j].dot(normal) >= gate {
            pull[near as usize] += v - c;
            count[near as usize] += 1.0;
        }
    }
    for i in 0..n {
        if count[i] > 0.0 {
            pull[i] /= count[i];
        }
    }
    fill_from_neighbours(&mut pull, &mut count, train, adj);
    pull
}

/// Training vertices without a pull (`count` 0) take the mean pull of their neighbours that have
/// one, ring by ring; a vertex no ring reaches keeps none.
fn fill_from_neighbours(
    pull: &mut [DVec3],
    count: &mut [f64],
    train: &[bool],
    (offsets, flat): &(Vec<usize>, Vec<u32>),
) {
    loop {
        let mut filled = Vec::new();
        for i in (0..pull.len()).filter(|&i| train[i] && count[i] == 0.0) {
            let (mut sum, mut k) = (DVec3::ZERO, 0.0);
            for j in flat[offsets[i]..offsets[i + 1]].iter().map(|&j| j as usize) {
                if train[j] && count[j] > 0.0 {
                    sum += pull[j];
                    k += 1.0;
                }
            }
            if k > 0.0 {
                filled.push((i, sum / k));
            }
        }
        if filled.is_empty() {
            return;
        }
        for (i, v) in filled {
            pull[i] = v;
            count[i] = 1.0;
        }
    }
}

/// The local terms' stiffness in round `round` of `rounds`: 1000, 100, 10, then 1 times their
/// ridge over four equal stages (fewer than four rounds end before the last). The first rounds'
/// closest points are far from where each vertex belongs (the base moves centimetres); free local
/// terms would follow them and slide the surface (annealed stiffness, as in Amberg et al. 2007's
/// optimal-step non-rigid ICP).
fn local_stiffness(round: usize, rounds: usize) -> f64 {
    let stage = (4 * round / rounds.max(1)).min(3) as i32;
    10f64.powi(3 - stage)
}

/// The applied force's local terms: centres on the exhale surface and their reach.
#[derive(Debug, Clone, Default)]
struct Local {
    centres: Vec<DVec3>,
    radius_mm: f64,
}

/// A local term reaches this many times the centres' spacing (`√(area / centres)`): a point of the
/// surface lies within reach of about ten centres, so the sum is smooth between them.
pub const LOCAL_REACH: f64 = 2.5;

/// Default normal compatibility of the ICP's correspondences, degrees ([`PairOptions::normal_gate_deg`]).
pub const NORMAL_GATE_DEG: f64 = 60.0;

/// The narrowest normal gate taken, degrees.
pub const MIN_NORMAL_GATE_DEG: f64 = 10.0;

impl Local {
    /// `count` farthest-point centres on the surface `p` (0: none).
    fn on_surface(p: &[DVec3], tris: &[[u32; 3]], count: usize) -> Self {
        if count == 0 {
            return Self::default();
        }
        let area: f64 = vertex_areas(p, tris).iter().sum();
        let centres = farthest_seeds(p, count).iter().map(|&i| p[i]).collect();
        Self {
            centres,
            radius_mm: LOCAL_REACH * (area / count as f64).sqrt(),
        }
    }
}

/// The largest volume change above the model's start volume, up to `up_to_ml`, up to which its
/// surface was found not to cross itself ([`crate::folds::fold_free_share`]): `up_to_ml` when no
/// fold was found up to there.
pub fn fold_free_ml(model: &LungModel, up_to_ml: f64) -> f64 {
    crate::folds::fold_free_share(model, up_to_ml) * up_to_ml
}

/// `count` farthest-point samples of `p` (indices), the first the highest point.
fn farthest_seeds(p: &[DVec3], count: usize) -> Vec<usize> {
    let mut seeds = vec![p
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.z.total_cmp(&b.1.z))
        .map_or(0, |x| x.0)];
    let mut near: Vec<f64> = p.iter().map(|x| (*x - p[seeds[0]]).length()).collect();
    while seeds.len() < count.min(p.len()) {
        let far = near
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map_or(0, |x| x.0);
        seeds.push(far);
        for (i, x) in p.iter().enumerate() {
            near[i] = near[i].min((*x - p[far]).length());
        }
    }
    seeds
}

/// Patches of the surface (nearest of `count` farthest-point seeds, the first the highest vertex).
fn patches(p: &[DVec3], count: usize) -> Vec<usize> {
    let seeds = farthest_seeds(p, count);
    p.iter()
        .map(|x| {
            (0..seeds.len())
                .min_by(|&a, &b| {
                    (*x - p[seeds[a]])
                        .length_squared()
                        .total_cmp(&(*x - p[seeds[b]]).length_squared())
                })
                .unwrap_or(0)
        })
        .collect()
}

/// The exhale lung's transfer (as the bake builds it: graph, pitcher–catcher pass, amplitude
/// smoothing) and its response `Tᵀm_k` to each monomial of the force degree, then to each local
/// term, with the lung's box.
#[cfg(test)]
fn operator_columns(
    side: Side,
    exhale: &TriMesh,
    settings: &BakeSettings,
    degree: u8,
    local: &Local,
) -> Result<(crate::operator::Transfer, Vec<Vec<f64>>, DVec3, DVec3), PairFitError> {
    let transfer = operator(side, exhale, settings)?;
    let (columns, lo, hi) = columns(&transfer, exhale, degree, local);
    Ok((transfer, columns, lo, hi))
}

/// The exhale lung's transfer, as the bake builds it (graph, pitcher–catcher pass, amplitude
/// smoothing): the costly part of a fit, built once per pair ([`fit_pair_for_breath`]'s second fit
/// uses it again).
fn operator(
    side: Side,
    exhale: &TriMesh,
    settings: &BakeSettings,
) -> Result<crate::operator::Transfer, PairFitError> {
    let bb = exhale.aabb();
    let norm = |q| lung_model::deform::normalised_position(q, &bb, side);
    let graph = NodeGraph::from_mesh(exhale, &settings.elasticity, norm)
        .map_err(crate::kernel::BakeError::from)?;
    let mut transfer = compute_transfer(
        &graph,
        settings.tolerance,
        Schedule::SpringsForward,
        &|_| {},
    )
    .map_err(crate::kernel::BakeError::from)?;
    crate::smooth::smooth_amplitude(&mut transfer, exhale, settings.amplitude_smoothing_mm)
        .map_err(crate::kernel::BakeError::from)?;
    Ok(transfer)
}

/// The transfer's response `Tᵀm_k` to each monomial of the force degree, then to each local term,
/// with the lung's box.
fn columns(
    transfer: &crate::operator::Transfer,
    exhale: &TriMesh,
    degree: u8,
    local: &Local,
) -> (Vec<Vec<f64>>, DVec3, DVec3) {
    let bb = exhale.aabb();
    let p = points(exhale);
    let (lo, hi) = (
        DVec3::from(bb.min.map(|v| v as f64)),
        DVec3::from(bb.max.map(|v| v as f64)),
    );
    let exps = monomials(degree);
    let mut values = Vec::new();
    let mut basis = vec![vec![0.0; p.len()]; exps.len()];
    for (i, &x) in p.iter().enumerate() {
        monomial_values(box_coords(x, lo, hi), &exps, &mut values);
        for (k, v) in values.iter().enumerate() {
            basis[k][i] = *v;
        }
    }
    for c in &local.centres {
        basis.push(
            p.iter()
                .map(|x| wendland((*x - *c).length() / local.radius_mm))
                .collect(),
        );
    }
    let columns = basis.iter().map(|b| transfer.elastostatic(b)).collect();
    (columns, lo, hi)
}

/// What [`fit_pair`] checks before fitting: two closed one-body surfaces, the options' ranges, and
/// an inhale larger than the exhale. Their volumes (exhale, inhale), ml.
fn check_pair(
    exhale: &TriMesh,
    inhale: &TriMesh,
    opts: &PairOptions,
) -> Result<(f64, f64), PairFitError> {
    for (what, m) in [("exhale", exhale), ("inhale", inhale)] {
        lung_model::mesh::check(m).map_err(|e| PairFitError::Surface {
            what,
            message: e.to_string(),
        })?;
        // One lung: a surface of both lungs (or with stray pieces) would be fitted as one body.
        let bodies = crate::surface_checks::components(m).count;
        if bodies != 1 {
            return Err(PairFitError::Surface {
                what,
                message: format!(
                    "it holds {bodies} separate bodies; a breath-hold pair is fitted one lung at a \
                     time: give one lung's surface (e.g. `lungdyn mesh from-mask ... --lung L`, or \
                     the masks themselves)"
                ),
            });
        }
    }
    opts.validate()?;
    let (exhale_ml, inhale_ml) = (exhale.enclosed_volume_ml(), inhale.enclosed_volume_ml());
    if !(inhale_ml > exhale_ml) {
        return Err(PairFitError::NotInhaled {
            exhale_ml,
            inhale_ml,
        });
    }
    Ok((exhale_ml, inhale_ml))
}

/// What a pair's fits share: the pair checked and aligned, the inhale surface indexed, the exhale
/// lung's operator built, and which exhale vertex each inhale point lies nearest to.
struct Prepared<'a> {
    side: Side,
    exhale: &'a TriMesh,
    inhale: &'a TriMesh,
    settings: &'a BakeSettings,
    exhale_ml: f64,
    inhale_ml: f64,
    alignment: Alignment,
    /// The aligned inhale points (f32-rounded, as kept).
    pi: Vec<DVec3>,
    target: Surface,
    transfer: crate::operator::Transfer,
    owner: Vec<u32>,
}

/// Check, align and build the operator for a pair (see [`fit_pair`]).
fn prepare<'a>(
    side: Side,
    (exhale, inhale): (&'a TriMesh, &'a TriMesh),
    settings: &'a BakeSettings,
    opts: &PairOptions,
    progress: &dyn Fn(&str),
) -> Result<Prepared<'a>, PairFitError> {
    let (exhale_ml, inhale_ml) = check_pair(exhale, inhale, opts)?;
    progress("aligning the inhale apex and apical cap onto the exhale surface");
    let alignment = align(exhale, inhale, opts.cap_fraction).ok_or(PairFitError::Surface {
        what: "exhale",
        message: "could not be indexed for closest points".into(),
    })?;
    let t = DVec3::from(alignment.translation_mm);
    // Rounded to f32 as it is kept (and written with --surfaces-out), so the target measured
    // against is exactly the surface anyone checking gets.
    let pi: Vec<DVec3> = points(inhale)
        .iter()
        .map(|&x| (x + t).as_vec3().as_dvec3())
        .collect();
    let target = Surface::new(&pi, &inhale.triangles).ok_or(PairFitError::Surface {
        what: "inhale",
        message: "could not be indexed for closest points".into(),
    })?;
    progress("building the exhale lung's operator (the bake's Green's-function pass)");
    let transfer = operator(side, exhale, settings)?;
    let p = points(exhale);
    let exhale_surface = Surface::new(&p, &exhale.triangles).ok_or(PairFitError::Surface {
        what: "exhale",
        message: "could not be indexed for closest points".into(),
    })?;
    let owner: Vec<u32> = pi.iter().map(|&v| exhale_surface.closest(v).1).collect();
    Ok(Prepared {
        side,
        exhale,
        inhale,
        settings,
        exhale_ml,
        inhale_ml,
        alignment,
        pi,
        target,
        transfer,
        owner,
    })
}

/// Fit `side`'s motion from the exhale surface to the inhale surface (both closed, mm, body frame,
/// not registered). `settings` gives the operator (elasticity, tolerance, amplitude smoothing) the
/// bake will use; `progress` hears each stage.
pub fn fit_pair(
    side: Side,
    exhale: &TriMesh,
    inhale: &TriMesh,
    settings: &BakeSettings,
    opts: &PairOptions,
    progress: &dyn Fn(&str),
) -> Result<PairFit, PairFitError> {
    let prepared = prepare(side, (exhale, inhale), settings, opts, progress)?;
    fit_prepared(&prepared, opts, progress)
}

/// [`fit_pair`] on a pair already prepared (`opts` valid: [`check_pair`] checked them, or they
/// differ from those only in the local terms' count).
fn fit_prepared(
    prepared: &Prepared,
    opts: &PairOptions,
    progress: &dyn Fn(&str),
) -> Result<PairFit, PairFitError> {
    let Prepared {
        side,
        exhale,
        inhale,
        settings,
        ..
    } = *prepared;
    let (exhale_ml, inhale_ml) = (prepared.exhale_ml, prepared.inhale_ml);
    let transfer = &prepared.transfer;
    let p = points(exhale);
    let local = Local::on_surface(&p, &exhale.triangles, opts.force_centres);
    let (columns, lo, hi) = columns(transfer, exhale, opts.force_degree, &local);
    let problem = Problem {
        side,
        mesh: exhale,
        p: p.clone(),
        columns,
        local,
        lo,
        hi,
        target: &prepared.target,
        inhale_ml,
        owner: prepared.owner.clone(),
        opts: *opts,
    };
    progress("fitting the force and direction fields (symmetric ICP)");
    let all = vec![true; p.len()];
    let fitted = problem.fit(&all)?;
    let n_poly = fitted.theta.len() - problem.local.centres.len();
    let force = ForceField {
        lo: problem.lo.to_array(),
        hi: problem.hi.to_array(),
        degree: opts.force_degree,
        coeffs: fitted.theta[..n_poly].to_vec(),
        centres: problem.local.centres.iter().map(|c| c.to_array()).collect(),
        weights: fitted.theta[n_poly..].to_vec(),
        radius_mm: problem.local.radius_mm,
    };
    // What the bake does with these fields (kernel::bake: applied forces, the operator, the
    // field's directions in the mesh's box, the volume normalisation), driven to the inhale volume.
    let mut baked = settings.clone();
    baked.force_field = Some(force.clone());
    baked.direction_field = Some(fitted.field.clone());
    let applied = crate::kernel::applied_forces(exhale, side, &baked);
    let elastostatic = transfer.elastostatic(&applied);
    let dirs = LungModel::field_directions(exhale, &fitted.field);
    let kernel_model = problem.model(&elastostatic, dirs)?;
    let delta_ml = inhale_ml - kernel_model.start_volume_ml;
    let moved = at_volume(&kernel_model, delta_ml);
    let in_sample = distance(&moved, &exhale.triangles, problem.target);
    let mut lengths: Vec<f64> = moved
        .iter()
        .zip(&p)
        .map(|(a, b)| (*a - *b).length())
        .collect();
    lengths.sort_by(|a, b| a.total_cmp(b));
    let at = |q: f64| lengths[((lengths.len() - 1) as f64 * q).round() as usize];
    let displacement_mm = [at(0.5), at(0.99), at(1.0)];
    let cross_validated = if opts.folds >= 2 {
        progress("held-out error: each part of the surface fitted without itself");
        Some(cross_validate(&problem)?)
    } else {
        None
    };
    let centre = volume_centroid(&p, &exhale.triangles);
    let k = (inhale_ml / exhale_ml).cbrt();
    let scaled: Vec<DVec3> = p.iter().map(|&x| centre + k * (x - centre)).collect();
    let to_mesh = |q: &[DVec3]| TriMesh {
        positions: q.iter().map(|x| x.as_vec3().to_array()).collect(),
        triangles: exhale.triangles.clone(),
    };
    let moved_mesh = to_mesh(&moved);
    let folds_at_inhale = crate::surface_checks::self_intersections(&moved_mesh, 100_000).count;
    // Scanned even where the inhale is clean: a crossing can come and go below it (lung_bake::folds).
    progress("finding the largest volume change the kernel draws without a fold");
    let fold_free_ml = fold_free_ml(&kernel_model, delta_ml);
    Ok(PairFit {
        side,
        folds_at_inhale,
        fold_free_ml,
        displacement_mm,
        force,
        direction: fitted.field,
        alignment: prepared.alignment,
        exhale_ml,
        inhale_ml,
        in_sample,
        cross_validated,
        no_motion: distance(&p, &exhale.triangles, problem.target),
        uniform_scaling: distance(&scaled, &exhale.triangles, problem.target),
        options: *opts,
        moved: moved_mesh,
        inhale_aligned: TriMesh {
            positions: prepared.pi.iter().map(|x| x.as_vec3().to_array()).collect(),
            triangles: inhale.triangles.clone(),
        },
    })
}

/// Whether `fit`'s kernel draws a breath of `share_ml` above the exhale volume without a fold (none
/// found up to the pair's own inspiration counts, whatever the share).
pub fn draws_breath(fit: &PairFit, share_ml: f64) -> bool {
    let pair_ml = fit.inhale_ml - fit.exhale_ml;
    // The kernel's start volume and the exhale surface's are the same mesh's, summed apart.
    fit.fold_free_ml >= share_ml.min(pair_ml) - 1e-6 * fit.exhale_ml
}

/// [`fit_pair`] for a lung that will breathe breaths of `share_ml` (its part of a tidal breath):
/// when the fit with local force terms folds the surface within that breath (they can, on a fine
/// mesh, where the polynomial alone does not), the polynomial force alone is fitted too and kept if
/// it draws the breath without a fold. The fit returned says which in `options.force_centres`.
pub fn fit_pair_for_breath(
    side: Side,
    exhale: &TriMesh,
    inhale: &TriMesh,
    settings: &BakeSettings,
    opts: &PairOptions,
    share_ml: f64,
    progress: &dyn Fn(&str),
) -> Result<PairFit, PairFitError> {
    let prepared = prepare(side, (exhale, inhale), settings, opts, progress)?;
    let fit = fit_prepared(&prepared, opts, progress)?;
    keep_for_breath(fit, share_ml, || {
        progress(
            "with local force terms it folds within a tidal breath: fitting the polynomial alone",
        );
        let plain = PairOptions {
            force_centres: 0,
            ..*opts
        };
        // The same pair, alignment and operator: only the force's terms differ.
        fit_prepared(&prepared, &plain, progress)
    })
}

/// `fit`, unless it has local terms and folds within `share_ml` while `plain()` does not.
fn keep_for_breath(
    fit: PairFit,
    share_ml: f64,
    plain: impl FnOnce() -> Result<PairFit, PairFitError>,
) -> Result<PairFit, PairFitError> {
    if fit.options.force_centres == 0 || draws_breath(&fit, share_ml) {
        return Ok(fit);
    }
    let other = plain()?;
    Ok(if draws_breath(&other, share_ml) {
        other
    } else {
        fit
    })
}

/// Patches each fold holds out: ten scattered patches (each about 2 % of the surface at five
/// folds, a few centimetres across), so a fold tests the fit across holes the size of a lobe's
/// corner rather than across a missing quarter of the lung, where a polynomial can only
/// extrapolate.
pub const PATCHES_PER_FOLD: usize = 10;

/// Held-out symmetric distance: patches dealt into folds, each fold fitted without itself.
fn cross_validate(problem: &Problem) -> Result<SurfaceDistance, PairFitError> {
    let k = problem.opts.folds;
    let patch = patches(&problem.p, PATCHES_PER_FOLD * k);
    let fold_of_patch = folds(PATCHES_PER_FOLD * k, k, problem.opts.seed);
    let fold: Vec<usize> = patch.iter().map(|&c| fold_of_patch[c]).collect();
    let (mut fw, mut fa, mut rw, mut ra) = (0.0, 0.0, 0.0, 0.0);
    let mut all = Vec::new();
    for f in 0..k {
        let train: Vec<bool> = fold.iter().map(|&x| x != f).collect();
        let model = problem.fit(&train)?;
        let force = problem.force(&model.theta);
        let moved = problem.driven(&force, problem.directions(&model.field))?;
        let held = |i: usize| fold[i] == f;
        let owned = |j: usize| fold[problem.owner[j] as usize] == f;
        let (a, b, c, d, e) = distances(
            &moved,
            &problem.mesh.triangles,
            problem.target,
            &held,
            &owned,
        )
        .ok_or(PairFitError::Singular("held-out surface"))?;
        fw += a;
        fa += b;
        rw += c;
        ra += d;
        all.extend(e);
    }
    Ok(summarise(fw, fa, rw, ra, all))
}

/// Mean symmetric surface distance (and its parts) between two closed surfaces, area-weighted
/// over vertices, exact point-to-triangle: how `fit_pair` measures, for anyone checking a bake.
pub fn surface_distance(moved: &TriMesh, target: &TriMesh) -> Option<SurfaceDistance> {
    let t = Surface::new(&points(target), &target.triangles)?;
    let (fw, fa, rw, ra, all) =
        distances(&points(moved), &moved.triangles, &t, &|_| true, &|_| true)?;
    Some(summarise(fw, fa, rw, ra, all))
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::anatomy;

    /// A known breath: zero at the apex, growing towards the base (down, forward, outward), then
    /// the whole inhale lung shifted as a patient lying down again would be.
    fn breathe(mesh: &TriMesh, shift: DVec3) -> TriMesh {
        let p = points(mesh);
        let top = p.iter().map(|x| x.z).fold(f64::NEG_INFINITY, f64::max);
        let bottom = p.iter().map(|x| x.z).fold(f64::INFINITY, f64::min);
        let c = p.iter().sum::<DVec3>() / p.len() as f64;
        TriMesh {
            positions: p
                .iter()
                .map(|&x| {
                    let t = (top - x.z) / (top - bottom);
                    let d = t * t * DVec3::new(0.12 * (x.x - c.x), 0.1 * (x.y - c.y) + 4.0, -22.0);
                    (x + d + shift).as_vec3().to_array()
                })
                .collect(),
            triangles: mesh.triangles.clone(),
        }
    }

    /// A breath that moves the base down by up to 60 mm and leaves the apex: the walls' closest
    /// points on the moved base lie across the recess, with normals pointing another way. Kept,
    /// they pull hundreds of vertices against their true motion and off along their normals;
    /// gated, they are dropped and the vertices take compatible neighbours' pulls.
    #[test]
    fn incompatible_normals_are_not_followed_and_their_vertices_take_their_neighbours_pulls() {
        let mesh = anatomy::lung(Side::Right, 3000).unwrap();
        let p = points(&mesh);
        let c = p.iter().sum::<DVec3>() / p.len() as f64;
        let truth: Vec<DVec3> = p
            .iter()
            .map(|x| {
                DVec3::new(
                    0.0,
                    0.0,
                    40.0 * ((x.z - c.z) / 120.0 - 0.5).clamp(-1.5, 0.0),
                )
            })
            .collect();
        let inhale: Vec<DVec3> = p.iter().zip(&truth).map(|(x, d)| *x + *d).collect();
        let (exhale, target) = (
            Surface::new(&p, &mesh.triangles).unwrap(),
            Surface::new(&inhale, &mesh.triangles).unwrap(),
        );
        let owner: Vec<u32> = target.p.iter().map(|&v| exhale.closest(v).1).collect();
        let adj = neighbour_rows(p.len(), &mesh.triangles);
        let train = vec![true; p.len()];
        // Pulls against the true motion, and the mean error along each vertex's normal, mm.
        let judge = |deg: f64| {
            let pull = pulls(&exhale, (&target, &owner), &train, deg, &adj);
            assert!(pull.iter().all(|v| v.is_finite()));
            let opposed = pull
                .iter()
                .zip(&truth)
                .filter(|(v, d)| v.dot(**d) < 0.0)
                .count();
            let along_normal = (0..p.len())
                .map(|i| (pull[i] - truth[i]).dot(exhale.vert_n[i]).abs())
                .sum::<f64>()
                / p.len() as f64;
            (opposed, along_normal)
        };
        let (all, gated) = (judge(180.0), judge(NORMAL_GATE_DEG));
        // A vertex with no pull at all is one no correspondence moves (the still apex, or a gated
        // vertex left unfilled): the gate leaves no more of them than following every one does.
        let still = |deg: f64| {
            let pull = pulls(&exhale, (&target, &owner), &train, deg, &adj);
            pull.iter().filter(|v| **v == DVec3::ZERO).count()
        };
        assert!(
            still(NORMAL_GATE_DEG) <= still(180.0),
            "gated vertices left without a pull"
        );
        assert!(
            2 * gated.0 < all.0 && 2.0 * gated.1 < all.1,
            "pulls against the motion, error along the normal: {gated:?} with the gate, {all:?} without"
        );
        // The lower half without pulls of its own takes the upper half's, ring by ring; vertices
        // outside the training set keep none.
        let mut pull: Vec<DVec3> = p.iter().map(|x| DVec3::Z * f64::from(x.z > c.z)).collect();
        let mut count: Vec<f64> = pull.iter().map(|v| v.z).collect();
        let odd: Vec<bool> = (0..p.len()).map(|i| i % 7 != 0).collect();
        fill_from_neighbours(&mut pull, &mut count, &odd, &adj);
        for i in 0..p.len() {
            let want = if odd[i] || p[i].z > c.z {
                DVec3::Z
            } else {
                DVec3::ZERO
            };
            assert!((pull[i] - want).length() < 1e-12, "vertex {i}: {}", pull[i]);
        }
        // Vertices outside the training set are neither pulled nor filled.
        let half: Vec<bool> = (0..p.len()).map(|i| i % 2 == 0).collect();
        let pull = pulls(&exhale, (&target, &owner), &half, NORMAL_GATE_DEG, &adj);
        assert!((0..p.len()).all(|i| half[i] || pull[i] == DVec3::ZERO));
    }

    #[test]
    fn a_known_breath_is_recovered_through_the_operator_and_beats_the_baselines() {
        let exhale = anatomy::lung(Side::Right, 3000).unwrap();
        let shift = DVec3::new(4.0, -3.0, 35.0);
        let inhale = breathe(&exhale, shift);
        let opts = PairOptions {
            iterations: 30,
            folds: 3,
            ..PairOptions::default()
        };
        let settings = BakeSettings::default_for(Side::Right);
        let fit = fit_pair(Side::Right, &exhale, &inhale, &settings, &opts, &|_| {}).unwrap();
        // The apex does not move in this breath: the alignment undoes the shift.
        let t = DVec3::from(fit.alignment.translation_mm);
        assert!(
            (t + shift).length() < 2.0,
            "translation {t} for shift {shift}"
        );
        let (none, scale, ins) = (
            fit.no_motion.mssd_mm,
            fit.uniform_scaling.mssd_mm,
            fit.in_sample.mssd_mm,
        );
        assert!(
            ins < 0.35 * none && ins < scale,
            "fit {ins} none {none} scaling {scale}"
        );
        let cv = fit.cross_validated.unwrap().mssd_mm;
        assert!(
            cv.is_finite() && cv >= 0.0 && cv < none,
            "held out {cv}, none {none}"
        );
        // The moved surface is the fitted kernel driven to the inhale volume.
        assert!((fit.moved.enclosed_volume_ml() / fit.inhale_ml - 1.0).abs() < 1e-3);
        // The figure is the distance between the two surfaces it keeps.
        let again = surface_distance(&fit.moved, &fit.inhale_aligned).unwrap();
        assert!((again.mssd_mm - ins).abs() < 1e-9);
        // Deterministic: the same inputs give the same bits.
        let twice = fit_pair(Side::Right, &exhale, &inhale, &settings, &opts, &|_| {}).unwrap();
        assert_eq!(twice.force, fit.force);
        assert_eq!(twice.in_sample, fit.in_sample);
    }

    /// A breath that moves one part of the wall, the size of a lobe's corner, twice as far as the
    /// rest, which a cubic force cannot follow: the local terms follow it, and the kernel baked from
    /// what is written draws it.
    #[test]
    fn local_force_terms_follow_a_local_bulge_the_polynomial_cannot() {
        let exhale = anatomy::lung(Side::Right, 3000).unwrap();
        let plain = breathe(&exhale, DVec3::ZERO);
        let p = points(&exhale);
        let (top, bottom) = p
            .iter()
            .fold((f64::MIN, f64::MAX), |(t, b), x| (t.max(x.z), b.min(x.z)));
        let c = p.iter().sum::<DVec3>() / p.len() as f64;
        // The most lateral vertex two thirds of the way down, where the breath moves the wall far.
        let level = top - 0.65 * (top - bottom);
        let at = *p
            .iter()
            .filter(|x| (x.z - level).abs() < 10.0)
            .max_by(|a, b| (a.x - c.x).abs().total_cmp(&(b.x - c.x).abs()))
            .unwrap();
        let inhale = TriMesh {
            positions: plain
                .positions
                .iter()
                .zip(&p)
                .map(|(q, x)| {
                    let u = DVec3::from(q.map(|v| v as f64)) - *x;
                    (*x + u * (1.0 + wendland((*x - at).length() / 40.0)))
                        .as_vec3()
                        .to_array()
                })
                .collect(),
            triangles: exhale.triangles.clone(),
        };
        let settings = BakeSettings::default_for(Side::Right);
        let fit = |centres| {
            let opts = PairOptions {
                iterations: 30,
                folds: 0,
                force_centres: centres,
                force_local_ridge: 0.01,
                ..PairOptions::default()
            };
            fit_pair(Side::Right, &exhale, &inhale, &settings, &opts, &|_| {}).unwrap()
        };
        let (poly, local) = (fit(0), fit(64));
        assert!(poly.force.centres.is_empty() && poly.force.weights.is_empty());
        assert_eq!(local.force.centres.len(), 64);
        assert_eq!(local.force.weights.len(), 64);
        assert!(local.force.radius_mm > 10.0 && local.force.validate().is_ok());
        // Near the bulge (within its reach) the local terms land closer to the inhale surface.
        let near = |fit: &PairFit| {
            let t =
                Surface::new(&points(&fit.inhale_aligned), &fit.inhale_aligned.triangles).unwrap();
            let moved = points(&fit.moved);
            let d: Vec<f64> = p
                .iter()
                .zip(&moved)
                .filter(|(x, _)| (**x - at).length() < 30.0)
                .map(|(_, q)| (t.closest(*q).0 - *q).length())
                .collect();
            d.iter().sum::<f64>() / d.len() as f64
        };
        let (np, nl) = (near(&poly), near(&local));
        assert!(
            nl < 0.75 * np,
            "near the bulge: local {nl} mm, polynomial {np} mm"
        );
        assert!(
            local.in_sample.mssd_mm < poly.in_sample.mssd_mm,
            "{} {}",
            local.in_sample.mssd_mm,
            poly.in_sample.mssd_mm
        );
        // The figure is the bake's: the written force (local terms included) through the operator.
        let mut baked = settings.clone();
        baked.force_field = Some(local.force.clone());
        baked.direction_field = Some(local.direction.clone());
        let (transfer, _, _, _) =
            operator_columns(Side::Right, &exhale, &settings, 1, &Local::default()).unwrap();
        let force =
            transfer.elastostatic(&crate::kernel::applied_forces(&exhale, Side::Right, &baked));
        let dirs = LungModel::field_directions(&exhale, &local.direction);
        let (model, _, _) =
            LungModel::from_force_and_directions(Side::Right, exhale.clone(), dirs, &force)
                .unwrap();
        let again = at_volume(&model, local.inhale_ml - model.start_volume_ml);
        let worst = again
            .iter()
            .zip(points(&local.moved))
            .map(|(a, b)| (*a - b).length())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-3,
            "the bake of the written force differs by {worst} mm"
        );
    }

    #[test]
    fn a_fit_that_folds_within_the_breath_gives_way_to_the_polynomial_alone_if_that_does_not() {
        let exhale = anatomy::lung(Side::Left, 1500).unwrap();
        let inhale = breathe(&exhale, DVec3::ZERO);
        let settings = BakeSettings::default_for(Side::Left);
        let opts = PairOptions {
            iterations: 8,
            folds: 0,
            force_centres: 16,
            ..PairOptions::default()
        };
        let local = fit_pair(Side::Left, &exhale, &inhale, &settings, &opts, &|_| {}).unwrap();
        let with = |folds: usize, free: f64, centres: usize| {
            let mut f = local.clone();
            f.folds_at_inhale = folds;
            f.fold_free_ml = free;
            f.options.force_centres = centres;
            f
        };
        let asked = std::cell::Cell::new(0);
        let plain = |folds, free| {
            asked.set(asked.get() + 1);
            Ok(with(folds, free, 0))
        };
        let pick = |fit: PairFit, p: (usize, f64)| {
            keep_for_breath(fit, 250.0, || plain(p.0, p.1))
                .unwrap()
                .options
                .force_centres
        };
        // Fold-free over the breath (or nowhere up to the pair's inspiration, a smaller breath
        // than the share here): kept, the polynomial never fitted.
        let pair = local.inhale_ml - local.exhale_ml;
        assert!(
            120.0 < pair && pair < 250.0,
            "the synthetic pair breathes {pair} ml"
        );
        assert_eq!(pick(with(30, 300.0, 16), (0, 0.0)), 16);
        assert_eq!(pick(with(0, pair, 16), (0, 0.0)), 16);
        assert_eq!(asked.get(), 0);
        // Folds within the breath: the polynomial alone, if it holds the breath; else the first.
        assert_eq!(pick(with(30, 100.0, 16), (5, 260.0)), 0);
        assert_eq!(pick(with(30, 100.0, 16), (0, pair)), 0);
        assert_eq!(pick(with(30, 100.0, 16), (5, 120.0)), 16);
        // Clean at the inhale but crossing on the way (a fold that comes and goes): not kept.
        assert_eq!(pick(with(0, 10.0, 16), (0, pair)), 0);
        assert_eq!(asked.get(), 4);
        // A polynomial fit that folds is what it is: nothing to fall back to.
        assert_eq!(pick(with(30, 100.0, 0), (0, 0.0)), 0);
        assert_eq!(asked.get(), 4);
        let share = 0.5 * pair;
        assert!(
            draws_breath(&with(1, share, 16), share)
                && !draws_breath(&with(1, share - 0.1, 16), share)
        );
    }

    #[test]
    fn the_local_terms_are_released_in_four_stages_and_end_free_from_four_rounds() {
        let s: Vec<f64> = (0..50).map(|r| local_stiffness(r, 50)).collect();
        assert_eq!(s[0], 1000.0);
        assert_eq!(s[49], 1.0);
        assert!(s.windows(2).all(|w| w[1] <= w[0]));
        for (v, n) in [(1000.0, 13), (100.0, 12), (10.0, 13), (1.0, 12)] {
            assert_eq!(s.iter().filter(|&&x| x == v).count(), n, "{v}");
        }
        for rounds in 4..=200 {
            assert_eq!(local_stiffness(rounds - 1, rounds), 1.0, "{rounds}");
        }
        // Fewer rounds end before the terms are free (what `--iterations 1..3` asks for).
        assert_eq!(local_stiffness(0, 1), 1000.0);
        assert_eq!(local_stiffness(0, 0), 1000.0);
    }

    /// The population motion shipped in scenes/motion (bench/population_motion.py) loads as a
    /// motion file and moves each built-in lung down at a tidal volume without folding it.
    #[test]
    fn the_shipped_population_motion_draws_the_built_in_lungs_without_a_fold() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../scenes/motion/breath_hold_population.toml");
        let file = lung_model::deform::MotionFile::load(&path).unwrap();
        for side in [Side::Right, Side::Left] {
            let mesh = anatomy::lung(side, 3000).unwrap();
            let mut settings = BakeSettings::default_for(side);
            settings.force_field = file.force_for_side(side).cloned();
            settings.direction_field = file.field_for_side(side).cloned();
            assert!(settings.force_field.is_some() && settings.direction_field.is_some());
            let (transfer, _, _, _) =
                operator_columns(side, &mesh, &settings, 1, &Local::default()).unwrap();
            let force =
                transfer.elastostatic(&crate::kernel::applied_forces(&mesh, side, &settings));
            let dirs =
                LungModel::field_directions(&mesh, settings.direction_field.as_ref().unwrap());
            let (model, _, _) =
                LungModel::from_force_and_directions(side, mesh.clone(), dirs, &force).unwrap();
            let moved = at_volume(&model, 250.0);
            let moved_mesh = TriMesh {
                positions: moved.iter().map(|x| x.as_vec3().to_array()).collect(),
                triangles: mesh.triangles.clone(),
            };
            assert_eq!(
                crate::surface_checks::self_intersections(&moved_mesh, 10).count,
                0
            );
            let p = points(&mesh);
            let before = volume_centroid(&p, &mesh.triangles);
            let after = volume_centroid(&moved, &mesh.triangles);
            assert!(
                after.z < before.z - 3.0,
                "{side:?}: centroid {before} -> {after}"
            );
            assert!(
                (moved_mesh.enclosed_volume_ml() - mesh.enclosed_volume_ml() - 250.0).abs() < 0.5
            );
        }
    }

    /// A motion file's force field that is not one (bake --motion input): each refused naming the
    /// lung and the reason, never baked.
    #[test]
    fn a_bad_force_field_in_a_motion_file_is_refused() {
        let good = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../scenes/motion/breath_hold_population.toml"),
        )
        .unwrap();
        let start = good.find("[left_force]").unwrap();
        let (head, force) = good.split_at(start);
        let coeffs_line = force.lines().find(|l| l.starts_with("coeffs")).unwrap();
        let dir = std::env::temp_dir().join(format!("lungdyn-force-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (case, bad, words) in [
            (
                "degree",
                force.replace("degree = 3", "degree = 6"),
                "degree 1..=5",
            ),
            (
                "count",
                force.replace(coeffs_line, "coeffs = [1.0, 2.0]"),
                "one coefficient per monomial",
            ),
            (
                "nan",
                force.replace(
                    coeffs_line,
                    &format!(
                        "coeffs = [nan{}",
                        &coeffs_line[coeffs_line.find(',').unwrap()..]
                    ),
                ),
                "finite",
            ),
            (
                "box",
                force.replace("hi = [1.0, 1.0, 1.0]", "hi = [-1.0, 1.0, 1.0]"),
                "no extent",
            ),
            (
                "local weights without centres",
                force.replace("degree = 3", "degree = 3\nweights = [1.0]"),
                "one weight per centre",
            ),
            (
                "local terms without a radius",
                force.replace(
                    "degree = 3",
                    "degree = 3\ncentres = [[0.0, 0.0, 0.0]]\nweights = [1.0]",
                ),
                "positive radius",
            ),
        ] {
            let path = dir.join(format!("{case}.toml"));
            std::fs::write(&path, format!("{head}{bad}")).unwrap();
            let e = lung_model::deform::MotionFile::load(&path)
                .map(|_| "loaded".to_string())
                .unwrap_or_else(|e| e.to_string());
            assert!(e != "loaded" && e.contains(words), "{case}: {e}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_pair_the_wrong_way_round_or_with_bad_options_is_refused() {
        let exhale = anatomy::lung(Side::Left, 1500).unwrap();
        let inhale = breathe(&exhale, DVec3::ZERO);
        let settings = BakeSettings::default_for(Side::Left);
        let e = fit_pair(
            Side::Left,
            &inhale,
            &exhale,
            &settings,
            &PairOptions::default(),
            &|_| {},
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("not larger") && e.contains("other way round"),
            "{e}"
        );
        for bad in [
            PairOptions {
                force_degree: 0,
                ..PairOptions::default()
            },
            PairOptions {
                field_degree: 6,
                ..PairOptions::default()
            },
            PairOptions {
                force_centres: 7,
                ..PairOptions::default()
            },
            PairOptions {
                force_centres: 64,
                force_local_ridge: 0.0,
                ..PairOptions::default()
            },
            PairOptions {
                folds: 1,
                ..PairOptions::default()
            },
            PairOptions {
                normal_gate_deg: 5.0,
                ..PairOptions::default()
            },
            PairOptions {
                normal_gate_deg: f64::NAN,
                ..PairOptions::default()
            },
            PairOptions {
                iterations: 0,
                ..PairOptions::default()
            },
        ] {
            assert!(fit_pair(Side::Left, &exhale, &inhale, &settings, &bad, &|_| {}).is_err());
        }
        // Two lungs in one surface: refused, not fitted as one body.
        let mut two = exhale.clone();
        let n = two.positions.len() as u32;
        two.positions
            .extend(exhale.positions.iter().map(|p| [p[0] + 300.0, p[1], p[2]]));
        two.triangles
            .extend(exhale.triangles.iter().map(|t| t.map(|v| v + n)));
        let refused = |e: &TriMesh| {
            fit_pair(
                Side::Left,
                e,
                &inhale,
                &settings,
                &PairOptions::default(),
                &|_| {},
            )
            .unwrap_err()
            .to_string()
        };
        let e = refused(&two);
        assert!(e.contains("2 separate bodies"), "{e}");
        let mut open = exhale.clone();
        open.triangles.pop();
        let e = refused(&open);
        assert!(e.contains("exhale surface"), "{e}");
        // A non-finite vertex.
        let mut nan = exhale.clone();
        nan.positions[0][2] = f32::NAN;
        let e = refused(&nan);
        assert!(e.contains("exhale surface") && e.contains("NaN"), "{e}");
    }
}
