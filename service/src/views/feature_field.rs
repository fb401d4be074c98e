//! What a package lifts and what the service keeps of each clip's feature field: the feature
//! decoder's kind, and each clip's PCA colouring basis (fitted once, cached).

use std::num::NonZeroUsize;
use std::sync::{Arc, Mutex, PoisonError};

use c4g_analysis::features::FeaturePca;
use lru::LruCache;

/// Clips whose colouring basis stays in memory (4 F-wide vectors each).
const BASES_KEPT: usize = 1024;

/// What a package's feature decoder was trained to lift (`feature_decoder.kind` in `model.json`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MapsKind {
    /// The encoding's own features.
    Encoder,
    /// Per-patch object-id fractions of each context frame (the client's to give).
    ObjectId,
    /// Nothing declared: any maps of the right width.
    Undeclared,
    /// A kind this server does not know.
    Other(String),
}

impl MapsKind {
    /// The kind `model.json` in `dir` declares (undeclared when it cannot be read: the engine
    /// has read it already, so that only happens when it says nothing).
    pub(crate) fn of_package(dir: &std::path::Path) -> Self {
        let kind = std::fs::read(dir.join("model.json"))
            .ok()
            .and_then(|bytes| serde_json::from_slice::<serde_json::Value>(&bytes).ok())
            .and_then(|m| m["feature_decoder"]["kind"].as_str().map(str::to_owned));
        match kind.as_deref() {
            None => Self::Undeclared,
            Some("encoder") => Self::Encoder,
            Some("object-id") => Self::ObjectId,
            Some(other) => Self::Other(other.to_owned()),
        }
    }
}

/// The package's feature kind and each clip's colouring basis.
pub struct FeatureField {
    pub(crate) kind: MapsKind,
    bases: Mutex<LruCache<String, Arc<FeaturePca>>>,
}

impl FeatureField {
    /// The field of the package in `dir`.
    pub fn of_package(dir: &std::path::Path) -> Self {
        Self {
            kind: MapsKind::of_package(dir),
            bases: Mutex::new(LruCache::new(
                NonZeroUsize::new(BASES_KEPT).unwrap_or(NonZeroUsize::MIN),
            )),
        }
    }

    /// Forgets clip `id`'s basis (the clip is gone).
    pub fn forget(&self, id: &str) {
        self.lock().pop(id);
    }

    pub(crate) fn lock(&self) -> std::sync::MutexGuard<'_, LruCache<String, Arc<FeaturePca>>> {
        self.bases.lock().unwrap_or_else(PoisonError::into_inner)
    }
}
