//! Object-size pose metrics of case folders: ADD-S against the object's diameter, and BOP's
//! MSSD and MSPD recalls (Hodaň et al. 2020), next to the rotation and translation errors of
//! [`crate::cases`].
//!
//! Every distance is in the case's normalised units (the units of `source.ply` and `gt.json`,
//! model → camera frame), every pixel in the case's image (`camera.json`). A pose is compared
//! with the truth under the object's symmetries (model-frame motions, the identity always
//! included): the same pose is wrong in rotation and right in MSSD when it is off by a
//! symmetry of the object.
//!
//! ```
//! use ic_eval::object_scores::{CaseGeometry, ObjectErrors, ObjectScore};
//! use ic_geometry::{Pose, glam::{DVec3, Vec3}};
//!
//! // A square, symmetric under a quarter turn about z.
//! let square = vec![
//!     Vec3::new(1.0, 1.0, 0.0), Vec3::new(-1.0, 1.0, 0.0),
//!     Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0),
//! ];
//! let quarter = Pose::from_axis_angle(DVec3::Z, std::f64::consts::FRAC_PI_2, DVec3::ZERO);
//! let geometry = CaseGeometry::new(square, vec![quarter], None);
//! let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 10.0));
//! let turned = truth.compose(&quarter);
//! let e = ObjectErrors::compute(&turned, &truth, &geometry).unwrap();
//! assert!(e.add_s < 1e-9 && e.mssd < 1e-9);
//! let score = ObjectScore::new(&[Some(e), None]);
//! assert_eq!((score.add_s_01d, score.ar_mssd), (0.5, 0.5));
//! ```

use std::path::Path;

use ic_geometry::glam::Vec3;
use ic_geometry::{GeometryError, Intrinsics, Pose};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::EvalError;
use crate::cases::CaseFolder;

/// BOP's MSSD thresholds, fractions of the object's diameter.
pub const MSSD_THRESHOLDS: [f64; 10] = [0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50];

/// BOP's MSPD thresholds in pixels of a 640-pixel-wide image (scaled by width / 640).
pub const MSPD_THRESHOLDS_PX: [f64; 10] =
    [5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0];

/// A pose is right in ADD-S when ADD-S is below this fraction of the diameter.
pub const ADD_S_FRACTION: f64 = 0.1;

/// The most model points the metrics use (an even subsample of `source.ply` beyond it): MSSD
/// is a maximum over points and symmetries, and the diameter is quadratic in the count.
pub const MAX_POINTS: usize = 2048;

/// What the object metrics need for one case.
#[derive(Clone, Debug, PartialEq)]
pub struct CaseGeometry {
    /// Model points (model frame, normalised units): `source.ply`, at most [`MAX_POINTS`].
    pub points: Vec<Vec3>,
    /// The largest distance between two of `points` (normalised units).
    pub diameter: f64,
    /// The object's symmetry motions (model frame); the identity is implied.
    pub symmetries: Vec<Pose>,
    /// The case's camera (pixels), for MSPD; `None` for object-alone cases.
    pub intrinsics: Option<Intrinsics>,
}

impl CaseGeometry {
    /// From the model points (subsampled evenly to [`MAX_POINTS`]), the symmetry motions and
    /// the camera.
    pub fn new(points: Vec<Vec3>, symmetries: Vec<Pose>, intrinsics: Option<Intrinsics>) -> Self {
        let points = if points.len() > MAX_POINTS {
            let step = points.len() as f64 / MAX_POINTS as f64;
            (0..MAX_POINTS)
                .map(|i| points[(i as f64 * step) as usize])
                .collect()
        } else {
            points
        };
        CaseGeometry {
            diameter: crate::diameter(&points),
            points,
            symmetries,
            intrinsics,
        }
    }

    /// Reads a case folder's model points (`source.ply`) and camera (`camera.json`, when the
    /// case has one); `symmetries` are the object's (e.g. from `ic_geometry::symmetry`).
    pub fn read(case: &CaseFolder, symmetries: Vec<Pose>) -> Result<Self, EvalError> {
        let source = case.source();
        let cloud = ic_geometry::io::read_ply_cloud(&source).map_err(|e| EvalError::Format {
            path: source.clone(),
            message: e.to_string(),
        })?;
        if cloud.points.is_empty() {
            return Err(EvalError::Format {
                path: source,
                message: "no model points".into(),
            });
        }
        let camera = case.camera();
        let intrinsics = if camera.is_file() {
            Some(read_case_camera(&camera)?)
        } else {
            None
        };
        Ok(CaseGeometry::new(cloud.points, symmetries, intrinsics))
    }
}

