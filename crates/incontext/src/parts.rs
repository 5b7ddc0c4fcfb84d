//! Instances that are parts of one object: the segmentation network trained on clutter may cut
//! a lone object of several parts (a mug and its handle, a composite of boxes and cylinders)
//! along its concave edges into instances each too small to be the model. This module finds
//! groups of touching instances that together fit the model's size, so that the pipeline can
//! register the group as one candidate (see [`crate::pipeline::InstanceCandidate::parts`]).
//! The reverse also happens, a heap of objects left as one instance: [`heap_pieces`] cuts it
//! into candidates of the model's size ([`crate::pipeline::InstanceCandidate::cut`]).
//!
//! Depths are in the object's normalised units along the camera's optical axis; pixel
//! coordinates are row-major (x right, y down).

use std::collections::HashMap;

use ic_geometry::{DepthImage, Mask};

/// Pixels at most this far apart (in each of x and y) can be a contact between two instances:
/// the segmentation's post-processing leaves a gap of a pixel or two between neighbours.
pub const CONTACT_RADIUS_PX: i64 = 2;

/// Fewer contact pixel pairs than this between two instances is no contact.
pub const MIN_CONTACTS: usize = 3;

/// How many pixel pairs of each pair of instances touch in the image: pairs at most
/// [`CONTACT_RADIUS_PX`] apart whose depths differ by at most `max_depth_gap` (the depth's
/// units). Parts of one object meet at a concave edge (depth continuous) or where one hides
/// the other (a depth jump smaller than the object), so the gap allowed is of the object's
/// size, and the union's size decides ([`merged_groups`]). Keys are `(a, b)` with `a < b`,
/// indices into `masks`; a pixel in several masks counts for the last.
pub fn contacts(
    masks: &[&Mask],
    depth: &DepthImage,
    max_depth_gap: f32,
) -> HashMap<(usize, usize), usize> {
    let (w, h) = (depth.width as i64, depth.height as i64);
    let mut label = vec![u32::MAX; (w * h) as usize];
    for (k, m) in masks.iter().enumerate() {
        if m.width != depth.width || m.height != depth.height {
            continue;
        }
        for (i, &on) in m.data.iter().enumerate() {
            if on {
                label[i] = k as u32;
            }
        }
    }
    let r = CONTACT_RADIUS_PX;
    // Each unordered pixel pair once: the rest of this row to the right, and the next rows.
    let offsets: Vec<(i64, i64)> = (1..=r)
        .map(|dx| (dx, 0))
        .chain((1..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))))
        .collect();
    let valid = |z: f32| z.is_finite() && z > 0.0;
    let mut out: HashMap<(usize, usize), usize> = HashMap::new();
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            let a = label[i];
            if a == u32::MAX || !valid(depth.data[i]) {
                continue;
            }
            for &(dx, dy) in &offsets {
                let (u, v) = (x + dx, y + dy);
                if u < 0 || u >= w || v >= h {
                    continue;
                }
                let j = (v * w + u) as usize;
                let b = label[j];
                if b == u32::MAX || b == a || !valid(depth.data[j]) {
                    continue;
                }
                if (depth.data[i] - depth.data[j]).abs() <= max_depth_gap {
                    let key = (a.min(b) as usize, a.max(b) as usize);
                    *out.entry(key).or_default() += 1;
                }
            }
        }
    }
    out
}

