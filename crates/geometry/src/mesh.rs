//! The triangle mesh type.
//!
//! Vertices are `f32` ([`glam::Vec3`]): that is what renderers and networks consume, and 24-bit
//! mantissas give ≈ 1e-7 relative precision, far below sensor noise. Computations that
//! accumulate (areas, normalisation, Procrustes) run in f64.

use glam::{DVec3, Vec3};

use crate::{MeshDataError, Pose};

/// A triangle mesh: vertex positions and counter-clockwise triangles (indices into `vertices`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

/// An axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    /// The box around `points`, or `None` when there are none.
    pub fn from_points(points: impl IntoIterator<Item = Vec3>) -> Option<Aabb> {
        let mut it = points.into_iter();
        let first = it.next()?.as_dvec3();
        Some(it.fold(
            Aabb {
                min: first,
                max: first,
            },
            |b, p| {
                let p = p.as_dvec3();
                Aabb {
                    min: b.min.min(p),
                    max: b.max.max(p),
                }
            },
        ))
    }
    pub fn centre(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }
    pub fn extent(&self) -> DVec3 {
        self.max - self.min
    }
    /// Length of the diagonal.
    pub fn diagonal(&self) -> f64 {
        self.extent().length()
    }
}

/// How a mesh was normalised: `normalised = (original − centre) / scale`.
///
/// `scale` is half the largest bounding-box side, so the normalised mesh spans [-1, 1] on its
/// longest axis and lies inside [-1, 1] on the others.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalisation {
    pub centre: DVec3,
    pub scale: f64,
}

impl Normalisation {
    /// Maps a point from original to normalised units.
    pub fn to_normalised(&self, p: DVec3) -> DVec3 {
        (p - self.centre) / self.scale
    }
    /// Maps a point from normalised to original units.
    pub fn to_original(&self, p: DVec3) -> DVec3 {
        p * self.scale + self.centre
    }
    /// Converts a model→camera pose estimated in normalised units (normalised model, camera
    /// frame scaled by `1/scale`) into the pose of the original model in original units:
    /// `x_cam = R·(x − centre) + scale·t`, i.e. `t' = scale·t − R·centre`.
    pub fn pose_to_original(&self, pose: &Pose) -> Pose {
        Pose::new(
            pose.rotation,
            self.scale * pose.translation - pose.rotation * self.centre,
        )
    }
    /// The inverse of [`Normalisation::pose_to_original`].
    pub fn pose_to_normalised(&self, pose: &Pose) -> Pose {
        Pose::new(
            pose.rotation,
            (pose.translation + pose.rotation * self.centre) / self.scale,
        )
    }
}

impl Mesh {
    /// A validated mesh: at least one vertex and one face, finite coordinates, indices in range.
    pub fn new(vertices: Vec<Vec3>, triangles: Vec<[u32; 3]>) -> Result<Mesh, MeshDataError> {
        let mesh = Mesh {
            vertices,
            triangles,
        };
        mesh.validate()?;
        Ok(mesh)
    }

    /// Checks the invariants that [`Mesh::new`] establishes.
    pub fn validate(&self) -> Result<(), MeshDataError> {
        if self.vertices.is_empty() {
            return Err(MeshDataError::NoVertices);
        }
        if self.triangles.is_empty() {
            return Err(MeshDataError::NoFaces);
        }
        for (vertex, v) in self.vertices.iter().enumerate() {
            if let Some(&value) = v.to_array().iter().find(|c| !c.is_finite()) {
                return Err(MeshDataError::NonFiniteVertex { vertex, value });
            }
        }
        let n = self.vertices.len();
        for (face, t) in self.triangles.iter().enumerate() {
            if let Some(&index) = t.iter().find(|&&i| i as usize >= n) {
                return Err(MeshDataError::IndexOutOfRange {
                    face,
                    index: index as u64,
                    vertex_count: n,
                });
            }
        }
        Ok(())
    }

    /// The three corners of triangle `i`, in f64.
    pub fn triangle(&self, i: usize) -> [DVec3; 3] {
        let [a, b, c] = self.triangles[i];
        [
            self.vertices[a as usize].as_dvec3(),
            self.vertices[b as usize].as_dvec3(),
            self.vertices[c as usize].as_dvec3(),
        ]
    }

    /// The area of every triangle.
    pub fn triangle_areas(&self) -> Vec<f64> {
        (0..self.triangles.len())
            .map(|i| {
                let [a, b, c] = self.triangle(i);
                0.5 * (b - a).cross(c - a).length()
            })
            .collect()
    }

    /// Total surface area.
    pub fn surface_area(&self) -> f64 {
        self.triangle_areas().iter().sum()
    }

    /// Unit face normals (right-hand rule on the triangle order); zero for degenerate faces.
    pub fn face_normals(&self) -> Vec<Vec3> {
        (0..self.triangles.len())
            .map(|i| {
                let [a, b, c] = self.triangle(i);
                (b - a).cross(c - a).normalize_or_zero().as_vec3()
            })
            .collect()
    }

