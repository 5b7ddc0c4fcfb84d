//! `incontext` — the 6D pose of a known object in one depth map, as a library and a command
//! line.
//!
//! The library is the pipeline the commands (and the benchmark tool) share:
//! [`pipeline::Pipeline`] loads the segmentation and pose networks ([`models`]: the shipped
//! ones are embedded in the binary), and registers an [`pipeline::Object`] (a mesh, normalised
//! and sampled) in a depth map or onto observed points, with per-stage timings. [`inputs`]
//! reads the user's files with checks that name the file, and [`arrays`] makes the same checks
//! on inputs held in memory (the Python module's entry point); [`overlay`] draws results; the
//! command modules ([`register`], [`demo`], [`eval`], [`render`], [`train`]) are what `incontext <command>`
//! runs. Every failure is a [`CliError`] whose kind gives the exit code: 2 bad input, 3 object
//! not found, 1 internal.
//!
//! ```no_run
//! use incontext::pipeline::{Object, Pipeline, PipelineOptions};
//! # fn main() -> Result<(), incontext::CliError> {
//! let camera = incontext::inputs::read_camera("camera.json".as_ref(), || unreachable!())?;
//! let depth = incontext::inputs::read_depth_mm("depth.png".as_ref(), &camera)?;
//! let mesh = incontext::inputs::read_mesh("model.ply".as_ref())?; // in mm, like the depth
//! let pipeline = Pipeline::load(None, None, None, true, PipelineOptions::default())?;
//! let object = Object::from_mesh(mesh, 0)?;
//! let r = pipeline.register_depth(&object, &depth, &camera.intrinsics, None, 0)?;
//! println!("{:?} (confidence {:.2}, {:.0} ms)", r.pose, r.confidence, r.seconds.total * 1e3);
//! # Ok(()) }
//! ```

pub mod arrays;
pub mod cli;
pub mod demo;
mod error;
pub mod eval;
pub mod inputs;
pub mod models;
pub mod outputs;
pub mod overlay;
pub mod pipeline;
pub mod register;
pub mod render;
pub mod train;
pub mod verify;

pub use error::{CliError, ErrorKind, Result, ResultExt};
pub use pipeline::{Object, Pipeline, PipelineOptions, Registration, StageSeconds};
