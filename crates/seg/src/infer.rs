//! The U-Net's inference on the CPU without candle's tensor ops: batch norm folded into the
//! convolutions, each 3×3 convolution as im2col + GEMM on horizontal strips of the image (so
//! the unfolded columns stay in cache; the strip loop is [`ic_nn::ops::conv::convolve`], the
//! one training runs), bias and ReLU applied in place.
//!
//! The same function as [`UNet::forward_t`] with `train` false (its oracle test:
//! `folded_inference_matches_the_tensor_forward`), for one image at a time. The tensor form,
//! built for training, still allocates and traverses a full-image tensor per batch norm,
//! bias, pooling, up-sampling and concatenation, and gets no folding; before its convolutions
//! were fused, the clutter network's 256×192 input took about five times the time of the
//! `cpu` preset's 160×120 for 2.6 times the pixels through it.

use candle_core::Result;
use ic_nn::ops::conv::{ConvShape, convolve};
use rayon::prelude::*;

use crate::unet::{Conv2d, ConvBnRelu, UNet};

/// One convolution with its batch norm folded in: `y = W·x + b`, then ReLU when `relu`.
struct Folded {
    /// `[out, in·k·k]`, row-major (the im2col order: channel, then kernel row, then column).
    weight: Vec<f32>,
    bias: Vec<f32>,
    inputs: usize,
    outputs: usize,
    kernel: usize,
    relu: bool,
}

impl Folded {
    fn conv(conv: &Conv2d, affine: Option<(Vec<f32>, Vec<f32>)>, relu: bool) -> Result<Self> {
        let (o, c, kh, kw) = conv.weight.dims4()?;
        debug_assert_eq!(kh, kw);
        let mut weight = conv.weight.flatten_all()?.to_vec1::<f32>()?;
        let mut bias = match &conv.bias {
            Some(b) => b.to_vec1::<f32>()?,
            None => vec![0.0; o],
        };
        if let Some((scale, shift)) = affine {
            let row = c * kh * kw;
            for j in 0..o {
                weight[j * row..(j + 1) * row]
                    .iter_mut()
                    .for_each(|w| *w *= scale[j]);
                bias[j] = bias[j] * scale[j] + shift[j];
            }
        }
        Ok(Folded {
            weight,
            bias,
            inputs: c,
            outputs: o,
            kernel: kh,
            relu,
        })
    }

    fn conv_bn_relu(block: &ConvBnRelu) -> Result<Self> {
        Self::conv(&block.conv, Some(block.bn.inference_affine()?), true)
    }

    /// `x`: `[inputs, h, w]` → `[outputs, h, w]` ("same" zero padding): the strips of
    /// [`ic_nn::ops::conv::convolve`], then bias and ReLU in place.
    fn forward(&self, x: &[f32], h: usize, w: usize) -> Vec<f32> {
        debug_assert_eq!(x.len(), self.inputs * h * w);
        let shape = ConvShape {
            batch: 1,
            inputs: self.inputs,
            outputs: self.outputs,
            height: h,
            width: w,
            kernel: self.kernel,
        };
        let mut y = convolve(x, &self.weight, shape);
        y.par_chunks_mut((h * w).max(1))
            .zip(&self.bias)
            .for_each(|(plane, &b)| {
                if self.relu {
                    plane.iter_mut().for_each(|v| *v = (*v + b).max(0.0));
                } else {
                    plane.iter_mut().for_each(|v| *v += b);
                }
            });
        y
    }
}

/// 2×2 max pooling, stride 2: `[c, h, w]` → `[c, h/2, w/2]` (h and w even).
fn max_pool2(x: &[f32], c: usize, h: usize, w: usize) -> Vec<f32> {
    let (h2, w2) = (h / 2, w / 2);
    let mut y = vec![0.0f32; c * h2 * w2];
    for ch in 0..c {
        let plane = &x[ch * h * w..(ch + 1) * h * w];
        for yy in 0..h2 {
            let a = &plane[2 * yy * w..(2 * yy + 1) * w];
            let b = &plane[(2 * yy + 1) * w..(2 * yy + 2) * w];
            let out = &mut y[(ch * h2 + yy) * w2..(ch * h2 + yy + 1) * w2];
            for (xx, v) in out.iter_mut().enumerate() {
                *v = a[2 * xx]
                    .max(a[2 * xx + 1])
                    .max(b[2 * xx])
                    .max(b[2 * xx + 1]);
            }
        }
    }
    y
}

