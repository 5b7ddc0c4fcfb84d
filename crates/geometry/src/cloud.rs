//! Point clouds: the container, voxel down-sampling and exact-count subsampling.

use glam::Vec3;

use crate::GeometryError;

/// Points with optional per-point normals and colours (same length as `points` when present).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub colors: Option<Vec<[u8; 3]>>,
}

impl PointCloud {
    /// A cloud of bare points.
    pub fn from_points(points: Vec<Vec3>) -> Self {
        PointCloud {
            points,
            normals: None,
            colors: None,
        }
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Checks that attribute arrays match the point count and that every point is finite.
    pub fn validate(&self) -> Result<(), GeometryError> {
        let n = self.points.len();
        if let Some(normals) = &self.normals {
            if normals.len() != n {
                return Err(GeometryError::LengthMismatch {
                    what: "normals vs points",
                    left: normals.len(),
                    right: n,
                });
            }
        }
        if let Some(colors) = &self.colors {
            if colors.len() != n {
                return Err(GeometryError::LengthMismatch {
                    what: "colours vs points",
                    left: colors.len(),
                    right: n,
                });
            }
        }
        check_finite("point cloud", &self.points)
    }

    /// Keeps the points at `indices` (with their attributes), in that order.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        PointCloud {
            points: indices.iter().map(|&i| self.points[i]).collect(),
            normals: self
                .normals
                .as_ref()
                .map(|n| indices.iter().map(|&i| n[i]).collect()),
            colors: self
                .colors
                .as_ref()
                .map(|c| indices.iter().map(|&i| c[i]).collect()),
        }
    }

    /// Appends another cloud; attributes are kept only when both clouds have them.
    pub fn extend(&mut self, other: &PointCloud) {
        self.points.extend_from_slice(&other.points);
        self.normals = match (self.normals.take(), &other.normals) {
            (Some(mut a), Some(b)) => {
                a.extend_from_slice(b);
                Some(a)
            }
            _ => None,
        };
        self.colors = match (self.colors.take(), &other.colors) {
            (Some(mut a), Some(b)) => {
                a.extend_from_slice(b);
                Some(a)
            }
            _ => None,
        };
    }
}

/// Fails with the index of the first non-finite point.
pub(crate) fn check_finite(what: &'static str, points: &[Vec3]) -> Result<(), GeometryError> {
    match points.iter().position(|p| !p.is_finite()) {
        Some(index) => Err(GeometryError::NonFinitePoint { what, index }),
        None => Ok(()),
    }
}

/// The integer voxel of a point on the grid of cell size `voxel_size` anchored at the origin:
/// voxel `(i, j, k)` covers `[i·s, (i+1)·s) × [j·s, (j+1)·s) × [k·s, (k+1)·s)`.
pub fn voxel_of(p: Vec3, voxel_size: f32) -> [i64; 3] {
    [
        (p.x / voxel_size).floor() as i64,
        (p.y / voxel_size).floor() as i64,
        (p.z / voxel_size).floor() as i64,
    ]
}

/// Voxel down-sampling: one point per occupied voxel, the centroid of the input points in it
/// (clamped to their bounding box so rounding can never move it into a neighbouring voxel).
///
/// Deterministic: the output is ordered by voxel index (x, then y, then z), independent of the
/// input order. Normals are averaged and re-normalised, colours averaged. Errors on a
/// non-positive or non-finite voxel size, or non-finite points.
pub fn voxel_downsample(cloud: &PointCloud, voxel_size: f32) -> Result<PointCloud, GeometryError> {
    if !(voxel_size > 0.0 && voxel_size.is_finite()) {
        return Err(GeometryError::InvalidParameter {
            name: "voxel_size",
            message: format!("{voxel_size} is not a positive finite size"),
        });
    }
    cloud.validate()?;
    let mut order: Vec<([i64; 3], u32)> = cloud
        .points
        .iter()
        .enumerate()
        .map(|(i, &p)| (voxel_of(p, voxel_size), i as u32))
        .collect();
    order.sort_unstable();
    let mut out = PointCloud {
        points: Vec::new(),
        normals: cloud.normals.as_ref().map(|_| Vec::new()),
        colors: cloud.colors.as_ref().map(|_| Vec::new()),
    };
    for group in order.chunk_by(|a, b| a.0 == b.0) {
        let (mut sum, mut lo, mut hi) = (glam::DVec3::ZERO, Vec3::INFINITY, Vec3::NEG_INFINITY);
        for &(_, i) in group {
            let p = cloud.points[i as usize];
            sum += p.as_dvec3();
            lo = lo.min(p);
            hi = hi.max(p);
        }
        out.points
            .push((sum / group.len() as f64).as_vec3().clamp(lo, hi));
        if let (Some(src), Some(dst)) = (&cloud.normals, out.normals.as_mut()) {
            let n: Vec3 = group.iter().map(|&(_, i)| src[i as usize]).sum();
            dst.push(n.normalize_or_zero());
        }
        if let (Some(src), Some(dst)) = (&cloud.colors, out.colors.as_mut()) {
            let mut acc = [0u32; 3];
            for &(_, i) in group {
                for c in 0..3 {
                    acc[c] += src[i as usize][c] as u32;
                }
            }
            let k = group.len() as u32;
            dst.push(acc.map(|a| ((a + k / 2) / k) as u8));
        }
    }
    Ok(out)
}

