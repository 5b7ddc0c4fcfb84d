//! `incontext demo`: the whole pipeline on a scene it makes itself.
//!
//! A procedural object (`ic_geometry::shapes`, through an `ic_data` procedural corpus) is put
//! in the room of the test scenes (`ic_data::RoomSampleGenerator`: 640×480, fx = fy = 525, 1
//! unit = 1 dm, camera 32 cm – 1 m from the object on the paper's view sphere) and rendered.
//! The demo writes what a user would have — the mesh in mm (`model.ply`), the depth map
//! (`depth.png`, 16-bit mm) and the camera (`camera.json`) — plus the ground truth
//! (`gt_pose.json`, `mask_gt.png`), then runs exactly `incontext register` on those files
//! (segmentation, pose network, ICP) and compares the result with the ground truth.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use ic_data::{
    Corpus, CorpusObject, CorpusOptions, ROOM_UNIT_MM, RoomSampleConfig, RoomSampleGenerator,
    RoomView, Split,
};
use ic_geometry::io::{PlyEncoding, write_mesh_ply};
use ic_geometry::{Image, Mesh, Normalisation};
use ic_render::CpuRenderer;
use serde_json::{Value, json};

use crate::error::{CliError, Result, ResultExt};
use crate::inputs;
use crate::register::{self, NetworkArgs, RegisterArgs, bop_pose_json, ms, pose_json};

/// Flags of `incontext demo`.
#[derive(clap::Args, Debug, Clone, serde::Serialize)]
pub struct DemoArgs {
    /// Output folder: model.ply, depth.png, camera.json, gt_pose.json, mask_gt.png (the inputs
    /// and the truth), pose.json, overlay.png, aligned.ply (the result).
    #[arg(long, default_value = "incontext-demo")]
    pub out: PathBuf,
    #[command(flatten)]
    pub networks: NetworkArgs,
    /// Use the rendered ground-truth mask instead of the segmentation network.
    #[arg(long)]
    pub gt_mask: bool,
}

/// The scene of `incontext demo --seed S`: one procedural object of the test stream alone in
/// the room, rendered at 640×480 (depth, pose and masks in normalised object units).
pub struct DemoScene {
    pub view: RoomView,
    pub object: Arc<CorpusObject>,
}

impl DemoScene {
    pub fn new(seed: u64) -> Result<DemoScene> {
        let options = CorpusOptions {
            // The corpus's cached model points are not used here (register samples its own).
            model_points: 16,
            ..CorpusOptions::default()
        };
        let corpus = Arc::new(
            Corpus::procedural(1, Split::Test, seed, options)
                .internal_err("building the object")?,
        );
        let generator = RoomSampleGenerator::new(corpus.clone(), RoomSampleConfig::default(), seed)
            .internal_err("setting up the room")?;
        let view = generator
            .view_with(&mut CpuRenderer::new(), 0)
            .internal_err("rendering the scene")?;
        let object = corpus
            .position(&view.object_id)
            .map(|i| corpus.object(i))
            .ok_or_else(|| CliError::internal("the rendered object is not in the corpus"))?
            .internal_err("loading the object")?;
        Ok(DemoScene { view, object })
    }

    /// The object's mesh in millimetres ([`ROOM_UNIT_MM`] per normalised unit), as the demo
    /// writes it.
    pub fn mesh_mm(&self) -> Mesh {
        let mesh = &self.object.mesh;
        Mesh {
            vertices: mesh
                .vertices
                .iter()
                .map(|v| *v * ROOM_UNIT_MM as f32)
                .collect(),
            triangles: mesh.triangles.clone(),
        }
    }

    /// The depth map in millimetres (0 = no return).
    pub fn depth_mm(&self) -> ic_geometry::DepthImage {
        let d = &self.view.depth;
        Image {
            width: d.width,
            height: d.height,
            data: d.data.iter().map(|&z| z * ROOM_UNIT_MM as f32).collect(),
        }
    }

    /// The true pose of [`DemoScene::mesh_mm`] in the camera frame, mm.
    pub fn truth_mm(&self) -> ic_geometry::Pose {
        Normalisation {
            centre: ic_geometry::glam::DVec3::ZERO,
            scale: ROOM_UNIT_MM,
        }
        .pose_to_original(&self.view.pose)
    }
}

