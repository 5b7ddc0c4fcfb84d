//! Pose recovery from the network's correspondences: weighted Procrustes, optional ICP.

use glam::Vec3;
use ic_geometry::{IcpMethod, IcpOptions, IcpTarget, Pose, estimate_normals, procrustes};
use serde::{Deserialize, Serialize};

use crate::network::Match;
use crate::{PoseError, Result};

/// Optional refinement after the one-shot estimate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Refine {
    None,
    /// Point-to-plane ICP of the observed points onto the model points (normals estimated by
    /// PCA over the model points), then inverted.
    Icp,
}

/// How correspondences become a pose.
///
/// Defaults measured on 100 validation views (objects 750–799, softmax head after 400
/// iterations of the `cpu` preset): probability-weighted Procrustes beats unweighted (rotation
/// acc@15° 0.57 vs 0.47), a probability floor of 0.05 changes nothing measurable, and ICP
/// refinement lifts acc@15° from 0.57 to 0.83 (median error 13.1° → 1.1°) for +15 ms per
/// case — so ICP is on by default.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RecoveryOptions {
    /// Matches below this probability are dropped (if fewer than 3 remain, or they are
    /// degenerate for Procrustes, the 16 most probable matches are used regardless, then all).
    pub min_probability: f32,
    /// Weight each pair by its probability in Procrustes.
    pub weighted: bool,
    pub refine: Refine,
    /// ICP correspondence distance (normalised units) and iterations.
    pub icp_max_distance: f32,
    pub icp_iterations: usize,
}

impl Default for RecoveryOptions {
    fn default() -> Self {
        RecoveryOptions {
            min_probability: 0.0,
            weighted: true,
            refine: Refine::Icp,
            icp_max_distance: 0.1,
            icp_iterations: 30,
        }
    }
}

/// A recovered pose and what it rests on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Recovered {
    pub pose: Pose,
    /// Correspondences used by Procrustes.
    pub inlier_count: usize,
    /// Mean probability of those correspondences.
    pub assignment_confidence: f32,
}

/// Model → camera pose from the arg-max matches of one pair.
pub fn recover_pose(
    model: &[Vec3],
    observed: &[Vec3],
    matches: &[Match],
    options: &RecoveryOptions,
) -> Result<Recovered> {
    // Candidate correspondence sets, tried in order until one gives a non-degenerate
    // Procrustes: the matches kept by the bins and the probability floor; the 16 most probable
    // matches regardless of both (the OT head can send all but a few collinear or coincident
    // points to the bins); every match.
    let kept: Vec<&Match> = matches
        .iter()
        .filter(|m| !m.outlier && m.probability >= options.min_probability)
        .collect();
    let mut by_probability: Vec<&Match> = matches.iter().collect();
    by_probability.sort_by(|a, b| b.probability.total_cmp(&a.probability));
    let top: Vec<&Match> = by_probability.iter().take(16).copied().collect();
    let candidates = [kept, top, by_probability];
    let mut first_error = None;
    for set in candidates.iter().filter(|c| c.len() >= 3) {
        let xs: Vec<Vec3> = set.iter().map(|m| model[m.model as usize]).collect();
        let ys: Vec<Vec3> = set.iter().map(|m| observed[m.observed as usize]).collect();
        let ws: Vec<f32> = set.iter().map(|m| m.probability.max(1e-12)).collect();
        let pose = match procrustes(&xs, &ys, options.weighted.then_some(&ws[..])) {
            Ok(p) => p,
            Err(e) => {
                first_error.get_or_insert(e);
                continue;
            }
        };
        let pose = if options.refine == Refine::Icp {
            refine_icp(model, observed, &pose, options)?
        } else {
            pose
        };
        return Ok(Recovered {
            pose,
            inlier_count: set.len(),
            assignment_confidence: ws.iter().sum::<f32>() / ws.len() as f32,
        });
    }
    Err(match first_error {
        Some(e) => e.into(),
        None => PoseError::TooFewPoints {
            what: "correspondences",
            got: matches.len(),
            needed: 3,
        },
    })
}

