//! Camera paths: interpolation between cameras and the preset moves a viewer asks for.
//!
//! A render along a path is a `Vec<Camera>`, one per output frame. Paths are built around a
//! *reference* camera (usually the first context camera of a clip) in its own terms — depths in
//! front of it, its up direction — so a preset means the same thing whatever the world frame.
//!
//! - [`interpolate`] / [`through`]: rotations by slerp (shortest arc), centres and intrinsics
//!   linearly. Poses must be rigid (orthonormal rotation, no scale).
//! - [`Trajectory::Orbit`]: a sweep around a look-at point at `depth` in front of the reference,
//!   about the reference's vertical axis, always facing the point.
//! - [`Trajectory::Spiral`]: the forward-facing spiral of NeRF's LLFF renders: the centre traces
//!   `(rx cos θ, ry sin θ, rz sin(z_rate θ))` in the reference's frame while looking at a point at
//!   `focus_depth` in front of the reference.
//! - [`Trajectory::Dolly`]: a move along the view axis; with `subject_depth` it becomes a dolly
//!   zoom, the focal length following the distance so the subject keeps its size on screen.
//!
//! Every parameter is checked up front; a bad one is a [`SceneError::InvalidTrajectory`] naming
//! it.

use glam::{Affine3A, Mat3, Quat, Vec3};
use serde::{Deserialize, Serialize};

use crate::{Camera, Intrinsics, SceneError};

/// How far a pose's rotation may be from orthonormal before interpolation refuses it.
const RIGID_TOLERANCE: f32 = 1e-3;

/// A preset camera path around a reference camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Trajectory {
    /// Sweep `angle_degrees` (split evenly either side of the reference; a full turn of ±360 makes
    /// a closed loop without repeating the first frame) about the vertical axis through the
    /// point `depth` in front of the reference, at `radius` from it (the reference's own distance
    /// `depth` when `None`).
    Orbit {
        /// Distance of the look-at point in front of the reference camera.
        depth: f32,
        /// Total sweep in degrees.
        angle_degrees: f32,
        /// Distance of the cameras from the look-at point.
        radius: Option<f32>,
    },
    /// NeRF's LLFF spiral: `rotations` turns with the centre at `(rx cos θ, ry sin θ,
    /// rz sin(z_rate θ))` in the reference's frame, looking at the point `focus_depth` ahead.
    Spiral {
        /// Half extents of the spiral along the reference's x, y and z axes (world units).
        radii: [f32; 3],
        /// Depth, in front of the reference, of the point every frame looks at.
        focus_depth: f32,
        /// Turns over the whole path (LLFF uses 2).
        rotations: f32,
        /// Turns of the forward/back motion per turn of the circle (LLFF uses 0.5).
        z_rate: f32,
    },
    /// Move `distance` along the view axis (positive: forward). With `subject_depth` (distance
    /// of the subject in front of the reference) the focal length scales as
    /// `(subject_depth − travelled) / subject_depth`, keeping the subject's size: a dolly zoom.
    Dolly {
        /// Signed distance travelled by the last frame.
        distance: f32,
        /// Depth of the subject whose size a dolly zoom keeps.
        subject_depth: Option<f32>,
    },
}

impl Trajectory {
    /// The `frames` cameras of this path around `reference` (which is rigid: see the module doc).
    pub fn cameras(&self, reference: &Camera, frames: usize) -> Result<Vec<Camera>, SceneError> {
        if frames == 0 {
            return Err(invalid("a trajectory needs at least one frame"));
        }
        let pose = RigidPose::of(reference)?;
        match *self {
            Self::Orbit {
                depth,
                angle_degrees,
                radius,
            } => orbit(reference, &pose, frames, depth, angle_degrees, radius),
            Self::Spiral {
                radii,
                focus_depth,
                rotations,
                z_rate,
            } => spiral(
                reference,
                &pose,
                frames,
                radii,
                focus_depth,
                rotations,
                z_rate,
            ),
            Self::Dolly {
                distance,
                subject_depth,
            } => dolly(reference, &pose, frames, distance, subject_depth),
        }
    }
}

