//! The clip store: every encoded clip, on disk and (its encoder features) in a memory cache.
//!
//! - Ids are content addresses ([`crate::clips::intake::clip_id`]): the same upload is encoded once.
//! - A clip is written to disk when it is encoded (`<dir>/<model key>/clips/<id>/`: `clip.json`,
//!   `features.f32` as little-endian floats, and the context frames as PNG), into a temporary
//!   directory whose files and directory are synced, then renamed into place (and the rename
//!   synced): a crash, even of the machine, leaves the whole clip or none of it. The write and
//!   the index update finish even when the uploading client goes away, so the index always
//!   agrees with the disk.
//! - On opening, leftovers of interrupted writes and deletes (dot-directories) are removed, and a
//!   clip directory that cannot be served (unreadable record, features of the wrong size, a
//!   missing frame) is moved aside to `<model key>/damaged/` and logged, never deleted.
//! - A full disk is [`ServiceError::InsufficientStorage`]; what a failed write left is removed at
//!   once, so a full disk does not stay full of half clips.
//! - Features live in an LRU cache under a byte budget; an evicted clip reloads from disk on its
//!   next request.
//! - Concurrent uploads of one clip encode it once: later callers wait for the first.
//!
//! Clips are kept per model (the model key hashes the package), so a server on another model
//! never decodes features it did not make.
//!
//! With a shared store ([`crate::clips::shared`], `C4G_SHARED_STORE`) this store is the replica's
//! cache of the cluster's clips: what it stores it publishes, what it lacks it fetches
//! ([`get_or_fetch`](ClipStore::get_or_fetch)), and an upload another replica is encoding is
//! waited for and fetched rather than encoded again.

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use c4g_engine::Encoding;
use image::RgbImage;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use lru::LruCache;
use tokio::sync::OnceCell;

use crate::ServiceError;
use crate::clips::durable::{sync_dir, write_synced};
use crate::clips::record::{ClipRecord, KeptFrames};
use crate::clips::shared::{Claim, RECHECK, SHARED_MARK, SharedClips};
use crate::faults;
use crate::quoted;

/// A freshly encoded clip, for [`ClipStore::get_or_create`].
pub struct NewClip {
    /// Its description.
    pub record: ClipRecord,
    /// Its features.
    pub encoding: Encoding,
    /// Its context frames (kept for rendering comparisons and refinement).
    pub frames: Vec<RgbImage>,
    /// Source frames kept for fits ([`ClipRecord::kept_frames`] describes them).
    pub kept_frames: Vec<RgbImage>,
}

/// See the module documentation.
pub struct ClipStore {
    dir: PathBuf,
    budget: u64,
    // Shared with the blocking task that writes a clip, which indexes it when the write is done
    // whether or not its caller is still waiting.
    state: Arc<Mutex<State>>,
    /// The cluster's clips, and how long to wait for another replica's encode.
    shared: Option<(SharedClips, std::time::Duration)>,
}

struct State {
    records: BTreeMap<String, Arc<ClipRecord>>,
    cache: LruCache<String, Arc<Encoding>>,
    cached_bytes: u64,
    inflight: HashMap<String, Arc<OnceCell<Arc<ClipRecord>>>>,
    /// Clips held here that are in the shared store, and when they were last seen there.
    shared_seen: HashMap<String, Instant>,
    /// Records of shared clips not held here, as listed: a record never changes (ids are content
    /// addresses), so each is read once; the shared store's list says which still exist.
    shared_records: HashMap<String, Arc<ClipRecord>>,
}

fn lock(state: &Mutex<State>) -> MutexGuard<'_, State> {
    // A panic while holding the lock leaves consistent data (every update is one step).
    state.lock().unwrap_or_else(|p| p.into_inner())
}

impl ClipStore {
    /// The clip's context frame `index` (upload order) as PNG bytes.
    pub async fn context_frame_png(&self, id: &str, index: usize) -> Result<Vec<u8>, ServiceError> {
        let record = self.get_or_fetch(id).await?;
        if index >= record.context_times.len() {
            return Err(ServiceError::NotFound(format!(
                "clip {id} has {} context frames (0..{})",
                record.context_times.len(),
                record.context_times.len()
            )));
        }
        let mut bytes = Vec::new();
        std::fs::File::open(self.frame_path(id, index))
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(|e| {
                let error = ServiceError::Internal(format!("cannot read a context frame: {e}"));
                self.unless_gone(id, error)
            })?;
        Ok(bytes)
    }