/// Point-to-plane ICP of `observed` onto `model` starting from `initial⁻¹`, inverted back.
pub fn refine_icp(
    model: &[Vec3],
    observed: &[Vec3],
    initial: &Pose,
    options: &RecoveryOptions,
) -> Result<Pose> {
    let centre = model.iter().copied().sum::<Vec3>() / model.len() as f32;
    let normals = estimate_normals(model, 10, centre + Vec3::splat(100.0))?;
    let target = IcpTarget::new(model, Some(&normals))?;
    let icp = IcpOptions {
        method: IcpMethod::PointToPlane,
        max_correspondence_distance: options.icp_max_distance,
        max_iterations: options.icp_iterations,
        ..Default::default()
    };
    let result = target.register(observed, &initial.inverse(), &icp)?;
    Ok(result.pose.inverse())
}

/// Settings of [`sample_poses`]: RANSAC over the network's soft assignment (PROSAC-style
/// draws in proportion to the match probabilities).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SamplingOptions {
    /// Minimal sets of three matches drawn.
    pub draws: usize,
    /// Distinct poses kept, most supported first.
    pub keep: usize,
    /// A match supports a pose when the moved model point lies within this distance of its
    /// observed point (normalised units); the three matches of a set must also agree on
    /// their pairwise distances within it.
    pub inlier_distance: f32,
    /// Poses supported by fewer matches are rejected.
    pub min_inliers: usize,
}

impl Default for SamplingOptions {
    fn default() -> Self {
        SamplingOptions {
            draws: 256,
            keep: 2,
            inlier_distance: 0.1,
            min_inliers: 8,
        }
    }
}

/// A pose of [`sample_poses`] and the matches that support it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampledPose {
    /// Model → camera (the frames of `model` and `observed`).
    pub pose: Pose,
    pub inliers: usize,
}

