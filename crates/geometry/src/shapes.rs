//! Procedural shapes: closed primitives and seeded composite objects.
//!
//! Every primitive is a closed, watertight triangle mesh whose triangles are counter-clockwise
//! seen from outside (face normals point outwards, signed volume > 0). Vertices are not shared
//! between the faces of different primitives, but inside one primitive every edge is shared by
//! exactly two triangles, once in each direction.
//!
//! Frame and units: primitives live in their own model frame, centred at the origin, with the
//! axis of rotational shapes (cylinder, cone, capsule, torus, poles of spheres and
//! superquadrics) along **+z**; sizes are in the caller's units. Composites
//! ([`composite`], [`random_object`]) are built z-up from primitives and then normalised
//! ([`Mesh::normalise`]): their bounding box is centred at the origin and their longest side
//! spans [-1, 1] (normalised object units).
//!
//! Bad parameters (non-finite or non-positive sizes, too few or too many segments) are answered
//! by [`GeometryError::InvalidParameter`], never by a panic. Resolution parameters are capped at
//! [`MAX_SEGMENTS`] (and icosphere subdivisions at [`MAX_SUBDIVISIONS`]) so that vertex indices
//! always fit in `u32` and memory stays bounded.
//!
//! ```
//! use ic_geometry::shapes::{cylinder, composite, CompositeKind};
//!
//! let c = cylinder(0.5, 1.0, 32).unwrap();
//! assert!(c.bounds().unwrap().max.z == 1.0);
//! let table = composite(CompositeKind::Table, 7);
//! assert_eq!(table, composite(CompositeKind::Table, 7));
//! ```

use std::collections::HashMap;
use std::f64::consts::{PI, TAU};

