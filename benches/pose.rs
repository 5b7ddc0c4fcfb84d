//! Benchmarks of `ic_pose` (random weights): forward time per pair at 512/1024/2048 model
//! points (N = ¾·M observed) for both presets (`cpu`, `paper`) and both heads, and one training step
//! (batch of the preset at its training sizes) → pairs/hour = batch · 3600 / step seconds.
//!
//! Points are random in the unit cube; timings do not depend on the values.
//!
//! `pose_kernels` times each fused CPU kernel against the tensor-op version it replaced (the
//! "before"), in the same run, forward + backward at the `cpu` preset's training sizes
//! (B = 4, 384 points, d = 128) and forward at 1024 inference points.

use std::hint::black_box;

use candle_core::Tensor;
use criterion::{Criterion, criterion_group, criterion_main};
use glam::Vec3;
use ic_data::Assignment;
use ic_pose::{Head, PoseConfig, PoseEstimator};
use ic_train::PoseTrainer as Trainer;
use rand::{Rng, SeedableRng};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn points(seed: u64, n: usize) -> Vec<Vec3> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
        .collect()
}

fn baseline(c: &mut Criterion) {
    // SAFETY: the first benchmark, before any pool thread exists (criterion runs on this thread).
    unsafe { ic_pose::tune_candle_cpu_pool() };
    let points: Vec<Vec3> = (0..300_000).map(|i| Vec3::splat(i as f32 * 1e-5)).collect();
    c.bench_function("baseline/sum_300k_points", |b| {
        b.iter(|| black_box(&points).iter().copied().sum::<Vec3>())
    });
}

fn forward(c: &mut Criterion) {
    // The paper's Table 3 columns, for both presets and both heads.
    for preset in ["cpu", "paper"] {
        let mut group = c.benchmark_group(format!("pose_forward_{preset}"));
        group.sample_size(10);
        for head in [Head::Softmax, Head::Ot] {
            let cfg = PoseConfig::preset(preset, head).expect("preset");
            let trainer = Trainer::new(cfg, 1).expect("network");
            let est: PoseEstimator = trainer.estimator();
            for m in [512usize, 1024, 2048] {
                let n = m * 3 / 4;
                let (x, y) = (points(1, m), points(2, n));
                group.bench_function(format!("{}_{m}x{n}", head.as_str()), |b| {
                    b.iter(|| est.infer(&x, &y).expect("forward"))
                });
            }
        }
        group.finish();
    }
}

fn train_step(c: &mut Criterion) {
    let mut group = c.benchmark_group("pose_train_step");
    group.sample_size(10);
    for head in [Head::Softmax, Head::Ot] {
        let cfg = PoseConfig::cpu(head);
        let (m, n, b) = (
            cfg.train.model_points,
            cfg.train.observed_points,
            cfg.train.batch_size,
        );
        let xs: Vec<Vec<Vec3>> = (0..b).map(|i| points(10 + i as u64, m)).collect();
        let ys: Vec<Vec<Vec3>> = (0..b).map(|i| points(100 + i as u64, n)).collect();
        let asg: Vec<Assignment> = (0..b)
            .map(|_| Assignment {
                model_count: m,
                observed_count: n,
                observed_to_model: (0..n)
                    .map(|j| (j % 3 == 0).then_some((j % m) as u32))
                    .collect(),
            })
            .collect();
        let pairs: Vec<(&[Vec3], &[Vec3])> =
            xs.iter().zip(&ys).map(|(x, y)| (&x[..], &y[..])).collect();
        let refs: Vec<&Assignment> = asg.iter().collect();
        let mut trainer = Trainer::new(cfg, 1).expect("network");
        group.bench_function(format!("{}_batch{b}_{m}x{n}", head.as_str()), |bch| {
            bch.iter(|| trainer.step_pairs(&pairs, &refs).expect("step"))
        });
    }
    group.finish();
}

/// Forward + backward of `f` (a weighted sum of its output as the loss).
fn fwd_bwd(f: &dyn Fn() -> Tensor) -> candle_core::backprop::GradStore {
    let y = f();
    let w = y.ones_like().expect("ones");
    (y * w)
        .expect("mul")
        .sum_all()
        .expect("sum")
        .backward()
        .expect("backward")
}