/// The camera a fraction `t` (0..=1) of the way from `from` to `to`: rotation by slerp along the
/// shorter arc, centre and intrinsics linearly. Both must render the same image size.
pub fn interpolate(from: &Camera, to: &Camera, t: f32) -> Result<Camera, SceneError> {
    if !(0.0..=1.0).contains(&t) {
        return Err(invalid(format!(
            "interpolation parameter {t} is outside [0, 1]"
        )));
    }
    let (a, b) = (RigidPose::of(from)?, RigidPose::of(to)?);
    let (ka, kb) = (from.intrinsics(), to.intrinsics());
    if (ka.width, ka.height) != (kb.width, kb.height) {
        return Err(invalid(format!(
            "cannot interpolate a {}x{} camera with a {}x{} one",
            ka.width, ka.height, kb.width, kb.height
        )));
    }
    let lerp = |x: f32, y: f32| x + (y - x) * t;
    let k = Intrinsics {
        fx: lerp(ka.fx, kb.fx),
        fy: lerp(ka.fy, kb.fy),
        cx: lerp(ka.cx, kb.cx),
        cy: lerp(ka.cy, kb.cy),
        ..*ka
    };
    let pose = RigidPose {
        rotation: a.rotation.slerp(b.rotation, t).normalize(),
        centre: a.centre.lerp(b.centre, t),
    };
    pose.camera(k)
}

/// `frames` cameras evenly spaced in parameter along the piecewise path through `keys` (each
/// segment gets the same share of frames; the first and last frames are the first and last keys).
pub fn through(keys: &[Camera], frames: usize) -> Result<Vec<Camera>, SceneError> {
    match (keys.len(), frames) {
        (0, _) => Err(invalid("a path needs at least one key camera")),
        (_, 0) => Err(invalid("a path needs at least one frame")),
        (1, _) => {
            RigidPose::of(&keys[0])?;
            Ok(vec![keys[0]; frames])
        }
        (n, 1) => interpolate(&keys[0], &keys[n - 1], 0.0).map(|c| vec![c]),
        (n, _) => (0..frames)
            .map(|f| {
                let s = f as f64 / (frames - 1) as f64 * (n - 1) as f64;
                let seg = (s.floor() as usize).min(n - 2);
                interpolate(
                    &keys[seg],
                    &keys[seg + 1],
                    ((s - seg as f64) as f32).clamp(0.0, 1.0),
                )
            })
            .collect(),
    }
}

/// A camera's pose as a unit quaternion (camera-to-world rotation) and a centre.
#[derive(Debug, Clone, Copy)]
struct RigidPose {
    rotation: Quat,
    centre: Vec3,
}

impl RigidPose {
    fn of(camera: &Camera) -> Result<Self, SceneError> {
        let c2w = camera.camera_to_world();
        let m = Mat3::from(c2w.matrix3);
        let off = (m.transpose() * m - Mat3::IDENTITY).abs().to_cols_array();
        if !off.iter().all(|v| *v <= RIGID_TOLERANCE) || m.determinant() < 0.0 {
            return Err(invalid(
                "camera paths need a rigid pose (a rotation without scale or reflection)",
            ));
        }
        Ok(Self {
            rotation: Quat::from_mat3(&m).normalize(),
            centre: c2w.translation.into(),
        })
    }

    /// The camera's axes in the world: right (x), down (y), forward (z).
    fn axes(&self) -> (Vec3, Vec3, Vec3) {
        (
            self.rotation * Vec3::X,
            self.rotation * Vec3::Y,
            self.rotation * Vec3::Z,
        )
    }

    fn camera(&self, k: Intrinsics) -> Result<Camera, SceneError> {
        Camera::from_camera_to_world(
            k,
            Affine3A::from_rotation_translation(self.rotation, self.centre),
        )
    }

    /// A pose at `centre` facing `target`, with `down` (a world direction) as close to the image's
    /// down as the view direction allows.
    fn looking_at(centre: Vec3, target: Vec3, down: Vec3) -> Result<Self, SceneError> {
        let forward = (target - centre).normalize_or_zero();
        let right = down.cross(forward).normalize_or_zero();
        if forward == Vec3::ZERO || right == Vec3::ZERO {
            return Err(invalid(
                "the view direction is undefined or parallel to the up axis",
            ));
        }
        let down = forward.cross(right);
        Ok(Self {
            rotation: Quat::from_mat3(&Mat3::from_cols(right, down, forward)).normalize(),
            centre,
        })
    }
}

fn orbit(
    reference: &Camera,
    pose: &RigidPose,
    frames: usize,
    depth: f32,
    angle_degrees: f32,
    radius: Option<f32>,
) -> Result<Vec<Camera>, SceneError> {
    positive("orbit depth", depth)?;
    finite("orbit angle_degrees", angle_degrees)?;
    let radius = radius.unwrap_or(depth);
    positive("orbit radius", radius)?;
    let (_, down, forward) = pose.axes();
    let target = pose.centre + forward * depth;
    let start = target - forward * radius;
    let sweep = angle_degrees.to_radians();
    let closed = angle_degrees.abs() >= 360.0;
    (0..frames)
        .map(|f| {
            let angle = if closed {
                sweep * f as f32 / frames as f32
            } else if frames == 1 {
                0.0
            } else {
                sweep * (f as f32 / (frames - 1) as f32 - 0.5)
            };
            // Positive angles move the camera to its right: a turn about "up" = −down.
            let turn = Quat::from_axis_angle(-down, angle);
            RigidPose {
                rotation: (turn * pose.rotation).normalize(),
                centre: target + turn * (start - target),
            }
            .camera(*reference.intrinsics())
        })
        .collect()
}

