//! Hypothesise and verify: many pose hypotheses, each scored by rendering the model at that
//! pose and comparing it with the observed depth.
//!
//! - [`rotation_set`]: rotations that cover SO(3) evenly (the finite rotation groups of the
//!   tetrahedron, cube and icosahedron: 12, 24, 60). The network is right when the rotation
//!   between model and view falls in the family it was trained on; registering a rotated copy
//!   of the model for each rotation puts one copy inside that family.
//! - [`Observation`]: the observed depth around the object, cropped and reduced to at most
//!   [`SCORE_SIDE`] pixels a side — from a depth map and the object mask, or, for point inputs,
//!   from the observed points splatted into a virtual camera at the origin.
//! - [`Observation::score`]: renders the model (its mesh with the CPU renderer, or its points
//!   splatted) at a pose into the same crop and counts agreeing pixels, free-space violations
//!   (the model in front of the observed surface, where the sensor would have seen it) and
//!   coverage of the object mask. Poses equivalent under the object's symmetry render alike
//!   and so score alike.
//!
//! Units: normalised object units (the model spans [-1, 1] on its longest side); camera frame
//! OpenCV (x right, y down, z forward); poses map model → camera; depth is camera-frame z, 0 =
//! no return.

use std::sync::Arc;

use ic_geometry::glam::Vec3;
use ic_geometry::{DepthImage, Image, Intrinsics, Mask, Mesh, Pose};
use ic_render::{Camera, CpuRenderer, Renderer, Scene};
use serde::Serialize;

/// The longest side of the scoring crop, in pixels: a pose is scored on at most 96×96 pixels
/// around the object (≈ 1–3 ms per render on one core for meshes of a few thousand triangles).
pub const SCORE_SIDE: u32 = 96;

/// Rotations covering SO(3) evenly: `count` ∈ {1, 12, 24, 60}; see
/// [`ic_geometry::rotations::rotation_group`].
pub fn rotation_set(count: usize) -> Result<Vec<Pose>, String> {
    ic_geometry::rotations::rotation_group(count).map_err(|e| e.to_string())
}

/// Pixels around each rendered pixel (of the crop) whose observed depth may explain it (see
/// `Observation::compare`).
pub const NEIGHBOURHOOD: usize = 1;

/// Depth agreement tolerance at camera distance `z` (normalised units) for a surface of the
/// given roughness: 0.03 (1.5 % of the object's size) plus 0.5 % of the distance, and at least
/// three times the roughness, so that sensor noise — which grows with distance and, in
/// normalised units, as the object gets smaller — does not read as disagreement.
pub fn depth_tolerance(z: f32, roughness: f32) -> f32 {
    (0.03 + 0.005 * z).max(3.0 * roughness)
}

