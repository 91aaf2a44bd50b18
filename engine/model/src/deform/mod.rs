//! # deform: per-vertex displacement (direction model × force), the volume cubic, the lung model
//!
//! Implements EQUATIONS.md §2.4. A baked kernel stores each node's unit displacement
//! `F[i]·d_i` with `F = Tᵀf` the elastostatic force of the Green's-function operator (eq. 6.1,
//! 6.11–6.13, computed by `lung-bake`); [`LungModel::build`] keeps the first mode (the applied force
//! used directly, no transfer pass) for comparison. The pieces:
//!
//! * **eq. 6.14–6.16** — direction of displacement from the node's normalised position in the lung's
//!   bounding box, `d = (c1·x̂^c2, c3·ŷ^c4, c5·ẑ^c6)` normalised, with x̂ from the mediastinum outwards,
//!   ŷ from posterior to anterior, ẑ from the apex to the base (Table 6.1 constants);
//! * **eq. 6.18** — applied-force magnitude `f = c7·x̂ + c8·ŷ + c9·ẑ`;
//! * the unit displacement `u_i = k · F_i · d_i` (F the elastostatic force; the applied force f in the
//!   first mode), with `k` chosen so that the enclosed volume grows by
//!   exactly one *unit volume* (TV / (66.66 steps/s × 5 s) ≈ 1.5 ml) — EQUATIONS.md §2.4, Decision.
//!
//! At run time a vertex moves to `p_i + s·u_i`. EQUATIONS.md says `s = ΔV / unit` ("linear in
//! volume"). The enclosed volume of `p + s·u` is, however, an exact cubic in `s`
//! ([`VolumeCubic`]); the linear reading under-/over-shoots by the quadratic and cubic terms (a few
//! percent of ΔV at tidal volume, see the test). **Refinement of the Decision:** the engine solves
//! the cubic for `s` each tick (a few Newton steps on four numbers), so the mesh's enclosed volume
//! tracks the PV volume exactly while the per-vertex work stays "3 additions per node" (one
//! multiply-add per coordinate) on the GPU.

pub mod field;
pub mod modes;
pub mod sh_coeffs;

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::DirectionPreset;

use glam::DVec3;
use thiserror::Error;

use crate::mesh::{Side, TriMesh};

/// Table 6.1 constants `c1..c9` of the direction model (eq. 6.14–6.16) and applied force (eq. 6.18).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionConstants {
    /// `c1..c9` (exactly nine: a longer list is refused, never cut to its first nine).
    #[serde(deserialize_with = "exactly_nine")]
    pub c: [f64; 9],
}

/// `c` as exactly nine numbers. serde's fixed-size arrays read the first nine of a longer list and
/// drop the rest silently; a file with twenty values is not the constants of eq. 6.14-6.18.
fn exactly_nine<'de, D: serde::Deserializer<'de>>(d: D) -> Result<[f64; 9], D::Error> {
    let v: Vec<f64> = serde::Deserialize::deserialize(d)?;
    <[f64; 9]>::try_from(v.as_slice()).map_err(|_| {
        serde::de::Error::custom(format!(
            "c has {} values; the motion model takes exactly 9 (c1..c9 of eq. 6.14-6.18)",
            v.len()
        ))
    })
}

impl MotionConstants {
    /// Population constants (lungdyn, EQUATIONS.md §2.4 "Breathing like a person"): a diaphragm
    /// drive. The direction turns from anterior at the apex (`ŷ`, chest wall) to inferior at the
    /// base (`ẑ²`, diaphragm); the applied force grows towards the base and anteriorly. Chosen so
    /// that the generated lungs' lower third moves as the DIR-Lab 4DCT landmarks do (mean |SI|
    /// 13.1 mm, |AP| 2.1, |LR| 1.2 at end-inhale, taken as a 500 ml breath); both sides alike.
    pub fn population(_side: Side) -> Self {
        Self {
            c: [0.1, 1.0, 0.15, 1.0, 1.0, 2.0, 0.0, 0.6, 0.4],
        }
    }

    /// Table 6.1 for `side`.
    pub fn table_6_1(side: Side) -> Self {
        match side {
            Side::Left => Self {
                c: [0.09, 0.23, 0.4, 0.5, 0.1, 2.3, 0.01, 0.95, 0.07],
            },
            Side::Right => Self {
                c: [0.09, 0.22, 0.39, 0.51, 0.11, 2.2, 0.01, 0.96, 0.05],
            },
        }
    }
}

