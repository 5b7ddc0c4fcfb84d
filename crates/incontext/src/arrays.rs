//! In-memory inputs: what `incontext register` reads from files, given as arrays instead (the
//! entry points of the Python module, `python/`). Every check and every message is the one
//! the command line gives for the same file, with the file's name replaced by the argument's
//! (`what`): `camera: invalid intrinsics: …`, `depth: image is 160×120, expected 320×240`.
//! All failures are bad input ([`crate::ErrorKind::Input`]), except "object not found".
//!
//! Units and frames, as on the command line:
//! - depth values are the sensor's: `value × depth_scale = mm` (BOP), 0 = no return;
//! - a mesh is in its own units, `unit_mm` millimetres each (1 for BOP meshes in mm);
//! - poses map model to camera coordinates (x right, y down, z forward), `x_cam = R·x + t`,
//!   in the mesh's units.
//!
//! ```no_run
//! use incontext::arrays::{self, DepthValues};
//! use incontext::pipeline::{Object, Pipeline};
//! # fn main() -> Result<(), incontext::CliError> {
//! let k = [525.0, 0.0, 319.5, 0.0, 525.0, 239.5, 0.0, 0.0, 1.0];
//! let camera = arrays::camera(k, 640, 480, 1.0, "camera")?;
//! let stored = vec![800u16; 640 * 480]; // 16-bit depth in mm (depth_scale 1)
//! let depth_mm = arrays::depth_mm(DepthValues::U16(&stored), 640, 480, &camera, "depth")?;
//! let mesh = incontext::inputs::read_mesh("model.ply".as_ref())?; // in mm
//! let pipeline = Pipeline::builder().build()?;
//! let object = Object::from_mesh(mesh, 0)?;
//! let r = arrays::register_depth_mm(&pipeline, &object, &depth_mm, &camera.intrinsics, None, 1.0, 0)?;
//! println!("{:?}", r.pose);
//! # Ok(()) }
//! ```

use std::path::Path;

use ic_geometry::glam::Vec3;
use ic_geometry::{DepthImage, Image, Intrinsics, Mask, Mesh};
use serde_json::json;

use crate::error::{CliError, Result};
use crate::inputs::{self, CameraFile};
use crate::pipeline::{Object, Pipeline, Registration, Verdict};