pub fn run(args: &DemoArgs, seed: u64) -> Result<Value> {
    let clock = Instant::now();
    if !args.gt_mask && args.networks.seg_model.is_none() && !crate::models::SEG.available() {
        return Err(CliError::input(format!(
            "the segmentation model models/{} is not built into this binary and {} does not exist: \
             pass --seg-model FILE, or run the demo with --gt-mask (the rendered object mask)",
            crate::models::SEG.file,
            crate::models::SEG.workspace_path().display()
        )));
    }
    tracing::info!(seed, config = %serde_json::to_string(args).unwrap_or_default(), "incontext demo");

    let scene = DemoScene::new(seed)?;
    let (view, object) = (&scene.view, &scene.object);
    let scene_seconds = clock.elapsed().as_secs_f64();

    // The files a user would have, in millimetres.
    let t = Instant::now();
    let out = &args.out;
    let files = DemoFiles::new(out);
    let ins: Vec<crate::outputs::Named> = [
        ("--pose-model", &args.networks.pose_model),
        ("--second-pose-model", &args.networks.second_pose_model),
        ("--seg-model", &args.networks.seg_model),
    ]
    .iter()
    .filter_map(|(what, p)| p.as_deref().map(|p| crate::outputs::Named::new(what, p)))
    .collect();
    crate::outputs::check_outputs(&ins, &files.named())?;
    inputs::create_dir(out)?;
    let unit = ROOM_UNIT_MM;
    write_mesh_ply(
        &files.model,
        &scene.mesh_mm(),
        PlyEncoding::BinaryLittleEndian,
    )?;
    let k = view.intrinsics;
    let metres = Image {
        width: view.depth.width,
        height: view.depth.height,
        data: view
            .depth
            .data
            .iter()
            .map(|&z| (z as f64 * unit / 1000.0) as f32)
            .collect(),
    };
    ic_render::io::write_depth_png(&files.depth, &metres, 1.0)?;
    inputs::write_json(
        &files.camera,
        &json!({"cam_K": k.k_row_major().concat(), "depth_scale": 1.0, "width": k.width, "height": k.height}),
    )?;
    ic_render::io::write_mask_png(&files.mask, &view.mask_visib)?;
    let truth_mm = scene.truth_mm();
    let mut gt = pose_json(&truth_mm);
    gt["bop"] = bop_pose_json(&truth_mm, 1.0);
    gt["units"] = json!("mm, camera frame");
    gt["object_id"] = json!(view.object_id);
    inputs::write_json(&files.gt_pose, &gt)?;
    let files_seconds = t.elapsed().as_secs_f64();

    // Exactly `incontext register` on those files.
    let rargs = RegisterArgs {
        model: files.model.clone(),
        depth: files.depth.clone(),
        camera: files.camera.clone(),
        mask: args.gt_mask.then(|| files.mask.clone()),
        networks: args.networks.clone(),
        model_unit_mm: 1.0,
        out: Some(files.pose.clone()),
        overlay: Some(files.overlay.clone()),
        ply: Some(files.ply.clone()),
        all: false,
        min_confidence: None,
    };
    let outcome = register::register_files(&rargs, seed)?;
    let r = &outcome.registration;

    let est = r.pose;
    let one_shot = outcome
        .object
        .normalisation
        .pose_to_original(&r.one_shot_normalised);
    let points_mm: Vec<_> = outcome
        .object
        .points
        .iter()
        .map(|p| {
            outcome
                .object
                .normalisation
                .to_original(p.as_dvec3())
                .as_vec3()
        })
        .collect();
    let diameter_mm = ic_eval::diameter(&points_mm[..points_mm.len().min(1024)]);
    let add_s = ic_eval::add_s(&est, &truth_mm, &points_mm)?;
    let errors = json!({
        "rotation_deg": ic_eval::rotation_error_deg(&est, &truth_mm),
        "translation_mm": ic_eval::translation_error(&est, &truth_mm),
        "translation_normalised": ic_eval::translation_error(&est, &truth_mm) / unit,
        "add_s_mm": add_s,
        "add_s_over_diameter": add_s / diameter_mm,
        "one_shot_rotation_deg": ic_eval::rotation_error_deg(&one_shot, &truth_mm),
        "one_shot_translation_mm": ic_eval::translation_error(&one_shot, &truth_mm),
    });
    let pixels = view.mask_visib.data.iter().filter(|&&m| m).count();
    let mut timings = outcome.report["timings_ms"].clone();
    timings["scene"] = json!(ms(scene_seconds));
    timings["write_inputs"] = json!(ms(files_seconds));
    timings["demo_total"] = json!(ms(clock.elapsed().as_secs_f64()));
    Ok(json!({
        "command": "demo",
        "seed": seed,
        "object": {"id": view.object_id, "triangles": object.mesh.triangles.len(), "diameter_mm": diameter_mm},
        "scene": {
            "width": k.width, "height": k.height,
            "camera_distance_mm": view.pose.translation.length() * unit,
            "object_pixels": pixels,
        },
        "segmentation": if args.gt_mask { "ground-truth mask (--gt-mask)" } else { "network" },
        "errors": errors,
        "pose": outcome.report["pose"],
        "truth": pose_json(&truth_mm),
        "confidence": r.confidence,
        "verdict": r.verdict,
        "details": outcome.report["details"],
        "config": outcome.report["config"],
        "timings_ms": timings,
        "files": files.json(),
    }))
}

