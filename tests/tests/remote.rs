//! A shared session end to end (issue 24, seed §8.3): `lungdyn demo` on a source scene (its
//! `[remote]` table starts `lungdyn remote serve` beside the engine) and one site joined with
//! `lungdyn remote join --observer` as its own process, on loopback (an explicit tcp/127.0.0.1 port,
//! multicast scouting off, a 2 s lease). The test reads both instances' engine streams and checks
//! the site stepped the source's ticks with the source's volumes, bit for bit, over whole cycles of
//! a tension pneumothorax's course; and both tools' own words (states published, applied, refused,
//! sites present). Counted in cycles, not milliseconds: slow starts on a loaded machine only wait.
//! The same through `lungdyn remote router` (the site syncs its clock with the router's time relay).
//! Also: `remote serve` and `remote join` take the same session flags, and `remote harness --router`
//! reports the source's own cost and the relay's.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lungdyn_tests::{bin, lungdyn, unique_instance};
use transport::{iox, Instance, Receive};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lungdyn-remote-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join(name)
}

/// Killed (SIGINT, then SIGKILL) if still running when dropped.
struct Proc(Child, &'static str);

impl Proc {
    fn interrupt_and_wait(&mut self) -> std::process::ExitStatus {
        // Already ended and reaped: its pid may belong to another process now.
        if let Some(s) = self.0.try_wait().unwrap() {
            return s;
        }
        // SAFETY: a signal to our own child, not reaped yet (we hold it).
        unsafe {
            libc::kill(self.0.id() as libc::pid_t, libc::SIGINT);
        }
        let asked = Instant::now();
        loop {
            if let Some(s) = self.0.try_wait().unwrap() {
                return s;
            }
            if asked.elapsed() > Duration::from_secs(20) {
                let _ = self.0.kill();
                panic!("{} did not stop within 20 s of SIGINT", self.1);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if matches!(self.0.try_wait(), Ok(None)) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

fn read(p: &PathBuf) -> String {
    std::fs::read_to_string(p).unwrap_or_default()
}

/// Wait (up to `limit`) until `log` contains `needle`; the log's text.
fn wait_for(log: &PathBuf, needle: &str, limit: Duration, what: &str) -> String {
    let start = Instant::now();
    loop {
        let t = read(log);
        if t.contains(needle) {
            return t;
        }
        assert!(
            start.elapsed() < limit,
            "{what}: no {needle:?} within {limit:?}:\n{t}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The number in `text` right before `tail` on the last line holding it ("12 states applied").
fn count_before(text: &str, tail: &str) -> Option<u64> {
    let line = text.lines().rev().find(|l| l.contains(tail))?;
    let head = &line[..line.find(tail)?];
    head.split_whitespace().last()?.parse().ok()
}

/// `lungdyn demo` on a source scene for `seconds`, its stderr in `log`; returned once its remote
/// serve relays (up to 120 s on a loaded machine).
fn source_demo(
    seconds: u32,
    instance: &str,
    scene: &PathBuf,
    out: &PathBuf,
    log: &PathBuf,
) -> Proc {
    let demo = Proc(
        Command::new(bin("lungdyn"))
            .args([
                "demo",
                "--seconds",
                &seconds.to_string(),
                "--snapshots",
                "0",
                "--instance",
            ])
            .arg(instance)
            .arg("--scene")
            .arg(scene)
            .arg("--out")
            .arg(out)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap(),
        "lungdyn demo",
    );
    wait_for(
        log,
        "relaying",
        Duration::from_secs(120),
        "the demo's remote serve",
    );
    demo
}

/// `lungdyn remote join --observer` of `room` at `endpoint` (2 s lease) in Zenoh `mode`, its
/// engine on `instance`, its stderr in `log`.
fn observer_site(
    endpoint: &str,
    room: &str,
    instance: &str,
    mode: &str,
    scene: &PathBuf,
    log: &PathBuf,
) -> Proc {
    Proc(
        Command::new(bin("lungdyn"))
            .args(["remote", "join", "--observer", "--connect", endpoint])
            .args(["--room", room, "--lease-ms", "2000", "--instance", instance])
            .args(["--mode", mode, "--scene"])
            .arg(scene)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap(),
        "lungdyn remote join",
    )
}

#[test]
fn a_joined_site_breathes_the_demos_ticks_bit_for_bit() {
    demo_and_joined_site(false);
}

/// The same through `lungdyn remote router` (a Zenoh router and the time relay): the source and
/// the site are its clients, the site syncs its clock with the relay (it says so) and the relay
/// alone probes the source (the router's own count at its end).
#[test]
fn through_lungdyn_remote_router_the_site_syncs_with_its_relay() {
    demo_and_joined_site(true);
}

fn demo_and_joined_site(via_router: bool) {
    let port = lungdyn_needs::free_local_port();
    let room = format!(
        "t{}{}",
        std::process::id(),
        if via_router { "r" } else { "" }
    );
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router_log = tmp(&format!("router-{via_router}.log"));
    let mut router = via_router.then(|| {
        Proc(
            Command::new(bin("lungdyn"))
                .args(["remote", "router", "--listen", &endpoint, "--room", &room])
                .args(["--lease-ms", "2000", "--probe-ms", "100"])
                .stdout(Stdio::null())
                .stderr(std::fs::File::create(&router_log).unwrap())
                .spawn()
                .unwrap(),
            "lungdyn remote router",
        )
    });
    if via_router {
        wait_for(
            &router_log,
            "time relay for room",
            Duration::from_secs(60),
            "remote router",
        );
    }
    // The source's and the site's endpoints: the source listens (peer to peer) or both connect to
    // the router as clients.
    let (source_net, site_net) = if via_router {
        (
            format!("listen = []\nconnect = [\"{endpoint}\"]\nmode = \"client\""),
            format!("connect = [\"{endpoint}\"]\nmode = \"client\""),
        )
    } else {
        (
            format!("listen = [\"{endpoint}\"]\nmode = \"peer\""),
            format!("connect = [\"{endpoint}\"]\nmode = \"peer\""),
        )
    };
    // The shipped source scene's course (a tension pneumothorax, onset at 2 s here) at 30 breaths
    // a minute (2 s cycles), on a loopback port of its own.
    let scene = tmp(&format!("source-{via_router}.toml"));
    let course = "[pv]\nbreaths_per_min = 30.0\n[lungs]\nsides = [\"right\", \"left\"]\n\
                  [disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nonset_s = 2.0\n\
                  v_p_ml = 40.0\n";
    std::fs::write(
        &scene,
        format!(
            "{course}[remote]\nrole = \"source\"\nroom = \"{room}\"\n{source_net}\n\
             lease_ms = 2000\n"
        ),
    )
    .unwrap();
    // The site's: the same course, as an observer of that room, prepared (its kernels baked) as
    // a site's engine needs.
    let site_scene = lungdyn_tests::prepared_scene(
        if via_router {
            "remote-site-routed"
        } else {
            "remote-site"
        },
        &format!(
            "{course}[remote]\nrole = \"observer\"\nroom = \"{room}\"\n{site_net}\n\
             lease_ms = 2000\n"
        ),
    );
    let source_instance = unique_instance("rsrc");
    let site_instance = unique_instance("rsite");
    let demo_log = tmp(&format!("demo-{via_router}.log"));
    let mut demo = source_demo(
        40,
        &source_instance,
        &scene,
        &tmp(&format!("demo-out-{via_router}")),
        &demo_log,
    );
    let services = Instance::new(&source_instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut source_frames = services.engine_inlet(&node).unwrap();
    let site_log = tmp(&format!("join-{via_router}.log"));
    let mut join = observer_site(
        &endpoint,
        &room,
        &site_instance,
        if via_router { "client" } else { "peer" },
        &site_scene,
        &site_log,
    );
    // The site's engine stream exists once join has opened its instance.
    let site_services = Instance::new(&site_instance).unwrap();
    let site_node = iox::node(&site_services, "test").unwrap();
    let mut site_frames = None;
    let (mut source, mut site) = (BTreeMap::new(), BTreeMap::new());
    let started = Instant::now();
    // Until the site has stepped three whole cycles of the source's (or 90 s on a loaded machine).
    let cycles = |m: &BTreeMap<u64, (u32, u32)>| {
        let mut c: Vec<u32> = m.values().map(|v| v.1).collect();
        c.dedup();
        c.len()
    };
    while started.elapsed() < Duration::from_secs(90) && cycles(&site) < 5 {
        if let Some(s) = join.0.try_wait().unwrap() {
            panic!("remote join ended ({s}):\n{}", read(&site_log));
        }
        source_frames
            .drain(&mut |f: &ipc_types::EngineFrame| {
                let v: f32 = f.lungs.iter().map(|l| l.volume_ml).sum();
                source.insert(f.tick, (v.to_bits(), f.lungs[0].cycle));
            })
            .unwrap();
        if site_frames.is_none() && read(&site_log).contains("waiting for the source") {
            site_frames = Some(site_services.engine_inlet(&site_node).unwrap());
        }
        if let Some(s) = site_frames.as_mut() {
            s.drain(&mut |f: &ipc_types::EngineFrame| {
                let v: f32 = f.lungs.iter().map(|l| l.volume_ml).sum();
                site.insert(f.tick, (v.to_bits(), f.lungs[0].cycle));
            })
            .unwrap();
        }
        std::thread::sleep(Duration::from_millis(3));
    }
    let join_status = join.interrupt_and_wait();
    let site_text = read(&site_log);
    assert!(join_status.success(), "remote join failed:\n{site_text}");
    let demo_status = demo.interrupt_and_wait();
    let demo_text = read(&demo_log);
    assert!(
        !demo_text.contains("panicked") && !site_text.contains("panicked"),
        "{demo_text}\n{site_text}"
    );
    let _ = demo_status;
    // The site stepped the source's ticks: every tick both streams showed has the same volume and
    // cycle, over at least two whole cycles (the first, partial one aside) of the course.
    let common: Vec<u64> = site
        .keys()
        .filter(|k| source.contains_key(k))
        .copied()
        .collect();
    let mut differ = Vec::new();
    for k in &common {
        if site[k] != source[k] {
            differ.push((*k, site[k], source[k]));
        }
    }
    assert!(
        differ.is_empty(),
        "{} of {} ticks differ, first {:?}\n{site_text}",
        differ.len(),
        common.len(),
        &differ[..differ.len().min(5)]
    );
    let mut seen: Vec<u32> = common.iter().map(|k| site[k].1).collect();
    seen.dedup();
    assert!(
        seen.len() >= 3 && common.len() >= 240,
        "compared {} ticks over cycles {seen:?}:\n{site_text}\n{demo_text}",
        common.len()
    );
    // The tools' own words: the site took the states, refused none, was in step; the source's
    // serve saw the site and published the states.
    assert!(site_text.contains("in step with the source"), "{site_text}");
    let applied = count_before(&site_text, "states applied").expect("join's counters");
    let refused = count_before(&site_text, "refused").unwrap_or(u64::MAX);
    assert!(applied >= 3 && refused == 0, "{site_text}");
    assert!(demo_text.contains("1 site(s) present"), "{demo_text}");
    if let Some(r) = router.as_mut() {
        assert!(
            site_text.contains("clock sync with the time relay")
                && site_text.contains("time relay present"),
            "{site_text}"
        );
        assert!(r.interrupt_and_wait().success());
        let text = read(&router_log);
        assert!(
            text.contains("clock relay in step with the source"),
            "{text}"
        );
        // "relay sent N probes to the source (M answered); answered K site probes, ..."
        let answered = count_before(&text, "site probes").expect("the router's counters");
        assert!(answered >= 10, "{text}");
        // The source's serve answered the relay's probes, no more than the relay sent.
        let sent = count_before(&text, "probes to the source").expect("the relay's probes");
        let source = count_before(&demo_text, "probes answered").expect("serve's counters");
        assert!(source >= 1 && source <= sent, "{demo_text}\n{text}");
    } else {
        assert!(
            site_text.contains("clock sync with the source"),
            "{site_text}"
        );
    }
}

/// A chest belt whose deeper breaths are cut by its sensor's range, as `time_s,amplitude_mm`: 2.5 s
/// breaths 6–14 mm deep (unequal, as the golden ratio spreads them), cut at 10 mm — about half of
/// them end at the ceiling while the others spread below it.
fn clipped_belt(path: &std::path::Path, seconds: f64) {
    let mut s = String::from("time_s,amplitude_mm\n");
    for k in 0..(seconds * 25.0) as u32 {
        let t = k as f64 * 0.04;
        let c = (t / 2.5).floor();
        let depth = 10.0 * (0.6 + 0.8 * (c * 0.618_034).fract());
        let v = depth * 0.5 * (1.0 - (std::f64::consts::TAU * t / 2.5).cos());
        s += &format!("{t:.3},{:.4}\n", v.min(10.0));
    }
    std::fs::write(path, s).unwrap();
}

/// Control-state v5 over a real Zenoh session (issue 35): `lungdyn demo` follows a clipped belt
/// replayed live as a remote source, a site joins with `lungdyn remote join --observer`, and the
/// site's own engine frames say the source's signal looks clipped (`SIGNAL_CLIPPED`) while they
/// follow the patient — the engine test `a_site_says_so_when_the_sources_signal_looks_clipped`
/// goes through the codec only; this goes through both processes and the network.
#[test]
fn a_joined_site_hears_over_zenoh_that_the_sources_signal_looks_clipped() {
    use ipc_types::engine_state as e;
    let port = lungdyn_needs::free_local_port();
    let room = format!("c{}", std::process::id());
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let belt = tmp("clipped-belt.csv");
    clipped_belt(&belt, 60.0);
    let scene = tmp("clipped-source.toml");
    std::fs::write(
        &scene,
        format!(
            "[breathing]\nsource = \"signal\"\nsignal = \"trace:{}\"\n[remote]\nrole = \"source\"\n\
             room = \"{room}\"\nlisten = [\"{endpoint}\"]\nmode = \"peer\"\nlease_ms = 2000\n",
            belt.display()
        ),
    )
    .unwrap();
    let site_scene = lungdyn_tests::prepared_scene(
        "remote-site-clipped",
        &format!(
            "[remote]\nrole = \"observer\"\nroom = \"{room}\"\nconnect = [\"{endpoint}\"]\n\
             mode = \"peer\"\nlease_ms = 2000\n"
        ),
    );
    let (source_instance, site_instance) = (unique_instance("csrc"), unique_instance("csite"));
    let demo_log = tmp("clipped-demo.log");
    let mut demo = source_demo(
        55,
        &source_instance,
        &scene,
        &tmp("clipped-demo-out"),
        &demo_log,
    );
    let services = Instance::new(&source_instance).unwrap();
    let node = iox::node(&services, "test").unwrap();
    let mut source_frames = services.engine_inlet(&node).unwrap();
    let site_log = tmp("clipped-join.log");
    let mut join = observer_site(
        &endpoint,
        &room,
        &site_instance,
        "peer",
        &site_scene,
        &site_log,
    );
    let site_services = Instance::new(&site_instance).unwrap();
    let site_node = iox::node(&site_services, "test").unwrap();
    let mut site_frames = None;
    // The first tick each side's frames said "clipped" while following, and frames seen.
    let (mut source_clipped, mut site_clipped) = (None::<u64>, None::<u64>);
    let (mut source_seen, mut site_following) = (0u64, 0u64);
    // The latest source tick seen not saying so before its first that did (the test's inlet may
    // drop frames: a lower bound that holds whatever it missed).
    let mut source_unclipped = 0u64;
    let clipped_following = |f: &ipc_types::EngineFrame| {
        f.state & e::SIGNAL_CLIPPED != 0 && f.state & e::SIGNAL_FOLLOWING != 0
    };
    let started = Instant::now();
    // Until the site has said so for a second (or 100 s on a loaded machine).
    while started.elapsed() < Duration::from_secs(100)
        && !site_clipped.is_some_and(|t| source_seen > t + 60)
    {
        if let Some(s) = join.0.try_wait().unwrap() {
            panic!("remote join ended ({s}):\n{}", read(&site_log));
        }
        if demo.0.try_wait().unwrap().is_some() {
            // Its 55 s are over: what the site said by then is judged below.
            break;
        }
        source_frames
            .drain(&mut |f: &ipc_types::EngineFrame| {
                source_seen = source_seen.max(f.tick);
                if clipped_following(f) {
                    source_clipped.get_or_insert(f.tick);
                } else if source_clipped.is_none() {
                    source_unclipped = source_unclipped.max(f.tick);
                }
            })
            .unwrap();
        if site_frames.is_none() && read(&site_log).contains("waiting for the source") {
            site_frames = Some(site_services.engine_inlet(&site_node).unwrap());
        }
        if let Some(s) = site_frames.as_mut() {
            s.drain(&mut |f: &ipc_types::EngineFrame| {
                if f.state & e::SIGNAL_FOLLOWING != 0 {
                    site_following += 1;
                }
                if clipped_following(f) {
                    site_clipped.get_or_insert(f.tick);
                }
            })
            .unwrap();
        }
        std::thread::sleep(Duration::from_millis(3));
    }
    let join_status = join.interrupt_and_wait();
    let site_text = read(&site_log);
    let _ = demo.interrupt_and_wait();
    let demo_text = read(&demo_log);
    assert!(join_status.success(), "remote join failed:\n{site_text}");
    assert!(
        !demo_text.contains("panicked") && !site_text.contains("panicked"),
        "{demo_text}\n{site_text}"
    );
    eprintln!(
        "the source's frames said clipped from tick {source_clipped:?}, the site's from {site_clipped:?} \
         ({site_following} site frames following the patient)"
    );
    let source_from = source_clipped
        .unwrap_or_else(|| panic!("the source never said its signal looks clipped:\n{demo_text}"));
    let site_from = site_clipped.unwrap_or_else(|| {
        panic!(
            "the site followed the patient for {site_following} frames and never said the \
             source's signal looks clipped (the source did from tick {source_from}):\n{site_text}"
        )
    });
    // The site hears it from the source: never on a tick the source's own frames did not say so.
    assert!(
        site_from > source_unclipped,
        "site {site_from}, the source not yet at {source_unclipped} (said so from {source_from})"
    );
}

/// `remote serve` and `remote join` take one set of session flags (--room, --mode, --lease-ms);
/// serve's help offers router mode, join's refuses it with what to do instead.
#[test]
fn serve_and_join_share_the_session_flags_and_only_serve_routes() {
    for role in ["serve", "join"] {
        let (ok, out, _) = lungdyn(&["remote", role, "--help"]);
        assert!(ok);
        for flag in ["--room", "--mode", "--lease-ms", "--seconds"] {
            assert!(out.contains(flag), "remote {role} --help: {out}");
        }
        assert!(out.contains("`remote serve` only"), "{out}");
    }
    let (ok, _, err) = lungdyn(&[
        "remote",
        "join",
        "--connect",
        "tcp/127.0.0.1:7447",
        "--mode",
        "router",
        "--seconds",
        "1",
    ]);
    assert!(!ok && err.contains("remote serve --mode router"), "{err}");
}

/// `remote harness --router` (a router and the time relay in the harness's process, the source in
/// its own): the source's own CPU and TCP bytes are reported, it sees both sites through the
/// router, the relay answers the sites' probes, and both step the source's volumes bit for bit.
#[test]
fn the_harness_through_a_router_reports_the_sources_own_cost() {
    let (ok, out, err) = lungdyn(&[
        "remote",
        "harness",
        "--sites",
        "2",
        "--seconds",
        "4",
        "--breaths-per-min",
        "30",
        "--observer",
        "--router",
        "--probe-ms",
        "100",
        "--json",
    ]);
    assert!(ok, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(v["topology"].as_str().unwrap().starts_with("router"), "{v}");
    assert_eq!(v["sites_seen_by_source"], 2, "{v}");
    assert!(v["source_cpu_s"].as_f64().unwrap() > 0.0, "{v}");
    assert!(
        v["source_tcp_bytes_sent_per_minute"].as_f64().unwrap()
            > v["state_bytes_per_minute"].as_f64().unwrap(),
        "{v}"
    );
    assert!(v["probes_per_minute"].as_f64().unwrap() > 0.0, "{v}");
    // The sites sync with the relay beside the router: it answers both sites' probes, the source
    // only the relay's (each probing every 100 ms).
    assert!(
        v["clock_sync"].as_str().unwrap().starts_with("relay"),
        "{v}"
    );
    let relay = &v["relay"];
    assert!(
        relay["probes_answered_per_minute"].as_f64().unwrap()
            > 1.5 * v["probes_per_minute"].as_f64().unwrap(),
        "{v}"
    );
    // Its own threads did the answering (a figure, not a budget: > 0 and below a whole core's half).
    let cpu = relay["threads_cpu_percent"].as_f64().unwrap();
    assert!(cpu > 0.0 && cpu < 50.0, "{v}");
    assert!(relay["offset_ms"].as_f64().unwrap().abs() < 1.0, "{v}");
    for s in v["per_site"].as_array().unwrap() {
        assert_eq!(s["ticks_differing"], 0, "{s}");
        assert!(s["ticks"].as_u64().unwrap() > 120, "{s}");
    }
}

/// `remote join` with nothing listening at `--connect` runs its seconds, then exits non-zero saying
/// no state came from the source and what to check (it used to exit 0 after "0 states applied",
/// never saying the source was not reached).
#[test]
fn a_join_that_never_hears_the_source_fails_saying_so() {
    // A port nothing listens on: bound, read and released.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let scene = lungdyn_tests::prepared_scene(
        "remote-nobody",
        &format!(
            "[remote]\nrole = \"site\"\nroom = \"nobody-here\"\nconnect = [\"tcp/127.0.0.1:{port}\"]\n"
        ),
    );
    let instance = unique_instance("join-nobody");
    let (ok, _, err) = lungdyn(&[
        "remote",
        "join",
        "--scene",
        scene.to_str().unwrap(),
        "--instance",
        &instance,
        "--seconds",
        "2",
    ]);
    assert!(!ok, "exited 0: {err}");
    assert!(
        err.contains("no state from the source")
            && err.contains(&format!("127.0.0.1:{port}"))
            && err.contains("nothing came from the source"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}
