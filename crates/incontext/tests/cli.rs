//! Runs the `incontext` binary as a user would: good inputs, every kind of bad input (each
//! must exit with its code and a message naming the problem, never a panic), and the demo end
//! to end.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use ic_geometry::Image;
use serde_json::{Value, json};

mod common;
use common::*;

#[test]
fn register_with_a_mask_finds_the_pose_and_writes_every_output() {
    let sc = SmallScene::new();
    let out = sc.p("pose.json");
    let o = check(
        &[
            "register",
            "--model",
            &sc.p("model.ply"),
            "--depth",
            &sc.p("depth.png"),
            "--camera",
            &sc.p("camera.json"),
            "--mask",
            &sc.p("mask.png"),
            "--out",
            &out,
            "--overlay",
            &sc.p("overlay.png"),
            "--ply",
            &sc.p("aligned.ply"),
            "--json",
            "--seed",
            "1",
        ],
        0,
        &["incontext register", "\"seed\":1"],
    );
    let report = json_stdout(&o);
    let pose = pose_of(&report["pose"]);
    // ADD-S, not the rotation error: the object may be symmetric.
    let (err, diameter) = add_s(&sc.path("model.ply"), &pose, &sc.truth);
    assert!(
        err < 0.1 * diameter,
        "ADD-S {err} mm, diameter {diameter} mm"
    );
    assert!(report["confidence"].as_f64().unwrap() > 0.5);
    for key in [
        "segmentation_network",
        "observed_points",
        "pose_network",
        "icp",
        "total",
    ] {
        assert!(report["timings_ms"][key].as_f64().is_some(), "timing {key}");
    }
    // BOP units: this mesh is in mm, so BOP's t equals ours.
    let bop_t = report["pose_bop"]["cam_t_m2c"][2].as_f64().unwrap();
    assert!((bop_t - pose.translation.z).abs() < 1e-9);
    // --out holds the same report; the other outputs exist.
    let written: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(written["pose"], report["pose"]);
    assert!(sc.path("overlay.png").is_file() && sc.path("aligned.ply").is_file());
    // The EXR depth (metres) gives the same pose as the PNG (0.1 mm steps).
    let o = check(
        &[
            "register",
            "--model",
            &sc.p("model.ply"),
            "--depth",
            &sc.p("depth.exr"),
            "--camera",
            &sc.p("camera.json"),
            "--mask",
            &sc.p("mask.png"),
            "--json",
            "-q",
            "--seed",
            "1",
        ],
        0,
        &[],
    );
    let exr = pose_of(&json_stdout(&o)["pose"]);
    let (apart, diameter) = add_s(&sc.path("model.ply"), &exr, &pose);
    assert!(apart < 0.01 * diameter, "{apart} mm apart");
}

#[test]
fn the_real_object_weights_beside_the_default_load_and_find_the_pose() {
    // models/pose-cpu-softmax-scratch.safetensors, the default pipeline's second pose
    // network, as the only one (`--pose-model`).
    let weights = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../models/pose-cpu-softmax-scratch.safetensors");
    let sc = SmallScene::new();
    assert_register_finds_the_pose(&sc, "--pose-model", weights.to_str().unwrap());
}

/// `register --json` with `flag value` on the small scene exits 0 with a pose within ADD-S
/// 0.1·diameter of the truth.
fn assert_register_finds_the_pose(sc: &SmallScene, flag: &str, value: &str) {
    let mut args = register_args(sc, flag, value);
    args.extend(["--json", "-q", "--seed", "1"].map(String::from));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = check(&args, 0, &[]);
    let pose = pose_of(&json_stdout(&o)["pose"]);
    let (err, diameter) = add_s(&sc.path("model.ply"), &pose, &sc.truth);
    assert!(
        err < 0.1 * diameter,
        "{flag} {value}: ADD-S {err} mm, diameter {diameter} mm"
    );
}

