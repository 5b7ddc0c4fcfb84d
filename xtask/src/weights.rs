//! `cargo xtask export-weights`: a training checkpoint's weights without its optimiser state;
//! `cargo xtask average-weights`: the mean of several checkpoints' weights.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

#[derive(Args)]
pub struct ExportWeightsArgs {
    /// A training checkpoint (`latest.safetensors`, `final.safetensors`) of a pose or
    /// segmentation run.
    #[arg(long)]
    checkpoint: PathBuf,
    /// Where to write the weights-only file (atomically; what `incontext --pose-model` /
    /// `--seg-model` load).
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: ExportWeightsArgs) -> Result<()> {
    let size = |p: &std::path::Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    let before = size(&args.checkpoint);
    let kind = ic_train::export_weights(&args.checkpoint, &args.out)?;
    println!(
        "{:?} weights of {} ({} bytes) written to {} ({} bytes)",
        kind,
        args.checkpoint.display(),
        before,
        args.out.display(),
        size(&args.out)
    );
    Ok(())
}

#[derive(Args)]
pub struct AverageWeightsArgs {
    /// Checkpoints of one network (weights-only or training), e.g. a run's `latest.safetensors`
    /// copied at several iterations; repeat the flag. The first one's configuration is kept.
    #[arg(long = "checkpoint", required = true)]
    checkpoints: Vec<PathBuf>,
    /// Where to write the averaged weights-only file (atomically).
    #[arg(long)]
    out: PathBuf,
}

pub fn average(args: AverageWeightsArgs) -> Result<()> {
    let kind = ic_train::average_weights(&args.checkpoints, &args.out)?;
    println!(
        "{:?} weights: the mean of {} checkpoints written to {}",
        kind,
        args.checkpoints.len(),
        args.out.display()
    );
    Ok(())
}
