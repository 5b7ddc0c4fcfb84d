//! The inference API: load a checkpoint, estimate poses.

use std::path::Path;
use std::sync::Mutex;

use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use glam::Vec3;
use ic_geometry::Pose;
use serde::{Deserialize, Serialize};

use crate::config::PoseConfig;
use crate::network::{HeadOutput, PairBatch, PoseNet, SweepBatch, check_points};
use crate::recover::{RecoveryOptions, SampledPose, SamplingOptions, recover_pose, sample_poses};
use crate::transformer::ModelSide;
use crate::{PoseError, Result, checkpoint};

/// The pose of the model in the camera frame and how well it is supported.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseEstimate {
    /// Maps model coordinates into camera coordinates.
    pub pose: Pose,
    /// Correspondences kept for Procrustes.
    pub inlier_count: usize,
    /// Mean probability of the kept correspondences, in [0, 1].
    pub assignment_confidence: f32,
}

/// One rotated copy's estimates of [`PoseEstimator::estimate_rotations`], mapped back to the
/// unrotated model.
#[derive(Clone, Debug, PartialEq)]
pub struct CopyEstimate {
    /// The copy's index in the rotations.
    pub rotation: usize,
    /// Weighted Procrustes of all the copy's correspondences.
    pub estimate: PoseEstimate,
    /// Poses of minimal sets drawn from them, most supported first (empty without sampling).
    pub sampled: Vec<SampledPose>,
}

/// Settings of [`PoseEstimator::estimate_rotations`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepOptions {
    /// Copies that go through the transformer (copy 0 and the best by DGCNN features); at
    /// least the number of rotations = all.
    pub keep: usize,
    /// Poses of minimal sets drawn from each kept copy's correspondences.
    pub sampling: Option<SamplingOptions>,
    /// Seed of the sampling (copy i uses `seed + i`).
    pub seed: u64,
}

impl Default for SweepOptions {
    fn default() -> Self {
        SweepOptions {
            keep: usize::MAX,
            sampling: None,
            seed: 0,
        }
    }
}

/// A trained network ready for inference (no autograd graph is recorded: the weights are
/// plain tensors memory-mapped from the checkpoint).
///
/// An estimator loaded from a checkpoint keeps the model side of its latest rotation sweeps
/// ([`PoseEstimator::estimate_rotations`]), up to [`MODEL_SIDE_BYTES`]: sweeping the same
/// model points with the same rotations again (the same object registered in another frame,
/// or another instance of it in the same frame) encodes only the observed cloud.
pub struct PoseEstimator {
    net: PoseNet,
    config: PoseConfig,
    device: Device,
    /// How correspondences become a pose (defaults: see [`RecoveryOptions`]).
    pub recovery: RecoveryOptions,
    /// `None` when the weights may change (an estimator wrapping a network being trained).
    model_sides: Option<Mutex<SideCache>>,
}

/// The memory a loaded [`PoseEstimator`] gives to kept model sides: 96 MiB, four sweeps of
/// the pipeline's default (24 copies of 320 points at d = 128 take 5·24·320·128 floats,
/// ≈ 19.7 MB).
pub const MODEL_SIDE_BYTES: usize = 96 << 20;

/// Kept model sides, most recently used last, with their memory budget in bytes.
struct SideCache {
    budget: usize,
    kept: Vec<CachedSide>,
}

/// One kept model side, with the exact inputs it was computed from.
struct CachedSide {
    model: Vec<Vec3>,
    rotations: Vec<[f64; 9]>,
    side: ModelSide,
    bytes: usize,
}

/// A rotation matrix as plain numbers (the cache compares them exactly).
fn rotation_key(p: &Pose) -> [f64; 9] {
    p.rotation.to_cols_array()
}