/// The breath-hold population's motion file (`bench/population_motion.py` wrote it; the same file
/// a scene can name as `motion = ...`), built in.
pub const BREATH_HOLD_POPULATION: &str =
    include_str!("../../../../scenes/motion/breath_hold_population.toml");

/// A preset's motion for one lung: the constants and, for a fitted preset, its direction and
/// applied force fields (as a motion file gives them, [`MotionFile`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PresetMotion {
    /// `c1..c9` (for a fitted preset Table 6.1's, whose `c7..c9` give the posture's change of the
    /// force in the orientation modes, EQUATIONS.md §3.3).
    pub constants: MotionConstants,
    /// The direction field, if any.
    pub direction_field: Option<field::Field>,
    /// The applied force field, if any.
    pub force_field: Option<field::ForceField>,
}

/// The motion of `preset` for `side`.
pub fn preset_motion(preset: DirectionPreset, side: Side) -> PresetMotion {
    let constants = |constants| PresetMotion {
        constants,
        direction_field: None,
        force_field: None,
    };
    match preset {
        DirectionPreset::Population => constants(MotionConstants::population(side)),
        DirectionPreset::BreathHold => {
            let f = breath_hold_population();
            PresetMotion {
                constants: f.for_side(side),
                direction_field: f.field_for_side(side).cloned(),
                force_field: f.force_for_side(side).cloned(),
            }
        }
        DirectionPreset::Seed => constants(MotionConstants::table_6_1(side)),
    }
}

/// The built-in breath-hold population, parsed and checked once (a broken built-in file is a
/// build defect: a test reads it).
fn breath_hold_population() -> &'static MotionFile {
    static FILE: std::sync::OnceLock<MotionFile> = std::sync::OnceLock::new();
    FILE.get_or_init(|| {
        MotionFile::parse(
            BREATH_HOLD_POPULATION,
            std::path::Path::new("scenes/motion/breath_hold_population.toml (built in)"),
        )
        .expect("the built-in breath-hold population is a valid motion file")
    })
}

/// Motion constants of both lungs as written by `lungdyn fit-motion` (TOML). Format 1: `c1..c9` per
/// lung. Format 2 adds, per lung, the displacement field the fit chose by cross-validation
/// (`[left_field]`, `[right_field]`: see [`field::Field`]) and what it was fitted from.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionFile {
    /// File format version (1 or 2).
    pub format: u32,
    /// Left lung `c1..c9`; Table 6.1 when absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub left: Option<MotionConstants>,
    /// Right lung `c1..c9`; Table 6.1 when absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub right: Option<MotionConstants>,
    /// Format 2: the frame the landmarks were read in (information).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    /// Format 2: the model chosen and its cross-validated mean error, mm (information).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chosen: Option<String>,
    /// Format 2: cross-validated mean landmark error of the chosen model, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cv_mean_error_mm: Option<f64>,
    /// Format 2: the left lung's displacement field (the kernel's directions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_field: Option<field::Field>,
    /// Format 2: the right lung's displacement field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right_field: Option<field::Field>,
    /// Format 2, from a breath-hold pair (`fit-motion --exhale/--inhale`): the left lung's
    /// applied force field, replacing `c7..c9`'s linear force before the operator.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_force: Option<field::ForceField>,
    /// Format 2: the right lung's applied force field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right_force: Option<field::ForceField>,
}

impl MotionFile {
    /// Read and validate `path`.
    pub fn load(path: &std::path::Path) -> Result<Self, MotionFileError> {
        let text = crate::input::read_text_bounded(path, crate::input::ReadLimits::CONFIG)
            .map_err(|source| MotionFileError::Input { source })?;
        Self::parse(&text, path)
    }

