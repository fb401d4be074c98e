//! `C4GS`: the service's packed binary format for Gaussian sets over time, written by the server
//! (`docs/api.md`, format `binary`) and read by the client. One codec, so both ends agree byte for
//! byte.
//!
//! Little endian throughout:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `b"C4GS"` |
//! | 2 | `u16` version (1) |
//! | 1 | `u8` precision: 0 `f32`, 1 `f16` |
//! | 1 | `u8` reserved (0; ignored when read, so a later minor change may set it) |
//! | 4 | `u32` frames |
//! | 4 | `u32` N, Gaussians per frame |
//!
//! then per frame an `f64` time and the five columns means (N×3), scales (N×3), rotations (N×4,
//! w x y z), opacities (N), colours (N×3), each value in the precision.
//!
//! **Features** (version 2): sets with per-Gaussian feature vectors (the feature-lifting
//! decoder's) are written as version 2, which is version 1 with one field after the header and
//! one column after the colours:
//!
//! | bytes | field |
//! |---|---|
//! | 16 | the header as above, version 2 |
//! | 4 | `u32` F, floats per feature vector (at least 1) |
//!
//! then per frame the time, the five columns and the features (N×F, row i Gaussian i's vector),
//! in the precision. Sets without features are always written as version 1, byte for byte what
//! they were before version 2 existed, so a reader of version 1 reads every payload that a client
//! which never asks for features can get; one that does ask gets version 2, which a version 1
//! reader refuses by its version (not by a length it cannot explain). This reader reads both.
//!
//! The same columns, packed the same way, are the arrays of the gRPC `GaussianSet` message, so
//! [`pack_columns`] and [`unpack_columns`] serve both.
//!
//! The reader checks every length against the header (with checked arithmetic) before it
//! allocates anything, so a truncated or hostile payload is a
//! [`SceneError::Format`] that says what is short, never a panic or a huge allocation.
//! `f32` round-trips exactly; `f16` rounds each value to the nearest half (relative error at most
//! 2⁻¹¹) and saturates values beyond its range at ±65504, so every finite set stays finite.

use std::fmt;
use std::str::FromStr;

use half::f16;
use serde::{Deserialize, Serialize};

use c4g_scene::{FeatureBlock, GaussianSet, SceneError};

/// The first four bytes.
pub const MAGIC: [u8; 4] = *b"C4GS";
/// The version of payloads without features: what this codec writes for sets without them.
pub const VERSION: u16 = 1;
/// The version of payloads with features (a feature width after the header, a feature column
/// after the colours).
pub const VERSION_FEATURES: u16 = 2;
/// Bytes before the first frame (version 1; version 2 has [`FEATURE_WIDTH_BYTES`] more).
pub const HEADER_BYTES: usize = 16;
/// Bytes of version 2's feature width, after the header.
pub const FEATURE_WIDTH_BYTES: usize = 4;
/// Bytes of a frame's time.
const TIME_BYTES: usize = 8;

/// The columns in payload order, with their values per Gaussian.
pub const COLUMNS: [(&str, usize); 5] = [
    ("means", 3),
    ("scales", 3),
    ("rotations", 4),
    ("opacities", 1),
    ("colors", 3),
];
/// Values per Gaussian over all columns.
const VALUES_PER_GAUSSIAN: usize = 14;

/// Float width of the packed values. Half precision halves the bytes at about three significant
/// digits, plenty for viewing; values unpack to `f32` either way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// 32-bit floats.
    #[default]
    F32,
    /// 16-bit (IEEE half) floats.
    F16,
}