    /// Opens (creating) the store for the model with key `model_key` under `root`, loading every
    /// clip's record (features load when first asked for). Leftovers of interrupted writes are
    /// removed; clip directories that cannot be served are moved aside to `damaged/`.
    pub fn open(root: &Path, model_key: &str, budget_bytes: u64) -> Result<Self, ServiceError> {
        let dir = root.join(model_key).join("clips");
        std::fs::create_dir_all(&dir).map_err(|e| {
            ServiceError::storage(format!("cannot create the store {}", dir.display()), &e)
        })?;
        let mut records = BTreeMap::new();
        let entries = std::fs::read_dir(&dir).map_err(|e| {
            ServiceError::storage(format!("cannot read the store {}", dir.display()), &e)
        })?;
        for entry in entries.flatten() {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                // An interrupted write or delete: never visible, safe to drop.
                tracing::info!(path = %path.display(), "removing the leftover of an interrupted write");
                let _ = std::fs::remove_dir_all(&path).or_else(|_| std::fs::remove_file(&path));
                continue;
            }
            match check_clip(&path, &name) {
                Ok(record) => {
                    records.insert(name, Arc::new(record));
                }
                Err(why) => set_aside(root.join(model_key), &path, &name, &why),
            }
        }
        tracing::info!(clips = records.len(), dir = %dir.display(), "clip store opened");
        metrics::gauge!("c4g_clips").set(records.len() as f64);
        metrics::gauge!("c4g_clips_in_progress").set(0.0);
        Ok(Self {
            dir,
            budget: budget_bytes,
            state: Arc::new(Mutex::new(State {
                records,
                cache: LruCache::unbounded(),
                cached_bytes: 0,
                inflight: HashMap::new(),
                shared_seen: HashMap::new(),
                shared_records: HashMap::new(),
            })),
            shared: None,
        })
    }

    /// Shares the store's clips with other replicas through `shared`; an upload another replica
    /// is encoding is waited for up to `encode_wait` (then encoded here after all).
    pub fn with_shared(mut self, shared: SharedClips, encode_wait: std::time::Duration) -> Self {
        tracing::info!(url = shared.url(), "clips are shared with other replicas");
        self.shared = Some((shared, encode_wait));
        // Shared copies kept from before a restart are checked against deletes at first use.
        let long_ago = Instant::now()
            .checked_sub(RECHECK)
            .unwrap_or_else(Instant::now);
        let mut state = self.lock();
        let held: Vec<String> = state.records.keys().cloned().collect();
        for id in held {
            if self.dir.join(&id).join(SHARED_MARK).exists() {
                state.shared_seen.insert(id, long_ago);
            }
        }
        drop(state);
        self
    }

    /// One clip's record, fetched from the shared store when this replica does not hold it. A
    /// shared clip held here is looked for in the shared store once [`RECHECK`] has passed since
    /// it was last seen there, and forgotten when another replica deleted it.
    pub async fn get_or_fetch(&self, id: &str) -> Result<Arc<ClipRecord>, ServiceError> {
        let found = match self.get(id) {
            Err(missing) => {
                return match self.fetch(id).await? {
                    Some(record) => Ok(record),
                    None => Err(missing),
                };
            }
            Ok(found) => found,
        };
        let Some((shared, _)) = &self.shared else {
            return Ok(found);
        };
        let due = self
            .lock()
            .shared_seen
            .get(id)
            .is_some_and(|seen| seen.elapsed() >= RECHECK);
        if !due {
            return Ok(found);
        }
        match shared.has(id).await {
            Ok(true) => {
                self.lock()
                    .shared_seen
                    .insert(id.to_owned(), Instant::now());
                Ok(found)
            }
            Ok(false) => {
                tracing::info!(clip = id, "deleted by another replica: forgotten here too");
                if let Err(e) = self.forget(id) {
                    tracing::warn!(clip = id, "cannot remove the deleted clip's copy: {e}");
                }
                Err(not_found(id))
            }
            // The shared store is down: the copy here is still the clip.
            Err(e) => {
                tracing::warn!(clip = id, "cannot check the clip against deletes: {e}");
                Ok(found)
            }
        }
    }

    /// Every clip: this replica's, and with a shared store the cluster's; oldest first.
    pub async fn list_all(&self) -> Result<Vec<Arc<ClipRecord>>, ServiceError> {
        use futures_util::StreamExt;
        let mut all = self.list();
        let Some((shared, _)) = &self.shared else {
            return Ok(all);
        };
        let held: std::collections::HashSet<String> = all.iter().map(|r| r.id.clone()).collect();
        let others: Vec<String> = shared
            .ids()
            .await?
            .into_iter()
            .filter(|id| is_clip_id(id) && !held.contains(id))
            .collect();
        let (known, unknown): (Vec<String>, Vec<String>) = {
            let state = self.lock();
            others
                .into_iter()
                .partition(|id| state.shared_records.contains_key(id))
        };
        // Records only (a few hundred bytes each), a few at a time, and each once.
        let records: Vec<Result<Option<ClipRecord>, ServiceError>> = futures_util::stream::iter(
            unknown
                .into_iter()
                .map(|id| async move { shared.record(&id).await }),
        )
        .buffer_unordered(16)
        .collect()
        .await;
        let mut state = self.lock();
        let listed: std::collections::HashSet<&String> = known.iter().collect();
        state.shared_records.retain(|id, _| listed.contains(id));
        for id in &known {
            all.extend(state.shared_records.get(id).cloned());
        }
        for record in records {
            if let Some(record) = record? {
                let record = Arc::new(record);
                state
                    .shared_records
                    .insert(record.id.clone(), record.clone());
                all.push(record);
            }
        }
        drop(state);
        all.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        Ok(all)
    }

    /// Fetches clip `id` from the shared store into this one; `None` without a shared store or
    /// when it has no such clip.
    async fn fetch(&self, id: &str) -> Result<Option<Arc<ClipRecord>>, ServiceError> {
        let Some((shared, _)) = &self.shared else {
            return Ok(None);
        };
        if !is_clip_id(id) {
            return Ok(None);
        }
        let tmp = self.dir.join(format!(".tmp-{id}-{}", nonce()));
        let fetched = shared.fetch(id, &tmp).await;
        if !matches!(fetched, Ok(Some(_))) {
            let _ = std::fs::remove_dir_all(&tmp);
            return fetched.map(|_| None);
        }
        let (dir, state, name) = (self.dir.clone(), self.state.clone(), id.to_owned());
        tokio::task::spawn_blocking(move || {
            let record = check_clip(&tmp, &name).map_err(|why| {
                let _ = std::fs::remove_dir_all(&tmp);
                ServiceError::Internal(format!("the shared clip {name} cannot be served: {why}"))
            })?;
            let target = dir.join(&name);
            if target.exists() {
                let _ = std::fs::remove_dir_all(&tmp);
            } else {
                std::fs::rename(&tmp, &target)
                    .and_then(|()| sync_dir(&dir))
                    .map_err(|e| store_error(&record, "moving a fetched clip into place", &e))?;
            }
            let record = Arc::new(record);
            let mut state = lock(&state);
            state.shared_seen.insert(name.clone(), Instant::now());
            let record = state.records.entry(name).or_insert(record).clone();
            metrics::gauge!("c4g_clips").set(state.records.len() as f64);
            tracing::info!(clip = %record.id, "clip fetched from the shared store");
            Ok(Some(record))
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("fetching a clip panicked: {e}")))?
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        lock(&self.state)
    }

    /// Every clip, oldest first.
    pub fn list(&self) -> Vec<Arc<ClipRecord>> {
        let mut all: Vec<_> = self.lock().records.values().cloned().collect();
        all.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        all
    }

    /// `error`, or `not_found` when clip `id` is no longer stored: a request that found the clip
    /// and then failed on its files lost a race with a delete, which is the client's 404, not the
    /// server's 500.
    pub fn unless_gone(&self, id: &str, error: ServiceError) -> ServiceError {
        match self.get(id) {
            Ok(_) => error,
            Err(gone) => gone,
        }
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
    /// failure is not shared: the next caller tries again). A call whose caller goes away
    /// leaves nothing behind: its clip is stored whole (when its write had begun) or not at all.
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
            let cell = state.inflight.entry(id.to_owned()).or_default().clone();
            metrics::gauge!("c4g_clips_in_progress").set(state.inflight.len() as f64);
            cell
        };
        let _done = Inflight {
            state: &self.state,
            id,
            cell: &cell,
        };
        let mut created = false;
        let result = cell
            .get_or_try_init(|| async {
                // Another replica may have it, or be encoding it.
                let mut claimed = false;
                if let Some((shared, encode_wait)) = &self.shared {
                    if let Some(record) = self.fetch(id).await? {
                        return Ok(record);
                    }
                    match shared.claim(id).await? {
                        Claim::Ours => claimed = true,
                        Claim::Theirs => {
                            tracing::info!(
                                clip = id,
                                "another replica is encoding this clip: waiting"
                            );
                            if shared.wait_for(id, *encode_wait).await?
                                && let Some(record) = self.fetch(id).await?
                            {
                                return Ok(record);
                            }
                        }
                    }
                }
                let made = async {
                    let new = create().await?;
                    let record = Arc::new(new.record.clone());
                    self.persist(new).await?;
                    if let Some((shared, _)) = &self.shared {
                        match shared.publish(&record, &self.dir.join(id)).await {
                            Ok(()) => self.mark_shared(id).await,
                            // Stored here all the same: other replicas encode it themselves.
                            Err(e) => tracing::warn!(clip = id, "cannot publish the clip: {e}"),
                        }
                    }
                    Ok::<_, ServiceError>(record)
                }
                .await;
                if claimed && let Some((shared, _)) = &self.shared {
                    shared.release(id).await;
                }
                created = made.is_ok();
                made
            })
            .await
            .cloned();
        result.map(|record| (record, created))
    }

    async fn persist(&self, new: NewClip) -> Result<(), ServiceError> {
        let (dir, state, budget) = (self.dir.clone(), self.state.clone(), self.budget);
        tokio::task::spawn_blocking(move || {
            let NewClip {
                record,
                encoding,
                frames,
                kept_frames,
            } = new;
            write_clip(&dir, &record, &encoding, &frames, &kept_frames)?;
            faults::pause("clip-stored");
            let id = record.id.clone();
            let mut state = lock(&state);
            state.records.insert(id.clone(), Arc::new(record));
            metrics::gauge!("c4g_clips").set(state.records.len() as f64);
            state.insert_cached(budget, id, Arc::new(encoding));
            Ok(())
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("writing a clip panicked: {e}")))?
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
            state.insert_cached(self.budget, id.to_owned(), encoding.clone());
        }
        Ok(encoding)
    }

    /// The cluster's clips, when this store is a replica's cache of them.
    pub fn shared(&self) -> Option<&SharedClips> {
        self.shared.as_ref().map(|(shared, _)| shared)
    }

    /// A file `name` kept in clip `id`'s directory beside its record (derived data, deleted
    /// with the clip).
    pub fn clip_file(&self, id: &str, name: &str) -> PathBuf {
        self.dir.join(id).join(name)
    }

    /// Where context frame `index` (in time order) of clip `id` is stored, as PNG.
    pub fn frame_path(&self, id: &str, index: usize) -> PathBuf {
        self.dir
            .join(id)
            .join("frames")
            .join(format!("{index:03}.png"))
    }

    /// Where kept source frame `index` (in time order) of clip `id` is stored, as PNG.
    pub fn kept_frame_path(&self, id: &str, index: usize) -> PathBuf {
        self.dir.join(id).join(KeptFrames::name(index))
    }

    /// Records that clip `id`, held here, is in the shared store (so its copy is checked
    /// against deletes, also after a restart).
    async fn mark_shared(&self, id: &str) {
        let mark = self.dir.join(id).join(SHARED_MARK);
        if let Err(e) = tokio::fs::write(&mark, b"").await {
            tracing::warn!(clip = id, "cannot mark the clip as shared: {e}");
        }
        self.lock()
            .shared_seen
            .insert(id.to_owned(), Instant::now());
    }

    /// Deletes a clip from memory and disk, and from the shared store.
    pub async fn delete(&self, id: &str) -> Result<(), ServiceError> {
        // From the shared store by its own record: a clip held only there is not fetched first.
        let shared = match &self.shared {
            Some((shared, _)) if is_clip_id(id) => shared.delete(id).await?,
            _ => false,
        };
        match self.forget(id)? {
            true => Ok(()),
            false if shared => Ok(()),
            false => Err(not_found(id)),
        }
    }

    /// Removes clip `id` from this replica's memory and disk; whether it held it.
    fn forget(&self, id: &str) -> Result<bool, ServiceError> {
        {
            let mut state = self.lock();
            state.shared_seen.remove(id);
            if state.records.remove(id).is_none() {
                return Ok(false);
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
            .and_then(|()| sync_dir(&self.dir))
            .and_then(|()| std::fs::remove_dir_all(&doomed))
            .map_err(|e| ServiceError::storage(format!("cannot delete clip {id} from disk"), &e))?;
        Ok(true)
    }
}

impl State {
    fn insert_cached(&mut self, budget: u64, id: String, encoding: Arc<Encoding>) {
        let bytes = (encoding.features().len() * 4) as u64;
        if let Some(old) = self.cache.put(id, encoding) {
            self.cached_bytes -= (old.features().len() * 4) as u64;
        }
        self.cached_bytes += bytes;
        // The newest entry stays even alone over the budget: evicting what was just asked for
        // would only thrash.
        while self.cached_bytes > budget && self.cache.len() > 1 {
            if let Some((_, old)) = self.cache.pop_lru() {
                self.cached_bytes -= (old.features().len() * 4) as u64;
                metrics::counter!("c4g_cache_evictions_total").increment(1);
            }
        }
        metrics::gauge!("c4g_cache_bytes").set(self.cached_bytes as f64);
    }
}

/// Takes an upload's entry out of the in-flight map when its call ends (answered, failed, or
/// dropped with its client), unless other callers still wait on it: the last one out removes it.
struct Inflight<'a> {
    state: &'a Mutex<State>,
    id: &'a str,
    cell: &'a Arc<OnceCell<Arc<ClipRecord>>>,
}

