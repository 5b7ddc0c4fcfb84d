//! Small helpers for the fused CPU ops (candle `CustomOp`s) of `ic_nn::ops` and `ic_pose`.

use candle_core::{CpuStorage, DType, Layout, Result, Tensor};

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

/// Whether every tensor is an f32 tensor on the CPU (where the fused ops run).
pub fn all_cpu_f32(ts: &[&Tensor]) -> bool {
    ts.iter()
        .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}
