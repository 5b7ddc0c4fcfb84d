use std::sync::Arc;
use std::time::Instant;
use ic_data::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(20);
    let dist: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let t = Instant::now();
    let corpus = Arc::new(Corpus::procedural(20, Split::Test, 1, CorpusOptions::default()).unwrap());
    corpus.preload().unwrap();
    println!("preload 20: {:?}", t.elapsed());
    let g = ObjectSampleGenerator::new(corpus.clone(), ObjectSampleConfig::default(), 3).unwrap();
    let t = Instant::now();
    let mut vox = vec![]; let mut inl = vec![];
    for i in 0..n { let s = g.sample(i).unwrap(); vox.push(s.observed_voxels); inl.push(s.inlier_count()); }
    println!("object: {:?}/sample; voxels {:?}; inliers {:?}", t.elapsed() / n as u32, vox, inl);
    let mut cfg = RoomSampleConfig::default();
    if dist > 0.0 { cfg.distance = (dist, dist); }
    let g = RoomSampleGenerator::new(corpus.clone(), cfg, 3).unwrap();
    let t = Instant::now();
    let mut rates = vec![]; let mut pts = vec![]; let mut obj = vec![];
    for i in 0..n { let s = g.sample(i).unwrap(); rates.push((s.inlier_rate * 1000.0).round() / 10.0); pts.push(s.scene_points.len()); obj.push(s.object_point_count()); }
    println!("room: {:?}/sample", t.elapsed() / n as u32);
    rates.sort_by(|a, b| a.partial_cmp(b).unwrap()); pts.sort(); obj.sort();
    println!("rates% {:?}\npts {:?}\nobj {:?}", rates, pts, obj);
}
