//! Clips shared by server replicas through object storage (the `object_store` crate): an
//! S3-compatible bucket (`s3://bucket/prefix`, configured by the usual `AWS_*` variables:
//! `AWS_ENDPOINT`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`,
//! `AWS_ALLOW_HTTP`) or a directory every replica mounts (`file:///shared/dir`).
//!
//! Each replica keeps its own store ([`crate::clips::store`]) as its cache of clips; this layer adds:
//! - **publish**: a clip a replica stores is copied to `<prefix>/<model key>/<id>/` (its
//!   `features.f32`, `frames/NNN.png`, then `clip.json`: the record goes last, so a clip whose
//!   record is there is whole);
//! - **fetch**: a replica asked for a clip it does not hold fetches it into its own store;
//! - **one encode cluster-wide**: before encoding, a replica claims the clip with a conditional
//!   put (`<id>/encoding`, which fails when it exists); a replica that finds it claimed waits for
//!   the record to appear and fetches the clip instead. A claim older than [`STALE_CLAIM`] (its
//!   replica died mid-encode) is taken over.
//!
//! - **the list**: `GET /v1/clips` lists the cluster's clips (this replica's and the bucket's);
//! - **deletes**: a delete removes the clip's objects, the record first; a replica that fetched
//!   or published the clip looks for its record again before serving it once [`RECHECK`] has
//!   passed since it last saw it, and forgets a clip that is gone.
//!
//! The shared store failing (down, refusing) is kind `unavailable` (503, retry): the request
//! changed nothing.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};

use crate::ServiceError;
use crate::clips::record::{ClipRecord, KeptFrames};

/// A claim this old is its replica's, which died: another may encode the clip.
pub const STALE_CLAIM: Duration = Duration::from_secs(600);

/// A file in a clip's local directory saying the clip is in the shared store (fetched from it,
/// or published to it): such a copy is checked against deletes; one never shared is not.
pub const SHARED_MARK: &str = "shared";

/// How long a replica serves a shared clip it holds before it checks the clip was not deleted
/// (by another replica): the longest a deleted clip stays visible.
pub const RECHECK: Duration = Duration::from_secs(5);

/// How often a replica waiting for another's encode looks for the record.
const POLL: Duration = Duration::from_millis(200);

/// The shared clips of one model.
pub struct SharedClips {
    store: Arc<dyn ObjectStore>,
    root: ObjectPath,
    url: String,
}

/// Whether this replica encodes a clip.
#[derive(Debug, PartialEq, Eq)]
pub enum Claim {
    /// It does (and releases the claim when it is done).
    Ours,
    /// Another replica is encoding it.
    Theirs,
}

impl SharedClips {
    /// The shared store at `url` for the model with key `model_key`.
    pub fn open(url: &str, model_key: &str) -> Result<Self, ServiceError> {
        let parsed = url::Url::parse(url)
            .map_err(|e| ServiceError::Internal(format!("C4G_SHARED_STORE {url:?}: {e}")))?;
        if parsed.scheme() == "file" {
            let dir = parsed.to_file_path().map_err(|()| {
                ServiceError::Internal(format!("C4G_SHARED_STORE {url:?} is not a local path"))
            })?;
            std::fs::create_dir_all(&dir).map_err(|e| {
                ServiceError::storage(format!("cannot create the shared store {url}"), &e)
            })?;
        }
        let options = std::env::vars().filter(|(k, _)| k.starts_with("AWS_"));
        let (store, prefix) = object_store::parse_url_opts(&parsed, options)
            .map_err(|e| ServiceError::Internal(format!("C4G_SHARED_STORE {url:?}: {e}")))?;
        Ok(Self {
            store: Arc::from(store),
            root: prefix.clone().join(model_key),
            url: url.to_owned(),
        })
    }

