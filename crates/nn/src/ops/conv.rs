//! The 2-D "same" convolution (stride 1, zero padding `k / 2`, no bias) of channel-first images
//! `[B, C, H, W]`, as im2col + GEMM on horizontal strips of each image, forward and backward.
//!
//! On the CPU with f32 one fused op: the unfolded columns of a strip (≈ 1 MB) stay in cache and
//! the strips of all images run in parallel. The backward needs no other kernel: the input
//! gradient is the same convolution of the output gradient with the kernel turned by half a
//! turn and its channel axes swapped, and the weight gradient is `Σ g · colsᵀ` over the same
//! strips. [`conv2d_same_reference`] computes the same thing from candle tensor ops (padding,
//! `k²` shifted copies, their stack and one product, whose backward copies each again): the
//! fallback on other devices and dtypes, and the oracle of the tests. Training the clutter
//! segmentation network through it made every step copy and sweep hundreds of megabytes.

use candle_core::{CpuStorage, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::cpu::{all_cpu_f32, f32_data, f32_slice, zeros_f32};
use super::fastmath::matmul;
use super::{MatMut, MatRef};

/// Unfolded input values (channels × k² × strip pixels) per strip, at most: about 1 MB of f32.
pub const STRIP_VALUES: usize = 1 << 18;

/// `y = conv(x, w)` for `x` `[B, C, H, W]` and `w` `[O, C, k, k]` (`k` odd): `[B, O, H, W]`,
/// stride 1, zero padding `k / 2` ("same" size), no bias. Row `(c·k + dy)·k + dx` of the
/// weight's `[O, C·k·k]` view multiplies `x[c][y + dy − k/2][x + dx − k/2]`.
///
/// On the CPU with f32 the fused op of this module; otherwise [`conv2d_same_reference`].
pub fn conv2d_same(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    let (_, c, _, _) = x.dims4()?;
    let (_, wc, kh, kw) = w.dims4()?;
    if wc != c || kh != kw || kh % 2 == 0 {
        candle_core::bail!(
            "conv2d_same: weight {:?} for input {:?} (odd square kernels over the input's channels)",
            w.dims(),
            x.dims()
        );
    }
    if all_cpu_f32(&[x, w]) {
        return x.contiguous()?.apply_op2(&w.contiguous()?, ConvSame);
    }
    conv2d_same_reference(x, w)
}

/// [`conv2d_same`] from candle tensor ops (zero padding, the `k²` shifted copies stacked into
/// the im2col matrix, one broadcast product): other devices and dtypes, and the test oracle.
pub fn conv2d_same_reference(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    let (b, c, h, wd) = x.dims4()?;
    let (o, _, kh, kw) = w.dims4()?;
    if kh == 1 && kw == 1 {
        return w
            .reshape((o, c))?
            .broadcast_matmul(&x.reshape((b, c, h * wd))?)?
            .reshape((b, o, h, wd));
    }
    let p = kh / 2;
    let xp = x.pad_with_zeros(2, p, p)?.pad_with_zeros(3, p, p)?;
    let mut shifted = Vec::with_capacity(kh * kw);
    for dy in 0..kh {
        for dx in 0..kw {
            shifted.push(xp.narrow(2, dy, h)?.narrow(3, dx, wd)?);
        }
    }
    // [B, C, k², H, W] → [B, C·k², H·W], matching the weight's [O, C, k, k].
    let cols = Tensor::stack(&shifted, 2)?.reshape((b, c * kh * kw, h * wd))?;
    w.reshape((o, c * kh * kw))?
        .broadcast_matmul(&cols)?
        .reshape((b, o, h, wd))
}

/// The im2col columns of rows `y0..y1` of `x` (`[c, h, w]`) for a `k`×`k` kernel with zero
/// padding `k / 2`: `[c·k·k, (y1 − y0)·w]`, row `(ch·k + dy)·k + dx` holding
/// `x[ch][y + dy − k/2][x + dx − k/2]` (0 outside the image).
pub fn unfold(x: &[f32], c: usize, h: usize, w: usize, k: usize, y0: usize, y1: usize) -> Vec<f32> {
    let n = (y1 - y0) * w;
    let p = k / 2;
    let mut cols = vec![0.0f32; c * k * k * n];
    for ch in 0..c {
        let plane = &x[ch * h * w..(ch + 1) * h * w];
        for dy in 0..k {
            for dx in 0..k {
                let row = &mut cols[((ch * k + dy) * k + dx) * n..][..n];
                for y in y0..y1 {
                    let sy = y as isize + dy as isize - p as isize;
                    if sy < 0 || sy >= h as isize {
                        continue;
                    }
                    let src = &plane[sy as usize * w..(sy as usize + 1) * w];
                    let dst = &mut row[(y - y0) * w..(y - y0 + 1) * w];
                    // dst[x] = src[x + dx − p] where that lies inside the row.
                    let shift = dx as isize - p as isize;
                    let (from, to) = if shift < 0 {
                        (0usize, shift.unsigned_abs())
                    } else {
                        (shift as usize, 0usize)
                    };
                    if from.max(to) >= w {
                        continue;
                    }
                    let len = w - from.max(to);
                    dst[to..to + len].copy_from_slice(&src[from..from + len]);
                }
            }
        }
    }
    cols
}

/// Rows per strip for `ck` unfolded rows of `w` pixels: the columns stay near
/// [`STRIP_VALUES`].
pub fn rows_per_strip(ck: usize, w: usize, h: usize) -> usize {
    (STRIP_VALUES / (ck * w).max(1)).clamp(1, h.max(1))
}

/// The shape of one convolution: `batch` images of `inputs` channels, `height` × `width`
/// pixels, to `outputs` channels, with a `kernel` × `kernel` kernel (odd).
#[derive(Clone, Copy, Debug)]
pub struct ConvShape {
    pub batch: usize,
    pub inputs: usize,
    pub outputs: usize,
    pub height: usize,
    pub width: usize,
    pub kernel: usize,
}

impl ConvShape {
    /// Rows of the weight's `[outputs, inputs·k·k]` view.
    fn unfolded(&self) -> usize {
        self.inputs * self.kernel * self.kernel
    }

    /// Every (image, first row of a strip) of the batch.
    fn tasks(&self) -> Vec<(usize, usize)> {
        let rows = rows_per_strip(self.unfolded(), self.width, self.height);
        (0..self.batch)
            .flat_map(|bi| (0..self.height).step_by(rows).map(move |y0| (bi, y0)))
            .collect()
    }

    /// The end of the strip starting at row `y0`.
    fn strip_end(&self, y0: usize) -> usize {
        (y0 + rows_per_strip(self.unfolded(), self.width, self.height)).min(self.height)
    }

    /// Image `bi` of `x` (`[batch, channels, height, width]`).
    fn image<'a>(&self, x: &'a [f32], channels: usize, bi: usize) -> &'a [f32] {
        let plane = channels * self.height * self.width;
        &x[bi * plane..(bi + 1) * plane]
    }

    /// `f` of the im2col columns `[inputs·k·k, (y1 − y0)·width]` of rows `y0..y1` of `image`
    /// (`[inputs, height, width]`): a strided view of the image for a 1×1 kernel, the
    /// [`unfold`]ed copy otherwise.
    fn with_columns<R>(
        &self,
        image: &[f32],
        y0: usize,
        y1: usize,
        f: impl FnOnce(MatRef) -> R,
    ) -> R {
        let (c, h, w, k) = (self.inputs, self.height, self.width, self.kernel);
        let n = (y1 - y0) * w;
        if k == 1 {
            f(MatRef::strided(&image[y0 * w..], c, n, h * w, 1))
        } else {
            let cols = unfold(image, c, h, w, k, y0, y1);
            f(MatRef::new(&cols, self.unfolded(), n, n))
        }
    }
}