    /// Parse and validate `text`, naming `path` in errors.
    pub fn parse(text: &str, path: &std::path::Path) -> Result<Self, MotionFileError> {
        let path_buf = || path.to_path_buf();
        let f: Self = toml::from_str(text).map_err(|e| MotionFileError::Toml {
            path: path_buf(),
            message: e.to_string(),
        })?;
        if !(1..=2).contains(&f.format) {
            return Err(MotionFileError::Format {
                path: path_buf(),
                found: f.format,
            });
        }
        if f.format == 2 && f.frame.is_none() {
            // Format 2 is what `fit-motion` writes from landmarks; it always says their frame. One
            // without it was edited by hand from a format-1 file and claims a fit it does not carry.
            return Err(MotionFileError::Incomplete {
                path: path_buf(),
                what: "format 2 names the frame its landmarks were read in (`frame = ...`, written by \
                       `lungdyn fit-motion`); write `format = 1` for constants alone",
            });
        }
        for (side, field) in [("left", &f.left_field), ("right", &f.right_field)] {
            if let Some(field) = field {
                field.validate().map_err(|reason| MotionFileError::Field {
                    path: path_buf(),
                    side,
                    reason,
                })?;
            }
        }
        for (side, force) in [("left", &f.left_force), ("right", &f.right_force)] {
            if let Some(force) = force {
                force.validate().map_err(|reason| MotionFileError::Field {
                    path: path_buf(),
                    side,
                    reason,
                })?;
            }
        }
        for (side, k) in [("left", &f.left), ("right", &f.right)] {
            if let Some(k) = k {
                check_constants(k).map_err(|source| MotionFileError::Constants {
                    path: path_buf(),
                    side,
                    source,
                })?;
            }
        }
        Ok(f)
    }

    /// The displacement field of `side`, if the file has one (format 2).
    pub fn field_for_side(&self, side: Side) -> Option<&field::Field> {
        match side {
            Side::Left => self.left_field.as_ref(),
            Side::Right => self.right_field.as_ref(),
        }
    }

    /// The applied force field of `side`, if the file has one (a breath-hold pair's fit).
    pub fn force_for_side(&self, side: Side) -> Option<&field::ForceField> {
        match side {
            Side::Left => self.left_force.as_ref(),
            Side::Right => self.right_force.as_ref(),
        }
    }

    /// Constants of `side` (Table 6.1 when the file has none).
    pub fn for_side(&self, side: Side) -> MotionConstants {
        match side {
            Side::Left => self.left,
            Side::Right => self.right,
        }
        .unwrap_or_else(|| MotionConstants::table_6_1(side))
    }
}

/// Errors reading a motion constants file.
#[derive(Debug, Error)]
pub enum MotionFileError {
    /// The file could not be read within the limits.
    #[error("motion constants: {source}")]
    Input {
        /// Why.
        source: crate::input::InputError,
    },
    /// Not TOML of the motion format (the parser's message names line and column).
    #[error("{} is not a motion constants file: {message}", path.display())]
    Toml {
        /// Path.
        path: std::path::PathBuf,
        /// Parser message.
        message: String,
    },
    /// Another format version.
    #[error("{}: motion constants format {found} (this lungdyn reads 1 and 2)", path.display())]
    Format {
        /// Path.
        path: std::path::PathBuf,
        /// Format in the file.
        found: u32,
    },
    /// A format-2 file lacks what format 2 carries.
    #[error("{}: {what}", path.display())]
    Incomplete {
        /// Path.
        path: std::path::PathBuf,
        /// What is missing.
        what: &'static str,
    },
    /// A lung's field is unusable.
    #[error("{}: {side}_field: {reason}", path.display())]
    Field {
        /// Path.
        path: std::path::PathBuf,
        /// "left" or "right".
        side: &'static str,
        /// What is wrong.
        reason: &'static str,
    },
    /// A lung's constants are unusable.
    #[error("{}: {side} lung", path.display())]
    Constants {
        /// Path.
        path: std::path::PathBuf,
        /// "left" or "right".
        side: &'static str,
        /// Why.
        source: DeformError,
    },
}

/// Unit volume of EQUATIONS.md §2.4: TV / (steps per second × phase length) = 500 / (66.66 × 5) ml.
pub const UNIT_VOLUME_ML: f64 = 500.0 / (66.66 * 5.0);

/// Normalised position `(x̂, ŷ, ẑ)` of a body-frame point in a lung's bounding box, with the axes of
/// eq. 6.14–6.16: x̂ mediastinum → lateral, ŷ posterior → anterior, ẑ apex → base. Each in [0, 1].
pub fn normalised_position(p: [f32; 3], bb: &crate::mesh::Aabb, side: Side) -> DVec3 {
    let unit = |v: f32, lo: f32, hi: f32| {
        let span = (hi - lo) as f64;
        if span > 0.0 {
            ((v - lo) as f64 / span).clamp(0.0, 1.0)
        } else {
            0.0
        }
    };
    let x_out = match side {
        Side::Left => unit(p[0], bb.min[0], bb.max[0]),
        Side::Right => 1.0 - unit(p[0], bb.min[0], bb.max[0]),
    };
    DVec3::new(
        x_out,
        unit(p[1], bb.min[1], bb.max[1]),
        1.0 - unit(p[2], bb.min[2], bb.max[2]),
    )
}

