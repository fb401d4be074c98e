//! antimatter15's `.splatv` (the splaTV web player of dynamic splats): a time range of one clip's
//! sets as ONE file, every Gaussian a small motion model that the viewer evaluates at its `time`.
//!
//! # Layout
//!
//! Little endian. `u32` magic `0x674b`, `u32` length `L` of a JSON header, `L` bytes of UTF-8
//! JSON: an array of chunk descriptors, each with a `type` and the `size` in bytes of its data;
//! the data of every chunk follows the header, in the array's order. The viewer draws the chunk
//! of type `"splat"`, which also carries `texwidth`, `texheight` and `cameras` (the viewer opens
//! at `cameras[0]`, so there must be one: OpenCV axes, `rotation` camera-to-world row by row,
//! `position` the centre, `fx`, `fy` in pixels, principal point assumed centred). We write one
//! chunk, and our own field `c4g` in it (the viewer ignores it): the number of Gaussians, the
//! clip's `start` and `end` in seconds, the input `times`, and the `fit` report.
//!
//! The chunk's data is an RGBA32UI texture 4096 texels wide: Gaussian `i` is the 16 `u32` at
//! texels `4 · (i mod 1024) .. +4` of row `i / 1024`, so the data is 64 bytes a Gaussian in
//! order, the last row padded with Gaussians that are never visible (opacity 0, temporal centre
//! far outside the clip). `h(a, b)` below packs two IEEE half floats, `a` in the low 16 bits:
//!
//! | `u32` | content |
//! |---|---|
//! | 0..3 | position `p` (f32) |
//! | 3, 4 | `h(q0, q1)`, `h(q2, q3)`: rotation `q`, scalar first |
//! | 5, 6 | `h(sx, sy)`, `h(sz, 0)`: linear scales |
//! | 7 | `r, g, b, a` bytes, `r` lowest: straight colour and opacity, `/255` |
//! | 8..13 | `v1 = (m0x, m0y, m1x)`, `v2 = (m1y, m2x, m2y)`, `v3 = (m3x, m3y, m4x)` for `mj = h(..)` at `8 + j` |
//! | 13, 14 | `h(ω0, ω1)`, `h(ω2, ω3)`: rotation velocity |
//! | 15 | `h(c, s)`: temporal centre and scale |
//!
//! At the viewer's time `τ` (0..1, the clip's range normalised: `τ = (t − start) / (end −
//! start)`, 0 for a clip of one set), with `dt = τ − c`: position `p + v1·dt + v2·dt² + v3·dt³`,
//! rotation `normalize(q + ω·dt)`, opacity `a/255 · exp(−(dt/s)²)`; scale and colour do not
//! change. The viewer also skips a Gaussian whose temporal factor `exp(−(dt/s)²)` is below
//! [`VISIBILITY_CUTOFF`]; [`Splatv::at`] does not.
//!
//! # The fit
//!
//! [`fit`] turns the sets of a clip (Gaussian `i` the same Gaussian in every set) into one model
//! a Gaussian, in float64, and makes it closed-loop where quantisation would otherwise add
//! error: each coefficient is rounded to what the file holds before the ones below it are fitted
//! to the remaining residual.
//!
//! - Opacity first, since its centre `c` is the origin of every polynomial: `c` is the time of
//!   the largest opacity and `a` that opacity, `s` the least-squares fit of
//!   `ln(o/a) ≈ −((τ − c)/s)²` (weighted by `(o/a)²`, opacities floored at [`OPACITY_FLOOR`]
//!   before the log, over the samples above it when there are any); a second candidate fits the
//!   whole Gaussian `ln o = ln a − ((τ − c)/s)²` by weighted least squares, and the one with the
//!   smaller largest error after rounding `c` and `s` (and trying the neighbouring bytes of `a`)
//!   is kept. An opacity that varies by at most 1/510 is flat: `c = 0.5` (so `|dt| ≤ 0.5`),
//!   `s = 65504`, the largest half.
//! - Position: the least-squares cubic in `dt` (lower degree with fewer than four sets, the set
//!   itself for one), closed-loop from `v3` down to `p`.
//! - Rotation: the unit quaternions sign-aligned along the clip, outwards from the set nearest
//!   `c`, then the least-squares line in `dt`. Since the viewer normalises, a second candidate
//!   first rescales each sample onto the line whose *directions* fit best (the homogeneous least
//!   squares of `u_k ∥ q + ω·dt_k`), which makes a rotation that is `normalize(q + ω·dt)` come
//!   back exactly; the candidate with the smaller largest angle is kept. Closed-loop: `ω`
//!   rounded, then `q` fitted to what is left.
//! - Scale: the geometric mean of the sets' (floored at 1e-7). Colour: the mean, clamped to 0..1.
//!
//! # What is lost, and how much
//!
//! Scale and colour become constant, opacity a single temporal bump, position a cubic,
//! rotation a normalised line; features are not part of the format. [`Splatv::report`] gives
//! the error of the quantised model over the input sets, measured with [`Splatv::at`] (the same
//! report is stored in the file). Measured on this module's tests (1100 Gaussians, 9 sets):
//!
//! - motion that is a cubic (coefficients up to 0.5 scene units a clip), a normalised linear
//!   rotation and a Gaussian opacity bump comes back within the file's rounding: position max
//!   5.3e-4 (rms 7e-5; what is left is the half-float step of the velocity, 2^-12 relative),
//!   rotation 1.1e-3 rad, opacity 2.0e-3 and colour 2.0e-3 (half a byte step), scale 4.8e-4
//!   relative (half a half-float step);
//! - circular motion, radius 0.1–0.5 and a quarter to a full turn over the clip, is beyond a
//!   cubic: position max 0.16 (rms 0.035) with the full turns, 0.014 for at most half a turn;
//!   rotation, opacity, colour and scale as above.

use std::path::Path;

use glam::{Quat, Vec3};
use half::f16;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use c4g_scene::{Gaussian, GaussianSet, SceneError};

/// The file's first `u32`.
pub const MAGIC: u32 = 0x674b;
/// Texels in a row of the splat texture (the viewer's addressing assumes it).
pub const TEXTURE_WIDTH: usize = 4096;
/// Gaussians in a row of the splat texture (four texels each).
pub const GAUSSIANS_PER_ROW: usize = TEXTURE_WIDTH / 4;
/// `u32` per Gaussian.
pub const RECORD_WORDS: usize = 16;
/// Bytes per Gaussian.
pub const RECORD: usize = RECORD_WORDS * 4;
/// The viewer skips a Gaussian whose temporal factor is below this.
pub const VISIBILITY_CUTOFF: f32 = 0.02;
/// The largest half float: the temporal scale of an opacity that does not change.
pub const FLAT_TEMPORAL_SCALE: f64 = 65504.0;
/// Opacities are floored at this before their logarithm is fitted (a quarter of the opacity
/// byte's step, so what flooring can add stays below the rounding).
pub const OPACITY_FLOOR: f64 = 1e-3;

const FORMAT: &str = "splatv";
/// Scales are floored at this before their logarithm is averaged.
const SCALE_FLOOR: f64 = 1e-7;
/// The smallest temporal scale written (the smallest normal half float).
const MIN_TEMPORAL_SCALE: f64 = 6.103_515_625e-5;
/// An opacity that varies by at most this over the clip is fitted as constant.
const FLAT_OPACITY: f64 = 1.0 / 510.0;

/// The viewer's camera: what it opens at (`cameras[0]`). OpenCV axes (x right, y down, z
/// forward), as our Gaussians.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length in pixels, x.
    pub fx: f64,
    /// Focal length in pixels, y.
    pub fy: f64,
    /// Camera centre in the scene's frame.
    pub position: [f64; 3],
    /// Camera-to-world rotation, `rotation[row][column]`.
    pub rotation: [[f64; 3]; 3],
}

