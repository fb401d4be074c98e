//! Pinhole cameras: what looks at a Gaussian set.
//!
//! Conventions, shared with the model (C4G_MODEL.md) and the rasterizers:
//! - Axes are OpenCV's: x right, y down, z forward (into the scene); a point is in front of the
//!   camera when its camera-space z is positive.
//! - The pose is stored world-to-camera (`p_cam = R p_world + t`), the form projection needs.
//! - Pixel coordinates: `u = fx · x/z + cx`, `v = fy · y/z + cy`, with pixel `(i, j)` covering
//!   `[i, i + 1) × [j, j + 1)`; so a principal point at the image centre is `(W/2, H/2)`.
//! - The model speaks of *normalised* intrinsics, fractions of the image size (its default is
//!   fx = fy = 0.8767, principal point at the centre); [`NormalizedIntrinsics`] converts them to
//!   pixels for any output resolution.

use glam::{Affine3A, Mat3, Mat4, Vec2, Vec3, Vec4};

use crate::SceneError;

/// Intrinsics as fractions of the image size: `fx` and `cx` of the width, `fy` and `cy` of the
/// height. Independent of resolution, which is how the model's training data states them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NormalizedIntrinsics {
    /// Focal length over image width.
    pub fx: f32,
    /// Focal length over image height.
    pub fy: f32,
    /// Principal point x over image width.
    pub cx: f32,
    /// Principal point y over image height.
    pub cy: f32,
}

impl NormalizedIntrinsics {
    /// The intrinsics the C4G reference renders with: fx = fy = 0.8767, principal point centred.
    pub const C4G_DEFAULT: Self = Self {
        fx: 0.8767,
        fy: 0.8767,
        cx: 0.5,
        cy: 0.5,
    };

    /// The same camera in pixels for a `width` × `height` image.
    pub fn to_pixels(&self, width: u32, height: u32) -> Intrinsics {
        let (w, h) = (width as f32, height as f32);
        Intrinsics {
            fx: self.fx * w,
            fy: self.fy * h,
            cx: self.cx * w,
            cy: self.cy * h,
            width,
            height,
        }
    }
}

impl Default for NormalizedIntrinsics {
    fn default() -> Self {
        Self::C4G_DEFAULT
    }
}

/// Pinhole intrinsics in pixels, with the image size they belong to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length in pixels along x.
    pub fx: f32,
    /// Focal length in pixels along y.
    pub fy: f32,
    /// Principal point x in pixels.
    pub cx: f32,
    /// Principal point y in pixels.
    pub cy: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Intrinsics {
    /// Checks that these can describe a camera: a non-empty image, positive finite focal lengths
    /// and a finite principal point.
    pub fn validate(&self) -> Result<(), SceneError> {
        if self.width == 0 || self.height == 0 {
            return Err(SceneError::InvalidCamera(format!(
                "image size {}x{} is empty",
                self.width, self.height
            )));
        }
        let focal_ok = |f: f32| f.is_finite() && f > 0.0;
        if !focal_ok(self.fx) || !focal_ok(self.fy) {
            return Err(SceneError::InvalidCamera(format!(
                "focal lengths ({}, {}) must be positive and finite",
                self.fx, self.fy
            )));
        }
        if !self.cx.is_finite() || !self.cy.is_finite() {
            return Err(SceneError::InvalidCamera(format!(
                "principal point ({}, {}) must be finite",
                self.cx, self.cy
            )));
        }
        Ok(())
    }

    /// The same camera as fractions of the image size.
    pub fn normalized(&self) -> NormalizedIntrinsics {
        let (w, h) = (self.width as f32, self.height as f32);
        NormalizedIntrinsics {
            fx: self.fx / w,
            fy: self.fy / h,
            cx: self.cx / w,
            cy: self.cy / h,
        }
    }

    /// The calibration matrix K (column-major, as glam stores it).
    pub fn matrix(&self) -> Mat3 {
        Mat3::from_cols(
            Vec3::new(self.fx, 0.0, 0.0),
            Vec3::new(0.0, self.fy, 0.0),
            Vec3::new(self.cx, self.cy, 1.0),
        )
    }

    /// Tangents of the half fields of view, (W / 2fx, H / 2fy): the x/z and y/z of the image
    /// border for a centred principal point.
    pub fn tan_half_fov(&self) -> Vec2 {
        Vec2::new(
            self.width as f32 / (2.0 * self.fx),
            self.height as f32 / (2.0 * self.fy),
        )
    }
}

