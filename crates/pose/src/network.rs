//! The whole network: shared DGCNN → transformer → score map → head, plus batching of point
//! pairs, the negative log-likelihood loss and arg-max correspondences.
//!
//! Paper: Dang, Wang, Salzmann, "3D Registration for Self-Occluded Objects in Context",
//! CVPR 2021 (<https://arxiv.org/abs/2011.11260>), Sec. 3 "Pose Estimation".

use candle_core::{DType, Device, Result as CResult, Tensor};
use candle_nn::VarBuilder;
use glam::Vec3;
use ic_geometry::Assignment;

use crate::config::{Head, NetConfig, OtLoss};
use crate::dgcnn::Dgcnn;
use crate::layers::log_softmax_last;
use crate::transformer::{KeyRows, ModelSide, Transformer};
use crate::{PoseError, Result, knn, sinkhorn};

/// A batch of (model, observed) point-set pairs ready for the network: centred,
/// channel-first coordinates and the k-NN graphs. All pairs share M and N.
#[derive(Clone, Debug)]
pub struct PairBatch {
    /// `[B, 3, M]`, each cloud centred on its centroid.
    pub model: Tensor,
    /// `[B, 3, N]`, each cloud centred on its centroid.
    pub observed: Tensor,
    /// `[B, M·k]` u32.
    pub model_graph: Tensor,
    /// `[B, N·k]` u32.
    pub observed_graph: Tensor,
}

/// Checks that `points` are finite and at least `needed`.
pub fn check_points(what: &'static str, points: &[Vec3], needed: usize) -> Result<()> {
    if points.len() < needed {
        return Err(PoseError::TooFewPoints {
            what,
            got: points.len(),
            needed,
        });
    }
    if let Some(index) = points.iter().position(|p| !p.is_finite()) {
        return Err(PoseError::NonFinite { what, index });
    }
    Ok(())
}

fn channel_first(clouds: &[&[Vec3]], k: usize, device: &Device) -> Result<(Tensor, Tensor)> {
    let b = clouds.len();
    let p = clouds[0].len();
    let mut coords = Vec::with_capacity(b * 3 * p);
    let mut graph = Vec::with_capacity(b * p * k);
    for cloud in clouds {
        let c = cloud.iter().copied().sum::<Vec3>() / p as f32;
        let centred: Vec<Vec3> = cloud.iter().map(|q| *q - c).collect();
        for axis in 0..3 {
            coords.extend(centred.iter().map(|q| q[axis]));
        }
        graph.extend(knn::knn_indices(&centred, k));
    }
    Ok((
        Tensor::from_vec(coords, (b, 3, p), device)?,
        Tensor::from_vec(graph, (b, p * k), device)?,
    ))
}

/// One model cloud in `B` rotated copies against one observed cloud, ready for
/// [`PoseNet::forward_sweep`]: the rotation sweep of hypothesise-and-verify.
///
/// Copy `b` is `rotations[b]` applied to the model points about the model frame's origin
/// (normalised units), then centred like [`PairBatch`]. The k-NN graph of a cloud does not
/// change under rotation, so the model's graph is computed once and shared by the copies.
#[derive(Clone, Debug)]
pub struct SweepBatch {
    /// The rotated copies, model frame rotated (not centred): what each copy's pose maps.
    pub copies: Vec<Vec<Vec3>>,
    /// `[B, 3, M]`, each copy centred on its centroid.
    pub model: Tensor,
    /// `[B, M·k]` u32, the same graph for every copy.
    pub model_graph: Tensor,
    /// `[1, 3, N]`, centred.
    pub observed: Tensor,
    /// `[1, N·k]` u32.
    pub observed_graph: Tensor,
}

