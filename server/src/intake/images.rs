//! Image frames: from a zip or tar archive (in name order), as separate uploads, or one image.
//!
//! Archives are untrusted: entry counts and declared sizes are checked before anything is
//! inflated, an entry that claims more than [`MAX_INFLATION`] times its compressed size is
//! refused as a decompression bomb, and reads stop at the declared size whatever the archive
//! claims. Image headers are read for sizes before pixels are decoded.

use std::io::{Cursor, Read};

use bytes::Bytes;
use image::{ImageReader, RgbImage};

use super::sampling::select;
use super::{
    DEFAULT_IMAGE_FPS, Intake, IntakeOptions, Media, MediaKind, SourceInfo, TimedFrame,
    check_duration, check_frame_count, check_frame_size, frame_step,
};
use crate::ServiceError;
use crate::config::Limits;

/// Largest ratio of inflated to compressed size an archive entry may claim. Image files are
/// already compressed: real frames inflate by a few percent, bombs by thousands of times.
const MAX_INFLATION: u64 = 100;

/// Reads image frames and picks the context frames (blocking: image decoding is CPU work).
pub fn read(
    media: Media,
    kind: MediaKind,
    options: &IntakeOptions,
    limits: &Limits,
) -> Result<Intake, ServiceError> {
    let files = match (kind, media) {
        (_, Media::Frames(frames)) => frames,
        (MediaKind::Zip, Media::File { data, .. }) => unzip(&data, limits)?,
        (MediaKind::Tar, Media::File { data, .. }) => untar(&data, limits)?,
        (MediaKind::Image, Media::File { data, .. }) => vec![data],
        (_, Media::File { .. }) => {
            return Err(ServiceError::UnsupportedMedia(
                "the upload is not a video, an image archive or an image".into(),
            ));
        }
    };
    if files.is_empty() {
        return Err(ServiceError::invalid(
            "the archive holds no PNG or JPEG frames",
        ));
    }
    check_frame_count(files.len(), limits)?;
    let times = frame_times(files.len(), options)?;
    check_duration(times.last().copied().unwrap_or(0.0), limits)?;

    // Every frame's header is checked (sizes agree, within limits) before any is decoded.
    let mut size = None;
    for (i, file) in files.iter().enumerate() {
        let (w, h) = dimensions(file).map_err(|e| {
            ServiceError::UnreadableMedia(format!("frame {i} is not a readable PNG or JPEG: {e}"))
        })?;
        check_frame_size(w, h, limits)?;
        match size {
            None => size = Some((w, h)),
            Some((w0, h0)) if (w0, h0) != (w, h) => {
                return Err(ServiceError::UnreadableMedia(format!(
                    "frames differ in size: frame 0 is {w0}x{h0}, frame {i} is {w}x{h}; \
                     every frame of a clip must have the same size"
                )));
            }
            Some(_) => {}
        }
    }
    let (width, height) = size.unwrap_or((0, 0));
    let chosen = select(&times, options, limits)?;
    let frames = chosen
        .iter()
        .map(|&i| {
            Ok(TimedFrame {
                time: times[i],
                image: decode(&files[i], limits).map_err(|e| {
                    ServiceError::UnreadableMedia(format!("frame {i} cannot be decoded: {e}"))
                })?,
            })
        })
        .collect::<Result<Vec<_>, ServiceError>>()?;
    let fps = options.fps.unwrap_or(DEFAULT_IMAGE_FPS);
    Ok(Intake {
        frames,
        source: SourceInfo {
            kind: "images".into(),
            frames: files.len(),
            width,
            height,
            duration: times.last().copied().unwrap_or(0.0),
            fps,
            warnings: Vec::new(),
        },
        frame_step: frame_step(&times, fps),
    })
}

/// Times of `n` image frames: the explicit timestamps (shifted to start at 0) or `i / fps`.
fn frame_times(n: usize, options: &IntakeOptions) -> Result<Vec<f64>, ServiceError> {
    match &options.timestamps {
        Some(times) if times.len() != n => Err(ServiceError::invalid(format!(
            "{} timestamps for {n} frames: give one per frame",
            times.len()
        ))),
        Some(times) => Ok(times.iter().map(|t| t - times[0]).collect()),
        None => {
            let fps = options.fps.unwrap_or(DEFAULT_IMAGE_FPS);
            Ok((0..n).map(|i| i as f64 / fps).collect())
        }
    }
}

