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
    /// Pose networks: write the configuration attending over this many farthest-point
    /// samples of each cloud (`all`: every point) with the same weights; the checkpoint may
    /// then be weights-only too.
    #[arg(long)]
    pooled_keys: Option<String>,
}

pub fn run(args: ExportWeightsArgs) -> Result<()> {
    let size = |p: &std::path::Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    let before = size(&args.checkpoint);
    if let Some(keys) = &args.pooled_keys {
        let keys = match keys.as_str() {
            "all" => None,
            n => Some(n.parse::<usize>().map_err(|_| {
                anyhow::anyhow!("--pooled-keys {n:?}: a number of keys per cloud, or all")
            })?),
        };
        ic_train::set_pooled_keys(&args.checkpoint, &args.out, keys)?;
        println!(
            "pose weights of {} ({} bytes) written to {} ({} bytes), pooled keys {keys:?}",
            args.checkpoint.display(),
            before,
            args.out.display(),
            size(&args.out)
        );
        return Ok(());
    }
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
