//! `ic_pose` — the paper's one-shot pose estimator.
//!
//! This crate will own the DGCNN encoder, the transformer block, the score map
//! S = fx·fyᵀ, the softmax and log-domain Sinkhorn (outlier bins) heads, the negative
//! log-likelihood loss, pose recovery by (weighted) Procrustes, the `PoseEstimator` inference
//! API and safetensors checkpoints. It knows nothing about rendering. See issue 5.
