//! # tracker-bridge: tracker samples in, validated and stamped tracker frames out at 60 Hz
//!
//! Sources: [`synthetic`] for now (NDI combined API, OpenIGTLink and recorded sessions are later
//! work). The loop is paced by an absolute deadline (`next += period; sleep_until(next)`), so the
//! rate never drifts; a late wake-up skips missed slots instead of bursting.

pub mod igtl;
pub mod ndi;
pub mod synthetic;

use ipc_types::{tool_status, TrackerFrame};
use thiserror::Error;
use transport::clock::{now_ns, sleep_until_ns};
use transport::process::{pin_to_core, run_ns, ArgError, PinError};
use transport::{iox, Instance, PortError, Publish};

/// Command-line options of the `tracker-bridge` process.
#[derive(Debug, Clone, clap::Args)]
pub struct BridgeArgs {
    /// Instance name shared by the three processes of one run.
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Sample rate, Hz.
    #[arg(long, default_value_t = 60.0)]
    pub rate_hz: f64,
    /// Peak patient orientation drift per axis, degrees.
    #[arg(long, default_value_t = 3.0)]
    pub drift_deg: f32,
    /// Pin this process to CPU core N.
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted); at most one week.
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
}

/// Why the bridge stopped with an error.
#[derive(Debug, Error)]
pub enum BridgeError {
    /// The sample rate is out of range.
    #[error("--rate-hz {0} must be within 1..1000")]
    Rate(f64),
    /// The synthetic drift is out of range.
    #[error("--drift-deg {0} must be within 0..45")]
    Drift(f32),
    /// A bad common option.
    #[error(transparent)]
    Args(#[from] ArgError),
    /// Pinning failed.
    #[error(transparent)]
    Pin(#[from] PinError),
    /// The stream failed.
    #[error(transparent)]
    Port(#[from] PortError),
}

/// Validate a frame in place: non-finite poses are rejected (flagged, never passed on as valid).
pub fn validate(frame: &mut TrackerFrame) {
    let count = (frame.tool_count as usize).min(ipc_types::MAX_TOOLS);
    frame.tool_count = count as u32;
    for tool in &mut frame.tools[..count] {
        if !tool.pose.is_finite() || !tool.rms_error_mm.is_finite() {
            tool.status = (tool.status & !tool_status::VALID) | tool_status::NON_FINITE;
        }
    }
}

/// Run the bridge until terminated (or `--seconds` elapse).
pub fn run(args: &BridgeArgs) -> Result<(), BridgeError> {
    if !(args.rate_hz.is_finite() && (1.0..=1000.0).contains(&args.rate_hz)) {
        return Err(BridgeError::Rate(args.rate_hz));
    }
    if !(args.drift_deg.is_finite() && (0.0..=45.0).contains(&args.drift_deg)) {
        return Err(BridgeError::Drift(args.drift_deg));
    }
    let run_ns = run_ns(args.seconds)?;
    let instance = Instance::new(&args.instance)?;
    let _lock = instance.lock("tracker-bridge")?;
    pin_to_core(args.cpu, "tracker-bridge")?;
    let source = synthetic::Synthetic {
        rate_hz: args.rate_hz,
        drift_deg: args.drift_deg,
        ..Default::default()
    };
    let node = iox::node(&instance, "tracker-bridge")?;
    let mut outlet = instance.tracker_outlet(&node)?;
    let period_ns = (1e9 / args.rate_hz).round() as u64;
    let start = now_ns();
    let stop_at = run_ns.map(|d| start.saturating_add(d));
    eprintln!(
        "tracker-bridge[{}]: synthetic source at {} Hz publishing on {:?}",
        instance.name(),
        args.rate_hz,
        instance.tracker()
    );
    let mut next = start;
    let mut n: u64 = 0;
    let mut skipped: u64 = 0;
    loop {
        if iox::termination_requested(&node) || stop_at.is_some_and(|t| now_ns() >= t) {
            break;
        }
        sleep_until_ns(next);
        n += 1;
        let mut frame = source.frame(n, now_ns());
        validate(&mut frame);
        frame.stamps.bridge_publish_ns = now_ns();
        outlet.publish(&frame)?;
        next += period_ns;
        let now = now_ns();
        if now > next + period_ns {
            // Overran by more than a period: drop the missed slots rather than bursting.
            let missed = (now - next) / period_ns;
            skipped += missed;
            next += missed * period_ns;
        }
    }
    eprintln!(
        "tracker-bridge[{}]: stopped after {n} frames ({skipped} slots skipped)",
        instance.name()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_poses_are_flagged_not_passed_as_valid() {
        let mut f = synthetic::Synthetic::default().frame(3, 1);
        f.tools[1].pose.translation_mm[2] = f32::NAN;
        validate(&mut f);
        assert!(f.tools[0].is_valid());
        assert!(!f.tools[1].is_valid());
        assert_ne!(f.tools[1].status & tool_status::NON_FINITE, 0);
        f.tool_count = 99;
        validate(&mut f);
        assert_eq!(f.tool_count as usize, ipc_types::MAX_TOOLS);
    }
}
