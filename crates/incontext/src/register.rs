//! `incontext register`: the pose of a mesh in one depth map, from files.

use std::path::PathBuf;
use std::time::Instant;

use ic_geometry::Pose;
use ic_pose::{Head, Refine};
use serde_json::{Value, json};

use crate::error::Result;
use crate::inputs;
use crate::outputs::{self, Named};
use crate::overlay;
use crate::pipeline::{Object, Pipeline, PipelineBuilder, PipelineOptions, Registration, Verdict};

/// The error of a registration whose verdict is `not_found` (exit code 3).
pub fn not_found_error(r: &Registration, options: &PipelineOptions) -> crate::CliError {
    let why = match &r.verification {
        Some(v) => format!(
            "the model rendered at the best pose agrees with {:.0} % of the object's depth \
             (render-and-compare score {:.2}, below {:.2})",
            100.0 * v.score,
            v.score,
            options.verified_found
        ),
        None => format!(
            "the best pose explains {:.0} % of the object (confidence {:.2}, below {:.2})",
            100.0 * r.confidence,
            r.confidence,
            options.confidence_found
        ),
    };
    crate::CliError::not_found(format!(
        "object not found: {why}; is this the right mesh, in the depth map's units \
         (--model-unit-mm), and is the object in view?"
    ))
}

/// Flags of `incontext register`.
#[derive(clap::Args, Debug, Clone, serde::Serialize)]
pub struct RegisterArgs {
    /// The object's mesh (OBJ, PLY, OFF, glTF/GLB), in the depth map's units (BOP: mm; see
    /// --model-unit-mm).
    #[arg(long)]
    pub model: PathBuf,
    /// The depth map: a 16-bit PNG or a one-channel TIFF, 16-bit or float (value × the camera's
    /// depth_scale = mm, BOP), or an EXR in metres; 0 = no return.
    #[arg(long)]
    pub depth: PathBuf,
    /// BOP-style camera JSON: cam_K (9 numbers, row-major) or fx/fy/cx/cy; width, height
    /// (optional: the depth map's size); depth_scale (default 1).
    #[arg(long)]
    pub camera: PathBuf,
    /// The object's pixels (8-bit PNG, non-zero = object) instead of the segmentation network.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    #[command(flatten)]
    pub networks: NetworkArgs,
    /// Millimetres per mesh unit (1 for BOP meshes in mm, 1000 for meshes in metres).
    #[arg(long, default_value_t = 1.0)]
    pub model_unit_mm: f64,
    /// Write the result (pose, confidence, timings) as JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Write the model rendered at the estimated pose over the colour-mapped depth (PNG).
    #[arg(long)]
    pub overlay: Option<PathBuf>,
    /// Write the scene points (grey) and the aligned model (red) as a PLY, in mesh units.
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// Every instance of the object in view (e.g. a bin of identical parts): the report's
    /// `instances` lists each found one (pose, confidence, verdict), best first; `pose` is
    /// the best. Needs the segmentation network (not with --mask).
    #[arg(long)]
    pub all: bool,
    /// With --all: also return `uncertain` instances whose confidence (the calibrated
    /// probability that the pose is right) reaches this, in [0, 1], and whose model rendered
    /// at the pose explains the depth map where it would be seen (`whole_view`). Default:
    /// only `ok` ones (confidence ≥ 0.9), or the best such `uncertain` one when none is `ok`.
    #[arg(long, requires = "all", value_parser = parse_probability)]
    pub min_confidence: Option<f64>,
}

/// A probability in [0, 1].
pub(crate) fn parse_probability(s: &str) -> std::result::Result<f64, String> {
    let p: f64 = s.parse().map_err(|_| format!("{s:?} is not a number"))?;
    if (0.0..=1.0).contains(&p) {
        Ok(p)
    } else {
        Err(format!("{p} is not in [0, 1]"))
    }
}

