//! Function-preserving widening of a U-Net's channels ("Net2WiderNet": Chen, Goodfellow and
//! Shlens, "Net2Net: Accelerating Learning via Knowledge Transfer", ICLR 2016,
//! <https://arxiv.org/abs/1511.05641>), so that a wider segmentation network starts from a
//! trained narrower one instead of from random weights.
//!
//! Level `l` of the wider network has `to[l]` ≥ `from[l]` channels; its channel `i` copies the
//! narrow network's channel `g_l(i)` = `i` for `i < from[l]`, else `(i − from[l]) mod from[l]`
//! (round robin: every channel is copied as evenly as the widths allow). A convolution's
//! output channels (and their batch-norm weight, bias and running statistics) are copied by
//! `g` of their level; its input weights are copied by `g` of the level they read and divided
//! by the number of copies of that channel, so that the copies together contribute what the
//! one channel did. Batch norm sees the same statistics in every copy, so the widened network
//! computes what the narrow one did, to rounding (tested). The weights into the new copies
//! then get a little seeded noise (± `NOISE` of the tensor's RMS, uniform), or a copy and its
//! original would receive the same gradient and stay equal forever.
//!
//! The layout is [`ic_seg::unet::UNet`]'s: `down{l}.{a,b}` read level `l − 1` (the image for
//! `down0.a`) and then level `l`; `up{l}.a` reads the up-sampled level `l + 1` and then the
//! skip of level `l`, concatenated; `up{l}.b` reads level `l`; `head` reads level 0.

use std::collections::HashMap;

use candle_core::Tensor;

/// Noise on the new copies' input weights, relative to the tensor's RMS, when a training run
/// starts from a narrower network.
pub const NOISE: f32 = 0.01;

/// The channel map of one level: the narrow channel of each wide one, and how many wide
/// channels copy each narrow one.
struct LevelMap {
    source: Vec<usize>,
    copies: Vec<usize>,
}

impl LevelMap {
    fn new(from: usize, to: usize) -> Self {
        let source: Vec<usize> = (0..to)
            .map(|i| if i < from { i } else { (i - from) % from })
            .collect();
        let mut copies = vec![0; from];
        for &s in &source {
            copies[s] += 1;
        }
        LevelMap { source, copies }
    }
}

/// Where an input channel of a convolution comes from: `(narrow index, divisor)` per wide
/// input channel; `None` for the image's channels (not widened).
fn input_map(levels: &[LevelMap], reads: &[usize]) -> Vec<(usize, f32)> {
    let mut out = Vec::new();
    let mut offset = 0;
    for &l in reads {
        let m = &levels[l];
        for &s in &m.source {
            out.push((offset + s, m.copies[s] as f32));
        }
        offset += m.copies.len();
    }
    out
}

/// What a tensor of the U-Net is: its level's output map (None for the head) and the levels
/// its input channels read, in order (empty for vectors and the first convolution).
fn role(name: &str, levels: usize) -> Result<(Option<usize>, Vec<usize>), String> {
    let unknown = || format!("{name}: not a tensor of the U-Net's layout");
    if let Some(rest) = name.strip_prefix("head.") {
        return match rest {
            "weight" => Ok((None, vec![0])),
            "bias" => Ok((None, vec![])),
            _ => Err(unknown()),
        };
    }
    let (up, rest) = if let Some(r) = name.strip_prefix("down") {
        (false, r)
    } else if let Some(r) = name.strip_prefix("up") {
        (true, r)
    } else {
        return Err(unknown());
    };
    let (level, rest) = rest.split_once('.').ok_or_else(unknown)?;
    let l: usize = level.parse().map_err(|_| unknown())?;
    if l >= levels {
        return Err(unknown());
    }
    let (block, leaf) = rest.split_once('.').ok_or_else(unknown)?;
    let reads = match (leaf, up, block) {
        ("conv.weight", false, "a") if l == 0 => vec![],
        ("conv.weight", false, "a") => vec![l - 1],
        ("conv.weight", true, "a") => vec![l + 1, l],
        ("conv.weight", _, "b") => vec![l],
        ("bn.weight" | "bn.bias" | "bn.running_mean" | "bn.running_var", _, "a" | "b") => {
            vec![]
        }
        _ => return Err(unknown()),
    };
    Ok((Some(l), reads))
}

