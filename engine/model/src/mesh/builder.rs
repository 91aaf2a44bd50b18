//! The builder the built-in lung shapes share ([`super::anatomy`], [`super::teardrop`]): the
//! spherified cube at a resolution, a shape's mapping of sphere directions to a lung, the exact
//! height, the volume and the place in the body frame, mirrored to its side. Its own file so each
//! shape uses it one way, and [`super::generate`] only chooses the shape.

use std::collections::HashMap;

use glam::DVec3;

use super::{Side, TriMesh};

/// Smallest accepted vertex request.
pub const MIN_VERTICES: usize = 100;
/// Largest accepted vertex request (≈ 4 M: a 400k lung ×10).
pub const MAX_VERTICES: usize = 4_000_000;

/// Errors of the generator.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GenerateError {
    /// The requested resolution is outside the supported range.
    #[error("--vertices {requested} is out of range: use {MIN_VERTICES} to {MAX_VERTICES}")]
    VertexCount {
        /// What was asked for.
        requested: usize,
    },
}

/// Cube subdivision giving at least `vertices` vertices (6·n² + 2).
pub fn subdivision_for(vertices: usize) -> usize {
    let n = (((vertices.saturating_sub(2)) as f64 / 6.0).sqrt()).ceil() as usize;
    n.max(2)
}

/// Where a shaped lung goes: its size and its place in the body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Placement {
    /// Apex-to-lowest-point height, mm.
    pub height_mm: f64,
    /// Enclosed volume, ml: the horizontal extent is scaled to it.
    pub volume_ml: f64,
    /// Distance from the mid-sagittal plane to the lung's most medial point, mm.
    pub mediastinum_half_mm: f64,
    /// Height of the apex in the body frame, mm.
    pub apex_z_mm: f64,
}

/// The shared builder: the spherified cube at the resolution for `vertices`, each unit-sphere
/// direction (x lateral, y anterior, z superior) mapped by `shape_point` to a lung-local point in
/// mm (lateral, anterior, superior; horizontal scale 1), then the height rescaled exactly with the
/// apex at `placement.apex_z_mm`, the horizontal extent scaled so the enclosed volume is
/// `placement.volume_ml`, the medial-most point put `mediastinum_half_mm` from the midline and the
/// lung mirrored to `side` (winding kept outward).
pub(super) fn build(
    side: Side,
    vertices: usize,
    placement: Placement,
    shape_point: impl Fn(DVec3) -> DVec3,
) -> Result<TriMesh, GenerateError> {
    if !(MIN_VERTICES..=MAX_VERTICES).contains(&vertices) {
        return Err(GenerateError::VertexCount {
            requested: vertices,
        });
    }
    let (sphere, mut triangles) = spherified_cube(subdivision_for(vertices));
    // Shape with unit horizontal scale, then scale horizontally to the target volume.
    let mut local: Vec<DVec3> = sphere.iter().map(|&s| shape_point(s)).collect();
    // Rescale vertically to the exact height (the shape's range may differ a little from it: a
    // dome lifting the lowest points), the apex at its level.
    let (z_lo, z_hi) = local
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.z), hi.max(p.z))
        });
    let z_scale = placement.height_mm / (z_hi - z_lo);
    for p in &mut local {
        p.z = placement.apex_z_mm - (z_hi - p.z) * z_scale;
    }
    let volume_of = |scale: f64| {
        super::enclosed_volume_with(&triangles, |i| {
            let p = local[i as usize];
            [p.x * scale, p.y * scale, p.z]
        })
    };
    // The local frame (lateral, anterior, superior) is right-handed; the volume is positive.
    let v1 = volume_of(1.0) / 1000.0;
    let scale = (placement.volume_ml / v1).sqrt();
    let medial_extent = local
        .iter()
        .map(|p| p.x * scale)
        .fold(f64::INFINITY, f64::min);
    let sign = side.lateral_sign() as f64;
    let positions: Vec<[f32; 3]> = local
        .iter()
        .map(|p| {
            // Lateral coordinate: the medial-most point sits `mediastinum_half_mm` from the midline.
            let lateral = p.x * scale - medial_extent + placement.mediastinum_half_mm;
            [(sign * lateral) as f32, (p.y * scale) as f32, p.z as f32]
        })
        .collect();
    if sign < 0.0 {
        // Mirroring X for the right lung flips the winding; flip it back so triangles face outward.
        for t in &mut triangles {
            t.swap(1, 2);
        }
    }
    Ok(TriMesh {
        positions,
        triangles,
    })
}

/// Unit-sphere vertices and outward-wound triangles of a cube subdivided `n` times per edge.
pub(super) fn spherified_cube(n: usize) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let mut index: HashMap<[u32; 3], u32> = HashMap::with_capacity(6 * n * n + 2);
    let mut points: Vec<DVec3> = Vec::with_capacity(6 * n * n + 2);
    let mut triangles: Vec<[u32; 3]> = Vec::with_capacity(12 * n * n);
    let n32 = n as u32;
    // Each face: the fixed axis and its value, and the (u, v) axes with u × v = outward normal.
    let faces: [(usize, u32, usize, usize); 6] = [
        (0, n32, 1, 2), // +X: Y × Z = X
        (0, 0, 2, 1),   // −X: Z × Y = −X
        (1, n32, 2, 0), // +Y: Z × X = Y
        (1, 0, 0, 2),   // −Y: X × Z = −Y
        (2, n32, 0, 1), // +Z: X × Y = Z
        (2, 0, 1, 0),   // −Z: Y × X = −Z
    ];
    for (fixed, value, ua, va) in faces {
        let mut id = |u: u32, v: u32| -> u32 {
            let mut key = [0u32; 3];
            key[fixed] = value;
            key[ua] = u;
            key[va] = v;
            *index.entry(key).or_insert_with(|| {
                let c = key.map(|k| 2.0 * k as f64 / n as f64 - 1.0);
                points.push(spherify(DVec3::from(c)));
                (points.len() - 1) as u32
            })
        };
        for u in 0..n32 {
            for v in 0..n32 {
                let a = id(u, v);
                let b = id(u + 1, v);
                let c = id(u + 1, v + 1);
                let d = id(u, v + 1);
                // Alternate the diagonal so the triangulation has no directional bias.
                if (u + v) % 2 == 0 {
                    triangles.push([a, b, c]);
                    triangles.push([a, c, d]);
                } else {
                    triangles.push([a, b, d]);
                    triangles.push([b, c, d]);
                }
            }
        }
    }
    (points, triangles)
}

/// Cube point in [−1, 1]³ → unit sphere, with the near-equal-area "spherified cube" map.
fn spherify(c: DVec3) -> DVec3 {
    let (x2, y2, z2) = (c.x * c.x, c.y * c.y, c.z * c.z);
    DVec3::new(
        c.x * (1.0 - y2 / 2.0 - z2 / 2.0 + y2 * z2 / 3.0).sqrt(),
        c.y * (1.0 - z2 / 2.0 - x2 / 2.0 + z2 * x2 / 3.0).sqrt(),
        c.z * (1.0 - x2 / 2.0 - y2 / 2.0 + x2 * y2 / 3.0).sqrt(),
    )
    .normalize()
}

/// Hermite step from 0 at `e0` to 1 at `e1`.
pub(super) fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}
