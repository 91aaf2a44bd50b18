//! The smooth teardrop lungs (`lungdyn mesh generate --shape teardrop`, `[lungs] shape =
//! "teardrop"`): the built-in default before the anatomical lungs ([`super::anatomy`]), kept for
//! comparison. Each sphere direction of the generator's spherified cube (`generate::build`) is
//! shaped into:
//!
//! * **apex** — a narrowed round dome at the top;
//! * **costal surface** — the convex lateral wall, deeper posteriorly than anteriorly;
//! * **medial surface** — flatter than the costal one, with a concave impression for the heart that
//!   is deep on the left lung (cardiac impression) and shallow on the right;
//! * **diaphragmatic base** — a flat rim with a concave dome pushed up in the middle.
//!
//! The horizontal extent is finally scaled so the enclosed volume is exactly the target (FRC share
//! of each lung: right 1300 ml + left 1100 ml = 2400 ml, Table 5.2's FRC), height kept (right
//! 230 mm, left 240 mm: the liver lifts the right dome), centred on z = 0. The surface is closed,
//! 2-manifold and wound outward by construction; [`super::check`] verifies it in tests at every
//! resolution.

use glam::DVec3;

use super::builder::{build, smoothstep, GenerateError, Placement};
use super::{Side, TriMesh};

/// Shape parameters of one teardrop lung.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungShape {
    /// Apex-to-base height, mm.
    pub height_mm: f64,
    /// Target enclosed volume, ml.
    pub volume_ml: f64,
    /// Lateral (costal) half-width before volume scaling, mm.
    pub lateral_mm: f64,
    /// Medial half-width before volume scaling, mm.
    pub medial_mm: f64,
    /// Anterior half-depth before volume scaling, mm.
    pub anterior_mm: f64,
    /// Posterior half-depth before volume scaling, mm.
    pub posterior_mm: f64,
    /// Depth of the medial (cardiac) impression as a fraction of the medial half-width.
    pub cardiac_impression: f64,
    /// Height of the diaphragmatic dome as a fraction of the lung height.
    pub diaphragm_dome: f64,
    /// Half-width of the mediastinum: distance from the mid-sagittal plane to the medial surface, mm.
    pub mediastinum_half_mm: f64,
}

impl LungShape {
    /// Default adult lung at FRC.
    pub fn adult(side: Side) -> Self {
        match side {
            Side::Right => LungShape {
                height_mm: 230.0,
                volume_ml: 1300.0,
                lateral_mm: 72.0,
                medial_mm: 50.0,
                anterior_mm: 62.0,
                posterior_mm: 88.0,
                cardiac_impression: 0.22,
                diaphragm_dome: 0.30,
                mediastinum_half_mm: 22.0,
            },
            Side::Left => LungShape {
                height_mm: 240.0,
                volume_ml: 1100.0,
                lateral_mm: 68.0,
                medial_mm: 46.0,
                anterior_mm: 58.0,
                posterior_mm: 86.0,
                cardiac_impression: 0.55,
                diaphragm_dome: 0.28,
                mediastinum_half_mm: 30.0,
            },
        }
    }
}

/// Generate the teardrop adult lung of `side` with at least `vertices` vertices (exactly
/// `6·n² + 2` for the smallest such `n`).
pub fn lung(side: Side, vertices: usize) -> Result<TriMesh, GenerateError> {
    lung_with(side, vertices, &LungShape::adult(side))
}

/// Generate a teardrop lung of `side` and explicit `shape`, centred vertically on z = 0.
pub fn lung_with(side: Side, vertices: usize, shape: &LungShape) -> Result<TriMesh, GenerateError> {
    let placement = Placement {
        height_mm: shape.height_mm,
        volume_ml: shape.volume_ml,
        mediastinum_half_mm: shape.mediastinum_half_mm,
        apex_z_mm: 0.5 * shape.height_mm,
    };
    build(side, vertices, placement, |s| shape_point(s, shape))
}

