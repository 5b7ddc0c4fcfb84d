//! Exact k-nearest-neighbour graphs in plain Rust, outside autograd.
//!
//! The DGCNN's graph needs no gradient; computing it here is much faster than a candle
//! arg-sort, and the result goes into the network as a `u32` tensor. Each point's neighbours
//! are searched in a uniform grid, ring after ring of cells around its own until the k-th
//! distance found is provably shorter than any point outside the rings; the graph is the
//! same as a brute-force scan's (the same distance formula, ties by index), which stays as the
//! fallback for small or degenerate clouds and as the test oracle ([`knn_indices_brute`]).

use glam::Vec3;
use rayon::prelude::*;

/// Rows of the graph per parallel task (each row only reads the points: the same output on
/// any thread count).
const ROWS_PER_TASK: usize = 64;

/// Below this many points the brute-force scan is as fast as building a grid.
const GRID_FROM: usize = 256;

/// Rings of cells searched around a point before its query falls back to scanning every point
/// (an isolated point far from the rest).
const MAX_RINGS: i32 = 4;

/// For each of the `points`, the indices of its `k` nearest points (itself included, as in
/// DGCNN), flattened row-major: `out[i * k + r]`. Ties break by index, so the graph is
/// deterministic. Requires `1 ≤ k ≤ points.len()`. Units: any (only distances matter).
pub fn knn_indices(points: &[Vec3], k: usize) -> Vec<u32> {
    let n = points.len();
    assert!(k >= 1 && k <= n, "knn: k = {k} for {n} points");
    let Some(grid) = (n >= GRID_FROM).then(|| Grid::new(points, k)).flatten() else {
        return knn_indices_brute(points, k);
    };
    let mut out = vec![0u32; n * k];
    out.par_chunks_mut(ROWS_PER_TASK * k)
        .enumerate()
        .for_each(|(t, rows)| {
            let mut best = KBest::new(k);
            for (r, row) in rows.chunks_exact_mut(k).enumerate() {
                let i = t * ROWS_PER_TASK + r;
                if !grid.search(points, i, &mut best) {
                    best.clear();
                    let p = points[i];
                    for (j, q) in points.iter().enumerate() {
                        best.offer(distance2(p, *q), j as u32);
                    }
                }
                for (o, b) in row.iter_mut().zip(best.finish()) {
                    *o = b.1;
                }
            }
        });
    out
}

/// [`knn_indices`] by scanning every point for every point: O(n²), the oracle of the grid.
pub fn knn_indices_brute(points: &[Vec3], k: usize) -> Vec<u32> {
    let n = points.len();
    assert!(k >= 1 && k <= n, "knn: k = {k} for {n} points");
    let mut out = vec![0u32; n * k];
    // Coordinates as three arrays: the distance loop then vectorises.
    let xs: Vec<f32> = points.iter().map(|p| p.x).collect();
    let ys: Vec<f32> = points.iter().map(|p| p.y).collect();
    let zs: Vec<f32> = points.iter().map(|p| p.z).collect();
    out.par_chunks_mut(ROWS_PER_TASK * k)
        .enumerate()
        .for_each(|(t, rows)| {
            let mut dist = vec![0.0f32; n];
            let mut best = KBest::new(k);
            for (r, row) in rows.chunks_exact_mut(k).enumerate() {
                let p = points[t * ROWS_PER_TASK + r];
                for (((d, &x), &y), &z) in dist.iter_mut().zip(&xs).zip(&ys).zip(&zs) {
                    *d = distance2(p, Vec3::new(x, y, z));
                }
                best.clear();
                for (j, &d) in dist.iter().enumerate() {
                    best.offer(d, j as u32);
                }
                for (o, b) in row.iter_mut().zip(best.finish()) {
                    *o = b.1;
                }
            }
        });
    out
}

/// The squared distance, in one fixed order of operations (the grid and the scan agree bit
/// for bit).
#[inline]
fn distance2(p: Vec3, q: Vec3) -> f32 {
    let (dx, dy, dz) = (p.x - q.x, p.y - q.y, p.z - q.z);
    dx * dx + dy * dy + dz * dz
}

