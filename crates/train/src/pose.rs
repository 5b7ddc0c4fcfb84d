//! The pose network (`ic_pose`) trained on object-alone views rendered on the fly by
//! `ic_data`, and measured on fixed views (`cargo xtask train-pose` / `eval-pose`,
//! `incontext train pose`).
//!
//! Objects ([`TrainArgs::objects`]): one folder or a weighted mixture of folders and
//! procedural objects ([`ObjectsSpec`]). A folder with `split.json` uses its `train`/`val`/`test`
//! lists; a folder of numeric stems (the blobs) uses 000–749 train, 750–799 val (the fixed
//! validation set that picks the best checkpoint), 800–999 test (left untouched for
//! `eval-pose`). `--protocol paper` (default) samples as the paper; `--protocol deployment`
//! as deployment (`ic_data::SamplingProtocol::Deployment`); validation uses the same protocol
//! on the `val` objects (seed [`VALIDATION_SEED`], whatever the run's seed).
//!
//! A run folder holds: `latest.safetensors` (resumable), `best.safetensors` + `best.json` (the
//! best validation by acc@15° up to symmetry), `final.safetensors`, `train.csv`
//! (`iteration,loss,accuracy,loss_avg,accuracy_avg,matched_fraction,samples_per_s,elapsed_s`),
//! `val.csv`, `data.json` (protocol, objects, sample settings: a resume warns when they
//! changed) and `symmetries.json` (the objects' symmetries found so far, reloaded on resume).
//! Units: normalised object units (the model spans [-1, 1]); poses model → camera.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::DType;
use candle_nn::VarBuilder;
use glam::Vec3;
use ic_data::{
    Corpus, CorpusOptions, ObjectSample, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher,
    SamplingProtocol, Split,
};
use ic_geometry::Assignment;
use ic_pose::checkpoint::{CONFIG_KEY, STATE_KEY};
use ic_pose::{
    Head, PairBatch, PoseConfig, PoseError, PoseEstimator, PoseNet, Refine,
    correspondence_accuracy, nearest_assignments, nll_loss,
};
use indicatif::ProgressBar;

pub use crate::objects::{ObjectsSpec, SourceKind, SourceSpec};
use crate::{Network, Outcome, RunControl, StepRow, Task, Trainer, Validation};

/// Seed of the validation sample stream (fixed whatever the run's seed).
pub const VALIDATION_SEED: u64 = 0x7661_6c69;

/// The pose network's trainer.
pub type PoseTrainer = Trainer<PoseNet>;

impl Network for PoseNet {
    type Config = PoseConfig;
    type Error = PoseError;
    const CONFIG_KEY: &'static str = CONFIG_KEY;
    const STATE_KEY: &'static str = STATE_KEY;

    fn build(vb: VarBuilder, config: &PoseConfig) -> Result<Self, PoseError> {
        Ok(PoseNet::new(vb, &config.net)?)
    }
    fn validate(config: &PoseConfig) -> Result<(), PoseError> {
        config.validate()
    }
    fn read_config(path: &Path) -> Result<PoseConfig, PoseError> {
        ic_pose::checkpoint::read_config(path)
    }
    /// The same weights: every setting equal but `pooled_keys`, which changes which points
    /// the attention reads, not a parameter's shape (a network trained with full attention
    /// fine-tunes with pooled keys).
    fn same_network(a: &PoseConfig, b: &PoseConfig) -> bool {
        let keys = |c: &PoseConfig| ic_pose::NetConfig {
            pooled_keys: None,
            ..c.net.clone()
        };
        keys(a) == keys(b)
    }
    fn learning_rate(config: &PoseConfig) -> f64 {
        config.train.learning_rate
    }
    fn set_learning_rate(config: &mut PoseConfig, learning_rate: f64) {
        config.train.learning_rate = learning_rate;
    }
    fn iterations(config: &PoseConfig) -> u64 {
        config.train.iterations
    }
    fn set_iterations(config: &mut PoseConfig, iterations: u64) {
        config.train.iterations = iterations;
    }
}

/// What one pose step measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    pub loss: f32,
    /// Arg-max correspondence accuracy over the matched observed points of the batch.
    pub accuracy: Option<f64>,
    /// Matched observed points in the batch.
    pub matched: usize,
}

impl Trainer<PoseNet> {
    /// An estimator sharing the current weights (inference mode), e.g. for validation.
    pub fn estimator(&self) -> PoseEstimator {
        PoseEstimator::from_net(self.net.clone(), self.config.clone(), self.device.clone())
    }

