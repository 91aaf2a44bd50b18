//! # folds: how far from its start volume a lung can be drawn before its surface crosses itself
//!
//! A kernel's precomputed field moves every vertex by `s·u_i`; past some volume a fitted motion
//! (which slides the base along the chest wall) or a population fitted on other lungs may push two
//! parts of the surface through each other (docs/masks/patient_motion.md). The search here checks the
//! surface as the GPU draws it (`p + s·u` in f32, [`LungModel::deform_into`]) for crossing triangles
//! ([`crate::surface_checks::self_intersections`]) at volumes stepping out from the start volume,
//! and refines the first fold found by bisection. The bake records the range in the kernel
//! ([`FoldFreeMeta`]) and the engine marks frames drawn outside it.

use glam::DVec3;
use lung_model::deform::LungModel;
use lung_model::kernel::FoldFreeMeta;
use lung_model::mesh::TriMesh;

/// Volumes checked on the way out from the start volume: the first fold is found to 1/24 of the
/// searched span, then refined by [`REFINE`] bisection steps. Folds are not monotone in the volume
/// (two triangles moving linearly can pass through each other and out again: case 09's left lung,
/// with the breath-hold population at 20 000 vertices, crosses from −17 to −29 ml and not at
/// −30 to −48 ml), so a bisection over the whole span alone steps over such a first fold, and a
/// crossing that comes and goes between two checked volumes (1/24 of the span: 11 ml below that
/// lung, 43 ml above) is not seen. Each check costs about 0.03 s at 10 000 vertices and 0.05 s at
/// 20 000 (two cores): the count is the bake's price for the range.
const SCAN: usize = 24;
/// Bisection steps between the last volume checked clean and the first that folds.
const REFINE: usize = 5;

/// The model's surface drawn `delta_ml` from its start volume (precomputed mode), in mm.
pub fn at_volume(model: &LungModel, delta_ml: f64) -> Vec<DVec3> {
    drawn(model, delta_ml)
        .iter()
        .map(|q| DVec3::from(q.map(|v| v as f64)))
        .collect()
}

fn drawn(model: &LungModel, delta_ml: f64) -> Vec<[f32; 3]> {
    let s = model.scale_for_delta(delta_ml) as f32;
    let mut out = vec![[0.0f32; 3]; model.mesh.positions.len()];
    model.deform_into(s, &mut out);
    out
}

/// Whether the surface drawn `delta_ml` from the start volume crosses itself.
pub fn folds_at(model: &LungModel, delta_ml: f64) -> bool {
    let mesh = TriMesh {
        positions: drawn(model, delta_ml),
        triangles: model.mesh.triangles.clone(),
    };
    crate::surface_checks::self_intersections(&mesh, 1).count > 0
}

