//! Seeded scene assembly: the object alone, or inside the paper's cube room, with optional
//! distractors and a support plane, plus a camera on the view sphere around the object.
//!
//! World frame: z up, metres (or normalised object units; the object is expected in
//! [-1, 1]³, ≈ 2 across). The room's floor is z = 0 and its walls are at x, y = ±side/2.

use std::sync::{Arc, Mutex};

use glam::{DMat3, DVec3};
use ic_geometry::{Intrinsics, Mesh, Pose, ViewSphere, Viewpoint};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::RenderError;
use crate::procedural;
use crate::renderer::{Camera, DEFAULT_NEAR, Scene};

/// Instance id of the object of interest.
pub const OBJECT_ID: u32 = 1;
/// Instance id of the room (walls, floor, ceiling).
pub const ROOM_ID: u32 = 2;
/// Instance id of the support plane.
pub const SUPPORT_ID: u32 = 3;
/// Distractor `i` gets id `DISTRACTOR_ID_BASE + i`.
pub const DISTRACTOR_ID_BASE: u32 = 10;

/// What surrounds the object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// Nothing: the object (plus optional distractors / support plane) in empty space.
    None,
    /// The paper's BlenderProc set-up: a closed cube room.
    Room,
}

/// How the object is oriented in the world.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectRotation {
    /// The model frame is the world frame (the paper: viewpoint ranges refer to the model).
    Canonical,
    /// A random rotation about the vertical (z) axis.
    Vertical,
    /// A uniformly random rotation.
    Uniform,
}

/// The cube room.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RoomConfig {
    /// Side length (the paper: 4).
    pub side: f64,
    /// Grid quads per face side.
    pub subdivisions: u32,
    /// Largest bump height on walls and ceiling (0 = flat).
    pub bump_amplitude: f64,
    /// Gaussian bumps per face.
    pub bumps_per_face: u32,
    /// Seed of the bumps. The room is built once per builder and shared by all samples, so a
    /// GPU renderer uploads it once.
    pub seed: u64,
}

impl Default for RoomConfig {
    fn default() -> Self {
        RoomConfig {
            side: 4.0,
            subdivisions: 24,
            bump_amplitude: 0.05,
            bumps_per_face: 8,
            seed: 0,
        }
    }
}

/// A square slab under the object (a table top).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SupportPlaneConfig {
    /// Side length of the square.
    pub size: f64,
    /// Thickness of the slab.
    pub thickness: f64,
}

impl Default for SupportPlaneConfig {
    fn default() -> Self {
        SupportPlaneConfig {
            size: 3.0,
            thickness: 0.05,
        }
    }
}

/// Clutter around the object: random boxes, or the meshes given to
/// [`SceneBuilder::with_distractor_meshes`] (normalised to `size`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DistractorConfig {
    pub count: usize,
    /// Range of the largest side of a distractor.
    pub size: (f64, f64),
    /// Range of the horizontal distance of a distractor from the object's bounding circle.
    pub gap: (f64, f64),
}

impl Default for DistractorConfig {
    fn default() -> Self {
        DistractorConfig {
            count: 0,
            size: (0.2, 0.8),
            gap: (0.05, 1.0),
        }
    }
}

/// Everything that defines a family of scenes. Serialisable; every random choice is drawn
/// from the seed given to [`SceneBuilder::build`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneConfig {
    pub background: Background,
    pub room: RoomConfig,
    /// Default: 640×480, fx = fy = 525 (a Kinect v1 / PrimeSense-like sensor, 49° vertical
    /// field of view), principal point at the image centre.
    pub intrinsics: Intrinsics,
    /// Default: the paper's ranges (elevation 15°–75°, azimuth 0°–89°) at distance 2.8: an
    /// object normalised to [-1, 1] has a bounding sphere of radius ≈ 1.0–1.5 (1.2 typical),
    /// which at 2.8 fills the 49° vertical field of view (1.2 / sin 24.5° ≈ 2.9).
    pub view: ViewSphere,
    /// Near clipping distance.
    pub near: f64,
    pub rotation: ObjectRotation,
    /// Room only: probability that the object floats instead of resting on the floor (or on
    /// the support plane).
    pub floating_probability: f64,
    /// Range of the gap between the floor and a floating object's lowest point.
    pub floating_gap: (f64, f64),
    /// Room only: the least distance between the camera or the object and a wall or the
    /// ceiling.
    pub wall_margin: f64,
    pub support_plane: Option<SupportPlaneConfig>,
    pub distractors: DistractorConfig,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            background: Background::Room,
            room: RoomConfig::default(),
            intrinsics: Intrinsics::KINECT_640X480,
            view: ViewSphere::paper(2.8),
            near: DEFAULT_NEAR,
            rotation: ObjectRotation::Canonical,
            floating_probability: 0.5,
            floating_gap: (0.1, 0.8),
            wall_margin: 0.05,
            support_plane: None,
            distractors: DistractorConfig::default(),
        }
    }
}