/// `--attention-keys N` runs the shipped networks over N keys per cloud (the same weights)
/// and still finds the pose; the builder applies it to both pose networks and says so in the
/// configuration every run logs; a count of 0 or a word is a bad flag.
#[test]
fn attention_keys_run_the_same_weights_over_fewer_keys_and_still_find_the_pose() {
    let sc = SmallScene::new();
    assert_register_finds_the_pose(&sc, "--attention-keys", "48");
    check_register(
        &sc,
        "--attention-keys",
        "0",
        2,
        &["--attention-keys", "≥ 1, or all"],
    );
    check_register(&sc, "--attention-keys", "most", 2, &["--attention-keys"]);
    let keys = |b: incontext::PipelineBuilder| {
        let d = b.segmentation(false).build().unwrap().describe();
        (
            d["attention_keys"].clone(),
            d["second_attention_keys"].clone(),
        )
    };
    let builder = incontext::Pipeline::builder;
    assert_eq!(
        keys(builder().attention_keys(Some(48))),
        (json!(48), json!(48))
    );
    assert_eq!(
        keys(builder().attention_keys(None)),
        (json!("all"), json!("all"))
    );
    assert_eq!(
        keys(builder()),
        (json!(64), json!(64)),
        "the shipped networks' own"
    );
    let alone = builder().second_pose(false);
    assert_eq!(keys(alone), (json!(64), json!(null)), "no second network");
}

#[test]
fn render_writes_depth_and_mask_that_match_the_scene() {
    let sc = SmallScene::new();
    let pose = sc.path("truth.json");
    write(&pose, &json!(sc.truth));
    let out = sc.path("rendered");
    let o = check(
        &[
            "render",
            "--model",
            &sc.p("model.ply"),
            "--camera",
            &sc.p("camera.json"),
            "--pose",
            s(&pose),
            "--out",
            s(&out),
            "--json",
        ],
        0,
        &[],
    );
    assert!(json_stdout(&o)["object_pixels"].as_u64().unwrap() > 100);
    let a = ic_render::io::read_depth_png(out.join("depth.png"), 0.1, None).unwrap();
    let b = ic_render::io::read_depth_png(sc.path("depth.png"), 0.1, None).unwrap();
    assert_eq!(
        a, b,
        "the same mesh, camera and pose render the same depth map"
    );
    let mask = ic_render::io::read_mask_png(out.join("mask.png"), None).unwrap();
    assert_eq!(
        mask,
        ic_render::io::read_mask_png(sc.path("mask.png"), None).unwrap()
    );
    assert!(out.join("depth.exr").is_file() && out.join("camera.json").is_file());
}

// ---------------------------------------------------------------------------------------------
// Bad input: exit code 2 and a message that names the file and the problem.

/// `register` on the small scene with `replace` swapped in for one flag's value.
#[test]
fn missing_or_unreadable_files_are_bad_input() {
    let sc = SmallScene::new();
    let missing = sc.p("nope.ply");
    check_register(&sc, "--model", &missing, 2, &["nope.ply", "cannot read"]);
    check_register(&sc, "--depth", &sc.p("nope.png"), 2, &["nope.png"]);
    check_register(
        &sc,
        "--camera",
        &sc.p("nope.json"),
        2,
        &["nope.json", "cannot read"],
    );
    check_register(&sc, "--mask", &sc.p("nope_mask.png"), 2, &["nope_mask.png"]);
    // Files that exist but are not what they claim.
    std::fs::write(sc.path("garbage.png"), b"not a png at all").unwrap();
    check_register(&sc, "--depth", &sc.p("garbage.png"), 2, &["garbage.png"]);
    std::fs::write(sc.path("garbage.tif"), b"II*\0 not a tiff").unwrap();
    check_register(&sc, "--depth", &sc.p("garbage.tif"), 2, &["garbage.tif"]);
    tiff::encoder::TiffEncoder::new(std::fs::File::create(sc.path("rgb.tif")).unwrap())
        .unwrap()
        .write_image::<tiff::encoder::colortype::RGB8>(160, 120, &vec![7; 160 * 120 * 3])
        .unwrap();
    check_register(
        &sc,
        "--depth",
        &sc.p("rgb.tif"),
        2,
        &["rgb.tif", "expected one channel"],
    );
    std::fs::write(sc.path("garbage.json"), b"{ cam_K: ").unwrap();
    check_register(
        &sc,
        "--camera",
        &sc.p("garbage.json"),
        2,
        &["garbage.json", "not valid JSON"],
    );
    check_register(
        &sc,
        "--depth",
        &sc.p("camera.json"),
        2,
        &["camera.json", "unsupported depth format"],
    );
    check_register(
        &sc,
        "--pose-model",
        &missing,
        2,
        &["nope.ply", "pose model"],
    );
    // --json: one JSON object with the error and the code on stdout.
    let args = register_args(&sc, "--model", &missing);
    let mut args: Vec<&str> = args.iter().map(String::as_str).collect();
    args.push("--json");
    let o = check(&args, 2, &["nope.ply"]);
    let v = json_stdout(&o);
    assert_eq!(v["exit_code"], 2);
    assert_eq!(v["kind"], "input");
    assert!(v["error"].as_str().unwrap().contains("nope.ply"));
}

