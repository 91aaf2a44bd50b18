//! Helpers shared by the workspace-level tests.

use std::path::PathBuf;

/// The folder holding the workspace's built binaries (`target/<profile>`), derived from the test
/// executable's own path (`target/<profile>/deps/<test>`).
pub fn bin_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    exe.parent()
        .and_then(|p| p.parent())
        .expect("target/<profile>/deps layout")
        .to_path_buf()
}

/// Path of workspace binary `name`; panics with a fix if it has not been built.
pub fn bin(name: &str) -> PathBuf {
    let p = bin_dir().join(name);
    assert!(
        p.exists(),
        "{} is missing: run the tests with `cargo test --workspace` so every binary is built",
        p.display()
    );
    p
}

/// A unique instance name for one test.
pub fn unique_instance(tag: &str) -> String {
    format!(
        "t-{tag}-{}-{}",
        std::process::id(),
        ipc_types::now_ns() % 1_000_000
    )
}

/// Run the `lungdyn` binary with `args`: (success, stdout, stderr).
pub fn lungdyn(args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(bin("lungdyn"))
        .args(args)
        .output()
        .expect("run lungdyn");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Run `lungdyn args`, expecting a non-zero exit whose stderr contains `needle` and no panic.
pub fn assert_clean_failure(args: &[&str], needle: &str) {
    let (ok, _, err) = lungdyn(args);
    assert!(!ok, "{args:?} should fail");
    assert!(
        err.contains(needle),
        "{args:?}: expected {needle:?} in: {err}"
    );
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
}
