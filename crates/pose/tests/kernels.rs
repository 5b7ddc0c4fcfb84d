//! The fused CPU kernels against their tensor-op references, in value and gradient: the
//! multi-head attention (`ic_pose::attention`) over shapes that exercise several query blocks,
//! a ragged last block, one key and more heads than pairs; the EdgeConv gather-max
//! (`ic_pose::dgcnn::neighbour_max`).

use candle_core::{Device, Tensor, Var};
use ic_pose::attention::{multi_head_attention, multi_head_attention_reference};
use ic_pose::dgcnn::{neighbour_max, neighbour_max_reference};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn randn(shape: (usize, usize, usize), scale: f32, seed: u64) -> Tensor {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = shape.0 * shape.1 * shape.2;
    let v: Vec<f32> = (0..n)
        .map(|_| (0..4).map(|_| rng.random_range(-1.0f32..1.0)).sum::<f32>() * scale)
        .collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

fn max_rel_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().map(|x| x.abs()).fold(1e-6, f32::max);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
        / scale
}

/// Values and gradients of a weighted sum of the output, fused vs reference.
fn check(b: usize, pq: usize, pk: usize, d: usize, heads: usize, scale: f32) {
    let q = Var::from_tensor(&randn((b, pq, d), scale, 1)).unwrap();
    let k = Var::from_tensor(&randn((b, pk, d), scale, 2)).unwrap();
    let v = Var::from_tensor(&randn((b, pk, d), 1.0, 3)).unwrap();
    let w = randn((b, pq, d), 1.0, 4);
    let run = |fused: bool| {
        let out = if fused {
            multi_head_attention(&q, &k, &v, heads)
        } else {
            multi_head_attention_reference(&q, &k, &v, heads)
        }
        .unwrap();
        let grads = (&out * &w).unwrap().sum_all().unwrap().backward().unwrap();
        let g = |x: &Var| flat(grads.get(x.as_tensor()).expect("gradient"));
        (flat(&out), g(&q), g(&k), g(&v))
    };
    let fused = run(true);
    let reference = run(false);
    let what = format!("b {b}, {pq}×{pk}, d {d}, {heads} heads");
    assert!(
        max_rel_diff(&fused.0, &reference.0) < 1e-5,
        "output, {what}"
    );
    assert!(max_rel_diff(&fused.1, &reference.1) < 1e-4, "dq, {what}");
    assert!(max_rel_diff(&fused.2, &reference.2) < 1e-4, "dk, {what}");
    assert!(max_rel_diff(&fused.3, &reference.3) < 1e-4, "dv, {what}");
}

#[test]
fn fused_attention_matches_reference_in_value_and_gradient() {
    // 300 keys → blocks of 109 query rows: three blocks, the last one ragged.
    check(2, 250, 300, 16, 4, 0.7);
    check(1, 7, 33, 8, 2, 1.0);
    check(3, 19, 1, 6, 3, 1.0);
}

#[test]
fn fused_attention_is_stable_for_large_scores() {
    // Scores of several hundred: a naive exp would overflow.
    check(1, 40, 50, 8, 2, 6.0);
}

#[test]
fn fused_attention_rejects_heads_that_do_not_divide_channels() {
    let q = randn((1, 4, 6), 1.0, 1);
    assert!(multi_head_attention(&q, &q, &q, 4).is_err());
}

#[test]
fn fused_neighbour_max_matches_gather_and_max() {
    let (b, c, p, k) = (2, 5, 40, 6);
    let a = Var::from_tensor(&randn((b, c, p), 1.0, 7)).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    // Distinct neighbours per point, as in a k-NN graph.
    let mut graph: Vec<u32> = Vec::with_capacity(b * p * k);
    for _ in 0..b * p {
        let mut ids: Vec<u32> = (0..p as u32).collect();
        for r in 0..k {
            let s = rng.random_range(r..p);
            ids.swap(r, s);
        }
        graph.extend(&ids[..k]);
    }
    let graph = Tensor::from_vec(graph, (b, p * k), &Device::Cpu).unwrap();
    let w = randn((b, c, p), 1.0, 9);
    let run = |fused: bool| {
        let out = if fused {
            neighbour_max(&a, &graph, k)
        } else {
            neighbour_max_reference(&a, &graph, k)
        }
        .unwrap();
        let grads = (&out * &w).unwrap().sum_all().unwrap().backward().unwrap();
        (
            flat(&out),
            flat(grads.get(a.as_tensor()).expect("gradient")),
        )
    };
    let (fo, fg) = run(true);
    let (ro, rg) = run(false);
    assert_eq!(fo, ro, "values");
    assert!(max_rel_diff(&fg, &rg) < 1e-6, "gradient");
}

#[test]
fn neighbour_max_rejects_out_of_range_neighbours() {
    let a = randn((1, 2, 4), 1.0, 1);
    let graph = Tensor::from_vec(vec![0u32, 1, 2, 9], (1, 4), &Device::Cpu).unwrap();
    assert!(neighbour_max(&a, &graph, 1).is_err());
}
