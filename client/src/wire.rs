//! Gaussian payloads as they travel: the REST API's `C4GS` binary format and the proto's
//! `GaussianSet` of packed arrays. Both are little-endian columns (means, scales, rotations,
//! opacities, colours) of `f32` or `f16`, so both parse through the same column reader.
//!
//! The `C4GS` layout (`docs/api.md`):
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `b"C4GS"` |
//! | 2 | `u16` version (1) |
//! | 1 | `u8` precision: 0 `f32`, 1 `f16` |
//! | 1 | `u8` reserved (0) |
//! | 4 | `u32` frames |
//! | 4 | `u32` N, Gaussians per frame |
//!
//! then per frame an `f64` time and the arrays means (N×3), scales (N×3), rotations (N×4,
//! w x y z), opacities (N), colours (N×3), each value in the precision.
//!
//! Parsers check every length against the header before reading, so a truncated or hostile
//! payload is an [`Error::Malformed`] that says what is short, never a panic or a huge allocation.

use c4g_proto::v1 as proto;
use c4g_renderer::GaussianSet;
use half::f16;

use crate::{Error, GaussianFrame, Precision};

/// The binary format's first four bytes.
pub const BINARY_MAGIC: [u8; 4] = *b"C4GS";
/// The binary format version this client reads.
pub const BINARY_VERSION: u16 = 1;
/// The binary format's media type.
pub const BINARY_CONTENT_TYPE: &str = "application/x-c4g-gaussians";
/// Bytes before the first frame.
pub const BINARY_HEADER_BYTES: usize = 16;

/// Values per Gaussian in each column, in payload order.
const COLUMNS: [(&str, usize); 5] = [
    ("means", 3),
    ("scales", 3),
    ("rotations", 4),
    ("opacities", 1),
    ("colors", 3),
];
/// Values per Gaussian over all columns.
const VALUES_PER_GAUSSIAN: usize = 14;

/// Parses a `C4GS` payload into its frames.
pub fn parse_binary(bytes: &[u8]) -> Result<Vec<GaussianFrame>, Error> {
    let header = bytes.get(..BINARY_HEADER_BYTES).ok_or_else(|| {
        malformed(format!(
            "a C4GS payload starts with a {BINARY_HEADER_BYTES}-byte header; got {} bytes",
            bytes.len()
        ))
    })?;
    if header[..4] != BINARY_MAGIC {
        return Err(malformed(format!(
            "not a C4GS payload (starts with {:?})",
            &header[..4]
        )));
    }
    let version = u16::from_le_bytes([header[4], header[5]]);
    if version != BINARY_VERSION {
        return Err(malformed(format!(
            "C4GS version {version}; this client reads version {BINARY_VERSION}"
        )));
    }
    let precision = match header[6] {
        0 => Precision::F32,
        1 => Precision::F16,
        other => return Err(malformed(format!("unknown C4GS precision code {other}"))),
    };
    // header[7] is reserved: a later minor change may set it without changing the layout.
    let frames = u32::from_le_bytes([header[8], header[9], header[10], header[11]]) as usize;
    let count = u32::from_le_bytes([header[12], header[13], header[14], header[15]]) as usize;

    let frame_bytes = count
        .checked_mul(VALUES_PER_GAUSSIAN * precision.value_bytes())
        .and_then(|b| b.checked_add(8));
    let expected = frame_bytes
        .and_then(|b| b.checked_mul(frames))
        .and_then(|b| b.checked_add(BINARY_HEADER_BYTES));
    let (Some(frame_bytes), Some(expected)) = (frame_bytes, expected) else {
        return Err(malformed(format!(
            "C4GS header claims {frames} frames of {count} Gaussians: too large"
        )));
    };
    if bytes.len() != expected {
        return Err(malformed(format!(
            "C4GS payload of {frames} frames of {count} {precision} Gaussians needs {expected} \
             bytes; got {}",
            bytes.len()
        )));
    }

    bytes[BINARY_HEADER_BYTES..]
        .chunks_exact(frame_bytes)
        .map(|frame| {
            let (time, arrays) = frame.split_at(8);
            let mut time_bytes = [0; 8];
            time_bytes.copy_from_slice(time);
            let time = f64::from_le_bytes(time_bytes);
            let mut offset = 0;
            let columns = COLUMNS.map(|(_, width)| {
                let len = count * width * precision.value_bytes();
                let column = &arrays[offset..offset + len];
                offset += len;
                column
            });
            Ok(GaussianFrame {
                time,
                gaussians: set_from_columns(count, precision, columns)?,
            })
        })
        .collect()
}

/// Unpacks a proto `GaussianSet` (packed little-endian arrays of its `precision`).
pub fn unpack_set(set: &proto::GaussianSet) -> Result<GaussianSet, Error> {
    let precision = match proto::Precision::try_from(set.precision) {
        Ok(proto::Precision::Unspecified | proto::Precision::F32) => Precision::F32,
        Ok(proto::Precision::F16) => Precision::F16,
        Err(_) => {
            return Err(malformed(format!(
                "unknown proto precision {}",
                set.precision
            )));
        }
    };
    let count = set.count as usize;
    let columns = [
        &set.means[..],
        &set.scales[..],
        &set.rotations[..],
        &set.opacities[..],
        &set.colors[..],
    ];
    for ((name, width), column) in COLUMNS.iter().zip(columns) {
        let expected = count
            .checked_mul(width * precision.value_bytes())
            .ok_or_else(|| malformed(format!("GaussianSet count {count} is too large")))?;
        if column.len() != expected {
            return Err(malformed(format!(
                "GaussianSet.{name} of {count} {precision} Gaussians needs {expected} bytes; \
                 got {}",
                column.len()
            )));
        }
    }
    set_from_columns(count, precision, columns)
}

/// Unpacks a proto `GaussianFrame`; a frame without a set is malformed (the server always sends
/// one, even for zero Gaussians).
pub fn unpack_frame(frame: &proto::GaussianFrame) -> Result<GaussianFrame, Error> {
    let set = frame.gaussians.as_ref().ok_or_else(|| {
        malformed(format!(
            "GaussianFrame at t={} has no Gaussians",
            frame.time
        ))
    })?;
    Ok(GaussianFrame {
        time: frame.time,
        gaussians: unpack_set(set)?,
    })
}

/// Builds a set from its five columns, whose lengths the caller has checked.
fn set_from_columns(
    count: usize,
    precision: Precision,
    [means, scales, rotations, opacities, colors]: [&[u8]; 5],
) -> Result<GaussianSet, Error> {
    let set = GaussianSet::new(
        rows::<3>(&floats(means, precision)),
        rows::<3>(&floats(scales, precision)),
        rows::<4>(&floats(rotations, precision)),
        floats(opacities, precision),
        rows::<3>(&floats(colors, precision)),
    )
    .map_err(|e| malformed(e.to_string()))?;
    debug_assert_eq!(set.len(), count);
    Ok(set)
}

/// Little-endian values of `precision`, widened to `f32`.
fn floats(bytes: &[u8], precision: Precision) -> Vec<f32> {
    match precision {
        Precision::F32 => bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect(),
        Precision::F16 => bytes
            .chunks_exact(2)
            .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect(),
    }
}

fn rows<const K: usize>(values: &[f32]) -> Vec<[f32; K]> {
    values
        .chunks_exact(K)
        .map(|row| std::array::from_fn(|i| row[i]))
        .collect()
}

fn malformed(message: String) -> Error {
    Error::Malformed(message)
}
