//! Normalisation kernels: layer norm over the last dimension, and batch norm followed by
//! LeakyReLU over channel-first `[B, C, L]` tensors (the DGCNN's), each a fused CPU op with a
//! hand-written backward pass beside its tensor-op reference. The layers that own the
//! parameters and running statistics are `ic_nn::norm::BatchNorm1` and `ic_pose`'s `LayerNorm`.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp3, D, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::cpu::{all_cpu_f32, f32_data, f32_slice, zeros_f32};

/// Layer normalisation over the last dimension of `x` (`[…, d]`) with weight and bias `[d]`:
/// `(x − mean)/√(var + eps)·w + b` (biased variance).
///
/// On the CPU with f32 one fused op (one pass per row; backward
/// `dx = (ĝ − mean(ĝ) − x̂·mean(ĝ·x̂))/σ` with `ĝ = g ∘ w`, from the kept row statistics);
/// elsewhere [`layer_norm_reference`].
pub fn layer_norm(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    if all_cpu_f32(&[x, w, b]) {
        return x.contiguous()?.apply_op3(
            &w.contiguous()?,
            &b.contiguous()?,
            FusedLayerNorm {
                eps: eps as f32,
                stats: Mutex::new(None),
            },
        );
    }
    layer_norm_reference(x, w, b, eps)
}

/// [`layer_norm`] from generic tensor ops (non-CPU devices, and the test oracle).
pub fn layer_norm_reference(x: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    xc.broadcast_div(&(var + eps)?.sqrt()?)?
        .broadcast_mul(w)?
        .broadcast_add(b)
}

/// (mean, variance) of each channel, in channel order.
pub type ChannelMoments = Vec<(f32, f32)>;

/// `LeakyReLU(BN(x))` for `x` `[B, C, L]` (f32 on the CPU) with weight and bias `[C]` and
/// negative slope `slope` (≥ 0; 0 is the ReLU), as one fused op (forward and backward one pass per channel).
///
/// With `running` = the (mean, variance) of each channel (inference) those normalise;
/// without (training), the batch statistics over B·L values per channel (computed in f64,
/// biased variance), which are returned beside the output for the running-statistics update.
/// The tensor-op version is `ic_nn::norm::BatchNorm1::forward_t` followed by
/// `max(y, slope·y)` (the test compares them).
pub fn batch_norm_leaky_relu(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    running: Option<ChannelMoments>,
    eps: f32,
    slope: f32,
) -> Result<(Tensor, Option<ChannelMoments>)> {
    let training = running.is_none();
    let kept = Arc::new(Mutex::new(None));
    let op = BnLeaky {
        eps,
        slope,
        fixed: running,
        batch: kept.clone(),
    };
    let y = x
        .contiguous()?
        .apply_op3(&weight.contiguous()?, &bias.contiguous()?, op)?;
    if !training {
        return Ok((y, None));
    }
    let batch = kept.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let Some(batch) = batch else {
        candle_core::bail!("batch norm: the fused op kept no statistics")
    };
    Ok((y, Some(batch.to_vec())))
}

/// Rows per rayon task of the row-wise kernels.
const ROWS_PER_TASK: usize = 64;

/// (mean, 1/σ) per row.
type RowStats = Arc<Vec<(f32, f32)>>;

/// LayerNorm over the last dimension in one pass per row; keeps each row's mean and 1/σ for
/// the backward pass `dx = (ĝ − mean(ĝ) − x̂·mean(ĝ·x̂))/σ` with `ĝ = g ∘ w`.
struct FusedLayerNorm {
    eps: f32,
    stats: Mutex<Option<RowStats>>,
}

impl FusedLayerNorm {
    fn stats(&self, x: &[f32], d: usize) -> Vec<(f32, f32)> {
        x.par_chunks(d * ROWS_PER_TASK)
            .flat_map_iter(|rows| {
                rows.chunks_exact(d).map(|r| {
                    let mean = r.iter().sum::<f32>() / d as f32;
                    let var = r.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
                    (mean, 1.0 / (var + self.eps).sqrt())
                })
            })
            .collect()
    }
}

