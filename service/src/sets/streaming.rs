//! Streams of Gaussian sets over a time range of a clip: what gRPC `StreamGaussians` and REST
//! `POST /v1/clips/{id}/stream` both serve, each in its own wire form.
//!
//! A stream is planned before its first set (the times, their keyframes, the Gaussians pruning
//! keeps: a plan that fails is the request's answer, not a stream cut short), then decoded in the
//! engine's batch size on work slots while a bounded channel holds at most [`STREAM_AHEAD`] sets
//! the client has not taken: a slow reader holds no work slot, and a reader that goes away ends
//! the decoding at the next set.
//!
//! [`SetStream::compact`] is the stream as `C4GV` bytes (the renderer's compact 4D stream,
//! `formats/src/c4gv/mod.rs`). Its static Gaussians (sent once) are those a keyframed
//! stream's keyframes show never to move; an exact stream's sets are known only as they are
//! decoded, so it sends every Gaussian in every frame (c4g-tiny moves all of them a little
//! anyway, `docs/benchmarks.md`).

use std::sync::Arc;

use c4g_engine::Encoding;
use c4g_formats::c4gv::{EncodeOptions, Encoder};
use c4g_scene::GaussianSet;
use futures_util::Stream;
use tokio::sync::mpsc;

use crate::ServiceError;
use crate::sets::SetSource;
use crate::sets::plan::SetPlan;
use crate::sets::quality::{Approximation, QualitySpec};

/// Sets a stream decodes ahead of what the client has taken: the backpressure bound.
pub const STREAM_AHEAD: usize = 4;

/// How far apart a stream's sets are.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Spacing {
    /// Seconds between sets.
    Step(f64),
    /// Sets a second.
    Fps(f64),
    /// The source's frame rate (10 a second when it has none).
    Source,
}

/// The largest `step` (seconds) or `fps` a stream may state: beyond any clip's length, or rate.
pub const MAX_SPACING: f64 = 1e6;

impl Spacing {
    /// The spacing a request states as `step` or `fps` (neither: the source's rate).
    pub fn stated(step: Option<f64>, fps: Option<f64>) -> Result<Self, ServiceError> {
        match (step, fps) {
            (Some(step), None) => Ok(Self::Step(step)),
            (None, Some(fps)) => Ok(Self::Fps(fps)),
            (None, None) => Ok(Self::Source),
            (Some(_), Some(_)) => Err(ServiceError::invalid("give \"step\" or \"fps\", not both")),
        }
    }

    fn step(self) -> Option<f64> {
        match self {
            Self::Step(step) => Some(step),
            _ => None,
        }
    }

    fn fps(self) -> Option<f64> {
        match self {
            Self::Fps(fps) => Some(fps),
            _ => None,
        }
    }
}

/// What a client asks a stream for.
#[derive(Debug, Clone)]
pub struct StreamRequest {
    /// First time (default: the span's start).
    pub start: Option<f64>,
    /// Last time (default: the span's end).
    pub end: Option<f64>,
    /// How far apart the sets are.
    pub spacing: Spacing,
    /// The speed/accuracy trade.
    pub quality: QualitySpec,
}

/// A planned stream: its times, and the sets as they are decoded.
pub struct SetStream {
    /// Every time the stream will send, in order.
    pub times: Vec<f64>,
    /// The sets, in the order of `times`; an error ends the stream.
    pub sets: mpsc::Receiver<Result<(f64, GaussianSet), ServiceError>>,
    plan: Arc<SetPlan>,
}

/// Plans the stream `request` asks of clip `id` and starts decoding it.
pub async fn stream(
    sets: &Arc<SetSource>,
    id: &str,
    request: &StreamRequest,
) -> Result<SetStream, ServiceError> {
    let record = sets.store.get_or_fetch(id).await?;
    let (first, last) = record.span();
    let (start, end) = (request.start.unwrap_or(first), request.end.unwrap_or(last));
    for (name, value) in [
        ("step", request.spacing.step()),
        ("fps", request.spacing.fps()),
    ] {
        if let Some(v) = value
            && !(v > 0.0 && v <= MAX_SPACING)
        {
            return Err(ServiceError::invalid(format!(
                "{name} must be above 0 and at most {MAX_SPACING:e}, got {v}"
            )));
        }
    }
    let step = match request.spacing {
        Spacing::Step(step) => step,
        Spacing::Fps(fps) => 1.0 / fps,
        Spacing::Source if record.source.fps > 0.0 => 1.0 / record.source.fps,
        Spacing::Source => 0.1,
    };
    // Positive now, or infinite: a rate so low that its step overflows is a step past any
    // span, which makes one set, at the start.
    sets.check_times(&record, &[start, end])?;
    if start > end {
        return Err(ServiceError::invalid(format!(
            "start {start} is after end {end}"
        )));
    }
    // Counted in f64 first: a tiny step makes more sets than a usize holds.
    let count = ((end - start) / step + 1e-9).floor() + 1.0;
    if count > sets.limits.max_times as f64 {
        return Err(ServiceError::TooLarge(format!(
            "{count:.0} sets in one stream; at most {} (C4G_MAX_TIMES): use a larger step",
            sets.limits.max_times
        )));
    }
    let times: Vec<f64> = (0..count as usize)
        .map(|i| match i {
            0 => start,
            i => (start + step * i as f64).min(end),
        })
        .collect();
    let approximation = sets
        .approximation(&record, &request.quality, &times)
        .await?;
    let encoding = sets.store.encoding(&record.id).await?;
    // With keyframes, those over the whole range are decoded now; each chunk is then
    // interpolated from them.
    let plan = plan_sets(sets, &record.id, &encoding, &times, approximation).await?;
    let (tx, rx) = mpsc::channel(STREAM_AHEAD);
    let (source, all, decoding) = (sets.clone(), times.clone(), plan.clone());
    tokio::spawn(async move {
        // Decode in the engine's batch size; a send waits while the client is behind.
        let batch = source
            .engine
            .decode_batch_size(encoding.frame_count())
            .max(1);
        for chunk in all.chunks(batch) {
            let (chunk, encoding, plan) = (chunk.to_vec(), encoding.clone(), decoding.clone());
            let frames = source
                .work(move |sets| sets.sets_now(&plan, &encoding, &chunk))
                .await;
            match frames {
                Ok(frames) => {
                    for frame in frames {
                        if tx.send(Ok(frame)).await.is_err() {
                            return; // the client went away
                        }
                    }
                }
                Err(e) => {
                    let _ = tx.send(Err(e)).await;
                    return;
                }
            }
        }
    });
    Ok(SetStream {
        times,
        sets: rx,
        plan,
    })
}

