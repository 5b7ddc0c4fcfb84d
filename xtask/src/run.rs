//! The scaffolding that `train-pose` and `train-seg` share: the progress bar, the running
//! averages, log lines, the best-checkpoint record, and periodic / interrupt checkpoints.

use std::path::Path;
use std::sync::atomic::Ordering;
use std::time::Instant;

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};

use crate::pose::STOP;

/// A progress bar over `total` iterations starting at `start`.
pub fn progress_bar(total: u64, start: u64) -> Result<ProgressBar> {
    let bar = ProgressBar::new(total);
    bar.set_position(start);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} {msg} ETA {eta_precise}",
        )?
        .progress_chars("=> "),
    );
    Ok(bar)
}

/// Exponential moving average (weight 0.05 on the new value); the first value starts it.
pub fn ema(avg: f64, x: f64) -> f64 {
    if avg.is_nan() {
        x
    } else {
        0.95 * avg + 0.05 * x
    }
}

/// Whether stderr is a terminal (the bar shows progress) or a log (lines do).
pub fn interactive() -> bool {
    std::io::IsTerminal::is_terminal(&std::io::stderr())
}

/// A line above the bar on a terminal, a plain line in a log.
pub fn report(bar: &ProgressBar, line: String) {
    if interactive() {
        bar.println(line);
    } else {
        eprintln!("{line}");
    }
}

/// The validation score of `best.json` when resuming (so a resumed run only replaces a better
/// checkpoint), −∞ otherwise.
pub fn previous_best_score(best_json: &Path, resume: bool) -> f64 {
    std::fs::read_to_string(best_json)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["score"].as_f64())
        .filter(|_| resume)
        .unwrap_or(f64::NEG_INFINITY)
}

/// Records the validation that selected the best weights.
pub fn write_best(
    best_json: &Path,
    iteration: u64,
    score: f64,
    validation: &impl serde::Serialize,
) -> Result<()> {
    let j = serde_json::json!({"iteration": iteration, "score": score, "validation": validation});
    std::fs::write(best_json, serde_json::to_string_pretty(&j)?)?;
    Ok(())
}

/// Saves a resumable checkpoint with `save` at the last iteration, on Ctrl-C / SIGTERM, or
/// every `every_secs`; returns whether the run was interrupted (the caller then stops).
pub fn checkpoint(
    last: bool,
    last_ckpt: &mut Instant,
    every_secs: u64,
    save: impl FnOnce() -> Result<()>,
) -> Result<bool> {
    let stop = STOP.load(Ordering::SeqCst);
    if last || stop || last_ckpt.elapsed().as_secs() >= every_secs {
        save()?;
        *last_ckpt = Instant::now();
    }
    Ok(stop)
}
