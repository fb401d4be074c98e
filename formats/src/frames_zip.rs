//! A time series of Gaussian sets as one zip of per-time files: what viewers of splat sequences
//! open (Brush plays a zip of `.ply` files in name order as an animation), and a way to hand a
//! whole time range to any tool that reads single sets.
//!
//! The archive holds one entry per set, in time order, named `frame_000000.ply`,
//! `frame_000001.ply`, … (or `.spz`): zero-padded so that name order is time order, which is the
//! only order a player of sequences knows. Nothing else is in it (a player that opens every entry
//! meets only frames). The times live in the archive's comment, which players ignore:
//!
//! ```json
//! {"format": "c4g-frames", "version": 1, "times": [0.0, 0.04]}
//! ```
//!
//! `.ply` entries are DEFLATE-compressed (f32 columns shrink by about a tenth); `.spz` entries are
//! stored, being compressed already. Each entry is exactly the file [`ply::encode`] or
//! [`spz::encode`] makes of its set, so what those formats keep and lose holds here too. Frames
//! keep Gaussian identity: Gaussian `i` is row `i` of every entry.

use std::io::{Cursor, Read, Write};

use serde::{Deserialize, Serialize};
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipArchive, ZipWriter};

use super::{ply, spz};
use c4g_scene::{GaussianSet, SceneError};

const FORMAT: &str = "c4g-frames";
const VERSION: u32 = 1;

/// The file each set becomes inside the archive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    /// The 3DGS `.ply` ([`ply`]), f32 columns.
    Ply,
    /// Niantic's `.spz` ([`spz`]), quantised and compressed.
    Spz,
}

