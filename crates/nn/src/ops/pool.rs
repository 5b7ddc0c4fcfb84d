//! The U-Net's 2×2 max pooling and 2× nearest-neighbour up-sampling of `[B, C, H, W]` images.
//!
//! As tensor ops both went through candle's reshape/permute/broadcast, whose backward passes
//! (a strided copy, a comparison and a product for the max; a sum over the broadcast
//! dimensions for the up-sampling, one index division per value) run on the calling thread
//! alone. The fused ops here work plane by plane on the rayon pool and give the same values
//! and gradients as the tensor ops (the oracle of their tests).

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::cpu::{all_cpu_f32, f32_data, f32_slice, zeros_f32};

/// 2×2 max pooling with stride 2: `[B, C, H, W]` → `[B, C, H/2, W/2]`; H and W must be even.
///
/// The gradient of an output goes to every input of its 2×2 window equal to the max (ties
/// included), as candle's `max` does.
pub fn max_pool2(x: &Tensor) -> Result<Tensor> {
    let (_, _, h, w) = x.dims4()?;
    if h % 2 != 0 || w % 2 != 0 {
        candle_core::bail!("max_pool2: {h}×{w} image, even sides expected");
    }
    if all_cpu_f32(&[x]) {
        return x.contiguous()?.apply_op1(MaxPool2);
    }
    max_pool2_reference(x)
}

/// [`max_pool2`] from candle tensor ops (reshape, permute, `max`): the test oracle, and the
/// path on other devices.
pub fn max_pool2_reference(x: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    x.reshape((b, c, h / 2, 2, w / 2, 2))?
        .permute((0, 1, 2, 4, 3, 5))?
        .contiguous()?
        .reshape((b, c, h / 2, w / 2, 4))?
        .max(4)
}

/// 2× nearest-neighbour up-sampling: `[B, C, H, W]` → `[B, C, 2H, 2W]`, each value copied to
/// its 2×2 block; the backward sums each block's four gradients (row by row, left to right,
/// the order of candle's sum over the broadcast dimensions).
pub fn upsample2(x: &Tensor) -> Result<Tensor> {
    x.dims4()?;
    if all_cpu_f32(&[x]) {
        return x.contiguous()?.apply_op1(Upsample2);
    }
    upsample2_reference(x)
}

/// [`upsample2`] as a broadcast (the test oracle, and the path on other devices).
pub fn upsample2_reference(x: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    x.reshape((b, c, h, 1, w, 1))?
        .broadcast_as((b, c, h, 2, w, 2))?
        .reshape((b, c, 2 * h, 2 * w))
}

struct MaxPool2;

impl CustomOp1 for MaxPool2 {
    fn name(&self) -> &'static str {
        "ic-max-pool2"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, c, h, w) = l.shape().dims4()?;
        let x = f32_slice(s, l, "max_pool2 x")?;
        let (ho, wo) = (h / 2, w / 2);
        let mut y = zeros_f32(b * c * ho * wo);
        if ho * wo > 0 {
            y.par_chunks_mut(ho * wo)
                .zip(x.par_chunks(h * w))
                .for_each(|(yp, xp)| {
                    for (i, yr) in yp.chunks_exact_mut(wo).enumerate() {
                        let (r0, r1) = (&xp[2 * i * w..][..w], &xp[(2 * i + 1) * w..][..w]);
                        for (j, v) in yr.iter_mut().enumerate() {
                            *v = r0[2 * j]
                                .max(r0[2 * j + 1])
                                .max(r1[2 * j])
                                .max(r1[2 * j + 1]);
                        }
                    }
                });
        }
        Ok((CpuStorage::F32(y), Shape::from((b, c, ho, wo))))
    }

    fn bwd(&self, x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let (ho, wo) = (h / 2, w / 2);
        let (xv, yv, gv) = (f32_data(x)?, f32_data(res)?, f32_data(grad)?);
        let mut dx = zeros_f32(b * c * h * w);
        if ho * wo > 0 {
            dx.par_chunks_mut(h * w)
                .zip(xv.par_chunks(h * w))
                .zip(yv.par_chunks(ho * wo).zip(gv.par_chunks(ho * wo)))
                .for_each(|((dp, xp), (yp, gp))| {
                    for i in 0..ho {
                        for j in 0..wo {
                            let (m, g) = (yp[i * wo + j], gp[i * wo + j]);
                            for at in [
                                2 * i * w + 2 * j,
                                2 * i * w + 2 * j + 1,
                                (2 * i + 1) * w + 2 * j,
                                (2 * i + 1) * w + 2 * j + 1,
                            ] {
                                // candle's max backward: mask (equal to the max) × gradient.
                                let mask = if xp[at] == m { 1.0 } else { 0.0 };
                                dp[at] = mask * g;
                            }
                        }
                    }
                });
        }
        Ok(Some(Tensor::from_vec(dx, (b, c, h, w), x.device())?))
    }
}

struct Upsample2;

impl CustomOp1 for Upsample2 {
    fn name(&self) -> &'static str {
        "ic-upsample2"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, c, h, w) = l.shape().dims4()?;
        let x = f32_slice(s, l, "upsample2 x")?;
        let mut y = zeros_f32(b * c * 4 * h * w);
        if h * w > 0 {
            y.par_chunks_mut(4 * h * w)
                .zip(x.par_chunks(h * w))
                .for_each(|(yp, xp)| {
                    for (rows, xr) in yp.chunks_exact_mut(4 * w).zip(xp.chunks_exact(w)) {
                        let (top, bottom) = rows.split_at_mut(2 * w);
                        for (pair, &v) in top.chunks_exact_mut(2).zip(xr) {
                            pair.fill(v);
                        }
                        bottom.copy_from_slice(top);
                    }
                });
        }
        Ok((CpuStorage::F32(y), Shape::from((b, c, 2 * h, 2 * w))))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (b, c, h, w) = x.dims4()?;
        let gv = f32_data(grad)?;
        let mut dx = zeros_f32(b * c * h * w);
        if h * w > 0 {
            dx.par_chunks_mut(h * w)
                .zip(gv.par_chunks(4 * h * w))
                .for_each(|(dp, gp)| {
                    for (dr, rows) in dp.chunks_exact_mut(w).zip(gp.chunks_exact(4 * w)) {
                        let (top, bottom) = rows.split_at(2 * w);
                        for (j, d) in dr.iter_mut().enumerate() {
                            *d = top[2 * j] + top[2 * j + 1] + bottom[2 * j] + bottom[2 * j + 1];
                        }
                    }
                });
        }
        Ok(Some(Tensor::from_vec(dx, (b, c, h, w), x.device())?))
    }
}
