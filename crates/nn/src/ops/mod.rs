//! The fused CPU kernels of incontext's networks, in one place.
//!
//! Every kernel here is a candle custom op (forward and hand-written backward) that runs on the
//! CPU with f32 inputs, beside a function computing the same thing from generic candle tensor
//! ops: the fallback on other devices and dtypes (so the `cuda` feature of the networks keeps
//! candle's own ops) and the oracle of the kernel's test (value and gradient).
//!
//! | module | kernels |
//! |---|---|
//! | [`fastmath`] | branch-free `exp`, a checked strided wrapper of the `gemm` crate, micro-kernels for 8·k-wide products (packed panels × row tiles, rows × matrix) |
//! | [`attention`] | fused multi-head attention (FlashAttention-style backward from saved log-sum-exps) |
//! | [`conv`] | the 2-D "same" convolution of images (im2col + GEMM on strips) |
//! | [`dense`] | `x·Wᵀ + b` (+ ReLU) and the 1×1 channel convolution |
//! | [`norm`] | layer norm over the last dimension, batch norm + LeakyReLU over `[B, C, L]` |
//! | [`softmax`] | softmax and log-softmax over the last dimension |
//! | [`gather`] | the EdgeConv gather-max over a k-NN graph (+ the centre term) |
//! | [`pool`] | the U-Net's 2×2 max pooling and 2× nearest up-sampling of images |
//! | [`cpu`] | storage slices and tensor values for the ops' glue |
//!
//! Matrices are passed as views ([`MatRef`], [`MatMut`]: slice, rows, columns, strides, checked
//! once per call) and every SIMD kernel is written once, generic over `const F: bool` (fused
//! multiply-add or not), and dispatched at run time by [`avx2_fma_dispatch!`].

pub mod attention;
pub mod conv;
pub mod cpu;
pub mod dense;
pub mod fastmath;
pub mod gather;
mod mat;
pub mod norm;
pub mod pool;
pub mod softmax;

pub use mat::{MatMut, MatRef};

/// `n` deterministic values in [−2, 2) (a multiplicative hash of the index and `seed`): the
/// inputs of the kernels' oracle tests.
#[cfg(test)]
pub(crate) fn test_values(n: usize, seed: u32) -> Vec<f32> {
    (0..n)
        .map(|i| {
            ((i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) % 1000) as f32 / 250.0 - 2.0
        })
        .collect()
}

/// Whether the CPU has AVX2 and FMA (the kernels then run their `target_feature` versions).
/// `std` caches the detection, so this is a load and a test after the first call.
#[inline]
pub fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Defines a function that runs a kernel generic over `const F: bool` (`true`: fused
/// multiply-add) compiled for AVX2 + FMA when the CPU has them (checked at run time by
/// [`ops::has_avx2_fma`](crate::ops::has_avx2_fma)), else its portable version (`F = false`).
///
/// ```ignore
/// ic_nn::avx2_fma_dispatch! {
///     /// Doc of the dispatching function.
///     pub fn scale(x: &mut [f32], s: f32) = scale_generic;
/// }
/// ```
/// defines `pub fn scale(x: &mut [f32], s: f32)` calling `scale_generic::<true>` inside a
/// `#[target_feature(enable = "avx2,fma")]` function, or `scale_generic::<false>`. The generic
/// should be `#[inline(always)]` so that it is compiled inside the AVX2 function. With
/// `unsafe fn … = generic;` the defined function and the generic are `unsafe` and the caller
/// takes on the generic's safety contract.
#[macro_export]
macro_rules! avx2_fma_dispatch {
    (
        $(#[$attr:meta])*
        $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? = $generic:ident;
    ) => {
        $(#[$attr])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn avx2($($arg: $ty),*) $(-> $ret)? {
                    $generic::<true>($($arg),*)
                }
                if $crate::ops::has_avx2_fma() {
                    // SAFETY: the CPU supports AVX2 and FMA (checked at run time just above),
                    // which is the only requirement of the `target_feature` function.
                    return unsafe { avx2($($arg),*) };
                }
            }
            $generic::<false>($($arg),*)
        }
    };
    (
        $(#[$attr:meta])*
        $vis:vis unsafe fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? = $generic:ident;
    ) => {
        $(#[$attr])*
        $vis unsafe fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                unsafe fn avx2($($arg: $ty),*) $(-> $ret)? {
                    // SAFETY: the contract of the generic kernel is the caller's, forwarded
                    // unchanged from the dispatching function.
                    unsafe { $generic::<true>($($arg),*) }
                }
                if $crate::ops::has_avx2_fma() {
                    // SAFETY: the CPU supports AVX2 and FMA (checked at run time just above);
                    // the kernel's own contract is the caller's.
                    return unsafe { avx2($($arg),*) };
                }
            }
            // SAFETY: the kernel's contract is the caller's (this function has the same one).
            unsafe { $generic::<false>($($arg),*) }
        }
    };
}

/// Environment settings for candle's own CPU thread pool that suit the fused kernels.
///
/// candle 0.11 runs its element-wise ops on a "barrier pool" whose workers spin for 25 000
/// rounds after every op before they sleep. The fused kernels here run on rayon's threads, so
/// on a 2-core machine a spinning candle worker takes a core from them: measured with
/// `benches/pose.rs` on 2 threads, a spin limit of 200 rounds cut the `cpu` training step from
/// ≈ 0.55 s to ≈ 0.42 s and the 1024×768 forward from ≈ 195 to ≈ 160 ms.
///
/// Since the heavy work moved into the fused kernels, candle's pool runs only small
/// element-wise ops (residual adds, reshapes, the head's log-softmax), and handing each to a
/// parked worker costs more than the op: one thread (`CANDLE_NUM_THREADS=1`, the op then runs
/// on the calling thread) made the bench's speed stage faster on 2 threads in one A/B run each
/// (`docs/decisions.md`, "candle's pool on one thread"): one-shot pose 384×288 8.8 → 7.8 ms,
/// 1024×768 23.2 → 15.7 ms, the `cpu` training step 117 → 107 ms (softmax) and 114 → 106 ms
/// (OT). A variable already set in the environment wins.
pub const CANDLE_CPU_ENV: [(&str, &str); 2] = [
    ("CANDLE_BARRIER_POOL_SPIN_LIMIT", "200"),
    ("CANDLE_NUM_THREADS", "1"),
];

/// Sets each of [`CANDLE_CPU_ENV`] that the environment does not already set.
///
/// # Safety
/// Writes the process environment: call it first thing in `main`, before any other thread
/// exists (candle reads the setting when its pool starts).
pub unsafe fn tune_candle_cpu_pool() {
    for (key, value) in CANDLE_CPU_ENV {
        if std::env::var_os(key).is_none() {
            // SAFETY: the caller guarantees that no other thread runs yet, so nothing reads
            // the environment concurrently.
            unsafe { std::env::set_var(key, value) };
        }
    }
}
