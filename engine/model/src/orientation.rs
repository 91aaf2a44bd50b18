//! # orientation: the patient's pose → gravity in the body frame → the applied force's weights
//!
//! The applied force of eq. 6.18 is `f = c7·x̂ + c8·ŷ + c9·ẑ` for a supine patient (Table 6.1); its
//! gradient follows gravity. Chapter 7 (§7.4) makes the force depend on the patient's orientation
//! and blends precomputed orientations (eq. 7.8–7.9). EQUATIONS.md §3.3 implements that blend as
//! the seed's baseline ([`SeedBlend`]) and an exact method beside it ([`exact_weights`]):
//!
//! * **Gravity in the body frame.** The tracker reports the patient reference's pose `R`, a
//!   rotation of the patient's right-handed RAS frame into the room (the renderer registers the
//!   lungs with the same pose); body → room is `R·BODY_TO_RAS` ([`crate::frame`]: the body frame
//!   is left-handed). With the room's gravity `g_room` (scene `[engine] gravity_room`, the
//!   tracker's "down"), `g_body = BODY_TO_RAS·Rᵀ·g_room` ([`gravity_in_body`]). Supine,
//!   `g_body = (0, −1, 0)`: posterior ([`SUPINE_GRAVITY`]); lying on the left side, `+X`: the left
//!   lung is the dependent one.
//! * **Exact weights.** `w(g)` is the Table 6.1 vector `(c7, c8, c9)` rotated by the rotation `M`
//!   that takes supine gravity to `g` (the shortest arc; upside down, where every axis ⊥ gravity is
//!   shortest, a half turn about the body's cranio-caudal axis — the patient rolled prone). The
//!   weights live on the normalised axes `x̂, ŷ, ẑ` (lateral, anterior, inferior), so they are mapped to
//!   body axes and back (`S = diag(±1, 1, −1)`). **Decision (lungdyn):** the constant term
//!   `w0 = Σ_a max(0, −w_a)` keeps the force's minimum over the lung's box at 0, as Table 6.1's
//!   force is for a supine patient (0 at the dependent, posterior edge): prone, `f = 0.95·(1 − ŷ) + …`,
//!   the largest force is again on the upper (now posterior) side. The force is then
//!   `f = w0 + w·(x̂, ŷ, ẑ)`: four numbers per lung per tick, exactly what the basis mode needs.
//! * **The seed's blend** (eq. 7.8–7.9): weights precomputed at rotations of π/2, π, 3π/2, 2π about X,
//!   Y and Z (`p, q, r`), and for rotation angles `(a, b, c)` (here the XYZ Euler angles of `M`,
//!   `M = R_x(a)·R_y(b)·R_z(c)`; the seed names no convention)
//!   `f = Σ_axis [ p(a0)·cos(a − a0) + p(a1)·cos(a − a1) ] / 3`. It is not a partition of unity (41 %
//!   overshoot half-way between grid angles) and is exact only at the identity; it is kept to measure
//!   it (`lungdyn bench tradeoff`), not to use it.
//!
//! * **Where the supine model ends** ([`VolumeLimit`]). The directions of eq. 6.14–6.16 are fitted to a
//!   supine breath and point anterior everywhere (`c3·ŷ^c4 ≥ 0`); a force concentrated on the
//!   posterior side (prone) or along one flank (lateral decubitus) therefore moves much of the surface
//!   *inwards* or along itself, and the field barely changes — or even shrinks — the enclosed volume:
//!   measured on the generated 10k left lung at 250 ml, the volume slope is 1,500 mm³ per unit supine, 113 lying on
//!   the left side, −616 prone, so the scale that gives the breath's volume runs to 2,000 or flips
//!   sign, and the surface moves by metres. **Decision (lungdyn):** the weights are limited so the
//!   volume slope stays at least a ratio `ρ` of the supine one, by moving them along the
//!   straight line towards the supine weights (the slope is linear in the weights, so the limit is
//!   one division; continuous in the pose, no state). A limited tick is flagged
//!   (`ipc_types::engine_state::ORIENTATION_LIMITED`). `ρ` is the scene's `[engine] min_slope_ratio`,
//!   default [`DEFAULT_MIN_SLOPE_RATIO`] (0.8; issue 19: at the earlier 0.5 a turned breath moved the
//!   surface up to 3× as far as the supine one at FRC + 1500 ml and folded it, EQUATIONS.md §3.3);
//!   0 turns the limit off (the seed's eq. 7.8–7.9 limit nothing). Rotating the directions with
//!   gravity would lift the limit but is not linear in the weights (no basis, no SH); it is left
//!   open (EQUATIONS.md §3.3).
//!
//! Everything is f64 and allocation-free: the engine calls [`Orientation::weights`] every tick.

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::engine::{OrientationMethod, DEFAULT_MIN_SLOPE_RATIO};

