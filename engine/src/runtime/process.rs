//! The engine process: wake on tracker frames, tick, publish.
//!
//! [`run_loop`] is the whole loop over the port traits and a clock: the [`Pacer`] decides when a
//! tick runs (a fresh tracker sample drives it at once; a late or silent tracker falls back to an
//! absolute deadline), [`EngineCore::step`] computes the frame, the loop stamps its two hops and
//! publishes. Per tick: one wait, one drain, the step (a table read and a few Newton steps per lung),
//! one zero-copy publish — no allocation, no lock, no logging beyond one line when the tracker
//! connects. [`run`] wires the loop to iceoryx2 and the host's clock.

use control_state::ControlStateFrame;
use ipc_types::{ControlPacket, ControlReply, EngineFrame, Message, TrackerFrame, LUNG_LEFT};
use lung_model::scene::{Scene, SceneError};
use thiserror::Error;
use transport::clock::{now_ns, Clock, Monotonic};
use transport::pacer::{PacerConfig, PacerStats, Wake};
use transport::process::{pin_to_core, ArgError, PinError, ProcessArgs};
use transport::{iox, Instance, Pacer, PortError, Publish, Receive};

use lung_model::disease::tension::Outcome;

use super::{CoreError, EngineCore};
use lung_model::scene::SceneExt;

/// Command-line options of the `engine` process.
#[derive(Debug, Clone, clap::Args)]
pub struct EngineArgs {
    /// Instance, scene, pinning and run time.
    #[command(flatten)]
    pub process: ProcessArgs,
    /// Resume at this tick instead of 0: a restarted engine continues the stream where it broke off
    /// (its first frame is the tick after the last one published), showing the breath an
    /// uninterrupted run shows at that tick ([`EngineCore::resume_at`]). The launcher's supervisor
    /// sets it; at most a week of ticks.
    #[arg(long, value_name = "TICK", default_value_t = 0)]
    pub start_tick: u64,
}

