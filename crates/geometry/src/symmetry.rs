//! Rotational symmetries of a model: the rigid motions that map its surface onto itself within
//! a tolerance — poses that no depth map can tell apart (a can turned about its axis, a box
//! turned half a turn).
//!
//! [`find_symmetries`] works on the mesh in its own frame and units (the normalised frame for
//! a normalised mesh). The surface is sampled twice with a seed: `samples` test points `X`
//! and a dense reference `Y` (`REFERENCE_FACTOR` × as many). A motion `S` is scored by its
//! *residual*: the 90th percentile of the distances from `S·x` to the nearest `y`, divided by
//! the diameter of `X`. The identity's residual is the sampling's own floor; `S` is a symmetry
//! when its residual is at most that floor plus `tolerance`.
//!
//! Candidates are rotations about the surface centroid (which every symmetry of the surface
//! fixes): axes spread over a hemisphere ([`fibonacci_sphere`]) times the angles 360°/n,
//! n = 2…6 and 8 (the powers of a generator follow from the axis). Candidates whose residual is
//! within `COARSE_FACTOR` × the threshold are refined by point-to-point ICP of `X` onto `Y`
//! (the sampled axes are a few degrees apart), accepted when the refined motion passes, and
//! merged when two are within `MERGE_DEG`. An accepted axis on which every multiple of
//! `CONTINUOUS_STEP_DEG` passes is a continuous symmetry axis, and its steps join the set.
//! Every random choice comes from `options.seed`.

use std::sync::atomic::{AtomicU64, Ordering};

use glam::{DMat3, DVec3, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::sampling::{fibonacci_sphere, sample_surface_uniform};
use crate::{GeometryError, IcpMethod, IcpOptions, IcpTarget, KdTree, Mesh, Pose};

/// The reference sample holds this many times the test samples.
const REFERENCE_FACTOR: usize = 8;
/// Candidates with a residual up to this multiple of the threshold are refined by ICP.
const COARSE_FACTOR: f64 = 3.0;
/// At most this many candidates are refined by ICP (the best coarse residuals first).
const MAX_REFINED: usize = 256;
/// Accepted motions closer than this (degrees, rotation part) are one symmetry.
const MERGE_DEG: f64 = 5.0;
/// The step (degrees) at which a continuous axis is tested and listed.
pub const CONTINUOUS_STEP_DEG: f64 = 10.0;
/// A refined motion turning less than this (degrees) is not a symmetry but the identity's
/// neighbourhood, where sliding along flat faces keeps residuals small.
const MIN_ANGLE_DEG: f64 = 20.0;
/// At most this many symmetries are listed (a sphere would otherwise list all of SO(3)).
pub const MAX_SYMMETRIES: usize = 512;

/// Settings of [`find_symmetries`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SymmetryOptions {
    /// Test points on the surface (the reference gets 8× as many).
    pub samples: usize,
    /// Allowed residual above the sampling's own, as a fraction of the diameter.
    pub tolerance: f64,
    /// Candidate axes over the hemisphere.
    pub axes: usize,
    pub seed: u64,
}

impl Default for SymmetryOptions {
    /// 1500 samples, tolerance 1 % of the diameter (for a normalised model about one voxel of
    /// the pose pipeline), 600 axes, seed 0.
    fn default() -> Self {
        SymmetryOptions {
            samples: 1500,
            tolerance: 0.01,
            axes: 600,
            seed: 0,
        }
    }
}

/// The symmetries found, in the mesh's frame and units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Symmetries {
    /// Non-identity motions `S` with `S·surface ≈ surface` (rotation about `centre`, plus the
    /// small translation ICP found), at most [`MAX_SYMMETRIES`], best residual first within
    /// each kind; continuous axes contribute their [`CONTINUOUS_STEP_DEG`] steps.
    pub motions: Vec<Pose>,
    /// Unit directions of the continuous symmetry axes (through `centre`).
    pub continuous_axes: Vec<DVec3>,
    /// The surface centroid of the samples (mesh frame).
    pub centre: DVec3,
    /// Diameter of the test samples (mesh units).
    pub diameter: f64,
    /// The identity's residual (the sampling floor), as a fraction of the diameter.
    pub floor: f64,
    /// The smallest residual of any candidate turn (45° or more, refined by ICP when it was
    /// promising), as a fraction of the diameter: how near the model came to a symmetry.
    pub nearest_residual: f64,
}

impl Symmetries {
    /// Whether the model has any symmetry (discrete or continuous).
    pub fn is_symmetric(&self) -> bool {
        !self.motions.is_empty()
    }

