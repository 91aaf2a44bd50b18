//! # sh_coeffs: eq. 7.7's transfer coefficients as the run time holds them
//!
//! The kernel stores `T^i_k` (seed eq. 7.4) as f32, `n²` per vertex. Per frame, eq. 7.7 reads all of
//! them: at 16 coefficients that is 64 of the 100 bytes a vertex costs, and the pass is bound by
//! those bytes, not by its 16 multiply-adds. At load the run time therefore holds them as signed
//! 16-bit integers with one scale per coefficient index (EQUATIONS.md §3.2, "run-time storage"):
//!
//! ```text
//!   scale_k = max_i |T^i_k|,     q^i_k = round(32767 · T^i_k / scale_k),     T^i_k ≈ q^i_k · scale_k / 32767
//! ```
//!
//! so each coefficient is within `scale_k / 65534` of the kernel's (≈ 1.5e-5 of its largest value;
//! the truncation to `n` bands leaves errors of percent). The scales fold into the frame's force
//! coefficients, `c'_k = s·F_k·scale_k / 32767`, so a vertex still costs `n²` multiply-adds, now on
//! 2 bytes each. The GPU reads the same integers as `snorm16` pairs (`unpack2x16snorm` gives
//! `q / 32767`) and folds the same scales, so CPU and GPU draw the same numbers to rounding
//! (measured 1.2e-7 relative on lavapipe, tested to 1e-5: `tests/tests/modes_gpu.rs`). The bytes
//! above are the CPU's traffic (68 instead of 100 per vertex at 16 coefficients); the GPU reads
//! positions and directions as vec4s, 80 instead of 112.
//!
//! On the CPU the integers are laid out in blocks of [`SH_BLOCK`] vertices, coefficient-major inside
//! a block (`q[(b·n + k)·8 + j]` for vertex `8b + j`), so the dot products run across eight vertices
//! at once; the tail block is padded with zeros. Measured at 400k vertices and 16 coefficients on
//! the 2-core VM (`cargo bench -p lungdyn-bench --bench modes_cpu`): see that bench and
//! docs/tradeoff.md.
//!
//! The kernel keeps the f32 values: the quantisation is a pure function of them (bit-exact replay
//! holds), and `lungdyn bake` reports both errors, eq. 7.7 as drawn (quantised) against eq. 7.1 and
//! the quantisation alone (`sh_quantisation_max_mm`).

use rayon::prelude::*;

/// Vertices per block of the CPU layout (eight f32 lanes: two SSE or one AVX register).
pub const SH_BLOCK: usize = 8;

/// The integer that stands for `scale_k` (`snorm16`: `q / 32767 ∈ [−1, 1]`).
pub const SH_Q_MAX: f32 = 32767.0;

/// Most coefficients per vertex: what a frame carries (`ipc_types::MAX_COEFFS`, 8 bands).
pub const SH_MAX_COEFFS: usize = ipc_types::MAX_COEFFS;

/// Vertices per parallel chunk (a whole number of blocks).
const CHUNK: usize = 8192;
const _: () = assert!(CHUNK % SH_BLOCK == 0);

/// Why coefficients cannot be held.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ShCoeffsError {
    /// Not 1 to 64 per vertex.
    #[error("{0} spherical-harmonic coefficients per vertex: a frame carries 1 to {SH_MAX_COEFFS} (8 bands)")]
    Count(usize),
    /// The array is not a whole number of vertices.
    #[error("{values} spherical-harmonic coefficients are not a whole number of vertices at {n_coeffs} each")]
    Length {
        /// Values given.
        values: usize,
        /// Per vertex.
        n_coeffs: usize,
    },
    /// A value is NaN or infinite (a verified kernel has none).
    #[error("spherical-harmonic coefficient {index} is {value}, not a finite number")]
    NotFinite {
        /// Index in the row-major array.
        index: usize,
        /// The value.
        value: f32,
    },
}

/// `T^i_k` quantised to 16 bits with one scale per `k` (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct ShCoeffs {
    n_coeffs: usize,
    vertices: usize,
    /// `scale_k`: the largest `|T^i_k|` over the lung (0 where all are 0 or subnormal).
    scale: Vec<f32>,
    /// Blocks of [`SH_BLOCK`] vertices, coefficient-major inside a block.
    q: Vec<i16>,
}

