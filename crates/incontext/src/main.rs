//! `incontext` — the command line.
//!
//! For now it has one command, `demo`, a seeded end-to-end run of the geometric half of the
//! pipeline (render → back-project → voxelise → sample → ICP refinement → errors). Issue 8 adds
//! `register`, `eval` and `render`, and the network stages replace the demo's stand-in for the
//! one-shot estimate.
//!
//! Exit codes: 0 ok, 2 bad input (flags, files), 1 internal error.

mod demo;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "incontext",
    version,
    about = "6D pose of a known object in one depth map"
)]
struct Cli {
    /// More log output (-v debug, -vv trace).
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
    /// Only errors.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Seeded demo that needs no files: a procedural object seen from one of the paper's
    /// viewpoints, its pose refined by ICP from a perturbed start; prints errors and timings.
    ///
    /// Example: incontext demo --seed 7 --out demo-out
    Demo(demo::DemoArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => "error",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| level.into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .without_time()
        .init();
    let result = match cli.command {
        Command::Demo(args) => demo::run(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(e.exit_code())
        }
    }
}

/// An error with the exit code it maps to.
#[derive(Debug)]
pub enum CliError {
    /// Bad input: flags, files, values (exit 2).
    Input(anyhow::Error),
    /// Anything else (exit 1).
    Internal(anyhow::Error),
}

impl CliError {
    fn exit_code(&self) -> u8 {
        match self {
            CliError::Input(_) => 2,
            CliError::Internal(_) => 1,
        }
    }
}

impl std::fmt::Display for CliError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CliError::Input(e) | CliError::Internal(e) => write!(f, "{e:#}"),
        }
    }
}
