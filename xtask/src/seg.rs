//! `cargo xtask train-seg`, `eval-seg` (thin wrappers of `ic_train::seg`) and `seg-post`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use ic_seg::Segmenter;

pub use ic_train::seg::{EvalArgs, TrainArgs};

pub fn train(args: TrainArgs) -> Result<()> {
    // SAFETY: first thing in the command, before any other thread exists.
    unsafe { ic_train::set_threads(args.threads) };
    ic_train::install_signal_handlers();
    let control = ic_train::RunControl {
        checkpoint_secs: args.checkpoint_secs,
        ..Default::default()
    };
    ic_train::seg::train(&args, control)?;
    Ok(())
}

pub fn eval(args: EvalArgs) -> Result<()> {
    // SAFETY: first thing in the command, before any other thread exists.
    unsafe { ic_train::set_threads(args.threads) };
    let report = ic_train::seg::eval(&args)?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

#[derive(clap::Args)]
pub struct PostArgs {
    /// A segmentation checkpoint (weights-only or training).
    #[arg(long)]
    model: PathBuf,
    /// The weights-only checkpoint to write, with the post-processing settings replaced.
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    pixel_threshold: Option<f32>,
    #[arg(long)]
    score_threshold: Option<f32>,
    #[arg(long)]
    depth_refine_px: Option<usize>,
    #[arg(long)]
    depth_jump: Option<f32>,
    #[arg(long)]
    min_pixels: Option<usize>,
    /// Two-output networks: the instance-core probability from which a pixel seeds an
    /// instance.
    #[arg(long)]
    core_threshold: Option<f32>,
    /// The network's input size at inference (the network is fully convolutional; each
    /// divisible by 2^(levels − 1)): a finer input than the training renders' keeps small,
    /// far objects.
    #[arg(long)]
    input_width: Option<u32>,
    #[arg(long)]
    input_height: Option<u32>,
    /// The instances standing out of the scene's support planes (`ic_seg::support`): the least
    /// height above a plane, relative to the depth (e.g. 0.01); 0 turns them off.
    #[arg(long)]
    support_height: Option<f32>,
    /// With support instances on: the planes' narrowest inlier band, relative to the depth.
    #[arg(long)]
    support_plane_threshold: Option<f32>,
    /// With support instances on: whether the network's instances first grow into the pixels
    /// off the planes that they reach (`true` / `false`).
    #[arg(long)]
    support_grow: Option<bool>,
    /// Four-output networks: cut a seed whose pixels' centre votes form two groups farther
    /// apart than this × their spread (`ic_seg::centres`; 0: never). Turns the centre votes
    /// on (with the defaults for what is not given).
    #[arg(long)]
    centre_split: Option<f32>,
    /// Four-output networks: join touching instances whose mean votes lie closer than this ×
    /// their spread (0: never). Turns the centre votes on.
    #[arg(long)]
    centre_merge: Option<f32>,
    /// Four-output networks: the least share of a seed's pixels in each part of a cut.
    #[arg(long)]
    centre_min_share: Option<f32>,
    /// Four-output networks: network pixels added in quadrature to the spread both vote rules
    /// compare with (votes agreeing to within it are one centre).
    #[arg(long)]
    centre_spread_floor: Option<f32>,
    /// Average the network's outputs on the depth map and on its mirror image (`true` /
    /// `false`; twice the network's time).
    #[arg(long)]
    mirror_average: Option<bool>,
    /// More input sizes the network also runs at, each `WIDTHxHEIGHT` (comma-separated, e.g.
    /// `384x288`; `none` clears them): `register` pools every size's instances as candidates
    /// (`ic_seg::PostConfig::extra_inputs`).
    #[arg(long, value_parser = parse_input_sizes)]
    extra_inputs: Option<InputSizes>,
    /// Size the network's input for each image's camera (`true`, the default of every file:
    /// a network pixel spans the angle it spanned in training, the image's aspect ratio
    /// kept; `ic_seg::Segmenter::input_size_for`) or always run it at its own input size
    /// (`false`: another aspect ratio is squeezed into it).
    #[arg(long)]
    camera_input: Option<bool>,
    /// Four-output networks: ignore the centre offsets (the instances of the cores alone).
    #[arg(long, conflicts_with_all = ["centre_split", "centre_merge", "centre_min_share", "centre_spread_floor"])]
    no_centres: bool,
}

/// Input sizes of `--extra-inputs` (a newtype: clap reads a bare `Vec` as a repeated flag).
#[derive(Clone, Debug)]
pub struct InputSizes(Vec<(u32, u32)>);

/// `WIDTHxHEIGHT[,WIDTHxHEIGHT…]` or `none`.
fn parse_input_sizes(s: &str) -> std::result::Result<InputSizes, String> {
    if s.trim() == "none" {
        return Ok(InputSizes(Vec::new()));
    }
    s.split(',')
        .map(|one| {
            let (w, h) = one
                .trim()
                .split_once(['x', '×'])
                .ok_or_else(|| format!("{one:?}: expected WIDTHxHEIGHT, e.g. 384x288"))?;
            let side = |v: &str| {
                v.trim()
                    .parse::<u32>()
                    .map_err(|e| format!("{one:?}: {v:?} is not a pixel count ({e})"))
            };
            Ok((side(w)?, side(h)?))
        })
        .collect::<std::result::Result<Vec<_>, String>>()
        .map(InputSizes)
}

/// `cargo xtask seg-post`: writes the weights of `--model` with new post-processing settings
/// (thresholds chosen on validation scenes after training), atomically. The weights are
/// copied bit for bit; only the configuration in the metadata changes.
pub fn set_post(args: PostArgs) -> Result<()> {
    let mut cfg = ic_seg::checkpoint::read_config(&args.model)?;
    let p = &mut cfg.post;
    if let Some(v) = args.pixel_threshold {
        p.pixel_threshold = v;
    }
    if let Some(v) = args.score_threshold {
        p.score_threshold = v;
    }
    if let Some(v) = args.depth_refine_px {
        p.depth_refine_px = v;
    }
    if let Some(v) = args.depth_jump {
        p.depth_jump = v;
    }
    if let Some(v) = args.min_pixels {
        p.min_pixels = v;
    }
    if let Some(v) = args.core_threshold {
        p.core_threshold = v;
    }
    if let Some(v) = args.mirror_average {
        p.mirror_average = v;
    }
    if let Some(InputSizes(v)) = args.extra_inputs {
        p.extra_inputs = v;
    }
    if let Some(v) = args.camera_input {
        p.camera_input = v;
    }
    if let Some(v) = args.input_width {
        cfg.net.input_width = v;
    }
    if let Some(v) = args.input_height {
        cfg.net.input_height = v;
    }
    if let Some(height) = args.support_height {
        cfg.post
            .set_support(height, args.support_plane_threshold, args.support_grow);
    } else if args.support_plane_threshold.is_some() || args.support_grow.is_some() {
        anyhow::bail!("--support-plane-threshold and --support-grow need --support-height");
    }
    if args.no_centres {
        cfg.post.centres = None;
    } else if args.centre_split.is_some()
        || args.centre_merge.is_some()
        || args.centre_min_share.is_some()
        || args.centre_spread_floor.is_some()
    {
        if !cfg.net.has_offsets() {
            anyhow::bail!(
                "{}: --centre-split/--centre-merge/--centre-min-share/--centre-spread-floor need a four-output network (this one has {})",
                args.model.display(),
                cfg.net.outputs
            );
        }
        let c = cfg.post.centres.get_or_insert_with(Default::default);
        if let Some(v) = args.centre_split {
            c.split = v;
        }
        if let Some(v) = args.centre_merge {
            c.merge = v;
        }
        if let Some(v) = args.centre_min_share {
            c.min_share = v;
        }
        if let Some(v) = args.centre_spread_floor {
            c.spread_floor = v;
        }
    }
    cfg.validate()?;
    // Only the network's tensors: a training checkpoint's Adam moments are left behind.
    let seg = Segmenter::load(&args.model)?;
    drop(seg);
    let tensors = candle_core::safetensors::load(&args.model, &candle_core::Device::Cpu)
        .with_context(|| format!("reading {}", args.model.display()))?;
    let weights: Vec<(String, candle_core::Tensor)> = tensors
        .into_iter()
        .filter(|(k, _)| !k.starts_with("adam."))
        .collect();
    let meta = std::collections::HashMap::from([(
        ic_seg::checkpoint::CONFIG_KEY.to_string(),
        serde_json::to_string(&cfg)?,
    )]);
    ic_nn::checkpoint::save(&args.out, &weights, meta)?;
    eprintln!("post-processing {}", serde_json::to_string(&cfg.post)?);
    eprintln!("written {}", args.out.display());
    Ok(())
}