impl SceneConfig {
    /// The object alone in empty space.
    pub fn object_only() -> Self {
        SceneConfig {
            background: Background::None,
            ..SceneConfig::default()
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |field: &'static str, message: String| {
            Err(RenderError::InvalidConfig { field, message })
        };
        self.intrinsics.validate()?;
        let range_ok = |(lo, hi): (f64, f64), min: f64| {
            lo.is_finite() && hi.is_finite() && lo >= min && hi >= lo
        };
        if !(self.room.side.is_finite() && self.room.side > 0.0) {
            return bad(
                "room.side",
                format!("must be positive, got {}", self.room.side),
            );
        }
        if !(self.room.bump_amplitude.is_finite()
            && self.room.bump_amplitude >= 0.0
            && self.room.bump_amplitude < self.room.side / 4.0)
        {
            return bad(
                "room.bump_amplitude",
                format!("must be in [0, side/4), got {}", self.room.bump_amplitude),
            );
        }
        if !(self.view.distance.is_finite() && self.view.distance > 0.0) {
            return bad(
                "view.distance",
                format!("must be positive, got {}", self.view.distance),
            );
        }
        if !range_ok(self.view.elevation_deg, -90.0) || self.view.elevation_deg.1 > 90.0 {
            return bad(
                "view.elevation_deg",
                format!(
                    "{:?} is not an ordered range in [-90, 90]",
                    self.view.elevation_deg
                ),
            );
        }
        if !range_ok(self.view.azimuth_deg, f64::NEG_INFINITY) {
            return bad(
                "view.azimuth_deg",
                format!("{:?} is not an ordered range", self.view.azimuth_deg),
            );
        }
        if !(self.near.is_finite() && self.near > 0.0) {
            return bad("near", format!("must be positive, got {}", self.near));
        }
        if !(0.0..=1.0).contains(&self.floating_probability) {
            return bad(
                "floating_probability",
                format!("must be in [0, 1], got {}", self.floating_probability),
            );
        }
        if !range_ok(self.floating_gap, 0.0) {
            return bad(
                "floating_gap",
                format!(
                    "{:?} is not an ordered range of non-negative values",
                    self.floating_gap
                ),
            );
        }
        if !(self.wall_margin.is_finite() && self.wall_margin >= 0.0) {
            return bad(
                "wall_margin",
                format!("must be non-negative, got {}", self.wall_margin),
            );
        }
        if let Some(p) = &self.support_plane
            && !(p.size > 0.0 && p.thickness > 0.0 && p.size.is_finite() && p.thickness.is_finite())
        {
            return bad(
                "support_plane",
                format!(
                    "size and thickness must be positive, got {} and {}",
                    p.size, p.thickness
                ),
            );
        }
        if !range_ok(self.distractors.size, 0.0) || self.distractors.size.0 <= 0.0 {
            return bad(
                "distractors.size",
                format!(
                    "{:?} is not an ordered range of positive values",
                    self.distractors.size
                ),
            );
        }
        if !range_ok(self.distractors.gap, 0.0) {
            return bad(
                "distractors.gap",
                format!(
                    "{:?} is not an ordered range of non-negative values",
                    self.distractors.gap
                ),
            );
        }
        if self.distractors.count as u64 + DISTRACTOR_ID_BASE as u64 > crate::MAX_INSTANCE_ID as u64
        {
            return bad(
                "distractors.count",
                format!(
                    "{} distractors do not fit 16-bit ids",
                    self.distractors.count
                ),
            );
        }
        Ok(())
    }
}