/// Why the engine process stopped with an error.
#[derive(Debug, Error)]
pub enum EngineError {
    /// A bad command-line option.
    #[error(transparent)]
    Args(#[from] ArgError),
    /// The scene could not be loaded.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The engine could not be built for the scene.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// Pinning failed.
    #[error(transparent)]
    Pin(#[from] PinError),
    /// A stream failed.
    #[error(transparent)]
    Port(#[from] PortError),
    /// The scene's wake strategy cannot run where the engine runs.
    #[error(transparent)]
    Wake(#[from] transport::wake::WakeError),
    /// `--start-tick` beyond a week of ticks.
    #[error("--start-tick {tick}: at most {max} (one week of ticks at the scene's rate)")]
    StartTick {
        /// As given.
        tick: u64,
        /// The limit.
        max: u64,
    },
    /// The control state cannot be described for remote sites.
    #[error("remote control state: {0}")]
    State(#[from] super::remote::RemoteStateError),
    /// The control state does not encode (a bug: the state's bounds fit its frame).
    #[error("remote control state: {0}")]
    StateEncode(control_state::EncodeError),
}

/// What a run of the loop did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoopStats {
    /// Ticks run (frames published).
    pub ticks: u64,
    /// A trainee's actions: received (queued), ignored (unusable), refused (over capacity) and
    /// repeated packets taken once.
    pub actions: ActionCounts,
    /// The pacer's counters (sample vs deadline ticks, held, coalesced, skipped deadlines).
    pub pacer: PacerStats,
    /// Disease cycles prepared after a publish, and the longest preparation (ns): the work the
    /// tick leaves to the slack of its period.
    pub prepared_cycles: u64,
    /// Longest preparation, ns.
    pub prepare_max_ns: u64,
    /// Ticks that had to wait for a disease cycle still being built.
    pub late_preparations: u64,
    /// Control-state packets published for remote sites.
    pub states_published: u64,
    /// Applied live actions announced to remote sites (with the tick they show from).
    pub events_announced: u64,
    /// Applied live actions that could not be announced (more waited than two breaths of
    /// queued actions): counted and reported, never dropped silently.
    pub events_unannounced: u64,
}

/// The thread that builds disease cycles ([`super::disease::Recipe::build`], ≈ 40 ms for two lungs on
/// the 2-core VM) so the loop never spends a tick on it.
struct Worker {
    tx: std::sync::mpsc::SyncSender<(super::disease::Recipe, u64)>,
    rx: std::sync::mpsc::Receiver<Result<(super::disease::CourseCycle, u64), CoreError>>,
    pending: bool,
}

impl Worker {
    fn start() -> Self {
        let (tx, work) = std::sync::mpsc::sync_channel::<(super::disease::Recipe, u64)>(1);
        let (done, rx) = std::sync::mpsc::sync_channel(1);
        std::thread::Builder::new()
            .name("engine-disease".into())
            .spawn(move || {
                while let Ok((recipe, asked_ns)) = work.recv() {
                    let built = recipe
                        .build()
                        .map(|c| (c, now_ns().saturating_sub(asked_ns)))
                        .map_err(CoreError::from);
                    if done.send(built).is_err() {
                        break;
                    }
                }
            })
            .expect("spawn the disease worker");
        Self {
            tx,
            rx,
            pending: false,
        }
    }

    fn request(&mut self, recipe: super::disease::Recipe, now: u64) {
        // One request at a time (the core asks again only after a delivery).
        if self.tx.send((recipe, now)).is_ok() {
            self.pending = true;
        }
    }

    fn try_take(&mut self) -> Result<Option<(super::disease::CourseCycle, u64)>, CoreError> {
        if !self.pending {
            return Ok(None);
        }
        match self.rx.try_recv() {
            Ok(r) => {
                self.pending = false;
                r.map(Some)
            }
            Err(_) => Ok(None),
        }
    }

    fn wait(&mut self) -> Result<(super::disease::CourseCycle, u64), CoreError> {
        self.pending = false;
        self.rx
            .recv()
            .map_err(|_| CoreError::Disease(super::disease::DiseaseRunError::WorkerGone))?
    }
}

/// What became of the control packets of a run: each one is counted once, and its sender got a
/// [`ControlReply`] saying so (never a silent drop).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ActionCounts {
    /// Queued for the next disease cycle (a [`ipc_types::REPLY_RECEIVED`] reply).
    pub received: u64,
    /// Applied to the disease state (a [`ipc_types::REPLY_APPLIED`] reply with the outcome).
    pub applied: u64,
    /// Not usable: no tension pneumothorax, an unknown kind or lung, another layout.
    pub ignored: u64,
    /// Over capacity: too many actions waiting for the next cycle.
    pub refused: u64,
    /// The same sequence number again (one action, not two; no second reply).
    pub repeated: u64,
}

/// The control ports of the loop: a trainee's actions in, the engine's answers out.
pub struct Controls<'a> {
    /// The control stream.
    pub inlet: &'a mut dyn Receive<ControlPacket>,
    /// The replies, one or two per action.
    pub replies: &'a mut dyn Publish<ControlReply>,
    /// Where the engine's control state goes (remote sites, seed §8.3); `None`: not published.
    pub state: Option<StateOut<'a>>,
}

/// The control-state stream of a source engine: one packet at tick 0 and at every lung's cycle
/// start (every change this engine makes takes effect there).
pub struct StateOut<'a> {
    /// The stream.
    pub outlet: &'a mut dyn Publish<ControlStateFrame>,
    /// This site's id.
    pub source: u64,
    /// This run's session (its start time, ns): a restarted source has another.
    pub epoch: u64,
    /// Ticks per second (the scene's).
    pub tick_hz: f64,
}

/// Events waiting to be announced at most (more are counted as unannounced and reported): two
/// breaths' worth of queued actions.
const WAITING_EVENTS: usize = 2 * super::disease::MAX_QUEUED_ACTIONS;

/// The state publisher's bookkeeping: what was last published ([`super::remote::StateSchedule`]),
/// the events not yet announced, the frame (4 KB, once).
struct StatePublisher {
    schedule: super::remote::StateSchedule,
    sequence: u64,
    frame: Box<ControlStateFrame>,
    /// Applied actions not yet announced, with the course cycle they show from.
    waiting: Vec<(control_state::RemoteEvent, u64)>,
    /// The events of the state being published (at most `MAX_EVENTS`).
    announce: Vec<control_state::RemoteEvent>,
    published: u64,
    announced: u64,
    unannounced: u64,
}

impl StatePublisher {
    fn new() -> Self {
        Self {
            schedule: super::remote::StateSchedule::default(),
            sequence: 0,
            frame: Box::default(),
            waiting: Vec::with_capacity(WAITING_EVENTS),
            announce: Vec::with_capacity(control_state::MAX_EVENTS),
            published: 0,
            announced: 0,
            unannounced: 0,
        }
    }

