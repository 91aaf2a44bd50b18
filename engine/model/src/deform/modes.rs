//! # modes: the four deformation modes on the CPU, their volume forms, and smooth vertex normals
//!
//! Every mode moves vertex `i` to `p_i + s·D_i·k·d_i + o` (the precomputed mode: `p_i + s·u_i + o`),
//! where `D_i` is the elastostatic force at the node for the current orientation's applied force
//! `f = w0 + w·(x̂, ŷ, ẑ)` ([`crate::orientation`]), `k·d_i` the baked direction scaled to one unit
//! volume (EQUATIONS.md §2.4), `s` the scale that makes the enclosed volume the PV volume, and `o` the
//! lung's rigid offset. The modes differ in how `D_i` is obtained (EQUATIONS.md §3):
//!
//! | mode | `D_i` | per vertex | orientation |
//! |---|---|---|---|
//! | precomputed | baked for the supine force | 3 MACs | fixed |
//! | direct | eq. 7.1, `Σ_J f(J)·T(J, i)` over the stored rows | ≈ nnz/row MACs | any |
//! | sh | eq. 7.7, `Σ_k F_k·T^i_k` with `F_k = α·Σ_a w_a·P_ak` | n² MACs | any |
//! | basis | `Σ_a w_a·G_a(i)` (exact, EQUATIONS.md §3.3) | 4 MACs | any |
//!
//! The coefficients a frame carries ([`ipc_types::LungFrame::coeffs`]) are `w` for direct and basis,
//! `F_k` for sh, none for precomputed. [`CpuLung`] is the CPU implementation of all four (the
//! reference the GPU pass is tested against, and the evaluator of `lungdyn bench tradeoff`);
//! [`VertexTriangles`] gives smooth vertex normals from the deformed positions (area-weighted
//! face normals), as the GPU's normal pass does. [`VolumeForms`] make `s` exact for every
//! orientation with 84 multiply-adds per tick instead of a pass over the triangles.

// The scene file's names for this module's vocabulary are `lungdyn-scene`'s (the schema crate).
pub use lungdyn_scene::lungs::DeformMode;

use glam::DVec3;
use rayon::prelude::*;

use crate::deform::VolumeCubic;
use crate::kernel::TumourMeta;
pub use crate::kernel::VolumeForms;
use crate::mesh::TriMesh;
use crate::operator::Columns;

pub use super::sh_coeffs::{ShCoeffs, ShCoeffsError};

/// Vertices per parallel chunk of the CPU passes.
const CHUNK: usize = 8192;

/// Evaluation of the kernel's [`VolumeForms`] record (the record itself is file format,
/// `crate::kernel`).
impl VolumeForms {
    /// Forms for the four fields `fields[a][i]` (one displacement per vertex each).
    pub fn of(mesh: &TriMesh, fields: [&[DVec3]; 4]) -> Self {
        let p = |i: u32| DVec3::from(mesh.positions[i as usize].map(|v| v as f64));
        let mut out = Self {
            v0: 0.0,
            l: [0.0; 4],
            q: [[0.0; 4]; 4],
            c: [[[0.0; 4]; 4]; 4],
        };
        for t in &mesh.triangles {
            let (ia, ib, ic) = (t[0] as usize, t[1] as usize, t[2] as usize);
            let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
            out.v0 += a.dot(b.cross(c));
            let u = |f: usize, i: usize| fields[f][i];
            for x in 0..4 {
                let (ua, ub, uc) = (u(x, ia), u(x, ib), u(x, ic));
                out.l[x] += ua.dot(b.cross(c)) + a.dot(ub.cross(c)) + a.dot(b.cross(uc));
                for y in 0..4 {
                    let (vb, vc) = (u(y, ib), u(y, ic));
                    out.q[x][y] += ua.dot(vb.cross(c)) + ua.dot(b.cross(vc)) + a.dot(ub.cross(vc));
                    for z in 0..4 {
                        out.c[x][y][z] += ua.dot(vb.cross(u(z, ic)));
                    }
                }
            }
        }
        let sixth = |v: &mut f64| *v /= 6.0;
        sixth(&mut out.v0);
        out.l.iter_mut().for_each(sixth);
        out.q.iter_mut().flatten().for_each(sixth);
        out.c.iter_mut().flatten().flatten().for_each(sixth);
        out
    }

