//! Fullscreen stereo on a chosen display, under a virtual X server (Xvfb) of a non-default size:
//! the window covers the whole screen, the frame is the screen's size and both eyes are drawn; a
//! display named wrongly or counted past the list is refused, listing the displays.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lungdyn_tests::bin;

/// A virtual X server of one screen, `w`×`h`, on a free display number; killed when dropped.
struct Xvfb {
    child: Child,
    display: String,
    log: std::path::PathBuf,
}

impl Xvfb {
    fn start(w: u32, h: u32) -> Self {
        // -displayfd: Xvfb picks a free display and writes its number once it accepts clients.
        // -noreset: without it the server resets whenever its last client leaves (each
        // `xwininfo` poll below), and a client connecting during that reset is refused — the
        // demo once failed "Failed to open connection to X server" so (CI, 2026-12-06).
        let log =
            std::env::temp_dir().join(format!("lungdyn-xvfb-{}-{w}x{h}.log", std::process::id()));
        let mut child = Command::new("Xvfb")
            .args([
                "-displayfd",
                "1",
                "-noreset",
                "-nolisten",
                "tcp",
                "-screen",
                "0",
            ])
            .arg(format!("{w}x{h}x24"))
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).expect("create the Xvfb log"))
            .spawn()
            .expect("start Xvfb (package xvfb)");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let n: u32 = line
            .trim()
            .parse()
            .unwrap_or_else(|e| panic!("Xvfb gave no display number ({e}): {line:?}"));
        Self {
            child,
            display: format!(":{n}"),
            log,
        }
    }

    /// What the server said on stderr, and whether it is still running: for a failure's message.
    fn said(&mut self) -> String {
        let state = match self.child.try_wait() {
            Ok(None) => "running".to_string(),
            Ok(Some(status)) => format!("exited ({status})"),
            Err(e) => format!("unknown ({e})"),
        };
        let log = std::fs::read_to_string(&self.log).unwrap_or_default();
        format!("Xvfb {} {state}; its stderr:\n{log}", self.display)
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_file(&self.log);
    }
}

