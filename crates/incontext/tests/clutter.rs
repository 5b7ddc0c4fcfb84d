//! Scenes with several objects, as `incontext register` meets them: every instance of the
//! model with `--all`, and a scene whose only object is not the model.

use std::path::Path;
use std::sync::Arc;

use ic_geometry::glam::DVec3;
use ic_geometry::io::{PlyEncoding, write_mesh_ply};
use ic_geometry::{Image, Intrinsics, Mesh, Pose, look_at};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use serde_json::json;

mod common;
use common::*;

/// The model of the tests: a procedural object 200 mm across, in mm.
fn model_mm() -> Mesh {
    let mut mesh = ic_geometry::shapes::random_object(3);
    mesh.normalise().unwrap();
    Mesh {
        vertices: mesh.vertices.iter().map(|v| *v * 100.0).collect(),
        triangles: mesh.triangles,
    }
}

/// Writes the model as `dir/model.ply` and returns it.
fn write_model(dir: &Path) -> Mesh {
    let mesh = model_mm();
    write_mesh_ply(
        dir.join("model.ply"),
        &mesh,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    mesh
}

/// Renders `objects` (mesh, model → world pose; world z up, mm) standing on a 1.2 m table top
/// at z = 0, seen from 750 mm by a 320×240 camera; writes depth.png (0.1 mm steps) and
/// camera.json into `dir` and returns the world → camera pose.
fn render_on_table(dir: &Path, objects: &[(Arc<Mesh>, Pose)]) -> Pose {
    let k = Intrinsics::new(262.5, 262.5, 159.5, 119.5, 320, 240).unwrap();
    let mut scene = Scene::new();
    for (i, (mesh, pose)) in objects.iter().enumerate() {
        scene.push(mesh.clone(), *pose, i as u32 + 1);
    }
    let table =
        ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::new(600.0, 600.0, 10.0)).unwrap();
    scene.push(
        Arc::new(table),
        Pose::from_translation(DVec3::new(0.0, 0.0, -10.0)),
        100,
    );
    let world_to_camera = look_at(
        DVec3::new(0.0, -450.0, 600.0),
        DVec3::new(0.0, 0.0, 40.0),
        DVec3::Z,
    )
    .unwrap();
    let view = CpuRenderer::new()
        .render(&scene, &Camera::new(k, world_to_camera))
        .unwrap();
    let metres = Image {
        width: 320,
        height: 240,
        data: view.depth.data.iter().map(|z| z / 1000.0).collect(),
    };
    ic_render::io::write_depth_png(dir.join("depth.png"), &metres, 0.1).unwrap();
    write(
        &dir.join("camera.json"),
        &json!({"cam_K": k.k_row_major(), "depth_scale": 0.1, "width": 320, "height": 240}),
    );
    world_to_camera
}

/// The model resting on the table at (x, y), turned by `yaw` about the vertical.
fn on_table(mesh: &Mesh, x: f64, y: f64, yaw: f64) -> Pose {
    let min_z = mesh
        .vertices
        .iter()
        .map(|v| v.z as f64)
        .fold(f64::INFINITY, f64::min);
    Pose::new(
        ic_geometry::glam::DMat3::from_rotation_z(yaw),
        DVec3::new(x, y, -min_z),
    )
}

