#![allow(dead_code)]

use ic_geometry::{Intrinsics, Mesh, glam::DVec3};
use ic_render::{Camera, Rendering};

/// The shared wgpu renderer (device creation costs 35–260 ms on lavapipe).
///
/// # Panics
/// When no adapter exists: a test of the `gpu` feature fails rather than passing unchecked
/// (CI installs Mesa's lavapipe; so can any machine: `mesa-vulkan-drivers libvulkan1`).
#[cfg(feature = "gpu")]
pub fn wgpu() -> std::sync::MutexGuard<'static, ic_render::WgpuRenderer> {
    use std::sync::{Mutex, OnceLock};
    static R: OnceLock<Mutex<ic_render::WgpuRenderer>> = OnceLock::new();
    R.get_or_init(|| match ic_render::WgpuRenderer::new() {
        Ok(r) => {
            eprintln!("wgpu adapter: {:?}", r.adapter_info());
            Mutex::new(r)
        }
        Err(e) => panic!("the wgpu tests need an adapter (a GPU, or Mesa's lavapipe): {e}"),
    })
    .lock()
    .unwrap_or_else(|e| e.into_inner())
}

/// Distance along the pixel ray to the sphere (centre `c` in the camera frame, radius `r`),
/// as camera-frame z; `None` when the ray misses.
pub fn ray_sphere_z(k: &Intrinsics, u: u32, v: u32, c: DVec3, r: f64) -> Option<f64> {
    let d = DVec3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
    // |t d − c|² = r²  →  t² d·d − 2 t d·c + c·c − r² = 0; z = t (d.z = 1).
    let (a, b, cc) = (d.dot(d), d.dot(c), c.dot(c) - r * r);
    let disc = b * b - a * cc;
    (disc >= 0.0).then(|| (b - disc.sqrt()) / a)
}

/// Largest distance between the sphere and the mesh surface: r − (distance of the nearest
/// face plane to the centre).
pub fn faceting_error(mesh: &Mesh, r: f64) -> f64 {
    (0..mesh.triangles.len())
        .map(|i| {
            let [a, b, c] = mesh.triangle(i);
            let n = (b - a).cross(c - a).normalize();
            r - n.dot(a).abs()
        })
        .fold(0.0, f64::max)
}

/// Pixels whose 3×3 neighbourhood (inside the image) all show the same id, and that id is not
/// background.
pub fn interior(r: &Rendering) -> Vec<usize> {
    let (w, h) = (r.instances.width as usize, r.instances.height as usize);
    let ids = &r.instances.data;
    let mut out = Vec::new();
    for v in 1..h - 1 {
        for u in 1..w - 1 {
            let id = ids[v * w + u];
            if id == 0 {
                continue;
            }
            let same = (0..3).all(|dv| (0..3).all(|du| ids[(v + dv - 1) * w + (u + du - 1)] == id));
            if same {
                out.push(v * w + u);
            }
        }
    }
    out
}

/// Compares two renderings on the interior pixels of `a`: returns (pixels compared, id
/// mismatches, max relative depth difference, 99.9th percentile of it).
pub fn compare(a: &Rendering, b: &Rendering) -> (usize, usize, f64, f64) {
    let px = interior(a);
    let mut mismatched = 0;
    let mut rel: Vec<f64> = Vec::with_capacity(px.len());
    for &i in &px {
        if a.instances.data[i] != b.instances.data[i] {
            mismatched += 1;
            continue;
        }
        let (za, zb) = (a.depth.data[i] as f64, b.depth.data[i] as f64);
        rel.push((za - zb).abs() / za);
    }
    rel.sort_by(f64::total_cmp);
    let max = rel.last().copied().unwrap_or(0.0);
    let p999 = if rel.is_empty() {
        0.0
    } else {
        rel[(rel.len() as f64 * 0.999) as usize]
    };
    (px.len(), mismatched, max, p999)
}

/// A camera on the −z side of the origin looking at it, y down.
pub fn camera_at(k: Intrinsics, distance: f64) -> Camera {
    let pose = ic_geometry::look_at(
        DVec3::new(0.0, 0.0, -distance),
        DVec3::ZERO,
        DVec3::new(0.0, -1.0, 0.0),
    )
    .unwrap();
    Camera::new(k, pose)
}
