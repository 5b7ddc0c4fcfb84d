//! A geometry-only segmentation, for comparison and for tabletop scenes: RANSAC plane
//! removal, then Euclidean clustering, keeping the cluster whose size is nearest the model's.
//!
//! Planes: up to `max_planes` times, fit a plane to the remaining valid pixels by RANSAC
//! (3-point hypotheses scored on a random subset, the best refitted by least squares on its
//! inliers) and remove its inliers, stopping when the best plane holds less than
//! `min_plane_fraction` of all the valid pixels. Clusters: Euclidean clustering on the organised
//! cloud (neighbouring pixels join when their 3-D distance is below `cluster_tolerance`),
//! which for a depth map is what PCL's organised Euclidean clustering computes. The cluster
//! whose extent (bounding-box diagonal) is nearest the model's diameter on a log scale wins.
//! Lengths are normalised object units, multiplied by the object scale given to
//! [`segment_geometric`].

use glam::DVec3;
use ic_geometry::{DepthImage, Intrinsics, Mask};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::post::flood_fill8;
use crate::{Result, SegError};

/// Settings of [`segment_geometric`] (lengths in normalised object units).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeometricConfig {
    pub max_planes: usize,
    /// A point within this distance of a plane belongs to it.
    pub plane_threshold: f64,
    /// Stop removing planes when the best one holds less than this fraction of all the valid
    /// pixels (so an object's flat face, smaller than that, is kept).
    pub min_plane_fraction: f64,
    pub ransac_iterations: usize,
    /// Points scored per hypothesis.
    pub ransac_subset: usize,
    pub cluster_tolerance: f64,
    /// Clusters with fewer pixels are ignored.
    pub min_cluster_pixels: usize,
    pub seed: u64,
}

impl Default for GeometricConfig {
    fn default() -> Self {
        GeometricConfig {
            max_planes: 6,
            plane_threshold: 0.05,
            min_plane_fraction: 0.05,
            ransac_iterations: 200,
            ransac_subset: 4000,
            cluster_tolerance: 0.05,
            min_cluster_pixels: 30,
            seed: 0,
        }
    }
}

/// What [`segment_geometric`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct GeometricSegmentation {
    pub mask: Mask,
    /// The chosen cluster's bounding-box diagonal (camera units).
    pub extent: f64,
    /// Planes removed and clusters considered.
    pub planes: usize,
    pub clusters: usize,
}

fn plane_from(a: DVec3, b: DVec3, c: DVec3) -> Option<(DVec3, f64)> {
    let n = (b - a).cross(c - a);
    let len = n.length();
    (len > 1e-12).then(|| {
        let n = n / len;
        (n, -n.dot(a))
    })
}

/// Least-squares plane through `points` (smallest-eigenvalue direction of the covariance).
pub(crate) fn refit(points: &[DVec3]) -> Option<(DVec3, f64)> {
    if points.len() < 3 {
        return None;
    }
    let c = points.iter().fold(DVec3::ZERO, |a, p| a + *p) / points.len() as f64;
    let mut cov = [[0f64; 3]; 3];
    for p in points {
        let d = (*p - c).to_array();
        for (r, row) in cov.iter_mut().enumerate() {
            for (k, v) in row.iter_mut().enumerate() {
                *v += d[r] * d[k];
            }
        }
    }
    let m = faer::Mat::from_fn(3, 3, |r, k| cov[r][k]);
    let eig = m.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let u = eig.U();
    let n = DVec3::new(u[(0, 0)], u[(1, 0)], u[(2, 0)]).normalize_or_zero();
    (n != DVec3::ZERO).then(|| (n, -n.dot(c)))
}

