//! The long-running commands run from the release build.
//!
//! `cargo xtask` (the alias in `.cargo/config.toml`) runs a dev build: every crate at
//! opt-level 1–3 but with debug assertions and overflow checks on. That build suits the tests
//! and the chores, and it is the wrong one for what runs for hours or is timed. Measured one
//! after the other on the 2-core machine, same arguments and seed (`docs/decisions.md`, "The
//! long commands run from the release build"): a `cpu` pose training step 29 900 pairs/h in
//! the dev build against 36 200 in release; one 384×288 registration 38.7 against 23.3 ms; the
//! first 40 iterations of a clutter segmentation run 113 against 90 s (in steady state its
//! iterations take about the same in both).
//!
//! `main` calls [`rerun_in_release`] first for those commands (`Cmd::runs_long`: training,
//! evaluation, data generation, the full bench): from a dev build it replaces the process with
//! `cargo run --release -p xtask -- <the same arguments>` (same folder, so relative paths keep
//! their meaning; on Unix the same process, so Ctrl-C and `kill -INT` reach the training loop,
//! which saves a checkpoint first). `INCONTEXT_XTASK_DEV=1` keeps the dev build (e.g. to debug).

use anyhow::{Context, Result};

/// The environment variable that keeps a command in the dev build.
pub const STAY_IN_DEV: &str = "INCONTEXT_XTASK_DEV";

/// Whether this process should hand over to the release build: a dev build, and not asked to
/// stay (`stay` is [`STAY_IN_DEV`]'s value, set to anything but "" or "0").
fn hand_over(dev_build: bool, stay: Option<&str>) -> bool {
    dev_build && !matches!(stay, Some(v) if !v.is_empty() && v != "0")
}

/// From a dev build (unless [`STAY_IN_DEV`] is set), runs this command line again from the
/// release build and does not return when that started (on Unix the process is replaced;
/// elsewhere this one waits and exits with its status). Returns `Ok(())` at once in a release
/// build. Errors when cargo cannot be started.
pub fn rerun_in_release() -> Result<()> {
    let stay = std::env::var(STAY_IN_DEV).ok();
    if !hand_over(cfg!(debug_assertions), stay.as_deref()) {
        return Ok(());
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    eprintln!(
        "== a long command: running it from the release build (cargo run --release -p xtask; \
         {STAY_IN_DEV}=1 keeps the dev build)"
    );
    let mut cmd = std::process::Command::new(cargo);
    cmd.args(["run", "--release", "--quiet", "--package", "xtask", "--"])
        .args(std::env::args_os().skip(1));
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        let err = cmd.exec();
        Err(err).context("starting `cargo run --release -p xtask`")
    }
    #[cfg(not(unix))]
    {
        let status = cmd
            .status()
            .context("starting `cargo run --release -p xtask`")?;
        std::process::exit(status.code().unwrap_or(1));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dev_build_hands_over_unless_told_to_stay_and_a_release_build_never() {
        assert!(hand_over(true, None));
        assert!(hand_over(true, Some("")));
        assert!(hand_over(true, Some("0")));
        assert!(!hand_over(true, Some("1")));
        assert!(!hand_over(false, None));
        assert!(!hand_over(false, Some("1")));
    }
}