/// The k smallest `(distance², index)` pairs offered, in the total order (distance by
/// `total_cmp`, then index). Candidates go unsorted into a buffer of 4k; when it fills, a
/// selection keeps its k first. `worst`, the k-th kept so far (NaN until known), filters the
/// rest: a candidate farther in plain float order cannot come before it. Each passing
/// candidate costs a push, not a sorted insertion.
struct KBest {
    k: usize,
    items: Vec<(f32, u32)>,
    worst: f32,
}

impl KBest {
    fn new(k: usize) -> Self {
        KBest {
            k,
            items: Vec::with_capacity(4 * k),
            worst: f32::NAN,
        }
    }

    fn clear(&mut self) {
        self.items.clear();
        self.worst = f32::NAN;
    }

    fn before(a: &(f32, u32), b: &(f32, u32)) -> std::cmp::Ordering {
        a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
    }

    #[inline]
    fn offer(&mut self, d: f32, j: u32) {
        // Equal distances pass: the index decides, and candidates need not come in index order.
        if d > self.worst {
            return;
        }
        self.items.push((d, j));
        if self.items.len() == 4 * self.k {
            self.keep_k();
        }
    }

    /// Keeps the k first (when there are that many) and sets `worst` to the k-th.
    fn keep_k(&mut self) {
        let k = self.k;
        if self.items.len() >= k {
            // Also with exactly k: the k-th must be the largest, not the last pushed.
            self.items.select_nth_unstable_by(k - 1, Self::before);
            self.items.truncate(k);
            self.worst = self.items[k - 1].0;
        }
    }

    /// The k-th smallest distance² so far, if k candidates were offered.
    fn kth(&mut self) -> Option<f32> {
        self.keep_k();
        (self.items.len() == self.k).then_some(self.worst)
    }

    /// The k best, sorted.
    fn finish(&mut self) -> &[(f32, u32)] {
        self.keep_k();
        self.items.sort_unstable_by(Self::before);
        &self.items
    }
}

/// Points bucketed in a uniform grid of cubic cells, each cell's points in index order.
struct Grid {
    lo: Vec3,
    cell: f32,
    dims: [i32; 3],
    /// `start[c]..start[c + 1]`: cell `c`'s points in `order`.
    start: Vec<u32>,
    order: Vec<u32>,
}

