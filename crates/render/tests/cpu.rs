//! CPU reference renderer, scenes, sensor and I/O.

mod common;

use std::sync::Arc;

use common::*;
use ic_geometry::{Image, Intrinsics, Pose, glam::DVec3};
use ic_render::*;

#[test]
fn cpu_sphere_matches_analytic_ray_sphere_intersection() {
    let r = 0.8;
    let mesh = ic_geometry::shapes::icosphere(r as f32, 5).expect("valid sphere");
    let tol = faceting_error(&mesh, r);
    assert!(tol < 1e-3, "faceting error {tol}");
    let centre = DVec3::new(0.1, -0.05, 3.0);
    let scene = Scene::single(Arc::new(mesh), Pose::from_translation(centre), 7);
    let k = Intrinsics::new(300.0, 300.0, 159.5, 119.5, 320, 240).unwrap();
    let view = CpuRenderer::new()
        .render(&scene, &Camera::new(k, Pose::IDENTITY))
        .unwrap();
    let (mut hits, mut worst) = (0, 0.0f64);
    for v in 0..k.height {
        for u in 0..k.width {
            let i = (v * k.width + u) as usize;
            let (z, id, cos) = (
                view.depth.data[i] as f64,
                view.instances.data[i],
                view.incidence.data[i] as f64,
            );
            match ray_sphere_z(&k, u, v, centre, r) {
                // Away from the rim: the facet lies at most `tol` inside the sphere, i.e. at
                // most tol / cos further along the ray.
                Some(want) if cos > 0.2 => {
                    assert_eq!(id, 7);
                    let err = z - want;
                    assert!(
                        err >= -1e-6 && err <= tol / cos + 1e-6,
                        "({u}, {v}): {z} vs {want}"
                    );
                    worst = worst.max(err.abs());
                    hits += 1;
                }
                Some(_) => {}
                None => {
                    // A miss of the true sphere is a miss of the inscribed mesh.
                    assert_eq!((z, id), (0.0, 0), "({u}, {v})");
                }
            }
        }
    }
    assert!(hits > 10_000, "{hits}");
    eprintln!(
        "cpu sphere: {hits} pixels, max |z − analytic| = {worst:.2e} (faceting bound {tol:.2e})"
    );
}

#[test]
fn cpu_box_head_on_gives_exact_plane_distance_and_top_left_fill() {
    // A 2×1×0.5 box, front face at z = 2.5, seen head-on. With f = 100 at z = 2.5 a unit is
    // 40 px, so the face spans u ∈ [cx − 40, cx + 40] exactly, through pixel centres.
    let mesh = ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::new(1.0, 0.5, 0.25))
        .expect("valid box");
    let scene = Scene::single(Arc::new(mesh), Pose::IDENTITY, 1);
    let k = Intrinsics::new(100.0, 100.0, 60.0, 40.0, 120, 80).unwrap();
    let view = CpuRenderer::new()
        .render(&scene, &camera_at(k, 2.75))
        .unwrap();
    let mut covered = (u32::MAX, 0, u32::MAX, 0);
    for v in 0..80 {
        for u in 0..120 {
            let i = (v * 120 + u) as usize;
            if view.instances.data[i] == 1 {
                assert_eq!(view.depth.data[i], 2.5, "({u}, {v})");
                // Normal (0, 0, −1) against the ray ((u − cx)/fx, (v − cy)/fy, 1): cos = 1/|r|.
                let ray = DVec3::new((u as f64 - 60.0) / 100.0, (v as f64 - 40.0) / 100.0, 1.0);
                assert!((view.incidence.data[i] as f64 - 1.0 / ray.length()).abs() < 1e-6);
                covered = (
                    covered.0.min(u),
                    covered.1.max(u),
                    covered.2.min(v),
                    covered.3.max(v),
                );
            } else {
                assert_eq!(view.depth.data[i], 0.0);
            }
        }
    }
    // Left and top edges are in, right and bottom edges out: u ∈ [20, 100), v ∈ [20, 60).
    assert_eq!(covered, (20, 99, 20, 59));
    let centre = (40 * 120 + 60) as usize;
    let cos = view.incidence.data[centre];
    assert!((cos - 1.0).abs() < 1e-6, "{cos}");
}

