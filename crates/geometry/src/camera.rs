//! Pinhole cameras in the OpenCV convention.
//!
//! Camera frame: x right, y down, z forward (metres). Pixel `(u, v)` = (column, row); integer
//! coordinates are pixel *centres*, so `u = fx·x/z + cx` lands on the centre of the pixel it
//! hits (BOP and OpenCV intrinsics use this convention). A camera pose is the world→camera
//! transform (`x_cam = R·x_world + t`), as BOP's `cam_R_w2c`/`cam_t_w2c`.

use glam::{DMat3, DVec3, Vec3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::{DepthImage, GeometryError, Mask, Pose};

/// Pinhole intrinsics (pixels) and image size.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    /// Checked constructor: focal lengths positive and finite, image non-empty, principal point
    /// finite.
    pub fn new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
    ) -> Result<Self, GeometryError> {
        let k = Intrinsics {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        };
        k.validate()?;
        Ok(k)
    }

    /// A Kinect-like 640×480 camera: fx = fy = 525 pixels, principal point at the image centre
    /// (a 49° vertical field of view).
    pub const KINECT_640X480: Intrinsics = Intrinsics {
        fx: 525.0,
        fy: 525.0,
        cx: 319.5,
        cy: 239.5,
        width: 640,
        height: 480,
    };

    /// Intrinsics with square pixels, the principal point at the image centre and the given
    /// vertical field of view (degrees).
    pub fn from_fov_y(width: u32, height: u32, fov_y_deg: f64) -> Result<Self, GeometryError> {
        if !(fov_y_deg > 0.0 && fov_y_deg < 180.0) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "vertical field of view {fov_y_deg}° is not in (0°, 180°)"
            )));
        }
        let f = 0.5 * height as f64 / (0.5 * fov_y_deg.to_radians()).tan();
        Self::centred(width, height, f, f)
    }

    /// Checked constructor ([`Intrinsics::new`]) with the principal point at the image's
    /// centre: `cx = (width − 1) / 2`, `cy = (height − 1) / 2` (pixel centres at integers).
    pub fn centred(width: u32, height: u32, fx: f64, fy: f64) -> Result<Self, GeometryError> {
        Self::new(
            fx,
            fy,
            (width as f64 - 1.0) / 2.0,
            (height as f64 - 1.0) / 2.0,
            width,
            height,
        )
    }

    /// Checks the invariants of [`Intrinsics::new`].
    pub fn validate(&self) -> Result<(), GeometryError> {
        if !(self.fx.is_finite() && self.fx > 0.0 && self.fy.is_finite() && self.fy > 0.0) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "focal lengths must be positive and finite (fx = {}, fy = {})",
                self.fx, self.fy
            )));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "principal point ({}, {}) is not finite",
                self.cx, self.cy
            )));
        }
        if self.width == 0 || self.height == 0 {
            return Err(GeometryError::InvalidIntrinsics(format!(
                "image size {}×{} is empty",
                self.width, self.height
            )));
        }
        Ok(())
    }

    /// Validates this camera ([`Intrinsics::validate`]) and that `image` (a depth map or a
    /// mask of this camera's view) has its size: what every function taking a view checks
    /// before it reads a pixel.
    pub fn check_image<T>(&self, image: &crate::Image<T>) -> Result<(), GeometryError> {
        self.validate()?;
        image.check_size(self.width, self.height)
    }

    /// The 3×3 matrix K, row-major (`cam_K` in BOP files).
    pub fn k_row_major(&self) -> [[f64; 3]; 3] {
        [
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }

    /// Projects a camera-frame point to continuous pixel coordinates `(u, v)`; `None` when the
    /// point is not in front of the camera (z ≤ 0).
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// The pixel whose centre is nearest to the projection, if it is inside the image.
    pub fn project_to_pixel(&self, p: DVec3) -> Option<(u32, u32)> {
        let (u, v) = self.project(p)?;
        let (u, v) = (u.round(), v.round());
        (u >= 0.0 && v >= 0.0 && u < self.width as f64 && v < self.height as f64)
            .then_some((u as u32, v as u32))
    }

    /// The camera-frame point at pixel `(u, v)` with depth `z` (camera-frame z, not ray length).
    pub fn back_project(&self, u: f64, v: f64, z: f64) -> DVec3 {
        DVec3::new((u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z)
    }

    /// Back-projects every pixel with a valid depth (finite, > 0), optionally only under
    /// `mask`, to camera-frame points, in row-major pixel order. Fails when the depth map or
    /// mask size differs from the intrinsics.
    pub fn back_project_depth(
        &self,
        depth: &DepthImage,
        mask: Option<&Mask>,
    ) -> Result<Vec<Vec3>, GeometryError> {
        depth.check_size(self.width, self.height)?;
        if let Some(m) = mask {
            m.check_size(self.width, self.height)?;
        }
        let w = self.width as usize;
        let mut out = Vec::new();
        for (i, &z) in depth.data.iter().enumerate() {
            if !(z.is_finite() && z > 0.0) || mask.is_some_and(|m| !m.data[i]) {
                continue;
            }
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            out.push(self.back_project(u, v, z as f64).as_vec3());
        }
        Ok(out)
    }

    /// The same camera at another resolution (principal point and focal lengths scaled so the
    /// field of view is unchanged, pixel centres kept consistent).
    pub fn resized(&self, width: u32, height: u32) -> Intrinsics {
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        Intrinsics {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            width,
            height,
        }
    }
}

/// The world→camera pose of a camera at `eye` looking at `target`, with `up` (world) pointing
/// roughly to the top of the image (camera −y). Fails when `eye == target` or `up` is parallel
/// to the viewing direction.
pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> Result<Pose, GeometryError> {
    let z = (target - eye)
        .try_normalize()
        .ok_or_else(|| GeometryError::InvalidParameter {
            name: "look_at",
            message: "eye and target coincide".into(),
        })?;
    let x = z
        .cross(up)
        .try_normalize()
        .ok_or_else(|| GeometryError::InvalidParameter {
            name: "look_at",
            message: "up is parallel to the viewing direction".into(),
        })?;
    let y = z.cross(x);
    // Rows of the world→camera rotation are the camera axes expressed in the world.
    let rotation = DMat3::from_cols(x, y, z).transpose();
    Ok(Pose::new(rotation, -(rotation * eye)))
}

/// A viewpoint on a sphere around a target: angles in degrees, distance in scene units.
///
/// World frame: z up. Elevation is measured from the xy-plane towards +z, azimuth from +x
/// towards +y: `eye = target + d·(cos e·cos a, cos e·sin a, sin e)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Viewpoint {
    pub elevation_deg: f64,
    pub azimuth_deg: f64,
    pub distance: f64,
}

