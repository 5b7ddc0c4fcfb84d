//! `ic_pose` — the paper's one-shot pose estimator.
//!
//! Dang, Wang, Salzmann, *3D Registration for Self-Occluded Objects in Context*, CVPR 2021,
//! Sec. 3 "Pose Estimation": a shared DGCNN encodes the model points X (M×3, model frame) and
//! the observed points Y (N×3, camera frame) into θx, θy; one transformer block gives
//! fx = θx + φ(θx, θy) and fy = θy + φ(θy, θx); the score map S = fx·fyᵀ/√d goes through a
//! **softmax** head (for each observed point, log P over the M model points) or an **OT** head
//! (log-domain Sinkhorn with outlier bins, [`sinkhorn::log_optimal_transport`]); the training
//! loss is the normalised negative log-likelihood of the ground-truth assignment
//! ([`nll_loss`]); the pose comes from weighted Procrustes over the arg-max correspondences,
//! optionally refined by ICP ([`recover_pose`]).
//!
//! Inference:
//!
//! ```no_run
//! use ic_pose::PoseEstimator;
//! # fn main() -> Result<(), ic_pose::PoseError> {
//! let estimator = PoseEstimator::load("models/pose-cpu-ot.safetensors")?;
//! # let (model, observed) = (vec![], vec![]);
//! let estimate = estimator.estimate(&model, &observed)?;
//! println!("{:?} from {} correspondences", estimate.pose, estimate.inlier_count);
//! # Ok(()) }
//! ```
//!
//! Training lives in `ic_train` (its `PoseTrainer` builds a network with seeded weights,
//! steps Adam on batches of rendered samples and saves the checkpoints [`checkpoint`]
//! describes); this crate holds what training needs of the network — [`nll_loss`] over a
//! ground-truth [`Assignment`], [`nearest_assignments`], [`correspondence_accuracy`] — and
//! depends on no renderer, so an inference-only user of [`PoseEstimator`] compiles none.
//!
//! Implementation notes (measured with candle 0.11 on CPU): on the CPU with f32 the hot
//! layers are fused candle custom ops with hand-written backward passes — attention, Dense,
//! LayerNorm, the EdgeConv gather-max and BN + LeakyReLU (all in [`ic_nn::ops`]), Sinkhorn
//! ([`sinkhorn`]) — each beside a tensor-op version that other
//! devices use and the tests compare against (candle-nn's own fused LayerNorm and softmax
//! have no backward); the k-NN graph is computed in plain Rust ([`knn`]); DGCNN runs
//! channel-first with the per-point products before the neighbour gather. Call
//! [`tune_candle_cpu_pool`] first thing in `main`.

pub mod checkpoint;
pub mod config;
pub mod dgcnn;
mod error;
pub mod estimator;
pub mod knn;
pub mod layers;
pub mod network;
pub mod recover;
pub mod sinkhorn;
pub mod transformer;

// The candle pool settings belong to the fused kernels, which live in `ic_nn::ops`.
pub use config::{Head, NetConfig, OtConfig, OtLoss, PoseConfig, TrainConfig};
pub use error::{PoseError, Result};
pub use estimator::{CopyEstimate, MODEL_SIDE_BYTES, PoseEstimate, PoseEstimator, SweepOptions};
/// The ground-truth assignment M̄ the loss reads (defined in `ic_geometry`, built by `ic_data`).
pub use ic_geometry::Assignment;
pub use ic_nn::ops::{CANDLE_CPU_ENV, tune_candle_cpu_pool};
pub use ic_nn::{adam, seeded_var_builder};
pub use network::{
    HeadOutput, Match, PairBatch, PoseNet, SweepBatch, correspondence_accuracy,
    nearest_assignments, nll_loss,
};
pub use recover::{
    Recovered, RecoveryOptions, Refine, SampledPose, SamplingOptions, recover_pose, sample_poses,
};
pub use transformer::ModelSide;