impl SweepBatch {
    /// Builds the sweep; errors on no rotation, fewer than `k` (or 3) points or non-finite
    /// coordinates.
    pub fn new(
        model: &[Vec3],
        rotations: &[ic_geometry::Pose],
        observed: &[Vec3],
        k: usize,
        device: &Device,
    ) -> Result<Self> {
        if rotations.is_empty() {
            return Err(PoseError::Batch(
                "a sweep needs at least one rotation".into(),
            ));
        }
        check_points("model points", model, k.max(3))?;
        check_points("observed points", observed, k.max(3))?;
        let copies: Vec<Vec<Vec3>> = rotations
            .iter()
            .map(|r| model.iter().map(|&p| r.rotate_f32(p)).collect())
            .collect();
        let m = model.len();
        let mut coords = Vec::with_capacity(copies.len() * 3 * m);
        for copy in &copies {
            let c = copy.iter().copied().sum::<Vec3>() / m as f32;
            for axis in 0..3 {
                coords.extend(copy.iter().map(|q| q[axis] - c[axis]));
            }
        }
        let centre = model.iter().copied().sum::<Vec3>() / m as f32;
        let centred: Vec<Vec3> = model.iter().map(|q| *q - centre).collect();
        let graph = knn::knn_indices(&centred, k);
        let b = copies.len();
        let model_graph = Tensor::from_vec(graph, (1, m * k), device)?
            .broadcast_as((b, m * k))?
            .contiguous()?;
        let (observed, observed_graph) = channel_first(&[observed], k, device)?;
        Ok(SweepBatch {
            model: Tensor::from_vec(coords, (b, 3, m), device)?,
            copies,
            model_graph,
            observed,
            observed_graph,
        })
    }

    pub fn len(&self) -> usize {
        self.copies.len()
    }

    pub fn is_empty(&self) -> bool {
        self.copies.is_empty()
    }
}

impl PairBatch {
    /// Builds the batch; errors on an empty batch, differing sizes, fewer than `k` points or
    /// non-finite coordinates.
    pub fn new(pairs: &[(&[Vec3], &[Vec3])], k: usize, device: &Device) -> Result<Self> {
        let Some(first) = pairs.first() else {
            return Err(PoseError::Batch("empty batch".into()));
        };
        let (m, n) = (first.0.len(), first.1.len());
        for (i, (x, y)) in pairs.iter().enumerate() {
            if x.len() != m || y.len() != n {
                return Err(PoseError::Batch(format!(
                    "pair {i} has {}×{} points, pair 0 has {m}×{n}",
                    x.len(),
                    y.len()
                )));
            }
            check_points("model points", x, k.max(3))?;
            check_points("observed points", y, k.max(3))?;
        }
        let xs: Vec<&[Vec3]> = pairs.iter().map(|p| p.0).collect();
        let ys: Vec<&[Vec3]> = pairs.iter().map(|p| p.1).collect();
        let (model, model_graph) = channel_first(&xs, k, device)?;
        let (observed, observed_graph) = channel_first(&ys, k, device)?;
        Ok(PairBatch {
            model,
            observed,
            model_graph,
            observed_graph,
        })
    }

    pub fn len(&self) -> usize {
        self.model.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Log-probabilities of a head.
#[derive(Clone, Debug)]
pub struct HeadOutput {
    pub head: Head,
    /// Softmax: `[B, N, M]` (for each observed point, log P over the model points).
    /// OT: `[B, M+1, N+1]` (log P̄ with the outlier bins in row M and column N).
    pub log_p: Tensor,
    pub model_points: usize,
    pub observed_points: usize,
    /// Weighting of the OT loss (ignored by the softmax head).
    pub loss: OtLoss,
}

/// For one observed point: its most probable model point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    pub observed: u32,
    /// Most probable real model point.
    pub model: u32,
    /// Its probability.
    pub probability: f32,
    /// Whether the outlier bin is more probable than every model point (OT head only).
    pub outlier: bool,
}

impl HeadOutput {
    /// Per pair, one [`Match`] per observed point.
    pub fn matches(&self) -> Result<Vec<Vec<Match>>> {
        let (m, n) = (self.model_points, self.observed_points);
        let b = self.log_p.dims()[0];
        let lp = self.log_p.flatten_all()?.to_vec1::<f32>()?;
        let mut out = Vec::with_capacity(b);
        for bi in 0..b {
            let mut row = Vec::with_capacity(n);
            match self.head {
                Head::Softmax => {
                    let base = bi * n * m;
                    for j in 0..n {
                        let r = &lp[base + j * m..base + (j + 1) * m];
                        let (i, v) = argmax(r.iter().copied());
                        row.push(Match {
                            observed: j as u32,
                            model: i as u32,
                            probability: v.exp(),
                            outlier: false,
                        });
                    }
                }
                Head::Ot => {
                    let base = bi * (m + 1) * (n + 1);
                    for j in 0..n {
                        let col = (0..m).map(|i| lp[base + i * (n + 1) + j]);
                        let (i, v) = argmax(col);
                        let bin = lp[base + m * (n + 1) + j];
                        row.push(Match {
                            observed: j as u32,
                            model: i as u32,
                            probability: v.exp(),
                            outlier: bin > v,
                        });
                    }
                }
            }
            out.push(row);
        }
        Ok(out)
    }
}

/// The first index of the largest value and that value (`(0, -inf)` when empty or all NaN).
pub(crate) fn argmax(it: impl Iterator<Item = f32>) -> (usize, f32) {
    let mut best = (0, f32::NEG_INFINITY);
    for (i, v) in it.enumerate() {
        if v > best.1 {
            best = (i, v);
        }
    }
    best
}

/// DGCNN (shared by both clouds) + transformer + score map + head.
#[derive(Clone, Debug)]
pub struct PoseNet {
    encoder: Dgcnn,
    transformer: Transformer,
    cfg: NetConfig,
}

impl PoseNet {
    pub fn new(vb: VarBuilder, cfg: &NetConfig) -> CResult<Self> {
        Ok(PoseNet {
            encoder: Dgcnn::new(vb.pp("dgcnn"), cfg)?,
            transformer: Transformer::new(vb.pp("transformer"), cfg)?,
            cfg: cfg.clone(),
        })
    }

