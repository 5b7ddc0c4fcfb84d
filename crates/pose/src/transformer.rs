//! The attention block φ of DCP: one encoder layer and one decoder layer of a pre-norm
//! transformer, giving `φ(a, b) = decoder(a, memory = encoder(b))`.
//!
//! Vaswani et al., "Attention Is All You Need" (<https://arxiv.org/abs/1706.03762>); DCP, Wang &
//! Solomon, ICCV 2019 (<https://arxiv.org/abs/1905.03304>, Sec. 4.2: fx = θx + φ(θx, θy),
//! fy = θy + φ(θy, θx)); the paper (Dang et al., CVPR 2021) uses one block, 4 heads, ff 1024.
//! Point-major layout `[B, P, d]`; LayerNorm is written from tensor ops, the attention itself
//! is the fused kernel of [`ic_nn::ops::attention`].
//!
//! With [`KeyRows`] (the `pooled_keys` setting) every point still queries, but the keys and
//! values of the decoder's self-attention and the whole encoder (the other direction's
//! memory) use only the chosen rows of each cloud: the same weights, attention cost
//! O(P·T) instead of O(P²).

use candle_core::{Device, Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::config::NetConfig;
use crate::layers::{Dense, LayerNorm};
use ic_nn::ops::attention::multi_head_attention;

/// The rows of each cloud's features `[B, P, d]` that serve as attention keys: `T` per cloud,
/// the same count in every cloud of a batch.
#[derive(Clone, Debug)]
pub struct KeyRows {
    /// `[B·T]` u32: row `b·P + i` of the flattened `[B·P, d]` features.
    flat: Tensor,
    per_cloud: usize,
}

impl KeyRows {
    /// `indices[b]`: the key rows of cloud `b` (each `< points`, all of one length).
    pub fn new(indices: &[Vec<u32>], points: usize, device: &Device) -> Result<Self> {
        let per_cloud = indices.first().map_or(0, Vec::len);
        let mut flat = Vec::with_capacity(indices.len() * per_cloud);
        for (b, rows) in indices.iter().enumerate() {
            if rows.len() != per_cloud || rows.iter().any(|&i| i as usize >= points) {
                candle_core::bail!(
                    "key rows of cloud {b}: {} rows, want {per_cloud} below {points}",
                    rows.len()
                );
            }
            flat.extend(rows.iter().map(|&i| (b * points) as u32 + i));
        }
        let len = flat.len();
        Ok(KeyRows {
            flat: Tensor::from_vec(flat, len, device)?,
            per_cloud,
        })
    }

    /// The key rows of `t` `[B, P, d]`: `[B, T, d]`.
    pub fn gather(&self, t: &Tensor) -> Result<Tensor> {
        let (b, p, d) = t.dims3()?;
        t.reshape((b * p, d))?
            .index_select(&self.flat, 0)?
            .reshape((b, self.per_cloud, d))
    }
}

/// `t`'s key rows, or `t` itself when every row is a key.
fn keys_of(t: &Tensor, keys: Option<&KeyRows>) -> Result<Tensor> {
    match keys {
        Some(k) => k.gather(t),
        None => Ok(t.clone()),
    }
}

/// Multi-head scaled dot-product attention.
#[derive(Clone, Debug)]
pub struct MultiHeadAttention {
    q: Dense,
    k: Dense,
    v: Dense,
    o: Dense,
    heads: usize,
}

impl MultiHeadAttention {
    pub fn new(vb: VarBuilder, dims: usize, heads: usize) -> Result<Self> {
        Ok(MultiHeadAttention {
            q: Dense::new(vb.pp("q"), dims, dims, true)?,
            k: Dense::new(vb.pp("k"), dims, dims, true)?,
            v: Dense::new(vb.pp("v"), dims, dims, true)?,
            o: Dense::new(vb.pp("o"), dims, dims, true)?,
            heads,
        })
    }

    /// `query`: `[B, Pq, d]`, `context`: `[B, Pk, d]` → `[B, Pq, d]`.
    pub fn forward(&self, query: &Tensor, context: &Tensor) -> Result<Tensor> {
        let (k, v) = self.keys_values(context)?;
        self.attend(&self.queries(query)?, &k, &v)
    }

    /// The scaled queries `Q·(1/√(d/heads))` of `query` `[B, Pq, d]`.
    pub fn queries(&self, query: &Tensor) -> Result<Tensor> {
        let d = query.dim(2)?;
        let scale = 1.0 / ((d / self.heads) as f64).sqrt();
        // Scaling Q (P·d values) instead of the scores (P·P' values).
        self.q.forward(query)? * scale
    }

    /// The keys and values of `context` `[B, Pk, d]`.
    pub fn keys_values(&self, context: &Tensor) -> Result<(Tensor, Tensor)> {
        Ok((self.k.forward(context)?, self.v.forward(context)?))
    }

    /// The attention of [`MultiHeadAttention::queries`] over
    /// [`MultiHeadAttention::keys_values`] (same batch size), through the output projection.
    pub fn attend(&self, q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
        self.o.forward(&multi_head_attention(q, k, v, self.heads)?)
    }
}

/// Position-wise feed-forward: Dense → ReLU → Dense.
#[derive(Clone, Debug)]
pub struct FeedForward {
    up: Dense,
    down: Dense,
}

impl FeedForward {
    pub fn new(vb: VarBuilder, dims: usize, hidden: usize) -> Result<Self> {
        Ok(FeedForward {
            up: Dense::new(vb.pp("up"), dims, hidden, true)?,
            down: Dense::new(vb.pp("down"), hidden, dims, true)?,
        })
    }
}

impl Module for FeedForward {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.down.forward(&self.up.forward_relu(x)?)
    }
}

