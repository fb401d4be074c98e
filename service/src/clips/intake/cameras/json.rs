//! The JSON form: a list with one object per frame, in frame order:
//! `{"world_to_camera": [16 numbers, row-major], "intrinsics": {"fx", "fy", "cx", "cy"}}`, or
//! `camera_to_world` instead of `world_to_camera` (OpenCV axes either way); intrinsics are
//! fractions of the image size, as a render's `CameraSpec` states them (the model's own when
//! left out).

use serde::Deserialize;

use super::pose::{GivenCamera, Intrinsics};
use crate::ServiceError;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Entry {
    world_to_camera: Option<Vec<f64>>,
    camera_to_world: Option<Vec<f64>>,
    intrinsics: Option<Intrinsics>,
}

/// Every camera of the list.
pub fn parse(text: &str) -> Result<Vec<GivenCamera>, ServiceError> {
    let entries: Vec<Entry> = serde_json::from_str(text).map_err(|e| {
        ServiceError::invalid(format!(
            "cameras is not a JSON list of cameras ({e}): give one object per frame with \
             world_to_camera or camera_to_world (16 numbers, row-major) and optional intrinsics"
        ))
    })?;
    entries
        .into_iter()
        .enumerate()
        .map(|(i, entry)| {
            let name = format!("cameras[{i}]");
            let k = entry.intrinsics.unwrap_or(Intrinsics::C4G_DEFAULT);
            match (entry.world_to_camera, entry.camera_to_world) {
                (Some(m), None) => GivenCamera::from_world_to_camera(&m, k, &name),
                (None, Some(m)) => GivenCamera::from_camera_to_world(&m, k, &name),
                _ => Err(ServiceError::invalid(format!(
                    "{name}: give exactly one of world_to_camera and camera_to_world"
                ))),
            }
        })
        .collect()
}

/// `cameras` as the list [`parse`] reads: `world_to_camera` row-major and intrinsics as fractions
/// of the image size.
pub fn write(cameras: &[GivenCamera]) -> String {
    let list: Vec<serde_json::Value> = cameras
        .iter()
        .map(|c| {
            serde_json::json!({
                "world_to_camera": c.world_to_camera_rows(),
                "intrinsics": c.intrinsics,
            })
        })
        .collect();
    serde_json::to_string_pretty(&list).unwrap_or_default()
}
