//! Per-sample pose errors.
//!
//! Poses map model coordinates into camera coordinates (`x_cam = R·x + t`), both in the same
//! units (normalised object units or millimetres — the functions do not care).

use ic_geometry::glam::{DVec3, Vec3};
use ic_geometry::{GeometryError, Intrinsics, KdTree, Pose};
use serde::{Deserialize, Serialize};

/// Rotation error E_rot = arccos((tr(R̂ᵀR) − 1)/2) in degrees, in [0, 180] (clamped, so rounding
/// never yields NaN; computed with atan2 for accuracy near 0 and 180°).
pub fn rotation_error_deg(estimate: &Pose, truth: &Pose) -> f64 {
    estimate.rotation_angle_to(truth).to_degrees()
}

/// The paper's translation error, the *squared* L2 distance ‖t̂ − t‖².
pub fn translation_error_sq(estimate: &Pose, truth: &Pose) -> f64 {
    estimate.translation.distance_squared(truth.translation)
}

/// The plain L2 translation error ‖t̂ − t‖.
pub fn translation_error(estimate: &Pose, truth: &Pose) -> f64 {
    estimate.translation.distance(truth.translation)
}

/// ADD (Hinterstoisser et al. 2012): mean distance between the model points moved by the
/// estimate and by the truth. Fails on an empty point set.
pub fn add(estimate: &Pose, truth: &Pose, model_points: &[Vec3]) -> Result<f64, GeometryError> {
    if model_points.is_empty() {
        return Err(GeometryError::Empty {
            what: "model points",
        });
    }
    let sum: f64 = model_points
        .iter()
        .map(|p| {
            estimate
                .apply(p.as_dvec3())
                .distance(truth.apply(p.as_dvec3()))
        })
        .sum();
    Ok(sum / model_points.len() as f64)
}

/// ADD-S: mean distance from each model point moved by the estimate to the *closest* model
/// point moved by the truth (for symmetric objects).
pub fn add_s(estimate: &Pose, truth: &Pose, model_points: &[Vec3]) -> Result<f64, GeometryError> {
    let moved_truth = truth.apply_all(model_points);
    let tree = KdTree::new(&moved_truth)?;
    let sum: f64 = estimate
        .apply_all(model_points)
        .iter()
        .map(|&p| tree.nearest(p).distance as f64)
        .sum();
    Ok(sum / model_points.len() as f64)
}

/// BOP's MSSD (Hodaň et al. 2020): the maximum distance between the model vertices moved by the
/// estimate and by the truth, minimised over the object's symmetry transformations
/// (`symmetries`, model frame; the identity is always included).
pub fn mssd(
    estimate: &Pose,
    truth: &Pose,
    vertices: &[Vec3],
    symmetries: &[Pose],
) -> Result<f64, GeometryError> {
    if vertices.is_empty() {
        return Err(GeometryError::Empty {
            what: "model vertices",
        });
    }
    let moved: Vec<DVec3> = vertices
        .iter()
        .map(|v| estimate.apply(v.as_dvec3()))
        .collect();
    Ok(with_identity(symmetries)
        .map(|s| {
            let t = truth.compose(&s);
            vertices
                .iter()
                .zip(&moved)
                .map(|(v, m)| m.distance(t.apply(v.as_dvec3())))
                .fold(0.0, f64::max)
        })
        .fold(f64::INFINITY, f64::min))
}

/// BOP's MSPD: the maximum distance in pixels between the projections of the model vertices
/// moved by the estimate and by the truth, minimised over the symmetries. Vertices behind the
/// camera under either pose count as infinitely far.
pub fn mspd(
    estimate: &Pose,
    truth: &Pose,
    vertices: &[Vec3],
    symmetries: &[Pose],
    intrinsics: &Intrinsics,
) -> Result<f64, GeometryError> {
    if vertices.is_empty() {
        return Err(GeometryError::Empty {
            what: "model vertices",
        });
    }
    let project = |pose: &Pose, v: &Vec3| intrinsics.project(pose.apply(v.as_dvec3()));
    let est: Vec<Option<(f64, f64)>> = vertices.iter().map(|v| project(estimate, v)).collect();
    Ok(with_identity(symmetries)
        .map(|s| {
            let t = truth.compose(&s);
            vertices
                .iter()
                .zip(&est)
                .map(|(v, e)| match (e, project(&t, v)) {
                    (Some((u0, v0)), Some((u1, v1))) => {
                        ((u0 - u1).powi(2) + (v0 - v1).powi(2)).sqrt()
                    }
                    _ => f64::INFINITY,
                })
                .fold(0.0, f64::max)
        })
        .fold(f64::INFINITY, f64::min))
}

