//! Rendering throughput (views/s): CPU reference vs wgpu (a GPU, or lavapipe) for a
//! 10 000-triangle torus at 640×480 and 160×120, single views and batches of 16.
//!
//! Run with `cargo xtask bench render` (or `cargo bench -p ic_render --bench render`; the wgpu
//! rows need `--features gpu`, without it the CPU renderer alone is measured). The same
//! baseline as `benches/geometry.rs` (summing 300 000 points) is measured in the run, so figures
//! can be reported as ratios on these shared, noisy machines.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use ic_geometry::glam::{DVec3, Vec3};
use ic_geometry::{Intrinsics, Pose, ViewSphere};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use rand::SeedableRng;

fn cameras(width: u32, height: u32, n: usize) -> Vec<Camera> {
    let k = Intrinsics::new(525.0, 525.0, 319.5, 239.5, 640, 480)
        .unwrap()
        .resized(width, height);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let sphere = ViewSphere::paper(2.8);
    (0..n)
        .map(|_| Camera::new(k, sphere.sample(&mut rng).camera_pose(DVec3::ZERO).unwrap()))
        .collect()
}

fn bench(c: &mut Criterion) {
    let points: Vec<Vec3> = (0..300_000).map(|i| Vec3::splat(i as f32 * 1e-5)).collect();
    c.bench_function("baseline/sum_300k_points", |b| {
        b.iter(|| black_box(&points).iter().copied().sum::<Vec3>())
    });

    let mesh = Arc::new(ic_geometry::shapes::torus(0.75, 0.25, 100, 50).expect("valid torus"));
    assert_eq!(mesh.triangles.len(), 10_000);
    let scene = Scene::single(mesh, Pose::IDENTITY, 1);
    #[cfg(feature = "gpu")]
    let mut gpu = match ic_render::WgpuRenderer::new() {
        Ok(r) => {
            eprintln!("wgpu adapter: {}", r.name());
            Some(r)
        }
        Err(e) => {
            eprintln!("skipping wgpu benchmarks: {e}");
            None
        }
    };
    #[cfg(not(feature = "gpu"))]
    let mut gpu: Option<CpuRenderer> = {
        eprintln!("skipping wgpu benchmarks: ic_render built without the `gpu` feature");
        None
    };
    let mut cpu = CpuRenderer::new();
    let mut group = c.benchmark_group("render_10k_triangles");
    group.sample_size(20);
    for (w, h) in [(640, 480), (160, 120)] {
        let cams = cameras(w, h, 16);
        let label = format!("{w}x{h}");
        group.throughput(Throughput::Elements(1));
        let mut i = 0;
        group.bench_function(BenchmarkId::new("cpu", &label), |b| {
            b.iter(|| {
                i = (i + 1) % cams.len();
                black_box(cpu.render(&scene, &cams[i]).unwrap())
            })
        });
        if let Some(gpu) = gpu.as_mut() {
            let mut i = 0;
            group.bench_function(BenchmarkId::new("wgpu", &label), |b| {
                b.iter(|| {
                    i = (i + 1) % cams.len();
                    black_box(gpu.render(&scene, &cams[i]).unwrap())
                })
            });
        }
        group.throughput(Throughput::Elements(cams.len() as u64));
        group.bench_function(BenchmarkId::new("cpu_batch16", &label), |b| {
            b.iter(|| black_box(cpu.render_batch(&scene, &cams).unwrap()))
        });
        if let Some(gpu) = gpu.as_mut() {
            group.bench_function(BenchmarkId::new("wgpu_batch16", &label), |b| {
                b.iter(|| black_box(gpu.render_batch(&scene, &cams).unwrap()))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
