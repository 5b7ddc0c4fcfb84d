//! The segmentation network (`ic_seg`) trained on room scenes rendered on the fly by
//! `ic_data`, and measured on test-split scenes beside the geometry-only alternative
//! (`cargo xtask train-seg` / `eval-seg`, `incontext train seg`).
//!
//! Objects as for the pose network: ids 000–749 train, 750–799 the fixed validation set
//! (seed [`VALIDATION_SEED`]), 800–999 (the test split) only for `eval-seg`; or every mesh of
//! a user's folder for both ([`train_objects`]). A run folder holds `latest.safetensors`,
//! `best.safetensors` + `best.json` (validation score = mean IoU + found rate),
//! `final.safetensors`, `train.csv` (`iteration,loss,iou,loss_avg,iou_avg,scenes_per_s,elapsed_s`)
//! and `val.csv`.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use ic_data::clutter::SUPPORT_ID_BASE;
use ic_data::{
    ClutterConfig, ClutterGenerator, ClutterScene, Corpus, CorpusOptions, FolderSplit, Prefetcher,
    RoomSampleConfig, RoomSampleGenerator, RoomView, Split,
};
use ic_geometry::Mask;
use ic_render::CpuRenderer;
use ic_seg::checkpoint::{CONFIG_KEY, STATE_KEY};
use ic_seg::post::iou;
use ic_seg::unet::UNet;
use ic_seg::{GeometricConfig, SegConfig, SegError, SegExample, SegInput, Segmenter, seg_loss};
use indicatif::ProgressBar;

use crate::{Network, Outcome, RunControl, StepRow, Task, Trainer, Validation};

/// Seed of the validation scene stream (fixed whatever the run's seed).
pub const VALIDATION_SEED: u64 = 0x7365_6776;

/// The segmentation network's trainer.
pub type SegTrainer = Trainer<UNet>;

impl Network for UNet {
    type Config = SegConfig;
    type Error = SegError;
    const CONFIG_KEY: &'static str = CONFIG_KEY;
    const STATE_KEY: &'static str = STATE_KEY;

    fn build(vb: VarBuilder, config: &SegConfig) -> Result<Self, SegError> {
        Ok(UNet::new(vb, &config.net)?)
    }
    fn validate(config: &SegConfig) -> Result<(), SegError> {
        config.validate()
    }
    fn read_config(path: &Path) -> Result<SegConfig, SegError> {
        ic_seg::checkpoint::read_config(path)
    }
    fn same_network(a: &SegConfig, b: &SegConfig) -> bool {
        a.net == b.net
    }
    fn learning_rate(config: &SegConfig) -> f64 {
        config.train.learning_rate
    }
    fn set_learning_rate(config: &mut SegConfig, learning_rate: f64) {
        config.train.learning_rate = learning_rate;
    }
    fn iterations(config: &SegConfig) -> u64 {
        config.train.iterations
    }
    fn set_iterations(config: &mut SegConfig, iterations: u64) {
        config.train.iterations = iterations;
    }
}

/// What one segmentation step measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegStepStats {
    pub loss: f32,
    /// Mean over the batch of the IoU of `logit > 0` with the target, at the network's
    /// resolution.
    pub iou: f64,
}

impl Trainer<UNet> {
    /// Changes the probability that a clutter training scene's sensor casts the projector's
    /// shadows from the next scene on (`SegTrainConfig::shadow_probability`); the
    /// configuration saved with later checkpoints records it.
    pub fn set_shadow_probability(&mut self, p: f64) -> Result<()> {
        let mut cfg = self.config.clone();
        cfg.train.shadow_probability = p;
        cfg.validate()?;
        self.config = cfg;
        Ok(())
    }

    /// Starts this network from a checkpoint with as many levels and at most as many channels
    /// per level ([`crate::widen`]: the copies of a channel share its weights, so the
    /// widened network computes what the checkpoint did), fewer outputs (one or two, where
    /// this one has two or four) or fewer inputs (depth alone, where this one also sees surface normals), or
    /// no centre-offset branch (where this one has one, `UNetConfig::offset_level`), or any of
    /// these together (the input size may differ: the network is fully convolutional). Every
    /// weight is copied; a one-output head's object output also starts the core map; new
    /// centre-offset maps start at zero, and so does a new offset branch's 1×1 head (its
    /// convolution keeps its seeded initialisation); the first convolution's weights of
    /// the new input channels start at zero, so the widened network computes what the
    /// checkpoint did until training teaches it to use them. Errors name `path` and the
    /// tensor that does not fit.
    pub fn load_widening(&mut self, path: &Path) -> Result<(), SegError> {
        let config = ic_seg::checkpoint::read_config(path)?;
        let bad = |message: String| SegError::Checkpoint {
            path: path.to_path_buf(),
            message,
        };
        let (from, to) = (&config.net, &self.config.net);
        // A network given the offset branch keeps the branch's fresh weights (its 1×1 head at
        // zero, so the offsets are the checkpoint's); a branch at another level is refused.
        let new_branch = from.offset_level == 0 && to.offset_level > 0;
        let fresh = |name: &str| new_branch && name.starts_with("offsets.");
        if from.offset_level != to.offset_level && !new_branch {
            return Err(bad(format!(
                "cannot move the offset branch from level {} to level {}",
                from.offset_level, to.offset_level
            )));
        }
        // 1 → 2 or 4 outputs: the object map also starts the core map; 2 → 4: the offset maps
        // start at zero (every pixel its own centre).
        let widen_head = [(1, 2), (1, 4), (2, 4)].contains(&(from.outputs, to.outputs));
        let (cin_from, cin_to) = (from.input.channels(), to.input.channels());
        let wider = from.channels.len() == to.channels.len()
            && from.channels.iter().zip(&to.channels).all(|(f, t)| f <= t);
        if !wider
            || !(widen_head || from.outputs == to.outputs)
            || !(from.input == to.input
                || (from.input, to.input) == (SegInput::Depth, SegInput::DepthNormals))
        {
            return Err(bad(format!(
                "cannot widen a network of channels {:?}, {} output(s) and input {:?} into one of channels {:?}, {} output(s) and input {:?}",
                from.channels, from.outputs, from.input, to.channels, to.outputs, to.input
            )));
        }
        let mut tensors =
            ic_nn::checkpoint::load_tensors(path, self.device()).map_err(|e| bad(e.to_string()))?;
        let data = self
            .varmap()
            .data()
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if from.channels != to.channels {
            let names: Vec<String> = data.keys().filter(|n| !fresh(n)).cloned().collect();
            tensors = crate::widen::widen_unet(
                &tensors,
                &names,
                &from.channels,
                &to.channels,
                crate::widen::NOISE,
                self.seed(),
            )
            .map_err(bad)?;
            tracing::info!(
                "channels {:?} widened into {:?} (Net2WiderNet, noise from seed {})",
                from.channels,
                to.channels,
                self.seed()
            );
        }
        for (name, var) in data.iter() {
            if fresh(name) {
                continue;
            }
            let t = tensors
                .get(name)
                .ok_or_else(|| bad(format!("missing tensor {name}")))?;
            let t = if widen_head && name.starts_with("head.") {
                let maps = if from.outputs == 1 {
                    Tensor::cat(&[t, t], 0)?
                } else {
                    t.clone()
                };
                if to.outputs == 4 {
                    let mut shape = t.dims().to_vec();
                    shape[0] = 2;
                    Tensor::cat(&[&maps, &Tensor::zeros(shape, t.dtype(), t.device())?], 0)?
                } else {
                    maps
                }
            } else if cin_to > cin_from
                && t.rank() == 4
                && t.dim(1)? == cin_from
                && var.dims4().is_ok_and(|(_, c, _, _)| c == cin_to)
                && name.starts_with("down0.")
            {
                let (o, _, kh, kw) = t.dims4()?;
                let zeros = Tensor::zeros((o, cin_to - cin_from, kh, kw), t.dtype(), t.device())?;
                Tensor::cat(&[t, &zeros], 1)?
            } else {
                t.clone()
            };
            if t.shape() != var.shape() {
                return Err(bad(format!(
                    "{name}: shape {:?}, expected {:?}",
                    t.shape(),
                    var.shape()
                )));
            }
            var.set(&t)?;
        }
        Ok(())
    }