fn with_identity(symmetries: &[Pose]) -> impl Iterator<Item = Pose> + '_ {
    std::iter::once(Pose::IDENTITY).chain(symmetries.iter().copied())
}

/// The diameter of a point set: the largest distance between two of its points (exact,
/// O(n²); pass mesh vertices or a few thousand samples).
pub fn diameter(points: &[Vec3]) -> f64 {
    let mut best = 0.0f64;
    for (i, a) in points.iter().enumerate() {
        for b in &points[i + 1..] {
            best = best.max(a.as_dvec3().distance(b.as_dvec3()));
        }
    }
    best
}

/// All errors of one estimate; `None` where the inputs for that error were not given.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseErrors {
    pub rotation_deg: f64,
    pub translation_sq: f64,
    pub translation: f64,
    pub add: Option<f64>,
    pub add_s: Option<f64>,
}

impl PoseErrors {
    /// Rotation and translation errors, plus ADD and ADD-S when model points are given.
    pub fn compute(
        estimate: &Pose,
        truth: &Pose,
        model_points: Option<&[Vec3]>,
    ) -> Result<Self, GeometryError> {
        Ok(PoseErrors {
            rotation_deg: rotation_error_deg(estimate, truth),
            translation_sq: translation_error_sq(estimate, truth),
            translation: translation_error(estimate, truth),
            add: model_points.map(|m| add(estimate, truth, m)).transpose()?,
            add_s: model_points
                .map(|m| add_s(estimate, truth, m))
                .transpose()?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> Vec<Vec3> {
        vec![
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
        ]
    }

    #[test]
    fn rotation_and_translation_errors_have_the_papers_definitions() {
        let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 2.0));
        let est = Pose::from_axis_angle(DVec3::Y, 30f64.to_radians(), DVec3::new(0.03, 0.0, 2.04));
        assert!((rotation_error_deg(&est, &truth) - 30.0).abs() < 1e-9);
        assert!((translation_error_sq(&est, &truth) - 0.0025).abs() < 1e-12);
        assert!((translation_error(&est, &truth) - 0.05).abs() < 1e-12);
        let flip = Pose::from_axis_angle(DVec3::X, std::f64::consts::PI, DVec3::ZERO);
        assert!((rotation_error_deg(&flip, &Pose::IDENTITY) - 180.0).abs() < 1e-9);
    }

    /// Hand-computed values: the identity, 90° about each axis (R̂ᵀR has trace 1, so
    /// arccos(0) = 90°), 180° about each axis and about a diagonal (trace −1), angles just
    /// below 180° (no NaN from rounding), symmetry of the error, and translations.
    #[test]
    fn errors_match_hand_computed_values() {
        use std::f64::consts::{FRAC_PI_2, PI};
        let t = DVec3::new(0.1, -0.2, 2.8);
        let truth = Pose::from_translation(t);
        assert_eq!(rotation_error_deg(&truth, &truth), 0.0);
        assert_eq!(translation_error_sq(&truth, &truth), 0.0);
        assert_eq!(translation_error(&truth, &truth), 0.0);
        let diag = DVec3::new(1.0, 1.0, 1.0).normalize();
        for axis in [DVec3::X, DVec3::Y, DVec3::Z, -DVec3::X, diag] {
            let quarter = Pose::from_axis_angle(axis, FRAC_PI_2, t);
            let e = rotation_error_deg(&quarter, &truth);
            assert!((e - 90.0).abs() < 1e-9, "{axis}: {e}");
            // The same error whichever pose is called the estimate.
            assert!((rotation_error_deg(&truth, &quarter) - e).abs() < 1e-12);
            // 90° about an axis and 90° back about it compose to 180° apart.
            let back = Pose::from_axis_angle(axis, -FRAC_PI_2, t);
            assert!((rotation_error_deg(&quarter, &back) - 180.0).abs() < 1e-9);
            // 180° about any axis is the largest error, whatever the axis (the ambiguity:
            // a half turn has two axis directions and the error must not depend on it).
            let half = Pose::from_axis_angle(axis, PI, t);
            let minus = Pose::from_axis_angle(-axis, PI, t);
            assert!((rotation_error_deg(&half, &truth) - 180.0).abs() < 1e-9);
            assert!(rotation_error_deg(&half, &minus) < 1e-6);
            for eps in [1e-9, 1e-6, 1e-3] {
                let near = Pose::from_axis_angle(axis, PI - eps, t);
                let e = rotation_error_deg(&near, &truth);
                assert!(
                    e.is_finite() && (e - (180.0 - eps.to_degrees())).abs() < 1e-6,
                    "{e}"
                );
            }
            // Errors never exceed 180°: 270° about an axis is 90° the other way.
            let big = Pose::from_axis_angle(axis, 1.5 * PI, t);
            assert!((rotation_error_deg(&big, &truth) - 90.0).abs() < 1e-9);
        }
        // The rotation error ignores translation and vice versa.
        let moved = Pose::from_axis_angle(DVec3::Z, FRAC_PI_2, t + DVec3::new(0.0, 0.0, 1.0));
        assert!((rotation_error_deg(&moved, &truth) - 90.0).abs() < 1e-9);
        assert!((translation_error(&moved, &truth) - 1.0).abs() < 1e-12);
        // Known translations: a 3-4-5 triangle, and the paper's 1e-2 threshold at 0.1.
        let est = Pose::from_translation(t + DVec3::new(0.3, 0.0, -0.4));
        assert!((translation_error(&est, &truth) - 0.5).abs() < 1e-12);
        assert!((translation_error_sq(&est, &truth) - 0.25).abs() < 1e-12);
        let est = Pose::from_translation(t + DVec3::new(0.0, 0.1, 0.0));
        assert!((translation_error_sq(&est, &truth) - 1e-2).abs() < 1e-15);
        let e = PoseErrors::compute(&est, &truth, None).unwrap();
        assert_eq!((e.rotation_deg, e.add, e.add_s), (0.0, None, None));
        assert!((e.translation - 0.1).abs() < 1e-12);
    }

    #[test]
    fn add_s_forgives_symmetry_that_add_punishes() {
        let pts = square();
        let quarter = Pose::from_axis_angle(DVec3::Z, std::f64::consts::FRAC_PI_2, DVec3::ZERO);
        assert!((add(&quarter, &Pose::IDENTITY, &pts).unwrap() - 2.0).abs() < 1e-6);
        assert!(add_s(&quarter, &Pose::IDENTITY, &pts).unwrap() < 1e-6);
        assert!(add(&Pose::IDENTITY, &Pose::IDENTITY, &[]).is_err());
    }

    #[test]
    fn mssd_and_mspd_use_the_symmetries() {
        let pts = square();
        let quarter = Pose::from_axis_angle(DVec3::Z, std::f64::consts::FRAC_PI_2, DVec3::ZERO);
        let at = Pose::from_translation(DVec3::new(0.0, 0.0, 10.0));
        let est = at.compose(&quarter);
        let d = mssd(&est, &at, &pts, &[]).unwrap();
        assert!((d - 2.0).abs() < 1e-6, "{d}");
        assert!(mssd(&est, &at, &pts, &[quarter]).unwrap() < 1e-6);
        let k = Intrinsics::new(100.0, 100.0, 50.0, 50.0, 100, 100).unwrap();
        let px = mspd(&est, &at, &pts, &[], &k).unwrap();
        assert!((px - 20.0).abs() < 1e-6, "{px}");
        assert!(mspd(&est, &at, &pts, &[quarter], &k).unwrap() < 1e-6);
        assert_eq!(diameter(&pts), 8f64.sqrt());
    }
}
