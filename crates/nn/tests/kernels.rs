//! The fused CPU kernels of `ic_nn::ops` against their tensor-op references, in value and
//! gradient: the multi-head attention over shapes that exercise several query blocks, a ragged
//! last block, one key and more heads than pairs; the EdgeConv gather-max (alone and with the
//! centre term added); layer norm; the
//! dense layer; the 1×1 channel convolution; the U-Net's max pooling and up-sampling. (Batch norm + LeakyReLU and the micro-kernels are
//! tested beside their code.)

use candle_core::{Device, Tensor, Var};
use ic_nn::ops::attention::{multi_head_attention, multi_head_attention_reference};
use ic_nn::ops::gather::{neighbour_max, neighbour_max_add, neighbour_max_reference};
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
    // Head widths that take the micro-kernels (multiples of 8: 32 as in the `cpu` preset, and
    // 40 = 32 + 8 column groups), with ragged row tiles and key panels.
    check(2, 45, 37, 64, 2, 0.5);
    check(1, 67, 130, 80, 2, 0.5);
    check(2, 5, 3, 16, 2, 1.0);
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

/// A `[B, P·k]` graph with `k` distinct random neighbours per point, as in a k-NN graph.
fn random_graph(b: usize, p: usize, k: usize, seed: u64) -> Tensor {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut graph: Vec<u32> = Vec::with_capacity(b * p * k);
    for _ in 0..b * p {
        let mut ids: Vec<u32> = (0..p as u32).collect();
        for r in 0..k {
            let s = rng.random_range(r..p);
            ids.swap(r, s);
        }
        graph.extend(&ids[..k]);
    }
    Tensor::from_vec(graph, (b, p * k), &Device::Cpu).unwrap()
}

#[test]
fn fused_neighbour_max_matches_gather_and_max() {
    // 150 points: several parallel tasks of the channel-last gather.
    for (b, c, p, k) in [(2, 5, 40, 6), (2, 9, 150, 16)] {
        let a = Var::from_tensor(&randn((b, c, p), 1.0, 7)).unwrap();
        let graph = random_graph(b, p, k, 8);
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
        assert_eq!(fo, ro, "values, {p} points");
        assert!(max_rel_diff(&fg, &rg) < 1e-6, "gradient, {p} points");
    }
}

#[test]
fn fused_neighbour_max_sends_a_tied_output_gradient_to_one_neighbour() {
    // Features rounded to integers tie often: the values still match the reference, and each
    // output's gradient goes to exactly one neighbour (the reference's goes to every tied one).
    let (b, c, p, k) = (1, 4, 100, 8);
    let a = randn((b, c, p), 1.0, 5)
        .affine(2.0, 0.0)
        .unwrap()
        .round()
        .unwrap();
    let a = Var::from_tensor(&a).unwrap();
    let graph = random_graph(b, p, k, 6);
    let out = neighbour_max(&a, &graph, k).unwrap();
    assert_eq!(
        flat(&out),
        flat(&neighbour_max_reference(&a, &graph, k).unwrap())
    );
    let grads = out.sum_all().unwrap().backward().unwrap();
    let g = flat(grads.get(a.as_tensor()).expect("gradient"));
    assert_eq!(g.iter().sum::<f32>(), (b * c * p) as f32);
}

#[test]
fn fused_neighbour_max_add_matches_gather_max_and_add_with_both_gradients() {
    let (b, c, p, k) = (2, 9, 150, 16);
    let a = Var::from_tensor(&randn((b, c, p), 1.0, 11)).unwrap();
    let centre = Var::from_tensor(&randn((b, c, p), 1.0, 12)).unwrap();
    let graph = random_graph(b, p, k, 13);
    let w = randn((b, c, p), 1.0, 14);
    let run = |fused: bool| {
        let out = if fused {
            neighbour_max_add(&a, &graph, k, &centre)
        } else {
            neighbour_max_reference(&a, &graph, k).unwrap() + centre.as_tensor()
        }
        .unwrap();
        let grads = (&out * &w).unwrap().sum_all().unwrap().backward().unwrap();
        (
            flat(&out),
            flat(grads.get(a.as_tensor()).expect("feature gradient")),
            flat(grads.get(centre.as_tensor()).expect("centre gradient")),
        )
    };
    let (fo, fa, fc) = run(true);
    let (ro, ra, rc) = run(false);
    assert_eq!(fo, ro, "values");
    assert!(max_rel_diff(&fa, &ra) < 1e-6, "feature gradient");
    assert_eq!(fc, rc, "centre gradient");
    let bad_centre = randn((b, c, p + 1), 1.0, 15);
    assert!(neighbour_max_add(&a, &graph, k, &bad_centre).is_err());
}

