//! `ic_seg` — finds the object in the depth map, the paper's first module.
//!
//! - [`unet::UNet`]: a compact U-Net on normalised depth (two input channels, or five with
//!   surface normals, see [`input`]) giving one object logit per pixel; it stands in for the paper's YOLACT, which
//!   needs ImageNet weights that cannot be fetched here (`docs/ARCHITECTURE.md` says how the
//!   two differ).
//! - [`infer::FoldedUNet`]: the same network for inference on the CPU, batch norms folded
//!   into the convolutions, im2col + GEMM on strips of the image (what [`Segmenter`] runs).
//! - [`post`]: the paper's post-processing — threshold, 8-connected components scored by
//!   their mean probability, the best instance, 3×3 erosion, back-projection, the crop to
//!   1.2 normalised units around the masked points' centre.
//! - [`Segmenter`]: the inference API, any resolution in, a full-resolution mask out, or a
//!   typed [`SegError::ObjectNotFound`].
//! - [`SegExample`], [`seg_loss`]: what training needs of the network (the trainer itself,
//!   seeded and resumable, is `ic_train::SegTrainer`).
//! - [`geometric`]: RANSAC plane removal + Euclidean clustering, no network.
//!
//! It knows nothing about pose.
//!
//! ```
//! use ic_geometry::{DepthImage, Intrinsics, Mask};
//! use ic_seg::{SegConfig, SegExample, Segmenter, seg_loss, unet::UNet};
//! // A tiny network with seeded weights on a synthetic depth map: a square in front of a wall.
//! let cfg = SegConfig::tiny();
//! let mut depth = DepthImage::filled(64, 48, 3.0);
//! let mut mask = Mask::filled(64, 48, false);
//! for v in 16..32 { for u in 24..40 { depth.data[v * 64 + u] = 2.0; mask.data[v * 64 + u] = true; } }
//! let k = Intrinsics::new(60.0, 60.0, 31.5, 23.5, 64, 48)?;
//! let example = SegExample::new(&depth, &k, &mask, &cfg)?;
//! assert_eq!(example.target.len(), (cfg.net.input_width * cfg.net.input_height) as usize);
//! let varmap = candle_nn::VarMap::new();
//! let device = candle_core::Device::Cpu;
//! let net = UNet::new(ic_nn::seeded_var_builder(&varmap, 7, &device), &cfg.net)?;
//! let segmenter = Segmenter::from_parts(net, cfg);
//! // Untrained, the object may or may not be found; either answer is typed.
//! match segmenter.segment(&depth, &k) {
//!     Ok(seg) => assert_eq!(seg.mask.width, 64),
//!     Err(ic_seg::SegError::ObjectNotFound { .. }) => {}
//!     Err(e) => return Err(e.into()),
//! }
//! # let _ = seg_loss;
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

// `!(x > 0.0)` deliberately rejects NaN as well.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod centres;
pub mod checkpoint;
pub mod config;
mod error;
pub mod geometric;
pub mod infer;
pub mod input;
pub mod post;
pub mod segmenter;
pub mod support;
pub mod train;
pub mod unet;

pub use config::{PostConfig, SegConfig, SegInput, SegTrainConfig, UNetConfig};
pub use error::{Result, SegError};
pub use geometric::{GeometricConfig, GeometricSegmentation, segment_geometric};
pub use segmenter::{Segmentation, Segmenter, TRAINING_CAMERA};
pub use support::{SupportConfig, SupportPlane};
pub use train::{SegExample, seg_loss};
