//! The remote room against an outside client (issue 37 item 6): the eclipse-zenoh Python package
//! (`tests/peers/zenoh_outsider.py`, not lungdyn's code) tries `lungdyn remote router` started
//! with the room's keys: over plain TCP, over TLS without a certificate and with another room's
//! certificate it does not connect; with this room's observer certificate it connects, and its
//! unsealed probes to the time relay are refused and counted by the router.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use lungdyn_tests::{bin, lungdyn};

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

#[test]
fn an_outside_zenoh_client_without_the_rooms_certificate_cannot_connect() {
    let Some(python) = lungdyn_needs::zenoh_python(&workspace_root()) else {
        return;
    };
    let dir = std::env::temp_dir().join(format!("lungdyn-outsider-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (ours, theirs) = (dir.join("ours"), dir.join("theirs"));
    for d in [&ours, &theirs] {
        let (ok, _, err) = lungdyn(&[
            "remote",
            "keys",
            "--room",
            "ward",
            "--out",
            d.to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
    }
    let port = lungdyn_needs::free_local_port();
    let router = Command::new(bin("lungdyn"))
        .args([
            "remote",
            "router",
            "--listen",
            &format!("tls/127.0.0.1:{port}"),
            "--keys",
        ])
        .arg(&ours)
        .args(["--seconds", "12"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The router's listener is up well before the outsider's first try (a client does not retry).
    std::thread::sleep(std::time::Duration::from_millis(2500));
    let out = Command::new(&python)
        .arg(workspace_root().join("tests/peers/zenoh_outsider.py"))
        .arg(port.to_string())
        .arg(&ours)
        .arg(&theirs)
        .arg("ward")
        .output()
        .unwrap();
    let router = router.wait_with_output().unwrap();
    let said = String::from_utf8_lossy(&router.stderr).to_string();
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for refused in [
        "plain_tcp",
        "tls_without_certificate",
        "another_rooms_certificate",
    ] {
        assert_eq!(v[refused]["connected"], false, "{refused}: {v}");
    }
    assert_eq!(v["this_rooms_observer"]["connected"], true, "{v}\n{said}");
    assert!(router.status.success(), "{said}");
    assert!(
        said.contains("mutual TLS as router (router) of room ward"),
        "{said}"
    );
    // The relay refused the outsider's five unsealed probes, and said so; an observer may probe,
    // so the access control in front of the relay let them through to be refused there.
    assert!(said.contains(", 5 refused"), "{said}");
    assert!(
        said.contains("access control by each link's role"),
        "{said}"
    );
    assert!(said.contains("access control stopped none"), "{said}");
}