    /// The volume cubic in `s` for weights `w`. No allocation.
    #[inline]
    pub fn cubic(&self, w: &[f64; 4]) -> VolumeCubic {
        let mut v1 = 0.0;
        let mut v2 = 0.0;
        let mut v3 = 0.0;
        for x in 0..4 {
            v1 += w[x] * self.l[x];
            for y in 0..4 {
                let wxy = w[x] * w[y];
                v2 += wxy * self.q[x][y];
                for z in 0..4 {
                    v3 += wxy * w[z] * self.c[x][y][z];
                }
            }
        }
        VolumeCubic {
            coeffs: [self.v0, v1, v2, v3],
        }
    }

    /// Every number finite.
    pub fn is_finite(&self) -> bool {
        self.v0.is_finite()
            && self.l.iter().all(|v| v.is_finite())
            && self.q.iter().flatten().all(|v| v.is_finite())
            && self.c.iter().flatten().flatten().all(|v| v.is_finite())
    }
}

/// Triangles incident to each vertex (compressed rows), for smooth normals.
#[derive(Debug, Clone, PartialEq)]
pub struct VertexTriangles {
    /// Row offsets, `vertices + 1`.
    pub ptr: Vec<u32>,
    /// Incident triangle indices.
    pub tris: Vec<u32>,
}

impl VertexTriangles {
    /// The incidence of `triangles` over `n_vertices` vertices (indices must be in range).
    pub fn of(triangles: &[[u32; 3]], n_vertices: usize) -> Self {
        let mut ptr = vec![0u32; n_vertices + 1];
        for t in triangles {
            for &v in t {
                ptr[v as usize + 1] += 1;
            }
        }
        for i in 0..n_vertices {
            ptr[i + 1] += ptr[i];
        }
        let mut fill: Vec<u32> = ptr[..n_vertices].to_vec();
        let mut tris = vec![0u32; ptr[n_vertices] as usize];
        for (k, t) in triangles.iter().enumerate() {
            for &v in t {
                tris[fill[v as usize] as usize] = k as u32;
                fill[v as usize] += 1;
            }
        }
        Self { ptr, tris }
    }

    /// Smooth unit normals of the surface at `positions`: the normalised sum of the incident
    /// triangles' area vectors `(b − a) × (c − a)` (f32, as on the GPU). A vertex whose sum vanishes
    /// gets the zero vector (the fragment shader then shades it flat). Parallel, no allocation.
    pub fn normals_into(
        &self,
        triangles: &[[u32; 3]],
        positions: &[[f32; 3]],
        out: &mut [[f32; 3]],
    ) {
        out.par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(c, chunk)| {
                for (k, o) in chunk.iter_mut().enumerate() {
                    let i = c * CHUNK + k;
                    *o = vertex_normal(
                        &self.tris[self.ptr[i] as usize..self.ptr[i + 1] as usize],
                        triangles,
                        positions,
                    );
                }
            });
    }
}

/// The GPU's normal formula, in f32 (see [`VertexTriangles::normals_into`]).
#[inline]
pub fn vertex_normal(incident: &[u32], triangles: &[[u32; 3]], positions: &[[f32; 3]]) -> [f32; 3] {
    let mut n = glam::Vec3::ZERO;
    for &t in incident {
        let [a, b, c] = triangles[t as usize].map(|v| glam::Vec3::from(positions[v as usize]));
        n += (b - a).cross(c - a);
    }
    let len = n.length();
    if len > 1e-30 && len.is_finite() {
        (n / len).to_array()
    } else {
        [0.0; 3]
    }
}

/// What one mode needs per vertex beyond positions and directions.
#[derive(Debug, Clone)]
pub enum ModeData {
    /// The baked unit displacement `u_i`.
    Precomputed {
        /// `u_i`, mm per unit scale.
        unit: Vec<[f32; 3]>,
    },
    /// The basis responses `(G_0, G_x, G_y, G_z)` per vertex.
    Basis {
        /// Responses.
        g: Vec<[f32; 4]>,
    },
    /// The SH transfer coefficients, `n²` per vertex, as the run time holds them (16-bit, one scale
    /// per coefficient index: [`ShCoeffs`]).
    Sh {
        /// `T^i_k`, quantised.
        t: ShCoeffs,
    },
    /// The transfer rows as columns (eq. 7.1 gathers) and each node's `(1, x̂, ŷ, ẑ)`.
    Direct {
        /// `Tᵀ`.
        columns: Columns,
        /// `(1, x̂, ŷ, ẑ)` per node.
        nhat: Vec<[f32; 4]>,
        /// Scratch: the applied force per node.
        force: Vec<f32>,
        /// Scratch: the elastostatic force per node.
        elastostatic: Vec<f32>,
    },
}

