//! Weighted Procrustes (Kabsch–Umeyama without scale) through faer's SVD.
//!
//! Given correspondences `model_points[i] ↔ observed_points[i]` with weights `w_i ≥ 0`, finds
//! the rigid pose minimising `Σ w_i ‖R·x_i + t − y_i‖²` (Umeyama 1991, §II; the reflection fix
//! `diag(1, 1, sign det(V·Uᵀ))` keeps `R` a proper rotation).

use faer::Mat;
use glam::{DMat3, DVec3, Vec3};

use crate::cloud::check_finite;
use crate::{GeometryError, Pose};

/// Relative size of the second singular value of the cross-covariance below which the
/// correspondences are considered collinear (rotation about the line undetermined).
const RANK_TOLERANCE: f64 = 1e-10;

/// The rigid pose that best maps `model_points` onto `observed_points` (pairs by index).
///
/// `weights` (optional, one per pair, each finite and ≥ 0) scale each pair's squared error.
/// Errors: lengths differ, a non-finite point or weight, fewer than 3 pairs with positive
/// weight, zero total weight, or degenerate (collinear/coincident) correspondences.
pub fn procrustes(
    model_points: &[Vec3],
    observed_points: &[Vec3],
    weights: Option<&[f32]>,
) -> Result<Pose, GeometryError> {
    let n = model_points.len();
    if observed_points.len() != n {
        return Err(GeometryError::LengthMismatch {
            what: "model vs observed points",
            left: n,
            right: observed_points.len(),
        });
    }
    check_finite("model points", model_points)?;
    check_finite("observed points", observed_points)?;
    if let Some(w) = weights {
        if w.len() != n {
            return Err(GeometryError::LengthMismatch {
                what: "weights vs points",
                left: w.len(),
                right: n,
            });
        }
        if let Some(index) = w.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(GeometryError::InvalidWeight {
                index,
                value: w[index] as f64,
            });
        }
    }
    let weight = |i: usize| weights.map_or(1.0, |w| w[i] as f64);
    let positive = (0..n).filter(|&i| weight(i) > 0.0).count();
    if positive < 3 {
        return Err(GeometryError::TooFewCorrespondences {
            needed: 3,
            got: positive,
        });
    }
    let total: f64 = (0..n).map(weight).sum();
    if !(total > 0.0 && total.is_finite()) {
        return Err(GeometryError::ZeroWeight);
    }

    let (mut mx, mut my) = (DVec3::ZERO, DVec3::ZERO);
    for i in 0..n {
        mx += weight(i) * model_points[i].as_dvec3();
        my += weight(i) * observed_points[i].as_dvec3();
    }
    mx /= total;
    my /= total;

    // Cross-covariance H = Σ w (x − x̄)(y − ȳ)ᵀ.
    let mut h = [[0.0f64; 3]; 3];
    for i in 0..n {
        let w = weight(i);
        if w == 0.0 {
            continue;
        }
        let (x, y) = (
            model_points[i].as_dvec3() - mx,
            observed_points[i].as_dvec3() - my,
        );
        let (x, y) = (x.to_array(), y.to_array());
        for r in 0..3 {
            for c in 0..3 {
                h[r][c] += w * x[r] * y[c];
            }
        }
    }
    let rotation = rotation_from_cross_covariance(&h)?;
    Ok(Pose::new(rotation, my - rotation * mx))
}