impl CustomOp3 for FusedLayerNorm {
    fn name(&self) -> &'static str {
        "ic-layer-norm"
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
        let d = *l1.shape().dims().last().unwrap_or(&0);
        if d == 0 || l2.shape().dims1()? != d || l3.shape().dims1()? != d {
            candle_core::bail!(
                "layer_norm: x {:?}, w {:?}, b {:?}",
                l1.shape(),
                l2.shape(),
                l3.shape()
            );
        }
        let (x, w, b) = (
            f32_slice(s1, l1, "layer_norm x")?,
            f32_slice(s2, l2, "layer_norm w")?,
            f32_slice(s3, l3, "layer_norm b")?,
        );
        let stats = self.stats(x, d);
        let mut y = zeros_f32(x.len());
        y.par_chunks_mut(d * ROWS_PER_TASK)
            .zip(x.par_chunks(d * ROWS_PER_TASK))
            .zip(stats.par_chunks(ROWS_PER_TASK))
            .for_each(|((yc, xc), sc)| {
                for ((yr, xr), &(mean, rstd)) in
                    yc.chunks_exact_mut(d).zip(xc.chunks_exact(d)).zip(sc)
                {
                    for (((o, &v), &wi), &bi) in yr.iter_mut().zip(xr).zip(w).zip(b) {
                        *o = (v - mean) * rstd * wi + bi;
                    }
                }
            });
        *self.stats.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(stats));
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = w.dim(0)?;
        let (xv, wv, g) = (f32_data(x)?, f32_data(w)?, f32_data(grad)?);
        let cached = self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let stats = match cached {
            Some(s) => s,
            None => Arc::new(self.stats(&xv, d)),
        };
        let mut dx = zeros_f32(xv.len());
        let partials: Vec<(Vec<f32>, Vec<f32>)> = dx
            .par_chunks_mut(d * ROWS_PER_TASK)
            .zip(xv.par_chunks(d * ROWS_PER_TASK))
            .zip(g.par_chunks(d * ROWS_PER_TASK))
            .zip(stats.par_chunks(ROWS_PER_TASK))
            .map(|(((dxc, xc), gc), sc)| {
                let mut dw = vec![0.0f32; d];
                let mut db = vec![0.0f32; d];
                let mut xhat = vec![0.0f32; d];
                for (((dxr, xr), gr), &(mean, rstd)) in dxc
                    .chunks_exact_mut(d)
                    .zip(xc.chunks_exact(d))
                    .zip(gc.chunks_exact(d))
                    .zip(sc)
                {
                    let (mut sg, mut sgx) = (0.0f32, 0.0f32);
                    for i in 0..d {
                        let xh = (xr[i] - mean) * rstd;
                        xhat[i] = xh;
                        let gh = gr[i] * wv[i];
                        sg += gh;
                        sgx += gh * xh;
                        dw[i] += gr[i] * xh;
                        db[i] += gr[i];
                    }
                    let (mg, mgx) = (sg / d as f32, sgx / d as f32);
                    for i in 0..d {
                        dxr[i] = (gr[i] * wv[i] - mg - xhat[i] * mgx) * rstd;
                    }
                }
                (dw, db)
            })
            .collect();
        let mut dw = vec![0.0f32; d];
        let mut db = vec![0.0f32; d];
        for (pw, pb) in &partials {
            for i in 0..d {
                dw[i] += pw[i];
                db[i] += pb[i];
            }
        }
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, x.shape(), dev)?),
            Some(Tensor::from_vec(dw, d, dev)?),
            Some(Tensor::from_vec(db, d, dev)?),
        ))
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

/// `y = LeakyReLU(x·scale + shift)` over one row. Both branches are computed and selected:
/// the sign of `t` is data, and a branch on it mispredicts about every other element (the
/// scalar, branching loop took most of the encoder's BN time); the select vectorises.
#[inline]
fn leaky_affine(y: &mut [f32], x: &[f32], scale: f32, shift: f32, slope: f32) {
    for (o, &v) in y.iter_mut().zip(x) {
        let t = v * scale + shift;
        let neg = t * slope;
        *o = if t > 0.0 { t } else { neg };
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
        let mut y = zeros_f32(x.len());
        let slope = self.slope;
        y.par_chunks_mut(l)
            .zip(x.par_chunks(l))
            .enumerate()
            .for_each(|(row, (yr, xr))| {
                let ch = row % c;
                let (mean, var) = stats[ch];
                let scale = w[ch] / (var + self.eps).sqrt();
                let shift = bias[ch] - mean * scale;
                leaky_affine(yr, xr, scale, shift, slope);
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
        let flat = f32_data;
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
        let mut dx = zeros_f32(b * c * l);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::norm::BatchNorm1;
    use candle_core::{DType, Device, Var};
    use candle_nn::{VarBuilder, VarMap};

    use crate::ops::test_values as values;

    /// Output, input/γ/β gradients and running statistics of `LeakyReLU(BN(x))`, fused or from
    /// tensor ops, in training or inference mode.
    fn run(fused: bool, train: bool, slope: f32) -> Vec<Vec<f32>> {
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
            bnw.forward_leaky_relu(&x, train, slope).unwrap()
        } else {
            let t = bnw.forward_t(&x, train).unwrap();
            t.maximum(&(&t * slope as f64).unwrap()).unwrap()
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
        // Slope 0 is the ReLU of the segmentation network's blocks.
        for (train, slope) in [(true, 0.2), (false, 0.2), (true, 0.0), (false, 0.0)] {
            let (a, b) = (run(true, train, slope), run(false, train, slope));
            for (i, (x, y)) in a.iter().zip(&b).enumerate() {
                for (u, v) in x.iter().zip(y) {
                    assert!(
                        (u - v).abs() <= 1e-4 * v.abs().max(1.0),
                        "train {train}, slope {slope}, item {i}: {u} vs {v}"
                    );
                }
            }
        }
    }
}