impl Camera {
    /// Our default focal length as a fraction of the image size (`fx / width`, `fy / height`).
    pub const DEFAULT_FOCAL: f64 = 0.8767;

    /// The first context camera, which is the scene's frame (identity rotation, at the origin),
    /// with our default intrinsics for a `width` × `height` image.
    pub fn first_context(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            fx: Self::DEFAULT_FOCAL * f64::from(width),
            fy: Self::DEFAULT_FOCAL * f64::from(height),
            position: [0.0; 3],
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    fn validate(&self, what: &str) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "{what}: image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if !(self.fx.is_finite() && self.fx > 0.0 && self.fy.is_finite() && self.fy > 0.0) {
            return Err(format!(
                "{what}: focal lengths ({}, {}) must be finite and positive",
                self.fx, self.fy
            ));
        }
        if !self
            .position
            .iter()
            .chain(self.rotation.iter().flatten())
            .all(|v| v.is_finite())
        {
            return Err(format!("{what}: position and rotation must be finite"));
        }
        Ok(())
    }
}

impl From<&c4g_scene::Camera> for Camera {
    /// The viewer's camera for one of ours (the principal point is dropped: the viewer centres it).
    fn from(camera: &c4g_scene::Camera) -> Self {
        let pose = camera.camera_to_world();
        let k = camera.intrinsics();
        let column = |c: usize| pose.matrix3.col(c).to_array().map(f64::from);
        let columns = [column(0), column(1), column(2)];
        Self {
            width: k.width,
            height: k.height,
            fx: f64::from(k.fx),
            fy: f64::from(k.fy),
            position: camera.position().to_array().map(f64::from),
            rotation: [0, 1, 2].map(|r| [0, 1, 2].map(|c| columns[c][r])),
        }
    }
}

/// The error of a fitted model over the sets it was fitted to, measured with [`Splatv::at`]
/// against the input values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Sets fitted.
    pub sets: usize,
    /// Largest position error (Euclidean distance, scene units).
    pub position_max: f64,
    /// Root mean square position error over all Gaussians of all sets (scene units).
    pub position_rms: f64,
    /// Largest rotation error (angle of the relative rotation, radians).
    pub rotation_max: f64,
    /// Largest opacity error (the viewer's temporal factor included).
    pub opacity_max: f64,
    /// Largest colour error, any channel (colours outside 0..1 count their clamping).
    pub color_max: f64,
    /// Largest relative scale error, any axis (scales floored at 1e-7).
    pub scale_max_relative: f64,
}

/// A `.splatv` model: the viewer's cameras and one motion model a Gaussian, as the file holds them.
#[derive(Debug, Clone, PartialEq)]
pub struct Splatv {
    cameras: Vec<Camera>,
    records: Vec<[u32; RECORD_WORDS]>,
    clip: Option<Clip>,
}

/// Our `c4g` field of the splat chunk.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Clip {
    /// Gaussians (the texture's last row is padded beyond them).
    count: usize,
    /// Time of the first set, seconds: τ = 0.
    start: f64,
    /// Time of the last set, seconds: τ = 1.
    end: f64,
    /// Times of the fitted sets, seconds.
    times: Vec<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    fit: Option<FitReport>,
}

#[derive(Debug, Serialize, Deserialize)]
struct ChunkJson {
    #[serde(rename = "type")]
    kind: String,
    size: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    texwidth: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    texheight: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cameras: Option<Vec<CameraJson>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    c4g: Option<Clip>,
}

#[derive(Debug, Serialize, Deserialize)]
struct CameraJson {
    #[serde(default)]
    id: u64,
    #[serde(default)]
    img_name: String,
    width: u32,
    height: u32,
    position: [f64; 3],
    rotation: [[f64; 3]; 3],
    fx: f64,
    fy: f64,
}

impl Splatv {
    /// Gaussians in the model.
    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// True when the model has no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// The viewer's cameras (at least one; it opens at the first).
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// The clip's time range in seconds (τ = 0 and τ = 1), when the file says (ours do).
    pub fn time_range(&self) -> Option<(f64, f64)> {
        self.clip.as_ref().map(|c| (c.start, c.end))
    }

    /// The times (seconds) of the sets the model was fitted to; empty when the file does not say.
    pub fn times(&self) -> &[f64] {
        self.clip.as_ref().map_or(&[], |c| &c.times)
    }

    /// The fit's error over its input sets (stored in the file; `None` for files that are not ours).
    pub fn report(&self) -> Option<&FitReport> {
        self.clip.as_ref().and_then(|c| c.fit.as_ref())
    }

    /// The viewer's time for `t_seconds`: the clip's range normalised (0 for a clip of one set),
    /// or `t_seconds` itself when the file has no time range.
    pub fn tau(&self, t_seconds: f64) -> f64 {
        match &self.clip {
            Some(c) if c.end > c.start => (t_seconds - c.start) / (c.end - c.start),
            Some(_) => 0.0,
            None => t_seconds,
        }
    }

    /// The Gaussians at `t_seconds`, evaluated as the viewer does (in `f32`, opacity times the
    /// temporal factor), in the fitted sets' order. Unlike the viewer, Gaussians whose temporal
    /// factor is below [`VISIBILITY_CUTOFF`] are kept.
    pub fn at(&self, t_seconds: f64) -> GaussianSet {
        let time = self.tau(t_seconds) as f32;
        GaussianSet::from_gaussians(self.records.iter().map(|r| evaluate(r, time)))
    }

    /// The `.splatv` bytes.
    pub fn encode(&self) -> Vec<u8> {
        let rows = self.records.len().div_ceil(GAUSSIANS_PER_ROW).max(1);
        let slots = rows * GAUSSIANS_PER_ROW;
        let header = [ChunkJson {
            kind: "splat".to_owned(),
            size: (slots * RECORD) as u64,
            texwidth: Some(TEXTURE_WIDTH as u64),
            texheight: Some(rows as u64),
            cameras: Some(
                self.cameras
                    .iter()
                    .enumerate()
                    .map(|(id, c)| CameraJson {
                        id: id as u64,
                        img_name: format!("c4g_camera_{id}"),
                        width: c.width,
                        height: c.height,
                        position: c.position,
                        rotation: c.rotation,
                        fx: c.fx,
                        fy: c.fy,
                    })
                    .collect(),
            ),
            c4g: self.clip.clone(),
        }];
        // Cannot fail: plain structs of strings and (checked finite) numbers.
        let json = serde_json::to_vec(&header).unwrap_or_default();
        let mut out = Vec::with_capacity(8 + json.len() + slots * RECORD);
        out.extend_from_slice(&MAGIC.to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&json);
        let padding = padding_record();
        for record in self
            .records
            .iter()
            .chain(std::iter::repeat_n(&padding, slots - self.records.len()))
        {
            for word in record {
                out.extend_from_slice(&word.to_le_bytes());
            }
        }
        out
    }
}

/// Writes `model` to a `.splatv` file.
pub fn write(path: &Path, model: &Splatv) -> Result<(), SceneError> {
    super::write_file(path, &model.encode())
}

/// Reads a `.splatv` file.
pub fn read(path: &Path) -> Result<Splatv, SceneError> {
    decode(&super::read_file(path)?)
}

fn format_error(reason: String) -> SceneError {
    SceneError::Format {
        format: FORMAT,
        reason,
    }
}