    /// A segmenter sharing the current weights (inference mode), e.g. for validation.
    pub fn segmenter(&self) -> Segmenter {
        Segmenter::from_parts(self.net.clone(), self.config.clone())
    }

    /// The batch's inputs, targets and per-pixel weights (`None` when the examples have none).
    fn tensors(
        &self,
        examples: &[SegExample],
    ) -> Result<(Tensor, Tensor, Option<Tensor>), SegError> {
        let (w, h) = (
            self.config.net.input_width as usize,
            self.config.net.input_height as usize,
        );
        let c = self.config.net.outputs;
        let cin = self.config.net.input.channels();
        let b = examples.len();
        let mut input = Vec::with_capacity(b * cin * w * h);
        let mut target = Vec::with_capacity(b * c * w * h);
        let weighted = examples.first().is_some_and(|e| !e.weight.is_empty());
        let mut weight = Vec::with_capacity(if weighted { b * w * h } else { 0 });
        for e in examples {
            if e.input.len() != cin * w * h
                || e.target.len() != c * w * h
                || e.weight.len() != if weighted { w * h } else { 0 }
            {
                return Err(SegError::Input(format!(
                    "example is not {cin}×{h}×{w} with {c}×{h}×{w} targets (and {h}×{w} weights \
                     in every example of the batch or in none)"
                )));
            }
            input.extend_from_slice(&e.input);
            target.extend_from_slice(&e.target);
            weight.extend_from_slice(&e.weight);
        }
        Ok((
            Tensor::from_vec(input, (b, cin, h, w), &self.device)?,
            Tensor::from_vec(target, (b, c, h, w), &self.device)?,
            weighted
                .then(|| Tensor::from_vec(weight, (b, 1, h, w), &self.device))
                .transpose()?,
        ))
    }

    /// The loss of `examples` without a step (inference mode).
    pub fn loss(&self, examples: &[SegExample]) -> Result<f32, SegError> {
        let (x, y, wt) = self.tensors(examples)?;
        let logits = self.net.forward_t(&x, false)?;
        Ok(seg_loss(
            &logits,
            &y,
            wt.as_ref(),
            self.config.train.dice_weight,
            self.config.train.offset_weight,
        )?
        .to_scalar::<f32>()?)
    }

    /// One step: forward (training mode), loss, backward, Adam.
    pub fn step(&mut self, examples: &[SegExample]) -> Result<SegStepStats, SegError> {
        if examples.is_empty() {
            return Err(SegError::Input("empty batch".into()));
        }
        let (x, y, wt) = self.tensors(examples)?;
        let logits = self.net.forward_t(&x, true)?;
        let loss = seg_loss(
            &logits,
            &y,
            wt.as_ref(),
            self.config.train.dice_weight,
            self.config.train.offset_weight,
        )?;
        let grads = loss.backward()?;
        self.apply(&grads)?;
        // IoU of the object map (the first output).
        let pred = logits
            .detach()
            .narrow(1, 0, 1)?
            .gt(0.0)?
            .to_dtype(DType::F32)?
            .flatten_from(1)?;
        let yt = y.narrow(1, 0, 1)?.flatten_from(1)?;
        let inter = (&pred * &yt)?.sum(1)?.to_vec1::<f32>()?;
        let union = ((&pred + &yt)?.gt(0.0)?.to_dtype(DType::F32)?)
            .sum(1)?
            .to_vec1::<f32>()?;
        let iou = inter
            .iter()
            .zip(&union)
            .map(|(i, u)| if *u > 0.0 { (i / u) as f64 } else { 1.0 })
            .sum::<f64>()
            / examples.len() as f64;
        Ok(SegStepStats {
            loss: loss.to_scalar::<f32>()?,
            iou,
        })
    }
}

#[derive(clap::Args)]
pub struct TrainArgs {
    /// `cpu`, `clutter`, `clutter-wide`, `clutter-offsets`, `clutter-offsets-coarse` or
    /// `clutter-offsets-fine` (with `--scenes clutter`), or `tiny` / `tiny-clutter` / `tiny-clutter-wide` /
    /// `tiny-clutter-offsets` / `tiny-clutter-offsets-coarse` (smoke tests).
    #[arg(long, default_value = "cpu")]
    pub preset: String,
    /// `room` (the paper's: one object in the cube room; `--objects` is a folder of meshes
    /// with numeric stems, 000–749 train, 750–799 validation) or `clutter` (tables, bins and
    /// shelves with 3–15 objects, `ic_data::clutter`; `--objects` is a folder with
    /// `split.json` or a weighted mixture as for train-pose, validation on its `val` objects).
    #[arg(long, default_value = "room")]
    pub scenes: String,
    /// With `--scenes clutter`: this fraction of the training scenes (drawn per scene, seeded)
    /// are room scenes of one object of the same corpus instead, so that the network keeps
    /// finding a lone object in a room. Validation stays on clutter scenes.
    #[arg(long, default_value_t = 0.0)]
    pub room_fraction: f64,
    /// See `--scenes`.
    #[arg(long)]
    pub objects: PathBuf,
    /// Start from these weights (fresh optimiser, iteration 0): a checkpoint of the same
    /// network, a one-output one of the same channels for a two-output preset (its head
    /// is widened: e.g. `--preset clutter --init models/seg-cpu.safetensors`), or one of
    /// narrower channels for a wider preset (function-preserving, `ic_train::widen`: e.g.
    /// `--preset clutter-wide --init models/runs/seg-clutter/best.safetensors`). Ignored when
    /// `--resume` finds a checkpoint.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// The network's input: `depth` (depth and validity, 2 channels; the presets') or
    /// `depth-normals` (also each pixel's surface normal, 5 channels). With `--init` from a
    /// depth-only checkpoint, the new channels' weights start at zero. Default: the preset's,
    /// or the `--init` checkpoint's.
    #[arg(long)]
    pub input: Option<String>,
    /// Two- and four-output networks: the instance cores' radius in network pixels (an
    /// object pixel is core when every pixel within it shows the same instance). Default:
    /// the preset's, or the `--init` checkpoint's; a resumed run keeps its checkpoint's.
    #[arg(long)]
    pub core_radius: Option<usize>,
    /// Clutter scenes: weigh each instance's object pixels by √(AREA / its pixels), between 1
    /// and 4, in the loss (`SegTrainConfig::balance_area`, network pixels; 0: off). Default:
    /// the preset's or the `--init` checkpoint's; a resumed run keeps its checkpoint's.
    #[arg(long)]
    pub balance_area: Option<f64>,
    /// Clutter scenes: weigh object pixels near another object by 1 + W·exp(−d²/8), d in
    /// network pixels (`SegTrainConfig::border_weight`; 0: off). Default: the preset's or the
    /// `--init` checkpoint's; a resumed run keeps its checkpoint's.
    #[arg(long)]
    pub border_weight: Option<f64>,
    /// Clutter scenes: the probability that a training scene's sensor casts the projector's
    /// shadows, and (drawn apart) that its depth is registered to a colour camera, with the
    /// registration's holes (`SegTrainConfig::shadow_probability`; 0: off). Default: the preset's or the
    /// `--init` checkpoint's; a resumed run may change it (the scenes after the resume).
    #[arg(long)]
    pub shadow_probability: Option<f64>,
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
    /// Compute threads (RAYON_NUM_THREADS); the scene renderers add `--data-workers` threads.
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long, default_value_t = 1)]
    pub data_workers: usize,
    #[arg(long, default_value_t = 300)]
    pub checkpoint_secs: u64,
    #[arg(long, default_value_t = 250)]
    pub validate_every: u64,
    #[arg(long, default_value_t = 48)]
    pub validation_count: u64,
    #[arg(long)]
    pub batch_size: Option<usize>,
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
}

