//! Instance segmentation quality on scenes with many objects: predicted instance masks
//! against the true visible masks of one image (pixels of one resolution).
//!
//! - A true instance is **found** when some predicted instance overlaps it with IoU ≥ 0.5
//!   (at most one prediction can, since two masks with IoU > 0.5 with a third overlap).
//! - **Over-segmentation**: a true instance of which two or more predicted instances each hold
//!   at least 20 % of the pixels (one object cut in pieces).
//! - **Under-segmentation**: a predicted instance holding at least 20 % of the pixels of two or
//!   more true instances (objects merged, e.g. a heap of cups as one).

use ic_geometry::Mask;
use serde::Serialize;

/// The share of a mask's pixels that counts as "holding" it for over/under-segmentation.
pub const HOLD_FRACTION: f64 = 0.2;

/// What one image's predicted instances did with its true instances.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct InstanceMatch {
    /// For each true instance, the best IoU of any predicted instance (0 if none overlaps),
    /// and that prediction's index.
    pub best_iou: Vec<f64>,
    pub best_prediction: Vec<Option<usize>>,
    /// For each true instance, the largest share of its pixels that one predicted instance
    /// holds (low: cut in pieces or missed).
    pub best_cover: Vec<f64>,
    /// For each true instance, the share of its pixels that any predicted instance holds
    /// (low: not seen as an object at all).
    pub covered: Vec<f64>,
    /// For each true instance, the share of the largest holder's pixels that are its own (low:
    /// merged with its neighbours).
    pub holder_precision: Vec<f64>,
    pub over_segmented: usize,
    pub under_segmented: usize,
    pub predictions: usize,
}

impl InstanceMatch {
    /// True instances found (best IoU ≥ 0.5).
    pub fn found(&self) -> usize {
        self.best_iou.iter().filter(|&&i| i >= 0.5).count()
    }
}

/// Matches `predicted` against `truth` (all masks of one size; checked).
pub fn match_instances(predicted: &[&Mask], truth: &[&Mask]) -> Result<InstanceMatch, String> {
    let size = truth
        .first()
        .or(predicted.first())
        .map(|m| (m.width, m.height));
    for m in predicted.iter().chain(truth) {
        if Some((m.width, m.height)) != size {
            return Err(format!(
                "masks of different sizes: {}×{} vs {:?}",
                m.width, m.height, size
            ));
        }
    }
    let count = |m: &Mask| m.data.iter().filter(|&&b| b).count();
    let pred_px: Vec<usize> = predicted.iter().map(|m| count(m)).collect();
    let true_px: Vec<usize> = truth.iter().map(|m| count(m)).collect();
    // overlap[t][p]
    let overlap: Vec<Vec<usize>> = truth
        .iter()
        .map(|t| {
            predicted
                .iter()
                .map(|p| {
                    t.data
                        .iter()
                        .zip(&p.data)
                        .filter(|(a, b)| **a && **b)
                        .count()
                })
                .collect()
        })
        .collect();
    let mut out = InstanceMatch {
        predictions: predicted.len(),
        ..InstanceMatch::default()
    };
    let share = |a: usize, b: usize| if b > 0 { a as f64 / b as f64 } else { 0.0 };
    let mut any = vec![false; truth.first().map_or(0, |m| m.data.len())];
    for p in predicted {
        any.iter_mut().zip(&p.data).for_each(|(a, &b)| *a |= b);
    }
    let in_any: Vec<usize> = truth
        .iter()
        .map(|m| m.data.iter().zip(&any).filter(|(a, b)| **a && **b).count())
        .collect();
    for (t, row) in overlap.iter().enumerate() {
        let mut best = (0.0, None);
        let mut holders = 0;
        let holder = (0..row.len()).max_by_key(|&p| (row[p], std::cmp::Reverse(p)));
        let held = holder.map_or(0, |p| row[p]);
        out.best_cover.push(share(held, true_px[t]));
        out.covered.push(share(in_any[t], true_px[t]));
        out.holder_precision
            .push(holder.map_or(0.0, |p| share(row[p], pred_px[p])));
        for (p, &o) in row.iter().enumerate() {
            let union = true_px[t] + pred_px[p] - o;
            let iou = if union > 0 {
                o as f64 / union as f64
            } else {
                0.0
            };
            if o > 0 && iou > best.0 {
                best = (iou, Some(p));
            }
            holders += usize::from(true_px[t] > 0 && o as f64 >= HOLD_FRACTION * true_px[t] as f64);
        }
        out.best_iou.push(best.0);
        out.best_prediction.push(best.1);
        out.over_segmented += usize::from(holders >= 2);
    }
    for p in 0..predicted.len() {
        let held = overlap
            .iter()
            .zip(&true_px)
            .filter(|(row, px)| **px > 0 && row[p] as f64 >= HOLD_FRACTION * **px as f64)
            .count();
        out.under_segmented += usize::from(held >= 2);
    }
    Ok(out)
}

