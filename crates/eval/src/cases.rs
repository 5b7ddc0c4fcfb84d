//! Scoring registration results on exported case folders.
//!
//! A case folder (written by `cargo xtask export-cases`) holds `gt.json` —
//! `{"R": [[…], […], […]], "t": [x, y, z]}` with `target ≈ R·source + t`, R row-major — and
//! usually `meta.json` (with `object_id`). Any tool that registers the cases writes one JSON line
//! per (case, method):
//!
//! ```json
//! {"case": "case_00000", "method": "ours-ot", "R": [[…], […], […]], "t": [x, y, z],
//!  "seconds": 0.05, "ok": true, "error": null}
//! ```
//!
//! ([`ResultLine`] reads and writes exactly this). [`score_results`] turns the lines of any
//! number of files into one [`MethodScore`] per method: a line with `ok: false`, a pose that is
//! not a finite rotation, and a case without a line all count as failures — rotation error 180°,
//! translation error ∞ — so every method is scored on every case.
//!
//! ```
//! use ic_eval::cases::{CaseTruth, ResultLine, score_results};
//! use ic_geometry::{Pose, glam::DVec3};
//!
//! let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 2.8));
//! let cases = vec![
//!     CaseTruth::new("a", truth),
//!     CaseTruth::new("b", truth),
//! ];
//! let line = ResultLine::from_pose("a", "icp", &truth, 0.01);
//! let scores = score_results(&cases, &[line]).unwrap();
//! assert_eq!(scores[0].method(), "icp");
//! assert_eq!((scores[0].scored, scores[0].missing), (1, 1));
//! assert_eq!(scores[0].result.summary.rotation_accuracy[0], (5.0, 0.5));
//! ```

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ic_geometry::Pose;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::object_scores::{CaseGeometry, ObjectErrors, ObjectScore};
use crate::{EvalError, MethodResult, PoseErrors, Summary, auc, median};

/// Rotation error given to a failed or missing estimate (degrees).
pub const FAILED_ROTATION_DEG: f64 = 180.0;

/// One case's ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct CaseTruth {
    /// The case folder's name (the `case` of the result lines).
    pub case: String,
    /// Model → camera (`target ≈ R·source + t`).
    pub pose: Pose,
    /// `object_id` from `meta.json`, when present.
    pub object_id: Option<String>,
    /// The model points, symmetries and camera of the object metrics (ADD-S, MSSD, MSPD);
    /// `None` scores rotation and translation only.
    pub geometry: Option<Arc<CaseGeometry>>,
}

impl CaseTruth {
    /// A case without object id or geometry.
    pub fn new(case: impl Into<String>, pose: Pose) -> Self {
        CaseTruth {
            case: case.into(),
            pose,
            object_id: None,
            geometry: None,
        }
    }
}

fn format_error(path: &Path, message: impl Into<String>) -> EvalError {
    EvalError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// The largest case or results file read (a results file of 100 000 lines is ≈ 50 MB).
const MAX_TEXT_BYTES: u64 = 1 << 30;

fn read_text(path: &Path) -> Result<String, EvalError> {
    let io = |source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bytes = ic_geometry::io::read_bounded(path, MAX_TEXT_BYTES).map_err(io)?;
    String::from_utf8(bytes).map_err(|e| {
        io(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("not UTF-8 text: {e}"),
        ))
    })
}

fn matrix3(v: &Value) -> Option<[[f64; 3]; 3]> {
    let rows = v.as_array().filter(|r| r.len() == 3)?;
    let mut m = [[0.0; 3]; 3];
    for (i, row) in rows.iter().enumerate() {
        m[i] = vector3(row)?;
    }
    Some(m)
}

fn vector3(v: &Value) -> Option<[f64; 3]> {
    let a = v.as_array().filter(|a| a.len() == 3)?;
    let mut out = [0.0; 3];
    for (o, x) in out.iter_mut().zip(a) {
        // null (how serde_json writes NaN/∞) reads as NaN: a non-finite pose, not bad syntax.
        *o = if x.is_null() { f64::NAN } else { x.as_f64()? };
    }
    Some(out)
}

