//! What a test needs from the machine, and one policy for when it is not there.
//!
//! A test that needs a GPU adapter, a display or a peer program and cannot get one **fails**, naming
//! the package that provides it and the command that installs it — a green run that tested none of
//! the renderer is worse than a red one. The person running the tests may opt out explicitly, per
//! need (`LUNGDYN_SKIP_GPU=1`, `LUNGDYN_SKIP_DISPLAY=1`, `LUNGDYN_SKIP_PYIGTL=1`,
//! `LUNGDYN_SKIP_PYZENOH=1`, `LUNGDYN_SKIP_GLTF=1`, `LUNGDYN_SKIP_BROWSER=1`, or
//! `LUNGDYN_SKIP_ALL=1`); then the test returns early and the skip is said aloud twice:
//!
//! - at once, on the terminal's stderr, past the test harness's output capture (so a passing test's
//!   skip is not swallowed), and
//! - as one line appended to the skip log (`LUNGDYN_SKIP_LOG`, default
//!   `$TMPDIR/lungdyn-skipped-tests.log`), which `./run test` empties before the run and counts after
//!   it ("3 tests skipped: …").
//!
//! `LUNGDYN_REQUIRE_GPU=1` / `LUNGDYN_REQUIRE_PYIGTL=1` (what CI sets) forbid the opt-out: with them a
//! missing need fails even where a skip variable is set.
//!
//! One need is the other way round: an OpenXR runtime ([`Need::OpenXr`]) is built from source (no
//! Debian 12 package; CI does not build it), so its tests run where one is named
//! (`LUNGDYN_XR_RUNTIME`) and are otherwise skipped — aloud and logged, as an
//! opt-out is — unless `LUNGDYN_REQUIRE_XR=1`, which makes a missing runtime a failure naming the fix.

use std::io::Write;
use std::path::PathBuf;

/// Something a test needs from the machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Need {
    /// A Vulkan adapter for wgpu (a real GPU, or Mesa's lavapipe on a machine without one).
    Gpu,
    /// An X display for windowed tests (Xvfb's `xvfb-run` on a headless machine).
    Display,
    /// Python 3 with pyigtl and numpy: a real OpenIGTLink peer for the interop tests.
    Pyigtl,
    /// Python 3 with eclipse-zenoh: an outside Zenoh client for the remote sessions' hostile tests.
    PyZenoh,
    /// systemd's `systemd-analyze` (package systemd), to verify the service units.
    Systemd,
    /// An OpenXR runtime's manifest (`LUNGDYN_XR_RUNTIME`) and a launcher
    /// built with the `openxr` feature. Opt-in: skipped unless named or required.
    OpenXr,
    /// Node.js with the Khronos glTF validator (npm `gltf-validator`), the independent judge of
    /// `lungdyn export gltf`'s files.
    GltfValidator,
    /// A real browser: Chromium driven by playwright-core, showing a glTF file in Google's
    /// `<model-viewer>` (npm `@google/model-viewer`).
    Browser,
}

impl Need {
    /// Every need, for listings.
    pub const ALL: [Need; 8] = [
        Need::Gpu,
        Need::Display,
        Need::Pyigtl,
        Need::PyZenoh,
        Need::Systemd,
        Need::OpenXr,
        Need::GltfValidator,
        Need::Browser,
    ];

