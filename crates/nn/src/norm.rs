//! Batch normalisation for channel-first tensors.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor, Var};
use candle_nn::{Init, VarBuilder};
use rayon::prelude::*;

use crate::cpu::{f32_slice, to_f32_vec};

/// Batch normalisation for channel-first tensors `[B, C, L]`: statistics over B and L.
///
/// Reduces over the last dimension first (fast in candle), then over the small batch
/// dimension, instead of candle-nn's transpose-and-copy. The running statistics live in the
/// `VarMap` as `running_mean` / `running_var` (no gradient) and are saved with the weights.
#[derive(Clone, Debug)]
pub struct BatchNorm1 {
    weight: Tensor,
    bias: Tensor,
    running_mean: Var,
    running_var: Var,
    momentum: f64,
    eps: f64,
}

impl BatchNorm1 {
    pub fn new(vb: VarBuilder, channels: usize, momentum: f64) -> Result<Self> {
        let running_mean = vb.get_with_hints(channels, "running_mean", Init::Const(0.0))?;
        let running_var = vb.get_with_hints(channels, "running_var", Init::Const(1.0))?;
        Ok(BatchNorm1 {
            weight: vb.get_with_hints(channels, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(channels, "bias", Init::Const(0.0))?,
            running_mean: Var::from_tensor(&running_mean)?,
            running_var: Var::from_tensor(&running_var)?,
            momentum,
            eps: 1e-5,
        })
    }

    /// `train`: normalise with the batch statistics and update the running ones; otherwise
    /// use the running statistics.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (b, c, l) = x.dims3()?;
        let shape = (1, c, 1);
        let w = self.weight.reshape(shape)?;
        let bias = self.bias.reshape(shape)?;
        if train {
            let n = (b * l) as f64;
            let mean = (x.sum_keepdim(2)?.sum_keepdim(0)? / n)?;
            let xc = x.broadcast_sub(&mean)?;
            let var = (xc.sqr()?.sum_keepdim(2)?.sum_keepdim(0)? / n)?;
            let m = self.momentum;
            let unbias = if n > 1.0 { n / (n - 1.0) } else { 1.0 };
            let rm = ((self.running_mean.as_detached_tensor() * (1.0 - m))?
                + (mean.detach().flatten_all()? * m)?)?;
            let rv = ((self.running_var.as_detached_tensor() * (1.0 - m))?
                + (var.detach().flatten_all()? * (m * unbias))?)?;
            self.running_mean.set(&rm)?;
            self.running_var.set(&rv)?;
            let scale = w.broadcast_div(&(var + self.eps)?.sqrt()?)?;
            xc.broadcast_mul(&scale)?.broadcast_add(&bias)
        } else {
            let rm = self.running_mean.as_detached_tensor().reshape(shape)?;
            let rv = self.running_var.as_detached_tensor().reshape(shape)?;
            let scale = w.broadcast_div(&(rv + self.eps)?.sqrt()?)?;
            let shift = bias.broadcast_sub(&rm.broadcast_mul(&scale)?)?;
            x.broadcast_mul(&scale)?.broadcast_add(&shift)
        }
    }
}

impl BatchNorm1 {
    /// `LeakyReLU(BN(x))` with negative slope `slope` (> 0): the same function as
    /// [`Self::forward_t`] followed by `max(y, slope·y)`, and the same running-statistics update.
    ///
    /// On the CPU with f32 one fused op (forward and backward, one pass per channel) instead of
    /// about fifteen tensor ops whose backward reduces over the non-last batch dimension; the
    /// batch statistics are computed in f32 over B·L values per channel.
    pub fn forward_leaky_relu(&self, x: &Tensor, train: bool, slope: f32) -> Result<Tensor> {
        let fused = x.device().is_cpu()
            && x.dtype() == DType::F32
            && self.weight.dtype() == DType::F32
            && slope > 0.0;
        if !fused {
            let y = self.forward_t(x, train)?;
            return y.maximum(&(&y * slope as f64)?);
        }
        let (b, c, l) = x.dims3()?;
        let stats = if train {
            None
        } else {
            let rm = self.running_mean.as_detached_tensor().to_vec1::<f32>()?;
            let rv = self.running_var.as_detached_tensor().to_vec1::<f32>()?;
            Some(rm.into_iter().zip(rv).collect())
        };
        let kept = Arc::new(Mutex::new(None));
        let op = BnLeaky {
            eps: self.eps as f32,
            slope,
            fixed: stats,
            batch: kept.clone(),
        };
        let y =
            x.contiguous()?
                .apply_op3(&self.weight.contiguous()?, &self.bias.contiguous()?, op)?;
        if train {
            let batch = kept.lock().unwrap_or_else(|e| e.into_inner()).clone();
            let Some(batch) = batch else {
                candle_core::bail!("batch norm: the fused op kept no statistics")
            };
            let n = (b * l) as f64;
            let unbias = if n > 1.0 { n / (n - 1.0) } else { 1.0 };
            let mean: Vec<f32> = batch.iter().map(|s| s.0).collect();
            let var: Vec<f32> = batch.iter().map(|s| s.1).collect();
            let dev = x.device();
            let m = self.momentum;
            let rm = ((self.running_mean.as_detached_tensor() * (1.0 - m))?
                + (Tensor::from_vec(mean, c, dev)? * m)?)?;
            let rv = ((self.running_var.as_detached_tensor() * (1.0 - m))?
                + (Tensor::from_vec(var, c, dev)? * (m * unbias))?)?;
            self.running_mean.set(&rm)?;
            self.running_var.set(&rv)?;
        }
        Ok(y)
    }
}