impl PoseEstimator {
    /// Loads a checkpoint written by training (weights-only or full) on the CPU.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        Self::load_on(path, &Device::Cpu)
    }

    /// Loads a checkpoint on `device`.
    pub fn load_on(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let path = path.as_ref();
        let config = checkpoint::read_config(path)?;
        // SAFETY: the file is memory-mapped read-only; it must not be truncated while in use
        // (checkpoints are replaced by rename, never rewritten in place).
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[path], DType::F32, device) }
            .map_err(|e| PoseError::Checkpoint {
                path: path.to_path_buf(),
                message: e.to_string(),
            })?;
        let net = PoseNet::new(vb, &config.net).map_err(|e| PoseError::Checkpoint {
            path: path.to_path_buf(),
            message: format!("does not match its configuration: {e}"),
        })?;
        Ok(PoseEstimator {
            net,
            config,
            device: device.clone(),
            recovery: RecoveryOptions::default(),
            model_sides: None,
        }
        .keeping_model_sides(MODEL_SIDE_BYTES))
    }

    /// Wraps an existing network (e.g. the one being trained, for validation). Its weights
    /// may change between calls, so no model side is kept (see
    /// [`PoseEstimator::keeping_model_sides`]).
    pub fn from_net(net: PoseNet, config: PoseConfig, device: Device) -> Self {
        PoseEstimator {
            net,
            config,
            device,
            recovery: RecoveryOptions::default(),
            model_sides: None,
        }
    }

    /// Keeps the model sides of the latest rotation sweeps, up to `budget` bytes (a loaded
    /// estimator keeps [`MODEL_SIDE_BYTES`]): only for weights that no longer change.
    pub fn keeping_model_sides(mut self, budget: usize) -> Self {
        self.model_sides = Some(Mutex::new(SideCache {
            budget,
            kept: Vec::new(),
        }));
        self
    }

    /// The rotation sweeps whose model side is kept now, and their bytes (0, 0 when none is
    /// kept).
    pub fn kept_model_sides(&self) -> (usize, usize) {
        self.model_sides.as_ref().map_or((0, 0), |m| {
            let cache = m.lock().unwrap_or_else(|e| e.into_inner());
            (cache.kept.len(), cache.kept.iter().map(|c| c.bytes).sum())
        })
    }

    /// The model side of `batch` (the copies of `model_points` by `rotations`): the kept one
    /// when these exact inputs were swept before, else computed (and kept when keeping).
    fn model_side(
        &self,
        batch: &SweepBatch,
        model_points: &[Vec3],
        rotations: &[Pose],
    ) -> Result<ModelSide> {
        let Some(cache) = &self.model_sides else {
            return Ok(self.net.sweep_model_side(batch)?);
        };
        let key: Vec<[f64; 9]> = rotations.iter().map(rotation_key).collect();
        let same = |c: &CachedSide| c.rotations == key && c.model == model_points;
        {
            let mut cache = cache.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(i) = cache.kept.iter().position(same) {
                let c = cache.kept.remove(i);
                let side = c.side.clone();
                cache.kept.push(c);
                return Ok(side);
            }
        }
        let side = self.net.sweep_model_side(batch)?;
        let bytes = side.bytes()?;
        let mut cache = cache.lock().unwrap_or_else(|e| e.into_inner());
        if bytes <= cache.budget && !cache.kept.iter().any(same) {
            // The least recently used go first.
            while cache.kept.iter().map(|c| c.bytes).sum::<usize>() + bytes > cache.budget {
                cache.kept.remove(0);
            }
            cache.kept.push(CachedSide {
                model: model_points.to_vec(),
                rotations: key,
                side: side.clone(),
                bytes,
            });
        }
        Ok(side)
    }

    pub fn config(&self) -> &PoseConfig {
        &self.config
    }

    /// Forgets the kept model sides (the network they came from changed), keeping the budget.
    fn dropping_model_sides(self) -> Self {
        match &self.model_sides {
            Some(cache) => {
                let budget = cache.lock().unwrap_or_else(|e| e.into_inner()).budget;
                self.keeping_model_sides(budget)
            }
            None => self,
        }
    }

    /// The same weights with `k` neighbours per point in the DGCNN's k-NN graph instead of
    /// the k they were trained with (no weight depends on k): to measure accuracy against
    /// speed at another k. Kept model sides are dropped (they depend on k). Errors when `k` is
    /// 0; inputs then need at least max(k, 3) points.
    pub fn with_neighbours(mut self, k: usize) -> Result<Self> {
        if k == 0 {
            return Err(PoseError::Config("k must be at least 1".into()));
        }
        self.net.set_neighbours(k);
        self.config.net.k = k;
        Ok(self.dropping_model_sides())
    }

    /// The same weights attending over `keys` farthest-point samples of each cloud instead of
    /// every point (`None`: every point; see [`crate::NetConfig::pooled_keys`]): to run a
    /// network trained with full attention the cheaper way, or back. Kept model sides are
    /// dropped (they depend on it). Errors on `Some(0)`.
    pub fn with_pooled_keys(mut self, keys: Option<usize>) -> Result<Self> {
        if keys == Some(0) {
            return Err(PoseError::Config("pooled keys must be at least 1".into()));
        }
        self.net.set_pooled_keys(keys);
        self.config.net.pooled_keys = keys;
        Ok(self.dropping_model_sides())
    }

    pub fn net(&self) -> &PoseNet {
        &self.net
    }

    /// Runs the network (inference mode) on one pair.
    pub fn infer(&self, model_points: &[Vec3], observed_points: &[Vec3]) -> Result<HeadOutput> {
        let k = self.config.net.k.max(3);
        check_points("model points", model_points, k)?;
        check_points("observed points", observed_points, k)?;
        let batch = PairBatch::new(
            &[(model_points, observed_points)],
            self.config.net.k,
            &self.device,
        )?;
        let out = self.net.forward_t(&batch, false)?;
        Ok(HeadOutput {
            log_p: out.log_p.detach(),
            ..out
        })
    }

    /// One estimate per pair, all pairs through the network as one batch (every pair must
    /// have the same model and observed point counts). Each pose maps its pair's model points
    /// (model frame, normalised units) onto its observed points (camera frame).
    ///
    /// Errors of the whole batch: an empty batch, differing point counts, fewer points than the
    /// network's k (or 3), non-finite coordinates. A pair whose correspondences admit no pose
    /// (degenerate for Procrustes) gets its own error in the returned list.
    pub fn estimate_batch(
        &self,
        pairs: &[(&[Vec3], &[Vec3])],
    ) -> Result<Vec<Result<PoseEstimate>>> {
        let batch = PairBatch::new(pairs, self.config.net.k, &self.device)?;
        let out = self.net.forward_t(&batch, false)?;
        let matches = out.matches()?;
        Ok(pairs
            .iter()
            .zip(&matches)
            .map(|((x, y), m)| {
                let r = recover_pose(x, y, m, &self.recovery)?;
                Ok(PoseEstimate {
                    pose: r.pose,
                    inlier_count: r.inlier_count,
                    assignment_confidence: r.assignment_confidence,
                })
            })
            .collect())
    }

    /// The rotation sweep of hypothesise-and-verify: one estimate per rotation, of the copy
    /// of `model_points` (model frame, normalised units) turned by that rotation about the
    /// model's origin, against the same `observed_points` (camera frame). All copies go through
    /// the network as one batch, with the observed cloud encoded once
    /// ([`PoseNet::forward_sweep_side`]; the copies' side comes from the kept ones when
    /// these model points and rotations were swept before); with `options.keep` below the
    /// number of rotations, only copy 0 and the `keep − 1` copies whose DGCNN features best
    /// match the observed ones meet the observed cloud in the transformer. Each returned pose maps the *unrotated* model
    /// points onto the observed points (the copy's pose composed with its rotation). With
    /// `options.sampling`, each copy also gets the poses of minimal sets drawn from its
    /// correspondences ([`sample_poses`], seeded by `options.seed` and the copy's index).
    ///
    /// Errors of the whole sweep: no rotation, fewer points than the network's k (or 3),
    /// non-finite coordinates. A copy whose correspondences admit no pose gets its own error.
    pub fn estimate_rotations(
        &self,
        model_points: &[Vec3],
        rotations: &[Pose],
        observed_points: &[Vec3],
        options: &SweepOptions,
    ) -> Result<Vec<Result<CopyEstimate>>> {
        let batch = SweepBatch::new(
            model_points,
            rotations,
            observed_points,
            self.config.net.k,
            &self.device,
        )?;
        let side = self.model_side(&batch, model_points, rotations)?;
        let (out, kept) = self.net.forward_sweep_side(&side, &batch, options.keep)?;
        let matches = out.matches()?;
        Ok(kept
            .iter()
            .zip(&matches)
            .map(|(&i, m)| {
                let (copy, r) = (&batch.copies[i], &rotations[i]);
                let e = recover_pose(copy, observed_points, m, &self.recovery)?;
                let rotation = Pose {
                    rotation: r.rotation,
                    translation: ic_geometry::glam::DVec3::ZERO,
                };
                let sampled = match &options.sampling {
                    Some(sampling) => sample_poses(
                        copy,
                        observed_points,
                        m,
                        sampling,
                        options.seed.wrapping_add(i as u64),
                    )
                    .into_iter()
                    .map(|s| SampledPose {
                        pose: s.pose.compose(&rotation),
                        inliers: s.inliers,
                    })
                    .collect(),
                    None => Vec::new(),
                };
                Ok(CopyEstimate {
                    rotation: i,
                    estimate: PoseEstimate {
                        pose: e.pose.compose(&rotation),
                        inlier_count: e.inlier_count,
                        assignment_confidence: e.assignment_confidence,
                    },
                    sampled,
                })
            })
            .collect())
    }

    /// The pose mapping `model_points` (model frame) onto `observed_points` (camera frame).
    ///
    /// Errors: fewer points than the network's k (or 3), non-finite coordinates.
    pub fn estimate(
        &self,
        model_points: &[Vec3],
        observed_points: &[Vec3],
    ) -> Result<PoseEstimate> {
        let out = self.infer(model_points, observed_points)?;
        let matches = out.matches()?.remove(0);
        let r = recover_pose(model_points, observed_points, &matches, &self.recovery)?;
        Ok(PoseEstimate {
            pose: r.pose,
            inlier_count: r.inlier_count,
            assignment_confidence: r.assignment_confidence,
        })
    }
}
