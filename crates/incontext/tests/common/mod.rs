//! Helpers shared by the CLI test binaries: run the binary, check its exit code and message,
//! and a small scene written as a user would have it.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;

use ic_geometry::glam::DVec3;
use ic_geometry::io::{PlyEncoding, write_mesh_ply};
use ic_geometry::{Image, Intrinsics, Mesh, Pose, look_at};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use serde_json::{Value, json};

pub fn incontext(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_incontext"))
        .args(args)
        .output()
        .expect("the binary runs")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Runs the binary and checks the exit code and that stderr contains every `needles`;
/// returns the output.
#[track_caller]
pub fn check(args: &[&str], code: i32, needles: &[&str]) -> Output {
    assert_exit(incontext(args), args, code, needles)
}

/// Checks a finished run of `incontext args`: its exit code, that stderr contains every
/// `needles`, and no panic; returns the output.
#[track_caller]
pub fn assert_exit(o: Output, args: &[&str], code: i32, needles: &[&str]) -> Output {
    let err = stderr(&o);
    assert_eq!(
        o.status.code(),
        Some(code),
        "incontext {}\nstdout: {}\nstderr: {err}",
        args.join(" "),
        String::from_utf8_lossy(&o.stdout)
    );
    for n in needles {
        assert!(
            err.contains(n),
            "incontext {}: stderr lacks {n:?}:\n{err}",
            args.join(" ")
        );
    }
    assert!(!err.contains("panicked"), "a panic: {err}");
    o
}

pub fn json_stdout(o: &Output) -> Value {
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not one JSON object ({e}):\n{}",
            String::from_utf8_lossy(&o.stdout)
        )
    })
}

pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A small scene written as a user would have it: a procedural object in mm (model.ply), seen
/// alone by a 160×120 camera from 280 mm (depth.png, 16-bit mm), camera.json, the object mask
/// (mask.png) and the true pose in mm.
pub struct SmallScene {
    pub dir: tempfile::TempDir,
    pub truth: Pose,
}

impl SmallScene {
    pub fn new() -> SmallScene {
        let dir = tempfile::tempdir().unwrap();
        let mut mesh = ic_geometry::shapes::random_object(3);
        mesh.normalise().unwrap();
        let mesh = Mesh {
            vertices: mesh.vertices.iter().map(|v| *v * 100.0).collect(),
            triangles: mesh.triangles,
        };
        write_mesh_ply(
            dir.path().join("model.ply"),
            &mesh,
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
        let k = Intrinsics::new(131.25, 131.25, 79.5, 59.5, 160, 120).unwrap();
        let eye = DVec3::new(180.0, 120.0, 180.0);
        let truth = look_at(eye, DVec3::ZERO, DVec3::Z).unwrap();
        let scene = Scene::single(Arc::new(mesh), Pose::IDENTITY, 1);
        let view = CpuRenderer::new()
            .render(&scene, &Camera::new(k, truth))
            .unwrap();
        let metres = Image {
            width: 160,
            height: 120,
            data: view.depth.data.iter().map(|z| z / 1000.0).collect(),
        };
        ic_render::io::write_depth_png(dir.path().join("depth.png"), &metres, 0.1).unwrap();
        ic_render::io::write_depth_exr(dir.path().join("depth.exr"), &metres).unwrap();
        ic_render::io::write_mask_png(dir.path().join("mask.png"), &view.mask(1)).unwrap();
        write(
            &dir.path().join("camera.json"),
            &json!({"cam_K": k.k_row_major(), "depth_scale": 0.1, "width": 160, "height": 120}),
        );
        SmallScene { dir, truth }
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    pub fn p(&self, name: &str) -> String {
        s(&self.path(name)).to_string()
    }
}

pub fn write(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).unwrap()).unwrap();
}

/// A pose in its serde form, `{"R": rows, "t": [..]}` (extra keys ignored).
pub fn pose_of(v: &Value) -> Pose {
    serde_json::from_value(v.clone()).unwrap()
}

pub fn register_args(sc: &SmallScene, flag: &str, value: &str) -> Vec<String> {
    let mut args: Vec<String> = vec!["register".into()];
    for (f, v) in [
        ("--model", sc.p("model.ply")),
        ("--depth", sc.p("depth.png")),
        ("--camera", sc.p("camera.json")),
        ("--mask", sc.p("mask.png")),
    ] {
        args.push(f.into());
        args.push(if f == flag { value.into() } else { v });
    }
    if !["--model", "--depth", "--camera", "--mask"].contains(&flag) {
        args.push(flag.into());
        args.push(value.into());
    }
    args
}

#[track_caller]
pub fn check_register(sc: &SmallScene, flag: &str, value: &str, code: i32, needles: &[&str]) {
    let args = register_args(sc, flag, value);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    check(&args, code, needles);
}

/// ADD-S between two poses of the mesh at `model` (mean distance from each vertex under `a`
/// to the nearest vertex under `b`), and the mesh's diameter, in the mesh's units. Poses
/// equivalent under the object's symmetry give ≈ 0.
pub fn add_s(model: &Path, a: &Pose, b: &Pose) -> (f32, f32) {
    let mesh = ic_geometry::io::load_mesh(model).unwrap();
    let pa: Vec<_> = mesh.vertices.iter().map(|v| a.apply_f32(*v)).collect();
    let pb: Vec<_> = mesh.vertices.iter().map(|v| b.apply_f32(*v)).collect();
    let add_s = pa
        .iter()
        .map(|p| pb.iter().map(|q| q.distance(*p)).fold(f32::MAX, f32::min))
        .sum::<f32>()
        / pa.len() as f32;
    let diameter = mesh
        .vertices
        .iter()
        .flat_map(|x| mesh.vertices.iter().map(move |y| x.distance(*y)))
        .fold(0.0f32, f32::max);
    (add_s, diameter)
}

/// Replaces a 16-bit depth PNG stored at `depth_scale` (`stored × depth_scale = mm`) by a
/// 16-bit TIFF of the same stored values beside it (as BOP's ITODD ships depth).
pub fn depth_png_to_tiff(png: &Path, depth_scale: f64) {
    let m = ic_render::io::read_depth_png(png, depth_scale, None).unwrap();
    let stored: Vec<u16> = m
        .data
        .iter()
        .map(|&z| (z as f64 * 1000.0 / depth_scale).round() as u16)
        .collect();
    tiff::encoder::TiffEncoder::new(std::fs::File::create(png.with_extension("tif")).unwrap())
        .unwrap()
        .write_image::<tiff::encoder::colortype::Gray16>(m.width, m.height, &stored)
        .unwrap();
    std::fs::remove_file(png).unwrap();
}