/// `y` `[batch, outputs, height, width]` = conv(`x` `[batch, inputs, height, width]`,
/// `weight` `[outputs, inputs·k·k]`), the function of [`conv2d_same`] on plain slices: the
/// strips of every image in parallel (what the segmentation network's folded inference runs).
pub fn convolve(x: &[f32], weight: &[f32], d: ConvShape) -> Vec<f32> {
    let (o, h, w) = (d.outputs, d.height, d.width);
    let wm = MatRef::new(weight, o, d.unfolded(), d.unfolded());
    let strips: Vec<((usize, usize), Vec<f32>)> = d
        .tasks()
        .into_par_iter()
        .map(|(bi, y0)| {
            let y1 = d.strip_end(y0);
            let n = (y1 - y0) * w;
            let mut out = vec![0.0f32; o * n];
            d.with_columns(d.image(x, d.inputs, bi), y0, y1, |cols| {
                matmul(wm, cols, MatMut::new(&mut out, o, n, n), false)
            });
            ((bi, y0), out)
        })
        .collect();
    // Each output plane (image, channel) gathers its rows from its image's strips, the planes
    // in parallel.
    let mut by_image: Vec<Vec<(usize, &[f32])>> = vec![Vec::new(); d.batch];
    for ((bi, y0), out) in &strips {
        by_image[*bi].push((*y0, out));
    }
    let mut y = zeros_f32(d.batch * o * h * w);
    if o * h * w > 0 {
        y.par_chunks_mut(h * w)
            .enumerate()
            .for_each(|(plane, dst)| {
                let (bi, j) = (plane / o, plane % o);
                for &(y0, out) in &by_image[bi] {
                    let n = out.len() / o;
                    dst[y0 * w..y0 * w + n].copy_from_slice(&out[j * n..(j + 1) * n]);
                }
            });
    }
    y
}

