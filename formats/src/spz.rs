//! Niantic's SPZ, version 4: the compressed splat format of Niantic's reference library
//! (`nianticlabs/spz`, also published as the WebAssembly package `@adobe/spz`), for the viewers
//! and tools that read it. About 20 bytes a Gaussian before compression.
//!
//! # Layout (what [`encode`] writes)
//! Little endian throughout. One file holds one set: a 32-byte header, a table of contents, then
//! one zstd frame per attribute stream.
//!
//! | offset | bytes | field |
//! |---|---|---|
//! | 0 | 4 | `u32` magic `0x5053474e` (`NGSP` in file order) |
//! | 4 | 4 | `u32` version: 4 |
//! | 8 | 4 | `u32` N, the number of Gaussians |
//! | 12 | 1 | `u8` spherical-harmonic degree: 0 |
//! | 13 | 1 | `u8` F, fractional bits of the positions (below) |
//! | 14 | 1 | `u8` flags: 0 (not trained with antialiasing, no extension records) |
//! | 15 | 1 | `u8` streams: 5 |
//! | 16 | 4 | `u32` offset of the table of contents: 32 (no extension records before it) |
//! | 20 | 12 | reserved: zeros |
//! | 32 | 5 × 16 | per stream `u64` compressed size, `u64` size once decompressed |
//! | 112 | … | the five streams, each one zstd frame, in this order |
//!
//! Each stream holds its attribute for every Gaussian, in the set's order (bytes clamped to
//! 0..=255):
//! 1. positions, 9N bytes: per Gaussian x, y, z, each a 24-bit two's complement integer
//!    `round(v · 2^F)`;
//! 2. alphas, N bytes: `round(255 · opacity)`;
//! 3. colours, 3N bytes: `round(255 · (0.15 · f_dc + 0.5))` with the degree-0 coefficient
//!    `f_dc = (rgb − 0.5) / C0` ([`SH_C0`]);
//! 4. scales, 3N bytes: `round(16 · (ln s + 10))`;
//! 5. rotations, 4N bytes: per Gaussian a `u32`, the "smallest three" of the unit quaternion in
//!    the file's `x, y, z, w` order: bits 30–31 hold the index of the component of largest
//!    magnitude (the first of equals), negated to be positive if it is not (`q` and `−q` are the
//!    same rotation), which is then implied by the norm; the other three follow in index order,
//!    10 bits each, the first in bits 20–29: a sign bit (set when negative), then the magnitude
//!    `round(511 · |c| / √½)` in 9 bits (no other component can exceed √½).
//!
//! Degree 0 has no spherical-harmonic stream: five streams, as the reference library writes. The
//! streams are compressed independently (in parallel), at zstd's default level.
//!
//! # Coordinates
//! SPZ stores RUB axes (x right, y up, z back); our sets are in OpenCV axes (x right, y down, z
//! forward). The conversion flips y and z: positions become `(x, −y, −z)` and quaternions
//! `(w, x, −y, −z)` (a rotation by π about x, which leaves degree-0 colour alone). [`decode`]
//! converts back, so a reader that asks the reference library for RDF gets our values.
//!
//! # Fractional bits
//! F is the largest value in 0..=[`MAX_FRACTIONAL_BITS`] at which every coordinate of the set
//! fits in 24 signed bits, so small scenes get finer positions: about 23 − log2 of the largest
//! magnitude, i.e. 20 for coordinates below 8, 12 below 2048 (what the reference library always
//! writes, wrapping larger coordinates around), 0 up to 8388607. Beyond 20 bits would buy
//! nothing: the step 2^−20 ≈ 1e-6 is already far below the smallest scale SPZ stores,
//! e^−10 ≈ 4.5e-5. A set with a coordinate beyond ±2^23 cannot be written. Each file chooses its
//! own F: the sets of a 4D export can differ.
//!
//! # Errors
//! Through [`encode`] and [`decode`] each value comes back within (constants below):
//! - position: 2^−(F+1) per coordinate (4.8e-7 below 8, 1.2e-4 below 2048);
//! - opacity: 1/510 ([`OPACITY_ERROR`]);
//! - colour: [`COLOR_ERROR`] ≈ 0.0037 per channel, for rgb within `0.5 ± C0 / 0.3`, i.e.
//!   −0.44..=1.44; beyond, clamped to those ends;
//! - scale: a factor `e^(1/32)`, 3.2 % ([`LOG_SCALE_ERROR`] on `ln s`), for scales within
//!   `e^−10 ≈ 4.5e-5` to `e^5.94 ≈ 379`; beyond (zero included), clamped to those ends;
//! - rotation: [`ROTATION_ERROR`] radians (the angle of the rotation between the two), the
//!   decoded quaternion normalised.
//!
//! # Left out
//! Features (SPZ has no place for them), spherical-harmonic degrees above 0, the antialiasing
//! flag and extension records. A Gaussian with a non-finite value, a negative scale or a zero
//! rotation is refused with an error naming it rather than dropped, so that the sets of a 4D
//! export keep their Gaussians' identity; opacities outside \[0, 1\] are clamped. The reference
//! library refuses to load a file of no Gaussians; [`encode`] still writes one (five empty
//! streams) and [`decode`] reads it.
//!
//! # Reading
//! [`decode`] reads version 4 only (versions 1 to 3 are gzip-compressed and refused as such): any
//! F up to 23, SH degrees 0 to 4 (coefficients beyond degree 0 skipped, their stream not even
//! decompressed), extension records skipped through the TOC offset, any flags, streams after the
//! ones it expects skipped. Every size is checked before anything is allocated: each stream must
//! lie within the file, its size once decompressed must be what N implies and it is decompressed
//! no further than that. Bytes after the last stream are refused.

use std::io::Read;
use std::path::Path;

