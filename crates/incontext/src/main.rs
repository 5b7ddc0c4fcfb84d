//! `incontext` — the command line (see `incontext --help`).
//!
//! Exit codes: 0 ok, 2 bad input (flags, files), 3 object not found, 4 pose uncertain (written,
//! with verdict `uncertain`), 130 interrupted, 1 internal error.

use std::io::Write;
use std::process::ExitCode;

use clap::Parser;
use incontext::cli::{Cli, run};
use serde_json::json;

// The networks' large tensors are allocated and freed on every pass: glibc's malloc returns
// their pages to the system each time, mimalloc keeps them (the 24-copy forward pass of
// `register` measured 0.24–0.27 s with glibc's malloc, 0.21 s with mimalloc, 2 threads).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return flag_error(e),
    };
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { ic_pose::tune_candle_cpu_pool() };
    // More compute threads than logical CPUs only slow everything down (and thousands of
    // threads take minutes to start): cap them, and say so below once logging is set up.
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    let capped = cli.threads.filter(|&t| t > cpus);
    if let Some(t) = cli.threads {
        // SAFETY: first thing in main, before any other thread exists; rayon and candle read
        // it when they start their pools.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", t.clamp(1, cpus).to_string()) };
    }
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
    if let Some(t) = capped {
        tracing::warn!(
            "--threads {t} is more than the {cpus} logical CPUs of this machine: using {cpus}"
        );
    }
    // Ctrl-C, SIGTERM, SIGHUP: remove the temporary files of writes in flight and exit 130;
    // outputs already written stay complete, none is left half-written. `train` first asks the
    // run to save its checkpoint and stop (exit 130 below); a second signal exits at once.
    let training = matches!(cli.command, incontext::cli::Command::Train(_));
    let _ = ctrlc::set_handler(move || {
        if training && !ic_train::stop_flag().swap(true, std::sync::atomic::Ordering::SeqCst) {
            let _ = writeln!(
                std::io::stderr(),
                "interrupted: saving a checkpoint after this iteration (again to quit at once)"
            );
            return;
        }
        let _guard = ic_geometry::io::abandon_pending_writes();
        let _ = writeln!(
            std::io::stderr(),
            "error: interrupted; no partial output was left behind"
        );
        std::process::exit(130);
    });
    // A panic is a bug: report it as an internal error (exit 1), in JSON when asked.
    let json_mode = cli.json;
    std::panic::set_hook(Box::new(move |info| {
        let message = format!("internal error (a bug, please report it): {info}");
        if json_mode {
            println!(
                "{}",
                json!({"error": message, "kind": "internal", "exit_code": 1})
            );
        }
        eprintln!("error: {message}");
    }));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&cli)));
    match result {
        Ok(Ok((report, text))) => {
            if cli.json {
                out(&incontext::inputs::pretty_json(&report));
            } else {
                out(text.trim_end());
            }
            // `train` stopped by a signal: its checkpoint is saved; exit 130 as documented.
            if report["command"] == "train" && report["interrupted"] == true {
                let _ = writeln!(
                    std::io::stderr(),
                    "error: interrupted; checkpoint saved in {}",
                    report["checkpoint"].as_str().unwrap_or("?")
                );
                return ExitCode::from(130);
            }
            // `register` found a pose but cannot vouch for it: written, flagged, exit 4.
            if report["command"] == "register" && report["verdict"] == "uncertain" {
                let _ = writeln!(
                    std::io::stderr(),
                    "warning: the pose is uncertain (confidence {:.2}): it may be a symmetric \
                     flip, the wrong side or another object; check it with --overlay (exit code 4)",
                    report["confidence"].as_f64().unwrap_or(f64::NAN)
                );
                return ExitCode::from(4);
            }
            ExitCode::SUCCESS
        }
        Ok(Err(e)) => {
            if cli.json {
                out(
                    &json!({"error": e.message, "kind": e.kind, "exit_code": e.exit_code()})
                        .to_string(),
                );
            }
            let _ = writeln!(std::io::stderr(), "error: {e}");
            ExitCode::from(e.exit_code())
        }
        Err(_) => ExitCode::from(1),
    }
}

/// A command line clap refuses: clap's text on stderr and exit code 2 (bad input), and with
/// `--json` among the arguments also the documented JSON object on stdout, so a caller parsing
/// stdout gets `{"error", "kind": "input", "exit_code": 2}` for a bad flag as for a bad file.
/// `--help` and `--version` print as usual and exit 0.
fn flag_error(e: clap::Error) -> ExitCode {
    use clap::error::ErrorKind;
    if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion) {
        let _ = e.print();
        return ExitCode::SUCCESS;
    }
    let json = std::env::args_os()
        .skip(1)
        .take_while(|a| a != "--")
        .any(|a| a == "--json");
    if json {
        // The first paragraph: clap's "error: …" line(s), without the usage and the tip.
        let text = e.render().to_string();
        let first = text.split("\n\n").next().unwrap_or(&text).trim();
        let message = first.strip_prefix("error: ").unwrap_or(first);
        out(&json!({"error": message, "kind": "input", "exit_code": 2}).to_string());
    }
    let _ = e.print();
    ExitCode::from(2)
}

/// Writes a line to stdout; a closed pipe (`| head`) is not an error worth a panic.
fn out(text: &str) {
    let mut stdout = std::io::stdout().lock();
    let _ = writeln!(stdout, "{text}").and_then(|_| stdout.flush());
}
