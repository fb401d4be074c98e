//! The context frames' given cameras in the model's frame, as a clip stores them.
//!
//! The model's frame is the first context camera's (OpenCV axes, that camera the identity), and
//! its scale is the public C4G code's DAVIS convention (`../shared/docs/C4G_MODEL.md`):
//! translations divided by the largest distance of any context camera from the first. Every
//! world frame the cameras were given in (COLMAP's, nerfstudio's with its `applied_transform`, a
//! tracker's) maps to the same stored cameras, since only poses relative to the first and
//! distances relative to the largest survive.

use glam::{DMat3, DQuat, DVec3};
use serde::{Deserialize, Serialize};

use super::pose::{GivenCamera, Intrinsics};

/// Below this fraction of the cameras' distance from the world origin (or of one unit), the
/// context cameras count as not moving: a rotation-only or tripod clip keeps its units.
const STILL: f64 = 1e-9;

/// A clip's given cameras: one per context frame, in the model's frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipCameras {
    /// The form they came in: `json`, `colmap` or `transforms`.
    pub format: String,
    /// Given units per model unit: every translation was divided by it (the largest distance of
    /// a context camera from the first, 1 when the context cameras do not move; over
    /// `scale_fit`'s factor when fitted).
    pub scale: f64,
    /// One per context frame, in time order (as `context_times`).
    pub frames: Vec<ContextCamera>,
    /// What was ignored or assumed reading them.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// How the translations were fitted to the model's depth scale (`camera_scale.rs`): absent
    /// when they were not (cameras that do not move, recovered cameras, clips stored before).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale_fit: Option<ScaleFit>,
}

/// Given cameras fitted to the model's depth scale: every translation multiplied by `factor`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScaleFit {
    /// What the convention's translations were multiplied by (1: the convention's scale stood).
    pub factor: f64,
    /// Given units per model unit by the convention alone (the largest distance of a context
    /// camera from the first).
    pub convention_scale: f64,
    /// Mean squared RGB error of the model's renders of the later context frames at their
    /// cameras, at the convention's scale.
    pub initial_error: f64,
    /// The same at the fitted scale.
    pub error: f64,
}

/// A context frame's camera in the model's frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ContextCamera {
    /// The context frame's time, seconds.
    pub t: f64,
    /// Row-major 4×4 world-to-camera (OpenCV axes), as a render's `CameraSpec` takes it.
    pub world_to_camera: Vec<f64>,
    /// Fractions of the image size.
    pub intrinsics: Intrinsics,
}

impl ClipCameras {
    /// The cameras of the context frames at `times` (time order), `given` in the same order.
    pub fn new(given: &[GivenCamera], times: &[f64], format: &str, mut notes: Vec<String>) -> Self {
        let Some(first) = given.first() else {
            return Self {
                format: format.to_owned(),
                scale: 1.0,
                frames: Vec::new(),
                notes,
                scale_fit: None,
            };
        };
        let c0 = first.centre();
        let largest = given
            .iter()
            .map(|g| (g.centre() - c0).length())
            .fold(0.0_f64, f64::max);
        let reach = given
            .iter()
            .map(|g| g.centre().length())
            .fold(1.0_f64, f64::max);
        let scale = if largest > STILL * reach {
            largest
        } else {
            notes.push("the context cameras do not move: translations are not scaled".to_owned());
            1.0
        };
        let frames = given
            .iter()
            .zip(times)
            .map(|(g, &t)| {
                // W'ᵢ = Wᵢ W₀⁻¹: a point of the first camera's frame into camera i.
                let rotation = g.rotation * first.rotation.transpose();
                let translation = (g.translation - rotation * first.translation) / scale;
                ContextCamera {
                    t,
                    world_to_camera: row_major(&rotation, translation),
                    intrinsics: g.intrinsics,
                }
            })
            .collect();
        Self {
            format: format.to_owned(),
            scale,
            frames,
            notes,
            scale_fit: None,
        }
    }

    /// Whether any context camera is away from the first (only then does a scale matter).
    pub fn moves(&self) -> bool {
        self.frames.iter().any(|f| f.pose().1 != DVec3::ZERO)
    }

    /// These cameras with every translation multiplied by `fit.factor`, `fit` recorded.
    pub fn fitted(mut self, fit: ScaleFit) -> Self {
        for frame in &mut self.frames {
            let (rotation, translation) = frame.pose();
            frame.world_to_camera = row_major(&rotation, translation * fit.factor);
        }
        self.scale /= fit.factor;
        self.notes.push(format!(
            "translations fitted to the model's depth scale: x{:.4} of the convention's \
             (the model's renders of the context frames: mean squared error {:.5} -> {:.5})",
            fit.factor, fit.initial_error, fit.error
        ));
        self.scale_fit = Some(fit);
        self
    }
}

impl ContextCamera {
    /// The rotation and translation of `world_to_camera`.
    pub fn pose(&self) -> (DMat3, DVec3) {
        let m = &self.world_to_camera;
        let at = |i: usize| m.get(i).copied().unwrap_or(0.0);
        (
            DMat3::from_cols_array(&[
                at(0),
                at(4),
                at(8),
                at(1),
                at(5),
                at(9),
                at(2),
                at(6),
                at(10),
            ]),
            DVec3::new(at(3), at(7), at(11)),
        )
    }

    /// The pose as a unit quaternion (world-to-camera rotation) and a camera centre.
    pub fn rotation_and_centre(&self) -> (DQuat, DVec3) {
        let (r, t) = self.pose();
        let q = DQuat::from_mat3(&r).normalize();
        (q, -(r.transpose() * t))
    }
}

/// `[R | t]` as 16 numbers, row-major, last row 0 0 0 1.
pub fn row_major(r: &DMat3, t: DVec3) -> Vec<f64> {
    let row = |i: usize| r.row(i);
    let (a, b, c) = (row(0), row(1), row(2));
    vec![
        a.x, a.y, a.z, t.x, b.x, b.y, b.z, t.y, c.x, c.y, c.z, t.z, 0.0, 0.0, 0.0, 1.0,
    ]
}
