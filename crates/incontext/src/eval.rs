//! `incontext eval`: our methods on a test set.
//!
//! - `--dataset DIR`: a BOP dataset (`models/` + `<split>/`) or a `cargo xtask gen-data`
//!   folder (its `noback/`, `room/` and `clutter/` datasets). Writes, per dataset, the `ic_eval` tables
//!   (`results.md`, `results.json`), accuracy curves (`rotation.{png,svg}`,
//!   `translation.{png,svg}`), one BOP results CSV per method (`<method>_<dataset>-<split>.csv`:
//!   `scene_id,im_id,obj_id,score,R,t,time`, R row-major, t in mm, time in seconds) and the
//!   per-instance errors (`per_image.jsonl`). Errors are in normalised object units (the
//!   paper's thresholds); ADD-S is divided by the object's diameter. What is registered: the
//!   targets of `test_targets_bop19.json` (else every annotated object of every image); a
//!   target of several instances through `register --all`'s search (at most `inst_count`
//!   estimates), one instance through `register`'s; each estimate, best first, claims the
//!   unclaimed true instance nearest it (ADD-S), and an unclaimed one counts as a failure.
//!   `--gt-mask` registers each true instance on its own visible mask instead. The CSV
//!   carries every estimate, with the image's total time on each of its rows (BOP's rule).
//!   A target with no annotated instance (a scene without `scene_gt.json`, as in a test set
//!   whose ground truth is withheld) is registered and written to the CSV, not scored: its
//!   `per_image.jsonl` line says `"scored": false`; `--gt-mask` leaves it out.
//! - `--cases DIR`: the registration cases of `cargo xtask export-cases`. Writes one JSON line
//!   per case and method, `{"case", "method", "R", "t", "seconds", "ok", "error"}` (the format
//!   of `benches/peers/open3d_peers.py`), then, when a pose was found, its `confidence` and
//!   `verdict` (and `details` with `--details`): `target ≈ R·source + t` in normalised units;
//!   `seconds` covers everything after reading the files (segmentation of `depth.png`
//!   included for room cases). `gt.json` is never read.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ic_data::bop::{BopDataset, BopLoadOptions, BopTarget};
use ic_data::{CorpusOptions, ROOM_UNIT_MM};
use ic_eval::cases::CaseFolder;
use ic_eval::{Curve, MethodResult, PoseErrors, Summary};
use ic_geometry::glam::Vec3;
use ic_geometry::{Image, Mask};
use ic_pose::{Head, Refine};
use serde_json::{Value, json};

use crate::error::{CliError, Result};
use crate::inputs;
use crate::pipeline::{Object, Pipeline, PipelineError, PipelineOptions, Registration};

/// Flags of `incontext eval`.
#[derive(clap::Args, Debug, Clone, serde::Serialize)]
#[command(group(clap::ArgGroup::new("input").required(true).args(["dataset", "cases", "frames"])))]
pub struct EvalArgs {
    /// A BOP dataset (models/ — T-LESS's models_cad/ when there is no models/ — and SPLIT/, e.g.
    /// `--split test_primesense` for T-LESS) or a `cargo xtask gen-data` folder (noback/,
    /// room/, clutter/). Scenes without scene_gt.json (withheld ground truth) are registered
    /// into the BOP CSV, not scored; their targets come from test_targets_bop19.json.
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// A folder of registration cases written by `cargo xtask export-cases`.
    #[arg(long)]
    pub cases: Option<PathBuf>,
    /// Real frames without ground truth: a folder with `model.ply` (mm), `camera.json` and
    /// depth maps in `*/depth/` (PNG, or TIFF / EXR as `register` reads them). Each frame is
    /// registered as `register` and `register --all` do, and each pose judged by rendering it
    /// against the depth map (`--tolerance-mm`).
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// --frames: a rendered pixel agrees with the depth map within this many millimetres.
    #[arg(long, default_value_t = 10.0)]
    pub tolerance_mm: f64,
    /// --frames: as `register --all --min-confidence`: the `--all` search also returns
    /// `uncertain` instances whose confidence reaches this, in [0, 1].
    #[arg(long, value_parser = crate::register::parse_probability)]
    pub min_confidence: Option<f64>,
    /// The BOP split folder (--dataset).
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Methods: ours-softmax, ours-softmax-icp, ours-ot, ours-ot-icp (one network pass, as in
    /// the paper); ours-softmax-verify, ours-ot-verify (hypothesise and verify, as `register`
    /// does by default); ours-softmax-sweep, ours-ot-sweep (the same sweep and
    /// render-and-compare choice without ICP: the one-shot pose for any viewpoint). Repeat the
    /// flag or separate with commas. Default: ours-softmax-icp.
    #[arg(long = "method", value_delimiter = ',')]
    pub methods: Vec<String>,
    /// --dataset: the output folder (default eval-out); --cases: the results file (default
    /// results.jsonl).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Use the ground-truth masks (BOP mask_visib/, or a case's mask.png) instead of the
    /// segmentation network.
    #[arg(long)]
    pub gt_mask: bool,
    /// Only the first N images (--dataset), cases (--cases) or frames (--frames, in name
    /// order; at least 1).
    #[arg(long)]
    pub limit: Option<usize>,
    /// --cases: add a "details" object (confidence, point counts, stage seconds) to each line.
    #[arg(long)]
    pub details: bool,
    /// --dataset, without --gt-mask: also register each of the best N instances the
    /// segmentation finds whose size fits the model, whatever its verdict, and write every
    /// one with its errors (to the nearest true instance of the target), its verification and
    /// its verified hypotheses (the pose network that made each, its score, its ADD-S to the
    /// returned pose and to the truth, over the diameter) to `candidates.jsonl` — the data for
    /// studying the verdict in clutter. 0 = off.
    #[arg(long, default_value_t = 0)]
    pub candidates: usize,
    /// A pose checkpoint instead of the shipped one (its head must be the methods' head); it
    /// is then the only pose network unless --second-pose-model is given.
    #[arg(long)]
    pub pose_model: Option<PathBuf>,
    /// A second pose checkpoint of the same head whose hypotheses join the main network's in
    /// the verified and sweep methods, instead of the shipped second network (softmax only).
    #[arg(long, conflicts_with = "no_second_pose")]
    pub second_pose_model: Option<PathBuf>,
    /// The verified and sweep methods use the main pose network alone.
    #[arg(long)]
    pub no_second_pose: bool,
    /// A segmentation checkpoint instead of the shipped ones (it is then the only one: no
    /// one-object second opinion).
    #[arg(long)]
    pub seg_model: Option<PathBuf>,
    /// The pose networks' attention keys (see `register`): N per cloud or `all`; default:
    /// each network's own.
    #[arg(long, value_parser = crate::register::parse_attention_keys)]
    pub attention_keys: Option<crate::register::AttentionKeys>,
    /// Pose hypotheses per registration (1 = the paper's one-shot pipeline; see `register`).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub hypotheses: u32,
    /// Rotation hypotheses of the `-verify` methods: 12, 24 (default) or 60.
    #[arg(long, value_parser = crate::register::parse_rotations)]
    pub rotations: Option<usize>,
    /// Model points per rotated copy in the `-verify` methods' sweep (observed: ¾ of it);
    /// default: the pipeline's.
    #[arg(long)]
    pub sweep_points: Option<usize>,
    /// Hypotheses of the `-verify` methods refined by ICP and verified (see `register`).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=60))]
    pub verify_top: u32,
    /// Rotated copies of the `-verify` methods that go on through the transformer (see
    /// `register`); default: the pipeline's.
    #[arg(long)]
    pub sweep_keep: Option<usize>,
    /// Sampled poses per rotated copy in the `-verify` methods (see `register`); default: the
    /// pipeline's.
    #[arg(long)]
    pub sampled_hypotheses: Option<usize>,
    /// Passes of the network over each verified hypothesis of the `-verify` and `-sweep`
    /// methods (see `register`); default: the pipeline's.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=4))]
    pub network_passes: Option<u32>,
    /// Hypotheses the second network pass takes (see `register`); default: the pipeline's.
    #[arg(long)]
    pub pass_top: Option<usize>,
    /// Instances of the model's size registered until one is `ok` (see `register`; 0 = every
    /// one that fits); default: the pipeline's.
    #[arg(long)]
    pub instance_tries: Option<usize>,
}

impl EvalArgs {
    fn pipeline_options(&self) -> PipelineOptions {
        PipelineOptions {
            hypotheses: self.hypotheses as usize,
            rotations: self.rotations.unwrap_or(1),
            verify_top: self.verify_top as usize,
            sweep_points: self
                .sweep_points
                .unwrap_or(PipelineOptions::default().sweep_points),
            sweep_keep: self
                .sweep_keep
                .unwrap_or(PipelineOptions::default().sweep_keep),
            sampled_hypotheses: self
                .sampled_hypotheses
                .unwrap_or(PipelineOptions::default().sampled_hypotheses),
            network_passes: self
                .network_passes
                .map_or(PipelineOptions::default().network_passes, |p| p as usize),
            pass_top: self.pass_top.unwrap_or(PipelineOptions::default().pass_top),
            instance_tries: self
                .instance_tries
                .unwrap_or(PipelineOptions::default().instance_tries),
            ..PipelineOptions::default()
        }
    }
}

/// One of our methods: a head and a refinement.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Method {
    pub name: String,
    pub head: Head,
    pub refine: Refine,
    /// Rotation hypotheses verified by render-and-compare (`-verify` methods: the 24
    /// rotations of the cube group, or `--rotations`); `None`: the pipeline's setting.
    pub rotations: Option<usize>,
}

