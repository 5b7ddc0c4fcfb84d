//! safetensors checkpoints with the configuration (and training state) in the metadata,
//! written atomically (temporary file + rename).
//!
//! Metadata keys: [`CONFIG_KEY`] (the [`PoseConfig`] as JSON), [`STATE_KEY`] (a
//! [`TrainState`] as JSON, training checkpoints only). Tensors: the network's variables by
//! name; training checkpoints add the Adam moments as `adam.m/<name>` and `adam.v/<name>`,
//! which inference ignores.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::path::Path;

use candle_core::Tensor;
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

/// Writes `tensors` with `metadata` to `path` atomically.
pub fn save(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<()> {
    let mut sorted: Vec<(&str, &Tensor)> = tensors.iter().map(|(k, t)| (k.as_str(), t)).collect();
    sorted.sort_by(|a, b| a.0.cmp(b.0));
    let bytes = safetensors::serialize(sorted, Some(metadata))
        .map_err(|e| ck_err(path, format!("serialising: {e}")))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| PoseError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    ic_geometry::io::write_atomic_with(path, |w| w.write_all(&bytes), |e| e).map_err(|source| {
        PoseError::Io {
            path: path.to_path_buf(),
            source,
        }
    })
}

/// The metadata of a safetensors file (reads only its header).
pub fn read_metadata(path: &Path) -> Result<HashMap<String, String>> {
    let mut f = std::fs::File::open(path).map_err(|source| PoseError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| ck_err(path, "not a safetensors file (too short)"))?;
    let len = u64::from_le_bytes(len);
    if len > 100_000_000 {
        return Err(ck_err(path, "not a safetensors file (header size)"));
    }
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header)
        .map_err(|_| ck_err(path, "truncated safetensors header"))?;
    let json: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| ck_err(path, format!("bad safetensors header: {e}")))?;
    let mut out = HashMap::new();
    if let Some(meta) = json.get("__metadata__").and_then(|m| m.as_object()) {
        for (k, v) in meta {
            if let Some(s) = v.as_str() {
                out.insert(k.clone(), s.to_string());
            }
        }
    }
    Ok(out)
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
