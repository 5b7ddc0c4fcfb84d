//! Surface sampling: area-weighted uniform sampling and visible-surface sampling.
//!
//! Both samplers work in the mesh's own frame and units (the model frame; normalised object
//! units for normalised meshes) and return a [`PointCloud`] whose `normals` hold the unit face
//! normal (right-hand rule on the triangle order, so outward for outward-oriented meshes) of the
//! triangle each point lies on. Both are deterministic for a given seed ([`ChaCha8Rng`]).
//!
//! [`sample_surface_uniform`] samples the whole triangle soup, including faces hidden inside the
//! object (interpenetrating parts of composites, internal walls). [`sample_visible_surface`]
//! keeps only points that can be seen from outside, which is what a depth sensor can observe
//! and what model point sets for correspondence should contain.
//!
//! ```
//! use ic_geometry::sampling::{sample_surface_uniform, sample_visible_surface, VisibleSurfaceOptions};
//! use ic_geometry::shapes::{composite, CompositeKind};
//!
//! let mug = composite(CompositeKind::Mug, 3);
//! let all = sample_surface_uniform(&mug, 500, 1).unwrap();
//! let outside = sample_visible_surface(&mug, 500, 1, VisibleSurfaceOptions::default()).unwrap();
//! assert_eq!((all.len(), outside.len()), (500, 500));
//! ```

use glam::{DVec3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::{GeometryError, Mesh, PointCloud};

/// Checks the mesh and returns its cumulative triangle areas (f64, last = total area).
fn cumulative_areas(mesh: &Mesh) -> Result<Vec<f64>, GeometryError> {
    mesh.validate()
        .map_err(|e| GeometryError::InvalidParameter {
            name: "mesh",
            message: e.to_string(),
        })?;
    let mut total = 0.0;
    let cumulative: Vec<f64> = mesh
        .triangle_areas()
        .into_iter()
        .map(|a| {
            total += a;
            total
        })
        .collect();
    if !(total > 0.0 && total.is_finite()) {
        return Err(GeometryError::InvalidParameter {
            name: "mesh",
            message: format!("surface area must be finite and > 0, got {total}"),
        });
    }
    Ok(cumulative)
}

/// Draws `count` area-uniform points with `rng`; returns the points and their face normals.
fn draw_uniform(
    mesh: &Mesh,
    cumulative: &[f64],
    normals: &[Vec3],
    count: usize,
    rng: &mut ChaCha8Rng,
) -> (Vec<Vec3>, Vec<Vec3>) {
    let total = *cumulative.last().unwrap_or(&0.0);
    let last = cumulative.len() - 1;
    let mut points = Vec::with_capacity(count);
    let mut point_normals = Vec::with_capacity(count);
    for _ in 0..count {
        // First triangle whose cumulative area exceeds r: zero-area faces are never chosen.
        let r = rng.random::<f64>() * total;
        let face = cumulative.partition_point(|&c| c <= r).min(last);
        let [a, b, c] = mesh.triangle(face);
        // Uniform on the triangle: p = (1 − √u)·a + √u·(1 − v)·b + √u·v·c.
        let s = rng.random::<f64>().sqrt();
        let v = rng.random::<f64>();
        points.push(((1.0 - s) * a + s * (1.0 - v) * b + s * v * c).as_vec3());
        point_normals.push(normals[face]);
    }
    (points, point_normals)
}

/// `count` points distributed uniformly over the surface area of `mesh` (model frame and
/// units): a triangle is chosen with probability proportional to its area (binary search in the
/// cumulative areas), then a uniform point in it (square-root barycentric trick). `normals`
/// holds each point's unit face normal. The same `(mesh, count, seed)` gives the same cloud;
/// `count = 0` gives an empty cloud.
///
/// Errors: [`GeometryError::InvalidParameter`] (`name = "mesh"`) when the mesh is invalid
/// (no faces, out-of-range indices, non-finite vertices) or has zero total area.
pub fn sample_surface_uniform(
    mesh: &Mesh,
    count: usize,
    seed: u64,
) -> Result<PointCloud, GeometryError> {
    let cumulative = cumulative_areas(mesh)?;
    let normals = mesh.face_normals();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (points, normals) = draw_uniform(mesh, &cumulative, &normals, count, &mut rng);
    Ok(PointCloud {
        points,
        normals: Some(normals),
        colors: None,
    })
}

/// Settings of [`sample_visible_surface`]. Lengths are relative to the diagonal of the mesh's
/// bounding box, so the same options suit any scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VisibleSurfaceOptions {
    /// Number of orthographic view directions, spread evenly over the whole sphere (Fibonacci
    /// sphere). Default 42.
    pub views: usize,
    /// Side of the square z-buffer of each view, in pixels; the image covers the bounding
    /// sphere of the mesh (radius = half the bbox diagonal), so one pixel is
    /// `diagonal / resolution`. Default 256.
    pub resolution: usize,
    /// Fine depth tolerance, as a fraction of the bbox diagonal: a candidate is visible in a
    /// view when its depth is at most this far behind the plane of the front-most triangle at
    /// each of the four pixels around it, that plane being evaluated at the candidate's exact
    /// image position. Default 1e-3. Points hidden less deep than this count as visible.
    pub depth_tolerance: f64,
    /// Coarse depth tolerance in pixels (`pixel = diagonal / resolution`): the candidate's
    /// depth must also be at most this far behind the z-buffer value at the pixel centre
    /// (guards against extrapolating steep front triangles). Default 2.0.
    pub pixel_tolerance: f64,
    /// Candidates drawn per requested point, uniformly over the whole surface. Default 8.
    pub oversample: usize,
    /// When fewer than `count` candidates are visible, up to this many further batches of
    /// `oversample × count` candidates are drawn. Default 4.
    pub max_retries: usize,
}

impl Default for VisibleSurfaceOptions {
    fn default() -> Self {
        VisibleSurfaceOptions {
            views: 42,
            resolution: 256,
            depth_tolerance: 1e-3,
            pixel_tolerance: 2.0,
            oversample: 8,
            max_retries: 4,
        }
    }
}

