//! Iterative closest point refinement, point-to-point and point-to-plane.
//!
//! Follows Open3D's `registration_icp` semantics so results can be compared one to one:
//! correspondences are nearest target points within `max_correspondence_distance` of each
//! transformed source point; `fitness` = matched source points / all source points;
//! `inlier_rmse` = RMS distance of the matched pairs; iteration stops when both fitness and RMSE
//! change by less than their relative tolerances, or at `max_iterations`.
//! Point-to-point solves each step with [`procrustes`](crate::procrustes) (Besl & McKay 1992);
//! point-to-plane linearises the rotation (Low 2004) and solves the 6×6 normal equations with
//! faer's symmetric eigen-solver, leaving unconstrained motions (sliding along a plane) untouched.

use glam::{DVec3, Vec3};
use serde::{Deserialize, Serialize};

use crate::cloud::check_finite;
use crate::{GeometryError, KdTree, Pose, procrustes};

/// Which error ICP minimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum IcpMethod {
    PointToPoint,
    /// Needs target normals (estimate them with [`estimate_normals`](crate::estimate_normals)).
    PointToPlane,
}

/// ICP settings. Distances are in the units of the points.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IcpOptions {
    pub method: IcpMethod,
    pub max_correspondence_distance: f32,
    pub max_iterations: usize,
    /// Stop when |Δfitness| < this (Open3D's `relative_fitness`, default 1e-6).
    pub relative_fitness: f64,
    /// Stop when |Δrmse| < this (Open3D's `relative_rmse`, default 1e-6).
    pub relative_rmse: f64,
}

impl Default for IcpOptions {
    fn default() -> Self {
        IcpOptions {
            method: IcpMethod::PointToPoint,
            max_correspondence_distance: 0.1,
            max_iterations: 30,
            relative_fitness: 1e-6,
            relative_rmse: 1e-6,
        }
    }
}

/// The refined pose (source → target) and how well it fits.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IcpResult {
    pub pose: Pose,
    /// Fraction of source points with a target point within the correspondence distance.
    pub fitness: f64,
    /// RMS distance over those correspondences (0 when there are none).
    pub inlier_rmse: f64,
    pub correspondences: usize,
    pub iterations: usize,
    /// Whether the tolerances were met before `max_iterations`.
    pub converged: bool,
}

/// A target cloud prepared for repeated ICP runs (k-d tree built once).
pub struct IcpTarget<'a> {
    points: &'a [Vec3],
    normals: Option<&'a [Vec3]>,
    tree: KdTree,
}

impl<'a> IcpTarget<'a> {
    /// Indexes the target points; `normals` (unit, one per point) are needed for point-to-plane.
    pub fn new(points: &'a [Vec3], normals: Option<&'a [Vec3]>) -> Result<Self, GeometryError> {
        if let Some(n) = normals {
            if n.len() != points.len() {
                return Err(GeometryError::LengthMismatch {
                    what: "target normals vs points",
                    left: n.len(),
                    right: points.len(),
                });
            }
            check_finite("target normals", n)?;
        }
        Ok(IcpTarget {
            points,
            normals,
            tree: KdTree::new(points)?,
        })
    }

    /// Refines `initial` (source → target). See the module documentation.
    pub fn register(
        &self,
        source: &[Vec3],
        initial: &Pose,
        options: &IcpOptions,
    ) -> Result<IcpResult, GeometryError> {
        if source.is_empty() {
            return Err(GeometryError::Empty {
                what: "ICP source points",
            });
        }
        check_finite("ICP source points", source)?;
        if !(options.max_correspondence_distance > 0.0) {
            return Err(GeometryError::InvalidParameter {
                name: "max_correspondence_distance",
                message: format!("{} must be positive", options.max_correspondence_distance),
            });
        }
        let normals = match (options.method, self.normals) {
            (IcpMethod::PointToPlane, None) => {
                return Err(GeometryError::InvalidParameter {
                    name: "method",
                    message: "point-to-plane ICP needs target normals".into(),
                });
            }
            (_, n) => n,
        };

        let mut pose = *initial;
        let mut eval = self.correspond(source, &pose, options.max_correspondence_distance);
        let mut iterations = 0;
        let mut converged = false;
        while iterations < options.max_iterations {
            if eval.pairs.len() < 3 {
                break;
            }
            let step = match options.method {
                IcpMethod::PointToPoint => {
                    let (src, dst): (Vec<Vec3>, Vec<Vec3>) = eval
                        .pairs
                        .iter()
                        .map(|&(s, t)| (pose.apply_f32(source[s]), self.points[t]))
                        .unzip();
                    match procrustes(&src, &dst, None) {
                        Ok(p) => p,
                        Err(_) => break,
                    }
                }
                IcpMethod::PointToPlane => match point_to_plane_step(
                    source,
                    self.points,
                    normals.unwrap_or_default(),
                    &eval.pairs,
                    &pose,
                ) {
                    Some(p) => p,
                    None => break,
                },
            };
            pose = step.compose(&pose).orthonormalised();
            iterations += 1;
            let next = self.correspond(source, &pose, options.max_correspondence_distance);
            let done = (next.fitness - eval.fitness).abs() < options.relative_fitness
                && (next.rmse - eval.rmse).abs() < options.relative_rmse;
            eval = next;
            if done {
                converged = true;
                break;
            }
        }
        Ok(IcpResult {
            pose,
            fitness: eval.fitness,
            inlier_rmse: eval.rmse,
            correspondences: eval.pairs.len(),
            iterations,
            converged,
        })
    }

