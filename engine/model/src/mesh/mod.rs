//! # mesh: lung surface meshes
//!
//! A [`TriMesh`] is a closed, 2-manifold, consistently wound triangle surface of one lung in the
//! patient (body) frame, millimetres: **+X patient left, +Y anterior, +Z superior (head)**. Triangles
//! wind counter-clockwise seen from outside, so the enclosed volume (divergence theorem,
//! [`TriMesh::enclosed_volume_mm3`]) is positive.
//!
//! **Handedness (issue 19).** Physically this frame is *left-handed*: patient-left × anterior points
//! inferior, not superior (in RAS terms it is diag(−1, 1, 1), determinant −1). The numbers are
//! consistent with each other (imported LPS/RAS data are converted axis by axis, by
//! [`crate::frame`]); the room, the tracker and the renderer are right-handed, so every crossing from
//! this frame to theirs goes through the one reflection [`crate::frame::BODY_TO_RAS`]
//! ([`crate::frame::body_to_room`], [`crate::orientation::gravity_in_body`], `lungdyn register`):
//! from the front the right lung is on the viewer's left (`renderer::record` test
//! `the_patients_right_lung_is_on_the_viewers_left_from_the_front`, and the image test reading the
//! lobe colours' sides). The triangles' winding is counter-clockwise from outside *in this frame's
//! coordinates*; in the room it is clockwise (the renderer's front face follows the determinant).
//!
//! [`generate`] builds the built-in default lungs procedurally at any resolution ([`anatomy`], the
//! default, or the earlier [`teardrop`]); [`check`] verifies
//! the topology every later stage (deformation operator, kernel baking) relies on; [`io`] writes
//! OBJ/PLY atomically. Importing patient meshes (OBJ/PLY/STL, welding, repairs) is bake-time work:
//! `lung_bake::import`.

pub mod anatomy;
pub mod builder;
pub mod generate;
pub mod io;
pub mod lobes;
pub mod teardrop;

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::Side;

use thiserror::Error;

/// A triangle surface mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct TriMesh {
    /// Vertex positions, mm.
    pub positions: Vec<[f32; 3]>,
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

/// Axis-aligned bounding box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    /// Minimum corner.
    pub min: [f32; 3],
    /// Maximum corner.
    pub max: [f32; 3],
}

impl Aabb {
    /// Bounding box of `points` (a zero box for none).
    pub fn of(points: &[[f32; 3]]) -> Aabb {
        let mut min = [f32::INFINITY; 3];
        let mut max = [f32::NEG_INFINITY; 3];
        for p in points {
            for a in 0..3 {
                min[a] = min[a].min(p[a]);
                max[a] = max[a].max(p[a]);
            }
        }
        if points.is_empty() {
            return Aabb {
                min: [0.0; 3],
                max: [0.0; 3],
            };
        }
        Aabb { min, max }
    }

    /// Extent along each axis.
    pub fn size(&self) -> [f32; 3] {
        [
            self.max[0] - self.min[0],
            self.max[1] - self.min[1],
            self.max[2] - self.min[2],
        ]
    }
}

impl TriMesh {
    /// Bounding box of the vertices (a zero box for an empty mesh).
    pub fn aabb(&self) -> Aabb {
        Aabb::of(&self.positions)
    }

    /// Enclosed volume in mm³ by the divergence theorem (sum of signed tetrahedra), in f64.
    pub fn enclosed_volume_mm3(&self) -> f64 {
        enclosed_volume_with(&self.triangles, |i| {
            let p = self.positions[i as usize];
            [p[0] as f64, p[1] as f64, p[2] as f64]
        })
    }

    /// Enclosed volume in ml (cm³).
    pub fn enclosed_volume_ml(&self) -> f64 {
        self.enclosed_volume_mm3() / 1000.0
    }

    /// Surface area in mm².
    pub fn area_mm2(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] =
                    t.map(|i| glam::DVec3::from(self.positions[i as usize].map(|v| v as f64)));
                0.5 * (b - a).cross(c - a).length()
            })
            .sum()
    }
}

/// Signed enclosed volume of a closed triangle surface whose vertex `i` is at `pos(i)`.
pub fn enclosed_volume_with(triangles: &[[u32; 3]], pos: impl Fn(u32) -> [f64; 3]) -> f64 {
    let mut six_v = 0.0;
    for t in triangles {
        let [a, b, c] = t.map(|i| glam::DVec3::from(pos(i)));
        six_v += a.dot(b.cross(c));
    }
    six_v / 6.0
}

/// Topology report of [`check`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topology {
    /// Vertex count.
    pub vertices: usize,
    /// Edge count.
    pub edges: usize,
    /// Triangle count.
    pub triangles: usize,
    /// Euler characteristic V − E + F (2 for a sphere-like closed surface).
    pub euler: i64,
}

