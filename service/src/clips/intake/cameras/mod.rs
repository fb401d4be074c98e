//! Given cameras: per-frame cameras a client uploads with its clip, in one of three forms, read
//! into one list and mapped into the model's frame.
//!
//! C4G predicts no cameras (`../shared/docs/C4G_MODEL.md`, "Cameras and time interpolation in
//! the public code"): its public code takes poses from an external estimator. A client that has
//! them (COLMAP, nerfstudio, its own tracker) sends them with the upload, one per source frame;
//! the clip keeps those of its context frames, so renders can follow the input path.
//!
//! | module | holds |
//! |---|---|
//! | `pose` | [`GivenCamera`]: one frame's pose and intrinsics, checked (rigid, finite, bounded) |
//! | `json` | the JSON list (`world_to_camera` or `camera_to_world`, normalised intrinsics) |
//! | `colmap` | COLMAP's text model: `cameras.txt` and `images.txt` |
//! | `nerfstudio` | nerfstudio's `transforms.json` (OpenGL camera-to-world, pixel intrinsics) |
//! | `model_frame` | the context frames' cameras in the model's frame ([`ClipCameras`]), as stored |
//! | `input_path` | the input camera at any time: the stored cameras interpolated ([`input_camera`]) |
//!
//! Each form's writer sits beside its reader ([`write`]): cameras go out as they came in.

mod colmap;
mod input_path;
mod json;
mod model_frame;
mod nerfstudio;
mod pose;

use sha2::{Digest, Sha256};

use crate::ServiceError;
use crate::quoted;
pub use input_path::{InputCamera, input_camera};
pub use model_frame::{ClipCameras, ContextCamera, ScaleFit};
pub use pose::{FOCAL_BOUND, GivenCamera, Intrinsics, SMALLEST_LENGTH};

/// Cameras as the client sent them: the text of one of the three forms.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraInput {
    /// A JSON list, one object per frame.
    Json(String),
    /// COLMAP's text model.
    Colmap {
        /// `cameras.txt`.
        cameras: String,
        /// `images.txt`.
        images: String,
        /// The images in frame order, by name; without it, images sorted by name.
        names: Option<Vec<String>>,
    },
    /// nerfstudio's `transforms.json`.
    Transforms {
        /// The file.
        json: String,
        /// The frames in frame order, by `file_path`; without it, frames sorted by `file_path`.
        names: Option<Vec<String>>,
    },
}

/// Cameras read from a [`CameraInput`]: one per source frame, and what was ignored.
#[derive(Debug, Clone, PartialEq)]
pub struct Parsed {
    /// One per source frame, in frame order.
    pub cameras: Vec<GivenCamera>,
    /// What the client should know: distortion that was ignored, say.
    pub notes: Vec<String>,
    /// `json`, `colmap` or `transforms`.
    pub format: &'static str,
    /// The image sizes (width, height, pixels) the cameras were estimated at, where the form
    /// states them (COLMAP, transforms.json): their shape must be the frames'.
    pub image_sizes: Vec<(f64, f64)>,
}

/// How far the shape (width over height) of the images cameras were estimated at may be from the
/// frames': 1%, more than rounding a size to whole pixels, less than any real crop.
pub const ASPECT_TOLERANCE: f64 = 0.01;

/// Most cameras an upload may carry: as many as the source frames a server takes at most would
/// be the natural bound, but parsing happens before the frames are read, so a fixed bound keeps
/// a hostile camera file from costing more than the frames themselves.
pub const MAX_CAMERAS: usize = 100_000;

/// The forms cameras go out in (`GET /v1/clips/{id}/cameras?format=`): each written beside its
/// reader, so what goes out is what an upload reads back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraFormat {
    /// The JSON list (`cameras.json`).
    Json,
    /// COLMAP's text model (`cameras.txt`, `images.txt`, and an empty `points3D.txt`, which
    /// COLMAP's model readers expect).
    Colmap,
    /// nerfstudio's `transforms.json`.
    Transforms,
}

/// `cameras` of `width` × `height` images named `names` (frame order) as the files of `format`:
/// (file name, contents).
pub fn write(
    format: CameraFormat,
    cameras: &[GivenCamera],
    names: &[String],
    width: u32,
    height: u32,
) -> Vec<(&'static str, String)> {
    match format {
        CameraFormat::Json => vec![("cameras.json", json::write(cameras))],
        CameraFormat::Colmap => {
            let (lenses, images) = colmap::write(cameras, names, width, height);
            vec![
                ("cameras.txt", lenses),
                ("images.txt", images),
                ("points3D.txt", String::new()),
            ]
        }
        CameraFormat::Transforms => vec![(
            "transforms.json",
            nerfstudio::write(cameras, names, width, height),
        )],
    }
}