    /// Publish when a lung started a cycle, a disease cycle was prepared (announced before it
    /// starts, so every site puts it in at the same tick), the patient started a breath or the
    /// signal stopped driving (a source following a live signal), applied actions wait to be announced
    /// with the tick they show from (at most `MAX_EVENTS` a state: the rest go with the next
    /// tick's) or the pacer skipped deadlines before this tick (`resync`: the ticks from here on
    /// fall a whole number of periods later than the last state's schedule, which the sites
    /// follow, so they take the new one at once rather than a cycle later). A few compares
    /// otherwise.
    fn after_tick(
        &mut self,
        core: &EngineCore,
        tick: u64,
        at_ns: u64,
        resync: bool,
        out: &mut StateOut<'_>,
    ) -> Result<(), EngineError> {
        let changed = self.schedule.changed(core) || resync;
        let ready = |(_, course): &(control_state::RemoteEvent, u64)| {
            core.course_cycle_start(*course).is_some()
        };
        if !changed && !self.waiting.iter().any(ready) {
            return Ok(());
        }
        let mut k = 0;
        while k < self.waiting.len() && self.announce.len() < control_state::MAX_EVENTS {
            match core.course_cycle_start(self.waiting[k].1) {
                Some((apply_tick, apply_cycle)) => {
                    let (mut e, _) = self.waiting.remove(k);
                    e.apply_tick = apply_tick;
                    e.apply_cycle = apply_cycle;
                    self.announce.push(e);
                }
                None => k += 1,
            }
        }
        let stamp = super::remote::StateStamp {
            source: out.source,
            epoch: out.epoch,
            sequence: self.sequence,
            tick_hz: out.tick_hz,
            source_time_ns: at_ns,
        };
        let state = core.control_state(tick, stamp, &self.announce)?;
        self.frame
            .set(&control_state::Packet::State(state))
            .map_err(EngineError::StateEncode)?;
        out.outlet.publish(&self.frame)?;
        self.sequence += 1;
        self.published += 1;
        self.announced += self.announce.len() as u64;
        self.announce.clear();
        Ok(())
    }

    /// An applied action to announce, showing from disease course cycle `course`.
    fn event(&mut self, e: control_state::RemoteEvent, course: u64) {
        if self.waiting.len() == WAITING_EVENTS {
            self.unannounced += 1;
            return;
        }
        self.waiting.push((e, course));
    }
}

/// The disease worker of a run and what it prepared.
#[derive(Default)]
struct Preparation {
    worker: Option<Worker>,
    prepared_cycles: u64,
    prepare_max_ns: u64,
    /// Cycles the loop had to wait for (due before the worker delivered them).
    late: u64,
}

impl Preparation {
    /// A disease cycle that starts now must be in the core before the tick, whatever the worker's
    /// timing: wait for it (counted; the worker has a whole breath to build it).
    fn before_tick(&mut self, core: &mut EngineCore, tick: u64) -> Result<(), EngineError> {
        if core.due_undelivered(tick) {
            if let Some(w) = self.worker.as_mut() {
                let (cycle, took) = w.wait()?;
                core.deliver(cycle);
                self.prepared_cycles += 1;
                self.prepare_max_ns = self.prepare_max_ns.max(took);
                self.late += 1;
            }
        }
        Ok(())
    }

    /// The disease state's next cycle: its cheap step here, the PV tables on the worker (started
    /// the first time one is needed); a cycle the worker finished is delivered.
    fn after_tick(&mut self, core: &mut EngineCore, clock: &dyn Clock) -> Result<(), EngineError> {
        if let Some(recipe) = core.next_recipe()? {
            let worker = self.worker.get_or_insert_with(Worker::start);
            worker.request(recipe, clock.now_ns());
        }
        if let Some(w) = self.worker.as_mut() {
            if let Some((cycle, took)) = w.try_take()? {
                core.deliver(cycle);
                self.prepared_cycles += 1;
                self.prepare_max_ns = self.prepare_max_ns.max(took);
            }
        }
        Ok(())
    }
}

/// A run's live actions: the packets seen, the tags that map an applied event back to its
/// sender, and the counts.
struct Live {
    seen: Seen,
    tags: Tags,
    counts: ActionCounts,
}

impl Live {
    /// Every pending packet, in the order the stream gives them (none is left behind or dropped:
    /// the stream's buffer holds one from each sender even after a stall), each answered.
    fn drain(
        &mut self,
        c: &mut Controls<'_>,
        core: &mut EngineCore,
        tick: u64,
        announce: Option<&str>,
    ) -> Result<(), EngineError> {
        let mut failed = None;
        c.inlet.drain(&mut |p: &ControlPacket| {
            if failed.is_some() {
                return;
            }
            if !self.seen.first(p.origin, p.sequence) {
                self.counts.repeated += 1;
                return;
            }
            let tag = self.tags.issue(p.origin, p.sequence);
            let reply = live_action(core, tick, p, tag, announce);
            match reply.status {
                ipc_types::REPLY_RECEIVED => self.counts.received += 1,
                ipc_types::REPLY_REFUSED => self.counts.refused += 1,
                _ => self.counts.ignored += 1,
            }
            if let Err(e) = c.replies.publish(&reply) {
                failed = Some(e);
            }
        })?;
        match failed {
            Some(e) => Err(e.into()),
            None => Ok(()),
        }
    }

