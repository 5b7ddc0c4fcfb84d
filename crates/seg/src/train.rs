//! What training needs of the network: examples at its resolution ([`SegExample`]) and the
//! loss ([`seg_loss`]). The trainer (seeded weights, Adam, resumable checkpoints) is
//! `ic_train::SegTrainer`.
//!
//! Loss: the mean per-pixel binary cross-entropy on each output logit plus `dice_weight` ×
//! (1 − soft Dice), the Dice term averaged over the images and outputs of the batch. The
//! objects cover 0.5–40 % of the pixels; the Dice term keeps a small object from being a
//! rounding error of the cross-entropy.

use candle_core::Tensor;
use ic_geometry::{DepthImage, Image, Intrinsics, Mask};

use crate::config::SegConfig;
use crate::input::{prepare_input, resize_nearest};
use crate::{Result, SegError};

/// One training example at the network's resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct SegExample {
    /// `[C, H, W]` flattened, C the configuration's input channels (see
    /// [`crate::input::prepare_input`]).
    pub input: Vec<f32>,
    /// `[outputs, H, W]`: 1 on the object (then on the instance cores), 0 elsewhere.
    pub target: Vec<f32>,
}

impl SegExample {
    /// Resizes `depth` and `mask` (the same size, seen by `intrinsics`) to the network input
    /// of `config`: the object is the one instance ([`SegExample::from_instances`]).
    pub fn new(
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        mask: &Mask,
        config: &SegConfig,
    ) -> Result<SegExample> {
        let ids = Image {
            width: mask.width,
            height: mask.height,
            data: mask.data.iter().map(|&m| m as u32).collect(),
        };
        Self::from_instances(depth, intrinsics, &ids, |_| true, config)
    }

    /// An example of a scene with many objects, seen by `intrinsics`: `instances` (the depth
    /// map's size) says which instance each pixel shows and `is_object` which ids are objects (not the support or
    /// the background). Targets at the network's resolution: every object pixel, then — for
    /// two-output networks — the instance cores (object pixels whose neighbours within
    /// `train.core_radius` pixels all show the same instance; outside the image counts as
    /// the same).
    pub fn from_instances(
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        instances: &Image<u32>,
        is_object: impl Fn(u32) -> bool,
        config: &SegConfig,
    ) -> Result<SegExample> {
        if (depth.width, depth.height) != (instances.width, instances.height) {
            return Err(SegError::Input(format!(
                "depth {}×{} vs its labels {}×{}",
                depth.width, depth.height, instances.width, instances.height
            )));
        }
        let (w, h) = (config.net.input_width, config.net.input_height);
        let as_depth = DepthImage {
            width: instances.width,
            height: instances.height,
            data: instances.data.iter().map(|&i| i as f32).collect(),
        };
        // Ids below 2^24 survive the round trip through f32 exactly.
        let ids: Vec<u32> = resize_nearest(&as_depth, w, h)
            .iter()
            .map(|&x| x as u32)
            .collect();
        let object: Vec<bool> = ids.iter().map(|&i| i != 0 && is_object(i)).collect();
        let mut target: Vec<f32> = object.iter().map(|&o| o as u8 as f32).collect();
        if config.net.outputs == 2 {
            let (wu, hu) = (w as usize, h as usize);
            let r = config.train.core_radius as i64;
            for y in 0..hu {
                for x in 0..wu {
                    let i = y * wu + x;
                    let mut core = object[i];
                    'scan: for dy in -r..=r {
                        for dx in -r..=r {
                            if !core {
                                break 'scan;
                            }
                            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                            if nx < 0 || ny < 0 || nx >= wu as i64 || ny >= hu as i64 {
                                continue;
                            }
                            core = ids[ny as usize * wu + nx as usize] == ids[i];
                        }
                    }
                    target.push(core as u8 as f32);
                }
            }
        }
        Ok(SegExample {
            input: prepare_input(depth, intrinsics, config.net.input, w, h)?,
            target,
        })
    }
}

/// The loss (see the module doc) of `logits` `[B, C, H, W]` against `targets` of the same
/// shape (each output map is its own Dice term).
pub fn seg_loss(logits: &Tensor, targets: &Tensor, dice_weight: f64) -> Result<Tensor> {
    let (b, c, h, w) = logits.dims4()?;
    let x = logits.reshape((b * c, h * w))?;
    let y = targets.reshape((b * c, h * w))?;
    let b = b * c;
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