fn spiral(
    reference: &Camera,
    pose: &RigidPose,
    frames: usize,
    radii: [f32; 3],
    focus_depth: f32,
    rotations: f32,
    z_rate: f32,
) -> Result<Vec<Camera>, SceneError> {
    for (name, r) in ["spiral radii[0]", "spiral radii[1]", "spiral radii[2]"]
        .into_iter()
        .zip(radii)
    {
        if !(r.is_finite() && r >= 0.0) {
            return Err(invalid(format!("{name} must be finite and ≥ 0, got {r}")));
        }
    }
    positive("spiral focus_depth", focus_depth)?;
    finite("spiral rotations", rotations)?;
    finite("spiral z_rate", z_rate)?;
    let (right, down, forward) = pose.axes();
    let target = pose.centre + forward * focus_depth;
    (0..frames)
        .map(|f| {
            let theta = std::f32::consts::TAU * rotations * f as f32 / frames as f32;
            let offset = right * (radii[0] * theta.cos())
                + down * (radii[1] * theta.sin())
                + forward * (radii[2] * (z_rate * theta).sin());
            let centre = pose.centre + offset;
            if (target - centre).dot(forward) <= 0.0 {
                return Err(invalid(format!(
                    "spiral radii[2] {} reaches past the focus depth {focus_depth}",
                    radii[2]
                )));
            }
            RigidPose::looking_at(centre, target, down)?.camera(*reference.intrinsics())
        })
        .collect()
}

fn dolly(
    reference: &Camera,
    pose: &RigidPose,
    frames: usize,
    distance: f32,
    subject_depth: Option<f32>,
) -> Result<Vec<Camera>, SceneError> {
    finite("dolly distance", distance)?;
    if let Some(depth) = subject_depth {
        positive("dolly subject_depth", depth)?;
        if distance >= depth {
            return Err(invalid(format!(
                "a dolly zoom of {distance} would reach the subject at depth {depth}"
            )));
        }
    }
    let (_, _, forward) = pose.axes();
    let k0 = *reference.intrinsics();
    (0..frames)
        .map(|f| {
            let travelled = if frames == 1 {
                0.0
            } else {
                distance * f as f32 / (frames - 1) as f32
            };
            let k = match subject_depth {
                // The subject's image size goes as focal / distance-to-subject.
                Some(depth) => {
                    let s = (depth - travelled) / depth;
                    Intrinsics {
                        fx: k0.fx * s,
                        fy: k0.fy * s,
                        ..k0
                    }
                }
                None => k0,
            };
            RigidPose {
                rotation: pose.rotation,
                centre: pose.centre + forward * travelled,
            }
            .camera(k)
        })
        .collect()
}

fn invalid(reason: impl Into<String>) -> SceneError {
    SceneError::InvalidTrajectory(reason.into())
}

fn finite(name: &str, value: f32) -> Result<(), SceneError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(invalid(format!("{name} must be finite, got {value}")))
    }
}