    /// Replaces the batch-norm running statistics by their plain mean over `batches`
    /// (forward passes in training mode; the weights do not change) — "precise BN" (Wu &
    /// Johnson, "Rethinking 'Batch' in BatchNorm", 2021). With batch 4 the exponential
    /// average of training (momentum 0.1, a window of ≈ 10 batches) is noisy enough to move
    /// the validation accuracy by tens of points between checkpoints 50 iterations apart.
    pub fn recalibrate_batch_norm(
        &mut self,
        batches: &[Vec<ObjectSample>],
    ) -> Result<(), PoseError> {
        for (k, samples) in batches.iter().enumerate() {
            let mut cfg = self.config.net.clone();
            cfg.bn_momentum = 1.0 / (k + 1) as f64;
            let vb = VarBuilder::from_varmap(&self.varmap, DType::F32, &self.device);
            let net = PoseNet::new(vb, &cfg)?;
            let pairs: Vec<(&[Vec3], &[Vec3])> = samples
                .iter()
                .map(|s| (&s.model_points[..], &s.observed_points[..]))
                .collect();
            let batch = PairBatch::new(&pairs, cfg.k, &self.device)?;
            net.forward_t(&batch, true)?;
        }
        // The trainer's own network shares the variables, so it sees the new statistics.
        Ok(())
    }

    /// One step on ic_data samples. A sample that lists poses equivalent to its true one
    /// (`ObjectSample::alternatives`, a symmetric object) is scored against the equivalent
    /// ground truth nearest the network's prediction ([`nearest_assignments`]), so the loss
    /// never asks for the one turn of a can that its depth cannot show.
    pub fn step(&mut self, samples: &[ObjectSample]) -> Result<StepStats, PoseError> {
        let pairs: Vec<(&[Vec3], &[Vec3])> = samples
            .iter()
            .map(|s| (&s.model_points[..], &s.observed_points[..]))
            .collect();
        let candidates: Vec<Vec<&Assignment>> = samples
            .iter()
            .map(|s| {
                std::iter::once(&s.assignment)
                    .chain(&s.alternatives)
                    .collect()
            })
            .collect();
        self.step_candidates(&pairs, &candidates)
    }

    /// One step on (model points, observed points) pairs, normalised units: forward
    /// (training mode), loss, backward, Adam.
    pub fn step_pairs(
        &mut self,
        pairs: &[(&[Vec3], &[Vec3])],
        assignments: &[&Assignment],
    ) -> Result<StepStats, PoseError> {
        let candidates: Vec<Vec<&Assignment>> = assignments.iter().map(|a| vec![*a]).collect();
        self.step_candidates(pairs, &candidates)
    }

    /// One step where each pair's ground truth is the candidate nearest the prediction.
    fn step_candidates(
        &mut self,
        pairs: &[(&[Vec3], &[Vec3])],
        candidates: &[Vec<&Assignment>],
    ) -> Result<StepStats, PoseError> {
        let batch = PairBatch::new(pairs, self.config.net.k, &self.device)?;
        let out = self.net.forward_t(&batch, true)?;
        let chosen = nearest_assignments(&out, candidates)?;
        let assignments: Vec<&Assignment> =
            candidates.iter().zip(&chosen).map(|(c, k)| c[*k]).collect();
        let assignments = &assignments[..];
        let loss = nll_loss(&out, assignments)?;
        let grads = loss.backward()?;
        self.apply(&grads)?;
        let matches = out.matches()?;
        let accuracy = correspondence_accuracy(&matches, assignments);
        Ok(StepStats {
            loss: loss.to_scalar::<f32>()?,
            accuracy,
            matched: assignments.iter().map(|a| a.inlier_count()).sum(),
        })
    }
}

