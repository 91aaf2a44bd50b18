//! `lungdyn tracker …`: tools for wiring and evaluating trackers.
//!
//! - `listen`: run a source through the bridge's own loop (same validation, same statistics) without
//!   publishing, and show each tool's rate, latest pose, flags and the counters;
//! - `simulate`: write a recording of realistic head motion (`tracker_bridge::head_motion`);
//! - `predict`: pose error at display time with and without prediction on a recording.

use std::path::PathBuf;

use anyhow::{bail, Context};
use ipc_types::{TrackerFrame, TOOL_HMD, TOOL_PATIENT};
use serde_json::{json, Value};
use tracker_bridge::record::{Record, RecordReader};
use tracker_bridge::run::{run_loop, Reporter};
use tracker_bridge::sample::ToolName;
use tracker_bridge::stats::status_names;
use tracker_pose::predict::{
    evaluate, AlphaBeta, ConstantVelocity, Errors, Hold, Predictor, TimedPose,
};
use transport::{PortError, Publish};

/// Options of `lungdyn tracker listen`.
#[derive(Debug, Clone, clap::Args)]
pub struct ListenArgs {
    /// The source and how its samples are judged (the bridge's options).
    #[command(flatten)]
    pub source: tracker_bridge::SourceArgs,
    /// Listen this long, then print the summary (until Ctrl-C when omitted).
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// Print the summary as one JSON object on stdout (`frames`, `rejected` by reason, `tools` with
    /// name, frames, rate and last pose as position mm + quaternion, `flagged`, `link`, ...).
    #[arg(long)]
    pub json: bool,
}

/// Counts frames and shows a line per second on a terminal.
struct Watch {
    frames: u64,
    last_line_ns: u64,
    live: bool,
}

impl Publish<TrackerFrame> for Watch {
    fn publish(&mut self, f: &TrackerFrame) -> Result<(), PortError> {
        self.frames += 1;
        let now = f.stamps.bridge_publish_ns;
        if self.live && now.saturating_sub(self.last_line_ns) >= 1_000_000_000 {
            self.last_line_ns = now;
            let tool = |slot: usize| {
                let t = &f.tools[slot];
                let p = t.pose.translation_mm;
                format!(
                    "({:8.1} {:8.1} {:8.1}) mm [{}]",
                    p[0],
                    p[1],
                    p[2],
                    status_names(t.status).join(",")
                )
            };
            eprintln!(
                "frame {:>6}  patient {}  hmd {}",
                f.frame_number,
                tool(TOOL_PATIENT),
                tool(TOOL_HMD)
            );
        }
        Ok(())
    }
}

/// Run `lungdyn tracker listen`: the statistics as JSON (also printed as text unless `--json`).
pub fn listen(args: &ListenArgs) -> anyhow::Result<Value> {
    let run_ns = transport::process::run_ns(args.seconds)?;
    let tracker_bridge::Opened {
        mut source,
        mut assembler,
        mut recorder,
    } = tracker_bridge::open(&args.source)?;
    let description = source.describe();
    eprintln!("lungdyn tracker listen: {description}; Ctrl-C to stop");
    transport::stop::install()?;
    let start = transport::now_ns();
    let stop_at = run_ns.map(|d| start.saturating_add(d));
    let mut watch = Watch {
        frames: 0,
        last_line_ns: 0,
        live: std::io::IsTerminal::is_terminal(&std::io::stderr()),
    };
    let mut reporter = Reporter::new("lungdyn tracker listen", false);
    run_loop(
        source.as_mut(),
        &mut assembler,
        &mut watch,
        &mut recorder,
        &transport::Monotonic,
        &mut |now| transport::stop::requested() || stop_at.is_some_and(|t| now >= t),
        &mut |e, now| reporter.event(e, now),
        &mut || 0, // a tracker listened to alone: no renderer's latency to measure
    )?;
    drop(source);
    let seconds = (transport::now_ns() - start) as f64 / 1e9;
    let mut v = assembler.stats.to_json();
    v["source"] = json!(description);
    v["seconds"] = json!(seconds);
    if let Some(r) = recorder.take() {
        let path = r.finish()?;
        v["recording"] = json!(path.display().to_string());
    }
    if !args.json {
        print!("{description}, {seconds:.1} s\n{}", assembler.stats.text());
    }
    Ok(v)
}

