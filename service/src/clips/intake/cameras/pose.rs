//! One frame's given camera: a rigid world-to-camera pose (OpenCV axes) and intrinsics as
//! fractions of the image size, checked once here whatever form it came in.

use glam::{DMat3, DQuat, DVec3};
use serde::{Deserialize, Serialize};

use crate::ServiceError;

/// Largest normalised focal length, and principal point offset, of a camera.
pub const FOCAL_BOUND: f64 = 1000.0;

/// Smallest positive length (focal length, depth, radius) a camera (given, or stated in a request) or preset may state.
pub const SMALLEST_LENGTH: f64 = 1e-6;

/// How far a given rotation may be from orthonormal (largest entry of RᵀR − I): files written
/// with six or seven significant digits stay well under it, a scaled or sheared matrix does not.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// Largest translation a given camera may state: any real capture's coordinates, and far from
/// where squaring them loses every digit.
pub const TRANSLATION_BOUND: f64 = 1e12;

/// Intrinsics as fractions of the image size (as `CameraSpec` states them).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Focal length over width.
    pub fx: f64,
    /// Focal length over height.
    pub fy: f64,
    /// Principal point x over width.
    #[serde(default = "half")]
    pub cx: f64,
    /// Principal point y over height.
    #[serde(default = "half")]
    pub cy: f64,
}

fn half() -> f64 {
    0.5
}

impl Intrinsics {
    /// The model's own (fx = fy = 0.8767, centred), for cameras that state none.
    pub const C4G_DEFAULT: Self = Self {
        fx: 0.8767,
        fy: 0.8767,
        cx: 0.5,
        cy: 0.5,
    };

    /// Pixel intrinsics of a `width` × `height` image as fractions of its size (the pixel
    /// conventions agree: COLMAP's, nerfstudio's and ours put the image centre at W/2, H/2).
    pub fn from_pixels(
        [fx, fy, cx, cy]: [f64; 4],
        width: f64,
        height: f64,
        name: &str,
    ) -> Result<Self, ServiceError> {
        if !(width.is_finite() && height.is_finite() && width >= 1.0 && height >= 1.0) {
            return Err(ServiceError::invalid(format!(
                "{name}: the image size must be at least 1x1 pixels, got {width}x{height}"
            )));
        }
        Self {
            fx: fx / width,
            fy: fy / height,
            cx: cx / width,
            cy: cy / height,
        }
        .checked(name)
    }

    /// Fractions of the whole `width` × `height` frame (as uploads state them) as fractions of
    /// its centred square crop (as the model's own camera, and cameras recovered from its
    /// views, are): one pixel seen alike.
    pub fn frame_to_crop(self, width: u32, height: u32) -> Self {
        let (w, h, side) = sides(width, height);
        Self {
            fx: self.fx * w / side,
            fy: self.fy * h / side,
            cx: (self.cx * w - (w - side) / 2.0) / side,
            cy: (self.cy * h - (h - side) / 2.0) / side,
        }
    }

    /// The inverse of [`frame_to_crop`](Self::frame_to_crop).
    pub fn crop_to_frame(self, width: u32, height: u32) -> Self {
        let (w, h, side) = sides(width, height);
        Self {
            fx: self.fx * side / w,
            fy: self.fy * side / h,
            cx: (self.cx * side + (w - side) / 2.0) / w,
            cy: (self.cy * side + (h - side) / 2.0) / h,
        }
    }

    /// These intrinsics, when every value is finite and in the range `CameraSpec` accepts.
    pub fn checked(self, name: &str) -> Result<Self, ServiceError> {
        let focal = SMALLEST_LENGTH..=FOCAL_BOUND;
        let offset = -FOCAL_BOUND..=FOCAL_BOUND;
        for (field, v, range) in [
            ("fx", self.fx, &focal),
            ("fy", self.fy, &focal),
            ("cx", self.cx, &offset),
            ("cy", self.cy, &offset),
        ] {
            if !range.contains(&v) {
                return Err(ServiceError::invalid(format!(
                    "{name}: intrinsics {field} must be between {:e} and {:e} as a fraction of \
                     the image size, got {v}",
                    range.start(),
                    range.end()
                )));
            }
        }
        Ok(self)
    }
}

/// A frame's width, height and the side of its centred square crop, at least 1 pixel.
fn sides(width: u32, height: u32) -> (f64, f64, f64) {
    let (w, h) = (f64::from(width.max(1)), f64::from(height.max(1)));
    (w, h, w.min(h))
}

/// A frame's camera as given: `p_cam = rotation · p_world + translation`, OpenCV axes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GivenCamera {
    /// World-to-camera rotation (orthonormal, determinant +1).
    pub rotation: DMat3,
    /// World-to-camera translation.
    pub translation: DVec3,
    /// Normalised intrinsics.
    pub intrinsics: Intrinsics,
}