#[derive(clap::Args)]
pub struct TrainArgs {
    /// `cpu` (≈ 1.5 h on one core) or `paper` (GPU, `cuda` feature); `tiny` for smoke tests.
    /// Ignored with `--init` (the configuration comes from the checkpoint).
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// `softmax` (default) or `ot`; with `--init`, must match the checkpoint's head if given.
    #[arg(long)]
    pub head: Option<String>,
    /// A folder (`split.json`, or numeric stems split as the blobs) or a weighted mixture,
    /// e.g. `real=../shared/data/objects/real_objects:0.6,blobs=../shared/data/objects/blobs:0.3,procedural:0.1`.
    #[arg(long)]
    pub objects: String,
    /// `paper` (the paper's sampling; old runs reproduce) or `deployment` (whole sphere, roll,
    /// 10–100 % image span, truncation, scale augmentation, occluders, sensor model).
    #[arg(long, default_value = "paper")]
    pub protocol: String,
    /// With `--protocol deployment`: this share of the training samples (a seeded draw per
    /// sample) follows the paper's protocol instead — its quarter of viewpoints at one
    /// distance, no sensor model, the objects and loss of the run — so that a run for
    /// deployment keeps what the paper protocol measures. Validation stays deployment. 0: none.
    #[arg(long, default_value_t = 0.0)]
    pub paper_fraction: f64,
    /// With `--paper-fraction`: the objects the paper-protocol samples draw from (training
    /// split; a folder or a weighted mixture, as `--objects`), e.g. only the blobs the paper
    /// trained on. Default: the run's objects.
    #[arg(long)]
    pub paper_objects: Option<String>,
    /// Start from these weights (e.g. models/pose-cpu-ot.safetensors) and their configuration
    /// (the preset's overrides still apply; the network must keep its shape). Fresh Adam
    /// moments, iteration 0. Ignored when `--resume` finds a checkpoint.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Output folder: latest.safetensors (resumable), best.safetensors (weights), CSV logs.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub iterations: Option<u64>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Continue from `<out>/latest.safetensors` (configuration and seed come from it).
    #[arg(long)]
    pub resume: bool,
    /// Compute threads (RAYON_NUM_THREADS, set by the caller before any thread starts); the
    /// data prefetcher adds `--data-workers` threads.
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long, default_value_t = 1)]
    pub data_workers: usize,
    /// Save `latest.safetensors` every this many seconds.
    #[arg(long, default_value_t = 300)]
    pub checkpoint_secs: u64,
    // Overrides of the preset.
    #[arg(long)]
    pub batch_size: Option<usize>,
    #[arg(long)]
    pub emb_dims: Option<usize>,
    #[arg(long)]
    pub ff_dims: Option<usize>,
    #[arg(long)]
    pub k: Option<usize>,
    /// Attend over this many farthest-point samples of each cloud instead of every point
    /// (`NetConfig::pooled_keys`; the weights do not change shape, so `--init` from a network
    /// trained with full attention works). Default: the preset's or the `--init` checkpoint's.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub pooled_keys: Option<u64>,
    #[arg(long)]
    pub model_points: Option<usize>,
    #[arg(long)]
    pub observed_points: Option<usize>,
    #[arg(long)]
    pub learning_rate: Option<f64>,
    /// From this run's current iteration and learning rate (after `--learning-rate`), decay
    /// the learning rate along a half cosine to `--lr-floor` at this iteration, then keep it;
    /// saved with the checkpoints, so later `--resume`s follow it without the flag (a new
    /// `--learning-rate` alone ends it).
    #[arg(long)]
    pub lr_decay_to: Option<u64>,
    /// The learning rate `--lr-decay-to` ends at.
    #[arg(long, default_value_t = 1e-5)]
    pub lr_floor: f64,
    #[arg(long)]
    pub validate_every: Option<u64>,
    #[arg(long)]
    pub validation_count: Option<usize>,
    /// Before each validation, replace the batch-norm running statistics by their mean over
    /// this many fixed batches of training-split samples (precise BN, as `eval-pose
    /// --recalibrate-bn`; the saved weights carry them). 0 = the training average.
    #[arg(long, default_value_t = 0)]
    pub precise_bn: usize,
}

#[derive(clap::Args)]
pub struct EvalArgs {
    /// A checkpoint (weights-only or training).
    #[arg(long)]
    pub model: PathBuf,
    /// As for train-pose: a folder or a weighted mixture.
    #[arg(long)]
    pub objects: String,
    /// `test` (blobs: ids 800–999), `val` (750–799, the validation objects held out of
    /// training) or `train` (000–749); folders with `split.json` use its lists.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// `paper` or `deployment` (as for train-pose).
    #[arg(long, default_value = "paper")]
    pub protocol: String,
    #[arg(long, default_value_t = 500)]
    pub count: u64,
    #[arg(long, default_value_t = 2021)]
    pub seed: u64,
    /// `icp` (the default of `PoseEstimator`) or `none` (the one-shot estimate).
    #[arg(long, default_value = "icp")]
    pub refine: String,
    /// Drop correspondences below this probability.
    #[arg(long)]
    pub min_probability: Option<f32>,
    /// Unweighted Procrustes.
    #[arg(long)]
    pub unweighted: bool,
    /// Before evaluating, replace the batch-norm running statistics by their mean over this
    /// many batches of training-split samples (precise BN; 0 = keep the checkpoint's).
    #[arg(long, default_value_t = 0)]
    pub recalibrate_bn: usize,
    /// With --recalibrate-bn: write the recalibrated weights here (weights-only checkpoint).
    #[arg(long)]
    pub save_recalibrated: Option<PathBuf>,
    /// Where to write the JSON (default `<model>.eval-<split>.json`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub threads: Option<usize>,
}

/// The samples of a run: the pose network's configuration sets M and N.
pub fn sample_config(cfg: &PoseConfig, protocol: SamplingProtocol) -> ObjectSampleConfig {
    ObjectSampleConfig {
        model_points: cfg.train.model_points,
        observed_points: cfg.train.observed_points,
        ..protocol.config()
    }
}

/// The objects of `split` under `spec`, with a line saying what they are.
pub fn open_objects(spec: &ObjectsSpec, split: Split) -> Result<Arc<Corpus>> {
    let corpus = spec.corpus(split, CorpusOptions::default())?;
    let sources = corpus.sources();
    if sources.is_empty() {
        tracing::info!("{split} objects: {}", corpus.len());
    } else {
        let parts: Vec<String> = sources
            .iter()
            .map(|s| format!("{} {} (p {:.3})", s.name, s.objects, s.probability))
            .collect();
        tracing::info!("{split} objects: {} = {}", corpus.len(), parts.join(" + "));
    }
    Ok(Arc::new(corpus))
}