/// Direction of displacement (eq. 6.14–6.16) in the body frame, unit length (zero at the single
/// point where every component vanishes).
pub fn direction(n: DVec3, k: &MotionConstants, side: Side) -> DVec3 {
    let c = &k.c;
    let local = DVec3::new(
        c[0] * n.x.powf(c[1]),
        c[2] * n.y.powf(c[3]),
        c[4] * n.z.powf(c[5]),
    );
    // Local axes → body frame: lateral is ±X, anterior +Y, towards the base −Z.
    let body = DVec3::new(side.lateral_sign() as f64 * local.x, local.y, -local.z);
    let len = body.length();
    if len > 1e-300 {
        body / len
    } else {
        DVec3::ZERO
    }
}

/// Applied-force magnitude of eq. 6.18 (before normalisation).
pub fn applied_force(n: DVec3, k: &MotionConstants) -> f64 {
    k.c[6] * n.x + k.c[7] * n.y + k.c[8] * n.z
}

/// The supine applied force of a lung whose motion carries a fitted force field (a breath-hold
/// pair's fit or the breath-hold population; EQUATIONS.md §3.3, "A fitted supine force"): the
/// field at each vertex of `mesh` in its own box, scaled so that its RMS over the vertices is that of
/// eq. 6.18's supine force with the same constants (`k`'s `c7..c9`, the weights of
/// [`crate::orientation::exact_weights`] at supine). The precomputed mode never sees the scale (its
/// field is normalised to a unit volume); the orientation modes add eq. 6.18's change with posture
/// to this force, so the scale gives the posture the share of the force it has in the seed's model.
/// Used by the bake and by every mode that evaluates the force itself (direct), so all agree.
pub fn fitted_supine_force(
    mesh: &TriMesh,
    side: Side,
    k: &MotionConstants,
    field: &field::ForceField,
) -> Vec<f64> {
    let bb = mesh.aabb();
    let (lo, hi) = (
        DVec3::from(bb.min.map(|v| v as f64)),
        DVec3::from(bb.max.map(|v| v as f64)),
    );
    let mut f: Vec<f64> = mesh
        .positions
        .iter()
        .map(|p| field.value_in_box(DVec3::from(p.map(|v| v as f64)), lo, hi))
        .collect();
    let w = crate::orientation::exact_weights(
        [k.c[6], k.c[7], k.c[8]],
        side,
        crate::orientation::SUPINE_GRAVITY,
    );
    let (mut linear, mut fitted) = (0.0, 0.0);
    for (p, v) in mesh.positions.iter().zip(&f) {
        let n = normalised_position(*p, &bb, side);
        let l = w[0] + w[1] * n.x + w[2] * n.y + w[3] * n.z;
        linear += l * l;
        fitted += v * v;
    }
    if linear > 0.0 && fitted > 0.0 && (linear / fitted).is_finite() {
        let scale = (linear / fitted).sqrt();
        for v in &mut f {
            *v *= scale;
        }
    }
    f
}

/// Enclosed volume of `p + s·u` as an exact cubic in `s`: `V(s) = v0 + v1·s + v2·s² + v3·s³` (mm³).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeCubic {
    /// Coefficients `[v0, v1, v2, v3]`, mm³.
    pub coeffs: [f64; 4],
}

impl VolumeCubic {
    /// Coefficients for a closed mesh with per-vertex displacement `u`.
    pub fn of(mesh: &TriMesh, u: &[DVec3]) -> Self {
        let mut k = [0.0; 4];
        let p = |i: u32| DVec3::from(mesh.positions[i as usize].map(|v| v as f64));
        for t in &mesh.triangles {
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            let (ua, ub, uc) = (u[t[0] as usize], u[t[1] as usize], u[t[2] as usize]);
            k[0] += a.dot(b.cross(c));
            k[1] += ua.dot(b.cross(c)) + a.dot(ub.cross(c)) + a.dot(b.cross(uc));
            k[2] += ua.dot(ub.cross(c)) + ua.dot(b.cross(uc)) + a.dot(ub.cross(uc));
            k[3] += ua.dot(ub.cross(uc));
        }
        Self {
            coeffs: k.map(|v| v / 6.0),
        }
    }