/// `dW` `[O, C·k·k]` = Σ over images and pixels of `g` `[B, O, H, W]` times the im2col columns
/// of `x`: per strip in parallel, the partial sums added in strip order (deterministic).
fn weight_gradient(x: &[f32], g: &[f32], d: ConvShape) -> Vec<f32> {
    let (o, ck, w) = (d.outputs, d.unfolded(), d.width);
    let partials: Vec<Vec<f32>> = d
        .tasks()
        .into_par_iter()
        .map(|(bi, y0)| {
            let y1 = d.strip_end(y0);
            let n = (y1 - y0) * w;
            let gs = MatRef::strided(&d.image(g, o, bi)[y0 * w..], o, n, d.height * w, 1);
            let mut dw = vec![0.0f32; o * ck];
            d.with_columns(d.image(x, d.inputs, bi), y0, y1, |cols| {
                matmul(gs, cols.t(), MatMut::new(&mut dw, o, ck, ck), false)
            });
            dw
        })
        .collect();
    // The partial sums added in strip order (the same bits at every thread count), over
    // chunks of dW in parallel.
    const CHUNK: usize = 1 << 12;
    let mut dw = zeros_f32(o * ck);
    dw.par_chunks_mut(CHUNK).enumerate().for_each(|(ci, acc)| {
        for p in &partials {
            for (a, v) in acc.iter_mut().zip(&p[ci * CHUNK..]) {
                *a += v;
            }
        }
    });
    dw
}

/// The kernel `[O, C, k, k]` turned by half a turn with its channel axes swapped:
/// `[C, O, k, k]`, `t[c][o][dy][dx] = w[o][c][k−1−dy][k−1−dx]` (the input gradient's kernel).
fn flipped(weight: &[f32], o: usize, c: usize, k: usize) -> Vec<f32> {
    let mut t = vec![0.0f32; weight.len()];
    for oi in 0..o {
        for ci in 0..c {
            for dy in 0..k {
                for dx in 0..k {
                    t[((ci * o + oi) * k + dy) * k + dx] =
                        weight[((oi * c + ci) * k + (k - 1 - dy)) * k + (k - 1 - dx)];
                }
            }
        }
    }
    t
}

/// The fused "same" convolution (see the module's documentation).
struct ConvSame;

