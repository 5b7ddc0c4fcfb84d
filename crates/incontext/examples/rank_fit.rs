//! Fits the weights of the instance ranking (`InstanceCandidate::fit`) on BOP clutter sets, as
//! `docs/decisions.md` ("Ranking the instances by the model's views") did:
//!
//! ```text
//! cargo run --release -p incontext --example rank_fit -- DIR/clutter [DIR2/clutter …]
//! ```
//!
//! For every target of each set, the segmentation network's plausible instances of its own
//! input size (what `register` tries, before pieces cut from heaps), each labelled by whether
//! it is the target's instance (IoU ≥ 0.5 with a true visible mask of the target). A logistic
//! regression (L2 penalty ½‖w‖², intercept free, Newton's method) on ln(pixels),
//! |ln(size ratio / 0.8)|, cut off by the border, and the shape distance (capped at 3) gives
//! the weights; then, per set, how often the target's instance stands first, in the first 3
//! and the first 8 in the shipped ranking and in the refitted one. `--features FILE` also
//! writes one JSON line per instance. Deterministic: the network and the fit have no random
//! choice.
use std::io::Write;

use ic_data::CorpusOptions;
use ic_data::bop::{BopDataset, BopLoadOptions};
use incontext::{Object, Pipeline};

/// One instance: its target (set, index), features, label, and place in the shipped ranking.
struct Row {
    target: (usize, usize),
    x: [f64; 4],
    right: bool,
    shipped_fit: f64,
}

/// Logistic regression with weights `w` (4) and intercept `b`: minimises
/// Σ log(1 + exp(−yᵢ(w·xᵢ + b))) + ½‖w‖² by Newton's method (`ic_eval::Logistic`, the features
/// as they are, not standardised).
fn fit_logistic(rows: &[Row]) -> anyhow::Result<([f64; 4], f64)> {
    let names = ["ln_pixels", "size", "truncated", "shape"]
        .map(String::from)
        .to_vec();
    let x: Vec<Vec<f64>> = rows.iter().map(|r| r.x.to_vec()).collect();
    let right: Vec<bool> = rows.iter().map(|r| r.right).collect();
    let options = ic_eval::LogisticOptions {
        l2: 1.0,
        standardise: false,
        ..ic_eval::LogisticOptions::default()
    };
    let m = ic_eval::Logistic::fit(names, &x, &right, options).map_err(anyhow::Error::msg)?;
    let w = &m.weights;
    Ok(([w[0], w[1], w[2], w[3]], m.bias))
}

/// (targets whose instance was found, first, in the first 3, in the first 8) when each
/// target's instances are ordered by `score`, highest first.
fn top_k(rows: &[&Row], score: impl Fn(&Row) -> f64) -> (usize, usize, usize, usize) {
    let mut by: std::collections::BTreeMap<(usize, usize), Vec<&Row>> = Default::default();
    for r in rows {
        by.entry(r.target).or_default().push(r);
    }
    let (mut has, mut first, mut three, mut eight) = (0, 0, 0, 0);
    for v in by.values_mut() {
        if !v.iter().any(|r| r.right) {
            continue;
        }
        has += 1;
        v.sort_by(|a, b| score(b).total_cmp(&score(a)));
        let pos = v.iter().position(|r| r.right).unwrap_or(usize::MAX);
        first += usize::from(pos == 0);
        three += usize::from(pos < 3);
        eight += usize::from(pos < 8);
    }
    (has, first, three, eight)
}

fn main() -> anyhow::Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut out = None;
    if let Some(i) = args.iter().position(|a| a == "--features") {
        anyhow::ensure!(i + 1 < args.len(), "--features needs a file");
        out = Some(std::fs::File::create(&args[i + 1])?);
        args.drain(i..=i + 1);
    }
    anyhow::ensure!(!args.is_empty(), "usage: rank_fit [--features FILE] DIR…");
    let pipeline = Pipeline::builder()
        .segmentation(true)
        .second_pose(false)
        .build()?;
    let mut rows = Vec::new();
    for (set, dir) in args.iter().enumerate() {
        let ds = BopDataset::open(dir, "test", CorpusOptions::default())?;
        let mut objects: std::collections::HashMap<String, Object> = Default::default();
        for (t, target) in ds.targets().iter().enumerate() {
            let samples: Vec<_> = ds
                .instances_of(target)
                .into_iter()
                .map(|i| ds.load(i, &BopLoadOptions::default()))
                .collect::<Result<_, _>>()?;
            let Some(first) = samples.first() else {
                continue;
            };
            if !objects.contains_key(&first.object_id) {
                let corpus = ds.corpus();
                let position = corpus
                    .position(&first.object_id)
                    .ok_or_else(|| anyhow::anyhow!("{} not in the corpus", first.object_id))?;
                let obj = corpus.object(position)?;
                let object = Object::from_normalised(
                    Some(obj.mesh.clone()),
                    obj.normalisation,
                    obj.model_points.clone(),
                )?;
                objects.insert(first.object_id.clone(), object);
            }
            let object = &objects[&first.object_id];
            let Ok(candidates) =
                pipeline.instance_candidates(object, &first.depth, &first.intrinsics)
            else {
                continue;
            };
            for c in candidates
                .iter()
                .filter(|c| c.plausible && !c.cut && c.input == 0)
            {
                let iou = samples
                    .iter()
                    .map(|s| ic_seg::post::iou(&c.mask, &s.mask_visib))
                    .fold(0.0, f64::max);
                let row = Row {
                    target: (set, t),
                    x: c.rank_features(),
                    right: iou >= 0.5,
                    shipped_fit: c.fit(),
                };
                if let Some(f) = out.as_mut() {
                    writeln!(
                        f,
                        "{}",
                        serde_json::json!({
                            "set": dir, "scene_id": target.scene_id, "im_id": target.im_id,
                            "obj_id": target.obj_id, "features": row.x, "iou": iou,
                            "fit": row.shipped_fit, "pixels": c.pixels,
                            "size_ratio": c.size_ratio, "parts": c.parts,
                        })
                    )?;
                }
                rows.push(row);
            }
        }
    }
    let (w, b) = fit_logistic(&rows)?;
    println!(
        "weights: ln(pixels) {:.3}, size {:.3}, truncated {:.3}, shape {:.3}; intercept {:.3} ({} instances, {} of targets)",
        w[0],
        -w[1],
        -w[2],
        -w[3],
        b,
        rows.len(),
        rows.iter().filter(|r| r.right).count()
    );
    for (set, dir) in args.iter().enumerate() {
        let these: Vec<&Row> = rows.iter().filter(|r| r.target.0 == set).collect();
        let shipped = top_k(&these, |r| r.shipped_fit);
        let refit = top_k(&these, |r| r.x.iter().zip(&w).map(|(x, w)| x * w).sum());
        println!(
            "{dir}: targets with their instance found {}; first / first 3 / first 8: shipped {} / {} / {}, refitted {} / {} / {}",
            shipped.0, shipped.1, shipped.2, shipped.3, refit.1, refit.2, refit.3
        );
    }
    Ok(())
}
