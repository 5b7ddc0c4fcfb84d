//! `cargo xtask fit-clutter-calibration`: the confidence of `incontext`'s poses on instances
//! the segmentation network chose among several (`models/verify-calibration-clutter.json`).
//!
//! Input: `candidates.jsonl` files of `incontext eval --dataset DIR --candidates N` on clutter
//! scenes of validation objects — every instance registered, whatever its verdict, with
//! `right` (ADD-S below 0.1 of the diameter of the nearest true instance of the object) and
//! the numbers `ic_eval::ClutterFeatures` reads (the verification, the whole view, the
//! instance, the segmentation). The fit: a logistic regression of `right` on the `--features`
//! (standardised, L2 penalty `--l2`; `ic_eval::Logistic`), then an isotonic calibration of its
//! output (`ic_eval::Calibration::fit`). Prints how honest the verdict `ok` (calibrated
//! confidence ≥ 0.9, score ≥ 0.05) is under the lines' own confidence and under the new one
//! (in-sample), and with two files or more the same for each file under a fit on the others
//! (held out); with `--reliability FILE.svg|png` it draws both reliability diagrams. With
//! `--replay` it also replays `register`'s search on every target of each file under each
//! confidence (each file held out when there are several): the target's instances in rank
//! order, the first `--tries`, stopping at the first `ok`, the best by verdict, confidence and
//! score kept — how many targets the choice gets right, against how many have a right pose
//! among the tried instances (`docs/decisions.md`'s tables of the confidence's features).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use ic_eval::calibration::{VERIFIED_FOUND, VERIFIED_OK};
use ic_eval::{
    Calibration, ClutterConfidence, ClutterFeatures, Logistic, LogisticOptions, reliability_bins,
};
use serde_json::{Value, json};

/// The features the shipped confidence weighs (`docs/decisions.md`, "A confidence in clutter
/// from several numbers").
pub const DEFAULT_FEATURES: &str = "evidence_x_agreement,evidence,rival_score,coverage,agreement,misfit,violation,whole_agreement,ln_voxels";

#[derive(Args, Debug)]
pub struct FitClutterCalibrationArgs {
    /// `candidates.jsonl` files of `incontext eval --dataset … --candidates N` (repeatable or
    /// comma-separated).
    #[arg(long, required = true, value_delimiter = ',')]
    pub candidates: Vec<PathBuf>,
    /// Where to write the calibration (JSON, as `models/verify-calibration-clutter.json`).
    #[arg(long)]
    pub out: PathBuf,
    /// The features of the logistic model (names of `ic_eval::clutter::FEATURE_NAMES`).
    #[arg(long, value_delimiter = ',', default_value = DEFAULT_FEATURES)]
    pub features: Vec<String>,
    /// λ of the logistic model's penalty ½λ‖w‖² on the standardised weights.
    #[arg(long, default_value_t = 1.0)]
    pub l2: f64,
    /// How the candidates were made (the commands), recorded in the file (repeatable).
    #[arg(long)]
    pub fitted_on: Vec<String>,
    /// Draw the reliability diagram of the lines' confidence and of the new one (.svg or .png).
    #[arg(long)]
    pub reliability: Option<PathBuf>,
    /// Also replay `register`'s search on every target under each confidence (see the module
    /// documentation); the lines must carry `scene_id`, `im_id`, `obj_id` and the instance's
    /// `rank`, as `eval --candidates` writes them.
    #[arg(long)]
    pub replay: bool,
    /// With `--replay`: the instances `register` tries (its `--instance-tries`).
    #[arg(long, default_value_t = 8)]
    pub tries: usize,
}

/// `incontext`'s verdict of a verified pose of calibrated `confidence` and raw
/// render-and-compare `score`, at its default thresholds: 0 not found (score below
/// [`VERIFIED_FOUND`]), 2 `ok` (confidence ≥ [`VERIFIED_OK`]), else 1 uncertain.
fn verdict(confidence: f64, score: f64) -> u8 {
    if score < VERIFIED_FOUND {
        0
    } else if confidence >= VERIFIED_OK {
        2
    } else {
        1
    }
}