/// The trainer a run starts with: its own checkpoint (`--resume`), the `--init` weights with
/// their configuration, or a fresh network of the preset.
pub fn make_trainer(args: &TrainArgs, latest: &Path) -> Result<(PoseTrainer, bool)> {
    let resuming = args.resume && latest.exists();
    let trainer = if resuming {
        let mut t = PoseTrainer::resume_run(latest, args.iterations)?;
        if args.init.is_some() {
            tracing::info!("--init ignored: resuming the run's own checkpoint");
        }
        if let Some(lr) = args.learning_rate {
            tracing::info!("learning rate {} from iteration {}", lr, t.iteration());
            t.set_learning_rate(lr);
        }
        t
    } else {
        if args.resume {
            tracing::info!("--resume: no {} yet, starting fresh", latest.display());
        }
        match &args.init {
            Some(init) => {
                let mut cfg = ic_pose::checkpoint::read_config(init)
                    .with_context(|| format!("--init {}", init.display()))?;
                if let Some(h) = &args.head {
                    let head: Head = h.parse()?;
                    if head != cfg.net.head {
                        bail!(
                            "--head {h}: {} has the {} head",
                            init.display(),
                            cfg.net.head.as_str()
                        );
                    }
                }
                apply_overrides(&mut cfg, args);
                let mut t = PoseTrainer::new(cfg, args.seed)?;
                t.load_weights(init)
                    .with_context(|| format!("--init {}", init.display()))?;
                tracing::info!(
                    "initialised from {} (preset {:?}, head {}); fresh optimiser at iteration 0",
                    init.display(),
                    t.config().preset,
                    t.config().net.head.as_str()
                );
                t
            }
            None => {
                let head: Head = args.head.as_deref().unwrap_or("softmax").parse()?;
                let mut cfg = PoseConfig::preset(&args.preset, head)?;
                apply_overrides(&mut cfg, args);
                PoseTrainer::new(cfg, args.seed)?
            }
        }
    };
    Ok((trainer, resuming))
}

/// `train-pose`: trains into `args.out` until the planned iterations are done, the stop flag
/// is set or the deadline passes (see the module doc for the files).
pub fn train(args: &TrainArgs, control: RunControl<'_>) -> Result<Outcome> {
    let objects: ObjectsSpec = args.objects.parse()?;
    train_objects(args, &objects, control)
}

/// [`train`] with the objects given as a spec (`args.objects` is then only a label).
pub fn train_objects(
    args: &TrainArgs,
    objects: &ObjectsSpec,
    control: RunControl<'_>,
) -> Result<Outcome> {
    let train_corpus = open_objects(objects, Split::Train)?;
    let val_corpus = open_objects(objects, Split::Val)?;
    train_corpora(args, objects, train_corpus, val_corpus, control)
}

/// [`train_objects`] with the corpora already open (they may be one and the same); `objects`
/// describes them in `data.json`.
pub fn train_corpora(
    args: &TrainArgs,
    objects: &ObjectsSpec,
    train_corpus: Arc<Corpus>,
    val_corpus: Arc<Corpus>,
    control: RunControl<'_>,
) -> Result<Outcome> {
    let protocol: SamplingProtocol = args.protocol.parse()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let latest = args.out.join("latest.safetensors");
    let (mut trainer, resuming) = make_trainer(args, &latest)?;
    trainer.start_lr_decay(args.lr_decay_to, args.lr_floor)?;
    let cfg = trainer.config().clone();
    let seed = trainer.seed();
    tracing::info!("seed {seed}");
    tracing::info!("config {}", serde_json::to_string_pretty(&cfg)?);
    tracing::info!(
        "threads: compute {}, data {}",
        std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".into()),
        args.data_workers
    );

    let scfg = sample_config(&cfg, protocol);
    let paper_fraction = args.paper_fraction;
    if !(0.0..=1.0).contains(&paper_fraction) {
        bail!("--paper-fraction {paper_fraction}: must be in [0, 1]");
    }
    if paper_fraction > 0.0 && protocol != SamplingProtocol::Deployment {
        bail!(
            "--paper-fraction needs --protocol deployment (the paper's samples are mixed into it)"
        );
    }
    let paper_objects: Option<ObjectsSpec> = match &args.paper_objects {
        None => None,
        Some(_) if paper_fraction == 0.0 => {
            bail!(
                "--paper-objects needs --paper-fraction above 0 (it names what those samples draw)"
            )
        }
        Some(spec) => Some(
            spec.parse()
                .with_context(|| format!("--paper-objects {spec}"))?,
        ),
    };
    // The `--paper-objects` corpus; `None`: the paper samples draw from the training corpus.
    let paper_corpus = paper_objects
        .as_ref()
        .map(|spec| open_objects(spec, Split::Train).context("--paper-objects"))
        .transpose()?;
    let paper_cfg = ObjectSampleConfig {
        symmetry_aware: scfg.symmetry_aware,
        ..sample_config(&cfg, SamplingProtocol::Paper)
    };
    let mut data = serde_json::json!({
        "protocol": protocol.as_str(),
        "objects": objects.describe(),
        "init": args.init,
        "sample": scfg,
        "validation_seed": VALIDATION_SEED,
        "precise_bn_batches": args.precise_bn,
    });
    if paper_fraction > 0.0 {
        // Only when used, so that the records of earlier runs still match.
        data["paper_fraction"] = serde_json::json!(paper_fraction);
        data["paper_sample"] = serde_json::to_value(&paper_cfg)?;
        if let Some(spec) = &paper_objects {
            data["paper_objects"] = spec.describe();
        }
    }
    tracing::info!("data {}", serde_json::to_string(&data)?);
    check_data_record(&args.out.join("data.json"), &data, resuming)?;
    // The objects' symmetries found by earlier parts of the run (the search takes ≈ 0.3 s per
    // object as it is first drawn); saved again with every checkpoint.
    let symmetries_path = args.out.join("symmetries.json");
    let symmetries = read_symmetry_cache(&symmetries_path)?;
    if !symmetries.is_empty() {
        tracing::info!(
            "symmetries of {} objects from {}",
            symmetries.len(),
            symmetries_path.display()
        );
    }
    train_corpus.set_known_symmetries(symmetries.clone());
    val_corpus.set_known_symmetries(symmetries.clone());
    if let Some(paper) = &paper_corpus {
        paper.set_known_symmetries(symmetries.clone());
    }
    let generator = Arc::new(ObjectSampleGenerator::new(
        train_corpus.clone(),
        scfg.clone(),
        seed,
    )?);
    let paper_generator = if paper_fraction > 0.0 {
        tracing::info!(
            "paper-protocol samples: {:.0} % of training",
            100.0 * paper_fraction
        );
        Some(Arc::new(ObjectSampleGenerator::new(
            paper_corpus.clone().unwrap_or_else(|| train_corpus.clone()),
            paper_cfg,
            seed,
        )?))
    } else {
        None
    };
    let val_gen = ObjectSampleGenerator::new(val_corpus.clone(), scfg.clone(), VALIDATION_SEED)?;
    let val_set: Vec<ObjectSample> = (0..cfg.train.validation_count as u64)
        .map(|i| val_gen.sample(i))
        .collect::<Result<_, _>>()?;
    let b = cfg.train.batch_size;
    let bn_batches = recalibration_batches(&train_corpus, &scfg, b, args.precise_bn)?;
    let mut task = PoseTask {
        trainer,
        val_set,
        bn_batches,
        symmetries,
        symmetries_path,
        paper_corpus,
        train_corpus,
        val_corpus,
    };
    let workers = args.data_workers;
    crate::run(
        &mut task,
        &args.out,
        args.resume,
        control,
        |start, count| {
            Prefetcher::new(
                start * b as u64,
                Some(count * b as u64),
                workers,
                2 * b,
                move |i| match &paper_generator {
                    Some(p) if is_paper_sample(seed, i, paper_fraction) => p.sample(i),
                    _ => generator.sample(i),
                },
            )
            .batches(b)
            .map(|r| r.map_err(anyhow::Error::from))
        },
    )
}

