//! `incontext render`: the depth map and mask a sensor would see of a mesh at a pose.

use std::path::PathBuf;
use std::sync::Arc;

use ic_geometry::Image;
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use serde_json::{Value, json};

use crate::error::{CliError, Result};
use crate::inputs;

/// Flags of `incontext render`.
#[derive(clap::Args, Debug, Clone, serde::Serialize)]
pub struct RenderArgs {
    /// The mesh (OBJ, PLY, OFF, glTF/GLB) in its own units.
    #[arg(long)]
    pub model: PathBuf,
    /// BOP-style camera JSON with width and height (cam_K or fx/fy/cx/cy, depth_scale).
    #[arg(long)]
    pub camera: PathBuf,
    /// Model → camera pose: {"R": 3×3 row-major, "t": [..]} in mesh units (what `register
    /// --out` writes), or BOP's cam_R_m2c / cam_t_m2c in mm.
    #[arg(long)]
    pub pose: PathBuf,
    /// Millimetres per mesh unit (1 for BOP meshes in mm).
    #[arg(long, default_value_t = 1.0)]
    pub model_unit_mm: f64,
    /// Output folder: depth.png (16-bit, the camera's depth_scale), depth.exr (metres),
    /// mask.png, camera.json.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: &RenderArgs) -> Result<Value> {
    if !(args.model_unit_mm.is_finite() && args.model_unit_mm > 0.0) {
        return Err(CliError::input(format!(
            "--model-unit-mm must be positive, got {}",
            args.model_unit_mm
        )));
    }
    let png = args.out.join("depth.png");
    let exr = args.out.join("depth.exr");
    let mask_path = args.out.join("mask.png");
    let cam_path = args.out.join("camera.json");
    {
        use crate::outputs::{Named, check_outputs};
        check_outputs(
            &[
                Named::new("--model", &args.model),
                Named::new("--camera", &args.camera),
                Named::new("--pose", &args.pose),
            ],
            &[
                Named::new("the rendered depth.png", &png),
                Named::new("the rendered depth.exr", &exr),
                Named::new("the rendered mask.png", &mask_path),
                Named::new("the rendered camera.json", &cam_path),
            ],
        )?;
    }
    // The camera's size is bounded by read_camera (ic_render::io::MAX_IMAGE_PIXELS), so the
    // render below allocates at most that many pixels.
    let camera = inputs::read_camera(&args.camera, || {
        Err(CliError::input(format!(
            "{}: width and height are needed to render",
            args.camera.display()
        )))
    })?;
    let pose = inputs::read_pose(&args.pose, args.model_unit_mm)?;
    let mesh = Arc::new(inputs::read_mesh(&args.model)?);
    tracing::info!(config = %serde_json::to_string(args).unwrap_or_default(), "incontext render");
    let k = camera.intrinsics;
    // The mesh stays where it is in the world; the camera's world→camera pose is the model pose.
    let scene = Scene::single(mesh, ic_geometry::Pose::IDENTITY, 1);
    // Near plane: 1 mm in mesh units.
    let mut cam = Camera::new(k, pose);
    cam.near = 1.0 / args.model_unit_mm;
    let view = CpuRenderer::new().render(&scene, &cam)?;
    let mask = view.mask(1);
    let pixels = mask.data.iter().filter(|&&m| m).count();
    if pixels == 0 {
        tracing::warn!("the object is not visible from this camera: the depth map is empty");
    }
    let metres = Image {
        width: view.depth.width,
        height: view.depth.height,
        data: view
            .depth
            .data
            .iter()
            .map(|&z| (z as f64 * args.model_unit_mm / 1000.0) as f32)
            .collect(),
    };
    inputs::create_dir(&args.out)?;
    ic_render::io::write_depth_png(&png, &metres, camera.depth_scale)?;
    ic_render::io::write_depth_exr(&exr, &metres)?;
    ic_render::io::write_mask_png(&mask_path, &mask)?;
    inputs::write_json(
        &cam_path,
        &json!({"cam_K": k.k_row_major().concat(), "depth_scale": camera.depth_scale, "width": k.width, "height": k.height}),
    )?;
    Ok(json!({
        "command": "render",
        "object_pixels": pixels,
        "outputs": {"depth_png": png, "depth_exr": exr, "mask": mask_path, "camera": cam_path},
    }))
}
