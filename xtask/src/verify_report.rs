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
//!
//! With `--symmetries FILE` (from `cargo xtask symmetries` on the cases' corpus, matched by
//! the `object_id` of each case's `meta.json`) two columns join: rotation accuracy at 15° on
//! the cases whose object has no symmetry, and BOP's AR_MSSD (mean over τ = 0.05…0.50 of the
//! share of cases with MSSD < τ·diameter, MSSD minimised over the symmetries found).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use ic_eval::cases::CaseFolder;
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
    /// The symmetries of the cases' objects (`cargo xtask symmetries --out`): adds acc@15° on
    /// the objects without symmetry and AR_MSSD.
    #[arg(long)]
    pub symmetries: Option<PathBuf>,
}

/// One object's symmetries as `cargo xtask symmetries` wrote them.
struct ObjectSymmetry {
    symmetric: bool,
    motions: Vec<Pose>,
}

/// The `objects` of a `cargo xtask symmetries` file, by id.
fn read_symmetries(path: &Path) -> Result<BTreeMap<String, ObjectSymmetry>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let doc: Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let objects = doc["objects"]
        .as_array()
        .with_context(|| format!("{}: no \"objects\" list", path.display()))?;
    let mut out = BTreeMap::new();
    for o in objects {
        let id = o["id"]
            .as_str()
            .with_context(|| format!("{}: an object without \"id\"", path.display()))?;
        let s: ic_geometry::symmetry::Symmetries = serde_json::from_value(o["symmetries"].clone())
            .with_context(|| format!("{}: object {id}: symmetries", path.display()))?;
        out.insert(
            id.to_string(),
            ObjectSymmetry {
                symmetric: s.is_symmetric(),
                motions: s.motions,
            },
        );
    }
    Ok(out)
}

use ic_eval::object_scores::MSSD_THRESHOLDS;

/// One scored line.
struct Scored {
    rotation_deg: f64,
    add_s_rel: f64,
    confidence: Option<f64>,
    verdict: Option<String>,
    raw_score: Option<f64>,
    seconds: f64,
    /// MSSD / diameter under the case's symmetries (only with `--symmetries`).
    mssd_rel: Option<f64>,
}

struct Case {
    truth: Pose,
    points: Vec<ic_geometry::glam::Vec3>,
    diameter: f64,
    /// `meta.json`'s `object_id`, when the case has one.
    object_id: Option<String>,
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
    let single = CaseFolder::new(dir).is_case();
    for t in ic_eval::cases::read_case_truths(dir)? {
        let case = if single {
            CaseFolder::new(dir)
        } else {
            CaseFolder::new(dir.join(&t.case))
        };
        let points = ic_geometry::io::read_ply_cloud(case.source())?.points;
        let diameter = ic_eval::diameter(&points);
        let meta = case.meta();
        let object_id = match std::fs::read_to_string(&meta) {
            Ok(text) => serde_json::from_str::<Value>(&text)
                .with_context(|| format!("parsing {}", meta.display()))?["object_id"]
                .as_str()
                .map(str::to_owned),
            Err(_) => None,
        };
        out.insert(
            t.case,
            Case {
                truth: t.pose,
                points,
                diameter,
                object_id,
            },
        );
    }
    Ok(out)
}

fn score_lines(
    cases: &BTreeMap<String, Case>,
    results: &[PathBuf],
    symmetries: Option<&BTreeMap<String, ObjectSymmetry>>,
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
            // The line's "R" and "t" in the pose's serde form (checked to be a rotation).
            let pose = (v["ok"].as_bool() == Some(true))
                .then(|| serde_json::from_value::<Pose>(v.clone()).ok())
                .flatten();
            let (rotation_deg, add_s_rel) = match pose {
                Some(p) => (
                    ic_eval::rotation_error_deg(&p, &c.truth),
                    ic_eval::add_s(&p, &c.truth, &c.points)? / c.diameter.max(1e-12),
                ),
                None => (180.0, f64::INFINITY),
            };
            let mssd_rel = match symmetries {
                None => None,
                Some(map) => {
                    let motions = &object_symmetry(map, c, &case)?.motions;
                    Some(match pose {
                        Some(p) => {
                            ic_eval::mssd(&p, &c.truth, &c.points, motions)? / c.diameter.max(1e-12)
                        }
                        None => f64::INFINITY,
                    })
                }
            };
            let scored = Scored {
                rotation_deg,
                add_s_rel,
                confidence: v["confidence"].as_f64(),
                verdict: v["verdict"].as_str().map(str::to_owned),
                raw_score: v["details"]["evidence"].as_f64(),
                seconds: v["seconds"].as_f64().unwrap_or(f64::NAN),
                mssd_rel,
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

/// The symmetry entry of a case's object.
fn object_symmetry<'a>(
    map: &'a BTreeMap<String, ObjectSymmetry>,
    c: &Case,
    case: &str,
) -> Result<&'a ObjectSymmetry> {
    let id = c.object_id.as_deref().with_context(|| {
        format!("case {case}: no object_id in meta.json to look its symmetries up")
    })?;
    map.get(id)
        .with_context(|| format!("case {case}: object {id} is not in the --symmetries file"))
}