#[test]
fn register_all_returns_each_instance_of_the_model_best_first() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = write_model(dir.path());
    let poses = [
        on_table(&mesh, -170.0, 0.0, 0.3),
        on_table(&mesh, 170.0, 40.0, 2.0),
    ];
    let shared = Arc::new(mesh);
    let world_to_camera = render_on_table(
        dir.path(),
        &poses
            .iter()
            .map(|p| (shared.clone(), *p))
            .collect::<Vec<_>>(),
    );
    let truths: Vec<Pose> = poses.iter().map(|p| world_to_camera.compose(p)).collect();
    let model = s(&dir.path().join("model.ply")).to_string();
    let depth = s(&dir.path().join("depth.png")).to_string();
    let camera = s(&dir.path().join("camera.json")).to_string();
    // The confidence of a network-segmented instance is calibrated on clutter, where a fit of
    // moderate quality is often another object: ask for every instance from 0.2 on.
    let register_all = |extra: &[&str]| {
        let mut args = vec![
            "register", "--model", &model, "--depth", &depth, "--camera", &camera, "--all",
        ];
        args.extend_from_slice(extra);
        incontext(&args)
    };
    let o = register_all(&["--min-confidence", "0.2", "--json", "--seed", "1"]);
    assert!(
        o.status.code() == Some(0) || o.status.code() == Some(4),
        "{}",
        stderr(&o)
    );
    let report = json_stdout(&o);
    let instances = report["instances"].as_array().expect("an instances list");
    assert!(
        instances.len() >= 2,
        "{} instances: {report:#}",
        instances.len()
    );
    // Each true instance is found, by a different returned pose.
    let mut used = Vec::new();
    for truth in &truths {
        let hit = instances.iter().enumerate().find(|(i, inst)| {
            let (err, diameter) = add_s(
                &dir.path().join("model.ply"),
                &pose_of(&inst["pose"]),
                truth,
            );
            !used.contains(i) && err < 0.1 * diameter
        });
        let (i, _) =
            hit.unwrap_or_else(|| panic!("no returned pose matches {truth:?}: {report:#}"));
        used.push(i);
    }
    // Best first, each at least as confident as asked, and the top-level pose is the first
    // instance's.
    let confidences: Vec<f64> = instances
        .iter()
        .map(|i| i["confidence"].as_f64().unwrap())
        .collect();
    assert!(confidences.iter().all(|&c| c >= 0.2), "{confidences:?}");
    // Each instance reports how its model, rendered over the whole image, explains the depth
    // map; an `uncertain` one is returned only when it does.
    for i in instances {
        let w = &i["whole_view"];
        let f = |k: &str| {
            w[k].as_f64()
                .unwrap_or_else(|| panic!("whole_view.{k}: {i:#}"))
        };
        assert!(f("rendered_pixels") >= f("visible_pixels"), "{i:#}");
        if i["verdict"] == "uncertain" {
            assert!(
                f("visible_pixels") >= 50.0 && f("agreement") >= 0.8 && f("in_front") < 0.05,
                "{i:#}"
            );
        }
    }
    // The network chose the pixels: the clutter calibration gave the confidence.
    assert!(
        instances.iter().all(|i| i["calibration"] == "segmentation"),
        "{report:#}"
    );
    assert_eq!(report["pose"], instances[0]["pose"]);
    // The text report lists the same instances, best first.
    let text = register_all(&["--min-confidence", "0.2", "--seed", "1"]);
    let out = String::from_utf8_lossy(&text.stdout);
    assert!(
        out.contains(&format!("instances ({}, best first):", instances.len())),
        "{out}"
    );
    for k in 1..=instances.len() {
        assert!(out.contains(&format!("\n  {k}. ")), "{out}");
    }
    // --min-confidence is for --all, and a probability.
    assert_exit(
        register_all(&["--min-confidence", "1.5"]),
        &[],
        2,
        &["--min-confidence", "1.5"],
    );
    // --all needs the network's instances.
    assert_exit(
        register_all(&["--mask", &depth]),
        &[],
        2,
        &["--all", "--mask"],
    );
}

#[test]
fn a_scene_whose_only_object_is_not_the_model_is_not_found() {
    let dir = tempfile::tempdir().unwrap();
    write_model(dir.path());
    // A 40 mm cube: another object, far too small to be the 200 mm model.
    let cube = ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::splat(20.0)).unwrap();
    render_on_table(
        dir.path(),
        &[(
            Arc::new(cube),
            Pose::from_translation(DVec3::new(0.0, 0.0, 20.0)),
        )],
    );
    let model = s(&dir.path().join("model.ply")).to_string();
    let depth = s(&dir.path().join("depth.png")).to_string();
    let camera = s(&dir.path().join("camera.json")).to_string();
    for all in [false, true] {
        let mut args = vec![
            "register", "--model", &model, "--depth", &depth, "--camera", &camera, "--json",
        ];
        if all {
            args.push("--all");
        }
        let o = check(&args, 3, &["object not found"]);
        assert_eq!(json_stdout(&o)["kind"], "not_found");
    }
}

