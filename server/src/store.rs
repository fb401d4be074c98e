//! The clip store: every encoded clip, on disk and (its encoder features) in a memory cache.
//!
//! - Ids are content addresses ([`crate::intake::clip_id`]): the same upload is encoded once.
//! - A clip is written to disk when it is encoded (`<dir>/<model key>/clips/<id>/`: `clip.json`,
//!   `features.f32` as little-endian floats, and the context frames as PNG), atomically (a
//!   temporary directory renamed into place), so a restart serves it without encoding again and a
//!   crash never leaves half a clip.
//! - Features live in an LRU cache under a byte budget; an evicted clip reloads from disk on its
//!   next request.
//! - Concurrent uploads of one clip encode it once: later callers wait for the first.
//!
//! Clips are kept per model (the model key hashes the package), so a server on another model
//! never decodes features it did not make.

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{SystemTime, UNIX_EPOCH};

use c4g_engine::Encoding;
use image::RgbImage;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use lru::LruCache;
use serde::{Deserialize, Serialize};
use tokio::sync::OnceCell;

use crate::ServiceError;
use crate::intake::{IntakeOptions, SourceInfo};

/// What the store knows about a clip without its features.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClipRecord {
    /// Content address.
    pub id: String,
    /// The model's name.
    pub model: String,
    /// Seconds since the Unix epoch when it was encoded.
    pub created_at: u64,
    /// How the upload was read.
    pub options: IntakeOptions,
    /// What the upload was.
    pub source: SourceInfo,
    /// Context times in encoded (increasing) order.
    pub context_times: Vec<f64>,
    /// Where each encoded frame was in the caller's list.
    pub frame_order: Vec<usize>,
    /// `[T, P, C]` of the features.
    pub feature_shape: [usize; 3],
    /// Seconds between the source's frames, when known (the time policy's floor; see
    /// [`frame_step`](Self::frame_step)). Absent in clips stored before it was recorded.
    #[serde(default)]
    pub frame_step: Option<f64>,
}

impl ClipRecord {
    /// Bytes of the clip's features.
    pub fn feature_bytes(&self) -> u64 {
        self.feature_shape.iter().product::<usize>() as u64 * 4
    }

    /// The source's frame step decodes use: the recorded one, else (a clip stored before it was
    /// recorded) the source's frame period `1 / fps`, else unknown.
    pub fn frame_step(&self) -> Option<f64> {
        let positive = |s: &f64| s.is_finite() && *s > 0.0;
        self.frame_step
            .filter(positive)
            .or_else(|| Some(1.0 / self.source.fps).filter(positive))
    }

    /// The span decode and render accept.
    pub fn span(&self) -> (f64, f64) {
        (
            self.context_times.first().copied().unwrap_or(0.0),
            self.context_times.last().copied().unwrap_or(0.0),
        )
    }
}

/// A freshly encoded clip, for [`ClipStore::get_or_create`].
pub struct NewClip {
    /// Its description.
    pub record: ClipRecord,
    /// Its features.
    pub encoding: Encoding,
    /// Its context frames (kept for rendering comparisons and refinement).
    pub frames: Vec<RgbImage>,
}

/// See the module documentation.
pub struct ClipStore {
    dir: PathBuf,
    budget: u64,
    state: Mutex<State>,
}

struct State {
    records: BTreeMap<String, Arc<ClipRecord>>,
    cache: LruCache<String, Arc<Encoding>>,
    cached_bytes: u64,
    inflight: HashMap<String, Arc<OnceCell<Arc<ClipRecord>>>>,
}

