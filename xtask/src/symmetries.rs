//! `cargo xtask symmetries`: which objects of a corpus have a rotational symmetry
//! (`ic_geometry::symmetry`), found on each normalised mesh — the objects whose rotation error
//! says nothing, left out of rotation-accuracy figures and scored by ADD-S / MSSD instead.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use ic_geometry::symmetry::{SymmetryOptions, find_symmetries};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::data::{CorpusArgs, open_corpus};

#[derive(Args, Debug)]
pub struct SymmetriesArgs {
    #[command(flatten)]
    pub corpus: CorpusArgs,
    /// Allowed surface residual above the sampling's own, as a fraction of the diameter.
    #[arg(long, default_value_t = SymmetryOptions::default().tolerance)]
    pub tolerance: f64,
    /// Surface samples tested per object (the reference gets 8× as many).
    #[arg(long, default_value_t = SymmetryOptions::default().samples)]
    pub samples: usize,
    /// Candidate axes over the hemisphere.
    #[arg(long, default_value_t = SymmetryOptions::default().axes)]
    pub axes: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write every object's result here (JSON).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: SymmetriesArgs) -> Result<()> {
    let (corpus, corpus_info) = open_corpus(&args.corpus, args.seed)?;
    let options = SymmetryOptions {
        tolerance: args.tolerance,
        samples: args.samples,
        axes: args.axes,
        seed: args.seed,
    };
    let bar = ProgressBar::new(corpus.len() as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} objects, {eta} left")
            .context("progress template")?,
    );
    let mut rows = Vec::new();
    let mut table = String::from(
        "| object | kind | motions | continuous axes | nearest residual / d | floor / d |\n\
         |---|---|---:|---:|---:|---:|\n",
    );
    for index in 0..corpus.len() {
        let object = corpus.object(index)?;
        let s = find_symmetries(&object.mesh, &options)
            .with_context(|| format!("object {}", object.id))?;
        table.push_str(&format!(
            "| {} | {} | {} | {} | {:.4} | {:.4} |\n",
            object.id,
            s.kind(),
            s.motions.len(),
            s.continuous_axes.len(),
            s.nearest_residual,
            s.floor
        ));
        rows.push(json!({
            "id": object.id, "symmetric": s.is_symmetric(), "kind": s.kind(),
            "symmetries": s,
        }));
        tracing::debug!(id = %object.id, kind = %s.kind(), "symmetries");
        bar.inc(1);
    }
    bar.finish_and_clear();
    print!("{table}");
    let symmetric = rows.iter().filter(|r| r["symmetric"] == true).count();
    println!("{symmetric} of {} objects have a symmetry", rows.len());
    if let Some(out) = &args.out {
        let doc = json!({
            "what": "rotational symmetries of each normalised mesh (ic_geometry::symmetry)",
            "corpus": corpus_info, "split": args.corpus.split, "options": options,
            "objects": rows,
        });
        let bytes = serde_json::to_vec_pretty(&doc)?;
        ic_geometry::io::write_atomic_with(out, |w| std::io::Write::write_all(w, &bytes), |e| e)
            .with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    Ok(())
}