/// Whether training sample `index` of a run with `--paper-fraction` follows the paper's
/// protocol: a uniform draw from (`seed`, `index`) below `fraction`.
pub fn is_paper_sample(seed: u64, index: u64, fraction: f64) -> bool {
    crate::uniform_draw(seed ^ 0x7061_7065_725f_6d69, index) < fraction
}

/// The pose network's side of [`crate::run`].
pub struct PoseTask {
    pub trainer: PoseTrainer,
    /// The fixed validation views.
    pub val_set: Vec<ObjectSample>,
    /// Fixed training-split batches for precise BN before each validation (empty: none).
    pub bn_batches: Vec<Vec<ObjectSample>>,
    /// Object id → symmetries (normalised frame), saved with every checkpoint.
    pub symmetries: HashMap<String, Vec<ic_geometry::Pose>>,
    pub symmetries_path: PathBuf,
    pub train_corpus: Arc<Corpus>,
    pub val_corpus: Arc<Corpus>,
    /// The `--paper-objects` corpus when it is not the training corpus.
    pub paper_corpus: Option<Arc<Corpus>>,
}

impl Task for PoseTask {
    type Batch = Vec<ObjectSample>;
    const TRAIN_HEADER: &'static str =
        "iteration,loss,accuracy,loss_avg,accuracy_avg,matched_fraction,samples_per_s,elapsed_s";
    const METRIC: &'static str = "acc";

