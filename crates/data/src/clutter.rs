//! Cluttered scenes like real ones (issue 15): a table top, a bin or a shelf holding 3–15
//! objects at their physical size, the target among them (sometimes several instances of it,
//! as in bin picking), seen by a depth sensor 0.4–1.5 m away.
//!
//! # Frames and units
//! Everything is in **metres**: the world frame has z up and the support's top surface at
//! z = 0; the camera frame is OpenCV's (x right, y down, z forward); depth maps hold camera z
//! in metres (0 = no return). Meshes come from a [`Corpus`] normalised into [-1, 1]; each
//! object is given a physical size (its longest side, 5–30 cm by default), i.e. a scale
//! `scale_m` in metres per normalised unit, and [`ClutterObject::pose`] maps the **scaled**
//! model (metres, `scale_m · normalised`) into the camera frame.
//!
//! # How a scene is built (decisions; the paper renders one object per room)
//! - **Resting poses**: an object lies on one of the six faces of its principal-axes box
//!   (chosen with probability ∝ the face's area, so a box lies flat more often than on its
//!   end and a can stands or lies), turned about the vertical, tilted by up to 8°. It is then
//!   dropped straight down onto a height map of what is already there (1 cm cells): objects
//!   land on the support or on top of earlier ones (stacks), never below the support. Leaning
//!   against a wall and physics beyond this vertical drop are not simulated, so objects may
//!   interpenetrate slightly at their sides.
//! - **Supports**: a table (top 0.5–1.4 m, a floor 0.75 m below, sometimes a wall behind), a
//!   bin (0.3–0.6 m inside, walls 8–25 cm high; objects stay inside), or a shelf (a plank with
//!   a back wall and a plank above, seen from the front and low).
//! - **Placement**: the objects' centres are drawn in a square of 0.2–0.6 m on the support
//!   (the bin's interior), so they touch, occlude and stack.
//! - **Camera**: it looks at the placement area's centre (±5 cm) from 0.4–1.5 m, from above for
//!   tables and bins (elevation 30–85°), from the front for shelves (5–35°), rolled by up to ±15°.
//! - **Sensor**: the deployment sensor model ([`SensorRanges`]) drawn per scene.
//!
//! Every scene is a pure function of (seed, index, corpus, configuration).

use std::sync::Arc;

use glam::{DMat3, DVec3, Vec3};
use ic_geometry::{DepthImage, InstanceImage, Intrinsics, Mask, Mesh, Pose, principal_axes};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::deploy::SensorRanges;
use crate::seed::{mix, sample_rng};
use crate::{Corpus, CorpusObject, DataError};

/// Instance ids of the objects are `1..=n` in placement order; the support's parts have ids
/// from this base on (the floor, the walls, the planks), so `id < SUPPORT_ID_BASE` means
/// "an object".
pub const SUPPORT_ID_BASE: u32 = 1000;

/// What holds the objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SupportKind {
    Table,
    Bin,
    Shelf,
}

impl SupportKind {
    pub fn as_str(self) -> &'static str {
        match self {
            SupportKind::Table => "table",
            SupportKind::Bin => "bin",
            SupportKind::Shelf => "shelf",
        }
    }
}

/// Settings of [`ClutterGenerator`]. Metres, degrees, pixels of `intrinsics`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClutterConfig {
    /// The camera (default 640×480, fx = fy = 525: a Kinect-like VGA depth camera).
    pub intrinsics: Intrinsics,
    /// Number of objects in the scene, target instances included (inclusive range).
    pub object_count: (usize, usize),
    /// Longest side of each object in metres, drawn log-uniformly.
    pub longest_side_m: (f64, f64),
    /// Distance from the camera to the placement area's centre, metres.
    pub distance_m: (f64, f64),
    /// Relative frequencies of table, bin and shelf.
    pub support_weights: [f64; 3],
    /// Probability that the target appears several times (bin picking) …
    pub multi_target_probability: f64,
    /// … and then how many times (inclusive range; capped by `object_count`).
    pub target_copies: (usize, usize),
    /// Largest camera roll about its viewing axis, degrees.
    pub camera_roll_deg: f64,
    /// The sensor model's strengths (None = ideal depth).
    pub sensor: Option<SensorRanges>,
    /// Give each object one size, drawn from its id (so a test set's models have fixed
    /// dimensions, as real objects do), instead of a size per scene.
    pub fixed_sizes: bool,
    /// Also render each object alone, for its full silhouette ([`ClutterObject::full_mask`];
    /// BOP's `mask/` and `visib_fract`).
    pub full_masks: bool,
    /// A scene is redrawn (another attempt stream) when the target's first instance shows
    /// fewer depth returns than this, in pixels of the 640×480 Kinect-like camera (scaled with
    /// fx·fy, what an object's pixel count scales with, for another camera).
    pub min_target_pixels: usize,
    pub max_attempts: usize,
}

