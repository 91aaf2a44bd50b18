//! The systemd service protocol of the processes: READY=1 once the ports are open, WATCHDOG=1 from
//! the loop at half of `WATCHDOG_USEC`, STOPPING=1 on a clean exit — and no ping while the loop is
//! stopped (SIGSTOP), which is what lets systemd's watchdog restart a hung process.
//! A fake `NOTIFY_SOCKET` (a unix datagram socket this test binds) stands in for systemd.

use std::os::unix::net::UnixDatagram;
use std::process::Command;
use std::time::{Duration, Instant};

use lungdyn_tests::{bin, prepared_scene, unique_instance};

/// Every datagram received within `for_`, with its arrival time.
fn receive(sock: &UnixDatagram, for_: Duration) -> Vec<(Instant, String)> {
    let end = Instant::now() + for_;
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        sock.set_read_timeout(Some(left.max(Duration::from_millis(1))))
            .unwrap();
        match sock.recv(&mut buf) {
            Ok(n) => got.push((
                Instant::now(),
                String::from_utf8_lossy(&buf[..n]).into_owned(),
            )),
            Err(e)
                if e.kind() == std::io::ErrorKind::WouldBlock
                    || e.kind() == std::io::ErrorKind::TimedOut =>
            {
                break
            }
            Err(e) => panic!("recv: {e}"),
        }
    }
    got
}

/// A small prepared scene (the engine never bakes).
fn scene(tag: &str) -> String {
    prepared_scene(tag, "[lungs]\nvertices = 600\n")
        .to_string_lossy()
        .into_owned()
}

fn count(msgs: &[(Instant, String)], line: &str) -> usize {
    msgs.iter()
        .filter(|(_, m)| m.lines().any(|l| l == line))
        .count()
}

#[test]
fn the_engine_notifies_ready_pings_the_watchdog_from_its_loop_and_stops_pinging_when_hung() {
    let dir = std::env::temp_dir().join(unique_instance("notify"));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("notify.sock");
    let sock = UnixDatagram::bind(&path).unwrap();
    let instance = unique_instance("notify");
    // WATCHDOG_USEC 200 ms: a ping every 100 ms.
    let child = std::process::Command::new(bin("lungdyn"))
        .args([
            "engine",
            "--instance",
            &instance,
            "--seconds",
            "4",
            "--scene",
            &scene("notify"),
        ])
        .env("NOTIFY_SOCKET", &path)
        .env("WATCHDOG_USEC", "200000")
        .env_remove("WATCHDOG_PID")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as libc::pid_t;
    let first = receive(&sock, Duration::from_millis(1500));
    // SAFETY: signalling our own child by its pid.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGSTOP) }, 0);
    // Let a datagram already in flight land, then nothing may come while the process is stopped.
    let _ = receive(&sock, Duration::from_millis(50));
    let hung = receive(&sock, Duration::from_millis(600));
    assert_eq!(unsafe { libc::kill(pid, libc::SIGCONT) }, 0);
    let rest = receive(&sock, Duration::from_secs(6));
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);

    assert!(
        first
            .first()
            .is_some_and(|(_, m)| m.lines().any(|l| l == "READY=1")
                && m.lines().any(|l| l.starts_with("STATUS=engine["))),
        "READY=1 with a status first: {first:?}"
    );
    let pings = count(&first, "WATCHDOG=1");
    // ≈ 1.5 s at one per 100 ms, minus start-up (scene load, ports): at least 5, never per tick.
    assert!(
        (5..=20).contains(&pings),
        "{pings} pings in 1.5 s: {first:?}"
    );
    let times: Vec<Instant> = first
        .iter()
        .filter(|(_, m)| m == "WATCHDOG=1\n")
        .map(|(t, _)| *t)
        .collect();
    for w in times.windows(2) {
        assert!(
            w[1] - w[0] >= Duration::from_millis(90),
            "pings closer than WatchdogSec/2: {:?}",
            w[1] - w[0]
        );
    }
    assert!(hung.is_empty(), "pings from a stopped process: {hung:?}");
    assert!(count(&rest, "WATCHDOG=1") >= 5, "pings resume: {rest:?}");
    assert_eq!(
        rest.last().map(|(_, m)| m.as_str()),
        Some("STOPPING=1\n"),
        "{rest:?}"
    );
}

