//! How well an instance's shape fits the model's, before any registration: the spreads of
//! the instance's back-projected points against those of the model's surface as seen from
//! many directions.
//!
//! The size test of [`crate::pipeline::InstanceCandidate`] compares one number, the visible
//! extent, with the model's diameter; in clutter several objects pass it. A view of the model
//! also has a shape: a plate seen from above is wide in two directions, a bottle seen from
//! the side long in one. [`ViewSpreads`] holds, for [`VIEWS`] directions spread evenly over the
//! sphere, the standard deviations of the model's visible surface along its two largest
//! principal axes, over the model's diameter; [`ViewSpreads::distance`] says how far an
//! instance's two spreads lie from the nearest view's (`docs/decisions.md`, "Ranking the
//! instances by the model's views").
//!
//! Units: points in normalised object units, any frame (principal spreads do not depend on
//! the frame); spreads over the model's diameter; distances are dimensionless.

use ic_geometry::glam::{DVec3, Vec3};
use rayon::prelude::*;

/// Directions the model's surface is seen from (a Fibonacci sphere).
pub const VIEWS: usize = 128;

/// Cells across the orthographic depth buffer that decides which model points a view sees.
const GRID: usize = 32;

/// A point is seen when it lies within this fraction of the diameter of the nearest point of
/// its cell and the 8 cells around it (the dense model points are ≈ 4 000: a cell holds
/// several, and a cell left empty by the sampling would otherwise let the back show through).
const DEPTH_TOLERANCE: f32 = 1.0 / 40.0;

/// The model's visible spreads from [`VIEWS`] directions.
#[derive(Clone, Debug)]
pub struct ViewSpreads {
    /// Per view, the standard deviations along the two largest principal axes of the visible
    /// points, over the diameter, largest first.
    spreads: Vec<[f64; 2]>,
}

/// The standard deviations along the two largest principal axes of `points`, largest first
/// (their units); `None` for fewer than 3 points or a non-finite one.
fn principal_spreads(points: &[Vec3]) -> Option<[f64; 2]> {
    if points.len() < 3 {
        return None;
    }
    let (_, v) = ic_geometry::principal_axes(points)?;
    Some([v[0].max(0.0).sqrt(), v[1].max(0.0).sqrt()])
}

/// Unit directions spread evenly over the sphere (the golden-angle spiral), deterministic.
fn sphere_directions(n: usize) -> Vec<DVec3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let t = golden * i as f64;
            DVec3::new(r * t.cos(), y, r * t.sin())
        })
        .collect()
}

/// The points of `points` seen along `dir` (orthographic, from −∞·dir): the nearest of each
/// cell of a [`GRID`]² buffer spanning `radius` around `centre`, and any within
/// [`DEPTH_TOLERANCE`]·`diameter` of the nearest of its 3×3 cells.
fn seen_along(points: &[Vec3], centre: Vec3, radius: f32, diameter: f32, dir: DVec3) -> Vec<Vec3> {
    let dir = dir.as_vec3();
    let helper = if dir.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let a = dir.cross(helper).normalize();
    let b = dir.cross(a);
    let cell = (2.0 * radius / GRID as f32).max(f32::MIN_POSITIVE);
    let index = |p: Vec3| {
        let q = p - centre;
        let i = ((q.dot(a) + radius) / cell)
            .floor()
            .clamp(0.0, (GRID - 1) as f32) as usize;
        let j = ((q.dot(b) + radius) / cell)
            .floor()
            .clamp(0.0, (GRID - 1) as f32) as usize;
        (i, j)
    };
    let mut nearest = vec![f32::INFINITY; GRID * GRID];
    for &p in points {
        let (i, j) = index(p);
        let z = p.dot(dir);
        let n = &mut nearest[j * GRID + i];
        *n = n.min(z);
    }
    let tolerance = DEPTH_TOLERANCE * diameter;
    points
        .iter()
        .copied()
        .filter(|&p| {
            let (i, j) = index(p);
            let mut front = f32::INFINITY;
            for jj in j.saturating_sub(1)..=(j + 1).min(GRID - 1) {
                for ii in i.saturating_sub(1)..=(i + 1).min(GRID - 1) {
                    front = front.min(nearest[jj * GRID + ii]);
                }
            }
            p.dot(dir) <= front + tolerance
        })
        .collect()
}

impl ViewSpreads {
    /// The spreads of the surface `points` (normalised units, the model's frame) of an object
    /// of `diameter` (same units, > 0), seen from [`VIEWS`] directions. Views that see fewer
    /// than 3 points are left out; with none left (a degenerate model) every distance is 0.
    pub fn of(points: &[Vec3], diameter: f64) -> ViewSpreads {
        let finite: Vec<Vec3> = points.iter().copied().filter(|p| p.is_finite()).collect();
        if finite.len() < 3 || diameter.is_nan() || diameter <= 0.0 {
            return ViewSpreads {
                spreads: Vec::new(),
            };
        }
        let centre = finite.iter().copied().sum::<Vec3>() / finite.len() as f32;
        let radius = finite
            .iter()
            .map(|p| p.distance(centre))
            .fold(0.0f32, f32::max)
            .max(1e-6);
        let spreads: Vec<[f64; 2]> = sphere_directions(VIEWS)
            .into_par_iter()
            .filter_map(|dir| {
                let seen = seen_along(&finite, centre, radius, diameter as f32, dir);
                principal_spreads(&seen).map(|s| [s[0] / diameter, s[1] / diameter])
            })
            .filter(|s| s[0] > 0.0 && s[1] > 0.0)
            .collect();
        ViewSpreads { spreads }
    }