#[test]
fn cpu_batch_equals_single_views() {
    let mesh = Arc::new(ic_geometry::shapes::torus(0.8, 0.3, 40, 20).expect("valid torus"));
    let scene = Scene::single(mesh, Pose::from_axis_angle(DVec3::X, 0.7, DVec3::ZERO), 3);
    let k = Intrinsics::from_fov_y(96, 72, 50.0).unwrap();
    let cams: Vec<Camera> = (0..5)
        .map(|i| {
            let vp = ic_geometry::Viewpoint {
                elevation_deg: 10.0 * i as f64,
                azimuth_deg: 20.0 * i as f64,
                distance: 3.0,
            };
            Camera::new(k, vp.camera_pose(DVec3::ZERO).unwrap())
        })
        .collect();
    let mut cpu = CpuRenderer::new();
    let batch = cpu.render_batch(&scene, &cams).unwrap();
    for (c, b) in cams.iter().zip(&batch) {
        assert_eq!(&cpu.render(&scene, c).unwrap(), b);
    }
}

#[test]
fn invalid_ids_and_cameras_are_rejected() {
    let mesh =
        Arc::new(ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::ONE).expect("valid box"));
    let k = Intrinsics::from_fov_y(32, 24, 50.0).unwrap();
    let cam = camera_at(k, 5.0);
    let mut cpu = CpuRenderer::new();
    for id in [0, 70_000] {
        let err = cpu
            .render(&Scene::single(mesh.clone(), Pose::IDENTITY, id), &cam)
            .unwrap_err();
        assert!(
            matches!(err, RenderError::InvalidInstanceId { .. }),
            "{err}"
        );
    }
    let bad = Camera { near: 0.0, ..cam };
    assert!(
        cpu.render(&Scene::single(mesh, Pose::IDENTITY, 1), &bad)
            .is_err()
    );
}

/// Voxel count of a point cloud (private stand-in for ic_geometry's down-sampling).
/// Number of occupied voxels (one output point per occupied voxel).
fn voxels(points: &[ic_geometry::glam::Vec3], size: f32) -> usize {
    ic_geometry::voxel_downsample_points(points, size)
        .expect("finite points")
        .len()
}

#[test]
fn room_scene_gives_a_sensible_inlier_fraction_over_50_views() {
    let object = Arc::new(ic_geometry::shapes::torus(0.75, 0.25, 60, 24).expect("valid torus")); // 2 × 2 × 0.5
    let cfg = SceneConfig {
        intrinsics: Intrinsics::new(262.5, 262.5, 159.5, 119.5, 320, 240).unwrap(),
        ..SceneConfig::default()
    };
    let builder = SceneBuilder::new(cfg).unwrap();
    let mut cpu = CpuRenderer::new();
    let (mut pix, mut vox) = (Vec::new(), Vec::new());
    for seed in 0..50 {
        let s = builder.build(&object, seed).unwrap();
        let view = cpu.render(&s.scene, &s.camera).unwrap();
        let (obj, all) = view.count_returns(OBJECT_ID);
        // The room is closed and the camera inside: every pixel has a return.
        assert_eq!(all, 320 * 240, "seed {seed}");
        assert!(obj > 0, "seed {seed}: object not visible");
        pix.push(obj as f64 / all as f64);
        let k = s.camera.intrinsics;
        let all_pts = k.back_project_depth(&view.depth, None).unwrap();
        let obj_pts = k
            .back_project_depth(&view.depth, Some(&view.mask(OBJECT_ID)))
            .unwrap();
        let size = 0.05 * std::f32::consts::SQRT_2 / 2.0;
        vox.push(voxels(&obj_pts, size) as f64 / voxels(&all_pts, size) as f64);
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[0], v[v.len() / 2], v[v.len() - 1])
    };
    let (p_lo, p_med, p_hi) = stats(&mut pix);
    let (v_lo, v_med, v_hi) = stats(&mut vox);
    eprintln!(
        "inlier fraction over 50 views: pixels min {p_lo:.3} median {p_med:.3} max {p_hi:.3}; voxels(0.0354) min {v_lo:.3} median {v_med:.3} max {v_hi:.3}"
    );
    assert!(
        p_lo > 0.01 && p_hi < 0.8,
        "pixel inlier fraction {p_lo}..{p_hi}"
    );
    assert!(
        v_lo > 0.005 && v_hi < 0.6,
        "voxel inlier fraction {v_lo}..{v_hi}"
    );
}

