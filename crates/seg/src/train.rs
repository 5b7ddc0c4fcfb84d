//! Training: seeded weights, a step on a batch of depth maps and masks, resumable
//! checkpoints.
//!
//! Loss: the mean per-pixel binary cross-entropy on the object logit plus `dice_weight` ×
//! (1 − soft Dice), the Dice term averaged over the images of the batch. The objects cover
//! 0.5–40 % of the pixels; the Dice term keeps a small object from being a rounding error of
//! the cross-entropy.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use ic_geometry::{DepthImage, Mask};
use ic_nn::adam::Adam;
use ic_nn::seeded_var_builder;

use crate::checkpoint::{self, CONFIG_KEY, STATE_KEY, SegTrainState};
use crate::config::SegConfig;
use crate::input::{INPUT_CHANNELS, prepare, resize_nearest};
use crate::segmenter::Segmenter;
use crate::unet::UNet;
use crate::{Result, SegError};

/// One training example at the network's resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct SegExample {
    /// `[2, H, W]` flattened (see [`crate::input::prepare`]).
    pub input: Vec<f32>,
    /// `[H, W]`: 1 on the object, 0 elsewhere.
    pub target: Vec<f32>,
}

impl SegExample {
    /// Resizes `depth` and `mask` (the same size) to the network input of `config`.
    pub fn new(depth: &DepthImage, mask: &Mask, config: &SegConfig) -> Result<SegExample> {
        if (depth.width, depth.height) != (mask.width, mask.height) {
            return Err(SegError::Input(format!(
                "depth {}×{} vs mask {}×{}",
                depth.width, depth.height, mask.width, mask.height
            )));
        }
        let (w, h) = (config.net.input_width, config.net.input_height);
        let as_depth = DepthImage {
            width: mask.width,
            height: mask.height,
            data: mask.data.iter().map(|&m| m as u8 as f32).collect(),
        };
        Ok(SegExample {
            input: prepare(depth, w, h)?,
            target: resize_nearest(&as_depth, w, h),
        })
    }
}

/// What one step measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegStepStats {
    pub loss: f32,
    /// Mean over the batch of the IoU of `logit > 0` with the target, at the network's
    /// resolution.
    pub iou: f64,
}

/// The loss (see the module doc) of `logits` `[B, 1, H, W]` against `targets` of the same
/// shape.
pub fn seg_loss(logits: &Tensor, targets: &Tensor, dice_weight: f64) -> Result<Tensor> {
    let b = logits.dim(0)?;
    let x = logits.flatten_from(1)?;
    let y = targets.flatten_from(1)?;
    // BCE with logits, stable: max(x, 0) − x·y + log(1 + exp(−|x|)).
    let bce = ((x.relu()? - (&x * &y)?)? + ((x.abs()?.neg()?.exp()? + 1.0)?.log()?))?;
    let bce = bce.mean_all()?;
    if dice_weight == 0.0 {
        return Ok(bce);
    }
    let p = candle_nn::ops::sigmoid(&x)?;
    let inter = (&p * &y)?.sum(1)?;
    let total = (p.sum(1)? + y.sum(1)?)?;
    let dice = ((inter * 2.0)? + 1.0)?.div(&(total + 1.0)?)?;
    let dice_loss = ((dice.sum_all()? / b as f64)?.neg()? + 1.0)?;
    Ok((bce + (dice_loss * dice_weight)?)?)
}

/// Network + optimiser + position in the run.
pub struct SegTrainer {
    config: SegConfig,
    varmap: VarMap,
    net: UNet,
    adam: Adam,
    iteration: u64,
    seed: u64,
    device: Device,
}

impl SegTrainer {
    /// A fresh run: weights drawn from `seed`.
    pub fn new(config: SegConfig, seed: u64) -> Result<Self> {
        config.validate()?;
        let device = Device::Cpu;
        let varmap = VarMap::new();
        let vb = seeded_var_builder(&varmap, seed, &device);
        let net = UNet::new(vb, &config.net)?;
        let adam = Adam::new(&varmap, config.train.learning_rate)?;
        Ok(SegTrainer {
            config,
            varmap,
            net,
            adam,
            iteration: 0,
            seed,
            device,
        })
    }