use rayon::prelude::*;

use super::ply::SH_C0;
use c4g_scene::{GaussianSet, SceneError};

/// The header's first four bytes, `NGSP` in file order.
pub const MAGIC: u32 = 0x5053_474e;
/// The version written and read.
pub const VERSION: u32 = 4;
/// Bytes of the plaintext header.
pub const HEADER_LEN: usize = 32;
/// The most fractional bits [`encode`] gives positions.
pub const MAX_FRACTIONAL_BITS: u8 = 20;
/// Largest opacity error of a round trip.
pub const OPACITY_ERROR: f32 = 1.0 / 510.0;
/// Largest colour error of a round trip (per channel, within the range): half a step of
/// `C0 / (0.15 · 255)`.
pub const COLOR_ERROR: f32 = (SH_C0 / (COLOR_SCALE * 255.0) / 2.0) as f32;
/// Largest error of `ln(scale)` in a round trip (within the range): half a step of 1/16.
pub const LOG_SCALE_ERROR: f32 = 1.0 / 32.0;
/// Largest rotation error of a round trip, in radians. The three stored components are each
/// within ε = √½ / 1022 (half a step), and the implied one, at least ½, moves by at most 3ε, so
/// the unit quaternion moves by at most √12 · ε and the rotation by twice that: 0.00479.
pub const ROTATION_ERROR: f32 = 0.0048;

/// Bytes of one entry of the table of contents.
const TOC_ENTRY: usize = 16;
/// The most fractional bits a 24-bit signed coordinate can have.
const MAX_READ_FRACTIONAL_BITS: u8 = 23;
/// The range of a 24-bit two's complement integer.
const FIXED_MIN: f64 = -8_388_608.0;
const FIXED_MAX: f64 = 8_388_607.0;
/// Colour bytes hold `0.15 · f_dc + 0.5`.
const COLOR_SCALE: f64 = 0.15;
/// Scale bytes hold `16 · (ln s + 10)`.
const LOG_SCALE_OFFSET: f64 = 10.0;
const LOG_SCALE_STEPS: f64 = 16.0;
/// The magnitude of a stored rotation component, 9 bits, for `|c| = √½`.
const ROTATION_STEPS: f64 = 511.0;
/// The highest SH degree of the format.
const MAX_SH_DEGREE: u8 = 4;
/// The attribute streams of every file, in file order, with their bytes per Gaussian. A file of
/// SH degree d ≥ 1 has a sixth, of `3 · ((d + 1)² − 1)` bytes per Gaussian.
const STREAMS: [(&str, u64); 5] = [
    ("positions", 9),
    ("alphas", 1),
    ("colors", 3),
    ("scales", 3),
    ("rotations", 4),
];

/// Writes `set` to an `.spz` file.
pub fn write(path: &Path, set: &GaussianSet) -> Result<(), SceneError> {
    super::write_file(path, &encode(set)?)
}

/// Reads an `.spz` file.
pub fn read(path: &Path) -> Result<GaussianSet, SceneError> {
    decode(&super::read_file(path)?)
}

/// The SPZ (version 4) bytes of `set`.
///
/// Fails on a Gaussian with a non-finite value, a negative scale or a zero rotation, on a
/// coordinate beyond ±2^23 (naming the Gaussian), and on more Gaussians than a `u32` counts.
pub fn encode(set: &GaussianSet) -> Result<Vec<u8>, SceneError> {
    for i in 0..set.len() {
        writable(set, i).map_err(|reason| SceneError::InvalidGaussian { index: i, reason })?;
    }
    let count = u32::try_from(set.len()).map_err(|_| {
        format_error(format!(
            "{} Gaussians are more than the header's u32 count holds",
            set.len()
        ))
    })?;
    // RUB, the file's axes.
    let positions: Vec<[f64; 3]> = set
        .positions()
        .iter()
        .map(|&[x, y, z]| [f64::from(x), -f64::from(y), -f64::from(z)])
        .collect();
    let bits = fractional_bits(set, &positions)?;
    let unit = f64::from(1u32 << bits);

    let n = set.len();
    let mut streams: [Vec<u8>; 5] =
        STREAMS.map(|(_, width)| Vec::with_capacity(n * width as usize));
    for (i, p) in positions.iter().enumerate() {
        for v in p {
            // In range: `fractional_bits` checked every coordinate at this unit.
            let fixed = (v * unit).round() as i32;
            streams[0].extend_from_slice(&fixed.to_le_bytes()[..3]);
        }
        streams[1].push(to_byte(255.0 * f64::from(set.opacities()[i])));
        for c in set.colors()[i] {
            let dc = (f64::from(c) - 0.5) / SH_C0;
            streams[2].push(to_byte(255.0 * (COLOR_SCALE * dc + 0.5)));
        }
        for s in set.scales()[i] {
            // ln 0 = −∞ clamps to the smallest scale.
            streams[3].push(to_byte(
                LOG_SCALE_STEPS * (f64::from(s).ln() + LOG_SCALE_OFFSET),
            ));
        }
        streams[4].extend_from_slice(&pack_rotation(set.rotations()[i]).to_le_bytes());
    }
    assemble(count, 0, bits, 0, &[], &streams)
}

