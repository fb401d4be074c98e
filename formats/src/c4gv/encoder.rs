//! Writing: the streaming encoder, the static mask, and whole streams at once.

use std::io::Write;

use flate2::Compression;
use flate2::write::DeflateEncoder;

use c4g_scene::{GaussianSet, SceneError};

use super::grid::{Values, out_of_bounds, quantise_set, reconstruct};
use super::*;

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
    fn validate(&self) -> Result<(), SceneError> {
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

/// The streaming encoder: a header first, then one record per pushed set, then the index.
#[derive(Debug)]
pub struct Encoder {
    options: EncodeOptions,
    header: Header,
    statics: Vec<usize>,
    movers: Vec<usize>,
    /// The static Gaussians' decoded values, from the first frame on.
    pub(super) held: Option<Vec<Values>>,
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
    ) -> Result<(Self, Vec<u8>), SceneError> {
        Self::with_static_mask(&vec![false; gaussian_count], options)
    }

    /// An encoder for frames of `static_mask.len()` Gaussians, those marked `true` sent once and
    /// held (see the module's "Static Gaussians"), and the header bytes to send first.
    pub fn with_static_mask(
        static_mask: &[bool],
        options: &EncodeOptions,
    ) -> Result<(Self, Vec<u8>), SceneError> {
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
    pub fn push(&mut self, time: f64, set: &GaussianSet) -> Result<Vec<u8>, SceneError> {
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
    ) -> Result<(), SceneError> {
        for (&i, values) in self.statics.iter().zip(held) {
            let same = reconstruct(&cells[i], &self.header.steps).as_ref() == Some(values);
            if same {
                continue;
            }
            if let Some(why) = out_of_bounds(set, i, values, self.options.position_error) {
                return Err(SceneError::InvalidGaussian {
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

/// A body: 14 columns of zigzag varints, `value(row, channel)` for every row of each in turn.
pub(super) fn columns(rows: &[Cells], value: impl Fn(usize, usize) -> i64) -> Vec<u8> {
    let mut out = Vec::with_capacity(rows.len() * CHANNELS * 2);
    for k in 0..CHANNELS {
        for g in 0..rows.len() {
            put_varint(&mut out, zigzag(value(g, k)));
        }
    }
    out
}

/// `body` as raw DEFLATE (`None` if the compressor fails, which writing to memory does not).
pub(super) fn deflate(body: &[u8]) -> Option<Vec<u8>> {
    let mut encoder = DeflateEncoder::new(Vec::new(), Compression::best());
    encoder.write_all(body).ok()?;
    encoder.finish().ok()
}

pub(super) fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Per Gaussian of one clip's sets, whether every cell is the same in all of them (at
/// `options`' grid): what [`encode`] sends once. Fails as [`Encoder::push`] would on the sets.
pub fn static_mask<'a>(
    sets: impl IntoIterator<Item = &'a GaussianSet>,
    options: &EncodeOptions,
) -> Result<Vec<bool>, SceneError> {
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
) -> Result<Vec<u8>, SceneError> {
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