impl Viewpoint {
    /// The camera position relative to the target.
    pub fn offset(&self) -> DVec3 {
        let (e, a) = (
            self.elevation_deg.to_radians(),
            self.azimuth_deg.to_radians(),
        );
        self.distance * DVec3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
    }

    /// The world→camera pose looking at `target` with world +z up in the image. At exactly 90°
    /// elevation world +y is used as the up direction instead.
    pub fn camera_pose(&self, target: DVec3) -> Result<Pose, GeometryError> {
        let eye = target + self.offset();
        look_at(eye, target, DVec3::Z).or_else(|_| look_at(eye, target, DVec3::Y))
    }
}

/// The distribution of the paper's viewpoints: elevation and azimuth uniform in ranges
/// (degrees), fixed distance.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewSphere {
    pub elevation_deg: (f64, f64),
    pub azimuth_deg: (f64, f64),
    pub distance: f64,
}

impl ViewSphere {
    /// The paper's ranges: elevation [15°, 75°], azimuth [0°, 89°], at `distance`.
    pub fn paper(distance: f64) -> Self {
        ViewSphere {
            elevation_deg: (15.0, 75.0),
            azimuth_deg: (0.0, 89.0),
            distance,
        }
    }

    /// Draws a viewpoint.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> Viewpoint {
        let uni = |rng: &mut R, (lo, hi): (f64, f64)| {
            if hi > lo {
                rng.random_range(lo..=hi)
            } else {
                lo
            }
        };
        Viewpoint {
            elevation_deg: uni(rng, self.elevation_deg),
            azimuth_deg: uni(rng, self.azimuth_deg),
            distance: self.distance,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn look_at_puts_target_on_the_optical_axis_and_up_at_the_top() {
        let eye = DVec3::new(3.0, 1.0, 2.0);
        let pose = look_at(eye, DVec3::ZERO, DVec3::Z).unwrap();
        let t = pose.apply(DVec3::ZERO);
        assert!(t.x.abs() < 1e-12 && t.y.abs() < 1e-12 && (t.z - eye.length()).abs() < 1e-12);
        // A point above the target appears above the centre: negative camera y.
        assert!(pose.apply(DVec3::Z * 0.1).y < 0.0);
        assert!((pose.rotation.determinant() - 1.0).abs() < 1e-12);
        assert!(look_at(eye, eye, DVec3::Z).is_err());
        assert!(look_at(DVec3::Z, DVec3::ZERO, DVec3::Z).is_err());
    }

    #[test]
    fn viewpoint_samples_stay_in_range_and_are_seeded() {
        let vs = ViewSphere::paper(2.5);
        let mut a = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut b = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for _ in 0..200 {
            let v = vs.sample(&mut a);
            assert_eq!(v, vs.sample(&mut b));
            assert!(
                (15.0..=75.0).contains(&v.elevation_deg) && (0.0..=89.0).contains(&v.azimuth_deg)
            );
            let p = v.camera_pose(DVec3::ZERO).unwrap();
            assert!((p.apply(DVec3::ZERO).z - 2.5).abs() < 1e-9);
        }
        let top = Viewpoint {
            elevation_deg: 90.0,
            azimuth_deg: 0.0,
            distance: 1.0,
        };
        assert!(top.camera_pose(DVec3::ZERO).is_ok());
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(256))]

