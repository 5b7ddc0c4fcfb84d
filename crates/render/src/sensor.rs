//! Seeded depth-sensor artefacts applied to a clean [`Rendering`]. Every effect is off by
//! default. Lengths are metres (depth, noise, thresholds) and pixels (jitter, patches): apply
//! the model to a rendering whose depth is in metres.
//!
//! Order: lateral jitter (depth, id and incidence move together, so edges move), the
//! projector's shadows and the holes of registration to a colour camera (both on the
//! jittered, otherwise clean depth), flying pixels (on the depth edges left), grazing-angle
//! dropout, dropout patches, axial noise, quantisation. A dropped pixel gets depth 0 (no
//! return) but keeps its instance id, which stays the ground-truth segmentation of what is in
//! front of the sensor.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::Rendering;

/// Gaussian axial noise with standard deviation `σ(z) = a + b·(z − z0)²` (metres). Defaults:
/// Nguyen, Izadi, Lovell 2012 (Kinect v1): a = 0.0012, b = 0.0019, z0 = 0.4.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AxialNoise {
    pub a: f64,
    pub b: f64,
    pub z0: f64,
}

impl Default for AxialNoise {
    fn default() -> Self {
        AxialNoise {
            a: 0.0012,
            b: 0.0019,
            z0: 0.4,
        }
    }
}

impl AxialNoise {
    /// σ at depth `z`.
    pub fn sigma(&self, z: f64) -> f64 {
        self.a + self.b * (z - self.z0).powi(2)
    }
}

/// Depth quantisation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum Quantisation {
    /// Round z to a multiple of `step` metres (e.g. 0.001: a 16-bit PNG at depth scale 1).
    Step { step: f64 },
    /// A structured-light sensor: disparity `d = focal·baseline/z` (pixels) rounded to
    /// `1/subpixel` pixel, then `z = focal·baseline/d`. Kinect v1: focal 580, baseline 0.075,
    /// subpixel 8.
    Disparity {
        focal: f64,
        baseline: f64,
        subpixel: f64,
    },
}

/// Missing returns where the surface is seen at a grazing angle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GrazingDropout {
    /// Pixels whose angle between surface normal and viewing ray exceeds this are dropped.
    pub max_angle_deg: f64,
}

impl Default for GrazingDropout {
    fn default() -> Self {
        GrazingDropout {
            max_angle_deg: 80.0,
        }
    }
}

/// Mixed ("flying") pixels at depth discontinuities: with `probability`, a pixel whose depth
/// differs from a 4-neighbour with a return by more than `edge_threshold` metres gets a depth
/// interpolated between its own and that neighbour's (the one with the largest jump), at a
/// uniformly random fraction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlyingPixels {
    pub edge_threshold: f64,
    pub probability: f64,
}

impl Default for FlyingPixels {
    fn default() -> Self {
        FlyingPixels {
            edge_threshold: 0.05,
            probability: 0.5,
        }
    }
}

/// Lateral jitter: every pixel shows what its neighbour at a Gaussian offset (σ pixels per
/// axis, rounded to the nearest pixel, at most 3σ) shows — depth, instance id and incidence
/// together, so depth edges and silhouettes become ragged as on structured-light sensors.
/// Offsets that leave the image give no return.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LateralJitter {
    pub sigma_px: f64,
}

impl Default for LateralJitter {
    fn default() -> Self {
        LateralJitter { sigma_px: 0.5 }
    }
}

/// Missing returns in patches (dark, shiny or transparent surfaces): `count` filled ellipses,
/// each centred on a random pixel with a return, with semi-axes drawn uniformly from
/// `radius_px` (pixels) and a random orientation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DropoutPatches {
    pub count: usize,
    pub radius_px: (f64, f64),
}

impl Default for DropoutPatches {
    fn default() -> Self {
        DropoutPatches {
            count: 1,
            radius_px: (2.0, 10.0),
        }
    }
}

