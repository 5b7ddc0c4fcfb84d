//! `ic_train` — training the pose and segmentation networks on data rendered on the fly.
//!
//! - [`Trainer`]: one network (any [`Network`]: `ic_pose::PoseNet`, `ic_seg::UNet`) with its
//!   seeded weights, Adam and position in the run; saved to and resumed from safetensors
//!   checkpoints whose metadata hold the configuration (`ic_pose.config` / `ic_seg.config`)
//!   and the training state (`ic_pose.train_state` / `ic_seg.train_state`:
//!   `{"iteration", "seed", "adam_step"}`) — the files `cargo xtask train-*` always wrote. A
//!   resumed run gives the same numbers as an uninterrupted one, bit for bit.
//! - [`run`]: the one training loop both networks use (a [`Task`] says what a step and a
//!   validation are): progress bar and log lines, running averages (EMA, weight 0.05), one CSV
//!   row per iteration (`<out>/train.csv`) and per validation (`<out>/val.csv`), the best
//!   validation's weights (`best.safetensors`, `best.json`), resumable checkpoints
//!   (`latest.safetensors`) every `checkpoint_secs`, at the end, on Ctrl-C / SIGTERM (a
//!   [`RunControl::stop`] flag) and at a deadline; the final weights (`final.safetensors`).
//! - [`pose`]: the pose network on object-alone views (`ic_data::ObjectSampleGenerator`),
//!   its evaluation (rotation, translation, ADD-S accuracies) and the run's symmetry cache.
//! - [`seg`]: the segmentation network on room scenes, its evaluation (IoU, found rate).
//!
//! `cargo xtask train-pose|train-seg|eval-pose|eval-seg` and `incontext train pose|seg` call
//! this crate. Determinism: iteration `i` uses samples `i·B … (i+1)·B − 1` of the seeded
//! sample stream, so the data side resumes by itself.

mod objects;
pub mod pose;
pub mod seg;
pub mod widen;

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use candle_core::{Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use ic_nn::adam::Adam;
use ic_nn::seeded_var_builder;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize, de::DeserializeOwned};

pub use objects::{ObjectsSpec, SourceKind, SourceSpec};
pub use pose::PoseTrainer;
pub use seg::SegTrainer;

/// A network the [`Trainer`] can build, checkpoint and resume.
pub trait Network: Clone + Sized {
    /// The whole configuration saved with every checkpoint (network shape and training
    /// settings).
    type Config: Clone + Serialize + DeserializeOwned;
    /// The network crate's error.
    type Error: From<candle_core::Error> + From<ic_nn::CheckpointError>;
    /// Metadata key of the configuration (JSON).
    const CONFIG_KEY: &'static str;
    /// Metadata key of the [`TrainState`] (JSON; training checkpoints only).
    const STATE_KEY: &'static str;

    /// The network with the variables of `vb`.
    fn build(vb: VarBuilder, config: &Self::Config) -> Result<Self, Self::Error>;
    /// Checks a configuration before a network is built from it.
    fn validate(config: &Self::Config) -> Result<(), Self::Error>;
    /// The configuration saved in a checkpoint (checked).
    fn read_config(path: &Path) -> Result<Self::Config, Self::Error>;
    /// Whether two configurations describe networks with the same variables.
    fn same_network(a: &Self::Config, b: &Self::Config) -> bool;
    /// Adam's step size in `config`.
    fn learning_rate(config: &Self::Config) -> f64;
    fn set_learning_rate(config: &mut Self::Config, learning_rate: f64);
    /// The planned iteration count in `config`.
    fn iterations(config: &Self::Config) -> u64;
    fn set_iterations(config: &mut Self::Config, iterations: u64);
}

/// Where a training run stands (the JSON under [`Network::STATE_KEY`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Completed iterations (the next one is this index).
    pub iteration: u64,
    /// Seed of the run (weights initialisation and the sample stream).
    pub seed: u64,
    /// Adam's step count.
    pub adam_step: u64,
    /// The learning-rate decay the run follows, if any (checkpoints of older runs have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lr_decay: Option<LrDecay>,
}

/// A half-cosine decay of Adam's learning rate: `start` at iteration `from`, `floor` at
/// iteration `to` and after, `floor + (start − floor)·(1 + cos(π·(i − from)/(to − from)))/2`
/// between. Saved with the run's checkpoints, so a resumed run goes on along it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LrDecay {
    pub from: u64,
    pub to: u64,
    pub start: f64,
    pub floor: f64,
}

