//! Displacement fields fitted to a patient's landmarks: what the direction model can be besides the
//! seed's power law (eq. 6.14–6.16).
//!
//! A field gives, for a point of one lung at the start phase (body frame, mm), its displacement to
//! the fitted phase (mm). Three kinds, all per lung:
//! * [`Field::Power`] — the seed's separable power law in normalised lung coordinates (eq. 6.14–6.16
//!   used point-wise, EQUATIONS §2.4);
//! * [`Field::Poly`] — a polynomial of total degree ≤ 5 per component in box coordinates `[-1, 1]³`;
//! * [`Field::Tps`] — an anisotropic polyharmonic (thin-plate) spline `δ(x) = Σ_j W_j φ(x, p_j) +
//!   Aᵀ[1, u, v, w]` with `φ(a, b) = −‖S(a − b)‖`, `S = diag(1, 1, s_z)`, in mm.
//!
//! Fitting (with cross-validated complexity) is bake-time work (`lung_bake::motion_models`); this
//! module only stores and evaluates, so a motion file can be loaded by a scene and used by a bake.
//!
//! **Where a field is evaluated.** Landmarks and a mesh of the same patient rarely share an origin
//! (image voxel indices vs scanner coordinates). A field is therefore evaluated at a mesh vertex
//! after mapping the mesh's bounding box onto the box of the landmarks the field was fitted on
//! ([`Field::displacement_in_box`]): the same normalised lung position, whatever the origin — the
//! way the seed's power law already works.

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::mesh::Side;

/// A fitted displacement field of one lung.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase", deny_unknown_fields)]
pub enum Field {
    /// The seed's power law: `c1..c6` as `lung_bake::motion_fit` fits them (mm at the fitted phase).
    Power {
        /// Which lung (sets the lateral sign).
        side: Side,
        /// Box of the fitted lung's start positions, mm.
        lo: [f64; 3],
        /// Box, upper corner.
        hi: [f64; 3],
        /// `c1..c6` (c7..c9 are not used by a field).
        c: [f64; 6],
    },
    /// A polynomial field in box coordinates.
    Poly {
        /// Box of the fitted lung's start positions, mm.
        lo: [f64; 3],
        /// Box, upper corner.
        hi: [f64; 3],
        /// Total degree (1..=5).
        degree: u8,
        /// One coefficient vector (mm) per monomial, in [`monomials`] order.
        coeffs: Vec<[f64; 3]>,
    },
    /// An anisotropic thin-plate spline in mm with an affine tail.
    Tps {
        /// Box of the fitted lung's start positions, mm (the affine tail's coordinates).
        lo: [f64; 3],
        /// Box, upper corner.
        hi: [f64; 3],
        /// Stretch of Z distances in the kernel.
        s_z: f64,
        /// Centres (the landmarks at the start phase), mm.
        centres: Vec<[f64; 3]>,
        /// Kernel weights, one vector per centre, mm.
        weights: Vec<[f64; 3]>,
        /// Affine tail: coefficient vectors of 1, u, v, w.
        affine: [[f64; 3]; 4],
    },
}

/// An applied-force field fitted to a patient's breath (lungdyn, beyond the seed): the force on each
/// vertex before the operator, a polynomial of total degree ≤ 5 in box coordinates `[-1, 1]³` of the
/// fitted lung — the seed's applied force (eq. 6.18's `c7·x̂ + c8·ŷ + c9·ẑ`, EQUATIONS §2.4) is the
/// degree-1 case. The operator turns it into the elastostatic force exactly as it turns the seed's
/// (`F = T·f`), so a patient's fit keeps the chapter-6 pipeline and only gives it the freedom a real
/// breath needs; local terms ([`ForceField::centres`]) may be added to the polynomial. Evaluated like [`Field`]: the mesh's box mapped onto the fitted box.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForceField {
    /// Box of the fitted lung (its exhale surface), mm.
    pub lo: [f64; 3],
    /// Box, upper corner.
    pub hi: [f64; 3],
    /// Total degree, 1..=5.
    pub degree: u8,
    /// One coefficient per monomial of [`monomials`]`(degree)`, in that order.
    pub coeffs: Vec<f64>,
    /// Local terms added to the polynomial (lungdyn, beyond the seed; none unless `fit-motion
    /// --force-centres` asked for them): `Σ_j w_j·ψ(‖x − c_j‖ / radius_mm)` with Wendland's
    /// compactly supported C² function [`wendland`], `x` the point in the fitted lung's frame (mm)
    /// and the centres on its exhale surface. Each reaches `radius_mm` and no further, so a
    /// centre's freedom stays in the part of the lung it was fitted on.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub centres: Vec<[f64; 3]>,
    /// One weight per centre.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub weights: Vec<f64>,
    /// Support radius of every local term, mm (0 without them).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub radius_mm: f64,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// The most local terms a force field may hold (`fit-motion --force-centres` takes 8 to 1000).
