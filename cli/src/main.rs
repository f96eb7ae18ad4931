//! `rayfarm`: what a person types. Prepare scenes, render them locally, and (with the cluster)
//! submit and watch jobs. A thin layer over `rayfarm-core`.

mod bench;
mod client;
mod cmd;
mod local_cluster;
mod table;
mod units;
mod view;

use clap::{Parser, Subcommand};

/// rayfarm: a distributed ray-tracing render farm for scenes larger than one machine.
#[derive(Parser)]
#[command(version, about, propagate_version = true)]
struct Cli {
    /// More log output (-v debug, -vv trace; the servers' flags mean the same); RUST_LOG
    /// overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate a cluster in this process on virtual time (real machines, real kernel), with
    /// faults from seeds; exits non-zero naming any seed that breaks an invariant.
    Sim(Box<cmd::sim::SimArgs>),
    /// Cut a mesh, a volume or a generated scene into domains on disk.
    Prepare(cmd::prepare::PrepareArgs),
    /// Render a scene in this process (the reference every distributed render must equal).
    Render(cmd::render::RenderArgs),
    /// Prepare the built-in scene if missing and render it on a local cluster, printing the
    /// statistics.
    Demo(cmd::demo::DemoArgs),
    /// Queue a frame on the cluster; prints the job id (or, with --wait, follows it and saves
    /// the image).
    Submit(cmd::submit::SubmitArgs),
    /// Follow a job's progress until it ends.
    Watch(cmd::watch::WatchArgs),
    /// List the cluster's jobs, newest first.
    Jobs(cmd::jobs::JobsArgs),
    /// Show the workers, their resident domains and queues, and the running job.
    Status(cmd::status::StatusArgs),
    /// Save a finished job's image (and statistics).
    Fetch(cmd::fetch::FetchArgs),
    /// Cancel a queued or running job.
    Cancel(cmd::cancel::CancelArgs),
    /// Render one scene with every schedule side by side (cold caches, repeats interleaved)
    /// on a local cluster and compare time, domain loads and traffic against the bound.
    Bench(cmd::bench::BenchArgs),
    /// Load the job API of a local cluster with many clients at once (submit, watch, list,
    /// fetch) over a store of finished jobs, and report each call's latency.
    BenchApi(cmd::bench_api::BenchApiArgs),
    /// Check that a coordinator or worker is up (the gRPC health service).
    Health(cmd::health::HealthArgs),
    /// Write a private CA, a node certificate for the given hosts and (optionally) a random
    /// cluster secret and user token: what a cluster needs to turn security on.
    Certs(cmd::certs::CertsArgs),
}

fn main() -> std::process::ExitCode {
    end_quietly_on_a_closed_stdout();
    let cli = Cli::parse();
    let default = match cli.verbose {
        0 => "warn",
        1 => "debug",
        _ => "trace",
    };
    rayfarm_node::telemetry::init_logging(default);
    let result = dispatch(cli.command);
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", error_text(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// A reader that went away (`rayfarm jobs --json | head -1`) makes `println!` panic with
/// "failed printing to stdout: Broken pipe". For a command-line tool that is the normal end
/// of its output: leave quietly with success, as `cat` does. (Restoring SIGPIPE's default
/// action instead would also kill the process on a peer's broken TLS connection, which
/// tokio writes with `writev`.)
fn end_quietly_on_a_closed_stdout() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let text = info
            .payload_as_str()
            .map_or_else(|| info.to_string(), str::to_string);
        if text.starts_with("failed printing to stdout") && text.contains("Broken pipe") {
            std::process::exit(0);
        }
        default(info);
    }));
}

/// An error and its causes on one line, leaving out a cause its parent already quotes
/// (`io::Error`s and transport errors are often both shown and chained as the source, which
/// `{:#}` prints twice: "No such file or directory (os error 2): No such file or directory
/// (os error 2)").
fn error_text(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let part = cause.to_string();
        if text.contains(&part) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    text
}

/// Runs one subcommand.
fn dispatch(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Prepare(a) => cmd::prepare::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::Sim(a) => cmd::sim::run(*a),
        Command::Demo(a) => cmd::demo::run(a),
        Command::Submit(a) => cmd::submit::run(a),
        Command::Watch(a) => cmd::watch::run(a),
        Command::Jobs(a) => cmd::jobs::run(a),
        Command::Status(a) => cmd::status::run(a),
        Command::Fetch(a) => cmd::fetch::run(a),
        Command::Cancel(a) => cmd::cancel::run(a),
        Command::Bench(a) => cmd::bench::run(a),
        Command::BenchApi(a) => cmd::bench_api::run(a),
        Command::Health(a) => cmd::health::run(a),
        Command::Certs(a) => cmd::certs::run(a),
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// Clap checks flag names, env twins and relations only when asked; a clash among the
    /// flattened option groups would otherwise surface as a panic in a user's hands.
    #[test]
    fn an_error_quotes_each_cause_once() {
        let io = std::io::Error::from(std::io::ErrorKind::NotFound);
        let e = anyhow::Error::new(io).context("missing.ply: entity not found");
        assert_eq!(super::error_text(&e), "missing.ply: entity not found");
        let e = anyhow::anyhow!("refused").context("connecting");
        assert_eq!(super::error_text(&e), "connecting: refused");
    }

    #[test]
    fn every_command_line_is_well_formed() {
        super::Cli::command().debug_assert();
    }
}
