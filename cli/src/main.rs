//! `lungdyn`: thin argument parsing around the library.
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "lungdyn",
    version,
    about = "lungdyn: real-time breathing lungs for AR overlays (PV model + deformation on the GPU)",
    long_about = "lungdyn simulates a patient's lungs breathing and renders them registered to the \
                  tracked patient. `lungdyn demo` runs the whole pipeline (tracker-bridge, engine, \
                  renderer as three processes over iceoryx2 shared memory) on the built-in lungs and \
                  prints how fast it was."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the three processes on the built-in scene, write PNGs across a breath, print latency.
    Demo(lungdyn::demo::DemoArgs),
    /// Seeded, repeatable fault injection against running demo pipelines: each round a fresh
    /// pipeline with two faults at engine ticks drawn from the seed (SIGKILL and SIGSTOP/SIGCONT of
    /// each process, an engine stall past its budget, corrupted and NaN tracker frames, a dead
    /// process's shared memory; every tenth round a restart storm past the intensity limit).
    /// Checks per round that the renderer never stops presenting for more than 2 frame periods
    /// while a fault is under way (a killed or stopped renderer excepted: its time to the first
    /// frame after it is reported; gaps with no fault under way are the machine's, counted apart),
    /// that a restarted engine resumes with the breath an uninterrupted run shows, that no frame
    /// carries a NaN and no file is left in /dev/shm or iceoryx2's folder; times every fault's
    /// recovery. Exits 1 when a round failed an assertion.
    Faults(lungdyn::faults::FaultsArgs),
    /// The stray process of `lungdyn faults` (garbage tracker frames, a node to be killed).
    #[command(hide = true)]
    FaultsStray(lungdyn::faults::StrayArgs),
    /// The latency harness: run the pipeline and measure every frame from tracker capture to
    /// submit, GPU done and (in a window) present — per hop p50/p99/p99.9/max, deadline misses with
    /// the stage that overran, each process's period jitter and CPU time; --sweep finds the largest
    /// mesh that holds 60 Hz. Writes latency.json, latency.md, latency.png/.svg and the trace
    /// latency.trace.json (unless --trace names another file) into --out.
    Latency(lungdyn::latency::LatencyArgs),
    /// A patient's lungs from CT lung masks in one command: both surfaces, both kernels (keeping
    /// the masks' lobes), PV constants with FRC from the exhale masks and a scene to run with
    /// `lungdyn demo --scene OUT/scene.toml`.
    Patient(lungdyn::patient_cmd::PatientArgs),
    /// Lung surface meshes.
    #[command(subcommand)]
    Mesh(MeshCommand),
    /// The pressure-volume relation: presets, simulate a breath, fit a measured loop.
    #[command(subcommand)]
    Pv(lungdyn::pv_cmd::PvCommand),
    /// Bake a lung mesh into a kernel: spring nodes, elasticity, every Green's-function transfer
    /// row (pitcher-catcher, in parallel), directions and the unit displacement.
    Bake(lungdyn::bake_cmd::BakeArgs),
    /// Fit the motion between breathing phases: landmarks (in a stated frame: body, LPS, RAS, voxel,
    /// DIR-Lab) by every model with in-sample and cross-validated errors beside the no-motion
    /// baseline, or two meshes by the kernel's own model; writes what `bake --motion` uses.
    FitMotion(lungdyn::motion_cmd::FitMotionArgs),
    /// Kernel files.
    #[command(subcommand)]
    Kernel(KernelCommand),
    /// Scenes: give every lung a kernel so the processes can be started on their own.
    #[command(subcommand)]
    Scene(SceneCommand),
    /// Trackers: listen to a source, simulate head motion, evaluate pose prediction.
    #[command(subcommand)]
    Tracker(TrackerCommand),
    /// Breathing with the patient: a respiratory recording replayed as the live signal through the
    /// engine's follower (calibration, breaths, prediction to the display time).
    #[command(subcommand)]
    Breathing(BreathingCommand),
    /// Register the lungs' model frame onto the patient reference from fiducials (Horn/Umeyama) and
    /// write the calibration file; reports each fiducial's registration error.
    Register(lungdyn::register_cmd::RegisterArgs),
    /// HMD optics files.
    #[command(subcommand)]
    Hmd(HmdCommand),
    /// One breath out of lungdyn: `export gltf` writes it as binary glTF (both lungs breathing as
    /// morph targets, lobes as materials, the tumour, the scene's figures) for any glTF viewer.
    #[command(subcommand)]
    Export(ExportCommand),
    /// Measurements: the deformation modes' speed/accuracy trade.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Check this machine for the HMD workstation: GPU, displays, X11, real-time limits, isolated
    /// cores, CPU governor, tracker serial ports, the OpenIGTLink port, shared-memory folders,
    /// systemd — each ok / warning / missing with what fixes it. Exits 2 when something is missing.
    Doctor(lungdyn::doctor::DoctorArgs),
    /// Install the workstation service under --prefix: the binary, the scene prepared with its
    /// kernels, one systemd unit per process (Type=notify, watchdog, restart limits, real-time
    /// limits, the scene's cores) and lungdyn.target, and a udev rule naming the tracker's serial
    /// adapter; says what it wrote and what to run next (docs/DEPLOY.md).
    Install(lungdyn::install::InstallArgs),
    /// List the running instances (what `scene event` needs): name, processes, scene, age.
    Instances(lungdyn::instances::InstancesArgs),
    /// Remote sites breathing in step over Zenoh (seed §8.3): serve a source engine's control
    /// state, join as a site, or measure drift with a loopback harness.
    #[command(subcommand)]
    Remote(RemoteCommand),
    /// Run only the tracker-bridge process (what `demo` starts).
    TrackerBridge(tracker_bridge::BridgeArgs),
    /// Run only the engine process (what `demo` starts).
    Engine(engine::runtime::process::EngineArgs),
    /// Run only the renderer process (what `demo` starts).
    Renderer(renderer::process::RendererArgs),
}

