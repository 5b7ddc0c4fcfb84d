//! `cargo xtask clutter-preview`: a look at cluttered scenes (`ic_data::clutter`) — per scene
//! one PNG with the depth map, the true instances (the target's outlined in white) and, with
//! `--seg-model`, the network's instances.

use std::path::PathBuf;

use anyhow::{Context, Result};
use ic_data::clutter::SUPPORT_ID_BASE;
use ic_data::{ClutterConfig, ClutterGenerator, Split};
use ic_geometry::Mask;
use ic_render::{depth_colours, is_mask_edge, write_rgb_png};

#[derive(clap::Args)]
pub struct PreviewArgs {
    /// A folder with `split.json` or a weighted mixture (as for train-pose).
    #[arg(long)]
    objects: String,
    #[arg(long, default_value = "test")]
    split: String,
    #[arg(long, default_value_t = 6)]
    count: u64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Also draw this segmentation checkpoint's instances.
    #[arg(long)]
    seg_model: Option<PathBuf>,
    #[arg(long)]
    out: PathBuf,
}

/// A colour per instance id (0: black).
fn colour(id: u32) -> [u8; 3] {
    if id == 0 {
        return [0, 0, 0];
    }
    if id >= SUPPORT_ID_BASE {
        return [70, 70, 70];
    }
    let h = ic_data::mix_seed(id as u64, 0x636f6c);
    // 60 + (0..=127)·3/2 ≤ 250: computed in u64, no overflow.
    let channel = |shift: u32| (60 + ((h >> shift) & 0x7f) * 3 / 2) as u8;
    [channel(0), channel(8), channel(16)]
}

pub fn preview(args: PreviewArgs) -> Result<()> {
    let spec: ic_train::ObjectsSpec = args.objects.parse()?;
    let split: Split = args.split.parse()?;
    let corpus = ic_train::pose::open_objects(&spec, split)?;
    let generator = ClutterGenerator::new(corpus, ClutterConfig::default(), args.seed)?;
    let seg = args
        .seg_model
        .as_ref()
        .map(|p| ic_seg::Segmenter::load(p).with_context(|| p.display().to_string()))
        .transpose()?;
    std::fs::create_dir_all(&args.out).with_context(|| args.out.display().to_string())?;
    for i in 0..args.count {
        let s = generator.scene(i)?;
        let (w, h) = (s.intrinsics.width as usize, s.intrinsics.height as usize);
        let panels = if seg.is_some() { 3 } else { 2 };
        let mut rgb = vec![0u8; panels * w * h * 3];
        let mut put = |panel: usize, x: usize, y: usize, c: [u8; 3]| {
            let o = ((y * panels * w) + panel * w + x) * 3;
            rgb[o..o + 3].copy_from_slice(&c);
        };
        let depth = depth_colours(&s.depth);
        let targets: Vec<Mask> = s.targets().map(|t| s.mask(t.instance_id)).collect();
        for y in 0..h {
            for x in 0..w {
                let k = y * w + x;
                put(0, x, y, depth[k]);
                let edge = targets.iter().any(|m| m.data[k] && is_mask_edge(m, x, y));
                put(
                    1,
                    x,
                    y,
                    if edge {
                        [255, 255, 255]
                    } else {
                        colour(s.instances.data[k])
                    },
                );
            }
        }
        if let Some(seg) = &seg {
            let found = seg.instances(&s.depth, &s.intrinsics)?;
            for (n, inst) in found.iter().enumerate() {
                for (k, &m) in inst.mask.data.iter().enumerate() {
                    if m {
                        put(2, k % w, k / w, colour(n as u32 + 1));
                    }
                }
            }
        }
        let path = args.out.join(format!("clutter_{i:03}.png"));
        write_rgb_png(&path, (panels * w) as u32, h as u32, &rgb)?;
        let visible = s.objects.iter().filter(|o| o.visible_pixels > 0).count();
        tracing::info!(
            "{}: {} on a {}, {} objects ({} visible), target {} ×{} ({} px)",
            path.display(),
            s.objects[0].object.id,
            s.support.as_str(),
            s.objects.len(),
            visible,
            s.objects[0].object.id,
            s.targets().count(),
            s.objects[0].visible_pixels
        );
    }
    Ok(())
}
