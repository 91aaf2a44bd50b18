//! Supervision of a run's processes, as a library component: one-for-one restart with an intensity
//! limit, each dead process's iceoryx2 resources removed before its successor starts.
//!
//! [`Children`] holds the processes and signals them safely ([`Proc`] never signals a reaped pid);
//! [`Supervisor`] adds, per process, how to start it again (a closure, so a restarted engine can be
//! given the tick to resume at) and restarts whichever one died — only that one (one-for-one, as in
//! Erlang/OTP) — at most [`Intensity::max_restarts`] times within [`Intensity::within_s`]; one more
//! death within the window stops the run with an error naming the process, its status and the
//! limit. Each restart is recorded ([`Restart`]) with the time until the pipeline showed a fresh
//! frame again (set by the caller, which sees the frames: [`Supervisor::recovered`]).
//!
//! A process can also stop answering without dying (stopped for good with SIGSTOP, deadlocked,
//! stuck in a driver call): the headset would show a frozen picture until the run ends. With a
//! [`Liveness`] the supervisor treats it like a dead one: the caller reports each sign of life
//! ([`Supervisor::beat`]: a frame the process published), and a watched process silent for longer
//! than [`Liveness::hang_ns`] is killed (SIGKILL), reaped and restarted under the same intensity
//! limit, its restart recorded as hung. The launcher's own stalls (it was stopped, or starved of
//! CPU) are told apart: a gap between two checks longer than half the hang time re-arms every
//! process's clock instead of blaming them, and is counted ([`Stalls`]).

use std::collections::VecDeque;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use serde::Serialize;
use transport::now_ns;

/// How a child ended: its status, or why it could not be collected (then it counts as gone too).
#[derive(Debug, Clone)]
pub enum Ended {
    /// Its exit status.
    Status(std::process::ExitStatus),
    /// Its status could not be collected.
    Unknown(String),
    /// It stopped answering (no frame for `silent_ms`) and was killed with SIGKILL; `stopped`: it
    /// was in the stopped state (SIGSTOP) when judged.
    Hung {
        /// How long it had been silent, ms.
        silent_ms: u64,
        /// It was stopped (state T) rather than running or sleeping.
        stopped: bool,
    },
}

impl Ended {
    /// Exited with status 0.
    pub fn success(&self) -> bool {
        matches!(self, Ended::Status(s) if s.success())
    }

    /// Exited by itself with a failure status (an error it reported), not killed by a signal.
    pub fn failed_by_itself(&self) -> bool {
        matches!(self, Ended::Status(s) if s.code().is_some_and(|c| c != 0))
    }
}

impl std::fmt::Display for Ended {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Ended::Status(s) => write!(f, "{s}"),
            Ended::Unknown(e) => write!(f, "status unknown: {e}"),
            Ended::Hung { silent_ms, stopped } => write!(
                f,
                "stopped answering: no frame for {silent_ms} ms{}; killed (SIGKILL)",
                if *stopped {
                    " (it was stopped, state T)"
                } else {
                    ""
                }
            ),
        }
    }
}

/// One child process of a run, signalled only through its handle.
///
/// A pid may be signalled only while the child is known not to be reaped: once `try_wait`/`wait`
/// has collected its status the kernel may hand the pid to an unrelated process. Only this handle
/// reaps the child (nobody else waits on it and SIGCHLD keeps its default), so a `try_wait` that
/// finds it still running guarantees the pid is ours until the next wait — a child that dies in
/// between stays a zombie holding the pid. Once it has ended, the child is never signalled again.
pub struct Proc {
    role: &'static str,
    child: Child,
    ended: Option<Ended>,
    /// When it was started (the launcher's clock, ns).
    spawned_ns: u64,
    /// Its latest sign of life ([`Supervisor::beat`]), ns; `None` until the first.
    beat_ns: Option<u64>,
}

impl Proc {
    /// Hold `child` of `role`, started now.
    pub fn new(role: &'static str, child: Child) -> Self {
        Proc {
            role,
            child,
            ended: None,
            spawned_ns: now_ns(),
            beat_ns: None,
        }
    }

    /// How long it has been silent at `now` when that is longer than `liveness` allows: since its
    /// latest sign of life, or since its start when it has shown none.
    fn silent_for(&self, now: u64, liveness: &Liveness) -> Option<u64> {
        let (since, allowed) = match self.beat_ns {
            Some(b) => (b, liveness.hang_ns),
            None => (self.spawned_ns, liveness.first_beat_ns),
        };
        let silent = now.saturating_sub(since);
        (silent > allowed).then_some(silent)
    }

