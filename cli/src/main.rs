//! `rayfarm`: what a person types. Prepare scenes, render them locally, and (with the cluster)
//! submit and watch jobs. A thin layer over `rayfarm-common`.

mod cmd;
mod table;
mod units;

use clap::{Parser, Subcommand};
use tracing_subscriber::EnvFilter;

/// rayfarm: a distributed ray-tracing render farm for scenes larger than one machine.
#[derive(Parser)]
#[command(version, about, propagate_version = true)]
struct Cli {
    /// More log output (-v info, -vv debug); RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Cut a mesh, a volume or a generated scene into domains on disk.
    Prepare(cmd::prepare::PrepareArgs),
    /// Render a scene in this process (the reference every distributed render must equal).
    Render(cmd::render::RenderArgs),
    /// Prepare the built-in scene if missing and render it, printing the statistics.
    Demo(cmd::demo::DemoArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let default = match cli.verbose {
        0 => "warn",
        1 => "info",
        _ => "debug",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default)),
        )
        .with_writer(std::io::stderr)
        .init();
    let result = match cli.command {
        Command::Prepare(a) => cmd::prepare::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::Demo(a) => cmd::demo::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