#[derive(clap::Args)]
pub struct EvalArgs {
    #[arg(long)]
    pub model: PathBuf,
    /// `room` (one object in the cube room; the network's best instance against its mask) or
    /// `clutter` (every object's instance, `ic_eval::instances`: target found rate, recall,
    /// matched IoU, over- and under-segmentation), at 640×480.
    #[arg(long, default_value = "room")]
    pub scenes: String,
    /// Room scenes: a folder of meshes with numeric stems; clutter scenes: a folder with
    /// `split.json` or a weighted mixture (as for train-pose).
    #[arg(long)]
    pub objects: PathBuf,
    /// `test` (800–999) or `val` (750–799); clutter scenes: the split of the objects' split file.
    #[arg(long, default_value = "test")]
    pub split: String,
    #[arg(long, default_value_t = 300)]
    pub count: u64,
    #[arg(long, default_value_t = 2021)]
    pub seed: u64,
    /// Also run the geometry-only alternative (RANSAC planes + Euclidean clustering).
    #[arg(long)]
    pub geometric: bool,
    /// Override the depth-edge refinement band (pixels at 640 wide; 0 = off). Room scenes
    /// only: clutter scenes score `Segmenter::instances`, which does not refine.
    #[arg(long)]
    pub depth_refine_px: Option<usize>,
    /// Override the pixel probability threshold.
    #[arg(long)]
    pub pixel_threshold: Option<f32>,
    /// Override the instances standing out of the scene's support planes (`ic_seg::support`):
    /// the least height above a plane, relative to the depth (e.g. 0.01); 0 turns them off.
    #[arg(long)]
    pub support_height: Option<f32>,
    /// With `--support-height`: the planes' narrowest inlier band, relative to the depth.
    #[arg(long)]
    pub support_plane_threshold: Option<f32>,
    /// With `--support-height`: the network's instances first grow into the pixels off the
    /// planes that they reach.
    #[arg(long)]
    pub support_grow: bool,
    /// Where to write the JSON (default `<model>.eval-<split>.json`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Clutter scenes: write a PNG of each scene whose target was missed (at most 40) to this
    /// folder, `miss-<scene>-<kind>.png`: the depth with the target's true pixels in red
    /// beside the network's instances in colours with the target's outline in white.
    #[arg(long)]
    pub misses: Option<PathBuf>,
    /// Clutter scenes: score the post-processing on the training targets (the maps a perfect
    /// network would output at its resolution: object, cores, centre offsets) instead of the
    /// network's outputs — what the representation allows. The network only gives its
    /// configuration.
    #[arg(long, conflicts_with = "oracle_maps")]
    pub oracle: bool,
    /// Clutter scenes: these maps from the training targets, the others from the network
    /// (`object`, `core`, `offsets`; comma-separated): which of the network's outputs costs
    /// the most targets. Every map is `--oracle`.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub oracle_maps: Vec<OracleMap>,
    /// With `--oracle` or `--oracle-maps`: the targets' instance-core radius (network pixels)
    /// instead of the network's training setting, to compare representations.
    #[arg(long)]
    pub core_radius: Option<usize>,
    /// Clutter scenes: render them at this width × height (pixels; the field of view and the
    /// scenes' geometry kept, the sensor model applied at that size) instead of 640×480,
    /// e.g. at the training resolution of the network, to tell what the input's size costs.
    #[arg(long, num_args = 2, value_names = ["WIDTH", "HEIGHT"])]
    pub render_size: Option<Vec<u32>>,
    /// Clutter scenes: see them through this camera instead (pixels: e.g. `1280 720 640 640`
    /// for a RealSense-like 16:9 depth camera; the principal point at the image's centre),
    /// the scenes' geometry kept: what another camera than the training one costs. The
    /// network runs at the input sized for it (`ic_seg::Segmenter::input_size_for`); the
    /// oracles (`--oracle`, `--oracle-maps`) at the network's own size.
    #[arg(long, num_args = 4, value_names = ["WIDTH", "HEIGHT", "FX", "FY"], conflicts_with = "render_size")]
    pub camera: Option<Vec<f64>>,
    /// Clutter scenes: the probability that a scene's sensor casts the projector's shadows,
    /// and (drawn apart) that its depth is registered to a colour camera
    /// (`ic_data::SensorRanges::set_shadows`; default 0, as the benchmark's sets).
    #[arg(long, default_value_t = 0.0)]
    pub shadow_probability: f64,
    #[arg(long)]
    pub threads: Option<usize>,
}

impl EvalArgs {
    /// Whether any map comes from the training targets (`--oracle` or `--oracle-maps`).
    fn any_oracle(&self) -> bool {
        self.oracle || !self.oracle_maps.is_empty()
    }
}

/// One output map of the segmentation network, for `eval-seg --oracle-maps`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OracleMap {
    /// The object probability (map 0).
    Object,
    /// The instance cores (map 1; two- and four-output networks).
    Core,
    /// The centre offsets x and y (maps 2 and 3; four-output networks).
    Offsets,
}

impl OracleMap {
    /// The maps (first, count) it covers in a network's outputs.
    fn maps(self) -> (usize, usize) {
        match self {
            OracleMap::Object => (0, 1),
            OracleMap::Core => (1, 1),
            OracleMap::Offsets => (2, 2),
        }
    }
}