impl LrDecay {
    /// The learning rate of the step that completes iteration `iteration + 1`.
    pub fn rate(&self, iteration: u64) -> f64 {
        if iteration <= self.from {
            return self.start;
        }
        if iteration >= self.to {
            return self.floor;
        }
        let x = (iteration - self.from) as f64 / (self.to - self.from) as f64;
        self.floor + (self.start - self.floor) * 0.5 * (1.0 + (std::f64::consts::PI * x).cos())
    }
}

fn checkpoint_error<N: Network>(path: &Path, message: impl Into<String>) -> N::Error {
    ic_nn::CheckpointError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
    .into()
}

/// Reads the training state of a training checkpoint.
pub fn read_state<N: Network>(path: &Path) -> Result<TrainState, N::Error> {
    let meta = ic_nn::checkpoint::read_metadata(path)?;
    let text = meta.get(N::STATE_KEY).ok_or_else(|| {
        checkpoint_error::<N>(path, "no training state (a weights-only checkpoint?)")
    })?;
    serde_json::from_str(text)
        .map_err(|e| checkpoint_error::<N>(path, format!("bad training state: {e}")))
}

/// Network + optimiser + position in the run.
pub struct Trainer<N: Network> {
    config: N::Config,
    varmap: VarMap,
    net: N,
    adam: Adam,
    iteration: u64,
    seed: u64,
    device: Device,
    lr_decay: Option<LrDecay>,
}

impl<N: Network> Trainer<N> {
    /// A fresh run on the CPU: weights drawn from `seed`.
    pub fn new(config: N::Config, seed: u64) -> Result<Self, N::Error> {
        Self::new_on(config, seed, Device::Cpu)
    }

    /// A fresh run on `device`.
    pub fn new_on(config: N::Config, seed: u64, device: Device) -> Result<Self, N::Error> {
        N::validate(&config)?;
        let varmap = VarMap::new();
        let vb = seeded_var_builder(&varmap, seed, &device);
        let net = N::build(vb, &config)?;
        let adam = Adam::new(&varmap, N::learning_rate(&config))?;
        Ok(Trainer {
            config,
            varmap,
            net,
            adam,
            iteration: 0,
            seed,
            device,
            lr_decay: None,
        })
    }

    /// Continues the run saved in `path` (configuration, weights, Adam moments, iteration).
    pub fn resume(path: &Path) -> Result<Self, N::Error> {
        let config = N::read_config(path)?;
        let state = read_state::<N>(path)?;
        let mut t = Self::new(config, state.seed)?;
        ic_nn::checkpoint::restore_training(
            path,
            &t.varmap,
            &mut t.adam,
            state.adam_step,
            &t.device,
        )?;
        t.iteration = state.iteration;
        t.lr_decay = state.lr_decay;
        if let Some(d) = t.lr_decay {
            t.set_rate(d.rate(t.iteration));
        }
        Ok(t)
    }

    /// [`Trainer::resume`] for a training command: logs where the run picks up and, when
    /// `iterations` is given, extends the planned iteration count to it.
    pub fn resume_run(latest: &Path, iterations: Option<u64>) -> anyhow::Result<Self>
    where
        N::Error: std::error::Error + Send + Sync + 'static,
    {
        let mut t =
            Self::resume(latest).with_context(|| format!("resuming {}", latest.display()))?;
        tracing::info!(
            "resuming {} at iteration {}",
            latest.display(),
            t.iteration()
        );
        if let Some(it) = iterations {
            t.set_iterations(it);
        }
        Ok(t)
    }

    pub fn config(&self) -> &N::Config {
        &self.config
    }

    /// Changes the learning rate from the next step on (a step schedule across a resume);
    /// the configuration saved with later checkpoints records the new rate.
    /// A decay set before ([`Trainer::decay_learning_rate`]) ends here: the rate stays.
    pub fn set_learning_rate(&mut self, learning_rate: f64) {
        self.lr_decay = None;
        self.set_rate(learning_rate);
    }

    fn set_rate(&mut self, learning_rate: f64) {
        N::set_learning_rate(&mut self.config, learning_rate);
        self.adam.learning_rate = learning_rate;
    }

    /// From the next step on, decays the learning rate from its current value to `floor` at
    /// iteration `to` along a half cosine ([`LrDecay`]), then keeps `floor`; saved with the
    /// checkpoints, so resumed runs follow it. `to` at or before the current iteration sets
    /// `floor` at once.
    pub fn decay_learning_rate(&mut self, to: u64, floor: f64) {
        self.lr_decay = Some(LrDecay {
            from: self.iteration,
            to: to.max(self.iteration),
            start: N::learning_rate(&self.config),
            floor,
        });
        self.set_rate(self.current_rate());
    }

    /// The decay the run follows, if any.
    pub fn lr_decay(&self) -> Option<LrDecay> {
        self.lr_decay
    }