/// One registration case folder, `case_NNNNN/`: the format's single owner (file names, how
/// the truth is read). Written by `ic_data::export` (`cargo xtask export-cases`, the bench),
/// read by this module's scorer, `incontext eval --cases` and xtask.
///
/// | file | what | frame, units |
/// |---|---|---|
/// | `source.ply` | model points X, binary little-endian `float x y z` | model, normalised |
/// | `target.ply` | observed points (object alone) or the voxelised scene (room) | camera, normalised |
/// | `gt.json` | the true pose ([`Pose`]'s serde form, `{"R": rows, "t": [x, y, z]}`), `target ≈ R·source + t` | model → camera, normalised |
/// | `meta.json` | object id, sample index, seed, counts, inlier rate | – |
/// | `depth.png` | room and view cases: 16-bit depth, `stored × depth_scale = mm` | camera, mm |
/// | `camera.json` | room and view cases: `cam_K` (row-major), `depth_scale`, `width`, `height`, `unit_mm` (mm per normalised unit) | pixels |
/// | `mask.png` | room and view cases: the visible object (8-bit, 255), for upper-bound runs only | pixels |
/// | `model.ply` | view cases: the normalised mesh the pose refers to | model, normalised |
///
/// The bench's room cases name their mask `mask_visib.png` ([`CaseFolder::MASK_VISIB`]).
///
/// ```
/// use ic_eval::cases::CaseFolder;
///
/// let case = CaseFolder::new("cases").child(7);
/// assert_eq!(case.name(), "case_00007");
/// assert_eq!(case.gt(), std::path::Path::new("cases/case_00007/gt.json"));
/// ```
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CaseFolder {
    dir: PathBuf,
}

impl CaseFolder {
    /// The normalised mesh (view cases).
    pub const MODEL: &'static str = "model.ply";
    /// The model points.
    pub const SOURCE: &'static str = "source.ply";
    /// The observed points.
    pub const TARGET: &'static str = "target.ply";
    /// The depth map (room and view cases).
    pub const DEPTH: &'static str = "depth.png";
    /// The visible object's mask (room and view cases).
    pub const MASK: &'static str = "mask.png";
    /// The mask's name in the bench's room cases.
    pub const MASK_VISIB: &'static str = "mask_visib.png";
    /// The camera (room and view cases).
    pub const CAMERA: &'static str = "camera.json";
    /// The true pose.
    pub const GT: &'static str = "gt.json";
    /// What the case is (object id, index, seed, counts).
    pub const META: &'static str = "meta.json";

    /// The case folder `dir` (nothing is read).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        CaseFolder { dir: dir.into() }
    }

    /// The name of case `index` in a set: `case_NNNNN` (5 digits, zero-padded).
    pub fn name_of(index: u64) -> String {
        format!("case_{index:05}")
    }

    /// Case `index` of the set whose folder is `self` (`self/case_NNNNN`).
    pub fn child(&self, index: u64) -> CaseFolder {
        CaseFolder::new(self.dir.join(CaseFolder::name_of(index)))
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The folder's name (the `case` of the result lines).
    pub fn name(&self) -> String {
        self.dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    }

    /// `model.ply`.
    pub fn model(&self) -> PathBuf {
        self.dir.join(Self::MODEL)
    }
    /// `source.ply`.
    pub fn source(&self) -> PathBuf {
        self.dir.join(Self::SOURCE)
    }
    /// `target.ply`.
    pub fn target(&self) -> PathBuf {
        self.dir.join(Self::TARGET)
    }
    /// `depth.png`.
    pub fn depth(&self) -> PathBuf {
        self.dir.join(Self::DEPTH)
    }
    /// `mask.png`.
    pub fn mask(&self) -> PathBuf {
        self.dir.join(Self::MASK)
    }
    /// `camera.json`.
    pub fn camera(&self) -> PathBuf {
        self.dir.join(Self::CAMERA)
    }
    /// `gt.json`.
    pub fn gt(&self) -> PathBuf {
        self.dir.join(Self::GT)
    }
    /// `meta.json`.
    pub fn meta(&self) -> PathBuf {
        self.dir.join(Self::META)
    }

    /// Whether the folder holds a case (a `gt.json`).
    pub fn is_case(&self) -> bool {
        self.gt().is_file()
    }

    /// Whether the case holds a depth map and its camera (room and view cases; an
    /// object-alone case holds only the PLY files).
    pub fn has_depth(&self) -> bool {
        self.depth().is_file() && self.camera().is_file()
    }

    /// The mask file, when the case has one (`mask.png`, else `mask_visib.png`).
    pub fn mask_file(&self) -> Option<PathBuf> {
        [Self::MASK, Self::MASK_VISIB]
            .iter()
            .map(|n| self.dir.join(n))
            .find(|p| p.is_file())
    }

    /// The true pose, model → camera in normalised units ([`read_gt`]).
    pub fn read_gt(&self) -> Result<Pose, EvalError> {
        read_gt(&self.gt())
    }

    /// `object_id` of `meta.json` (a string, or a number as text); `None` without the file or
    /// the key.
    pub fn read_object_id(&self) -> Result<Option<String>, EvalError> {
        let meta = self.meta();
        if !meta.is_file() {
            return Ok(None);
        }
        let v: Value = serde_json::from_str(&read_text(&meta)?)
            .map_err(|e| format_error(&meta, e.to_string()))?;
        Ok(match &v["object_id"] {
            Value::String(s) => Some(s.clone()),
            Value::Number(n) => Some(n.to_string()),
            _ => None,
        })
    }

    /// The case folders under `dir` (its subfolders, sorted by name); `dir` itself when it is
    /// a case.
    pub fn list(dir: &Path) -> Result<Vec<CaseFolder>, EvalError> {
        let single = CaseFolder::new(dir);
        if single.is_case() {
            return Ok(vec![single]);
        }
        let entries = std::fs::read_dir(dir).map_err(|source| EvalError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut dirs: Vec<PathBuf> = Vec::new();
        for e in entries {
            let e = e.map_err(|source| EvalError::Io {
                path: dir.to_path_buf(),
                source,
            })?;
            if e.path().is_dir() {
                dirs.push(e.path());
            }
        }
        dirs.sort();
        Ok(dirs.into_iter().map(CaseFolder::new).collect())
    }
}

/// Reads one `gt.json`, a [`Pose`] in its serde form (`{"R": 3×3 row-major, "t": [3]}`);
/// fails, naming the file, when it is not one or R is not a rotation.
pub fn read_gt(path: &Path) -> Result<Pose, EvalError> {
    let text = read_text(path)?;
    serde_json::from_str::<Pose>(&text).map_err(|e| {
        format_error(
            path,
            format!("not a pose {{\"R\": 3×3 row-major, \"t\": [3 numbers]}}: {e}"),
        )
    })
}

/// The ground truth of every case folder under `dir` (each subfolder, sorted by name, must
/// hold `gt.json`; `meta.json` is optional); `dir` may also be a single case folder.
pub fn read_case_truths(dir: &Path) -> Result<Vec<CaseTruth>, EvalError> {
    let cases = CaseFolder::list(dir)?;
    if cases.is_empty() {
        return Err(format_error(dir, "no case folders"));
    }
    cases
        .iter()
        .map(|c| {
            Ok(CaseTruth {
                case: c.name(),
                pose: c.read_gt()?,
                object_id: c.read_object_id()?,
                geometry: None,
            })
        })
        .collect()
}

/// One result line: the pose a method found for a case (or why it found none).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResultLine {
    pub case: String,
    pub method: String,
    /// Row-major rotation; `None` when the method failed.
    #[serde(rename = "R")]
    pub rotation: Option<[[f64; 3]; 3]>,
    pub t: Option<[f64; 3]>,
    /// Wall time of the registration.
    pub seconds: Option<f64>,
    /// Whether the method returned a pose.
    pub ok: bool,
    pub error: Option<String>,
    /// File and line the record came from (not written).
    #[serde(skip)]
    pub origin: Option<(PathBuf, usize)>,
}

