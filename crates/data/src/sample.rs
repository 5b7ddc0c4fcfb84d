//! Object-alone samples, as the paper trains and tests without background.
//!
//! Sample `index` of a generator seeded with `seed` is a pure function of `(seed, index)`, the
//! corpus and the configuration: pick an object of the split, a camera on the view sphere,
//! render depth, back-project the object's pixels, voxelise, draw M model points and N
//! observed points, and build the ground-truth assignment.
//!
//! With every deployment switch off ([`ObjectSampleConfig::default`], the paper's protocol)
//! samples are those of the first version, byte for byte. Any switch on (see
//! [`crate::deploy`] and [`ObjectSampleConfig::deployment`]) selects the deployment path:
//! whole-sphere views, roll, distances by image span, border truncation, scale augmentation,
//! occluders and the sensor model, each on its own.

use std::sync::Arc;

use glam::Vec3;
use ic_geometry::{
    DepthImage, Intrinsics, Mask, Normalisation, Pose, ViewSphere, Viewpoint,
    random_subsample_indices, voxel_downsample_points,
};
use ic_render::{
    Background, CpuRenderer, OBJECT_ID, ObjectRotation, Renderer, SceneBuilder, SceneConfig,
};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::deploy::{
    CameraDistance, ImagePlacement, OccluderConfig, PhysicalScale, ScaleAugmentation, SensorRanges,
    ViewSampling,
};
use crate::seed::sample_rng;
use crate::{Assignment, Corpus, DataError};

/// The paper's voxel size, 0.05·√2/2 ≈ 0.0354 normalised units.
pub const PAPER_VOXEL_SIZE: f32 = 0.05 * std::f32::consts::FRAC_1_SQRT_2;
/// The paper's ground-truth match threshold (normalised units).
pub const PAPER_MATCH_THRESHOLD: f32 = 0.05;

/// Settings of [`ObjectSampleGenerator`]. Lengths are normalised object units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ObjectSampleConfig {
    /// Default 160×120, fx = fy = 131.25, principal point at the centre: the 640×480 / 525 px
    /// Kinect-like camera of the room set scaled by 1/4 (same 49° vertical field of view).
    /// At the default distance 2.8 a pixel covers 2.8/131.25 ≈ 0.021 units, finer than the
    /// 0.0354 voxel, so the voxelised view is voxel-limited (about 1 500–5 000 points for a
    /// visible area of 2–6 units²), comfortably above N = 768; a larger image only costs time.
    pub intrinsics: Intrinsics,
    /// Default: the paper's ranges (elevation 15°–75°, azimuth 0°–89°) at distance 2.8. The
    /// paper's 0.65 was in its renderer's scale; an object normalised into [-1, 1] has a
    /// bounding sphere of radius ≈ 1.0–1.5, which at 2.8 fills the 49° vertical field of view
    /// (1.2 / sin 24.5° ≈ 2.9) without leaving the image.
    pub view: ViewSphere,
    pub rotation: ObjectRotation,
    /// Voxel size before sampling (the paper: 0.05·√2/2).
    pub voxel_size: f32,
    /// M (the paper: 1024).
    pub model_points: usize,
    /// N (the paper: 768).
    pub observed_points: usize,
    /// Ground-truth match threshold (the paper: 0.05).
    pub match_threshold: f32,
    /// A view with fewer voxels than this is redrawn (another object and viewpoint from the
    /// same sample stream), up to `max_attempts` times.
    pub min_observed_voxels: usize,
    pub max_attempts: usize,
    /// Keep the depth map and object mask in the sample (needed to write BOP datasets).
    pub keep_images: bool,

    // Deployment switches (all off: the paper's protocol; see `crate::deploy`).
    /// View directions: the paper's ranges of `view`, or the whole sphere.
    pub viewpoints: ViewSampling,
    /// A uniform camera roll about the optical axis.
    pub camera_roll: bool,
    /// The camera distance: `view.distance`, or by the object's span in the image.
    pub distance: CameraDistance,
    /// Where the object projects (`None`: centred, the paper); truncation by the border.
    pub placement: Option<ImagePlacement>,
    /// Anisotropic scale of the model (renormalised to [-1, 1]).
    pub scale_augmentation: Option<ScaleAugmentation>,
    /// A board or bar hiding part of the object.
    pub occluder: Option<OccluderConfig>,
    /// The sensor model with strengths drawn per sample (`None`: ideal depth).
    pub sensor: Option<SensorRanges>,
    /// Physical size and distance of the object (used by the sensor model only).
    pub physical: PhysicalScale,
    /// 3×3 erosions of the object mask before back-projection (the pipeline: 1).
    pub mask_erosions: usize,
    /// Keep observed points within this distance of their centroid (the pipeline: 1.2).
    pub crop_radius: Option<f32>,
    /// Re-express each view in a rotated copy of the model: 0 = off; 12, 24 or 60 = the
    /// rotation group (`ic_geometry::rotations`) whose element `G` puts the model → camera
    /// rotation of the copy `G·X` (the pose becomes `pose·G⁻¹`) nearest the paper's central
    /// view rotation. The network then learns only the rotations within the group's covering
    /// radius (≈ 63° for 24) of the family it already knows, and `register --rotations 24`
    /// registers the same copies at inference and verifies them.
    pub copy_rotations: usize,
    /// List the poses equivalent to the true one under the object's symmetries
    /// ([`crate::CorpusObject::symmetries`]) and their assignments
    /// ([`ObjectSample::equivalent_poses`], [`ObjectSample::alternatives`]), so that training
    /// can score the equivalent pose nearest its prediction and validation can measure the
    /// rotation error up to symmetry. Deployment path only.
    #[serde(default)]
    pub symmetry_aware: bool,
}

