//! `C4GV`: a compact, streamable format for the Gaussian sets of one clip over a range of times.
//! This comment is its specification (version 1).
//!
//! C4G decodes the same N Gaussians at every time, in the same order: Gaussian i at 0.2 s is
//! Gaussian i at 0.4 s, moved. So a stream of sets is sent as one stream of per-Gaussian changes:
//! every value is put on a grid whose step meets a stated error bound, Gaussians that never change
//! their grid cell are sent once, and the others as small integer changes from the previous frame,
//! with a full keyframe every K frames so that a reader can seek. Where [`c4gs`](super::c4gs)
//! spends 56 (or 28) bytes a Gaussian a frame, this spends about 4: 7-9 % of `C4GS` f32 on
//! c4g-tiny's decoded clips at a position error of 10⁻³ (`docs/benchmarks.md`, "Compact 4D
//! stream").
//!
//! # Layout
//! Little endian throughout. A stream is a header, then records: one static record, the frames in
//! time order, and an index record that ends it:
//!
//! ```text
//! header | static | frame 0 (keyframe) | frame 1 | ... | frame F-1 | index
//! ```
//!
//! Every record is self-delimiting, so a reader decodes frame by frame as bytes arrive (over
//! chunked HTTP, say) without knowing how many frames will come; the index is a trailer for
//! readers with the whole stream (a file, a buffer, HTTP ranges), which find it from the stream's
//! last 12 bytes. A trailer and not a table in the header because the encoder streams: it does not
//! know where frames will land when it writes the header.
//!
//! ## Header (56 + ⌈N/8⌉ bytes)
//! | offset | bytes | field |
//! |---|---|---|
//! | 0 | 4 | magic `b"C4GV"` |
//! | 4 | 2 | `u16` version (1) |
//! | 6 | 1 | `u8` predictor: 0, the previous frame's cells (the only one of version 1) |
//! | 7 | 1 | `u8` reserved (0; ignored when read) |
//! | 8 | 4 | `u32` N, Gaussians per frame |
//! | 12 | 4 | `u32` S, static Gaussians |
//! | 16 | 40 | five `f64` grid steps: position, log-scale, rotation, opacity, colour |
//! | 56 | ⌈N/8⌉ | static mask: bit `i % 8` of byte `i / 8` is set when Gaussian i is static |
//!
//! Exactly S bits are set and the padding bits after bit N − 1 are 0. The steps are finite and
//! positive. The other N − S Gaussians are **moving**.
//!
//! ## Records
//! | bytes | field |
//! |---|---|
//! | 1 | `u8` kind: 1 static, 2 keyframe, 3 delta frame, 4 index |
//! | 1 | `u8` body coding: 0 stored, 1 raw DEFLATE (RFC 1951; the index is always 0) |
//! | 4 | `u32` L, bytes of the record after these 6 |
//! | L | payload |
//!
//! - **static** (first, exactly once; a stream of no frames may go straight to the index):
//!   `u32` R, the body's length once inflated, then the body: the grid cells of the S static
//!   Gaussians. They hold these values in every frame.
//! - **keyframe** and **delta frame**: `f64` time in seconds, `u32` R, then the body: one value
//!   per channel of each of the N − S moving Gaussians: their cells in a keyframe, their changes
//!   from the frame before in a delta frame. The first frame is a keyframe; times are finite and
//!   strictly increasing.
//! - **index**: per frame 17 bytes (`f64` time, `u64` offset of the frame's record from the
//!   stream's first byte, `u8` 1 for a keyframe else 0), then `u64` the offset of this record and
//!   the magic `b"C4GI"`. Nothing follows it.
//!
//! A body is 14 columns, in the canonical channel order (position x y z, scale x y z, rotation
//! w x y z, opacity, colour R G B: [`crate::CANONICAL_CHANNELS`]), each holding one value per
//! Gaussian of the record in ascending Gaussian order: column-major, so that DEFLATE sees runs of
//! like values. A value is a signed integer, zigzag-mapped (`n ≥ 0 → 2n`, `n < 0 → −2n − 1`; back:
//! even `u → u/2`, odd `u → −(u + 1)/2`) and written as an unsigned LEB128 varint of at most
//! 5 bytes (7 bits a byte, low first, the high bit set on every byte but the last), so a body of
//! `c` Gaussians is `14c` to `70c` bytes and R must lie in that range. A stored body is R bytes; a
//! deflated one is a single raw DEFLATE stream that fills its bytes exactly and inflates to R
//! bytes (the encoder deflates only when that is shorter, so a deflated body is under R bytes; an
//! empty body is stored). Browsers inflate it with `DecompressionStream("deflate-raw")`.
//!
//! ## Cells and prediction
//! A Gaussian's 14 values become 14 integer cells (its grid indices); every cell lies strictly
//! inside ±2³⁰. With the header's steps Δ, a value v is sent as `round(v / Δ)` of:
//!
//! | channel | grid value | decoded as (f64, then rounded to f32) |
//! |---|---|---|
//! | position | x | `cell · Δpos` |
//! | scale | ln s | `exp(cell · Δlog)` |
//! | rotation | each of w, x, y, z of the unit quaternion | `cell · Δrot`, then divided by the four's norm (zero is an error) |
//! | opacity | o | `cell · Δop` |
//! | colour | each of R, G, B | `cell · Δcol` |
//!
//! Prediction works on cells, which the decoder reproduces exactly: integer residuals are
//! lossless, so the encoder predicts from precisely the decoder's reconstruction (the loop is
//! closed) and a frame's error is its own quantisation error, however many frames lie since the
//! keyframe; an open loop that quantised `v(t) − v(t − 1)` instead would let the errors add up.
//! A keyframe's values are the cells. A delta frame's value is its cell minus the same cell one
//! frame before; the decoder adds it (in 64-bit integers) and refuses a cell outside ±2³⁰.
//! Linear extrapolation from two frames was measured and left out: C4G's sets jitter from frame
//! to frame at these steps, and extrapolating doubles the jitter (`docs/benchmarks.md`).
//!
//! ## Static Gaussians
//! A static Gaussian is sent once, in the static record, and holds those values in every frame.
//! [`encode`] finds them (with [`EncodeOptions::detect_static`], the default): the Gaussians whose
//! 14 cells are the same in every frame given, which moved less than one grid step over the range
//! and decode to the same values per-frame coding would give. A streaming [`Encoder`] sees one
//! frame at a time and cannot know which Gaussians will stay put, so it takes a caller's mask
//! ([`Encoder::with_static_mask`]; [`static_mask`] makes one from sets the caller has, and
//! [`pruning`](crate::pruning)'s static/moving split is another source): a masked Gaussian holds
//! its first frame's cells, and [`Encoder::push`] refuses a frame where that no longer meets every
//! bound below, so the bounds stay promises. A mask from centres alone (pruning's) can miss a
//! change of opacity or colour; such a frame is refused, not sent wrong.
//!
//! # Error bounds
//! What this encoder guarantees, per value, between a set given and the set decoded (the tests
//! check each in f64). `e` is [`EncodeOptions::position_error`], in scene units.
//!
//! | channel | step | largest error | range (outside it the encoder refuses the set) |
//! |---|---|---|---|
//! | position | 1.875 · e | e per coordinate | \|x\| ≤ 10⁶ · e |
//! | scale | ln: 1/1024 | relative 4.9 · 10⁻⁴ (e^(1/2048) − 1, and f32 rounding) | every finite s ≥ 0; s < 2⁻⁶⁴ is sent as 2⁻⁶⁴ (absolute error < 6 · 10⁻²⁰) |
//! | rotation | 1/4096 | 4.9 · 10⁻⁴ rad, 0.028° (2 · asin(1/4096): each component off by at most half a step, so the quaternion by at most one step) | unit quaternions (validated) |
//! | opacity | 1/1023 | 4.9 · 10⁻⁴ (1/2046) | \[0, 1\] |
//! | colour | 1/1023 | 4.9 · 10⁻⁴ (1/2046) | \[0, 16\] |
//!
//! Why these. The position step is under 2e so that the grid's half step (0.9375 e) leaves e/16
//! for rounding the decoded value to f32; within the range f32's spacing is at most e/8, so that
//! rounding costs at most e/16. Scales multiply, so their grid is logarithmic: one relative bound
//! from a hair to a room. The rotation step moves the surface of a Gaussian of scale s by about
//! 5 · 10⁻⁴ s, far under any position bound worth asking for at C4G's scene sizes; opacity and
//! colour steps are a quarter of an 8-bit display's; colour stops at 16 (C4G's are in \[0, 1\])
//! where f32's spacing still fits the bound. Non-finite values, negative scales or colours,
//! opacities outside \[0, 1\] and non-unit rotations are refused by
//! [`GaussianSet::validate`] before anything else. The decoder needs none of this: it reads the
//! steps from the header, so a later encoder may choose other steps without a new version.
//! Features ([`crate::FeatureBlock`]) are not part of the format.
//!
//! # Reading
//! [`Decoder`] takes bytes as they come ([`Decoder::feed`]) and hands out each frame as soon as
//! its record is whole ([`Decoder::next_frame`]); [`decode`] reads a whole stream; [`seek`] reads
//! the header, the static record, the index and the frames from the last keyframe at or before a
//! time, and nothing before that keyframe. Every length is checked against what it can be (a body
//! of `c` Gaussians is 14c to 70c bytes; the index holds one entry per frame) before anything is
//! buffered or allocated, inflating stops at the stated length, and memory grows with the bytes
//! actually received, never with what a header claims; a truncated or corrupt stream is a
//! [`RendererError::Format`] that says what is wrong, never a panic. Decoded sets are checked with
//! [`GaussianSet::validate`], so even a hostile stream yields valid sets or an error.
//!
//! A reader in another language (the browser viewer's), step by step: read the header and the
//! mask; read records by their 6-byte heads; inflate a body whose coding is 1; read its 14 ·
//! count varints column by column; a static record fills the static Gaussians once, a keyframe
//! sets the moving ones' cells, a delta frame adds to them; decode the cells as the table above
//! says (in f64, then `Math.fround`) and scatter the static and moving Gaussians back into
//! Gaussian order; stop at the index record. Computed that way its floats are this decoder's,
//! except perhaps the last bit of a scale where its `exp` rounds differently.

use std::io::{Read, Write};

use flate2::Compression;
use flate2::bufread::DeflateDecoder;
use flate2::write::DeflateEncoder;

use crate::{GaussianSet, RendererError};

/// The first four bytes.
pub const MAGIC: [u8; 4] = *b"C4GV";
/// The version this codec writes and the only one it reads.
pub const VERSION: u16 = 1;
/// Bytes of the header before the static mask.
pub const HEADER_BYTES: usize = 56;
/// The last four bytes of a complete stream.
pub const INDEX_MAGIC: [u8; 4] = *b"C4GI";