#[test]
fn scene_builder_is_seeded_and_places_things_sensibly() {
    let object = Arc::new(ic_geometry::shapes::icosphere(1.0, 2).expect("valid sphere"));
    let cfg = SceneConfig {
        support_plane: Some(SupportPlaneConfig::default()),
        distractors: DistractorConfig {
            count: 3,
            size: (0.2, 0.5),
            ..Default::default()
        },
        rotation: ObjectRotation::Uniform,
        ..SceneConfig::default()
    };
    let builder = SceneBuilder::new(cfg.clone()).unwrap();
    for seed in 0..20 {
        let a = builder.build(&object, seed).unwrap();
        let b = builder.build(&object, seed).unwrap();
        assert_eq!(a.camera, b.camera);
        assert_eq!(a.object_pose, b.object_pose);
        let ids: Vec<u32> = a.scene.objects.iter().map(|o| o.id).collect();
        assert_eq!(ids, vec![OBJECT_ID, ROOM_ID, SUPPORT_ID, 10, 11, 12]);
        assert!(
            Arc::ptr_eq(&a.scene.objects[1].mesh, &b.scene.objects[1].mesh),
            "room mesh shared"
        );
        // Camera inside the room, at the configured distance from the object centre.
        let eye = a.camera.pose.inverse().translation;
        assert!(
            eye.x.abs() < 2.0 && eye.y.abs() < 2.0 && eye.z > 0.0 && eye.z < 4.0,
            "{eye}"
        );
        let centre = a.object_to_camera().translation;
        assert!((centre.length() - 2.8).abs() < 1e-9);
        // Object inside the room, above the floor.
        let pts = a.object_pose.apply_all(&object.vertices);
        assert!(
            pts.iter()
                .all(|p| p.x.abs() < 2.0 && p.y.abs() < 2.0 && p.z > 0.0 && p.z < 4.0)
        );
    }
    // Resting vs floating: the lowest point is on the slab top (0.051) or above it.
    let resting = SceneBuilder::new(SceneConfig {
        floating_probability: 0.0,
        ..cfg.clone()
    })
    .unwrap();
    let s = resting.build(&object, 3).unwrap();
    let low = s
        .object_pose
        .apply_all(&object.vertices)
        .iter()
        .map(|p| p.z)
        .fold(f32::INFINITY, f32::min);
    assert!((low - 0.051).abs() < 1e-4, "{low}");
    let json = serde_json::to_string(&cfg).unwrap();
    let back: SceneConfig = serde_json::from_str(&json).unwrap();
    assert_eq!(back, cfg);
    let bad = SceneConfig {
        floating_probability: 2.0,
        ..SceneConfig::default()
    };
    assert!(matches!(
        SceneBuilder::new(bad),
        Err(RenderError::InvalidConfig {
            field: "floating_probability",
            ..
        })
    ));
    // Object-only scenes: just the object (and optional distractors), centred at the origin.
    let alone = SceneBuilder::new(SceneConfig::object_only())
        .unwrap()
        .build(&object, 1)
        .unwrap();
    assert_eq!(alone.scene.objects.len(), 1);
    let view = CpuRenderer::new()
        .render(
            &alone.scene,
            &Camera {
                intrinsics: alone.camera.intrinsics.resized(160, 120),
                ..alone.camera
            },
        )
        .unwrap();
    let (obj, all) = view.count_returns(OBJECT_ID);
    assert!(obj == all && obj > 2000, "{obj} {all}");
}

