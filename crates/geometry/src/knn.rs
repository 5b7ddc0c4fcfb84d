//! Nearest-neighbour queries on 3-D points through a kiddo k-d tree.

use std::num::NonZero;

use glam::Vec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::GeometryError;
use crate::cloud::check_finite;

/// An immutable k-d tree over a fixed set of points (f32). Query results are indices into the
/// slice the tree was built from, with *Euclidean* (not squared) distances.
pub struct KdTree {
    tree: ImmutableKdTree<f32, 3>,
    len: usize,
}

/// One neighbour: index into the indexed points and Euclidean distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbour {
    pub index: usize,
    pub distance: f32,
}

impl KdTree {
    /// Builds the tree. Fails on an empty or non-finite input, or more than `u32::MAX` points.
    pub fn new(points: &[Vec3]) -> Result<KdTree, GeometryError> {
        if points.is_empty() {
            return Err(GeometryError::Empty {
                what: "kd-tree points",
            });
        }
        check_finite("kd-tree points", points)?;
        let arrays: Vec<[f32; 3]> = points.iter().map(|p| p.to_array()).collect();
        let tree = ImmutableKdTree::new_from_slice(&arrays).map_err(|e| {
            GeometryError::InvalidParameter {
                name: "kd-tree points",
                message: format!("{e:?}"),
            }
        })?;
        Ok(KdTree {
            tree,
            len: points.len(),
        })
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The nearest indexed point to `query`.
    pub fn nearest(&self, query: Vec3) -> Neighbour {
        let r = self
            .tree
            .query(&query.to_array())
            .nearest_one::<SquaredEuclidean<f32>>()
            .execute();
        Neighbour {
            index: r.item as usize,
            distance: r.distance.sqrt(),
        }
    }

    /// The `k` nearest indexed points, nearest first (fewer when the tree holds fewer than `k`).
    pub fn k_nearest(&self, query: Vec3, k: usize) -> Vec<Neighbour> {
        let Some(k) = NonZero::new(k.min(self.len)) else {
            return Vec::new();
        };
        self.tree
            .query(&query.to_array())
            .nearest_n::<SquaredEuclidean<f32>>(k)
            .execute()
            .into_iter()
            .map(|r| Neighbour {
                index: r.item as usize,
                distance: r.distance.sqrt(),
            })
            .collect()
    }

    /// All indexed points within `radius` (inclusive) of `query`, nearest first.
    pub fn within_radius(&self, query: Vec3, radius: f32) -> Vec<Neighbour> {
        if !(radius >= 0.0) {
            return Vec::new();
        }
        self.tree
            .query(&query.to_array())
            .within::<SquaredEuclidean<f32>>(radius * radius)
            .execute()
            .into_iter()
            .map(|r| Neighbour {
                index: r.item as usize,
                distance: r.distance.sqrt(),
            })
            .collect()
    }

    /// For each query, its nearest indexed point (parallel over queries).
    pub fn nearest_all(&self, queries: &[Vec3]) -> Vec<Neighbour> {
        use rayon::prelude::*;
        queries.par_iter().map(|&q| self.nearest(q)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_points(n: usize, seed: u64) -> Vec<Vec3> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| Vec3::new(rng.random(), rng.random(), rng.random()))
            .collect()
    }

    #[test]
    fn queries_match_brute_force() {
        let pts = random_points(2000, 1);
        let tree = KdTree::new(&pts).unwrap();
        for q in random_points(50, 2) {
            let mut brute: Vec<(f32, usize)> = pts
                .iter()
                .enumerate()
                .map(|(i, p)| (p.distance(q), i))
                .collect();
            brute.sort_by(|a, b| a.0.total_cmp(&b.0));
            assert_eq!(tree.nearest(q).index, brute[0].1);
            let knn = tree.k_nearest(q, 20);
            assert_eq!(
                knn.iter().map(|n| n.index).collect::<Vec<_>>(),
                brute[..20].iter().map(|b| b.1).collect::<Vec<_>>()
            );
            assert!((knn[19].distance - brute[19].0).abs() < 1e-6);
            let r = 0.1;
            let mut within: Vec<usize> = tree.within_radius(q, r).iter().map(|n| n.index).collect();
            within.sort();
            let mut expect: Vec<usize> = brute.iter().filter(|b| b.0 <= r).map(|b| b.1).collect();
            expect.sort();
            assert_eq!(within, expect);
        }
    }

    #[test]
    fn k_larger_than_the_tree_returns_everything_and_bad_input_errors() {
        let tree = KdTree::new(&[Vec3::ZERO, Vec3::X]).unwrap();
        assert_eq!(tree.k_nearest(Vec3::ZERO, 5).len(), 2);
        assert!(tree.k_nearest(Vec3::ZERO, 0).is_empty());
        assert!(KdTree::new(&[]).is_err());
        assert!(KdTree::new(&[Vec3::new(f32::NAN, 0.0, 0.0)]).is_err());
    }

    #[test]
    fn many_duplicate_points_do_not_break_the_tree() {
        let mut pts = vec![Vec3::splat(0.5); 500];
        pts.push(Vec3::ZERO);
        let tree = KdTree::new(&pts).unwrap();
        assert_eq!(tree.nearest(Vec3::splat(-0.1)).index, 500);
        assert_eq!(tree.within_radius(Vec3::splat(0.5), 1e-3).len(), 500);
    }
}