    fn correspond(&self, source: &[Vec3], pose: &Pose, max_distance: f32) -> Correspondences {
        use rayon::prelude::*;
        let found: Vec<Option<(usize, usize, f32)>> = source
            .par_iter()
            .enumerate()
            .map(|(s, &p)| {
                let nb = self.tree.nearest(pose.apply_f32(p));
                (nb.distance <= max_distance).then_some((s, nb.index, nb.distance))
            })
            .collect();
        let mut pairs = Vec::with_capacity(found.len());
        let mut sq = 0.0f64;
        for (s, t, d) in found.into_iter().flatten() {
            pairs.push((s, t));
            sq += (d as f64) * (d as f64);
        }
        let rmse = if pairs.is_empty() {
            0.0
        } else {
            (sq / pairs.len() as f64).sqrt()
        };
        Correspondences {
            fitness: pairs.len() as f64 / source.len() as f64,
            rmse,
            pairs,
        }
    }
}

struct Correspondences {
    pairs: Vec<(usize, usize)>,
    fitness: f64,
    rmse: f64,
}

/// One Gauss–Newton step of point-to-plane ICP: the small motion `(ω, v)` minimising
/// `Σ ((p + ω×p + v − q)·n)²` over the current correspondences, returned as a pose.
fn point_to_plane_step(
    source: &[Vec3],
    target: &[Vec3],
    normals: &[Vec3],
    pairs: &[(usize, usize)],
    pose: &Pose,
) -> Option<Pose> {
    let mut ata = [[0.0f64; 6]; 6];
    let mut atb = [0.0f64; 6];
    for &(s, t) in pairs {
        let p = pose.apply(source[s].as_dvec3());
        let q = target[t].as_dvec3();
        let n = normals[t].as_dvec3();
        if n == DVec3::ZERO {
            continue;
        }
        let c = p.cross(n);
        let row = [c.x, c.y, c.z, n.x, n.y, n.z];
        let r = (p - q).dot(n);
        for i in 0..6 {
            atb[i] -= row[i] * r;
            for j in 0..6 {
                ata[i][j] += row[i] * row[j];
            }
        }
    }
    // Solve A·x = b by the eigen-decomposition of the symmetric A, dropping directions whose
    // eigenvalue is below 1e-9 of the largest: on degenerate geometry (a plane, a cylinder) those
    // motions are unconstrained and the step leaves them unchanged instead of exploding.
    let a = faer::Mat::<f64>::from_fn(6, 6, |i, j| ata[i][j]);
    let eig = a.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (values, vectors) = (eig.S().column_vector(), eig.U());
    let largest = (0..6).map(|i| values[i]).fold(0.0f64, f64::max);
    if !(largest > 0.0 && largest.is_finite()) {
        return None;
    }
    let mut x = [0.0f64; 6];
    for k in 0..6 {
        if values[k] > 1e-9 * largest {
            let coeff = (0..6).map(|i| vectors[(i, k)] * atb[i]).sum::<f64>() / values[k];
            for (i, xi) in x.iter_mut().enumerate() {
                *xi += coeff * vectors[(i, k)];
            }
        }
    }
    let omega = DVec3::new(x[0], x[1], x[2]);
    let v = DVec3::new(x[3], x[4], x[5]);
    if !(omega.is_finite() && v.is_finite()) {
        return None;
    }
    Some(Pose::from_rotation_vector(omega, v))
}

