//! Checked views of f32 matrices stored in slices: the argument type of the kernels instead of
//! `(slice, rows, cols, stride)` lists. A view is in bounds by construction (the constructors
//! assert it), which is what the unchecked inner loops of [`super::fastmath`] rely on.

/// Index of the last element of a `rows × cols` view with the given strides, `None` if empty.
fn last_index(rows: usize, cols: usize, row_stride: usize, col_stride: usize) -> Option<usize> {
    (rows > 0 && cols > 0).then(|| (rows - 1) * row_stride + (cols - 1) * col_stride)
}

/// A read-only, strided f32 matrix view: element `(r, c)` is `data[r·row_stride + c·col_stride]`.
/// Every element of a non-empty view lies in `data` (checked on construction).
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a> {
    data: &'a [f32],
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a> MatRef<'a> {
    /// Row-major `rows × cols` with row stride `row_stride` (elements) starting at `data[0]`.
    ///
    /// # Panics
    /// If a non-empty view's last element lies past the end of `data`.
    pub fn new(data: &'a [f32], rows: usize, cols: usize, row_stride: usize) -> Self {
        Self::strided(data, rows, cols, row_stride, 1)
    }

    /// Any strides (elements), e.g. a column-major view.
    ///
    /// # Panics
    /// If a non-empty view's last element lies past the end of `data`.
    pub fn strided(
        data: &'a [f32],
        rows: usize,
        cols: usize,
        row_stride: usize,
        col_stride: usize,
    ) -> Self {
        if let Some(last) = last_index(rows, cols, row_stride, col_stride) {
            assert!(
                last < data.len(),
                "matrix view {rows}×{cols} (strides {row_stride}, {col_stride}) out of bounds of {} values",
                data.len()
            );
        }
        MatRef {
            data,
            rows,
            cols,
            row_stride,
            col_stride,
        }
    }

    /// The transpose (no copy).
    pub fn t(self) -> Self {
        MatRef {
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            data: self.data,
        }
    }

    /// The underlying values (element `(0, 0)` first).
    pub fn data(&self) -> &'a [f32] {
        self.data
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    pub fn row_stride(&self) -> usize {
        self.row_stride
    }

    pub fn col_stride(&self) -> usize {
        self.col_stride
    }

    /// Element `(r, c)` (bounds-checked by the slice).
    #[inline(always)]
    pub fn at(&self, r: usize, c: usize) -> f32 {
        self.data[r * self.row_stride + c * self.col_stride]
    }

    /// Whether rows are contiguous (`col_stride == 1`).
    pub fn is_row_major(&self) -> bool {
        self.col_stride == 1 || self.cols <= 1
    }
}

/// A mutable, row-major f32 matrix view: element `(r, c)` is `data[r·row_stride + c]`, with
/// `row_stride ≥ cols`; every element of a non-empty view lies in `data` (checked on
/// construction). Values between rows (`cols..row_stride`) are never written.
#[derive(Debug)]
pub struct MatMut<'a> {
    data: &'a mut [f32],
    rows: usize,
    cols: usize,
    row_stride: usize,
}

impl<'a> MatMut<'a> {
    /// Row-major `rows × cols` with row stride `row_stride` (elements) starting at `data[0]`.
    ///
    /// # Panics
    /// If `row_stride < cols` with more than one row, or a non-empty view's last element lies
    /// past the end of `data`.
    pub fn new(data: &'a mut [f32], rows: usize, cols: usize, row_stride: usize) -> Self {
        assert!(
            rows <= 1 || row_stride >= cols,
            "matrix view: row stride {row_stride} below {cols} columns"
        );
        if let Some(last) = last_index(rows, cols, row_stride, 1) {
            assert!(
                last < data.len(),
                "matrix view {rows}×{cols} (row stride {row_stride}) out of bounds of {} values",
                data.len()
            );
        }
        MatMut {
            data,
            rows,
            cols,
            row_stride,
        }
    }

    /// A shorter-lived view of the same matrix.
    pub fn rb_mut(&mut self) -> MatMut<'_> {
        MatMut {
            data: self.data,
            rows: self.rows,
            cols: self.cols,
            row_stride: self.row_stride,
        }
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    pub fn row_stride(&self) -> usize {
        self.row_stride
    }

    /// The underlying values (element `(0, 0)` first).
    pub fn data_mut(&mut self) -> &mut [f32] {
        self.data
    }

    /// Row `r` (`cols` values).
    #[inline(always)]
    pub fn row_mut(&mut self, r: usize) -> &mut [f32] {
        let o = r * self.row_stride;
        &mut self.data[o..o + self.cols]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_check_their_bounds() {
        let v = vec![0.0f32; 12];
        let m = MatRef::new(&v, 3, 4, 4);
        assert_eq!((m.t().rows(), m.t().cols()), (4, 3));
        assert_eq!(m.t().at(3, 2), v[2 * 4 + 3]);
        assert!(std::panic::catch_unwind(|| MatRef::new(&v, 3, 4, 5)).is_err());
        // Empty views need no storage.
        let _ = MatRef::new(&[], 0, 7, 7);
        let mut w = vec![0.0f32; 11];
        let mut mm = MatMut::new(&mut w, 3, 3, 4);
        mm.row_mut(2).fill(1.0);
        assert_eq!(&w[8..11], &[1.0; 3]);
    }
}