    /// Area-weighted unit vertex normals; zero for vertices only on degenerate faces.
    pub fn vertex_normals(&self) -> Vec<Vec3> {
        let mut acc = vec![DVec3::ZERO; self.vertices.len()];
        for (i, t) in self.triangles.iter().enumerate() {
            let [a, b, c] = self.triangle(i);
            let n = (b - a).cross(c - a); // length = 2·area
            for &v in t {
                acc[v as usize] += n;
            }
        }
        acc.into_iter()
            .map(|n| n.normalize_or_zero().as_vec3())
            .collect()
    }

    /// The bounding box of the vertices (`None` for an empty mesh).
    pub fn bounds(&self) -> Option<Aabb> {
        Aabb::from_points(self.vertices.iter().copied())
    }

    /// Centres the bounding box at the origin and scales uniformly so the longest side spans
    /// [-1, 1]. Returns the transform applied (to report poses in original units).
    pub fn normalise(&mut self) -> Result<Normalisation, MeshDataError> {
        let b = self.bounds().ok_or(MeshDataError::NoVertices)?;
        let half = 0.5 * b.extent().max_element();
        if !(half > 0.0 && half.is_finite()) {
            return Err(MeshDataError::ZeroArea);
        }
        let norm = Normalisation {
            centre: b.centre(),
            scale: half,
        };
        for v in &mut self.vertices {
            *v = norm.to_normalised(v.as_dvec3()).as_vec3();
        }
        Ok(norm)
    }

    /// A copy with every vertex transformed by `pose`.
    pub fn transformed(&self, pose: &Pose) -> Mesh {
        Mesh {
            vertices: pose.apply_all(&self.vertices),
            triangles: self.triangles.clone(),
        }
    }

    /// Appends another mesh (indices shifted).
    pub fn append(&mut self, other: &Mesh) {
        let offset = self.vertices.len() as u32;
        self.vertices.extend_from_slice(&other.vertices);
        self.triangles
            .extend(other.triangles.iter().map(|t| t.map(|i| i + offset)));
    }

    /// Flips the orientation of every triangle.
    pub fn flip_faces(&mut self) {
        for t in &mut self.triangles {
            t.swap(1, 2);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetra() -> Mesh {
        Mesh::new(
            vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(4.0, 0.0, 0.0),
                Vec3::new(0.0, 2.0, 0.0),
                Vec3::new(0.0, 0.0, 1.0),
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap()
    }

    #[test]
    fn validation_names_the_bad_element() {
        assert_eq!(Mesh::new(vec![], vec![]), Err(MeshDataError::NoVertices));
        assert_eq!(
            Mesh::new(vec![Vec3::ZERO], vec![]),
            Err(MeshDataError::NoFaces)
        );
        assert_eq!(
            Mesh::new(vec![Vec3::ZERO; 3], vec![[0, 1, 2], [0, 1, 3]]),
            Err(MeshDataError::IndexOutOfRange {
                face: 1,
                index: 3,
                vertex_count: 3
            })
        );
        assert!(matches!(
            Mesh::new(
                vec![Vec3::ZERO, Vec3::new(0.0, f32::NAN, 0.0), Vec3::ONE],
                vec![[0, 1, 2]]
            ),
            Err(MeshDataError::NonFiniteVertex { vertex: 1, .. })
        ));
    }

    #[test]
    fn normalise_fits_longest_side_to_unit_box_and_round_trips_poses() {
        let mut m = tetra();
        let original = m.clone();
        let n = m.normalise().unwrap();
        let b = m.bounds().unwrap();
        assert!((b.min.x + 1.0).abs() < 1e-6 && (b.max.x - 1.0).abs() < 1e-6);
        assert!(b.min.y >= -1.0 - 1e-6 && b.max.y <= 1.0 + 1e-6);
        assert_eq!(n.scale, 2.0);
        // A pose on the normalised mesh, converted, must move the original mesh to the same
        // camera points (scaled by `scale`).
        let p = Pose::from_axis_angle(DVec3::new(1.0, 1.0, 0.0), 0.7, DVec3::new(0.1, 0.2, 3.0));
        let po = n.pose_to_original(&p);
        for (vn, vo) in m.vertices.iter().zip(&original.vertices) {
            let a = p.apply(vn.as_dvec3()) * n.scale;
            let b = po.apply(vo.as_dvec3());
            assert!(a.abs_diff_eq(b, 1e-5), "{a} vs {b}");
        }
        let back = n.pose_to_normalised(&po);
        assert!(back.translation.abs_diff_eq(p.translation, 1e-12));
    }

    #[test]
    fn area_and_normals_of_a_right_tetrahedron() {
        let m = tetra();
        // Faces: xy (4·2/2 = 4), xz (4·1/2 = 2), yz (2·1/2 = 1), slanted.
        let a = m.triangle_areas();
        assert!(
            (a[0] - 4.0).abs() < 1e-12 && (a[1] - 2.0).abs() < 1e-12 && (a[2] - 1.0).abs() < 1e-12
        );
        let n = m.face_normals();
        assert!(n[0].abs_diff_eq(Vec3::new(0.0, 0.0, -1.0), 1e-6));
        assert!(n[1].abs_diff_eq(Vec3::new(0.0, -1.0, 0.0), 1e-6));
    }
}