/// After `tracker listen`'s statistics are out: an error when not one sample arrived, naming what
/// to check — a wiring check that heard nothing has failed, whatever it printed.
pub fn heard_something(v: &Value) -> anyhow::Result<()> {
    if v["samples"].as_u64().unwrap_or(0) > 0 {
        return Ok(());
    }
    let link = &v["link"];
    let (connects, retries) = (
        link["connects"].as_u64().unwrap_or(0),
        link["retries"].as_u64().unwrap_or(0),
    );
    bail!(
        "no sample arrived from {} in {:.1} s ({connects} connects, {retries} retries): check that \
         the tracker is plugged in and on, its port or address, and that this user may open it \
         (`lungdyn doctor` lists the serial ports and their access)",
        v["source"].as_str().unwrap_or("the source"),
        v["seconds"].as_f64().unwrap_or(0.0)
    )
}

/// Options of `lungdyn tracker simulate`.
#[derive(Debug, Clone, clap::Args)]
pub struct SimulateArgs {
    /// The recording to write (never overwritten).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// Length, seconds.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Sample rate, Hz.
    #[arg(long, default_value_t = 60.0)]
    pub rate_hz: f64,
    /// Random seed (the same seed gives the same motion).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Tracker position noise per axis (1 sigma), mm.
    #[arg(long, default_value_t = 0.05)]
    pub noise_mm: f64,
    /// Tracker rotation noise per axis (1 sigma), degrees.
    #[arg(long, default_value_t = 0.02)]
    pub noise_deg: f64,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Run `lungdyn tracker simulate`.
pub fn simulate(args: &SimulateArgs) -> anyhow::Result<Value> {
    if !(args.seconds.is_finite() && (1.0..=3600.0).contains(&args.seconds)) {
        bail!("--seconds {} must be within 1..3600", args.seconds);
    }
    if !(args.rate_hz.is_finite() && (10.0..=1000.0).contains(&args.rate_hz)) {
        bail!("--rate-hz {} must be within 10..1000", args.rate_hz);
    }
    for (name, v, max) in [
        ("--noise-mm", args.noise_mm, 10.0),
        ("--noise-deg", args.noise_deg, 5.0),
    ] {
        if !(v.is_finite() && (0.0..=max).contains(&v)) {
            bail!("{name} {v} must be within 0..{max}");
        }
    }
    let m = tracker_bridge::head_motion::HeadMotion {
        seconds: args.seconds,
        rate_hz: args.rate_hz,
        seed: args.seed,
        noise_mm: args.noise_mm,
        noise_deg: args.noise_deg,
    };
    let n = tracker_bridge::head_motion::write(&args.out, &m)?;
    Ok(json!({
        "recording": args.out.display().to_string(),
        "samples_per_tool": n,
        "seconds": args.seconds,
        "rate_hz": args.rate_hz,
        "seed": args.seed,
    }))
}

/// Options of `lungdyn tracker predict`.
#[derive(Debug, Clone, clap::Args)]
pub struct PredictArgs {
    /// A recording (`--record` of any source, or `lungdyn tracker simulate`).
    #[arg(long, value_name = "FILE")]
    pub recording: PathBuf,
    /// Look-ahead times (sample to display), ms.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "16,33",
        value_name = "MS"
    )]
    pub lookahead_ms: Vec<f64>,
    /// The tool to predict (default: the recording's HMD tool).
    #[arg(long, value_name = "NAME")]
    pub tool: Option<String>,
    /// Gains of the alpha-beta filters compared.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.3,0.5,0.7",
        value_name = "A"
    )]
    pub alpha: Vec<f64>,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
}

fn summary_json(e: &Errors) -> Value {
    let s = |x: &tracker_pose::predict::Summary| json!({"mean": x.mean, "p50": x.p50, "p95": x.p95, "p99": x.p99, "max": x.max});
    json!({"n": e.n, "translation_mm": s(&e.translation_mm), "rotation_deg": s(&e.rotation_deg)})
}