/// `network`'s outputs (`[outputs, H, W]` flattened) with `maps` taken from `truth` (same
/// layout): the mixed outputs of `eval-seg --oracle-maps`. Errors when a map is not among the
/// network's outputs or the two differ in size.
fn mix_oracle(
    network: &mut [f32],
    truth: &[f32],
    maps: &[OracleMap],
    outputs: usize,
) -> Result<()> {
    if network.len() != truth.len() || outputs == 0 || network.len() % outputs != 0 {
        bail!(
            "network outputs ({}) and targets ({}) differ in size",
            network.len(),
            truth.len()
        );
    }
    let plane = network.len() / outputs;
    for &m in maps {
        let (first, count) = m.maps();
        if first + count > outputs {
            bail!("--oracle-maps {m:?}: the network has {outputs} output map(s), not this one");
        }
        let range = first * plane..(first + count) * plane;
        network[range.clone()].copy_from_slice(&truth[range]);
    }
    Ok(())
}

/// The room-scene objects of a flat folder of numeric stems: with `holdout`, 000–749 train and
/// 750–799 as the "test" split (the validation objects); else 000–799 / 800–999.
pub fn corpus(objects: &Path, split: Split, holdout: bool) -> Result<Arc<Corpus>> {
    let fs = if holdout {
        FolderSplit::IdRange {
            train: (0, 749),
            test: (750, 799),
        }
    } else {
        FolderSplit::blobs()
    };
    Ok(Arc::new(Corpus::mesh_folder(
        objects,
        &fs,
        split,
        CorpusOptions::default(),
    )?))
}

/// IoU and found-rate over views, as `eval-seg` and the validation report them.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct MaskMetrics {
    pub count: usize,
    /// Views where an instance was returned and its IoU with the visible mask is ≥ 0.5.
    pub found_rate: f64,
    /// Views where nothing scored above the threshold.
    pub not_found: usize,
    pub iou_median: f64,
    pub iou_mean: f64,
    /// Fraction of views with IoU ≥ 0.9.
    pub iou_at_least_0_9: f64,
    pub seconds_median: f64,
}

/// Per-view IoUs, times and misses of one method, as the views come.
#[derive(Default)]
pub struct MaskTally {
    pub ious: Vec<f64>,
    pub seconds: Vec<f64>,
    pub not_found: usize,
}

impl MaskTally {
    /// Records one view: `found` is the method's mask (or its error) for `truth`, computed
    /// since `started`. Object-not-found counts IoU 0; any other error stops the evaluation.
    pub fn add(
        &mut self,
        truth: &Mask,
        started: Instant,
        found: Result<Mask, SegError>,
    ) -> Result<()> {
        match found {
            Ok(mask) => self.ious.push(iou(&mask, truth)),
            Err(SegError::ObjectNotFound { .. }) => {
                self.not_found += 1;
                self.ious.push(0.0);
            }
            Err(e) => return Err(e.into()),
        }
        self.seconds.push(started.elapsed().as_secs_f64());
        Ok(())
    }

    pub fn metrics(&self) -> MaskMetrics {
        let ious = &self.ious;
        let n = ious.len();
        MaskMetrics {
            count: n,
            found_rate: ious.iter().filter(|&&i| i >= 0.5).count() as f64 / n.max(1) as f64,
            not_found: self.not_found,
            iou_median: ic_eval::median(ious),
            iou_mean: ious.iter().sum::<f64>() / n.max(1) as f64,
            iou_at_least_0_9: ious.iter().filter(|&&i| i >= 0.9).count() as f64 / n.max(1) as f64,
            seconds_median: ic_eval::median(&self.seconds),
        }
    }
}

/// The network's masks on `views` (a view where nothing is found counts IoU 0).
pub fn evaluate_network(seg: &Segmenter, views: &[RoomView]) -> Result<MaskMetrics> {
    let mut tally = MaskTally::default();
    for v in views {
        let t = Instant::now();
        let found = seg.segment(&v.depth, &v.intrinsics).map(|s| s.mask);
        tally.add(&v.mask_visib, t, found)?;
    }
    Ok(tally.metrics())
}

/// The trainer a run starts with: its own checkpoint (`--resume`), `init` weights (fresh
/// optimiser, iteration 0; the preset's overrides apply), or a fresh network of the preset.
pub fn make_trainer(args: &TrainArgs, latest: &Path, init: Option<&Path>) -> Result<SegTrainer> {
    if args.resume && latest.exists() {
        let mut t = SegTrainer::resume_run(latest, args.iterations)?;
        // What the run's targets and loss are made of stays the checkpoint's.
        let run = &t.config().train;
        for (flag, asked, kept) in [
            (
                "--core-radius",
                args.core_radius.map(|r| r as f64),
                run.core_radius as f64,
            ),
            ("--balance-area", args.balance_area, run.balance_area),
            ("--border-weight", args.border_weight, run.border_weight),
        ] {
            if asked.is_some_and(|v| v != kept) {
                anyhow::bail!(
                    "{}: the run's {flag} is {kept}; {flag} applies when a run starts",
                    latest.display()
                );
            }
        }
        if let Some(p) = args.shadow_probability
            && p != t.config().train.shadow_probability
        {
            tracing::info!(
                "projector shadows in {:.0} % of the scenes from iteration {}",
                100.0 * p,
                t.iteration()
            );
            t.set_shadow_probability(p)?;
        }
        // As for the pose network: a resumed run may continue at another learning rate.
        if let Some(lr) = args.learning_rate {
            tracing::info!("learning rate {} from iteration {}", lr, t.iteration());
            t.set_learning_rate(lr);
        }
        return Ok(t);
    }
    if args.resume {
        tracing::info!("--resume: no {} yet, starting fresh", latest.display());
    }
    // A one-output init for a two-output preset, a depth-only init for `--input
    // depth-normals`, or a narrower init for a preset of wider channels (`clutter-wide` from
    // `clutter`): the preset's configuration (with the asked input), the init's weights
    // widened.
    let input: Option<SegInput> = args.input.as_deref().map(str::parse).transpose()?;
    let init_config = init
        .map(|p| ic_seg::checkpoint::read_config(p).with_context(|| format!("{}", p.display())))
        .transpose()?;
    let preset = SegConfig::preset(&args.preset)?;
    let wider_preset = |c: &SegConfig| {
        c.net.channels != preset.net.channels
            && c.net.channels.len() == preset.net.channels.len()
            && c.net
                .channels
                .iter()
                .zip(&preset.net.channels)
                .all(|(a, b)| a <= b)
    };
    let widen = init_config.as_ref().is_some_and(|c| {
        c.net.outputs < preset.net.outputs
            || (c.net.offset_level == 0 && preset.net.offset_level > 0)
            || input.is_some_and(|i| i != c.net.input)
            || wider_preset(c)
    });
    let mut cfg = match init_config {
        Some(c) if !widen => c,
        _ => preset,
    };
    if let Some(i) = input {
        cfg.net.input = i;
    }
    if let Some(v) = args.iterations {
        cfg.train.iterations = v;
    }
    if let Some(v) = args.batch_size {
        cfg.train.batch_size = v;
    }
    if let Some(v) = args.learning_rate {
        cfg.train.learning_rate = v;
    }
    if let Some(v) = args.core_radius {
        cfg.train.core_radius = v;
    }
    if let Some(v) = args.balance_area {
        cfg.train.balance_area = v;
    }
    if let Some(v) = args.border_weight {
        cfg.train.border_weight = v;
    }
    if let Some(v) = args.shadow_probability {
        cfg.train.shadow_probability = v;
    }
    let mut t = SegTrainer::new(cfg, args.seed)?;
    if let Some(p) = init {
        if widen {
            t.load_widening(p)?;
        } else {
            t.load_weights(p)
                .with_context(|| format!("{}", p.display()))?;
        }
        tracing::info!(
            "initialised from {}; fresh optimiser at iteration 0",
            p.display()
        );
    }
    Ok(t)
}