/// The median |Δz| between horizontally adjacent pixels that are both in the mask and have a
/// return, within rows `v0..=v1` and columns `u0..=u1`.
fn roughness(
    depth: &DepthImage,
    mask: &Mask,
    (u0, v0, u1, v1): (usize, usize, usize, usize),
) -> f32 {
    let w = depth.width as usize;
    let mut d = Vec::new();
    for v in v0..=v1 {
        for u in u0..u1 {
            let (i, j) = (v * w + u, v * w + u + 1);
            let (a, b) = (depth.data[i], depth.data[j]);
            if mask.data[i] && mask.data[j] && a > 0.0 && b > 0.0 {
                d.push((a - b).abs());
            }
        }
    }
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    *d.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// How the model is drawn into a crop: its mesh (normalised) or its points (splatted).
#[derive(Clone)]
pub enum ModelShape {
    Mesh(Arc<Mesh>),
    /// Surface points (normalised units), each drawn as a square of side `2·radius` (normalised
    /// units) facing the camera; `radius` ≈ the points' spacing, so the squares close the
    /// surface.
    Points {
        points: Arc<Vec<Vec3>>,
        radius: f32,
    },
}

impl ModelShape {
    /// Points splatted with a radius of their median nearest-neighbour distance (at least
    /// `min_radius`, normalised units).
    pub fn points(points: Vec<Vec3>, min_radius: f32) -> ModelShape {
        let mut d: Vec<f32> = match ic_geometry::KdTree::new(&points) {
            Ok(tree) => points
                .iter()
                .filter_map(|p| tree.k_nearest(*p, 2).get(1).map(|n| n.distance))
                .collect(),
            Err(_) => Vec::new(),
        };
        d.sort_by(f32::total_cmp);
        let median = d.get(d.len() / 2).copied().unwrap_or(min_radius);
        ModelShape::Points {
            points: Arc::new(points),
            radius: median.max(min_radius),
        }
    }
}

/// The observed depth around the object, at reduced resolution.
#[derive(Clone, Debug)]
pub struct Observation {
    /// The crop's intrinsics (principal point shifted, focal lengths reduced).
    pub intrinsics: Intrinsics,
    /// Observed depth in the crop (normalised units; 0 = no return).
    pub depth: DepthImage,
    /// The object's pixels in the crop.
    pub mask: Mask,
    /// Pixels of the mask with a return.
    pub mask_pixels: usize,
    /// The observed surface's roughness: the median |Δz| between horizontally adjacent mask
    /// pixels of the full-resolution depth (normalised units). Sensor noise and quantisation
    /// show up here; the agreement tolerance is never below three times it.
    pub roughness: f32,
}

/// The render-and-compare score of one pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Score {
    /// In [0, 1]: coverage × (1 − 3·violation), clamped at 0.
    pub score: f64,
    /// Fraction of the object mask's pixels whose depth the model explains.
    pub coverage: f64,
    /// Fraction of the model's rendered pixels (where the sensor returned) that agree.
    pub agreement: f64,
    /// Fraction of the model's rendered pixels in front of the observed surface (free-space
    /// violations).
    pub violation: f64,
    /// Fraction of the model's rendered pixels (where the sensor returned) that agree, among
    /// those not hidden: a rendered pixel lying behind the observed surface of its pixel and of
    /// all its neighbours (by more than the tolerance) is consistent with a nearer object
    /// occluding it, and left out. In clutter a right pose is often partly hidden by its
    /// neighbours; [`Score::agreement`] counts those pixels against it, this does not.
    pub visible_agreement: f64,
    /// Mean depth residual of the agreeing pixels, each in units of its tolerance (in [0, 1]):
    /// |rendered − observed| at the pixel, or at the nearest-in-depth neighbour that explains
    /// it. Two poses that explain the same pixels (a near-symmetric object and its flip) differ
    /// here: the right one fits the surface to within the sensor noise.
    pub misfit: f64,
}

impl Observation {
    /// From a depth map (normalised units), its intrinsics and the object mask: the mask's
    /// bounding box grown by 30 % on each side (clamped to the image), reduced so its longest
    /// side is at most [`SCORE_SIDE`]. `None` when the mask has no pixel with a return.
    pub fn from_depth(depth: &DepthImage, k: &Intrinsics, mask: &Mask) -> Option<Observation> {
        let (w, h) = (depth.width as usize, depth.height as usize);
        let (mut u0, mut v0, mut u1, mut v1) = (usize::MAX, usize::MAX, 0usize, 0usize);
        for v in 0..h {
            for u in 0..w {
                if mask.data[v * w + u] && depth.data[v * w + u] > 0.0 {
                    u0 = u0.min(u);
                    v0 = v0.min(v);
                    u1 = u1.max(u);
                    v1 = v1.max(v);
                }
            }
        }
        if u0 == usize::MAX {
            return None;
        }
        let grow = |lo: usize, hi: usize, max: usize| {
            let m = ((hi - lo + 1) as f64 * 0.3).ceil() as usize;
            (lo.saturating_sub(m), (hi + m).min(max - 1))
        };
        let rough = roughness(depth, mask, (u0, v0, u1, v1));
        let (u0, u1) = grow(u0, u1, w);
        let (v0, v1) = grow(v0, v1, h);
        let (cw, ch) = (u1 - u0 + 1, v1 - v0 + 1);
        let f = cw.max(ch).div_ceil(SCORE_SIDE as usize).max(1);
        let (ow, oh) = (cw.div_ceil(f), ch.div_ceil(f));
        // Crop pixel i samples source pixel u0 + i·f + ⌊f/2⌋: the crop's camera puts its pixel
        // centres exactly there.
        let half = (f / 2) as f64;
        let intrinsics = Intrinsics {
            fx: k.fx / f as f64,
            fy: k.fy / f as f64,
            cx: (k.cx - u0 as f64 - half) / f as f64,
            cy: (k.cy - v0 as f64 - half) / f as f64,
            width: ow as u32,
            height: oh as u32,
        };
        let mut d = Image::filled(ow as u32, oh as u32, 0.0f32);
        let mut m = Image::filled(ow as u32, oh as u32, false);
        let mut mask_pixels = 0;
        for j in 0..oh {
            for i in 0..ow {
                let u = (u0 + i * f + f / 2).min(w - 1);
                let v = (v0 + j * f + f / 2).min(h - 1);
                let z = depth.data[v * w + u];
                d.data[j * ow + i] = z;
                let inside = mask.data[v * w + u];
                m.data[j * ow + i] = inside;
                mask_pixels += (inside && z > 0.0) as usize;
            }
        }
        Some(Observation {
            intrinsics,
            depth: d,
            mask: m,
            mask_pixels,
            roughness: rough,
        })
    }

