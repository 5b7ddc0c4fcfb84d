use std::path::PathBuf;

/// Errors of `ic_seg`.
#[derive(Debug, thiserror::Error)]
pub enum SegError {
    /// No connected component scored above the threshold: the object is not in the image (or
    /// the network missed it).
    #[error("object not found: no instance scored above {threshold} (best {best_score:?})")]
    ObjectNotFound {
        threshold: f32,
        best_score: Option<f32>,
    },
    #[error("bad input: {0}")]
    Input(String),
    #[error("bad configuration: {0}")]
    Config(String),
    #[error("{}: {message}", path.display())]
    Checkpoint { path: PathBuf, message: String },
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Geometry(#[from] ic_geometry::GeometryError),
    #[error(transparent)]
    Data(#[from] ic_data::DataError),
    #[error("network: {0}")]
    Candle(#[from] candle_core::Error),
}

impl From<ic_nn::CheckpointError> for SegError {
    fn from(e: ic_nn::CheckpointError) -> Self {
        match e {
            ic_nn::CheckpointError::Io { path, source } => SegError::Io { path, source },
            ic_nn::CheckpointError::Format { path, message } => {
                SegError::Checkpoint { path, message }
            }
        }
    }
}

pub type Result<T, E = SegError> = std::result::Result<T, E>;
