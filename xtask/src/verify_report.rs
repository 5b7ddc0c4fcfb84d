//! `cargo xtask verify-report`: how right, how fast and how honest are the poses of
//! `incontext eval --cases` on exported view cases.
//!
//! For each `--set NAME=CASES:RESULTS[,RESULTS…]` and each method in the results: rotation
//! accuracy at 15°, ADD-S < 0.1·diameter (the model points are the case's `source.ply`,
//! normalised units), the verdict counts, the precision of `ok` (right among `ok`) and its
//! recall (`ok` among right), the median seconds. Writes a markdown table (stdout and
//! `--markdown`), the numbers as JSON (`--json`), a reliability diagram of the lines'
//! `confidence` (`--reliability FILE.svg|png`, one series per set and method with a verdict),
//! and with `--fit-calibration FILE` the isotonic calibration of the raw render-and-compare
//! score (`details.verification.score`, from `eval --details`) of the verified methods.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use ic_eval::{Calibration, ReliabilityBin, reliability_bins};
use ic_geometry::Pose;
use serde_json::{Value, json};

#[derive(Args, Debug)]
pub struct VerifyReportArgs {
    /// NAME=CASES_DIR:RESULTS.jsonl[,RESULTS.jsonl…] (repeatable).
    #[arg(long = "set", required = true)]
    pub sets: Vec<String>,
    /// Write the table here as well (markdown).
    #[arg(long)]
    pub markdown: Option<PathBuf>,
    /// Write every number as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Draw the reliability diagram of the `-verify` methods' confidences (.svg or .png;
    /// repeatable).
    #[arg(long)]
    pub reliability: Vec<PathBuf>,
    /// Fit the isotonic calibration of the evidence (`details.evidence`) of the methods ending
    /// in `-verify` on these sets, and write it here (JSON).
    #[arg(long)]
    pub fit_calibration: Option<PathBuf>,
    /// Sets named `LABEL@X` (X a number, e.g. the rotation count K), each with one method's
    /// results: draw acc@15° against X, one line per label, here (.svg or .png; repeatable).
    #[arg(long)]
    pub curve: Vec<PathBuf>,
    /// A pose is right when ADD-S is below this fraction of the object's diameter.
    #[arg(long, default_value_t = 0.1)]
    pub add_s_fraction: f64,
}

/// One scored line.
struct Scored {
    rotation_deg: f64,
    add_s_rel: f64,
    confidence: Option<f64>,
    verdict: Option<String>,
    raw_score: Option<f64>,
    seconds: f64,
}

struct Case {
    truth: Pose,
    points: Vec<ic_geometry::glam::Vec3>,
    diameter: f64,
}

fn parse_set(s: &str) -> Result<(String, PathBuf, Vec<PathBuf>)> {
    let (name, rest) = s
        .split_once('=')
        .with_context(|| format!("--set {s:?}: expected NAME=CASES:RESULTS"))?;
    let (cases, results) = rest
        .split_once(':')
        .with_context(|| format!("--set {s:?}: expected NAME=CASES:RESULTS"))?;
    Ok((
        name.to_string(),
        PathBuf::from(cases),
        results.split(',').map(PathBuf::from).collect(),
    ))
}

/// The truth (`gt.json`, via `ic_eval::cases`) and the model points (`source.ply`) of every
/// case folder under `dir`.
fn read_cases(dir: &Path) -> Result<BTreeMap<String, Case>> {
    let mut out = BTreeMap::new();
    // `dir` may be a single case folder, as `read_case_truths` allows.
    let single = dir.join("gt.json").is_file();
    for t in ic_eval::cases::read_case_truths(dir)? {
        let case_dir = if single {
            dir.to_path_buf()
        } else {
            dir.join(&t.case)
        };
        let points = ic_geometry::io::read_ply_cloud(case_dir.join("source.ply"))?.points;
        let diameter = ic_eval::diameter(&points);
        out.insert(
            t.case,
            Case {
                truth: t.pose,
                points,
                diameter,
            },
        );
    }
    Ok(out)
}

fn score_lines(
    cases: &BTreeMap<String, Case>,
    results: &[PathBuf],
) -> Result<BTreeMap<String, BTreeMap<String, Scored>>> {
    let mut by_method: BTreeMap<String, BTreeMap<String, Scored>> = BTreeMap::new();
    for path in results {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        for (i, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            let v: Value = serde_json::from_str(line)
                .with_context(|| format!("{}:{}", path.display(), i + 1))?;
            let case = v["case"].as_str().unwrap_or_default().to_string();
            let method = v["method"].as_str().unwrap_or_default().to_string();
            let c = cases.get(&case).with_context(|| {
                format!(
                    "{}:{}: case {case:?} is not in the set",
                    path.display(),
                    i + 1
                )
            })?;
            let pose = (v["ok"].as_bool() == Some(true))
                .then(|| {
                    let r: [[f64; 3]; 3] = serde_json::from_value(v["R"].clone()).ok()?;
                    let t: [f64; 3] = serde_json::from_value(v["t"].clone()).ok()?;
                    Pose::from_row_major(r, t).ok()
                })
                .flatten();
            let (rotation_deg, add_s_rel) = match pose {
                Some(p) => (
                    ic_eval::rotation_error_deg(&p, &c.truth),
                    ic_eval::add_s(&p, &c.truth, &c.points)? / c.diameter.max(1e-12),
                ),
                None => (180.0, f64::INFINITY),
            };
            let scored = Scored {
                rotation_deg,
                add_s_rel,
                confidence: v["confidence"].as_f64(),
                verdict: v["verdict"].as_str().map(str::to_owned),
                raw_score: v["details"]["evidence"].as_f64(),
                seconds: v["seconds"].as_f64().unwrap_or(f64::NAN),
            };
            if by_method
                .entry(method.clone())
                .or_default()
                .insert(case.clone(), scored)
                .is_some()
            {
                bail!(
                    "{}: two lines for case {case}, method {method}",
                    path.display()
                );
            }
        }
    }
    Ok(by_method)
}

