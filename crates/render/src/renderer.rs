//! The renderer-independent API: scenes, cameras, renderings and the [`Renderer`] trait.

use std::sync::Arc;

use ic_geometry::{DepthImage, Image, InstanceImage, Intrinsics, Mask, Mesh, Pose};

use crate::RenderError;

/// The largest instance id (ids are stored in 16-bit PNGs; 0 is the background).
pub const MAX_INSTANCE_ID: u32 = 65_535;

/// Default near clipping distance in metres (camera-frame z).
pub const DEFAULT_NEAR: f64 = 0.01;

/// One object of a scene: a mesh in its own (model) frame, its model→world pose and its id.
#[derive(Clone, Debug)]
pub struct SceneObject {
    /// Shared so that renderers can cache the uploaded geometry: a wgpu renderer re-uploads a
    /// mesh only when an object holds a different `Arc` (pointer identity).
    pub mesh: Arc<Mesh>,
    /// Model→world: `x_world = R·x_model + t`.
    pub pose: Pose,
    /// Instance id written to the instance image, in 1..=[`MAX_INSTANCE_ID`].
    pub id: u32,
}

/// A list of posed meshes. Triangles are drawn from both sides (no back-face culling): meshes
/// from model corpora are often not consistently oriented, and a sensor sees both sides too.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    pub objects: Vec<SceneObject>,
}

impl Scene {
    /// An empty scene.
    pub fn new() -> Self {
        Scene::default()
    }

    /// A scene with one object.
    pub fn single(mesh: Arc<Mesh>, pose: Pose, id: u32) -> Self {
        Scene {
            objects: vec![SceneObject { mesh, pose, id }],
        }
    }

    /// Adds an object.
    pub fn push(&mut self, mesh: Arc<Mesh>, pose: Pose, id: u32) -> &mut Self {
        self.objects.push(SceneObject { mesh, pose, id });
        self
    }

    /// Checks ids (1..=65535) and meshes.
    pub fn validate(&self) -> Result<(), RenderError> {
        for (index, o) in self.objects.iter().enumerate() {
            if o.id == 0 || o.id > MAX_INSTANCE_ID {
                return Err(RenderError::InvalidInstanceId { index, id: o.id });
            }
            o.mesh
                .validate()
                .map_err(|source| RenderError::InvalidMesh { index, source })?;
        }
        Ok(())
    }

    /// Total number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.objects.iter().map(|o| o.mesh.triangles.len()).sum()
    }
}

/// A pinhole camera: OpenCV intrinsics, the world→camera pose and the near clipping distance.
///
/// Camera frame: x right, y down, z forward (metres). Integer pixel coordinates are pixel
/// centres; pixel `(u, v)` shows the surface along the ray through
/// `((u − cx)/fx, (v − cy)/fy, 1)`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// World→camera: `x_cam = R·x_world + t` (BOP's `cam_R_w2c`, `cam_t_w2c`).
    pub pose: Pose,
    /// Surfaces closer than this camera-frame z are clipped.
    pub near: f64,
}

impl Camera {
    /// A camera with the default near distance ([`DEFAULT_NEAR`]).
    pub fn new(intrinsics: Intrinsics, pose: Pose) -> Self {
        Camera {
            intrinsics,
            pose,
            near: DEFAULT_NEAR,
        }
    }

    pub(crate) fn validate(&self) -> Result<(), RenderError> {
        self.intrinsics.validate()?;
        if !(self.near.is_finite() && self.near > 0.0) {
            return Err(RenderError::Geometry(
                ic_geometry::GeometryError::InvalidParameter {
                    name: "near",
                    message: format!(
                        "near distance must be positive and finite, got {}",
                        self.near
                    ),
                },
            ));
        }
        Ok(())
    }
}

/// What a sensor sees from one camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Rendering {
    /// Camera-frame z in metres; 0 = no return.
    pub depth: DepthImage,
    /// Instance id of the visible surface; 0 = background.
    pub instances: InstanceImage,
    /// |cos| of the angle between the surface normal and the viewing ray (1 = head-on, 0 =
    /// grazing); 0 where nothing was hit. Used by the grazing-angle dropout of
    /// [`crate::SensorConfig`]. The wgpu backend stores it with 16-bit precision.
    pub incidence: Image<f32>,
}

impl Rendering {
    /// An empty rendering (no returns).
    pub fn empty(width: u32, height: u32) -> Self {
        Rendering {
            depth: Image::filled(width, height, 0.0),
            instances: Image::filled(width, height, 0),
            incidence: Image::filled(width, height, 0.0),
        }
    }

    /// The pixels showing instance `id`.
    pub fn mask(&self, id: u32) -> Mask {
        Image {
            width: self.instances.width,
            height: self.instances.height,
            data: self.instances.data.iter().map(|&i| i == id).collect(),
        }
    }

    /// The pixels with a depth return.
    pub fn valid(&self) -> Mask {
        Image {
            width: self.depth.width,
            height: self.depth.height,
            data: self.depth.data.iter().map(|&z| z > 0.0).collect(),
        }
    }

    /// Number of pixels with a depth return showing instance `id`, and with any return.
    pub fn count_returns(&self, id: u32) -> (usize, usize) {
        let mut hit = 0;
        let mut all = 0;
        for (&z, &i) in self.depth.data.iter().zip(&self.instances.data) {
            if z > 0.0 {
                all += 1;
                hit += (i == id) as usize;
            }
        }
        (hit, all)
    }
}

/// A depth + instance renderer. Both backends ([`crate::CpuRenderer`],
/// [`crate::WgpuRenderer`]) follow the same conventions: pixel centres at integer OpenCV
/// coordinates, a top-left fill rule, nearest surface wins (the first drawn on exact ties,
/// objects in scene order), no back-face culling, clipping at `camera.near`.
pub trait Renderer {
    /// Renders one view.
    fn render(&mut self, scene: &Scene, camera: &Camera) -> Result<Rendering, RenderError>;

    /// Renders several views of the same scene. Backends override this where batching pays
    /// (one submission and one readback per batch on the GPU, views in parallel on the CPU).
    fn render_batch(
        &mut self,
        scene: &Scene,
        cameras: &[Camera],
    ) -> Result<Vec<Rendering>, RenderError> {
        cameras.iter().map(|c| self.render(scene, c)).collect()
    }

    /// A human-readable name of the backend (and adapter).
    fn name(&self) -> String;
}

/// Model→camera transform of every object for a camera (f64).
pub(crate) fn model_to_camera(scene: &Scene, camera: &Camera) -> Vec<Pose> {
    scene
        .objects
        .iter()
        .map(|o| camera.pose.compose(&o.pose))
        .collect()
}