/// Parses `.splatv` bytes: the first chunk of type `"splat"` (other chunks are skipped), its
/// cameras and, when present, our `c4g` field (without it every Gaussian of the texture is
/// taken, and [`Splatv::at`] takes its time as the viewer's τ).
pub fn decode(bytes: &[u8]) -> Result<Splatv, SceneError> {
    let len = bytes.len();
    if len < 8 {
        return Err(format_error(format!(
            "{len} bytes, shorter than the 8-byte preamble (magic, header length)"
        )));
    }
    let word =
        |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let magic = word(0);
    if magic != MAGIC {
        return Err(format_error(format!(
            "magic 0x{magic:x} at byte 0, expected 0x{MAGIC:x}"
        )));
    }
    let json_len = word(4) as usize;
    let json_end = 8usize
        .checked_add(json_len)
        .filter(|&end| end <= len)
        .ok_or_else(|| {
            format_error(format!(
                "the header claims {json_len} bytes of JSON at byte 8, the file has {} after the preamble",
                len - 8
            ))
        })?;
    let chunks: Vec<Value> = serde_json::from_slice(&bytes[8..json_end]).map_err(|e| {
        format_error(format!(
            "JSON header (bytes 8..{json_end}) is not an array of chunks: {e}"
        ))
    })?;

    let mut offset = json_end;
    let mut splat = None;
    for (c, chunk) in chunks.iter().enumerate() {
        let kind = chunk.get("type").and_then(Value::as_str).ok_or_else(|| {
            format_error(format!("chunk {c} of the header has no \"type\" string"))
        })?;
        let size = chunk
            .get("size")
            .and_then(Value::as_u64)
            .and_then(|s| usize::try_from(s).ok())
            .ok_or_else(|| format_error(format!("chunk {c} ({kind}) has no \"size\" in bytes")))?;
        let end = offset.checked_add(size).filter(|&e| e <= len).ok_or_else(|| {
            format_error(format!(
                "chunk {c} ({kind}): {size} bytes from byte {offset} run past the end of the file ({len} bytes)"
            ))
        })?;
        if kind == "splat" && splat.is_none() {
            splat = Some((c, chunk, offset, size));
        }
        offset = end;
    }
    let (c, chunk, data_start, size) = splat.ok_or_else(|| {
        format_error(format!(
            "none of the header's {} chunks has type \"splat\"",
            chunks.len()
        ))
    })?;
    let chunk: ChunkJson = serde_json::from_value(chunk.clone())
        .map_err(|e| format_error(format!("chunk {c} (splat): {e}")))?;

    let width = chunk
        .texwidth
        .ok_or_else(|| format_error(format!("chunk {c} (splat) has no texwidth")))?;
    if width != TEXTURE_WIDTH as u64 {
        return Err(format_error(format!(
            "texwidth {width}: the viewer addresses a texture {TEXTURE_WIDTH} texels wide"
        )));
    }
    let height = chunk
        .texheight
        .ok_or_else(|| format_error(format!("chunk {c} (splat) has no texheight")))?;
    let slots = usize::try_from(height)
        .ok()
        .and_then(|h| h.checked_mul(GAUSSIANS_PER_ROW));
    if slots.and_then(|s| s.checked_mul(RECORD)) != Some(size) {
        return Err(format_error(format!(
            "splat chunk of {size} bytes, but a {width}x{height} RGBA32UI texture is {width} · {height} · 16 bytes"
        )));
    }
    let slots = slots.unwrap_or(0);

    let cameras: Vec<Camera> = chunk
        .cameras
        .unwrap_or_default()
        .into_iter()
        .map(|c| Camera {
            width: c.width,
            height: c.height,
            fx: c.fx,
            fy: c.fy,
            position: c.position,
            rotation: c.rotation,
        })
        .collect();
    if cameras.is_empty() {
        return Err(format_error(
            "the splat chunk has no cameras (the viewer opens at cameras[0])".to_owned(),
        ));
    }
    for (k, camera) in cameras.iter().enumerate() {
        camera
            .validate(&format!("camera {k}"))
            .map_err(format_error)?;
    }

    if let Some(clip) = &chunk.c4g {
        if clip.count > slots {
            return Err(format_error(format!(
                "c4g.count {} is more than the texture's {slots} Gaussians",
                clip.count
            )));
        }
        if !(clip.start.is_finite() && clip.end.is_finite() && clip.end >= clip.start) {
            return Err(format_error(format!(
                "c4g time range {}..{} s is not a finite, increasing range",
                clip.start, clip.end
            )));
        }
        if !clip.times.iter().all(|t| t.is_finite()) {
            return Err(format_error("c4g.times holds a non-finite time".to_owned()));
        }
    }
    let count = chunk.c4g.as_ref().map_or(slots, |clip| clip.count);

    let mut records = Vec::with_capacity(count);
    for i in 0..count {
        let at = data_start + i * RECORD;
        let mut record = [0u32; RECORD_WORDS];
        for (j, w) in record.iter_mut().enumerate() {
            *w = word(at + 4 * j);
        }
        check_record(&record)
            .map_err(|what| format_error(format!("Gaussian {i} (byte {at}): {what}")))?;
        records.push(record);
    }
    Ok(Splatv {
        cameras,
        records,
        clip: chunk.c4g,
    })
}

/// What is wrong with a record's values, if anything.
fn check_record(r: &[u32; RECORD_WORDS]) -> Result<(), String> {
    if !r[..3].iter().all(|&w| f32::from_bits(w).is_finite()) {
        return Err("non-finite position".to_owned());
    }
    for (j, w) in r.iter().enumerate().skip(3) {
        let (low, high) = unpack(*w);
        let used_high = j != 6 && j != 12;
        if j != 7 && !(low.is_finite() && (!used_high || high.is_finite())) {
            return Err(format!("non-finite half float in u32 {j}"));
        }
    }
    if unpack(r[15]).1 == 0.0 {
        return Err("temporal scale 0".to_owned());
    }
    Ok(())
}

/// A texel group that the viewer never shows: opacity 0 and a temporal centre far from 0..1.
fn padding_record() -> [u32; RECORD_WORDS] {
    let mut r = [0u32; RECORD_WORDS];
    r[3] = pack(1.0, 0.0);
    r[15] = pack(FLAT_TEMPORAL_SCALE, 1.0);
    r
}

fn half(v: f64) -> f16 {
    f16::from_f64(v.clamp(-FLAT_TEMPORAL_SCALE, FLAT_TEMPORAL_SCALE))
}

/// `v` as the file holds it in a half float.
fn round_half(v: f64) -> f64 {
    half(v).to_f64()
}

/// Two half floats as GLSL `packHalf2x16`: `a` in the low bits.
fn pack(a: f64, b: f64) -> u32 {
    u32::from(half(a).to_bits()) | (u32::from(half(b).to_bits()) << 16)
}

fn unpack(w: u32) -> (f32, f32) {
    (
        f16::from_bits(w as u16).to_f32(),
        f16::from_bits((w >> 16) as u16).to_f32(),
    )
}

/// One record at the viewer's time, in `f32` as the viewer computes it.
fn evaluate(r: &[u32; RECORD_WORDS], time: f32) -> Gaussian {
    let p = Vec3::new(
        f32::from_bits(r[0]),
        f32::from_bits(r[1]),
        f32::from_bits(r[2]),
    );
    let (q0, q1) = unpack(r[3]);
    let (q2, q3) = unpack(r[4]);
    let (sx, sy) = unpack(r[5]);
    let (sz, _) = unpack(r[6]);
    let [cr, cg, cb, ca] = r[7].to_le_bytes().map(|b| f32::from(b) / 255.0);
    let m = [8, 9, 10, 11, 12].map(|j| unpack(r[j]));
    let v1 = Vec3::new(m[0].0, m[0].1, m[1].0);
    let v2 = Vec3::new(m[1].1, m[2].0, m[2].1);
    let v3 = Vec3::new(m[3].0, m[3].1, m[4].0);
    let (w0, w1) = unpack(r[13]);
    let (w2, w3) = unpack(r[14]);
    let (center, scale) = unpack(r[15]);

    let dt = time - center;
    let position = p + v1 * dt + v2 * (dt * dt) + v3 * (dt * dt * dt);
    let q = [q0 + w0 * dt, q1 + w1 * dt, q2 + w2 * dt, q3 + w3 * dt];
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    let rotation = if norm > 0.0 && norm.is_finite() {
        Quat::from_xyzw(q[1] / norm, q[2] / norm, q[3] / norm, q[0] / norm)
    } else {
        Quat::IDENTITY
    };
    let x = dt / scale;
    Gaussian {
        position,
        scale: Vec3::new(sx, sy, sz),
        rotation,
        opacity: ca * (-(x * x)).exp(),
        color: Vec3::new(cr, cg, cb),
    }
}