    /// The role it runs.
    pub fn role(&self) -> &'static str {
        self.role
    }

    /// How the child ended, collecting its status (and so reaping it) if it has exited.
    pub fn poll(&mut self) -> Option<&Ended> {
        if self.ended.is_none() {
            self.ended = match self.child.try_wait() {
                Ok(s) => s.map(Ended::Status),
                // ECHILD: something else reaped it, so the pid is not ours any more either.
                Err(e) => Some(Ended::Unknown(e.to_string())),
            };
        }
        self.ended.as_ref()
    }

    /// Send `sig` if the child is still un-reaped; false (and nothing sent) once it has ended.
    pub fn signal(&mut self, sig: libc::c_int) -> bool {
        if self.poll().is_some() {
            return false;
        }
        // SAFETY: `poll` just found the child un-reaped, and only this handle reaps it, so the pid
        // still names our child (at worst a zombie); kill(2) has no memory-safety preconditions.
        unsafe { libc::kill(self.child.id() as libc::pid_t, sig) == 0 }
    }

    /// Whether the child is stopped (SIGSTOP, Ctrl-Z: state `T` in `/proc/PID/stat`); false once it
    /// has ended or when the state cannot be read.
    pub fn stopped(&mut self) -> bool {
        if self.poll().is_some() {
            return false;
        }
        std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).is_ok_and(|s| {
            // "pid (comm) S ...": the state follows the last ')' (comm may hold one).
            s.rsplit_once(')')
                .is_some_and(|(_, rest)| rest.trim_start().starts_with(['T', 't']))
        })
    }

    /// Ask the child to stop: SIGINT, then SIGCONT if it is stopped (SIGSTOP, Ctrl-Z), which it
    /// needs to act on the SIGINT — systemd's order. The processes latch a stop request
    /// (`transport::stop`), so the SIGCONT after it cannot take it back; a running child gets no
    /// SIGCONT. Returns whether the SIGINT was sent.
    pub fn interrupt(&mut self) -> bool {
        let stopped = self.stopped();
        let sent = self.signal(libc::SIGINT);
        if stopped {
            self.signal(libc::SIGCONT);
        }
        sent
    }

    /// SIGKILL (through the handle, which refuses a reaped child) and reap.
    pub fn kill_and_reap(&mut self) {
        if self.poll().is_none() {
            let _ = self.child.kill();
            self.ended = Some(match self.child.wait() {
                Ok(s) => Ended::Status(s),
                Err(e) => Ended::Unknown(e.to_string()),
            });
        }
    }
}

/// The processes of one run, each signalled only through its [`Proc`].
pub struct Children {
    /// The processes, in start order.
    pub procs: Vec<Proc>,
}

impl Children {
    /// The processes still held, (role, pid), in start order.
    pub fn pids(&self) -> Vec<(&'static str, u32)> {
        self.procs.iter().map(|p| (p.role, p.child.id())).collect()
    }

    /// Start `exe role args…` with stdin and stdout closed, stderr shared, and SIGTERM when the
    /// launcher dies (`PR_SET_PDEATHSIG`).
    pub fn spawn(exe: &Path, role: &'static str, args: &[String]) -> anyhow::Result<Child> {
        let mut cmd = Command::new(exe);
        cmd.arg(role)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        // SAFETY: prctl and signal are async-signal-safe; prctl only arms a signal for when the
        // parent dies. SIGINT and SIGTERM go back to their default actions: a launcher started in
        // the background by a non-interactive shell inherits SIGINT ignored, and a child that kept
        // ignoring it could not be stopped but by SIGKILL.
        unsafe {
            use std::os::unix::process::CommandExt;
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                libc::signal(libc::SIGINT, libc::SIG_DFL);
                libc::signal(libc::SIGTERM, libc::SIG_DFL);
                Ok(())
            });
        }
        let child = cmd
            .spawn()
            .with_context(|| format!("cannot start the {role} process ({})", exe.display()))?;
        Ok(child)
    }

    /// Send `sig` to the running process of `role`; false when there is none (or it has ended).
    pub fn signal_role(&mut self, role: &str, sig: libc::c_int) -> bool {
        self.procs
            .iter_mut()
            .find(|p| p.role == role)
            .is_some_and(|p| p.signal(sig))
    }

    /// The first child that exited, with its status.
    pub fn exited(&mut self) -> Option<(&'static str, Ended)> {
        self.procs
            .iter_mut()
            .find_map(|p| p.poll().cloned().map(|e| (p.role, e)))
    }

    /// SIGINT everyone still running, wait up to `grace`, SIGKILL stragglers. Returns roles that
    /// had to be killed.
    pub fn stop(&mut self, grace: Duration) -> Vec<&'static str> {
        for p in &mut self.procs {
            // A stopped child (SIGSTOP, Ctrl-Z) cannot act on SIGINT until it continues.
            p.interrupt();
        }
        let until = now_ns() + grace.as_nanos() as u64;
        let mut killed = Vec::new();
        for p in &mut self.procs {
            while p.poll().is_none() {
                if now_ns() >= until {
                    p.kill_and_reap();
                    killed.push(p.role);
                    break;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
        killed
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        for p in &mut self.procs {
            p.kill_and_reap();
        }
    }
}

/// How often processes may die before the supervisor gives up: at most `max_restarts` restarts (of
/// any process) within any `within_s` seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intensity {
    /// Restarts allowed within the window.
    pub max_restarts: u32,
    /// The window, seconds.
    pub within_s: f64,
}