#[derive(Subcommand)]
enum MeshCommand {
    /// Generate the built-in adult lung (closed, 2-manifold) as OBJ or PLY.
    Generate(lungdyn::mesh_cmd::GenerateArgs),
    /// Import a patient lung surface (OBJ, PLY, STL), weld and repair what is safe, verify it is
    /// closed, 2-manifold and consistently wound; optionally write the repaired mesh.
    Check(lungdyn::mesh_cmd::CheckArgs),
    /// Make a patient's lung surface from a CT lung segmentation (NIfTI, NRRD, MetaImage): this
    /// lung's labels (lungmask, TotalSegmentator, Chest Imaging Platform, 3D Slicer segment names,
    /// or one label for both lungs, separated where they touch), tunnels closed, smoothed keeping
    /// the volume, the vertex count asked, the checks `mesh check` runs, lobes from lobe labels.
    FromMask(lungdyn::mask_cmd::FromMaskArgs),
}

#[derive(Subcommand)]
enum ExportCommand {
    /// One breath of a scene as a .glb (kernels baked when missing, as `scene prepare` does).
    Gltf(lungdyn::export::GltfArgs),
}

#[derive(Subcommand)]
enum SceneCommand {
    /// Bake the default lung for every lung the scene names no kernel for (once; reused while the
    /// settings are unchanged) and write OUT/kernels/scene.resolved.toml, the scene to start the
    /// engine and renderer with (`--scene`). The engine and the renderer never bake.
    Prepare(lungdyn::prepare::PrepareArgs),
    /// Validate a scene (every key, the files it names, its [disease] table) and report what it
    /// simulates; for a disease state, the model's course: a closed pneumothorax's plan, a tension
    /// pneumothorax cycle by cycle with the scene's interventions (--json for every number).
    Check(lungdyn::scene_check::CheckArgs),
    /// Run a scene through the engine's tick function headless for --seconds of simulated time (no
    /// processes, no GPU; bakes missing kernels once) and report per lung volumes, tidal volume, rate,
    /// offset and collapse, the disease course with its events, and how often each stage worked.
    /// `lungdyn demo --scene FILE` runs the same scene in the three processes with pictures.
    Run(lungdyn::scene_check::RunArgs),
    /// Send a trainee's intervention to a running scene (tension pneumothorax): e.g.
    /// `lungdyn scene event demo-12345 needle-decompression --side left`, with the instance name
    /// the demo printed (`demo-<its pid>`, or its --instance) — `lungdyn instances` lists them. The
    /// engine applies it at its next disease cycle and prints the tick.
    Event(lungdyn::scene_event::EventArgs),
}