impl ModeData {
    /// The mode this data serves.
    pub fn mode(&self) -> DeformMode {
        match self {
            ModeData::Precomputed { .. } => DeformMode::Precomputed,
            ModeData::Basis { .. } => DeformMode::Basis,
            ModeData::Sh { .. } => DeformMode::Sh,
            ModeData::Direct { .. } => DeformMode::Direct,
        }
    }
}

/// One lung deformed on the CPU in any mode: the test reference of the GPU pass and the evaluator
/// of the trade study. Per frame it allocates nothing.
#[derive(Debug, Clone)]
pub struct CpuLung {
    /// FRC positions, mm.
    pub positions: Vec<[f32; 3]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
    /// `k·d_i`: the direction scaled to one unit volume per unit of force (unused by precomputed).
    pub scaled_directions: Vec<[f32; 3]>,
    /// The mode's data.
    pub data: ModeData,
    /// Incident triangles, for normals.
    pub incidence: VertexTriangles,
}

/// The frame's coefficients do not fit the mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("{mode} mode needs {expected} coefficients, the frame has {found}")]
pub struct CoeffError {
    /// Mode.
    pub mode: DeformMode,
    /// Coefficients needed.
    pub expected: usize,
    /// Coefficients given.
    pub found: usize,
}

/// The tumour centre's response in each mode: evaluation of the kernel's [`TumourMeta`] record,
/// kept here with the modes it evaluates (the record itself is file format, `crate::kernel`).
impl TumourMeta {
    /// The centre's displacement per unit deformation scale in `mode` with the frame's
    /// coefficients (none for precomputed, 4 weights for basis/direct, `bands²` for SH); `None`
    /// when the coefficients do not fit the mode.
    pub fn displacement_mm(&self, mode: DeformMode, coeffs: &[f32]) -> Option<[f64; 3]> {
        use DeformMode as M;
        let rows: &[[f64; 3]] = match mode {
            M::Precomputed => return Some(self.precomputed_mm),
            M::Basis | M::Direct => &self.basis_mm,
            M::Sh => &self.sh_mm,
        };
        if rows.is_empty() || coeffs.len() != rows.len() {
            return None;
        }
        let mut d = [0.0; 3];
        for (r, &c) in rows.iter().zip(coeffs) {
            for a in 0..3 {
                d[a] += c as f64 * r[a];
            }
        }
        Some(d)
    }
}

/// Why a kernel cannot be deformed in a mode.
#[derive(Debug, thiserror::Error)]
pub enum ModeLoadError {
    /// A section could not be read or failed verification.
    #[error(transparent)]
    Kernel(#[from] crate::kernel::KernelError),
    /// The kernel's SH coefficients cannot be held (too many per vertex for a frame).
    #[error("{path}: {source}")]
    Sh {
        /// Kernel.
        path: String,
        /// Why.
        source: ShCoeffsError,
    },
    /// The kernel lacks the mode's data.
    #[error(
        "{path}: the kernel has no {what} for the {mode} mode (bake it again with this lungdyn)"
    )]
    Missing {
        /// Kernel.
        path: String,
        /// Mode.
        mode: DeformMode,
        /// What is missing.
        what: &'static str,
    },
}