/// Groups of at least two touching instances that together fit the model's size, each as
/// sorted indices. Only instances too small to be the whole object alone (`ratios[i]` below
/// `lower`) are merged; a group grows from each of them by the touching one with the most
/// contacts ([`MIN_CONTACTS`] at least) while the group's size ratio (`ratio_of`, the visible
/// extent of the union over the model's diameter) stays at most `upper`, and is kept when it
/// reaches `lower`. Duplicates are dropped; the order is that of the seeds.
pub fn merged_groups(
    ratios: &[f64],
    contacts: &HashMap<(usize, usize), usize>,
    lower: f64,
    upper: f64,
    mut ratio_of: impl FnMut(&[usize]) -> f64,
) -> Vec<Vec<usize>> {
    let small = |i: usize| ratios[i] < lower;
    let touching = |a: usize, b: usize| contacts.get(&(a.min(b), a.max(b))).copied().unwrap_or(0);
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for seed in (0..ratios.len()).filter(|&i| small(i)) {
        let mut group = vec![seed];
        let mut ratio = ratios[seed];
        let mut rejected: Vec<usize> = Vec::new();
        loop {
            // The neighbour with the most contacts with the group (ties: the lowest index).
            let next = (0..ratios.len())
                .filter(|&j| small(j) && !group.contains(&j) && !rejected.contains(&j))
                .map(|j| (j, group.iter().map(|&g| touching(g, j)).sum::<usize>()))
                .filter(|&(_, c)| c >= MIN_CONTACTS)
                .max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0)));
            let Some((j, _)) = next else { break };
            let mut grown = group.clone();
            grown.push(j);
            let r = ratio_of(&grown);
            if r <= upper {
                group = grown;
                ratio = r;
            } else {
                rejected.push(j);
            }
        }
        group.sort_unstable();
        if group.len() > 1 && ratio >= lower && !groups.contains(&group) {
            groups.push(group);
        }
    }
    groups
}