    /// Continues the run saved in `path` (configuration, weights, Adam moments, iteration).
    pub fn resume(path: &Path) -> Result<Self> {
        let config = checkpoint::read_config(path)?;
        let state = checkpoint::read_state(path)?;
        let mut t = Self::new(config, state.seed)?;
        ic_nn::checkpoint::restore_training(
            path,
            &t.varmap,
            &mut t.adam,
            state.adam_step,
            &t.device,
        )?;
        t.iteration = state.iteration;
        Ok(t)
    }

    pub fn config(&self) -> &SegConfig {
        &self.config
    }

    pub fn set_iterations(&mut self, iterations: u64) {
        self.config.train.iterations = iterations;
    }

    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    pub fn varmap(&self) -> &VarMap {
        &self.varmap
    }

    pub fn net(&self) -> &UNet {
        &self.net
    }

    /// A segmenter sharing the current weights (inference mode), e.g. for validation.
    pub fn segmenter(&self) -> Segmenter {
        Segmenter::from_parts(self.net.clone(), self.config.clone())
    }

    fn tensors(&self, examples: &[SegExample]) -> Result<(Tensor, Tensor)> {
        let (w, h) = (
            self.config.net.input_width as usize,
            self.config.net.input_height as usize,
        );
        let b = examples.len();
        let mut input = Vec::with_capacity(b * INPUT_CHANNELS * w * h);
        let mut target = Vec::with_capacity(b * w * h);
        for e in examples {
            if e.input.len() != INPUT_CHANNELS * w * h || e.target.len() != w * h {
                return Err(SegError::Input(format!(
                    "example is not {INPUT_CHANNELS}×{h}×{w}"
                )));
            }
            input.extend_from_slice(&e.input);
            target.extend_from_slice(&e.target);
        }
        Ok((
            Tensor::from_vec(input, (b, INPUT_CHANNELS, h, w), &self.device)?,
            Tensor::from_vec(target, (b, 1, h, w), &self.device)?,
        ))
    }

    /// The loss of `examples` without a step (inference mode).
    pub fn loss(&self, examples: &[SegExample]) -> Result<f32> {
        let (x, y) = self.tensors(examples)?;
        let logits = self.net.forward_t(&x, false)?;
        Ok(seg_loss(&logits, &y, self.config.train.dice_weight)?.to_scalar::<f32>()?)
    }

    /// One step: forward (training mode), loss, backward, Adam.
    pub fn step(&mut self, examples: &[SegExample]) -> Result<SegStepStats> {
        if examples.is_empty() {
            return Err(SegError::Input("empty batch".into()));
        }
        let (x, y) = self.tensors(examples)?;
        let logits = self.net.forward_t(&x, true)?;
        let loss = seg_loss(&logits, &y, self.config.train.dice_weight)?;
        let grads = loss.backward()?;
        self.adam.step(&grads)?;
        self.iteration += 1;
        let pred = logits
            .detach()
            .gt(0.0)?
            .to_dtype(DType::F32)?
            .flatten_from(1)?;
        let yt = y.flatten_from(1)?;
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

    fn metadata(&self, with_state: bool) -> Result<HashMap<String, String>> {
        let json = |e: serde_json::Error| SegError::Config(e.to_string());
        let mut meta = HashMap::new();
        meta.insert(
            CONFIG_KEY.to_string(),
            serde_json::to_string(&self.config).map_err(json)?,
        );
        if with_state {
            let state = SegTrainState {
                iteration: self.iteration,
                seed: self.seed,
                adam_step: self.adam.step_count(),
            };
            meta.insert(
                STATE_KEY.to_string(),
                serde_json::to_string(&state).map_err(json)?,
            );
        }
        Ok(meta)
    }

    /// Saves everything needed to resume exactly (atomically).
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut tensors = ic_nn::checkpoint::varmap_tensors(&self.varmap);
        tensors.extend(self.adam.state());
        Ok(ic_nn::checkpoint::save(
            path,
            &tensors,
            self.metadata(true)?,
        )?)
    }

    /// Saves the weights and configuration only (what inference needs; atomically).
    pub fn save_weights(&self, path: &Path) -> Result<()> {
        Ok(ic_nn::checkpoint::save(
            path,
            &ic_nn::checkpoint::varmap_tensors(&self.varmap),
            self.metadata(false)?,
        )?)
    }
}
