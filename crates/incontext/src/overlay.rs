//! Pictures of a result: the overlay PNG (the model rendered at the estimated pose over the
//! colour-mapped depth map) and the aligned PLY (scene points and aligned model in two colours).

use std::path::Path;
use std::sync::Arc;

use ic_geometry::io::{PlyEncoding, write_ply};
use ic_geometry::{DepthImage, Intrinsics, Mask, Mesh, PointCloud, Pose, voxel_downsample_points};
use ic_render::{Camera, CpuRenderer, Renderer, Scene, depth_colours, is_mask_edge};

use crate::error::{CliError, Result};

/// Colour of the model in the overlay (fill blended half-way, outline solid).
const MODEL_COLOUR: [u8; 3] = [255, 0, 200];
/// Colour of the segmentation mask's outline.
const MASK_COLOUR: [u8; 3] = [255, 255, 255];
/// Scene points and aligned model in the PLY.
const SCENE_COLOUR: [u8; 3] = [150, 150, 150];
const ALIGNED_COLOUR: [u8; 3] = [230, 40, 40];

/// The silhouette of `mesh` (in the frame `pose` maps from) seen through `intrinsics`.
pub fn render_mask(mesh: &Arc<Mesh>, pose: &Pose, intrinsics: &Intrinsics) -> Result<Mask> {
    let scene = Scene::single(mesh.clone(), Pose::IDENTITY, 1);
    let view = CpuRenderer::new().render(&scene, &Camera::new(*intrinsics, *pose))?;
    Ok(view.mask(1))
}

/// RGB8 pixels of the overlay: the depth colour-mapped (turbo-like, near blue, far red, no
/// return black), the model's silhouette blended in magenta with a solid outline,
/// and the segmentation mask's outline in white when given.
pub fn overlay_rgb(depth: &DepthImage, model: &Mask, segmentation: Option<&Mask>) -> Vec<u8> {
    let w = depth.width as usize;
    let mut out = Vec::with_capacity(depth.data.len() * 3);
    for (i, mut c) in depth_colours(depth).into_iter().enumerate() {
        let (u, v) = (i % w, i / w);
        if model.data[i] {
            c = if is_mask_edge(model, u, v) {
                MODEL_COLOUR
            } else {
                [0, 1, 2].map(|k| ((c[k] as u16 + MODEL_COLOUR[k] as u16) / 2) as u8)
            };
        }
        if let Some(s) = segmentation
            && is_mask_edge(s, u, v)
        {
            c = MASK_COLOUR;
        }
        out.extend_from_slice(&c);
    }
    out
}

/// Writes an RGB8 PNG atomically.
pub fn write_rgb_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    crate::inputs::create_parent(path)?;
    ic_render::write_rgb_png(path, width, height, rgb).map_err(|e| CliError::input(e.to_string()))
}

/// Renders `mesh` (normalised) at `pose_normalised` and writes the overlay over `depth`.
pub fn write_overlay(
    path: &Path,
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    mesh: &Arc<Mesh>,
    pose_normalised: &Pose,
    segmentation: Option<&Mask>,
) -> Result<()> {
    let model = render_mask(mesh, pose_normalised, intrinsics)?;
    let rgb = overlay_rgb(depth, &model, segmentation);
    write_rgb_png(path, depth.width, depth.height, &rgb)
}

/// The scene for the PLY: every valid depth pixel back-projected and voxelised at `voxel` (in
/// the depth's units).
pub fn scene_points(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    voxel: f32,
) -> Result<Vec<ic_geometry::glam::Vec3>> {
    let scene = intrinsics.back_project_depth(depth, None)?;
    if scene.is_empty() {
        return Ok(scene);
    }
    Ok(voxel_downsample_points(&scene, voxel)?)
}

/// Writes `scene` (grey) and `aligned` (the model points at the estimated pose, red) into one
/// binary PLY, atomically.
pub fn write_two_colour_ply(
    path: &Path,
    scene: &[ic_geometry::glam::Vec3],
    aligned: &[ic_geometry::glam::Vec3],
) -> Result<()> {
    let mut cloud = PointCloud {
        points: scene.to_vec(),
        normals: None,
        colors: Some(vec![SCENE_COLOUR; scene.len()]),
    };
    cloud.extend(&PointCloud {
        points: aligned.to_vec(),
        normals: None,
        colors: Some(vec![ALIGNED_COLOUR; aligned.len()]),
    });
    crate::inputs::create_parent(path)?;
    write_ply(path, &cloud, PlyEncoding::BinaryLittleEndian)?;
    Ok(())
}