impl Intensity {
    /// Check the limit is usable: a whole number of restarts (0 disables restarting) and a window of
    /// 0.1 s to a day.
    pub fn checked(max_restarts: u32, within_s: f64) -> anyhow::Result<Self> {
        if !(within_s.is_finite() && (0.1..=86_400.0).contains(&within_s)) {
            anyhow::bail!(
                "--restart-window-s {}: must be from 0.1 s to a day (86400 s)",
                lung_model::plausible::compact(within_s)
            );
        }
        if max_restarts > 1000 {
            anyhow::bail!("--max-restarts {max_restarts}: at most 1000");
        }
        Ok(Self {
            max_restarts,
            within_s,
        })
    }
}

/// When a process that is still there counts as hung.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Liveness {
    /// A watched process silent this long after a sign of life is killed and restarted, ns.
    pub hang_ns: u64,
    /// A watched process (re)started once the pipeline runs, and silent this long since its
    /// start, is killed and restarted too, ns (it gets the start-up time a first start gets).
    pub first_beat_ns: u64,
}

impl Liveness {
    /// From `--hang-after-s` (0: off) and the start-up timeout, checked: the hang time from 0.1 s
    /// to 10 minutes.
    pub fn checked(hang_after_s: f64, startup_s: f64) -> anyhow::Result<Option<Self>> {
        if hang_after_s == 0.0 {
            return Ok(None);
        }
        if !(hang_after_s.is_finite() && (0.1..=600.0).contains(&hang_after_s)) {
            anyhow::bail!(
                "--hang-after-s {}: must be from 0.1 s to 600 s, or 0 to never restart a process \
                 that stops answering",
                lung_model::plausible::compact(hang_after_s)
            );
        }
        Ok(Some(Self {
            hang_ns: (hang_after_s * 1e9) as u64,
            first_beat_ns: (startup_s.max(hang_after_s) * 1e9) as u64,
        }))
    }
}

/// The launcher's own stalls: gaps between two [`Supervisor::check`]s longer than half the hang
/// time (it was stopped, or starved of CPU), when the children's silence is not theirs to answer
/// for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Stalls {
    /// Gaps longer than half the hang time.
    pub count: u64,
    /// The longest gap between two checks, ms (whether or not it counted).
    pub max_gap_ms: f64,
}

/// One restart: who died, how, and how long the run took to recover.
#[derive(Debug, Clone, Serialize)]
pub struct Restart {
    /// The process restarted.
    pub role: &'static str,
    /// How it ended (exit status or signal, or how long it was silent).
    pub ended: String,
    /// It had stopped answering (killed by the supervisor), rather than dying by itself.
    pub hung: bool,
    /// When its death was seen, seconds since the supervisor started.
    pub at_s: f64,
    /// Dead iceoryx2 nodes whose resources were removed before the restart.
    pub cleaned_nodes: Vec<String>,
    /// Time from the death seen to the first fresh frame after the restart, ms (`None`: never).
    pub recover_ms: Option<f64>,
    #[serde(skip)]
    seen_ns: u64,
}

/// How a process is started (again).
pub type Spawn<'a> = Box<dyn FnMut() -> anyhow::Result<Child> + 'a>;

/// Removes a dead process's transport resources before its successor starts.
pub type Cleaner<'a> = Box<dyn FnMut() -> anyhow::Result<Vec<String>> + 'a>;

/// One-for-one restart of a run's processes, within an [`Intensity`] limit.
pub struct Supervisor<'a> {
    /// The processes now running (the latest start of each).
    pub children: Children,
    spawns: Vec<Spawn<'a>>,
    intensity: Intensity,
    recent: VecDeque<u64>,
    clean: Cleaner<'a>,
    started_ns: u64,
    /// The pipeline has shown a frame ([`Supervisor::pipeline_running`]).
    running: bool,
    /// Every restart so far, in order.
    pub restarts: Vec<Restart>,
    liveness: Option<Liveness>,
    /// Roles whose signs of life are reported ([`Supervisor::watch`]).
    watched: Vec<&'static str>,
    last_check_ns: Option<u64>,
    /// The launcher's own stalls seen by [`Supervisor::check`].
    pub stalls: Stalls,
}

impl<'a> Supervisor<'a> {
    /// A supervisor with no processes; `clean` runs before every restart.
    pub fn new(intensity: Intensity, clean: Cleaner<'a>) -> Self {
        Self {
            children: Children { procs: Vec::new() },
            spawns: Vec::new(),
            intensity,
            recent: VecDeque::new(),
            clean,
            started_ns: now_ns(),
            running: false,
            restarts: Vec::new(),
            liveness: None,
            watched: Vec::new(),
            last_check_ns: None,
            stalls: Stalls::default(),
        }
    }

    /// Restart a watched process that stops answering ([`Liveness`]); `None` turns it off.
    pub fn with_liveness(mut self, liveness: Option<Liveness>) -> Self {
        self.liveness = liveness;
        self
    }