    /// The training commands' `--lr-decay-to TO --lr-floor FLOOR`: starts the decay (logged)
    /// when `to` is given; otherwise logs the one a resumed run goes on with.
    pub fn start_lr_decay(&mut self, to: Option<u64>, floor: f64) -> anyhow::Result<()> {
        if let Some(to) = to {
            if !(floor > 0.0 && floor.is_finite()) {
                anyhow::bail!("--lr-floor {floor}: must be a positive learning rate");
            }
            self.decay_learning_rate(to, floor);
        }
        if let Some(d) = self.lr_decay {
            tracing::info!(
                "learning rate {:.3e} → {:.3e} along a half cosine over iterations {}–{} (now {:.3e})",
                d.start,
                d.floor,
                d.from,
                d.to,
                self.current_rate()
            );
        }
        Ok(())
    }

    fn current_rate(&self) -> f64 {
        match self.lr_decay {
            Some(d) => d.rate(self.iteration),
            None => self.adam.learning_rate,
        }
    }

    /// Changes the planned iteration count (e.g. to extend a resumed run).
    pub fn set_iterations(&mut self, iterations: u64) {
        N::set_iterations(&mut self.config, iterations);
    }

    /// Completed iterations.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn net(&self) -> &N {
        &self.net
    }

    pub fn varmap(&self) -> &VarMap {
        &self.varmap
    }

    /// Loads the network weights of `path` (weights-only or training checkpoint; its network
    /// configuration must equal this trainer's) without touching Adam or the iteration count:
    /// fine-tuning from shipped weights, or recalibrating batch norm.
    pub fn load_weights(&mut self, path: &Path) -> Result<(), N::Error> {
        let config = N::read_config(path)?;
        if !N::same_network(&config, &self.config) {
            return Err(checkpoint_error::<N>(
                path,
                "its network configuration differs from this trainer's",
            ));
        }
        let tensors = ic_nn::checkpoint::load_tensors(path, &self.device)?;
        ic_nn::checkpoint::load_into_varmap(&self.varmap, &tensors, path)?;
        Ok(())
    }

    /// Adam's step over `grads`, and one more completed iteration.
    fn apply(&mut self, grads: &candle_core::backprop::GradStore) -> Result<(), N::Error> {
        if self.lr_decay.is_some() {
            self.set_rate(self.current_rate());
        }
        self.adam.step(grads)?;
        self.iteration += 1;
        Ok(())
    }

    fn metadata(&self, with_state: bool) -> Result<HashMap<String, String>, N::Error> {
        let json = |e: serde_json::Error| candle_core::Error::Msg(e.to_string());
        let mut meta = HashMap::new();
        meta.insert(
            N::CONFIG_KEY.to_string(),
            serde_json::to_string(&self.config).map_err(json)?,
        );
        if with_state {
            let state = TrainState {
                iteration: self.iteration,
                seed: self.seed,
                adam_step: self.adam.step_count(),
                lr_decay: self.lr_decay,
            };
            meta.insert(
                N::STATE_KEY.to_string(),
                serde_json::to_string(&state).map_err(json)?,
            );
        }
        Ok(meta)
    }

    fn weights(&self) -> Vec<(String, Tensor)> {
        ic_nn::checkpoint::varmap_tensors(&self.varmap)
    }

    /// Saves everything needed to resume exactly (atomically): weights, Adam's moments
    /// (`adam.m/<name>`, `adam.v/<name>`), configuration and [`TrainState`].
    pub fn save(&self, path: &Path) -> Result<(), N::Error> {
        let mut tensors = self.weights();
        tensors.extend(self.adam.state());
        Ok(ic_nn::checkpoint::save(
            path,
            &tensors,
            self.metadata(true)?,
        )?)
    }

    /// Saves the weights and configuration only (what inference needs; atomically).
    pub fn save_weights(&self, path: &Path) -> Result<(), N::Error> {
        Ok(ic_nn::checkpoint::save(
            path,
            &self.weights(),
            self.metadata(false)?,
        )?)
    }
}

/// Which network a training checkpoint holds, by the training state in its metadata.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CheckpointKind {
    /// `ic_pose.train_state`: a pose network's run.
    Pose,
    /// `ic_seg.train_state`: a segmentation network's run.
    Seg,
}

impl CheckpointKind {
    /// The metadata key of a training checkpoint of this network (its training state).
    fn state_key(self) -> &'static str {
        match self {
            CheckpointKind::Pose => <ic_pose::PoseNet as Network>::STATE_KEY,
            CheckpointKind::Seg => <ic_seg::unet::UNet as Network>::STATE_KEY,
        }
    }

    /// The metadata key of any checkpoint of this network (its configuration).
    fn config_key(self) -> &'static str {
        match self {
            CheckpointKind::Pose => <ic_pose::PoseNet as Network>::CONFIG_KEY,
            CheckpointKind::Seg => <ic_seg::unet::UNet as Network>::CONFIG_KEY,
        }
    }
}