#[test]
fn a_depth_map_of_another_size_than_the_camera_is_bad_input() {
    let sc = SmallScene::new();
    let cam = sc.path("camera_big.json");
    write(
        &cam,
        &json!({"cam_K": [131.25, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], "depth_scale": 0.1, "width": 320, "height": 240}),
    );
    check_register(
        &sc,
        "--camera",
        s(&cam),
        2,
        &["depth.png", "160×120", "expected 320×240"],
    );
}

#[test]
fn wrong_bit_depth_or_channel_count_is_bad_input() {
    let sc = SmallScene::new();
    // An 8-bit grayscale PNG as the depth.
    check_register(
        &sc,
        "--depth",
        &sc.p("mask.png"),
        2,
        &["mask.png", "16-bit", "8-bit"],
    );
    // A 16-bit RGB PNG as the depth.
    let rgb = sc.path("rgb16.png");
    let file = std::fs::File::create(&rgb).unwrap();
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), 160, 120);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Sixteen);
    let mut w = enc.write_header().unwrap();
    w.write_image_data(&vec![0u8; 160 * 120 * 6]).unwrap();
    w.finish().unwrap();
    check_register(&sc, "--depth", s(&rgb), 2, &["rgb16.png", "3 channel"]);
    // A 16-bit depth PNG as the mask.
    check_register(
        &sc,
        "--mask",
        &sc.p("depth.png"),
        2,
        &["depth.png", "8-bit", "16-bit"],
    );
    // An EXR with two channels.
    let two = sc.path("two.exr");
    write_two_channel_exr(&two);
    check_register(
        &sc,
        "--depth",
        s(&two),
        2,
        &["two.exr", "one channel named Z or Y", "2 channel"],
    );
}

fn write_two_channel_exr(path: &Path) {
    use exr::prelude::*;
    let (w, h) = (160usize, 120usize);
    let channels = vec![
        AnyChannel::new("Z", FlatSamples::F32(vec![1.0; w * h])),
        AnyChannel::new("A", FlatSamples::F32(vec![1.0; w * h])),
    ];
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    exr::image::Image::from_layer(layer)
        .write()
        .to_file(path)
        .unwrap();
}

#[test]
fn all_zero_or_nan_depth_is_bad_input() {
    let sc = SmallScene::new();
    let zero = sc.path("zero.png");
    ic_render::io::write_depth_png(&zero, &Image::filled(160, 120, 0.0), 1.0).unwrap();
    check_register(&sc, "--depth", s(&zero), 2, &["zero.png", "no valid pixel"]);
    let nan = sc.path("nan.exr");
    ic_render::io::write_depth_exr(&nan, &Image::filled(160, 120, f32::NAN)).unwrap();
    check_register(&sc, "--depth", s(&nan), 2, &["nan.exr", "no valid pixel"]);
}

#[test]
fn non_positive_focal_length_is_bad_input() {
    let sc = SmallScene::new();
    for (name, fx) in [("zero_fx.json", 0.0), ("negative_fx.json", -131.25)] {
        let cam = sc.path(name);
        write(
            &cam,
            &json!({"cam_K": [fx, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], "depth_scale": 0.1, "width": 160, "height": 120}),
        );
        check_register(
            &sc,
            "--camera",
            s(&cam),
            2,
            &[name, "focal lengths must be positive"],
        );
    }
    let cam = sc.path("no_k.json");
    write(
        &cam,
        &json!({"depth_scale": 0.1, "width": 160, "height": 120}),
    );
    check_register(&sc, "--camera", s(&cam), 2, &["no_k.json", "cam_K"]);
}

