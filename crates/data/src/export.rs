//! Registration cases for other tools (Open3D, TEASER++, our own CLI): one folder per case,
//! laid out as [`CaseFolder`] says (the format's one owner, in `ic_eval::cases` so that the
//! scorer, which depends on `ic_geometry` only, reads what this module writes):
//!
//! - `source.ply`: the model points X (model frame, normalised units), binary little-endian
//!   `float x y z`;
//! - `target.ply`: the observed points — the N sampled object points (object alone) or the
//!   whole voxelised scene (room) — camera frame, normalised units;
//! - `gt.json`: the pose in [`Pose`]'s serde form, `{"R": [[…], […], […]], "t": [x, y, z]}`
//!   with `target ≈ R·source + t` (R row-major, model → camera, normalised units);
//! - `meta.json`: object id, sample index, seed, counts, inlier rate;
//! - room cases also hold `depth.png` (16-bit, `stored × depth_scale = mm`, 1 normalised unit
//!   = `unit_mm` mm) and `camera.json` (`cam_K` row-major 9 numbers, `depth_scale`, `width`,
//!   `height`, `unit_mm`): back-projecting `depth.png` with `cam_K` and dividing by `unit_mm`
//!   gives the scene in the units of `target.ply` (before voxelising), and `mask.png` (8-bit,
//!   255 on the visible object), the ground-truth mask for upper-bound runs only.
//!
//! Every file is written atomically (temporary file + rename).

use std::path::Path;

use ic_geometry::io::{PlyEncoding, write_ply};
use ic_geometry::{Image, PointCloud, Pose};
use serde_json::{Value, json};

pub use ic_eval::cases::CaseFolder;

use crate::{DataError, ObjectSample, ROOM_UNIT_MM, RoomSample};

pub(crate) fn write_json_atomic(path: &Path, value: &Value) -> Result<(), DataError> {
    let text = serde_json::to_string_pretty(value).map_err(|e| DataError::json(path, e))?;
    ic_render::io::write_atomic(path, |w| {
        std::io::Write::write_all(w, text.as_bytes()).map_err(|source| {
            ic_render::ImageIoError::Io {
                path: path.to_path_buf(),
                source,
            }
        })
    })?;
    Ok(())
}

/// `{"R": rows, "t": [x, y, z]}`: [`Pose`]'s serde form.
pub fn pose_json(pose: &Pose) -> Value {
    json!(pose)
}

