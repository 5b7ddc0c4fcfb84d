//! Depth map → network input, and network output → full-resolution probabilities.
//!
//! The input, at the network's resolution ([`SegInput`]): the depth divided by the median
//! valid depth, minus one (so the input does not depend on the depth unit or the camera's
//! distance), and a validity flag; with [`SegInput::DepthNormals`] also the unit surface normal
//! of each pixel (camera frame). Invalid pixels (0, NaN, ∞) read 0 in every channel.

use ic_geometry::{DepthImage, Intrinsics};

use crate::config::SegInput;
use crate::{Result, SegError};

/// Normals are central differences over this many pixels each way (at the network's
/// resolution): at 256×192 and 1 m, ±2 pixels span ≈ 2 cm of surface, several times the
/// sensor model's noise, and still fit a 5 cm object 1.5 m away (≈ 7 pixels).
pub const NORMAL_STEP: usize = 2;

/// A neighbour further than this fraction of the depth from a pixel lies across a depth edge
/// and is not used for its normal. [`NORMAL_STEP`] pixels at 256×192 are ≈ 5 pixels of a
/// 640×480 Kinect-type camera, ≈ 1 cm of surface at 1 m: 8 % keeps surfaces inclined up to
/// ≈ 80° to the image plane, and the steps between objects are larger.
pub const NORMAL_DEPTH_STEP: f32 = 0.08;

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
    let mut out = vec![0f32; 2 * n];
    for (i, &z) in small.iter().enumerate() {
        if valid(z) {
            out[i] = z / reference - 1.0;
            out[n + i] = 1.0;
        }
    }
    Ok(out)
}

/// The network input `[C, height, width]` (flattened, channel-major) of `kind` for `depth`,
/// whose camera is `intrinsics` (needed for the normals; it must match the depth map's size).
///
/// Errors: as [`prepare`], and intrinsics of another size than the depth map.
pub fn prepare_input(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    kind: SegInput,
    width: u32,
    height: u32,
) -> Result<Vec<f32>> {
    let mut out = prepare(depth, width, height)?;
    if kind == SegInput::Depth {
        return Ok(out);
    }
    depth.check_size(intrinsics.width, intrinsics.height)?;
    let n = (width * height) as usize;
    let normals = normals(depth, intrinsics, width, height);
    out.resize(kind.channels() * n, 0.0);
    for (i, v) in normals.iter().enumerate() {
        for (c, x) in v.iter().enumerate() {
            out[(2 + c) * n + i] = *x;
        }
    }
    Ok(out)
}

/// Mirrors every `width`×`height` plane of `planes` (channel-major, as the network's input
/// and output) left to right, in place: column x becomes column `width − 1 − x`. Plane
/// `x_plane`, when given, holds the x component of a vector (a surface normal's, a centre
/// offset's) and is negated too, as a mirror image turns it.
pub fn mirror_planes(planes: &mut [f32], width: usize, height: usize, x_plane: Option<usize>) {
    let plane = width * height;
    debug_assert_eq!(planes.len() % plane.max(1), 0);
    if width > 0 {
        planes.chunks_exact_mut(width).for_each(<[f32]>::reverse);
    }
    if let Some(c) = x_plane {
        planes[c * plane..(c + 1) * plane]
            .iter_mut()
            .for_each(|v| *v = -*v);
    }
}