    /// Judge `role` by its signs of life: the caller reports each one with [`Supervisor::beat`].
    /// (A process without a stream the launcher reads is judged by its exit alone.)
    pub fn watch(&mut self, role: &'static str) {
        if !self.watched.contains(&role) {
            self.watched.push(role);
        }
    }

    /// `role` showed a sign of life at `now`: a frame it published at `published_ns` (the shared
    /// monotonic clock; 0 when unstamped). A frame published before the running process started
    /// is its predecessor's, still queued, and says nothing about this one.
    pub fn beat(&mut self, role: &str, published_ns: u64, now: u64) {
        if let Some(p) = self.children.procs.iter_mut().find(|p| p.role == role) {
            if published_ns == 0 || published_ns >= p.spawned_ns {
                p.beat_ns = Some(now);
            }
        }
    }

    /// The pipeline has shown its first frame: from now on a process that exits with an error is
    /// restarted. Before it, such an exit is a start-up error (a display that is not there, `--xr`
    /// without a runtime, a scene a process refuses) that a restart would only repeat, so
    /// [`Supervisor::check`] ends the run with it at once. A process killed by a signal is
    /// restarted either way.
    pub fn pipeline_running(&mut self) {
        self.running = true;
    }

    /// Start `role` with `spawn`, which is also how it is restarted.
    pub fn start(&mut self, role: &'static str, mut spawn: Spawn<'a>) -> anyhow::Result<()> {
        let child = spawn()?;
        self.children.procs.push(Proc::new(role, child));
        self.spawns.push(spawn);
        Ok(())
    }

    /// Restart whichever process died (each at most once per call), and, with a [`Liveness`],
    /// kill and restart a watched one that stopped answering; returns the roles restarted. An
    /// error once a death would exceed the intensity limit (nothing is restarted then), or when
    /// cleaning or starting fails.
    pub fn check(&mut self) -> anyhow::Result<Vec<&'static str>> {
        self.check_at(now_ns())
    }

    /// [`Supervisor::check`] at `now` (the launcher's clock, ns).
    pub fn check_at(&mut self, now: u64) -> anyhow::Result<Vec<&'static str>> {
        self.launcher_gap(now);
        let mut restarted = Vec::new();
        for k in 0..self.children.procs.len() {
            let Some(ended) = self.ended_or_hung(k, now) else {
                continue;
            };
            if ended.success() {
                // Finished its work (a replay reached its end): not a fault, see `finished`.
                continue;
            }
            let role = self.children.procs[k].role;
            if !self.running && ended.failed_by_itself() {
                anyhow::bail!(
                    "the {role} process exited ({ended}) before the pipeline's first frame: not \
                     restarted, as a start-up error would only repeat — see its message above"
                );
            }
            self.restart(k, ended, now)?;
            restarted.push(role);
        }
        Ok(restarted)
    }

    /// The launcher's gap since the previous check: a stall (longer than half the hang time)
    /// re-arms every clock, the children's silence meanwhile not being theirs.
    fn launcher_gap(&mut self, now: u64) {
        let gap = self
            .last_check_ns
            .map_or(0, |prev| now.saturating_sub(prev));
        self.last_check_ns = Some(now);
        self.stalls.max_gap_ms = self.stalls.max_gap_ms.max(gap as f64 / 1e6);
        let Some(l) = self.liveness else {
            return;
        };
        if gap > l.hang_ns / 2 {
            self.stalls.count += 1;
            for p in &mut self.children.procs {
                p.spawned_ns = p.spawned_ns.max(now);
                p.beat_ns = p.beat_ns.map(|_| now);
            }
        }
    }

    /// How process `k` ended, or — watched, the pipeline running, silent past the limit — that it
    /// hung, after killing and reaping it.
    fn ended_or_hung(&mut self, k: usize, now: u64) -> Option<Ended> {
        let (running, liveness) = (self.running, self.liveness);
        let watched = self.watched.contains(&self.children.procs[k].role);
        let p = &mut self.children.procs[k];
        if let Some(ended) = p.poll().cloned() {
            return Some(ended);
        }
        let silent = liveness
            .filter(|_| running && watched)
            .and_then(|l| p.silent_for(now, &l))?;
        let stopped = p.stopped();
        p.kill_and_reap();
        let ended = Ended::Hung {
            silent_ms: silent / 1_000_000,
            stopped,
        };
        p.ended = Some(ended.clone());
        Some(ended)
    }

    /// Start process `k` again after it `ended`, within the intensity limit.
    fn restart(&mut self, k: usize, ended: Ended, now: u64) -> anyhow::Result<()> {
        let role = self.children.procs[k].role;
        let window = (self.intensity.within_s * 1e9) as u64;
        while self
            .recent
            .front()
            .is_some_and(|&t| now.saturating_sub(t) > window)
        {
            self.recent.pop_front();
        }
        let how = match ended {
            Ended::Hung { .. } => "was killed",
            _ => "exited",
        };
        if self.recent.len() >= self.intensity.max_restarts as usize {
            anyhow::bail!(
                "the {role} process {how} ({ended}) after {} restart(s) within {} s: more than the \
                 limit (--max-restarts {} within --restart-window-s {}); giving up — see its \
                 message above",
                self.recent.len(),
                self.intensity.within_s,
                self.intensity.max_restarts,
                self.intensity.within_s
            );
        }
        let cleaned_nodes =
            (self.clean)().with_context(|| format!("before restarting the {role} process"))?;
        let child = (self.spawns[k])()?;
        self.children.procs[k] = Proc::new(role, child);
        self.recent.push_back(now);
        self.restarts.push(Restart {
            role,
            ended: ended.to_string(),
            hung: matches!(ended, Ended::Hung { .. }),
            at_s: now.saturating_sub(self.started_ns) as f64 / 1e9,
            cleaned_nodes,
            recover_ms: None,
            seen_ns: now,
        });
        Ok(())
    }

    /// The first process that exited successfully (transient, as in OTP: a process that finished
    /// its work — the tracker-bridge at the end of a replay — is not restarted; the caller decides
    /// whether the run ends).
    pub fn finished(&mut self) -> Option<&'static str> {
        self.children
            .procs
            .iter_mut()
            .find_map(|p| p.poll().is_some_and(Ended::success).then_some(p.role))
    }

    /// The pipeline showed a fresh frame at `now_ns`: every restart not yet recovered is, now.
    pub fn recovered(&mut self, now_ns: u64) {
        for r in self.restarts.iter_mut().rev() {
            if r.recover_ms.is_some() {
                break;
            }
            r.recover_ms = Some(now_ns.saturating_sub(r.seen_ns) as f64 / 1e6);
        }
    }

    /// Restarts waiting for a fresh frame.
    pub fn recovering(&self) -> bool {
        self.restarts.last().is_some_and(|r| r.recover_ms.is_none())
    }
}

