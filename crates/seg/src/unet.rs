//! The instance-mask network: a compact U-Net on normalised depth.
//!
//! U-Net: Ronneberger et al., "U-Net: Convolutional Networks for Biomedical Image
//! Segmentation", MICCAI 2015 (<https://arxiv.org/abs/1505.04597>). Each level is two
//! 3×3 convolution + batch norm + ReLU blocks; the encoder halves the resolution with 2×2 max
//! pooling, the decoder doubles it with nearest-neighbour up-sampling and concatenates the
//! encoder's features of the same level. A 1×1 convolution gives one object logit per pixel.
//! It stands in for the paper's YOLACT (see `docs/ARCHITECTURE.md`).

use candle_core::{Result, Tensor};
use candle_nn::{Init, VarBuilder};
use ic_nn::norm::BatchNorm2;

use crate::config::UNetConfig;

/// A 2-D convolution with seeded Kaiming-uniform weights (`bound = √(6 / fan_in)`), stride 1.
#[derive(Clone, Debug)]
pub struct Conv2d {
    pub(crate) weight: Tensor,
    pub(crate) bias: Option<Tensor>,
}

impl Conv2d {
    pub fn new(
        vb: VarBuilder,
        in_channels: usize,
        out_channels: usize,
        kernel: usize,
        bias: bool,
    ) -> Result<Self> {
        let fan_in = (in_channels * kernel * kernel) as f64;
        let bound = (6.0 / fan_in).sqrt();
        let weight = vb.get_with_hints(
            (out_channels, in_channels, kernel, kernel),
            "weight",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        let bias = if bias {
            Some(vb.get_with_hints(out_channels, "bias", Init::Const(0.0))?)
        } else {
            None
        };
        Ok(Conv2d { weight, bias })
    }

    /// `[B, C, H, W]` → `[B, O, H, W]` ("same" padding).
    ///
    /// [`ic_nn::ops::conv::conv2d_same`]: im2col + GEMM on strips, one fused op on the CPU
    /// (candle's own `conv2d` backward goes through a direct `conv_transpose2d` that made a
    /// training step of the `cpu` preset take ≈ 37 s at batch 8).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = ic_nn::ops::conv::conv2d_same(x, &self.weight)?;
        match &self.bias {
            Some(b) => y.broadcast_add(&b.reshape((1, b.dim(0)?, 1, 1))?),
            None => Ok(y),
        }
    }
}

/// 2×2 max pooling (stride 2) and 2× nearest-neighbour up-sampling of `[B, C, H, W]`: fused
/// CPU ops with their backward passes on the rayon pool (the tensor-op versions, their oracle,
/// are `ic_nn::ops::pool::*_reference`; candle's `upsample_nearest2d` backward overwrites
/// instead of accumulating, so neither is candle's own).
pub use ic_nn::ops::pool::{max_pool2, upsample2};

/// 3×3 convolution → batch norm → ReLU.
#[derive(Clone, Debug)]
pub(crate) struct ConvBnRelu {
    pub(crate) conv: Conv2d,
    pub(crate) bn: BatchNorm2,
}

impl ConvBnRelu {
    fn new(vb: VarBuilder, cin: usize, cout: usize, momentum: f64) -> Result<Self> {
        Ok(ConvBnRelu {
            conv: Conv2d::new(vb.pp("conv"), cin, cout, 3, false)?,
            bn: BatchNorm2::new(vb.pp("bn"), cout, momentum)?,
        })
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.bn.forward_relu(&self.conv.forward(x)?, train)
    }
}

/// Two [`ConvBnRelu`] blocks.
#[derive(Clone, Debug)]
pub(crate) struct DoubleConv(pub(crate) ConvBnRelu, pub(crate) ConvBnRelu);

impl DoubleConv {
    fn new(vb: VarBuilder, cin: usize, cout: usize, momentum: f64) -> Result<Self> {
        Ok(DoubleConv(
            ConvBnRelu::new(vb.pp("a"), cin, cout, momentum)?,
            ConvBnRelu::new(vb.pp("b"), cout, cout, momentum)?,
        ))
    }

    fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.1.forward_t(&self.0.forward_t(x, train)?, train)
    }
}

