//! Small helpers for the fused CPU ops (candle `CustomOp`s) of `ic_nn::ops` and `ic_pose`.

use std::ops::Deref;

use candle_core::{CpuStorage, DType, Layout, Result, Storage, StorageRef, Tensor};

/// The f32 values of a contiguous CPU storage under `layout`; errors (naming `what`) on another
/// dtype or a strided layout.
pub fn f32_slice<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = storage else {
        candle_core::bail!("{what}: f32 expected")
    };
    let Some((start, end)) = layout.contiguous_offsets() else {
        candle_core::bail!("{what}: contiguous input expected")
    };
    Ok(&v[start..end])
}

/// All values of `t` as f32, row-major (for the backward passes, which get tensors).
pub fn to_f32_vec(t: &Tensor) -> Result<Vec<f32>> {
    t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()
}

/// The f32 values of a tensor, row-major, for the backward passes (which get tensors, not
/// storages): borrowed from the tensor's CPU storage when it is a contiguous f32 tensor — no
/// copy, the storage stays read-locked while this lives — and copied otherwise.
pub struct F32Data<'a>(F32DataInner<'a>);

enum F32DataInner<'a> {
    Borrowed(StorageRef<'a>, usize, usize),
    Owned(Vec<f32>),
}

/// [`F32Data`] of `t`: borrowed where `t` is a contiguous f32 CPU tensor, else a copy
/// ([`to_f32_vec`]).
pub fn f32_data(t: &Tensor) -> Result<F32Data<'_>> {
    if t.dtype() == DType::F32 && t.device().is_cpu() {
        let (guard, layout) = t.storage_and_layout();
        let is_f32 = matches!(&*guard, Storage::Cpu(CpuStorage::F32(_)));
        if let (true, Some((start, end))) = (is_f32, layout.contiguous_offsets()) {
            return Ok(F32Data(F32DataInner::Borrowed(guard, start, end)));
        }
    }
    Ok(F32Data(F32DataInner::Owned(to_f32_vec(t)?)))
}

impl F32Data<'_> {
    /// Whether the values are the tensor's own storage (no copy was made).
    pub fn is_borrowed(&self) -> bool {
        matches!(self.0, F32DataInner::Borrowed(..))
    }
}

impl Deref for F32Data<'_> {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        match &self.0 {
            F32DataInner::Borrowed(guard, start, end) => match &**guard {
                Storage::Cpu(CpuStorage::F32(v)) => &v[*start..*end],
                _ => unreachable!("f32_data borrows only f32 CPU storage"),
            },
            F32DataInner::Owned(v) => v,
        }
    }
}

/// Whether every tensor is an f32 tensor on the CPU (where the fused ops run).
pub fn all_cpu_f32(ts: &[&Tensor]) -> bool {
    ts.iter()
        .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}

/// `n` zeros, written by the rayon pool when `n` is large (at least 2¹⁵ values): a fused op's
/// output buffer is filled on the calling thread otherwise, while the pool's threads wait.
pub fn zeros_f32(n: usize) -> Vec<f32> {
    use rayon::prelude::*;
    const PARALLEL_FROM: usize = 1 << 15;
    if n < PARALLEL_FROM {
        return vec![0.0; n];
    }
    (0..n)
        .into_par_iter()
        .with_min_len(PARALLEL_FROM / 2)
        .map(|_| 0.0f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, IndexOp};

    use super::*;

    #[test]
    fn f32_data_reads_views_row_major_whether_it_borrows_or_copies() {
        let dev = Device::Cpu;
        let t = Tensor::arange(0f32, 12.0, &dev)
            .unwrap()
            .reshape((3, 4))
            .unwrap();
        // Contiguous: borrowed, the whole storage.
        assert_eq!(&*f32_data(&t).unwrap(), &to_f32_vec(&t).unwrap()[..]);
        assert!(f32_data(&t).unwrap().is_borrowed());
        // A contiguous view with an offset (rows 1..3): borrowed from the middle of the storage.
        let rows = t.i(1..3).unwrap();
        assert_eq!(
            &*f32_data(&rows).unwrap(),
            &[4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0]
        );
        assert!(f32_data(&rows).unwrap().is_borrowed());
        // Strided (transposed): copied, in the view's row-major order.
        let tt = t.t().unwrap();
        let want: Vec<f32> = vec![0.0, 4.0, 8.0, 1.0, 5.0, 9.0, 2.0, 6.0, 10.0, 3.0, 7.0, 11.0];
        assert_eq!(&*f32_data(&tt).unwrap(), &want[..]);
        assert!(!f32_data(&tt).unwrap().is_borrowed());
        // Another dtype: converted.
        let f64s = t.to_dtype(DType::F64).unwrap();
        assert_eq!(&*f32_data(&f64s).unwrap(), &to_f32_vec(&t).unwrap()[..]);
    }

    #[test]
    fn zeros_f32_is_all_zeros_at_every_size() {
        for n in [0, 1, (1 << 15) - 1, 1 << 15, (1 << 17) + 3] {
            let z = zeros_f32(n);
            assert_eq!(z.len(), n);
            assert!(z.iter().all(|&v| v.to_bits() == 0));
        }
    }
}