impl ResultLine {
    /// A successful line.
    pub fn from_pose(case: &str, method: &str, pose: &Pose, seconds: f64) -> Self {
        let t = pose.translation;
        ResultLine {
            case: case.into(),
            method: method.into(),
            rotation: Some(pose.rotation_row_major()),
            t: Some([t.x, t.y, t.z]),
            seconds: Some(seconds),
            ok: true,
            error: None,
            origin: None,
        }
    }

    /// A failed line.
    pub fn failed(case: &str, method: &str, error: impl Into<String>, seconds: f64) -> Self {
        ResultLine {
            case: case.into(),
            method: method.into(),
            rotation: None,
            t: None,
            seconds: Some(seconds),
            ok: false,
            error: Some(error.into()),
            origin: None,
        }
    }

    /// The pose, when the line is ok and holds a finite rotation; else why not.
    pub fn pose(&self) -> Result<Pose, String> {
        if !self.ok {
            return Err(self
                .error
                .clone()
                .unwrap_or_else(|| "failed (no message)".into()));
        }
        match (self.rotation, self.t) {
            (Some(r), Some(t)) => Pose::from_row_major(r, t).map_err(|e| e.to_string()),
            _ => Err("ok but R or t is missing".into()),
        }
    }

    fn location(&self) -> String {
        match &self.origin {
            Some((p, l)) => format!("{}:{l}", p.display()),
            None => "a result line".into(),
        }
    }