impl GivenCamera {
    /// A camera from a row-major 4×4 world-to-camera matrix.
    pub fn from_world_to_camera(
        m: &[f64],
        intrinsics: Intrinsics,
        name: &str,
    ) -> Result<Self, ServiceError> {
        let (rotation, translation) = rigid_rows(m, name)?;
        Self::new(rotation, translation, intrinsics, name)
    }

    /// A camera from a row-major 4×4 camera-to-world matrix (OpenCV axes).
    pub fn from_camera_to_world(
        m: &[f64],
        intrinsics: Intrinsics,
        name: &str,
    ) -> Result<Self, ServiceError> {
        let (r, centre) = rigid_rows(m, name)?;
        let rotation = r.transpose();
        Self::new(rotation, -(rotation * centre), intrinsics, name)
    }

    /// A camera from a rotation quaternion (w, x, y, z; any non-zero length) and a translation,
    /// both world-to-camera, as COLMAP writes them.
    pub fn from_quaternion(
        [w, x, y, z]: [f64; 4],
        translation: DVec3,
        intrinsics: Intrinsics,
        name: &str,
    ) -> Result<Self, ServiceError> {
        let q = DQuat::from_xyzw(x, y, z, w);
        let length = q.length();
        if !(length.is_finite() && length > 1e-9) {
            return Err(ServiceError::invalid(format!(
                "{name}: the rotation quaternion must be finite and not zero, got \
                 ({w}, {x}, {y}, {z})"
            )));
        }
        Self::new(DMat3::from_quat(q / length), translation, intrinsics, name)
    }

    fn new(
        rotation: DMat3,
        translation: DVec3,
        intrinsics: Intrinsics,
        name: &str,
    ) -> Result<Self, ServiceError> {
        check_rotation(&rotation, name)?;
        if let Some(v) = translation
            .to_array()
            .into_iter()
            .find(|v| !v.is_finite() || v.abs() > TRANSLATION_BOUND)
        {
            return Err(ServiceError::invalid(format!(
                "{name}: a translation must be finite and at most {TRANSLATION_BOUND:e} in size, \
                 got {v}"
            )));
        }
        Ok(Self {
            // Re-orthonormalised through a unit quaternion: rounding in the file must not turn
            // into scale once poses are composed.
            rotation: DMat3::from_quat(DQuat::from_mat3(&rotation).normalize()),
            translation,
            intrinsics: intrinsics.checked(name)?,
        })
    }

    /// The camera's centre in the world.
    pub fn centre(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// The world-to-camera pose as a row-major 4×4 matrix.
    pub fn world_to_camera_rows(&self) -> Vec<f64> {
        let (r, t) = (self.rotation, self.translation);
        vec![
            r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x, //
            r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y, //
            r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z, //
            0.0, 0.0, 0.0, 1.0,
        ]
    }
}

/// The rotation and translation columns of a row-major rigid 4×4 matrix.
fn rigid_rows(m: &[f64], name: &str) -> Result<(DMat3, DVec3), ServiceError> {
    if m.len() != 16 {
        return Err(ServiceError::invalid(format!(
            "{name}: a pose needs 16 numbers (row-major 4x4), got {}",
            m.len()
        )));
    }
    if let Some((i, v)) = m.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(ServiceError::invalid(format!(
            "{name}: entry {i} of the pose is {v}; every entry must be a finite number"
        )));
    }
    let last = [m[12], m[13], m[14], m[15]];
    if last
        .iter()
        .zip([0.0, 0.0, 0.0, 1.0])
        .any(|(a, b)| (a - b).abs() > 1e-6)
    {
        return Err(ServiceError::invalid(format!(
            "{name}: a pose must end in the row 0 0 0 1, got {last:?}"
        )));
    }
    let rotation = DMat3::from_cols_array(&[m[0], m[4], m[8], m[1], m[5], m[9], m[2], m[6], m[10]]);
    Ok((rotation, DVec3::new(m[3], m[7], m[11])))
}

fn check_rotation(r: &DMat3, name: &str) -> Result<(), ServiceError> {
    let error = (r.transpose() * *r - DMat3::IDENTITY)
        .to_cols_array()
        .into_iter()
        .fold(0.0_f64, |a, v| a.max(v.abs()));
    // Entries are finite by now; NaN is refused all the same should that change.
    if error.is_nan() || error > ROTATION_TOLERANCE {
        return Err(ServiceError::invalid(format!(
            "{name}: the pose's 3x3 part is not a rotation (RᵀR differs from the identity by \
             {error:.3e}, more than {ROTATION_TOLERANCE:e}): no scale or shear is allowed"
        )));
    }
    if r.determinant() <= 0.0 {
        return Err(ServiceError::invalid(format!(
            "{name}: the pose's 3x3 part is a reflection (determinant {:.3}), not a rotation: \
             check the handedness of the axes",
            r.determinant()
        )));
    }
    Ok(())
}