impl Drop for Inflight<'_> {
    fn drop(&mut self) {
        let mut state = lock(self.state);
        let ours = state
            .inflight
            .get(self.id)
            .is_some_and(|c| Arc::ptr_eq(c, self.cell));
        // Two holders: the map and this call. More: another caller waits and will clean up.
        if ours && (self.cell.initialized() || Arc::strong_count(self.cell) <= 2) {
            state.inflight.remove(self.id);
        }
        metrics::gauge!("c4g_clips_in_progress").set(state.inflight.len() as f64);
    }
}

/// Whether `id` is a content address: ids name directories and shared objects, so nothing else
/// is looked for there.
fn is_clip_id(id: &str) -> bool {
    id.len() == 24 && id.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

fn not_found(id: &str) -> ServiceError {
    ServiceError::NotFound(format!(
        "no clip {id_quoted}: upload it with POST /v1/clips (GET /v1/clips lists the stored ones)",
        id_quoted = quoted(id)
    ))
}

fn read_record(dir: &Path) -> Result<ClipRecord, String> {
    let text = std::fs::read(dir.join("clip.json")).map_err(|e| format!("clip.json: {e}"))?;
    serde_json::from_slice(&text).map_err(|e| format!("clip.json: {e}"))
}

/// The record of the clip directory `dir` named `name`, when the directory holds everything a
/// request may read: the record, features of the recorded size, one PNG per context frame.
fn check_clip(dir: &Path, name: &str) -> Result<ClipRecord, String> {
    let record = read_record(dir)?;
    if record.id != name {
        return Err(format!("its record is of clip {:?}", record.id));
    }
    let features = std::fs::metadata(dir.join("features.f32"))
        .map_err(|e| format!("features.f32: {e}"))?
        .len();
    if features != record.feature_bytes() {
        return Err(format!(
            "features.f32 holds {features} bytes, its record says {}",
            record.feature_bytes()
        ));
    }
    for index in 0..record.context_times.len() {
        let frame = dir.join("frames").join(format!("{index:03}.png"));
        if !frame.is_file() {
            return Err(format!("context frame {index} is missing"));
        }
    }
    Ok(record)
}

/// Moves the unservable clip directory `path` to `<model dir>/damaged/`, for an operator to look
/// at: never deleted, never served.
fn set_aside(model_dir: PathBuf, path: &Path, name: &str, why: &str) {
    let damaged = model_dir.join("damaged");
    let target = damaged.join(format!("{name}-{}", nonce()));
    match std::fs::create_dir_all(&damaged).and_then(|()| std::fs::rename(path, &target)) {
        Ok(()) => tracing::warn!(
            clip = name, moved_to = %target.display(),
            "a stored clip cannot be served ({why}): moved aside"
        ),
        Err(e) => tracing::warn!(
            path = %path.display(),
            "a stored clip cannot be served ({why}) nor moved aside ({e}): skipped"
        ),
    }
}

fn nonce() -> u128 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0)
}