/// Step of the natural logarithm of scales.
pub const LOG_SCALE_STEP: f64 = 1.0 / 1024.0;
/// Step of each rotation quaternion component.
pub const ROTATION_STEP: f64 = 1.0 / 4096.0;
/// Step of opacities.
pub const OPACITY_STEP: f64 = 1.0 / 1023.0;
/// Step of colour channels.
pub const COLOR_STEP: f64 = 1.0 / 1023.0;
/// Scales below this are sent as it (the logarithm of zero is no grid value).
pub const SCALE_FLOOR: f32 = 5.421_011e-20; // 2⁻⁶⁴
/// The largest colour channel the encoder takes.
pub const COLOR_MAX: f32 = 16.0;
/// Positions reach ± this many times the position error.
pub const POSITION_RANGE: f64 = 1e6;
/// The most Gaussians a frame the encoder writes: a body of 70 bytes each still has a `u32`
/// length.
pub const MAX_GAUSSIANS: usize = (u32::MAX as usize - FRAME_HEAD) / (CHANNELS * VARINT_MAX);
/// The most frames a stream holds: the index's length still fits a `u32`.
pub const MAX_FRAMES: usize = (u32::MAX as usize - INDEX_TAIL) / INDEX_ENTRY;

/// Largest relative error of a decoded scale (at or above [`SCALE_FLOOR`]).
pub const SCALE_ERROR: f64 = 4.9e-4;
/// Largest angle, in radians, between a rotation and its decoded one.
pub const ROTATION_ERROR: f64 = 4.9e-4;
/// Largest error of a decoded opacity.
pub const OPACITY_ERROR: f64 = 4.9e-4;
/// Largest error of a decoded colour channel.
pub const COLOR_ERROR: f64 = 4.9e-4;

/// The position step per unit of position error: under 2, leaving a sixteenth of the bound for
/// rounding to f32.
const POSITION_STEP_PER_ERROR: f64 = 1.875;
/// Cells lie strictly inside ± this.
const CELL_LIMIT: i64 = 1 << 30;
/// Bytes of a record's kind, coding and length.
const RECORD_HEAD: usize = 6;
/// Bytes of a frame record's payload before its body: time and inflated length.
const FRAME_HEAD: usize = 12;
/// Bytes of the static record's payload before its body: inflated length.
const STATIC_HEAD: usize = 4;
/// Bytes of one index entry.
const INDEX_ENTRY: usize = 17;
/// Bytes that end the index: its offset and [`INDEX_MAGIC`].
const INDEX_TAIL: usize = 12;
/// Values per Gaussian.
const CHANNELS: usize = crate::CANONICAL_CHANNELS;
/// Longest varint.
const VARINT_MAX: usize = 5;
/// DEFLATE inflates at most about this many times (1032:1); a bound for reserving output.
const INFLATE_RATIO: usize = 1032;

const KIND_STATIC: u8 = 1;
const KIND_KEYFRAME: u8 = 2;
const KIND_DELTA: u8 = 3;
const KIND_INDEX: u8 = 4;
const CODING_STORED: u8 = 0;
const CODING_DEFLATE: u8 = 1;

/// A Gaussian's grid indices, in canonical channel order.
type Cells = [i64; CHANNELS];

/// The grid steps, as the header carries them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Steps {
    /// Of positions, scene units.
    pub position: f64,
    /// Of the natural logarithm of scales.
    pub log_scale: f64,
    /// Of each rotation component.
    pub rotation: f64,
    /// Of opacities.
    pub opacity: f64,
    /// Of colour channels.
    pub color: f64,
}

impl Steps {
    /// This encoder's steps for a position error.
    fn for_error(position_error: f64) -> Self {
        Self {
            position: POSITION_STEP_PER_ERROR * position_error,
            log_scale: LOG_SCALE_STEP,
            rotation: ROTATION_STEP,
            opacity: OPACITY_STEP,
            color: COLOR_STEP,
        }
    }

    fn as_array(&self) -> [f64; 5] {
        [
            self.position,
            self.log_scale,
            self.rotation,
            self.opacity,
            self.color,
        ]
    }
}

/// What the encoder may spend and must keep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncodeOptions {
    /// The largest error of any position coordinate, scene units (finite, > 0). Default 10⁻³.
    pub position_error: f64,
    /// Every how many frames a keyframe comes (≥ 1; 1: every frame). Default 16.
    pub keyframe_interval: u32,
    /// Deflate each body where that makes it shorter. Default on.
    pub deflate: bool,
    /// [`encode`] only: send the Gaussians whose cells never change once. Default on.
    pub detect_static: bool,
}

impl Default for EncodeOptions {
    fn default() -> Self {
        Self {
            position_error: 1e-3,
            keyframe_interval: 16,
            deflate: true,
            detect_static: true,
        }
    }
}

impl EncodeOptions {
    fn validate(&self) -> Result<(), RendererError> {
        if !(self.position_error.is_finite() && self.position_error > 0.0) {
            return Err(format_error(format!(
                "the position error must be finite and positive, got {}",
                self.position_error
            )));
        }
        if self.keyframe_interval == 0 {
            return Err(format_error(
                "the keyframe interval must be at least 1 frame".into(),
            ));
        }
        Ok(())
    }
}

/// One frame in the index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IndexEntry {
    /// The frame's time, seconds.
    pub time: f64,
    /// Where its record starts, from the stream's first byte.
    pub offset: u64,
    /// Whether it is a keyframe (a reader may start there).
    pub keyframe: bool,
}

/// What a stream's header says.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// Gaussians per frame.
    pub gaussians: usize,
    /// Per Gaussian, whether it is static.
    pub static_mask: Vec<bool>,
    /// The grid steps.
    pub steps: Steps,
}

impl Header {
    fn to_bytes(&self) -> Vec<u8> {
        let statics = self.static_mask.iter().filter(|&&s| s).count();
        let mut out = Vec::with_capacity(HEADER_BYTES + self.gaussians.div_ceil(8));
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.push(0);
        out.push(0);
        // Both fit: the encoder checked N against u32.
        out.extend_from_slice(&(self.gaussians as u32).to_le_bytes());
        out.extend_from_slice(&(statics as u32).to_le_bytes());
        for step in self.steps.as_array() {
            out.extend_from_slice(&step.to_le_bytes());
        }
        let mut mask = vec![0u8; self.gaussians.div_ceil(8)];
        for (i, _) in self.static_mask.iter().enumerate().filter(|(_, s)| **s) {
            mask[i / 8] |= 1 << (i % 8);
        }
        out.extend_from_slice(&mask);
        out
    }

    /// The header at the start of `bytes`, and its length; `None` while it is incomplete.
    fn parse(bytes: &[u8]) -> Result<Option<(Self, usize)>, RendererError> {
        let prefix = &bytes[..bytes.len().min(MAGIC.len())];
        if prefix != &MAGIC[..prefix.len()] {
            return Err(format_error(format!(
                "not a C4GV stream (starts with {prefix:?})"
            )));
        }
        let Some(fixed) = bytes.get(..HEADER_BYTES) else {
            return Ok(None);
        };
        let version = u16::from_le_bytes([fixed[4], fixed[5]]);
        if version != VERSION {
            return Err(format_error(format!(
                "C4GV version {version}; this reader reads version {VERSION} only"
            )));
        }
        if fixed[6] != 0 {
            return Err(format_error(format!(
                "unknown C4GV predictor {} (version 1 has 0 only)",
                fixed[6]
            )));
        }
        // fixed[7] is reserved.
        let gaussians = read_u32(&fixed[8..]) as usize;
        let statics = read_u32(&fixed[12..]) as usize;
        let step = |k: usize| read_f64(&fixed[16 + 8 * k..]);
        let steps = Steps {
            position: step(0),
            log_scale: step(1),
            rotation: step(2),
            opacity: step(3),
            color: step(4),
        };
        if let Some(bad) = steps
            .as_array()
            .into_iter()
            .find(|s| !(s.is_finite() && *s > 0.0))
        {
            return Err(format_error(format!(
                "C4GV grid steps must be finite and positive; the header has {bad}"
            )));
        }
        if statics > gaussians {
            return Err(format_error(format!(
                "C4GV header claims {statics} static Gaussians of {gaussians}"
            )));
        }
        let length = HEADER_BYTES + gaussians.div_ceil(8);
        let Some(mask) = bytes.get(HEADER_BYTES..length) else {
            return Ok(None);
        };
        // The mask is here, so everything sized by N below is bounded by bytes received.
        let static_mask: Vec<bool> = (0..gaussians)
            .map(|i| mask[i / 8] & (1 << (i % 8)) != 0)
            .collect();
        let padding = gaussians % 8;
        if padding != 0 && mask[mask.len() - 1] >> padding != 0 {
            return Err(format_error(
                "C4GV static mask sets bits past the last Gaussian".into(),
            ));
        }
        let set = static_mask.iter().filter(|&&s| s).count();
        if set != statics {
            return Err(format_error(format!(
                "C4GV header claims {statics} static Gaussians; its mask marks {set}"
            )));
        }
        Ok(Some((
            Self {
                gaussians,
                static_mask,
                steps,
            },
            length,
        )))
    }

    fn statics(&self) -> Vec<usize> {
        (0..self.gaussians)
            .filter(|&i| self.static_mask[i])
            .collect()
    }

    fn movers(&self) -> Vec<usize> {
        (0..self.gaussians)
            .filter(|&i| !self.static_mask[i])
            .collect()
    }
}

// ---------------------------------------------------------------------------------------------
// Quantising

/// Gaussian `i` of a validated set on the grid; refuses values outside the encoder's ranges.
fn quantise(set: &GaussianSet, i: usize, steps: &Steps, range: f64) -> Result<Cells, String> {
    let mut cells = [0i64; CHANNELS];
    let cell = |v: f64, step: f64| (v / step).round() as i64;
    for (k, &x) in set.positions()[i].iter().enumerate() {
        if f64::from(x).abs() > range {
            return Err(format!(
                "position {:?} is beyond C4GV's range at this position error (±{range} scene \
                 units: a million times the error)",
                set.positions()[i]
            ));
        }
        cells[k] = cell(f64::from(x), steps.position);
    }
    for (k, &s) in set.scales()[i].iter().enumerate() {
        cells[3 + k] = cell(f64::from(s.max(SCALE_FLOOR)).ln(), steps.log_scale);
    }
    let q = set.rotations()[i].map(f64::from);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    for (k, v) in q.iter().enumerate() {
        cells[6 + k] = cell(v / norm, steps.rotation);
    }
    cells[10] = cell(f64::from(set.opacities()[i]), steps.opacity);
    for (k, &c) in set.colors()[i].iter().enumerate() {
        if c > COLOR_MAX {
            return Err(format!(
                "color {:?} is beyond C4GV's range (0 to {COLOR_MAX})",
                set.colors()[i]
            ));
        }
        cells[11 + k] = cell(f64::from(c), steps.color);
    }
    Ok(cells)
}