/// Parses SPZ (version 4) bytes.
pub fn decode(bytes: &[u8]) -> Result<GaussianSet, SceneError> {
    if bytes.starts_with(&[0x1f, 0x8b]) {
        return Err(format_error(
            "gzip-compressed, i.e. SPZ version 1 to 3: only version 4 is read".to_owned(),
        ));
    }
    if bytes.len() < HEADER_LEN {
        return Err(format_error(format!(
            "{} bytes, shorter than the {HEADER_LEN}-byte header",
            bytes.len()
        )));
    }
    let magic = read_u32(bytes, 0);
    if magic != MAGIC {
        return Err(format_error(format!(
            "magic {magic:#010x} at byte 0, expected {MAGIC:#010x} (\"NGSP\")"
        )));
    }
    let version = read_u32(bytes, 4);
    if version != VERSION {
        return Err(format_error(format!(
            "version {version} (byte 4): only version {VERSION} is read"
        )));
    }
    let count = read_u32(bytes, 8);
    let n = u64::from(count);
    let degree = bytes[12];
    if degree > MAX_SH_DEGREE {
        return Err(format_error(format!(
            "spherical-harmonic degree {degree} (byte 12) is above {MAX_SH_DEGREE}"
        )));
    }
    let bits = bytes[13];
    if bits > MAX_READ_FRACTIONAL_BITS {
        return Err(format_error(format!(
            "{bits} fractional bits (byte 13): a 24-bit signed coordinate has at most \
             {MAX_READ_FRACTIONAL_BITS}"
        )));
    }
    let stream_count = usize::from(bytes[15]);
    // A file of no Gaussians needs no streams (the reference library writes none).
    let needed = match (count, degree) {
        (0, _) => 0,
        (_, 0) => STREAMS.len(),
        _ => STREAMS.len() + 1,
    };
    if stream_count < needed {
        return Err(format_error(format!(
            "{stream_count} streams (byte 15), a file of SH degree {degree} has {needed}"
        )));
    }
    let toc = u64::from(read_u32(bytes, 16));
    let len = bytes.len();
    if toc < HEADER_LEN as u64 {
        return Err(format_error(format!(
            "table of contents at byte {toc} (byte 16), inside the {HEADER_LEN}-byte header"
        )));
    }
    let toc_end = toc + (stream_count * TOC_ENTRY) as u64;
    if toc_end > len as u64 {
        return Err(format_error(format!(
            "table of contents at byte {toc} ({stream_count} × {TOC_ENTRY} bytes) runs past the \
             end of the file ({len} bytes)"
        )));
    }
    // Within the file: fits a usize.
    let toc = toc as usize;

    // Locate every stream and check its sizes before decompressing any.
    let coefficients = 3 * ((u64::from(degree) + 1).pow(2) - 1);
    let mut offset = toc_end;
    let mut wanted = Vec::with_capacity(STREAMS.len());
    for k in 0..stream_count {
        let entry = toc + k * TOC_ENTRY;
        let (compressed, raw) = (read_u64(bytes, entry), read_u64(bytes, entry + 8));
        let name = STREAMS.get(k).map_or("spherical harmonics", |s| s.0);
        let start = offset;
        let end = start
            .checked_add(compressed)
            .filter(|&end| end <= len as u64)
            .ok_or_else(|| {
                format_error(format!(
                    "stream {k} ({name}): {compressed} compressed bytes from byte {start} run past \
                     the end of the file ({len} bytes)"
                ))
            })?;
        offset = end;
        if k >= needed {
            continue;
        }
        let width = STREAMS.get(k).map_or(coefficients, |s| s.1);
        // At most 2^32 · 72: no overflow.
        let expected = n * width;
        if raw != expected {
            return Err(format_error(format!(
                "stream {k} ({name}) holds {raw} bytes once decompressed (table of contents, byte \
                 {}), {count} Gaussians need {expected}",
                entry + 8
            )));
        }
        // The spherical-harmonic coefficients beyond degree 0 are not read.
        if k < STREAMS.len() {
            // Within the file's length: fits a usize.
            wanted.push((k, name, start as usize..end as usize, expected));
        }
    }
    if offset != len as u64 {
        return Err(format_error(format!(
            "{} bytes after the last stream, which ends at byte {offset}",
            len as u64 - offset
        )));
    }
    if count == 0 {
        return Ok(GaussianSet::default());
    }

    let streams = wanted
        .into_par_iter()
        .map(|(k, name, range, expected)| decompress(&bytes[range], expected, k, name))
        .collect::<Result<Vec<_>, _>>()?;
    let [positions, alphas, colors, scales, rotations] = &streams[..] else {
        return Err(format_error("streams missing".to_owned()));
    };

    let unit = (1u32 << bits) as f32;
    let coordinate = |b: &[u8]| {
        // Sign-extend the 24-bit integer.
        let fixed = i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8 >> 8;
        // Exact: |fixed| ≤ 2^23 and `unit` is a power of two.
        fixed as f32 / unit
    };
    let positions = positions
        .chunks_exact(9)
        .map(|p| {
            let [x, y, z] = [0, 3, 6].map(|k| coordinate(&p[k..k + 3]));
            [x, -y, -z]
        })
        .collect();
    let opacities = alphas.iter().map(|&a| f32::from(a) / 255.0).collect();
    let colors = colors
        .chunks_exact(3)
        .map(|c| {
            [c[0], c[1], c[2]].map(|b| {
                let dc = (f64::from(b) / 255.0 - 0.5) / COLOR_SCALE;
                (0.5 + SH_C0 * dc) as f32
            })
        })
        .collect();
    let scales = scales
        .chunks_exact(3)
        .map(|s| {
            [s[0], s[1], s[2]]
                .map(|b| (f64::from(b) / LOG_SCALE_STEPS - LOG_SCALE_OFFSET).exp() as f32)
        })
        .collect();
    let rotations = rotations
        .chunks_exact(4)
        .map(|r| unpack_rotation(u32::from_le_bytes([r[0], r[1], r[2], r[3]])))
        .collect();
    GaussianSet::new(positions, scales, rotations, opacities, colors)
}