    /// Volume at scale `s`, mm³.
    pub fn volume(&self, s: f64) -> f64 {
        let [v0, v1, v2, v3] = self.coeffs;
        v0 + s * (v1 + s * (v2 + s * v3))
    }

    fn slope(&self, s: f64) -> f64 {
        let [_, v1, v2, v3] = self.coeffs;
        v1 + s * (2.0 * v2 + s * 3.0 * v3)
    }

    /// The coefficients after scaling `u` by `k`.
    pub fn rescaled(&self, k: f64) -> Self {
        let [v0, v1, v2, v3] = self.coeffs;
        Self {
            coeffs: [v0, v1 * k, v2 * k * k, v3 * k * k * k],
        }
    }

    /// Scale `s` with `V(s) − V(0) = delta_mm3`, by a fixed number of guarded Newton steps from the
    /// linear guess (deterministic, bounded time, no allocation). Requires `v1 > 0`.
    pub fn solve_delta(&self, delta_mm3: f64) -> f64 {
        let v1 = self.coeffs[1];
        let mut s = delta_mm3 / v1;
        for _ in 0..12 {
            let slope = self.slope(s);
            if !(slope > 0.0) {
                // Outside the monotone range: the linear reading is the safe answer.
                return delta_mm3 / v1;
            }
            let step = (self.volume(s) - self.coeffs[0] - delta_mm3) / slope;
            s -= step;
            if step.abs() <= 1e-12 * (1.0 + s.abs()) {
                break;
            }
        }
        s
    }
}

fn check_constants(k: &MotionConstants) -> Result<(), DeformError> {
    // Exponents c2, c4, c6 must be ≥ 0 (x̂ = 0 occurs); the factors may carry a sign (a fitted
    // data set whose axes run the other way), the volume check catches a field that does not expand.
    if let Some((i, &v)) =
        k.c.iter()
            .enumerate()
            .find(|(i, v)| !(v.is_finite() && (![1, 3, 5].contains(i) || **v >= 0.0)))
    {
        return Err(DeformError::BadConstant {
            index: i + 1,
            value: v,
        });
    }
    Ok(())
}

/// One lung ready to deform: its mesh at FRC, its unit displacement field and its volume cubic.
#[derive(Debug, Clone)]
pub struct LungModel {
    /// Which lung.
    pub side: Side,
    /// Surface at the start (FRC) volume.
    pub mesh: TriMesh,
    /// Unit displacement per vertex, mm per unit of scale (one unit = [`UNIT_VOLUME_ML`] ml).
    pub unit_displacement: Vec<[f32; 3]>,
    /// Enclosed volume of `mesh + s·unit_displacement` as a cubic in `s`.
    pub cubic: VolumeCubic,
    /// Enclosed volume of `mesh`, ml.
    pub start_volume_ml: f64,
    /// Identity of the kernel file this model was loaded from ([`crate::kernel::KernelFile::id`]);
    /// 0 for a model built in memory.
    pub kernel_id: u64,
}

/// Errors building a deformation field.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DeformError {
    /// The displacement field does not increase the enclosed volume.
    #[error("the direction model does not expand the {side} lung (volume slope {slope_mm3} mm^3 per unit): check the motion constants and the mesh orientation")]
    DoesNotExpand {
        /// Lung.
        side: &'static str,
        /// dV/ds at s = 0.
        slope_mm3: f64,
    },
    /// A constant is not finite or negative where the model needs it positive.
    #[error("motion constant c{index} = {value} is invalid (must be finite; the exponents c2, c4, c6 also non-negative)")]
    BadConstant {
        /// 1-based index.
        index: usize,
        /// Value.
        value: f64,
    },
}

impl LungModel {
    /// Build the first-mode deformation of `mesh` (a closed, outward-wound lung surface): the eq. 6.18
    /// applied force used directly as each node's force, without the transfer pass.
    pub fn build(side: Side, mesh: TriMesh, k: &MotionConstants) -> Result<Self, DeformError> {
        check_constants(k)?;
        let bb = mesh.aabb();
        let force: Vec<f64> = mesh
            .positions
            .iter()
            .map(|&p| applied_force(normalised_position(p, &bb, side), k))
            .collect();
        Ok(Self::from_force(side, mesh, k, &force)?.0)
    }