/// The centre-offset branch of a four-output network with `offset_level` > 0: 3×3
/// convolution + batch norm + ReLU, then a 1×1 convolution to (x, y), whose weights and bias
/// start at zero (a network given the branch computes what it did before).
#[derive(Clone, Debug)]
pub(crate) struct OffsetBranch {
    pub(crate) level: usize,
    pub(crate) conv: ConvBnRelu,
    pub(crate) head: Conv2d,
}

/// The U-Net. Input `[B, C, H, W]` with C = `cfg.input.channels()` (see [`crate::input`]),
/// output logits `[B, outputs, H, W]` (object, then instance core when `outputs` ≥ 2, then
/// the centre offsets x and y when `outputs` = 4; see [`UNetConfig`]).
#[derive(Clone, Debug)]
pub struct UNet {
    pub(crate) down: Vec<DoubleConv>,
    pub(crate) up: Vec<DoubleConv>,
    pub(crate) head: Conv2d,
    pub(crate) offsets: Option<OffsetBranch>,
    cfg: UNetConfig,
}

impl UNet {
    pub fn new(vb: VarBuilder, cfg: &UNetConfig) -> Result<Self> {
        let ch = &cfg.channels;
        let m = cfg.bn_momentum;
        let mut down = Vec::with_capacity(ch.len());
        let mut cin = cfg.input.channels();
        for (l, &c) in ch.iter().enumerate() {
            down.push(DoubleConv::new(vb.pp(format!("down{l}")), cin, c, m)?);
            cin = c;
        }
        // Decoder level l (from the second-coarsest up to the finest) takes the up-sampled
        // features of level l + 1 concatenated with the encoder's level-l features.
        let mut up = Vec::with_capacity(ch.len().saturating_sub(1));
        for l in (0..ch.len() - 1).rev() {
            up.push(DoubleConv::new(
                vb.pp(format!("up{l}")),
                ch[l + 1] + ch[l],
                ch[l],
                m,
            )?);
        }
        let offsets = if cfg.offset_level > 0 {
            let (l, c) = (cfg.offset_level, ch[cfg.offset_level]);
            let vb = vb.pp("offsets");
            Some(OffsetBranch {
                level: l,
                conv: ConvBnRelu::new(vb.pp("conv"), c, c, m)?,
                head: Conv2d {
                    weight: vb.get_with_hints((2, c, 1, 1), "head.weight", Init::Const(0.0))?,
                    bias: Some(vb.get_with_hints(2, "head.bias", Init::Const(0.0))?),
                },
            })
        } else {
            None
        };
        Ok(UNet {
            down,
            up,
            head: Conv2d::new(vb.pp("head"), ch[0], cfg.outputs, 1, true)?,
            offsets,
            cfg: cfg.clone(),
        })
    }

    pub fn config(&self) -> &UNetConfig {
        &self.cfg
    }

    /// Per-pixel logits `[B, outputs, H, W]`; `train` selects batch statistics.
    pub fn forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let mut skips = Vec::with_capacity(self.down.len());
        let mut h = x.clone();
        for (l, block) in self.down.iter().enumerate() {
            if l > 0 {
                h = max_pool2(&h)?;
            }
            h = block.forward_t(&h, train)?;
            skips.push(h.clone());
        }
        let mut h = skips.pop().expect("at least one level");
        // The offset branch reads the bottleneck or a decoder level's output.
        let mut level = self.down.len() - 1;
        let mut branch = None;
        for block in &self.up {
            if let Some(b) = self.offsets.as_ref().filter(|b| b.level == level) {
                branch = Some(b.head.forward(&b.conv.forward_t(&h, train)?)?);
            }
            let skip = skips.pop().expect("one skip per decoder level");
            let (_, _, sh, sw) = skip.dims4()?;
            let upsampled = upsample2(&h)?;
            debug_assert_eq!(upsampled.dims4()?.2, sh);
            debug_assert_eq!(upsampled.dims4()?.3, sw);
            h = block.forward_t(&Tensor::cat(&[&upsampled, &skip], 1)?, train)?;
            level -= 1;
        }
        let logits = self.head.forward(&h)?;
        match branch {
            Some(mut off) => {
                // Nearest up-sampling by 2^level, added to the head's offset maps (2 and 3).
                for _ in 0..self.cfg.offset_level {
                    off = upsample2(&off)?;
                }
                let maps = logits.narrow(1, 0, 2)?;
                let offsets = (logits.narrow(1, 2, 2)? + off)?;
                Tensor::cat(&[&maps, &offsets], 1)
            }
            None => Ok(logits),
        }
    }
}