#[test]
fn a_mesh_without_faces_is_bad_input() {
    let sc = SmallScene::new();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures");
    let obj = fixtures.join("cli/no_faces.obj");
    check_register(&sc, "--model", s(&obj), 2, &["no_faces.obj", "no faces"]);
    let ply = fixtures.join("meshes/cloud_binary_le.ply");
    check_register(
        &sc,
        "--model",
        s(&ply),
        2,
        &["cloud_binary_le.ply", "no faces"],
    );
    check_register(
        &sc,
        "--model",
        &sc.p("camera.json"),
        2,
        &["camera.json", "unsupported mesh format"],
    );
}

/// The shipped pose checkpoint with its recorded configuration changed to another shape.
fn checkpoint_of_another_shape(dir: &Path) -> PathBuf {
    let shipped = incontext::models::POSE_SOFTMAX.workspace_path();
    let bytes = std::fs::read(&shipped).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let key = "ic_pose.config";
    let mut config: Value =
        serde_json::from_str(header["__metadata__"][key].as_str().unwrap()).unwrap();
    config["net"]["emb_dims"] = json!(64);
    header["__metadata__"][key] = json!(config.to_string());
    let new_header = serde_json::to_vec(&header).unwrap();
    let mut out = (new_header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&new_header);
    out.extend_from_slice(&bytes[8 + n..]);
    let path = dir.join("other-shape.safetensors");
    std::fs::write(&path, out).unwrap();
    path
}

#[test]
fn a_checkpoint_of_another_network_shape_is_bad_input() {
    let sc = SmallScene::new();
    let other = checkpoint_of_another_shape(sc.dir.path());
    check_register(
        &sc,
        "--pose-model",
        s(&other),
        2,
        &[
            "other-shape.safetensors",
            "does not match its configuration",
        ],
    );
    // A file that is not a checkpoint at all.
    check_register(
        &sc,
        "--pose-model",
        &sc.p("camera.json"),
        2,
        &["camera.json"],
    );
    // A segmentation checkpoint that is not one (no --mask, so the network is loaded).
    let (m, d, c) = (sc.p("model.ply"), sc.p("depth.png"), sc.p("camera.json"));
    check(
        &[
            "register",
            "--model",
            &m,
            "--depth",
            &d,
            "--camera",
            &c,
            "--seg-model",
            &m,
        ],
        2,
        &["model.ply", "segmentation model"],
    );
}

#[test]
fn an_empty_mask_is_bad_input() {
    let sc = SmallScene::new();
    let empty = sc.path("empty.png");
    ic_render::io::write_mask_png(&empty, &Image::filled(160, 120, false)).unwrap();
    check_register(&sc, "--mask", s(&empty), 2, &["empty.png", "mask is empty"]);
    // A mask on pixels without depth.
    let mut corner = Image::filled(160, 120, false);
    corner.data[0] = true;
    let p = sc.path("corner.png");
    ic_render::io::write_mask_png(&p, &corner).unwrap();
    check_register(
        &sc,
        "--mask",
        s(&p),
        2,
        &["mask", "no pixel with a valid depth"],
    );
}

#[test]
fn a_sliver_of_object_is_object_not_found() {
    let sc = SmallScene::new();
    // Five object pixels: far fewer object points than the network needs.
    let full = ic_render::io::read_mask_png(sc.path("mask.png"), None).unwrap();
    let mut sliver = Image::filled(160, 120, false);
    for i in full
        .data
        .iter()
        .enumerate()
        .filter(|(_, m)| **m)
        .map(|(i, _)| i)
        .take(5)
    {
        sliver.data[i] = true;
    }
    let p = sc.path("sliver.png");
    ic_render::io::write_mask_png(&p, &sliver).unwrap();
    let args = register_args(&sc, "--mask", s(&p));
    let mut args: Vec<&str> = args.iter().map(String::as_str).collect();
    args.push("--json");
    let o = check(&args, 3, &["object not found"]);
    assert_eq!(json_stdout(&o)["exit_code"], 3);
}

