//! The deformation operator at 10k / 100k / 400k vertices (generated left lung):
//! bake time and peak memory, then the per-frame CPU cost of
//!
//! * the precomputed mode `out = p + s·u` (EQUATIONS §2.4, "3 additions per node"), single thread;
//! * eq. 7.1, `F = Tᵀf` gathered per node (sparse transfer × force, rayon) plus `out = p + s·k·F·d`;
//!
//! and the precomputed mode's throughput as a fraction of a plain copy of the same number of bytes
//! measured in the same run (36 bytes per vertex: read p and u, write out).
//! Run: `cargo bench -p lungdyn-bench --bench operator` (about a minute on two cores).

use lungdyn_bench::median;
use std::hint::black_box;
use std::time::Instant;

use lung_bake::kernel::{bake, BakeSettings};
use lung_model::mesh::{generate, Side};

fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map(|kb| kb / 1024.0)
        .unwrap_or(0.0)
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    println!(
        "{:>8} {:>8} {:>9} {:>8} {:>9} | {:>12} {:>12} {:>10} {:>9} | {:>12}",
        "vertices",
        "nnz/row",
        "bake s",
        "peak MiB",
        "trunc",
        "precomp µs",
        "copy µs",
        "fraction",
        "GB/s",
        "eq7.1 µs"
    );
    // Largest first, so the process's peak memory after it is that bake's.
    for n in [400_000usize, 100_000, 10_000] {
        let mesh = generate::lung(Side::Left, n).unwrap();
        let t = Instant::now();
        let k = bake(
            Side::Left,
            mesh,
            &BakeSettings::default_for(Side::Left),
            &|_| {},
        )
        .unwrap();
        let bake_s = t.elapsed().as_secs_f64();
        let peak = peak_rss_mib();
        let v = k.mesh.positions.len();
        let runs = if v > 200_000 { 101 } else { 301 };

        // Precomputed mode, one thread: what the CPU reference of the GPU pass does.
        let p = &k.mesh.positions;
        let model = lung_model::deform::LungModel::from_unit_displacement(
            Side::Left,
            k.mesh.clone(),
            k.unit_displacement.clone(),
        );
        let mut out = vec![[0.0f32; 3]; v];
        let s = black_box(37.5f32);
        let pre = median(runs, || {
            model.deform_into(s, &mut out);
            black_box(&out);
        });
        // A plain copy moving the same 36 bytes per vertex (read 18, write 18).
        let src = vec![1u8; v * 18];
        let mut dst = vec![0u8; v * 18];
        let copy = median(runs, || {
            dst.copy_from_slice(black_box(&src));
            black_box(&dst);
        });
        let gbs = (36 * v) as f64 / pre / 1e9;

        // eq. 7.1: per-frame sparse transfer × force, then the displacement along d.
        let cols = k.transfer.transposed();
        let f: Vec<f32> = k.applied_force.clone();
        let d = &k.directions;
        let scale = k.meta.force_scale as f32;
        let mut big_f = vec![0.0f32; v];
        let eq71 = median(runs.min(51), || {
            cols.apply_into(black_box(&f), &mut big_f);
            for (((o, p), d), &fi) in out.iter_mut().zip(p).zip(d).zip(&big_f) {
                for a in 0..3 {
                    o[a] = p[a] + s * scale * fi * d[a];
                }
            }
            black_box(&out);
        });
        // The two modes agree (eq. 7.1 with the stored f reproduces the baked F).
        let worst = big_f
            .iter()
            .zip(&k.elastostatic)
            .map(|(a, b)| ((a - b) / b.abs().max(1e-12)).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst < 1e-3,
            "eq. 7.1 and the baked force disagree by {worst}"
        );
        println!(
            "{:>8} {:>8.1} {:>9.2} {:>8.0} {:>9.1e} | {:>12.1} {:>12.1} {:>9.0}% {:>9.2} | {:>12.1}",
            v,
            k.meta.transfer.mean_row_nnz,
            bake_s,
            peak,
            k.meta.transfer.truncated_force_mean,
            pre * 1e6,
            copy * 1e6,
            100.0 * copy / pre,
            gbs,
            eq71 * 1e6
        );
    }
}