use glam::{DMat3, DQuat, DVec3, EulerRot};
use thiserror::Error;

use crate::mesh::Side;

/// Gravity in the body frame of a supine patient: towards posterior (−Y).
pub const SUPINE_GRAVITY: DVec3 = DVec3::new(0.0, -1.0, 0.0);

/// Largest deviation of a pose quaternion's norm from 1 accepted as a rotation (tracker
/// quaternions are f32 and normalised by the tracker; anything further off is not a rotation).
pub const QUAT_NORM_TOLERANCE: f64 = 1e-3;

/// The force of one lung for one orientation: `f = w[0] + w[1]·x̂ + w[2]·ŷ + w[3]·ẑ`.
pub type ForceWeights = [f64; 4];

/// Why a pose gives no gravity direction.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum PoseError {
    /// A component is NaN or infinite.
    #[error("the patient pose quaternion has a non-finite component")]
    NonFinite,
    /// The quaternion is not of unit length: not a rotation.
    #[error("the patient pose quaternion has norm {norm}, not 1 (±{QUAT_NORM_TOLERANCE}): not a rotation")]
    NotARotation {
        /// Its norm.
        norm: f64,
    },
}

/// Gravity in the body frame for a patient pose `quat` (RAS → room, `[x, y, z, w]` as
/// `ipc_types::Pose`) and the room's unit gravity direction: the pose's inverse, then the
/// boundary reflection [`crate::frame::ras_to_body`].
pub fn gravity_in_body(quat: [f32; 4], gravity_room: DVec3) -> Result<DVec3, PoseError> {
    let q = DQuat::from_xyzw(
        quat[0] as f64,
        quat[1] as f64,
        quat[2] as f64,
        quat[3] as f64,
    );
    if !q.is_finite() {
        return Err(PoseError::NonFinite);
    }
    let norm = q.length();
    if !((norm - 1.0).abs() <= QUAT_NORM_TOLERANCE) {
        return Err(PoseError::NotARotation { norm });
    }
    let q = q / norm;
    Ok(crate::frame::room_dir_to_body(q, gravity_room).normalize())
}

/// The rotation `M` (body frame) with `M·SUPINE_GRAVITY = g`: the shortest arc; at `g = −SUPINE_GRAVITY`
/// a half turn about the body's Z (cranio-caudal) axis. `g` must be unit length.
pub fn rotation_from_supine(g: DVec3) -> DQuat {
    let from = SUPINE_GRAVITY;
    let d = from.dot(g);
    if d < -1.0 + 1e-12 {
        return DQuat::from_rotation_z(std::f64::consts::PI);
    }
    DQuat::from_rotation_arc(from, g)
}

/// `S = diag(lateral, 1, −1)`: normalised axes (x̂ lateral, ŷ anterior, ẑ inferior) ↔ body axes.
fn axes(side: Side) -> DVec3 {
    DVec3::new(side.lateral_sign() as f64, 1.0, -1.0)
}

/// The weights of a rotated weight vector `w_n` (on the normalised axes) with the constant term
/// that keeps the force's minimum over the box at 0.
fn with_offset(w: DVec3) -> ForceWeights {
    let w0 = (-w.x).max(0.0) + (-w.y).max(0.0) + (-w.z).max(0.0);
    [w0, w.x, w.y, w.z]
}

/// Rotate Table 6.1's `(c7, c8, c9)` by the body-frame rotation `m`.
fn rotate_weights(c789: [f64; 3], side: Side, m: DQuat) -> ForceWeights {
    let s = axes(side);
    let body = DVec3::from(c789) * s;
    with_offset((m * body) * s)
}

/// Exact force weights for gravity `g` (body frame, unit): Table 6.1's `(c7, c8, c9)` rotated by
/// [`rotation_from_supine`], plus the offset `w0` (EQUATIONS.md §3.3).
pub fn exact_weights(c789: [f64; 3], side: Side, g: DVec3) -> ForceWeights {
    rotate_weights(c789, side, rotation_from_supine(g))
}