/// The target a line was registered for: its scene, image and object ids.
type TargetKey = (u64, u64, u64);

/// One registered instance.
#[derive(Clone, Copy)]
struct Sample {
    features: ClutterFeatures,
    /// The confidence the line was given.
    confidence: f64,
    right: bool,
    /// The target it was registered for (scene, image, object) and its rank among the
    /// target's instances, when the line says them.
    target: Option<(TargetKey, u64)>,
}

impl Sample {
    fn score(&self) -> f64 {
        self.features.verification.score
    }
}

fn read_samples(path: &Path) -> Result<Vec<Sample>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out = Vec::new();
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let at = || format!("{} line {}", path.display(), i + 1);
        let v: Value = serde_json::from_str(line).with_context(|| format!("{}: not JSON", at()))?;
        let right = v["right"]
            .as_bool()
            .with_context(|| format!("{}: no boolean \"right\"", at()))?;
        let confidence = v["confidence"]
            .as_f64()
            .with_context(|| format!("{}: no number \"confidence\"", at()))?;
        let id = |k: &str| v[k].as_u64();
        let target = match (
            id("scene_id"),
            id("im_id"),
            id("obj_id"),
            v["instance"]["rank"].as_u64(),
        ) {
            (Some(s), Some(i), Some(o), Some(r)) => Some(((s, i, o), r)),
            _ => None,
        };
        let features: ClutterFeatures = serde_json::from_value(v)
            .with_context(|| format!("{}: not a registration's numbers", at()))?;
        out.push(Sample {
            features,
            confidence,
            right,
            target,
        });
    }
    Ok(out)
}

/// The logistic model on `samples`, then the isotonic calibration of its output.
fn fit(samples: &[Sample], features: &[String], l2: f64) -> Result<ClutterConfidence> {
    let x = samples
        .iter()
        .map(|s| s.features.values(features))
        .collect::<Result<Vec<_>, String>>()
        .map_err(anyhow::Error::msg)?;
    let right: Vec<bool> = samples.iter().map(|s| s.right).collect();
    let options = LogisticOptions {
        l2,
        ..LogisticOptions::default()
    };
    let model =
        Logistic::fit(features.to_vec(), &x, &right, options).map_err(anyhow::Error::msg)?;
    let evidence: Vec<(f64, bool)> = x
        .iter()
        .zip(&right)
        .map(|(x, &r)| (model.probability(x), r))
        .collect();
    let calibration = Calibration::fit(&evidence).map_err(anyhow::Error::msg)?;
    Ok(ClutterConfidence {
        evidence_model: model,
        calibration,
    })
}

/// (`ok` count, right among them, right overall) under `confidence` ([`verdict`] 2).
fn ok_counts(samples: &[Sample], confidence: impl Fn(&Sample) -> f64) -> (usize, usize, usize) {
    let ok: Vec<&Sample> = samples
        .iter()
        .filter(|s| verdict(confidence(s), s.score()) == 2)
        .collect();
    (
        ok.len(),
        ok.iter().filter(|s| s.right).count(),
        samples.iter().filter(|s| s.right).count(),
    )
}

/// `register`'s search replayed on every target of one file (see the module documentation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Replay {
    targets: usize,
    /// Targets whose kept pose is right.
    right: usize,
    /// Targets with a right pose among the tried instances.
    right_tried: usize,
    /// Targets whose kept pose is `ok`, and right among them.
    ok: usize,
    ok_right: usize,
}

impl std::ops::AddAssign for Replay {
    fn add_assign(&mut self, o: Replay) {
        self.targets += o.targets;
        self.right += o.right;
        self.right_tried += o.right_tried;
        self.ok += o.ok;
        self.ok_right += o.ok_right;
    }
}

