//! Cameras as clients state them: a row-major world-to-camera matrix and intrinsics as
//! fractions of the image size, turned into the renderer's [`Camera`] at a request's image size;
//! or the input camera (`input`), resolved against the clip's given cameras at a frame's time.
//! REST bodies and gRPC messages both arrive here.

use c4g_scene::{Camera, NormalizedIntrinsics};
use glam::{Affine3A, Mat4};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::ServiceError;
use crate::clips::intake::cameras::{ClipCameras, FOCAL_BOUND, SMALLEST_LENGTH, input_camera};

/// Largest coordinate, distance or angle a camera or trajectory preset may state: far beyond
/// any scene C4G reconstructs (its scenes are a few units across), small enough that every
/// product the renderer forms of them stays finite in f32.
pub const SCENE_BOUND: f64 = 1e6;

/// A camera as a client states it: a row-major 4×4 world-to-camera matrix (OpenCV axes) and
/// intrinsics as fractions of the image size. Both default to the first context camera's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// 16 numbers, row-major, last row 0 0 0 1.
    pub world_to_camera: Option<Vec<f32>>,
    /// Normalised intrinsics.
    pub intrinsics: Option<IntrinsicsSpec>,
    /// The input camera instead of a stated one (see [`InputSpec`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input: Option<InputSpec>,
}

/// "The input camera at time t": the clip's given cameras interpolated
/// ([`crate::clips::intake::cameras::input_camera`]; the identity without given cameras). `{}` follows
/// the time each frame renders at; `at` fixes the time; `start` and `end` sweep the input path
/// evenly over a path's frames whatever times they render (the same path at a new time).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InputSpec {
    /// The input camera at this time, seconds.
    pub at: Option<f64>,
    /// A path's first frame takes the input camera at this time…
    pub start: Option<f64>,
    /// …and its last at this one.
    pub end: Option<f64>,
}

/// Intrinsics as fractions of the image size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsSpec {
    /// Focal length over width.
    pub fx: f32,
    /// Focal length over height.
    pub fy: f32,
    /// Principal point x over width.
    #[serde(default = "half")]
    pub cx: f32,
    /// Principal point y over height.
    #[serde(default = "half")]
    pub cy: f32,
}

fn half() -> f32 {
    0.5
}

impl CameraSpec {
    /// True when the camera depends on the frame (the input camera without a fixed `at`).
    pub fn follows_frames(&self) -> bool {
        self.input.is_some_and(|i| i.at.is_none())
    }

    /// True when it sweeps the input path over a path's frames.
    pub fn sweeps(&self) -> bool {
        self.input
            .is_some_and(|i| i.start.is_some() || i.end.is_some())
    }

    /// The camera stated outright: the input camera, when asked for, of the clip whose given
    /// cameras are `cameras`, for the frame rendering at `t`, `fraction` (0..=1) of the way
    /// along its path (`None` for a single view).
    pub fn resolve(
        &self,
        cameras: Option<&ClipCameras>,
        t: f64,
        fraction: Option<f64>,
    ) -> Result<CameraSpec, ServiceError> {
        let Some(input) = self.input else {
            return Ok(self.clone());
        };
        if self.world_to_camera.is_some() || self.intrinsics.is_some() {
            return Err(ServiceError::invalid(
                "a camera is either stated (world_to_camera, intrinsics) or the input camera \
                 (input), not both",
            ));
        }
        let time = match (input.at, input.start, input.end, fraction) {
            (Some(at), None, None, _) => at,
            (None, None, None, _) => t,
            (None, Some(start), Some(end), Some(f)) => start + (end - start) * f,
            (None, Some(_), Some(_), None) => {
                return Err(ServiceError::invalid(
                    "input start and end sweep the input path over a trajectory's frames; a \
                     single view takes input at (or {} for the view's own time)",
                ));
            }
            _ => {
                return Err(ServiceError::invalid(
                    "input takes `at` (a time, seconds), or `start` and `end` together (a sweep \
                     over the frames), or nothing (each frame's own time)",
                ));
            }
        };
        if !time.is_finite() {
            return Err(ServiceError::invalid(format!(
                "the input camera's time must be finite, got {time}"
            )));
        }
        let camera = input_camera(cameras, time);
        Ok(CameraSpec {
            world_to_camera: Some(camera.world_to_camera.iter().map(|v| *v as f32).collect()),
            intrinsics: Some(IntrinsicsSpec {
                fx: camera.intrinsics.fx as f32,
                fy: camera.intrinsics.fy as f32,
                cx: camera.intrinsics.cx as f32,
                cy: camera.intrinsics.cy as f32,
            }),
            input: None,
        })
    }

