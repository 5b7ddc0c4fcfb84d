//! `incontext demo`: the geometric half of the pipeline on a procedural object.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, anyhow};
use ic_geometry::glam::DVec3;
use ic_geometry::io::{PlyEncoding, write_ply};
use ic_geometry::sampling::{VisibleSurfaceOptions, sample_visible_surface};
use ic_geometry::{
    IcpMethod, IcpOptions, IcpTarget, Intrinsics, PointCloud, Pose, ViewSphere, random_subsample,
    voxel_downsample,
};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use rand::{Rng, SeedableRng};
use serde::Serialize;

use crate::CliError;

/// Settings of the demo (printed with every run).
#[derive(clap::Args, Debug, Serialize)]
pub struct DemoArgs {
    /// Seed of every random choice (object, viewpoint, sampling, perturbation).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Folder for the PLY clouds and the depth image; nothing is written without it.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Rotation of the stand-in initial estimate away from the truth, degrees.
    #[arg(long, default_value_t = 10.0)]
    pub init_rotation_deg: f64,
    /// Translation of the stand-in initial estimate away from the truth, normalised units.
    #[arg(long, default_value_t = 0.05)]
    pub init_translation: f64,
}

/// The paper's sizes: M model points (the demo's ICP uses 4·M, a denser model), N observed
/// points, voxel 0.05·√2/2.
const MODEL_POINTS: usize = 1024;
const OBSERVED_POINTS: usize = 768;
const VOXEL: f32 = 0.05 * std::f32::consts::SQRT_2 / 2.0;
/// Camera distance (normalised units) at which a [-1, 1] object fills a 60° view.
const CAMERA_DISTANCE: f64 = 2.5;

#[derive(Serialize)]
struct Report {
    seed: u64,
    object_triangles: usize,
    observed_points_after_voxelising: usize,
    initial_rotation_error_deg: f64,
    initial_translation_error: f64,
    rotation_error_deg: f64,
    translation_error: f64,
    icp_fitness: f64,
    icp_inlier_rmse: f64,
    icp_iterations: usize,
    timings_ms: Timings,
}

#[derive(Serialize, Default)]
struct Timings {
    object: f64,
    model_points: f64,
    render: f64,
    observed_points: f64,
    icp: f64,
}

pub fn run(args: &DemoArgs) -> Result<(), CliError> {
    tracing::info!(config = %serde_json::to_string(args).unwrap_or_default(), "incontext demo");
    if !(args.init_rotation_deg.is_finite() && args.init_translation.is_finite()) {
        return Err(CliError::Input(anyhow!(
            "--init-rotation-deg and --init-translation must be finite"
        )));
    }
    let internal = |e: anyhow::Error| CliError::Internal(e);
    let mut t = Timings::default();
    let clock = Instant::now();

    let mut object = ic_geometry::shapes::random_object(args.seed);
    object
        .normalise()
        .context("normalising the procedural object")
        .map_err(internal)?;
    t.object = ms(clock);

    let clock = Instant::now();
    let model = sample_visible_surface(
        &object,
        4 * MODEL_POINTS,
        args.seed,
        VisibleSurfaceOptions::default(),
    )
    .context("sampling model points")
    .map_err(internal)?;
    t.model_points = ms(clock);

    // The true pose: the object at the origin, the camera on the paper's view sphere.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed ^ 0x5eed);
    let viewpoint = ViewSphere::paper(CAMERA_DISTANCE).sample(&mut rng);
    let truth = viewpoint
        .camera_pose(DVec3::ZERO)
        .map_err(|e| internal(e.into()))?;
    tracing::info!(?viewpoint, "camera");

    let clock = Instant::now();
    let intrinsics = Intrinsics::from_fov_y(320, 240, 60.0).map_err(|e| internal(e.into()))?;
    let scene = Scene::single(Arc::new(object.clone()), Pose::IDENTITY, 1);
    let view = CpuRenderer::new()
        .render(&scene, &Camera::new(intrinsics, truth))
        .map_err(|e| internal(e.into()))?;
    t.render = ms(clock);

    let clock = Instant::now();
    let back_projected = intrinsics
        .back_project_depth(&view.depth, None)
        .map_err(|e| internal(e.into()))?;
    let voxelised = voxel_downsample(&PointCloud::from_points(back_projected), VOXEL)
        .map_err(|e| internal(e.into()))?;
    if voxelised.len() < 3 {
        return Err(internal(anyhow!(
            "the object covers too few pixels ({} points)",
            voxelised.len()
        )));
    }
    let observed =
        random_subsample(&voxelised, OBSERVED_POINTS, &mut rng).map_err(|e| internal(e.into()))?;
    t.observed_points = ms(clock);

    // Stand-in for the network's one-shot estimate (issue 5): the truth, perturbed.
    let axis = DVec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    );
    let shift = DVec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    );
    // Rotate about the object's centre and shift, in the camera frame.
    let initial = Pose::new(
        Pose::from_axis_angle(axis, args.init_rotation_deg.to_radians(), DVec3::ZERO).rotation
            * truth.rotation,
        truth.translation + shift.normalize_or_zero() * args.init_translation,
    );

    let clock = Instant::now();
    // The view shows one side of the object, the model points cover all of it: every observed
    // point has a model counterpart but not the reverse, so ICP registers the observed points
    // onto the model (point-to-plane, the model's face normals) and the result is inverted.
    let model_normals = model.normals.as_deref();
    let target = IcpTarget::new(&model.points, model_normals).map_err(|e| internal(e.into()))?;
    let options = IcpOptions {
        method: IcpMethod::PointToPlane,
        max_correspondence_distance: 0.2,
        max_iterations: 50,
        ..Default::default()
    };
    let result = target
        .register(&observed.points, &initial.inverse(), &options)
        .map_err(|e| internal(e.into()))?;
    let estimate = result.pose.inverse();
    t.icp = ms(clock);

    let report = Report {
        seed: args.seed,
        object_triangles: object.triangles.len(),
        observed_points_after_voxelising: voxelised.len(),
        initial_rotation_error_deg: initial.rotation_angle_to(&truth).to_degrees(),
        initial_translation_error: initial.translation.distance(truth.translation),
        rotation_error_deg: estimate.rotation_angle_to(&truth).to_degrees(),
        translation_error: estimate.translation.distance(truth.translation),
        icp_fitness: result.fitness,
        icp_inlier_rmse: result.inlier_rmse,
        icp_iterations: result.iterations,
        timings_ms: t,
    };
    println!(
        "{}",
        serde_json::to_string_pretty(&report).map_err(|e| internal(e.into()))?
    );

    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating {}", dir.display()))
            .map_err(CliError::Input)?;
        let mut scene_cloud = observed.clone();
        scene_cloud.colors = Some(vec![[160, 160, 160]; scene_cloud.len()]);
        let aligned = PointCloud {
            points: estimate.apply_all(&model.points),
            normals: None,
            colors: Some(vec![[230, 60, 40]; model.len()]),
        };
        scene_cloud.normals = None;
        scene_cloud.extend(&aligned);
        write_ply(
            dir.join("aligned.ply"),
            &scene_cloud,
            PlyEncoding::BinaryLittleEndian,
        )
        .map_err(|e| CliError::Input(e.into()))?;
        ic_render::write_debug_png(dir.join("depth.png"), &view.depth, Some(&view.mask(1)))
            .map_err(|e| CliError::Input(e.into()))?;
        tracing::info!(dir = %dir.display(), "wrote aligned.ply (observed grey, aligned model red) and depth.png");
    }
    Ok(())
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}