#[test]
fn tiff_depth_reads_in_the_bop_convention_and_reports_bad_files() {
    use tiff::encoder::{TiffEncoder, colortype};
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let write = |name: &str, f: &dyn Fn(&mut TiffEncoder<std::fs::File>)| {
        let mut e = TiffEncoder::new(std::fs::File::create(p(name)).unwrap()).unwrap();
        f(&mut e);
    };
    // 16-bit: stored × depth_scale = mm (ITODD's depth maps), as the PNG reader.
    write("d16.tif", &|e| {
        e.write_image::<colortype::Gray16>(3, 2, &[0, 1000, 2500, 65_535, 1, 7])
            .unwrap()
    });
    let d = io::read_depth_tiff(p("d16.tif"), 0.1, Some((3, 2))).unwrap();
    let want = [0.0, 0.1, 0.25, 6.5535, 0.0001, 0.0007];
    assert!(
        d.data.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{:?}",
        d.data
    );
    assert_eq!(io::tiff_size(p("d16.tif")).unwrap(), (3, 2));
    // 32-bit float, scaled the same way; non-finite and negative samples are no return.
    write("f32.tif", &|e| {
        e.write_image::<colortype::Gray32Float>(2, 2, &[1500.0, f32::NAN, -3.0, 0.5])
            .unwrap()
    });
    let f = io::read_depth_tiff(p("f32.tif"), 1.0, None).unwrap();
    assert_eq!(f.data, [1.5, 0.0, 0.0, 0.0005]);
    // Errors name the file and say what is wrong.
    let e = io::read_depth_tiff(p("d16.tif"), 1.0, Some((4, 2))).unwrap_err();
    assert!(matches!(e, ImageIoError::SizeMismatch { .. }), "{e}");
    write("rgb.tif", &|e| {
        e.write_image::<colortype::RGB8>(1, 1, &[1, 2, 3]).unwrap()
    });
    let e = io::read_depth_tiff(p("rgb.tif"), 1.0, None).unwrap_err();
    assert!(
        matches!(e, ImageIoError::Format { .. }) && e.to_string().contains("rgb.tif"),
        "{e}"
    );
    write("u8.tif", &|e| {
        e.write_image::<colortype::Gray8>(1, 1, &[9]).unwrap()
    });
    assert!(matches!(
        io::read_depth_tiff(p("u8.tif"), 1.0, None).unwrap_err(),
        ImageIoError::Format { .. }
    ));
    std::fs::write(p("junk.tif"), b"II*\0 not a tiff").unwrap();
    let e = io::read_depth_tiff(p("junk.tif"), 1.0, None).unwrap_err();
    assert!(e.to_string().contains("junk.tif"), "{e}");
    let e = io::read_depth_tiff(p("d16.tif"), 0.0, None).unwrap_err();
    assert!(e.to_string().contains("d16.tif"), "{e}");
}

