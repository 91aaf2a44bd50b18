//! The `lungdyn` binary's command line: `--help` explains it, an unknown argument is one clear
//! error with a non-zero exit. (Also makes `cargo test` build the binary, which the workspace's
//! multi-process tests start.)

use std::process::Command;

#[test]
fn help_explains_and_unknown_arguments_fail_cleanly() {
    let exe = env!("CARGO_BIN_EXE_lungdyn");
    let help = Command::new(exe).arg("--help").output().unwrap();
    assert!(help.status.success());
    let text = String::from_utf8_lossy(&help.stdout);
    assert!(text.contains("Usage"), "{text}");
    let bad = Command::new(exe).arg("--no-such-flag").output().unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("--no-such-flag") && !err.contains("panicked"),
        "{err}"
    );
}