        #[test]
        fn project_then_back_project_is_the_identity(
            x in -3.0f64..3.0, y in -3.0f64..3.0, z in 0.05f64..20.0,
            fx in 50.0f64..2000.0, fy in 50.0f64..2000.0, cx in -100.0f64..800.0, cy in -100.0f64..600.0,
        ) {
            let k = Intrinsics::new(fx, fy, cx, cy, 640, 480).unwrap();
            let p = DVec3::new(x, y, z);
            let (u, v) = k.project(p).unwrap();
            let back = k.back_project(u, v, z);
            proptest::prop_assert!(back.abs_diff_eq(p, 1e-9 * (1.0 + p.length())), "{p} -> ({u}, {v}) -> {back}");
            // And the other way round: pixel -> point -> pixel.
            let (u2, v2) = k.project(k.back_project(u, v, z)).unwrap();
            proptest::prop_assert!((u2 - u).abs() < 1e-6 && (v2 - v).abs() < 1e-6);
        }
    }

    #[test]
    fn depth_map_back_projection_reprojects_onto_its_pixels() {
        let k = Intrinsics::from_fov_y(32, 24, 60.0).unwrap();
        let depth = DepthImage::from_vec(
            32,
            24,
            (0..32 * 24).map(|i| 1.0 + (i % 7) as f32 * 0.25).collect(),
        )
        .unwrap();
        let points = k.back_project_depth(&depth, None).unwrap();
        assert_eq!(points.len(), 32 * 24);
        for (i, p) in points.iter().enumerate() {
            let (u, v) = k.project_to_pixel(p.as_dvec3()).unwrap();
            assert_eq!((u as usize, v as usize), (i % 32, i / 32));
            assert_eq!(p.z, depth.data[i]);
        }
    }

    #[test]
    fn invalid_intrinsics_are_rejected() {
        assert!(Intrinsics::new(0.0, 500.0, 320.0, 240.0, 640, 480).is_err());
        assert!(Intrinsics::new(500.0, f64::NAN, 320.0, 240.0, 640, 480).is_err());
        assert!(Intrinsics::new(500.0, 500.0, 320.0, 240.0, 0, 480).is_err());
        assert!(Intrinsics::from_fov_y(640, 480, 0.0).is_err());
    }

    #[test]
    fn check_image_rejects_a_bad_camera_before_the_size_and_a_wrong_size_after() {
        let k = Intrinsics::new(100.0, 100.0, 1.0, 0.5, 3, 2).unwrap();
        assert!(k.check_image(&DepthImage::filled(3, 2, 1.0)).is_ok());
        assert!(matches!(
            k.check_image(&Mask::from_vec(2, 3, vec![true; 6]).unwrap()),
            Err(GeometryError::ImageSizeMismatch {
                got_width: 2,
                got_height: 3,
                ..
            })
        ));
        // A camera built field by field (e.g. deserialised) is validated, not trusted.
        let bad = Intrinsics { fx: -1.0, ..k };
        assert!(matches!(
            bad.check_image(&DepthImage::filled(3, 2, 1.0)),
            Err(GeometryError::InvalidIntrinsics(_))
        ));
    }

    #[test]
    fn back_projection_honours_mask_and_skips_invalid_depth() {
        let k = Intrinsics::new(100.0, 100.0, 1.0, 0.5, 3, 2).unwrap();
        let depth = DepthImage::from_vec(3, 2, vec![1.0, 0.0, f32::NAN, 2.0, 2.0, -1.0]).unwrap();
        let all = k.back_project_depth(&depth, None).unwrap();
        assert_eq!(all.len(), 3);
        assert!(all[0].abs_diff_eq(Vec3::new(-0.01, -0.005, 1.0), 1e-7));
        let mask = Mask::from_vec(3, 2, vec![false, true, true, false, true, true]).unwrap();
        let masked = k.back_project_depth(&depth, Some(&mask)).unwrap();
        assert_eq!(masked, vec![Vec3::new(0.0, 0.01, 2.0)]);
        let wrong = DepthImage::filled(2, 2, 1.0);
        assert!(matches!(
            k.back_project_depth(&wrong, None),
            Err(GeometryError::ImageSizeMismatch { .. })
        ));
    }
}