/// Instance segmentation quality over many images.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct InstanceSummary {
    pub images: usize,
    pub true_instances: usize,
    /// Images whose target (the first true instance given) was found.
    pub target_found_rate: f64,
    /// True instances found, over all true instances.
    pub recall: f64,
    /// Mean IoU of the found instances.
    pub matched_iou_mean: f64,
    /// Mean best IoU over all true instances (0 for a missed one).
    pub best_iou_mean: f64,
    pub over_segmented: usize,
    pub under_segmented: usize,
    pub predictions_per_image: f64,
    /// How the images' targets that were not found were missed.
    pub target_misses: TargetMisses,
}

/// The targets not found (best IoU < 0.5), by how they were missed.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct TargetMisses {
    /// Under half of the target's pixels are in any predicted instance: not seen as an object
    /// (e.g. a flat object on the table).
    pub not_object: usize,
    /// One instance holds at least half of the target but is mostly other objects.
    pub merged: usize,
    /// No instance holds half of the target, though instances cover it: cut in pieces.
    pub split: usize,
    /// An instance holds half of the target and is mostly the target, yet the IoU is under
    /// 0.5 (a large holder that spills over, or a small target).
    pub borderline: usize,
}

impl TargetMisses {
    /// How `m`'s target (its first true instance) was missed: `not_object`, `merged`,
    /// `split` or `borderline` (the fields' names), or `None` when it was found.
    pub fn kind(m: &InstanceMatch) -> Option<&'static str> {
        let first = |v: &[f64]| v.first().copied().unwrap_or(0.0);
        if m.best_iou.is_empty() || first(&m.best_iou) >= 0.5 {
            return None;
        }
        Some(if first(&m.covered) < 0.5 {
            "not_object"
        } else if first(&m.best_cover) < 0.5 {
            "split"
        } else if first(&m.holder_precision) < 0.5 {
            "merged"
        } else {
            "borderline"
        })
    }

    fn add(&mut self, m: &InstanceMatch) {
        match Self::kind(m) {
            Some("not_object") => self.not_object += 1,
            Some("split") => self.split += 1,
            Some("merged") => self.merged += 1,
            Some(_) => self.borderline += 1,
            None => {}
        }
    }
}

