//! Hand-vectorisable numerics shared by the fused CPU kernels ([`super::attention`], the
//! Sinkhorn layer of `ic_pose`): a branch-free f32 `exp`, a checked wrapper around the `gemm`
//! crate (the GEMM candle itself uses) for strided f32 products, and register-tiled
//! micro-kernels for products with a short (8·k-wide) inner or outer dimension.

use super::{MatMut, MatRef};

/// `a·b + c`, fused (one rounding) when `F`.
#[inline(always)]
pub fn fmadd<const F: bool>(a: f32, b: f32, c: f32) -> f32 {
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

/// `dst = a·b` (or `dst += a·b` with `accumulate`) for `a` `m × k`, `b` `k × n` (any strides)
/// and `dst` `m × n`. Single-threaded: the callers parallelise over pairs and heads with rayon.
///
/// # Panics
/// If the shapes do not fit together.
pub fn matmul(a: MatRef, b: MatRef, dst: MatMut, accumulate: bool) {
    matmul_with(a, b, dst, accumulate, gemm::Parallelism::None)
}

/// [`matmul`] on rayon's threads (for one large product: at least 2¹⁸ multiply-adds).
pub fn matmul_par(a: MatRef, b: MatRef, dst: MatMut, accumulate: bool) {
    let threads = rayon::current_num_threads();
    let par = if threads > 1 && a.rows() * b.cols() * a.cols() >= 1 << 18 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    matmul_with(a, b, dst, accumulate, par)
}

fn matmul_with(a: MatRef, b: MatRef, mut dst: MatMut, accumulate: bool, par: gemm::Parallelism) {
    assert_eq!(a.cols(), b.rows(), "matmul: inner dimensions differ");
    let (m, n, k) = (a.rows(), b.cols(), a.cols());
    assert!(
        dst.rows() == m && dst.cols() == n,
        "matmul: dst is {}×{}, the product {m}×{n}",
        dst.rows(),
        dst.cols()
    );
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            for r in 0..m {
                dst.row_mut(r).fill(0.0);
            }
        }
        return;
    }
    let dst_rs = dst.row_stride();
    // SAFETY: the three views are in bounds by construction (every element (r, c) of a, b and
    // dst that the product touches, at the strides given); dst does not alias a or b (it is a
    // distinct &mut borrow); gemm reads a and b and writes only the m × n elements of dst.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.data_mut().as_mut_ptr(),
            1,
            dst_rs as isize,
            accumulate,
            a.data().as_ptr(),
            a.col_stride() as isize,
            a.row_stride() as isize,
            b.data().as_ptr(),
            b.col_stride() as isize,
            b.row_stride() as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            par,
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Micro-kernels for products with a short inner or outer dimension (the attention heads: 32
// channels in the `cpu` preset), where the general GEMM spends most of its time packing.

/// Rows of `b` per panel of [`Panels`].
pub const PANEL: usize = 16;

/// A matrix `b` (`rows × cols`) packed for [`dot_rows_panels`]: panels of [`PANEL`] rows,
/// transposed, `data[p·cols·PANEL + c·PANEL + l] = b[p·PANEL + l][c]` (zero past the last row).
#[derive(Clone, Debug, Default)]
pub struct Panels {
    data: Vec<f32>,
    rows: usize,
    cols: usize,
}

impl Panels {
    /// Packs any strided view (e.g. the transpose of a point-major head).
    pub fn pack(b: MatRef) -> Self {
        let mut p = Panels::default();
        p.repack(b);
        p
    }

    /// Packs `b` into this buffer (reusing its allocation).
    pub fn repack(&mut self, b: MatRef) {
        let (rows, cols) = (b.rows(), b.cols());
        let panels = rows.div_ceil(PANEL);
        self.rows = rows;
        self.cols = cols;
        self.data.clear();
        self.data.resize(panels * cols * PANEL, 0.0);
        for r in 0..rows {
            let (p, l) = (r / PANEL, r % PANEL);
            let base = p * cols * PANEL + l;
            for c in 0..cols {
                self.data[base + c * PANEL] = b.at(r, c);
            }
        }
    }

    /// Rows of the packed matrix.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Columns of the packed matrix.
    pub fn cols(&self) -> usize {
        self.cols
    }
}

/// Rows of `a` per micro-tile of [`dot_rows_panels`].
const DOT_ROWS: usize = 6;

/// One full `DOT_ROWS × PANEL` tile: no bounds checks (and so no panic path) in the loop, which
/// lets the compiler keep the twelve accumulators in registers.
///
/// # Safety
/// `a` must point at `DOT_ROWS` rows of `cols` readable values with row stride `ars`, and
/// `panel` at `cols·PANEL` readable values.
#[inline(always)]
unsafe fn dot_tile<const F: bool>(
    a: *const f32,
    ars: usize,
    cols: usize,
    panel: *const f32,
) -> [[f32; PANEL]; DOT_ROWS] {
    let mut acc = [[0.0f32; PANEL]; DOT_ROWS];
    for c in 0..cols {
        // SAFETY: c < cols, so the PANEL values at c·PANEL lie within the cols·PANEL readable
        // values the caller promises at `panel`; f32 arrays have the alignment of f32.
        let kv: &[f32; PANEL] = unsafe { &*(panel.add(c * PANEL) as *const [f32; PANEL]) };
        for (i, acc_i) in acc.iter_mut().enumerate() {
            // SAFETY: i < DOT_ROWS and c < cols: within the rows the caller promises at `a`.
            let q = unsafe { *a.add(i * ars + c) };
            for l in 0..PANEL {
                acc_i[l] = fmadd::<F>(q, kv[l], acc_i[l]);
            }
        }
    }
    acc
}

/// The portable (`F = false`) or FMA (`F = true`) body of [`dot_rows_panels`].
///
/// # Panics
/// As [`dot_rows_panels`].
#[inline(always)]
pub fn dot_rows_panels_generic<const F: bool>(a: MatRef, panels: &Panels, mut dst: MatMut) {
    let (rows, cols, n) = (a.rows(), a.cols(), panels.rows);
    assert!(
        a.is_row_major() && cols == panels.cols,
        "dot_rows_panels: a {rows}×{cols} (column stride {}) against panels of {} columns",
        a.col_stride(),
        panels.cols
    );
    assert!(
        dst.rows() == rows && dst.cols() == n,
        "dot_rows_panels: dst {}×{}, product {rows}×{n}",
        dst.rows(),
        dst.cols()
    );
    let (ad, ars) = (a.data(), a.row_stride());
    for r0 in (0..rows).step_by(DOT_ROWS) {
        let rr = DOT_ROWS.min(rows - r0);
        for p in 0..n.div_ceil(PANEL) {
            let panel = &panels.data[p * cols * PANEL..(p + 1) * cols * PANEL];
            let mut acc = [[0.0f32; PANEL]; DOT_ROWS];
            if rr == DOT_ROWS && cols > 0 {
                // SAFETY: `a` is a row-major view (asserted above) and in bounds by
                // construction, so rows r0..r0 + DOT_ROWS < rows, each of `cols` contiguous
                // values at row stride `ars`, are readable from offset r0·ars (which is then
                // inside `ad`); `panel` holds exactly cols·PANEL values.
                acc =
                    unsafe { dot_tile::<F>(ad.as_ptr().add(r0 * ars), ars, cols, panel.as_ptr()) };
            } else {
                for c in 0..cols {
                    let kv = &panel[c * PANEL..(c + 1) * PANEL];
                    for i in 0..rr {
                        let q = ad[(r0 + i) * ars + c];
                        for l in 0..PANEL {
                            acc[i][l] = fmadd::<F>(q, kv[l], acc[i][l]);
                        }
                    }
                }
            }
            let j0 = p * PANEL;
            let w = PANEL.min(n - j0);
            for (i, row) in acc.iter().enumerate().take(rr) {
                dst.row_mut(r0 + i)[j0..j0 + w].copy_from_slice(&row[..w]);
            }
        }
    }
}

crate::avx2_fma_dispatch! {
    /// `dst[r][j] = Σ_c a[r][c]·b[j][c]` for `a` `rows × cols` (row-major: column stride 1)
    /// and `b` `n × cols` packed in `panels`; `dst` is `rows × n`.
    ///
    /// # Panics
    /// If `a` is not row-major or the shapes do not fit together.
    pub fn dot_rows_panels(a: MatRef<'_>, panels: &Panels, dst: MatMut<'_>) = dot_rows_panels_generic;
}

/// Rows of the output per micro-tile of [`rows_times_matrix`].
const AXPY_ROWS: usize = 2;

/// `R` rows (from `r0`) of `l` times the `inner × W` block of `b` at `b` (row stride `brs`),
/// with no bounds checks in the loop (the accumulators stay in registers).
///
/// # Safety
/// Rows `r0..r0 + R` of `l` must exist, `l.cols()` must be `inner`, and `inner` rows of `W`
/// values at `b` (row stride `brs`) must be readable.
#[inline(always)]
unsafe fn axpy_tile<const F: bool, const W: usize, const R: usize>(
    l: MatRef,
    r0: usize,
    inner: usize,
    b: *const f32,
    brs: usize,
) -> [[f32; W]; R] {
    let mut acc = [[0.0f32; W]; R];
    let (lp, lrs, lcs) = (l.data().as_ptr(), l.row_stride(), l.col_stride());
    for t in 0..inner {
        // SAFETY: t < inner: row t of the block at `b` has W readable values (caller's
        // promise); f32 arrays have the alignment of f32.
        let bv: &[f32; W] = unsafe { &*(b.add(t * brs) as *const [f32; W]) };
        for (i, acc_i) in acc.iter_mut().enumerate() {
            // SAFETY: element (r0 + i, t) of the view `l` exists (i < R, t < inner = l.cols())
            // and views are in bounds by construction.
            let s = unsafe { *lp.add((r0 + i) * lrs + t * lcs) };
            for k in 0..W {
                acc_i[k] = fmadd::<F>(s, bv[k], acc_i[k]);
            }
        }
    }
    acc
}

/// One column group `c0..c0 + W` of [`rows_times_matrix`].
///
/// # Safety
/// `l.cols() == b.rows() > 0`, `b` is row-major, `c0 + W ≤ b.cols()` and `dst` is
/// `l.rows() × b.cols()`.
#[inline(always)]
unsafe fn rows_times_matrix_group<const F: bool, const W: usize>(
    l: MatRef,
    b: MatRef,
    c0: usize,
    dst: &mut MatMut,
    accumulate: bool,
) {
    let (rows, inner) = (l.rows(), l.cols());
    let brs = b.row_stride();
    // SAFETY: c0 < b.cols() and the view `b` is non-empty and in bounds, so offset c0 (element
    // (0, c0)) lies inside its data.
    let bp = unsafe { b.data().as_ptr().add(c0) };
    for r0 in (0..rows).step_by(AXPY_ROWS) {
        let rr = AXPY_ROWS.min(rows - r0);
        // SAFETY: rows r0..r0 + rr of `l` exist; `b` is row-major with `inner` rows, so each
        // row t < inner has the W values c0..c0 + W ≤ b.cols() readable at t·brs from `bp`.
        let acc = unsafe {
            if rr == AXPY_ROWS {
                axpy_tile::<F, W, AXPY_ROWS>(l, r0, inner, bp, brs)
            } else {
                // The ragged last tile, one row at a time.
                let mut acc = [[0.0f32; W]; AXPY_ROWS];
                for (i, acc_i) in acc.iter_mut().enumerate().take(rr) {
                    *acc_i = axpy_tile::<F, W, 1>(l, r0 + i, inner, bp, brs)[0];
                }
                acc
            }
        };
        for (i, row) in acc.iter().enumerate().take(rr) {
            let o = &mut dst.row_mut(r0 + i)[c0..c0 + W];
            if accumulate {
                for (d, v) in o.iter_mut().zip(row) {
                    *d += v;
                }
            } else {
                o.copy_from_slice(row);
            }
        }
    }
}

/// The portable (`F = false`) or FMA (`F = true`) body of [`rows_times_matrix`].
///
/// # Panics
/// As [`rows_times_matrix`].
#[inline(always)]
pub fn rows_times_matrix_generic<const F: bool>(
    l: MatRef,
    b: MatRef,
    mut dst: MatMut,
    accumulate: bool,
) {
    let cols = b.cols();
    assert!(
        cols % 8 == 0,
        "rows_times_matrix: {cols} columns is not a multiple of 8"
    );
    assert!(
        b.is_row_major() && l.cols() == b.rows(),
        "rows_times_matrix: l {}×{} times b {}×{cols} (column stride {})",
        l.rows(),
        l.cols(),
        b.rows(),
        b.col_stride()
    );
    assert!(
        dst.rows() == l.rows() && dst.cols() == cols,
        "rows_times_matrix: dst {}×{}, product {}×{cols}",
        dst.rows(),
        dst.cols(),
        l.rows()
    );
    if l.rows() == 0 || cols == 0 {
        return;
    }
    if l.cols() == 0 {
        if !accumulate {
            for r in 0..l.rows() {
                dst.row_mut(r).fill(0.0);
            }
        }
        return;
    }
    let mut c0 = 0;
    while c0 < cols {
        let left = cols - c0;
        // SAFETY: l.cols() == b.rows() > 0, b is row-major, dst is l.rows() × cols (all
        // asserted above), and each group ends at c0 + W ≤ cols (cols and c0 are multiples of
        // 8, and W ≤ left).
        unsafe {
            if left >= 32 {
                rows_times_matrix_group::<F, 32>(l, b, c0, &mut dst, accumulate);
                c0 += 32;
            } else if left >= 16 {
                rows_times_matrix_group::<F, 16>(l, b, c0, &mut dst, accumulate);
                c0 += 16;
            } else {
                rows_times_matrix_group::<F, 8>(l, b, c0, &mut dst, accumulate);
                c0 += 8;
            }
        }
    }
}

crate::avx2_fma_dispatch! {
    /// `dst (=|+=) l·b` where `l` is any strided `rows × inner` view and `b` is `inner × cols`
    /// row-major (column stride 1) with `cols` a multiple of 8; `dst` is `rows × cols`.
    ///
    /// # Panics
    /// If `cols` is not a multiple of 8, `b` is not row-major or the shapes do not fit.
    pub fn rows_times_matrix(l: MatRef<'_>, b: MatRef<'_>, dst: MatMut<'_>, accumulate: bool) = rows_times_matrix_generic;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::has_avx2_fma;

    fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n)
            .map(|i| (((i * 7919 + seed * 104_729) % 1000) as f32) / 500.0 - 1.0)
            .collect()
    }

    #[test]
    fn micro_kernels_match_the_definition_on_ragged_shapes() {
        // Rows not a multiple of the row tiles, keys not a multiple of the panel width, column
        // groups 32 + 16 + 8, a row stride larger than the width, and a transposed left factor.
        for &(rows, n, cols) in &[
            (7usize, 21usize, 8usize),
            (13, 35, 56),
            (1, 1, 16),
            (6, 16, 32),
        ] {
            let ars = cols + 3;
            let a = values(rows * ars, 1);
            let bm = values(n * ars, 2);
            let panels = Panels::pack(MatRef::new(&bm, n, cols, ars));
            for fma in [false, true] {
                let mut dst = vec![7.0f32; rows * (n + 2)];
                let av = MatRef::new(&a, rows, cols, ars);
                let dv = MatMut::new(&mut dst, rows, n, n + 2);
                if fma && has_avx2_fma() {
                    dot_rows_panels(av, &panels, dv);
                } else {
                    dot_rows_panels_generic::<false>(av, &panels, dv);
                }
                for r in 0..rows {
                    for j in 0..n {
                        let want: f32 = (0..cols).map(|c| a[r * ars + c] * bm[j * ars + c]).sum();
                        assert!(
                            (dst[r * (n + 2) + j] - want).abs() < 1e-4,
                            "dot {rows}×{n}×{cols}"
                        );
                    }
                    assert_eq!(dst[r * (n + 2) + n], 7.0, "dot wrote past its row");
                }
            }
            // l: rows × n as the transpose of an n × rows matrix; b: n × cols.
            let lt = values(n * rows, 3);
            let l = MatRef::new(&lt, n, rows, rows).t();
            for accumulate in [false, true] {
                let mut dst = vec![0.5f32; rows * (cols + 8)];
                rows_times_matrix(
                    l,
                    MatRef::new(&bm, n, cols, ars),
                    MatMut::new(&mut dst, rows, cols, cols + 8),
                    accumulate,
                );
                for r in 0..rows {
                    for c in 0..cols {
                        let want: f32 = (0..n)
                            .map(|t| lt[t * rows + r] * bm[t * ars + c])
                            .sum::<f32>()
                            + if accumulate { 0.5 } else { 0.0 };
                        assert!(
                            (dst[r * (cols + 8) + c] - want).abs() < 1e-4,
                            "rows_times {rows}×{n}×{cols}"
                        );
                    }
                    assert_eq!(
                        dst[r * (cols + 8) + cols],
                        0.5,
                        "rows_times wrote past its row"
                    );
                }
            }
        }
    }

    #[test]
    fn strided_matmul_matches_the_definition() {
        // a: 3×4 stored with row stride 6; b = cᵀ with c 5×4 row-major.
        let a_data: Vec<f32> = (0..18).map(|i| (i as f32 * 0.37).sin()).collect();
        let c_data: Vec<f32> = (0..20).map(|i| (i as f32 * 0.11).cos()).collect();
        let a = MatRef::new(&a_data, 3, 4, 6);
        let b = MatRef::new(&c_data, 5, 4, 4).t();
        let mut dst = vec![1.0f32; 3 * 7];
        matmul(a, b, MatMut::new(&mut dst, 3, 5, 7), true);
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

    #[test]
    fn exp_approx_is_accurate_on_both_paths() {
        let mut x = -87.0f32;
        while x < 88.0 {
            let want = (x as f64).exp();
            for got in [exp_approx::<false>(x) as f64, exp_approx::<true>(x) as f64] {
                assert!(
                    ((got - want) / want).abs() < 5e-7,
                    "exp({x}) = {got}, want {want}"
                );
            }
            x += 0.013;
        }
        for x in [-87.5f32, -1e4, f32::NEG_INFINITY] {
            assert_eq!(exp_approx::<false>(x), 0.0);
            assert_eq!(exp_approx::<true>(x), 0.0);
        }
        assert!(exp_approx::<false>(f32::NAN).is_nan());
    }
}
