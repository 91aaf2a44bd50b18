//! # tracker-bridge: tracker samples in, validated and stamped tracker frames out at 60 Hz
//!
//! The stages, in the order a sample passes them:
//!
//! * [`source`] — where samples come from, one module per source behind the [`source::Source`]
//!   trait, chosen by `--source` (synthetic, OpenIGTLink client or server, NDI over a serial port
//!   or TCP, a replayed recording); the wire codecs are [`igtl`] and [`ndi`];
//! * [`sample`] — what a source hands over: fixed-size samples and link events;
//! * [`validate`] — every sample checked (finite, a rotation, inside the tracking volume, RMS,
//!   what the device said);
//! * [`assemble`] — samples mapped to tool slots by name, frame-number gaps and repeats, staleness,
//!   one [`TrackerFrame`] per tick;
//! * [`signal`] — `--breathing`: the patient's respiratory signal, a source beside the tracker's,
//!   its samples carried in each frame's signal block;
//! * [`record`] — `--record FILE`: every sample with its receive time, replayable bit for bit;
//! * [`run`] — the shared loop: device samples published on arrival, an absolute-deadline schedule
//!   for the synthetic source, replays and a silent device;
//! * [`stats`] — counters printed at exit and written as JSON.
//!
//! Nothing downstream of the bridge ever sees a rejected sample's numbers: a tool is `VALID` with
//! its newest good pose, or not valid with its last good pose and the reasons as
//! [`ipc_types::tool_status`] bits.

pub mod allow;
pub mod assemble;
pub mod head_motion;
pub mod igtl;
pub mod igtl_polydata;
pub mod igtl_send;
pub mod latency;
pub mod ndi;
/// A simulated NDI tracker for tests and benchmarks: built only for them (the `testing` feature),
/// never into the deployed bridge.
#[cfg(any(test, feature = "testing"))]
pub mod ndi_sim;
pub mod record;
pub mod run;
pub mod sample;
pub mod signal;
pub mod signal_igtl;
pub mod signal_tool;
pub mod signal_udp;
pub mod source;
pub mod stats;
pub mod synthetic;
/// The loop run for a test ([`testing::run_source`]): built only for tests and benchmarks (the
/// `testing` feature).
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod validate;

use std::path::PathBuf;

use ipc_types::{TrackerFrame, MAX_TOOLS};
use lungdyn_scene::tracker::{Posture, TrackerScene};
use thiserror::Error;
use transport::process::{pin_to_core, run_ns, ArgError, PinError};
use transport::{iox, Instance, PortError};

use crate::assemble::{BridgeConfig, ConfigError};
use crate::record::{RecordError, RecordWriter};
use crate::run::{run_loop, Ended, Reporter};
use crate::sample::{NameError, ToolName};
use crate::source::{Source, SourceError, SourceOptions, SourceSpec};
use crate::validate::{Validation, Volume};

