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

/// RGB8 pixels (row-major) of the debug view; the depth range is that of the valid pixels.
pub fn debug_rgb(depth: &DepthImage, mask: Option<&Mask>) -> Vec<u8> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let valid = depth
        .data
        .iter()
        .copied()
        .filter(|&z| z > 0.0 && z.is_finite());
    let (lo, hi) = valid.fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), z| {
        (lo.min(z), hi.max(z))
    });
    let span = if hi > lo { hi - lo } else { 1.0 };
    let m =
        |u: usize, v: usize| mask.is_some_and(|m| m.data.get(v * w + u).copied().unwrap_or(false));
    let mut out = Vec::with_capacity(w * h * 3);
    for v in 0..h {
        for u in 0..w {
            let z = depth.data[v * w + u];
            let mut c = if z > 0.0 && z.is_finite() {
                turbo_like((z - lo) / span)
            } else {
                [0, 0, 0]
            };
            if m(u, v) {
                let edge = u == 0
                    || v == 0
                    || u + 1 == w
                    || v + 1 == h
                    || !m(u - 1, v)
                    || !m(u + 1, v)
                    || !m(u, v - 1)
                    || !m(u, v + 1);
                c = if edge {
                    [255, 255, 255]
                } else {
                    c.map(|x| ((x as u16 + 255) / 2) as u8)
                };
            }
            out.extend_from_slice(&c);
        }
    }
    out
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
    let rgb = debug_rgb(depth, mask);
    write_atomic(path, |w| {
        let codec = |e: png::EncodingError| ImageIoError::Codec {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut enc = png::Encoder::new(w, depth.width, depth.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(codec)?;
        writer.write_image_data(&rgb).map_err(codec)?;
        writer.finish().map_err(codec)
    })
}
