//! Fused multi-head scaled dot-product attention (forward and backward) for the CPU.
//!
//! Vaswani et al., "Attention Is All You Need" (<https://arxiv.org/abs/1706.03762>), computed
//! block by block as in FlashAttention (Dao et al., 2022, <https://arxiv.org/abs/2205.14135>):
//! for each pair, head and block of query rows, the scores `Q·Kᵀ` of the block live only in a
//! cache-sized scratch buffer, are turned into probabilities in place and multiplied by `V`; the
//! backward pass recomputes them from the saved row log-sum-exps instead of keeping the
//! `[B, H, Pq, Pk]` attention maps (16 MB per head at 1024×1024) that the tensor-op version
//! allocates, fills and reads back several times.
//!
//! Heads are read from and written to the point-major `[B, P, d]` layout directly (head `h` is
//! the column range `h·d/H .. (h+1)·d/H`), so no transpose or copy splits or merges heads.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use super::cpu::{all_cpu_f32, f32_data, f32_slice, zeros_f32};
use super::fastmath::{Panels, dot_rows_panels, exp_approx, matmul, rows_times_matrix};
use super::softmax::softmax_last;
use super::{MatMut, MatRef};

fn check_args(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
) -> Result<(usize, usize, usize, usize)> {
    let (b, pq, d) = q.dims3()?;
    let (bk, pk, dk) = k.dims3()?;
    if v.dims3()? != (bk, pk, dk) || bk != b || dk != d {
        candle_core::bail!(
            "attention: q {:?}, k {:?}, v {:?} do not fit together",
            q.dims(),
            k.dims(),
            v.dims()
        );
    }
    if heads == 0 || d % heads != 0 {
        candle_core::bail!("attention: {d} channels do not split into {heads} heads");
    }
    if pk == 0 {
        candle_core::bail!("attention: no keys");
    }
    Ok((b, pq, pk, d))
}

/// Reference [`multi_head_attention`] from generic tensor ops (split heads, `softmax(Q·Kᵀ)·V`,
/// merge): the test oracle, and the path on non-CPU devices and dtypes.
pub fn multi_head_attention_reference(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
) -> Result<Tensor> {
    let (b, pq, pk, d) = check_args(q, k, v, heads)?;
    let split = |x: &Tensor, p: usize| {
        x.reshape((b, p, heads, d / heads))?
            .transpose(1, 2)?
            .contiguous()
    };
    let (qh, kh, vh) = (split(q, pq)?, split(k, pk)?, split(v, pk)?);
    let att = softmax_last(&qh.matmul(&kh.t()?)?)?;
    att.matmul(&vh)?.transpose(1, 2)?.reshape((b, pq, d))
}

/// `concat_h softmax(Q_h·K_hᵀ)·V_h` for `q` `[B, Pq, d]` and `k`, `v` `[B, Pk, d]` split into
/// `heads` heads of `d / heads` channels; returns `[B, Pq, d]`. The caller scales `q` (by
/// 1/√(d/heads) for scaled dot-product attention).
///
/// On the CPU with f32 inputs a fused op (forward and exact backward, see the module docs);
/// elsewhere [`multi_head_attention_reference`]. The two agree to f32 rounding (tested).
pub fn multi_head_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Result<Tensor> {
    check_args(q, k, v, heads)?;
    if !all_cpu_f32(&[q, k, v]) {
        return multi_head_attention_reference(q, k, v, heads);
    }
    q.contiguous()?.apply_op3(
        &k.contiguous()?,
        &v.contiguous()?,
        FusedAttention {
            heads,
            lse: Mutex::new(None),
        },
    )
}

/// The fused op; `lse` keeps the row log-sum-exps `[B·H, Pq]` of the last forward for the
/// backward pass.
struct FusedAttention {
    heads: usize,
    lse: Mutex<Option<Arc<Vec<f32>>>>,
}

/// Shapes of one call.
#[derive(Clone, Copy)]
struct Dims {
    b: usize,
    pq: usize,
    pk: usize,
    d: usize,
    heads: usize,
}

impl Dims {
    fn dh(&self) -> usize {
        self.d / self.heads
    }

    /// Query rows per block: the block's scores take at most ≈ 128 KB (fits in L2).
    fn block_rows(&self) -> usize {
        (32 * 1024 / self.pk.max(1)).clamp(8, 256)
    }
}