/// `[2x upsampled coarse (cc channels), skip (sc channels)]` at the skip's `h`×`w`.
fn upsample_concat(coarse: &[f32], cc: usize, skip: &[f32], h: usize, w: usize) -> Vec<f32> {
    let (h2, w2) = (h / 2, w / 2);
    let mut y = Vec::with_capacity(cc * h * w + skip.len());
    for ch in 0..cc {
        let plane = &coarse[ch * h2 * w2..(ch + 1) * h2 * w2];
        for yy in 0..h {
            let src = &plane[(yy / 2) * w2..(yy / 2 + 1) * w2];
            y.extend(src.iter().flat_map(|&v| [v, v]));
        }
    }
    y.extend_from_slice(skip);
    y
}

/// A [`UNet`] with its weights copied and batch norms folded, for inference.
pub struct FoldedUNet {
    down: Vec<(Folded, Folded)>,
    up: Vec<(Folded, Folded)>,
    head: Folded,
    /// The centre-offset branch: its level, convolution and 1×1 head.
    offsets: Option<(usize, Folded, Folded)>,
}

impl FoldedUNet {
    /// Copies `net`'s current weights and running statistics.
    pub fn new(net: &UNet) -> Result<Self> {
        let pair = |d: &crate::unet::DoubleConv| -> Result<(Folded, Folded)> {
            Ok((Folded::conv_bn_relu(&d.0)?, Folded::conv_bn_relu(&d.1)?))
        };
        Ok(FoldedUNet {
            down: net.down.iter().map(pair).collect::<Result<_>>()?,
            up: net.up.iter().map(pair).collect::<Result<_>>()?,
            head: Folded::conv(&net.head, None, false)?,
            offsets: match &net.offsets {
                Some(b) => Some((
                    b.level,
                    Folded::conv_bn_relu(&b.conv)?,
                    Folded::conv(&b.head, None, false)?,
                )),
                None => None,
            },
        })
    }