/// A case's `camera.json` as `ic_data::export` writes it: `cam_K` (9 numbers, row-major
/// `[fx, 0, cx, 0, fy, cy, 0, 0, 1]`, pixels), `width`, `height`.
pub fn read_case_camera(path: &Path) -> Result<Intrinsics, EvalError> {
    let bad = |message: String| EvalError::Format {
        path: path.to_path_buf(),
        message,
    };
    let bytes = ic_geometry::io::read_bounded(path, 1 << 20).map_err(|source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let v: Value = serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
    let k: Vec<f64> = v["cam_K"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    if k.len() != 9 {
        return Err(bad("cam_K is not 9 numbers (row-major 3×3)".into()));
    }
    let size = |key: &str| {
        v[key]
            .as_u64()
            .and_then(|n| u32::try_from(n).ok())
            .ok_or_else(|| bad(format!("no {key} (a positive integer, pixels)")))
    };
    Intrinsics::new(k[0], k[4], k[2], k[5], size("width")?, size("height")?)
        .map_err(|e| bad(format!("cam_K: {e}")))
}

/// One pose's object metrics against the truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectErrors {
    /// ADD-S / diameter.
    pub add_s: f64,
    /// MSSD / diameter, minimised over the symmetries.
    pub mssd: f64,
    /// MSPD in pixels (minimised over the symmetries), when the case has a camera.
    pub mspd_px: Option<f64>,
}

impl ObjectErrors {
    /// The metrics of `estimate` against `truth` (both model → camera, normalised units).
    pub fn compute(
        estimate: &Pose,
        truth: &Pose,
        geometry: &CaseGeometry,
    ) -> Result<Self, GeometryError> {
        let d = geometry.diameter.max(1e-12);
        let pts = &geometry.points;
        Ok(ObjectErrors {
            add_s: crate::add_s(estimate, truth, pts)? / d,
            mssd: crate::mssd(estimate, truth, pts, &geometry.symmetries)? / d,
            mspd_px: geometry
                .intrinsics
                .map(|k| crate::mspd(estimate, truth, pts, &geometry.symmetries, &k))
                .transpose()?,
        })
    }
}

/// A method's object metrics over a set of cases (failures count as wrong at every threshold).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectScore {
    /// Cases scored (failures included).
    pub cases: usize,
    /// Share of cases with ADD-S < [`ADD_S_FRACTION`] · diameter.
    pub add_s_01d: f64,
    /// BOP's AR_MSSD: the mean over [`MSSD_THRESHOLDS`] of the share below τ · diameter.
    pub ar_mssd: f64,
    /// BOP's AR_MSPD: the mean over [`MSPD_THRESHOLDS_PX`] (× width / 640) of the share below
    /// τ; `None` when a case has no camera.
    pub ar_mspd: Option<f64>,
}

impl ObjectScore {
    /// Over per-case errors (`None`: the method failed on the case). `image_width` scales the
    /// MSPD thresholds (640 when unknown).
    pub fn new(errors: &[Option<ObjectErrors>]) -> Self {
        Self::with_width(errors, 640)
    }