/// The files the demo writes.
struct DemoFiles {
    model: PathBuf,
    depth: PathBuf,
    camera: PathBuf,
    mask: PathBuf,
    gt_pose: PathBuf,
    pose: PathBuf,
    overlay: PathBuf,
    ply: PathBuf,
}

impl DemoFiles {
    fn new(out: &Path) -> Self {
        DemoFiles {
            model: out.join("model.ply"),
            depth: out.join("depth.png"),
            camera: out.join("camera.json"),
            mask: out.join("mask_gt.png"),
            gt_pose: out.join("gt_pose.json"),
            pose: out.join("pose.json"),
            overlay: out.join("overlay.png"),
            ply: out.join("aligned.ply"),
        }
    }

    /// Every file the demo writes, with what it is.
    fn named(&self) -> Vec<crate::outputs::Named<'_>> {
        use crate::outputs::Named;
        vec![
            Named::new("the demo's model.ply", &self.model),
            Named::new("the demo's depth.png", &self.depth),
            Named::new("the demo's camera.json", &self.camera),
            Named::new("the demo's mask_gt.png", &self.mask),
            Named::new("the demo's gt_pose.json", &self.gt_pose),
            Named::new("the demo's pose.json", &self.pose),
            Named::new("the demo's overlay.png", &self.overlay),
            Named::new("the demo's aligned.ply", &self.ply),
        ]
    }

    fn json(&self) -> Value {
        json!({
            "model": self.model, "depth": self.depth, "camera": self.camera, "mask_gt": self.mask,
            "gt_pose": self.gt_pose, "pose": self.pose, "overlay": self.overlay, "aligned_ply": self.ply,
        })
    }
}

/// Human-readable lines of a demo report.
pub fn summary_text(report: &Value) -> String {
    let e = &report["errors"];
    let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
    let mut s = format!(
        "demo seed {}: object {} ({} triangles) at {:.0} mm, {} object pixels, segmentation: {}\n",
        report["seed"],
        report["object"]["id"].as_str().unwrap_or("?"),
        report["object"]["triangles"],
        f(&report["scene"]["camera_distance_mm"]),
        report["scene"]["object_pixels"],
        report["segmentation"].as_str().unwrap_or("?"),
    );
    s.push_str(&format!(
        "errors: rotation {:.2}° (one-shot {:.2}°), translation {:.1} mm ({:.4} normalised), ADD-S {:.1} mm = {:.3} of the diameter; confidence {:.3} (verdict {})\n",
        f(&e["rotation_deg"]),
        f(&e["one_shot_rotation_deg"]),
        f(&e["translation_mm"]),
        f(&e["translation_normalised"]),
        f(&e["add_s_mm"]),
        f(&e["add_s_over_diameter"]),
        f(&report["confidence"]),
        report["verdict"].as_str().unwrap_or("?"),
    ));
    let t = &report["timings_ms"];
    s.push_str(&format!(
        "timings (ms): scene {:.0}, write inputs {:.0}, load {:.0}, networks {:.0}, model points {:.0}, segmentation {:.0} + {:.0}, observed points {:.0}, pose network {:.0}, ranking {:.0}, ICP {:.0}, verification {:.0}, registration {:.0}, outputs {:.0}, total {:.0}\n",
        f(&t["scene"]),
        f(&t["write_inputs"]),
        f(&t["load_inputs"]),
        f(&t["load_networks"]),
        f(&t["model_points"]),
        f(&t["segmentation_network"]),
        f(&t["segmentation_post"]),
        f(&t["observed_points"]),
        f(&t["pose_network"]),
        f(&t["ranking"]),
        f(&t["icp"]),
        f(&t["verification"]),
        f(&t["registration"]),
        f(&t["outputs"]),
        f(&t["demo_total"]),
    ));
    s.push_str(&format!(
        "wrote {} (overlay: {})\n",
        report["files"]["pose"].as_str().unwrap_or("?"),
        report["files"]["overlay"].as_str().unwrap_or("?"),
    ));
    s
}
