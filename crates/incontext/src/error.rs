//! The error every command returns, classified by exit code.

use std::fmt;

/// What kind of failure an error is; decides the exit code.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// Bad input: flags, files, values (exit code 2). The message names the file and what is
    /// wrong with it.
    Input,
    /// The object was not found in the depth map (exit code 3).
    NotFound,
    /// Anything else: a bug or an environment problem (exit code 1).
    Internal,
}

impl ErrorKind {
    /// The process exit code of this kind: 2 bad input, 3 object not found, 1 internal.
    pub fn exit_code(self) -> u8 {
        match self {
            ErrorKind::Input => 2,
            ErrorKind::NotFound => 3,
            ErrorKind::Internal => 1,
        }
    }
}

/// An error with its kind (and so its exit code) and a message for people.
#[derive(Debug)]
pub struct CliError {
    pub kind: ErrorKind,
    pub message: String,
}

impl CliError {
    pub fn input(message: impl Into<String>) -> Self {
        CliError {
            kind: ErrorKind::Input,
            message: message.into(),
        }
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        CliError {
            kind: ErrorKind::NotFound,
            message: message.into(),
        }
    }

    pub fn internal(message: impl Into<String>) -> Self {
        CliError {
            kind: ErrorKind::Internal,
            message: message.into(),
        }
    }

    pub fn exit_code(&self) -> u8 {
        self.kind.exit_code()
    }

    /// The same error with `context: ` in front of its message.
    pub fn context(self, context: impl fmt::Display) -> Self {
        CliError {
            kind: self.kind,
            message: format!("{context}: {}", self.message),
        }
    }
}

impl fmt::Display for CliError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for CliError {}

/// Results of this crate.
pub type Result<T, E = CliError> = std::result::Result<T, E>;

/// The pipeline's errors keep their message; their variant gives the kind.
impl From<crate::pipeline::PipelineError> for CliError {
    fn from(e: crate::pipeline::PipelineError) -> Self {
        use crate::pipeline::PipelineError as P;
        match e {
            P::Input(m) => CliError::input(m),
            P::NotFound(m) => CliError::not_found(m),
            P::Internal(m) => CliError::internal(m),
        }
    }
}

/// Classified as the pipeline classifies them ([`crate::pipeline::PipelineError`]).
impl From<ic_pose::PoseError> for CliError {
    fn from(e: ic_pose::PoseError) -> Self {
        crate::pipeline::PipelineError::from(e).into()
    }
}

/// Classified as the pipeline classifies them ([`crate::pipeline::PipelineError`]).
impl From<ic_seg::SegError> for CliError {
    fn from(e: ic_seg::SegError) -> Self {
        crate::pipeline::PipelineError::from(e).into()
    }
}

/// Image files are user input: every error names the file.
impl From<ic_render::ImageIoError> for CliError {
    fn from(e: ic_render::ImageIoError) -> Self {
        CliError::input(e.to_string())
    }
}

/// Mesh files are user input: every error names the file.
impl From<ic_geometry::MeshError> for CliError {
    fn from(e: ic_geometry::MeshError) -> Self {
        CliError::input(e.to_string())
    }
}

/// Geometry errors that reach the command line come from computations on valid input.
impl From<ic_geometry::GeometryError> for CliError {
    fn from(e: ic_geometry::GeometryError) -> Self {
        CliError::internal(e.to_string())
    }
}

impl From<ic_data::DataError> for CliError {
    fn from(e: ic_data::DataError) -> Self {
        CliError::input(e.to_string())
    }
}

impl From<ic_render::RenderError> for CliError {
    fn from(e: ic_render::RenderError) -> Self {
        CliError::internal(format!("rendering: {e}"))
    }
}

impl From<ic_eval::EvalError> for CliError {
    fn from(e: ic_eval::EvalError) -> Self {
        CliError::internal(e.to_string())
    }
}

/// Extension to attach a kind and a context to foreign errors.
pub trait ResultExt<T> {
    /// Bad input, with `context: ` before the message.
    fn input_err(self, context: impl fmt::Display) -> Result<T>;
    /// Internal error, with `context: ` before the message.
    fn internal_err(self, context: impl fmt::Display) -> Result<T>;
}

impl<T, E: fmt::Display> ResultExt<T> for std::result::Result<T, E> {
    fn input_err(self, context: impl fmt::Display) -> Result<T> {
        self.map_err(|e| CliError::input(format!("{context}: {e}")))
    }
    fn internal_err(self, context: impl fmt::Display) -> Result<T> {
        self.map_err(|e| CliError::internal(format!("{context}: {e}")))
    }
}
