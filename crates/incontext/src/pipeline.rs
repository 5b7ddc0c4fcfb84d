//! The registration pipeline, shared by `register`, `demo`, `eval` and the benchmark tool:
//!
//! ```text
//! depth (model units) ÷ scale ──seg net──► mask ──erode 3×3, back-project, crop 1.2──►
//!   voxelise 0.0354 ──sample N──► pose network on 24 rotated copies of M model points
//!   (one sweep) ──► per copy: weighted Procrustes + 2 poses sampled from its matches
//!   ──rank by point-distance confidence──► best 8: ICP (≤ 1024 voxels) + render-and-compare
//!   ──► best score: ICP again (≤ 4096 voxels) ──► evidence → calibrated confidence, verdict
//!   ──Normalisation::pose_to_original──► pose in the model's own units
//! ```
//!
//! With `rotations = 1` (the paper's pipeline): one pass of the network, weighted Procrustes,
//! ICP of all object voxels onto the dense model points, the point-distance confidence.
//!
//! The networks work in normalised object units: the mesh is normalised to [-1, 1] on its
//! longest side (`Normalisation { centre, scale }`) and the depth map, which must be in the
//! mesh's own units, is divided by `scale`, so the camera frame is scaled but not moved.
//!
//! A pipeline is made by [`Pipeline::builder`] (the networks, the settings of `incontext
//! register` as defaults, optionally its own threads) and fails with [`PipelineError`]: bad
//! input, object not found, or internal — the distinction the command line turns into its exit
//! codes 2, 3 and 1 (through `CliError`) and the Python module into its exceptions. Poses map
//! model to camera coordinates (`x_cam = R·x + t`, R row-major in files).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use ic_geometry::glam::Vec3;
use ic_geometry::sampling::{VisibleSurfaceOptions, sample_visible_surface};
use ic_geometry::{
    DepthImage, IcpMethod, IcpOptions, IcpTarget, Image, Intrinsics, KdTree, Mask, Mesh,
    Normalisation, Pose, estimate_normals, random_subsample_indices, voxel_downsample_points,
};
use ic_pose::{Head, Refine};
use ic_seg::PostConfig;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;

use crate::models::{LoadedPose, LoadedSeg};

/// Why a pipeline could not be built or a registration failed, by what the caller can do
/// about it. The command line maps the variants to its exit codes (2, 3, 1) and the Python
/// module to `ValueError`, `NotFoundError` and `RuntimeError`; the message names the file or
/// the value at fault.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// Bad input: a checkpoint that cannot be read or does not fit, a mesh that cannot be
    /// normalised, sizes that do not match, an empty mask, a setting out of range.
    #[error("{0}")]
    Input(String),
    /// The object is not in the depth map (segmentation finds nothing, too few object points).
    #[error("{0}")]
    NotFound(String),
    /// Anything else: a bug or an environment problem.
    #[error("{0}")]
    Internal(String),
}

impl PipelineError {
    /// [`PipelineError::Input`].
    pub fn input(message: impl Into<String>) -> Self {
        PipelineError::Input(message.into())
    }

    /// [`PipelineError::NotFound`].
    pub fn not_found(message: impl Into<String>) -> Self {
        PipelineError::NotFound(message.into())
    }

    /// [`PipelineError::Internal`].
    pub fn internal(message: impl Into<String>) -> Self {
        PipelineError::Internal(message.into())
    }

    /// The message, for people.
    pub fn message(&self) -> &str {
        match self {
            PipelineError::Input(m) | PipelineError::NotFound(m) | PipelineError::Internal(m) => m,
        }
    }

    /// The same error with `context: ` in front of its message.
    pub fn context(self, context: impl std::fmt::Display) -> Self {
        match self {
            PipelineError::Input(m) => PipelineError::Input(format!("{context}: {m}")),
            PipelineError::NotFound(m) => PipelineError::NotFound(format!("{context}: {m}")),
            PipelineError::Internal(m) => PipelineError::Internal(format!("{context}: {m}")),
        }
    }
}

/// Classifies the pose crate's errors: a checkpoint that cannot be read or does not fit its
/// network is bad input; too few points means the object was not found; the rest is internal.
impl From<ic_pose::PoseError> for PipelineError {
    fn from(e: ic_pose::PoseError) -> Self {
        use ic_pose::PoseError as P;
        match &e {
            P::Checkpoint { .. } | P::Io { .. } => PipelineError::input(e.to_string()),
            P::TooFewPoints { .. } => {
                PipelineError::not_found(format!("too few points to estimate a pose: {e}"))
            }
            P::NonFinite { .. } => PipelineError::input(e.to_string()),
            P::Geometry(g @ ic_geometry::GeometryError::DegenerateCorrespondences { .. }) => {
                PipelineError::from(g.clone())
            }
            _ => PipelineError::internal(e.to_string()),
        }
    }
}

/// Classifies the segmentation crate's errors.
impl From<ic_seg::SegError> for PipelineError {
    fn from(e: ic_seg::SegError) -> Self {
        use ic_seg::SegError as S;
        match &e {
            S::ObjectNotFound { .. } => PipelineError::not_found(e.to_string()),
            S::Input(_) | S::Checkpoint { .. } | S::Io { .. } | S::Geometry(_) => {
                PipelineError::input(e.to_string())
            }
            _ => PipelineError::internal(e.to_string()),
        }
    }
}

/// Geometry errors inside the pipeline come from computations on checked input.
impl From<ic_geometry::GeometryError> for PipelineError {
    fn from(e: ic_geometry::GeometryError) -> Self {
        match e {
            // Object points on a line (a one-pixel sliver of a mask): they fix no pose.
            ic_geometry::GeometryError::DegenerateCorrespondences { .. } => {
                PipelineError::not_found(format!(
                    "object not found: no pose can be estimated from the object points ({e})"
                ))
            }
            e => PipelineError::internal(e.to_string()),
        }
    }
}

/// Results of the pipeline.
pub type Result<T, E = PipelineError> = std::result::Result<T, E>;

/// The paper's voxel size, 0.05·√2/2 normalised units.
pub const VOXEL_SIZE: f32 = ic_data::PAPER_VOXEL_SIZE;
/// Visible-surface model points sampled per mesh (the M the network sees are drawn from them,
/// and ICP registers onto all of them), as `ic_data` caches them for training.
pub const DENSE_MODEL_POINTS: usize = 4096;
/// The paper's match distance (normalised units): an observed point within it of the aligned
/// model counts as explained in the confidence.
pub const MATCH_DISTANCE: f32 = ic_data::PAPER_MATCH_THRESHOLD;

/// The confidence from which a pose's [`Verdict`] is `ok` (chosen on validation views: see
/// `docs/decisions.md`).
pub const CONFIDENCE_OK: f64 = 0.6;

/// The confidence below which the object counts as not found ([`Verdict::NotFound`]).
pub const CONFIDENCE_FOUND: f64 = 0.25;

/// The calibrated confidence (the probability that the pose is right, see
/// [`verified_calibration`]) from which a verified pose is `ok` (`docs/decisions.md`). One
/// value with the calibration fits' ([`ic_eval::calibration::VERIFIED_OK`]).
pub const VERIFIED_OK: f64 = ic_eval::calibration::VERIFIED_OK;

/// The raw render-and-compare score below which a verified pose counts as not found: the
/// model at its best pose explains almost none of the object's depth. One value with the
/// calibration fits' ([`ic_eval::calibration::VERIFIED_FOUND`]).
pub const VERIFIED_FOUND: f64 = ic_eval::calibration::VERIFIED_FOUND;

/// The isotonic calibration of a verified pose's [`evidence`],
/// `models/verify-calibration.json` (fitted by `cargo xtask verify-report --fit-calibration` on
/// validation views of unseen objects, see `models/README.md`): the probability that the pose
/// is right (ADD-S below 0.1 of the diameter) given its evidence. Embedded in the binary.
pub fn verified_calibration() -> &'static ic_eval::Calibration {
    static CALIBRATION: std::sync::OnceLock<ic_eval::Calibration> = std::sync::OnceLock::new();
    CALIBRATION.get_or_init(|| {
        embedded_calibration(
            "models/verify-calibration.json",
            include_str!("../../../models/verify-calibration.json"),
        )
    })
}

/// The calibration in `text`, the embedded JSON file `name` (`{"knots": [[x, p], …], …}`);
/// it is part of the binary, so a bad one is a build defect, not an input error.
fn embedded_calibration(name: &str, text: &str) -> ic_eval::Calibration {
    #[derive(serde::Deserialize)]
    struct File {
        knots: Vec<(f64, f64)>,
    }
    let file: File =
        serde_json::from_str(text).unwrap_or_else(|e| panic!("{name} does not parse: {e}"));
    ic_eval::Calibration::new(file.knots)
        .unwrap_or_else(|e| panic!("{name} is not a calibration: {e}"))
}

/// The confidence of a verified pose when the segmentation network chose its pixels among
/// several instances, `models/verify-calibration-clutter.json` (fitted by `cargo xtask
/// fit-clutter-calibration` on every instance registered in clutter scenes of validation
/// objects, see `models/README.md`): a logistic model over the registration's numbers
/// ([`clutter_features`]), then an isotonic calibration of its output — the probability that
/// the pose is right (ADD-S below 0.1 of the diameter of a true instance of the object). In
/// clutter most wrong poses are good fits of *another* object, which the single-object
/// calibration ([`verified_calibration`]) calls right. Embedded in the binary.
pub fn clutter_confidence() -> &'static ic_eval::ClutterConfidence {
    static CONFIDENCE: std::sync::OnceLock<ic_eval::ClutterConfidence> = std::sync::OnceLock::new();
    CONFIDENCE.get_or_init(|| {
        // Part of the binary: a bad file is a build defect, not an input error.
        ic_eval::ClutterConfidence::from_json(include_str!(
            "../../../models/verify-calibration-clutter.json"
        ))
        .unwrap_or_else(|e| panic!("models/verify-calibration-clutter.json: {e}"))
    })
}

/// The numbers of a verified registration on a network-chosen instance that
/// [`clutter_confidence`] weighs: its evidence and rival, its render-and-compare score in the
/// crop, its whole view (when computed), its object voxels, its instance and segmentation.
/// `None` for an unverified registration.
pub fn clutter_features(r: &Registration) -> Option<ic_eval::ClutterFeatures> {
    let v = r.verification?;
    let instance = r.instance.unwrap_or_default();
    Some(ic_eval::ClutterFeatures {
        evidence: r.evidence?,
        rival_score: r.rival_score.unwrap_or(0.0),
        object_voxels: r.object_voxels,
        verification: ic_eval::clutter::CropScore {
            score: v.score,
            coverage: v.coverage,
            agreement: v.agreement,
            visible_agreement: v.visible_agreement,
            misfit: v.misfit,
            violation: v.violation,
        },
        whole_view: r.whole_view.map(|w| ic_eval::clutter::WholeViewFractions {
            agreement: w.agreement,
            in_front: w.in_front,
            missing: w.missing,
        }),
        instance: ic_eval::clutter::InstanceNumbers {
            size_ratio: instance.size_ratio,
            shape_distance: Some(instance.shape_distance),
            truncated: instance.truncated,
            cut: instance.cut,
        },
        segmentation: ic_eval::clutter::SegmentationNumbers {
            pixels: r.segmentation.as_ref().map_or(0, |s| s.pixels),
            score: r.segmentation.as_ref().and_then(|s| s.score).map(f64::from),
        },
    })
}

/// The winner of the verification is refined again on more object voxels; that finer fit is
/// kept unless its render-and-compare score drops by more than this.
pub const FINE_REFINE_SLACK: f64 = 0.02;

/// Two poses are equivalent (the same up to the object's symmetry, as far as the model can
/// tell) when their ADD-S distance is below this fraction of the object's diameter.
pub const EQUIVALENT_ADD_S: f64 = 0.1;

/// The evidence a verified pose rests on, in [0, 1]: its render-and-compare `score`, capped by
/// four times its margin over the best pose that is not equivalent to it (`rival`). Measured on
/// validation views (`docs/decisions.md`): without the cap, 3 % of poses that scored above 0.9
/// were wrong — views that another, different pose explains as well.
pub fn evidence(score: f64, rival: f64) -> f64 {
    score.min(4.0 * (score - rival)).clamp(0.0, 1.0)
}

/// Object voxels each verified hypothesis is refined on by ICP (the winner is refined again
/// on up to `icp_max_points`).
pub const VERIFY_ICP_POINTS: usize = 1024;

/// Object voxels (at most) on which the one-shot hypotheses are ranked by the point-distance
/// confidence before verification.
pub const RANKING_POINTS: usize = 512;

/// A known object, ready to be registered: its normalised mesh (when it came from one), how it
/// was normalised, and its dense visible-surface points with normals (normalised units).
pub struct Object {
    pub mesh: Option<Arc<Mesh>>,
    pub normalisation: Normalisation,
    pub points: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    tree: KdTree,
    /// The largest distance between two of `points` (normalised units; from at most 512 of
    /// them, evenly strided).
    pub diameter: f64,
    /// Seconds spent sampling the points and normals.
    pub seconds: f64,
    /// The spreads of its surface seen from many directions, computed when first needed
    /// ([`Object::view_spreads`]).
    view_spreads: std::sync::OnceLock<crate::shape::ViewSpreads>,
}

impl std::fmt::Debug for Object {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Object")
            .field("triangles", &self.mesh.as_ref().map(|m| m.triangles.len()))
            .field("normalisation", &self.normalisation)
            .field("points", &self.points.len())
            .finish()
    }
}

impl Object {
    /// ADD-S between the model at poses `a` and `b` (normalised units): the mean distance from
    /// each of 256 of the object's points (evenly strided) at `a` to the nearest point at `b`.
    pub fn add_s(&self, a: &Pose, b: &Pose) -> f64 {
        let b_inv = b.inverse();
        let (mut sum, mut n) = (0.0f64, 0usize);
        for p in strided(&self.points, 256) {
            let q = b_inv.apply_f32(a.apply_f32(*p));
            sum += self.tree.nearest(q).distance as f64;
            n += 1;
        }
        sum / n.max(1) as f64
    }

    /// `depth` (in the object's own units) divided by its normalisation scale: the normalised
    /// units the networks work in.
    pub fn normalised_depth(&self, depth: &DepthImage) -> DepthImage {
        let inv = (1.0 / self.normalisation.scale) as f32;
        Image {
            width: depth.width,
            height: depth.height,
            data: depth.data.iter().map(|&z| z * inv).collect(),
        }
    }

    /// Normalises `mesh` (in its own units) and samples its visible surface (seeded).
    pub fn from_mesh(mut mesh: Mesh, seed: u64) -> Result<Object> {
        let clock = Instant::now();
        let normalisation = mesh
            .normalise()
            .map_err(|e| PipelineError::input(format!("the mesh cannot be normalised: {e}")))?;
        let cloud = sample_visible_surface(
            &mesh,
            DENSE_MODEL_POINTS,
            seed,
            VisibleSurfaceOptions::default(),
        )
        .map_err(|e| PipelineError::input(format!("sampling the mesh surface: {e}")))?;
        if cloud.points.len() < 16 {
            return Err(PipelineError::input(format!(
                "the mesh has almost no visible surface ({} points could be sampled)",
                cloud.points.len()
            )));
        }
        let normals = match cloud.normals {
            Some(n) if n.len() == cloud.points.len() => n,
            _ => pca_normals(&cloud.points)?,
        };
        let mut object = Object::build(cloud.points, normals, normalisation)?;
        object.mesh = Some(Arc::new(mesh));
        object.seconds = clock.elapsed().as_secs_f64();
        Ok(object)
    }

