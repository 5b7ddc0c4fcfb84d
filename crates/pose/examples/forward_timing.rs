//! Forward time per pair of the `cpu` preset network at 512/1024/2048 model points (N = ¾·M),
//! both heads, one thread unless RAYON_NUM_THREADS says otherwise (a quick stand-in for
//! `cargo xtask bench pose`, which needs a release build).
use std::time::Instant;

use glam::Vec3;
use ic_pose::{Head, PoseConfig, Trainer};
use rand::{Rng, SeedableRng};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    let reps: usize = std::env::args().nth(1).map_or(3, |s| s.parse().unwrap());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut pts = |c: usize| -> Vec<Vec3> {
        (0..c)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
            .collect()
    };
    for head in [Head::Softmax, Head::Ot] {
        let est = Trainer::new(PoseConfig::cpu(head), 1).unwrap().estimator();
        for m in [512usize, 1024, 2048] {
            let (x, y) = (pts(m), pts(m * 3 / 4));
            est.infer(&x, &y).unwrap();
            let mut best = f64::INFINITY;
            for _ in 0..reps {
                let c = Instant::now();
                est.infer(&x, &y).unwrap();
                best = best.min(c.elapsed().as_secs_f64());
            }
            println!(
                "{} {m}x{}: {:.1} ms/pair (best of {reps})",
                head.as_str(),
                m * 3 / 4,
                best * 1e3
            );
        }
    }
}
