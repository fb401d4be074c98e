//! [`SetSource`]: the one answer to "the Gaussian sets of this clip at these times, under these
//! options". Exact decodes (batched across requests), keyframed ones, quality presets and pruning
//! all resolve here, on work slots; renders, streams, exports, tracks and refinement jobs ask it
//! for sets. A clip's fitted scene is served here too, in place of the decoder, when the request's
//! scene resolves to it ([`crate::sets::scene`]). (Decodes with lifted features still run the
//! feature decoder from the views' `features` module: moving them behind this seam is the next
//! step.) It asks only the clips layer (records, encodings, fitted scenes) below it.

use std::sync::Arc;

use c4g_engine::{Encoding, Engine, EngineError, KeyframeTrack, Keyframes, QuerySubset};
use c4g_scene::{Footprint, GaussianSet};

use crate::ServiceError;
use crate::clips::fitted::{Fitted, FittedScenes};
use crate::clips::record::ClipRecord;
use crate::clips::store::ClipStore;
use crate::config::Limits;
use crate::sets::batching::DecodeBatcher;
use crate::sets::decoder::{self, count_sets};
use crate::sets::plan::{Kept, SetPlan};
use crate::sets::pruning::Analyses;
use crate::sets::quality::{self, Approximation, QualitySpec};
use crate::sets::scene::Scene;
use crate::work::WorkSlots;

/// See the module documentation.
pub struct SetSource {
    /// The model.
    pub(crate) engine: Arc<Engine>,
    /// Every clip.
    pub(crate) store: Arc<ClipStore>,
    /// Request limits.
    pub(crate) limits: Limits,
    /// Decodes run here, shared with the views above.
    work: Arc<WorkSlots>,
    /// Exact decodes of one clip gathered into shared decoder runs.
    batcher: Arc<DecodeBatcher>,
    /// What pruning measured of each clip.
    analyses: Analyses,
    /// The package's footprint: pruning's renders see what the service renders.
    footprint: Footprint,
    /// Every clip's fitted scene.
    pub fitted: Arc<FittedScenes>,
}

impl SetSource {
    /// The set source of `engine`'s clips in `store`.
    pub fn new(
        engine: Arc<Engine>,
        store: Arc<ClipStore>,
        limits: Limits,
        work: Arc<WorkSlots>,
        batcher: Arc<DecodeBatcher>,
        footprint: Footprint,
    ) -> Self {
        Self {
            fitted: Arc::new(FittedScenes::new(store.clone())),
            engine,
            store,
            limits,
            work,
            batcher,
            analyses: Analyses::default(),
            footprint,
        }
    }