/// (mean, biased variance) per channel.
type ChannelStats = Arc<Vec<(f32, f32)>>;

/// The fused `LeakyReLU(BN(x))` for `[B, C, L]`: per-channel statistics from the batch
/// (`fixed` = None, training) or given (running statistics, inference). `batch` keeps the
/// (mean, biased variance) of each channel of the last forward.
struct BnLeaky {
    eps: f32,
    slope: f32,
    fixed: Option<Vec<(f32, f32)>>,
    batch: Arc<Mutex<Option<ChannelStats>>>,
}

impl BnLeaky {
    /// (mean, biased variance) of every channel of `x` `[B, C, L]`.
    fn channel_stats(x: &[f32], b: usize, c: usize, l: usize) -> Vec<(f32, f32)> {
        (0..c)
            .into_par_iter()
            .map(|ch| {
                let n = (b * l) as f64;
                let mut sum = 0.0f64;
                for bi in 0..b {
                    sum += x[(bi * c + ch) * l..(bi * c + ch + 1) * l]
                        .iter()
                        .map(|&v| v as f64)
                        .sum::<f64>();
                }
                let mean = sum / n;
                let mut sq = 0.0f64;
                for bi in 0..b {
                    sq += x[(bi * c + ch) * l..(bi * c + ch + 1) * l]
                        .iter()
                        .map(|&v| (v as f64 - mean) * (v as f64 - mean))
                        .sum::<f64>();
                }
                (mean as f32, (sq / n) as f32)
            })
            .collect()
    }
}

impl CustomOp3 for BnLeaky {
    fn name(&self) -> &'static str {
        "ic-batch-norm-leaky-relu"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, c, l) = l1.shape().dims3()?;
        let (x, w, bias) = (
            f32_slice(s1, l1, "batch norm x")?,
            f32_slice(s2, l2, "batch norm weight")?,
            f32_slice(s3, l3, "batch norm bias")?,
        );
        if w.len() != c || bias.len() != c {
            candle_core::bail!(
                "batch norm: {c} channels, {} weights, {} biases",
                w.len(),
                bias.len()
            );
        }
        let stats = match &self.fixed {
            Some(s) => s.clone(),
            None => Self::channel_stats(x, b, c, l),
        };
        let mut y = vec![0.0f32; x.len()];
        let slope = self.slope;
        y.par_chunks_mut(l)
            .zip(x.par_chunks(l))
            .enumerate()
            .for_each(|(row, (yr, xr))| {
                let ch = row % c;
                let (mean, var) = stats[ch];
                let scale = w[ch] / (var + self.eps).sqrt();
                let shift = bias[ch] - mean * scale;
                for (o, &v) in yr.iter_mut().zip(xr) {
                    let t = v * scale + shift;
                    *o = if t > 0.0 { t } else { t * slope };
                }
            });
        if self.fixed.is_none() {
            *self.batch.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(stats));
        }
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (b, c, l) = x.dims3()?;
        let flat = to_f32_vec;
        let (xv, wv, yv, gv) = (flat(x)?, flat(w)?, flat(res)?, flat(grad)?);
        let stats: Vec<(f32, f32)> = match &self.fixed {
            Some(s) => s.clone(),
            None => match self.batch.lock().unwrap_or_else(|e| e.into_inner()).clone() {
                Some(s) => s.to_vec(),
                None => Self::channel_stats(&xv, b, c, l),
            },
        };
        let train = self.fixed.is_none();
        let n = (b * l) as f32;
        let slope = self.slope;
        // Per channel: dγ, dβ, and (writing dx) the input gradient.
        let per_channel: Vec<(f32, f32, Vec<f32>)> = (0..c)
            .into_par_iter()
            .map(|ch| {
                let (mean, var) = stats[ch];
                let rstd = 1.0 / (var + self.eps).sqrt();
                let (mut dgamma, mut dbeta) = (0.0f32, 0.0f32);
                let mut gpre = vec![0.0f32; b * l];
                for bi in 0..b {
                    let o = (bi * c + ch) * l;
                    for i in 0..l {
                        // LeakyReLU keeps the sign, so the output tells which branch was taken.
                        let g = if yv[o + i] > 0.0 {
                            gv[o + i]
                        } else {
                            gv[o + i] * slope
                        };
                        let xh = (xv[o + i] - mean) * rstd;
                        gpre[bi * l + i] = g;
                        dgamma += g * xh;
                        dbeta += g;
                    }
                }
                let k = wv[ch] * rstd;
                let mut dx = gpre;
                for bi in 0..b {
                    let o = (bi * c + ch) * l;
                    for i in 0..l {
                        let g = dx[bi * l + i];
                        dx[bi * l + i] = if train {
                            let xh = (xv[o + i] - mean) * rstd;
                            k * (g - dbeta / n - xh * dgamma / n)
                        } else {
                            k * g
                        };
                    }
                }
                (dgamma, dbeta, dx)
            })
            .collect();
        let mut dx = vec![0.0f32; b * c * l];
        let mut dw = vec![0.0f32; c];
        let mut db = vec![0.0f32; c];
        for (ch, (dg, dbe, d)) in per_channel.into_iter().enumerate() {
            dw[ch] = dg;
            db[ch] = dbe;
            for bi in 0..b {
                dx[(bi * c + ch) * l..(bi * c + ch + 1) * l]
                    .copy_from_slice(&d[bi * l..(bi + 1) * l]);
            }
        }
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, (b, c, l), dev)?),
            Some(Tensor::from_vec(dw, c, dev)?),
            Some(Tensor::from_vec(db, c, dev)?),
        ))
    }
}

