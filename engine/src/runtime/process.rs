//! The engine process: wake on tracker frames, tick, publish.
//!
//! [`run_loop`] is the whole loop over the port traits and a clock: the [`Pacer`] decides when a
//! tick runs (a fresh tracker sample drives it at once; a late or silent tracker falls back to an
//! absolute deadline), [`EngineCore::step`] computes the frame, the loop stamps its two hops and
//! publishes. Per tick: one wait, one drain, the step (a table read and a few Newton steps per lung),
//! one zero-copy publish — no allocation, no lock, no logging beyond one line when the tracker
//! connects. [`run`] wires the loop to iceoryx2 and the host's clock.

use ipc_types::{EngineFrame, Message, TrackerFrame};
use lung_model::scene::{Scene, SceneError};
use thiserror::Error;
use transport::clock::{now_ns, Clock, Monotonic};
use transport::pacer::{PacerConfig, PacerStats, Wake};
use transport::process::{pin_to_core, ArgError, PinError, ProcessArgs};
use transport::{iox, Instance, Pacer, PortError, Publish, Receive};

use super::{CoreError, EngineCore};

/// Command-line options of the `engine` process.
#[derive(Debug, Clone, clap::Args)]
pub struct EngineArgs {
    /// Instance, scene, pinning and run time.
    #[command(flatten)]
    pub process: ProcessArgs,
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
}

/// What a run of the loop did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LoopStats {
    /// Ticks run (frames published).
    pub ticks: u64,
    /// The pacer's counters (sample vs deadline ticks, held, coalesced, skipped deadlines).
    pub pacer: PacerStats,
}

/// Run the engine loop until `stop()` says so: pace on `rx`, step `core`, publish on `tx`.
/// `announce` names the instance in the one line printed when the first tracker frame arrives
/// (`None`: silent, for tests).
pub fn run_loop(
    core: &mut EngineCore,
    rx: &mut dyn Receive<TrackerFrame>,
    tx: &mut dyn Publish<EngineFrame>,
    clock: &dyn Clock,
    pacer: PacerConfig,
    stop: &mut dyn FnMut() -> bool,
    announce: Option<&str>,
) -> Result<LoopStats, PortError> {
    let mut pacer = Pacer::new(pacer, clock.now_ns());
    let mut frame = EngineFrame::default();
    let mut tick: u64 = 0;
    let mut announced = false;
    while !stop() {
        let Some(t) = pacer.poll(clock, rx)? else {
            continue;
        };
        let input = match t.wake {
            Wake::Sample(s) => {
                s.check_layout()?;
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
        core.step(tick, input.as_ref(), &mut frame);
        frame.stamps.engine_receive_ns = t.at_ns;
        frame.stamps.engine_publish_ns = clock.now_ns();
        tx.publish(&frame)?;
        tick += 1;
    }
    Ok(LoopStats {
        ticks: tick,
        pacer: pacer.stats(),
    })
}

/// Run the engine process until terminated (or `--seconds` elapse).
pub fn run(args: &EngineArgs) -> Result<(), EngineError> {
    let args = &args.process;
    let run_ns = args.run_ns()?;
    let instance = Instance::new(&args.instance)?;
    let _lock = instance.lock("engine")?;
    pin_to_core(args.cpu, "engine")?;
    let scene = Scene::load_or_default(args.scene.as_deref())?;
    scene.refuse_unsimulated_disease(&scene_origin(args.scene.as_deref()))?;
    let mut core = EngineCore::new(&scene)?;
    let node = iox::node(&instance, "engine")?;
    let mut tracker = instance.tracker_inlet(&node)?;
    let mut outlet = instance.engine_outlet(&node)?;
    let period_ns = (1e9 / scene.engine.tick_hz).round() as u64;
    let stop_at = run_ns.map(|d| now_ns().saturating_add(d));
    eprintln!(
        "engine[{}]: {} lung(s), {} ticks/breath at {} Hz; waiting for tracker frames on {:?} \
         (ticking on the deadline meanwhile)",
        instance.name(),
        core.lung_count(),
        core.cycle_ticks(),
        scene.engine.tick_hz,
        instance.tracker()
    );
    let stats = run_loop(
        &mut core,
        &mut tracker,
        &mut outlet,
        &Monotonic,
        PacerConfig::for_period(period_ns),
        &mut || iox::termination_requested(&node) || stop_at.is_some_and(|t| now_ns() >= t),
        Some(instance.name()),
    )?;
    eprintln!(
        "engine[{}]: stopped after {} ticks ({} on a tracker sample, {} on the deadline, {} deadlines \
         skipped)",
        instance.name(),
        stats.ticks,
        stats.pacer.sample_ticks,
        stats.pacer.deadline_ticks,
        stats.pacer.skipped_deadlines
    );
    Ok(())
}

/// How a scene is named in messages: its path, or the built-in default.
fn scene_origin(path: Option<&std::path::Path>) -> String {
    path.map_or_else(|| "(built-in default)".to_string(), |p| p.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::runtime::LungGeometry;
    use ipc_types::{engine_state, LAYOUT_VERSION};
    use lung_model::deform::{LungModel, MotionConstants};
    use lung_model::mesh::{generate, Side};
    use transport::memory::{Recorder, Scripted};
    use transport::FakeClock;

    const P: u64 = 16_666_667;

    fn core() -> EngineCore {
        let lungs = [Side::Right, Side::Left]
            .into_iter()
            .map(|side| {
                let m = LungModel::build(
                    side,
                    generate::lung(side, 500).unwrap(),
                    &MotionConstants::table_6_1(side),
                )
                .unwrap();
                LungGeometry::of(&m)
            })
            .collect();
        EngineCore::with_geometry(&Scene::default(), lungs).unwrap()
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
        let clock = FakeClock::at(0);
        let mut rx = Scripted::new(&clock, arrivals, 4);
        let mut tx = Recorder::new(&clock);
        let out = tx.clone();
        let c = clock.clone();
        let stats = run_loop(
            &mut core(),
            &mut rx,
            &mut tx,
            &clock,
            PacerConfig::for_period(P),
            &mut || c.now_ns() >= until,
            None,
        )
        .unwrap();
        (out.records(), stats)
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
            &clock,
            PacerConfig::for_period(P),
            &mut || false,
            None,
        )
        .unwrap_err();
        assert!(e.to_string().contains("TrackerFrame with layout v1"), "{e}");
    }
}
