//! `lungdyn faults`: seeded, repeatable fault injection against running demo pipelines.
//!
//! Each round is one `lungdyn demo` pipeline ([`crate::demo::run_watched`], supervised by
//! [`crate::supervise`]) with a [`Watch`] that injects the round's faults at engine ticks drawn from
//! the seed, one after the other (the next once the previous has recovered): SIGKILL of each
//! process, SIGSTOP/SIGCONT of each process, an engine stall longer than its budget, corrupted and
//! NaN tracker frames (published by a stray process into the tracker stream), a dead process's
//! shared memory (a stray node SIGKILLed, its resources removed the way the supervisor does); every
//! tenth round is a restart storm past the intensity limit, which must end the run with the
//! limit's error. Per round it checks that the renderer never stops presenting for more than two
//! frame periods (a killed or stopped renderer excepted: its time to the first frame after it came
//! back is reported), that a restarted engine shows the breath an uninterrupted run shows at its
//! resume tick (the demo's [`crate::supervise::PhaseCheck`]), that no frame carries a NaN, that no
//! file of the instance is left in `/dev/shm` or iceoryx2's folder, and it times each fault's
//! recovery: from the end of the fault (the kill, the SIGCONT, the last corrupted frame) to the
//! first frame drawn from a live engine showing a new tracker sample.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context};
use ipc_types::{report_flags, EngineFrame, FrameReport, TrackerFrame};
use rand::{RngExt, SeedableRng};
use rand_xorshift::XorShiftRng;
use serde::Serialize;
use transport::{iox, now_ns, Instance, Publish};

use crate::demo::{Run, Watch};
use lung_model::scene::SceneExt;

/// Options of `lungdyn faults`.
#[derive(Debug, Clone, clap::Args)]
pub struct FaultsArgs {
    /// Seed of the fault plan: the same seed gives the same faults, in the same order, the same
    /// number of engine ticks after the pipeline is ready, with the same pauses and the same
    /// corrupted frames.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Rounds to run (1 to 10000): each a fresh pipeline with two faults; every tenth round a
    /// restart storm instead.
    #[arg(long, default_value_t = 10)]
    pub rounds: u32,
    /// Print one JSON object with the results on stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
    /// Folder for the rounds' kernels and scene (created if missing).
    #[arg(long, default_value = "out/faults")]
    pub out: PathBuf,
    /// Scene file (TOML). Default: the built-in lungs at 1500 vertices drawn as points at 160x120
    /// (a software rasteriser keeps its frame rate, so a frozen picture is the faults' doing).
    #[arg(long)]
    pub scene: Option<PathBuf>,
}

/// Options of the stray process `lungdyn faults-stray` (started by `lungdyn faults` only).
#[derive(Debug, Clone, clap::Args)]
pub struct StrayArgs {
    /// Instance whose tracker stream to publish into.
    #[arg(long)]
    pub instance: String,
    /// What to publish: "corrupt" (garbage tool counts, flags, poses), "nan" (NaN poses flagged
    /// valid), or "hold" (nothing: wait to be killed, leaving a dead node's shared memory).
    #[arg(long)]
    pub mode: String,
    /// Frames to publish, one per 60 Hz period.
    #[arg(long, default_value_t = 30)]
    pub frames: u32,
    /// Seed of the garbage.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// One fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// SIGKILL of a process (restarted by the supervisor).
    Kill(&'static str),
    /// SIGSTOP of a process, SIGCONT after a pause of 150 to 700 ms.
    Pause(&'static str),
    /// SIGSTOP of the engine for 10 to 30 times its per-tick budget (at least 20 ms).
    EngineStall,
    /// 30 tracker frames of garbage (tool counts, status bits, poses, frame numbers) from a stray
    /// publisher beside the bridge.
    CorruptFrames,
    /// 30 tracker frames whose poses are NaN yet flagged valid.
    NanFrames,
    /// A stray node with a tracker publisher, SIGKILLed: its shared memory is a dead process's.
    DeadShm,
    /// A process killed again and again, past the intensity limit (2 restarts): the run must end
    /// with the limit's error.
    Storm(&'static str),
}

const ROLES: [&str; 3] = ["tracker-bridge", "engine", "renderer"];

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Fault::Kill(r) => write!(f, "SIGKILL {r}"),
            Fault::Pause(r) => write!(f, "SIGSTOP/SIGCONT {r}"),
            Fault::EngineStall => write!(f, "engine stall"),
            Fault::CorruptFrames => write!(f, "corrupted tracker frames"),
            Fault::NanFrames => write!(f, "NaN tracker frames"),
            Fault::DeadShm => write!(f, "dead process's shared memory"),
            Fault::Storm(r) => write!(f, "restart storm of the {r}"),
        }
    }
}

impl Fault {
    /// Whether the renderer stops presenting by design during this fault.
    fn stops_renderer(&self) -> bool {
        matches!(
            self,
            Fault::Kill("renderer") | Fault::Pause("renderer") | Fault::Storm("renderer")
        )
    }
}