/// The seed's eq. 7.8–7.9 blend: force weights precomputed at rotations of π/2, π, 3π/2, 2π about X, Y
/// and Z, blended by the cosines of the angle to the neighbouring grid angles.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeedBlend {
    /// `table[axis][i]`: weights at rotation `i·π/2` about axis X, Y, Z (i = 0 is 2π).
    table: [[ForceWeights; 4]; 3],
}

impl SeedBlend {
    /// Precompute the 12 orientations of eq. 7.9 (`p`, `q`, `r`).
    pub fn new(c789: [f64; 3], side: Side) -> Self {
        let mut table = [[[0.0; 4]; 4]; 3];
        for (axis, row) in table.iter_mut().enumerate() {
            for (i, w) in row.iter_mut().enumerate() {
                let angle = i as f64 * std::f64::consts::FRAC_PI_2;
                let m = match axis {
                    0 => DQuat::from_rotation_x(angle),
                    1 => DQuat::from_rotation_y(angle),
                    _ => DQuat::from_rotation_z(angle),
                };
                *w = rotate_weights(c789, side, m);
            }
        }
        Self { table }
    }

    /// Eq. 7.8–7.9 for gravity `g` (body frame, unit): the rotation angles `(a, b, c)` are the XYZ
    /// Euler angles of [`rotation_from_supine`]`(g)`.
    pub fn weights(&self, g: DVec3) -> ForceWeights {
        let (a, b, c) = rotation_from_supine(g).to_euler(EulerRot::XYZ);
        self.weights_at_angles([a, b, c])
    }

    /// Eq. 7.8–7.9 for rotation angles `(a, b, c)` about X, Y, Z (radians, any range).
    pub fn weights_at_angles(&self, angles: [f64; 3]) -> ForceWeights {
        let quarter = std::f64::consts::FRAC_PI_2;
        let mut out = [0.0; 4];
        for (axis, &angle) in angles.iter().enumerate() {
            let a = angle.rem_euclid(std::f64::consts::TAU);
            let i0 = ((a / quarter).floor() as usize).min(3);
            let a0 = i0 as f64 * quarter;
            let a1 = a0 + quarter;
            let i1 = (i0 + 1) % 4;
            let (c0, c1) = ((a - a0).cos(), (a - a1).cos());
            for k in 0..4 {
                out[k] += (self.table[axis][i0][k] * c0 + self.table[axis][i1][k] * c1) / 3.0;
            }
        }
        out
    }
}

/// Whether `ratio` is a usable [`VolumeLimit`] ratio: finite, in `[0, 1]` (0: no limit).
pub fn min_slope_ratio_ok(ratio: f64) -> bool {
    ratio.is_finite() && (0.0..=1.0).contains(&ratio)
}

/// The limit on the weights that keeps the field expanding the lung like the supine breath (see the
/// module doc): the volume slope `v1(w) = Σ_a w_a·L_a` (the linear volume form of the exact basis
/// fields) must stay at least `ratio`·`v1(w_supine)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeLimit {
    /// Linear volume form `L_a`.
    pub linear: [f64; 4],
    /// Supine weights.
    pub supine: ForceWeights,
    /// Smallest slope as a fraction of the supine one (0: no limit).
    pub ratio: f64,
}

impl VolumeLimit {
    /// The limit for a lung whose exact fields have linear volume form `linear`; `ratio` as
    /// [`min_slope_ratio_ok`] (a value outside `[0, 1]` or NaN is taken as 0: no limit).
    pub fn new(linear: [f64; 4], c789: [f64; 3], side: Side, ratio: f64) -> Self {
        Self {
            linear,
            supine: exact_weights(c789, side, SUPINE_GRAVITY),
            ratio: if min_slope_ratio_ok(ratio) {
                ratio
            } else {
                0.0
            },
        }
    }

    /// The limit around given supine weights (a kernel with a fitted supine force,
    /// [`Orientation::with_fitted_supine`], whose supine weights are [`FITTED_SUPINE`]).
    pub fn around(linear: [f64; 4], supine: ForceWeights, ratio: f64) -> Self {
        Self {
            linear,
            supine,
            ratio: if min_slope_ratio_ok(ratio) {
                ratio
            } else {
                0.0
            },
        }
    }

    fn slope(&self, w: &ForceWeights) -> f64 {
        (0..4).map(|a| w[a] * self.linear[a]).sum()
    }