    fn from_value(v: &Value, path: &Path, line: usize) -> Result<Self, EvalError> {
        let at = |m: &str| format_error(path, format!("line {line}: {m}"));
        let text = |key: &str| -> Result<String, EvalError> {
            match &v[key] {
                Value::String(s) => Ok(s.clone()),
                Value::Number(n) => Ok(n.to_string()),
                _ => Err(at(&format!("\"{key}\" must be a string"))),
            }
        };
        let ok = v["ok"]
            .as_bool()
            .ok_or_else(|| at("\"ok\" must be true or false"))?;
        let rotation = match &v["R"] {
            Value::Null => None,
            r => Some(matrix3(r).unwrap_or([[f64::NAN; 3]; 3])),
        };
        let t = match &v["t"] {
            Value::Null => None,
            t => Some(vector3(t).unwrap_or([f64::NAN; 3])),
        };
        Ok(ResultLine {
            case: text("case")?,
            method: text("method")?,
            rotation,
            t,
            seconds: v["seconds"].as_f64(),
            ok,
            error: v["error"].as_str().map(str::to_owned),
            origin: Some((path.to_path_buf(), line)),
        })
    }
}

/// Reads a JSONL file of [`ResultLine`]s (blank lines skipped). A line that is not JSON or lacks
/// `case`, `method` or `ok` is an error naming the file and line; a malformed `R`/`t` on an ok
/// line is kept and scored as a failure.
pub fn read_result_lines(path: &Path) -> Result<Vec<ResultLine>, EvalError> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v: Value = serde_json::from_str(line)
            .map_err(|e| format_error(path, format!("line {}: {e}", i + 1)))?;
        out.push(ResultLine::from_value(&v, path, i + 1)?);
    }
    Ok(out)
}

/// Writes result lines as JSONL, atomically.
pub fn write_result_lines(path: &Path, lines: &[ResultLine]) -> Result<(), EvalError> {
    let mut text = String::new();
    for l in lines {
        let s = serde_json::to_string(l).map_err(|e| format_error(path, e.to_string()))?;
        text.push_str(&s);
        text.push('\n');
    }
    let io = |source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    };
    ic_geometry::io::write_atomic_with(
        path,
        |w| std::io::Write::write_all(w, text.as_bytes()).map_err(io),
        io,
    )
}

/// What happened to one case under one method.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum CaseOutcome {
    /// A pose was scored.
    Scored { errors: PoseErrors },
    /// `ok: false`, or a pose that is not a finite rotation.
    Failed { error: String },
    /// No line for this case.
    Missing,
}

/// One case's result under one method.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaseScore {
    pub case: String,
    pub object_id: Option<String>,
    #[serde(flatten)]
    pub outcome: CaseOutcome,
    pub seconds: Option<f64>,
    /// ADD-S, MSSD and MSPD of a scored pose, when the case has its geometry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object: Option<ObjectErrors>,
}

/// One method scored on a set of cases.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MethodScore {
    /// Summary and per-case errors (failures as 180° and ∞, in case order).
    pub result: MethodResult,
    /// Cases with a scored pose.
    pub scored: usize,
    /// Cases whose line failed (`ok: false` or an invalid pose).
    pub failed: usize,
    /// Cases without a line.
    pub missing: usize,
    /// Area under the rotation accuracy curve on [0°, 15°], normalised to [0, 1].
    pub rotation_auc_15: f64,
    /// Area under the squared-translation accuracy curve on [0, 1e-2], normalised.
    pub translation_auc_1e2: f64,
    /// Median of the plain L2 translation error (failures as ∞).
    pub translation_l2_median: f64,
    /// ADD-S < 0.1·d, AR_MSSD and AR_MSPD, when every case has its geometry.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object: Option<ObjectScore>,
    pub cases: Vec<CaseScore>,
}

impl MethodScore {
    pub fn method(&self) -> &str {
        &self.result.method
    }

    /// The first few distinct failure messages with their counts, most frequent first.
    pub fn failure_reasons(&self, limit: usize) -> Vec<(String, usize)> {
        let mut counts: BTreeMap<String, usize> = BTreeMap::new();
        for c in &self.cases {
            let key = match &c.outcome {
                CaseOutcome::Failed { error } => error.clone(),
                CaseOutcome::Missing => "no result line".into(),
                CaseOutcome::Scored { .. } => continue,
            };
            *counts.entry(key).or_default() += 1;
        }
        let mut v: Vec<(String, usize)> = counts.into_iter().collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        v.truncate(limit);
        v
    }
}

