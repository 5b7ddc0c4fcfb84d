//! The ground-truth assignment M̄ of the paper, stored compactly.
//!
//! It lives here, beside the k-d tree and the poses it is built from, so that the training
//! data (`ic_data`, which builds it) and the pose network (`ic_pose`, whose loss reads it) share
//! it without the network depending on the renderer.
//!
//! Built as in the paper (Sec. 4, "ground-truth assignment"): the model points X are moved by
//! the true pose, and a model point i and an observed point j match when each is the other's
//! nearest neighbour (the forward–backward check that keeps the matching bipartite) and they
//! are closer than the threshold (0.05 normalised units). Every other row and column goes to
//! its outlier bin. The dense (M+1)×(N+1) matrix is therefore a partial permutation plus bins:
//! every real row and every real column sums to 1.

use crate::{GeometryError, KdTree, Pose};
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// M̄ for M model points and N observed points: for each observed point, the matched model
/// point or `None` (the observed point goes to the outlier bin, column… row M).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Assignment {
    pub model_count: usize,
    pub observed_count: usize,
    pub observed_to_model: Vec<Option<u32>>,
}

impl Assignment {
    /// Mutual nearest neighbours between `pose·model` and `observed` closer than `threshold`.
    ///
    /// Errors: empty or non-finite point sets, or a non-finite / negative threshold.
    pub fn from_pose(
        model: &[Vec3],
        observed: &[Vec3],
        pose: &Pose,
        threshold: f32,
    ) -> Result<Assignment, GeometryError> {
        if !(threshold.is_finite() && threshold >= 0.0) {
            return Err(GeometryError::InvalidParameter {
                name: "match threshold",
                message: format!("must be finite and ≥ 0, got {threshold}"),
            });
        }
        let moved = pose.apply_all(model);
        let model_tree = KdTree::new(&moved)?;
        let observed_tree = KdTree::new(observed)?;
        let forward = model_tree.nearest_all(observed); // observed j → nearest model i
        let backward = observed_tree.nearest_all(&moved); // model i → nearest observed j
        let observed_to_model = forward
            .iter()
            .enumerate()
            .map(|(j, n)| {
                (n.distance < threshold && backward[n.index].index == j).then_some(n.index as u32)
            })
            .collect();
        Ok(Assignment {
            model_count: model.len(),
            observed_count: observed.len(),
            observed_to_model,
        })
    }

    /// Number of matched pairs (inliers).
    pub fn inlier_count(&self) -> usize {
        self.observed_to_model
            .iter()
            .filter(|m| m.is_some())
            .count()
    }

    /// Fraction of observed points that have a match.
    pub fn observed_inlier_rate(&self) -> f64 {
        if self.observed_count == 0 {
            0.0
        } else {
            self.inlier_count() as f64 / self.observed_count as f64
        }
    }

    /// For each model point, the matched observed point or `None`.
    pub fn model_to_observed(&self) -> Vec<Option<u32>> {
        let mut out = vec![None; self.model_count];
        for (j, m) in self.observed_to_model.iter().enumerate() {
            if let Some(i) = m
                && let Some(slot) = out.get_mut(*i as usize)
            {
                *slot = Some(j as u32);
            }
        }
        out
    }

    /// Matched pairs `(model index, observed index)`, in observed order.
    pub fn pairs(&self) -> Vec<(usize, usize)> {
        self.observed_to_model
            .iter()
            .enumerate()
            .filter_map(|(j, m)| m.map(|i| (i as usize, j)))
            .collect()
    }

    /// The dense M̄, row-major (M+1)×(N+1): rows are model points, columns observed points, the
    /// last row and column are the outlier bins; the bin–bin corner is 0.
    pub fn dense(&self) -> Vec<f32> {
        let (m, n) = (self.model_count, self.observed_count);
        let cols = n + 1;
        let mut out = vec![0.0f32; (m + 1) * cols];
        let model_to_observed = self.model_to_observed();
        for (i, o) in model_to_observed.iter().enumerate() {
            match o {
                Some(j) => out[i * cols + *j as usize] = 1.0,
                None => out[i * cols + n] = 1.0,
            }
        }
        for (j, o) in self.observed_to_model.iter().enumerate() {
            if o.is_none() {
                out[m * cols + j] = 1.0;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn mutual_nearest_neighbours_within_the_threshold_match() {
        let model = vec![Vec3::ZERO, Vec3::X, Vec3::new(5.0, 0.0, 0.0)];
        let pose = Pose::from_translation(DVec3::new(0.0, 0.0, 2.0));
        let observed = vec![
            Vec3::new(0.0, 0.0, 2.01),
            Vec3::new(1.0, 0.0, 2.02),
            Vec3::new(1.0, 0.0, 2.03),
            Vec3::new(9.0, 9.0, 9.0),
        ];
        let a = Assignment::from_pose(&model, &observed, &pose, 0.05).unwrap();
        assert_eq!(a.observed_to_model, vec![Some(0), Some(1), None, None]);
        assert_eq!(a.inlier_count(), 2);
        assert_eq!(a.model_to_observed(), vec![Some(0), Some(1), None]);
        let d = a.dense();
        assert_eq!(d.len(), 4 * 5);
        // Row 2 (far model point) goes to the bin; columns 2 and 3 too.
        assert_eq!(d[2 * 5 + 4], 1.0);
        assert_eq!(d[3 * 5 + 2], 1.0);
        assert_eq!(d[3 * 5 + 3], 1.0);
        assert_eq!(d[3 * 5 + 4], 0.0);
        assert!(Assignment::from_pose(&model, &observed, &pose, f32::NAN).is_err());
        assert!(Assignment::from_pose(&model, &[], &pose, 0.05).is_err());
    }
}
