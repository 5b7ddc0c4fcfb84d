//! Hand-vectorisable numerics shared by the fused CPU kernels ([`crate::sinkhorn`],
//! [`crate::attention`]): a branch-free f32 `exp`, run-time AVX2/FMA detection, and a checked
//! wrapper around the `gemm` crate (the GEMM candle itself uses) for strided f32 products.

#[inline(always)]
pub(crate) fn fmadd<const F: bool>(a: f32, b: f32, c: f32) -> f32 {
    if F { a.mul_add(b, c) } else { a * b + c }
}

/// exp(x) in f32 (Cephes-style range reduction + degree-7 polynomial, ≈ 1–2 ulp), branch-free
/// so that it vectorises; returns exactly 0 below −87 (including −∞) and saturates at e^88.
#[allow(clippy::excessive_precision)]
#[inline(always)]
pub fn exp_approx<const F: bool>(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_375; // exact in f32: n·LN2_HI is exact
    const LN2_LO: f32 = -2.121_944_4e-4;
    const SHIFTER: f32 = 12_582_912.0; // 1.5 · 2^23: adding it rounds to an integer
    let xc = x.clamp(-87.0, 88.0); // NaN stays NaN
    let kf = fmadd::<F>(xc, LOG2E, SHIFTER);
    let n = kf - SHIFTER;
    let r = fmadd::<F>(n, -LN2_HI, xc);
    let r = fmadd::<F>(n, -LN2_LO, r);
    let mut p = 1.987_569_2e-4f32;
    p = fmadd::<F>(p, r, 1.398_199_9e-3);
    p = fmadd::<F>(p, r, 8.333_452e-3);
    p = fmadd::<F>(p, r, 4.166_579_6e-2);
    p = fmadd::<F>(p, r, 1.666_666_5e-1);
    p = fmadd::<F>(p, r, 0.5);
    let y = fmadd::<F>(p, r * r, r) + 1.0;
    let ni = (kf.to_bits() as i32).wrapping_sub(SHIFTER.to_bits() as i32);
    let scale = f32::from_bits((ni.wrapping_add(127) << 23) as u32);
    let out = y * scale;
    if x < -87.0 { 0.0 } else { out }
}

/// Whether the CPU has AVX2 and FMA (the kernels then run their `target_feature` versions).
#[inline]
pub(crate) fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// A strided, read-only f32 matrix view: element (r, c) is `data[r·rs + c·cs]`.
#[derive(Clone, Copy)]
pub struct MatRef<'a> {
    pub data: &'a [f32],
    pub rows: usize,
    pub cols: usize,
    pub rs: usize,
    pub cs: usize,
}

impl<'a> MatRef<'a> {
    /// Row-major `rows × cols` with row stride `rs`.
    pub fn rows(data: &'a [f32], rows: usize, cols: usize, rs: usize) -> Self {
        MatRef {
            data,
            rows,
            cols,
            rs,
            cs: 1,
        }
    }

    /// The transpose (no copy).
    pub fn t(self) -> Self {
        MatRef {
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
            ..self
        }
    }

    fn check(&self) {
        if self.rows > 0 && self.cols > 0 {
            let last = (self.rows - 1) * self.rs + (self.cols - 1) * self.cs;
            assert!(last < self.data.len(), "matrix view out of bounds");
        }
    }
}

/// `dst = a·b` (or `dst += a·b` with `accumulate`), `dst` row-major `a.rows × b.cols` with row
/// stride `dst_rs`. Single-threaded: the callers parallelise over pairs and heads with rayon.
pub fn matmul(a: MatRef, b: MatRef, dst: &mut [f32], dst_rs: usize, accumulate: bool) {
    matmul_with(a, b, dst, dst_rs, accumulate, gemm::Parallelism::None)
}

/// [`matmul`] on rayon's threads (for one large product).
pub fn matmul_par(a: MatRef, b: MatRef, dst: &mut [f32], dst_rs: usize, accumulate: bool) {
    let threads = rayon::current_num_threads();
    let par = if threads > 1 && a.rows * b.cols * a.cols >= 1 << 18 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    matmul_with(a, b, dst, dst_rs, accumulate, par)
}

fn matmul_with(
    a: MatRef,
    b: MatRef,
    dst: &mut [f32],
    dst_rs: usize,
    accumulate: bool,
    par: gemm::Parallelism,
) {
    assert_eq!(a.cols, b.rows, "matmul: inner dimensions differ");
    let (m, n, k) = (a.rows, b.cols, a.cols);
    if m == 0 || n == 0 {
        return;
    }
    assert!(
        dst_rs >= n && (m - 1) * dst_rs + n <= dst.len(),
        "matmul: dst out of bounds"
    );
    if k == 0 {
        if !accumulate {
            for r in 0..m {
                dst[r * dst_rs..r * dst_rs + n].fill(0.0);
            }
        }
        return;
    }
    a.check();
    b.check();
    // SAFETY: every index the product touches was bounds-checked above (views and dst); dst
    // does not alias a or b (it is a distinct &mut borrow).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            dst_rs as isize,
            accumulate,
            a.data.as_ptr(),
            a.cs as isize,
            a.rs as isize,
            b.data.as_ptr(),
            b.cs as isize,
            b.rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            par,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strided_matmul_matches_the_definition() {
        // a: 3×4 stored with row stride 6; b = cᵀ with c 5×4 row-major.
        let a_data: Vec<f32> = (0..18).map(|i| (i as f32 * 0.37).sin()).collect();
        let c_data: Vec<f32> = (0..20).map(|i| (i as f32 * 0.11).cos()).collect();
        let a = MatRef::rows(&a_data, 3, 4, 6);
        let b = MatRef::rows(&c_data, 5, 4, 4).t();
        let mut dst = vec![1.0f32; 3 * 7];
        matmul(a, b, &mut dst, 7, true);
        for r in 0..3 {
            for c in 0..5 {
                let want: f32 = 1.0
                    + (0..4)
                        .map(|k| a_data[r * 6 + k] * c_data[c * 4 + k])
                        .sum::<f32>();
                assert!((dst[r * 7 + c] - want).abs() < 1e-5);
            }
            assert_eq!(dst[r * 7 + 5], 1.0, "untouched padding");
        }
    }
}
