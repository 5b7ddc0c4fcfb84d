//! The scaled-domain forward of the fused Sinkhorn op: `exp(Z − row max)` and
//! `exp(Zᵀ − column max)` once per forward, then each half-iteration is a matrix-vector product
//! with the exponentiated potentials (one FMA per entry instead of one `exp`); a row or column
//! whose sum underflows is recomputed in the log domain ([`super::log`]).

use rayon::prelude::*;

use ic_nn::ops::fastmath::exp_approx;

use super::log::lse_row;
use super::{GRAIN, LANES, log_marginals, rows_per_task};

/// Σ_j k_j · w_j (16 independent lanes, then summed).
#[inline(always)]
fn dot_generic<const F: bool>(k: &[f32], w: &[f32]) -> f32 {
    let w = &w[..k.len()];
    let kc = k.chunks_exact(LANES);
    let wc = w.chunks_exact(LANES);
    let (kr, wr) = (kc.remainder(), wc.remainder());
    let mut acc = [0.0f32; LANES];
    for (a, b) in kc.zip(wc) {
        for l in 0..LANES {
            acc[l] = ic_nn::ops::fastmath::fmadd::<F>(a[l], b[l], acc[l]);
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (&a, &b) in kr.iter().zip(wr) {
        s += a * b;
    }
    s
}

/// Smallest kernel sum trusted by the scaled iterations (see [`forward_pair`]).
const SCALED_SUM_FLOOR: f32 = 1e-25;

/// out[r] = base[r] − LSE_j(z[r, j] + add[j]) from the pre-exponentiated rows
/// `kern[r, j] = exp(z[r, j] − zmax[r])` and `w[j] = exp(add[j] − amax)`:
/// LSE = zmax + amax + ln Σ_j kern·w. A row whose sum falls below [`SCALED_SUM_FLOOR`] (its
/// dominant terms underflowed) is recomputed exactly in the log domain from `z`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn scaled_rows_generic<const F: bool>(
    kern: &[f32],
    z: &[f32],
    zmax: &[f32],
    w: &[f32],
    add: &[f32],
    amax: f32,
    base: &[f32],
    out: &mut [f32],
) {
    let n = w.len();
    for ((((kr, zr), &zm), &b), o) in kern
        .chunks_exact(n)
        .zip(z.chunks_exact(n))
        .zip(zmax)
        .zip(base)
        .zip(out.iter_mut())
    {
        let sum = dot_generic::<F>(kr, w);
        *o = if sum > SCALED_SUM_FLOOR && sum.is_finite() {
            b - (zm + amax + sum.ln())
        } else {
            b - lse_row::<F>(zr, add)
        };
    }
}

ic_nn::avx2_fma_dispatch! {
    /// [`scaled_rows_generic`], with FMA when the CPU has it.
    #[allow(clippy::too_many_arguments)]
    fn scaled_rows(kern: &[f32], z: &[f32], zmax: &[f32], w: &[f32], add: &[f32], amax: f32, base: &[f32], out: &mut [f32]) = scaled_rows_generic;
}

/// One half-iteration over all rows of `z` (row length `add.len()`), in parallel blocks.
#[allow(clippy::too_many_arguments)]
fn scaled_all_rows(
    kern: &[f32],
    z: &[f32],
    zmax: &[f32],
    add: &[f32],
    base: &[f32],
    out: &mut [f32],
    w: &mut Vec<f32>,
) {
    let n = add.len();
    let amax = add.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    w.clear();
    w.extend(add.iter().map(|&a| exp_approx_any(a - amax)));
    let w = &w[..];
    let rows = out.len();
    if rows * n <= GRAIN {
        scaled_rows(kern, z, zmax, w, add, amax, base, out);
        return;
    }
    let rpt = rows_per_task(n);
    out.par_chunks_mut(rpt).enumerate().for_each(|(t, o)| {
        let (r0, r1) = (t * rpt, t * rpt + o.len());
        scaled_rows(
            &kern[r0 * n..r1 * n],
            &z[r0 * n..r1 * n],
            &zmax[r0..r1],
            w,
            add,
            amax,
            &base[r0..r1],
            o,
        );
    });
}

/// The portable `exp`, for the M + N + 2 potentials of an iteration (too few for SIMD dispatch
/// to matter).
fn exp_approx_any(x: f32) -> f32 {
    exp_approx::<false>(x)
}

/// `out = exp(src − m)`, element-wise.
#[inline(always)]
fn exp_shifted_generic<const F: bool>(src: &[f32], m: f32, out: &mut [f32]) {
    for (o, &v) in out.iter_mut().zip(src) {
        *o = exp_approx::<F>(v - m);
    }
}

ic_nn::avx2_fma_dispatch! {
    /// [`exp_shifted_generic`], with FMA when the CPU has it.
    fn exp_shifted(src: &[f32], m: f32, out: &mut [f32]) = exp_shifted_generic;
}

/// Row maxima of `z` (`rows × n`) and `exp(z − row max)`.
fn row_kernel(z: &[f32], n: usize) -> (Vec<f32>, Vec<f32>) {
    let zmax: Vec<f32> = z
        .par_chunks(n)
        .map(|r| r.iter().copied().fold(f32::NEG_INFINITY, f32::max))
        .collect();
    let mut kern = vec![0.0f32; z.len()];
    kern.par_chunks_mut(n)
        .zip(z.par_chunks(n))
        .zip(&zmax)
        .for_each(|((k, r), &m)| exp_shifted(r, m, k));
    (zmax, kern)
}

/// Runs the k iterations for one pair in the scaled domain (the default forward):
/// `exp(Z − row max)` and `exp(Zᵀ − column max)` are computed once, and each half-iteration is
/// a matrix-vector product with the exponentiated potentials instead of one `exp` per entry.
/// Exactness: every term that underflows is below 2⁻¹²⁶ while the sum is above
/// [`SCALED_SUM_FLOOR`], so the dropped mass is below `len · 1e-13` of the sum; a row or column
/// whose sum is below the floor is recomputed in the log domain. The iterates equal
/// [`forward_pair`]'s (the log-domain version) to f32 rounding, which the tests check.
pub(super) fn forward_pair_scaled(
    z: &[f32],
    zt: &[f32],
    m: usize,
    n: usize,
    k: usize,
    us: &mut [f32],
    vs: &mut [f32],
) {
    let (m1, n1) = (m + 1, n + 1);
    let (la, lb) = log_marginals(m, n);
    let (zmax, kz) = row_kernel(z, n1);
    let (ztmax, kzt) = row_kernel(zt, m1);
    let zeros = vec![0.0f32; n1];
    let mut w = Vec::with_capacity(m1.max(n1));
    for t in 0..k {
        let cur_u = &mut us[t * m1..];
        let (done_v, cur_v) = vs.split_at_mut(t * n1);
        let vprev: &[f32] = if t == 0 {
            &zeros
        } else {
            &done_v[(t - 1) * n1..]
        };
        let u = &mut cur_u[..m1];
        scaled_all_rows(&kz, z, &zmax, vprev, &la, u, &mut w);
        scaled_all_rows(&kzt, zt, &ztmax, u, &lb, &mut cur_v[..n1], &mut w);
    }
}