    /// An object given by points already in normalised units (e.g. a case's `source.ply`);
    /// normals are estimated by PCA.
    pub fn from_points(points: Vec<Vec3>) -> Result<Object> {
        let clock = Instant::now();
        if points.len() < 16 {
            return Err(PipelineError::input(format!(
                "the model has {} points; at least 16 are needed",
                points.len()
            )));
        }
        if points.iter().any(|p| !p.is_finite()) {
            return Err(PipelineError::input("the model points are not all finite"));
        }
        let normals = pca_normals(&points)?;
        let mut object = Object::build(
            points,
            normals,
            Normalisation {
                centre: ic_geometry::glam::DVec3::ZERO,
                scale: 1.0,
            },
        )?;
        object.seconds = clock.elapsed().as_secs_f64();
        Ok(object)
    }

    /// An object already normalised (e.g. from an `ic_data` corpus): its normalised mesh, the
    /// normalisation of the original, and dense surface points in normalised units.
    pub fn from_normalised(
        mesh: Option<Arc<Mesh>>,
        normalisation: Normalisation,
        points: Vec<Vec3>,
    ) -> Result<Object> {
        let mut object = Object::from_points(points)?;
        object.mesh = mesh;
        object.normalisation = normalisation;
        Ok(object)
    }

    fn build(
        points: Vec<Vec3>,
        normals: Vec<Vec3>,
        normalisation: Normalisation,
    ) -> Result<Object> {
        let tree = KdTree::new(&points)?;
        let some: Vec<Vec3> = strided(&points, 512).copied().collect();
        let diameter = ic_eval::diameter(&some);
        Ok(Object {
            mesh: None,
            normalisation,
            points,
            normals,
            tree,
            diameter,
            seconds: 0.0,
            view_spreads: std::sync::OnceLock::new(),
        })
    }

    /// The spreads of the object's surface seen from [`crate::shape::VIEWS`] directions, which
    /// the ranking of instances compares their shapes with; computed on the first call
    /// (≈ 12 ms for 4 096 points on 2 threads) and kept.
    pub fn view_spreads(&self) -> &crate::shape::ViewSpreads {
        self.view_spreads
            .get_or_init(|| crate::shape::ViewSpreads::of(&self.points, self.diameter))
    }
}

/// The camera is valid and `depth` has its size.
fn check_depth_input(depth: &DepthImage, intrinsics: &Intrinsics) -> Result<()> {
    intrinsics
        .validate()
        .map_err(|e| PipelineError::input(e.to_string()))?;
    depth
        .check_size(intrinsics.width, intrinsics.height)
        .map_err(|e| PipelineError::input(format!("depth map: {e}")))
}

fn pca_normals(points: &[Vec3]) -> Result<Vec<Vec3>> {
    let centre = points.iter().copied().sum::<Vec3>() / points.len().max(1) as f32;
    Ok(estimate_normals(points, 10, centre + Vec3::splat(100.0))?)
}

/// How far a registration can be trusted. Verified registrations (`rotations > 1`, the
/// default): from the confidence, the calibrated probability that the pose is right, and the
/// raw render-and-compare score ([`Verdict::of_verified`]). Unverified ones: from the
/// point-distance confidence ([`Verdict::of`]). Thresholds in [`PipelineOptions`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// The pose is right with a probability of at least `verified_ok` (unverified: it explains
    /// at least `confidence_ok` of the object points); use it.
    Ok,
    /// A pose was found but it may be wrong (a symmetric flip, the wrong side, another object,
    /// a view that other poses explain as well); check it (`--overlay`), look from another
    /// side, or try more hypotheses.
    Uncertain,
    /// The best pose explains almost nothing (render-and-compare score below
    /// `verified_found`; unverified: confidence below `confidence_found`): the object is not
    /// in view, or the mesh or its units are wrong.
    NotFound,
}

impl Verdict {
    /// The verdict of a point-distance confidence in [0, 1] (`confidence_ok`,
    /// `confidence_found`).
    pub fn of(confidence: f64, options: &PipelineOptions) -> Verdict {
        if confidence >= options.confidence_ok {
            Verdict::Ok
        } else if confidence >= options.confidence_found {
            Verdict::Uncertain
        } else {
            Verdict::NotFound
        }
    }

    /// The verdict of a verified pose: `not_found` when its raw render-and-compare `score` is
    /// below `verified_found`, else `ok` when its calibrated `confidence` reaches
    /// `verified_ok`, else `uncertain`.
    pub fn of_verified(score: f64, confidence: f64, options: &PipelineOptions) -> Verdict {
        if score < options.verified_found {
            Verdict::NotFound
        } else if confidence >= options.verified_ok {
            Verdict::Ok
        } else {
            Verdict::Uncertain
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Ok => "ok",
            Verdict::Uncertain => "uncertain",
            Verdict::NotFound => "not_found",
        }
    }
}

/// Settings of the pipeline (printed with every run).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PipelineOptions {
    /// Refinement after the one-shot estimate.
    pub refine: Refine,
    /// Voxel size of the observed points (normalised units).
    pub voxel_size: f32,
    /// ICP: correspondence distance (normalised units) and iterations.
    pub icp_max_distance: f32,
    pub icp_iterations: usize,
    /// ICP registers at most this many object voxels (drawn at random when there are more).
    pub icp_max_points: usize,
    /// Fewer object voxels than this after segmentation means the object was not found.
    pub min_object_points: usize,
    /// Pose hypotheses: each draws its own M model and N observed points and runs the network
    /// and the refinement; the one whose pose explains the most observed points wins. 1 is
    /// the paper's one-shot pipeline.
    pub hypotheses: usize,
    /// The [`Verdict`] thresholds on the confidence: `ok` from `confidence_ok`, `uncertain`
    /// from `confidence_found`, `not_found` below (measured in `docs/decisions.md`).
    pub confidence_ok: f64,
    pub confidence_found: f64,
    /// When hypotheses are verified (`rotations > 1`): `ok` from a calibrated confidence of
    /// `verified_ok`, `not_found` below a raw render-and-compare score of `verified_found`.
    pub verified_ok: f64,
    pub verified_found: f64,
    /// Rotation hypotheses (1, 12, 24 or 60; see [`crate::verify::rotation_set`]): the model
    /// points are registered in that many rotated copies, batched through the network, and the
    /// best are verified by render-and-compare. 1 = the paper's single orientation.
    pub rotations: usize,
    /// How many one-shot hypotheses (ranked by the point-distance confidence) are refined by
    /// ICP and scored by render-and-compare when `rotations > 1`.
    pub verify_top: usize,
    /// Model points of the rotation sweep (the observed points are ¾ of it); 0 = the
    /// network's own M and N (384 and 288). Fewer points make the sweep faster; the verified
    /// hypotheses are refined by ICP on the object voxels anyway. Default 320: as accurate as
    /// 384 on 600 views of three sets and ≈ 40 ms faster with 24 rotations; 192 lost the
    /// pose of a close-up object entirely (`docs/decisions.md`).
    pub sweep_points: usize,
    /// Per rotated copy, poses of minimal sets of three correspondences drawn from the
    /// network's soft assignment ([`ic_pose::sample_poses`]) that join the copy's weighted
    /// Procrustes pose as hypotheses; 0 = none.
    pub sampled_hypotheses: usize,
    /// Rotated copies that go on through the transformer after the DGCNN (the unrotated copy
    /// and those whose features best match the observed ones); 0 = all.
    pub sweep_keep: usize,
    /// Passes of the network when hypotheses are verified: 1 = the sweep's pass only; each
    /// further pass registers, for each of the previous pass's hypotheses (the first
    /// `pass_top` of the `verify_top`), a copy of the model turned so that the hypothesis's
    /// rotation sits at the centre of the rotations the network was trained on, and adds that
    /// pass's pose as one more verified hypothesis. The originals stay: a pass can turn a
    /// right pose into a near-symmetric wrong one (`docs/decisions.md`, "More passes of the
    /// network"). With the segmentation network, only the best-ranked instance gets the
    /// further passes (the others one): `register` may try several. Default 3.
    pub network_passes: usize,
    /// How many hypotheses the second pass of the network takes (the best by the
    /// point-distance ranking; each later pass takes the previous pass's); 0 = all
    /// `verify_top`.
    pub pass_top: usize,
    /// With the segmentation network: how many of its instances (ranked by how well their
    /// size fits the model, [`InstanceCandidate`]) are registered before giving up, and as
    /// many pieces of heaps after them; the first whose verdict is `ok` ends the search,
    /// otherwise the best verified one wins. 0 = every instance that fits. Default 8
    /// (`docs/decisions.md`, "How many instances `register` tries").
    pub instance_tries: usize,
    /// `register --all` ([`Pipeline::register_depth_all`]) also returns `uncertain` instances
    /// whose confidence reaches this and whose whole projection is consistent with the depth
    /// map ([`crate::verify::WholeView::consistent`]; `None`: only `ok` ones). The confidence of a
    /// network-segmented instance is calibrated on clutter ([`clutter_confidence`]), so a
    /// lower bar trades the share of right poses among those returned for more of the
    /// instances.
    pub all_min_confidence: Option<f64>,
    /// Whether `register --all` keeps an `uncertain` instance only when its whole projection
    /// is consistent with the depth map (default true). `incontext eval --dataset` turns it
    /// off: BOP scores the best estimates of a target of several instances whatever their
    /// confidence, and a doubtful estimate there costs nothing.
    pub all_whole_view: bool,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        PipelineOptions {
            refine: Refine::Icp,
            voxel_size: VOXEL_SIZE,
            icp_max_distance: 0.1,
            icp_iterations: 30,
            icp_max_points: 4096,
            min_object_points: 32,
            hypotheses: 1,
            confidence_ok: CONFIDENCE_OK,
            confidence_found: CONFIDENCE_FOUND,
            verified_ok: VERIFIED_OK,
            verified_found: VERIFIED_FOUND,
            rotations: 1,
            verify_top: 8,
            sweep_points: 320,
            sampled_hypotheses: 2,
            sweep_keep: 0,
            network_passes: 3,
            pass_top: 0,
            instance_tries: 8,
            all_min_confidence: None,
            all_whole_view: true,
        }
    }
}

/// Visible extent over the model's diameter below which an instance is too small to be the
/// object (most of it hidden, or another, smaller object): it is never registered.
pub const MIN_SIZE_RATIO: f64 = 0.25;
/// … and above which it is too large (another, larger object, or several merged): it is
/// registered only when no instance fits (the crop around its centre may still hold the
/// object, as when a mask runs into the support).
pub const MAX_SIZE_RATIO: f64 = 1.3;
/// The visible extent of an unoccluded object relative to its diameter, roughly: the
/// ranking prefers instances near it. One value with the clutter confidence's `size_misfit`
/// ([`ic_eval::clutter::TYPICAL_SIZE_RATIO`]).
pub const TYPICAL_SIZE_RATIO: f64 = ic_eval::clutter::TYPICAL_SIZE_RATIO;

/// One object instance found by the segmentation network, and how well its size fits the
/// model.
#[derive(Clone, Debug, Serialize)]
pub struct InstanceCandidate {
    /// The network's instance score (mean object probability).
    pub score: f32,
    /// Pixels of its mask.
    pub pixels: usize,
    /// The extent of its back-projected points (normalised units): twice the 90th
    /// percentile of their distances to their centroid.
    pub extent: f64,
    /// `extent` over the model's diameter.
    pub size_ratio: f64,
    /// Whether the size ratio lies in [[`MIN_SIZE_RATIO`], [`MAX_SIZE_RATIO`]].
    pub plausible: bool,
    /// How far the two principal spreads of its back-projected points lie from those of the
    /// nearest of the model's views ([`crate::shape::ViewSpreads::distance`]; dimensionless,
    /// 0 = a view of the model spreads exactly so).
    pub shape_distance: f64,
    /// Whether its mask reaches the border of the sensor's frame (within [`BORDER_PX`]): the
    /// object may be cut off, its extent and pose less sure.
    pub truncated: bool,
    /// Whether it is a piece cut from an instance too large to be the model (a heap the
    /// network did not split; [`crate::parts::heap_pieces`]).
    pub cut: bool,
    /// How many of the network's instances it joins: 1, or more for touching instances each
    /// too small to be the object that together fit its size ([`crate::parts`]).
    pub parts: usize,
    /// Which input size of the segmentation network found it: 0 its own, `i` the `i`-th of
    /// [`ic_seg::PostConfig::extra_inputs`].
    pub input: usize,
    #[serde(skip)]
    pub mask: Mask,
}

/// A candidate of a later input size whose mask overlaps one of an earlier candidate's by at
/// least this IoU is the same instance found again, and dropped.
pub const DUPLICATE_IOU: f64 = 0.7;

/// A mask's pixels as sorted indices with their bounding box, for overlaps of sparse masks
/// without sweeping whole images.
struct PixelSet {
    indices: Vec<u32>,
    /// `(x0, y0, x1, y1)` inclusive; meaningless when empty.
    bbox: (u32, u32, u32, u32),
}

impl PixelSet {
    fn of(mask: &Mask) -> PixelSet {
        let w = mask.width.max(1);
        let mut bbox = (u32::MAX, u32::MAX, 0, 0);
        let indices: Vec<u32> = (0..mask.data.len() as u32)
            .filter(|&i| mask.data[i as usize])
            .inspect(|&i| {
                let (x, y) = (i % w, i / w);
                bbox = (bbox.0.min(x), bbox.1.min(y), bbox.2.max(x), bbox.3.max(y));
            })
            .collect();
        PixelSet { indices, bbox }
    }

    /// Intersection over union (0 when both are empty).
    fn iou(&self, other: &PixelSet) -> f64 {
        let (a, b) = (&self.indices, &other.indices);
        let union_max = a.len() + b.len();
        if union_max == 0 {
            return 0.0;
        }
        let (p, q) = (self.bbox, other.bbox);
        if a.is_empty() || b.is_empty() || p.0 > q.2 || q.0 > p.2 || p.1 > q.3 || q.1 > p.3 {
            return 0.0;
        }
        let (mut i, mut j, mut both) = (0, 0, 0usize);
        while i < a.len() && j < b.len() {
            match a[i].cmp(&b[j]) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    both += 1;
                    i += 1;
                    j += 1;
                }
            }
        }
        both as f64 / (union_max - both) as f64
    }
}

/// The visible extent of back-projected points (their units): twice the 90th percentile of
/// their distances to their centroid. At least one point.
fn visible_extent(points: &[Vec3]) -> f64 {
    let centre = points.iter().copied().sum::<Vec3>() / points.len() as f32;
    let mut d: Vec<f32> = points.iter().map(|p| p.distance(centre)).collect();
    let k = ((d.len() as f64 * 0.9) as usize).min(d.len() - 1);
    let (_, p90, _) = d.select_nth_unstable_by(k, f32::total_cmp);
    2.0 * *p90 as f64
}

/// An instance with a pixel this close to the border of the sensor's frame is cut off by it
/// ([`InstanceCandidate::truncated`]).
pub const BORDER_PX: u32 = 2;