#[derive(Subcommand)]
enum TrackerCommand {
    /// Read a tracker source through the bridge's validation without publishing: each tool's rate,
    /// latest pose and flags, rejections by reason, link events (for wiring a tracker).
    Listen(lungdyn::tracker_cmd::ListenArgs),
    /// Write a recording of realistic head motion at the bedside (for evaluating prediction).
    Simulate(lungdyn::tracker_cmd::SimulateArgs),
    /// Pose error at display time with and without prediction on a recording (mm, degrees).
    Predict(lungdyn::tracker_cmd::PredictArgs),
}

#[derive(Subcommand)]
enum BreathingCommand {
    /// Replay a ventilator recording as if it were the live respiratory signal, capture-to-display
    /// latency included, and compare the volume the lungs would show at each frame's display time
    /// with the recording's own: RMS error (% of the tidal volume) with each predictor and without,
    /// end-inspiration lag, breaths found, irregular breaths and pauses — against issue 35's goal.
    Check(lungdyn::breathing_check::CheckArgs),
    /// Run the three processes with a recording replayed live as the patient's signal and hold
    /// every drawn frame against the recording at the moment it was shown: RMS error with and
    /// without prediction, end-inspiration lag, breaths followed, the latency measured; a CSV of
    /// every frame (--frames-out), a signal loss (--drop-at/--drop-for), a plot (--plot).
    Follow(lungdyn::breathing_follow::FollowArgs),
    /// How remote sites of a shared session follow a live patient: a source engine follows the
    /// recording as its live signal, a site engine takes its control states a network delay late
    /// and plays the patient's breath they carry; per delay, the site's volume against the
    /// source's (RMS, % of tidal), beside a site without the patient's breath, and the lag.
    Sites(lungdyn::breathing_sites::SitesArgs),
}

#[derive(Subcommand)]
enum HmdCommand {
    /// Load and check an HMD optics file (IPD, eye offsets, fields of view) and show the eyes.
    Check(lungdyn::register_cmd::HmdArgs),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Every deformation mode's error against eq. 7.1 and its per-frame time on the CPU and GPU,
    /// SH for 1..8 bands, the orientation methods, stereo vs mono: writes tradeoff.md, .csv, .png and .svg
    /// into --out, a new folder out/tradeoff-N by default (several minutes at the default sizes; --sizes 10000 for a quick look).
    Tradeoff(lungdyn::tradeoff::TradeoffArgs),
}

#[derive(Subcommand)]
enum RemoteCommand {
    /// Relay a running engine's control state (`--instance`) to Zenoh and take the sites' events.
    Serve(lungdyn_remote::roles::ServeArgs),
    /// Run this site's engine in step with a remote source (`--connect tcp/HOST:7447`); a renderer
    /// on `--instance` draws it.
    Join(lungdyn_remote::roles::JoinArgs),
    /// A classroom's Zenoh router with the time relay beside it: the source and the sites connect
    /// as clients; the sites sync their clocks with the relay, which alone probes the source.
    Router(lungdyn_remote::roles::RouterArgs),
    /// A source and N sites on loopback: drift per cycle, phase error, packets per minute.
    Harness(lungdyn_remote::harness::HarnessArgs),
    /// Make a room's authority and each participant's certificate and private key (mutual TLS,
    /// sealed packets): `--room ROOM --out DIR [--participant NAME:ROLE ...]`.
    Keys(lungdyn_remote::roles::MakeKeysArgs),
    /// The harness's source in its own process (started by `remote harness`).
    #[command(hide = true)]
    HarnessSource(lungdyn_remote::harness::SourceChildArgs),
}

#[derive(Subcommand)]
enum KernelCommand {
    /// Verify a kernel file (every checksum and index) and print its metadata.
    Inspect(lungdyn::bake_cmd::InspectArgs),
    /// Write the lung deformed to a volume (start + delta) as OBJ or PLY.
    Export(lungdyn::bake_cmd::ExportArgs),
}