/// Every fault kind but the storm, in a fixed order (the seed shuffles it).
fn kinds() -> Vec<Fault> {
    let mut k: Vec<Fault> = ROLES.iter().map(|&r| Fault::Kill(r)).collect();
    k.extend(ROLES.iter().map(|&r| Fault::Pause(r)));
    k.extend([
        Fault::EngineStall,
        Fault::CorruptFrames,
        Fault::NanFrames,
        Fault::DeadShm,
    ]);
    k
}

/// One fault of a round's plan.
#[derive(Debug, Clone, PartialEq)]
pub struct Planned {
    /// What.
    pub fault: Fault,
    /// Engine ticks after the pipeline is ready (first frame, or the previous fault recovered).
    pub after_ticks: u64,
    /// Pause of a SIGSTOP, ms (0 for the others).
    pub hold_ms: u64,
    /// Seed of a stray's garbage.
    pub garbage_seed: u64,
}

/// Rounds whose number (from 0) is 9 mod 10 are restart storms.
pub fn is_storm(round: u32) -> bool {
    round % 10 == 9
}

/// The faults of `round` under `seed`: two of the ten kinds (the seed's shuffle of them, dealt
/// two per round, so any ten rounds cover every kind), or a storm. A pure function of its
/// arguments: the same round of a run of any length.
pub fn plan(seed: u64, round: u32, engine_budget_ms: f64) -> Vec<Planned> {
    let mut order = kinds();
    let mut shuffle = XorShiftRng::seed_from_u64(seed);
    for i in (1..order.len()).rev() {
        let j = shuffle.random_range(0..=i);
        order.swap(i, j);
    }
    let mut rng =
        XorShiftRng::seed_from_u64(seed ^ (round as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let stall_ms = (engine_budget_ms * rng.random_range(10.0..30.0)).max(20.0) as u64;
    let mut one = |fault: Fault, first: bool| Planned {
        fault,
        after_ticks: if first {
            rng.random_range(30..90)
        } else {
            rng.random_range(10..40)
        },
        hold_ms: match fault {
            Fault::Pause(_) => rng.random_range(150..700),
            Fault::EngineStall => stall_ms,
            _ => 0,
        },
        garbage_seed: rng.random_range(0..u64::MAX),
    };
    if is_storm(round) {
        let role = ROLES[(round / 10) as usize % ROLES.len()];
        // The first start and 2 restarts are allowed; the third death is one too many.
        return (0..3).map(|k| one(Fault::Storm(role), k == 0)).collect();
    }
    let dealt = (round - round / 10) as usize * 2;
    (0..2)
        .map(|k| one(order[(dealt + k) % order.len()], k == 0))
        .collect()
}

/// A fault as it happened.
#[derive(Debug, Clone, Serialize)]
pub struct FaultRecord {
    /// Round (from 0).
    pub round: u32,
    /// What.
    pub fault: String,
    /// The engine tick it was injected at.
    pub at_tick: u64,
    /// The pause of a SIGSTOP, ms.
    pub hold_ms: u64,
    /// From the end of the fault (kill, SIGCONT, last stray frame) to the first frame drawn from a
    /// live engine with a new tracker sample, ms; for a dead node, to its resources removed; for a
    /// storm, to the run stopped with the limit's error. `None`: never within the round.
    pub recover_ms: Option<f64>,
    /// Processes restarted during the fault that were not its target (must be 0).
    pub unexpected_restarts: usize,
}

/// A presentation gap over two frame periods.
#[derive(Debug, Clone, Serialize)]
pub struct Frozen {
    /// Round.
    pub round: u32,
    /// The gap between two presented frames, ms.
    pub gap_ms: f64,
    /// When it ended, seconds after the round's first frame.
    pub at_s: f64,
    /// The fault under way (injected, not yet recovered), if any.
    pub during: Option<String>,
}

/// One round's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct RoundReport {
    /// Round (from 0).
    pub round: u32,
    /// The instance it ran as.
    pub instance: String,
    /// How the demo ended ("completed", or the storm's error).
    pub ended: String,
    /// Frames the renderer drew.
    pub frames: u64,
    /// Restarts the supervisor made.
    pub restarts: usize,
    /// Engine restarts whose resumed breath differed from the deterministic expectation.
    pub phase_errors: u64,
    /// Files of the instance still in `/dev/shm` or iceoryx2's folder after the round.
    pub leaked_files: usize,
    /// Files iceoryx2 did not clean (a node killed while it was being created is not "dead" to
    /// it) that the launcher's final sweep of the instance's prefix removed.
    pub removed_by_launcher: usize,
    /// Presentation gaps over two frame periods during its faults.
    pub frozen_during_faults: usize,
    /// Whether the round met every assertion.
    pub ok: bool,
    /// What failed, when not ok.
    pub problems: Vec<String>,
}

/// The result of `lungdyn faults`.
#[derive(Debug, Serialize)]
pub struct FaultsReport {
    /// Seed of the plan.
    pub seed: u64,
    /// Rounds run.
    pub rounds: u32,
    /// Rounds that met every assertion.
    pub rounds_ok: u32,
    /// Faults injected.
    pub faults: usize,
    /// Presentation gaps over two frame periods while a fault was under way (from its injection
    /// to its recovery; a killed or stopped renderer excepted): the assertion.
    pub frozen_over_2_frames: usize,
    /// Gaps over two frame periods with no fault under way: the machine's load, reported apart
    /// (the fault rounds run on whatever else the machine does).
    pub frozen_outside_faults: usize,
    /// Files of the rounds' instances still in `/dev/shm` or iceoryx2's folder after their round.
    pub leaked_files: usize,
    /// Files iceoryx2 left that the launcher's final sweep removed (see [`RoundReport`]).
    pub removed_by_launcher: usize,
    /// Resumed engines that differed from the deterministic expectation.
    pub phase_errors: u64,
    /// Engine frames with a non-finite volume, phase, coefficient or pose.
    pub nan_frames: u64,
    /// Faults that did not recover within their round.
    pub unrecovered: usize,
    /// Restarts of processes a fault did not target.
    pub unexpected_restarts: usize,
    /// Time to recover, all faults but storms and dead nodes: median, ms (HdrHistogram).
    pub recover_p50_ms: f64,
    /// 99th percentile, ms.
    pub recover_p99_ms: f64,
    /// Maximum, ms.
    pub recover_max_ms: f64,
    /// Per fault kind: count, median and maximum time to recover, ms.
    pub by_kind: Vec<KindRow>,
    /// Time from a killed renderer's restart to its first frame, ms, each.
    pub renderer_first_frame_ms: Vec<f64>,
    /// Every fault.
    pub log: Vec<FaultRecord>,
    /// Every frozen picture.
    pub frozen: Vec<Frozen>,
    /// Every round.
    pub round_log: Vec<RoundReport>,
    /// Seconds the run took.
    pub seconds: f64,
}

/// One fault kind's figures.
#[derive(Debug, Clone, Serialize)]
pub struct KindRow {
    /// The kind.
    pub fault: String,
    /// Injected.
    pub count: usize,
    /// Median time to recover, ms.
    pub p50_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

/// The default scene of the fault rounds: small enough that a software rasteriser keeps 60 Hz.
const SMALL_SCENE: &str = "# lungdyn faults: the built-in lungs, small and cheap to draw\n\
[lungs]\nvertices = 1500\n[render]\nwidth = 160\nheight = 120\nstereo = false\nmode = \"points\"\n";

/// The fault in progress.
struct Active {
    planned: Planned,
    at_tick: u64,
    injected_ns: u64,
    /// When the fault's action ended (kill, SIGCONT, stray done); recovery is timed from here.
    ended_ns: Option<u64>,
    /// The tick and sample shown when it ended: a recovered frame is newer in both.
    tick_at_end: u64,
    sample_at_end: u64,
    restarts_before: usize,
    /// A killed process's restart has been seen (its recovery counts from frames after it).
    restart_seen: bool,
    stray: Option<Child>,
    storm_kills: u32,
}

/// The injector of one round.
struct Injector<'x> {
    round: u32,
    plan: Vec<Planned>,
    next: usize,
    exe: &'x Path,
    period_ns: u64,
    /// Tick from which the next fault's `after_ticks` count (first frame, or last recovery).
    ready_tick: Option<u64>,
    active: Option<Active>,
    /// Latest report's sample, tick and flags, and when the last frame was presented.
    last_sample: u64,
    last_submit: Option<u64>,
    first_submit: Option<u64>,
    /// Reports seen since the active fault ended that show recovery (set in `report`).
    healthy_since_end: Option<u64>,
    /// Renderer fault windows (start, end): presentation gaps inside are excepted.
    renderer_windows: Vec<(u64, Option<u64>)>,
    /// Fault windows (start, end, name) for attributing gaps.
    windows: Vec<(u64, Option<u64>, String)>,
    records: Vec<FaultRecord>,
    frozen: Vec<Frozen>,
    nan_frames: u64,
    renderer_first_frame_ms: Vec<f64>,
    done_at_tick: Option<u64>,
}

impl<'x> Injector<'x> {
    fn new(round: u32, plan: Vec<Planned>, exe: &'x Path, period_ns: u64) -> Self {
        Self {
            round,
            plan,
            next: 0,
            exe,
            period_ns,
            ready_tick: None,
            active: None,
            last_sample: 0,
            last_submit: None,
            first_submit: None,
            healthy_since_end: None,
            renderer_windows: Vec::new(),
            windows: Vec::new(),
            records: Vec::new(),
            frozen: Vec::new(),
            nan_frames: 0,
            renderer_first_frame_ms: Vec::new(),
            done_at_tick: None,
        }
    }

    fn stray(&self, instance: &str, mode: &str, seed: u64) -> anyhow::Result<Child> {
        Command::new(self.exe)
            .args(["faults-stray", "--instance", instance, "--mode", mode])
            .args(["--seed", &seed.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("cannot start the stray process of a fault")
    }

    /// Start the next fault.
    fn inject(&mut self, run: &mut Run<'_, '_>, tick: u64) -> anyhow::Result<()> {
        let planned = self.plan[self.next].clone();
        self.next += 1;
        let now = now_ns();
        let instance = run.services.name().to_string();
        let mut a = Active {
            planned: planned.clone(),
            at_tick: tick,
            injected_ns: now,
            ended_ns: None,
            tick_at_end: tick,
            sample_at_end: self.last_sample,
            restarts_before: run.supervisor.restarts.len(),
            restart_seen: false,
            stray: None,
            storm_kills: 0,
        };
        let children = &mut run.supervisor.children;
        match planned.fault {
            Fault::Kill(role) | Fault::Storm(role) => {
                if !children.signal_role(role, libc::SIGKILL) {
                    bail!(
                        "round {}: the {role} was not running to be killed",
                        self.round
                    );
                }
                a.ended_ns = Some(now);
                a.storm_kills = 1;
            }
            Fault::Pause(role) => {
                if !children.signal_role(role, libc::SIGSTOP) {
                    bail!(
                        "round {}: the {role} was not running to be stopped",
                        self.round
                    );
                }
            }
            Fault::EngineStall => {
                if !children.signal_role("engine", libc::SIGSTOP) {
                    bail!("round {}: the engine was not running to stall", self.round);
                }
            }
            Fault::CorruptFrames => {
                a.stray = Some(self.stray(&instance, "corrupt", planned.garbage_seed)?)
            }
            Fault::NanFrames => {
                a.stray = Some(self.stray(&instance, "nan", planned.garbage_seed)?)
            }
            Fault::DeadShm => {
                let mut child = self.stray(&instance, "hold", planned.garbage_seed)?;
                // Killed once its node and publisher exist (it says "ready").
                let mut line = String::new();
                let out = child.stdout.take().context("the stray's stdout")?;
                std::io::BufReader::new(out).read_line(&mut line)?;
                if line.trim() != "ready" {
                    let _ = child.kill();
                    let _ = child.wait();
                    bail!("round {}: the stray node did not start", self.round);
                }
                child.kill()?;
                child.wait()?;
                a.ended_ns = Some(now_ns());
            }
        }
        let name = planned.fault.to_string();
        if planned.fault.stops_renderer() {
            self.renderer_windows.push((now, None));
        }
        self.windows.push((now, None, name));
        self.healthy_since_end = None;
        self.active = Some(a);
        Ok(())
    }

    /// Close the active fault: record it.
    fn close(&mut self, recover_ms: Option<f64>, restarts_now: usize) {
        let Some(a) = self.active.take() else { return };
        let now = now_ns();
        let expected = match a.planned.fault {
            Fault::Kill(_) => 1,
            Fault::Storm(_) => a.storm_kills.min(2) as usize,
            _ => 0,
        };
        if let Some(w) = self.windows.last_mut() {
            w.1 = Some(now);
        }
        if a.planned.fault.stops_renderer() {
            if let Some(w) = self.renderer_windows.last_mut() {
                w.1 = Some(now);
            }
            if a.planned.fault == Fault::Kill("renderer") {
                if let Some(ms) = recover_ms {
                    self.renderer_first_frame_ms.push(ms);
                }
            }
        }
        self.records.push(FaultRecord {
            round: self.round,
            fault: a.planned.fault.to_string(),
            at_tick: a.at_tick,
            hold_ms: a.planned.hold_ms,
            recover_ms,
            unexpected_restarts: (restarts_now - a.restarts_before).saturating_sub(expected),
        });
    }
}

/// Whether an engine frame carries a non-finite value anywhere it could be drawn.
fn has_nan(f: &EngineFrame) -> bool {
    !f.patient_pose.is_finite()
        || f.lungs.iter().any(|l| {
            !(l.volume_ml.is_finite()
                && l.phase.is_finite()
                && l.deform_scale.is_finite()
                && l.collapse.is_finite()
                && l.offset_mm.iter().all(|v| v.is_finite())
                && l.hilum_mm.iter().all(|v| v.is_finite())
                && l.coeffs.iter().all(|v| v.is_finite()))
        })
}

impl Watch for Injector<'_> {
    fn report(&mut self, r: &FrameReport) {
        let submit = r.stamps.renderer_submit_ns;
        if let Some(last) = self.last_submit {
            let gap = submit.saturating_sub(last);
            if gap > 2 * self.period_ns {
                let overlaps =
                    |(s, e): (u64, Option<u64>)| last < e.unwrap_or(u64::MAX) && submit > s;
                let excepted = self.renderer_windows.iter().any(|&w| overlaps(w));
                if !excepted {
                    let during = self
                        .windows
                        .iter()
                        .find(|(s, e, _)| overlaps((*s, *e)))
                        .map(|w| w.2.clone());
                    self.frozen.push(Frozen {
                        round: self.round,
                        gap_ms: gap as f64 / 1e6,
                        at_s: submit.saturating_sub(self.first_submit.unwrap_or(submit)) as f64
                            / 1e9,
                        during,
                    });
                }
            }
        }
        self.last_submit = Some(self.last_submit.map_or(submit, |l| l.max(submit)));
        self.first_submit.get_or_insert(submit);
        let fresh = r.flags & (report_flags::STALE_ENGINE | report_flags::ENGINE_DOWN) == 0;
        if let Some(a) = &self.active {
            if let Some(end) = a.ended_ns {
                if self.healthy_since_end.is_none()
                    && fresh
                    && submit > end
                    && r.engine_tick > a.tick_at_end
                    && r.tracker_frame != a.sample_at_end
                {
                    self.healthy_since_end = Some(now_ns());
                }
            }
        }
        self.last_sample = r.tracker_frame;
    }

    fn engine_frame(&mut self, f: &EngineFrame) {
        if has_nan(f) {
            self.nan_frames += 1;
        }
    }

    fn pass(&mut self, run: &mut Run<'_, '_>) -> anyhow::Result<bool> {
        let Some(tick) = run.last_tick else {
            return Ok(true);
        };
        if run.first_frame_ns.is_none() {
            return Ok(true);
        }
        let ready = *self.ready_tick.get_or_insert(tick);
        let restarts = run.supervisor.restarts.len();
        let Some(a) = self.active.as_mut() else {
            if self.next < self.plan.len() {
                if tick >= ready + self.plan[self.next].after_ticks {
                    self.inject(run, tick)?;
                }
                return Ok(true);
            }
            // All done: 20 more ticks of normal running, then the round ends.
            let end = *self.done_at_tick.get_or_insert(tick + 20);
            return Ok(tick < end);
        };
        let now = run.now_ns;
        // Faults with a second act: SIGCONT after the pause, the stray's exit.
        if a.ended_ns.is_none() {
            match a.planned.fault {
                Fault::Pause(role) if now >= a.injected_ns + a.planned.hold_ms * 1_000_000 => {
                    run.supervisor.children.signal_role(role, libc::SIGCONT);
                    a.ended_ns = Some(now_ns());
                }
                Fault::EngineStall if now >= a.injected_ns + a.planned.hold_ms * 1_000_000 => {
                    run.supervisor.children.signal_role("engine", libc::SIGCONT);
                    a.ended_ns = Some(now_ns());
                }
                Fault::CorruptFrames | Fault::NanFrames => {
                    let stray = a.stray.as_mut().expect("a stray publishes these");
                    if let Some(status) = stray.try_wait()? {
                        if !status.success() {
                            bail!(
                                "round {}: the stray publisher of {} failed ({status})",
                                self.round,
                                a.planned.fault
                            );
                        }
                        a.ended_ns = Some(now_ns());
                    }
                }
                _ => {}
            }
            if a.ended_ns.is_some() {
                a.tick_at_end = tick;
                a.sample_at_end = self.last_sample;
                self.healthy_since_end = None;
            }
            return Ok(true);
        }
        let end = a.ended_ns.expect("checked");
        match a.planned.fault {
            Fault::DeadShm => {
                let cleaned = iox::remove_dead_nodes(run.services)?;
                if cleaned.iter().any(|n| n.ends_with("-stray")) {
                    let ms = now_ns().saturating_sub(end) as f64 / 1e6;
                    self.close(Some(ms), restarts);
                    self.ready_tick = Some(tick);
                } else if now > end + 5_000_000_000 {
                    self.close(None, restarts);
                    self.ready_tick = Some(tick);
                }
            }
            Fault::Storm(role) => {
                // Kill the freshly restarted process again as soon as it is back, until the limit
                // ends the run (the demo then stops with the limit's error: see `run_round`).
                if restarts > a.restarts_before + a.storm_kills as usize - 1
                    && self.next < self.plan.len()
                    && tick >= a.tick_at_end + self.plan[self.next].after_ticks
                    && run.supervisor.children.signal_role(role, libc::SIGKILL)
                {
                    self.next += 1;
                    a.storm_kills += 1;
                    a.tick_at_end = tick;
                    a.ended_ns = Some(now_ns());
                }
            }
            _ => {
                if matches!(a.planned.fault, Fault::Kill(_)) && !a.restart_seen {
                    // Frames before the restart (one in flight from the killed engine) do not
                    // count: the successor's must be newer.
                    if restarts > a.restarts_before {
                        a.restart_seen = true;
                        a.tick_at_end = tick;
                        self.healthy_since_end = None;
                    }
                } else if let Some(at) = self.healthy_since_end {
                    let ms = at.saturating_sub(end) as f64 / 1e6;
                    self.close(Some(ms), restarts);
                    self.ready_tick = Some(tick);
                } else if now > end + 10_000_000_000 {
                    self.close(None, restarts);
                    self.ready_tick = Some(tick);
                }
            }
        }
        Ok(true)
    }
}

/// Check the options before any work.
pub fn check(args: &FaultsArgs) -> anyhow::Result<()> {
    if !(1..=10_000).contains(&args.rounds) {
        bail!("--rounds {}: must be from 1 to 10000", args.rounds);
    }
    if let Some(s) = &args.scene {
        lung_model::scene::Scene::load(s)?;
    }
    crate::outputs::check_writable(&args.out)
}

/// One round: a demo pipeline with the injector watching.
fn run_round<'x>(
    args: &FaultsArgs,
    scene: &Path,
    round: u32,
    exe: &'x Path,
    budget_ms: f64,
    period_ns: u64,
) -> anyhow::Result<(RoundReport, Injector<'x>)> {
    let plan = plan(args.seed, round, budget_ms);
    let storm = is_storm(round);
    let instance = format!("faults-{}-r{round}", std::process::id());
    let mut demo_args = vec![
        "demo".to_string(),
        "--seconds".into(),
        "20".into(),
        "--snapshots".into(),
        "0".into(),
        "--out".into(),
        args.out.display().to_string(),
        "--scene".into(),
        scene.display().to_string(),
        "--instance".into(),
        instance.clone(),
    ];
    if storm {
        demo_args.extend(["--max-restarts".into(), "2".into()]);
    }
    let demo = crate::demo::DemoArgs::from_args(&demo_args)?;
    let mut inj = Injector::new(round, plan, exe, period_ns);
    let report = match crate::demo::run_watched(&demo, &mut inj) {
        Ok(report) => report,
        // A round whose pipeline cannot start (seen on an NVIDIA H200: no adapter for a moment
        // after a storm of killed renderers) fails that round; the rounds after it still run and
        // the report is still written.
        Err(e) => {
            return Ok((
                RoundReport {
                    round,
                    instance,
                    ended: "did not start".into(),
                    frames: 0,
                    restarts: 0,
                    phase_errors: 0,
                    leaked_files: 0,
                    removed_by_launcher: 0,
                    frozen_during_faults: 0,
                    ok: false,
                    problems: vec![format!("the pipeline could not start: {e:#}")],
                },
                inj,
            ));
        }
    };
    let mut problems = Vec::new();
    if storm {
        let stopped = report
            .failure
            .as_deref()
            .is_some_and(|f| f.contains("--max-restarts 2"));
        let ms = inj.active.as_ref().and_then(|a| a.ended_ns).map(|end| {
            // The run has ended: from the last kill to now (the report is written).
            now_ns().saturating_sub(end) as f64 / 1e6
        });
        let restarts = report.restarts;
        inj.close(if stopped { ms } else { None }, restarts);
        if !stopped {
            problems.push(format!(
                "the restart storm did not end the run with the limit's error (ended: {})",
                report.ended
            ));
        }
    } else {
        if let Some(f) = &report.failure {
            problems.push(format!("the run failed: {f}"));
        }
        if inj.active.is_some() {
            inj.close(None, report.restarts);
        }
        if inj.next < inj.plan.len() {
            problems.push(format!(
                "only {} of {} faults were injected",
                inj.next,
                inj.plan.len()
            ));
        }
    }
    let leaked = report.remaining_files;
    if leaked > 0 {
        problems.push(format!("{leaked} files of the instance left behind"));
    }
    if report.phase_errors > 0 {
        problems.push(format!("{} breathing-phase errors", report.phase_errors));
    }
    for r in inj.records.iter().filter(|r| r.round == round) {
        if r.recover_ms.is_none() {
            problems.push(format!("{} did not recover", r.fault));
        }
        if r.unexpected_restarts > 0 {
            problems.push(format!(
                "{} restarted {} process(es) it did not target",
                r.fault, r.unexpected_restarts
            ));
        }
    }
    if inj.nan_frames > 0 {
        problems.push(format!("{} engine frames with a NaN", inj.nan_frames));
    }
    // A gap with no fault under way is the machine's doing (reported, see `frozen_outside_faults`);
    // one during a fault is the pipeline failing to keep presenting through it.
    let during = inj.frozen.iter().filter(|f| f.during.is_some()).count();
    if during > 0 {
        problems.push(format!(
            "{during} presentation gaps over 2 frame periods during a fault"
        ));
    }
    Ok((
        RoundReport {
            round,
            instance,
            ended: report.ended.clone(),
            frames: report.frames_rendered,
            restarts: report.restarts,
            phase_errors: report.phase_errors,
            leaked_files: leaked,
            removed_by_launcher: report.leftover_files,
            frozen_during_faults: during,
            ok: problems.is_empty(),
            problems,
        },
        inj,
    ))
}

/// Run `lungdyn faults`; returns the report (the caller prints it and sets the exit status).
pub fn run(args: &FaultsArgs) -> anyhow::Result<FaultsReport> {
    check(args)?;
    let started = now_ns();
    let scene_path = match &args.scene {
        Some(s) => s.clone(),
        None => {
            let p = args.out.join("faults-scene.toml");
            outfile::write_atomically(&p, |w| std::io::Write::write_all(w, SMALL_SCENE.as_bytes()))
                .with_context(|| format!("cannot write {}", p.display()))?;
            p
        }
    };
    let scene = lung_model::scene::Scene::load(&scene_path)?;
    let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
    let budget_ms = scene.processes.budget_ms.engine;
    let exe = std::env::current_exe().context("cannot find the lungdyn executable")?;
    let mut records = Vec::new();
    let mut frozen = Vec::new();
    let mut rounds = Vec::new();
    let mut nan_frames = 0;
    let mut renderer_first_frame_ms = Vec::new();
    for round in 0..args.rounds {
        let (r, inj) = run_round(args, &scene_path, round, &exe, budget_ms, period_ns)?;
        eprintln!(
            "lungdyn faults: round {round}: {} — {}",
            inj.records
                .iter()
                .map(|f| format!(
                    "{} at tick {}: {}",
                    f.fault,
                    f.at_tick,
                    f.recover_ms
                        .map_or("NOT recovered".to_string(), |m| format!(
                            "recovered in {m:.0} ms"
                        ))
                ))
                .collect::<Vec<_>>()
                .join("; "),
            if r.ok {
                "ok".to_string()
            } else {
                format!("FAILED: {}", r.problems.join("; "))
            }
        );
        records.extend(inj.records);
        frozen.extend(inj.frozen);
        nan_frames += inj.nan_frames;
        renderer_first_frame_ms.extend(inj.renderer_first_frame_ms);
        rounds.push(r);
    }
    Ok(summarise(
        args,
        records,
        frozen,
        rounds,
        nan_frames,
        renderer_first_frame_ms,
        (now_ns() - started) as f64 / 1e9,
    ))
}

fn histogram(ms: impl Iterator<Item = f64>) -> hdrhistogram::Histogram<u64> {
    let mut h =
        hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000, 3).expect("valid bounds");
    for m in ms {
        h.saturating_record((m * 1000.0).max(1.0) as u64);
    }
    h
}