#[test]
fn image_io_round_trips_and_reports_bad_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let depth = Image::from_vec(3, 2, vec![0.0, 1.2345, 2.0, 65.535, 0.0005, 3.25]).unwrap();

    write_depth_png_and_back(&p("d.png"), &depth);
    io::write_depth_exr(p("d.exr"), &depth).unwrap();
    assert_eq!(io::read_depth_exr(p("d.exr"), Some((3, 2))).unwrap(), depth);

    let mask = Image::from_vec(3, 2, vec![true, false, false, true, true, false]).unwrap();
    io::write_mask_png(p("m.png"), &mask).unwrap();
    assert_eq!(io::read_mask_png(p("m.png"), None).unwrap(), mask);
    let ids = Image::from_vec(3, 2, vec![0, 1, 2, 65_535, 10, 0]).unwrap();
    io::write_instances_png(p("i.png"), &ids).unwrap();
    assert_eq!(
        io::read_instances_png(p("i.png"), Some((3, 2))).unwrap(),
        ids
    );

    // Errors name the file and say what is wrong.
    let e = io::read_mask_png(p("i.png"), None).unwrap_err();
    assert!(
        matches!(e, ImageIoError::Format { .. })
            && e.to_string().contains("i.png")
            && e.to_string().contains("8-bit"),
        "{e}"
    );
    let e = io::read_instances_png(p("i.png"), Some((4, 2))).unwrap_err();
    assert!(matches!(e, ImageIoError::SizeMismatch { .. }), "{e}");
    let e = io::read_depth_png(p("missing.png"), 1.0, None).unwrap_err();
    assert!(matches!(e, ImageIoError::Io { .. }) && e.path().ends_with("missing.png"));
    let e = io::write_depth_png(p("far.png"), &Image::filled(2, 2, 70.0f32), 1.0).unwrap_err();
    assert!(matches!(e, ImageIoError::ValueOutOfRange { .. }), "{e}");
    let e = io::write_instances_png(p("big.png"), &Image::filled(2, 2, 70_000u32)).unwrap_err();
    assert!(matches!(e, ImageIoError::ValueOutOfRange { .. }), "{e}");
    std::fs::write(p("junk.exr"), b"not an exr").unwrap();
    let e = io::read_depth_exr(p("junk.exr"), None).unwrap_err();
    assert!(e.to_string().contains("junk.exr"), "{e}");
    // A three-channel EXR is refused.
    {
        use exr::prelude::*;
        let ch = |n: &str| AnyChannel::new(n, FlatSamples::F32(vec![1.0; 6]));
        let layer = Layer::new(
            (3, 2),
            LayerAttributes::default(),
            Encoding::UNCOMPRESSED,
            AnyChannels::sort(SmallVec::from_vec(vec![ch("R"), ch("G"), ch("B")])),
        );
        exr::image::Image::from_layer(layer)
            .write()
            .to_file(p("rgb.exr"))
            .unwrap();
    }
    let e = io::read_depth_exr(p("rgb.exr"), None).unwrap_err();
    assert!(
        matches!(e, ImageIoError::Format { .. }) && e.to_string().contains("3 channel"),
        "{e}"
    );
    // Failed writes leave no temporary file behind; the directory holds only what we wrote.
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
    assert!(!p("far.png").exists() && !p("big.png").exists());

    // Debug view.
    let mut r = Rendering::empty(40, 30);
    for i in 0..r.depth.data.len() {
        r.depth.data[i] = 1.0 + (i % 40) as f32 * 0.05;
        r.instances.data[i] = (i % 40 > 20) as u32;
    }
    write_debug_png(p("debug.png"), &r.depth, Some(&r.mask(1))).unwrap();
    assert!(std::fs::metadata(p("debug.png")).unwrap().len() > 100);
    assert_eq!(turbo_like(0.0), [48, 18, 59]);
}

fn write_depth_png_and_back(path: &std::path::Path, depth: &ic_geometry::DepthImage) {
    // depth_scale 0.1: stored in 0.1 mm steps, so 65.535 m does not fit; use scale 1 for that.
    io::write_depth_png(path, depth, 1.0).unwrap();
    let back = io::read_depth_png(path, 1.0, Some((3, 2))).unwrap();
    for (a, b) in depth.data.iter().zip(&back.data) {
        assert!((a - b).abs() <= 0.0005 + 1e-6, "{a} vs {b}");
    }
    let near = Image::from_vec(2, 1, vec![1.23456f32, 0.0]).unwrap();
    io::write_depth_png(path, &near, 0.1).unwrap();
    let back = io::read_depth_png(path, 0.1, None).unwrap();
    assert!(
        (back.data[0] - 1.2346).abs() < 1e-6 && back.data[1] == 0.0,
        "{:?}",
        back.data
    );
    assert!(io::write_depth_png(path, &near, 0.0).is_err());
}