impl Command {
    /// A command that reads files, computes and prints, with no socket and no child process: its
    /// output may go to a pipe that is closed early (`lungdyn scene check FILE | head`).
    fn prints_only(&self) -> bool {
        matches!(
            self,
            Command::Mesh(_)
                | Command::Patient(_)
                | Command::Pv(_)
                | Command::Bake(_)
                | Command::FitMotion(_)
                | Command::Kernel(_)
                | Command::Register(_)
                | Command::Breathing(BreathingCommand::Check(_))
                | Command::Hmd(_)
                | Command::Doctor(_)
                | Command::Instances(_)
                | Command::Install(_)
                | Command::Scene(
                    SceneCommand::Check(_) | SceneCommand::Run(_) | SceneCommand::Prepare(_)
                )
                | Command::Tracker(TrackerCommand::Simulate(_) | TrackerCommand::Predict(_))
        )
    }
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    if cli.command.prints_only() {
        // A reader that stops early (`| head`) ends such a command quietly, as it does any Unix
        // filter, instead of `println!` panicking on EPIPE. Not for the processes, the launcher or
        // the network commands: there SIGPIPE stays ignored and a write to a closed socket is an
        // error they handle.
        // SAFETY: signal(2) with SIG_DFL, before any thread is started.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let result = match cli.command {
        Command::Doctor(args) => return doctor(&args),
        Command::Demo(args) => lungdyn::demo::run(&args).and_then(|report| {
            // The report so far is printed whatever ended the run; a failure then exits non-zero.
            print_report(args.json, &lungdyn::demo::table(&report), &report)?;
            match &report.failure {
                Some(f) => Err(anyhow::anyhow!("{f}")),
                None => Ok(()),
            }
        }),
        Command::Faults(args) => lungdyn::faults::run(&args).and_then(|report| {
            print_report(args.json, &lungdyn::faults::table(&report), &report)?;
            let failed = report.rounds - report.rounds_ok;
            match failed {
                0 => Ok(()),
                n => Err(anyhow::anyhow!(
                    "{n} of {} fault rounds failed an assertion (see above)",
                    report.rounds
                )),
            }
        }),
        Command::FaultsStray(args) => lungdyn::faults::stray(&args),
        Command::Latency(args) => lungdyn::latency::run(&args).and_then(|out| {
            print_report(args.json, &lungdyn::latency::summary(&out), &out)
        }),
        Command::Mesh(MeshCommand::Generate(args)) => lungdyn::mesh_cmd::run(&args).and_then(|m| {
            emit(args.json, &m, |m| {
                format!(
                    "wrote {}: {} lung, {} vertices, {} triangles, {:.1} ml, {:.0} x {:.0} x {:.0} mm (closed 2-manifold)\n",
                    m.path, m.lung, m.vertices, m.triangles, m.volume_ml, m.size_mm[0], m.size_mm[1], m.size_mm[2]
                )
            })
        }),
        Command::Patient(args) => lungdyn::patient_cmd::run(&args).and_then(|s| emit(args.json, &s, lungdyn::patient_cmd::text)),
        Command::Mesh(MeshCommand::FromMask(args)) => lungdyn::mask_cmd::run(&args).and_then(|s| emit(args.json, &s, lungdyn::mask_cmd::text)),
        Command::Mesh(MeshCommand::Check(args)) => lungdyn::mesh_cmd::check_mesh(&args)
            .and_then(|c| emit(args.json, &c, mesh_check_text)),
        Command::Bench(BenchCommand::Tradeoff(args)) => lungdyn::tradeoff::run(&args).and_then(|t| emit(args.json, &t, lungdyn::tradeoff::text)),
        Command::Bake(args) => lungdyn::bake_cmd::bake(&args).and_then(|b| {
            if let (Some(budget), Some(false), Some(rms)) = (b.sh_budget_mm, b.sh_budget_met, b.sh_rms_mm) {
                eprintln!(
                    "lungdyn: warning: the spherical harmonics reach {rms:.3} mm RMS with {} bands, over the \
                     {budget} mm budget; the \"basis\" mode is exact for this force (set [lungs] mode = \"basis\")",
                    b.sh_bands
                );
            }
            if args.json {
                println!("{}", serde_json::to_string(&b)?);
            } else {
                print!("{}", lungdyn::bake_cmd::bake_text(&b));
            }
            Ok(())
        }),
        Command::Kernel(KernelCommand::Inspect(args)) => lungdyn::bake_cmd::inspect(&args).and_then(|i| {
            emit(args.json, &i, |i| {
                let mut t = lungdyn::bake_cmd::inspect_text(i);
                if let Some(png) = &args.plot {
                    t.push_str(&format!("wrote {}\n", png.display()));
                }
                t
            })
        }),
        Command::FitMotion(args) => lungdyn::motion_cmd::run(&args)
            .and_then(|f| emit(args.json, &f, |f| lungdyn::motion_cmd::text(f, &args))),
        Command::Kernel(KernelCommand::Export(args)) => lungdyn::bake_cmd::export(&args).and_then(|e| {
            emit(args.json, &e, |e| {
                format!(
                    "wrote {}: {:+.1} ml -> {:.1} ml (start {:.1} ml), scale {:.3}, largest displacement {:.2} mm\n",
                    e.path, e.delta_ml, e.volume_ml, e.start_volume_ml, e.scale, e.max_displacement_mm
                )
            })
        }),
        Command::Install(args) => lungdyn::install::run(&args).and_then(|r| emit(args.json, &r, lungdyn::install::text)),
        Command::Instances(args) => {
            let list = lungdyn::instances::list();
            if args.json {
                serde_json::to_string(&list)
                    .map(|j| println!("{j}"))
                    .map_err(anyhow::Error::from)
            } else {
                print!("{}", lungdyn::instances::text(&list));
                Ok(())
            }
        }
        Command::Scene(SceneCommand::Event(args)) => lungdyn::scene_event::run(&args),
        Command::Scene(SceneCommand::Run(args)) => lungdyn::scene_check::run_scene(&args).and_then(|v| emit(args.json, &v, lungdyn::scene_check::run_text)),
        Command::Scene(SceneCommand::Check(args)) => lungdyn::scene_check::run(&args).and_then(|v| emit(args.json, &v, lungdyn::scene_check::text)),
        Command::Scene(SceneCommand::Prepare(args)) => lungdyn::prepare::run(&args)
            .and_then(|p| emit(args.json, &p, lungdyn::prepare::text)),
        Command::Pv(cmd) => lungdyn::pv_cmd::run(&cmd),
        Command::Export(ExportCommand::Gltf(a)) => lungdyn::export::run(&a).and_then(|v| emit(a.json, &v, lungdyn::export::text)),
        Command::Tracker(TrackerCommand::Listen(args)) => lungdyn::tracker_cmd::listen(&args).and_then(|v| {
            if args.json {
                println!("{}", serde_json::to_string(&v)?);
            }
            lungdyn::tracker_cmd::heard_something(&v)
        }),
        Command::Tracker(TrackerCommand::Simulate(args)) => lungdyn::tracker_cmd::simulate(&args).and_then(|v| {
            emit(args.json, &v, |v| {
                format!(
                    "wrote {}: {} samples per tool, {} s of head motion at {} Hz (seed {})\n",
                    v["recording"].as_str().unwrap_or(""), v["samples_per_tool"], v["seconds"], v["rate_hz"], v["seed"]
                )
            })
        }),
        Command::Tracker(TrackerCommand::Predict(args)) => lungdyn::tracker_cmd::predict(&args).and_then(|v| emit(args.json, &v, lungdyn::tracker_cmd::predict_text)),
        Command::Breathing(BreathingCommand::Check(args)) => lungdyn::breathing_check::check(&args).and_then(|r| emit(args.json, &r, lungdyn::breathing_check::check_text)),
        Command::Breathing(BreathingCommand::Sites(args)) => lungdyn::breathing_sites::sites(&args).and_then(|r| emit(args.json, &r, lungdyn::breathing_sites::sites_text)),
        Command::Breathing(BreathingCommand::Follow(args)) => lungdyn::breathing_follow::follow(&args).and_then(|r| emit(args.json, &r, lungdyn::breathing_follow::follow_text)),
        Command::Register(args) => lungdyn::register_cmd::run(&args).and_then(|v| emit(args.json, &v, lungdyn::register_cmd::text)),
        Command::Hmd(HmdCommand::Check(args)) => lungdyn::register_cmd::hmd(&args).and_then(|v| emit(args.json, &v, lungdyn::register_cmd::hmd_text)),
        Command::Remote(RemoteCommand::Serve(args)) => {
            lungdyn_remote::roles::serve(&args).map_err(Into::into)
        }
        Command::Remote(RemoteCommand::Join(args)) => {
            lungdyn_remote::roles::join(&args).map_err(Into::into)
        }
        Command::Remote(RemoteCommand::Router(args)) => {
            lungdyn_remote::roles::router(&args).map_err(Into::into)
        }
        Command::Remote(RemoteCommand::HarnessSource(args)) => {
            lungdyn_remote::harness::source_child(&args).map_err(Into::into)
        }
        Command::Remote(RemoteCommand::Harness(args)) => remote_harness(args),
        Command::Remote(RemoteCommand::Keys(args)) => {
            lungdyn_remote::roles::make_keys(&args).map_err(Into::into)
        }
        Command::TrackerBridge(args) => tracker_bridge::run(&args).map_err(Into::into),
        Command::Engine(args) => engine::runtime::run(&args).map_err(Into::into),
        Command::Renderer(args) => renderer::process::run(&args).map_err(Into::into),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => fail(e),
    }
}