/// Missing returns where the projector's light cannot reach (structured light, active
/// stereo): a pixel is dropped when a nearer surface hides its point from a projector set
/// `baseline_m` metres along the camera's x axis (right in the image; negative: left). The
/// camera and the projector are rectified, so a point at depth z (metres) lies on the
/// projector's row at column `u − focal_px·baseline_m/z`; a pixel whose projector column
/// comes after that of a pixel on the projector's side of it is hidden. The shadow falls
/// beside each foreground edge on the side away from the projector, `focal_px·|baseline_m|·
/// (1/z_near − 1/z_far)` pixels wide (Kinect v1, 580 px and 0.075 m: ≈ 5 px beside a cup
/// 10 cm above a table at 0.9 m). `focal_px` is the rendering's fx.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorShadow {
    pub baseline_m: f64,
    pub focal_px: f64,
}

/// A pixel is hidden from the projector when its projector column passes that of a pixel on
/// the projector's side by more than this (pixels): a surface seen at an angle near the
/// projector's rays does not flicker at the rasteriser's rounding.
const SHADOW_TOLERANCE_PX: f64 = 0.5;

impl ProjectorShadow {
    /// Marks in `hidden` (one flag per pixel, row-major) the pixels of `depth` (metres, 0 =
    /// no return) that a nearer surface hides from the projector.
    fn mark_hidden(&self, depth: &[f32], width: usize, hidden: &mut [bool]) {
        let fb = self.focal_px * self.baseline_m;
        if !(fb.is_finite() && fb != 0.0) || width == 0 {
            return;
        }
        for (row, hidden) in depth.chunks(width).zip(hidden.chunks_mut(width)) {
            // Walk from the projector's side; `reach`: the smallest (projector right) or
            // largest (left) projector column of the pixels walked.
            let mut reach: Option<f64> = None;
            let mut visit = |u: usize| {
                let z = row[u] as f64;
                if z <= 0.0 {
                    return;
                }
                let up = u as f64 - fb / z;
                match reach {
                    Some(m)
                        if (fb > 0.0 && up > m + SHADOW_TOLERANCE_PX)
                            || (fb < 0.0 && up < m - SHADOW_TOLERANCE_PX) =>
                    {
                        hidden[u] = true
                    }
                    Some(m) if (fb > 0.0) == (up < m) => reach = Some(up),
                    Some(_) => {}
                    None => reach = Some(up),
                }
            };
            if fb > 0.0 {
                (0..row.len()).rev().for_each(&mut visit);
            } else {
                (0..row.len()).for_each(&mut visit);
            }
        }
    }
}

/// Which artefacts to simulate (all `None` = a perfect sensor).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SensorConfig {
    pub noise: Option<AxialNoise>,
    pub quantisation: Option<Quantisation>,
    pub grazing: Option<GrazingDropout>,
    pub flying_pixels: Option<FlyingPixels>,
    pub lateral_jitter: Option<LateralJitter>,
    pub dropout_patches: Option<DropoutPatches>,
    pub shadow: Option<ProjectorShadow>,
    /// Depth registered to a colour camera beside the depth camera (what BOP's and most
    /// drivers' depth maps are): the depth camera is then a "projector" on the colour
    /// camera's x axis, and what it cannot see from there has no depth in the registered
    /// map — a second band, beside the edges on the side away from the depth camera
    /// (`baseline_m`: the depth camera's offset from the colour camera). Found on the same
    /// depth as [`SensorConfig::shadow`].
    pub registration: Option<ProjectorShadow>,
}

impl SensorConfig {
    /// Whether any effect is on.
    pub fn is_ideal(&self) -> bool {
        self.noise.is_none()
            && self.quantisation.is_none()
            && self.grazing.is_none()
            && self.flying_pixels.is_none()
            && self.lateral_jitter.is_none()
            && self.dropout_patches.is_none()
            && self.shadow.is_none()
            && self.registration.is_none()
    }