/// Replays the search on `samples` (one file's lines) with `confidence`: per target, its
/// instances by rank, the first `tries`, stopping at the first `ok` ([`verdict`]); the kept
/// pose is the tried one with the highest (verdict, confidence,
/// score), the first on a tie, as `register` sorts. Errors on a line without its target.
fn replay(
    samples: &[Sample],
    tries: usize,
    confidence: impl Fn(&Sample) -> f64,
    file: &Path,
) -> Result<Replay> {
    let mut targets: std::collections::BTreeMap<TargetKey, Vec<(u64, &Sample)>> =
        Default::default();
    for s in samples {
        let (key, rank) = s.target.with_context(|| {
            format!(
                "{}: a line without scene_id, im_id, obj_id and instance.rank cannot be replayed",
                file.display()
            )
        })?;
        targets.entry(key).or_default().push((rank, s));
    }
    let mut out = Replay::default();
    for (_, mut list) in targets {
        list.sort_by_key(|(rank, _)| *rank);
        let mut best: Option<(u8, f64, f64, bool)> = None;
        let mut right_tried = false;
        for (_, s) in list.iter().take(tries.max(1)) {
            let c = confidence(s);
            let v = verdict(c, s.score());
            right_tried |= s.right;
            let better = best.is_none_or(|(bv, bc, bs, _)| {
                (v, c, s.score())
                    .partial_cmp(&(bv, bc, bs))
                    .is_some_and(|o| o.is_gt())
            });
            if better {
                best = Some((v, c, s.score(), s.right));
            }
            if v == 2 {
                break;
            }
        }
        out.targets += 1;
        out.right_tried += usize::from(right_tried);
        if let Some((verdict, _, _, right)) = best {
            out.right += usize::from(right);
            out.ok += usize::from(verdict == 2);
            out.ok_right += usize::from(verdict == 2 && right);
        }
    }
    Ok(out)
}

fn report_replay(name: &str, r: Replay) {
    println!(
        "{name}: replayed search right on {} of {} targets (a right pose among the tried: {}), ok {} (right {})",
        r.right, r.targets, r.right_tried, r.ok, r.ok_right
    )
}

fn report(name: &str, n: usize, (ok, right_ok, right): (usize, usize, usize)) {
    println!(
        "{name}: ok {ok} of {n}, right among ok {right_ok} (precision {:.3}), ok among right {:.3}",
        right_ok as f64 / ok.max(1) as f64,
        right_ok as f64 / right.max(1) as f64,
    )
}