    /// The opt-out variable for this need.
    pub fn skip_var(self) -> &'static str {
        match self {
            Need::Gpu => "LUNGDYN_SKIP_GPU",
            Need::Display => "LUNGDYN_SKIP_DISPLAY",
            Need::Pyigtl => "LUNGDYN_SKIP_PYIGTL",
            Need::PyZenoh => "LUNGDYN_SKIP_PYZENOH",
            Need::Systemd => "LUNGDYN_SKIP_SYSTEMD",
            Need::OpenXr => "LUNGDYN_SKIP_XR",
            Need::GltfValidator => "LUNGDYN_SKIP_GLTF",
            Need::Browser => "LUNGDYN_SKIP_BROWSER",
        }
    }

    /// The variable that forbids the opt-out (CI sets it).
    pub fn require_var(self) -> &'static str {
        match self {
            Need::Gpu | Need::Display => "LUNGDYN_REQUIRE_GPU",
            Need::Pyigtl => "LUNGDYN_REQUIRE_PYIGTL",
            Need::PyZenoh => "LUNGDYN_REQUIRE_PYZENOH",
            Need::Systemd => "LUNGDYN_REQUIRE_SYSTEMD",
            Need::OpenXr => "LUNGDYN_REQUIRE_XR",
            Need::GltfValidator => "LUNGDYN_REQUIRE_GLTF",
            Need::Browser => "LUNGDYN_REQUIRE_BROWSER",
        }
    }

    /// What provides it, and the command that installs it.
    pub fn fix(self) -> &'static str {
        match self {
            Need::Gpu => {
                "install a Vulkan driver — on a machine without a GPU, Mesa's lavapipe: \
                 `sudo apt-get install mesa-vulkan-drivers libvulkan1` (or run the tests with `./run test`, \
                 which installs it)"
            }
            Need::Display => {
                "install Xvfb for a virtual display: `sudo apt-get install xvfb xauth` (or run the tests \
                 with `./run test`, which installs it)"
            }
            Need::Pyigtl => {
                "install the pyigtl Python package (a real OpenIGTLink peer): `./run test` makes a \
                 virtual environment with it under target/pyenv; or `python3 -m pip install pyigtl` and \
                 point LUNGDYN_PYTHON at that python"
            }
            Need::PyZenoh => {
                "install the eclipse-zenoh Python package (an outside Zenoh client): `./run test` \
                 puts it in the virtual environment under target/pyenv; or `python3 -m pip install \
                 eclipse-zenoh==1.10.2` and point LUNGDYN_PYTHON at that python"
            }
            Need::Systemd => {
                "install systemd's tools for `systemd-analyze verify`: `sudo apt-get install systemd` \
                 (it needs no running systemd)"
            }
            Need::OpenXr => {
                "install an OpenXR runtime and name its manifest: `deploy/xr_check.sh` builds Monado \
                 (pinned commit, null compositor, simulated headset) and runs this check against it; \
                 by hand, set LUNGDYN_XR_RUNTIME to the runtime's JSON manifest \
                 (XRT_COMPOSITOR_NULL=1 for Monado without a display); the launcher is built with \
                 OpenXR by default (`--features openxr` where default features are off)"
            }
            Need::GltfValidator => {
                "install Node.js and the Khronos glTF validator: `./run test` installs them \
                 (`sudo apt-get install nodejs npm`, then `npm install --prefix target/npm \
                 gltf-validator@2.0.0-dev.3.10`); or point LUNGDYN_NODE_MODULES at a node_modules \
                 folder that has it"
            }
            Need::Browser => {
                "install Chromium and the page's packages: `./run test` installs them (`sudo apt-get \
                 install chromium`, then `npm install --prefix target/npm playwright-core@1.58.2 \
                 @google/model-viewer@4.4.0`); LUNGDYN_CHROMIUM names another Chromium"
            }
        }
    }

    fn article(self) -> &'static str {
        match self {
            Need::OpenXr => "an",
            _ => "a",
        }
    }

    fn name(self) -> &'static str {
        match self {
            Need::Gpu => "GPU adapter",
            Need::Display => "display",
            Need::Pyigtl => "pyigtl",
            Need::PyZenoh => "eclipse-zenoh",
            Need::Systemd => "systemd-analyze",
            Need::OpenXr => "OpenXR runtime",
            Need::GltfValidator => "glTF validator",
            Need::Browser => "browser",
        }
    }
}

fn var_is_1(name: &str) -> bool {
    std::env::var(name).as_deref() == Ok("1")
}

/// Whether `need` is one whose tests run only where it is named or required ([`Need::OpenXr`]).
pub fn opt_in(need: Need) -> bool {
    need == Need::OpenXr
}

/// Whether the person running the tests opted out of `need` (and nothing forbids it); an opt-in
/// need is out unless required.
pub fn opted_out(need: Need) -> bool {
    !var_is_1(need.require_var())
        && (opt_in(need) || var_is_1(need.skip_var()) || var_is_1("LUNGDYN_SKIP_ALL"))
}

