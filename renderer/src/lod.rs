//! Draw levels of detail: fewer triangles over the same vertices when the lungs cover few pixels.
//!
//! The deformation pass moves every physics vertex each frame (it is cheap: 0.13 ms for 400k
//! vertices on an H200); what costs is drawing them (4.7 ms per eye there, most of it the raster
//! work of sub-pixel triangles: `docs/gpu/h200-2026-11-26`). So each lung's triangle list is
//! simplified once, at load, into coarser index lists that reference the **same** vertex buffer
//! (meshoptimizer's edge-collapse simplifier keeps a subset of the vertices and never moves them):
//! level k has about 4⁻ᵏ of the triangles, down to [`MIN_TRIANGLES`] per lung. The deformed
//! positions and the smooth normals (computed from the full mesh) are the same buffers at every
//! level, so a coarser level is the same breathing surface through fewer of its points.
//!
//! **Choosing a level** ([`Chooser`]): each frame, the lungs' box (rest box moved by the lungs'
//! offsets) is projected through every eye and the largest on-screen area, clipped to the eye, in
//! pixels, gives a budget of [`TRIANGLES_PER_PIXEL`] triangles per covered pixel; the finest
//! level within the budget is drawn. Both eyes draw the same level (the larger eye's), so a stereo
//! pair never shows two different surfaces. Hysteresis: the level changes only when the budget
//! leaves the band ±[`HYSTERESIS`] around the current level's count, so a lung breathing at the
//! threshold does not flicker. A box that does not project (an eye inside or behind it) draws every
//! triangle.

use std::ops::Range;

use glam::{Mat4, Vec3, Vec4};

use crate::camera::EyeUniform;

/// Triangles drawn per pixel the lungs' box covers, at most: beyond about one triangle per pixel
/// of the surface seen (a box's pixels are about twice the front-facing surface's triangles' share)
/// the extra triangles are sub-pixel and change nothing on screen but the cost.
pub const TRIANGLES_PER_PIXEL: f32 = 2.0;
/// Hysteresis: a coarser level is taken only when the current one exceeds the budget by this
/// factor, a finer one only when it fits the budget shrunk by it.
pub const HYSTERESIS: f32 = 1.25;
/// Each level keeps about this fraction of the previous level's triangles.
pub const LEVEL_RATIO: f32 = 0.25;
/// No level of a lung has fewer triangles than this (the lung's outline stays smooth at the sizes
/// where such a level is chosen: a few dozen pixels).
pub const MIN_TRIANGLES: usize = 500;
/// The simplifier's error bound, relative to the lung's largest extent (about 1 mm on an adult
/// lung at level 1; coarser levels are allowed [`ERROR_GROWTH`] times their finer level's bound).
pub const ERROR_RELATIVE: f32 = 0.004;
/// How much more error each coarser level may have than the one before.
pub const ERROR_GROWTH: f32 = 2.5;

/// Every draw level of one lung ([`lung_levels`]), and why there are no coarser ones when the
/// simplifier's next level was refused.
#[derive(Debug, Clone, PartialEq)]
pub struct LungLevels {
    /// Level 0 the lung's own triangles, then coarser lists over the same vertices.
    pub levels: Vec<Vec<[u32; 3]>>,
    /// The first level built and refused, with the topology check's words: that level and every
    /// coarser one are not drawn (the coarsest kept is drawn in their place).
    pub refused: Option<(usize, String)>,
}

