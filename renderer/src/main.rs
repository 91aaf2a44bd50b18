//! The `renderer` process: see [`renderer::process`].
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "renderer",
    about = "lungdyn renderer: deforms and draws the lungs with wgpu, fed over iceoryx2",
    long_about = "lungdyn renderer: draws each engine frame as it arrives (redrawing the last one, flagged \
                  stale, when the engine is late), deforming both lungs in one compute pass from the \
                  scene's kernels. The scene must name a kernel for every lung (`lungdyn scene prepare` \
                  writes such a scene); a lung whose kernel differs from the engine's is drawn at rest \
                  and reported."
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
            eprintln!(
                "renderer: error: {}",
                transport::process::describe_error(&e)
            );
            std::process::ExitCode::FAILURE
        }
    }
}
