//! `incontext train pose|seg`: fine-tunes a network on the user's own meshes, with views
//! rendered on the fly (`ic_train`, the code behind `cargo xtask train-pose|train-seg`).
//!
//! Every mesh of `--objects` (OBJ, PLY, OFF, glTF; any unit: each is normalised to [-1, 1]
//! on its longest side) is a training object; validation uses other views of the same objects
//! (a fixed seed), so it measures how well the network fits them, not how it generalises. By
//! default training starts from the shipped weights (`--from` picks another checkpoint,
//! `--scratch` a fresh network) and, for the pose network, samples views like deployment
//! (whole sphere, roll, truncation, occluders, sensor model; `--protocol paper` for the
//! paper's), and for the segmentation network cluttered tables, bins and shelves of the meshes
//! with a fifth of lone objects in a room (a one-output checkpoint given with `--from`: room
//! scenes only). It stops after `--iterations`, after `--minutes` (a clean stop: checkpoint and
//! weights saved), or on Ctrl-C / SIGTERM (checkpoint saved, exit code 130).
//!
//! `--out` holds `final.safetensors` (the weights to use: `incontext register --pose-model
//! OUT/final.safetensors`, or `--seg-model`), `best.safetensors` (the best validation),
//! `latest.safetensors` (continue with `--resume`), `train.csv`, `val.csv`, `best.json`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use clap::{Args, Subcommand};
use serde_json::{Value, json};

use ic_data::{Corpus, CorpusOptions, FolderSplit, Split};
use ic_pose::Head;
use ic_train::{Ending, Outcome, RunControl};

use crate::error::{CliError, Result};
use crate::models::Shipped;

/// `incontext train`.
#[derive(Args, Debug)]
pub struct TrainArgs {
    #[command(subcommand)]
    pub network: TrainNetwork,
}

/// Which network to train.
#[derive(Subcommand, Debug)]
pub enum TrainNetwork {
    /// The pose network (model points + observed points → correspondences).
    #[command(after_help = "\
Example:
  incontext train pose --objects my-meshes --out my-pose --minutes 30
  incontext register --pose-model my-pose/final.safetensors --model my-meshes/part.ply ...")]
    Pose(PoseTrainArgs),
    /// The segmentation network (depth map → every object's instances).
    #[command(after_help = "\
Example:
  incontext train seg --objects my-meshes --out my-seg --minutes 30
  incontext register --seg-model my-seg/final.safetensors ...")]
    Seg(SegTrainArgs),
}

/// What both networks' training takes.
#[derive(Args, Debug, Clone)]
pub struct CommonArgs {
    /// A folder of meshes (OBJ, PLY, OFF, glTF/GLB): every one is a training object.
    #[arg(long)]
    pub objects: PathBuf,
    /// Output folder (created): final.safetensors, best.safetensors, latest.safetensors,
    /// train.csv, val.csv.
    #[arg(long)]
    pub out: PathBuf,
    /// Start from this checkpoint's weights and configuration (default: the shipped network).
    #[arg(long, conflicts_with = "scratch")]
    pub from: Option<PathBuf>,
    /// Start from a fresh network instead of trained weights (the pose network's `cpu` preset;
    /// the segmentation network's `clutter` preset, two outputs).
    #[arg(long)]
    pub scratch: bool,
    /// Continue the run saved in OUT/latest.safetensors.
    #[arg(long)]
    pub resume: bool,
    /// Stop cleanly after this many minutes (checkpoint and weights saved).
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Training iterations (batches) in all.
    #[arg(long, default_value_t = 2000)]
    pub iterations: u64,
    /// Adam's step size (fine-tuning wants a small one).
    #[arg(long, default_value_t = 1e-4)]
    pub learning_rate: f64,
    /// Decay the learning rate along a half cosine from --learning-rate (from the current
    /// iteration on) to --lr-floor at this iteration; resumed runs keep following it.
    #[arg(long)]
    pub lr_decay_to: Option<u64>,
    /// The learning rate --lr-decay-to ends at.
    #[arg(long, default_value_t = 1e-6)]
    pub lr_floor: f64,
    /// Samples per iteration (default: the network's).
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Validate every this many iterations.
    #[arg(long, default_value_t = 250)]
    pub validate_every: u64,
    /// Fixed validation views.
    #[arg(long, default_value_t = 48)]
    pub validation_count: usize,
    /// Save OUT/latest.safetensors every this many seconds.
    #[arg(long, default_value_t = 300)]
    pub checkpoint_secs: u64,
    /// Threads rendering training views, beside the compute threads (--threads).
    #[arg(long, default_value_t = 1)]
    pub data_workers: usize,
}