/// Which networks and refinement (shared by `register`, `demo`, `eval`).
#[derive(clap::Args, Debug, Clone, serde::Serialize)]
pub struct NetworkArgs {
    /// Correspondence head of the shipped pose network: softmax or ot.
    #[arg(long, value_parser = parse_head)]
    #[serde(serialize_with = "ser_head")]
    pub head: Option<Head>,
    /// Refinement after the one-shot estimate: icp or none.
    #[arg(long, default_value = "icp", value_parser = parse_refine)]
    pub refine: Refine,
    /// A pose checkpoint instead of the shipped one; it is then the only pose network unless
    /// --second-pose-model is given.
    #[arg(long)]
    pub pose_model: Option<PathBuf>,
    /// A second pose checkpoint of the same head whose hypotheses join the main network's in
    /// verification, instead of the shipped second network (softmax head only).
    #[arg(long, conflicts_with = "no_second_pose")]
    pub second_pose_model: Option<PathBuf>,
    /// Verify the main pose network's hypotheses alone (faster; without it the shipped second
    /// network's join them).
    #[arg(long)]
    pub no_second_pose: bool,
    /// A segmentation checkpoint instead of the shipped ones (it is then the only one: no
    /// one-object second opinion; e.g. models/seg-cpu.safetensors for one object per scene).
    #[arg(long)]
    pub seg_model: Option<PathBuf>,
    /// The pose networks' attention keys: N farthest-point samples of each cloud (fewer is
    /// faster, same weights) or `all` (every point, the paper's transformer); default: each
    /// network's own setting.
    #[arg(long, value_parser = parse_attention_keys)]
    pub attention_keys: Option<AttentionKeys>,
    /// Pose hypotheses (each its own point draw, network run and refinement; the one that
    /// explains the most object points wins). 1 = the paper's one-shot pipeline.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub hypotheses: u32,
    /// Rotation hypotheses: 24 (default), 12 or 60 rotated copies of the model (rotation groups
    /// covering SO(3) evenly), batched through the network; the best are refined by ICP and
    /// verified by rendering the model against the depth map. 1 = the paper's single
    /// orientation, unverified (faster; right only for views like the training ones).
    #[arg(long, default_value_t = 24, value_parser = parse_rotations)]
    pub rotations: usize,
    /// With --rotations: how many of the hypotheses (the rotated copies' one-shot and sampled
    /// poses, ranked by how many object points they explain) are refined by ICP and verified
    /// by render-and-compare.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=60))]
    pub verify_top: u32,
    /// With --rotations: how many rotated copies go on through the network's transformer after
    /// its first stage (the unrotated copy and those whose point features best match the
    /// observed ones); 0 = all. Fewer is faster.
    #[arg(long, default_value_t = PipelineOptions::default().sweep_keep)]
    pub sweep_keep: usize,
    /// With --rotations: poses per rotated copy drawn as minimal sets of three of its
    /// correspondences (seeded RANSAC over the soft assignment), added to the hypotheses.
    #[arg(long, default_value_t = PipelineOptions::default().sampled_hypotheses)]
    pub sampled_hypotheses: usize,
    /// With --rotations: passes of the network over each verified hypothesis. Each pass after
    /// the first registers a copy of the model turned by the hypothesis's rotation, where the
    /// network is most precise, before ICP and verification (among several instances, only
    /// the best-ranked one gets them). 1 = the sweep alone (faster).
    #[arg(long, default_value_t = PipelineOptions::default().network_passes as u32,
          value_parser = clap::value_parser!(u32).range(1..=4))]
    pub network_passes: u32,
    /// With --network-passes above 1: how many hypotheses (the best by the point-distance
    /// ranking) the second pass takes; each later pass takes the previous pass's. 0 = all
    /// --verify-top.
    #[arg(long, default_value_t = PipelineOptions::default().pass_top)]
    pub pass_top: usize,
    /// With the segmentation network: instances of the model's size registered, best-fitting
    /// first, until one is `ok` (then as many pieces cut from heaps); the best verified pose
    /// wins. Fewer is faster when nothing is `ok`; 0 = every instance that fits.
    #[arg(long, default_value_t = PipelineOptions::default().instance_tries)]
    pub instance_tries: usize,
}

