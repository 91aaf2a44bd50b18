//! The demo's summary picture: the snapshots of one breath side by side, then a motion panel that
//! tints where the lungs' silhouette grew between the smallest and the largest volume.

use std::path::{Path, PathBuf};

use image::{imageops, Rgba, RgbaImage};

/// Volume (ml) encoded in a snapshot file name (`..._2650ml.png`).
pub fn volume_of(path: &Path) -> Option<f32> {
    let stem = path.file_stem()?.to_str()?;
    stem.rsplit('_').next()?.strip_suffix("ml")?.parse().ok()
}

/// Compose `frames` (same size) into `out`: each frame at half size, then the motion panel.
/// Returns `None` when there are fewer than two frames.
pub fn breath_strip(frames: &[PathBuf], out: &Path) -> anyhow::Result<Option<PathBuf>> {
    if frames.len() < 2 {
        return Ok(None);
    }
    let images: Vec<RgbaImage> = frames
        .iter()
        .map(|p| image::open(p).map(|i| i.to_rgba8()))
        .collect::<Result<_, _>>()?;
    let (w, h) = images[0].dimensions();
    if images.iter().any(|i| i.dimensions() != (w, h)) {
        anyhow::bail!("snapshots differ in size; cannot compose the strip");
    }
    let vol = |i: usize| volume_of(&frames[i]).unwrap_or(i as f32);
    let lo = (0..frames.len())
        .min_by(|&a, &b| vol(a).total_cmp(&vol(b)))
        .unwrap_or(0);
    let hi = (0..frames.len())
        .max_by(|&a, &b| vol(a).total_cmp(&vol(b)))
        .unwrap_or(0);
    let background = *images[lo].get_pixel(0, 0);
    let is_lung = |img: &RgbaImage, x: u32, y: u32| *img.get_pixel(x, y) != background;
    // Motion panel: the end-inspiration image, dimmed, with the band the lungs grew into in green.
    let mut motion = images[hi].clone();
    for (x, y, p) in motion.enumerate_pixels_mut() {
        let (a, b) = (is_lung(&images[lo], x, y), is_lung(&images[hi], x, y));
        *p = match (a, b) {
            (false, true) => Rgba([60, 230, 120, 255]),
            (true, false) => Rgba([230, 80, 60, 255]),
            (true, true) => Rgba([p[0] / 2, p[1] / 2, p[2] / 2, 255]),
            (false, false) => *p,
        };
    }
    // Crop every panel to the box holding the lungs in any frame, with a margin.
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for img in &images {
        for (x, y, _) in img
            .enumerate_pixels()
            .filter(|&(x, y, _)| is_lung(img, x, y))
        {
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
        }
    }
    if x1 < x0 {
        (x0, y0, x1, y1) = (0, 0, w - 1, h - 1);
    }
    let margin = 12;
    let (x0, y0) = (x0.saturating_sub(margin), y0.saturating_sub(margin));
    let (cw, ch) = (
        (x1 + margin).min(w - 1) - x0 + 1,
        (y1 + margin).min(h - 1) - y0 + 1,
    );
    let mut strip = RgbaImage::from_pixel(cw * (images.len() as u32 + 1), ch, background);
    for (i, img) in images.iter().chain(std::iter::once(&motion)).enumerate() {
        let panel = imageops::crop_imm(img, x0, y0, cw, ch).to_image();
        imageops::replace(&mut strip, &panel, (i as u32 * cw) as i64, 0);
    }
    renderer::write_png(&strip, out)?;
    Ok(Some(out.to_path_buf()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn volumes_are_read_from_snapshot_names() {
        assert_eq!(
            volume_of(Path::new("out/lungs_03_tick00450_2900ml.png")),
            Some(2900.0)
        );
        assert_eq!(volume_of(Path::new("out/other.png")), None);
    }
}