/// The deterministic expectation of a restarted engine: its first frame (at the resume tick) must
/// show the breath an uninterrupted engine of the same scene shows at that tick — each lung's
/// phase, cycle and volume, bit for bit (an [`engine::runtime::EngineCore`] resumed there, stepped
/// without tracker input: the breath does not depend on the pose).
pub struct PhaseCheck {
    scene: lung_model::scene::Scene,
    /// Resumed frames checked.
    pub checked: u64,
    /// Resumed frames that differed from the expectation.
    pub errors: u64,
}

impl PhaseCheck {
    /// A check against `scene` (its kernels are loaded at the first check).
    pub fn new(scene: &lung_model::scene::Scene) -> Self {
        Self {
            scene: scene.clone(),
            checked: 0,
            errors: 0,
        }
    }

    /// Check the first frame `got` of a resumed engine; false (counted, and said) when it differs.
    pub fn check(&mut self, got: &ipc_types::EngineFrame) -> bool {
        self.checked += 1;
        let expected = (|| -> anyhow::Result<ipc_types::EngineFrame> {
            let mut core = engine::runtime::EngineCore::new(&self.scene)?;
            core.resume_at(got.tick)?;
            let mut f = ipc_types::EngineFrame::default();
            core.step(got.tick, None, &mut f);
            Ok(f)
        })();
        let why = match expected {
            Err(e) => Some(format!("no expectation: {e:#}")),
            Ok(want) => want
                .lungs
                .iter()
                .zip(&got.lungs)
                .enumerate()
                .find(|(_, (w, g))| {
                    w.phase.to_bits() != g.phase.to_bits()
                        || w.cycle != g.cycle
                        || w.volume_ml.to_bits() != g.volume_ml.to_bits()
                })
                .map(|(k, (w, g))| {
                    format!(
                        "lung slot {k}: phase {} cycle {} volume {} ml, expected phase {} cycle {} \
                         volume {} ml",
                        g.phase, g.cycle, g.volume_ml, w.phase, w.cycle, w.volume_ml
                    )
                }),
        };
        match why {
            None => true,
            Some(why) => {
                self.errors += 1;
                eprintln!(
                    "lungdyn: BREATHING PHASE ERROR after the engine restart at tick {}: {why}",
                    got.tick
                );
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `sh -c script` with SIGINT at its default (whatever the test runner inherited), stdout
    /// piped; returns once the script has printed its first line (so its traps are in place).
    fn sh(role: &'static str, script: &str) -> Proc {
        use std::io::BufRead;
        use std::os::unix::process::CommandExt;
        let mut cmd = Command::new("sh");
        cmd.args(["-c", script]).stdout(Stdio::piped());
        // SAFETY: signal(2) is async-signal-safe.
        unsafe {
            cmd.pre_exec(|| {
                libc::signal(libc::SIGINT, libc::SIG_DFL);
                Ok(())
            });
        }
        let mut child = cmd.spawn().unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        assert_eq!(line.trim(), "ready", "{role}");
        Proc::new(role, child)
    }

    fn code(e: &Ended) -> Option<i32> {
        match e {
            Ended::Status(s) => s.code(),
            Ended::Unknown(_) | Ended::Hung { .. } => None,
        }
    }

    fn signal_of(e: &Ended) -> Option<i32> {
        use std::os::unix::process::ExitStatusExt;
        match e {
            Ended::Status(s) => s.signal(),
            Ended::Unknown(_) | Ended::Hung { .. } => None,
        }
    }

    #[test]
    fn a_reaped_child_is_never_signalled_again() {
        let mut children = Children {
            procs: vec![sh("quits", "echo ready; exit 3")],
        };
        let (role, ended) = loop {
            if let Some(e) = children.exited() {
                break e;
            }
            std::thread::sleep(Duration::from_millis(5));
        };
        assert_eq!((role, code(&ended)), ("quits", Some(3)));
        // Reaped: its pid may belong to someone else now, so nothing is sent to it.
        assert!(!children.procs[0].signal(libc::SIGINT));
        assert!(children.stop(Duration::from_millis(50)).is_empty());
        assert_eq!(code(children.procs[0].poll().unwrap()), Some(3));
    }

    #[test]
    fn stop_interrupts_then_kills_only_stragglers() {
        let mut children = Children {
            procs: vec![
                sh("polite", "echo ready; exec sleep 30"),
                sh("stubborn", "trap '' INT; echo ready; exec sleep 30"),
            ],
        };
        assert!(children.exited().is_none());
        let killed = children.stop(Duration::from_millis(300));
        assert_eq!(killed, vec!["stubborn"]);
        assert_eq!(
            signal_of(children.procs[0].poll().unwrap()),
            Some(libc::SIGINT)
        );
        assert_eq!(
            signal_of(children.procs[1].poll().unwrap()),
            Some(libc::SIGKILL)
        );
        // Both reaped: a second stop sends nothing and kills nothing.
        assert!(!children.procs[0].signal(libc::SIGTERM));
        assert!(children.stop(Duration::from_millis(10)).is_empty());
    }

    #[test]
    fn a_stopped_child_is_interrupted_and_continued_and_a_running_one_is_not_continued() {
        let mut children = Children {
            procs: vec![
                sh("stopped", "echo ready; exec sleep 30"),
                // Counts the SIGCONTs it catches: a running child must get none.
                sh(
                    "running",
                    "n=0; trap 'n=$((n+1))' CONT; trap 'exit $((40+n))' INT; echo ready; \
                     while :; do sleep 0.01; done",
                ),
            ],
        };
        assert!(children.procs[0].signal(libc::SIGSTOP));
        until(|| children.procs[0].stopped().then_some(()));
        assert!(!children.procs[1].stopped());
        assert!(
            children.stop(Duration::from_secs(5)).is_empty(),
            "none killed"
        );
        assert_eq!(
            signal_of(children.procs[0].poll().unwrap()),
            Some(libc::SIGINT)
        );
        assert_eq!(code(children.procs[1].poll().unwrap()), Some(40));
        assert!(
            !children.procs[0].stopped(),
            "an ended child is not stopped"
        );
    }

    fn no_cleaning<'a>() -> Cleaner<'a> {
        Box::new(|| Ok(Vec::new()))
    }

    /// `sh -c script` as a supervised child, SIGINT at its default (a test runner started in the
    /// background by a non-interactive shell passes SIGINT on ignored, and `stop` would then have
    /// to kill).
    fn shell<'a>(script: &'static str, starts: &'a std::cell::Cell<u32>) -> Spawn<'a> {
        Box::new(move || {
            use std::os::unix::process::CommandExt;
            starts.set(starts.get() + 1);
            let mut cmd = Command::new("sh");
            cmd.args(["-c", script])
                .stdin(Stdio::null())
                .stdout(Stdio::null());
            // SAFETY: signal(2) is async-signal-safe.
            unsafe {
                cmd.pre_exec(|| {
                    libc::signal(libc::SIGINT, libc::SIG_DFL);
                    Ok(())
                });
            }
            Ok(cmd.spawn()?)
        })
    }

    fn until<T>(mut f: impl FnMut() -> Option<T>) -> T {
        let t0 = now_ns();
        loop {
            if let Some(t) = f() {
                return t;
            }
            assert!(now_ns() - t0 < 10_000_000_000, "timed out");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    #[test]
    fn only_the_dead_process_is_restarted_and_its_cleaner_runs_first() {
        let (a, b) = (std::cell::Cell::new(0), std::cell::Cell::new(0));
        let cleaned = std::cell::Cell::new(0);
        let mut s = Supervisor::new(
            Intensity::checked(3, 60.0).unwrap(),
            Box::new(|| {
                cleaned.set(cleaned.get() + 1);
                Ok(vec!["node".to_string()])
            }),
        );
        s.start("steady", shell("exec sleep 30", &a)).unwrap();
        s.start("victim", shell("exec sleep 30", &b)).unwrap();
        assert!(s.check().unwrap().is_empty());
        assert!(s.children.procs[1].signal(libc::SIGKILL));
        let restarted = until(|| {
            let r = s.check().unwrap();
            (!r.is_empty()).then_some(r)
        });
        assert_eq!(restarted, vec!["victim"]);
        assert_eq!((a.get(), b.get(), cleaned.get()), (1, 2, 1));
        let r = &s.restarts[0];
        assert_eq!(r.role, "victim");
        assert!(
            r.ended.contains("9") || r.ended.contains("KILL"),
            "{}",
            r.ended
        );
        assert_eq!(r.cleaned_nodes, vec!["node"]);
        assert!(s.recovering());
        s.recovered(now_ns());
        assert!(!s.recovering() && s.restarts[0].recover_ms.unwrap() >= 0.0);
        // The new victim runs.
        assert!(s.children.procs[1].poll().is_none());
        assert!(s.children.stop(Duration::from_millis(500)).is_empty());
    }

    #[test]
    fn a_restart_storm_past_the_limit_stops_with_a_clear_error() {
        let starts = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(2, 60.0).unwrap(), no_cleaning());
        s.pipeline_running();
        s.start("crasher", shell("exit 7", &starts)).unwrap();
        let e = until(|| s.check().err());
        let msg = format!("{e:#}");
        assert!(
            msg.contains("crasher") && msg.contains("--max-restarts 2"),
            "{msg}"
        );
        assert!(msg.contains("exit status: 7"), "{msg}");
        assert_eq!(starts.get(), 3, "the first start and two restarts");
        assert_eq!(s.restarts.len(), 2);
    }

    #[test]
    fn a_start_up_error_ends_the_run_at_once_but_a_kill_before_the_first_frame_is_restarted() {
        let (a, b) = (std::cell::Cell::new(0), std::cell::Cell::new(0));
        let mut s = Supervisor::new(Intensity::checked(5, 60.0).unwrap(), no_cleaning());
        s.start("renderer", shell("exit 1", &a)).unwrap();
        let e = until(|| s.check().err());
        let msg = format!("{e:#}");
        assert!(
            msg.contains("renderer") && msg.contains("before the pipeline's first frame"),
            "{msg}"
        );
        assert_eq!((a.get(), s.restarts.len()), (1, 0), "not restarted");
        // Killed by a signal before the first frame: not an error it reported, restarted.
        let mut s = Supervisor::new(Intensity::checked(5, 60.0).unwrap(), no_cleaning());
        s.start("engine", shell("exec sleep 30", &b)).unwrap();
        assert!(s.children.procs[0].signal(libc::SIGKILL));
        until(|| (!s.check().unwrap().is_empty()).then_some(()));
        assert_eq!((b.get(), s.restarts.len()), (2, 1));
        assert!(s.children.stop(Duration::from_millis(500)).is_empty());
    }

    #[test]
    fn a_process_that_finished_its_work_is_not_restarted() {
        let starts = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(3, 60.0).unwrap(), no_cleaning());
        s.start("replay", shell("exit 0", &starts)).unwrap();
        assert_eq!(until(|| s.finished()), "replay");
        assert!(s.check().unwrap().is_empty());
        assert_eq!((starts.get(), s.restarts.len()), (1, 0));
    }

    const MS: u64 = 1_000_000;

    fn liveness() -> Option<Liveness> {
        Liveness::checked(1.0, 5.0).unwrap()
    }

    #[test]
    fn a_watched_process_that_stops_answering_is_killed_and_restarted() {
        let (a, b) = (std::cell::Cell::new(0), std::cell::Cell::new(0));
        let mut s = Supervisor::new(Intensity::checked(3, 60.0).unwrap(), no_cleaning())
            .with_liveness(liveness());
        s.start("renderer", shell("exec sleep 30", &a)).unwrap();
        s.start("remote", shell("exec sleep 30", &b)).unwrap();
        s.watch("renderer");
        s.pipeline_running();
        let t0 = now_ns();
        s.beat("renderer", t0, t0);
        // Stopped for good (SIGSTOP), and so is the unwatched one: only exits judge that.
        assert!(s.children.procs[0].signal(libc::SIGSTOP));
        assert!(s.children.procs[1].signal(libc::SIGSTOP));
        until(|| s.children.procs[0].stopped().then_some(()));
        // Checked often (no launcher stall), it is silent for just under, then just over, 1 s.
        let mut t = t0;
        while t < t0 + 990 * MS {
            t += 100 * MS;
            assert!(s.check_at(t.min(t0 + 990 * MS)).unwrap().is_empty());
        }
        assert_eq!(s.check_at(t0 + 1010 * MS).unwrap(), vec!["renderer"]);
        let r = &s.restarts[0];
        assert!(r.hung, "{r:?}");
        assert!(
            r.ended.contains("no frame for 1010 ms") && r.ended.contains("state T"),
            "{}",
            r.ended
        );
        assert_eq!(
            (a.get(), b.get()),
            (2, 1),
            "the renderer alone started again"
        );
        assert!(
            s.children.procs[0].poll().is_none(),
            "the new renderer runs"
        );
        assert!(
            s.children.procs[1].stopped(),
            "the unwatched one is left alone"
        );
        assert!(s.children.stop(Duration::from_secs(5)).is_empty());
    }

    #[test]
    fn a_hung_process_counts_against_the_restart_limit() {
        let a = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(0, 60.0).unwrap(), no_cleaning())
            .with_liveness(liveness());
        s.start("engine", shell("exec sleep 30", &a)).unwrap();
        s.watch("engine");
        s.pipeline_running();
        let t0 = now_ns();
        s.beat("engine", t0, t0);
        s.check_at(t0 + 400 * MS).unwrap();
        s.check_at(t0 + 800 * MS).unwrap();
        let e = s.check_at(t0 + 1200 * MS).unwrap_err();
        let msg = format!("{e:#}");
        assert!(
            msg.contains("engine process was killed (stopped answering: no frame for 1200 ms")
                && msg.contains("--max-restarts 0"),
            "{msg}"
        );
        assert_eq!(a.get(), 1);
    }

    #[test]
    fn the_launchers_own_stall_is_counted_and_blames_no_one() {
        let a = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(3, 60.0).unwrap(), no_cleaning())
            .with_liveness(liveness());
        s.start("engine", shell("exec sleep 30", &a)).unwrap();
        s.watch("engine");
        s.pipeline_running();
        let t0 = now_ns();
        s.beat("engine", t0, t0);
        s.check_at(t0 + 10 * MS).unwrap();
        // The launcher itself was frozen 3 s (Ctrl-Z of the whole job): nobody is restarted.
        assert!(s.check_at(t0 + 3010 * MS).unwrap().is_empty());
        assert_eq!(s.stalls.count, 1);
        assert!(
            (s.stalls.max_gap_ms - 3000.0).abs() < 1e-6,
            "{:?}",
            s.stalls
        );
        // The clock started again at the stall's end: silent 1 s after it, the engine is hung.
        assert!(s.check_at(t0 + 3500 * MS).unwrap().is_empty());
        assert!(s.check_at(t0 + 3900 * MS).unwrap().is_empty());
        assert_eq!(s.check_at(t0 + 4100 * MS).unwrap(), vec!["engine"]);
        assert!(!s.restarts[0].ended.contains("state T"), "it was running");
        assert!(s.children.stop(Duration::from_secs(5)).is_empty());
    }

    #[test]
    fn a_frame_of_the_predecessor_is_no_sign_of_life_and_a_silent_start_gets_the_start_up_time() {
        let a = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(3, 60.0).unwrap(), no_cleaning())
            .with_liveness(liveness());
        let before = now_ns();
        s.start("renderer", shell("exec sleep 30", &a)).unwrap();
        s.watch("renderer");
        // Not judged before the pipeline's first frame (the start-up timeout is the caller's).
        assert!(s.check_at(before + 9000 * MS).unwrap().is_empty());
        s.pipeline_running();
        let t0 = now_ns();
        s.last_check_ns = Some(t0);
        // A report its predecessor published before this one started: not this one's.
        s.beat("renderer", before.saturating_sub(1), t0);
        assert!(s.children.procs[0].beat_ns.is_none());
        // Silent since its start: it has the start-up time (5 s), not the hang time (1 s).
        let mut t = t0;
        while t < t0 + 4500 * MS {
            t += 400 * MS;
            assert!(s.check_at(t).unwrap().is_empty(), "at {} ms", (t - t0) / MS);
        }
        assert_eq!(s.check_at(t0 + 5200 * MS).unwrap(), vec!["renderer"]);
        assert!(s.children.stop(Duration::from_secs(5)).is_empty());
    }

