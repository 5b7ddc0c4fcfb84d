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

/// `count` indices of `points` chosen by farthest-point sampling: the first is the point
/// farthest from the centroid, each next one the point farthest from all chosen so far (ties
/// by the lower index). Depends only on the distances between the points (and the centroid),
/// so a rotated copy of a cloud gets the same indices up to float rounding. Returns every
/// index, in order, when `count ≥ points.len()`. Units: whatever the points are in.
pub fn farthest_point_indices(points: &[Vec3], count: usize) -> Vec<u32> {
    let n = points.len();
    if count >= n {
        return (0..n as u32).collect();
    }
    if count == 0 {
        return Vec::new();
    }
    let centre = points.iter().copied().sum::<Vec3>() / n as f32;
    let farthest = |d: &[f32]| crate::network::argmax(d.iter().copied()).0;
    let from_centre: Vec<f32> = points.iter().map(|p| p.distance_squared(centre)).collect();
    let mut next = farthest(&from_centre);
    // Squared distance of each point to the nearest chosen one.
    let mut nearest = vec![f32::INFINITY; n];
    let mut chosen = Vec::with_capacity(count);
    for _ in 0..count {
        chosen.push(next as u32);
        let p = points[next];
        for (d, q) in nearest.iter_mut().zip(points) {
            *d = d.min(p.distance_squared(*q));
        }
        // A chosen point's own distance is 0, so it is never chosen again while others remain.
        nearest[next] = f32::NEG_INFINITY;
        next = farthest(&nearest);
    }
    chosen
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

    #[test]
    fn farthest_points_start_far_from_the_centre_spread_out_and_ignore_rotation() {
        // A 5×5×5 grid with one point pulled out: it is the first, then its farthest corner.
        let mut pts: Vec<Vec3> = (0..125)
            .map(|i| Vec3::new((i % 5) as f32, (i / 5 % 5) as f32, (i / 25) as f32))
            .collect();
        pts[0] = Vec3::new(-3.0, -3.0, -3.0);
        let idx = farthest_point_indices(&pts, 10);
        assert_eq!(idx.len(), 10);
        assert_eq!(idx[0], 0);
        assert_eq!(idx[1], 124);
        let mut unique = idx.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), 10, "no index twice: {idx:?}");
        // Distances alone decide: a rotated and shifted cloud (no ties) gets the same indices.
        let mut state = 7u64;
        let mut unit = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let cloud: Vec<Vec3> = (0..300)
            .map(|_| Vec3::new(unit(), unit(), unit()))
            .collect();
        let turn = glam::Quat::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 1.1);
        let moved: Vec<Vec3> = cloud.iter().map(|&p| turn * p + Vec3::splat(5.0)).collect();
        let picked = farthest_point_indices(&cloud, 32);
        assert_eq!(farthest_point_indices(&moved, 32), picked);
        assert_eq!(
            farthest_point_indices(&pts, 200),
            (0..125).collect::<Vec<u32>>()
        );
        assert!(farthest_point_indices(&pts, 0).is_empty());
    }
}