#[test]
fn neighbour_max_rejects_out_of_range_neighbours() {
    let a = randn((1, 2, 4), 1.0, 1);
    let graph = Tensor::from_vec(vec![0u32, 1, 2, 9], (1, 4), &Device::Cpu).unwrap();
    assert!(neighbour_max(&a, &graph, 1).is_err());
}

/// Variables of the given shapes set to random values, seeded 100, 101, … in the order given
/// (the order of their names, as the layers' variables were drawn when these tests built the
/// layers of `ic_pose`: "bias" before "weight").
fn random_vars(shapes: &[(&str, &[usize])]) -> Vec<(String, Var)> {
    shapes
        .iter()
        .enumerate()
        .map(|(i, (name, dims))| {
            let n: usize = dims.iter().product();
            let r = randn((1, 1, n), 0.5, 100 + i as u64)
                .reshape(dims.to_vec())
                .unwrap();
            (name.to_string(), Var::from_tensor(&r).unwrap())
        })
        .collect()
}

/// Output and gradients (input first, then every variable) of a weighted sum of `f(x)`.
fn value_and_grads(
    f: impl Fn(&Tensor) -> Tensor,
    x: &Var,
    vars: &[(String, Var)],
    w: &Tensor,
) -> Vec<Vec<f32>> {
    let out = f(x.as_tensor());
    let grads = (&out * w).unwrap().sum_all().unwrap().backward().unwrap();
    let mut all = vec![flat(&out), flat(grads.get(x.as_tensor()).expect("dx"))];
    for (name, v) in vars {
        all.push(flat(
            grads
                .get(v.as_tensor())
                .unwrap_or_else(|| panic!("no gradient for {name}")),
        ));
    }
    all
}

#[test]
fn fused_layer_norm_matches_tensor_ops() {
    use ic_nn::ops::norm::{layer_norm, layer_norm_reference};
    let vars = random_vars(&[("bias", &[24]), ("weight", &[24])]);
    let (bias, weight) = (vars[0].1.as_tensor().clone(), vars[1].1.as_tensor().clone());
    let x = Var::from_tensor(&randn((3, 70, 24), 2.0, 11)).unwrap();
    let w = randn((3, 70, 24), 1.0, 12);
    let fused = value_and_grads(
        |t| layer_norm(t, &weight, &bias, 1e-5).unwrap(),
        &x,
        &vars,
        &w,
    );
    let reference = value_and_grads(
        |t| layer_norm_reference(t, &weight, &bias, 1e-5).unwrap(),
        &x,
        &vars,
        &w,
    );
    for (i, (a, b)) in fused.iter().zip(&reference).enumerate() {
        assert!(max_rel_diff(a, b) < 1e-4, "layer norm output/gradient {i}");
    }
}

#[test]
fn fused_dense_matches_matmul_plus_bias() {
    use ic_nn::ops::dense::dense;
    let vars = random_vars(&[("bias", &[36]), ("weight", &[36, 20])]);
    let (bias, weight) = (vars[0].1.as_tensor().clone(), vars[1].1.as_tensor().clone());
    let x = Var::from_tensor(&randn((2, 45, 20), 1.0, 13)).unwrap();
    let w = randn((2, 45, 36), 1.0, 14);
    let fused = value_and_grads(
        |t| dense(t, &weight, Some(&bias), false).unwrap(),
        &x,
        &vars,
        &w,
    );
    let reference = value_and_grads(
        |t| {
            t.broadcast_matmul(&weight.t().unwrap())
                .unwrap()
                .broadcast_add(&bias)
                .unwrap()
        },
        &x,
        &vars,
        &w,
    );
    for (i, (a, b)) in fused.iter().zip(&reference).enumerate() {
        assert!(max_rel_diff(a, b) < 1e-5, "dense output/gradient {i}");
    }
}

#[test]
fn fused_dense_relu_matches_tensor_ops() {
    use ic_nn::ops::dense::{dense, dense_reference};
    let vars = random_vars(&[("bias", &[24]), ("weight", &[24, 16])]);
    let (bias, weight) = (vars[0].1.as_tensor().clone(), vars[1].1.as_tensor().clone());
    let x = Var::from_tensor(&randn((3, 30, 16), 1.0, 15)).unwrap();
    let w = randn((3, 30, 24), 1.0, 16);
    let fused = value_and_grads(
        |t| dense(t, &weight, Some(&bias), true).unwrap(),
        &x,
        &vars,
        &w,
    );
    let reference = value_and_grads(
        |t| dense_reference(t, &weight, Some(&bias), true).unwrap(),
        &x,
        &vars,
        &w,
    );
    for (i, (a, b)) in fused.iter().zip(&reference).enumerate() {
        assert!(
            max_rel_diff(a, b) < 1e-5,
            "dense + ReLU output/gradient {i}"
        );
    }
}

