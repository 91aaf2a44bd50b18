//! # tri_intersect: exact triangle–triangle intersection for meshes with f32 coordinates
//!
//! [`crate::surface_checks::self_intersections`] decides, per candidate pair of a mesh's triangles,
//! whether the two *closed* triangles share a point other than the mesh vertices they have in
//! common. Every decision here is made from the **signs of exact predicates** — Shewchuk's adaptive
//! `orient3d` and `orient2d` (the `robust` crate) — on the mesh's coordinates, with no tolerance:
//!
//! * A mesh stores f32 coordinates; each converts to f64 exactly, and Shewchuk's predicates return
//!   the exact sign of their determinant for any f64 input whose products neither overflow nor
//!   underflow. Products of three differences of f32 values lie between ≈ 10⁻¹³⁵ and ≈ 10¹¹⁵, well
//!   inside f64's range, so every sign below is exact for every finite mesh.
//! * The test this replaced (Möller 1997 in floating point, corner distances within 10⁻⁶ of the
//!   bounding-box diagonal snapped onto the other plane) refused the generator's 300k- and
//!   400k-vertex lungs: where neighbouring-but-one triangles of a smooth surface are nearly coplanar
//!   (angle ≈ 10⁻³ rad), a corner 0.1 µm off the other plane was snapped *onto* it, which moved it
//!   onto the planes' common line — ≈ 0.3 mm away in the plane — and the intervals on that line
//!   overlapped. MeshLab finds 0 intersecting faces in those files; so does this test.
//!
//! ## The decision, case by case
//!
//! Two closed triangles `p`, `q` (each with non-collinear corners):
//!
//! * **No shared vertex.** They meet iff an edge of one meets the other triangle. (If they meet and
//!   are not coplanar, their intersection is a segment on the planes' common line whose end points
//!   lie on the boundary of `p` or of `q`; if coplanar, either edges cross or one holds a corner of
//!   the other.) A plane-side rejection (all corners of one strictly on one side of the other's
//!   plane) runs first.
//! * **One shared vertex `v`**, `p = (v, a, b)`, `q = (v, c, d)`: they meet other than at `v` iff
//!   segment `ab` meets `q` or segment `cd` meets `p`. (Not coplanar: each meets the common line
//!   in a segment from `v` to a point of its opposite edge; the two overlap beyond `v` iff the
//!   shorter one's end, on that opposite edge, lies in the other triangle. Coplanar: their angular
//!   sectors at `v` overlap, and then an edge from `v` of one enters the other, which holds its
//!   far end or is crossed by the other's opposite edge.)
//! * **A shared edge `uw`**, apexes `a` (of `p`) and `b` (of `q`): they meet beyond the edge iff
//!   the four points are coplanar and `a`, `b` lie strictly on the same side of `uw` (folded flat
//!   onto each other). Not coplanar, two triangles through one edge meet only in that edge.
//! * **Three shared vertices**: the same face twice, always reported.
//!
//! *Closed segment `ab` against closed triangle `q`*: if `a`, `b` are strictly on one side of
//! `q`'s plane, no. If both lie on the plane, the question is asked in 2D (below). Otherwise the
//! line `ab` crosses the plane at one point of the segment, which is in `q` iff the three
//! orientations `orient3d(a, b, qᵢ, qᵢ₊₁)` are not of mixed strict sign.
//!
//! *Coplanar questions* are answered in the projection that drops the coordinate axis for which
//! the reference triangle's projected orientation is non-zero (exact: dropping a coordinate is
//! exact, and such an axis exists for every non-collinear triangle, the projection is then one to
//! one on its plane).
//!
//! Touching counts as meeting (closed triangles): two sheets of a surface that touch in one point
//! have lost the "inside is a region" property just as crossing sheets have.

use robust::{orient2d, orient3d, Coord, Coord3D};

/// A point in f64 (exactly the f32 it was read from, for a mesh).
pub type P = [f64; 3];

/// A mesh vertex as an exact f64 point.
pub fn point(v: [f32; 3]) -> P {
    [v[0] as f64, v[1] as f64, v[2] as f64]
}

fn c3(p: P) -> Coord3D<f64> {
    Coord3D {
        x: p[0],
        y: p[1],
        z: p[2],
    }
}

/// Exact sign (−1, 0, 1) of the orientation of `d` against the plane through `a`, `b`, `c`.
fn o3(a: P, b: P, c: P, d: P) -> i8 {
    sign(orient3d(c3(a), c3(b), c3(c), c3(d)))
}

fn sign(x: f64) -> i8 {
    if x > 0.0 {
        1
    } else if x < 0.0 {
        -1
    } else {
        0
    }
}

