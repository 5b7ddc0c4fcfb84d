//! The bumpy cube room of the paper's BlenderProc set-up. Its triangles are counter-clockwise
//! seen from inside. Objects (boxes, spheres, tori, composites) come from `ic_geometry::shapes`.

use glam::DVec3;
use ic_geometry::Mesh;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A closed cube room, floor at z = 0, walls at x, y = ±side/2, ceiling at z = side, with
/// inward-facing triangles (normals point into the room). Each face is a grid of
/// `subdivisions`² quads; walls and ceiling carry seeded smooth bumps of height up to
/// `bump_amplitude` along their normal (the floor stays flat so objects can rest on it). The
/// bumps vanish at the face borders, so the faces still meet.
pub fn room(
    side: f64,
    subdivisions: u32,
    bump_amplitude: f64,
    bumps_per_face: u32,
    seed: u64,
) -> Mesh {
    let n = subdivisions.max(1);
    let h = side / 2.0;
    let s = side;
    // (origin, U, V) with U × V the inward normal.
    let faces: [(DVec3, DVec3, DVec3, bool); 6] = [
        (
            DVec3::new(-h, -h, 0.0),
            DVec3::new(s, 0.0, 0.0),
            DVec3::new(0.0, s, 0.0),
            false,
        ), // floor
        (
            DVec3::new(-h, -h, s),
            DVec3::new(0.0, s, 0.0),
            DVec3::new(s, 0.0, 0.0),
            true,
        ), // ceiling
        (
            DVec3::new(-h, -h, 0.0),
            DVec3::new(0.0, s, 0.0),
            DVec3::new(0.0, 0.0, s),
            true,
        ), // x = −h
        (
            DVec3::new(h, -h, 0.0),
            DVec3::new(0.0, 0.0, s),
            DVec3::new(0.0, s, 0.0),
            true,
        ), // x = +h
        (
            DVec3::new(-h, -h, 0.0),
            DVec3::new(0.0, 0.0, s),
            DVec3::new(s, 0.0, 0.0),
            true,
        ), // y = −h
        (
            DVec3::new(-h, h, 0.0),
            DVec3::new(s, 0.0, 0.0),
            DVec3::new(0.0, 0.0, s),
            true,
        ), // y = +h
    ];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut mesh = Mesh::default();
    for (origin, u, v, bumpy) in faces {
        let normal = u.cross(v).normalize();
        // Gaussian bumps: centre (s, t), width, signed height.
        let bumps: Vec<(f64, f64, f64, f64)> = if bumpy && bump_amplitude > 0.0 {
            (0..bumps_per_face)
                .map(|_| {
                    (
                        rng.random_range(0.1..0.9),
                        rng.random_range(0.1..0.9),
                        rng.random_range(0.05..0.2),
                        rng.random_range(-1.0..1.0),
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        let base = mesh.vertices.len() as u32;
        for j in 0..=n {
            for i in 0..=n {
                let (a, b) = (i as f64 / n as f64, j as f64 / n as f64);
                let mut p = origin + u * a + v * b;
                if !bumps.is_empty() && i > 0 && i < n && j > 0 && j < n {
                    let window = 16.0 * a * (1.0 - a) * b * (1.0 - b);
                    let height: f64 = bumps
                        .iter()
                        .map(|&(ca, cb, w, amp)| {
                            amp * (-((a - ca).powi(2) + (b - cb).powi(2)) / (2.0 * w * w)).exp()
                        })
                        .sum();
                    p += normal * (bump_amplitude * window * height.clamp(-1.0, 1.0));
                }
                mesh.vertices.push(p.as_vec3());
            }
        }
        let at = |i: u32, j: u32| base + j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles
                    .push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                mesh.triangles
                    .push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn room_faces_point_inward() {
        let r = room(4.0, 6, 0.05, 4, 1);
        assert_eq!(r.triangles.len(), 6 * 6 * 6 * 2);
        for (t, n) in r.triangles.iter().zip(r.face_normals()) {
            let c =
                (r.vertices[t[0] as usize] + r.vertices[t[1] as usize] + r.vertices[t[2] as usize])
                    / 3.0;
            // Pointing towards the room centre (0, 0, 2).
            assert!(n.dot(glam::Vec3::new(0.0, 0.0, 2.0) - c) > 0.0);
        }
        assert_eq!(room(4.0, 6, 0.05, 4, 1), r, "seeded");
    }
}