    /// From observed points alone (camera frame, normalised units; e.g. a registration
    /// case's `target.ply`): a virtual pinhole camera at the origin looking down +z whose
    /// pixel at the cloud's median depth is `pixel` units wide (about the voxel size), the
    /// points z-buffered into it with a one-pixel splat; every covered pixel is the mask.
    pub fn from_points(points: &[Vec3], pixel: f32) -> Option<Observation> {
        let finite: Vec<Vec3> = points
            .iter()
            .copied()
            .filter(|p| p.is_finite() && p.z > 1e-3)
            .collect();
        if finite.len() < 3 {
            return None;
        }
        let mut zs: Vec<f32> = finite.iter().map(|p| p.z).collect();
        zs.sort_by(f32::total_cmp);
        let z_med = zs[zs.len() / 2];
        let f = (z_med / pixel) as f64;
        let (mut u0, mut v0, mut u1, mut v1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in &finite {
            let (u, v) = (f * (p.x / p.z) as f64, f * (p.y / p.z) as f64);
            u0 = u0.min(u);
            v0 = v0.min(v);
            u1 = u1.max(u);
            v1 = v1.max(v);
        }
        let margin = 0.3 * (u1 - u0).max(v1 - v0) + 2.0;
        let side = ((u1 - u0).max(v1 - v0) + 2.0 * margin).ceil();
        let scale = (side / SCORE_SIDE as f64).max(1.0);
        let f = f / scale;
        let (u0, v0, u1, v1) = (u0 / scale, v0 / scale, u1 / scale, v1 / scale);
        let margin = margin / scale;
        let width = ((u1 - u0) + 2.0 * margin).ceil().max(1.0) as u32;
        let height = ((v1 - v0) + 2.0 * margin).ceil().max(1.0) as u32;
        let intrinsics = Intrinsics {
            fx: f,
            fy: f,
            cx: margin - u0,
            cy: margin - v0,
            width,
            height,
        };
        let depth = splat(&finite, &Pose::IDENTITY, &intrinsics, 0.75 * pixel);
        let mask = Image {
            width,
            height,
            data: depth.data.iter().map(|&z| z > 0.0).collect(),
        };
        let mask_pixels = mask.data.iter().filter(|&&m| m).count();
        let rough = roughness(
            &depth,
            &mask,
            (0, 0, width as usize - 1, height as usize - 1),
        );
        Some(Observation {
            intrinsics,
            depth,
            mask,
            mask_pixels,
            roughness: rough,
        })
    }

    /// Renders `model` at `pose` (model → camera) into the crop and compares it with the
    /// observed depth. Deterministic; equal renders give equal scores.
    ///
    /// Coverage comes from the rendered depth (mesh, or splatted points). Free-space
    /// violations come from the rendered depth for a mesh, and for points from the points
    /// themselves, unsplatted (a splat spills past the silhouette onto the background).
    pub fn score(&self, model: &ModelShape, pose: &Pose) -> Score {
        match model {
            ModelShape::Mesh(mesh) => {
                let scene = Scene::single(mesh.clone(), Pose::IDENTITY, 1);
                let mut camera = Camera::new(self.intrinsics, *pose);
                camera.near = 1e-3;
                match CpuRenderer::new().render(&scene, &camera) {
                    Ok(r) => Score::new(self.compare(&r.depth, 0.0)),
                    Err(_) => Score::default(),
                }
            }
            ModelShape::Points { points, radius } => {
                // Splatted squares stand off a slanted surface by up to their radius.
                let rendered = splat(points, pose, &self.intrinsics, *radius);
                let compared = self.compare(&rendered, *radius);
                Score::new(Compared {
                    violation: self.point_violations(points, pose),
                    ..compared
                })
            }
        }
    }

    /// A rendered depth against the observed one: the fractions [`Score`] reports.
    ///
    /// A rendered pixel agrees when the observed depth of its own pixel or of one of its 8
    /// neighbours lies within the tolerance, and violates free space when it lies in front of
    /// all of them: a pose a fraction of a pixel off (what ICP leaves) must not lose the
    /// steep parts of the surface, where depth changes fast from pixel to pixel.
    fn compare(&self, rendered: &DepthImage, slack: f32) -> Compared {
        let (w, h) = (self.depth.width as usize, self.depth.height as usize);
        let radius = NEIGHBOURHOOD;
        let (mut with_return, mut agree, mut violate, mut covered) = (0usize, 0usize, 0usize, 0);
        let mut hidden = 0usize;
        let mut misfit = 0.0f64;
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                let (r, o) = (rendered.data[i], self.depth.data[i]);
                if r <= 0.0 || o <= 0.0 {
                    continue;
                }
                with_return += 1;
                let tol = depth_tolerance(o, self.roughness) + slack;
                let (mut near, mut behind_all) = ((r - o).abs() <= tol, r < o - tol);
                let mut hidden_all = r > o + tol;
                // The residual of the pixel in units of its tolerance (1 when it disagrees).
                let mut residual = if near { (r - o).abs() / tol } else { 1.0 };
                if !near && radius > 0 {
                    for vv in v.saturating_sub(radius)..=(v + radius).min(h - 1) {
                        for uu in u.saturating_sub(radius)..=(u + radius).min(w - 1) {
                            let on = self.depth.data[vv * w + uu];
                            if on <= 0.0 {
                                continue;
                            }
                            let tol = depth_tolerance(on, self.roughness) + slack;
                            if (r - on).abs() <= tol {
                                near = true;
                                residual = residual.min((r - on).abs() / tol);
                            }
                            behind_all &= r < on - tol;
                            hidden_all &= r > on + tol;
                        }
                    }
                }
                if near {
                    agree += 1;
                    misfit += residual as f64;
                    covered += self.mask.data[i] as usize;
                } else if behind_all {
                    violate += 1;
                } else if hidden_all {
                    hidden += 1;
                }
            }
        }
        if with_return == 0 || self.mask_pixels == 0 {
            return Compared::default();
        }
        let unhidden = with_return - hidden;
        Compared {
            coverage: covered as f64 / self.mask_pixels as f64,
            agreement: agree as f64 / with_return as f64,
            violation: violate as f64 / with_return as f64,
            visible_agreement: if unhidden > 0 {
                agree as f64 / unhidden as f64
            } else {
                0.0
            },
            misfit: if agree > 0 {
                misfit / agree as f64
            } else {
                1.0
            },
        }
    }

    /// Fraction of the points (at `pose`) landing on a pixel with a return that lie in front of
    /// the observed surface by more than the tolerance.
    fn point_violations(&self, points: &[Vec3], pose: &Pose) -> f64 {
        let k = &self.intrinsics;
        let (w, h) = (k.width as i64, k.height as i64);
        let (mut landed, mut front) = (0usize, 0usize);
        for p in points {
            let c = pose.apply_f32(*p);
            if c.z <= 1e-3 {
                continue;
            }
            let u = (k.fx * (c.x / c.z) as f64 + k.cx).round() as i64;
            let v = (k.fy * (c.y / c.z) as f64 + k.cy).round() as i64;
            if u < 0 || v < 0 || u >= w || v >= h {
                continue;
            }
            let o = self.depth.data[(v * w + u) as usize];
            if o <= 0.0 {
                continue;
            }
            landed += 1;
            front += (c.z < o - depth_tolerance(o, self.roughness)) as usize;
        }
        if landed == 0 {
            0.0
        } else {
            front as f64 / landed as f64
        }
    }
}