/// A BOP clutter set of `images` images at 320×240 (mm, 0.1 mm depth steps), each with two
/// copies of the target and two or three other objects, written to `root`.
fn write_clutter_bop(root: &Path, images: u64) {
    use ic_data::bop::{BopWriteOptions, BopWriter};
    use ic_data::{ClutterConfig, ClutterGenerator, Corpus, CorpusOptions, Split};
    let corpus =
        Arc::new(Corpus::procedural(4, Split::Test, 21, CorpusOptions::default()).unwrap());
    let cfg = ClutterConfig {
        fixed_sizes: true,
        full_masks: true,
        multi_target_probability: 1.0,
        target_copies: (2, 2),
        object_count: (4, 5),
        longest_side_m: (0.12, 0.2),
        distance_m: (0.5, 0.6),
        ..ClutterConfig::default().with_resolution(320, 240)
    };
    let g = ClutterGenerator::new(corpus, cfg, 5).unwrap();
    let mut w = BopWriter::create(
        root,
        BopWriteOptions {
            depth_scale: 0.1,
            ..BopWriteOptions::default()
        },
    )
    .unwrap();
    for i in 0..images {
        w.add_clutter(&g.scene(i).unwrap()).unwrap();
    }
    w.finish().unwrap();
}

/// `incontext eval --dataset root <extra> --out out --json --seed 3`, which must exit 0.
fn eval_dataset(root: &Path, extra: &[&str], out: &Path) -> std::process::Output {
    let mut args = vec!["eval", "--dataset", s(root)];
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--out", s(out), "--json", "--seed", "3"]);
    check(&args, 0, &[])
}

/// [`eval_dataset`] with `--gt-mask`.
fn eval_with_true_masks(root: &Path, out: &Path) -> std::process::Output {
    eval_dataset(root, &["--gt-mask"], out)
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn jsonl(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn eval_dataset_registers_every_target_instance_of_a_bop_clutter_set() {
    let dir = tempfile::tempdir().unwrap();
    // Two images, each with two copies of the target and two or three other objects.
    let root = dir.path().join("clutter-bop");
    write_clutter_bop(&root, 2);
    let out = dir.path().join("eval");
    let o = eval_with_true_masks(&root, &out);
    let report = json_stdout(&o);
    assert_eq!(report["mode"], "dataset");
    // Every true instance of every target has a line (two per image here).
    let lines = jsonl(&out.join("per_image.jsonl"));
    let targets = read_json(&root.join("test_targets_bop19.json"));
    let targets = targets.as_array().unwrap();
    assert_eq!(targets.len(), 2);
    for t in targets {
        let n = lines
            .iter()
            .filter(|l| l["im_id"] == t["im_id"] && l["obj_id"] == t["obj_id"])
            .count();
        assert_eq!(n, 2, "two lines for the two copies of {t}");
    }
    // The BOP CSV: one time per image on every row of it.
    let csv = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "csv"))
        .expect("a BOP results CSV");
    let text = std::fs::read_to_string(csv).unwrap();
    let mut time_of = std::collections::HashMap::new();
    for row in text.lines().skip(1) {
        let cols: Vec<&str> = row.split(',').collect();
        assert_eq!(cols.len(), 7, "{row}");
        let t = time_of
            .entry(cols[1].to_string())
            .or_insert(cols[6].to_string());
        assert_eq!(*t, cols[6], "image {} has two times", cols[1]);
    }
    assert!(!time_of.is_empty());
}

/// The rows of a BOP results CSV without their time column, sorted.
fn csv_rows_without_time(out: &Path) -> Vec<String> {
    let csv = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "csv"))
        .expect("a BOP results CSV");
    let mut rows: Vec<String> = std::fs::read_to_string(csv)
        .unwrap()
        .lines()
        .skip(1)
        .map(|r| r.rsplit_once(',').unwrap().0.to_string())
        .collect();
    rows.sort();
    rows
}

