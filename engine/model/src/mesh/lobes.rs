//! # lobes: the lobes of a lung as per-vertex data
//!
//! Each vertex of a lung surface gets a lobe code (`u8`, [`Lobe`]): 0 unknown, 1 right upper,
//! 2 right middle, 3 right lower, 4 left upper (with the lingula), 5 left lower. The lobes are cut
//! by the fissures, taken as planes in the **normalised lung coordinates** the tumour already uses
//! (`disease::tumour::Tumour::centre_mm`): `x̂` mediastinum → lateral, `ŷ` posterior → anterior,
//! `ẑ` apex → base, each 0..1 over the lung's bounding box. The planes follow the surface anatomy
//! of the fissures (Moore, Dalley & Agur, *Clinically Oriented Anatomy*, 7th ed., ch. 1, "Surface
//! anatomy of the pleurae and lungs"; Standring (ed.), *Gray's Anatomy*, 41st ed., ch. 54):
//!
//! * **Oblique fissure** (both lungs): from the posterior surface level with the T2–T3 spinous
//!   processes (about the fourth rib behind: ẑ ≈ 0.30 of the apex-to-recess height, a little higher
//!   on the left, 0.28) down and forwards to the inferior border at the 6th costal cartilage
//!   (ẑ ≈ 0.86 at the anterior border, just below the anterior end of the inferior border, so the
//!   front of the diaphragmatic surface belongs to the upper or middle lobe). The plane is
//!   `ẑ = ẑ_p + (ẑ_a − ẑ_p)·ŷ`; below and behind it lies the lower lobe.
//! * **Horizontal fissure** (right only): along the 4th rib and costal cartilage from the sternum
//!   back to the oblique fissure, which it meets near the midaxillary line: `ẑ = 0.56`. Between it
//!   and the oblique fissure lies the middle lobe.
//!
//! A surface lobe is the lobe of its vertex's position; the lobes' shares of area that this gives
//! on the anatomical lungs (`lungdyn mesh check --json`, `"lobes"`) are in [`super::anatomy`]'s doc.
//! The planes apply to any lung surface by its bounding box (an imported one, the default
//! generator's), approximately where its shape differs from the anatomy.

use serde::Serialize;

use super::{Side, TriMesh};

/// A lobe, as its `u8` code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[repr(u8)]
pub enum Lobe {
    /// Not classified (no side known).
    Unknown = 0,
    /// Right upper lobe.
    RightUpper = 1,
    /// Right middle lobe.
    RightMiddle = 2,
    /// Right lower lobe.
    RightLower = 3,
    /// Left upper lobe, lingula included.
    LeftUpper = 4,
    /// Left lower lobe.
    LeftLower = 5,
}

/// Every named lobe, in code order.
pub const ALL: [Lobe; 5] = [
    Lobe::RightUpper,
    Lobe::RightMiddle,
    Lobe::RightLower,
    Lobe::LeftUpper,
    Lobe::LeftLower,
];

impl Lobe {
    /// The `u8` code.
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The lobe of a code (`None` for codes above 5).
    pub fn from_code(code: u8) -> Option<Lobe> {
        match code {
            0 => Some(Lobe::Unknown),
            c => ALL.get(c as usize - 1).copied(),
        }
    }

    /// Name as a scene writes it ("right lower").
    pub fn name(self) -> &'static str {
        match self {
            Lobe::Unknown => "unknown",
            Lobe::RightUpper => "right upper",
            Lobe::RightMiddle => "right middle",
            Lobe::RightLower => "right lower",
            Lobe::LeftUpper => "left upper",
            Lobe::LeftLower => "left lower",
        }
    }

    /// The lung it belongs to (`None` for [`Lobe::Unknown`]).
    pub fn side(self) -> Option<Side> {
        match self {
            Lobe::Unknown => None,
            Lobe::RightUpper | Lobe::RightMiddle | Lobe::RightLower => Some(Side::Right),
            Lobe::LeftUpper | Lobe::LeftLower => Some(Side::Left),
        }
    }

    /// Display colour (sRGB) for exports: distinct hues per lobe.
    pub fn colour(self) -> [u8; 3] {
        match self {
            Lobe::Unknown => [160, 160, 160],
            Lobe::RightUpper => [228, 140, 140],
            Lobe::RightMiddle => [140, 205, 140],
            Lobe::RightLower => [135, 160, 230],
            Lobe::LeftUpper => [232, 195, 120],
            Lobe::LeftLower => [180, 140, 225],
        }
    }
}