/// Depth values as the sensor stores them (`value × depth_scale = mm`, 0 = no return), row
/// by row from the top-left pixel.
#[derive(Clone, Copy, Debug)]
pub enum DepthValues<'a> {
    /// A 16-bit depth map (a BOP PNG's values).
    U16(&'a [u16]),
    F32(&'a [f32]),
    F64(&'a [f64]),
}

impl DepthValues<'_> {
    fn len(&self) -> usize {
        match self {
            DepthValues::U16(v) => v.len(),
            DepthValues::F32(v) => v.len(),
            DepthValues::F64(v) => v.len(),
        }
    }

    /// Metres, converted exactly as `ic_render::io::read_depth_png` converts a PNG's values.
    fn metres(&self, depth_scale: f64) -> Vec<f32> {
        fn convert<T: Copy + Into<f64>>(v: &[T], depth_scale: f64) -> Vec<f32> {
            v.iter()
                .map(|&x| (x.into() * depth_scale / 1000.0) as f32)
                .collect()
        }
        match self {
            DepthValues::U16(v) => convert(v, depth_scale),
            DepthValues::F32(v) => convert(v, depth_scale),
            DepthValues::F64(v) => convert(v, depth_scale),
        }
    }
}

/// A pinhole camera from its matrix `k` (9 numbers, row-major: `[fx, 0, cx, 0, fy, cy, 0, 0,
/// 1]`, pixels), the image size (pixels) and the depth scale (`value × depth_scale = mm`),
/// with the checks of [`inputs::read_camera`] on a camera file that gives the size; errors
/// start with `what`.
pub fn camera(
    k: [f64; 9],
    width: u64,
    height: u64,
    depth_scale: f64,
    what: &str,
) -> Result<CameraFile> {
    let path = Path::new(what);
    // JSON has no NaN or infinity: refuse them before the JSON checks would call them null.
    if let Some(i) = k.iter().position(|x| !x.is_finite()) {
        return Err(CliError::input(format!(
            "{what}: cam_K: entry {i} ({}) is not a finite number",
            k[i]
        )));
    }
    if !depth_scale.is_finite() {
        return Err(CliError::input(format!(
            "{what}: depth_scale: {depth_scale} is not a finite number"
        )));
    }
    let spec = inputs::parse_camera(
        &json!({"cam_K": k, "width": width, "height": height, "depth_scale": depth_scale}),
        path,
    )?;
    let (w, h) = spec
        .size
        .ok_or_else(|| CliError::internal("the camera's size was given"))?;
    inputs::check_intrinsics(path, &spec, w, h, true)?;
    let intrinsics = Intrinsics::new(spec.fx, spec.fy, spec.cx, spec.cy, w, h)
        .map_err(|e| CliError::input(format!("{what}: {e}")))?;
    Ok(CameraFile {
        intrinsics,
        depth_scale: spec.depth_scale,
        size_given: true,
        unit_mm: None,
    })
}

/// A depth map in millimetres from the sensor's values (`value × camera.depth_scale = mm`,
/// `width × height`, row-major), with the checks of [`inputs::read_depth_mm`]: the size must
/// be the camera's; negative, non-finite and beyond-[`inputs::MAX_DEPTH_MM`] values are missing
/// returns; at least one pixel must hold a depth. Errors start with `what`.
pub fn depth_mm(
    values: DepthValues,
    width: u32,
    height: u32,
    camera: &CameraFile,
    what: &str,
) -> Result<DepthImage> {
    check_size(values.len(), width, height, &camera.intrinsics, what)?;
    let metres = Image {
        width,
        height,
        data: values.metres(camera.depth_scale),
    };
    inputs::checked_depth_mm(
        metres,
        Path::new(what),
        "is the camera's depth_scale right? (stored value × depth_scale = mm)",
    )
}

/// An image of `width × height` pixels given as `len` values must have the camera's size
/// (bad input otherwise) and one value per pixel (the caller's bug otherwise).
fn check_size(len: usize, width: u32, height: u32, k: &Intrinsics, what: &str) -> Result<()> {
    if (width, height) != (k.width, k.height) {
        return Err(CliError::input(format!(
            "{what}: image is {width}×{height}, expected {}×{}",
            k.width, k.height
        )));
    }
    if len != width as usize * height as usize {
        return Err(CliError::internal(format!(
            "{what}: {len} values for a {width}×{height} image"
        )));
    }
    Ok(())
}

/// An object mask (`true` = the object's pixel, row-major) of the camera's size, with the
/// checks of [`inputs::read_mask`]: the size, and at least one pixel set. Errors start with
/// `what`.
pub fn mask(
    values: Vec<bool>,
    width: u32,
    height: u32,
    intrinsics: &Intrinsics,
    what: &str,
) -> Result<Mask> {
    check_size(values.len(), width, height, intrinsics, what)?;
    if !values.iter().any(|&m| m) {
        return Err(CliError::input(format!(
            "{what}: the mask is empty (no pixel is set)"
        )));
    }
    Ok(Image {
        width,
        height,
        data: values,
    })
}

/// A mesh from vertices (in the mesh's own units) and triangles (indices into `vertices`),
/// with the checks of the mesh readers: some vertices and faces, finite coordinates, indices
/// in range. Errors start with `what`.
pub fn mesh(vertices: Vec<Vec3>, triangles: Vec<[u32; 3]>, what: &str) -> Result<Mesh> {
    Mesh::new(vertices, triangles).map_err(|e| CliError::input(format!("{what}: {e}")))
}

/// Checks millimetres per mesh unit (`what` names the argument, e.g. `--model-unit-mm`).
pub fn check_unit_mm(unit_mm: f64, what: &str) -> Result<()> {
    if unit_mm.is_finite() && unit_mm > 0.0 {
        Ok(())
    } else {
        Err(CliError::input(format!(
            "{what} must be positive, got {unit_mm}"
        )))
    }
}

/// What `incontext register` does once its files are read: the depth map (mm) in the mesh's
/// units (`model_unit_mm` mm each), [`Pipeline::register_depth`], and a `not_found` verdict
/// as the error of [`crate::register::not_found_error`]. The same inputs and `seed` give the
/// command's pose bit for bit (`object` sampled with the same seed by [`Object::from_mesh`];
/// the command loads the segmentation network only when there is no mask).
pub fn register_depth_mm(
    pipeline: &Pipeline,
    object: &Object,
    depth_mm: &DepthImage,
    intrinsics: &Intrinsics,
    mask: Option<&Mask>,
    model_unit_mm: f64,
    seed: u64,
) -> Result<Registration> {
    check_unit_mm(model_unit_mm, "model_unit_mm")?;
    let to_units = (1.0 / model_unit_mm) as f32;
    let depth = Image {
        width: depth_mm.width,
        height: depth_mm.height,
        data: depth_mm.data.iter().map(|&z| z * to_units).collect(),
    };
    let r = pipeline.register_depth(object, &depth, intrinsics, mask, seed)?;
    if r.verdict == Verdict::NotFound {
        return Err(crate::register::not_found_error(&r, &pipeline.options));
    }
    Ok(r)
}

/// [`Pipeline::register_points`] on observed object points in millimetres (camera frame):
/// they are brought to the object's normalised units (the camera frame scaled, not moved),
/// and a `not_found` verdict is an error as in [`register_depth_mm`]. The pose is in the
/// mesh's units.
pub fn register_points_mm(
    pipeline: &Pipeline,
    object: &Object,
    points_mm: &[Vec3],
    model_unit_mm: f64,
    seed: u64,
) -> Result<Registration> {
    check_unit_mm(model_unit_mm, "model_unit_mm")?;
    if let Some(i) = points_mm.iter().position(|p| !p.is_finite()) {
        return Err(CliError::input(format!(
            "points: point {i} ({:?}) is not finite",
            points_mm[i].to_array()
        )));
    }
    let to_normalised = (1.0 / (model_unit_mm * object.normalisation.scale)) as f32;
    let observed: Vec<Vec3> = points_mm.iter().map(|&p| p * to_normalised).collect();
    let r = pipeline.register_points(object, &observed, seed)?;
    if r.verdict == Verdict::NotFound {
        return Err(crate::register::not_found_error(&r, &pipeline.options));
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> CameraFile {
        camera(
            [131.25, 0.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
            160,
            120,
            0.1,
            "camera",
        )
        .unwrap()
    }

    #[test]
    fn cameras_from_arrays_are_checked_like_camera_files() {
        let c = cam();
        assert_eq!((c.intrinsics.width, c.intrinsics.height), (160, 120));
        assert_eq!(c.depth_scale, 0.1);
        for (k, w, scale, needle) in [
            (
                [0.0, 0.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
                160,
                0.1,
                "focal lengths must be positive",
            ),
            (
                [131.25, 1.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
                160,
                0.1,
                "skew",
            ),
            (
                [131.25, 0.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
                0,
                0.1,
                "width",
            ),
            (
                [131.25, 0.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
                160,
                0.0,
                "depth_scale",
            ),
            (
                [f64::NAN, 0.0, 79.5, 0.0, 131.25, 59.5, 0.0, 0.0, 1.0],
                160,
                0.1,
                "not a finite number",
            ),
        ] {
            let e = camera(k, w, 120, scale, "camera").unwrap_err();
            assert_eq!(e.exit_code(), 2);
            assert!(
                e.message.starts_with("camera: ") && e.message.contains(needle),
                "{}",
                e.message
            );
        }
    }

    #[test]
    fn depth_from_arrays_converts_like_the_png_reader_and_is_checked() {
        let c = cam();
        let stored: Vec<u16> = (0..160 * 120).map(|i| (i % 5000) as u16).collect();
        let ours = depth_mm(DepthValues::U16(&stored), 160, 120, &c, "depth").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let png = dir.path().join("depth.png");
        let metres = Image {
            width: 160,
            height: 120,
            data: stored
                .iter()
                .map(|&v| (v as f64 * 0.1 / 1000.0) as f32)
                .collect(),
        };
        ic_render::io::write_depth_png(&png, &metres, 0.1).unwrap();
        let read = inputs::read_depth_mm(&png, &c).unwrap();
        assert_eq!(ours, read, "the same millimetres, bit for bit");
        // Floats of the same values give the same depth.
        let floats: Vec<f32> = stored.iter().map(|&v| v as f32).collect();
        assert_eq!(
            depth_mm(DepthValues::F32(&floats), 160, 120, &c, "depth").unwrap(),
            ours
        );
        let e = depth_mm(DepthValues::U16(&stored[..80 * 60]), 80, 60, &c, "depth").unwrap_err();
        assert!(
            e.message
                .contains("depth: image is 80×60, expected 160×120"),
            "{}",
            e.message
        );
        let nan = vec![f32::NAN; 160 * 120];
        let e = depth_mm(DepthValues::F32(&nan), 160, 120, &c, "depth").unwrap_err();
        assert!(e.message.contains("no valid pixel"), "{}", e.message);
    }

    #[test]
    fn masks_and_meshes_from_arrays_are_checked() {
        let k = cam().intrinsics;
        let e = mask(vec![false; 160 * 120], 160, 120, &k, "mask").unwrap_err();
        assert!(
            e.message.contains("mask: the mask is empty"),
            "{}",
            e.message
        );
        assert!(mask(vec![true; 160 * 120], 160, 120, &k, "mask").is_ok());
        let e = mesh(vec![Vec3::ZERO; 3], vec![], "faces").unwrap_err();
        assert!(
            e.message.contains("faces: the mesh has no faces"),
            "{}",
            e.message
        );
        let e = mesh(vec![Vec3::ZERO; 3], vec![[0, 1, 3]], "faces").unwrap_err();
        assert!(e.message.contains("refers to vertex 3"), "{}", e.message);
        assert!(check_unit_mm(0.0, "unit_mm").is_err() && check_unit_mm(1.0, "unit_mm").is_ok());
    }
}