    /// How many views it holds.
    pub fn len(&self) -> usize {
        self.spreads.len()
    }

    pub fn is_empty(&self) -> bool {
        self.spreads.is_empty()
    }

    /// How far the two principal spreads of an instance's back-projected `points`
    /// (normalised units, camera frame) lie from the nearest view's, both over the model's
    /// `diameter`: the smallest, over the views, of √(ln²(s₁/v₁) + ln²(s₂/v₂)). 0 when a view
    /// of the model spreads exactly so; ln 2 ≈ 0.69 is one spread twice or half the nearest
    /// view's. Infinite for an instance of fewer than 3 points or with no spread; 0 for a
    /// model without views.
    pub fn distance(&self, points: &[Vec3], diameter: f64) -> f64 {
        if self.spreads.is_empty() {
            return 0.0;
        }
        let Some(s) = principal_spreads(points) else {
            return f64::INFINITY;
        };
        let s = [s[0] / diameter, s[1] / diameter];
        if !(s[0] > 0.0 && s[1] > 0.0) {
            return f64::INFINITY;
        }
        self.spreads
            .iter()
            .map(|v| ((s[0] / v[0]).ln().powi(2) + (s[1] / v[1]).ln().powi(2)).sqrt())
            .fold(f64::INFINITY, f64::min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points on the surface of an axis-aligned box of the given sides, on a regular grid.
    fn box_surface(sides: [f32; 3], step: f32) -> Vec<Vec3> {
        let mut out = Vec::new();
        let h = [sides[0] / 2.0, sides[1] / 2.0, sides[2] / 2.0];
        let n = |s: f32| ((s / step).round() as i32).max(1);
        let (nx, ny, nz) = (n(sides[0]), n(sides[1]), n(sides[2]));
        for i in 0..=nx {
            for j in 0..=ny {
                for k in 0..=nz {
                    let p = Vec3::new(
                        -h[0] + sides[0] * i as f32 / nx as f32,
                        -h[1] + sides[1] * j as f32 / ny as f32,
                        -h[2] + sides[2] * k as f32 / nz as f32,
                    );
                    let on = i == 0 || i == nx || j == 0 || j == ny || k == 0 || k == nz;
                    if on {
                        out.push(p);
                    }
                }
            }
        }
        out
    }

    fn diameter(points: &[Vec3]) -> f64 {
        let mut d = 0.0f32;
        for a in points {
            for b in points {
                d = d.max(a.distance(*b));
            }
        }
        d as f64
    }

    #[test]
    fn a_view_of_the_model_itself_fits_and_another_shape_of_the_same_size_does_not() {
        // A flat plate (20 × 20 × 1) and a long bar (28 × 4 × 4) of nearly the same diameter.
        let plate = box_surface([20.0, 20.0, 1.0], 0.5);
        let bar = box_surface([28.0, 4.0, 4.0], 0.5);
        let d_plate = diameter(&plate);
        let spreads = ViewSpreads::of(&plate, d_plate);
        assert!(spreads.len() > VIEWS / 2, "{} views", spreads.len());
        // The plate's top face, as a camera above it sees it: a view of the model.
        let top: Vec<Vec3> = plate.iter().copied().filter(|p| p.z > 0.4).collect();
        let fits = spreads.distance(&top, d_plate);
        // The bar seen from the side, its size against the plate's.
        let side: Vec<Vec3> = bar.iter().copied().filter(|p| p.z > 1.9).collect();
        let misfits = spreads.distance(&side, d_plate);
        assert!(fits < 0.15, "the plate's own top: {fits}");
        assert!(misfits > 0.5, "a bar of the plate's size: {misfits}");
        // The same in any frame: rotating the instance changes nothing.
        let r =
            ic_geometry::glam::Quat::from_euler(ic_geometry::glam::EulerRot::XYZ, 0.3, -1.1, 2.0);
        let turned: Vec<Vec3> = top
            .iter()
            .map(|&p| r * p + Vec3::new(5.0, -2.0, 40.0))
            .collect();
        assert!((spreads.distance(&turned, d_plate) - fits).abs() < 1e-3);
    }

    #[test]
    fn degenerate_inputs_give_defined_distances() {
        let plate = box_surface([20.0, 20.0, 1.0], 1.0);
        let spreads = ViewSpreads::of(&plate, diameter(&plate));
        assert_eq!(
            spreads.distance(&[Vec3::ZERO, Vec3::X], 28.0),
            f64::INFINITY
        );
        assert_eq!(spreads.distance(&[Vec3::ZERO; 10], 28.0), f64::INFINITY);
        let none = ViewSpreads::of(&[Vec3::ZERO, Vec3::X], 1.0);
        assert!(none.is_empty());
        assert_eq!(none.distance(&plate, 28.0), 0.0);
        let nan = ViewSpreads::of(&[Vec3::NAN; 20], 1.0);
        assert!(nan.is_empty());
    }
}