impl CpuLung {
    /// The lung of `kernel` in `mode`, reading only the sections the mode needs.
    pub fn from_kernel(
        kernel: &crate::kernel::KernelFile,
        mode: DeformMode,
    ) -> Result<Self, ModeLoadError> {
        let missing = |what| ModeLoadError::Missing {
            path: kernel.path().display().to_string(),
            mode,
            what,
        };
        if mode != DeformMode::Precomputed && kernel.meta().orientation_predates_fitted_force() {
            return Err(missing(
                "orientation data of its fitted force (baked before the orientation modes drew it)",
            ));
        }
        let mesh = kernel.mesh();
        let k = kernel.meta().force_scale as f32;
        let scaled_directions = kernel
            .directions()
            .iter()
            .map(|d| d.map(|v| v * k))
            .collect();
        let data = match mode {
            DeformMode::Precomputed => ModeData::Precomputed {
                unit: kernel.unit_displacement().to_vec(),
            },
            DeformMode::Basis => ModeData::Basis {
                g: kernel
                    .basis_responses()?
                    .ok_or_else(|| missing("basis responses"))?
                    .to_vec(),
            },
            DeformMode::Sh => {
                let bands = kernel
                    .meta()
                    .sh
                    .as_ref()
                    .ok_or_else(|| missing("spherical harmonics"))?
                    .bands as usize;
                let t = kernel
                    .sh_coefficients()?
                    .ok_or_else(|| missing("spherical harmonics"))?;
                ModeData::Sh {
                    t: ShCoeffs::quantise(bands * bands, t).map_err(|source| {
                        ModeLoadError::Sh {
                            path: kernel.path().display().to_string(),
                            source,
                        }
                    })?,
                }
            }
            DeformMode::Direct => {
                let columns = kernel.transfer()?.transposed();
                let n = mesh.positions.len();
                ModeData::Direct {
                    columns,
                    nhat: force_basis(&mesh, kernel.meta()),
                    force: vec![0.0; n],
                    elastostatic: vec![0.0; n],
                }
            }
        };
        Ok(Self::new(mesh, scaled_directions, data))
    }

    /// A lung from its FRC mesh, `k·d_i` and the mode's data.
    ///
    /// # Panics
    /// If SH data holds another number of vertices than the mesh (a kernel's sections are checked
    /// against each other when it is opened).
    ///
    /// Subnormal per-vertex values are flushed to zero here, once: they displace a vertex by less
    /// than 1e-38 mm, and on x86 every arithmetic operation on one costs about a hundred cycles
    /// (measured: a basis pass with half its responses subnormal went from 0.75 to 17.5 ms at 400k
    /// vertices, `cargo bench -p lungdyn-bench --bench modes_cpu`). Baked kernels have had none.
    pub fn new(mesh: TriMesh, mut scaled_directions: Vec<[f32; 3]>, mut data: ModeData) -> Self {
        fn flush(v: &mut [f32]) {
            for x in v.iter_mut().filter(|x| x.is_subnormal()) {
                *x = 0.0;
            }
        }
        flush(scaled_directions.as_flattened_mut());
        match &mut data {
            ModeData::Precomputed { unit } => flush(unit.as_flattened_mut()),
            ModeData::Basis { g } => flush(g.as_flattened_mut()),
            // Quantised at construction: 16-bit integers and normal (or zero) scales.
            ModeData::Sh { .. } => {}
            ModeData::Direct { columns, nhat, .. } => {
                columns.flush_subnormals();
                flush(nhat.as_flattened_mut());
            }
        }
        if let ModeData::Sh { t } = &data {
            assert_eq!(
                t.vertices(),
                mesh.positions.len(),
                "spherical-harmonic coefficients for {} vertices, the mesh has {}",
                t.vertices(),
                mesh.positions.len()
            );
        }
        let incidence = VertexTriangles::of(&mesh.triangles, mesh.positions.len());
        Self {
            positions: mesh.positions,
            triangles: mesh.triangles,
            scaled_directions,
            data,
            incidence,
        }
    }

    /// Vertices.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// No vertices.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Coefficients a frame must carry for this mode.
    pub fn coeff_count(&self) -> usize {
        match &self.data {
            ModeData::Precomputed { .. } => 0,
            ModeData::Basis { .. } | ModeData::Direct { .. } => 4,
            ModeData::Sh { t } => t.n_coeffs(),
        }
    }

