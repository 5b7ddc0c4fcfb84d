//! `ic_render` — what a depth sensor would see.
//!
//! Renders depth maps and instance-id maps of posed triangle meshes, headless, on two backends
//! behind one [`Renderer`] trait:
//!
//! - `WgpuRenderer` (cargo feature `gpu`, off by default): wgpu without a window (a real GPU
//!   when present, else Mesa's software Vulkan, lavapipe, from the Debian package
//!   `mesa-vulkan-drivers`); honours and validates `WGPU_BACKEND`; reversed infinite-far depth;
//!   batches of views in one submission.
//! - [`CpuRenderer`]: a rayon z-buffer rasteriser with f64 triangle set-up, the reference the
//!   GPU path is tested against and the default without a GPU ([`default_renderer`]).
//!
//! Both use the same conventions, so instance ids agree exactly away from silhouettes and
//! depths to ≈ 1e-6 relative.
//!
//! Also here: seeded scene assembly ([`SceneBuilder`]: the object alone, or inside the
//! paper's cube room of side 4 with bumpy walls, plus distractors and a support plane), sensor
//! artefacts ([`SensorConfig`]: Kinect-style axial noise, quantisation, grazing-angle dropout,
//! flying pixels, lateral jitter, dropout patches, the projector's shadows; all off by default), image I/O ([`io`]: 16-bit PNG depth with a BOP depth
//! scale, 32-bit EXR, 8-bit masks, 16-bit instance ids, atomic writes) and a colour-mapped
//! debug view ([`write_debug_png`]).
//!
//! # Units and frames
//! - Lengths in metres (or the normalised object units of the scene; the renderer does not
//!   care). Depth is the **camera-frame z** of the surface (not the ray length); `0.0` means no
//!   return. Instance id `0` is background; ids are 1..=65535.
//! - Camera frame: OpenCV (x right, y down, z forward). Intrinsics are OpenCV's: integer pixel
//!   coordinates are pixel centres, `u = fx·x/z + cx`.
//! - [`SceneObject::pose`] is model→world; [`Camera::pose`] is world→camera
//!   (`x_cam = R·x_world + t`), as `ic_geometry::look_at` returns.
//! - Scene world frame (for [`SceneBuilder`]): z up; the room's floor is z = 0.
//!
//! # Example
//! ```
//! use std::sync::Arc;
//! use ic_geometry::{glam::DVec3, look_at, Intrinsics, Pose};
//! use ic_geometry::{glam::Vec3, shapes};
//! use ic_render::{Camera, CpuRenderer, Renderer, Scene};
//!
//! // A 1 m cube, 3 m in front of a camera on the world z axis, seen head-on.
//! let cube = Arc::new(shapes::box_mesh(Vec3::splat(0.5)).unwrap());
//! let scene = Scene::single(cube, Pose::IDENTITY, 1);
//! let k = Intrinsics::new(100.0, 100.0, 31.5, 23.5, 64, 48).unwrap();
//! let eye = DVec3::new(0.0, 0.0, -3.0);
//! let camera = Camera::new(k, look_at(eye, DVec3::ZERO, DVec3::Y).unwrap());
//! let view = CpuRenderer::new().render(&scene, &camera).unwrap();
//!
//! // The centre pixel sees the front face at z = 3 − 0.5 = 2.5 m; the corners see nothing.
//! assert!((view.depth.get(32, 24).copied().unwrap() - 2.5).abs() < 1e-6);
//! assert_eq!(view.instances.get(32, 24), Some(&1));
//! assert_eq!(view.depth.get(0, 0), Some(&0.0));
//! assert_eq!(view.instances.get(0, 0), Some(&0));
//! ```

mod cpu;
mod debug;
mod error;
#[cfg(feature = "gpu")]
mod gpu;
/// Depth, mask and instance-id images on disk (PNG, EXR), written atomically.
pub mod io;
/// The cube room (objects come from `ic_geometry::shapes`).
pub mod procedural;
mod renderer;
mod scene;
mod sensor;

pub use cpu::CpuRenderer;
pub use debug::{
    debug_rgb, depth_colours, is_mask_edge, turbo_like, write_debug_png, write_rgb_png,
};
pub use error::{ImageIoError, RenderError};
#[cfg(feature = "gpu")]
pub use gpu::{WgpuOptions, WgpuRenderer, parse_backends};
pub use renderer::{
    Camera, DEFAULT_NEAR, MAX_INSTANCE_ID, Renderer, Rendering, Scene, SceneObject,
};
pub use scene::{
    Background, DISTRACTOR_ID_BASE, DistractorConfig, OBJECT_ID, ObjectRotation, ROOM_ID,
    RoomConfig, SUPPORT_ID, SceneBuilder, SceneConfig, SceneSample, SupportPlaneConfig,
};
pub use sensor::{
    AxialNoise, DropoutPatches, FlyingPixels, GrazingDropout, LateralJitter, ProjectorShadow,
    Quantisation, SensorConfig,
};

/// With the `gpu` feature, the wgpu renderer when an adapter exists, else the CPU renderer (the
/// reason is logged with `tracing`); an invalid `WGPU_BACKEND` is still an error. Without the
/// feature, the CPU renderer.
#[cfg(feature = "gpu")]
pub fn default_renderer() -> Result<Box<dyn Renderer + Send>, RenderError> {
    match WgpuRenderer::new() {
        Ok(r) => Ok(Box::new(r)),
        Err(e @ RenderError::InvalidBackend { .. }) => Err(e),
        Err(e) => {
            tracing::info!("using the CPU renderer: {e}");
            Ok(Box::new(CpuRenderer::new()))
        }
    }
}

/// With the `gpu` feature, the wgpu renderer when an adapter exists, else the CPU renderer.
/// Without the feature (this build), the CPU renderer.
#[cfg(not(feature = "gpu"))]
pub fn default_renderer() -> Result<Box<dyn Renderer + Send>, RenderError> {
    Ok(Box::new(CpuRenderer::new()))
}