fn write_common(
    dir: &Path,
    source: &[ic_geometry::glam::Vec3],
    target: &[ic_geometry::glam::Vec3],
    pose: &Pose,
    meta: Value,
) -> Result<(), DataError> {
    std::fs::create_dir_all(dir).map_err(DataError::io(dir))?;
    let case = CaseFolder::new(dir);
    write_ply(
        case.source(),
        &PointCloud::from_points(source.to_vec()),
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_ply(
        case.target(),
        &PointCloud::from_points(target.to_vec()),
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_json_atomic(&case.gt(), &pose_json(pose))?;
    write_json_atomic(&case.meta(), &meta)
}

/// Writes an object-alone case into `dir` (created if needed).
pub fn write_object_case(
    dir: impl AsRef<Path>,
    sample: &ObjectSample,
    seed: u64,
) -> Result<(), DataError> {
    let meta = json!({
        "set": "noback",
        "object_id": sample.object_id,
        "index": sample.index,
        "seed": seed,
        "source_points": sample.model_points.len(),
        "target_points": sample.observed_points.len(),
        "observed_voxels": sample.observed_voxels,
        "inliers": sample.inlier_count(),
        "inlier_rate": sample.assignment.observed_inlier_rate(),
        "units": "normalised object units",
    });
    write_common(
        dir.as_ref(),
        &sample.model_points,
        &sample.observed_points,
        &sample.pose,
        meta,
    )
}

/// Writes a room case into `dir`: the common files plus `depth.png` and `camera.json`
/// (1 unit = [`ROOM_UNIT_MM`] mm, depth scale 1.0).
pub fn write_room_case(
    dir: impl AsRef<Path>,
    sample: &RoomSample,
    seed: u64,
) -> Result<(), DataError> {
    let dir = dir.as_ref();
    let unit_mm = ROOM_UNIT_MM;
    let depth_scale = 1.0;
    let meta = json!({
        "set": "room",
        "object_id": sample.object_id,
        "index": sample.index,
        "seed": seed,
        "source_points": sample.model_points.len(),
        "target_points": sample.scene_points.len(),
        "object_points": sample.object_point_count(),
        "inlier_rate": sample.inlier_rate,
        "bbox_visib": sample.bbox_visib,
        "units": "normalised object units",
        "unit_mm": unit_mm,
    });
    write_common(
        dir,
        &sample.model_points,
        &sample.scene_points,
        &sample.pose,
        meta,
    )?;
    let k = sample.intrinsics;
    let metres = Image {
        width: k.width,
        height: k.height,
        data: sample
            .depth
            .data
            .iter()
            .map(|&z| (z as f64 * unit_mm / 1000.0) as f32)
            .collect(),
    };
    let case = CaseFolder::new(dir);
    ic_render::io::write_depth_png(case.depth(), &metres, depth_scale)?;
    // The visible object mask, for methods run with the ground-truth mask (an upper bound);
    // a method under test must not read it otherwise.
    ic_render::io::write_mask_png(case.mask(), &sample.mask_visib)?;
    write_json_atomic(
        &case.camera(),
        &json!({"cam_K": k.k_row_major().concat(), "depth_scale": depth_scale, "width": k.width, "height": k.height, "unit_mm": unit_mm}),
    )
}

/// Writes a deployment view case into `dir`: the object-alone files, plus `depth.png`
/// (16-bit, depth scale 0.1: tenths of a mm), `camera.json` (`unit_mm` = the sample's
/// millimetres per normalised unit), `mask.png` (the visible object) and `model.ply` (the
/// normalised mesh the pose refers to, so a case can be registered like a user's mesh).
/// Fails unless the sample kept its images and its model was not scale-augmented.
pub fn write_view_case(
    dir: impl AsRef<Path>,
    sample: &ObjectSample,
    mesh: &ic_geometry::Mesh,
    seed: u64,
) -> Result<(), DataError> {
    let dir = dir.as_ref();
    let (Some(depth), Some(mask)) = (&sample.depth, &sample.mask) else {
        return Err(DataError::Config {
            field: "keep_images",
            message: "a view case needs the sample's depth map and mask".into(),
        });
    };
    if sample.model_scale != ic_geometry::glam::Vec3::ONE {
        return Err(DataError::Config {
            field: "scale_augmentation",
            message: "a view case needs the corpus mesh itself (no scale augmentation)".into(),
        });
    }
    write_object_case(dir, sample, seed)?;
    let unit_mm = if sample.metres_per_unit > 0.0 {
        sample.metres_per_unit * 1000.0
    } else {
        ROOM_UNIT_MM
    };
    let depth_scale = 0.1;
    let metres = Image {
        width: depth.width,
        height: depth.height,
        data: depth
            .data
            .iter()
            .map(|&z| (z as f64 * unit_mm / 1000.0) as f32)
            .collect(),
    };
    let case = CaseFolder::new(dir);
    ic_render::io::write_depth_png(case.depth(), &metres, depth_scale)?;
    ic_render::io::write_mask_png(case.mask(), mask)?;
    ic_geometry::io::write_mesh_ply(case.model(), mesh, PlyEncoding::BinaryLittleEndian)?;
    let k = sample.intrinsics;
    write_json_atomic(
        &case.camera(),
        &json!({"cam_K": k.k_row_major().concat(), "depth_scale": depth_scale, "width": k.width, "height": k.height, "unit_mm": unit_mm}),
    )
}
