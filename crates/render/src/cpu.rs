//! The CPU reference rasteriser: a z-buffer over horizontal bands of rows (rayon), with
//! triangle set-up in f64.
//!
//! Per triangle: vertices go to the camera frame in f64, the triangle is clipped against the
//! near plane (a convex polygon of 3 or 4 vertices), projected to OpenCV pixel coordinates, and
//! covered pixels are found with exact edge functions evaluated at integer pixel coordinates
//! (pixel centres) with the top-left rule for samples exactly on an edge. Depth comes from the
//! triangle's plane in the camera frame, `1/z = (n·r)/(n·p₀)` with `r` the pixel's ray, so it
//! is exact up to f64 rounding whatever the clipping did.

use glam::{DVec2, DVec3};
use ic_geometry::Intrinsics;
use rayon::prelude::*;

use crate::RenderError;
use crate::renderer::{Camera, Renderer, Rendering, Scene, model_to_camera};

/// Rows per parallel work item.
const BAND_ROWS: usize = 8;

/// The CPU reference renderer. Stateless apart from its options; `render` is parallel over
/// bands of rows, `render_batch` parallel over views.
#[derive(Clone, Debug, Default)]
pub struct CpuRenderer {
    _private: (),
}

impl CpuRenderer {
    pub fn new() -> Self {
        CpuRenderer { _private: () }
    }
}

impl Renderer for CpuRenderer {
    fn render(&mut self, scene: &Scene, camera: &Camera) -> Result<Rendering, RenderError> {
        scene.validate()?;
        camera.validate()?;
        Ok(rasterise(scene, camera, true))
    }

    fn render_batch(
        &mut self,
        scene: &Scene,
        cameras: &[Camera],
    ) -> Result<Vec<Rendering>, RenderError> {
        scene.validate()?;
        for c in cameras {
            c.validate()?;
        }
        if cameras.len() == 1 {
            return Ok(vec![rasterise(scene, &cameras[0], true)]);
        }
        Ok(cameras
            .par_iter()
            .map(|c| rasterise(scene, c, false))
            .collect())
    }

    fn name(&self) -> String {
        "cpu".into()
    }
}

/// A clipped, projected triangle (convex polygon) ready for scan conversion.
struct Poly {
    n: usize,
    pts: [DVec2; 4],
    /// Unit plane normal in the camera frame.
    normal: DVec3,
    /// `1/z = a·u + b·v + c` at pixel `(u, v)`.
    plane: [f64; 3],
    /// Inclusive pixel bounds.
    u0: usize,
    u1: usize,
    v0: usize,
    v1: usize,
    id: u32,
}

fn setup(tri: [DVec3; 3], id: u32, k: &Intrinsics, near: f64) -> Option<Poly> {
    let normal_raw = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
    let d = normal_raw.dot(tri[0]);
    // Degenerate triangles, and triangles seen exactly edge-on (plane through the eye), cover
    // no area.
    if normal_raw.length_squared() == 0.0 || d == 0.0 {
        return None;
    }
    // Clip against z >= near (Sutherland–Hodgman with one plane).
    let mut clipped = [DVec3::ZERO; 4];
    let mut n = 0;
    for i in 0..3 {
        let a = tri[i];
        let b = tri[(i + 1) % 3];
        let a_in = a.z >= near;
        let b_in = b.z >= near;
        if a_in {
            clipped[n] = a;
            n += 1;
        }
        if a_in != b_in {
            let t = (near - a.z) / (b.z - a.z);
            let mut p = a + (b - a) * t;
            p.z = near;
            clipped[n] = p;
            n += 1;
        }
    }
    if n < 3 {
        return None;
    }
    let mut pts = [DVec2::ZERO; 4];
    for i in 0..n {
        let p = clipped[i];
        pts[i] = DVec2::new(k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
    }
    // Orientation: positive shoelace area in (u, v) (clockwise on screen, v down).
    let mut area = 0.0;
    for i in 0..n {
        area += pts[i].perp_dot(pts[(i + 1) % n]);
    }
    if area == 0.0 || !area.is_finite() {
        return None;
    }
    if area < 0.0 {
        pts[..n].reverse();
    }
    let (mut umin, mut umax, mut vmin, mut vmax) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in &pts[..n] {
        umin = umin.min(p.x);
        umax = umax.max(p.x);
        vmin = vmin.min(p.y);
        vmax = vmax.max(p.y);
    }
    let (w, h) = (k.width as f64, k.height as f64);
    let u0 = umin.ceil().max(0.0);
    let u1 = umax.floor().min(w - 1.0);
    let v0 = vmin.ceil().max(0.0);
    let v1 = vmax.floor().min(h - 1.0);
    if u0 > u1 || v0 > v1 {
        return None;
    }
    // Plane n·p = d; the pixel ray r = ((u − cx)/fx, (v − cy)/fy, 1) meets it at z = d/(n·r).
    let a = normal_raw.x / (k.fx * d);
    let b = normal_raw.y / (k.fy * d);
    let c = (normal_raw.z - normal_raw.x * k.cx / k.fx - normal_raw.y * k.cy / k.fy) / d;
    Some(Poly {
        n,
        pts,
        normal: normal_raw.normalize(),
        plane: [a, b, c],
        u0: u0 as usize,
        u1: u1 as usize,
        v0: v0 as usize,
        v1: v1 as usize,
        id,
    })
}

/// Whether a sample exactly on edge `a → b` belongs to the polygon (top-left rule, v down,
/// positive orientation).
#[inline]
fn top_left(a: DVec2, b: DVec2) -> bool {
    let e = b - a;
    (e.y == 0.0 && e.x > 0.0) || e.y < 0.0
}

struct Band<'a> {
    row0: usize,
    depth: &'a mut [f32],
    ids: &'a mut [u32],
    inc: &'a mut [f32],
    zbuf: Vec<f64>,
}

