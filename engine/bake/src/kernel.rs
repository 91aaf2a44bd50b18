//! # kernel: baking a lung (seed ch. 6 end to end) into a kernel file
//!
//! [`bake`] runs the whole of seed ch. 6 for one lung mesh: the elasticity field and node graph
//! (§6.2, eq. 6.7), every transfer row by the pitcher–catcher pass (eq. 6.11–6.13), the applied
//! force of eq. 6.18 and the elastostatic force `F = Tᵀf` (eq. 6.1), the directions of
//! eq. 6.14–6.16 and the unit displacement `F[i]·d_i` scaled to one unit volume (EQUATIONS §2.4).
//! [`Kernel::write`] stores it in the format `lung_model::kernel` defines and reads.

use std::path::Path;

use thiserror::Error;

use lung_model::deform::{
    applied_force, normalised_position, DeformError, LungModel, UNIT_VOLUME_ML,
};
use lung_model::kernel::{mesh_hash, section, write_file};
pub use lung_model::kernel::{BakeSettings, KernelError, KernelMeta, DEFAULT_TOLERANCE};
use lung_model::mesh::{Side, TriMesh};

use crate::operator::{compute_transfer, NodeGraph, OperatorError, Schedule, Transfer};
use crate::orient::{basis_error, orientation_set, reference_delta_ml, Responses, ShProjection};
use crate::tumour::RowChange;
use lung_model::disease::tumour::Tumour;
use lung_model::kernel::{OrientationMeta, ShMeta, TumourMeta};

/// A baked lung, in memory.
#[derive(Debug, Clone)]
pub struct Kernel {
    /// Metadata.
    pub meta: KernelMeta,
    /// The mesh.
    pub mesh: TriMesh,
    /// Unit directions (eq. 6.14–6.16).
    pub directions: Vec<[f32; 3]>,
    /// Applied force (eq. 6.18).
    pub applied_force: Vec<f32>,
    /// Elastostatic force `F = Tᵀf` (eq. 6.1).
    pub elastostatic: Vec<f32>,
    /// Unit displacement, mm per unit volume.
    pub unit_displacement: Vec<[f32; 3]>,
    /// Transfer rows.
    pub transfer: Transfer,
    /// Basis responses `(G_0, G_x, G_y, G_z)` per vertex (EQUATIONS.md §3.3).
    pub basis: Vec<[f32; 4]>,
    /// SH transfer coefficients `T^I_lm`, `bands²` per vertex (when baked with bands).
    pub sh: Option<Vec<f32>>,
    /// The mesh's own lobe code per vertex (from the patient's lobe labels: `mesh from-mask`),
    /// written instead of the fissure planes' ([`Kernel::write`]); `None` after [`bake`] until the
    /// caller sets it.
    pub lobes: Option<Vec<u8>>,
}

