//! Fitted scenes, stored with their clip: what a fit job (`crate::jobs::fit`) made of a clip's
//! own frames, kept beside the clip's record and served in place of the feed-forward scene.
//!
//! - **One file, written whole**: `<clip>/fitted.bin` holds the summary (JSON, length-prefixed)
//!   and the scene (`c4g_fit::file`'s `C4GF` bytes). It is written to a temporary name, synced,
//!   renamed into place and the rename synced, so a crash (even of the machine) leaves the earlier
//!   fitted scene or the new one, never a mix; a fit that fails or is cancelled writes nothing,
//!   and the feed-forward scene is never touched.
//! - **Checked when read**: a file that does not decode (bit rot, a foreign file) is logged and
//!   served as no fitted scene, never as an error of every request on the clip.
//! - **Shared**: with a shared store the same bytes go to `<id>/fitted.bin` there (after the local
//!   write), so every replica serves the fitted scene; a replica looks there again at most every
//!   [`RECHECK`] for a scene it does not have or one that was replaced.
//! - Deleted with the clip (its directory, and the shared object with the clip's objects).

use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use c4g_engine::KeyframeTrack;
use c4g_fit::FittedScene;
use serde::{Deserialize, Serialize};

use crate::ServiceError;
use crate::clips::durable::{sync_dir, write_synced};
use crate::clips::store::ClipStore;

/// The file in a clip's directory (and the object beside the clip's in a shared store).
pub const FILE: &str = "fitted.bin";

/// How long a replica trusts what it last saw of a shared fitted scene.
pub const RECHECK: Duration = Duration::from_secs(5);

/// What a fit made, as the clip's record shows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FittedSummary {
    /// The job that made it.
    pub job_id: String,
    /// The preset it started from (`fast`, `default`, `best`).
    pub preset: String,
    /// Gaussians per keyframe.
    pub gaussians: usize,
    /// Of those, the ones that share one value across keyframes.
    pub static_gaussians: usize,
    /// Keyframe times, seconds.
    pub keyframes: Vec<f64>,
    /// Optimisation steps taken.
    pub steps: u64,
    /// Seconds the fit took on its worker.
    pub seconds: f64,
    /// Source frames it was supervised by (training and held out).
    pub frames: usize,
    /// Working resolution (width, height) of those frames.
    pub resolution: [u32; 2],
    /// Indices (among the fit's source frames, in time order) of the frames never trained on.
    pub holdout_frames: Vec<usize>,
    /// Their times, seconds.
    pub holdout_times: Vec<f64>,
    /// Mean PSNR of the held-out frames at their input cameras: the fitted scene's.
    pub holdout_psnr: Option<f64>,
    /// The same for the feed-forward scene the fit started from.
    pub holdout_psnr_feed_forward: Option<f64>,
    /// Mean PSNR of the training frames, fitted.
    pub train_psnr: f64,
    /// The fit stopped before its steps (time budget).
    pub stopped_early: bool,
    /// Unix seconds.
    pub created_at: u64,
    /// What a person should know about this fit beyond its numbers (a camera that probably
    /// moved); empty for most. Absent from scenes stored before it.
    #[serde(default)]
    pub notes: Vec<String>,
}

/// A fitted scene ready to serve: its summary, keyframes and the engine's track through them.
pub struct Fitted {
    /// What the fit made.
    pub summary: FittedSummary,
    /// The keyframe sets.
    pub scene: FittedScene,
    /// The track the sets are served from (built once, shared by the plans that serve it).
    pub track: Arc<KeyframeTrack>,
}

impl std::fmt::Debug for Fitted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Fitted")
            .field("summary", &self.summary)
            .finish_non_exhaustive()
    }
}

impl PartialEq for Fitted {
    fn eq(&self, other: &Self) -> bool {
        self.summary == other.summary && self.scene == other.scene
    }
}

impl Fitted {
    /// Checks and prepares a scene with its summary.
    pub fn new(summary: FittedSummary, scene: FittedScene) -> Result<Self, ServiceError> {
        let track = scene.track().map_err(|e| {
            ServiceError::invalid(format!("the fitted scene cannot be served: {e}"))
        })?;
        Ok(Self {
            summary,
            scene,
            track: Arc::new(track),
        })
    }