/// The sensor's frame in `depth`: the first and last rows and columns of which at least a
/// quarter of the pixels have a depth, as `(x0, y0, x1, y1)` inclusive (Kinect-type sensors
/// leave bands of no return along the image's borders). The whole image when none qualifies.
fn sensor_frame(depth: &DepthImage) -> (u32, u32, u32, u32) {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let valid = |x: usize, y: usize| {
        let z = depth.data[y * w + x];
        z.is_finite() && z > 0.0
    };
    let rows: Vec<bool> = (0..h)
        .map(|y| 4 * (0..w).filter(|&x| valid(x, y)).count() >= w)
        .collect();
    let cols: Vec<bool> = (0..w)
        .map(|x| 4 * (0..h).filter(|&y| valid(x, y)).count() >= h)
        .collect();
    let span = |v: &[bool]| {
        let first = v.iter().position(|&b| b);
        let last = v.iter().rposition(|&b| b);
        match (first, last) {
            (Some(a), Some(b)) => (a as u32, b as u32),
            _ => (0, v.len().saturating_sub(1) as u32),
        }
    };
    let ((x0, x1), (y0, y1)) = (span(&cols), span(&rows));
    (x0, y0, x1, y1)
}

/// Whether `mask` has a pixel within [`BORDER_PX`] of the sensor's `frame` (see
/// [`sensor_frame`]) or outside it.
fn touches_border(mask: &Mask, frame: (u32, u32, u32, u32)) -> bool {
    let (x0, y0, x1, y1) = frame;
    let w = mask.width;
    mask.data.iter().enumerate().any(|(i, &on)| {
        let (x, y) = (i as u32 % w, i as u32 / w);
        on && (x < x0 + BORDER_PX || y < y0 + BORDER_PX || x + BORDER_PX > x1 || y + BORDER_PX > y1)
    })
}

/// At most this many pieces are cut from one instance too large to be the model, and from
/// all of them together ([`crate::parts::heap_pieces`]).
pub const MAX_PIECES_PER_INSTANCE: usize = 6;
pub const MAX_PIECES: usize = 12;

/// The one-object network's instance is not registered again when its mask overlaps one the
/// main network's tries registered by at least this intersection over union
/// ([`Pipeline::with_one_object_seg`]).
pub const SAME_INSTANCE_IOU: f64 = 0.8;

/// Intersection over union of two masks of the same size (0 when both are empty).
fn mask_iou(a: &Mask, b: &Mask) -> f64 {
    let (mut both, mut either) = (0usize, 0usize);
    for (&x, &y) in a.data.iter().zip(&b.data) {
        both += usize::from(x && y);
        either += usize::from(x || y);
    }
    if either == 0 {
        0.0
    } else {
        both as f64 / either as f64
    }
}

/// Touching instances are joined as parts of one object when their depths differ by at most
/// this fraction of the model's diameter where they meet ([`crate::parts::contacts`]).
pub const PART_DEPTH_GAP: f64 = 0.5;

/// Touching instances each too small for the model are joined ([`crate::parts`]) when
/// together their size ratio reaches [`TYPICAL_SIZE_RATIO`] over this factor, without
/// passing it times this factor.
pub const CLOSE_SIZE_FACTOR: f64 = 1.25;

/// Weights of [`InstanceCandidate::fit`], the ranking's logistic model (`docs/decisions.md`,
/// "Ranking the instances by the model's views"): per unit of ln(pixels), …
pub const RANK_WEIGHT_PIXELS: f64 = 0.52;
/// … per unit of |ln(size ratio / [`TYPICAL_SIZE_RATIO`])|, …
pub const RANK_WEIGHT_SIZE: f64 = 2.63;
/// … for an instance the border cuts off, …
pub const RANK_WEIGHT_TRUNCATED: f64 = 0.73;
/// … and per unit of [`InstanceCandidate::shape_distance`], which counts up to
/// [`RANK_MAX_SHAPE_DISTANCE`] (an instance of no spread is infinitely far).
pub const RANK_WEIGHT_SHAPE: f64 = 2.59;
/// One value with the clutter confidence's `shape_distance` cap
/// ([`ic_eval::clutter::MAX_SHAPE_DISTANCE`]).
pub const RANK_MAX_SHAPE_DISTANCE: f64 = ic_eval::clutter::MAX_SHAPE_DISTANCE;

impl InstanceCandidate {
    /// A candidate of `mask`, whose back-projected `points` (normalised units, camera frame,
    /// at least one) fix its extent against the diameter of `object` and its shape against
    /// the object's views; `frame` is the sensor's ([`sensor_frame`]).
    fn new(
        mask: Mask,
        points: &[Vec3],
        score: f32,
        object: &Object,
        frame: (u32, u32, u32, u32),
        parts: usize,
        cut: bool,
    ) -> InstanceCandidate {
        let diameter = object.diameter.max(1e-9);
        let extent = visible_extent(points);
        let size_ratio = extent / diameter;
        InstanceCandidate {
            score,
            pixels: mask.data.iter().filter(|&&b| b).count(),
            extent,
            size_ratio,
            plausible: (MIN_SIZE_RATIO..=MAX_SIZE_RATIO).contains(&size_ratio),
            shape_distance: object.view_spreads().distance(points, diameter),
            truncated: touches_border(&mask, frame),
            cut,
            parts,
            input: 0,
            mask,
        }
    }

    /// How well the candidate fits the model, the ranking's order among candidates of one
    /// kind (higher first): a logistic model of "this is the target's instance" fitted on
    /// validation clutter scenes (`docs/decisions.md`, "Ranking the instances by the model's
    /// views"), on ln(pixels) (the nearest, least hidden instance), the size ratio's distance
    /// to [`TYPICAL_SIZE_RATIO`] in log scale, whether the border cuts it off, and
    /// [`Self::shape_distance`] (capped at [`RANK_MAX_SHAPE_DISTANCE`]). Only differences
    /// between candidates of one image matter: the image's size shifts every candidate's
    /// ln(pixels) alike.
    pub fn fit(&self) -> f64 {
        let [pixels, size, truncated, shape] = self.rank_features();
        RANK_WEIGHT_PIXELS * pixels
            - RANK_WEIGHT_SIZE * size
            - RANK_WEIGHT_TRUNCATED * truncated
            - RANK_WEIGHT_SHAPE * shape
    }

    /// What [`Self::fit`] weighs: ln(pixels), |ln(size ratio / [`TYPICAL_SIZE_RATIO`])|, 1
    /// when the border cuts the instance off (else 0), and [`Self::shape_distance`] capped at
    /// [`RANK_MAX_SHAPE_DISTANCE`].
    pub fn rank_features(&self) -> [f64; 4] {
        [
            (self.pixels.max(1) as f64).ln(),
            (self.size_ratio / TYPICAL_SIZE_RATIO).ln().abs(),
            f64::from(u8::from(self.truncated)),
            self.shape_distance.min(RANK_MAX_SHAPE_DISTANCE),
        ]
    }

    /// Ranking key: plausible first; the network's instances (and joined parts) before
    /// pieces cut from heaps; those of the network's own input size before an extra size's
    /// ([`InstanceCandidate::input`]); then by [`Self::fit`]; then the segmentation score.
    fn rank_key(&self) -> (bool, bool, bool, f64, f32) {
        (
            self.plausible,
            !self.cut,
            self.input == 0,
            self.fit(),
            self.score,
        )
    }

    /// The candidates to register, in order, from `ranked` (sorted by [`Self::rank`]): the
    /// network's instances (and joined parts) that fit; when none does, the largest one that
    /// is too large (its crop may still hold the object); then the pieces cut from heaps
    /// (reached only when the others gave no `ok` pose: the search stops at the first).
    /// At most `per_group` of the first two kinds and `per_group` pieces (0 = all).
    fn to_try(ranked: &[InstanceCandidate], per_group: usize) -> Vec<&InstanceCandidate> {
        let per_group = if per_group == 0 {
            usize::MAX
        } else {
            per_group
        };
        let own: Vec<&InstanceCandidate> =
            ranked.iter().filter(|c| c.plausible && !c.cut).collect();
        let fallback: Vec<&InstanceCandidate> = if own.is_empty() {
            ranked
                .iter()
                .filter(|c| c.size_ratio > MAX_SIZE_RATIO && !c.cut)
                .take(1)
                .collect()
        } else {
            Vec::new()
        };
        let pieces = ranked.iter().filter(|c| c.plausible && c.cut);
        own.into_iter()
            .chain(fallback)
            .take(per_group)
            .chain(pieces.take(per_group))
            .collect()
    }

    /// Sorts `candidates` best first: plausible ones first, the network's instances (and
    /// joined parts) before pieces cut from heaps, the network's own input size before an
    /// extra size's, then by [`Self::fit`], then by the segmentation score.
    pub fn rank(candidates: &mut [InstanceCandidate]) {
        candidates.sort_by(|a, b| {
            let (ka, kb) = (a.rank_key(), b.rank_key());
            kb.0.cmp(&ka.0)
                .then(kb.1.cmp(&ka.1))
                .then(kb.2.cmp(&ka.2))
                .then(kb.3.total_cmp(&ka.3))
                .then(kb.4.total_cmp(&ka.4))
        });
    }
}

/// Which of the segmentation network's instances [`Pipeline::register_instances`] registers
/// and returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum InstanceSearch {
    /// The best [`PipelineOptions::instance_tries`] until one is `ok`; all registered, best
    /// first.
    FirstOk,
    /// Every plausible one; the `ok` ones (or the best `uncertain` one), one per object
    /// ([`all_ok_choice`]).
    AllOk,
    /// The best `limit` plausible ones (0 = all), every registration, best first, unfiltered.
    Every { limit: usize },
}

/// What [`all_ok_choice`] reads of one registration of the `--all` search.
#[derive(Clone, Copy, Debug)]
struct AllEntry {
    verdict: Verdict,
    confidence: f64,
    /// Its whole projection explains the depth map ([`crate::verify::WholeView::consistent`];
    /// true when it was not measured).
    consistent: bool,
}

/// Which registrations of the `--all` search (best first) it returns, before poses of the
/// same object are merged: every `ok` one, and every `uncertain` one whose confidence reaches
/// `min_confidence` and whose whole projection is consistent with the depth map; when there
/// is none, the first `uncertain` one that is consistent, else the first that is not
/// `not_found` (a bin of parts wants confident picks; an `uncertain` pose that does not
/// explain the depth where its model would be seen is not one, while an `ok` one is kept:
/// on synthetic clutter the `ok` poses the whole view doubts were right, slightly off or over
/// the sensor's holes; `docs/decisions.md`).
fn all_ok_choice(entries: &[AllEntry], min_confidence: Option<f64>) -> Vec<usize> {
    let wanted = |e: &AllEntry| {
        e.verdict == Verdict::Ok
            || (e.verdict == Verdict::Uncertain
                && e.consistent
                && min_confidence.is_some_and(|m| e.confidence >= m))
    };
    let chosen: Vec<usize> = (0..entries.len())
        .filter(|&i| wanted(&entries[i]))
        .collect();
    if !chosen.is_empty() {
        return chosen;
    }
    let found = |e: &&AllEntry| e.verdict != Verdict::NotFound;
    entries
        .iter()
        .position(|e| found(&e) && e.consistent)
        .or_else(|| entries.iter().position(|e| found(&e)))
        .into_iter()
        .collect()
}

/// Seconds spent in each stage of one registration.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageSeconds {
    pub segmentation_network: f64,
    pub segmentation_post: f64,
    /// Erosion, back-projection, crop, voxelising, sampling.
    pub observed_points: f64,
    pub pose_network: f64,
    /// Ranking the one-shot hypotheses by the point-distance confidence.
    pub ranking: f64,
    pub icp: f64,
    /// Render-and-compare of the verified hypotheses.
    pub verification: f64,
    /// Everything from the depth map (or points) in memory to the final pose.
    pub total: f64,
}

/// Where the object's pixels came from.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SegmentationSummary {
    /// `network` or `mask` (given by the user).
    pub source: &'static str,
    /// The network's instance score (mean object probability), when it ran.
    pub score: Option<f32>,
    /// Pixels of the mask (before erosion).
    pub pixels: usize,
}

/// ICP's result.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct IcpSummary {
    pub fitness: f64,
    pub inlier_rmse: f64,
    pub iterations: usize,
}

/// The result of one registration.
#[derive(Clone, Debug, Serialize)]
pub struct Registration {
    /// Model → camera in the model's own units (the depth map's units).
    pub pose: Pose,
    /// Model → camera in normalised units (the network's).
    pub pose_normalised: Pose,
    /// The network's one-shot estimate (normalised units), before refinement.
    pub one_shot_normalised: Pose,
    /// In [0, 1]. Verified registrations: the probability that the pose is right (ADD-S below
    /// 0.1 of the diameter), the calibration ([`verified_calibration`]) of the [`evidence`];
    /// when the segmentation network chose the pixels among several instances, the clutter
    /// confidence ([`clutter_confidence`]) of its numbers ([`Registration::calibration`]).
    /// Unverified: the fraction of the observed object voxels within [`MATCH_DISTANCE`]
    /// (normalised) of the model at the final pose.
    pub confidence: f64,
    /// Which calibration turned the verification into the confidence.
    pub calibration: CalibrationUsed,
    /// What the confidence says of the pose.
    pub verdict: Verdict,
    /// The render-and-compare score of the pose, when hypotheses were verified.
    pub verification: Option<crate::verify::Score>,
    /// Every verified hypothesis in the order they were ranked (the first is the network's
    /// unrotated estimate): its render-and-compare score and refined pose (normalised units).
    pub verified: Vec<VerifiedHypothesis>,
    /// The best score of a verified pose that is not equivalent to the chosen one (ADD-S
    /// between them ≥ 0.1·diameter), 0 when there is none.
    pub rival_score: Option<f64>,
    /// What the confidence is calibrated from: [`evidence`] of the score and the rival.
    pub evidence: Option<f64>,
    /// One-shot hypotheses made, and how many were refined and verified.
    pub hypotheses_made: usize,
    pub hypotheses_verified: usize,
    pub segmentation: Option<SegmentationSummary>,
    /// Which of the segmentation's instances this is, when the network chose the pixels.
    pub instance: Option<InstanceChoice>,
    /// Object points after erosion and crop, and after voxelising.
    pub object_points: usize,
    pub object_voxels: usize,
    /// Correspondences the pose rests on, and their mean probability.
    pub inlier_count: usize,
    pub assignment_confidence: f32,
    pub icp: Option<IcpSummary>,
    /// How the model's whole projection at the pose agrees with the depth map
    /// ([`crate::verify::whole_view`]): for the pose a depth map's registration returns and
    /// for every instance of `register --all`'s search; `None` for point inputs.
    pub whole_view: Option<crate::verify::WholeView>,
    pub seconds: StageSeconds,
    /// The observed object voxels (camera frame, normalised units).
    #[serde(skip)]
    pub observed: Vec<Vec3>,
    /// The object mask used (before erosion), for depth inputs.
    #[serde(skip)]
    pub mask: Option<Mask>,
}

/// How a registration's confidence was obtained ([`Registration::calibration`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationUsed {
    /// Not verified: the point-distance confidence, not a probability.
    None,
    /// The pixels were given (a mask, points), or the segmentation network found one instance
    /// only: [`verified_calibration`] of the [`evidence`], fitted on single objects.
    Object,
    /// The segmentation network chose the pixels among several instances:
    /// [`clutter_confidence`] of the registration's numbers, fitted on clutter scenes.
    Segmentation,
}