/// Pieces of an instance too large to be the model (a heap of objects the network did not
/// split), each a candidate for one object of the heap, nearest first. `points` are the
/// instance's back-projected pixels (camera frame, the same units as `diameter`, the model's
/// diameter).
///
/// The nearest pixel not yet covered seeds a piece: the object it lies on is taken to be
/// centred `0.3·diameter` behind it along its viewing ray, and the piece holds the instance's
/// pixels within `0.5·diameter` of that centre; those within `0.35·diameter` seed no other.
/// Pieces under `min_pixels`, or sharing more than half their pixels with pieces already
/// cut, are dropped; at most `max_pieces` are returned, each as sorted indices into
/// `points`.
pub fn heap_pieces(
    points: &[ic_geometry::glam::Vec3],
    diameter: f32,
    min_pixels: usize,
    max_pieces: usize,
) -> Vec<Vec<usize>> {
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by(|&a, &b| points[a].z.total_cmp(&points[b].z).then(a.cmp(&b)));
    let mut covered = vec![false; points.len()];
    let mut taken = vec![false; points.len()];
    let mut pieces: Vec<Vec<usize>> = Vec::new();
    for &seed in &order {
        if pieces.len() >= max_pieces {
            break;
        }
        if covered[seed] {
            continue;
        }
        let p = points[seed];
        let centre = p + p.normalize_or_zero() * (0.3 * diameter);
        let (r_piece, r_cover) = (0.5 * diameter, 0.35 * diameter);
        let mut piece = Vec::new();
        for (i, q) in points.iter().enumerate() {
            let d = q.distance(centre);
            if d <= r_piece {
                piece.push(i);
            }
            if d <= r_cover {
                covered[i] = true;
            }
        }
        covered[seed] = true;
        // Mostly of a piece already cut (the rim of an object whose front seeded one): not
        // another object.
        let shared = piece.iter().filter(|&&i| taken[i]).count();
        if piece.len() >= min_pixels.max(1) && 2 * shared <= piece.len() {
            for &i in &piece {
                taken[i] = true;
            }
            pieces.push(piece);
        }
    }
    pieces
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::Image;

    fn mask(w: u32, h: u32, f: impl Fn(u32, u32) -> bool) -> Mask {
        let mut m = Mask::filled(w, h, false);
        for y in 0..h {
            for x in 0..w {
                m.data[(y * w + x) as usize] = f(x, y);
            }
        }
        m
    }

    #[test]
    fn instances_across_a_one_pixel_gap_touch_unless_their_depths_differ_by_more_than_the_gap() {
        let (w, h) = (20, 10);
        // Left block x < 9 at depth 1.0; right block x > 9; column 9 is the gap.
        let left = mask(w, h, |x, _| x < 9);
        let right = mask(w, h, |x, _| x > 9);
        let flat = Image {
            width: w,
            height: h,
            data: vec![1.0f32; (w * h) as usize],
        };
        let c = contacts(&[&left, &right], &flat, 0.3);
        // Pairs 2 px apart across the gap: from x = 8 to x = 10, dy in -2..=2 clipped.
        assert!(c[&(0, 1)] >= h as usize, "{c:?}");
        let mut stepped = flat.clone();
        for y in 0..h {
            for x in 10..w {
                stepped.data[(y * w + x) as usize] = 1.5;
            }
        }
        assert_eq!(
            contacts(&[&left, &right], &stepped, 0.6)[&(0, 1)],
            c[&(0, 1)]
        );
        assert!(contacts(&[&left, &right], &stepped, 0.3).is_empty());
        // Masks apart by more than the radius do not touch.
        let far = mask(w, h, |x, _| x > 11);
        assert!(contacts(&[&left, &far], &flat, 0.3).is_empty());
    }

    #[test]
    fn a_heap_is_cut_into_pieces_one_per_object_nearest_first() {
        use ic_geometry::glam::Vec3;
        // Two balls of diameter 1 side by side, the right one 0.5 nearer the camera: the
        // points of their camera-facing halves.
        let mut points = Vec::new();
        for (cx, cz) in [(-0.6f32, 3.0f32), (0.6, 2.5)] {
            for i in 0..20 {
                for j in 0..20 {
                    let (a, b) = (
                        std::f32::consts::PI * i as f32 / 19.0,
                        std::f32::consts::PI * j as f32 / 19.0,
                    );
                    let n = Vec3::new(a.cos() * b.sin(), b.cos(), -a.sin() * b.sin());
                    points.push(Vec3::new(cx, 0.0, cz) + 0.5 * n);
                }
            }
        }
        let pieces = heap_pieces(&points, 1.0, 10, 6);
        assert!(pieces.len() >= 2, "{}", pieces.len());
        // The first piece is the nearer ball (its front; the rim seen edge-on is left out),
        // and almost nothing of the other.
        let right = |i: &usize| points[*i].x > 0.0;
        let first = &pieces[0];
        let (r, l) = (
            first.iter().filter(|i| right(i)).count(),
            first.iter().filter(|i| !right(i)).count(),
        );
        assert!(
            r >= 150 && l <= 20,
            "{r} of the nearer ball, {l} of the other"
        );
        // Some later piece is mostly the other ball.
        assert!(
            pieces[1..]
                .iter()
                .any(|p| p.iter().filter(|i| !right(i)).count() >= 150)
        );
        // The cap holds.
        assert_eq!(heap_pieces(&points, 1.0, 10, 1).len(), 1);
    }

    #[test]
    fn parts_too_small_alone_merge_until_the_model_size_and_whole_objects_stay_apart() {
        // Three parts of 0.4 each in a chain, and a whole object (0.8) touching the last.
        let ratios = [0.4, 0.4, 0.4, 0.8];
        let contacts: HashMap<(usize, usize), usize> = [((0, 1), 10), ((1, 2), 10), ((2, 3), 50)]
            .into_iter()
            .collect();
        // The union's ratio: the sum of the parts' (a chain), capped nowhere.
        let sum = |g: &[usize]| g.iter().map(|&i| ratios[i]).sum::<f64>() * 0.8;
        let groups = merged_groups(&ratios, &contacts, 0.6, 1.0, sum);
        // 0+1 = 0.64, +2 = 0.96 <= 1.0: the three parts, never the whole object 3.
        assert_eq!(groups, vec![vec![0, 1, 2]]);
        // A tighter upper bound stops at two parts; seeds from either end give both pairs.
        let groups = merged_groups(&ratios, &contacts, 0.6, 0.7, sum);
        assert_eq!(groups, vec![vec![0, 1], vec![1, 2]]);
        // Too few contacts: nothing merges.
        let weak: HashMap<(usize, usize), usize> = [((0, 1), 2)].into_iter().collect();
        assert!(merged_groups(&ratios, &weak, 0.6, 1.0, sum).is_empty());
    }
}
