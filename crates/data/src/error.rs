//! Typed errors of corpora, sample generation, BOP interop and case export.

use std::path::PathBuf;

/// Everything that can go wrong in `ic_data`. Errors about files name the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file or folder could not be read or written.
    #[error("{path}: cannot read or write: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A corpus folder holds no object for the requested split.
    #[error("{folder}: the {split} split is empty ({detail})")]
    EmptySplit {
        folder: PathBuf,
        split: String,
        detail: String,
    },
    /// A corpus folder does not have the expected layout.
    #[error("{folder}: {message}")]
    Layout { folder: PathBuf, message: String },
    /// A mesh could not be loaded (and the corpus was told to stop on bad meshes, or no good
    /// mesh is left).
    #[error(transparent)]
    Mesh(#[from] ic_geometry::MeshError),
    /// A mesh loaded but is unusable (degenerate, no visible surface…).
    #[error("{path}: unusable mesh: {message}")]
    BadMesh { path: PathBuf, message: String },
    /// Every object of the corpus failed to load.
    #[error("{folder}: no object of the {split} split could be loaded ({skipped} skipped)")]
    NoUsableObject {
        folder: PathBuf,
        split: String,
        skipped: usize,
    },
    /// A JSON file is malformed or misses a field.
    #[error("{path}: {message}")]
    Json { path: PathBuf, message: String },
    /// A configuration value is out of range.
    #[error("invalid configuration: {field}: {message}")]
    Config {
        field: &'static str,
        message: String,
    },
    /// A geometric operation failed.
    #[error(transparent)]
    Geometry(#[from] ic_geometry::GeometryError),
    /// Rendering or scene assembly failed.
    #[error(transparent)]
    Render(#[from] ic_render::RenderError),
    /// Reading or writing an image failed.
    #[error(transparent)]
    Image(#[from] ic_render::ImageIoError),
    /// A sample could not be produced (e.g. the object is not visible from the camera).
    #[error("sample {index}: {message}")]
    Sample { index: u64, message: String },
    /// A prefetch worker stopped unexpectedly.
    #[error("prefetch worker failed: {0}")]
    Worker(String),
}

impl DataError {
    pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> DataError {
        let path = path.into();
        move |source| DataError::Io { path, source }
    }

    pub(crate) fn json(path: impl Into<PathBuf>, message: impl std::fmt::Display) -> DataError {
        DataError::Json {
            path: path.into(),
            message: message.to_string(),
        }
    }
}