    /// Logits `[outputs, h, w]` of one input `[2, h, w]` (see [`crate::input`]); `h` and `w`
    /// must be divisible by 2^(levels − 1), as for [`UNet::forward_t`].
    pub fn forward(&self, input: &[f32], h: usize, w: usize) -> Result<Vec<f32>> {
        let levels = self.down.len();
        let step = 1usize << levels.saturating_sub(1);
        let inputs = self.down.first().map_or(0, |d| d.0.inputs);
        if h % step != 0 || w % step != 0 || input.len() != inputs * h * w {
            candle_core::bail!(
                "the U-Net's input must be [{inputs}, H, W] with H and W divisible by {step}, got {} values for {h}×{w}",
                input.len()
            );
        }
        let mut skips: Vec<(Vec<f32>, usize, usize, usize)> = Vec::with_capacity(levels);
        let (mut x, mut c, mut hh, mut ww) = (input.to_vec(), inputs, h, w);
        for (l, (a, b)) in self.down.iter().enumerate() {
            if l > 0 {
                x = max_pool2(&x, c, hh, ww);
                hh /= 2;
                ww /= 2;
            }
            x = b.forward(&a.forward(&x, hh, ww), hh, ww);
            c = b.outputs;
            skips.push((x.clone(), c, hh, ww));
        }
        let (mut x, mut c, _, _) = skips.pop().expect("at least one level");
        // The offset branch's output at its level: (values, level's height, width).
        let mut branch = None;
        let mut level = levels - 1;
        for (a, b) in &self.up {
            if let Some((l, conv, head)) = &self.offsets
                && *l == level
            {
                branch = Some((head.forward(&conv.forward(&x, hh, ww), hh, ww), hh, ww));
            }
            let (skip, _, sh, sw) = skips.pop().expect("one skip per decoder level");
            let cat = upsample_concat(&x, c, &skip, sh, sw);
            x = b.forward(&a.forward(&cat, sh, sw), sh, sw);
            c = b.outputs;
            (hh, ww) = (sh, sw);
            level -= 1;
        }
        let mut out = self.head.forward(&x, hh, ww);
        if let Some((off, bh, bw)) = branch {
            // Nearest up-sampling by 2^level, added to the head's offset maps (2 and 3).
            let (fy, fx) = (hh / bh, ww / bw);
            for ch in 0..2 {
                let plane = &mut out[(2 + ch) * hh * ww..(3 + ch) * hh * ww];
                let src = &off[ch * bh * bw..(ch + 1) * bh * bw];
                for (i, v) in plane.iter_mut().enumerate() {
                    *v += src[(i / ww / fy) * bw + (i % ww) / fx];
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{DType, Device, Tensor};
    use candle_nn::{VarBuilder, VarMap};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::config::{SegInput, UNetConfig};
    use ic_nn::ops::conv::{STRIP_VALUES, unfold};

    /// A U-Net with every weight, bias and running statistic drawn at random (variances
    /// positive), so that folding the batch norms is exercised in full.
    fn random_unet(channels: Vec<usize>, outputs: usize, input: SegInput, seed: u64) -> UNet {
        random_unet_with(channels, outputs, input, 0, seed)
    }

    /// [`random_unet`] with a centre-offset branch on `offset_level` (0: none).
    fn random_unet_with(
        channels: Vec<usize>,
        outputs: usize,
        input: SegInput,
        offset_level: usize,
        seed: u64,
    ) -> UNet {
        let cfg = UNetConfig {
            input_width: 40,
            input_height: 24,
            channels,
            bn_momentum: 0.1,
            outputs,
            input,
            offset_level,
        };
        let map = VarMap::new();
        let net = UNet::new(
            VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu),
            &cfg,
        )
        .unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for (name, var) in map.data().lock().unwrap().iter() {
            let n = var.elem_count();
            let values: Vec<f32> = (0..n)
                .map(|_| {
                    let u: f32 = rng.random_range(-1.0..1.0);
                    if name.ends_with("running_var") {
                        0.2 + u.abs()
                    } else {
                        u * 0.5
                    }
                })
                .collect();
            var.set(&Tensor::from_vec(values, var.shape(), &Device::Cpu).unwrap())
                .unwrap();
        }
        net
    }

    #[test]
    fn folded_inference_matches_the_tensor_forward() {
        // (channels, outputs, offset branch level, input, size)
        for (channels, outputs, level, kind, (h, w)) in [
            (
                vec![8, 16, 32, 64],
                2,
                0,
                SegInput::Depth,
                (24usize, 40usize),
            ),
            (vec![8, 16, 32, 64], 2, 0, SegInput::DepthNormals, (24, 40)),
            (vec![4, 8], 1, 0, SegInput::Depth, (10, 6)),
            (vec![3], 2, 0, SegInput::DepthNormals, (5, 7)),
            (vec![8, 16, 32, 64], 4, 2, SegInput::Depth, (24, 40)),
            (vec![8, 16, 32, 64], 4, 3, SegInput::Depth, (16, 24)),
            (vec![4, 8], 4, 1, SegInput::Depth, (10, 6)),
        ] {
            let net = random_unet_with(channels.clone(), outputs, kind, level, 7);
            let c = kind.channels();
            let mut rng = ChaCha8Rng::seed_from_u64(11);
            let input: Vec<f32> = (0..c * h * w)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let x = Tensor::from_vec(input.clone(), (1, c, h, w), &Device::Cpu).unwrap();
            let want = net
                .forward_t(&x, false)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let got = FoldedUNet::new(&net)
                .unwrap()
                .forward(&input, h, w)
                .unwrap();
            assert_eq!(got.len(), want.len());
            let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let worst = got
                .iter()
                .zip(&want)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                worst <= 1e-4 * scale.max(1.0),
                "{channels:?}, offset level {level}: worst difference {worst} (largest logit {scale})"
            );
        }
    }

    #[test]
    fn strips_of_one_row_give_the_whole_image_convolution() {
        // A wide layer forces one row per strip; the result must not depend on the split.
        let net = random_unet(vec![8], 1, SegInput::Depth, 3);
        let folded = FoldedUNet::new(&net).unwrap();
        let conv = &folded.down[0].1;
        let (h, w) = (9usize, 8192usize);
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let x: Vec<f32> = (0..8 * h * w)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        assert_eq!((STRIP_VALUES / (8 * 9 * w)).clamp(1, h), 1);
        let got = conv.forward(&x, h, w);
        let cols = unfold(&x, 8, h, w, 3, 0, h);
        let mut want = vec![0.0f32; 8 * h * w];
        for j in 0..8 {
            for p in 0..h * w {
                let s: f32 = (0..72)
                    .map(|r| conv.weight[j * 72 + r] * cols[r * h * w + p])
                    .sum();
                want[j * h * w + p] = (s + conv.bias[j]).max(0.0);
            }
        }
        let worst = got
            .iter()
            .zip(&want)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst < 1e-4, "worst difference {worst}");
        // The 1×1 head (no unfolding): strips of 4 rows.
        let head = &folded.head;
        assert_eq!((STRIP_VALUES / (8 * w)).clamp(1, h), 4);
        let got = head.forward(&x, h, w);
        for p in 0..h * w {
            let s: f32 = (0..8).map(|c| head.weight[c] * x[c * h * w + p]).sum();
            assert!((got[p] - (s + head.bias[0])).abs() < 1e-4, "pixel {p}");
        }
    }

    #[test]
    fn an_input_not_divisible_by_the_levels_is_an_error_not_a_panic() {
        let net = random_unet(vec![4, 8, 16], 1, SegInput::Depth, 1);
        let folded = FoldedUNet::new(&net).unwrap();
        assert!(folded.forward(&vec![0.0; 2 * 10 * 6], 10, 6).is_err());
        assert!(folded.forward(&[0.0; 5], 8, 8).is_err());
    }
}