impl Default for ClutterConfig {
    fn default() -> Self {
        ClutterConfig {
            intrinsics: Intrinsics::KINECT_640X480,
            object_count: (3, 15),
            longest_side_m: (0.05, 0.30),
            distance_m: (0.4, 1.5),
            support_weights: [0.5, 0.3, 0.2],
            multi_target_probability: 0.25,
            target_copies: (2, 6),
            camera_roll_deg: 15.0,
            sensor: Some(SensorRanges::default()),
            fixed_sizes: false,
            full_masks: false,
            min_target_pixels: 100,
            max_attempts: 16,
        }
    }
}

impl ClutterConfig {
    /// The same scenes at another resolution (field of view kept), e.g. for training the
    /// segmentation network.
    pub fn with_resolution(mut self, width: u32, height: u32) -> Self {
        self.intrinsics = self.intrinsics.resized(width, height);
        self
    }

    /// The same scenes seen through another camera (pixels; e.g. a 1280×720 RealSense-like
    /// one): the scenes' geometry and the camera's pose are kept, the image is what this
    /// camera sees of them, and the sensor model is applied at its resolution.
    pub fn with_camera(mut self, intrinsics: Intrinsics) -> Self {
        self.intrinsics = intrinsics;
        self
    }

    /// The same scenes with the projector's shadows and the registration's holes, each with
    /// probability `p` (`SensorRanges::set_shadows`); no change with an ideal sensor.
    pub fn with_shadows(mut self, p: f64) -> Self {
        if let Some(sensor) = &mut self.sensor {
            sensor.set_shadows(p);
        }
        self
    }

    pub fn validate(&self) -> Result<(), DataError> {
        let bad = |field: &'static str, message: String| Err(DataError::Config { field, message });
        self.intrinsics.validate().map_err(|e| DataError::Config {
            field: "intrinsics",
            message: e.to_string(),
        })?;
        let ordered =
            |(lo, hi): (f64, f64)| lo.is_finite() && hi.is_finite() && lo > 0.0 && hi >= lo;
        let (lo, hi) = self.object_count;
        if lo == 0 || hi < lo || hi >= SUPPORT_ID_BASE as usize {
            return bad(
                "object_count",
                format!("must be an ordered range within 1..{SUPPORT_ID_BASE}, got {lo}..={hi}"),
            );
        }
        if !ordered(self.longest_side_m) || !ordered(self.distance_m) {
            return bad(
                "longest_side_m/distance_m",
                "must be ordered ranges of positive lengths".into(),
            );
        }
        if self
            .support_weights
            .iter()
            .any(|w| !(w.is_finite() && *w >= 0.0))
            || self.support_weights.iter().sum::<f64>() <= 0.0
        {
            return bad(
                "support_weights",
                format!(
                    "must be non-negative with a positive sum, got {:?}",
                    self.support_weights
                ),
            );
        }
        if !(0.0..=1.0).contains(&self.multi_target_probability) {
            return bad(
                "multi_target_probability",
                format!("must be in [0, 1], got {}", self.multi_target_probability),
            );
        }
        if self.target_copies.0 < 1 || self.target_copies.1 < self.target_copies.0 {
            return bad(
                "target_copies",
                format!("must be an ordered range ≥ 1, got {:?}", self.target_copies),
            );
        }
        if !(self.camera_roll_deg.is_finite() && (0.0..=180.0).contains(&self.camera_roll_deg)) {
            return bad(
                "camera_roll_deg",
                format!("must be in [0, 180], got {}", self.camera_roll_deg),
            );
        }
        if let Some(s) = &self.sensor {
            s.validate_ranges().map_err(|message| DataError::Config {
                field: "sensor",
                message,
            })?;
        }
        if self.max_attempts == 0 {
            return bad("max_attempts", "must be ≥ 1".into());
        }
        Ok(())
    }
}

