//! Tests of the log-domain Sinkhorn OT layer (`ic_pose::sinkhorn`).

use candle_core::{Device, Tensor};
use ic_pose::sinkhorn::{log_optimal_transport, log_optimal_transport_reference};

fn marginal_err(lp: &Tensor, m: usize, n: usize) -> f32 {
    let p = lp.exp().unwrap();
    let rows: Vec<Vec<f32>> = p.sum(2).unwrap().to_vec2().unwrap();
    let cols: Vec<Vec<f32>> = p.sum(1).unwrap().to_vec2().unwrap();
    let mut err = 0.0f32;
    for (r, c) in rows.iter().zip(&cols) {
        for (i, &x) in r.iter().enumerate() {
            let a = if i < m { 1.0 } else { n as f32 };
            err = err.max((x - a).abs());
        }
        for (j, &x) in c.iter().enumerate() {
            let b = if j < n { 1.0 } else { m as f32 };
            err = err.max((x - b).abs());
        }
    }
    err
}

#[test]
fn reference_marginals_smoke() {
    let s = Tensor::randn(0f32, 1.0, (2, 7, 5), &Device::Cpu).unwrap();
    let lp = log_optimal_transport_reference(&s, 0.01, 0.5, 50).unwrap();
    assert_eq!(lp.dims(), &[2, 8, 6]);
    assert!(marginal_err(&lp, 7, 5) < 1e-3);
    let lp2 = log_optimal_transport(&s, 0.01, 0.5, 50).unwrap();
    assert_eq!(lp2.dims(), &[2, 8, 6]);
}