impl Grid {
    /// `None` for clouds it cannot bucket (a non-finite coordinate, all points in one place).
    fn new(points: &[Vec3], k: usize) -> Option<Self> {
        let (lo, hi) = points.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(a, b), p| (a.min(*p), b.max(*p)),
        );
        let extent = hi - lo;
        let longest = extent.max_element();
        if !extent.is_finite() || longest <= 0.0 {
            return None;
        }
        // Sampled surfaces hold about k points in a square of side √(k/n)·L; cells of 0.6 times
        // that side were the fastest of 0.45, 0.6, 0.8 and 1 on the bench's object views
        // (384 to 1024 points, k = 16): the k nearest then mostly lie within the first one or
        // two rings. At most 4n cells.
        let n = points.len();
        let mut cell = longest * (k as f32 / n as f32).sqrt() * 0.6;
        let dims_for = |cell: f32| extent.to_array().map(|e| ((e / cell) as i32 + 1).max(1));
        let mut dims = dims_for(cell);
        while dims.iter().map(|&d| d as usize).product::<usize>() > 4 * n {
            cell *= 1.25;
            dims = dims_for(cell);
        }
        let cells = dims.iter().map(|&d| d as usize).product::<usize>();
        let grid = Grid {
            lo,
            cell,
            dims,
            start: Vec::new(),
            order: Vec::new(),
        };
        let ids: Vec<u32> = points
            .iter()
            .map(|p| grid.cell_id(grid.coords(*p)))
            .collect();
        let mut start = vec![0u32; cells + 1];
        for &c in &ids {
            start[c as usize + 1] += 1;
        }
        for c in 0..cells {
            start[c + 1] += start[c];
        }
        let mut next = start.clone();
        let mut order = vec![0u32; n];
        for (j, &c) in ids.iter().enumerate() {
            order[next[c as usize] as usize] = j as u32;
            next[c as usize] += 1;
        }
        Some(Grid {
            start,
            order,
            ..grid
        })
    }

    fn coords(&self, p: Vec3) -> [i32; 3] {
        let c = ((p - self.lo) / self.cell).to_array();
        [0, 1, 2].map(|a| (c[a] as i32).clamp(0, self.dims[a] - 1))
    }

    fn cell_id(&self, c: [i32; 3]) -> u32 {
        ((c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]) as u32
    }

    /// The k nearest of point `i` into `best` (cleared first), ring after ring of cells; false
    /// when [`MAX_RINGS`] rings did not settle them (the caller then scans every point).
    ///
    /// After ring r every unvisited point lies more than r cells away along some axis, so at
    /// least r·cell from the point: once the k-th distance found is below that (with a margin
    /// for the rounding of the cell coordinates), no unvisited point can come before it.
    fn search(&self, points: &[Vec3], i: usize, best: &mut KBest) -> bool {
        best.clear();
        let p = points[i];
        let c = self.coords(p);
        let whole = self.dims.iter().copied().max().unwrap_or(1);
        for r in 0..=MAX_RINGS {
            for dz in -r..=r {
                let z = c[2] + dz;
                if z < 0 || z >= self.dims[2] {
                    continue;
                }
                for dy in -r..=r {
                    let y = c[1] + dy;
                    if y < 0 || y >= self.dims[1] {
                        continue;
                    }
                    // On the ring's faces in z or y every x; inside, only the two x ends.
                    let inner = dz.abs() < r && dy.abs() < r;
                    let step = if inner { (2 * r).max(1) } else { 1 };
                    let mut dx = -r;
                    while dx <= r {
                        let x = c[0] + dx;
                        if x >= 0 && x < self.dims[0] {
                            let id = self.cell_id([x, y, z]) as usize;
                            let (a, b) = (self.start[id] as usize, self.start[id + 1] as usize);
                            for &j in &self.order[a..b] {
                                best.offer(distance2(p, points[j as usize]), j);
                            }
                        }
                        dx += step;
                    }
                }
            }
            if r >= whole {
                // Every cell visited.
                return best.kth().is_some();
            }
            let reach = r as f32 * self.cell;
            if let Some(kth) = best.kth()
                && kth < reach * reach * (1.0 - 1e-4)
            {
                return true;
            }
        }
        false
    }
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
    fn the_grid_search_gives_the_brute_force_graph() {
        // Surfaces, a volume, a flat square, duplicates, a far outlier, scan order and
        // shuffled order: the grid's graph is the scan's, tie for tie.
        let mut state = 11u64;
        let mut unit = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let sphere: Vec<Vec3> = (0..1000)
            .map(|_| Vec3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5).normalize() * 0.3)
            .collect();
        let volume: Vec<Vec3> = (0..700)
            .map(|_| Vec3::new(unit(), unit(), unit()))
            .collect();
        let square: Vec<Vec3> = (0..900)
            .map(|i| Vec3::new((i % 30) as f32 * 0.01, (i / 30) as f32 * 0.01, 0.0))
            .collect();
        let mut dupes: Vec<Vec3> = sphere[..300].iter().flat_map(|&p| [p, p]).collect();
        dupes.push(Vec3::new(50.0, 0.0, 0.0));
        let mut shuffled = square.clone();
        for i in (1..shuffled.len()).rev() {
            let j = (unit() * (i + 1) as f32) as usize % (i + 1);
            shuffled.swap(i, j);
        }
        for (name, cloud) in [
            ("sphere", &sphere),
            ("volume", &volume),
            ("square", &square),
            ("duplicates and an outlier", &dupes),
            ("shuffled square", &shuffled),
        ] {
            for k in [1, 16, 20] {
                let (grid, brute) = (knn_indices(cloud, k), knn_indices_brute(cloud, k));
                let first_bad = (0..cloud.len())
                    .find(|&i| grid[i * k..(i + 1) * k] != brute[i * k..(i + 1) * k]);
                assert_eq!(
                    first_bad.map(|i| (i, &grid[i * k..(i + 1) * k], &brute[i * k..(i + 1) * k])),
                    None,
                    "{name}, k = {k}: point, grid row, scan row"
                );
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