impl ShCoeffs {
    /// Quantise `t` (row-major, `n_coeffs` per vertex, as the kernel stores it).
    pub fn quantise(n_coeffs: usize, t: &[f32]) -> Result<Self, ShCoeffsError> {
        if n_coeffs == 0 || n_coeffs > SH_MAX_COEFFS {
            return Err(ShCoeffsError::Count(n_coeffs));
        }
        if t.len() % n_coeffs != 0 {
            return Err(ShCoeffsError::Length {
                values: t.len(),
                n_coeffs,
            });
        }
        if let Some((index, &value)) = t.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(ShCoeffsError::NotFinite { index, value });
        }
        let vertices = t.len() / n_coeffs;
        let mut scale = vec![0.0f32; n_coeffs];
        for row in t.chunks_exact(n_coeffs) {
            for (s, v) in scale.iter_mut().zip(row) {
                *s = s.max(v.abs());
            }
        }
        // A coefficient index whose largest value is subnormal moves no vertex by more than 1e-38 mm;
        // folded into a frame's coefficients it would make every multiply a slow subnormal one.
        for s in &mut scale {
            if *s < f32::MIN_POSITIVE {
                *s = 0.0;
            }
        }
        let mut q = vec![0i16; vertices.div_ceil(SH_BLOCK) * SH_BLOCK * n_coeffs];
        for (i, row) in t.chunks_exact(n_coeffs).enumerate() {
            let (b, j) = (i / SH_BLOCK, i % SH_BLOCK);
            for (k, (&v, &s)) in row.iter().zip(&scale).enumerate() {
                q[(b * n_coeffs + k) * SH_BLOCK + j] = quantise_one(v, s);
            }
        }
        Ok(Self {
            n_coeffs,
            vertices,
            scale,
            q,
        })
    }

    /// Coefficients per vertex.
    pub fn n_coeffs(&self) -> usize {
        self.n_coeffs
    }

    /// Bands (`n_coeffs = n_bands²`).
    pub fn n_bands(&self) -> usize {
        self.n_coeffs.isqrt()
    }

    /// Vertices.
    pub fn vertices(&self) -> usize {
        self.vertices
    }

    /// `scale_k` per coefficient index.
    pub fn scale(&self) -> &[f32] {
        &self.scale
    }

    /// `q^i_k`.
    ///
    /// # Panics
    /// If `i` or `k` is out of range.
    pub fn quantised(&self, i: usize, k: usize) -> i16 {
        assert!(
            i < self.vertices && k < self.n_coeffs,
            "vertex {i}, coefficient {k}"
        );
        self.q[((i / SH_BLOCK) * self.n_coeffs + k) * SH_BLOCK + i % SH_BLOCK]
    }

    /// The value the run time uses for `T^i_k`, `q·scale_k/32767`, in f64.
    pub fn value(&self, i: usize, k: usize) -> f64 {
        self.quantised(i, k) as f64 * self.scale[k] as f64 / SH_Q_MAX as f64
    }

    /// Bytes the run time holds per vertex for the coefficients (2 per coefficient).
    pub fn bytes_per_vertex(&self) -> usize {
        2 * self.n_coeffs
    }

    /// 32-bit words per vertex in the GPU layout ([`Self::gpu_words`]).
    pub fn gpu_words_per_vertex(&self) -> usize {
        self.n_coeffs.div_ceil(2)
    }

    /// The GPU layout: per vertex, in vertex order, [`Self::gpu_words_per_vertex`] words of two
    /// `snorm16` each (coefficient `2m` in the low half, `2m + 1` in the high half, a zero pad after
    /// an odd count), as WGSL's `unpack2x16snorm` reads them.
    pub fn gpu_words(&self) -> Vec<u32> {
        let w = self.gpu_words_per_vertex();
        let mut out = Vec::with_capacity(self.vertices * w);
        for i in 0..self.vertices {
            for m in 0..w {
                let lo = self.quantised(i, 2 * m) as u16 as u32;
                let hi = if 2 * m + 1 < self.n_coeffs {
                    self.quantised(i, 2 * m + 1) as u16 as u32
                } else {
                    0
                };
                out.push(lo | (hi << 16));
            }
        }
        out
    }

    /// A frame's force coefficients `F_k` at scale `s` with the scales folded in:
    /// `s·F_k·scale_k/32767` (subnormal results flushed to zero, as at load).
    pub fn folded(&self, s: f32, coeffs: &[f32]) -> [f32; SH_MAX_COEFFS] {
        let mut c = [0.0f32; SH_MAX_COEFFS];
        for ((c, &f), &scale) in c.iter_mut().zip(coeffs).zip(&self.scale) {
            let v = s * f * (scale / SH_Q_MAX);
            *c = if v.is_subnormal() { 0.0 } else { v };
        }
        c
    }

    /// Eq. 7.7 for every vertex, `out_i = p_i + (Σ_k c'_k·q^i_k)·kd_i + offset` with `c'` from
    /// [`Self::folded`]; parallel over chunks of vertices, no allocation.
    ///
    /// # Panics
    /// If `p`, `kd` and `out` do not all have [`Self::vertices`] entries or `coeffs` has fewer than
    /// [`Self::n_coeffs`] (the caller checks the count: [`crate::deform::modes::CpuLung::deform_into`]).
    pub fn deform_into(
        &self,
        p: &[[f32; 3]],
        kd: &[[f32; 3]],
        s: f32,
        coeffs: &[f32],
        offset: &[f32; 3],
        out: &mut [[f32; 3]],
    ) {
        assert!(
            p.len() == self.vertices
                && kd.len() == self.vertices
                && out.len() == self.vertices
                && coeffs.len() >= self.n_coeffs,
            "one position, direction and output per vertex and {} coefficients",
            self.n_coeffs
        );
        let c = self.folded(s, coeffs);
        let c = &c[..self.n_coeffs];
        // One body, specialised for the band counts a kernel can have (n = bands²): with `n` a
        // constant the coefficient loop unrolls and the eight lanes stay in registers.
        match self.n_coeffs {
            1 => blocks(1, &self.q, c, p, kd, offset, out),
            4 => blocks(4, &self.q, c, p, kd, offset, out),
            9 => blocks(9, &self.q, c, p, kd, offset, out),
            16 => blocks(16, &self.q, c, p, kd, offset, out),
            25 => blocks(25, &self.q, c, p, kd, offset, out),
            36 => blocks(36, &self.q, c, p, kd, offset, out),
            49 => blocks(49, &self.q, c, p, kd, offset, out),
            64 => blocks(64, &self.q, c, p, kd, offset, out),
            n => blocks(n, &self.q, c, p, kd, offset, out),
        }
    }
}

