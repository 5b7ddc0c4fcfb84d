//! Benchmarks of `ic_pose` (random weights): forward time per pair at 512/1024/2048 model
//! points (N = ¾·M observed) for both presets (`cpu`, `paper`) and both heads, and one training step
//! (batch of the preset at its training sizes) → pairs/hour = batch · 3600 / step seconds.
//!
//! Points are random in the unit cube; timings do not depend on the values.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use glam::Vec3;
use ic_data::Assignment;
use ic_pose::{Head, PoseConfig, PoseEstimator, Trainer};
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

criterion_group!(benches, baseline, forward, train_step);
criterion_main!(benches);