fn positive(name: &str, value: f32) -> Result<(), SceneError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(invalid(format!(
            "{name} must be positive and finite, got {value}"
        )))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec2;

    use super::*;
    use crate::NormalizedIntrinsics;

    fn reference() -> Camera {
        let rotation = Quat::from_rotation_y(0.4) * Quat::from_rotation_x(-0.25);
        Camera::from_camera_to_world(
            NormalizedIntrinsics::C4G_DEFAULT.to_pixels(160, 120),
            Affine3A::from_rotation_translation(rotation, Vec3::new(0.5, -0.3, 1.0)),
        )
        .unwrap()
    }

    fn ahead(camera: &Camera, depth: f32) -> Vec3 {
        camera.camera_to_world().transform_point3(Vec3::Z * depth)
    }

    fn principal_point(camera: &Camera) -> Vec2 {
        Vec2::new(camera.intrinsics().cx, camera.intrinsics().cy)
    }

    #[test]
    fn interpolation_hits_both_ends_and_halves_the_rotation() {
        let a = reference();
        let turn = Affine3A::from_rotation_y(std::f32::consts::FRAC_PI_2);
        let b_pose =
            a.camera_to_world() * turn * Affine3A::from_translation(Vec3::new(2.0, 0.0, 0.0));
        let k = Intrinsics {
            fx: 200.0,
            ..*a.intrinsics()
        };
        let b = Camera::from_camera_to_world(k, b_pose).unwrap();
        let start = interpolate(&a, &b, 0.0).unwrap();
        let end = interpolate(&a, &b, 1.0).unwrap();
        assert!(
            start
                .world_to_camera()
                .abs_diff_eq(a.world_to_camera(), 1e-5)
        );
        assert!(end.world_to_camera().abs_diff_eq(b.world_to_camera(), 1e-5));
        let mid = interpolate(&a, &b, 0.5).unwrap();
        let rel = a.world_to_camera() * mid.camera_to_world();
        let (_, q, _) = rel.to_scale_rotation_translation();
        assert!((q.angle_between(Quat::IDENTITY) - std::f32::consts::FRAC_PI_4).abs() < 1e-4);
        assert!((mid.position() - (a.position() + b.position()) / 2.0).length() < 1e-5);
        assert!((mid.intrinsics().fx - (a.intrinsics().fx + 200.0) / 2.0).abs() < 1e-3);
    }

    #[test]
    fn interpolation_refuses_mismatched_sizes_and_bad_parameters() {
        let a = reference();
        let small = Camera::new(
            NormalizedIntrinsics::C4G_DEFAULT.to_pixels(80, 60),
            a.world_to_camera(),
        )
        .unwrap();
        assert!(interpolate(&a, &small, 0.5).is_err());
        assert!(interpolate(&a, &a, f32::NAN).is_err());
        assert!(interpolate(&a, &a, 1.5).is_err());
        let scaled = Camera::new(
            *a.intrinsics(),
            Affine3A::from_scale(Vec3::splat(2.0)) * a.world_to_camera(),
        )
        .unwrap();
        assert!(matches!(
            interpolate(&a, &scaled, 0.5),
            Err(SceneError::InvalidTrajectory(_))
        ));
    }

    #[test]
    fn a_path_through_keys_starts_and_ends_on_them() {
        let a = reference();
        let b = Trajectory::Dolly {
            distance: 1.0,
            subject_depth: None,
        }
        .cameras(&a, 2)
        .unwrap()[1];
        let c = Trajectory::Orbit {
            depth: 3.0,
            angle_degrees: 40.0,
            radius: None,
        }
        .cameras(&a, 2)
        .unwrap()[1];
        let path = through(&[a, b, c], 9).unwrap();
        assert_eq!(path.len(), 9);
        assert!(
            path[0]
                .world_to_camera()
                .abs_diff_eq(a.world_to_camera(), 1e-5)
        );
        assert!(
            path[4]
                .world_to_camera()
                .abs_diff_eq(b.world_to_camera(), 1e-4)
        );
        assert!(
            path[8]
                .world_to_camera()
                .abs_diff_eq(c.world_to_camera(), 1e-4)
        );
        assert!(through(&[], 3).is_err());
        assert!(through(&[a], 0).is_err());
        assert_eq!(through(&[a], 3).unwrap(), vec![a; 3]);
    }

    #[test]
    fn an_orbit_keeps_facing_the_look_at_point_at_its_radius() {
        let reference = reference();
        let target = ahead(&reference, 3.0);
        let path = Trajectory::Orbit {
            depth: 3.0,
            angle_degrees: 90.0,
            radius: Some(2.0),
        }
        .cameras(&reference, 7)
        .unwrap();
        for cam in &path {
            assert!((cam.position().distance(target) - 2.0).abs() < 1e-4);
            let uv = cam.project(target).unwrap();
            assert!((uv - principal_point(cam)).length() < 1e-3);
        }
        // The sweep is ±45° about the vertical axis: the end frames are 90° apart, the middle
        // one faces the reference's way.
        let fwd = |c: &Camera| c.camera_to_world().transform_vector3(Vec3::Z);
        assert!((fwd(&path[0]).angle_between(fwd(&path[6])) - 90f32.to_radians()).abs() < 1e-4);
        assert!(fwd(&path[3]).angle_between(fwd(&reference)) < 1e-4);
        // Positive angles end on the reference's right.
        let right = reference.camera_to_world().transform_vector3(Vec3::X);
        assert!((path[6].position() - path[0].position()).dot(right) > 0.0);
    }

    #[test]
    fn a_full_orbit_closes_without_repeating_the_first_frame() {
        let reference = reference();
        let path = Trajectory::Orbit {
            depth: 2.0,
            angle_degrees: 360.0,
            radius: None,
        }
        .cameras(&reference, 4)
        .unwrap();
        assert!(
            path[0]
                .world_to_camera()
                .abs_diff_eq(reference.world_to_camera(), 1e-5)
        );
        assert!(path[2].position().distance(reference.position()) > 3.9);
    }

    #[test]
    fn a_spiral_looks_at_its_focus_and_starts_at_radius_x() {
        let reference = reference();
        let focus = ahead(&reference, 4.0);
        let path = Trajectory::Spiral {
            radii: [0.3, 0.2, 0.1],
            focus_depth: 4.0,
            rotations: 2.0,
            z_rate: 0.5,
        }
        .cameras(&reference, 12)
        .unwrap();
        let right = reference.camera_to_world().transform_vector3(Vec3::X);
        assert!((path[0].position() - (reference.position() + right * 0.3)).length() < 1e-5);
        for cam in &path {
            let uv = cam.project(focus).unwrap();
            assert!((uv - principal_point(cam)).length() < 1e-2);
            let offset = reference.to_camera(cam.position());
            assert!(offset.x.abs() <= 0.3 + 1e-5 && offset.y.abs() <= 0.2 + 1e-5);
        }
    }

    #[test]
    fn a_dolly_zoom_keeps_the_subject_size() {
        let reference = reference();
        let path = Trajectory::Dolly {
            distance: 1.5,
            subject_depth: Some(3.0),
        }
        .cameras(&reference, 5)
        .unwrap();
        let to_world = reference.camera_to_world();
        let (p, q) = (
            to_world.transform_point3(Vec3::new(-0.5, 0.0, 3.0)),
            to_world.transform_point3(Vec3::new(0.5, 0.0, 3.0)),
        );
        let size = |c: &Camera| (c.project(p).unwrap() - c.project(q).unwrap()).length();
        for cam in &path {
            assert!((size(cam) - size(&reference)).abs() < 1e-3);
        }
        assert!((path[4].position().distance(reference.position()) - 1.5).abs() < 1e-5);
        assert!((path[4].intrinsics().fx - reference.intrinsics().fx / 2.0).abs() < 1e-3);
        // A plain dolly keeps the focal length.
        let plain = Trajectory::Dolly {
            distance: -1.0,
            subject_depth: None,
        }
        .cameras(&reference, 3)
        .unwrap();
        assert_eq!(plain[2].intrinsics(), reference.intrinsics());
    }

    #[test]
    fn bad_parameters_are_named_in_the_error() {
        let reference = reference();
        let cases = [
            (
                Trajectory::Orbit {
                    depth: -1.0,
                    angle_degrees: 30.0,
                    radius: None,
                },
                "orbit depth",
            ),
            (
                Trajectory::Orbit {
                    depth: 1.0,
                    angle_degrees: f32::NAN,
                    radius: None,
                },
                "angle_degrees",
            ),
            (
                Trajectory::Spiral {
                    radii: [0.1, -0.1, 0.0],
                    focus_depth: 1.0,
                    rotations: 2.0,
                    z_rate: 0.5,
                },
                "radii[1]",
            ),
            (
                Trajectory::Spiral {
                    radii: [0.1, 0.1, 2.0],
                    focus_depth: 1.0,
                    rotations: 2.0,
                    z_rate: 0.5,
                },
                "past the focus",
            ),
            (
                Trajectory::Dolly {
                    distance: 3.0,
                    subject_depth: Some(2.0),
                },
                "reach the subject",
            ),
            (
                Trajectory::Dolly {
                    distance: f32::INFINITY,
                    subject_depth: None,
                },
                "dolly distance",
            ),
        ];
        for (trajectory, needle) in cases {
            let err = trajectory.cameras(&reference, 5).unwrap_err().to_string();
            assert!(err.contains(needle), "{err} lacks {needle}");
        }
        let ok = Trajectory::Dolly {
            distance: 1.0,
            subject_depth: None,
        };
        assert!(ok.cameras(&reference, 0).is_err());
        let one = ok.cameras(&reference, 1).unwrap();
        assert_eq!(one.len(), 1);
        assert!(
            one[0]
                .world_to_camera()
                .abs_diff_eq(reference.world_to_camera(), 1e-5)
        );
    }

    #[test]
    fn presets_read_from_json_by_kind() {
        let t: Trajectory = serde_json::from_str(
            r#"{"kind": "orbit", "depth": 2.0, "angle_degrees": 30.0, "radius": null}"#,
        )
        .unwrap();
        assert_eq!(
            t,
            Trajectory::Orbit {
                depth: 2.0,
                angle_degrees: 30.0,
                radius: None
            }
        );
    }
}
