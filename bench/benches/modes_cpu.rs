//! The CPU deformation modes at 400k vertices on synthetic data (no bake, so it runs in seconds):
//! the basis mode and eq. 7.7 with 16 coefficients (held in 16 bits) as `CpuLung` runs them, against a plain copy of
//! the same bytes, one thread and all threads, measured in the same run.
//!
//! Run: `cargo bench -p lungdyn-bench --bench modes_cpu` (`-- --vertices N` for another size).
//! The same figures for baked lungs, with errors and the GPU, come from `lungdyn bench tradeoff`.

use lungdyn_bench::median;
use std::hint::black_box;

use lung_model::deform::modes::{CpuLung, ModeData, ShCoeffs};
use lung_model::mesh::TriMesh;
use rayon::prelude::*;

/// A deterministic pseudo-random sequence in [-1, 1) (seeded xorshift), so runs compare.
fn values(n: usize, seed: u64) -> Vec<f32> {
    use rand::{RngExt, SeedableRng};
    let mut r = rand_xorshift::XorShiftRng::seed_from_u64(seed);
    (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect()
}

fn triples(n: usize, seed: u64) -> Vec<[f32; 3]> {
    values(3 * n, seed)
        .chunks_exact(3)
        .map(|c| [c[0] * 100.0, c[1] * 100.0, c[2] * 100.0])
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.iter().any(|a| a == "--list") {
        return;
    }
    let v = args
        .iter()
        .position(|a| a == "--vertices")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(400_000usize);
    let runs = 101;
    if let Some(path) = args
        .iter()
        .position(|a| a == "--kernel")
        .and_then(|i| args.get(i + 1))
    {
        // A baked kernel's own data: the timing and how many stored values are subnormal.
        let k = lung_model::kernel::KernelFile::open(std::path::Path::new(path)).unwrap();
        for mode in [
            lung_model::deform::modes::DeformMode::Basis,
            lung_model::deform::modes::DeformMode::Sh,
        ] {
            let Ok(mut lung) = CpuLung::from_kernel(&k, mode) else {
                println!("{path}: no data for the {mode:?} mode");
                continue;
            };
            let n = lung.coeff_count();
            let c: Vec<f32> = values(n, 9);
            let subnormal = match &lung.data {
                ModeData::Basis { g } => g.iter().flatten().filter(|x| x.is_subnormal()).count(),
                // As stored in the kernel (the run time holds them as 16-bit integers).
                ModeData::Sh { .. } => k
                    .sh_coefficients()
                    .ok()
                    .flatten()
                    .map_or(0, |t| t.iter().filter(|x| x.is_subnormal()).count()),
                _ => 0,
            };
            let mut out = vec![[0.0f32; 3]; lung.len()];
            let ms = median(runs, || {
                lung.deform_into(1.7, &c, [0.0; 3], &mut out).unwrap();
                black_box(&out);
            }) * 1e3;
            println!("{path}: {mode:?} {ms:.3} ms, {subnormal} subnormal stored values");
        }
        return;
    }
    let mesh = TriMesh {
        positions: triples(v, 1),
        triangles: Vec::new(),
    };
    let kd = triples(v, 2);
    let g: Vec<[f32; 4]> = values(4 * v, 3)
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect();
    let t = values(16 * v, 4);
    let mut out = vec![[0.0f32; 3]; v];
    let s = black_box(1.7f32);
    let offset = [0.5, -0.25, 1.0];

    let mut basis = CpuLung::new(mesh.clone(), kd.clone(), ModeData::Basis { g });
    let w = [0.9f32, -0.3, 0.45, 0.2];
    let basis_s = median(runs, || {
        basis.deform_into(s, &w, offset, &mut out).unwrap();
        black_box(&out);
    });
    let mut sh = CpuLung::new(
        mesh,
        kd,
        ModeData::Sh {
            t: ShCoeffs::quantise(16, &t).expect("16 finite coefficients per vertex"),
        },
    );
    let c = values(16, 5);
    let sh_s = median(runs, || {
        sh.deform_into(s, &c, offset, &mut out).unwrap();
        black_box(&out);
    });

    // Copies of the same bytes: the basis mode reads p, G, k·d (40 B) and writes 12 B per vertex;
    // eq. 7.7 with 16 coefficients reads p, T (16-bit), k·d (56 B) and writes 12 B.
    let copy = |bytes: usize, threads: bool| {
        let half = v * bytes / 2;
        let src = vec![1u8; half];
        let mut dst = vec![0u8; half];
        median(runs, || {
            if threads {
                dst.par_chunks_mut(1 << 16)
                    .zip(black_box(&src).par_chunks(1 << 16))
                    .for_each(|(d, s)| d.copy_from_slice(s));
            } else {
                dst.copy_from_slice(black_box(&src));
            }
            black_box(&dst);
        })
    };
    let threads = rayon::current_num_threads();
    println!("{v} vertices, {threads} rayon threads, median of {runs} runs");
    for (name, bytes, mode_s) in [("basis", 52usize, basis_s), ("sh 16", 68, sh_s)] {
        let (one, all) = (copy(bytes, false), copy(bytes, true));
        println!(
            "{name:>6}: {:.3} ms ({:.1} GB/s); copy of the same {bytes} B/vertex: 1 thread {:.3} ms \
             ({:.0} % of it), {threads} threads {:.3} ms ({:.0} % of it)",
            mode_s * 1e3,
            (bytes * v) as f64 / mode_s / 1e9,
            one * 1e3,
            100.0 * one / mode_s,
            all * 1e3,
            100.0 * all / mode_s
        );
    }
}
