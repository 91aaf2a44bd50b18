//! The `renderer` process: see [`renderer::process`].
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "renderer",
    about = "lungdyn renderer: deforms and draws the lungs with wgpu, fed over iceoryx2"
)]
struct Cli {
    #[command(flatten)]
    args: renderer::process::RendererArgs,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    match renderer::process::run(&cli.args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("renderer: error: {}", ipc_types::describe_error(e.as_ref()));
            std::process::ExitCode::FAILURE
        }
    }
}
