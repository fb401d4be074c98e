//! nerfstudio's `transforms.json` (its data format documentation, "Dataset format"):
//! `frames[].transform_matrix` is camera-to-world with OpenGL axes (x right, y up, z back), so it
//! becomes OpenCV's by flipping the camera's y and z axes; intrinsics are pixels, `fl_x`,
//! `fl_y`, `cx`, `cy` with the image size `w`, `h`, at the top level or per frame (a frame's own
//! win). `camera_angle_x` (the Blender / instant-ngp form) stands for `fl_x` when that is absent,
//! and `fl_y` defaults to `fl_x`, the principal point to the centre. Distortion (`k1`..`k4`,
//! `p1`, `p2`) is ignored with a note, as for COLMAP; camera models other than `OPENCV` and
//! `PINHOLE` are refused. A world transform the file applies (`applied_transform`) cancels out:
//! every pose is taken relative to the first context camera.

use serde_json::{Map, Value};

use super::pose::{GivenCamera, Intrinsics};
use super::{Parsed, frame_order};
use crate::ServiceError;

const DISTORTION: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];

/// Every frame's camera in frame order, the notes about ignored distortion, and the image sizes
/// the file states.
pub fn parse(text: &str, names: Option<&[String]>) -> Result<Parsed, ServiceError> {
    let root: Map<String, Value> = serde_json::from_str(text).map_err(|e| {
        ServiceError::invalid(format!(
            "transforms.json is not a JSON object ({e}): give nerfstudio's transforms.json"
        ))
    })?;
    let frames = match root.get("frames") {
        Some(Value::Array(frames)) if !frames.is_empty() => frames,
        _ => {
            return Err(ServiceError::invalid(
                "transforms.json needs a non-empty `frames` list",
            ));
        }
    };
    let frames: Vec<&Map<String, Value>> = frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            f.as_object().ok_or_else(|| {
                ServiceError::invalid(format!("transforms.json frames[{i}] is not an object"))
            })
        })
        .collect::<Result<_, _>>()?;
    let paths: Vec<&str> = frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            f.get("file_path").and_then(Value::as_str).ok_or_else(|| {
                ServiceError::invalid(format!(
                    "transforms.json frames[{i}] needs a `file_path` (frames are matched by it)"
                ))
            })
        })
        .collect::<Result<_, _>>()?;
    let order = frame_order(&paths, names, "transforms.json")?;
    let mut notes = Vec::new();
    let mut sizes = Vec::new();
    let cameras = order
        .iter()
        .map(|&i| {
            let name = format!("transforms.json frames[{i}] ({})", paths[i]);
            let frame = frames[i];
            let (intrinsics, size) = intrinsics(&root, frame, &name, &mut notes)?;
            if !sizes.contains(&size) {
                sizes.push(size);
            }
            let matrix = transform_matrix(frame, &name)?;
            GivenCamera::from_camera_to_world(&opengl_to_opencv(&matrix), intrinsics, &name)
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Parsed {
        cameras,
        notes,
        format: "transforms",
        image_sizes: sizes,
    })
}

/// A frame's field, else the file's.
fn field<'a>(
    root: &'a Map<String, Value>,
    frame: &'a Map<String, Value>,
    key: &str,
) -> Option<&'a Value> {
    frame.get(key).or_else(|| root.get(key))
}

fn number(
    root: &Map<String, Value>,
    frame: &Map<String, Value>,
    key: &str,
    name: &str,
) -> Result<Option<f64>, ServiceError> {
    match field(root, frame, key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => match v.as_f64() {
            Some(x) if x.is_finite() => Ok(Some(x)),
            _ => Err(ServiceError::invalid(format!(
                "{name}: `{key}` must be a number, got {v}"
            ))),
        },
    }
}