/// Which network the checkpoint `path` holds, by which network's `key` its metadata carries;
/// otherwise the error `path: {not_what} (no … or … in its metadata{hint})`.
fn checkpoint_kind(
    path: &Path,
    key: fn(CheckpointKind) -> &'static str,
    not_what: &str,
    hint: &str,
) -> anyhow::Result<CheckpointKind> {
    let meta = ic_nn::checkpoint::read_metadata(path)?;
    let kinds = [CheckpointKind::Pose, CheckpointKind::Seg];
    match kinds.into_iter().find(|&k| meta.contains_key(key(k))) {
        Some(kind) => Ok(kind),
        None => bail!(
            "{}: {not_what} (no {} or {} in its metadata{hint})",
            path.display(),
            key(kinds[0]),
            key(kinds[1])
        ),
    }
}

/// Writes the weights and configuration of the training checkpoint `checkpoint` (a run's
/// `latest.safetensors` or `final.safetensors`) to `out` atomically, without Adam's moments
/// or the training state: the file inference loads, as the run writes `best.safetensors`.
/// `out` may be `checkpoint` itself.
///
/// Errors (naming the file): unreadable, not a training checkpoint of either network (for
/// instance already weights-only), or tensors that do not fit its configuration.
pub fn export_weights(checkpoint: &Path, out: &Path) -> anyhow::Result<CheckpointKind> {
    let kind = checkpoint_kind(
        checkpoint,
        CheckpointKind::state_key,
        "not a training checkpoint",
        "; already weights only?",
    )?;
    match kind {
        CheckpointKind::Pose => resave_weights::<ic_pose::PoseNet>(checkpoint, out)?,
        CheckpointKind::Seg => resave_weights::<ic_seg::unet::UNet>(checkpoint, out)?,
    }
    Ok(kind)
}

/// Writes the pose network of `checkpoint` (weights-only or training) to `out` atomically as a
/// weights-only file whose configuration attends over `keys` farthest-point samples of each
/// cloud (`None`: every point; `ic_pose::NetConfig::pooled_keys`): the same weights, the
/// inference setting changed. `out` may be `checkpoint` itself.
///
/// Errors (naming the file): unreadable, not a pose checkpoint, `Some(0)` keys, or tensors
/// that do not fit its configuration.
pub fn set_pooled_keys(checkpoint: &Path, out: &Path, keys: Option<usize>) -> anyhow::Result<()> {
    let mut config = ic_pose::checkpoint::read_config(checkpoint)
        .with_context(|| format!("reading {}", checkpoint.display()))?;
    config.net.pooled_keys = keys;
    config
        .validate()
        .with_context(|| format!("{}: pooled keys {keys:?}", checkpoint.display()))?;
    let mut trainer = PoseTrainer::new(config, 0)?;
    trainer
        .load_weights(checkpoint)
        .with_context(|| format!("reading {}", checkpoint.display()))?;
    trainer.save_weights(out)?;
    Ok(())
}

/// [`Trainer::resume`] from `checkpoint`, then [`Trainer::save_weights`] to `out`.
fn resave_weights<N: Network>(checkpoint: &Path, out: &Path) -> anyhow::Result<()>
where
    N::Error: std::error::Error + Send + Sync + 'static,
{
    Trainer::<N>::resume(checkpoint)
        .with_context(|| format!("reading {}", checkpoint.display()))?
        .save_weights(out)?;
    Ok(())
}

/// Writes the element-wise mean of the network weights of `checkpoints` (weights-only or
/// training checkpoints of one network, e.g. a run's checkpoints along the end of its
/// learning-rate decay) to `out` atomically, as a weights-only file with the first one's
/// configuration: weight averaging (Polyak; SWA, Izmailov et al. 2018), which smooths the
/// swings between neighbouring checkpoints. Batch-norm running statistics are averaged
/// like every other variable (`eval-pose --recalibrate-bn` re-estimates them if wanted).
/// The mean is taken in f64. `out` may be one of the inputs.
///
/// Errors (naming the file): none given, unreadable, neither network's checkpoint, or a
/// network configuration or tensor that differs from the first file's.
pub fn average_weights(checkpoints: &[PathBuf], out: &Path) -> anyhow::Result<CheckpointKind> {
    let Some(first) = checkpoints.first() else {
        bail!("no checkpoint to average");
    };
    let kind_of = |path: &Path| {
        checkpoint_kind(
            path,
            CheckpointKind::config_key,
            "not a checkpoint of either network",
            "",
        )
    };
    let kind = kind_of(first)?;
    for path in &checkpoints[1..] {
        let other = kind_of(path)?;
        if other != kind {
            bail!(
                "{}: a {other:?} checkpoint, but {} is a {kind:?} one",
                path.display(),
                first.display()
            );
        }
    }
    match kind {
        CheckpointKind::Pose => average::<ic_pose::PoseNet>(checkpoints, out)?,
        CheckpointKind::Seg => average::<ic_seg::unet::UNet>(checkpoints, out)?,
    }
    Ok(kind)
}

