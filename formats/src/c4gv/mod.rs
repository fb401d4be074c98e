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
//! w x y z, opacity, colour R G B: [`c4g_scene::CANONICAL_CHANNELS`]), each holding one value per
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
//! [`pruning`](c4g_analysis::pruning)'s static/moving split is another source): a masked Gaussian holds
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
//! Features ([`c4g_scene::FeatureBlock`]) are not part of the format.
//!
//! # Reading
//! [`Decoder`] takes bytes as they come ([`Decoder::feed`]) and hands out each frame as soon as
//! its record is whole ([`Decoder::next_frame`]); [`decode`] reads a whole stream; [`seek`] reads
//! the header, the static record, the index and the frames from the last keyframe at or before a
//! time, and nothing before that keyframe. Every length is checked against what it can be (a body
//! of `c` Gaussians is 14c to 70c bytes; the index holds one entry per frame) before anything is
//! buffered or allocated, inflating stops at the stated length, and memory grows with the bytes
//! actually received, never with what a header claims; a truncated or corrupt stream is a
//! [`SceneError::Format`] that says what is wrong, never a panic. Decoded sets are checked with
//! [`GaussianSet::validate`], so even a hostile stream yields valid sets or an error.
//!
//! A reader in another language (the browser viewer's), step by step: read the header and the
//! mask; read records by their 6-byte heads; inflate a body whose coding is 1; read its 14 ·
//! count varints column by column; a static record fills the static Gaussians once, a keyframe
//! sets the moving ones' cells, a delta frame adds to them; decode the cells as the table above
//! says (in f64, then `Math.fround`) and scatter the static and moving Gaussians back into
//! Gaussian order; stop at the index record. Computed that way its floats are this decoder's,
//! except perhaps the last bit of a scale where its `exp` rounds differently.

mod decoder;
mod encoder;
mod grid;
mod header;
#[cfg(test)]
mod tests;

pub use decoder::{Decoder, decode, read_index, seek};
pub use encoder::{EncodeOptions, Encoder, encode, static_mask};
pub use grid::{rotation_angle, scale_error};
pub use header::{Header, IndexEntry, Steps};

use c4g_scene::SceneError;

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
pub(super) const POSITION_STEP_PER_ERROR: f64 = 1.875;
/// Cells lie strictly inside ± this.
pub(super) const CELL_LIMIT: i64 = 1 << 30;
/// Bytes of a record's kind, coding and length.
pub(super) const RECORD_HEAD: usize = 6;
/// Bytes of a frame record's payload before its body: time and inflated length.
pub(super) const FRAME_HEAD: usize = 12;
/// Bytes of the static record's payload before its body: inflated length.
pub(super) const STATIC_HEAD: usize = 4;
/// Bytes of one index entry.
pub(super) const INDEX_ENTRY: usize = 17;
/// Bytes that end the index: its offset and [`INDEX_MAGIC`].
pub(super) const INDEX_TAIL: usize = 12;
/// Values per Gaussian.
pub(super) const CHANNELS: usize = c4g_scene::CANONICAL_CHANNELS;
/// Longest varint.
pub(super) const VARINT_MAX: usize = 5;
/// DEFLATE inflates at most about this many times (1032:1); a bound for reserving output.
pub(super) const INFLATE_RATIO: usize = 1032;

pub(super) const KIND_STATIC: u8 = 1;
pub(super) const KIND_KEYFRAME: u8 = 2;
pub(super) const KIND_DELTA: u8 = 3;
pub(super) const KIND_INDEX: u8 = 4;
pub(super) const CODING_STORED: u8 = 0;
pub(super) const CODING_DEFLATE: u8 = 1;

/// A Gaussian's grid indices, in canonical channel order.
pub(super) type Cells = [i64; CHANNELS];

pub(super) fn format_error(reason: String) -> SceneError {
    SceneError::Format {
        format: "c4gv",
        reason,
    }
}

/// Fails when `time` is not finite or not after `last`.
pub(super) fn check_time(frame: usize, time: f64, last: Option<f64>) -> Result<(), SceneError> {
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

pub(super) fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

pub(super) fn unzigzag(u: u64) -> i64 {
    ((u >> 1) as i64) ^ -((u & 1) as i64)
}

pub(super) fn read_u32(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

pub(super) fn read_u64(b: &[u8]) -> u64 {
    let mut bytes = [0; 8];
    bytes.copy_from_slice(&b[..8]);
    u64::from_le_bytes(bytes)
}

pub(super) fn read_f64(b: &[u8]) -> f64 {
    f64::from_bits(read_u64(b))
}
