//! Typed errors of the renderers, the scene builder and the image I/O.

use std::path::PathBuf;

/// Rendering or scene assembly failed.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// `WGPU_BACKEND` (or `WgpuOptions::backends`, feature `gpu`) named a backend wgpu does not
    /// know.
    #[error(
        "invalid wgpu backend list {value:?}: unknown name {name:?} (expected a comma-separated \
         list of vulkan|vk, gl|gles|opengl, metal|mtl, dx12|d3d12)"
    )]
    InvalidBackend { value: String, name: String },
    /// No adapter: neither a GPU nor a software rasteriser is installed.
    #[error(
        "no wgpu adapter found for backends {backends}: no GPU driver and no software Vulkan. \
         Install the Debian package `mesa-vulkan-drivers` (with `libvulkan1`) for lavapipe, or \
         use the CPU renderer"
    )]
    NoAdapter { backends: String },
    /// The adapter refused to create a device.
    #[error("the wgpu adapter {adapter:?} could not create a device: {message}")]
    Device { adapter: String, message: String },
    /// A GPU operation (readback, validation) failed.
    #[error("wgpu error: {0}")]
    Gpu(String),
    /// Instance ids must fit the 16-bit instance PNG: 1..=65535 (0 is the background).
    #[error("object {index}: instance id {id} is not in 1..=65535 (0 is the background)")]
    InvalidInstanceId { index: usize, id: u32 },
    /// A mesh of the scene is not valid.
    #[error("object {index}: invalid mesh: {source}")]
    InvalidMesh {
        index: usize,
        #[source]
        source: ic_geometry::MeshDataError,
    },
    /// Intrinsics, a pose or a parameter is invalid.
    #[error(transparent)]
    Geometry(#[from] ic_geometry::GeometryError),
    /// The image is larger than the device supports.
    #[error("image {width}×{height} exceeds the device's maximum texture size {max}")]
    ImageTooLarge { width: u32, height: u32, max: u32 },
    /// A scene configuration value is out of range.
    #[error("invalid scene configuration: {field}: {message}")]
    InvalidConfig {
        field: &'static str,
        message: String,
    },
    /// Rejection sampling found no valid placement.
    #[error(
        "could not place {what} after {tries} tries (room too small for the object and camera distance?)"
    )]
    PlacementFailed { what: &'static str, tries: usize },
}

/// Reading or writing an image file failed; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    #[error("{path}: cannot read or write: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The PNG or EXR decoder/encoder failed.
    #[error("{path}: {message}")]
    Codec { path: PathBuf, message: String },
    /// The file decoded but has the wrong kind of pixels (bit depth, colour type, channels).
    #[error("{path}: expected {expected}, found {found}")]
    Format {
        path: PathBuf,
        expected: String,
        found: String,
    },
    /// The image size differs from the expected one.
    #[error("{path}: image is {got_width}×{got_height}, expected {width}×{height}")]
    SizeMismatch {
        path: PathBuf,
        width: u32,
        height: u32,
        got_width: u32,
        got_height: u32,
    },
    /// A value cannot be stored in the format (depth too far for 16 bits, NaN, id > 65535, …).
    #[error("{path}: pixel ({u}, {v}): {message}")]
    ValueOutOfRange {
        path: PathBuf,
        u: u32,
        v: u32,
        message: String,
    },
    /// A parameter (e.g. the depth scale) is invalid.
    #[error("{path}: invalid parameter: {message}")]
    InvalidParameter { path: PathBuf, message: String },
    /// The header declares an image larger than [`crate::io::MAX_IMAGE_SIDE`] per side or
    /// [`crate::io::MAX_IMAGE_PIXELS`] in all; refused before any pixel is decoded.
    #[error(
        "{path}: the image declares {width}×{height} pixels, more than the largest supported \
         ({} per side, {} pixels in all); is the file damaged?",
        crate::io::MAX_IMAGE_SIDE,
        crate::io::MAX_IMAGE_PIXELS
    )]
    TooLarge {
        path: PathBuf,
        width: u64,
        height: u64,
    },
}

impl ImageIoError {
    /// The file this error is about.
    pub fn path(&self) -> &std::path::Path {
        match self {
            ImageIoError::Io { path, .. }
            | ImageIoError::Codec { path, .. }
            | ImageIoError::Format { path, .. }
            | ImageIoError::SizeMismatch { path, .. }
            | ImageIoError::ValueOutOfRange { path, .. }
            | ImageIoError::InvalidParameter { path, .. }
            | ImageIoError::TooLarge { path, .. } => path,
        }
    }
}