/// The fractions of one comparison of a rendered depth with the observed one (see [`Score`]).
#[derive(Clone, Copy, Debug, Default)]
struct Compared {
    coverage: f64,
    agreement: f64,
    violation: f64,
    visible_agreement: f64,
    misfit: f64,
}

impl Score {
    /// `coverage × (1 − 3·violation)`, clamped to [0, 1]: a pose must explain the object's
    /// pixels and must not put the model where the sensor saw through.
    fn new(c: Compared) -> Score {
        Score {
            score: (c.coverage * (1.0 - 3.0 * c.violation)).clamp(0.0, 1.0),
            coverage: c.coverage,
            agreement: c.agreement,
            violation: c.violation,
            visible_agreement: c.visible_agreement,
            misfit: c.misfit,
        }
    }
}

/// A pose's whole projection against the depth map: [`WholeView::consistent`] when at least
/// this fraction of its visible rendered pixels agree with the observed depth …
pub const WHOLE_AGREEMENT: f64 = 0.8;
/// … less than this fraction lies in front of the observed surface …
pub const WHOLE_IN_FRONT: f64 = 0.05;
/// … and at least this many rendered pixels are visible.
pub const WHOLE_MIN_VISIBLE: usize = 50;
/// A network-segmented registration is never `ok` when at least this fraction of its model's
/// visible rendered pixels ([`WholeView::in_front`], [`WHOLE_MIN_VISIBLE`] or more of them)
/// lie in front of the observed surface: the sensor would have seen the model there. Far
/// above what noise and the tolerance leave for a right pose (`docs/decisions.md`,
/// "Attention over pooled keys", the false `ok` on a fragment).
pub const OK_MAX_IN_FRONT: f64 = 0.5;