/// At most this many equivalent poses are listed per sample (evenly spread over the
/// symmetries found, which a continuous axis fills with one per 10°).
pub const MAX_EQUIVALENT_POSES: usize = 36;

impl Default for ObjectSampleConfig {
    fn default() -> Self {
        ObjectSampleConfig {
            intrinsics: Intrinsics {
                fx: 131.25,
                fy: 131.25,
                cx: 79.5,
                cy: 59.5,
                width: 160,
                height: 120,
            },
            view: ViewSphere::paper(2.8),
            rotation: ObjectRotation::Canonical,
            voxel_size: PAPER_VOXEL_SIZE,
            model_points: 1024,
            observed_points: 768,
            match_threshold: PAPER_MATCH_THRESHOLD,
            min_observed_voxels: 64,
            max_attempts: 8,
            keep_images: false,
            viewpoints: ViewSampling::Paper,
            camera_roll: false,
            distance: CameraDistance::Fixed,
            placement: None,
            scale_augmentation: None,
            occluder: None,
            sensor: None,
            physical: PhysicalScale::default(),
            mask_erosions: 0,
            crop_radius: None,
            copy_rotations: 0,
            symmetry_aware: false,
        }
    }
}

impl ObjectSampleConfig {
    /// The paper's protocol (the default).
    pub fn paper() -> Self {
        ObjectSampleConfig::default()
    }

    /// Samples like deployment (every switch of [`crate::deploy`] on): a 640×480 Kinect-like
    /// camera (fx = fy = 525), view directions on the whole sphere, camera roll, any object
    /// orientation, the object's bounding sphere spanning 10 %–100 % of the image height
    /// (log-uniform), a quarter of the views free to be cut by the image border, ±20 %
    /// anisotropic scale, an occluder in 60 % of the views hiding 0–50 % of the object, the
    /// sensor model with drawn strengths at a physical size of 5–40 cm and 0.4–2 m, the
    /// pipeline's mask erosion and 1.2-unit crop, symmetry-aware ground truth. Voxel size, M,
    /// N, the match threshold and the minimum of 64 voxels are the paper's.
    pub fn deployment() -> Self {
        ObjectSampleConfig {
            intrinsics: Intrinsics::KINECT_640X480,
            rotation: ObjectRotation::Uniform,
            viewpoints: ViewSampling::Sphere,
            camera_roll: true,
            distance: CameraDistance::ImageSpan { min: 0.1, max: 1.0 },
            placement: Some(ImagePlacement::default()),
            scale_augmentation: Some(ScaleAugmentation::default()),
            occluder: Some(OccluderConfig::default()),
            sensor: Some(SensorRanges::default()),
            mask_erosions: 1,
            crop_radius: Some(1.2),
            copy_rotations: 24,
            symmetry_aware: true,
            ..ObjectSampleConfig::default()
        }
    }