/// One object placed in a scene.
#[derive(Clone, Debug)]
pub struct ClutterObject {
    /// Its id in [`ClutterScene::instances`] (`1..=n`).
    pub instance_id: u32,
    pub object: Arc<CorpusObject>,
    /// Metres per normalised unit (half the longest side in metres).
    pub scale_m: f64,
    /// Scaled model (metres) → camera (metres).
    pub pose: Pose,
    /// An instance of the scene's target object.
    pub is_target: bool,
    /// Pixels showing it with a depth return (after the sensor model).
    pub visible_pixels: usize,
    /// Its whole silhouette, as if nothing hid it (before the sensor model), when the
    /// configuration asks for it.
    pub full_mask: Option<Mask>,
}

impl ClutterObject {
    /// The normalised model → camera pose in metres, i.e. [`ClutterObject::pose`] applied
    /// after scaling by `scale_m`: `x_cam = R·(scale_m·x) + t`. Dividing by `scale_m` gives the
    /// pose in the object's normalised units (what `ic_pose` estimates).
    pub fn pose_normalised(&self) -> Pose {
        Pose::new(self.pose.rotation, self.pose.translation / self.scale_m)
    }
}

/// One rendered cluttered scene.
#[derive(Clone, Debug)]
pub struct ClutterScene {
    pub index: u64,
    pub support: SupportKind,
    pub intrinsics: Intrinsics,
    /// Camera z in metres, 0 = no return, after the sensor model.
    pub depth: DepthImage,
    /// Which instance each pixel shows (0: nothing or no return; `≥ SUPPORT_ID_BASE`: the
    /// support), after the sensor model.
    pub instances: InstanceImage,
    /// In placement order; the target's instances first.
    pub objects: Vec<ClutterObject>,
    /// World → camera (metres).
    pub camera_pose: Pose,
}

impl ClutterScene {
    /// The visible pixels (with a depth return) of instance `id`.
    pub fn mask(&self, id: u32) -> Mask {
        Mask {
            width: self.instances.width,
            height: self.instances.height,
            data: self.instances.data.iter().map(|&i| i == id).collect(),
        }
    }

    /// The pixels of every object (the support excluded), with a depth return.
    pub fn objects_mask(&self) -> Mask {
        Mask {
            width: self.instances.width,
            height: self.instances.height,
            data: self
                .instances
                .data
                .iter()
                .map(|&i| i != 0 && i < SUPPORT_ID_BASE)
                .collect(),
        }
    }

    /// The target's instances, in placement order.
    pub fn targets(&self) -> impl Iterator<Item = &ClutterObject> {
        self.objects.iter().filter(|o| o.is_target)
    }
}

/// Renders [`ClutterScene`]s from a corpus on the CPU.
pub struct ClutterGenerator {
    corpus: Arc<Corpus>,
    config: ClutterConfig,
    seed: u64,
}

impl std::fmt::Debug for ClutterGenerator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClutterGenerator")
            .field("objects", &self.corpus.len())
            .field("seed", &self.seed)
            .finish_non_exhaustive()
    }
}

/// FNV-1a of `bytes` (a stable hash of an object id, whatever the platform).
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// Height-map cell (metres) of the vertical drop.
const CELL_M: f64 = 0.01;
/// Model points used for the drop, per object.
const DROP_POINTS: usize = 1500;
/// Largest random tilt of a resting object, degrees.
const MAX_TILT_DEG: f64 = 8.0;

/// The support's parts (world frame, metres), the square objects are dropped in, and
/// whether objects must stay inside it (a bin).
struct Support {
    parts: Vec<(Mesh, DVec3)>,
    /// Centre (x, y) and half side of the placement square.
    area_centre: (f64, f64),
    area_half: f64,
    confined: bool,
    /// Camera elevation range (degrees) and azimuth centre ± half range (degrees).
    elevation_deg: (f64, f64),
    azimuth_deg: (f64, f64),
}

fn uniform<R: Rng + ?Sized>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    if hi > lo {
        rng.random_range(lo..=hi)
    } else {
        lo
    }
}

fn slab(half: DVec3, centre: DVec3) -> (Mesh, DVec3) {
    let mesh = ic_geometry::shapes::box_mesh(half.as_vec3()).expect("positive half extents");
    (mesh, centre)
}

