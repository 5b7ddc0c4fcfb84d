use std::path::PathBuf;

/// Errors of `ic_seg`.
#[derive(Debug, thiserror::Error)]
pub enum SegError {
    /// No connected component scored above the threshold: the object is not in the image (or
    /// the network missed it).
    #[error(
        "object not found: no instance scored above {threshold}; {}",
        match best_score {
            Some(b) => format!("the best scored {b:.2}"),
            None => "no instance was found at all".to_string(),
        }
    )]
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

#[cfg(test)]
mod tests {
    use super::SegError;

    #[test]
    fn object_not_found_reads_as_a_sentence_without_debug_text() {
        let some = SegError::ObjectNotFound {
            threshold: 0.5,
            best_score: Some(0.345_885),
        }
        .to_string();
        assert_eq!(
            some,
            "object not found: no instance scored above 0.5; the best scored 0.35"
        );
        let none = SegError::ObjectNotFound {
            threshold: 0.5,
            best_score: None,
        }
        .to_string();
        assert_eq!(
            none,
            "object not found: no instance scored above 0.5; no instance was found at all"
        );
        assert!(!some.contains("Some(") && !none.contains("None"));
    }
}