    /// A one-word description: `none`, `spherical` (two continuous axes), `continuous` or
    /// `discrete(n)` with n the number of non-identity motions.
    pub fn kind(&self) -> String {
        if self.continuous_axes.len() >= 2 {
            "spherical".into()
        } else if !self.continuous_axes.is_empty() {
            "continuous".into()
        } else if self.motions.is_empty() {
            "none".into()
        } else {
            format!("discrete({})", self.motions.len())
        }
    }
}

/// Finds the symmetries of `mesh` (see the module documentation).
///
/// Errors: [`GeometryError::InvalidParameter`] for `samples` < 16, `axes` = 0, a tolerance
/// that is not positive and finite, or an invalid / zero-area mesh.
pub fn find_symmetries(
    mesh: &Mesh,
    options: &SymmetryOptions,
) -> Result<Symmetries, GeometryError> {
    let bad = |name: &'static str, message: String| {
        Err(GeometryError::InvalidParameter { name, message })
    };
    if options.samples < 16 {
        return bad(
            "samples",
            format!("{} is too few (at least 16)", options.samples),
        );
    }
    if options.axes == 0 {
        return bad("axes", "must be at least 1".into());
    }
    if !(options.tolerance > 0.0 && options.tolerance.is_finite()) {
        return bad(
            "tolerance",
            format!("{} must be positive", options.tolerance),
        );
    }
    let test = sample_surface_uniform(mesh, options.samples, options.seed)?.points;
    let reference = sample_surface_uniform(
        mesh,
        options.samples * REFERENCE_FACTOR,
        options.seed.wrapping_add(1),
    )?
    .points;
    let centre = test.iter().map(|p| p.as_dvec3()).sum::<DVec3>() / test.len() as f64;
    let diameter = sample_diameter(&test);
    if !(diameter > 0.0) {
        return bad("mesh", "its surface is a single point".into());
    }
    let scorer = Scorer {
        test: &test,
        tree: KdTree::new(&reference)?,
        diameter,
    };
    let floor = scorer.residual(&Pose::IDENTITY);
    let threshold = floor + options.tolerance;

    // Coarse pass over axes × angles, then ICP from the promising candidates.
    let target = IcpTarget::new(&reference, None)?;
    let icp = IcpOptions {
        method: IcpMethod::PointToPoint,
        max_correspondence_distance: (0.1 * diameter) as f32,
        max_iterations: 30,
        ..IcpOptions::default()
    };
    let axes: Vec<DVec3> = fibonacci_sphere(2 * options.axes)
        .into_iter()
        .filter(|a| a.z >= 0.0)
        .collect();
    let candidates: Vec<Pose> = axes
        .iter()
        .flat_map(|axis| {
            [2usize, 3, 4, 5, 6, 8].map(|n| about(centre, *axis, std::f64::consts::TAU / n as f64))
        })
        .collect();
    // Only the residuals up to the refinement cut, and the smallest of all, are needed: a
    // candidate is dropped as soon as it is known to be above both (the running minimum is
    // shared between threads; non-negative floats order like their bits).
    let cut = COARSE_FACTOR * threshold;
    let best = AtomicU64::new(f64::INFINITY.to_bits());
    let mut coarse: Vec<(f64, Pose)> = candidates
        .into_par_iter()
        .filter_map(|m| {
            let bound = cut.max(f64::from_bits(best.load(Ordering::Relaxed)));
            let r = scorer.residual_within(&m, bound)?;
            best.fetch_min(r.to_bits(), Ordering::Relaxed);
            Some((r, m))
        })
        .collect();
    coarse.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Every candidate turns by 45° or more: the best of them bounds how near the model came.
    let mut nearest_residual = coarse.first().map_or(f64::MAX, |c| c.0);
    coarse.retain(|(r, _)| *r <= COARSE_FACTOR * threshold);
    let mut accepted: Vec<(f64, Pose)> = Vec::new();
    for (_, start) in coarse.into_iter().take(MAX_REFINED) {
        if accepted.len() >= MAX_SYMMETRIES {
            break;
        }
        if accepted.iter().any(|(_, s)| near(s, &start)) {
            continue;
        }
        let refined = target.register(&test, &start, &icp)?.pose;
        if refined.rotation_angle().to_degrees() < MIN_ANGLE_DEG {
            continue;
        }
        let r = scorer.residual(&refined);
        nearest_residual = nearest_residual.min(r);
        if r <= threshold && !accepted.iter().any(|(_, s)| near(s, &refined)) {
            accepted.push((r, refined));
        }
    }

    // Continuous axes: every step about an accepted motion's axis passes.
    let mut continuous_axes: Vec<DVec3> = Vec::new();
    let steps = (360.0 / CONTINUOUS_STEP_DEG).round() as usize;
    let mut axis_points: Vec<DVec3> = Vec::new();
    for (_, motion) in &accepted {
        // Two continuous axes make every rotation a symmetry (a sphere): nothing to add.
        if continuous_axes.len() >= 2 {
            break;
        }
        let axis = rotation_axis(&motion.rotation);
        // The refined motion's own axis line: the centroid of the samples is a few hundredths
        // off, which large turns would magnify.
        let through = point_on_axis(motion);
        if continuous_axes
            .iter()
            .any(|a| a.dot(axis).abs() > MERGE_DEG.to_radians().cos())
        {
            continue;
        }
        let all_pass = (1..steps).all(|k| {
            let angle = (k as f64 * CONTINUOUS_STEP_DEG).to_radians();
            scorer
                .residual_within(&about(through, axis, angle), threshold)
                .is_some()
        });
        if all_pass {
            continuous_axes.push(axis);
            axis_points.push(through);
        }
    }
    let mut motions: Vec<Pose> = accepted.into_iter().map(|(_, s)| s).collect();
    for (axis, through) in continuous_axes.iter().zip(&axis_points) {
        let discrete = motions.clone();
        for k in 1..steps {
            let step = about(
                *through,
                *axis,
                (k as f64 * CONTINUOUS_STEP_DEG).to_radians(),
            );
            for m in std::iter::once(Pose::IDENTITY).chain(discrete.iter().copied()) {
                if motions.len() >= MAX_SYMMETRIES {
                    break;
                }
                let s = step.compose(&m);
                if s.rotation_angle().to_degrees() >= MERGE_DEG
                    && !motions.iter().any(|o| near(o, &s))
                {
                    motions.push(s);
                }
            }
        }
    }
    Ok(Symmetries {
        motions,
        continuous_axes,
        centre,
        diameter,
        floor,
        nearest_residual,
    })
}