/// Every Gaussian of `set` on the grid, after checking it against the canonical layout.
fn quantise_set(set: &GaussianSet, steps: &Steps, range: f64) -> Result<Vec<Cells>, RendererError> {
    set.validate()?;
    (0..set.len())
        .map(|i| {
            quantise(set, i, steps, range)
                .map_err(|reason| RendererError::InvalidGaussian { index: i, reason })
        })
        .collect()
}

/// One Gaussian's decoded values.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Values {
    position: [f32; 3],
    scale: [f32; 3],
    rotation: [f32; 4],
    opacity: f32,
    color: [f32; 3],
}

/// The values of `cells`; `None` for a rotation of zero norm (only a corrupt stream has one).
fn reconstruct(cells: &Cells, steps: &Steps) -> Option<Values> {
    let value = |k: usize, step: f64| (cells[k] as f64 * step) as f32;
    let q: [f64; 4] = std::array::from_fn(|k| cells[6 + k] as f64 * steps.rotation);
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm == 0.0 || !norm.is_finite() {
        return None;
    }
    Some(Values {
        position: std::array::from_fn(|k| value(k, steps.position)),
        scale: std::array::from_fn(|k| (cells[3 + k] as f64 * steps.log_scale).exp() as f32),
        rotation: q.map(|v| (v / norm) as f32),
        opacity: value(10, steps.opacity),
        color: std::array::from_fn(|k| value(11 + k, steps.color)),
    })
}

/// Why Gaussian `i` of `set` is not within the bounds of `held` (its decoded values), if it
/// is not.
fn out_of_bounds(
    set: &GaussianSet,
    i: usize,
    held: &Values,
    position_error: f64,
) -> Option<String> {
    let (p, s, q, o, c) = (
        set.positions()[i],
        set.scales()[i],
        set.rotations()[i],
        set.opacities()[i],
        set.colors()[i],
    );
    let worst = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
            .fold(0.0, f64::max)
    };
    let dp = worst(&p, &held.position);
    if dp > position_error {
        return Some(format!("its position moved {dp} (bound {position_error})"));
    }
    let ds = s
        .iter()
        .zip(held.scale)
        .map(|(&s, h)| scale_error(s, h))
        .fold(0.0, f64::max);
    if ds > SCALE_ERROR {
        return Some(format!(
            "its scale changed by a factor of {ds} (bound {SCALE_ERROR})"
        ));
    }
    let dq = rotation_angle(q, held.rotation);
    if dq > ROTATION_ERROR {
        return Some(format!(
            "its rotation turned {dq} rad (bound {ROTATION_ERROR})"
        ));
    }
    let d = (f64::from(o) - f64::from(held.opacity)).abs();
    if d > OPACITY_ERROR {
        return Some(format!("its opacity changed {d} (bound {OPACITY_ERROR})"));
    }
    let d = worst(&c, &held.color);
    if d > COLOR_ERROR {
        return Some(format!("its colour changed {d} (bound {COLOR_ERROR})"));
    }
    None
}

/// How far a decoded scale is from the scale it stands for: relative at or above
/// [`SCALE_FLOOR`], else absolute (then under 6e-20).
pub fn scale_error(original: f32, decoded: f32) -> f64 {
    let (a, b) = (f64::from(original), f64::from(decoded));
    if original < SCALE_FLOOR {
        (a - b).abs()
    } else {
        (b / a - 1.0).abs()
    }
}

/// The angle, in radians, of the rotation between two quaternions `[w, x, y, z]` (of any norm).
pub fn rotation_angle(a: [f32; 4], b: [f32; 4]) -> f64 {
    let norm = |q: [f32; 4]| q.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
    let dot: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, y)| f64::from(x) * f64::from(y))
        .sum::<f64>()
        / (norm(a) * norm(b));
    2.0 * dot.abs().min(1.0).acos()
}

// ---------------------------------------------------------------------------------------------
// Writing

/// The streaming encoder: a header first, then one record per pushed set, then the index.
#[derive(Debug)]
pub struct Encoder {
    options: EncodeOptions,
    header: Header,
    statics: Vec<usize>,
    movers: Vec<usize>,
    /// The static Gaussians' decoded values, from the first frame on.
    held: Option<Vec<Values>>,
    /// The moving Gaussians' cells one frame before.
    previous: Vec<Cells>,
    /// Bytes written so far: the next record's offset.
    written: u64,
    index: Vec<IndexEntry>,
}

impl Encoder {
    /// An encoder for frames of `gaussian_count` Gaussians, none static, and the header bytes to
    /// send first.
    ///
    /// Fails on options that describe no grid, or more than `u32::MAX` Gaussians.
    pub fn new(
        gaussian_count: usize,
        options: &EncodeOptions,
    ) -> Result<(Self, Vec<u8>), RendererError> {
        Self::with_static_mask(&vec![false; gaussian_count], options)
    }

    /// An encoder for frames of `static_mask.len()` Gaussians, those marked `true` sent once and
    /// held (see the module's "Static Gaussians"), and the header bytes to send first.
    pub fn with_static_mask(
        static_mask: &[bool],
        options: &EncodeOptions,
    ) -> Result<(Self, Vec<u8>), RendererError> {
        options.validate()?;
        if static_mask.len() > MAX_GAUSSIANS {
            return Err(format_error(format!(
                "C4GV holds at most {MAX_GAUSSIANS} Gaussians a frame (a record's length must fit \
                 u32); got {}",
                static_mask.len()
            )));
        }
        let header = Header {
            gaussians: static_mask.len(),
            static_mask: static_mask.to_vec(),
            steps: Steps::for_error(options.position_error),
        };
        let bytes = header.to_bytes();
        let encoder = Self {
            options: *options,
            statics: header.statics(),
            movers: header.movers(),
            header,
            held: None,
            previous: Vec::new(),
            written: bytes.len() as u64,
            index: Vec::new(),
        };
        Ok((encoder, bytes))
    }

    /// The header this encoder wrote.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The bytes of the frame at `time` (seconds): its record, after the static record for the
    /// first frame.
    ///
    /// Fails, and leaves the stream as it was, when the set has another length, when `time` is
    /// not finite or not after the last frame's, when a value breaks the canonical layout or lies
    /// outside the grid's range, or when a static Gaussian moved out of its bounds.
    pub fn push(&mut self, time: f64, set: &GaussianSet) -> Result<Vec<u8>, RendererError> {
        let frame = self.index.len();
        if frame >= MAX_FRAMES {
            return Err(format_error(format!(
                "a C4GV stream holds at most {MAX_FRAMES} frames"
            )));
        }
        if set.len() != self.header.gaussians {
            return Err(format_error(format!(
                "frame {frame} holds {} Gaussians; the stream holds {}",
                set.len(),
                self.header.gaussians
            )));
        }
        check_time(frame, time, self.index.last().map(|e| e.time))?;
        let cells = quantise_set(
            set,
            &self.header.steps,
            POSITION_RANGE * self.options.position_error,
        )?;
        let mut out = Vec::new();
        let held = match &self.held {
            Some(held) => {
                self.check_statics(set, &cells, held)?;
                None
            }
            None => {
                let rows: Vec<Cells> = self.statics.iter().map(|&i| cells[i]).collect();
                let values = rows
                    .iter()
                    .map(|c| reconstruct(c, &self.header.steps))
                    .collect::<Option<Vec<_>>>()
                    .ok_or_else(|| format_error("a rotation quantised to zero".into()))?;
                let body = columns(&rows, |g, k| rows[g][k]);
                self.record(&mut out, KIND_STATIC, &[], &body);
                Some(values)
            }
        };
        let rows: Vec<Cells> = self.movers.iter().map(|&i| cells[i]).collect();
        let keyframe = frame.is_multiple_of(self.options.keyframe_interval as usize);
        let body = if keyframe {
            columns(&rows, |g, k| rows[g][k])
        } else {
            columns(&rows, |g, k| rows[g][k] - self.previous[g][k])
        };
        let kind = if keyframe { KIND_KEYFRAME } else { KIND_DELTA };
        self.index.push(IndexEntry {
            time,
            offset: self.written + out.len() as u64,
            keyframe,
        });
        self.record(&mut out, kind, &time.to_le_bytes(), &body);
        if let Some(values) = held {
            self.held = Some(values);
        }
        self.previous = rows;
        self.written += out.len() as u64;
        Ok(out)
    }

    /// The index record: the stream's last bytes.
    pub fn finish(self) -> Vec<u8> {
        let mut payload = Vec::with_capacity(self.index.len() * INDEX_ENTRY + INDEX_TAIL);
        for entry in &self.index {
            payload.extend_from_slice(&entry.time.to_le_bytes());
            payload.extend_from_slice(&entry.offset.to_le_bytes());
            payload.push(u8::from(entry.keyframe));
        }
        payload.extend_from_slice(&self.written.to_le_bytes());
        payload.extend_from_slice(&INDEX_MAGIC);
        let mut out = Vec::with_capacity(RECORD_HEAD + payload.len());
        out.push(KIND_INDEX);
        out.push(CODING_STORED);
        out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        out.extend_from_slice(&payload);
        out
    }

    /// Fails when a static Gaussian has left the bounds of its held values.
    fn check_statics(
        &self,
        set: &GaussianSet,
        cells: &[Cells],
        held: &[Values],
    ) -> Result<(), RendererError> {
        for (&i, values) in self.statics.iter().zip(held) {
            let same = reconstruct(&cells[i], &self.header.steps).as_ref() == Some(values);
            if same {
                continue;
            }
            if let Some(why) = out_of_bounds(set, i, values, self.options.position_error) {
                return Err(RendererError::InvalidGaussian {
                    index: i,
                    reason: format!(
                        "marked static in this C4GV stream, but {why} since the first frame"
                    ),
                });
            }
        }
        Ok(())
    }

    /// Appends a record of `kind` with `head` and the body (its inflated length first), deflated
    /// when that is shorter.
    fn record(&self, out: &mut Vec<u8>, kind: u8, head: &[u8], body: &[u8]) {
        let deflated = (self.options.deflate && !body.is_empty())
            .then(|| deflate(body))
            .flatten()
            .filter(|d| d.len() < body.len());
        let (coding, stored) = match &deflated {
            Some(d) => (CODING_DEFLATE, d.as_slice()),
            None => (CODING_STORED, body),
        };
        // Fits u32: at most 70 bytes a Gaussian of at most MAX_GAUSSIANS.
        let length = head.len() + 4 + stored.len();
        out.push(kind);
        out.push(coding);
        out.extend_from_slice(&(length as u32).to_le_bytes());
        out.extend_from_slice(head);
        out.extend_from_slice(&(body.len() as u32).to_le_bytes());
        out.extend_from_slice(stored);
    }
}

