//! COLMAP's text model (`cameras.txt`, `images.txt`), as COLMAP writes it
//! (`colmap model_converter --output_type TXT`; format in COLMAP's documentation, "Output
//! format").
//!
//! - `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`. Pinhole models are exact:
//!   `PINHOLE` (fx fy cx cy), `SIMPLE_PINHOLE` (f cx cy). Models with lens distortion whose first
//!   parameters are a pinhole's, `SIMPLE_RADIAL` (f cx cy k), `RADIAL` (f cx cy k1 k2) and
//!   `OPENCV` (fx fy cx cy k1 k2 p1 p2), are accepted with the distortion ignored: C4G's
//!   renderers are pinhole and the model sees the frames as they are; a note says so on the clip
//!   when a coefficient is not zero. Fisheye and the rest are refused, naming the models taken.
//! - `images.txt`: two lines per image, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and its
//!   2D points (`X Y POINT3D_ID` triples, possibly empty), which are skipped. The pose is
//!   world-to-camera, OpenCV axes, the quaternion Hamilton's with the scalar first.
//! - Frames get images by name order, or by the file-name list when one is given.

use std::collections::HashMap;

use glam::DVec3;

use super::pose::{GivenCamera, Intrinsics};
use super::{Parsed, frame_order};
use crate::ServiceError;
use crate::quoted;

/// A camera of `cameras.txt`: intrinsics, and the distortion it had.
struct Lens {
    intrinsics: Intrinsics,
    size: (f64, f64),
    model: String,
    distortion: Vec<f64>,
}

/// Every image's camera in frame order, the notes about ignored distortion, and the image sizes
/// the cameras used state.
pub fn parse(
    cameras_txt: &str,
    images_txt: &str,
    names: Option<&[String]>,
) -> Result<Parsed, ServiceError> {
    let lenses = parse_cameras(cameras_txt)?;
    let images = parse_images(images_txt)?;
    if images.is_empty() {
        return Err(ServiceError::invalid("images.txt lists no image"));
    }
    let available: Vec<&str> = images.iter().map(|i| i.name.as_str()).collect();
    let order = frame_order(&available, names, "images.txt")?;
    let mut distorted: Vec<u64> = Vec::new();
    let mut sizes: Vec<(f64, f64)> = Vec::new();
    let cameras = order
        .iter()
        .map(|&i| {
            let image = &images[i];
            let lens = lenses.get(&image.camera_id).ok_or_else(|| {
                ServiceError::invalid(format!(
                    "images.txt line {}: image {:?} uses camera {}, which cameras.txt does not \
                     list",
                    image.line, image.name, image.camera_id
                ))
            })?;
            if !sizes.contains(&lens.size) {
                sizes.push(lens.size);
            }
            if lens.distortion.iter().any(|d| *d != 0.0) && !distorted.contains(&image.camera_id) {
                distorted.push(image.camera_id);
            }
            GivenCamera::from_quaternion(
                image.quaternion,
                image.translation,
                lens.intrinsics,
                &format!("images.txt line {} ({})", image.line, image.name),
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let notes = distorted
        .iter()
        .map(|id| {
            let lens = &lenses[id];
            format!(
                "COLMAP camera {id} is {} with distortion {:?}: the distortion is ignored \
                 (renders are pinhole)",
                lens.model, lens.distortion
            )
        })
        .collect();
    Ok(Parsed {
        cameras,
        notes,
        format: "colmap",
        image_sizes: sizes,
    })
}

/// Non-comment lines with their 1-based numbers.
fn content(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.starts_with('#'))
}

fn number(file: &str, line: usize, field: &str, text: &str) -> Result<f64, ServiceError> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(ServiceError::invalid(format!(
            "{file} line {line}: {field} must be a finite number, got {text_quoted}",
            text_quoted = quoted(text)
        ))),
    }
}

fn id(file: &str, line: usize, field: &str, text: &str) -> Result<u64, ServiceError> {
    text.parse().map_err(|_| {
        ServiceError::invalid(format!(
            "{file} line {line}: {field} must be a whole number, got {text_quoted}",
            text_quoted = quoted(text)
        ))
    })
}