    /// The tension pneumothorax's new events: announced on stderr; a live action's (tag: the
    /// engine's, for its sender's origin and sequence) answered and announced to remote sites; a
    /// timed one not.
    fn report_applied(
        &mut self,
        core: &mut EngineCore,
        mut control: Option<&mut Controls<'_>>,
        states: &mut StatePublisher,
        announce: Option<&str>,
    ) -> Result<(), EngineError> {
        let Some(super::disease::DiseaseRun::Tension(run)) = core.disease_mut() else {
            return Ok(());
        };
        let affected = run.affected();
        for (e, tag) in run.take_new_events() {
            let (word, detail) = e.outcome.words(e.kind);
            if let Some(name) = announce {
                eprintln!(
                    "engine[{name}]: {} on the {} lung (arrived at tick {}, shows from disease \
                     cycle {}): {word} — {detail}{}",
                    e.kind.name(),
                    e.side.name(),
                    e.tick,
                    e.cycle,
                    if e.side != affected && e.outcome != Outcome::WrongSide {
                        " (the pneumothorax is on the other side)"
                    } else {
                        ""
                    }
                );
            }
            let sender = self.tags.get(tag);
            let (Some(c), Some((origin, sequence))) = (control.as_deref_mut(), sender) else {
                continue;
            };
            let mut reply = ControlReply {
                status: ipc_types::REPLY_APPLIED,
                sequence,
                tick: e.tick,
                cycle: e.cycle,
                kind: e.kind.code(),
                lung: e.side.index() as u32,
                outcome: match e.outcome {
                    Outcome::Applied => ipc_types::OUTCOME_APPLIED,
                    Outcome::WrongSide => ipc_types::OUTCOME_WRONG_SIDE,
                    Outcome::AlreadyApplied => ipc_types::OUTCOME_ALREADY_APPLIED,
                    Outcome::NoEffect(_) => ipc_types::OUTCOME_NO_EFFECT,
                },
                ..Default::default()
            };
            reply.set_text(&[detail]);
            c.replies.publish(&reply)?;
            self.counts.applied += 1;
            if let Some(out) = c.state.as_ref() {
                let event = control_state::RemoteEvent {
                    origin: if origin == ipc_types::ORIGIN_LOCAL {
                        out.source
                    } else {
                        origin
                    },
                    sequence,
                    kind: e.kind.code(),
                    lung: e.side.index() as u32,
                    // Stamped when announced: the tick and breathing cycle its course cycle
                    // starts.
                    apply_cycle: 0,
                    apply_tick: 0,
                    course_cycle: e.cycle,
                    outcome: reply.outcome,
                };
                states.event(event, e.cycle);
            }
        }
        Ok(())
    }
}

/// Sequence numbers seen lately, per origin (a repeated packet is one action): a fixed ring, no
/// allocation.
struct Seen {
    ring: [(u64, u64); 128],
    next: usize,
}

impl Seen {
    /// True the first time `(origin, sequence)` is offered (within the last 128).
    fn first(&mut self, origin: u64, sequence: u64) -> bool {
        if self.ring.contains(&(origin, sequence)) {
            return false;
        }
        self.ring[self.next] = (origin, sequence);
        self.next = (self.next + 1) % self.ring.len();
        true
    }
}

/// The engine's own tag for each live action taken (the disease course hands it back with the
/// applied event), mapped to the sender's origin and sequence: a fixed ring, no allocation. Two
/// breaths of queued actions fit, so a tag is still there when its action is applied.
struct Tags {
    ring: [(u64, u64, u64); WAITING_EVENTS],
    last: u64,
}

impl Tags {
    fn new() -> Self {
        Self {
            ring: [(0, 0, 0); WAITING_EVENTS],
            last: 0,
        }
    }

    /// A new tag (never 0: 0 marks the scene's timed events) for `(origin, sequence)`.
    fn issue(&mut self, origin: u64, sequence: u64) -> u64 {
        self.last += 1;
        self.ring[self.last as usize % WAITING_EVENTS] = (self.last, origin, sequence);
        self.last
    }

