//! The `engine` process: see [`engine::runtime`].
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "engine",
    about = "lungdyn engine: PV model + per-lung deformation state at a fixed tick, over iceoryx2",
    long_about = "lungdyn engine: ticks when a tracker frame arrives (deadline fallback when the tracker \
                  is late or silent), computes each lung's volume and deformation scale from the scene's \
                  PV model and kernels, and publishes one engine frame per tick. The scene must name a \
                  kernel for every lung: `lungdyn scene prepare` writes such a scene."
)]
struct Cli {
    #[command(flatten)]
    args: engine::runtime::process::EngineArgs,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    match engine::runtime::run(&cli.args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("engine: error: {}", transport::process::describe_error(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
