//! `ic_nn` — the training utilities that incontext's two networks (`ic_seg`, `ic_pose`) share,
//! so that neither depends on the other.
//!
//! - [`seeded_var_builder`]: a `VarBuilder` whose random initialisers draw from a seeded
//!   ChaCha8 generator (candle's CPU initialisers are unseeded);
//! - [`adam::Adam`]: Adam with its moments exposed, so a resumed run continues to the same
//!   numbers;
//! - [`norm::BatchNorm1`] / [`norm::BatchNorm2`]: batch normalisation laid out for fast
//!   last-dimension reductions, running statistics stored beside the weights;
//! - [`checkpoint`]: atomic safetensors writing with string metadata, and a header-only reader;
//! - [`ops`]: the fused CPU kernels of both networks (attention, dense, layer and batch norm,
//!   softmax, the EdgeConv gather-max, the `gemm` wrapper and SIMD micro-kernels), each beside
//!   its tensor-op reference.
//!
//! ```
//! use candle_core::{Device, Tensor};
//! use candle_nn::VarMap;
//! let map = VarMap::new();
//! let vb = ic_nn::seeded_var_builder(&map, 7, &Device::Cpu);
//! let bn = ic_nn::norm::BatchNorm1::new(vb.pp("bn"), 3, 0.1)?;
//! let x = Tensor::ones((2, 3, 5), candle_core::DType::F32, &Device::Cpu)?;
//! assert_eq!(bn.forward_t(&x, true)?.dims(), &[2, 3, 5]);
//! # Ok::<(), candle_core::Error>(())
//! ```

pub mod adam;
pub mod checkpoint;
pub mod norm;
pub mod ops;
mod params;

pub use checkpoint::CheckpointError;
pub use params::seeded_var_builder;