pub const MAX_LOCAL_TERMS: usize = 1000;

/// Wendland's C² function in 3-D, `ψ(r) = (1 − r)⁴(4r + 1)` for `r < 1`, 0 beyond: positive
/// definite, smooth, with compact support (Wendland 1995).
pub fn wendland(r: f64) -> f64 {
    if (0.0..1.0).contains(&r) {
        let a = 1.0 - r;
        a * a * a * a * (4.0 * r + 1.0)
    } else {
        0.0
    }
}

impl ForceField {
    /// The applied force at `p` of a lung whose box is (`lo`, `hi`).
    pub fn value_in_box(&self, p: DVec3, lo: DVec3, hi: DVec3) -> f64 {
        let (flo, fhi) = (DVec3::from(self.lo), DVec3::from(self.hi));
        let t = (p - lo) / (hi - lo);
        let x = flo + t * (fhi - flo);
        let u = box_coords(x, flo, fhi);
        let poly: f64 = monomials(self.degree)
            .iter()
            .zip(&self.coeffs)
            .map(|(e, c)| c * u.x.powi(e[0] as i32) * u.y.powi(e[1] as i32) * u.z.powi(e[2] as i32))
            .sum();
        if self.centres.is_empty() {
            return poly;
        }
        poly + self.local_value(x)
    }

    /// The local terms at `x` in the fitted lung's frame, mm.
    pub fn local_value(&self, x: DVec3) -> f64 {
        self.centres
            .iter()
            .zip(&self.weights)
            .map(|(c, w)| w * wendland((x - DVec3::from(*c)).length() / self.radius_mm))
            .sum()
    }

    /// Every number finite, one coefficient per monomial, the box non-degenerate.
    pub fn validate(&self) -> Result<(), &'static str> {
        let (lo, hi) = (DVec3::from(self.lo), DVec3::from(self.hi));
        if !(lo.is_finite() && hi.is_finite() && (hi - lo).min_element() > 1e-9) {
            return Err("the force field's box is not finite or has no extent");
        }
        if !(1..=5).contains(&self.degree) || self.coeffs.len() != monomials(self.degree).len() {
            return Err("a force field needs degree 1..=5 and one coefficient per monomial");
        }
        if !self.coeffs.iter().all(|c| c.is_finite()) {
            return Err("force field coefficients must be finite");
        }
        if self.centres.len() != self.weights.len() {
            return Err("a force field's local terms need one weight per centre");
        }
        if !self.centres.is_empty() {
            if !(self.radius_mm.is_finite() && self.radius_mm > 0.0) {
                return Err("a force field's local terms need a finite, positive radius_mm");
            }
            let mut finite = self.centres.iter().flatten().chain(&self.weights);
            if !finite.all(|v| v.is_finite()) {
                return Err("a force field's centres and weights must be finite");
            }
            if self.centres.len() > MAX_LOCAL_TERMS {
                return Err("a force field holds at most 1000 local terms (fit-motion's limit)");
            }
            if self.radius_mm < 1.0 {
                return Err("a force field's radius_mm is below 1 mm: a radius in metres?");
            }
            // On the fitted lung's surface: inside its box (a centre in another frame is not).
            let (lo, hi) = (lo - self.radius_mm, hi + self.radius_mm);
            let inside = |c: &[f64; 3]| (0..3).all(|k| c[k] >= lo[k] && c[k] <= hi[k]);
            if !self.centres.iter().all(inside) {
                return Err("a force field's centres lie outside its box: another frame or unit?");
            }
        }
        Ok(())
    }
}

/// The monomials `u^i v^j w^k` of total degree ≤ `degree` in graded order (1, u, v, w, u², uv, …):
/// a lower degree's basis is a prefix of a higher one's.
pub fn monomials(degree: u8) -> Vec<[u8; 3]> {
    let mut out = Vec::new();
    for t in 0..=degree {
        for i in (0..=t).rev() {
            for j in (0..=t - i).rev() {
                out.push([i, j, t - i - j]);
            }
        }
    }
    out
}