/// Fits one `.splatv` model to the sets of a clip, `(time in seconds, set)` in increasing time,
/// every set holding the same Gaussians in the same order; `camera` is the one the viewer opens
/// at. The result's [`report`](Splatv::report) is the quantised model's error over `frames`.
pub fn fit(frames: &[(f64, GaussianSet)], camera: &Camera) -> Result<Splatv, SceneError> {
    camera
        .validate("the viewer's camera")
        .map_err(SceneError::InvalidCamera)?;
    let Some((start, first)) = frames.first() else {
        return Err(format_error("cannot fit: no sets".to_owned()));
    };
    let (start, n) = (*start, first.len());
    for (k, (t, set)) in frames.iter().enumerate() {
        let fail = |what: String| format_error(format!("cannot fit set {k} (t = {t} s): {what}"));
        if !t.is_finite() {
            return Err(fail("its time is not finite".to_owned()));
        }
        if k > 0 && *t <= frames[k - 1].0 {
            return Err(fail(format!(
                "it does not follow set {}'s time {} s (times must increase)",
                k - 1,
                frames[k - 1].0
            )));
        }
        if set.len() != n {
            return Err(fail(format!(
                "it holds {} Gaussians, set 0 holds {n} (every set of a clip has the same Gaussians)",
                set.len()
            )));
        }
        if let Some((i, what)) = first_invalid(set) {
            return Err(fail(format!("Gaussian {i} has {what}")));
        }
    }
    let end = frames[frames.len() - 1].0;
    let taus: Vec<f64> = frames
        .iter()
        .map(|(t, _)| {
            if end > start {
                (t - start) / (end - start)
            } else {
                0.0
            }
        })
        .collect();
    let records = (0..n).map(|i| fit_gaussian(frames, &taus, i)).collect();
    let mut model = Splatv {
        cameras: vec![camera.clone()],
        records,
        clip: Some(Clip {
            count: n,
            start,
            end,
            times: frames.iter().map(|(t, _)| *t).collect(),
            fit: None,
        }),
    };
    let report = measure(&model, frames);
    if let Some(clip) = &mut model.clip {
        clip.fit = Some(report);
    }
    Ok(model)
}

/// The first Gaussian of `set` with a value the fit cannot take, and what is wrong with it.
fn first_invalid(set: &GaussianSet) -> Option<(usize, &'static str)> {
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    (0..set.len()).find_map(|i| {
        let q = set.rotations()[i];
        if !finite(&set.positions()[i]) {
            Some((i, "a non-finite position"))
        } else if !finite(&set.scales()[i]) {
            Some((i, "a non-finite scale"))
        } else if !finite(&q) || q.iter().all(|v| *v == 0.0) {
            Some((i, "a non-finite or zero rotation"))
        } else if !set.opacities()[i].is_finite() {
            Some((i, "a non-finite opacity"))
        } else if !finite(&set.colors()[i]) {
            Some((i, "a non-finite colour"))
        } else {
            None
        }
    })
}

/// The record of Gaussian `i` over the clip (`taus`: the sets' normalised times).
fn fit_gaussian(frames: &[(f64, GaussianSet)], taus: &[f64], i: usize) -> [u32; RECORD_WORDS] {
    let sets = frames.len();
    let opacities: Vec<f64> = frames
        .iter()
        .map(|(_, s)| f64::from(s.opacities()[i]).clamp(0.0, 1.0))
        .collect();
    let (center, temporal_scale, alpha) = fit_opacity(taus, &opacities);
    let dts: Vec<f64> = taus.iter().map(|t| t - center).collect();

    // Position: closed-loop cubic per axis, the highest power first.
    let degree = 3.min(sets - 1);
    let mut position = [0.0f32; 3];
    let mut velocity = [[0.0f64; 3]; 4]; // velocity[j][axis]: coefficient of dt^j
    for axis in 0..3 {
        let mut residual: Vec<f64> = frames
            .iter()
            .map(|(_, s)| f64::from(s.positions()[i][axis]))
            .collect();
        for power in (1..=degree).rev() {
            let v = round_half(polyfit(&dts, &residual, None, power)[power]);
            velocity[power][axis] = v;
            for (r, dt) in residual.iter_mut().zip(&dts) {
                *r -= v * dt.powi(power as i32);
            }
        }
        position[axis] = mean(&residual) as f32;
    }

    let (rotation, omega) = fit_rotation(frames, taus, &dts, center, i);

    let scale: [f64; 3] = std::array::from_fn(|axis| {
        let logs: Vec<f64> = frames
            .iter()
            .map(|(_, s)| f64::from(s.scales()[i][axis]).max(SCALE_FLOOR).ln())
            .collect();
        mean(&logs).exp()
    });
    let color: [u8; 3] = std::array::from_fn(|c| {
        let values: Vec<f64> = frames
            .iter()
            .map(|(_, s)| f64::from(s.colors()[i][c]))
            .collect();
        (mean(&values).clamp(0.0, 1.0) * 255.0).round() as u8
    });

    let mut r = [0u32; RECORD_WORDS];
    for axis in 0..3 {
        r[axis] = position[axis].to_bits();
    }
    r[3] = pack(rotation[0], rotation[1]);
    r[4] = pack(rotation[2], rotation[3]);
    r[5] = pack(scale[0], scale[1]);
    r[6] = pack(scale[2], 0.0);
    r[7] = u32::from_le_bytes([color[0], color[1], color[2], alpha]);
    let [_, v1, v2, v3] = velocity;
    r[8] = pack(v1[0], v1[1]);
    r[9] = pack(v1[2], v2[0]);
    r[10] = pack(v2[1], v2[2]);
    r[11] = pack(v3[0], v3[1]);
    r[12] = pack(v3[2], 0.0);
    r[13] = pack(omega[0], omega[1]);
    r[14] = pack(omega[2], omega[3]);
    r[15] = pack(center, temporal_scale);
    r
}

/// Temporal centre and scale (both as half floats hold them) and the opacity byte.
fn fit_opacity(taus: &[f64], opacities: &[f64]) -> (f64, f64, u8) {
    let (lo, hi) = opacities
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &o| {
            (lo.min(o), hi.max(o))
        });
    let mut candidates = Vec::with_capacity(2);
    if opacities.len() == 1 {
        candidates.push((0.0, FLAT_TEMPORAL_SCALE, hi));
    } else if hi - lo <= FLAT_OPACITY {
        candidates.push((0.5, FLAT_TEMPORAL_SCALE, hi));
    } else {
        let peak = (0..opacities.len()).fold(0, |best, k| {
            if opacities[k] > opacities[best] {
                k
            } else {
                best
            }
        });
        let center = round_half(taus[peak]);
        candidates.push((center, bump_scale(taus, opacities, center, hi), hi));
        if let Some(bump) = log_quadratic(taus, opacities) {
            candidates.push(bump);
        }
    }
    let mut best = (0.0, FLAT_TEMPORAL_SCALE, 0u8, f64::INFINITY);
    for (center, scale, alpha) in candidates {
        let (center, scale) = (round_half(center), round_half(scale));
        let guess = (alpha * 255.0).round();
        for byte in [guess, guess - 1.0, guess + 1.0] {
            let byte = byte.clamp(0.0, 255.0) as u8;
            let error = taus
                .iter()
                .zip(opacities)
                .map(|(t, o)| {
                    let x = (t - center) / scale;
                    (f64::from(byte) / 255.0 * (-(x * x)).exp() - o).abs()
                })
                .fold(0.0, f64::max);
            if error < best.3 {
                best = (center, scale, byte, error);
            }
        }
    }
    (best.0, best.1, best.2)
}