/// Fails when `time` is not finite or not after `last`.
fn check_time(frame: usize, time: f64, last: Option<f64>) -> Result<(), RendererError> {
    if !time.is_finite() {
        return Err(format_error(format!(
            "frame {frame}: time {time} is not finite"
        )));
    }
    if let Some(last) = last.filter(|&last| time <= last) {
        return Err(format_error(format!(
            "frame {frame}: time {time} is not after the frame before's ({last}): frames come in \
             strictly increasing time"
        )));
    }
    Ok(())
}

/// A body: 14 columns of zigzag varints, `value(row, channel)` for every row of each in turn.
fn columns(rows: &[Cells], value: impl Fn(usize, usize) -> i64) -> Vec<u8> {
    let mut out = Vec::with_capacity(rows.len() * CHANNELS * 2);
    for k in 0..CHANNELS {
        for g in 0..rows.len() {
            put_varint(&mut out, zigzag(value(g, k)));
        }
    }
    out
}

/// `body` as raw DEFLATE (`None` if the compressor fails, which writing to memory does not).
fn deflate(body: &[u8]) -> Option<Vec<u8>> {
    let mut encoder = DeflateEncoder::new(Vec::new(), Compression::best());
    encoder.write_all(body).ok()?;
    encoder.finish().ok()
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(u: u64) -> i64 {
    ((u >> 1) as i64) ^ -((u & 1) as i64)
}

/// Per Gaussian of one clip's sets, whether every cell is the same in all of them (at
/// `options`' grid): what [`encode`] sends once. Fails as [`Encoder::push`] would on the sets.
pub fn static_mask<'a>(
    sets: impl IntoIterator<Item = &'a GaussianSet>,
    options: &EncodeOptions,
) -> Result<Vec<bool>, RendererError> {
    options.validate()?;
    let steps = Steps::for_error(options.position_error);
    let range = POSITION_RANGE * options.position_error;
    let mut first: Option<Vec<Cells>> = None;
    let mut mask = Vec::new();
    for (frame, set) in sets.into_iter().enumerate() {
        let cells = quantise_set(set, &steps, range)?;
        match &first {
            None => {
                mask = vec![true; cells.len()];
                first = Some(cells);
            }
            Some(first) if first.len() != cells.len() => {
                return Err(format_error(format!(
                    "frame {frame} holds {} Gaussians; the first holds {}: the sets of one clip \
                     hold the same Gaussians",
                    cells.len(),
                    first.len()
                )));
            }
            Some(first) => {
                for ((m, a), b) in mask.iter_mut().zip(first).zip(&cells) {
                    *m &= a == b;
                }
            }
        }
    }
    Ok(mask)
}

/// The `C4GV` bytes of `frames` (time in seconds, set), all of one length, in strictly
/// increasing time. With [`EncodeOptions::detect_static`], Gaussians whose cells never change
/// are sent once.
pub fn encode<'a>(
    frames: impl IntoIterator<Item = (f64, &'a GaussianSet)>,
    options: &EncodeOptions,
) -> Result<Vec<u8>, RendererError> {
    let frames: Vec<(f64, &GaussianSet)> = frames.into_iter().collect();
    let count = frames.first().map_or(0, |(_, s)| s.len());
    let mask = if options.detect_static {
        static_mask(frames.iter().map(|(_, s)| *s), options)?
    } else {
        vec![false; count]
    };
    let (mut encoder, mut out) = Encoder::with_static_mask(&mask, options)?;
    for (time, set) in frames {
        out.extend(encoder.push(time, set)?);
    }
    out.extend(encoder.finish());
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Reading

/// Where a [`Decoder`] is in the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    Header,
    Static,
    Frames,
    Done,
}

/// The incremental reader: [`feed`](Self::feed) it bytes as they arrive and take the frames
/// whose records are whole with [`next_frame`](Self::next_frame).
#[derive(Debug)]
pub struct Decoder {
    /// Bytes received and not yet read, from `buffer[read..]`.
    buffer: Vec<u8>,
    read: usize,
    /// The stream offset of `buffer[read]`.
    position: u64,
    stage: Stage,
    header: Option<Header>,
    /// The header's steps (placeholders until it is read).
    steps: Steps,
    statics: Vec<usize>,
    movers: Vec<usize>,
    held: Vec<Values>,
    previous: Option<Vec<Cells>>,
    /// Frames in the stream before the first this decoder read (a seek's keyframe).
    skipped: usize,
    /// The frames read, as the index must list them.
    seen: Vec<IndexEntry>,
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// A decoder at the start of a stream.
    pub fn new() -> Self {
        Self {
            buffer: Vec::new(),
            read: 0,
            position: 0,
            stage: Stage::Header,
            header: None,
            steps: Steps::for_error(1.0),
            statics: Vec::new(),
            movers: Vec::new(),
            held: Vec::new(),
            previous: None,
            skipped: 0,
            seen: Vec::new(),
        }
    }

    /// The header, once it has arrived.
    pub fn header(&self) -> Option<&Header> {
        self.header.as_ref()
    }

    /// Whether the index record has been read: the stream is complete.
    pub fn is_done(&self) -> bool {
        self.stage == Stage::Done
    }

    /// Takes the next bytes of the stream.
    pub fn feed(&mut self, bytes: &[u8]) {
        if self.read > 0 && self.read >= self.buffer.len() / 2 {
            self.buffer.drain(..self.read);
            self.read = 0;
        }
        self.buffer.extend_from_slice(bytes);
    }

    /// The next frame (time, set) if its record has arrived whole; `None` while more bytes are
    /// needed, and after the index.
    pub fn next_frame(&mut self) -> Result<Option<(f64, GaussianSet)>, RendererError> {
        loop {
            let pending = &self.buffer[self.read..];
            match self.stage {
                Stage::Header => {
                    let Some((header, length)) = Header::parse(pending)? else {
                        return Ok(None);
                    };
                    self.statics = header.statics();
                    self.movers = header.movers();
                    self.steps = header.steps;
                    self.header = Some(header);
                    self.consume(length);
                    self.stage = Stage::Static;
                }
                Stage::Done => {
                    if !pending.is_empty() {
                        return Err(format_error(format!(
                            "{} bytes after the index record, which ends a stream",
                            pending.len()
                        )));
                    }
                    return Ok(None);
                }
                Stage::Static | Stage::Frames => {
                    let Some((kind, coding, length)) = self.record_head()? else {
                        return Ok(None);
                    };
                    let Some(payload) = pending.get(RECORD_HEAD..RECORD_HEAD + length) else {
                        return Ok(None);
                    };
                    let payload = payload.to_vec();
                    let offset = self.position;
                    self.consume(RECORD_HEAD + length);
                    match kind {
                        KIND_STATIC => self.read_static(coding, &payload)?,
                        KIND_INDEX => self.read_index(&payload)?,
                        _ => return self.read_frame(offset, kind, coding, &payload).map(Some),
                    }
                }
            }
        }
    }

    /// Fails unless the stream has ended with its index and nothing after it.
    pub fn finish(&self) -> Result<(), RendererError> {
        let pending = self.buffer.len() - self.read;
        match self.stage {
            Stage::Done if pending == 0 => Ok(()),
            Stage::Done => Err(format_error(format!(
                "{pending} bytes after the index record, which ends a stream"
            ))),
            Stage::Header => Err(format_error(format!(
                "truncated: the stream ended inside its header ({pending} bytes)"
            ))),
            Stage::Static | Stage::Frames => Err(format_error(format!(
                "truncated: the stream ended after {} frames{}, before its index record",
                self.skipped + self.seen.len(),
                if pending > 0 {
                    format!(" and {pending} bytes of an incomplete record")
                } else {
                    String::new()
                }
            ))),
        }
    }

    fn consume(&mut self, bytes: usize) {
        self.read += bytes;
        self.position += bytes as u64;
    }

    /// The kind, coding and payload length of the record at the read position, once its 6 bytes
    /// are here, with the length checked against what that kind of record can hold.
    fn record_head(&self) -> Result<Option<(u8, u8, usize)>, RendererError> {
        let Some(head) = self.buffer[self.read..].get(..RECORD_HEAD) else {
            return Ok(None);
        };
        let (kind, coding, length) = (head[0], head[1], read_u32(&head[2..]) as usize);
        let frames = self.skipped + self.seen.len();
        let at = self.position;
        let (min, max) = match (self.stage, kind) {
            (Stage::Static, KIND_STATIC) => body_range(STATIC_HEAD, self.statics.len()),
            (Stage::Frames, KIND_KEYFRAME | KIND_DELTA) => {
                body_range(FRAME_HEAD, self.movers.len())
            }
            (Stage::Static | Stage::Frames, KIND_INDEX) => {
                let exact = frames
                    .checked_mul(INDEX_ENTRY)
                    .and_then(|b| b.checked_add(INDEX_TAIL));
                (exact, exact)
            }
            (Stage::Static, KIND_KEYFRAME | KIND_DELTA) => {
                return Err(format_error(format!(
                    "the record at byte {at} is a frame, but the static record comes first"
                )));
            }
            (Stage::Frames, KIND_STATIC) => {
                return Err(format_error(format!("a second static record at byte {at}")));
            }
            _ => {
                return Err(format_error(format!(
                    "unknown record kind {kind} at byte {at}"
                )));
            }
        };
        if coding > CODING_DEFLATE || (kind == KIND_INDEX && coding != CODING_STORED) {
            return Err(format_error(format!(
                "record at byte {at}: unknown body coding {coding}"
            )));
        }
        let fits = min.is_some_and(|min| length >= min) && max.is_none_or(|max| length <= max);
        if !fits {
            return Err(format_error(format!(
                "record at byte {at} (kind {kind}) claims {length} bytes: {}",
                match (min, max) {
                    (Some(min), Some(max)) if min == max => format!("it must hold {min}"),
                    (Some(min), Some(max)) => format!("it must hold {min} to {max}"),
                    _ => "too large".to_owned(),
                }
            )));
        }
        Ok(Some((kind, coding, length)))
    }

    fn read_static(&mut self, coding: u8, payload: &[u8]) -> Result<(), RendererError> {
        let what = "the static record";
        let rows = read_body(coding, payload, self.statics.len(), what)?;
        check_cells(&rows, &self.statics, what)?;
        let steps = self.steps;
        self.held = rows
            .iter()
            .zip(&self.statics)
            .map(|(cells, &i)| {
                reconstruct(cells, &steps).ok_or_else(|| zero_rotation("the static record", i))
            })
            .collect::<Result<_, _>>()?;
        self.stage = Stage::Frames;
        Ok(())
    }