/// The largest share of `delta_ml` (`delta_ml` may be negative: a shrinking lung) up to which the
/// surface was found not to cross itself: 1 when no fold was found at any of the [`SCAN`] shares
/// checked, else the first fold's share refined to 1/768.
pub fn fold_free_share(model: &LungModel, delta_ml: f64) -> f64 {
    let folds = |share: f64| folds_at(model, share * delta_ml);
    let Some(k) = (1..=SCAN).find(|&k| folds(k as f64 / SCAN as f64)) else {
        return 1.0;
    };
    let (mut lo, mut hi) = ((k - 1) as f64 / SCAN as f64, k as f64 / SCAN as f64);
    for _ in 0..REFINE {
        let mid = 0.5 * (lo + hi);
        if folds(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    lo
}

/// The range a kernel's lung is drawn without a fold: searched up to
/// [`FoldFreeMeta::ABOVE_SHARE`] of its start volume above it and [`FoldFreeMeta::BELOW_SHARE`]
/// below (at most 2 × ([`SCAN`] + [`REFINE`]) surface checks, 2 × [`SCAN`] where it folds nowhere).
pub fn range(model: &LungModel) -> FoldFreeMeta {
    range_within(
        model,
        FoldFreeMeta::ABOVE_SHARE * model.start_volume_ml,
        FoldFreeMeta::BELOW_SHARE * model.start_volume_ml,
    )
}

/// The range searched `up_ml` above the start volume and `down_ml` below it (both positive).
pub fn range_within(model: &LungModel, up_ml: f64, down_ml: f64) -> FoldFreeMeta {
    FoldFreeMeta {
        above_ml: fold_free_share(model, up_ml) * up_ml,
        below_ml: fold_free_share(model, -down_ml) * down_ml,
        searched_above_ml: up_ml,
        searched_below_ml: down_ml,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::Side;

    /// A tetrahedron with outward faces, corner at `at`, edge `size`.
    fn tetra(at: [f32; 3], size: f32, first: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        let unit = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let p = unit
            .iter()
            .map(|c: &[f32; 3]| [0, 1, 2].map(|k| at[k] + size * c[k]))
            .collect();
        let t = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
            .iter()
            .map(|f: &[u32; 3]| f.map(|v| v + first))
            .collect();
        (p, t)
    }

    /// Folds need not grow with the volume: a small tetrahedron that grows as it moves through a
    /// fixed one and out again crosses it only on the way. A bisection over the whole span sees no
    /// fold at its end and stops there; the scan finds the first crossing, and every volume it
    /// reports free is free.
    #[test]
    fn a_crossing_that_comes_and_goes_is_found_on_the_way_out() {
        let (mut p, mut t) = tetra([-2.5, -2.5, -2.5], 10.0, 0);
        let (q, u) = tetra([45.0, -5.0, -5.0], 20.0, 4);
        p.extend(q);
        t.extend(u);
        // The small one moves 1 mm along +X per unit scale and grows 1 % about its centroid (so
        // the volume grows with the scale); the large one stays.
        let disp: Vec<[f32; 3]> = (0..8)
            .map(|i| {
                if i < 4 {
                    let c = p[i];
                    [1.0 + 0.01 * c[0], 0.01 * c[1], 0.01 * c[2]]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let mesh = TriMesh {
            positions: p,
            triangles: t,
        };
        let model = LungModel::from_unit_displacement(Side::Right, mesh, disp);
        // Scale 100: the small one lies past the large one, its volume 2³ of its start.
        let small_ml = 1000.0f64 / 6.0 / 1000.0;
        let end_ml = small_ml * 7.0;
        let s_end = model.scale_for_delta(end_ml);
        assert!((s_end - 100.0).abs() < 1e-3, "scale {s_end}");
        assert!(!folds_at(&model, 0.0));
        assert!(!folds_at(&model, end_ml), "clean again at the end");
        assert!(folds_at(&model, 0.5 * end_ml), "crossing on the way");
        let share = fold_free_share(&model, end_ml);
        assert!(share < 0.5, "the first crossing is found: share {share}");
        // The threshold is tight: free there, and crossing within one refinement step past it.
        assert!(!folds_at(&model, share * end_ml));
        let step = 1.0 / (SCAN as f64 * (1 << REFINE) as f64);
        assert!(folds_at(&model, (share + step) * end_ml));
        // Every scanned volume below it is free.
        for k in 0..SCAN {
            let s = k as f64 / SCAN as f64;
            if s < share {
                assert!(!folds_at(&model, s * end_ml), "share {s}");
            }
        }
        let r = range_within(&model, end_ml, 0.1);
        assert_eq!(r.above_ml, share * end_ml);
        assert!(r.contains(0.0) && !r.contains(0.5 * end_ml) && !r.contains(end_ml));
    }

    /// The bake records the range of the motion it baked, found as the search finds it: the
    /// breath-hold population folds the generated right lung within the span searched above it.
    #[test]
    fn the_bake_records_where_its_motion_first_folds() {
        use lung_model::deform::DirectionPreset;
        let mesh = lung_model::mesh::anatomy::lung(Side::Right, 1_500).unwrap();
        let bake = |preset| {
            let settings = lung_model::kernel::BakeSettings::for_preset(preset, Side::Right);
            crate::kernel::bake(Side::Right, mesh.clone(), &settings, &|_| {}).unwrap()
        };
        let k = bake(DirectionPreset::BreathHold);
        let r = k.meta.fold_free.expect("measured");
        let model = LungModel::from_unit_displacement(
            Side::Right,
            k.mesh.clone(),
            k.unit_displacement.clone(),
        );
        assert_eq!(r, range(&model), "the recorded range is the kernel's own");
        assert_eq!(
            r.searched_above_ml,
            FoldFreeMeta::ABOVE_SHARE * k.meta.start_volume_ml
        );
        assert!(!folds_at(&model, r.above_ml) && !folds_at(&model, -r.below_ml));
        assert!(r.above_ml < r.searched_above_ml, "{}", r.describe());
        let step = r.searched_above_ml / (SCAN as f64 * (1 << REFINE) as f64);
        assert!(folds_at(&model, r.above_ml + step));
    }
}