/// Unit sphere direction (x lateral, y anterior, z superior) → lung-local point in mm
/// (lateral, anterior, superior), horizontal scale 1.
fn shape_point(s: DVec3, shape: &LungShape) -> DVec3 {
    // h: 0 at the apex, 1 at the bottom pole of the base.
    let h = ((1.0 - s.z) / 2.0).clamp(0.0, 1.0);
    let phi = s.y.atan2(s.x);
    let (sin_phi, cos_phi) = phi.sin_cos();
    // Horizontal profile: a narrowed round dome above, a flat-rimmed superellipse below.
    // The taper spans both halves so the profile is continuous at h = 0.5 (no ridge).
    let taper = 0.62 + 0.38 * smoothstep(0.0, 0.75, h);
    let profile = taper
        * if h < 0.5 {
            (1.0 - (1.0 - 2.0 * h).powi(2)).max(0.0).powf(0.4)
        } else {
            (1.0 - (2.0 * h - 1.0).powi(5)).max(0.0).powf(0.2)
        };
    // Costal side wider than medial; posterior deeper than anterior (both smooth in φ).
    let half_width = 0.5 * (shape.lateral_mm + shape.medial_mm)
        + 0.5 * (shape.lateral_mm - shape.medial_mm) * cos_phi;
    let half_depth = 0.5 * (shape.anterior_mm + shape.posterior_mm)
        + 0.5 * (shape.anterior_mm - shape.posterior_mm) * sin_phi;
    let mut lateral = profile * half_width * cos_phi;
    let anterior = profile * half_depth * sin_phi;
    // Medial impression: scale the medial coordinate towards the centre around the heart's position
    // (anteromedial, lower middle). Scaling one coordinate of a star-shaped section cannot fold it.
    if cos_phi < 0.0 {
        let around_heart = (phi - 0.75 * std::f64::consts::PI).cos().max(0.0).powi(2);
        let at_heart_level = (-((h - 0.62) / 0.2).powi(2)).exp();
        lateral *= 1.0 - shape.cardiac_impression * around_heart * at_heart_level;
    }
    // Vertical: linear in h, the base centre lifted by the diaphragmatic dome.
    let dome = shape.diaphragm_dome
        * shape.height_mm
        * smoothstep(0.5, 1.0, h)
        * (1.0 - profile * profile);
    let superior = shape.height_mm * (0.5 - h) + dome;
    DVec3::new(lateral, anterior, superior)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::check;

    #[test]
    fn adult_dimensions_match_the_targets() {
        let right = lung(Side::Right, 20_000).unwrap();
        let left = lung(Side::Left, 20_000).unwrap();
        assert!((right.enclosed_volume_ml() - 1300.0).abs() < 1e-6 * 1300.0);
        assert!((left.enclosed_volume_ml() - 1100.0).abs() < 1e-6 * 1100.0);
        let total = right.enclosed_volume_ml() + left.enclosed_volume_ml();
        assert!((total - 2400.0).abs() < 0.01);
        // About 24 cm tall at FRC (the dome lowers the measured height of neither: apex and rim).
        for (m, h) in [(&left, 240.0), (&right, 230.0)] {
            let size = m.aabb().size();
            assert!((size[2] - h).abs() < 1.0, "height {}", size[2]);
            assert!(size[0] > 80.0 && size[0] < 160.0, "width {}", size[0]);
            assert!(size[1] > 100.0 && size[1] < 220.0, "depth {}", size[1]);
        }
        // The mid-sagittal gap separates the lungs.
        assert!(right.aabb().max[0] < -10.0 && left.aabb().min[0] > 10.0);
    }

    #[test]
    fn the_base_is_concave_and_the_left_lung_has_a_cardiac_impression() {
        let left = lung(Side::Left, 20_000).unwrap();
        let bb = left.aabb();
        // Concave base: the lowest point under the lung's centre is well above the lowest rim point.
        let centre = [0.5 * (bb.min[0] + bb.max[0]), 0.5 * (bb.min[1] + bb.max[1])];
        let near_axis_min_z = left
            .positions
            .iter()
            .filter(|p| {
                (p[0] - centre[0]).abs() < 8.0 && (p[1] - centre[1]).abs() < 8.0 && p[2] < 0.0
            })
            .map(|p| p[2])
            .fold(f32::INFINITY, f32::min);
        assert!(
            near_axis_min_z > bb.min[2] + 25.0,
            "{near_axis_min_z} vs {}",
            bb.min[2]
        );
        // Cardiac impression: at heart level, the anteromedial surface lies further from the midline
        // than the posteromedial one.
        let z_heart = bb.max[2] - 0.62 * (bb.max[2] - bb.min[2]);
        let medial_x = |anterior: bool| {
            left.positions
                .iter()
                .filter(|p| (p[2] - z_heart).abs() < 6.0 && ((p[1] > centre[1] + 20.0) == anterior))
                .map(|p| p[0])
                .fold(f32::INFINITY, f32::min)
        };
        assert!(
            medial_x(true) > medial_x(false) + 5.0,
            "{} vs {}",
            medial_x(true),
            medial_x(false)
        );
    }

    #[test]
    fn generation_is_deterministic() {
        assert_eq!(
            lung(Side::Left, 3000).unwrap(),
            lung(Side::Left, 3000).unwrap()
        );
    }

    #[test]
    fn four_hundred_thousand_vertices_are_supported() {
        let mesh = lung(Side::Right, 400_000).unwrap();
        assert!(mesh.positions.len() >= 400_000);
        check(&mesh).unwrap();
    }
}