/// `lungdyn doctor`: exit status 2 when anything is missing.
fn doctor(args: &lungdyn::doctor::DoctorArgs) -> std::process::ExitCode {
    match lungdyn::doctor::run(args).and_then(|r| {
        emit(args.json, &r, lungdyn::doctor::text)?;
        Ok(r.worst())
    }) {
        Ok(lungdyn::doctor::Status::Missing) => std::process::ExitCode::from(2),
        Ok(_) => std::process::ExitCode::SUCCESS,
        Err(e) => fail(e),
    }
}

/// `lungdyn remote harness`: the source in its own process (this executable), so its CPU and
/// bytes are its own.
fn remote_harness(mut args: lungdyn_remote::harness::HarnessArgs) -> anyhow::Result<()> {
    args.source_exe = std::env::current_exe().ok();
    lungdyn_remote::harness::run(&args)
        .and_then(|r| {
            if args.json {
                serde_json::to_string_pretty(&r)
                    .map(|j| println!("{j}"))
                    .map_err(|e| lungdyn_remote::RemoteError::Usage(e.to_string()))
            } else {
                lungdyn_remote::harness::print(&r);
                Ok(())
            }
        })
        .map_err(Into::into)
}

/// Print a command's result: one JSON object on stdout with `--json`, else its text for a person.
fn emit<T: serde::Serialize>(
    json: bool,
    value: &T,
    text: impl FnOnce(&T) -> String,
) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string(value)?);
    } else {
        print!("{}", text(value));
    }
    Ok(())
}