#[derive(Args, Debug, Clone)]
pub struct PoseTrainArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    /// `deployment` (views as `register` sees them) or `paper`.
    #[arg(long, default_value = "deployment")]
    pub protocol: String,
    /// `softmax` or `ot`: which shipped network to start from (with --from or --resume it
    /// must match the checkpoint's head).
    #[arg(long)]
    pub head: Option<String>,
    /// Model points per sample (default: the network's, 384 for the shipped ones).
    #[arg(long)]
    pub model_points: Option<usize>,
    /// Observed points per sample (default: the network's, 288 for the shipped ones).
    #[arg(long)]
    pub observed_points: Option<usize>,
}

#[derive(Args, Debug, Clone)]
pub struct SegTrainArgs {
    #[command(flatten)]
    pub common: CommonArgs,
}

/// Runs `incontext train`; returns the JSON report.
pub fn run(args: &TrainArgs, seed: u64) -> Result<Value> {
    match &args.network {
        TrainNetwork::Pose(a) => train_pose(a, seed),
        TrainNetwork::Seg(a) => train_seg(a, seed),
    }
}

/// The text for people.
pub fn summary_text(report: &Value) -> String {
    let weights = report["weights"].as_str().unwrap_or("?");
    let flag = report["register_flag"].as_str().unwrap_or("--pose-model");
    match report["ending"].as_str() {
        Some("interrupted") => format!(
            "interrupted at iteration {}; continue with --resume (checkpoint {})\n",
            report["iteration"],
            report["checkpoint"].as_str().unwrap_or("?")
        ),
        _ => format!(
            "{} network trained to iteration {} ({}); weights {weights}\nuse them with: incontext register {flag} {weights} ...\n",
            report["network"].as_str().unwrap_or("?"),
            report["iteration"],
            report["ending"].as_str().unwrap_or("?"),
        ),
    }
}

/// Checks `--objects` (a folder with at least one readable mesh) and builds its corpus: every
/// mesh in every split.
fn user_corpus(dir: &Path) -> Result<Arc<Corpus>> {
    match std::fs::metadata(dir) {
        Ok(m) if m.is_dir() => {}
        Ok(_) => {
            return Err(CliError::input(format!(
                "{}: --objects must be a folder of meshes",
                dir.display()
            )));
        }
        Err(e) => {
            return Err(CliError::input(format!(
                "{}: cannot read the --objects folder: {e}",
                dir.display()
            )));
        }
    }
    let corpus = Corpus::mesh_folder(
        dir,
        &FolderSplit::All,
        Split::Train,
        CorpusOptions::default(),
    )
    .map_err(|e| CliError::input(format!("--objects {}: {e}", dir.display())))?;
    // Loads every mesh now, so a bad file is reported before training starts.
    for i in 0..corpus.len() {
        corpus
            .object(i)
            .map_err(|e| CliError::input(format!("--objects {}: {e}", dir.display())))?;
    }
    Ok(Arc::new(corpus))
}

/// The checkpoint to start from: `--from`, or the shipped network written to a temporary file.
enum Start {
    Scratch,
    File(PathBuf),
    Shipped(tempfile::NamedTempFile, String),
}

impl Start {
    fn path(&self) -> Option<&Path> {
        match self {
            Start::Scratch => None,
            Start::File(p) => Some(p),
            Start::Shipped(t, _) => Some(t.path()),
        }
    }

    fn describe(&self) -> String {
        match self {
            Start::Scratch => "a fresh network".into(),
            Start::File(p) => p.display().to_string(),
            Start::Shipped(_, d) => d.clone(),
        }
    }
}