/// In place, each row of `s` (`rows × n`) becomes `exp(s − row max)` (unnormalised: the
/// caller scales the row's product with `V` by `inv` = 1/Σ instead of the `n` entries), `lse`
/// receives the row's log-sum-exp and `inv` the inverse sum; with `recompute`, `lse` is read
/// instead and each row becomes `exp(s − lse)` (the probabilities, in the backward pass).
#[inline(always)]
fn softmax_rows_generic<const F: bool>(
    s: &mut [f32],
    n: usize,
    lse: &mut [f32],
    inv: &mut [f32],
    recompute: bool,
) {
    let mut inv = inv.iter_mut();
    for (row, l) in s.chunks_exact_mut(n).zip(lse.iter_mut()) {
        if recompute {
            let c = *l;
            for x in row.iter_mut() {
                *x = exp_approx::<F>(*x - c);
            }
            continue;
        }
        let mut mx = [f32::NEG_INFINITY; 8];
        let mut chunks = row.chunks_exact(8);
        for ch in &mut chunks {
            for k in 0..8 {
                mx[k] = if ch[k] > mx[k] { ch[k] } else { mx[k] };
            }
        }
        let mut m = f32::NEG_INFINITY;
        for &x in mx.iter().chain(chunks.remainder()) {
            m = if x > m { x } else { m };
        }
        let mut acc = [0.0f32; 8];
        let mut chunks = row.chunks_exact_mut(8);
        for ch in &mut chunks {
            for k in 0..8 {
                let e = exp_approx::<F>(ch[k] - m);
                ch[k] = e;
                acc[k] += e;
            }
        }
        let mut sum: f32 = acc.iter().sum();
        for x in chunks.into_remainder() {
            let e = exp_approx::<F>(*x - m);
            *x = e;
            sum += e;
        }
        *inv.next().expect("one inverse sum per row") = 1.0 / sum;
        *l = m + sum.ln();
    }
}

crate::avx2_fma_dispatch! {
    /// [`softmax_rows_generic`] with FMA when the CPU has it.
    fn softmax_rows(s: &mut [f32], n: usize, lse: &mut [f32], inv: &mut [f32], recompute: bool) = softmax_rows_generic;
}

/// `ds = p ∘ (dp − D_row)` in place in `dp` (rows × n).
fn softmax_grad_rows(p: &[f32], dp: &mut [f32], n: usize, dsum: &[f32]) {
    for ((pr, dr), &dd) in p.chunks_exact(n).zip(dp.chunks_exact_mut(n)).zip(dsum) {
        for (x, &pv) in dr.iter_mut().zip(pr) {
            *x = pv * (*x - dd);
        }
    }
}

/// The products of one head with a point-major `[n, dh]` matrix `M` (`K` or `V`), by the
/// micro-kernels of [`super::fastmath`] when the head width is a multiple of 8 (the presets:
/// 32, 128), by the general GEMM otherwise.
struct HeadProducts<'a> {
    /// `M` packed for [`dot_rows_panels`] (products `A·Mᵀ`), when the kernels apply.
    panels: Option<Panels>,
    /// `Mᵀ` packed likewise (products `A·M`), when the kernels apply and it was asked for.
    panels_t: Option<Panels>,
    /// `M`: `[n, dh]` with row stride `d`.
    m: MatRef<'a>,
}

impl<'a> HeadProducts<'a> {
    /// `rows`: the `[n, d]` point-major matrix starting at the head's first column; `dot` and
    /// `times` say which of the two products will be used.
    fn new(rows: &'a [f32], n: usize, dh: usize, d: usize, dot: bool, times: bool) -> Self {
        let kernels = dh % 8 == 0;
        let m = MatRef::new(rows, n, dh, d);
        HeadProducts {
            panels: (kernels && dot).then(|| Panels::pack(m)),
            panels_t: (kernels && times).then(|| Panels::pack(m.t())),
            m,
        }
    }

    /// `dst[i][j] = Σ_c a[i][c]·M[j][c]` for `a` `[r, dh]`; `dst` is `[r, n]`.
    fn dot(&self, a: MatRef, dst: &mut [f32]) {
        let (r, n) = (a.rows(), self.m.rows());
        let dst = MatMut::new(dst, r, n, n);
        match &self.panels {
            Some(p) => dot_rows_panels(a, p, dst),
            None => matmul(a, self.m.t(), dst, false),
        }
    }

    /// `dst[i][c] = Σ_j a[i][j]·M[j][c]` for `a` `[r, n]`; `dst` is `[r, dh]`.
    fn times(&self, a: MatRef, dst: &mut [f32]) {
        match &self.panels_t {
            Some(p) => {
                let (r, dh) = (a.rows(), self.m.cols());
                dot_rows_panels(a, p, MatMut::new(dst, r, dh, dh))
            }
            None => times_rows(a, self.m, dst, false),
        }
    }
}

