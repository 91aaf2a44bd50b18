//! The `tracker-bridge` process: see the library docs.
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "tracker-bridge",
    about = "lungdyn tracker-bridge: publishes tracker frames at 60 Hz over iceoryx2"
)]
struct Cli {
    #[command(flatten)]
    args: tracker_bridge::BridgeArgs,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    match tracker_bridge::run(&cli.args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!(
                "tracker-bridge: error: {}",
                transport::process::describe_error(&e)
            );
            std::process::ExitCode::FAILURE
        }
    }
}