/// The geometry `xwininfo` reports for the window titled `lungdyn`: (x, y, width, height).
fn window_geometry(display: &str) -> Option<(i64, i64, i64, i64)> {
    let out = Command::new("xwininfo")
        .args(["-name", "lungdyn"])
        .env("DISPLAY", display)
        .output()
        .expect("run xwininfo (package x11-utils)");
    if !out.status.success() {
        return None;
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let field = |key: &str| {
        text.lines()
            .find_map(|l| l.trim().strip_prefix(key)?.trim().parse::<i64>().ok())
    };
    Some((
        field("Absolute upper-left X:")?,
        field("Absolute upper-left Y:")?,
        field("Width:")?,
        field("Height:")?,
    ))
}

/// Pixels of `img`'s columns `x0..x1` that differ clearly from the background (lungs drawn there).
fn drawn_pixels(img: &image::RgbaImage, x0: u32, x1: u32) -> usize {
    let bg = img.get_pixel(0, 0).0;
    (x0..x1)
        .flat_map(|x| (0..img.height()).map(move |y| (x, y)))
        .filter(|&(x, y)| {
            let p = img.get_pixel(x, y).0;
            (0..3).any(|c| (p[c] as i32 - bg[c] as i32).abs() > 24)
        })
        .count()
}

fn write_scene(path: &Path, extra: &str) {
    std::fs::write(
        path,
        format!("[lungs]\nvertices = 2000\n[render]\nstereo = true\n{extra}"),
    )
    .unwrap();
}

#[test]
fn fullscreen_stereo_fills_a_1280x720_screen_and_draws_both_eyes() {
    if renderer::gpu::Gpu::for_tests().is_none() || !lungdyn_tests::xvfb_available() {
        return;
    }
    let (w, h) = (1280u32, 720u32);
    let mut x = Xvfb::start(w, h);
    let dir = std::env::temp_dir().join(format!("lungdyn-fullscreen-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = dir.join("scene.toml");
    // The scene asks for 800x600 eyes: fullscreen makes them half the screen each instead.
    write_scene(&scene, "width = 800\nheight = 600\n");
    let mut demo = Command::new(bin("lungdyn"))
        .args(["demo", "--fullscreen", "--display", "0", "--seconds", "4"])
        .args(["--snapshots", "1", "--json", "--out"])
        .arg(dir.join("out"))
        .arg("--scene")
        .arg(&scene)
        .env("DISPLAY", &x.display)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // While it runs: the server's own view of the window.
    let t0 = Instant::now();
    let mut geometry = None;
    while t0.elapsed() < Duration::from_secs(120) {
        geometry = window_geometry(&x.display);
        // Stop looking once the demo has ended (its window with it): a failed start is said at
        // once rather than after the whole wait.
        if geometry == Some((0, 0, w as i64, h as i64)) || !matches!(demo.try_wait(), Ok(None)) {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let out = demo.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}\n{}", x.said());
    assert_eq!(
        geometry,
        Some((0, 0, w as i64, h as i64)),
        "the window does not cover the {w}x{h} screen: {stderr}\n{}",
        x.said()
    );
    let v: serde_json::Value =
        serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout}"));
    lungdyn_tests::assert_demo_report_is_consistent(&v, &stderr);
    assert!(v["presented_frames"].as_u64().unwrap() >= 1, "{v}");
    assert_ne!(v["present_mode"], "none", "{v}");
    assert_eq!(v["frame_latency"], 1, "{v}");
    let (p50, max) = (
        v["submit_to_present_p50_ms"].as_f64().unwrap(),
        v["submit_to_present_max_ms"].as_f64().unwrap(),
    );
    assert!(0.0 < p50 && p50 <= max, "{v}");
    // The frame (what the present pass blits 1:1 onto the screen) is the screen's size.
    let png = v["pngs"][0].as_str().expect("one PNG");
    let img = image::open(png).unwrap().to_rgba8();
    assert_eq!(img.dimensions(), (w, h), "{png}");
    // Both eyes drawn: lungs in the left and the right half, and neither is the other's copy
    // (the eyes are an IPD apart).
    let half = w / 2;
    let (left, right) = (drawn_pixels(&img, 0, half), drawn_pixels(&img, half, w));
    let area = (half * h) as usize;
    assert!(
        left > area / 100 && right > area / 100,
        "left eye {left}, right eye {right} of {area} px drawn"
    );
    let differs = (0..half)
        .flat_map(|x| (0..h).map(move |y| (x, y)))
        .any(|(x, y)| img.get_pixel(x, y) != img.get_pixel(x + half, y));
    assert!(differs, "the two eyes are identical: not a stereo pair");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_display_named_wrongly_or_counted_past_the_list_is_refused_listing_the_displays() {
    if !lungdyn_tests::xvfb_available() {
        return;
    }
    let x = Xvfb::start(1024, 600);
    let run = |display: &str| {
        let out = Command::new(bin("lungdyn"))
            .args(["renderer", "--fullscreen", "--display", display])
            .args(["--seconds", "1", "--instance"])
            .arg(lungdyn_tests::unique_instance("display"))
            .env("DISPLAY", &x.display)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(!out.status.success(), "--display {display}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        err
    };
    // Xvfb's one output is 1024x600; the error lists it.
    let err = run("DP-9");
    assert!(
        err.contains("--display DP-9: no display of that name") && err.contains("0: "),
        "{err}"
    );
    assert!(err.contains("1024x600"), "{err}");
    let err = run("3");
    assert!(
        err.contains("--display 3: there are only 1 display(s)") && err.contains("1024x600"),
        "{err}"
    );
}

/// `--xr` on a machine without an OpenXR runtime (CI, this one): a clear error naming what to
/// install and a non-zero exit, never a panic — from the renderer and from the demo. A build
/// without the `openxr` feature says how to build it; a build with it names the loader or the
/// runtime it could not find (`XR_RUNTIME_JSON` pointed at nothing, so an installed runtime is
/// not picked up).
#[test]
fn xr_without_a_runtime_is_a_clear_error_naming_the_loader_or_runtime() {
    let dir = std::env::temp_dir().join(format!("lungdyn-xr-{}", std::process::id()));
    let check = |args: &[&str]| {
        let out = Command::new(bin("lungdyn"))
            .args(args)
            .env("XR_RUNTIME_JSON", "/nonexistent/openxr_runtime.json")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(!out.status.success(), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        let no_feature = err.contains("--xr: this build has no OpenXR support")
            && err.contains("--features openxr");
        let no_loader = err.contains("--xr: no OpenXR loader") && err.contains("libopenxr-loader1");
        let no_runtime = err.contains("--xr: no OpenXR runtime")
            && err.contains("Monado")
            && err.contains("XR_RUNTIME_JSON");
        assert!(no_feature || no_loader || no_runtime, "{args:?}: {err}");
        // Said once: a start-up error is not restarted into a storm of the same message.
        assert_eq!(
            err.matches("lungdyn: error: --xr").count(),
            1,
            "{args:?}: {err}"
        );
    };
    check(&["renderer", "--xr", "--seconds", "1"]);
    let out = dir.join("out");
    check(&[
        "demo",
        "--xr",
        "--seconds",
        "1",
        "--startup-timeout",
        "30",
        "--snapshots",
        "0",
        "--out",
        out.to_str().unwrap(),
    ]);
    std::fs::remove_dir_all(&dir).ok();
}