fn kernels(c: &mut Criterion) {
    use candle_core::{DType, Device, Module, Var};
    use ic_nn::ops::attention::{multi_head_attention, multi_head_attention_reference};
    use ic_pose::dgcnn::{neighbour_max, neighbour_max_reference};
    use ic_pose::layers::{Dense, LayerNorm};
    let dev = Device::Cpu;
    let randn = |shape: &[usize], seed: u64| {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect();
        Var::from_vec(v, shape, &dev).expect("var")
    };
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    let ln = LayerNorm::new(vb.pp("ln"), 128).expect("ln");
    let up = Dense::new(vb.pp("up"), 128, 512, true).expect("dense");
    let bn = ic_nn::norm::BatchNorm1::new(vb.pp("bn"), 128, 0.1).expect("bn");
    let (w_up, b_up) = (
        up.weight().clone(),
        varmap.data().lock().unwrap()["up.bias"].clone(),
    );
    let x = randn(&[4, 384, 128], 1);
    let xc = randn(&[4, 128, 384], 2);
    let big = randn(&[1, 1024, 128], 3);
    let graph: Vec<u32> = (0..4 * 384 * 16)
        .map(|i| ((i * 7919) % 384) as u32)
        .collect();
    let graph = Tensor::from_vec(graph, (4, 384 * 16), &dev).expect("graph");

    let mut g = c.benchmark_group("pose_kernels");
    g.sample_size(10);
    type Case<'a> = (
        &'a str,
        Box<dyn Fn() -> Tensor + 'a>,
        Box<dyn Fn() -> Tensor + 'a>,
    );
    let train: Vec<Case> = vec![
        (
            "attention_4x384x384",
            Box::new(|| multi_head_attention(&x, &x, &x, 4).unwrap()),
            Box::new(|| multi_head_attention_reference(&x, &x, &x, 4).unwrap()),
        ),
        (
            "layer_norm_4x384x128",
            Box::new(|| ln.forward(&x).unwrap()),
            Box::new(|| ln.forward_reference(&x).unwrap()),
        ),
        (
            "dense_relu_128_512",
            Box::new(|| up.forward_relu(&x).unwrap()),
            Box::new(|| {
                x.broadcast_matmul(&w_up.t().unwrap())
                    .unwrap()
                    .broadcast_add(b_up.as_tensor())
                    .unwrap()
                    .relu()
                    .unwrap()
            }),
        ),
        (
            "batch_norm_leaky_4x128x384",
            Box::new(|| bn.forward_leaky_relu(&xc, true, 0.2).unwrap()),
            Box::new(|| {
                let y = bn.forward_t(&xc, true).unwrap();
                y.maximum(&(&y * 0.2).unwrap()).unwrap()
            }),
        ),
        (
            "neighbour_max_4x128x384_k16",
            Box::new(|| neighbour_max(&xc, &graph, 16).unwrap()),
            Box::new(|| neighbour_max_reference(&xc, &graph, 16).unwrap()),
        ),
    ];
    for (name, fused, reference) in &train {
        g.bench_function(format!("{name}_fwd_bwd/fused"), |b| {
            b.iter(|| fwd_bwd(fused.as_ref()))
        });
        g.bench_function(format!("{name}_fwd_bwd/reference"), |b| {
            b.iter(|| fwd_bwd(reference.as_ref()))
        });
    }
    g.bench_function("attention_1024x1024_fwd/fused", |b| {
        b.iter(|| multi_head_attention(&big, &big, &big, 4).unwrap())
    });
    g.bench_function("attention_1024x1024_fwd/reference", |b| {
        b.iter(|| multi_head_attention_reference(&big, &big, &big, 4).unwrap())
    });
    g.finish();
}

/// One registration with a shipped model (`models/pose-cpu-{ot,softmax}.safetensors`, skipped
/// when absent): `PoseEstimator::estimate` on 1024 model and 768 observed points, one-shot
/// (network + weighted Procrustes) and with the default ICP refinement. The points are one
/// random cloud and a rotated, shifted subset of it, so the network sees a plausible pair.
fn register(c: &mut Criterion) {
    use ic_pose::Refine;
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models");
    let mut group = c.benchmark_group("pose_register_shipped");
    group.sample_size(10);
    let x = points(7, 1024);
    let rot = glam::Quat::from_euler(glam::EulerRot::XYZ, 0.4, -0.3, 0.9);
    let y: Vec<Vec3> = x[..768]
        .iter()
        .map(|p| rot * *p + Vec3::new(0.1, -0.2, 3.0))
        .collect();
    for head in ["ot", "softmax"] {
        let path = models.join(format!("pose-cpu-{head}.safetensors"));
        let Ok(mut est) = PoseEstimator::load(&path) else {
            eprintln!(
                "{} not found: skipping pose_register_shipped/{head}",
                path.display()
            );
            continue;
        };
        for refine in [Refine::None, Refine::Icp] {
            est.recovery.refine = refine;
            let label = if refine == Refine::Icp {
                "icp"
            } else {
                "one_shot"
            };
            group.bench_function(format!("{head}_{label}_1024x768"), |b| {
                b.iter(|| black_box(est.estimate(&x, &y).is_ok()))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, baseline, forward, train_step, kernels, register);
criterion_main!(benches);