fn start_from(common: &CommonArgs, shipped: Shipped, what: &str) -> Result<Start> {
    if common.scratch {
        return Ok(Start::Scratch);
    }
    if let Some(p) = &common.from {
        return match std::fs::metadata(p) {
            Ok(m) if m.is_file() => Ok(Start::File(p.clone())),
            Ok(_) => Err(CliError::input(format!(
                "{}: --from is not a file",
                p.display()
            ))),
            Err(e) => Err(CliError::input(format!(
                "{}: cannot read the --from checkpoint: {e}",
                p.display()
            ))),
        };
    }
    let bytes: Vec<u8> = match shipped.bytes {
        Some(b) => b.to_vec(),
        None => std::fs::read(shipped.workspace_path()).map_err(|e| {
            CliError::input(format!(
                "the shipped {what} models/{} is not built into this binary and {} cannot be \
                 read ({e}); pass --from CHECKPOINT or --scratch",
                shipped.file,
                shipped.workspace_path().display()
            ))
        })?,
    };
    let mut tmp = tempfile::Builder::new()
        .prefix("incontext-train-")
        .suffix(".safetensors")
        .tempfile()
        .map_err(|e| CliError::internal(format!("creating a temporary file: {e}")))?;
    std::io::Write::write_all(&mut tmp, &bytes)
        .and_then(|_| std::io::Write::flush(&mut tmp))
        .map_err(|e| CliError::internal(format!("writing a temporary file: {e}")))?;
    Ok(Start::Shipped(tmp, shipped.describe()))
}

/// Checks `--out` and refuses to start over a run without `--resume`.
fn prepare_out(common: &CommonArgs) -> Result<()> {
    if common.out.exists() && !common.out.is_dir() {
        return Err(CliError::input(format!(
            "{}: --out must be a folder",
            common.out.display()
        )));
    }
    let latest = common.out.join("latest.safetensors");
    if latest.exists() && !common.resume {
        return Err(CliError::input(format!(
            "{}: a run is already there; pass --resume to continue it, or choose another --out",
            latest.display()
        )));
    }
    if !(common.minutes.is_none_or(|m| m.is_finite() && m >= 0.0)) {
        return Err(CliError::input("--minutes must be a number ≥ 0"));
    }
    if common.iterations == 0 || common.validate_every == 0 || common.validation_count == 0 {
        return Err(CliError::input(
            "--iterations, --validate-every and --validation-count must be ≥ 1",
        ));
    }
    if common.batch_size == Some(0) {
        return Err(CliError::input("--batch-size must be ≥ 1"));
    }
    if !(common.learning_rate.is_finite() && common.learning_rate > 0.0) {
        return Err(CliError::input(format!(
            "--learning-rate must be a positive number, got {}",
            common.learning_rate
        )));
    }
    if !(common.lr_floor.is_finite() && common.lr_floor >= 0.0) {
        return Err(CliError::input(format!(
            "--lr-floor must be a number ≥ 0, got {}",
            common.lr_floor
        )));
    }
    std::fs::create_dir_all(&common.out).map_err(|e| {
        CliError::input(format!(
            "{}: cannot create --out: {e}",
            common.out.display()
        ))
    })
}

/// Peak training memory per pose pair of `m` model and `n` observed points, in bytes: the
/// activations the backward pass keeps, a·(M + N) (the DGCNN's edge features) + b·M·N (the
/// attention and the soft assignment), fitted to the peak resident memory of `incontext train
/// pose` at two batch sizes each at 384×288 (≈ 35 MB a pair) and 1024×768 (≈ 112 MB).
fn pose_pair_bytes(m: usize, n: usize) -> f64 {
    46.4e3 * (m + n) as f64 + 36.3 * m as f64 * n as f64
}

/// Peak training memory per segmentation sample of `pixels` network input pixels, in bytes:
/// ≈ 134 MB at 256×192 for the shipped clutter network (16-32-64-128 channels), measured as
/// [`pose_pair_bytes`].
fn seg_sample_bytes(pixels: u64) -> f64 {
    2.72e3 * pixels as f64
}