/// The rotations of the `-verify` methods unless `--rotations` says otherwise.
pub const VERIFY_ROTATIONS: usize = 24;

impl std::str::FromStr for Method {
    type Err = CliError;
    fn from_str(s: &str) -> Result<Method> {
        let (head, refine, verify) = match s.trim() {
            "ours-softmax" => (Head::Softmax, Refine::None, false),
            "ours-softmax-icp" => (Head::Softmax, Refine::Icp, false),
            "ours-softmax-verify" => (Head::Softmax, Refine::Icp, true),
            "ours-softmax-sweep" => (Head::Softmax, Refine::None, true),
            "ours-ot" => (Head::Ot, Refine::None, false),
            "ours-ot-icp" => (Head::Ot, Refine::Icp, false),
            "ours-ot-verify" => (Head::Ot, Refine::Icp, true),
            "ours-ot-sweep" => (Head::Ot, Refine::None, true),
            other => {
                return Err(CliError::input(format!(
                    "--method {other:?}: expected ours-softmax, ours-softmax-icp, ours-softmax-verify, \
                     ours-softmax-sweep, ours-ot, ours-ot-icp, ours-ot-verify or ours-ot-sweep"
                )));
            }
        };
        Ok(Method {
            name: s.trim().to_string(),
            head,
            refine,
            rotations: verify.then_some(VERIFY_ROTATIONS),
        })
    }
}

/// The methods of `names` (default: ours-softmax-icp), without duplicates.
pub fn parse_methods(names: &[String]) -> Result<Vec<Method>> {
    let mut out: Vec<Method> = Vec::new();
    for n in names.iter().filter(|n| !n.trim().is_empty()) {
        let m: Method = n.parse()?;
        if !out.contains(&m) {
            out.push(m);
        }
    }
    if out.is_empty() {
        out.push("ours-softmax-icp".parse()?);
    }
    Ok(out)
}

/// One pipeline per head the methods need.
pub struct Pipelines {
    /// Each head's pipeline and the `--rotations` it was loaded with.
    by_head: BTreeMap<&'static str, (Pipeline, usize)>,
}

impl Pipelines {
    /// One pipeline per head of `methods`, with the networks `args` names (`--pose-model`,
    /// `--second-pose-model`, `--no-second-pose`, `--seg-model`); the segmentation network
    /// only `with_seg`.
    pub fn load(
        methods: &[Method],
        args: &EvalArgs,
        with_seg: bool,
        options: PipelineOptions,
    ) -> Result<Pipelines> {
        let mut by_head = BTreeMap::new();
        for m in methods {
            if by_head.contains_key(m.head.as_str()) {
                continue;
            }
            let mut builder = Pipeline::builder()
                .head(m.head)
                .segmentation(with_seg)
                .options(options)
                .second_pose(!args.no_second_pose);
            if let Some(path) = &args.pose_model {
                builder = builder.pose_model(path);
            }
            if let Some(path) = &args.second_pose_model {
                builder = builder.second_pose_model(path);
            }
            if let Some(path) = &args.seg_model {
                builder = builder.seg_model(path);
            }
            if let Some(crate::register::AttentionKeys(keys)) = args.attention_keys {
                builder = builder.attention_keys(keys);
            }
            let p = builder.build()?;
            by_head.insert(m.head.as_str(), (p, options.rotations));
        }
        Ok(Pipelines { by_head })
    }