/// How the model's whole projection at a pose agrees with the depth map, at the depth map's
/// own resolution. The verification ([`Observation::score`]) compares the model with the
/// observed depth inside a reduced crop around the instance mask and leaves out pixels without
/// a return; a pose fitted to one instance may still reach past that crop, or over pixels
/// where the sensor returned nothing, where a real surface would have returned a depth. This
/// counts every pixel the model covers.
///
/// A rendered pixel is *hidden* when the observed surface lies in front of it (by more than
/// the tolerance) at its pixel and all 8 neighbours — a nearer object occludes it; the other
/// rendered pixels are *visible*. Of those, it *agrees* when the observed depth of its pixel
/// or a neighbour is within [`depth_tolerance`], is *in front* when it lies in front of all of
/// them (free space the sensor saw through), and is *missing* when its pixel has no return.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct WholeView {
    /// Pixels of the depth map the model covers.
    pub rendered_pixels: usize,
    /// Of those, the ones not hidden.
    pub visible_pixels: usize,
    /// Fraction of the visible pixels that agree.
    pub agreement: f64,
    /// Fraction of the visible pixels in front of the observed surface.
    pub in_front: f64,
    /// Fraction of the visible pixels without an observed return.
    pub missing: f64,
}

impl WholeView {
    /// Whether the pose explains the depth where its model would be seen: at least
    /// [`WHOLE_AGREEMENT`] of [`WHOLE_MIN_VISIBLE`] or more visible pixels agree and less than
    /// [`WHOLE_IN_FRONT`] lie in front.
    /// Whether the model would hide what the sensor saw: [`OK_MAX_IN_FRONT`] or more of at
    /// least [`WHOLE_MIN_VISIBLE`] visible pixels in front of the observed surface.
    pub fn impossible(&self) -> bool {
        self.visible_pixels >= WHOLE_MIN_VISIBLE && self.in_front >= OK_MAX_IN_FRONT
    }

    pub fn consistent(&self) -> bool {
        self.visible_pixels >= WHOLE_MIN_VISIBLE
            && self.agreement >= WHOLE_AGREEMENT
            && self.in_front < WHOLE_IN_FRONT
    }
}

