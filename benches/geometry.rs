//! Criterion benchmarks of `ic_geometry`'s hot paths (issue 2):
//! voxelise 300 000 points, k-d tree build + 1 024-point k = 20 query on 10 000 points,
//! Procrustes on 1 024 pairs, ICP on 1 024 vs 10 000 points.
//!
//! Run with `cargo xtask bench geometry` (or `cargo bench -p ic_geometry --bench geometry`).
//! Besides the absolute medians, a baseline is measured in the same run (summing the points),
//! so figures can be reported as ratios on these shared, noisy machines.

use criterion::{Criterion, criterion_group, criterion_main};
use ic_geometry::glam::{DVec3, Vec3};
use ic_geometry::{IcpOptions, IcpTarget, KdTree, PointCloud, Pose, procrustes, voxel_downsample};
use rand::{Rng, SeedableRng};
use std::hint::black_box;

fn points_in_box(n: usize, half: f32, seed: u64) -> Vec<Vec3> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-half..half),
                rng.random_range(-half..half),
                rng.random_range(-half..half),
            )
        })
        .collect()
}

/// Points on an ellipsoid surface: a realistic ICP target.
fn ellipsoid(n: usize, seed: u64) -> Vec<Vec3> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let d = Vec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        if let Some(d) = d.try_normalize() {
            out.push(d * Vec3::new(1.0, 0.6, 0.35));
        }
    }
    out
}

fn benches(c: &mut Criterion) {
    let scene = PointCloud::from_points(points_in_box(300_000, 2.0, 1));
    c.bench_function("baseline/sum_300k_points", |b| {
        b.iter(|| black_box(&scene.points).iter().copied().sum::<Vec3>())
    });
    c.bench_function("voxelise/300k_points_0.0354", |b| {
        b.iter(|| {
            voxel_downsample(black_box(&scene), 0.05 * std::f32::consts::SQRT_2 / 2.0).unwrap()
        })
    });

    let cloud10k = points_in_box(10_000, 1.0, 2);
    let queries = points_in_box(1024, 1.0, 3);
    c.bench_function("kdtree/build_10k_query_1024_k20", |b| {
        b.iter(|| {
            let tree = KdTree::new(black_box(&cloud10k)).unwrap();
            queries
                .iter()
                .map(|&q| tree.k_nearest(q, 20).len())
                .sum::<usize>()
        })
    });

    let model = points_in_box(1024, 1.0, 4);
    let truth = Pose::from_axis_angle(DVec3::new(0.2, 0.5, 1.0), 0.8, DVec3::new(0.1, 0.2, 2.0));
    let observed = truth.apply_all(&model);
    let weights: Vec<f32> = (0..1024).map(|i| (i % 7) as f32 / 7.0).collect();
    c.bench_function("procrustes/1024_pairs_weighted", |b| {
        b.iter(|| procrustes(black_box(&model), black_box(&observed), Some(&weights)).unwrap())
    });

    let target = ellipsoid(10_000, 5);
    let source = ellipsoid(1024, 6);
    let init = Pose::from_axis_angle(
        DVec3::new(0.3, -0.5, 0.8),
        10f64.to_radians(),
        DVec3::new(0.03, 0.02, -0.03),
    );
    let opts = IcpOptions {
        max_correspondence_distance: 0.3,
        max_iterations: 30,
        ..Default::default()
    };
    c.bench_function("icp/point_to_point_1024_vs_10k_30it", |b| {
        b.iter(|| {
            IcpTarget::new(black_box(&target), None)
                .unwrap()
                .register(&source, &init, &opts)
                .unwrap()
        })
    });
}

criterion_group! {
    name = geometry;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = benches
}
criterion_main!(geometry);