    /// The pipeline of `method`, set to its refinement and rotation hypotheses (`-verify`
    /// methods: `--rotations` when above 1, else [`VERIFY_ROTATIONS`]; other methods: 1).
    pub fn get(&mut self, method: &Method) -> &Pipeline {
        let (p, base) = self
            .by_head
            .get_mut(method.head.as_str())
            .expect("a pipeline was loaded for every method's head");
        p.options.refine = method.refine;
        p.options.rotations = match method.rotations {
            Some(_) if *base > 1 => *base,
            Some(default) => default,
            None => 1,
        };
        p
    }

    pub fn describe(&self) -> Value {
        self.by_head
            .iter()
            .map(|(h, (p, _))| (h.to_string(), p.describe()))
            .collect::<serde_json::Map<_, _>>()
            .into()
    }
}

/// A seed that depends only on (seed, name): results do not depend on what ran before.
pub fn case_seed(seed: u64, name: &str) -> u64 {
    let h = name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    });
    ic_data::mix_seed(seed, h)
}

pub fn run(args: &EvalArgs, seed: u64) -> Result<Value> {
    let methods = parse_methods(&args.methods)?;
    match (&args.dataset, &args.cases, &args.frames) {
        (Some(d), None, None) => run_dataset(args, d, &methods, seed),
        (None, Some(c), None) => run_cases(args, c, &methods, seed),
        (None, None, Some(f)) => {
            let methods = if args.methods.is_empty() {
                parse_methods(&["ours-softmax-verify".into()])?
            } else {
                methods
            };
            run_frames(args, f, &methods, seed)
        }
        _ => Err(CliError::input(
            "give exactly one of --dataset, --cases and --frames",
        )),
    }
}

fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    if !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{msg:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} (eta {eta})",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_string());
    bar
}

// ---------------------------------------------------------------------------------------------
// --cases

/// The model of a case: its points (`source.ply`), or its normalised mesh (`model.ply`, in
/// the view cases of `export-cases --set view`), registered like a user's mesh.
pub enum CaseModel {
    Points(Vec<Vec3>),
    Mesh(ic_geometry::Mesh),
}

/// What a case folder holds, read before the clock starts.
pub enum CaseInput {
    /// Object alone: the observed points of `target.ply`.
    Points(Vec<Vec3>),
    /// Room: the depth map in normalised units, the camera and an optional mask.
    Depth {
        depth: ic_geometry::DepthImage,
        intrinsics: ic_geometry::Intrinsics,
        mask: Option<Mask>,
    },
}

/// A room case holds `depth.png` and `camera.json` (an object-alone case only the PLY files).
pub fn is_room_case(dir: &Path) -> bool {
    CaseFolder::new(dir).has_depth()
}

/// Reads a case folder (never `gt.json`): the model points (`source.ply`) and the observation.
pub fn read_case(dir: &Path, gt_mask: bool) -> Result<(CaseModel, CaseInput)> {
    let case = CaseFolder::new(dir);
    let mesh_path = case.model();
    let source = if mesh_path.is_file() {
        CaseModel::Mesh(inputs::read_mesh(&mesh_path)?)
    } else {
        CaseModel::Points(ic_geometry::io::read_ply_cloud(case.source())?.points)
    };
    if !case.has_depth() {
        let target = ic_geometry::io::read_ply_cloud(case.target())?.points;
        return Ok((source, CaseInput::Points(target)));
    }
    let cam_path = case.camera();
    let depth_path = case.depth();
    let camera = inputs::read_camera(&cam_path, || inputs::depth_size(&depth_path))?;
    let unit_mm = camera.unit_mm.unwrap_or_else(|| {
        tracing::warn!(file = %cam_path.display(), "no unit_mm: assuming {ROOM_UNIT_MM} mm per unit");
        ROOM_UNIT_MM
    });
    let mm = inputs::read_depth_mm(&depth_path, &camera)?;
    let to_units = (1.0 / unit_mm) as f32;
    let depth = Image {
        width: mm.width,
        height: mm.height,
        data: mm.data.iter().map(|&z| z * to_units).collect(),
    };
    let mask = if gt_mask {
        let p = case.mask_file().ok_or_else(|| {
            CliError::input(format!(
                "{}: --gt-mask, but the case has no mask.png",
                dir.display()
            ))
        })?;
        Some(inputs::read_mask(&p, &camera.intrinsics)?)
    } else {
        None
    };
    Ok((
        source,
        CaseInput::Depth {
            depth,
            intrinsics: camera.intrinsics,
            mask,
        },
    ))
}

/// Registers a case read by [`read_case`]: everything that `seconds` counts.
pub fn register_case(
    pipeline: &Pipeline,
    model: &CaseModel,
    input: &CaseInput,
    seed: u64,
) -> Result<Registration> {
    let object = match model {
        CaseModel::Points(source) => Object::from_points(source.clone())?,
        CaseModel::Mesh(mesh) => Object::from_mesh(mesh.clone(), seed)?,
    };
    Ok(match input {
        CaseInput::Points(target) => pipeline.register_points(&object, target, seed)?,
        CaseInput::Depth {
            depth,
            intrinsics,
            mask,
        } => pipeline.register_depth_normalised(&object, depth, intrinsics, mask.as_ref(), seed)?,
    })
}

fn case_dirs(root: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(root)
        .map_err(|e| CliError::input(format!("{}: cannot list the cases: {e}", root.display())))?;
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        return Err(CliError::input(format!(
            "{}: no case folders (expected one folder per case with source.ply)",
            root.display()
        )));
    }
    Ok(dirs)
}

fn write_lines(path: &Path, lines: &[String]) -> Result<()> {
    inputs::create_parent(path)?;
    ic_geometry::io::write_atomic_with(
        path,
        |w| {
            for l in lines {
                std::io::Write::write_all(w, l.as_bytes())?;
                std::io::Write::write_all(w, b"\n")?;
            }
            Ok(())
        },
        |e| e,
    )
    .map_err(|e| CliError::input(format!("{}: cannot write: {e}", path.display())))
}

/// One line of the results file, in the field order of `open3d_peers.py`.
#[derive(serde::Serialize)]
struct CaseLine {
    case: String,
    method: String,
    #[serde(rename = "R")]
    r: Option<[[f64; 3]; 3]>,
    t: Option<[f64; 3]>,
    seconds: f64,
    ok: bool,
    error: Option<String>,
    /// The pose's confidence in [0, 1] and its verdict, when a pose was found.
    #[serde(skip_serializing_if = "Option::is_none")]
    confidence: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    verdict: Option<crate::pipeline::Verdict>,
    #[serde(skip_serializing_if = "Option::is_none")]
    details: Option<Value>,
}