/// [`WholeView`] of `model` at `pose` (model → camera, normalised units) against `depth`
/// (camera-frame z, normalised units, 0 = no return) seen through `k`; `roughness` as
/// [`Observation::roughness`] (the tolerance is never below three times it). The model is
/// rendered only over the box its projection covers. All zeros when no part of it projects
/// into the image in front of the camera.
pub fn whole_view(
    model: &ModelShape,
    pose: &Pose,
    depth: &DepthImage,
    k: &Intrinsics,
    roughness: f32,
) -> WholeView {
    let points: &[Vec3] = match model {
        ModelShape::Mesh(mesh) => &mesh.vertices,
        ModelShape::Points { points, .. } => points,
    };
    let slack = match model {
        ModelShape::Mesh(_) => 0.0,
        ModelShape::Points { radius, .. } => *radius,
    };
    // The projection's box (a splat's radius and a pixel of margin).
    let (mut u0, mut v0, mut u1, mut v1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in points {
        let c = pose.apply_f32(*p);
        if c.z <= 1e-3 {
            // Part of the model at or behind the camera: its projection is unbounded.
            (u0, v0, u1, v1) = (0.0, 0.0, k.width as f64, k.height as f64);
            break;
        }
        let (u, v) = (
            k.fx * (c.x / c.z) as f64 + k.cx,
            k.fy * (c.y / c.z) as f64 + k.cy,
        );
        let r = k.fx.max(k.fy) * (slack / c.z) as f64;
        u0 = u0.min(u - r);
        v0 = v0.min(v - r);
        u1 = u1.max(u + r);
        v1 = v1.max(v + r);
    }
    if !(u0.is_finite() && v0.is_finite() && u1.is_finite() && v1.is_finite()) {
        return WholeView::default();
    }
    let (w, h) = (depth.width as i64, depth.height as i64);
    let ua = ((u0.floor() as i64) - 1).clamp(0, w);
    let va = ((v0.floor() as i64) - 1).clamp(0, h);
    let ub = ((u1.ceil() as i64) + 2).clamp(0, w);
    let vb = ((v1.ceil() as i64) + 2).clamp(0, h);
    if ua >= ub || va >= vb {
        return WholeView::default();
    }
    let crop = Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx - ua as f64,
        cy: k.cy - va as f64,
        width: (ub - ua) as u32,
        height: (vb - va) as u32,
    };
    let rendered = match model {
        ModelShape::Mesh(mesh) => {
            let scene = Scene::single(mesh.clone(), Pose::IDENTITY, 1);
            let mut camera = Camera::new(crop, *pose);
            camera.near = 1e-3;
            match CpuRenderer::new().render(&scene, &camera) {
                Ok(r) => r.depth,
                Err(_) => return WholeView::default(),
            }
        }
        ModelShape::Points { points, radius } => splat(points, pose, &crop, *radius),
    };
    let (cw, ch) = (crop.width as usize, crop.height as usize);
    let (w, h) = (w as usize, h as usize);
    let observed = |x: usize, y: usize| depth.data[y * w + x];
    let (mut covered, mut visible, mut agree, mut front, mut missing) = (0, 0, 0, 0, 0);
    for j in 0..ch {
        for i in 0..cw {
            let r = rendered.data[j * cw + i];
            if r <= 0.0 {
                continue;
            }
            covered += 1;
            let (u, v) = (ua as usize + i, va as usize + j);
            let o = observed(u, v);
            if o <= 0.0 {
                visible += 1;
                missing += 1;
                continue;
            }
            let (mut near, mut front_all, mut hidden_all) = (false, true, true);
            for vv in v.saturating_sub(NEIGHBOURHOOD)..=(v + NEIGHBOURHOOD).min(h - 1) {
                for uu in u.saturating_sub(NEIGHBOURHOOD)..=(u + NEIGHBOURHOOD).min(w - 1) {
                    let on = observed(uu, vv);
                    if on <= 0.0 {
                        continue;
                    }
                    let tol = depth_tolerance(on, roughness) + slack;
                    near |= (r - on).abs() <= tol;
                    front_all &= r < on - tol;
                    hidden_all &= r > on + tol;
                }
            }
            if near {
                visible += 1;
                agree += 1;
            } else if front_all {
                visible += 1;
                front += 1;
            } else if !hidden_all {
                // Neither near, nor in front of every neighbour, nor behind every one: a
                // depth step runs through the neighbourhood; it counts as visible and not
                // agreeing.
                visible += 1;
            }
        }
    }
    WholeView {
        rendered_pixels: covered,
        visible_pixels: visible,
        agreement: share(agree, visible),
        in_front: share(front, visible),
        missing: share(missing, visible),
    }
}

/// `n / of`, 0 when `of` is 0.
pub(crate) fn share(n: usize, of: usize) -> f64 {
    if of > 0 { n as f64 / of as f64 } else { 0.0 }
}

/// Points (model frame) moved by `pose` and z-buffered into an image of `k`, each filling the
/// square of half-side `radius` (normalised units) around it, seen face-on.
fn splat(points: &[Vec3], pose: &Pose, k: &Intrinsics, radius: f32) -> DepthImage {
    let (w, h) = (k.width as i64, k.height as i64);
    let mut depth = Image::filled(k.width, k.height, 0.0f32);
    for p in points {
        let c = pose.apply_f32(*p);
        if c.z <= 1e-3 {
            continue;
        }
        let (u, v) = (
            k.fx * (c.x / c.z) as f64 + k.cx,
            k.fy * (c.y / c.z) as f64 + k.cy,
        );
        let (ru, rv) = (k.fx * (radius / c.z) as f64, k.fy * (radius / c.z) as f64);
        let (ua, ub) = ((u - ru).round().max(0.0) as i64, (u + ru).round() as i64);
        let (va, vb) = ((v - rv).round().max(0.0) as i64, (v + rv).round() as i64);
        for vv in va..=vb.min(h - 1) {
            for uu in ua..=ub.min(w - 1) {
                let z = &mut depth.data[(vv * w + uu) as usize];
                if *z == 0.0 || c.z < *z {
                    *z = c.z;
                }
            }
        }
    }
    depth
}

#[cfg(test)]
mod tests {
    use super::*;
    use ic_geometry::glam::DVec3;

    /// A procedural object (normalised) seen from 3 units by a 160×120 camera: its depth map,
    /// mask, intrinsics, mesh and true pose.
    fn scene(seed: u64) -> (DepthImage, Mask, Intrinsics, Arc<Mesh>, Pose) {
        let mut mesh = ic_geometry::shapes::random_object(seed);
        mesh.normalise().unwrap();
        let mesh = Arc::new(mesh);
        let k = Intrinsics::new(131.25, 131.25, 79.5, 59.5, 160, 120).unwrap();
        let truth = ic_geometry::look_at(DVec3::new(1.8, 1.2, 1.8), DVec3::ZERO, DVec3::Z).unwrap();
        let view = CpuRenderer::new()
            .render(
                &Scene::single(mesh.clone(), Pose::IDENTITY, 1),
                &Camera::new(k, truth),
            )
            .unwrap();
        (view.depth.clone(), view.mask(1), k, mesh, truth)
    }

