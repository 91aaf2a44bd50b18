//! Time to fit a 1,000-sample PV loop (Venegas sigmoid limbs, closed loop), q and c chosen by the
//! fit and fixed, three runs each. Run: `cargo bench -p lungdyn-bench --bench pv_fit`.

use lung_bake::pv::fit::{fit_curve, FitOptions, PvSample};

fn venegas(c: f64, d: f64) -> impl Fn(f64) -> f64 {
    move |p| 1500.0 + 3000.0 / (1.0 + (-(p - c) / d).exp())
}

fn closed_loop(n: usize) -> Vec<PvSample> {
    let (fin, fex) = (venegas(14.0, 4.0), venegas(9.0, 4.0));
    let scale =
        |f: &dyn Fn(f64) -> f64, p: f64| 2400.0 + 500.0 * (f(p) - f(0.0)) / (f(30.0) - f(0.0));
    let mut out = Vec::new();
    for i in 0..n {
        let p = 30.0 * i as f64 / (n - 1) as f64;
        out.push(PvSample {
            pressure: p,
            volume: scale(&fin, p),
            phase: None,
        });
    }
    for i in 1..n {
        let p = 30.0 * (1.0 - i as f64 / (n - 1) as f64);
        out.push(PvSample {
            pressure: p,
            volume: scale(&fex, p),
            phase: None,
        });
    }
    out
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let data = closed_loop(500);
    println!(
        "fit of a {}-sample loop (both limbs, two threads)",
        data.len()
    );
    for (label, opts) in [
        ("q, c chosen by the fit", FitOptions::default()),
        (
            "q = 2, c = 1 given",
            FitOptions {
                q: Some(2.0),
                c: Some(1.0),
                ..Default::default()
            },
        ),
    ] {
        let mut times = Vec::new();
        let mut rms = 0.0;
        for _ in 0..3 {
            let t = std::time::Instant::now();
            rms = fit_curve(&data, &opts).expect("fit").rms_percent;
            times.push(t.elapsed().as_secs_f64());
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{label:<24} median {:.2} s (min {:.2}, max {:.2}), RMS {:.3} %",
            times[1], times[0], times[2], rms
        );
    }
}