/// Batch normalisation for images `[B, C, H, W]`: [`BatchNorm1`] over the flattened pixels.
#[derive(Clone, Debug)]
pub struct BatchNorm2(BatchNorm1);

impl BatchNorm2 {
    pub fn new(vb: VarBuilder, channels: usize, momentum: f64) -> Result<Self> {
        Ok(BatchNorm2(BatchNorm1::new(vb, channels, momentum)?))
    }

    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        self.0
            .forward_t(&x.reshape((b, c, h * w))?, train)?
            .reshape((b, c, h, w))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use candle_nn::VarMap;

    fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| {
                ((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) % 1000) as f32 / 250.0
                    - 2.0
            })
            .collect()
    }

    /// Output, input/γ/β gradients and running statistics of `LeakyReLU(BN(x))`, fused or from
    /// tensor ops, in training or inference mode.
    fn run(fused: bool, train: bool) -> Vec<Vec<f32>> {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
        let bn = BatchNorm1::new(vb, 5, 0.3).unwrap();
        bn.running_mean
            .set(&Tensor::from_vec(values(5, 1), 5, &dev).unwrap())
            .unwrap();
        let rv: Vec<f32> = values(5, 2).iter().map(|v| v.abs() + 0.5).collect();
        bn.running_var
            .set(&Tensor::from_vec(rv, 5, &dev).unwrap())
            .unwrap();
        let w = Var::from_tensor(&Tensor::from_vec(values(5, 3), 5, &dev).unwrap()).unwrap();
        let bnw = BatchNorm1 {
            weight: w.as_tensor().clone(),
            ..bn.clone()
        };
        let x = Var::from_tensor(&Tensor::from_vec(values(3 * 5 * 7, 4), (3, 5, 7), &dev).unwrap())
            .unwrap();
        let g = Tensor::from_vec(values(3 * 5 * 7, 5), (3, 5, 7), &dev).unwrap();
        let y = if fused {
            bnw.forward_leaky_relu(&x, train, 0.2).unwrap()
        } else {
            let t = bnw.forward_t(&x, train).unwrap();
            t.maximum(&(&t * 0.2).unwrap()).unwrap()
        };
        let grads = (&y * &g).unwrap().sum_all().unwrap().backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        vec![
            flat(&y),
            flat(grads.get(x.as_tensor()).unwrap()),
            flat(grads.get(w.as_tensor()).unwrap()),
            flat(grads.get(&bnw.bias).unwrap()),
            flat(bnw.running_mean.as_tensor()),
            flat(bnw.running_var.as_tensor()),
        ]
    }

    #[test]
    fn fused_batch_norm_leaky_relu_matches_tensor_ops() {
        for train in [true, false] {
            let (a, b) = (run(true, train), run(false, train));
            for (i, (x, y)) in a.iter().zip(&b).enumerate() {
                for (u, v) in x.iter().zip(y) {
                    assert!(
                        (u - v).abs() <= 1e-4 * v.abs().max(1.0),
                        "train {train}, item {i}: {u} vs {v}"
                    );
                }
            }
        }
    }
}
