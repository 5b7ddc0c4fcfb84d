//! The wgpu backend (feature `gpu`) against analytic geometry and against the CPU reference.
//! Every test fails when no adapter exists (install `mesa-vulkan-drivers libvulkan1` to run
//! them without a GPU): `cargo test -p ic_render --features gpu`; `cargo xtask test` runs them in
//! its one workspace test build (`--features ic_render/gpu`).
#![cfg(feature = "gpu")]

mod common;

use std::sync::Arc;

use common::*;
use ic_geometry::{Intrinsics, Pose, glam::DVec3};
use ic_render::*;

#[test]
fn invalid_wgpu_backend_is_a_clear_error() {
    let err = WgpuRenderer::with_options(&WgpuOptions {
        backends: Some("vulkan,bogus".into()),
        ..Default::default()
    })
    .unwrap_err();
    assert!(
        matches!(&err, RenderError::InvalidBackend { name, .. } if name == "bogus"),
        "{err}"
    );
    assert!(err.to_string().contains("bogus") && err.to_string().contains("vulkan"));
    assert!(parse_backends("").is_err());
    assert_eq!(
        parse_backends(" VK , gl").unwrap(),
        parse_backends("vulkan").unwrap() | parse_backends("gles").unwrap()
    );
    let no = RenderError::NoAdapter {
        backends: "VULKAN".into(),
    };
    assert!(no.to_string().contains("mesa-vulkan-drivers"));
}

#[test]
fn wgpu_sphere_matches_analytic_and_cpu() {
    let mut gpu = wgpu();
    let r = 0.8;
    let mesh = ic_geometry::shapes::icosphere(r as f32, 5).expect("valid sphere");
    let tol = faceting_error(&mesh, r);
    let centre = DVec3::new(0.1, -0.05, 3.0);
    let scene = Scene::single(Arc::new(mesh), Pose::from_translation(centre), 7);
    let k = Intrinsics::new(300.0, 300.0, 159.5, 119.5, 320, 240).unwrap();
    let cam = Camera::new(k, Pose::IDENTITY);
    let g = gpu.render(&scene, &cam).unwrap();
    let c = CpuRenderer::new().render(&scene, &cam).unwrap();
    let mut hits = 0;
    for v in 0..k.height {
        for u in 0..k.width {
            let i = (v * k.width + u) as usize;
            if let Some(want) = ray_sphere_z(&k, u, v, centre, r)
                && g.incidence.data[i] > 0.2
            {
                let err = g.depth.data[i] as f64 - want;
                assert!(
                    err >= -1e-5 && err <= tol / g.incidence.data[i] as f64 + 1e-5,
                    "({u}, {v}): {} vs {want}",
                    g.depth.data[i]
                );
                hits += 1;
            } else if ray_sphere_z(&k, u, v, centre, r).is_none() {
                assert_eq!(g.instances.data[i], 0);
            }
        }
    }
    assert!(hits > 10_000);
    let (n, mismatched, max_rel, p999) = compare(&c, &g);
    eprintln!(
        "sphere cpu vs wgpu: {n} interior pixels, {mismatched} id mismatches, max rel depth diff {max_rel:.2e}, p99.9 {p999:.2e}"
    );
    assert_eq!(mismatched, 0);
    assert!(max_rel < 1e-5, "{max_rel}");
    // Incidence: 16-bit quantised on the GPU.
    let worst_cos = interior(&c)
        .iter()
        .map(|&i| (c.incidence.data[i] - g.incidence.data[i]).abs())
        .fold(0.0f32, f32::max);
    assert!(worst_cos < 0.02, "{worst_cos}");
}

#[test]
fn wgpu_box_head_on_gives_exact_plane_distance() {
    let mut gpu = wgpu();
    let mesh = ic_geometry::shapes::box_mesh(ic_geometry::glam::Vec3::new(1.0, 0.5, 0.25))
        .expect("valid box");
    let scene = Scene::single(Arc::new(mesh), Pose::IDENTITY, 1);
    let k = Intrinsics::new(100.0, 100.0, 60.0, 40.0, 120, 80).unwrap();
    let cam = camera_at(k, 2.75);
    let g = gpu.render(&scene, &cam).unwrap();
    let c = CpuRenderer::new().render(&scene, &cam).unwrap();
    let mut n = 0;
    for i in 0..g.depth.data.len() {
        if g.instances.data[i] == 1 {
            assert!(
                (g.depth.data[i] - 2.5).abs() <= 2.5 * 2e-7,
                "{}",
                g.depth.data[i]
            );
            n += 1;
        }
    }
    // Same top-left fill as the CPU: identical coverage even with edges through pixel centres.
    assert_eq!(n, 80 * 40);
    assert_eq!(g.instances, c.instances);
}

