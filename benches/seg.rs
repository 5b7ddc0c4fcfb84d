//! Benchmarks of `ic_seg`: segmentation of one 640×480 depth map by the shipped model
//! (input preparation, network, up-sampling, components, depth refinement), the geometry-only
//! alternative on the same map, one training step of the `cpu` and `clutter` presets at their
//! batch size, and (`seg_kernels`) the fused convolution and batch norm + ReLU of the U-Net's
//! training against the tensor-op versions they replaced, forward + backward in the same run,
//! at the `clutter` preset's finest (8 channels, 256×192) and coarsest (128, 32×24) levels.
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
    let cfg = SegConfig::clutter();
    let (depth, mask) = scene(cfg.train.render_width, cfg.train.render_height);
    let k = Intrinsics::new(210.0, 210.0, 127.5, 95.5, 256, 192).expect("camera");
    let ex = SegExample::new(&depth, &k, &mask, &cfg).expect("example");
    let batch = vec![ex; cfg.train.batch_size];
    let mut trainer = SegTrainer::new(cfg, 1).expect("network");
    group.bench_function("clutter_batch", |b| {
        b.iter(|| trainer.step(&batch).expect("step"))
    });
    group.finish();
}

/// `f()` then a backward pass of its sum.
fn fwd_bwd(f: &dyn Fn() -> candle_core::Tensor) -> candle_core::backprop::GradStore {
    f().sum_all().expect("sum").backward().expect("backward")
}

fn kernels(c: &mut Criterion) {
    use candle_core::{DType, Device, Var};
    use ic_nn::ops::conv::{conv2d_same, conv2d_same_reference};
    use rand::{Rng, SeedableRng};
    let dev = Device::Cpu;
    let randn = |shape: &[usize], seed: u64| {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
        Var::from_vec(v, shape, &dev).expect("var")
    };
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    let bn = ic_nn::norm::BatchNorm2::new(vb.pp("bn"), 8, 0.1).expect("bn");
    let mut g = c.benchmark_group("seg_kernels");
    g.sample_size(10);
    for (name, x, w) in [
        (
            "conv3x3_4x8x192x256",
            randn(&[4, 8, 192, 256], 1),
            randn(&[8, 8, 3, 3], 2),
        ),
        (
            "conv3x3_4x128x24x32",
            randn(&[4, 128, 24, 32], 3),
            randn(&[128, 128, 3, 3], 4),
        ),
    ] {
        g.bench_function(format!("{name}_fwd_bwd/fused"), |b| {
            b.iter(|| fwd_bwd(&|| conv2d_same(&x, &w).expect("conv")))
        });
        g.bench_function(format!("{name}_fwd_bwd/reference"), |b| {
            b.iter(|| fwd_bwd(&|| conv2d_same_reference(&x, &w).expect("conv")))
        });
    }
    let x = randn(&[4, 8, 192, 256], 5);
    g.bench_function("batch_norm_relu_4x8x192x256_fwd_bwd/fused", |b| {
        b.iter(|| fwd_bwd(&|| bn.forward_relu(&x, true).expect("bn")))
    });
    g.bench_function("batch_norm_relu_4x8x192x256_fwd_bwd/reference", |b| {
        b.iter(|| fwd_bwd(&|| bn.forward_t(&x, true).and_then(|y| y.relu()).expect("bn")))
    });
    g.finish();
}

criterion_group!(benches, baseline, segment, train_step, kernels);
criterion_main!(benches);