/// Where skips are logged: `LUNGDYN_SKIP_LOG`, or a file in the temporary folder.
pub fn skip_log() -> PathBuf {
    std::env::var_os("LUNGDYN_SKIP_LOG")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("lungdyn-skipped-tests.log"))
}

/// The test's name as libtest gives it to its thread ("module::test_name"), or "a test".
fn test_name() -> String {
    std::thread::current()
        .name()
        .filter(|n| *n != "main")
        .unwrap_or("a test")
        .to_string()
}

/// `need` is missing (`detail` says how it was found missing): panic naming the fix, or — when the
/// person opted out — say the skip aloud, log it, and return so the test can return early.
///
/// # Panics
/// Unless opted out: that is the point (a missing need is a failing test).
pub fn missing(need: Need, detail: &str) {
    let test = test_name();
    if !opted_out(need) {
        // Under the require variable no skip is possible, so the advice is to unset it.
        let skip = if var_is_1(need.require_var()) {
            format!(
                "{}=1 is set, which forbids skipping it; unset it to let such tests be skipped",
                need.require_var()
            )
        } else {
            format!(
                "To skip such tests deliberately, set {}=1 (the run then counts them as skipped).",
                need.skip_var()
            )
        };
        panic!(
            "{test} needs {} {}, and there is none ({detail}).\nFix: {}.\n{skip}",
            need.article(),
            need.name(),
            need.fix(),
        );
    }
    let why = if opt_in(need) && !var_is_1(need.skip_var()) {
        format!(
            "it runs only where one is named; {}=1 makes this a failure",
            need.require_var()
        )
    } else {
        format!("{}=1 is set", need.skip_var())
    };
    let line = format!("SKIPPED {test}: no {} ({detail}); {why}", need.name());
    // Past the harness's capture: libtest captures `eprintln!`, not writes to the stream itself.
    let _ = writeln!(std::io::stderr(), "lungdyn: {line}");
    if let Ok(mut f) = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(skip_log())
    {
        // One `write` of one line: appends from parallel tests do not interleave.
        let _ = f.write_all(format!("{line}\n").as_bytes());
    }
}

/// `Some(value)` when `probe` finds the need, else [`missing`] (panic, or `None` on an opt-out).
pub fn require<T, E: std::fmt::Display>(need: Need, probe: Result<T, E>) -> Option<T> {
    match probe {
        Ok(v) => Some(v),
        Err(e) => {
            missing(need, &e.to_string());
            None
        }
    }
}

/// Whether a display can be had for a windowed test: `xvfb-run` on PATH ([`missing`] otherwise).
pub fn display() -> bool {
    let found = std::process::Command::new("xvfb-run")
        .arg("--help")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok();
    if !found {
        missing(Need::Display, "xvfb-run is not on PATH");
    }
    found
}

/// The `node_modules` folder with every one of `packages` and a `node` that runs:
/// `LUNGDYN_NODE_MODULES`, else `target/npm/node_modules` under the workspace (made by `./run test`),
/// or [`missing`] `need`.
pub fn node_modules(
    workspace_root: &std::path::Path,
    packages: &[&str],
    need: Need,
) -> Option<PathBuf> {
    let dir = std::env::var_os("LUNGDYN_NODE_MODULES")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root.join("target/npm/node_modules"));
    let node = std::process::Command::new("node")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !node {
        missing(
            need,
            "`node --version` does not run: Node.js is not on PATH",
        );
        return None;
    }
    let absent: Vec<&str> = packages
        .iter()
        .copied()
        .filter(|p| !dir.join(p).join("package.json").is_file())
        .collect();
    if !absent.is_empty() {
        missing(
            need,
            &format!("{} has no {}", dir.display(), absent.join(", ")),
        );
        return None;
    }
    Some(dir)
}

/// A Chromium to drive: `LUNGDYN_CHROMIUM`, else `chromium` or `chromium-browser` on PATH, the first
/// that answers `--version`, or [`missing`] [`Need::Browser`].
pub fn chromium() -> Option<PathBuf> {
    let candidates = std::env::var_os("LUNGDYN_CHROMIUM")
        .map(PathBuf::from)
        .into_iter()
        .chain(["chromium", "chromium-browser"].map(PathBuf::from));
    let mut tried = Vec::new();
    for c in candidates {
        let ok = std::process::Command::new(&c)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success());
        if ok {
            // playwright wants a path, not a name to look up.
            return Some(which(&c).unwrap_or(c));
        }
        tried.push(c.display().to_string());
    }
    missing(Need::Browser, &format!("none of {} runs", tried.join(", ")));
    None
}