fn build_support(kind: SupportKind, rng: &mut ChaCha8Rng) -> Support {
    let mut parts = Vec::new();
    match kind {
        SupportKind::Table => {
            let (w, d) = (uniform(rng, (0.5, 1.4)), uniform(rng, (0.5, 0.9)));
            parts.push(slab(
                DVec3::new(w / 2.0, d / 2.0, 0.015),
                DVec3::new(0.0, 0.0, -0.015),
            ));
            parts.push(slab(
                DVec3::new(3.0, 3.0, 0.01),
                DVec3::new(0.0, 0.0, -0.76),
            ));
            if rng.random_bool(0.5) {
                let y = d / 2.0 + uniform(rng, (0.05, 1.0));
                parts.push(slab(DVec3::new(3.0, 0.01, 1.5), DVec3::new(0.0, y, 0.5)));
            }
            let half = uniform(rng, (0.1, 0.3))
                .min(w / 2.0 - 0.05)
                .min(d / 2.0 - 0.05);
            Support {
                parts,
                area_centre: (
                    uniform(rng, (-(w / 2.0 - half - 0.05), w / 2.0 - half - 0.05)),
                    uniform(rng, (-(d / 2.0 - half - 0.05), d / 2.0 - half - 0.05)),
                ),
                area_half: half,
                confined: false,
                elevation_deg: (30.0, 85.0),
                azimuth_deg: (0.0, 180.0),
            }
        }
        SupportKind::Bin => {
            let (w, d) = (uniform(rng, (0.3, 0.6)), uniform(rng, (0.3, 0.6)));
            let h = uniform(rng, (0.08, 0.25));
            let t = 0.01;
            parts.push(slab(
                DVec3::new(w / 2.0 + t, d / 2.0 + t, t / 2.0),
                DVec3::new(0.0, 0.0, -t / 2.0),
            ));
            for s in [-1.0, 1.0] {
                parts.push(slab(
                    DVec3::new(t / 2.0, d / 2.0 + t, h / 2.0),
                    DVec3::new(s * (w / 2.0 + t / 2.0), 0.0, h / 2.0),
                ));
                parts.push(slab(
                    DVec3::new(w / 2.0 + t, t / 2.0, h / 2.0),
                    DVec3::new(0.0, s * (d / 2.0 + t / 2.0), h / 2.0),
                ));
            }
            parts.push(slab(
                DVec3::new(3.0, 3.0, 0.01),
                DVec3::new(0.0, 0.0, -t - 0.01 - uniform(rng, (0.0, 0.8))),
            ));
            Support {
                parts,
                area_centre: (0.0, 0.0),
                area_half: w.min(d) / 2.0,
                confined: true,
                elevation_deg: (45.0, 85.0),
                azimuth_deg: (0.0, 180.0),
            }
        }
        SupportKind::Shelf => {
            let (w, d) = (uniform(rng, (0.6, 1.2)), uniform(rng, (0.3, 0.45)));
            let gap = uniform(rng, (0.3, 0.5));
            parts.push(slab(
                DVec3::new(w / 2.0, d / 2.0, 0.01),
                DVec3::new(0.0, 0.0, -0.01),
            ));
            parts.push(slab(
                DVec3::new(w / 2.0, d / 2.0, 0.01),
                DVec3::new(0.0, 0.0, gap + 0.01),
            ));
            parts.push(slab(
                DVec3::new(w / 2.0, 0.01, gap / 2.0 + 0.3),
                DVec3::new(0.0, d / 2.0 + 0.01, gap / 2.0),
            ));
            parts.push(slab(DVec3::new(3.0, 3.0, 0.01), DVec3::new(0.0, 0.0, -0.9)));
            let half = (d / 2.0 - 0.02).min(0.25);
            Support {
                parts,
                area_centre: (uniform(rng, (-(w / 2.0 - half), w / 2.0 - half)), 0.0),
                area_half: half,
                confined: false,
                elevation_deg: (5.0, 35.0),
                // The shelf opens towards −y: the camera stands at azimuth −90° ± 50°.
                azimuth_deg: (-90.0, 50.0),
            }
        }
    }
}

