//! Splits a training step's time into forward / backward / Adam, and the forward into parts.
use std::time::Instant;

use candle_core::Device;
use glam::Vec3;
use ic_data::Assignment;
use ic_pose::{Head, PairBatch, PoseConfig, Trainer, nll_loss};
use rand::{Rng, SeedableRng};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    let a: Vec<usize> = std::env::args()
        .skip(1)
        .map(|s| s.parse().unwrap())
        .collect();
    let (emb, k, m, n, b) = (a[0], a[1], a[2], a[3], a[4]);
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
    let ar: Vec<&Assignment> = asg.iter().collect();
    let pairs: Vec<(&[Vec3], &[Vec3])> =
        xs.iter().zip(&ys).map(|(x, y)| (&x[..], &y[..])).collect();
    for head in [Head::Softmax, Head::Ot] {
        let mut cfg = PoseConfig::cpu(head);
        cfg.net.emb_dims = emb;
        cfg.net.k = k;
        let t = Trainer::new(cfg, 0).unwrap();
        for _ in 0..2 {
            let c = Instant::now();
            let batch = PairBatch::new(&pairs, k, &Device::Cpu).unwrap();
            let t0 = c.elapsed().as_secs_f64();
            let (fx, fy) = t.net().embed(&batch, true).unwrap();
            let t1 = c.elapsed().as_secs_f64();
            let out = t.net().forward_t(&batch, true).unwrap();
            let t2 = c.elapsed().as_secs_f64();
            let loss = nll_loss(&out, &ar).unwrap();
            let g = loss.backward().unwrap();
            let t3 = c.elapsed().as_secs_f64();
            drop((fx, fy, g));
            let c = Instant::now();
            let (tx, ty) = t.net().encode(&batch, true).unwrap();
            let t4 = c.elapsed().as_secs_f64();
            let l = (tx.sqr().unwrap().sum_all().unwrap() + ty.sqr().unwrap().sum_all().unwrap())
                .unwrap();
            let _g = l.backward().unwrap();
            let t5 = c.elapsed().as_secs_f64();
            println!("  dgcnn forward {t4:.3}s backward {:.3}s", t5 - t4);
            println!(
                "{head:?}: batch+knn {t0:.3}s embed {:.3}s full forward {:.3}s backward {:.3}s",
                t1 - t0,
                t2 - t1,
                t3 - t2
            );
        }
    }
}
