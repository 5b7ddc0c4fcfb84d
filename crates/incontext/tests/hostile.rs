//! Hostile and extreme inputs, one test per defect found by an adversarial sweep of the
//! binary: bounded memory (a child process under `RLIMIT_AS`), bounded time (a child killed
//! past a deadline), no output that replaces a device, a link, an input or another output,
//! honest exit codes and messages, and no temporary file left by an interrupted run.
//! Device nodes, FIFOs and links are made inside each test's temporary folder.

use std::io::Write;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use ic_geometry::Image;
use serde_json::json;

mod common;
use common::*;

/// The address-space limit of the bounded runs.
const TWO_GIB: u64 = 2 << 30;

/// Runs the binary with `RLIMIT_AS = mem` bytes, killed after `secs` seconds (a failure).
fn run_bounded(args: &[&str], envs: &[(&str, &str)], mem: u64, secs: u64) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_incontext"));
    cmd.args(args)
        .envs(envs.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    // SAFETY: setrlimit is async-signal-safe; the closure touches nothing else.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: mem as libc::rlim_t,
                rlim_max: mem as libc::rlim_t,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = cmd.spawn().expect("the binary starts");
    let start = Instant::now();
    loop {
        if child.try_wait().expect("wait").is_some() {
            return child.wait_with_output().expect("output");
        }
        if start.elapsed() > Duration::from_secs(secs) {
            let _ = child.kill();
            let o = child.wait_with_output().expect("output");
            panic!(
                "incontext {} did not finish within {secs} s\nstderr: {}",
                args.join(" "),
                stderr(&o)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// [`run_bounded`] under 2 GiB and 60 s, then the checks of `check`: exit code, stderr
/// needles, no panic.
#[track_caller]
fn check_bounded(args: &[&str], code: i32, needles: &[&str]) -> Output {
    assert_exit(run_bounded(args, &[], TWO_GIB, 60), args, code, needles)
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let mut body = kind.to_vec();
    body.extend_from_slice(data);
    out.extend_from_slice(&body);
    out.extend_from_slice(&crc32(&body).to_be_bytes());
}

/// A PNG whose header declares `width × height` 16-bit grey pixels, followed by `idat_bytes`
/// of compressed zeros (a decompression bomb when decoded in full).
fn bomb_png(path: &Path, width: u32, height: u32, idat_bytes: usize) {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[16, 0, 0, 0, 0]);
    png_chunk(&mut png, b"IHDR", &ihdr);
    // A stored zlib stream header, then runs of zero bytes compressed as one deflate block
    // would be; the decoder must never get this far.
    let mut idat = vec![0x78, 0x9c];
    idat.resize(idat_bytes, 0);
    png_chunk(&mut png, b"IDAT", &idat);
    png_chunk(&mut png, b"IEND", &[]);
    std::fs::write(path, png).unwrap();
}

/// The small scene's register arguments with the given replacements and extra flags.
fn reg(sc: &SmallScene, replace: &[(&str, &str)], extra: &[&str]) -> Vec<String> {
    let mut args: Vec<String> = vec!["register".into()];
    for (flag, name) in [
        ("--model", "model.ply"),
        ("--depth", "depth.png"),
        ("--camera", "camera.json"),
        ("--mask", "mask.png"),
    ] {
        let value = replace
            .iter()
            .find(|(f, _)| *f == flag)
            .map(|(_, v)| v.to_string())
            .unwrap_or_else(|| sc.p(name));
        if value.is_empty() {
            continue; // dropped
        }
        args.push(flag.into());
        args.push(value);
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

#[test]
fn a_normal_registration_fits_the_memory_limit_of_these_tests() {
    // The control of every bounded test below: the limit itself does not make them fail.
    let sc = SmallScene::new();
    check_bounded(&strs(&reg(&sc, &[], &["--threads", "2"])), 0, &[]);
}

#[test]
fn a_png_declaring_40000_squared_pixels_is_refused_before_decoding() {
    let sc = SmallScene::new();
    let bomb = sc.path("bomb.png");
    bomb_png(&bomb, 40_000, 40_000, 3 << 20);
    // No width/height in the camera: the depth map's header gives the size.
    let cam = sc.path("nosize.json");
    write(
        &cam,
        &json!({"cam_K": [131.25, 0, 79.5, 0, 131.25, 59.5, 0, 0, 1], "depth_scale": 0.1}),
    );
    let args = reg(
        &sc,
        &[("--depth", s(&bomb)), ("--camera", s(&cam)), ("--mask", "")],
        &[],
    );
    check_bounded(
        &strs(&args),
        2,
        &["bomb.png", "40000×40000", "largest supported"],
    );
    // With the camera's size given, the header is checked against it first.
    let args = reg(&sc, &[("--depth", s(&bomb))], &[]);
    check_bounded(&strs(&args), 2, &["bomb.png", "40000×40000"]);
}

#[test]
fn render_refuses_a_camera_of_50000_squared_pixels() {
    let sc = SmallScene::new();
    let cam = sc.path("huge.json");
    write(
        &cam,
        &json!({"cam_K": [40000, 0, 25000, 0, 40000, 25000, 0, 0, 1], "width": 50000, "height": 50000}),
    );
    let pose = sc.path("pose.json");
    write(
        &pose,
        &json!({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 300]}),
    );
    let out = sc.path("rendered");
    check_bounded(
        &[
            "render",
            "--model",
            &sc.p("model.ply"),
            "--camera",
            s(&cam),
            "--pose",
            s(&pose),
            "--out",
            s(&out),
        ],
        2,
        &["huge.json", "50000×50000", "largest supported"],
    );
    assert!(!out.exists(), "nothing is written");
}

#[test]
fn device_files_and_escaping_gltf_buffers_are_never_read() {
    let sc = SmallScene::new();
    let zero_cam = sc.path("camera_zero.json");
    std::os::unix::fs::symlink("/dev/zero", &zero_cam).unwrap();
    let args = reg(&sc, &[("--camera", s(&zero_cam))], &[]);
    check_bounded(&strs(&args), 2, &["camera_zero.json", "not a regular file"]);

    let random_obj = sc.path("random.obj");
    std::os::unix::fs::symlink("/dev/urandom", &random_obj).unwrap();
    let args = reg(&sc, &[("--model", s(&random_obj))], &[]);
    check_bounded(&strs(&args), 2, &["random.obj", "not a regular file"]);

    let fifo = sc.path("depth_fifo.png");
    let c = std::ffi::CString::new(s(&fifo)).unwrap();
    // SAFETY: a valid C string; mkfifo only creates the node.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let args = reg(&sc, &[("--depth", s(&fifo))], &[]);
    check_bounded(&strs(&args), 2, &["depth_fifo.png", "not a regular file"]);

    // A glTF whose buffer climbs out of the model's folder to /dev/zero.
    let dir = sc.path("gltf");
    std::fs::create_dir(&dir).unwrap();
    let gltf = dir.join("escape.gltf");
    std::fs::write(
        &gltf,
        json!({
            "asset": {"version": "2.0"},
            "buffers": [{"uri": "../../../../../../../../../../dev/zero", "byteLength": 36}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "nodes": [{"mesh": 0}],
            "scenes": [{"nodes": [0]}],
            "scene": 0
        })
        .to_string(),
    )
    .unwrap();
    let args = reg(&sc, &[("--model", s(&gltf))], &[]);
    check_bounded(&strs(&args), 2, &["escape.gltf", "outside"]);
}

#[test]
fn absurd_thread_counts_are_capped_or_refused() {
    let sc = SmallScene::new();
    let o = check_bounded(&strs(&reg(&sc, &[], &["--threads", "10000"])), 0, &[]);
    assert!(
        stderr(&o).contains("logical CPUs"),
        "the cap is announced: {}",
        stderr(&o)
    );
    let o = incontext(&strs(&reg(&sc, &[], &["--threads", "0"])));
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

#[test]
fn a_flag_refused_by_the_parser_still_gives_the_json_error_object() {
    let sc = SmallScene::new();
    // `--json` before or after the command; a bad value, a missing argument.
    for extra in [
        &["--rotations", "7"][..],
        &["--threads", "0"][..],
        &["--min-confidence", "x"][..],
    ] {
        let args = reg(&sc, &[], &[&["--json"], extra].concat());
        let o = incontext(&strs(&args));
        assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
        let v = json_stdout(&o);
        assert_eq!(v["kind"], "input", "{v}");
        assert_eq!(v["exit_code"], 2, "{v}");
        assert!(v["error"].as_str().unwrap().contains(extra[0]), "{v}");
        assert!(stderr(&o).contains("error:"), "{}", stderr(&o));
    }
    let o = incontext(&["--json", "register", "--model", "m.ply"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(
        json_stdout(&o)["error"]
            .as_str()
            .unwrap()
            .contains("--depth")
    );
    // Without --json stdout stays empty; --help is not an error.
    let o = incontext(&["register", "--rotations", "7"]);
    assert_eq!((o.status.code(), o.stdout.is_empty()), (Some(2), true));
    let o = incontext(&["--json", "--help"]);
    assert_eq!(o.status.code(), Some(0));
    assert!(String::from_utf8_lossy(&o.stdout).contains("Usage"));
}

#[test]
fn outputs_never_replace_links_fifos_or_device_nodes() {
    let sc = SmallScene::new();
    let target = sc.path("precious.json");
    std::fs::write(&target, b"precious").unwrap();
    let link = sc.path("link.json");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let fifo = sc.path("fifo.png");
    let c = std::ffi::CString::new(s(&fifo)).unwrap();
    // SAFETY: a valid C string; mkfifo only creates the node.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
    let mut special: Vec<(&str, PathBuf)> =
        vec![("--out", link.clone()), ("--overlay", fifo.clone())];
    // A character device like /dev/null, made in the test's folder (needs root, as CI runs).
    let null = sc.path("null.ply");
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } == 0 {
        let c = std::ffi::CString::new(s(&null)).unwrap();
        // SAFETY: a valid C string; mknod only creates the node (major 1, minor 3: null).
        let made = unsafe { libc::mknod(c.as_ptr(), libc::S_IFCHR | 0o666, libc::makedev(1, 3)) };
        assert_eq!(made, 0, "mknod as root");
        special.push(("--ply", null.clone()));
    }
    for (flag, path) in &special {
        let args = reg(&sc, &[], &[flag, s(path)]);
        check_bounded(
            &strs(&args),
            2,
            &[s(path), "refusing to write", "not a regular file"],
        );
    }
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    assert_eq!(std::fs::read(&target).unwrap(), b"precious");
    use std::os::unix::fs::FileTypeExt;
    assert!(
        std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo()
    );
    if special.len() == 3 {
        assert!(
            std::fs::symlink_metadata(&null)
                .unwrap()
                .file_type()
                .is_char_device()
        );
    }
}

#[test]
fn outputs_that_name_an_input_or_each_other_are_refused() {
    let sc = SmallScene::new();
    let before: Vec<(String, Vec<u8>)> = ["camera.json", "depth.png", "mask.png", "model.ply"]
        .iter()
        .map(|n| (n.to_string(), std::fs::read(sc.path(n)).unwrap()))
        .collect();
    std::fs::create_dir(sc.path("sub")).unwrap();
    let hard = sc.path("hard_link_of_mask.png");
    std::fs::hard_link(sc.path("mask.png"), &hard).unwrap();
    let dotted_camera = sc.path("sub").join("..").join(".").join("camera.json");
    let pose = sc.p("pose.json");
    for (extra, needle) in [
        (vec!["--out", &sc.p("camera.json")], "--camera input"),
        (vec!["--out", s(&dotted_camera)], "--camera input"),
        (vec!["--overlay", &sc.p("depth.png")], "--depth input"),
        (vec!["--overlay", &sc.p("mask.png")], "--mask input"),
        (vec!["--overlay", s(&hard)], "--mask input"),
        (vec!["--ply", &sc.p("model.ply")], "--model input"),
        (vec!["--out", &pose, "--ply", &pose], "name the same file"),
    ] {
        let args = reg(&sc, &[], &extra);
        check_bounded(&strs(&args), 2, &[needle]);
    }
    for (name, bytes) in &before {
        assert_eq!(
            &std::fs::read(sc.path(name)).unwrap(),
            bytes,
            "{name} intact"
        );
    }
    assert!(!sc.path("pose.json").exists());
}

#[test]
fn a_pose_of_the_wrong_mesh_is_not_reported_as_found() {
    // The demo scene (a procedural object in the room, found by the segmentation network) and
    // a cube of the object's bounding box in place of its mesh: whatever pose comes out
    // explains only part of the object, and the exit code must say so.
    let dir = tempfile::tempdir().unwrap();
    let demo = dir.path().join("demo");
    check_bounded(&["demo", "--seed", "1", "--out", s(&demo)], 0, &[]);
    let model = ic_geometry::io::load_mesh(demo.join("model.ply")).unwrap();
    let lo = model
        .vertices
        .iter()
        .fold(ic_geometry::glam::Vec3::INFINITY, |a, v| a.min(*v));
    let hi = model
        .vertices
        .iter()
        .fold(ic_geometry::glam::Vec3::NEG_INFINITY, |a, v| a.max(*v));
    let half = (hi - lo).max_element() / 2.0;
    let centre = (lo + hi) / 2.0;
    let mut cube = ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::splat(half)).unwrap();
    for v in &mut cube.vertices {
        *v += centre;
    }
    let path = dir.path().join("cube.ply");
    ic_geometry::io::write_mesh_ply(&path, &cube, ic_geometry::io::PlyEncoding::Ascii).unwrap();
    let out = dir.path().join("cube_pose.json");
    let register = |model: &Path, out: &Path| {
        run_bounded(
            &[
                "register",
                "--model",
                s(model),
                "--depth",
                s(&demo.join("depth.png")),
                "--camera",
                s(&demo.join("camera.json")),
                "--out",
                s(out),
            ],
            &[],
            TWO_GIB,
            60,
        )
    };
    let o = register(&path, &out);
    let code = o.status.code();
    assert!(
        matches!(code, Some(3) | Some(4)),
        "the wrong mesh gives exit {code:?}: {}",
        stderr(&o)
    );
    if code == Some(4) {
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
        assert_eq!(report["verdict"], "uncertain");
        assert!(stderr(&o).contains("uncertain"));
    } else {
        assert!(!out.exists(), "nothing is written for an object not found");
    }
    // The right mesh on the same scene: verdict ok, exit 0.
    let good = dir.path().join("good.json");
    let o = register(&demo.join("model.ply"), &good);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&good).unwrap()).unwrap();
    assert_eq!(report["verdict"], "ok");
}

#[test]
fn a_depth_column_without_the_object_is_not_found() {
    let sc = SmallScene::new();
    // One column of the depth map, with intrinsics for it.
    let full = ic_render::io::read_depth_png(sc.path("depth.png"), 0.1, None).unwrap();
    let column: Vec<f32> = (0..120).map(|v| full.data[v * 160 + 80]).collect();
    let depth = sc.path("column.png");
    ic_render::io::write_depth_png(&depth, &Image::from_vec(1, 120, column).unwrap(), 0.1).unwrap();
    let cam = sc.path("column.json");
    write(
        &cam,
        &json!({"cam_K": [131.25, 0, 0, 0, 131.25, 59.5, 0, 0, 1], "depth_scale": 0.1, "width": 1, "height": 120}),
    );
    let args = reg(
        &sc,
        &[
            ("--depth", s(&depth)),
            ("--camera", s(&cam)),
            ("--mask", ""),
        ],
        &[],
    );
    check_bounded(&strs(&args), 3, &["not found"]);
}

#[test]
fn an_exr_of_3e38_metres_names_the_file_and_the_range() {
    let sc = SmallScene::new();
    let exr = sc.path("far.exr");
    ic_render::io::write_depth_exr(&exr, &Image::filled(160, 120, 3e38)).unwrap();
    let args = reg(&sc, &[("--depth", s(&exr))], &[]);
    check_bounded(&strs(&args), 2, &["far.exr", "beyond", "3e38"]);
}

#[test]
fn object_not_found_messages_carry_no_debug_text() {
    let sc = SmallScene::new();
    let flat = sc.path("flat.png");
    ic_render::io::write_depth_png(&flat, &Image::filled(160, 120, 1.0), 0.1).unwrap();
    let args = reg(&sc, &[("--depth", s(&flat)), ("--mask", "")], &[]);
    let o = check_bounded(&strs(&args), 3, &["not found"]);
    let err = stderr(&o);
    assert!(
        !err.contains("Some(") && !err.contains("None"),
        "debug text in: {err}"
    );
}

#[test]
fn eval_with_limit_zero_writes_an_empty_results_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("cases/case_00000")).unwrap();
    let out = dir.path().join("r.jsonl");
    let o = check_bounded(
        &[
            "eval",
            "--cases",
            s(&dir.path().join("cases")),
            "--limit",
            "0",
            "--out",
            s(&out),
        ],
        0,
        &[],
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("r.jsonl"));
    assert_eq!(std::fs::read(&out).unwrap(), b"", "an empty results file");
}

#[test]
fn implausible_intrinsics_are_bad_input() {
    let sc = SmallScene::new();
    for (name, camera, needle) in [
        (
            "skew.json",
            json!({"cam_K": [131.25, 3, 79.5, 0, 131.25, 59.5, 0, 0, 1], "width": 160, "height": 120, "depth_scale": 0.1}),
            "skew",
        ),
        (
            "bottom.json",
            json!({"cam_K": [131.25, 0, 79.5, 0, 131.25, 59.5, 0.1, 0, 1], "width": 160, "height": 120, "depth_scale": 0.1}),
            "bottom row",
        ),
        (
            "far_centre.json",
            json!({"cam_K": [131.25, 0, 5000, 0, 131.25, -3000, 0, 0, 1], "width": 160, "height": 120, "depth_scale": 0.1}),
            "principal point",
        ),
        (
            "tiny_focal.json",
            json!({"cam_K": [1e-30, 0, 79.5, 0, 1e-30, 59.5, 0, 0, 1], "width": 160, "height": 120, "depth_scale": 0.1}),
            "field of view",
        ),
        (
            // Intrinsics of a camera twice the size, and no size: the principal point gives it
            // away.
            "other_size.json",
            json!({"cam_K": [262.5, 0, 159.5, 0, 262.5, 119.5, 0, 0, 1], "depth_scale": 0.1}),
            "another image size",
        ),
    ] {
        let cam = sc.path(name);
        write(&cam, &camera);
        let args = reg(&sc, &[("--camera", s(&cam)), ("--mask", "")], &[]);
        check_bounded(&strs(&args), 2, &[name, needle]);
    }
}

#[test]
fn a_polygon_of_100000_vertices_is_sampled_in_seconds() {
    let sc = SmallScene::new();
    let n = 100_000;
    let path = sc.path("fan.obj");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    for i in 0..n {
        let a = i as f64 / n as f64 * std::f64::consts::TAU;
        writeln!(f, "v {} {} 0", 50.0 * a.cos(), 50.0 * a.sin()).unwrap();
    }
    write!(f, "f").unwrap();
    for i in 1..=n {
        write!(f, " {i}").unwrap();
    }
    writeln!(f).unwrap();
    drop(f);
    let args = reg(&sc, &[("--model", s(&path))], &["--json"]);
    let start = Instant::now();
    let o = run_bounded(&strs(&args), &[], TWO_GIB, 60);
    assert!(
        matches!(o.status.code(), Some(0) | Some(3) | Some(4)),
        "{:?}: {}",
        o.status.code(),
        stderr(&o)
    );
    let v = json_stdout(&o);
    if let Some(ms) = v["timings_ms"]["model_points"].as_f64() {
        assert!(ms < 10_000.0, "model points took {ms} ms");
    }
    assert!(
        start.elapsed() < Duration::from_secs(30),
        "{:?}",
        start.elapsed()
    );
}

#[test]
fn an_interrupted_run_leaves_no_temporary_file_and_no_output_without_its_pose() {
    use std::os::unix::process::ExitStatusExt;
    let sc = SmallScene::new();
    let out_dir = sc.path("out");
    std::fs::create_dir(&out_dir).unwrap();
    let (pose, overlay, ply) = (
        out_dir.join("pose.json"),
        out_dir.join("overlay.png"),
        out_dir.join("aligned.ply"),
    );
    let args = reg(
        &sc,
        &[],
        &[
            "--out",
            s(&pose),
            "--overlay",
            s(&overlay),
            "--ply",
            s(&ply),
        ],
    );
    let temporaries = |dir: &Path| -> Vec<String> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".tmp"))
            .collect()
    };
    // Each write sleeps 5 s between its temporary file and the rename (fault injection), so
    // the signal lands while a temporary file exists. The run's own temporary folder must be
    // left empty too (the shipped networks are copied there from the binary).
    let tmp_dir = sc.path("tmp");
    std::fs::create_dir(&tmp_dir).unwrap();
    for signal in [libc::SIGTERM, libc::SIGINT] {
        for p in [&pose, &overlay, &ply] {
            let _ = std::fs::remove_file(p);
        }
        let mut child = Command::new(env!("CARGO_BIN_EXE_incontext"))
            .args(strs(&args))
            .env("INCONTEXT_TEST_WRITE_DELAY_MS", "5000")
            .env("TMPDIR", &tmp_dir)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let start = Instant::now();
        while temporaries(&out_dir).is_empty() {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "no temporary file appeared"
            );
            assert!(child.try_wait().unwrap().is_none(), "the run ended early");
            std::thread::sleep(Duration::from_millis(10));
        }
        // SAFETY: kill with a valid pid of our own child.
        assert_eq!(unsafe { libc::kill(child.id() as i32, signal) }, 0);
        let o = child.wait_with_output().unwrap();
        assert_eq!(
            o.status.code(),
            Some(130),
            "signal {signal}: {:?} {:?} {}",
            o.status.code(),
            o.status.signal(),
            stderr(&o)
        );
        assert_eq!(temporaries(&out_dir), Vec::<String>::new());
        let left: Vec<_> = std::fs::read_dir(&tmp_dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert!(left.is_empty(), "signal {signal}: left in TMPDIR: {left:?}");
        if overlay.exists() || ply.exists() {
            assert!(pose.exists(), "an output without pose.json");
        }
    }
}
