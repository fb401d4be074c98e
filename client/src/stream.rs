//! Streaming Gaussian sets over a time range (gRPC `StreamGaussians`).
//!
//! gRPC rather than REST because a stream of sets is many messages with backpressure: the server
//! decodes a bounded number ahead, and a slow reader slows it down through HTTP/2 flow control.

use c4g_formats::c4gv;
use c4g_proto::v1 as proto;
use futures_util::StreamExt;
use futures_util::stream::BoxStream;

use crate::{Approximation, Client, Error, GaussianFrame, Keyframes, Precision, Prune, wire};

/// The spacing of streamed sets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Spacing {
    /// One set every this many seconds.
    Step(f64),
    /// This many sets per second.
    Fps(f64),
}

/// What to stream; every field defaults to the server's choice (the whole context span, at the
/// clip's frame rate, in `f32`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StreamOptions {
    /// First time, seconds.
    pub start: Option<f64>,
    /// Last time, seconds.
    pub end: Option<f64>,
    /// Spacing of the times.
    pub spacing: Option<Spacing>,
    /// Precision on the wire (the sets arrive as `f32` either way).
    pub precision: Precision,
    /// A quality preset, keyframes (decoded over the range first, the sets between them
    /// interpolated), pruning (default: exact).
    pub approximation: Approximation,
    /// The sets as one compact 4D stream (`C4GV`: quantised within a stated bound, a fraction
    /// of the bytes), decoded here as they arrive; `precision` does not apply then.
    pub compact: Option<Compact>,
}

/// A compact stream's settings (`formats/src/c4gv/mod.rs` states every bound).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Compact {
    /// Largest error of a position coordinate, scene units (1e-5 to 1).
    pub position_error: f64,
    /// A full set every this many sets (1 to 1024).
    pub keyframe_interval: u32,
}

impl Default for Compact {
    fn default() -> Self {
        let options = c4gv::EncodeOptions::default();
        Self {
            position_error: options.position_error,
            keyframe_interval: options.keyframe_interval,
        }
    }
}

/// Gaussian sets in time order, as they arrive; the first error ends the stream.
pub type GaussianStream = BoxStream<'static, Result<GaussianFrame, Error>>;

impl Client {
    /// Streams the Gaussian sets of a clip over a time range. The call returns once the server
    /// accepted the request (an unknown clip or a bad range fails here); sets follow as the
    /// server decodes them.
    pub async fn stream(
        &self,
        clip_id: &str,
        options: &StreamOptions,
    ) -> Result<GaussianStream, Error> {
        let request = proto::StreamGaussiansRequest {
            clip_id: clip_id.to_owned(),
            start: options.start,
            end: options.end,
            spacing: options.spacing.map(|spacing| match spacing {
                Spacing::Step(step) => proto::stream_gaussians_request::Spacing::Step(step),
                Spacing::Fps(fps) => proto::stream_gaussians_request::Spacing::Fps(fps),
            }),
            precision: wire::proto_precision(options.precision).into(),
            keyframes: options
                .approximation
                .keyframes
                .as_ref()
                .map(Keyframes::to_proto),
            quality: options.approximation.proto_quality(),
            prune: options.approximation.prune.as_ref().map(Prune::to_proto),
            compact: options.compact.map(|c| proto::CompactStream {
                position_error: c.position_error,
                keyframe_interval: c.keyframe_interval,
            }),
            scene: options
                .approximation
                .scene
                .map_or(String::new(), |s| s.name().to_owned()),
        };
        let mut grpc = self.grpc().await?;
        let frames = grpc
            .stream_gaussians(self.grpc_request(request))
            .await?
            .into_inner();
        if options.compact.is_none() {
            return Ok(frames.map(|frame| wire::unpack_frame(&frame?)).boxed());
        }
        // Each message holds a piece of one C4GV stream: fed to one decoder, in order.
        let decoded = frames.scan(c4gv::Decoder::new(), |decoder, message| {
            let sets = match message {
                Ok(message) => {
                    decoder.feed(&message.c4gv);
                    let mut sets = Vec::new();
                    loop {
                        match decoder.next_frame() {
                            Ok(Some((time, gaussians))) => {
                                sets.push(Ok(GaussianFrame { time, gaussians }));
                            }
                            Ok(None) => break,
                            Err(e) => {
                                sets.push(Err(Error::Malformed(format!("the C4GV stream: {e}"))));
                                break;
                            }
                        }
                    }
                    sets
                }
                Err(status) => vec![Err(status.into())],
            };
            std::future::ready(Some(futures_util::stream::iter(sets)))
        });
        Ok(decoded.flatten().boxed())
    }
}
