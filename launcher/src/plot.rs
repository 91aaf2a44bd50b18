//! Plots for `lungdyn pv`: the PV loop (pressure in cmH2O against volume in ml, both phases) beside
//! a second panel (the damping functions, or the normalised limbs with the fit), drawn once for a PNG
//! and once for an SVG with the same code.

use std::path::{Path, PathBuf};

use plotters::coord::Shift;
use plotters::prelude::*;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Register the bundled font once (every plot's text uses it).
pub fn ensure_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The bundled font is valid; a failure here would only mean text-less plots.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// One line or point series.
pub struct Series {
    /// Legend label.
    pub label: String,
    /// Points (x, y).
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub color: RGBColor,
    /// Draw markers instead of a line.
    pub markers: bool,
}

/// One panel.
pub struct Panel {
    /// Title above the panel.
    pub title: String,
    /// X axis label (with unit).
    pub x_label: String,
    /// Y axis label (with unit).
    pub y_label: String,
    /// Series.
    pub series: Vec<Series>,
}

/// Inhalation colour.
pub const INHALE: RGBColor = RGBColor(31, 119, 180);
/// Exhalation colour.
pub const EXHALE: RGBColor = RGBColor(230, 110, 20);
/// Measured data colour.
pub const DATA: RGBColor = RGBColor(90, 90, 90);

fn bounds(panel: &Panel) -> ((f64, f64), (f64, f64)) {
    let mut xs = (f64::INFINITY, f64::NEG_INFINITY);
    let mut ys = (f64::INFINITY, f64::NEG_INFINITY);
    for s in &panel.series {
        for &(x, y) in s
            .points
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
        {
            xs = (xs.0.min(x), xs.1.max(x));
            ys = (ys.0.min(y), ys.1.max(y));
        }
    }
    // No finite point: a unit range (plotters' tick search never ends on an infinite range).
    let pad = |(lo, hi): (f64, f64)| {
        if !(lo.is_finite() && hi.is_finite()) {
            return (0.0, 1.0);
        }
        let d = if hi > lo { 0.05 * (hi - lo) } else { 1.0 };
        (lo - d, hi + d)
    };
    (pad(xs), pad(ys))
}

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    let ((x0, x1), (y0, y1)) = bounds(panel);
    let mut chart = ChartBuilder::on(area)
        .caption(&panel.title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(44)
        .y_label_area_size(64)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    chart
        .configure_mesh()
        .x_desc(&panel.x_label)
        .y_desc(&panel.y_label)
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()
        .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    for s in &panel.series {
        let color = s.color;
        if s.markers {
            chart
                .draw_series(
                    s.points
                        .iter()
                        .map(|&(x, y)| Circle::new((x, y), 3, color.filled())),
                )
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                .label(&s.label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 3, color.filled()));
        } else {
            let drawn = chart
                .draw_series(LineSeries::new(
                    s.points.iter().copied(),
                    color.stroke_width(2),
                ))
                .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
            // An unlabelled series (a later stretch of one already in the legend) has no entry.
            if !s.label.is_empty() {
                drawn.label(&s.label).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
                });
            }
        }
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::LowerRight)
        .draw()
        .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    Ok(())
}

fn draw<DB: DrawingBackend>(root: DrawingArea<DB, Shift>, panels: &[Panel]) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    root.fill(&WHITE)
        .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    let areas = root.split_evenly((1, panels.len()));
    for (area, panel) in areas.iter().zip(panels) {
        draw_panel(area, panel)?;
    }
    root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    Ok(())
}

/// Files drawn to temporary siblings and not yet in place: [`Staged::commit`] renames them over
/// their targets (each checked again by [`outfile::Staged::commit`]); dropped uncommitted, the
/// temporary files are removed and nothing is replaced.
#[derive(Debug)]
pub struct Staged {
    files: Vec<outfile::Staged>,
}

impl Staged {
    /// Put every file in place (renames within one folder); returns the final paths. A file that
    /// cannot be put in place stops the rest (their temporary files are removed).
    pub fn commit(self) -> anyhow::Result<Vec<PathBuf>> {
        let mut done = Vec::with_capacity(self.files.len());
        for f in self.files {
            done.push(f.commit()?);
        }
        Ok(done)
    }
}

/// Draw into a temporary sibling of `path` with `draw`, then put it in place: a target that is not
/// a regular file is refused before drawing, and a failed drawing replaces nothing.
pub fn draw_then_rename(
    path: &Path,
    draw: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let staged = outfile::Staged::new(path)?;
    draw(staged.path())?;
    staged.commit()?;
    Ok(())
}

/// The SVG written beside a plot `png`.
pub fn svg_of(png: &Path) -> PathBuf {
    png.with_extension("svg")
}

/// Check a `--plot` path before any work: a `.png` in a writable folder (see [`crate::outputs`]).
pub fn check_path(png: &Path) -> anyhow::Result<()> {
    crate::outputs::check(&crate::outputs::Output {
        flag: "--plot",
        path: png,
        extensions: &["png"],
    })
}

/// Draw `panels` side by side to temporary siblings of `png` and of the SVG with the same stem;
/// nothing is replaced until [`Staged::commit`]. A failure names the plot's path.
pub fn render(png: &Path, panels: &[Panel]) -> anyhow::Result<Staged> {
    ensure_font();
    check_path(png)?;
    let svg = svg_of(png);
    let size = (560 * panels.len() as u32, 480);
    let staged = Staged {
        files: vec![outfile::Staged::new(png)?, outfile::Staged::new(&svg)?],
    };
    draw(
        BitMapBackend::new(staged.files[0].path(), size).into_drawing_area(),
        panels,
    )
    .map_err(|e| anyhow::anyhow!("--plot {}: {e}", png.display()))?;
    draw(
        SVGBackend::new(staged.files[1].path(), size).into_drawing_area(),
        panels,
    )
    .map_err(|e| anyhow::anyhow!("--plot {}: {e}", svg.display()))?;
    Ok(staged)
}

/// Write `panels` side by side to `png` and to the SVG with the same stem; returns both paths.
/// Each file is drawn to a temporary sibling first and renamed, so a failed plot never replaces a
/// good one.
pub fn write(png: &Path, panels: &[Panel]) -> anyhow::Result<(PathBuf, PathBuf)> {
    let files = render(png, panels)?.commit()?;
    Ok((files[0].clone(), files[1].clone()))
}