/// The memory this process may take now, in bytes: `MemAvailable` of `/proc/meminfo` (Linux);
/// `None` elsewhere.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Refuses a batch whose training activations (`batch × per_sample` bytes) would not fit in
/// 80 % of the memory available now: a mistyped `--batch-size 100000` or `--model-points`
/// is bad input, not a machine driven into swap or the OOM killer. `sample_size` names what
/// sets `per_sample`, for the message.
fn check_batch_memory(batch: usize, per_sample: f64, what: &str, sample_size: &str) -> Result<()> {
    let Some(available) = available_memory() else {
        return Ok(());
    };
    let need = batch as f64 * per_sample;
    let budget = 0.8 * available as f64;
    if need > budget {
        let gib = |b: f64| b / (1u64 << 30) as f64;
        let fits = (budget / per_sample).floor() as u64;
        let fix = match fits {
            0 => format!("not even one fits: lower {sample_size}"),
            _ => format!("at most {fits} fit: lower --batch-size or {sample_size}"),
        };
        return Err(CliError::input(format!(
            "a training batch of {batch} {what} needs ≈ {:.1} GiB, more than this machine has \
             free ({:.1} GiB available); {fix}",
            gib(need),
            gib(available as f64),
        )));
    }
    Ok(())
}

/// `--data-workers` capped to the logical CPUs (thousands of render threads only take
/// memory and minutes to start), with a warning.
fn data_workers(asked: usize) -> usize {
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    if asked > cpus {
        tracing::warn!(
            "--data-workers {asked} is more than the {cpus} logical CPUs of this machine: using {cpus}"
        );
    }
    asked.clamp(1, cpus)
}

fn control(common: &CommonArgs) -> RunControl<'static> {
    RunControl {
        stop: ic_train::stop_flag(),
        deadline: RunControl::deadline_in(common.minutes),
        checkpoint_secs: common.checkpoint_secs,
    }
}

fn report(network: &str, common: &CommonArgs, from: &str, outcome: &Outcome, flag: &str) -> Value {
    let files = ic_train::RunFiles {
        out: common.out.clone(),
    };
    let best = files.best();
    json!({
        "command": "train",
        "network": network,
        "objects": common.objects,
        "out": common.out,
        "from": from,
        "ending": outcome.ending,
        "interrupted": outcome.ending == Ending::Interrupted,
        "iteration": outcome.iteration,
        "iterations_run": outcome.iterations_run,
        "seconds": outcome.seconds,
        "weights": files.final_weights(),
        "best": best.is_file().then_some(best),
        "best_score": outcome.best_score.is_finite().then_some(outcome.best_score),
        "checkpoint": files.latest(),
        "register_flag": flag,
    })
}

fn train_error(e: anyhow::Error) -> CliError {
    CliError::internal(format!("training: {e:#}"))
}

