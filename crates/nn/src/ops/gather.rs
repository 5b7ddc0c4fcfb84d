//! The EdgeConv gather-max of DGCNN: for each point, the channel-wise max of a feature over
//! its k neighbours in a graph, without building the `[B, C, P, k]` edge tensor.

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp2, D, DType, Layout, Result, Shape, Tensor};
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
/// each output (`[B, C, P]`).
struct NeighbourMax {
    k: usize,
    argmax: Mutex<Option<Arc<Vec<u32>>>>,
}

impl NeighbourMax {
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
        let mut arg = vec![0u32; b * c * p];
        out.par_chunks_mut(p)
            .zip(arg.par_chunks_mut(p))
            .enumerate()
            .for_each(|(row, (o, am))| {
                let bi = row / c;
                let src = &a[row * p..(row + 1) * p];
                let g = &graph[bi * p * k..(bi + 1) * p * k];
                for ((ov, av), nb) in o.iter_mut().zip(am.iter_mut()).zip(g.chunks_exact(k)) {
                    let mut best = nb[0];
                    let mut bv = src[best as usize];
                    for &j in &nb[1..] {
                        let x = src[j as usize];
                        if x > bv {
                            bv = x;
                            best = j;
                        }
                    }
                    *ov = bv;
                    *av = best;
                }
            });
        Ok((out, arg))
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
        Ok((Some(Tensor::from_vec(da, (b, c, p), a.device())?), None))
    }
}