fn summarise(
    args: &FaultsArgs,
    records: Vec<FaultRecord>,
    frozen: Vec<Frozen>,
    rounds: Vec<RoundReport>,
    nan_frames: u64,
    renderer_first_frame_ms: Vec<f64>,
    seconds: f64,
) -> FaultsReport {
    // Storms end the run and dead nodes are cleaned by the launcher: neither is a pipeline recovery.
    let timed =
        |r: &&FaultRecord| !r.fault.starts_with("restart storm") && !r.fault.starts_with("dead");
    let h = histogram(records.iter().filter(timed).filter_map(|r| r.recover_ms));
    let at = |q: f64| {
        if h.is_empty() {
            0.0
        } else {
            h.value_at_quantile(q) as f64 / 1000.0
        }
    };
    let mut names: Vec<String> = records.iter().map(|r| r.fault.clone()).collect();
    names.sort();
    names.dedup();
    let by_kind = names
        .into_iter()
        .map(|name| {
            let of: Vec<&FaultRecord> = records.iter().filter(|r| r.fault == name).collect();
            let hk = histogram(of.iter().filter_map(|r| r.recover_ms));
            KindRow {
                fault: name,
                count: of.len(),
                p50_ms: if hk.is_empty() {
                    0.0
                } else {
                    hk.value_at_quantile(0.5) as f64 / 1000.0
                },
                max_ms: hk.max() as f64 / 1000.0,
            }
        })
        .collect();
    FaultsReport {
        seed: args.seed,
        rounds: rounds.len() as u32,
        rounds_ok: rounds.iter().filter(|r| r.ok).count() as u32,
        faults: records.len(),
        frozen_over_2_frames: frozen.iter().filter(|f| f.during.is_some()).count(),
        frozen_outside_faults: frozen.iter().filter(|f| f.during.is_none()).count(),
        leaked_files: rounds.iter().map(|r| r.leaked_files).sum(),
        removed_by_launcher: rounds.iter().map(|r| r.removed_by_launcher).sum(),
        phase_errors: rounds.iter().map(|r| r.phase_errors).sum(),
        nan_frames,
        unrecovered: records.iter().filter(|r| r.recover_ms.is_none()).count(),
        unexpected_restarts: records.iter().map(|r| r.unexpected_restarts).sum(),
        recover_p50_ms: at(0.5),
        recover_p99_ms: at(0.99),
        recover_max_ms: if h.is_empty() {
            0.0
        } else {
            h.max() as f64 / 1000.0
        },
        by_kind,
        renderer_first_frame_ms,
        log: records,
        frozen,
        round_log: rounds,
        seconds,
    }
}