impl CustomOp2 for ConvSame {
    fn name(&self) -> &'static str {
        "ic-conv2d-same"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, c, h, w) = l1.shape().dims4()?;
        let (o, _, k, _) = l2.shape().dims4()?;
        let x = f32_slice(s1, l1, "conv2d x")?;
        let weight = f32_slice(s2, l2, "conv2d weight")?;
        let shape = ConvShape {
            batch: b,
            inputs: c,
            outputs: o,
            height: h,
            width: w,
            kernel: k,
        };
        let y = convolve(x, weight, shape);
        Ok((CpuStorage::F32(y), Shape::from((b, o, h, w))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (b, c, h, wd) = x.dims4()?;
        let (o, _, k, _) = w.dims4()?;
        let (xv, wv, gv) = (f32_data(x)?, f32_data(w)?, f32_data(grad)?);
        let shape = ConvShape {
            batch: b,
            inputs: c,
            outputs: o,
            height: h,
            width: wd,
            kernel: k,
        };
        let back = ConvShape {
            inputs: o,
            outputs: c,
            ..shape
        };
        let dx = convolve(&gv, &flipped(&wv, o, c, k), back);
        let dw = weight_gradient(&xv, &gv, shape);
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, (b, c, h, wd), dev)?),
            Some(Tensor::from_vec(dw, (o, c, k, k), dev)?),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::test_values as values;
    use candle_core::{Device, Var};

    /// Output and the input and weight gradients of `Σ y ∘ r` (`r` fixed values), fused or
    /// from tensor ops.
    fn run(
        fused: bool,
        (b, c, o, h, w, k): (usize, usize, usize, usize, usize, usize),
    ) -> Vec<Vec<f32>> {
        let dev = Device::Cpu;
        let x = Var::from_tensor(
            &Tensor::from_vec(values(b * c * h * w, 3), (b, c, h, w), &dev).unwrap(),
        )
        .unwrap();
        let wt = Var::from_tensor(
            &Tensor::from_vec(values(o * c * k * k, 7), (o, c, k, k), &dev).unwrap(),
        )
        .unwrap();
        let y = if fused {
            conv2d_same(x.as_tensor(), wt.as_tensor()).unwrap()
        } else {
            conv2d_same_reference(x.as_tensor(), wt.as_tensor()).unwrap()
        };
        let r = Tensor::from_vec(values(b * o * h * w, 11), (b, o, h, w), &dev).unwrap();
        let grads = (&y * &r).unwrap().sum_all().unwrap().backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        vec![
            flat(&y),
            flat(grads.get(x.as_tensor()).unwrap()),
            flat(grads.get(wt.as_tensor()).unwrap()),
        ]
    }

    #[test]
    fn the_fused_convolution_matches_the_tensor_ops_in_value_and_gradients() {
        // 3×3 over several images, a kernel wider than the image, a 1×1, one image of one
        // row, and a wide image cut into one-row strips.
        for dims in [
            (3, 5, 4, 7, 9, 3),
            (2, 2, 3, 4, 3, 5),
            (2, 6, 3, 5, 4, 1),
            (1, 3, 2, 1, 8, 3),
            (2, 8, 3, 3, 2048, 3),
        ] {
            let (fused, reference) = (run(true, dims), run(false, dims));
            for (what, (a, b)) in ["y", "dx", "dw"].iter().zip(fused.iter().zip(&reference)) {
                assert_eq!(a.len(), b.len());
                let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
                let worst = a
                    .iter()
                    .zip(b)
                    .fold(0.0f32, |m, (p, q)| m.max((p - q).abs()));
                assert!(
                    worst <= 1e-5 * scale,
                    "{dims:?} {what}: worst difference {worst} (scale {scale})"
                );
            }
        }
        assert_eq!(rows_per_strip(8 * 9, 2048, 3), 1);
    }

    #[test]
    fn the_same_inputs_give_the_same_bits() {
        let dims = (4, 8, 16, 24, 32, 3);
        assert_eq!(run(true, dims), run(true, dims));
    }

    #[test]
    fn a_kernel_that_does_not_fit_the_input_is_an_error() {
        let dev = Device::Cpu;
        let x = Tensor::zeros((1, 3, 4, 4), candle_core::DType::F32, &dev).unwrap();
        for shape in [(2, 2, 3, 3), (2, 3, 2, 2), (2, 3, 3, 1)] {
            let w = Tensor::zeros(shape, candle_core::DType::F32, &dev).unwrap();
            assert!(conv2d_same(&x, &w).is_err(), "{shape:?}");
        }
    }
}