/// One-shot ICP: builds the target index and refines `initial`.
pub fn icp(
    source: &[Vec3],
    target: &[Vec3],
    target_normals: Option<&[Vec3]>,
    initial: &Pose,
    options: &IcpOptions,
) -> Result<IcpResult, GeometryError> {
    IcpTarget::new(target, target_normals)?.register(source, initial, options)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Points on a closed, asymmetric surface (an ellipsoid with a bump), dense target.
    fn surface(n: usize, seed: u64) -> (Vec<Vec3>, Vec<Vec3>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut pts = Vec::new();
        let mut nrm = Vec::new();
        while pts.len() < n {
            let d = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let Some(d) = d.try_normalize() else { continue };
            let radii = DVec3::new(1.0, 0.6, 0.35);
            let bump = 1.0
                + 0.3 * (-(d - DVec3::new(0.6, 0.6, 0.5).normalize()).length_squared() * 6.0).exp();
            let p = d * radii * bump;
            pts.push(p.as_vec3());
            nrm.push((p / (radii * radii)).normalize().as_vec3());
        }
        (pts, nrm)
    }

    fn perturbation(deg: f64, trans: f64) -> Pose {
        Pose::from_axis_angle(
            DVec3::new(0.3, -0.5, 0.8),
            deg.to_radians(),
            DVec3::new(1.0, 0.5, -0.7).normalize() * trans,
        )
    }

    #[test]
    fn point_to_point_converges_from_10_degrees_and_5_cm() {
        let (target, _) = surface(10_000, 1);
        let (source, _) = surface(1024, 2);
        let truth = Pose::IDENTITY;
        let init = perturbation(10.0, 0.05);
        let opts = IcpOptions {
            max_correspondence_distance: 0.3,
            max_iterations: 100,
            ..Default::default()
        };
        let r = icp(&source, &target, None, &init, &opts).unwrap();
        let deg = r.pose.rotation_angle_to(&truth).to_degrees();
        assert!(deg < 1.0, "rotation error {deg}°");
        assert!(
            r.pose.translation.length() < 0.01,
            "translation error {}",
            r.pose.translation.length()
        );
        assert!(r.fitness > 0.99 && r.inlier_rmse < 0.03, "{r:?}");
    }

    #[test]
    fn converges_from_10_degrees_and_5_cm_on_sampled_procedural_shapes() {
        use crate::sampling::sample_surface_uniform;
        use crate::shapes::{CompositeKind, composite, random_object};
        let opts = IcpOptions {
            method: IcpMethod::PointToPlane,
            max_correspondence_distance: 0.3,
            max_iterations: 100,
            ..Default::default()
        };
        let run = |mesh: &crate::Mesh, seed: u64| {
            let target = sample_surface_uniform(mesh, 10_000, seed).unwrap();
            let source = sample_surface_uniform(mesh, 1024, seed + 100).unwrap();
            let index = IcpTarget::new(&target.points, target.normals.as_deref()).unwrap();
            let at_truth = index
                .register(
                    &source.points,
                    &Pose::IDENTITY,
                    &IcpOptions {
                        max_iterations: 0,
                        ..opts
                    },
                )
                .unwrap();
            (
                index
                    .register(&source.points, &perturbation(10.0, 0.05), &opts)
                    .unwrap(),
                at_truth,
            )
        };
        // Asymmetric composites: the pose itself is recovered.
        for (i, kind) in [CompositeKind::Chair, CompositeKind::Bracket]
            .into_iter()
            .enumerate()
        {
            let mesh = composite(kind, i as u64);
            let (r, _) = run(&mesh, i as u64);
            let deg = r.pose.rotation_angle().to_degrees();
            assert!(
                deg < 1.0 && r.pose.translation.length() < 0.01,
                "{kind:?}: {deg}°, {r:?}"
            );
        }
        // Any random object (some are symmetric about an axis, so the pose is ambiguous): the
        // surfaces are aligned as well as they are at the true pose.
        for seed in 0..6 {
            let mut mesh = random_object(seed);
            mesh.normalise().unwrap();
            let (r, truth) = run(&mesh, seed);
            assert!(
                r.fitness == 1.0 && r.inlier_rmse < truth.inlier_rmse * 1.1 + 1e-3,
                "object {seed}: {r:?} vs truth {truth:?}"
            );
        }
    }

    #[test]
    fn point_to_plane_converges_faster_than_point_to_point() {
        let (target, normals) = surface(10_000, 3);
        let (source, _) = surface(1024, 4);
        let init = perturbation(10.0, 0.05);
        let target_index = IcpTarget::new(&target, Some(&normals)).unwrap();
        let opts = IcpOptions {
            max_correspondence_distance: 0.3,
            max_iterations: 100,
            ..Default::default()
        };
        let plane = target_index
            .register(
                &source,
                &init,
                &IcpOptions {
                    method: IcpMethod::PointToPlane,
                    ..opts
                },
            )
            .unwrap();
        let point = target_index.register(&source, &init, &opts).unwrap();
        assert!(plane.pose.rotation_angle().to_degrees() < 1.0, "{plane:?}");
        assert!(plane.pose.translation.length() < 0.01, "{plane:?}");
        assert!(
            plane.iterations <= point.iterations,
            "plane {} vs point {}",
            plane.iterations,
            point.iterations
        );
    }

    #[test]
    fn exact_copy_converges_to_the_truth() {
        let (pts, normals) = surface(2000, 5);
        let truth =
            Pose::from_axis_angle(DVec3::new(1.0, 0.2, 0.1), 0.1, DVec3::new(0.02, 0.0, 0.03));
        let target = truth.apply_all(&pts);
        let target_normals: Vec<Vec3> = normals.iter().map(|&n| truth.rotate_f32(n)).collect();
        for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
            let opts = IcpOptions {
                method,
                max_correspondence_distance: 0.5,
                max_iterations: 200,
                relative_fitness: 1e-9,
                relative_rmse: 1e-9,
            };
            let r = icp(&pts, &target, Some(&target_normals), &Pose::IDENTITY, &opts).unwrap();
            assert!(r.pose.rotation_angle_to(&truth) < 1e-4, "{method:?}: {r:?}");
            assert!(
                r.inlier_rmse < 1e-4 && r.fitness == 1.0,
                "{method:?}: {r:?}"
            );
        }
    }

    #[test]
    fn point_to_plane_on_a_plane_does_not_slide_along_unconstrained_directions() {
        // A flat target constrains only the out-of-plane motion; the in-plane translation and
        // the rotation about the normal must stay as they were, not explode.
        let target: Vec<Vec3> = (0..900)
            .map(|i| Vec3::new((i % 30) as f32 * 0.05, (i / 30) as f32 * 0.05, 0.0))
            .collect();
        let normals = vec![Vec3::Z; target.len()];
        let source: Vec<Vec3> = target
            .iter()
            .step_by(3)
            .map(|p| *p + Vec3::new(0.0, 0.0, 0.02))
            .collect();
        let opts = IcpOptions {
            method: IcpMethod::PointToPlane,
            max_correspondence_distance: 0.5,
            max_iterations: 20,
            ..Default::default()
        };
        let r = icp(&source, &target, Some(&normals), &Pose::IDENTITY, &opts).unwrap();
        assert!(
            r.pose.translation.z.abs() > 0.0199 && r.pose.translation.z.abs() < 0.0201,
            "{r:?}"
        );
        assert!(
            r.pose.translation.x.abs() < 1e-6 && r.pose.translation.y.abs() < 1e-6,
            "{r:?}"
        );
        assert!(r.pose.rotation_angle() < 1e-6 && r.fitness == 1.0, "{r:?}");
    }

    #[test]
    fn bad_input_is_an_error_and_no_overlap_reports_zero_fitness() {
        let (pts, _) = surface(100, 6);
        assert!(icp(&[], &pts, None, &Pose::IDENTITY, &IcpOptions::default()).is_err());
        assert!(icp(&pts, &[], None, &Pose::IDENTITY, &IcpOptions::default()).is_err());
        let plane = IcpOptions {
            method: IcpMethod::PointToPlane,
            ..Default::default()
        };
        assert!(
            icp(&pts, &pts, None, &Pose::IDENTITY, &plane).is_err(),
            "point-to-plane without normals"
        );
        let bad = IcpOptions {
            max_correspondence_distance: -1.0,
            ..Default::default()
        };
        assert!(icp(&pts, &pts, None, &Pose::IDENTITY, &bad).is_err());
        let far = Pose::from_translation(DVec3::new(100.0, 0.0, 0.0));
        let r = icp(&pts, &pts, None, &far, &IcpOptions::default()).unwrap();
        assert_eq!((r.fitness, r.correspondences, r.iterations), (0.0, 0, 0));
        assert_eq!(r.pose, far);
    }
}