impl VisibleSurfaceOptions {
    fn validate(&self) -> Result<(), GeometryError> {
        let bad = |name: &'static str, message: String| {
            Err(GeometryError::InvalidParameter { name, message })
        };
        if self.views == 0 {
            return bad("views", "must be ≥ 1".into());
        }
        if !(2..=8192).contains(&self.resolution) {
            return bad(
                "resolution",
                format!("must be in 2..=8192, got {}", self.resolution),
            );
        }
        if !(self.depth_tolerance.is_finite() && self.depth_tolerance >= 0.0) {
            return bad(
                "depth_tolerance",
                format!("must be finite and ≥ 0, got {}", self.depth_tolerance),
            );
        }
        if !(self.pixel_tolerance.is_finite() && self.pixel_tolerance >= 0.0) {
            return bad(
                "pixel_tolerance",
                format!("must be finite and ≥ 0, got {}", self.pixel_tolerance),
            );
        }
        if self.oversample == 0 {
            return bad("oversample", "must be ≥ 1".into());
        }
        Ok(())
    }
}

/// `n` unit directions spread evenly over the sphere (Fibonacci / golden-angle spiral).
pub fn fibonacci_sphere(n: usize) -> Vec<DVec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * i as f64;
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// An orthographic view along `dir`: image axes `u`, `v` ⟂ `dir`, depth along `dir` (smaller
/// is nearer the viewer, who sits at −∞·dir). Image coordinates are in pixels with pixel
/// `(i, j)`'s centre at `(i, j)`.
struct View {
    u: DVec3,
    v: DVec3,
    d: DVec3,
    centre: DVec3,
    half: f64,
    pixel: f64,
    res: usize,
}

impl View {
    fn new(d: DVec3, centre: DVec3, half: f64, res: usize) -> View {
        let helper = if d.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
        let u = d.cross(helper).normalize();
        let v = d.cross(u);
        View {
            u,
            v,
            d,
            centre,
            half,
            pixel: 2.0 * half / res as f64,
            res,
        }
    }

    /// Image position (pixels) and depth of a point.
    fn project(&self, p: DVec3) -> DVec3 {
        let q = p - self.centre;
        DVec3::new(
            (q.dot(self.u) + self.half) / self.pixel - 0.5,
            (q.dot(self.v) + self.half) / self.pixel - 0.5,
            q.dot(self.d),
        )
    }
}

/// Depth of the plane through the projected triangle `t` at image position `(x, y)`
/// (extrapolated outside it); `None` for a triangle seen edge-on.
fn plane_depth(t: &[DVec3; 3], x: f64, y: f64) -> Option<f64> {
    let [a, b, c] = *t;
    let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    if area.abs() < 1e-12 {
        return None;
    }
    let wb = ((x - a.x) * (c.y - a.y) - (y - a.y) * (c.x - a.x)) / area;
    let wc = ((b.x - a.x) * (y - a.y) - (b.y - a.y) * (x - a.x)) / area;
    Some(a.z + wb * (b.z - a.z) + wc * (c.z - a.z))
}

/// Work done by [`rasterise`] for one view, in operations (not time).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct RasterWork {
    /// Scan lines (pixel rows or columns) set up for triangles rasterised line by line.
    lines: u64,
    /// Pixel centres tested against a triangle (coverage test and depth interpolation).
    pixels: u64,
}

/// Triangles whose clamped bounding box holds at most this many pixel centres are tested at
/// every one of them: cheaper than setting up scan lines, and the result is the same.
const SMALL_BOX_PIXELS: usize = 16;

/// A z-buffer of one orthographic view: `depth[py·res + px]` is the depth (model units along
/// the view direction, see [`View`]) of the front-most triangle whose projection covers the
/// centre of pixel `(px, py)`, and `front[..]` that triangle's index; `INFINITY` and `u32::MAX`
/// where no triangle covers it.
struct ZBuffer {
    depth: Vec<f64>,
    front: Vec<u32>,
    res: usize,
}

impl ZBuffer {
    /// Draws triangle `f` (`t`: vertices in image pixels and depth; `area`: its signed area in
    /// px², nonzero) at pixel `(px, py)` if it covers the pixel's centre and is in front.
    #[inline(always)]
    fn cover(&mut self, t: &[DVec3; 3], area: f64, f: u32, px: usize, py: usize) {
        let [a, b, c] = *t;
        let (x, y) = (px as f64, py as f64);
        // Barycentric weights; all share the sign of `area` inside the triangle.
        let wa = ((b.x - x) * (c.y - y) - (b.y - y) * (c.x - x)) / area;
        let wb = ((c.x - x) * (a.y - y) - (c.y - y) * (a.x - x)) / area;
        let wc = 1.0 - wa - wb;
        if wa < 0.0 || wb < 0.0 || wc < 0.0 {
            return;
        }
        let z = wa * a.z + wb * b.z + wc * c.z;
        let k = py * self.res + px;
        if z < self.depth[k] {
            self.depth[k] = z;
            self.front[k] = f;
        }
    }
}