    /// Whether every deployment switch is off (samples follow the paper's path).
    pub fn is_paper_protocol(&self) -> bool {
        self.viewpoints == ViewSampling::Paper
            && !self.camera_roll
            && self.distance == CameraDistance::Fixed
            && self.placement.is_none()
            && self.scale_augmentation.is_none()
            && self.occluder.is_none()
            && self.sensor.is_none()
            && self.mask_erosions == 0
            && self.crop_radius.is_none()
            && self.copy_rotations == 0
            && !self.symmetry_aware
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), DataError> {
        let bad = |field: &'static str, message: String| Err(DataError::Config { field, message });
        if !(self.voxel_size.is_finite() && self.voxel_size > 0.0) {
            return bad(
                "voxel_size",
                format!("must be positive, got {}", self.voxel_size),
            );
        }
        if self.model_points == 0 || self.observed_points == 0 {
            return bad("model_points/observed_points", "must be ≥ 1".into());
        }
        if !(self.match_threshold.is_finite() && self.match_threshold >= 0.0) {
            return bad(
                "match_threshold",
                format!("must be ≥ 0, got {}", self.match_threshold),
            );
        }
        if self.max_attempts == 0 {
            return bad("max_attempts", "must be ≥ 1".into());
        }
        crate::deploy::validate(self)
    }

    fn scene_config(&self) -> SceneConfig {
        SceneConfig {
            background: Background::None,
            intrinsics: self.intrinsics,
            view: self.view,
            rotation: self.rotation,
            ..SceneConfig::object_only()
        }
    }
}

/// One object-alone training/test sample.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectSample {
    pub index: u64,
    /// Corpus id of the object.
    pub object_id: String,
    /// X: M model points (model frame, normalised units).
    pub model_points: Vec<Vec3>,
    /// Y: N observed points (camera frame, normalised units).
    pub observed_points: Vec<Vec3>,
    /// The true model→camera pose: Y ≈ pose·X on the matched pairs.
    pub pose: Pose,
    /// M̄.
    pub assignment: Assignment,
    pub viewpoint: Viewpoint,
    /// Object pixels with a depth return.
    pub visible_pixels: usize,
    /// Points after voxelising, before drawing N.
    pub observed_voxels: usize,
    pub normalisation: Normalisation,
    pub intrinsics: Intrinsics,
    /// Depth (normalised units) and object mask, when `keep_images` is set.
    pub depth: Option<DepthImage>,
    pub mask: Option<Mask>,
    /// Per-axis factors that map the corpus object's normalised mesh and model points to the
    /// model given to the network (scale augmentation, renormalised; 1 without it).
    pub model_scale: Vec3,
    /// Metres per normalised unit at which the sensor model saw the object (deployment path;
    /// 0 on the paper's path).
    pub metres_per_unit: f64,
    /// Fraction of the object's visible pixels hidden by the occluder (0 without one).
    pub occluded_fraction: f64,
    /// Whether the object touches the image border.
    pub truncated: bool,
    /// The sensor drawn for this sample (`None`: ideal depth).
    pub sensor: Option<ic_render::SensorConfig>,
    /// Poses equivalent to `pose` under the object's symmetries (the same surface in the same
    /// place; model points as given → camera), without `pose` itself; empty unless
    /// [`ObjectSampleConfig::symmetry_aware`] and the object has a symmetry that survives the
    /// sample's scale augmentation.
    pub equivalent_poses: Vec<Pose>,
    /// M̄ under each of `equivalent_poses`, in the same order.
    pub alternatives: Vec<Assignment>,
}

impl ObjectSample {
    /// Matched pairs (rows of M̄ that are not in the bin).
    pub fn inlier_count(&self) -> usize {
        self.assignment.inlier_count()
    }
}

/// Seeded object-alone sample generator. Cheap to share across threads (`Arc`).
pub struct ObjectSampleGenerator {
    corpus: Arc<Corpus>,
    config: ObjectSampleConfig,
    seed: u64,
    builder: SceneBuilder,
    /// The rotation group of `config.copy_rotations` (`None` when 0).
    copy_group: Option<Vec<ic_geometry::Pose>>,
}

impl std::fmt::Debug for ObjectSampleGenerator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectSampleGenerator")
            .field("corpus", &self.corpus)
            .field("config", &self.config)
            .field("seed", &self.seed)
            .finish()
    }
}

impl ObjectSampleGenerator {
    pub fn new(
        corpus: Arc<Corpus>,
        config: ObjectSampleConfig,
        seed: u64,
    ) -> Result<Self, DataError> {
        config.validate()?;
        let builder = SceneBuilder::new(config.scene_config())?;
        let copy_group =
            match config.copy_rotations {
                0 => None,
                n => Some(ic_geometry::rotations::rotation_group(n).map_err(|e| {
                    DataError::Config {
                        field: "copy_rotations",
                        message: e.to_string(),
                    }
                })?),
            };
        Ok(ObjectSampleGenerator {
            corpus,
            config,
            seed,
            builder,
            copy_group,
        })
    }

    pub fn config(&self) -> &ObjectSampleConfig {
        &self.config
    }