/// Every draw level of one lung: level 0 its own triangles, then coarser lists over the same
/// vertices. Each coarser level is checked as the bake checks a lung (`lung_model::mesh::check`:
/// closed, 2-manifold, consistently wound, no degenerate triangle, positive volume) after its
/// zero-volume fins are dropped ([`drop_fins`]); a level that still fails is not drawn, nor is any
/// coarser one — a hole or a fold in the drawn surface is worse than drawing more triangles.
pub fn lung_levels(positions: &[[f32; 3]], triangles: &[[u32; 3]], coarsest: u8) -> LungLevels {
    let mut levels = vec![triangles.to_vec()];
    let adapter = meshopt::VertexDataAdapter::new(
        bytemuck::cast_slice(positions),
        std::mem::size_of::<[f32; 3]>(),
        0,
    );
    let Ok(adapter) = adapter else {
        return LungLevels {
            levels,
            refused: None,
        };
    };
    let mut error = ERROR_RELATIVE;
    for _ in 0..coarsest {
        let prev = levels.last().expect("level 0");
        let target = (prev.len() as f32 * LEVEL_RATIO) as usize;
        if target < MIN_TRIANGLES {
            break;
        }
        let indices: &[u32] = bytemuck::cast_slice(prev);
        let out = meshopt::simplify(
            indices,
            &adapter,
            target * 3,
            error,
            meshopt::SimplifyOptions::None,
            None,
        );
        // A level that could not get much coarser within its error bound is not worth a level.
        if out.len() / 3 < MIN_TRIANGLES || out.len() as f32 > indices.len() as f32 * 0.6 {
            break;
        }
        let mut level: Vec<[u32; 3]> = bytemuck::cast_slice(&out).to_vec();
        drop_fins(&mut level);
        if let Err(e) = lung_model::mesh::check(&compact(positions, &level)) {
            return LungLevels {
                refused: Some((levels.len(), e.to_string())),
                levels,
            };
        }
        levels.push(level);
        error *= ERROR_GROWTH;
    }
    LungLevels {
        levels,
        refused: None,
    }
}

/// Drop every pair of triangles over the same three vertices wound opposite ways: a zero-volume
/// fin, two faces back to back, that meshoptimizer's edge collapses leave where a thin strip folds
/// onto itself (at 2 × 400k, level 4 of the right lung had 9 such pairs, each a flap on one
/// surface edge, shared then by four triangles, its third vertex used by nothing else; MeshLab
/// counted the same 9 non-manifold edges, docs/lod.md). The surface around a fin is closed
/// without it.
pub fn drop_fins(tris: &mut Vec<[u32; 3]>) {
    use std::collections::HashMap;
    // Each triangle rotated to start at its smallest index keeps its winding: [m, a, b] and
    // [m, b, a] are the two windings of one vertex set.
    let rotated = |t: &[u32; 3]| {
        let k = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
        [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
    };
    let mut seen: HashMap<[u32; 3], usize> = HashMap::with_capacity(tris.len());
    let mut fin = vec![false; tris.len()];
    for (n, t) in tris.iter().enumerate() {
        let r = rotated(t);
        if let Some(&m) = seen.get(&[r[0], r[2], r[1]]) {
            if !fin[m] {
                fin[m] = true;
                fin[n] = true;
                continue;
            }
        }
        seen.insert(r, n);
    }
    let mut n = 0;
    tris.retain(|_| {
        n += 1;
        !fin[n - 1]
    });
}

/// Triangles `tris` over `positions` as a mesh of their own (the vertices they use, renumbered),
/// for `lung_model::mesh::check`, which refuses unused vertices.
pub(crate) fn compact(positions: &[[f32; 3]], tris: &[[u32; 3]]) -> lung_model::mesh::TriMesh {
    let mut map = vec![u32::MAX; positions.len()];
    let mut used = Vec::new();
    let triangles = tris
        .iter()
        .map(|t| {
            t.map(|i| {
                if map[i as usize] == u32::MAX {
                    map[i as usize] = used.len() as u32;
                    used.push(positions[i as usize]);
                }
                map[i as usize]
            })
        })
        .collect();
    lung_model::mesh::TriMesh {
        positions: used,
        triangles,
    }
}

/// The levels of every lung in one index buffer: per level, each lung's triangles offset to its
/// place in the shared vertex buffer, one range per level.
#[derive(Debug, Clone, Default)]
pub struct Levels {
    /// Indices of every level, level 0 first.
    pub indices: Vec<u32>,
    /// Per level, its range in `indices`.
    pub ranges: Vec<Range<u32>>,
}

impl Levels {
    /// Join each lung's levels (`per_lung[k]`: lung k's levels, `counts[k]` its vertices): a lung
    /// with fewer levels than another draws its coarsest at the others' coarser levels.
    pub fn join(per_lung: &[Vec<Vec<[u32; 3]>>], counts: &[u32]) -> Self {
        let n = per_lung.iter().map(Vec::len).max().unwrap_or(0);
        let mut out = Self::default();
        for level in 0..n {
            let start = out.indices.len() as u32;
            let mut offset = 0;
            for (lung, &count) in per_lung.iter().zip(counts) {
                if let Some(tris) = lung.get(level).or(lung.last()) {
                    out.indices
                        .extend(tris.iter().flat_map(|t| t.map(|i| i + offset)));
                }
                offset += count;
            }
            out.ranges.push(start..out.indices.len() as u32);
        }
        out
    }

    /// Triangles of level `level`.
    pub fn triangles(&self, level: usize) -> u32 {
        self.ranges.get(level).map_or(0, |r| (r.end - r.start) / 3)
    }
}

/// Pixels of the eye (`width` × `height`) covered by the box `(lo, hi)` (body frame) seen through
/// `eye`: the bounding rectangle of its projected corners, clipped to the eye; `None` when a
/// corner is not in front of the eye (the eye is in or beside the box: draw every triangle).
pub fn covered_pixels(
    eye: &EyeUniform,
    (lo, hi): (Vec3, Vec3),
    width: u32,
    height: u32,
) -> Option<f32> {
    let m = Mat4::from_cols_array_2d(&eye.view_proj) * Mat4::from_cols_array_2d(&eye.model);
    let (mut min, mut max) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    for corner in 0..8 {
        let p = Vec3::new(
            if corner & 1 == 0 { lo.x } else { hi.x },
            if corner & 2 == 0 { lo.y } else { hi.y },
            if corner & 4 == 0 { lo.z } else { hi.z },
        );
        let c = m * Vec4::new(p.x, p.y, p.z, 1.0);
        if !(c.w > 1e-3 && c.is_finite()) {
            return None;
        }
        for a in 0..2 {
            let v = c[a] / c.w;
            min[a] = min[a].min(v);
            max[a] = max[a].max(v);
        }
    }
    let span = |a: usize| (max[a].min(1.0) - min[a].max(-1.0)).max(0.0) * 0.5;
    Some(span(0) * width as f32 * span(1) * height as f32)
}

/// What the lungs were drawn with last frame (the HUD's frame-time line says it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Shown {
    /// The level drawn (0: every triangle).
    pub level: u8,
    /// The coarsest level built (0: no levels; `[render] lod = "off"` or point splats).
    pub coarsest: u8,
    /// Triangles drawn per eye.
    pub triangles: u32,
    /// The level follows the lungs' size on screen (`[render] lod = "auto"`).
    pub auto: bool,
}