impl CameraInput {
    /// Reads and checks every camera.
    pub fn parse(&self) -> Result<Parsed, ServiceError> {
        let parsed = match self {
            Self::Json(text) => Parsed {
                cameras: json::parse(text)?,
                notes: Vec::new(),
                format: "json",
                image_sizes: Vec::new(),
            },
            Self::Colmap {
                cameras,
                images,
                names,
            } => colmap::parse(cameras, images, names.as_deref())?,
            Self::Transforms { json, names } => nerfstudio::parse(json, names.as_deref())?,
        };
        let cameras = &parsed.cameras;
        if cameras.is_empty() {
            return Err(ServiceError::invalid(
                "the cameras list no camera: give one per frame",
            ));
        }
        if cameras.len() > MAX_CAMERAS {
            return Err(ServiceError::invalid(format!(
                "{} cameras; at most {MAX_CAMERAS} are accepted",
                cameras.len()
            )));
        }
        Ok(parsed)
    }

    /// Feeds the cameras into a clip's content address: other cameras make another clip.
    pub fn hash_into(&self, hasher: &mut Sha256) {
        let mut part = |tag: &[u8], text: &str| {
            hasher.update(tag);
            hasher.update((text.len() as u64).to_le_bytes());
            hasher.update(text.as_bytes());
        };
        match self {
            Self::Json(text) => part(b"cameras-json\0", text),
            Self::Colmap {
                cameras,
                images,
                names,
            } => {
                part(b"cameras-colmap\0", cameras);
                part(b"images\0", images);
                part(
                    b"names\0",
                    &names.as_ref().map(|n| n.join("\n")).unwrap_or_default(),
                );
            }
            Self::Transforms { json, names } => {
                part(b"cameras-transforms\0", json);
                part(
                    b"names\0",
                    &names.as_ref().map(|n| n.join("\n")).unwrap_or_default(),
                );
            }
        }
    }
}

impl Parsed {
    /// Checks the cameras against the frames they belong to: one per source frame (`frames`, of
    /// `width` × `height` pixels), estimated at images of the same shape.
    pub fn check_against(
        &self,
        frames: usize,
        width: u32,
        height: u32,
    ) -> Result<(), ServiceError> {
        if self.cameras.len() != frames {
            return Err(ServiceError::invalid(format!(
                "{} cameras for {frames} frames: give one camera per frame of the upload (every \
                 source frame that was read, in order), not only the context frames",
                self.cameras.len()
            )));
        }
        let aspect = f64::from(width) / f64::from(height.max(1));
        if let Some((w, h)) = self
            .image_sizes
            .iter()
            .find(|(w, h)| ((w / h) / aspect - 1.0).abs() > ASPECT_TOLERANCE)
        {
            return Err(ServiceError::invalid(format!(
                "the cameras were estimated on {w}x{h} images but the frames are \
                 {width}x{height}: a different shape (a crop or a rotation) makes the \
                 intrinsics wrong; give cameras for these frames"
            )));
        }
        Ok(())
    }
}

/// A file-name list (`camera_names`): one name per line, or comma-separated; blanks trimmed.
pub fn parse_names(text: &str) -> Result<Vec<String>, ServiceError> {
    let separator = if text.contains('\n') { '\n' } else { ',' };
    let names: Vec<String> = text
        .split(separator)
        .map(|n| n.trim().to_owned())
        .filter(|n| !n.is_empty())
        .collect();
    if names.is_empty() {
        return Err(ServiceError::invalid(
            "camera_names lists no name: give the image names in frame order",
        ));
    }
    Ok(names)
}

/// `names` (the frame order) as indices into `available`, each name found exactly once; without
/// `names`, `available` sorted by name. `what` names the file for messages.
fn frame_order(
    available: &[&str],
    names: Option<&[String]>,
    what: &str,
) -> Result<Vec<usize>, ServiceError> {
    match names {
        None => {
            let mut order: Vec<usize> = (0..available.len()).collect();
            order.sort_by(|&a, &b| available[a].cmp(available[b]));
            if let Some(w) = order
                .windows(2)
                .find(|w| available[w[0]] == available[w[1]])
            {
                return Err(ServiceError::invalid(format!(
                    "{what} names the image {:?} twice: frames are matched to images by name",
                    available[w[0]]
                )));
            }
            Ok(order)
        }
        Some(names) => names
            .iter()
            .enumerate()
            .map(|(frame, name)| {
                available.iter().position(|a| a == name).ok_or_else(|| {
                    ServiceError::invalid(format!(
                        "camera_names[{frame}] is {name_quoted}, which {what} does not have \
                             (it has {} images)",
                        available.len(),
                        name_quoted = quoted(name)
                    ))
                })
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests;
