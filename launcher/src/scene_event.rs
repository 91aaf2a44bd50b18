//! `lungdyn scene event INSTANCE KIND [--side SIDE]`: a trainee's intervention sent to a running
//! engine (a tension pneumothorax, EQUATIONS.md §4.3), and the engine's answer in words.
//!
//! The packet goes over the instance's control stream with a sequence number of its own
//! ([`ipc_types::control_sequence`]); the engine answers on the control-reply stream: at once
//! "received" (or "ignored: …" / "refused: …", final), then, when it prepares its next disease
//! cycle, the outcome and the cycle it shows from. This command keeps its publisher until the final
//! answer: a sample's publisher must outlive its delivery, so an engine that is busy (or stopped)
//! for a while still gets it when it resumes, and a sender is never told "sent" for an action that
//! was lost — it gets the outcome, or an error saying the engine did not answer.

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use ipc_types::{
    lung_words, ControlPacket, ControlReply, Intervention, Message, LAYOUT_VERSION, LUNG_AFFECTED,
};
use lung_model::mesh::Side;
use transport::{iox, Instance, Publish, Receive};

/// Options of `lungdyn scene event`.
#[derive(Debug, Clone, clap::Args)]
pub struct EventArgs {
    /// The running instance: the name `lungdyn demo` printed when it started (`demo-<its pid>`, or
    /// its `--instance NAME`); `lungdyn instances` lists the running ones.
    pub instance: String,
    /// The intervention: needle-decompression, occlusive-dressing or chest-tube.
    pub kind: Intervention,
    /// The side it is done on: left or right. Default: the side of the scene's pneumothorax (the
    /// engine knows it).
    #[arg(long)]
    pub side: Option<Side>,
    /// Seconds to wait for the engine's outcome (it comes when the engine prepares its next
    /// disease cycle: within a breath of receiving the action).
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS")]
    pub timeout_s: f64,
}

/// Running instances with an engine, for messages.
fn running_engines() -> String {
    let running: Vec<String> = Instance::running()
        .into_iter()
        .filter(|r| r.process("engine").is_some())
        .map(|r| r.name)
        .collect();
    if running.is_empty() {
        "none is running".to_string()
    } else {
        format!("running: {}", running.join(", "))
    }
}

/// The intervention's name in words ("needle decompression").
fn kind_words(kind: Intervention) -> String {
    kind.name().replace('-', " ")
}

/// The outcome as one line: "needle decompression, left: applied at tick 3612, shows from disease
/// cycle 19 (in ≤ 2 breaths) — air venting", or for an action that changed nothing "chest tube,
/// right: no effect (arrived at tick 3612, disease cycle 19) — the pneumothorax is on the other
/// side". The cycle is the disease course's (from the onset), not the breath count.
pub fn outcome_line(kind: Intervention, r: &ControlReply) -> String {
    let head = format!("{}, {}", kind_words(kind), lung_words(r.lung));
    let (tick, cycle, text) = (r.tick, r.cycle, r.text());
    match r.outcome {
        ipc_types::OUTCOME_APPLIED => format!(
            "{head}: applied at tick {tick}, shows from disease cycle {cycle} (in ≤ 2 breaths) \
             — {text}"
        ),
        o => {
            let word = match o {
                ipc_types::OUTCOME_ALREADY_APPLIED => "no change",
                ipc_types::OUTCOME_WRONG_SIDE | ipc_types::OUTCOME_NO_EFFECT => "no effect",
                _ => "an outcome this build does not know",
            };
            format!("{head}: {word} (arrived at tick {tick}, disease cycle {cycle}) — {text}")
        }
    }
}

