//! Typed errors. Nothing in `ic_geometry` panics on user data: every malformed input is answered
//! by one of these, naming the file and the line or element where that is known.

use std::path::PathBuf;

/// What is wrong with the vertex/face data of a mesh, independent of where it came from.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshDataError {
    #[error("the mesh has no vertices")]
    NoVertices,
    #[error("the mesh has no faces")]
    NoFaces,
    #[error("vertex {vertex} has a non-finite coordinate ({value})")]
    NonFiniteVertex { vertex: usize, value: f32 },
    #[error("face {face} refers to vertex {index}, but the mesh has {vertex_count} vertices")]
    IndexOutOfRange {
        face: usize,
        index: u64,
        vertex_count: usize,
    },
    #[error("the mesh has zero surface area (all faces are degenerate)")]
    ZeroArea,
}

/// Reading or writing a mesh or point-cloud file failed.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("{path}: cannot read or write: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A syntax error at a known line (1-based).
    #[error("{path}:{line}: {message}")]
    Parse {
        path: PathBuf,
        line: usize,
        message: String,
    },
    /// A structural error without a line (binary formats, glTF accessors, …).
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    /// The file parsed, but its content is not a valid mesh.
    #[error("{path}: {source}")]
    Data {
        path: PathBuf,
        #[source]
        source: MeshDataError,
    },
    #[error(
        "{path}: unsupported mesh format {extension:?} (expected .obj, .off, .ply, .gltf or .glb)"
    )]
    UnsupportedFormat { path: PathBuf, extension: String },
    /// A point cloud to be written is invalid (attribute lengths, non-finite values).
    #[error("{path}: invalid point cloud: {source}")]
    Cloud {
        path: PathBuf,
        #[source]
        source: GeometryError,
    },
}

impl MeshError {
    /// The file this error is about.
    pub fn path(&self) -> &std::path::Path {
        match self {
            MeshError::Io { path, .. }
            | MeshError::Parse { path, .. }
            | MeshError::Format { path, .. }
            | MeshError::Data { path, .. }
            | MeshError::UnsupportedFormat { path, .. }
            | MeshError::Cloud { path, .. } => path,
        }
    }
}

/// Errors of the geometric algorithms (Procrustes, ICP, cameras, sampling).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    #[error("need at least {needed} correspondences with positive weight, got {got}")]
    TooFewCorrespondences { needed: usize, got: usize },
    #[error("the correspondences are degenerate (collinear or coincident points): rank {rank} < 2")]
    DegenerateCorrespondences { rank: usize },
    #[error("the total correspondence weight is zero")]
    ZeroWeight,
    #[error("weight {index} is negative or not finite ({value})")]
    InvalidWeight { index: usize, value: f64 },
    #[error("{what}: lengths differ ({left} vs {right})")]
    LengthMismatch {
        what: &'static str,
        left: usize,
        right: usize,
    },
    #[error("{what}: point {index} has a non-finite coordinate")]
    NonFinitePoint { what: &'static str, index: usize },
    #[error("{what} is empty")]
    Empty { what: &'static str },
    #[error("invalid camera intrinsics: {0}")]
    InvalidIntrinsics(String),
    #[error("image is {got_width}×{got_height}, expected {width}×{height}")]
    ImageSizeMismatch {
        width: u32,
        height: u32,
        got_width: u32,
        got_height: u32,
    },
    #[error("invalid parameter {name}: {message}")]
    InvalidParameter { name: &'static str, message: String },
    #[error("invalid rotation: {0}")]
    InvalidRotation(String),
}