/// Options that choose and shape the source, shared by the bridge and `lungdyn tracker listen`.
#[derive(Debug, Clone, clap::Args)]
pub struct SourceArgs {
    /// The scene file whose [tracker] table gives the source and the synthetic patient's posture
    /// (`--source` and `--posture` given here win); the other tables are not read.
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Tracker source: synthetic, igtl-client:HOST[:PORT], igtl-server[:BIND[:PORT]] (default
    /// 0.0.0.0:18944), ndi-serial:DEVICE, ndi-tcp:HOST[:PORT] (default port 8765), replay:FILE.
    /// Default: the scene's [tracker] source, else synthetic.
    #[arg(long, value_name = "URI")]
    pub source: Option<String>,
    /// The patient reference tool's name at the source (slot 0): an OpenIGTLink device or tool
    /// name, an NDI port handle (0A) or ROM file stem.
    #[arg(long, default_value = "Patient", value_name = "NAME")]
    pub patient_tool: String,
    /// The HMD tool's name at the source (slot 1).
    #[arg(long, default_value = "HMD", value_name = "NAME")]
    pub hmd_tool: String,
    /// Tracking volume in the tracker's frame: auto (the seed's cone, 1.5 m high, 0.5 m radius,
    /// apex at the camera, axis along -Z, for trackers; none for synthetic), none,
    /// cone:HEIGHT_MM,RADIUS_MM or box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX.
    #[arg(long, default_value = "auto", value_name = "VOLUME")]
    pub volume: String,
    /// Samples whose tracker-reported RMS fit error exceeds this (mm) are not valid.
    #[arg(long, default_value_t = 1.0, value_name = "MM")]
    pub max_rms_mm: f32,
    /// Largest accepted | |q| - 1 | of a quaternion.
    #[arg(long, default_value_t = 1e-3, value_name = "T")]
    pub quat_tolerance: f32,
    /// Largest accepted deviation of a rotation matrix from orthonormal with determinant +1.
    #[arg(long, default_value_t = 1e-3, value_name = "T")]
    pub matrix_tolerance: f32,
    /// A tool with no new sample for longer than this is stale (ms).
    #[arg(long, default_value_t = 50.0, value_name = "MS")]
    pub stale_ms: f64,
    /// Sample (tick) rate, Hz.
    #[arg(long, default_value_t = 60.0)]
    pub rate_hz: f64,
    /// Synthetic source: peak patient orientation drift per axis, degrees.
    #[arg(long, default_value_t = 3.0)]
    pub drift_deg: f32,
    /// Synthetic source: roll the patient about the bed's long axis, sweeping ±DEG (90: onto each
    /// side; 180: over to prone) once per --sweep-period-s. Shows the breath following gravity in
    /// the orientation modes.
    #[arg(long, value_name = "DEG", default_value_t = 0.0)]
    pub roll_deg: f32,
    /// Synthetic source: pitch the patient head-up/head-down, sweeping ±DEG (90: sitting up and
    /// head down) once per --sweep-period-s, a quarter period after the roll.
    #[arg(long, value_name = "DEG", default_value_t = 0.0)]
    pub pitch_deg: f32,
    /// Synthetic source: seconds per roll/pitch sweep.
    #[arg(long, value_name = "S", default_value_t = 20.0)]
    pub sweep_period_s: f32,
    /// Synthetic source: the patient's posture — supine, sitting, prone, left-lateral or
    /// right-lateral (a fixed turn before the drift and the sweeps). Default: the scene's [tracker]
    /// posture, else supine.
    #[arg(long, value_enum)]
    pub posture: Option<Posture>,
    /// Record every received sample with its receive time to FILE (never overwritten).
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
    /// replay: play without waiting for the schedule.
    #[arg(long)]
    pub as_fast_as_possible: bool,
    /// NDI: a passive tool definition (.rom) to load; the tool is named by the file stem.
    /// Repeat for several tools.
    #[arg(long, value_name = "FILE")]
    pub ndi_rom: Vec<PathBuf>,
    /// NDI: poll with TX (ASCII) instead of BX (binary).
    #[arg(long)]
    pub ndi_tx: bool,
    /// NDI: polling rate, Hz (default: the tick rate).
    #[arg(long, value_name = "HZ")]
    pub ndi_poll_hz: Option<f64>,
    /// igtl-server: also serve senders at ADDR (an address, 10.0.0.5, or a network, 10.0.0.0/24);
    /// repeat for several. Loopback is always served; no one else unless named here, since any
    /// host that reaches the port could otherwise stream the patient tool's pose.
    #[arg(long = "igtl-allow", value_name = "ADDR")]
    pub igtl_allow: Vec<String>,
    /// pyigtl POSITION items: quaternion component order as the sender packed them.
    #[arg(long, value_enum, default_value_t = igtl::QuatOrder::Xyzw)]
    pub pyigtl_quat_order: igtl::QuatOrder,
    /// The patient's respiratory signal, sent in every frame beside the poses: trace:FILE (a Varian
    /// RPM .vxp, a CSV trace or a ventilator recording, replayed at its own rate from the start),
    /// udp:[BIND:]PORT (a live amplitude stream, one `mm=VALUE`, `ml=VALUE` or `au=VALUE` per
    /// datagram, stamped on arrival; 127.0.0.1 unless a BIND is given, senders off loopback only
    /// from --igtl-allow / [tracker] allow), tool:NAME (a tracked tool on the chest, by its name at
    /// the source: its rise along the patient reference's anterior axis, mm, one sample per
    /// measurement; tool:NAME:auto along the axis the tool moves on, learnt from its first 12 s,
    /// for a reference not mounted on the patient's RAS frame), igtl:NAME (an amplitude from the OpenIGTLink device NAME on an igtl: or
    /// igtl-server: source: SENSOR in a length, volume or no unit, or STRING `mm=VALUE`), recorded (the signal a --source replay:FILE recording was made with; --record
    /// writes the signal of a run that has one) or none. Default: the scene's [breathing] signal,
    /// else none.
    #[arg(long, value_name = "SOURCE")]
    pub breathing: Option<String>,
    /// Withhold the signal's samples from S seconds after the start (a signal loss, to test one;
    /// with --breathing-cut-for).
    #[arg(long, value_name = "S", requires = "breathing_cut_for")]
    pub breathing_cut_at: Option<f64>,
    /// How long the cut lasts, s.
    #[arg(long, value_name = "S", requires = "breathing_cut_at")]
    pub breathing_cut_for: Option<f64>,
}

impl Default for SourceArgs {
    fn default() -> Self {
        SourceArgs {
            scene: None,
            source: None,
            patient_tool: "Patient".into(),
            hmd_tool: "HMD".into(),
            volume: "auto".into(),
            max_rms_mm: 1.0,
            quat_tolerance: 1e-3,
            matrix_tolerance: 1e-3,
            stale_ms: 50.0,
            rate_hz: 60.0,
            drift_deg: 3.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            sweep_period_s: 20.0,
            posture: None,
            record: None,
            as_fast_as_possible: false,
            ndi_rom: Vec::new(),
            ndi_tx: false,
            ndi_poll_hz: None,
            igtl_allow: Vec::new(),
            pyigtl_quat_order: igtl::QuatOrder::Xyzw,
            breathing: None,
            breathing_cut_at: None,
            breathing_cut_for: None,
        }
    }
}

/// Everything needed to run a source: what it is, its options, and how samples become frames.
#[derive(Debug, Clone)]
pub struct Resolved {
    /// The parsed `--source`.
    pub spec: SourceSpec,
    /// Options of the source.
    pub options: SourceOptions,
    /// Mapping, validation, staleness, rate (a replay uses its recorded one instead).
    pub config: BridgeConfig,
    /// The respiratory signal's source.
    pub signal: signal::SignalSpec,
}

impl SourceArgs {
    /// The source and posture in force: the command line's, else the scene's `[tracker]` table's
    /// (`--scene`), else the defaults (synthetic, supine).
    pub fn tracker_table(&self) -> Result<TrackerScene, BridgeError> {
        let mut t = match &self.scene {
            Some(path) => lungdyn_scene::read_table::<TrackerScene>(path, "tracker")
                .map_err(|e| BridgeError::Scene(e.to_string()))?,
            None => TrackerScene::default(),
        };
        if let Some(s) = &self.source {
            t.source = s.clone();
        }
        if let Some(p) = self.posture {
            t.posture = p;
        }
        Ok(t)
    }

