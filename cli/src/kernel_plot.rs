//! `lungdyn kernel inspect --plot`: what a kernel holds, as pictures (seed Fig. 6.5 style).
//!
//! Three side views of the lung (anterior to the right, superior up, seen from the lateral side):
//! the unit displacement's magnitude (where the surface moves most per unit volume), and two transfer
//! rows — the force a unit push on one node sends to its neighbours — for a node near the base and a
//! node near the apex, on a log colour scale.

use std::path::Path;

use lung_model::kernel::KernelFile;
use plotters::prelude::*;

/// Draw the three panels into `png` (drawn to a temporary sibling, then renamed).
pub fn write(kernel: &KernelFile, png: &Path) -> anyhow::Result<()> {
    // A .png in a folder that takes a new file, or an error naming the path (not a drawing error).
    crate::plot::check_path(png)?;
    crate::plot::draw_then_rename(png, |tmp| draw(kernel, tmp))
}

fn draw(kernel: &KernelFile, png: &Path) -> anyhow::Result<()> {
    crate::plot::ensure_font();
    let pos = kernel.positions();
    let side = kernel.meta().side;
    let n = pos.len();
    // Painter's order: the lateral surface last, so it is what the viewer sees.
    let mut order: Vec<usize> = (0..n).collect();
    let lateral = |i: usize| pos[i][0] * side.lateral_sign();
    order.sort_by(|&a, &b| lateral(a).total_cmp(&lateral(b)));
    let mag: Vec<f64> = kernel
        .unit_displacement()
        .iter()
        .map(|u| ((u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) as f64).sqrt())
        .collect();
    // Rows of a lateral node near the base and near the apex.
    let bb = kernel.mesh().aabb();
    let pick = |z_frac: f32| {
        let z = bb.min[2] + z_frac * (bb.max[2] - bb.min[2]);
        (0..n)
            .min_by(|&a, &b| {
                let score = |i: usize| (pos[i][2] - z).abs() * 4.0 - lateral(i);
                score(a).total_cmp(&score(b))
            })
            .unwrap_or(0)
    };
    let (base, apex) = (pick(0.15), pick(0.85));
    let (row_ptr, cols, vals) = (kernel.row_ptr()?, kernel.cols()?, kernel.vals()?);
    let row = |j: usize| {
        let r = row_ptr[j] as usize..row_ptr[j + 1] as usize;
        let mut v = vec![0.0f64; n];
        for (&c, &t) in cols[r.clone()].iter().zip(&vals[r]) {
            v[c as usize] = t as f64;
        }
        v
    };
    let (rb, ra) = (row(base), row(apex));

    let root = BitMapBackend::new(png, (1500, 620)).into_drawing_area();
    root.fill(&WHITE)?;
    let (title, body) = root.split_vertically(50);
    title.titled(
        &format!(
            "{} lung kernel: {} vertices, {:.0} transfer non-zeros per row, tolerance {:e} (lateral view, anterior →)",
            side.name(),
            n,
            kernel.meta().transfer.mean_row_nnz,
            kernel.meta().transfer.tolerance
        ),
        ("sans-serif", 22),
    )?;
    let panels = body.split_evenly((1, 3));
    let (mmin, mmax) = mag
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
    draw_view(
        &panels[0],
        &format!(
            "unit displacement {mmin:.3}–{mmax:.3} mm per {:.2} ml",
            kernel.meta().unit_volume_ml
        ),
        pos,
        &order,
        |i| Some((mag[i] - mmin) / (mmax - mmin).max(1e-30)),
        None,
    )?;
    for (panel, values, node, label) in [
        (&panels[1], &rb, base, "near the base"),
        (&panels[2], &ra, apex, "near the apex"),
    ] {
        let vmax = values.iter().cloned().fold(0.0, f64::max).max(1e-30);
        let count = values.iter().filter(|&&v| v > 0.0).count();
        draw_view(
            panel,
            &format!("transfer row of a node {label}: {count} non-zeros, log scale"),
            pos,
            &order,
            |i| (values[i] > 0.0).then(|| (1.0 + (values[i] / vmax).log10() / 4.0).clamp(0.0, 1.0)),
            Some(node),
        )?;
    }
    root.present()?;
    Ok(())
}

fn draw_view(
    area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
    caption: &str,
    pos: &[[f32; 3]],
    order: &[usize],
    value: impl Fn(usize) -> Option<f64>,
    marker: Option<usize>,
) -> anyhow::Result<()> {
    let (mut y0, mut y1, mut z0, mut z1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for p in pos {
        y0 = y0.min(p[1]);
        y1 = y1.max(p[1]);
        z0 = z0.min(p[2]);
        z1 = z1.max(p[2]);
    }
    let pad = 0.05 * (y1 - y0).max(z1 - z0);
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(45)
        .build_cartesian_2d(
            (y0 - pad) as f64..(y1 + pad) as f64,
            (z0 - pad) as f64..(z1 + pad) as f64,
        )?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc("Y, posterior → anterior (mm)")
        .y_desc("Z, inferior → superior (mm)")
        .label_style(("sans-serif", 12))
        .draw()?;
    let map = ViridisRGB;
    chart.draw_series(order.iter().map(|&i| {
        let c = match value(i) {
            Some(v) => map.get_color(v as f32),
            None => RGBColor(215, 215, 215),
        };
        Circle::new((pos[i][1] as f64, pos[i][2] as f64), 2, c.filled())
    }))?;
    if let Some(j) = marker {
        chart.draw_series(std::iter::once(Cross::new(
            (pos[j][1] as f64, pos[j][2] as f64),
            7,
            RED.stroke_width(2),
        )))?;
    }
    Ok(())
}