/// The least-squares `s` of `ln(o/a) ≈ −((τ − c)/s)²`, weighted by `(o/a)²`, over the samples
/// above the floor when any of them constrain `s`.
fn bump_scale(taus: &[f64], opacities: &[f64], center: f64, alpha: f64) -> f64 {
    let solve = |use_floored: bool| {
        let (mut num, mut den) = (0.0, 0.0);
        for (t, o) in taus.iter().zip(opacities) {
            if !use_floored && *o <= OPACITY_FLOOR {
                continue;
            }
            let ratio = o.max(OPACITY_FLOOR) / alpha;
            let (u, w) = ((t - center).powi(2), ratio * ratio);
            num -= w * u * ratio.ln();
            den += w * u * u;
        }
        (den > 0.0).then(|| num / den)
    };
    match solve(false).or_else(|| solve(true)) {
        Some(x) if x > 0.0 => (1.0 / x.sqrt()).clamp(MIN_TEMPORAL_SCALE, FLAT_TEMPORAL_SCALE),
        _ => FLAT_TEMPORAL_SCALE,
    }
}

/// The Gaussian bump `ln o = ln a − ((τ − c)/s)²` by weighted least squares (a parabola in τ
/// through the log-opacities), when it is one with its centre in the clip.
fn log_quadratic(taus: &[f64], opacities: &[f64]) -> Option<(f64, f64, f64)> {
    let above: Vec<usize> = (0..taus.len())
        .filter(|&k| opacities[k] > OPACITY_FLOOR)
        .collect();
    let keep: Vec<usize> = if above.len() >= 3 {
        above
    } else {
        (0..taus.len()).collect()
    };
    if keep.len() < 3 {
        return None;
    }
    let x: Vec<f64> = keep.iter().map(|&k| taus[k]).collect();
    let floored: Vec<f64> = keep
        .iter()
        .map(|&k| opacities[k].max(OPACITY_FLOOR))
        .collect();
    let y: Vec<f64> = floored.iter().map(|o| o.ln()).collect();
    let w: Vec<f64> = floored.iter().map(|o| o * o).collect();
    let [a0, a1, a2] = polyfit(&x, &y, Some(&w), 2)[..] else {
        return None;
    };
    if a2 >= 0.0 {
        return None;
    }
    let center = -a1 / (2.0 * a2);
    if !(0.0..=1.0).contains(&center) {
        return None;
    }
    let scale = (1.0 / (-a2).sqrt()).clamp(MIN_TEMPORAL_SCALE, FLAT_TEMPORAL_SCALE);
    let alpha = (a0 - a1 * a1 / (4.0 * a2)).exp().min(1.0);
    alpha.is_finite().then_some((center, scale, alpha))
}

/// Rotation `q` and velocity `ω`, as half floats hold them.
fn fit_rotation(
    frames: &[(f64, GaussianSet)],
    taus: &[f64],
    dts: &[f64],
    center: f64,
    i: usize,
) -> ([f64; 4], [f64; 4]) {
    let mut unit: Vec<[f64; 4]> = frames
        .iter()
        .map(|(_, s)| {
            let q = s.rotations()[i].map(f64::from);
            let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            q.map(|v| v / norm)
        })
        .collect();
    // Sign-align along the clip, outwards from the set nearest the temporal centre.
    let reference = (0..taus.len())
        .min_by(|&a, &b| {
            (taus[a] - center)
                .abs()
                .total_cmp(&(taus[b] - center).abs())
        })
        .unwrap_or(0);
    for k in (reference + 1..unit.len()).chain((0..reference).rev()) {
        let neighbour = if k > reference {
            unit[k - 1]
        } else {
            unit[k + 1]
        };
        if dot(&unit[k], &neighbour) < 0.0 {
            unit[k] = unit[k].map(|v| -v);
        }
    }

    let mut candidates = vec![unit.clone()];
    if let Some(rescaled) = onto_projective_line(&unit, dts) {
        candidates.push(rescaled);
    }
    let mut best = ([1.0, 0.0, 0.0, 0.0], [0.0; 4], f64::INFINITY);
    for samples in candidates {
        // Closed-loop: ω rounded first, then q fitted to what is left.
        let mut q = [0.0; 4];
        let mut omega = [0.0; 4];
        for c in 0..4 {
            let mut residual: Vec<f64> = samples.iter().map(|s| s[c]).collect();
            if frames.len() > 1 {
                omega[c] = round_half(polyfit(dts, &residual, None, 1)[1]);
                for (r, dt) in residual.iter_mut().zip(dts) {
                    *r -= omega[c] * dt;
                }
            }
            q[c] = round_half(mean(&residual));
        }
        let error = unit
            .iter()
            .zip(dts)
            .map(|(u, dt)| rotation_angle(u, &std::array::from_fn(|c| q[c] + omega[c] * dt)))
            .fold(0.0, f64::max);
        if error < best.2 {
            best = (q, omega, error);
        }
    }
    (best.0, best.1)
}

/// The unit quaternions `unit` rescaled onto the line `A + B·dt` whose directions fit them best:
/// the least-squares solution of `u_k ∥ A + B·dt_k` (the smallest eigenvector of the normal
/// matrix of `Σ ‖(I − u_k u_kᵀ)(A + B·dt_k)‖²`, by inverse iteration from the plain line), each
/// sample scaled to its point on the line, the scales averaging 1. `None` when there is no such
/// line on the samples' side of the origin, or fewer than two samples.
fn onto_projective_line(unit: &[[f64; 4]], dts: &[f64]) -> Option<Vec<[f64; 4]>> {
    if unit.len() < 2 {
        return None;
    }
    // M = Σ_k [1, dt; dt, dt²] ⊗ P_k, P_k = I − u_k u_kᵀ, acting on x = (A, B).
    let mut m = [[0.0f64; 8]; 8];
    for (u, &dt) in unit.iter().zip(dts) {
        let weights = [[1.0, dt], [dt, dt * dt]];
        for r in 0..4 {
            for c in 0..4 {
                let p = f64::from(u8::from(r == c)) - u[r] * u[c];
                for (br, row) in weights.iter().enumerate() {
                    for (bc, w) in row.iter().enumerate() {
                        m[4 * br + r][4 * bc + c] += w * p;
                    }
                }
            }
        }
    }
    let trace: f64 = (0..8).map(|d| m[d][d]).sum();
    let shift = 1e-10 * trace + f64::MIN_POSITIVE;
    let mut x: Vec<f64> = {
        let plain: Vec<[f64; 2]> = (0..4)
            .map(|c| {
                let y: Vec<f64> = unit.iter().map(|u| u[c]).collect();
                let fit = polyfit(dts, &y, None, 1);
                [fit[0], fit[1]]
            })
            .collect();
        (0..8).map(|k| plain[k % 4][k / 4]).collect()
    };
    for _ in 0..3 {
        let system = (0..8)
            .map(|r| {
                let mut row: Vec<f64> = m[r].to_vec();
                row[r] += shift;
                row.push(x[r]);
                row
            })
            .collect();
        let next = solve(system)?;
        let norm = next.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm.is_nan() || norm <= 0.0 {
            return None;
        }
        x = next.iter().map(|v| v / norm).collect();
    }
    let point = |dt: f64| std::array::from_fn::<f64, 4, _>(|c| x[c] + x[4 + c] * dt);
    let mut scales: Vec<f64> = unit
        .iter()
        .zip(dts)
        .map(|(u, dt)| dot(u, &point(*dt)))
        .collect();
    if scales.iter().sum::<f64>() < 0.0 {
        scales.iter_mut().for_each(|s| *s = -*s);
    }
    if !scales.iter().all(|s| *s > 0.0) {
        return None;
    }
    let norm = mean(&scales);
    Some(
        unit.iter()
            .zip(&scales)
            .map(|(u, s)| u.map(|v| v * s / norm))
            .collect(),
    )
}

