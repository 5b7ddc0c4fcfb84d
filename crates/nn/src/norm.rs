//! Batch normalisation for channel-first tensors (the layers: parameters and running
//! statistics; the fused BN + LeakyReLU kernel is [`crate::ops::norm::batch_norm_leaky_relu`]).

use candle_core::{DType, Result, Tensor, Var};
use candle_nn::{Init, VarBuilder};

/// Batch normalisation for channel-first tensors `[B, C, L]`: statistics over B and L.
///
/// Reduces over the last dimension first (fast in candle), then over the small batch
/// dimension, instead of candle-nn's transpose-and-copy. The running statistics live in the
/// `VarMap` as `running_mean` / `running_var` (no gradient) and are saved with the weights.
#[derive(Clone, Debug)]
pub struct BatchNorm1 {
    pub(crate) weight: Tensor,
    pub(crate) bias: Tensor,
    pub(crate) running_mean: Var,
    pub(crate) running_var: Var,
    pub(crate) momentum: f64,
    pub(crate) eps: f64,
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
    /// The inference-mode normalisation as a per-channel affine map `y = scale·x + shift`
    /// (running statistics): what [`Self::forward_t`] computes with `train` false, for folding
    /// into a preceding linear layer.
    pub fn inference_affine(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        let w = self.weight.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        let b = self.bias.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        let rm = self
            .running_mean
            .as_detached_tensor()
            .to_dtype(DType::F32)?
            .to_vec1::<f32>()?;
        let rv = self
            .running_var
            .as_detached_tensor()
            .to_dtype(DType::F32)?
            .to_vec1::<f32>()?;
        let scale: Vec<f32> = w
            .iter()
            .zip(&rv)
            .map(|(w, v)| w / (v + self.eps as f32).sqrt())
            .collect();
        let shift = b
            .iter()
            .zip(&rm)
            .zip(&scale)
            .map(|((b, m), s)| b - m * s)
            .collect();
        Ok((scale, shift))
    }

    /// `LeakyReLU(BN(x))` with negative slope `slope` (≥ 0; 0 is the ReLU): the same function as
    /// [`Self::forward_t`] followed by `max(y, slope·y)`, and the same running-statistics update.
    ///
    /// On the CPU with f32 one fused op (forward and backward, one pass per channel) instead of
    /// about fifteen tensor ops whose backward reduces over the non-last batch dimension; the
    /// batch statistics are computed in f32 over B·L values per channel.
    pub fn forward_leaky_relu(&self, x: &Tensor, train: bool, slope: f32) -> Result<Tensor> {
        let fused = x.device().is_cpu()
            && x.dtype() == DType::F32
            && self.weight.dtype() == DType::F32
            && slope >= 0.0;
        if !fused {
            let y = self.forward_t(x, train)?;
            return y.maximum(&(&y * slope as f64)?);
        }
        let (b, c, l) = x.dims3()?;
        let running = if train {
            None
        } else {
            let rm = self.running_mean.as_detached_tensor().to_vec1::<f32>()?;
            let rv = self.running_var.as_detached_tensor().to_vec1::<f32>()?;
            Some(rm.into_iter().zip(rv).collect())
        };
        let (y, batch) = crate::ops::norm::batch_norm_leaky_relu(
            x,
            &self.weight,
            &self.bias,
            running,
            self.eps as f32,
            slope,
        )?;
        if let Some(batch) = batch {
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

/// Batch normalisation for images `[B, C, H, W]`: [`BatchNorm1`] over the flattened pixels.
#[derive(Clone, Debug)]
pub struct BatchNorm2(BatchNorm1);

impl BatchNorm2 {
    pub fn new(vb: VarBuilder, channels: usize, momentum: f64) -> Result<Self> {
        Ok(BatchNorm2(BatchNorm1::new(vb, channels, momentum)?))
    }

    /// [`BatchNorm1::inference_affine`]: per-channel `(scale, shift)` of inference mode.
    pub fn inference_affine(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        self.0.inference_affine()
    }

    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        self.0
            .forward_t(&x.reshape((b, c, h * w))?, train)?
            .reshape((b, c, h, w))
    }

    /// `ReLU(BN(x))`: [`BatchNorm1::forward_leaky_relu`] with slope 0 over the flattened
    /// pixels (one fused op on the CPU with f32).
    pub fn forward_relu(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        self.0
            .forward_leaky_relu(&x.reshape((b, c, h * w))?, train, 0.0)?
            .reshape((b, c, h, w))
    }
}