impl CalibrationUsed {
    /// `none`, `object` or `segmentation` (as serialised).
    pub fn as_str(self) -> &'static str {
        match self {
            CalibrationUsed::None => "none",
            CalibrationUsed::Object => "object",
            CalibrationUsed::Segmentation => "segmentation",
        }
    }
}

/// Which segmentation instance a registration used ([`Registration::instance`]).
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct InstanceChoice {
    /// Its rank among the candidates (0 = the best size fit).
    pub rank: usize,
    /// How many instances scored above the segmentation threshold.
    pub candidates: usize,
    /// Its visible extent over the model's diameter.
    pub size_ratio: f64,
    /// How far its spreads lie from the nearest of the model's views
    /// ([`InstanceCandidate::shape_distance`]).
    pub shape_distance: f64,
    /// How many of the network's instances it joins ([`InstanceCandidate::parts`]).
    pub parts: usize,
    /// Whether its mask reaches the sensor frame's border ([`InstanceCandidate::truncated`]).
    pub truncated: bool,
    /// Whether it is a piece cut from a heap ([`InstanceCandidate::cut`]).
    pub cut: bool,
    /// Whether the one-object network's second opinion ([`Pipeline::with_one_object_seg`])
    /// chose it (`candidates` and `rank` then count that network's instances) or confirmed
    /// it as a lone object (the single-object calibration then applies).
    pub one_object_network: bool,
    /// Which input size of the segmentation network found it ([`InstanceCandidate::input`]).
    pub input: usize,
}

/// One verified hypothesis of [`Registration::verified`].
#[derive(Clone, Copy, Debug, Serialize)]
pub struct VerifiedHypothesis {
    pub score: f64,
    /// [`crate::verify::Score::misfit`] of the pose: the mean depth residual of the pixels it
    /// explains, in units of their tolerance.
    pub misfit: f64,
    /// RMS distance (normalised units) of the ICP pairs that refined it, when ICP ran.
    pub icp_rmse: Option<f64>,
    /// Model → camera, normalised units.
    pub pose_normalised: Pose,
    /// Which pose network made it: 0 the main one, 1 the second
    /// ([`Pipeline::with_second_pose`]).
    pub network: usize,
}

/// The rotation hypotheses of `incontext register` (and of [`PipelineBuilder`]) by default:
/// the 24 rotations of the cube group.
pub const DEFAULT_ROTATIONS: usize = 24;

/// The networks and settings of the pipeline. Made by [`Pipeline::builder`].
///
/// All its inputs and outputs follow the workspace's conventions: poses map model to camera
/// coordinates (`x_cam = R·x_model + t`, OpenCV camera frame: x right, y down, z forward),
/// in the mesh's own units (those of the depth map) or, where a name says so, in normalised
/// object units (the mesh scaled to [-1, 1] on its longest side).
pub struct Pipeline {
    pose: LoadedPose,
    /// A second pose network whose hypotheses join the main one's in verification
    /// ([`Pipeline::with_second_pose`]).
    pose_second: Option<LoadedPose>,
    seg: Option<LoadedSeg>,
    /// The one-object network, asked when the instances of `seg` gave no `ok` pose
    /// ([`Pipeline::with_one_object_seg`]).
    seg_one_object: Option<LoadedSeg>,
    pub options: PipelineOptions,
    /// The threads registrations run on (`None`: rayon's global pool).
    pool: Option<rayon::ThreadPool>,
}

/// How to load a [`Pipeline`]: which networks, which settings. The defaults are those of
/// `incontext register`: the shipped softmax pose network with its second
/// ([`Pipeline::with_second_pose`]), the shipped clutter segmentation
/// network with the one-object network as its second opinion ([`Pipeline::with_one_object_seg`]), ICP,
/// [`DEFAULT_ROTATIONS`] rotation hypotheses verified by render-and-compare (the best 8), one
/// hypothesis per copy, the global thread pool.
///
/// ```no_run
/// use incontext::{Head, Pipeline, Refine};
/// # fn main() -> Result<(), incontext::PipelineError> {
/// let pipeline = Pipeline::builder()
///     .pose_model("models/pose-cpu-softmax.safetensors")
///     .head(Head::Softmax)
///     .refine(Refine::Icp)
///     .rotations(24)
///     .threads(2)
///     .build()?;
/// # Ok(()) }
/// ```
#[derive(Clone, Debug)]
pub struct PipelineBuilder {
    pose_model: Option<PathBuf>,
    second_pose_model: Option<PathBuf>,
    second_pose: bool,
    head: Option<Head>,
    seg_model: Option<PathBuf>,
    segmentation: bool,
    options: PipelineOptions,
    threads: Option<usize>,
    /// `Some`: every pose network's attention keys, whatever its checkpoint says.
    attention_keys: Option<Option<usize>>,
}

impl Default for PipelineBuilder {
    fn default() -> Self {
        PipelineBuilder {
            pose_model: None,
            second_pose_model: None,
            second_pose: true,
            head: None,
            seg_model: None,
            segmentation: true,
            options: PipelineOptions {
                rotations: DEFAULT_ROTATIONS,
                ..PipelineOptions::default()
            },
            threads: None,
            attention_keys: None,
        }
    }
}

impl PipelineBuilder {
    /// A pose checkpoint (written by `cargo xtask train-pose`) instead of the shipped network.
    pub fn pose_model(mut self, path: impl Into<PathBuf>) -> Self {
        self.pose_model = Some(path.into());
        self
    }

    /// The correspondence head: picks the shipped network of that head, or, with
    /// [`PipelineBuilder::pose_model`], requires the checkpoint to have it. Unset: the shipped
    /// softmax network, or the checkpoint's own head.
    pub fn head(mut self, head: Head) -> Self {
        self.head = Some(head);
        self
    }

    /// A second pose checkpoint of the same head, whose hypotheses join the main network's in
    /// verification ([`Pipeline::with_second_pose`]), instead of the shipped second network.
    pub fn second_pose_model(mut self, path: impl Into<PathBuf>) -> Self {
        self.second_pose_model = Some(path.into());
        self
    }

    /// Whether to load a second pose network (default true): the one of
    /// [`PipelineBuilder::second_pose_model`], else the shipped one of the head
    /// ([`crate::models::POSE_SOFTMAX_SECOND`] for softmax; none for OT) unless
    /// [`PipelineBuilder::pose_model`] replaced the main network (a checkpoint given alone is
    /// used alone).
    pub fn second_pose(mut self, load: bool) -> Self {
        self.second_pose = load;
        self
    }

    /// A segmentation checkpoint instead of the shipped networks (it is then the only one:
    /// no one-object second opinion).
    pub fn seg_model(mut self, path: impl Into<PathBuf>) -> Self {
        self.seg_model = Some(path.into());
        self
    }

    /// Whether to load the segmentation network (default true). Without it, depth inputs need
    /// a mask; points inputs never need it.
    pub fn segmentation(mut self, load: bool) -> Self {
        self.segmentation = load;
        self
    }

    /// All the settings at once (replaces those set before; the rotation default of the
    /// builder, [`DEFAULT_ROTATIONS`], is `options.rotations` then).
    pub fn options(mut self, options: PipelineOptions) -> Self {
        self.options = options;
        self
    }

    /// Every pose network attends over `keys` farthest-point samples of each cloud (`None`:
    /// every point, as DCP and the paper), whatever its checkpoint says
    /// ([`ic_pose::NetConfig::pooled_keys`]; unset: each checkpoint's own). The weights are
    /// the same either way: fewer keys are faster (`docs/decisions.md`, "Attention over
    /// pooled keys").
    pub fn attention_keys(mut self, keys: Option<usize>) -> Self {
        self.attention_keys = Some(keys);
        self
    }

    /// Refinement after the one-shot estimate ([`PipelineOptions::refine`]).
    pub fn refine(mut self, refine: Refine) -> Self {
        self.options.refine = refine;
        self
    }

    /// Rotation hypotheses: 1, 12, 24 or 60 ([`PipelineOptions::rotations`]).
    pub fn rotations(mut self, rotations: usize) -> Self {
        self.options.rotations = rotations;
        self
    }

    /// Pose hypotheses of the unverified pipeline ([`PipelineOptions::hypotheses`]).
    pub fn hypotheses(mut self, hypotheses: usize) -> Self {
        self.options.hypotheses = hypotheses;
        self
    }

    /// Hypotheses refined and verified ([`PipelineOptions::verify_top`]).
    pub fn verify_top(mut self, verify_top: usize) -> Self {
        self.options.verify_top = verify_top;
        self
    }

    /// Rotated copies kept after the DGCNN ([`PipelineOptions::sweep_keep`]; 0 = all).
    pub fn sweep_keep(mut self, sweep_keep: usize) -> Self {
        self.options.sweep_keep = sweep_keep;
        self
    }

    /// Sampled poses per rotated copy ([`PipelineOptions::sampled_hypotheses`]).
    pub fn sampled_hypotheses(mut self, sampled_hypotheses: usize) -> Self {
        self.options.sampled_hypotheses = sampled_hypotheses;
        self
    }

    /// Passes of the network over the verified hypotheses
    /// ([`PipelineOptions::network_passes`]).
    pub fn network_passes(mut self, network_passes: usize) -> Self {
        self.options.network_passes = network_passes;
        self
    }

    /// Hypotheses the second pass takes ([`PipelineOptions::pass_top`]; 0 = all verified).
    pub fn pass_top(mut self, pass_top: usize) -> Self {
        self.options.pass_top = pass_top;
        self
    }

    /// Instances tried before giving up ([`PipelineOptions::instance_tries`]; 0 = every one
    /// that fits).
    pub fn instance_tries(mut self, instance_tries: usize) -> Self {
        self.options.instance_tries = instance_tries;
        self
    }

    /// `register --all` also returns `uncertain` instances of at least this confidence
    /// ([`PipelineOptions::all_min_confidence`]).
    pub fn all_min_confidence(mut self, confidence: f64) -> Self {
        self.options.all_min_confidence = Some(confidence);
        self
    }

    /// Registrations run on their own pool of `threads` threads (at least 1) instead of
    /// rayon's global pool. Loading and [`Object::from_mesh`] are not affected.
    pub fn threads(mut self, threads: usize) -> Self {
        self.threads = Some(threads);
        self
    }

    /// Loads the networks (the shipped ones are embedded in the binary when they existed at
    /// build time) and checks the settings.
    ///
    /// Errors: [`PipelineError::Input`] for a checkpoint that cannot be read or lacks the asked
    /// head, a shipped network that is neither embedded nor in the workspace, a rotation count
    /// other than 1, 12, 24 or 60, zero threads; [`PipelineError::Internal`] when the threads
    /// cannot be started.
    pub fn build(self) -> Result<Pipeline> {
        crate::verify::rotation_set(self.options.rotations)
            .map_err(|e| PipelineError::input(format!("rotations: {e}")))?;
        let pool = match self.threads {
            None => None,
            Some(0) => {
                return Err(PipelineError::input(
                    "threads: 0 is not a number of threads (at least 1)",
                ));
            }
            Some(t) => Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .map_err(|e| PipelineError::internal(format!("starting {t} threads: {e}")))?,
            ),
        };
        let keys = |p: crate::models::LoadedPose| match self.attention_keys {
            Some(k) => p.with_attention_keys(k),
            None => Ok(p),
        };
        let pose = keys(crate::models::load_pose(
            self.pose_model.as_deref(),
            self.head,
        )?)?;
        let (seg, one_object) = if self.segmentation {
            let one_object = match self.seg_model {
                Some(_) => None,
                None => crate::models::load_seg_one_object()?,
            };
            (
                Some(crate::models::load_seg(self.seg_model.as_deref())?),
                one_object,
            )
        } else {
            (None, None)
        };
        let head = pose.estimator.config().net.head;
        let second = match (self.second_pose, &self.second_pose_model, &self.pose_model) {
            (false, _, _) | (true, None, Some(_)) => None,
            (true, path, _) => crate::models::load_pose_second(path.as_deref(), head)?
                .map(keys)
                .transpose()?,
        };
        let mut pipeline = Pipeline::new(pose, seg, self.options);
        if let Some(second) = second {
            pipeline = pipeline.with_second_pose(second)?;
        }
        pipeline.seg_one_object = one_object;
        pipeline.pool = pool;
        Ok(pipeline)
    }
}

/// A network's attention keys as a run's configuration prints them: the count, or `"all"`.
fn keys_json(keys: Option<usize>) -> serde_json::Value {
    keys.map_or_else(|| serde_json::json!("all"), |k| serde_json::json!(k))
}

impl Pipeline {
    /// How to load a pipeline; `Pipeline::builder().build()` is what `incontext register`
    /// loads with its default flags.
    pub fn builder() -> PipelineBuilder {
        PipelineBuilder::default()
    }

    /// A pipeline over networks already loaded ([`crate::models::load_pose`],
    /// [`crate::models::load_seg`]), on rayon's global pool. Without a segmentation network,
    /// depth inputs need a mask.
    pub fn new(mut pose: LoadedPose, seg: Option<LoadedSeg>, options: PipelineOptions) -> Self {
        // The pipeline refines itself (onto the dense model, with every object voxel).
        pose.estimator.recovery.refine = Refine::None;
        Pipeline {
            pose,
            pose_second: None,
            seg,
            seg_one_object: None,
            options,
            pool: None,
        }
    }

    /// Adds a one-object segmentation network (trained on scenes holding one object, e.g.
    /// [`crate::models::load_seg_one_object`]) as a second opinion: when no instance of the
    /// main network gives an `ok` pose, its best instance of a fitting size that the main
    /// network's tries did not already cover is registered too, and its pose is kept when it
    /// is `ok` (or when the main network gave none). A clutter network cuts a lone object of
    /// several parts (a mug and its handle, a table and its legs) into instances none of which
    /// is the object; a one-object network keeps it whole. When the one-object network sees a
    /// single instance in the image, its pose (or the main network's pose of the same pixels)
    /// gets the single-object calibration. Costs nothing when the first tries give an `ok`
    /// pose.
    pub fn with_one_object_seg(mut self, seg: LoadedSeg) -> Self {
        self.seg_one_object = Some(seg);
        self
    }

    /// Adds a second pose network of the same head: in the verified pipeline (`register`'s
    /// default, and the sweep without ICP) its own rotated copies, ranking and passes make a
    /// second set of up to [`PipelineOptions::verify_top`] hypotheses that render-and-compare
    /// verifies beside the main network's, the best score winning (ties: the main network's).
    /// Two networks trained differently fail on different views, so the right pose is more
    /// often among the verified ones (`docs/decisions.md`, "Two pose networks"); the network
    /// part of a registration takes twice as long. The one-pass methods use the main network
    /// alone.
    ///
    /// Errors: [`PipelineError::Input`] when its head differs from the main network's.
    pub fn with_second_pose(mut self, mut pose: LoadedPose) -> Result<Self> {
        let (main, second) = (self.head(), pose.estimator.config().net.head);
        if main != second {
            return Err(PipelineError::input(format!(
                "{}: the second pose model has a {} head, the main one {}",
                pose.source,
                second.as_str(),
                main.as_str()
            )));
        }
        pose.estimator.recovery.refine = Refine::None;
        self.pose_second = Some(pose);
        Ok(self)
    }