/// Residuals of motions against one surface.
struct Scorer<'a> {
    test: &'a [Vec3],
    tree: KdTree,
    diameter: f64,
}

impl Scorer<'_> {
    /// The 90th percentile distance from the moved test points to the reference, over the
    /// diameter.
    fn residual(&self, motion: &Pose) -> f64 {
        let mut d: Vec<f32> = self
            .test
            .iter()
            .map(|&p| self.tree.nearest(motion.apply_f32(p)).distance)
            .collect();
        let k = (d.len() * 9 / 10).min(d.len() - 1);
        let (_, v, _) = d.select_nth_unstable_by(k, f32::total_cmp);
        *v as f64 / self.diameter
    }

    /// [`Scorer::residual`] when it is at most `bound`, else `None` — found without scoring
    /// every point once more than a tenth of them lie beyond the bound.
    fn residual_within(&self, motion: &Pose, bound: f64) -> Option<f64> {
        let n = self.test.len();
        let k = (n * 9 / 10).min(n - 1);
        let mut d: Vec<f32> = Vec::with_capacity(n);
        let mut above = 0;
        for &p in self.test {
            let x = self.tree.nearest(motion.apply_f32(p)).distance;
            if x as f64 / self.diameter > bound {
                above += 1;
                // At most k points at or below the bound: the k-th smallest is above it.
                if above >= n - k {
                    return None;
                }
            }
            d.push(x);
        }
        let (_, v, _) = d.select_nth_unstable_by(k, f32::total_cmp);
        let r = *v as f64 / self.diameter;
        (r <= bound).then_some(r)
    }
}

/// The rotation by `angle` (radians) about the axis through `centre` along `axis`.
fn about(centre: DVec3, axis: DVec3, angle: f64) -> Pose {
    let r = DMat3::from_axis_angle(axis.normalize(), angle);
    Pose::new(r, centre - r * centre)
}

/// A point on the axis line of `motion` (a turn by an angle well above 0): the
/// solution of `(I − R)·p = t` in the plane perpendicular to the axis, i.e. in complex form
/// `p = t / (1 − e^{iθ}) = ½·(t + cot(θ/2)·(axis × t))`.
fn point_on_axis(motion: &Pose) -> DVec3 {
    let (axis, angle) = glam::DQuat::from_mat3(&motion.rotation).to_axis_angle();
    let t = motion.translation - motion.translation.dot(axis) * axis;
    0.5 * (t + axis.cross(t) / (0.5 * angle).tan())
}

/// Whether two motions' rotations are within [`MERGE_DEG`].
fn near(a: &Pose, b: &Pose) -> bool {
    a.rotation_angle_to(b).to_degrees() < MERGE_DEG
}

/// The unit axis of a rotation (sign chosen with a non-negative largest component).
fn rotation_axis(r: &DMat3) -> DVec3 {
    let (axis, _) = glam::DQuat::from_mat3(r).to_axis_angle();
    let axis = axis.normalize_or_zero();
    let largest = if axis.x.abs() >= axis.y.abs() && axis.x.abs() >= axis.z.abs() {
        axis.x
    } else if axis.y.abs() >= axis.z.abs() {
        axis.y
    } else {
        axis.z
    };
    if largest < 0.0 { -axis } else { axis }
}