/// Voxel down-sampling of bare points (see [`voxel_downsample`]).
pub fn voxel_downsample_points(
    points: &[Vec3],
    voxel_size: f32,
) -> Result<Vec<Vec3>, GeometryError> {
    // Copies the points once into a cloud; callers that already hold a cloud use the other form.
    Ok(voxel_downsample(&PointCloud::from_points(points.to_vec()), voxel_size)?.points)
}

/// Indices of exactly `count` points drawn at random, as the paper samples M model and N
/// observed points.
///
/// - `len ≥ count`: `count` distinct indices, uniformly without replacement (partial
///   Fisher–Yates), in random order.
/// - `0 < len < count`: every index once, then random repeats (with replacement) to fill up,
///   shuffled — the network still sees exactly `count` points and duplicates carry no new
///   information.
/// - `len == 0` and `count > 0`: an error.
pub fn random_subsample_indices<R: rand::Rng + ?Sized>(
    len: usize,
    count: usize,
    rng: &mut R,
) -> Result<Vec<usize>, GeometryError> {
    use rand::seq::SliceRandom;
    if count == 0 {
        return Ok(Vec::new());
    }
    if len == 0 {
        return Err(GeometryError::Empty {
            what: "points to subsample",
        });
    }
    let mut idx: Vec<usize> = (0..len).collect();
    if len >= count {
        let (chosen, _) = idx.partial_shuffle(rng, count);
        return Ok(chosen.to_vec());
    }
    idx.extend((len..count).map(|_| rng.random_range(0..len)));
    idx.shuffle(rng);
    Ok(idx)
}

/// Exactly `count` points of `cloud` drawn at random; see [`random_subsample_indices`].
pub fn random_subsample<R: rand::Rng + ?Sized>(
    cloud: &PointCloud,
    count: usize,
    rng: &mut R,
) -> Result<PointCloud, GeometryError> {
    Ok(cloud.select(&random_subsample_indices(cloud.len(), count, rng)?))
}

/// Unit normals estimated by PCA over each point's `k` nearest neighbours (the eigenvector of
/// the smallest covariance eigenvalue), oriented towards `viewpoint` (e.g. the camera origin
/// for back-projected depth). Points with fewer than 3 neighbours get a zero normal.
pub fn estimate_normals(
    points: &[Vec3],
    k: usize,
    viewpoint: Vec3,
) -> Result<Vec<Vec3>, GeometryError> {
    use rayon::prelude::*;
    let tree = crate::KdTree::new(points)?;
    Ok(points
        .par_iter()
        .map(|&p| {
            let nb = tree.k_nearest(p, k.max(3));
            if nb.len() < 3 {
                return Vec3::ZERO;
            }
            let mean = nb
                .iter()
                .map(|n| points[n.index].as_dvec3())
                .sum::<glam::DVec3>()
                / nb.len() as f64;
            let mut c = [[0.0f64; 3]; 3];
            for n in &nb {
                let d = (points[n.index].as_dvec3() - mean).to_array();
                for r in 0..3 {
                    for s in 0..3 {
                        c[r][s] += d[r] * d[s];
                    }
                }
            }
            let normal = smallest_eigenvector(&c);
            let flip = if normal.dot((viewpoint - p).as_dvec3()) < 0.0 {
                -1.0
            } else {
                1.0
            };
            (normal * flip).as_vec3()
        })
        .collect())
}