/// `p` without coordinate `axis`.
fn drop_axis(p: P, axis: usize) -> Coord<f64> {
    match axis {
        0 => Coord { x: p[1], y: p[2] },
        1 => Coord { x: p[2], y: p[0] },
        _ => Coord { x: p[0], y: p[1] },
    }
}

/// Exact sign of the 2D orientation of `a`, `b`, `c` projected along `axis`.
fn o2(a: P, b: P, c: P, axis: usize) -> i8 {
    sign(orient2d(
        drop_axis(a, axis),
        drop_axis(b, axis),
        drop_axis(c, axis),
    ))
}

/// A coordinate axis along which triangle `t` projects to a non-degenerate triangle, or `None`
/// when its corners are exactly collinear (or coincide).
pub fn projection_axis(t: &[P; 3]) -> Option<usize> {
    (0..3).find(|&k| o2(t[0], t[1], t[2], k) != 0)
}

/// Mixed strict signs among `s`.
fn mixed(s: &[i8]) -> bool {
    s.iter().any(|&x| x > 0) && s.iter().any(|&x| x < 0)
}

/// `x`, collinear with `a` and `b` (in projection `axis`), lies on the closed segment `ab`.
fn within(a: P, b: P, x: P, axis: usize) -> bool {
    let (a, b, x) = (drop_axis(a, axis), drop_axis(b, axis), drop_axis(x, axis));
    a.x.min(b.x) <= x.x && x.x <= a.x.max(b.x) && a.y.min(b.y) <= x.y && x.y <= a.y.max(b.y)
}

/// Closed segments `ab` and `cd`, all four in one plane, meet (projection `axis`, one to one on
/// that plane).
fn segments_meet_2d(a: P, b: P, c: P, d: P, axis: usize) -> bool {
    let s1 = o2(c, d, a, axis);
    let s2 = o2(c, d, b, axis);
    let s3 = o2(a, b, c, axis);
    let s4 = o2(a, b, d, axis);
    if s1 * s2 < 0 && s3 * s4 < 0 {
        return true;
    }
    (s1 == 0 && within(c, d, a, axis))
        || (s2 == 0 && within(c, d, b, axis))
        || (s3 == 0 && within(a, b, c, axis))
        || (s4 == 0 && within(a, b, d, axis))
}

/// `x`, in the plane of the non-degenerate triangle `t`, lies in closed `t` (projection `axis`).
fn point_in_triangle_2d(x: P, t: &[P; 3], axis: usize) -> bool {
    !mixed(&[
        o2(t[0], t[1], x, axis),
        o2(t[1], t[2], x, axis),
        o2(t[2], t[0], x, axis),
    ])
}

/// Closed segment `ab` meets the closed, non-degenerate triangle `q` (exact).
pub fn segment_meets_triangle(a: P, b: P, q: &[P; 3]) -> bool {
    let sa = o3(q[0], q[1], q[2], a);
    let sb = o3(q[0], q[1], q[2], b);
    if sa * sb > 0 {
        return false;
    }
    if sa == 0 && sb == 0 {
        let Some(axis) = projection_axis(q) else {
            return false;
        };
        return point_in_triangle_2d(a, q, axis)
            || point_in_triangle_2d(b, q, axis)
            || (0..3).any(|k| segments_meet_2d(a, b, q[k], q[(k + 1) % 3], axis));
    }
    // The segment reaches the plane at exactly one point; is it inside q?
    !mixed(&[
        o3(a, b, q[0], q[1]),
        o3(a, b, q[1], q[2]),
        o3(a, b, q[2], q[0]),
    ])
}

/// All corners of `t` strictly on one side of the plane of `q`.
fn one_side_of(t: &[P; 3], q: &[P; 3]) -> bool {
    let s = t.map(|x| o3(q[0], q[1], q[2], x));
    (s[0] > 0 && s[1] > 0 && s[2] > 0) || (s[0] < 0 && s[1] < 0 && s[2] < 0)
}

/// Closed, non-degenerate triangles `p` and `q` meet (exact; no shared vertices assumed, though a
/// shared corner simply counts as meeting).
pub fn triangles_meet(p: &[P; 3], q: &[P; 3]) -> bool {
    if one_side_of(p, q) || one_side_of(q, p) {
        return false;
    }
    (0..3).any(|k| segment_meets_triangle(p[k], p[(k + 1) % 3], q))
        || (0..3).any(|k| segment_meets_triangle(q[k], q[(k + 1) % 3], p))
}

/// Triangles with the common edge `u`–`w` and apexes `a`, `b` overlap beyond that edge: coplanar,
/// apexes strictly on the same side of the edge.
pub fn folded_onto_each_other(u: P, w: P, a: P, b: P) -> bool {
    if o3(u, w, a, b) != 0 {
        return false;
    }
    let Some(axis) = projection_axis(&[u, w, a]) else {
        return false;
    };
    o2(u, w, a, axis) * o2(u, w, b, axis) > 0
}