/// `train-seg`: trains into `args.out` on the blob-style folder `args.objects` until the
/// planned iterations are done, the stop flag is set or the deadline passes.
pub fn train(args: &TrainArgs, control: RunControl<'_>) -> Result<Outcome> {
    let (train_corpus, val_corpus) = if check_scenes(args)? == SceneKind::Clutter {
        let spec = objects_spec(&args.objects)?;
        (
            crate::pose::open_objects(&spec, Split::Train)?,
            crate::pose::open_objects(&spec, Split::Val)?,
        )
    } else {
        (
            corpus(&args.objects, Split::Train, true)?,
            corpus(&args.objects, Split::Test, true)?,
        )
    };
    train_objects(
        args,
        args.init.as_deref(),
        train_corpus,
        val_corpus,
        control,
    )
}

/// Which scenes a run trains on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneKind {
    Room,
    Clutter,
}

/// `--scenes` and `--room-fraction` (a fraction in [0, 1], only for clutter scenes).
fn check_scenes(args: &TrainArgs) -> Result<SceneKind> {
    let kind = scene_kind(&args.scenes)?;
    if !(0.0..=1.0).contains(&args.room_fraction)
        || (args.room_fraction > 0.0 && kind != SceneKind::Clutter)
    {
        bail!(
            "--room-fraction {}: a fraction in [0, 1], only with --scenes clutter",
            args.room_fraction
        );
    }
    Ok(kind)
}

/// The `--scenes` flag.
fn scene_kind(scenes: &str) -> Result<SceneKind> {
    match scenes {
        "room" => Ok(SceneKind::Room),
        "clutter" => Ok(SceneKind::Clutter),
        other => bail!("--scenes {other:?}: expected room or clutter"),
    }
}

/// `--objects` of clutter scenes: a folder with `split.json` or a weighted mixture.
fn objects_spec(objects: &Path) -> Result<crate::objects::ObjectsSpec> {
    let text = objects
        .to_str()
        .with_context(|| format!("--objects {}: not UTF-8", objects.display()))?;
    text.parse()
}

/// Where training examples come from.
enum Source {
    Room(RoomSampleGenerator),
    Clutter(ClutterGenerator),
    /// Clutter scenes, and room scenes for a `room_fraction` of the indices (drawn from
    /// `seed` and the index).
    Mixed {
        clutter: Box<ClutterGenerator>,
        room: Box<RoomSampleGenerator>,
        room_fraction: f64,
        seed: u64,
    },
}

/// Whether training scene `index` of a mixed run is a room scene: a uniform draw from
/// (`seed`, `index`) below `room_fraction`.
pub fn is_room_scene(seed: u64, index: u64, room_fraction: f64) -> bool {
    crate::uniform_draw(seed ^ 0x0072_6f6f_6d6d_6978, index) < room_fraction
}

impl Source {
    fn example(&self, index: u64, cfg: &SegConfig) -> Result<SegExample, ic_data::DataError> {
        let room = |g: &RoomSampleGenerator| -> Result<_, ic_data::DataError> {
            let v = g.view_with(&mut CpuRenderer::new(), index)?;
            Ok(SegExample::new(&v.depth, &v.intrinsics, &v.mask_visib, cfg))
        };
        let clutter = |g: &ClutterGenerator| -> Result<_, ic_data::DataError> {
            let s = g.scene(index)?;
            Ok(SegExample::from_instances(
                &s.depth,
                &s.intrinsics,
                &s.instances,
                |id| id < SUPPORT_ID_BASE,
                cfg,
            ))
        };
        let example = match self {
            Source::Room(g) => room(g)?,
            Source::Clutter(g) => clutter(g)?,
            Source::Mixed {
                clutter: c,
                room: r,
                room_fraction,
                seed,
            } => {
                if is_room_scene(*seed, index, *room_fraction) {
                    room(r)?
                } else {
                    clutter(c)?
                }
            }
        };
        example.map_err(|e| ic_data::DataError::Sample {
            index,
            message: e.to_string(),
        })
    }
}

/// The fixed validation scenes.
pub enum ValidationSet {
    Room(Vec<RoomView>),
    Clutter(Vec<ClutterScene>),
}

/// True instances of a clutter scene worth finding: at least this many visible pixels at
/// 640×480 (scaled with the image area); the target's first instance always counts.
pub const MIN_TRUE_PIXELS_640: f64 = 30.0;

/// The network's instances against the true ones of clutter `scenes`.
pub fn evaluate_instances(
    seg: &Segmenter,
    scenes: &[ClutterScene],
) -> Result<ic_eval::instances::InstanceSummary> {
    let matches = scenes
        .iter()
        .map(|s| scene_instances(seg, s))
        .collect::<Result<Vec<_>>>()?;
    Ok(ic_eval::instances::summarise(&matches))
}

/// The network's instances in one clutter scene against its true instances (the target's
/// first instance first, then every object with at least [`MIN_TRUE_PIXELS_640`] visible
/// pixels, scaled with the image area).
pub fn scene_instances(
    seg: &Segmenter,
    s: &ClutterScene,
) -> Result<ic_eval::instances::InstanceMatch> {
    let found = seg.instances(&s.depth, &s.intrinsics)?;
    match_scene(&found, s)
}

/// `found` (instance masks at the scene's resolution) against the true instances of `s`, as
/// [`scene_instances`] scores them.
fn match_scene(
    found: &[ic_seg::post::Instance],
    s: &ClutterScene,
) -> Result<ic_eval::instances::InstanceMatch> {
    let area = (s.intrinsics.width as f64 * s.intrinsics.height as f64) / (640.0 * 480.0);
    let min = (MIN_TRUE_PIXELS_640 * area).round().max(1.0) as usize;
    let truth: Vec<Mask> = s
        .objects
        .iter()
        .enumerate()
        .filter(|(i, o)| *i == 0 || o.visible_pixels >= min)
        .map(|(_, o)| s.mask(o.instance_id))
        .collect();
    let pred: Vec<&Mask> = found.iter().map(|i| &i.mask).collect();
    let truth: Vec<&Mask> = truth.iter().collect();
    ic_eval::instances::match_instances(&pred, &truth).map_err(|e| anyhow::anyhow!(e))
}

/// The mean distance, in pixels, from the vote of each visible pixel of the scene's objects
/// (those [`match_scene`] scores) to the centroid of its object's visible pixels, and the
/// same from the pixel itself (what votes without offsets would score).
fn centre_vote_error(votes: &ic_seg::centres::CentreVotes, s: &ClutterScene) -> (f64, f64) {
    let area = (s.intrinsics.width as f64 * s.intrinsics.height as f64) / (640.0 * 480.0);
    let min = (MIN_TRUE_PIXELS_640 * area).round().max(1.0) as usize;
    let w = s.intrinsics.width as usize;
    let (mut sum, mut at_pixel, mut n) = (0.0, 0.0, 0usize);
    for (k, o) in s.objects.iter().enumerate() {
        if k > 0 && o.visible_pixels < min {
            continue;
        }
        let mask = s.mask(o.instance_id);
        let pixels: Vec<usize> = (0..mask.data.len()).filter(|&i| mask.data[i]).collect();
        if pixels.is_empty() {
            continue;
        }
        let c = pixels.iter().fold((0.0, 0.0), |(x, y), &i| {
            (x + (i % w) as f64, y + (i / w) as f64)
        });
        let c = (c.0 / pixels.len() as f64, c.1 / pixels.len() as f64);
        for &i in &pixels {
            sum += ((votes.x[i] as f64 - c.0).powi(2) + (votes.y[i] as f64 - c.1).powi(2)).sqrt();
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            at_pixel += ((x - c.0).powi(2) + (y - c.1).powi(2)).sqrt();
            n += 1;
        }
    }
    (sum / n.max(1) as f64, at_pixel / n.max(1) as f64)
}

