//! Typed errors of the pose crate.

use std::path::PathBuf;

/// Everything that can go wrong while building, training or running the pose network.
#[derive(Debug, thiserror::Error)]
pub enum PoseError {
    /// A point set is smaller than the network or Procrustes needs.
    #[error("too few {what}: got {got}, need at least {needed}")]
    TooFewPoints {
        what: &'static str,
        got: usize,
        needed: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error("{what}: point {index} is not finite")]
    NonFinite { what: &'static str, index: usize },
    /// A checkpoint could not be read, lacks its configuration, or does not fit the network.
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: PathBuf, message: String },
    /// A configuration value is out of range.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Inputs of a batch disagree in size.
    #[error("batch mismatch: {0}")]
    Batch(String),
    #[error("I/O error on {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Geometry(#[from] ic_geometry::GeometryError),
}

pub type Result<T, E = PoseError> = std::result::Result<T, E>;