    /// Where the second pose network came from, when loaded ([`Pipeline::with_second_pose`]).
    pub fn second_pose_source(&self) -> Option<&str> {
        self.pose_second.as_ref().map(|p| p.source.as_str())
    }

    /// Runs `f` on the pipeline's threads (or the caller's pool).
    fn in_pool<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        match &self.pool {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }

    pub fn head(&self) -> Head {
        self.pose.estimator.config().net.head
    }

    /// Where the pose network came from.
    pub fn pose_source(&self) -> &str {
        &self.pose.source
    }

    /// Where the segmentation network came from, when loaded.
    pub fn seg_source(&self) -> Option<&str> {
        self.seg.as_ref().map(|s| s.source.as_str())
    }

    /// Where the one-object second opinion came from, when loaded
    /// ([`Pipeline::with_one_object_seg`]).
    pub fn seg_one_object_source(&self) -> Option<&str> {
        self.seg_one_object.as_ref().map(|s| s.source.as_str())
    }

    /// M and N: the model and observed point counts the pose network was trained with.
    pub fn point_counts(&self) -> (usize, usize) {
        let t = &self.pose.estimator.config().train;
        (t.model_points, t.observed_points)
    }

    /// The post-processing settings (erosions, crop) — the segmentation network's, or the
    /// paper's defaults without one.
    pub fn post_config(&self) -> PostConfig {
        self.seg
            .as_ref()
            .map(|s| s.segmenter.config().post.clone())
            .unwrap_or_default()
    }

    /// The configuration printed with every run.
    pub fn describe(&self) -> serde_json::Value {
        let (m, n) = self.point_counts();
        serde_json::json!({
            "pose_model": self.pose.source,
            "second_pose_model": self.second_pose_source(),
            "head": self.head().as_str(),
            "seg_model": self.seg_source(),
            "seg_one_object_model": self.seg_one_object_source(),
            "model_points": m,
            "observed_points": n,
            "attention_keys": keys_json(self.pose.attention_keys()),
            "second_attention_keys": self.pose_second.as_ref().map(|p| keys_json(p.attention_keys())),
            "pipeline": self.options,
            "post": self.post_config(),
        })
    }

    /// Registers `object` in `depth` (the object's own units; 0 = no return) seen through
    /// `intrinsics`. `mask` (the object's pixels) replaces the segmentation network.
    ///
    /// Errors: bad input (sizes, an empty mask, no segmentation network and no mask), object
    /// not found (segmentation finds nothing, or too few object points).
    pub fn register_depth(
        &self,
        object: &Object,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        mask: Option<&Mask>,
        seed: u64,
    ) -> Result<Registration> {
        self.in_pool(|| {
            let clock = Instant::now();
            let depth_n = object.normalised_depth(depth);
            self.register_depth_inner(object, &depth_n, intrinsics, mask, seed, clock)
        })
    }

    /// [`Pipeline::register_depth`] for a depth map already in normalised units (the depth in
    /// the object's units divided by its normalisation scale).
    pub fn register_depth_normalised(
        &self,
        object: &Object,
        depth_normalised: &DepthImage,
        intrinsics: &Intrinsics,
        mask: Option<&Mask>,
        seed: u64,
    ) -> Result<Registration> {
        self.in_pool(|| {
            self.register_depth_inner(
                object,
                depth_normalised,
                intrinsics,
                mask,
                seed,
                Instant::now(),
            )
        })
    }

    fn register_depth_inner(
        &self,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
        mask: Option<&Mask>,
        seed: u64,
        clock: Instant,
    ) -> Result<Registration> {
        check_depth_input(depth_n, intrinsics)?;
        let seconds = StageSeconds::default();
        if let Some(m) = mask {
            m.check_size(intrinsics.width, intrinsics.height)
                .map_err(|e| PipelineError::input(format!("mask: {e}")))?;
            let pixels = m.data.iter().filter(|&&b| b).count();
            if pixels == 0 {
                return Err(PipelineError::input("the mask is empty (no pixel is set)"));
            }
            let summary = SegmentationSummary {
                source: "mask",
                score: None,
                pixels,
            };
            let mut r = self.register_mask(
                object,
                depth_n,
                intrinsics,
                m.clone(),
                summary,
                seed,
                self.options.network_passes,
                seconds,
                clock,
            )?;
            r.whole_view = self.whole_view(object, depth_n, intrinsics, &r);
            return Ok(r);
        }
        let mut all = self.register_instances(
            object,
            depth_n,
            intrinsics,
            seed,
            clock,
            InstanceSearch::FirstOk,
        )?;
        // The returned pose's whole view is reported. The search measured it already for a
        // pose on an instance chosen among several (its agreement is one of the clutter
        // confidence's numbers); a lone instance's is measured here.
        let mut r = all.remove(0);
        if r.whole_view.is_none() {
            r.whole_view = self.whole_view(object, depth_n, intrinsics, &r);
        }
        Ok(r)
    }

    /// Every instance of the object in `depth` (normalised units, as
    /// [`Pipeline::register_depth_normalised`]): each instance the segmentation network finds
    /// whose size fits the model is registered, and those whose verdict is `ok` (or whose
    /// confidence reaches [`PipelineOptions::all_min_confidence`] and whose whole projection
    /// is consistent with the depth map, [`Registration::whole_view`]) are returned, best
    /// first (verdict, confidence, render-and-compare score); when there is none, the best
    /// consistent `uncertain` one alone (else the best one). Two registrations of one object
    /// (ADD-S between their poses below 0.1 of the diameter) keep the better. An empty list
    /// when none is found.
    pub fn register_depth_all_normalised(
        &self,
        object: &Object,
        depth_normalised: &DepthImage,
        intrinsics: &Intrinsics,
        seed: u64,
    ) -> Result<Vec<Registration>> {
        self.instances_or_none(
            object,
            depth_normalised,
            intrinsics,
            seed,
            InstanceSearch::AllOk,
        )
    }

    /// [`Pipeline::register_instances`] on the pipeline's threads, with the input checked; an
    /// empty list instead of a not-found error.
    fn instances_or_none(
        &self,
        object: &Object,
        depth_normalised: &DepthImage,
        intrinsics: &Intrinsics,
        seed: u64,
        search: InstanceSearch,
    ) -> Result<Vec<Registration>> {
        self.in_pool(|| {
            check_depth_input(depth_normalised, intrinsics)?;
            match self.register_instances(
                object,
                depth_normalised,
                intrinsics,
                seed,
                Instant::now(),
                search,
            ) {
                Ok(found) => Ok(found),
                Err(PipelineError::NotFound(_)) => Ok(Vec::new()),
                Err(e) => Err(e),
            }
        })
    }

    /// The registration of each of the best `limit` instances (0 = all) whose size fits the
    /// model (or of the one too-large instance when none fits, as `register` does), whatever
    /// its verdict, best first (verdict, confidence, render-and-compare score); `depth` in
    /// normalised units as [`Pipeline::register_depth_normalised`]. For studying the verdict
    /// in clutter: [`Pipeline::register_depth_all_normalised`] keeps only the `ok` ones of
    /// these. An empty list when no instance fits or can be registered.
    pub fn register_every_instance_normalised(
        &self,
        object: &Object,
        depth_normalised: &DepthImage,
        intrinsics: &Intrinsics,
        limit: usize,
        seed: u64,
    ) -> Result<Vec<Registration>> {
        self.instances_or_none(
            object,
            depth_normalised,
            intrinsics,
            seed,
            InstanceSearch::Every { limit },
        )
    }

    /// [`Pipeline::register_depth_all_normalised`] for a depth map in the object's units.
    pub fn register_depth_all(
        &self,
        object: &Object,
        depth: &DepthImage,
        intrinsics: &Intrinsics,
        seed: u64,
    ) -> Result<Vec<Registration>> {
        self.register_depth_all_normalised(
            object,
            &object.normalised_depth(depth),
            intrinsics,
            seed,
        )
    }

    /// The segmentation network's instances in `depth_n`, scored above its threshold, with
    /// their size fit to `object`, best first ([`InstanceCandidate`]).
    pub fn instance_candidates(
        &self,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
    ) -> Result<Vec<InstanceCandidate>> {
        let seg = self.seg.as_ref().ok_or_else(|| {
            PipelineError::input("no segmentation network loaded and no mask given")
        })?;
        Self::candidates_of(seg, object, depth_n, intrinsics)
    }

    /// [`Pipeline::instance_candidates`] of the network `seg`: the candidates of each of its
    /// input sizes ([`ic_seg::PostConfig::extra_inputs`]) pooled, the network's own size
    /// first; a candidate of a later size whose mask is nearly one of an earlier candidate's
    /// (IoU ≥ [`DUPLICATE_IOU`]) is dropped.
    fn candidates_of(
        seg: &LoadedSeg,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
    ) -> Result<Vec<InstanceCandidate>> {
        let post = &seg.segmenter.config().post;
        let per_input = seg.segmenter.instances_per_input(depth_n, intrinsics)?;
        let best_score = per_input.iter().flatten().map(|i| i.score).reduce(f32::max);
        let sizes = per_input.len();
        let mut out: Vec<InstanceCandidate> = Vec::new();
        // The pixels of the candidates of the sizes before the current one (none needed
        // without extra sizes).
        let mut earlier: Vec<PixelSet> = Vec::new();
        for (input, found) in per_input.into_iter().enumerate() {
            let mut this_size = Vec::new();
            for mut c in Self::partition_candidates(post, found, object, depth_n, intrinsics)? {
                if sizes > 1 {
                    let pixels = PixelSet::of(&c.mask);
                    if earlier.iter().any(|k| k.iou(&pixels) >= DUPLICATE_IOU) {
                        continue;
                    }
                    this_size.push(pixels);
                }
                c.input = input;
                out.push(c);
            }
            earlier.extend(this_size);
        }
        if out.is_empty() {
            return Err(PipelineError::not_found(format!(
                "object not found: the segmentation found no object instance scoring above {} (best score {})",
                post.score_threshold,
                best_score.map_or("none".into(), |s| format!("{s:.3}"))
            )));
        }
        InstanceCandidate::rank(&mut out);
        Ok(out)
    }

    /// The candidates of one input size's instances `found`: the network's instances scoring
    /// above the threshold (or standing off the support), touching parts joined, pieces cut
    /// from heaps; unranked.
    fn partition_candidates(
        post: &ic_seg::PostConfig,
        found: Vec<ic_seg::post::Instance>,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
    ) -> Result<Vec<InstanceCandidate>> {
        let diameter = object.diameter.max(1e-9);
        let frame = sensor_frame(depth_n);
        let mut out = Vec::new();
        let mut clouds: Vec<Vec<Vec3>> = Vec::new();
        // Instances standing out of the support planes are kept whatever the network's score:
        // they are where the network saw no object.
        for inst in found
            .into_iter()
            .filter(|i| i.score > post.score_threshold || i.off_support)
        {
            let mask = post.refine(inst.mask, depth_n);
            let points = intrinsics.back_project_depth(depth_n, Some(&mask))?;
            if points.len() < 3 {
                continue;
            }
            out.push(InstanceCandidate::new(
                mask, &points, inst.score, object, frame, 1, false,
            ));
            clouds.push(points);
        }
        // Touching instances each too small to be the object that together fit its size: a
        // lone object the network cut into parts.
        if out.len() > 1 {
            let masks: Vec<&Mask> = out.iter().map(|c| &c.mask).collect();
            let touching =
                crate::parts::contacts(&masks, depth_n, (PART_DEPTH_GAP * diameter) as f32);
            let ratios: Vec<f64> = out.iter().map(|c| c.size_ratio).collect();
            let union_of = |g: &[usize]| -> Vec<Vec3> {
                g.iter().flat_map(|&i| clouds[i].iter().copied()).collect()
            };
            let groups = crate::parts::merged_groups(
                &ratios,
                &touching,
                TYPICAL_SIZE_RATIO / CLOSE_SIZE_FACTOR,
                TYPICAL_SIZE_RATIO * CLOSE_SIZE_FACTOR,
                |g| visible_extent(&union_of(g)) / diameter,
            );
            for g in groups {
                let mut mask = out[g[0]].mask.clone();
                for &i in &g[1..] {
                    for (m, &o) in mask.data.iter_mut().zip(&out[i].mask.data) {
                        *m |= o;
                    }
                }
                let union = union_of(&g);
                let pixels: usize = g.iter().map(|&i| out[i].pixels).sum();
                let score = g
                    .iter()
                    .map(|&i| out[i].score * out[i].pixels as f32)
                    .sum::<f32>()
                    / pixels.max(1) as f32;
                out.push(InstanceCandidate::new(
                    mask,
                    &union,
                    score,
                    object,
                    frame,
                    g.len(),
                    false,
                ));
            }
        }
        // Pieces of instances too large to be the object: heaps the network did not split.
        let large: Vec<usize> = (0..out.len())
            .filter(|&i| out[i].parts == 1 && out[i].size_ratio > MAX_SIZE_RATIO)
            .collect();
        let min_pixels = post.min_pixels_at(depth_n.width, depth_n.height);
        let mut cut = 0;
        for i in large {
            if cut >= MAX_PIECES {
                break;
            }
            let pixels: Vec<usize> = (0..depth_n.data.len())
                .filter(|&k| {
                    let z = depth_n.data[k];
                    out[i].mask.data[k] && z.is_finite() && z > 0.0
                })
                .collect();
            let pieces = crate::parts::heap_pieces(
                &clouds[i],
                diameter as f32,
                min_pixels,
                MAX_PIECES_PER_INSTANCE.min(MAX_PIECES - cut),
            );
            for piece in pieces {
                let mut mask = Mask::filled(depth_n.width, depth_n.height, false);
                for &k in &piece {
                    mask.data[pixels[k]] = true;
                }
                let points: Vec<Vec3> = piece.iter().map(|&k| clouds[i][k]).collect();
                let score = out[i].score;
                out.push(InstanceCandidate::new(
                    mask, &points, score, object, frame, 1, true,
                ));
                cut += 1;
            }
        }
        Ok(out)
    }

