//! `lungdyn demo --record FILE`: the frames of one whole breath (the renderer's snapshots, one
//! fixed front viewpoint, with the HUD) as an animation that plays in real time: a GIF through the
//! `image` crate, or an MP4 through `ffmpeg` when it is on PATH.
//!
//! Each frame lasts until the next one's engine tick (the snapshot file names carry the ticks), the
//! last one as long as the one before it, so the animation runs at the breath's own pace.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context};

/// The file types `--record` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RecordFormat {
    /// Animated GIF (the `image` crate; no external tool).
    Gif,
    /// H.264 MP4 through `ffmpeg` on PATH.
    Mp4,
}

/// Most frames of a recording (the renderer's snapshot limit).
pub const MAX_RECORD_FRAMES: u32 = 240;

impl RecordFormat {
    /// The format of `path` by its extension, checked before the run: `.gif`, or `.mp4` with
    /// `ffmpeg` on PATH.
    pub fn of(path: &Path) -> anyhow::Result<Self> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("gif") => Ok(RecordFormat::Gif),
            Some("mp4") => {
                if ffmpeg_on_path() {
                    Ok(RecordFormat::Mp4)
                } else {
                    bail!(
                        "--record {}: an .mp4 needs ffmpeg on PATH, and there is none; record a .gif \
                         instead (written without external tools)",
                        path.display()
                    )
                }
            }
            _ => bail!(
                "--record {}: the file must end in .gif (animated GIF) or .mp4 (through ffmpeg)",
                path.display()
            ),
        }
    }
}

fn ffmpeg_on_path() -> bool {
    std::env::var_os("PATH")
        .is_some_and(|paths| std::env::split_paths(&paths).any(|d| d.join("ffmpeg").is_file()))
}

/// Check `--record FILE` and `--record-frames N` before anything runs: a known format, a frame
/// count within 2..=[`MAX_RECORD_FRAMES`], a folder that exists.
pub fn check(path: &Path, frames: u32) -> anyhow::Result<RecordFormat> {
    let format = RecordFormat::of(path)?;
    if !(2..=MAX_RECORD_FRAMES).contains(&frames) {
        bail!("--record-frames {frames}: a breath needs 2 to {MAX_RECORD_FRAMES} frames");
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        bail!(
            "--record {}: the folder {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(format)
}

/// The engine tick in a snapshot file name (`lungs_03_tick00480_2650ml.png`).
pub fn tick_of(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_str()?;
    stem.split('_')
        .find_map(|p| p.strip_prefix("tick"))?
        .parse()
        .ok()
}

/// The snapshots among `frames` that show a later frame than their planned tick (the renderer
/// skipped that tick under load: `…_tick00480_2650ml_drawn00495.png`).
pub fn substituted(frames: &[PathBuf]) -> usize {
    frames
        .iter()
        .filter(|p| {
            p.file_stem()
                .and_then(|s| s.to_str())
                .is_some_and(|s| s.split('_').any(|w| w.starts_with("drawn")))
        })
        .count()
}

/// How long each frame shows, ms: until the next frame's tick; the last as long as the one before
/// (at least 10 ms each: GIF delays are in hundredths of a second).
pub fn frame_delays_ms(ticks: &[u64], tick_hz: f64) -> Vec<u32> {
    let ms =
        |a: u64, b: u64| ((b.saturating_sub(a) as f64 / tick_hz * 1000.0).round() as u32).max(10);
    let mut d: Vec<u32> = ticks.windows(2).map(|w| ms(w[0], w[1])).collect();
    if let Some(&last) = d.last() {
        d.push(last);
    } else if !ticks.is_empty() {
        d.push(100);
    }
    d
}

/// Write `frames` (PNG files of one size) as an animation at `out`, each shown for its delay.
pub fn write(
    format: RecordFormat,
    frames: &[PathBuf],
    delays_ms: &[u32],
    out: &Path,
) -> anyhow::Result<()> {
    if frames.is_empty() || frames.len() != delays_ms.len() {
        bail!("no frames to record");
    }
    match format {
        RecordFormat::Gif => write_gif(frames, delays_ms, out),
        RecordFormat::Mp4 => write_mp4(frames, delays_ms, out),
    }
}

fn write_gif(frames: &[PathBuf], delays_ms: &[u32], out: &Path) -> anyhow::Result<()> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let mut size = None;
    let mut images = Vec::with_capacity(frames.len());
    for p in frames {
        let img = image::open(p)
            .with_context(|| format!("cannot read the frame {}", p.display()))?
            .to_rgba8();
        if *size.get_or_insert(img.dimensions()) != img.dimensions() {
            bail!("the frames differ in size; cannot record them as one animation");
        }
        images.push(img);
    }
    outfile::write_atomically(out, |w| {
        let mut enc = GifEncoder::new_with_speed(w, 10);
        enc.set_repeat(Repeat::Infinite)
            .map_err(std::io::Error::other)?;
        for (img, &ms) in images.into_iter().zip(delays_ms) {
            let delay = image::Delay::from_numer_denom_ms(ms, 1);
            enc.encode_frame(image::Frame::from_parts(img, 0, 0, delay))
                .map_err(std::io::Error::other)?;
        }
        Ok(())
    })?;
    Ok(())
}

fn write_mp4(frames: &[PathBuf], delays_ms: &[u32], out: &Path) -> anyhow::Result<()> {
    // ffmpeg's concat demuxer: each frame with its duration (the last repeated, as it requires).
    let dir = out
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let list = dir.join(format!(".lungdyn-record-{}.txt", std::process::id()));
    let mut text = String::new();
    for (p, ms) in frames.iter().zip(delays_ms) {
        let abs = std::fs::canonicalize(p)?;
        text.push_str(&format!(
            "file '{}'\nduration {:.3}\n",
            abs.display().to_string().replace('\'', "'\\''"),
            *ms as f64 / 1000.0
        ));
    }
    if let Some(last) = frames.last() {
        text.push_str(&format!(
            "file '{}'\n",
            std::fs::canonicalize(last)?.display()
        ));
    }
    std::fs::write(&list, text)?;
    let tmp = dir.join(format!(".lungdyn-record-{}.mp4", std::process::id()));
    let status = Command::new("ffmpeg")
        .args([
            "-hide_banner",
            "-loglevel",
            "error",
            "-y",
            "-f",
            "concat",
            "-safe",
            "0",
            "-i",
        ])
        .arg(&list)
        // Even sides for yuv420p; a fixed rate the durations are sampled at.
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-pix_fmt",
            "yuv420p",
            "-r",
            "30",
        ])
        .arg(&tmp)
        .stdin(std::process::Stdio::null())
        .spawn()
        .and_then(|child| wait_bounded(child, encoder_timeout(frames.len())));
    let _ = std::fs::remove_file(&list);
    let status = match status {
        Ok(Waited::Exited(s)) => Ok(s),
        Ok(Waited::Killed(why)) => {
            let _ = std::fs::remove_file(&tmp);
            bail!(
                "ffmpeg was stopped before it wrote {}: {why}",
                out.display()
            )
        }
        Err(e) => Err(e),
    };
    match status {
        Ok(s) if s.success() => {
            std::fs::rename(&tmp, out)
                .with_context(|| format!("cannot move the recording to {}", out.display()))?;
            Ok(())
        }
        Ok(s) => {
            let _ = std::fs::remove_file(&tmp);
            bail!("ffmpeg could not write {} ({s})", out.display())
        }
        Err(e) => bail!("cannot run ffmpeg for {}: {e}", out.display()),
    }
}

