//! Still pixels: where a still camera's frames do not change over the clip, measured on the
//! frames themselves. A Gaussian that stays on still pixels at every keyframe is static whatever
//! its start says: c4g-tiny's keyframe copies of still background differ by a few of its own
//! (64 px) pixels, several working pixels, so a tolerance on the start's motion alone leaves
//! most of a tripod shot's background free to drift.
//!
//! A pixel is still when its colour's standard deviation over the training frames, in every
//! channel, is under a threshold ([`crate::FitOptions::still_threshold`], 0.02 of full scale:
//! above sensor noise and compression, below any visible motion). Counted once (NumPy, frames
//! box-shrunk to 128×72; no script in the repository), 0.02 finds
//! 60 % of the dog clip's tripod shot still and 2 % of the bedroom clip's handheld pan (its flat
//! walls). Only for a still camera: frames from different cameras see different things at a
//! pixel, so there are no still pixels then.

use c4g_scene::Camera;
use glam::Vec3;

/// Which pixels of the one camera's image are still.
#[derive(Debug, Clone)]
pub(crate) struct StillPixels {
    camera: Camera,
    still: Vec<bool>,
}

impl StillPixels {
    /// The still pixels of `frames` (each its camera and its RGB, 3 floats a pixel), or `None`
    /// when they are not all from one camera ([`same_view`]; or fewer than two, or `threshold` is
    /// not positive).
    pub(crate) fn measure(frames: &[(Camera, &[f32])], threshold: f64) -> Option<Self> {
        let &(camera, first) = frames.first()?;
        if frames.len() < 2
            || threshold <= 0.0
            || frames
                .iter()
                .any(|(c, rgb)| !same_view(c, &camera) || rgb.len() != first.len())
        {
            return None;
        }
        let mut sum = vec![0.0f64; first.len()];
        let mut squares = vec![0.0f64; first.len()];
        for (_, rgb) in frames {
            for ((s, q), &v) in sum.iter_mut().zip(&mut squares).zip(rgb.iter()) {
                let v = f64::from(v);
                *s += v;
                *q += v * v;
            }
        }
        let n = frames.len() as f64;
        let limit = threshold * threshold;
        let still = sum
            .chunks_exact(3)
            .zip(squares.chunks_exact(3))
            .map(|(s, q)| {
                (0..3).all(|c| {
                    let mean = s[c] / n;
                    (q[c] / n - mean * mean).max(0.0) < limit
                })
            })
            .collect();
        Some(Self { camera, still })
    }

    /// Whether `position` projects onto a still pixel whose eight neighbours are still too (a
    /// Gaussian at the edge of something moving is not still).
    pub(crate) fn holds(&self, position: [f64; 3]) -> bool {
        let p = Vec3::new(position[0] as f32, position[1] as f32, position[2] as f32);
        let Some(pixel) = self.camera.project(p) else {
            return false;
        };
        let (w, h) = (self.camera.width() as i64, self.camera.height() as i64);
        let (x, y) = (pixel.x.floor() as i64, pixel.y.floor() as i64);
        (-1..=1).all(|dy| {
            (-1..=1).all(|dx| {
                let (u, v) = (x + dx, y + dy);
                (0..w).contains(&u) && (0..h).contains(&v) && self.still[(v * w + u) as usize]
            })
        })
    }

    /// The share of pixels that are still.
    pub(crate) fn fraction(&self) -> f64 {
        self.still.iter().filter(|s| **s).count() as f64 / self.still.len().max(1) as f64
    }
}

/// Largest difference between two poses' world-to-camera entries for one still camera: given
/// cameras of a tripod shot differ by rounding (the synthetic clips' by 1e-17 before they are
/// made relative to the first and stored in `f32`), and a turn of 1e-5 rad or a step of 1e-5
/// scene units moves a pixel by a hundredth at a focal of 1000 px and depth 1.
const SAME_POSE: f32 = 1e-5;
/// … and between their intrinsics, in pixels.
const SAME_INTRINSICS_PX: f32 = 1e-3;

/// Whether `a` and `b` see the same image: the same size, and pose and intrinsics equal within
/// [`SAME_POSE`] and [`SAME_INTRINSICS_PX`].
fn same_view(a: &Camera, b: &Camera) -> bool {
    let (ka, kb) = (a.intrinsics(), b.intrinsics());
    let close = |x: f32, y: f32| (x - y).abs() <= SAME_INTRINSICS_PX;
    ka.width == kb.width
        && ka.height == kb.height
        && close(ka.fx, kb.fx)
        && close(ka.fy, kb.fy)
        && close(ka.cx, kb.cx)
        && close(ka.cy, kb.cy)
        && a.world_to_camera_matrix()
            .abs_diff_eq(b.world_to_camera_matrix(), SAME_POSE)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use c4g_scene::Intrinsics;

    fn camera() -> Camera {
        let k = Intrinsics {
            fx: 8.0,
            fy: 8.0,
            cx: 4.0,
            cy: 4.0,
            width: 8,
            height: 8,
        };
        Camera::from_world_to_camera_matrix(k, Default::default()).unwrap()
    }

    /// Frames of 8×8 where column 6 flickers: pixels around it are not still, the rest are;
    /// frames from two cameras have no still pixels.
    #[test]
    fn still_pixels_are_those_that_do_not_change() {
        let frame = |t: usize| {
            let mut rgb = vec![0.5f32; 8 * 8 * 3];
            for y in 0..8 {
                for c in 0..3 {
                    rgb[(y * 8 + 6) * 3 + c] = if t.is_multiple_of(2) { 0.2 } else { 0.8 };
                }
            }
            rgb
        };
        let images: Vec<Vec<f32>> = (0..4).map(frame).collect();
        let frames: Vec<(Camera, &[f32])> = images
            .iter()
            .map(|rgb| (camera(), rgb.as_slice()))
            .collect();
        let still = StillPixels::measure(&frames, 0.02).unwrap();
        assert_eq!(still.fraction(), 56.0 / 64.0);
        // The camera looks down +z: x = 0 is column 4, x = 0.25·z is column 6.
        assert!(still.holds([-0.1, 0.0, 2.0]));
        assert!(!still.holds([0.5, 0.0, 2.0]), "on the flickering column");
        assert!(!still.holds([0.3, 0.0, 2.0]), "beside it");
        assert!(!still.holds([0.0, 0.0, -2.0]), "behind the camera");
        let mut moved = frames.clone();
        moved[1].0 = Camera::from_world_to_camera_matrix(
            Intrinsics {
                fx: 9.0,
                ..*camera().intrinsics()
            },
            Default::default(),
        )
        .unwrap();
        assert!(StillPixels::measure(&moved, 0.02).is_none());
        // Rounding is not a move: a pose off by 1e-7 (as given cameras made relative to the
        // first come out) is the same camera; one turned by a thousandth of a radian is not.
        let pose = |angle: f32, noise: f32| {
            let mut m = glam::Mat4::from_rotation_y(angle);
            m.x_axis.z += noise;
            Camera::from_world_to_camera_matrix(*camera().intrinsics(), m).unwrap()
        };
        let mut rounded = frames.clone();
        rounded[2].0 = pose(0.0, 1e-7);
        assert!(StillPixels::measure(&rounded, 0.02).is_some());
        rounded[2].0 = pose(1e-3, 0.0);
        assert!(StillPixels::measure(&rounded, 0.02).is_none());
    }
}