/// Triangles `ti` (corners `p`) and `tj` (corners `q`) of one mesh, both non-degenerate, meet
/// other than in the vertices they share (see the module doc).
pub fn pair_intersects(ti: &[u32; 3], p: &[P; 3], tj: &[u32; 3], q: &[P; 3]) -> bool {
    let mut shared = 0usize;
    let mut sp = [0usize; 3];
    let mut sq = [0usize; 3];
    for (a, va) in ti.iter().enumerate() {
        for (b, vb) in tj.iter().enumerate() {
            if va == vb {
                if shared < 3 {
                    sp[shared] = a;
                    sq[shared] = b;
                }
                shared += 1;
            }
        }
    }
    match shared {
        0 => triangles_meet(p, q),
        1 => {
            let (a, b) = (sp[0], sq[0]);
            segment_meets_triangle(p[(a + 1) % 3], p[(a + 2) % 3], q)
                || segment_meets_triangle(q[(b + 1) % 3], q[(b + 2) % 3], p)
        }
        2 => folded_onto_each_other(
            p[sp[0]],
            p[sp[1]],
            p[3 - sp[0] - sp[1]],
            q[3 - sq[0] - sq[1]],
        ),
        _ => true, // the same three corners: coincident triangles
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const BASE: [P; 3] = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]];

    #[test]
    fn every_case_of_two_triangles() {
        // Piercing the interior.
        assert!(triangles_meet(
            &BASE,
            &[[2.0, 2.0, -1.0], [2.0, 2.0, 1.0], [3.0, 3.0, 1.0]]
        ));
        // Above the plane; crossing the plane beside the triangle.
        assert!(!triangles_meet(
            &BASE,
            &[[2.0, 2.0, 1.0], [3.0, 2.0, 1.0], [2.0, 3.0, 2.0]]
        ));
        assert!(!triangles_meet(
            &BASE,
            &[[20.0, 20.0, -1.0], [20.0, 20.0, 1.0], [21.0, 21.0, 1.0]]
        ));
        // A corner resting on the interior; a corner resting exactly on an edge.
        assert!(triangles_meet(
            &BASE,
            &[[2.0, 2.0, 0.0], [3.0, 2.0, 1.0], [2.0, 3.0, 1.0]]
        ));
        assert!(triangles_meet(
            &BASE,
            &[[5.0, 5.0, 0.0], [6.0, 5.0, 1.0], [5.0, 6.0, 1.0]]
        ));
        // The same, one f32 step outside the hypotenuse x + y = 10: apart.
        let out = 5.0f32.next_up() as f64;
        assert!(!triangles_meet(
            &BASE,
            &[[out, 5.0, 0.0], [6.0, 5.0, 1.0], [5.0, 6.0, 1.0]]
        ));
        // Coplanar: overlapping, nested (both ways), apart, touching corner to edge.
        let overlap = [[5.0, -1.0, 0.0], [15.0, -1.0, 0.0], [5.0, 9.0, 0.0]];
        assert!(triangles_meet(&BASE, &overlap));
        let nested = [[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [1.0, 2.0, 0.0]];
        assert!(triangles_meet(&BASE, &nested) && triangles_meet(&nested, &BASE));
        let apart = [[20.0, 0.0, 0.0], [30.0, 0.0, 0.0], [20.0, 10.0, 0.0]];
        assert!(!triangles_meet(&BASE, &apart));
        let touching = [[5.0, 5.0, 0.0], [15.0, 5.0, 0.0], [15.0, 15.0, 0.0]];
        assert!(triangles_meet(&BASE, &touching));
        // Edge through edge.
        assert!(triangles_meet(
            &BASE,
            &[[5.0, -5.0, 0.0], [5.0, 5.0, 0.0], [5.0, 0.0, 5.0]]
        ));
        // Nearly coplanar, side by side 1 mm apart, one 10⁻⁷ mm off the plane: apart (the case
        // the tolerance-snapping test called a crossing).
        assert!(!triangles_meet(
            &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            &[[2.0, 0.0, 1e-7], [3.0, 0.0, 0.0], [2.0, 1.0, 0.0]]
        ));
    }

    #[test]
    fn segments_against_a_triangle() {
        assert!(segment_meets_triangle(
            [1.0, 1.0, -1.0],
            [1.0, 1.0, 1.0],
            &BASE
        ));
        assert!(!segment_meets_triangle(
            [9.0, 9.0, -1.0],
            [9.0, 9.0, 1.0],
            &BASE
        ));
        // In the plane: entering, apart, along an edge, a single point inside.
        assert!(segment_meets_triangle(
            [-1.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            &BASE
        ));
        assert!(!segment_meets_triangle(
            [-3.0, 1.0, 0.0],
            [-1.0, 1.0, 0.0],
            &BASE
        ));
        assert!(segment_meets_triangle(
            [-1.0, 0.0, 0.0],
            [20.0, 0.0, 0.0],
            &BASE
        ));
        assert!(segment_meets_triangle(
            [1.0, 1.0, 0.0],
            [1.0, 1.0, 0.0],
            &BASE
        ));
        // Ending exactly on the plane inside / outside.
        assert!(segment_meets_triangle(
            [1.0, 1.0, 0.0],
            [1.0, 1.0, 5.0],
            &BASE
        ));
        assert!(!segment_meets_triangle(
            [11.0, 1.0, 0.0],
            [1.0, 1.0, 5.0],
            &BASE
        ));
        // Through a corner.
        assert!(segment_meets_triangle(
            [10.0, 0.0, -1.0],
            [10.0, 0.0, 1.0],
            &BASE
        ));
    }

    #[test]
    fn shared_vertices_and_edges() {
        let (i, j) = ([0u32, 1, 2], [0u32, 2, 3]);
        // Shared edge 0–2: open (apexes on opposite sides) versus folded flat.
        let open = [BASE[0], BASE[2], [-10.0, 0.0, 0.0]];
        assert!(!pair_intersects(&i, &BASE, &j, &open));
        let folded = [BASE[0], BASE[2], [5.0, 1.0, 0.0]];
        assert!(pair_intersects(&i, &BASE, &j, &folded));
        // Hinged out of the plane: only the edge in common.
        let hinged = [BASE[0], BASE[2], [5.0, 1.0, 1e-30]];
        assert!(!pair_intersects(&i, &BASE, &j, &hinged));
        // One shared vertex (0): fanned apart, or the second swung through the first.
        let (j1, q_apart) = (
            [0u32, 4, 5],
            [BASE[0], [-1.0, -1.0, 0.0], [-2.0, -0.5, 0.0]],
        );
        assert!(!pair_intersects(&i, &BASE, &j1, &q_apart));
        let q_through = [BASE[0], [5.0, 1.0, -1.0], [5.0, 1.0, 1.0]];
        assert!(pair_intersects(&i, &BASE, &j1, &q_through));
        // Coplanar, one shared vertex, sectors overlapping without any corner inside the other.
        let q_sector = [BASE[0], [20.0, 1.0, 0.0], [1.0, 20.0, 0.0]];
        assert!(pair_intersects(&i, &BASE, &j1, &q_sector));
        // Three shared: the same face twice.
        assert!(pair_intersects(&i, &BASE, &[2, 0, 1], &BASE));
    }

    #[test]
    fn collinear_triangles_have_no_projection() {
        assert_eq!(
            projection_axis(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]),
            None
        );
        assert_eq!(projection_axis(&[BASE[0], BASE[0], BASE[1]]), None);
        assert_eq!(projection_axis(&BASE), Some(2));
    }

    fn coord() -> impl Strategy<Value = f64> {
        // Small integers make exact coincidences (shared planes, edges, corners) frequent.
        (-4i32..=4).prop_map(|v| v as f64)
    }

    fn tri() -> impl Strategy<Value = [P; 3]> {
        proptest::array::uniform3(proptest::array::uniform3(coord()))
            .prop_filter("non-degenerate", |t| projection_axis(t).is_some())
    }

    proptest! {
        /// Symmetric, invariant under the corners' order and under a translation by a power of
        /// two (exact), and consistent with a sampled point of each triangle: a barycentric
        /// point of `p` lying in `q` (exactly on its plane, tested in 2D) means they meet.
        #[test]
        fn the_test_is_symmetric_and_order_free(p in tri(), q in tri(), shift in -3i32..3) {
            let m = triangles_meet(&p, &q);
            prop_assert_eq!(m, triangles_meet(&q, &p));
            prop_assert_eq!(m, triangles_meet(&[p[1], p[2], p[0]], &[q[2], q[1], q[0]]));
            let s = 2f64.powi(shift);
            let mv = |t: &[P; 3]| t.map(|x| [x[0] + s, x[1] - s, x[2] + 2.0 * s]);
            prop_assert_eq!(m, triangles_meet(&mv(&p), &mv(&q)));
            for x in [p[0], p[1], p[2]] {
                if o3(q[0], q[1], q[2], x) == 0 {
                    let axis = projection_axis(&q).unwrap();
                    if point_in_triangle_2d(x, &q, axis) {
                        prop_assert!(m);
                    }
                }
            }
        }
    }
}
