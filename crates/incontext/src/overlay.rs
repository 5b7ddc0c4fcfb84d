//! Pictures of a result: the overlay PNG (the model rendered at the estimated pose over the
//! colour-mapped depth map) and the aligned PLY (scene points and aligned model in two colours).

use std::path::Path;
use std::sync::Arc;

use ic_geometry::io::{PlyEncoding, write_ply};
use ic_geometry::{DepthImage, Intrinsics, Mask, Mesh, PointCloud, Pose, voxel_downsample_points};
use ic_render::{Camera, CpuRenderer, Renderer, Rendering, Scene, depth_colours, is_mask_edge};

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
    Ok(render_at(mesh, pose, intrinsics)?.mask(1))
}

/// The union of the silhouettes of `mesh` at each of `poses` (as [`render_mask`]); nothing
/// set when `poses` is empty.
pub fn render_masks(mesh: &Arc<Mesh>, poses: &[Pose], intrinsics: &Intrinsics) -> Result<Mask> {
    let mut union = Mask::filled(intrinsics.width, intrinsics.height, false);
    for pose in poses {
        let m = render_mask(mesh, pose, intrinsics)?;
        for (a, b) in union.data.iter_mut().zip(&m.data) {
            *a |= *b;
        }
    }
    Ok(union)
}

/// `mesh` (instance id 1) seen from a camera at `pose` (model → camera).
fn render_at(mesh: &Arc<Mesh>, pose: &Pose, intrinsics: &Intrinsics) -> Result<Rendering> {
    let scene = Scene::single(mesh.clone(), Pose::IDENTITY, 1);
    Ok(CpuRenderer::new().render(&scene, &Camera::new(*intrinsics, *pose))?)
}

/// How a pose agrees with a real depth map that has no ground truth: the model rendered at
/// the pose, compared pixel by pixel with the observed depth (both in the depth map's units).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct DepthAgreement {
    /// Pixels the rendered model covers.
    pub model_pixels: usize,
    /// Of those, the ones not hidden: the observed surface is not in front of the model by
    /// more than the tolerance (a pixel without a return counts as not hidden).
    pub visible_pixels: usize,
    /// Fraction of the visible pixels where the observed depth is within the tolerance.
    pub agreement: f64,
    /// Fraction of the visible pixels where the model lies in front of the observed surface
    /// by more than the tolerance (free space the sensor saw through).
    pub in_front: f64,
    /// Fraction of the visible pixels without an observed return.
    pub missing: f64,
}

/// [`DepthAgreement`] of `mesh` (normalised, as `pose` maps it) rendered through
/// `intrinsics` against `depth` (the same units as `pose`'s translation scaled by `scale`:
/// rendered depth × `scale` is compared with `depth`), within `tolerance` (depth units).
pub fn depth_agreement(
    mesh: &Arc<Mesh>,
    pose: &Pose,
    scale: f64,
    intrinsics: &Intrinsics,
    depth: &DepthImage,
    tolerance: f64,
) -> Result<DepthAgreement> {
    let view = render_at(mesh, pose, intrinsics)?;
    let (mut model, mut visible, mut agree, mut front, mut missing) = (0, 0, 0, 0, 0);
    for ((&zr, &id), &zo) in view
        .depth
        .data
        .iter()
        .zip(&view.instances.data)
        .zip(&depth.data)
    {
        if id != 1 || zr <= 0.0 {
            continue;
        }
        model += 1;
        let zr = zr as f64 * scale;
        let zo = zo as f64;
        if !(zo.is_finite() && zo > 0.0) {
            visible += 1;
            missing += 1;
        } else if zr <= zo + tolerance {
            visible += 1;
            if zr < zo - tolerance {
                front += 1;
            } else {
                agree += 1;
            }
        }
    }
    Ok(DepthAgreement {
        model_pixels: model,
        visible_pixels: visible,
        agreement: crate::verify::share(agree, visible),
        in_front: crate::verify::share(front, visible),
        missing: crate::verify::share(missing, visible),
    })
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

#[cfg(test)]
mod agreement_tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    #[test]
    fn a_pose_agrees_with_its_own_depth_and_one_moved_closer_lies_in_front() {
        let mesh = Arc::new(ic_geometry::shapes::icosphere(1.0, 2).unwrap());
        let k = Intrinsics::new(100.0, 100.0, 39.5, 29.5, 80, 60).unwrap();
        let pose = Pose::from_translation(DVec3::new(0.0, 0.0, 5.0));
        let scene = Scene::single(mesh.clone(), Pose::IDENTITY, 1);
        // The observed depth in mm, the pose in units of 10 mm.
        let view = CpuRenderer::new()
            .render(&scene, &Camera::new(k, pose))
            .unwrap();
        let depth = DepthImage {
            width: 80,
            height: 60,
            data: view.depth.data.iter().map(|z| z * 10.0).collect(),
        };
        let same = depth_agreement(&mesh, &pose, 10.0, &k, &depth, 1.0).unwrap();
        assert!(same.model_pixels > 100);
        assert_eq!(same.visible_pixels, same.model_pixels);
        assert_eq!(
            (same.agreement, same.in_front, same.missing),
            (1.0, 0.0, 0.0)
        );
        let closer = Pose::from_translation(DVec3::new(0.0, 0.0, 4.0));
        let a = depth_agreement(&mesh, &closer, 10.0, &k, &depth, 1.0).unwrap();
        assert!(a.in_front > 0.5, "{a:?}");
        // Farther away: hidden behind the observed surface where it overlaps it.
        let farther = Pose::from_translation(DVec3::new(0.0, 0.0, 8.0));
        let a = depth_agreement(&mesh, &farther, 10.0, &k, &depth, 1.0).unwrap();
        assert!(a.visible_pixels < a.model_pixels / 2, "{a:?}");
    }
}
