//! Deployment-like object-alone samples: the switches of [`ObjectSampleConfig`] beyond the
//! paper's protocol, and the sampling path that honours them.
//!
//! The paper renders every object of one corpus from a quarter of the view sphere
//! (azimuth 0–89°, elevation 15–75°) at one distance with perfect depth. A user points a
//! Kinect or RealSense at a mug, a box or a machined part from any side at 0.4–2 m, partly
//! hidden or cut by the image border. The switches here draw such views, each on its own:
//!
//! - [`ViewSampling::Sphere`]: view directions uniform on the whole sphere (elevation
//!   `asin(U(−1, 1))`, azimuth `U(0°, 360°)`); `camera_roll`: a uniform roll about the optical
//!   axis; `ObjectRotation::Uniform`: any object orientation.
//! - [`CameraDistance::ImageSpan`]: the distance at which the object's bounding sphere spans a
//!   drawn fraction of the image height (log-uniform; 0.1–1.0 in the deployment protocol).
//! - [`ImagePlacement`]: the object's centre projects anywhere it keeps the object inside the
//!   image, or, with a probability, anywhere in the image (truncation by the border).
//! - [`ScaleAugmentation`]: anisotropic scale of the mesh per axis, then renormalised so that
//!   its longest side spans [-1, 1] again.
//! - [`OccluderConfig`]: a fronto-parallel board (half-plane) or bar (stripe) in front of the
//!   object, hiding a drawn fraction of its visible pixels.
//! - [`SensorRanges`]: the sensor model of `ic_render` ([`SensorConfig`]) with strengths drawn
//!   per sample, applied in metres ([`PhysicalScale`] maps the normalised object to a physical
//!   size and distance).
//! - `mask_erosions`, `crop_radius`: the deployment pipeline's 3×3 erosion of the mask and
//!   its 1.2-unit crop around the centroid.
//!
//! Every random choice of a sample comes from its own stream derived from the sample's
//! stream, so switching one effect on or off leaves the others' draws unchanged (the tests
//! rely on it: the same sample with and without noise, with and without the occluder).
//!
//! Rendering: only the window of the image that holds the object's projected vertices (plus a
//! margin) is rasterised, with the principal point shifted: the same rays, pixel for pixel, as
//! a full-size render, and a window clipped by the image border is exactly the truncated view.
//!
//! The ground truth stays exact under every switch: the pose maps the model points *as given
//! to the network* (scaled and renormalised) into the camera frame of the observed points
//! (normalised units), and M̄ is built from them as in the paper.

use std::sync::Arc;

use glam::{DMat3, DQuat, DVec3, Vec3};
use ic_geometry::{Intrinsics, Mask, Mesh, Pose, Viewpoint, look_at};
use ic_render::{
    AxialNoise, Camera, DropoutPatches, FlyingPixels, GrazingDropout, LateralJitter, OBJECT_ID,
    ProjectorShadow, Quantisation, Renderer, Rendering, Scene, SensorConfig,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::seed::mix;
use crate::{CorpusObject, DataError, ObjectSampleConfig};

/// Instance id of the occluder in the rendering of a deployment sample.
pub const OCCLUDER_ID: u32 = 4;

/// Pixels of margin around the object's projected vertices in the rendered window (covers the
/// 3σ reach of the lateral jitter at σ ≤ 1 px and the flying pixels' 4-neighbourhood).
const WINDOW_MARGIN: i64 = 4;

/// How view directions are drawn.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ViewSampling {
    /// Elevation and azimuth uniform (in degrees) in the ranges of `view` (the paper:
    /// elevation 15°–75°, azimuth 0°–89°).
    #[default]
    Paper,
    /// Uniform on the whole sphere: elevation `asin(U(−1, 1))`, azimuth `U(0°, 360°)`.
    Sphere,
}

impl ViewSampling {
    /// A unit direction from the object's centre towards the camera (world = model frame
    /// before the object's rotation; z up), and the viewpoint angles in degrees.
    pub fn draw<R: Rng + ?Sized>(
        &self,
        view: &ic_geometry::ViewSphere,
        rng: &mut R,
    ) -> (DVec3, f64, f64) {
        match self {
            ViewSampling::Paper => {
                let v = view.sample(rng);
                let (e, a) = (v.elevation_deg.to_radians(), v.azimuth_deg.to_radians());
                let dir = DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
                (dir, v.elevation_deg, v.azimuth_deg)
            }
            ViewSampling::Sphere => {
                let z: f64 = rng.random_range(-1.0..=1.0);
                let phi: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                let rho = (1.0 - z * z).max(0.0).sqrt();
                let dir = DVec3::new(rho * phi.cos(), rho * phi.sin(), z);
                (dir, z.asin().to_degrees(), phi.to_degrees())
            }
        }
    }
}

/// How far the camera is from the object's centre (normalised units).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum CameraDistance {
    /// `view.distance` (the paper's protocol: 2.8).
    #[default]
    Fixed,
    /// The distance at which the object's bounding sphere (radius `r` about its bounding-box
    /// centre, per object and after scale augmentation) spans a fraction `f` of the image
    /// height, `d = r / sin(atan(f·height / (2·fy)))`, with `f` log-uniform in `[min, max]`
    /// (as many views per octave of size). At the 640×480 / 525 px camera `f = 1` puts a
    /// sphere of radius 1.2 at 2.9 units, `f = 0.1` at 26 units, where a pixel covers
    /// 0.05 units — wider than the 0.0354 voxel, so the view yields about one voxel per pixel,
    /// a few hundred for small spans, as a 15 cm object at 1.2 m does on a Kinect.
    ImageSpan { min: f64, max: f64 },
}