pub fn run(args: VerifyReportArgs) -> Result<()> {
    let symmetries = args
        .symmetries
        .as_deref()
        .map(read_symmetries)
        .transpose()?;
    let mut rows = Vec::new();
    let mut reliability: Vec<(String, Vec<ReliabilityBin>)> = Vec::new();
    let mut calibration_samples: Vec<(f64, bool)> = Vec::new();
    let mut curves: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    let mut table = String::from(
        "| set | method | cases | acc@15° | ADD-S<0.1d | ok | uncertain | not_found | ok precision | ok recall | median s |",
    );
    table.push_str(if symmetries.is_some() {
        " asymmetric cases | acc@15° asymmetric | AR_MSSD |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    });
    for spec in &args.sets {
        let (name, dir, results) = parse_set(spec)?;
        let cases = read_cases(&dir)?;
        let scored = score_lines(&cases, &results, symmetries.as_ref())?;
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
                "| {name} | {method} | {n} | {acc15:.3} | {adds:.3} | {ok} | {unc} | {nf} | {precision:.3} | {recall:.3} | {median:.3} |"
            ));
            let mut symmetric_json = json!(null);
            if let Some(map) = &symmetries {
                // Cases without a line count as failures, as above.
                let mut asymmetric = Vec::new();
                for (case, c) in &cases {
                    if !object_symmetry(map, c, case)?.symmetric {
                        asymmetric.push(case);
                    }
                }
                let asym_right = asymmetric
                    .iter()
                    .filter(|case| lines.get(**case).is_some_and(|s| s.rotation_deg < 15.0))
                    .count();
                let asym_acc = asym_right as f64 / asymmetric.len().max(1) as f64;
                let ar_mssd = MSSD_THRESHOLDS
                    .iter()
                    .map(|tau| {
                        lines
                            .values()
                            .filter(|s| s.mssd_rel.is_some_and(|m| m < *tau))
                            .count() as f64
                            / n as f64
                    })
                    .sum::<f64>()
                    / MSSD_THRESHOLDS.len() as f64;
                table.push_str(&format!(
                    " {} | {asym_acc:.3} | {ar_mssd:.3} |",
                    asymmetric.len()
                ));
                symmetric_json = json!({
                    "asymmetric_cases": asymmetric.len(), "rotation_acc_15_asymmetric": asym_acc,
                    "ar_mssd": ar_mssd, "mssd_thresholds": MSSD_THRESHOLDS,
                });
            }
            table.push('\n');
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
                "reliability": bins, "symmetry": symmetric_json,
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

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::{DVec3, Vec3};
    use ic_geometry::io::{PlyEncoding, write_ply};
    use ic_geometry::{PointCloud, symmetry::Symmetries};

    fn write_case(dir: &Path, object: &str, truth: &Pose, points: &[Vec3]) {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("gt.json"), serde_json::to_string(truth).unwrap()).unwrap();
        std::fs::write(
            dir.join("meta.json"),
            json!({"object_id": object}).to_string(),
        )
        .unwrap();
        write_ply(
            dir.join("source.ply"),
            &PointCloud::from_points(points.to_vec()),
            PlyEncoding::Ascii,
        )
        .unwrap();
    }

    fn symmetries(motions: Vec<Pose>) -> Symmetries {
        Symmetries {
            motions,
            continuous_axes: vec![],
            centre: DVec3::ZERO,
            diameter: 2.0,
            floor: 0.01,
            nearest_residual: 0.0,
        }
    }

    /// A symmetric object's pose off by its symmetry is wrong in rotation, right in MSSD, and
    /// left out of the asymmetric accuracy; the asymmetric object's right pose counts there.
    #[test]
    fn symmetries_split_the_rotation_accuracy_and_forgive_mssd() {
        let tmp = tempfile::tempdir().unwrap();
        // A box-like point set with a half turn about z as its symmetry.
        let points: Vec<Vec3> = (0..64)
            .map(|i| {
                let s = |b: usize| if i >> b & 1 == 1 { 1.0 } else { -1.0 };
                Vec3::new(s(0) * (1.0 + 0.1 * (i % 3) as f32), s(1) * 0.5, s(2) * 0.3)
            })
            .collect();
        let half_turn = Pose::from_axis_angle(DVec3::Z, std::f64::consts::PI, DVec3::ZERO);
        let truth =
            Pose::from_axis_angle(DVec3::new(1.0, 2.0, 3.0), 0.7, DVec3::new(0.0, 0.0, 4.0));
        let cases = tmp.path().join("cases");
        write_case(&cases.join("case_00000"), "box", &truth, &points);
        write_case(&cases.join("case_00001"), "other", &truth, &points);
        let line = |case: &str, pose: &Pose| {
            json!({"case": case, "method": "m", "ok": true, "R": pose.rotation_row_major(),
                   "t": pose.translation.to_array(), "seconds": 0.1})
            .to_string()
        };
        let results = tmp.path().join("r.jsonl");
        std::fs::write(
            &results,
            [
                line("case_00000", &truth.compose(&half_turn)),
                line("case_00001", &truth),
            ]
            .join("\n"),
        )
        .unwrap();
        let sym = tmp.path().join("sym.json");
        std::fs::write(
            &sym,
            json!({"objects": [
                {"id": "box", "symmetries": symmetries(vec![half_turn])},
                {"id": "other", "symmetries": symmetries(vec![])},
            ]})
            .to_string(),
        )
        .unwrap();
        let out = tmp.path().join("report.json");
        run(VerifyReportArgs {
            sets: vec![format!("s={}:{}", cases.display(), results.display())],
            markdown: None,
            json: Some(out.clone()),
            reliability: vec![],
            fit_calibration: None,
            curve: vec![],
            add_s_fraction: 0.1,
            symmetries: Some(sym),
        })
        .unwrap();
        let report: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        let row = &report["rows"][0];
        assert_eq!(row["rotation_acc_15"], 0.5);
        assert_eq!(row["symmetry"]["asymmetric_cases"], 1);
        assert_eq!(row["symmetry"]["rotation_acc_15_asymmetric"], 1.0);
        assert!((row["symmetry"]["ar_mssd"].as_f64().unwrap() - 1.0).abs() < 1e-12);
    }
}
