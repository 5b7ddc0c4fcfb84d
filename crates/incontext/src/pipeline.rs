//! The registration pipeline, shared by `register`, `demo`, `eval` and the benchmark tool:
//!
//! ```text
//! depth (model units) ÷ scale ──seg net──► mask ──erode 3×3, back-project, crop 1.2──►
//!   voxelise 0.0354 ──sample N──► pose network (with M model points) ──► one-shot pose
//!   ──point-to-plane ICP (all object voxels onto the dense model points)──► pose
//!   ──Normalisation::pose_to_original──► pose in the model's own units
//! ```
//!
//! The networks work in normalised object units: the mesh is normalised to [-1, 1] on its
//! longest side (`Normalisation { centre, scale }`) and the depth map, which must be in the
//! mesh's own units, is divided by `scale`, so the camera frame is scaled but not moved.

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
use serde::Serialize;

use crate::error::{CliError, Result};
use crate::models::{LoadedPose, LoadedSeg};

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

/// The render-and-compare score from which a verified pose is `ok` (on whole-sphere views of
/// unseen real objects: 98 % of such poses right, 91 % of right poses `ok`;
/// `docs/decisions.md`).
pub const VERIFIED_OK: f64 = 0.5;

/// The render-and-compare score below which a verified pose counts as not found (no right pose
/// scored below it on those views' wrong ones; a few right ones do, under heavy noise).
pub const VERIFIED_FOUND: f64 = 0.05;

