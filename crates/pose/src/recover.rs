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
    /// Matches below this probability are dropped (if fewer than 3 remain, the 3+ most
    /// probable matches are used regardless).
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
    let mut kept: Vec<&Match> = matches
        .iter()
        .filter(|m| !m.outlier && m.probability >= options.min_probability)
        .collect();
    if kept.len() < 3 {
        kept = matches.iter().collect();
        kept.sort_by(|a, b| b.probability.total_cmp(&a.probability));
        kept.truncate(16);
    }
    if kept.len() < 3 {
        return Err(PoseError::TooFewPoints {
            what: "correspondences",
            got: kept.len(),
            needed: 3,
        });
    }
    let xs: Vec<Vec3> = kept.iter().map(|m| model[m.model as usize]).collect();
    let ys: Vec<Vec3> = kept.iter().map(|m| observed[m.observed as usize]).collect();
    let ws: Vec<f32> = kept.iter().map(|m| m.probability.max(1e-12)).collect();
    let confidence = ws.iter().sum::<f32>() / ws.len() as f32;
    let mut pose = procrustes(&xs, &ys, options.weighted.then_some(&ws[..]))?;
    if options.refine == Refine::Icp {
        pose = refine_icp(model, observed, &pose, options)?;
    }
    Ok(Recovered {
        pose,
        inlier_count: kept.len(),
        assignment_confidence: confidence,
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
