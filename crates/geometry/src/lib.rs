//! `ic_geometry` — the geometric foundation of incontext.
//!
//! Meshes (OBJ, glTF/GLB, OFF, PLY) and their normalisation, point clouds (area-weighted and
//! visible-surface sampling, voxel down-sampling, exact-count subsampling, PLY export), pinhole
//! cameras (OpenCV frame, look-at, the paper's view sphere, projection and back-projection),
//! SE(3) poses, kNN (kiddo), weighted Procrustes (faer SVD), ICP, and procedural shapes.
//!
//! Conventions, kept by every function here:
//! - units are metres in the camera frame, or normalised object units ([-1, 1]) for models;
//! - the camera frame is OpenCV's: x right, y down, z forward;
//! - a [`Pose`] maps source (model) coordinates into target (camera) coordinates,
//!   `x_cam = R·x_model + t`; rotations are written row-major in files;
//! - every random choice takes a seed or an `Rng`; no hidden global state;
//! - bad input returns a typed error ([`MeshError`], [`GeometryError`]), never a panic.
//!
//! ```
//! use ic_geometry::{procrustes, Pose};
//! use glam::{DVec3, Vec3};
//!
//! let model_points = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z];
//! let truth = Pose::from_axis_angle(DVec3::new(1.0, 2.0, 3.0), 0.4, DVec3::new(0.1, 0.0, 2.0));
//! let observed_points = truth.apply_all(&model_points);
//! let estimate = procrustes(&model_points, &observed_points, None).unwrap();
//! assert!(estimate.rotation_angle_to(&truth) < 1e-6);
//! ```

// `!(x > 0.0)` is how this crate rejects NaN together with non-positive values, on purpose.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

/// The ground-truth assignment M̄ between model and observed points (mutual nearest
/// neighbours under the true pose).
pub mod assignment;
mod camera;
mod cloud;
mod error;
mod icp;
mod image;
mod knn;
mod mesh;
mod pose;
mod procrustes;

/// Reading and writing meshes and point clouds (OBJ, OFF, PLY, glTF/GLB).
pub mod io;
/// Surface sampling: area-weighted uniform and visible-surface.
pub mod rotations;
pub mod sampling;
/// Procedural shapes: primitives and seeded composite objects.
pub mod shapes;
/// Rotational symmetries of a model (discrete and continuous), found on its surface.
pub mod symmetry;

pub use assignment::Assignment;
pub use camera::{Intrinsics, ViewSphere, Viewpoint, look_at};
pub use cloud::{
    PointCloud, estimate_normals, principal_axes, random_subsample, random_subsample_indices,
    voxel_downsample, voxel_downsample_points, voxel_of,
};
pub use error::{GeometryError, MeshDataError, MeshError};
pub use icp::*;
pub use image::{DepthImage, Image, InstanceImage, Mask};
pub use knn::*;
pub use mesh::{Aabb, Mesh, Normalisation};
pub use pose::{Pose, rotation_angle};
pub use procrustes::*;

/// Re-exported so users build points and poses with the same types.
pub use glam;