/// Where the object's centre projects in the image. Without it the centre projects at the
/// principal point (the paper).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImagePlacement {
    /// With this probability the centre projects uniformly anywhere in the image (the object
    /// is then often cut by the border); otherwise uniformly where the projected bounding
    /// circle stays inside the image (at the principal point when it is larger than the
    /// image).
    pub truncation_probability: f64,
}

impl Default for ImagePlacement {
    fn default() -> Self {
        ImagePlacement {
            truncation_probability: 0.25,
        }
    }
}

/// Anisotropic scale of the normalised mesh: each axis of the model frame is multiplied by a
/// factor uniform in `[1 − max_relative, 1 + max_relative]`, then the mesh is renormalised
/// (divided by its largest half-extent) so that its longest side spans [-1, 1] again, as the
/// deployment pipeline normalises every mesh. Its bounding-box centre stays at the origin.
/// The model points given to the network are the object's cached points under the same map
/// (an affine map keeps a surface point on the surface and a visible point visible from the
/// mapped viewpoint; the density varies by at most the ratio of the factors).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScaleAugmentation {
    pub max_relative: f64,
}

impl Default for ScaleAugmentation {
    fn default() -> Self {
        ScaleAugmentation { max_relative: 0.2 }
    }
}

/// A flat occluder between the camera and the object: a board whose straight edge crosses
/// the object (a half-plane in the image) or, with `stripe_probability`, a bar (a stripe
/// between two parallel lines), in a random image direction. Its position is chosen on the
/// object's visible pixels so that it hides a fraction drawn uniformly from `hidden_fraction`
/// of them (exactly, up to pixels tied on the edge line). It is fronto-parallel, `gap`
/// normalised units (drawn uniformly) in front of the nearest object pixel it hides, and it
/// also covers the background on its side of the edge, so the sensor model sees its depth
/// edges against the object (flying pixels).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OccluderConfig {
    /// Probability that a sample has an occluder.
    pub probability: f64,
    pub hidden_fraction: (f64, f64),
    pub stripe_probability: f64,
    pub gap: (f64, f64),
}

impl Default for OccluderConfig {
    fn default() -> Self {
        OccluderConfig {
            probability: 0.6,
            hidden_fraction: (0.0, 0.5),
            stripe_probability: 0.3,
            gap: (0.1, 1.0),
        }
    }
}

/// The physical size of the object and its distance, which the sensor model needs (its noise
/// and thresholds are in metres; samples are in normalised units). Per sample, the scale `s`
/// (metres per normalised unit = half the object's longest side in metres) is drawn
/// log-uniformly from the scales that satisfy both ranges at the sample's normalised distance
/// `d`: `longest_side_m / 2` and `distance_m / d` (the closest scale of the size range to the
/// distance range when they do not meet). Depth in metres = depth in normalised units · `s`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhysicalScale {
    /// Longest side of the object in metres (default 5–40 cm: a part to a shoe box).
    pub longest_side_m: (f64, f64),
    /// Distance of the camera to the object's centre in metres (default 0.4–2 m: Kinect and
    /// RealSense working range, a little wider than the 0.5–1.5 m of use).
    pub distance_m: (f64, f64),
}

impl Default for PhysicalScale {
    fn default() -> Self {
        PhysicalScale {
            longest_side_m: (0.05, 0.40),
            distance_m: (0.4, 2.0),
        }
    }
}

/// Ranges of the sensor model's strengths; each sample draws one [`SensorConfig`] from them
/// (uniformly unless said otherwise). Metres and pixels of the full-resolution camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SensorRanges {
    /// Axial noise σ(z) = k·(a + b·(z − z0)²), Kinect v1's a, b, z0 ([`AxialNoise`]), k
    /// log-uniform in this range (1 = Kinect v1; RealSense D4xx is noisier with distance).
    pub noise_factor: (f64, f64),
    /// Disparity quantisation `z = fb / round_to(fb/z, 1/subpixel)`: the product focal ·
    /// baseline (px·m; Kinect v1 580 · 0.075 = 43.5, D435 ≈ 640 · 0.05 = 32) …
    pub focal_baseline: (f64, f64),
    /// … and the subpixel resolution (Kinect v1: 8).
    pub subpixel: (f64, f64),
    /// Missing returns beyond this angle between normal and ray (degrees).
    pub grazing_max_angle_deg: (f64, f64),
    /// Flying pixels: probability per edge pixel, and the depth jump (m) that makes an edge.
    pub flying_probability: (f64, f64),
    pub flying_edge_threshold_m: (f64, f64),
    /// Lateral jitter σ in pixels.
    pub jitter_sigma_px: (f64, f64),
    /// Dropout patches: count (inclusive range) and semi-axes as a fraction of the object's
    /// size in pixels (√ of its visible pixel count).
    pub patch_count: (usize, usize),
    pub patch_radius: (f64, f64),
    /// The probability that a drawn sensor casts the projector's shadows
    /// ([`ProjectorShadow`]: structured light and active stereo, e.g. Kinect v1, Primesense,
    /// RealSense D4xx): the pixels beside a nearer edge that the projector cannot light give
    /// no return. The baseline is the drawn focal · baseline product over Kinect v1's 580 px
    /// focal (0.05–0.09 m with the default range), on the camera's right or left at even
    /// odds. 0 (the default) keeps every earlier set's draws.
    pub shadow_probability: f64,
    /// The probability that the depth map is registered to a colour camera
    /// ([`SensorConfig::registration`]: a second, narrower band of holes beside the edges, on
    /// the other side), the depth camera `registration_baseline_m` away (Kinect v1 ≈ 0.025 m),
    /// on the side opposite the projector when the sensor has one, else either. 0 (the
    /// default) keeps every earlier set's draws.
    pub registration_probability: f64,
    pub registration_baseline_m: (f64, f64),
}

