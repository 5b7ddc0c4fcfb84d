//! Stage 5 of `cargo xtask bench`: the [`Report`] — the run's [`Config`], the machine, the
//! stages' times, every result file scored by `ic_eval::cases` — and its two renderings,
//! [`markdown`] (`results.md` and the plots) and [`json`] (`results.json`).
//!
//! Dependencies point one way: `markdown` and `json` read this module's types; this module
//! uses [`machine`] and the earlier stages (`cases`, `run`, `speed`), never its renderings.

pub mod json;
pub mod machine;
pub mod markdown;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Result;
use ic_eval::cases::{MethodScore, ResultLine, read_case_truths, read_result_lines, score_results};
use ic_eval::object_scores::CaseGeometry;
use serde::Serialize;
use serde_json::{Value, json};

use crate::bench::cases::{CaseSet, Set};
use crate::bench::common::rel;
use crate::bench::run::{Cli, MethodRun, RunStatus, SEG_MODEL, pose_model};
use crate::bench::speed::Speed;
use machine::{Machine, git_commit, load_average, utc};

/// Everything a run is, resolved from the arguments; printed first and saved in results.json.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Config {
    pub quick: bool,
    pub peers: bool,
    pub seed: u64,
    pub noback_count: u64,
    pub room_count: u64,
    /// Real-object views (0: the set did not run).
    pub real_count: u64,
    /// The real set's objects, when it ran.
    pub real_objects: Option<serde_json::Value>,
    /// OpenCV's PPF peers run on the first this many cases of each set (0: all).
    pub ppf_cases: u64,
    /// Timing repeats of the PPF peers.
    pub ppf_repeats: usize,
    pub threads: usize,
    pub repeats: usize,
    /// Object-alone cases the registration times are measured on (ours and Open3D's; PPF the
    /// first only).
    pub timing_pairs: usize,
    /// Object-alone cases of the accuracy/speed curve (0: none).
    pub curve_cases: usize,
    pub train_steps: usize,
    pub out: PathBuf,
    pub work: PathBuf,
    pub objects: serde_json::Value,
    pub speed: bool,
    pub resume: bool,
}

impl Config {
    /// A quick run's configuration writing under `dir`, without peers or speed (the tests').
    #[cfg(test)]
    pub(crate) fn for_tests(dir: &Path) -> Config {
        Config {
            quick: true,
            peers: false,
            seed: 1,
            noback_count: 1,
            room_count: 1,
            real_count: 0,
            real_objects: None,
            ppf_cases: 1,
            ppf_repeats: 1,
            threads: 1,
            repeats: 1,
            timing_pairs: 1,
            curve_cases: 0,
            train_steps: 1,
            out: dir.into(),
            work: dir.into(),
            objects: serde_json::json!({"kind": "procedural", "count": 3}),
            speed: false,
            resume: false,
        }
    }
}

/// One case set's scores.
#[derive(Clone, Debug, Serialize)]
pub struct SetReport {
    pub set: Set,
    pub count: u64,
    pub dir: PathBuf,
    pub cases: Vec<Value>,
    pub scores: Vec<MethodScore>,
    /// (label, reason) of methods without scores.
    pub missing: Vec<(String, String)>,
    /// Cases whose object has no symmetry (found on its mesh): where the rotation accuracy
    /// means what it says.
    pub asymmetric_cases: Vec<String>,
    /// Where our methods' time goes, from their lines' `details.stage_seconds`.
    pub stage_split: Vec<StageSplit>,
}

/// The median seconds of each pipeline stage of one of our methods on one set.
#[derive(Clone, Debug, Serialize)]
pub struct StageSplit {
    pub label: String,
    /// Lines with stage seconds (the registrations that returned a pose).
    pub cases: usize,
    /// Stage name (`segmentation_network`, `pose_network`, `icp`, …, `total`) → median
    /// seconds.
    pub median_seconds: std::collections::BTreeMap<String, f64>,
}

