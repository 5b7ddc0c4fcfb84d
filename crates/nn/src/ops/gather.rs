//! The EdgeConv gather-max of DGCNN: for each point, the channel-wise max of a feature over
//! its k neighbours in a graph, without building the `[B, C, P, k]` edge tensor.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp2, CustomOp3, D, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// `out[b, c, i] = max_{r < k} a[b, c, graph[b, i·k + r]]` for `a` `[B, C, P]` and `graph`
/// `[B, P·k]` (u32): the EdgeConv's gather and max over the neighbours in one pass.
///
/// On the CPU with f32 a fused op that never builds the `[B, C, P, k]` edge tensor; its
/// backward sends each output's gradient to the neighbour that attained the max (the first one
/// on ties). Elsewhere the gather (`index_select`) and `max` tensor ops, whose gradient goes
/// to every tied neighbour instead — the same away from ties.
pub fn neighbour_max(a: &Tensor, graph: &Tensor, k: usize) -> Result<Tensor> {
    let (b, _, p) = a.dims3()?;
    if graph.dims2()? != (b, p * k) || k == 0 {
        candle_core::bail!(
            "neighbour_max: graph {:?} does not fit features {:?} with k = {k}",
            graph.dims(),
            a.dims()
        );
    }
    if a.device().is_cpu() && a.dtype() == DType::F32 && graph.dtype() == DType::U32 {
        return a.contiguous()?.apply_op2(
            &graph.contiguous()?,
            NeighbourMax {
                k,
                argmax: Mutex::new(None),
            },
        );
    }
    neighbour_max_reference(a, graph, k)
}

/// `neighbour_max(a, graph, k) + centre` for `centre` `[B, C, P]`: the EdgeConv's pooled
/// neighbour term plus its centre term. On the CPU with f32 the add happens in the same op
/// (a separate element-wise add on candle's thread pool cost more in thread hand-offs than
/// the add itself); elsewhere [`neighbour_max_reference`] and an add.
pub fn neighbour_max_add(a: &Tensor, graph: &Tensor, k: usize, centre: &Tensor) -> Result<Tensor> {
    let (b, c, p) = a.dims3()?;
    if graph.dims2()? != (b, p * k) || k == 0 || centre.dims() != [b, c, p] {
        candle_core::bail!(
            "neighbour_max_add: graph {:?} or centre {:?} does not fit features {:?} with k = {k}",
            graph.dims(),
            centre.dims(),
            a.dims()
        );
    }
    let cpu_f32 = |t: &Tensor| t.device().is_cpu() && t.dtype() == DType::F32;
    if cpu_f32(a) && cpu_f32(centre) && graph.dtype() == DType::U32 {
        return a.contiguous()?.apply_op3(
            &graph.contiguous()?,
            &centre.contiguous()?,
            NeighbourMax {
                k,
                argmax: Mutex::new(None),
            },
        );
    }
    neighbour_max_reference(a, graph, k)? + centre
}

/// [`neighbour_max`] from candle's gather and max (the test oracle, and non-CPU devices).
pub fn neighbour_max_reference(a: &Tensor, graph: &Tensor, k: usize) -> Result<Tensor> {
    let (b, c, p) = a.dims3()?;
    let mut parts = Vec::with_capacity(b);
    for i in 0..b {
        parts.push(a.get(i)?.index_select(&graph.get(i)?, 1)?);
    }
    Tensor::stack(&parts, 0)?
        .reshape((b, c, p, k))?
        .max(D::Minus1)
}

/// The fused gather-max; `argmax` keeps, for the backward pass, the point index that won
/// each output, channel-last (`[B, P, C]`: transposed only if a backward pass asks for it).
struct NeighbourMax {
    k: usize,
    argmax: Mutex<Option<Arc<Vec<u32>>>>,
}

/// Points per parallel task of the gather.
const POINTS_PER_TASK: usize = 64;

impl NeighbourMax {
    /// `(out [B, C, P], argmax [B, P, C])`.
    ///
    /// Channel-last inside: each cloud's `[C, P]` features are transposed to `[P, C]`, so a
    /// point's max over its neighbours is a running max of contiguous `C`-vectors (vectorised,
    /// selects rather than branches) instead of `C · k` scattered scalar reads with a branch
    /// each; the max is transposed back. The same values and (first-on-ties) arg-max as the
    /// scalar loop over the neighbours in graph order.
    fn run(
        &self,
        a: &[f32],
        graph: &[u32],
        b: usize,
        c: usize,
        p: usize,
    ) -> Result<(Vec<f32>, Vec<u32>)> {
        let k = self.k;
        if let Some(bad) = graph.iter().find(|&&j| j as usize >= p) {
            candle_core::bail!("neighbour_max: neighbour index {bad} ≥ {p} points");
        }
        let mut out = super::cpu::zeros_f32(b * c * p);
        let mut arg = vec![0u32; b * p * c];
        let mut at = super::cpu::zeros_f32(p * c);
        let mut max_t = super::cpu::zeros_f32(p * c);
        for bi in 0..b {
            transpose::transpose(&a[bi * c * p..(bi + 1) * c * p], &mut at, p, c);
            let g = &graph[bi * p * k..(bi + 1) * p * k];
            let at = &at;
            max_t
                .par_chunks_mut(POINTS_PER_TASK * c)
                .zip(arg[bi * p * c..(bi + 1) * p * c].par_chunks_mut(POINTS_PER_TASK * c))
                .enumerate()
                .for_each(|(t, (mb, ab))| {
                    let rows = mb.chunks_exact_mut(c).zip(ab.chunks_exact_mut(c));
                    for (r, (mrow, arow)) in rows.enumerate() {
                        let i = t * POINTS_PER_TASK + r;
                        let nb = &g[i * k..(i + 1) * k];
                        let j0 = nb[0] as usize;
                        mrow.copy_from_slice(&at[j0 * c..(j0 + 1) * c]);
                        arow.fill(nb[0]);
                        for &j in &nb[1..] {
                            let xr = &at[j as usize * c..(j as usize + 1) * c];
                            running_max(mrow, arow, xr, j);
                        }
                    }
                });
            transpose::transpose(&max_t, &mut out[bi * c * p..(bi + 1) * c * p], c, p);
        }
        Ok((out, arg))
    }
}