/// The per-frame choice of level, with hysteresis ([`HYSTERESIS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Chooser {
    current: usize,
}

impl Chooser {
    /// A chooser whose current level is `level`.
    pub fn at(level: usize) -> Self {
        Self { current: level }
    }

    /// The level to draw this frame for a budget of `budget` triangles (`None`: every triangle),
    /// given each level's triangle count (`triangles[k]`, decreasing).
    pub fn choose(&mut self, triangles: &[u32], budget: Option<f32>) -> usize {
        let Some(budget) = budget.filter(|b| b.is_finite()) else {
            self.current = 0;
            return 0;
        };
        let finest_within = |b: f32| {
            triangles
                .iter()
                .position(|&t| t as f32 <= b)
                .unwrap_or(triangles.len().saturating_sub(1))
        };
        // Keep the current level while it is within the band: not over the budget by more than
        // the hysteresis, and no finer level fits a budget shrunk by it.
        let coarser_from = finest_within(budget * HYSTERESIS);
        let finer_to = finest_within(budget / HYSTERESIS);
        if self.current < coarser_from || self.current > finer_to {
            self.current = finest_within(budget);
        }
        self.current = self.current.min(triangles.len().saturating_sub(1));
        self.current
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::{check, generate, Side, TriMesh};

    /// A surface for distances (parry3d's BVH over its triangles).
    fn surface(positions: &[[f32; 3]], tris: &[[u32; 3]]) -> parry3d::shape::TriMesh {
        let v = positions
            .iter()
            .map(|p| parry3d::math::Vector::new(p[0], p[1], p[2]))
            .collect();
        parry3d::shape::TriMesh::new(v, tris.to_vec()).unwrap()
    }

    /// Symmetric Hausdorff-like distance, mm: the farthest full-mesh vertex from the level's
    /// surface, and the farthest point of the level's triangles (vertices, edge midpoints,
    /// centroids) from the full surface.
    pub(crate) fn level_error_mm(mesh: &TriMesh, tris: &[[u32; 3]]) -> f32 {
        use parry3d::query::PointQuery;
        let full = surface(&mesh.positions, &mesh.triangles);
        let level = surface(&mesh.positions, tris);
        let pt = |p: [f32; 3]| parry3d::math::Vector::new(p[0], p[1], p[2]);
        let d = |s: &parry3d::shape::TriMesh, p: [f32; 3]| s.distance_to_local_point(pt(p), true);
        let mut worst: f32 = 0.0;
        for &p in &mesh.positions {
            worst = worst.max(d(&level, p));
        }
        for t in tris {
            let [a, b, c] = t.map(|i| glam::Vec3::from(mesh.positions[i as usize]));
            for q in [
                (a + b) * 0.5,
                (b + c) * 0.5,
                (c + a) * 0.5,
                (a + b + c) / 3.0,
            ] {
                worst = worst.max(d(&full, q.to_array()));
            }
        }
        worst
    }

    /// Every level of both built-in lungs, at the default 10k vertices and at 100k, is a closed,
    /// 2-manifold, consistently wound surface (no holes), each coarser than the one before by about
    /// the level ratio, within a few mm of the full mesh (growing with the level).
    #[test]
    fn every_level_is_closed_manifold_and_close_to_the_full_mesh() {
        every_level_closed_manifold_and_close(&[
            (Side::Right, 10_000, 3),
            (Side::Left, 10_000, 3),
            (Side::Right, 100_000, 5),
            (Side::Left, 100_000, 5),
        ]);
    }

    /// The same at 2 × 400k, the GPU target's size (`bench/gpu_check.sh`'s LOD study), where the
    /// levels are drawn most: a separate test so it runs beside the smaller ones.
    #[test]
    fn every_level_at_400k_is_closed_manifold_and_close_to_the_full_mesh() {
        every_level_closed_manifold_and_close(&[
            (Side::Right, 400_000, 6),
            (Side::Left, 400_000, 6),
        ]);
    }

    fn every_level_closed_manifold_and_close(cases: &[(Side, usize, usize)]) {
        for &(side, vertices, want) in cases {
            let mesh = generate::lung(side, vertices).unwrap();
            let t0 = std::time::Instant::now();
            let built = lung_levels(&mesh.positions, &mesh.triangles, 5);
            let took = t0.elapsed();
            assert_eq!(built.refused, None, "{side:?} {vertices}");
            let levels = built.levels;
            assert!(levels.len() >= want, "{side:?}: {} levels", levels.len());
            assert_eq!(levels[0], mesh.triangles);
            let mut errors = Vec::new();
            for (k, tris) in levels.iter().enumerate() {
                let topo = check(&compact(&mesh.positions, tris))
                    .unwrap_or_else(|e| panic!("{side:?} level {k}: {e}"));
                assert_eq!(topo.euler, 2, "{side:?} level {k}: sphere-like");
                assert!(tris.len() >= MIN_TRIANGLES, "{side:?} level {k}");
                if k > 0 {
                    let ratio = tris.len() as f32 / levels[k - 1].len() as f32;
                    assert!(
                        (0.15..=0.6).contains(&ratio),
                        "{side:?} level {k}: {ratio} of the level before"
                    );
                }
                errors.push(level_error_mm(&mesh, tris));
            }
            eprintln!(
                "{side:?} {vertices}: built in {took:.2?}, triangles {:?}, error mm {errors:?}",
                { levels.iter().map(Vec::len).collect::<Vec<_>>() }
            );
            assert!(errors[0] < 1e-3, "level 0 is the mesh itself: {errors:?}");
            // A 200-odd mm lung: level 1 within 2 mm, the coarsest within 15 mm.
            assert!(errors[1] < 2.0, "{side:?}: {errors:?}");
            assert!(errors.iter().all(|&e| e < 15.0), "{side:?}: {errors:?}");
        }
    }

    /// A fin — a triangle and its reverse over the same vertices — is dropped, both faces; the
    /// closed surface around it and a triangle repeated with the same winding are kept.
    #[test]
    fn fins_are_dropped_and_nothing_else() {
        // A tetrahedron: closed, outward wound.
        let tet = vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]];
        let positions = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let mut same = tet.clone();
        drop_fins(&mut same);
        assert_eq!(same, tet);
        // A fin lying on the face (1, 2, 3), its two faces given in other rotations: the face's
        // edges are then shared by four triangles. Whichever same-wound copy goes, the same
        // closed tetrahedron is left.
        let mut finned = tet.clone();
        finned.insert(1, [3, 1, 2]);
        finned.push([2, 1, 3]);
        assert!(check(&compact(&positions, &finned)).is_err());
        drop_fins(&mut finned);
        assert_eq!(finned.len(), 4, "{finned:?}");
        assert!(check(&compact(&positions, &finned)).is_ok(), "{finned:?}");
        // A repeat with the same winding is no fin: left for the check to refuse.
        let mut twice = tet.clone();
        twice.push([2, 3, 1]);
        drop_fins(&mut twice);
        assert_eq!(twice.len(), 5);
    }

    /// Levels of two lungs join into one buffer, each lung's indices offset to its vertices; a
    /// lung with fewer levels repeats its coarsest.
    #[test]
    fn levels_join_with_offsets_and_repeat_the_coarsest() {
        let a = vec![vec![[0, 1, 2], [2, 1, 0]], vec![[0, 1, 2]]];
        let b = vec![vec![[0, 1, 2]]];
        let l = Levels::join(&[a, b], &[3, 3]);
        assert_eq!(l.ranges, vec![0..9, 9..15]);
        assert_eq!(&l.indices[6..9], &[3, 4, 5]);
        assert_eq!(&l.indices[9..], &[0, 1, 2, 3, 4, 5]);
        assert_eq!((l.triangles(0), l.triangles(1), l.triangles(9)), (3, 2, 0));
    }

    /// The finest level within the budget; no change inside the hysteresis band; every triangle
    /// when the box does not project or the budget is not a number.
    #[test]
    fn the_chooser_takes_the_finest_level_within_budget_with_hysteresis() {
        let t = [40_000, 10_000, 2_500, 600];
        let mut c = Chooser::default();
        assert_eq!(c.choose(&t, Some(100_000.0)), 0);
        assert_eq!(c.choose(&t, Some(39_000.0)), 0, "within the band: kept");
        assert_eq!(c.choose(&t, Some(30_000.0)), 1, "over by more than 1.25");
        assert_eq!(c.choose(&t, Some(45_000.0)), 1, "0 fits, but not by 1.25");
        assert_eq!(c.choose(&t, Some(51_000.0)), 0);
        assert_eq!(c.choose(&t, Some(100.0)), 3, "nothing fits: the coarsest");
        assert_eq!(c.choose(&t, Some(2_600.0)), 3, "2 fits, but not by 1.25");
        assert_eq!(c.choose(&t, Some(3_200.0)), 2);
        assert_eq!(c.choose(&t, None), 0);
        assert_eq!(c.choose(&t, Some(1.0)), 3);
        assert_eq!(c.choose(&t, Some(f32::NAN)), 0);
        assert_eq!(c.choose(&[], Some(5.0)), 0);
        // Flicker: a budget oscillating ±10 % about a level's count never switches.
        let mut c = Chooser::default();
        c.choose(&t, Some(10_000.0));
        for k in 0..100 {
            let b = 10_000.0 * if k % 2 == 0 { 1.1 } else { 0.9 };
            assert_eq!(c.choose(&t, Some(b)), 1);
        }
    }

    /// The covered area of a box straight ahead, and none for a box around the eye.
    #[test]
    fn covered_pixels_of_a_box_in_front_and_around_the_eye() {
        // A 90° field of view looking down −Z from the origin (clip w = −z).
        let proj = Mat4::from_cols(Vec4::X, Vec4::Y, Vec4::new(0.0, 0.0, -1.0, -1.0), -Vec4::Z);
        let eye = EyeUniform {
            view_proj: proj.to_cols_array_2d(),
            model: Mat4::IDENTITY.to_cols_array_2d(),
            eye_pos: [0.0; 4],
            cam_right: [1.0, 0.0, 0.0, 0.0],
            cam_up: [0.0, 1.0, 0.0, 0.0],
        };
        // A flat box at depth 100 spanning ±10: a tenth of the half-width each way.
        let b = (
            Vec3::new(-10.0, -10.0, -100.0),
            Vec3::new(10.0, 10.0, -100.0),
        );
        let px = covered_pixels(&eye, b, 200, 200).unwrap();
        assert!((px - 400.0).abs() < 1.0, "{px}");
        // Larger than the view: clipped to the eye's pixels.
        let big = (Vec3::new(-1e3, -1e3, -100.0), Vec3::new(1e3, 1e3, -100.0));
        assert_eq!(covered_pixels(&eye, big, 200, 200), Some(40_000.0));
        let around = (Vec3::splat(-10.0), Vec3::splat(10.0));
        assert_eq!(covered_pixels(&eye, around, 200, 200), None);
    }
}
