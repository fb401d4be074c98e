//! Streaming Gaussian sets over a time range (gRPC `StreamGaussians`).
//!
//! gRPC rather than REST because a stream of sets is many messages with backpressure: the server
//! decodes a bounded number ahead, and a slow reader slows it down through HTTP/2 flow control.

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
        };
        let mut grpc = self.grpc().await?;
        let frames = grpc
            .stream_gaussians(self.grpc_request(request))
            .await?
            .into_inner();
        Ok(frames.map(|frame| wire::unpack_frame(&frame?)).boxed())
    }
}
