//! Finite rotation groups that cover SO(3) evenly, and the reference rotation of the paper's
//! viewpoints: the tools of "several rotated copies of the model scored against each other".
//!
//! The pose network is right when the rotation between the model frame and the camera frame
//! lies in the family it was trained on (around [`paper_view_rotation`]). Registering the
//! model in each rotation `G` of a group puts one copy within the group's covering radius of
//! that family; training on views re-expressed in the nearest copy
//! ([`nearest_in_group`]) teaches the network exactly the family the copies need.

use glam::{DMat3, DQuat, DVec3};

use crate::{GeometryError, Pose, Viewpoint};

/// Rotations covering SO(3) evenly: `count` ∈ {1, 12, 24, 60} (identity; the rotation groups
/// of the tetrahedron, the cube and the icosahedron). Row-major rotations as [`Pose`]s with
/// zero translation; the identity is first.
pub fn rotation_group(count: usize) -> Result<Vec<Pose>, GeometryError> {
    let quats: Vec<DQuat> = match count {
        1 => vec![DQuat::IDENTITY],
        12 => tetrahedral(),
        24 => octahedral(),
        60 => icosahedral(),
        other => {
            return Err(GeometryError::InvalidRotation(format!(
                "{other} rotations: expected 1, 12, 24 or 60 (the rotation groups that cover SO(3) evenly)"
            )));
        }
    };
    Ok(quats
        .into_iter()
        .map(|q| Pose::new(DMat3::from_quat(q.normalize()), DVec3::ZERO))
        .collect())
}

/// The 12 rotations of the tetrahedral group: the unit quaternions ±1, ±i, ±j, ±k and
/// (±1 ± i ± j ± k)/2, up to sign.
fn tetrahedral() -> Vec<DQuat> {
    let mut out = vec![
        DQuat::from_xyzw(0.0, 0.0, 0.0, 1.0),
        DQuat::from_xyzw(1.0, 0.0, 0.0, 0.0),
        DQuat::from_xyzw(0.0, 1.0, 0.0, 0.0),
        DQuat::from_xyzw(0.0, 0.0, 1.0, 0.0),
    ];
    for sx in [-0.5, 0.5] {
        for sy in [-0.5, 0.5] {
            for sz in [-0.5, 0.5] {
                out.push(DQuat::from_xyzw(sx, sy, sz, 0.5));
            }
        }
    }
    out
}

/// The 24 rotations of the cube: the tetrahedral group and the 12 quaternions with two
/// non-zero components ±1/√2 (up to sign).
fn octahedral() -> Vec<DQuat> {
    let mut out = tetrahedral();
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let axes = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
    for (a, b) in axes {
        for sb in [-h, h] {
            let mut v = [0.0; 4];
            v[a] = h;
            v[b] = sb;
            // v = (w, x, y, z)
            out.push(DQuat::from_xyzw(v[1], v[2], v[3], v[0]));
        }
    }
    out
}

/// The 60 rotations of the icosahedron: the tetrahedral group and the even permutations of
/// (±φ, ±1, ±1/φ, 0)/2 (up to sign).
fn icosahedral() -> Vec<DQuat> {
    let phi = (1.0 + 5f64.sqrt()) / 2.0;
    let base = [phi / 2.0, 0.5, 1.0 / (2.0 * phi), 0.0];
    let even_perms: [[usize; 4]; 12] = [
        [0, 1, 2, 3],
        [0, 2, 3, 1],
        [0, 3, 1, 2],
        [1, 0, 3, 2],
        [1, 2, 0, 3],
        [1, 3, 2, 0],
        [2, 0, 1, 3],
        [2, 1, 3, 0],
        [2, 3, 0, 1],
        [3, 0, 2, 1],
        [3, 1, 0, 2],
        [3, 2, 1, 0],
    ];
    let mut out = tetrahedral();
    for p in even_perms {
        for s1 in [-1.0, 1.0] {
            for s2 in [-1.0, 1.0] {
                for s3 in [-1.0, 1.0] {
                    let signs = [1.0, s1, s2, s3];
                    let mut v = [0.0; 4];
                    for k in 0..4 {
                        v[p[k]] = base[k] * signs[k];
                    }
                    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]);
                    if !out.iter().any(|o| o.dot(q).abs() > 1.0 - 1e-9) {
                        out.push(q);
                    }
                }
            }
        }
    }
    out
}

/// The rotation of the paper's central viewpoint (elevation 45°, azimuth 44.5°, world +z up),
/// model frame = world frame: the centre of the family of model → camera rotations the shipped
/// networks were trained on.
pub fn paper_view_rotation() -> Pose {
    let vp = Viewpoint {
        elevation_deg: 45.0,
        azimuth_deg: 44.5,
        distance: 1.0,
    };
    let pose = vp
        .camera_pose(DVec3::ZERO)
        .expect("a 45° elevation viewpoint has a look-at pose");
    Pose::new(pose.rotation, DVec3::ZERO)
}

/// The element `G` of `group` for which the model → camera rotation `rotation · G⁻¹` (the
/// rotation a copy of the model turned by `G` is seen in) lies nearest `reference`; returns
/// its index and that angle (radians).
pub fn nearest_in_group(rotation: &Pose, group: &[Pose], reference: &Pose) -> (usize, f64) {
    let mut best = (0, f64::MAX);
    for (i, g) in group.iter().enumerate() {
        let seen = rotation.compose(&g.inverse());
        let angle = seen.rotation_angle_to(reference);
        if angle < best.1 {
            best = (i, angle);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_groups_are_groups_of_distinct_rotations() {
        for n in [1, 12, 24, 60] {
            let set = rotation_group(n).unwrap();
            assert_eq!(set.len(), n);
            for (i, a) in set.iter().enumerate() {
                for b in &set[..i] {
                    assert!(a.rotation_angle_to(b) > 1e-6, "duplicates in the {n}-set");
                }
                // Closed under composition: a·b is in the set.
                for b in &set {
                    let ab = a.compose(b);
                    assert!(
                        set.iter().any(|c| c.rotation_angle_to(&ab) < 1e-6),
                        "the {n}-set is not closed"
                    );
                }
            }
        }
        assert!(rotation_group(7).is_err());
    }

    #[test]
    fn every_rotation_is_within_63_degrees_of_its_nearest_cube_rotation() {
        // Quasi-random rotations: each is re-expressed within the cube group's covering radius
        // (≈ 62.8°) of the reference.
        use rand::{Rng, SeedableRng};
        let group = rotation_group(24).unwrap();
        let reference = paper_view_rotation();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for _ in 0..2000 {
            let mut g = || rng.random::<f64>() * 2.0 - 1.0;
            let r = Pose::from_quaternion(g(), g(), g(), g(), DVec3::ZERO).unwrap();
            let (_, angle) = nearest_in_group(&r, &group, &reference);
            assert!(angle.to_degrees() < 63.0, "{}", angle.to_degrees());
        }
    }
}