impl ClipStore {
    /// Opens (creating) the store for the model with key `model_key` under `root`, loading every
    /// clip's record (features load when first asked for). Unreadable clip directories are
    /// logged and skipped, never deleted.
    pub fn open(root: &Path, model_key: &str, budget_bytes: u64) -> Result<Self, ServiceError> {
        let dir = root.join(model_key).join("clips");
        std::fs::create_dir_all(&dir).map_err(|e| {
            ServiceError::Internal(format!("cannot create the store {}: {e}", dir.display()))
        })?;
        let mut records = BTreeMap::new();
        let entries = std::fs::read_dir(&dir).map_err(|e| {
            ServiceError::Internal(format!("cannot read the store {}: {e}", dir.display()))
        })?;
        for entry in entries.flatten() {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                // An interrupted write: never complete, safe to drop.
                let _ = std::fs::remove_dir_all(&path);
                continue;
            }
            match read_record(&path) {
                Ok(record) if record.id == name => {
                    records.insert(name, Arc::new(record));
                }
                Ok(_) => {
                    tracing::warn!(path = %path.display(), "clip id does not match its directory; skipped")
                }
                Err(e) => tracing::warn!(path = %path.display(), "unreadable clip skipped: {e}"),
            }
        }
        tracing::info!(clips = records.len(), dir = %dir.display(), "clip store opened");
        metrics::gauge!("c4g_clips").set(records.len() as f64);
        Ok(Self {
            dir,
            budget: budget_bytes,
            state: Mutex::new(State {
                records,
                cache: LruCache::unbounded(),
                cached_bytes: 0,
                inflight: HashMap::new(),
            }),
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves consistent data (every update is one step).
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Every clip, oldest first.
    pub fn list(&self) -> Vec<Arc<ClipRecord>> {
        let mut all: Vec<_> = self.lock().records.values().cloned().collect();
        all.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        all
    }

    /// One clip's record.
    pub fn get(&self, id: &str) -> Result<Arc<ClipRecord>, ServiceError> {
        self.lock()
            .records
            .get(id)
            .cloned()
            .ok_or_else(|| not_found(id))
    }

    /// The clip `id`, made by `create` when it does not exist yet; `true` when this call made it.
    /// Concurrent calls for one id run `create` once; the others wait and share its result (a
    /// failure is not shared: the next caller tries again).
    pub async fn get_or_create<F, Fut>(
        &self,
        id: &str,
        create: F,
    ) -> Result<(Arc<ClipRecord>, bool), ServiceError>
    where
        F: FnOnce() -> Fut,
        Fut: Future<Output = Result<NewClip, ServiceError>>,
    {
        let cell = {
            let mut state = self.lock();
            if let Some(record) = state.records.get(id) {
                return Ok((record.clone(), false));
            }
            state.inflight.entry(id.to_owned()).or_default().clone()
        };
        let mut created = false;
        let result = cell
            .get_or_try_init(|| async {
                let new = create().await?;
                let record = Arc::new(new.record.clone());
                self.persist(new).await?;
                created = true;
                Ok::<_, ServiceError>(record)
            })
            .await
            .cloned();
        let mut state = self.lock();
        if state
            .inflight
            .get(id)
            .is_some_and(|c| Arc::ptr_eq(c, &cell))
            && cell.initialized()
        {
            state.inflight.remove(id);
        }
        result.map(|record| (record, created))
    }

    async fn persist(&self, new: NewClip) -> Result<(), ServiceError> {
        let NewClip {
            record,
            encoding,
            frames,
        } = new;
        let encoding = Arc::new(encoding);
        let (dir, id) = (self.dir.clone(), record.id.clone());
        let to_write = (record.clone(), encoding.clone());
        tokio::task::spawn_blocking(move || write_clip(&dir, &to_write.0, &to_write.1, &frames))
            .await
            .map_err(|e| ServiceError::Internal(format!("writing a clip panicked: {e}")))??;
        let mut state = self.lock();
        state.records.insert(id.clone(), Arc::new(record));
        metrics::gauge!("c4g_clips").set(state.records.len() as f64);
        self.insert_cached(&mut state, id, encoding);
        Ok(())
    }

    /// The clip's encoder features: from memory, or read back from disk.
    pub async fn encoding(&self, id: &str) -> Result<Arc<Encoding>, ServiceError> {
        let record = {
            let mut state = self.lock();
            if let Some(encoding) = state.cache.get(id) {
                metrics::counter!("c4g_cache_hits_total").increment(1);
                return Ok(encoding.clone());
            }
            state
                .records
                .get(id)
                .cloned()
                .ok_or_else(|| not_found(id))?
        };
        metrics::counter!("c4g_cache_misses_total").increment(1);
        let path = self.dir.join(id);
        let encoding = tokio::task::spawn_blocking(move || read_features(&path, &record))
            .await
            .map_err(|e| ServiceError::Internal(format!("reading features panicked: {e}")))??;
        let encoding = Arc::new(encoding);
        let mut state = self.lock();
        if state.records.contains_key(id) {
            self.insert_cached(&mut state, id.to_owned(), encoding.clone());
        }
        Ok(encoding)
    }

    /// Where context frame `index` (in time order) of clip `id` is stored, as PNG.
    pub fn frame_path(&self, id: &str, index: usize) -> PathBuf {
        self.dir
            .join(id)
            .join("frames")
            .join(format!("{index:03}.png"))
    }

    fn insert_cached(&self, state: &mut State, id: String, encoding: Arc<Encoding>) {
        let bytes = (encoding.features().len() * 4) as u64;
        if let Some(old) = state.cache.put(id, encoding) {
            state.cached_bytes -= (old.features().len() * 4) as u64;
        }
        state.cached_bytes += bytes;
        // The newest entry stays even alone over the budget: evicting what was just asked for
        // would only thrash.
        while state.cached_bytes > self.budget && state.cache.len() > 1 {
            if let Some((_, old)) = state.cache.pop_lru() {
                state.cached_bytes -= (old.features().len() * 4) as u64;
                metrics::counter!("c4g_cache_evictions_total").increment(1);
            }
        }
        metrics::gauge!("c4g_cache_bytes").set(state.cached_bytes as f64);
    }

    /// Deletes a clip from memory and disk.
    pub fn delete(&self, id: &str) -> Result<(), ServiceError> {
        {
            let mut state = self.lock();
            if state.records.remove(id).is_none() {
                return Err(not_found(id));
            }
            if let Some(old) = state.cache.pop(id) {
                state.cached_bytes -= (old.features().len() * 4) as u64;
            }
            metrics::gauge!("c4g_clips").set(state.records.len() as f64);
            metrics::gauge!("c4g_cache_bytes").set(state.cached_bytes as f64);
        }
        // Renamed first so that a crash mid-delete leaves a dot-directory the next start drops.
        let path = self.dir.join(id);
        let doomed = self.dir.join(format!(".deleted-{id}"));
        std::fs::rename(&path, &doomed)
            .and_then(|()| std::fs::remove_dir_all(&doomed))
            .map_err(|e| ServiceError::Internal(format!("cannot delete clip {id} from disk: {e}")))
    }
}

fn not_found(id: &str) -> ServiceError {
    ServiceError::NotFound(format!(
        "no clip {id:?}: upload it with POST /v1/clips (GET /v1/clips lists the stored ones)"
    ))
}

fn read_record(dir: &Path) -> Result<ClipRecord, String> {
    let text = std::fs::read(dir.join("clip.json")).map_err(|e| e.to_string())?;
    serde_json::from_slice(&text).map_err(|e| e.to_string())
}

fn write_clip(
    root: &Path,
    record: &ClipRecord,
    encoding: &Encoding,
    frames: &[RgbImage],
) -> Result<(), ServiceError> {
    let fail = |what: &str, e: &dyn std::fmt::Display| {
        ServiceError::Internal(format!("cannot store clip {}: {what}: {e}", record.id))
    };
    let nonce = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let tmp = root.join(format!(".tmp-{}-{nonce}", record.id));
    std::fs::create_dir_all(tmp.join("frames")).map_err(|e| fail("creating", &e))?;
    let json = serde_json::to_vec_pretty(record).map_err(|e| fail("serialising", &e))?;
    std::fs::write(tmp.join("clip.json"), json).map_err(|e| fail("clip.json", &e))?;
    let bytes: Vec<u8> = encoding
        .features()
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    std::fs::write(tmp.join("features.f32"), bytes).map_err(|e| fail("features", &e))?;
    for (i, frame) in frames.iter().enumerate() {
        let file = std::fs::File::create(tmp.join("frames").join(format!("{i:03}.png")))
            .map_err(|e| fail("a context frame", &e))?;
        // Fast compression: these are written once per upload, on the upload's clock.
        let encoder = PngEncoder::new_with_quality(
            std::io::BufWriter::new(file),
            CompressionType::Fast,
            FilterType::Adaptive,
        );
        frame
            .write_with_encoder(encoder)
            .map_err(|e| fail("a context frame", &e))?;
    }
    let target = root.join(&record.id);
    if target.exists() {
        // Another writer finished first with the same content.
        let _ = std::fs::remove_dir_all(&tmp);
        return Ok(());
    }
    std::fs::rename(&tmp, &target).map_err(|e| fail("moving into place", &e))
}

fn read_features(dir: &Path, record: &ClipRecord) -> Result<Encoding, ServiceError> {
    let bytes = std::fs::read(dir.join("features.f32")).map_err(|e| {
        ServiceError::Internal(format!(
            "cannot read the features of clip {}: {e}",
            record.id
        ))
    })?;
    let features = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Encoding::from_parts(
        record.context_times.clone(),
        record.frame_order.clone(),
        features,
        record.feature_shape,
    )
    .and_then(|encoding| encoding.with_frame_step(record.frame_step()))
    .map_err(|e| {
        ServiceError::Internal(format!(
            "the stored features of clip {} are damaged: {e}",
            record.id
        ))
    })
}

/// Seconds since the Unix epoch.
pub fn now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record_json(frame_step: Option<f64>, fps: f64) -> serde_json::Value {
        let mut json = serde_json::json!({
            "id": "abc", "model": "c4g-small", "created_at": 0,
            "options": {},
            "source": {"kind": "video", "frames": 90, "width": 64, "height": 64, "duration": 3.0, "fps": fps},
            "context_times": [0.0, 1.0, 2.0, 3.0], "frame_order": [0, 1, 2, 3], "feature_shape": [4, 1, 1],
        });
        if let Some(step) = frame_step {
            json["frame_step"] = step.into();
        }
        json
    }

    #[test]
    fn a_clip_stored_before_frame_steps_were_recorded_loads_and_falls_back_to_the_frame_period() {
        let old: ClipRecord = serde_json::from_value(record_json(None, 30.0)).unwrap();
        assert_eq!(old.frame_step, None);
        assert_eq!(old.frame_step(), Some(1.0 / 30.0));
        let no_rate: ClipRecord = serde_json::from_value(record_json(None, 0.0)).unwrap();
        assert_eq!(no_rate.frame_step(), None);
        let new: ClipRecord = serde_json::from_value(record_json(Some(0.02), 30.0)).unwrap();
        assert_eq!(new.frame_step(), Some(0.02));
        let again: ClipRecord =
            serde_json::from_value(serde_json::to_value(&new).unwrap()).unwrap();
        assert_eq!(again, new);
    }

    #[test]
    fn features_read_back_from_disk_carry_the_frame_step() {
        let dir = std::env::temp_dir().join(format!("c4g-store-step-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("features.f32"), [0u8; 16]).unwrap();
        let record: ClipRecord = serde_json::from_value(record_json(None, 25.0)).unwrap();
        let encoding = read_features(&dir, &record).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(encoding.frame_step(), Some(1.0 / 25.0));
    }
}