/// `m[c], a[c] = x[c], j` where `x[c] > m[c]` (strictly: the earlier neighbour keeps a tie).
/// Written with bit masks so that it compiles to straight vector code on any x86-64 (as
/// selects, LLVM emitted a branch per lane for the stores).
#[inline]
fn running_max(m: &mut [f32], a: &mut [u32], x: &[f32], j: u32) {
    for ((mv, av), &xv) in m.iter_mut().zip(a.iter_mut()).zip(x) {
        let take = 0u32.wrapping_sub((xv > *mv) as u32);
        *mv = f32::from_bits((mv.to_bits() & !take) | (xv.to_bits() & take));
        *av = (*av & !take) | (j & take);
    }
}

impl CustomOp2 for NeighbourMax {
    fn name(&self) -> &'static str {
        "ic-neighbour-max"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, c, p) = l1.shape().dims3()?;
        let (CpuStorage::F32(a), CpuStorage::U32(g)) = (s1, s2) else {
            candle_core::bail!("neighbour_max: f32 features and u32 graph expected")
        };
        let (Some((a0, a1)), Some((g0, g1))) = (l1.contiguous_offsets(), l2.contiguous_offsets())
        else {
            candle_core::bail!("neighbour_max: contiguous inputs expected")
        };
        let (out, arg) = self.run(&a[a0..a1], &g[g0..g1], b, c, p)?;
        *self.argmax.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(arg));
        Ok((CpuStorage::F32(out), Shape::from((b, c, p))))
    }

    fn bwd(
        &self,
        a: &Tensor,
        graph: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        Ok((Some(self.input_grad(a, graph, grad)?), None))
    }
}

impl CustomOp3 for NeighbourMax {
    fn name(&self) -> &'static str {
        "ic-neighbour-max-add"
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
        let (mut out, shape) = CustomOp2::cpu_fwd(self, s1, l1, s2, l2)?;
        let centre = super::cpu::f32_slice(s3, l3, "neighbour_max_add centre")?;
        let CpuStorage::F32(o) = &mut out else {
            candle_core::bail!("neighbour_max_add: f32 output expected")
        };
        if centre.len() != o.len() {
            candle_core::bail!(
                "neighbour_max_add: {} centre values for {}",
                centre.len(),
                o.len()
            );
        }
        o.par_chunks_mut(1 << 14)
            .zip(centre.par_chunks(1 << 14))
            .for_each(|(o, c)| o.iter_mut().zip(c).for_each(|(o, &c)| *o += c));
        Ok((out, shape))
    }

    fn bwd(
        &self,
        a: &Tensor,
        graph: &Tensor,
        _centre: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        Ok((
            Some(self.input_grad(a, graph, grad)?),
            None,
            Some(grad.clone()),
        ))
    }
}

impl NeighbourMax {
    /// The gradient of the features `a`: each output's gradient goes to the neighbour that
    /// won it.
    fn input_grad(&self, a: &Tensor, graph: &Tensor, grad: &Tensor) -> Result<Tensor> {
        let (b, c, p) = a.dims3()?;
        let cached = self
            .argmax
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let arg = match cached {
            Some(arg) => arg,
            None => {
                let av: Vec<f32> = a.flatten_all()?.to_vec1()?;
                let gv: Vec<u32> = graph.flatten_all()?.to_vec1()?;
                Arc::new(self.run(&av, &gv, b, c, p)?.1)
            }
        };
        // [B, P, C] → [B, C, P], the layout of the gradient rows.
        let mut arg_cp = vec![0u32; b * c * p];
        for bi in 0..b {
            let r = bi * c * p..(bi + 1) * c * p;
            transpose::transpose(&arg[r.clone()], &mut arg_cp[r], c, p);
        }
        let arg = arg_cp;
        let g = super::cpu::f32_data(grad)?;
        let mut da = super::cpu::zeros_f32(b * c * p);
        da.par_chunks_mut(p)
            .zip(g.par_chunks(p))
            .zip(arg.par_chunks(p))
            .for_each(|((d, g), am)| {
                for (&gi, &j) in g.iter().zip(am) {
                    d[j as usize] += gi;
                }
            });
        Tensor::from_vec(da, (b, c, p), a.device())
    }
}