/// Evaluate every monomial of `exps` at box coordinates `u` into `out`.
pub fn monomial_values(u: DVec3, exps: &[[u8; 3]], out: &mut Vec<f64>) {
    out.clear();
    out.extend(
        exps.iter()
            .map(|e| u.x.powi(e[0] as i32) * u.y.powi(e[1] as i32) * u.z.powi(e[2] as i32)),
    );
}

/// Box coordinates `2(p − lo)/(hi − lo) − 1` (not clamped).
pub fn box_coords(p: DVec3, lo: DVec3, hi: DVec3) -> DVec3 {
    2.0 * (p - lo) / (hi - lo) - DVec3::ONE
}

/// The seed's normalised position (eq. 6.14–6.16 axes, clamped to [0, 1]): x̂ from the mediastinum
/// outwards, ŷ posterior → anterior, ẑ apex → base.
pub fn seed_coords(p: DVec3, lo: DVec3, hi: DVec3, side: Side) -> DVec3 {
    let t = ((p - lo) / (hi - lo)).clamp(DVec3::ZERO, DVec3::ONE);
    let x = match side {
        Side::Left => t.x,
        Side::Right => 1.0 - t.x,
    };
    DVec3::new(x, t.y, 1.0 - t.z)
}

/// The power law's displacement (mm) at seed coordinates `n`.
pub fn power_displacement(n: DVec3, c: &[f64], side: Side) -> DVec3 {
    DVec3::new(
        side.lateral_sign() as f64 * c[0] * n.x.powf(c[1]),
        c[2] * n.y.powf(c[3]),
        -c[4] * n.z.powf(c[5]),
    )
}

impl Field {
    /// The box of the landmarks the field was fitted on.
    pub fn fitted_box(&self) -> (DVec3, DVec3) {
        let (lo, hi) = match self {
            Field::Power { lo, hi, .. }
            | Field::Poly { lo, hi, .. }
            | Field::Tps { lo, hi, .. } => (lo, hi),
        };
        (DVec3::from(*lo), DVec3::from(*hi))
    }

