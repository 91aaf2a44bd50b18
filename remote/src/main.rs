//! The `remote` process (installed as `lungdyn-remote`): a shared session's roles without the rest of
//! lungdyn — the source's relay beside its engine (`serve`), a site's engine in step with the source
//! (`join`), a classroom's router with its time relay (`router`). See [`lungdyn_remote::roles`].
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "remote",
    about = "lungdyn remote: remote sites breathing in step over Zenoh (seed §8.3) — serve a source \
             engine's control state, join a source as a site, or run a classroom's router",
    long_about = "lungdyn remote: the shared session's roles as their own process (the service's \
                  `lungdyn-remote`; `lungdyn remote ...` runs the same code). Each takes its settings \
                  from the scene's [remote] table (`--scene`); flags given here win."
)]
struct Cli {
    #[command(subcommand)]
    role: Role,
}

#[derive(Subcommand)]
enum Role {
    /// Relay a running engine's control state (`--instance`) to Zenoh and take the sites' events.
    Serve(lungdyn_remote::roles::ServeArgs),
    /// Run this site's engine in step with a remote source (`--connect tcp/HOST:7447`); a renderer
    /// on `--instance` draws it.
    Join(lungdyn_remote::roles::JoinArgs),
    /// A classroom's Zenoh router with the time relay beside it.
    Router(lungdyn_remote::roles::RouterArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let done = match &cli.role {
        Role::Serve(a) => lungdyn_remote::roles::serve(a),
        Role::Join(a) => lungdyn_remote::roles::join(a),
        Role::Router(a) => lungdyn_remote::roles::router(a),
    };
    match done {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("remote: error: {}", transport::process::describe_error(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
