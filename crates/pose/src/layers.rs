//! Small building blocks with a backward pass for every parameter (candle-nn 0.11's fused
//! `layer_norm` and `softmax_last_dim` silently have none).
//!
//! On the CPU with f32, [`Dense`] (with bias) and [`LayerNorm`] run as fused custom ops with
//! hand-written backward passes: candle's generic backward of a broadcast bias or of a
//! per-channel scale reduces over non-last dimensions and allocates one tensor per elementary
//! op, which made the backward pass 3.5× the forward. The tensor-op versions remain as
//! references (other devices, and the tests).

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp3, D, Layout, Module, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::fastmath::{MatRef, matmul_par};
use candle_nn::{Init, VarBuilder};
use ic_nn::cpu::{all_cpu_f32 as cpu_f32, f32_slice, to_f32_vec};

/// A dense layer `y = x·Wᵀ + b` over the last dimension of a tensor of any rank. The leading
/// dimensions are flattened into one matrix product (faster than candle's broadcast matmul).
#[derive(Clone, Debug)]
pub struct Dense {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl Dense {
    pub fn new(vb: VarBuilder, in_dims: usize, out_dims: usize, bias: bool) -> Result<Self> {
        Self::build(vb, in_dims, out_dims, in_dims, bias)
    }

    /// No bias; weights initialised as if the layer had `fan_in` inputs.
    pub fn with_fan_in(
        vb: VarBuilder,
        in_dims: usize,
        out_dims: usize,
        fan_in: usize,
    ) -> Result<Self> {
        Self::build(vb, in_dims, out_dims, fan_in, false)
    }

    fn build(
        vb: VarBuilder,
        in_dims: usize,
        out_dims: usize,
        fan_in: usize,
        bias: bool,
    ) -> Result<Self> {
        let bound = 1.0 / (fan_in as f64).sqrt();
        let init = Init::Uniform {
            lo: -bound,
            up: bound,
        };
        let weight = vb.get_with_hints((out_dims, in_dims), "weight", init)?;
        let bias = if bias {
            Some(vb.get_with_hints(out_dims, "bias", init)?)
        } else {
            None
        };
        Ok(Dense { weight, bias })
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }
}

impl Dense {
    /// `ReLU(x·Wᵀ + b)`, fused into the product on the CPU.
    pub fn forward_relu(&self, x: &Tensor) -> Result<Tensor> {
        self.apply(x, true)
    }

    fn apply(&self, x: &Tensor, relu: bool) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let (in_dims, lead) = match dims.split_last() {
            Some((&c, lead)) => (c, lead.to_vec()),
            None => candle_core::bail!("Dense on a scalar"),
        };
        let rows: usize = lead.iter().product();
        let x2 = x.reshape((rows, in_dims))?;
        let y = match &self.bias {
            Some(b) if cpu_f32(&[&x2, &self.weight, b]) => x2.contiguous()?.apply_op3(
                &self.weight.contiguous()?,
                &b.contiguous()?,
                FusedDense { relu },
            )?,
            bias => {
                let y = x2.matmul(&self.weight.t()?)?;
                let y = match bias {
                    Some(b) => y.broadcast_add(b)?,
                    None => y,
                };
                if relu { y.relu()? } else { y }
            }
        };
        let mut out = lead;
        out.push(self.weight.dim(0)?);
        y.reshape(out)
    }
}

impl Module for Dense {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.apply(x, false)
    }
}

/// Layer normalisation over the last dimension, from tensor ops (differentiable).
#[derive(Clone, Debug)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    pub fn new(vb: VarBuilder, dims: usize) -> Result<Self> {
        Ok(LayerNorm {
            weight: vb.get_with_hints(dims, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(dims, "bias", Init::Const(0.0))?,
            eps: 1e-5,
        })
    }
}

impl Module for LayerNorm {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if cpu_f32(&[x, &self.weight, &self.bias]) {
            return x.contiguous()?.apply_op3(
                &self.weight.contiguous()?,
                &self.bias.contiguous()?,
                FusedLayerNorm {
                    eps: self.eps as f32,
                    stats: Mutex::new(None),
                },
            );
        }
        self.forward_reference(x)
    }
}

impl LayerNorm {
    /// The same function from generic tensor ops (non-CPU devices, and the test oracle).
    pub fn forward_reference(&self, x: &Tensor) -> Result<Tensor> {
        let mean = x.mean_keepdim(D::Minus1)?;
        let xc = x.broadcast_sub(&mean)?;
        let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
        xc.broadcast_div(&(var + self.eps)?.sqrt()?)?
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)
    }
}