fn parse_cameras(text: &str) -> Result<HashMap<u64, Lens>, ServiceError> {
    let mut lenses = HashMap::new();
    for (line, fields) in content(text).filter(|(_, l)| !l.is_empty()) {
        let fields: Vec<&str> = fields.split_whitespace().collect();
        let file = "cameras.txt";
        if fields.len() < 4 {
            return Err(ServiceError::invalid(format!(
                "{file} line {line}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {} \
                 fields",
                fields.len()
            )));
        }
        let camera_id = id(file, line, "CAMERA_ID", fields[0])?;
        let model = fields[1];
        let width = number(file, line, "WIDTH", fields[2])?;
        let height = number(file, line, "HEIGHT", fields[3])?;
        let params = fields[4..]
            .iter()
            .map(|p| number(file, line, "a parameter", p))
            .collect::<Result<Vec<_>, _>>()?;
        // (parameters, focal lengths and principal point from them, distortion from index).
        let (count, pinhole, distortion_from) = match model {
            "PINHOLE" => (4, [0, 1, 2, 3], 4),
            "SIMPLE_PINHOLE" => (3, [0, 0, 1, 2], 3),
            "SIMPLE_RADIAL" => (4, [0, 0, 1, 2], 3),
            "RADIAL" => (5, [0, 0, 1, 2], 3),
            "OPENCV" => (8, [0, 1, 2, 3], 4),
            other => {
                return Err(ServiceError::invalid(format!(
                    "{file} line {line}: camera model {other} is not supported: give PINHOLE, \
                     SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV (distortion is ignored), \
                     or undistort the images first (colmap image_undistorter)"
                )));
            }
        };
        if params.len() != count {
            return Err(ServiceError::invalid(format!(
                "{file} line {line}: a {model} camera has {count} parameters, got {}",
                params.len()
            )));
        }
        let intrinsics = Intrinsics::from_pixels(
            pinhole.map(|i| params[i]),
            width,
            height,
            &format!("{file} line {line}"),
        )?;
        let lens = Lens {
            intrinsics,
            size: (width, height),
            model: model.to_owned(),
            distortion: params[distortion_from..].to_vec(),
        };
        if lenses.insert(camera_id, lens).is_some() {
            return Err(ServiceError::invalid(format!(
                "{file} line {line}: camera {camera_id} is listed twice"
            )));
        }
    }
    Ok(lenses)
}

struct Image {
    line: usize,
    quaternion: [f64; 4],
    translation: DVec3,
    camera_id: u64,
    name: String,
}

fn parse_images(text: &str) -> Result<Vec<Image>, ServiceError> {
    let file = "images.txt";
    let mut images = Vec::new();
    let mut lines = content(text);
    while let Some((line, fields)) = lines.next() {
        if fields.is_empty() {
            continue;
        }
        let parts: Vec<&str> = fields.splitn(10, char::is_whitespace).collect();
        let parts: Vec<&str> = parts.iter().map(|p| p.trim()).collect();
        if parts.len() < 10 || parts[9].is_empty() {
            return Err(ServiceError::invalid(format!(
                "{file} line {line}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got \
                 {fields:?}"
            )));
        }
        id(file, line, "IMAGE_ID", parts[0])?;
        let n = |i: usize, field: &str| number(file, line, field, parts[i]);
        let image = Image {
            line,
            quaternion: [n(1, "QW")?, n(2, "QX")?, n(3, "QY")?, n(4, "QZ")?],
            translation: DVec3::new(n(5, "TX")?, n(6, "TY")?, n(7, "TZ")?),
            camera_id: id(file, line, "CAMERA_ID", parts[8])?,
            name: parts[9].to_owned(),
        };
        // The points line follows every image line, even when empty (COLMAP's own reader
        // takes it unconditionally); one that is not triples of numbers means it is missing.
        let points = lines.next();
        if let Some((points_line, points)) = points {
            let tokens: Vec<&str> = points.split_whitespace().collect();
            if !tokens.len().is_multiple_of(3) || tokens.iter().any(|t| t.parse::<f64>().is_err()) {
                return Err(ServiceError::invalid(format!(
                    "{file} line {points_line}: expected the 2D points of image {:?} (X Y \
                     POINT3D_ID triples, or an empty line): every image takes two lines",
                    image.name
                )));
            }
        }
        images.push(image);
    }
    Ok(images)
}

/// `cameras` (of `width` × `height` images named `names`) as COLMAP's text model: `cameras.txt`
/// with one `PINHOLE` camera per image (pixel intrinsics) and `images.txt` with each image's
/// world-to-camera quaternion (scalar first) and translation and an empty line of 2D points, as
/// [`parse`] reads them. Numbers are written in full (Rust's shortest round-trip form).
pub fn write(
    cameras: &[GivenCamera],
    names: &[String],
    width: u32,
    height: u32,
) -> (String, String) {
    let (w, h) = (f64::from(width), f64::from(height));
    let mut lenses = String::from(
        "# Camera list with one line of data per camera:\n\
         #   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
    );
    let mut images = String::from(
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    for (k, (camera, name)) in cameras.iter().zip(names).enumerate() {
        let id = k + 1;
        let i = camera.intrinsics;
        lenses.push_str(&format!(
            "{id} PINHOLE {width} {height} {} {} {} {}\n",
            i.fx * w,
            i.fy * h,
            i.cx * w,
            i.cy * h
        ));
        let q = glam::DQuat::from_mat3(&camera.rotation).normalize();
        let t = camera.translation;
        images.push_str(&format!(
            "{id} {} {} {} {} {} {} {} {id} {name}\n\n",
            q.w, q.x, q.y, q.z, t.x, t.y, t.z
        ));
    }
    (lenses, images)
}