/// One assembled sample: the scene, the camera and the ground truth.
#[derive(Clone, Debug)]
pub struct SceneSample {
    pub scene: Scene,
    pub camera: Camera,
    /// Model→world pose of the object (id [`OBJECT_ID`]).
    pub object_pose: Pose,
    /// The viewpoint relative to the object's bounding-box centre.
    pub viewpoint: Viewpoint,
}

impl SceneSample {
    /// The ground-truth model→camera pose, `x_cam = R·x_model + t`.
    pub fn object_to_camera(&self) -> Pose {
        self.camera.pose.compose(&self.object_pose)
    }
}

/// Builds seeded scenes from a [`SceneConfig`].
#[derive(Debug)]
pub struct SceneBuilder {
    config: SceneConfig,
    distractor_meshes: Vec<Arc<Mesh>>,
    room: Mutex<Option<Arc<Mesh>>>,
}

const MAX_TRIES: usize = 10_000;

impl SceneBuilder {
    /// Validates the configuration.
    pub fn new(config: SceneConfig) -> Result<Self, RenderError> {
        config.validate()?;
        Ok(SceneBuilder {
            config,
            distractor_meshes: Vec::new(),
            room: Mutex::new(None),
        })
    }

    /// Uses these meshes (scaled to the configured size) instead of random boxes.
    pub fn with_distractor_meshes(mut self, meshes: Vec<Arc<Mesh>>) -> Self {
        self.distractor_meshes = meshes;
        self
    }

    pub fn config(&self) -> &SceneConfig {
        &self.config
    }

    /// The room mesh (built once, shared by every sample).
    pub fn room_mesh(&self) -> Arc<Mesh> {
        let mut guard = self.room.lock().unwrap_or_else(|e| e.into_inner());
        guard
            .get_or_insert_with(|| {
                let r = &self.config.room;
                Arc::new(procedural::room(
                    r.side,
                    r.subdivisions,
                    r.bump_amplitude,
                    r.bumps_per_face,
                    r.seed,
                ))
            })
            .clone()
    }