    /// The file's bytes: the summary's length (u32, little-endian), the summary (JSON), the scene.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ServiceError> {
        let summary = serde_json::to_vec(&self.summary)
            .map_err(|e| ServiceError::Internal(format!("cannot write a fitted summary: {e}")))?;
        let length = u32::try_from(summary.len())
            .map_err(|_| ServiceError::Internal("the fitted summary is too long".into()))?;
        let mut bytes = length.to_le_bytes().to_vec();
        bytes.extend_from_slice(&summary);
        bytes.extend_from_slice(&c4g_fit::file::to_bytes(&self.scene));
        Ok(bytes)
    }

    /// Reads [`to_bytes`](Self::to_bytes)' layout; any other bytes are refused with the reason.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        let (head, rest) = bytes
            .split_first_chunk::<4>()
            .ok_or("shorter than its header")?;
        let length = u32::from_le_bytes(*head) as usize;
        if rest.len() < length {
            return Err("the summary is cut short".into());
        }
        let (summary, scene) = rest.split_at(length);
        let summary: FittedSummary =
            serde_json::from_slice(summary).map_err(|e| format!("the summary: {e}"))?;
        let scene = c4g_fit::file::from_bytes(scene).map_err(|e| format!("the scene: {e}"))?;
        Self::new(summary, scene).map_err(|e| e.to_string())
    }
}

/// What this replica knows of one clip's fitted scene.
struct Known {
    fitted: Option<Arc<Fitted>>,
    /// When the shared store was last asked (`None`: never, or no shared store).
    checked: Option<Instant>,
    /// The shared object's version as last loaded (its `e_tag` or time).
    version: Option<String>,
}

/// Every clip's fitted scene, read from disk (or the shared store) once and kept in memory.
pub struct FittedScenes {
    store: Arc<ClipStore>,
    known: Mutex<HashMap<String, Known>>,
}

impl FittedScenes {
    /// The fitted scenes of the clips in `store`.
    pub fn new(store: Arc<ClipStore>) -> Self {
        Self {
            store,
            known: Mutex::new(HashMap::new()),
        }
    }

    fn known(&self) -> std::sync::MutexGuard<'_, HashMap<String, Known>> {
        // Every update is one insert or remove: a panic elsewhere leaves the map consistent.
        self.known.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Clip `id`'s fitted scene, if it has one (the clip must exist: callers looked it up).
    pub async fn get(&self, id: &str) -> Result<Option<Arc<Fitted>>, ServiceError> {
        let fresh = |k: &Known| k.checked.is_none_or(|t| t.elapsed() < RECHECK);
        if let Some(known) = self.known().get(id)
            && (self.store.shared().is_none() || fresh(known))
        {
            return Ok(known.fitted.clone());
        }
        let path = self.store.clip_file(id, FILE);
        let local = read_local(id, &path);
        let Some(shared) = self.store.shared() else {
            self.known().insert(
                id.to_owned(),
                Known {
                    fitted: local.clone(),
                    checked: None,
                    version: None,
                },
            );
            return Ok(local);
        };
        // The shared store says which version is current; fetch it when this replica's differs.
        let version = shared.version(id, FILE).await?;
        let loaded_version = self.known().get(id).and_then(|k| k.version.clone());
        let fitted = match &version {
            None => None,
            Some(v) if local.is_some() && loaded_version.as_ref() == Some(v) => local,
            Some(_) => match shared.get_file(id, FILE).await? {
                None => None,
                Some(bytes) => match Fitted::from_bytes(&bytes) {
                    Ok(fitted) => {
                        if let Err(e) = replace(&path, &bytes) {
                            tracing::warn!(clip = id, "cannot keep the shared fitted scene: {e}");
                        }
                        Some(Arc::new(fitted))
                    }
                    Err(why) => {
                        tracing::warn!(clip = id, "the shared fitted scene is unreadable: {why}");
                        None
                    }
                },
            },
        };
        self.known().insert(
            id.to_owned(),
            Known {
                fitted: fitted.clone(),
                checked: Some(Instant::now()),
                version,
            },
        );
        Ok(fitted)
    }