/// A resting orientation of an object whose (normalised) model points are `points`: the
/// world-from-model rotation.
fn resting_rotation(points: &[Vec3], rng: &mut ChaCha8Rng) -> DMat3 {
    let (axes, _) = principal_axes(points).unwrap_or(([DVec3::X, DVec3::Y, DVec3::Z], [1.0; 3]));
    let extent = |a: DVec3| {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in points {
            let x = p.as_dvec3().dot(a);
            lo = lo.min(x);
            hi = hi.max(x);
        }
        (hi - lo).max(1e-6)
    };
    let e = [extent(axes[0]), extent(axes[1]), extent(axes[2])];
    let areas = [e[1] * e[2], e[0] * e[2], e[0] * e[1]];
    let u: f64 = rng.random::<f64>() * areas.iter().sum::<f64>();
    let k = if u < areas[0] {
        0
    } else if u < areas[0] + areas[1] {
        1
    } else {
        2
    };
    let down = if rng.random_bool(0.5) {
        axes[k]
    } else {
        -axes[k]
    };
    // The rotation taking `down` (model frame) to −z (world).
    let r0 = DMat3::from_quat(glam::DQuat::from_rotation_arc(down, DVec3::NEG_Z));
    let yaw = DMat3::from_rotation_z(rng.random_range(0.0..std::f64::consts::TAU));
    let tilt_axis = DVec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        0.0,
    )
    .try_normalize()
    .unwrap_or(DVec3::X);
    let tilt = DMat3::from_axis_angle(tilt_axis, rng.random_range(0.0..=MAX_TILT_DEG).to_radians());
    tilt * yaw * r0
}

/// The height map of the vertical drop.
struct HeightMap {
    origin: (f64, f64),
    cells: usize,
    heights: Vec<f64>,
}

impl HeightMap {
    fn new(centre: (f64, f64), half: f64) -> Self {
        let cells = ((2.0 * half) / CELL_M).ceil() as usize + 1;
        HeightMap {
            origin: (centre.0 - half, centre.1 - half),
            cells,
            heights: vec![0.0; cells * cells],
        }
    }

    fn cell(&self, x: f64, y: f64) -> Option<usize> {
        let i = ((x - self.origin.0) / CELL_M).floor();
        let j = ((y - self.origin.1) / CELL_M).floor();
        (i >= 0.0 && j >= 0.0 && (i as usize) < self.cells && (j as usize) < self.cells)
            .then(|| j as usize * self.cells + i as usize)
    }

    /// The lift that puts `points` (world offsets from (x, y, 0)) on what is below them.
    fn drop(&mut self, x: f64, y: f64, points: &[DVec3]) -> f64 {
        let mut z = f64::NEG_INFINITY;
        for p in points {
            let h = self.cell(x + p.x, y + p.y).map_or(0.0, |c| self.heights[c]);
            z = z.max(h - p.z);
        }
        for p in points {
            if let Some(c) = self.cell(x + p.x, y + p.y) {
                self.heights[c] = self.heights[c].max(z + p.z);
            }
        }
        z
    }
}

impl ClutterGenerator {
    pub fn new(corpus: Arc<Corpus>, config: ClutterConfig, seed: u64) -> Result<Self, DataError> {
        config.validate()?;
        if corpus.is_empty() {
            return Err(DataError::Config {
                field: "corpus",
                message: "no objects to place".into(),
            });
        }
        Ok(ClutterGenerator {
            corpus,
            config,
            seed,
        })
    }

    pub fn config(&self) -> &ClutterConfig {
        &self.config
    }

    pub fn corpus(&self) -> &Arc<Corpus> {
        &self.corpus
    }

    /// Scene `index` (a pure function of the seed, the index, the corpus and the config).
    pub fn scene(&self, index: u64) -> Result<ClutterScene, DataError> {
        let mut renderer = CpuRenderer::new();
        let mut last = 0;
        for attempt in 0..self.config.max_attempts as u64 {
            let stream = mix(mix(self.seed, index), attempt);
            let scene = self.attempt(&mut renderer, index, stream)?;
            // An object's pixel count scales with fx·fy: the same as the image's area for
            // `with_resolution` (the field of view kept).
            let (k, kinect) = (&self.config.intrinsics, Intrinsics::KINECT_640X480);
            let need = (self.config.min_target_pixels as f64 * (k.fx * k.fy)
                / (kinect.fx * kinect.fy))
                .round() as usize;
            last = scene.objects[0].visible_pixels;
            if last >= need.max(1) {
                return Ok(scene);
            }
        }
        Err(DataError::Sample {
            index,
            message: format!(
                "the target stayed hidden in {} attempts (last: {last} visible pixels, {} needed at 640×480)",
                self.config.max_attempts, self.config.min_target_pixels
            ),
        })
    }