/// `dst (=|+=) l·m` with `m` `[inner, dh]` (row-major, any row stride) and `dst` `[·, dh]`
/// contiguous.
fn times_rows(l: MatRef, m: MatRef, dst: &mut [f32], accumulate: bool) {
    let dh = m.cols();
    let dst = MatMut::new(dst, l.rows(), dh, dh);
    if dh % 8 == 0 {
        rows_times_matrix(l, m, dst, accumulate)
    } else {
        matmul(l, m, dst, accumulate)
    }
}

/// Forward of one (pair, head): writes `out` (`[Pq, dh]`) and `lse` (`[Pq]`).
fn forward_head(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    h: usize,
    dims: Dims,
    out: &mut [f32],
    lse: &mut [f32],
) {
    let Dims { pq, pk, d, .. } = dims;
    let dh = dims.dh();
    let off = h * dh;
    let br = dims.block_rows();
    let mut s = vec![0.0f32; br * pk];
    let mut inv = vec![0.0f32; br];
    let keys = HeadProducts::new(&k[off..], pk, dh, d, true, false);
    let values = HeadProducts::new(&v[off..], pk, dh, d, false, true);
    for r0 in (0..pq).step_by(br) {
        let r = br.min(pq - r0);
        let s = &mut s[..r * pk];
        keys.dot(MatRef::new(&q[r0 * d + off..], r, dh, d), s);
        softmax_rows(s, pk, &mut lse[r0..r0 + r], &mut inv[..r], false);
        let o = &mut out[r0 * dh..(r0 + r) * dh];
        values.times(MatRef::new(s, r, pk, pk), o);
        for (row, &f) in o.chunks_exact_mut(dh).zip(&inv[..r]) {
            row.iter_mut().for_each(|x| *x *= f);
        }
    }
}

/// Gradients of one (pair, head): `dq` `[Pq, dh]`, `dk`, `dv` `[Pk, dh]`.
#[allow(clippy::too_many_arguments)]
fn backward_head(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    o: &[f32],
    g: &[f32],
    lse: &[f32],
    h: usize,
    dims: Dims,
    dq: &mut [f32],
    dk: &mut [f32],
    dv: &mut [f32],
) {
    let Dims { pq, pk, d, .. } = dims;
    let dh = dims.dh();
    let off = h * dh;
    let br = dims.block_rows();
    let mut p = vec![0.0f32; br * pk];
    let mut dp = vec![0.0f32; br * pk];
    let mut lse_blk = vec![0.0f32; br];
    let mut dsum = vec![0.0f32; br];
    let keys = HeadProducts::new(&k[off..], pk, dh, d, true, true);
    let values = HeadProducts::new(&v[off..], pk, dh, d, true, false);
    for r0 in (0..pq).step_by(br) {
        let r = br.min(pq - r0);
        let (p, dp) = (&mut p[..r * pk], &mut dp[..r * pk]);
        let (qb, gb) = (&q[r0 * d + off..], &g[r0 * d + off..]);
        // P = exp(Q·Kᵀ − lse).
        keys.dot(MatRef::new(qb, r, dh, d), p);
        lse_blk[..r].copy_from_slice(&lse[r0..r0 + r]);
        softmax_rows(p, pk, &mut lse_blk[..r], &mut [], true);
        // dV += Pᵀ·dO.
        let gm = MatRef::new(gb, r, dh, d);
        times_rows(MatRef::new(p, r, pk, pk).t(), gm, dv, r0 > 0);
        // dP = dO·Vᵀ;  D_i = Σ_c dO_ic O_ic;  dS = P ∘ (dP − D).
        values.dot(gm, dp);
        for (i, ds) in dsum[..r].iter_mut().enumerate() {
            let row = (r0 + i) * d + off;
            *ds = g[row..row + dh]
                .iter()
                .zip(&o[row..row + dh])
                .map(|(a, b)| a * b)
                .sum();
        }
        softmax_grad_rows(p, dp, pk, &dsum[..r]);
        let dsm = MatRef::new(dp, r, pk, pk);
        // dQ = dS·K;  dK += dSᵀ·Q.
        keys.times(dsm, &mut dq[r0 * dh..(r0 + r) * dh]);
        times_rows(dsm.t(), MatRef::new(qb, r, dh, d), dk, r0 > 0);
    }
}