/// The header, the table of contents and the compressed `streams`, with `extensions` (extension
/// records, already encoded) between the header and the table.
fn assemble(
    count: u32,
    degree: u8,
    bits: u8,
    flags: u8,
    extensions: &[u8],
    streams: &[Vec<u8>],
) -> Result<Vec<u8>, SceneError> {
    let compressed = streams
        .par_iter()
        .map(|raw| {
            zstd::bulk::compress(raw, zstd::DEFAULT_COMPRESSION_LEVEL)
                .map_err(|e| format_error(format!("zstd compression failed: {e}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let toc = HEADER_LEN + extensions.len();
    let body: usize = compressed.iter().map(Vec::len).sum();
    let mut out = Vec::with_capacity(toc + streams.len() * TOC_ENTRY + body);
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&count.to_le_bytes());
    // At most 6 streams (callers in this module), and a TOC offset within a u32.
    out.extend([degree, bits, flags, streams.len() as u8]);
    out.extend_from_slice(&(toc as u32).to_le_bytes());
    out.extend([0; 12]);
    out.extend_from_slice(extensions);
    for (raw, packed) in streams.iter().zip(&compressed) {
        out.extend_from_slice(&(packed.len() as u64).to_le_bytes());
        out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    }
    for packed in &compressed {
        out.extend_from_slice(packed);
    }
    Ok(out)
}

/// One stream decompressed, refused unless it is exactly `expected` bytes; never decompresses
/// more than that.
fn decompress(
    compressed: &[u8],
    expected: u64,
    k: usize,
    name: &str,
) -> Result<Vec<u8>, SceneError> {
    let fail = |reason: String| format_error(format!("stream {k} ({name}): {reason}"));
    let decoder = zstd::stream::read::Decoder::with_buffer(compressed)
        .map_err(|e| fail(format!("zstd: {e}")))?;
    // Grown as bytes come, so a lying frame costs no more memory than it really holds.
    let mut out = Vec::with_capacity(expected.min(1 << 24) as usize);
    decoder
        .take(expected + 1)
        .read_to_end(&mut out)
        .map_err(|e| fail(format!("zstd: {e}")))?;
    if out.len() as u64 != expected {
        let got = if out.len() as u64 > expected {
            "more".to_owned()
        } else {
            out.len().to_string()
        };
        return Err(fail(format!(
            "decompresses to {got} bytes, the table of contents says {expected}"
        )));
    }
    Ok(out)
}

/// Why Gaussian `i` cannot be written, if it cannot.
fn writable(set: &GaussianSet, i: usize) -> Result<(), String> {
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    let (p, s, q, o, c) = (
        set.positions()[i],
        set.scales()[i],
        set.rotations()[i],
        set.opacities()[i],
        set.colors()[i],
    );
    if !finite(&p) {
        return Err(format!("position {p:?} is not finite"));
    }
    if !finite(&s) || s.iter().any(|&v| v < 0.0) {
        return Err(format!("scale {s:?} is not finite and non-negative"));
    }
    if !finite(&q) || q.iter().all(|&v| v == 0.0) {
        return Err(format!(
            "rotation {q:?} is not a finite, non-zero quaternion"
        ));
    }
    if !o.is_finite() {
        return Err(format!("opacity {o} is not finite"));
    }
    if !finite(&c) {
        return Err(format!("color {c:?} is not finite"));
    }
    Ok(())
}

/// The most fractional bits (up to [`MAX_FRACTIONAL_BITS`]) at which every coordinate of
/// `positions` (finite) fits a 24-bit signed integer.
fn fractional_bits(set: &GaussianSet, positions: &[[f64; 3]]) -> Result<u8, SceneError> {
    let (lo, hi) = positions
        .iter()
        .flatten()
        .fold((0.0f64, 0.0f64), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    // Rounding is monotone: the extremes decide.
    let fits = |v: f64, unit: f64| (FIXED_MIN..=FIXED_MAX).contains(&(v * unit).round());
    if let Some(bits) = (0..=MAX_FRACTIONAL_BITS)
        .rev()
        .find(|&bits| fits(lo, f64::from(1u32 << bits)) && fits(hi, f64::from(1u32 << bits)))
    {
        return Ok(bits);
    }
    let index = positions
        .iter()
        .position(|p| p.iter().any(|&v| !fits(v, 1.0)))
        .unwrap_or(0);
    Err(SceneError::InvalidGaussian {
        index,
        reason: format!(
            "position {:?} is beyond SPZ's 24-bit coordinates (−8388608 to 8388607)",
            set.positions()[index]
        ),
    })
}

/// The "smallest three" `u32` of the OpenCV-axes rotation `[w, x, y, z]` (finite, non-zero).
fn pack_rotation(q: [f32; 4]) -> u32 {
    let [w, x, y, z] = q.map(f64::from);
    // RUB, in the file's x, y, z, w order.
    let mut c = [x, -y, -z, w];
    let norm = c.iter().map(|v| v * v).sum::<f64>().sqrt();
    let largest = (0..4).fold(
        0,
        |best, k| {
            if c[k].abs() > c[best].abs() { k } else { best }
        },
    );
    // The largest is implied positive: q and −q are the same rotation.
    let sign = if c[largest] < 0.0 { -norm } else { norm };
    c = c.map(|v| v / sign);
    (0..4)
        .filter(|&k| k != largest)
        .fold(largest as u32, |packed, k| {
            let magnitude = (c[k].abs() / std::f64::consts::FRAC_1_SQRT_2 * ROTATION_STEPS).round();
            let field = u32::from(c[k] < 0.0) << 9 | magnitude.min(ROTATION_STEPS) as u32;
            packed << 10 | field
        })
}

/// The OpenCV-axes rotation `[w, x, y, z]` (normalised) of a "smallest three" `u32`.
fn unpack_rotation(packed: u32) -> [f32; 4] {
    let largest = (packed >> 30) as usize;
    let mut c = [0.0f64; 4];
    let mut rest = packed;
    // The last component is in the lowest bits.
    for k in (0..4).rev().filter(|&k| k != largest) {
        let field = rest & 0x3ff;
        rest >>= 10;
        let magnitude = f64::from(field & 0x1ff) / ROTATION_STEPS * std::f64::consts::FRAC_1_SQRT_2;
        c[k] = if field & 0x200 != 0 {
            -magnitude
        } else {
            magnitude
        };
    }
    // Corrupt bytes can make the three exceed a unit norm: the largest is then 0, and the
    // normalisation below restores a unit quaternion (the three are never all zero then).
    c[largest] = (1.0 - c.iter().map(|v| v * v).sum::<f64>()).max(0.0).sqrt();
    let norm = c.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [x, y, z, w] = c.map(|v| (v / norm) as f32);
    [w, x, -y, -z]
}

/// `v` rounded and clamped to a byte.
fn to_byte(v: f64) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

fn read_u32(b: &[u8], at: usize) -> u32 {
    let mut bytes = [0u8; 4];
    bytes.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(bytes)
}

fn read_u64(b: &[u8], at: usize) -> u64 {
    let mut bytes = [0u8; 8];
    bytes.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(bytes)
}

fn format_error(reason: String) -> SceneError {
    SceneError::Format {
        format: "spz",
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use c4g_scene::test_rng::{Rng, unit};
    use proptest::prelude::*;

    /// One Gaussian: position, scale, rotation (not yet normalised), opacity, colour.
    type Row = ([f32; 3], [f32; 3], [f64; 4], f32, [f32; 3]);

    /// `n` random Gaussians with coordinates within ±`extent`, then the extremes.
    fn sample(n: usize, extent: f64, seed: u64) -> GaussianSet {
        let mut rng = Rng(seed);
        let mut g = Vec::new();
        for _ in 0..n {
            let q = unit([0; 4].map(|_| rng.next() * 2.0 - 1.0));
            g.push((
                [0; 3].map(|_| rng.range(-extent, extent)),
                [0; 3].map(|_| rng.range(-10.0, 5.9).exp()),
                q,
                rng.range(0.0, 1.0),
                [0; 3].map(|_| rng.range(0.0, 1.4)),
            ));
        }
        let e = extent as f32;
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let extremes: [Row; 12] = [
            (
                [e, -e, e],
                [0.0, 1e-9, 1e4],
                [-0.9, 0.1, 0.2, 0.3],
                0.0,
                [0.0, 2.0, 1.44],
            ),
            ([-e, e, -e], [1.0; 3], [0.1, -0.9, 0.2, 0.3], 1.0, [0.5; 3]),
            (
                [0.0; 3],
                [4.6e-5, 378.0, 1.0],
                [0.1, 0.2, -0.9, 0.3],
                -0.5,
                [1.0; 3],
            ),
            ([e, e, e], [0.5; 3], [0.1, 0.2, 0.3, -0.9], 1.5, [0.0; 3]),
            ([-e, -e, -e], [0.5; 3], [0.9, -0.1, 0.2, 0.3], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [0.1, 0.9, 0.2, -0.3], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [0.1, 0.2, 0.9, 0.3], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [-0.1, 0.2, 0.3, 0.9], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [0.5, -0.5, 0.5, 0.5], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [h, 0.0, -h, 0.0], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [0.0, 0.0, 0.0, -1.0], 0.5, [0.3; 3]),
            ([0.0; 3], [0.5; 3], [-1.0, 0.0, 0.0, 0.0], 0.5, [0.3; 3]),
        ];
        for (p, s, q, o, c) in extremes {
            g.push((p, s, unit(q), o, c));
        }
        GaussianSet::new(
            g.iter().map(|x| x.0).collect(),
            g.iter().map(|x| x.1).collect(),
            g.iter().map(|x| x.2).collect(),
            g.iter().map(|x| x.3).collect(),
            g.iter().map(|x| x.4).collect(),
        )
        .unwrap()
    }

    /// The rotation angle between two unit quaternions, in radians.
    fn angle(a: [f32; 4], b: [f32; 4]) -> f64 {
        // From the chord rather than the dot product: acos near 1 would add f32 noise of 1e-3.
        let chord = |sign: f64| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (f64::from(*x) - sign * f64::from(y)).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        4.0 * (chord(1.0).min(chord(-1.0)) / 2.0).min(1.0).asin()
    }

    /// The largest error per attribute (position, opacity, colour, ln scale, rotation), each
    /// against the clamped value, after checking it is within the documented bound.
    fn check_round_trip(set: &GaussianSet, bytes: &[u8]) -> [f64; 5] {
        let back = decode(bytes).unwrap();
        assert_eq!(back.len(), set.len());
        let half_step = 0.5 / f64::from(1u32 << bytes[13]);
        let (c_lo, c_hi) = (0.5 - SH_C0 / 0.3, 0.5 + SH_C0 / 0.3);
        let (s_lo, s_hi) = (-10.0, 255.0 / 16.0 - 10.0);
        let mut worst = [0.0f64; 5];
        let mut note = |k: usize, err: f64, bound: f64, i: usize| {
            assert!(
                err <= bound,
                "Gaussian {i}: attribute {k} off by {err} > {bound}"
            );
            worst[k] = worst[k].max(err);
        };
        for i in 0..set.len() {
            for (a, b) in set.positions()[i].iter().zip(back.positions()[i]) {
                note(0, (f64::from(*a) - f64::from(b)).abs(), half_step, i);
            }
            let o = f64::from(set.opacities()[i]).clamp(0.0, 1.0);
            let bound = f64::from(OPACITY_ERROR) + 1e-7;
            note(1, (o - f64::from(back.opacities()[i])).abs(), bound, i);
            for (a, b) in set.colors()[i].iter().zip(back.colors()[i]) {
                let err = (f64::from(*a).clamp(c_lo, c_hi) - f64::from(b)).abs();
                note(2, err, f64::from(COLOR_ERROR) + 1e-7, i);
            }
            for (a, b) in set.scales()[i].iter().zip(back.scales()[i]) {
                let err = (f64::from(*a).ln().clamp(s_lo, s_hi) - f64::from(b).ln()).abs();
                note(3, err, f64::from(LOG_SCALE_ERROR) + 1e-6, i);
            }
            let q = back.rotations()[i];
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!(
                (norm - 1.0).abs() < 1e-6,
                "Gaussian {i}: rotation norm {norm}"
            );
            let err = angle(set.rotations()[i], q);
            note(4, err, f64::from(ROTATION_ERROR), i);
        }
        worst
    }

    fn raw_streams(bytes: &[u8]) -> Vec<Vec<u8>> {
        let count = usize::from(bytes[15]);
        let toc = read_u32(bytes, 16) as usize;
        let mut at = toc + count * TOC_ENTRY;
        (0..count)
            .map(|k| {
                let size = read_u64(bytes, toc + k * TOC_ENTRY) as usize;
                let raw = read_u64(bytes, toc + k * TOC_ENTRY + 8) as usize;
                at += size;
                zstd::bulk::decompress(&bytes[at - size..at], raw).unwrap()
            })
            .collect()
    }

    fn from_hex(hex: &str) -> Vec<u8> {
        (0..hex.len())
            .step_by(2)
            .map(|k| u8::from_str_radix(&hex[k..k + 2], 16).unwrap())
            .collect()
    }

    fn format_reason(err: SceneError) -> String {
        match err {
            SceneError::Format { format, reason } => {
                assert_eq!(format, "spz");
                reason
            }
            other => panic!("not a format error: {other}"),
        }
    }

    fn decode_err(bytes: &[u8]) -> String {
        format_reason(decode(bytes).unwrap_err())
    }

    #[test]
    fn round_trips_within_the_stated_bounds() {
        // Small scenes get 20 fractional bits, coordinates near ±2048 12, near ±2^23 none.
        for (extent, bits) in [(3.9, 20), (1000.0, 13), (2047.99, 12), (8_388_607.0, 0)] {
            let set = sample(2000, extent, bits);
            let bytes = encode(&set).unwrap();
            assert_eq!(bytes[13], bits as u8, "extent {extent}");
            check_round_trip(&set, &bytes);
        }
    }

    #[test]
    fn rotations_round_trip_within_the_stated_angle() {
        let mut rng = Rng(7);
        let rotations: Vec<[f32; 4]> = (0..100_000)
            .map(|_| unit([0; 4].map(|_| rng.next() * 2.0 - 1.0)))
            .collect();
        let n = rotations.len();
        let set = GaussianSet::new(
            vec![[0.0; 3]; n],
            vec![[1.0; 3]; n],
            rotations,
            vec![1.0; n],
            vec![[0.5; 3]; n],
        )
        .unwrap();
        let worst = check_round_trip(&set, &encode(&set).unwrap())[4];
        assert!(
            worst > 0.6 * f64::from(ROTATION_ERROR),
            "a loose bound: {worst}"
        );
    }

    #[test]
    fn header_and_table_of_contents() {
        let set = sample(0, 3.0, 1).select(&[true; 12]).unwrap();
        let bytes = encode(&set).unwrap();
        assert_eq!(&bytes[..4], b"NGSP");
        assert_eq!(read_u32(&bytes, 4), 4);
        assert_eq!(read_u32(&bytes, 8), 12);
        assert_eq!(bytes[12..16], [0, 20, 0, 5]);
        assert_eq!(read_u32(&bytes, 16), 32);
        assert_eq!(bytes[20..32], [0; 12]);
        let mut at = 32 + 5 * 16;
        for (k, raw) in [9 * 12, 12, 3 * 12, 3 * 12, 4 * 12].into_iter().enumerate() {
            assert_eq!(read_u64(&bytes, 32 + 16 * k + 8), raw);
            // Each stream is one zstd frame.
            assert_eq!(bytes[at..at + 4], [0x28, 0xb5, 0x2f, 0xfd]);
            at += read_u64(&bytes, 32 + 16 * k) as usize;
        }
        assert_eq!(at, bytes.len());
    }

    #[test]
    fn fractional_bits_are_the_most_that_fit_in_rub_axes() {
        // The positive end of 24 bits is 2^23 − 1, the negative −2^23; y and z flip sign.
        for (p, bits) in [
            ([3.0, 0.0, 0.0], 20),
            ([10.0, 0.0, 0.0], 19),
            ([1000.0, 0.0, 0.0], 13),
            ([1024.0, 0.0, 0.0], 12),
            ([-1024.0, 0.0, 0.0], 13),
            ([0.0, 1024.0, 0.0], 13),
            ([0.0, 0.0, -1024.0], 12),
            ([0.0, 0.0, 0.0], 20),
            ([8_388_607.0, 0.0, 0.0], 0),
        ] {
            let set = GaussianSet::new(
                vec![[0.5, 0.5, 0.5], p],
                vec![[1.0; 3]; 2],
                vec![[1.0, 0.0, 0.0, 0.0]; 2],
                vec![1.0; 2],
                vec![[0.5; 3]; 2],
            )
            .unwrap();
            let bytes = encode(&set).unwrap();
            assert_eq!(bytes[13], bits, "{p:?}");
            check_round_trip(&set, &bytes);
        }
    }

    #[test]
    fn positions_are_stored_in_rub_axes() {
        let set = GaussianSet::new(
            vec![[1.0, 2.0, 3.0]],
            vec![[1.0; 3]],
            vec![[1.0, 0.0, 0.0, 0.0]],
            vec![1.0],
            vec![[0.5; 3]],
        )
        .unwrap();
        let bytes = encode(&set).unwrap();
        assert_eq!(bytes[13], 20);
        let fixed: Vec<i32> = raw_streams(&bytes)[0]
            .chunks_exact(3)
            .map(|b| i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8 >> 8)
            .collect();
        assert_eq!(fixed, [1 << 20, -2 << 20, -3 << 20]);
    }

    /// A file the reference library (`@adobe/spz` 0.2.3, `saveSpzToBuffer` version 4, `from:
    /// RDF`) wrote of [`reference_values`]: it writes 12 fractional bits.
    const REFERENCE_FILE: &str = "4e4753500400000003000000000c000520000000000000000000000000000000\
        24000000000000001b000000000000000c000000000000000300000000000000\
        1200000000000000090000000000000012000000000000000900000000000000\
        15000000000000000c0000000000000028b52ffd201bd9000000100000e0ff00\
        d0ff00e8ff00fcff00020000400600800c0040ed28b52ffd2003190000d9800d\
        28b52ffd20094900005780a8c33c8049b6de28b52ffd20094900007b868da056\
        ab31badf28b52ffd200c610000000000c069a59d1648661ba9";

    /// The set behind [`REFERENCE_FILE`], in our axes and activations.
    fn reference_values() -> GaussianSet {
        GaussianSet::new(
            vec![
                [1.0, 2.0, 3.0],
                [-1.5, 0.25, -0.125],
                [100.0, -200.0, 300.0],
            ],
            vec![[0.1, 0.2, 0.3], [1.0, 0.01, 2.0], [0.001, 5.0, 50.0]],
            vec![
                [1.0, 0.0, 0.0, 0.0],
                [0.5, 0.5, -0.5, 0.5],
                unit([0.1, 0.2, -0.3, 0.927_361_849_549_570_3]),
            ],
            vec![0.85, 0.5, 0.05],
            vec![[0.2, 0.5, 0.8], [1.0, 0.0, 0.5], [0.1, 0.9, 1.2]],
        )
        .unwrap()
    }

    #[test]
    fn reads_what_the_reference_library_writes() {
        let bytes = from_hex(REFERENCE_FILE);
        assert_eq!(bytes.len(), 217);
        assert_eq!(bytes[13], 12);
        check_round_trip(&reference_values(), &bytes);
    }

    #[test]
    fn writes_the_attribute_bytes_the_reference_library_writes() {
        let theirs = raw_streams(&from_hex(REFERENCE_FILE));
        let ours = raw_streams(&encode(&reference_values()).unwrap());
        assert_eq!(ours.len(), 5);
        // Positions differ by the fractional bits (14 here, 12 there); alphas, colours and
        // scales are the same bytes.
        assert_eq!(ours[1..4], theirs[1..4]);
        // Rotations too, but for the sign bit of components that are zero: the reference sets
        // it when it negates the quaternion to make the largest component positive.
        let rotations = |s: &[u8]| -> Vec<u32> {
            s.chunks_exact(4)
                .map(|r| {
                    let v = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
                    (0..3).fold(v, |v, k| {
                        let field = v >> (10 * k) & 0x3ff;
                        if field == 0x200 {
                            v & !(0x200 << (10 * k))
                        } else {
                            v
                        }
                    })
                })
                .collect()
        };
        assert_eq!(rotations(&ours[4]), rotations(&theirs[4]));
        // Bytes checked by hand against the reference: opacity 0.5 is 128, rgb 1 (f_dc 1.77)
        // is 195, scale 1 is 160, and x y z w = (0.5, −0.5, 0.5, 0.5) in RUB stores index 0 and
        // 361 = round(511 · 0.5 / √½) thrice, the middle one negative.
        assert_eq!(ours[1][1], 128);
        assert_eq!(ours[2][3], 195);
        assert_eq!(ours[3][3], 160);
        assert_eq!(&ours[4][4..8], &0x169d_a569u32.to_le_bytes());
    }

    #[test]
    fn extension_records_sh_and_extra_streams_are_skipped() {
        let set = reference_values();
        let plain = encode(&set).unwrap();
        let want = decode(&plain).unwrap();
        let mut streams = raw_streams(&plain);
        let with_extension = assemble(3, 0, plain[13], 0x3, &[0xab; 20], &streams).unwrap();
        assert_eq!(read_u32(&with_extension, 16), 52);
        assert_eq!(decode(&with_extension).unwrap(), want);

        // Degree 1: nine SH bytes a Gaussian, not read; a missing SH stream is an error.
        let with_sh = assemble(3, 1, plain[13], 0, &[], &streams).unwrap();
        assert!(decode_err(&with_sh).contains("5 streams (byte 15), a file of SH degree 1 has 6"));
        streams.push(vec![7; 27]);
        let with_sh = assemble(3, 1, plain[13], 0, &[], &streams).unwrap();
        assert_eq!(decode(&with_sh).unwrap(), want);
        let short_sh = assemble(3, 2, plain[13], 0, &[], &streams).unwrap();
        assert!(
            decode_err(&short_sh).contains("stream 5 (spherical harmonics) holds 27 bytes"),
            "{}",
            decode_err(&short_sh)
        );
        // A sixth stream at degree 0 is skipped.
        let extra = assemble(3, 0, plain[13], 0, &[], &streams).unwrap();
        assert_eq!(decode(&extra).unwrap(), want);
    }

    #[test]
    fn empty_sets_and_the_reference_library_s_empty_file() {
        let empty = GaussianSet::default();
        assert!(decode(&encode(&empty).unwrap()).unwrap().is_empty());
        // What the reference writes for no points: a header and no streams.
        let theirs = from_hex("4e4753500400000000000000000c010020000000000000000000000000000000");
        assert!(decode(&theirs).unwrap().is_empty());
    }

    #[test]
    fn files_round_trip() {
        let set = sample(50, 5.0, 3);
        let path = std::env::temp_dir().join(format!("c4g-spz-test-{}.spz", std::process::id()));
        write(&path, &set).unwrap();
        let back = read(&path);
        std::fs::remove_file(&path).unwrap();
        assert_eq!(back.unwrap(), decode(&encode(&set).unwrap()).unwrap());
    }

    #[test]
    fn gaussians_that_cannot_be_written_are_refused_by_index() {
        let base = sample(3, 1.0, 5);
        // Each case spoils Gaussian 2 in one of the five columns.
        let cases: [(&str, usize, usize, f32); 6] = [
            ("position", 0, 1, f32::NAN),
            ("scale", 1, 0, -1.0),
            ("scale", 1, 2, f32::INFINITY),
            ("rotation", 2, 4, 0.0),
            ("opacity", 3, 0, f32::NAN),
            ("color", 4, 1, f32::NEG_INFINITY),
        ];
        for (what, column, k, v) in cases {
            let (mut p, mut s, mut q, mut o, mut c) = (
                base.positions().to_vec(),
                base.scales().to_vec(),
                base.rotations().to_vec(),
                base.opacities().to_vec(),
                base.colors().to_vec(),
            );
            match column {
                0 => p[2][k] = v,
                1 => s[2][k] = v,
                2 => q[2] = [v; 4],
                3 => o[2] = v,
                _ => c[2][k] = v,
            }
            let set = GaussianSet::new(p, s, q, o, c).unwrap();
            match encode(&set) {
                Err(SceneError::InvalidGaussian { index: 2, reason }) => {
                    assert!(reason.starts_with(what), "{reason}");
                }
                other => panic!("{what}: {other:?}"),
            }
        }
        let far = GaussianSet::new(
            vec![[0.0; 3], [0.0, -8_388_609.0, 0.0]],
            vec![[1.0; 3]; 2],
            vec![[1.0, 0.0, 0.0, 0.0]; 2],
            vec![1.0; 2],
            vec![[0.5; 3]; 2],
        )
        .unwrap();
        match encode(&far) {
            Err(SceneError::InvalidGaussian { index: 1, reason }) => {
                assert!(reason.contains("24-bit"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn malformed_files_are_errors_that_say_what_and_where() {
        let good = encode(&reference_values()).unwrap();
        let patched = |at: usize, with: &[u8]| {
            let mut b = good.clone();
            b[at..at + with.len()].copy_from_slice(with);
            b
        };
        // The rotations' frame starts where the other four end.
        let rotations_at = 32
            + 5 * 16
            + (0..4)
                .map(|k| read_u64(&good, 32 + 16 * k) as usize)
                .sum::<usize>();
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (vec![0x1f, 0x8b, 8, 0], "gzip-compressed"),
            (
                good[..31].to_vec(),
                "31 bytes, shorter than the 32-byte header",
            ),
            (patched(0, b"NGSQ"), "magic 0x5153474e at byte 0"),
            (patched(4, &[3]), "version 3 (byte 4)"),
            (patched(8, &[4]), "stream 0 (positions) holds 27 bytes"),
            (patched(12, &[5]), "degree 5 (byte 12)"),
            (patched(13, &[24]), "24 fractional bits (byte 13)"),
            (patched(15, &[4]), "4 streams (byte 15)"),
            (patched(16, &[16]), "table of contents at byte 16 (byte 16)"),
            (patched(16, &[0, 0, 0, 1]), "runs past the end of the file"),
            (
                patched(32 + 16 + 8, &[4]),
                "stream 1 (alphas) holds 4 bytes",
            ),
            (patched(32 + 16 * 4, &[0xff]), "stream 4 (rotations)"),
            (
                patched(32, &[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff]),
                "stream 0 (positions): 18446744073709551615 compressed bytes",
            ),
            ([&good[..], &[0]].concat(), "1 bytes after the last stream"),
            (
                patched(rotations_at, &[0x55; 4]),
                "stream 4 (rotations): zstd",
            ),
        ];
        for (bytes, want) in cases {
            let reason = decode_err(&bytes);
            assert!(reason.contains(want), "{want:?} not in {reason:?}");
        }
        // A frame holding more than its table entry says is cut off, not decompressed.
        let mut streams = raw_streams(&good);
        streams[1].push(9);
        let mut long = assemble(3, 0, good[13], 0, &[], &streams).unwrap();
        long[32 + 16 + 8] = 3;
        assert!(decode_err(&long).contains("stream 1 (alphas): decompresses to more bytes"));
        streams[1].truncate(2);
        let mut short = assemble(3, 0, good[13], 0, &[], &streams).unwrap();
        short[32 + 16 + 8] = 3;
        assert!(decode_err(&short).contains("decompresses to 2 bytes"));
        // Every truncation.
        for cut in 0..good.len() {
            assert!(decode(&good[..cut]).is_err(), "cut at {cut}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn spoiled_files_never_panic(
            spoils in proptest::collection::vec((0usize..4096, any::<u8>()), 1..8),
        ) {
            let mut bytes = encode(&sample(20, 2.0, 11)).unwrap();
            for (at, v) in spoils {
                let at = at % bytes.len();
                bytes[at] = v;
            }
            let _ = decode(&bytes);
        }

        #[test]
        fn arbitrary_bytes_after_a_header_never_panic(
            header in proptest::collection::vec(any::<u8>(), 20),
            rest in proptest::collection::vec(any::<u8>(), 0..256),
        ) {
            let bytes = [&b"NGSP\x04\0\0\0"[..], &header[..], &rest[..]].concat();
            let _ = decode(&bytes);
        }
    }
}