impl Default for SensorRanges {
    fn default() -> Self {
        SensorRanges {
            noise_factor: (0.5, 2.5),
            focal_baseline: (30.0, 50.0),
            subpixel: (4.0, 16.0),
            grazing_max_angle_deg: (70.0, 85.0),
            flying_probability: (0.0, 0.8),
            flying_edge_threshold_m: (0.02, 0.08),
            jitter_sigma_px: (0.0, 0.8),
            patch_count: (0, 3),
            patch_radius: (0.03, 0.2),
            shadow_probability: 0.0,
            registration_probability: 0.0,
            registration_baseline_m: (0.02, 0.05),
        }
    }
}

fn uniform<R: Rng + ?Sized>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    if hi > lo {
        rng.random_range(lo..=hi)
    } else {
        lo
    }
}

fn log_uniform<R: Rng + ?Sized>(rng: &mut R, (lo, hi): (f64, f64)) -> f64 {
    uniform(rng, (lo.ln(), hi.ln())).exp()
}

impl SensorRanges {
    /// One sensor drawn from the ranges; `object_px` is the object's size in pixels and
    /// `focal_px` the rendering's fx (the projector's shadows are as wide as the disparities
    /// it sees).
    pub fn draw<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        object_px: f64,
        focal_px: f64,
    ) -> SensorConfig {
        let k = log_uniform(rng, self.noise_factor);
        let base = AxialNoise::default();
        let (pl, ph) = self.patch_count;
        let count = if ph > pl {
            rng.random_range(pl..=ph)
        } else {
            pl
        };
        let r = self.patch_radius;
        // Kinect v1's focal length; the drawn product sets the baseline.
        let baseline = uniform(rng, self.focal_baseline) / 580.0;
        let mut sensor = SensorConfig {
            noise: Some(AxialNoise {
                a: k * base.a,
                b: k * base.b,
                z0: base.z0,
            }),
            quantisation: Some(Quantisation::Disparity {
                focal: 580.0,
                baseline,
                subpixel: uniform(rng, self.subpixel),
            }),
            grazing: Some(GrazingDropout {
                max_angle_deg: uniform(rng, self.grazing_max_angle_deg),
            }),
            flying_pixels: Some(FlyingPixels {
                probability: uniform(rng, self.flying_probability),
                edge_threshold: uniform(rng, self.flying_edge_threshold_m),
            }),
            lateral_jitter: Some(LateralJitter {
                sigma_px: uniform(rng, self.jitter_sigma_px),
            }),
            dropout_patches: (count > 0).then_some(DropoutPatches {
                count,
                radius_px: (r.0 * object_px, r.1 * object_px),
            }),
            shadow: None,
            registration: None,
        };
        // Drawn last, and only when asked, so that sets without shadows draw as before.
        if self.shadow_probability > 0.0 && rng.random_bool(self.shadow_probability.min(1.0)) {
            let side = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            sensor.shadow = Some(ProjectorShadow {
                baseline_m: side * baseline,
                focal_px,
            });
        }
        if self.registration_probability > 0.0
            && rng.random_bool(self.registration_probability.min(1.0))
        {
            let side = match sensor.shadow {
                Some(s) => -s.baseline_m.signum(),
                None if rng.random_bool(0.5) => 1.0,
                None => -1.0,
            };
            sensor.registration = Some(ProjectorShadow {
                baseline_m: side * uniform(rng, self.registration_baseline_m),
                focal_px,
            });
        }
        sensor
    }

    /// A structured-light sensor whose depth is registered to a colour camera: the
    /// projector's shadows and the registration's holes, each with probability `p`, drawn
    /// independently ([`SensorRanges::shadow_probability`],
    /// [`SensorRanges::registration_probability`]).
    pub fn set_shadows(&mut self, p: f64) {
        self.shadow_probability = p;
        self.registration_probability = p;
    }

    /// Whether every range is ordered and allowed (a message naming the first bad one).
    pub fn validate_ranges(&self) -> Result<(), String> {
        self.validate()
    }

    fn validate(&self) -> Result<(), String> {
        let ordered = |(lo, hi): (f64, f64), min: f64| {
            lo.is_finite() && hi.is_finite() && lo >= min && hi >= lo
        };
        let checks = [
            (
                "noise_factor",
                ordered(self.noise_factor, f64::MIN_POSITIVE),
            ),
            (
                "focal_baseline",
                ordered(self.focal_baseline, f64::MIN_POSITIVE),
            ),
            ("subpixel", ordered(self.subpixel, f64::MIN_POSITIVE)),
            (
                "grazing_max_angle_deg",
                ordered(self.grazing_max_angle_deg, 0.0) && self.grazing_max_angle_deg.1 <= 90.0,
            ),
            (
                "flying_probability",
                ordered(self.flying_probability, 0.0) && self.flying_probability.1 <= 1.0,
            ),
            (
                "flying_edge_threshold_m",
                ordered(self.flying_edge_threshold_m, 0.0),
            ),
            (
                "jitter_sigma_px",
                ordered(self.jitter_sigma_px, 0.0) && self.jitter_sigma_px.1 <= 1.0,
            ),
            ("patch_count", self.patch_count.1 >= self.patch_count.0),
            ("patch_radius", ordered(self.patch_radius, 0.0)),
            (
                "shadow_probability",
                (0.0..=1.0).contains(&self.shadow_probability),
            ),
            (
                "registration_probability",
                (0.0..=1.0).contains(&self.registration_probability),
            ),
            (
                "registration_baseline_m",
                ordered(self.registration_baseline_m, 0.0),
            ),
        ];
        match checks.iter().find(|c| !c.1) {
            Some((name, _)) => Err(format!(
                "sensor.{name} is not an ordered range of allowed values (jitter ≤ 1 px, angles ≤ 90°, probabilities ≤ 1)"
            )),
            None => Ok(()),
        }
    }
}