/// [`average_weights`] for one network type.
fn average<N: Network>(checkpoints: &[PathBuf], out: &Path) -> anyhow::Result<()>
where
    N::Error: std::error::Error + Send + Sync + 'static,
{
    let first = &checkpoints[0];
    let config = N::read_config(first).with_context(|| format!("reading {}", first.display()))?;
    let mut trainer = Trainer::<N>::new(config, 0)?;
    let mut sums: HashMap<String, Tensor> = HashMap::new();
    for path in checkpoints {
        // Checks the network configuration and every tensor's shape against the first's.
        trainer
            .load_weights(path)
            .with_context(|| format!("reading {}", path.display()))?;
        for (name, t) in trainer.weights() {
            let t = t.to_dtype(candle_core::DType::F64)?;
            let sum = match sums.remove(&name) {
                Some(s) => (s + t)?,
                None => t,
            };
            sums.insert(name, sum);
        }
    }
    let n = checkpoints.len() as f64;
    let mean = sums
        .into_iter()
        .map(|(name, s)| Ok((name, (s / n)?.to_dtype(candle_core::DType::F32)?)))
        .collect::<candle_core::Result<HashMap<_, _>>>()?;
    ic_nn::checkpoint::load_into_varmap(trainer.varmap(), &mean, out)?;
    trainer.save_weights(out)?;
    Ok(())
}

/// The camera of a `--camera WIDTH HEIGHT FX FY` flag (pixels; the principal point at the
/// image's centre), checked: whole sizes of 1–8192 pixels, positive finite focal lengths.
pub fn camera_arg(values: &[f64]) -> anyhow::Result<ic_geometry::Intrinsics> {
    let [w, h, fx, fy] = values else {
        anyhow::bail!(
            "a camera is WIDTH HEIGHT FX FY (4 numbers), got {}",
            values.len()
        );
    };
    for (name, v) in [("width", w), ("height", h)] {
        if !(v.fract() == 0.0 && (1.0..=8192.0).contains(v)) {
            anyhow::bail!("camera {name} {v} is not a whole number of pixels in 1–8192");
        }
    }
    Ok(ic_geometry::Intrinsics::centred(
        *w as u32, *h as u32, *fx, *fy,
    )?)
}

// ---------------------------------------------------------------------------------------
// Stopping: Ctrl-C / SIGTERM set a flag that the loop reads after every iteration.

static STOP: AtomicBool = AtomicBool::new(false);

/// The process-wide stop flag that [`install_signal_handlers`] and [`request_stop`] set.
pub fn stop_flag() -> &'static AtomicBool {
    &STOP
}

/// Asks every loop that watches [`stop_flag`] to save a checkpoint and stop.
pub fn request_stop() {
    STOP.store(true, Ordering::SeqCst);
}