/// [`train`] on given corpora, optionally starting from the weights of `init`.
pub fn train_objects(
    args: &TrainArgs,
    init: Option<&Path>,
    train_corpus: Arc<Corpus>,
    val_corpus: Arc<Corpus>,
    control: RunControl<'_>,
) -> Result<Outcome> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let latest = args.out.join("latest.safetensors");
    let mut trainer = make_trainer(args, &latest, init)?;
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
    tracing::info!(
        "objects: {} train, {} validation",
        train_corpus.len(),
        val_corpus.len()
    );
    let (w, h) = (cfg.train.render_width, cfg.train.render_height);
    let kind = check_scenes(args)?;
    if (kind == SceneKind::Clutter) != cfg.net.has_core() {
        bail!(
            "--scenes {} needs a {} network (preset {:?} has {} output(s)): use --preset {}",
            args.scenes,
            if kind == SceneKind::Clutter {
                "two- or four-output"
            } else {
                "one-output"
            },
            cfg.preset,
            cfg.net.outputs,
            if kind == SceneKind::Clutter {
                "clutter"
            } else {
                "cpu"
            }
        );
    }
    let (generator, val) = match kind {
        SceneKind::Room => {
            let room = RoomSampleConfig::default().with_resolution(w, h);
            let val_gen = RoomSampleGenerator::new(val_corpus, room.clone(), VALIDATION_SEED)?;
            let mut renderer = CpuRenderer::new();
            let views: Vec<RoomView> = (0..args.validation_count)
                .map(|i| val_gen.view_with(&mut renderer, i))
                .collect::<Result<_, _>>()?;
            (
                Source::Room(RoomSampleGenerator::new(train_corpus, room, seed)?),
                ValidationSet::Room(views),
            )
        }
        SceneKind::Clutter => {
            let clutter = ClutterConfig::default()
                .with_resolution(w, h)
                .with_shadows(cfg.train.shadow_probability);
            tracing::info!("clutter scenes {}", serde_json::to_string(&clutter)?);
            let val_gen = ClutterGenerator::new(val_corpus, clutter.clone(), VALIDATION_SEED)?;
            let scenes: Vec<ClutterScene> = (0..args.validation_count)
                .map(|i| val_gen.scene(i))
                .collect::<Result<_, _>>()?;
            let source = if args.room_fraction > 0.0 {
                tracing::info!(
                    "room scenes of one object: {:.0} % of the training scenes",
                    100.0 * args.room_fraction
                );
                let room = RoomSampleConfig::default().with_resolution(w, h);
                Source::Mixed {
                    room: Box::new(RoomSampleGenerator::new(train_corpus.clone(), room, seed)?),
                    clutter: Box::new(ClutterGenerator::new(train_corpus, clutter, seed)?),
                    room_fraction: args.room_fraction,
                    seed,
                }
            } else {
                Source::Clutter(ClutterGenerator::new(train_corpus, clutter, seed)?)
            };
            (source, ValidationSet::Clutter(scenes))
        }
    };
    let generator = Arc::new(generator);
    let b = cfg.train.batch_size;
    let mut task = SegTask {
        trainer,
        val,
        validate_every: args.validate_every,
    };
    let example_cfg = cfg.clone();
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
                move |i| generator.example(i, &example_cfg),
            )
            .batches(b)
            .map(|r| r.map_err(anyhow::Error::from))
        },
    )
}

/// The segmentation network's side of [`crate::run`].
pub struct SegTask {
    pub trainer: SegTrainer,
    /// The fixed validation scenes.
    pub val: ValidationSet,
    pub validate_every: u64,
}

impl Task for SegTask {
    type Batch = Vec<SegExample>;
    const TRAIN_HEADER: &'static str = "iteration,loss,iou,loss_avg,iou_avg,scenes_per_s,elapsed_s";
    const METRIC: &'static str = "IoU";

    fn val_header(&self) -> &'static str {
        match self.val {
            ValidationSet::Room(_) => {
                "iteration,iou_median,iou_mean,found_rate,not_found,elapsed_s"
            }
            ValidationSet::Clutter(_) => {
                "iteration,target_found_rate,recall,matched_iou_mean,over_segmented,under_segmented,instances_per_scene,elapsed_s"
            }
        }
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
        self.validate_every
    }

    fn step(&mut self, examples: Vec<SegExample>) -> Result<StepRow> {
        let stats = self.trainer.step(&examples)?;
        Ok(StepRow {
            loss: stats.loss as f64,
            metric: stats.iou,
            extra: Vec::new(),
        })
    }

    fn validate(&mut self, done: u64, elapsed: f64) -> Result<Validation> {
        let views = match &self.val {
            ValidationSet::Room(v) => v,
            ValidationSet::Clutter(scenes) => {
                let m = evaluate_instances(&self.trainer.segmenter(), scenes)?;
                let row = format!(
                    "{done},{:.4},{:.4},{:.4},{},{},{:.2},{elapsed:.1}",
                    m.target_found_rate,
                    m.recall,
                    m.matched_iou_mean,
                    m.over_segmented,
                    m.under_segmented,
                    m.predictions_per_image
                );
                let line = format!(
                    "iteration {done}: validation target found {:.3}, recall {:.3}, matched IoU {:.3}, over {} under {}, {:.1} instances/scene",
                    m.target_found_rate,
                    m.recall,
                    m.matched_iou_mean,
                    m.over_segmented,
                    m.under_segmented,
                    m.predictions_per_image
                );
                return Ok(Validation {
                    row,
                    score: m.target_found_rate + m.recall + m.matched_iou_mean,
                    line,
                    report: serde_json::to_value(&m)?,
                });
            }
        };
        let m = evaluate_network(&self.trainer.segmenter(), views)?;
        let row = format!(
            "{done},{:.4},{:.4},{:.4},{},{elapsed:.1}",
            m.iou_median, m.iou_mean, m.found_rate, m.not_found
        );
        let line = format!(
            "iteration {done}: validation IoU median {:.3} mean {:.3}, found {:.3}",
            m.iou_median, m.iou_mean, m.found_rate
        );
        Ok(Validation {
            row,
            score: m.iou_mean + m.found_rate,
            line,
            report: serde_json::to_value(&m)?,
        })
    }

    fn save(&mut self, path: &Path) -> Result<()> {
        Ok(self.trainer.save(path)?)
    }

    fn save_weights(&self, path: &Path) -> Result<()> {
        Ok(self.trainer.save_weights(path)?)
    }

    fn rate(sps: f64) -> String {
        format!("{sps:.2} scenes/s")
    }
}