    /// The origin and sequence of `tag`.
    fn get(&self, tag: u64) -> Option<(u64, u64)> {
        let (t, origin, sequence) = self.ring[tag as usize % WAITING_EVENTS];
        (t == tag && tag != 0).then_some((origin, sequence))
    }
}

/// Run the engine loop until `stop()` says so: pace on `rx`, step `core`, publish on `tx`.
/// `announce` names the instance in the one line printed when the first tracker frame arrives and
/// in the one line per applied intervention (`None`: silent, for tests). After each publish (the
/// tick's slack): a trainee's actions from `control` (each answered on its reply port: received,
/// ignored or refused now, applied with its outcome when the next cycle takes it), then the disease
/// state's next cycle.
#[allow(clippy::too_many_arguments)]
pub fn run_loop(
    core: &mut EngineCore,
    rx: &mut dyn Receive<TrackerFrame>,
    tx: &mut dyn Publish<EngineFrame>,
    control: Option<Controls<'_>>,
    clock: &dyn Clock,
    pacer: PacerConfig,
    stop: &mut dyn FnMut() -> bool,
    announce: Option<&str>,
    first_tick: u64,
) -> Result<LoopStats, EngineError> {
    let mut control = control;
    let mut live = Live {
        seen: Seen {
            ring: [(0, 0); 128],
            next: 0,
        },
        tags: Tags::new(),
        counts: ActionCounts::default(),
    };
    let mut prep = Preparation::default();
    let mut pacer = Pacer::new(pacer, clock.now_ns());
    let mut frame = EngineFrame::default();
    let mut steps: u64 = 0;
    let mut announced = false;
    let mut states = StatePublisher::new();
    while !stop() {
        let Some(t) = pacer.poll(clock, rx)? else {
            continue;
        };
        // The pacer numbers the ticks (by the clock in the engine process: the breathing clock
        // keeps time whatever the tracker's rate; a number may repeat, never go back).
        let tick = first_tick + t.number;
        let input = match t.wake {
            Wake::Sample(s) => {
                s.check_layout().map_err(PortError::from)?;
                if !announced {
                    announced = true;
                    if let Some(name) = announce {
                        eprintln!(
                            "engine[{name}]: tracker connected (frame {})",
                            s.frame_number
                        );
                    }
                }
                Some(s)
            }
            Wake::Deadline => None,
        };
        prep.before_tick(core, tick)?;
        {
            let _tick = tracing::info_span!(target: transport::trace::TARGET, "tick").entered();
            core.step(tick, input.as_ref(), &mut frame);
        }
        frame.stamps.engine_receive_ns = t.at_ns;
        frame.stamps.engine_publish_ns = clock.now_ns();
        {
            let _publish =
                tracing::info_span!(target: transport::trace::TARGET, "publish").entered();
            tx.publish(&frame)?;
        }
        if let Some(out) = control.as_mut().and_then(|c| c.state.as_mut()) {
            // A site schedules by the tick's due time, not when this host happened to wake.
            states.after_tick(core, tick, t.due_ns, t.skipped > 0, out)?;
        }
        if let Some(c) = control.as_mut() {
            live.drain(c, core, tick, announce)?;
        }
        prep.after_tick(core, clock)?;
        live.report_applied(core, control.as_mut(), &mut states, announce)?;
        steps += 1;
    }
    Ok(LoopStats {
        actions: live.counts,
        late_preparations: prep.late,
        prepared_cycles: prep.prepared_cycles,
        prepare_max_ns: prep.prepare_max_ns,
        ticks: steps,
        pacer: pacer.stats(),
        states_published: states.published,
        events_announced: states.announced,
        events_unannounced: states.unannounced + states.waiting.len() as u64,
    })
}

/// Hand one control packet to the engine core and say what became of it (the reply to send): a
/// packet it cannot use is reported, never applied. No allocation.
fn live_action(
    core: &mut EngineCore,
    tick: u64,
    p: &ControlPacket,
    tag: u64,
    announce: Option<&str>,
) -> ControlReply {
    use lung_model::mesh::Side;
    let mut reply = ControlReply {
        status: ipc_types::REPLY_IGNORED,
        sequence: p.sequence,
        tick,
        kind: p.kind,
        lung: p.lung,
        ..Default::default()
    };
    let kind = ipc_types::Intervention::from_code(p.kind);
    let side = match p.lung {
        l if l == ipc_types::LUNG_RIGHT as u32 => Some(Side::Right),
        l if l == LUNG_LEFT as u32 => Some(Side::Left),
        ipc_types::LUNG_AFFECTED => core.tension_side(),
        _ => None,
    };
    let why: &str = match (kind, side, p.check_layout()) {
        (_, _, Err(_)) => "ignored: the sender speaks another protocol layout (rebuild it)",
        (None, ..) => "ignored: not an intervention this engine knows",
        (_, _, _) if core.tension_side().is_none() => {
            "ignored: the scene has no tension pneumothorax to act on"
        }
        (_, None, _) => "ignored: not a lung (left or right)",
        (Some(kind), Some(side), Ok(())) => {
            reply.lung = side.index() as u32;
            match core.intervene_tagged(tick, kind, side, tag) {
                super::LiveAction::Queued => {
                    reply.status = ipc_types::REPLY_RECEIVED;
                    if let Some(name) = announce {
                        transport::process::say(&format!(
                            "engine[{name}]: {} on the {} lung received at tick {tick}; it shows \
                             from the cycle after the next (within two breaths)",
                            kind.name(),
                            side.name()
                        ));
                    }
                    reply.set_text(&["received: it shows from the cycle after the next"]);
                    return reply;
                }
                super::LiveAction::QueueFull => {
                    reply.status = ipc_types::REPLY_REFUSED;
                    "refused: too many actions wait for the next breath; send it again after it"
                }
                super::LiveAction::NoTension => {
                    "ignored: the scene has no tension pneumothorax to act on"
                }
            }
        }
    };
    reply.set_text(&[why]);
    if let Some(name) = announce {
        eprintln!(
            "engine[{name}]: control packet {} (kind {}, lung {}) {why}",
            p.sequence, p.kind, p.lung
        );
    }
    reply
}

/// Run the engine process until terminated (or `--seconds` elapse).
pub fn run(args: &EngineArgs) -> Result<(), EngineError> {
    transport::stop::install()?;
    let start_tick = args.start_tick;
    let args = &args.process;
    let run_ns = args.run_ns()?;
    let instance = Instance::new(&args.instance)?;
    let _lock = instance.lock("engine")?;
    pin_to_core(args.cpu, "engine")?;
    transport::trace::init("engine");
    let scene = Scene::load_or_default(args.scene.as_deref())?;
    let max = (transport::process::MAX_SECONDS * scene.engine.tick_hz) as u64;
    if start_tick > max {
        return Err(EngineError::StartTick {
            tick: start_tick,
            max,
        });
    }
    if args.realtime || scene.processes.realtime {
        transport::realtime::apply("engine");
    }
    let mut core = EngineCore::new(&scene)?;
    core.resume_at(start_tick)?;
    let node = iox::node(&instance, "engine")?;
    let mut tracker = instance.tracker_inlet(&node)?;
    tracker.set_wake(transport::wake::announce(
        "engine",
        instance.name(),
        "tracker frames",
        scene.processes.wake.engine,
        scene.processes.spin_us,
        args.cpu,
        scene.processes.reserved_core(lung_model::scene::ENGINE),
    )?);
    let mut outlet = instance.engine_outlet(&node)?;
    let mut control = instance.control_inlet(&node)?;
    let mut replies = instance.control_reply_outlet(&node)?;
    let mut state_outlet = instance.control_state_outlet(&node)?;
    let epoch = now_ns();
    let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
    let stop_at = run_ns.map(|d| now_ns().saturating_add(d));
    let mut watchdog = transport::notify::Watchdog::from_env();
    transport::notify::ready(&format!("engine[{}]: ticking", instance.name()));
    if start_tick > 0 {
        eprintln!(
            "engine[{}]: resuming at tick {start_tick} (breath cycle {}, phase {:.3})",
            instance.name(),
            start_tick / core.cycle_ticks().max(1) as u64,
            (start_tick % core.cycle_ticks().max(1) as u64) as f64
                / core.cycle_ticks().max(1) as f64
        );
    }
    eprintln!(
        "engine[{}]: {} lung(s), {} ticks/breath at {} Hz; waiting for tracker frames on {:?} \
         (ticking on the deadline meanwhile)",
        instance.name(),
        core.lung_count(),
        core.cycle_ticks(),
        scene.engine.tick_hz,
        instance.tracker()
    );
    announce_signal(&core, &scene, instance.name());
    let stats = run_loop(
        &mut core,
        &mut tracker,
        &mut outlet,
        Some(Controls {
            inlet: &mut control,
            replies: &mut replies,
            state: Some(StateOut {
                outlet: &mut state_outlet,
                source: ipc_types::control_sequence(std::process::id(), epoch),
                epoch,
                tick_hz: scene.engine.tick_hz,
            }),
        }),
        &Monotonic,
        PacerConfig::clock_numbered(period_ns),
        &mut || {
            // The stop check runs every pass of the loop: the watchdog's ping lives here, so a hung
            // tick stops it (at most one datagram per WatchdogSec/2).
            let now = now_ns();
            watchdog.ping(now);
            transport::stop::requested() || stop_at.is_some_and(|t| now >= t)
        },
        Some(instance.name()),
        start_tick,
    )?;
    transport::notify::stopping();
    transport::trace::flush();
    transport::process::say(&format!(
        "engine[{}]: stopped after {} ticks ({} on a tracker sample, {} on the deadline, {} deadlines \
         skipped; breathing clock: {} tick(s) repeated its number, the input faster than {} Hz, {} \
         number(s) passed over)",
        instance.name(),
        stats.ticks,
        stats.pacer.sample_ticks,
        stats.pacer.deadline_ticks,
        stats.pacer.skipped_deadlines,
        stats.pacer.repeated_numbers,
        scene.engine.tick_hz,
        stats.pacer.skipped_numbers
    ));
    let a = stats.actions;
    if a != ActionCounts::default() {
        transport::process::say(&format!(
            "engine[{}]: trainee actions: {} received, {} applied, {} ignored, {} refused (over \
             capacity), {} repeated packets taken once",
            instance.name(),
            a.received,
            a.applied,
            a.ignored,
            a.refused,
            a.repeated
        ));
    }
    if stats.events_announced > 0 || stats.events_unannounced > 0 {
        transport::process::say(&format!(
            "engine[{}]: {} applied action(s) announced to remote sites with the tick they show \
             from{}",
            instance.name(),
            stats.events_announced,
            if stats.events_unannounced > 0 {
                format!(
                    "; {} could not be announced (more than {WAITING_EVENTS} waited at once)",
                    stats.events_unannounced
                )
            } else {
                String::new()
            }
        ));
    }
    report_signal(&core, instance.name());
    if stats.prepared_cycles > 0 {
        transport::process::say(&format!(
            "engine[{}]: {} disease cycles built on the worker thread, the longest in {:.2} ms; {} \
             tick(s) waited for one",
            instance.name(),
            stats.prepared_cycles,
            stats.prepare_max_ns as f64 / 1e6,
            stats.late_preparations
        ));
    }
    Ok(())
}

/// Say at start-up that the scene breathes with the patient's signal.
fn announce_signal(core: &EngineCore, scene: &Scene, name: &str) {
    if core.signal().is_some() {
        eprintln!(
            "engine[{name}]: breathing with the patient's signal ({}), predicted {} ms ahead; the \
             model breathes while it calibrates or is lost",
            scene.breathing.signal, scene.breathing.latency_ms
        );
    }
}

/// The breathing signal's counts at exit, when the scene follows one.
fn report_signal(core: &EngineCore, name: &str) {
    if let Some(signal) = core.signal() {
        let f = signal.follower();
        let (c, n) = (f.counts(), f.samples());
        transport::process::say(&format!(
            "engine[{}]: breathing signal: {} samples used ({} invalid, {} not newer, {} losses), {} \
             breaths ({} sighs, {} coughs); ticks following {}, calibrating {}, lost {}; last state: \
             {}{}",
            name,
            n.used,
            n.invalid,
            n.not_newer,
            n.restarts,
            c.breaths,
            c.sighs,
            c.coughs,
            signal.ticks().following,
            signal.ticks().calibrating,
            signal.ticks().lost,
            signal
                .followed()
                .map_or("no sample", |x| x.state.describe()),
            if signal.source_ended() {
                " (the source ended)"
            } else {
                ""
            }
        ));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::{engine_state, LAYOUT_VERSION};
    use transport::memory::{Recorder, Scripted};
    use transport::FakeClock;

    const P: u64 = 16_666_667;

    fn core() -> EngineCore {
        crate::runtime::generated_core(&Scene::default())
    }

    fn tracker(n: u64) -> TrackerFrame {
        TrackerFrame {
            layout_version: LAYOUT_VERSION,
            frame_number: n,
            ..Default::default()
        }
    }

    /// Run the loop on scripted tracker arrivals until the fake clock reaches `until`.
    fn run(arrivals: Vec<(u64, TrackerFrame)>, until: u64) -> (Vec<(u64, EngineFrame)>, LoopStats) {
        run_paced(arrivals, until, PacerConfig::for_period(P))
    }

    fn run_paced(
        arrivals: Vec<(u64, TrackerFrame)>,
        until: u64,
        pacer: PacerConfig,
    ) -> (Vec<(u64, EngineFrame)>, LoopStats) {
        let clock = FakeClock::at(0);
        let mut rx = Scripted::new(&clock, arrivals, 4);
        let mut tx = Recorder::new(&clock);
        let out = tx.clone();
        let c = clock.clone();
        let stats = run_loop(
            &mut core(),
            &mut rx,
            &mut tx,
            None,
            &clock,
            pacer,
            &mut || c.now_ns() >= until,
            None,
            0,
        )
        .unwrap();
        (out.records(), stats)
    }

    /// The breathing clock keeps time whatever the tracker's rate. Found with a pyigtl sender
    /// that sends each tool in its own message: the bridge published 87 frames a second, the
    /// engine ticked on each and the model breathed 1.4x fast (3398 ticks in a 40 s demo). Numbered
    /// by the clock (the engine process's pacer), every frame's tick is within one of the clock's
    /// 60 Hz slot and a breath takes its own time; counted, the same input runs 1.45x ahead.
    #[test]
    fn the_breath_keeps_the_clocks_time_whatever_the_trackers_rate() {
        let seconds = 12;
        for hz in [40u64, 50, 87, 120] {
            let arrivals: Vec<(u64, TrackerFrame)> = (1..=hz * seconds)
                .map(|k| (k * 1_000_000_000 / hz, tracker(k)))
                .collect();
            let until = seconds * 1_000_000_000;
            let (frames, stats) =
                run_paced(arrivals.clone(), until, PacerConfig::clock_numbered(P));
            for (at, f) in &frames {
                assert!(
                    f.tick.abs_diff(at / P) <= 1,
                    "{hz} Hz: tick {} at {at} ns",
                    f.tick
                );
            }
            let used = frames.iter().filter(|(_, f)| f.tracker_frame > 0).count();
            assert!(
                used as u64 >= hz.min(120) * seconds * 9 / 10,
                "{hz} Hz: {used}"
            );
            let (_, counted) = run_paced(arrivals, until, PacerConfig::for_period(P));
            let last = frames.last().map_or(0, |(_, f)| f.tick);
            if hz > 60 {
                assert!(
                    counted.ticks > last * 13 / 10,
                    "{hz} Hz: {counted:?} vs {last}"
                );
                assert!(stats.pacer.repeated_numbers > 0, "{hz} Hz: {stats:?}");
            }
        }
    }

    /// Regression (engine loop): a tracker sample that arrives within half a period of the
    /// previous tick used to be taken from the subscriber and dropped, and the next tick was
    /// flagged DEADLINE_FALLBACK although the tracker was on time. Every sample must reach a frame.
    #[test]
    fn an_early_tracker_sample_reaches_a_frame_and_no_tick_is_flagged_late() {
        let arrivals = vec![
            (P, tracker(1)),
            (13 * P / 10, tracker(2)),
            (23 * P / 10, tracker(3)),
            (33 * P / 10, tracker(4)),
        ];
        let (frames, stats) = run(arrivals, 33 * P / 10);
        let used: Vec<u64> = frames.iter().map(|(_, f)| f.tracker_frame).collect();
        assert_eq!(used, vec![1, 2, 3, 4]);
        for (_, f) in &frames {
            assert_eq!(
                f.state & engine_state::DEADLINE_FALLBACK,
                0,
                "tick {}",
                f.tick
            );
            assert_ne!(f.state & engine_state::TRACKER_FRESH, 0);
        }
        assert_eq!(stats.pacer.deadline_ticks, 0);
        assert_eq!(stats.ticks, 4);
    }

    #[test]
    fn a_silent_tracker_still_breathes_on_the_deadline_with_every_frame_flagged() {
        let (frames, stats) = run(vec![], P + P / 4 + 59 * P);
        assert_eq!(stats.ticks, 60);
        for (k, (at, f)) in frames.iter().enumerate() {
            assert_eq!(f.tick, k as u64);
            assert_ne!(f.state & engine_state::DEADLINE_FALLBACK, 0);
            assert_ne!(f.state & engine_state::NO_TRACKER_YET, 0);
            assert_eq!(*at, P + P / 4 + k as u64 * P, "absolute deadlines");
            assert_eq!(f.stamps.engine_receive_ns, *at);
        }
        // The lungs breathe on the deadline ticks.
        let v: Vec<f32> = frames.iter().map(|(_, f)| f.lungs[0].volume_ml).collect();
        assert!(
            v.windows(2).all(|w| w[1] >= w[0]) && v[59] > v[0],
            "inhaling"
        );
    }

    #[test]
    fn a_sample_of_another_layout_stops_the_loop_with_a_clear_error() {
        let clock = FakeClock::at(0);
        let bad = TrackerFrame {
            layout_version: 1,
            ..Default::default()
        };
        let mut rx = Scripted::new(&clock, vec![(P, bad)], 4);
        let mut tx = Recorder::new(&clock);
        let e = run_loop(
            &mut core(),
            &mut rx,
            &mut tx,
            None,
            &clock,
            PacerConfig::for_period(P),
            &mut || false,
            None,
            0,
        )
        .unwrap_err();
        assert!(e.to_string().contains("TrackerFrame with layout v1"), "{e}");
    }

    /// The loop of a restarted engine numbers its frames from the start tick on, with the breath
    /// an uninterrupted core shows at those ticks.
    #[test]
    fn a_loop_started_at_a_tick_publishes_from_that_tick() {
        let clock = FakeClock::at(0);
        let mut rx = Scripted::new(&clock, vec![], 4);
        let mut tx = Recorder::new(&clock);
        let out = tx.clone();
        let c = clock.clone();
        let mut resumed = core();
        resumed.resume_at(500).unwrap();
        let stats = run_loop(
            &mut resumed,
            &mut rx,
            &mut tx,
            None,
            &clock,
            PacerConfig::for_period(P),
            &mut || c.now_ns() >= P + P / 4 + 9 * P,
            None,
            500,
        )
        .unwrap();
        assert_eq!(stats.ticks, 10);
        let mut reference = core();
        let mut f = EngineFrame::default();
        for (k, (_, got)) in out.records().iter().enumerate() {
            reference.step(500 + k as u64, None, &mut f);
            assert_eq!(got.tick, 500 + k as u64);
            assert_eq!(got.lungs, f.lungs, "tick {}", got.tick);
        }
    }
}
