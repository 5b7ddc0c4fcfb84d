//! The centre offsets of a four-output network at work: each object pixel votes for the
//! centre of its instance (its position plus the predicted offset), and the votes cut a seed
//! that joins two objects ([`cut_seeds`]) and join the pieces of one object
//! ([`merge_pieces`]). Pixel coordinates throughout (x right, y down, at the depth map's
//! resolution).
//!
//! The idea is Panoptic-DeepLab's offset regression (Cheng et al., CVPR 2020,
//! <https://arxiv.org/abs/1911.10194>) on top of the instance cores rather than in place of
//! them: where the votes agree, the cores' instances stand as they are.

use serde::{Deserialize, Serialize};

use crate::{Result, SegError};

/// The settings of the centre votes' post-processing (`PostConfig::centres`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CentreConfig {
    /// A seed is cut in two when its pixels' votes form two groups (2-means) whose centres lie
    /// farther apart than `split` × √(s₁² + s₂²), s the groups' root-mean-square distances
    /// of their votes to their centre; each part is cut again the same way. 0: never.
    pub split: f32,
    /// Each part of a cut holds at least this share of the pixels it is cut from (and
    /// `min_pixels`).
    pub min_share: f32,
    /// Two touching instances (at least `min_contact` pairs of 4-neighbours, within the
    /// relative depth step) become one when their mean votes lie closer than `merge` ×
    /// √(s₁² + s₂²). 0: never.
    pub merge: f32,
    /// See `merge`.
    pub min_contact: usize,
    /// Network pixels added (in quadrature) to both rules' spread √(s₁² + s₂²): the votes
    /// do not resolve distances below the network's pixel, so votes that agree to within it
    /// are one centre whatever their spread. Without it, near-perfect votes (spread ≈ 0) cut
    /// an object at any rounding difference and never join its pieces. Files without it get
    /// the default.
    #[serde(default = "default_spread_floor")]
    pub spread_floor: f32,
}

fn default_spread_floor() -> f32 {
    1.0
}

impl Default for CentreConfig {
    fn default() -> Self {
        CentreConfig {
            split: 2.0,
            min_share: 0.15,
            merge: 1.0,
            min_contact: 3,
            spread_floor: default_spread_floor(),
        }
    }
}

impl CentreConfig {
    pub fn validate(&self) -> Result<()> {
        let ok = |v: f32| v.is_finite() && v >= 0.0;
        if !(ok(self.split)
            && ok(self.merge)
            && ok(self.spread_floor)
            && (0.0..0.5).contains(&self.min_share))
        {
            return Err(SegError::Config(format!(
                "centres: split {}, merge {} and spread_floor {} must be finite and not negative, \
                 min_share {} in [0, 0.5)",
                self.split, self.merge, self.spread_floor, self.min_share
            )));
        }
        Ok(())
    }
}

/// Where each pixel of a `width`-wide map says its instance's centre is, in pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct CentreVotes {
    pub width: u32,
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    /// One network pixel, in pixels of this map: the finest distance the votes resolve.
    pub cell: f32,
}

impl CentreVotes {
    /// Votes from offsets at the depth map's resolution (`dx`, `dy`, row-major `width` wide),
    /// each in units of `scale_x` / `scale_y` pixels, from a network whose pixel is `cell`
    /// pixels of this map.
    pub fn from_offsets(
        dx: &[f32],
        dy: &[f32],
        width: u32,
        scale_x: f32,
        scale_y: f32,
        cell: f32,
    ) -> Self {
        let w = width as usize;
        CentreVotes {
            width,
            cell,
            x: dx
                .iter()
                .enumerate()
                .map(|(i, &o)| (i % w) as f32 + o * scale_x)
                .collect(),
            y: dy
                .iter()
                .enumerate()
                .map(|(i, &o)| (i / w) as f32 + o * scale_y)
                .collect(),
        }
    }

    fn at(&self, i: usize) -> [f64; 2] {
        [self.x[i] as f64, self.y[i] as f64]
    }

