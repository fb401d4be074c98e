//! Reading: the incremental decoder, whole streams, the index and seeking.

use std::io::Read;

use flate2::bufread::DeflateDecoder;

use c4g_scene::{GaussianSet, SceneError};

use super::grid::{Values, reconstruct};
use super::*;

/// Where a [`Decoder`] is in the stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Stage {
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
    pub fn next_frame(&mut self) -> Result<Option<(f64, GaussianSet)>, SceneError> {
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
    pub fn finish(&self) -> Result<(), SceneError> {
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
    fn record_head(&self) -> Result<Option<(u8, u8, usize)>, SceneError> {
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

    fn read_static(&mut self, coding: u8, payload: &[u8]) -> Result<(), SceneError> {
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
    ) -> Result<(f64, GaussianSet), SceneError> {
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
    fn assemble(&self, rows: &[Cells], what: &str) -> Result<GaussianSet, SceneError> {
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

    fn read_index(&mut self, payload: &[u8]) -> Result<(), SceneError> {
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
pub(super) fn body_range(head: usize, count: usize) -> (Option<usize>, Option<usize>) {
    let max = count
        .checked_mul(CHANNELS * VARINT_MAX)
        .and_then(|b| b.checked_add(head));
    (Some(head + usize::from(count > 0)), max)
}

/// The cells of `count` Gaussians from a record body: `u32` inflated length, then the stored or
/// deflated columns.
pub(super) fn read_body(
    coding: u8,
    payload: &[u8],
    count: usize,
    what: &str,
) -> Result<Vec<Cells>, SceneError> {
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
pub(super) fn check_cells(rows: &[Cells], ids: &[usize], what: &str) -> Result<(), SceneError> {
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
pub(super) fn inflate(stored: &[u8], raw: usize, what: &str) -> Result<Vec<u8>, SceneError> {
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
pub(super) fn read_varint(bytes: &[u8]) -> Option<(u64, usize)> {
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
pub(super) fn parse_index(payload: &[u8], end: u64) -> Result<Vec<IndexEntry>, SceneError> {
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
pub fn decode(bytes: &[u8]) -> Result<Vec<(f64, GaussianSet)>, SceneError> {
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
pub fn read_index(bytes: &[u8]) -> Result<Vec<IndexEntry>, SceneError> {
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
pub fn seek(bytes: &[u8], time: f64) -> Result<Vec<(f64, GaussianSet)>, SceneError> {
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

pub(super) fn zero_rotation(what: &str, gaussian: usize) -> SceneError {
    format_error(format!(
        "{what}: Gaussian {gaussian}'s rotation decodes to no unit quaternion (zero or not finite)"
    ))
}
