//! `cargo xtask train-pose` and `cargo xtask eval-pose`: thin wrappers of `ic_train::pose`
//! (training and evaluation of the `ic_pose` network on object-alone views rendered on the fly).

use anyhow::Result;

pub use ic_train::pose::{EvalArgs, TrainArgs};

pub fn train(args: TrainArgs) -> Result<()> {
    set_threads(args.threads);
    ic_train::install_signal_handlers();
    let control = ic_train::RunControl {
        checkpoint_secs: args.checkpoint_secs,
        ..Default::default()
    };
    ic_train::pose::train(&args, control)?;
    Ok(())
}

pub fn eval(args: EvalArgs) -> Result<()> {
    set_threads(args.threads);
    let report = ic_train::pose::eval(&args)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// Sets RAYON_NUM_THREADS (at least 1) when `threads` is given; call it before any other
/// thread exists (the bench uses it too).
pub(crate) fn set_threads(threads: Option<usize>) {
    // SAFETY: the commands call it first thing, before any other thread exists.
    unsafe { ic_train::set_threads(threads) };
}