/// Encoder layer: `x + SelfAttn(LN(x))`, then `x + FF(LN(x))`, then a final LayerNorm.
#[derive(Clone, Debug)]
pub struct EncoderLayer {
    ln1: LayerNorm,
    attn: MultiHeadAttention,
    ln2: LayerNorm,
    ff: FeedForward,
    norm: LayerNorm,
}

impl EncoderLayer {
    pub fn new(vb: VarBuilder, cfg: &NetConfig) -> Result<Self> {
        let d = cfg.emb_dims;
        Ok(EncoderLayer {
            ln1: LayerNorm::new(vb.pp("ln1"), d)?,
            attn: MultiHeadAttention::new(vb.pp("attn"), d, cfg.heads)?,
            ln2: LayerNorm::new(vb.pp("ln2"), d)?,
            ff: FeedForward::new(vb.pp("ff"), d, cfg.ff_dims)?,
            norm: LayerNorm::new(vb.pp("norm"), d)?,
        })
    }
}

impl Module for EncoderLayer {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.ln1.forward(x)?;
        let x = (x + self.attn.forward(&h, &h)?)?;
        let x = (&x + self.ff.forward(&self.ln2.forward(&x)?)?)?;
        self.norm.forward(&x)
    }
}

/// Decoder layer: self-attention, cross-attention to the encoder's memory, feed-forward
/// (each pre-norm with a residual), then a final LayerNorm.
#[derive(Clone, Debug)]
pub struct DecoderLayer {
    ln1: LayerNorm,
    self_attn: MultiHeadAttention,
    ln2: LayerNorm,
    cross_attn: MultiHeadAttention,
    ln3: LayerNorm,
    ff: FeedForward,
    norm: LayerNorm,
}

impl DecoderLayer {
    pub fn new(vb: VarBuilder, cfg: &NetConfig) -> Result<Self> {
        let d = cfg.emb_dims;
        Ok(DecoderLayer {
            ln1: LayerNorm::new(vb.pp("ln1"), d)?,
            self_attn: MultiHeadAttention::new(vb.pp("self_attn"), d, cfg.heads)?,
            ln2: LayerNorm::new(vb.pp("ln2"), d)?,
            cross_attn: MultiHeadAttention::new(vb.pp("cross_attn"), d, cfg.heads)?,
            ln3: LayerNorm::new(vb.pp("ln3"), d)?,
            ff: FeedForward::new(vb.pp("ff"), d, cfg.ff_dims)?,
            norm: LayerNorm::new(vb.pp("norm"), d)?,
        })
    }