/// The human-readable summary.
pub fn table(r: &FaultsReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "lungdyn faults: seed {}, {} rounds ({} ok), {} faults in {:.0} s",
        r.seed, r.rounds, r.rounds_ok, r.faults, r.seconds
    );
    let _ = writeln!(
        s,
        "frozen pictures over 2 frame periods during faults: {} (and {} with no fault under way); leaked files: {} \
         ({} more removed by the launcher's final sweep); breathing-phase errors: {}; frames with a \
         NaN: {}; unrecovered: {}; unexpected restarts: {}",
        r.frozen_over_2_frames,
        r.frozen_outside_faults,
        r.leaked_files,
        r.removed_by_launcher,
        r.phase_errors,
        r.nan_frames,
        r.unrecovered,
        r.unexpected_restarts
    );
    let _ = writeln!(
        s,
        "time to recover (to a fresh frame after the fault ended): p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        r.recover_p50_ms, r.recover_p99_ms, r.recover_max_ms
    );
    let _ = writeln!(
        s,
        "{:<40} {:>6} {:>10} {:>10}",
        "fault", "count", "p50 ms", "max ms"
    );
    for k in &r.by_kind {
        let _ = writeln!(
            s,
            "{:<40} {:>6} {:>10.1} {:>10.1}",
            k.fault, k.count, k.p50_ms, k.max_ms
        );
    }
    if !r.renderer_first_frame_ms.is_empty() {
        let _ = writeln!(
            s,
            "killed renderer to its first frame after the restart, ms: {}",
            r.renderer_first_frame_ms
                .iter()
                .map(|m| format!("{m:.0}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    for f in &r.frozen {
        let _ = writeln!(
            s,
            "  frozen {:.1} ms in round {} at {:.2} s ({})",
            f.gap_ms,
            f.round,
            f.at_s,
            f.during.as_deref().unwrap_or("no fault under way")
        );
    }
    for round in r.round_log.iter().filter(|x| !x.ok) {
        let _ = writeln!(
            s,
            "  round {} FAILED: {}",
            round.round,
            round.problems.join("; ")
        );
    }
    s
}

/// A garbage tracker frame: the right layout (a wrong one is a mixed build, refused by design),
/// everything else corrupted; or (`nan`) NaN poses flagged valid.
pub fn garbage_frame(rng: &mut XorShiftRng, nan: bool, number: u64) -> TrackerFrame {
    let mut f = TrackerFrame {
        layout_version: ipc_types::LAYOUT_VERSION,
        tool_count: rng.random_range(0..u32::MAX),
        frame_number: rng.random_range(0..u64::MAX),
        ..Default::default()
    };
    f.stamps.capture_ns = now_ns();
    f.stamps.bridge_publish_ns = f.stamps.capture_ns;
    for t in f.tools.iter_mut() {
        t.tool_id = rng.random_range(0..u32::MAX);
        if nan {
            t.status = ipc_types::tool_status::VALID;
            t.pose.quat = [f32::NAN, 0.0, 0.0, f32::NAN];
            t.pose.translation_mm = [f32::NAN, f32::INFINITY, -f32::INFINITY];
            t.rms_error_mm = f32::NAN;
        } else {
            t.status = rng.random_range(0..u32::MAX) | ipc_types::tool_status::VALID;
            let mut wild = || {
                // Tiny, huge, negative, denormal: finite garbage of every size.
                f32::from_bits(rng.random_range(0..0x7f00_0000u32))
                    * if rng.random_range(0..2) == 0 {
                        -1.0
                    } else {
                        1.0
                    }
            };
            t.pose.quat = [wild(), wild(), wild(), wild()];
            t.pose.translation_mm = [wild(), wild(), wild()];
            t.rms_error_mm = wild();
        }
    }
    if nan {
        f.tool_count = ipc_types::MAX_TOOLS as u32;
        f.frame_number = number;
    }
    f
}

/// The stray process: publish garbage into an instance's tracker stream, or hold a node until
/// killed.
pub fn stray(args: &StrayArgs) -> anyhow::Result<()> {
    let nan = match args.mode.as_str() {
        "corrupt" => false,
        "nan" => true,
        "hold" => false,
        m => bail!("--mode {m:?}: one of corrupt, nan, hold"),
    };
    // A stop signal ends a held node cleanly (its files removed).
    transport::stop::install()?;
    let instance = Instance::new(&args.instance)?;
    let node = iox::node(&instance, "stray")?;
    let mut outlet = instance.tracker_outlet(&node)?;
    if args.mode == "hold" {
        println!("ready");
        use std::io::Write;
        std::io::stdout().flush()?;
        // Killed by `lungdyn faults`; ends by itself after a minute should that never come.
        let until = now_ns() + 60_000_000_000;
        while now_ns() < until && transport::stop::idle(Duration::from_millis(50)) {}
        return Ok(());
    }
    let mut rng = XorShiftRng::seed_from_u64(args.seed);
    for k in 0..args.frames {
        outlet.publish(&garbage_frame(&mut rng, nan, u64::MAX - k as u64))?;
        std::thread::sleep(Duration::from_nanos(16_666_667));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plan_is_a_function_of_seed_and_round_and_ten_rounds_cover_every_kind() {
        assert_eq!(plan(7, 3, 2.0), plan(7, 3, 2.0));
        assert_ne!(plan(7, 3, 2.0), plan(8, 3, 2.0));
        let mut seen: Vec<Fault> = (0..10)
            .filter(|&r| !is_storm(r))
            .flat_map(|r| plan(7, r, 2.0).into_iter().map(|p| p.fault))
            .collect();
        seen.sort_by_key(|f| f.to_string());
        seen.dedup();
        assert_eq!(seen.len(), kinds().len(), "{seen:?}");
        let storm = plan(7, 9, 2.0);
        assert_eq!(storm.len(), 3);
        assert!(storm.iter().all(|p| matches!(p.fault, Fault::Storm(_))));
        for p in plan(7, 0, 2.0).iter().chain(&plan(7, 1, 2.0)) {
            match p.fault {
                Fault::Pause(_) => assert!((150..700).contains(&p.hold_ms)),
                // Longer than the engine's 2 ms budget.
                Fault::EngineStall => assert!(p.hold_ms >= 20),
                _ => assert_eq!(p.hold_ms, 0),
            }
        }
    }

    #[test]
    fn garbage_frames_carry_no_usable_nan_pose() {
        let mut rng = XorShiftRng::seed_from_u64(1);
        for _ in 0..100 {
            let f = garbage_frame(&mut rng, true, 5);
            assert_eq!(f.layout_version, ipc_types::LAYOUT_VERSION);
            for slot in 0..ipc_types::MAX_TOOLS {
                assert!(f.valid_tool(slot).is_none(), "a NaN pose is never valid");
            }
            let g = garbage_frame(&mut rng, false, 5);
            assert!(g.tools.iter().all(|t| t.pose.is_finite()));
        }
    }

    #[test]
    fn nan_in_any_drawn_field_is_found() {
        let mut f = EngineFrame::default();
        assert!(!has_nan(&f));
        f.lungs[1].coeffs[3] = f32::NAN;
        assert!(has_nan(&f));
        let mut g = EngineFrame::default();
        g.patient_pose.translation_mm[0] = f32::INFINITY;
        assert!(has_nan(&g));
    }
}