    /// Uses `k` neighbours in the DGCNN's k-NN graph instead of the configured k (no weight
    /// depends on it; batches must then be built with this k).
    pub fn set_neighbours(&mut self, k: usize) {
        self.encoder.set_neighbours(k);
        self.cfg.k = k;
    }

    /// Attends over `keys` farthest-point samples of each cloud instead of every point
    /// (`None`: every point; see [`NetConfig::pooled_keys`]). No weight depends on it.
    pub fn set_pooled_keys(&mut self, keys: Option<usize>) {
        self.cfg.pooled_keys = keys;
    }

    pub fn config(&self) -> &NetConfig {
        &self.cfg
    }

    /// The attention key rows of channel-first clouds `coords` `[B, 3, P]`: the
    /// [`NetConfig::pooled_keys`] farthest-point samples of each, or `None` (every point) when
    /// unset or not fewer than P.
    fn key_rows(&self, coords: &Tensor) -> CResult<Option<KeyRows>> {
        let (_, _, p) = coords.dims3()?;
        let Some(t) = self.cfg.pooled_keys.filter(|&t| t < p) else {
            return Ok(None);
        };
        let clouds = coords.to_vec3::<f32>()?;
        let rows: Vec<Vec<u32>> = clouds
            .iter()
            .map(|c| {
                let points: Vec<Vec3> = (0..p)
                    .map(|i| Vec3::new(c[0][i], c[1][i], c[2][i]))
                    .collect();
                knn::farthest_point_indices(&points, t)
            })
            .collect();
        KeyRows::new(&rows, p, coords.device()).map(Some)
    }

    /// The DGCNN features `(θx [B, M, d], θy [B, N, d])`.
    pub fn encode(&self, batch: &PairBatch, train: bool) -> CResult<(Tensor, Tensor)> {
        Ok((
            self.encode_cloud(&batch.model, &batch.model_graph, train)?,
            self.encode_cloud(&batch.observed, &batch.observed_graph, train)?,
        ))
    }

    /// The DGCNN features `[B, P, d]` of channel-first clouds `[B, 3, P]` with their k-NN
    /// graphs `[B, P·k]`.
    fn encode_cloud(&self, coords: &Tensor, graph: &Tensor, train: bool) -> CResult<Tensor> {
        self.encoder
            .forward_t(coords, graph, train)?
            .transpose(1, 2)?
            .contiguous()
    }

    /// `(fx [B, M, d], fy [B, N, d])`.
    pub fn embed(&self, batch: &PairBatch, train: bool) -> CResult<(Tensor, Tensor)> {
        let (tx, ty) = self.encode(batch, train)?;
        let (kx, ky) = (
            self.key_rows(&batch.model)?,
            self.key_rows(&batch.observed)?,
        );
        self.transformer.forward(&tx, &ty, kx.as_ref(), ky.as_ref())
    }