/// The rotation `R = V·diag(1, 1, d)·Uᵀ` from the SVD `H = U·S·Vᵀ` of a 3×3 cross-covariance.
fn rotation_from_cross_covariance(h: &[[f64; 3]; 3]) -> Result<DMat3, GeometryError> {
    let hm = Mat::<f64>::from_fn(3, 3, |r, c| h[r][c]);
    let svd = hm.svd().map_err(|e| GeometryError::InvalidParameter {
        name: "procrustes",
        message: format!("SVD did not converge: {e:?}"),
    })?;
    let s = svd.S().column_vector();
    let (s0, s1) = (s[0], s[1]);
    if !(s0 > 0.0) || s1 <= RANK_TOLERANCE * s0 {
        let rank = usize::from(s0 > 0.0) + usize::from(s1 > RANK_TOLERANCE * s0);
        return Err(GeometryError::DegenerateCorrespondences { rank });
    }
    let (u, v) = (svd.U(), svd.V());
    let to_glam = |m: faer::MatRef<'_, f64>| {
        DMat3::from_cols(
            DVec3::new(m[(0, 0)], m[(1, 0)], m[(2, 0)]),
            DVec3::new(m[(0, 1)], m[(1, 1)], m[(2, 1)]),
            DVec3::new(m[(0, 2)], m[(1, 2)], m[(2, 2)]),
        )
    };
    let (u, v) = (to_glam(u), to_glam(v));
    let d = (v * u.transpose()).determinant().signum();
    let fix = DMat3::from_diagonal(DVec3::new(1.0, 1.0, if d < 0.0 { -1.0 } else { 1.0 }));
    Ok(v * fix * u.transpose())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    fn cloud(n: usize, seed: u64) -> Vec<Vec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                Vec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                )
            })
            .collect()
    }

    fn pose_strategy() -> impl Strategy<Value = Pose> {
        (
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            0.0f64..std::f64::consts::PI,
            (-5.0f64..5.0, -5.0f64..5.0, -5.0f64..5.0),
        )
            .prop_map(|(a, angle, t)| {
                Pose::from_axis_angle(
                    DVec3::new(a.0, a.1, a.2 + 1e-3),
                    angle,
                    DVec3::new(t.0, t.1, t.2),
                )
            })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn recovers_random_poses_from_exact_correspondences(truth in pose_strategy(), seed in 0u64..1000) {
            let x = cloud(50, seed);
            let y = truth.apply_all(&x);
            let est = procrustes(&x, &y, None).unwrap();
            prop_assert!(est.rotation_angle_to(&truth) < 1e-6);
            prop_assert!(est.translation.distance(truth.translation) < 1e-5);
        }

        #[test]
        fn recovers_random_poses_with_30_percent_outliers_when_weighted(truth in pose_strategy(), seed in 0u64..1000) {
            let n = 100;
            let x = cloud(n, seed);
            let mut y = truth.apply_all(&x);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed + 7);
            let mut w = vec![1.0f32; n];
            for i in 0..30 {
                y[i] = Vec3::new(rng.random_range(-9.0..9.0), rng.random_range(-9.0..9.0), rng.random_range(-9.0..9.0));
                w[i] = 0.0;
            }
            let est = procrustes(&x, &y, Some(&w)).unwrap();
            prop_assert!(est.rotation_angle_to(&truth) < 1e-6);
            // Unweighted, the outliers must pull it off: the weights are doing the work.
            let bad = procrustes(&x, &y, None).unwrap();
            prop_assert!(bad.rotation_angle_to(&truth) > 1e-3);
        }
    }

    #[test]
    fn planar_points_give_a_rotation_not_a_reflection() {
        // Coplanar points are the classic case where the plain SVD solution is a reflection.
        let x = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
        ];
        let truth = Pose::from_axis_angle(DVec3::X, 3.0, DVec3::new(0.0, 0.0, 1.0));
        let est = procrustes(&x, &truth.apply_all(&x), None).unwrap();
        assert!((est.rotation.determinant() - 1.0).abs() < 1e-9);
        assert!(est.rotation_angle_to(&truth) < 1e-6);
    }

    #[test]
    fn degenerate_inputs_are_typed_errors() {
        let x = cloud(3, 0);
        assert_eq!(
            procrustes(&x[..2], &x[..2], None),
            Err(GeometryError::TooFewCorrespondences { needed: 3, got: 2 })
        );
        assert_eq!(
            procrustes(&x, &x[..2], None).unwrap_err(),
            GeometryError::LengthMismatch {
                what: "model vs observed points",
                left: 3,
                right: 2
            }
        );
        let line = vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0, Vec3::X * 3.0];
        assert!(matches!(
            procrustes(&line, &line, None),
            Err(GeometryError::DegenerateCorrespondences { .. })
        ));
        let same = vec![Vec3::ONE; 5];
        assert!(matches!(
            procrustes(&same, &same, None),
            Err(GeometryError::DegenerateCorrespondences { rank: 0 })
        ));
        assert_eq!(
            procrustes(&x, &x, Some(&[1.0, 1.0, 0.0])),
            Err(GeometryError::TooFewCorrespondences { needed: 3, got: 2 })
        );
        assert!(matches!(
            procrustes(&x, &x, Some(&[1.0, -1.0, 1.0])),
            Err(GeometryError::InvalidWeight { index: 1, .. })
        ));
        let mut nan = x.clone();
        nan[2].y = f32::NAN;
        assert!(matches!(
            procrustes(&nan, &x, None),
            Err(GeometryError::NonFinitePoint { index: 2, .. })
        ));
    }
}