    /// The model whose unit displacement is `F[i]·d_i` (EQUATIONS §2.4), scaled so the enclosed
    /// volume grows by exactly [`UNIT_VOLUME_ML`]. Returns the model, the unit directions and the
    /// scale applied to `F`.
    pub fn from_force(
        side: Side,
        mesh: TriMesh,
        k: &MotionConstants,
        force: &[f64],
    ) -> Result<(Self, Vec<[f32; 3]>, f64), DeformError> {
        check_constants(k)?;
        let bb = mesh.aabb();
        let dirs: Vec<DVec3> = mesh
            .positions
            .iter()
            .map(|&p| direction(normalised_position(p, &bb, side), k, side))
            .collect();
        Self::from_force_and_directions(side, mesh, dirs, force)
    }

    /// Directions from a fitted displacement field (normalised per vertex; the mesh's box is
    /// mapped onto the field's landmark box) instead of eq. 6.14–6.16.
    pub fn field_directions(mesh: &TriMesh, field: &field::Field) -> Vec<DVec3> {
        let bb = mesh.aabb();
        let (lo, hi) = (
            DVec3::from(bb.min.map(|v| v as f64)),
            DVec3::from(bb.max.map(|v| v as f64)),
        );
        mesh.positions
            .iter()
            .map(|&p| {
                let d = field.displacement_in_box(DVec3::from(p.map(|v| v as f64)), lo, hi);
                let len = d.length();
                if len > 1e-300 && len.is_finite() {
                    d / len
                } else {
                    DVec3::ZERO
                }
            })
            .collect()
    }

    /// The model whose unit displacement is `F[i]·d_i` for given unit directions `dirs`, scaled so the
    /// enclosed volume grows by exactly [`UNIT_VOLUME_ML`]. Returns the model, the directions and the
    /// scale applied to `F`.
    pub fn from_force_and_directions(
        side: Side,
        mesh: TriMesh,
        dirs: Vec<DVec3>,
        force: &[f64],
    ) -> Result<(Self, Vec<[f32; 3]>, f64), DeformError> {
        let raw: Vec<DVec3> = dirs.iter().zip(force).map(|(d, f)| *d * *f).collect();
        let cubic = VolumeCubic::of(&mesh, &raw);
        if !(cubic.coeffs[1] > 0.0) {
            return Err(DeformError::DoesNotExpand {
                side: side.name(),
                slope_mm3: cubic.coeffs[1],
            });
        }
        // Scale so the volume grows by exactly one unit volume at s = 1: V_raw(k) − V0 = unit.
        let unit_mm3 = UNIT_VOLUME_ML * 1000.0;
        let scale = cubic.solve_delta(unit_mm3);
        let unit_displacement: Vec<[f32; 3]> = raw
            .iter()
            .map(|d| (*d * scale).as_vec3().to_array())
            .collect();
        let model = Self::from_unit_displacement(side, mesh, unit_displacement);
        Ok((
            model,
            dirs.iter().map(|d| d.as_vec3().to_array()).collect(),
            scale,
        ))
    }

    /// The model for a stored unit displacement field (a loaded kernel); the volume cubic is
    /// computed from the f32 field, so run time matches what the GPU applies.
    pub fn from_unit_displacement(
        side: Side,
        mesh: TriMesh,
        unit_displacement: Vec<[f32; 3]>,
    ) -> Self {
        let u64s: Vec<DVec3> = unit_displacement
            .iter()
            .map(|u| DVec3::from(u.map(|v| v as f64)))
            .collect();
        let cubic = VolumeCubic::of(&mesh, &u64s);
        let start_volume_ml = cubic.coeffs[0] / 1000.0;
        Self {
            side,
            mesh,
            unit_displacement,
            cubic,
            start_volume_ml,
            kernel_id: 0,
        }
    }

    /// Deformation scale that makes the enclosed volume `start + delta_ml`.
    #[inline]
    pub fn scale_for_delta(&self, delta_ml: f64) -> f64 {
        self.cubic.solve_delta(delta_ml * 1000.0)
    }

