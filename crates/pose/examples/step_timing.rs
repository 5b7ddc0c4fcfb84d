//! Measures training-step and forward time of candidate configurations on random data:
//! `cargo run -p ic_pose --example step_timing -- EMB K M N BATCH FF [STEPS]`.
use std::time::Instant;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

use glam::Vec3;
use ic_data::Assignment;
use ic_pose::{Head, PoseConfig, Trainer};
use rand::{Rng, SeedableRng};

fn main() {
    let a: Vec<usize> = std::env::args()
        .skip(1)
        .map(|s| s.parse().unwrap())
        .collect();
    let (emb, k, m, n, b, ff) = (a[0], a[1], a[2], a[3], a[4], a[5]);
    let steps = a.get(6).copied().unwrap_or(3);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut pts = |c: usize| -> Vec<Vec3> {
        (0..c)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
            .collect()
    };
    let xs: Vec<Vec<Vec3>> = (0..b).map(|_| pts(m)).collect();
    let ys: Vec<Vec<Vec3>> = (0..b).map(|_| pts(n)).collect();
    let asg: Vec<Assignment> = (0..b)
        .map(|_| Assignment {
            model_count: m,
            observed_count: n,
            observed_to_model: (0..n)
                .map(|j| (j % 2 == 0).then_some((j % m) as u32))
                .collect(),
        })
        .collect();
    for head in [Head::Softmax, Head::Ot] {
        let mut cfg = PoseConfig::cpu(head);
        cfg.net.emb_dims = emb;
        cfg.net.k = k;
        cfg.net.ff_dims = ff;
        cfg.train.batch_size = b;
        let mut t = Trainer::new(cfg, 0).unwrap();
        let pairs: Vec<(&[Vec3], &[Vec3])> =
            xs.iter().zip(&ys).map(|(x, y)| (&x[..], &y[..])).collect();
        let ar: Vec<&Assignment> = asg.iter().collect();
        t.step_pairs(&pairs, &ar).unwrap();
        let c = Instant::now();
        for _ in 0..steps {
            t.step_pairs(&pairs, &ar).unwrap();
        }
        let dt = c.elapsed().as_secs_f64() / steps as f64;
        let est = t.estimator();
        let c = Instant::now();
        for i in 0..steps {
            est.infer(&xs[i % b], &ys[i % b]).unwrap();
        }
        let fwd = c.elapsed().as_secs_f64() / steps as f64;
        println!(
            "{head:?} emb {emb} k {k} ff {ff} {m}x{n} batch {b}: step {dt:.3}s = {:.0} pairs/h; forward {:.1} ms/pair",
            b as f64 * 3600.0 / dt,
            fwd * 1e3
        );
    }
}
