//! Brute-force k-nearest-neighbour graphs in plain Rust, outside autograd.
//!
//! The DGCNN's graph needs no gradient; computing it here (one pass of distances per point, a
//! sorted k-best list that most candidates leave after one comparison, rows in parallel) is
//! much faster than a candle arg-sort, and the result goes into the network as a `u32` tensor.

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
            let mut dist = vec![0.0f32; n];
            let mut best: Vec<(f32, u32)> = Vec::with_capacity(k + 1);
            for (r, row) in rows.chunks_exact_mut(k).enumerate() {
                let p = points[t * ROWS_PER_TASK + r];
                for (d, q) in dist.iter_mut().zip(points) {
                    *d = p.distance_squared(*q);
                }
                // The k smallest (distance, index) pairs in that total order, kept sorted: a
                // candidate is compared with the current k-th and inserted only when smaller
                // (few insertions after the first k), the same set and order as sorting all.
                best.clear();
                let before =
                    |a: (f32, u32), b: (f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).is_lt();
                for (j, &d) in dist.iter().enumerate() {
                    let cand = (d, j as u32);
                    if best.len() == k {
                        if !before(cand, best[k - 1]) {
                            continue;
                        }
                        best.pop();
                    }
                    let at = best.partition_point(|&b| before(b, cand));
                    best.insert(at, cand);
                }
                for (o, b) in row.iter_mut().zip(&best) {
                    *o = b.1;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_equals_a_full_sort_with_ties_broken_by_index() {
        // A grid has many equal distances; the graph must be the first k of the full
        // (distance, index) order.
        let pts: Vec<Vec3> = (0..150)
            .map(|i| Vec3::new((i % 5) as f32, ((i / 5) % 6) as f32, (i / 30) as f32))
            .collect();
        for k in [1, 7, 16, 150] {
            let got = knn_indices(&pts, k);
            for (i, p) in pts.iter().enumerate() {
                let mut all: Vec<(f32, u32)> = pts
                    .iter()
                    .enumerate()
                    .map(|(j, q)| (p.distance_squared(*q), j as u32))
                    .collect();
                all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let want: Vec<u32> = all[..k].iter().map(|a| a.1).collect();
                assert_eq!(&got[i * k..(i + 1) * k], &want[..], "point {i}, k {k}");
            }
        }
    }

    #[test]
    fn knn_on_a_line() {
        let pts: Vec<Vec3> = (0..6).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let idx = knn_indices(&pts, 3);
        assert_eq!(&idx[0..3], &[0, 1, 2]);
        assert_eq!(&idx[3 * 3..3 * 3 + 3], &[3, 2, 4]);
    }
}