    /// [`ObjectScore::new`] for images `image_width` pixels wide.
    pub fn with_width(errors: &[Option<ObjectErrors>], image_width: u32) -> Self {
        let n = errors.len().max(1) as f64;
        let share = |f: &dyn Fn(&ObjectErrors) -> bool| {
            errors.iter().flatten().filter(|e| f(e)).count() as f64 / n
        };
        let mean = |ts: &[f64], f: &dyn Fn(&ObjectErrors, f64) -> bool| {
            ts.iter().map(|&t| share(&|e| f(e, t))).sum::<f64>() / ts.len() as f64
        };
        let r = image_width as f64 / 640.0;
        let has_mspd = !errors.is_empty() && errors.iter().flatten().all(|e| e.mspd_px.is_some());
        let thresholds_px: Vec<f64> = MSPD_THRESHOLDS_PX.iter().map(|t| t * r).collect();
        ObjectScore {
            cases: errors.len(),
            add_s_01d: share(&|e| e.add_s < ADD_S_FRACTION),
            ar_mssd: mean(&MSSD_THRESHOLDS, &|e, t| e.mssd < t),
            ar_mspd: has_mspd
                .then(|| mean(&thresholds_px, &|e, t| e.mspd_px.is_some_and(|m| m < t))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    fn cube() -> Vec<Vec3> {
        let mut v = Vec::new();
        for x in [-0.5f32, 0.5] {
            for y in [-0.5f32, 0.5] {
                for z in [-0.25f32, 0.25] {
                    v.push(Vec3::new(x, y, z));
                }
            }
        }
        v
    }

    #[test]
    fn a_pose_off_by_a_symmetry_is_right_in_mssd_and_mspd_and_wrong_without_it() {
        let half = Pose::from_axis_angle(DVec3::Z, std::f64::consts::PI, DVec3::ZERO);
        let k = Intrinsics::KINECT_640X480;
        let truth = Pose::from_translation(DVec3::new(0.1, 0.0, 3.0));
        let turned = truth.compose(&half);
        let with = CaseGeometry::new(cube(), vec![half], Some(k));
        let without = CaseGeometry::new(cube(), vec![], Some(k));
        let e = ObjectErrors::compute(&turned, &truth, &with).unwrap();
        assert!(
            e.add_s < 1e-6 && e.mssd < 1e-6 && e.mspd_px.unwrap() < 1e-6,
            "{e:?}"
        );
        let e = ObjectErrors::compute(&turned, &truth, &without).unwrap();
        // ADD-S forgives the turn on its own; MSSD without the symmetry does not: the corner
        // (0.5, 0.5) goes to (−0.5, −0.5), √2 away, and the diameter is √(1 + 1 + 0.25) = 1.5.
        assert!(e.add_s < 1e-6);
        assert!((e.mssd - 2f64.sqrt() / 1.5).abs() < 1e-6, "{e:?}");
        // √2 normalised units at the near face, z = 3 − 0.25, with f = 525: ≈ 270 px.
        assert!(
            (e.mspd_px.unwrap() - 525.0 * 2f64.sqrt() / 2.75).abs() < 0.5,
            "{e:?}"
        );
    }

    #[test]
    fn recalls_average_the_thresholds_and_count_failures_as_wrong() {
        let e = |add_s, mssd, mspd| {
            Some(ObjectErrors {
                add_s,
                mssd,
                mspd_px: Some(mspd),
            })
        };
        // MSSD 0.12 passes 8 of the 10 thresholds (0.15…0.50); MSPD 12 px passes 8 of 10.
        let s = ObjectScore::new(&[e(0.05, 0.12, 12.0), e(0.2, 0.6, 60.0), None, None]);
        assert_eq!(s.cases, 4);
        assert!((s.add_s_01d - 0.25).abs() < 1e-12);
        assert!((s.ar_mssd - 0.8 / 4.0).abs() < 1e-12, "{s:?}");
        assert!((s.ar_mspd.unwrap() - 0.8 / 4.0).abs() < 1e-12, "{s:?}");
        // On a 1280-pixel-wide image the pixel thresholds double: 12 px passes 9 of 10.
        let s = ObjectScore::with_width(&[e(0.05, 0.12, 12.0)], 1280);
        assert!((s.ar_mspd.unwrap() - 0.9).abs() < 1e-12, "{s:?}");
        // Without a camera on some case there is no AR_MSPD.
        let no_cam = Some(ObjectErrors {
            add_s: 0.0,
            mssd: 0.0,
            mspd_px: None,
        });
        assert_eq!(ObjectScore::new(&[e(0.0, 0.0, 0.0), no_cam]).ar_mspd, None);
    }

    #[test]
    fn a_long_model_is_subsampled_evenly() {
        let pts: Vec<Vec3> = (0..10_000).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let g = CaseGeometry::new(pts, vec![], None);
        assert_eq!(g.points.len(), MAX_POINTS);
        // The ends stay (near) the ends: the diameter is still about 10 000.
        assert!(g.diameter > 9_990.0, "{}", g.diameter);
    }

    #[test]
    fn a_case_camera_names_the_file_and_the_fault() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("camera.json");
        std::fs::write(
            &p,
            r#"{"cam_K": [525, 0, 319.5, 0, 525, 239.5, 0, 0, 1], "width": 640, "height": 480}"#,
        )
        .unwrap();
        assert_eq!(read_case_camera(&p).unwrap(), Intrinsics::KINECT_640X480);
        std::fs::write(
            &p,
            r#"{"cam_K": [525, 0, 319.5], "width": 640, "height": 480}"#,
        )
        .unwrap();
        let e = read_case_camera(&p).unwrap_err().to_string();
        assert!(e.contains("camera.json") && e.contains("cam_K"), "{e}");
        std::fs::write(
            &p,
            r#"{"cam_K": [525, 0, 319.5, 0, 525, 239.5, 0, 0, 1], "width": 640}"#,
        )
        .unwrap();
        let e = read_case_camera(&p).unwrap_err().to_string();
        assert!(e.contains("height"), "{e}");
    }
}
