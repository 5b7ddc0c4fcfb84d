//! `register --rotations`: rotation hypotheses verified by render-and-compare, end to end.

use serde_json::Value;

mod common;
use common::*;

/// A file of the workspace (e.g. a shipped model).
fn workspace_path(relative: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(relative)
}

fn register_json(sc: &SmallScene, extra: &[&str]) -> (Option<i32>, Value, String) {
    let mut args = vec![
        "register".to_string(),
        "--model".into(),
        sc.p("model.ply"),
        "--depth".into(),
        sc.p("depth.png"),
        "--camera".into(),
        sc.p("camera.json"),
        "--json".into(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = incontext(&args);
    let v: Value = serde_json::from_slice(&o.stdout).unwrap_or(Value::Null);
    (o.status.code(), v, stderr(&o))
}

#[test]
fn rotation_hypotheses_find_the_pose_verify_it_and_repeat_exactly() {
    let sc = SmallScene::new();
    let (code, a, err) = register_json(&sc, &["--rotations", "24", "--mask", &sc.p("mask.png")]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(a["verdict"], "ok");
    // For each of the two shipped pose networks: 24 rotated copies' weighted-Procrustes
    // poses and up to 2 sampled poses each, then two further passes of the network over its
    // 8 verified ones (8 more each).
    let made = a["details"]["hypotheses_made"].as_u64().unwrap();
    assert!((2 * (24 + 16)..=2 * (72 + 16)).contains(&made), "{made}");
    let checked = a["details"]["hypotheses_verified"].as_u64().unwrap();
    assert_eq!(checked, 2 * (8 + 16), "{a:#}");
    let v = &a["details"]["verification"];
    assert!(v["score"].as_f64().unwrap() > 0.8, "{v}");
    // The model rendered at the pose over the whole image explains the depth map.
    let w = &a["details"]["whole_view"];
    assert!(
        w["agreement"].as_f64().unwrap() >= 0.8 && w["in_front"].as_f64().unwrap() < 0.05,
        "{w}"
    );
    // The confidence is the calibrated probability of being right: `ok` needs at least 0.9.
    let confidence = a["confidence"].as_f64().unwrap();
    assert!((0.9..=1.0).contains(&confidence), "{confidence}");
    // ADD-S against the truth (the object may be symmetric: the rotation error need not be
    // small), in mm, against a 0.1·diameter bound.
    let est = pose_of(&a["pose"]);
    let (error, diameter) = add_s(&sc.path("model.ply"), &est, &sc.truth);
    assert!(
        error < 0.1 * diameter,
        "ADD-S {error} mm, diameter {diameter} mm"
    );
    // Seeded: the same numbers again, and with another thread count.
    let (_, b, _) = register_json(
        &sc,
        &[
            "--rotations",
            "24",
            "--mask",
            &sc.p("mask.png"),
            "--threads",
            "1",
        ],
    );
    assert_eq!(a["pose"], b["pose"]);
    assert_eq!(a["details"]["verification"], b["details"]["verification"]);
    assert_eq!(a["details"]["whole_view"], b["details"]["whole_view"]);
    // The hypotheses are refined and scored in parallel: the rival (the best score of the
    // verified poses unlike the winner) and the confidence built on it repeat too.
    assert!(a["details"]["rival_score"].is_f64(), "{a:#}");
    assert_eq!(a["details"]["rival_score"], b["details"]["rival_score"]);
    assert_eq!(a["confidence"], b["confidence"]);
}

#[test]
fn rotation_hypotheses_without_the_object_find_nothing() {
    let sc = SmallScene::new();
    let flat = sc.path("flat.png");
    ic_render::io::write_depth_png(&flat, &ic_geometry::Image::filled(160, 120, 1.0), 0.1).unwrap();
    let o = incontext(&[
        "register",
        "--model",
        &sc.p("model.ply"),
        "--depth",
        s(&flat),
        "--camera",
        &sc.p("camera.json"),
        "--rotations",
        "24",
    ]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
}

#[test]
fn a_rotation_count_that_is_no_group_is_bad_input() {
    let sc = SmallScene::new();
    let (code, _, err) = register_json(&sc, &["--rotations", "7"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("1, 12, 24 or 60"), "{err}");
}

#[test]
fn the_main_pose_network_alone_verifies_half_the_hypotheses_and_still_finds_the_pose() {
    let sc = SmallScene::new();
    let (code, a, err) = register_json(&sc, &["--mask", &sc.p("mask.png"), "--no-second-pose"]);
    assert_eq!(code, Some(0), "{err}");
    let made = a["details"]["hypotheses_made"].as_u64().unwrap();
    assert!((24 + 16..=72 + 16).contains(&made), "{made}");
    assert_eq!(a["details"]["hypotheses_verified"].as_u64(), Some(8 + 16));
    let (error, diameter) = add_s(&sc.path("model.ply"), &pose_of(&a["pose"]), &sc.truth);
    assert!(
        error < 0.1 * diameter,
        "ADD-S {error} mm, diameter {diameter} mm"
    );
    // A checkpoint given as the second network joins the main one; a flag pair that
    // contradicts itself is a usage error.
    let second = workspace_path("models/pose-cpu-softmax-scratch.safetensors");
    let (code, b, err) = register_json(
        &sc,
        &[
            "--mask",
            &sc.p("mask.png"),
            "--second-pose-model",
            s(&second),
        ],
    );
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(
        b["details"]["hypotheses_verified"].as_u64(),
        Some(2 * (8 + 16))
    );
    let (code, _, err) = register_json(
        &sc,
        &["--no-second-pose", "--second-pose-model", s(&second)],
    );
    assert_eq!(code, Some(2), "{err}");
}

#[test]
fn a_second_pose_network_of_another_head_is_bad_input_naming_the_file() {
    let sc = SmallScene::new();
    let ot = workspace_path("models/pose-cpu-ot.safetensors");
    let (code, _, err) = register_json(
        &sc,
        &["--mask", &sc.p("mask.png"), "--second-pose-model", s(&ot)],
    );
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("pose-cpu-ot.safetensors") && err.contains("ot head"),
        "{err}"
    );
}
