//! The clip's input cameras as files other tools open (`GET /v1/clips/{id}/cameras?format=`):
//! its given cameras, or the recovered ones, in the model's frame (the first context camera is
//! the identity; translations in model units, `scale` given units each), as the JSON list, COLMAP's
//! text model (zipped: `cameras.txt`, `images.txt`, `points3D.txt`) or nerfstudio's
//! `transforms.json`: one camera per context frame, named as `GET /v1/clips/{id}/frames/{k}` serves
//! it (`000.png`, ...), with pixel intrinsics of the source frame's size. Each is written by the
//! writer beside the upload's reader of that form, so a file that goes out uploads back as the
//! same cameras.

use std::io::Write;

use zip::ZipWriter;
use zip::write::SimpleFileOptions;

use crate::ServiceError;
use crate::clips::intake::cameras::{self, CameraFormat, GivenCamera};
use crate::views::render::Views;

/// A file of cameras, ready to send.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFile {
    /// Its media type.
    pub content_type: &'static str,
    /// A name for it.
    pub file_name: String,
    /// Its bytes.
    pub bytes: Vec<u8>,
}

impl Views {
    /// Clip `id`'s input cameras as `format`; `not_found` for a clip with none.
    pub async fn camera_file(
        &self,
        id: &str,
        format: CameraFormat,
    ) -> Result<CameraFile, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        let clip_cameras = self.input_cameras(&record).ok_or_else(|| {
            ServiceError::NotFound(format!(
                "clip {id} has no cameras: upload it with cameras, or recover them (POST \
                 /v1/clips/{id}/cameras/recover)"
            ))
        })?;
        let (width, height) = (record.source.width, record.source.height);
        // Recovered cameras are the model's, whose intrinsics are fractions of its square crop;
        // files state the whole frame's.
        let recovered = clip_cameras.format == "recovered";
        let given = clip_cameras
            .frames
            .iter()
            .enumerate()
            .map(|(k, frame)| {
                let intrinsics = if recovered {
                    frame.intrinsics.crop_to_frame(width, height)
                } else {
                    frame.intrinsics
                };
                GivenCamera::from_world_to_camera(
                    &frame.world_to_camera,
                    intrinsics,
                    &format!("context camera {k}"),
                )
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| ServiceError::Internal(format!("a stored camera is unreadable: {e}")))?;
        let names: Vec<String> = (0..given.len()).map(|k| format!("{k:03}.png")).collect();
        let files = cameras::write(format, &given, &names, width, height);
        let stem: String = id.chars().take(12).collect();
        Ok(match format {
            CameraFormat::Colmap => CameraFile {
                content_type: "application/zip",
                file_name: format!("{stem}-colmap.zip"),
                bytes: zipped(&files)?,
            },
            CameraFormat::Json | CameraFormat::Transforms => {
                let (name, text) = files.into_iter().next().unwrap_or_default();
                CameraFile {
                    content_type: "application/json",
                    file_name: format!("{stem}-{name}"),
                    bytes: text.into_bytes(),
                }
            }
        })
    }
}

/// `files` as one zip archive, stored uncompressed (they are small text).
fn zipped(files: &[(&str, String)]) -> Result<Vec<u8>, ServiceError> {
    let failed =
        |e: &dyn std::fmt::Display| ServiceError::Internal(format!("cannot zip cameras: {e}"));
    let mut zip = ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, text) in files {
        zip.start_file(*name, SimpleFileOptions::default())
            .map_err(|e| failed(&e))?;
        zip.write_all(text.as_bytes()).map_err(|e| failed(&e))?;
    }
    Ok(zip.finish().map_err(|e| failed(&e))?.into_inner())
}