/// `--attention-keys`: a count of keys per cloud, or `None` for every point.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct AttentionKeys(pub Option<usize>);

pub fn parse_attention_keys(s: &str) -> std::result::Result<AttentionKeys, String> {
    if s == "all" {
        return Ok(AttentionKeys(None));
    }
    match s.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(AttentionKeys(Some(n))),
        _ => Err(format!(
            "{s:?} is not a number of attention keys (a count ≥ 1, or all)"
        )),
    }
}

pub fn parse_rotations(s: &str) -> std::result::Result<usize, String> {
    let n: usize = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number of rotations"))?;
    crate::verify::rotation_set(n).map(|_| n)
}

fn ser_head<S: serde::Serializer>(h: &Option<Head>, s: S) -> std::result::Result<S::Ok, S::Error> {
    match h {
        Some(h) => s.serialize_str(h.as_str()),
        None => s.serialize_none(),
    }
}

pub fn parse_head(s: &str) -> std::result::Result<Head, String> {
    match s {
        "softmax" => Ok(Head::Softmax),
        "ot" => Ok(Head::Ot),
        other => Err(format!("unknown head {other:?}: expected softmax or ot")),
    }
}

pub fn parse_refine(s: &str) -> std::result::Result<Refine, String> {
    match s {
        "icp" => Ok(Refine::Icp),
        "none" => Ok(Refine::None),
        other => Err(format!(
            "unknown refinement {other:?}: expected icp or none"
        )),
    }
}

impl NetworkArgs {
    /// The pipeline these flags describe (the segmentation network only when `with_seg`),
    /// not loaded yet.
    pub fn builder(&self, with_seg: bool) -> PipelineBuilder {
        let mut b = Pipeline::builder()
            .segmentation(with_seg)
            .refine(self.refine)
            .hypotheses(self.hypotheses as usize)
            .rotations(self.rotations)
            .verify_top(self.verify_top as usize)
            .sweep_keep(self.sweep_keep)
            .sampled_hypotheses(self.sampled_hypotheses)
            .network_passes(self.network_passes as usize)
            .pass_top(self.pass_top)
            .instance_tries(self.instance_tries)
            .second_pose(!self.no_second_pose);
        if let Some(path) = &self.second_pose_model {
            b = b.second_pose_model(path);
        }
        if let Some(head) = self.head {
            b = b.head(head);
        }
        if let Some(path) = &self.pose_model {
            b = b.pose_model(path);
        }
        if let Some(path) = &self.seg_model {
            b = b.seg_model(path);
        }
        if let Some(AttentionKeys(keys)) = self.attention_keys {
            b = b.attention_keys(keys);
        }
        b
    }

    /// Loads the pipeline (the segmentation network only when `with_seg`).
    pub fn pipeline(&self, with_seg: bool) -> Result<Pipeline> {
        Ok(self.builder(with_seg).build()?)
    }
}

/// `{"R": rows, "t": [x, y, z]}`: [`Pose`]'s serde form (R row-major).
pub fn pose_json(pose: &Pose) -> Value {
    json!(pose)
}

/// BOP's `cam_R_m2c` (9 numbers, row-major) and `cam_t_m2c` (mm) of a pose in mesh units.
pub fn bop_pose_json(pose: &Pose, model_unit_mm: f64) -> Value {
    let r = pose.rotation_row_major();
    let t = pose.translation * model_unit_mm;
    json!({"cam_R_m2c": r.concat(), "cam_t_m2c": [t.x, t.y, t.z], "units": "mm"})
}

pub(crate) fn ms(seconds: f64) -> f64 {
    (seconds * 1e6).round() / 1e3
}

/// The result of `register` (also what `demo` runs on its own files).
pub struct RegisterOutcome {
    pub registration: Registration,
    pub object: Object,
    /// The JSON report (also written to `--out`).
    pub report: Value,
}