impl FrameFormat {
    /// The entries' extension.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Ply => "ply",
            Self::Spz => "spz",
        }
    }

    fn encode(self, set: &GaussianSet) -> Result<Vec<u8>, SceneError> {
        match self {
            Self::Ply => Ok(ply::encode(set)),
            Self::Spz => spz::encode(set),
        }
    }

    fn decode(self, bytes: &[u8]) -> Result<GaussianSet, SceneError> {
        match self {
            Self::Ply => ply::decode(bytes),
            Self::Spz => spz::decode(bytes),
        }
    }

    fn compression(self) -> CompressionMethod {
        match self {
            Self::Ply => CompressionMethod::Deflated,
            Self::Spz => CompressionMethod::Stored,
        }
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct Index {
    format: String,
    version: u32,
    times: Vec<f64>,
}

/// A zip comment holds at most this many bytes (its length is a u16).
const MAX_COMMENT: usize = u16::MAX as usize;

/// Frames one archive holds at most: their times (JSON numbers of at most 24 characters and a
/// comma) always fit in the comment.
pub const MAX_FRAMES: usize = 2500;

/// The entry name of frame `index`.
pub fn entry_name(index: usize, format: FrameFormat) -> String {
    format!("frame_{index:06}.{}", format.extension())
}

/// The zip of `frames` (times in seconds, strictly increasing) with one `format` file each.
pub fn encode(frames: &[(f64, GaussianSet)], format: FrameFormat) -> Result<Vec<u8>, SceneError> {
    let mut writer = Writer::new(format);
    for (time, set) in frames {
        writer.push(*time, set)?;
    }
    writer.finish()
}

/// A frames zip written set by set, as a stream of sets arrives: only the archive's bytes are
/// held, never the sets.
pub struct Writer {
    zip: ZipWriter<Cursor<Vec<u8>>>,
    format: FrameFormat,
    times: Vec<f64>,
    /// The frames' bytes before compression: at least what the archive holds.
    written: usize,
}

impl Writer {
    /// An empty archive of `format` frames.
    pub fn new(format: FrameFormat) -> Self {
        Self {
            zip: ZipWriter::new(Cursor::new(Vec::new())),
            format,
            times: Vec::new(),
            written: 0,
        }
    }

    /// Appends the set at `time` (seconds, after the previous one's).
    pub fn push(&mut self, time: f64, set: &GaussianSet) -> Result<(), SceneError> {
        if self.times.len() >= MAX_FRAMES {
            return Err(zip_error(format!(
                "a frames zip holds at most {MAX_FRAMES} frames: export fewer times at once"
            )));
        }
        let last = self.times.last().copied().unwrap_or(f64::NEG_INFINITY);
        if !(time.is_finite() && time > last) {
            return Err(zip_error(format!(
                "frame {}: time {time} is not finite and after the previous one ({last})",
                self.times.len()
            )));
        }
        let bytes = self.format.encode(set)?;
        let options = SimpleFileOptions::default()
            .compression_method(self.format.compression())
            .large_file(bytes.len() as u64 >= u64::from(u32::MAX));
        self.zip
            .start_file(entry_name(self.times.len(), self.format), options)
            .map_err(|e| zip_error(e.to_string()))?;
        self.zip
            .write_all(&bytes)
            .map_err(|e| zip_error(e.to_string()))?;
        self.times.push(time);
        self.written += bytes.len();
        Ok(())
    }

    /// The frames' bytes so far, before compression: a bound on the archive's size.
    pub fn bytes(&self) -> usize {
        self.written
    }

    /// The finished archive, its index in the comment.
    pub fn finish(mut self) -> Result<Vec<u8>, SceneError> {
        let index = Index {
            format: FORMAT.to_owned(),
            version: VERSION,
            times: self.times,
        };
        let comment = serde_json::to_string(&index).map_err(|e| zip_error(e.to_string()))?;
        if comment.len() > MAX_COMMENT {
            return Err(zip_error(format!(
                "{} frames make a {}-byte index, more than a zip comment holds ({MAX_COMMENT}): \
                 export fewer times at once",
                index.times.len(),
                comment.len()
            )));
        }
        self.zip
            .set_comment(comment)
            .map_err(|e| zip_error(e.to_string()))?;
        let cursor = self.zip.finish().map_err(|e| zip_error(e.to_string()))?;
        Ok(cursor.into_inner())
    }
}

/// Reads a zip [`encode`] made: its sets with their times, in order. Each entry is read up to
/// `max_entry_bytes` uncompressed (a zip can claim any size).
pub fn decode(
    bytes: &[u8],
    max_entry_bytes: u64,
) -> Result<(FrameFormat, Vec<(f64, GaussianSet)>), SceneError> {
    let mut archive =
        ZipArchive::new(Cursor::new(bytes)).map_err(|e| zip_error(format!("not a zip: {e}")))?;
    let index: Index = serde_json::from_slice(archive.comment())
        .map_err(|e| zip_error(format!("the archive comment is not a {FORMAT} index: {e}")))?;
    if index.format != FORMAT || index.version != VERSION {
        return Err(zip_error(format!(
            "the index is format {:?} version {}, not {FORMAT:?} version {VERSION}",
            index.format, index.version
        )));
    }
    super::series::check_times(index.times.iter().copied())?;
    if archive.len() != index.times.len() {
        return Err(zip_error(format!(
            "{} entries for {} times",
            archive.len(),
            index.times.len()
        )));
    }
    let format = match archive.len() {
        0 => FrameFormat::Ply,
        _ => {
            let first = archive
                .name_for_index(0)
                .and_then(Result::ok)
                .map(|name| name.into_owned())
                .unwrap_or_default();
            [FrameFormat::Ply, FrameFormat::Spz]
                .into_iter()
                .find(|f| first.ends_with(&format!(".{}", f.extension())))
                .ok_or_else(|| zip_error(format!("entry {first:?} is neither .ply nor .spz")))?
        }
    };
    let mut frames = Vec::with_capacity(index.times.len());
    for (i, &time) in index.times.iter().enumerate() {
        let mut entry = archive
            .by_index(i)
            .map_err(|e| zip_error(format!("entry {i}: {e}")))?;
        let expected = entry_name(i, format);
        let name = entry.name().map(|n| n.into_owned()).unwrap_or_default();
        if name != expected {
            return Err(zip_error(format!(
                "entry {i} is {name:?}, expected {expected:?}"
            )));
        }
        let mut data = Vec::new();
        (&mut entry)
            .take(max_entry_bytes.saturating_add(1))
            .read_to_end(&mut data)
            .map_err(|e| zip_error(format!("{expected}: {e}")))?;
        if data.len() as u64 > max_entry_bytes {
            return Err(zip_error(format!(
                "{expected} is larger than {max_entry_bytes} bytes"
            )));
        }
        let set = format.decode(&data).map_err(|e| match e {
            SceneError::Format { format, reason } => SceneError::Format {
                format,
                reason: format!("{expected}: {reason}"),
            },
            other => other,
        })?;
        frames.push((time, set));
    }
    Ok((format, frames))
}

fn zip_error(reason: String) -> SceneError {
    SceneError::Format {
        format: "frames zip",
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(shift: f32) -> GaussianSet {
        GaussianSet::new(
            vec![[shift, 0.5, 2.0], [-0.25, shift, 3.0]],
            vec![[0.01, 0.02, 0.03], [0.1, 0.1, 0.1]],
            vec![[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]],
            vec![0.25, 0.9],
            vec![[0.1, 0.5, 0.9], [0.8, 0.2, 0.4]],
        )
        .unwrap()
    }

    fn frames() -> Vec<(f64, GaussianSet)> {
        vec![(0.0, set(0.0)), (0.04, set(0.1)), (0.08, set(0.2))]
    }

    #[test]
    fn ply_frames_come_back_exactly_with_their_times_in_name_order() {
        let bytes = encode(&frames(), FrameFormat::Ply).unwrap();
        let mut archive = ZipArchive::new(Cursor::new(&bytes[..])).unwrap();
        let names: Vec<String> = archive
            .file_names()
            .map(|n| n.unwrap().into_owned())
            .collect();
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        assert_eq!(names[0], "frame_000000.ply");
        // Each entry is the single-set file, byte for byte.
        let mut first = Vec::new();
        archive
            .by_index(0)
            .unwrap()
            .read_to_end(&mut first)
            .unwrap();
        assert_eq!(first, ply::encode(&frames()[0].1));

        let (format, back) = decode(&bytes, 1 << 20).unwrap();
        assert_eq!(format, FrameFormat::Ply);
        assert_eq!(back.len(), 3);
        for ((t, s), (t2, s2)) in frames().iter().zip(&back) {
            assert_eq!(t, t2);
            assert_eq!(s.positions(), s2.positions());
        }
    }

    #[test]
    fn spz_frames_are_stored_and_read_back() {
        let bytes = encode(&frames(), FrameFormat::Spz).unwrap();
        let archive = ZipArchive::new(Cursor::new(&bytes[..])).unwrap();
        assert_eq!(
            archive.name_for_index(2).unwrap().unwrap(),
            "frame_000002.spz"
        );
        let (format, back) = decode(&bytes, 1 << 20).unwrap();
        assert_eq!(format, FrameFormat::Spz);
        assert_eq!(back[1].0, 0.04);
        assert_eq!(back[1].1.len(), 2);
    }

    #[test]
    fn bad_times_archives_and_oversized_entries_are_refused() {
        let mut unordered = frames();
        unordered.swap(0, 1);
        assert!(encode(&unordered, FrameFormat::Ply).is_err());

        let bytes = encode(&frames(), FrameFormat::Ply).unwrap();
        let e = decode(&bytes, 64).unwrap_err().to_string();
        assert!(e.contains("larger than 64 bytes"), "{e}");
        assert!(decode(b"not a zip", 1 << 20).is_err());
        for cut in [0, 10, bytes.len() / 2, bytes.len() - 1] {
            assert!(decode(&bytes[..cut], 1 << 20).is_err(), "cut at {cut}");
        }
        // A zip without our index.
        let mut plain = ZipWriter::new(Cursor::new(Vec::new()));
        plain
            .start_file("frame_000000.ply", SimpleFileOptions::default())
            .unwrap();
        plain.write_all(&ply::encode(&set(0.0))).unwrap();
        let plain = plain.finish().unwrap().into_inner();
        let e = decode(&plain, 1 << 20).unwrap_err().to_string();
        assert!(e.contains("index"), "{e}");
    }
}
