//! Objects the network takes for support: pixels off the scene's large planes (a table top,
//! the floor, a bin's floor and walls, a shelf board) that no network instance holds.
//!
//! A depth-only network learns "object" from shape, and a large flat box top or a thin book
//! looks like the table it lies on; what tells them apart in depth is that they stand out of
//! the table's plane. [`support_planes`] finds the large planes by RANSAC on a strided subset
//! of the pixels; [`off_planes`] marks the pixels clearly off all of them; the network's
//! instances may first take the ones they reach ([`grow_into`]); [`free_groups`] returns the
//! depth-continuous groups of the rest, which `Segmenter::instances` adds as instances
//! (`Instance::off_support`).
//!
//! Every length is relative to the pixel's own depth (a threshold of 0.01 is 10 mm at 1 m
//! and 5 mm at 0.5 m), so the step works in any depth unit (metres or millimetres) and follows
//! a depth sensor's error, which grows with distance; each plane's band also widens to the
//! noise measured on it. Points are in the camera frame of the depth map's units.

use glam::DVec3;
use ic_geometry::{DepthImage, Intrinsics};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::post::flood_fill8;
use crate::{Result, SegError};

/// The widest plane band, in units of `SupportConfig::plane_threshold`: noisier planes than
/// that are not support.
const NOISE_BAND: f64 = 4.0;

/// Settings of [`support_planes`] and [`above_support`]; lengths relative to the depth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SupportConfig {
    /// A pixel within this × its depth of a plane lies on it.
    pub plane_threshold: f32,
    /// A pixel at least this × its depth in front of the plane stands out of it.
    pub height: f32,
    /// A plane must hold at least this fraction of the valid pixels to count as support.
    pub min_plane_fraction: f64,
    /// At most this many support planes.
    pub max_planes: usize,
    /// RANSAC hypotheses (three pixels each).
    pub iterations: usize,
    /// Every `stride`-th pixel in both directions is scored.
    pub stride: usize,
    /// The network's instances first grow into the free pixels they reach ([`grow_into`]).
    pub grow: bool,
    /// Seed of the RANSAC draws (the same depth map gives the same plane).
    pub seed: u64,
}

impl Default for SupportConfig {
    fn default() -> Self {
        SupportConfig {
            plane_threshold: 0.004,
            height: 0.01,
            min_plane_fraction: 0.1,
            max_planes: 4,
            grow: false,
            iterations: 200,
            stride: 4,
            seed: 0,
        }
    }
}

impl SupportConfig {
    /// Errors ([`SegError::Config`]) for a threshold or height that is not a small positive
    /// fraction of the depth, a plane fraction outside (0, 1], no RANSAC iteration or a zero
    /// stride.
    pub fn validate(&self) -> Result<()> {
        let fraction = |v: f32| v > 0.0 && v < 0.5;
        if !fraction(self.plane_threshold) || !fraction(self.height) {
            return Err(SegError::Config(format!(
                "support: plane_threshold ({}) and height ({}) must be in (0, 0.5), fractions of the depth",
                self.plane_threshold, self.height
            )));
        }
        if !(self.min_plane_fraction > 0.0 && self.min_plane_fraction <= 1.0) {
            return Err(SegError::Config(format!(
                "support: min_plane_fraction ({}) must be in (0, 1]",
                self.min_plane_fraction
            )));
        }
        if self.iterations == 0 || self.stride == 0 || self.max_planes == 0 {
            return Err(SegError::Config(
                "support: iterations, stride and max_planes must be positive".into(),
            ));
        }
        Ok(())
    }
}

/// A plane in the camera frame: the signed distance of a point `p` (depth-map units) is
/// `normal · p + offset`, positive on the camera's side (`offset > 0`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupportPlane {
    pub normal: DVec3,
    pub offset: f64,
    /// A point within `band` × its depth of the plane lies on it: `cfg.plane_threshold`, or
    /// wider where the sensor's noise on the plane is larger.
    pub band: f64,
    /// Fraction of the scored valid pixels on the plane.
    pub inlier_fraction: f64,
}