    fn read_frame(
        &mut self,
        offset: u64,
        kind: u8,
        coding: u8,
        payload: &[u8],
    ) -> Result<(f64, GaussianSet), RendererError> {
        let frame = self.skipped + self.seen.len();
        let what = format!("frame {frame} (byte {offset})");
        let time = read_f64(payload);
        check_time(frame, time, self.seen.last().map(|e| e.time))?;
        let values = read_body(coding, &payload[8..], self.movers.len(), &what)?;
        let keyframe = kind == KIND_KEYFRAME;
        let rows = if keyframe {
            check_cells(&values, &self.movers, &what)?;
            values
        } else {
            let Some(previous) = &self.previous else {
                return Err(format_error(format!(
                    "{what} is a delta frame, but no keyframe came before it"
                )));
            };
            let mut rows = Vec::with_capacity(values.len());
            for (g, residuals) in values.iter().enumerate() {
                let mut cells = [0i64; CHANNELS];
                for k in 0..CHANNELS {
                    let cell = previous[g][k] + residuals[k];
                    if cell.abs() >= CELL_LIMIT {
                        return Err(format_error(format!(
                            "{what}: Gaussian {}'s cell {cell} is outside ±2^30",
                            self.movers[g]
                        )));
                    }
                    cells[k] = cell;
                }
                rows.push(cells);
            }
            rows
        };
        let set = self.assemble(&rows, &what)?;
        self.previous = Some(rows);
        self.seen.push(IndexEntry {
            time,
            offset,
            keyframe,
        });
        Ok((time, set))
    }

    /// The whole set of a frame: the moving Gaussians' `rows` among the held static ones,
    /// validated.
    fn assemble(&self, rows: &[Cells], what: &str) -> Result<GaussianSet, RendererError> {
        let n = self.statics.len() + rows.len();
        let steps = self.steps;
        let mut values = vec![None; n];
        for (&i, v) in self.statics.iter().zip(&self.held) {
            values[i] = Some(*v);
        }
        for (&i, cells) in self.movers.iter().zip(rows) {
            values[i] = Some(reconstruct(cells, &steps).ok_or_else(|| zero_rotation(what, i))?);
        }
        let values: Vec<Values> = values.into_iter().flatten().collect();
        let set = GaussianSet::new(
            values.iter().map(|v| v.position).collect(),
            values.iter().map(|v| v.scale).collect(),
            values.iter().map(|v| v.rotation).collect(),
            values.iter().map(|v| v.opacity).collect(),
            values.iter().map(|v| v.color).collect(),
        )?;
        set.validate()
            .map_err(|e| format_error(format!("{what} decodes to an invalid set: {e}")))?;
        Ok(set)
    }

    fn read_index(&mut self, payload: &[u8]) -> Result<(), RendererError> {
        let entries = parse_index(payload, self.position)?;
        let listed = entries.get(self.skipped..).unwrap_or_default();
        if listed != self.seen.as_slice() {
            let first = listed
                .iter()
                .zip(&self.seen)
                .position(|(a, b)| a != b)
                .map_or(listed.len().min(self.seen.len()), |k| k);
            return Err(format_error(format!(
                "the index does not list the frames as they came (first difference at frame {})",
                self.skipped + first
            )));
        }
        self.stage = Stage::Done;
        Ok(())
    }

    /// Skips to the keyframe record at `offset`, frame `frame` of the stream (for [`seek`]).
    fn skip_to(&mut self, offset: u64, frame: usize) {
        self.buffer.clear();
        self.read = 0;
        self.position = offset;
        self.skipped = frame;
        self.previous = None;
    }
}

/// The smallest and largest payload of a record with `head` bytes (the inflated length's
/// included) before a body of `count` Gaussians (`None`: beyond `usize`). A deflated body may be
/// far shorter than 14 bytes a Gaussian, but is empty only when there is nothing to send.
fn body_range(head: usize, count: usize) -> (Option<usize>, Option<usize>) {
    let max = count
        .checked_mul(CHANNELS * VARINT_MAX)
        .and_then(|b| b.checked_add(head));
    (Some(head + usize::from(count > 0)), max)
}

/// The cells of `count` Gaussians from a record body: `u32` inflated length, then the stored or
/// deflated columns.
fn read_body(
    coding: u8,
    payload: &[u8],
    count: usize,
    what: &str,
) -> Result<Vec<Cells>, RendererError> {
    let raw = read_u32(payload) as usize;
    let stored = &payload[4..];
    // `count` is bounded by bytes received (the header's mask), so these do not overflow.
    let (min, max) = (
        count.saturating_mul(CHANNELS),
        count.saturating_mul(CHANNELS * VARINT_MAX),
    );
    if raw < min || raw > max {
        return Err(format_error(format!(
            "{what}: a body of {count} Gaussians inflates to {min} to {max} bytes; it claims {raw}"
        )));
    }
    let inflated;
    let body = match coding {
        CODING_STORED => {
            if stored.len() != raw {
                return Err(format_error(format!(
                    "{what}: a stored body of {raw} bytes holds {}",
                    stored.len()
                )));
            }
            stored
        }
        _ => {
            inflated = inflate(stored, raw, what)?;
            &inflated
        }
    };
    let mut rows = vec![[0i64; CHANNELS]; count];
    let mut at = 0;
    for k in 0..CHANNELS {
        for row in rows.iter_mut() {
            let (value, used) = read_varint(&body[at..]).ok_or_else(|| {
                format_error(format!("{what}: a varint is cut short or too long"))
            })?;
            at += used;
            row[k] = unzigzag(value);
        }
    }
    if at != body.len() {
        return Err(format_error(format!(
            "{what}: {} bytes after the last value",
            body.len() - at
        )));
    }
    Ok(rows)
}

/// Fails when a cell of `rows` (the Gaussians `ids`) is outside ±2³⁰.
fn check_cells(rows: &[Cells], ids: &[usize], what: &str) -> Result<(), RendererError> {
    for (cells, &i) in rows.iter().zip(ids) {
        if let Some(cell) = cells.iter().find(|c| c.abs() >= CELL_LIMIT) {
            return Err(format_error(format!(
                "{what}: Gaussian {i}'s cell {cell} is outside ±2^30"
            )));
        }
    }
    Ok(())
}

/// Inflates a raw DEFLATE stream that must fill `stored` exactly and give `raw` bytes.
fn inflate(stored: &[u8], raw: usize, what: &str) -> Result<Vec<u8>, RendererError> {
    if stored.len() >= raw {
        return Err(format_error(format!(
            "{what}: a deflated body of {} bytes is not shorter than its {raw} bytes inflated",
            stored.len()
        )));
    }
    let mut decoder = DeflateDecoder::new(stored);
    let mut out = Vec::with_capacity(raw.min(stored.len().saturating_mul(INFLATE_RATIO)));
    let read = (&mut decoder)
        .take(raw as u64 + 1)
        .read_to_end(&mut out)
        .map_err(|e| format_error(format!("{what}: corrupt DEFLATE data ({e})")))?;
    if read != raw {
        return Err(format_error(format!(
            "{what}: the body inflates to {}{read} bytes; its record says {raw}",
            if read > raw { "more than " } else { "" }
        )));
    }
    if decoder.total_in() != stored.len() as u64 {
        return Err(format_error(format!(
            "{what}: {} bytes after the DEFLATE stream",
            stored.len() as u64 - decoder.total_in()
        )));
    }
    Ok(out)
}

/// An unsigned LEB128 varint of at most 5 bytes and the bytes it used.
fn read_varint(bytes: &[u8]) -> Option<(u64, usize)> {
    let mut value = 0u64;
    for (i, &b) in bytes.iter().take(VARINT_MAX).enumerate() {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            return Some((value, i + 1));
        }
    }
    None
}

/// The index record's entries, checked: times finite and increasing, offsets increasing and
/// before the record (at `end`, the offset just past it, minus its length).
fn parse_index(payload: &[u8], end: u64) -> Result<Vec<IndexEntry>, RendererError> {
    let (entries, tail) = payload.split_at(payload.len() - INDEX_TAIL);
    if tail[8..] != INDEX_MAGIC {
        return Err(format_error(
            "the index record does not end with C4GI".into(),
        ));
    }
    let own = read_u64(tail);
    let expected = end.saturating_sub((RECORD_HEAD + payload.len()) as u64);
    if own != expected {
        return Err(format_error(format!(
            "the index record says it starts at byte {own}; it starts at {expected}"
        )));
    }
    let mut out: Vec<IndexEntry> = Vec::with_capacity(entries.len() / INDEX_ENTRY);
    for (k, e) in entries.chunks_exact(INDEX_ENTRY).enumerate() {
        let entry = IndexEntry {
            time: read_f64(e),
            offset: read_u64(&e[8..]),
            keyframe: match e[16] {
                0 => false,
                1 => true,
                other => {
                    return Err(format_error(format!(
                        "index entry {k}: keyframe flag {other} (0 or 1)"
                    )));
                }
            },
        };
        check_time(k, entry.time, out.last().map(|e| e.time))
            .map_err(|e| format_error(format!("the index: {e}")))?;
        let previous = out.last().map_or(0, |e| e.offset);
        if (k > 0 && entry.offset <= previous) || entry.offset >= own {
            return Err(format_error(format!(
                "index entry {k}: offset {} is out of order or past the index",
                entry.offset
            )));
        }
        if k == 0 && !entry.keyframe {
            return Err(format_error(
                "the index's first frame is not a keyframe".into(),
            ));
        }
        out.push(entry);
    }
    Ok(out)
}

/// The frames of a whole `C4GV` stream (time in seconds, set).
pub fn decode(bytes: &[u8]) -> Result<Vec<(f64, GaussianSet)>, RendererError> {
    let mut decoder = Decoder::new();
    decoder.feed(bytes);
    let mut frames = Vec::new();
    while let Some(frame) = decoder.next_frame()? {
        frames.push(frame);
    }
    decoder.finish()?;
    Ok(frames)
}

/// The index of a whole `C4GV` stream, read from its end: one entry per frame.
pub fn read_index(bytes: &[u8]) -> Result<Vec<IndexEntry>, RendererError> {
    let truncated = || {
        format_error(format!(
            "a complete C4GV stream ends with an index record; these {} bytes do not",
            bytes.len()
        ))
    };
    let tail = bytes
        .len()
        .checked_sub(INDEX_TAIL)
        .and_then(|at| bytes.get(at..))
        .ok_or_else(truncated)?;
    if tail[8..] != INDEX_MAGIC {
        return Err(truncated());
    }
    let at = usize::try_from(read_u64(tail)).map_err(|_| truncated())?;
    let record = bytes
        .get(at..)
        .filter(|r| r.len() >= RECORD_HEAD + INDEX_TAIL)
        .ok_or_else(truncated)?;
    let length = read_u32(&record[2..]) as usize;
    if record[0] != KIND_INDEX
        || record[1] != CODING_STORED
        || length != record.len() - RECORD_HEAD
        || !(length - INDEX_TAIL).is_multiple_of(INDEX_ENTRY)
    {
        return Err(format_error(format!(
            "the stream's last bytes point at byte {at}, which holds no index record"
        )));
    }
    parse_index(&record[RECORD_HEAD..], bytes.len() as u64)
}