/// log-softmax over the last dimension with the max detached (its gradient is exact and no
/// gradient flows through the max).
pub fn log_softmax_last(x: &Tensor) -> Result<Tensor> {
    let m = x.max_keepdim(D::Minus1)?.detach();
    let d = x.broadcast_sub(&m)?;
    let lse = d.exp()?.sum_keepdim(D::Minus1)?.log()?;
    d.broadcast_sub(&lse)
}

/// Softmax over the last dimension: one fused pass forward (a custom op), and the exact
/// backward `∂x = y ⊙ (g − Σ g ⊙ y)` from tensor ops. On CPU f32 contiguous input; other
/// inputs fall back to the tensor-op version.
pub fn softmax_last(x: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == candle_core::DType::F32 {
        x.contiguous()?.apply_op1(SoftmaxLast)
    } else {
        let m = x.max_keepdim(D::Minus1)?.detach();
        let e = x.broadcast_sub(&m)?.exp()?;
        e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
    }
}

struct SoftmaxLast;

impl candle_core::CustomOp1 for SoftmaxLast {
    fn name(&self) -> &'static str {
        "ic-softmax-last"
    }

    fn cpu_fwd(
        &self,
        storage: &candle_core::CpuStorage,
        layout: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let src = f32_slice(storage, layout, "softmax_last")?;
        let dims = layout.shape().dims();
        let n = *dims.last().unwrap_or(&1);
        let mut dst = vec![0f32; src.len()];
        if n > 0 {
            for (row, out) in src.chunks_exact(n).zip(dst.chunks_exact_mut(n)) {
                let m = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let mut sum = 0f32;
                for (o, &v) in out.iter_mut().zip(row) {
                    let e = (v - m).exp();
                    *o = e;
                    sum += e;
                }
                let inv = 1.0 / sum;
                for o in out.iter_mut() {
                    *o *= inv;
                }
            }
        }
        Ok((candle_core::CpuStorage::F32(dst), layout.shape().clone()))
    }

    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let gy = (grad_res * res)?;
        let s = gy.sum_keepdim(D::Minus1)?;
        Ok(Some((gy - res.broadcast_mul(&s)?)?))
    }
}

/// `y = x·Wᵀ + b` (then ReLU with `relu`) for `x` `[rows, in]`, `W` `[out, in]`, `b` `[out]`:
/// one GEMM into a bias-filled output; backward `dx = g·W`, `dW = gᵀ·x`, `db = Σ_rows g` with
/// `g` zeroed where the ReLU output is 0.
struct FusedDense {
    relu: bool,
}

impl CustomOp3 for FusedDense {
    fn name(&self) -> &'static str {
        "ic-dense"
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
        let (rows, in_dims) = l1.shape().dims2()?;
        let (out_dims, w_in) = l2.shape().dims2()?;
        if w_in != in_dims || l3.shape().dims1()? != out_dims {
            candle_core::bail!(
                "dense: x {:?}, W {:?}, b {:?}",
                l1.shape(),
                l2.shape(),
                l3.shape()
            );
        }
        let (x, w, b) = (
            f32_slice(s1, l1, "dense x")?,
            f32_slice(s2, l2, "dense W")?,
            f32_slice(s3, l3, "dense b")?,
        );
        let mut y = Vec::with_capacity(rows * out_dims);
        for _ in 0..rows {
            y.extend_from_slice(b);
        }
        matmul_par(
            MatRef::rows(x, rows, in_dims, in_dims),
            MatRef::rows(w, out_dims, in_dims, in_dims).t(),
            &mut y,
            out_dims,
            true,
        );
        if self.relu {
            y.par_chunks_mut(1 << 14)
                .for_each(|c| c.iter_mut().for_each(|v| *v = v.max(0.0)));
        }
        Ok((CpuStorage::F32(y), Shape::from((rows, out_dims))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (rows, in_dims) = x.dims2()?;
        let out_dims = w.dim(0)?;
        let (xv, wv, mut g) = (to_f32_vec(x)?, to_f32_vec(w)?, to_f32_vec(grad)?);
        if self.relu {
            let y = to_f32_vec(res)?;
            g.par_chunks_mut(1 << 14)
                .zip(y.par_chunks(1 << 14))
                .for_each(|(gc, yc)| {
                    for (gv, &yv) in gc.iter_mut().zip(yc) {
                        if yv <= 0.0 {
                            *gv = 0.0;
                        }
                    }
                });
        }
        let gm = MatRef::rows(&g, rows, out_dims, out_dims);
        let mut dx = vec![0.0f32; rows * in_dims];
        matmul_par(
            gm,
            MatRef::rows(&wv, out_dims, in_dims, in_dims),
            &mut dx,
            in_dims,
            false,
        );
        let mut dw = vec![0.0f32; out_dims * in_dims];
        matmul_par(
            gm.t(),
            MatRef::rows(&xv, rows, in_dims, in_dims),
            &mut dw,
            in_dims,
            false,
        );
        let mut db = vec![0.0f32; out_dims];
        for row in g.chunks_exact(out_dims) {
            for (d, &v) in db.iter_mut().zip(row) {
                *d += v;
            }
        }
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, (rows, in_dims), dev)?),
            Some(Tensor::from_vec(dw, (out_dims, in_dims), dev)?),
            Some(Tensor::from_vec(db, out_dims, dev)?),
        ))
    }
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
        let mut y = vec![0.0f32; x.len()];
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
        let (xv, wv, g) = (to_f32_vec(x)?, to_f32_vec(w)?, to_f32_vec(grad)?);
        let cached = self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let stats = match cached {
            Some(s) => s,
            None => Arc::new(self.stats(&xv, d)),
        };
        let mut dx = vec![0.0f32; xv.len()];
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