    /// Registers the instances `search` asks for, see [`InstanceSearch`] and
    /// [`PipelineOptions::instance_tries`]; best first, never empty (not-found error instead).
    fn register_instances(
        &self,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
        seed: u64,
        clock: Instant,
        search: InstanceSearch,
    ) -> Result<Vec<Registration>> {
        let t = Instant::now();
        // With a second opinion, the main network finding nothing that fits is not the end.
        let (all_candidates, mut first_error) =
            match self.instance_candidates(object, depth_n, intrinsics) {
                Ok(c) => (c, None),
                Err(e @ PipelineError::NotFound(_)) if self.seg_one_object.is_some() => {
                    (Vec::new(), Some(e))
                }
                Err(e) => return Err(e),
            };
        let seg_seconds = t.elapsed().as_secs_f64();
        // The network's own instances at its own input size (an extra size's find the same
        // objects again): more than one means clutter.
        let network_instances = all_candidates
            .iter()
            .filter(|c| c.parts == 1 && !c.cut && c.input == 0)
            .count();
        let per_group = match search {
            InstanceSearch::FirstOk => self.options.instance_tries,
            _ => 0,
        };
        let candidates = InstanceCandidate::to_try(&all_candidates, per_group);
        if candidates.is_empty() && first_error.is_none() {
            let largest = all_candidates
                .iter()
                .map(|c| c.size_ratio)
                .fold(0.0, f64::max);
            let e = PipelineError::not_found(format!(
                "object not found: the segmentation found {} instance(s), all too small for the model \
                 (the largest spans {:.2} of its diameter, at least {MIN_SIZE_RATIO} is needed); \
                 is the mesh in the depth map's units (--model-unit-mm)?",
                network_instances, largest
            ));
            if self.seg_one_object.is_none() {
                return Err(e);
            }
            first_error = Some(e);
        }
        let tries = match search {
            InstanceSearch::FirstOk
            | InstanceSearch::AllOk
            | InstanceSearch::Every { limit: 0 } => candidates.len(),
            InstanceSearch::Every { limit } => limit,
        };
        let mut done: Vec<Registration> = Vec::new();
        // Registers one candidate; false when the search stops there.
        let register = |c: &InstanceCandidate,
                        choice: InstanceChoice,
                        clutter: bool,
                        passes: usize,
                        seg_seconds: f64,
                        done: &mut Vec<Registration>,
                        first_error: &mut Option<PipelineError>|
         -> Result<bool> {
            let seconds = StageSeconds {
                segmentation_network: seg_seconds,
                ..StageSeconds::default()
            };
            let summary = SegmentationSummary {
                source: "network",
                score: Some(c.score),
                pixels: c.pixels,
            };
            match self.register_mask(
                object,
                depth_n,
                intrinsics,
                c.mask.clone(),
                summary,
                seed,
                passes,
                seconds,
                clock,
            ) {
                Ok(mut r) => {
                    // The network chose the pixels among several instances, or they are a
                    // piece of a heap: the confidence of a verified pose is the clutter
                    // confidence of its numbers (it may be another object). A lone instance
                    // keeps the single-object calibration: the clutter one was fitted on
                    // scenes with several (`docs/decisions.md`).
                    r.instance = Some(choice);
                    // The clutter confidence of a verified pose weighs the whole view;
                    // `--all` filters by it.
                    if (clutter && r.verification.is_some()) || search != InstanceSearch::FirstOk {
                        r.whole_view = self.whole_view(object, depth_n, intrinsics, &r);
                    }
                    if let (Some(f), Some(v), true) =
                        (clutter_features(&r), r.verification, clutter)
                    {
                        r.confidence = clutter_confidence().apply(&f);
                        r.verdict = Verdict::of_verified(v.score, r.confidence, &self.options);
                        r.calibration = CalibrationUsed::Segmentation;
                    }
                    // A model that would hide what the sensor saw is not trusted, whatever
                    // the crop's score (a pose fitted to a fragment of the object).
                    if r.verdict == Verdict::Ok && r.whole_view.is_some_and(|w| w.impossible()) {
                        r.verdict = Verdict::Uncertain;
                    }
                    let stop = search == InstanceSearch::FirstOk && r.verdict == Verdict::Ok;
                    done.push(r);
                    Ok(!stop)
                }
                Err(e @ PipelineError::NotFound(_)) => {
                    first_error.get_or_insert(e);
                    Ok(true)
                }
                Err(e) => Err(e),
            }
        };
        for (i, c) in candidates.iter().take(tries).enumerate() {
            let choice = InstanceChoice {
                rank: i,
                candidates: network_instances,
                size_ratio: c.size_ratio,
                shape_distance: c.shape_distance,
                parts: c.parts,
                truncated: c.truncated,
                cut: c.cut,
                one_object_network: false,
                input: c.input,
            };
            let clutter = network_instances > 1 || c.cut;
            // The further network passes go to the best-ranked instance only: in clutter
            // `register` may try several, each pass costs a sweep of new model copies.
            let passes = if i == 0 {
                self.options.network_passes
            } else {
                1
            };
            if !register(
                c,
                choice,
                clutter,
                passes,
                seg_seconds,
                &mut done,
                &mut first_error,
            )? {
                break;
            }
        }
        // The one-object network's second opinion, when nothing so far is `ok`: its best
        // instance of a fitting size that the tries above did not already cover.
        if let (Some(one), false, false) = (
            &self.seg_one_object,
            matches!(search, InstanceSearch::Every { .. }),
            done.iter().any(|r| r.verdict == Verdict::Ok),
        ) {
            let t = Instant::now();
            let others = match Self::candidates_of(one, object, depth_n, intrinsics) {
                Ok(c) => c,
                Err(PipelineError::NotFound(_)) => Vec::new(),
                Err(e) => return Err(e),
            };
            let one_seconds = seg_seconds + t.elapsed().as_secs_f64();
            let tried: Vec<&Mask> = candidates.iter().take(tries).map(|c| &c.mask).collect();
            // Each network judges how many objects its own instances hold: the one-object
            // network seeing a single instance in the whole image is a lone object.
            let its_instances = others.iter().filter(|c| c.parts == 1 && !c.cut).count();
            let lone = its_instances == 1;
            let best = others
                .iter()
                .find(|c| c.plausible && !c.cut && c.parts == 1);
            let same = best.and_then(|c| {
                tried
                    .iter()
                    .position(|m| mask_iou(m, &c.mask) >= SAME_INSTANCE_IOU)
            });
            match (best, same) {
                (Some(c), None) => {
                    let choice = InstanceChoice {
                        rank: 0,
                        candidates: its_instances,
                        size_ratio: c.size_ratio,
                        shape_distance: c.shape_distance,
                        parts: c.parts,
                        truncated: c.truncated,
                        cut: c.cut,
                        one_object_network: true,
                        input: c.input,
                    };
                    // Kept when `ok`, or when the main network gave nothing: in clutter the
                    // one-object network's instances are rarely the object, and an `uncertain`
                    // pose of its would only push aside the main network's.
                    let mut second = Vec::new();
                    register(
                        c,
                        choice,
                        !lone,
                        self.options.network_passes,
                        one_seconds,
                        &mut second,
                        &mut first_error,
                    )?;
                    let nothing_yet = done.is_empty();
                    done.extend(
                        second
                            .into_iter()
                            .filter(|r| nothing_yet || r.verdict == Verdict::Ok),
                    );
                }
                // Both networks chose these pixels, and the one-object network sees nothing
                // else: a lone object, whose registration gets the single-object calibration.
                (Some(_), Some(j)) if lone => {
                    for r in done.iter_mut().filter(|r| {
                        r.instance
                            .is_some_and(|i| i.rank == j && !i.one_object_network)
                            && r.calibration == CalibrationUsed::Segmentation
                    }) {
                        if let (Some(e), Some(v)) = (r.evidence, r.verification) {
                            r.confidence = verified_calibration().apply(e);
                            r.verdict = Verdict::of_verified(v.score, r.confidence, &self.options);
                            r.calibration = CalibrationUsed::Object;
                            r.seconds.segmentation_network = one_seconds;
                            if let Some(i) = &mut r.instance {
                                i.one_object_network = true;
                            }
                        }
                    }
                }
                _ => {}
            }
        }
        if done.is_empty() {
            return Err(first_error
                .unwrap_or_else(|| PipelineError::not_found("no instance could be registered")));
        }
        // Best first: the verdict (ok, uncertain, not found), then the confidence, then the
        // raw render-and-compare score.
        let key = |r: &Registration| {
            let verdict = match r.verdict {
                Verdict::Ok => 2,
                Verdict::Uncertain => 1,
                Verdict::NotFound => 0,
            };
            (
                verdict,
                r.confidence,
                r.verification.map_or(r.confidence, |v| v.score),
            )
        };
        done.sort_by(|a, b| {
            let (ka, kb) = (key(a), key(b));
            kb.0.cmp(&ka.0)
                .then(kb.1.total_cmp(&ka.1))
                .then(kb.2.total_cmp(&ka.2))
        });
        if search == InstanceSearch::AllOk {
            // Every `ok` instance (and, with `all_min_confidence`, every consistent `uncertain`
            // one that reaches it), one per object: `all_ok_choice`.
            let entries: Vec<AllEntry> = done
                .iter()
                .map(|r| AllEntry {
                    verdict: r.verdict,
                    confidence: r.confidence,
                    consistent: !self.options.all_whole_view
                        || r.whole_view.is_none_or(|w| w.consistent()),
                })
                .collect();
            let chosen = all_ok_choice(&entries, self.options.all_min_confidence);
            let mut kept: Vec<Registration> = Vec::new();
            for (i, r) in done.into_iter().enumerate() {
                if !chosen.contains(&i) {
                    continue;
                }
                let same = kept.iter().any(|k| {
                    object.add_s(&k.pose_normalised, &r.pose_normalised) < 0.1 * object.diameter
                });
                if !same {
                    kept.push(r);
                }
            }
            if kept.is_empty() {
                return Err(PipelineError::not_found(
                    "no instance of the object was found",
                ));
            }
            return Ok(kept);
        }
        for r in &mut done {
            r.seconds.total = clock.elapsed().as_secs_f64();
        }
        Ok(done)
    }

    /// [`crate::verify::whole_view`] of a registration from a depth map (normalised units),
    /// the tolerance floored by the roughness of its mask's pixels; `None` without a mask.
    fn whole_view(
        &self,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
        r: &Registration,
    ) -> Option<crate::verify::WholeView> {
        let observation =
            crate::verify::Observation::from_depth(depth_n, intrinsics, r.mask.as_ref()?)?;
        Some(crate::verify::whole_view(
            &self.model_shape(object),
            &r.pose_normalised,
            depth_n,
            intrinsics,
            observation.roughness,
        ))
    }

    /// How the verification draws `object`: its mesh, or its points splatted at half the voxel
    /// size.
    fn model_shape(&self, object: &Object) -> crate::verify::ModelShape {
        match &object.mesh {
            Some(mesh) => crate::verify::ModelShape::Mesh(mesh.clone()),
            None => crate::verify::ModelShape::points(
                object.points.clone(),
                0.5 * self.options.voxel_size,
            ),
        }
    }

    /// Registers `object` on the pixels of `mask` in `depth_n`.
    #[allow(clippy::too_many_arguments)]
    fn register_mask(
        &self,
        object: &Object,
        depth_n: &DepthImage,
        intrinsics: &Intrinsics,
        mask: Mask,
        summary: SegmentationSummary,
        seed: u64,
        passes: usize,
        mut seconds: StageSeconds,
        clock: Instant,
    ) -> Result<Registration> {
        let t = Instant::now();
        let post = self.post_config();
        let eroded = mask.eroded3x3_keeping_some(post.erosions);
        let points = ic_seg::post::masked_points(depth_n, intrinsics, &eroded, post.crop_radius)
            .map_err(|e| match (summary.source, e) {
                ("mask", e) => PipelineError::input(format!("mask: {e}")),
                (_, e) => PipelineError::not_found(format!("segmentation: {e}")),
            })?;
        let voxels = voxel_downsample_points(&points, self.options.voxel_size)?;
        seconds.observed_points = t.elapsed().as_secs_f64();
        if voxels.len() < self.options.min_object_points {
            return Err(PipelineError::not_found(format!(
                "object not found: only {} object points ({} voxels) after segmentation, at least {} are needed \
                 (is the mesh in the depth map's units? see --model-unit-mm)",
                points.len(),
                voxels.len(),
                self.options.min_object_points
            )));
        }
        check_units(&voxels);
        let observation = if self.options.rotations > 1 {
            crate::verify::Observation::from_depth(depth_n, intrinsics, &mask)
        } else {
            None
        };
        let mut r = self.register_observed(
            object,
            voxels,
            observation.as_ref(),
            seed,
            passes,
            seconds,
            clock,
        )?;
        r.object_points = points.len();
        r.segmentation = Some(summary);
        r.mask = Some(mask);
        Ok(r)
    }

    /// Registers `object` onto observed object points (camera frame, normalised units), e.g.
    /// a case's `target.ply`. No segmentation, no voxelising.
    pub fn register_points(
        &self,
        object: &Object,
        observed: &[Vec3],
        seed: u64,
    ) -> Result<Registration> {
        self.in_pool(|| self.register_points_inner(object, observed, seed))
    }

    fn register_points_inner(
        &self,
        object: &Object,
        observed: &[Vec3],
        seed: u64,
    ) -> Result<Registration> {
        let clock = Instant::now();
        if observed.iter().any(|p| !p.is_finite()) {
            return Err(PipelineError::input(
                "the observed points are not all finite",
            ));
        }
        if observed.len() < self.options.min_object_points.min(16) {
            return Err(PipelineError::not_found(format!(
                "only {} observed points",
                observed.len()
            )));
        }
        let observation = if self.options.rotations > 1 {
            crate::verify::Observation::from_points(observed, self.options.voxel_size)
        } else {
            None
        };
        let mut r = self.register_observed(
            object,
            observed.to_vec(),
            observation.as_ref(),
            seed,
            self.options.network_passes,
            StageSeconds::default(),
            clock,
        )?;
        r.object_points = observed.len();
        Ok(r)
    }

    #[allow(clippy::too_many_arguments)]
    fn register_observed(
        &self,
        object: &Object,
        voxels: Vec<Vec3>,
        observation: Option<&crate::verify::Observation>,
        seed: u64,
        passes: usize,
        mut seconds: StageSeconds,
        clock: Instant,
    ) -> Result<Registration> {
        if let (Some(obs), true) = (observation, self.options.rotations > 1) {
            return self.register_verified(object, voxels, obs, seed, passes, seconds, clock);
        }
        let mut best: Option<(f64, Hypothesis)> = None;
        let target = self.icp_target(object, &mut seconds)?;
        for h in 0..self.options.hypotheses.max(1) {
            let hseed = hypothesis_seed(seed, h);
            let hyp = self.hypothesis(object, &voxels, target.as_ref(), hseed, &mut seconds)?;
            let confidence = self.explained(object, &voxels, &hyp.pose);
            if best.as_ref().is_none_or(|(b, _)| confidence > *b) {
                best = Some((confidence, hyp));
            }
        }
        let (confidence, best) = best.expect("at least one hypothesis");
        seconds.total = clock.elapsed().as_secs_f64();
        let made = self.options.hypotheses.max(1);
        Ok(self.registration(object, best, confidence, None, (made, 0), voxels, seconds))
    }

    /// The registration of the winning hypothesis, with the confidence its verdict rests on
    /// and (made, verified) hypothesis counts.
    #[allow(clippy::too_many_arguments)]
    fn registration(
        &self,
        object: &Object,
        best: Hypothesis,
        confidence: f64,
        verification: Option<crate::verify::Score>,
        (made, verified): (usize, usize),
        voxels: Vec<Vec3>,
        seconds: StageSeconds,
    ) -> Registration {
        Registration {
            pose: object.normalisation.pose_to_original(&best.pose),
            pose_normalised: best.pose,
            one_shot_normalised: best.one_shot,
            confidence,
            calibration: match &verification {
                Some(_) => CalibrationUsed::Object,
                None => CalibrationUsed::None,
            },
            verdict: match &verification {
                Some(score) => Verdict::of_verified(score.score, confidence, &self.options),
                None => Verdict::of(confidence, &self.options),
            },
            verification,
            verified: Vec::new(),
            rival_score: None,
            evidence: None,
            hypotheses_made: made,
            hypotheses_verified: verified,
            segmentation: None,
            instance: None,
            object_points: voxels.len(),
            object_voxels: voxels.len(),
            inlier_count: best.inlier_count,
            assignment_confidence: best.assignment_confidence,
            icp: best.icp,
            whole_view: None,
            seconds,
            observed: voxels,
            mask: None,
        }
    }