    /// `w` itself when it expands enough (or the ratio is 0), else the point on the segment from
    /// the supine weights to `w` where the slope is `ratio` of the supine one; and whether it was
    /// limited.
    pub fn apply(&self, w: ForceWeights) -> (ForceWeights, bool) {
        let v_s = self.slope(&self.supine);
        let v = self.slope(&w);
        let floor = self.ratio * v_s;
        if self.ratio == 0.0 || !(v_s > 0.0) || v >= floor {
            return (w, false);
        }
        // v1 is linear along the segment: t·v + (1 − t)·v_s = floor.
        let t = ((v_s - floor) / (v_s - v)).clamp(0.0, 1.0);
        let mut out = [0.0; 4];
        for a in 0..4 {
            out[a] = self.supine[a] + t * (w[a] - self.supine[a]);
        }
        (out, true)
    }
}

/// One lung's orientation model: the method, what it precomputed and the volume limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Orientation {
    method: OrientationMethod,
    c789: [f64; 3],
    side: Side,
    seed: SeedBlend,
    limit: Option<VolumeLimit>,
    /// The kernel's first basis function is its fitted supine force ([`Self::with_fitted_supine`]).
    fitted: bool,
}

/// The supine weights of a kernel with a fitted supine force: the fitted force alone.
pub const FITTED_SUPINE: ForceWeights = [1.0, 0.0, 0.0, 0.0];

/// Weights `w` of eq. 6.18's force for a posture, as weights of a kernel whose first basis function
/// is a fitted supine force `F` (EQUATIONS.md §3.3, "A fitted supine force"): `F` once, plus the
/// change of eq. 6.18's linear part from its supine weights `supine`. Exactly [`FITTED_SUPINE`] at
/// `w = supine`. The constant offset `w0` is not carried over: the basis has no constant function
/// left (the fitted force has its own level). Carrying it through the constant's least-squares
/// weights in `(F, x̂, ŷ, ẑ)` was tried and folded the breath-hold population's lungs in more
/// postures (225 surfaces against 196 of 416, EQUATIONS.md §3.3).
pub fn fitted_weights(w: ForceWeights, supine: ForceWeights) -> ForceWeights {
    [1.0, w[1] - supine[1], w[2] - supine[2], w[3] - supine[3]]
}

impl Orientation {
    /// The model of `side` with Table 6.1-style constants `c789`; `linear` is the exact fields'
    /// linear volume form (the kernel's `orientation.volume_forms.l`), `None` for no limit, and
    /// `min_slope_ratio` the limit's ratio ([`VolumeLimit`]; 0: no limit).
    pub fn new(
        method: OrientationMethod,
        c789: [f64; 3],
        side: Side,
        linear: Option<[f64; 4]>,
        min_slope_ratio: f64,
    ) -> Self {
        Self {
            method,
            c789,
            side,
            seed: SeedBlend::new(c789, side),
            limit: linear.map(|l| VolumeLimit::new(l, c789, side, min_slope_ratio)),
            fitted: false,
        }
    }

    /// The same model for a kernel baked with a fitted supine force (a breath-hold fit or the
    /// breath-hold population, `KernelMeta::orientation.fitted_supine_force`): its basis is
    /// `(F, x̂, ŷ, ẑ)` with `F` the fitted force, and the weights are [`fitted_weights`] — exactly
    /// `F` supine, so every orientation mode draws the fitted motion there; eq. 6.18's change with
    /// posture added elsewhere. The volume limit is kept, around [`FITTED_SUPINE`].
    pub fn with_fitted_supine(mut self) -> Self {
        self.fitted = true;
        self.limit = self
            .limit
            .map(|l| VolumeLimit::around(l.linear, FITTED_SUPINE, l.ratio));
        self
    }

    /// Whether the weights are those of a fitted supine force ([`Self::with_fitted_supine`]).
    pub fn is_fitted(&self) -> bool {
        self.fitted
    }

    /// The method.
    pub fn method(&self) -> OrientationMethod {
        self.method
    }

