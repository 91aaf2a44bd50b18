//! `lungdyn fit-motion --plot`: a report a physicist can read. One row per model: the held-out error
//! of every landmark as a colour, seen from the front (X–Z), the side (Y–Z) and above (X–Y), and the
//! histogram of the held-out errors with its mean — the same colour scale for every model, so the
//! rows compare at a glance.

use std::path::Path;

use glam::DVec3;
use plotters::prelude::*;

use crate::motion_report::PointsReport;

/// Draw into `png` (a temporary sibling, then renamed).
pub fn write(png: &Path, start: &[DVec3], report: &PointsReport) -> anyhow::Result<()> {
    // A .png in a folder that takes a new file, or an error naming the path (not a drawing error).
    crate::plot::check_path(png)?;
    crate::plot::draw_then_rename(png, |tmp| draw(tmp, start, report))
}

fn color(e: f64, max: f64) -> RGBColor {
    let t = (e / max).clamp(0.0, 1.0);
    let c = colorous_like(t);
    RGBColor(c[0], c[1], c[2])
}

/// A perceptual ramp (dark blue → teal → yellow → red) without another dependency.
fn colorous_like(t: f64) -> [u8; 3] {
    let stops = [
        (0.0, [40.0, 30.0, 110.0]),
        (0.33, [30.0, 150.0, 140.0]),
        (0.66, [240.0, 210.0, 40.0]),
        (1.0, [200.0, 30.0, 30.0]),
    ];
    for w in stops.windows(2) {
        let ((a, ca), (b, cb)) = (w[0], w[1]);
        if t <= b {
            let s = (t - a) / (b - a);
            return [0, 1, 2].map(|k| (ca[k] + s * (cb[k] - ca[k])) as u8);
        }
    }
    [200, 30, 30]
}

fn draw(png: &Path, start: &[DVec3], report: &PointsReport) -> anyhow::Result<()> {
    crate::plot::ensure_font();
    let rows = report.models.len().max(1);
    let (w, h) = (1600u32, 90 + 330 * rows as u32);
    let root = BitMapBackend::new(png, (w, h)).into_drawing_area();
    root.fill(&WHITE)?;
    let (title, body) = root.split_vertically(70);
    // Colour scale shared by every row: the 95th percentile of all held-out errors.
    let mut all: Vec<f64> = report
        .models
        .iter()
        .flat_map(|m| m.cv_point_errors.iter().copied())
        .filter(|v| v.is_finite())
        .collect();
    all.sort_by(f64::total_cmp);
    let emax = all
        .get((all.len() as f64 * 0.95) as usize)
        .copied()
        .unwrap_or(1.0)
        .max(0.5);
    title.titled(
        &format!(
            "fit-motion: held-out error per landmark ({}-fold CV) — colour 0 to {emax:.1} mm; no-motion {:.2} mm; {}",
            report.folds, report.baseline_mean_mm, report.frame_description
        ),
        ("sans-serif", 20),
    )?;
    let (lo, hi) = start.iter().fold(
        (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN)),
        |(a, b), p| (a.min(*p), b.max(*p)),
    );
    let pad = (hi - lo) * 0.05 + DVec3::ONE;
    let (lo, hi) = (lo - pad, hi + pad);
    for (row, m) in body.split_evenly((rows, 1)).iter().zip(&report.models) {
        let cells = row.split_evenly((1, 4));
        let views: [(&str, usize, usize); 3] = [
            ("front (X–Z)", 0, 2),
            ("side (Y–Z)", 1, 2),
            ("above (X–Y)", 0, 1),
        ];
        let name = format!(
            "{}{}: held-out {:.2} mm (in-sample {:.2})",
            m.model.name(),
            if m.model.name() == report.chosen {
                " (chosen)"
            } else {
                ""
            },
            m.cv.mean_mm,
            m.in_sample.mean_mm
        );
        for (v, (cell, (view, a, b))) in cells.iter().zip(views).enumerate() {
            let caption = if v == 0 {
                format!("{name} — {view}")
            } else {
                view.to_string()
            };
            let mut chart = ChartBuilder::on(cell)
                .caption(caption, ("sans-serif", 14))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(58)
                .build_cartesian_2d(lo[a]..hi[a], lo[b]..hi[b])?;
            chart
                .configure_mesh()
                .x_desc(format!(
                    "{} mm",
                    ["X (left)", "Y (anterior)", "Z (superior)"][a]
                ))
                .y_desc(format!(
                    "{} mm",
                    ["X (left)", "Y (anterior)", "Z (superior)"][b]
                ))
                .label_style(("sans-serif", 11))
                .draw()?;
            // Largest errors last, so they are on top.
            let mut order: Vec<usize> = (0..start.len()).collect();
            order.sort_by(|&i, &j| m.cv_point_errors[i].total_cmp(&m.cv_point_errors[j]));
            chart.draw_series(order.iter().map(|&i| {
                let p = start[i];
                Circle::new((p[a], p[b]), 3, color(m.cv_point_errors[i], emax).filled())
            }))?;
        }
        // Histogram of held-out errors.
        let bins = 24usize;
        let top = (emax * 1.5).max(1.0);
        let mut counts = vec![0u32; bins];
        for &e in &m.cv_point_errors {
            if e.is_finite() {
                counts[((e / top * bins as f64) as usize).min(bins - 1)] += 1;
            }
        }
        let ymax = counts.iter().copied().max().unwrap_or(1).max(1);
        let mut chart = ChartBuilder::on(&cells[3])
            .caption(
                format!(
                    "{}: held-out errors (max {:.1} mm)",
                    m.model.name(),
                    m.cv.max_mm
                ),
                ("sans-serif", 14),
            )
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(40)
            .build_cartesian_2d(0.0..top, 0u32..ymax + 1)?;
        chart
            .configure_mesh()
            .x_desc("held-out error mm (last bin: all above)")
            .y_desc("landmarks")
            .label_style(("sans-serif", 11))
            .draw()?;
        let width = top / bins as f64;
        chart.draw_series(counts.iter().enumerate().map(|(k, &c)| {
            let x0 = k as f64 * width;
            Rectangle::new(
                [(x0, 0), (x0 + width * 0.9, c)],
                color(x0 + width / 2.0, emax).filled(),
            )
        }))?;
        chart.draw_series(std::iter::once(PathElement::new(
            vec![(m.cv.mean_mm, 0), (m.cv.mean_mm, ymax)],
            BLACK.stroke_width(2),
        )))?;
    }
    root.present()?;
    Ok(())
}