    fn val_header(&self) -> &'static str {
        "iteration,rotation_median_deg,rotation_acc_5,rotation_acc_10,rotation_acc_15,translation_sq_median,translation_acc_1e2,correspondence_accuracy,elapsed_s,add_s_acc_01d,rotation_acc_15_sym"
    }
    fn iteration(&self) -> u64 {
        self.trainer.iteration()
    }
    fn total(&self) -> u64 {
        self.trainer.config().train.iterations
    }
    fn batch_size(&self) -> usize {
        self.trainer.config().train.batch_size
    }
    fn validate_every(&self) -> u64 {
        self.trainer.config().train.validate_every
    }

    fn step(&mut self, batch: Vec<ObjectSample>) -> Result<StepRow> {
        let stats = self.trainer.step(&batch)?;
        let cfg = self.trainer.config();
        Ok(StepRow {
            loss: stats.loss as f64,
            metric: stats.accuracy.unwrap_or(f64::NAN),
            extra: vec![
                stats.matched as f64 / (cfg.train.batch_size * cfg.train.observed_points) as f64,
            ],
        })
    }

    fn validate(&mut self, done: u64, elapsed: f64) -> Result<Validation> {
        if !self.bn_batches.is_empty() {
            // Training mode normalises with batch statistics, so replacing the running ones
            // changes only what inference (validation, saved weights) sees.
            self.trainer.recalibrate_batch_norm(&self.bn_batches)?;
        }
        let est = self.trainer.estimator();
        let m = evaluate(&est, self.val_set.iter().cloned().map(Ok), |_| {})?;
        let row = format!(
            "{done},{:.3},{:.4},{:.4},{:.4},{:.6},{:.4},{:.4},{elapsed:.1},{:.4},{:.4}",
            m.rotation_median_deg,
            m.rotation_acc_5,
            m.rotation_acc_10,
            m.rotation_acc_15,
            m.translation_sq_median,
            m.translation_acc_1e2,
            m.correspondence_accuracy,
            m.add_s_acc_01d,
            m.rotation_acc_15_sym
        );
        // Up to symmetry: a can turned about its axis is not an error.
        let score = m.rotation_acc_15_sym - 1e-4 * m.rotation_median_deg;
        let line = format!(
            "iteration {done}: validation rot median {:.2}°, acc@5/10/15 {:.3}/{:.3}/{:.3}, acc@15 up to symmetry {:.3}, ADD-S<0.1d {:.3}, corr acc {:.3}",
            m.rotation_median_deg,
            m.rotation_acc_5,
            m.rotation_acc_10,
            m.rotation_acc_15,
            m.rotation_acc_15_sym,
            m.add_s_acc_01d,
            m.correspondence_accuracy
        );
        Ok(Validation {
            row,
            score,
            line,
            report: serde_json::to_value(&m)?,
        })
    }

    fn save(&mut self, path: &Path) -> Result<()> {
        self.symmetries.extend(self.train_corpus.found_symmetries());
        self.symmetries.extend(self.val_corpus.found_symmetries());
        if let Some(paper) = &self.paper_corpus {
            self.symmetries.extend(paper.found_symmetries());
        }
        write_symmetry_cache(&self.symmetries_path, &self.symmetries)?;
        Ok(self.trainer.save(path)?)
    }

    fn save_weights(&self, path: &Path) -> Result<()> {
        Ok(self.trainer.save_weights(path)?)
    }

    fn rate(sps: f64) -> String {
        format!("{:.0} pairs/h", sps * 3600.0)
    }
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Metrics {
    pub count: usize,
    pub failures: usize,
    pub rotation_median_deg: f64,
    pub rotation_mean_deg: f64,
    pub rotation_acc_5: f64,
    pub rotation_acc_10: f64,
    pub rotation_acc_15: f64,
    /// acc@15° of the rotation error up to the object's symmetry: the smallest error to the
    /// true pose or any pose equivalent to it (`ObjectSample::equivalent_poses`; the same as
    /// `rotation_acc_15` without symmetry-aware samples). The selection score.
    pub rotation_acc_15_sym: f64,
    /// Fraction of samples with an equivalent pose (symmetric objects).
    pub symmetric_fraction: f64,
    /// Median of ‖t̂ − t‖² (normalised units²), as the paper.
    pub translation_sq_median: f64,
    /// Median of ‖t̂ − t‖.
    pub translation_l2_median: f64,
    pub translation_acc_1e3: f64,
    pub translation_acc_5e3: f64,
    pub translation_acc_1e2: f64,
    /// Arg-max correspondence accuracy over matched observed points.
    pub correspondence_accuracy: f64,
    /// Median ADD-S (normalised units: mean distance of the model points moved by the
    /// estimate to the closest model point moved by the truth).
    pub add_s_median: f64,
    /// Fraction with ADD-S below 0.1 × the model's diameter (the usual ADD-S accuracy).
    pub add_s_acc_01d: f64,
    /// Median observed voxels per sample (before drawing N).
    pub observed_voxels_median: f64,
    pub seconds_per_case: f64,
}