impl SupportPlane {
    /// Signed distance of `p` (camera frame), positive toward the camera.
    pub fn height(&self, p: DVec3) -> f64 {
        self.normal.dot(p) + self.offset
    }
}

fn back_project(depth: &DepthImage, intrinsics: &Intrinsics, i: usize) -> Option<DVec3> {
    let z = depth.data[i];
    let w = depth.width as usize;
    (z.is_finite() && z > 0.0)
        .then(|| intrinsics.back_project((i % w) as f64, (i / w) as f64, z as f64))
}

/// The large planes of `depth` (a floor, a table top, a bin's floor and walls), largest
/// first: up to `cfg.max_planes` times, the plane holding the most of the remaining pixels
/// (RANSAC over every `cfg.stride`-th pixel, the best hypothesis refitted by least squares on
/// its inliers) is kept and its pixels removed, until the best holds less than
/// `cfg.min_plane_fraction` of all the scored valid pixels. Empty with fewer than 3 valid
/// pixels. `depth` must fit `intrinsics` (the caller checks).
pub fn support_planes(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    cfg: &SupportConfig,
) -> Vec<SupportPlane> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let stride = cfg.stride.max(1);
    let mut points: Vec<DVec3> = (0..h)
        .step_by(stride)
        .flat_map(|y| (0..w).step_by(stride).map(move |x| y * w + x))
        .filter_map(|i| back_project(depth, intrinsics, i))
        .collect();
    let total = points.len();
    let tau = cfg.plane_threshold as f64;
    let on = |n: DVec3, d: f64, p: &DVec3| (n.dot(*p) + d).abs() < tau * p.z;
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut planes = Vec::new();
    while planes.len() < cfg.max_planes && points.len() >= 3 {
        let mut best: Option<(DVec3, f64, usize)> = None;
        for _ in 0..cfg.iterations {
            let mut pick = || points[rng.random_range(0..points.len())];
            let (a, b, c) = (pick(), pick(), pick());
            let n = (b - a).cross(c - a);
            let len = n.length();
            if len <= 1e-12 {
                continue;
            }
            let n = n / len;
            let d = -n.dot(a);
            let count = points.iter().filter(|p| on(n, d, p)).count();
            if best.is_none_or(|(_, _, c)| count > c) {
                best = Some((n, d, count));
            }
        }
        let Some((n, d, _)) = best else { break };
        let inliers: Vec<DVec3> = points.iter().copied().filter(|p| on(n, d, p)).collect();
        let (mut n, mut d) = crate::geometric::refit(&inliers).unwrap_or((n, d));
        if d < 0.0 {
            (n, d) = (-n, -d);
        }
        // The sensor's noise on this plane: 3 robust standard deviations (1.4826 × the
        // median absolute relative residual) of the points within the wider band, never
        // narrower than `cfg.plane_threshold`.
        let mut residuals: Vec<f64> = points
            .iter()
            .map(|p| (n.dot(*p) + d).abs() / p.z)
            .filter(|&r| r < NOISE_BAND * tau)
            .collect();
        let band = if residuals.is_empty() {
            tau
        } else {
            let mid = residuals.len() / 2;
            let (_, median, _) = residuals.select_nth_unstable_by(mid, f64::total_cmp);
            (3.0 * 1.4826 * *median).clamp(tau, NOISE_BAND * tau)
        };
        let before = points.len();
        points.retain(|p| (n.dot(*p) + d).abs() >= band * p.z);
        let fraction = (before - points.len()) as f64 / total as f64;
        if fraction < cfg.min_plane_fraction {
            break;
        }
        planes.push(SupportPlane {
            normal: n,
            offset: d,
            band,
            inlier_fraction: fraction,
        });
    }
    planes
}

/// The pixels of `depth` off every one of `planes`: valid, and farther than `cfg.height` ×
/// their depth from each plane (row-major, one flag per pixel).
pub fn off_planes(
    depth: &DepthImage,
    intrinsics: &Intrinsics,
    planes: &[SupportPlane],
    cfg: &SupportConfig,
) -> Vec<bool> {
    (0..depth.data.len())
        .map(|i| {
            back_project(depth, intrinsics, i).is_some_and(|p| {
                planes
                    .iter()
                    .all(|q| q.height(p).abs() > (cfg.height as f64).max(2.0 * q.band) * p.z)
            })
        })
        .collect()
}