    /// Keeps `fitted` as clip `id`'s fitted scene, replacing any earlier one, on disk (crash-safe)
    /// and in the shared store. A clip deleted meanwhile is `not_found`, and nothing is left in
    /// its place.
    pub async fn put(&self, id: &str, fitted: Fitted) -> Result<Arc<Fitted>, ServiceError> {
        let bytes = fitted.to_bytes()?;
        let dir = self.store.clip_file(id, "");
        if !dir.is_dir() {
            self.store.get_or_fetch(id).await?;
        }
        let path = self.store.clip_file(id, FILE);
        replace(&path, &bytes).map_err(|e| {
            let error = ServiceError::storage("cannot keep the fitted scene", &e);
            self.store.unless_gone(id, error)
        })?;
        // Deleted while it was written: the delete renames the directory away first, so the
        // write above failed, or it landed in the directory the delete then removes.
        self.store.get(id)?;
        let version = match self.store.shared() {
            Some(shared) => {
                shared.put_file(id, FILE, bytes).await?;
                shared.version(id, FILE).await?
            }
            None => None,
        };
        let fitted = Arc::new(fitted);
        self.known().insert(
            id.to_owned(),
            Known {
                fitted: Some(fitted.clone()),
                checked: self.store.shared().map(|_| Instant::now()),
                version,
            },
        );
        Ok(fitted)
    }

    /// Forgets clip `id`'s fitted scene (the clip was deleted).
    pub fn forget(&self, id: &str) {
        self.known().remove(id);
    }
}

/// The local file, when it reads; an unreadable one is logged and ignored.
fn read_local(id: &str, path: &Path) -> Option<Arc<Fitted>> {
    let bytes = std::fs::read(path).ok()?;
    match Fitted::from_bytes(&bytes) {
        Ok(fitted) => Some(Arc::new(fitted)),
        Err(why) => {
            tracing::warn!(clip = id, path = %path.display(), "unreadable fitted scene, ignored: {why}");
            None
        }
    }
}

/// `bytes` at `path`, replacing what was there in one rename.
fn replace(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let tmp = dir.join(format!(".tmp-{}", FILE));
    let written = write_synced(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, path))
        .and_then(|()| sync_dir(dir));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use c4g_scene::GaussianSet;

    fn summary() -> FittedSummary {
        FittedSummary {
            job_id: "job-1".into(),
            preset: "fast".into(),
            gaussians: 2,
            static_gaussians: 1,
            keyframes: vec![0.0, 1.0],
            steps: 10,
            seconds: 1.5,
            frames: 8,
            resolution: [32, 24],
            holdout_frames: vec![7],
            holdout_times: vec![0.7],
            holdout_psnr: Some(30.0),
            holdout_psnr_feed_forward: Some(20.0),
            train_psnr: 31.0,
            stopped_early: false,
            created_at: 1,
            notes: vec!["a note".into()],
        }
    }

    fn scene() -> FittedScene {
        let set = |x: f32| {
            GaussianSet::new(
                vec![[x, 0.0, 2.0], [0.0, 1.0, 3.0]],
                vec![[0.1; 3]; 2],
                vec![[1.0, 0.0, 0.0, 0.0]; 2],
                vec![0.5; 2],
                vec![[0.2, 0.4, 0.6]; 2],
            )
            .unwrap()
        };
        FittedScene::new(vec![(0.0, set(0.0)), (1.0, set(0.5))]).unwrap()
    }

    #[test]
    fn a_summary_stored_before_notes_reads_with_none() {
        let mut old = serde_json::to_value(summary()).unwrap();
        old.as_object_mut().unwrap().remove("notes");
        let read: FittedSummary = serde_json::from_value(old).unwrap();
        assert_eq!(read.notes, Vec::<String>::new());
    }

    #[test]
    fn the_file_round_trips_and_damage_is_refused_with_a_reason() {
        let fitted = Fitted::new(summary(), scene()).unwrap();
        let bytes = fitted.to_bytes().unwrap();
        let back = Fitted::from_bytes(&bytes).unwrap();
        assert_eq!((back.summary, back.scene), (summary(), scene()));
        for cut in [0, 3, 10, bytes.len() - 1] {
            assert!(Fitted::from_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut long = bytes.clone();
        long[0..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(Fitted::from_bytes(&long).is_err());
    }

    #[test]
    fn a_replaced_file_is_the_new_one_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE);
        replace(&path, b"old").unwrap();
        replace(&path, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().flatten().collect();
        assert_eq!(names.len(), 1);
    }
}