fn run_cases(args: &EvalArgs, root: &Path, methods: &[Method], seed: u64) -> Result<Value> {
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("results.jsonl"));
    let ins: Vec<crate::outputs::Named> = [
        ("--pose-model", &args.pose_model),
        ("--second-pose-model", &args.second_pose_model),
        ("--seg-model", &args.seg_model),
    ]
    .iter()
    .filter_map(|(what, p)| p.as_deref().map(|p| crate::outputs::Named::new(what, p)))
    .collect();
    crate::outputs::check_outputs(&ins, &[crate::outputs::Named::new("--out", &out)])?;
    let mut dirs = case_dirs(root)?;
    if let Some(n) = args.limit {
        dirs.truncate(n);
    }
    let any_room = dirs.iter().any(|d| is_room_case(d));
    if args.gt_mask
        && let Some(d) = dirs
            .iter()
            .find(|d| is_room_case(d) && CaseFolder::new(d.as_path()).mask_file().is_none())
    {
        return Err(CliError::input(format!(
            "{}: --gt-mask, but the case has no mask.png (export-cases does not write masks)",
            d.display()
        )));
    }
    let mut pipelines = Pipelines::load(
        methods,
        args,
        any_room && !args.gt_mask,
        args.pipeline_options(),
    )?;
    let config = json!({
        "cases": root, "out": out, "seed": seed, "methods": methods.iter().map(|m| &m.name).collect::<Vec<_>>(),
        "case_count": dirs.len(), "gt_mask": args.gt_mask, "networks": pipelines.describe(),
    });
    tracing::info!(seed, config = %config, "incontext eval --cases");
    let total = dirs.len() * methods.len();
    let (mut lines, mut failures, mut k) = (Vec::new(), 0usize, 0usize);
    let mut seconds: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    let started = Instant::now();
    for dir in &dirs {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let read = read_case(dir, args.gt_mask);
        let cseed = case_seed(seed, &name);
        for m in methods {
            k += 1;
            let mut rec = CaseLine {
                case: name.clone(),
                method: m.name.clone(),
                r: None,
                t: None,
                seconds: 0.0,
                ok: false,
                error: None,
                confidence: None,
                verdict: None,
                details: None,
            };
            match &read {
                Err(e) => rec.error = Some(e.message.clone()),
                Ok((source, input)) => {
                    let pipeline = pipelines.get(m);
                    let clock = Instant::now();
                    let result = register_case(pipeline, source, input, cseed);
                    let s = clock.elapsed().as_secs_f64();
                    rec.seconds = s;
                    match result {
                        Ok(r) => {
                            let p = &r.pose_normalised;
                            rec.r = Some(p.rotation_row_major());
                            rec.t = Some([p.translation.x, p.translation.y, p.translation.z]);
                            rec.ok = true;
                            rec.confidence = Some(r.confidence);
                            rec.verdict = Some(r.verdict);
                            seconds.entry(m.name.clone()).or_default().push(s);
                            if args.details {
                                rec.details = Some(json!({
                                    "confidence": r.confidence,
                                    "verdict": r.verdict,
                                    "segmentation": r.segmentation,
                                    "object_points": r.object_points,
                                    "object_voxels": r.object_voxels,
                                    "inlier_count": r.inlier_count,
                                    "icp": r.icp,
                                    "verification": r.verification,
                                    "rival_score": r.rival_score,
                                    "evidence": r.evidence,
                                    "verified": r.verified.iter().map(|h| {
                                        // {"R", "t", "score", "misfit", "icp_rmse", "network"}: the
                                        // pose's serde form, how well it explains the depth and
                                        // which pose network made it (0 main, 1 second).
                                        let mut v = json!(h.pose_normalised);
                                        v["score"] = json!(h.score);
                                        v["misfit"] = json!(h.misfit);
                                        v["icp_rmse"] = json!(h.icp_rmse);
                                        v["network"] = json!(h.network);
                                        v
                                    }).collect::<Vec<_>>(),
                                    "stage_seconds": r.seconds,
                                }));
                            }
                        }
                        Err(e) => rec.error = Some(e.message),
                    }
                }
            }
            failures += !rec.ok as usize;
            tracing::info!(
                "[{k}/{total}] {name} {} {:.3}s {}",
                m.name,
                rec.seconds,
                if rec.ok {
                    "ok".to_string()
                } else {
                    format!("FAILED: {}", rec.error.as_deref().unwrap_or("?"))
                }
            );
            lines.push(
                serde_json::to_string(&rec)
                    .map_err(|e| CliError::internal(format!("serialising a result: {e}")))?,
            );
        }
        write_lines(&out, &lines)?;
    }
    if lines.is_empty() {
        // Nothing to register (e.g. --limit 0): the results file exists, and is empty.
        write_lines(&out, &lines)?;
    }
    let medians: BTreeMap<String, f64> = seconds
        .iter()
        .map(|(m, s)| (m.clone(), ic_eval::median(s)))
        .collect();
    Ok(json!({
        "command": "eval",
        "mode": "cases",
        "seed": seed,
        "results": lines.len(),
        "failed": failures,
        "median_seconds": medians,
        "wall_seconds": started.elapsed().as_secs_f64(),
        "out": out,
    }))
}

// ---------------------------------------------------------------------------------------------
// --dataset

/// The BOP datasets under `dir`: itself, or the `noback/`, `room/` and `clutter/` of a
/// gen-data folder.
fn datasets(dir: &Path, split: &str) -> Result<Vec<(String, PathBuf)>> {
    if !dir.is_dir() {
        return Err(CliError::input(format!("{}: not a folder", dir.display())));
    }
    if ic_data::bop::models_folder(dir).is_some() {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().replace('_', "-"))
            .unwrap_or_else(|| "dataset".into());
        return Ok(vec![(name, dir.to_path_buf())]);
    }
    let subsets: Vec<(String, PathBuf)> = ["noback", "room", "clutter"]
        .iter()
        .map(|n| (n.to_string(), dir.join(n)))
        .filter(|(_, p)| ic_data::bop::models_folder(p).is_some() && p.join(split).is_dir())
        .collect();
    if subsets.is_empty() {
        return Err(CliError::input(format!(
            "{}: neither a BOP dataset (models/, or T-LESS's models_cad/, and {split}/) nor a \
             gen-data folder (noback/, room/)",
            dir.display()
        )));
    }
    Ok(subsets)
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    ic_geometry::io::write_atomic_with(
        path,
        |w| std::io::Write::write_all(w, text.as_bytes()),
        |e| e,
    )
    .map_err(|e| CliError::input(format!("{}: cannot write: {e}", path.display())))
}