/// Evaluates `estimator` on `samples` (a failed estimate counts as 180° / infinite error).
pub fn evaluate<'a>(
    estimator: &PoseEstimator,
    samples: impl Iterator<Item = Result<ObjectSample>> + 'a,
    mut progress: impl FnMut(usize),
) -> Result<Metrics> {
    let clock = Instant::now();
    let (mut rot, mut trans) = (Vec::<f64>::new(), Vec::<f64>::new());
    let (mut rot_sym, mut symmetric) = (Vec::<f64>::new(), 0usize);
    let (mut add_s, mut add_s_rel, mut voxels) = (Vec::new(), Vec::new(), Vec::new());
    let (mut right, mut total) = (0usize, 0usize);
    let mut failures = 0;
    for (i, s) in samples.enumerate() {
        let s = s?;
        voxels.push(s.observed_voxels as f64);
        symmetric += !s.equivalent_poses.is_empty() as usize;
        let diameter = ic_eval::diameter(&s.model_points);
        let out = estimator.infer(&s.model_points, &s.observed_points)?;
        let matches = out.matches()?.remove(0);
        if let Some(acc) =
            ic_pose::correspondence_accuracy(std::slice::from_ref(&matches), &[&s.assignment])
        {
            let n = s.assignment.inlier_count();
            right += (acc * n as f64).round() as usize;
            total += n;
        }
        match ic_pose::recover_pose(
            &s.model_points,
            &s.observed_points,
            &matches,
            &estimator.recovery,
        ) {
            Ok(r) => {
                rot.push(ic_eval::rotation_error_deg(&r.pose, &s.pose));
                rot_sym.push(
                    s.equivalent_poses
                        .iter()
                        .map(|p| ic_eval::rotation_error_deg(&r.pose, p))
                        .fold(ic_eval::rotation_error_deg(&r.pose, &s.pose), f64::min),
                );
                trans.push(ic_eval::translation_error_sq(&r.pose, &s.pose));
                let a = ic_eval::add_s(&r.pose, &s.pose, &s.model_points)?;
                add_s.push(a);
                add_s_rel.push(a / diameter.max(1e-12));
            }
            Err(e) => {
                tracing::debug!("sample {}: {e}", s.index);
                failures += 1;
                rot.push(180.0);
                rot_sym.push(180.0);
                trans.push(f64::INFINITY);
                add_s.push(f64::INFINITY);
                add_s_rel.push(f64::INFINITY);
            }
        }
        progress(i + 1);
    }
    let n = rot.len();
    let frac = ic_eval::accuracy;
    let mut m = Metrics {
        count: n,
        failures,
        rotation_mean_deg: rot.iter().sum::<f64>() / n.max(1) as f64,
        rotation_acc_5: frac(&rot, 5.0),
        rotation_acc_10: frac(&rot, 10.0),
        rotation_acc_15: frac(&rot, 15.0),
        rotation_acc_15_sym: frac(&rot_sym, 15.0),
        symmetric_fraction: symmetric as f64 / n.max(1) as f64,
        translation_acc_1e3: frac(&trans, 1e-3),
        translation_acc_5e3: frac(&trans, 5e-3),
        translation_acc_1e2: frac(&trans, 1e-2),
        correspondence_accuracy: right as f64 / total.max(1) as f64,
        add_s_median: ic_eval::median(&add_s),
        add_s_acc_01d: frac(&add_s_rel, 0.1),
        observed_voxels_median: ic_eval::median(&voxels),
        seconds_per_case: clock.elapsed().as_secs_f64() / n.max(1) as f64,
        ..Default::default()
    };
    m.rotation_median_deg = ic_eval::median(&rot);
    let l2: Vec<f64> = trans.iter().map(|t| t.sqrt()).collect();
    m.translation_sq_median = ic_eval::median(&trans);
    m.translation_l2_median = ic_eval::median(&l2);
    Ok(m)
}

pub fn apply_overrides(cfg: &mut PoseConfig, a: &TrainArgs) {
    if let Some(v) = a.iterations {
        cfg.train.iterations = v;
    }
    if let Some(v) = a.batch_size {
        cfg.train.batch_size = v;
    }
    if let Some(v) = a.emb_dims {
        cfg.net.emb_dims = v;
    }
    if let Some(v) = a.ff_dims {
        cfg.net.ff_dims = v;
    }
    if let Some(v) = a.k {
        cfg.net.k = v;
    }
    if let Some(v) = a.pooled_keys {
        cfg.net.pooled_keys = Some(v as usize);
    }
    if let Some(v) = a.model_points {
        cfg.train.model_points = v;
    }
    if let Some(v) = a.observed_points {
        cfg.train.observed_points = v;
    }
    if let Some(v) = a.learning_rate {
        cfg.train.learning_rate = v;
    }
    if let Some(v) = a.validate_every {
        cfg.train.validate_every = v;
    }
    if let Some(v) = a.validation_count {
        cfg.train.validation_count = v;
    }
}

/// The symmetry cache of a run (`<out>/symmetries.json`): object id → motions, valid only
/// for the search settings it records (`ic_data::TRAINING_SYMMETRY_OPTIONS`); absent or made
/// with other settings → empty.
pub fn read_symmetry_cache(path: &Path) -> Result<HashMap<String, Vec<ic_geometry::Pose>>> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Ok(HashMap::new());
    };
    let doc: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
    if doc["options"] != serde_json::to_value(ic_data::TRAINING_SYMMETRY_OPTIONS)? {
        tracing::warn!(
            "{}: made with other search settings; searching again",
            path.display()
        );
        return Ok(HashMap::new());
    }
    serde_json::from_value(doc["objects"].clone())
        .with_context(|| format!("reading {}: objects", path.display()))
}

pub fn write_symmetry_cache(
    path: &Path,
    symmetries: &HashMap<String, Vec<ic_geometry::Pose>>,
) -> Result<()> {
    let sorted: std::collections::BTreeMap<_, _> = symmetries.iter().collect();
    let bytes = serde_json::to_vec(&serde_json::json!({
        "what": "rotational symmetries of the run's objects (normalised frame), by id",
        "options": ic_data::TRAINING_SYMMETRY_OPTIONS,
        "objects": sorted,
    }))?;
    crate::write_atomic(path, &bytes)
}

