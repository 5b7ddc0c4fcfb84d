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
