//! Softmax and log-softmax over the last dimension, with exact backward passes (candle-nn
//! 0.11's fused `softmax_last_dim` has none).

use candle_core::{CpuStorage, CustomOp1, D, DType, Layout, Result, Shape, Tensor};

use super::cpu::f32_slice;

/// log-softmax over the last dimension with the max detached (its gradient is exact and no
/// gradient flows through the max). Tensor ops only (any device and dtype).
pub fn log_softmax_last(x: &Tensor) -> Result<Tensor> {
    let m = x.max_keepdim(D::Minus1)?.detach();
    let d = x.broadcast_sub(&m)?;
    let lse = d.exp()?.sum_keepdim(D::Minus1)?.log()?;
    d.broadcast_sub(&lse)
}

/// Softmax over the last dimension: one fused pass forward (a custom op), and the exact
/// backward `∂x = y ⊙ (g − Σ g ⊙ y)` from tensor ops. On CPU f32 input; other inputs use
/// [`softmax_last_reference`].
pub fn softmax_last(x: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?.apply_op1(SoftmaxLast)
    } else {
        softmax_last_reference(x)
    }
}

/// [`softmax_last`] from tensor ops (max detached): other devices and dtypes, and the oracle.
pub fn softmax_last_reference(x: &Tensor) -> Result<Tensor> {
    let m = x.max_keepdim(D::Minus1)?.detach();
    let e = x.broadcast_sub(&m)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

struct SoftmaxLast;

impl CustomOp1 for SoftmaxLast {
    fn name(&self) -> &'static str {
        "ic-softmax-last"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
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
        Ok((CpuStorage::F32(dst), layout.shape().clone()))
    }

    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let gy = (grad_res * res)?;
        let s = gy.sum_keepdim(D::Minus1)?;
        Ok(Some((gy - res.broadcast_mul(&s)?)?))
    }
}