    fn score_scale(&self) -> f64 {
        if self.cfg.scale_scores {
            1.0 / (self.cfg.emb_dims as f64).sqrt()
        } else {
            1.0
        }
    }

    /// The score map `S = fx·fyᵀ` (divided by √d when `scale_scores`), `[B, M, N]`.
    pub fn scores(&self, batch: &PairBatch, train: bool) -> CResult<Tensor> {
        let (fx, fy) = self.embed(batch, train)?;
        fx.matmul(&fy.t()?)? * self.score_scale()
    }

    /// Runs the network and its head. `train` selects batch statistics (and updates the
    /// running ones) in the batch-norm layers.
    pub fn forward_t(&self, batch: &PairBatch, train: bool) -> CResult<HeadOutput> {
        let (fx, fy) = self.embed(batch, train)?;
        self.head(&fx, &fy)
    }

    /// Inference on a [`SweepBatch`]: the same log-probabilities as [`PoseNet::forward_t`] on
    /// the pairs (copy b, observed) for every b, with the observed cloud's DGCNN features, its
    /// transformer memory and its decoder self-attention computed once instead of `B` times.
    pub fn forward_sweep(&self, batch: &SweepBatch) -> CResult<HeadOutput> {
        Ok(self.forward_sweep_pruned(batch, batch.len())?.0)
    }

    /// [`PoseNet::forward_sweep`] for the `keep` most promising copies only: after the DGCNN,
    /// each copy is ranked by how well its features match the observed cloud's (for each
    /// observed point the best cosine similarity over the copy's points, averaged), and only
    /// copy 0 and the best `keep − 1` others meet the observed cloud in the transformer and
    /// go through the head. Returns the head output of the kept copies and their indices in
    /// the batch, in batch order. The copies' own side is computed for all of them
    /// ([`PoseNet::sweep_model_side`], then [`PoseNet::forward_sweep_side`]).
    pub fn forward_sweep_pruned(
        &self,
        batch: &SweepBatch,
        keep: usize,
    ) -> CResult<(HeadOutput, Vec<usize>)> {
        self.forward_sweep_side(&self.sweep_model_side(batch)?, batch, keep)
    }

    /// Everything a sweep computes from the model's rotated copies alone (their DGCNN
    /// features and the transformer's model side): independent of the observed cloud, so it
    /// can be kept and reused against any observed cloud ([`PoseNet::forward_sweep_side`]).
    pub fn sweep_model_side(&self, batch: &SweepBatch) -> CResult<ModelSide> {
        let tx = self.encode_cloud(&batch.model, &batch.model_graph, false)?;
        self.transformer
            .model_side(&tx, self.key_rows(&batch.model)?.as_ref())
    }

    /// [`PoseNet::forward_sweep_pruned`] with the model side computed beforehand by
    /// [`PoseNet::sweep_model_side`] on the same copies (kept, or computed for another
    /// observed cloud); only `batch`'s observed cloud is encoded.
    pub fn forward_sweep_side(
        &self,
        side: &ModelSide,
        batch: &SweepBatch,
        keep: usize,
    ) -> CResult<(HeadOutput, Vec<usize>)> {
        let b = side.copies()?;
        if b != batch.len() {
            candle_core::bail!(
                "forward_sweep_side: the model side has {b} copies, the sweep {}",
                batch.len()
            );
        }
        let ty = self.encode_cloud(&batch.observed, &batch.observed_graph, false)?;
        // Tensors share their storage: cloning the side copies no values.
        let (side, kept) = match prune_copies(&side.features, &ty, keep)? {
            Some((idx, kept)) => (side.select(&idx)?, kept),
            None => (side.clone(), (0..b).collect()),
        };
        let ky = self.key_rows(&batch.observed)?;
        let (fx, fy) = self
            .transformer
            .forward_model_side(&side, &ty, ky.as_ref())?;
        Ok((self.head(&fx, &fy)?, kept))
    }