/// BOP rows of one method by (scene_id, im_id), with the image's total seconds.
type ImageRows = BTreeMap<(u32, u32), (Vec<String>, f64)>;

fn run_dataset(args: &EvalArgs, dir: &Path, methods: &[Method], seed: u64) -> Result<Value> {
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("eval-out"));
    let subsets = datasets(dir, &args.split)?;
    let mut pipelines = Pipelines::load(
        methods,
        args,
        !args.gt_mask,
        // BOP scores the best `inst_count` estimates of a target whatever their confidence
        // (it only ranks them): several instances come from every one the `--all` search
        // registers, `uncertain` included (whether or not its whole view is consistent), not
        // only the `ok` ones `register --all` returns.
        PipelineOptions {
            all_min_confidence: Some(0.0),
            all_whole_view: false,
            ..args.pipeline_options()
        },
    )?;
    let config = json!({
        "dataset": dir, "split": args.split, "out": out, "seed": seed,
        "methods": methods.iter().map(|m| &m.name).collect::<Vec<_>>(),
        "gt_mask": args.gt_mask, "limit": args.limit, "networks": pipelines.describe(),
        "errors": "normalised object units; add_s divided by the object's diameter",
    });
    tracing::info!(seed, config = %config, "incontext eval --dataset");
    let mut report = serde_json::Map::new();
    let mut tables = String::new();
    for (name, root) in &subsets {
        let ds = BopDataset::open(root, &args.split, CorpusOptions::default())?;
        let targets: Vec<BopTarget> = ds.targets().to_vec();
        let n = args.limit.map_or(targets.len(), |l| l.min(targets.len()));
        let sub_out = if subsets.len() > 1 {
            out.join(name)
        } else {
            out.clone()
        };
        inputs::create_dir(&sub_out)?;
        let mut errors: BTreeMap<String, Vec<Option<PoseErrors>>> = BTreeMap::new();
        let mut times: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        // BOP rows per method and image, written with the image's total time (BOP's rule:
        // one time per image, the same on each of its rows).
        let mut rows: BTreeMap<String, ImageRows> = BTreeMap::new();
        let mut per_image = Vec::new();
        let mut candidates = Vec::new();
        let mut objects: BTreeMap<String, (Object, f64)> = BTreeMap::new();
        // Targets without an annotated instance (a withheld ground truth): registered and
        // written to the BOP CSV, not scored; with --gt-mask (no mask to give) left out.
        let (mut unscored, mut no_mask) = (0usize, 0usize);
        let bar = progress(n as u64, name);
        for target in &targets[..n] {
            let gt_indices = ds.instances_of(target);
            if gt_indices.is_empty() && args.gt_mask {
                no_mask += 1;
                bar.inc(1);
                continue;
            }
            let samples: Vec<_> = gt_indices
                .iter()
                .map(|&i| {
                    ds.load(
                        i,
                        &BopLoadOptions {
                            seed,
                            ..BopLoadOptions::default()
                        },
                    )
                })
                .collect::<std::result::Result<_, _>>()?;
            // BOP's rule: a target of `inst_count` instances is scored on its `inst_count`
            // most visible true instances; a copy hidden behind the others is not a target.
            let keep = most_visible(
                &samples.iter().map(visible_fraction).collect::<Vec<_>>(),
                target.inst_count,
            );
            let gt_indices: Vec<usize> = keep.iter().map(|&k| gt_indices[k]).collect();
            let mut samples: Vec<Option<ic_data::RoomSample>> =
                samples.into_iter().map(Some).collect();
            let samples: Vec<ic_data::RoomSample> =
                keep.iter().filter_map(|&k| samples[k].take()).collect();
            // The image every estimate comes from: the first true instance's, or the image
            // alone when none is annotated.
            let bare;
            let (depth, intrinsics, object_id) = match samples.first() {
                Some(first) => (&first.depth, &first.intrinsics, &first.object_id),
                None => {
                    unscored += 1;
                    bare = ds.image(target.scene_id, target.im_id, target.obj_id)?;
                    (&bare.depth, &bare.intrinsics, &bare.object.id)
                }
            };
            if !objects.contains_key(object_id) {
                let corpus = ds.corpus();
                let obj = corpus
                    .position(object_id)
                    .map(|p| corpus.object(p))
                    .ok_or_else(|| CliError::internal("object missing from the corpus"))??;
                let object = Object::from_normalised(
                    Some(obj.mesh.clone()),
                    obj.normalisation,
                    obj.model_points.clone(),
                )?;
                let d = ic_eval::diameter(&object.points[..object.points.len().min(1024)]);
                objects.insert(object_id.clone(), (object, d));
            }
            let (object, diameter) = &objects[object_id];
            let cseed = case_seed(
                seed,
                &format!("{}/{}/{}", target.scene_id, target.im_id, target.obj_id),
            );
            for m in methods {
                let pipeline = pipelines.get(m);
                let clock = Instant::now();
                // Estimates, best first: one per true instance with --gt-mask (its own mask),
                // every instance found for a target of several, else the best one.
                let mut estimates: Vec<std::result::Result<Registration, PipelineError>> =
                    Vec::new();
                if args.gt_mask {
                    for sample in &samples {
                        estimates.push(pipeline.register_depth_normalised(
                            object,
                            &sample.depth,
                            &sample.intrinsics,
                            Some(&sample.mask_visib),
                            cseed,
                        ));
                    }
                } else if target.inst_count > 1 {
                    match pipeline.register_depth_all_normalised(object, depth, intrinsics, cseed) {
                        Ok(found) => {
                            estimates.extend(found.into_iter().take(target.inst_count).map(Ok))
                        }
                        Err(e) => estimates.push(Err(e)),
                    }
                } else {
                    estimates.push(
                        pipeline.register_depth_normalised(object, depth, intrinsics, None, cseed),
                    );
                }
                let s = clock.elapsed().as_secs_f64();
                // A candidate line needs the truth to score its hypotheses against.
                if args.candidates > 0 && !args.gt_mask && !samples.is_empty() {
                    let every = pipeline.register_every_instance_normalised(
                        object,
                        depth,
                        intrinsics,
                        args.candidates,
                        cseed,
                    )?;
                    for r in &every {
                        candidates.push(candidate_line(
                            target, &m.name, r, object, *diameter, &samples,
                        )?);
                    }
                }
                let found: Vec<&Registration> =
                    estimates.iter().filter_map(|e| e.as_ref().ok()).collect();
                // Each estimate (best first) claims the unclaimed true instance nearest it
                // (ADD-S); with --gt-mask, the estimate from an instance's own mask is that
                // instance's. A true instance no estimate claims is a failure.
                let mut claimed: Vec<Option<&Registration>> = vec![None; samples.len()];
                for (k, r) in estimates.iter().enumerate() {
                    let Ok(r) = r else { continue };
                    let near = if args.gt_mask {
                        Some(k)
                    } else {
                        (0..samples.len())
                            .filter(|&g| claimed[g].is_none())
                            .min_by(|&a, &b| {
                                let d =
                                    |g: usize| object.add_s(&r.pose_normalised, &samples[g].pose);
                                d(a).total_cmp(&d(b))
                            })
                    };
                    if let Some(g) = near.filter(|&g| g < samples.len() && claimed[g].is_none()) {
                        claimed[g] = Some(r);
                    }
                }
                let mut recs = Vec::new();
                for (g, sample) in samples.iter().enumerate() {
                    let inst = ds.instances()[gt_indices[g]];
                    let mut rec = json!({"scene_id": inst.scene_id, "im_id": inst.im_id, "obj_id": inst.obj_id, "gt_index": inst.gt_index, "method": m.name, "seconds": s});
                    match claimed[g] {
                        Some(r) => {
                            let mut e = PoseErrors::compute(
                                &r.pose_normalised,
                                &sample.pose,
                                Some(&object.points),
                            )?;
                            e.add_s = e.add_s.map(|a| a / diameter);
                            e.add = e.add.map(|a| a / diameter);
                            errors.entry(m.name.clone()).or_default().push(Some(e));
                            rec["ok"] = json!(true);
                            rec["errors"] = json!(e);
                            rec["confidence"] = json!(r.confidence);
                            rec["verdict"] = json!(r.verdict);
                            rec["verification"] = json!(r.verification);
                            rec["whole_view"] = json!(r.whole_view);
                            rec["instance"] = json!(r.instance);
                        }
                        None => {
                            errors.entry(m.name.clone()).or_default().push(None);
                            rec["ok"] = json!(false);
                            let why = estimates
                                .iter()
                                .find_map(|e| e.as_ref().err().map(|e| e.message().to_string()))
                                .unwrap_or_else(|| "no estimate for this instance".into());
                            tracing::debug!(method = %m.name, "failed: {why}");
                            rec["error"] = json!(why);
                        }
                    }
                    recs.push(rec.to_string());
                }
                if samples.is_empty() {
                    // Nothing to score: the line says what was returned.
                    let mut rec = json!({"scene_id": target.scene_id, "im_id": target.im_id, "obj_id": target.obj_id, "method": m.name, "seconds": s, "scored": false, "estimates": found.len()});
                    if let Some(e) = estimates.iter().find_map(|e| e.as_ref().err()) {
                        rec["error"] = json!(e.message());
                    }
                    recs.push(rec.to_string());
                }
                times.entry(m.name.clone()).or_default().push(s);
                per_image.extend(recs);
                let join = |v: &[f64]| {
                    v.iter()
                        .map(|x| format!("{x:.9}"))
                        .collect::<Vec<_>>()
                        .join(" ")
                };
                let image = rows
                    .entry(m.name.clone())
                    .or_default()
                    .entry((target.scene_id, target.im_id))
                    .or_default();
                image.1 += s;
                for r in &found {
                    let rr = r.pose.rotation_row_major().concat();
                    let t = r.pose.translation; // mm: BOP models are in mm
                    image.0.push(format!(
                        "{},{},{},{:.6},{},{}",
                        target.scene_id,
                        target.im_id,
                        target.obj_id,
                        r.confidence,
                        join(&rr),
                        join(&[t.x, t.y, t.z]),
                    ));
                }
            }
            bar.inc(1);
        }
        let csv: BTreeMap<String, String> = methods
            .iter()
            .map(|m| {
                let mut text = "scene_id,im_id,obj_id,score,R,t,time\n".to_string();
                for (rows, time) in rows.get(&m.name).into_iter().flat_map(|r| r.values()) {
                    for row in rows {
                        text.push_str(&format!("{row},{time:.6}\n"));
                    }
                }
                (m.name.clone(), text)
            })
            .collect();
        bar.finish_and_clear();
        let results: Vec<MethodResult> = methods
            .iter()
            .map(|m| {
                let e = errors.remove(&m.name).unwrap_or_default();
                let pick = |f: fn(&PoseErrors) -> f64| -> Vec<f64> {
                    e.iter()
                        .map(|x| x.as_ref().map_or(f64::INFINITY, f))
                        .collect()
                };
                MethodResult {
                    method: m.name.clone(),
                    summary: Summary::new(&e, Some(1.0)),
                    rotation_errors_deg: pick(|x| x.rotation_deg),
                    translation_sq_errors: pick(|x| x.translation_sq),
                    seconds_median: times.get(&m.name).map(|t| ic_eval::median(t)),
                }
            })
            .collect();
        let table = ic_eval::markdown_table(&results);
        let heading = format!(
            "## {name} ({} targets of {}, split {}{}{})\n\n",
            n,
            root.display(),
            args.split,
            if args.gt_mask {
                ", ground-truth masks"
            } else {
                ""
            },
            match (unscored, no_mask) {
                (0, 0) => String::new(),
                (k, 0) =>
                    format!("; {k} without ground truth: registered and in the BOP CSV, not scored"),
                (_, k) => format!("; {k} without ground truth left out (no mask to give)"),
            }
        );
        write_text(&sub_out.join("results.md"), &format!("{heading}{table}"))?;
        ic_eval::write_json(&sub_out.join("results.json"), &results)?;
        write_lines(&sub_out.join("per_image.jsonl"), &per_image)?;
        if args.candidates > 0 && !args.gt_mask {
            write_lines(&sub_out.join("candidates.jsonl"), &candidates)?;
        }
        for ext in ["png", "svg"] {
            ic_eval::plot_accuracy_curves(
                &sub_out.join(format!("rotation.{ext}")),
                &results,
                Curve::Rotation,
                30.0,
            )?;
            ic_eval::plot_accuracy_curves(
                &sub_out.join(format!("translation.{ext}")),
                &results,
                Curve::TranslationSq,
                0.02,
            )?;
        }
        let mut csv_files = Vec::new();
        for (m, text) in &csv {
            let p = sub_out.join(format!("{m}_{name}-{}.csv", args.split.replace('_', "-")));
            write_text(&p, text)?;
            csv_files.push(p);
        }
        tables.push_str(&heading);
        tables.push_str(&table);
        tables.push('\n');
        report.insert(
            name.clone(),
            json!({"images": n, "unscored": unscored + no_mask, "out": sub_out, "bop_csv": csv_files, "results": results.iter().map(|r| json!({"method": r.method, "summary": r.summary, "seconds_median": r.seconds_median})).collect::<Vec<_>>()}),
        );
    }
    Ok(
        json!({"command": "eval", "mode": "dataset", "seed": seed, "config": config, "datasets": report, "tables": tables}),
    )
}