/// Grows each labelled pixel group of `label` (row-major; `u32::MAX`: none) into the `free`
/// pixels it reaches through 4-neighbours whose depths differ by at most `depth_jump` × the
/// nearer one (breadth first, all groups at once, so the nearest group takes a pixel). The
/// pixels taken are labelled and no longer free.
pub fn grow_into(label: &mut [u32], free: &mut [bool], depth: &DepthImage, depth_jump: f32) {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let queue = (0..w * h).filter(|&i| label[i] != u32::MAX).collect();
    crate::post::grow4(w, h, queue, |i, j| {
        let (a, b) = (depth.data[i], depth.data[j]);
        let admit = free[j] && (a - b).abs() <= depth_jump * a.min(b);
        if admit {
            free[j] = false;
            label[j] = label[i];
        }
        admit
    });
}

/// The 8-connected groups of `free` pixels (row-major over `depth`) whose neighbouring pixels
/// differ in depth by at most `depth_jump` × the nearer one, of at least `min_pixels` pixels,
/// largest first (ties: the earlier first).
pub fn free_groups(
    free: &[bool],
    depth: &DepthImage,
    depth_jump: f32,
    min_pixels: usize,
) -> Vec<Vec<usize>> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let mut seen = vec![false; w * h];
    let mut groups = Vec::new();
    for start in 0..w * h {
        if !free[start] || seen[start] {
            continue;
        }
        seen[start] = true;
        let members = flood_fill8(w, h, vec![start], |i, j| {
            let (a, b) = (depth.data[i], depth.data[j]);
            let admit = free[j] && !seen[j] && (a - b).abs() <= depth_jump * a.min(b);
            seen[j] |= admit;
            admit
        });
        if members.len() >= min_pixels.max(1) {
            groups.push(members);
        }
    }
    groups.sort_by_key(|g| std::cmp::Reverse(g.len()));
    groups
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 160;

    /// A camera looking straight down at a table 1 unit away (160×120 pixels), with a flat box
    /// 0.03 thick on it (3 % of the depth: what a depth-only network takes for table) and a
    /// sliver 0.005 thick, each a small part of the view.
    fn table() -> (DepthImage, Intrinsics) {
        let k = Intrinsics::new(200.0, 200.0, 79.5, 59.5, 160, 120).unwrap();
        let mut depth = DepthImage::filled(160, 120, 1.0);
        for v in 10..25 {
            for u in 10..30 {
                depth.data[v * W + u] = 0.97;
            }
        }
        for v in 80..90 {
            for u in 100..120 {
                depth.data[v * W + u] = 0.995;
            }
        }
        (depth, k)
    }

    fn box_pixels() -> Vec<usize> {
        (10..25)
            .flat_map(|v| (10..30).map(move |u| v * W + u))
            .collect()
    }

    #[test]
    fn a_flat_box_standing_out_of_the_table_is_found_and_a_sliver_is_not() {
        let (depth, k) = table();
        let cfg = SupportConfig::default();
        let planes = support_planes(&depth, &k, &cfg);
        assert_eq!(planes.len(), 1, "the table only: {planes:?}");
        let table = planes[0];
        assert!((table.normal.z.abs() - 1.0).abs() < 1e-9, "{table:?}");
        assert!(
            table.offset > 0.0,
            "the camera's side is positive: {table:?}"
        );
        assert!((table.height(DVec3::new(0.0, 0.0, 0.97)) - 0.03).abs() < 1e-9);
        let free = off_planes(&depth, &k, &planes, &cfg);
        let groups = free_groups(&free, &depth, 0.02, 10);
        assert_eq!(groups.len(), 1, "only the box: {groups:?}");
        let mut got = groups[0].clone();
        got.sort_unstable();
        assert_eq!(got, box_pixels());
    }

    #[test]
    fn an_instance_grows_over_the_box_it_holds_part_of_and_not_across_a_depth_step() {
        let (depth, k) = table();
        let cfg = SupportConfig::default();
        let planes = support_planes(&depth, &k, &cfg);
        let mut free = off_planes(&depth, &k, &planes, &cfg);
        let mut label = vec![u32::MAX; W * 120];
        // The instance holds the box's left half and a table pixel beside it.
        for v in 10..25 {
            for u in 9..20 {
                label[v * W + u] = 0;
                free[v * W + u] = false;
            }
        }
        let mut left = free.clone();
        assert_eq!(
            free_groups(&left, &depth, 0.02, 10)[0].len(),
            15 * 10,
            "the free half"
        );
        grow_into(&mut label, &mut left, &depth, 0.02);
        assert!(free_groups(&left, &depth, 0.02, 1).is_empty(), "all taken");
        let held: Vec<usize> = (0..W * 120).filter(|&i| label[i] == 0).collect();
        let mut expected = box_pixels();
        expected.extend((10..25).map(|v| v * W + 9));
        expected.sort_unstable();
        assert_eq!(
            held, expected,
            "the box and the one table pixel, never more table"
        );
        // A step of 3 % between the halves stops the growth at 2 %.
        let mut stepped = depth.clone();
        for v in 10..25 {
            for u in 20..30 {
                stepped.data[v * W + u] = 0.94;
            }
        }
        let mut label2 = vec![u32::MAX; W * 120];
        for v in 10..25 {
            for u in 10..20 {
                label2[v * W + u] = 0;
                free[v * W + u] = false;
            }
        }
        grow_into(&mut label2, &mut free, &stepped, 0.02);
        assert_eq!(free_groups(&free, &stepped, 0.02, 10)[0].len(), 15 * 10);
    }

    #[test]
    fn a_noisy_table_widens_its_band_so_its_noise_is_not_objects() {
        let (mut depth, k) = table();
        // ±0.6 % noise (a far sensor) on every table pixel: above the 0.4 % band.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for z in depth.data.iter_mut() {
            if *z == 1.0 {
                *z = 1.0 + rng.random_range(-0.006f32..0.006);
            }
        }
        let cfg = SupportConfig {
            plane_threshold: 0.004,
            height: 0.01,
            ..SupportConfig::default()
        };
        let planes = support_planes(&depth, &k, &cfg);
        assert_eq!(planes.len(), 1, "{planes:?}");
        assert!(planes[0].band > 0.004, "{:?}", planes[0]);
        let free = off_planes(&depth, &k, &planes, &cfg);
        let groups = free_groups(&free, &depth, 0.02, 10);
        assert_eq!(
            groups.len(),
            1,
            "the box alone, not the noise: {}",
            groups.len()
        );
    }

    #[test]
    fn no_plane_large_enough_is_no_support() {
        // A bowl of depths: no plane holds 10 % of it.
        let k = Intrinsics::new(100.0, 100.0, 39.5, 29.5, 80, 60).unwrap();
        let mut depth = DepthImage::filled(80, 60, 1.0);
        for (i, z) in depth.data.iter_mut().enumerate() {
            let (x, y) = ((i % 80) as f32 - 40.0, (i / 80) as f32 - 30.0);
            *z = 1.0 + 0.002 * (x * x + y * y);
        }
        assert!(support_planes(&depth, &k, &SupportConfig::default()).is_empty());
        let empty = DepthImage::filled(80, 60, 0.0);
        assert!(support_planes(&empty, &k, &SupportConfig::default()).is_empty());
    }

    #[test]
    fn settings_out_of_range_are_refused() {
        assert!(SupportConfig::default().validate().is_ok());
        for bad in [
            SupportConfig {
                height: 0.0,
                ..SupportConfig::default()
            },
            SupportConfig {
                plane_threshold: f32::NAN,
                ..SupportConfig::default()
            },
            SupportConfig {
                min_plane_fraction: 1.5,
                ..SupportConfig::default()
            },
            SupportConfig {
                stride: 0,
                ..SupportConfig::default()
            },
        ] {
            assert!(
                matches!(bad.validate(), Err(SegError::Config(_))),
                "{bad:?}"
            );
        }
    }
}