/// Runs `register` on files: reads them, registers, writes the requested outputs.
pub fn register_files(args: &RegisterArgs, seed: u64) -> Result<RegisterOutcome> {
    let clock = Instant::now();
    if !(args.model_unit_mm.is_finite() && args.model_unit_mm > 0.0) {
        return Err(crate::CliError::input(format!(
            "--model-unit-mm must be positive, got {}",
            args.model_unit_mm
        )));
    }
    if args.all && args.mask.is_some() {
        return Err(crate::CliError::input(
            "--all finds every instance with the segmentation network; it cannot take --mask",
        ));
    }
    // Outputs before any work: none may replace a device, a link, an input or another output.
    let mut ins = vec![
        Named::new("--model", &args.model),
        Named::new("--depth", &args.depth),
        Named::new("--camera", &args.camera),
    ];
    let optional_ins = [
        ("--mask", &args.mask),
        ("--pose-model", &args.networks.pose_model),
        ("--second-pose-model", &args.networks.second_pose_model),
        ("--seg-model", &args.networks.seg_model),
    ];
    for (what, p) in &optional_ins {
        if let Some(p) = p {
            ins.push(Named::new(what, p));
        }
    }
    let outs: Vec<Named> = [
        ("--out", &args.out),
        ("--overlay", &args.overlay),
        ("--ply", &args.ply),
    ]
    .iter()
    .filter_map(|(what, p)| p.as_deref().map(|p| Named::new(what, p)))
    .collect();
    outputs::check_outputs(&ins, &outs)?;

    // Inputs: the camera first (the depth map's size is checked against it).
    let camera = inputs::read_camera(&args.camera, || inputs::depth_size(&args.depth))?;
    let k = camera.intrinsics;
    let depth_mm = inputs::read_depth_mm(&args.depth, &camera)?;
    let mask = match &args.mask {
        Some(p) => Some(inputs::read_mask(p, &k)?),
        None => None,
    };
    let mesh = inputs::read_mesh(&args.model)?;
    let triangles = mesh.triangles.len();
    // Depth in mesh units.
    let to_units = (1.0 / args.model_unit_mm) as f32;
    let depth = ic_geometry::Image {
        width: depth_mm.width,
        height: depth_mm.height,
        data: depth_mm.data.iter().map(|&z| z * to_units).collect(),
    };
    let load_seconds = clock.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut pipeline = args.networks.pipeline(mask.is_none())?;
    pipeline.options.all_min_confidence = args.min_confidence;
    let networks_seconds = t.elapsed().as_secs_f64();
    let config = json!({
        "seed": seed,
        "networks": pipeline.describe(),
        "model_unit_mm": args.model_unit_mm,
        "depth_scale": camera.depth_scale,
        "intrinsics": k,
    });
    tracing::info!(seed, config = %config, "incontext register");

    let object = Object::from_mesh(mesh, seed).map_err(|e| e.context(args.model.display()))?;
    let (registration, others) = if args.all {
        let mut found = pipeline.register_depth_all(&object, &depth, &k, seed)?;
        if found.is_empty() {
            return Err(crate::CliError::not_found(
                "object not found: no instance of the model was found in the depth map; is this \
                 the right mesh, in the depth map's units (--model-unit-mm), and is it in view?",
            ));
        }
        let best = found.remove(0);
        (best, found)
    } else {
        let r = pipeline.register_depth(&object, &depth, &k, mask.as_ref(), seed)?;
        (r, Vec::new())
    };
    if registration.verdict == Verdict::NotFound {
        return Err(not_found_error(&registration, &pipeline.options));
    }

    // Every output is computed first, then written: pose.json, the overlay, the PLY.
    let t = Instant::now();
    let mut outputs = serde_json::Map::new();
    if let Some(path) = &args.out {
        outputs.insert("pose".into(), json!(path));
    }
    let overlay_rgb = match &args.overlay {
        Some(path) => {
            let mesh = object
                .mesh
                .as_ref()
                .ok_or_else(|| crate::CliError::internal("the object has no mesh"))?;
            let poses: Vec<Pose> = std::iter::once(&registration)
                .chain(&others)
                .map(|r| r.pose_normalised)
                .collect();
            let model = overlay::render_masks(mesh, &poses, &k)?;
            outputs.insert("overlay".into(), json!(path));
            Some(overlay::overlay_rgb(
                &depth,
                &model,
                registration.mask.as_ref(),
            ))
        }
        None => None,
    };
    let ply_points = match &args.ply {
        Some(path) => {
            let scale = object.normalisation.scale as f32;
            let voxel = pipeline.options.voxel_size * scale;
            let scene = overlay::scene_points(&depth, &k, voxel)?;
            let aligned: Vec<_> = object
                .points
                .iter()
                .map(|p| registration.pose_normalised.apply_f32(*p) * scale)
                .collect();
            outputs.insert("ply".into(), json!(path));
            Some((scene, aligned))
        }
        None => None,
    };
    let outputs_seconds = t.elapsed().as_secs_f64();

    let s = &registration.seconds;
    let instance_json = |r: &Registration| {
        json!({
            "pose": pose_json(&r.pose),
            "pose_bop": bop_pose_json(&r.pose, args.model_unit_mm),
            "pose_normalised": pose_json(&r.pose_normalised),
            "confidence": r.confidence,
            "calibration": r.calibration,
            "verdict": r.verdict,
            "segmentation": r.segmentation,
            "instance": r.instance,
            "verification": r.verification,
            "whole_view": r.whole_view,
        })
    };
    let instances: Option<Vec<Value>> = args.all.then(|| {
        std::iter::once(&registration)
            .chain(&others)
            .map(instance_json)
            .collect()
    });
    let report = json!({
        "command": "register",
        "seed": seed,
        "inputs": {"model": args.model, "depth": args.depth, "camera": args.camera, "mask": args.mask, "model_triangles": triangles},
        "config": config,
        "pose": pose_json(&registration.pose),
        "units": format!("pose in the mesh's own units, camera frame (x right, y down, z forward); 1 mesh unit = {} mm", args.model_unit_mm),
        "pose_bop": bop_pose_json(&registration.pose, args.model_unit_mm),
        "pose_normalised": pose_json(&registration.pose_normalised),
        "confidence": registration.confidence,
        "calibration": registration.calibration,
        "verdict": registration.verdict,
        "instances": instances,
        "details": {
            "segmentation": registration.segmentation,
            "instance": registration.instance,
            "object_points": registration.object_points,
            "object_voxels": registration.object_voxels,
            "inlier_count": registration.inlier_count,
            "assignment_confidence": registration.assignment_confidence,
            "icp": registration.icp,
            "verification": registration.verification,
            "whole_view": registration.whole_view,
            "rival_score": registration.rival_score,
            "evidence": registration.evidence,
            "hypotheses_made": registration.hypotheses_made,
            "hypotheses_verified": registration.hypotheses_verified,
            "one_shot_normalised": pose_json(&registration.one_shot_normalised),
            "normalisation": object.normalisation,
        },
        "timings_ms": {
            "load_inputs": ms(load_seconds),
            "load_networks": ms(networks_seconds),
            "model_points": ms(object.seconds),
            "segmentation_network": ms(s.segmentation_network),
            "segmentation_post": ms(s.segmentation_post),
            "observed_points": ms(s.observed_points),
            "pose_network": ms(s.pose_network),
            "ranking": ms(s.ranking),
            "icp": ms(s.icp),
            "verification": ms(s.verification),
            "registration": ms(s.total),
            "outputs": ms(outputs_seconds),
            "total": ms(clock.elapsed().as_secs_f64()),
        },
        "outputs": outputs,
    });
    if let Some(path) = &args.out {
        inputs::write_json(path, &report)?;
    }
    if let (Some(path), Some(rgb)) = (&args.overlay, &overlay_rgb) {
        overlay::write_rgb_png(path, depth.width, depth.height, rgb)?;
    }
    if let (Some(path), Some((scene, aligned))) = (&args.ply, &ply_points) {
        overlay::write_two_colour_ply(path, scene, aligned)?;
    }
    Ok(RegisterOutcome {
        registration,
        object,
        report,
    })
}