/// A pinhole camera: intrinsics in pixels and a world-to-camera pose (OpenCV axes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    intrinsics: Intrinsics,
    world_to_camera: Affine3A,
}

impl Camera {
    /// A camera from pixel intrinsics and a world-to-camera transform.
    ///
    /// Fails on invalid intrinsics or a pose that is not finite and invertible.
    pub fn new(intrinsics: Intrinsics, world_to_camera: Affine3A) -> Result<Self, SceneError> {
        intrinsics.validate()?;
        let det = world_to_camera.matrix3.determinant();
        if !world_to_camera.is_finite() || !det.is_finite() || det.abs() < 1e-12 {
            return Err(SceneError::InvalidCamera(format!(
                "world-to-camera transform must be finite and invertible (determinant {det})"
            )));
        }
        Ok(Self {
            intrinsics,
            world_to_camera,
        })
    }

    /// A camera from normalised intrinsics rendered at `width` × `height`.
    pub fn from_normalized(
        intrinsics: NormalizedIntrinsics,
        width: u32,
        height: u32,
        world_to_camera: Affine3A,
    ) -> Result<Self, SceneError> {
        Self::new(intrinsics.to_pixels(width, height), world_to_camera)
    }

    /// A camera from a 4x4 world-to-camera matrix, whose last row must be (0, 0, 0, 1).
    pub fn from_world_to_camera_matrix(
        intrinsics: Intrinsics,
        world_to_camera: Mat4,
    ) -> Result<Self, SceneError> {
        if world_to_camera.row(3) != Vec4::W {
            return Err(SceneError::InvalidCamera(format!(
                "a rigid pose matrix ends in the row (0, 0, 0, 1), got {}",
                world_to_camera.row(3)
            )));
        }
        Self::new(intrinsics, Affine3A::from_mat4(world_to_camera))
    }

    /// A camera placed by its camera-to-world transform (its pose in the world).
    pub fn from_camera_to_world(
        intrinsics: Intrinsics,
        camera_to_world: Affine3A,
    ) -> Result<Self, SceneError> {
        let det = camera_to_world.matrix3.determinant();
        if !camera_to_world.is_finite() || !det.is_finite() || det.abs() < 1e-12 {
            return Err(SceneError::InvalidCamera(format!(
                "camera-to-world transform must be finite and invertible (determinant {det})"
            )));
        }
        Self::new(intrinsics, camera_to_world.inverse())
    }

    /// Pixel intrinsics.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.intrinsics.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.intrinsics.height
    }

    /// World-to-camera transform.
    pub fn world_to_camera(&self) -> Affine3A {
        self.world_to_camera
    }

    /// World-to-camera transform as a 4x4 matrix.
    pub fn world_to_camera_matrix(&self) -> Mat4 {
        Mat4::from(self.world_to_camera)
    }

    /// Camera-to-world transform (the camera's pose in the world).
    pub fn camera_to_world(&self) -> Affine3A {
        self.world_to_camera.inverse()
    }

    /// The camera centre in world coordinates.
    pub fn position(&self) -> Vec3 {
        self.camera_to_world().translation.into()
    }

    /// A world point in camera coordinates.
    pub fn to_camera(&self, world: Vec3) -> Vec3 {
        self.world_to_camera.transform_point3(world)
    }

    /// Projects a world point to pixel coordinates; `None` when it is not in front of the camera.
    pub fn project(&self, world: Vec3) -> Option<Vec2> {
        let p = self.to_camera(world);
        if p.z <= 0.0 || !p.is_finite() {
            return None;
        }
        let k = &self.intrinsics;
        Some(Vec2::new(k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy))
    }
}

#[cfg(test)]
mod tests {
    use glam::Quat;

    use super::*;

    fn default_camera(width: u32, height: u32) -> Camera {
        Camera::from_normalized(
            NormalizedIntrinsics::C4G_DEFAULT,
            width,
            height,
            Affine3A::IDENTITY,
        )
        .unwrap()
    }