/// Renders `triangles` (indices into `projected`: vertices in image pixels and depth, as
/// [`View::project`] returns them) into a `res × res` z-buffer. Both faces of every triangle are
/// drawn; triangles with a projected area below 1e-12 px² (seen edge-on) are skipped.
///
/// Coverage rule: pixel `(px, py)` is covered when all three barycentric weights of the point
/// `(px, py)` (its centre) are ≥ 0, so a centre on an edge is covered by both triangles sharing
/// it; at equal depth the earlier triangle stays in front.
///
/// Cost: a triangle whose clamped bounding box holds more than [`SMALL_BOX_PIXELS`] pixel
/// centres is scanned line by line across the shorter side of that box, testing only the
/// pixels of each line that may lie inside it ([`scan_lines`]). The work is the number of
/// covered pixels plus one short step per line, so a sliver costs its length in pixels, not
/// its bounding-box area (testing whole boxes, a 10⁵-vertex polygon fan-triangulated into
/// slivers took 20 s for the 42 default views, 75× a well-shaped sphere of 3·10⁵ triangles;
/// now 0.4 s). The spans are conservative and every pixel in them goes through the same test
/// as a pixel of the whole box would, so the z-buffer is bit-identical to testing every pixel
/// of every bounding box.
fn rasterise(projected: &[DVec3], triangles: &[[u32; 3]], res: usize) -> (ZBuffer, RasterWork) {
    let mut z = ZBuffer {
        depth: vec![f64::INFINITY; res * res],
        front: vec![u32::MAX; res * res],
        res,
    };
    let mut work = RasterWork::default();
    let last = (res - 1) as f64;
    for (f, &[i, j, k]) in triangles.iter().enumerate() {
        let t = [
            projected[i as usize],
            projected[j as usize],
            projected[k as usize],
        ];
        let [a, b, c] = t;
        let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = a.x.min(b.x).min(c.x).ceil().max(0.0);
        let x1 = a.x.max(b.x).max(c.x).floor().min(last);
        let y0 = a.y.min(b.y).min(c.y).ceil().max(0.0);
        let y1 = a.y.max(b.y).max(c.y).floor().min(last);
        if x0 > x1 || y0 > y1 {
            continue;
        }
        let (px0, px1, py0, py1) = (x0 as usize, x1 as usize, y0 as usize, y1 as usize);
        let pixels = (px1 - px0 + 1) * (py1 - py0 + 1);
        if pixels <= SMALL_BOX_PIXELS {
            work.pixels += pixels as u64;
            for py in py0..=py1 {
                for px in px0..=px1 {
                    z.cover(&t, area, f as u32, px, py);
                }
            }
        } else {
            let w = scan_triangle(&mut z, t, area, f as u32, (x0, x1), (y0, y1));
            work.lines += w.lines;
            work.pixels += w.pixels;
        }
    }
    (z, work)
}

/// Draws triangle `f` (as [`ZBuffer::cover`]) at the pixels of its clamped bounding box
/// `x0..=x1 × y0..=y1` (integer pixels) that may lie inside it, line by line across the
/// shorter side of the box ([`scan_lines`]). Returns the work done.
// Not inlined: in the per-triangle loop of `rasterise` it slowed the common case (triangles of
// a pixel or less) by ~10%.
#[inline(never)]
fn scan_triangle(
    z: &mut ZBuffer,
    t: [DVec3; 3],
    area: f64,
    f: u32,
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
) -> RasterWork {
    let [a, b, c] = t;
    let extent = (a.x.max(b.x).max(c.x) - a.x.min(b.x).min(c.x))
        .max(a.y.max(b.y).max(c.y) - a.y.min(b.y).min(c.y));
    if y1 - y0 <= x1 - x0 {
        // Lines are pixel rows: s = y, r = x.
        let tri = t.map(|p| (p.y, p.x));
        let pixels = scan_lines(tri, area, extent, (y0, y1), (x0, x1), |r, s| {
            z.cover(&t, area, f, r, s)
        });
        RasterWork {
            lines: (y1 - y0) as u64 + 1,
            pixels,
        }
    } else {
        // Lines are pixel columns: s = x, r = y; swapping the axes mirrors the triangle.
        let tri = t.map(|p| (p.x, p.y));
        let pixels = scan_lines(tri, -area, extent, (x0, x1), (y0, y1), |r, s| {
            z.cover(&t, area, f, s, r)
        });
        RasterWork {
            lines: (x1 - x0) as u64 + 1,
            pixels,
        }
    }
}

/// The span of a run of scan lines `s = s0 + k` allowed by two edges of a triangle: pixel
/// offsets `r − r0` in `[lower.0 + k·lower.1, upper.0 + k·upper.1]` (see [`scan_lines`]).
/// A missing bound is `(−∞, 0)` or `(+∞, 0)`.
#[derive(Clone, Copy)]
struct Wedge {
    lower: (f64, f64),
    upper: (f64, f64),
}

