//! Procedural adult lungs: the built-in default geometry, at any resolution.
//!
//! Two shapes share one builder ([`super::builder::build`]): a subdivided cube is projected onto the sphere (the
//! "spherified cube": near-uniform vertices at any resolution, no pole singularities), each sphere
//! direction is mapped to a lung-local point by the shape's function, and the result is scaled
//! horizontally to the target volume, placed vertically and mirrored to its side:
//!
//! * [`Shape::Anatomical`] (the default: [`super::anatomy`]) — hilum, cardiac impression, notch and
//!   lingula, a domed diaphragmatic base with posterior costophrenic recesses, sharp anterior and
//!   inferior borders; both apices at one level, the right lung shorter and wider;
//! * [`Shape::Teardrop`] ([`super::teardrop`]) — the earlier smooth teardrop, kept for comparison
//!   (`lungdyn mesh generate --shape teardrop`, `[lungs] shape = "teardrop"`).
//!
//! Every step is deterministic: the same `(shape, side, vertices)` always gives bit-identical
//! meshes, which is what lets the engine and the renderer build the same lung independently.

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::Shape;

pub use super::builder::{subdivision_for, GenerateError, MAX_VERTICES, MIN_VERTICES};
use super::{Side, TriMesh};

/// Generate the default adult lung ([`Shape::default`], anatomical) of `side` with at least
/// `vertices` vertices (exactly `6·n² + 2` for the smallest such `n`).
pub fn lung(side: Side, vertices: usize) -> Result<TriMesh, GenerateError> {
    lung_of(Shape::default(), side, vertices)
}

/// Generate the adult lung of `shape` and `side` with at least `vertices` vertices.
pub fn lung_of(shape: Shape, side: Side, vertices: usize) -> Result<TriMesh, GenerateError> {
    match shape {
        Shape::Anatomical => super::anatomy::lung(side, vertices),
        Shape::Teardrop => super::teardrop::lung(side, vertices),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::builder::spherified_cube;

    /// Every shape, both sides, many resolutions: closed, 2-manifold, outward, 6n² + 2 vertices.
    #[test]
    fn generated_lungs_are_closed_manifold_and_outward_at_many_resolutions() {
        for shape in Shape::ALL {
            for side in [Side::Left, Side::Right] {
                for n in [100, 1000, 5000, 20_000] {
                    let mesh = lung_of(shape, side, n).unwrap();
                    let topo = crate::mesh::check(&mesh)
                        .unwrap_or_else(|e| panic!("{shape:?} {side:?} {n}: {e}"));
                    assert_eq!(topo.euler, 2, "sphere-like surface");
                    assert!(mesh.positions.len() >= n);
                    assert_eq!(mesh.positions.len(), 6 * subdivision_for(n).pow(2) + 2);
                }
            }
        }
    }

    #[test]
    fn the_default_shape_is_anatomical_and_names_round_trip() {
        assert_eq!(Shape::default(), Shape::Anatomical);
        for shape in Shape::ALL {
            assert_eq!(shape.name().parse::<Shape>(), Ok(shape));
        }
        assert!("pear"
            .parse::<Shape>()
            .unwrap_err()
            .contains("anatomical or teardrop"));
        assert_eq!(
            lung(Side::Right, 1000).unwrap(),
            super::super::anatomy::lung(Side::Right, 1000).unwrap()
        );
        assert_eq!(
            lung_of(Shape::Teardrop, Side::Left, 1000).unwrap(),
            super::super::teardrop::lung(Side::Left, 1000).unwrap()
        );
    }

    #[test]
    fn the_subdivision_meets_the_request() {
        for n in [MIN_VERTICES, 101, 1000, 10_000, 400_000] {
            let s = subdivision_for(n);
            assert!(
                6 * s * s + 2 >= n && 6 * (s - 1) * (s - 1) + 2 < n.max(27),
                "{n}: {s}"
            );
        }
    }

    #[test]
    fn the_spherified_cube_is_a_closed_outward_unit_sphere() {
        let (points, triangles) = spherified_cube(7);
        assert_eq!(points.len(), 6 * 49 + 2);
        assert_eq!(triangles.len(), 12 * 49);
        assert!(points.iter().all(|p| (p.length() - 1.0).abs() < 1e-12));
        let v = super::super::enclosed_volume_with(&triangles, |i| points[i as usize].into());
        // Inscribed polyhedron of the unit ball: positive, a little under 4π/3.
        assert!(v > 0.9 * 4.0 / 3.0 * std::f64::consts::PI && v < 4.0 / 3.0 * std::f64::consts::PI);
    }

    #[test]
    fn out_of_range_requests_are_refused_for_every_shape() {
        for shape in Shape::ALL {
            assert_eq!(
                lung_of(shape, Side::Left, 10),
                Err(GenerateError::VertexCount { requested: 10 })
            );
            assert!(lung_of(shape, Side::Right, MAX_VERTICES + 1).is_err());
        }
    }
}