    /// Where the store is, for logs.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn path(&self, id: &str, name: &str) -> ObjectPath {
        name.split('/')
            .fold(self.root.clone().join(id), |path, part| path.join(part))
    }

    /// Copies the clip stored locally in `dir` (`clip.json`, `features.f32`, `frames/`).
    pub async fn publish(&self, record: &ClipRecord, dir: &Path) -> Result<(), ServiceError> {
        let mut names = vec!["features.f32".to_owned()];
        names.extend((0..record.context_times.len()).map(frame_name));
        names.extend(kept_names(record));
        // The record last: its presence says the clip is whole.
        names.push("clip.json".to_owned());
        for name in names {
            let bytes = tokio::fs::read(dir.join(&name)).await.map_err(|e| {
                ServiceError::storage(format!("cannot read {name} of clip {}", record.id), &e)
            })?;
            self.store
                .put(&self.path(&record.id, &name), PutPayload::from(bytes))
                .await
                .map_err(|e| shared_error(&record.id, "publishing", &e))?;
        }
        Ok(())
    }

    /// Fetches clip `id` into the directory `into` (created), as the local store lays it out;
    /// `None` when the shared store has no whole clip `id`.
    pub async fn fetch(&self, id: &str, into: &Path) -> Result<Option<ClipRecord>, ServiceError> {
        let Some(json) = self.get(id, "clip.json").await? else {
            return Ok(None);
        };
        let record: ClipRecord = serde_json::from_slice(&json).map_err(|e| {
            ServiceError::Internal(format!("the shared record of clip {id} is damaged: {e}"))
        })?;
        // Marked as the cluster's: the copy is checked against deletes (RECHECK).
        tokio::fs::create_dir_all(into)
            .await
            .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        crate::clips::durable::write_synced(&into.join(SHARED_MARK), b"")
            .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        tokio::fs::create_dir_all(into.join("frames"))
            .await
            .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        if record.kept_frames.is_some() {
            tokio::fs::create_dir_all(into.join(KeptFrames::DIR))
                .await
                .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        }
        let mut names = vec!["features.f32".to_owned()];
        names.extend((0..record.context_times.len()).map(frame_name));
        names.extend(kept_names(&record));
        for name in names {
            let bytes = self.get(id, &name).await?.ok_or_else(|| {
                ServiceError::Internal(format!("the shared clip {id} has a record but no {name}"))
            })?;
            crate::clips::durable::write_synced(&into.join(&name), &bytes)
                .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        }
        crate::clips::durable::write_synced(&into.join("clip.json"), &json)
            .map_err(|e| ServiceError::storage(format!("cannot fetch clip {id}"), &e))?;
        Ok(Some(record))
    }

    async fn get(&self, id: &str, name: &str) -> Result<Option<Bytes>, ServiceError> {
        match self.store.get(&self.path(id, name)).await {
            Ok(found) => found
                .bytes()
                .await
                .map(Some)
                .map_err(|e| shared_error(id, "fetching", &e)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(shared_error(id, "fetching", &e)),
        }
    }

    /// The record of clip `id`, when the shared store has it whole.
    pub async fn record(&self, id: &str) -> Result<Option<ClipRecord>, ServiceError> {
        let Some(json) = self.get(id, "clip.json").await? else {
            return Ok(None);
        };
        serde_json::from_slice(&json).map(Some).map_err(|e| {
            ServiceError::Internal(format!("the shared record of clip {id} is damaged: {e}"))
        })
    }

    /// Whether the shared store still has clip `id`'s record.
    pub async fn has(&self, id: &str) -> Result<bool, ServiceError> {
        match self.store.head(&self.path(id, "clip.json")).await {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(shared_error(id, "looking for", &e)),
        }
    }

    /// The ids of the whole clips under the model's prefix: those whose record is there (one
    /// listing of the objects, no read of any).
    pub async fn ids(&self) -> Result<Vec<String>, ServiceError> {
        use futures_util::TryStreamExt;
        let depth = self.root.parts().count();
        let objects: Vec<object_store::ObjectMeta> = self
            .store
            .list(Some(&self.root))
            .try_collect()
            .await
            .map_err(|e| {
                ServiceError::Unavailable(format!("the shared store cannot list its clips: {e}"))
            })?;
        Ok(objects
            .iter()
            .filter_map(|meta| {
                let parts: Vec<_> = meta.location.parts().skip(depth).collect();
                match parts.as_slice() {
                    [id, record] if record.as_ref() == "clip.json" => Some(id.as_ref().to_owned()),
                    _ => None,
                }
            })
            .collect())
    }

    /// Claims the encode of clip `id` for this replica, unless another holds a live claim.
    pub async fn claim(&self, id: &str) -> Result<Claim, ServiceError> {
        let path = self.path(id, "encoding");
        let stamp = || PutPayload::from(now_s().to_string().into_bytes());
        let create = PutOptions {
            mode: PutMode::Create,
            ..PutOptions::default()
        };
        match self.store.put_opts(&path, stamp(), create).await {
            Ok(_) => Ok(Claim::Ours),
            Err(object_store::Error::AlreadyExists { .. }) => {
                let since: u64 = self
                    .get(id, "encoding")
                    .await?
                    .and_then(|b| String::from_utf8_lossy(&b).trim().parse().ok())
                    .unwrap_or(0);
                if now_s().saturating_sub(since) > STALE_CLAIM.as_secs() {
                    tracing::warn!(clip = id, "taking over a stale encode claim");
                    self.store
                        .put(&path, stamp())
                        .await
                        .map_err(|e| shared_error(id, "claiming", &e))?;
                    Ok(Claim::Ours)
                } else {
                    Ok(Claim::Theirs)
                }
            }
            Err(e) => Err(shared_error(id, "claiming", &e)),
        }
    }

    /// Gives up this replica's claim on clip `id` (encoded and published, or failed).
    pub async fn release(&self, id: &str) {
        if let Err(e) = self.store.delete(&self.path(id, "encoding")).await
            && !matches!(e, object_store::Error::NotFound { .. })
        {
            tracing::warn!(clip = id, "cannot release the encode claim: {e}");
        }
    }

    /// Waits up to `within` for another replica to publish clip `id`; whether it did.
    pub async fn wait_for(&self, id: &str, within: Duration) -> Result<bool, ServiceError> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            if self.get(id, "clip.json").await?.is_some() {
                return Ok(true);
            }
            if tokio::time::Instant::now() >= deadline {
                return Ok(false);
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// A file `name` kept beside clip `id`'s objects (derived data such as its fitted scene,
    /// deleted with the clip).
    pub async fn put_file(&self, id: &str, name: &str, bytes: Vec<u8>) -> Result<(), ServiceError> {
        self.store
            .put(&self.path(id, name), PutPayload::from(bytes))
            .await
            .map(|_| ())
            .map_err(|e| shared_error(id, "publishing", &e))
    }

    /// The file `name` kept beside clip `id`'s objects, if there is one.
    pub async fn get_file(&self, id: &str, name: &str) -> Result<Option<Bytes>, ServiceError> {
        self.get(id, name).await
    }

    /// Which version of file `name` beside clip `id` the shared store holds (its entity tag, else
    /// its time and size), `None` when it holds none: what a replica compares before fetching.
    pub async fn version(&self, id: &str, name: &str) -> Result<Option<String>, ServiceError> {
        match self.store.head(&self.path(id, name)).await {
            Ok(meta) => Ok(Some(meta.e_tag.unwrap_or_else(|| {
                format!(
                    "{}-{}",
                    meta.last_modified.timestamp_nanos_opt().unwrap_or(0),
                    meta.size
                )
            }))),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(shared_error(id, "fetching", &e)),
        }
    }

    /// Deletes clip `id` from the shared store; whether it was there.
    pub async fn delete(&self, id: &str) -> Result<bool, ServiceError> {
        let Some(record) = self.record(id).await? else {
            return Ok(false);
        };
        // The record first: from then on no replica fetches it.
        let mut names = vec!["clip.json".to_owned(), "features.f32".to_owned()];
        names.extend((0..record.context_times.len()).map(frame_name));
        names.extend(kept_names(&record));
        for name in names {
            match self.store.delete(&self.path(id, &name)).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(shared_error(id, "deleting", &e)),
            }
        }
        // Then whatever else was kept beside the clip (its fitted scene, say).
        use futures_util::TryStreamExt;
        let prefix = self.root.clone().join(id);
        let rest: Vec<object_store::ObjectMeta> = self
            .store
            .list(Some(&prefix))
            .try_collect()
            .await
            .map_err(|e| shared_error(id, "deleting", &e))?;
        for meta in rest {
            match self.store.delete(&meta.location).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => return Err(shared_error(id, "deleting", &e)),
            }
        }
        Ok(true)
    }
}

/// The kept source frames' object names.
fn kept_names(record: &ClipRecord) -> impl Iterator<Item = String> + use<> {
    let kept = record.kept_frames.as_ref().map_or(0, |k| k.times.len());
    (0..kept).map(KeptFrames::name)
}

fn frame_name(index: usize) -> String {
    format!("frames/{index:03}.png")
}

fn now_s() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// The shared store failed: a service the server depends on, so `unavailable` (retry), not the
/// server's own failure.
fn shared_error(id: &str, what: &str, e: &object_store::Error) -> ServiceError {
    ServiceError::Unavailable(format!(
        "the shared store (C4G_SHARED_STORE) failed {what} clip {id}: {e}"
    ))
}
