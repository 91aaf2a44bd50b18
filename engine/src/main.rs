//! The `engine` process: see [`engine::runtime`].
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "engine",
    about = "lungdyn engine: PV model + deformation scale at a fixed tick, over iceoryx2"
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
            eprintln!("engine: error: {}", ipc_types::describe_error(e.as_ref()));
            std::process::ExitCode::FAILURE
        }
    }
}