/// Human-readable lines of a register report.
pub fn summary_text(report: &Value) -> String {
    let mut s = String::new();
    let fmt3 = |v: &Value| -> String {
        v.as_array()
            .map(|a| {
                a.iter()
                    .map(|x| format!("{:.6}", x.as_f64().unwrap_or(f64::NAN)))
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .unwrap_or_default()
    };
    let pose = &report["pose"];
    s.push_str("pose (mesh units, camera frame):\n");
    if let Some(rows) = pose["R"].as_array() {
        for (i, row) in rows.iter().enumerate() {
            s.push_str(&format!(
                "  {} [{}]\n",
                if i == 0 { "R =" } else { "   " },
                fmt3(row)
            ));
        }
    }
    s.push_str(&format!("  t = [{}]\n", fmt3(&pose["t"])));
    s.push_str(&format!(
        "  BOP cam_t_m2c = [{}] mm\n",
        fmt3(&report["pose_bop"]["cam_t_m2c"])
    ));
    let d = &report["details"];
    s.push_str(&format!(
        "verdict {}: confidence {:.3} ({} object voxels; segmentation: {}{}; ICP fitness {})\n",
        report["verdict"].as_str().unwrap_or("?"),
        report["confidence"].as_f64().unwrap_or(f64::NAN),
        d["object_voxels"],
        d["segmentation"]["source"].as_str().unwrap_or("?"),
        d["segmentation"]["score"]
            .as_f64()
            .map(|x| format!(" score {x:.3}"))
            .unwrap_or_default(),
        d["icp"]["fitness"]
            .as_f64()
            .map(|x| format!("{x:.3}"))
            .unwrap_or_else(|| "–".into()),
    ));
    // --all: every instance returned, best first (the first is the pose above).
    if let Some(instances) = report["instances"].as_array() {
        s.push_str(&format!("instances ({}, best first):\n", instances.len()));
        for (i, inst) in instances.iter().enumerate() {
            let agreement = inst["whole_view"]["agreement"]
                .as_f64()
                .map(|a| format!(", whole view {:.0} % agreeing", 100.0 * a))
                .unwrap_or_default();
            s.push_str(&format!(
                "  {}. {} confidence {:.3}, t = [{}]{agreement}\n",
                i + 1,
                inst["verdict"].as_str().unwrap_or("?"),
                inst["confidence"].as_f64().unwrap_or(f64::NAN),
                fmt3(&inst["pose"]["t"]),
            ));
        }
    }
    if let Ok(w) = serde_json::from_value::<crate::verify::WholeView>(d["whole_view"].clone()) {
        s.push_str(&format!(
            "whole view: {:.0} % of the model's {} visible pixels agree with the depth, \
             {:.0} % lie in front of it, {:.0} % have no return{}\n",
            100.0 * w.agreement,
            w.visible_pixels,
            100.0 * w.in_front,
            100.0 * w.missing,
            if w.consistent() {
                ""
            } else {
                " — the pose does not explain the depth where its model would be seen: check it \
                 (--overlay)"
            }
        ));
    }
    let t = &report["timings_ms"];
    let f = |k: &str| t[k].as_f64().unwrap_or(f64::NAN);
    s.push_str(&format!(
        "timings (ms): load {:.0}, networks {:.0}, model points {:.0}, segmentation {:.0} + {:.0}, observed points {:.0}, pose network {:.0}, ranking {:.0}, ICP {:.0}, verification {:.0}, registration {:.0}, total {:.0}\n",
        f("load_inputs"),
        f("load_networks"),
        f("model_points"),
        f("segmentation_network"),
        f("segmentation_post"),
        f("observed_points"),
        f("pose_network"),
        f("ranking"),
        f("icp"),
        f("verification"),
        f("registration"),
        f("total"),
    ));
    if let Some(o) = report["outputs"].as_object() {
        for (k, v) in o {
            s.push_str(&format!("wrote {k}: {}\n", v.as_str().unwrap_or("?")));
        }
    }
    s
}