/// `y[b] = W·x[b]` for `W` `[C', C]` and channel-first `x` `[B, C, P]` (a 1×1 convolution):
/// `[B, C', P]`. On the CPU with f32 one GEMM per pair, with the backward `dx[b] = Wᵀ·g[b]`,
/// `dW = Σ_b g[b]·x[b]ᵀ` (candle's broadcast matmul reduces `dW` over the batch dimension
/// with a slow non-last-dimension sum); elsewhere candle's broadcast matmul.
pub fn channel_linear(w: &Tensor, x: &Tensor) -> Result<Tensor> {
    let (b, c, _) = x.dims3()?;
    let (_, wc) = w.dims2()?;
    if wc != c {
        candle_core::bail!("channel_linear: W {:?} for x {:?}", w.dims(), x.dims());
    }
    if cpu_f32(&[w, x]) {
        return w.contiguous()?.apply_op2(&x.contiguous()?, ChannelLinear);
    }
    w.broadcast_left(b)?.matmul(x)
}

struct ChannelLinear;

impl candle_core::CustomOp2 for ChannelLinear {
    fn name(&self) -> &'static str {
        "ic-channel-linear"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (co, c) = l1.shape().dims2()?;
        let (b, _, p) = l2.shape().dims3()?;
        let (w, x) = (
            f32_slice(s1, l1, "channel_linear W")?,
            f32_slice(s2, l2, "channel_linear x")?,
        );
        let mut y = vec![0.0f32; b * co * p];
        for (yb, xb) in y.chunks_exact_mut(co * p).zip(x.chunks_exact(c * p)) {
            matmul_par(
                MatRef::rows(w, co, c, c),
                MatRef::rows(xb, c, p, p),
                yb,
                p,
                false,
            );
        }
        Ok((CpuStorage::F32(y), Shape::from((b, co, p))))
    }

    fn bwd(
        &self,
        w: &Tensor,
        x: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (co, c) = w.dims2()?;
        let (b, _, p) = x.dims3()?;
        let (wv, xv, g) = (to_f32_vec(w)?, to_f32_vec(x)?, to_f32_vec(grad)?);
        let wm = MatRef::rows(&wv, co, c, c);
        let mut dx = vec![0.0f32; b * c * p];
        let mut dw = vec![0.0f32; co * c];
        for (bi, (dxb, gb)) in dx
            .chunks_exact_mut(c * p)
            .zip(g.chunks_exact(co * p))
            .enumerate()
        {
            let gm = MatRef::rows(gb, co, p, p);
            matmul_par(wm.t(), gm, dxb, p, false);
            let xm = MatRef::rows(&xv[bi * c * p..(bi + 1) * c * p], c, p, p);
            matmul_par(gm, xm.t(), &mut dw, c, bi > 0);
        }
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dw, (co, c), dev)?),
            Some(Tensor::from_vec(dx, (b, c, p), dev)?),
        ))
    }
}
