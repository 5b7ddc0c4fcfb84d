//! Times a training step and a forward pass of a preset (default `cpu`) at its batch size.
//! `cargo run --release -p ic_seg --example seg_step_timing [preset]`

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

use std::time::Instant;

use ic_geometry::{DepthImage, Mask};
use ic_seg::{SegConfig, SegExample};
use ic_train::SegTrainer;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let preset = std::env::args().nth(1).unwrap_or_else(|| "cpu".into());
    let mut cfg = SegConfig::preset(&preset)?;
    // Optional overrides for exploring sizes: SEG_CHANNELS=8,16,32,64 SEG_INPUT=160x120.
    if let Ok(c) = std::env::var("SEG_CHANNELS") {
        cfg.net.channels = c.split(',').map(|x| x.parse()).collect::<Result<_, _>>()?;
    }
    if let Ok(s) = std::env::var("SEG_INPUT")
        && let Some((w, h)) = s.split_once('x')
    {
        cfg.net.input_width = w.parse()?;
        cfg.net.input_height = h.parse()?;
    }
    let (w, h) = (cfg.train.render_width, cfg.train.render_height);
    let mut depth = DepthImage::filled(w, h, 5.0);
    let mut mask = Mask::filled(w, h, false);
    for v in h / 3..h / 2 {
        for u in w / 3..w / 2 {
            depth.data[(v * w + u) as usize] = 4.0;
            mask.data[(v * w + u) as usize] = true;
        }
    }
    let k = ic_geometry::Intrinsics::new(
        w as f64 * 0.82,
        w as f64 * 0.82,
        (w as f64 - 1.0) / 2.0,
        (h as f64 - 1.0) / 2.0,
        w,
        h,
    )?;
    let ex = SegExample::new(&depth, &k, &mask, &cfg)?;
    let batch = vec![ex; cfg.train.batch_size];
    let mut t = SegTrainer::new(cfg.clone(), 1)?;
    t.step(&batch)?;
    let n = 3;
    let clock = Instant::now();
    for _ in 0..n {
        t.step(&batch)?;
    }
    let step = clock.elapsed().as_secs_f64() / n as f64;
    let seg = t.segmenter();
    let full = DepthImage::filled(640, 480, 5.0);
    let k = ic_geometry::Intrinsics::new(525.0, 525.0, 319.5, 239.5, 640, 480)?;
    let _ = seg.segment(&full, &k);
    let clock = Instant::now();
    for _ in 0..n {
        let _ = seg.segment(&full, &k);
    }
    let fwd = clock.elapsed().as_secs_f64() / n as f64;
    println!(
        "{preset}: step {:.3} s at batch {} ({:.0} scenes/h); segment 640×480 {:.1} ms",
        step,
        cfg.train.batch_size,
        cfg.train.batch_size as f64 * 3600.0 / step,
        fwd * 1e3
    );
    Ok(())
}