/// Send the intervention and wait for the engine's outcome. Refuses when no engine runs in the
/// instance; fails (non-zero exit) when the engine ignores or refuses it, or does not answer within
/// `--timeout-s`.
pub fn run(args: &EventArgs) -> anyhow::Result<()> {
    if !(args.timeout_s.is_finite() && args.timeout_s > 0.0 && args.timeout_s <= 3600.0) {
        bail!(
            "--timeout-s {} must be a number of seconds within (0, 3600]",
            args.timeout_s
        );
    }
    let timeout = Duration::from_secs_f64(args.timeout_s);
    let instance = Instance::new(&args.instance)?;
    // The engine holds its role's lock while it runs (read, never taken here: taking it even for
    // an instant could refuse an engine that is starting).
    if instance.holder("engine").is_none() {
        bail!(
            "no engine is running in instance {:?} ({}; `lungdyn instances` lists them): start \
             the scene first (`lungdyn demo --scene FILE --instance {}`)",
            args.instance,
            running_engines(),
            args.instance
        );
    }
    let node = iox::node(&instance, "control").context("cannot join the instance")?;
    // Listen for the answer before sending, so it cannot pass unseen.
    let mut replies = instance
        .control_reply_inlet(&node)
        .context("cannot listen for the engine's answers")?;
    let mut outlet = instance
        .control_outlet(&node)
        .context("cannot open the control stream (too many senders at once?)")?;
    // The engine takes its lock first and subscribes once its lungs are loaded: a packet sent
    // before that would not be kept, so wait for the subscription.
    let start = Instant::now();
    while outlet.subscribers() == 0 {
        if start.elapsed() > Duration::from_secs(60) {
            bail!(
                "the engine of instance {:?} is running but not listening for actions after 60 s \
                 (still loading its lungs?); nothing was sent, try again",
                args.instance
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let sequence = ipc_types::control_sequence(std::process::id(), transport::now_ns());
    let packet = ControlPacket {
        layout_version: LAYOUT_VERSION,
        kind: args.kind.code(),
        lung: match args.side {
            Some(side) => side.index() as u32,
            None => LUNG_AFFECTED,
        },
        _pad: 0,
        sequence,
        origin: ipc_types::ORIGIN_LOCAL,
    };
    outlet.publish(&packet)?;
    let side = args.side.map_or("the affected", |s| s.name());
    let sent_at = Instant::now();
    let mut received: Option<ControlReply> = None;
    loop {
        let mut answer: Option<ControlReply> = None;
        replies.drain(&mut |r: &ControlReply| {
            if r.sequence == sequence && answer.is_none() {
                answer = Some(*r);
            }
        })?;
        if let Some(r) = answer {
            r.check_layout()?;
            match r.status {
                ipc_types::REPLY_RECEIVED => {
                    eprintln!(
                        "lungdyn: the engine of {:?} received {} on the {} lung at tick {}; \
                         waiting for the disease cycle that applies it",
                        args.instance,
                        args.kind.name(),
                        lung_words(r.lung),
                        r.tick
                    );
                    received = Some(r);
                    continue;
                }
                ipc_types::REPLY_APPLIED => {
                    println!("{}", outcome_line(args.kind, &r));
                    return Ok(());
                }
                ipc_types::REPLY_IGNORED | ipc_types::REPLY_REFUSED => bail!(
                    "{} on {side} side, instance {:?}: {}",
                    kind_words(args.kind),
                    args.instance,
                    r.text()
                ),
                other => bail!(
                    "the engine of {:?} answered with status {other}, which this build does not \
                     know (rebuild all processes from one version)",
                    args.instance
                ),
            }
        }
        if instance.holder("engine").is_none() {
            bail!(
                "the engine of instance {:?} stopped before answering {} on {side} side ({})",
                args.instance,
                args.kind.name(),
                match received {
                    Some(r) => format!("it had received it at tick {} but not applied it", r.tick),
                    None => "it had not received it".to_string(),
                }
            );
        }
        if sent_at.elapsed() > timeout {
            bail!(
                "no outcome from the engine of instance {:?} within {} s for {} on {side} side: {}",
                args.instance,
                args.timeout_s,
                args.kind.name(),
                match received {
                    Some(r) => format!(
                        "it received it at tick {} but has not prepared the disease cycle that \
                         applies it (is the pneumothorax's onset still to come?)",
                        r.tick
                    ),
                    None => "it never acknowledged it (stopped or stalled?), so it is not known \
                             to have arrived; the engine's log says whether it did (\"received at \
                             tick\") — check it before sending again, or wait longer with \
                             --timeout-s"
                        .to_string(),
                },
            );
        }
        // Not in a hurry: the engine answers once per tick at most.
        replies.wait_until(transport::now_ns() + 20_000_000)?;
    }
}
