//! Point clouds: the container, voxel down-sampling and exact-count subsampling.

use glam::Vec3;

use crate::GeometryError;

/// Points with optional per-point normals and colours (same length as `points` when present).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub colors: Option<Vec<[u8; 3]>>,
}

impl PointCloud {
    /// A cloud of bare points.
    pub fn from_points(points: Vec<Vec3>) -> Self {
        PointCloud { points, normals: None, colors: None }
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Checks that attribute arrays match the point count and that every point is finite.
    pub fn validate(&self) -> Result<(), GeometryError> {
        let n = self.points.len();
        if let Some(normals) = &self.normals {
            if normals.len() != n {
                return Err(GeometryError::LengthMismatch { what: "normals vs points", left: normals.len(), right: n });
            }
        }
        if let Some(colors) = &self.colors {
            if colors.len() != n {
                return Err(GeometryError::LengthMismatch { what: "colours vs points", left: colors.len(), right: n });
            }
        }
        check_finite("point cloud", &self.points)
    }

    /// Keeps the points at `indices` (with their attributes), in that order.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        PointCloud {
            points: indices.iter().map(|&i| self.points[i]).collect(),
            normals: self.normals.as_ref().map(|n| indices.iter().map(|&i| n[i]).collect()),
            colors: self.colors.as_ref().map(|c| indices.iter().map(|&i| c[i]).collect()),
        }
    }

    /// Appends another cloud; attributes are kept only when both clouds have them.
    pub fn extend(&mut self, other: &PointCloud) {
        self.points.extend_from_slice(&other.points);
        self.normals = match (self.normals.take(), &other.normals) {
            (Some(mut a), Some(b)) => {
                a.extend_from_slice(b);
                Some(a)
            }
            _ => None,
        };
        self.colors = match (self.colors.take(), &other.colors) {
            (Some(mut a), Some(b)) => {
                a.extend_from_slice(b);
                Some(a)
            }
            _ => None,
        };
    }
}

/// Fails with the index of the first non-finite point.
pub(crate) fn check_finite(what: &'static str, points: &[Vec3]) -> Result<(), GeometryError> {
    match points.iter().position(|p| !p.is_finite()) {
        Some(index) => Err(GeometryError::NonFinitePoint { what, index }),
        None => Ok(()),
    }
}
