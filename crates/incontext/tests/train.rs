//! `incontext train` as a user runs it: a couple of iterations on two of their own meshes
//! write weights that `register --pose-model` / `--seg-model` loads; bad `--objects` / `--from`
//! exit 2 naming the file.

use std::path::Path;

use ic_geometry::io::{PlyEncoding, write_mesh_ply};

mod common;
use common::*;

/// Two meshes with non-numeric names, as a user's folder has them.
fn objects(dir: &Path) -> String {
    let objects = dir.join("my-meshes");
    std::fs::create_dir_all(&objects).unwrap();
    for (name, seed) in [("bracket.ply", 3), ("housing.ply", 4)] {
        let mesh = ic_geometry::shapes::random_object(seed);
        write_mesh_ply(objects.join(name), &mesh, PlyEncoding::BinaryLittleEndian).unwrap();
    }
    s(&objects).to_string()
}

/// Small samples and few validation views: seconds, not minutes.
const FAST: [&str; 12] = [
    "--iterations",
    "2",
    "--batch-size",
    "2",
    "--validate-every",
    "1",
    "--validation-count",
    "2",
    "--threads",
    "2",
    "--seed",
    "1",
];

#[test]
fn train_pose_writes_weights_that_register_loads() {
    let dir = tempfile::tempdir().unwrap();
    let objects = objects(dir.path());
    let out = dir.path().join("my-pose");
    let mut args = vec![
        "train",
        "pose",
        "--objects",
        &objects,
        "--out",
        s(&out),
        "--model-points",
        "64",
        "--observed-points",
        "48",
        "--json",
    ];
    args.extend(FAST);
    let o = check(&args, 0, &[]);
    let report = json_stdout(&o);
    assert_eq!(report["command"], "train");
    assert_eq!(report["ending"], "finished");
    assert_eq!(report["iteration"], 2);
    let weights = out.join("final.safetensors");
    assert_eq!(report["weights"], s(&weights));
    let text = std::fs::read_to_string(out.join("train.csv")).unwrap();
    assert_eq!(text.lines().count(), 3, "{text}");
    // register loads it (whatever it makes of this scene after two tiny steps: found, not
    // found or uncertain, never a bad-input or internal error).
    let sc = SmallScene::new();
    let reg = register_args(&sc, "--pose-model", s(&weights));
    let reg: Vec<&str> = reg.iter().map(String::as_str).collect();
    let r = incontext(&reg);
    assert!(
        matches!(r.status.code(), Some(0 | 3 | 4)),
        "register --pose-model {}: {:?}\n{}",
        weights.display(),
        r.status.code(),
        stderr(&r)
    );
    // The same folder again without --resume is refused; with it, nothing is left to do.
    let mut again = args.clone();
    again.retain(|a| *a != "--json");
    check(&again, 2, &["--resume"]);
    again.push("--resume");
    check(&again, 0, &[]);
}

#[test]
fn train_seg_writes_weights_that_register_loads() {
    let dir = tempfile::tempdir().unwrap();
    let objects = objects(dir.path());
    let out = dir.path().join("my-seg");
    let mut args = vec!["train", "seg", "--objects", &objects, "--out", s(&out)];
    args.extend(FAST);
    check(&args, 0, &[]);
    let weights = out.join("final.safetensors");
    let sc = SmallScene::new();
    // Without a mask, register runs the segmentation network it is given.
    let mut reg: Vec<String> = register_args(&sc, "--seg-model", s(&weights));
    let mask = reg.iter().position(|a| a == "--mask").unwrap();
    reg.drain(mask..mask + 2);
    let reg: Vec<&str> = reg.iter().map(String::as_str).collect();
    let r = incontext(&reg);
    assert!(
        matches!(r.status.code(), Some(0 | 3 | 4)),
        "register --seg-model: {:?}\n{}",
        r.status.code(),
        stderr(&r)
    );
}

#[test]
fn bad_objects_or_from_exit_2_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let missing = dir.path().join("no-such-folder");
    check(
        &["train", "pose", "--objects", s(&missing), "--out", s(&out)],
        2,
        &["no-such-folder"],
    );
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    check(
        &["train", "seg", "--objects", s(&empty), "--out", s(&out)],
        2,
        &["empty"],
    );
    let objects = objects(dir.path());
    let from = dir.path().join("missing.safetensors");
    check(
        &[
            "train",
            "pose",
            "--objects",
            &objects,
            "--out",
            s(&out),
            "--from",
            s(&from),
        ],
        2,
        &["missing.safetensors"],
    );
    // A mesh is not a checkpoint.
    let mesh = Path::new(&objects).join("bracket.ply");
    check(
        &[
            "train",
            "seg",
            "--objects",
            &objects,
            "--out",
            s(&out),
            "--from",
            s(&mesh),
        ],
        2,
        &["bracket.ply", "not a segmentation checkpoint"],
    );
}

#[test]
fn a_batch_beyond_the_machines_memory_or_a_bad_learning_rate_is_refused_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let objects = objects(dir.path());
    let out = dir.path().join("out");
    let refused = |extra: &[&str], needles: &[&str]| {
        let mut args = vec!["train", extra[0], "--objects", &objects, "--out", s(&out)];
        args.extend_from_slice(&extra[1..]);
        check(&args, 2, needles);
    };
    // A pose batch of 100 000 pairs holds terabytes of activations; so does one pair of 10⁸
    // model points; a segmentation batch of 100 000 scenes too. Each is refused at once.
    refused(
        &["pose", "--batch-size", "100000"],
        &["100000 pose pairs", "GiB", "--batch-size"],
    );
    refused(
        &["pose", "--model-points", "100000000"],
        &["not even one fits", "point counts"],
    );
    refused(
        &["seg", "--batch-size", "100000"],
        &["100000 segmentation samples", "GiB"],
    );
    refused(
        &["pose", "--learning-rate", "nan"],
        &["--learning-rate must be a positive number"],
    );
    refused(&["seg", "--lr-floor", "inf"], &["--lr-floor"]);
    // Nothing was trained or written.
    assert!(!out.join("latest.safetensors").exists());
}
