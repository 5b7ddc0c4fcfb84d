//! A debug view of a rendering: depth colour-mapped (a turbo-like map, near = blue, far = red,
//! no return = black) with a mask overlaid (tinted white, outlined).

use std::path::Path;

use ic_geometry::{DepthImage, Mask};

use crate::ImageIoError;
use crate::io::write_atomic;

/// Colour stops of a turbo-like rainbow (dark blue → cyan → green → yellow → red), sRGB.
const STOPS: [[f32; 3]; 9] = [
    [0.19, 0.07, 0.23],
    [0.27, 0.36, 0.85],
    [0.16, 0.64, 0.98],
    [0.10, 0.89, 0.73],
    [0.45, 0.99, 0.36],
    [0.82, 0.91, 0.21],
    [0.99, 0.64, 0.17],
    [0.89, 0.28, 0.04],
    [0.48, 0.02, 0.01],
];

/// The colour of `t` in [0, 1] (clamped).
pub fn turbo_like(t: f32) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    [0, 1, 2].map(|c| ((a[c] + f * (b[c] - a[c])) * 255.0).round() as u8)
}

/// The colour of every pixel of `depth` (row-major): turbo-like over the range of the valid
/// pixels, black where there is no return.
pub fn depth_colours(depth: &DepthImage) -> Vec<[u8; 3]> {
    let valid = |z: f32| z > 0.0 && z.is_finite();
    let (lo, hi) = depth
        .data
        .iter()
        .copied()
        .filter(|&z| valid(z))
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), z| {
            (lo.min(z), hi.max(z))
        });
    let span = if hi > lo { hi - lo } else { 1.0 };
    depth
        .data
        .iter()
        .map(|&z| {
            if valid(z) {
                turbo_like((z - lo) / span)
            } else {
                [0, 0, 0]
            }
        })
        .collect()
}

/// Whether pixel `(u, v)` of `mask` is set and on its boundary (a 4-neighbour is unset or
/// outside the image).
pub fn is_mask_edge(mask: &Mask, u: usize, v: usize) -> bool {
    let (w, h) = (mask.width as usize, mask.height as usize);
    let at = |x: usize, y: usize| mask.data[y * w + x];
    at(u, v)
        && (u == 0
            || v == 0
            || u + 1 == w
            || v + 1 == h
            || !at(u - 1, v)
            || !at(u + 1, v)
            || !at(u, v - 1)
            || !at(u, v + 1))
}

/// RGB8 pixels (row-major) of the debug view; the depth range is that of the valid pixels.
pub fn debug_rgb(depth: &DepthImage, mask: Option<&Mask>) -> Vec<u8> {
    let w = depth.width as usize;
    let mut out = Vec::with_capacity(depth.data.len() * 3);
    for (i, mut c) in depth_colours(depth).into_iter().enumerate() {
        if let Some(m) = mask
            && m.data[i]
        {
            c = if is_mask_edge(m, i % w, i / w) {
                [255, 255, 255]
            } else {
                c.map(|x| ((x as u16 + 255) / 2) as u8)
            };
        }
        out.extend_from_slice(&c);
    }
    out
}

/// Writes RGB8 pixels (row-major) as a PNG, atomically.
pub fn write_rgb_png(
    path: impl AsRef<Path>,
    width: u32,
    height: u32,
    rgb: &[u8],
) -> Result<(), ImageIoError> {
    let path = path.as_ref();
    write_atomic(path, |w| {
        let codec = |e: png::EncodingError| ImageIoError::Codec {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut enc = png::Encoder::new(w, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(codec)?;
        writer.write_image_data(rgb).map_err(codec)?;
        writer.finish().map_err(codec)
    })
}

/// Writes the debug view as an RGB PNG (atomically).
pub fn write_debug_png(
    path: impl AsRef<Path>,
    depth: &DepthImage,
    mask: Option<&Mask>,
) -> Result<(), ImageIoError> {
    let path = path.as_ref();
    if let Some(m) = mask
        && (m.width, m.height) != (depth.width, depth.height)
    {
        return Err(ImageIoError::SizeMismatch {
            path: path.to_path_buf(),
            width: depth.width,
            height: depth.height,
            got_width: m.width,
            got_height: m.height,
        });
    }
    write_rgb_png(path, depth.width, depth.height, &debug_rgb(depth, mask))
}