#[test]
fn a_test_set_without_ground_truth_is_registered_into_the_csv_as_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("clutter-bop");
    write_clutter_bop(&root, 2);
    let method = ["--method", "ours-softmax"];
    let with_gt = dir.path().join("with-gt");
    let o = eval_dataset(&root, &method, &with_gt);
    assert_eq!(json_stdout(&o)["datasets"]["clutter-bop"]["unscored"], 0);
    // The ground truth withheld, as in a BOP test set whose annotations are private.
    let scene = root.join("test/000000");
    for f in ["scene_gt.json", "scene_gt_info.json"] {
        std::fs::remove_file(scene.join(f)).unwrap();
    }
    for d in ["mask", "mask_visib"] {
        std::fs::remove_dir_all(scene.join(d)).unwrap();
    }
    let without = dir.path().join("without-gt");
    let o = eval_dataset(&root, &method, &without);
    let report = json_stdout(&o);
    assert_eq!(report["datasets"]["clutter-bop"]["unscored"], 2, "{report}");
    let lines = jsonl(&without.join("per_image.jsonl"));
    assert_eq!(lines.len(), 2);
    assert!(lines.iter().all(|l| l["scored"] == false), "{lines:?}");
    // The estimates are the ground truth's business only when scoring: the same rows.
    let rows = csv_rows_without_time(&without);
    assert!(!rows.is_empty());
    assert_eq!(rows, csv_rows_without_time(&with_gt));
    // Without the targets file nothing says what to find; a target naming no model is refused.
    let targets = root.join("test_targets_bop19.json");
    let kept = std::fs::read_to_string(&targets).unwrap();
    std::fs::remove_file(&targets).unwrap();
    let o = incontext(&["eval", "--dataset", s(&root), "--out", s(&without)]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("test_targets_bop19.json"),
        "{}",
        stderr(&o)
    );
    std::fs::write(&targets, kept.replacen("\"obj_id\": ", "\"obj_id\": 9", 1)).unwrap();
    let o = incontext(&["eval", "--dataset", s(&root), "--out", s(&without)]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("test_targets_bop19.json") && stderr(&o).contains("no such model"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn eval_candidates_lists_every_verified_hypothesis_with_its_network_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("clutter-bop");
    write_clutter_bop(&root, 1);
    let out = dir.path().join("eval");
    let o = eval_dataset(
        &root,
        &["--method", "ours-softmax-verify", "--candidates", "2"],
        &out,
    );
    assert_eq!(json_stdout(&o)["mode"], "dataset");
    let lines = jsonl(&out.join("candidates.jsonl"));
    assert!(!lines.is_empty(), "no candidate registered");
    for l in &lines {
        let verified = l["verified"].as_array().unwrap();
        // Both shipped pose networks verify their own hypotheses, the main network's first.
        let networks: Vec<u64> = verified
            .iter()
            .map(|h| h["network"].as_u64().unwrap())
            .collect();
        assert!(
            networks.contains(&0) && networks.contains(&1),
            "{networks:?}"
        );
        assert!(networks.is_sorted(), "{networks:?}");
        // The returned pose is the best-scoring hypothesis, at most refined once more.
        let best = verified
            .iter()
            .max_by(|a, b| {
                a["score"]
                    .as_f64()
                    .unwrap()
                    .total_cmp(&b["score"].as_f64().unwrap())
            })
            .unwrap();
        assert!(best["to_pose"].as_f64().unwrap() < 0.05, "{best}");
        for h in verified {
            assert!(h["to_truth"].as_f64().unwrap() >= 0.0, "{h}");
        }
    }
    // The numbers `cargo xtask fit-clutter-calibration` reads from a line are the ones the
    // pipeline weighed: the clutter confidence of the line's features is its confidence.
    let clutter: Vec<&serde_json::Value> = lines
        .iter()
        .filter(|l| l["calibration"] == "segmentation")
        .collect();
    assert!(!clutter.is_empty(), "no line with the clutter confidence");
    for l in clutter {
        let features: ic_eval::ClutterFeatures = serde_json::from_value((*l).clone()).unwrap();
        let p = incontext::clutter_confidence().apply(&features);
        let given = l["confidence"].as_f64().unwrap();
        assert!((p - given).abs() < 1e-9, "{p} against {given}: {l}");
        assert!(l["whole_view"].is_object(), "{l}");
    }
}

/// BOP scores a target of `inst_count` instances on its `inst_count` most visible true
/// instances, and with `--gt-mask` each instance's pose comes from its own mask — even when
/// the registration of an instance before it fails.
#[test]
fn eval_dataset_scores_the_most_visible_copies_and_each_copy_by_its_own_mask() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("clutter-bop");
    write_clutter_bop(&root, 1);
    let scene = root.join("test/000000");
    let target = &read_json(&root.join("test_targets_bop19.json"))[0];
    assert_eq!(target["inst_count"], 2, "{target}");
    let mut gt = read_json(&scene.join("scene_gt.json"));
    let list = gt["0"].as_array_mut().unwrap();
    let copies: Vec<usize> = (0..list.len())
        .filter(|&g| list[g]["obj_id"] == target["obj_id"])
        .collect();
    assert_eq!(copies.len(), 2);
    // A third copy, hidden behind the others: annotated, no pixel visible.
    let hidden = list.len();
    let mut entry = list[copies[0]].clone();
    entry["cam_t_m2c"][2] = json!(entry["cam_t_m2c"][2].as_f64().unwrap() + 300.0);
    list.push(entry);
    std::fs::write(scene.join("scene_gt.json"), gt.to_string()).unwrap();
    let mask_file = |folder: &str, g: usize| scene.join(folder).join(format!("000000_{g:06}.png"));
    let mut block = Image::filled(320, 240, false);
    for v in 100..110 {
        for u in 100..110 {
            block.data[v * 320 + u] = true;
        }
    }
    ic_render::io::write_mask_png(mask_file("mask", hidden), &block).unwrap();
    ic_render::io::write_mask_png(
        mask_file("mask_visib", hidden),
        &Image::filled(320, 240, false),
    )
    .unwrap();
    // The first copy keeps 4 pixels, all of its silhouette (the most visible), too few to
    // register: its estimate fails, and the second copy's must not take its place.
    let mut tiny = Image::filled(320, 240, false);
    let first_visible =
        ic_render::io::read_mask_png(mask_file("mask_visib", copies[0]), Some((320, 240))).unwrap();
    let at = first_visible.data.iter().position(|&m| m).unwrap();
    for d in [0, 1, 320, 321] {
        tiny.data[(at + d).min(320 * 240 - 1)] = true;
    }
    for folder in ["mask", "mask_visib"] {
        ic_render::io::write_mask_png(mask_file(folder, copies[0]), &tiny).unwrap();
    }
    let out = dir.path().join("eval");
    eval_with_true_masks(&root, &out);
    let lines = jsonl(&out.join("per_image.jsonl"));
    assert_eq!(
        lines.len(),
        2,
        "the hidden copy is not a target: {lines:#?}"
    );
    let of = |g: usize| {
        lines
            .iter()
            .find(|l| l["gt_index"] == g)
            .unwrap_or_else(|| panic!("no line for copy {g}: {lines:#?}"))
    };
    assert_eq!(of(copies[0])["ok"], false, "{lines:#?}");
    assert!(
        of(copies[0])["error"]
            .as_str()
            .unwrap()
            .contains("object points"),
        "{lines:#?}"
    );
    assert_eq!(of(copies[1])["ok"], true, "{lines:#?}");
    assert!(of(copies[1])["errors"]["add_s"].is_number(), "{lines:#?}");
}

