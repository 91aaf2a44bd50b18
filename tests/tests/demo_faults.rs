//! The demo under faults: it survives SIGKILL of its engine and of its tracker-bridge (each
//! restarted, the engine resuming with the breath an uninterrupted run shows), reports the restarts
//! and leaves nothing behind; a renderer or engine stopped for good is killed and restarted like a
//! dead one, its silence showing as missed deadlines; the launcher's own stall blames no one; a restart storm
//! past the limit ends the run with a clear error — and the report so far still printed.

use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use lungdyn_tests::bin;

const SCENE: &str = "[lungs]\nvertices = 1500\n[render]\nwidth = 160\nheight = 120\nstereo = false\nmode = \"points\"\n";

struct Demo {
    child: Child,
    err: std::path::PathBuf,
    dir: std::path::PathBuf,
}

impl Demo {
    fn start(tag: &str, seconds: &str, extra: &[&str]) -> Demo {
        let dir = std::env::temp_dir().join(format!("lungdyn-faults-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scene = dir.join("scene.toml");
        std::fs::write(&scene, SCENE).unwrap();
        let err = dir.join("stderr.txt");
        let child = Command::new(bin("lungdyn"))
            .args([
                "demo",
                "--seconds",
                seconds,
                "--snapshots",
                "0",
                "--json",
                "--out",
            ])
            .arg(&dir)
            .arg("--scene")
            .arg(&scene)
            .args(extra)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&err).unwrap())
            // Its own process group, as a shell starts a job: a terminal's Ctrl-Z and `fg` signal
            // the whole group (launcher and children), which `Demo::signal_job` does.
            .process_group(0)
            .spawn()
            .unwrap();
        Demo { child, err, dir }
    }

    /// Send `sig` to the demo's whole process group, as the terminal does for the foreground job
    /// (Ctrl-Z: SIGTSTP) and the shell's `fg` does (SIGCONT).
    fn signal_job(&self, sig: libc::c_int) {
        // SAFETY: the group our child leads (process_group(0) at spawn).
        assert_eq!(
            unsafe { libc::killpg(self.child.id() as libc::pid_t, sig) },
            0
        );
    }

    /// Whether the launcher is stopped (state T in /proc).
    fn launcher_stopped(&self) -> bool {
        std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).is_ok_and(|s| {
            s.rsplit_once(") ")
                .is_some_and(|(_, rest)| rest.starts_with('T'))
        })
    }

    fn stderr(&self) -> String {
        std::fs::read_to_string(&self.err).unwrap_or_default()
    }

    /// Wait until stderr contains `needle` (60 s at most).
    fn wait_for(&self, needle: &str) {
        self.wait_for_count(needle, 1);
    }

    /// Wait until stderr contains `needle` `n` times (60 s at most): the `n`th event of a kind, not
    /// the first one again.
    fn wait_for_count(&self, needle: &str, n: usize) {
        for _ in 0..1200 {
            if self.stderr().matches(needle).count() >= n {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!(
            "fewer than {n} {needle:?} on the demo's stderr: {}",
            self.stderr()
        );
    }

    /// Wait until the whole pipeline runs: the engine has tracker samples and the renderer engine
    /// frames, which it draws at once. ("tracker connected" alone comes from the engine, possibly
    /// while the renderer still opens its GPU: on a cold, loaded machine lavapipe takes seconds,
    /// and a fault injected then hits a run that has not drawn a frame.)
    fn wait_until_drawing(&self) {
        self.wait_for("tracker connected");
        self.wait_for("engine connected");
    }

    /// Send `sig` to the demo's child of `role`.
    fn signal(&self, role: &str, sig: libc::c_int) {
        let children = std::fs::read_to_string(format!(
            "/proc/{}/task/{}/children",
            self.child.id(),
            self.child.id()
        ))
        .unwrap();
        let pid = children
            .split_whitespace()
            .find(|p| {
                std::fs::read(format!("/proc/{p}/cmdline"))
                    .is_ok_and(|c| c.split(|&b| b == 0).nth(1) == Some(role.as_bytes()))
            })
            .unwrap_or_else(|| panic!("no {role} child"));
        // SAFETY: a child of our child, found alive just now.
        assert_eq!(unsafe { libc::kill(pid.parse().unwrap(), sig) }, 0);
    }

    fn finish(self) -> (bool, serde_json::Value, String) {
        let out = self.child.wait_with_output().unwrap();
        let err = std::fs::read_to_string(&self.err).unwrap_or_default();
        let v = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{e}: {}\n{err}", String::from_utf8_lossy(&out.stdout)));
        std::fs::remove_dir_all(&self.dir).ok();
        (out.status.success(), v, err)
    }
}

#[test]
fn the_demo_survives_sigkill_of_its_engine_and_tracker_bridge() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let demo = Demo::start("kill", "7", &[]);
    demo.wait_until_drawing();
    std::thread::sleep(Duration::from_millis(1500));
    demo.signal("engine", libc::SIGKILL);
    demo.wait_for("resuming at tick");
    std::thread::sleep(Duration::from_millis(1500));
    demo.signal("tracker-bridge", libc::SIGKILL);
    let (ok, v, err) = demo.finish();
    assert!(ok, "{err}");
    assert_eq!(v["restarts"], 2, "{v}");
    let log = v["restart_log"].as_array().unwrap();
    assert_eq!(log[0]["role"], "engine");
    assert_eq!(log[1]["role"], "tracker-bridge");
    for r in log {
        assert!(r["ended"].as_str().unwrap().contains("SIGKILL"), "{r}");
        assert!(r["recover_ms"].as_f64().is_some(), "recovered: {r}");
        assert!(!r["cleaned_nodes"].as_array().unwrap().is_empty(), "{r}");
    }
    assert_eq!(v["phase_errors"], 0, "{err}");
    assert_eq!(v["ended"], "completed");
    assert_eq!(v["remaining_files"], 0);
    assert!(err.contains("RESTARTS 2"), "{err}");
    // The resumed engine continued the tick sequence: hardly any tick went undrawn beyond those a
    // renderer slower than 60 Hz leaves anyway (lavapipe under load draws 40-odd frames a second:
    // a third of the ticks go undrawn with no restart at all).
    let seconds = v["seconds"].as_f64().unwrap();
    let slow = (seconds * 60.0 - v["frames_rendered"].as_f64().unwrap()).max(0.0) as u64;
    assert!(
        v["skipped_ticks"].as_u64().unwrap() < 30 + slow,
        "more than 30 ticks undrawn beyond the {slow} a slow renderer leaves: {v}"
    );
}