    /// The mean vote of `pixels` and the root-mean-square distance of their votes to it.
    fn centre(&self, pixels: &[usize]) -> ([f64; 2], f64) {
        let n = pixels.len().max(1) as f64;
        let mut c = [0.0; 2];
        for &i in pixels {
            let v = self.at(i);
            c[0] += v[0] / n;
            c[1] += v[1] / n;
        }
        let s = pixels.iter().map(|&i| dist2(self.at(i), c)).sum::<f64>() / n;
        (c, s.sqrt())
    }

    /// The spread two groups of votes are judged by: √(s₁² + s₂² + (floor · cell)²).
    fn joint_spread(&self, s1: f64, s2: f64, cfg: &CentreConfig) -> f64 {
        let floor = cfg.spread_floor as f64 * self.cell as f64;
        (s1 * s1 + s2 * s2 + floor * floor).sqrt()
    }
}

fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// Cuts of `pixels` by their votes (see [`CentreConfig::split`]); `pixels` itself when its
/// votes form one group. At most 16 parts (four rounds of halving).
pub fn cut(
    pixels: &[usize],
    votes: &CentreVotes,
    cfg: &CentreConfig,
    min_pixels: usize,
) -> Vec<Vec<usize>> {
    let least = |n: usize| ((cfg.min_share as f64 * n as f64).ceil() as usize).max(min_pixels);
    let mut done = Vec::new();
    let mut todo = vec![(pixels.to_vec(), 0u32)];
    while let Some((part, depth)) = todo.pop() {
        let halves = if cfg.split > 0.0 && depth < 4 && part.len() >= 2 * least(part.len()) {
            two_means(&part, votes)
        } else {
            None
        };
        match halves {
            Some((a, b)) if a.len().min(b.len()) >= least(part.len()) => {
                let ((ca, sa), (cb, sb)) = (votes.centre(&a), votes.centre(&b));
                if dist2(ca, cb).sqrt() > cfg.split as f64 * votes.joint_spread(sa, sb, cfg) {
                    todo.push((a, depth + 1));
                    todo.push((b, depth + 1));
                } else {
                    done.push(part);
                }
            }
            _ => done.push(part),
        }
    }
    done.sort_by_key(|p| p.first().copied());
    done
}

