//! The candle `CustomOp1` glue of the fused Sinkhorn layer: Z = S̄/λ from the scores, the
//! forward over a batch of pairs on rayon (log or scaled domain), the kept iterates, and the
//! backward pass's dispatch to [`super::log::backward_pair`].

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::log::{backward_pair, forward_pair};
use super::scaled::forward_pair_scaled;

/// The fused op. `history` keeps, per pair, the log u / log v iterates of the last forward so
/// that the backward pass can replay the iterations in reverse.
pub(super) struct LogOt {
    alpha: f32,
    lambda: f32,
    iterations: usize,
    /// Forward iterations in the scaled domain ([`super::scaled::forward_pair_scaled`]).
    scaled: bool,
    history: Mutex<Option<Arc<History>>>,
}

/// log u^t (`[B, k, M+1]`) and log v^t (`[B, k, N+1]`) for t = 1..=k.
struct History {
    us: Vec<f32>,
    vs: Vec<f32>,
}

/// Z = S̄/λ (`[M+1, N+1]`, row-major) and its transpose for one pair.
fn build_z(s: &[f32], m: usize, n: usize, alpha: f32, lambda: f32) -> (Vec<f32>, Vec<f32>) {
    let (m1, n1) = (m + 1, n + 1);
    let z = build_z_only(s, m, n, alpha, lambda);
    let mut zt = vec![0.0f32; m1 * n1];
    const BLK: usize = 32;
    for i0 in (0..m1).step_by(BLK) {
        for j0 in (0..n1).step_by(BLK) {
            for i in i0..(i0 + BLK).min(m1) {
                for j in j0..(j0 + BLK).min(n1) {
                    zt[j * m1 + i] = z[i * n1 + j];
                }
            }
        }
    }
    (z, zt)
}

/// log P̄ = Z + u^k + v^k for one pair.
fn write_output(z: &[f32], u: Option<&[f32]>, v: Option<&[f32]>, n1: usize, out: &mut [f32]) {
    out.copy_from_slice(z);
    if let (Some(u), Some(v)) = (u, v) {
        for (orow, &ui) in out.chunks_exact_mut(n1).zip(u) {
            for (o, &vj) in orow.iter_mut().zip(v) {
                *o = *o + ui + vj;
            }
        }
    }
}

impl LogOt {
    /// The op for [`super::log_optimal_transport_with`]'s arguments (no kept iterates yet).
    pub(super) fn new(alpha: f32, lambda: f32, iterations: usize, scaled: bool) -> Self {
        LogOt {
            alpha,
            lambda,
            iterations,
            scaled,
            history: Mutex::new(None),
        }
    }

    /// Forward over all pairs: (log P̄ `[B, M+1, N+1]`, history).
    #[allow(clippy::type_complexity)]
    fn run_forward(&self, s: &[f32], b: usize, m: usize, n: usize) -> (Vec<f32>, History) {
        let (m1, n1, k) = (m + 1, n + 1, self.iterations);
        // One chunk per pair even for k = 0 (so that the zipped chunk iterators stay aligned).
        let uk = (k * m1).max(1);
        let vk = (k * n1).max(1);
        let mut out = vec![0.0f32; b * m1 * n1];
        let mut us = vec![0.0f32; b * uk];
        let mut vs = vec![0.0f32; b * vk];
        let job = |(((sp, op), up), vp): (((&[f32], &mut [f32]), &mut [f32]), &mut [f32])| {
            let (z, zt) = build_z(sp, m, n, self.alpha, self.lambda);
            if self.scaled {
                forward_pair_scaled(&z, &zt, m, n, k, up, vp);
            } else {
                forward_pair(&z, &zt, m, n, k, up, vp);
            }
            let (u, v) = if k > 0 {
                (Some(&up[(k - 1) * m1..]), Some(&vp[(k - 1) * n1..]))
            } else {
                (None, None)
            };
            write_output(&z, u, v, n1, op);
        };
        if b == 1 {
            job((((s, &mut out[..]), &mut us[..]), &mut vs[..]));
        } else {
            s.par_chunks(m * n)
                .zip(out.par_chunks_mut(m1 * n1))
                .zip(us.par_chunks_mut(uk))
                .zip(vs.par_chunks_mut(vk))
                .for_each(job);
        }
        (out, History { us, vs })
    }
}

impl CustomOp1 for LogOt {
    fn name(&self) -> &'static str {
        "log-optimal-transport"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, m, n) = layout.shape().dims3()?;
        let data = match storage {
            CpuStorage::F32(v) => v.as_slice(),
            _ => candle_core::bail!("log_optimal_transport: fused op expects f32 scores"),
        };
        let Some((start, end)) = layout.contiguous_offsets() else {
            candle_core::bail!("log_optimal_transport: fused op expects contiguous scores");
        };
        let (out, history) = self.run_forward(&data[start..end], b, m, n);
        *self.history.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(history));
        Ok((CpuStorage::F32(out), Shape::from((b, m + 1, n + 1))))
    }

    #[allow(clippy::type_complexity)]
    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let (b, m, n) = arg.dims3()?;
        let (m1, n1, k) = (m + 1, n + 1, self.iterations);
        let s = ic_nn::ops::cpu::f32_data(arg)?;
        let g = ic_nn::ops::cpu::f32_data(grad_res)?;
        let cached = self
            .history
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let history = match cached {
            Some(h) => h,
            None => Arc::new(self.run_forward(&s, b, m, n).1),
        };
        let mut ds = vec![0.0f32; b * m * n];
        let uk = (k * m1).max(1);
        let vk = (k * n1).max(1);
        let job =
            |(((sp, gp), dp), (up, vp)): (((&[f32], &[f32]), &mut [f32]), (&[f32], &[f32]))| {
                let z = build_z_only(sp, m, n, self.alpha, self.lambda);
                backward_pair(&z, gp, m, n, k, up, vp, self.lambda, dp);
            };
        if b == 1 {
            job((
                ((&s[..], &g[..]), &mut ds[..]),
                (&history.us[..], &history.vs[..]),
            ));
        } else {
            s.par_chunks(m * n)
                .zip(g.par_chunks(m1 * n1))
                .zip(ds.par_chunks_mut(m * n))
                .zip(history.us.par_chunks(uk).zip(history.vs.par_chunks(vk)))
                .for_each(job);
        }
        Ok(Some(Tensor::from_vec(ds, (b, m, n), arg.device())?))
    }
}

/// Z = S̄/λ (`[M+1, N+1]`, row-major) for one pair; same arithmetic as the reference
/// (multiplication by the f32 rounding of 1/λ).
fn build_z_only(s: &[f32], m: usize, n: usize, alpha: f32, lambda: f32) -> Vec<f32> {
    let n1 = n + 1;
    let inv = (1.0 / lambda as f64) as f32;
    let mut z = vec![alpha * inv; (m + 1) * n1];
    for (zr, sr) in z.chunks_exact_mut(n1).zip(s.chunks_exact(n)) {
        for (zv, &sv) in zr[..n].iter_mut().zip(sr) {
            *zv = sv * inv;
        }
    }
    z
}