/// `round(32767·v/scale)`; `|v| ≤ scale`, so the result is within ±32767.
fn quantise_one(v: f32, scale: f32) -> i16 {
    if scale == 0.0 {
        0
    } else {
        (v as f64 / scale as f64 * SH_Q_MAX as f64).round() as i16
    }
}

#[inline(always)]
fn blocks(
    n: usize,
    q: &[i16],
    c: &[f32],
    p: &[[f32; 3]],
    kd: &[[f32; 3]],
    offset: &[f32; 3],
    out: &mut [[f32; 3]],
) {
    let offsets: [f32; 3 * SH_BLOCK] = std::array::from_fn(|i| offset[i % 3]);
    out.par_chunks_mut(CHUNK)
        .zip(p.par_chunks(CHUNK))
        .zip(q.par_chunks(CHUNK * n))
        .zip(kd.par_chunks(CHUNK))
        .for_each(|(((out, p), q), kd)| {
            for (((o, p), q), kd) in out
                .chunks_mut(SH_BLOCK)
                .zip(p.chunks(SH_BLOCK))
                .zip(q.chunks_exact(SH_BLOCK * n))
                .zip(kd.chunks(SH_BLOCK))
            {
                let mut d = [0.0f32; SH_BLOCK];
                for (qk, &ck) in q.chunks_exact(SH_BLOCK).zip(c) {
                    let qk: &[i16; SH_BLOCK] = qk.try_into().expect("a block");
                    for j in 0..SH_BLOCK {
                        d[j] += qk[j] as f32 * ck;
                    }
                }
                if let (Ok(o), Ok(p), Ok(kd)) = (
                    <&mut [[f32; 3]; SH_BLOCK]>::try_from(&mut *o),
                    <&[[f32; 3]; SH_BLOCK]>::try_from(p),
                    <&[[f32; 3]; SH_BLOCK]>::try_from(kd),
                ) {
                    // A whole block as 24 flat floats, so the move vectorises too.
                    let mut dd = [0.0f32; 3 * SH_BLOCK];
                    for j in 0..SH_BLOCK {
                        dd[3 * j..3 * j + 3].fill(d[j]);
                    }
                    let (o, p, kd) = (o.as_flattened_mut(), p.as_flattened(), kd.as_flattened());
                    for i in 0..3 * SH_BLOCK {
                        o[i] = p[i] + dd[i] * kd[i] + offsets[i];
                    }
                } else {
                    // The tail block: the same arithmetic, vertex by vertex.
                    for (((o, p), kd), d) in o.iter_mut().zip(p).zip(kd).zip(d) {
                        for a in 0..3 {
                            o[a] = p[a] + d * kd[a] + offset[a];
                        }
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{RngExt, SeedableRng};
    use rand_xorshift::XorShiftRng;

    /// `n` seeded values in [−1, 1).
    fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut r = XorShiftRng::seed_from_u64(seed);
        (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect()
    }

    /// Eq. 7.7 in f64 from the values the run time holds.
    fn reference(
        sh: &ShCoeffs,
        p: &[[f32; 3]],
        kd: &[[f32; 3]],
        s: f32,
        c: &[f32],
        o: [f32; 3],
    ) -> Vec<[f64; 3]> {
        (0..sh.vertices())
            .map(|i| {
                let d: f64 = (0..sh.n_coeffs())
                    .map(|k| sh.value(i, k) * c[k] as f64)
                    .sum::<f64>()
                    * s as f64;
                std::array::from_fn(|a| p[i][a] as f64 + d * kd[i][a] as f64 + o[a] as f64)
            })
            .collect()
    }

    #[test]
    fn every_value_is_within_half_a_step_of_the_kernels_and_the_largest_is_exact() {
        for n in [1usize, 4, 9, 16, 25, 36, 49, 64, 7] {
            let v = 37; // four whole blocks and a tail of five
            let mut t = values(v * n, n as u64 + 3);
            t[5 % n] = 3.5; // one large value (vertex 0): its index's scale
            let sh = ShCoeffs::quantise(n, &t).unwrap();
            assert_eq!(sh.vertices(), v);
            for i in 0..v {
                for k in 0..n {
                    let want = t[i * n + k] as f64;
                    let step = sh.scale()[k] as f64 / SH_Q_MAX as f64;
                    assert!(
                        (sh.value(i, k) - want).abs() <= 0.5 * step * (1.0 + 1e-6),
                        "n {n}, vertex {i}, k {k}: {} vs {want}",
                        sh.value(i, k)
                    );
                }
            }
            assert_eq!(sh.quantised(0, 5 % n), 32767);
            assert_eq!(sh.value(0, 5 % n), 3.5);
        }
    }

    #[test]
    fn the_pass_is_eq_7_7_on_the_held_values_for_every_band_count_and_a_tail() {
        for n in [1usize, 4, 9, 16, 25, 36, 49, 64, 10] {
            for v in [1usize, 8, 13, 8200, 8203, 16393] {
                let t = values(v * n, 11 + n as u64);
                let sh = ShCoeffs::quantise(n, &t).unwrap();
                let p: Vec<[f32; 3]> = values(3 * v, 5)
                    .chunks_exact(3)
                    .map(|c| [c[0] * 90.0, c[1] * 90.0, c[2] * 90.0])
                    .collect();
                let kd: Vec<[f32; 3]> = values(3 * v, 6)
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect();
                let c = values(n, 7);
                let (s, o) = (1.7f32, [0.5f32, -0.25, 1.0]);
                let mut out = vec![[f32::NAN; 3]; v];
                sh.deform_into(&p, &kd, s, &c, &o, &mut out);
                let want = reference(&sh, &p, &kd, s, &c, o);
                // f32 sums of n products of magnitude ≤ 1.7·1·1: round-off ≈ n·1e-7 of 90 mm.
                for (i, (g, w)) in out.iter().zip(&want).enumerate() {
                    for a in 0..3 {
                        assert!(
                            (g[a] as f64 - w[a]).abs() <= 1e-4 * (1.0 + n as f64 / 16.0),
                            "n {n}, v {v}, vertex {i}: {g:?} vs {w:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_gpu_words_hold_the_same_integers_as_snorm16_pairs() {
        for n in [1usize, 9, 16] {
            let t = values(11 * n, 21);
            let sh = ShCoeffs::quantise(n, &t).unwrap();
            let w = sh.gpu_words();
            assert_eq!(w.len(), 11 * n.div_ceil(2));
            for i in 0..11 {
                for k in 0..n {
                    let word = w[i * sh.gpu_words_per_vertex() + k / 2];
                    let half = if k % 2 == 0 {
                        word & 0xffff
                    } else {
                        word >> 16
                    } as u16 as i16;
                    assert_eq!(half, sh.quantised(i, k));
                    // Never −32768, where `unpack2x16snorm` clamps: the value is q/32767.
                    assert!(half >= -32767);
                }
                if n % 2 == 1 {
                    assert_eq!(
                        w[i * sh.gpu_words_per_vertex() + n / 2] >> 16,
                        0,
                        "the pad is zero"
                    );
                }
            }
        }
    }

    #[test]
    fn extremes_give_an_error_or_finite_values_never_nan() {
        assert_eq!(ShCoeffs::quantise(0, &[]), Err(ShCoeffsError::Count(0)));
        assert_eq!(
            ShCoeffs::quantise(65, &[0.0; 65]),
            Err(ShCoeffsError::Count(65))
        );
        assert_eq!(
            ShCoeffs::quantise(4, &[0.0; 6]),
            Err(ShCoeffsError::Length {
                values: 6,
                n_coeffs: 4
            })
        );
        let e = ShCoeffs::quantise(2, &[0.0, f32::NAN]).unwrap_err();
        assert!(
            matches!(e, ShCoeffsError::NotFinite { index: 1, .. }),
            "{e}"
        );
        assert!(ShCoeffs::quantise(1, &[f32::INFINITY]).is_err());
        // No vertices, all zeros, subnormal only, and the f32 extremes.
        let empty = ShCoeffs::quantise(16, &[]).unwrap();
        empty.deform_into(&[], &[], 1.0, &[0.0; 16], &[0.0; 3], &mut []);
        let zeros = ShCoeffs::quantise(4, &[0.0; 12]).unwrap();
        assert_eq!(zeros.scale(), &[0.0; 4]);
        let tiny = ShCoeffs::quantise(1, &[1e-40, -1e-41]).unwrap();
        assert_eq!((tiny.scale()[0], tiny.quantised(0, 0)), (0.0, 0));
        // Huge beside tiny in one index: the tiny one is below half a step, so it is 0.
        let huge = ShCoeffs::quantise(2, &[1e30, -1e30, 1.0, f32::MIN_POSITIVE]).unwrap();
        assert_eq!(huge.quantised(0, 0), 32767);
        assert_eq!(huge.quantised(0, 1), -32767);
        assert_eq!((huge.quantised(1, 0), huge.quantised(1, 1)), (0, 0));
        let mut out = [[0.0f32; 3]; 2];
        huge.deform_into(
            &[[1.0; 3]; 2],
            &[[1.0; 3]; 2],
            1.0,
            &[1.0, 1.0],
            &[0.0; 3],
            &mut out,
        );
        assert!(out.iter().flatten().all(|v| v.is_finite()), "{out:?}");
        assert_eq!(out[1], [1.0; 3]);
        // Folded coefficients that would be subnormal are zero.
        assert_eq!(tiny.folded(1.0, &[1.0])[0], 0.0);
        let small = ShCoeffs::quantise(1, &[1e-30]).unwrap();
        assert_eq!(small.folded(1e-5, &[1e-5])[0], 0.0);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// Quantising what was quantised gives the same integers and scales (a round trip).
        #[test]
        fn quantising_the_held_values_again_changes_nothing(
            n in 1usize..=64, v in 0usize..40, seed in 1u64..1000, mag in -30i32..30
        ) {
            let m = 2f32.powi(mag);
            let t: Vec<f32> = values(n * v, seed).iter().map(|x| x * m).collect();
            let a = ShCoeffs::quantise(n, &t).unwrap();
            let back: Vec<f32> = (0..v)
                .flat_map(|i| (0..n).map(move |k| (i, k)))
                .map(|(i, k)| a.value(i, k) as f32)
                .collect();
            let b = ShCoeffs::quantise(n, &back).unwrap();
            prop_assert_eq!(a.scale(), b.scale());
            for i in 0..v {
                for k in 0..n {
                    prop_assert_eq!(a.quantised(i, k), b.quantised(i, k));
                }
            }
        }
    }
}
