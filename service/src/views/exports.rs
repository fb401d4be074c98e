//! 4D exports: a time range of a clip's sets as one file that other viewers open.
//!
//! - [`ExportFormat::PlyZip`]: a zip of per-time 3DGS `.ply` files (Brush plays these);
//! - [`ExportFormat::SpzZip`]: a zip of per-time `.spz` files (Niantic's compressed splats);
//! - [`ExportFormat::Splatv`]: one `.splatv` for splaTV-style web players, fitted from the sets
//!   (each Gaussian a cubic path, a linear spin and one temporal opacity bump): small and smooth,
//!   but an approximation, whose measured error comes with the file.
//!
//! The sets come from the same plan as a stream ([`Service::stream`]): the times, the quality,
//! keyframes and pruning mean the same, and the answer is refused before anything is decoded
//! when the range is wrong. The file is made in memory, so its size is bounded: the zips by their
//! bytes as each set is appended, `.splatv` by the sets it is fitted from (all are needed at
//! once), both against `C4G_MAX_EXPORT_MIB`.

use std::sync::Arc;

use c4g_formats::frames_zip::{self, FrameFormat};
use c4g_formats::splatv;
use c4g_scene::{CANONICAL_CHANNELS, GaussianSet};

use crate::ServiceError;
use crate::sets::streaming::StreamRequest;
use crate::views::render::Views;

/// The files an export can be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExportFormat {
    /// A zip of per-time `.ply` files.
    PlyZip,
    /// A zip of per-time `.spz` files.
    SpzZip,
    /// One `.splatv`, fitted.
    Splatv,
}

impl ExportFormat {
    /// The file name's extension.
    pub fn extension(self) -> &'static str {
        match self {
            Self::PlyZip => "ply.zip",
            Self::SpzZip => "spz.zip",
            Self::Splatv => "splatv",
        }
    }

    /// The file's media type.
    pub fn content_type(self) -> &'static str {
        match self {
            Self::PlyZip | Self::SpzZip => "application/zip",
            Self::Splatv => "application/octet-stream",
        }
    }
}

/// Side of the square image the `.splatv` camera states, pixels: its focal length is C4G's
/// (0.8767 of the side), and players scale it to their window.
pub const SPLATV_CAMERA_SIDE: u32 = 1024;

/// A finished export.
#[derive(Debug)]
pub struct Export {
    /// The file.
    pub bytes: Vec<u8>,
    /// The times it holds (`.splatv`: those it was fitted to).
    pub times: Vec<f64>,
    /// For `.splatv`, how far the fitted file strays from the sets it was fitted to.
    pub fit: Option<splatv::FitReport>,
}

impl Views {
    /// Exports the sets `request` asks of clip `id` as one `format` file.
    pub async fn export(
        self: &Arc<Self>,
        id: &str,
        request: &StreamRequest,
        format: ExportFormat,
    ) -> Result<Export, ServiceError> {
        let mut stream = crate::sets::streaming::stream(&self.sets, id, request).await?;
        let limit = self.limits.max_export_bytes;
        let total = stream.times.len();
        if format != ExportFormat::Splatv && total > frames_zip::MAX_FRAMES {
            return Err(ServiceError::TooLarge(format!(
                "{total} frames in one zip; at most {}: use a larger step",
                frames_zip::MAX_FRAMES
            )));
        }
        match format {
            ExportFormat::PlyZip | ExportFormat::SpzZip => {
                let frame = match format {
                    ExportFormat::PlyZip => FrameFormat::Ply,
                    _ => FrameFormat::Spz,
                };
                let mut writer = frames_zip::Writer::new(frame);
                let mut times = Vec::with_capacity(total);
                while let Some(next) = stream.sets.recv().await {
                    let (time, set) = next?;
                    writer.push(time, &set).map_err(|e| {
                        ServiceError::invalid(format!(
                            "the set at {time} s cannot be exported: {e}"
                        ))
                    })?;
                    times.push(time);
                    if writer.bytes() as u64 > limit {
                        return Err(over_limit("file", limit, times.len(), total));
                    }
                }
                let bytes = writer
                    .finish()
                    .map_err(|e| ServiceError::invalid(format!("cannot finish the export: {e}")))?;
                Ok(Export {
                    bytes,
                    times,
                    fit: None,
                })
            }
            ExportFormat::Splatv => {
                let mut frames: Vec<(f64, GaussianSet)> = Vec::with_capacity(total);
                let mut held = 0u64;
                while let Some(next) = stream.sets.recv().await {
                    let (time, set) = next?;
                    held += set_bytes(&set);
                    frames.push((time, set));
                    if held > limit {
                        return Err(over_limit("sets", limit, frames.len(), total));
                    }
                }
                let times = frames.iter().map(|(t, _)| *t).collect();
                let (bytes, fit) = self
                    .work(move |_| {
                        let camera =
                            splatv::Camera::first_context(SPLATV_CAMERA_SIDE, SPLATV_CAMERA_SIDE);
                        let fitted = splatv::fit(&frames, &camera).map_err(|e| {
                            ServiceError::invalid(format!(
                                "cannot fit a .splatv to these sets: {e}"
                            ))
                        })?;
                        let report = fitted.report().cloned();
                        Ok((fitted.encode(), report))
                    })
                    .await?;
                Ok(Export { bytes, times, fit })
            }
        }
    }
}

/// Bytes a set holds in memory (its f32 columns; features are not exported).
fn set_bytes(set: &GaussianSet) -> u64 {
    (set.len() * CANONICAL_CHANNELS * 4) as u64
}

fn over_limit(what: &str, limit: u64, done: usize, total: usize) -> ServiceError {
    ServiceError::TooLarge(format!(
        "the export's {what} passed {} MiB (C4G_MAX_EXPORT_MIB) after {done} of {total} sets: \
         export fewer times (a larger step or a shorter range)",
        limit >> 20
    ))
}