    /// `keys`: the rows of `x` its self-attention attends to (`None`: all).
    pub fn forward(&self, x: &Tensor, keys: Option<&KeyRows>, memory: &Tensor) -> Result<Tensor> {
        self.after_self_attention(&self.self_attention(x, keys)?, memory)
    }

    /// The first sub-layer, `x + SelfAttn(LN(x))` over the key rows `keys` of `LN(x)` (all
    /// when `None`): it does not see the memory.
    pub fn self_attention(&self, x: &Tensor, keys: Option<&KeyRows>) -> Result<Tensor> {
        let h = self.ln1.forward(x)?;
        x + self.self_attn.forward(&h, &keys_of(&h, keys)?)?
    }

    /// The rest of the layer (cross-attention, feed-forward, final LayerNorm) on the output of
    /// [`DecoderLayer::self_attention`].
    pub fn after_self_attention(&self, x: &Tensor, memory: &Tensor) -> Result<Tensor> {
        let (k, v) = self.cross_attn.keys_values(memory)?;
        self.after_cross_queries(x, &self.cross_queries(x)?, &k, &v)
    }

    /// The cross-attention's scaled queries of `x`, the output of
    /// [`DecoderLayer::self_attention`].
    pub fn cross_queries(&self, x: &Tensor) -> Result<Tensor> {
        self.cross_attn.queries(&self.ln2.forward(x)?)
    }

    /// The cross-attention's keys and values of the encoder memory.
    pub fn cross_keys_values(&self, memory: &Tensor) -> Result<(Tensor, Tensor)> {
        self.cross_attn.keys_values(memory)
    }

    /// [`DecoderLayer::after_self_attention`] from the parts computed apart: `x` (the output of
    /// the self-attention), its cross queries `q` and the memory's keys and values `k`, `v`.
    pub fn after_cross_queries(
        &self,
        x: &Tensor,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
    ) -> Result<Tensor> {
        let x = (x + self.cross_attn.attend(q, k, v)?)?;
        let x = (&x + self.ff.forward(&self.ln3.forward(&x)?)?)?;
        self.norm.forward(&x)
    }
}

/// What φ needs from `B` model clouds alone in a sweep against one observed cloud
/// ([`Transformer::model_side`]): computed once per set of rotated copies and reusable
/// against any observed cloud. All `[B, M, d]`, point-major.
#[derive(Clone, Debug)]
pub struct ModelSide {
    /// θx, the DGCNN features of the copies.
    pub features: Tensor,
    /// The decoder's self-attention sub-layer on θx.
    self_attended: Tensor,
    /// Its cross-attention queries (scaled).
    cross_queries: Tensor,
    /// The keys and values of the model's encoder memory, for the observed side's
    /// cross-attention.
    memory_keys: Tensor,
    memory_values: Tensor,
}

impl ModelSide {
    /// Copies in the side.
    pub fn copies(&self) -> Result<usize> {
        self.features.dim(0)
    }

    /// The memory the side's tensors take, in bytes.
    pub fn bytes(&self) -> Result<usize> {
        let all = [
            &self.features,
            &self.self_attended,
            &self.cross_queries,
            &self.memory_keys,
            &self.memory_values,
        ];
        Ok(all
            .iter()
            .map(|t| t.elem_count() * t.dtype().size_in_bytes())
            .sum())
    }

    /// The copies `indices` (u32 `[K]`) of the side, in that order.
    pub fn select(&self, indices: &Tensor) -> Result<ModelSide> {
        let pick = |t: &Tensor| t.index_select(indices, 0)?.contiguous();
        Ok(ModelSide {
            features: pick(&self.features)?,
            self_attended: pick(&self.self_attended)?,
            cross_queries: pick(&self.cross_queries)?,
            memory_keys: pick(&self.memory_keys)?,
            memory_values: pick(&self.memory_values)?,
        })
    }
}

/// φ: one encoder layer and one decoder layer shared by both directions.
#[derive(Clone, Debug)]
pub struct Transformer {
    encoder: EncoderLayer,
    decoder: DecoderLayer,
}