    /// The score map and the head on the embeddings `fx [B, M, d]`, `fy [B, N, d]`.
    fn head(&self, fx: &Tensor, fy: &Tensor) -> CResult<HeadOutput> {
        let (m, n) = (fx.dim(1)?, fy.dim(1)?);
        let log_p = match self.cfg.head {
            Head::Softmax => log_softmax_last(&(fy.matmul(&fx.t()?)? * self.score_scale())?)?,
            Head::Ot => {
                let s = (fx.matmul(&fy.t()?)? * self.score_scale())?;
                let ot = self.cfg.ot;
                sinkhorn::log_optimal_transport(&s, ot.alpha, ot.lambda, ot.iterations)?
            }
        };
        Ok(HeadOutput {
            head: self.cfg.head,
            log_p,
            model_points: m,
            observed_points: n,
            loss: self.cfg.ot.loss,
        })
    }
}

/// The copies a pruned sweep keeps (see [`PoseNet::forward_sweep_pruned`]): `None` when
/// `keep` covers every copy of `tx` (`[B, M, d]`), else their indices as a u32 tensor and as a
/// list, in batch order, copy 0 first. `ty`: `[1, N, d]`.
fn prune_copies(tx: &Tensor, ty: &Tensor, keep: usize) -> CResult<Option<(Tensor, Vec<usize>)>> {
    let b = tx.dim(0)?;
    let keep = keep.clamp(1, b);
    if keep >= b {
        return Ok(None);
    }
    let unit = |t: &Tensor| -> CResult<Tensor> {
        t.broadcast_div(&(t.sqr()?.sum_keepdim(2)?.sqrt()? + 1e-6)?)
    };
    let (nx, ny) = (unit(tx)?, unit(ty)?);
    let (_, n, d) = ny.dims3()?;
    let sim = ny.broadcast_as((b, n, d))?.contiguous()?.matmul(&nx.t()?)?;
    let score: Vec<f32> = sim.max(2)?.mean(1)?.to_vec1()?;
    let mut order: Vec<usize> = (1..b).collect();
    order.sort_by(|&i, &j| score[j].total_cmp(&score[i]).then(i.cmp(&j)));
    let mut kept: Vec<usize> = std::iter::once(0)
        .chain(order.into_iter().take(keep - 1))
        .collect();
    kept.sort_unstable();
    let idx = Tensor::from_vec(
        kept.iter().map(|&i| i as u32).collect::<Vec<_>>(),
        kept.len(),
        tx.device(),
    )?;
    Ok(Some((idx, kept)))
}

/// The paper's normalised negative log-likelihood, averaged over the pairs of the batch.
///
/// Softmax head: over the matched pairs only, `−Σ log P_ji M_ij / Σ M_ij` (a pair without a
/// match contributes nothing). OT head: over M̄ including the bins — an unmatched observed
/// point j counts `log P̄[M, j]`, an unmatched model point i counts `log P̄[i, N]`; with
/// [`OtLoss::Balanced`] (the default) the matched entries and the bin entries are averaged
/// separately and the loss is the mean of the two means. A batch with nothing to count gives a zero loss (with
/// zero, finite gradients).
pub fn nll_loss(out: &HeadOutput, assignments: &[&Assignment]) -> Result<Tensor> {
    let b = out.log_p.dims()[0];
    if assignments.len() != b {
        return Err(PoseError::Batch(format!(
            "{} assignments for {b} pairs",
            assignments.len()
        )));
    }
    let per_pair: Vec<(Vec<u32>, Vec<f32>)> = assignments
        .iter()
        .enumerate()
        .map(|(bi, a)| pair_entries(out, bi, a))
        .collect::<Result<_>>()?;
    let counted = per_pair.iter().filter(|p| !p.0.is_empty()).count();
    let device = out.log_p.device();
    if counted == 0 {
        return Ok((out.log_p.sum_all()? * 0.0)?);
    }
    let (mut idx, mut w) = (Vec::new(), Vec::new());
    for (i, weights) in per_pair {
        idx.extend(i);
        w.extend(weights.into_iter().map(|x| x / counted as f32));
    }
    let k = idx.len();
    let idx = Tensor::from_vec(idx, k, device)?;
    let w = Tensor::from_vec(w, k, device)?.to_dtype(DType::F32)?;
    let picked = out.log_p.flatten_all()?.index_select(&idx, 0)?;
    Ok((picked.mul(&w)?.sum_all()? * -1.0)?)
}

/// The entries of `out.log_p` (flat indices) that pair `bi`'s loss counts under `a`, and
/// their weights: the pair's share of [`nll_loss`] before the average over pairs (the weights
/// sum to 1 when there is any entry).
fn pair_entries(out: &HeadOutput, bi: usize, a: &Assignment) -> Result<(Vec<u32>, Vec<f32>)> {
    let (m, n) = (out.model_points, out.observed_points);
    if a.model_count != m || a.observed_count != n || a.observed_to_model.len() != n {
        return Err(PoseError::Batch(format!(
            "assignment {bi} is {}×{}, the network output {m}×{n}",
            a.model_count, a.observed_count
        )));
    }
    // Each counted entry and its group: 0 = matched pair, 1 = outlier bin.
    let mut idx: Vec<u32> = Vec::new();
    let mut group: Vec<u8> = Vec::new();
    match out.head {
        Head::Softmax => {
            let base = bi * n * m;
            for (j, i) in a.observed_to_model.iter().enumerate() {
                if let Some(i) = i {
                    idx.push((base + j * m + *i as usize) as u32);
                    group.push(0);
                }
            }
        }
        Head::Ot => {
            let base = bi * (m + 1) * (n + 1);
            let mut model_matched = vec![false; m];
            for (j, i) in a.observed_to_model.iter().enumerate() {
                let row = match i {
                    Some(i) => {
                        model_matched[*i as usize] = true;
                        group.push(0);
                        *i as usize
                    }
                    None => {
                        group.push(1);
                        m
                    }
                };
                idx.push((base + row * (n + 1) + j) as u32);
            }
            for (i, matched) in model_matched.iter().enumerate() {
                if !matched {
                    idx.push((base + i * (n + 1) + n) as u32);
                    group.push(1);
                }
            }
        }
    }
    let count = idx.len();
    let balanced = out.head == Head::Ot && out.loss == OtLoss::Balanced;
    let w: Vec<f32> = if balanced {
        let matched = group.iter().filter(|g| **g == 0).count();
        let bins = count - matched;
        let present = (matched > 0) as usize + (bins > 0) as usize;
        group
            .iter()
            .map(|g| {
                let in_group = if *g == 0 { matched } else { bins };
                1.0 / (in_group as f32 * present as f32)
            })
            .collect()
    } else {
        vec![1.0 / count.max(1) as f32; count]
    };
    Ok((idx, w))
}

/// For each pair, which of its candidate ground truths (`candidates[b]`: the true pose's M̄
/// first, then M̄ under each pose equivalent to it by the object's symmetry) the current
/// output fits best, i.e. has the lowest [`nll_loss`] share: the symmetric-equivalent pose
/// nearest the prediction. A pair with one candidate gets 0 without reading the output.
pub fn nearest_assignments(
    out: &HeadOutput,
    candidates: &[Vec<&Assignment>],
) -> Result<Vec<usize>> {
    if candidates.iter().all(|c| c.len() <= 1) {
        return Ok(vec![0; candidates.len()]);
    }
    let log_p = out.log_p.flatten_all()?.to_vec1::<f32>()?;
    candidates
        .iter()
        .enumerate()
        .map(|(bi, cands)| {
            let mut best = (0, f32::INFINITY);
            for (k, a) in cands.iter().enumerate() {
                let (idx, w) = pair_entries(out, bi, a)?;
                if idx.is_empty() {
                    continue;
                }
                let loss: f32 = idx
                    .iter()
                    .zip(&w)
                    .map(|(i, w)| -log_p[*i as usize] * w)
                    .sum();
                if loss < best.1 {
                    best = (k, loss);
                }
            }
            Ok(best.0)
        })
        .collect()
}

/// Fraction of matched observed points whose arg-max model point is the true one (`None`
/// when the batch has no matched point).
pub fn correspondence_accuracy(matches: &[Vec<Match>], assignments: &[&Assignment]) -> Option<f64> {
    let mut total = 0usize;
    let mut right = 0usize;
    for (ms, a) in matches.iter().zip(assignments) {
        for (mt, truth) in ms.iter().zip(&a.observed_to_model) {
            if let Some(t) = truth {
                total += 1;
                if !mt.outlier && mt.model == *t {
                    right += 1;
                }
            }
        }
    }
    (total > 0).then(|| right as f64 / total as f64)
}
