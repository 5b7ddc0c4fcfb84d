//! `cargo xtask fit-clutter-calibration`: the calibration of `incontext`'s confidence for poses
//! on instances the segmentation network chose (`models/verify-calibration-clutter.json`).
//!
//! Input: `candidates.jsonl` files of `incontext eval --dataset DIR --candidates N` on clutter
//! scenes of validation objects — every instance registered, whatever its verdict, with
//! `right` (ADD-S below 0.1 of the diameter of the nearest true instance of the object), its
//! `evidence` and its `verification` (`score`, `agreement`, …). The feature is the pipeline's
//! `segmentation_evidence`: evidence × agreement (clamped to [0, 1]); the fit is isotonic
//! (`ic_eval::Calibration::fit`). Prints how honest the verdict `ok` (calibrated confidence ≥
//! 0.9, score ≥ 0.05) is under the lines' own confidence and under the new one (in-sample),
//! and, with `--reliability FILE.svg|png`, draws both reliability diagrams.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use ic_eval::{Calibration, reliability_bins};
use serde_json::{Value, json};

#[derive(Args, Debug)]
pub struct FitClutterCalibrationArgs {
    /// `candidates.jsonl` files of `incontext eval --dataset … --candidates N` (repeatable or
    /// comma-separated).
    #[arg(long, required = true, value_delimiter = ',')]
    pub candidates: Vec<PathBuf>,
    /// Where to write the calibration (JSON, as `models/verify-calibration-clutter.json`).
    #[arg(long)]
    pub out: PathBuf,
    /// How the candidates were made (the commands), recorded in the file (repeatable).
    #[arg(long)]
    pub fitted_on: Vec<String>,
    /// Draw the reliability diagram of the lines' confidence and of the new one (.svg or .png).
    #[arg(long)]
    pub reliability: Option<PathBuf>,
}

/// The verdict `ok` needs this calibrated confidence (incontext's `VERIFIED_OK`) …
const OK: f64 = 0.9;
/// … and this raw render-and-compare score (incontext's `VERIFIED_FOUND`).
const FOUND: f64 = 0.05;

/// One registered instance: (segmentation evidence, score, confidence it was given, right).
type Sample = (f64, f64, f64, bool);

fn read_samples(path: &Path) -> Result<Vec<Sample>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let v: Value = serde_json::from_str(line)
            .with_context(|| format!("{} line {}: not JSON", path.display(), i + 1))?;
        let field = |name: &str, x: Option<f64>| {
            x.with_context(|| format!("{} line {}: no number \"{name}\"", path.display(), i + 1))
        };
        let right = v["right"]
            .as_bool()
            .with_context(|| format!("{} line {}: no boolean \"right\"", path.display(), i + 1))?;
        let evidence = field("evidence", v["evidence"].as_f64())?;
        let agreement = field(
            "verification.agreement",
            v["verification"]["agreement"].as_f64(),
        )?;
        let score = field("verification.score", v["verification"]["score"].as_f64())?;
        let confidence = field("confidence", v["confidence"].as_f64())?;
        out.push((
            (evidence * agreement).clamp(0.0, 1.0),
            score,
            confidence,
            right,
        ));
    }
    Ok(out)
}

/// (`ok` count, right among them, right overall) when `ok` = confidence ≥ [`OK`] and score ≥
/// [`FOUND`].
fn ok_counts(samples: &[Sample], confidence: impl Fn(&Sample) -> f64) -> (usize, usize, usize) {
    let ok: Vec<&Sample> = samples
        .iter()
        .filter(|s| confidence(s) >= OK && s.1 >= FOUND)
        .collect();
    (
        ok.len(),
        ok.iter().filter(|s| s.3).count(),
        samples.iter().filter(|s| s.3).count(),
    )
}

pub fn run(args: FitClutterCalibrationArgs) -> Result<()> {
    let mut samples = Vec::new();
    for p in &args.candidates {
        samples.extend(read_samples(p)?);
    }
    if samples.is_empty() {
        bail!("no candidate lines in {:?}", args.candidates);
    }
    let fit: Vec<(f64, bool)> = samples.iter().map(|s| (s.0, s.3)).collect();
    let c = Calibration::fit(&fit).map_err(anyhow::Error::msg)?;
    let report = |name: &str, (ok, right_ok, right): (usize, usize, usize)| {
        println!(
            "{name}: ok {ok} of {n}, right among ok {right_ok} (precision {:.3}), ok among right {:.3}",
            right_ok as f64 / ok.max(1) as f64,
            right_ok as f64 / right.max(1) as f64,
            n = samples.len(),
        )
    };
    let before = ok_counts(&samples, |s| s.2);
    let after = ok_counts(&samples, |s| c.apply(s.0));
    report("the lines' confidence", before);
    report("clutter calibration (in-sample)", after);
    let doc = json!({
        "what": "isotonic calibration of incontext's segmentation evidence (evidence × verification agreement) on network-segmented instances in clutter: P(ADD-S < 0.1 d of a true instance | evidence)",
        "fitted_on": args.fitted_on,
        "candidate_files": args.candidates,
        "samples": samples.len(),
        "right": samples.iter().filter(|s| s.3).count(),
        "add_s_fraction": 0.1,
        "in_sample_ok": {"before": {"ok": before.0, "right": before.1}, "after": {"ok": after.0, "right": after.1}},
        "knots": c.knots,
    });
    ic_geometry::io::write_atomic_with(
        &args.out,
        |w| std::io::Write::write_all(w, serde_json::to_string_pretty(&doc)?.as_bytes()),
        |e| e,
    )
    .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "wrote {} ({} knots from {} samples)",
        args.out.display(),
        c.knots.len(),
        samples.len()
    );
    if let Some(p) = &args.reliability {
        let given: Vec<(f64, bool)> = samples.iter().map(|s| (s.2, s.3)).collect();
        let calibrated: Vec<(f64, bool)> = samples.iter().map(|s| (c.apply(s.0), s.3)).collect();
        ic_eval::calibration::plot_reliability(
            p,
            "Confidence in clutter (ADD-S < 0.1 d)",
            &[
                (
                    "the lines' confidence".to_string(),
                    reliability_bins(&given, 10),
                ),
                (
                    "clutter calibration (in-sample)".to_string(),
                    reliability_bins(&calibrated, 10),
                ),
            ],
        )
        .with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_multiply_evidence_by_agreement_and_bad_lines_name_the_file() {
        let dir = std::env::temp_dir().join(format!("xtask-clutter-cal-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.jsonl");
        std::fs::write(
            &good,
            "{\"right\":true,\"evidence\":0.8,\"confidence\":0.95,\"verification\":{\"agreement\":0.5,\"score\":0.8}}\n",
        )
        .unwrap();
        let s = read_samples(&good).unwrap();
        assert_eq!(s.len(), 1);
        assert!((s[0].0 - 0.4).abs() < 1e-12);
        let bad = dir.join("bad.jsonl");
        std::fs::write(&bad, "{\"right\":true}\n").unwrap();
        let e = read_samples(&bad).unwrap_err().to_string();
        assert!(e.contains("bad.jsonl") && e.contains("evidence"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn ok_counts_need_both_the_confidence_and_the_score() {
        let s = [
            (0.0, 0.9, 0.95, true),
            (0.0, 0.01, 0.95, true),
            (0.0, 0.9, 0.5, false),
        ];
        assert_eq!(ok_counts(&s, |x| x.2), (1, 1, 2));
    }
}