/// The visible share of a true instance, as BOP's `visib_fract`: its visible pixels over the
/// pixels of its whole silhouette (`mask_visib/` over `mask/`; the visible mask stands in for
/// a missing whole one, so 1 when only the visible mask exists, 0 when neither does).
fn visible_fraction(sample: &ic_data::RoomSample) -> f64 {
    let visible = sample.mask_visib.data.iter().filter(|&&m| m).count();
    let all = sample.mask_all.data.iter().filter(|&&m| m).count();
    if all == 0 {
        return 0.0;
    }
    (visible as f64 / all as f64).min(1.0)
}

/// The positions of the `count` most visible of the given instances' visible shares, most
/// visible first (equal shares in their order): the true instances BOP scores a target of
/// `count` instances on.
fn most_visible(fractions: &[f64], count: usize) -> Vec<usize> {
    let mut order: Vec<usize> = (0..fractions.len()).collect();
    order.sort_by(|&a, &b| fractions[b].total_cmp(&fractions[a]));
    order.truncate(count);
    order
}

/// One line of `candidates.jsonl`: a registration of one of the segmentation's instances
/// for `target`, its errors to the nearest of its scored true instances (ADD-S; normalised units, `add_s`
/// divided by the `diameter`), the best IoU of its mask with a true instance's visible mask,
/// and what the verdict rests on.
fn candidate_line(
    target: &BopTarget,
    method: &str,
    r: &Registration,
    object: &Object,
    diameter: f64,
    samples: &[ic_data::RoomSample],
) -> Result<String> {
    let nearest = samples
        .iter()
        .min_by(|a, b| {
            let d = |s: &ic_data::RoomSample| object.add_s(&r.pose_normalised, &s.pose);
            d(a).total_cmp(&d(b))
        })
        .ok_or_else(|| CliError::internal("a target without true instances"))?;
    let mut e = PoseErrors::compute(&r.pose_normalised, &nearest.pose, Some(&object.points))?;
    e.add_s = e.add_s.map(|a| a / diameter);
    e.add = e.add.map(|a| a / diameter);
    let instance_iou = r.mask.as_ref().map_or(0.0, |m| {
        samples
            .iter()
            .map(|s| ic_seg::post::iou(m, &s.mask_visib))
            .fold(0.0, f64::max)
    });
    // Every verified hypothesis: which network made it, its score, and its ADD-S (over the
    // diameter) to the returned pose and to the nearest true instance.
    let verified: Vec<_> = r
        .verified
        .iter()
        .map(|h| {
            json!({
                "network": h.network, "score": h.score, "misfit": h.misfit,
                "to_pose": object.add_s(&h.pose_normalised, &r.pose_normalised) / diameter,
                "to_truth": object.add_s(&h.pose_normalised, &nearest.pose) / diameter,
            })
        })
        .collect();
    Ok(json!({
        "scene_id": target.scene_id, "im_id": target.im_id, "obj_id": target.obj_id,
        "method": method, "true_instances": samples.len(), "errors": e,
        "right": e.add_s.is_some_and(|a| a < 0.1), "instance_iou": instance_iou,
        "confidence": r.confidence, "calibration": r.calibration, "verdict": r.verdict,
        "verification": r.verification,
        "rival_score": r.rival_score, "evidence": r.evidence, "instance": r.instance,
        "segmentation": r.segmentation, "object_voxels": r.object_voxels,
        "verified": verified, "whole_view": r.whole_view,
    })
    .to_string())
}

