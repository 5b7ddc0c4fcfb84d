//! DGCNN encoder: EdgeConv layers on a k-NN graph, concatenated, then a 1×1 convolution.
//!
//! Wang et al., "Dynamic Graph CNN for Learning on Point Clouds", TOG 2019
//! (<https://arxiv.org/abs/1801.07829>), as used by DCP (Wang & Solomon, ICCV 2019,
//! <https://arxiv.org/abs/1905.03304>) and by the paper (Dang et al., CVPR 2021, Sec. 3).
//!
//! Layout and two implementation choices, both measured on CPU:
//! - channel-first `[B, C, P]` features; the EdgeConv's shared 1×1 convolution of the edge
//!   feature `[x_j − x_i, x_i]` is split as `W·[x_j − x_i; x_i] = Wₙ·x_j + W_c·x_i` and applied
//!   per point *before* gathering the neighbours (k times fewer multiply-adds, identical output);
//! - BN and LeakyReLU after the max over neighbours (see [`EdgeConv`]);
//! - the graph is the k-NN graph of the input coordinates, computed once in plain Rust
//!   ([`crate::knn`]) and shared by all layers (DGCNN recomputes it in feature space per layer;
//!   the static graph is cheaper and, for registration, what matters is local geometry).

use std::sync::{Arc, Mutex};

use candle_core::{CpuStorage, CustomOp2, D, DType, Layout, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

use crate::config::NetConfig;
use crate::layers::{Dense, channel_linear};
use ic_nn::norm::BatchNorm1;

/// One EdgeConv: `LeakyReLU(BN(max_{j∈N(i)} (Wₙ·x_j + W_c·x_i)))`.
///
/// DGCNN applies BN and LeakyReLU to every edge before the max; here the max comes first
/// (BN's statistics are taken over the pooled features). For a positive BN scale the two are
/// the same function at inference (a per-channel increasing affine map and LeakyReLU commute
/// with the max); the edge-domain tensors `[B, C', P, k]` then only see one gather and one max,
/// which made the CPU training step several times faster.
#[derive(Clone, Debug)]
pub struct EdgeConv {
    neighbour: Dense,
    centre: Dense,
    bn: BatchNorm1,
}

impl EdgeConv {
    pub fn new(vb: VarBuilder, in_dims: usize, out_dims: usize, momentum: f64) -> Result<Self> {
        // fan-in of the original 1×1 conv over the 2·C edge feature.
        Ok(EdgeConv {
            neighbour: Dense::with_fan_in(vb.pp("neighbour"), in_dims, out_dims, 2 * in_dims)?,
            centre: Dense::with_fan_in(vb.pp("centre"), in_dims, out_dims, 2 * in_dims)?,
            bn: BatchNorm1::new(vb.pp("bn"), out_dims, momentum)?,
        })
    }

    /// `x`: `[B, C, P]`; `graph`: `[B, P·k]` u32 neighbour indices. Returns `[B, C', P]`.
    pub fn forward_t(&self, x: &Tensor, graph: &Tensor, k: usize, train: bool) -> Result<Tensor> {
        let (b, _, p) = x.dims3()?;
        let wn = self.neighbour.weight();
        let wc = self.centre.weight();
        let cout = wn.dim(0)?;
        // Per-point products: [C', C] × [B, C, P] → [B, C', P].
        let a = channel_linear(wn, x)?;
        let c = channel_linear(wc, x)?;
        // max_j (Wₙ·x_j + W_c·x_i) = max_j (Wₙ·x_j) + W_c·x_i: the centre term is constant over
        // the neighbours, so only the neighbour term is gathered and pooled.
        let pooled = neighbour_max(&a, graph, k)?;
        debug_assert_eq!(pooled.dims(), &[b, cout, p]);
        self.bn
            .forward_leaky_relu(&(pooled + c)?, train, LEAKY_SLOPE)
    }
}

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
        let mut out = vec![0.0f32; b * c * p];
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
        let g: Vec<f32> = grad.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        let mut da = vec![0.0f32; b * c * p];
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

/// Negative slope of DGCNN's LeakyReLU.
pub const LEAKY_SLOPE: f32 = 0.2;

/// The encoder: EdgeConvs 64-64-128-256 (configurable), concatenated, 1×1 conv to `emb_dims`
/// with BN and LeakyReLU. Input `[B, 3, P]`, output `[B, emb, P]`.
#[derive(Clone, Debug)]
pub struct Dgcnn {
    edges: Vec<EdgeConv>,
    out: Dense,
    out_bn: BatchNorm1,
    k: usize,
}

impl Dgcnn {
    pub fn new(vb: VarBuilder, cfg: &NetConfig) -> Result<Self> {
        let mut edges = Vec::new();
        let mut c = 3;
        for (i, &o) in cfg.edge_channels.iter().enumerate() {
            edges.push(EdgeConv::new(
                vb.pp(format!("edge{i}")),
                c,
                o,
                cfg.bn_momentum,
            )?);
            c = o;
        }
        let total: usize = cfg.edge_channels.iter().sum();
        Ok(Dgcnn {
            edges,
            out: Dense::new(vb.pp("out"), total, cfg.emb_dims, false)?,
            out_bn: BatchNorm1::new(vb.pp("out_bn"), cfg.emb_dims, cfg.bn_momentum)?,
            k: cfg.k,
        })
    }

    pub fn forward_t(&self, x: &Tensor, graph: &Tensor, train: bool) -> Result<Tensor> {
        let mut h = x.clone();
        let mut feats = Vec::with_capacity(self.edges.len());
        for e in &self.edges {
            h = e.forward_t(&h, graph, self.k, train)?;
            feats.push(h.clone());
        }
        let cat = Tensor::cat(&feats, 1)?;
        let y = channel_linear(self.out.weight(), &cat)?;
        self.out_bn.forward_leaky_relu(&y, train, LEAKY_SLOPE)
    }
}