extern "C" fn on_signal(_: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

/// SIGINT and SIGTERM set [`stop_flag`] (the run then saves its checkpoint and returns).
pub fn install_signal_handlers() {
    // SAFETY: the handler only stores into an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
}

/// Sets RAYON_NUM_THREADS (compute threads; at least 1).
///
/// # Safety
/// Writes the process environment: call it before any other thread exists.
pub unsafe fn set_threads(threads: Option<usize>) {
    if let Some(t) = threads {
        // SAFETY: the caller guarantees that no other thread runs yet.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", t.max(1).to_string()) };
    }
}

// ---------------------------------------------------------------------------------------
// The loop.

/// What one training step measured, for the CSV row and the running averages.
#[derive(Clone, Debug, PartialEq)]
pub struct StepRow {
    pub loss: f64,
    /// The task's accuracy (pose: correspondence accuracy; seg: IoU); NaN when undefined
    /// (then the running average keeps its value).
    pub metric: f64,
    /// Further columns written after the averages (4 decimals).
    pub extra: Vec<f64>,
}

/// What one validation measured.
#[derive(Clone, Debug)]
pub struct Validation {
    /// The whole `val.csv` row (without newline).
    pub row: String,
    /// Higher is better: the best score's weights are kept.
    pub score: f64,
    /// A line for people.
    pub line: String,
    /// What `best.json` records under `validation`.
    pub report: serde_json::Value,
}

/// One network's training run, as [`run`] drives it.
pub trait Task {
    /// What one step consumes.
    type Batch;
    /// `train.csv` header.
    const TRAIN_HEADER: &'static str;
    /// `val.csv` header (it may depend on the run, e.g. on the kind of validation scenes).
    fn val_header(&self) -> &'static str;
    /// Name of [`StepRow::metric`] in log lines.
    const METRIC: &'static str;

    /// Completed iterations.
    fn iteration(&self) -> u64;
    /// Planned iterations.
    fn total(&self) -> u64;
    /// Samples per batch.
    fn batch_size(&self) -> usize;
    /// Validate every this many iterations (and at the last).
    fn validate_every(&self) -> u64;
    /// One step (increments the iteration).
    fn step(&mut self, batch: Self::Batch) -> anyhow::Result<StepRow>;
    /// Measures the current weights on the fixed validation set.
    fn validate(&mut self, iteration: u64, elapsed_s: f64) -> anyhow::Result<Validation>;
    /// Saves a resumable checkpoint at `path` (and whatever else the run keeps beside it).
    fn save(&mut self, path: &Path) -> anyhow::Result<()>;
    /// Saves the weights only.
    fn save_weights(&self, path: &Path) -> anyhow::Result<()>;
    /// The throughput for people, from samples per second.
    fn rate(samples_per_s: f64) -> String;
}

/// How a run is driven from outside.
#[derive(Clone, Copy, Debug)]
pub struct RunControl<'a> {
    /// Set (by a signal handler, or a test) to save a checkpoint and stop after the current
    /// iteration.
    pub stop: &'a AtomicBool,
    /// Save a checkpoint and the final weights and stop after the first iteration that ends
    /// past this instant.
    pub deadline: Option<Instant>,
    /// Save `latest.safetensors` every this many seconds.
    pub checkpoint_secs: u64,
}

impl Default for RunControl<'static> {
    fn default() -> Self {
        RunControl {
            stop: stop_flag(),
            deadline: None,
            checkpoint_secs: 300,
        }
    }
}

impl RunControl<'_> {
    /// A deadline `minutes` from now (none for `None`).
    pub fn deadline_in(minutes: Option<f64>) -> Option<Instant> {
        minutes
            .filter(|m| m.is_finite() && *m >= 0.0)
            .map(|m| Instant::now() + Duration::from_secs_f64(m * 60.0))
    }
}

/// How a run ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Ending {
    /// The planned iterations are done (`final.safetensors` written).
    Finished,
    /// The checkpoint was already at or past the planned iterations: nothing was done.
    AlreadyDone,
    /// Stopped by the stop flag; `latest.safetensors` saved.
    Interrupted,
    /// Stopped at the deadline; `latest.safetensors` and `final.safetensors` saved.
    TimeUp,
}

/// What a run did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Outcome {
    pub ending: Ending,
    /// The iteration reached.
    pub iteration: u64,
    /// Iterations run by this call.
    pub iterations_run: u64,
    pub seconds: f64,
    /// The best validation score so far (−∞ when none).
    pub best_score: f64,
}

/// The files of a run folder.
#[derive(Clone, Debug)]
pub struct RunFiles {
    pub out: PathBuf,
}

impl RunFiles {
    /// Resumable checkpoint.
    pub fn latest(&self) -> PathBuf {
        self.out.join("latest.safetensors")
    }
    /// Weights of the best validation.
    pub fn best(&self) -> PathBuf {
        self.out.join("best.safetensors")
    }
    /// Weights at the end of the run.
    pub fn final_weights(&self) -> PathBuf {
        self.out.join("final.safetensors")
    }
    pub fn best_json(&self) -> PathBuf {
        self.out.join("best.json")
    }
    pub fn train_csv(&self) -> PathBuf {
        self.out.join("train.csv")
    }
    pub fn val_csv(&self) -> PathBuf {
        self.out.join("val.csv")
    }
}