/// Writes a clip into a temporary directory next to its place and renames it there; on failure
/// removes what it wrote.
fn write_clip(
    root: &Path,
    record: &ClipRecord,
    encoding: &Encoding,
    frames: &[RgbImage],
    kept_frames: &[RgbImage],
) -> Result<(), ServiceError> {
    let tmp = root.join(format!(".tmp-{}-{}", record.id, nonce()));
    let result = write_clip_files(&tmp, record, encoding, frames, kept_frames).and_then(|()| {
        let target = root.join(&record.id);
        if target.exists() {
            // Another writer finished first with the same content.
            let _ = std::fs::remove_dir_all(&tmp);
            return Ok(());
        }
        std::fs::rename(&tmp, &target)
            .and_then(|()| sync_dir(root))
            .map_err(|e| store_error(record, "moving it into place", &e))
    });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

fn store_error(record: &ClipRecord, what: &str, e: &std::io::Error) -> ServiceError {
    ServiceError::storage(format!("cannot store clip {} ({what})", record.id), e)
}

fn write_clip_files(
    tmp: &Path,
    record: &ClipRecord,
    encoding: &Encoding,
    frames: &[RgbImage],
    kept_frames: &[RgbImage],
) -> Result<(), ServiceError> {
    let frames_dir = tmp.join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| store_error(record, "creating it", &e))?;
    let json = serde_json::to_vec_pretty(record)
        .map_err(|e| ServiceError::Internal(format!("cannot serialise clip {}: {e}", record.id)))?;
    write_synced(&tmp.join("clip.json"), &json)
        .map_err(|e| store_error(record, "clip.json", &e))?;
    let bytes: Vec<u8> = encoding
        .features()
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    write_synced(&tmp.join("features.f32"), &bytes)
        .map_err(|e| store_error(record, "features", &e))?;
    faults::pause("clip-features-written");
    for (i, frame) in frames.iter().enumerate() {
        write_png(&frames_dir.join(format!("{i:03}.png")), frame)
            .map_err(|e| store_error(record, &format!("context frame {i}"), &e))?;
    }
    let mut dirs = vec![frames_dir];
    if !kept_frames.is_empty() {
        let kept_dir = tmp.join(KeptFrames::DIR);
        std::fs::create_dir_all(&kept_dir).map_err(|e| store_error(record, "creating it", &e))?;
        for (i, frame) in kept_frames.iter().enumerate() {
            write_png(&tmp.join(KeptFrames::name(i)), frame)
                .map_err(|e| store_error(record, &format!("kept frame {i}"), &e))?;
        }
        dirs.push(kept_dir);
    }
    dirs.push(tmp.to_path_buf());
    dirs.iter()
        .try_for_each(|dir| sync_dir(dir))
        .map_err(|e| store_error(record, "syncing it", &e))
}