/// Verify that `mesh` is a closed, 2-manifold, consistently wound surface with finite coordinates,
/// no degenerate triangles, no unused vertices and positive enclosed volume.
pub fn check(mesh: &TriMesh) -> Result<Topology, MeshError> {
    if mesh.triangles.is_empty() {
        return Err(MeshError::Empty);
    }
    if let Some(i) = mesh
        .positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(MeshError::NonFinite { vertex: i });
    }
    let n = mesh.positions.len() as u32;
    let mut used = vec![false; mesh.positions.len()];
    // Directed edges (a, b) packed as `a << 32 | b`, sorted: a closed, consistently wound
    // 2-manifold has every directed edge exactly once and its reverse exactly once. A sorted list
    // rather than a hash map: the check runs on every mesh made from a mask (several per lung at
    // 100k vertices), where hashing cost more than the rest of the check.
    let mut directed: Vec<u64> = Vec::with_capacity(mesh.triangles.len() * 3);
    for (ti, t) in mesh.triangles.iter().enumerate() {
        if t.iter().any(|&i| i >= n) {
            return Err(MeshError::IndexOutOfRange { triangle: ti });
        }
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            return Err(MeshError::Degenerate { triangle: ti });
        }
        for k in 0..3 {
            used[t[k] as usize] = true;
            directed.push((t[k] as u64) << 32 | t[(k + 1) % 3] as u64);
        }
    }
    directed.sort_unstable();
    // (edge, count) runs.
    let mut runs: Vec<(u64, u32)> = Vec::with_capacity(directed.len());
    for &e in &directed {
        match runs.last_mut() {
            Some((last, c)) if *last == e => *c += 1,
            _ => runs.push((e, 1)),
        }
    }
    let count_of = |e: u64| {
        runs.binary_search_by_key(&e, |&(k, _)| k)
            .ok()
            .map(|i| runs[i].1)
    };
    let mut open = 0u64;
    let mut inconsistent = 0u64;
    let mut non_manifold = 0u64;
    for &(e, count) in &runs {
        if count > 1 {
            non_manifold += 1;
        }
        let reverse = (e & 0xFFFF_FFFF) << 32 | e >> 32;
        match count_of(reverse) {
            None => open += 1,
            Some(back) if back != count => inconsistent += 1,
            _ => {}
        }
    }
    if non_manifold > 0 {
        return Err(MeshError::NotManifoldOrInconsistent {
            edges: non_manifold,
        });
    }
    if open > 0 {
        return Err(MeshError::NotClosed { open_edges: open });
    }
    if inconsistent > 0 {
        return Err(MeshError::NotManifoldOrInconsistent {
            edges: inconsistent,
        });
    }
    if let Some(i) = used.iter().position(|u| !u) {
        return Err(MeshError::UnusedVertex { vertex: i });
    }
    for (ti, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|i| glam::DVec3::from(mesh.positions[i as usize].map(|v| v as f64)));
        if (b - a).cross(c - a).length_squared() == 0.0 {
            return Err(MeshError::ZeroArea { triangle: ti });
        }
    }
    let volume = mesh.enclosed_volume_mm3();
    if volume <= 0.0 {
        return Err(MeshError::InsideOut { volume_mm3: volume });
    }
    let edges = runs.len() / 2;
    Ok(Topology {
        vertices: mesh.positions.len(),
        edges,
        triangles: mesh.triangles.len(),
        euler: mesh.positions.len() as i64 - edges as i64 + mesh.triangles.len() as i64,
    })
}

/// What is wrong with a mesh.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum MeshError {
    /// No triangles.
    #[error("the mesh has no triangles")]
    Empty,
    /// A coordinate is NaN or infinite.
    #[error("vertex {vertex} has a NaN or infinite coordinate")]
    NonFinite {
        /// Vertex index.
        vertex: usize,
    },
    /// A triangle references a vertex that does not exist.
    #[error("triangle {triangle} references a vertex index beyond the vertex list")]
    IndexOutOfRange {
        /// Triangle index.
        triangle: usize,
    },
    /// A triangle repeats a vertex.
    #[error("triangle {triangle} is degenerate (repeats a vertex)")]
    Degenerate {
        /// Triangle index.
        triangle: usize,
    },
    /// A triangle has zero area.
    #[error("triangle {triangle} has zero area")]
    ZeroArea {
        /// Triangle index.
        triangle: usize,
    },
    /// The surface has holes.
    #[error("the surface is not closed: {open_edges} open boundary edges")]
    NotClosed {
        /// Number of boundary edges.
        open_edges: u64,
    },
    /// Edges shared by more than two triangles, or neighbours wound in opposite directions.
    #[error("{edges} edges are non-manifold or have inconsistent winding")]
    NotManifoldOrInconsistent {
        /// Number of bad edges.
        edges: u64,
    },
    /// A vertex no triangle uses.
    #[error("vertex {vertex} is not used by any triangle")]
    UnusedVertex {
        /// Vertex index.
        vertex: usize,
    },
    /// Triangles wind clockwise seen from outside (negative volume).
    #[error("the surface is wound inside out (enclosed volume {volume_mm3} mm^3)")]
    InsideOut {
        /// The signed volume found.
        volume_mm3: f64,
    },
}
