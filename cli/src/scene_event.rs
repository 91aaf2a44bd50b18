//! `lungdyn scene event INSTANCE KIND --side SIDE`: a trainee's intervention sent to a running engine
//! (a tension pneumothorax, EQUATIONS.md §4.3). The packet goes over the instance's control stream;
//! the engine applies it when it prepares its next disease cycle (it shows within two breaths) and
//! prints one line with the tick it arrived at and what it did.

use anyhow::{bail, Context};
use ipc_types::{ControlPacket, LAYOUT_VERSION, LUNG_LEFT, LUNG_RIGHT};
use lung_model::disease::tension::Intervention;
use lung_model::mesh::Side;
use transport::{iox, Instance, Publish};

/// Options of `lungdyn scene event`.
#[derive(Debug, Clone, clap::Args)]
pub struct EventArgs {
    /// The running instance: the name `lungdyn demo` printed when it started (`demo-<its pid>`, or
    /// its `--instance NAME`); `lungdyn instances` lists the running ones.
    pub instance: String,
    /// The intervention: needle-decompression, occlusive-dressing or chest-tube.
    pub kind: Intervention,
    /// The side it is done on.
    #[arg(long, value_parser = parse_side)]
    pub side: Side,
}

fn parse_side(s: &str) -> Result<Side, String> {
    match s {
        "left" => Ok(Side::Left),
        "right" => Ok(Side::Right),
        _ => Err(format!("{s:?} is not a lung: left or right")),
    }
}

/// Send the intervention; refuses when no engine runs in the instance.
pub fn run(args: &EventArgs) -> anyhow::Result<()> {
    let instance = Instance::new(&args.instance)?;
    // The engine holds its role's lock while it runs (read, never taken here: taking it even for
    // an instant could refuse an engine that is starting).
    if instance.holder("engine").is_none() {
        let running: Vec<String> = Instance::running()
            .into_iter()
            .filter(|r| r.process("engine").is_some())
            .map(|r| r.name)
            .collect();
        let known = if running.is_empty() {
            "none is running".to_string()
        } else {
            format!("running: {}", running.join(", "))
        };
        bail!(
            "no engine is running in instance {:?} ({known}; `lungdyn instances` lists them): start \
             the scene first (`lungdyn demo --scene FILE --instance {}`)",
            args.instance,
            args.instance
        );
    }
    let node = iox::node(&instance, "control").context("cannot join the instance")?;
    let mut outlet = instance.control_outlet(&node)?;
    // The engine takes its lock first and subscribes once its lungs are loaded: a packet sent
    // before that would be lost, so wait for the subscription.
    let start = std::time::Instant::now();
    while outlet.subscribers() == 0 {
        if start.elapsed() > std::time::Duration::from_secs(60) {
            bail!(
                "the engine of instance {:?} is running but not listening for actions after 60 s \
                 (still loading its lungs?); try again",
                args.instance
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let packet = ControlPacket {
        layout_version: LAYOUT_VERSION,
        kind: args.kind.code(),
        lung: match args.side {
            Side::Right => LUNG_RIGHT,
            Side::Left => LUNG_LEFT,
        } as u32,
        _pad: 0,
        sequence: transport::now_ns(),
    };
    outlet.publish(&packet)?;
    // The engine drains the control stream after every tick (60 Hz): stay long enough for it to
    // take the packet before this publisher goes away.
    std::thread::sleep(std::time::Duration::from_millis(300));
    eprintln!(
        "lungdyn: sent {} on the {} lung to instance {:?}; the engine reports the tick it applied it \
         at",
        args.kind.name(),
        args.side.name(),
        args.instance
    );
    Ok(())
}