/// Calls `visit(r, s)` for pixel centres `(r, s)` in scan coordinates (`r` along a line, `s`
/// across lines; integer pixels) with `s` in `s0..=s1` and `r` in `r0..=r1`: a superset of the
/// centres inside the triangle `tri` (vertices as `(s, r)` in pixels; `area` is its signed
/// area in `(r, s)` axes, i.e. in the orientation [`rasterise`] tests with). Returns the number
/// of pixels visited. `extent` is the larger side (px) of the triangle's bounding box.
///
/// Each edge p→q (in the triangle's cyclic order) is the half-plane
/// `σ·((q − p) × (P − p)) ≥ −margin` (σ = sign of `area`), which on line `s` bounds `r` from
/// one side. Lines up to the middle vertex (in `s`) are bounded by the two edges from the first
/// vertex, later lines by the two edges to the last one: in cyclic order, one of these goes
/// towards larger `s` and the other towards smaller, so one is a lower and the other an upper
/// bound. The third edge is dropped, which can only widen a span (any two edges enclose the
/// triangle), and so is an edge parallel to the lines or with an overflowing bound.
///
/// Why no pixel accepted by the barycentric test of [`rasterise`] is missed: with `u = 2⁻⁵³`
/// and `W = extent`, that test's rounding errors amount to less than `40·u·W²` in units of the
/// cross product above (px²), and the bound arithmetic here (offsets from `(r0, s0)`, all
/// `≤ W`) to less than `60·u·(1 + W²)`; the `margin` of `1e-9·(1 + W²)` exceeds both by a
/// factor of 10⁵.
fn scan_lines(
    tri: [(f64, f64); 3],
    area: f64,
    extent: f64,
    (s0, s1): (f64, f64),
    (r0, r1): (f64, f64),
    mut visit: impl FnMut(usize, usize),
) -> u64 {
    let sigma = area.signum();
    let margin = 1e-9 * (1.0 + extent * extent);
    // Edge p→q, in the triangle's cyclic order, as a bound `(c0, c1)` on `r − r0` and whether
    // it is a lower one; `None` when it bounds nothing (parallel to the lines, or overflowing).
    let bound = |p: (f64, f64), q: (f64, f64)| {
        // σ·((q − p) × (P − p)) = alpha·(r − p.r) + beta·(s − p.s) with P = (r, s).
        let alpha = -sigma * (q.0 - p.0);
        let beta = sigma * (q.1 - p.1);
        let inv = 1.0 / alpha;
        let c0 = (p.1 - r0) + (-margin + beta * (p.0 - s0)) * inv;
        let c1 = -beta * inv;
        (c0.is_finite() && c1.is_finite()).then_some(((c0, c1), alpha > 0.0))
    };
    let edge = |i: usize, j: usize| {
        if (j + 3 - i) % 3 == 1 {
            bound(tri[i], tri[j])
        } else {
            bound(tri[j], tri[i])
        }
    };
    let wedge = |edges: [Option<((f64, f64), bool)>; 2]| {
        let mut w = Wedge {
            lower: (f64::NEG_INFINITY, 0.0),
            upper: (f64::INFINITY, 0.0),
        };
        let (mut has_lower, mut has_upper) = (false, false);
        // Two bounds on the same side cannot happen (see above); were they to, keeping one
        // would still be conservative.
        for (b, is_lower) in edges.into_iter().flatten() {
            if is_lower && !has_lower {
                (w.lower, has_lower) = (b, true);
            } else if !is_lower && !has_upper {
                (w.upper, has_upper) = (b, true);
            }
        }
        w
    };
    let mut order = [0, 1, 2];
    for (i, j) in [(0, 1), (1, 2), (0, 1)] {
        if tri[order[j]].0 < tri[order[i]].0 {
            order.swap(i, j);
        }
    }
    let [first, middle, last] = order;
    let before = wedge([edge(first, middle), edge(first, last)]);
    let after = wedge([edge(middle, last), edge(first, last)]);
    // Lines k < split are at or before the middle vertex.
    let split = (tri[middle].0.floor() - s0 + 1.0).clamp(0.0, s1 - s0 + 1.0) as i64;
    let width = r1 - r0;
    let (r0, s0) = (r0 as usize, s0 as usize);
    let mut visited = 0;
    for k in 0..=(s1 as usize - s0) as i64 {
        let w = if k < split { &before } else { &after };
        let kf = k as f64;
        // No NaN: c0 and c1 are finite, or (±∞, 0).
        let lo = (w.lower.0 + kf * w.lower.1).max(0.0);
        let hi = (w.upper.0 + kf * w.upper.1).min(width);
        if !(lo <= hi) {
            continue;
        }
        // 0 ≤ lo ≤ hi ≤ width: truncation is floor.
        let end = hi as i64;
        if (end as f64) < lo {
            continue;
        }
        let start = lo as i64 + i64::from((lo as i64 as f64) < lo);
        visited += (end - start + 1) as u64;
        let s = s0 + k as usize;
        for r in start as usize..=end as usize {
            visit(r0 + r, s);
        }
    }
    visited
}

/// Renders the mesh into a z-buffer ([`rasterise`]; `projected` holds the mesh's vertices in
/// this view's image pixels and depth) and returns which `candidates` (model frame and units)
/// are visible in this view.
fn visible_in_view(
    view: &View,
    projected: &[DVec3],
    mesh: &Mesh,
    candidates: &[DVec3],
    depth_tol: f64,
    pixel_tol: f64,
) -> Vec<bool> {
    let res = view.res;
    let (ZBuffer { depth, front, .. }, _) = rasterise(projected, &mesh.triangles, res);
    let tri = |f: usize| {
        let [i, j, k] = mesh.triangles[f];
        [
            projected[i as usize],
            projected[j as usize],
            projected[k as usize],
        ]
    };
    candidates
        .iter()
        .map(|&p| {
            let q = view.project(p);
            // The four pixel centres around the candidate's image position. Every covered one
            // must not hide it: the candidate lies at most `pixel_tol` behind the depth there,
            // and at most `depth_tol` behind the plane of that pixel's front triangle extended
            // to the candidate's exact position. Uncovered pixels (background) hide nothing.
            let (x0, y0) = (q.x.floor(), q.y.floor());
            if x0 < -1.0 || y0 < -1.0 || x0 > res as f64 || y0 > res as f64 {
                return false;
            }
            for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                let (px, py) = (x0 + dx, y0 + dy);
                if px < 0.0 || py < 0.0 || px >= res as f64 || py >= res as f64 {
                    continue;
                }
                let k = py as usize * res + px as usize;
                if front[k] == u32::MAX {
                    continue;
                }
                if q.z > depth[k] + pixel_tol {
                    return false;
                }
                if let Some(z) = plane_depth(&tri(front[k] as usize), q.x, q.y) {
                    if q.z > z + depth_tol {
                        return false;
                    }
                }
            }
            true
        })
        .collect()
}

/// Marks which `candidates` (points on the surface) are visible from at least one view.
fn visibility(mesh: &Mesh, candidates: &[DVec3], options: &VisibleSurfaceOptions) -> Vec<bool> {
    let Some(bounds) = mesh.bounds() else {
        return vec![false; candidates.len()];
    };
    let diagonal = bounds.diagonal().max(f64::MIN_POSITIVE);
    // A small margin keeps silhouettes off the image border.
    let half = 0.5 * diagonal * 1.02;
    let pixel = 2.0 * half / options.resolution as f64;
    let depth_tol = options.depth_tolerance * diagonal;
    let pixel_tol = options.pixel_tolerance * pixel;
    let vertices: Vec<DVec3> = mesh.vertices.iter().map(|v| v.as_dvec3()).collect();
    fibonacci_sphere(options.views)
        .into_par_iter()
        .map(|d| {
            let view = View::new(d, bounds.centre(), half, options.resolution);
            let projected: Vec<DVec3> = vertices.iter().map(|&p| view.project(p)).collect();
            visible_in_view(&view, &projected, mesh, candidates, depth_tol, pixel_tol)
        })
        .reduce(
            || vec![false; candidates.len()],
            |mut a, b| {
                a.iter_mut().zip(b).for_each(|(x, y)| *x |= y);
                a
            },
        )
}