/// Bounds a compact stream's position error may have, scene units: from a hundredth of a
/// millimetre in a scene a few metres across (C4GV's range is 10⁶ steps, so ±10 units at the
/// finest) to a whole unit.
pub const POSITION_ERROR: std::ops::RangeInclusive<f64> = 1e-5..=1.0;

/// Keyframes a compact stream may put between its full sets for seeking, at most.
pub const MAX_KEYFRAME_INTERVAL: u32 = 1024;

impl SetStream {
    /// The stream as `C4GV` bytes, one piece per set (the first with the header and the static
    /// record), then the index record (time: the last set's). `options` are checked with
    /// [`check_compact`].
    pub fn compact(
        self,
        options: EncodeOptions,
    ) -> impl Stream<Item = Result<(f64, Vec<u8>), ServiceError>> + Send {
        let statics = self.plan.static_mask(&options);
        let state = Compact {
            sets: self.sets,
            encoder: None,
            statics,
            options,
            last: 0.0,
            done: false,
        };
        futures_util::stream::unfold(state, |mut state| async move {
            if state.done {
                return None;
            }
            let piece = match state.sets.recv().await {
                Some(Ok((time, set))) => state.push(time, &set).map(|bytes| (time, bytes)),
                Some(Err(e)) => Err(e),
                None => {
                    state.done = true;
                    let index = state.encoder.take().map(Encoder::finish);
                    return index.map(|bytes| (Ok((state.last, bytes)), state));
                }
            };
            state.done = piece.is_err();
            Some((piece, state))
        })
    }
}

/// Checks a compact stream's options as a client states them.
pub fn check_compact(options: &EncodeOptions) -> Result<(), ServiceError> {
    if !POSITION_ERROR.contains(&options.position_error) {
        return Err(ServiceError::invalid(format!(
            "position_error must be between {:e} and {:e} scene units, got {}",
            POSITION_ERROR.start(),
            POSITION_ERROR.end(),
            options.position_error
        )));
    }
    if !(1..=MAX_KEYFRAME_INTERVAL).contains(&options.keyframe_interval) {
        return Err(ServiceError::invalid(format!(
            "keyframe_interval must be between 1 and {MAX_KEYFRAME_INTERVAL}, got {}",
            options.keyframe_interval
        )));
    }
    Ok(())
}

/// A compact stream's encoder, made with the first set (whose length pruning decides).
struct Compact {
    sets: mpsc::Receiver<Result<(f64, GaussianSet), ServiceError>>,
    encoder: Option<Encoder>,
    statics: Option<Vec<bool>>,
    options: EncodeOptions,
    last: f64,
    done: bool,
}

impl Compact {
    fn push(&mut self, time: f64, set: &GaussianSet) -> Result<Vec<u8>, ServiceError> {
        let mut out = Vec::new();
        if self.encoder.is_none() {
            let mask = match self.statics.take() {
                Some(mask) if mask.len() == set.len() => mask,
                _ => vec![false; set.len()],
            };
            let (encoder, header) = Encoder::with_static_mask(&mask, &self.options)
                .map_err(|e| ServiceError::invalid(format!("cannot start the stream: {e}")))?;
            out = header;
            self.encoder = Some(encoder);
        }
        let encoder = self
            .encoder
            .as_mut()
            .ok_or_else(|| ServiceError::Internal("the compact stream lost its encoder".into()))?;
        // The model's sets are canonical, so what C4GV refuses is a set beyond the grid's range:
        // the bound asked for is too fine for this scene.
        let frame = encoder.push(time, set).map_err(|e| {
            ServiceError::invalid(format!(
                "the set at {time} s cannot be sent at position_error {}: {e} (ask for a \
                 larger position_error)",
                self.options.position_error
            ))
        })?;
        out.extend_from_slice(&frame);
        self.last = time;
        Ok(out)
    }
}

/// Where a stream's sets come from, decided on a work slot before the first is sent: keyframes
/// decoded over all of `times` (or none: the stream decodes chunk by chunk as it goes), and the
/// Gaussians pruning keeps.
pub async fn plan_sets(
    sets: &Arc<SetSource>,
    id: &str,
    encoding: &Arc<Encoding>,
    times: &[f64],
    approximation: Approximation,
) -> Result<Arc<SetPlan>, ServiceError> {
    let (id, encoding, times) = (id.to_owned(), encoding.clone(), times.to_vec());
    let plan = sets
        .work(move |sets| sets.plan_sets_now(&id, &encoding, &times, &approximation))
        .await?;
    Ok(Arc::new(plan))
}