    /// The camera at `width` × `height` (an input camera must be [`resolve`](Self::resolve)d
    /// first).
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera, ServiceError> {
        if self.input.is_some() {
            return Err(ServiceError::Internal(
                "an input camera reached rendering unresolved".into(),
            ));
        }
        let pose = match &self.world_to_camera {
            None => Affine3A::IDENTITY,
            Some(m) if m.len() == 16 => {
                let rows = Mat4::from_cols_slice(m).transpose();
                if rows.row(3) != glam::Vec4::W {
                    return Err(ServiceError::invalid(format!(
                        "world_to_camera must end in the row 0 0 0 1, got {:?}",
                        &m[12..]
                    )));
                }
                if let Some((i, v)) = m[..12].iter().enumerate().find(|(_, v)| !bounded(**v)) {
                    return Err(ServiceError::invalid(format!(
                        "world_to_camera[{i}] must be between {:e} and {SCENE_BOUND:e}, got {v}",
                        -SCENE_BOUND
                    )));
                }
                Affine3A::from_mat4(rows)
            }
            Some(m) => {
                return Err(ServiceError::invalid(format!(
                    "world_to_camera needs 16 numbers (row-major 4x4), got {}",
                    m.len()
                )));
            }
        };
        if let Some(i) = self.intrinsics {
            // Compared in f32, as the values are held: a bound stated in the contract (1e-6)
            // rounds as the value at that bound does, so the bound itself is accepted.
            let focal = (SMALLEST_LENGTH as f32)..=(FOCAL_BOUND as f32);
            let offset = (-FOCAL_BOUND as f32)..=(FOCAL_BOUND as f32);
            for (name, v, range) in [
                ("fx", i.fx, &focal),
                ("fy", i.fy, &focal),
                ("cx", i.cx, &offset),
                ("cy", i.cy, &offset),
            ] {
                if !range.contains(&v) {
                    return Err(ServiceError::invalid(format!(
                        "intrinsics {name} must be between {:e} and {:e} (fractions of the \
                         image size), got {v}",
                        range.start(),
                        range.end()
                    )));
                }
            }
        }
        let intrinsics = self
            .intrinsics
            .map(|i| NormalizedIntrinsics {
                fx: i.fx,
                fy: i.fy,
                cx: i.cx,
                cy: i.cy,
            })
            .unwrap_or(NormalizedIntrinsics::C4G_DEFAULT);
        Ok(Camera::from_normalized(intrinsics, width, height, pose)?)
    }
}

fn bounded(v: f32) -> bool {
    (-SCENE_BOUND..=SCENE_BOUND).contains(&f64::from(v))
}

/// A preset's fields: those of its `kind` only (serde would ignore others), each in range.
pub fn check_preset(preset: &Value) -> Result<(), ServiceError> {
    let Value::Object(fields) = preset else {
        return Ok(());
    };
    let kind = fields
        .get("kind")
        .and_then(Value::as_str)
        .unwrap_or_default();
    // (field, lowest, highest) of each kind's numbers.
    let length = (SMALLEST_LENGTH, SCENE_BOUND);
    let signed = (-SCENE_BOUND, SCENE_BOUND);
    let known: &[(&str, (f64, f64))] = match kind {
        "orbit" => &[
            ("depth", length),
            ("angle_degrees", signed),
            ("radius", length),
        ],
        "spiral" => &[
            ("radii", (0.0, SCENE_BOUND)),
            ("focus_depth", length),
            ("rotations", signed),
            ("z_rate", signed),
        ],
        "dolly" => &[("distance", signed), ("subject_depth", length)],
        // serde names the kinds it knows.
        _ => return Ok(()),
    };
    for (name, value) in fields.iter().filter(|(name, _)| *name != "kind") {
        let Some((_, (low, high))) = known.iter().find(|(k, _)| k == name) else {
            let names: Vec<&str> = known.iter().map(|(k, _)| *k).collect();
            return Err(ServiceError::invalid(format!(
                "unknown field `{name}` in the trajectory: a {kind} takes {}",
                names.join(", ")
            )));
        };
        match value {
            Value::Array(items) => items.iter().enumerate().try_for_each(|(i, v)| {
                within(Some(v), &format!("{kind} {name}[{i}]"), *low, *high)
            })?,
            v => within(Some(v), &format!("{kind} {name}"), *low, *high)?,
        }
    }
    Ok(())
}

/// `value`, when it is a number, in `low..=high`.
pub fn within(value: Option<&Value>, name: &str, low: f64, high: f64) -> Result<(), ServiceError> {
    match value.and_then(Value::as_f64) {
        Some(v) if !(low..=high).contains(&v) => Err(ServiceError::invalid(format!(
            "{name} must be between {low:e} and {high:e}, got {v}"
        ))),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn refusal(spec: CameraSpec) -> String {
        spec.camera(32, 32).unwrap_err().to_string()
    }

    /// Both transports build cameras here, so gRPC's f32 fields meet the bounds REST states.
    #[test]
    fn cameras_out_of_bounds_are_refused_whatever_the_transport() {
        let mut pose = vec![
            1.0, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
        ];
        assert!(
            CameraSpec {
                world_to_camera: Some(pose.clone()),
                intrinsics: None,
                input: None,
            }
            .camera(32, 32)
            .is_ok()
        );
        pose[3] = 2e6;
        let message = refusal(CameraSpec {
            world_to_camera: Some(pose),
            intrinsics: None,
            input: None,
        });
        assert!(message.contains("world_to_camera[3]"), "{message}");
        let intrinsics = |fx, cx| IntrinsicsSpec {
            fx,
            fy: 0.9,
            cx,
            cy: 0.5,
        };
        for (fx, cx, name) in [(1e30, 0.5, "fx"), (0.0, 0.5, "fx"), (0.9, -2e3, "cx")] {
            let message = refusal(CameraSpec {
                world_to_camera: None,
                intrinsics: Some(intrinsics(fx, cx)),
                input: None,
            });
            assert!(message.contains(&format!("intrinsics {name}")), "{message}");
        }
    }

    #[test]
    fn presets_are_held_to_their_own_fields_and_ranges() {
        let check = |v: serde_json::Value| check_preset(&v).map_err(|e| e.to_string());
        check(serde_json::json!({"kind": "orbit", "depth": 2.0, "angle_degrees": 30})).unwrap();
        assert!(
            check(serde_json::json!({"kind": "orbit", "depth": 0}))
                .unwrap_err()
                .contains("orbit depth")
        );
        assert!(
            check(serde_json::json!({"kind": "dolly", "radii": [1]}))
                .unwrap_err()
                .contains("unknown field `radii`")
        );
    }
}