    pub fn corpus(&self) -> &Arc<Corpus> {
        &self.corpus
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Sample `index`, rendered with the CPU renderer.
    pub fn sample(&self, index: u64) -> Result<ObjectSample, DataError> {
        self.sample_with(&mut CpuRenderer::new(), index)
    }

    /// Sample `index`, rendered with `renderer` (any backend gives the same sample up to the
    /// backends' depth agreement).
    pub fn sample_with(
        &self,
        renderer: &mut dyn Renderer,
        index: u64,
    ) -> Result<ObjectSample, DataError> {
        if self.config.is_paper_protocol() {
            self.sample_paper(renderer, index)
        } else {
            self.sample_deployment(renderer, index)
        }
    }

    fn sample_deployment(
        &self,
        renderer: &mut dyn Renderer,
        index: u64,
    ) -> Result<ObjectSample, DataError> {
        let cfg = &self.config;
        let mut rng = sample_rng(self.seed, index);
        let mut last_count = 0;
        for _ in 0..cfg.max_attempts {
            let object = self.corpus.pick(&mut rng)?;
            let view_seed: u64 = rng.random();
            let view = crate::deploy::render_view(cfg, renderer, &object, view_seed)?;
            let drawn = draw_points(
                cfg,
                &object,
                &view.points,
                view.model_scale,
                index,
                &mut rng,
            )?;
            last_count = drawn.voxels;
            let Some((observed_points, mut model_points)) = drawn.points else {
                continue;
            };
            let mut pose = view.pose;
            let mut copy = Pose::IDENTITY;
            if let Some(group) = &self.copy_group {
                let (g, _) = ic_geometry::rotations::nearest_in_group(
                    &pose,
                    group,
                    &ic_geometry::rotations::paper_view_rotation(),
                );
                copy = group[g];
                model_points = copy.apply_all(&model_points);
                pose = pose.compose(&copy.inverse());
            }
            let assignment =
                Assignment::from_pose(&model_points, &observed_points, &pose, cfg.match_threshold)?;
            let equivalent_poses = if cfg.symmetry_aware {
                equivalent_poses(&pose, &object.symmetries(), view.model_scale, &copy)
            } else {
                Vec::new()
            };
            let alternatives = equivalent_poses
                .iter()
                .map(|p| {
                    Assignment::from_pose(&model_points, &observed_points, p, cfg.match_threshold)
                })
                .collect::<Result<Vec<_>, _>>()?;
            let (depth, mask) = match view.images {
                Some((d, m)) => (Some(d), Some(m)),
                None => (None, None),
            };
            return Ok(ObjectSample {
                index,
                object_id: object.id.clone(),
                model_points,
                observed_points,
                pose,
                assignment,
                viewpoint: view.viewpoint,
                visible_pixels: view.visible_pixels,
                observed_voxels: drawn.voxels,
                normalisation: object.normalisation,
                intrinsics: cfg.intrinsics,
                depth,
                mask,
                model_scale: view.model_scale,
                metres_per_unit: view.metres_per_unit,
                occluded_fraction: view.occluded_fraction,
                truncated: view.truncated,
                sensor: view.sensor,
                equivalent_poses,
                alternatives,
            });
        }
        Err(too_few_voxels(cfg, index, last_count))
    }

    /// The paper's protocol, exactly as the first version drew it.
    fn sample_paper(
        &self,
        renderer: &mut dyn Renderer,
        index: u64,
    ) -> Result<ObjectSample, DataError> {
        let cfg = &self.config;
        let mut rng = sample_rng(self.seed, index);
        let mut last_count = 0;
        for _ in 0..cfg.max_attempts {
            let object = self.corpus.pick(&mut rng)?;
            let scene_seed: u64 = rng.random();
            let built = self.builder.build(&object.mesh, scene_seed)?;
            let rendering = renderer.render(&built.scene, &built.camera)?;
            let mask = rendering.mask(OBJECT_ID);
            let pixels = cfg
                .intrinsics
                .back_project_depth(&rendering.depth, Some(&mask))?;
            let drawn = draw_points(cfg, &object, &pixels, Vec3::ONE, index, &mut rng)?;
            last_count = drawn.voxels;
            let Some((observed_points, model_points)) = drawn.points else {
                continue;
            };
            let pose = built.object_to_camera();
            let assignment =
                Assignment::from_pose(&model_points, &observed_points, &pose, cfg.match_threshold)?;
            let (depth, mask) = if cfg.keep_images {
                (Some(rendering.depth), Some(mask))
            } else {
                (None, None)
            };
            return Ok(ObjectSample {
                index,
                object_id: object.id.clone(),
                model_points,
                observed_points,
                pose,
                assignment,
                viewpoint: built.viewpoint,
                visible_pixels: pixels.len(),
                observed_voxels: drawn.voxels,
                normalisation: object.normalisation,
                intrinsics: cfg.intrinsics,
                depth,
                mask,
                model_scale: Vec3::ONE,
                metres_per_unit: 0.0,
                occluded_fraction: 0.0,
                truncated: false,
                sensor: None,
                equivalent_poses: Vec::new(),
                alternatives: Vec::new(),
            });
        }
        Err(too_few_voxels(cfg, index, last_count))
    }
}

/// The poses equivalent to `pose` (model points as given → camera) under `symmetries` of the
/// corpus object (normalised frame), when the model given is the corpus object scaled per axis
/// by `model_scale` and then rotated by `copy`: each symmetry `S = (R, t)` becomes
/// `A·S·A⁻¹ = (G·D·R·D⁻¹·Gᵀ, G·D·t)` with `A = G·D`, kept when `D·R·D⁻¹` is still a rotation
/// (an anisotropic scale breaks the symmetries that mix unequally scaled axes), and the
/// equivalent pose is `pose·A·S·A⁻¹`. At most [`MAX_EQUIVALENT_POSES`], evenly spread.
pub fn equivalent_poses(
    pose: &Pose,
    symmetries: &[Pose],
    model_scale: Vec3,
    copy: &Pose,
) -> Vec<Pose> {
    use glam::{DMat3, DVec3};
    let d = DMat3::from_diagonal(model_scale.as_dvec3());
    let d_inv = DMat3::from_diagonal(DVec3::ONE / model_scale.as_dvec3());
    let g = copy.rotation;
    let kept: Vec<Pose> = symmetries
        .iter()
        .filter_map(|s| {
            let r = d * s.rotation * d_inv;
            let off = (r.transpose() * r - DMat3::IDENTITY)
                .to_cols_array()
                .iter()
                .fold(0.0f64, |m, x| m.max(x.abs()));
            (off < 0.01).then(|| {
                let r = Pose::new(r, DVec3::ZERO).orthonormalised().rotation;
                pose.compose(&Pose::new(g * r * g.transpose(), g * (d * s.translation)))
            })
        })
        .collect();
    if kept.len() <= MAX_EQUIVALENT_POSES {
        return kept;
    }
    (0..MAX_EQUIVALENT_POSES)
        .map(|k| kept[k * kept.len() / MAX_EQUIVALENT_POSES])
        .collect()
}

/// What [`draw_points`] drew from one view.
struct Drawn {
    /// Observed voxels of the view.
    voxels: usize,
    /// N observed points (camera frame) and M model points (model frame, scaled by the view's
    /// model scale); `None` when the view has fewer voxels than `min_observed_voxels`.
    points: Option<(Vec<Vec3>, Vec<Vec3>)>,
}

/// Voxelises a view's observed `points` and draws N of the voxels, then M of the object's
/// model points (scaled by `model_scale`), in that order, from `rng`; both protocols draw this
/// way.
fn draw_points(
    cfg: &ObjectSampleConfig,
    object: &crate::CorpusObject,
    points: &[Vec3],
    model_scale: Vec3,
    index: u64,
    rng: &mut impl Rng,
) -> Result<Drawn, DataError> {
    let voxels = if points.is_empty() {
        Vec::new()
    } else {
        voxel_downsample_points(points, cfg.voxel_size)?
    };
    if voxels.len() < cfg.min_observed_voxels.max(1) {
        tracing::debug!(index, object = %object.id, voxels = voxels.len(), "too few observed voxels; redrawing");
        return Ok(Drawn {
            voxels: voxels.len(),
            points: None,
        });
    }
    let yi = random_subsample_indices(voxels.len(), cfg.observed_points, rng)?;
    let observed: Vec<Vec3> = yi.iter().map(|&i| voxels[i]).collect();
    let xi = random_subsample_indices(object.model_points.len(), cfg.model_points, rng)?;
    let model: Vec<Vec3> = xi
        .iter()
        .map(|&i| object.model_points[i] * model_scale)
        .collect();
    Ok(Drawn {
        voxels: voxels.len(),
        points: Some((observed, model)),
    })
}

/// The error of a sample whose `max_attempts` views all had too few observed voxels.
fn too_few_voxels(cfg: &ObjectSampleConfig, index: u64, last_count: usize) -> DataError {
    DataError::Sample {
        index,
        message: format!(
            "no view with at least {} observed voxels in {} attempts (last: {last_count})",
            cfg.min_observed_voxels, cfg.max_attempts
        ),
    }
}