    /// Check every option and resolve `auto`.
    pub fn resolve(&self) -> Result<Resolved, BridgeError> {
        if !(self.drift_deg.is_finite() && (0.0..=45.0).contains(&self.drift_deg)) {
            return Err(BridgeError::Drift(self.drift_deg));
        }
        if !(self.rate_hz.is_finite() && (1.0..=1000.0).contains(&self.rate_hz)) {
            return Err(BridgeError::Rate(self.rate_hz));
        }
        let ok_deg = |v: f32| v.is_finite() && (0.0..=180.0).contains(&v);
        if !(ok_deg(self.roll_deg)
            && ok_deg(self.pitch_deg)
            && self.sweep_period_s.is_finite()
            && (1.0..=3600.0).contains(&self.sweep_period_s))
        {
            return Err(BridgeError::Sweep {
                roll: self.roll_deg,
                pitch: self.pitch_deg,
                period: self.sweep_period_s,
            });
        }
        if !(self.stale_ms.is_finite() && (1.0..=10_000.0).contains(&self.stale_ms)) {
            return Err(BridgeError::Option(format!(
                "--stale-ms {} must be within 1..10000",
                self.stale_ms
            )));
        }
        let tracker = self.tracker_table()?;
        let spec = SourceSpec::parse(&tracker.source)?;
        let volume = if self.volume.trim().eq_ignore_ascii_case("auto") {
            if spec.is_device() {
                Volume::SEED_CONE
            } else {
                Volume::Unbounded
            }
        } else {
            Volume::parse(&self.volume)
                .map_err(|e| BridgeError::Option(format!("--volume: {e}")))?
        };
        let signal_text = match &self.breathing {
            Some(b) => b.clone(),
            None => self.breathing_table()?.signal,
        };
        let signal = signal::SignalSpec::parse(&signal_text).map_err(BridgeError::Option)?;
        let mut slots = [None; MAX_TOOLS];
        slots[ipc_types::TOOL_PATIENT] = Some(ToolName::new(&self.patient_tool)?);
        slots[ipc_types::TOOL_HMD] = Some(ToolName::new(&self.hmd_tool)?);
        if let signal::SignalSpec::Tool(name, _) = &signal {
            if name.eq_ignore_ascii_case(&self.patient_tool)
                || name.eq_ignore_ascii_case(&self.hmd_tool)
            {
                return Err(BridgeError::Option(format!(
                    "--breathing tool:{name}: that is the {} tool; the chest tool is a tool of its \
                     own, tracked beside the patient reference (its motion relative to the \
                     reference is the breath)",
                    if name.eq_ignore_ascii_case(&self.patient_tool) {
                        "patient reference"
                    } else {
                        "HMD"
                    }
                )));
            }
            slots[ipc_types::TOOL_CHEST] = Some(ToolName::new(name)?);
        }
        let config = BridgeConfig {
            rate_hz: self.rate_hz,
            slots,
            validation: Validation {
                quat_tolerance: self.quat_tolerance,
                matrix_tolerance: self.matrix_tolerance,
                max_rms_mm: self.max_rms_mm,
                volume,
            },
            stale_ns: (self.stale_ms * 1e6).round() as u64,
        };
        config.check()?;
        let options = SourceOptions {
            igtl_allow: crate::source::igtl_server::AllowList::parse(
                &[tracker.allow.clone(), self.igtl_allow.clone()].concat(),
            )
            .map_err(BridgeError::Option)?,
            pyigtl_quat_order: self.pyigtl_quat_order,
            ndi_roms: self.ndi_rom.clone(),
            ndi_tx: self.ndi_tx,
            ndi_poll_hz: self.ndi_poll_hz.unwrap_or(self.rate_hz),
            as_fast_as_possible: self.as_fast_as_possible,
            synthetic: synthetic::Synthetic {
                rate_hz: self.rate_hz,
                drift_deg: self.drift_deg,
                roll_deg: self.roll_deg,
                pitch_deg: self.pitch_deg,
                sweep_period_s: self.sweep_period_s,
                posture: tracker.posture,
                ..Default::default()
            },
            ..SourceOptions::default()
        };
        if let (Some(at), Some(dur)) = (self.breathing_cut_at, self.breathing_cut_for) {
            signal::check_cut(at, dur)?;
        }
        if self.breathing_cut_at.is_some()
            && matches!(
                signal,
                signal::SignalSpec::Udp(_)
                    | signal::SignalSpec::Tool(..)
                    | signal::SignalSpec::Igtl(_)
            )
        {
            return Err(BridgeError::Option(
                "--breathing-cut-at: a live stream (UDP, OpenIGTLink) or chest tool is not cut by \
                 the bridge (stop its sender, or cover the tool, to test a loss); the cut is for \
                 trace:FILE"
                    .into(),
            ));
        }
        if self.breathing_cut_at.is_some() && signal == signal::SignalSpec::None {
            return Err(BridgeError::Option(
                "--breathing-cut-at: there is no signal to cut (give --breathing trace:FILE)"
                    .into(),
            ));
        }
        Ok(Resolved {
            spec,
            options,
            config,
            signal,
        })
    }