/// The principal axes of `points` (any frame): unit vectors, largest variance first, with
/// the variance along each. `None` for an empty set or a non-finite point.
pub fn principal_axes(points: &[Vec3]) -> Option<([glam::DVec3; 3], [f64; 3])> {
    if points.is_empty() || points.iter().any(|p| !p.is_finite()) {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().map(|p| p.as_dvec3()).sum::<glam::DVec3>() / n;
    let mut c = [[0.0f64; 3]; 3];
    for p in points {
        let d = p.as_dvec3() - mean;
        let d = [d.x, d.y, d.z];
        for r in 0..3 {
            for s in 0..3 {
                c[r][s] += d[r] * d[s] / n;
            }
        }
    }
    let m = faer::Mat::<f64>::from_fn(3, 3, |r, s| c[r][s]);
    let eig = m.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (u, values) = (eig.U(), eig.S());
    // faer sorts the eigenvalues in ascending order.
    let axis = |k: usize| glam::DVec3::new(u[(0, k)], u[(1, k)], u[(2, k)]).normalize_or_zero();
    let value = |k: usize| values[k].max(0.0);
    Some(([axis(2), axis(1), axis(0)], [value(2), value(1), value(0)]))
}

/// The unit eigenvector of the smallest eigenvalue of a symmetric 3×3 matrix (faer).
fn smallest_eigenvector(c: &[[f64; 3]; 3]) -> glam::DVec3 {
    let m = faer::Mat::<f64>::from_fn(3, 3, |r, s| c[r][s]);
    match m.self_adjoint_eigen(faer::Side::Lower) {
        Ok(eig) => {
            let u = eig.U();
            glam::DVec3::new(u[(0, 0)], u[(1, 0)], u[(2, 0)]).normalize_or_zero()
        }
        Err(_) => glam::DVec3::ZERO,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::SeedableRng;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn voxel_output_has_one_point_per_voxel_and_covers_every_input(
            pts in prop::collection::vec((-3.0f32..3.0, -3.0f32..3.0, -3.0f32..3.0), 1..400),
            size in 0.01f32..1.0,
        ) {
            let points: Vec<Vec3> = pts.iter().map(|&(x, y, z)| Vec3::new(x, y, z)).collect();
            let out = voxel_downsample_points(&points, size).unwrap();
            let out_voxels: Vec<[i64; 3]> = out.iter().map(|&p| voxel_of(p, size)).collect();
            let unique: std::collections::BTreeSet<_> = out_voxels.iter().copied().collect();
            prop_assert_eq!(unique.len(), out.len(), "two output points share a voxel");
            for &p in &points {
                prop_assert!(unique.contains(&voxel_of(p, size)), "input point {} has no output voxel", p);
            }
            prop_assert_eq!(unique.len(), points.iter().map(|&p| voxel_of(p, size)).collect::<std::collections::BTreeSet<_>>().len());
        }
    }

    #[test]
    fn principal_axes_of_a_stretched_box_are_its_sides_largest_first() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let points: Vec<Vec3> = (0..2000)
            .map(|_| {
                use rand::Rng;
                Vec3::new(
                    rng.random_range(-0.2..0.2),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-1.0..1.0),
                )
            })
            .collect();
        let (axes, var) = principal_axes(&points).unwrap();
        assert!(axes[0].y.abs() > 0.99 && axes[1].z.abs() > 0.99 && axes[2].x.abs() > 0.99);
        assert!(var[0] > var[1] && var[1] > var[2]);
        // Uniform on [-a, a]: variance a²/3.
        assert!((var[0] - 3.0).abs() < 0.3, "{var:?}");
        assert!(principal_axes(&[]).is_none());
    }

    #[test]
    fn voxel_downsample_is_independent_of_input_order_and_averages_attributes() {
        let cloud = PointCloud {
            points: vec![
                Vec3::new(0.1, 0.1, 0.1),
                Vec3::new(0.3, 0.3, 0.3),
                Vec3::new(1.5, 0.0, 0.0),
            ],
            normals: Some(vec![Vec3::X, Vec3::Y, Vec3::Z]),
            colors: Some(vec![[0, 0, 0], [255, 100, 2], [9, 9, 9]]),
        };
        let a = voxel_downsample(&cloud, 1.0).unwrap();
        let b = voxel_downsample(&cloud.select(&[2, 1, 0]), 1.0).unwrap();
        assert_eq!(a, b);
        assert_eq!(
            a.points,
            vec![Vec3::new(0.2, 0.2, 0.2), Vec3::new(1.5, 0.0, 0.0)]
        );
        assert!(
            a.normals.as_ref().unwrap()[0].abs_diff_eq(Vec3::new(1.0, 1.0, 0.0).normalize(), 1e-6)
        );
        assert_eq!(a.colors.as_ref().unwrap()[0], [128, 50, 1]);
        assert!(voxel_downsample(&cloud, 0.0).is_err());
        assert!(voxel_downsample(&cloud, f32::NAN).is_err());
    }

    #[test]
    fn subsample_gives_exact_counts_and_documented_shortfall_behaviour() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let idx = random_subsample_indices(100, 40, &mut rng).unwrap();
        assert_eq!(idx.len(), 40);
        assert_eq!(
            idx.iter().collect::<std::collections::HashSet<_>>().len(),
            40,
            "without replacement"
        );
        let short = random_subsample_indices(5, 12, &mut rng).unwrap();
        assert_eq!(short.len(), 12);
        for i in 0..5 {
            assert!(short.contains(&i), "every point is used before any repeats");
        }
        assert!(random_subsample_indices(0, 3, &mut rng).is_err());
        assert!(random_subsample_indices(0, 0, &mut rng).unwrap().is_empty());
        let mut a = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut b = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        assert_eq!(
            random_subsample_indices(1000, 768, &mut a).unwrap(),
            random_subsample_indices(1000, 768, &mut b).unwrap()
        );
    }

    #[test]
    fn normals_of_a_plane_point_to_the_viewpoint() {
        let points: Vec<Vec3> = (0..400)
            .map(|i| Vec3::new((i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1, 2.0))
            .collect();
        let normals = estimate_normals(&points, 10, Vec3::ZERO).unwrap();
        for n in normals {
            assert!(n.abs_diff_eq(Vec3::new(0.0, 0.0, -1.0), 1e-5), "{n}");
        }
    }
}