fn raster_band(band: &mut Band, polys: &[Poly], list: &[u32], k: &Intrinsics) {
    let w = k.width as usize;
    let rows = band.depth.len() / w;
    let row_end = band.row0 + rows - 1;
    for &pi in list {
        let p = &polys[pi as usize];
        let v_lo = p.v0.max(band.row0);
        let v_hi = p.v1.min(row_end);
        let mut edges = [(DVec2::ZERO, DVec2::ZERO, false); 4];
        for (i, e) in edges.iter_mut().enumerate().take(p.n) {
            let a = p.pts[i];
            let b = p.pts[(i + 1) % p.n];
            *e = (a, b - a, top_left(a, b));
        }
        let edges = &edges[..p.n];
        for v in v_lo..=v_hi {
            let vf = v as f64;
            let row = (v - band.row0) * w;
            for u in p.u0..=p.u1 {
                let uf = u as f64;
                let inside = edges.iter().all(|&(a, e, tl)| {
                    let f = e.x * (vf - a.y) - e.y * (uf - a.x);
                    f > 0.0 || (f == 0.0 && tl)
                });
                if !inside {
                    continue;
                }
                let inv_z = p.plane[0] * uf + p.plane[1] * vf + p.plane[2];
                if inv_z.is_nan() || inv_z <= 0.0 {
                    continue;
                }
                let z = 1.0 / inv_z;
                let i = row + u;
                if z < band.zbuf[i] {
                    band.zbuf[i] = z;
                    band.depth[i] = z as f32;
                    band.ids[i] = p.id;
                    let r = DVec3::new((uf - k.cx) / k.fx, (vf - k.cy) / k.fy, 1.0);
                    band.inc[i] = (p.normal.dot(r).abs() / r.length()) as f32;
                }
            }
        }
    }
}

/// A band's index and its rows of depth, ids and incidence.
type BandSlices<'a> = (usize, ((&'a mut [f32], &'a mut [u32]), &'a mut [f32]));

/// Renders one view; `parallel` spreads set-up and bands over rayon's pool.
pub(crate) fn rasterise(scene: &Scene, camera: &Camera, parallel: bool) -> Rendering {
    let k = camera.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let poses = model_to_camera(scene, camera);
    // Triangle set-up, in scene order (object order, then triangle order) so that exact depth
    // ties resolve like the GPU's draw order.
    let mut polys: Vec<Poly> = Vec::new();
    for (o, pose) in scene.objects.iter().zip(&poses) {
        let verts: Vec<DVec3> = o
            .mesh
            .vertices
            .iter()
            .map(|v| pose.apply(v.as_dvec3()))
            .collect();
        let make = |t: &[u32; 3]| {
            setup(
                [
                    verts[t[0] as usize],
                    verts[t[1] as usize],
                    verts[t[2] as usize],
                ],
                o.id,
                &k,
                camera.near,
            )
        };
        if parallel && o.mesh.triangles.len() > 2048 {
            polys.par_extend(o.mesh.triangles.par_iter().filter_map(make));
        } else {
            polys.extend(o.mesh.triangles.iter().filter_map(make));
        }
    }
    // Bin polygons into bands of rows.
    let n_bands = h.div_ceil(BAND_ROWS);
    let mut bins: Vec<Vec<u32>> = vec![Vec::new(); n_bands];
    for (i, p) in polys.iter().enumerate() {
        for bin in &mut bins[p.v0 / BAND_ROWS..=p.v1 / BAND_ROWS] {
            bin.push(i as u32);
        }
    }
    let mut out = Rendering::empty(k.width, k.height);
    let chunk = BAND_ROWS * w;
    let work = |(bi, ((depth, ids), inc)): BandSlices| {
        let mut band = Band {
            row0: bi * BAND_ROWS,
            zbuf: vec![f64::INFINITY; depth.len()],
            depth,
            ids,
            inc,
        };
        raster_band(&mut band, &polys, &bins[bi], &k);
    };
    let Rendering {
        depth,
        instances,
        incidence,
    } = &mut out;
    if parallel {
        depth
            .data
            .par_chunks_mut(chunk)
            .zip(instances.data.par_chunks_mut(chunk))
            .zip(incidence.data.par_chunks_mut(chunk))
            .enumerate()
            .for_each(work);
    } else {
        depth
            .data
            .chunks_mut(chunk)
            .zip(instances.data.chunks_mut(chunk))
            .zip(incidence.data.chunks_mut(chunk))
            .enumerate()
            .for_each(work);
    }
    out
}