    /// A short name ("power", "poly", "tps").
    pub fn name(&self) -> &'static str {
        match self {
            Field::Power { .. } => "power",
            Field::Poly { .. } => "poly",
            Field::Tps { .. } => "tps",
        }
    }

    /// Number of stored numbers (the model's size).
    pub fn parameters(&self) -> usize {
        match self {
            Field::Power { .. } => 6,
            Field::Poly { coeffs, .. } => 3 * coeffs.len(),
            Field::Tps { centres, .. } => 6 * centres.len() + 12,
        }
    }

    /// Displacement (mm) at `p`, in the frame and at the scale the field was fitted in.
    pub fn displacement(&self, p: DVec3) -> DVec3 {
        match self {
            Field::Power { side, lo, hi, c } => {
                power_displacement(seed_coords(p, (*lo).into(), (*hi).into(), *side), c, *side)
            }
            Field::Poly {
                lo,
                hi,
                degree,
                coeffs,
            } => {
                let u = box_coords(p, (*lo).into(), (*hi).into());
                monomials(*degree)
                    .iter()
                    .zip(coeffs)
                    .map(|(e, c)| {
                        DVec3::from(*c)
                            * (u.x.powi(e[0] as i32)
                                * u.y.powi(e[1] as i32)
                                * u.z.powi(e[2] as i32))
                    })
                    .sum()
            }
            Field::Tps {
                lo,
                hi,
                s_z,
                centres,
                weights,
                affine,
            } => {
                let s = DVec3::new(1.0, 1.0, *s_z);
                let mut d = DVec3::ZERO;
                for (c, w) in centres.iter().zip(weights) {
                    d += DVec3::from(*w) * -((p - DVec3::from(*c)) * s).length();
                }
                let u = box_coords(p, (*lo).into(), (*hi).into());
                d + DVec3::from(affine[0])
                    + DVec3::from(affine[1]) * u.x
                    + DVec3::from(affine[2]) * u.y
                    + DVec3::from(affine[3]) * u.z
            }
        }
    }

    /// Displacement at a point `p` of a surface whose box is `(lo, hi)`: `p` is first mapped onto the
    /// fitted landmarks' box (same normalised position), so meshes and landmarks need not share an
    /// origin or exact extent.
    pub fn displacement_in_box(&self, p: DVec3, lo: DVec3, hi: DVec3) -> DVec3 {
        let (flo, fhi) = self.fitted_box();
        let t = (p - lo) / (hi - lo);
        self.displacement(flo + t * (fhi - flo))
    }

    /// Every number finite, sizes consistent, the box non-degenerate: what a loaded file must be.
    pub fn validate(&self) -> Result<(), &'static str> {
        let (lo, hi) = self.fitted_box();
        if !(lo.is_finite() && hi.is_finite() && (hi - lo).min_element() > 1e-9) {
            return Err("the fitted box is not finite or has no extent");
        }
        let finite3 = |v: &[[f64; 3]]| v.iter().flatten().all(|x| x.is_finite());
        match self {
            Field::Power { c, .. } => {
                if !c.iter().all(|v| v.is_finite()) || c[1] < 0.0 || c[3] < 0.0 || c[5] < 0.0 {
                    return Err("power law constants must be finite with non-negative exponents");
                }
            }
            Field::Poly { degree, coeffs, .. } => {
                if !(1..=5).contains(degree) || coeffs.len() != monomials(*degree).len() {
                    return Err(
                        "a polynomial field needs degree 1..=5 and one coefficient per monomial",
                    );
                }
                if !finite3(coeffs) {
                    return Err("polynomial coefficients must be finite");
                }
            }
            Field::Tps {
                s_z,
                centres,
                weights,
                affine,
                ..
            } => {
                if !(s_z.is_finite() && *s_z > 0.0) {
                    return Err("s_z must be finite and positive");
                }
                if centres.is_empty() || centres.len() != weights.len() {
                    return Err("a spline needs as many weights as centres");
                }
                if !(finite3(centres) && finite3(weights) && finite3(affine)) {
                    return Err("spline centres, weights and tail must be finite");
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monomials_are_graded_and_nested() {
        assert_eq!(
            monomials(1),
            vec![[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
        );
        let counts: Vec<usize> = (1..=5).map(|d| monomials(d).len()).collect();
        assert_eq!(counts, vec![4, 10, 20, 35, 56]);
        assert_eq!(monomials(5)[..20], monomials(3)[..]);
    }

    #[test]
    fn an_affine_spline_tail_alone_is_an_affine_map_of_box_coordinates() {
        let f = Field::Tps {
            lo: [0.0; 3],
            hi: [2.0; 3],
            s_z: 2.0,
            centres: vec![[1.0; 3]],
            weights: vec![[0.0; 3]],
            affine: [
                [1.0, 0.0, 0.0],
                [0.0, 2.0, 0.0],
                [0.0, 0.0, 0.0],
                [0.0, 0.0, 3.0],
            ],
        };
        assert!(f.validate().is_ok());
        // p = (2, 0, 1): u = (1, −1, 0).
        assert_eq!(
            f.displacement(DVec3::new(2.0, 0.0, 1.0)),
            DVec3::new(1.0, 2.0, 0.0)
        );
        // A surface box twice as large maps onto the fitted box.
        let d = f.displacement_in_box(DVec3::new(4.0, 0.0, 2.0), DVec3::ZERO, DVec3::splat(4.0));
        assert_eq!(d, DVec3::new(1.0, 2.0, 0.0));
    }

    #[test]
    fn the_power_field_is_the_seed_law_used_point_wise() {
        let c = [2.0, 1.0, 0.0, 0.0, 10.0, 1.0];
        let f = Field::Power {
            side: Side::Left,
            lo: [0.0; 3],
            hi: [100.0; 3],
            c,
        };
        // Lateral edge of a left lung (x̂ = 1), at the base (ẑ = 1): 2 mm out, 10 mm down.
        let d = f.displacement(DVec3::new(100.0, 50.0, 0.0));
        assert_eq!(d, DVec3::new(2.0, 0.0, -10.0));
        assert!(Field::Power {
            side: Side::Left,
            lo: [0.0; 3],
            hi: [0.0, 1.0, 1.0],
            c
        }
        .validate()
        .is_err());
    }

    #[test]
    fn wendlands_function_is_one_at_its_centre_smooth_and_zero_past_its_reach() {
        assert_eq!(wendland(0.0), 1.0);
        assert_eq!(wendland(1.0), 0.0);
        assert_eq!(wendland(1.5), 0.0);
        assert_eq!(wendland(-0.1), 0.0);
        assert_eq!(wendland(f64::NAN), 0.0);
        let h = 1e-4;
        let mut last = 1.0;
        for k in 1..1000 {
            let r = k as f64 / 1000.0;
            let v = wendland(r);
            assert!(
                v > 0.0 && v < last,
                "decreasing and positive inside: {r} {v}"
            );
            last = v;
        }
        // C²: first and second differences vanish at the rim, and the slope at the centre is 0.
        let d1 = |r: f64| (wendland(r + h) - wendland(r - h)) / (2.0 * h);
        let d2 = |r: f64| (wendland(r + h) - 2.0 * wendland(r) + wendland(r - h)) / (h * h);
        assert!(
            d1(1.0).abs() < 1e-8 && d2(1.0).abs() < 1e-3,
            "{} {}",
            d1(1.0),
            d2(1.0)
        );
        assert!(d1(h).abs() < 1e-2, "{}", d1(h));
    }

    fn force_with_local(centres: Vec<[f64; 3]>, weights: Vec<f64>, radius_mm: f64) -> ForceField {
        ForceField {
            lo: [0.0, 0.0, 0.0],
            hi: [100.0, 100.0, 200.0],
            degree: 1,
            coeffs: vec![1.0, 0.0, 0.0, 0.0],
            centres,
            weights,
            radius_mm,
        }
    }

    #[test]
    fn a_forces_local_terms_add_where_they_reach_and_nowhere_else() {
        let f = force_with_local(vec![[50.0, 50.0, 100.0]], vec![2.0], 20.0);
        assert!(f.validate().is_ok());
        let (lo, hi) = (DVec3::from(f.lo), DVec3::from(f.hi));
        assert!((f.value_in_box(DVec3::new(50.0, 50.0, 100.0), lo, hi) - 3.0).abs() < 1e-12);
        assert!(
            (f.value_in_box(DVec3::new(50.0, 60.0, 100.0), lo, hi) - 1.0 - 2.0 * wendland(0.5))
                .abs()
                < 1e-12
        );
        assert_eq!(f.value_in_box(DVec3::new(50.0, 71.0, 100.0), lo, hi), 1.0);
        // Another box: the point is mapped into the fitted lung's frame first.
        let (lo2, hi2) = (lo + 7.0, lo + 7.0 + 2.0 * (hi - lo));
        assert!((f.value_in_box(DVec3::new(107.0, 107.0, 207.0), lo2, hi2) - 3.0).abs() < 1e-9);
        // Without local terms the file is what it was: no new keys, and an old file still loads.
        let plain = force_with_local(vec![], vec![], 0.0);
        let text = toml::to_string(&plain).unwrap();
        assert!(
            !text.contains("centres") && !text.contains("radius"),
            "{text}"
        );
        let back: ForceField = toml::from_str(&text).unwrap();
        assert_eq!(back, plain);
        let back: ForceField = toml::from_str(&toml::to_string(&f).unwrap()).unwrap();
        assert_eq!(back, f);
    }

    #[test]
    fn a_forces_bad_local_terms_are_refused_with_the_reason() {
        for (bad, words) in [
            (
                force_with_local(vec![[0.0; 3]], vec![], 10.0),
                "one weight per centre",
            ),
            (
                force_with_local(vec![[0.0; 3]], vec![1.0], 0.0),
                "positive radius",
            ),
            (
                force_with_local(vec![[0.0; 3]], vec![1.0], f64::INFINITY),
                "positive radius",
            ),
            (
                force_with_local(vec![[f64::NAN, 0.0, 0.0]], vec![1.0], 10.0),
                "finite",
            ),
            (
                force_with_local(vec![[0.0; 3]], vec![f64::NAN], 10.0),
                "finite",
            ),
            (
                force_with_local(vec![[50.0, 50.0, 100.0]; 1001], vec![1.0; 1001], 10.0),
                "at most 1000",
            ),
            (
                force_with_local(vec![[50.0, 50.0, 100.0]], vec![1.0], 0.045),
                "in metres",
            ),
            (
                force_with_local(vec![[50.0, 50.0, 400.0]], vec![1.0], 10.0),
                "outside its box",
            ),
        ] {
            let e = bad.validate().unwrap_err();
            assert!(e.contains(words), "{e}");
        }
    }
}