fn is_frame_name(name: &str) -> bool {
    let base = name.rsplit('/').next().unwrap_or(name);
    let lower = base.to_ascii_lowercase();
    !base.starts_with('.')
        && !name.starts_with("__MACOSX/")
        && [".png", ".jpg", ".jpeg"]
            .iter()
            .any(|ext| lower.ends_with(ext))
}

fn unzip(data: &[u8], limits: &Limits) -> Result<Vec<Bytes>, ServiceError> {
    let mut archive = zip::ZipArchive::new(Cursor::new(data)).map_err(|e| {
        ServiceError::UnreadableMedia(format!("the zip archive cannot be read: {e}"))
    })?;
    check_frame_count(archive.len(), limits)?;
    let mut entries = Vec::new();
    let mut declared = 0u64;
    for i in 0..archive.len() {
        let entry = archive.by_index_raw(i).map_err(|e| {
            ServiceError::UnreadableMedia(format!("zip entry {i} cannot be read: {e}"))
        })?;
        let name = entry
            .name()
            .map_err(|e| {
                ServiceError::UnreadableMedia(format!("zip entry {i} has a bad name: {e}"))
            })?
            .into_owned();
        if entry.is_dir() || !is_frame_name(&name) {
            continue;
        }
        let (size, packed) = (entry.size(), entry.compressed_size());
        if size > packed.max(1).saturating_mul(MAX_INFLATION) && size > (1 << 20) {
            return Err(ServiceError::TooLarge(format!(
                "zip entry {name} inflates {packed} bytes to {size}: refused as a decompression bomb"
            )));
        }
        declared = declared.saturating_add(size);
        entries.push((name, i, size));
    }
    if declared > limits.max_archive_bytes {
        return Err(ServiceError::TooLarge(format!(
            "the archive expands to {declared} bytes; at most {} are accepted (C4G_MAX_ARCHIVE_MIB)",
            limits.max_archive_bytes
        )));
    }
    entries.sort();
    entries
        .into_iter()
        .map(|(name, i, size)| {
            let entry = archive.by_index(i).map_err(|e| {
                ServiceError::UnreadableMedia(format!("zip entry {name} cannot be read: {e}"))
            })?;
            // The declared size bounds the read, whatever the stream inside claims.
            let mut bytes = Vec::with_capacity(size.min(1 << 26) as usize);
            entry
                .take(size)
                .read_to_end(&mut bytes)
                .map_err(|e| ServiceError::UnreadableMedia(format!("zip entry {name}: {e}")))?;
            Ok(Bytes::from(bytes))
        })
        .collect()
}

fn untar(data: &[u8], limits: &Limits) -> Result<Vec<Bytes>, ServiceError> {
    let mut archive = tar::Archive::new(Cursor::new(data));
    let entries = archive.entries().map_err(|e| {
        ServiceError::UnreadableMedia(format!("the tar archive cannot be read: {e}"))
    })?;
    let mut frames = Vec::new();
    for entry in entries {
        let mut entry = entry.map_err(|e| {
            ServiceError::UnreadableMedia(format!("a tar entry cannot be read: {e}"))
        })?;
        let name = entry
            .path()
            .map(|p| p.to_string_lossy().into_owned())
            .unwrap_or_default();
        if !entry.header().entry_type().is_file() || !is_frame_name(&name) {
            continue;
        }
        check_frame_count(frames.len() + 1, limits)?;
        // A tar is not compressed: an entry's bytes are inside the (already limited) body.
        let mut bytes = Vec::new();
        entry
            .read_to_end(&mut bytes)
            .map_err(|e| ServiceError::UnreadableMedia(format!("tar entry {name}: {e}")))?;
        frames.push((name, Bytes::from(bytes)));
    }
    frames.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(frames.into_iter().map(|(_, b)| b).collect())
}

fn reader(bytes: &[u8]) -> std::io::Result<ImageReader<Cursor<&[u8]>>> {
    ImageReader::new(Cursor::new(bytes)).with_guessed_format()
}

fn dimensions(bytes: &[u8]) -> Result<(u32, u32), image::ImageError> {
    reader(bytes)?.into_dimensions()
}

fn decode(bytes: &[u8], limits: &Limits) -> Result<RgbImage, image::ImageError> {
    let mut reader = reader(bytes)?;
    let mut image_limits = image::Limits::default();
    image_limits.max_image_width = Some(limits.max_side);
    image_limits.max_image_height = Some(limits.max_side);
    image_limits.max_alloc = Some(u64::from(limits.max_side).pow(2) * 8);
    reader.limits(image_limits);
    Ok(reader.decode()?.to_rgb8())
}