/// `eval-seg`: the network's masks (and with `--geometric` the geometry-only alternative's)
/// on room scenes at 640×480; returns the report and writes it (default
/// `<model>.eval-<split>.json`). RAYON_NUM_THREADS (`--threads`) is the caller's to set.
pub fn eval(args: &EvalArgs) -> Result<serde_json::Value> {
    let mut seg = Segmenter::load(&args.model)?;
    if let Some(px) = args.depth_refine_px {
        seg.config_mut().post.depth_refine_px = px;
    }
    if let Some(t) = args.pixel_threshold {
        seg.config_mut().post.pixel_threshold = t;
    }
    if let Some(height) = args.support_height {
        seg.config_mut().post.set_support(
            height,
            args.support_plane_threshold,
            Some(args.support_grow),
        );
    }
    if args.core_radius.is_some() && !args.any_oracle() {
        bail!("--core-radius sets the oracle's cores: it needs --oracle or --oracle-maps");
    }
    if scene_kind(&args.scenes)? == SceneKind::Clutter {
        return eval_clutter(args, &seg);
    }
    if args.any_oracle() {
        bail!(
            "--oracle and --oracle-maps score the instances of clutter scenes: they need --scenes clutter"
        );
    }
    let (split, holdout) = match args.split.as_str() {
        "test" => (Split::Test, false),
        "val" => (Split::Test, true),
        other => bail!("--split {other:?}: expected test or val"),
    };
    let generator = Arc::new(RoomSampleGenerator::new(
        corpus(&args.objects, split, holdout)?,
        RoomSampleConfig::default(),
        args.seed,
    )?);
    tracing::info!(
        "seed {}; {} scenes of the {} split at 640×480",
        args.seed,
        args.count,
        args.split
    );
    let views = Prefetcher::new(0, Some(args.count), 1, 4, move |i| {
        generator.view_with(&mut CpuRenderer::new(), i)
    });
    let bar = ProgressBar::new(args.count);
    let geo_cfg = GeometricConfig::default();
    let (mut network, mut geometric) = (MaskTally::default(), MaskTally::default());
    for (i, v) in views.enumerate() {
        let v = v?;
        let t = Instant::now();
        let found = seg.segment(&v.depth, &v.intrinsics).map(|s| s.mask);
        network.add(&v.mask_visib, t, found)?;
        if args.geometric {
            let t = Instant::now();
            let cfg = GeometricConfig {
                seed: i as u64,
                ..geo_cfg.clone()
            };
            let found =
                ic_seg::segment_geometric(&v.depth, &v.intrinsics, v.model_extent, 1.0, &cfg)
                    .map(|g| g.mask);
            geometric.add(&v.mask_visib, t, found)?;
        }
        bar.set_position(i as u64 + 1);
        if (i + 1) % 50 == 0 && !crate::interactive() {
            tracing::info!("{}/{} scenes", i + 1, args.count);
        }
    }
    bar.finish_and_clear();
    let network_metrics = network.metrics();
    let mut report = serde_json::json!({
        "per_scene_iou": network.ious,
        "model": args.model,
        "split": args.split,
        "seed": args.seed,
        "resolution": [640, 480],
        "config": seg.config(),
        "network": network_metrics,
    });
    if args.geometric {
        report["geometric"] = serde_json::to_value(geometric.metrics())?;
        report["geometric_config"] = serde_json::to_value(&geo_cfg)?;
        report["per_scene_iou_geometric"] = serde_json::to_value(&geometric.ious)?;
    }
    let text = serde_json::to_string_pretty(&report)?;
    let out = args.out.clone().unwrap_or_else(|| {
        let mut p = args.model.clone().into_os_string();
        p.push(format!(".eval-{}.json", args.split));
        PathBuf::from(p)
    });
    crate::write_atomic(&out, text.as_bytes())?;
    tracing::info!("written {}", out.display());
    Ok(report)
}

/// The most PNG sheets `eval-seg --misses` writes.
const MAX_MISS_SHEETS: usize = 40;

/// A sheet of one clutter scene (`eval-seg --misses`): left, the depth (near bright) with the
/// target's true pixels (its first instance) tinted red; right, `found` in colours (a hash of
/// the instance's rank) with the target's true outline in white.
fn write_miss_sheet(path: &Path, s: &ClutterScene, found: &[ic_seg::post::Instance]) -> Result<()> {
    let (w, h) = (s.depth.width as usize, s.depth.height as usize);
    let target = s.mask(s.objects[0].instance_id);
    let valid: Vec<f32> = s.depth.data.iter().copied().filter(|&z| z > 0.0).collect();
    let (lo, hi) = valid
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &z| (a.min(z), b.max(z)));
    let shade = |z: f32| -> u8 {
        if z <= 0.0 || hi <= lo {
            0
        } else {
            (40.0 + 215.0 * (hi - z) / (hi - lo)) as u8
        }
    };
    let mut label = vec![usize::MAX; w * h];
    for (k, inst) in found.iter().enumerate() {
        for (i, &m) in inst.mask.data.iter().enumerate() {
            if m {
                label[i] = k;
            }
        }
    }
    let colour = |k: usize| -> [u8; 3] {
        let x = (k as u32).wrapping_mul(2_654_435_761).rotate_left(7);
        [
            60 + (x & 0xff) as u8 % 196,
            60 + ((x >> 8) & 0xff) as u8 % 196,
            60 + ((x >> 16) & 0xff) as u8 % 196,
        ]
    };
    let mut rgb = vec![0u8; 2 * w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let g = shade(s.depth.data[i]);
            let left = if target.data[i] {
                [g.max(120), g / 3, g / 3]
            } else {
                [g, g, g]
            };
            let right = if ic_render::is_mask_edge(&target, x, y) {
                [255, 255, 255]
            } else if label[i] != usize::MAX {
                colour(label[i])
            } else {
                [g / 3, g / 3, g / 3]
            };
            let l = (y * 2 * w + x) * 3;
            rgb[l..l + 3].copy_from_slice(&left);
            let r = (y * 2 * w + w + x) * 3;
            rgb[r..r + 3].copy_from_slice(&right);
        }
    }
    ic_render::write_rgb_png(path, (2 * w) as u32, h as u32, &rgb)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// `eval-seg --scenes clutter`: every instance of `args.count` cluttered scenes (640×480,
