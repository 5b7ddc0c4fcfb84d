//! Procedural meshes used by the scenes, tests and benchmarks: boxes, spheres, tori and the
//! bumpy cube room. Triangles are counter-clockwise seen from outside (the room: from inside).

use std::collections::HashMap;

use glam::{DVec3, Vec3};
use ic_geometry::Mesh;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// An axis-aligned box centred at the origin with the given half extents; 8 vertices, 12
/// outward-facing triangles.
pub fn cuboid(half: DVec3) -> Mesh {
    let h = half.as_vec3();
    let vertices = (0..8)
        .map(|i| Vec3::new(if i & 1 == 0 { -h.x } else { h.x }, if i & 2 == 0 { -h.y } else { h.y }, if i & 4 == 0 { -h.z } else { h.z }))
        .collect();
    // Faces as quads (a, b, c, d) counter-clockwise seen from outside.
    let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
    let triangles = quads.iter().flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]]).collect();
    Mesh { vertices, triangles }
}

/// A geodesic sphere: an icosahedron subdivided `subdivisions` times (20·4ⁿ triangles), all
/// vertices at distance `radius` from the origin.
pub fn icosphere(radius: f64, subdivisions: u32) -> Mesh {
    let phi = (1.0 + 5f64.sqrt()) / 2.0;
    let mut verts: Vec<DVec3> = [
        (-1.0, phi, 0.0),
        (1.0, phi, 0.0),
        (-1.0, -phi, 0.0),
        (1.0, -phi, 0.0),
        (0.0, -1.0, phi),
        (0.0, 1.0, phi),
        (0.0, -1.0, -phi),
        (0.0, 1.0, -phi),
        (phi, 0.0, -1.0),
        (phi, 0.0, 1.0),
        (-phi, 0.0, -1.0),
        (-phi, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut midpoint = |a: u32, b: u32, verts: &mut Vec<DVec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *mid.entry(key).or_insert_with(|| {
                verts.push((verts[a as usize] + verts[b as usize]).normalize());
                verts.len() as u32 - 1
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for [a, b, c] in faces {
            let ab = midpoint(a, b, &mut verts);
            let bc = midpoint(b, c, &mut verts);
            let ca = midpoint(c, a, &mut verts);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    Mesh { vertices: verts.iter().map(|v| (*v * radius).as_vec3()).collect(), triangles: faces }
}

/// A torus around the z axis: ring radius `major`, tube radius `minor`, `segments` around the
/// ring and `sides` around the tube (2·segments·sides triangles).
pub fn torus(major: f64, minor: f64, segments: u32, sides: u32) -> Mesh {
    let (segments, sides) = (segments.max(3), sides.max(3));
    let mut vertices = Vec::with_capacity((segments * sides) as usize);
    for i in 0..segments {
        let a = std::f64::consts::TAU * i as f64 / segments as f64;
        for j in 0..sides {
            let b = std::f64::consts::TAU * j as f64 / sides as f64;
            let r = major + minor * b.cos();
            vertices.push(DVec3::new(r * a.cos(), r * a.sin(), minor * b.sin()).as_vec3());
        }
    }
    let idx = |i: u32, j: u32| (i % segments) * sides + (j % sides);
    let mut triangles = Vec::with_capacity((2 * segments * sides) as usize);
    for i in 0..segments {
        for j in 0..sides {
            let (a, b, c, d) = (idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    Mesh { vertices, triangles }
}

/// A closed cube room, floor at z = 0, walls at x, y = ±side/2, ceiling at z = side, with
/// inward-facing triangles (normals point into the room). Each face is a grid of
/// `subdivisions`² quads; walls and ceiling carry seeded smooth bumps of height up to
/// `bump_amplitude` along their normal (the floor stays flat so objects can rest on it). The
/// bumps vanish at the face borders, so the faces still meet.
pub fn room(side: f64, subdivisions: u32, bump_amplitude: f64, bumps_per_face: u32, seed: u64) -> Mesh {
    let n = subdivisions.max(1);
    let h = side / 2.0;
    let s = side;
    // (origin, U, V) with U × V the inward normal.
    let faces: [(DVec3, DVec3, DVec3, bool); 6] = [
        (DVec3::new(-h, -h, 0.0), DVec3::new(s, 0.0, 0.0), DVec3::new(0.0, s, 0.0), false), // floor
        (DVec3::new(-h, -h, s), DVec3::new(0.0, s, 0.0), DVec3::new(s, 0.0, 0.0), true),   // ceiling
        (DVec3::new(-h, -h, 0.0), DVec3::new(0.0, s, 0.0), DVec3::new(0.0, 0.0, s), true), // x = −h
        (DVec3::new(h, -h, 0.0), DVec3::new(0.0, 0.0, s), DVec3::new(0.0, s, 0.0), true),  // x = +h
        (DVec3::new(-h, -h, 0.0), DVec3::new(0.0, 0.0, s), DVec3::new(s, 0.0, 0.0), true), // y = −h
        (DVec3::new(-h, h, 0.0), DVec3::new(s, 0.0, 0.0), DVec3::new(0.0, 0.0, s), true),  // y = +h
    ];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut mesh = Mesh::default();
    for (origin, u, v, bumpy) in faces {
        let normal = u.cross(v).normalize();
        // Gaussian bumps: centre (s, t), width, signed height.
        let bumps: Vec<(f64, f64, f64, f64)> = if bumpy && bump_amplitude > 0.0 {
            (0..bumps_per_face)
                .map(|_| {
                    (rng.random_range(0.1..0.9), rng.random_range(0.1..0.9), rng.random_range(0.05..0.2), rng.random_range(-1.0..1.0))
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
                        .map(|&(ca, cb, w, amp)| amp * (-((a - ca).powi(2) + (b - cb).powi(2)) / (2.0 * w * w)).exp())
                        .sum();
                    p += normal * (bump_amplitude * window * height.clamp(-1.0, 1.0));
                }
                mesh.vertices.push(p.as_vec3());
            }
        }
        let at = |i: u32, j: u32| base + j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                mesh.triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cuboid_and_sphere_are_closed_and_outward() {
        let b = cuboid(DVec3::new(1.0, 2.0, 3.0));
        assert!((b.surface_area() - 2.0 * (2.0 * 4.0 + 2.0 * 6.0 + 4.0 * 6.0)).abs() < 1e-9);
        for (t, n) in b.triangles.iter().zip(b.face_normals()) {
            let c = (b.vertices[t[0] as usize] + b.vertices[t[1] as usize] + b.vertices[t[2] as usize]) / 3.0;
            assert!(n.dot(c) > 0.0, "inward face {t:?}");
        }
        let s = icosphere(2.0, 2);
        assert_eq!(s.triangles.len(), 320);
        assert!(s.vertices.iter().all(|v| (v.length() - 2.0).abs() < 1e-6));
        for (t, n) in s.triangles.iter().zip(s.face_normals()) {
            assert!(n.dot(s.vertices[t[0] as usize]) > 0.0);
        }
        assert_eq!(torus(1.0, 0.3, 100, 50).triangles.len(), 10_000);
    }

    #[test]
    fn room_faces_point_inward() {
        let r = room(4.0, 6, 0.05, 4, 1);
        assert_eq!(r.triangles.len(), 6 * 6 * 6 * 2);
        for (t, n) in r.triangles.iter().zip(r.face_normals()) {
            let c = (r.vertices[t[0] as usize] + r.vertices[t[1] as usize] + r.vertices[t[2] as usize]) / 3.0;
            // Pointing towards the room centre (0, 0, 2).
            assert!(n.dot(Vec3::new(0.0, 0.0, 2.0) - c) > 0.0);
        }
        assert_eq!(room(4.0, 6, 0.05, 4, 1), r, "seeded");
    }
}
