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

use super::cpu::{all_cpu_f32, f32_slice, to_f32_vec};
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

/// Shapes of one convolution: batch, input and output channels, height, width, kernel.
#[derive(Clone, Copy, Debug)]
struct Dims {
    b: usize,
    c: usize,
    o: usize,
    h: usize,
    w: usize,
    k: usize,
}

impl Dims {
    /// Every (image, first row of a strip) of the batch.
    fn tasks(&self) -> Vec<(usize, usize)> {
        let rows = rows_per_strip(self.c * self.k * self.k, self.w, self.h);
        (0..self.b)
            .flat_map(|bi| (0..self.h).step_by(rows).map(move |y0| (bi, y0)))
            .collect()
    }

    fn strip_end(&self, y0: usize) -> usize {
        (y0 + rows_per_strip(self.c * self.k * self.k, self.w, self.h)).min(self.h)
    }
}

/// `[B, O, H, W]` = conv(`x` `[B, C, H, W]`, `weight` `[O, C·k·k]`), strips in parallel.
fn convolve(x: &[f32], weight: &[f32], d: Dims) -> Vec<f32> {
    let (c, o, h, w, k) = (d.c, d.o, d.h, d.w, d.k);
    let ck = c * k * k;
    let wm = MatRef::new(weight, o, ck, ck);
    let strips: Vec<((usize, usize), Vec<f32>)> = d
        .tasks()
        .into_par_iter()
        .map(|(bi, y0)| {
            let y1 = d.strip_end(y0);
            let n = (y1 - y0) * w;
            let image = &x[bi * c * h * w..(bi + 1) * c * h * w];
            let mut out = vec![0.0f32; o * n];
            if k == 1 {
                let cols = MatRef::strided(&image[y0 * w..], c, n, h * w, 1);
                matmul(wm, cols, MatMut::new(&mut out, o, n, n), false);
            } else {
                let cols = unfold(image, c, h, w, k, y0, y1);
                matmul(
                    wm,
                    MatRef::new(&cols, ck, n, n),
                    MatMut::new(&mut out, o, n, n),
                    false,
                );
            }
            ((bi, y0), out)
        })
        .collect();
    let mut y = vec![0.0f32; d.b * o * h * w];
    for ((bi, y0), out) in strips {
        let n = out.len() / o.max(1);
        for j in 0..o {
            let at = (bi * o + j) * h * w + y0 * w;
            y[at..at + n].copy_from_slice(&out[j * n..(j + 1) * n]);
        }
    }
    y
}

/// `dW` `[O, C·k·k]` = Σ over images and pixels of `g` `[B, O, H, W]` times the im2col columns
/// of `x`: per strip in parallel, the partial sums added in strip order (deterministic).
fn weight_gradient(x: &[f32], g: &[f32], d: Dims) -> Vec<f32> {
    let (c, o, h, w, k) = (d.c, d.o, d.h, d.w, d.k);
    let ck = c * k * k;
    let partials: Vec<Vec<f32>> = d
        .tasks()
        .into_par_iter()
        .map(|(bi, y0)| {
            let y1 = d.strip_end(y0);
            let n = (y1 - y0) * w;
            let image = &x[bi * c * h * w..(bi + 1) * c * h * w];
            let gs = MatRef::strided(&g[bi * o * h * w + y0 * w..], o, n, h * w, 1);
            let mut dw = vec![0.0f32; o * ck];
            let dst = MatMut::new(&mut dw, o, ck, ck);
            if k == 1 {
                let cols = MatRef::strided(&image[y0 * w..], c, n, h * w, 1);
                matmul(gs, cols.t(), dst, false);
            } else {
                let cols = unfold(image, c, h, w, k, y0, y1);
                matmul(gs, MatRef::new(&cols, ck, n, n).t(), dst, false);
            }
            dw
        })
        .collect();
    let mut dw = vec![0.0f32; o * ck];
    for p in &partials {
        for (a, v) in dw.iter_mut().zip(p) {
            *a += v;
        }
    }
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
        let y = convolve(x, weight, Dims { b, c, o, h, w, k });
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
        let (xv, wv, gv) = (to_f32_vec(x)?, to_f32_vec(w)?, to_f32_vec(grad)?);
        let back = Dims {
            b,
            c: o,
            o: c,
            h,
            w: wd,
            k,
        };
        let dx = convolve(&gv, &flipped(&wv, o, c, k), back);
        let dw = weight_gradient(
            &xv,
            &gv,
            Dims {
                b,
                c,
                o,
                h,
                w: wd,
                k,
            },
        );
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
    use candle_core::{Device, Var};

    fn values(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| {
                ((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) % 1000) as f32 / 250.0
                    - 2.0
            })
            .collect()
    }

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