    /// CPU reference of the GPU compute pass: `out[i] = p[i] + s·u[i]`, in f32 as on the GPU.
    pub fn deform_into(&self, scale: f32, out: &mut [[f32; 3]]) {
        // Flat f32 views: one multiply-add per coordinate, which the compiler vectorises.
        let out: &mut [f32] = bytemuck::cast_slice_mut(out);
        let p: &[f32] = bytemuck::cast_slice(&self.mesh.positions);
        let u: &[f32] = bytemuck::cast_slice(&self.unit_displacement);
        for ((o, p), u) in out.iter_mut().zip(p).zip(u) {
            *o = p + scale * u;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate;

    fn model(side: Side, n: usize) -> LungModel {
        LungModel::build(
            side,
            generate::lung(side, n).unwrap(),
            &MotionConstants::table_6_1(side),
        )
        .unwrap()
    }

    #[test]
    fn unit_scale_adds_exactly_one_unit_volume() {
        for side in [Side::Left, Side::Right] {
            let m = model(side, 5000);
            let mut out = vec![[0.0; 3]; m.mesh.positions.len()];
            m.deform_into(1.0, &mut out);
            let deformed = TriMesh {
                positions: out,
                triangles: m.mesh.triangles.clone(),
            };
            let dv = deformed.enclosed_volume_ml() - m.start_volume_ml;
            assert!(
                (dv - UNIT_VOLUME_ML).abs() < 1e-3 * UNIT_VOLUME_ML,
                "{side:?}: {dv}"
            );
        }
    }

    #[test]
    fn the_enclosed_volume_tracks_the_target_exactly_across_the_tidal_range() {
        let m = model(Side::Left, 5000);
        let mut out = vec![[0.0; 3]; m.mesh.positions.len()];
        for delta_ml in [0.0, 1.0, 50.0, 115.0, 229.0, 400.0] {
            let s = m.scale_for_delta(delta_ml);
            m.deform_into(s as f32, &mut out);
            let v = TriMesh {
                positions: out.clone(),
                triangles: m.mesh.triangles.clone(),
            }
            .enclosed_volume_ml();
            // f32 vertex storage limits agreement to about 1e-5 relative of the lung volume.
            assert!(
                (v - m.start_volume_ml - delta_ml).abs() < 0.05,
                "target +{delta_ml}: got +{}",
                v - m.start_volume_ml
            );
        }
    }

    #[test]
    fn the_linear_reading_misses_the_volume_at_tidal_range() {
        // Documents why the cubic is solved: s = ΔV/unit alone is measurably off at full tidal volume.
        let m = model(Side::Left, 5000);
        let delta = 229.0;
        let linear = delta / UNIT_VOLUME_ML;
        let err_ml = m.cubic.volume(linear) / 1000.0 - m.start_volume_ml - delta;
        assert!(err_ml.abs() > 0.5, "linear reading error {err_ml} ml");
    }

    #[test]
    fn directions_are_unit_and_point_lateral_anterior_inferior() {
        for side in [Side::Left, Side::Right] {
            let k = MotionConstants::table_6_1(side);
            let d = direction(DVec3::new(0.8, 0.5, 0.9), &k, side);
            assert!((d.length() - 1.0).abs() < 1e-12);
            assert_eq!(d.x.signum() as f32, side.lateral_sign());
            assert!(d.y > 0.0 && d.z < 0.0);
            assert_eq!(direction(DVec3::ZERO, &k, side), DVec3::ZERO);
        }
    }

    #[test]
    fn invalid_constants_are_refused() {
        let mesh = generate::lung(Side::Left, 1000).unwrap();
        let mut k = MotionConstants::table_6_1(Side::Left);
        k.c[3] = f64::NAN;
        assert!(matches!(
            LungModel::build(Side::Left, mesh.clone(), &k),
            Err(DeformError::BadConstant { index: 4, .. })
        ));
        let zero = MotionConstants { c: [0.0; 9] };
        assert!(matches!(
            LungModel::build(Side::Left, mesh, &zero),
            Err(DeformError::DoesNotExpand { .. })
        ));
    }

    #[test]
    fn scale_solve_is_monotone_and_finite_at_extremes() {
        let m = model(Side::Right, 2000);
        let mut last = f64::NEG_INFINITY;
        for i in 0..=200 {
            let s = m.scale_for_delta(i as f64 * 2.5);
            assert!(s.is_finite() && s > last);
            last = s;
        }
        assert_eq!(m.scale_for_delta(0.0), 0.0);
        assert!(m.scale_for_delta(-100.0) < 0.0);
        assert!(m.scale_for_delta(1e9).is_finite());
    }
}
