//! Small building blocks written from plain tensor ops, so that every parameter has a backward
//! pass (candle-nn 0.11's fused `layer_norm` and `softmax_last_dim` silently have none).

use candle_core::{D, Module, Result, Tensor};
use candle_nn::{Init, VarBuilder};

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

impl Module for Dense {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let (in_dims, lead) = match dims.split_last() {
            Some((&c, lead)) => (c, lead.to_vec()),
            None => candle_core::bail!("Dense on a scalar"),
        };
        let rows: usize = lead.iter().product();
        let y = x.reshape((rows, in_dims))?.matmul(&self.weight.t()?)?;
        let y = match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        };
        let mut out = lead;
        out.push(self.weight.dim(0)?);
        y.reshape(out)
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
        let src = match storage {
            candle_core::CpuStorage::F32(v) => v,
            _ => candle_core::bail!("softmax_last: f32 only"),
        };
        let Some((start, end)) = layout.contiguous_offsets() else {
            candle_core::bail!("softmax_last: contiguous input required")
        };
        let src = &src[start..end];
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
