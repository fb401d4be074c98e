//! The engine's decodes on the calling (blocking) thread, timed and counted: what the set
//! source and the batcher both run on their work slots.

use std::time::Instant;

use c4g_engine::{Encoding, Engine, KeyframeTrack, Keyframes, QuerySubset};
use c4g_scene::GaussianSet;

use crate::ServiceError;

/// The sets at `times`, exactly or through `keyframes`, on the queries `queries` alone when
/// given.
pub fn decode(
    engine: &Engine,
    encoding: &Encoding,
    times: &[f64],
    keyframes: &Keyframes,
    queries: Option<&QuerySubset>,
) -> Result<Vec<(f64, GaussianSet)>, ServiceError> {
    let started = Instant::now();
    let (sets, stats) = engine.decode_keyframed_on(encoding, times, keyframes, queries)?;
    metrics::histogram!("c4g_decode_duration_seconds").record(started.elapsed().as_secs_f64());
    record_resident(engine);
    count_sets(stats.exact_decodes, stats.interpolated);
    Ok(times.iter().copied().zip(sets).collect())
}

/// The keyframes `keyframes` chooses for `times`, decoded (on the queries `queries` alone when
/// given), for sets to be interpolated from piece by piece.
pub fn keyframe_track(
    engine: &Engine,
    encoding: &Encoding,
    times: &[f64],
    keyframes: &Keyframes,
    queries: Option<&QuerySubset>,
) -> Result<KeyframeTrack, ServiceError> {
    let started = Instant::now();
    let (track, stats) = engine.keyframe_track_on(encoding, times, keyframes, queries)?;
    metrics::histogram!("c4g_decode_duration_seconds").record(started.elapsed().as_secs_f64());
    record_resident(engine);
    count_sets(stats.exact_decodes, 0);
    Ok(track)
}

/// The device-resident encodings' gauges (nothing when residency is off).
pub fn record_resident(engine: &Engine) {
    if let Some(stats) = engine.resident_stats() {
        metrics::gauge!("c4g_device_cache_bytes").set(stats.bytes as f64);
        metrics::gauge!("c4g_device_cache_clips").set(stats.encodings as f64);
        metrics::counter!("c4g_device_cache_placements_total").absolute(stats.placements);
        metrics::counter!("c4g_device_cache_spills_total").absolute(stats.spills);
    }
}

/// Counts the sets the decoder computed and those interpolated between keyframes.
pub fn count_sets(exact: usize, interpolated: usize) {
    for (how, n) in [("exact", exact), ("interpolated", interpolated)] {
        if n > 0 {
            metrics::counter!("c4g_decoded_sets_total", "how" => how).increment(n as u64);
        }
    }
}
