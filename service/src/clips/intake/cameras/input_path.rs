//! The input camera at any time: the clip's given context cameras interpolated (rotations by
//! slerp on the shorter arc, camera centres and intrinsics linearly), clamped to the end cameras
//! outside the context span. Without given cameras the input camera is the identity with the
//! model's intrinsics, the public C4G code's "static camera".

use glam::{DMat3, DQuat, DVec3};

use super::model_frame::{ClipCameras, ContextCamera, row_major};
use super::pose::Intrinsics;

/// A camera in the model's frame: row-major 4×4 world-to-camera and normalised intrinsics.
#[derive(Debug, Clone, PartialEq)]
pub struct InputCamera {
    /// Row-major 4×4 world-to-camera, OpenCV axes.
    pub world_to_camera: Vec<f64>,
    /// Fractions of the image size.
    pub intrinsics: Intrinsics,
}

/// The input camera of a clip with `cameras` (or none) at media time `t`.
pub fn input_camera(cameras: Option<&ClipCameras>, t: f64) -> InputCamera {
    let frames = cameras.map(|c| c.frames.as_slice()).unwrap_or_default();
    let (Some(first), Some(last)) = (frames.first(), frames.last()) else {
        return InputCamera {
            world_to_camera: row_major(&DMat3::IDENTITY, DVec3::ZERO),
            intrinsics: Intrinsics::C4G_DEFAULT,
        };
    };
    if t.is_nan() || t <= first.t {
        return exactly(first);
    }
    if t >= last.t {
        return exactly(last);
    }
    // The first context time at or after t; t is strictly inside (first.t, last.t) here.
    let after = frames.partition_point(|f| f.t < t).min(frames.len() - 1);
    let (a, b) = (&frames[after - 1], &frames[after]);
    let s = (t - a.t) / (b.t - a.t);
    between(a, b, s)
}

fn exactly(camera: &ContextCamera) -> InputCamera {
    InputCamera {
        world_to_camera: camera.world_to_camera.clone(),
        intrinsics: camera.intrinsics,
    }
}

/// The camera a fraction `s` of the way from `a` to `b`.
fn between(a: &ContextCamera, b: &ContextCamera, s: f64) -> InputCamera {
    let (qa, ca) = a.rotation_and_centre();
    let (qb, cb) = b.rotation_and_centre();
    // q and −q are one rotation: take the one nearer qa, so the slerp takes the shorter arc.
    let qb = if qa.dot(qb) < 0.0 { -qb } else { qb };
    let q: DQuat = qa.slerp(qb, s).normalize();
    let rotation = DMat3::from_quat(q);
    let centre = ca.lerp(cb, s);
    let lerp = |x: f64, y: f64| x + (y - x) * s;
    let (ka, kb) = (a.intrinsics, b.intrinsics);
    InputCamera {
        world_to_camera: row_major(&rotation, -(rotation * centre)),
        intrinsics: Intrinsics {
            fx: lerp(ka.fx, kb.fx),
            fy: lerp(ka.fy, kb.fy),
            cx: lerp(ka.cx, kb.cx),
            cy: lerp(ka.cy, kb.cy),
        },
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    /// A camera at time `t` turned by `angle` about y, its centre at `centre`.
    fn context(t: f64, angle: f64, centre: DVec3, fx: f64) -> ContextCamera {
        let r = DMat3::from_rotation_y(angle);
        ContextCamera {
            t,
            world_to_camera: row_major(&r, -(r * centre)),
            intrinsics: Intrinsics {
                fx,
                fy: fx,
                cx: 0.5,
                cy: 0.5,
            },
        }
    }

    fn clip(frames: Vec<ContextCamera>) -> ClipCameras {
        ClipCameras {
            format: "json".into(),
            scale: 1.0,
            frames,
            notes: Vec::new(),
            scale_fit: None,
        }
    }

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    /// Independent of the slerp: between two turns about one axis, the turn at a fraction s of
    /// the time is the same fraction of the way, and the centre is on the segment.
    #[test]
    fn the_input_camera_interpolates_between_context_cameras_and_is_them_at_their_times() {
        let cameras = clip(vec![
            context(0.0, 0.0, DVec3::ZERO, 0.8),
            context(0.4, 0.6, DVec3::new(1.0, 0.0, 0.2), 1.0),
            context(0.6, 0.2, DVec3::new(0.5, 0.1, 0.0), 1.0),
        ]);
        for frame in &cameras.frames {
            let at = input_camera(Some(&cameras), frame.t);
            assert!(close(&at.world_to_camera, &frame.world_to_camera));
            assert_eq!(at.intrinsics, frame.intrinsics);
        }
        let at = input_camera(Some(&cameras), 0.1);
        let expected = context(0.1, 0.15, DVec3::new(0.25, 0.0, 0.05), 0.85);
        assert!(
            close(&at.world_to_camera, &expected.world_to_camera),
            "{:?}",
            at.world_to_camera
        );
        assert!((at.intrinsics.fx - 0.85).abs() < 1e-12);
        // Outside the span: the end cameras.
        assert!(close(
            &input_camera(Some(&cameras), -3.0).world_to_camera,
            &cameras.frames[0].world_to_camera
        ));
        assert!(close(
            &input_camera(Some(&cameras), 9.0).world_to_camera,
            &cameras.frames[2].world_to_camera
        ));
    }

    /// A turn of 350° one way is 10° the other: the path takes the 10°.
    #[test]
    fn rotations_take_the_shorter_arc() {
        let cameras = clip(vec![
            context(0.0, 0.0, DVec3::ZERO, 0.8),
            context(1.0, (-10.0_f64).to_radians(), DVec3::ZERO, 0.8),
        ]);
        let halfway = input_camera(Some(&cameras), 0.5);
        let expected = context(0.5, (-5.0_f64).to_radians(), DVec3::ZERO, 0.8);
        assert!(close(&halfway.world_to_camera, &expected.world_to_camera));
    }

    #[test]
    fn without_given_cameras_the_input_camera_is_the_static_identity() {
        let at = input_camera(None, 0.3);
        assert!(close(
            &at.world_to_camera,
            &row_major(&DMat3::IDENTITY, DVec3::ZERO)
        ));
        assert_eq!(at.intrinsics, Intrinsics::C4G_DEFAULT);
    }
}
