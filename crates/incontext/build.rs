//! Embeds the shipped models that exist at build time.
//!
//! For each file of `../../models` listed below, emits `cargo:rustc-cfg=<flag>` when it exists,
//! so `src/models.rs` can `include_bytes!` it; a model that does not exist yet is looked up at
//! run time under the workspace's `models/` folder instead (with a clear error when missing).
//! Cargo re-runs this script whenever the `models/` folder changes, so a model that lands later
//! is embedded by the next build.

use std::path::Path;

const MODELS: [(&str, &str); 5] = [
    ("pose-cpu-softmax.safetensors", "ic_embed_pose_softmax"),
    (
        "pose-cpu-softmax-scratch.safetensors",
        "ic_embed_pose_softmax_second",
    ),
    ("pose-cpu-ot.safetensors", "ic_embed_pose_ot"),
    ("seg-clutter.safetensors", "ic_embed_seg"),
    ("seg-cpu.safetensors", "ic_embed_seg_one_object"),
];

fn main() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models");
    println!("cargo:rerun-if-changed={}", dir.display());
    println!("cargo:rerun-if-env-changed=INCONTEXT_NO_EMBED");
    let off = std::env::var_os("INCONTEXT_NO_EMBED").is_some();
    let flags: Vec<&str> = MODELS.iter().map(|m| m.1).collect();
    println!("cargo:rustc-check-cfg=cfg({})", flags.join(", "));
    for (file, flag) in MODELS {
        let path = dir.join(file);
        if !off && path.is_file() {
            println!("cargo:rerun-if-changed={}", path.display());
            println!("cargo:rustc-cfg={flag}");
        }
    }
}