fn intrinsics(
    root: &Map<String, Value>,
    frame: &Map<String, Value>,
    name: &str,
    notes: &mut Vec<String>,
) -> Result<(Intrinsics, (f64, f64)), ServiceError> {
    if let Some(model) = field(root, frame, "camera_model") {
        match model.as_str() {
            Some("OPENCV" | "PINHOLE") => {}
            _ => {
                return Err(ServiceError::invalid(format!(
                    "{name}: camera_model {model} is not supported: give OPENCV or PINHOLE \
                     (distortion is ignored), or undistort the images first"
                )));
            }
        }
    }
    let get = |key: &str| number(root, frame, key, name);
    let (Some(w), Some(h)) = (get("w")?, get("h")?) else {
        return Err(ServiceError::invalid(format!(
            "{name}: the image size `w` and `h` is needed to read pixel intrinsics"
        )));
    };
    let fx = match (get("fl_x")?, get("camera_angle_x")?) {
        (Some(f), _) => f,
        (None, Some(angle)) => 0.5 * w / (0.5 * angle).tan(),
        (None, None) => {
            return Err(ServiceError::invalid(format!(
                "{name}: give the focal length `fl_x` (or `camera_angle_x`)"
            )));
        }
    };
    let fy = get("fl_y")?.unwrap_or(fx);
    let cx = get("cx")?.unwrap_or(w / 2.0);
    let cy = get("cy")?.unwrap_or(h / 2.0);
    let distortion: Vec<(&str, f64)> = DISTORTION
        .iter()
        .filter_map(|k| get(k).transpose().map(|v| v.map(|v| (*k, v))))
        .collect::<Result<Vec<_>, _>>()?
        .into_iter()
        .filter(|(_, v)| *v != 0.0)
        .collect();
    if !distortion.is_empty() {
        let note =
            format!("transforms.json distortion {distortion:?} is ignored (renders are pinhole)");
        if !notes.contains(&note) {
            notes.push(note);
        }
    }
    Ok((
        Intrinsics::from_pixels([fx, fy, cx, cy], w, h, name)?,
        (w, h),
    ))
}

/// `transform_matrix`: 4 rows of 4 numbers (3 rows are taken too, as some writers leave the last
/// out), row-major.
fn transform_matrix(frame: &Map<String, Value>, name: &str) -> Result<Vec<f64>, ServiceError> {
    let bad = || {
        ServiceError::invalid(format!(
            "{name}: transform_matrix must be 4 rows of 4 numbers"
        ))
    };
    let rows = frame
        .get("transform_matrix")
        .and_then(Value::as_array)
        .ok_or_else(bad)?;
    if rows.len() != 4 && rows.len() != 3 {
        return Err(bad());
    }
    let mut m = Vec::with_capacity(16);
    for row in rows {
        let row = row.as_array().filter(|r| r.len() == 4).ok_or_else(bad)?;
        for v in row {
            m.push(v.as_f64().ok_or_else(bad)?);
        }
    }
    if rows.len() == 3 {
        m.extend([0.0, 0.0, 0.0, 1.0]);
    }
    Ok(m)
}

/// An OpenGL camera-to-world (camera y up, z back) as OpenCV's (y down, z forward): the
/// camera's y and z axes, the matrix's second and third columns, change sign.
fn opengl_to_opencv(m: &[f64]) -> Vec<f64> {
    let mut out = m.to_vec();
    for row in 0..3 {
        out[row * 4 + 1] = -m[row * 4 + 1];
        out[row * 4 + 2] = -m[row * 4 + 2];
    }
    out
}

/// `cameras` (of `width` × `height` images at `file_paths`) as nerfstudio's `transforms.json`:
/// per frame, its pixel intrinsics and its camera-to-world `transform_matrix` with OpenGL axes
/// (OpenCV's camera y and z flipped), as [`parse`] reads them.
pub fn write(cameras: &[GivenCamera], file_paths: &[String], width: u32, height: u32) -> String {
    let (w, h) = (f64::from(width), f64::from(height));
    let frames: Vec<Value> = cameras
        .iter()
        .zip(file_paths)
        .map(|(camera, path)| {
            let to_world = camera.rotation.transpose();
            // Columns: the camera's axes in the world (y and z flipped), then its centre.
            let axes = [to_world.x_axis, -to_world.y_axis, -to_world.z_axis];
            let centre = camera.centre();
            let row = |r: usize| {
                let pick = |v: glam::DVec3| v.to_array()[r];
                serde_json::json!([pick(axes[0]), pick(axes[1]), pick(axes[2]), pick(centre)])
            };
            let i = camera.intrinsics;
            serde_json::json!({
                "file_path": path,
                "fl_x": i.fx * w,
                "fl_y": i.fy * h,
                "cx": i.cx * w,
                "cy": i.cy * h,
                "w": width,
                "h": height,
                "transform_matrix": [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]],
            })
        })
        .collect();
    let root = serde_json::json!({"camera_model": "PINHOLE", "frames": frames});
    serde_json::to_string_pretty(&root).unwrap_or_default()
}
