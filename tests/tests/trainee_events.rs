//! A trainee's actions on a running engine (`lungdyn scene event`, issue 20 item 3): every event is
//! delivered once and its sender told the outcome in words — through an engine stalled for up to a
//! second (SIGSTOP), from 20 senders at once, and "ignored: …" with a non-zero exit on a scene
//! without a pneumothorax. The engine runs alone (`lungdyn engine`, ticking on its deadline): no
//! GPU, display or tracker needed.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

fn exe() -> PathBuf {
    lungdyn_tests::bin("lungdyn")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lungdyn-events-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join(name)
}

fn lungdyn(args: &[&str]) -> Output {
    Command::new(exe())
        .args(args)
        .output()
        .expect("lungdyn built (cargo build --release -p lungdyn)")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A `lungdyn engine` of a prepared scene, alone in its instance; stopped (and its instance's files
/// removed) when dropped.
struct Engine {
    child: Option<Child>,
    instance: String,
    log: PathBuf,
}

impl Engine {
    /// Prepare `scene` (bake its kernels) and start its engine; returns once it answers actions.
    fn start(scene: &str, tag: &str) -> Engine {
        let out = tmp(tag);
        let s = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../scenes")
            .join(scene);
        let o = lungdyn(&[
            "scene",
            "prepare",
            s.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", text(&o.stderr));
        let instance = format!("events-{tag}-{}", std::process::id());
        let log = tmp(&format!("{tag}.engine.log"));
        let child = Command::new(exe())
            .args([
                "engine",
                "--instance",
                &instance,
                "--seconds",
                "300",
                "--scene",
                out.join("kernels/scene.resolved.toml").to_str().unwrap(),
            ])
            .stdout(Stdio::null())
            .stderr(File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let e = Engine {
            child: Some(child),
            instance,
            log,
        };
        let start = Instant::now();
        while !e.log().contains("waiting for tracker frames") {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "the engine did not start: {}",
                e.log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        e
    }

    fn pid(&self) -> libc::pid_t {
        self.child.as_ref().unwrap().id() as libc::pid_t
    }

    fn signal(&self, sig: libc::c_int) {
        // SAFETY: a signal to our own child, which has not been reaped (we hold it).
        assert_eq!(unsafe { libc::kill(self.pid(), sig) }, 0);
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// `lungdyn scene event INSTANCE ARGS...`, started (not waited for).
    fn send(&self, args: &[&str]) -> Child {
        Command::new(exe())
            .args(["scene", "event", &self.instance])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    }

    /// Stop the engine the way systemd does — SIGTERM, then SIGCONT (it may still be stopped) — and
    /// return its log (it says its counters). The stop request is latched, so the SIGCONT after it
    /// cannot take it back.
    fn stop(mut self) -> String {
        self.signal(libc::SIGTERM);
        self.signal(libc::SIGCONT);
        let asked = Instant::now();
        let status = self.child.take().unwrap().wait().unwrap();
        eprintln!("engine exited {:?} after SIGTERM+SIGCONT", asked.elapsed());
        let log = self.log();
        assert!(status.success(), "{log}");
        log
    }
}

impl Drop for Engine {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
        if let Ok(i) = transport::Instance::new(&self.instance) {
            i.remove_leftovers();
        }
    }
}

/// The tick in a sender's outcome line ("... at tick 612, ..." or "(arrived at tick 612, ...").
fn tick_of(line: &str) -> u64 {
    let at = line.find("at tick ").expect(line) + "at tick ".len();
    line[at..]
        .split(|c: char| !c.is_ascii_digit())
        .next()
        .unwrap()
        .parse()
        .expect(line)
}

#[test]
fn an_event_sent_while_the_engine_is_stopped_arrives_when_it_resumes_and_its_sender_gets_the_outcome(
) {
    let e = Engine::start("tension_untreated.toml", "stall");
    // Before: events lost from 0.3 s on (the sender left 0.3 s after publishing). Each stall below
    // is longer than that; the sender waits for the answer instead.
    let mut figures = Vec::new();
    for (stall_s, kind, expect) in [
        (
            0.45,
            "needle-decompression",
            "needle decompression, left: applied at tick ",
        ),
        (0.7, "chest-tube", "chest tube, left: applied at tick "),
        (
            1.0,
            "occlusive-dressing",
            "occlusive dressing, left: no effect (arrived at tick ",
        ),
    ] {
        e.signal(libc::SIGSTOP);
        let t0 = Instant::now();
        // No --side: the engine acts on the pneumothorax's side (left).
        let sender = e.send(&[kind]);
        std::thread::sleep(Duration::from_secs_f64(stall_s));
        e.signal(libc::SIGCONT);
        let o = sender.wait_with_output().unwrap();
        let took = t0.elapsed().as_secs_f64();
        let (out, err) = (text(&o.stdout), text(&o.stderr));
        assert!(o.status.success(), "{stall_s} s: {out}{err}");
        assert!(out.starts_with(expect), "{stall_s} s: {out}");
        assert!(
            out.contains("— ") && !out.contains("Applied"),
            "in words: {out}"
        );
        // It cannot have been answered before the engine resumed.
        assert!(took >= stall_s, "{took} < {stall_s}");
        figures.push(format!("{stall_s} s stall: outcome after {took:.2} s"));
    }
    eprintln!("delivery through a stopped engine: {}", figures.join("; "));
    let log = e.stop();
    assert!(
        log.contains(
            "trainee actions: 3 received, 3 applied, 0 ignored, 0 refused (over capacity), 0 \
             repeated"
        ),
        "{log}"
    );
}

/// Start `n` senders at once (optionally while the engine is stopped) and check each got an
/// outcome for an action applied once; returns the senders' ticks.
fn burst(e: &Engine, n: usize, stall: Option<Duration>) -> Vec<u64> {
    let kinds = ["needle-decompression", "chest-tube", "occlusive-dressing"];
    if stall.is_some() {
        e.signal(libc::SIGSTOP);
    }
    let senders: Vec<Child> = (0..n)
        .map(|i| e.send(&[kinds[i % 3], "--side", "left"]))
        .collect();
    if let Some(s) = stall {
        std::thread::sleep(s);
        e.signal(libc::SIGCONT);
    }
    let mut ticks = Vec::new();
    for (i, s) in senders.into_iter().enumerate() {
        let o = s.wait_with_output().unwrap();
        let (out, err) = (text(&o.stdout), text(&o.stderr));
        // (20 > the 4 publishers the stream used to allow: ExceedsMaxSupportedPublishers.)
        assert!(o.status.success(), "sender {i}: {out}{err}");
        let kind_words = kinds[i % 3].replace('-', " ");
        assert!(out.starts_with(&format!("{kind_words}, left: ")), "{out}");
        ticks.push(tick_of(&out));
    }
    ticks
}

#[test]
fn twenty_senders_at_once_each_get_an_outcome_for_an_action_applied_once_in_order_of_arrival() {
    let e = Engine::start("tension_untreated.toml", "burst");
    let mut sent = burst(&e, 20, None);
    // Twenty more while the engine is stopped for 0.7 s: all wait in the stream's buffer.
    sent.extend(burst(&e, 20, Some(Duration::from_millis(700))));
    let log = e.stop();
    // Each action applied once: one engine line per action, with the tick its sender was told.
    let applied: Vec<u64> = log
        .lines()
        .filter(|l| l.contains("on the left lung (arrived at tick"))
        .map(tick_of)
        .collect();
    assert_eq!(applied.len(), 40, "{log}");
    // In order of arrival: the engine applies them in the order it took them.
    assert!(applied.windows(2).all(|w| w[0] <= w[1]), "{applied:?}");
    let (mut a, mut b) = (applied.clone(), sent.clone());
    a.sort_unstable();
    b.sort_unstable();
    assert_eq!(a, b, "the ticks the senders were told are the engine's");
    // The first needle applied; the rest are "no change" or "no effect", never a silent drop.
    assert!(
        log.contains(
            "trainee actions: 40 received, 40 applied, 0 ignored, 0 refused (over capacity), 0 \
             repeated"
        ),
        "{log}"
    );
}

#[test]
fn an_event_on_a_scene_without_a_pneumothorax_is_ignored_with_a_non_zero_exit() {
    let e = Engine::start("default.toml", "ignored");
    for args in [
        &["chest-tube", "--side", "left"][..],
        &["needle-decompression"][..],
    ] {
        let o = e.send(args).wait_with_output().unwrap();
        let err = text(&o.stderr);
        assert!(!o.status.success(), "{err}");
        assert!(
            err.contains("ignored: the scene has no tension pneumothorax"),
            "{err}"
        );
        assert!(o.stdout.is_empty());
    }
    let log = e.stop();
    assert!(log.contains("0 received, 0 applied, 2 ignored"), "{log}");
}

#[test]
fn an_engine_that_never_answers_is_a_clear_error_after_the_timeout() {
    let e = Engine::start("tension_untreated.toml", "silent");
    e.signal(libc::SIGSTOP);
    let t0 = Instant::now();
    let o = e
        .send(&["chest-tube", "--timeout-s", "1"])
        .wait_with_output()
        .unwrap();
    let took = t0.elapsed();
    let err = text(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("no outcome from the engine") && err.contains("never acknowledged"),
        "{err}"
    );
    assert!(took >= Duration::from_secs(1), "{took:?}");
    assert!(took < Duration::from_secs(20), "{took:?}");
    // Still stopped: systemd's SIGTERM then SIGCONT ends it cleanly.
    e.stop();
}