    fn attempt(
        &self,
        renderer: &mut CpuRenderer,
        index: u64,
        stream: u64,
    ) -> Result<ClutterScene, DataError> {
        let cfg = &self.config;
        let mut rng = sample_rng(stream, 0);
        let w = cfg.support_weights;
        let u: f64 = rng.random::<f64>() * w.iter().sum::<f64>();
        let kind = if u < w[0] {
            SupportKind::Table
        } else if u < w[0] + w[1] {
            SupportKind::Bin
        } else {
            SupportKind::Shelf
        };
        let support = build_support(kind, &mut rng);
        let n = rng.random_range(cfg.object_count.0..=cfg.object_count.1);
        let copies = if n > 1 && rng.random_bool(cfg.multi_target_probability) {
            rng.random_range(cfg.target_copies.0..=cfg.target_copies.1)
                .min(n)
        } else {
            1
        };
        let target = self.corpus.pick(&mut rng)?;
        let log_uniform = |rng: &mut ChaCha8Rng| {
            let (lo, hi) = cfg.longest_side_m;
            uniform(rng, (lo.ln(), hi.ln())).exp() / 2.0
        };
        // A fixed size per object: its own stream from its id (the draw from `rng` still
        // happens, so the rest of the scene does not depend on the switch).
        let size_of = |o: &CorpusObject, drawn: f64| {
            if cfg.fixed_sizes {
                log_uniform(&mut sample_rng(fnv1a(o.id.as_bytes()), 0x7369_7a65))
            } else {
                drawn
            }
        };
        let mut chosen: Vec<(Arc<CorpusObject>, f64, bool)> = Vec::with_capacity(n);
        let target_scale = size_of(&target, log_uniform(&mut rng));
        for _ in 0..copies {
            chosen.push((target.clone(), target_scale, true));
        }
        while chosen.len() < n {
            let mut o = self.corpus.pick(&mut rng)?;
            // Other objects are other objects (a corpus of one repeats it).
            for _ in 0..8 {
                if o.id != target.id {
                    break;
                }
                o = self.corpus.pick(&mut rng)?;
            }
            let s = size_of(&o, log_uniform(&mut rng));
            chosen.push((o, s, false));
        }
        // Drop the objects in a random order, so targets are not always at the bottom.
        let mut order: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            order.swap(i, rng.random_range(0..=i));
        }
        let mut heights = HeightMap::new(support.area_centre, support.area_half + 0.4);
        let mut world_poses = vec![Pose::default(); n];
        for &i in &order {
            let (o, s, _) = &chosen[i];
            let r = resting_rotation(&o.model_points, &mut rng);
            // The mesh's vertices (its lowest point is one) and surface samples (so wide flat
            // faces mark the cells between their corners).
            let step = (o.model_points.len() / DROP_POINTS).max(1);
            let offsets: Vec<DVec3> = o
                .mesh
                .vertices
                .iter()
                .chain(o.model_points.iter().step_by(step))
                .map(|p| r * (p.as_dvec3() * *s))
                .collect();
            let half = offsets
                .iter()
                .map(|p| p.x.abs().max(p.y.abs()))
                .fold(0.0, f64::max);
            let room = if support.confined {
                (support.area_half - half).max(0.0)
            } else {
                support.area_half
            };
            let x = support.area_centre.0 + uniform(&mut rng, (-room, room));
            let y = support.area_centre.1 + uniform(&mut rng, (-room, room));
            let z = heights.drop(x, y, &offsets);
            world_poses[i] = Pose::new(r, DVec3::new(x, y, z));
        }

        // The camera.
        let (ax, ay) = support.area_centre;
        let look = DVec3::new(
            ax + uniform(&mut rng, (-0.05, 0.05)),
            ay + uniform(&mut rng, (-0.05, 0.05)),
            uniform(&mut rng, (0.0, 0.05)),
        );
        let d = uniform(&mut rng, cfg.distance_m);
        let e = uniform(&mut rng, support.elevation_deg).to_radians();
        let (ac, ah) = support.azimuth_deg;
        let a = uniform(&mut rng, (ac - ah, ac + ah)).to_radians();
        let eye = look + d * DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
        let world_to_camera = ic_geometry::look_at(eye, look, DVec3::Z)?;
        let roll = uniform(&mut rng, (-cfg.camera_roll_deg, cfg.camera_roll_deg)).to_radians();
        let world_to_camera =
            Pose::new(DMat3::from_rotation_z(roll), DVec3::ZERO).compose(&world_to_camera);

