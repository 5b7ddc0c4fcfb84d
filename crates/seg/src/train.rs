//! What training needs of the network: examples at its resolution ([`SegExample`]) and the
//! loss ([`seg_loss`]). The trainer (seeded weights, Adam, resumable checkpoints) is
//! `ic_train::SegTrainer`.
//!
//! Loss: the mean per-pixel binary cross-entropy on each probability map's logit plus
//! `dice_weight` × (1 − soft Dice), the Dice term averaged over the images and maps of the
//! batch. The objects cover 0.5–40 % of the pixels; the Dice term keeps a small object from
//! being a rounding error of the cross-entropy. A four-output network's centre offsets add
//! `offset_weight` × their mean absolute error over the true object pixels (in
//! [`crate::config::OFFSET_UNIT`]s; the offsets of other pixels are not trained). With
//! per-pixel weights ([`SegExample::weight`], `train.balance_area`, `train.border_weight`) the
//! cross-entropy and the offsets' error are weighted means; the Dice term is not weighted.

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
    /// `[outputs, H, W]`: 1 on the object (then on the instance cores), 0 elsewhere; then, for
    /// four-output networks, the centre offsets x and y (0 off the objects).
    pub target: Vec<f32>,
    /// `[H, W]` per-pixel loss weights (`train.balance_area`, `train.border_weight`), or
    /// empty: every pixel 1.
    pub weight: Vec<f32>,
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
    /// two- and four-output networks — the instance cores (object pixels whose neighbours
    /// within `train.core_radius` pixels all show the same instance; outside the image counts
    /// as the same), then — for four-output networks — each object pixel's offset to the
    /// centroid of its instance's pixels at the network's resolution, in
    /// [`crate::config::OFFSET_UNIT`]s.
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
        let (wu, hu) = (w as usize, h as usize);
        if config.net.has_core() {
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
        if config.net.has_offsets() {
            // Centroid of each instance's pixels (x, y, count), by id.
            let mut sums: std::collections::HashMap<u32, (f64, f64, f64)> = Default::default();
            for (i, (&id, &o)) in ids.iter().zip(&object).enumerate() {
                if o {
                    let s = sums.entry(id).or_default();
                    s.0 += (i % wu) as f64;
                    s.1 += (i / wu) as f64;
                    s.2 += 1.0;
                }
            }
            let unit = crate::config::OFFSET_UNIT as f64;
            for axis in 0..2 {
                for (i, (&id, &o)) in ids.iter().zip(&object).enumerate() {
                    let v = if o {
                        let s = sums[&id];
                        let (c, p) = if axis == 0 {
                            (s.0 / s.2, (i % wu) as f64)
                        } else {
                            (s.1 / s.2, (i / wu) as f64)
                        };
                        ((c - p) / unit) as f32
                    } else {
                        0.0
                    };
                    target.push(v);
                }
            }
        }
        let weight = loss_weights(&ids, &object, wu, hu, &config.train);
        Ok(SegExample {
            input: prepare_input(depth, intrinsics, config.net.input, w, h)?,
            target,
            weight,
        })
    }
}

/// The per-pixel loss weights of `train.balance_area` and `train.border_weight` for instance
/// ids `ids` (`w`×`h`, row-major; `object` says which are objects), or empty when both are
/// off.
fn loss_weights(
    ids: &[u32],
    object: &[bool],
    w: usize,
    h: usize,
    train: &crate::config::SegTrainConfig,
) -> Vec<f32> {
    if train.balance_area <= 0.0 && train.border_weight <= 0.0 {
        return Vec::new();
    }
    let mut weight = vec![1.0f32; w * h];
    if train.balance_area > 0.0 {
        let mut count: std::collections::HashMap<u32, f64> = Default::default();
        for (&id, &o) in ids.iter().zip(object) {
            if o {
                *count.entry(id).or_default() += 1.0;
            }
        }
        for ((wt, id), &o) in weight.iter_mut().zip(ids).zip(object) {
            if o {
                *wt = (train.balance_area / count[id])
                    .sqrt()
                    .clamp(1.0, crate::config::BALANCE_CAP) as f32;
            }
        }
    }
    if train.border_weight > 0.0 {
        // The nearest pixel of another object within 3 σ (square window, Euclidean distance).
        let sigma = crate::config::BORDER_SIGMA;
        let r = (3.0 * sigma).ceil() as i64;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !object[i] {
                    continue;
                }
                let mut d2 = f64::INFINITY;
                for dy in -r..=r {
                    let ny = y as i64 + dy;
                    if ny < 0 || ny >= h as i64 {
                        continue;
                    }
                    for dx in -r..=r {
                        let nx = x as i64 + dx;
                        if nx < 0 || nx >= w as i64 {
                            continue;
                        }
                        let j = ny as usize * w + nx as usize;
                        if object[j] && ids[j] != ids[i] {
                            d2 = d2.min((dx * dx + dy * dy) as f64);
                        }
                    }
                }
                if d2.is_finite() {
                    let near = (-d2 / (2.0 * sigma * sigma)).exp();
                    weight[i] *= (1.0 + train.border_weight * near) as f32;
                }
            }
        }
    }
    weight
}

/// The loss (see the module doc) of `logits` `[B, C, H, W]` against `targets` of the same
/// shape (each probability map is its own Dice term), with optional per-pixel `weights`
/// `[B, 1, H, W]`. With C = 4 the last two maps are the centre offsets, weighted by
/// `offset_weight`.
pub fn seg_loss(
    logits: &Tensor,
    targets: &Tensor,
    weights: Option<&Tensor>,
    dice_weight: f64,
    offset_weight: f64,
) -> Result<Tensor> {
    let c = logits.dim(1)?;
    if c == 4 {
        let maps = map_loss(
            &logits.narrow(1, 0, 2)?,
            &targets.narrow(1, 0, 2)?,
            weights,
            dice_weight,
        )?;
        let object = targets.narrow(1, 0, 1)?;
        let object = match weights {
            Some(w) => (object * w)?,
            None => object,
        };
        let err = (logits.narrow(1, 2, 2)? - targets.narrow(1, 2, 2)?)?
            .abs()?
            .broadcast_mul(&object)?;
        // Mean over the object pixels of both axes' errors (one pixel at least, so a batch
        // without objects adds nothing).
        let pixels = (object.sum_all()? * 2.0)?.maximum(1.0)?;
        let offsets = err.sum_all()?.div(&pixels)?;
        return Ok((maps + (offsets * offset_weight)?)?);
    }
    map_loss(logits, targets, weights, dice_weight)
}

/// Cross-entropy (weighted mean with `weights` `[B, 1, H, W]`) and Dice over every map of
/// `logits`.
fn map_loss(
    logits: &Tensor,
    targets: &Tensor,
    weights: Option<&Tensor>,
    dice_weight: f64,
) -> Result<Tensor> {
    let (b, c, h, w) = logits.dims4()?;
    let x = logits.reshape((b * c, h * w))?;
    let y = targets.reshape((b * c, h * w))?;
    // BCE with logits, stable: max(x, 0) − x·y + log(1 + exp(−|x|)).
    let bce = ((x.relu()? - (&x * &y)?)? + ((x.abs()?.neg()?.exp()? + 1.0)?.log()?))?;
    let bce = match weights {
        Some(wt) => {
            let wt = wt.broadcast_as((b, c, h, w))?.reshape((b * c, h * w))?;
            (bce * &wt)?.sum_all()?.div(&wt.sum_all()?)?
        }
        None => bce.mean_all()?,
    };
    let b = b * c;
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