impl std::fmt::Display for Lobe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Lobe {
    type Err = String;
    /// "right lower", "right-lower", "right_lower" or the abbreviation ("RLL"), any case.
    fn from_str(s: &str) -> Result<Self, String> {
        let key = s.trim().to_ascii_lowercase().replace(['-', '_'], " ");
        let found = ALL.iter().copied().find(|l| {
            let abbreviation: String = l.name().split(' ').map(|w| &w[..1]).collect();
            key == l.name() || key == format!("{abbreviation}l")
        });
        found.ok_or_else(|| {
            format!(
                "unknown lobe {s:?}: use one of {}",
                ALL.map(|l| format!("{:?}", l.name())).join(", ")
            )
        })
    }
}

/// Fissure planes of one lung in normalised coordinates (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fissures {
    /// `ẑ` of the oblique fissure at the posterior surface (`ŷ = 0`).
    pub oblique_posterior: f64,
    /// `ẑ` of the oblique fissure at the anterior border (`ŷ = 1`).
    pub oblique_anterior: f64,
    /// `ẑ` of the horizontal fissure (right lung; `None` on the left).
    pub horizontal: Option<f64>,
}

impl Fissures {
    /// The adult fissures of `side` (module doc).
    pub fn adult(side: Side) -> Self {
        match side {
            Side::Right => Fissures {
                oblique_posterior: 0.30,
                oblique_anterior: 0.86,
                horizontal: Some(0.56),
            },
            Side::Left => Fissures {
                oblique_posterior: 0.28,
                oblique_anterior: 0.86,
                horizontal: None,
            },
        }
    }

    /// Signed distances in `ẑ` of normalised point `n = [x̂, ŷ, ẑ]` from the oblique fissure
    /// (positive: in the lower lobe) and the horizontal one (positive: below it; 0 without one).
    /// Each is affine in the point, so interpolated linearly across a triangle it is exact: its zero
    /// is where the plane cuts the triangle (the renderer draws fissures there).
    pub fn signed(&self, n: [f64; 3]) -> [f64; 2] {
        let [_, y, z] = n;
        let oblique = self.oblique_posterior + (self.oblique_anterior - self.oblique_posterior) * y;
        [z - oblique, self.horizontal.map_or(0.0, |h| z - h)]
    }

    /// The lobe of a point at normalised coordinates `n = [x̂, ŷ, ẑ]`.
    pub fn lobe_at(&self, side: Side, n: [f64; 3]) -> Lobe {
        let [oblique, horizontal] = self.signed(n);
        match (side, oblique > 0.0) {
            (Side::Right, true) => Lobe::RightLower,
            (Side::Left, true) => Lobe::LeftLower,
            (Side::Left, false) => Lobe::LeftUpper,
            (Side::Right, false) => match self.horizontal {
                Some(_) if horizontal > 0.0 => Lobe::RightMiddle,
                _ => Lobe::RightUpper,
            },
        }
    }
}

/// Normalised lung coordinates `[x̂, ŷ, ẑ]` of body-frame point `p` (mm) for a lung of `side` whose
/// bounding box is `bb` (the inverse of `Tumour::centre_mm`).
pub fn normalise(side: Side, bb: &super::Aabb, p: [f64; 3]) -> [f64; 3] {
    let (lo, hi) = (bb.min.map(|v| v as f64), bb.max.map(|v| v as f64));
    let frac = |v: f64, a: usize| {
        let span = hi[a] - lo[a];
        if span > 0.0 {
            (v - lo[a]) / span
        } else {
            0.5
        }
    };
    let x = frac(p[0], 0);
    [
        match side {
            Side::Left => x,
            Side::Right => 1.0 - x,
        },
        frac(p[1], 1),
        1.0 - frac(p[2], 2),
    ]
}