    /// Deformed positions for scale `s`, coefficients `coeffs` (weights or SH force coefficients, as
    /// [`DeformMode::coeff_kind`]) and rigid offset, into `out` (one per vertex). f32 throughout, as
    /// the GPU; parallel over vertices.
    pub fn deform_into(
        &mut self,
        s: f32,
        coeffs: &[f32],
        offset: [f32; 3],
        out: &mut [[f32; 3]],
    ) -> Result<(), CoeffError> {
        let need = self.coeff_count();
        if coeffs.len() != need {
            return Err(CoeffError {
                mode: self.data.mode(),
                expected: need,
                found: coeffs.len(),
            });
        }
        let p = &self.positions;
        let kd = &self.scaled_directions;
        match &mut self.data {
            ModeData::Precomputed { unit } => {
                out.par_chunks_mut(CHUNK)
                    .zip(p.par_chunks(CHUNK))
                    .zip(unit.par_chunks(CHUNK))
                    .for_each(|((out, p), u)| {
                        for ((o, p), u) in out.iter_mut().zip(p).zip(u) {
                            *o = moved(p, s, u, &offset);
                        }
                    });
            }
            ModeData::Basis { g } => {
                let w = [coeffs[0], coeffs[1], coeffs[2], coeffs[3]];
                out.par_chunks_mut(CHUNK)
                    .zip(p.par_chunks(CHUNK))
                    .zip(g.par_chunks(CHUNK))
                    .zip(kd.par_chunks(CHUNK))
                    .for_each(|(((out, p), g), kd)| {
                        for (((o, p), g), kd) in out.iter_mut().zip(p).zip(g).zip(kd) {
                            let d = w[0] * g[0] + w[1] * g[1] + w[2] * g[2] + w[3] * g[3];
                            *o = moved(p, s * d, kd, &offset);
                        }
                    });
            }
            ModeData::Sh { t } => t.deform_into(p, kd, s, coeffs, &offset, out),
            ModeData::Direct {
                columns,
                nhat,
                force,
                elastostatic,
            } => {
                let w = [coeffs[0], coeffs[1], coeffs[2], coeffs[3]];
                force
                    .par_chunks_mut(CHUNK)
                    .zip(nhat.par_chunks(CHUNK))
                    .for_each(|(f, n)| {
                        for (f, n) in f.iter_mut().zip(n) {
                            *f = w[0] * n[0] + w[1] * n[1] + w[2] * n[2] + w[3] * n[3];
                        }
                    });
                columns.apply_into(force, elastostatic);
                out.par_chunks_mut(CHUNK)
                    .zip(p.par_chunks(CHUNK))
                    .zip(elastostatic.par_chunks(CHUNK))
                    .zip(kd.par_chunks(CHUNK))
                    .for_each(|(((out, p), e), kd)| {
                        for (((o, p), e), kd) in out.iter_mut().zip(p).zip(e).zip(kd) {
                            *o = moved(p, s * e, kd, &offset);
                        }
                    });
            }
        }
        Ok(())
    }

    /// Smooth vertex normals of `deformed` (this lung's deformed positions).
    pub fn normals_into(&self, deformed: &[[f32; 3]], out: &mut [[f32; 3]]) {
        self.incidence.normals_into(&self.triangles, deformed, out);
    }
}

/// `p + amount·dir + offset`, the one multiply-add per coordinate every mode ends with.
#[inline(always)]
fn moved(p: &[f32; 3], amount: f32, dir: &[f32; 3], offset: &[f32; 3]) -> [f32; 3] {
    [
        p[0] + amount * dir[0] + offset[0],
        p[1] + amount * dir[1] + offset[1],
        p[2] + amount * dir[2] + offset[2],
    ]
}

/// `(1, x̂, ŷ, ẑ)` of every vertex (the box coordinates of eq. 6.14–6.18 in the mesh's own box).
pub fn box_coordinates(mesh: &TriMesh, side: crate::mesh::Side) -> Vec<[f32; 4]> {
    let bb = mesh.aabb();
    mesh.positions
        .iter()
        .map(|&p| {
            let n = super::normalised_position(p, &bb, side);
            [1.0, n.x as f32, n.y as f32, n.z as f32]
        })
        .collect()
}

