//! Time of each stage of the `cpu` preset forward pass (DGCNN, transformer, score map, head)
//! at 1024×768, one thread unless RAYON_NUM_THREADS says otherwise.
use std::time::Instant;

use glam::Vec3;
use ic_pose::{Head, PairBatch, PoseConfig, Trainer};
use rand::{Rng, SeedableRng};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let m: usize = std::env::args().nth(1).map_or(Ok(1024), |s| s.parse())?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut pts = |c: usize| -> Vec<Vec3> {
        (0..c)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
            .collect()
    };
    let (x, y) = (pts(m), pts(m * 3 / 4));
    let trainer = Trainer::new(PoseConfig::cpu(Head::Ot), 1)?;
    let net = trainer.net();
    for _ in 0..3 {
        let t = Instant::now();
        let batch = PairBatch::new(
            &[(&x[..], &y[..])],
            net.config().k,
            &candle_core::Device::Cpu,
        )?;
        let t_graph = t.elapsed();
        let t = Instant::now();
        let (tx, ty) = net.encode(&batch, false)?;
        let t_enc = t.elapsed();
        let t = Instant::now();
        let (fx, fy) = net.embed(&batch, false)?;
        let t_embed = t.elapsed();
        let t = Instant::now();
        let _ = net.forward_t(&batch, false)?;
        let t_all = t.elapsed();
        let _ = (tx, ty, fx, fy);
        println!(
            "{m}: knn graph {:.1} ms, encoder {:.1} ms, encoder+transformer {:.1} ms, whole forward {:.1} ms",
            t_graph.as_secs_f64() * 1e3,
            t_enc.as_secs_f64() * 1e3,
            t_embed.as_secs_f64() * 1e3,
            t_all.as_secs_f64() * 1e3
        );
    }
    Ok(())
}