/// Which switches a protocol turns on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplingProtocol {
    /// The paper's: [`ObjectSampleConfig::default`] (old numbers stay reproducible).
    #[default]
    Paper,
    /// The paper's, with viewpoints uniform on the whole sphere
    /// ([`ViewSampling::Sphere`]): what `../shared/notes/whole-sphere.md` measured.
    Sphere,
    /// Every deployment switch on: [`ObjectSampleConfig::deployment`].
    Deployment,
}

impl SamplingProtocol {
    pub fn as_str(&self) -> &'static str {
        match self {
            SamplingProtocol::Paper => "paper",
            SamplingProtocol::Sphere => "sphere",
            SamplingProtocol::Deployment => "deployment",
        }
    }

    /// The sample configuration of this protocol.
    pub fn config(&self) -> ObjectSampleConfig {
        match self {
            SamplingProtocol::Paper => ObjectSampleConfig::default(),
            SamplingProtocol::Sphere => ObjectSampleConfig {
                viewpoints: ViewSampling::Sphere,
                ..ObjectSampleConfig::default()
            },
            SamplingProtocol::Deployment => ObjectSampleConfig::deployment(),
        }
    }
}

impl std::fmt::Display for SamplingProtocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for SamplingProtocol {
    type Err = DataError;
    fn from_str(s: &str) -> Result<Self, DataError> {
        match s {
            "paper" => Ok(SamplingProtocol::Paper),
            "sphere" => Ok(SamplingProtocol::Sphere),
            "deployment" => Ok(SamplingProtocol::Deployment),
            _ => Err(DataError::Config {
                field: "protocol",
                message: format!("expected paper, sphere or deployment, got {s:?}"),
            }),
        }
    }
}

/// Checks the deployment fields of `cfg`.
pub(crate) fn validate(cfg: &ObjectSampleConfig) -> Result<(), DataError> {
    let bad = |field: &'static str, message: String| Err(DataError::Config { field, message });
    let prob = |p: f64| (0.0..=1.0).contains(&p);
    if let CameraDistance::ImageSpan { min, max } = cfg.distance
        && !(min.is_finite() && max.is_finite() && min > 0.0 && max >= min && max <= 4.0)
    {
        return bad(
            "distance",
            format!("image span [{min}, {max}] must be an ordered range in (0, 4]"),
        );
    }
    if let Some(p) = cfg.placement
        && !prob(p.truncation_probability)
    {
        return bad(
            "placement.truncation_probability",
            format!("must be in [0, 1], got {}", p.truncation_probability),
        );
    }
    if let Some(s) = cfg.scale_augmentation
        && !(s.max_relative.is_finite() && (0.0..0.9).contains(&s.max_relative))
    {
        return bad(
            "scale_augmentation.max_relative",
            format!("must be in [0, 0.9), got {}", s.max_relative),
        );
    }
    if let Some(o) = cfg.occluder {
        let (lo, hi) = o.hidden_fraction;
        if !(prob(o.probability) && prob(o.stripe_probability)) {
            return bad("occluder", "probabilities must be in [0, 1]".into());
        }
        if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi >= lo && hi < 1.0) {
            return bad(
                "occluder.hidden_fraction",
                format!("[{lo}, {hi}] must be an ordered range in [0, 1)"),
            );
        }
        let (glo, ghi) = o.gap;
        if !(glo.is_finite() && ghi.is_finite() && glo > 0.0 && ghi >= glo) {
            return bad(
                "occluder.gap",
                format!("[{glo}, {ghi}] must be an ordered range of positive lengths"),
            );
        }
    }
    let p = cfg.physical;
    for (name, (lo, hi)) in [
        ("physical.longest_side_m", p.longest_side_m),
        ("physical.distance_m", p.distance_m),
    ] {
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi >= lo) {
            return bad(
                name,
                format!("[{lo}, {hi}] must be an ordered range of positive lengths"),
            );
        }
    }
    if let Some(s) = &cfg.sensor
        && let Err(message) = s.validate()
    {
        return bad("sensor", message);
    }
    if let Some(r) = cfg.crop_radius
        && !(r.is_finite() && r > 0.0)
    {
        return bad("crop_radius", format!("must be positive, got {r}"));
    }
    Ok(())
}

