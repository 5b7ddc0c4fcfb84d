//! Runs the `incontext` binary as a user would.

use std::process::Command;

fn incontext(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_incontext"))
        .args(args)
        .output()
        .expect("the binary runs")
}

#[test]
fn demo_recovers_the_pose_and_writes_its_files() {
    let out = tempfile::tempdir().unwrap();
    let dir = out.path().join("demo");
    let o = incontext(&["demo", "--seed", "1", "--out", dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["seed"], 1);
    let rot = report["rotation_error_deg"].as_f64().unwrap();
    let init = report["initial_rotation_error_deg"].as_f64().unwrap();
    assert!(
        (init - 10.0).abs() < 1e-6,
        "the stand-in estimate starts 10° off"
    );
    assert!(rot < 1.0, "ICP should refine 10° to under 1°, got {rot}°");
    assert!(dir.join("aligned.ply").is_file() && dir.join("depth.png").is_file());
    // The run prints its config.
    assert!(String::from_utf8_lossy(&o.stderr).contains("\"seed\":1"));
}

#[test]
fn demo_is_deterministic() {
    let a = incontext(&["demo", "-q", "--seed", "4"]);
    let b = incontext(&["demo", "-q", "--seed", "4"]);
    let strip = |o: &std::process::Output| {
        let mut v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        v.as_object_mut().unwrap().remove("timings_ms");
        v
    };
    assert_eq!(strip(&a), strip(&b));
}

#[test]
fn bad_flags_exit_with_2_and_a_message() {
    let o = incontext(&["demo", "--init-rotation-deg", "NaN"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("must be finite"));
    let o = incontext(&["demo", "--seed", "minus-one"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--seed"));
}