    #[test]
    fn the_true_pose_scores_near_one_and_a_flip_far_below() {
        for seed in [1, 2, 3] {
            let (depth, mask, k, mesh, truth) = scene(seed);
            let obs = Observation::from_depth(&depth, &k, &mask).unwrap();
            let shape = ModelShape::Mesh(mesh.clone());
            let right = obs.score(&shape, &truth);
            assert!(right.score > 0.9, "seed {seed}: {right:?}");
            // The true pose turned 180° about the camera's viewing axis through the object.
            let centre = truth.apply(DVec3::ZERO);
            let flip = Pose::from_translation(centre)
                .compose(&Pose::from_axis_angle(
                    DVec3::Z,
                    std::f64::consts::PI,
                    DVec3::ZERO,
                ))
                .compose(&Pose::from_translation(-centre))
                .compose(&truth);
            let wrong = obs.score(&shape, &flip);
            assert!(
                wrong.score < right.score - 0.2,
                "seed {seed}: {wrong:?} vs {right:?}"
            );
            // Points splatted score the true pose well too.
            let pts = ic_geometry::sampling::sample_surface_uniform(&mesh, 4096, seed)
                .unwrap()
                .points;
            let splat = ModelShape::points(pts, 0.01);
            let right_pts = obs.score(&splat, &truth);
            assert!(right_pts.score > 0.8, "seed {seed}: {right_pts:?}");
            assert!(obs.score(&splat, &flip).score < right_pts.score - 0.2);
        }
    }

    #[test]
    fn poses_equivalent_under_a_cylinders_symmetry_score_alike() {
        let mut mesh = ic_geometry::shapes::cylinder(0.6, 1.0, 64).unwrap();
        mesh.normalise().unwrap();
        let mesh = Arc::new(mesh);
        let k = Intrinsics::new(131.25, 131.25, 79.5, 59.5, 160, 120).unwrap();
        let truth = ic_geometry::look_at(DVec3::new(2.2, 1.0, 1.5), DVec3::ZERO, DVec3::Z).unwrap();
        let view = CpuRenderer::new()
            .render(
                &Scene::single(mesh.clone(), Pose::IDENTITY, 1),
                &Camera::new(k, truth),
            )
            .unwrap();
        let obs = Observation::from_depth(&view.depth, &k, &view.mask(1)).unwrap();
        let shape = ModelShape::Mesh(mesh);
        let base = obs.score(&shape, &truth);
        assert!(base.score > 0.9, "{base:?}");
        // Turned about the cylinder's own axis (z of the model frame): the same surface.
        for deg in [17.0f64, 90.0, 180.0, 271.0] {
            let turned = truth.compose(&Pose::from_axis_angle(
                DVec3::Z,
                deg.to_radians(),
                DVec3::ZERO,
            ));
            let s = obs.score(&shape, &turned);
            assert!(
                (s.score - base.score).abs() < 0.03,
                "{deg}°: {s:?} vs {base:?}"
            );
        }
        // Tipped over by 90°: not equivalent, scores far lower.
        let tipped = truth.compose(&Pose::from_axis_angle(
            DVec3::X,
            90f64.to_radians(),
            DVec3::ZERO,
        ));
        assert!(obs.score(&shape, &tipped).score < base.score - 0.2);
    }

