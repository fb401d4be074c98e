//! A camera adjustment: a rigid motion and a focal scale put in front of a camera's
//! world-to-camera pose, held in f64, and the exponential map that makes one from the seven
//! numbers alignment solves for.
//!
//! Why a group element and not just a tangent: Gauss–Newton linearises at the current camera and
//! steps from there, so steps compose on the left (`exp(step) ∘ current`), which tangents do not
//! do by addition. And why f64 beside the f32 [`Camera`]: finite differences of a render with
//! respect to the camera take steps of 1e-7, which an f32 pose would round away; the
//! differentiable render reads the adjustment in f64, and only [`CameraAdjustment::apply`] rounds
//! to a `Camera`.

use glam::{Affine3A, DMat3, DVec3, Mat3A, Vec3A};

use c4g_scene::{Camera, Intrinsics, SceneError};

/// The number of camera parameters a [`super::CameraJacobian`] differentiates by, in this order:
/// the rotation ω (3, radians, about the camera's axes), the translation ν (3, scene units, along
/// the camera's axes) of a left-multiplied se(3) perturbation of world-to-camera, then the log of
/// a scale shared by fx and fy (the principal point stays).
pub const CAMERA_PARAMETERS: usize = 7;

/// Names of the [`CAMERA_PARAMETERS`], in order (for messages and reports).
pub const CAMERA_PARAMETER_NAMES: [&str; CAMERA_PARAMETERS] =
    ["ωx", "ωy", "ωz", "νx", "νy", "νz", "log focal"];

/// A rigid motion `(R, t)` and a focal scale `s`, applied to a camera after its own pose: the
/// adjusted camera maps a world point `p` to `R (W p + t_cam) + t` and has focal lengths
/// `s·fx`, `s·fy` (principal point and image size unchanged). `W` need not be a rotation; `R` is
/// one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraAdjustment {
    rotation: DMat3,
    translation: DVec3,
    focal_scale: f64,
}

impl Default for CameraAdjustment {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl CameraAdjustment {
    /// No change.
    pub const IDENTITY: Self = Self {
        rotation: DMat3::IDENTITY,
        translation: DVec3::ZERO,
        focal_scale: 1.0,
    };

    /// The exponential map: `[ωx, ωy, ωz, νx, νy, νz, log focal]` ([`CAMERA_PARAMETERS`]) to the
    /// adjustment `exp([ω, ν]^)` of SE(3) (rotation by |ω| about ω, translation `V(ω) ν`) and the
    /// focal scale `e^{log focal}`. Its derivative at zero is the identity: moving a camera-space
    /// point `p` by `ω × p + ν`, which is what [`super::CameraJacobian`] differentiates by.
    pub fn exp(tangent: [f64; CAMERA_PARAMETERS]) -> Self {
        let omega = DVec3::new(tangent[0], tangent[1], tangent[2]);
        let nu = DVec3::new(tangent[3], tangent[4], tangent[5]);
        let theta2 = omega.length_squared();
        let theta = theta2.sqrt();
        // sin θ / θ, (1 − cos θ) / θ², (θ − sin θ) / θ³; Taylor series where they cancel.
        let (a, b, c) = if theta < 1e-4 {
            (
                1.0 - theta2 / 6.0,
                0.5 - theta2 / 24.0,
                1.0 / 6.0 - theta2 / 120.0,
            )
        } else {
            (
                theta.sin() / theta,
                (1.0 - theta.cos()) / theta2,
                (theta - theta.sin()) / (theta2 * theta),
            )
        };
        let k = skew(omega);
        let k2 = k * k;
        Self {
            rotation: DMat3::IDENTITY + k * a + k2 * b,
            translation: (DMat3::IDENTITY + k * b + k2 * c) * nu,
            focal_scale: tangent[6].exp(),
        }
    }

    /// This adjustment followed by `outer`: `outer ∘ self`, what a step of alignment does to the
    /// current adjustment (`current.then(&CameraAdjustment::exp(step))`).
    pub fn then(&self, outer: &Self) -> Self {
        Self {
            rotation: outer.rotation * self.rotation,
            translation: outer.rotation * self.translation + outer.translation,
            focal_scale: outer.focal_scale * self.focal_scale,
        }
    }

    /// The rotation `R`.
    pub fn rotation(&self) -> DMat3 {
        self.rotation
    }

    /// The translation `t` (camera-space, after the rotation).
    pub fn translation(&self) -> DVec3 {
        self.translation
    }

    /// The factor on both focal lengths.
    pub fn focal_scale(&self) -> f64 {
        self.focal_scale
    }

    /// The angle of the rotation, radians in `[0, π]`.
    pub fn rotation_angle(&self) -> f64 {
        let r = &self.rotation;
        let cos = 0.5 * (r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0);
        cos.clamp(-1.0, 1.0).acos()
    }

    /// The adjusted camera, rounded to f32.
    ///
    /// Fails (`InvalidCamera`) when the result is not a camera: an adjustment with non-finite
    /// numbers, or a focal scale that overflows f32.
    pub fn apply(&self, camera: &Camera) -> Result<Camera, SceneError> {
        let (matrix, translation, k) = self.apply_f64(camera);
        let to_f32 = |v: DVec3| Vec3A::new(v.x as f32, v.y as f32, v.z as f32);
        let pose = Affine3A {
            matrix3: Mat3A::from_cols(
                to_f32(matrix.x_axis),
                to_f32(matrix.y_axis),
                to_f32(matrix.z_axis),
            ),
            translation: to_f32(translation),
        };
        Camera::new(
            Intrinsics {
                fx: k[0] as f32,
                fy: k[1] as f32,
                ..*camera.intrinsics()
            },
            pose,
        )
    }