/// Runs `task` from its iteration to its total over `batches(start, count)` (the batch stream
/// from iteration `start`, `count` batches), writing into `out` (see the crate doc). With
/// `resume`, the CSVs keep their rows up to the starting iteration and `best.json`'s score
/// must be beaten.
pub fn run<T: Task, I>(
    task: &mut T,
    out: &Path,
    resume: bool,
    control: RunControl<'_>,
    batches: impl FnOnce(u64, u64) -> I,
) -> anyhow::Result<Outcome>
where
    I: Iterator<Item = anyhow::Result<T::Batch>>,
{
    let files = RunFiles {
        out: out.to_path_buf(),
    };
    let start = task.iteration();
    let total = task.total();
    let b = task.batch_size();
    if start >= total {
        tracing::info!("already at iteration {start} of {total}");
        return Ok(Outcome {
            ending: Ending::AlreadyDone,
            iteration: start,
            iterations_run: 0,
            seconds: 0.0,
            best_score: previous_best_score(&files.best_json(), resume),
        });
    }
    let keep = resume.then_some(start);
    let mut csv = open_csv(&files.train_csv(), T::TRAIN_HEADER, keep)?;
    let mut val_csv = open_csv(&files.val_csv(), task.val_header(), keep)?;
    let mut best_score = previous_best_score(&files.best_json(), resume);
    let bar = progress_bar(total, start)?;
    let clock = Instant::now();
    let mut last_ckpt = Instant::now();
    let (mut loss_avg, mut metric_avg) = (f64::NAN, f64::NAN);
    let mut done = start;
    for batch in batches(start, total - start) {
        let row = task.step(batch?)?;
        done = task.iteration();
        let loss = row.loss;
        if !loss.is_finite() {
            task.save(&out.join("nonfinite.safetensors"))?;
            bail!("non-finite loss at iteration {done}");
        }
        loss_avg = ema(loss_avg, loss);
        if row.metric.is_finite() {
            metric_avg = ema(metric_avg, row.metric);
        }
        let elapsed = clock.elapsed().as_secs_f64();
        let sps = ((done - start) * b as u64) as f64 / elapsed;
        let mut line = format!(
            "{done},{loss:.5},{:.4},{loss_avg:.5},{metric_avg:.4}",
            row.metric
        );
        for x in &row.extra {
            line.push_str(&format!(",{x:.4}"));
        }
        writeln!(csv, "{line},{sps:.3},{elapsed:.1}")?;
        let rate = T::rate(sps);
        let metric = T::METRIC;
        bar.set_position(done);
        bar.set_message(format!(
            "loss {loss_avg:.3} {metric} {metric_avg:.3} {rate}"
        ));
        let last = done >= total;
        if !interactive() && (done % 10 == 0 || last) {
            tracing::info!(
                "iteration {done}/{total}: loss {loss_avg:.3} {metric} {metric_avg:.3} {rate}, {elapsed:.0} s"
            );
        }
        if done % task.validate_every().max(1) == 0 || last {
            let v = task.validate(done, elapsed)?;
            writeln!(val_csv, "{}", v.row)?;
            report(&bar, v.line);
            if v.score > best_score {
                best_score = v.score;
                task.save_weights(&files.best())?;
                write_best(&files.best_json(), done, v.score, &v.report)?;
            }
        }
        let stop = control.stop.load(Ordering::SeqCst);
        let time_up = control.deadline.is_some_and(|d| Instant::now() >= d);
        if last || stop || time_up || last_ckpt.elapsed().as_secs() >= control.checkpoint_secs {
            csv.flush()?;
            val_csv.flush()?;
            task.save(&files.latest())?;
            last_ckpt = Instant::now();
        }
        if stop || (time_up && !last) {
            let outcome = Outcome {
                ending: if stop {
                    Ending::Interrupted
                } else {
                    Ending::TimeUp
                },
                iteration: done,
                iterations_run: done - start,
                seconds: clock.elapsed().as_secs_f64(),
                best_score,
            };
            if stop {
                bar.abandon_with_message(format!(
                    "interrupted; checkpoint saved at iteration {done}"
                ));
                tracing::info!(
                    "interrupted: saved {} (iteration {done})",
                    files.latest().display()
                );
            } else {
                bar.abandon_with_message(format!("time is up at iteration {done}"));
                task.save_weights(&files.final_weights())?;
                tracing::info!(
                    "time is up: saved {} and {} (iteration {done})",
                    files.latest().display(),
                    files.final_weights().display()
                );
            }
            return Ok(outcome);
        }
    }
    bar.finish();
    task.save_weights(&files.final_weights())?;
    tracing::info!(
        "done: {} iterations in {:.0} s; best weights {}",
        done - start,
        clock.elapsed().as_secs_f64(),
        files.best().display()
    );
    Ok(Outcome {
        ending: if done >= total {
            Ending::Finished
        } else {
            // The batch stream ended early (it never does with the crate's generators).
            Ending::Interrupted
        },
        iteration: done,
        iterations_run: done - start,
        seconds: clock.elapsed().as_secs_f64(),
        best_score,
    })
}

/// A progress bar over `total` iterations starting at `start` (hidden when stderr is not a
/// terminal: log lines report progress then).
pub fn progress_bar(total: u64, start: u64) -> anyhow::Result<ProgressBar> {
    let bar = if interactive() {
        ProgressBar::new(total)
    } else {
        ProgressBar::hidden()
    };
    bar.set_length(total);
    bar.set_position(start);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} {msg} ETA {eta_precise}",
        )?
        .progress_chars("=> "),
    );
    Ok(bar)
}