    /// Hypothesise and verify: for each draw of points (`hypotheses`) and each rotation of
    /// the rotation set, a rotated copy of the model points goes through the network (one
    /// batch per draw); the one-shot poses are ranked by the point-distance confidence, the
    /// best `verify_top` are refined by ICP and scored by render-and-compare against
    /// `observation`; the best score wins.
    #[allow(clippy::too_many_arguments)]
    fn register_verified(
        &self,
        object: &Object,
        voxels: Vec<Vec3>,
        observation: &crate::verify::Observation,
        seed: u64,
        passes: usize,
        mut seconds: StageSeconds,
        clock: Instant,
    ) -> Result<Registration> {
        use crate::verify::rotation_set;
        let rotations = rotation_set(self.options.rotations).map_err(PipelineError::input)?;
        let (m, n) = match self.options.sweep_points {
            0 => self.point_counts(),
            m => (m, m * 3 / 4),
        };
        // The pose networks: the main one, then the second one when loaded
        // ([`Pipeline::with_second_pose`]); each makes, ranks and passes its own hypotheses.
        let networks: Vec<&ic_pose::PoseEstimator> = std::iter::once(&self.pose)
            .chain(self.pose_second.as_ref())
            .map(|p| &p.estimator)
            .collect();
        let mut per_network: Vec<Vec<(f64, Pose, ic_pose::PoseEstimate)>> =
            vec![Vec::new(); networks.len()];
        let mut first_draw = None;
        // The hypotheses are ranked by the point-distance confidence on a few of the voxels.
        let ranking: Vec<Vec3> = strided(&voxels, RANKING_POINTS).copied().collect();
        for h in 0..self.options.hypotheses.max(1) {
            let t = Instant::now();
            let (x, y, _) = draw_points(object, &voxels, (m, n), hypothesis_seed(seed, h))?;
            seconds.observed_points += t.elapsed().as_secs_f64();
            let sampled = self.options.sampled_hypotheses;
            let sweep = ic_pose::SweepOptions {
                keep: match self.options.sweep_keep {
                    0 => rotations.len(),
                    k => k,
                },
                sampling: (sampled > 0).then_some(ic_pose::SamplingOptions {
                    keep: sampled,
                    ..ic_pose::SamplingOptions::default()
                }),
                seed: ic_data::mix_seed(hypothesis_seed(seed, h), 0x5a3d),
            };
            let mut first_error = None;
            for (estimator, candidates) in networks.iter().zip(per_network.iter_mut()) {
                let t = Instant::now();
                let estimates = estimator.estimate_rotations(&x, &rotations, &y, &sweep)?;
                seconds.pose_network += t.elapsed().as_secs_f64();
                let t = Instant::now();
                // Every estimate of the copies in order (a copy whose correspondences admit no
                // pose is one hypothesis fewer), then their point-distance confidences in
                // parallel.
                let mut found: Vec<ic_pose::PoseEstimate> = Vec::new();
                for e in estimates {
                    match e {
                        Ok(c) => {
                            let e = c.estimate;
                            found.push(e);
                            found.extend(c.sampled.iter().map(|s| ic_pose::PoseEstimate {
                                pose: s.pose,
                                inlier_count: s.inliers,
                                ..e
                            }));
                        }
                        Err(err) => {
                            tracing::debug!("a rotated copy gave no pose: {err}");
                            first_error.get_or_insert(err);
                        }
                    }
                }
                let explained: Vec<f64> = found
                    .par_iter()
                    .map(|e| self.explained(object, &ranking, &e.pose))
                    .collect();
                candidates.extend(
                    found
                        .into_iter()
                        .zip(explained)
                        .map(|(e, confidence)| (confidence, e.pose, e)),
                );
                seconds.ranking += t.elapsed().as_secs_f64();
            }
            first_draw.get_or_insert((x, y));
            if per_network.iter().all(|c| c.is_empty())
                && let Some(err) = first_error
            {
                return Err(err.into());
            }
        }
        // Each network's best `verify_top` go on to verification, the main network's first:
        // its first draw's unrotated estimate (the paper's pipeline) is always verified; the
        // others compete for the remaining places by the point-distance confidence; then the
        // further passes of the same network over them. Each keeps the index of the network
        // that made it.
        let mut candidates: Vec<(usize, (f64, Pose, ic_pose::PoseEstimate))> = Vec::new();
        let mut made = 0;
        for (network, (estimator, mut mine)) in networks.iter().zip(per_network).enumerate() {
            if mine.is_empty() {
                continue;
            }
            let first = mine.remove(0);
            mine.sort_by(|a, b| b.0.total_cmp(&a.0));
            mine.insert(0, first);
            let mut top = self.options.verify_top.max(1).min(mine.len());
            if let Some((x, y)) = &first_draw {
                let t = Instant::now();
                let (mut from, mut to) = match self.options.pass_top {
                    0 => (0, top),
                    p => (0, p.min(top)),
                };
                for _ in 1..passes.max(1) {
                    let passed = self.network_pass(estimator, x, y, &mine[from..to])?;
                    from = top;
                    to = top + passed.len();
                    top = to;
                    mine.splice(from..from, passed);
                }
                seconds.pose_network += t.elapsed().as_secs_f64();
            }
            made += mine.len();
            mine.truncate(top);
            candidates.extend(mine.into_iter().map(|c| (network, c)));
        }
        let top = candidates.len();
        let shape = self.model_shape(object);
        let mut rng = ChaCha8Rng::seed_from_u64(ic_data::mix_seed(seed, 0x5e1f));
        let target = self.icp_target(object, &mut seconds)?;
        let mut verified: Vec<(crate::verify::Score, Hypothesis)> = Vec::new();
        // The hypotheses are refined on at most VERIFY_ICP_POINTS voxels; the winner again on
        // up to `icp_max_points` below.
        let coarse = VERIFY_ICP_POINTS.min(self.options.icp_max_points);
        // Each hypothesis's ICP points are drawn first, in the list's order (the draws of
        // refining them one after the other), then the hypotheses are refined and scored in
        // parallel: the same poses and scores on any number of threads.
        let sources: Vec<Option<Vec<Vec3>>> = match &target {
            None => vec![None; top],
            Some(_) => candidates[..top]
                .iter()
                .map(|_| icp_source(&voxels, coarse, &mut rng).map(Some))
                .collect::<Result<_>>()?,
        };
        let t = Instant::now();
        let done: Vec<Result<Refined>> = candidates[..top]
            .par_iter()
            .zip(&sources)
            .map(|((_, (_, one_shot, _)), source)| {
                let t_icp = Instant::now();
                let (pose, icp) = match (&target, source) {
                    (Some(target), Some(source)) => {
                        let (pose, icp) = self.icp_from(target, source, one_shot)?;
                        (pose, Some(icp))
                    }
                    _ => (*one_shot, None),
                };
                let icp_seconds = t_icp.elapsed().as_secs_f64();
                let t_score = Instant::now();
                let score = observation.score(&shape, &pose);
                Ok(Refined {
                    pose,
                    icp,
                    score,
                    icp_seconds,
                    score_seconds: t_score.elapsed().as_secs_f64(),
                })
            })
            .collect();
        // The block's wall time, split between the stages as their summed times are.
        let (icp_s, score_s) = done.iter().flatten().fold((0.0, 0.0), |(a, b), d| {
            (a + d.icp_seconds, b + d.score_seconds)
        });
        let wall = t.elapsed().as_secs_f64();
        let busy = icp_s + score_s;
        if busy > 0.0 {
            seconds.icp += wall * icp_s / busy;
            seconds.verification += wall * score_s / busy;
        }
        for ((network, (_, one_shot, estimate)), d) in candidates[..top].iter().zip(done) {
            let Refined {
                pose, icp, score, ..
            } = d?;
            let hyp = Hypothesis {
                pose,
                network: *network,
                one_shot: *one_shot,
                inlier_count: estimate.inlier_count,
                assignment_confidence: estimate.assignment_confidence,
                icp,
            };
            verified.push((score, hyp));
        }
        // The best score wins; on an exact tie, the first in the order above (the network's own
        // unrotated estimate, then the most consistent hypotheses). Widening the tie to
        // near-equal scores was measured and lost accuracy (`docs/decisions.md`).
        let winner =
            verified.iter().enumerate().fold(
                0,
                |w, (i, (s, _))| if s.score > verified[w].0.score { i } else { w },
            );
        let listed: Vec<VerifiedHypothesis> = verified
            .iter()
            .map(|(s, h)| VerifiedHypothesis {
                score: s.score,
                misfit: s.misfit,
                icp_rmse: h.icp.as_ref().map(|i| i.inlier_rmse),
                pose_normalised: h.pose,
                network: h.network,
            })
            .collect();
        let (mut score, mut best) = verified.swap_remove(winner);
        if voxels.len() > coarse {
            let (pose, icp) =
                self.refine(target.as_ref(), &voxels, &best.pose, &mut rng, &mut seconds)?;
            let t = Instant::now();
            let fine = observation.score(&shape, &pose);
            seconds.verification += t.elapsed().as_secs_f64();
            // The finer fit is kept unless it explains the depth clearly worse.
            if fine.score >= score.score - FINE_REFINE_SLACK {
                best.pose = pose;
                best.icp = icp;
                score = fine;
            }
        }
        seconds.total = clock.elapsed().as_secs_f64();
        let checked = top;
        // Ambiguity: the best score among the verified poses that are not equivalent to the
        // winner (ADD-S between them of at least 0.1 of the diameter). A view that another,
        // different pose explains about as well cannot be trusted, however well it is explained.
        let rival = listed
            .iter()
            .filter(|h| {
                object.add_s(&h.pose_normalised, &best.pose) >= EQUIVALENT_ADD_S * object.diameter
            })
            .map(|h| h.score)
            .fold(0.0f64, f64::max);
        let evidence = evidence(score.score, rival);
        let confidence = verified_calibration().apply(evidence);
        let mut r = self.registration(
            object,
            best,
            confidence,
            Some(score),
            (made, checked),
            voxels,
            seconds,
        );
        r.verified = listed;
        r.rival_score = Some(rival);
        r.evidence = Some(evidence);
        Ok(r)
    }

    /// One more pass of the network `estimator` over `candidates`, in one batch: the model points `x`
    /// (model frame) turned so that each candidate's rotation R̂ becomes the centre of the
    /// network's training rotations ([`ic_geometry::rotations::paper_view_rotation`]), against
    /// the observed points `y` (camera frame): one new hypothesis per candidate whose pass
    /// gives a pose, ranked like its candidate.
    fn network_pass(
        &self,
        estimator: &ic_pose::PoseEstimator,
        x: &[Vec3],
        y: &[Vec3],
        candidates: &[(f64, Pose, ic_pose::PoseEstimate)],
    ) -> Result<Vec<(f64, Pose, ic_pose::PoseEstimate)>> {
        // The copy G with R̂·G⁻¹ = P, the centre of the rotations the network was trained on.
        let centre_inv = ic_geometry::rotations::paper_view_rotation().inverse();
        let turns: Vec<Pose> = candidates
            .iter()
            .map(|(_, pose, _)| {
                centre_inv.compose(&Pose {
                    rotation: pose.rotation,
                    translation: ic_geometry::glam::DVec3::ZERO,
                })
            })
            .collect();
        let passes =
            estimator.estimate_rotations(x, &turns, y, &ic_pose::SweepOptions::default())?;
        Ok(passes
            .into_iter()
            .flatten()
            .map(|c| (candidates[c.rotation].0, c.estimate.pose, c.estimate))
            .collect())
    }

    /// Fraction of `voxels` (camera frame) within [`MATCH_DISTANCE`] of the model's dense
    /// points at `pose`: the point-distance confidence.
    fn explained(&self, object: &Object, voxels: &[Vec3], pose: &Pose) -> f64 {
        let back = pose.inverse();
        let explained = voxels
            .iter()
            .filter(|&&p| object.tree.nearest(back.apply_f32(p)).distance <= MATCH_DISTANCE)
            .count();
        explained as f64 / voxels.len().max(1) as f64
    }

    /// The ICP target of the dense model points with their normals, indexed once per
    /// registration; `None` when the pipeline does not refine.
    fn icp_target<'o>(
        &self,
        object: &'o Object,
        seconds: &mut StageSeconds,
    ) -> Result<Option<IcpTarget<'o>>> {
        match self.options.refine {
            Refine::None => Ok(None),
            Refine::Icp => {
                let t = Instant::now();
                let target = IcpTarget::new(&object.points, Some(&object.normals))?;
                seconds.icp += t.elapsed().as_secs_f64();
                Ok(Some(target))
            }
        }
    }

    /// The pipeline's refinement of a one-shot pose: ICP of at most `icp_max_points` object
    /// voxels onto `target` ([`Pipeline::icp_target`]), or nothing without a target.
    fn refine(
        &self,
        target: Option<&IcpTarget>,
        voxels: &[Vec3],
        one_shot: &Pose,
        rng: &mut ChaCha8Rng,
        seconds: &mut StageSeconds,
    ) -> Result<(Pose, Option<IcpSummary>)> {
        self.refine_with(
            target,
            voxels,
            one_shot,
            self.options.icp_max_points,
            rng,
            seconds,
        )
    }

    /// [`Pipeline::refine`] with at most `max_points` object voxels.
    fn refine_with(
        &self,
        target: Option<&IcpTarget>,
        voxels: &[Vec3],
        one_shot: &Pose,
        max_points: usize,
        rng: &mut ChaCha8Rng,
        seconds: &mut StageSeconds,
    ) -> Result<(Pose, Option<IcpSummary>)> {
        match target {
            None => Ok((*one_shot, None)),
            Some(target) => {
                let t = Instant::now();
                let source = icp_source(voxels, max_points, rng)?;
                let (pose, icp) = self.icp_from(target, &source, one_shot)?;
                seconds.icp += t.elapsed().as_secs_f64();
                Ok((pose, Some(icp)))
            }
        }
    }

    /// ICP of `source` (object voxels, camera frame, normalised units) onto `target` from
    /// `one_shot`: the refined pose (model → camera) and its summary.
    fn icp_from(
        &self,
        target: &IcpTarget,
        source: &[Vec3],
        one_shot: &Pose,
    ) -> Result<(Pose, IcpSummary)> {
        let options = IcpOptions {
            method: IcpMethod::PointToPlane,
            max_correspondence_distance: self.options.icp_max_distance,
            max_iterations: self.options.icp_iterations,
            ..IcpOptions::default()
        };
        let result = target.register(source, &one_shot.inverse(), &options)?;
        Ok((
            result.pose.inverse().orthonormalised(),
            IcpSummary {
                fitness: result.fitness,
                inlier_rmse: result.inlier_rmse,
                iterations: result.iterations,
            },
        ))
    }

    /// One draw of M model and N observed points, the network and ICP.
    fn hypothesis(
        &self,
        object: &Object,
        voxels: &[Vec3],
        target: Option<&IcpTarget>,
        seed: u64,
        seconds: &mut StageSeconds,
    ) -> Result<Hypothesis> {
        let t = Instant::now();
        let (x, y, mut rng) = draw_points(object, voxels, self.point_counts(), seed)?;
        seconds.observed_points += t.elapsed().as_secs_f64();

        let t = Instant::now();
        let estimate = self.pose.estimator.estimate(&x, &y)?;
        seconds.pose_network += t.elapsed().as_secs_f64();
        let one_shot = estimate.pose;

        let (pose, icp) = self.refine(target, voxels, &one_shot, &mut rng, seconds)?;
        Ok(Hypothesis {
            pose,
            network: 0,
            one_shot,
            inlier_count: estimate.inlier_count,
            assignment_confidence: estimate.assignment_confidence,
            icp,
        })
    }
}

