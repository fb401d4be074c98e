//! Which Gaussians of a clip a pruned request keeps: the clip's [`SceneAnalysis`], measured once
//! and kept in memory, so every set of the clip, at any time and in any request, keeps the same
//! Gaussians (a stream's sets stay one to one).
//!
//! The analysis samples the clip at its context times (decoded exactly) and halfway between
//! them (interpolated from those), and renders each sample at the model's input size from the
//! first context camera and a ring of novel views: an orbit of ±15° about the point at the
//! scene's median depth. What pruning drops then changes no render from those views by more than
//! the stated floors (`c4g_analysis::pruning`); views far outside that ring are not covered.

use std::num::NonZeroUsize;
use std::sync::{Arc, Mutex, PoisonError};

use c4g_analysis::pruning::{PruneOptions, SceneAnalysis};
use c4g_engine::{Encoding, Engine, KeyframeTrack};
use c4g_renderer::{CpuRasterizer, RenderOptions};
use c4g_scene::Footprint;
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics, Trajectory};
use glam::Affine3A;
use lru::LruCache;

use crate::ServiceError;

/// Clips whose analysis stays in memory (a few floats per Gaussian: 24 KB a clip at 2,048).
const ANALYSES_KEPT: usize = 1024;

/// The ring of novel views: its total sweep and its cameras besides the context camera.
const RING_DEGREES: f32 = 30.0;
const RING_VIEWS: usize = 5;

/// The analyses of recently pruned clips, by clip id.
pub struct Analyses {
    cache: Mutex<LruCache<String, Arc<SceneAnalysis>>>,
    rasterizer: CpuRasterizer,
}

impl Default for Analyses {
    fn default() -> Self {
        Self {
            cache: Mutex::new(LruCache::new(
                NonZeroUsize::new(ANALYSES_KEPT).unwrap_or(NonZeroUsize::MIN),
            )),
            rasterizer: CpuRasterizer::new(),
        }
    }
}

impl Analyses {
    /// Which Gaussians of clip `id` to keep under `options`, measuring the clip first if it has
    /// not been (on the calling thread: a few decodes and renders). Two requests that miss at
    /// once both measure; they get the same answer.
    pub fn keep(
        &self,
        id: &str,
        engine: &Engine,
        encoding: &Encoding,
        footprint: Footprint,
        options: &PruneOptions,
    ) -> Result<Vec<bool>, ServiceError> {
        let cached = self.lock().get(id).cloned();
        let analysis = match cached {
            Some(analysis) => analysis,
            None => {
                let analysis = Arc::new(self.measure(engine, encoding, footprint)?);
                self.lock().put(id.to_owned(), analysis.clone());
                metrics::counter!("c4g_scene_analyses_total").increment(1);
                analysis
            }
        };
        let mut keep = analysis.keep(options);
        // A set of no Gaussians renders nothing and serialises awkwardly everywhere; keeping the
        // most visible one costs nothing and keeps every consumer's shapes non-empty.
        if !keep.iter().any(|k| *k)
            && let Some(best) = (0..keep.len()).max_by(|&a, &b| {
                analysis.max_contribution[a].total_cmp(&analysis.max_contribution[b])
            })
        {
            keep[best] = true;
        }
        Ok(keep)
    }

    /// Forgets a deleted clip's analysis.
    pub fn forget(&self, id: &str) {
        self.lock().pop(id);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LruCache<String, Arc<SceneAnalysis>>> {
        self.cache.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn measure(
        &self,
        engine: &Engine,
        encoding: &Encoding,
        footprint: Footprint,
    ) -> Result<SceneAnalysis, ServiceError> {
        let mut times = encoding.times().to_vec();
        times.sort_by(f64::total_cmp);
        times.dedup();
        let decoded = engine.decode(encoding, &times)?;
        let track = KeyframeTrack::new(times.iter().copied().zip(decoded).collect())?;
        let mut samples: Vec<GaussianSet> = Vec::with_capacity(2 * times.len());
        for (i, &t) in times.iter().enumerate() {
            if i > 0 {
                samples.push(track.at(0.5 * (times[i - 1] + t))?);
            }
            samples.push(track.at(t)?);
        }
        let input = &engine.manifest().input;
        let cameras = analysis_cameras(&samples[0], input.width, input.height)?;
        Ok(SceneAnalysis::measure(
            &samples,
            &cameras,
            &self.rasterizer,
            &RenderOptions {
                footprint,
                ..RenderOptions::default()
            },
        )?)
    }
}

/// The first context camera and the ring about the point at `set`'s median depth.
fn analysis_cameras(
    set: &GaussianSet,
    width: u32,
    height: u32,
) -> Result<Vec<Camera>, ServiceError> {
    let reference = Camera::from_normalized(
        NormalizedIntrinsics::C4G_DEFAULT,
        width,
        height,
        Affine3A::IDENTITY,
    )?;
    let mut depths: Vec<f32> = set
        .positions()
        .iter()
        .map(|p| p[2])
        .filter(|z| z.is_finite() && *z > 0.0)
        .collect();
    depths.sort_by(f32::total_cmp);
    // C4G's scale puts a static camera's median depth at 2: the fallback when nothing is ahead.
    let depth = depths.get(depths.len() / 2).copied().unwrap_or(2.0);
    let mut cameras = vec![reference];
    cameras.extend(
        Trajectory::Orbit {
            depth,
            angle_degrees: RING_DEGREES,
            radius: None,
        }
        .cameras(&reference, RING_VIEWS)?,
    );
    Ok(cameras)
}