    /// The adjusted camera in f64: world-to-camera matrix and translation, and `(fx, fy)`.
    pub(super) fn apply_f64(&self, camera: &Camera) -> (DMat3, DVec3, [f64; 2]) {
        let pose = camera.world_to_camera();
        let w = DMat3::from_cols(
            pose.matrix3.x_axis.as_dvec3(),
            pose.matrix3.y_axis.as_dvec3(),
            pose.matrix3.z_axis.as_dvec3(),
        );
        let k = camera.intrinsics();
        (
            self.rotation * w,
            self.rotation * pose.translation.as_dvec3() + self.translation,
            [
                f64::from(k.fx) * self.focal_scale,
                f64::from(k.fy) * self.focal_scale,
            ],
        )
    }

    /// True when every number is finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite() && self.focal_scale.is_finite()
    }
}

/// `[v]×`: the matrix of `p ↦ v × p`.
pub(super) fn skew(v: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, v.z, -v.y),
        DVec3::new(-v.z, 0.0, v.x),
        DVec3::new(v.y, -v.x, 0.0),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_of_zero_is_the_identity() {
        assert_eq!(CameraAdjustment::exp([0.0; 7]), CameraAdjustment::IDENTITY);
    }

    #[test]
    fn exp_rotates_by_the_vector_length_about_its_direction() {
        let a = CameraAdjustment::exp([0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]);
        let p = a.rotation() * DVec3::X;
        assert!((p - DVec3::new(0.5f64.cos(), 0.5f64.sin(), 0.0)).length() < 1e-15);
        assert!((a.rotation_angle() - 0.5).abs() < 1e-12);
        let r = a.rotation();
        assert!(
            (r * r.transpose() - DMat3::IDENTITY)
                .to_cols_array()
                .iter()
                .all(|v| v.abs() < 1e-15)
        );
    }

    #[test]
    fn small_angles_agree_with_the_closed_form() {
        // Just inside the Taylor branch, against the closed form (accurate there to ~1e-12).
        let omega = DVec3::new(0.6e-4, -0.5e-4, 0.5e-4);
        let nu = DVec3::new(1.0, 2.0, 3.0);
        let a = CameraAdjustment::exp([omega.x, omega.y, omega.z, nu.x, nu.y, nu.z, 0.0]);
        let theta = omega.length();
        assert!(theta < 1e-4);
        let k = skew(omega);
        let v = DMat3::IDENTITY
            + k * ((1.0 - theta.cos()) / (theta * theta))
            + k * k * ((theta - theta.sin()) / theta.powi(3));
        assert!((a.translation() - v * nu).length() < 1e-12);
        let r = DMat3::IDENTITY
            + k * (theta.sin() / theta)
            + k * k * ((1.0 - theta.cos()) / (theta * theta));
        let diff = (a.rotation() - r).to_cols_array();
        assert!(diff.iter().all(|d| d.abs() < 1e-15), "{diff:?}");
    }

    #[test]
    fn the_derivative_at_zero_moves_points_by_omega_cross_p_plus_nu() {
        let h = 1e-6;
        let (omega, nu) = (DVec3::new(0.3, -0.2, 0.7), DVec3::new(-1.0, 0.5, 2.0));
        let a = CameraAdjustment::exp([
            h * omega.x,
            h * omega.y,
            h * omega.z,
            h * nu.x,
            h * nu.y,
            h * nu.z,
            0.0,
        ]);
        let p = DVec3::new(0.4, -1.1, 3.0);
        let moved = (a.rotation() * p + a.translation() - p) / h;
        assert!((moved - (omega.cross(p) + nu)).length() < 1e-5);
    }

    #[test]
    fn then_composes_outer_after_inner() {
        let inner = CameraAdjustment::exp([0.1, 0.2, -0.3, 1.0, 0.0, -2.0, 0.1]);
        let outer = CameraAdjustment::exp([-0.4, 0.0, 0.2, 0.0, 3.0, 1.0, -0.05]);
        let both = inner.then(&outer);
        let p = DVec3::new(1.0, 2.0, 3.0);
        let step = |a: &CameraAdjustment, p: DVec3| a.rotation() * p + a.translation();
        assert!((step(&both, p) - step(&outer, step(&inner, p))).length() < 1e-14);
        assert!((both.focal_scale() - 0.05f64.exp()).abs() < 1e-15);
    }

    #[test]
    fn apply_moves_the_camera_and_scales_its_focal_lengths() {
        let k = c4g_scene::NormalizedIntrinsics::C4G_DEFAULT.to_pixels(64, 48);
        let camera = Camera::new(
            k,
            Affine3A::from_translation(glam::Vec3::new(0.0, 0.0, 2.0)),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let a = CameraAdjustment::exp([0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.1]);
        let moved = a.apply(&camera).unwrap_or_else(|e| panic!("{e}"));
        let t = moved.world_to_camera().translation;
        assert!((t - Vec3A::new(0.5, 0.0, 2.0)).length() < 1e-6);
        assert!((moved.intrinsics().fx - k.fx * 0.1f32.exp()).abs() < 1e-3);
        assert_eq!(moved.intrinsics().cx, k.cx);
        let broken = CameraAdjustment::exp([0.0, 0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0]);
        assert!(!broken.is_finite());
        assert!(broken.apply(&camera).is_err());
    }
}