/// The narrow network's `tensors` (checkpoint names) laid out for the wider channels `to`
/// (same number of levels, each at least as wide as in `from`); `names` are the wide network's
/// variables, each of which must be in `tensors`. The new copies' input weights get uniform
/// noise of ± `noise` × the tensor's RMS ([`NOISE`] for training; 0 gives the exact widening),
/// drawn from `seed` and the tensor's rank among the sorted names. Errors name the tensor.
pub fn widen_unet(
    tensors: &HashMap<String, Tensor>,
    names: &[String],
    from: &[usize],
    to: &[usize],
    noise: f32,
    seed: u64,
) -> Result<HashMap<String, Tensor>, String> {
    if from.len() != to.len() || from.iter().zip(to).any(|(f, t)| t < f || *f == 0) {
        return Err(format!(
            "channels {from:?} cannot be widened into {to:?} (same number of levels, each at least as wide)"
        ));
    }
    let levels: Vec<LevelMap> = from
        .iter()
        .zip(to)
        .map(|(&f, &t)| LevelMap::new(f, t))
        .collect();
    let mut names = names.to_vec();
    names.sort();
    let mut out = HashMap::new();
    for (k, name) in names.iter().enumerate() {
        let t = tensors
            .get(name)
            .ok_or_else(|| format!("missing tensor {name}"))?;
        let (level, reads) = role(name, from.len())?;
        let shape = t.dims().to_vec();
        let values = t
            .flatten_all()
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| format!("{name}: {e}"))?;
        let out_map: Vec<usize> = match level {
            Some(l) => levels[l].source.clone(),
            None => (0..shape[0]).collect(),
        };
        if out_map.iter().any(|&s| s >= shape[0]) {
            return Err(format!(
                "{name}: shape {shape:?} does not fit channels {from:?}"
            ));
        }
        let widened = if shape.len() == 4 {
            let (cin, kk) = (shape[1], shape[2] * shape[3]);
            let in_map: Vec<(usize, f32)> = if reads.is_empty() {
                (0..cin).map(|i| (i, 1.0)).collect()
            } else {
                input_map(&levels, &reads)
            };
            let narrow_in: usize = if reads.is_empty() {
                cin
            } else {
                reads.iter().map(|&l| from[l]).sum()
            };
            if narrow_in != cin {
                return Err(format!(
                    "{name}: {cin} input channels, expected {narrow_in} for channels {from:?}"
                ));
            }
            let rms =
                (values.iter().map(|v| v * v).sum::<f32>() / values.len().max(1) as f32).sqrt();
            let mut w = Vec::with_capacity(out_map.len() * in_map.len() * kk);
            for (o, &so) in out_map.iter().enumerate() {
                let new_copy = level.is_some_and(|l| o >= from[l]);
                for (i, &(si, div)) in in_map.iter().enumerate() {
                    for j in 0..kk {
                        let mut v = values[(so * cin + si) * kk + j] / div;
                        if new_copy && noise > 0.0 {
                            let index = ((o * in_map.len() + i) * kk + j) as u64;
                            let u = crate::uniform_draw(ic_data::mix_seed(seed, k as u64), index);
                            v += noise * rms * (2.0 * u as f32 - 1.0);
                        }
                        w.push(v);
                    }
                }
            }
            Tensor::from_vec(
                w,
                (out_map.len(), in_map.len(), shape[2], shape[3]),
                t.device(),
            )
        } else if shape.len() == 1 {
            let v: Vec<f32> = out_map.iter().map(|&s| values[s]).collect();
            Tensor::from_vec(v, out_map.len(), t.device())
        } else {
            return Err(format!("{name}: unexpected shape {shape:?}"));
        }
        .map_err(|e| format!("{name}: {e}"))?;
        out.insert(name.clone(), widened);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_maps_copy_every_channel_as_evenly_as_the_widths_allow() {
        let m = LevelMap::new(16, 24);
        assert_eq!(&m.source[..16], &(0..16).collect::<Vec<_>>()[..]);
        assert_eq!(&m.source[16..], &(0..8).collect::<Vec<_>>()[..]);
        assert_eq!(m.copies.iter().filter(|&&c| c == 2).count(), 8);
        assert_eq!(m.copies.iter().filter(|&&c| c == 1).count(), 8);
        let m = LevelMap::new(4, 12);
        assert!(m.copies.iter().all(|&c| c == 3));
    }

    #[test]
    fn roles_follow_the_unet_layout_and_refuse_other_names() {
        assert_eq!(role("down0.a.conv.weight", 4).unwrap(), (Some(0), vec![]));
        assert_eq!(role("down2.a.conv.weight", 4).unwrap(), (Some(2), vec![1]));
        assert_eq!(role("up1.a.conv.weight", 4).unwrap(), (Some(1), vec![2, 1]));
        assert_eq!(role("up1.b.bn.running_var", 4).unwrap(), (Some(1), vec![]));
        assert_eq!(role("head.weight", 4).unwrap(), (None, vec![0]));
        assert!(role("down7.a.conv.weight", 4).is_err());
        assert!(role("mlp.weight", 4).is_err());
    }
}