/// A uniformly distributed rotation (Shoemake's unit-quaternion method).
fn uniform_rotation<R: Rng + ?Sized>(rng: &mut R) -> DMat3 {
    let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
    let tau = std::f64::consts::TAU;
    let q = DQuat::from_xyzw(
        (1.0 - u1).sqrt() * (tau * u2).sin(),
        (1.0 - u1).sqrt() * (tau * u2).cos(),
        u1.sqrt() * (tau * u3).sin(),
        u1.sqrt() * (tau * u3).cos(),
    );
    DMat3::from_quat(q.normalize())
}

/// Stream numbers of the sub-streams of one attempt.
mod stream {
    pub const SCALE: u64 = 1;
    pub const ROTATION: u64 = 2;
    pub const VIEW: u64 = 3;
    pub const ROLL: u64 = 4;
    pub const DISTANCE: u64 = 5;
    pub const PLACEMENT: u64 = 6;
    pub const PHYSICAL: u64 = 7;
    pub const OCCLUDER: u64 = 8;
    pub const SENSOR_DRAW: u64 = 9;
    pub const SENSOR_APPLY: u64 = 10;
}

/// What one deployment view produced (before the points are drawn).
pub(crate) struct View {
    /// Model → camera (normalised units), for the scaled model.
    pub pose: Pose,
    pub viewpoint: Viewpoint,
    /// Per-axis factors applied to the corpus object's normalised mesh and points.
    pub model_scale: Vec3,
    /// Metres per normalised unit (the sensor model's scale).
    pub metres_per_unit: f64,
    /// Object pixels with a return after the sensor model (before erosion).
    pub visible_pixels: usize,
    /// Fraction of the object's visible pixels the occluder hid (0 without one).
    pub occluded_fraction: f64,
    /// Whether the object touches the image border (truncated).
    pub truncated: bool,
    /// The sensor drawn for this view (`None`: ideal depth).
    pub sensor: Option<SensorConfig>,
    /// Observed points before voxelising (camera frame, normalised units).
    pub points: Vec<Vec3>,
    /// Full-size depth (normalised units) and object mask, when asked for.
    pub images: Option<(ic_geometry::DepthImage, Mask)>,
}