/// A known object, ready to be registered: its normalised mesh (when it came from one), how it
/// was normalised, and its dense visible-surface points with normals (normalised units).
pub struct Object {
    pub mesh: Option<Arc<Mesh>>,
    pub normalisation: Normalisation,
    pub points: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    tree: KdTree,
    /// Seconds spent sampling the points and normals.
    pub seconds: f64,
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
    /// Normalises `mesh` (in its own units) and samples its visible surface (seeded).
    pub fn from_mesh(mut mesh: Mesh, seed: u64) -> Result<Object> {
        let clock = Instant::now();
        let normalisation = mesh
            .normalise()
            .map_err(|e| CliError::input(format!("the mesh cannot be normalised: {e}")))?;
        let cloud = sample_visible_surface(
            &mesh,
            DENSE_MODEL_POINTS,
            seed,
            VisibleSurfaceOptions::default(),
        )
        .map_err(|e| CliError::input(format!("sampling the mesh surface: {e}")))?;
        if cloud.points.len() < 16 {
            return Err(CliError::input(format!(
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
            return Err(CliError::input(format!(
                "the model has {} points; at least 16 are needed",
                points.len()
            )));
        }
        if points.iter().any(|p| !p.is_finite()) {
            return Err(CliError::input("the model points are not all finite"));
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
        Ok(Object {
            mesh: None,
            normalisation,
            points,
            normals,
            tree,
            seconds: 0.0,
        })
    }
}

fn pca_normals(points: &[Vec3]) -> Result<Vec<Vec3>> {
    let centre = points.iter().copied().sum::<Vec3>() / points.len().max(1) as f32;
    Ok(estimate_normals(points, 10, centre + Vec3::splat(100.0))?)
}

/// How far a registration can be trusted, from its confidence (the fraction of the observed
/// object voxels the aligned model explains) and the thresholds of [`PipelineOptions`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// Confidence ≥ `confidence_ok`: the pose explains the object; use it.
    Ok,
    /// `confidence_found` ≤ confidence < `confidence_ok`: a pose was found but it may be wrong
    /// (a symmetric flip, the wrong side, or another object); check it (`--overlay`) or try
    /// more hypotheses.
    Uncertain,
    /// Confidence < `confidence_found`: the best pose explains almost nothing; the object is
    /// not in view, or the mesh or its units are wrong.
    NotFound,
}

impl Verdict {
    /// The verdict of a point-distance confidence in [0, 1] (`confidence_ok`,
    /// `confidence_found`).
    pub fn of(confidence: f64, options: &PipelineOptions) -> Verdict {
        Verdict::by(confidence, options.confidence_ok, options.confidence_found)
    }

    /// The verdict of a render-and-compare score in [0, 1] (`verified_ok`, `verified_found`).
    pub fn of_verified(score: f64, options: &PipelineOptions) -> Verdict {
        Verdict::by(score, options.verified_ok, options.verified_found)
    }

    fn by(value: f64, ok: f64, found: f64) -> Verdict {
        if value >= ok {
            Verdict::Ok
        } else if value >= found {
            Verdict::Uncertain
        } else {
            Verdict::NotFound
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
    /// The same thresholds on the render-and-compare score, when hypotheses are verified
    /// (`rotations > 1`).
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
    /// network's own M and N. Fewer points make the sweep faster; the verified hypotheses are
    /// refined by ICP on every object voxel anyway. Default 0: 192 was as accurate as 384 on
    /// 102 paper-protocol room and object-alone views (0.30 s instead of 0.63 s with 24
    /// rotations), but lost the pose of a close-up object entirely (`docs/decisions.md`).
    pub sweep_points: usize,
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
            sweep_points: 0,
        }
    }
}

/// Seconds spent in each stage of one registration.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageSeconds {
    pub segmentation_network: f64,
    pub segmentation_post: f64,
    /// Erosion, back-projection, crop, voxelising, sampling.
    pub observed_points: f64,
    pub pose_network: f64,
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
    /// Fraction of the observed object voxels within [`MATCH_DISTANCE`] (normalised) of the
    /// model at the final pose, in [0, 1].
    pub confidence: f64,
    /// What the confidence says of the pose.
    pub verdict: Verdict,
    /// The render-and-compare score of the pose, when hypotheses were verified.
    pub verification: Option<crate::verify::Score>,
    /// One-shot hypotheses made, and how many were refined and verified.
    pub hypotheses_made: usize,
    pub hypotheses_verified: usize,
    pub segmentation: Option<SegmentationSummary>,
    /// Object points after erosion and crop, and after voxelising.
    pub object_points: usize,
    pub object_voxels: usize,
    /// Correspondences the pose rests on, and their mean probability.
    pub inlier_count: usize,
    pub assignment_confidence: f32,
    pub icp: Option<IcpSummary>,
    pub seconds: StageSeconds,
    /// The observed object voxels (camera frame, normalised units).
    #[serde(skip)]
    pub observed: Vec<Vec3>,
    /// The object mask used (before erosion), for depth inputs.
    #[serde(skip)]
    pub mask: Option<Mask>,
}

/// The networks and settings of the pipeline.
pub struct Pipeline {
    pose: LoadedPose,
    seg: Option<LoadedSeg>,
    pub options: PipelineOptions,
}

impl Pipeline {
    /// A pipeline over loaded networks. Without a segmentation network, depth inputs need a
    /// mask.
    pub fn new(mut pose: LoadedPose, seg: Option<LoadedSeg>, options: PipelineOptions) -> Self {
        // The pipeline refines itself (onto the dense model, with every object voxel).
        pose.estimator.recovery.refine = Refine::None;
        Pipeline { pose, seg, options }
    }

    /// Loads the networks: `pose_model` or the shipped one of `head`; the segmentation network
    /// when `with_seg` (`seg_model` or the shipped one).
    pub fn load(
        pose_model: Option<&std::path::Path>,
        head: Option<Head>,
        seg_model: Option<&std::path::Path>,
        with_seg: bool,
        options: PipelineOptions,
    ) -> Result<Pipeline> {
        let pose = crate::models::load_pose(pose_model, head)?;
        let seg = if with_seg {
            Some(crate::models::load_seg(seg_model)?)
        } else {
            None
        };
        Ok(Pipeline::new(pose, seg, options))
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
            "head": self.head().as_str(),
            "seg_model": self.seg_source(),
            "model_points": m,
            "observed_points": n,
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
        let clock = Instant::now();
        let inv = (1.0 / object.normalisation.scale) as f32;
        let depth_n = Image {
            width: depth.width,
            height: depth.height,
            data: depth.data.iter().map(|&z| z * inv).collect(),
        };
        self.register_depth_inner(object, &depth_n, intrinsics, mask, seed, clock)
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
        self.register_depth_inner(
            object,
            depth_normalised,
            intrinsics,
            mask,
            seed,
            Instant::now(),
        )
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
        intrinsics
            .validate()
            .map_err(|e| CliError::input(e.to_string()))?;
        depth_n
            .check_size(intrinsics.width, intrinsics.height)
            .map_err(|e| CliError::input(format!("depth map: {e}")))?;
        let mut seconds = StageSeconds::default();
        let (mask, summary) = match mask {
            Some(m) => {
                m.check_size(intrinsics.width, intrinsics.height)
                    .map_err(|e| CliError::input(format!("mask: {e}")))?;
                let pixels = m.data.iter().filter(|&&b| b).count();
                if pixels == 0 {
                    return Err(CliError::input("the mask is empty (no pixel is set)"));
                }
                (
                    m.clone(),
                    SegmentationSummary {
                        source: "mask",
                        score: None,
                        pixels,
                    },
                )
            }
            None => {
                let seg = self.seg.as_ref().ok_or_else(|| {
                    CliError::input("no segmentation network loaded and no mask given")
                })?;
                let s = seg.segmenter.segment(depth_n, intrinsics)?;
                seconds.segmentation_network = s.network_seconds;
                seconds.segmentation_post = s.post_seconds;
                let pixels = s.mask.data.iter().filter(|&&b| b).count();
                (
                    s.mask,
                    SegmentationSummary {
                        source: "network",
                        score: Some(s.score),
                        pixels,
                    },
                )
            }
        };
        let t = Instant::now();
        let post = self.post_config();
        let eroded = mask.eroded3x3_keeping_some(post.erosions);
        let points = ic_seg::post::masked_points(depth_n, intrinsics, &eroded, post.crop_radius)
            .map_err(|e| match (summary.source, e) {
                ("mask", e) => CliError::input(format!("mask: {e}")),
                (_, e) => CliError::not_found(format!("segmentation: {e}")),
            })?;
        let voxels = voxel_downsample_points(&points, self.options.voxel_size)?;
        seconds.observed_points = t.elapsed().as_secs_f64();
        if voxels.len() < self.options.min_object_points {
            return Err(CliError::not_found(format!(
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
        let mut r =
            self.register_observed(object, voxels, observation.as_ref(), seed, seconds, clock)?;
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
        let clock = Instant::now();
        if observed.iter().any(|p| !p.is_finite()) {
            return Err(CliError::input("the observed points are not all finite"));
        }
        if observed.len() < self.options.min_object_points.min(16) {
            return Err(CliError::not_found(format!(
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
            StageSeconds::default(),
            clock,
        )?;
        r.object_points = observed.len();
        Ok(r)
    }

    fn register_observed(
        &self,
        object: &Object,
        voxels: Vec<Vec3>,
        observation: Option<&crate::verify::Observation>,
        seed: u64,
        mut seconds: StageSeconds,
        clock: Instant,
    ) -> Result<Registration> {
        if let (Some(obs), true) = (observation, self.options.rotations > 1) {
            return self.register_verified(object, voxels, obs, seed, seconds, clock);
        }
        let mut best: Option<Hypothesis> = None;
        let target = self.icp_target(object, &mut seconds)?;
        for h in 0..self.options.hypotheses.max(1) {
            let hseed = hypothesis_seed(seed, h);
            let hyp = self.hypothesis(object, &voxels, target.as_ref(), hseed, &mut seconds)?;
            if best.as_ref().is_none_or(|b| hyp.confidence > b.confidence) {
                best = Some(hyp);
            }
        }
        let best = best.expect("at least one hypothesis");
        seconds.total = clock.elapsed().as_secs_f64();
        let confidence = best.confidence;
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
            verdict: match verification {
                Some(_) => Verdict::of_verified(confidence, &self.options),
                None => Verdict::of(confidence, &self.options),
            },
            verification,
            hypotheses_made: made,
            hypotheses_verified: verified,
            segmentation: None,
            object_points: voxels.len(),
            object_voxels: voxels.len(),
            inlier_count: best.inlier_count,
            assignment_confidence: best.assignment_confidence,
            icp: best.icp,
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
    fn register_verified(
        &self,
        object: &Object,
        voxels: Vec<Vec3>,
        observation: &crate::verify::Observation,
        seed: u64,
        mut seconds: StageSeconds,
        clock: Instant,
    ) -> Result<Registration> {
        use crate::verify::{ModelShape, rotate_points, rotation_set, unrotate};
        let rotations = rotation_set(self.options.rotations).map_err(CliError::input)?;
        let (m, n) = match self.options.sweep_points {
            0 => self.point_counts(),
            m => (m, m * 3 / 4),
        };
        let mut candidates: Vec<(f64, Pose, ic_pose::PoseEstimate)> = Vec::new();
        for h in 0..self.options.hypotheses.max(1) {
            let t = Instant::now();
            let (x, y, _) = draw_points(object, &voxels, (m, n), hypothesis_seed(seed, h))?;
            let copies: Vec<Vec<Vec3>> = rotations.iter().map(|r| rotate_points(&x, r)).collect();
            seconds.observed_points += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let pairs: Vec<(&[Vec3], &[Vec3])> = copies
                .iter()
                .map(|c| (c.as_slice(), y.as_slice()))
                .collect();
            let estimates = self.pose.estimator.estimate_batch(&pairs)?;
            seconds.pose_network += t.elapsed().as_secs_f64();
            let mut first_error = None;
            for (e, r) in estimates.into_iter().zip(&rotations) {
                // A copy whose correspondences admit no pose is one hypothesis fewer.
                match e {
                    Ok(e) => {
                        let pose = unrotate(&e.pose, r);
                        candidates.push((self.explained(object, &voxels, &pose), pose, e));
                    }
                    Err(err) => {
                        tracing::debug!("a rotated copy gave no pose: {err}");
                        first_error.get_or_insert(err);
                    }
                }
            }
            if candidates.is_empty()
                && let Some(err) = first_error
            {
                return Err(err.into());
            }
        }
        let made = candidates.len();
        // The first draw's unrotated estimate (the paper's pipeline) is always verified; the
        // others compete for the remaining places by the point-distance confidence.
        let first = candidates.remove(0);
        candidates.sort_by(|a, b| b.0.total_cmp(&a.0));
        candidates.insert(0, first);
        let shape = match &object.mesh {
            Some(mesh) => ModelShape::Mesh(mesh.clone()),
            None => ModelShape::points(object.points.clone(), 0.5 * self.options.voxel_size),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(ic_data::mix_seed(seed, 0x5e1f));
        let target = self.icp_target(object, &mut seconds)?;
        let mut best: Option<(crate::verify::Score, Hypothesis)> = None;
        for (_, one_shot, estimate) in candidates.iter().take(self.options.verify_top.max(1)) {
            let (pose, icp) =
                self.refine(target.as_ref(), &voxels, one_shot, &mut rng, &mut seconds)?;
            let t = Instant::now();
            let score = observation.score(&shape, &pose);
            seconds.verification += t.elapsed().as_secs_f64();
            let hyp = Hypothesis {
                pose,
                one_shot: *one_shot,
                confidence: self.explained(object, &voxels, &pose),
                inlier_count: estimate.inlier_count,
                assignment_confidence: estimate.assignment_confidence,
                icp,
            };
            if best.as_ref().is_none_or(|(b, _)| score.score > b.score) {
                best = Some((score, hyp));
            }
        }
        let (score, best) = best.expect("at least one hypothesis");
        seconds.total = clock.elapsed().as_secs_f64();
        let verified = self.options.verify_top.max(1).min(made);
        Ok(self.registration(
            object,
            best,
            score.score,
            Some(score),
            (made, verified),
            voxels,
            seconds,
        ))
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
        match target {
            None => Ok((*one_shot, None)),
            Some(target) => {
                let t = Instant::now();
                let source: Vec<Vec3> = if voxels.len() > self.options.icp_max_points {
                    random_subsample_indices(voxels.len(), self.options.icp_max_points, rng)?
                        .into_iter()
                        .map(|i| voxels[i])
                        .collect()
                } else {
                    voxels.to_vec()
                };
                let options = IcpOptions {
                    method: IcpMethod::PointToPlane,
                    max_correspondence_distance: self.options.icp_max_distance,
                    max_iterations: self.options.icp_iterations,
                    ..IcpOptions::default()
                };
                let result = target.register(&source, &one_shot.inverse(), &options)?;
                seconds.icp += t.elapsed().as_secs_f64();
                Ok((
                    result.pose.inverse().orthonormalised(),
                    Some(IcpSummary {
                        fitness: result.fitness,
                        inlier_rmse: result.inlier_rmse,
                        iterations: result.iterations,
                    }),
                ))
            }
        }
    }

    /// One draw of M model and N observed points, the network, ICP, and the confidence.
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
            one_shot,
            confidence: self.explained(object, voxels, &pose),
            inlier_count: estimate.inlier_count,
            assignment_confidence: estimate.assignment_confidence,
            icp,
        })
    }
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
    one_shot: Pose,
    confidence: f64,
    inlier_count: usize,
    assignment_confidence: f32,
    icp: Option<IcpSummary>,
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
