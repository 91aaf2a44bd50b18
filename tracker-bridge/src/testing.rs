//! The bridge's loop run for a test: a source into memory instead of shared memory, stopped by the
//! test's own condition. Built only for tests and benchmarks (the `testing` feature), never into the
//! deployed bridge; the source tests (OpenIGTLink, NDI, replay, pyigtl) share it instead of each
//! wiring [`run_loop`] itself.

use ipc_types::TrackerFrame;
use transport::memory::Recorder;
use transport::Clock;

use crate::assemble::{Assembler, BridgeConfig};
use crate::record::RecordWriter;
use crate::run::{run_loop, Ended};
use crate::source::Source;
use crate::BridgeError;

/// What a test run of the loop leaves.
pub struct TestRun {
    /// Every frame published, in order.
    pub frames: Vec<TrackerFrame>,
    /// The assembler, with its counters.
    pub assembler: Assembler,
    /// Why the loop ended.
    pub ended: Ended,
}

/// Run the bridge's loop on `source` with `config` on `clock` until `stop()` says so (asked once
/// per turn of the loop) or the source ends, recording into `recorder` when there is one. Each
/// event is printed on stderr after `tag` (none when `tag` is empty).
pub fn run_source<C: Clock + Clone + 'static>(
    source: &mut dyn Source,
    config: BridgeConfig,
    clock: &C,
    recorder: &mut Option<RecordWriter>,
    stop: &mut dyn FnMut() -> bool,
    tag: &str,
) -> Result<TestRun, BridgeError> {
    run_assembled(
        source,
        Assembler::new(config),
        clock,
        recorder,
        stop,
        tag,
        &mut || 0,
    )
}

/// [`run_source`] with an assembler of the caller's (a respiratory signal set on it) and the
/// pipeline's latency as `latency` says it was measured (`run_loop`'s).
pub fn run_assembled<C: Clock + Clone + 'static>(
    source: &mut dyn Source,
    mut assembler: Assembler,
    clock: &C,
    recorder: &mut Option<RecordWriter>,
    stop: &mut dyn FnMut() -> bool,
    tag: &str,
    latency: &mut dyn FnMut() -> u64,
) -> Result<TestRun, BridgeError> {
    let mut out = Recorder::new(clock);
    let ended = run_loop(
        source,
        &mut assembler,
        &mut out,
        recorder,
        clock,
        &mut |_| stop(),
        &mut |e, _| {
            if !tag.is_empty() {
                eprintln!("{tag}: {}", e.text);
            }
        },
        latency,
    )?;
    Ok(TestRun {
        frames: out.values(),
        assembler,
        ended,
    })
}