/// `frame` as PNG at `path`, synced. Encoded in memory, so that a write error is seen (a
/// buffered writer's last flush, on drop, would lose it). Fast compression: written once per
/// upload, on its clock.
fn write_png(path: &Path, frame: &RgbImage) -> std::io::Result<()> {
    let mut png = Vec::new();
    let encoder =
        PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Adaptive);
    frame
        .write_with_encoder(encoder)
        .map_err(std::io::Error::other)?;
    write_synced(path, &png)
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
    fn opening_drops_interrupted_writes_and_sets_aside_clips_that_cannot_be_served() {
        let root = tempfile::tempdir().unwrap();
        let clips = root.path().join("key").join("clips");
        let write = |name: &str, features: usize, frames: usize| {
            let dir = clips.join(name);
            std::fs::create_dir_all(dir.join("frames")).unwrap();
            let mut record = record_json(Some(0.1), 10.0);
            record["id"] = name.into();
            std::fs::write(dir.join("clip.json"), record.to_string()).unwrap();
            std::fs::write(dir.join("features.f32"), vec![0u8; features]).unwrap();
            for i in 0..frames {
                std::fs::write(dir.join("frames").join(format!("{i:03}.png")), b"png").unwrap();
            }
        };
        // Shape [4, 1, 1]: 16 bytes of features, 4 context frames.
        write("whole", 16, 4);
        write("short", 12, 4);
        write("frameless", 16, 3);
        write(".tmp-half-123", 16, 0);
        let store = ClipStore::open(root.path(), "key", 1 << 20).unwrap();
        let ids: Vec<String> = store.list().iter().map(|r| r.id.clone()).collect();
        assert_eq!(ids, ["whole"]);
        let left: Vec<String> = std::fs::read_dir(&clips)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(left, ["whole"], "the index and the directory disagree");
        let mut damaged: Vec<String> = std::fs::read_dir(root.path().join("key/damaged"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        damaged.sort();
        assert_eq!(damaged.len(), 2);
        assert!(damaged[0].starts_with("frameless-") && damaged[1].starts_with("short-"));
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
