//! The systemd service protocol of the processes: READY=1 once the ports are open, WATCHDOG=1 from
//! the loop at half of `WATCHDOG_USEC`, STOPPING=1 on a clean exit — and no ping while the loop is
//! stopped (SIGSTOP), which is what lets systemd's watchdog restart a hung process.
//! A fake `NOTIFY_SOCKET` (a unix datagram socket this test binds) stands in for systemd.

use std::os::unix::net::UnixDatagram;
use std::process::Command;
use std::time::{Duration, Instant};

use lungdyn_tests::{bin, prepared_scene, unique_instance};

/// A datagram and the kernel's time of its sending.
type Stamped = (Duration, String);

/// Have the kernel stamp each datagram when its sender queues it (`SO_TIMESTAMPNS`): the spacing of
/// the pings is then the sender's, not when this test, sharing a loaded machine, got to read them.
fn stamp_datagrams(sock: &UnixDatagram) {
    use std::os::fd::AsRawFd;
    let on: libc::c_int = 1;
    // SAFETY: setsockopt on an open socket with a c_int option of the size passed.
    let rc = unsafe {
        libc::setsockopt(
            sock.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_TIMESTAMPNS,
            (&on as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    assert_eq!(rc, 0, "SO_TIMESTAMPNS: {}", std::io::Error::last_os_error());
}

/// One datagram (waiting up to `left`) with its kernel send time (realtime clock); None on timeout.
fn recv_stamped(sock: &UnixDatagram, left: Duration) -> Option<Stamped> {
    use std::os::fd::AsRawFd;
    sock.set_read_timeout(Some(left.max(Duration::from_millis(1))))
        .unwrap();
    let mut buf = [0u8; 512];
    let mut control = [0u64; 16];
    let mut iov = libc::iovec {
        iov_base: buf.as_mut_ptr().cast(),
        iov_len: buf.len(),
    };
    // SAFETY: recvmsg into the buffers above, which outlive the call; the control messages are
    // walked with the kernel's own macros within `msg_controllen`.
    unsafe {
        let mut msg: libc::msghdr = std::mem::zeroed();
        msg.msg_iov = &mut iov;
        msg.msg_iovlen = 1;
        msg.msg_control = control.as_mut_ptr().cast();
        msg.msg_controllen = std::mem::size_of_val(&control) as _;
        let n = loop {
            let n = libc::recvmsg(sock.as_raw_fd(), &mut msg, 0);
            if n >= 0 {
                break n;
            }
            let e = std::io::Error::last_os_error();
            match e.kind() {
                std::io::ErrorKind::Interrupted => continue,
                std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => return None,
                _ => panic!("recvmsg: {e}"),
            }
        };
        let text = String::from_utf8_lossy(&buf[..n as usize]).into_owned();
        let mut c = libc::CMSG_FIRSTHDR(&msg);
        while !c.is_null() {
            if (*c).cmsg_level == libc::SOL_SOCKET && (*c).cmsg_type == libc::SCM_TIMESTAMPNS {
                let ts: libc::timespec = std::ptr::read_unaligned(libc::CMSG_DATA(c).cast());
                let sent = Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32);
                return Some((sent, text));
            }
            c = libc::CMSG_NXTHDR(&msg, c);
        }
        panic!("a datagram without its kernel timestamp: {text:?}");
    }
}

/// Every datagram received within `for_`.
fn receive(sock: &UnixDatagram, for_: Duration) -> Vec<Stamped> {
    let end = Instant::now() + for_;
    let mut got = Vec::new();
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        match recv_stamped(sock, left) {
            Some(m) => got.push(m),
            None => break,
        }
    }
    got
}

/// Datagrams until `done` holds for one (included), waiting `limit` at most for it.
fn receive_until(
    sock: &UnixDatagram,
    limit: Duration,
    what: &str,
    done: impl Fn(&Stamped) -> bool,
) -> Vec<Stamped> {
    let end = Instant::now() + limit;
    let mut got = Vec::new();
    loop {
        let left = end
            .checked_duration_since(Instant::now())
            .unwrap_or_else(|| panic!("{what} within {limit:?}: got {got:?}"));
        match recv_stamped(sock, left) {
            Some(m) => {
                let last = done(&m);
                got.push(m);
                if last {
                    return got;
                }
            }
            None => panic!("{what} within {limit:?}: got {got:?}"),
        }
    }
}

/// A small prepared scene (the engine never bakes).
fn scene(tag: &str) -> String {
    prepared_scene(tag, "[lungs]\nvertices = 600\n")
        .to_string_lossy()
        .into_owned()
}

fn count(msgs: &[Stamped], line: &str) -> usize {
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
    stamp_datagrams(&sock);
    let instance = unique_instance("notify");
    // WATCHDOG_USEC 200 ms: a ping every 100 ms.
    // The thin binary the unit runs (installed as lungdyn-engine).
    let child = std::process::Command::new(bin("engine"))
        .args([
            "--instance",
            &instance,
            "--seconds",
            "5",
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
    // Counted from READY=1 by the datagrams' send times (a cold start — scene load, ports — on a
    // loaded machine may take longer than the 1.5 s once counted from the spawn): the first
    // datagram, then every one sent in the 1.5 s after it (read until one sent later arrives).
    let mut first = receive_until(&sock, Duration::from_secs(120), "a first datagram", |_| {
        true
    });
    let ready_at = first[0].0;
    let window = Duration::from_millis(1500);
    first.extend(receive_until(
        &sock,
        Duration::from_secs(60),
        "a datagram sent 1.5 s after the first",
        |(t, _)| *t > ready_at + window,
    ));
    // SAFETY: signalling our own child by its pid.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGSTOP) }, 0);
    // Let a datagram already in flight land, then nothing may come while the process is stopped.
    let _ = receive(&sock, Duration::from_millis(50));
    let hung = receive(&sock, Duration::from_millis(600));
    assert_eq!(unsafe { libc::kill(pid, libc::SIGCONT) }, 0);
    // Until it says it stops (its --seconds end), however long a loaded machine takes.
    let rest = receive_until(&sock, Duration::from_secs(60), "STOPPING=1", |(_, m)| {
        m == "STOPPING=1\n"
    });
    let out = child.wait_with_output().unwrap();
    let after = receive(&sock, Duration::from_millis(50));
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
    let in_window: Vec<Stamped> = first
        .iter()
        .filter(|(t, _)| *t <= ready_at + window)
        .cloned()
        .collect();
    let pings = count(&in_window, "WATCHDOG=1");
    // ≈ 15: 1.5 s at one per 100 ms; at least 5, never per tick.
    assert!(
        (5..=20).contains(&pings),
        "{pings} pings in the 1.5 s after READY=1: {first:?}"
    );
    // Every ping of the run, by its send time: never two within WatchdogSec/2.
    let times: Vec<Duration> = first
        .iter()
        .chain(&rest)
        .filter(|(_, m)| m == "WATCHDOG=1\n")
        .map(|(t, _)| *t)
        .collect();
    for w in times.windows(2) {
        assert!(
            w[1].saturating_sub(w[0]) >= Duration::from_millis(90),
            "pings closer than WatchdogSec/2: {:?}",
            w[1].saturating_sub(w[0])
        );
    }
    assert!(hung.is_empty(), "pings from a stopped process: {hung:?}");
    assert!(count(&rest, "WATCHDOG=1") >= 5, "pings resume: {rest:?}");
    assert!(after.is_empty(), "nothing after STOPPING=1: {after:?}");
}

#[test]
fn without_notify_socket_the_engine_runs_as_before() {
    let instance = unique_instance("nonotify");
    let out = Command::new(bin("engine"))
        .args([
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
        assert_eq!(written.len(), 12, "{written:?}");
        for w in &written {
            assert!(w.starts_with(p), "{w} outside {p}");
            assert!(std::path::Path::new(w).is_file(), "{w}");
        }
        use std::os::unix::fs::PermissionsExt;
        for b in [
            "lungdyn",
            "lungdyn-engine",
            "lungdyn-renderer",
            "lungdyn-tracker-bridge",
        ] {
            assert_eq!(
                std::fs::metadata(prefix.join("bin").join(b))
                    .unwrap()
                    .permissions()
                    .mode()
                    & 0o777,
                0o755,
                "{b}"
            );
        }
        let unit_dir = prefix.join(if user {
            "share/systemd/user"
        } else {
            "lib/systemd/system"
        });
        let engine = std::fs::read_to_string(unit_dir.join("lungdyn-engine.service")).unwrap();
        assert!(engine.contains("CPUAffinity=1\n"), "{engine}");
        // The units run the thin role binaries, never the whole lungdyn.
        for (unit, binary) in [
            ("lungdyn-engine.service", "lungdyn-engine"),
            ("lungdyn-renderer.service", "lungdyn-renderer"),
            ("lungdyn-tracker-bridge.service", "lungdyn-tracker-bridge"),
        ] {
            let text = std::fs::read_to_string(unit_dir.join(unit)).unwrap();
            let exec = prefix.join("bin").join(binary);
            assert!(
                text.contains(&format!("ExecStart={} --instance", exec.display())),
                "{text}"
            );
            let installed = std::fs::read(&exec).unwrap();
            let built = std::fs::read(bin(binary.trim_start_matches("lungdyn-"))).unwrap();
            assert!(installed == built, "{binary} is the crate's own binary");
        }
        let units = [
            "lungdyn-tracker-bridge.service",
            "lungdyn-engine.service",
            "lungdyn-renderer.service",
            "lungdyn.target",
        ];
        if !verify_units(&root, &unit_dir, &units, user) {
            return;
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// `systemd-analyze verify` of the units `names` in `unit_dir` (`--user`, with a runtime folder
/// under `root`, for user units): accepted without a word. False when systemd-analyze is missing and
/// the run opted out of it (`lungdyn_needs::require` counts the skip).
fn verify_units(
    root: &std::path::Path,
    unit_dir: &std::path::Path,
    names: &[&str],
    user: bool,
) -> bool {
    use std::os::unix::fs::PermissionsExt;
    let units: Vec<String> = names
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
        return false;
    };
    let verr = String::from_utf8_lossy(&v.stderr);
    assert!(
        v.status.success() && verr.trim().is_empty(),
        "systemd-analyze verify{}: {verr}",
        if user { " --user" } else { "" }
    );
    true
}

/// A shared session's source installs its relay as its own thin binary (`lungdyn-remote serve`)
/// beside the three, in a unit `systemd-analyze verify` accepts; a site's scene is refused and
/// nothing is written.
#[test]
fn a_sessions_source_installs_its_relay_and_a_site_is_refused() {
    let root = std::env::temp_dir().join(unique_instance("install-remote"));
    std::fs::create_dir_all(&root).unwrap();
    let scene = root.join("source.toml");
    std::fs::write(
        &scene,
        "[lungs]\nvertices = 600\n[remote]\nrole = \"source\"\nroom = \"ward-3\"\n",
    )
    .unwrap();
    let prefix = root.join("p");
    let (ok, out, err) = lungdyn_tests::lungdyn(&[
        "install",
        "--prefix",
        prefix.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let r: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert!(r.to_string().contains("lungdyn-remote.service"), "{r}");
    let unit_dir = prefix.join("lib/systemd/system");
    let unit = std::fs::read_to_string(unit_dir.join("lungdyn-remote.service")).unwrap();
    let exe = prefix.join("bin/lungdyn-remote");
    assert!(
        unit.contains(&format!("ExecStart={} serve --instance", exe.display())),
        "{unit}"
    );
    assert!(std::fs::read(&exe).unwrap() == std::fs::read(bin("remote")).unwrap());
    let target = std::fs::read_to_string(unit_dir.join("lungdyn.target")).unwrap();
    assert!(target.contains("lungdyn-remote.service"), "{target}");
    let units = [
        "lungdyn-tracker-bridge.service",
        "lungdyn-engine.service",
        "lungdyn-renderer.service",
        "lungdyn-remote.service",
        "lungdyn.target",
    ];
    verify_units(&root, &unit_dir, &units, false);
    let site = root.join("site.toml");
    std::fs::write(
        &site,
        "[remote]\nrole = \"site\"\nroom = \"ward-3\"\nconnect = [\"tcp/127.0.0.1:7447\"]\n",
    )
    .unwrap();
    let site_prefix = root.join("site");
    let (ok, _, err) = lungdyn_tests::lungdyn(&[
        "install",
        "--prefix",
        site_prefix.to_str().unwrap(),
        "--scene",
        site.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("lungdyn remote join"), "{err}");
    assert!(!site_prefix.exists(), "nothing written for a refused scene");
    let _ = std::fs::remove_dir_all(&root);
}

/// The deployed processes are thin (issue 33, the architecture's rule): the crates whose binaries
/// the units run link no baking (lung-bake), plotting (plotters), networking (zenoh, the remote
/// crate) or the whole CLI — read from `cargo tree` of each crate's normal dependencies, which must
/// also name the transport they do need (so an empty or failed listing cannot pass).
#[test]
fn the_deployed_binaries_link_no_baking_plotting_or_networking() {
    const BANNED: &[&str] = &[
        "lung-bake",
        "plotters",
        "zenoh",
        "lungdyn-remote",
        "lungdyn",
    ];
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    for (krate, needs, banned) in [
        ("engine", "iceoryx2", BANNED),
        ("renderer", "iceoryx2", BANNED),
        ("tracker-bridge", "iceoryx2", BANNED),
        // The session's relay is networking by design: zenoh, and nothing that bakes or plots.
        (
            "lungdyn-remote",
            "zenoh",
            &["lung-bake", "plotters", "lungdyn", "renderer"][..],
        ),
    ] {
        let out = Command::new(&cargo)
            .args([
                "tree",
                "--offline",
                "-p",
                krate,
                "-e",
                "normal",
                "--prefix",
                "none",
            ])
            .args(["--format", "{p}"])
            .current_dir(&root)
            .output()
            .expect("run cargo tree");
        let tree = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "cargo tree -p {krate}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let names: std::collections::BTreeSet<&str> = tree
            .lines()
            .filter_map(|l| l.split_whitespace().next())
            .collect();
        assert!(names.contains(needs), "{krate}: {names:?}");
        for &banned in banned {
            assert!(
                !names.contains(banned),
                "the {krate} binary links {banned}: `cargo tree -p {krate} -e normal -i {banned}`"
            );
        }
    }
}

/// `install` from a lungdyn with no thin role binaries beside it (a `cargo install` of the CLI
/// alone), or with something else under a role's name, is refused naming the build command, and
/// nothing is written under the prefix.
#[test]
fn install_without_the_thin_binaries_is_refused_and_writes_nothing() {
    use std::os::unix::fs::PermissionsExt;
    // A hard link (current_exe would see through a symbolic one) in a folder of its own.
    let dir = lungdyn_tests::bin_dir().join(unique_instance("thinless"));
    std::fs::create_dir_all(&dir).unwrap();
    let alone = dir.join("lungdyn");
    std::fs::hard_link(bin("lungdyn"), &alone).unwrap();
    let prefix = dir.join("prefix");
    let install = |what: &str| {
        let out = Command::new(&alone)
            .args(["install", "--prefix", prefix.to_str().unwrap()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr).into_owned();
        assert!(!out.status.success(), "{what}: {err}");
        assert!(
            err.contains("cargo build --release -p engine -p renderer -p tracker-bridge"),
            "{what}: {err}"
        );
        assert!(!prefix.exists(), "{what}: nothing written");
        err
    };
    let err = install("no thin binaries");
    for role in ["engine", "renderer", "tracker-bridge"] {
        assert!(
            err.contains(&format!("{}/{role}", dir.display())),
            "{role}: {err}"
        );
    }
    // Something else answering to the role's name.
    for role in ["engine", "renderer", "tracker-bridge"] {
        std::fs::hard_link(bin(role), dir.join(role)).unwrap();
    }
    std::fs::remove_file(dir.join("renderer")).unwrap();
    std::fs::write(
        dir.join("renderer"),
        "#!/bin/sh\necho 'some other renderer'\n",
    )
    .unwrap();
    std::fs::set_permissions(dir.join("renderer"), std::fs::Permissions::from_mode(0o755)).unwrap();
    let err = install("a foreign renderer");
    assert!(err.contains("is not lungdyn's renderer binary"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An installed scene carries the files it names: a `[pv] waveform` recording and a replayed
/// tracker recording are copied under the prefix and named there (the bridge's unit too), so the
/// service keeps working once the folder the scene came from is gone.
#[test]
fn an_installed_scene_carries_the_files_it_names() {
    let root = std::env::temp_dir().join(unique_instance("carry"));
    let src = root.join("src");
    std::fs::create_dir_all(src.join("recordings")).unwrap();
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    std::fs::copy(
        repo.join("scenes/recordings/ventilated_vc_synthetic.csv"),
        src.join("recordings/vc.csv"),
    )
    .unwrap();
    let poses = src.join("poses.rec");
    let (ok, _, err) = lungdyn_tests::lungdyn(&[
        "tracker",
        "simulate",
        "--out",
        poses.to_str().unwrap(),
        "--seconds",
        "1",
    ]);
    assert!(ok, "{err}");
    let scene = src.join("scene.toml");
    std::fs::write(
        &scene,
        format!(
            "[pv]\npreset = \"venegas-human\"\nwaveform = \"recordings/vc.csv\"\n[lungs]\n\
             vertices = 600\n[tracker]\nsource = \"replay:{}\"\n",
            poses.display()
        ),
    )
    .unwrap();
    let prefix = root.join("prefix");
    let (ok, out, err) = lungdyn_tests::lungdyn(&[
        "install",
        "--prefix",
        prefix.to_str().unwrap(),
        "--scene",
        scene.to_str().unwrap(),
        "--json",
    ]);
    assert!(ok, "{err}");
    let r: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let carried: Vec<&str> = r["written"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|w| w["what"].as_str().unwrap().contains("copied from"))
        .map(|w| w["path"].as_str().unwrap())
        .collect();
    assert_eq!(carried.len(), 2, "{r}");
    std::fs::remove_dir_all(&src).unwrap();
    let resolved = prefix.join("share/lungdyn/kernels/scene.resolved.toml");
    let (ok, _, err) = lungdyn_tests::lungdyn(&["scene", "check", resolved.to_str().unwrap()]);
    assert!(ok, "the installed scene without its source folder: {err}");
    let text = std::fs::read_to_string(&resolved).unwrap();
    let files = prefix.join("share/lungdyn/files");
    assert!(
        text.contains(&format!("{}/pv-waveform-vc.csv", files.display())),
        "{text}"
    );
    let bridge =
        std::fs::read_to_string(prefix.join("lib/systemd/system/lungdyn-tracker-bridge.service"))
            .unwrap();
    // The unit passes the scene, not its values: the bridge reads the carried recording from the
    // installed scene's [tracker] table itself.
    assert!(
        bridge.contains(&format!("--scene {}", resolved.display())) && !bridge.contains("--source"),
        "{bridge}"
    );
    assert!(
        text.contains(&format!(
            "source = \"replay:{}/tracker-replay-poses.rec\"",
            files.display()
        )),
        "{text}"
    );
    let out = std::process::Command::new(lungdyn_tests::bin("tracker-bridge"))
        .args(["--instance", &format!("svc-carry-{}", std::process::id())])
        .args(["--scene", resolved.to_str().unwrap(), "--seconds", "1"])
        .args(["--as-fast-as-possible"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "the installed bridge on its scene: {err}"
    );
    assert!(err.contains("tracker-replay-poses.rec"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}