/// Segments `depth` without a network; see the module doc. `model_diameter` and
/// `object_scale` are in the depth map's units (`object_scale` = the model's normalisation
/// scale; 1 for normalised units).
///
/// Errors: the depth map does not fit the camera, has no valid pixel, or no cluster is left
/// ([`SegError::ObjectNotFound`]).
pub fn segment_geometric(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    model_diameter: f64,
    object_scale: f64,
    cfg: &GeometricConfig,
) -> Result<GeometricSegmentation> {
    intrinsics.check_image(depth)?;
    if !(model_diameter > 0.0 && object_scale > 0.0) {
        return Err(SegError::Input(
            "model diameter and object scale must be positive".into(),
        ));
    }
    let (w, h) = (depth.width as usize, depth.height as usize);
    let mut points: Vec<Option<DVec3>> = depth
        .data
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            (z.is_finite() && z > 0.0)
                .then(|| intrinsics.back_project((i % w) as f64, (i / w) as f64, z as f64))
        })
        .collect();
    if points.iter().all(|p| p.is_none()) {
        return Err(SegError::Input(
            "the depth map has no valid pixel (all zero, NaN or infinite)".into(),
        ));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let threshold = cfg.plane_threshold * object_scale;
    let mut planes = 0;
    let total = points.iter().filter(|p| p.is_some()).count();
    for _ in 0..cfg.max_planes {
        let alive: Vec<usize> = (0..w * h).filter(|&i| points[i].is_some()).collect();
        if alive.len() < 3 {
            break;
        }
        let subset: Vec<DVec3> = (0..cfg.ransac_subset.min(alive.len()))
            .map(|_| points[alive[rng.random_range(0..alive.len())]].unwrap())
            .collect();
        let mut best: Option<((DVec3, f64), usize)> = None;
        for _ in 0..cfg.ransac_iterations {
            let pick = |r: &mut ChaCha8Rng| points[alive[r.random_range(0..alive.len())]].unwrap();
            let (a, b, c) = (pick(&mut rng), pick(&mut rng), pick(&mut rng));
            let Some((n, d)) = plane_from(a, b, c) else {
                continue;
            };
            let count = subset
                .iter()
                .filter(|p| (n.dot(**p) + d).abs() < threshold)
                .count();
            if best.is_none_or(|(_, c)| count > c) {
                best = Some(((n, d), count));
            }
        }
        let Some(((n, d), count)) = best else { break };
        let estimated = count as f64 / subset.len() as f64 * alive.len() as f64;
        if estimated < cfg.min_plane_fraction * total as f64 {
            break;
        }
        let inliers: Vec<DVec3> = subset
            .iter()
            .copied()
            .filter(|p| (n.dot(*p) + d).abs() < threshold)
            .collect();
        let (n, d) = refit(&inliers).unwrap_or((n, d));
        for p in points.iter_mut() {
            if p.is_some_and(|q| (n.dot(q) + d).abs() < threshold) {
                *p = None;
            }
        }
        planes += 1;
    }
    // Organised Euclidean clustering: components of the graph joining 8-neighbours closer
    // than the tolerance.
    let tol2 = (cfg.cluster_tolerance * object_scale).powi(2);
    let mut label = vec![usize::MAX; w * h];
    let mut clusters: Vec<Vec<usize>> = Vec::new();
    for start in 0..w * h {
        if points[start].is_none() || label[start] != usize::MAX {
            continue;
        }
        let id = clusters.len();
        label[start] = id;
        let members = flood_fill8(w, h, vec![start], |i, j| {
            let admit = label[j] == usize::MAX
                && points[j].is_some_and(|q| (q - points[i].unwrap()).length_squared() < tol2);
            if admit {
                label[j] = id;
            }
            admit
        });
        clusters.push(members);
    }
    let considered: Vec<(f64, &Vec<usize>)> = clusters
        .iter()
        .filter(|c| c.len() >= cfg.min_cluster_pixels.max(1))
        .map(|c| {
            let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            for &i in c.iter() {
                let p = points[i].unwrap();
                lo = lo.min(p);
                hi = hi.max(p);
            }
            ((hi - lo).length(), c)
        })
        .collect();
    let best = considered.iter().min_by(|a, b| {
        let da = (a.0 / model_diameter).ln().abs();
        let db = (b.0 / model_diameter).ln().abs();
        da.total_cmp(&db)
    });
    let Some((extent, members)) = best else {
        return Err(SegError::ObjectNotFound {
            threshold: 0.0,
            best_score: None,
        });
    };
    let mut mask = Mask::filled(depth.width, depth.height, false);
    for &i in members.iter() {
        mask.data[i] = true;
    }
    Ok(GeometricSegmentation {
        mask,
        extent: *extent,
        planes,
        clusters: considered.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor plane z = 5 (camera looking straight at it) with a box standing out of it.
    #[test]
    fn finds_a_box_in_front_of_a_plane() {
        // fx = 200: neighbouring pixels are 0.02–0.025 apart, under the 0.05 tolerance.
        let k = Intrinsics::new(200.0, 200.0, 39.5, 29.5, 80, 60).unwrap();
        let mut depth = DepthImage::filled(80, 60, 5.0);
        for v in 20..35 {
            for u in 30..45 {
                depth.data[v * 80 + u] = 4.0;
            }
        }
        let cfg = GeometricConfig {
            min_cluster_pixels: 10,
            ..GeometricConfig::default()
        };
        // The box face is 15 px = 0.3 units wide at depth 4: diameter ≈ 0.42.
        let seg = segment_geometric(&depth, &k, 0.42, 1.0, &cfg).unwrap();
        assert_eq!(seg.planes, 1);
        let expected: Vec<bool> = (0..80 * 60)
            .map(|i| (20..35).contains(&(i / 80)) && (30..45).contains(&(i % 80)))
            .collect();
        assert_eq!(seg.mask.data, expected);
    }

    #[test]
    fn nothing_but_a_plane_is_object_not_found() {
        let k = Intrinsics::new(50.0, 50.0, 39.5, 29.5, 80, 60).unwrap();
        let depth = DepthImage::filled(80, 60, 5.0);
        let r = segment_geometric(&depth, &k, 1.0, 1.0, &GeometricConfig::default());
        assert!(matches!(r, Err(SegError::ObjectNotFound { .. })));
    }
}
