//! What training needs of the network: examples at its resolution ([`SegExample`]) and the
//! loss ([`seg_loss`]). The trainer (seeded weights, Adam, resumable checkpoints) is
//! `ic_train::SegTrainer`.
//!
//! Loss: the mean per-pixel binary cross-entropy on the object logit plus `dice_weight` ×
//! (1 − soft Dice), the Dice term averaged over the images of the batch. The objects cover
//! 0.5–40 % of the pixels; the Dice term keeps a small object from being a rounding error of
//! the cross-entropy.

use candle_core::Tensor;
use ic_geometry::{DepthImage, Mask};

use crate::config::SegConfig;
use crate::input::{prepare, resize_nearest};
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