#[test]
fn wgpu_room_scenes_match_cpu() {
    let mut gpu = wgpu();
    let object = Arc::new(ic_geometry::shapes::torus(0.75, 0.25, 60, 24).expect("valid torus"));
    let cfg = SceneConfig {
        intrinsics: Intrinsics::new(262.5, 262.5, 159.5, 119.5, 320, 240).unwrap(),
        support_plane: Some(SupportPlaneConfig::default()),
        distractors: DistractorConfig {
            count: 2,
            size: (0.2, 0.5),
            ..Default::default()
        },
        rotation: ObjectRotation::Uniform,
        ..SceneConfig::default()
    };
    let builder = SceneBuilder::new(cfg).unwrap();
    let mut cpu = CpuRenderer::new();
    let (mut total, mut worst, mut worst999) = (0, 0.0f64, 0.0f64);
    for seed in 0..6 {
        let s = builder.build(&object, seed).unwrap();
        let g = gpu.render(&s.scene, &s.camera).unwrap();
        let c = cpu.render(&s.scene, &s.camera).unwrap();
        let (n, mismatched, max_rel, p999) = compare(&c, &g);
        assert_eq!(mismatched, 0, "seed {seed}");
        total += n;
        worst = worst.max(max_rel);
        worst999 = worst999.max(p999);
        // Everything differs only along silhouettes.
        let differing = c
            .instances
            .data
            .iter()
            .zip(&g.instances.data)
            .filter(|(a, b)| a != b)
            .count();
        assert!(
            differing < c.instances.data.len() / 100,
            "seed {seed}: {differing}"
        );
    }
    eprintln!(
        "room cpu vs wgpu: {total} interior pixels, max rel depth diff {worst:.2e}, p99.9 {worst999:.2e}"
    );
    assert!(worst < 1e-5, "{worst}");
}

#[test]
fn wgpu_batches_match_single_views_and_geometry_is_cached() {
    let mut gpu = wgpu();
    let object = Arc::new(ic_geometry::shapes::torus(0.75, 0.25, 40, 16).expect("valid torus"));
    let builder = SceneBuilder::new(SceneConfig {
        intrinsics: Intrinsics::new(100.0, 100.0, 63.5, 47.5, 128, 96).unwrap(),
        ..SceneConfig::default()
    })
    .unwrap();
    let s = builder.build(&object, 5).unwrap();
    let cams: Vec<Camera> = (0..20u64)
        .map(|seed| builder.build(&object, seed).unwrap().camera)
        .collect();
    // All views of the same scene (the object pose of seed 5).
    let batch = gpu.render_batch(&s.scene, &cams).unwrap();
    assert_eq!(gpu.cached_meshes(), 2);
    for (c, b) in cams.iter().zip(&batch) {
        assert_eq!(&gpu.render(&s.scene, c).unwrap(), b);
    }
    let cpu = CpuRenderer::new().render_batch(&s.scene, &cams).unwrap();
    for (c, g) in cpu.iter().zip(&batch) {
        assert_eq!(compare(c, g).1, 0);
    }
    // A new scene with a different object mesh: the room stays cached, the old object goes.
    let other = Arc::new(ic_geometry::shapes::icosphere(1.0, 3).expect("valid sphere"));
    let s2 = builder.build(&other, 5).unwrap();
    gpu.render(&s2.scene, &s2.camera).unwrap();
    assert_eq!(gpu.cached_meshes(), 2);
    // Mixed image sizes in one batch.
    let small = Camera {
        intrinsics: cams[0].intrinsics.resized(64, 48),
        ..cams[0]
    };
    let mixed = gpu
        .render_batch(&s.scene, &[cams[0], small, cams[1]])
        .unwrap();
    assert_eq!((mixed[1].depth.width, mixed[1].depth.height), (64, 48));
    assert_eq!(mixed[2], batch[1]);
}