    /// Force weights for gravity `g` in the body frame (unit), and whether the volume limit
    /// changed them. No allocation.
    pub fn weights(&self, g: DVec3) -> (ForceWeights, bool) {
        let w = match self.method {
            OrientationMethod::Fixed => exact_weights(self.c789, self.side, SUPINE_GRAVITY),
            OrientationMethod::Exact => exact_weights(self.c789, self.side, g),
            OrientationMethod::Seed => self.seed.weights(g),
        };
        let w = if self.fitted {
            fitted_weights(w, exact_weights(self.c789, self.side, SUPINE_GRAVITY))
        } else {
            w
        };
        match &self.limit {
            Some(l) => l.apply(w),
            None => (w, false),
        }
    }
}

/// Rotation matrix of a pose quaternion (RAS → room; for tests and tools).
pub fn pose_matrix(quat: [f32; 4]) -> DMat3 {
    DMat3::from_quat(
        DQuat::from_xyzw(
            quat[0] as f64,
            quat[1] as f64,
            quat[2] as f64,
            quat[3] as f64,
        )
        .normalize(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    const LEFT: [f64; 3] = [0.01, 0.95, 0.07];

    fn supine_room() -> DQuat {
        // RAS X (patient right) → room Y, anterior → room Z (up), superior → room X (the head):
        // the synthetic tracker's supine.
        DQuat::from_mat3(&DMat3::from_cols(DVec3::Y, DVec3::Z, DVec3::X))
    }

    /// The patient rolled a quarter turn about the bed's long axis (room X) from supine.
    fn rolled(angle: f64) -> [f32; 4] {
        as_pose(DQuat::from_rotation_x(angle) * supine_room())
    }

    /// Lying on the LEFT side (left lateral decubitus), gravity points to the patient's left: the
    /// left lung (body +X) is dependent, in the gravity the engine computes and in the force
    /// weights it gives. Supine, the patient's left is room −Y (head at +X, face up); the roll
    /// that puts it down is +90° about room X. Before the boundary reflection (issue 19) this
    /// pose gave gravity towards body −X: the right lung dependent.
    #[test]
    fn lying_on_the_left_side_makes_the_left_lung_dependent() {
        let down = DVec3::new(0.0, 0.0, -1.0);
        let left_down = gravity_in_body(rolled(FRAC_PI_2), down).unwrap();
        assert!((left_down - DVec3::X).length() < 1e-6, "{left_down}");
        let right_down = gravity_in_body(rolled(-FRAC_PI_2), down).unwrap();
        assert!((right_down + DVec3::X).length() < 1e-6, "{right_down}");
        // The physical check, without the body frame's conventions: the patient's left side,
        // taken to the room through the same boundary, points down.
        let q = DQuat::from_rotation_x(FRAC_PI_2) * supine_room();
        let left_in_room = q * crate::frame::body_to_ras(DVec3::X);
        assert!((left_in_room - down).length() < 1e-12, "{left_in_room}");
        // The force is largest on the upper (here right, medial for the left lung) side: for the
        // left lung, x̂ runs lateral (+X, down), so the weight on x̂ is negative.
        let w = exact_weights(LEFT, Side::Left, left_down);
        assert!(w[1] < -0.9, "{w:?}");
        assert!(force(w, DVec3::new(0.0, 0.5, 0.5)) > force(w, DVec3::new(1.0, 0.5, 0.5)));
    }

    fn as_pose(q: DQuat) -> [f32; 4] {
        q.to_array().map(|v| v as f32)
    }

    fn force(w: ForceWeights, n: DVec3) -> f64 {
        w[0] + w[1] * n.x + w[2] * n.y + w[3] * n.z
    }

    #[test]
    fn supine_gives_table_6_1_with_no_offset() {
        let g = gravity_in_body(as_pose(supine_room()), DVec3::new(0.0, 0.0, -1.0)).unwrap();
        assert!((g - SUPINE_GRAVITY).length() < 1e-7, "{g}");
        for side in [Side::Left, Side::Right] {
            let w = exact_weights(LEFT, side, SUPINE_GRAVITY);
            assert_eq!(w, [0.0, 0.01, 0.95, 0.07], "{side:?}");
        }
    }

    #[test]
    fn prone_puts_the_largest_force_on_the_upper_posterior_side() {
        let w = exact_weights(LEFT, Side::Left, -SUPINE_GRAVITY);
        // Half turn about body Z: x̂ and ŷ flip, ẑ stays.
        let expect = [0.01 + 0.95, -0.01, -0.95, 0.07];
        for k in 0..4 {
            assert!((w[k] - expect[k]).abs() < 1e-12, "{w:?}");
        }
        assert!(force(w, DVec3::new(0.5, 0.0, 0.5)) > force(w, DVec3::new(0.5, 1.0, 0.5)));
    }

    #[test]
    fn upright_puts_the_largest_force_at_the_apex() {
        // Sitting up: gravity towards the feet (−Z body).
        let w = exact_weights(LEFT, Side::Left, DVec3::new(0.0, 0.0, -1.0));
        assert!(force(w, DVec3::new(0.5, 0.5, 0.0)) > force(w, DVec3::new(0.5, 0.5, 1.0)));
        assert!((w[3] + 0.95).abs() < 1e-12, "{w:?}");
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(512))]
        #[test]
        fn exact_weights_are_a_rotation_and_never_negative_over_the_box(
            x in -1.0f64..1.0, y in -1.0f64..1.0, z in -1.0f64..1.0, right in proptest::bool::ANY,
        ) {
            let v = DVec3::new(x, y, z);
            proptest::prop_assume!(v.length() > 1e-3);
            let g = v.normalize();
            let side = if right { Side::Right } else { Side::Left };
            let w = exact_weights(LEFT, side, g);
            proptest::prop_assert!(w.iter().all(|v| v.is_finite()));
            // A rotation keeps the length of (c7, c8, c9).
            let len = (w[1] * w[1] + w[2] * w[2] + w[3] * w[3]).sqrt();
            proptest::prop_assert!((len - DVec3::from(LEFT).length()).abs() < 1e-12);
            // The force's minimum over the box is 0 (at a corner).
            let mut min = f64::INFINITY;
            for c in 0..8 {
                let n = DVec3::new((c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64);
                min = min.min(force(w, n));
            }
            proptest::prop_assert!(min.abs() < 1e-12, "min {}", min);
            // The rotation really takes supine gravity to g.
            let m = rotation_from_supine(g);
            proptest::prop_assert!((m * SUPINE_GRAVITY - g).length() < 1e-9);
        }
    }

    #[test]
    fn the_seed_blend_is_exact_at_the_identity_only() {
        let s = SeedBlend::new(LEFT, Side::Left);
        let id = s.weights(SUPINE_GRAVITY);
        let exact = exact_weights(LEFT, Side::Left, SUPINE_GRAVITY);
        for k in 0..4 {
            assert!((id[k] - exact[k]).abs() < 1e-12, "{id:?}");
        }
        // A quarter turn about X alone: the blend averages it with two identities (seed's /3).
        let m = DQuat::from_rotation_x(FRAC_PI_2);
        let g = m * SUPINE_GRAVITY;
        let blended = s.weights_at_angles([FRAC_PI_2, 0.0, 0.0]);
        let exact = exact_weights(LEFT, Side::Left, g);
        let err: f64 = (0..4).map(|k| (blended[k] - exact[k]).abs()).sum();
        assert!(
            err > 0.3,
            "the seed blend is not exact away from the identity: {err}"
        );
        // Half-way between grid angles the cosine weights sum to √2 (not a partition of unity).
        let half = s.weights_at_angles([PI / 4.0, 0.0, 0.0]);
        assert!(half.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn the_seed_blend_is_finite_at_gimbal_lock_and_every_extreme() {
        let s = SeedBlend::new(LEFT, Side::Right);
        for g in [
            DVec3::X,
            -DVec3::X,
            DVec3::Y,
            -DVec3::Y,
            DVec3::Z,
            -DVec3::Z,
            DVec3::new(1.0, -1.0, 0.0).normalize(),
        ] {
            let w = s.weights(g);
            assert!(w.iter().all(|v| v.is_finite()), "{g}: {w:?}");
        }
        for b in [FRAC_PI_2, -FRAC_PI_2] {
            let w = s.weights_at_angles([0.3, b, 1.1]);
            assert!(w.iter().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn a_nan_or_non_rotation_pose_is_a_specific_error() {
        let down = DVec3::new(0.0, 0.0, -1.0);
        assert_eq!(
            gravity_in_body([f32::NAN, 0.0, 0.0, 1.0], down),
            Err(PoseError::NonFinite)
        );
        assert!(matches!(
            gravity_in_body([0.0, 0.0, 0.0, 0.0], down),
            Err(PoseError::NotARotation { .. })
        ));
        assert!(matches!(
            gravity_in_body([0.0, 0.0, 0.0, 2.0], down),
            Err(PoseError::NotARotation { .. })
        ));
        assert!(matches!(
            gravity_in_body([f32::INFINITY, 0.0, 0.0, 1.0], down),
            Err(PoseError::NonFinite)
        ));
        // A slightly denormalised f32 quaternion is still a rotation.
        assert!(gravity_in_body([0.0, 0.0, 0.0, 1.0005], down).is_ok());
    }

    #[test]
    fn the_volume_limit_keeps_the_slope_and_moves_towards_supine() {
        // A lung whose posterior-weighted force shrinks it: L_y large, L_0 smaller.
        let l = VolumeLimit::new(
            [877.0, 50.0, 1550.0, 200.0],
            LEFT,
            Side::Left,
            DEFAULT_MIN_SLOPE_RATIO,
        );
        let supine = exact_weights(LEFT, Side::Left, SUPINE_GRAVITY);
        let (w, limited) = l.apply(supine);
        assert!(!limited && w == supine);
        let prone = exact_weights(LEFT, Side::Left, -SUPINE_GRAVITY);
        let (w, limited) = l.apply(prone);
        assert!(limited);
        let v_s: f64 = (0..4).map(|a| supine[a] * l.linear[a]).sum();
        let v: f64 = (0..4).map(|a| w[a] * l.linear[a]).sum();
        assert!(
            (v - DEFAULT_MIN_SLOPE_RATIO * v_s).abs() < 1e-9 * v_s,
            "{v} vs {v_s}"
        );
        // Continuous: a hair on either side of the limit gives nearly the same weights.
        for ratio in [0.5, DEFAULT_MIN_SLOPE_RATIO, 1.0] {
            let o = Orientation::new(
                OrientationMethod::Exact,
                LEFT,
                Side::Left,
                Some(l.linear),
                ratio,
            );
            for g in [DVec3::X, -DVec3::Z, DVec3::new(0.3, 0.9, 0.1).normalize()] {
                let (w, _) = o.weights(g);
                assert!(w.iter().all(|v| v.is_finite()));
                let v: f64 = (0..4).map(|a| w[a] * l.linear[a]).sum();
                assert!(
                    v >= ratio * v_s * (1.0 - 1e-12),
                    "ratio {ratio}: {v} vs {v_s}"
                );
            }
        }
        // A larger ratio keeps the prone weights nearer supine; 1 gives supine's slope exactly.
        let near = |ratio| {
            let (w, _) = VolumeLimit::new(l.linear, LEFT, Side::Left, ratio).apply(prone);
            (0..4).map(|a| (w[a] - supine[a]).abs()).sum::<f64>()
        };
        assert!(near(0.8) < near(0.5) && near(1.0) < near(0.8));
    }

    /// Ratio 0 is no limit (the seed's eq. 7.8–7.9 limit nothing): every posture's exact weights
    /// come through unchanged, even one whose field shrinks the lung; a ratio that is not in
    /// `[0, 1]` is refused by [`min_slope_ratio_ok`] and taken as 0 by the limit.
    #[test]
    fn ratio_zero_is_the_unlimited_reading_and_bad_ratios_are_refused() {
        let linear = [877.0, 50.0, 1550.0, 200.0];
        let prone = exact_weights(LEFT, Side::Left, -SUPINE_GRAVITY);
        let o = Orientation::new(
            OrientationMethod::Exact,
            LEFT,
            Side::Left,
            Some(linear),
            0.0,
        );
        assert_eq!(o.weights(-SUPINE_GRAVITY), (prone, false));
        for bad in [f64::NAN, -0.1, 1.5, f64::INFINITY] {
            assert!(!min_slope_ratio_ok(bad), "{bad}");
            assert_eq!(VolumeLimit::new(linear, LEFT, Side::Left, bad).ratio, 0.0);
        }
        for good in [0.0, 0.5, DEFAULT_MIN_SLOPE_RATIO, 1.0] {
            assert!(min_slope_ratio_ok(good), "{good}");
        }
    }

    #[test]
    fn euler_convention_is_xyz_intrinsic() {
        let q = DQuat::from_rotation_x(0.3)
            * DQuat::from_rotation_y(0.2)
            * DQuat::from_rotation_z(-0.4);
        let (a, b, c) = q.to_euler(EulerRot::XYZ);
        assert!((a - 0.3).abs() < 1e-12 && (b - 0.2).abs() < 1e-12 && (c + 0.4).abs() < 1e-12);
    }
}
