//! `ic_data` — samples for training and testing, built as the paper builds them.
//!
//! - [`Corpus`]: object corpora and splits — a ModelNet40 folder (`<class>/{train,test}/*.off`),
//!   a flat folder of meshes split by id range or a split file, a BOP `models/` folder, or the
//!   procedural stream of `ic_geometry::shapes::random_object`, or a weighted mixture of
//!   these ([`Corpus::mixture`]). Meshes are loaded once,
//!   normalised into [-1, 1] (the `Normalisation` is kept) and their visible-surface model
//!   points cached.
//! - [`ObjectSampleGenerator`]: the object alone (X, Y, true pose, ground-truth assignment M̄),
//!   under the paper's protocol or like deployment ([`deploy`], [`SamplingProtocol`]).
//! - [`RoomSampleGenerator`]: the object in the paper's cube room (640×480 depth, the whole
//!   scene voxelised, the visible-object mask, pose, boxes, inlier rate).
//! - [`Prefetcher`]: multi-threaded, bounded, order-preserving prefetching of samples/batches.
//! - [`bop`]: writing generated sets as BOP datasets and reading BOP datasets (TUD-L layout).
//! - [`export`]: registration cases for other tools (`source.ply`, `target.ply`, `gt.json`, …).
//!
//! Units: normalised object units everywhere (the object spans [-1, 1] on its longest side);
//! camera frame OpenCV (x right, y down, z forward); poses map model → camera. Every sample is a
//! pure function of `(seed, index)`, the corpus and the configuration, whatever the number of
//! threads. Bad input returns [`DataError`], never a panic.
//!
//! ```
//! use std::sync::Arc;
//! use ic_data::{Corpus, CorpusOptions, ObjectSampleConfig, ObjectSampleGenerator, Split};
//!
//! let options = CorpusOptions { model_points: 2048, ..CorpusOptions::default() };
//! let corpus = Arc::new(Corpus::procedural(4, Split::Train, 7, options).unwrap());
//! let generator = ObjectSampleGenerator::new(corpus, ObjectSampleConfig::default(), 42).unwrap();
//! let sample = generator.sample(0).unwrap();
//! assert_eq!(sample.model_points.len(), 1024);
//! assert_eq!(sample.observed_points.len(), 768);
//! // Matched pairs are closer than the threshold under the true pose.
//! for (i, j) in sample.assignment.pairs() {
//!     let moved = sample.pose.apply_f32(sample.model_points[i]);
//!     assert!(moved.distance(sample.observed_points[j]) < 0.05);
//! }
//! assert_eq!(generator.sample(0).unwrap(), sample);
//! ```

/// Cluttered scenes like real ones: tables, bins and shelves holding many objects.
pub mod clutter;
mod corpus;
/// Deployment-like sampling: whole-sphere views, roll, distance by image span, truncation,
/// scale augmentation, occluders, the sensor model with drawn strengths.
pub mod deploy;
mod error;
mod prefetch;
mod room;
mod sample;
mod seed;

/// BOP datasets: writing generated sets, reading BOP (e.g. TUD-L) datasets.
pub mod bop;
/// Registration cases for external tools (Open3D, TEASER++).
pub mod export;

pub use clutter::{ClutterConfig, ClutterGenerator, ClutterObject, ClutterScene, SupportKind};
pub use corpus::{
    Corpus, CorpusInfo, CorpusKind, CorpusObject, CorpusOptions, FolderSplit, MixturePart,
    ObjectEntry, ObjectSource, OnBadMesh, SourceInfo, Split, TRAINING_SYMMETRY_OPTIONS,
};
pub use deploy::SamplingProtocol;
pub use error::DataError;
/// The ground-truth assignment, defined in `ic_geometry` (so `ic_pose` reads it without
/// depending on this crate) and built here by every sample generator.
pub use ic_geometry::Assignment;
pub use prefetch::{Batches, Prefetcher};
pub use room::{
    ROOM_UNIT_MM, RoomSample, RoomSampleConfig, RoomSampleGenerator, RoomView, mask_bbox,
    voxelise_scene,
};
pub use sample::{
    ObjectSample, ObjectSampleConfig, ObjectSampleGenerator, PAPER_MATCH_THRESHOLD,
    PAPER_VOXEL_SIZE,
};
pub use seed::{mix as mix_seed, sample_rng};
