//! Batch normalisation for channel-first tensors.

use candle_core::{Result, Tensor, Var};
use candle_nn::{Init, VarBuilder};

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