/// The lobe code of every vertex of `mesh`, a lung of `side`.
pub fn classify(side: Side, mesh: &TriMesh) -> Vec<u8> {
    let bb = mesh.aabb();
    let fissures = Fissures::adult(side);
    mesh.positions
        .iter()
        .map(|p| {
            fissures
                .lobe_at(side, normalise(side, &bb, p.map(|v| v as f64)))
                .code()
        })
        .collect()
}

/// Each of `positions`' signed distances from the fissure planes of `side` ([`Fissures::signed`]:
/// oblique, horizontal) over the positions' own box: the planes [`classify`] gives lobes by, which
/// the renderer colours each fragment by (`renderer::draw::lung_surface`) and `lungdyn export gltf`
/// cuts the lobes apart at.
pub fn fissure_distances(side: Side, positions: &[[f32; 3]]) -> Vec<[f64; 2]> {
    let bb = super::Aabb::of(positions);
    let fissures = Fissures::adult(side);
    positions
        .iter()
        .map(|p| fissures.signed(normalise(side, &bb, p.map(|v| v as f64))))
        .collect()
}

/// One lobe's share of a surface.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LobeSummary {
    /// Lobe name ("right lower").
    pub name: &'static str,
    /// Lobe code.
    pub code: u8,
    /// Vertices in it.
    pub vertices: usize,
    /// Surface area, mm² (each triangle's area shared equally among its corners' lobes).
    pub area_mm2: f64,
}

/// Vertices and area per lobe present in `lobes` (codes per vertex of `mesh`), in code order.
pub fn summarise(mesh: &TriMesh, lobes: &[u8]) -> Vec<LobeSummary> {
    let mut vertices = [0usize; 6];
    let mut area = [0f64; 6];
    for &c in lobes {
        vertices[(c as usize).min(5)] += 1;
    }
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| glam::DVec3::from(mesh.positions[i as usize].map(|v| v as f64)));
        let third = (b - a).cross(c - a).length() / 6.0;
        for &i in t {
            area[(lobes[i as usize] as usize).min(5)] += third;
        }
    }
    (0..6u8)
        .filter(|&c| vertices[c as usize] > 0)
        .map(|c| {
            let lobe = Lobe::from_code(c).unwrap_or(Lobe::Unknown);
            LobeSummary {
                name: lobe.name(),
                code: c,
                vertices: vertices[c as usize],
                area_mm2: area[c as usize],
            }
        })
        .collect()
}