/// The frames of a whole `C4GV` stream from the last one at or before `time` (the first frame
/// when `time` is before it) to the end. Reads the header, the static record, the index and the
/// records from the keyframe before that frame on; nothing else.
pub fn seek(bytes: &[u8], time: f64) -> Result<Vec<(f64, GaussianSet)>, RendererError> {
    if time.is_nan() {
        return Err(format_error("cannot seek to a NaN time".into()));
    }
    let index = read_index(bytes)?;
    let Some(first) = index.first() else {
        return Ok(Vec::new());
    };
    let target = index.partition_point(|e| e.time <= time).saturating_sub(1);
    let Some(key) = index[..=target].iter().rposition(|e| e.keyframe) else {
        return Err(format_error("the index lists no keyframe".into()));
    };
    let start = |offset: u64| {
        usize::try_from(offset)
            .ok()
            .filter(|&o| o <= bytes.len())
            .ok_or_else(|| format_error(format!("index offset {offset} is past the stream")))
    };
    let mut decoder = Decoder::new();
    decoder.feed(&bytes[..start(first.offset)?]);
    if decoder.next_frame()?.is_some() || decoder.stage != Stage::Frames {
        return Err(format_error(format!(
            "the first frame's record is not at byte {} (the index's)",
            first.offset
        )));
    }
    decoder.skip_to(index[key].offset, key);
    decoder.feed(&bytes[start(index[key].offset)?..]);
    let mut frames = Vec::new();
    while let Some(frame) = decoder.next_frame()? {
        if decoder.skipped + decoder.seen.len() > target {
            frames.push(frame);
        }
    }
    decoder.finish()?;
    Ok(frames)
}

fn zero_rotation(what: &str, gaussian: usize) -> RendererError {
    format_error(format!(
        "{what}: Gaussian {gaussian}'s rotation decodes to no unit quaternion (zero or not finite)"
    ))
}

