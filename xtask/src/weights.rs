//! `cargo xtask export-weights`: a training checkpoint's weights without its optimiser state.

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