/// A point well inside `lobe` of the built-in lung of `shape`, in normalised coordinates: the
/// interior grid point of that lobe nearest its interior centroid, so a scene can place a tumour
/// "in the right lower lobe" of the lungs it generates (`[lungs] shape`). The lobes of every shape
/// are the same fissure planes ([`Fissures`]) over its bounding box, but the shapes fill that box
/// differently (the anatomical base is a dome, the teardrop's a blunt flat end), so the point is
/// the shape's own. Deterministic (that shape's 2k-vertex lung and a fixed grid).
pub fn interior_point(shape: super::generate::Shape, lobe: Lobe) -> Option<[f64; 3]> {
    let side = lobe.side()?;
    let mesh = super::generate::lung_of(shape, side, 2_000).ok()?;
    let bb = mesh.aabb();
    let fissures = Fissures::adult(side);
    let (lo, hi) = (bb.min.map(|v| v as f64), bb.max.map(|v| v as f64));
    const N: usize = 24;
    let mut inside: Vec<[f64; 3]> = Vec::new();
    for i in 0..N {
        for j in 0..N {
            for k in 0..N {
                let f = |g: usize| (g as f64 + 0.5) / N as f64;
                let p = [0, 1, 2].map(|a| lo[a] + [f(i), f(j), f(k)][a] * (hi[a] - lo[a]));
                let n = normalise(side, &bb, p);
                if fissures.lobe_at(side, n) == lobe
                    && crate::disease::tumour::winding_number(&mesh, p) > 0.5
                {
                    inside.push(n);
                }
            }
        }
    }
    if inside.is_empty() {
        return None;
    }
    let mean = [0, 1, 2].map(|a| inside.iter().map(|n| n[a]).sum::<f64>() / inside.len() as f64);
    let d2 = |n: &[f64; 3]| (0..3).map(|a| (n[a] - mean[a]).powi(2)).sum::<f64>();
    inside.into_iter().min_by(|a, b| d2(a).total_cmp(&d2(b)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

    #[test]
    fn codes_names_and_abbreviations_round_trip() {
        for lobe in ALL {
            assert_eq!(Lobe::from_code(lobe.code()), Some(lobe));
            assert_eq!(lobe.name().parse::<Lobe>(), Ok(lobe));
        }
        assert_eq!("RLL".parse::<Lobe>(), Ok(Lobe::RightLower));
        assert_eq!("left-upper".parse::<Lobe>(), Ok(Lobe::LeftUpper));
        assert_eq!("rml".parse::<Lobe>(), Ok(Lobe::RightMiddle));
        assert!("left middle"
            .parse::<Lobe>()
            .unwrap_err()
            .contains("right lower"));
        assert_eq!(Lobe::from_code(0), Some(Lobe::Unknown));
        assert_eq!(Lobe::from_code(6), None);
        assert_eq!(Lobe::from_code(255), None);
    }

    #[test]
    fn generated_lungs_have_their_lobes_where_anatomy_puts_them() {
        for side in [Side::Right, Side::Left] {
            let mesh = crate::mesh::anatomy::lung(side, 10_000).unwrap();
            let lobes = classify(side, &mesh);
            let summary = summarise(&mesh, &lobes);
            let total: f64 = summary.iter().map(|s| s.area_mm2).sum();
            assert!((total - mesh.area_mm2()).abs() < 1e-6 * total);
            let expected: &[Lobe] = match side {
                Side::Right => &[Lobe::RightUpper, Lobe::RightMiddle, Lobe::RightLower],
                Side::Left => &[Lobe::LeftUpper, Lobe::LeftLower],
            };
            let names: Vec<&str> = summary.iter().map(|s| s.name).collect();
            assert_eq!(names, expected.iter().map(|l| l.name()).collect::<Vec<_>>());
            // Every lobe is a real share of the surface; the middle lobe is the smallest.
            for s in &summary {
                assert!(s.area_mm2 > 0.08 * total, "{side:?} {s:?}");
            }
            if side == Side::Right {
                assert!(summary[1].area_mm2 < summary[0].area_mm2.min(summary[2].area_mm2));
            }
            // The apex is upper lobe, the bottom of the posterior recess lower lobe.
            let top = (0..mesh.positions.len())
                .max_by(|&a, &b| mesh.positions[a][2].total_cmp(&mesh.positions[b][2]))
                .unwrap();
            let bottom = (0..mesh.positions.len())
                .min_by(|&a, &b| mesh.positions[a][2].total_cmp(&mesh.positions[b][2]))
                .unwrap();
            assert_eq!(Lobe::from_code(lobes[top]).unwrap(), expected[0]);
            assert_eq!(
                Lobe::from_code(lobes[bottom]).unwrap(),
                *expected.last().unwrap()
            );
        }
    }

    #[test]
    fn interior_points_lie_inside_their_lobe_of_each_shape() {
        for shape in generate::Shape::ALL {
            for lobe in ALL {
                let side = lobe.side().unwrap();
                let n = interior_point(shape, lobe).unwrap();
                assert_eq!(Fissures::adult(side).lobe_at(side, n), lobe);
                let mesh = generate::lung_of(shape, side, 5_000).unwrap();
                let t = crate::disease::tumour::Tumour::new(side, n, [5.0; 3]);
                let c = t.centre_mm(&mesh);
                assert!(
                    crate::disease::tumour::winding_number(&mesh, c) > 0.5,
                    "{shape:?} {lobe}"
                );
            }
            assert_eq!(interior_point(shape, Lobe::Unknown), None);
        }
    }

    #[test]
    fn normalise_inverts_the_tumour_centre() {
        for side in [Side::Right, Side::Left] {
            let mesh = generate::lung(side, 1_000).unwrap();
            let n = [0.25, 0.6, 0.7];
            let t = crate::disease::tumour::Tumour::new(side, n, [5.0; 3]);
            let back = normalise(side, &mesh.aabb(), t.centre_mm(&mesh));
            for a in 0..3 {
                assert!((back[a] - n[a]).abs() < 1e-9);
            }
        }
    }
}