#[test]
fn eval_frames_judges_each_pose_against_the_depth_without_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = write_model(dir.path());
    let frame = dir.path().join("scene1");
    std::fs::create_dir_all(frame.join("depth")).unwrap();
    let shared = Arc::new(mesh.clone());
    render_on_table(&frame, &[(shared, on_table(&mesh, 0.0, 0.0, 0.7))]);
    std::fs::rename(frame.join("depth.png"), frame.join("depth/0000.png")).unwrap();
    std::fs::rename(frame.join("camera.json"), dir.path().join("camera.json")).unwrap();
    // A second frame, left out by --limit 1 (the first in name order is registered).
    std::fs::copy(frame.join("depth/0000.png"), frame.join("depth/0001.png")).unwrap();
    // The first as a 16-bit TIFF of the same stored values.
    let scale = read_json(&dir.path().join("camera.json"))["depth_scale"]
        .as_f64()
        .unwrap_or(1.0);
    depth_png_to_tiff(&frame.join("depth/0000.png"), scale);
    let out = dir.path().join("out");
    let o = check(
        &[
            "eval",
            "--frames",
            s(dir.path()),
            "--out",
            s(&out),
            "--json",
            "--seed",
            "2",
            "--limit",
            "1",
        ],
        0,
        &[],
    );
    let report = json_stdout(&o);
    let m = &report["methods"]["ours-softmax-verify"];
    assert_eq!(m["frames"], 1);
    assert_eq!(m["best_agrees"], 1, "{report:#}");
    let line: serde_json::Value = serde_json::from_str(
        std::fs::read_to_string(out.join("frames.jsonl"))
            .unwrap()
            .lines()
            .next()
            .unwrap(),
    )
    .unwrap();
    assert!(line["best"]["agreement"]["agreement"].as_f64().unwrap() >= 0.8);
    let overlay = std::path::Path::new(line["overlay"].as_str().unwrap());
    assert!(overlay.is_file());
    assert!(
        overlay.ends_with("ours-softmax-verify_scene1_depth_0000.png"),
        "{line:#}"
    );
    assert!(
        line["frame"].as_str().unwrap().ends_with("0000.tif"),
        "{line:#}"
    );
    // A folder without depth maps is bad input, and so is a limit that leaves no frame.
    let empty = tempfile::tempdir().unwrap();
    check(&["eval", "--frames", s(empty.path())], 2, &["no depth map"]);
    check(
        &["eval", "--frames", s(dir.path()), "--limit", "0"],
        2,
        &["--limit 0"],
    );
}