/// The unit surface normal (camera frame: x right, y down, z forward; turned towards the
/// camera) of each pixel of `depth` resized to `width`×`height` as [`resize_nearest`] does,
/// each small pixel back-projected at the source pixel it was taken from. Central
/// differences over [`NORMAL_STEP`] pixels each way; one-sided where one side has no depth or
/// lies across a depth edge ([`NORMAL_DEPTH_STEP`]); zero where a direction has neither, and
/// everywhere for an empty depth map.
pub fn normals(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    width: u32,
    height: u32,
) -> Vec<[f32; 3]> {
    let (sw, sh) = (depth.width as usize, depth.height as usize);
    let (w, h) = (width as usize, height as usize);
    if sw == 0 || sh == 0 || depth.data.len() != sw * sh {
        return vec![[0.0; 3]; w * h];
    }
    let src = |i: usize, s: usize, d: usize| {
        (((i as f64 + 0.5) * s as f64 / d as f64) as usize).min(s - 1)
    };
    let cols: Vec<usize> = (0..w).map(|x| src(x, sw, w)).collect();
    let rows: Vec<usize> = (0..h).map(|y| src(y, sh, h)).collect();
    let point = |x: usize, y: usize| -> Option<glam::DVec3> {
        let (u, v) = (cols[x], rows[y]);
        let z = depth.data[v * sw + u];
        valid(z).then(|| intrinsics.back_project(u as f64, v as f64, z as f64))
    };
    let points: Vec<Option<glam::DVec3>> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| point(x, y))
        .collect();
    let near = |p: glam::DVec3, q: Option<glam::DVec3>| {
        q.filter(|q| (q.z - p.z).abs() <= NORMAL_DEPTH_STEP as f64 * p.z.min(q.z))
    };
    let s = NORMAL_STEP;
    let mut out = vec![[0.0f32; 3]; w * h];
    for y in 0..h {
        for x in 0..w {
            let Some(p) = points[y * w + x] else { continue };
            let at = |xx: Option<usize>, yy: Option<usize>| match (xx, yy) {
                (Some(a), Some(b)) if a < w && b < h => near(p, points[b * w + a]),
                _ => None,
            };
            // The tangent along one image direction: the two sides, else one side and p.
            let tangent =
                |before: Option<glam::DVec3>, after: Option<glam::DVec3>| match (before, after) {
                    (Some(a), Some(b)) => Some(b - a),
                    (None, Some(b)) => Some(b - p),
                    (Some(a), None) => Some(p - a),
                    (None, None) => None,
                };
            let tx = tangent(at(x.checked_sub(s), Some(y)), at(Some(x + s), Some(y)));
            let ty = tangent(at(Some(x), y.checked_sub(s)), at(Some(x), Some(y + s)));
            let (Some(tx), Some(ty)) = (tx, ty) else {
                continue;
            };
            let Some(mut n) = ty.cross(tx).try_normalize() else {
                continue;
            };
            if n.dot(p) > 0.0 {
                n = -n;
            }
            out[y * w + x] = [n.x as f32, n.y as f32, n.z as f32];
        }
    }
    out
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
    fn normals_of_a_tilted_plane_point_to_the_camera_and_stop_at_a_depth_edge() {
        // A plane z = 1 + 0.5·X (metres) seen by a 64×48 camera, with a box 0.5 m nearer
        // in its left quarter: the plane's normal is (0.5, 0, −1)/|·| (turned to the camera).
        let k = Intrinsics::new(60.0, 60.0, 31.5, 23.5, 64, 48).unwrap();
        let mut depth = DepthImage::filled(64, 48, 0.0);
        for v in 0..48 {
            for u in 0..64 {
                // Ray (a, b, 1)·z on the plane: z = 1 + 0.5·a·z → z = 1 / (1 − 0.5·a).
                let a = (u as f64 - k.cx) / k.fx;
                let plane = 1.0 / (1.0 - 0.5 * a);
                depth.data[v * 64 + u] = if u < 16 { 0.5 } else { plane as f32 };
            }
        }
        depth.data[47 * 64 + 63] = 0.0; // a pixel without depth
        let n = normals(&depth, &k, 32, 24);
        let want = glam::DVec3::new(0.5, 0.0, -1.0).normalize();
        for y in 0..24 {
            for x in 0..32 {
                let got = glam::DVec3::new(
                    n[y * 32 + x][0] as f64,
                    n[y * 32 + x][1] as f64,
                    n[y * 32 + x][2] as f64,
                );
                if (x, y) == (31, 23) {
                    assert_eq!(got, glam::DVec3::ZERO);
                } else if x < 8 {
                    // The box's face, one-sided at its edge: facing the camera.
                    assert!(
                        (got - glam::DVec3::new(0.0, 0.0, -1.0)).length() < 1e-4,
                        "{x},{y}: {got}"
                    );
                } else {
                    assert!((got - want).length() < 1e-4, "{x},{y}: {got}");
                }
            }
        }
        let input = prepare_input(&depth, &k, SegInput::DepthNormals, 32, 24).unwrap();
        assert_eq!(input.len(), 5 * 32 * 24);
        assert_eq!(&input[..2 * 32 * 24], &prepare(&depth, 32, 24).unwrap()[..]);
        assert!((input[4 * 32 * 24 + 10] as f64 - want.z).abs() < 1e-4);
        assert_eq!(
            prepare_input(&depth, &k, SegInput::Depth, 32, 24).unwrap(),
            prepare(&depth, 32, 24).unwrap()
        );
        let other = Intrinsics::new(60.0, 60.0, 31.5, 23.5, 32, 24).unwrap();
        assert!(prepare_input(&depth, &other, SegInput::DepthNormals, 32, 24).is_err());
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