/// Run `lungdyn tracker predict`.
pub fn predict(args: &PredictArgs) -> anyhow::Result<Value> {
    if args.lookahead_ms.is_empty()
        || !args
            .lookahead_ms
            .iter()
            .all(|l| l.is_finite() && (0.0..=500.0).contains(l))
    {
        bail!(
            "--lookahead-ms {:?}: give look-aheads within 0..500 ms",
            args.lookahead_ms
        );
    }
    if !args
        .alpha
        .iter()
        .all(|a| a.is_finite() && *a > 0.0 && *a <= 1.0)
    {
        bail!("--alpha {:?}: gains within (0, 1]", args.alpha);
    }
    let mut reader = RecordReader::open(&args.recording)?;
    let config = reader.header.config.clone();
    let name = match &args.tool {
        Some(n) => ToolName::new(n)?,
        None => {
            config.slots[TOOL_HMD].context("the recording maps no HMD tool: pass --tool NAME")?
        }
    };
    let mut samples: Vec<TimedPose> = Vec::new();
    let mut rejected = 0usize;
    loop {
        match reader.next_record() {
            Ok(Some(Record::Sample(s))) if s.name.matches(&name) => match config
                .validation
                .check(&s)
                .pose
            {
                Some(p) => {
                    if samples.last().is_none_or(|l| s.receive_ns > l.t_ns) {
                        samples.push(TimedPose::from_xyzw(s.receive_ns, p.quat, p.translation_mm));
                    }
                }
                None => rejected += 1,
            },
            Ok(Some(_)) => {}
            Ok(None) => break,
            Err(e @ tracker_bridge::record::RecordError::Truncated { .. }) => {
                eprintln!("lungdyn tracker predict: {e}; using the complete part");
                break;
            }
            Err(e) => return Err(e.into()),
        }
    }
    if samples.len() < 10 {
        bail!(
            "{} has {} valid samples of tool {name} (of the names it maps: {:?}); need at least 10",
            args.recording.display(),
            samples.len(),
            config
                .slots
                .iter()
                .flatten()
                .map(|n| n.as_str().to_string())
                .collect::<Vec<_>>()
        );
    }
    let span = (samples.last().map_or(0, |s| s.t_ns) - samples[0].t_ns) as f64 / 1e9;
    let rate = (samples.len() - 1) as f64 / span.max(1e-9);
    // A gap of more than 3 sample periods restarts the predictors (tracking was lost).
    let max_gap = (3e9 / rate) as u64;
    let mut predictors: Vec<Box<dyn Predictor>> = vec![
        Box::new(Hold::default()),
        Box::new(ConstantVelocity::default()),
    ];
    for a in &args.alpha {
        predictors.push(Box::new(AlphaBeta::new(*a)));
    }
    let mut results = Vec::new();
    for &l in &args.lookahead_ms {
        let la = (l * 1e6).round() as u64;
        for p in predictors.iter_mut() {
            let e = evaluate(&samples, p.as_mut(), la, max_gap);
            let mut r = summary_json(&e);
            r["lookahead_ms"] = json!(l);
            r["method"] = json!(p.name());
            results.push(r);
        }
    }
    Ok(json!({
        "recording": args.recording.display().to_string(),
        "tool": name.as_str(),
        "samples": samples.len(),
        "rejected_samples": rejected,
        "seconds": span,
        "rate_hz": rate,
        "results": results,
    }))
}

/// The table `lungdyn tracker predict` prints.
pub fn predict_text(v: &Value) -> String {
    let mut s = format!(
        "pose error at display time, tool {} ({} samples, {:.1} s at {:.1} Hz), recording {}\n",
        v["tool"].as_str().unwrap_or(""),
        v["samples"],
        v["seconds"].as_f64().unwrap_or(0.0),
        v["rate_hz"].as_f64().unwrap_or(0.0),
        v["recording"].as_str().unwrap_or("")
    );
    s += "look-ahead  method                     translation mm: mean    p95    max   rotation deg: mean   p95    max\n";
    for r in v["results"].as_array().into_iter().flatten() {
        let g = |k: &str, q: &str| r[k][q].as_f64().unwrap_or(f64::NAN);
        s += &format!(
            "{:>7.1} ms  {:<26} {:>20.2} {:>6.2} {:>6.2} {:>19.3} {:>6.3} {:>6.3}\n",
            r["lookahead_ms"].as_f64().unwrap_or(0.0),
            r["method"].as_str().unwrap_or(""),
            g("translation_mm", "mean"),
            g("translation_mm", "p95"),
            g("translation_mm", "max"),
            g("rotation_deg", "mean"),
            g("rotation_deg", "p95"),
            g("rotation_deg", "max"),
        );
    }
    s
}