/// The largest distance between two samples (exact, O(n²) on the test samples).
fn sample_diameter(points: &[Vec3]) -> f64 {
    let mut best = 0.0f32;
    for (i, a) in points.iter().enumerate() {
        for b in &points[i + 1..] {
            best = best.max(a.distance_squared(*b));
        }
    }
    (best as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes;

    fn options() -> SymmetryOptions {
        SymmetryOptions {
            samples: 600,
            axes: 200,
            ..SymmetryOptions::default()
        }
    }

    /// The early-exit residual is the residual whenever it is within the bound, and `None`
    /// exactly when it is not (the oracle: the full residual), over many motions and bounds.
    #[test]
    fn the_bounded_residual_is_the_residual_or_says_it_is_above_the_bound() {
        let mesh = shapes::box_mesh(Vec3::new(1.0, 0.6, 0.3)).unwrap();
        let test = sample_surface_uniform(&mesh, 300, 1).unwrap().points;
        let reference = sample_surface_uniform(&mesh, 2400, 2).unwrap().points;
        let scorer = Scorer {
            test: &test,
            tree: KdTree::new(&reference).unwrap(),
            diameter: sample_diameter(&test),
        };
        let mut checked = (0, 0);
        for (i, axis) in fibonacci_sphere(40).into_iter().enumerate() {
            let m = about(DVec3::ZERO, axis, 0.3 + 0.2 * i as f64);
            let full = scorer.residual(&m);
            for bound in [0.0, 0.01, 0.05, 0.1, 0.2, 0.5, full, f64::INFINITY] {
                match scorer.residual_within(&m, bound) {
                    Some(r) => {
                        assert_eq!(r, full);
                        checked.0 += 1;
                    }
                    None => {
                        assert!(full > bound, "{full} ≤ {bound} but None");
                        checked.1 += 1;
                    }
                }
            }
        }
        // Both outcomes were exercised.
        assert!(checked.0 > 20 && checked.1 > 20, "{checked:?}");
    }

    #[test]
    fn a_cylinder_has_a_continuous_axis_along_its_length() {
        let mesh = shapes::cylinder(0.5, 1.0, 48).unwrap();
        let s = find_symmetries(&mesh, &options()).unwrap();
        assert_eq!(s.continuous_axes.len(), 1, "{s:?}");
        assert!(
            s.continuous_axes[0].z.abs() > 0.99,
            "{:?}",
            s.continuous_axes
        );
        assert!(s.is_symmetric());
    }

    #[test]
    fn a_box_with_three_different_sides_has_exactly_the_three_half_turns() {
        let mesh = shapes::box_mesh(Vec3::new(1.0, 0.6, 0.3)).unwrap();
        let s = find_symmetries(&mesh, &options()).unwrap();
        assert!(s.continuous_axes.is_empty(), "{s:?}");
        assert_eq!(s.motions.len(), 3, "{:?}", s.motions);
        for m in &s.motions {
            assert!((m.rotation_angle().to_degrees() - 180.0).abs() < 2.0);
        }
    }

    #[test]
    fn an_asymmetric_composite_has_none_and_says_how_near_it_came() {
        // A box with two smaller boxes stuck on at different places: no motion maps it
        // onto itself.
        let mut mesh = shapes::box_mesh(Vec3::new(1.0, 0.6, 0.3)).unwrap();
        for (half, at) in [
            (Vec3::splat(0.25), DVec3::new(0.7, 0.6, 0.1)),
            (Vec3::new(0.1, 0.2, 0.4), DVec3::new(-0.5, -0.2, 0.5)),
        ] {
            let bump = shapes::box_mesh(half).unwrap();
            mesh.append(&bump.transformed(&Pose::from_translation(at)));
        }
        let s = find_symmetries(&mesh, &options()).unwrap();
        assert!(!s.is_symmetric(), "{:?}", s.motions);
        assert_eq!(s.kind(), "none");
        assert!(s.nearest_residual > s.floor + 0.01);
    }

    #[test]
    fn same_seed_same_symmetries_and_bad_options_are_refused() {
        let mesh = shapes::box_mesh(Vec3::new(1.0, 0.6, 0.3)).unwrap();
        assert_eq!(
            find_symmetries(&mesh, &options()).unwrap(),
            find_symmetries(&mesh, &options()).unwrap()
        );
        for bad in [
            SymmetryOptions {
                samples: 3,
                ..options()
            },
            SymmetryOptions {
                axes: 0,
                ..options()
            },
            SymmetryOptions {
                tolerance: f64::NAN,
                ..options()
            },
        ] {
            assert!(find_symmetries(&mesh, &bad).is_err());
        }
    }
}
