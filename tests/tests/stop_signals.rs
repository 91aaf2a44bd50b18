//! A stop request is never lost (issue 23). `systemctl stop` sends SIGTERM and then SIGCONT (so a
//! stopped process can act on it); so does any stop of a SIGSTOPped process. iceoryx2's own signal
//! handling kept only the last signal caught, so that SIGCONT replaced the SIGTERM and the process
//! ran on until something killed it. Each of the three processes and the `lungdyn demo` launcher
//! must exit cleanly, soon, after SIGTERM immediately followed by SIGCONT — running, and stopped
//! (SIGSTOP) when the two arrive.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use lungdyn_tests::{bin, prepared_scene, unique_instance};

/// How long a process may take from the stop request to its exit. Far longer than a clean stop
/// takes (well under a second), far shorter than the run it was started for (`RUN_S`): a lost
/// request shows as a process still running.
const STOP_WITHIN: Duration = Duration::from_secs(15);
/// The run each process is started for (`--seconds`).
const RUN_S: &str = "300";

/// Whether the signals arrive at a running process or one stopped by SIGSTOP, and the pause between
/// the SIGTERM and the SIGCONT (systemd sends them back to back; a few tens of microseconds is
/// about when a running process has taken the SIGTERM but not yet looked for it, where a handler
/// that keeps only the last signal lost it).
#[derive(Clone, Copy, Debug)]
enum When {
    Running { gap_us: u64 },
    Stopped { gap_us: u64 },
}

/// The trials of one process, each a fresh process (started together, stopped one after another):
/// `running` of them running, with pauses of 0 to 120 us spread over them, and `stopped` stopped.
fn trials(running: usize, stopped: usize) -> Vec<When> {
    let step = 120 / running.max(1) as u64;
    (0..running as u64)
        .map(|i| When::Running { gap_us: i * step })
        .chain((0..stopped as u64).map(|i| When::Stopped { gap_us: i * 30 }))
        .collect()
}

/// A process under test: its stderr goes to a file, read while it runs.
struct Proc {
    child: Option<Child>,
    name: String,
    log: PathBuf,
    instance: Option<String>,
}

