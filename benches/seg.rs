//! Benchmarks of `ic_seg`: segmentation of one 640×480 depth map by the shipped model
//! (input preparation, network, up-sampling, components, depth refinement), the geometry-only
//! alternative on the same map, and one training step of the `cpu` preset at its batch size.
//!
//! The scene is a box in front of a wall, so both methods find one object.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use glam::Vec3;
use ic_geometry::{DepthImage, Intrinsics, Mask};
use ic_seg::{GeometricConfig, SegConfig, SegExample, segment_geometric};
use ic_train::SegTrainer;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn baseline(c: &mut Criterion) {
    let points: Vec<Vec3> = (0..300_000).map(|i| Vec3::splat(i as f32 * 1e-5)).collect();
    c.bench_function("baseline/sum_300k_points", |b| {
        b.iter(|| black_box(&points).iter().copied().sum::<Vec3>())
    });
}

fn scene(w: u32, h: u32) -> (DepthImage, Mask) {
    let mut depth = DepthImage::filled(w, h, 8.0);
    let mut mask = Mask::filled(w, h, false);
    for v in h / 3..h / 2 {
        for u in w / 3..w / 2 {
            let i = (v * w + u) as usize;
            depth.data[i] = 6.0;
            mask.data[i] = true;
        }
    }
    (depth, mask)
}

fn segment(c: &mut Criterion) {
    let mut group = c.benchmark_group("seg");
    group.sample_size(20);
    // The shipped model (random weights would threshold the whole image into one component and
    // time the post-processing of 300 000 pixels instead).
    let shipped =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/seg-cpu.safetensors");
    let seg = ic_seg::Segmenter::load(&shipped).expect("models/seg-cpu.safetensors");
    let (depth, _) = scene(640, 480);
    let k = Intrinsics::new(525.0, 525.0, 319.5, 239.5, 640, 480).expect("camera");
    group.bench_function("network_640x480", |b| {
        b.iter(|| black_box(seg.segment(&depth, &k)).ok())
    });
    let geo = GeometricConfig::default();
    group.bench_function("geometric_640x480", |b| {
        b.iter(|| black_box(segment_geometric(&depth, &k, 2.0, 1.0, &geo)).ok())
    });
    group.finish();
}

fn train_step(c: &mut Criterion) {
    let mut group = c.benchmark_group("seg_train_step");
    group.sample_size(10);
    let cfg = SegConfig::cpu();
    let (depth, mask) = scene(cfg.train.render_width, cfg.train.render_height);
    let (w, h) = (cfg.train.render_width, cfg.train.render_height);
    let k = Intrinsics::new(525.0, 525.0, 319.5, 239.5, 640, 480)
        .expect("camera")
        .resized(w, h);
    let ex = SegExample::new(&depth, &k, &mask, &cfg).expect("example");
    let batch = vec![ex; cfg.train.batch_size];
    let mut trainer = SegTrainer::new(cfg, 1).expect("network");
    group.bench_function("cpu_batch", |b| {
        b.iter(|| trainer.step(&batch).expect("step"))
    });
    group.finish();
}

criterion_group!(benches, baseline, segment, train_step);
criterion_main!(benches);