pub fn run(args: VerifyReportArgs) -> Result<()> {
    let mut rows = Vec::new();
    let mut reliability: Vec<(String, Vec<ReliabilityBin>)> = Vec::new();
    let mut calibration_samples: Vec<(f64, bool)> = Vec::new();
    let mut curves: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    let mut table = String::from(
        "| set | method | cases | acc@15° | ADD-S<0.1d | ok | uncertain | not_found | ok precision | ok recall | median s |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for spec in &args.sets {
        let (name, dir, results) = parse_set(spec)?;
        let cases = read_cases(&dir)?;
        let scored = score_lines(&cases, &results)?;
        for (method, lines) in &scored {
            let n = cases.len();
            // A case without a line counts as a failure.
            let right = |s: &Scored| s.add_s_rel < args.add_s_fraction;
            let acc15 = lines.values().filter(|s| s.rotation_deg < 15.0).count() as f64 / n as f64;
            let adds = lines.values().filter(|s| right(s)).count() as f64 / n as f64;
            let count = |v: &str| {
                lines
                    .values()
                    .filter(|s| s.verdict.as_deref() == Some(v))
                    .count()
            };
            let (ok, unc, nf) = (count("ok"), count("uncertain"), count("not_found"));
            let ok_right = lines
                .values()
                .filter(|s| s.verdict.as_deref() == Some("ok") && right(s))
                .count();
            let n_right = lines.values().filter(|s| right(s)).count();
            let precision = ok_right as f64 / ok.max(1) as f64;
            let recall = ok_right as f64 / n_right.max(1) as f64;
            let secs: Vec<f64> = lines
                .values()
                .map(|s| s.seconds)
                .filter(|s| s.is_finite())
                .collect();
            let median = ic_eval::median(&secs);
            table.push_str(&format!(
                "| {name} | {method} | {n} | {acc15:.3} | {adds:.3} | {ok} | {unc} | {nf} | {precision:.3} | {recall:.3} | {median:.3} |\n"
            ));
            let samples: Vec<(f64, bool)> = lines
                .values()
                .filter_map(|s| s.confidence.map(|c| (c, right(s))))
                .collect();
            let bins = reliability_bins(&samples, 10);
            let ece = ic_eval::expected_calibration_error(&bins);
            // Only the verified methods' confidence is a calibrated probability.
            if method.ends_with("-verify") {
                reliability.push((
                    format!("{name} {method} (n {}, ECE {ece:.3})", samples.len()),
                    bins.clone(),
                ));
            }
            if method.ends_with("-verify") {
                calibration_samples.extend(
                    lines
                        .values()
                        .filter_map(|s| s.raw_score.map(|c| (c, right(s)))),
                );
            }
            if let Some((label, x)) = name.rsplit_once('@')
                && let Ok(x) = x.parse::<f64>()
            {
                curves
                    .entry(label.to_string())
                    .or_default()
                    .push((x, acc15));
            }
            rows.push(json!({
                "set": name, "cases_dir": dir, "results": results, "method": method, "cases": n,
                "lines": lines.len(), "rotation_acc_15": acc15, "add_s_acc": adds,
                "add_s_fraction": args.add_s_fraction, "ok": ok, "uncertain": unc,
                "not_found": nf, "ok_precision": precision, "ok_recall": recall,
                "seconds_median": median, "expected_calibration_error": ece,
                "reliability": bins,
            }));
        }
    }
    print!("{table}");
    if let Some(p) = &args.markdown {
        write(p, table.as_bytes())?;
    }
    if let Some(p) = &args.json {
        write(
            p,
            serde_json::to_string_pretty(&json!({"rows": rows}))?.as_bytes(),
        )?;
    }
    for p in &args.reliability {
        ic_eval::calibration::plot_reliability(
            p,
            "Confidence calibration (ADD-S < 0.1 d)",
            &reliability,
        )?;
        println!("wrote {}", p.display());
    }
    let series: Vec<(String, Vec<(f64, f64)>)> = curves
        .iter()
        .map(|(name, points)| {
            let mut v = points.clone();
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            (name.clone(), v)
        })
        .collect();
    for p in &args.curve {
        ic_eval::plot_xy(
            p,
            "Rotation accuracy at 15° against the number of rotated copies K",
            ("K", "acc@15°"),
            1.0,
            &series,
        )?;
        println!("wrote {}", p.display());
    }
    if let Some(p) = &args.fit_calibration {
        if calibration_samples.is_empty() {
            bail!(
                "--fit-calibration: no line of a -verify method has details.evidence (run eval with --details)"
            );
        }
        let c = Calibration::fit(&calibration_samples).map_err(anyhow::Error::msg)?;
        let doc = json!({
            "what": "isotonic calibration of incontext's verification evidence: P(ADD-S < 0.1 d | evidence)",
            "fitted_on": args.sets,
            "samples": calibration_samples.len(),
            "add_s_fraction": args.add_s_fraction,
            "knots": c.knots,
        });
        write(p, serde_json::to_string_pretty(&doc)?.as_bytes())?;
        println!(
            "wrote {} ({} knots from {} samples)",
            p.display(),
            c.knots.len(),
            calibration_samples.len()
        );
    }
    Ok(())
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    ic_geometry::io::write_atomic_with(path, |w| std::io::Write::write_all(w, bytes), |e| e)
        .with_context(|| format!("writing {}", path.display()))
}
