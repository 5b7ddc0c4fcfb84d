//! safetensors checkpoints with the configuration (and training state) in the metadata,
//! written atomically (temporary file + rename).
//!
//! Metadata keys: [`CONFIG_KEY`] (the [`PoseConfig`] as JSON), [`STATE_KEY`] (a
//! [`TrainState`] as JSON, training checkpoints only). Tensors: the network's variables by
//! name; training checkpoints add the Adam moments as `adam.m/<name>` and `adam.v/<name>`,
//! which inference ignores.

use std::collections::HashMap;
use std::path::Path;

use candle_core::Tensor;
use ic_nn::CheckpointError;
use serde::{Deserialize, Serialize};

use crate::config::PoseConfig;
use crate::{PoseError, Result};

pub const CONFIG_KEY: &str = "ic_pose.config";
pub const STATE_KEY: &str = "ic_pose.train_state";

/// Where a training run stands.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Completed iterations (the next one is this index).
    pub iteration: u64,
    /// Seed of the run (weights initialisation and the sample stream).
    pub seed: u64,
    /// Adam's step count.
    pub adam_step: u64,
}

fn ck_err(path: &Path, message: impl Into<String>) -> PoseError {
    PoseError::Checkpoint {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

impl From<CheckpointError> for PoseError {
    fn from(e: CheckpointError) -> Self {
        match e {
            CheckpointError::Io { path, source } => PoseError::Io { path, source },
            CheckpointError::Format { path, message } => PoseError::Checkpoint { path, message },
        }
    }
}

/// Writes `tensors` with `metadata` to `path` atomically.
pub fn save(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<()> {
    Ok(ic_nn::checkpoint::save(path, tensors, metadata)?)
}

/// The metadata of a safetensors file (reads only its header).
pub fn read_metadata(path: &Path) -> Result<HashMap<String, String>> {
    Ok(ic_nn::checkpoint::read_metadata(path)?)
}

/// The configuration embedded in a checkpoint.
pub fn read_config(path: &Path) -> Result<PoseConfig> {
    let meta = read_metadata(path)?;
    let text = meta.get(CONFIG_KEY).ok_or_else(|| {
        ck_err(
            path,
            format!("no {CONFIG_KEY} metadata (not an ic_pose checkpoint?)"),
        )
    })?;
    let cfg: PoseConfig =
        serde_json::from_str(text).map_err(|e| ck_err(path, format!("bad config: {e}")))?;
    cfg.net
        .validate()
        .map_err(|e| ck_err(path, format!("bad config: {e}")))?;
    Ok(cfg)
}

/// The training state embedded in a training checkpoint.
pub fn read_state(path: &Path) -> Result<TrainState> {
    let meta = read_metadata(path)?;
    let text = meta
        .get(STATE_KEY)
        .ok_or_else(|| ck_err(path, "no training state (a weights-only checkpoint?)"))?;
    serde_json::from_str(text).map_err(|e| ck_err(path, format!("bad training state: {e}")))
}