/// The stage split of a result file of ours, when its lines carry `details.stage_seconds`.
fn stage_split(label: &str, file: &Path) -> Option<StageSplit> {
    let text = std::fs::read_to_string(file).ok()?;
    let mut by_stage: std::collections::BTreeMap<String, Vec<f64>> = Default::default();
    let mut cases = 0;
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let Ok(v) = serde_json::from_str::<Value>(line) else {
            continue;
        };
        let Some(stages) = v["details"]["stage_seconds"].as_object() else {
            continue;
        };
        cases += 1;
        for (k, x) in stages {
            if let Some(x) = x.as_f64().filter(|x| x.is_finite()) {
                by_stage.entry(k.clone()).or_default().push(x);
            }
        }
    }
    (cases > 0).then(|| StageSplit {
        label: label.to_string(),
        cases,
        median_seconds: by_stage
            .into_iter()
            .map(|(k, v)| (k, ic_eval::median(&v)))
            .collect(),
    })
}

/// Everything results.md and results.json are made of.
#[derive(Debug, Serialize)]
pub struct Report {
    pub config: Config,
    pub command: String,
    pub date: String,
    pub commit: Option<String>,
    pub machine: Machine,
    /// Whether this process (which times the speed stage) is a release build: a dev build
    /// keeps debug assertions and overflow checks on and times our code slower.
    pub release_build: bool,
    pub models: Vec<Value>,
    pub cli: Option<Cli>,
    pub open3d_version: Option<String>,
    /// OpenCV's version when the PPF peers ran.
    pub opencv_version: Option<String>,
    pub notes: Vec<String>,
    pub stages: Vec<(String, f64)>,
    pub runs: Vec<MethodRun>,
    pub sets: Vec<SetReport>,
    pub speed: Option<Speed>,
    pub open3d_timing: Option<Value>,
    /// `ppf_peers.py --timing`'s JSON.
    pub ppf_timing: Option<Value>,
    /// The clutter benchmark, when it ran.
    pub clutter: Option<crate::bench::scenes::ClutterReport>,
    /// The real frames, one folder each.
    pub frames: Vec<crate::bench::scenes::FramesReport>,
    pub total_seconds: f64,
}

impl Report {
    pub fn start(root: &Path, config: &Config) -> Report {
        let args: Vec<String> = std::env::args().skip(1).collect();
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let models = [
            pose_model("softmax"),
            // The default pipeline's second pose network, whose hypotheses `register` verifies
            // beside the main one's.
            pose_model("softmax-scratch"),
            pose_model("ot"),
            PathBuf::from(SEG_MODEL),
            PathBuf::from(crate::bench::scenes::CLUTTER_SEG_MODEL),
        ]
        .iter()
        .map(|m| {
            let meta = std::fs::metadata(root.join(m)).ok();
            json!({"file": m, "present": meta.is_some(), "bytes": meta.map(|m| m.len())})
        })
        .collect();
        let mut config = config.clone();
        config.out = rel(&config.out);
        config.work = rel(&config.work);
        Report {
            config,
            command: format!("cargo xtask {}", args.join(" ")),
            date: utc(now),
            commit: git_commit(root),
            machine: Machine::probe(),
            release_build: !cfg!(debug_assertions),
            models,
            cli: None,
            open3d_version: None,
            opencv_version: None,
            notes: Vec::new(),
            stages: Vec::new(),
            runs: Vec::new(),
            sets: Vec::new(),
            speed: None,
            open3d_timing: None,
            ppf_timing: None,
            clutter: None,
            frames: Vec::new(),
            total_seconds: 0.0,
        }
    }

    pub fn stage(&mut self, name: &str, seconds: f64) {
        tracing::info!(
            stage = name,
            seconds = format!("{seconds:.1}"),
            "stage done"
        );
        self.stages.push((name.to_string(), seconds));
    }