/// Renders one deployment view of `object` from the attempt stream `seed`.
pub(crate) fn render_view(
    cfg: &ObjectSampleConfig,
    renderer: &mut dyn Renderer,
    object: &CorpusObject,
    seed: u64,
) -> Result<View, DataError> {
    let sub = |k: u64| ChaCha8Rng::seed_from_u64(mix(seed, k));
    let k = cfg.intrinsics;

    // The model as given to the network: scaled, renormalised.
    let model_scale = match cfg.scale_augmentation {
        Some(s) if s.max_relative > 0.0 => {
            let mut rng = sub(stream::SCALE);
            let m = s.max_relative;
            let f = DVec3::new(
                rng.random_range(1.0 - m..=1.0 + m),
                rng.random_range(1.0 - m..=1.0 + m),
                rng.random_range(1.0 - m..=1.0 + m),
            );
            let half = object
                .mesh
                .bounds()
                .map(|b| 0.5 * b.extent())
                .unwrap_or(DVec3::ONE);
            (f / (f * half).max_element().max(1e-12)).as_vec3()
        }
        _ => Vec3::ONE,
    };
    let mesh: Arc<Mesh> = if model_scale == Vec3::ONE {
        object.mesh.clone()
    } else {
        Arc::new(Mesh {
            vertices: object
                .mesh
                .vertices
                .iter()
                .map(|&v| v * model_scale)
                .collect(),
            triangles: object.mesh.triangles.clone(),
        })
    };
    // Bounding sphere about the bounding-box centre (the origin of the normalised frame).
    let radius = mesh
        .vertices
        .iter()
        .map(|v| v.as_dvec3().length())
        .fold(0.0, f64::max)
        .max(1e-6);

    let rotation = match cfg.rotation {
        ic_render::ObjectRotation::Canonical => DMat3::IDENTITY,
        ic_render::ObjectRotation::Vertical => {
            DMat3::from_rotation_z(sub(stream::ROTATION).random_range(0.0..std::f64::consts::TAU))
        }
        ic_render::ObjectRotation::Uniform => uniform_rotation(&mut sub(stream::ROTATION)),
    };
    let (direction, elevation_deg, azimuth_deg) =
        cfg.viewpoints.draw(&cfg.view, &mut sub(stream::VIEW));
    let look = look_at(direction, DVec3::ZERO, DVec3::Z)
        .or_else(|_| look_at(direction, DVec3::ZERO, DVec3::Y))?
        .rotation;
    let roll = if cfg.camera_roll {
        DMat3::from_rotation_z(sub(stream::ROLL).random_range(0.0..std::f64::consts::TAU))
    } else {
        DMat3::IDENTITY
    };
    let distance = match cfg.distance {
        CameraDistance::Fixed => cfg.view.distance,
        CameraDistance::ImageSpan { min, max } => {
            let f = log_uniform(&mut sub(stream::DISTANCE), (min, max));
            let half_angle = (f * k.height as f64 / (2.0 * k.fy)).atan();
            radius / half_angle.sin()
        }
    };
    // Where the centre projects: the principal point, or a drawn pixel.
    let base = roll * look * rotation;
    let pose_at = |uc: f64, vc: f64| {
        let ray = DVec3::new((uc - k.cx) / k.fx, (vc - k.cy) / k.fy, 1.0).normalize();
        let offset = DMat3::from_quat(DQuat::from_rotation_arc(DVec3::Z, ray));
        Pose::new(offset * base, distance * ray)
    };
    // Whether every vertex projects at least one pixel inside the image border.
    let fits = |pose: &Pose| {
        mesh.vertices.iter().all(|v| {
            let p = pose.apply(v.as_dvec3());
            let (u, w) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
            p.z > 0.0
                && (0.5..=k.width as f64 - 1.5).contains(&u)
                && (0.5..=k.height as f64 - 1.5).contains(&w)
        })
    };
    let pose = match cfg.placement {
        None => pose_at(k.cx, k.cy),
        Some(p) => {
            let mut rng = sub(stream::PLACEMENT);
            let (w, h) = (k.width as f64, k.height as f64);
            if rng.random_bool(p.truncation_probability) {
                pose_at(
                    rng.random_range(-0.5..w - 0.5),
                    rng.random_range(-0.5..h - 0.5),
                )
            } else {
                // Where the bounding circle (on the axis) stays inside, then checked on the
                // vertices (off the axis the silhouette stretches); the principal point when
                // no draw fits.
                let rp = (radius / distance).min(1.0).asin().tan();
                let (ru, rv) = (k.fx * rp, k.fy * rp);
                let mut found = None;
                for _ in 0..8 {
                    let (ulo, uhi, vlo, vhi) = (ru - 0.5, w - 0.5 - ru, rv - 0.5, h - 0.5 - rv);
                    if ulo >= uhi || vlo >= vhi {
                        break;
                    }
                    let pose = pose_at(rng.random_range(ulo..=uhi), rng.random_range(vlo..=vhi));
                    if fits(&pose) {
                        found = Some(pose);
                        break;
                    }
                }
                found.unwrap_or_else(|| pose_at(k.cx, k.cy))
            }
        }
    };

    // Physical scale for the sensor model.
    let metres_per_unit = {
        let p = cfg.physical;
        let (slo, shi) = (p.longest_side_m.0 / 2.0, p.longest_side_m.1 / 2.0);
        let (dlo, dhi) = (p.distance_m.0 / distance, p.distance_m.1 / distance);
        let (lo, hi) = (slo.max(dlo), shi.min(dhi));
        if lo <= hi {
            log_uniform(&mut sub(stream::PHYSICAL), (lo, hi))
        } else if shi < dlo {
            shi
        } else {
            slo
        }
    };

    // The window of the image that can show the object.
    let (mut ulo, mut uhi, mut vlo, mut vhi) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    let mut behind = false;
    for v in &mesh.vertices {
        let p = pose.apply(v.as_dvec3());
        if p.z <= ic_render::DEFAULT_NEAR {
            behind = true;
            break;
        }
        let (u, w) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
        ulo = ulo.min(u);
        uhi = uhi.max(u);
        vlo = vlo.min(w);
        vhi = vhi.max(w);
    }
    let clampi = |x: f64, hi: u32| (x as i64).clamp(0, hi as i64 - 1);
    let (u0, u1, v0, v1) = if behind {
        (0, k.width as i64 - 1, 0, k.height as i64 - 1)
    } else {
        (
            clampi(ulo.floor() - WINDOW_MARGIN as f64, k.width),
            clampi(uhi.ceil() + WINDOW_MARGIN as f64, k.width),
            clampi(vlo.floor() - WINDOW_MARGIN as f64, k.height),
            clampi(vhi.ceil() + WINDOW_MARGIN as f64, k.height),
        )
    };
    let window = Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx - u0 as f64,
        cy: k.cy - v0 as f64,
        width: (u1 - u0 + 1) as u32,
        height: (v1 - v0 + 1) as u32,
    };
    let camera = Camera::new(window, Pose::IDENTITY);
    let scene = Scene::single(mesh.clone(), pose, OBJECT_ID);
    let mut rendering = renderer.render(&scene, &camera)?;
    let (ww, wh) = (window.width as usize, window.height as usize);
    let truncated = {
        let touches = |u: usize, v: usize| rendering.instances.data[v * ww + u] == OBJECT_ID;
        (u0 == 0 && (0..wh).any(|v| touches(0, v)))
            || (u1 == k.width as i64 - 1 && (0..wh).any(|v| touches(ww - 1, v)))
            || (v0 == 0 && (0..ww).any(|u| touches(u, 0)))
            || (v1 == k.height as i64 - 1 && (0..ww).any(|u| touches(u, wh - 1)))
    };

    let occluded_fraction = match cfg.occluder {
        Some(o) => occlude(&mut rendering, &window, o, &mut sub(stream::OCCLUDER)),
        None => 0.0,
    };

    let sensor = cfg.sensor.map(|ranges| {
        let object_pixels = rendering
            .instances
            .data
            .iter()
            .filter(|&&i| i == OBJECT_ID)
            .count();
        ranges.draw(
            &mut sub(stream::SENSOR_DRAW),
            (object_pixels as f64).sqrt(),
            window.fx,
        )
    });
    if let Some(s) = &sensor {
        let to_m = metres_per_unit as f32;
        rendering.depth.data.iter_mut().for_each(|z| *z *= to_m);
        s.apply(&mut rendering, mix(seed, stream::SENSOR_APPLY));
        rendering.depth.data.iter_mut().for_each(|z| *z /= to_m);
    }

    let mask = rendering.mask(OBJECT_ID);
    let visible_pixels = mask
        .data
        .iter()
        .zip(&rendering.depth.data)
        .filter(|(m, z)| **m && **z > 0.0)
        .count();
    let eroded = mask.eroded3x3_keeping_some(cfg.mask_erosions);
    let mut points = window.back_project_depth(&rendering.depth, Some(&eroded))?;
    if let Some(r) = cfg.crop_radius
        && !points.is_empty()
    {
        let centre = points.iter().fold(DVec3::ZERO, |a, p| a + p.as_dvec3()) / points.len() as f64;
        let r2 = (r as f64) * (r as f64);
        points.retain(|p| (p.as_dvec3() - centre).length_squared() <= r2);
    }
    let images = cfg.keep_images.then(|| {
        let mut depth = ic_geometry::DepthImage::filled(k.width, k.height, 0.0);
        let mut full_mask = Mask::filled(k.width, k.height, false);
        for v in 0..wh {
            for u in 0..ww {
                let dst = (v + v0 as usize) * k.width as usize + u + u0 as usize;
                depth.data[dst] = rendering.depth.data[v * ww + u];
                full_mask.data[dst] = mask.data[v * ww + u];
            }
        }
        (depth, full_mask)
    });
    Ok(View {
        pose,
        viewpoint: Viewpoint {
            elevation_deg,
            azimuth_deg,
            distance,
        },
        model_scale,
        metres_per_unit,
        visible_pixels,
        occluded_fraction,
        truncated,
        sensor,
        points,
        images,
    })
}

