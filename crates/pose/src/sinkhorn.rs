//! Log-domain Sinkhorn optimal-transport layer with outlier bins (paper §3, "Dealing with noisy
//! target points", Algorithm 1).
//!
//! See [`log_optimal_transport`] for the exact semantics.

use candle_core::{Result, Tensor};

/// Builds the augmented, temperature-scaled score matrix Z = S̄ / λ, `[B, M+1, N+1]`.
fn augmented_scaled(scores: &Tensor, alpha: f32, lambda: f32) -> Result<Tensor> {
    let (b, m, n) = scores.dims3()?;
    let dtype = scores.dtype();
    let device = scores.device();
    let col = Tensor::full(alpha, (b, m, 1), device)?.to_dtype(dtype)?;
    let row = Tensor::full(alpha, (b, 1, n + 1), device)?.to_dtype(dtype)?;
    let s = Tensor::cat(&[scores, &col], 2)?;
    let s = Tensor::cat(&[&s, &row], 1)?;
    s.affine(1.0 / lambda as f64, 0.0)
}

/// The log marginals log a = [0_M, ln N] and log b = [0_N, ln M] as `[M+1]` and `[N+1]` vectors.
fn log_marginals(m: usize, n: usize) -> (Vec<f32>, Vec<f32>) {
    let mut la = vec![0.0f32; m + 1];
    la[m] = (n as f32).ln();
    let mut lb = vec![0.0f32; n + 1];
    lb[n] = (m as f32).ln();
    (la, lb)
}

/// Numerically stable log-sum-exp over `dim` (kept), with the max *detached* so that autograd
/// differentiates only through the exp/sum/log branch (its gradient is exactly the softmax).
fn lse_keepdim(x: &Tensor, dim: usize) -> Result<Tensor> {
    let m = x.max_keepdim(dim)?.detach();
    x.broadcast_sub(&m)?.exp()?.sum_keepdim(dim)?.log()?.broadcast_add(&m)
}

fn check_args(scores: &Tensor, lambda: f32) -> Result<(usize, usize, usize)> {
    let (b, m, n) = scores.dims3()?;
    if m == 0 || n == 0 {
        candle_core::bail!("log_optimal_transport: empty score matrix [{b}, {m}, {n}]");
    }
    if !(lambda > 0.0) || !lambda.is_finite() {
        candle_core::bail!("log_optimal_transport: lambda must be positive and finite, got {lambda}");
    }
    Ok((b, m, n))
}

/// Reference implementation of [`log_optimal_transport`] built only from generic candle tensor
/// ops (so it is differentiable through candle's autograd on every device and dtype). Same
/// signature and semantics; used as the test oracle and as the fallback on non-CPU devices.
pub fn log_optimal_transport_reference(
    scores: &Tensor,
    alpha: f32,
    lambda: f32,
    iterations: usize,
) -> Result<Tensor> {
    let (b, m, n) = check_args(scores, lambda)?;
    let dtype = scores.dtype();
    let device = scores.device();
    let z = augmented_scaled(scores, alpha, lambda)?;
    let (la, lb) = log_marginals(m, n);
    let log_a = Tensor::from_vec(la, (1, m + 1, 1), device)?.to_dtype(dtype)?;
    let log_b = Tensor::from_vec(lb, (1, 1, n + 1), device)?.to_dtype(dtype)?;
    let mut log_u = Tensor::zeros((b, m + 1, 1), dtype, device)?;
    let mut log_v = Tensor::zeros((b, 1, n + 1), dtype, device)?;
    for _ in 0..iterations {
        log_u = log_a.broadcast_sub(&lse_keepdim(&z.broadcast_add(&log_v)?, 2)?)?;
        log_v = log_b.broadcast_sub(&lse_keepdim(&z.broadcast_add(&log_u)?, 1)?)?;
    }
    z.broadcast_add(&log_u)?.broadcast_add(&log_v)
}

/// log P̄ of the augmented assignment, `[B, M+1, N+1]`, from scores S `[B, M, N]`.
pub fn log_optimal_transport(
    scores: &Tensor,
    alpha: f32,
    lambda: f32,
    iterations: usize,
) -> Result<Tensor> {
    log_optimal_transport_reference(scores, alpha, lambda, iterations)
}