use glam::{DVec3, Vec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::{GeometryError, Mesh, Pose};

/// The largest accepted value of any `segments`/`rings` parameter.
pub const MAX_SEGMENTS: u32 = 4096;
/// The largest accepted number of icosphere subdivisions (20·4⁸ ≈ 1.3 M triangles).
pub const MAX_SUBDIVISIONS: u32 = 8;

// ---------------------------------------------------------------------------------------------
// Parameter checks
// ---------------------------------------------------------------------------------------------

fn positive(name: &'static str, value: f32) -> Result<f64, GeometryError> {
    if value.is_finite() && value > 0.0 {
        Ok(value as f64)
    } else {
        Err(GeometryError::InvalidParameter {
            name,
            message: format!("must be finite and > 0, got {value}"),
        })
    }
}

fn non_negative(name: &'static str, value: f32) -> Result<f64, GeometryError> {
    if value.is_finite() && value >= 0.0 {
        Ok(value as f64)
    } else {
        Err(GeometryError::InvalidParameter {
            name,
            message: format!("must be finite and ≥ 0, got {value}"),
        })
    }
}

fn resolution(name: &'static str, value: u32, min: u32) -> Result<usize, GeometryError> {
    if (min..=MAX_SEGMENTS).contains(&value) {
        Ok(value as usize)
    } else {
        Err(GeometryError::InvalidParameter {
            name,
            message: format!("must be in {min}..={MAX_SEGMENTS}, got {value}"),
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Builders shared by the primitives
// ---------------------------------------------------------------------------------------------

/// A closed surface made of a bottom pole, `rings` (each a loop of points ordered by increasing
/// angle around +z, i.e. counter-clockwise seen from +z, all of equal length, listed from bottom
/// to top) and a top pole. Poles are joined to the first/last ring by triangle fans, neighbouring
/// rings by quads split into two triangles. Orientation is outward as long as the rings go
/// around +z counter-clockwise and bottom→top, whatever their radii.
fn pole_grid(bottom: DVec3, rings: &[Vec<DVec3>], top: DVec3) -> Mesh {
    let n = rings[0].len();
    let mut vertices = Vec::with_capacity(rings.len() * n + 2);
    vertices.push(bottom.as_vec3());
    for ring in rings {
        debug_assert_eq!(ring.len(), n);
        vertices.extend(ring.iter().map(|p| p.as_vec3()));
    }
    let top_index = vertices.len() as u32;
    vertices.push(top.as_vec3());
    let at = |ring: usize, j: usize| (1 + ring * n + j % n) as u32;
    let mut triangles = Vec::with_capacity(2 * n * rings.len());
    for j in 0..n {
        triangles.push([0, at(0, j + 1), at(0, j)]);
    }
    for k in 0..rings.len() - 1 {
        for j in 0..n {
            let (a, b, c, d) = (at(k, j), at(k, j + 1), at(k + 1, j + 1), at(k + 1, j));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    let last = rings.len() - 1;
    for j in 0..n {
        triangles.push([top_index, at(last, j), at(last, j + 1)]);
    }
    Mesh {
        vertices,
        triangles,
    }
}

/// A ring of `n` points at height `z` and radius `r` around the z axis, starting on +x.
fn circle(r: f64, z: f64, n: usize) -> Vec<DVec3> {
    (0..n)
        .map(|j| {
            let a = TAU * j as f64 / n as f64;
            DVec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// `sign(x)·|x|^e`, the signed power used by superquadrics.
fn signed_pow(x: f64, e: f64) -> f64 {
    x.signum() * x.abs().powf(e)
}

// ---------------------------------------------------------------------------------------------
// Primitives (unchecked versions are used by the composites, whose parameters are known good)
// ---------------------------------------------------------------------------------------------

fn box_raw(h: DVec3) -> Mesh {
    let vertices = (0..8)
        .map(|i| {
            let s = DVec3::new(
                if i & 1 == 0 { -1.0 } else { 1.0 },
                if i & 2 == 0 { -1.0 } else { 1.0 },
                if i & 4 == 0 { -1.0 } else { 1.0 },
            );
            (s * h).as_vec3()
        })
        .collect();
    // Vertex i has x = bit 0, y = bit 1, z = bit 2. Each face is CCW seen from outside.
    let triangles = vec![
        [0, 2, 3],
        [0, 3, 1], // -z
        [4, 5, 7],
        [4, 7, 6], // +z
        [0, 1, 5],
        [0, 5, 4], // -y
        [2, 6, 7],
        [2, 7, 3], // +y
        [0, 4, 6],
        [0, 6, 2], // -x
        [1, 3, 7],
        [1, 7, 5], // +x
    ];
    Mesh {
        vertices,
        triangles,
    }
}

fn cylinder_raw(r: f64, hh: f64, n: usize) -> Mesh {
    pole_grid(
        DVec3::new(0.0, 0.0, -hh),
        &[circle(r, -hh, n), circle(r, hh, n)],
        DVec3::new(0.0, 0.0, hh),
    )
}

fn cone_raw(r: f64, hh: f64, n: usize) -> Mesh {
    pole_grid(
        DVec3::new(0.0, 0.0, -hh),
        &[circle(r, -hh, n)],
        DVec3::new(0.0, 0.0, hh),
    )
}

fn sphere_raw(r: f64, segments: usize, rings: usize) -> Mesh {
    let rings: Vec<_> = (1..rings)
        .map(|k| {
            let lat = -PI / 2.0 + PI * k as f64 / rings as f64;
            circle(r * lat.cos(), r * lat.sin(), segments)
        })
        .collect();
    pole_grid(DVec3::new(0.0, 0.0, -r), &rings, DVec3::new(0.0, 0.0, r))
}

fn capsule_raw(r: f64, hh: f64, segments: usize, rings: usize) -> Mesh {
    let mut loops = Vec::with_capacity(2 * rings);
    for k in 1..=rings {
        let lat = -PI / 2.0 + (PI / 2.0) * k as f64 / rings as f64;
        loops.push(circle(r * lat.cos(), -hh + r * lat.sin(), segments));
    }
    // With no cylindrical part the two equators coincide: keep one (no zero-area band).
    let first = if hh > 0.0 { 0 } else { 1 };
    for k in first..rings {
        let lat = (PI / 2.0) * k as f64 / rings as f64;
        loops.push(circle(r * lat.cos(), hh + r * lat.sin(), segments));
    }
    pole_grid(
        DVec3::new(0.0, 0.0, -hh - r),
        &loops,
        DVec3::new(0.0, 0.0, hh + r),
    )
}

fn torus_raw(major: f64, minor: f64, nu: usize, nv: usize) -> Mesh {
    let mut vertices = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        let u = TAU * i as f64 / nu as f64;
        for k in 0..nv {
            let v = TAU * k as f64 / nv as f64;
            let rho = major + minor * v.cos();
            vertices.push(DVec3::new(rho * u.cos(), rho * u.sin(), minor * v.sin()).as_vec3());
        }
    }
    let at = |i: usize, k: usize| ((i % nu) * nv + k % nv) as u32;
    let mut triangles = Vec::with_capacity(2 * nu * nv);
    for i in 0..nu {
        for k in 0..nv {
            // ∂p/∂u × ∂p/∂v points out of the tube, so (u, v) order is CCW from outside.
            let (a, b, c, d) = (at(i, k), at(i + 1, k), at(i + 1, k + 1), at(i, k + 1));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    Mesh {
        vertices,
        triangles,
    }
}

fn superquadric_raw(a: DVec3, e1: f64, e2: f64, segments: usize, rings: usize) -> Mesh {
    let loops: Vec<_> = (1..rings)
        .map(|k| {
            let eta = -PI / 2.0 + PI * k as f64 / rings as f64;
            let (ce, se) = (signed_pow(eta.cos(), e1), signed_pow(eta.sin(), e1));
            (0..segments)
                .map(|j| {
                    let w = -PI + TAU * j as f64 / segments as f64;
                    DVec3::new(
                        a.x * ce * signed_pow(w.cos(), e2),
                        a.y * ce * signed_pow(w.sin(), e2),
                        a.z * se,
                    )
                })
                .collect()
        })
        .collect();
    pole_grid(
        DVec3::new(0.0, 0.0, -a.z),
        &loops,
        DVec3::new(0.0, 0.0, a.z),
    )
}

fn icosphere_raw(r: f64, subdivisions: u32) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut points: Vec<DVec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| DVec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::with_capacity(faces.len() * 3 / 2);
        let mut mid = |a: u32, b: u32, points: &mut Vec<DVec3>| -> u32 {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                points.push((points[a as usize] + points[b as usize]).normalize());
                (points.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for &[a, b, c] in &faces {
            let ab = mid(a, b, &mut points);
            let bc = mid(b, c, &mut points);
            let ca = mid(c, a, &mut points);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    Mesh {
        vertices: points.iter().map(|p| (*p * r).as_vec3()).collect(),
        triangles: faces,
    }
}

// ---------------------------------------------------------------------------------------------
// Public primitives
// ---------------------------------------------------------------------------------------------

/// An axis-aligned box spanning `[-h, h]` on each axis (`h = half_extents`, model units):
/// 8 vertices, 12 triangles.
pub fn box_mesh(half_extents: Vec3) -> Result<Mesh, GeometryError> {
    let h = DVec3::new(
        positive("half_extents.x", half_extents.x)?,
        positive("half_extents.y", half_extents.y)?,
        positive("half_extents.z", half_extents.z)?,
    );
    Ok(box_raw(h))
}

/// A closed cylinder of `radius` around the z axis, spanning z ∈ [-half_height, half_height],
/// its circles approximated by `segments` (≥ 3) inscribed polygon sides; caps are triangle
/// fans around a centre vertex.
pub fn cylinder(radius: f32, half_height: f32, segments: u32) -> Result<Mesh, GeometryError> {
    let r = positive("radius", radius)?;
    let hh = positive("half_height", half_height)?;
    let n = resolution("segments", segments, 3)?;
    Ok(cylinder_raw(r, hh, n))
}

/// A closed cone around the z axis: base circle of `radius` at z = -half_height, apex at
/// z = +half_height; `segments` (≥ 3) sides.
pub fn cone(radius: f32, half_height: f32, segments: u32) -> Result<Mesh, GeometryError> {
    let r = positive("radius", radius)?;
    let hh = positive("half_height", half_height)?;
    let n = resolution("segments", segments, 3)?;
    Ok(cone_raw(r, hh, n))
}

/// A torus around the z axis: the tube of radius `minor` follows a circle of radius `major` in
/// the xy-plane. Requires `major > minor > 0` (no self-intersection), `major_segments ≥ 3`
/// around the z axis and `minor_segments ≥ 3` around the tube.
pub fn torus(
    major: f32,
    minor: f32,
    major_segments: u32,
    minor_segments: u32,
) -> Result<Mesh, GeometryError> {
    let big = positive("major", major)?;
    let small = positive("minor", minor)?;
    if small >= big {
        return Err(GeometryError::InvalidParameter {
            name: "minor",
            message: format!("must be smaller than major ({major}), got {minor}"),
        });
    }
    let nu = resolution("major_segments", major_segments, 3)?;
    let nv = resolution("minor_segments", minor_segments, 3)?;
    Ok(torus_raw(big, small, nu, nv))
}

/// A capsule around the z axis: a cylinder of `radius` over z ∈ [-half_height, half_height]
/// closed by two hemispheres, so it spans z ∈ [-half_height − radius, half_height + radius].
/// `half_height` may be 0 (a sphere). `segments ≥ 3` around the axis, `rings ≥ 1` latitude
/// bands per hemisphere.
pub fn capsule(
    radius: f32,
    half_height: f32,
    segments: u32,
    rings: u32,
) -> Result<Mesh, GeometryError> {
    let r = positive("radius", radius)?;
    let hh = non_negative("half_height", half_height)?;
    let n = resolution("segments", segments, 3)?;
    let m = resolution("rings", rings, 1)?;
    Ok(capsule_raw(r, hh, n, m))
}

/// A superquadric (superellipsoid) with radii `a` along x, y, z and shape exponents `e1`
/// (north–south, along z) and `e2` (east–west, in the xy-plane), both in (0, 10]:
/// `p(η, ω) = (a.x·c(η)^e1·c(ω)^e2, a.y·c(η)^e1·s(ω)^e2, a.z·s(η)^e1)` with signed powers.
/// `e = 1` gives an ellipsoid, `e → 0` a box, `e = 2` an octahedron, `e > 2` pinched stars.
/// Sampled on a uniform (η, ω) grid: `segments ≥ 3` around z, `rings ≥ 2` latitude bands
/// (poles included as single vertices).
pub fn superquadric(
    a: Vec3,
    e1: f32,
    e2: f32,
    segments: u32,
    rings: u32,
) -> Result<Mesh, GeometryError> {
    let radii = DVec3::new(
        positive("a.x", a.x)?,
        positive("a.y", a.y)?,
        positive("a.z", a.z)?,
    );
    let e1 = positive("e1", e1)?;
    let e2 = positive("e2", e2)?;
    for (name, e) in [("e1", e1), ("e2", e2)] {
        if e > 10.0 {
            return Err(GeometryError::InvalidParameter {
                name,
                message: format!("must be ≤ 10, got {e}"),
            });
        }
    }
    let n = resolution("segments", segments, 3)?;
    let m = resolution("rings", rings, 2)?;
    Ok(superquadric_raw(radii, e1, e2, n, m))
}

/// A UV sphere of `radius`: `segments ≥ 3` meridian sides, `rings ≥ 2` latitude bands, a single
/// vertex at each pole (z = ±radius).
pub fn sphere(radius: f32, segments: u32, rings: u32) -> Result<Mesh, GeometryError> {
    let r = positive("radius", radius)?;
    let n = resolution("segments", segments, 3)?;
    let m = resolution("rings", rings, 2)?;
    Ok(sphere_raw(r, n, m))
}

/// A geodesic sphere of `radius`: an icosahedron whose triangles are split into four
/// `subdivisions` times (0..=[`MAX_SUBDIVISIONS`]), vertices pushed onto the sphere;
/// `20·4^subdivisions` near-equal triangles.
pub fn icosphere(radius: f32, subdivisions: u32) -> Result<Mesh, GeometryError> {
    let r = positive("radius", radius)?;
    if subdivisions > MAX_SUBDIVISIONS {
        return Err(GeometryError::InvalidParameter {
            name: "subdivisions",
            message: format!("must be ≤ {MAX_SUBDIVISIONS}, got {subdivisions}"),
        });
    }
    Ok(icosphere_raw(r, subdivisions))
}

// ---------------------------------------------------------------------------------------------
// Composites
// ---------------------------------------------------------------------------------------------

/// The families of seeded composite objects. Each is assembled from primitives whose
/// proportions are drawn from the seed; parts interpenetrate (the union is not re-meshed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CompositeKind {
    /// A box top on four box or cylinder legs.
    Table,
    /// A seat on four legs with a backrest, sometimes armrests.
    Chair,
    /// A cylindrical body with a torus handle partly sunk into it.
    Mug,
    /// An L-shaped pair of plates with a diagonal gusset and bolt heads.
    Bracket,
    /// A disc base, a pole, a tilted arm and a conical shade.
    Lamp,
    /// A cylindrical (or capsule) body, conical shoulder, neck and cap.
    Bottle,
}

impl CompositeKind {
    /// Every kind, in declaration order.
    pub const ALL: [CompositeKind; 6] = [
        CompositeKind::Table,
        CompositeKind::Chair,
        CompositeKind::Mug,
        CompositeKind::Bracket,
        CompositeKind::Lamp,
        CompositeKind::Bottle,
    ];
}

/// Resolution used for the curved parts of composites.
const COMPOSITE_SEGMENTS: usize = 32;

/// Appends `part` moved by `pose` to `into`.
fn put(into: &mut Mesh, part: Mesh, pose: Pose) {
    into.append(&part.transformed(&pose));
}

fn at(x: f64, y: f64, z: f64) -> Pose {
    Pose::from_translation(DVec3::new(x, y, z))
}

/// Rotation that maps +z onto `dir` (unit or not), then translation to `centre`.
fn along(dir: DVec3, centre: DVec3) -> Pose {
    let d = dir.normalize();
    let axis = DVec3::Z.cross(d);
    let angle = DVec3::Z.dot(d).clamp(-1.0, 1.0).acos();
    if axis.length() < 1e-12 {
        // Parallel or anti-parallel: rotate about x when anti-parallel.
        return Pose::from_axis_angle(DVec3::X, if d.z < 0.0 { PI } else { 0.0 }, centre);
    }
    Pose::from_axis_angle(axis, angle, centre)
}

/// A cylinder spanning the segment `p → q` with radius `r`.
fn rod(into: &mut Mesh, p: DVec3, q: DVec3, r: f64) {
    let half = 0.5 * (q - p).length();
    put(
        into,
        cylinder_raw(r, half, COMPOSITE_SEGMENTS),
        along(q - p, 0.5 * (p + q)),
    );
}

fn range(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    rng.random_range(lo..hi)
}

/// Table top half-sizes and legs (z up, floor at z = 0).
fn build_table(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let (w, d) = (range(rng, 0.5, 1.0), range(rng, 0.3, 0.8));
    let t = range(rng, 0.02, 0.06);
    let h = range(rng, 0.4, 0.9);
    put(&mut m, box_raw(DVec3::new(w, d, t)), at(0.0, 0.0, h - t));
    let inset = range(rng, 0.05, 0.25);
    let (lx, ly) = (w * (1.0 - inset), d * (1.0 - inset));
    let round_legs = rng.random_bool(0.5);
    let leg = range(rng, 0.02, 0.06);
    // Legs reach half-way into the top: the parts interpenetrate.
    let leg_half = 0.5 * (h - t);
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        let part = if round_legs {
            cylinder_raw(leg, leg_half, COMPOSITE_SEGMENTS)
        } else {
            box_raw(DVec3::new(leg, leg, leg_half))
        };
        put(&mut m, part, at(sx * lx, sy * ly, leg_half));
    }
    if rng.random_bool(0.4) {
        // A stretcher between the legs along x.
        let z = range(rng, 0.15, 0.4) * h;
        rod(
            &mut m,
            DVec3::new(-lx, 0.0, z),
            DVec3::new(lx, 0.0, z),
            0.6 * leg,
        );
        rod(
            &mut m,
            DVec3::new(-lx, -ly, z),
            DVec3::new(-lx, ly, z),
            0.6 * leg,
        );
        rod(
            &mut m,
            DVec3::new(lx, -ly, z),
            DVec3::new(lx, ly, z),
            0.6 * leg,
        );
    }
    m
}

fn build_chair(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let (w, d) = (range(rng, 0.2, 0.3), range(rng, 0.2, 0.3));
    let t = range(rng, 0.02, 0.04);
    let seat_z = range(rng, 0.35, 0.5);
    put(&mut m, box_raw(DVec3::new(w, d, t)), at(0.0, 0.0, seat_z));
    let leg = range(rng, 0.015, 0.03);
    let leg_half = 0.5 * seat_z;
    let round_legs = rng.random_bool(0.5);
    for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
        let (x, y) = (sx * (w - leg), sy * (d - leg));
        let part = if round_legs {
            cylinder_raw(leg, leg_half, COMPOSITE_SEGMENTS)
        } else {
            box_raw(DVec3::new(leg, leg, leg_half))
        };
        put(&mut m, part, at(x, y, leg_half));
    }
    // Backrest at -y, slightly tilted backwards, sunk into the seat.
    let back_h = range(rng, 0.2, 0.45);
    let back_t = range(rng, 0.015, 0.03);
    let tilt = range(rng, 0.0, 0.25);
    let back = box_raw(DVec3::new(w, back_t, 0.5 * back_h));
    let centre = DVec3::new(
        0.0,
        -d + back_t - 0.5 * back_h * tilt.sin(),
        seat_z + 0.5 * back_h * tilt.cos(),
    );
    put(&mut m, back, Pose::from_axis_angle(DVec3::X, tilt, centre));
    if rng.random_bool(0.35) {
        // Armrests: posts and bars on both sides.
        let arm_h = range(rng, 0.12, 0.25);
        for sx in [-1.0, 1.0] {
            let x = sx * (w - leg);
            rod(
                &mut m,
                DVec3::new(x, d - 2.0 * leg, seat_z),
                DVec3::new(x, d - 2.0 * leg, seat_z + arm_h),
                leg,
            );
            put(
                &mut m,
                box_raw(DVec3::new(1.5 * leg, d, leg)),
                at(x, 0.0, seat_z + arm_h),
            );
        }
    }
    m
}

fn build_mug(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let r = range(rng, 0.3, 0.5);
    let hh = range(rng, 0.35, 0.6);
    put(
        &mut m,
        cylinder_raw(r, hh, 2 * COMPOSITE_SEGMENTS),
        Pose::IDENTITY,
    );
    // Handle: a torus in the xz-plane (axis along y), its inner part inside the body.
    let big = range(rng, 0.45, 0.8) * hh;
    let small = range(rng, 0.12, 0.25) * big;
    let sink = range(rng, 0.2, 0.5);
    let handle = torus_raw(big, small, COMPOSITE_SEGMENTS, COMPOSITE_SEGMENTS / 2);
    let z = range(rng, -0.2, 0.2) * hh;
    // Its inner side reaches `sink·big` inside the body wall.
    put(
        &mut m,
        handle,
        Pose::from_axis_angle(
            DVec3::X,
            PI / 2.0,
            DVec3::new(r + big * (1.0 - sink), 0.0, z),
        ),
    );
    if rng.random_bool(0.5) {
        // A foot ring.
        let foot = cylinder_raw(r * range(rng, 0.7, 0.95), 0.04 * hh, 2 * COMPOSITE_SEGMENTS);
        put(&mut m, foot, at(0.0, 0.0, -hh));
    }
    m
}

fn build_bracket(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let len_x = range(rng, 0.4, 0.8);
    let len_z = range(rng, 0.3, 0.7);
    let width = range(rng, 0.15, 0.4);
    let t = range(rng, 0.02, 0.06);
    // Base plate along +x, upright plate along +z; they share the corner region.
    put(
        &mut m,
        box_raw(DVec3::new(0.5 * len_x, width, t)),
        at(0.5 * len_x, 0.0, t),
    );
    put(
        &mut m,
        box_raw(DVec3::new(t, width, 0.5 * len_z)),
        at(t, 0.0, 0.5 * len_z),
    );
    // Diagonal gusset in the middle.
    if rng.random_bool(0.7) {
        let g = range(rng, 0.3, 0.6) * len_x.min(len_z);
        let diag = std::f64::consts::SQRT_2 * g;
        let gusset = box_raw(DVec3::new(0.5 * diag, 0.3 * t + 0.01, t));
        put(
            &mut m,
            gusset,
            Pose::from_axis_angle(DVec3::Y, -PI / 4.0, DVec3::new(0.5 * g, 0.0, 0.5 * g)),
        );
    }
    // Bolt heads: short cylinders through the plates.
    let bolts = rng.random_range(1..=3);
    let bolt_r = range(rng, 0.02, 0.045);
    for i in 0..bolts {
        let f = (i as f64 + 1.0) / (bolts as f64 + 1.0);
        let y = if bolts == 1 {
            0.0
        } else {
            range(rng, -0.5, 0.5) * width
        };
        put(
            &mut m,
            cylinder_raw(bolt_r, 1.6 * t, COMPOSITE_SEGMENTS),
            at(0.3 * len_x + 0.6 * len_x * f, y, t),
        );
        let bolt = cylinder_raw(bolt_r, 1.6 * t, COMPOSITE_SEGMENTS);
        put(
            &mut m,
            bolt,
            along(DVec3::X, DVec3::new(t, -y, 0.3 * len_z + 0.6 * len_z * f)),
        );
    }
    m
}

fn build_lamp(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let base_r = range(rng, 0.15, 0.3);
    let base_t = range(rng, 0.02, 0.05);
    put(
        &mut m,
        cylinder_raw(base_r, base_t, 2 * COMPOSITE_SEGMENTS),
        at(0.0, 0.0, base_t),
    );
    let pole_r = range(rng, 0.012, 0.03);
    let pole_h = range(rng, 0.4, 0.9);
    let top = DVec3::new(0.0, 0.0, pole_h);
    rod(&mut m, DVec3::new(0.0, 0.0, base_t), top, pole_r);
    put(
        &mut m,
        sphere_raw(1.8 * pole_r, 16, 8),
        Pose::from_translation(top),
    );
    // Arm: tilted up or down from the pole top.
    let arm_len = range(rng, 0.15, 0.4);
    let arm_angle = range(rng, -0.6, 0.6);
    let azimuth = range(rng, 0.0, TAU);
    let dir = DVec3::new(
        arm_angle.cos() * azimuth.cos(),
        arm_angle.cos() * azimuth.sin(),
        arm_angle.sin(),
    );
    let end = top + arm_len * dir;
    rod(&mut m, top, end, 0.8 * pole_r);
    // Shade: a cone opening downwards, apex near the arm end (inside the joint sphere).
    let shade_r = range(rng, 0.08, 0.2);
    let shade_hh = range(rng, 0.06, 0.15);
    let tilt = range(rng, 0.0, 0.5);
    let shade_dir = (DVec3::new(dir.x, dir.y, 0.0).normalize_or_zero() * tilt.sin()
        - DVec3::Z * tilt.cos())
    .normalize();
    // The cone's +z axis (apex side) points against the opening direction.
    let shade_centre = end + shade_dir * (shade_hh * 0.9);
    put(
        &mut m,
        cone_raw(shade_r, shade_hh, COMPOSITE_SEGMENTS),
        along(-shade_dir, shade_centre),
    );
    put(
        &mut m,
        sphere_raw(1.5 * pole_r, 16, 8),
        Pose::from_translation(end),
    );
    m
}

fn build_bottle(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = Mesh::default();
    let r = range(rng, 0.15, 0.35);
    let body_hh = range(rng, 0.3, 0.6);
    if rng.random_bool(0.3) {
        // Rounded body.
        let hh = (body_hh - r).max(0.05);
        put(
            &mut m,
            capsule_raw(r, hh, 2 * COMPOSITE_SEGMENTS, 8),
            at(0.0, 0.0, hh + r),
        );
    } else {
        put(
            &mut m,
            cylinder_raw(r, body_hh, 2 * COMPOSITE_SEGMENTS),
            at(0.0, 0.0, body_hh),
        );
    }
    let body_top = 2.0 * body_hh;
    // Shoulder: a cone on the body (its lowest part sunk into it).
    let shoulder_hh = range(rng, 0.08, 0.25);
    put(
        &mut m,
        cone_raw(r, shoulder_hh, 2 * COMPOSITE_SEGMENTS),
        at(0.0, 0.0, body_top + shoulder_hh - 0.01),
    );
    // Neck through the cone's apex, and a cap.
    let neck_r = range(rng, 0.25, 0.45) * r;
    let neck_hh = range(rng, 0.05, 0.15);
    let neck_z = body_top + 2.0 * shoulder_hh - 0.3 * shoulder_hh + neck_hh;
    put(
        &mut m,
        cylinder_raw(neck_r, neck_hh + 0.3 * shoulder_hh, COMPOSITE_SEGMENTS),
        at(0.0, 0.0, neck_z - 0.3 * shoulder_hh),
    );
    let cap_hh = range(rng, 0.02, 0.05);
    put(
        &mut m,
        cylinder_raw(neck_r * 1.15, cap_hh, COMPOSITE_SEGMENTS),
        at(0.0, 0.0, neck_z + neck_hh),
    );
    m
}

/// Centres the bounding box at the origin and scales the longest side to [-1, 1].
fn normalised(mut mesh: Mesh) -> Mesh {
    // Cannot fail: every builder produces vertices with a positive extent.
    let _ = mesh.normalise();
    mesh
}

/// A seeded composite object of the given `kind`, z up, normalised (bounding box centred at the
/// origin, longest side spanning [-1, 1]). The same `(kind, seed)` always gives the identical
/// mesh. Parts are closed primitives that interpenetrate; the mesh is the concatenation of the
/// parts, so every edge still belongs to exactly two triangles, but some faces lie inside the
/// object (see [`crate::sampling::sample_visible_surface`]).
pub fn composite(kind: CompositeKind, seed: u64) -> Mesh {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mesh = match kind {
        CompositeKind::Table => build_table(&mut rng),
        CompositeKind::Chair => build_chair(&mut rng),
        CompositeKind::Mug => build_mug(&mut rng),
        CompositeKind::Bracket => build_bracket(&mut rng),
        CompositeKind::Lamp => build_lamp(&mut rng),
        CompositeKind::Bottle => build_bottle(&mut rng),
    };
    normalised(mesh)
}

/// A superquadric with random radii and exponents, then tapered, bent and twisted along z.
/// Every deformation is an orientation-preserving bijection of space, so the surface stays
/// closed, outward-oriented and free of self-intersections.
fn deformed_superquadric(rng: &mut ChaCha8Rng) -> Mesh {
    let a = DVec3::new(
        range(rng, 0.3, 1.0),
        range(rng, 0.3, 1.0),
        range(rng, 0.3, 1.0),
    );
    let (e1, e2) = (range(rng, 0.25, 1.6), range(rng, 0.25, 1.6));
    let mut m = superquadric_raw(a, e1, e2, 64, 32);
    let taper = range(rng, -0.6, 0.6); // scale factor 1 + taper·z/a.z ∈ [0.4, 1.6]
    let bend = range(rng, -0.5, 0.5); // x shift by bend·z²
    let twist = range(rng, -1.5, 1.5); // radians per unit z
    for v in &mut m.vertices {
        let p = v.as_dvec3();
        let s = 1.0 + taper * p.z / a.z;
        let (x, y) = (p.x * s, p.y * s);
        let (sin, cos) = (twist * p.z).sin_cos();
        let (x, y) = (cos * x - sin * y, sin * x + cos * y);
        *v = DVec3::new(x + bend * p.z * p.z, y, p.z).as_vec3();
    }
    m
}

/// A star-shaped blob: an icosphere whose radius varies with direction as
/// `1 + Σ bumps` (Gaussian bumps on the sphere), clamped to stay positive, then scaled
/// anisotropically. Star-shaped radial graphs never self-intersect.
fn blob(rng: &mut ChaCha8Rng) -> Mesh {
    let mut m = icosphere_raw(1.0, 4);
    let bumps: Vec<(DVec3, f64, f64)> = (0..rng.random_range(3..9))
        .map(|_| {
            let z = range(rng, -1.0, 1.0);
            let phi = range(rng, 0.0, TAU);
            let s = (1.0 - z * z).sqrt();
            let centre = DVec3::new(s * phi.cos(), s * phi.sin(), z);
            (centre, range(rng, -0.35, 0.7), range(rng, 0.1, 0.5))
        })
        .collect();
    let scale = DVec3::new(
        range(rng, 0.5, 1.0),
        range(rng, 0.5, 1.0),
        range(rng, 0.5, 1.0),
    );
    for v in &mut m.vertices {
        let d = v.as_dvec3().normalize();
        let r: f64 = 1.0
            + bumps
                .iter()
                .map(|(c, amp, w)| amp * (-(1.0 - d.dot(*c)) / w).exp())
                .sum::<f64>();
        *v = (d * r.max(0.3) * scale).as_vec3();
    }
    m
}

/// An object from an unlimited seeded stream: a [`composite`] of a random kind (6 in 8 cases),
/// a randomly deformed superquadric (1 in 8) or a star-shaped bumpy blob (1 in 8). Normalised
/// like [`composite`]; the same seed gives the identical mesh.
pub fn random_object(seed: u64) -> Mesh {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pick = rng.random_range(0..8usize);
    let sub_seed: u64 = rng.random();
    match pick {
        0..=5 => composite(CompositeKind::ALL[pick], sub_seed),
        6 => normalised(deformed_superquadric(&mut ChaCha8Rng::seed_from_u64(
            sub_seed,
        ))),
        _ => normalised(blob(&mut ChaCha8Rng::seed_from_u64(sub_seed))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every directed edge appears exactly once and its reverse exactly once: closed, manifold
    /// in the edge sense and consistently oriented.
    fn assert_closed(m: &Mesh, what: &str) {
        let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &m.triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        for (&(a, b), &n) in &edges {
            assert_eq!(n, 1, "{what}: directed edge {a}→{b} used {n} times");
            assert_eq!(
                edges.get(&(b, a)),
                Some(&1),
                "{what}: edge {a}→{b} has no opposite"
            );
        }
        m.validate().unwrap();
    }

    fn signed_volume(m: &Mesh) -> f64 {
        (0..m.triangles.len())
            .map(|i| {
                let [a, b, c] = m.triangle(i);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    fn assert_volume(m: &Mesh, expected: f64, rel: f64, what: &str) {
        let v = signed_volume(m);
        assert!(
            v > 0.0,
            "{what}: signed volume {v} ≤ 0 (inward orientation)"
        );
        assert!(
            (v - expected).abs() <= rel * expected,
            "{what}: volume {v} vs analytic {expected} (rel tol {rel})"
        );
    }

    fn assert_bounds(m: &Mesh, min: DVec3, max: DVec3, tol: f64, what: &str) {
        let b = m.bounds().unwrap();
        assert!(
            b.min.abs_diff_eq(min, tol) && b.max.abs_diff_eq(max, tol),
            "{what}: bounds {b:?} vs {min}..{max}"
        );
    }

    #[test]
    fn primitives_are_closed_and_consistently_oriented() {
        let shapes = [
            ("box", box_mesh(Vec3::new(1.0, 2.0, 3.0)).unwrap()),
            ("cylinder", cylinder(1.0, 2.0, 7).unwrap()),
            ("cone", cone(1.0, 2.0, 3).unwrap()),
            ("torus", torus(2.0, 0.5, 12, 5).unwrap()),
            ("capsule", capsule(0.5, 1.0, 9, 3).unwrap()),
            ("capsule h=0", capsule(0.5, 0.0, 9, 1).unwrap()),
            (
                "superquadric",
                superquadric(Vec3::new(1.0, 2.0, 0.5), 0.3, 1.7, 16, 9).unwrap(),
            ),
            ("sphere", sphere(1.0, 5, 2).unwrap()),
            ("icosphere 0", icosphere(1.0, 0).unwrap()),
            ("icosphere 3", icosphere(1.0, 3).unwrap()),
        ];
        for (what, m) in &shapes {
            assert_closed(m, what);
            assert!(signed_volume(m) > 0.0, "{what}: inward orientation");
            // Every face normal points away from the centre for these star-shaped solids
            // (except faces through the origin, which the torus does not have).
            if *what != "torus" && !what.starts_with("superquadric") {
                for (i, n) in m.face_normals().iter().enumerate() {
                    let [a, b, c] = m.triangle(i);
                    assert!(
                        n.as_dvec3().dot((a + b + c) / 3.0) > 0.0,
                        "{what}: face {i} points inwards"
                    );
                }
            }
        }
        assert_eq!(icosphere(1.0, 3).unwrap().triangles.len(), 20 * 64);
        assert_eq!(icosphere(1.0, 3).unwrap().vertices.len(), 642);
    }

    #[test]
    fn volumes_match_analytic_values() {
        assert_volume(
            &box_mesh(Vec3::new(1.0, 2.0, 3.0)).unwrap(),
            48.0,
            1e-12,
            "box",
        );
        assert_volume(&cylinder(1.0, 2.0, 64).unwrap(), PI * 4.0, 0.01, "cylinder");
        assert_volume(&cone(1.0, 1.5, 64).unwrap(), PI * 3.0 / 3.0, 0.01, "cone");
        assert_volume(
            &sphere(2.0, 64, 32).unwrap(),
            4.0 / 3.0 * PI * 8.0,
            0.01,
            "uv sphere",
        );
        assert_volume(
            &icosphere(2.0, 4).unwrap(),
            4.0 / 3.0 * PI * 8.0,
            0.01,
            "icosphere",
        );
        assert_volume(
            &torus(2.0, 0.5, 64, 32).unwrap(),
            2.0 * PI * PI * 2.0 * 0.25,
            0.02,
            "torus",
        );
        assert_volume(
            &capsule(0.5, 1.0, 64, 16).unwrap(),
            PI * 0.25 * 2.0 + 4.0 / 3.0 * PI * 0.125,
            0.01,
            "capsule",
        );
        // Superquadric with e1 = e2 = 1 is an ellipsoid.
        assert_volume(
            &superquadric(Vec3::new(1.0, 2.0, 0.5), 1.0, 1.0, 64, 32).unwrap(),
            4.0 / 3.0 * PI,
            0.01,
            "ellipsoid",
        );
        // Small exponents approach the box 2a × 2b × 2c; e = 0.1: within 10 %.
        let v = signed_volume(&superquadric(Vec3::new(1.0, 2.0, 0.5), 0.1, 0.1, 128, 64).unwrap());
        assert!(
            v > 0.85 * 8.0 && v < 8.0,
            "near-box superquadric volume {v}"
        );
    }

    #[test]
    fn bounding_boxes_are_as_documented() {
        let h = DVec3::new(1.0, 2.0, 3.0);
        assert_bounds(&box_mesh(h.as_vec3()).unwrap(), -h, h, 0.0, "box");
        assert_bounds(
            &cylinder(1.0, 2.0, 64).unwrap(),
            DVec3::new(-1.0, -1.0, -2.0),
            DVec3::new(1.0, 1.0, 2.0),
            2e-3,
            "cylinder",
        );
        assert_bounds(
            &cone(1.0, 2.0, 64).unwrap(),
            DVec3::new(-1.0, -1.0, -2.0),
            DVec3::new(1.0, 1.0, 2.0),
            2e-3,
            "cone",
        );
        assert_bounds(
            &torus(2.0, 0.5, 64, 32).unwrap(),
            DVec3::new(-2.5, -2.5, -0.5),
            DVec3::new(2.5, 2.5, 0.5),
            2e-3,
            "torus",
        );
        assert_bounds(
            &capsule(0.5, 1.0, 64, 16).unwrap(),
            DVec3::new(-0.5, -0.5, -1.5),
            DVec3::new(0.5, 0.5, 1.5),
            2e-3,
            "capsule",
        );
        assert_bounds(
            &sphere(2.0, 64, 32).unwrap(),
            DVec3::splat(-2.0),
            DVec3::splat(2.0),
            5e-3,
            "sphere",
        );
        assert_bounds(
            &icosphere(2.0, 4).unwrap(),
            DVec3::splat(-2.0),
            DVec3::splat(2.0),
            0.02,
            "icosphere",
        );
        let a = DVec3::new(1.0, 2.0, 0.5);
        assert_bounds(
            &superquadric(a.as_vec3(), 0.5, 0.5, 64, 32).unwrap(),
            -a,
            a,
            5e-3,
            "superquadric",
        );
        for v in icosphere(2.0, 2).unwrap().vertices {
            assert!((v.length() - 2.0).abs() < 1e-5);
        }
    }

    #[test]
    fn bad_parameters_are_errors_not_panics() {
        let bad = |r: Result<Mesh, GeometryError>, name: &str| match r {
            Err(GeometryError::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
            other => panic!("expected InvalidParameter({name}), got {other:?}"),
        };
        bad(box_mesh(Vec3::new(1.0, 0.0, 1.0)), "half_extents.y");
        bad(box_mesh(Vec3::new(f32::NAN, 1.0, 1.0)), "half_extents.x");
        bad(cylinder(-1.0, 1.0, 8), "radius");
        bad(cylinder(1.0, 1.0, 2), "segments");
        bad(cylinder(1.0, f32::INFINITY, 8), "half_height");
        bad(cone(1.0, 0.0, 8), "half_height");
        bad(torus(1.0, 1.0, 8, 8), "minor");
        bad(torus(2.0, 1.0, 8, 2), "minor_segments");
        bad(capsule(1.0, -0.1, 8, 2), "half_height");
        bad(capsule(1.0, 1.0, 8, 0), "rings");
        bad(superquadric(Vec3::ONE, 0.0, 1.0, 8, 8), "e1");
        bad(superquadric(Vec3::ONE, 1.0, 11.0, 8, 8), "e2");
        bad(
            superquadric(Vec3::new(1.0, 1.0, -1.0), 1.0, 1.0, 8, 8),
            "a.z",
        );
        bad(sphere(1.0, 8, 1), "rings");
        bad(sphere(1.0, MAX_SEGMENTS + 1, 8), "segments");
        bad(icosphere(0.0, 1), "radius");
        bad(icosphere(1.0, MAX_SUBDIVISIONS + 1), "subdivisions");
    }

    #[test]
    fn composites_are_seeded_normalised_and_closed() {
        for kind in CompositeKind::ALL {
            for seed in 0..8 {
                let m = composite(kind, seed);
                assert_eq!(
                    m,
                    composite(kind, seed),
                    "{kind:?} {seed} not deterministic"
                );
                assert_closed(&m, &format!("{kind:?} {seed}"));
                assert!(signed_volume(&m) > 0.0);
                let b = m.bounds().unwrap();
                assert!(
                    b.centre().abs().max_element() < 1e-5,
                    "{kind:?} {seed}: centre {}",
                    b.centre()
                );
                assert!(
                    (b.extent().max_element() - 2.0).abs() < 1e-5,
                    "{kind:?} {seed}: extent {}",
                    b.extent()
                );
            }
            assert_ne!(
                composite(kind, 1),
                composite(kind, 2),
                "{kind:?}: seeds give the same mesh"
            );
        }
    }

    #[test]
    fn random_objects_are_seeded_diverse_and_closed() {
        let mut sizes = std::collections::HashSet::new();
        for seed in 0..40 {
            let m = random_object(seed);
            assert_eq!(m, random_object(seed));
            assert_closed(&m, &format!("random_object({seed})"));
            assert!(signed_volume(&m) > 0.0, "random_object({seed}) inward");
            let b = m.bounds().unwrap();
            assert!((b.extent().max_element() - 2.0).abs() < 1e-5);
            sizes.insert(m.triangles.len());
        }
        assert!(
            sizes.len() >= 8,
            "only {} distinct triangle counts in 40 objects",
            sizes.len()
        );
    }

    #[test]
    fn random_shapes_keep_every_face_outward() {
        for seed in 0..10 {
            let m = deformed_superquadric(&mut ChaCha8Rng::seed_from_u64(seed));
            assert_closed(&m, "deformed superquadric");
            assert!(signed_volume(&m) > 0.0);
            // A radial graph over the icosphere: every face, seen from the origin, keeps the
            // icosphere's counter-clockwise order, i.e. its tetrahedron with the origin has
            // positive volume.
            let b = blob(&mut ChaCha8Rng::seed_from_u64(seed));
            assert_closed(&b, "blob");
            for i in 0..b.triangles.len() {
                let [p, q, r] = b.triangle(i);
                assert!(p.dot(q.cross(r)) > 0.0, "blob {seed}: face {i} inverted");
            }
        }
    }
}