/// The scene of `incontext demo --seed 50` (a procedural object of several parts, alone in
/// the room, mm) and its true pose.
fn lone_composite_scene() -> (incontext::Object, ic_geometry::DepthImage, Intrinsics, Pose) {
    let scene = incontext::demo::DemoScene::new(50).unwrap();
    let object = incontext::Object::from_mesh(scene.mesh_mm(), 3).unwrap();
    (
        object,
        scene.depth_mm(),
        scene.view.intrinsics,
        scene.truth_mm(),
    )
}

#[test]
fn a_lone_object_the_clutter_network_cuts_into_parts_is_registered_whole_by_the_one_object_network()
{
    let (object, depth, intrinsics, truth) = lone_composite_scene();
    // The clutter network alone cuts the object into parts; with one pose network, the pose
    // fitted to the best of them (about half of the object) cannot be trusted: with the
    // default weights it scores well on the part's crop but puts most of the model in front
    // of what the sensor saw (`verify::OK_MAX_IN_FRONT`), so it is not `ok`.
    let clutter_only = incontext::Pipeline::builder()
        .seg_model(incontext::models::SEG.workspace_path())
        .second_pose(false)
        .threads(2)
        .build()
        .unwrap();
    assert!(clutter_only.seg_one_object_source().is_none());
    assert!(clutter_only.second_pose_source().is_none());
    let r = clutter_only
        .register_depth(&object, &depth, &intrinsics, None, 3)
        .unwrap();
    assert_ne!(r.verdict, incontext::Verdict::Ok, "{:?}", r.instance);
    assert!(r.instance.unwrap().size_ratio < 0.64, "{:?}", r.instance);
    // Without the rule it would have been: the crop scored it, the whole view refused it.
    let whole = r.whole_view.unwrap();
    assert!(whole.impossible(), "{whole:?}");
    // The pipeline with the one-object network asks it when nothing was `ok`: the whole
    // object, the right pose, trusted.
    let default_one_network = incontext::Pipeline::builder()
        .second_pose(false)
        .threads(2)
        .build()
        .unwrap();
    assert!(default_one_network.seg_one_object_source().is_some());
    let r = default_one_network
        .register_depth(&object, &depth, &intrinsics, None, 3)
        .unwrap();
    assert_eq!(r.verdict, incontext::Verdict::Ok, "{:?}", r.instance);
    assert!(r.instance.unwrap().one_object_network, "{:?}", r.instance);
    assert!(
        r.pose.rotation_angle_to(&truth).to_degrees() < 2.0
            && (r.pose.translation - truth.translation).length() < 5.0, // mm
        "{:?}",
        r.pose
    );
    // `register`'s default, both pose networks: the same (before the rule, the second
    // network's pose of a part, 141 mm off, was returned as `ok`).
    let r = incontext::Pipeline::builder()
        .threads(2)
        .build()
        .unwrap()
        .register_depth(&object, &depth, &intrinsics, None, 3)
        .unwrap();
    assert_eq!(r.verdict, incontext::Verdict::Ok, "{:?}", r.instance);
    assert!(
        r.pose.rotation_angle_to(&truth).to_degrees() < 2.0
            && (r.pose.translation - truth.translation).length() < 5.0, // mm
        "{:?} {:?}",
        r.pose,
        r.instance
    );
}

