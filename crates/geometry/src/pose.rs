//! Rigid transforms SE(3).
//!
//! A [`Pose`] maps points from a source frame into a target frame: `x_target = R·x_source + t`.
//! In this project the source is usually the model (object) frame and the target the camera
//! frame (OpenCV: x right, y down, z forward), in metres or in normalised object units.
//! Everything is f64: rotations are composed and inverted many times and feed Procrustes.
//! In files, `R` is written row-major as a 3×3 array (`{"R": [[..],[..],[..]], "t": [..]}`).

use glam::{DMat3, DQuat, DVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::GeometryError;

/// A rigid transform `x ↦ R·x + t` (rotation `R` proper orthogonal, translation `t`).
///
/// Its serde form is the project's pose format, `{"R": [[..],[..],[..]], "t": [x, y, z]}` with
/// `R` row-major (other keys are ignored on read); reading checks that `R` is a rotation
/// ([`Pose::from_row_major`]) and fails with `invalid rotation: …` otherwise.
///
/// ```
/// use ic_geometry::Pose;
///
/// let p: Pose = serde_json::from_str(r#"{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 2.8]}"#).unwrap();
/// assert_eq!(p.translation.z, 2.8);
/// let e = serde_json::from_str::<Pose>(r#"{"R": [[1, 0, 0], [0, 1, 0], [0, 0, -1]], "t": [0, 0, 0]}"#);
/// assert!(e.unwrap_err().to_string().contains("invalid rotation: det R < 0"));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "PoseFile", into = "PoseFile")]
pub struct Pose {
    pub rotation: DMat3,
    pub translation: DVec3,
}

/// The on-disk form of a pose: row-major `R` and `t`.
#[derive(Serialize, Deserialize)]
struct PoseFile {
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    t: [f64; 3],
}

impl TryFrom<PoseFile> for Pose {
    type Error = GeometryError;
    fn try_from(f: PoseFile) -> Result<Self, GeometryError> {
        Pose::from_row_major(f.r, f.t)
    }
}

impl From<Pose> for PoseFile {
    fn from(p: Pose) -> Self {
        PoseFile {
            r: p.rotation_row_major(),
            t: p.translation.to_array(),
        }
    }
}

impl Default for Pose {
    fn default() -> Self {
        Pose::IDENTITY
    }
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// A pose from a rotation matrix and a translation (the rotation is trusted; see
    /// [`Pose::from_row_major`] for a checked constructor).
    pub fn new(rotation: DMat3, translation: DVec3) -> Self {
        Pose {
            rotation,
            translation,
        }
    }

    /// A pure translation.
    pub fn from_translation(translation: DVec3) -> Self {
        Pose {
            rotation: DMat3::IDENTITY,
            translation,
        }
    }

    /// Rotation by `angle` radians about `axis` (need not be unit length), then translation.
    /// A zero axis gives the identity rotation.
    pub fn from_axis_angle(axis: DVec3, angle: f64, translation: DVec3) -> Self {
        let rotation = match axis.try_normalize() {
            Some(a) => DMat3::from_axis_angle(a, angle),
            None => DMat3::IDENTITY,
        };
        Pose {
            rotation,
            translation,
        }
    }

    /// Rotation from a rotation vector (axis × angle in radians).
    pub fn from_rotation_vector(rotvec: DVec3, translation: DVec3) -> Self {
        Self::from_axis_angle(rotvec, rotvec.length(), translation)
    }

    /// Rotation from a quaternion `(w, x, y, z)`; it is normalised first.
    pub fn from_quaternion(
        w: f64,
        x: f64,
        y: f64,
        z: f64,
        translation: DVec3,
    ) -> Result<Self, GeometryError> {
        let q = DQuat::from_xyzw(x, y, z, w);
        let n = q.length();
        if !n.is_finite() || n < 1e-12 {
            return Err(GeometryError::InvalidRotation(format!(
                "quaternion ({w}, {x}, {y}, {z}) has no direction"
            )));
        }
        Ok(Pose {
            rotation: DMat3::from_quat(q / n),
            translation,
        })
    }

    /// A pose from a row-major rotation and a translation, as written in files. Fails when the
    /// values are not finite or `R` is not a rotation (‖RᵀR − I‖ > 1e-4 or det R < 0).
    pub fn from_row_major(r: [[f64; 3]; 3], t: [f64; 3]) -> Result<Self, GeometryError> {
        if r.iter().flatten().chain(t.iter()).any(|v| !v.is_finite()) {
            return Err(GeometryError::InvalidRotation(
                "R or t holds a non-finite value".into(),
            ));
        }
        let rotation = DMat3::from_cols_array_2d(&r).transpose();
        let err = (rotation.transpose() * rotation - DMat3::IDENTITY)
            .to_cols_array()
            .iter()
            .map(|v| v.abs())
            .fold(0.0, f64::max);
        if err > 1e-4 {
            return Err(GeometryError::InvalidRotation(format!(
                "R is not orthonormal (max |RᵀR − I| = {err:.2e})"
            )));
        }
        if rotation.determinant() < 0.0 {
            return Err(GeometryError::InvalidRotation(
                "det R < 0 (a reflection, not a rotation)".into(),
            ));
        }
        Ok(Pose {
            rotation,
            translation: DVec3::from_array(t),
        })
    }

    /// The rotation as row-major rows `R[i][j]`.
    pub fn rotation_row_major(&self) -> [[f64; 3]; 3] {
        self.rotation.transpose().to_cols_array_2d()
    }

    /// The 4×4 homogeneous matrix, row-major.
    pub fn to_matrix_row_major(&self) -> [[f64; 4]; 4] {
        let r = self.rotation_row_major();
        let t = self.translation;
        [
            [r[0][0], r[0][1], r[0][2], t.x],
            [r[1][0], r[1][1], r[1][2], t.y],
            [r[2][0], r[2][1], r[2][2], t.z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose {
            rotation: self.rotation * other.rotation,
            translation: self.rotation * other.translation + self.translation,
        }
    }

    /// The inverse transform `x ↦ Rᵀ(x − t)`.
    pub fn inverse(&self) -> Pose {
        let rt = self.rotation.transpose();
        Pose {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }

    /// Applies the pose to an f64 point.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.translation
    }

    /// Applies the pose to an f32 point (computed in f64).
    pub fn apply_f32(&self, p: Vec3) -> Vec3 {
        self.apply(p.as_dvec3()).as_vec3()
    }

    /// Applies the rotation only (for directions and normals).
    pub fn rotate_f32(&self, v: Vec3) -> Vec3 {
        (self.rotation * v.as_dvec3()).as_vec3()
    }

    /// Transforms every point.
    pub fn apply_all(&self, points: &[Vec3]) -> Vec<Vec3> {
        points.iter().map(|&p| self.apply_f32(p)).collect()
    }

    /// The rotation angle of `R` in radians, in [0, π].
    pub fn rotation_angle(&self) -> f64 {
        rotation_angle(&self.rotation)
    }

    /// The geodesic angle between the two rotations, arccos((tr(R̂ᵀR) − 1)/2), in radians.
    pub fn rotation_angle_to(&self, other: &Pose) -> f64 {
        rotation_angle(&(self.rotation.transpose() * other.rotation))
    }

    /// The rotation as a unit quaternion `(w, x, y, z)`.
    pub fn quaternion(&self) -> [f64; 4] {
        let q = DQuat::from_mat3(&self.rotation).normalize();
        [q.w, q.x, q.y, q.z]
    }

    /// Re-orthonormalises `R` (nearest rotation through the quaternion), to undo drift after
    /// many compositions.
    pub fn orthonormalised(&self) -> Pose {
        let q = DQuat::from_mat3(&self.rotation).normalize();
        Pose {
            rotation: DMat3::from_quat(q),
            translation: self.translation,
        }
    }
}

/// The rotation angle of a rotation matrix in radians, clamped so rounding never yields NaN.
pub fn rotation_angle(r: &DMat3) -> f64 {
    let c = ((r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0) / 2.0).clamp(-1.0, 1.0);
    // arccos loses precision near 0; use atan2 with the skew part for small angles.
    let s = 0.5
        * DVec3::new(
            r.y_axis.z - r.z_axis.y,
            r.z_axis.x - r.x_axis.z,
            r.x_axis.y - r.y_axis.x,
        )
        .length();
    s.atan2(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compose_with_inverse_is_identity() {
        let p = Pose::from_axis_angle(DVec3::new(1.0, 2.0, -0.5), 1.1, DVec3::new(0.3, -2.0, 5.0));
        let i = p.compose(&p.inverse());
        assert!(i.rotation.abs_diff_eq(DMat3::IDENTITY, 1e-12));
        assert!(i.translation.abs_diff_eq(DVec3::ZERO, 1e-12));
    }

    #[test]
    fn compose_applies_right_operand_first() {
        let a = Pose::from_axis_angle(DVec3::Z, 0.5, DVec3::X);
        let b = Pose::from_axis_angle(DVec3::Y, -0.2, DVec3::new(0.0, 1.0, 2.0));
        let x = DVec3::new(0.1, 0.2, 0.3);
        assert!(
            a.compose(&b)
                .apply(x)
                .abs_diff_eq(a.apply(b.apply(x)), 1e-12)
        );
    }

    #[test]
    fn rotation_angle_matches_axis_angle_including_tiny_and_pi() {
        for &angle in &[
            0.0,
            1e-9,
            1e-4,
            0.7,
            2.0,
            std::f64::consts::PI - 1e-6,
            std::f64::consts::PI,
        ] {
            let p = Pose::from_axis_angle(DVec3::new(0.2, -1.0, 0.4), angle, DVec3::ZERO);
            assert!(
                (p.rotation_angle() - angle).abs() < 1e-7,
                "{angle} vs {}",
                p.rotation_angle()
            );
        }
    }

    #[test]
    fn quaternion_round_trip() {
        let p = Pose::from_axis_angle(DVec3::new(0.3, 0.1, -1.0), 2.5, DVec3::ZERO);
        let [w, x, y, z] = p.quaternion();
        let q = Pose::from_quaternion(w, x, y, z, DVec3::ZERO).unwrap();
        assert!(q.rotation_angle_to(&p) < 1e-9);
        assert!(Pose::from_quaternion(0.0, 0.0, 0.0, 0.0, DVec3::ZERO).is_err());
    }

    #[test]
    fn json_is_row_major() {
        let p = Pose::from_axis_angle(
            DVec3::Z,
            std::f64::consts::FRAC_PI_2,
            DVec3::new(1.0, 2.0, 3.0),
        );
        let json = serde_json::to_value(p).unwrap();
        // Rz(90°): first row is (0, -1, 0).
        let r0: Vec<f64> = json["R"][0]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert!((r0[0]).abs() < 1e-12 && (r0[1] + 1.0).abs() < 1e-12 && r0[2].abs() < 1e-12);
        let back: Pose = serde_json::from_value(json).unwrap();
        assert!(back.rotation.abs_diff_eq(p.rotation, 1e-12));
    }

    #[test]
    fn json_reading_checks_the_rotation_and_names_the_fault() {
        let scaled = r#"{"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0]}"#;
        let e = serde_json::from_str::<Pose>(scaled)
            .unwrap_err()
            .to_string();
        assert!(e.contains("invalid rotation: R is not orthonormal"), "{e}");
        let short = r#"{"R": [[1, 0, 0], [0, 1, 0]], "t": [0, 0, 0]}"#;
        assert!(serde_json::from_str::<Pose>(short).is_err());
        let no_t = r#"{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}"#;
        let e = serde_json::from_str::<Pose>(no_t).unwrap_err().to_string();
        assert!(e.contains("missing field `t`"), "{e}");
        // Written row-major with "R" before "t", as every file of the project holds it.
        let p = Pose::from_translation(DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(
            serde_json::to_string(&p).unwrap(),
            r#"{"R":[[1.0,0.0,0.0],[0.0,1.0,0.0],[0.0,0.0,1.0]],"t":[1.0,2.0,3.0]}"#
        );
    }

    #[test]
    fn from_row_major_rejects_reflections_and_nan() {
        let refl = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        assert!(Pose::from_row_major(refl, [0.0; 3]).is_err());
        let scaled = [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(Pose::from_row_major(scaled, [0.0; 3]).is_err());
        let ident = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(Pose::from_row_major(ident, [f64::NAN, 0.0, 0.0]).is_err());
    }
}