/// Scores `lines` against `cases`: one [`MethodScore`] per method, in the order the methods first
/// appear. Errors: a line for a case that is not in `cases`, or two lines for the same
/// (case, method).
pub fn score_results(
    cases: &[CaseTruth],
    lines: &[ResultLine],
) -> Result<Vec<MethodScore>, EvalError> {
    let index: HashMap<&str, usize> = cases
        .iter()
        .enumerate()
        .map(|(i, c)| (c.case.as_str(), i))
        .collect();
    let mut order: Vec<&str> = Vec::new();
    let mut by_method: HashMap<&str, Vec<Option<&ResultLine>>> = HashMap::new();
    for l in lines {
        let Some(&i) = index.get(l.case.as_str()) else {
            return Err(EvalError::Format {
                path: l.origin.as_ref().map(|o| o.0.clone()).unwrap_or_default(),
                message: format!(
                    "{}: case {:?} is not one of the {} cases scored",
                    l.location(),
                    l.case,
                    cases.len()
                ),
            });
        };
        let slots = by_method.entry(l.method.as_str()).or_insert_with(|| {
            order.push(l.method.as_str());
            vec![None; cases.len()]
        });
        if let Some(prev) = slots[i] {
            return Err(EvalError::Format {
                path: l.origin.as_ref().map(|o| o.0.clone()).unwrap_or_default(),
                message: format!(
                    "{}: a second line for case {:?}, method {:?} (first at {})",
                    l.location(),
                    l.case,
                    l.method,
                    prev.location()
                ),
            });
        }
        slots[i] = Some(l);
    }
    Ok(order
        .iter()
        .map(|m| score_method(m, cases, &by_method[m]))
        .collect())
}

fn score_method(method: &str, cases: &[CaseTruth], lines: &[Option<&ResultLine>]) -> MethodScore {
    let mut scores = Vec::with_capacity(cases.len());
    let (mut scored, mut failed, mut missing) = (0, 0, 0);
    for (truth, line) in cases.iter().zip(lines) {
        let mut object = None;
        let outcome = match line {
            None => {
                missing += 1;
                CaseOutcome::Missing
            }
            Some(l) => match l.pose() {
                Ok(p) => match PoseErrors::compute(&p, &truth.pose, None).and_then(|errors| {
                    let o = truth
                        .geometry
                        .as_deref()
                        .map(|g| ObjectErrors::compute(&p, &truth.pose, g))
                        .transpose()?;
                    Ok((errors, o))
                }) {
                    Ok((errors, o)) => {
                        scored += 1;
                        object = o;
                        CaseOutcome::Scored { errors }
                    }
                    Err(e) => {
                        failed += 1;
                        CaseOutcome::Failed {
                            error: e.to_string(),
                        }
                    }
                },
                Err(error) => {
                    failed += 1;
                    CaseOutcome::Failed { error }
                }
            },
        };
        scores.push(CaseScore {
            case: truth.case.clone(),
            object_id: truth.object_id.clone(),
            outcome,
            seconds: line.and_then(|l| l.seconds).filter(|s| s.is_finite()),
            object,
        });
    }
    let errors: Vec<Option<PoseErrors>> = scores
        .iter()
        .map(|c| match &c.outcome {
            CaseOutcome::Scored { errors } => Some(*errors),
            _ => None,
        })
        .collect();
    let pick = |f: fn(&PoseErrors) -> f64, failed: f64| -> Vec<f64> {
        errors
            .iter()
            .map(|e| e.as_ref().map_or(failed, f))
            .collect()
    };
    let rot = pick(|e| e.rotation_deg, FAILED_ROTATION_DEG);
    let tsq = pick(|e| e.translation_sq, f64::INFINITY);
    let l2 = pick(|e| e.translation, f64::INFINITY);
    let mut summary = Summary::new(&errors, None);
    // Summary counts failures as infinitely wrong; the median here uses 180° instead, the
    // largest rotation error there is (the accuracies are the same either way).
    summary.rotation_median_deg = median(&rot);
    let seconds: Vec<f64> = scores
        .iter()
        .filter(|c| matches!(c.outcome, CaseOutcome::Scored { .. }))
        .filter_map(|c| c.seconds)
        .collect();
    MethodScore {
        result: MethodResult {
            method: method.to_string(),
            summary,
            rotation_errors_deg: rot.clone(),
            translation_sq_errors: tsq.clone(),
            seconds_median: (!seconds.is_empty()).then(|| median(&seconds)),
        },
        scored,
        failed,
        missing,
        rotation_auc_15: auc(&rot, 15.0, 1501),
        translation_auc_1e2: auc(&tsq, 1e-2, 1001),
        translation_l2_median: median(&l2),
        object: object_score(cases, &scores),
        cases: scores,
    }
}

/// The object metrics over the cases, when every case has its geometry (a failed or missing
/// case counts as wrong); MSPD's pixel thresholds follow the first camera's width.
fn object_score(cases: &[CaseTruth], scores: &[CaseScore]) -> Option<ObjectScore> {
    if cases.is_empty() || cases.iter().any(|c| c.geometry.is_none()) {
        return None;
    }
    let width = cases
        .iter()
        .find_map(|c| c.geometry.as_ref()?.intrinsics.map(|k| k.width))
        .unwrap_or(640);
    let errors: Vec<Option<ObjectErrors>> = scores.iter().map(|c| c.object).collect();
    Some(ObjectScore::with_width(&errors, width))
}