    /// The scene's `[breathing]` table (`--scene`), else its defaults.
    fn breathing_table(&self) -> Result<lungdyn_scene::breathing::BreathingScene, BridgeError> {
        use lungdyn_scene::breathing::{trace_relative_to, BreathingScene};
        match &self.scene {
            Some(path) => {
                let mut t: BreathingScene = lungdyn_scene::read_table(path, "breathing")
                    .map_err(|e| BridgeError::Scene(e.to_string()))?;
                // A scene's files are relative to the scene file.
                let base = path.parent().unwrap_or(std::path::Path::new("."));
                if let Some(f) = trace_relative_to(&t.signal, base) {
                    t.signal = format!("trace:{}", f.display());
                }
                Ok(t)
            }
            None => Ok(Default::default()),
        }
    }
}

/// An opened source with the assembler that goes with it (its recorded configuration for a
/// replay) and the recording, when asked for.
pub struct Opened {
    /// The source.
    pub source: Box<dyn Source>,
    /// The assembler.
    pub assembler: assemble::Assembler,
    /// The recording being written.
    pub recorder: Option<RecordWriter>,
}

/// The signal against the tracker source: an OpenIGTLink amplitude (`igtl:NAME`) needs an
/// OpenIGTLink source; `recorded` needs a replay whose file carries a signal; a file that carries
/// one plays it, so another signal beside it is refused.
/// `source_flag` names the option that chose the replay (`--source`, the demo's `--tracker`) and
/// `no_signal` the word for no signal (`none`, the demo's `model`). The launcher checks with it
/// before any process starts; the bridge again when it opens.
pub fn check_recorded_signal(
    signal: &signal::SignalSpec,
    spec: &source::SourceSpec,
    source_flag: &str,
    no_signal: &str,
) -> Result<(), BridgeError> {
    let replay = match spec {
        source::SourceSpec::Replay { path } => Some(path),
        _ => None,
    };
    if let signal::SignalSpec::Igtl(name) = signal {
        if !matches!(
            spec,
            source::SourceSpec::IgtlClient { .. }
                | source::SourceSpec::IgtlServer { .. }
                | source::SourceSpec::Replay { .. }
        ) {
            return Err(BridgeError::Option(format!(
                "--breathing igtl:{name}: reads the amplitude from the OpenIGTLink link the tracker \
                 comes on; use it with {source_flag} igtl:HOST:PORT or igtl-server:[BIND:]PORT (for \
                 a stream beside another tracker, send it over UDP: --breathing udp:PORT)"
            )));
        }
    }
    match (signal, replay) {
        (signal::SignalSpec::Recorded, None) => Err(BridgeError::Option(format!(
            "--breathing recorded: plays the signal a tracker recording carries; use it with \
             {source_flag} replay:FILE (a recording made with --record and a --breathing signal)"
        ))),
        // A replay's tools are those it was recorded with: the chest tool's signal is recorded
        // with the run (`--record` writes it) and played as `recorded`.
        (signal::SignalSpec::Tool(name, _), Some(path)) => Err(BridgeError::Option(format!(
            "--breathing tool:{name}: {} is a replayed recording, whose tools and signal are \
             those it was recorded with; record a run with --breathing tool:{name} and replay it \
             with --breathing recorded",
            path.display()
        ))),
        (signal::SignalSpec::Igtl(name), Some(path)) => Err(BridgeError::Option(format!(
            "--breathing igtl:{name}: {} is a replayed recording, whose signal is the one it was \
             recorded with; record a run with --breathing igtl:{name} and replay it with \
             --breathing recorded",
            path.display()
        ))),
        (signal::SignalSpec::Recorded, Some(path)) if !record::carries_signal(path)? => {
            Err(BridgeError::Option(format!(
                "--breathing recorded: {} carries no respiratory signal (it was recorded without \
                 --breathing); give a signal with --breathing trace:FILE, or {no_signal}",
                path.display()
            )))
        }
        (signal::SignalSpec::Trace(_) | signal::SignalSpec::Udp(_), Some(path))
            if record::carries_signal(path)? =>
        {
            Err(BridgeError::Option(format!(
                "--breathing {}: {} carries the respiratory signal it was recorded with and plays \
                 it; use --breathing recorded (or replay a recording made without one)",
                match signal {
                    signal::SignalSpec::Trace(t) => format!("trace:{}", t.display()),
                    signal::SignalSpec::Udp(a) => format!("udp:{a}"),
                    signal::SignalSpec::Tool(n, a) => format!("tool:{n}{}", a.suffix()),
                    _ => String::new(),
                },
                path.display()
            )))
        }
        _ => Ok(()),
    }
}

/// Open what `args` describe.
pub fn open(args: &SourceArgs) -> Result<Opened, BridgeError> {
    let r = args.resolve()?;
    check_recorded_signal(&r.signal, &r.spec, "--source", "none")?;
    let source = source::open(&r.spec, &r.options)?;
    let config = source.recorded_config().cloned().unwrap_or(r.config);
    let mut assembler = assemble::Assembler::new(config);
    if let signal::SignalSpec::Trace(path) = &r.signal {
        let mut replay = signal::TraceReplay::open(path)?;
        if let Some(w) = replay.warning() {
            // Said once, when the file is opened (never per sample).
            eprintln!("tracker-bridge: warning: {}: {w}", path.display());
        }
        if let (Some(at), Some(dur)) = (args.breathing_cut_at, args.breathing_cut_for) {
            replay.cut(at, dur)?;
        }
        assembler.set_signal(replay);
    }
    if let signal::SignalSpec::Udp(addr) = &r.signal {
        let udp = signal_udp::UdpSignal::bind(*addr, r.options.igtl_allow.clone())
            .map_err(signal::SignalError::Spec)?;
        assembler.set_signal(udp);
    }
    if let signal::SignalSpec::Igtl(name) = &r.signal {
        assembler.set_signal(signal_igtl::IgtlSignal::new(ToolName::new(name)?));
    }
    if let signal::SignalSpec::Tool(name, axis) = &r.signal {
        assembler.set_signal(signal_tool::ToolSignal::new(
            name,
            assembler.config().rate_hz,
            *axis,
        ));
    }
    let recorder = match &args.record {
        Some(path) => Some(RecordWriter::create(
            path,
            assembler.config(),
            &source.describe(),
        )?),
        None => None,
    };
    Ok(Opened {
        source,
        assembler,
        recorder,
    })
}

/// Command-line options of the `tracker-bridge` process.
#[derive(Debug, Clone, clap::Args)]
pub struct BridgeArgs {
    /// Instance name shared by the three processes of one run.
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Pin this process to CPU core N.
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Run SCHED_FIFO with locked memory where permitted (a warning names the missing capability or
    /// limit where not).
    #[arg(long)]
    pub realtime: bool,
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted); at most one week.
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// Write the statistics as JSON to FILE at exit.
    #[arg(long, value_name = "FILE")]
    pub stats_json: Option<PathBuf>,
    /// The source and how its samples become frames.
    #[command(flatten)]
    pub source: SourceArgs,
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
    /// A sweep amplitude or period is out of range.
    #[error("--roll-deg and --pitch-deg must be within 0..180 and --sweep-period-s within 1..3600 (got {roll}, {pitch}, {period})")]
    Sweep {
        /// Roll amplitude.
        roll: f32,
        /// Pitch amplitude.
        pitch: f32,
        /// Period.
        period: f32,
    },
    /// Another option is out of range.
    #[error("{0}")]
    Option(String),
    /// `--scene`'s `[tracker]` table could not be read.
    #[error("--scene: {0}")]
    Scene(String),
    /// A tool name cannot be used.
    #[error(transparent)]
    Name(#[from] NameError),
    /// The mapping or validation settings cannot be used.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The source could not start or failed.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// The recording could not be made.
    #[error(transparent)]
    Record(#[from] RecordError),
    /// A bad common option.
    #[error(transparent)]
    Args(#[from] ArgError),
    /// Pinning failed.
    #[error(transparent)]
    Pin(#[from] PinError),
    /// The stream failed.
    #[error(transparent)]
    Port(#[from] PortError),
    /// The respiratory signal cannot be used.
    #[error(transparent)]
    Signal(#[from] signal::SignalError),
    /// The statistics could not be written (or `--stats-json` names a device, FIFO, folder, …).
    #[error("--stats-json: {0}")]
    Stats(outfile::WriteError),
}

/// Run the bridge until terminated (or `--seconds` elapse, or a replay ends).
pub fn run(args: &BridgeArgs) -> Result<(), BridgeError> {
    transport::stop::install()?;
    let run_ns = run_ns(args.seconds)?;
    args.source.resolve()?;
    if let Some(path) = &args.stats_json {
        // Refused now, not after the run: the statistics are written at its end.
        outfile::check(path).map_err(BridgeError::Stats)?;
    }
    let instance = Instance::new(&args.instance)?;
    let _lock = instance.lock("tracker-bridge")?;
    pin_to_core(args.cpu, "tracker-bridge")?;
    transport::trace::init("tracker-bridge");
    if args.realtime {
        transport::realtime::apply("tracker-bridge");
    }
    let Opened {
        mut source,
        mut assembler,
        mut recorder,
    } = open(&args.source)?;
    let node = iox::node(&instance, "tracker-bridge")?;
    let mut outlet = instance.tracker_outlet(&node)?;
    let prefix = format!("tracker-bridge[{}]", instance.name());
    eprintln!(
        "{prefix}: {} at {} Hz publishing on {:?}{}{}",
        source.describe(),
        assembler.config().rate_hz,
        instance.tracker(),
        assembler
            .signal()
            .map(|s| format!(", breathing signal: {}", s.describe()))
            .unwrap_or_default(),
        recorder
            .as_ref()
            .map(|r| format!(", recording to {}", r.path().display()))
            .unwrap_or_default()
    );
    // The pipeline's latency for the engine's prediction of the breath (issue 35): read from the
    // renderer's reports while the bridge carries a live signal (a replay carries the recorded one).
    let mut meter = latency::LatencyMeter::new();
    let mut reports = match assembler.signal() {
        Some(_) => Some(instance.report_inlet(&node)?),
        None => None,
    };
    let mut report_errors = 0u64;
    let start = transport::now_ns();
    let stop_at = run_ns.map(|d| start.saturating_add(d));
    let mut reporter = Reporter::new(prefix.clone(), false);
    let mut watchdog = transport::notify::Watchdog::from_env();
    transport::notify::ready(&format!("{prefix}: publishing"));
    let ended = run_loop(
        source.as_mut(),
        &mut assembler,
        &mut outlet as &mut dyn transport::Publish<TrackerFrame>,
        &mut recorder,
        &transport::Monotonic,
        &mut |now| {
            // Checked every pass of the loop: a hung source read stops the watchdog's pings.
            watchdog.ping(now);
            transport::stop::requested() || stop_at.is_some_and(|t| now >= t)
        },
        &mut |e, now| reporter.event(e, now),
        &mut || {
            if let Some(inlet) = reports.as_mut() {
                // A failed read keeps the last median; counted, said at the end.
                if transport::Receive::drain(inlet, &mut |r| {
                    meter.report(r);
                })
                .is_err()
                {
                    report_errors += 1;
                }
            }
            meter.median_ns()
        },
    )?;
    transport::notify::stopping();
    transport::trace::flush();
    drop(source);
    let stats = &assembler.stats;
    if ended == Ended::SourceEnded {
        eprintln!("{prefix}: the source ended (end of the recording)");
    }
    transport::process::say(&format!(
        "{prefix}: stopped after {} frames ({} slots skipped)",
        stats.frames, stats.ticks_skipped
    ));
    eprint!("{}", indent(&stats.text(), &prefix));
    if reports.is_some() {
        let (taken, refused) = meter.counts();
        eprintln!(
            "{prefix}: pipeline latency (bridge publish → display) from {taken} renderer reports{}{}: {}",
            if refused > 0 { format!(", {refused} refused") } else { String::new() },
            if report_errors > 0 { format!(", {report_errors} failed reads") } else { String::new() },
            match meter.median_ns() {
                0 => "not measured (the engine predicted across the scene's latency_ms)".to_string(),
                ns => format!("median {:.1} ms over the last {} at the end, sent to the engine", ns as f64 / 1e6, latency::WINDOW),
            }
        );
    }
    if let Some(r) = recorder.take() {
        let path = r.finish()?;
        eprintln!("{prefix}: recorded to {}", path.display());
    }
    if let Some(path) = &args.stats_json {
        outfile::write_atomically(path, |w| {
            std::io::Write::write_all(w, format!("{}\n", stats.to_json()).as_bytes())
        })
        .map_err(BridgeError::Stats)?;
    }
    Ok(())
}

fn indent(text: &str, prefix: &str) -> String {
    text.lines().map(|l| format!("{prefix}: {l}\n")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scenes_tracker_table_is_read_and_the_command_line_wins() {
        let dir = std::env::temp_dir().join(format!("bridge-scene-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scene = dir.join("s.toml");
        std::fs::write(
            &scene,
            "[render]\nlook = \"translucent\"\n[tracker]\nsource = \"igtl-server\"\n\
             posture = \"left-lateral\"\n",
        )
        .unwrap();
        let from_scene = SourceArgs {
            scene: Some(scene.clone()),
            ..Default::default()
        };
        let t = from_scene.tracker_table().unwrap();
        assert_eq!(
            (t.source.as_str(), t.posture),
            ("igtl-server", Posture::LeftLateral)
        );
        let r = from_scene.resolve().unwrap();
        assert_eq!(r.spec, SourceSpec::parse("igtl-server").unwrap());
        assert_eq!(r.options.synthetic.posture, Posture::LeftLateral);
        let overridden = SourceArgs {
            scene: Some(scene.clone()),
            source: Some("synthetic".into()),
            posture: Some(Posture::Prone),
            ..Default::default()
        };
        let t = overridden.tracker_table().unwrap();
        assert_eq!(
            (t.source.as_str(), t.posture),
            ("synthetic", Posture::Prone)
        );
        // Without a scene: synthetic, supine.
        let t = SourceArgs::default().tracker_table().unwrap();
        assert_eq!(t, TrackerScene::default());
        // A bad table is refused naming the option, the file and the key.
        std::fs::write(&scene, "[tracker]\nposture = \"standing\"\n").unwrap();
        let e = from_scene.resolve().unwrap_err().to_string();
        assert!(
            e.starts_with("--scene: ") && e.contains("s.toml") && e.contains("standing"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn auto_volume_is_the_seed_cone_for_trackers_and_none_for_synthetic() {
        let r = SourceArgs::default().resolve().unwrap();
        assert_eq!(r.config.validation.volume, Volume::Unbounded);
        let r = SourceArgs {
            source: Some("igtl-server".into()),
            ..Default::default()
        }
        .resolve()
        .unwrap();
        assert_eq!(r.config.validation.volume, Volume::SEED_CONE);
        let bad = SourceArgs {
            hmd_tool: "patient".into(),
            ..Default::default()
        };
        assert!(bad.resolve().unwrap_err().to_string().contains("two slots"));
        let bad = SourceArgs {
            volume: "cone:1".into(),
            ..Default::default()
        };
        assert!(bad.resolve().is_err());
    }
}