        // The scene: scaled meshes (target copies share one), then the support.
        let mut scene = Scene::new();
        let mut meshes: Vec<(String, u64, Arc<Mesh>)> = Vec::new();
        for (i, (o, s, _)) in chosen.iter().enumerate() {
            let key = s.to_bits();
            let mesh = match meshes.iter().find(|(id, k, _)| *id == o.id && *k == key) {
                Some((_, _, m)) => m.clone(),
                None => {
                    let m = Arc::new(Mesh {
                        vertices: o
                            .mesh
                            .vertices
                            .iter()
                            .map(|v| (v.as_dvec3() * *s).as_vec3())
                            .collect(),
                        triangles: o.mesh.triangles.clone(),
                    });
                    meshes.push((o.id.clone(), key, m.clone()));
                    m
                }
            };
            scene.push(mesh, world_poses[i], i as u32 + 1);
        }
        for (k, (mesh, centre)) in support.parts.into_iter().enumerate() {
            scene.push(
                Arc::new(mesh),
                Pose::from_translation(centre),
                SUPPORT_ID_BASE + k as u32,
            );
        }
        let camera = Camera::new(cfg.intrinsics, world_to_camera);
        let full_masks: Vec<Option<Mask>> = if cfg.full_masks {
            scene
                .objects
                .iter()
                .take(n)
                .map(|o| {
                    let alone = Scene::single(o.mesh.clone(), o.pose, o.id);
                    Ok(Some(renderer.render(&alone, &camera)?.mask(o.id)))
                })
                .collect::<Result<_, DataError>>()?
        } else {
            vec![None; n]
        };
        let mut r = renderer.render(&scene, &camera)?;
        if let Some(ranges) = &cfg.sensor {
            let mut srng = sample_rng(stream, 1);
            let target_px = r.count_returns(1).0.max(1) as f64;
            let sensor = ranges.draw(&mut srng, target_px.sqrt(), cfg.intrinsics.fx);
            sensor.apply(&mut r, mix(stream, 2));
        }
        // No id where the sensor returned nothing.
        for (id, z) in r.instances.data.iter_mut().zip(&r.depth.data) {
            if z.is_nan() || *z <= 0.0 {
                *id = 0;
            }
        }
        let mut visible = vec![0usize; n + 1];
        for &id in &r.instances.data {
            if id >= 1 && (id as usize) <= n {
                visible[id as usize] += 1;
            }
        }
        let objects = chosen
            .into_iter()
            .zip(full_masks)
            .enumerate()
            .map(
                |(i, ((object, scale_m, is_target), full_mask))| ClutterObject {
                    instance_id: i as u32 + 1,
                    object,
                    scale_m,
                    pose: world_to_camera.compose(&world_poses[i]),
                    is_target,
                    visible_pixels: visible[i + 1],
                    full_mask,
                },
            )
            .collect();
        Ok(ClutterScene {
            index,
            support: kind,
            intrinsics: cfg.intrinsics,
            depth: r.depth,
            instances: r.instances,
            objects,
            camera_pose: world_to_camera,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CorpusOptions, Split};

    fn corpus() -> Arc<Corpus> {
        let options = CorpusOptions {
            model_points: 1024,
            ..CorpusOptions::default()
        };
        Arc::new(Corpus::procedural(6, Split::Train, 11, options).unwrap())
    }

    fn small() -> ClutterConfig {
        ClutterConfig::default().with_resolution(160, 120)
    }

    #[test]
    fn a_scene_is_a_pure_function_of_seed_and_index() {
        let g = ClutterGenerator::new(corpus(), small(), 5).unwrap();
        let (a, b) = (g.scene(3).unwrap(), g.scene(3).unwrap());
        assert_eq!(a.depth, b.depth);
        assert_eq!(a.instances, b.instances);
        let other = g.scene(4).unwrap();
        assert_ne!(a.depth, other.depth);
    }

    #[test]
    fn objects_rest_on_the_support_or_on_each_other_never_below_it() {
        let cfg = ClutterConfig {
            sensor: None,
            ..small()
        };
        let g = ClutterGenerator::new(corpus(), cfg, 9).unwrap();
        for index in 0..6 {
            let s = g.scene(index).unwrap();
            let (lo, hi) = g.config.object_count;
            assert!((lo..=hi).contains(&s.objects.len()));
            let camera_to_world = s.camera_pose.inverse();
            let mut on_support = 0;
            for o in &s.objects {
                let step = (o.object.mesh.vertices.len() / 2000).max(1);
                let min_z = o
                    .object
                    .mesh
                    .vertices
                    .iter()
                    .step_by(step)
                    .map(|v| {
                        camera_to_world
                            .apply(
                                o.pose
                                    .apply((v.as_dvec3() * o.scale_m).as_vec3().as_dvec3()),
                            )
                            .z
                    })
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    min_z > -0.002,
                    "scene {index}: an object sinks to z = {min_z}"
                );
                on_support += usize::from(min_z < 0.01);
            }
            assert!(
                on_support >= 1,
                "scene {index}: nothing stands on the support"
            );
            // Target copies are the same object at the same size.
            let targets: Vec<_> = s.targets().collect();
            assert!(!targets.is_empty() && s.objects[0].is_target);
            assert!(targets.iter().all(|t| t.object.id == targets[0].object.id
                && t.scale_m == targets[0].scale_m));
        }
    }

