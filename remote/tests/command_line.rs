//! The `remote` binary's command line: `--help` explains it, an unknown argument is one clear error
//! with a non-zero exit (the check every binary shares, `lungdyn_needs::check_command_line`). Also
//! makes `cargo test` build the binary, which `lungdyn install` copies for a source's scene.

#[test]
fn help_explains_and_unknown_arguments_fail_cleanly() {
    lungdyn_needs::check_command_line(env!("CARGO_BIN_EXE_remote"), "remote");
}