impl Proc {
    fn spawn(name: &str, cmd: &mut Command, log: PathBuf, instance: Option<String>) -> Proc {
        let child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        Proc {
            child: Some(child),
            name: name.to_string(),
            log,
            instance,
        }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn pid(&self) -> libc::pid_t {
        self.child.as_ref().unwrap().id() as libc::pid_t
    }

    fn signal(&self, sig: libc::c_int) {
        // SAFETY: a signal to our own child, not yet reaped (we hold its handle).
        assert_eq!(unsafe { libc::kill(self.pid(), sig) }, 0);
    }

    /// Wait (90 s at most) until its stderr contains `needle`: it runs its loop.
    fn wait_for(&mut self, needle: &str) {
        let start = Instant::now();
        while !self.log().contains(needle) {
            if let Some(status) = self.child.as_mut().unwrap().try_wait().unwrap() {
                panic!(
                    "{} exited ({status}) before {needle:?}: {}",
                    self.name,
                    self.log()
                );
            }
            assert!(
                start.elapsed() < Duration::from_secs(90),
                "{} did not say {needle:?} within 90 s: {}",
                self.name,
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Whether it is stopped (state `T` in `/proc/PID/stat`).
    fn stopped(&self) -> bool {
        std::fs::read_to_string(format!("/proc/{}/stat", self.pid())).is_ok_and(|s| {
            s.rsplit_once(')')
                .is_some_and(|(_, rest)| rest.trim_start().starts_with('T'))
        })
    }

    /// Ask it to stop the way systemd does: SIGTERM, then SIGCONT (after a SIGSTOP when `when`
    /// says so).
    fn stop_like_systemd(&self, when: When) {
        let gap_us = match when {
            When::Running { gap_us } => gap_us,
            When::Stopped { gap_us } => {
                self.signal(libc::SIGSTOP);
                let start = Instant::now();
                while !self.stopped() {
                    assert!(start.elapsed() < Duration::from_secs(10), "SIGSTOP ignored");
                    std::thread::sleep(Duration::from_millis(2));
                }
                gap_us
            }
        };
        self.signal(libc::SIGTERM);
        let sent = Instant::now();
        while sent.elapsed() < Duration::from_micros(gap_us) {
            std::hint::spin_loop();
        }
        self.signal(libc::SIGCONT);
    }

    /// Wait for its exit, at most until `until`; its success, stdout and stderr, or None (and
    /// killed) when it still runs then.
    fn exit_by(&mut self, until: Instant) -> Option<(bool, String, String)> {
        let mut child = self.child.take().unwrap();
        while child.try_wait().unwrap().is_none() {
            if Instant::now() > until {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let out = child.wait_with_output().unwrap();
        Some((
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            self.log(),
        ))
    }
}

/// Stop each of `procs` per its trial in `trials` (all running their loops), then wait for every
/// exit; panics naming the trials whose stop request was lost. Returns each trial's outcome.
fn stop_all(
    role: &str,
    trials: &[When],
    mut procs: Vec<Proc>,
) -> Vec<(When, (bool, String, String))> {
    for (p, &when) in procs.iter().zip(trials) {
        p.stop_like_systemd(when);
    }
    let until = Instant::now() + STOP_WITHIN;
    let mut lost = Vec::new();
    let mut ended = Vec::new();
    for (p, &when) in procs.iter_mut().zip(trials) {
        match p.exit_by(until) {
            Some(e) => ended.push((when, e)),
            None => lost.push(format!("{when:?}: {}", p.log())),
        }
    }
    assert!(
        lost.is_empty(),
        "{role}: {} of {} still ran {STOP_WITHIN:?} after SIGTERM+SIGCONT (the stop request was \
         lost):\n{}",
        lost.len(),
        trials.len(),
        lost.join("\n")
    );
    ended
}

impl Drop for Proc {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
        if let Some(i) = self.instance.as_deref() {
            if let Ok(i) = transport::Instance::new(i) {
                i.remove_leftovers();
            }
        }
    }
}

fn dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(unique_instance(&format!("stop-{tag}")));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Start `role` (its own binary) alone in a fresh instance: one per trial, started together, each
/// waited for until it runs its loop (its stderr says `ready`).
fn start_alone(role: &str, n: usize, scene: Option<&Path>, ready: &str) -> Vec<Proc> {
    let mut procs: Vec<Proc> = (0..n)
        .map(|i| {
            let tag = format!("{role}-{i}");
            let instance = unique_instance(&tag);
            let mut cmd = Command::new(bin(role));
            cmd.args(["--instance", &instance, "--seconds", RUN_S]);
            if let Some(s) = scene {
                cmd.arg("--scene").arg(s);
            }
            Proc::spawn(role, &mut cmd, dir(&tag).join("stderr.txt"), Some(instance))
        })
        .collect();
    for p in &mut procs {
        p.wait_for(ready);
    }
    // Into their steady ticking (waiting for the next tick, or busy with one).
    std::thread::sleep(Duration::from_millis(300));
    procs
}

/// Every trial of `role` stopped, `rounds` times: exit 0, said what it did, left nothing of its
/// instance. (A lost request needs the SIGCONT to land between the SIGTERM's handler and the
/// loop's next look: many trials, each a few ms, make one likely where a handler loses it.)
fn stop_alone(role: &str, rounds: usize, trials: &[When], scene: Option<&Path>, ready: &str) {
    for _ in 0..rounds {
        stop_round(role, trials, scene, ready);
    }
}

fn stop_round(role: &str, trials: &[When], scene: Option<&Path>, ready: &str) {
    let procs = start_alone(role, trials.len(), scene, ready);
    let instances: Vec<String> = procs.iter().map(|p| p.instance.clone().unwrap()).collect();
    for ((when, (ok, _, err)), instance) in stop_all(role, trials, procs).into_iter().zip(instances)
    {
        assert!(ok, "{role} ({when:?}) did not exit cleanly: {err}");
        assert!(
            err.lines()
                .any(|l| l.starts_with(&format!("{role}[")) && l.contains("stopped after")),
            "{role} ({when:?}) did not say what it did: {err}"
        );
        let services = transport::Instance::new(&instance).unwrap();
        assert!(
            services.leftovers().is_empty(),
            "{role} ({when:?}) left {:?}",
            services.leftovers()
        );
    }
}

/// The engine's and the renderer's scene, prepared once for the tests running in parallel: each
/// preparing its own in the one folder `prepared_scene("stop")` names rewrote `scene.toml` (a
/// truncate, then a write) while the other's `scene prepare` might be reading it.
fn scene() -> PathBuf {
    static SCENE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    SCENE
        .get_or_init(|| prepared_scene("stop", "[lungs]\nvertices = 600\n"))
        .clone()
}

#[test]
fn the_engine_honours_sigterm_followed_by_sigcont() {
    stop_alone(
        "engine",
        3,
        &trials(60, 4),
        Some(&scene()),
        "waiting for tracker frames",
    );
}

#[test]
fn the_tracker_bridge_honours_sigterm_followed_by_sigcont() {
    stop_alone("tracker-bridge", 3, &trials(60, 4), None, "publishing on");
}

#[test]
fn the_renderer_honours_sigterm_followed_by_sigcont() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    stop_alone(
        "renderer",
        1,
        &trials(12, 2),
        Some(&scene()),
        "waiting for engine frames",
    );
}

/// The launcher, drawing frames (each run with its three processes), stopped the same way: it
/// stops its processes and reports the run as interrupted.
#[test]
fn the_demo_launcher_honours_sigterm_followed_by_sigcont() {
    if renderer::gpu::Gpu::for_tests().is_none() {
        return;
    }
    let d = dir("demo");
    let scene_file = d.join("scene.toml");
    std::fs::write(
        &scene_file,
        "[lungs]\nvertices = 600\n[render]\nwidth = 96\nheight = 72\nstereo = false\n\
         mode = \"points\"\n",
    )
    .unwrap();
    // Bake the kernels once, so that the runs do not all bake at once.
    let (ok, _, err) = lungdyn_tests::lungdyn(&[
        "scene",
        "prepare",
        scene_file.to_str().unwrap(),
        "--out",
        d.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    // Fewer runs at once than for a lone process: each is four processes drawing frames.
    let trials = trials(3, 1);
    let mut procs: Vec<Proc> = (0..trials.len())
        .map(|i| {
            let out = d.join(format!("run{i}"));
            std::fs::create_dir_all(&out).unwrap();
            let mut cmd = Command::new(bin("lungdyn"));
            cmd.args(["demo", "--seconds", RUN_S, "--snapshots", "0", "--json"])
                .arg("--out")
                .arg(&out)
                .arg("--scene")
                .arg(d.join("kernels/scene.resolved.toml"));
            Proc::spawn("lungdyn demo", &mut cmd, out.join("stderr.txt"), None)
        })
        .collect();
    // Every run draws: its engine has tracker samples and its renderer engine frames (it draws the
    // first at once). "tracker connected" alone can come while a renderer still opens its GPU (four
    // at once on lavapipe, on a loaded machine), and a run stopped before its first frame fails as
    // "interrupted before any frame was drawn" — not what this test is about.
    for p in &mut procs {
        p.wait_for("tracker connected");
        p.wait_for("engine connected");
    }
    // Frames drawn in every run.
    std::thread::sleep(Duration::from_secs(2));
    for (when, (ok, out, err)) in stop_all("lungdyn demo", &trials, procs) {
        assert!(ok, "demo ({when:?}) did not exit cleanly: {err}");
        let v: serde_json::Value = serde_json::from_str(out.trim())
            .unwrap_or_else(|e| panic!("demo ({when:?}) --json: {e}: {out}\n{err}"));
        assert_eq!(v["ended"], "interrupted", "{when:?}: {v}");
        assert_eq!(v["remaining_files"], 0, "{when:?}: {v}");
        // Its processes were asked to stop, not killed at the end of the grace period.
        assert!(!err.contains("had to kill"), "{when:?}: {err}");
    }
    std::fs::remove_dir_all(&d).ok();
}
