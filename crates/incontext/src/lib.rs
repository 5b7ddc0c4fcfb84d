//! `incontext` — the 6D pose of a known object in one depth map, as a library and a command
//! line.
//!
//! The library is the pipeline the commands (and the benchmark tool, and the Python module)
//! share: [`Pipeline::builder`] loads the segmentation and pose networks ([`models`]: the
//! shipped ones are embedded in the binary) with the settings of `incontext register` as
//! defaults, and [`Pipeline`] registers an [`Object`] (a mesh, normalised and sampled) in a
//! depth map or onto observed points, with per-stage timings, a calibrated confidence and a
//! [`Verdict`]. Its failures are [`PipelineError`]s: bad input, object not found, internal.
//!
//! Poses map model to camera coordinates, `x_cam = R·x_model + t` (OpenCV camera frame: x
//! right, y down, z forward), in the mesh's own units — those of the depth map, mm for BOP.
//! In files they are `{"R": [[..],[..],[..]], "t": [..]}` with `R` row-major, the serde form
//! of [`ic_geometry::Pose`].
//!
//! The command line's side: [`inputs`] reads the user's files with checks that name the file,
//! and [`arrays`] makes the same checks on inputs held in memory (the Python module's entry
//! point); [`overlay`] draws results; the command modules ([`register`], [`demo`], [`eval`],
//! [`render`], [`train`]) are what `incontext <command>` runs. Their failures are [`CliError`]s whose
//! kind gives the exit code: 2 bad input, 3 object not found, 1 internal (a
//! [`PipelineError`] converts into the kind of the same name).
//!
//! The demo's scene — a procedural object in the room, rendered at 640×480 — registered with
//! the shipped networks and checked against the truth:
//!
//! ```
//! use std::sync::Arc;
//!
//! use ic_data::{Corpus, CorpusOptions, ROOM_UNIT_MM, RoomSampleConfig, RoomSampleGenerator, Split};
//! use ic_geometry::{Image, Mesh, Normalisation, glam::DVec3};
//! use incontext::{Object, Pipeline, Refine, Verdict};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! // The scene of `incontext demo --seed 3`: the depth map in mm, the mesh in mm.
//! let seed = 3;
//! let options = CorpusOptions { model_points: 16, ..CorpusOptions::default() };
//! let corpus = Arc::new(Corpus::procedural(1, Split::Test, seed, options)?);
//! let generator = RoomSampleGenerator::new(corpus.clone(), RoomSampleConfig::default(), seed)?;
//! let view = generator.view_with(&mut ic_render::CpuRenderer::new(), 0)?;
//! let object = corpus.object(corpus.position(&view.object_id).ok_or("no object")?)?;
//! let mm = ROOM_UNIT_MM; // millimetres per normalised unit
//! let mesh_mm = Mesh {
//!     vertices: object.mesh.vertices.iter().map(|v| *v * mm as f32).collect(),
//!     triangles: object.mesh.triangles.clone(),
//! };
//! let depth_mm = Image {
//!     width: view.depth.width,
//!     height: view.depth.height,
//!     data: view.depth.data.iter().map(|&z| z * mm as f32).collect(),
//! };
//! let truth_mm = Normalisation { centre: DVec3::ZERO, scale: mm }.pose_to_original(&view.pose);
//!
//! // `incontext register` with its default flags, on two threads.
//! let pipeline = Pipeline::builder().refine(Refine::Icp).rotations(24).threads(2).build()?;
//! let object = Object::from_mesh(mesh_mm.clone(), seed)?;
//! let r = pipeline.register_depth(&object, &depth_mm, &view.intrinsics, None, seed)?;
//!
//! assert_eq!(r.verdict, Verdict::Ok);
//! assert!((r.pose.translation - truth_mm.translation).length() < 5.0); // mm
//! // The object is a table: a half turn about its legs gives the same surface, so the pose
//! // is judged by ADD-S (mean distance of each model vertex to the nearest vertex of the
//! // model at the true pose, mm) against the diameter, not by the rotation angle.
//! let diameter_mm = ic_eval::diameter(&mesh_mm.vertices);
//! let add_s_mm = ic_eval::add_s(&r.pose, &truth_mm, &mesh_mm.vertices)?;
//! assert!(add_s_mm < 0.01 * diameter_mm, "ADD-S {add_s_mm} mm");
//! // Poses are written as {"R": rows, "t": [x, y, z]} and read back checked.
//! let json = serde_json::to_string(&r.pose)?;
//! let back: ic_geometry::Pose = serde_json::from_str(&json)?;
//! assert!(back.rotation_angle_to(&r.pose) < 1e-9);
//! # Ok(()) }
//! ```
//!
//! From files, as `incontext register` reads them:
//!
//! ```no_run
//! use incontext::{Object, Pipeline};
//! # fn main() -> Result<(), incontext::CliError> {
//! let camera = incontext::inputs::read_camera("camera.json".as_ref(), || unreachable!())?;
//! let depth = incontext::inputs::read_depth_mm("depth.png".as_ref(), &camera)?;
//! let mesh = incontext::inputs::read_mesh("model.ply".as_ref())?; // in mm, like the depth
//! let pipeline = Pipeline::builder().build()?;
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
pub mod parts;
pub mod pipeline;
pub mod register;
pub mod render;
pub mod shape;
pub mod train;
pub mod verify;

pub use error::{CliError, ErrorKind, Result, ResultExt};
pub use ic_pose::{Head, Refine};
pub use pipeline::{
    CalibrationUsed, Object, Pipeline, PipelineBuilder, PipelineError, PipelineOptions,
    Registration, StageSeconds, Verdict, clutter_confidence, clutter_features,
};