/// Reads the cases under `cases_dir` and every result file, and scores them.
pub fn score_files(cases_dir: &Path, results: &[PathBuf]) -> Result<Vec<MethodScore>, EvalError> {
    let cases = read_case_truths(cases_dir)?;
    let mut lines = Vec::new();
    for r in results {
        lines.extend(read_result_lines(r)?);
    }
    score_results(&cases, &lines)
}

fn fmt_num(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        "∞".into()
    }
}

fn fmt_sci(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.2e}")
    } else {
        "∞".into()
    }
}

/// The markdown table of one case set: the paper's accuracies and mAP, AUC, medians, failure
/// counts and the median time per registration, one row per method; with the object metrics
/// (ADD-S < 0.1·d, AR_MSSD, AR_MSPD) when a method has them. Explains the columns.
pub fn markdown_cases_table(scores: &[MethodScore]) -> String {
    let object = scores.iter().any(|m| m.object.is_some());
    let mut s = String::from(
        "| method | cases | failed | rot. median (°) | acc@5° | acc@10° | acc@15° | mAP@15° | AUC@15° \
         | ‖Δt‖² median | acc@1e-3 | acc@5e-3 | acc@1e-2 | mAP@1e-2 |",
    );
    s.push_str(if object {
        " ADD-S < 0.1·d | AR_MSSD | AR_MSPD | median s |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    } else {
        " median s |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    });
    for m in scores {
        let sm = &m.result.summary;
        let acc = |v: &[(f64, f64)]| {
            v.iter()
                .map(|(_, a)| format!("{a:.3}"))
                .collect::<Vec<_>>()
                .join(" | ")
        };
        let objects = if !object {
            String::new()
        } else if let Some(o) = &m.object {
            format!(
                " {:.3} | {:.3} | {} |",
                o.add_s_01d,
                o.ar_mssd,
                o.ar_mspd.map_or("–".into(), |v| format!("{v:.3}"))
            )
        } else {
            " – | – | – |".into()
        };
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.3} | {:.3} | {} | {} | {:.3} |{objects} {} |\n",
            m.result.method,
            sm.count,
            m.failed + m.missing,
            fmt_num(sm.rotation_median_deg, 2),
            acc(&sm.rotation_accuracy),
            sm.rotation_map_15,
            m.rotation_auc_15,
            fmt_sci(sm.translation_sq_median),
            acc(&sm.translation_accuracy),
            sm.translation_map_1e2,
            m.result
                .seconds_median
                .map_or("–".into(), |t| format!("{t:.4}")),
        ));
    }
    s.push_str(
        "\nacc@x: fraction of cases with error ≤ x (rotation E_rot = arccos((tr(R̂ᵀR) − 1)/2); \
         translation on the squared L2 error ‖t̂ − t‖² in normalised units, as the paper). \
         mAP in the convention of Yi et al. 2018: mean of the accuracies at step, 2·step, …, τ \
         (rotation step 5°, translation step 1e-3). AUC: area under the accuracy curve on \
         [0, 15°], normalised to [0, 1]. Failed: no pose, an invalid pose or no result line; \
         a failure counts as 180° and ∞ in every column. Median s: over the scored cases.\n",
    );
    if object {
        s.push_str(
            "ADD-S < 0.1·d: share of cases whose ADD-S (mean distance from each model point \
             under the estimate to the nearest under the truth) is below a tenth of the \
             object's diameter. AR_MSSD, AR_MSPD: BOP's recalls (Hodaň et al. 2020), the mean \
             over τ = 0.05…0.50·d of the share with MSSD < τ, and over τ = 5…50 px (× width / \
             640) of the share with MSPD < τ; both the largest model-point distance (3D, or \
             projected in the image), minimised over the object's symmetries. A failure is \
             wrong at every threshold.\n",
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    fn write_case(root: &Path, name: &str, pose: &Pose, object: &str) {
        let d = root.join(name);
        std::fs::create_dir_all(&d).unwrap();
        let t = pose.translation;
        let gt = serde_json::json!({"R": pose.rotation_row_major(), "t": [t.x, t.y, t.z]});
        std::fs::write(d.join("gt.json"), gt.to_string()).unwrap();
        std::fs::write(
            d.join("meta.json"),
            serde_json::json!({"object_id": object}).to_string(),
        )
        .unwrap();
    }

    /// Three cases at z = 2.8; a method that is exact on one, 10° and 0.05 off on another and
    /// fails the third; a second that is 90° off on all, with one line missing.
    #[test]
    fn scores_hand_made_case_folders_and_jsonl() {
        let dir = tempfile::tempdir().unwrap();
        let at = DVec3::new(0.0, 0.0, 2.8);
        let truths = [
            Pose::from_translation(at),
            Pose::from_axis_angle(DVec3::Y, 0.5, at),
            Pose::from_axis_angle(DVec3::X, 2.0, at),
        ];
        for (i, p) in truths.iter().enumerate() {
            write_case(
                dir.path(),
                &format!("case_{i:05}"),
                p,
                &format!("{}", 800 + i),
            );
        }
        let off = |p: &Pose, deg: f64, dt: DVec3| {
            Pose::from_axis_angle(DVec3::Z, deg.to_radians(), dt).compose(p)
        };
        let lines = [
            ResultLine::from_pose("case_00000", "a", &truths[0], 0.1),
            ResultLine::from_pose(
                "case_00001",
                "a",
                &off(&truths[1], 10.0, DVec3::new(0.03, 0.04, 0.0)),
                0.3,
            ),
            ResultLine::failed("case_00002", "a", "no inliers", 0.2),
            ResultLine::from_pose("case_00000", "b", &off(&truths[0], 90.0, DVec3::ZERO), 1.0),
            ResultLine::from_pose("case_00001", "b", &off(&truths[1], 90.0, DVec3::ZERO), 1.0),
        ];
        let a_path = dir.path().join("a.jsonl");
        write_result_lines(&a_path, &lines[..3]).unwrap();
        let b_path = dir.path().join("b.jsonl");
        // A non-rotation in an ok line is a failure, not a read error.
        let mut bad = lines[4].clone();
        bad.rotation = Some([[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let mut text = serde_json::to_string(&lines[3]).unwrap() + "\n\n";
        text += &serde_json::to_string(&bad).unwrap();
        std::fs::write(&b_path, text).unwrap();

        let scores = score_files(dir.path(), &[a_path.clone(), b_path]).unwrap();
        assert_eq!(scores.len(), 2);
        let a = &scores[0];
        assert_eq!(a.method(), "a");
        assert_eq!((a.scored, a.failed, a.missing), (2, 1, 0));
        let rot = &a.result.rotation_errors_deg;
        assert!(rot[0].abs() < 1e-6 && (rot[1] - 10.0).abs() < 1e-6 && rot[2] == 180.0);
        let tsq = &a.result.translation_sq_errors;
        // The Z rotation is applied about the camera origin, so t moves too: compute the truth.
        let moved = off(&truths[1], 10.0, DVec3::new(0.03, 0.04, 0.0)).translation;
        assert!((tsq[1] - moved.distance_squared(at)).abs() < 1e-12);
        assert!(tsq[2].is_infinite());
        let sm = &a.result.summary;
        assert_eq!((sm.count, sm.failures), (3, 1));
        assert_eq!(
            sm.rotation_accuracy,
            vec![(5.0, 1.0 / 3.0), (10.0, 2.0 / 3.0), (15.0, 2.0 / 3.0)]
        );
        assert!((sm.rotation_map_15 - 5.0 / 9.0).abs() < 1e-12);
        assert!((sm.rotation_median_deg - 10.0).abs() < 1e-6);
        assert_eq!(a.result.seconds_median, Some(0.2)); // the two scored lines: 0.1 and 0.3
        assert_eq!(a.cases[2].object_id.as_deref(), Some("802"));
        assert!(
            matches!(&a.cases[2].outcome, CaseOutcome::Failed { error } if error == "no inliers")
        );
        // AUC on [0, 15°] of errors {0, 10, 180}: (1/3·10 + 2/3·5) / 15 = 4/9.
        assert!(
            (a.rotation_auc_15 - 4.0 / 9.0).abs() < 1e-3,
            "{}",
            a.rotation_auc_15
        );

        let b = &scores[1];
        assert_eq!((b.scored, b.failed, b.missing), (1, 1, 1));
        assert!((b.result.rotation_errors_deg[0] - 90.0).abs() < 1e-6);
        assert_eq!(b.result.summary.rotation_median_deg, 180.0);
        assert_eq!(b.result.summary.rotation_accuracy[2], (15.0, 0.0));
        let reasons = b.failure_reasons(5);
        assert_eq!(reasons.len(), 2);
        assert!(reasons.iter().any(|r| r.0 == "no result line"));
        assert!(
            reasons.iter().any(|r| r.0.contains("not orthonormal")),
            "{reasons:?}"
        );

        let table = markdown_cases_table(&scores);
        assert!(
            table.contains("| a | 3 | 1 | 10.00 | 0.333 | 0.667 | 0.667 | 0.556 |"),
            "{table}"
        );
        assert!(table.contains("| b | 3 | 2 | 180.00 |"), "{table}");
        assert!(table.contains("Yi et al. 2018"));
    }

    /// With geometry on every case, a method gets ADD-S / AR_MSSD / AR_MSPD (a failure wrong
    /// at every threshold) and the table grows their columns; one case without geometry and
    /// there are none.
    #[test]
    fn cases_with_geometry_get_the_object_metrics_and_their_columns() {
        use crate::object_scores::CaseGeometry;
        let pts: Vec<ic_geometry::glam::Vec3> = (0..8)
            .map(|i| {
                ic_geometry::glam::Vec3::new(
                    (i & 1) as f32 - 0.5,
                    ((i >> 1) & 1) as f32 - 0.5,
                    ((i >> 2) & 1) as f32 * 0.5 - 0.25,
                )
            })
            .collect();
        let half = Pose::from_axis_angle(DVec3::Z, std::f64::consts::PI, DVec3::ZERO);
        let geometry = Arc::new(CaseGeometry::new(
            pts,
            vec![half],
            Some(ic_geometry::Intrinsics::KINECT_640X480),
        ));
        let at = Pose::from_translation(DVec3::new(0.0, 0.0, 3.0));
        let mut truths = vec![CaseTruth::new("a", at), CaseTruth::new("b", at)];
        for t in &mut truths {
            t.geometry = Some(geometry.clone());
        }
        // "a": off by the symmetry (180° in rotation, exact in every object metric); "b" fails.
        let lines = [
            ResultLine::from_pose("a", "m", &at.compose(&half), 0.1),
            ResultLine::failed("b", "m", "no pose", 0.1),
        ];
        let scores = score_results(&truths, &lines).unwrap();
        let o = scores[0].object.as_ref().unwrap();
        assert_eq!(o.cases, 2);
        assert!((o.add_s_01d - 0.5).abs() < 1e-12 && (o.ar_mssd - 0.5).abs() < 1e-12);
        assert!((o.ar_mspd.unwrap() - 0.5).abs() < 1e-12);
        assert!(scores[0].result.rotation_errors_deg[0] > 179.0);
        let table = markdown_cases_table(&scores);
        assert!(table.contains("| AR_MSSD |"), "{table}");
        assert!(table.contains("| 0.500 | 0.500 | 0.500 |"), "{table}");
        truths[1].geometry = None;
        let scores = score_results(&truths, &lines).unwrap();
        assert!(scores[0].object.is_none());
        assert!(!markdown_cases_table(&scores).contains("AR_MSSD"));
    }

    #[test]
    fn bad_input_is_an_error_naming_the_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        write_case(dir.path(), "case_00000", &Pose::IDENTITY, "1");
        let truths = read_case_truths(dir.path()).unwrap();
        assert_eq!(truths[0].case, "case_00000");
        // A single case folder works too.
        assert_eq!(
            read_case_truths(&dir.path().join("case_00000"))
                .unwrap()
                .len(),
            1
        );

        let p = dir.path().join("r.jsonl");
        std::fs::write(
            &p,
            "{\"case\": \"case_00000\", \"method\": \"x\", \"ok\": true}\nnot json\n",
        )
        .unwrap();
        let e = read_result_lines(&p).unwrap_err().to_string();
        assert!(e.contains("r.jsonl") && e.contains("line 2"), "{e}");
        std::fs::write(&p, "{\"case\": \"case_00000\", \"ok\": true}\n").unwrap();
        let e = read_result_lines(&p).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("method"), "{e}");

        // Unknown cases and duplicates.
        let line = ResultLine::from_pose("case_00001", "x", &Pose::IDENTITY, 0.0);
        assert!(score_results(&truths, &[line]).is_err());
        let line = ResultLine::from_pose("case_00000", "x", &Pose::IDENTITY, 0.0);
        let e = score_results(&truths, &[line.clone(), line])
            .unwrap_err()
            .to_string();
        assert!(e.contains("second line"), "{e}");

        // ok with R = null, and null inside t (serde_json's NaN): failures.
        std::fs::write(
            &p,
            "{\"case\": \"case_00000\", \"method\": \"x\", \"R\": null, \"t\": null, \"ok\": true, \"seconds\": 1, \"error\": null}\n\
             {\"case\": \"case_00000\", \"method\": \"y\", \"R\": [[1,0,0],[0,1,0],[0,0,1]], \"t\": [0, null, 0], \"ok\": true, \"seconds\": 1, \"error\": null}\n",
        )
        .unwrap();
        let s = score_files(dir.path(), &[p]).unwrap();
        assert!(
            s.iter()
                .all(|m| m.failed == 1 && m.result.seconds_median.is_none())
        );

        // Broken gt.json.
        std::fs::write(dir.path().join("case_00000/gt.json"), "{\"R\": [1, 2]}").unwrap();
        let e = read_case_truths(dir.path()).unwrap_err().to_string();
        assert!(e.contains("gt.json") && e.contains("3×3"), "{e}");
    }
}