/// Errors baking.
#[derive(Debug, Error)]
pub enum BakeError {
    /// The operator could not be built.
    #[error(transparent)]
    Operator(#[from] OperatorError),
    /// The displacement field is unusable.
    #[error(transparent)]
    Deform(#[from] DeformError),
    /// The surface is not a closed, consistently wound 2-manifold with positive volume.
    #[error("the mesh cannot be baked: {0}")]
    Mesh(#[from] lung_model::mesh::MeshError),
    /// The spherical-harmonic form cannot be baked.
    #[error("spherical harmonics: {0}")]
    Sh(#[from] crate::orient::ShError),
    /// The tumour cannot be applied to this lung.
    #[error("{0}")]
    Tumour(#[from] lung_model::disease::DiseaseError),
    /// The tumour is in the other lung.
    #[error("the tumour is in the {tumour} lung; this bake is of the {lung} lung")]
    TumourSide {
        /// The tumour's lung.
        tumour: &'static str,
        /// The lung being baked.
        lung: &'static str,
    },
    /// The amplitude cannot be smoothed.
    #[error(transparent)]
    Smooth(#[from] crate::smooth::SmoothError),
    /// Band count out of range.
    #[error("--bands {0}: 0 (none) to {max} are supported (n² ≤ 64 coefficients travel per lung per frame)", max = lung_model::kernel::MAX_RUNTIME_BANDS)]
    Bands(u32),
}

/// The applied force on each vertex of `mesh`: the fitted force field where the settings carry one
/// (a breath-hold pair's fit), else eq. 6.18's `c7·x̂ + c8·ŷ + c9·ẑ` (EQUATIONS §2.4).
/// The field's scale is [`lung_model::deform::fitted_supine_force`]'s (the precomputed mode does not
/// see it; the orientation modes add the posture's change of eq. 6.18 to it).
pub fn applied_forces(mesh: &TriMesh, side: Side, settings: &BakeSettings) -> Vec<f64> {
    let bb = mesh.aabb();
    match &settings.force_field {
        Some(f) => lung_model::deform::fitted_supine_force(mesh, side, &settings.motion, f),
        None => mesh
            .positions
            .iter()
            .map(|&p| applied_force(normalised_position(p, &bb, side), &settings.motion))
            .collect(),
    }
}

impl Kernel {
    /// The basis responses as the bake computed them (the same basis functions, fitted supine
    /// force included): for evaluations that need them in f64.
    pub fn responses(&self) -> Responses {
        let side = self.meta.side;
        let c = &self.meta.settings.motion.c;
        let fitted = match (&self.meta.settings.force_field, &self.meta.orientation) {
            (Some(f), Some(o)) if o.fitted_supine_force => {
                Some(lung_model::deform::fitted_supine_force(
                    &self.mesh,
                    side,
                    &self.meta.settings.motion,
                    f,
                ))
            }
            _ => None,
        };
        Responses::compute(
            &self.mesh,
            side,
            &self.transfer,
            &self.directions,
            self.meta.force_scale,
            [c[6], c[7], c[8]],
            fitted.as_deref(),
        )
    }
}

/// Bake `mesh` (a closed lung surface in mm; checked again here). `progress(rows)` is called as transfer rows
/// finish (from worker threads).
pub fn bake(
    side: Side,
    mesh: TriMesh,
    settings: &BakeSettings,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<Kernel, BakeError> {
    if settings.sh_bands > lung_model::kernel::MAX_RUNTIME_BANDS {
        return Err(BakeError::Bands(settings.sh_bands));
    }
    crate::smooth::check_length(settings.amplitude_smoothing_mm)?;
    lung_model::mesh::check(&mesh)?;
    if let Some(t) = &settings.tumour {
        // Before the expensive pass: a tumour outside this lung is refused at once.
        check_tumour(t, side, &mesh)?;
    }
    let bb = mesh.aabb();
    let norm = |p| normalised_position(p, &bb, side);
    let graph = NodeGraph::from_mesh(&mesh, &settings.elasticity, norm)?;
    let mut transfer = compute_transfer(
        &graph,
        settings.tolerance,
        Schedule::SpringsForward,
        progress,
    )?;
    // The amplitude made smooth at the stated length (EQUATIONS §2.4): a column scaling of the
    // stored rows, so every mode below — and the tumour's rows — derive from the smoothed transfer.
    crate::smooth::smooth_amplitude(&mut transfer, &mesh, settings.amplitude_smoothing_mm)?;
    // Seed §8.2: a tumour changes the transfer rows (eq. 8.14–8.20) before everything derived from
    // them — the elastostatic force, the unit displacement, the basis responses and the SH
    // coefficients — so every deformation mode draws the tumour-influenced lung (EQUATIONS §4.4).
    let tumour_change = match &settings.tumour {
        None => None,
        Some(t) => Some(apply_tumour(t, &mesh, &mut transfer)?),
    };
    let force = applied_forces(&mesh, side, settings);
    let elastostatic = transfer.elastostatic(&force);
    let hash = mesh_hash(&mesh);
    let (model, directions, force_scale) = match &settings.direction_field {
        // A field fitted to the patient's landmarks gives the directions (EQUATIONS §2.4, lungdyn).
        Some(field) => {
            let dirs = LungModel::field_directions(&mesh, field);
            LungModel::from_force_and_directions(side, mesh, dirs, &elastostatic)?
        }
        None => LungModel::from_force(side, mesh, &settings.motion, &elastostatic)?,
    };
    // Seed ch. 7: what the orientation-following modes need (EQUATIONS.md §3).
    // With a fitted force field its supine force is the first basis function (EQUATIONS.md §3.3,
    // "A fitted supine force"): every orientation mode draws the fit supine, as precomputed does.
    let c = &settings.motion.c;
    let fitted_supine = settings.force_field.as_ref().map(|_| force.as_slice());
    let mut responses = Responses::compute(
        &model.mesh,
        side,
        &transfer,
        &directions,
        force_scale,
        [c[6], c[7], c[8]],
        fitted_supine,
    );
    let orientations = orientation_set();
    let delta_ml = reference_delta_ml(model.start_volume_ml);
    let exact_forms = responses.forms_of(&model.mesh, &responses.g);
    responses.set_limit(&exact_forms);
    let basis = responses.stored();
    let basis_check = basis_error(
        &transfer,
        &responses,
        &basis,
        &directions,
        force_scale,
        &exact_forms,
        &orientations,
        delta_ml,
    );
    let (sh_meta, sh) = if settings.sh_bands > 0 {
        let (m, t) = sh_section(
            settings,
            &model.mesh,
            &transfer,
            &responses,
            &exact_forms,
            &orientations,
            delta_ml,
        )?;
        (Some(m), Some(t))
    } else {
        (None, None)
    };
    let tumour = match (tumour_change, &settings.tumour) {
        (Some((change, normal_transfer)), Some(t)) => Some(tumour_meta(
            t,
            &change,
            &normal_transfer,
            &force,
            settings,
            &model,
            &directions,
            force_scale,
            &basis,
            sh.as_deref()
                .map(|v| (v, sh_meta.as_ref().map_or(0, |m| m.bands as usize))),
        )?),
        _ => None,
    };
    // How far the lung can be drawn before its surface crosses itself (the engine marks frames past it).
    let fold_free = Some(crate::folds::range(&model));
    let meta = KernelMeta {
        side,
        units: "mm".into(),
        vertices: model.mesh.positions.len() as u64,
        triangles: model.mesh.triangles.len() as u64,
        spring_nodes: graph.spring_count() as u64,
        nnz: transfer.nnz() as u64,
        mesh_hash: format!("{hash:016x}"),
        settings: settings.clone(),
        transfer: transfer.stats,
        unit_volume_ml: UNIT_VOLUME_ML,
        force_scale,
        start_volume_ml: model.start_volume_ml,
        written_by: format!("lungdyn {}", env!("CARGO_PKG_VERSION")),
        orientation: Some(OrientationMeta {
            volume_forms: exact_forms,
            basis_max_error_mm: basis_check.max_mm,
            reference_delta_ml: delta_ml,
            orientations_checked: orientations.len() as u32,
            fitted_supine_force: responses.fitted,
        }),
        sh: sh_meta,
        tumour,
        fold_free,
    };
    Ok(Kernel {
        meta,
        directions,
        applied_force: force.iter().map(|&v| v as f32).collect(),
        elastostatic: elastostatic.iter().map(|&v| v as f32).collect(),
        unit_displacement: model.unit_displacement,
        mesh: model.mesh,
        transfer,
        basis,
        sh,
        lobes: None,
    })
}

/// Seed ch. 7's spherical harmonics: the projection up to `settings.sh_bands`, the band count the
/// error budget chooses (the fewest meeting it, else the most), its record and its stored
/// coefficients.
#[allow(clippy::too_many_arguments)]
fn sh_section(
    settings: &BakeSettings,
    mesh: &TriMesh,
    transfer: &Transfer,
    responses: &Responses,
    exact_forms: &lung_model::deform::modes::VolumeForms,
    orientations: &[glam::DVec3],
    delta_ml: f64,
) -> Result<(ShMeta, Vec<f32>), BakeError> {
    let n_max = settings.sh_bands as usize;
    let projection = ShProjection::compute(mesh, &transfer.transposed(), &responses.nhat, n_max)?;
    let fit = |n| projection.fit(n, mesh, responses, exact_forms, orientations, delta_ml);
    // The one error-budget rule (`bake --max-error-mm`, `bake --scene`, `scene prepare`): the
    // fewest bands from 1 up to `sh_bands` whose RMS error meets the budget, else `sh_bands`.
    let mut trials = Vec::new();
    let chosen = match settings.max_error_mm {
        None => fit(n_max),
        Some(budget) => {
            let mut n = 1;
            loop {
                let f = fit(n);
                trials.push(f.error.rms_mm);
                if f.error.rms_mm <= budget || n >= n_max {
                    break f;
                }
                n += 1;
            }
        }
    };
    Ok((
        ShMeta {
            bands: chosen.n as u32,
            centre_mm: projection.centre,
            alpha: chosen.alpha,
            projection: projection.projection(chosen.n),
            volume_forms: chosen.forms.clone(),
            rms_percent: chosen.error.rms_percent,
            rms_mm: chosen.error.rms_mm,
            max_mm: chosen.error.max_mm,
            quantisation_max_mm: chosen.quantisation_max_mm,
            foldover_nodes: projection.weights.foldover_vertices.len() as u64,
            budget_mm: settings.max_error_mm,
            budget_trials_rms_mm: trials,
        },
        projection.stored(chosen.n),
    ))
}

/// The tumour's parameters, its lung and that its centre lies inside the surface (winding number).
pub fn check_tumour(t: &Tumour, side: Side, mesh: &TriMesh) -> Result<(), BakeError> {
    use lung_model::disease::tumour as tu;
    if t.side != side {
        return Err(BakeError::TumourSide {
            tumour: t.side.name(),
            lung: side.name(),
        });
    }
    t.validate()?;
    let centre = t.centre_mm(mesh);
    let winding = tu::winding_number(mesh, centre);
    if !(winding > 0.5) {
        return Err(
            lung_model::disease::DiseaseError::from(tu::TumourError::CentreOutside {
                side: t.side.name(),
                centre_mm: centre,
                winding,
            })
            .into(),
        );
    }
    Ok(())
}

/// Eq. 8.14–8.20 on `transfer` in place (the tumour kernel); returns what changed and the
/// tumour-free rows (for the comparison track). The centre must lie inside the surface.
fn apply_tumour(
    t: &Tumour,
    mesh: &TriMesh,
    transfer: &mut Transfer,
) -> Result<(RowChange, Transfer), BakeError> {
    use crate::tumour as tu;
    let a = t.expandability_of(mesh);
    let phi = tu::phi_values(mesh, t.side, t.phi);
    let reach = tu::kernel_reach_mm(&mesh.positions, &transfer.row_ptr, &transfer.cols)
        .map_err(lung_model::disease::DiseaseError::from)?;
    let normal = transfer.clone();
    let change = tu::modify_rows(
        &mesh.positions,
        &normal.row_ptr,
        &normal.cols,
        &normal.vals,
        &a,
        &phi,
        t.coupling,
        reach,
        &mut transfer.vals,
    )?;
    Ok((change, normal))
}

/// The tumour's record in the kernel: its centre's response in every mode from the stored data
/// (`TumourMeta`), and the track the same centre has in the tumour-free lung.
#[allow(clippy::too_many_arguments)]
fn tumour_meta(
    t: &Tumour,
    change: &RowChange,
    normal_transfer: &Transfer,
    force: &[f64],
    settings: &BakeSettings,
    model: &LungModel,
    directions: &[[f32; 3]],
    force_scale: f64,
    basis: &[[f32; 4]],
    sh: Option<(&[f32], usize)>,
) -> Result<TumourMeta, BakeError> {
    use lung_model::disease::tumour as tu;
    let mesh = &model.mesh;
    let centre = t.centre_mm(mesh);
    let tumour_err = |e: tu::TumourError| BakeError::Tumour(e.into());
    let weights = tu::mean_value_weights(mesh, centre).map_err(tumour_err)?;
    let kd: Vec<[f32; 3]> = directions
        .iter()
        .map(|d| d.map(|v| v * force_scale as f32))
        .collect();
    let precomputed_mm = tu::TumourTrack::new(mesh, &model.unit_displacement, centre)
        .map_err(tumour_err)?
        .unit_displacement_mm;
    let basis_flat: Vec<f32> = basis.iter().flatten().copied().collect();
    let b = crate::tumour::weighted_rows(&weights, &basis_flat, 4, &kd);
    let sh_mm = match sh {
        Some((coeffs, bands)) if bands > 0 => {
            // The values the run time draws with (16-bit, EQUATIONS.md §3.2), so the centre
            // follows the drawn surface.
            let n = bands * bands;
            let held = lung_model::deform::modes::ShCoeffs::quantise(n, coeffs)
                .map_err(crate::orient::ShError::Held)?;
            let rows: Vec<f32> = (0..held.vertices())
                .flat_map(|i| (0..n).map(move |k| (i, k)))
                .map(|(i, k)| held.value(i, k) as f32)
                .collect();
            crate::tumour::weighted_rows(&weights, &rows, n, &kd)
        }
        _ => Vec::new(),
    };
    // The same centre in the lung without the tumour.
    let normal_force = normal_transfer.elastostatic(force);
    let (normal, _, _) = match &settings.direction_field {
        Some(_) => LungModel::from_force_and_directions(
            t.side,
            mesh.clone(),
            directions
                .iter()
                .map(|d| glam::DVec3::from(d.map(|v| v as f64)))
                .collect(),
            &normal_force,
        )?,
        None => LungModel::from_force(t.side, mesh.clone(), &settings.motion, &normal_force)?,
    };
    let normal_track =
        tu::TumourTrack::new(mesh, &normal.unit_displacement, centre).map_err(tumour_err)?;
    let a = t.expandability_of(mesh);
    let (mut sum, mut max, mut count) = (0.0f64, 0.0f64, 0usize);
    for ((u, v), &a) in model
        .unit_displacement
        .iter()
        .zip(&normal.unit_displacement)
        .zip(&a)
    {
        let norm = v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt();
        if a >= 1.0 || norm == 0.0 {
            continue;
        }
        let diff = (0..3)
            .map(|k| (u[k] as f64 - v[k] as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let change = 100.0 * diff / norm;
        sum += change;
        max = max.max(change);
        count += 1;
    }
    Ok(TumourMeta {
        tumour: *t,
        centre_mm: centre,
        volume_ml: t.volume_ml(),
        vertices_affected: count as u64,
        affected_motion_change_percent: [if count > 0 { sum / count as f64 } else { 0.0 }, max],
        entries_changed: change.changed,
        entries_clamped: change.clamped,
        entries_nonpositive: change.nonpositive,
        reach_mm: change.reach_mm,
        factor_range: [change.min_factor, change.max_factor],
        precomputed_mm,
        normal_precomputed_mm: normal_track.unit_displacement_mm,
        basis_mm: [b[0], b[1], b[2], b[3]],
        sh_mm,
    })
}

impl Kernel {
    /// Write the kernel to `path` atomically (temporary sibling, then rename); returns its length.
    pub fn write(&self, path: &Path) -> Result<u64, KernelError> {
        let lobes = match &self.lobes {
            Some(own) if own.len() == self.mesh.positions.len() => own.clone(),
            _ => lung_model::mesh::lobes::classify(self.meta.side, &self.mesh),
        };
        write_file(
            path,
            &self.meta,
            &[
                (
                    section::POSITIONS,
                    12,
                    bytemuck::cast_slice(&self.mesh.positions),
                ),
                (
                    section::TRIANGLES,
                    12,
                    bytemuck::cast_slice(&self.mesh.triangles),
                ),
                (
                    section::DIRECTIONS,
                    12,
                    bytemuck::cast_slice(&self.directions),
                ),
                (
                    section::APPLIED_FORCE,
                    4,
                    bytemuck::cast_slice(&self.applied_force),
                ),
                (
                    section::ELASTOSTATIC,
                    4,
                    bytemuck::cast_slice(&self.elastostatic),
                ),
                (
                    section::UNIT_DISPLACEMENT,
                    12,
                    bytemuck::cast_slice(&self.unit_displacement),
                ),
                (
                    section::ROW_PTR,
                    8,
                    bytemuck::cast_slice(&self.transfer.row_ptr),
                ),
                (section::COLS, 4, bytemuck::cast_slice(&self.transfer.cols)),
                (section::VALS, 4, bytemuck::cast_slice(&self.transfer.vals)),
                (section::BASIS, 16, bytemuck::cast_slice(&self.basis)),
                (section::LOBES, 1, &lobes),
                (
                    section::SH,
                    4,
                    bytemuck::cast_slice(self.sh.as_deref().unwrap_or(&[])),
                ),
            ]
            .into_iter()
            .filter(|s| s.0 != section::SH || self.sh.is_some())
            .collect::<Vec<_>>(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::kernel::KernelFile;
    use lung_model::mesh::generate;
    use std::path::PathBuf;

    fn small(side: Side) -> Kernel {
        bake(
            side,
            generate::lung(side, 600).unwrap(),
            &BakeSettings::default_for(side),
            &|_| {},
        )
        .unwrap()
    }

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lungdyn-kernel-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn write_then_open_round_trips_every_section() {
        let k = small(Side::Left);
        let path = tmp("rt.kernel");
        let len = k.write(&path).unwrap();
        let f = KernelFile::open(&path).unwrap();
        assert_eq!(f.len_bytes() as u64, len);
        assert_eq!(f.meta(), &k.meta);
        assert_eq!(f.mesh(), k.mesh);
        assert_eq!(f.directions(), &k.directions[..]);
        assert_eq!(f.applied_force().unwrap(), &k.applied_force[..]);
        assert_eq!(f.elastostatic().unwrap(), &k.elastostatic[..]);
        assert_eq!(f.basis_responses().unwrap().unwrap(), &k.basis[..]);
        assert_eq!(
            f.sh_coefficients().unwrap().unwrap(),
            k.sh.as_deref().unwrap()
        );
        assert_eq!(f.unit_displacement(), &k.unit_displacement[..]);
        assert_eq!(f.transfer().unwrap(), k.transfer);
        // The loaded model adds exactly the unit volume at s = 1.
        let m = f.lung_model();
        let dv = m.cubic.volume(1.0) / 1000.0 - m.start_volume_ml;
        assert!((dv - UNIT_VOLUME_ML).abs() < 1e-3, "{dv}");
    }

    #[test]
    fn extremes_bake_or_fail_clearly() {
        // A tetrahedron: the smallest closed surface.
        let tet = TriMesh {
            positions: vec![
                [0.0; 3],
                [100.0, 0.0, 0.0],
                [0.0, 100.0, 0.0],
                [0.0, 0.0, 100.0],
            ],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        };
        let k = bake(
            Side::Left,
            tet.clone(),
            &BakeSettings::default_for(Side::Left),
            &|_| {},
        )
        .map_err(|e| e.to_string())
        .unwrap();
        assert!(k.unit_displacement.iter().flatten().all(|v| v.is_finite()));
        // Tolerances at both ends: a huge one pitches each unit force once (rows hold only their
        // own node, the rest is spring-caught or truncated, all accounted for); a tiny one converges.
        let mut s = BakeSettings::default_for(Side::Left);
        s.tolerance = 0.999;
        let k = bake(
            Side::Left,
            generate::lung(Side::Left, 200).unwrap(),
            &s,
            &|_| {},
        )
        .map_err(|e| e.to_string())
        .unwrap();
        assert_eq!(k.meta.transfer.max_row_nnz, 1);
        assert!(k.meta.transfer.conservation_error_max < 1e-9);
        assert!(k.unit_displacement.iter().flatten().all(|v| v.is_finite()));
        s.tolerance = 1e-12;
        let k = bake(
            Side::Left,
            generate::lung(Side::Left, 200).unwrap(),
            &s,
            &|_| {},
        )
        .map_err(|e| e.to_string())
        .unwrap();
        assert!(k.meta.transfer.truncated_force_max < 1e-9);
        assert!(k.meta.transfer.conservation_error_max < 1e-9);
        // A degenerate, flat "lung" (all z equal) has no volume slope: refused, not NaN.
        let mut flat = tet;
        for p in &mut flat.positions {
            p[2] = 0.0;
        }
        assert!(bake(
            Side::Left,
            flat,
            &BakeSettings::default_for(Side::Left),
            &|_| {}
        )
        .is_err());
    }

    #[test]
    fn baking_is_reproducible_byte_for_byte() {
        let a = tmp("a.kernel");
        let b = tmp("b.kernel");
        small(Side::Right).write(&a).unwrap();
        small(Side::Right).write(&b).unwrap();
        assert_eq!(std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    }

    #[test]
    fn kernels_carry_lobes_and_kernels_without_them_still_load() {
        let k = small(Side::Right);
        let path = tmp("lobes.kernel");
        k.write(&path).unwrap();
        let file = KernelFile::open(&path).unwrap();
        let codes = lung_model::mesh::lobes::classify(Side::Right, &k.mesh);
        assert_eq!(file.lobes().unwrap(), Some(&codes[..]));
        assert!(codes.iter().all(|&c| (1..=3).contains(&c)));
        // A kernel written before the section existed: the same sections less the lobes.
        let old = tmp("no-lobes.kernel");
        let bytes = std::fs::read(&path).unwrap();
        let (_, sections) = lung_model::kernel::verify_bytes(&bytes).unwrap();
        let kept: Vec<(u32, u32, &[u8])> = sections
            .iter()
            .filter(|s| s.kind != section::META && s.kind != section::LOBES)
            .map(|s| (s.kind, s.elem, &bytes[s.offset..s.offset + s.len]))
            .collect();
        write_file(&old, &k.meta, &kept).unwrap();
        let file = KernelFile::open(&old).unwrap();
        assert_eq!(file.lobes().unwrap(), None);
        assert_eq!(file.positions(), &k.mesh.positions[..]);
        // A code outside 0..=5 is refused by name.
        let mut bad = codes.clone();
        bad[3] = 9;
        let mut with_bad = kept.clone();
        with_bad.push((section::LOBES, 1, &bad));
        let broken = tmp("bad-lobes.kernel");
        write_file(&broken, &k.meta, &with_bad).unwrap();
        let e = KernelFile::open(&broken).unwrap_err().to_string();
        assert!(e.contains("lobe code 9"), "{e}");
    }

    fn tumour_settings(side: Side, t: Option<Tumour>) -> BakeSettings {
        let mut s = BakeSettings::default_for(side);
        s.tumour = t;
        s
    }

    /// A 15 mm tumour low, posterior and lateral in the right lung (the shipped scene's).
    fn tumour() -> Tumour {
        Tumour::new(Side::Right, [0.7, 0.3, 0.75], [15.0, 15.0, 15.0])
    }

    #[test]
    fn a_tumour_of_normal_expandability_changes_nothing_bit_for_bit() {
        // a = 1 everywhere and φ = 0: e = 0 for every entry, so eq. 8.19 gives d' = d and every
        // entry is kept as it is (module Decision "e = 0 and φ = 0 leave the entry bit for bit").
        let mesh = generate::lung(Side::Right, 800).unwrap();
        let normal = bake(
            Side::Right,
            mesh.clone(),
            &tumour_settings(Side::Right, None),
            &|_| {},
        )
        .unwrap();
        let mut t = tumour();
        t.expandability = 1.0;
        let k = bake(
            Side::Right,
            mesh,
            &tumour_settings(Side::Right, Some(t)),
            &|_| {},
        )
        .unwrap();
        assert_eq!(k.transfer.vals, normal.transfer.vals);
        assert_eq!(k.unit_displacement, normal.unit_displacement);
        assert_eq!(k.basis, normal.basis);
        let m = k.meta.tumour.as_ref().unwrap();
        assert_eq!((m.entries_changed, m.vertices_affected), (0, 0));
        assert_eq!(m.precomputed_mm, m.normal_precomputed_mm);
        assert!(normal.meta.tumour.is_none());
    }

    #[test]
    fn the_tumour_centre_moves_as_the_mean_value_sum_of_the_surface_in_every_mode() {
        use lung_model::deform::modes::{CpuLung, DeformMode, ModeData};
        use lung_model::disease::tumour as tu;
        let mesh = generate::lung(Side::Right, 1500).unwrap();
        let k = bake(
            Side::Right,
            mesh,
            &tumour_settings(Side::Right, Some(tumour())),
            &|_| {},
        )
        .unwrap();
        let m = k.meta.tumour.clone().unwrap();
        assert!(m.vertices_affected > 0 && m.entries_changed > 0, "{m:?}");
        assert_eq!(m.sh_mm.len(), 16, "4 bands by default");
        let lambda = tu::mean_value_weights(&k.mesh, m.centre_mm).unwrap();
        let kd: Vec<[f32; 3]> = k
            .directions
            .iter()
            .map(|d| d.map(|v| v * k.meta.force_scale as f32))
            .collect();
        let cases: Vec<(DeformMode, ModeData, Vec<f32>)> = vec![
            (
                DeformMode::Precomputed,
                ModeData::Precomputed {
                    unit: k.unit_displacement.clone(),
                },
                vec![],
            ),
            (
                DeformMode::Basis,
                ModeData::Basis { g: k.basis.clone() },
                vec![0.9, -0.3, 0.45, 0.2],
            ),
            (
                DeformMode::Sh,
                ModeData::Sh {
                    t: lung_model::deform::modes::ShCoeffs::quantise(16, k.sh.as_ref().unwrap())
                        .unwrap(),
                },
                (0..16).map(|i| ((i * 7 % 5) as f32 - 2.0) * 0.3).collect(),
            ),
        ];
        let s = 1.7f32;
        for (mode, data, coeffs) in cases {
            let mut lung = CpuLung::new(k.mesh.clone(), kd.clone(), data);
            let mut out = vec![[0.0f32; 3]; lung.len()];
            lung.deform_into(s, &coeffs, [0.0; 3], &mut out).unwrap();
            // The reference: Σ λ_i (deformed_i − p_i), over the whole surface, per unit scale.
            let mut want = [0.0f64; 3];
            for ((l, o), p) in lambda.iter().zip(&out).zip(&k.mesh.positions) {
                for a in 0..3 {
                    want[a] += l * (o[a] as f64 - p[a] as f64) / s as f64;
                }
            }
            let got = m.displacement_mm(mode, &coeffs).unwrap();
            let scale = want.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-3);
            for a in 0..3 {
                // f32 positions minus f32 positions: round-off of order 1e-5 mm per vertex.
                assert!(
                    (got[a] - want[a]).abs() <= 1e-3 * scale + 1e-4,
                    "{mode:?} axis {a}: {got:?} vs {want:?}"
                );
            }
            // Coefficients that do not fit the mode give no position, not a wrong one.
            if mode != DeformMode::Precomputed {
                assert!(m
                    .displacement_mm(mode, &coeffs[..coeffs.len() - 1])
                    .is_none());
            }
        }
        // Position: collapse 0 and zero offset give centre + s·d; a collapse moves it to the hilum.
        let d = m.precomputed_mm;
        let p = m.position_mm(d, 2.0, 0.0, [0.0; 3], [1.0, 2.0, 3.0]);
        for a in 0..3 {
            assert!((p[a] - (m.centre_mm[a] + 2.0 * d[a] + [1.0, 2.0, 3.0][a])).abs() < 1e-12);
        }
        assert_eq!(
            m.position_mm(d, 0.0, 1.0, [5.0, 6.0, 7.0], [0.0; 3]),
            [5.0, 6.0, 7.0]
        );
    }

    /// On the baked lung (the production path): the tumour region moves less relative to the rest
    /// than in the healthy lung, more so with a larger coupling `B`, while the lung still breathes
    /// its unit volume; a lower-lobe tumour's centre moves more along Z than an upper-lobe one's.
    #[test]
    fn a_tumour_stiffens_its_region_and_the_lower_lobe_moves_most() {
        let side = Side::Right;
        let mesh = generate::lung(side, 1500).unwrap();
        // A lateral tumour near the base touching the costal surface, 25 mm radius.
        let tumour = Tumour::new(side, [0.75, 0.5, 0.75], [25.0; 3]);
        let a = tumour.expandability_of(&mesh);
        let baked = |t: Option<Tumour>| {
            bake(side, mesh.clone(), &tumour_settings(side, t), &|_| {}).unwrap()
        };
        let mag = |u: &[f32; 3]| (u[0] as f64).hypot(u[1] as f64).hypot(u[2] as f64);
        let ratio = |k: &Kernel| {
            let mean = |inside: bool| {
                let v: Vec<f64> = k
                    .unit_displacement
                    .iter()
                    .zip(&a)
                    .filter(|(_, &a)| (a < 0.2) == inside)
                    .map(|(u, _)| mag(u))
                    .collect();
                assert!(!v.is_empty(), "inside {inside}: no vertex");
                v.iter().sum::<f64>() / v.len() as f64
            };
            mean(true) / mean(false)
        };
        let mut ratios = vec![ratio(&baked(None))];
        for coupling in [0.25, 0.5, 1.0, 2.0] {
            let k = baked(Some(Tumour { coupling, ..tumour }));
            let m = k.meta.tumour.as_ref().unwrap();
            assert!(m.vertices_affected > 0 && m.entries_changed > 0, "{m:?}");
            // The lung still breathes its unit volume (EQUATIONS §2.4).
            assert_eq!(k.meta.unit_volume_ml, UNIT_VOLUME_ML);
            ratios.push(ratio(&k));
        }
        eprintln!(
            "tumour region / rest, mean unit displacement: normal, B = 0.25, 0.5, 1, 2: {ratios:.4?}"
        );
        assert!(ratios.windows(2).all(|w| w[1] < w[0]), "{ratios:?}");
        // A lower-lobe tumour moves more along Z than an upper-lobe one (clinically: lower-lobe
        // tumours move most), both finite.
        let z_motion = |centre: [f64; 3]| {
            let k = baked(Some(Tumour::new(side, centre, [15.0; 3])));
            k.meta.tumour.as_ref().unwrap().precomputed_mm
        };
        // Each centre well inside its lobe (`lobes::interior_point`): below the middle of the
        // anatomical lung's box lies the domed diaphragm, outside the lung.
        let inside = |lobe| {
            lung_model::mesh::lobes::interior_point(generate::Shape::Anatomical, lobe).unwrap()
        };
        let upper = z_motion(inside(lung_model::mesh::lobes::Lobe::RightUpper));
        let lower = z_motion(inside(lung_model::mesh::lobes::Lobe::RightLower));
        eprintln!("per unit scale: upper {upper:?} mm, lower {lower:?} mm");
        assert!(lower[2].abs() > upper[2].abs());
        assert!(upper.iter().chain(&lower).all(|v| v.is_finite()));
    }

    #[test]
    fn every_bad_tumour_key_is_named_before_the_pass() {
        let side = Side::Left;
        let mesh = generate::lung(side, 600).unwrap();
        let rows = std::sync::atomic::AtomicUsize::new(0);
        let count = |n: usize| {
            rows.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
        };
        let base = Tumour::new(side, [0.5; 3], [5.0; 3]);
        for (t, key) in [
            (Tumour::new(side, [1.5, 0.5, 0.5], [5.0; 3]), "centre"),
            (Tumour::new(side, [0.5; 3], [0.0; 3]), "radii_mm"),
            (
                Tumour {
                    expandability: 0.0,
                    ..base
                },
                "expandability",
            ),
            (
                Tumour {
                    falloff: -1.0,
                    ..base
                },
                "falloff",
            ),
            (
                Tumour {
                    coupling: f64::NAN,
                    ..base
                },
                "coupling",
            ),
            (
                Tumour {
                    resistance_phi: 2.0,
                    ..base
                },
                "resistance_phi",
            ),
        ] {
            let e = bake(side, mesh.clone(), &tumour_settings(side, Some(t)), &count)
                .unwrap_err()
                .to_string();
            assert!(e.contains(key), "{key}: {e}");
        }
        assert_eq!(rows.into_inner(), 0, "no transfer row was computed");
    }

    #[test]
    fn a_tumour_outside_the_lung_or_in_the_other_lung_is_refused_before_the_pass() {
        let mesh = generate::lung(Side::Right, 600).unwrap();
        let rows = std::sync::atomic::AtomicUsize::new(0);
        let count = |n: usize| {
            rows.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
        };
        // The box corner is outside the rounded lung.
        let outside = Tumour::new(Side::Right, [0.0, 0.0, 0.0], [10.0; 3]);
        let e = bake(
            Side::Right,
            mesh.clone(),
            &tumour_settings(Side::Right, Some(outside)),
            &count,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("not inside the right lung"), "{e}");
        let e = bake(
            Side::Left,
            generate::lung(Side::Left, 600).unwrap(),
            &tumour_settings(Side::Left, Some(tumour())),
            &count,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("the tumour is in the right lung"), "{e}");
        let mut bad = tumour();
        bad.radii_mm[1] = 0.0;
        let e = bake(
            Side::Right,
            mesh,
            &tumour_settings(Side::Right, Some(bad)),
            &count,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("radii_mm"), "{e}");
        assert_eq!(rows.into_inner(), 0, "no transfer row was computed");
    }
}

/// How the default lungs breathe (EQUATIONS.md §2.4, "Breathing like a person").
#[cfg(test)]
mod breathing {
    use super::*;
    use glam::DVec3;
    use lung_model::deform::{DirectionPreset, VolumeCubic};
    use lung_model::mesh::generate;

    /// Total tidal volume the DIR-Lab end-exhale → end-inhale scans are taken to be, ml.
    const DIRLAB_TIDAL_ML: f64 = 500.0;

    /// A default lung at 10k vertices baked with `preset` (no SH: the unit displacement does not
    /// depend on it), and its share of a breath of both generated lungs (by FRC volume).
    fn baked(side: Side, preset: DirectionPreset) -> (Kernel, f64) {
        baked_with(
            side,
            preset,
            lung_model::kernel::DEFAULT_AMPLITUDE_SMOOTHING_MM,
        )
    }

    /// [`baked`] with the amplitude smoothed over `smoothing_mm` (0: the seed's reading).
    fn baked_with(side: Side, preset: DirectionPreset, smoothing_mm: f64) -> (Kernel, f64) {
        let mesh = generate::lung(side, 10_000).unwrap();
        let both: f64 = [Side::Left, Side::Right]
            .into_iter()
            .map(|s| generate::lung(s, 2_000).unwrap().enclosed_volume_ml())
            .sum();
        let share = mesh.enclosed_volume_ml() / both;
        let mut s = BakeSettings::for_preset(preset, side);
        s.sh_bands = 0;
        s.amplitude_smoothing_mm = smoothing_mm;
        (bake(side, mesh, &s, &|_| {}).unwrap(), share)
    }

    /// The surface at `delta_ml` from FRC, as `lungdyn kernel export --delta-ml` draws it.
    fn deformed(k: &Kernel, delta_ml: f64) -> TriMesh {
        let u: Vec<DVec3> = k
            .unit_displacement
            .iter()
            .map(|v| DVec3::new(v[0] as f64, v[1] as f64, v[2] as f64))
            .collect();
        let s = VolumeCubic::of(&k.mesh, &u).solve_delta(delta_ml * 1000.0) as f32;
        let positions = k
            .mesh
            .positions
            .iter()
            .zip(&k.unit_displacement)
            .map(|(p, u)| [0, 1, 2].map(|a| p[a] + s * u[a]))
            .collect();
        TriMesh {
            positions,
            triangles: k.mesh.triangles.clone(),
        }
    }

    /// Mean |LR|, |AP|, |SI| displacement (mm) of the vertices in the lowest third of the height.
    fn lower_third(k: &Kernel, delta_ml: f64) -> [f64; 3] {
        let moved = deformed(k, delta_ml);
        let bb = k.mesh.aabb();
        let cut = bb.min[2] + (bb.max[2] - bb.min[2]) / 3.0;
        let mut sum = [0.0f64; 3];
        let mut n = 0.0;
        for (p, q) in k.mesh.positions.iter().zip(&moved.positions) {
            if p[2] < cut {
                for a in 0..3 {
                    sum[a] += (q[a] - p[a]).abs() as f64;
                }
                n += 1.0;
            }
        }
        sum.map(|v| v / n)
    }

    /// DIR-Lab (10 cases × 300 landmarks, end-exhale → end-inhale), lower third: mean |SI| 13.1 mm,
    /// |AP| 2.1, |LR| 1.2 (SI : AP = 6.2). The default lungs at their share of a 500 ml breath:
    /// SI at least 4 × AP, SI within ±30 % of DIR-Lab's 13.1 mm. The seed's Table 6.1 (still
    /// reachable as `directions = "seed"`) moves the lower third mostly anteriorly.
    #[test]
    fn the_default_lungs_breathe_mostly_superior_inferior() {
        for side in [Side::Right, Side::Left] {
            // The breath-hold population was fitted to six COPDgene breath-hold pairs, not to these
            // 4DCT landmarks: an independent check (measured: right SI 16.7, AP 3.1, LR 2.1 mm;
            // left 13.2, 2.6, 2.9; the population refitted with the ICP's normal gate, 2026-12-07).
            for preset in [DirectionPreset::Population, DirectionPreset::BreathHold] {
                let (k, share) = baked(side, preset);
                let [lr, ap, si] = lower_third(&k, share * DIRLAB_TIDAL_ML);
                eprintln!("{side:?} {}, {:.0} ml: lower third LR {lr:.2} AP {ap:.2} SI {si:.2} mm (SI/AP {:.1})", preset.name(), share * DIRLAB_TIDAL_ML, si / ap);
                assert!(si >= 4.0 * ap, "{side:?} {preset:?}: SI {si} AP {ap}");
                assert!(si >= 4.0 * lr, "{side:?} {preset:?}: SI {si} LR {lr}");
                assert!(
                    (0.7 * 13.1..=1.3 * 13.1).contains(&si),
                    "{side:?} {preset:?}: SI {si}"
                );
            }
            let (k, share) = baked(side, DirectionPreset::Seed);
            let [lr, ap, si] = lower_third(&k, share * DIRLAB_TIDAL_ML);
            eprintln!(
                "{side:?} seed, {:.0} ml: lower third LR {lr:.2} AP {ap:.2} SI {si:.2} mm",
                share * DIRLAB_TIDAL_ML
            );
            assert!(ap > 2.0 * si, "{side:?} seed: SI {si} AP {ap}");
        }
    }

    /// From FRC − 500 ml to FRC + 1500 ml of both lungs (each lung its share), in steps of 250 ml
    /// of the whole, neither default lung folds: every deformed surface is a closed 2-manifold
    /// without self-intersection (the exact test), with the population and seed presets (the
    /// breath-hold population from FRC − 500 to FRC + 750 ml), the amplitude smoothed over the
    /// default 10 mm (EQUATIONS.md §2.4). The precomputed field is the one checked here; the
    /// basis, SH and direct modes and the tumour derive from the same smoothed transfer rows (the
    /// consistency tests in `orient` and `tests/` hold them to it).
    #[test]
    fn the_default_lungs_do_not_fold_over_the_whole_range() {
        for side in [Side::Right, Side::Left] {
            // The breath-hold population folds the generated right lung beyond its share of FRC +
            // 750 ml (4 triangle pairs at +542 ml, 10k vertices; from +406 ml before it was refitted
            // with the ICP's normal gate on 2026-12-07): held to FRC − 500 … + 750 ml below.
            for (preset, steps) in [
                (DirectionPreset::Population, -2..=6),
                (DirectionPreset::Seed, -2..=6),
                (DirectionPreset::BreathHold, -2..=3),
            ] {
                let (k, share) = baked(side, preset);
                for step in steps {
                    let delta = share * 250.0 * step as f64;
                    let m = deformed(&k, delta);
                    lung_model::mesh::check(&m).unwrap();
                    let si = crate::surface_checks::self_intersections(&m, 4);
                    if let Some((a, b)) = si.first {
                        let bb = k.mesh.aabb();
                        let at = |t: u32| {
                            k.mesh.triangles[t as usize].map(|v| {
                                lung_model::deform::normalised_position(
                                    k.mesh.positions[v as usize],
                                    &bb,
                                    side,
                                )
                            })
                        };
                        eprintln!(
                            "{side:?} {preset:?} {delta:+.0}: {si:?} at {:?} {:?}",
                            at(a),
                            at(b)
                        );
                    }
                    assert_eq!(si.count, 0, "{side:?} {preset:?} at {delta:+.0} ml: {si:?}");
                }
            }
        }
    }

    /// The orientation-following field (basis mode, which eq. 7.1's direct mode equals; EQUATIONS.md
    /// §3.3) of both default lungs at 10k vertices, at the force weights the run time gives for every
    /// gravity of the bake's orientation set (supine, prone, both lateral decubitus postures,
    /// upright, head-down and 20 random ones) with the default orientation limit, from FRC − 500 to
    /// FRC + 1500 ml of both lungs in steps of 250 ml: no surface intersects itself. With the limit
    /// at lungdyn's earlier ratio 0.5 this failed: of the surfaces at −500, +500, +1000 and +1500 ml,
    /// 22 of 208 folded (prone-like postures already at FRC − 500 ml), and the largest vertex move
    /// at +1500 ml reached 3.2× the supine one (1.7× at the default 0.8).
    #[test]
    fn the_default_lungs_do_not_fold_in_any_posture() {
        let mut folds = Vec::new();
        let mut worst = 0.0f64;
        for side in [Side::Right, Side::Left] {
            let (k, share) = baked(side, DirectionPreset::Population);
            let mut r = k.responses();
            let forms = r.forms_of(&k.mesh, &r.g);
            r.set_limit(&forms);
            let field = |g: DVec3| -> Vec<DVec3> {
                let d = r.force(&r.weights(g));
                d.iter().zip(&r.kd).map(|(d, kd)| *kd * *d).collect()
            };
            let largest =
                |u: &[DVec3], s: f64| u.iter().map(|u| u.length() * s).fold(0.0, f64::max);
            let supine = field(lung_model::orientation::SUPINE_GRAVITY);
            let top = share * 1500.0 * 1000.0;
            let supine_max = largest(&supine, VolumeCubic::of(&k.mesh, &supine).solve_delta(top));
            for (n, g) in crate::orient::orientation_set().into_iter().enumerate() {
                let u = field(g);
                let cubic = VolumeCubic::of(&k.mesh, &u);
                for step in (-2..=6).filter(|&s| s != 0) {
                    let delta = share * 250.0 * step as f64;
                    let s = cubic.solve_delta(delta * 1000.0);
                    assert!(s.is_finite(), "{side:?} g {g:?} {delta:+.0} ml");
                    let m = TriMesh {
                        positions: k
                            .mesh
                            .positions
                            .iter()
                            .zip(&u)
                            .map(|(p, u)| [0, 1, 2].map(|a| p[a] + (s * u[a]) as f32))
                            .collect(),
                        triangles: k.mesh.triangles.clone(),
                    };
                    // The volume the run time solves for is the one drawn.
                    let v = m.enclosed_volume_ml() - k.mesh.enclosed_volume_ml();
                    assert!((v - delta).abs() < 0.05, "{side:?} g {g:?}: {v} vs {delta}");
                    let count = crate::surface_checks::self_intersections(&m, 4).count;
                    if count > 0 {
                        folds.push(format!(
                            "{side:?} posture {n} (g {g:.2}) at {delta:+.0} ml: {count}"
                        ));
                    }
                    if step == 6 {
                        worst = worst.max(largest(&u, s) / supine_max);
                    }
                }
            }
        }
        eprintln!("largest vertex move at +1500 ml over the postures: {worst:.2}× the supine one");
        assert!(
            folds.is_empty(),
            "{} folded:\n{}",
            folds.len(),
            folds.join("\n")
        );
    }

    /// The seed's unsmoothed reading (`amplitude_smoothing_mm = 0`) is still reachable and still
    /// folds where issue 19 found it (right lung, population preset, its share of +500 ml of the
    /// whole); smoothing over 6 mm already removes it, and barely changes the lower third's motion.
    #[test]
    fn the_unsmoothed_reading_folds_and_smoothing_removes_it() {
        let side = Side::Right;
        let (raw, share) = baked_with(side, DirectionPreset::Population, 0.0);
        let (smooth, _) = baked_with(side, DirectionPreset::Population, 6.0);
        let delta = share * 500.0;
        let count =
            |k: &Kernel| crate::surface_checks::self_intersections(&deformed(k, delta), 4).count;
        assert!(
            count(&raw) > 0,
            "the unsmoothed amplitude folds at {delta:+.0} ml"
        );
        assert_eq!(count(&smooth), 0, "smoothed over 6 mm at {delta:+.0} ml");
        let (a, b) = (lower_third(&raw, delta), lower_third(&smooth, delta));
        for axis in 0..3 {
            assert!(
                (a[axis] - b[axis]).abs() <= 0.05 * a[axis].max(1.0),
                "{a:?} vs {b:?}"
            );
        }
    }
}