/// Paints an occluder (see [`OccluderConfig`]) into `r`; returns the fraction of the object's
/// pixels with a return that it hid.
fn occlude(r: &mut Rendering, window: &Intrinsics, o: OccluderConfig, rng: &mut ChaCha8Rng) -> f64 {
    if !rng.random_bool(o.probability) {
        return 0.0;
    }
    let fraction = uniform(rng, o.hidden_fraction);
    let stripe = rng.random_bool(o.stripe_probability);
    let angle: f64 = rng.random_range(0.0..std::f64::consts::TAU);
    let start_q: f64 = rng.random(); // where a stripe starts, as a quantile of the free range
    let gap = uniform(rng, o.gap);
    let w = r.depth.width as usize;
    let (cs, sn) = (angle.cos(), angle.sin());
    let coord = |i: usize| (i % w) as f64 * cs + (i / w) as f64 * sn;
    let object: Vec<usize> = (0..r.depth.data.len())
        .filter(|&i| r.instances.data[i] == OBJECT_ID && r.depth.data[i] > 0.0)
        .collect();
    let n = object.len();
    let hide = (fraction * n as f64).round() as usize;
    if n == 0 || hide == 0 {
        return 0.0;
    }
    let mut s: Vec<f64> = object.iter().map(|&i| coord(i)).collect();
    s.sort_by(f64::total_cmp);
    // The threshold between sorted positions k−1 and k (−∞ / +∞ at the ends).
    let cut = |k: usize| {
        if k == 0 {
            f64::NEG_INFINITY
        } else if k >= n {
            f64::INFINITY
        } else {
            0.5 * (s[k - 1] + s[k])
        }
    };
    let (lo, hi) = if stripe {
        let first = (start_q * (n - hide) as f64).round() as usize;
        (cut(first), cut(first + hide))
    } else {
        (f64::NEG_INFINITY, cut(hide))
    };
    let inside = |i: usize| {
        let c = coord(i);
        c > lo && c < hi
    };
    let nearest = object
        .iter()
        .filter(|&&i| inside(i))
        .map(|&i| r.depth.data[i] as f64)
        .fold(f64::INFINITY, f64::min);
    if !nearest.is_finite() {
        return 0.0;
    }
    let z = (nearest - gap)
        .max(0.5 * nearest)
        .max(2.0 * ic_render::DEFAULT_NEAR);
    let mut hidden = 0;
    for i in 0..r.depth.data.len() {
        if inside(i) {
            hidden += (r.instances.data[i] == OBJECT_ID && r.depth.data[i] > 0.0) as usize;
            let x = ((i % w) as f64 - window.cx) / window.fx;
            let y = ((i / w) as f64 - window.cy) / window.fy;
            r.depth.data[i] = z as f32;
            r.instances.data[i] = OCCLUDER_ID;
            r.incidence.data[i] = (1.0 / (x * x + y * y + 1.0).sqrt()) as f32;
        }
    }
    hidden as f64 / n as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_directions_are_uniform_and_cover_every_octant() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let view = ic_geometry::ViewSphere::paper(2.8);
        let mut octants = [0usize; 8];
        let (mut z_sum, mut abs_z_sum) = (0.0, 0.0);
        let n = 20_000;
        for _ in 0..n {
            let (d, e, a) = ViewSampling::Sphere.draw(&view, &mut rng);
            assert!((d.length() - 1.0).abs() < 1e-9);
            assert!((d.z - e.to_radians().sin()).abs() < 1e-9);
            assert!((0.0..360.0).contains(&a));
            octants[(d.x > 0.0) as usize + 2 * (d.y > 0.0) as usize + 4 * (d.z > 0.0) as usize] +=
                1;
            z_sum += d.z;
            abs_z_sum += d.z.abs();
        }
        // Uniform on the sphere: z uniform in [-1, 1] (mean 0, mean |z| 1/2 — uniform
        // elevation in degrees would give 2/π ≈ 0.64), each octant 1/8.
        assert!((z_sum / n as f64).abs() < 0.02);
        assert!((abs_z_sum / n as f64 - 0.5).abs() < 0.02);
        for c in octants {
            assert!((c as f64 / n as f64 - 0.125).abs() < 0.015, "{octants:?}");
        }
        // The paper's ranges stay in one octant.
        let mut paper = [0usize; 8];
        for _ in 0..2000 {
            let (d, _, _) = ViewSampling::Paper.draw(&view, &mut rng);
            paper[(d.x > 0.0) as usize + 2 * (d.y > 0.0) as usize + 4 * (d.z > 0.0) as usize] += 1;
        }
        assert_eq!(paper[7], 2000);
    }

    #[test]
    fn projector_shadows_are_drawn_last_from_the_quantisation_baseline_on_either_side() {
        let without = SensorRanges::default();
        let with = SensorRanges {
            shadow_probability: 1.0,
            ..without
        };
        let (mut a, mut b) = (ChaCha8Rng::seed_from_u64(4), ChaCha8Rng::seed_from_u64(4));
        let mut sides = [0usize; 2];
        for _ in 0..100 {
            let plain = without.draw(&mut a, 100.0, 210.0);
            let shadowed = with.draw(&mut b, 100.0, 210.0);
            assert_eq!(plain.shadow, None);
            let shadow = shadowed.shadow.expect("probability 1");
            // Everything else is the sensor the same stream drew without shadows.
            assert_eq!(
                SensorConfig {
                    shadow: None,
                    ..shadowed
                },
                plain
            );
            let Some(Quantisation::Disparity { baseline, .. }) = plain.quantisation else {
                panic!("a disparity sensor")
            };
            assert_eq!(shadow.baseline_m.abs(), baseline);
            assert_eq!(shadow.focal_px, 210.0);
            sides[(shadow.baseline_m > 0.0) as usize] += 1;
            // The next draw of both streams starts where the shadowed one ended.
            a = b.clone();
        }
        assert!(sides.iter().all(|&n| n > 30), "{sides:?}");
        let bad = SensorRanges {
            shadow_probability: 1.5,
            ..without
        };
        assert!(
            bad.validate_ranges()
                .unwrap_err()
                .contains("shadow_probability")
        );
        // Registered to a colour camera: the second band on the projector's other side, or
        // on either side without a projector shadow.
        let registered = SensorRanges {
            registration_probability: 1.0,
            ..with
        };
        let alone = SensorRanges {
            registration_probability: 1.0,
            ..without
        };
        let mut alone_sides = [0usize; 2];
        for _ in 0..100 {
            let s = registered.draw(&mut a, 100.0, 210.0);
            let (p, r) = (s.shadow.unwrap(), s.registration.unwrap());
            assert_eq!(p.baseline_m.signum(), -r.baseline_m.signum());
            assert!((0.02..=0.05).contains(&r.baseline_m.abs()), "{r:?}");
            let s = alone.draw(&mut a, 100.0, 210.0);
            assert_eq!(s.shadow, None);
            alone_sides[(s.registration.unwrap().baseline_m > 0.0) as usize] += 1;
        }
        assert!(alone_sides.iter().all(|&n| n > 30), "{alone_sides:?}");
    }

    #[test]
    fn drawn_sensors_stay_in_their_ranges() {
        let ranges = SensorRanges::default();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..200 {
            let s = ranges.draw(&mut rng, 100.0, 525.0);
            let n = s.noise.unwrap();
            let k = n.a / AxialNoise::default().a;
            assert!((0.5 - 1e-9..=2.5 + 1e-9).contains(&k));
            assert!((n.b / AxialNoise::default().b - k).abs() < 1e-9);
            let g = s.grazing.unwrap().max_angle_deg;
            assert!((70.0..=85.0).contains(&g));
            let j = s.lateral_jitter.unwrap().sigma_px;
            assert!((0.0..=0.8).contains(&j));
            if let Some(p) = s.dropout_patches {
                assert!((1..=3).contains(&p.count));
                assert!(p.radius_px.0 >= 3.0 - 1e-9 && p.radius_px.1 <= 20.0 + 1e-9);
            }
        }
    }
}