    #[test]
    fn normalized_defaults_scale_with_the_image_size() {
        let k = NormalizedIntrinsics::default().to_pixels(224, 224);
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy),
            (0.8767 * 224.0, 0.8767 * 224.0, 112.0, 112.0)
        );
        let k = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(960, 540);
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy),
            (0.8767 * 960.0, 0.8767 * 540.0, 480.0, 270.0)
        );
        let back = k.normalized();
        assert!((back.fx - 0.8767).abs() < 1e-6 && (back.cy - 0.5).abs() < 1e-6);
    }

    #[test]
    fn a_point_on_the_optical_axis_projects_to_the_principal_point() {
        let cam = default_camera(224, 224);
        assert_eq!(
            cam.project(Vec3::new(0.0, 0.0, 3.0)),
            Some(Vec2::new(112.0, 112.0))
        );
    }

    #[test]
    fn opencv_axes_put_positive_y_below_the_centre() {
        let cam = default_camera(200, 100);
        let uv = cam.project(Vec3::new(1.0, 1.0, 2.0)).unwrap();
        let k = cam.intrinsics();
        assert!((uv.x - (k.fx * 0.5 + 100.0)).abs() < 1e-4);
        assert!((uv.y - (k.fy * 0.5 + 50.0)).abs() < 1e-4);
        assert!(uv.y > 50.0, "y down");
    }

    #[test]
    fn points_behind_the_camera_do_not_project() {
        let cam = default_camera(64, 64);
        assert_eq!(cam.project(Vec3::new(0.0, 0.0, -1.0)), None);
        assert_eq!(cam.project(Vec3::ZERO), None);
    }

    #[test]
    fn pose_round_trips_between_its_forms() {
        let rotation = Quat::from_rotation_y(0.3) * Quat::from_rotation_x(-0.2);
        let cam_to_world = Affine3A::from_rotation_translation(rotation, Vec3::new(1.0, -2.0, 0.5));
        let k = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(64, 48);
        let cam = Camera::from_camera_to_world(k, cam_to_world).unwrap();
        assert!((cam.position() - Vec3::new(1.0, -2.0, 0.5)).length() < 1e-5);
        let again = Camera::from_world_to_camera_matrix(k, cam.world_to_camera_matrix()).unwrap();
        assert!(
            again
                .world_to_camera()
                .abs_diff_eq(cam.world_to_camera(), 1e-6)
        );
        // A point one unit ahead of the camera projects to the principal point.
        let ahead = cam_to_world.transform_point3(Vec3::Z);
        let uv = cam.project(ahead).unwrap();
        assert!((uv - Vec2::new(32.0, 24.0)).length() < 1e-3);
    }

    #[test]
    fn invalid_cameras_are_rejected() {
        let good = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(64, 64);
        let zero_size = Intrinsics { width: 0, ..good };
        assert!(Camera::new(zero_size, Affine3A::IDENTITY).is_err());
        let bad_focal = Intrinsics { fx: -1.0, ..good };
        assert!(Camera::new(bad_focal, Affine3A::IDENTITY).is_err());
        let nan_centre = Intrinsics {
            cx: f32::NAN,
            ..good
        };
        assert!(Camera::new(nan_centre, Affine3A::IDENTITY).is_err());
        let singular = Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0));
        assert!(Camera::new(good, singular).is_err());
        let projective = Mat4::from_cols(Vec4::X, Vec4::Y, Vec4::Z, Vec4::new(0.0, 0.0, 1.0, 2.0));
        assert!(Camera::from_world_to_camera_matrix(good, projective).is_err());
        let translation_nan = Affine3A::from_translation(Vec3::new(f32::NAN, 0.0, 0.0));
        assert!(Camera::new(good, translation_nan).is_err());
    }

    #[test]
    fn calibration_matrix_maps_camera_points_to_homogeneous_pixels() {
        let cam = default_camera(100, 80);
        let p = Vec3::new(0.3, -0.2, 2.0);
        let h = cam.intrinsics().matrix() * p;
        let uv = cam.project(p).unwrap();
        assert!((Vec2::new(h.x / h.z, h.y / h.z) - uv).length() < 1e-4);
        let tan = cam.intrinsics().tan_half_fov();
        assert!((tan.x - 1.0 / (2.0 * 0.8767)).abs() < 1e-6);
    }
}