/// A renderer stopped for good (SIGSTOP, never continued) is a frozen picture on the headset: the
/// launcher sees no frame from it for --hang-after-s (1 s), kills it and starts another, whose
/// first frame comes well within a second; the second of silence shows as missed deadlines.
#[test]
fn a_renderer_stopped_for_good_is_killed_and_restarted_and_its_silence_shows_as_missed_deadlines() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let demo = Demo::start("stop", "5", &[]);
    demo.wait_until_drawing();
    std::thread::sleep(Duration::from_millis(1000));
    demo.signal("renderer", libc::SIGSTOP);
    let (ok, v, err) = demo.finish();
    assert!(ok, "{err}");
    assert_eq!(
        (v["restarts"].as_u64(), v["hung_restarts"].as_u64()),
        (Some(1), Some(1)),
        "{v}"
    );
    let r = &v["restart_log"][0];
    assert_eq!(
        (r["role"].as_str(), r["hung"].as_bool()),
        (Some("renderer"), Some(true)),
        "{r}"
    );
    let ended = r["ended"].as_str().unwrap();
    assert!(
        ended.contains("stopped answering") && ended.contains("state T"),
        "{ended}"
    );
    assert!(
        r["recover_ms"].as_f64().unwrap() < 1000.0,
        "first frame within 1 s: {r}"
    );
    assert!(v["deadline_misses"].as_u64().unwrap() > 50, "{v}");
    assert!(v["missed_frame_slots"].as_u64().unwrap() > 50, "{v}");
    assert!(v["worst_case_ms"].as_f64().unwrap() > 1000.0, "{v}");
    assert_eq!(v["launcher_stalls"], 0, "{v}");
    assert_eq!(v["ended"], "completed");
    assert_eq!(v["remaining_files"], 0);
    assert!(err.contains("renderer process stopped answering"), "{err}");
}

/// An engine stopped for good is killed and restarted like a dead one, and the new engine resumes
/// the breath where the stream left it (checked bit for bit); with --hang-after-s 0 the same stop
/// is left alone (the picture stays frozen, stale, to the end).
#[test]
fn an_engine_that_stops_answering_is_restarted_and_resumes_the_breath() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let demo = Demo::start("hang-engine", "5", &[]);
    demo.wait_until_drawing();
    std::thread::sleep(Duration::from_millis(1000));
    demo.signal("engine", libc::SIGSTOP);
    let (ok, v, err) = demo.finish();
    assert!(ok, "{err}");
    assert_eq!(
        (v["restarts"].as_u64(), v["hung_restarts"].as_u64()),
        (Some(1), Some(1)),
        "{v}"
    );
    assert_eq!(v["restart_log"][0]["role"], "engine", "{v}");
    assert!(
        v["restart_log"][0]["recover_ms"].as_f64().unwrap() < 1000.0,
        "{v}"
    );
    assert_eq!(v["phase_errors"], 0, "{err}");
    assert!(
        err.contains("engine process stopped answering") && err.contains("resuming at tick"),
        "{err}"
    );

    let demo = Demo::start("hang-off", "4", &["--hang-after-s", "0"]);
    demo.wait_until_drawing();
    std::thread::sleep(Duration::from_millis(1000));
    demo.signal("engine", libc::SIGSTOP);
    let (ok, v, err) = demo.finish();
    assert!(ok, "{err}");
    assert_eq!(v["restarts"], 0, "{v}");
    assert!(v["stale_frames"].as_u64().unwrap() > 60, "{v}");
}