/// 2-means of the votes of `pixels`, started from a cut through their mean across their
/// principal axis; `None` when the votes do not spread.
fn two_means(pixels: &[usize], votes: &CentreVotes) -> Option<(Vec<usize>, Vec<usize>)> {
    let (c, _) = votes.centre(pixels);
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for &i in pixels {
        let v = votes.at(i);
        let (dx, dy) = (v[0] - c[0], v[1] - c[1]);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    // The principal axis of the 2×2 covariance.
    let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let axis = [angle.cos(), angle.sin()];
    let side = |v: [f64; 2], a: [f64; 2], b: [f64; 2]| dist2(v, a) <= dist2(v, b);
    let mut assign: Vec<bool> = pixels
        .iter()
        .map(|&i| {
            let v = votes.at(i);
            (v[0] - c[0]) * axis[0] + (v[1] - c[1]) * axis[1] < 0.0
        })
        .collect();
    for _ in 0..10 {
        let (a, b) = partition(pixels, &assign);
        if a.is_empty() || b.is_empty() {
            return None;
        }
        let (ca, cb) = (votes.centre(&a).0, votes.centre(&b).0);
        let next: Vec<bool> = pixels.iter().map(|&i| side(votes.at(i), ca, cb)).collect();
        if next == assign {
            return Some((a, b));
        }
        assign = next;
    }
    let (a, b) = partition(pixels, &assign);
    (!a.is_empty() && !b.is_empty()).then_some((a, b))
}

/// `pixels` split by `first`: those marked, then the others.
fn partition(pixels: &[usize], first: &[bool]) -> (Vec<usize>, Vec<usize>) {
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for (&i, &f) in pixels.iter().zip(first) {
        if f { a.push(i) } else { b.push(i) }
    }
    (a, b)
}

/// The seeds (groups of pixel indices) with every seed cut by its votes ([`cut`]).
pub fn cut_seeds(
    seeds: Vec<Vec<usize>>,
    votes: &CentreVotes,
    cfg: &CentreConfig,
    min_pixels: usize,
) -> Vec<Vec<usize>> {
    seeds
        .into_iter()
        .flat_map(|s| cut(&s, votes, cfg, min_pixels))
        .collect()
}

/// Joins touching instances whose votes agree (see [`CentreConfig::merge`]): `label` holds
/// each pixel's instance (`u32::MAX`: none), as wide as `votes`; `continuous(i, j)` says whether
/// neighbouring pixels `i` and `j` lie on one surface. Labels are rewritten in place to the
/// smallest label of each merged group.
pub fn merge_pieces(
    label: &mut [u32],
    votes: &CentreVotes,
    cfg: &CentreConfig,
    continuous: impl Fn(usize, usize) -> bool,
) {
    const NONE: u32 = u32::MAX;
    if cfg.merge <= 0.0 {
        return;
    }
    let width = votes.width as usize;
    let count = label
        .iter()
        .filter(|&&l| l != NONE)
        .max()
        .map_or(0, |&l| l + 1) as usize;
    let mut pixels: Vec<Vec<usize>> = vec![Vec::new(); count];
    for (i, &l) in label.iter().enumerate() {
        if l != NONE {
            pixels[l as usize].push(i);
        }
    }
    let stats: Vec<([f64; 2], f64)> = pixels.iter().map(|p| votes.centre(p)).collect();
    let mut contact: std::collections::BTreeMap<(u32, u32), usize> = Default::default();
    let n = label.len();
    for i in 0..n {
        let a = label[i];
        if a == NONE {
            continue;
        }
        let right = (i % width + 1 < width).then_some(i + 1);
        let down = (i + width < n).then_some(i + width);
        for j in [right, down].into_iter().flatten() {
            let b = label[j];
            if b != NONE && b != a && continuous(i, j) {
                *contact.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
    }
    let mut parent: Vec<u32> = (0..count as u32).collect();
    fn root(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            parent[x as usize] = parent[parent[x as usize] as usize];
            x = parent[x as usize];
        }
        x
    }
    for (&(a, b), &k) in &contact {
        if k < cfg.min_contact {
            continue;
        }
        let ((ca, sa), (cb, sb)) = (stats[a as usize], stats[b as usize]);
        if dist2(ca, cb).sqrt() < cfg.merge as f64 * votes.joint_spread(sa, sb, cfg) {
            let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
            if ra != rb {
                parent[ra.max(rb) as usize] = ra.min(rb);
            }
        }
    }
    for l in label.iter_mut() {
        if *l != NONE {
            *l = root(&mut parent, *l);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic, continuous-looking value in [−1.8, 1.8] px for index `i`.
    fn jitter(i: usize) -> f32 {
        let r = ((i as f32 * 12.9898).sin() * 43_758.547).fract().abs();
        (r - 0.5) * 3.6
    }

    /// Votes of a `w`×`h` map: each pixel votes for the centre its column half names
    /// (left half: `left`, right half: `right`), plus a small deterministic jitter.
    fn two_centre_votes(w: usize, h: usize, left: [f32; 2], right: [f32; 2]) -> CentreVotes {
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for i in 0..w * h {
            let c = if i % w < w / 2 { left } else { right };
            x.push(c[0] + jitter(i));
            y.push(c[1] + jitter(i + 100_003));
        }
        CentreVotes {
            width: w as u32,
            x,
            y,
            cell: 1.0,
        }
    }

    #[test]
    fn a_seed_whose_pixels_vote_for_two_centres_is_cut_between_them() {
        let (w, h) = (20, 10);
        let votes = two_centre_votes(w, h, [5.0, 5.0], [15.0, 5.0]);
        let all: Vec<usize> = (0..w * h).collect();
        let parts = cut(&all, &votes, &CentreConfig::default(), 5);
        assert_eq!(parts.len(), 2);
        for p in &parts {
            let left = p.iter().filter(|&&i| i % w < w / 2).count();
            assert!(left == 0 || left == p.len(), "a part mixes the halves");
            assert_eq!(p.len(), w * h / 2);
        }
    }

    #[test]
    fn a_seed_whose_pixels_vote_for_one_centre_stays_whole() {
        let (w, h) = (20, 10);
        let votes = two_centre_votes(w, h, [10.0, 5.0], [10.0, 5.0]);
        let all: Vec<usize> = (0..w * h).collect();
        assert_eq!(cut(&all, &votes, &CentreConfig::default(), 5), vec![all]);
        // Two centres 2 px apart in the jitter of ±1.8 px: one object.
        let votes = two_centre_votes(w, h, [9.0, 5.0], [11.0, 5.0]);
        let all: Vec<usize> = (0..w * h).collect();
        assert_eq!(cut(&all, &votes, &CentreConfig::default(), 5).len(), 1);
        // Cutting off: whole.
        let votes = two_centre_votes(w, h, [5.0, 5.0], [15.0, 5.0]);
        let off = CentreConfig {
            split: 0.0,
            ..CentreConfig::default()
        };
        assert_eq!(cut(&all, &votes, &off, 5).len(), 1);
    }

    #[test]
    fn a_cut_never_leaves_a_part_below_its_share() {
        // 190 pixels vote left, 10 right: the 10 are under 15 % and stay with the rest.
        let (w, h) = (20, 10);
        let mut votes = two_centre_votes(w, h, [5.0, 5.0], [5.0, 5.0]);
        for i in 0..10 {
            votes.x[i] = 15.0;
        }
        let all: Vec<usize> = (0..w * h).collect();
        assert_eq!(cut(&all, &votes, &CentreConfig::default(), 5).len(), 1);
    }

    #[test]
    fn touching_pieces_that_vote_for_one_centre_are_merged_and_others_are_not() {
        // Three pieces side by side: 0 and 1 vote for one centre, 2 for another.
        let (w, h) = (30, 6);
        let mut label: Vec<u32> = (0..w * h).map(|i| ((i % w) / 10) as u32).collect();
        let votes = CentreVotes {
            width: w as u32,
            x: (0..w * h)
                .map(|i| if i % w >= 20 { 25.0 } else { 10.0 } + jitter(i))
                .collect(),
            y: vec![3.0; w * h],
            cell: 1.0,
        };
        merge_pieces(&mut label, &votes, &CentreConfig::default(), |_, _| true);
        assert!(
            label[..]
                .iter()
                .enumerate()
                .all(|(i, &l)| l == if i % w < 20 { 0 } else { 2 })
        );
        // Across a depth step, nothing merges.
        let mut label: Vec<u32> = (0..w * h).map(|i| ((i % w) / 10) as u32).collect();
        merge_pieces(&mut label, &votes, &CentreConfig::default(), |_, _| false);
        assert!(
            label
                .iter()
                .enumerate()
                .all(|(i, &l)| l == ((i % w) / 10) as u32)
        );
    }

    #[test]
    fn votes_that_agree_to_within_the_network_pixel_neither_cut_an_object_nor_keep_its_pieces_apart()
     {
        // Exact votes (a perfect network): the two halves differ only by rounding, so their
        // spread is ≈ 0 and the relative rule alone cuts them and never joins them.
        let (w, h) = (20, 10);
        let votes = CentreVotes {
            width: w as u32,
            x: (0..w * h)
                .map(|i| 10.0 + if i % w < w / 2 { 0.0 } else { 0.01 })
                .collect(),
            y: vec![5.0; w * h],
            cell: 2.5,
        };
        let all: Vec<usize> = (0..w * h).collect();
        let bare = CentreConfig {
            spread_floor: 0.0,
            ..CentreConfig::default()
        };
        assert_eq!(cut(&all, &votes, &bare, 5).len(), 2);
        assert_eq!(
            cut(&all, &votes, &CentreConfig::default(), 5),
            vec![all.clone()]
        );
        let halves = || -> Vec<u32> { (0..w * h).map(|i| ((i % w) / 10) as u32).collect() };
        let mut label = halves();
        merge_pieces(&mut label, &votes, &bare, |_, _| true);
        assert_eq!(label, halves());
        merge_pieces(&mut label, &votes, &CentreConfig::default(), |_, _| true);
        assert!(label.iter().all(|&l| l == 0));
        // Two objects' exact centres 4 network pixels apart are still cut.
        let two = CentreVotes {
            x: (0..w * h)
                .map(|i| if i % w < w / 2 { 5.0 } else { 15.0 })
                .collect(),
            ..votes
        };
        assert_eq!(cut(&all, &two, &CentreConfig::default(), 5).len(), 2);
    }
}