/// Exponential moving average (weight 0.05 on the new value); the first value starts it.
pub fn ema(avg: f64, x: f64) -> f64 {
    if avg.is_nan() {
        x
    } else {
        0.95 * avg + 0.05 * x
    }
}

/// A uniform draw in [0, 1) from (`seed`, `index`): the per-sample choices of a mixed run
/// (room scenes among clutter, paper samples among deployment ones), each with its own salt
/// in `seed`.
pub(crate) fn uniform_draw(seed: u64, index: u64) -> f64 {
    (ic_data::mix_seed(seed, index) >> 11) as f64 / (1u64 << 53) as f64
}

/// Whether stderr is a terminal (the bar shows progress) or a log (lines do).
pub fn interactive() -> bool {
    std::io::IsTerminal::is_terminal(&std::io::stderr())
}

/// A line above the bar on a terminal, a log line otherwise.
fn report(bar: &ProgressBar, line: String) {
    if interactive() {
        bar.println(line);
    } else {
        tracing::info!("{line}");
    }
}

/// The validation score of `best.json` when resuming (so a resumed run only replaces a better
/// checkpoint), −∞ otherwise.
pub fn previous_best_score(best_json: &Path, resume: bool) -> f64 {
    std::fs::read_to_string(best_json)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["score"].as_f64())
        .filter(|_| resume)
        .unwrap_or(f64::NEG_INFINITY)
}

/// Records the validation that selected the best weights:
/// `{"iteration", "score", "validation"}` (atomically).
pub fn write_best(
    best_json: &Path,
    iteration: u64,
    score: f64,
    validation: &impl Serialize,
) -> anyhow::Result<()> {
    let j = serde_json::json!({"iteration": iteration, "score": score, "validation": validation});
    write_atomic(best_json, serde_json::to_string_pretty(&j)?.as_bytes())
}

/// Writes `bytes` to `path` through a temporary file and a rename, creating its folder when
/// missing (a report asked for under a new folder is written, not refused).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    ic_geometry::io::create_parent_dir(path)
        .with_context(|| format!("creating the folder of {}", path.display()))?;
    ic_geometry::io::write_atomic_with(path, |w| w.write_all(bytes), |e| e)
        .with_context(|| format!("writing {}", path.display()))
}

/// Keeps the CSV rows up to `iteration` (after a resume, the rows written past the last
/// checkpoint are dropped so the log matches an uninterrupted run; rewritten atomically) and
/// opens it for append.
pub fn open_csv(
    path: &Path,
    header: &str,
    keep_up_to: Option<u64>,
) -> anyhow::Result<std::fs::File> {
    let mut keep = String::new();
    if let (Some(limit), Ok(text)) = (keep_up_to, std::fs::read_to_string(path)) {
        for (i, line) in text.lines().enumerate() {
            let it: Option<u64> = line.split(',').next().and_then(|s| s.parse().ok());
            if i == 0 || it.is_some_and(|it| it <= limit) {
                keep.push_str(line);
                keep.push('\n');
            }
        }
    }
    if keep.is_empty() {
        keep = format!("{header}\n");
    }
    write_atomic(path, keep.as_bytes())?;
    std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))
}

#[cfg(test)]
mod tests {
    /// `cargo xtask eval-seg --out new/folder/report.json` wrote nothing and failed: the report
    /// writer now makes the folder.
    #[test]
    fn write_atomic_creates_a_missing_report_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("new/folder/report.json");
        super::write_atomic(&out, b"{}").unwrap();
        assert_eq!(std::fs::read(&out).unwrap(), b"{}");
    }

    #[test]
    fn a_camera_flag_centres_its_principal_point_and_refuses_what_is_not_a_camera() {
        let k = super::camera_arg(&[1280.0, 720.0, 640.0, 645.0]).unwrap();
        assert_eq!((k.width, k.height, k.fx, k.fy), (1280, 720, 640.0, 645.0));
        assert_eq!((k.cx, k.cy), (639.5, 359.5));
        for (bad, says) in [
            (vec![1280.0, 720.0, 640.0], "4 numbers"),
            (vec![1280.5, 720.0, 640.0, 640.0], "width"),
            (vec![1280.0, 0.0, 640.0, 640.0], "height"),
            (vec![1e9, 720.0, 640.0, 640.0], "width"),
            (vec![1280.0, 720.0, -640.0, 640.0], "focal"),
            (vec![1280.0, 720.0, 640.0, f64::NAN], "focal"),
        ] {
            let err = format!("{:#}", super::camera_arg(&bad).unwrap_err());
            assert!(err.contains(says), "{bad:?}: {err}");
        }
    }
}
