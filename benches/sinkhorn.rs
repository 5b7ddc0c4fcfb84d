//! Criterion benchmarks of the Sinkhorn OT layer (`ic_pose::sinkhorn`): the fused CPU op
//! (`fused`: scaled-domain forward, the default; `fused_log_domain`: one exp per entry and
//! iteration, the fused op before the scaled forward) vs the reference made of generic candle
//! tensor ops, forward and forward + backward, for B = 1 and augmented sizes 513×385,
//! 1025×769 and 2049×1537 (α = 0.01, λ = 0.5, k = 50).
//!
//! Run with `cargo bench -p ic_pose --bench sinkhorn`; medians are in
//! `target/criterion/sinkhorn_*/*/new/estimates.json`. Uses mimalloc like the training binary
//! (with glibc malloc the reference's large element-wise ops are much slower).

use candle_core::{Device, Tensor, Var};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use ic_pose::sinkhorn::{
    log_optimal_transport, log_optimal_transport_reference, log_optimal_transport_with,
};
use rand::{Rng, SeedableRng};
use std::hint::black_box;
use std::time::Duration;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

type OtFn = fn(&Tensor, f32, f32, usize) -> candle_core::Result<Tensor>;

const SIZES: [(usize, usize); 3] = [(512, 384), (1024, 768), (2048, 1536)];

fn random(shape: (usize, usize, usize), seed: u64) -> Tensor {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = shape.0 * shape.1 * shape.2;
    let v: Vec<f32> = (0..n).map(|_| rng.random_range(-2.0f32..2.0)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn log_domain(s: &Tensor, alpha: f32, lambda: f32, k: usize) -> candle_core::Result<Tensor> {
    log_optimal_transport_with(s, alpha, lambda, k, false)
}

fn impls() -> [(&'static str, OtFn); 3] {
    [
        ("fused", log_optimal_transport),
        ("fused_log_domain", log_domain),
        ("reference", log_optimal_transport_reference),
    ]
}

fn forward(c: &mut Criterion) {
    // SAFETY: the first benchmark, before any pool thread exists.
    unsafe { ic_pose::tune_candle_cpu_pool() };
    let mut g = c.benchmark_group("sinkhorn_fwd");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    for (m, n) in SIZES {
        let s = random((1, m, n), 1);
        for (name, f) in impls() {
            g.bench_with_input(
                BenchmarkId::new(name, format!("{}x{}", m + 1, n + 1)),
                &s,
                |b, s| b.iter(|| black_box(f(s, 0.01, 0.5, 50).unwrap())),
            );
        }
    }
    g.finish();
}

fn forward_backward(c: &mut Criterion) {
    let mut g = c.benchmark_group("sinkhorn_fwd_bwd");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(6))
        .warm_up_time(Duration::from_secs(1));
    for (m, n) in SIZES {
        let var = Var::from_tensor(&random((1, m, n), 2)).unwrap();
        let w = random((1, m + 1, n + 1), 3);
        for (name, f) in impls() {
            g.bench_with_input(
                BenchmarkId::new(name, format!("{}x{}", m + 1, n + 1)),
                &var,
                |b, var| {
                    b.iter(|| {
                        let lp = f(var.as_tensor(), 0.01, 0.5, 50).unwrap();
                        let loss = (&lp * &w).unwrap().sum_all().unwrap();
                        black_box(loss.backward().unwrap())
                    })
                },
            );
        }
    }
    g.finish();
}

criterion_group!(sinkhorn, forward, forward_backward);
criterion_main!(sinkhorn);
