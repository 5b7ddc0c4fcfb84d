//! Depth map → network input, and network output → full-resolution probabilities.
//!
//! The input has two channels at the network's resolution: the depth divided by the median
//! valid depth, minus one (so the input does not depend on the depth unit or the camera's
//! distance), and a validity flag. Invalid pixels (0, NaN, ∞) read 0 in both channels.

use ic_geometry::DepthImage;

use crate::{Result, SegError};

/// Number of input channels.
pub const INPUT_CHANNELS: usize = 2;

fn valid(z: f32) -> bool {
    z.is_finite() && z > 0.0
}

/// Nearest-neighbour resize of `depth` to `width`×`height` (pixel centres aligned), which
/// never mixes depths across an edge.
pub fn resize_nearest(depth: &DepthImage, width: u32, height: u32) -> Vec<f32> {
    let (sw, sh) = (depth.width as usize, depth.height as usize);
    let mut out = Vec::with_capacity(width as usize * height as usize);
    for y in 0..height as usize {
        let v = (((y as f64 + 0.5) * sh as f64 / height as f64) as usize).min(sh - 1);
        for x in 0..width as usize {
            let u = (((x as f64 + 0.5) * sw as f64 / width as f64) as usize).min(sw - 1);
            out.push(depth.data[v * sw + u]);
        }
    }
    out
}

/// The network input `[2, height, width]` (flattened, channel-major) for `depth`.
///
/// Errors: an empty depth map, or one without a single valid pixel.
pub fn prepare(depth: &DepthImage, width: u32, height: u32) -> Result<Vec<f32>> {
    if depth.width == 0 || depth.height == 0 || depth.data.is_empty() {
        return Err(SegError::Input("the depth map is empty".into()));
    }
    let small = resize_nearest(depth, width, height);
    let mut valid_depths: Vec<f32> = small.iter().copied().filter(|&z| valid(z)).collect();
    if valid_depths.is_empty() {
        // The small image may miss a sparse map's few valid pixels: look at the full one.
        if !depth.data.iter().any(|&z| valid(z)) {
            return Err(SegError::Input(
                "the depth map has no valid pixel (all zero, NaN or infinite)".into(),
            ));
        }
        valid_depths = depth.data.iter().copied().filter(|&z| valid(z)).collect();
    }
    let mid = valid_depths.len() / 2;
    let reference = *valid_depths.select_nth_unstable_by(mid, f32::total_cmp).1;
    let n = small.len();
    let mut out = vec![0f32; INPUT_CHANNELS * n];
    for (i, &z) in small.iter().enumerate() {
        if valid(z) {
            out[i] = z / reference - 1.0;
            out[n + i] = 1.0;
        }
    }
    Ok(out)
}

/// Bilinear resize of a probability map from `width`×`height` to `out_width`×`out_height`
/// (pixel centres aligned, edges clamped).
pub fn upsample_bilinear(
    prob: &[f32],
    width: u32,
    height: u32,
    out_width: u32,
    out_height: u32,
) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    let mut out = Vec::with_capacity(out_width as usize * out_height as usize);
    let coord = |i: usize, src: usize, dst: u32| -> (usize, usize, f32) {
        let x = ((i as f64 + 0.5) * src as f64 / dst as f64 - 0.5).clamp(0.0, (src - 1) as f64);
        let x0 = x.floor() as usize;
        let x1 = (x0 + 1).min(src - 1);
        (x0, x1, (x - x0 as f64) as f32)
    };
    let cols: Vec<(usize, usize, f32)> = (0..out_width as usize)
        .map(|x| coord(x, w, out_width))
        .collect();
    for y in 0..out_height as usize {
        let (y0, y1, fy) = coord(y, h, out_height);
        for &(x0, x1, fx) in &cols {
            let top = prob[y0 * w + x0] * (1.0 - fx) + prob[y0 * w + x1] * fx;
            let bottom = prob[y1 * w + x0] * (1.0 - fx) + prob[y1 * w + x1] * fx;
            out.push(top * (1.0 - fy) + bottom * fy);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prepare_is_unit_free_and_flags_invalid_pixels() {
        let metres =
            DepthImage::from_vec(4, 2, vec![1.0, 2.0, 0.0, 1.0, 1.0, f32::NAN, 2.0, 1.0]).unwrap();
        let mm =
            DepthImage::from_vec(4, 2, metres.data.iter().map(|z| z * 1000.0).collect()).unwrap();
        let a = prepare(&metres, 4, 2).unwrap();
        let b = prepare(&mm, 4, 2).unwrap();
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-6);
        }
        // median of the valid depths is 1 → depth 2 reads 1, depth 1 reads 0.
        assert_eq!(&a[..8], &[0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        assert_eq!(&a[8..], &[1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0]);
    }

    #[test]
    fn prepare_rejects_a_map_without_valid_pixels() {
        let d = DepthImage::from_vec(2, 2, vec![0.0, f32::NAN, f32::INFINITY, -1.0]).unwrap();
        assert!(matches!(prepare(&d, 2, 2), Err(SegError::Input(_))));
    }

    #[test]
    fn resize_nearest_picks_the_covering_pixel() {
        let d = DepthImage::from_vec(4, 2, (0..8).map(|i| i as f32).collect()).unwrap();
        // Output pixel centres (0.5, 0.5)·scale land on source pixels (1, 1) and (3, 1).
        assert_eq!(resize_nearest(&d, 2, 1), vec![5.0, 7.0]);
    }

    #[test]
    fn upsample_bilinear_keeps_constants_and_interpolates_edges() {
        assert_eq!(upsample_bilinear(&[0.25; 4], 2, 2, 5, 3), vec![0.25; 15]);
        let up = upsample_bilinear(&[0.0, 1.0], 2, 1, 4, 1);
        assert_eq!(up, vec![0.0, 0.25, 0.75, 1.0]);
    }
}