    #[test]
    fn the_hang_time_is_checked() {
        assert_eq!(Liveness::checked(0.0, 60.0).unwrap(), None);
        let l = Liveness::checked(1.5, 60.0).unwrap().unwrap();
        assert_eq!(
            (l.hang_ns, l.first_beat_ns),
            (1_500_000_000, 60_000_000_000)
        );
        for bad in [-1.0, 0.05, 601.0, f64::NAN, f64::INFINITY] {
            let e = Liveness::checked(bad, 60.0).unwrap_err().to_string();
            assert!(e.contains("--hang-after-s") && e.contains("or 0"), "{e}");
        }
    }

    #[test]
    fn restarts_older_than_the_window_do_not_count() {
        let starts = std::cell::Cell::new(0);
        let mut s = Supervisor::new(Intensity::checked(1, 0.1).unwrap(), no_cleaning());
        s.pipeline_running();
        s.start("slow-crasher", shell("sleep 0.3; exit 1", &starts))
            .unwrap();
        // Each death comes more than 0.1 s after the previous restart: always within the limit.
        until(|| (s.check().unwrap().len() + s.restarts.len() >= 3).then_some(()));
        assert!(starts.get() >= 3);
        assert!(Intensity::checked(1, 0.0).is_err());
        assert!(Intensity::checked(1, f64::NAN).is_err());
        assert!(Intensity::checked(5000, 1.0).is_err());
    }
}