// ---------------------------------------------------------------------------------------------
// --frames

/// A pose agrees with a real frame when at least this fraction of its visible rendered pixels
/// lie within the tolerance of the observed depth …
pub const FRAME_AGREEMENT: f64 = 0.8;
/// … and less than this fraction lies in front of the observed surface.
pub const FRAME_IN_FRONT: f64 = 0.05;
/// … and at least this many of its rendered pixels are visible.
pub const FRAME_MIN_VISIBLE: usize = 50;

/// The depth maps of a frames folder: `<dir>/*/depth/*.{png,tif,tiff,exr}`, sorted.
fn frame_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let read = |d: &Path| -> Result<Vec<PathBuf>> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(d)
            .map_err(|e| CliError::input(format!("{}: cannot list: {e}", d.display())))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        v.sort();
        Ok(v)
    };
    let mut out = Vec::new();
    for sub in read(dir)?.into_iter().filter(|p| p.join("depth").is_dir()) {
        out.extend(
            read(&sub.join("depth"))?
                .into_iter()
                .filter(|p| inputs::is_depth_file(p)),
        );
    }
    if out.is_empty() {
        return Err(CliError::input(format!(
            "{}: no depth map in */depth/ (expected model.ply, camera.json and SCENE/depth/*.png, \
             or .tif / .exr as register reads them)",
            dir.display()
        )));
    }
    Ok(out)
}