fn train_pose(a: &PoseTrainArgs, seed: u64) -> Result<Value> {
    let c = &a.common;
    let protocol: ic_data::SamplingProtocol = a
        .protocol
        .parse()
        .map_err(|e| CliError::input(format!("--protocol: {e}")))?;
    let head: Option<Head> = a
        .head
        .as_deref()
        .map(str::parse)
        .transpose()
        .map_err(|e| CliError::input(format!("--head: {e}")))?;
    if a.model_points == Some(0) || a.observed_points == Some(0) {
        return Err(CliError::input(
            "--model-points and --observed-points must be ≥ 1",
        ));
    }
    let corpus = user_corpus(&c.objects)?;
    prepare_out(c)?;
    let start = start_from(
        c,
        crate::models::shipped_pose(head.unwrap_or(Head::Softmax)),
        "pose network",
    )?;
    // The configuration started from: the checkpoint's (a resumed run's own holds the same),
    // or the `cpu` preset that --scratch trains.
    let cfg = match start.path() {
        Some(p) => ic_pose::checkpoint::read_config(p).map_err(|e| {
            CliError::input(format!("{}: not a pose checkpoint: {e}", start.describe()))
        })?,
        None => ic_pose::PoseConfig::cpu(head.unwrap_or(Head::Softmax)),
    };
    if let Some(h) = head
        && h != cfg.net.head
    {
        return Err(CliError::input(format!(
            "{}: the checkpoint has the {} head, but --head {} was asked for",
            start.describe(),
            cfg.net.head.as_str(),
            h.as_str()
        )));
    }
    check_batch_memory(
        c.batch_size.unwrap_or(cfg.train.batch_size),
        pose_pair_bytes(
            a.model_points.unwrap_or(cfg.train.model_points),
            a.observed_points.unwrap_or(cfg.train.observed_points),
        ),
        "pose pairs",
        "the point counts",
    )?;
    let args = ic_train::pose::TrainArgs {
        preset: "cpu".into(),
        head: a.head.clone(),
        objects: c.objects.display().to_string(),
        protocol: protocol.as_str().into(),
        paper_fraction: 0.0,
        paper_objects: None,
        init: start.path().map(Path::to_path_buf),
        out: c.out.clone(),
        iterations: Some(c.iterations),
        seed,
        resume: c.resume,
        threads: None,
        data_workers: data_workers(c.data_workers),
        checkpoint_secs: c.checkpoint_secs,
        batch_size: c.batch_size,
        emb_dims: None,
        ff_dims: None,
        k: None,
        pooled_keys: None,
        model_points: a.model_points,
        observed_points: a.observed_points,
        learning_rate: Some(c.learning_rate),
        validate_every: Some(c.validate_every),
        validation_count: Some(c.validation_count),
        precise_bn: 0,
        lr_decay_to: c.lr_decay_to,
        lr_floor: c.lr_floor,
    };
    let objects = ic_train::ObjectsSpec::every_mesh_of(&c.objects);
    // Every mesh trains and validates: one corpus, loaded (and checked) once.
    let outcome =
        ic_train::pose::train_corpora(&args, &objects, corpus.clone(), corpus, control(c))
            .map_err(train_error)?;
    Ok(report(
        "pose",
        c,
        &start.describe(),
        &outcome,
        "--pose-model",
    ))
}

fn train_seg(a: &SegTrainArgs, seed: u64) -> Result<Value> {
    let c = &a.common;
    let corpus = user_corpus(&c.objects)?;
    prepare_out(c)?;
    let start = start_from(c, crate::models::SEG, "segmentation network")?;
    // A four-output network (the shipped one: every object, its instance core and the centre
    // offsets) or a two-output one (object and core) trains on cluttered scenes of the user's
    // meshes with a fifth of lone objects in a room, as it was trained (its loss weights
    // included: they come with its configuration); a one-output network (`--from` an older
    // checkpoint) on room scenes.
    let cfg = match start.path() {
        Some(p) => ic_seg::checkpoint::read_config(p).map_err(|e| {
            CliError::input(format!(
                "{}: not a segmentation checkpoint: {e}",
                start.describe()
            ))
        })?,
        // --scratch: the `clutter` preset, two outputs.
        None => ic_seg::SegConfig::clutter(),
    };
    check_batch_memory(
        c.batch_size.unwrap_or(cfg.train.batch_size),
        seg_sample_bytes(cfg.net.input_width as u64 * cfg.net.input_height as u64),
        "segmentation samples",
        "the network's input size",
    )?;
    let (preset, scenes, room_fraction) = match cfg.net.outputs {
        4 => ("clutter-offsets", "clutter", 0.2),
        2 => ("clutter", "clutter", 0.2),
        _ => ("cpu", "room", 0.0),
    };
    let args = ic_train::seg::TrainArgs {
        preset: preset.into(),
        scenes: scenes.into(),
        room_fraction,
        init: None,
        objects: c.objects.clone(),
        out: c.out.clone(),
        iterations: Some(c.iterations),
        seed,
        resume: c.resume,
        threads: None,
        data_workers: data_workers(c.data_workers),
        checkpoint_secs: c.checkpoint_secs,
        validate_every: c.validate_every,
        validation_count: c.validation_count as u64,
        batch_size: c.batch_size,
        learning_rate: Some(c.learning_rate),
        lr_decay_to: c.lr_decay_to,
        lr_floor: c.lr_floor,
        input: None,
        core_radius: None,
        balance_area: None,
        border_weight: None,
        shadow_probability: None,
    };
    let outcome =
        ic_train::seg::train_objects(&args, start.path(), corpus.clone(), corpus, control(c))
            .map_err(train_error)?;
    Ok(report(
        "segmentation",
        c,
        &start.describe(),
        &outcome,
        "--seg-model",
    ))
}
