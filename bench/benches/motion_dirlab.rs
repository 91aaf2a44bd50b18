//! Motion models on the DIR-Lab 4DCT landmarks (10 cases × 300 pairs, end-exhale T50 → end-inhale
//! T00): no-motion baseline, and per model the in-sample and 5-fold cross-validated mean error,
//! the configuration chosen, and the fit time. The data are not in the repository (their
//! redistribution terms are not ours to waive): point `LUNGDYN_DIRLAB` at a folder holding
//! `Case{N}_300_T00_xyz.txt` / `Case{N}_300_T50_xyz.txt` (either DIR-Lab naming style).
//!
//! `LUNGDYN_DIRLAB=/path/to/dirlab cargo bench -p lungdyn-bench --bench motion_dirlab`

use std::path::{Path, PathBuf};

use lung_bake::landmarks::{read, Frame, VoxelAxes};
use lung_bake::motion_models::{check_frame, evaluate, split, ModelKind};
use lung_model::input::ReadLimits;

/// DIR-Lab's voxel spacing per case (mm), from the data set's documentation.
const SPACING: [[f64; 3]; 10] = [
    [0.97, 0.97, 2.5],
    [1.16, 1.16, 2.5],
    [1.15, 1.15, 2.5],
    [1.13, 1.13, 2.5],
    [1.10, 1.10, 2.5],
    [0.97, 0.97, 2.5],
    [0.97, 0.97, 2.5],
    [0.97, 0.97, 2.5],
    [0.97, 0.97, 2.5],
    [0.97, 0.97, 2.5],
];

fn find(dir: &Path, case: usize, phase: &str) -> Option<PathBuf> {
    let want = [
        format!("case{case}_300_{phase}_xyz.txt").to_ascii_lowercase(),
        format!("case{case}_dirlab300_{phase}_xyz.txt").to_ascii_lowercase(),
    ];
    std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .find(|p| {
            p.file_name()
                .map(|n| n.to_string_lossy().to_ascii_lowercase())
                .is_some_and(|n| want.iter().any(|w| *w == n))
        })
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let Some(dir) = std::env::var_os("LUNGDYN_DIRLAB").map(PathBuf::from) else {
        println!(
            "motion_dirlab: set LUNGDYN_DIRLAB to a folder with the DIR-Lab 300-landmark files"
        );
        return;
    };
    println!(
        "{:<5} {:>9} | {:>19} | {:>19} | {:>19} | {:>19} | {:>7} {:>6}",
        "case",
        "baseline",
        "power in / CV",
        "affine in / CV",
        "poly in / CV",
        "rbf in / CV",
        "rho_z",
        "s"
    );
    let mut sums = [0.0f64; 4];
    let mut base_sum = 0.0;
    let mut cases = 0;
    for case in 1..=10 {
        let (Some(t00), Some(t50)) = (find(&dir, case, "T00"), find(&dir, case, "T50")) else {
            println!("{case:<5} missing");
            continue;
        };
        let frame = Frame::Voxel {
            axes: VoxelAxes::DIRLAB,
            base: 1,
            spacing: SPACING[case - 1],
        };
        let start = read(&t50, &frame, ReadLimits::TABLE).unwrap();
        let target = read(&t00, &frame, ReadLimits::TABLE).unwrap();
        let delta: Vec<_> = start.iter().zip(&target).map(|(a, b)| *b - *a).collect();
        let baseline = delta.iter().map(|d| d.length()).sum::<f64>() / delta.len() as f64;
        let (_, lungs, _) = split(&start, &delta, None).unwrap();
        let fc = check_frame(&lungs);
        let t = std::time::Instant::now();
        let mut row = format!("{case:<5} {baseline:>9.3} |");
        for (k, kind) in ModelKind::ALL.into_iter().enumerate() {
            let r = evaluate(kind, &start, &delta, None, 5, 10).unwrap();
            sums[k] += r.cv.mean_mm;
            row += &format!(" {:>8.4} / {:>8.4} |", r.in_sample.mean_mm, r.cv.mean_mm);
        }
        base_sum += baseline;
        cases += 1;
        println!(
            "{row} {:>+7.2} {:>6.2}",
            fc.rho_z,
            t.elapsed().as_secs_f64()
        );
    }
    if cases > 0 {
        let n = cases as f64;
        println!(
            "mean  {:>9.3} | {:>19.4} | {:>19.4} | {:>19.4} | {:>19.4} |",
            base_sum / n,
            sums[0] / n,
            sums[1] / n,
            sums[2] / n,
            sums[3] / n
        );
    }
}