/// One verified hypothesis after its ICP and scoring, with the seconds each took.
struct Refined {
    pose: Pose,
    icp: Option<IcpSummary>,
    score: crate::verify::Score,
    icp_seconds: f64,
    score_seconds: f64,
}

/// The ICP source of a refinement: at most `max_points` (at least 3) of `voxels`, drawn with
/// `rng` when there are more, else all of them.
fn icp_source(voxels: &[Vec3], max_points: usize, rng: &mut ChaCha8Rng) -> Result<Vec<Vec3>> {
    let max_points = max_points.max(3);
    Ok(if voxels.len() > max_points {
        random_subsample_indices(voxels.len(), max_points, rng)?
            .into_iter()
            .map(|i| voxels[i])
            .collect()
    } else {
        voxels.to_vec()
    })
}

/// The seed of hypothesis `h`: hypothesis 0 draws from `seed` itself, so one hypothesis is the
/// paper's pipeline.
fn hypothesis_seed(seed: u64, h: usize) -> u64 {
    if h == 0 {
        seed
    } else {
        ic_data::mix_seed(seed, h as u64)
    }
}

/// `m` of the object's dense points and `n` of the observed voxels, drawn in that order by a
/// generator seeded with `seed`, which is returned for the draws that follow.
fn draw_points(
    object: &Object,
    voxels: &[Vec3],
    (m, n): (usize, usize),
    seed: u64,
) -> Result<(Vec<Vec3>, Vec<Vec3>, ChaCha8Rng)> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let xi = random_subsample_indices(object.points.len(), m, &mut rng)?;
    let yi = random_subsample_indices(voxels.len(), n, &mut rng)?;
    let x = xi.iter().map(|&i| object.points[i]).collect();
    let y = yi.iter().map(|&i| voxels[i]).collect();
    Ok((x, y, rng))
}

/// One pose hypothesis of [`Pipeline::register_observed`].
struct Hypothesis {
    pose: Pose,
    network: usize,
    one_shot: Pose,
    inlier_count: usize,
    assignment_confidence: f32,
    icp: Option<IcpSummary>,
}

/// At most about `count` of `points`, evenly strided (every ⌈len / count⌉-th, from the first).
fn strided(points: &[Vec3], count: usize) -> impl Iterator<Item = &Vec3> {
    points.iter().step_by(points.len().div_ceil(count).max(1))
}

/// Warns when the observed object is far larger or smaller than the model: the usual cause is
/// a mesh in other units than the depth map.
fn check_units(voxels: &[Vec3]) {
    let lo = voxels.iter().fold(Vec3::INFINITY, |a, p| a.min(*p));
    let hi = voxels.iter().fold(Vec3::NEG_INFINITY, |a, p| a.max(*p));
    let extent = (hi - lo).max_element();
    // The normalised model spans 2 on its longest side; a view shows at most its diagonal.
    if !(0.05..=8.0).contains(&extent) {
        tracing::warn!(
            observed_extent = extent,
            "the observed object spans {extent:.3} normalised units (the model spans 2): are the mesh and the depth map in the same units? (--model-unit-mm)"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    #[test]
    fn pixel_set_overlap_is_the_masks_iou_and_disjoint_boxes_give_zero() {
        let rect = |x0: usize, y0: usize, x1: usize, y1: usize| {
            let mut m = Mask::filled(20, 10, false);
            for y in y0..y1 {
                for x in x0..x1 {
                    m.data[y * 20 + x] = true;
                }
            }
            m
        };
        let masks = [
            rect(0, 0, 5, 5),
            rect(3, 2, 9, 8),
            rect(3, 2, 9, 8),
            rect(10, 0, 20, 10), // beside the first, no shared column
            rect(4, 4, 5, 5),    // one pixel inside the first two
            rect(0, 0, 0, 0),    // empty
        ];
        for a in &masks {
            for b in &masks {
                // The dense IoU over the whole image is the oracle.
                let got = PixelSet::of(a).iou(&PixelSet::of(b));
                assert!(
                    (got - mask_iou(a, b)).abs() < 1e-12,
                    "{got} vs {}",
                    mask_iou(a, b)
                );
            }
        }
        assert_eq!(PixelSet::of(&masks[1]).iou(&PixelSet::of(&masks[2])), 1.0);
    }

    #[test]
    fn instances_are_ranked_by_pixels_size_and_shape_together_and_kinds_stay_apart() {
        let c = |size_ratio: f64, pixels: usize, shape_distance: f64| InstanceCandidate {
            score: 0.9,
            pixels,
            extent: size_ratio,
            size_ratio,
            plausible: (MIN_SIZE_RATIO..=MAX_SIZE_RATIO).contains(&size_ratio),
            shape_distance,
            truncated: false,
            cut: false,
            parts: 1,
            input: 0,
            mask: Mask::filled(1, 1, false),
        };
        let key = |c: &InstanceCandidate| (c.pixels, (c.size_ratio * 100.0).round() as usize);
        let mut v = vec![
            c(0.8, 900, 0.1),   // the typical size, partly hidden
            c(0.7, 2500, 0.1),  // a little small, but many more pixels: first
            c(0.8, 2500, 0.8),  // as many pixels, a shape no view of the model has
            c(0.45, 5000, 0.1), // the most pixels, half the typical extent
            c(2.0, 20000, 0.0), // implausible (too large): last
        ];
        InstanceCandidate::rank(&mut v);
        let order: Vec<_> = v.iter().map(key).collect();
        assert_eq!(
            order,
            [(2500, 70), (900, 80), (5000, 45), (2500, 80), (20000, 200)]
        );
        // The fit is one score: a shape twice as far from the model's views costs what
        // fewer pixels or a worse size would.
        assert!(v[0].fit() > v[1].fit() && v[1].fit() > v[2].fit() && v[2].fit() > v[3].fit());

        // Cut off by the image's border: the same instance moves down, not to the end.
        v[0].truncated = true;
        InstanceCandidate::rank(&mut v);
        let order: Vec<_> = v.iter().map(key).collect();
        assert_eq!(
            order,
            [(900, 80), (2500, 70), (5000, 45), (2500, 80), (20000, 200)]
        );

        // An extra input size's candidates come after every plausible one of the network's
        // own size, whatever their fit, and before the implausible ones; pieces cut from heaps
        // after both.
        v.push(InstanceCandidate {
            input: 1,
            ..c(0.8, 30000, 0.0)
        });
        v.push(InstanceCandidate {
            cut: true,
            ..c(0.8, 40000, 0.0)
        });
        InstanceCandidate::rank(&mut v);
        let order: Vec<_> = v.iter().map(key).collect();
        assert_eq!(
            order,
            [
                (900, 80),
                (2500, 70),
                (5000, 45),
                (2500, 80),
                (30000, 80),
                (40000, 80),
                (20000, 200)
            ]
        );
    }

    #[test]
    fn instance_tries_bound_the_instances_and_the_pieces_tried_and_zero_tries_every_one() {
        let c = |size_ratio: f64, pixels: usize, cut: bool| InstanceCandidate {
            score: 0.9,
            pixels,
            extent: size_ratio,
            size_ratio,
            plausible: (MIN_SIZE_RATIO..=MAX_SIZE_RATIO).contains(&size_ratio),
            shape_distance: 0.0,
            truncated: false,
            cut,
            parts: 1,
            input: 0,
            mask: Mask::filled(1, 1, false),
        };
        let mut v = vec![
            c(0.8, 100, false),
            c(0.7, 200, false),
            c(0.9, 300, false),
            c(0.75, 400, false),
            c(0.8, 50, true), // pieces of a heap: after every instance of the network's
            c(0.8, 60, true),
            c(0.8, 70, true),
            c(2.0, 5000, false), // too large, never tried while others fit
            c(0.1, 10, false),   // too small, never tried
        ];
        InstanceCandidate::rank(&mut v);
        let tried = |n: usize| -> Vec<usize> {
            InstanceCandidate::to_try(&v, n)
                .iter()
                .map(|c| c.pixels)
                .collect()
        };
        assert_eq!(tried(2), [400, 300, 70, 60]);
        assert_eq!(tried(3), [400, 300, 200, 70, 60, 50]);
        assert_eq!(tried(0), [400, 300, 200, 100, 70, 60, 50]);
        // Nothing fits but one too large: that one alone (its crop may hold the object).
        let mut big = vec![c(3.0, 9000, false), c(2.0, 5000, false), c(0.1, 10, false)];
        InstanceCandidate::rank(&mut big);
        let tried: Vec<usize> = InstanceCandidate::to_try(&big, 0)
            .iter()
            .map(|c| c.pixels)
            .collect();
        assert_eq!(tried, [5000]);
    }

    #[test]
    fn all_returns_ok_poses_and_consistent_uncertain_ones_and_falls_back_to_the_best_consistent_one()
     {
        let e = |verdict: Verdict, confidence: f64, consistent: bool| AllEntry {
            verdict,
            confidence,
            consistent,
        };
        use Verdict::{NotFound, Ok as Good, Uncertain};
        let v = [
            e(Good, 0.95, true),
            e(Good, 0.93, false), // `ok`: kept though its whole view disagrees
            e(Uncertain, 0.5, true),
            e(Uncertain, 0.45, false),
            e(Uncertain, 0.2, true),
            e(NotFound, 0.0, true),
        ];
        assert_eq!(all_ok_choice(&v, None), [0, 1]);
        assert_eq!(all_ok_choice(&v, Some(0.3)), [0, 1, 2]);
        assert_eq!(all_ok_choice(&v, Some(0.0)), [0, 1, 2, 4]);
        // Nothing wanted: the best consistent pose, else the best found.
        let w = [
            e(Uncertain, 0.6, false),
            e(Uncertain, 0.3, true),
            e(NotFound, 0.0, true),
        ];
        assert_eq!(all_ok_choice(&w, None), [1]);
        assert_eq!(all_ok_choice(&w, Some(0.9)), [1]);
        let x = [e(NotFound, 0.0, true), e(Uncertain, 0.4, false)];
        assert_eq!(all_ok_choice(&x, None), [1]);
        assert!(all_ok_choice(&[e(NotFound, 0.0, true)], Some(0.0)).is_empty());
    }

    #[test]
    fn clutter_confidence_doubts_moderate_fits_that_a_given_mask_would_trust() {
        let fit = |evidence: f64, coverage: f64, agreement: f64, misfit: f64, voxels: usize| {
            ic_eval::ClutterFeatures {
                evidence,
                rival_score: 0.0,
                object_voxels: voxels,
                verification: ic_eval::clutter::CropScore {
                    score: coverage,
                    coverage,
                    agreement,
                    visible_agreement: agreement,
                    misfit,
                    violation: 0.0,
                },
                whole_view: Some(ic_eval::clutter::WholeViewFractions {
                    agreement,
                    in_front: 0.0,
                    missing: 0.0,
                }),
                instance: ic_eval::clutter::InstanceNumbers {
                    size_ratio: 0.8,
                    shape_distance: Some(0.1),
                    truncated: false,
                    cut: false,
                },
                segmentation: ic_eval::clutter::SegmentationNumbers {
                    pixels: 2000,
                    score: Some(0.8),
                },
            }
        };
        // The embedded file loads (every feature known, a valid model and calibration).
        let c = clutter_confidence();
        // A pose that explains its instance fully, on many voxels, is `ok` in clutter …
        let full = c.apply(&fit(0.99, 0.99, 1.0, 0.15, 400));
        assert!(full >= VERIFIED_OK, "{full}");
        // … a moderate fit, `ok` with a given mask, is often another object in clutter.
        let single = verified_calibration().apply(0.75);
        let moderate = c.apply(&fit(0.75, 0.75, 0.9, 0.4, 150));
        assert!(
            single >= VERIFIED_OK && moderate < 0.7,
            "{single} {moderate}"
        );
        // The calibration of the model's output is monotone and a probability.
        let mut last = 0.0;
        for i in 0..=100 {
            let p = c.calibration.apply(i as f64 / 100.0);
            assert!((0.0..=1.0).contains(&p) && p >= last);
            last = p;
        }
    }

    #[test]
    fn evidence_is_capped_by_the_margin_over_a_different_pose() {
        // Unambiguous: no rival, the score itself.
        assert_eq!(evidence(0.9, 0.0), 0.9);
        // A different pose explains the view almost as well: little evidence.
        assert!((evidence(0.95, 0.9) - 0.2).abs() < 1e-12);
        // A clear margin leaves the score.
        assert_eq!(evidence(0.8, 0.3), 0.8);
        // Never negative, never above 1.
        assert_eq!(evidence(0.5, 0.6), 0.0);
        assert_eq!(evidence(1.5, 0.0), 1.0);
        // The calibration is monotone in the evidence and a probability.
        let c = verified_calibration();
        let mut last = 0.0;
        for i in 0..=100 {
            let p = c.apply(i as f64 / 100.0);
            assert!((0.0..=1.0).contains(&p) && p >= last);
            last = p;
        }
    }

    #[test]
    fn add_s_between_poses_is_zero_for_the_same_pose_and_grows_with_a_turn() {
        let mut mesh = ic_geometry::shapes::random_object(5);
        mesh.normalise().unwrap();
        let object = Object::from_mesh(mesh, 1).unwrap();
        assert!(
            object.diameter > 1.0 && object.diameter < 4.0,
            "{}",
            object.diameter
        );
        let a = Pose::from_translation(DVec3::new(0.1, 0.0, 3.0));
        assert!(object.add_s(&a, &a) < 1e-6);
        let turned = a.compose(&Pose::from_axis_angle(DVec3::X, 1.0, DVec3::ZERO));
        assert!(object.add_s(&a, &turned) > 0.02);
        // A shift bounds ADD-S from above (every point's own copy is that far), and a shift of
        // the object's size makes the poses different (not equivalent).
        let moved = Pose::from_translation(DVec3::new(0.1 + object.diameter, 0.0, 3.0));
        let d = object.add_s(&a, &moved);
        assert!(d <= object.diameter + 1e-4, "{d}");
        assert!(d > EQUIVALENT_ADD_S * object.diameter, "{d}");
    }

    #[test]
    fn collinear_object_points_are_not_found_rather_than_an_internal_error() {
        let pipeline = Pipeline::builder()
            .segmentation(false)
            .rotations(24)
            .threads(1)
            .build()
            .unwrap();
        let mesh = ic_geometry::shapes::random_object(3);
        let object = Object::from_mesh(mesh, 0).unwrap();
        // A sliver: 64 points on one line 2 units in front of the camera.
        let line: Vec<Vec3> = (0..64)
            .map(|i| Vec3::new(-0.5 + i as f32 / 64.0, 0.0, 2.0))
            .collect();
        match pipeline.register_points(&object, &line, 0) {
            Ok(r) => assert_ne!(r.verdict, Verdict::Ok),
            Err(e) => assert!(matches!(e, PipelineError::NotFound(_)), "{e:?}"),
        }
    }
}
