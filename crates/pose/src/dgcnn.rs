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

use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

use crate::config::NetConfig;
use crate::layers::{Dense, channel_linear};
use ic_nn::norm::BatchNorm1;
// The gather-max kernel lives in `ic_nn::ops`; re-exported here, where EdgeConv uses it.
pub use ic_nn::ops::gather::{neighbour_max, neighbour_max_add, neighbour_max_reference};

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
        let pooled = neighbour_max_add(&a, graph, k, &c)?;
        debug_assert_eq!(pooled.dims(), &[b, cout, p]);
        self.bn.forward_leaky_relu(&pooled, train, LEAKY_SLOPE)
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

    /// Sets the neighbours per point of the graph `forward_t` expects (the weights do not
    /// depend on it).
    pub(crate) fn set_neighbours(&mut self, k: usize) {
        self.k = k;
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