fn run_frames(args: &EvalArgs, dir: &Path, methods: &[Method], seed: u64) -> Result<Value> {
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("eval-frames"));
    if !(args.tolerance_mm.is_finite() && args.tolerance_mm > 0.0) {
        return Err(CliError::input(format!(
            "--tolerance-mm must be positive, got {}",
            args.tolerance_mm
        )));
    }
    let model_path = dir.join("model.ply");
    let mut files = frame_files(dir)?;
    if let Some(n) = args.limit {
        if n == 0 {
            return Err(CliError::input(
                "--limit 0 leaves no frame to register (--frames takes the first N in name order)",
            ));
        }
        files.truncate(n);
    }
    let first = files[0].clone();
    let camera = inputs::read_camera(&dir.join("camera.json"), || inputs::depth_size(&first))?;
    let k = camera.intrinsics;
    let object = Object::from_mesh(inputs::read_mesh(&model_path)?, seed)
        .map_err(|e| e.context(model_path.display()))?;
    let mesh = object
        .mesh
        .clone()
        .ok_or_else(|| CliError::internal("the object has no mesh"))?;
    let scale = object.normalisation.scale;
    inputs::create_dir(&out)?;
    let mut pipelines = Pipelines::load(
        methods,
        args,
        true,
        PipelineOptions {
            all_min_confidence: args.min_confidence,
            ..args.pipeline_options()
        },
    )?;
    let tol = args.tolerance_mm;
    let judge = |r: &Registration, depth: &ic_geometry::DepthImage| -> Result<Value> {
        let a = crate::overlay::depth_agreement(&mesh, &r.pose_normalised, scale, &k, depth, tol)?;
        let pass = a.visible_pixels >= FRAME_MIN_VISIBLE
            && a.agreement >= FRAME_AGREEMENT
            && a.in_front < FRAME_IN_FRONT;
        Ok(json!({
            "pose": r.pose, "confidence": r.confidence, "verdict": r.verdict,
            "verification": r.verification, "instance": r.instance,
            "agreement": a, "agrees": pass, "whole_view": r.whole_view,
        }))
    };
    let mut lines = Vec::new();
    let mut summary = serde_json::Map::new();
    for m in methods {
        let pipeline = pipelines.get(m);
        let (mut best_pass, mut all_found, mut all_pass, mut frames_all_ok) = (0, 0, 0, 0);
        let mut seconds = Vec::new();
        for path in &files {
            let depth = inputs::read_depth_mm(path, &camera)?;
            let name = path.strip_prefix(dir).unwrap_or(path).display().to_string();
            let fseed = case_seed(seed, &name);
            let clock = Instant::now();
            let best = pipeline.register_depth(&object, &depth, &k, None, fseed);
            let best_seconds = clock.elapsed().as_secs_f64();
            seconds.push(best_seconds);
            let all = pipeline.register_depth_all(&object, &depth, &k, fseed)?;
            let best_json = match &best {
                Ok(r) => {
                    let j = judge(r, &depth)?;
                    best_pass += usize::from(j["agrees"] == json!(true));
                    j
                }
                Err(e) => json!({"error": e.message()}),
            };
            let all_json: Vec<Value> = all
                .iter()
                .map(|r| judge(r, &depth))
                .collect::<Result<_>>()?;
            let passing = all_json
                .iter()
                .filter(|j| j["agrees"] == json!(true))
                .count();
            all_found += all.len();
            all_pass += passing;
            frames_all_ok += usize::from(!all.is_empty() && passing == all.len());
            // The overlay: every instance found, the best one's mask outlined.
            let poses: Vec<_> = all.iter().map(|r| r.pose_normalised).collect();
            let union = crate::overlay::render_masks(&mesh, &poses, &k)?;
            let best_mask = match &best {
                Ok(r) => Some(crate::overlay::render_mask(&mesh, &r.pose_normalised, &k)?),
                Err(_) => None,
            };
            let png = out.join(format!(
                "{}_{}.png",
                m.name,
                Path::new(&name)
                    .with_extension("")
                    .display()
                    .to_string()
                    .replace(['/', '\\'], "_")
            ));
            crate::overlay::write_rgb_png(
                &png,
                k.width,
                k.height,
                &crate::overlay::overlay_rgb(&depth, &union, best_mask.as_ref()),
            )?;
            lines.push(
                json!({"frame": name, "method": m.name, "seconds": best_seconds, "best": best_json, "all": all_json, "overlay": png})
                    .to_string(),
            );
            tracing::info!(frame = %name, method = %m.name, best_agrees = %best_json["agrees"], found = all.len(), agreeing = passing, "frame");
        }
        summary.insert(
            m.name.clone(),
            json!({
                "frames": files.len(),
                "best_agrees": best_pass,
                "instances_found": all_found,
                "instances_agreeing": all_pass,
                "frames_where_every_instance_agrees": frames_all_ok,
                "seconds_median": ic_eval::median(&seconds),
            }),
        );
    }
    write_lines(&out.join("frames.jsonl"), &lines)?;
    let report = json!({
        "command": "eval", "mode": "frames", "seed": seed, "frames": dir, "out": out,
        "tolerance_mm": tol,
        "rule": format!("a pose agrees when ≥ {FRAME_AGREEMENT} of its visible rendered pixels are within the tolerance of the depth, < {FRAME_IN_FRONT} lie in front of it, and ≥ {FRAME_MIN_VISIBLE} are visible"),
        "networks": pipelines.describe(),
        "methods": summary,
    });
    inputs::write_json(&out.join("summary.json"), &report)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_target_is_scored_on_its_inst_count_most_visible_instances_in_order_of_visibility() {
        // A copy hidden behind the others (0) is left out; equal shares keep their order.
        assert_eq!(most_visible(&[0.0, 0.8, 0.3, 0.8], 2), [1, 3]);
        assert_eq!(most_visible(&[0.0, 0.8, 0.3, 0.8], 3), [1, 3, 2]);
        assert_eq!(most_visible(&[0.5], 4), [0]);
        assert!(most_visible(&[0.5, 0.2], 0).is_empty());
    }

    #[test]
    fn methods_parse_with_defaults_and_without_duplicates() {
        let m = parse_methods(&[]).unwrap();
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].head, m[0].refine), (Head::Softmax, Refine::Icp));
        let m = parse_methods(&[
            "ours-ot".into(),
            "ours-softmax-icp".into(),
            "ours-ot".into(),
        ])
        .unwrap();
        let names: Vec<&str> = m.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["ours-ot", "ours-softmax-icp"]);
        assert_eq!((m[0].head, m[0].refine), (Head::Ot, Refine::None));
        // The sweep methods verify the rotated copies like -verify, without ICP.
        let m = parse_methods(&["ours-softmax-sweep".into(), "ours-ot-verify".into()]).unwrap();
        assert_eq!(
            (m[0].head, m[0].refine, m[0].rotations),
            (Head::Softmax, Refine::None, Some(VERIFY_ROTATIONS))
        );
        assert_eq!(
            (m[1].head, m[1].refine, m[1].rotations),
            (Head::Ot, Refine::Icp, Some(VERIFY_ROTATIONS))
        );
        let e = parse_methods(&["o3d-fgr".into()]).unwrap_err();
        assert_eq!(e.exit_code(), 2);
        assert!(e.message.contains("o3d-fgr"));
    }

    #[test]
    fn case_seeds_depend_on_the_seed_and_the_name_only() {
        assert_eq!(case_seed(3, "case_00001"), case_seed(3, "case_00001"));
        assert_ne!(case_seed(3, "case_00001"), case_seed(3, "case_00002"));
        assert_ne!(case_seed(3, "case_00001"), case_seed(4, "case_00001"));
    }
}