/// Sums per-image matches (each image's first true instance is its target).
pub fn summarise(matches: &[InstanceMatch]) -> InstanceSummary {
    let n = matches.len();
    let all: Vec<f64> = matches.iter().flat_map(|m| m.best_iou.clone()).collect();
    let found: Vec<f64> = all.iter().copied().filter(|&i| i >= 0.5).collect();
    let mean = |v: &[f64]| {
        if v.is_empty() {
            0.0
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    InstanceSummary {
        images: n,
        true_instances: all.len(),
        target_found_rate: matches
            .iter()
            .filter(|m| m.best_iou.first().is_some_and(|&i| i >= 0.5))
            .count() as f64
            / n.max(1) as f64,
        recall: found.len() as f64 / all.len().max(1) as f64,
        matched_iou_mean: mean(&found),
        best_iou_mean: mean(&all),
        over_segmented: matches.iter().map(|m| m.over_segmented).sum(),
        under_segmented: matches.iter().map(|m| m.under_segmented).sum(),
        predictions_per_image: matches.iter().map(|m| m.predictions).sum::<usize>() as f64
            / n.max(1) as f64,
        target_misses: matches.iter().fold(TargetMisses::default(), |mut t, m| {
            t.add(m);
            t
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask(rows: &[&str], c: char) -> Mask {
        let h = rows.len() as u32;
        let w = rows[0].len() as u32;
        Mask::from_vec(
            w,
            h,
            rows.iter()
                .flat_map(|r| r.chars().map(|x| x == c))
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn a_merge_is_under_segmentation_and_a_cut_is_over_segmentation() {
        // Truth: a (left) and b (right). Prediction 1 merges them; then a cut of a in two.
        let truth = ["aaabbb", "aaabbb"];
        let (a, b) = (mask(&truth, 'a'), mask(&truth, 'b'));
        let merged = mask(&["xxxxxx", "xxxxxx"], 'x');
        let m = match_instances(&[&merged], &[&a, &b]).unwrap();
        assert_eq!((m.under_segmented, m.over_segmented), (1, 0));
        assert_eq!(m.best_iou, vec![0.5, 0.5]);
        assert_eq!(m.best_cover, vec![1.0, 1.0]);
        assert_eq!(m.holder_precision, vec![0.5, 0.5]);
        let cut = ["ppqbbb", "ppqbbb"];
        let (p, q, r) = (mask(&cut, 'p'), mask(&cut, 'q'), mask(&cut, 'b'));
        let m = match_instances(&[&p, &q, &r], &[&a, &b]).unwrap();
        assert_eq!((m.under_segmented, m.over_segmented), (0, 1));
        assert_eq!(m.best_prediction, vec![Some(0), Some(2)]);
        assert_eq!(m.found(), 2);
        assert_eq!(m.best_cover, vec![2.0 / 3.0, 1.0]);
        assert_eq!(m.covered, vec![1.0, 1.0]);
        assert_eq!(m.holder_precision, vec![1.0, 1.0]);
        let s = summarise(&[m]);
        assert_eq!((s.images, s.true_instances, s.recall), (1, 2, 1.0));
        assert_eq!(s.target_found_rate, 1.0);
        assert_eq!(s.target_misses, TargetMisses::default());
        assert!(match_instances(&[&mask(&["x"], 'x')], &[&a]).is_err());
    }

    #[test]
    fn a_missed_target_is_counted_as_not_an_object_merged_split_or_borderline() {
        // One row of pixels; the target is the first true instance.
        let one = |row: &str, c: char| mask(&[row], c);
        let target = one("tttttt....", 't');
        let other = one("......oooo", 'o');
        let summary = |pred: &[&str]| {
            let masks: Vec<Mask> = pred.iter().map(|r| one(r, 'x')).collect();
            let refs: Vec<&Mask> = masks.iter().collect();
            summarise(&[match_instances(&refs, &[&target, &other]).unwrap()]).target_misses
        };
        let only = |f: fn(&mut TargetMisses) -> &mut usize| {
            let mut t = TargetMisses::default();
            *f(&mut t) = 1;
            t
        };
        assert_eq!(summary(&["xx........"]), only(|t| &mut t.not_object));
        assert_eq!(summary(&[]), only(|t| &mut t.not_object));
        // One instance over the target and the other object, and more: IoU 0.6 is found;
        // with half the target only, merged.
        assert_eq!(summary(&["xxxxxxxxxx"]), TargetMisses::default());
        assert_eq!(summary(&["...xxxxxxx"]), only(|t| &mut t.merged));
        assert_eq!(
            summary(&["xx........", "..xx......", "....xx...."]),
            only(|t| &mut t.split)
        );
        // Half the target and as much again of the other: cover and precision 0.5, IoU 1/3.
        assert_eq!(summary(&["...xxxxxx."]), only(|t| &mut t.borderline));
    }
}