    /// Runs set work on a blocking thread once a work slot is free.
    pub async fn work<T: Send + 'static>(
        self: &Arc<Self>,
        work: impl FnOnce(&SetSource) -> Result<T, ServiceError> + Send + 'static,
    ) -> Result<T, ServiceError> {
        let sets = self.clone();
        self.work.run(move || work(&sets)).await
    }

    /// The exact sets of clip `id` at `times` (already checked), decoded in a batch with other
    /// requests' targets when some arrive within the batching wait.
    pub async fn exact(
        self: &Arc<Self>,
        id: &str,
        encoding: Arc<Encoding>,
        times: Vec<f64>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        self.batcher.decode(id, encoding, times).await
    }

    /// Forgets what was measured of clip `id`, and its fitted scene (it was deleted).
    pub fn forget(&self, id: &str) {
        self.analyses.forget(id);
        self.fitted.forget(id);
    }

    /// Pins `spec.scene` to the scene that serves a request on clip `id` (feed-forward or
    /// fitted; the module documentation of [`crate::sets::scene`] says how `auto` chooses), and
    /// says which. A request for lifted `features` is the feed-forward scene's.
    pub async fn resolve_scene(
        &self,
        id: &str,
        spec: &mut QualitySpec,
        features: bool,
    ) -> Result<Scene, ServiceError> {
        if features {
            if spec.scene == Scene::Fitted {
                return Err(ServiceError::Unsupported(
                    "lifted features are the feed-forward scene's: a fitted scene carries none \
                     (ask scene \"auto\" or \"feed-forward\" with features)"
                        .into(),
                ));
            }
            spec.scene = Scene::FeedForward;
            return Ok(Scene::FeedForward);
        }
        let scene = match spec.scene {
            Scene::FeedForward => Scene::FeedForward,
            Scene::Auto if spec.approximates() => Scene::FeedForward,
            Scene::Auto => match self.fitted.get(id).await? {
                Some(_) => Scene::Fitted,
                None => Scene::FeedForward,
            },
            Scene::Fitted => {
                if spec.approximates() {
                    return Err(ServiceError::invalid(
                        "the fitted scene is served as it was fitted: quality presets, keyframes \
                         and pruning approximate the feed-forward scene (ask scene \
                         \"feed-forward\", or leave them out)",
                    ));
                }
                self.fitted_scene(id).await?;
                Scene::Fitted
            }
        };
        spec.scene = scene;
        Ok(scene)
    }

    /// Clip `id`'s fitted scene, or `not_found` saying how to make one.
    pub async fn fitted_scene(&self, id: &str) -> Result<Arc<Fitted>, ServiceError> {
        self.fitted.get(id).await?.ok_or_else(|| {
            ServiceError::NotFound(format!(
                "clip {id} has no fitted scene: POST /v1/clips/{id}/fit makes one (or ask scene \
                 \"auto\" or \"feed-forward\")"
            ))
        })
    }

    /// Checks that `times` can be decoded for `record`: finite, inside the context span, not
    /// too many.
    pub fn check_times(&self, record: &ClipRecord, times: &[f64]) -> Result<(), ServiceError> {
        if times.is_empty() {
            return Err(ServiceError::invalid(
                "give at least one time (\"t\" or \"times\")",
            ));
        }
        if times.len() > self.limits.max_times {
            return Err(ServiceError::TooLarge(format!(
                "{} times in one request; at most {} (C4G_MAX_TIMES)",
                times.len(),
                self.limits.max_times
            )));
        }
        let (first, last) = record.span();
        for &t in times {
            if !t.is_finite() {
                return Err(ServiceError::invalid(format!(
                    "times must be finite numbers of seconds, got {t}"
                )));
            }
            if t < first || t > last {
                return Err(ServiceError::invalid(format!(
                    "t = {t} s is outside the clip's context span [{first}, {last}] s: the model \
                     interpolates between its context frames and does not extrapolate"
                )));
            }
        }
        Ok(())
    }

    /// The approximation a request over `times` of clip `record` asks for, checked (by
    /// default: exact). Presets space their keyframes by the clip's context spacing.
    pub async fn approximation(
        &self,
        record: &ClipRecord,
        spec: &QualitySpec,
        times: &[f64],
    ) -> Result<Approximation, ServiceError> {
        let mut spec = *spec;
        if self.resolve_scene(&record.id, &mut spec, false).await? == Scene::Fitted {
            let fitted = self.fitted_scene(&record.id).await?;
            return Ok(Approximation {
                fitted: Some(fitted),
                ..Approximation::EXACT
            });
        }
        let spec = &spec;
        let spacing = quality::context_spacing(&record.context_times);
        let approximation = quality::resolve(spec, times, self.limits.max_times, spacing)?;
        // Refused before any work is spent: the package's decoder cannot drop queries.
        if approximation.drop_queries && !self.engine.has_query_subset() {
            return Err(EngineError::NoQuerySubset {
                package: self.engine.manifest().name.clone(),
            }
            .into());
        }
        Ok(approximation)
    }

    /// The Gaussians of clip `id` at each time: decoded exactly, or approximated as `quality`
    /// asks (keyframes, pruning).
    pub async fn decode(
        self: &Arc<Self>,
        id: &str,
        times: Vec<f64>,
        quality: QualitySpec,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let record = self.store.get_or_fetch(id).await?;
        self.check_times(&record, &times)?;
        let approximation = self.approximation(&record, &quality, &times).await?;
        if let Some(fitted) = approximation.fitted {
            return self
                .work(move |sets| sets.interpolate_now(&fitted.track, &times))
                .await;
        }
        let encoding = self.store.encoding(id).await?;
        if approximation.is_exact() {
            return self.batcher.decode(id, encoding, times).await;
        }
        let id = id.to_owned();
        self.work(move |sets| {
            let kept = sets.kept_now(&id, &encoding, &approximation)?;
            let sets = sets.decode_keyframed_now(
                &encoding,
                &times,
                &approximation.keyframes,
                kept.queries.as_ref(),
            )?;
            kept.select(sets)
        })
        .await
    }

    /// Decodes on the calling (blocking) thread.
    pub fn decode_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        self.decode_keyframed_now(encoding, times, &Keyframes::Exact, None)
    }

    /// Decodes on the calling (blocking) thread, exactly or through `keyframes`, on the queries
    /// `queries` alone when given.
    pub fn decode_keyframed_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        decoder::decode(&self.engine, encoding, times, keyframes, queries)
    }

    /// Which Gaussians of clip `id` a request pruned by `prune` keeps (`None`: all of them),
    /// measuring the clip on the calling thread the first time.
    pub fn keep_now(
        &self,
        id: &str,
        encoding: &Encoding,
        prune: Option<&c4g_analysis::pruning::PruneOptions>,
    ) -> Result<Option<Vec<bool>>, ServiceError> {
        prune
            .map(|options| {
                self.analyses
                    .keep(id, &self.engine, encoding, self.footprint, options)
            })
            .transpose()
    }

    /// What a request approximated by `approximation` keeps of clip `id`: which Gaussians, and,
    /// when it drops queries, the queries its decodes run (measuring the clip on the calling
    /// thread the first time).
    pub fn kept_now(
        &self,
        id: &str,
        encoding: &Encoding,
        approximation: &Approximation,
    ) -> Result<Kept, ServiceError> {
        let keep = self.keep_now(id, encoding, approximation.prune.as_ref())?;
        let queries = match &keep {
            Some(keep) if approximation.drop_queries => Some(QuerySubset::from_mask(keep)?),
            _ => None,
        };
        Ok(Kept { keep, queries })
    }

    /// Decides, on the calling thread, where the sets of a multi-time request over `times`
    /// come from (keyframes decoded now, or the decoder set by set) and which Gaussians they
    /// keep, so that [`sets_now`](Self::sets_now) can serve them piece by piece.
    pub fn plan_sets_now(
        &self,
        id: &str,
        encoding: &Encoding,
        times: &[f64],
        approximation: &Approximation,
    ) -> Result<SetPlan, ServiceError> {
        if let Some(fitted) = &approximation.fitted {
            return Ok(SetPlan {
                track: Some(fitted.track.clone()),
                kept: Kept {
                    keep: None,
                    queries: None,
                },
            });
        }
        let kept = self.kept_now(id, encoding, approximation)?;
        let track = if approximation.keyframes.interpolates(times) {
            let keyframes = &approximation.keyframes;
            let track =
                self.keyframe_track_now(encoding, times, keyframes, kept.queries.as_ref())?;
            Some(Arc::new(track))
        } else {
            None
        };
        Ok(SetPlan { track, kept })
    }

    /// The sets at `times` as `plan` says (on the calling thread).
    pub fn sets_now(
        &self,
        plan: &SetPlan,
        encoding: &Encoding,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let sets = match &plan.track {
            Some(track) => self.interpolate_now(track, times)?,
            None => self.decode_keyframed_now(
                encoding,
                times,
                &Keyframes::Exact,
                plan.kept.queries.as_ref(),
            )?,
        };
        plan.kept.select(sets)
    }

    /// Decodes the keyframes `keyframes` chooses for `times` (on the calling thread; on the
    /// queries `queries` alone when given), for [`interpolate_now`](Self::interpolate_now) to
    /// serve the sets from piece by piece.
    pub fn keyframe_track_now(
        &self,
        encoding: &Encoding,
        times: &[f64],
        keyframes: &Keyframes,
        queries: Option<&QuerySubset>,
    ) -> Result<KeyframeTrack, ServiceError> {
        decoder::keyframe_track(&self.engine, encoding, times, keyframes, queries)
    }

    /// The sets at `times` from a track's keyframes: exact at a keyframe, else interpolated.
    pub fn interpolate_now(
        &self,
        track: &KeyframeTrack,
        times: &[f64],
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        let sets = times
            .iter()
            .map(|&t| Ok((t, track.at(t)?)))
            .collect::<Result<Vec<_>, ServiceError>>()?;
        let interpolated = times.iter().filter(|&&t| track.keyframe(t).is_none());
        count_sets(0, interpolated.count());
        Ok(sets)
    }
}