/// How long an encoder may take for `frames` frames: a minute, and half a second a frame (a
/// breath of 240 frames encodes in seconds; an encoder that hangs must not hold the run forever).
pub fn encoder_timeout(frames: usize) -> std::time::Duration {
    std::time::Duration::from_secs(60) + std::time::Duration::from_millis(500 * frames as u64)
}

/// How a bounded wait for a child ended.
#[derive(Debug)]
pub enum Waited {
    /// It exited by itself.
    Exited(std::process::ExitStatus),
    /// It was killed (SIGKILL) and reaped: past its time, or the run was asked to stop.
    Killed(String),
}

/// Wait for `child` at most `limit`, and no longer than the run's stop request (SIGTERM, SIGINT,
/// SIGHUP latched by `transport::stop`): past either it is killed and reaped, and says which.
pub fn wait_bounded(
    mut child: std::process::Child,
    limit: std::time::Duration,
) -> std::io::Result<Waited> {
    let start = std::time::Instant::now();
    loop {
        if let Some(s) = child.try_wait()? {
            return Ok(Waited::Exited(s));
        }
        let why = if start.elapsed() > limit {
            Some(format!(
                "it ran past {:.0} s without finishing",
                limit.as_secs_f64()
            ))
        } else if !transport::stop::idle(std::time::Duration::from_millis(20)) {
            Some("the run was asked to stop".to_string())
        } else {
            None
        };
        if let Some(why) = why {
            let _ = child.kill();
            let _ = child.wait();
            return Ok(Waited::Killed(why));
        }
    }
}

