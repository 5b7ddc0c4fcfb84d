//! Brute-force k-nearest-neighbour graphs in plain Rust, outside autograd.
//!
//! The DGCNN's graph needs no gradient; computing it here with `select_nth_unstable` is several
//! times faster than a candle arg-sort and the result goes into the network as a `u32` tensor.

use glam::Vec3;
use rayon::prelude::*;

/// For each of the `points`, the indices of its `k` nearest points (itself included, as in
/// DGCNN), flattened row-major: `out[i * k + r]`. Ties break by index, so the graph is
/// deterministic. Requires `1 ≤ k ≤ points.len()`.
pub fn knn_indices(points: &[Vec3], k: usize) -> Vec<u32> {
    let n = points.len();
    assert!(k >= 1 && k <= n, "knn: k = {k} for {n} points");
    let mut out = vec![0u32; n * k];
    // Rows of the graph in parallel (each row only reads `points`): same output on any thread
    // count.
    const ROWS_PER_TASK: usize = 64;
    out.par_chunks_mut(ROWS_PER_TASK * k)
        .enumerate()
        .for_each(|(t, rows)| {
            let mut dist: Vec<(f32, u32)> = Vec::with_capacity(n);
            for (r, row) in rows.chunks_exact_mut(k).enumerate() {
                let p = points[t * ROWS_PER_TASK + r];
                dist.clear();
                dist.extend(
                    points
                        .iter()
                        .enumerate()
                        .map(|(j, q)| (p.distance_squared(*q), j as u32)),
                );
                let cmp = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
                if k < n {
                    dist.select_nth_unstable_by(k - 1, cmp);
                }
                let head = &mut dist[..k];
                head.sort_unstable_by(cmp);
                for (o, d) in row.iter_mut().zip(head.iter()) {
                    *o = d.1;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_on_a_line() {
        let pts: Vec<Vec3> = (0..6).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let idx = knn_indices(&pts, 3);
        assert_eq!(&idx[0..3], &[0, 1, 2]);
        assert_eq!(&idx[3 * 3..3 * 3 + 3], &[3, 2, 4]);
    }
}