/// Ctrl-Z then `fg` at a terminal: the whole job is stopped (SIGTSTP to its process group) and
/// continued (SIGCONT to the group). The run goes on to its end and exits 0 with its report, the
/// stopped time counted as missed frame slots against the schedule, nothing restarted. (Checked by
/// hand too, in a pty with an interactive bash's job control: 4 of 4 runs completed.)
#[test]
fn ctrl_z_then_fg_pauses_the_whole_run_and_it_completes() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let demo = Demo::start("ctrlz", "6", &[]);
    demo.wait_until_drawing();
    std::thread::sleep(Duration::from_millis(1000));
    demo.signal_job(libc::SIGTSTP);
    let mut stopped = false;
    for _ in 0..100 {
        if demo.launcher_stopped() {
            stopped = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(stopped, "SIGTSTP stops the launcher: {}", demo.stderr());
    std::thread::sleep(Duration::from_millis(2000));
    demo.signal_job(libc::SIGCONT);
    let (ok, v, err) = demo.finish();
    assert!(ok, "{err}");
    assert_eq!(v["ended"], "completed", "{v}");
    assert_eq!(v["restarts"], 0, "{v}");
    // The launcher was stopped too: its own stall is counted, and no child blamed for it.
    assert!(v["launcher_stalls"].as_u64().unwrap() >= 1, "{v}");
    assert!(v["launcher_max_gap_ms"].as_f64().unwrap() > 1500.0, "{v}");
    // Two seconds stopped are 120 slots of the 60 Hz schedule: they show as missed.
    assert!(v["missed_frame_slots"].as_u64().unwrap() >= 100, "{v}");
    assert!(v["frames_rendered"].as_u64().unwrap() > 0, "{v}");
    assert_eq!(v["remaining_files"], 0);
}

#[test]
fn a_restart_storm_past_the_limit_ends_the_run_with_the_report_printed() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let demo = Demo::start("storm", "20", &["--max-restarts", "2"]);
    demo.wait_until_drawing();
    for k in 0..3 {
        demo.signal("tracker-bridge", libc::SIGKILL);
        if k < 2 {
            // This kill's restart, not the first one's line again (the launcher restarts at once:
            // the new bridge is its child when the line is printed).
            demo.wait_for_count("process died", k + 1);
            std::thread::sleep(Duration::from_millis(700));
        }
    }
    let (ok, v, err) = demo.finish();
    assert!(!ok, "a storm past the limit fails");
    assert_eq!(v["restarts"], 2, "{v}");
    let failure = v["failure"].as_str().unwrap();
    assert!(
        failure.contains("tracker-bridge") && failure.contains("--max-restarts 2"),
        "{failure}"
    );
    assert_eq!(v["ended"], failure);
    assert!(v["frames_rendered"].as_u64().unwrap() > 0);
    assert_eq!(v["remaining_files"], 0);
    assert!(err.contains("giving up"), "{err}");
}

/// A replay shorter than --seconds ends the run cleanly (not looped, not a fault): exit 0, the
/// report says why it ended, nothing is restarted.
#[test]
fn a_replay_shorter_than_the_run_ends_it_cleanly() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let rec = std::env::temp_dir().join(format!("lungdyn-faults-2s-{}.rec", std::process::id()));
    std::fs::remove_file(&rec).ok();
    let (ok, _, err) = lungdyn_tests::lungdyn(&[
        "tracker",
        "simulate",
        "--out",
        rec.to_str().unwrap(),
        "--seconds",
        "2",
    ]);
    assert!(ok, "{err}");
    let source = format!("replay:{}", rec.display());
    let demo = Demo::start("replay", "8", &["--tracker", &source]);
    let (ok, v, err) = demo.finish();
    std::fs::remove_file(&rec).ok();
    assert!(ok, "{err}");
    assert_eq!(v["restarts"], 0, "{v}");
    let ended = v["ended"].as_str().unwrap();
    assert!(ended.contains("tracker-bridge finished"), "{ended}");
    assert!(v["seconds"].as_f64().unwrap() < 6.0, "{v}");
    assert!(v["frames_rendered"].as_u64().unwrap() > 0);
    assert_eq!(v["remaining_files"], 0);
}