    /// Assembles the scene for `seed` around `object` (a mesh in its model frame, expected
    /// normalised to [-1, 1]).
    pub fn build(&self, object: &Arc<Mesh>, seed: u64) -> Result<SceneSample, RenderError> {
        object
            .validate()
            .map_err(|source| RenderError::InvalidMesh { index: 0, source })?;
        let cfg = &self.config;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let rotation = match cfg.rotation {
            ObjectRotation::Canonical => DMat3::IDENTITY,
            ObjectRotation::Vertical => {
                DMat3::from_rotation_z(rng.random_range(0.0..std::f64::consts::TAU))
            }
            ObjectRotation::Uniform => uniform_rotation(&mut rng),
        };
        // Extent of the rotated object (world axes, relative to its model origin).
        let rotated: Vec<DVec3> = object
            .vertices
            .iter()
            .map(|v| rotation * v.as_dvec3())
            .collect();
        let (lo, hi) = rotated
            .iter()
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            });
        let centre_offset = 0.5 * (lo + hi);
        let half = 0.5 * (hi - lo);
        // Radius of the object's footprint around its bounding-box centre.
        let footprint = rotated
            .iter()
            .map(|p| DVec3::new(p.x - centre_offset.x, p.y - centre_offset.y, 0.0).length())
            .fold(0.0, f64::max);
        let slab = cfg.support_plane.clone();
        let slab_top = slab.as_ref().map_or(0.0, |p| p.thickness + 0.001);

        let mut scene = Scene::new();
        let (object_pose, viewpoint, camera_pose, floor_z);
        match cfg.background {
            Background::None => {
                // The object's bounding-box centre at the world origin.
                object_pose = Pose::new(rotation, -centre_offset);
                viewpoint = cfg.view.sample(&mut rng);
                camera_pose = viewpoint.camera_pose(DVec3::ZERO)?;
                floor_z = f64::NEG_INFINITY; // no floor: only the slab, if any, supports
            }
            Background::Room => {
                let h = cfg.room.side / 2.0;
                let m = cfg.wall_margin;
                let floating = rng.random_bool(cfg.floating_probability);
                let mut found = None;
                for _ in 0..MAX_TRIES {
                    let lift = if floating {
                        uniform(&mut rng, cfg.floating_gap)
                    } else {
                        0.0
                    };
                    let (lx, ly) = (h - m - half.x, h - m - half.y);
                    if lx <= 0.0 || ly <= 0.0 {
                        break;
                    }
                    let x = rng.random_range(-lx..=lx);
                    let y = rng.random_range(-ly..=ly);
                    let z = slab_top + lift + half.z;
                    if z + half.z > cfg.room.side - m {
                        continue;
                    }
                    let centre = DVec3::new(x, y, z);
                    let vp = cfg.view.sample(&mut rng);
                    let eye = centre + vp.offset();
                    let inside = eye.x.abs() < h - m
                        && eye.y.abs() < h - m
                        && eye.z > m
                        && eye.z < cfg.room.side - m;
                    if inside {
                        found = Some((centre, vp));
                        break;
                    }
                }
                let (centre, vp) = found.ok_or(RenderError::PlacementFailed {
                    what: "the object and camera in the room",
                    tries: MAX_TRIES,
                })?;
                object_pose = Pose::new(rotation, centre - centre_offset);
                viewpoint = vp;
                camera_pose = vp.camera_pose(centre)?;
                floor_z = 0.0;
                scene.push(self.room_mesh(), Pose::IDENTITY, ROOM_ID);
            }
        }
        scene.objects.insert(
            0,
            crate::SceneObject {
                mesh: object.clone(),
                pose: object_pose,
                id: OBJECT_ID,
            },
        );
        // The object's bounding-box centre in the world.
        let centre = object_pose.translation + centre_offset;

        // The slab lies on the floor in the room (1 mm above it, so no face is coplanar), and
        // 1 mm under the object's lowest point otherwise.
        let slab_top_z = match cfg.background {
            Background::Room => slab_top,
            Background::None => centre.z - half.z - 0.001,
        };
        if let Some(p) = &slab {
            let mesh = ic_geometry::shapes::box_mesh(
                DVec3::new(p.size / 2.0, p.size / 2.0, p.thickness / 2.0).as_vec3(),
            )
            .map_err(|e| RenderError::InvalidConfig {
                field: "support_plane",
                message: e.to_string(),
            })?;
            let pose = Pose::from_translation(DVec3::new(
                centre.x,
                centre.y,
                slab_top_z - p.thickness / 2.0,
            ));
            scene.push(Arc::new(mesh), pose, SUPPORT_ID);
        }

        // Distractors: on the slab or floor when there is one, else floating at the object's
        // height; never over the object's footprint or the camera.
        let eye = camera_pose.inverse().translation;
        let has_ground = slab.is_some() || cfg.background == Background::Room;
        let rest_z = |c: DVec3| match &slab {
            Some(p)
                if (c.x - centre.x).abs() < p.size / 2.0
                    && (c.y - centre.y).abs() < p.size / 2.0 =>
            {
                slab_top_z
            }
            _ => floor_z,
        };
        let mut placed: Vec<(DVec3, f64)> = Vec::new();
        for i in 0..cfg.distractors.count {
            let size = uniform(&mut rng, cfg.distractors.size);
            let mesh = if self.distractor_meshes.is_empty() {
                let e = DVec3::new(
                    rng.random_range(0.3..1.0),
                    rng.random_range(0.3..1.0),
                    rng.random_range(0.3..1.0),
                );
                ic_geometry::shapes::box_mesh((e / e.max_element() * (size / 2.0)).as_vec3())
                    .map_err(|e| RenderError::InvalidConfig {
                        field: "distractors.size",
                        message: e.to_string(),
                    })?
            } else {
                let src =
                    &self.distractor_meshes[rng.random_range(0..self.distractor_meshes.len())];
                scaled_to(src, size)
            };
            let yaw = DMat3::from_rotation_z(rng.random_range(0.0..std::f64::consts::TAU));
            let pts: Vec<DVec3> = mesh.vertices.iter().map(|v| yaw * v.as_dvec3()).collect();
            let (dlo, dhi) = pts
                .iter()
                .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &p| {
                    (lo.min(p), hi.max(p))
                });
            let dr = DVec3::new(0.5 * (dhi.x - dlo.x), 0.5 * (dhi.y - dlo.y), 0.0).length();
            let dc = 0.5 * (dlo + dhi);
            let mut ok = None;
            for _ in 0..MAX_TRIES {
                // In the room: anywhere on the floor; else on a ring around the object.
                let xy = if cfg.background == Background::Room {
                    let h = cfg.room.side / 2.0 - cfg.wall_margin - dr;
                    if h <= 0.0 {
                        break;
                    }
                    let xy = DVec3::new(rng.random_range(-h..=h), rng.random_range(-h..=h), 0.0);
                    let d = DVec3::new(xy.x - centre.x, xy.y - centre.y, 0.0).length();
                    if d < footprint + dr + cfg.distractors.gap.0 {
                        continue;
                    }
                    xy
                } else {
                    let dist = footprint + dr + uniform(&mut rng, cfg.distractors.gap);
                    let ang = rng.random_range(0.0..std::f64::consts::TAU);
                    DVec3::new(
                        centre.x + dist * ang.cos(),
                        centre.y + dist * ang.sin(),
                        0.0,
                    )
                };
                let c = DVec3::new(xy.x, xy.y, 0.0);
                let ground = rest_z(c);
                if has_ground && !ground.is_finite() {
                    continue; // off the slab, and there is no floor
                }
                let z = if has_ground {
                    ground - dlo.z + 0.001
                } else {
                    centre.z + rng.random_range(-half.z..=half.z) - dc.z
                };
                let pos = DVec3::new(xy.x - dc.x, xy.y - dc.y, z);
                if cfg.background == Background::Room {
                    let h = cfg.room.side / 2.0 - cfg.wall_margin;
                    if c.x.abs() + dr > h || c.y.abs() + dr > h {
                        continue;
                    }
                }
                if DVec3::new(eye.x - c.x, eye.y - c.y, 0.0).length() < dr + 0.2 {
                    continue;
                }
                if placed.iter().any(|&(q, r)| (q - c).length() < r + dr) {
                    continue;
                }
                ok = Some((pos, c));
                break;
            }
            let Some((pos, c)) = ok else {
                return Err(RenderError::PlacementFailed {
                    what: "a distractor",
                    tries: MAX_TRIES,
                });
            };
            placed.push((c, dr));
            scene.push(
                Arc::new(mesh),
                Pose::new(yaw, pos),
                DISTRACTOR_ID_BASE + i as u32,
            );
        }

        let camera = Camera {
            intrinsics: cfg.intrinsics,
            pose: camera_pose,
            near: cfg.near,
        };
        Ok(SceneSample {
            scene,
            camera,
            object_pose,
            viewpoint,
        })
    }
}

fn uniform<R: Rng>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    if hi > lo {
        rng.random_range(lo..=hi)
    } else {
        lo
    }
}

/// A uniformly distributed rotation (Shoemake's unit-quaternion method).
fn uniform_rotation<R: Rng>(rng: &mut R) -> DMat3 {
    let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
    let tau = std::f64::consts::TAU;
    let q = glam::DQuat::from_xyzw(
        (1.0 - u1).sqrt() * (tau * u2).sin(),
        (1.0 - u1).sqrt() * (tau * u2).cos(),
        u1.sqrt() * (tau * u3).sin(),
        u1.sqrt() * (tau * u3).cos(),
    );
    DMat3::from_quat(q.normalize())
}

/// A copy of `mesh` centred on its bounding box and scaled so its largest side is `size`.
fn scaled_to(mesh: &Mesh, size: f64) -> Mesh {
    let b = mesh.bounds().expect("validated mesh");
    let s = size / b.extent().max_element().max(1e-12);
    let c = b.centre();
    Mesh {
        vertices: mesh
            .vertices
            .iter()
            .map(|v| ((v.as_dvec3() - c) * s).as_vec3())
            .collect(),
        triangles: mesh.triangles.clone(),
    }
}