/// `count` points on the part of the surface of `mesh` that is visible from outside (model
/// frame and units), with their unit face normals in `normals`.
///
/// Method: draw `options.oversample × count` candidates uniformly over the whole surface
/// (as [`sample_surface_uniform`]), render an orthographic z-buffer of the mesh from
/// `options.views` directions evenly spread over the sphere (Fibonacci sphere; images of
/// `options.resolution²` pixels covering the bounding sphere; rendered in parallel with rayon),
/// and call a candidate visible when, in at least one view, none of the four pixel centres
/// around its image position shows a surface in front of it: at each covered one, the
/// candidate lies no further than the depth tolerances behind the front-most triangle's plane
/// (evaluated at the candidate's exact image position) and the z-buffer value (see
/// [`VisibleSurfaceOptions`]); background pixels hide nothing. Faces
/// inside the object — interpenetrating parts of composites, internal walls — are therefore not
/// sampled; nor are deep crevices that no orthographic ray from outside reaches. Then `count`
/// of the visible candidates are chosen uniformly at random without replacement (partial
/// Fisher–Yates with the same seeded generator), which keeps the result area-uniform over the
/// visible surface.
///
/// If fewer than `count` candidates are visible, further batches of `oversample × count`
/// candidates are drawn (at most `options.max_retries` batches); if still too few are visible,
/// all visible candidates are returned, so the cloud may then hold fewer than `count` points
/// (possibly none, e.g. for a mesh too thin to cover any pixel centre).
///
/// Deterministic for a given `(mesh, count, seed, options)`, independent of the thread count.
///
/// Errors: those of [`sample_surface_uniform`], and [`GeometryError::InvalidParameter`] for
/// bad options (0 views, resolution outside 2..=8192, negative or non-finite tolerances,
/// oversample 0).
pub fn sample_visible_surface(
    mesh: &Mesh,
    count: usize,
    seed: u64,
    options: VisibleSurfaceOptions,
) -> Result<PointCloud, GeometryError> {
    options.validate()?;
    let cumulative = cumulative_areas(mesh)?;
    let face_normals = mesh.face_normals();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut points = Vec::new();
    let mut normals = Vec::new();
    if count == 0 {
        return Ok(PointCloud {
            points,
            normals: Some(normals),
            colors: None,
        });
    }
    let batch = count.saturating_mul(options.oversample);
    for _ in 0..=options.max_retries {
        let (candidates, cand_normals) =
            draw_uniform(mesh, &cumulative, &face_normals, batch, &mut rng);
        let cand64: Vec<DVec3> = candidates.iter().map(|p| p.as_dvec3()).collect();
        let visible = visibility(mesh, &cand64, &options);
        for ((p, n), v) in candidates.into_iter().zip(cand_normals).zip(visible) {
            if v {
                points.push(p);
                normals.push(n);
            }
        }
        if points.len() >= count {
            break;
        }
    }
    // Partial Fisher–Yates: the first `count` slots become a uniform random subset.
    let keep = count.min(points.len());
    for i in 0..keep {
        let j = rng.random_range(i..points.len());
        points.swap(i, j);
        normals.swap(i, j);
    }
    points.truncate(keep);
    normals.truncate(keep);
    Ok(PointCloud {
        points,
        normals: Some(normals),
        colors: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Pose;
    use crate::shapes::{CompositeKind, box_mesh, composite, icosphere};

    /// Two unit-half-extent boxes, the second shifted by (1, 0.5, 0.25): they interpenetrate.
    fn overlapping_boxes() -> (Mesh, [(Vec3, Vec3); 2]) {
        let mut m = box_mesh(Vec3::ONE).unwrap();
        let shift = Vec3::new(1.0, 0.5, 0.25);
        m.append(
            &box_mesh(Vec3::ONE)
                .unwrap()
                .transformed(&Pose::from_translation(shift.as_dvec3())),
        );
        (
            m,
            [
                (-Vec3::ONE, Vec3::ONE),
                (shift - Vec3::ONE, shift + Vec3::ONE),
            ],
        )
    }

    /// Strictly inside a box, more than `margin` from its faces.
    fn inside(p: Vec3, (lo, hi): (Vec3, Vec3), margin: f32) -> bool {
        p.cmpgt(lo + margin).all() && p.cmplt(hi - margin).all()
    }

    fn interior_fraction(cloud: &PointCloud, boxes: &[(Vec3, Vec3); 2], margin: f32) -> f64 {
        let n = cloud
            .points
            .iter()
            .filter(|&&p| boxes.iter().any(|&b| inside(p, b, margin)))
            .count();
        n as f64 / cloud.len() as f64
    }

    #[test]
    fn visible_sampling_avoids_interior_faces_of_overlapping_boxes() {
        let (m, boxes) = overlapping_boxes();
        let uniform = sample_surface_uniform(&m, 4000, 5).unwrap();
        let visible =
            sample_visible_surface(&m, 4000, 5, VisibleSurfaceOptions::default()).unwrap();
        assert_eq!(visible.len(), 4000);
        let (fu, fv) = (
            interior_fraction(&uniform, &boxes, 1e-4),
            interior_fraction(&visible, &boxes, 1e-4),
        );
        eprintln!("interior fraction: uniform {fu:.4}, visible {fv:.4}");
        // About a quarter of the faces' area lies inside the other box.
        assert!(fu > 0.1, "uniform interior fraction {fu}");
        assert!(fv < 0.01, "visible interior fraction {fv}");
        // Nothing is deeper inside than a few depth tolerances (1e-3 × diagonal ≈ 0.0045).
        assert_eq!(interior_fraction(&visible, &boxes, 0.01), 0.0);
    }

    #[test]
    fn a_box_enclosed_in_another_is_never_sampled() {
        let mut m = box_mesh(Vec3::ONE).unwrap();
        m.append(&icosphere(0.5, 2).unwrap());
        let cloud = sample_visible_surface(&m, 3000, 4, VisibleSurfaceOptions::default()).unwrap();
        assert_eq!(cloud.len(), 3000);
        assert!(
            cloud
                .points
                .iter()
                .all(|p| p.abs().max_element() > 1.0 - 1e-5)
        );
    }

    #[test]
    fn visible_samples_of_a_box_lie_on_its_surface() {
        let h = Vec3::new(0.5, 1.0, 1.5);
        let m = box_mesh(h).unwrap();
        let cloud = sample_visible_surface(&m, 2000, 9, VisibleSurfaceOptions::default()).unwrap();
        assert_eq!(cloud.len(), 2000);
        let normals = cloud.normals.as_ref().unwrap();
        for (p, n) in cloud.points.iter().zip(normals) {
            let d = (p.abs() - h).abs();
            assert!(d.min_element() < 1e-5, "{p} is not on a face");
            assert!(p.abs().cmple(h + 1e-5).all(), "{p} is outside the box");
            // The normal is that of the face the point is on.
            let axis = d.min_position();
            assert!(
                (n[axis].abs() - 1.0).abs() < 1e-6 && n[axis] * p[axis] > 0.0,
                "normal {n} at {p}"
            );
        }
        // All six faces are reached, roughly in proportion to their areas.
        let face_area = [h.y * h.z, h.x * h.z, h.x * h.y];
        let total: f32 = 2.0 * face_area.iter().sum::<f32>();
        for axis in 0..3 {
            let n = cloud
                .points
                .iter()
                .filter(|p| ((p[axis].abs() - h[axis]).abs()) < 1e-5)
                .count();
            let expected = 2.0 * face_area[axis] / total;
            let got = n as f32 / cloud.len() as f32;
            assert!(
                (got - expected).abs() < 0.04,
                "axis {axis}: {got} vs {expected}"
            );
        }
    }

    #[test]
    fn sampling_is_seeded() {
        let m = composite(CompositeKind::Chair, 4);
        let o = VisibleSurfaceOptions {
            resolution: 128,
            views: 20,
            ..Default::default()
        };
        assert_eq!(
            sample_surface_uniform(&m, 300, 1).unwrap(),
            sample_surface_uniform(&m, 300, 1).unwrap()
        );
        assert_ne!(
            sample_surface_uniform(&m, 300, 1).unwrap(),
            sample_surface_uniform(&m, 300, 2).unwrap()
        );
        let a = sample_visible_surface(&m, 300, 1, o).unwrap();
        assert_eq!(a, sample_visible_surface(&m, 300, 1, o).unwrap());
        assert_ne!(a, sample_visible_surface(&m, 300, 2, o).unwrap());
    }

    #[test]
    fn triangles_are_chosen_by_area() {
        // A big triangle (area 8) and a small one (area 0.5), far apart.
        let m = Mesh::new(
            vec![
                Vec3::ZERO,
                Vec3::new(4.0, 0.0, 0.0),
                Vec3::new(0.0, 4.0, 0.0),
                Vec3::new(10.0, 0.0, 0.0),
                Vec3::new(11.0, 0.0, 0.0),
                Vec3::new(10.0, 1.0, 0.0),
            ],
            vec![[0, 1, 2], [3, 4, 5]],
        )
        .unwrap();
        let cloud = sample_surface_uniform(&m, 20000, 3).unwrap();
        let big = cloud.points.iter().filter(|p| p.x < 5.0).count() as f64 / cloud.len() as f64;
        assert!(
            (big - 8.0 / 8.5).abs() < 0.01,
            "fraction on the big triangle {big}"
        );
        // Points lie inside their triangle, uniformly: the mean of the big one's is its centroid.
        let on_big: Vec<_> = cloud.points.iter().filter(|p| p.x < 5.0).collect();
        let mean = on_big.iter().fold(Vec3::ZERO, |s, p| s + **p) / on_big.len() as f32;
        assert!(
            mean.abs_diff_eq(Vec3::new(4.0 / 3.0, 4.0 / 3.0, 0.0), 0.03),
            "mean {mean}"
        );
        assert!(
            on_big
                .iter()
                .all(|p| p.x >= 0.0 && p.y >= 0.0 && p.x + p.y <= 4.0 + 1e-5)
        );
        assert!(cloud.normals.unwrap().iter().all(|n| *n == Vec3::Z));
    }

    #[test]
    fn empty_counts_and_bad_input() {
        let m = icosphere(1.0, 1).unwrap();
        assert!(sample_surface_uniform(&m, 0, 1).unwrap().is_empty());
        assert!(
            sample_visible_surface(&m, 0, 1, VisibleSurfaceOptions::default())
                .unwrap()
                .is_empty()
        );
        let flat = Mesh::new(vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0], vec![[0, 1, 2]]).unwrap();
        assert!(matches!(
            sample_surface_uniform(&flat, 10, 1),
            Err(GeometryError::InvalidParameter { name: "mesh", .. })
        ));
        assert!(matches!(
            sample_surface_uniform(&Mesh::default(), 10, 1),
            Err(GeometryError::InvalidParameter { .. })
        ));
        let bad = VisibleSurfaceOptions {
            views: 0,
            ..Default::default()
        };
        assert!(matches!(
            sample_visible_surface(&m, 10, 1, bad),
            Err(GeometryError::InvalidParameter { name: "views", .. })
        ));
        let bad = VisibleSurfaceOptions {
            depth_tolerance: f64::NAN,
            ..Default::default()
        };
        assert!(sample_visible_surface(&m, 10, 1, bad).is_err());
    }

    #[test]
    fn visible_sampling_of_a_composite_is_fast_enough_and_complete() {
        let m = composite(CompositeKind::Mug, 11);
        let start = std::time::Instant::now();
        let cloud = sample_visible_surface(&m, 1024, 0, VisibleSurfaceOptions::default()).unwrap();
        eprintln!(
            "visible sampling, 1024 points on a mug ({} triangles): {:?}",
            m.triangles.len(),
            start.elapsed()
        );
        assert_eq!(cloud.len(), 1024);
        cloud.validate().unwrap();
    }

    /// Fraction of uniform candidates that the visibility test keeps.
    fn kept_fraction(m: &Mesh, n: usize) -> f64 {
        let c = sample_surface_uniform(m, n, 21).unwrap();
        let p: Vec<DVec3> = c.points.iter().map(|p| p.as_dvec3()).collect();
        let v = visibility(m, &p, &VisibleSurfaceOptions::default());
        v.iter().filter(|&&b| b).count() as f64 / n as f64
    }

    #[test]
    fn outer_surfaces_are_kept_almost_entirely() {
        use crate::shapes::{cylinder, torus};
        let shapes = [
            ("icosphere", icosphere(1.0, 3).unwrap()),
            ("cylinder", cylinder(0.3, 1.0, 32).unwrap()),
            ("torus", torus(1.0, 0.3, 48, 24).unwrap()),
            ("box", box_mesh(Vec3::new(1.0, 0.2, 0.05)).unwrap()),
        ];
        for (what, m) in &shapes {
            let f = kept_fraction(m, 5000);
            eprintln!("{what}: kept {f:.4}");
            assert!(f > 0.995, "{what}: only {f} of the outer surface kept");
        }
        for kind in CompositeKind::ALL {
            let m = composite(kind, 2);
            eprintln!(
                "{kind:?}: kept {:.4} of the uniform samples",
                kept_fraction(&m, 5000)
            );
        }
    }

    #[test]
    fn fibonacci_directions_are_unit_and_balanced() {
        let d = fibonacci_sphere(42);
        assert!(d.iter().all(|v| (v.length() - 1.0).abs() < 1e-12));
        assert!(d.iter().sum::<DVec3>().length() < 0.5);
    }

    /// The rasteriser as it was before scan lines: every pixel centre of every triangle's
    /// clamped bounding box goes through the coverage test. Returns (depth, front, pixels
    /// tested).
    fn rasterise_every_box_pixel(
        projected: &[DVec3],
        triangles: &[[u32; 3]],
        res: usize,
    ) -> (Vec<f64>, Vec<u32>, u64) {
        let mut depth = vec![f64::INFINITY; res * res];
        let mut front = vec![u32::MAX; res * res];
        let mut tested = 0;
        for (f, &[i, j, k]) in triangles.iter().enumerate() {
            let [a, b, c] = [i, j, k].map(|i| projected[i as usize]);
            let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
            if area.abs() < 1e-12 {
                continue;
            }
            let x0 = a.x.min(b.x).min(c.x).ceil().max(0.0);
            let x1 = a.x.max(b.x).max(c.x).floor().min((res - 1) as f64);
            let y0 = a.y.min(b.y).min(c.y).ceil().max(0.0);
            let y1 = a.y.max(b.y).max(c.y).floor().min((res - 1) as f64);
            if x0 > x1 || y0 > y1 {
                continue;
            }
            for py in y0 as usize..=y1 as usize {
                let y = py as f64;
                for px in x0 as usize..=x1 as usize {
                    tested += 1;
                    let x = px as f64;
                    let wa = ((b.x - x) * (c.y - y) - (b.y - y) * (c.x - x)) / area;
                    let wb = ((c.x - x) * (a.y - y) - (c.y - y) * (a.x - x)) / area;
                    let wc = 1.0 - wa - wb;
                    if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                        continue;
                    }
                    let z = wa * a.z + wb * b.z + wc * c.z;
                    let k = py * res + px;
                    if z < depth[k] {
                        depth[k] = z;
                        front[k] = f as u32;
                    }
                }
            }
        }
        (depth, front, tested)
    }

    /// Asserts that [`rasterise`] gives bit for bit the z-buffer of
    /// [`rasterise_every_box_pixel`], testing no more pixels; returns its work.
    fn assert_same_raster(projected: &[DVec3], triangles: &[[u32; 3]], res: usize) -> RasterWork {
        let (z, work) = rasterise(projected, triangles, res);
        let (depth, front, tested) = rasterise_every_box_pixel(projected, triangles, res);
        let bits = |d: &[f64]| d.iter().map(|z| z.to_bits()).collect::<Vec<_>>();
        if z.front != front || bits(&z.depth) != bits(&depth) {
            let k = (0..res * res)
                .find(|&k| z.front[k] != front[k] || z.depth[k].to_bits() != depth[k].to_bits())
                .unwrap();
            panic!(
                "pixel ({}, {}): front {} depth {} instead of {} {}; triangles {:?}",
                k % res,
                k / res,
                z.front[k],
                z.depth[k],
                front[k],
                depth[k],
                triangles
                    .iter()
                    .map(|t| t.map(|i| projected[i as usize]))
                    .collect::<Vec<_>>()
            );
        }
        assert!(work.pixels <= tested, "{work:?} vs {tested} pixels tested");
        work
    }

    /// A planar convex polygon of `n` vertices on the unit circle, fan-triangulated from vertex
    /// 0 as the OBJ reader does: `n − 2` slivers.
    fn circle_fan(n: u32) -> Mesh {
        let vertices = (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * f64::from(i) / f64::from(n);
                Vec3::new(a.cos() as f32, a.sin() as f32, 0.0)
            })
            .collect();
        Mesh::new(vertices, (1..n - 1).map(|i| [0, i, i + 1]).collect()).unwrap()
    }

    #[test]
    fn scan_lines_cover_exactly_the_pixels_the_bounding_box_test_covers() {
        // Each triangle alone (so that no other triangle hides a difference), at 40×40 pixels.
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let res = 40;
        let mut lines = 0;
        for n in 0..30_000 {
            let mut p = |lo: f64, hi: f64| rng.random_range(lo..hi);
            let z = [p(-1.0, 1.0), p(-1.0, 1.0), p(-1.0, 1.0)];
            let xy: [(f64, f64); 3] = match n % 6 {
                // Anywhere, also partly or wholly outside the image.
                0 => [(); 3].map(|_| (p(-10.0, 50.0), p(-10.0, 50.0))),
                // Vertices on pixel centres and on half pixels: edges through pixel centres.
                1 => [(); 3].map(|_| (p(-3.0, 43.0).round(), p(-3.0, 43.0).round())),
                2 => [(); 3].map(|_| {
                    (
                        (p(-3.0, 43.0) * 2.0).round() / 2.0,
                        (p(-3.0, 43.0) * 2.0).round() / 2.0,
                    )
                }),
                // Slivers of any direction and width 1e-12 … 1 px.
                3 | 4 => {
                    let (x, y) = (p(-5.0, 45.0), p(-5.0, 45.0));
                    let (dx, dy) = (p(-50.0, 50.0), p(-50.0, 50.0));
                    let t = p(0.0, 1.0);
                    let w = 10f64.powf(p(-12.0, 0.0)) / (dx * dx + dy * dy).sqrt().max(1e-9);
                    [
                        (x, y),
                        (x + dx, y + dy),
                        (x + t * dx - w * dy, y + t * dy + w * dx),
                    ]
                }
                // Slivers along a pixel row, column or diagonal, through pixel centres.
                _ => {
                    let (x, y) = (p(0.0, 40.0).round(), p(0.0, 40.0).round());
                    let len = p(2.0, 40.0).round();
                    let (dx, dy) = [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, -1.0)][n / 6 % 4];
                    let w = 10f64.powf(p(-13.0, -3.0));
                    let t = p(0.0, 1.0);
                    [
                        (x, y),
                        (x + len * dx, y + len * dy),
                        (x + t * len * dx - w * dy, y + t * len * dy + w * dx),
                    ]
                }
            };
            let projected: Vec<DVec3> =
                (0..3).map(|i| DVec3::new(xy[i].0, xy[i].1, z[i])).collect();
            lines += assert_same_raster(&projected, &[[0, 1, 2]], res).lines;
        }
        assert!(
            lines > 100_000,
            "only {lines} scan lines: the scan path was hardly run"
        );
    }

    #[test]
    fn scan_line_z_buffers_of_meshes_are_identical_to_the_bounding_box_test() {
        let meshes = [
            composite(CompositeKind::Chair, 4),
            icosphere(1.0, 2).unwrap(),
            box_mesh(Vec3::new(1.0, 0.2, 0.05)).unwrap(),
            circle_fan(3000),
        ];
        for mut m in meshes {
            m.normalise().unwrap();
            let bounds = m.bounds().unwrap();
            let half = 0.5 * bounds.diagonal() * 1.02;
            for (res, d) in [(256, 5), (64, 12), (97, 20)] {
                let dirs = fibonacci_sphere(d);
                for &d in dirs.iter().step_by(4) {
                    let view = View::new(d, bounds.centre(), half, res);
                    let projected: Vec<DVec3> = m
                        .vertices
                        .iter()
                        .map(|v| view.project(v.as_dvec3()))
                        .collect();
                    assert_same_raster(&projected, &m.triangles, res);
                }
            }
        }
    }

    #[test]
    fn a_fan_of_slivers_samples_as_fast_as_its_area() {
        // One polygon of 10⁵ vertices, fan-triangulated into slivers from vertex 0: each has a
        // bounding box of up to half the image but almost no area. Testing every pixel of every
        // box took 24 s; the work must instead follow the covered pixels and scan lines.
        let mut m = circle_fan(100_000);
        m.normalise().unwrap();
        let options = VisibleSurfaceOptions::default();
        let res = options.resolution;
        let bounds = m.bounds().unwrap();
        let half = 0.5 * bounds.diagonal() * 1.02;
        let (mut work, mut box_pixels) = (RasterWork::default(), 0u64);
        for d in fibonacci_sphere(options.views) {
            let view = View::new(d, bounds.centre(), half, res);
            let projected: Vec<DVec3> = m
                .vertices
                .iter()
                .map(|v| view.project(v.as_dvec3()))
                .collect();
            let (_, w) = rasterise(&projected, &m.triangles, res);
            // Outside the small boxes tested whole, every pixel centre is tested about once.
            assert!(
                w.pixels <= (SMALL_BOX_PIXELS * m.triangles.len() + 2 * res * res) as u64,
                "{w:?}"
            );
            work.lines += w.lines;
            work.pixels += w.pixels;
            // What the bounding-box rasteriser tested: every pixel centre of every box.
            for t in &m.triangles {
                let [a, b, c] = t.map(|i| projected[i as usize]);
                let side = |lo: f64, hi: f64| {
                    let (lo, hi) = (lo.ceil().max(0.0), hi.floor().min((res - 1) as f64));
                    if lo > hi { 0 } else { (hi - lo) as u64 + 1 }
                };
                box_pixels += side(a.x.min(b.x).min(c.x), a.x.max(b.x).max(c.x))
                    * side(a.y.min(b.y).min(c.y), a.y.max(b.y).max(c.y));
            }
        }
        let total = work.lines + work.pixels;
        eprintln!("fan of slivers: {work:?} ({total} steps) against {box_pixels} box pixels");
        assert!(
            total * 50 < box_pixels,
            "{total} steps is not far below the {box_pixels} box pixels"
        );
        // And it samples: the visible surface of a flat disc is all of it.
        let cloud = sample_visible_surface(&m, 1000, 3, options).unwrap();
        assert_eq!(cloud.len(), 1000);
        assert!(
            cloud
                .points
                .iter()
                .all(|p| p.z.abs() < 1e-6 && p.length() < 1.0 + 1e-5)
        );
    }
}