pub fn run(args: FitClutterCalibrationArgs) -> Result<()> {
    let mut per_file = Vec::new();
    for p in &args.candidates {
        per_file.push(read_samples(p)?);
    }
    let samples: Vec<Sample> = per_file.iter().flatten().copied().collect();
    if samples.is_empty() {
        bail!("no candidate lines in {:?}", args.candidates);
    }
    let c = fit(&samples, &args.features, args.l2)?;
    let before = ok_counts(&samples, |s| s.confidence);
    let after = ok_counts(&samples, |s| c.apply(&s.features));
    report("the lines' confidence", samples.len(), before);
    report("clutter confidence (in-sample)", samples.len(), after);
    if args.replay && per_file.len() == 1 {
        let file = &args.candidates[0];
        let lines = replay(&samples, args.tries, |s| s.confidence, file)?;
        report_replay("the lines' confidence", lines);
        let fitted = replay(&samples, args.tries, |s| c.apply(&s.features), file)?;
        report_replay("clutter confidence (in-sample)", fitted);
    }
    let (mut lines_total, mut held_total) = (Replay::default(), Replay::default());
    if per_file.len() > 1 {
        for (i, held) in per_file.iter().enumerate() {
            let others: Vec<Sample> = per_file
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .flat_map(|(_, f)| f.iter().copied())
                .collect();
            let h = fit(&others, &args.features, args.l2)?;
            let name = args.candidates[i].display();
            report(
                &format!("{name}, the lines' confidence"),
                held.len(),
                ok_counts(held, |s| s.confidence),
            );
            report(
                &format!("{name}, held out (fitted on the other files)"),
                held.len(),
                ok_counts(held, |s| h.apply(&s.features)),
            );
            if args.replay {
                let file = &args.candidates[i];
                let lines = replay(held, args.tries, |s| s.confidence, file)?;
                let fitted = replay(held, args.tries, |s| h.apply(&s.features), file)?;
                report_replay(&format!("{name}, the lines' confidence"), lines);
                report_replay(&format!("{name}, held out"), fitted);
                lines_total += lines;
                held_total += fitted;
            }
        }
        if args.replay {
            report_replay("every file, the lines' confidence", lines_total);
            report_replay("every file, held out", held_total);
        }
    }
    let m = &c.evidence_model;
    println!(
        "weights (standardised): {}; bias {:.3}",
        m.features
            .iter()
            .zip(&m.weights)
            .map(|(f, w)| format!("{f} {w:.3}"))
            .collect::<Vec<_>>()
            .join(", "),
        m.bias
    );
    let doc = json!({
        "what": "the confidence of incontext's poses on network-segmented instances in clutter: an isotonic calibration (knots) of a logistic model's output (evidence_model) over the registration's numbers: P(ADD-S < 0.1 d of a true instance | numbers)",
        "fitted_on": args.fitted_on,
        "candidate_files": args.candidates,
        "samples": samples.len(),
        "right": samples.iter().filter(|s| s.right).count(),
        "add_s_fraction": 0.1,
        "l2": args.l2,
        "in_sample_ok": {"before": {"ok": before.0, "right": before.1}, "after": {"ok": after.0, "right": after.1}},
        "evidence_model": m,
        "knots": c.calibration.knots,
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
        c.calibration.knots.len(),
        samples.len()
    );
    if let Some(p) = &args.reliability {
        let given: Vec<(f64, bool)> = samples.iter().map(|s| (s.confidence, s.right)).collect();
        let calibrated: Vec<(f64, bool)> = samples
            .iter()
            .map(|s| (c.apply(&s.features), s.right))
            .collect();
        ic_eval::calibration::plot_reliability(
            p,
            "Confidence in clutter (ADD-S < 0.1 d)",
            &[
                (
                    "the lines' confidence".to_string(),
                    reliability_bins(&given, 10),
                ),
                (
                    "clutter confidence (in-sample)".to_string(),
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

    fn line(right: bool, evidence: f64, agreement: f64, score: f64) -> String {
        format!(
            "{{\"right\":{right},\"evidence\":{evidence},\"rival_score\":0.0,\"confidence\":0.5,\"object_voxels\":100,\
             \"verification\":{{\"score\":{score},\"coverage\":{score},\"agreement\":{agreement},\"visible_agreement\":1.0,\"misfit\":0.2,\"violation\":0.0}},\
             \"whole_view\":null,\"instance\":{{\"size_ratio\":0.8,\"shape_distance\":0.1,\"truncated\":false,\"cut\":false}},\
             \"segmentation\":{{\"pixels\":500,\"score\":0.7}}}}\n"
        )
    }

    #[test]
    fn the_fitted_confidence_rises_with_the_evidence_and_bad_lines_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let good = dir.path().join("good.jsonl");
        let mut text = String::new();
        for i in 0..40 {
            let e = i as f64 / 40.0;
            // Right mostly at high evidence, with a few exceptions both ways.
            let right = (e > 0.6) ^ (i % 7 == 0);
            text.push_str(&line(right, e, 0.9, e));
        }
        std::fs::write(&good, text).unwrap();
        let s = read_samples(&good).unwrap();
        assert_eq!(s.len(), 40);
        let features: Vec<String> = ["evidence", "agreement"].map(String::from).to_vec();
        let c = fit(&s, &features, 1.0).unwrap();
        assert!(c.apply(&s[39].features) > c.apply(&s[5].features));
        assert!((0.0..=1.0).contains(&c.apply(&s[20].features)));
        // The written file reads back as the pipeline reads it.
        let out = dir.path().join("cal.json");
        run(FitClutterCalibrationArgs {
            candidates: vec![good.clone(), good.clone()],
            out: out.clone(),
            features: features.clone(),
            l2: 1.0,
            fitted_on: vec![],
            reliability: None,
            replay: false,
            tries: 8,
        })
        .unwrap();
        let back = ClutterConfidence::from_json(&std::fs::read_to_string(&out).unwrap()).unwrap();
        assert_eq!(back.evidence_model.features, features);
        let bad = dir.path().join("bad.jsonl");
        std::fs::write(&bad, "{\"right\":true,\"confidence\":0.5}\n").unwrap();
        let e = format!("{:#}", read_samples(&bad).err().unwrap());
        assert!(e.contains("bad.jsonl"), "{e}");
        let unknown = fit(&s, &["colour".to_string()], 1.0)
            .err()
            .unwrap()
            .to_string();
        assert!(unknown.contains("colour"), "{unknown}");
    }

    /// A sample of this raw score, line confidence and rightness, registered for `target`.
    fn sample(
        score: f64,
        confidence: f64,
        right: bool,
        target: Option<(TargetKey, u64)>,
    ) -> Sample {
        Sample {
            features: ClutterFeatures {
                verification: ic_eval::clutter::CropScore {
                    score,
                    ..Default::default()
                },
                ..Default::default()
            },
            confidence,
            right,
            target,
        }
    }

    #[test]
    fn ok_counts_need_both_the_confidence_and_the_score() {
        let s = [
            sample(0.9, 0.95, true, None),
            sample(0.01, 0.95, true, None),
            sample(0.9, 0.5, false, None),
        ];
        assert_eq!(ok_counts(&s, |x| x.confidence), (1, 1, 2));
    }

    #[test]
    fn the_replay_stops_at_the_first_ok_keeps_the_best_tried_and_needs_the_target() {
        // (target, rank, confidence, score, right)
        let sample = |t: u64, rank: u64, confidence: f64, score: f64, right: bool| {
            sample(score, confidence, right, Some(((t, 0, 1), rank)))
        };
        let s = [
            // Target 0: rank 1 is ok and wrong, so the right rank 2 is never tried.
            sample(0, 2, 0.95, 0.9, true),
            sample(0, 0, 0.5, 0.9, false),
            sample(0, 1, 0.92, 0.9, false),
            // Target 1: nothing ok; the best confidence (rank 1, right) is kept.
            sample(1, 0, 0.3, 0.9, false),
            sample(1, 1, 0.6, 0.5, true),
            // Target 2: a confident pose with too low a score is not ok; the right pose at
            // rank 3 lies beyond two tries.
            sample(2, 0, 0.95, 0.01, false),
            sample(2, 1, 0.2, 0.9, false),
            sample(2, 3, 0.99, 0.9, true),
        ];
        let file = Path::new("c.jsonl");
        let r = replay(&s, 2, |x| x.confidence, file).unwrap();
        assert_eq!(
            r,
            Replay {
                targets: 3,
                right: 1,
                right_tried: 1,
                ok: 1,
                ok_right: 0
            }
        );
        // With three tries target 2 reaches its right, ok pose.
        let r = replay(&s, 3, |x| x.confidence, file).unwrap();
        assert_eq!((r.right, r.right_tried, r.ok, r.ok_right), (2, 2, 2, 1));
        let mut lost = s;
        lost[4].target = None;
        let e = format!(
            "{:#}",
            replay(&lost, 2, |x| x.confidence, file).unwrap_err()
        );
        assert!(e.contains("c.jsonl") && e.contains("instance.rank"), "{e}");
    }
}