    /// Applies the configured effects in place; deterministic for a given `seed`. Effects
    /// that are off draw nothing from the random stream, and the effects of the first
    /// version (noise, quantisation, grazing, flying pixels) draw exactly as they did.
    pub fn apply(&self, r: &mut Rendering, seed: u64) {
        if self.is_ideal() {
            return;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (w, h) = (r.depth.width as usize, r.depth.height as usize);
        if let Some(j) = self.lateral_jitter
            && j.sigma_px > 0.0
            && j.sigma_px.is_finite()
        {
            // Its own stream, so switching it on leaves the other effects' draws unchanged.
            let mut jrng = ChaCha8Rng::seed_from_u64(seed ^ 0x6a69_7474_6572);
            let limit = (3.0 * j.sigma_px).ceil();
            let (depth, ids, inc) = (
                r.depth.data.clone(),
                r.instances.data.clone(),
                r.incidence.data.clone(),
            );
            for v in 0..h {
                for u in 0..w {
                    let mut offset = || {
                        let e: f64 = StandardNormal.sample(&mut jrng);
                        (e * j.sigma_px).round().clamp(-limit, limit) as i64
                    };
                    let (su, sv) = (u as i64 + offset(), v as i64 + offset());
                    let i = v * w + u;
                    if su < 0 || sv < 0 || su >= w as i64 || sv >= h as i64 {
                        r.depth.data[i] = 0.0;
                        r.instances.data[i] = 0;
                        r.incidence.data[i] = 0.0;
                    } else {
                        let s = sv as usize * w + su as usize;
                        r.depth.data[i] = depth[s];
                        r.instances.data[i] = ids[s];
                        r.incidence.data[i] = inc[s];
                    }
                }
            }
        }
        if self.shadow.is_some() || self.registration.is_some() {
            // Both from the same surfaces: what hides a point is geometry, not a return.
            let mut hidden = vec![false; w * h];
            for shadow in [self.shadow, self.registration].into_iter().flatten() {
                shadow.mark_hidden(&r.depth.data, w, &mut hidden);
            }
            for (z, gone) in r.depth.data.iter_mut().zip(hidden) {
                if gone {
                    *z = 0.0;
                }
            }
        }
        if let Some(f) = self.flying_pixels {
            let clean = r.depth.data.clone();
            for v in 0..h {
                for u in 0..w {
                    let i = v * w + u;
                    let z = clean[i];
                    if z <= 0.0 {
                        continue;
                    }
                    // The neighbour with the largest jump.
                    let mut best: Option<f32> = None;
                    let mut jump = f.edge_threshold as f32;
                    let neighbours = [
                        (u > 0).then(|| i - 1),
                        (u + 1 < w).then(|| i + 1),
                        (v > 0).then(|| i - w),
                        (v + 1 < h).then(|| i + w),
                    ];
                    for n in neighbours.into_iter().flatten() {
                        let zn = clean[n];
                        if zn > 0.0 && (zn - z).abs() > jump {
                            jump = (zn - z).abs();
                            best = Some(zn);
                        }
                    }
                    if let Some(zn) = best
                        && rng.random_bool(f.probability.clamp(0.0, 1.0))
                    {
                        let t: f32 = rng.random();
                        r.depth.data[i] = z + t * (zn - z);
                    }
                }
            }
        }
        if let Some(g) = self.grazing {
            let min_cos = g.max_angle_deg.to_radians().cos() as f32;
            for (z, &c) in r.depth.data.iter_mut().zip(&r.incidence.data) {
                if *z > 0.0 && c < min_cos {
                    *z = 0.0;
                }
            }
        }
        if let Some(p) = self.dropout_patches {
            let mut prng = ChaCha8Rng::seed_from_u64(seed ^ 0x7061_7463_6865);
            drop_patches(r, p, &mut prng);
        }
        if let Some(n) = self.noise {
            for z in r.depth.data.iter_mut().filter(|z| **z > 0.0) {
                let e: f64 = StandardNormal.sample(&mut rng);
                let noisy = *z as f64 + n.sigma(*z as f64) * e;
                *z = if noisy > 0.0 { noisy as f32 } else { 0.0 };
            }
        }
        if let Some(q) = self.quantisation {
            for z in r.depth.data.iter_mut().filter(|z| **z > 0.0) {
                let zf = *z as f64;
                let out = match q {
                    Quantisation::Step { step } if step > 0.0 => (zf / step).round() * step,
                    Quantisation::Step { .. } => zf,
                    Quantisation::Disparity {
                        focal,
                        baseline,
                        subpixel,
                    } => {
                        let fb = focal * baseline;
                        let d = (fb / zf * subpixel).round() / subpixel;
                        if d > 0.0 { fb / d } else { 0.0 }
                    }
                };
                *z = out as f32;
            }
        }
    }
}

/// Zeroes the depth inside `p.count` random ellipses centred on pixels with a return.
fn drop_patches(r: &mut Rendering, p: DropoutPatches, rng: &mut ChaCha8Rng) {
    let (w, h) = (r.depth.width as usize, r.depth.height as usize);
    let (lo, hi) = p.radius_px;
    if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi >= lo) {
        return;
    }
    for _ in 0..p.count {
        let valid: Vec<usize> = (0..w * h).filter(|&i| r.depth.data[i] > 0.0).collect();
        if valid.is_empty() {
            return;
        }
        let c = valid[rng.random_range(0..valid.len())];
        let (cu, cv) = ((c % w) as f64, (c / w) as f64);
        let mut radius = || {
            if hi > lo {
                rng.random_range(lo..=hi)
            } else {
                lo
            }
        };
        let (a, b) = (radius().max(0.5), radius().max(0.5));
        let angle: f64 = rng.random_range(0.0..std::f64::consts::PI);
        let (cs, sn) = (angle.cos(), angle.sin());
        let reach = a.max(b).ceil() as i64;
        for dv in -reach..=reach {
            for du in -reach..=reach {
                let (u, v) = (cu as i64 + du, cv as i64 + dv);
                if u < 0 || v < 0 || u >= w as i64 || v >= h as i64 {
                    continue;
                }
                let (x, y) = (
                    du as f64 * cs + dv as f64 * sn,
                    -(du as f64) * sn + dv as f64 * cs,
                );
                if (x / a).powi(2) + (y / b).powi(2) <= 1.0 {
                    r.depth.data[v as usize * w + u as usize] = 0.0;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::Image;

    fn flat(z: f32) -> Rendering {
        let mut r = Rendering::empty(40, 30);
        r.depth = Image::filled(40, 30, z);
        r.instances = Image::filled(40, 30, 1);
        r.incidence = Image::filled(40, 30, 1.0);
        r
    }

    #[test]
    fn default_is_ideal_and_noise_matches_sigma() {
        let mut r = flat(2.0);
        let clean = r.clone();
        SensorConfig::default().apply(&mut r, 1);
        assert_eq!(r, clean);
        let cfg = SensorConfig {
            noise: Some(AxialNoise::default()),
            ..Default::default()
        };
        let mut a = flat(2.0);
        cfg.apply(&mut a, 7);
        let mut b = flat(2.0);
        cfg.apply(&mut b, 7);
        assert_eq!(a, b, "seeded");
        let n = a.depth.data.len() as f64;
        let mean = a.depth.data.iter().map(|&z| z as f64).sum::<f64>() / n;
        let sd = (a
            .depth
            .data
            .iter()
            .map(|&z| (z as f64 - mean).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        let want = AxialNoise::default().sigma(2.0);
        assert!((sd - want).abs() < 0.1 * want, "sd {sd} vs {want}");
        assert!((mean - 2.0).abs() < 3.0 * want / n.sqrt() + 1e-6);
    }

    #[test]
    fn quantisation_grazing_and_flying_pixels() {
        let mut r = flat(1.23456);
        SensorConfig {
            quantisation: Some(Quantisation::Step { step: 0.001 }),
            ..Default::default()
        }
        .apply(&mut r, 0);
        assert!((r.depth.data[0] - 1.235).abs() < 1e-6);
        let mut r = flat(2.0);
        SensorConfig {
            quantisation: Some(Quantisation::Disparity {
                focal: 580.0,
                baseline: 0.075,
                subpixel: 8.0,
            }),
            ..Default::default()
        }
        .apply(&mut r, 0);
        // d = 21.75 exactly, so 2.0 is representable.
        assert!((r.depth.data[0] - 2.0).abs() < 1e-6);

        let mut r = flat(2.0);
        r.incidence.data[5] = 0.1; // ≈ 84°
        SensorConfig {
            grazing: Some(GrazingDropout::default()),
            ..Default::default()
        }
        .apply(&mut r, 0);
        assert_eq!(r.depth.data[5], 0.0);
        assert_eq!(r.depth.data[6], 2.0);
        assert_eq!(r.instances.data[5], 1, "ids are kept");

        // A step edge: left half at 1 m, right half at 3 m.
        let mut r = flat(1.0);
        for v in 0..30 {
            for u in 20..40 {
                r.depth.data[v * 40 + u] = 3.0;
            }
        }
        let cfg = SensorConfig {
            flying_pixels: Some(FlyingPixels {
                edge_threshold: 0.5,
                probability: 1.0,
            }),
            ..Default::default()
        };
        cfg.apply(&mut r, 3);
        for v in 0..30 {
            let (a, b) = (r.depth.data[v * 40 + 19], r.depth.data[v * 40 + 20]);
            assert!((1.0..=3.0).contains(&a) && (1.0..=3.0).contains(&b));
            assert_eq!(r.depth.data[v * 40 + 10], 1.0);
            assert_eq!(r.depth.data[v * 40 + 30], 3.0);
        }
        assert!((0..30).any(|v| r.depth.data[v * 40 + 19] != 1.0));
    }

    #[test]
    fn lateral_jitter_moves_edges_and_dropout_patches_remove_returns() {
        // A step edge in depth and id: left half id 1 at 1 m, right half id 2 at 3 m.
        let edge = || {
            let mut r = flat(1.0);
            for v in 0..30 {
                for u in 20..40 {
                    r.depth.data[v * 40 + u] = 3.0;
                    r.instances.data[v * 40 + u] = 2;
                }
            }
            r
        };
        let clean = edge();
        let jitter = SensorConfig {
            lateral_jitter: Some(LateralJitter { sigma_px: 1.0 }),
            ..Default::default()
        };
        let mut a = edge();
        jitter.apply(&mut a, 5);
        let mut b = edge();
        jitter.apply(&mut b, 5);
        assert_eq!(a, b, "seeded");
        // Depth and id move together: every pixel still pairs 1 m with id 1 and 3 m with id 2
        // (or lost its return at the image border).
        for (z, id) in a.depth.data.iter().zip(&a.instances.data) {
            assert!(
                (*z == 1.0 && *id == 1) || (*z == 3.0 && *id == 2) || (*z == 0.0 && *id == 0),
                "{z} {id}"
            );
        }
        // The edge is ragged: some pixels left of it show the far side and vice versa, while
        // pixels far from the edge (and from the image border, where offsets leave the image)
        // keep their value.
        let changed = |u: usize| {
            (3..27)
                .filter(|&v| a.depth.data[v * 40 + u] != clean.depth.data[v * 40 + u])
                .count()
        };
        assert!(changed(19) + changed(20) > 10, "edge pixels moved");
        assert_eq!(changed(10), 0);

        let patches = SensorConfig {
            dropout_patches: Some(DropoutPatches {
                count: 2,
                radius_px: (3.0, 3.0),
            }),
            ..Default::default()
        };
        let mut r = flat(2.0);
        patches.apply(&mut r, 9);
        let dropped = r.depth.data.iter().filter(|&&z| z == 0.0).count();
        // Two discs of radius 3 (29 pixels each on the grid, possibly overlapping or cut by the
        // border), ids kept.
        assert!((10..=58).contains(&dropped), "{dropped} pixels dropped");
        assert!(r.instances.data.iter().all(|&i| i == 1));
        // Off: nothing changes.
        let mut r = flat(2.0);
        SensorConfig::default().apply(&mut r, 9);
        assert!(r.depth.data.iter().all(|&z| z == 2.0));
    }

    /// A wall at 1 m with a box at 0.8 m over columns 100..150 of a 240-pixel-wide image.
    fn box_before_wall() -> Rendering {
        let (w, h) = (240u32, 4u32);
        let mut r = Rendering::empty(w, h);
        r.depth = Image::filled(w, h, 1.0);
        r.instances = Image::filled(w, h, 1000);
        r.incidence = Image::filled(w, h, 1.0);
        for v in 0..h as usize {
            for u in 100..150 {
                r.depth.data[v * w as usize + u] = 0.8;
                r.instances.data[v * w as usize + u] = 1;
            }
        }
        r
    }

    #[test]
    fn the_projector_shadow_falls_beside_the_nearer_edge_away_from_the_projector() {
        // 525 px · 0.075 m: disparities 39.375 px at 1 m and 49.22 px at 0.8 m, so the wall
        // loses ≈ 9.8 − 0.5 (tolerance) pixels beside the box.
        let shadowed = |baseline_m: f64| {
            let mut r = box_before_wall();
            let before = r.clone();
            SensorConfig {
                shadow: Some(ProjectorShadow {
                    baseline_m,
                    focal_px: 525.0,
                }),
                ..Default::default()
            }
            .apply(&mut r, 3);
            assert_eq!(r.instances, before.instances, "ids stay");
            let w = r.depth.width as usize;
            let rows: Vec<Vec<usize>> = r
                .depth
                .data
                .chunks(w)
                .map(|row| (0..w).filter(|&u| row[u] == 0.0).collect())
                .collect();
            assert!(rows.iter().all(|row| *row == rows[0]), "every row alike");
            rows[0].clone()
        };
        // Projector to the right: the shadow is on the wall left of the box.
        assert_eq!(shadowed(0.075), (91..100).collect::<Vec<_>>());
        // To the left: right of the box.
        assert_eq!(shadowed(-0.075), (150..159).collect::<Vec<_>>());
        // Registered to a colour camera 2.5 cm to the projector's side of the depth camera:
        // the depth camera (2.5 cm the other way) leaves a narrower band on the other side: a
        // disparity step of 525 · 0.025 · (1/0.8 − 1/1) = 3.3 px, of which the wall pixels
        // hidden by more than the half-pixel tolerance are 2.
        let mut r = box_before_wall();
        SensorConfig {
            shadow: Some(ProjectorShadow {
                baseline_m: 0.05,
                focal_px: 525.0,
            }),
            registration: Some(ProjectorShadow {
                baseline_m: -0.025,
                focal_px: 525.0,
            }),
            ..Default::default()
        }
        .apply(&mut r, 3);
        let row = &r.depth.data[..r.depth.width as usize];
        let holes: Vec<usize> = (0..row.len()).filter(|&u| row[u] == 0.0).collect();
        assert_eq!(holes, [94, 95, 96, 97, 98, 99, 150, 151]);
        // A surface facing the camera and the projector casts none on itself.
        let mut wall = flat(1.0);
        let clean = wall.clone();
        SensorConfig {
            shadow: Some(ProjectorShadow {
                baseline_m: 0.075,
                focal_px: 525.0,
            }),
            ..Default::default()
        }
        .apply(&mut wall, 3);
        assert_eq!(wall, clean);
    }
}
