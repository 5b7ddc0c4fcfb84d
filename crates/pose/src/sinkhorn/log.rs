//! The log-domain Sinkhorn iterations of the fused CPU op: stable row log-sum-exps (shifted
//! by the row max, or by the previous iteration's value when it is provably close), the
//! k-iteration forward, and the exact backward pass that replays the unrolled iterations in
//! reverse. The scaled forward ([`super::scaled`]) reuses the row kernels where its sums
//! underflow.

use rayon::prelude::*;

use ic_nn::ops::fastmath::exp_approx;

use super::{GRAIN, LANES, log_marginals, rows_per_task};

/// LSE_j(z_j + add_j), max subtracted.
#[inline(always)]
pub(super) fn lse_row<const F: bool>(z: &[f32], add: &[f32]) -> f32 {
    let add = &add[..z.len()];
    let zc = z.chunks_exact(LANES);
    let ac = add.chunks_exact(LANES);
    let (zr, ar) = (zc.remainder(), ac.remainder());
    let mut mx = [f32::NEG_INFINITY; LANES];
    for (zc, ac) in zc.clone().zip(ac.clone()) {
        for k in 0..LANES {
            let x = zc[k] + ac[k];
            mx[k] = if x > mx[k] { x } else { mx[k] };
        }
    }
    let mut m = f32::NEG_INFINITY;
    for &x in &mx {
        m = if x > m { x } else { m };
    }
    for (&a, &b) in zr.iter().zip(ar) {
        let x = a + b;
        m = if x > m { x } else { m };
    }
    if !m.is_finite() {
        // All −∞ (→ −∞), or +∞ somewhere (unsupported input).
        return m;
    }
    let mut acc = [0.0f32; LANES];
    for (zc, ac) in zc.zip(ac) {
        for k in 0..LANES {
            acc[k] += exp_approx::<F>(zc[k] + ac[k] - m);
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (&a, &b) in zr.iter().zip(ar) {
        s += exp_approx::<F>(a + b - m);
    }
    m + s.ln()
}

/// LSE_j(z_j + add_j) with a caller-supplied shift `c` instead of the max (saves the max pass).
/// `c` must be within ±40 of the true max (the forward guarantees it; see `forward_pair`);
/// falls back to the max-subtracted version if the sum is out of the safe range anyway.
#[inline(always)]
fn lse_row_shifted<const F: bool>(z: &[f32], add: &[f32], c: f32) -> f32 {
    let add = &add[..z.len()];
    let zc = z.chunks_exact(LANES);
    let ac = add.chunks_exact(LANES);
    let (zr, ar) = (zc.remainder(), ac.remainder());
    let mut acc = [0.0f32; LANES];
    for (zc, ac) in zc.zip(ac) {
        for k in 0..LANES {
            acc[k] += exp_approx::<F>(zc[k] + ac[k] - c);
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (&a, &b) in zr.iter().zip(ar) {
        s += exp_approx::<F>(a + b - c);
    }
    if s > 1e-25 && s < 1e25 {
        c + s.ln()
    } else {
        lse_row::<F>(z, add)
    }
}

/// out[r] = base[r] − LSE_j(z[r, j] + add[j]) for the rows of `z` (row length `add.len()`),
/// shifting each LSE by `shift[r]` when given, else by the row max.
#[inline(always)]
pub(super) fn lse_rows_generic<const F: bool>(
    z: &[f32],
    add: &[f32],
    base: &[f32],
    shift: Option<&[f32]>,
    out: &mut [f32],
) {
    let n = add.len();
    match shift {
        Some(c) => {
            for (((zr, o), &b), &c) in z.chunks_exact(n).zip(out.iter_mut()).zip(base).zip(c) {
                *o = b - lse_row_shifted::<F>(zr, add, c);
            }
        }
        None => {
            for ((zr, o), &b) in z.chunks_exact(n).zip(out.iter_mut()).zip(base) {
                *o = b - lse_row::<F>(zr, add);
            }
        }
    }
}

/// One reverse step of the unrolled iterations over a block of rows (see `backward_pair`).
/// Returns nothing; writes `gu` for the rows and accumulates the R-weights' column sums.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn bwd_rows_generic<const F: bool>(
    z: &[f32],
    u: &[f32],
    la: &[f32],
    extra: &[f32],
    c: &[f32],
    gv: &[f32],
    vprev: &[f32],
    dz: &mut [f32],
    gu: &mut [f32],
    colacc: &mut [f32],
) {
    let n = c.len();
    let gv = &gv[..n];
    let vprev = &vprev[..n];
    let colacc = &mut colacc[..n];
    for (r, (zr, dzr)) in z.chunks_exact(n).zip(dz.chunks_exact_mut(n)).enumerate() {
        let ui = u[r];
        // Q step: v^t_j = lb_j − LSE_i(Z_ij + u^t_i), Q_ij = exp(Z_ij + u_i + v_j − lb_j).
        let mut acc = [0.0f32; LANES];
        let mut tail = 0.0f32;
        {
            let mut zc = zr.chunks_exact(LANES);
            let mut cc = c.chunks_exact(LANES);
            let mut gc = gv.chunks_exact(LANES);
            let mut dc = dzr.chunks_exact_mut(LANES);
            for (((zc, cc), gc), dc) in (&mut zc).zip(&mut cc).zip(&mut gc).zip(&mut dc) {
                for k in 0..LANES {
                    let w = gc[k] * exp_approx::<F>(zc[k] + cc[k] + ui);
                    dc[k] -= w;
                    acc[k] += w;
                }
            }
            for (((&zv, &cv), &gvv), dv) in zc
                .remainder()
                .iter()
                .zip(cc.remainder())
                .zip(gc.remainder())
                .zip(dc.into_remainder())
            {
                let w = gvv * exp_approx::<F>(zv + cv + ui);
                *dv -= w;
                tail += w;
            }
        }
        let g = extra[r] - (acc.iter().sum::<f32>() + tail);
        gu[r] = g;
        // R step: u^t_i = la_i − LSE_j(Z_ij + v^{t−1}_j), R_ij = exp(Z_ij + v^{t−1}_j + u_i − la_i).
        let off = ui - la[r];
        {
            let mut zc = zr.chunks_exact(LANES);
            let mut pc = vprev.chunks_exact(LANES);
            let mut dc = dzr.chunks_exact_mut(LANES);
            let mut ac = colacc.chunks_exact_mut(LANES);
            for (((zc, pc), dc), ac) in (&mut zc).zip(&mut pc).zip(&mut dc).zip(&mut ac) {
                for k in 0..LANES {
                    let w = g * exp_approx::<F>(zc[k] + pc[k] + off);
                    dc[k] -= w;
                    ac[k] += w;
                }
            }
            for (((&zv, &pv), dv), av) in zc
                .remainder()
                .iter()
                .zip(pc.remainder())
                .zip(dc.into_remainder())
                .zip(ac.into_remainder())
            {
                let w = g * exp_approx::<F>(zv + pv + off);
                *dv -= w;
                *av += w;
            }
        }
    }
}

ic_nn::avx2_fma_dispatch! {
    /// [`lse_rows_generic`], with FMA when the CPU has it.
    fn lse_rows(z: &[f32], add: &[f32], base: &[f32], shift: Option<&[f32]>, out: &mut [f32]) = lse_rows_generic;
}

ic_nn::avx2_fma_dispatch! {
    /// [`bwd_rows_generic`], with FMA when the CPU has it.
    #[allow(clippy::too_many_arguments)]
    fn bwd_rows(z: &[f32], u: &[f32], la: &[f32], extra: &[f32], c: &[f32], gv: &[f32], vprev: &[f32], dz: &mut [f32], gu: &mut [f32], colacc: &mut [f32]) = bwd_rows_generic;
}

/// out[r] = base[r] − LSE_j(z[r, j] + add[j]) for all rows, in parallel blocks of rows.
pub(super) fn lse_all_rows(
    z: &[f32],
    add: &[f32],
    base: &[f32],
    shift: Option<&[f32]>,
    out: &mut [f32],
) {
    let n = add.len();
    let rows = out.len();
    if rows * n <= GRAIN {
        lse_rows(z, add, base, shift, out);
        return;
    }
    let rpt = rows_per_task(n);
    out.par_chunks_mut(rpt).enumerate().for_each(|(t, o)| {
        let r0 = t * rpt;
        let r1 = r0 + o.len();
        let sh = shift.map(|c| &c[r0..r1]);
        lse_rows(&z[r0 * n..r1 * n], add, &base[r0..r1], sh, o);
    });
}

/// max_j |a_j − b_j| ≤ 40 (false on NaN).
pub(super) fn close_enough(a: &[f32], b: &[f32]) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 40.0)
}

/// Runs the k iterations for one pair, filling `us` (`[k, M+1]`) and `vs` (`[k, N+1]`).
pub(super) fn forward_pair(
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
    let zeros = vec![0.0f32; n1];
    // Shifts for the LSEs: the previous iteration's LSE of the same row (la − u_{t−1}) or column
    // (lb − v_{t−1}). It stays within ±40 of the new max whenever the potential it is added to
    // moved by at most 40 since then (LSE − ln(len) ≤ max ≤ LSE), which makes the max pass
    // unnecessary; otherwise the max is computed as usual.
    let mut row_shift = vec![0.0f32; m1];
    let mut col_shift = vec![0.0f32; n1];
    for t in 0..k {
        let (done_u, cur_u) = us.split_at_mut(t * m1);
        let (done_v, cur_v) = vs.split_at_mut(t * n1);
        let vprev: &[f32] = if t == 0 {
            &zeros
        } else {
            &done_v[(t - 1) * n1..]
        };
        let vprev2: &[f32] = if t < 2 {
            &zeros
        } else {
            &done_v[(t - 2) * n1..(t - 1) * n1]
        };
        let u = &mut cur_u[..m1];
        let row_sh = if t >= 1 && close_enough(vprev, vprev2) {
            for ((c, &a), &up) in row_shift.iter_mut().zip(&la).zip(&done_u[(t - 1) * m1..]) {
                *c = a - up;
            }
            Some(&row_shift[..])
        } else {
            None
        };
        lse_all_rows(z, vprev, &la, row_sh, u);
        let col_sh = if t >= 1 && close_enough(u, &done_u[(t - 1) * m1..]) {
            for ((c, &b), &vp) in col_shift.iter_mut().zip(&lb).zip(vprev) {
                *c = b - vp;
            }
            Some(&col_shift[..])
        } else {
            None
        };
        lse_all_rows(zt, u, &lb, col_sh, &mut cur_v[..n1]);
    }
}

/// Gradient w.r.t. the scores of one pair, by replaying the unrolled iterations in reverse.
///
/// With Q^t_ij = exp(Z_ij + u^t_i + v^t_j − lb_j) (column softmax of the v-update) and
/// R^t_ij = exp(Z_ij + v^{t−1}_j + u^t_i − la_i) (row softmax of the u-update):
///   dZ = G − Σ_t (gv^t_j Q^t_ij + gu^t_i R^t_ij),
///   gu^t_i = [t = k] Σ_j G_ij − Σ_j gv^t_j Q^t_ij,
///   gv^k_j = Σ_i G_ij,  gv^{t−1}_j = −Σ_i gu^t_i R^t_ij.
/// One pass over Z per iteration (gu^t_i only needs row i), two exps per entry.
#[allow(clippy::too_many_arguments)]
pub(super) fn backward_pair(
    z: &[f32],
    g: &[f32],
    m: usize,
    n: usize,
    k: usize,
    us: &[f32],
    vs: &[f32],
    lambda: f32,
    ds: &mut [f32],
) {
    let (m1, n1) = (m + 1, n + 1);
    let (la, lb) = log_marginals(m, n);
    let mut dz = g.to_vec();
    let mut extra = vec![0.0f32; m1];
    let mut gv = vec![0.0f32; n1];
    for (grow, e) in g.chunks_exact(n1).zip(extra.iter_mut()) {
        *e = grow.iter().sum();
        for (a, &x) in gv.iter_mut().zip(grow) {
            *a += x;
        }
    }
    let zeros = vec![0.0f32; n1];
    let mut gu = vec![0.0f32; m1];
    let mut c = vec![0.0f32; n1];
    let rpt = rows_per_task(n1);
    for t in (0..k).rev() {
        let u = &us[t * m1..(t + 1) * m1];
        let v = &vs[t * n1..(t + 1) * n1];
        let vprev: &[f32] = if t == 0 {
            &zeros
        } else {
            &vs[(t - 1) * n1..t * n1]
        };
        for ((cj, &vj), &lbj) in c.iter_mut().zip(v).zip(&lb) {
            *cj = vj - lbj;
        }
        let colsum = if m1 * n1 <= GRAIN {
            let mut acc = vec![0.0f32; n1];
            bwd_rows(
                z, u, &la, &extra, &c, &gv, vprev, &mut dz, &mut gu, &mut acc,
            );
            acc
        } else {
            let (extra_r, c_r, gv_r, la_r) = (&extra, &c, &gv, &la);
            dz.par_chunks_mut(rpt * n1)
                .zip(gu.par_chunks_mut(rpt))
                .enumerate()
                .map(|(ti, (dzc, guc))| {
                    let r0 = ti * rpt;
                    let r1 = r0 + guc.len();
                    let mut acc = vec![0.0f32; n1];
                    bwd_rows(
                        &z[r0 * n1..r1 * n1],
                        &u[r0..r1],
                        &la_r[r0..r1],
                        &extra_r[r0..r1],
                        c_r,
                        gv_r,
                        vprev,
                        dzc,
                        guc,
                        &mut acc,
                    );
                    acc
                })
                .reduce(
                    || vec![0.0f32; n1],
                    |mut a, b| {
                        for (x, y) in a.iter_mut().zip(&b) {
                            *x += y;
                        }
                        a
                    },
                )
        };
        for (g, s) in gv.iter_mut().zip(&colsum) {
            *g = -s;
        }
        if t + 1 == k {
            extra.iter_mut().for_each(|e| *e = 0.0);
        }
    }
    let inv = (1.0 / lambda as f64) as f32;
    for (dsr, dzr) in ds.chunks_exact_mut(n).zip(dz.chunks_exact(n1)) {
        for (d, &x) in dsr.iter_mut().zip(&dzr[..n]) {
            *d = x * inv;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generic_and_fma_kernels_agree() {
        // Whatever the CPU, compare the plain (no-FMA) kernels with the FMA ones (the generic
        // code with `mul_add`; on x86-64 without FMA hardware this is the slow libm fallback).
        let (m1, n1) = (9usize, 37usize);
        let z: Vec<f32> = (0..m1 * n1)
            .map(|i| ((i * 7919) % 101) as f32 * 0.05 - 2.5)
            .collect();
        let add: Vec<f32> = (0..n1).map(|j| (j as f32 * 0.37).sin()).collect();
        let base = vec![0.5f32; m1];
        let shift: Vec<f32> = (0..m1).map(|i| i as f32 * 0.1).collect();
        for sh in [None, Some(&shift[..])] {
            let mut a = vec![0.0f32; m1];
            let mut b = vec![0.0f32; m1];
            lse_rows_generic::<false>(&z, &add, &base, sh, &mut a);
            lse_rows_generic::<true>(&z, &add, &base, sh, &mut b);
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() < 1e-5, "{x} vs {y}");
            }
        }
        let u: Vec<f32> = (0..m1).map(|i| -(i as f32) * 0.2).collect();
        let la = vec![0.0f32; m1];
        let extra = vec![0.3f32; m1];
        let gv: Vec<f32> = (0..n1).map(|j| (j as f32).cos()).collect();
        let run = |fma: bool| {
            let mut dz = vec![0.0f32; m1 * n1];
            let mut gu = vec![0.0f32; m1];
            let mut acc = vec![0.0f32; n1];
            if fma {
                bwd_rows_generic::<true>(
                    &z, &u, &la, &extra, &add, &gv, &add, &mut dz, &mut gu, &mut acc,
                );
            } else {
                bwd_rows_generic::<false>(
                    &z, &u, &la, &extra, &add, &gv, &add, &mut dz, &mut gu, &mut acc,
                );
            }
            (dz, gu, acc)
        };
        let (d0, g0, a0) = run(false);
        let (d1, g1, a1) = run(true);
        for (x, y) in d0
            .iter()
            .chain(&g0)
            .chain(&a0)
            .zip(d1.iter().chain(&g1).chain(&a1))
        {
            assert!((x - y).abs() <= 1e-4 * x.abs().max(1.0), "{x} vs {y}");
        }
    }
}
