//! Dense products with hand-written backward passes: `x·Wᵀ + b` (+ ReLU) over the last
//! dimension, and the 1×1 channel convolution `W·x[b]` of channel-first tensors.
//!
//! On the CPU with f32 both are fused custom ops: candle's generic backward of a broadcast bias
//! reduces over non-last dimensions and allocates one tensor per elementary op, and its
//! broadcast matmul reduces `dW` over the batch with a slow non-last-dimension sum. The
//! tensor-op versions ([`dense_reference`], [`channel_linear_reference`]) run elsewhere and are
//! the oracles of the tests.

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::cpu::{all_cpu_f32, f32_data, f32_slice, zeros_f32};
use super::fastmath::matmul_par;
use super::{MatMut, MatRef};

/// `y = x·Wᵀ + b` (then `ReLU` with `relu`) over the last dimension of `x` (any rank ≥ 1,
/// `[…, in]`) for `W` `[out, in]` and `b` `[out]`: `[…, out]`. The leading dimensions are
/// flattened into one matrix product (faster than candle's broadcast matmul).
///
/// On the CPU with f32 and a bias, one fused op (a GEMM into a bias-filled output, ReLU in
/// place; backward `dx = g·W`, `dW = gᵀ·x`, `db = Σ_rows g` with `g` zeroed where the ReLU
/// output is 0); otherwise [`dense_reference`]'s tensor ops.
pub fn dense(x: &Tensor, w: &Tensor, b: Option<&Tensor>, relu: bool) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (in_dims, lead) = match dims.split_last() {
        Some((&c, lead)) => (c, lead.to_vec()),
        None => candle_core::bail!("Dense on a scalar"),
    };
    let rows: usize = lead.iter().product();
    let x2 = x.reshape((rows, in_dims))?;
    let y = match b {
        Some(b) if all_cpu_f32(&[&x2, w, b]) => {
            x2.contiguous()?
                .apply_op3(&w.contiguous()?, &b.contiguous()?, FusedDense { relu })?
        }
        bias => dense_2d_reference(&x2, w, bias, relu)?,
    };
    let mut out = lead;
    out.push(w.dim(0)?);
    y.reshape(out)
}

/// [`dense`] from tensor ops (`matmul`, `broadcast_add`, `relu`): other devices and dtypes, and
/// the test oracle.
pub fn dense_reference(x: &Tensor, w: &Tensor, b: Option<&Tensor>, relu: bool) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (in_dims, lead) = match dims.split_last() {
        Some((&c, lead)) => (c, lead.to_vec()),
        None => candle_core::bail!("Dense on a scalar"),
    };
    let rows: usize = lead.iter().product();
    let y = dense_2d_reference(&x.reshape((rows, in_dims))?, w, b, relu)?;
    let mut out = lead;
    out.push(w.dim(0)?);
    y.reshape(out)
}

/// The tensor-op dense layer on `[rows, in]`.
fn dense_2d_reference(x2: &Tensor, w: &Tensor, b: Option<&Tensor>, relu: bool) -> Result<Tensor> {
    let y = x2.matmul(&w.t()?)?;
    let y = match b {
        Some(b) => y.broadcast_add(b)?,
        None => y,
    };
    if relu { y.relu() } else { Ok(y) }
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
        // y starts as the bias in every row (written in parallel), the product is added to it
        // (the same numbers as a serial fill), then the ReLU.
        let mut y = zeros_f32(rows * out_dims);
        // Tasks of about 4 096 values, whole rows (none without outputs).
        if let Some(per_task) = (1usize << 12).checked_div(out_dims) {
            y.par_chunks_mut(out_dims * (per_task + 1)).for_each(|c| {
                for row in c.chunks_exact_mut(out_dims) {
                    row.copy_from_slice(b);
                }
            });
        }
        matmul_par(
            MatRef::new(x, rows, in_dims, in_dims),
            MatRef::new(w, out_dims, in_dims, in_dims).t(),
            MatMut::new(&mut y, rows, out_dims, out_dims),
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
        let (xv, wv, gv) = (f32_data(x)?, f32_data(w)?, f32_data(grad)?);
        let masked: Vec<f32>;
        let g: &[f32] = if self.relu {
            // The gradient through the ReLU, written in parallel into a new buffer.
            let y = f32_data(res)?;
            masked = gv
                .par_iter()
                .zip(y.par_iter())
                .map(|(&gv, &yv)| if yv <= 0.0 { 0.0 } else { gv })
                .collect();
            &masked
        } else {
            &gv
        };
        let gm = MatRef::new(g, rows, out_dims, out_dims);
        let mut dx = zeros_f32(rows * in_dims);
        matmul_par(
            gm,
            MatRef::new(&wv, out_dims, in_dims, in_dims),
            MatMut::new(&mut dx, rows, in_dims, in_dims),
            false,
        );
        let mut dw = vec![0.0f32; out_dims * in_dims];
        matmul_par(
            gm.t(),
            MatRef::new(&xv, rows, in_dims, in_dims),
            MatMut::new(&mut dw, out_dims, in_dims, in_dims),
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
    if all_cpu_f32(&[w, x]) {
        return w.contiguous()?.apply_op2(&x.contiguous()?, ChannelLinear);
    }
    w.broadcast_left(b)?.matmul(x)
}

/// [`channel_linear`] from candle's broadcast matmul: the test oracle.
pub fn channel_linear_reference(w: &Tensor, x: &Tensor) -> Result<Tensor> {
    let (b, _, _) = x.dims3()?;
    w.broadcast_left(b)?.matmul(x)
}

struct ChannelLinear;

impl CustomOp2 for ChannelLinear {
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
        let mut y = zeros_f32(b * co * p);
        for (yb, xb) in y.chunks_exact_mut(co * p).zip(x.chunks_exact(c * p)) {
            matmul_par(
                MatRef::new(w, co, c, c),
                MatRef::new(xb, c, p, p),
                MatMut::new(yb, co, p, p),
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
        let (wv, xv, g) = (f32_data(w)?, f32_data(x)?, f32_data(grad)?);
        let wm = MatRef::new(&wv, co, c, c);
        let mut dx = zeros_f32(b * c * p);
        let mut dw = vec![0.0f32; co * c];
        for (bi, (dxb, gb)) in dx
            .chunks_exact_mut(c * p)
            .zip(g.chunks_exact(co * p))
            .enumerate()
        {
            let gm = MatRef::new(gb, co, p, p);
            matmul_par(wm.t(), gm, MatMut::new(dxb, c, p, p), false);
            let xm = MatRef::new(&xv[bi * c * p..(bi + 1) * c * p], c, p, p);
            matmul_par(gm, xm.t(), MatMut::new(&mut dw, co, c, c), bi > 0);
        }
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dw, (co, c), dev)?),
            Some(Tensor::from_vec(dx, (b, c, p), dev)?),
        ))
    }
}
