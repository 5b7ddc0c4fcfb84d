//! `ic_seg` checkpoints: safetensors with the [`SegConfig`] (and, for training checkpoints,
//! the [`SegTrainState`] and Adam's moments) — see `ic_nn::checkpoint`.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::SegConfig;
use crate::{Result, SegError};

pub const CONFIG_KEY: &str = "ic_seg.config";
pub const STATE_KEY: &str = "ic_seg.train_state";

/// Where a training run stands.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SegTrainState {
    /// Completed iterations (the next one is this index).
    pub iteration: u64,
    pub seed: u64,
    pub adam_step: u64,
}

fn bad(path: &Path, message: String) -> SegError {
    SegError::Checkpoint {
        path: path.to_path_buf(),
        message,
    }
}

/// The configuration embedded in a checkpoint.
pub fn read_config(path: &Path) -> Result<SegConfig> {
    let meta = ic_nn::checkpoint::read_metadata(path)?;
    let text = meta.get(CONFIG_KEY).ok_or_else(|| {
        bad(
            path,
            format!("no {CONFIG_KEY} metadata (not a segmentation checkpoint?)"),
        )
    })?;
    let cfg: SegConfig =
        serde_json::from_str(text).map_err(|e| bad(path, format!("bad config: {e}")))?;
    cfg.validate()
        .map_err(|e| bad(path, format!("bad config: {e}")))?;
    Ok(cfg)
}

/// The training state embedded in a training checkpoint.
pub fn read_state(path: &Path) -> Result<SegTrainState> {
    let meta = ic_nn::checkpoint::read_metadata(path)?;
    let text = meta.get(STATE_KEY).ok_or_else(|| {
        bad(
            path,
            "no training state (a weights-only checkpoint?)".into(),
        )
    })?;
    serde_json::from_str(text).map_err(|e| bad(path, format!("bad training state: {e}")))
}