fn dot(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The angle (radians) of the rotation between the orientations of two quaternions (any norm).
fn rotation_angle(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let unit = |q: &[f64; 4]| {
        let norm = dot(q, q).sqrt();
        if norm > 0.0 {
            q.map(|v| v / norm)
        } else {
            [1.0, 0.0, 0.0, 0.0]
        }
    };
    let (a, mut b) = (unit(a), unit(b));
    if dot(&a, &b) < 0.0 {
        b = b.map(|v| -v);
    }
    let diff: f64 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt();
    let sum: f64 = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x + y).powi(2))
        .sum::<f64>()
        .sqrt();
    4.0 * diff.atan2(sum)
}

fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// Least-squares polynomial coefficients (lowest power first, `degree + 1` of them) of `y` over
/// `x`, optionally weighted; a degree the samples cannot determine is dropped (its coefficients 0).
fn polyfit(x: &[f64], y: &[f64], w: Option<&[f64]>, degree: usize) -> Vec<f64> {
    let mut coeffs = vec![0.0; degree + 1];
    let mut d = degree.min(x.len().saturating_sub(1));
    loop {
        let m = d + 1;
        let mut a = vec![vec![0.0; m + 1]; m];
        for k in 0..x.len() {
            let weight = w.map_or(1.0, |w| w[k]);
            for (r, row) in a.iter_mut().enumerate() {
                for (c, cell) in row[..m].iter_mut().enumerate() {
                    *cell += weight * x[k].powi((r + c) as i32);
                }
                row[m] += weight * x[k].powi(r as i32) * y[k];
            }
        }
        if let Some(solution) = solve(a) {
            coeffs[..m].copy_from_slice(&solution);
            return coeffs;
        }
        if d == 0 {
            return coeffs;
        }
        d -= 1;
    }
}