/// seed `args.seed`, objects of `args.split`).
fn eval_clutter(args: &EvalArgs, seg: &Segmenter) -> Result<serde_json::Value> {
    let spec = objects_spec(&args.objects)?;
    let split: Split = args.split.parse()?;
    let corpus = crate::pose::open_objects(&spec, split)?;
    let mut cfg = ClutterConfig {
        fixed_sizes: true,
        ..ClutterConfig::default()
    };
    if let Some(size) = &args.render_size {
        cfg = cfg.with_resolution(size[0], size[1]);
    }
    if let Some(c) = &args.camera {
        cfg = cfg.with_camera(crate::camera_arg(c).context("--camera")?);
    }
    cfg = cfg.with_shadows(args.shadow_probability);
    let (width, height) = (cfg.intrinsics.width, cfg.intrinsics.height);
    let generator = Arc::new(ClutterGenerator::new(corpus, cfg.clone(), args.seed)?);
    tracing::info!(
        "seed {}; {} clutter scenes of the {} split at {width}×{height}",
        args.seed,
        args.count,
        args.split
    );
    let scenes = Prefetcher::new(0, Some(args.count), 1, 2, move |i| generator.scene(i));
    let bar = ProgressBar::new(args.count);
    let mut matches = Vec::new();
    let mut seconds = Vec::new();
    let mut drawn = 0;
    let mut vote_errors = Vec::new();
    let mut rows = String::from(
        "scene,support,objects,target_copies,target_object,target_size_m,target_depth_m,\
         target_visible_px,target_best_iou,target_best_cover,target_covered,\
         target_holder_precision,target_miss,predictions,target_best_iou_pooled\n",
    );
    // The network's extra input sizes (`PostConfig::extra_inputs`): their instances pooled
    // with the own size's, as `register` pools its candidates; not with the oracles.
    let extra: Vec<Segmenter> = if args.any_oracle() {
        Vec::new()
    } else {
        seg.config()
            .post
            .extra_inputs
            .iter()
            .map(|&(w, h)| seg.at_input(w, h))
            .collect()
    };
    let mut pooled_found = 0usize;
    // `--oracle`: the targets of the network's configuration, with `--core-radius`'s cores.
    let mut oracle_cfg = seg.config().clone();
    if let Some(r) = args.core_radius {
        oracle_cfg.train.core_radius = r;
    }
    for (i, s) in scenes.enumerate() {
        let s = s?;
        let t = Instant::now();
        let (found, votes) = if args.any_oracle() {
            let truth = SegExample::from_instances(
                &s.depth,
                &s.intrinsics,
                &s.instances,
                |id| id < SUPPORT_ID_BASE,
                &oracle_cfg,
            )?;
            let small = if args.oracle {
                truth.target
            } else {
                let mut small = seg
                    .probabilities_small(&[(&s.depth, &s.intrinsics)])?
                    .remove(0);
                mix_oracle(
                    &mut small,
                    &truth.target,
                    &args.oracle_maps,
                    seg.config().net.outputs,
                )?;
                small
            };
            seg.instances_from_small(&small, &s.depth, &s.intrinsics, true)?
        } else {
            seg.instances_and_votes(&s.depth, &s.intrinsics)?
        };
        let m = match_scene(&found, &s)?;
        let mut pooled_iou = m.best_iou.first().copied().unwrap_or(0.0);
        for other in &extra {
            let more = other.instances(&s.depth, &s.intrinsics)?;
            let o = match_scene(&more, &s)?;
            pooled_iou = pooled_iou.max(o.best_iou.first().copied().unwrap_or(0.0));
        }
        pooled_found += usize::from(pooled_iou >= 0.5);
        seconds.push(t.elapsed().as_secs_f64());
        if let Some(votes) = votes {
            vote_errors.push(centre_vote_error(&votes, &s));
        }
        let target = &s.objects[0];
        if let (Some(dir), Some(kind)) = (&args.misses, ic_eval::instances::TargetMisses::kind(&m))
            && drawn < MAX_MISS_SHEETS
        {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
            let path = dir.join(format!("miss-{:04}-{kind}.png", s.index));
            write_miss_sheet(&path, &s, &found)?;
            drawn += 1;
        }
        rows.push_str(&format!(
            "{},{},{},{},{},{:.3},{:.3},{},{:.4},{:.4},{:.4},{:.4},{},{},{:.4}\n",
            s.index,
            s.support.as_str(),
            s.objects.len(),
            s.targets().count(),
            target.object.id,
            2.0 * target.scale_m,
            target.pose.translation.z,
            target.visible_pixels,
            m.best_iou.first().copied().unwrap_or(0.0),
            m.best_cover.first().copied().unwrap_or(0.0),
            m.covered.first().copied().unwrap_or(0.0),
            m.holder_precision.first().copied().unwrap_or(0.0),
            ic_eval::instances::TargetMisses::kind(&m).unwrap_or(""),
            m.predictions,
            pooled_iou,
        ));
        matches.push(m);
        bar.set_position(i as u64 + 1);
        if (i + 1) % 50 == 0 && !crate::interactive() {
            tracing::info!("{}/{} scenes", i + 1, args.count);
        }
    }
    bar.finish_and_clear();
    let summary = ic_eval::instances::summarise(&matches);
    let report = serde_json::json!({
        "model": args.model,
        "oracle": args.oracle,
        "oracle_maps": args.oracle_maps,
        "scenes": "clutter",
        "split": args.split,
        "seed": args.seed,
        "resolution": [width, height],
        "clutter": cfg,
        "config": seg.config(),
        "instances": summary,
        // The share of scenes whose target an instance of any input size finds (IoU ≥ 0.5):
        // the candidates `register` pools; the same as `instances`' target found rate
        // without extra input sizes.
        "pooled_target_found_rate": pooled_found as f64 / matches.len().max(1) as f64,
        "seconds_median": ic_eval::median(&seconds),
        // Four-output networks: per scene, the mean distance (pixels of the 640×480 map)
        // from each true object pixel's vote to its instance's centroid; `at_pixel`: the
        // same from the pixel itself (votes without offsets).
        "centre_vote_error_px": (!vote_errors.is_empty()).then(|| {
            let (err, base): (Vec<f64>, Vec<f64>) = vote_errors.iter().copied().unzip();
            serde_json::json!({
                "median": ic_eval::median(&err),
                "mean": err.iter().sum::<f64>() / err.len() as f64,
                "at_pixel_median": ic_eval::median(&base),
            })
        }),
    });
    let out = args.out.clone().unwrap_or_else(|| {
        let mut p = args.model.clone().into_os_string();
        p.push(format!(".eval-clutter-{}.json", args.split));
        PathBuf::from(p)
    });
    crate::write_atomic(&out, serde_json::to_string_pretty(&report)?.as_bytes())?;
    let csv = out.with_extension("csv");
    crate::write_atomic(&csv, rows.as_bytes())?;
    tracing::info!(
        "written {} and {} (one row per scene)",
        out.display(),
        csv.display()
    );
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn oracle_maps_replace_only_the_named_maps_and_refuse_a_map_the_network_lacks() {
        // Four maps of 2 pixels: object, core, offset x, offset y.
        let truth = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        let mut net = [0.0f32; 8];
        mix_oracle(&mut net, &truth, &[OracleMap::Core], 4).unwrap();
        assert_eq!(net, [0.0, 0.0, 3.0, 4.0, 0.0, 0.0, 0.0, 0.0]);
        mix_oracle(&mut net, &truth, &[OracleMap::Offsets], 4).unwrap();
        assert_eq!(net, [0.0, 0.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
        mix_oracle(&mut net, &truth, &[OracleMap::Object], 4).unwrap();
        assert_eq!(net, truth);
        // A two-output network has no offsets; sizes must agree.
        let mut two = [0.0f32; 4];
        let err = mix_oracle(&mut two, &truth[..4], &[OracleMap::Offsets], 2).unwrap_err();
        assert!(err.to_string().contains("2 output map(s)"), "{err}");
        assert!(mix_oracle(&mut two, &truth, &[OracleMap::Object], 2).is_err());
    }
}
