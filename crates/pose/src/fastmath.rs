//! Hand-vectorisable numerics shared by the fused CPU kernels ([`crate::sinkhorn`],
//! [`crate::attention`]): a branch-free f32 `exp`, run-time AVX2/FMA detection, and a checked
//! wrapper around the `gemm` crate (the GEMM candle itself uses) for strided f32 products.

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

// ---------------------------------------------------------------------------------------------
// Micro-kernels for products with a short inner or outer dimension (the attention heads: 32
// channels in the `cpu` preset), where the general GEMM spends most of its time packing.

/// Keys per panel of [`pack_panels`].
pub const PANEL: usize = 16;

/// Packs the rows of `b` (`rows × cols`, row stride `rs`) into panels of [`PANEL`] rows,
/// transposed: `out[p·cols·PANEL + c·PANEL + l] = b[p·PANEL + l][c]` (zero past the last row).
pub fn pack_panels(b: &[f32], rows: usize, cols: usize, rs: usize, out: &mut Vec<f32>) {
    pack_panels_view(MatRef::rows(b, rows, cols, rs), out)
}

/// [`pack_panels`] of any strided view (e.g. the transpose of a point-major head).
pub fn pack_panels_view(b: MatRef, out: &mut Vec<f32>) {
    let (rows, cols) = (b.rows, b.cols);
    let panels = rows.div_ceil(PANEL);
    out.clear();
    out.resize(panels * cols * PANEL, 0.0);
    if rows == 0 || cols == 0 {
        return;
    }
    b.check();
    for r in 0..rows {
        let (p, l) = (r / PANEL, r % PANEL);
        let base = p * cols * PANEL + l;
        for c in 0..cols {
            out[base + c * PANEL] = b.data[r * b.rs + c * b.cs];
        }
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
        // SAFETY: within the bounds promised by the caller.
        let kv: &[f32; PANEL] = unsafe { &*(panel.add(c * PANEL) as *const [f32; PANEL]) };
        for (i, acc_i) in acc.iter_mut().enumerate() {
            let q = unsafe { *a.add(i * ars + c) };
            for l in 0..PANEL {
                acc_i[l] = fmadd::<F>(q, kv[l], acc_i[l]);
            }
        }
    }
    acc
}

/// `dst[r][j] = Σ_c a[r][c] · b[j][c]` for `r < rows`, `j < n`, with `b` packed by
/// [`pack_panels`] (`cols` columns); `a` row-major with row stride `ars`, `dst` with row
/// stride `drs`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn dot_rows_panels_generic<const F: bool>(
    a: &[f32],
    rows: usize,
    cols: usize,
    ars: usize,
    panels: &[f32],
    n: usize,
    dst: &mut [f32],
    drs: usize,
) {
    for r0 in (0..rows).step_by(DOT_ROWS) {
        let rr = DOT_ROWS.min(rows - r0);
        for p in 0..n.div_ceil(PANEL) {
            let panel = &panels[p * cols * PANEL..(p + 1) * cols * PANEL];
            let mut acc = [[0.0f32; PANEL]; DOT_ROWS];
            if rr == DOT_ROWS {
                // SAFETY: rows r0..r0 + DOT_ROWS of `a` (each `cols` long, stride `ars`) and the
                // panel (`cols·PANEL` long) are in bounds (checked by `dot_rows_panels`).
                acc = unsafe { dot_tile::<F>(a.as_ptr().add(r0 * ars), ars, cols, panel.as_ptr()) };
            } else {
                for c in 0..cols {
                    let kv = &panel[c * PANEL..(c + 1) * PANEL];
                    for i in 0..rr {
                        let q = a[(r0 + i) * ars + c];
                        for l in 0..PANEL {
                            acc[i][l] = fmadd::<F>(q, kv[l], acc[i][l]);
                        }
                    }
                }
            }
            let j0 = p * PANEL;
            let w = PANEL.min(n - j0);
            for (i, row) in acc.iter().enumerate().take(rr) {
                let o = (r0 + i) * drs + j0;
                dst[o..o + w].copy_from_slice(&row[..w]);
            }
        }
    }
}

