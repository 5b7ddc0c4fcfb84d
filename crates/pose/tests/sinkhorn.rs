//! Tests of the log-domain Sinkhorn OT layer (`ic_pose::sinkhorn`): marginals, fused op ==
//! reference (value and gradient), gradient == finite differences (f64), degenerate inputs.

use candle_core::{DType, Device, Tensor, Var};
use ic_pose::sinkhorn::{log_optimal_transport, log_optimal_transport_reference};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const ALPHA: f32 = 0.01;
const LAMBDA: f32 = 0.5;
const K: usize = 50;

/// Standard-normal-ish values (sum of uniforms) scaled by `scale`.
fn randn(n: usize, scale: f32, seed: u64) -> Vec<f32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let s: f32 = (0..4).map(|_| rng.random_range(-1.0f32..1.0)).sum();
            s * 0.866 * scale
        })
        .collect()
}

fn scores(b: usize, m: usize, n: usize, scale: f32, seed: u64) -> Tensor {
    Tensor::from_vec(randn(b * m * n, scale, seed), (b, m, n), &Device::Cpu).unwrap()
}

fn flat(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn max_abs(a: &[f32]) -> f32 {
    a.iter().map(|x| x.abs()).fold(0.0, f32::max)
}

/// Max deviation of the row / column sums of exp(log P̄) from a = [1_M, N], b = [1_N, M].
fn marginal_err(lp: &Tensor) -> f32 {
    let (_, m1, n1) = lp.dims3().unwrap();
    let (m, n) = (m1 - 1, n1 - 1);
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

/// d/dS of sum(log P̄ ⊙ W) through `f`.
fn grad_of(
    f: fn(&Tensor, f32, f32, usize) -> candle_core::Result<Tensor>,
    s: &Tensor,
    w: &Tensor,
    k: usize,
) -> (Vec<f32>, Vec<f32>) {
    let var = Var::from_tensor(s).unwrap();
    let lp = f(var.as_tensor(), ALPHA, LAMBDA, k).unwrap();
    let loss = (&lp * w).unwrap().sum_all().unwrap();
    let grads = loss.backward().unwrap();
    let g = grads
        .get(var.as_tensor())
        .expect("no gradient for the scores");
    (flat(&lp), flat(g))
}

fn upstream(b: usize, m: usize, n: usize, seed: u64) -> Tensor {
    Tensor::from_vec(
        randn(b * (m + 1) * (n + 1), 1.0, seed),
        (b, m + 1, n + 1),
        &Device::Cpu,
    )
    .unwrap()
}

#[test]
fn marginals_match_a_and_b() {
    for &(b, m, n, seed) in &[(2, 7, 5, 1u64), (1, 64, 48, 2), (2, 300, 200, 3)] {
        let s = scores(b, m, n, 1.0, seed);
        for f in [log_optimal_transport, log_optimal_transport_reference] {
            let lp = f(&s, ALPHA, LAMBDA, K).unwrap();
            assert_eq!(lp.dims(), &[b, m + 1, n + 1]);
            let err = marginal_err(&lp);
            assert!(err < 1e-3, "marginal error {err} at B={b} M={m} N={n}");
        }
    }
}

#[test]
fn fused_matches_reference_value() {
    // The last case exceeds the parallel grain (rows split over rayon tasks); the second has
    // rows shorter than one vector lane block and the third a non-multiple of the lane width.
    for &(b, m, n, seed) in &[
        (2, 7, 5, 4u64),
        (3, 1, 1, 5),
        (1, 64, 48, 6),
        (2, 200, 150, 7),
    ] {
        let s = scores(b, m, n, 1.0, seed);
        let fused = flat(&log_optimal_transport(&s, ALPHA, LAMBDA, K).unwrap());
        let refr = flat(&log_optimal_transport_reference(&s, ALPHA, LAMBDA, K).unwrap());
        let d = max_abs_diff(&fused, &refr);
        assert!(d < 1e-4, "value diff {d} at B={b} M={m} N={n}");
    }
}

#[test]
fn fused_matches_reference_gradient() {
    for &(b, m, n, seed) in &[
        (2, 7, 5, 8u64),
        (1, 1, 3, 9),
        (1, 64, 48, 10),
        (2, 200, 150, 11),
    ] {
        let s = scores(b, m, n, 1.0, seed);
        let w = upstream(b, m, n, seed + 100);
        let (vf, gf) = grad_of(log_optimal_transport, &s, &w, K);
        let (vr, gr) = grad_of(log_optimal_transport_reference, &s, &w, K);
        assert!(max_abs_diff(&vf, &vr) < 1e-4);
        let d = max_abs_diff(&gf, &gr);
        let scale = max_abs(&gr).max(1.0);
        assert!(
            d < 1e-4 * scale,
            "grad diff {d} (max |g| {scale}) at B={b} M={m} N={n}"
        );
    }
}

#[test]
fn gradient_matches_finite_differences() {
    // Central differences of the reference run in f64 (the same algorithm through candle ops),
    // compared with the fused op's analytic (unrolled) gradient in f32.
    let (m, n) = (4, 3);
    let s = scores(1, m, n, 1.0, 12);
    let w = upstream(1, m, n, 13);
    let (_, g_fused) = grad_of(log_optimal_transport, &s, &w, K);
    let w64 = w.to_dtype(DType::F64).unwrap();
    let s64: Vec<f64> = flat(&s).iter().map(|&x| x as f64).collect();
    let loss = |v: &[f64]| -> f64 {
        let t = Tensor::from_vec(v.to_vec(), (1, m, n), &Device::Cpu).unwrap();
        let lp = log_optimal_transport_reference(&t, ALPHA, LAMBDA, K).unwrap();
        (&lp * &w64)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    };
    let eps = 1e-5;
    for i in 0..m * n {
        let mut p = s64.clone();
        p[i] += eps;
        let mut q = s64.clone();
        q[i] -= eps;
        let fd = (loss(&p) - loss(&q)) / (2.0 * eps);
        let g = g_fused[i] as f64;
        assert!(
            (g - fd).abs() <= 1e-3 * fd.abs().max(1.0),
            "entry {i}: analytic {g} vs finite difference {fd}"
        );
    }
    // And the reference's own autograd in f64 agrees with the same differences (detached max).
    let var =
        Var::from_tensor(&Tensor::from_vec(s64.clone(), (1, m, n), &Device::Cpu).unwrap()).unwrap();
    let lp = log_optimal_transport_reference(var.as_tensor(), ALPHA, LAMBDA, K).unwrap();
    let grads = (&lp * &w64).unwrap().sum_all().unwrap().backward().unwrap();
    let g64: Vec<f64> = grads
        .get(var.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    for (i, &g) in g64.iter().enumerate() {
        let mut p = s64.clone();
        p[i] += eps;
        let mut q = s64.clone();
        q[i] -= eps;
        let fd = (loss(&p) - loss(&q)) / (2.0 * eps);
        assert!(
            (g - fd).abs() <= 1e-6 * fd.abs().max(1.0),
            "reference entry {i}: {g} vs {fd}"
        );
    }
}

/// Output and gradient have no NaN; output entries are finite except where the score is −∞.
fn assert_sane(s: &Tensor, label: &str) {
    let (b, m, n) = s.dims3().unwrap();
    let w = upstream(b, m, n, 77);
    for (name, f) in [
        (
            "fused",
            log_optimal_transport as fn(&Tensor, f32, f32, usize) -> _,
        ),
        ("reference", log_optimal_transport_reference),
    ] {
        let (v, g) = grad_of(f, s, &w, K);
        let sv = flat(s);
        for (idx, &x) in v.iter().enumerate() {
            let (i, j) = ((idx / (n + 1)) % (m + 1), idx % (n + 1));
            let neg_inf_score = i < m
                && j < n
                && sv[(idx / ((m + 1) * (n + 1))) * m * n + i * n + j] == f32::NEG_INFINITY;
            if neg_inf_score {
                assert_eq!(x, f32::NEG_INFINITY, "{label}/{name}: entry {idx}");
            } else {
                assert!(x.is_finite(), "{label}/{name}: value {x} at {idx}");
            }
        }
        assert!(
            g.iter().all(|x| x.is_finite()),
            "{label}/{name}: non-finite gradient"
        );
    }
}

#[test]
fn degenerate_inputs_stay_finite() {
    let dev = &Device::Cpu;
    assert_sane(
        &Tensor::zeros((2, 6, 4), DType::F32, dev).unwrap(),
        "all zero",
    );
    assert_sane(&Tensor::full(3.0f32, (1, 9, 9), dev).unwrap(), "all equal");
    assert_sane(&scores(1, 20, 15, 1e4, 20), "huge");
    assert_sane(
        &Tensor::full(-1e4f32, (1, 5, 3), dev).unwrap(),
        "huge negative",
    );
    assert_sane(&scores(2, 1, 6, 1.0, 21), "M = 1");
    assert_sane(&scores(2, 6, 1, 1.0, 22), "N = 1");
    assert_sane(&scores(1, 1, 1, 1.0, 23), "M = N = 1");
    let mut v = randn(6 * 5, 1.0, 24);
    v[3] = f32::NEG_INFINITY;
    for x in &mut v[10..15] {
        *x = f32::NEG_INFINITY; // a whole row that can only go to the bin
    }
    assert_sane(&Tensor::from_vec(v, (1, 6, 5), dev).unwrap(), "-inf");
    // The all-equal case is symmetric: every real entry gets the same probability.
    let lp = flat(
        &log_optimal_transport(
            &Tensor::zeros((1, 5, 5), DType::F32, dev).unwrap(),
            ALPHA,
            LAMBDA,
            K,
        )
        .unwrap(),
    );
    let first = lp[0];
    for i in 0..5 {
        for j in 0..5 {
            assert!((lp[i * 6 + j] - first).abs() < 1e-5);
        }
    }
}

#[test]
fn huge_scores_match_reference() {
    let s = scores(1, 20, 15, 1e4, 30);
    let fused = flat(&log_optimal_transport(&s, ALPHA, LAMBDA, K).unwrap());
    let refr = flat(&log_optimal_transport_reference(&s, ALPHA, LAMBDA, K).unwrap());
    // log P̄ entries are O(1e4) here, so compare relative to that magnitude.
    let d = max_abs_diff(&fused, &refr);
    assert!(d <= 1e-6 * max_abs(&refr).max(1.0) * 10.0, "diff {d}");
}

#[test]
fn batch_pairs_are_independent() {
    let s = scores(3, 30, 20, 1.0, 40);
    let all = flat(&log_optimal_transport(&s, ALPHA, LAMBDA, K).unwrap());
    for b in 0..3 {
        let one =
            flat(&log_optimal_transport(&s.narrow(0, b, 1).unwrap(), ALPHA, LAMBDA, K).unwrap());
        assert_eq!(&all[b * 31 * 21..(b + 1) * 31 * 21], &one[..]);
    }
}

#[test]
fn non_contiguous_input_and_zero_iterations() {
    let s = scores(1, 9, 12, 1.0, 50);
    let t = s.transpose(1, 2).unwrap(); // [1, 12, 9], strided
    let fused = flat(&log_optimal_transport(&t, ALPHA, LAMBDA, K).unwrap());
    let refr = flat(&log_optimal_transport_reference(&t, ALPHA, LAMBDA, K).unwrap());
    assert!(max_abs_diff(&fused, &refr) < 1e-4);
    // k = 0: log P̄ is just Z = S̄/λ, and the gradient is W/λ on the real entries.
    let w = upstream(1, 9, 12, 51);
    let (v0, g0) = grad_of(log_optimal_transport, &s, &w, 0);
    let (r0, h0) = grad_of(log_optimal_transport_reference, &s, &w, 0);
    assert!(max_abs_diff(&v0, &r0) < 1e-6);
    assert!(max_abs_diff(&g0, &h0) < 1e-6);
    assert!((v0[12] - ALPHA / LAMBDA).abs() < 1e-7);
}

#[test]
fn scaled_forward_matches_log_domain_forward() {
    use ic_pose::sinkhorn::log_optimal_transport_with;
    // Ordinary, peaked and huge score ranges (the huge ones underflow the scaled sums and take
    // the exact log-domain fallback), and a pair with −∞ entries.
    for (scale, seed) in [(0.3f32, 31u64), (1.0, 32), (8.0, 33), (1e4, 34)] {
        let s = scores(2, 70, 45, scale, seed);
        let a = flat(&log_optimal_transport_with(&s, ALPHA, LAMBDA, K, true).unwrap());
        let b = flat(&log_optimal_transport_with(&s, ALPHA, LAMBDA, K, false).unwrap());
        let tol = 1e-4 * max_abs(&b).max(1.0);
        assert!(
            max_abs_diff(&a, &b) <= tol,
            "scale {scale}: {} > {tol}",
            max_abs_diff(&a, &b)
        );
    }
    let mut v = randn(30 * 20, 1.0, 35);
    for x in v.iter_mut().step_by(7) {
        *x = f32::NEG_INFINITY;
    }
    let s = Tensor::from_vec(v, (1, 30, 20), &Device::Cpu).unwrap();
    let a = flat(&log_optimal_transport_with(&s, ALPHA, LAMBDA, K, true).unwrap());
    let b = flat(&log_optimal_transport_with(&s, ALPHA, LAMBDA, K, false).unwrap());
    for (x, y) in a.iter().zip(&b) {
        assert!(
            x == y || (x - y).abs() <= 1e-4 * y.abs().max(1.0),
            "{x} vs {y}"
        );
    }
}