/// The force's basis functions at every vertex, as the kernel's orientation modes were baked with
/// them: [`box_coordinates`], with the first replaced by the fitted supine force
/// ([`super::fitted_supine_force`]) when the kernel carries one
/// ([`crate::kernel::OrientationMeta::fitted_supine_force`]).
pub fn force_basis(mesh: &TriMesh, meta: &crate::kernel::KernelMeta) -> Vec<[f32; 4]> {
    let mut nhat = box_coordinates(mesh, meta.side);
    let fitted = meta
        .orientation
        .as_ref()
        .is_some_and(|o| o.fitted_supine_force);
    if let (true, Some(field)) = (fitted, &meta.settings.force_field) {
        let f = super::fitted_supine_force(mesh, meta.side, &meta.settings.motion, field);
        for (n, f) in nhat.iter_mut().zip(f) {
            n[0] = f as f32;
        }
    }
    nhat
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{generate, Side};

    #[test]
    fn subnormal_data_is_flushed_at_load_and_the_result_is_unchanged_beyond_them() {
        let mesh = TriMesh {
            positions: vec![[0.0; 3], [1.0, 0.0, 0.0]],
            triangles: Vec::new(),
        };
        let tiny = f32::MIN_POSITIVE / 4.0;
        assert!(tiny.is_subnormal());
        let mut lung = CpuLung::new(
            mesh,
            vec![[1.0, tiny, 0.0], [0.0, 1.0, 0.0]],
            ModeData::Basis {
                g: vec![[0.5, tiny, -tiny, 0.25], [tiny, 1.0, 0.0, 0.0]],
            },
        );
        let ModeData::Basis { g } = &lung.data else {
            unreachable!()
        };
        assert!(g.iter().flatten().all(|x| !x.is_subnormal()));
        assert!(lung
            .scaled_directions
            .iter()
            .flatten()
            .all(|x| !x.is_subnormal()));
        let mut out = [[0.0f32; 3]; 2];
        lung.deform_into(2.0, &[1.0, 1.0, 1.0, 1.0], [0.0; 3], &mut out)
            .unwrap();
        // d_0 = 0.5 + 0.25 = 0.75 → 2·0.75 along (1, 0, 0); d_1 = 1 → 2 along (0, 1, 0).
        assert_eq!(out, [[1.5, 0.0, 0.0], [1.0, 2.0, 0.0]]);
    }

    #[test]
    fn forms_reproduce_the_cubic_of_the_combined_field() {
        let mesh = generate::lung(Side::Left, 800).unwrap();
        let n = mesh.positions.len();
        let fields: Vec<Vec<DVec3>> = (0..4)
            .map(|a| {
                mesh.positions
                    .iter()
                    .enumerate()
                    .map(|(i, p)| {
                        DVec3::new(
                            (p[0] as f64 * 0.01 + a as f64).sin(),
                            (i as f64 * 0.37 + a as f64).cos(),
                            0.3 * a as f64 - 0.5,
                        )
                    })
                    .collect()
            })
            .collect();
        let forms = VolumeForms::of(&mesh, [&fields[0], &fields[1], &fields[2], &fields[3]]);
        for w in [
            [0.0, 0.01, 0.95, 0.07],
            [0.3, -0.2, 0.1, 0.9],
            [1.0, 0.0, 0.0, 0.0],
        ] {
            let u: Vec<DVec3> = (0..n)
                .map(|i| (0..4).map(|a| fields[a][i] * w[a]).sum())
                .collect();
            let direct = VolumeCubic::of(&mesh, &u);
            let via = forms.cubic(&w);
            for k in 0..4 {
                let scale = direct.coeffs[k].abs().max(1.0);
                assert!(
                    (direct.coeffs[k] - via.coeffs[k]).abs() < 1e-9 * scale,
                    "w {w:?} k {k}: {} vs {}",
                    direct.coeffs[k],
                    via.coeffs[k]
                );
            }
        }
    }

    #[test]
    fn normals_of_a_sphere_point_outwards() {
        let mesh = generate::lung(Side::Right, 2000).unwrap();
        let inc = VertexTriangles::of(&mesh.triangles, mesh.positions.len());
        let mut n = vec![[0.0; 3]; mesh.positions.len()];
        inc.normals_into(&mesh.triangles, &mesh.positions, &mut n);
        let centroid = mesh
            .positions
            .iter()
            .fold(glam::Vec3::ZERO, |a, p| a + glam::Vec3::from(*p))
            / mesh.positions.len() as f32;
        let outward = n
            .iter()
            .zip(&mesh.positions)
            .filter(|(n, p)| glam::Vec3::from(**n).dot(glam::Vec3::from(**p) - centroid) > 0.0)
            .count();
        assert!(
            outward as f64 > 0.9 * n.len() as f64,
            "{outward} of {}",
            n.len()
        );
        assert!(n.iter().all(|v| {
            let l = glam::Vec3::from(*v).length();
            (l - 1.0).abs() < 1e-5
        }));
        // A degenerate (zero-area) neighbourhood gives zero, never NaN.
        let flat = vec![[0.0f32; 3]; mesh.positions.len()];
        inc.normals_into(&mesh.triangles, &flat, &mut n);
        assert!(n.iter().all(|v| *v == [0.0; 3]));
    }

    #[test]
    fn modes_parse_and_name_round_trip() {
        for m in DeformMode::ALL {
            assert_eq!(m.name().parse::<DeformMode>().unwrap(), m);
        }
        assert!("fast"
            .parse::<DeformMode>()
            .unwrap_err()
            .contains("precomputed"));
    }
}