/// Copies per-(pair, head) blocks `[P, dh]` into the point-major `[B, P, d]` layout.
fn merge_heads(parts: &[Vec<f32>], b: usize, p: usize, d: usize, heads: usize) -> Vec<f32> {
    let dh = d / heads;
    let mut out = zeros_f32(b * p * d);
    if dh == 0 {
        return out;
    }
    // Row r = bi·p + i of the output gathers row i of each of batch bi's heads.
    const ROWS: usize = 64;
    out.par_chunks_mut(d * ROWS)
        .enumerate()
        .for_each(|(chunk, rows)| {
            for (j, row) in rows.chunks_exact_mut(d).enumerate() {
                let (bi, i) = ((chunk * ROWS + j) / p, (chunk * ROWS + j) % p);
                for (h, dst) in row.chunks_exact_mut(dh).enumerate() {
                    dst.copy_from_slice(&parts[bi * heads + h][i * dh..(i + 1) * dh]);
                }
            }
        });
    out
}

impl FusedAttention {
    fn run_forward(&self, q: &[f32], k: &[f32], v: &[f32], dims: Dims) -> (Vec<f32>, Vec<f32>) {
        let Dims {
            b,
            pq,
            pk,
            d,
            heads,
        } = dims;
        let dh = dims.dh();
        let results: Vec<(Vec<f32>, Vec<f32>)> = (0..b * heads)
            .into_par_iter()
            .map(|t| {
                let (bi, h) = (t / heads, t % heads);
                let mut out = vec![0.0f32; pq * dh];
                let mut lse = vec![0.0f32; pq];
                forward_head(
                    &q[bi * pq * d..(bi + 1) * pq * d],
                    &k[bi * pk * d..(bi + 1) * pk * d],
                    &v[bi * pk * d..(bi + 1) * pk * d],
                    h,
                    dims,
                    &mut out,
                    &mut lse,
                );
                (out, lse)
            })
            .collect();
        let (outs, lses): (Vec<Vec<f32>>, Vec<Vec<f32>>) = results.into_iter().unzip();
        (merge_heads(&outs, b, pq, d, heads), lses.concat())
    }
}

impl CustomOp3 for FusedAttention {
    fn name(&self) -> &'static str {
        "ic-fused-attention"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, pq, d) = l1.shape().dims3()?;
        let pk = l2.shape().dims3()?.1;
        let dims = Dims {
            b,
            pq,
            pk,
            d,
            heads: self.heads,
        };
        let (q, k, v) = (
            f32_slice(s1, l1, "attention q")?,
            f32_slice(s2, l2, "attention k")?,
            f32_slice(s3, l3, "attention v")?,
        );
        let (out, lse) = self.run_forward(q, k, v, dims);
        *self.lse.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(lse));
        Ok((CpuStorage::F32(out), Shape::from((b, pq, d))))
    }

    fn bwd(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        res: &Tensor,
        grad_res: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (b, pq, d) = q.dims3()?;
        let pk = k.dim(1)?;
        let heads = self.heads;
        let dims = Dims {
            b,
            pq,
            pk,
            d,
            heads,
        };
        let dh = dims.dh();
        let flat = f32_data;
        let (qv, kv, vv, ov, gv) = (flat(q)?, flat(k)?, flat(v)?, flat(res)?, flat(grad_res)?);
        let cached = self.lse.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let lse = match cached {
            Some(l) => l,
            None => Arc::new(self.run_forward(&qv, &kv, &vv, dims).1),
        };
        let grads: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..b * heads)
            .into_par_iter()
            .map(|t| {
                let (bi, h) = (t / heads, t % heads);
                let (qs, ks) = (
                    bi * pq * d..(bi + 1) * pq * d,
                    bi * pk * d..(bi + 1) * pk * d,
                );
                let mut dq = vec![0.0f32; pq * dh];
                let mut dk = vec![0.0f32; pk * dh];
                let mut dv = vec![0.0f32; pk * dh];
                backward_head(
                    &qv[qs.clone()],
                    &kv[ks.clone()],
                    &vv[ks],
                    &ov[qs.clone()],
                    &gv[qs],
                    &lse[t * pq..(t + 1) * pq],
                    h,
                    dims,
                    &mut dq,
                    &mut dk,
                    &mut dv,
                );
                (dq, dk, dv)
            })
            .collect();
        let mut dqs = Vec::with_capacity(grads.len());
        let mut dks = Vec::with_capacity(grads.len());
        let mut dvs = Vec::with_capacity(grads.len());
        for (a, bb, c) in grads {
            dqs.push(a);
            dks.push(bb);
            dvs.push(c);
        }
        let dev = q.device();
        let dq = Tensor::from_vec(merge_heads(&dqs, b, pq, d, heads), (b, pq, d), dev)?;
        let dk = Tensor::from_vec(merge_heads(&dks, b, pk, d, heads), (b, pk, d), dev)?;
        let dv = Tensor::from_vec(merge_heads(&dvs, b, pk, d, heads), (b, pk, d), dev)?;
        Ok((Some(dq), Some(dk), Some(dv)))
    }
}