/// Pose hypotheses from the arg-max matches of one pair: `options.draws` minimal sets of three
/// matches (not sent to the outlier bin), each match drawn with probability proportional to
/// its assignment probability (seeded, so the same seed gives the same poses); sets whose
/// pairwise distances disagree between model and observation, or that are nearly collinear,
/// are rejected before any fit. Each surviving set's rigid fit is scored by the matches it
/// explains; the best `options.keep` distinct poses (more than 10° or 0.1 apart), refitted by
/// weighted Procrustes on their supporting matches, are returned, most supported first. Empty
/// when fewer than three matches remain or nothing reaches `options.min_inliers`.
pub fn sample_poses(
    model: &[Vec3],
    observed: &[Vec3],
    matches: &[Match],
    options: &SamplingOptions,
    seed: u64,
) -> Vec<SampledPose> {
    use rand::{Rng, SeedableRng};
    let usable: Vec<&Match> = matches
        .iter()
        .filter(|m| !m.outlier && m.probability.is_finite() && m.probability > 0.0)
        .collect();
    if usable.len() < 3 || options.draws == 0 || options.keep == 0 {
        return Vec::new();
    }
    let pair = |m: &Match| (model[m.model as usize], observed[m.observed as usize]);
    let mut cumulative = Vec::with_capacity(usable.len());
    let mut total = 0.0f64;
    for m in &usable {
        total += m.probability as f64;
        cumulative.push(total);
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let draw = |rng: &mut rand_chacha::ChaCha8Rng| -> usize {
        let u = rng.random::<f64>() * total;
        cumulative
            .partition_point(|&c| c <= u)
            .min(usable.len() - 1)
    };
    let tol = options.inlier_distance;
    let tol2 = tol * tol;
    let support = |pose: &Pose| -> Vec<usize> {
        (0..usable.len())
            .filter(|&i| {
                let (x, y) = pair(usable[i]);
                pose.apply_f32(x).distance_squared(y) <= tol2
            })
            .collect()
    };
    let mut found: Vec<(usize, Pose)> = Vec::new();
    for _ in 0..options.draws {
        let a = draw(&mut rng);
        let b = draw(&mut rng);
        let c = draw(&mut rng);
        if a == b || b == c || a == c {
            continue;
        }
        let (xa, ya) = pair(usable[a]);
        let (xb, yb) = pair(usable[b]);
        let (xc, yc) = pair(usable[c]);
        let agree = |x0: Vec3, x1: Vec3, y0: Vec3, y1: Vec3| {
            (x0.distance(x1) - y0.distance(y1)).abs() <= tol
        };
        if !(agree(xa, xb, ya, yb) && agree(xb, xc, yb, yc) && agree(xa, xc, ya, yc)) {
            continue;
        }
        // Nearly collinear sets fix no rotation about their line.
        let area = (xb - xa).cross(xc - xa).length();
        if area < tol2 {
            continue;
        }
        let Ok(pose) = procrustes(&[xa, xb, xc], &[ya, yb, yc], None) else {
            continue;
        };
        let n = support(&pose).len();
        if n >= options.min_inliers {
            found.push((n, pose));
        }
    }
    // Most supported first (ties: the earlier draw), then distinct poses only.
    found.sort_by_key(|f| std::cmp::Reverse(f.0));
    let mut kept: Vec<SampledPose> = Vec::new();
    for (_, pose) in found {
        if kept.len() == options.keep {
            break;
        }
        // Refit on the supporting matches, weighted by probability.
        let inliers = support(&pose);
        let xs: Vec<Vec3> = inliers.iter().map(|&i| pair(usable[i]).0).collect();
        let ys: Vec<Vec3> = inliers.iter().map(|&i| pair(usable[i]).1).collect();
        let ws: Vec<f32> = inliers.iter().map(|&i| usable[i].probability).collect();
        let refit = procrustes(&xs, &ys, Some(&ws)).unwrap_or(pose);
        let distinct = kept.iter().all(|k| {
            k.pose.rotation_angle_to(&refit).to_degrees() > 10.0
                || (k.pose.translation - refit.translation).length() > 0.1
        });
        if distinct {
            let inliers = support(&refit).len();
            kept.push(SampledPose {
                pose: refit,
                inliers,
            });
        }
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    #[test]
    fn sampled_poses_recover_the_pose_among_heavy_outliers_and_repeat_exactly() {
        // 60 true matches and 140 wrong ones of equal probability: weighted Procrustes of all
        // is dragged away, the sampled poses are not.
        let truth = Pose::from_axis_angle(
            DVec3::new(0.3, -1.0, 0.5).normalize(),
            2.0,
            DVec3::new(0.1, 0.2, 3.0),
        );
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        };
        let model: Vec<Vec3> = (0..200)
            .map(|_| Vec3::new(next(), next(), next()))
            .collect();
        let observed: Vec<Vec3> = model.iter().map(|&p| truth.apply_f32(p)).collect();
        let matches: Vec<Match> = (0..200)
            .map(|j| Match {
                observed: j as u32,
                model: if j < 60 {
                    j as u32
                } else {
                    ((j * 7 + 3) % 200) as u32
                },
                probability: 0.5,
                outlier: false,
            })
            .collect();
        let options = SamplingOptions::default();
        let poses = sample_poses(&model, &observed, &matches, &options, 7);
        assert!(!poses.is_empty());
        let best = poses[0];
        assert!(best.inliers >= 60, "{best:?}");
        assert!(best.pose.rotation_angle_to(&truth).to_degrees() < 1.0);
        assert!((best.pose.translation - truth.translation).length() < 0.01);
        let all = recover_pose(
            &model,
            &observed,
            &matches,
            &RecoveryOptions {
                refine: Refine::None,
                ..RecoveryOptions::default()
            },
        )
        .unwrap();
        assert!(all.pose.rotation_angle_to(&truth).to_degrees() > 5.0);
        assert_eq!(
            poses,
            sample_poses(&model, &observed, &matches, &options, 7)
        );
        // Nothing to sample from.
        assert!(sample_poses(&model, &observed, &matches[..2], &options, 7).is_empty());
    }
}