    /// Scores every run that produced a file; a file that cannot be read or scored turns that
    /// method into a missing one with the reason (the others are still reported).
    ///
    /// `geometry` (by set, then case name) gives the cases their object metrics.
    pub fn score(
        &mut self,
        sets: &[CaseSet],
        runs: Vec<MethodRun>,
        geometry: &HashMap<Set, HashMap<String, Arc<CaseGeometry>>>,
    ) -> Result<()> {
        let mut files: HashMap<PathBuf, Result<Vec<ResultLine>, String>> = HashMap::new();
        for cs in sets {
            let mut truths = read_case_truths(&cs.dir)?;
            if let Some(g) = geometry.get(&cs.set) {
                for t in &mut truths {
                    t.geometry = g.get(&t.case).cloned();
                }
            }
            let mut report = SetReport {
                set: cs.set,
                count: cs.count,
                dir: rel(&cs.dir),
                cases: cs.cases.clone(),
                scores: Vec::new(),
                missing: Vec::new(),
                asymmetric_cases: truths
                    .iter()
                    .filter(|t| t.geometry.as_ref().is_some_and(|g| g.symmetries.is_empty()))
                    .map(|t| t.case.clone())
                    .collect(),
                stage_split: Vec::new(),
            };
            for run in runs.iter().filter(|r| r.set == cs.set) {
                let file = match &run.status {
                    RunStatus::Ran { file, .. } => file,
                    RunStatus::Missing { reason } => {
                        report
                            .missing
                            .push((run.label.clone(), format!("not run: {reason}")));
                        continue;
                    }
                    RunStatus::Failed { reason } => {
                        report
                            .missing
                            .push((run.label.clone(), format!("failed: {reason}")));
                        continue;
                    }
                };
                let lines = files
                    .entry(file.clone())
                    .or_insert_with(|| read_result_lines(file).map_err(|e| e.to_string()));
                let lines: Vec<ResultLine> = match lines {
                    Ok(l) => l
                        .iter()
                        // The peers share one file; our files hold one method each.
                        .filter(|l| !run.peer || l.method == run.method)
                        .cloned()
                        .map(|mut l| {
                            l.method = run.label.clone();
                            l
                        })
                        .collect(),
                    Err(e) => {
                        report.missing.push((run.label.clone(), e.clone()));
                        continue;
                    }
                };
                if lines.is_empty() {
                    report.missing.push((
                        run.label.clone(),
                        format!("{} holds no line for it", file.display()),
                    ));
                    continue;
                }
                if !run.peer
                    && let Some(split) = stage_split(&run.label, file)
                {
                    report.stage_split.push(split);
                }
                // The slow peers ran on the first cases only: score them on those.
                let n = run
                    .case_limit
                    .map_or(truths.len(), |l| (l as usize).min(truths.len()));
                match score_results(&truths[..n], &lines) {
                    Ok(mut s) => report.scores.append(&mut s),
                    Err(e) => report.missing.push((run.label.clone(), e.to_string())),
                }
            }
            self.sets.push(report);
        }
        self.runs = runs;
        self.machine.load_average_end = load_average();
        Ok(())
    }

    pub(super) fn open3d_median(&self, method: &str, size: (usize, usize)) -> Option<f64> {
        timing_median(self.open3d_timing.as_ref()?, method, size)
    }

    pub(super) fn ppf_median(&self, method: &str, size: (usize, usize)) -> Option<f64> {
        timing_median(self.ppf_timing.as_ref()?, method, size)
    }
}

/// The median seconds of `method` at (model, observed) points in a peers' script's timing
/// JSON (a record without `observed_points` is square).
fn timing_median(timing: &Value, method: &str, (m, n): (usize, usize)) -> Option<f64> {
    timing["results"].as_array()?.iter().find(|r| {
        let points = r["points"].as_u64();
        r["method"] == method
            && points == Some(m as u64)
            && r["observed_points"].as_u64().or(points) == Some(n as u64)
    })?["median_seconds"]
        .as_f64()
}