#[test]
fn a_depth_map_without_the_object_is_object_not_found() {
    let sc = SmallScene::new();
    let flat = sc.path("flat.png");
    ic_render::io::write_depth_png(&flat, &Image::filled(160, 120, 1.0), 0.1).unwrap();
    let (m, c) = (sc.p("model.ply"), sc.p("camera.json"));
    let o = check(
        &[
            "register",
            "--model",
            &m,
            "--depth",
            s(&flat),
            "--camera",
            &c,
            "--json",
        ],
        3,
        &["object not found"],
    );
    assert_eq!(json_stdout(&o)["kind"], "not_found");
}

#[test]
fn bad_flags_are_bad_input() {
    let sc = SmallScene::new();
    check_register(&sc, "--head", "sinkhorn2", 2, &["--head", "softmax or ot"]);
    check_register(&sc, "--refine", "gn", 2, &["--refine", "icp or none"]);
    check_register(
        &sc,
        "--model-unit-mm",
        "0",
        2,
        &["--model-unit-mm must be positive"],
    );
    check(&["demo", "--seed", "minus-one"], 2, &["--seed"]);
    check(&["eval"], 2, &["--dataset", "--cases"]);
    check(
        &["eval", "--cases", s(sc.dir.path()), "--method", "ours-icp"],
        2,
        &["ours-icp"],
    );
    if !incontext::models::POSE_OT.available() {
        check_register(
            &sc,
            "--head",
            "ot",
            2,
            &["pose-cpu-ot.safetensors", "--pose-model"],
        );
    }
    // Every command documents itself with an example.
    for cmd in ["register", "demo", "eval", "render"] {
        let o = check(&[cmd, "--help"], 0, &[]);
        assert!(
            String::from_utf8_lossy(&o.stdout).contains("Example"),
            "{cmd} --help"
        );
    }
    let o = check(&["--help"], 0, &[]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("Exit codes"));
}

// ---------------------------------------------------------------------------------------------
// eval

/// Two object-alone cases as `cargo xtask export-cases` writes them.
fn write_cases(dir: &Path) {
    use ic_data::{Corpus, CorpusOptions, ObjectSampleConfig, ObjectSampleGenerator, Split};
    let corpus = Arc::new(Corpus::procedural(2, Split::Test, 1, CorpusOptions::default()).unwrap());
    let cfg = ObjectSampleConfig {
        keep_images: true,
        ..ObjectSampleConfig::default()
    };
    let g = ObjectSampleGenerator::new(corpus.clone(), cfg, 1).unwrap();
    let mut bop = ic_data::bop::BopWriter::create(dir.join("bop"), Default::default()).unwrap();
    for i in 0..2 {
        let sample = g.sample(i).unwrap();
        ic_data::export::write_object_case(dir.join(format!("cases/case_{i:05}")), &sample, 1)
            .unwrap();
        let obj = corpus
            .object(corpus.position(&sample.object_id).unwrap())
            .unwrap();
        bop.add(&sample.bop_frame(&obj).unwrap()).unwrap();
    }
    bop.finish().unwrap();
}