impl Precision {
    /// The API's name (`f32`, `f16`).
    pub fn as_str(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        }
    }

    /// Bytes per value.
    pub fn value_bytes(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F16 => 2,
        }
    }

    /// The header's precision byte.
    fn code(self) -> u8 {
        match self {
            Precision::F32 => 0,
            Precision::F16 => 1,
        }
    }

    fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Precision::F32),
            1 => Some(Precision::F16),
            _ => None,
        }
    }

    fn push(self, out: &mut Vec<u8>, values: impl Iterator<Item = f32>) {
        match self {
            Precision::F32 => values.for_each(|v| out.extend_from_slice(&v.to_le_bytes())),
            Precision::F16 => values.for_each(|v| out.extend_from_slice(&to_f16(v).to_le_bytes())),
        }
    }

    /// The value at the start of `bytes` (at least `value_bytes` long), widened to `f32`.
    fn read(self, bytes: &[u8]) -> f32 {
        match self {
            Precision::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
            Precision::F16 => f16::from_le_bytes([bytes[0], bytes[1]]).to_f32(),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Precision {
    type Err = SceneError;

    fn from_str(s: &str) -> Result<Self, SceneError> {
        match s {
            "f32" => Ok(Precision::F32),
            "f16" => Ok(Precision::F16),
            other => Err(format_error(format!(
                "unknown precision {other:?} (f32 or f16)"
            ))),
        }
    }
}

/// The `C4GS` bytes of `frames` (time in seconds, set). N is the first set's length; version 2
/// (with a feature column) when the first set has features, else version 1.
///
/// Fails when the sets differ in length or in their features' presence or width, or when there
/// are more than `u32::MAX` frames, Gaussians or feature channels: the header could not describe
/// the payload. (The frames of one clip always share N.)
pub fn encode<'a>(
    frames: impl IntoIterator<Item = (f64, &'a GaussianSet)>,
    precision: Precision,
) -> Result<Vec<u8>, SceneError> {
    let mut frames = frames.into_iter().peekable();
    let width = frames
        .peek()
        .and_then(|(_, set)| set.features().map(|f| f.width()));
    let header_bytes = HEADER_BYTES + width.map_or(0, |_| FEATURE_WIDTH_BYTES);
    let mut out = Vec::with_capacity(header_bytes);
    out.extend_from_slice(&MAGIC);
    let version = if width.is_some() {
        VERSION_FEATURES
    } else {
        VERSION
    };
    out.extend_from_slice(&version.to_le_bytes());
    out.push(precision.code());
    out.push(0);
    // Frames and N, known once the frames are seen.
    out.extend_from_slice(&[0; 8]);
    if let Some(width) = width {
        let width = u32::try_from(width).map_err(|_| {
            format_error(format!(
                "C4GS holds at most u32::MAX feature channels; got {width}"
            ))
        })?;
        out.extend_from_slice(&width.to_le_bytes());
    }
    let (mut written, mut count) = (0usize, None);
    for (time, set) in frames {
        let n = *count.get_or_insert(set.len());
        if set.len() != n {
            return Err(format_error(format!(
                "frame {written} holds {} Gaussians; the first holds {n}: one C4GS payload holds \
                 sets of one size",
                set.len()
            )));
        }
        let features = set.features();
        if features.map(|f| f.width()) != width {
            return Err(format_error(format!(
                "frame {written} has features of width {:?}; the first has {width:?}: one C4GS \
                 payload holds sets with features of one width, or none",
                features.map(|f| f.width())
            )));
        }
        let values = VALUES_PER_GAUSSIAN + width.unwrap_or(0);
        out.reserve(TIME_BYTES + n * values * precision.value_bytes());
        out.extend_from_slice(&time.to_le_bytes());
        push_columns(&mut out, set, precision);
        if let Some(block) = features {
            precision.push(&mut out, block.values().iter().copied());
        }
        written += 1;
    }
    let header_u32 = |n: usize, what: &str| {
        u32::try_from(n)
            .map_err(|_| format_error(format!("C4GS holds at most u32::MAX {what}; got {n}")))
    };
    out[8..12].copy_from_slice(&header_u32(written, "frames")?.to_le_bytes());
    out[12..16].copy_from_slice(&header_u32(count.unwrap_or(0), "Gaussians")?.to_le_bytes());
    Ok(out)
}

/// Parses `C4GS` bytes into their frames (time in seconds, set).
pub fn decode(bytes: &[u8]) -> Result<Vec<(f64, GaussianSet)>, SceneError> {
    let header = bytes.get(..HEADER_BYTES).ok_or_else(|| {
        format_error(format!(
            "a C4GS payload starts with a {HEADER_BYTES}-byte header; got {} bytes",
            bytes.len()
        ))
    })?;
    if header[..4] != MAGIC {
        return Err(format_error(format!(
            "not a C4GS payload (starts with {:?})",
            &header[..4]
        )));
    }
    let version = u16::from_le_bytes([header[4], header[5]]);
    if version != VERSION && version != VERSION_FEATURES {
        return Err(format_error(format!(
            "C4GS version {version}; this reader reads versions {VERSION} and {VERSION_FEATURES}"
        )));
    }
    let precision = Precision::from_code(header[6])
        .ok_or_else(|| format_error(format!("unknown C4GS precision code {}", header[6])))?;
    // header[7] is reserved.
    let frames = u32::from_le_bytes([header[8], header[9], header[10], header[11]]) as usize;
    let count = u32::from_le_bytes([header[12], header[13], header[14], header[15]]) as usize;
    let (width, header_bytes) = if version == VERSION_FEATURES {
        let field = bytes
            .get(HEADER_BYTES..HEADER_BYTES + FEATURE_WIDTH_BYTES)
            .ok_or_else(|| {
                format_error(format!(
                    "a C4GS version 2 payload has its feature width after the header; got {} \
                     bytes",
                    bytes.len()
                ))
            })?;
        let width = u32::from_le_bytes([field[0], field[1], field[2], field[3]]) as usize;
        if width == 0 {
            return Err(format_error(
                "a C4GS version 2 payload's feature width is at least 1; got 0".to_owned(),
            ));
        }
        (width, HEADER_BYTES + FEATURE_WIDTH_BYTES)
    } else {
        (0, HEADER_BYTES)
    };

    let frame_bytes = width
        .checked_add(VALUES_PER_GAUSSIAN)
        .and_then(|values| values.checked_mul(precision.value_bytes()))
        .and_then(|b| b.checked_mul(count))
        .and_then(|b| b.checked_add(TIME_BYTES));
    let expected = frame_bytes
        .and_then(|b| b.checked_mul(frames))
        .and_then(|b| b.checked_add(header_bytes));
    let (Some(frame_bytes), Some(expected)) = (frame_bytes, expected) else {
        return Err(format_error(format!(
            "C4GS header claims {frames} frames of {count} Gaussians: too large"
        )));
    };
    if bytes.len() != expected {
        let with = if width > 0 {
            format!(" with {width} feature channels")
        } else {
            String::new()
        };
        return Err(format_error(format!(
            "C4GS payload of {frames} frames of {count} {precision} Gaussians{with} needs \
             {expected} bytes; got {}",
            bytes.len()
        )));
    }

    // The length matched, so every allocation below is bounded by the payload's size.
    let mut out = Vec::with_capacity(frames);
    for frame in bytes[header_bytes..].chunks_exact(frame_bytes) {
        let (time, mut rest) = frame.split_at(TIME_BYTES);
        let mut time_bytes = [0; TIME_BYTES];
        time_bytes.copy_from_slice(time);
        let columns = COLUMNS.map(|(_, width)| {
            let (column, tail) = rest.split_at(count * width * precision.value_bytes());
            rest = tail;
            column
        });
        let mut set = unpack_columns(count, precision, columns)?;
        if width > 0 {
            let values = rest
                .chunks_exact(precision.value_bytes())
                .map(|v| precision.read(v))
                .collect();
            set = set.with_features(FeatureBlock::new(width, values)?)?;
        }
        out.push((f64::from_le_bytes(time_bytes), set));
    }
    Ok(out)
}

/// The largest finite half.
const F16_MAX: f32 = 65504.0;

/// `v` as a half, saturating at ±65504: a set is finite (it is validated when decoded), and a
/// value past half's range (a huge scale, a far position) must not become infinite on the wire,
/// where the reader would refuse the set. Values below half's smallest subnormal (2⁻²⁴) round to
/// zero, which keeps scales non-negative and so valid.
fn to_f16(v: f32) -> f16 {
    f16::from_f32(v.clamp(-F16_MAX, F16_MAX))
}

/// The five columns of `set` (means, scales, rotations, opacities, colours), each packed
/// little endian in `precision`: the arrays of the proto `GaussianSet`.
pub fn pack_columns(set: &GaussianSet, precision: Precision) -> [Vec<u8>; 5] {
    let n = set.len();
    let column = |width: usize, values: &mut dyn Iterator<Item = f32>| {
        let mut out = Vec::with_capacity(n * width * precision.value_bytes());
        precision.push(&mut out, values);
        out
    };
    [
        column(3, &mut set.positions().iter().flatten().copied()),
        column(3, &mut set.scales().iter().flatten().copied()),
        column(4, &mut set.rotations().iter().flatten().copied()),
        column(1, &mut set.opacities().iter().copied()),
        column(3, &mut set.colors().iter().flatten().copied()),
    ]
}

/// `values` packed little endian in `precision`, as a column is (the proto's feature vectors).
pub fn pack_values(values: &[f32], precision: Precision) -> Vec<u8> {
    let mut out = Vec::with_capacity(values.len() * precision.value_bytes());
    precision.push(&mut out, values.iter().copied());
    out
}

/// Values packed by [`pack_values`], widened to `f32`; `None` when the bytes are not a whole
/// number of values.
pub fn unpack_values(bytes: &[u8], precision: Precision) -> Option<Vec<f32>> {
    let size = precision.value_bytes();
    bytes.len().is_multiple_of(size).then(|| {
        bytes
            .chunks_exact(size)
            .map(|v| precision.read(v))
            .collect()
    })
}

/// Appends the five columns of `set` to `out`, as [`pack_columns`] packs them.
fn push_columns(out: &mut Vec<u8>, set: &GaussianSet, precision: Precision) {
    precision.push(out, set.positions().iter().flatten().copied());
    precision.push(out, set.scales().iter().flatten().copied());
    precision.push(out, set.rotations().iter().flatten().copied());
    precision.push(out, set.opacities().iter().copied());
    precision.push(out, set.colors().iter().flatten().copied());
}

/// The set of `count` Gaussians in five packed columns (means, scales, rotations, opacities,
/// colours, as [`pack_columns`] writes them). Each column's length is checked against `count`
/// first; the error names the column that is off. Values are taken as they are (no
/// [`GaussianSet::validate`]).
pub fn unpack_columns(
    count: usize,
    precision: Precision,
    columns: [&[u8]; 5],
) -> Result<GaussianSet, SceneError> {
    for ((name, width), column) in COLUMNS.iter().zip(columns) {
        let expected = count
            .checked_mul(width * precision.value_bytes())
            .ok_or_else(|| format_error(format!("{count} Gaussians are too many")))?;
        if column.len() != expected {
            return Err(format_error(format!(
                "{name} of {count} {precision} Gaussians needs {expected} bytes; got {}",
                column.len()
            )));
        }
    }
    let [means, scales, rotations, opacities, colors] = columns;
    GaussianSet::new(
        rows::<3>(means, precision),
        rows::<3>(scales, precision),
        rows::<4>(rotations, precision),
        rows::<1>(opacities, precision)
            .into_iter()
            .map(|[o]| o)
            .collect(),
        rows::<3>(colors, precision),
    )
}

/// Rows of `K` values, widened to `f32`, from a column whose length the caller has checked.
fn rows<const K: usize>(bytes: &[u8], precision: Precision) -> Vec<[f32; K]> {
    let size = precision.value_bytes();
    bytes
        .chunks_exact(K * size)
        .map(|row| std::array::from_fn(|i| precision.read(&row[i * size..])))
        .collect()
}

fn format_error(reason: String) -> SceneError {
    SceneError::Format {
        format: "c4gs",
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use c4g_scene::Gaussian;
    use glam::{Quat, Vec3};

    fn set() -> GaussianSet {
        GaussianSet::from_gaussians([Gaussian {
            position: Vec3::new(1.0, -2.0, 3.5),
            scale: Vec3::new(0.1, 0.2, 0.3),
            rotation: Quat::IDENTITY,
            opacity: 0.75,
            color: Vec3::new(0.25, 0.5, 1.0),
        }])
    }

    #[test]
    fn binary_layout_is_as_documented() {
        let set = set();
        let bytes = encode([(0.5, &set)], Precision::F32).unwrap();
        assert_eq!(&bytes[..4], b"C4GS");
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 1);
        assert_eq!((bytes[6], bytes[7]), (0, 0));
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 1);
        assert_eq!(u32::from_le_bytes(bytes[12..16].try_into().unwrap()), 1);
        assert_eq!(f64::from_le_bytes(bytes[16..24].try_into().unwrap()), 0.5);
        let floats: Vec<f32> = bytes[24..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(
            floats,
            [
                1.0, -2.0, 3.5, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0, 0.75, 0.25, 0.5, 1.0
            ]
        );
        let half = encode([(0.5, &set)], Precision::F16).unwrap();
        assert_eq!(half.len(), 24 + 14 * 2);
        assert_eq!(half[6], 1);
    }

    #[test]
    fn packed_columns_are_the_payload_after_the_time() {
        let set = set();
        for precision in [Precision::F32, Precision::F16] {
            let bytes = encode([(0.5, &set)], precision).unwrap();
            assert_eq!(pack_columns(&set, precision).concat(), &bytes[24..]);
        }
    }

    #[test]
    fn the_reserved_byte_is_ignored_and_other_versions_are_refused() {
        let set = set();
        let mut bytes = encode([(0.5, &set)], Precision::F32).unwrap();
        bytes[7] = 9;
        assert_eq!(decode(&bytes).unwrap(), [(0.5, set)]);
        bytes[4] = 3;
        let err = decode(&bytes).unwrap_err().to_string();
        assert!(err.contains("version 3"), "{err}");
    }

    #[test]
    fn frames_of_different_lengths_cannot_be_written() {
        let one = set();
        let two = GaussianSet::from_gaussians(one.iter().chain(one.iter()));
        let err = encode([(0.0, &one), (1.0, &two)], Precision::F32).unwrap_err();
        assert!(
            err.to_string()
                .contains("frame 1 holds 2 Gaussians; the first holds 1"),
            "{err}"
        );
    }

    #[test]
    fn half_precision_saturates_instead_of_overflowing_and_stays_valid() {
        let huge = GaussianSet::from_gaussians([Gaussian {
            position: Vec3::new(1e6, -1e9, 3.0),
            scale: Vec3::new(1e5, 1e-9, 0.5),
            rotation: Quat::IDENTITY,
            opacity: 1.0,
            color: Vec3::new(0.0, 0.5, 1.0),
        }]);
        huge.validate().unwrap();
        let bytes = encode([(0.0, &huge)], Precision::F16).unwrap();
        let (_, back) = decode(&bytes).unwrap().remove(0);
        back.validate().unwrap();
        assert_eq!(back.positions()[0], [65504.0, -65504.0, 3.0]);
        assert_eq!(back.scales()[0], [65504.0, 0.0, 0.5]);
    }

    #[test]
    fn features_make_version_2_with_a_width_and_a_column_after_the_colours() {
        let plain = set();
        let with = plain
            .clone()
            .with_features(FeatureBlock::new(2, vec![0.5, -1.5]).unwrap())
            .unwrap();
        let bytes = encode([(0.5, &with), (0.75, &with)], Precision::F32).unwrap();
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 2);
        assert_eq!(u32::from_le_bytes(bytes[16..20].try_into().unwrap()), 2);
        assert_eq!(f64::from_le_bytes(bytes[20..28].try_into().unwrap()), 0.5);
        // The five columns as version 1 has them, then the features.
        assert_eq!(
            &bytes[28..28 + 14 * 4],
            &encode([(0.5, &plain)], Precision::F32).unwrap()[24..]
        );
        let tail: Vec<f32> = bytes[28 + 14 * 4..28 + 16 * 4]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(tail, [0.5, -1.5]);
        assert_eq!(bytes.len(), 20 + 2 * (8 + 16 * 4));
        assert_eq!(
            decode(&bytes).unwrap(),
            [(0.5, with.clone()), (0.75, with.clone())]
        );
        let half = decode(&encode([(0.0, &with)], Precision::F16).unwrap()).unwrap();
        assert_eq!(half[0].1.features(), with.features());
        // Without features: version 1, byte for byte.
        assert_eq!(encode([(0.5, &plain)], Precision::F32).unwrap()[4], 1);
        // Mixed sets cannot share a payload, and a truncated one says what it needed.
        assert!(encode([(0.0, &with), (1.0, &plain)], Precision::F32).is_err());
        assert!(encode([(0.0, &plain), (1.0, &with)], Precision::F32).is_err());
        let err = decode(&bytes[..bytes.len() - 1]).unwrap_err().to_string();
        assert!(err.contains("with 2 feature channels"), "{err}");
        assert!(decode(&bytes[..18]).is_err());
        let mut zero = bytes.clone();
        zero[16..20].copy_from_slice(&0u32.to_le_bytes());
        assert!(decode(&zero).is_err());
    }

    #[test]
    fn precision_names_are_the_apis() {
        for precision in [Precision::F32, Precision::F16] {
            assert_eq!(precision.to_string().parse::<Precision>(), Ok(precision));
            let json = serde_json::to_string(&precision).unwrap();
            assert_eq!(json, format!("\"{precision}\""));
        }
        assert!("f64".parse::<Precision>().is_err());
    }
}