impl Transformer {
    pub fn new(vb: VarBuilder, cfg: &NetConfig) -> Result<Self> {
        Ok(Transformer {
            encoder: EncoderLayer::new(vb.pp("encoder"), cfg)?,
            decoder: DecoderLayer::new(vb.pp("decoder"), cfg)?,
        })
    }

    /// `φ(a, b)`: `a` attends to the encoded `b`. Both `[B, P, d]`; `ka`, `kb` their key rows
    /// (`None`: every point).
    pub fn phi(
        &self,
        a: &Tensor,
        b: &Tensor,
        ka: Option<&KeyRows>,
        kb: Option<&KeyRows>,
    ) -> Result<Tensor> {
        self.decoder.forward(a, ka, &self.memory(b, kb)?)
    }

    /// The encoder's output on the key rows of `b`: the memory the other cloud attends to.
    fn memory(&self, b: &Tensor, kb: Option<&KeyRows>) -> Result<Tensor> {
        self.encoder.forward(&keys_of(b, kb)?)
    }

    /// `(θx + φ(θx, θy), θy + φ(θy, θx))`, with the key rows `kx`, `ky` of each cloud.
    pub fn forward(
        &self,
        tx: &Tensor,
        ty: &Tensor,
        kx: Option<&KeyRows>,
        ky: Option<&KeyRows>,
    ) -> Result<(Tensor, Tensor)> {
        let fx = (tx + self.phi(tx, ty, kx, ky)?)?;
        let fy = (ty + self.phi(ty, tx, ky, kx)?)?;
        Ok((fx, fy))
    }

    /// The part of [`Transformer::forward`] that depends on the model clouds `tx`
    /// (`[B, M, d]`, key rows `kx`) alone, for [`Transformer::forward_model_side`].
    pub fn model_side(&self, tx: &Tensor, kx: Option<&KeyRows>) -> Result<ModelSide> {
        let self_attended = self.decoder.self_attention(tx, kx)?;
        let cross_queries = self.decoder.cross_queries(&self_attended)?;
        let (memory_keys, memory_values) = self.decoder.cross_keys_values(&self.memory(tx, kx)?)?;
        Ok(ModelSide {
            features: tx.clone(),
            self_attended,
            cross_queries,
            memory_keys,
            memory_values,
        })
    }

    /// [`Transformer::forward`] for `B` model clouds, given as their
    /// [`Transformer::model_side`], against one observed cloud `ty` (`[1, N, d]`), as if `ty`
    /// were repeated `B` times: everything that depends on `ty` alone — its encoder memory
    /// with that memory's keys and values, its decoder self-attention and cross queries — is
    /// computed once and shared by the copies. Returns `(fx [B, M, d], fy [B, N, d])`, the
    /// same values as `forward` on the repeated batch (tested through
    /// [`crate::PoseNet::forward_sweep`]).
    /// `ky`: the observed cloud's key rows.
    pub fn forward_model_side(
        &self,
        side: &ModelSide,
        ty: &Tensor,
        ky: Option<&KeyRows>,
    ) -> Result<(Tensor, Tensor)> {
        let b = side.copies()?;
        if ty.dim(0)? != 1 {
            candle_core::bail!(
                "forward_model_side: the observed batch has {} clouds, not 1",
                ty.dim(0)?
            );
        }
        let repeat = |t: &Tensor| -> Result<Tensor> {
            let (_, p, d) = t.dims3()?;
            t.broadcast_as((b, p, d))?.contiguous()
        };
        let (mk, mv) = self.decoder.cross_keys_values(&self.memory(ty, ky)?)?;
        let fx = (&side.features
            + self.decoder.after_cross_queries(
                &side.self_attended,
                &side.cross_queries,
                &repeat(&mk)?,
                &repeat(&mv)?,
            )?)?;
        let self_y = self.decoder.self_attention(ty, ky)?;
        let qy = self.decoder.cross_queries(&self_y)?;
        let fy = (repeat(ty)?
            + self.decoder.after_cross_queries(
                &repeat(&self_y)?,
                &repeat(&qy)?,
                &side.memory_keys,
                &side.memory_values,
            )?)?;
        Ok((fx, fy))
    }
}