#[test]
fn eval_writes_peer_lines_for_cases_and_tables_for_a_bop_dataset() {
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let out = dir.path().join("results.jsonl");
    let cases = dir.path().join("cases");
    check(
        &[
            "eval",
            "--cases",
            s(&cases),
            "--method",
            "ours-softmax",
            "--method",
            "ours-softmax-icp",
            "--out",
            s(&out),
            "--seed",
            "2",
        ],
        0,
        &["[4/4] case_00001 ours-softmax-icp"],
    );
    let text = std::fs::read_to_string(&out).unwrap();
    let lines: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 4);
    for (raw, l) in text.lines().zip(&lines) {
        // The keys of open3d_peers.py, in its order.
        let at: Vec<usize> = ["case", "method", "R", "t", "seconds", "ok", "error"]
            .iter()
            .map(|k| {
                raw.find(&format!("\"{k}\":"))
                    .unwrap_or_else(|| panic!("{k} in {raw}"))
            })
            .collect();
        assert!(at.windows(2).all(|w| w[0] < w[1]), "{raw}");
        // Then ours add the confidence and the verdict (the scorer ignores extra keys).
        assert_eq!(l.as_object().unwrap().len(), 9, "{l}");
        let c = l["confidence"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&c), "{l}");
        assert!(["ok", "uncertain", "not_found"].contains(&l["verdict"].as_str().unwrap()));
        assert_eq!(l["ok"], true, "{l}");
        assert!(l["error"].is_null() && l["seconds"].as_f64().unwrap() > 0.0);
    }
    // The refined pose is close to the truth (gt.json is read here, never by the method).
    for l in lines.iter().filter(|l| l["method"] == "ours-softmax-icp") {
        let gt: Value = serde_json::from_str(
            &std::fs::read_to_string(cases.join(l["case"].as_str().unwrap()).join("gt.json"))
                .unwrap(),
        )
        .unwrap();
        let err = pose_of(l).rotation_angle_to(&pose_of(&gt)).to_degrees();
        assert!(err < 30.0, "{}: {err}°", l["case"]);
    }

    // The same views as a BOP dataset, with the ground-truth masks (no segmentation network).
    let eval_out = dir.path().join("eval-out");
    let o = check(
        &[
            "eval",
            "--dataset",
            s(&dir.path().join("bop")),
            "--gt-mask",
            "--out",
            s(&eval_out),
            "--json",
            "-q",
        ],
        0,
        &[],
    );
    let report = json_stdout(&o);
    assert!(
        report["tables"]
            .as_str()
            .unwrap()
            .contains("| ours-softmax-icp | 2 |")
    );
    for f in [
        "results.md",
        "results.json",
        "rotation.png",
        "translation.svg",
        "per_image.jsonl",
    ] {
        assert!(eval_out.join(f).is_file(), "{f}");
    }
    let csv = std::fs::read_to_string(eval_out.join("ours-softmax-icp_bop-test.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows[0], "scene_id,im_id,obj_id,score,R,t,time");
    assert_eq!(rows.len(), 3);
    let fields: Vec<&str> = rows[1].split(',').collect();
    assert_eq!(fields.len(), 7);
    assert_eq!(fields[4].split(' ').count(), 9);
    assert_eq!(fields[5].split(' ').count(), 3);
}

#[test]
fn eval_reads_the_tless_layout_models_cad_and_a_primesense_split() {
    // T-LESS ships models_cad/ (no models/) and its test images in test_primesense/: the same
    // two views moved into that layout register as in the plain one, and the BOP results file
    // is named as BOP's toolkit parses it (`<method>_<dataset>-<split>-<split type>.csv`).
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let plain = dir.path().join("bop");
    let tless = dir.path().join("tless");
    let want = bop_rows(dir.path(), &plain, "test", "ours-softmax-icp_bop-test.csv");
    assert_eq!(want.len(), 3, "{want:?}");
    std::fs::rename(&plain, &tless).unwrap();
    std::fs::rename(tless.join("models"), tless.join("models_cad")).unwrap();
    std::fs::rename(tless.join("test"), tless.join("test_primesense")).unwrap();
    let got = bop_rows(
        dir.path(),
        &tless,
        "test_primesense",
        "ours-softmax-icp_tless-test-primesense.csv",
    );
    assert_eq!(got, want);
    // Without either models folder the error names the dataset's folder and what it lacks.
    std::fs::rename(tless.join("models_cad"), tless.join("models_reconst")).unwrap();
    check(
        &[
            "eval",
            "--dataset",
            s(&tless),
            "--split",
            "test_primesense",
            "--gt-mask",
        ],
        2,
        &["neither a BOP dataset (models/, or T-LESS's models_cad/"],
    );
}

#[test]
fn eval_reads_depth_stored_as_tiff_as_itodd_ships_it() {
    // ITODD stores its depth maps as TIFF (`depth/{im_id:06}.tif`, `stored × depth_scale =
    // mm` as the PNGs): the same two views with their depth rewritten as 16-bit TIFF give the
    // same BOP rows.
    let dir = tempfile::tempdir().unwrap();
    write_cases(dir.path());
    let root = dir.path().join("bop");
    let want = bop_rows(dir.path(), &root, "test", "ours-softmax-icp_bop-test.csv");
    assert_eq!(want.len(), 3, "{want:?}");
    let mut converted = 0;
    for scene in std::fs::read_dir(root.join("test")).unwrap() {
        let depth_dir = scene.unwrap().path().join("depth");
        for png in std::fs::read_dir(&depth_dir).unwrap() {
            // Written at depth_scale 1 (1 mm per step).
            depth_png_to_tiff(&png.unwrap().path(), 1.0);
            converted += 1;
        }
    }
    assert!(converted >= 2, "{converted}");
    let got = bop_rows(dir.path(), &root, "test", "ours-softmax-icp_bop-test.csv");
    assert_eq!(got, want);
}

/// `eval --dataset root --split split --gt-mask` of the shipped default method; the rows of
/// its BOP results file `csv`, every field but the time.
fn bop_rows(dir: &Path, root: &Path, split: &str, csv: &str) -> Vec<Vec<String>> {
    let out = dir.join(format!(
        "out-{split}-{}",
        root.file_name().unwrap().to_string_lossy()
    ));
    let _ = std::fs::remove_dir_all(&out);
    check(
        &[
            "eval",
            "--dataset",
            s(root),
            "--split",
            split,
            "--gt-mask",
            "--seed",
            "2",
            "--out",
            s(&out),
            "-q",
        ],
        0,
        &[],
    );
    let text = std::fs::read_to_string(out.join(csv)).unwrap();
    text.lines()
        .map(|l| l.split(',').take(6).map(str::to_owned).collect())
        .collect()
}

// ---------------------------------------------------------------------------------------------
// The demo, end to end.

#[test]
fn demo_finds_the_pose_and_register_on_its_files_agrees() {
    // The README's seed: the rotation error the demo reports must be under 15°.
    let seed = "3";
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    // Three pose hypotheses: robust to the draw of points whatever masks the shipped
    // segmentation network gives (one hypothesis is the paper's one-shot pipeline).
    let args = vec![
        "demo",
        "--seed",
        seed,
        "--hypotheses",
        "3",
        "--out",
        s(&out),
        "--json",
    ];
    // The shipped segmentation network, not the ground-truth mask.
    assert!(
        incontext::models::SEG.available(),
        "models/{} is missing",
        incontext::models::SEG.file
    );
    let o = check(&args, 0, &["incontext demo", "\"seed\":3"]);
    let report = json_stdout(&o);
    // ADD-S, not the rotation error: procedural objects are often symmetric.
    let add_s = report["errors"]["add_s_over_diameter"].as_f64().unwrap();
    assert!(add_s < 0.1, "ADD-S {add_s} of the diameter\n{report:#}");
    for key in [
        "scene",
        "segmentation_network",
        "pose_network",
        "icp",
        "demo_total",
    ] {
        assert!(report["timings_ms"][key].as_f64().is_some(), "timing {key}");
    }
    for f in [
        "model.ply",
        "depth.png",
        "camera.json",
        "gt_pose.json",
        "pose.json",
        "overlay.png",
        "aligned.ply",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // `register` on the demo's own files gives the same pose.
    let args = vec![
        "register".to_string(),
        "--model".into(),
        s(&out.join("model.ply")).into(),
        "--depth".into(),
        s(&out.join("depth.png")).into(),
        "--camera".into(),
        s(&out.join("camera.json")).into(),
        "--seed".into(),
        seed.into(),
        "--json".into(),
        "--hypotheses".into(),
        "3".into(),
    ];
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = check(&args, 0, &[]);
    let a = pose_of(&report["pose"]);
    let b = pose_of(&json_stdout(&o)["pose"]);
    assert!(
        a.rotation_angle_to(&b).to_degrees() < 1e-3,
        "{a:?} vs {b:?}"
    );
    assert!(
        a.translation.distance(b.translation) < 1e-3,
        "{a:?} vs {b:?}"
    );
}

#[test]
fn the_demo_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str| {
        let out = dir.path().join(name);
        let o = check(
            &[
                "demo",
                "-q",
                "--seed",
                "4",
                "--gt-mask",
                "--json",
                "--out",
                s(&out),
            ],
            0,
            &[],
        );
        let v = json_stdout(&o);
        (v["pose"].clone(), v["errors"].clone())
    };
    assert_eq!(run("a"), run("b"));
}