pub fn check_data_record(path: &Path, data: &serde_json::Value, resuming: bool) -> Result<()> {
    if resuming && let Ok(text) = std::fs::read_to_string(path) {
        let old: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
        // `init` only matters for a fresh start; precise BN only changes what validation sees.
        let strip = |v: &serde_json::Value| {
            let mut v = v.clone();
            if let Some(o) = v.as_object_mut() {
                o.remove("init");
                o.remove("precise_bn_batches");
            }
            v
        };
        if strip(&old) != strip(data) {
            tracing::warn!(
                "WARNING: the data differ from {} (protocol, objects or sample settings): the resumed run is not the uninterrupted one",
                path.display()
            );
        }
        return Ok(());
    }
    crate::write_atomic(path, serde_json::to_string_pretty(data)?.as_bytes())
}

/// Seed of the sample stream used to recalibrate batch norm (training split).
const RECALIBRATION_SEED: u64 = 0x0062_726e;

/// `count` fixed batches of `batch` training-split samples for precise BN (seed
/// [`RECALIBRATION_SEED`], whatever the run's seed).
fn recalibration_batches(
    corpus: &Arc<Corpus>,
    scfg: &ObjectSampleConfig,
    batch: usize,
    count: usize,
) -> Result<Vec<Vec<ObjectSample>>> {
    if count == 0 {
        return Ok(Vec::new());
    }
    let generator = ObjectSampleGenerator::new(corpus.clone(), scfg.clone(), RECALIBRATION_SEED)?;
    let b = batch as u64;
    Ok((0..count as u64)
        .map(|k| (0..b).map(|i| generator.sample(k * b + i)).collect())
        .collect::<Result<_, _>>()?)
}

/// `eval-pose`: measures a checkpoint on fixed samples, prints the JSON report and writes it
/// (default `<model>.eval-<split>-<refine>.json`, `<model>.eval-<protocol>-<split>-<refine>.json`
/// for the deployment protocol). RAYON_NUM_THREADS (`--threads`) is the caller's to set.
pub fn eval(args: &EvalArgs) -> Result<serde_json::Value> {
    let protocol: SamplingProtocol = args.protocol.parse()?;
    let objects: ObjectsSpec = args.objects.parse()?;
    let split: Split = args.split.parse()?;
    let mut est = if args.recalibrate_bn > 0 {
        let cfg = ic_pose::checkpoint::read_config(&args.model)?;
        let mut trainer = PoseTrainer::new(cfg.clone(), 0)?;
        trainer.load_weights(&args.model)?;
        let corpus = open_objects(&objects, Split::Train)?;
        let b = cfg.train.batch_size;
        let batches = recalibration_batches(
            &corpus,
            &sample_config(&cfg, protocol),
            b,
            args.recalibrate_bn,
        )?;
        trainer.recalibrate_batch_norm(&batches)?;
        tracing::info!(
            "batch norm recalibrated on {} batches of {b} training-split samples (seed {RECALIBRATION_SEED:#x})",
            args.recalibrate_bn
        );
        if let Some(out) = &args.save_recalibrated {
            trainer.save_weights(out)?;
            tracing::info!("written {}", out.display());
        }
        let mut e = trainer.estimator();
        e.recovery = PoseEstimator::load(&args.model)?.recovery;
        e
    } else {
        PoseEstimator::load(&args.model)?
    };
    est.recovery.refine = match args.refine.as_str() {
        "none" => Refine::None,
        "icp" => Refine::Icp,
        other => bail!("--refine {other:?}: expected none or icp"),
    };
    if let Some(p) = args.min_probability {
        est.recovery.min_probability = p;
    }
    if args.unweighted {
        est.recovery.weighted = false;
    }
    let cfg = est.config().clone();
    let corpus = open_objects(&objects, split)?;
    let generator = Arc::new(ObjectSampleGenerator::new(
        corpus,
        sample_config(&cfg, protocol),
        args.seed,
    )?);
    let samples = Prefetcher::new(0, Some(args.count), 1, 8, move |i| generator.sample(i))
        .map(|r| r.map_err(anyhow::Error::from));
    let bar = ProgressBar::new(args.count);
    let m = evaluate(&est, samples, |i| {
        bar.set_position(i as u64);
        if i % 50 == 0 && !crate::interactive() {
            tracing::info!("{i}/{} cases", args.count);
        }
    })?;
    bar.finish_and_clear();
    let report = serde_json::json!({
        "model": args.model,
        "split": split.as_str(),
        "protocol": protocol.as_str(),
        "objects": objects.describe(),
        "seed": args.seed,
        "refine": args.refine,
        "recovery": est.recovery,
        "config": cfg,
        "metrics": m,
    });
    let text = serde_json::to_string_pretty(&report)?;
    let out = args.out.clone().unwrap_or_else(|| {
        // The paper protocol keeps the old names.
        let mut p = args.model.clone().into_os_string();
        match protocol {
            SamplingProtocol::Paper => p.push(format!(".eval-{split}-{}.json", args.refine)),
            _ => p.push(format!(".eval-{protocol}-{split}-{}.json", args.refine)),
        }
        PathBuf::from(p)
    });
    crate::write_atomic(&out, text.as_bytes())?;
    tracing::info!("written {}", out.display());
    Ok(report)
}