#[test]
fn fused_channel_linear_matches_broadcast_matmul() {
    let wv = Var::from_tensor(&randn((1, 12, 7), 1.0, 21).reshape((12, 7)).unwrap()).unwrap();
    let x = Var::from_tensor(&randn((3, 7, 50), 1.0, 22)).unwrap();
    let g = randn((3, 12, 50), 1.0, 23);
    let run = |fused: bool| {
        let y = if fused {
            ic_nn::ops::dense::channel_linear(&wv, &x).unwrap()
        } else {
            ic_nn::ops::dense::channel_linear_reference(&wv, &x).unwrap()
        };
        let grads = (&y * &g).unwrap().sum_all().unwrap().backward().unwrap();
        vec![
            flat(&y),
            flat(grads.get(wv.as_tensor()).unwrap()),
            flat(grads.get(x.as_tensor()).unwrap()),
        ]
    };
    for (i, (a, b)) in run(true).iter().zip(&run(false)).enumerate() {
        assert!(
            max_rel_diff(a, b) < 1e-5,
            "channel linear output/gradient {i}"
        );
    }
}

/// `[B, C, H, W]` values on a coarse grid (steps of 0.5 in [−2, 2]), so that 2×2 windows
/// often hold their max twice or more.
fn coarse_image(dims: (usize, usize, usize, usize), seed: u64) -> Tensor {
    let n = dims.0 * dims.1 * dims.2 * dims.3;
    let v: Vec<f32> = flat(&randn((1, 1, n), 1.0, seed))
        .iter()
        .map(|x| (x * 2.0).round().clamp(-4.0, 4.0) / 2.0)
        .collect();
    Tensor::from_vec(v, dims, &Device::Cpu).unwrap()
}

#[test]
fn fused_max_pool_matches_tensor_ops_with_ties_in_value_and_gradient() {
    use ic_nn::ops::pool::{max_pool2, max_pool2_reference};
    let x = Var::from_tensor(&coarse_image((2, 3, 6, 8), 21)).unwrap();
    let w = randn((2, 3, 12), 1.0, 22).reshape((2, 3, 3, 4)).unwrap();
    let fused = value_and_grads(|t| max_pool2(t).unwrap(), &x, &[], &w);
    let reference = value_and_grads(|t| max_pool2_reference(t).unwrap(), &x, &[], &w);
    // Ties are common on this grid: every tied input gets the gradient, as in candle's max.
    let xv = flat(x.as_tensor());
    let tied = (0..2 * 3 * 3 * 4)
        .filter(|&o| {
            let (p, i, j) = (o / 12, (o % 12) / 4, o % 4);
            let at = |r: usize, c: usize| xv[p * 48 + r * 8 + c];
            let win = [
                at(2 * i, 2 * j),
                at(2 * i, 2 * j + 1),
                at(2 * i + 1, 2 * j),
                at(2 * i + 1, 2 * j + 1),
            ];
            let m = win.iter().cloned().fold(f32::MIN, f32::max);
            win.iter().filter(|&&v| v == m).count() > 1
        })
        .count();
    assert!(tied > 5, "only {tied} tied windows");
    assert_eq!(fused, reference);
}

#[test]
fn fused_upsample_matches_the_broadcast_in_value_and_gradient() {
    use ic_nn::ops::pool::{upsample2, upsample2_reference};
    let x = Var::from_tensor(&randn((2, 3, 20), 1.0, 23).reshape((2, 3, 4, 5)).unwrap()).unwrap();
    let w = randn((2, 3, 80), 1.0, 24).reshape((2, 3, 8, 10)).unwrap();
    let fused = value_and_grads(|t| upsample2(t).unwrap(), &x, &[], &w);
    let reference = value_and_grads(|t| upsample2_reference(t).unwrap(), &x, &[], &w);
    // The same four gradients summed in the same order: equal, not merely close.
    assert_eq!(fused, reference);
}

#[test]
fn max_pool_rejects_an_odd_side() {
    let x = Tensor::zeros((1, 2, 5, 4), candle_core::DType::F32, &Device::Cpu).unwrap();
    let err = ic_nn::ops::pool::max_pool2(&x).unwrap_err().to_string();
    assert!(err.contains("5×4") && err.contains("even"), "{err}");
}
