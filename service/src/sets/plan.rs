//! What a request keeps of a clip's Gaussians, and where the sets of a multi-time request come
//! from: decided once by the [`SetSource`](crate::sets::SetSource), then served piece by piece.

use std::sync::Arc;

use c4g_engine::{KeyframeTrack, QuerySubset};
use c4g_scene::GaussianSet;

use c4g_formats::c4gv::{self, EncodeOptions};

use crate::ServiceError;

/// What a request keeps of a clip's Gaussians ([`SetSource::kept_now`](crate::sets::SetSource::kept_now)).
pub struct Kept {
    /// The Gaussians kept (`None`: all).
    pub(crate) keep: Option<Vec<bool>>,
    /// The queries decodes run when the request drops queries (`None`: all of them, the
    /// Gaussians outside `keep` then removed from each decoded set).
    pub(crate) queries: Option<QuerySubset>,
}

impl Kept {
    /// The kept Gaussians of `sets`: sets decoded on the kept queries hold nothing else.
    pub(crate) fn select(
        &self,
        sets: Vec<(f64, GaussianSet)>,
    ) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
        if self.queries.is_some() {
            return Ok(sets);
        }
        prune(self.keep.as_deref(), sets)
    }
}

/// Where the sets of a multi-time request come from, and which Gaussians they keep: decided once
/// ([`SetSource::plan_sets_now`](crate::sets::SetSource::plan_sets_now)), then served piece by piece ([`SetSource::sets_now`](crate::sets::SetSource::sets_now)).
pub struct SetPlan {
    /// The keyframes to interpolate from (`None`: every set decoded exactly).
    pub(crate) track: Option<Arc<KeyframeTrack>>,
    /// The Gaussians kept, and the queries decoded.
    pub(crate) kept: Kept,
}

impl SetPlan {
    /// The Gaussians (of those kept) that never move, when keyframes show it: interpolation
    /// between keyframes that agree gives the same values. `None` for an exact plan.
    pub fn static_mask(&self, options: &EncodeOptions) -> Option<Vec<bool>> {
        let track = self.track.as_ref()?;
        // Keyframes decoded on the kept queries hold the kept Gaussians only.
        let keep = self
            .kept
            .keep
            .as_ref()
            .filter(|_| self.kept.queries.is_none());
        let sets: Vec<GaussianSet> = match keep {
            Some(keep) => track
                .sets()
                .iter()
                .map(|set| set.select(keep))
                .collect::<Result<_, _>>()
                .ok()?,
            None => track.sets().to_vec(),
        };
        static_mask(&sets, options)
    }
}

/// The Gaussians of each set that `keep` keeps (all of them without it).
fn prune(
    keep: Option<&[bool]>,
    sets: Vec<(f64, GaussianSet)>,
) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
    let Some(keep) = keep else {
        return Ok(sets);
    };
    sets.into_iter()
        .map(|(t, set)| Ok((t, set.select(keep)?)))
        .collect()
}

/// A `C4GV` mask of the Gaussians that `sets` show never to move, or `None` when they show
/// nothing (fewer than two sets, or sets C4GV cannot quantise).
pub fn static_mask(sets: &[GaussianSet], options: &EncodeOptions) -> Option<Vec<bool>> {
    (sets.len() >= 2)
        .then(|| c4gv::static_mask(sets, options).ok())
        .flatten()
}
