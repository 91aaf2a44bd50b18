//! The engine process: wake on tracker frames, tick, publish.
//!
//! Per tick (after start-up): one event wait, one subscriber drain, [`super::EngineCore::step`]
//! (table read + a few Newton steps per lung), one zero-copy publish. No allocation, no lock, no
//! logging above debug level on this path.

use std::path::PathBuf;

use ipc_types::{
    now_ns, termination_requested, EngineFrame, Inlet, Outlet, Services, TrackerFrame,
};

use super::EngineCore;
use crate::scene::Scene;

/// Options every lungdyn process that reads a scene takes (flattened into its own options).
#[derive(Debug, Clone, clap::Args)]
pub struct ProcessArgs {
    /// Instance name shared by the three processes of one run (service and file names derive from it).
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Scene file (TOML); the built-in default scene when omitted.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Pin this process to CPU core N.
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted).
    #[arg(long)]
    pub seconds: Option<f64>,
}

impl ProcessArgs {
    /// Absolute monotonic time at which `--seconds` ends, counted from `start_ns`.
    pub fn stop_at(&self, start_ns: u64) -> Option<u64> {
        self.seconds.map(|s| start_ns + (s * 1e9) as u64)
    }
}

/// Command-line options of the `engine` process.
#[derive(Debug, Clone, clap::Args)]
pub struct EngineArgs {
    /// Instance, scene, pinning and run time.
    #[command(flatten)]
    pub process: ProcessArgs,
}

/// Run the engine process until terminated (or `--seconds` elapse).
pub fn run(args: &EngineArgs) -> anyhow::Result<()> {
    let args = &args.process;
    let scene = Scene::load_or_default(args.scene.as_deref())?;
    let services = Services::new(&args.instance)?;
    let mut core = EngineCore::new(&scene)?;
    ipc_types::pin_to_core(args.cpu, "engine")?;
    let node = services.node("engine")?;
    let tracker: Inlet<TrackerFrame> =
        Inlet::new(&node, &services.tracker(), &services.tracker_event())?;
    let outlet: Outlet<EngineFrame> =
        Outlet::new(&node, &services.engine(), &services.engine_event())?;

    let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
    // A tracker running at the tick rate arrives well inside this grace; only a late or silent
    // tracker lets the deadline fire.
    let grace_ns = period_ns / 4;
    let start = now_ns();
    let stop_at = args.stop_at(start);
    eprintln!(
        "engine[{}]: {} lung(s), {} ticks/breath at {} Hz; waiting for tracker frames on {:?} \
         (ticking on the deadline meanwhile)",
        services.instance,
        core.lungs().len(),
        core.breathing().cycle_ticks(),
        scene.engine.tick_hz,
        services.tracker()
    );
    let mut tick: u64 = 0;
    let mut deadline = start + period_ns + grace_ns;
    let mut last_tick_ns = 0u64;
    let mut frame = EngineFrame::default();
    let mut announced = false;
    loop {
        if termination_requested(&node) || stop_at.is_some_and(|t| now_ns() >= t) {
            break;
        }
        tracker.wait_until(deadline);
        let latest = tracker.take_latest()?;
        let now = now_ns();
        // Never tick faster than half a period, whatever the tracker's rate.
        if latest.is_some() && now < last_tick_ns + period_ns / 2 {
            continue;
        }
        if latest.is_none() && now < deadline {
            continue; // spurious wake-up
        }
        if let Some(t) = &latest {
            ipc_types::check_layout("TrackerFrame", t.layout_version)?;
            if !announced {
                eprintln!(
                    "engine[{}]: tracker connected (frame {})",
                    services.instance, t.frame_number
                );
                announced = true;
            }
        }
        core.step(tick, latest.as_ref(), &mut frame);
        frame.stamps.engine_receive_ns = now;
        if latest.is_none() {
            // Fallback tick: next deadline one period later (absolute, no drift).
            deadline += period_ns;
        } else {
            deadline = now + period_ns + grace_ns;
        }
        frame.stamps.engine_publish_ns = now_ns();
        outlet.publish(frame)?;
        last_tick_ns = now;
        tick += 1;
    }
    eprintln!("engine[{}]: stopped after {tick} ticks", services.instance);
    Ok(())
}