/// `name` found on PATH (a path with a slash is itself).
fn which(name: &std::path::Path) -> Option<PathBuf> {
    if name.components().count() > 1 {
        return Some(name.to_path_buf());
    }
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// The Python that has eclipse-zenoh: `LUNGDYN_PYTHON`, else `target/pyenv/bin/python3`, else
/// `python3` on PATH — the first that imports zenoh, or [`missing`].
pub fn zenoh_python(workspace_root: &std::path::Path) -> Option<PathBuf> {
    python_with(workspace_root, "zenoh", Need::PyZenoh)
}

/// The Python that has pyigtl: `LUNGDYN_PYTHON`, else `target/pyenv/bin/python3` under the workspace
/// (made by `./run test`), else `python3` on PATH — the first that imports pyigtl and numpy, or
/// [`missing`].
pub fn pyigtl_python(workspace_root: &std::path::Path) -> Option<PathBuf> {
    python_with(workspace_root, "pyigtl, numpy", Need::Pyigtl)
}

/// The first of `LUNGDYN_PYTHON`, the workspace's `target/pyenv` and `python3` that runs
/// `import {imports}`, or [`missing`] `need`.
fn python_with(workspace_root: &std::path::Path, imports: &str, need: Need) -> Option<PathBuf> {
    let mut tried = Vec::new();
    let candidates = std::env::var_os("LUNGDYN_PYTHON")
        .map(PathBuf::from)
        .into_iter()
        .chain([
            workspace_root.join("target/pyenv/bin/python3"),
            PathBuf::from("python3"),
        ]);
    for py in candidates {
        let ok = std::process::Command::new(&py)
            .args(["-c", &format!("import {imports}")])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if ok {
            return Some(py);
        }
        tried.push(py.display().to_string());
    }
    missing(
        need,
        &format!("none of {} imports {imports}", tried.join(", ")),
    );
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_need_names_a_fix_and_its_variables() {
        for n in Need::ALL {
            assert!(n.fix().contains("install"), "{n:?}");
            assert!(n.skip_var().starts_with("LUNGDYN_SKIP_"));
            assert!(n.require_var().starts_with("LUNGDYN_REQUIRE_"));
        }
    }

    #[test]
    fn a_missing_need_fails_unless_opted_out() {
        // The process environment is shared by the tests of this binary: only this test touches it.
        // SAFETY (edition 2021: set_var is safe to call): no other thread of this binary reads these.
        std::env::remove_var("LUNGDYN_SKIP_GPU");
        std::env::remove_var("LUNGDYN_SKIP_ALL");
        std::env::remove_var("LUNGDYN_REQUIRE_GPU");
        let log = std::env::temp_dir().join(format!("lungdyn-needs-{}.log", std::process::id()));
        std::env::set_var("LUNGDYN_SKIP_LOG", &log);
        let _ = std::fs::remove_file(&log);
        let failed = std::panic::catch_unwind(|| {
            missing(Need::Gpu, "the skip path's own unit test, not a real skip")
        });
        let msg = failed
            .expect_err("no opt-out: a failure")
            .downcast::<String>()
            .map(|s| *s)
            .unwrap_or_default();
        assert!(
            msg.contains("mesa-vulkan-drivers") && msg.contains("LUNGDYN_SKIP_GPU=1"),
            "{msg}"
        );
        assert!(!log.exists(), "a failure is not a skip");

        std::env::set_var("LUNGDYN_SKIP_GPU", "1");
        assert!(opted_out(Need::Gpu));
        assert!(!opted_out(Need::Pyigtl), "an opt-out is per need");
        missing(Need::Gpu, "the skip path's own unit test, not a real skip");
        let logged = std::fs::read_to_string(&log).unwrap();
        assert_eq!(logged.lines().count(), 1, "{logged}");
        assert!(
            logged.contains("SKIPPED") && logged.contains("not a real skip"),
            "{logged}"
        );

        // What CI sets forbids the opt-out.
        std::env::set_var("LUNGDYN_REQUIRE_GPU", "1");
        assert!(!opted_out(Need::Gpu));
        assert!(std::panic::catch_unwind(|| missing(Need::Gpu, "x")).is_err());

        // The OpenXR runtime is opt-in: skipped aloud and logged unless required, then a failure
        // naming the fix.
        std::env::remove_var("LUNGDYN_REQUIRE_XR");
        assert!(opted_out(Need::OpenXr));
        missing(
            Need::OpenXr,
            "the opt-in path's own unit test, not a real skip",
        );
        let logged = std::fs::read_to_string(&log).unwrap();
        assert_eq!(logged.lines().count(), 2, "{logged}");
        assert!(
            logged.contains("no OpenXR runtime") && logged.contains("LUNGDYN_REQUIRE_XR=1 makes"),
            "{logged}"
        );
        std::env::set_var("LUNGDYN_REQUIRE_XR", "1");
        assert!(!opted_out(Need::OpenXr));
        let msg = std::panic::catch_unwind(|| missing(Need::OpenXr, "x"))
            .expect_err("required: a failure")
            .downcast::<String>()
            .map(|s| *s)
            .unwrap_or_default();
        assert!(
            msg.contains("deploy/xr_check.sh") && msg.contains("LUNGDYN_XR_RUNTIME"),
            "{msg}"
        );
        for v in [
            "LUNGDYN_SKIP_GPU",
            "LUNGDYN_REQUIRE_GPU",
            "LUNGDYN_REQUIRE_XR",
            "LUNGDYN_SKIP_LOG",
        ] {
            std::env::remove_var(v);
        }
        let _ = std::fs::remove_file(&log);
    }
}

/// A TCP port on 127.0.0.1 that is free now, for a server a test starts a moment later (often in a
/// child process). Taken below the kernel's ephemeral range (32768–60999 by default), where neither
/// `bind(0)` nor a client's source port is ever picked, and never the same one twice in a process:
/// a port found with `bind(0)` and released can be handed to another test's `bind(0)` or to a
/// connection's source port before the server takes it, which made tests running side by side fail
/// (the server's bind refused, or a client reaching the other test's server).
pub fn free_local_port() -> u16 {
    use std::sync::atomic::{AtomicU32, Ordering};
    const LOW: u32 = 20_000;
    const SPAN: u32 = 10_000;
    static NEXT: AtomicU32 = AtomicU32::new(0);
    // Where this process starts in the span, from its pid and the time, spread over the whole
    // span: two test binaries running at once (parallel cargo runs on one machine) start far apart.
    static START: std::sync::OnceLock<u32> = std::sync::OnceLock::new();
    let start = *START.get_or_init(|| {
        use std::hash::{BuildHasher, Hasher};
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u32(std::process::id());
        h.write_u128(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos()),
        );
        (h.finish() % u64::from(SPAN)) as u32
    });
    loop {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        assert!(
            n < SPAN,
            "no free TCP port in {LOW}..{} on 127.0.0.1",
            LOW + SPAN
        );
        let port = (LOW + (start + n) % SPAN) as u16;
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok() {
            return port;
        }
    }
}

/// The command-line check every lungdyn binary's tests share (`cli`, `engine`, `renderer`,
/// `tracker-bridge`: each crate's `tests/command_line.rs`, which also makes `cargo test` build the
/// binary the multi-process tests start): `--help` succeeds, explains (a usage line) and names the
/// binary as `lungdyn <name>` in its first line (what `lungdyn install` checks a thin role binary
/// by); an unknown flag is one clear error naming it, with a non-zero exit and no panic.
pub fn check_command_line(exe: &str, name: &str) {
    use std::process::Command;
    let help = Command::new(exe).arg("--help").output().unwrap();
    assert!(help.status.success(), "{exe} --help");
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("Usage"), "{text}");
    assert!(
        text.starts_with(&format!("lungdyn {name}")) || name == "lungdyn",
        "the first line of {exe} --help names it as `lungdyn {name}`: {text}"
    );
    let bad = Command::new(exe).arg("--no-such-flag").output().unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("--no-such-flag") && !err.contains("panicked"),
        "{err}"
    );
}