#[test]
fn an_extra_input_size_adds_only_instances_not_found_at_the_networks_own() {
    // The lone composite the clutter network cuts into parts: several instances.
    let (object, depth, intrinsics, _) = lone_composite_scene();
    let depth_n = object.normalised_depth(&depth);
    let candidates = |extra: Vec<(u32, u32)>| {
        let mut seg = incontext::models::load_seg(None).unwrap();
        seg.segmenter.config_mut().post.extra_inputs = extra;
        let pose = incontext::models::load_pose(None, None).unwrap();
        let pipeline = incontext::Pipeline::new(pose, Some(seg), Default::default());
        pipeline
            .instance_candidates(&object, &depth_n, &intrinsics)
            .unwrap()
    };
    let masks = |c: &[incontext::pipeline::InstanceCandidate]| -> Vec<Vec<bool>> {
        c.iter().map(|c| c.mask.data.clone()).collect()
    };
    let own = candidates(Vec::new());
    assert!(own.len() >= 2, "{own:?}");
    assert!(own.iter().all(|c| c.input == 0));
    // The network's own size again finds every instance again: nothing is added.
    let (w, h) = {
        let cfg = incontext::models::load_seg(None).unwrap();
        let net = &cfg.segmenter.config().net;
        (net.input_width, net.input_height)
    };
    assert_eq!(masks(&candidates(vec![(w, h)])), masks(&own));
    // A finer size: every candidate of the own size is still there; what it adds comes from
    // it and overlaps none of those by the duplicate IoU; the same twice.
    let pooled = candidates(vec![(w * 3 / 2, h * 3 / 2)]);
    assert_eq!(
        masks(&pooled),
        masks(&candidates(vec![(w * 3 / 2, h * 3 / 2)]))
    );
    let pooled_own: Vec<Vec<bool>> = pooled
        .iter()
        .filter(|c| c.input == 0)
        .map(|c| c.mask.data.clone())
        .collect();
    let mut sorted_own = masks(&own);
    sorted_own.sort();
    let mut sorted_pooled_own = pooled_own.clone();
    sorted_pooled_own.sort();
    assert_eq!(sorted_pooled_own, sorted_own);
    let iou = |a: &[bool], b: &[bool]| {
        let both = a.iter().zip(b).filter(|(p, q)| **p && **q).count();
        let either = a.iter().zip(b).filter(|(p, q)| **p || **q).count();
        both as f64 / either.max(1) as f64
    };
    // On this scene the finer size cuts parts the own size did not (else this test could not
    // tell a size that is ignored).
    assert!(
        pooled.iter().any(|c| c.input == 1),
        "{} own, {} pooled",
        own.len(),
        pooled.len()
    );
    for c in pooled.iter().filter(|c| c.input == 1) {
        for o in &pooled_own {
            assert!(iou(&c.mask.data, o) < incontext::pipeline::DUPLICATE_IOU);
        }
    }
}
