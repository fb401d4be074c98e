//! A time series of Gaussian sets on disk: what decoding a clip at many timestamps produces.
//!
//! A directory holding one 3DGS `.ply` per timestamp (any tool opens a single frame) and
//! `series.json`, the index:
//!
//! ```json
//! {"format": "c4g-series", "version": 1,
//!  "frames": [{"time": 0.0, "file": "000000.ply"}, {"time": 0.04, "file": "000001.ply"}]}
//! ```
//!
//! Times are seconds (f64), finite and strictly increasing. File names are plain names inside the
//! directory (no separators, no `..`). [`Series::open`] reads only the index; frames load one at
//! a time, so a long series never has to fit in memory.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{ply, read_file, write_file};
use c4g_scene::{GaussianSet, SceneError};

/// Name of the index file inside a series directory.
pub const INDEX: &str = "series.json";
const FORMAT: &str = "c4g-series";
const VERSION: u32 = 1;

#[derive(Debug, Serialize, Deserialize)]
struct Index {
    format: String,
    version: u32,
    frames: Vec<Entry>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct Entry {
    time: f64,
    file: String,
}

/// An opened series: its timestamps and where each frame lives.
#[derive(Debug, Clone)]
pub struct Series {
    dir: PathBuf,
    frames: Vec<Entry>,
}

impl Series {
    /// Reads and checks the index of the series in `dir`.
    pub fn open(dir: &Path) -> Result<Self, SceneError> {
        let path = dir.join(INDEX);
        let index: Index = serde_json::from_slice(&read_file(&path)?)
            .map_err(|e| series_error(format!("{}: {e}", path.display())))?;
        if index.format != FORMAT || index.version != VERSION {
            return Err(series_error(format!(
                "{}: format {:?} version {} is not {FORMAT:?} version {VERSION}",
                path.display(),
                index.format,
                index.version
            )));
        }
        check_times(index.frames.iter().map(|e| e.time))?;
        for entry in &index.frames {
            check_file_name(&entry.file)?;
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            frames: index.frames,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True when the series has no frames.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Timestamps in seconds, increasing.
    pub fn times(&self) -> Vec<f64> {
        self.frames.iter().map(|e| e.time).collect()
    }

    /// Loads frame `index`.
    pub fn load(&self, index: usize) -> Result<GaussianSet, SceneError> {
        let entry = self.frames.get(index).ok_or_else(|| {
            series_error(format!(
                "frame {index} of a series of {}",
                self.frames.len()
            ))
        })?;
        ply::read(&self.dir.join(&entry.file))
    }
}

/// Writes `frames` (time in seconds, set) as a series in `dir`, creating it if needed; frame `k`
/// goes to `{k:06}.ply`.
pub fn write(dir: &Path, frames: &[(f64, &GaussianSet)]) -> Result<(), SceneError> {
    check_times(frames.iter().map(|(t, _)| *t))?;
    std::fs::create_dir_all(dir).map_err(|e| super::io_error(dir, e))?;
    let mut entries = Vec::with_capacity(frames.len());
    for (k, (time, set)) in frames.iter().enumerate() {
        let file = format!("{k:06}.ply");
        ply::write(&dir.join(&file), set)?;
        entries.push(Entry { time: *time, file });
    }
    let index = Index {
        format: FORMAT.to_owned(),
        version: VERSION,
        frames: entries,
    };
    let json = serde_json::to_vec_pretty(&index).map_err(|e| series_error(e.to_string()))?;
    write_file(&dir.join(INDEX), &json)
}

pub(super) fn check_times(times: impl Iterator<Item = f64>) -> Result<(), SceneError> {
    let mut last = f64::NEG_INFINITY;
    for (k, t) in times.enumerate() {
        if !t.is_finite() || t <= last {
            return Err(series_error(format!(
                "frame {k}: time {t} is not finite and after the previous one ({last})"
            )));
        }
        last = t;
    }
    Ok(())
}

fn check_file_name(name: &str) -> Result<(), SceneError> {
    let plain = !name.is_empty()
        && name != "."
        && name != ".."
        && !name.contains(['/', '\\'])
        && Path::new(name).file_name().is_some_and(|f| f == name);
    if plain {
        Ok(())
    } else {
        Err(series_error(format!(
            "frame file {name:?} is not a plain name inside the series directory"
        )))
    }
}

fn series_error(reason: impl Into<String>) -> SceneError {
    SceneError::Format {
        format: "series",
        reason: reason.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("c4g-series-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn set(x: f32) -> GaussianSet {
        GaussianSet::new(
            vec![[x, 0.0, 1.0]],
            vec![[0.1; 3]],
            vec![[1.0, 0.0, 0.0, 0.0]],
            vec![0.5],
            vec![[0.5; 3]],
        )
        .unwrap()
    }

    #[test]
    fn a_series_round_trips_times_and_frames() {
        let dir = tmp("round-trip");
        let (a, b) = (set(1.0), set(2.0));
        write(&dir, &[(0.0, &a), (0.04, &b)]).unwrap();
        let series = Series::open(&dir).unwrap();
        assert_eq!(series.times(), vec![0.0, 0.04]);
        assert_eq!(series.load(1).unwrap().positions(), b.positions());
        assert!(series.load(2).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn times_must_increase_and_files_stay_inside() {
        let a = set(0.0);
        assert!(write(&tmp("bad-times"), &[(1.0, &a), (1.0, &a)]).is_err());
        assert!(write(&tmp("nan-time"), &[(f64::NAN, &a)]).is_err());
        let dir = tmp("escape");
        std::fs::create_dir_all(&dir).unwrap();
        for file in ["../x.ply", "/etc/passwd", "..", "a/b.ply", ""] {
            let json = format!(
                r#"{{"format": "c4g-series", "version": 1, "frames": [{{"time": 0, "file": {file:?}}}]}}"#
            );
            std::fs::write(dir.join(INDEX), json).unwrap();
            let err = Series::open(&dir).unwrap_err().to_string();
            assert!(err.contains("plain name"), "{file}: {err}");
        }
        std::fs::write(
            dir.join(INDEX),
            r#"{"format": "other", "version": 1, "frames": []}"#,
        )
        .unwrap();
        assert!(Series::open(&dir).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
