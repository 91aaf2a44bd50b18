//! # tracker-bridge: tracker samples in, validated and stamped tracker frames out at 60 Hz
//!
//! Sources: [`synthetic`] for now (NDI combined API, OpenIGTLink and recorded sessions are later
//! work). The loop is paced by an absolute deadline (`next += period; sleep_until(next)`), so the
//! rate never drifts; a late wake-up skips missed slots instead of bursting.

pub mod synthetic;

use ipc_types::{
    now_ns, sleep_until_ns, termination_requested, tool_status, Outlet, Services, TrackerFrame,
};

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
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted).
    #[arg(long)]
    pub seconds: Option<f64>,
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
pub fn run(args: &BridgeArgs) -> anyhow::Result<()> {
    if !(args.rate_hz.is_finite() && (1.0..=1000.0).contains(&args.rate_hz)) {
        anyhow::bail!("--rate-hz {} must be within 1..1000", args.rate_hz);
    }
    if !(args.drift_deg.is_finite() && (0.0..=45.0).contains(&args.drift_deg)) {
        anyhow::bail!("--drift-deg {} must be within 0..45", args.drift_deg);
    }
    let services = Services::new(&args.instance)?;
    ipc_types::pin_to_core(args.cpu, "tracker-bridge")?;
    let source = synthetic::Synthetic {
        rate_hz: args.rate_hz,
        drift_deg: args.drift_deg,
        ..Default::default()
    };
    let node = services.node("tracker-bridge")?;
    let outlet: Outlet<TrackerFrame> =
        Outlet::new(&node, &services.tracker(), &services.tracker_event())?;
    let period_ns = (1e9 / args.rate_hz).round() as u64;
    let start = now_ns();
    let stop_at = args.seconds.map(|s| start + (s * 1e9) as u64);
    eprintln!(
        "tracker-bridge[{}]: synthetic source at {} Hz publishing on {:?}",
        services.instance,
        args.rate_hz,
        services.tracker()
    );
    let mut next = start;
    let mut n: u64 = 0;
    let mut skipped: u64 = 0;
    loop {
        if termination_requested(&node) || stop_at.is_some_and(|t| now_ns() >= t) {
            break;
        }
        sleep_until_ns(next);
        n += 1;
        let mut frame = source.frame(n, now_ns());
        validate(&mut frame);
        frame.stamps.bridge_publish_ns = now_ns();
        outlet.publish(frame)?;
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
        services.instance
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