    #[test]
    fn the_whole_view_counts_free_space_and_missing_returns_that_the_crop_score_leaves_out() {
        let (mut depth, mask, k, mesh, truth) = scene(5);
        // A wall behind the object fills the background: free space in front of it.
        let far = depth.data.iter().copied().fold(0.0f32, f32::max) + 2.0;
        for z in depth.data.iter_mut().filter(|z| **z <= 0.0) {
            *z = far;
        }
        let shape = ModelShape::Mesh(mesh.clone());
        let right = whole_view(&shape, &truth, &depth, &k, 0.0);
        assert!(right.consistent(), "{right:?}");
        assert!(right.agreement > 0.95 && right.in_front < 0.01, "{right:?}");
        assert_eq!(right.missing, 0.0);
        assert!(right.visible_pixels * 10 >= mask.data.iter().filter(|&&m| m).count() * 9);
        // Splatted points see the same.
        let pts = ic_geometry::sampling::sample_surface_uniform(&mesh, 4096, 5)
            .unwrap()
            .points;
        let points = whole_view(&ModelShape::points(pts, 0.01), &truth, &depth, &k, 0.0);
        assert!(points.consistent(), "{points:?}");
        // Moved 0.6 units towards the camera: in front of what the sensor saw.
        let near = Pose::from_translation(DVec3::new(0.0, 0.0, -0.6)).compose(&truth);
        let front = whole_view(&shape, &near, &depth, &k, 0.0);
        assert!(front.in_front > 0.5 && !front.consistent(), "{front:?}");
        // The model would hide what the sensor saw: never `ok`; the right pose is possible.
        assert!(front.impossible() && !right.impossible(), "{front:?}");
        // No return on the right half of the object: the crop score, which leaves such
        // pixels out, still trusts the pose; the whole view does not.
        let w = depth.width as usize;
        let mut holed = depth.clone();
        let mut kept = mask.clone();
        for i in 0..holed.data.len() {
            if mask.data[i] && i % w >= w / 2 {
                holed.data[i] = 0.0;
                kept.data[i] = false;
            }
        }
        let crop = Observation::from_depth(&holed, &k, &kept)
            .unwrap()
            .score(&shape, &truth);
        assert!(crop.agreement > 0.9, "{crop:?}");
        let missing = whole_view(&shape, &truth, &holed, &k, 0.0);
        assert!(
            missing.missing > 0.25 && missing.agreement < 0.75 && !missing.consistent(),
            "{missing:?}"
        );
        // Behind a surface nearer than the object everywhere: hidden, nothing visible.
        let wall = Image::filled(depth.width, depth.height, 1.0f32);
        let hidden = whole_view(&shape, &truth, &wall, &k, 0.0);
        assert!(
            hidden.rendered_pixels > 0 && hidden.visible_pixels == 0,
            "{hidden:?}"
        );
        assert!(!hidden.consistent() && !hidden.impossible());
        // Entirely outside the image, or behind the camera: nothing rendered.
        let away = Pose::from_translation(DVec3::new(50.0, 0.0, 0.0)).compose(&truth);
        assert_eq!(
            whole_view(&shape, &away, &depth, &k, 0.0),
            WholeView::default()
        );
        let behind = Pose::from_translation(DVec3::new(0.0, 0.0, -20.0)).compose(&truth);
        assert_eq!(
            whole_view(&shape, &behind, &depth, &k, 0.0).visible_pixels,
            0
        );
    }

    #[test]
    fn pixels_hidden_by_a_nearer_surface_do_not_count_against_visible_agreement() {
        let (mut depth, mask, k, mesh, truth) = scene(4);
        // A nearer surface (0.5 units in front of the object) hides the left half of the view.
        let w = depth.width as usize;
        let z_near = depth
            .data
            .iter()
            .copied()
            .filter(|&z| z > 0.0)
            .fold(f32::MAX, f32::min)
            - 0.5;
        let mut kept = mask.clone();
        for (i, z) in depth.data.iter_mut().enumerate() {
            if i % w < w / 2 {
                *z = z_near;
                kept.data[i] = false;
            }
        }
        let obs = Observation::from_depth(&depth, &k, &kept).unwrap();
        let s = obs.score(&ModelShape::Mesh(mesh), &truth);
        assert!(
            s.agreement < 0.8,
            "hidden pixels lower the plain agreement: {s:?}"
        );
        assert!(s.visible_agreement > 0.95, "{s:?}");
        assert!(s.violation < 0.01, "{s:?}");
    }

    #[test]
    fn misfit_grows_with_a_depth_offset_the_score_does_not_see() {
        let (depth, mask, k, mesh, truth) = scene(5);
        let obs = Observation::from_depth(&depth, &k, &mask).unwrap();
        let shape = ModelShape::Mesh(mesh);
        let right = obs.score(&shape, &truth);
        assert!(
            right.misfit < 0.15,
            "noise-free depth, true pose: {right:?}"
        );
        // Pushed back along the viewing ray by 0.02 units, under half of the tolerance
        // (≈ 0.045 units at 3 units away): the same pixels agree, each less closely.
        let ray = truth.apply(DVec3::ZERO).normalize();
        let pushed = Pose::from_translation(0.02 * ray).compose(&truth);
        let off = obs.score(&shape, &pushed);
        assert!(
            (off.score - right.score).abs() < 0.03,
            "{off:?} vs {right:?}"
        );
        assert!(off.misfit > right.misfit + 0.15, "{off:?} vs {right:?}");
        assert!((0.0..=1.0).contains(&off.misfit));
    }
}