/// Solves an augmented `m × (m + 1)` system by Gaussian elimination with partial pivoting;
/// `None` when it is (numerically) singular.
fn solve(mut a: Vec<Vec<f64>>) -> Option<Vec<f64>> {
    let m = a.len();
    let size = a
        .iter()
        .flat_map(|row| &row[..m])
        .fold(0.0f64, |s, v| s.max(v.abs()));
    for col in 0..m {
        let pivot = (col..m).max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))?;
        // Also refuses a NaN pivot.
        if a[pivot][col].abs().partial_cmp(&(1e-12 * size)) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        a.swap(col, pivot);
        let (top, below) = a.split_at_mut(col + 1);
        let pivot_row = &top[col];
        for row in below {
            let factor = row[col] / pivot_row[col];
            for (cell, p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                *cell -= factor * p;
            }
        }
    }
    let mut x = vec![0.0; m];
    for row in (0..m).rev() {
        let tail: f64 = (row + 1..m).map(|c| a[row][c] * x[c]).sum();
        x[row] = (a[row][m] - tail) / a[row][row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The error of `model` over the sets it was fitted to.
fn measure(model: &Splatv, frames: &[(f64, GaussianSet)]) -> FitReport {
    let mut report = FitReport {
        sets: frames.len(),
        position_max: 0.0,
        position_rms: 0.0,
        rotation_max: 0.0,
        opacity_max: 0.0,
        color_max: 0.0,
        scale_max_relative: 0.0,
    };
    let mut squares = 0.0;
    for (t, set) in frames {
        let got = model.at(*t);
        for i in 0..set.len() {
            let d2: f64 = (0..3)
                .map(|a| {
                    (f64::from(got.positions()[i][a]) - f64::from(set.positions()[i][a])).powi(2)
                })
                .sum();
            squares += d2;
            report.position_max = report.position_max.max(d2.sqrt());
            report.rotation_max = report.rotation_max.max(rotation_angle(
                &set.rotations()[i].map(f64::from),
                &got.rotations()[i].map(f64::from),
            ));
            report.opacity_max = report
                .opacity_max
                .max((f64::from(got.opacities()[i]) - f64::from(set.opacities()[i])).abs());
            for a in 0..3 {
                report.color_max = report
                    .color_max
                    .max((f64::from(got.colors()[i][a]) - f64::from(set.colors()[i][a])).abs());
                let (g, s) = (
                    f64::from(got.scales()[i][a]).max(SCALE_FLOOR),
                    f64::from(set.scales()[i][a]).max(SCALE_FLOOR),
                );
                report.scale_max_relative = report.scale_max_relative.max((g / s - 1.0).abs());
            }
        }
    }
    let samples = frames.len() * frames.first().map_or(0, |(_, s)| s.len());
    report.position_rms = (squares / samples.max(1) as f64).sqrt();
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (no dependency for tests).
    struct Rng(u64);

    impl Rng {
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((self.0 >> 11) as f64 / (1u64 << 53) as f64)
        }
        fn vec3(&mut self, lo: f64, hi: f64) -> [f64; 3] {
            [0; 3].map(|_| self.uniform(lo, hi))
        }
    }

    /// The per-Gaussian truth of a synthetic clip, as functions of the normalised time.
    struct Truth {
        p: [f64; 3],
        a: [[f64; 3]; 3],
        circle: Option<(f64, f64)>, // radius, turns over the clip
        q: [f64; 4],
        w: [f64; 4],
        bump: (f64, f64, f64), // peak opacity, centre (τ), width
        scale: [f64; 3],
        color: [f64; 3],
    }

    impl Truth {
        fn position(&self, tau: f64) -> [f32; 3] {
            std::array::from_fn(|c| {
                let mut v = self.p[c]
                    + self.a[0][c] * tau
                    + self.a[1][c] * tau.powi(2)
                    + self.a[2][c] * tau.powi(3);
                if let Some((radius, turns)) = self.circle {
                    let angle = std::f64::consts::TAU * turns * tau;
                    v += radius * [angle.cos(), angle.sin(), 0.0][c];
                }
                v as f32
            })
        }
        fn rotation(&self, tau: f64) -> [f32; 4] {
            let q: [f64; 4] = std::array::from_fn(|c| self.q[c] + self.w[c] * tau);
            let norm = dot(&q, &q).sqrt();
            q.map(|v| (v / norm) as f32)
        }
        fn opacity(&self, tau: f64) -> f32 {
            let (a, c, s) = self.bump;
            (a * (-((tau - c) / s).powi(2)).exp()) as f32
        }
    }

    fn truths(n: usize, seed: u64, times: usize, circle: bool) -> Vec<Truth> {
        let mut rng = Rng(seed);
        (0..n)
            .map(|i| {
                let q = [0; 4].map(|_| rng.uniform(-1.0, 1.0));
                let peak = (rng.uniform(0.0, times as f64) as usize).min(times - 1);
                Truth {
                    p: {
                        let [x, y, z] = rng.vec3(-1.0, 1.0);
                        [x, y, z + 3.0]
                    },
                    a: if circle {
                        [[0.0; 3]; 3]
                    } else {
                        [0; 3].map(|_| rng.vec3(-0.5, 0.5))
                    },
                    circle: circle.then(|| (rng.uniform(0.1, 0.5), rng.uniform(0.25, 1.0))),
                    q,
                    w: [0; 4].map(|_| rng.uniform(-0.3, 0.3)),
                    bump: if i % 5 == 0 {
                        (rng.uniform(0.2, 1.0), 0.5, f64::INFINITY) // flat
                    } else {
                        (
                            rng.uniform(0.3, 1.0),
                            peak as f64 / (times - 1).max(1) as f64,
                            rng.uniform(0.3, 2.0),
                        )
                    },
                    scale: rng.vec3(-5.0, -1.0).map(f64::exp),
                    color: rng.vec3(0.0, 1.0),
                }
            })
            .collect()
    }

    fn clip(truths: &[Truth], times: &[f64]) -> Vec<(f64, GaussianSet)> {
        let (start, end) = (times[0], times[times.len() - 1]);
        times
            .iter()
            .map(|&t| {
                let tau = if end > start {
                    (t - start) / (end - start)
                } else {
                    0.0
                };
                let set = GaussianSet::new(
                    truths.iter().map(|g| g.position(tau)).collect(),
                    truths.iter().map(|g| g.scale.map(|v| v as f32)).collect(),
                    truths.iter().map(|g| g.rotation(tau)).collect(),
                    truths.iter().map(|g| g.opacity(tau)).collect(),
                    truths.iter().map(|g| g.color.map(|v| v as f32)).collect(),
                )
                .unwrap();
                (t, set)
            })
            .collect()
    }

    fn times(k: usize) -> Vec<f64> {
        (0..k).map(|j| 2.0 + 0.125 * j as f64).collect()
    }

    fn camera() -> Camera {
        Camera::first_context(224, 224)
    }

    #[test]
    fn a_scene_the_model_can_express_comes_back_within_the_files_rounding() {
        let truths = truths(1100, 1, 9, false);
        let frames = clip(&truths, &times(9));
        let model = fit(&frames, &camera()).unwrap();
        let report = *model.report().unwrap();
        println!("cubic scene: {report:?}");
        // Velocities about the centre reach |v1| + |v2| + |v3| ≈ 3 scene units a clip; a half
        // float holds them within 2^-12 relative, and the closed loop leaves mostly v1's rounding.
        let largest: f64 = truths
            .iter()
            .map(|g| {
                (0..3)
                    .map(|c| g.a.iter().map(|a| a[c].abs()).sum::<f64>())
                    .fold(0.0, f64::max)
            })
            .fold(0.0, f64::max);
        assert!(
            report.position_max <= 3.0 * largest * 2f64.powi(-12),
            "{report:?}"
        );
        assert!(report.position_rms < report.position_max / 2.0);
        // Normalised linear rotations are recovered exactly but for the halves of q and ω.
        assert!(report.rotation_max < 2e-3, "{report:?}");
        // A byte's half step (1/510) plus the halves of c and s.
        assert!(report.opacity_max < 1.0 / 510.0 + 1e-4, "{report:?}");
        assert!(report.color_max <= 1.0 / 510.0 + 1e-6, "{report:?}");
        assert!(report.scale_max_relative <= 2f64.powi(-11), "{report:?}");
        // The report is what `at` shows, and in between sets the model stays on the truth.
        assert_eq!(measure(&model, &frames), report);
        let tau = 0.5 / 8.0 + 3.0 / 8.0;
        let between = model.at(2.0 + tau);
        for (i, g) in truths.iter().enumerate() {
            for c in 0..3 {
                let d = (between.positions()[i][c] - g.position(tau)[c]).abs();
                assert!(
                    f64::from(d) <= 3.0 * largest * 2f64.powi(-12),
                    "Gaussian {i}: {d}"
                );
            }
        }
    }

    #[test]
    fn circular_motion_reports_the_error_at_shows() {
        let truths = truths(1100, 2, 9, true);
        let frames = clip(&truths, &times(9));
        let model = fit(&frames, &camera()).unwrap();
        let report = *model.report().unwrap();
        println!("circular scene: {report:?}");
        let mut worst = 0.0f64;
        for (t, set) in &frames {
            let got = model.at(*t);
            for i in 0..set.len() {
                let d: f64 = (0..3)
                    .map(|c| f64::from(got.positions()[i][c] - set.positions()[i][c]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                worst = worst.max(d);
            }
        }
        assert!(
            (report.position_max - worst).abs() < 1e-6,
            "{} vs {worst}",
            report.position_max
        );
        assert!(
            report.position_max > 1e-3,
            "a cubic cannot follow a circle: {report:?}"
        );
        assert!(
            report.position_max < 0.5,
            "better than standing still: {report:?}"
        );
        let sampled: Vec<GaussianSet> = frames.iter().map(|(t, _)| model.at(*t)).collect();
        let mild = truths
            .iter()
            .enumerate()
            .filter(|(_, g)| g.circle.is_some_and(|(_, turns)| turns <= 0.5))
            .map(|(i, _)| {
                frames
                    .iter()
                    .zip(&sampled)
                    .map(|((_, set), got)| {
                        (0..3)
                            .map(|c| {
                                f64::from(got.positions()[i][c] - set.positions()[i][c]).powi(2)
                            })
                            .sum::<f64>()
                            .sqrt()
                    })
                    .fold(0.0, f64::max)
            })
            .fold(0.0, f64::max);
        println!("circular scene, at most half a turn: position max {mild}");
        assert!(mild < report.position_max);
        // The stored report survives the file.
        assert_eq!(decode(&model.encode()).unwrap().report(), Some(&report));
    }

    #[test]
    fn one_set_is_the_set_and_two_sets_a_line() {
        let truths = truths(10, 3, 2, false);
        let one = clip(&truths, &[5.0]);
        let model = fit(&one, &camera()).unwrap();
        for t in [5.0, 0.0, 100.0] {
            let got = model.at(t);
            assert_eq!(got.positions(), one[0].1.positions());
            for i in 0..10 {
                assert!((got.opacities()[i] - one[0].1.opacities()[i]).abs() <= 1.0 / 510.0 + 1e-6);
            }
        }
        let report = model.report().unwrap();
        assert_eq!((report.sets, report.position_max), (1, 0.0));
        assert!(report.rotation_max < 2e-3 && report.color_max <= 1.0 / 510.0 + 1e-6);

        let two = clip(&truths, &[1.0, 1.5]);
        let model = fit(&two, &camera()).unwrap();
        let report = *model.report().unwrap();
        println!("two sets: {report:?}");
        // A line through two points, its velocity (≤ 1.5) rounded to a half: ≤ 1.5 · 2^-12.
        assert!(report.position_max < 4e-4, "{report:?}");
        assert!(
            report.rotation_max < 2e-3 && report.opacity_max < 1.0 / 510.0 + 1e-4,
            "{report:?}"
        );
        assert_eq!(model.tau(1.25), 0.5);
    }

    #[test]
    fn encode_decode_encode_is_byte_identical_and_laid_out_for_the_viewer() {
        let truths = truths(1025, 4, 4, false);
        let frames = clip(&truths, &times(4));
        let model = fit(&frames, &camera()).unwrap();
        let bytes = model.encode();
        let back = decode(&bytes).unwrap();
        assert_eq!(back, model);
        assert_eq!(back.encode(), bytes);

        assert_eq!(u32::from_le_bytes(bytes[0..4].try_into().unwrap()), MAGIC);
        let json_len = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
        let header: Value = serde_json::from_slice(&bytes[8..8 + json_len]).unwrap();
        let chunk = &header[0];
        assert_eq!(chunk["type"], "splat");
        assert_eq!(
            (chunk["texwidth"].as_u64(), chunk["texheight"].as_u64()),
            (Some(4096), Some(2))
        );
        assert_eq!(chunk["size"].as_u64(), Some(2 * 4096 * 16));
        assert_eq!(bytes.len(), 8 + json_len + 2 * 4096 * 16);
        assert_eq!(chunk["cameras"][0]["fx"].as_f64(), Some(0.8767 * 224.0));
        assert_eq!(chunk["c4g"]["count"].as_u64(), Some(1025));
        assert_eq!(chunk["c4g"]["times"].as_array().map(Vec::len), Some(4));
        // Gaussian 1024 opens the second texture row: 4096 texels of 16 bytes in.
        let at = 8 + json_len + 4096 * 16;
        let x = f32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        assert_eq!(x, f32::from_bits(model.records[1024][0]));
        // The padding is never visible in the viewer: its temporal factor is 0 all clip long.
        let pad = at + RECORD;
        let word = u32::from_le_bytes(bytes[pad + 60..pad + 64].try_into().unwrap());
        let (c, s) = unpack(word);
        assert!((-((1.0 - c) / s).powi(2)).exp() < VISIBILITY_CUTOFF);
        assert_eq!(bytes[pad + 31], 0);
    }

    #[test]
    fn files_without_our_field_take_every_texel_group_and_time_as_tau() {
        let truths = truths(3, 5, 3, false);
        let model = fit(&clip(&truths, &[0.0, 1.0, 2.0]), &camera()).unwrap();
        let foreign = Splatv {
            clip: None,
            ..model.clone()
        };
        let back = decode(&foreign.encode()).unwrap();
        assert_eq!(back.len(), GAUSSIANS_PER_ROW);
        assert_eq!(back.tau(0.5), 0.5);
        assert_eq!(back.at(0.5).positions()[..3], model.at(1.0).positions()[..]);
        assert_eq!(back.at(0.5).opacities()[3..], [0.0; GAUSSIANS_PER_ROW - 3]);
    }

    fn with_header(bytes: &[u8], edit: impl Fn(&mut Value)) -> Vec<u8> {
        let json_len = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
        let mut header: Value = serde_json::from_slice(&bytes[8..8 + json_len]).unwrap();
        edit(&mut header);
        let json = serde_json::to_vec(&header).unwrap();
        let mut out = bytes[..4].to_vec();
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(&bytes[8 + json_len..]);
        out
    }

    #[test]
    fn bad_bytes_are_errors_that_say_what_and_where() {
        let truths = truths(5, 6, 3, false);
        let bytes = fit(&clip(&truths, &[0.0, 1.0, 2.0]), &camera())
            .unwrap()
            .encode();
        let json_len = u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize;
        let data = 8 + json_len;
        // Every cut through the preamble, header and first records, and some further in.
        for cut in (0..data + 3 * RECORD).chain((data..bytes.len()).step_by(997)) {
            let err = decode(&bytes[..cut]).unwrap_err();
            assert!(
                matches!(
                    err,
                    SceneError::Format {
                        format: "splatv",
                        ..
                    }
                ),
                "{err}"
            );
        }
        let mut rng = Rng(7);
        for _ in 0..2000 {
            let mut bad = bytes.clone();
            let at = rng.uniform(0.0, (data + 5 * RECORD) as f64) as usize;
            bad[at] ^= 1 << (rng.uniform(0.0, 8.0) as u32);
            let _ = decode(&bad); // an error or a model, never a panic
        }
        let expect = |bytes: &[u8], words: &str| {
            let err = decode(bytes).unwrap_err().to_string();
            assert!(err.contains(words), "{err:?} does not say {words:?}");
        };
        expect(&bytes[..5], "5 bytes");
        expect(&[0u8; 16], "magic 0x0");
        expect(&bytes[..data - 1], "JSON");
        expect(&bytes[..bytes.len() - 1], "past the end");
        expect(
            &with_header(&bytes, |h| h[0]["type"] = "other".into()),
            "type \"splat\"",
        );
        expect(
            &with_header(&bytes, |h| h[0]["texwidth"] = 2048.into()),
            "texwidth 2048",
        );
        expect(
            &with_header(&bytes, |h| h[0]["texheight"] = 2.into()),
            "4096 · 2 · 16",
        );
        expect(
            &with_header(&bytes, |h| h[0]["cameras"] = Value::Array(vec![])),
            "no cameras",
        );
        expect(
            &with_header(&bytes, |h| h[0]["cameras"][0]["fx"] = (-1.0).into()),
            "camera 0",
        );
        expect(
            &with_header(&bytes, |h| h[0]["c4g"]["count"] = 5000.into()),
            "c4g.count 5000",
        );
        expect(
            &with_header(&bytes, |h| h[0]["c4g"]["end"] = (-1.0).into()),
            "time range",
        );
        expect(
            &with_header(&bytes, |h| h[0]["size"] = "big".into()),
            "no \"size\"",
        );
        let mut nan = bytes.clone();
        nan[data + RECORD..data + RECORD + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        expect(&nan, "Gaussian 1");
        let mut zero_scale = bytes.clone();
        let w = data + 2 * RECORD + 62;
        zero_scale[w..w + 2].copy_from_slice(&[0, 0]);
        expect(&zero_scale, "Gaussian 2");
        // A preceding chunk of another type is skipped.
        let mut two_chunks = with_header(&bytes, |h| {
            let splat = h[0].clone();
            *h = Value::Array(vec![serde_json::json!({"type": "other", "size": 3}), splat]);
        });
        let json_len = u32::from_le_bytes(two_chunks[4..8].try_into().unwrap()) as usize;
        two_chunks.splice(8 + json_len..8 + json_len, [1, 2, 3]);
        assert_eq!(decode(&two_chunks).unwrap().len(), 5);
    }

    #[test]
    fn inputs_the_fit_cannot_take_are_refused() {
        let truths = truths(4, 8, 2, false);
        let mut frames = clip(&truths, &[0.0, 1.0]);
        let short = GaussianSet::new(
            frames[1].1.positions()[..3].to_vec(),
            frames[1].1.scales()[..3].to_vec(),
            frames[1].1.rotations()[..3].to_vec(),
            frames[1].1.opacities()[..3].to_vec(),
            frames[1].1.colors()[..3].to_vec(),
        )
        .unwrap();
        let err = fit(&[frames[0].clone(), (1.0, short)], &camera())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("set 1") && err.contains("3 Gaussians") && err.contains("4"),
            "{err}"
        );
        let err = fit(&[frames[1].clone(), frames[0].clone()], &camera())
            .unwrap_err()
            .to_string();
        assert!(err.contains("times must increase"), "{err}");
        assert!(
            fit(&[], &camera())
                .unwrap_err()
                .to_string()
                .contains("no sets")
        );
        let err = fit(&frames, &Camera::first_context(0, 10)).unwrap_err();
        assert!(matches!(err, SceneError::InvalidCamera(_)), "{err}");
        frames[1].1 = GaussianSet::new(
            frames[1].1.positions().to_vec(),
            frames[1].1.scales().to_vec(),
            vec![[0.0; 4]; 4],
            frames[1].1.opacities().to_vec(),
            frames[1].1.colors().to_vec(),
        )
        .unwrap();
        let err = fit(&frames, &camera()).unwrap_err().to_string();
        assert!(
            err.contains("Gaussian 0") && err.contains("rotation"),
            "{err}"
        );
    }

    #[test]
    fn cameras_convert_from_ours() {
        let k = c4g_scene::NormalizedIntrinsics::C4G_DEFAULT.to_pixels(224, 224);
        let pose = glam::Affine3A::from_rotation_translation(
            Quat::from_rotation_y(0.3),
            Vec3::new(1.0, 2.0, 3.0),
        );
        let ours = c4g_scene::Camera::from_camera_to_world(k, pose).unwrap();
        let theirs = Camera::from(&ours);
        assert!((theirs.fx - 0.8767 * 224.0).abs() < 1e-3);
        assert!((theirs.position[2] - 3.0).abs() < 1e-5);
        // rotation[row][column]: the camera's x axis is the first column.
        let x = pose.matrix3.col(0);
        assert!((theirs.rotation[2][0] - f64::from(x.z)).abs() < 1e-6);
        let identity = Camera::from(
            &c4g_scene::Camera::from_camera_to_world(k, glam::Affine3A::IDENTITY).unwrap(),
        );
        assert_eq!(identity.rotation, camera().rotation);
    }
}