fn read_u32(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

fn read_u64(b: &[u8]) -> u64 {
    let mut bytes = [0; 8];
    bytes.copy_from_slice(&b[..8]);
    u64::from_le_bytes(bytes)
}

fn read_f64(b: &[u8]) -> f64 {
    f64::from_bits(read_u64(b))
}

fn format_error(reason: String) -> RendererError {
    RendererError::Format {
        format: "c4gv",
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::{Rng, unit};
    use proptest::prelude::*;

    /// A clip of `frames` sets of `n` Gaussians: the first `still` never change, the others
    /// move smoothly in every attribute.
    fn clip(n: usize, still: usize, frames: usize, seed: u64) -> Vec<(f64, GaussianSet)> {
        let mut rng = Rng(seed);
        let base: Vec<[f32; 16]> = (0..n)
            .map(|_| std::array::from_fn(|_| rng.range(0.0, 1.0)))
            .collect();
        (0..frames)
            .map(|f| {
                let t = f as f64 / 30.0;
                let mut columns = (vec![], vec![], vec![], vec![], vec![]);
                for (i, b) in base.iter().enumerate() {
                    let m = if i < still { 0.0 } else { 1.0 };
                    let w = |k: usize| (f64::from(b[k]) * 6.0 + t * (1.0 + f64::from(b[15]))).sin();
                    let p = |k: usize| (f64::from(b[k]) * 6.0 - 3.0 + m * 0.3 * w(k)) as f32;
                    columns.0.push([p(0), p(1), p(2) + 4.0]);
                    let s =
                        |k: usize| (0.01 + 0.2 * f64::from(b[k]) * (1.0 + m * 0.2 * w(k))) as f32;
                    columns.1.push([s(3), s(4), s(5)]);
                    let q = |k: usize| f64::from(b[k]) - 0.5 + m * 0.1 * w(k);
                    columns.2.push(unit([q(6), q(7), q(8), q(9)]));
                    columns
                        .3
                        .push((f64::from(b[10]) * (1.0 - m * 0.1 * (1.0 + w(10)) / 2.0)) as f32);
                    let c = |k: usize| (f64::from(b[k]) * (1.0 - m * 0.05 * (1.0 + w(k)))) as f32;
                    columns.4.push([c(11), c(12), c(13)]);
                }
                let set = GaussianSet::new(columns.0, columns.1, columns.2, columns.3, columns.4)
                    .unwrap();
                set.validate().unwrap();
                (t, set)
            })
            .collect()
    }

    fn refs(frames: &[(f64, GaussianSet)]) -> impl Iterator<Item = (f64, &GaussianSet)> {
        frames.iter().map(|(t, s)| (*t, s))
    }

    fn options(position_error: f64) -> EncodeOptions {
        EncodeOptions {
            position_error,
            ..EncodeOptions::default()
        }
    }

    /// The largest error of each channel group of `decoded` against `original`, in f64:
    /// position (scene units), scale (relative, or absolute below the floor), rotation
    /// (radians), opacity, colour.
    fn errors(original: &GaussianSet, decoded: &GaussianSet) -> [f64; 5] {
        assert_eq!(original.len(), decoded.len());
        let mut worst = [0.0f64; 5];
        let diff = |a: f32, b: f32| (f64::from(a) - f64::from(b)).abs();
        for i in 0..original.len() {
            for k in 0..3 {
                worst[0] =
                    worst[0].max(diff(original.positions()[i][k], decoded.positions()[i][k]));
                worst[1] =
                    worst[1].max(scale_error(original.scales()[i][k], decoded.scales()[i][k]));
                worst[4] = worst[4].max(diff(original.colors()[i][k], decoded.colors()[i][k]));
            }
            worst[2] = worst[2].max(rotation_angle(
                original.rotations()[i],
                decoded.rotations()[i],
            ));
            worst[3] = worst[3].max(diff(original.opacities()[i], decoded.opacities()[i]));
        }
        worst
    }

    fn assert_within_bounds(original: &GaussianSet, decoded: &GaussianSet, position_error: f64) {
        let [p, s, r, o, c] = errors(original, decoded);
        assert!(p <= position_error, "position error {p} > {position_error}");
        assert!(s <= SCALE_ERROR, "scale error {s}");
        assert!(r <= ROTATION_ERROR, "rotation error {r}");
        assert!(o <= OPACITY_ERROR, "opacity error {o}");
        assert!(c <= COLOR_ERROR, "colour error {c}");
        decoded.validate().unwrap();
    }

    fn reason(err: RendererError) -> String {
        match err {
            RendererError::Format { format, reason } => {
                assert_eq!(format, "c4gv");
                reason
            }
            other => panic!("expected a C4GV format error, got {other:?}"),
        }
    }

    fn set_of(positions: Vec<[f32; 3]>) -> GaussianSet {
        let n = positions.len();
        GaussianSet::new(
            positions,
            vec![[0.1; 3]; n],
            vec![[1.0, 0.0, 0.0, 0.0]; n],
            vec![0.5; n],
            vec![[0.25; 3]; n],
        )
        .unwrap()
    }

    #[test]
    fn binary_layout_is_as_documented() {
        let set = set_of(vec![[0.5, -1.0, 2.0]]);
        let opts = EncodeOptions {
            deflate: false,
            ..options(1e-3)
        };
        let bytes = encode([(0.25, &set)], &opts).unwrap();
        assert_eq!(&bytes[..4], b"C4GV");
        assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 1);
        assert_eq!((bytes[6], bytes[7]), (0, 0), "predictor 0, reserved 0");
        assert_eq!(read_u32(&bytes[8..]), 1, "N");
        assert_eq!(
            read_u32(&bytes[12..]),
            1,
            "one frame: every Gaussian is static"
        );
        assert_eq!(read_f64(&bytes[16..]), 1.875e-3);
        assert_eq!(read_f64(&bytes[24..]), 1.0 / 1024.0);
        assert_eq!(read_f64(&bytes[32..]), 1.0 / 4096.0);
        assert_eq!(read_f64(&bytes[40..]), 1.0 / 1023.0);
        assert_eq!(read_f64(&bytes[48..]), 1.0 / 1023.0);
        assert_eq!(bytes[56], 1, "the static mask");
        // The static record: kind, coding, length, inflated length, 14 varints.
        let st = 57;
        assert_eq!((bytes[st], bytes[st + 1]), (KIND_STATIC, CODING_STORED));
        let body_len = read_u32(&bytes[st + 6..]) as usize;
        assert_eq!(read_u32(&bytes[st + 2..]) as usize, 4 + body_len);
        let body = &bytes[st + 10..st + 10 + body_len];
        let mut values = vec![];
        let mut at = 0;
        while at < body.len() {
            let (v, used) = read_varint(&body[at..]).unwrap();
            values.push(unzigzag(v));
            at += used;
        }
        let ln = |s: f64| (s.ln() * 1024.0).round() as i64;
        assert_eq!(
            values,
            [
                267,
                -533,
                1067, // 0.5 / 1.875e-3 and so on
                ln(0.1f32 as f64),
                ln(0.1f32 as f64),
                ln(0.1f32 as f64),
                4096,
                0,
                0,
                0,
                512, // round(0.5 · 1023)
                256,
                256,
                256, // round(0.25 · 1023)
            ]
        );
        // The keyframe: no moving Gaussian, so an empty body.
        let kf = st + 10 + body_len;
        assert_eq!(
            &bytes[kf..kf + 6],
            &[KIND_KEYFRAME, CODING_STORED, 12, 0, 0, 0]
        );
        assert_eq!(read_f64(&bytes[kf + 6..]), 0.25);
        assert_eq!(read_u32(&bytes[kf + 14..]), 0);
        // The index: one entry, its own offset, the magic.
        let ix = kf + 18;
        assert_eq!(
            &bytes[ix..ix + 6],
            &[KIND_INDEX, CODING_STORED, 29, 0, 0, 0]
        );
        assert_eq!(read_f64(&bytes[ix + 6..]), 0.25);
        assert_eq!(read_u64(&bytes[ix + 14..]), kf as u64);
        assert_eq!(bytes[ix + 22], 1);
        assert_eq!(read_u64(&bytes[ix + 23..]), ix as u64);
        assert_eq!(&bytes[ix + 31..], b"C4GI");
        assert_eq!(read_index(&bytes).unwrap()[0].offset, kf as u64);
    }

    #[test]
    fn round_trip_meets_every_stated_bound() {
        let frames = clip(64, 16, 40, 7);
        for e in [1e-2, 1e-3, 1e-4, 1e-5] {
            let bytes = encode(refs(&frames), &options(e)).unwrap();
            let back = decode(&bytes).unwrap();
            assert_eq!(back.len(), frames.len());
            for ((t, set), (tb, decoded)) in frames.iter().zip(&back) {
                assert_eq!(t, tb);
                assert_within_bounds(set, decoded, e);
            }
        }
    }

    #[test]
    fn the_bounds_hold_at_the_edges_of_every_range() {
        let e = 1e-3;
        let edge = (POSITION_RANGE * e) as f32;
        let set = GaussianSet::new(
            vec![
                [edge, -edge, 0.0],
                [999.9991, -0.000_937_4, 1e-30],
                [0.0; 3],
            ],
            vec![
                [0.0, SCALE_FLOOR / 3.0, f32::MAX],
                [f32::MIN_POSITIVE, 1e-10, 1e30],
                [1.0; 3],
            ],
            vec![
                [1.0009, 0.0, 0.0, 0.0],
                unit([0.5, -0.5, 0.5, -0.5]),
                unit([1e-6, 0.7, -0.7, 1e-3]),
            ],
            vec![0.0, 1.0, 0.5 / 1023.0],
            vec![
                [0.0, COLOR_MAX, 1.0],
                [15.999, 1.0 / 2046.0, 0.999],
                [0.0; 3],
            ],
        )
        .unwrap();
        set.validate().unwrap();
        let bytes = encode([(0.0, &set), (1.0, &set)], &options(e)).unwrap();
        for (_, decoded) in decode(&bytes).unwrap() {
            assert_within_bounds(&set, &decoded, e);
            assert!(decoded.scales()[0][0] > 0.0 && decoded.scales()[0][0] < 6e-20);
        }
    }

    #[test]
    fn values_outside_the_grid_or_the_layout_are_refused_by_the_encoder() {
        let e = 1e-3;
        let beyond = (POSITION_RANGE * e * 1.001) as f32;
        let (mut encoder, _) = Encoder::new(2, &options(e)).unwrap();
        let cases: Vec<(GaussianSet, &str)> = vec![
            (
                set_of(vec![[0.0; 3], [0.0, beyond, 0.0]]),
                "beyond C4GV's range",
            ),
            (set_of(vec![[0.0; 3], [f32::NAN, 0.0, 0.0]]), "not finite"),
            (
                set_of(vec![[0.0; 3], [f32::INFINITY, 0.0, 0.0]]),
                "not finite",
            ),
            (
                GaussianSet::new(
                    vec![[0.0; 3]; 2],
                    vec![[0.1; 3]; 2],
                    vec![[1.0, 0.0, 0.0, 0.0]; 2],
                    vec![0.5; 2],
                    vec![[0.0; 3], [16.5, 0.0, 0.0]],
                )
                .unwrap(),
                "beyond C4GV's range (0 to 16)",
            ),
            (
                GaussianSet::new(
                    vec![[0.0; 3]; 2],
                    vec![[0.1; 3], [f32::INFINITY, 0.1, 0.1]],
                    vec![[1.0, 0.0, 0.0, 0.0]; 2],
                    vec![0.5; 2],
                    vec![[0.0; 3]; 2],
                )
                .unwrap(),
                "scale",
            ),
        ];
        for (set, expected) in cases {
            match encoder.push(0.0, &set).unwrap_err() {
                RendererError::InvalidGaussian { index, reason } => {
                    assert_eq!(index, 1);
                    assert!(reason.contains(expected), "{reason}");
                }
                other => panic!("unexpected {other:?}"),
            }
        }
        // Nothing was written: the encoder still starts with a keyframe at any time.
        let ok = encoder.push(-5.0, &set_of(vec![[0.0; 3]; 2])).unwrap();
        assert_eq!(ok[0], KIND_STATIC);
    }

    #[test]
    fn a_bound_of_zero_negative_or_not_finite_and_a_zero_keyframe_interval_are_refused() {
        for e in [0.0, -1e-3, f64::NAN, f64::INFINITY] {
            let err = Encoder::new(1, &options(e)).unwrap_err();
            assert!(reason(err).contains("finite and positive"));
            let set = set_of(vec![[0.0; 3]]);
            assert!(encode([(0.0, &set)], &options(e)).is_err());
        }
        let opts = EncodeOptions {
            keyframe_interval: 0,
            ..options(1e-3)
        };
        assert!(reason(Encoder::new(1, &opts).unwrap_err()).contains("keyframe interval"));
    }

    #[test]
    fn frames_of_another_length_or_out_of_time_order_are_refused() {
        let (mut encoder, _) = Encoder::new(2, &options(1e-3)).unwrap();
        let two = set_of(vec![[0.0; 3]; 2]);
        let err = encoder.push(0.0, &set_of(vec![[0.0; 3]])).unwrap_err();
        assert!(reason(err).contains("frame 0 holds 1 Gaussians; the stream holds 2"));
        encoder.push(1.0, &two).unwrap();
        for t in [1.0, 0.5, f64::NAN, f64::INFINITY] {
            assert!(reason(encoder.push(t, &two).unwrap_err()).contains("time"));
        }
        encoder.push(1.5, &two).unwrap();
    }

    #[test]
    fn the_loop_is_closed_a_frame_decodes_the_same_however_far_from_its_keyframe() {
        // 201 frames of a random walk of every attribute; frame 200 is frame 1's set again.
        let mut frames = clip(32, 0, 201, 3);
        let mut rng = Rng(11);
        for f in 2..200 {
            let (_, previous) = &frames[f - 1];
            let mut walk = |v: f32, size: f64| v + rng.range(-size, size);
            let mut p = previous.positions().to_vec();
            p.iter_mut().flatten().for_each(|v| *v = walk(*v, 0.01));
            let set = GaussianSet::new(
                p,
                frames[f].1.scales().to_vec(),
                frames[f].1.rotations().to_vec(),
                frames[f].1.opacities().to_vec(),
                frames[f].1.colors().to_vec(),
            )
            .unwrap();
            frames[f].1 = set;
        }
        frames[200].1 = frames[1].1.clone();
        let e = 1e-3;
        let opts = EncodeOptions {
            keyframe_interval: 1000,
            ..options(e)
        };
        let bytes = encode(refs(&frames), &opts).unwrap();
        let back = decode(&bytes).unwrap();
        // Frame 200 is 199 deltas from the only keyframe and decodes exactly as frame 1.
        assert_eq!(back[200].1, back[1].1);
        let (first, last) = (
            errors(&frames[1].1, &back[1].1),
            errors(&frames[200].1, &back[200].1),
        );
        assert!(
            last[0] <= first[0] && last[0] <= e,
            "{last:?} against {first:?}"
        );
        // And every frame is what coding it alone, as a keyframe, gives.
        let alone = EncodeOptions {
            keyframe_interval: 1,
            ..opts
        };
        assert_eq!(
            decode(&encode(refs(&frames), &alone).unwrap()).unwrap(),
            back
        );
    }

    #[test]
    fn seeking_from_every_keyframe_gives_the_sets_decoding_from_the_start_gives() {
        let frames = clip(40, 10, 37, 5);
        let opts = EncodeOptions {
            keyframe_interval: 8,
            ..options(1e-3)
        };
        let bytes = encode(refs(&frames), &opts).unwrap();
        let all = decode(&bytes).unwrap();
        let index = read_index(&bytes).unwrap();
        assert_eq!(index.len(), 37);
        let keyframes: Vec<usize> = (0..37).filter(|f| index[*f].keyframe).collect();
        assert_eq!(keyframes, [0, 8, 16, 24, 32]);
        for (f, entry) in index.iter().enumerate() {
            assert_eq!(entry.time, frames[f].0);
            assert_eq!(seek(&bytes, entry.time).unwrap(), all[f..], "frame {f}");
            // Between two frames: from the earlier.
            let between = entry.time + 0.5 / 30.0;
            assert_eq!(seek(&bytes, between).unwrap(), all[f..]);
        }
        assert_eq!(seek(&bytes, -1.0).unwrap(), all);
        assert_eq!(seek(&bytes, f64::NEG_INFINITY).unwrap(), all);
        assert_eq!(seek(&bytes, f64::INFINITY).unwrap(), all[36..]);
        assert!(seek(&bytes, f64::NAN).is_err());
    }

    #[test]
    fn seeking_reads_nothing_before_the_keyframe() {
        let frames = clip(20, 0, 20, 8);
        let opts = EncodeOptions {
            keyframe_interval: 10,
            ..options(1e-3)
        };
        let mut bytes = encode(refs(&frames), &opts).unwrap();
        let all = decode(&bytes).unwrap();
        let index = read_index(&bytes).unwrap();
        // Spoil frames 1 to 9: a seek to frame 12 never reads them.
        for b in &mut bytes[index[1].offset as usize..index[10].offset as usize] {
            *b = 0xAA;
        }
        assert_eq!(seek(&bytes, frames[12].0).unwrap(), all[12..]);
        assert!(decode(&bytes).is_err());
    }

    #[test]
    fn an_all_static_clip_costs_one_set_and_tiny_frames() {
        let frames = clip(100, 100, 50, 2);
        let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        let header = HEADER_BYTES + 100usize.div_ceil(8);
        let one = encode(refs(&frames[..1]), &options(1e-3)).unwrap();
        // One frame's stream: the header, the static record, an 18-byte frame, the index.
        let static_record = one.len() - header - 18 - (RECORD_HEAD + INDEX_ENTRY + INDEX_TAIL);
        assert!(
            static_record < 100 * 14 * 3,
            "{static_record} bytes for 100 Gaussians"
        );
        let expected =
            header + static_record + 50 * 18 + RECORD_HEAD + 50 * INDEX_ENTRY + INDEX_TAIL;
        assert_eq!(bytes.len(), expected);
        for ((_, set), (_, back)) in frames.iter().zip(decode(&bytes).unwrap()) {
            assert_within_bounds(set, &back, 1e-3);
        }
    }

    #[test]
    fn one_frame_no_gaussians_and_no_frames_round_trip() {
        let frames = clip(5, 0, 1, 4);
        let back = decode(&encode(refs(&frames), &options(1e-3)).unwrap()).unwrap();
        assert_eq!(back.len(), 1);
        assert_within_bounds(&frames[0].1, &back[0].1, 1e-3);

        let empty = GaussianSet::default();
        let sets = [(0.0, &empty), (0.5, &empty), (1.0, &empty)];
        let back = decode(&encode(sets, &options(1e-3)).unwrap()).unwrap();
        assert_eq!(
            back,
            [
                (0.0, empty.clone()),
                (0.5, empty.clone()),
                (1.0, empty.clone())
            ]
        );

        let none = encode(std::iter::empty(), &options(1e-3)).unwrap();
        assert_eq!(none.len(), HEADER_BYTES + RECORD_HEAD + INDEX_TAIL);
        assert!(decode(&none).unwrap().is_empty());
        assert!(seek(&none, 0.0).unwrap().is_empty());
    }

    #[test]
    fn deflate_changes_the_bytes_not_the_sets() {
        let frames = clip(64, 8, 20, 9);
        let on = encode(refs(&frames), &options(1e-3)).unwrap();
        let off = encode(
            refs(&frames),
            &EncodeOptions {
                deflate: false,
                ..options(1e-3)
            },
        )
        .unwrap();
        assert!(on.len() < off.len(), "{} against {}", on.len(), off.len());
        assert_eq!(decode(&on).unwrap(), decode(&off).unwrap());
    }

    #[test]
    fn a_streaming_encoder_holds_masked_gaussians_and_refuses_one_that_moves_too_far() {
        let frames = clip(10, 4, 12, 6);
        let opts = options(1e-3);
        let mask = static_mask(frames.iter().map(|(_, s)| s), &opts).unwrap();
        assert_eq!(
            mask,
            [
                true, true, true, true, false, false, false, false, false, false
            ]
        );
        let (mut encoder, mut bytes) = Encoder::with_static_mask(&mask, &opts).unwrap();
        for (t, set) in &frames {
            bytes.extend(encoder.push(*t, set).unwrap());
        }
        // Gaussian 2 strays 0.9 e from its held position: still held; then 3 e: refused, and
        // the stream stays whole.
        let held = encoder.held.as_ref().unwrap()[2].position;
        let at = |x: f32| {
            let set = &frames[11].1;
            let mut p = set.positions().to_vec();
            p[2] = [x, held[1], held[2]];
            GaussianSet::new(
                p,
                set.scales().to_vec(),
                set.rotations().to_vec(),
                set.opacities().to_vec(),
                set.colors().to_vec(),
            )
            .unwrap()
        };
        let near = at(held[0] + 0.9e-3);
        bytes.extend(encoder.push(2.0, &near).unwrap());
        match encoder.push(3.0, &at(held[0] + 3e-3)).unwrap_err() {
            RendererError::InvalidGaussian { index: 2, reason } => {
                assert!(reason.contains("marked static"), "{reason}");
            }
            other => panic!("unexpected {other:?}"),
        }
        bytes.extend(encoder.finish());
        let back = decode(&bytes).unwrap();
        assert_eq!(back.len(), 13);
        assert_within_bounds(&near, &back[12].1, 1e-3);
        for ((_, set), (_, decoded)) in frames.iter().zip(&back) {
            assert_within_bounds(set, decoded, 1e-3);
        }
    }

    #[test]
    fn a_delta_frame_needs_a_keyframe_before_it() {
        let frames = clip(4, 0, 3, 1);
        let mut bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        let first = read_index(&bytes).unwrap()[0].offset as usize;
        bytes[first] = KIND_DELTA;
        assert!(reason(decode(&bytes).unwrap_err()).contains("no keyframe came before it"));
    }

    #[test]
    fn an_index_that_lies_is_refused() {
        let frames = clip(4, 0, 3, 1);
        let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        let at = bytes.len() - INDEX_TAIL - 2 * INDEX_ENTRY; // frame 1's time
        let mut lying = bytes.clone();
        lying[at..at + 8].copy_from_slice(&0.04f64.to_le_bytes());
        assert!(reason(decode(&lying).unwrap_err()).contains("does not list the frames"));
    }

    #[test]
    fn every_truncation_is_an_error_and_never_a_panic() {
        let frames = clip(12, 3, 6, 10);
        let opts = EncodeOptions {
            keyframe_interval: 4,
            ..options(1e-3)
        };
        let bytes = encode(refs(&frames), &opts).unwrap();
        let all = decode(&bytes).unwrap();
        for cut in 0..bytes.len() {
            let prefix = &bytes[..cut];
            assert!(decode(prefix).is_err(), "prefix of {cut} bytes decoded");
            assert!(read_index(prefix).is_err() || seek(prefix, 0.0).is_err());
            // The incremental decoder hands out exactly the frames whose records are whole.
            let mut decoder = Decoder::new();
            decoder.feed(prefix);
            let mut got = vec![];
            while let Ok(Some(frame)) = decoder.next_frame() {
                got.push(frame);
            }
            assert_eq!(got, all[..got.len()]);
            assert!(decoder.finish().is_err());
        }
    }

    #[test]
    fn every_corrupted_byte_is_an_error_or_valid_sets_never_a_panic() {
        let frames = clip(6, 2, 5, 12);
        let opts = EncodeOptions {
            keyframe_interval: 2,
            ..options(1e-2)
        };
        for deflate in [false, true] {
            let bytes = encode(refs(&frames), &EncodeOptions { deflate, ..opts }).unwrap();
            for at in 0..bytes.len() {
                for flip in [0x01u8, 0x80, 0xFF] {
                    let mut bad = bytes.clone();
                    bad[at] ^= flip;
                    if let Ok(back) = decode(&bad) {
                        back.iter().for_each(|(_, s)| s.validate().unwrap());
                    }
                    let _ = seek(&bad, 0.1);
                }
            }
        }
    }

    #[test]
    fn hostile_lengths_are_refused_before_anything_is_buffered_or_allocated() {
        // A header claiming u32::MAX Gaussians, and nothing else.
        let mut header = Header {
            gaussians: 0,
            static_mask: vec![],
            steps: Steps::for_error(1e-3),
        }
        .to_bytes();
        header[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(reason(decode(&header).unwrap_err()).contains("truncated"));

        // A stream of 2 moving Gaussians whose keyframe claims 4 GiB: refused on its 6 bytes.
        let frames = clip(2, 0, 2, 1);
        let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        let first = read_index(&bytes).unwrap()[0].offset as usize;
        let mut decoder = Decoder::new();
        decoder.feed(&bytes[..first]);
        assert!(decoder.next_frame().unwrap().is_none());
        decoder.feed(&[KIND_KEYFRAME, CODING_STORED, 0xFF, 0xFF, 0xFF, 0xFF]);
        assert!(reason(decoder.next_frame().unwrap_err()).contains("claims 4294967295 bytes"));

        // A body claiming to inflate to more than 70 bytes a Gaussian.
        let mut bad = bytes.clone();
        bad[first + 14..first + 18].copy_from_slice(&1000u32.to_le_bytes());
        assert!(reason(decode(&bad).unwrap_err()).contains("it claims 1000"));

        // Steps that are not finite and positive.
        let mut bad = bytes.clone();
        bad[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
        assert!(reason(decode(&bad).unwrap_err()).contains("grid steps"));
        // Another version; an unknown predictor; a mask that disagrees with S.
        for (at, value, expected) in [
            (4, 2, "version 2"),
            (6, 7, "predictor 7"),
            (12, 1, "static"),
        ] {
            let mut bad = bytes.clone();
            bad[at] = value;
            assert!(reason(decode(&bad).unwrap_err()).contains(expected));
        }
        assert!(reason(decode(b"C4GS....").unwrap_err()).contains("not a C4GV stream"));
    }

    #[test]
    fn bytes_after_the_index_are_refused() {
        let frames = clip(2, 0, 2, 1);
        let mut bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        bytes.push(0);
        assert!(reason(decode(&bytes).unwrap_err()).contains("after the index record"));
    }

    fn any_gaussian() -> impl Strategy<Value = (Vec<f32>, Vec<f32>, Vec<f32>, f32, Vec<f32>)> {
        let e = 1e-3f32;
        let edge = 1e6 * e;
        (
            proptest::collection::vec(-edge..=edge, 3),
            proptest::collection::vec(
                prop_oneof![
                    0.0f32..1e-19,
                    1e-19f32..1e3,
                    proptest::num::f32::POSITIVE | proptest::num::f32::ZERO
                ],
                3,
            ),
            proptest::collection::vec(-1.0f32..1.0, 4).prop_filter("a rotation", |q| {
                q.iter().map(|v| v * v).sum::<f32>() > 1e-6
            }),
            0.0f32..=1.0,
            proptest::collection::vec(0.0f32..=COLOR_MAX, 3),
        )
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn any_valid_set_round_trips_within_the_bounds(
            gaussians in proptest::collection::vec(any_gaussian(), 0..6),
            moves in proptest::collection::vec(-0.05f32..0.05, 1..5),
        ) {
            let frames: Vec<(f64, GaussianSet)> = moves
                .iter()
                .enumerate()
                .map(|(f, &by)| {
                    let set = GaussianSet::new(
                        gaussians.iter().map(|g| [g.0[0], g.0[1], (g.0[2] + by).clamp(-1e3, 1e3)]).collect(),
                        gaussians.iter().map(|g| [g.1[0], g.1[1], g.1[2]]).collect(),
                        gaussians.iter().map(|g| unit(std::array::from_fn(|k| f64::from(g.2[k])))).collect(),
                        gaussians.iter().map(|g| g.3).collect(),
                        gaussians.iter().map(|g| [g.4[0], g.4[1], g.4[2]]).collect(),
                    )
                    .unwrap();
                    (f as f64, set)
                })
                .collect();
            let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
            let back = decode(&bytes).unwrap();
            prop_assert_eq!(back.len(), frames.len());
            for ((_, set), (_, decoded)) in frames.iter().zip(&back) {
                assert_within_bounds(set, decoded, 1e-3);
            }
        }

        #[test]
        fn any_chunking_of_the_bytes_decodes_the_same_frames(
            cuts in proptest::collection::vec(0usize..2000, 0..12),
            seed in 0u64..1000,
        ) {
            let frames = clip(9, 3, 7, seed);
            let opts = EncodeOptions { keyframe_interval: 3, ..options(1e-3) };
            let bytes = encode(refs(&frames), &opts).unwrap();
            let mut cuts: Vec<usize> = cuts.into_iter().map(|c| c % (bytes.len() + 1)).collect();
            cuts.sort_unstable();
            let mut decoder = Decoder::new();
            let (mut got, mut from) = (vec![], 0);
            for cut in cuts.into_iter().chain([bytes.len()]) {
                decoder.feed(&bytes[from..cut]);
                from = cut;
                while let Some(frame) = decoder.next_frame().unwrap() {
                    got.push(frame);
                }
            }
            decoder.finish().unwrap();
            prop_assert_eq!(got, decode(&bytes).unwrap());
        }

        #[test]
        fn arbitrary_bytes_never_panic(tail in proptest::collection::vec(any::<u8>(), 0..400)) {
            let frames = clip(3, 1, 2, 1);
            let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
            // A real header, then anything.
            let head = HEADER_BYTES + 1;
            let _ = decode(&[&bytes[..head], &tail].concat());
            let _ = decode(&tail);
            let _ = seek(&tail, 0.0);
        }
    }
}