#[test]
fn without_notify_socket_the_engine_runs_as_before() {
    let instance = unique_instance("nonotify");
    let out = Command::new(bin("lungdyn"))
        .args([
            "engine",
            "--instance",
            &instance,
            "--seconds",
            "0.3",
            "--scene",
            &scene("nonotify"),
        ])
        .env_remove("NOTIFY_SOCKET")
        .env("WATCHDOG_USEC", "1000")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(!stderr.contains("systemd"), "{stderr}");
}

/// `lungdyn install` writes only under its prefix (system and user layouts), the binary executable,
/// and units that `systemd-analyze verify` accepts without a warning.
#[test]
fn install_writes_under_its_prefix_and_the_units_verify() {
    let root = std::env::temp_dir().join(unique_instance("install"));
    let scene = root.join("scene.toml");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 600\n[processes]\ncpus = [0, 1, 1]\n",
    )
    .unwrap();
    for user in [false, true] {
        let prefix = root.join(if user { "user" } else { "system" });
        let p = prefix.to_str().unwrap();
        let mut args = vec![
            "install",
            "--prefix",
            p,
            "--scene",
            scene.to_str().unwrap(),
            "--json",
        ];
        if user {
            args.push("--user");
        }
        let (ok, out, err) = lungdyn_tests::lungdyn(&args);
        assert!(ok, "{err}");
        let r: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        let written: Vec<&str> = r["written"]
            .as_array()
            .unwrap()
            .iter()
            .map(|w| w["path"].as_str().unwrap())
            .collect();
        assert_eq!(written.len(), 9, "{written:?}");
        for w in &written {
            assert!(w.starts_with(p), "{w} outside {p}");
            assert!(std::path::Path::new(w).is_file(), "{w}");
        }
        use std::os::unix::fs::PermissionsExt;
        let bin = prefix.join("bin/lungdyn");
        assert_eq!(
            std::fs::metadata(&bin).unwrap().permissions().mode() & 0o777,
            0o755
        );
        let unit_dir = prefix.join(if user {
            "share/systemd/user"
        } else {
            "lib/systemd/system"
        });
        let engine = std::fs::read_to_string(unit_dir.join("lungdyn-engine.service")).unwrap();
        assert!(engine.contains("CPUAffinity=1\n"), "{engine}");
        assert!(engine.contains(&format!("ExecStart={} engine", bin.display())));
        let units: Vec<String> = [
            "lungdyn-tracker-bridge.service",
            "lungdyn-engine.service",
            "lungdyn-renderer.service",
            "lungdyn.target",
        ]
        .iter()
        .map(|u| unit_dir.join(u).to_string_lossy().into_owned())
        .collect();
        let mut verify = Command::new("systemd-analyze");
        if user {
            // The user manager needs a runtime folder even to verify.
            let rt = root.join("runtime");
            std::fs::create_dir_all(&rt).unwrap();
            std::fs::set_permissions(&rt, std::fs::Permissions::from_mode(0o700)).unwrap();
            verify.arg("--user").env("XDG_RUNTIME_DIR", &rt);
        }
        let Some(v) = lungdyn_needs::require(
            lungdyn_needs::Need::Systemd,
            verify.arg("verify").args(&units).output(),
        ) else {
            return;
        };
        let verr = String::from_utf8_lossy(&v.stderr);
        assert!(
            v.status.success() && verr.trim().is_empty(),
            "systemd-analyze verify{}: {verr}",
            if user { " --user" } else { "" }
        );
    }
    let _ = std::fs::remove_dir_all(&root);
}