/// `mesh check`'s text.
fn mesh_check_text(c: &lungdyn::mesh_cmd::CheckSummary) -> String {
    let r = &c.repairs;
    let mut t = format!(
        "{}: closed 2-manifold surface, {} vertices, {} triangles, Euler {}, {:.1} ml, {:.0} x {:.0} x {:.0} mm\n",
        c.path, c.vertices, c.triangles, c.euler, c.volume_ml, c.size_mm[0], c.size_mm[1], c.size_mm[2]
    );
    t.push_str(&format!(
        "repairs: {} vertices welded, {} degenerate and {} duplicate triangles removed, {} unused vertices removed{}\n",
        r.welded_vertices,
        r.degenerate_triangles,
        r.duplicate_triangles,
        r.unused_vertices,
        if r.flipped_inside_out { ", winding flipped (was inside out)" } else { "" }
    ));
    if !c.lobes.is_empty() {
        let parts: Vec<String> = c
            .lobes
            .iter()
            .map(|l| format!("{} {} vertices {:.0} mm²", l.name, l.vertices, l.area_mm2))
            .collect();
        t.push_str(&format!("lobes (fissure planes): {}\n", parts.join(", ")));
    }
    if let Some(out) = &c.out {
        t.push_str(&format!("wrote {out} (mm, body frame)\n"));
    }
    t
}

/// A run's report: with `json`, one JSON object on stdout and the table on stderr; else the table
/// on stdout.
fn print_report(json: bool, table: &str, report: &impl serde::Serialize) -> anyhow::Result<()> {
    if json {
        eprint!("{table}");
        println!("{}", serde_json::to_string(report)?);
    } else {
        print!("{table}");
    }
    Ok(())
}

/// Say why a command failed; exit 1.
fn fail(e: anyhow::Error) -> std::process::ExitCode {
    eprintln!(
        "lungdyn: error: {}",
        transport::process::describe_error(e.as_ref())
    );
    std::process::ExitCode::FAILURE
}