/// `count` of `n` items, evenly spread, the first always included (the strip's frames out of a
/// recording's).
pub fn spread(n: usize, count: usize) -> Vec<usize> {
    let count = count.min(n);
    (0..count).map(|k| k * n / count).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_encoder_that_never_exits_is_killed_past_its_time() {
        let child = Command::new("sleep").arg("30").spawn().unwrap();
        let t = std::time::Instant::now();
        let w = wait_bounded(child, std::time::Duration::from_millis(200)).unwrap();
        assert!(
            matches!(&w, Waited::Killed(why) if why.contains("ran past")),
            "{w:?}"
        );
        assert!(t.elapsed() < std::time::Duration::from_secs(10));
        let child = Command::new("true").spawn().unwrap();
        let w = wait_bounded(child, std::time::Duration::from_secs(10)).unwrap();
        assert!(matches!(w, Waited::Exited(s) if s.success()), "{w:?}");
        assert_eq!(encoder_timeout(240), std::time::Duration::from_secs(180));
    }

    #[test]
    fn formats_come_from_the_extension() {
        assert_eq!(
            RecordFormat::of(Path::new("out/breath.gif")).unwrap(),
            RecordFormat::Gif
        );
        assert_eq!(
            RecordFormat::of(Path::new("BREATH.GIF")).unwrap(),
            RecordFormat::Gif
        );
        for bad in ["breath.png", "breath", "breath.apng", ".gif/x"] {
            let e = RecordFormat::of(Path::new(bad)).unwrap_err().to_string();
            assert!(e.contains("must end in .gif"), "{bad}: {e}");
        }
    }

    #[test]
    fn frame_counts_and_folders_are_checked() {
        assert!(check(Path::new("b.gif"), 36).is_ok());
        for n in [0, 1, 241, u32::MAX] {
            let e = check(Path::new("b.gif"), n).unwrap_err().to_string();
            assert!(e.contains("--record-frames"), "{e}");
        }
        let e = check(Path::new("/nonexistent/dir/b.gif"), 36)
            .unwrap_err()
            .to_string();
        assert!(e.contains("does not exist"), "{e}");
    }

    #[test]
    fn ticks_and_delays_follow_the_breath() {
        assert_eq!(
            tick_of(Path::new("out/lungs_03_tick00480_2650ml.png")),
            Some(480)
        );
        assert_eq!(tick_of(Path::new("out/lungs_03.png")), None);
        // A planned tick skipped under load: named by its planned tick (the animation keeps the
        // breath's pace), the frame drawn instead after it, and counted as substituted.
        let sub = PathBuf::from("out/lungs_04_tick00495_2660ml_drawn00498.png");
        assert_eq!(tick_of(&sub), Some(495));
        let frames = [
            PathBuf::from("out/lungs_03_tick00480_2650ml.png"),
            sub,
            PathBuf::from("out/lungs_05_tick00510_2670ml_drawn00512.png"),
            PathBuf::from("out/drawn/lungs_06_tick00525_2680ml.png"),
        ];
        assert_eq!(substituted(&frames), 2);
        assert_eq!(substituted(&[]), 0);
        // 40/min at 60 Hz: 90 ticks, 6 frames 15 ticks apart, 250 ms each.
        let ticks: Vec<u64> = (0..6).map(|k| 180 + 15 * k).collect();
        assert_eq!(frame_delays_ms(&ticks, 60.0), vec![250; 6]);
        assert_eq!(frame_delays_ms(&[5], 60.0), vec![100]);
        assert!(frame_delays_ms(&[], 60.0).is_empty());
        // Same tick twice: the least GIF delay, never zero.
        assert_eq!(frame_delays_ms(&[7, 7], 60.0), vec![10, 10]);
    }

    #[test]
    fn a_strip_takes_frames_spread_over_the_recording() {
        assert_eq!(spread(36, 6), vec![0, 6, 12, 18, 24, 30]);
        assert_eq!(spread(4, 6), vec![0, 1, 2, 3]);
        assert!(spread(0, 6).is_empty());
    }

    #[test]
    fn a_gif_decodes_with_every_frame() {
        use image::AnimationDecoder;
        let dir = std::env::temp_dir().join(format!("lungdyn-record-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let frames: Vec<PathBuf> = (0..5u8)
            .map(|k| {
                let p = dir.join(format!("lungs_{k:02}_tick{:05}_2500ml.png", k as u64 * 10));
                image::RgbaImage::from_pixel(24, 16, image::Rgba([k * 50, 20, 200, 255]))
                    .save(&p)
                    .unwrap();
                p
            })
            .collect();
        let out = dir.join("breath.gif");
        let ticks: Vec<u64> = frames.iter().map(|p| tick_of(p).unwrap()).collect();
        write(
            RecordFormat::Gif,
            &frames,
            &frame_delays_ms(&ticks, 60.0),
            &out,
        )
        .unwrap();
        let dec = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
            std::fs::File::open(&out).unwrap(),
        ))
        .unwrap();
        let decoded = dec.into_frames().collect_frames().unwrap();
        assert_eq!(decoded.len(), 5);
        let (n, d) = decoded[0].delay().numer_denom_ms();
        // 10 ticks at 60 Hz = 167 ms, within the GIF's hundredths of a second.
        let ms = n as f64 / d as f64;
        assert!((ms - 1000.0 / 6.0).abs() <= 10.0, "{ms} ms");
        assert_eq!(decoded[4].buffer().dimensions(), (24, 16));
        // Mismatched sizes are refused, nothing written over the good file.
        let odd = dir.join("odd.png");
        image::RgbaImage::new(8, 8).save(&odd).unwrap();
        let e = write(
            RecordFormat::Gif,
            &[frames[0].clone(), odd],
            &[100, 100],
            &out,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("differ in size"), "{e}");
        assert!(image::open(&out).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