    #[test]
    fn the_camera_stays_in_its_range_and_ids_match_the_objects() {
        let cfg = ClutterConfig {
            sensor: None,
            distance_m: (0.6, 0.9),
            ..small()
        };
        let g = ClutterGenerator::new(corpus(), cfg, 2).unwrap();
        for index in 0..4 {
            let s = g.scene(index).unwrap();
            let eye = s.camera_pose.inverse().translation;
            // The camera looks at a point within 5 cm of the area centre, ≤ 5 cm up.
            assert!(eye.z > 0.0, "the camera is above the support");
            let n = s.objects.len() as u32;
            for &id in &s.instances.data {
                assert!(id == 0 || (1..=n).contains(&id) || id >= SUPPORT_ID_BASE);
            }
            for o in &s.objects {
                let px = s
                    .instances
                    .data
                    .iter()
                    .filter(|&&i| i == o.instance_id)
                    .count();
                assert_eq!(px, o.visible_pixels);
                // Every object lies in front of the camera.
                assert!(o.pose.translation.z > 0.0);
            }
            assert!(s.objects[0].visible_pixels >= 1);
        }
    }

    #[test]
    fn the_sensor_model_changes_depth_but_not_where_objects_are() {
        let clean = ClutterGenerator::new(
            corpus(),
            ClutterConfig {
                sensor: None,
                ..small()
            },
            4,
        )
        .unwrap()
        .scene(1)
        .unwrap();
        let noisy = ClutterGenerator::new(corpus(), small(), 4)
            .unwrap()
            .scene(1)
            .unwrap();
        assert_eq!(clean.objects.len(), noisy.objects.len());
        assert_eq!(clean.camera_pose, noisy.camera_pose);
        assert_ne!(clean.depth, noisy.depth);
    }

    #[test]
    fn fixed_sizes_give_an_object_one_size_and_full_masks_contain_the_visible_ones() {
        let cfg = ClutterConfig {
            fixed_sizes: true,
            full_masks: true,
            sensor: None,
            ..small()
        };
        let g = ClutterGenerator::new(corpus(), cfg, 8).unwrap();
        let mut sizes = std::collections::HashMap::new();
        let mut hidden = 0;
        for index in 0..5 {
            let s = g.scene(index).unwrap();
            for o in &s.objects {
                let size = *sizes.entry(o.object.id.clone()).or_insert(o.scale_m);
                assert_eq!(size, o.scale_m, "{} changed size", o.object.id);
                let full = o.full_mask.as_ref().unwrap();
                let visible = s.mask(o.instance_id);
                let full_px = full.data.iter().filter(|&&b| b).count();
                // Visible pixels lie inside the silhouette.
                let outside = visible
                    .data
                    .iter()
                    .zip(&full.data)
                    .filter(|(v, f)| **v && !**f)
                    .count();
                assert_eq!(outside, 0, "visible pixels outside the silhouette");
                hidden += usize::from(o.visible_pixels + 5 < full_px);
            }
        }
        assert!(sizes.len() > 1);
        assert!(hidden > 0, "no object was ever partly hidden");
    }

    #[test]
    fn bad_settings_are_refused() {
        for cfg in [
            ClutterConfig {
                object_count: (0, 3),
                ..ClutterConfig::default()
            },
            ClutterConfig {
                longest_side_m: (0.3, 0.1),
                ..ClutterConfig::default()
            },
            ClutterConfig {
                support_weights: [0.0; 3],
                ..ClutterConfig::default()
            },
            ClutterConfig {
                multi_target_probability: 1.5,
                ..ClutterConfig::default()
            },
        ] {
            assert!(matches!(
                ClutterGenerator::new(corpus(), cfg, 0),
                Err(DataError::Config { .. })
            ));
        }
    }
}