/// Rows of the output per micro-tile of [`rows_times_matrix`].
const AXPY_ROWS: usize = 2;

/// `R` rows (from `r0`) of `l` times the `inner × W` block of `b` at `b` (row stride `brs`),
/// with no bounds checks in the loop (the accumulators stay in registers).
///
/// # Safety
/// Rows `r0..r0 + R` of `l` and `inner` rows of `W` values at `b` must be readable.
#[inline(always)]
unsafe fn axpy_tile<const F: bool, const W: usize, const R: usize>(
    l: MatRef,
    r0: usize,
    inner: usize,
    b: *const f32,
    brs: usize,
) -> [[f32; W]; R] {
    let mut acc = [[0.0f32; W]; R];
    let lp = l.data.as_ptr();
    for t in 0..inner {
        // SAFETY: within the bounds promised by the caller.
        let bv: &[f32; W] = unsafe { &*(b.add(t * brs) as *const [f32; W]) };
        for (i, acc_i) in acc.iter_mut().enumerate() {
            let s = unsafe { *lp.add((r0 + i) * l.rs + t * l.cs) };
            for k in 0..W {
                acc_i[k] = fmadd::<F>(s, bv[k], acc_i[k]);
            }
        }
    }
    acc
}

/// One column group of width `W` of [`rows_times_matrix`].
///
/// # Safety
/// The caller ([`rows_times_matrix`]) has checked that every index of `l`, `b` (rows
/// `0..l.cols`, columns `c0..c0 + W` with row stride `brs`) and `dst` is in bounds.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn rows_times_matrix_group<const F: bool, const W: usize>(
    l: MatRef,
    b: &[f32],
    brs: usize,
    c0: usize,
    dst: &mut [f32],
    drs: usize,
    accumulate: bool,
) {
    let (rows, inner) = (l.rows, l.cols);
    for r0 in (0..rows).step_by(AXPY_ROWS) {
        let rr = AXPY_ROWS.min(rows - r0);
        // SAFETY: rows r0..r0 + rr of `l` and rows 0..inner of `b` (columns c0..c0 + W) are in
        // bounds by the caller's checks.
        let acc = unsafe {
            if rr == AXPY_ROWS {
                axpy_tile::<F, W, AXPY_ROWS>(l, r0, inner, b.as_ptr().add(c0), brs)
            } else {
                // The ragged last tile, one row at a time.
                let mut acc = [[0.0f32; W]; AXPY_ROWS];
                for (i, acc_i) in acc.iter_mut().enumerate().take(rr) {
                    *acc_i = axpy_tile::<F, W, 1>(l, r0 + i, inner, b.as_ptr().add(c0), brs)[0];
                }
                acc
            }
        };
        for (i, row) in acc.iter().enumerate().take(rr) {
            let o = &mut dst[(r0 + i) * drs + c0..(r0 + i) * drs + c0 + W];
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

/// # Safety
/// As [`rows_times_matrix_group`], for all columns `0..cols`.
#[inline(always)]
unsafe fn rows_times_matrix_generic<const F: bool>(
    l: MatRef,
    b: &[f32],
    cols: usize,
    brs: usize,
    dst: &mut [f32],
    drs: usize,
    accumulate: bool,
) {
    let mut c0 = 0;
    while c0 < cols {
        let left = cols - c0;
        // SAFETY: bounds checked by `rows_times_matrix` for all columns `0..cols`.
        unsafe {
            if left >= 32 {
                rows_times_matrix_group::<F, 32>(l, b, brs, c0, dst, drs, accumulate);
                c0 += 32;
            } else if left >= 16 {
                rows_times_matrix_group::<F, 16>(l, b, brs, c0, dst, drs, accumulate);
                c0 += 16;
            } else {
                rows_times_matrix_group::<F, 8>(l, b, brs, c0, dst, drs, accumulate);
                c0 += 8;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn dot_rows_panels_avx2(
    a: &[f32],
    rows: usize,
    cols: usize,
    ars: usize,
    panels: &[f32],
    n: usize,
    dst: &mut [f32],
    drs: usize,
) {
    dot_rows_panels_generic::<true>(a, rows, cols, ars, panels, n, dst, drs)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn rows_times_matrix_avx2(
    l: MatRef,
    b: &[f32],
    cols: usize,
    brs: usize,
    dst: &mut [f32],
    drs: usize,
    accumulate: bool,
) {
    // SAFETY: forwarded from the caller.
    unsafe { rows_times_matrix_generic::<true>(l, b, cols, brs, dst, drs, accumulate) }
}

/// `dst[r][j] = Σ_c a[r][c]·b[j][c]` (`a` is `rows × cols` with row stride `ars`; `panels` is
/// `b`, `n × cols`, packed by [`pack_panels`]; `dst` has row stride `drs`).
#[allow(clippy::too_many_arguments)]
pub fn dot_rows_panels(
    a: &[f32],
    rows: usize,
    cols: usize,
    ars: usize,
    panels: &[f32],
    n: usize,
    dst: &mut [f32],
    drs: usize,
) {
    if rows == 0 || n == 0 {
        return;
    }
    assert!(
        (rows - 1) * ars + cols <= a.len(),
        "dot_rows_panels: a out of bounds"
    );
    assert!(
        panels.len() >= n.div_ceil(PANEL) * cols * PANEL,
        "dot_rows_panels: panels"
    );
    assert!(
        drs >= n && (rows - 1) * drs + n <= dst.len(),
        "dot_rows_panels: dst"
    );
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        // SAFETY: the CPU supports AVX2 and FMA (checked at run time); bounds checked above.
        unsafe { dot_rows_panels_avx2(a, rows, cols, ars, panels, n, dst, drs) };
        return;
    }
    dot_rows_panels_generic::<false>(a, rows, cols, ars, panels, n, dst, drs)
}

/// `dst (=|+=) l·b` where `l` is any strided `rows × inner` view and `b` is `inner × cols`
/// row-major with row stride `brs`; `cols` must be a multiple of 8.
pub fn rows_times_matrix(
    l: MatRef,
    b: &[f32],
    cols: usize,
    brs: usize,
    dst: &mut [f32],
    drs: usize,
    accumulate: bool,
) {
    assert!(
        cols % 8 == 0,
        "rows_times_matrix: {cols} columns is not a multiple of 8"
    );
    if l.rows == 0 || cols == 0 {
        return;
    }
    l.check();
    if l.cols > 0 {
        assert!(
            (l.cols - 1) * brs + cols <= b.len(),
            "rows_times_matrix: b out of bounds"
        );
    }
    assert!(
        drs >= cols && (l.rows - 1) * drs + cols <= dst.len(),
        "rows_times_matrix: dst"
    );
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        // SAFETY: the CPU supports AVX2 and FMA (checked at run time); bounds checked above.
        unsafe { rows_times_matrix_avx2(l, b, cols, brs, dst, drs, accumulate) };
        return;
    }
    // SAFETY: bounds checked above.
    unsafe { rows_times_matrix_generic::<false>(l, b, cols, brs, dst, drs, accumulate) }
}

#[cfg(test)]
mod tests {
    use super::*;

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
            let mut panels = Vec::new();
            pack_panels(&bm, n, cols, ars, &mut panels);
            for fma in [false, true] {
                let mut dst = vec![7.0f32; rows * (n + 2)];
                if fma && has_avx2_fma() {
                    dot_rows_panels(&a, rows, cols, ars, &panels, n, &mut dst, n + 2);
                } else {
                    dot_rows_panels_generic::<false>(
                        &a,
                        rows,
                        cols,
                        ars,
                        &panels,
                        n,
                        &mut dst,
                        n + 2,
                    );
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
            let l = MatRef::rows(&lt, n, rows, rows).t();
            for accumulate in [false, true] {
                let mut dst = vec![0.5f32; rows * (cols + 8)];
                rows_times_matrix(l, &bm, cols, ars, &mut dst, cols + 8, accumulate);
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
