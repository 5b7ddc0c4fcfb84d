//! Small building blocks with a backward pass for every parameter (candle-nn 0.11's fused
//! `layer_norm` and `softmax_last_dim` silently have none).
//!
//! [`Dense`] and [`LayerNorm`] own their parameters and call the fused CPU kernels of
//! [`ic_nn::ops`] (`dense`, `layer_norm`: hand-written backward passes, because candle's
//! generic backward of a broadcast bias or of a per-channel scale reduces over non-last
//! dimensions and allocates one tensor per elementary op, which made the backward pass 3.5×
//! the forward); the kernels' tensor-op versions remain as references (other devices, and the
//! tests).

use candle_core::{Module, Result, Tensor};
use candle_nn::{Init, VarBuilder};
use ic_nn::ops::{dense, norm};

pub use ic_nn::ops::dense::channel_linear;
pub use ic_nn::ops::softmax::{log_softmax_last, softmax_last};

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
        dense::dense(x, &self.weight, self.bias.as_ref(), relu)
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
        norm::layer_norm(x, &self.weight, &self.bias, self.eps)
    }
}

impl LayerNorm {
    /// The same function from generic tensor ops (non-CPU devices, and the test oracle).
    pub fn forward_reference(&self, x: &Tensor) -> Result<Tensor> {
        norm::layer_norm_reference(x, &self.weight, &self.bias, self.eps)
    }
}
