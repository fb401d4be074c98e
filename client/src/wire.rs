//! Gaussian payloads as they travel: the REST API's `C4GS` binary format and the proto's
//! `GaussianSet` of packed arrays. Both are little-endian columns (means, scales, rotations,
//! opacities, colours) of `f32` or `f16`; both parse through the renderer's [`c4gs`] codec, the
//! one the server writes with (its module doc has the layout; `docs/api.md` the contract).
//!
//! The codec checks every length against the header before reading, so a truncated or hostile
//! payload is an [`Error::Malformed`] that says what is short, never a panic or a huge allocation.

use c4g_formats::c4gs;
use c4g_proto::v1 as proto;
use c4g_scene::{GaussianSet, SceneError};

use crate::{Error, GaussianFrame, Precision};

pub use c4gs::{
    HEADER_BYTES as BINARY_HEADER_BYTES, MAGIC as BINARY_MAGIC, VERSION as BINARY_VERSION,
};

/// The binary format's media type.
pub const BINARY_CONTENT_TYPE: &str = "application/x-c4g-gaussians";

/// Parses a `C4GS` payload into its frames.
pub fn parse_binary(bytes: &[u8]) -> Result<Vec<GaussianFrame>, Error> {
    let frames = c4gs::decode(bytes).map_err(|e| malformed("", e))?;
    Ok(frames
        .into_iter()
        .map(|(time, gaussians)| GaussianFrame { time, gaussians })
        .collect())
}

/// Unpacks a proto `GaussianSet` (packed little-endian arrays of its `precision`).
pub fn unpack_set(set: &proto::GaussianSet) -> Result<GaussianSet, Error> {
    let precision = match proto::Precision::try_from(set.precision) {
        Ok(proto::Precision::Unspecified | proto::Precision::F32) => Precision::F32,
        Ok(proto::Precision::F16) => Precision::F16,
        Err(_) => {
            return Err(Error::Malformed(format!(
                "unknown proto precision {}",
                set.precision
            )));
        }
    };
    let columns = [
        &set.means[..],
        &set.scales[..],
        &set.rotations[..],
        &set.opacities[..],
        &set.colors[..],
    ];
    c4gs::unpack_columns(set.count as usize, precision, columns)
        .map_err(|e| malformed("GaussianSet.", e))
}

/// Unpacks a proto `GaussianFrame`; a frame without a set is malformed (the server always sends
/// one, even for zero Gaussians).
pub fn unpack_frame(frame: &proto::GaussianFrame) -> Result<GaussianFrame, Error> {
    let set = frame.gaussians.as_ref().ok_or_else(|| {
        Error::Malformed(format!(
            "GaussianFrame at t={} has no Gaussians",
            frame.time
        ))
    })?;
    Ok(GaussianFrame {
        time: frame.time,
        gaussians: unpack_set(set)?,
    })
}

/// The proto enum's value of a precision (`PRECISION_F32`, `PRECISION_F16`).
pub fn proto_precision(precision: Precision) -> proto::Precision {
    match precision {
        Precision::F32 => proto::Precision::F32,
        Precision::F16 => proto::Precision::F16,
    }
}

/// The codec's reason (which says what is short) as a malformed answer, after `context`.
fn malformed(context: &str, e: SceneError) -> Error {
    match e {
        SceneError::Format { reason, .. } => Error::Malformed(format!("{context}{reason}")),
        other => Error::Malformed(format!("{context}{other}")),
    }
}
