//! `StreamGaussians`: sets over a time range, as sets or compact `C4GV` pieces (REST: `api/stream.rs`).

use c4g_proto::v1 as pb;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::error::{IntoStatus, status};
use crate::wire::{self, Precision};
use c4g_formats::c4gv::EncodeOptions;
use c4g_service::sets::streaming::{self, Spacing, StreamRequest, check_compact};

use super::context::{BoxStream, Grpc};
use super::convert::*;

pub(super) async fn stream_gaussians(
    grpc: &Grpc,
    request: Request<pb::StreamGaussiansRequest>,
) -> Result<Response<BoxStream<pb::GaussianFrame>>, Status> {
    let request = request.into_inner();
    let service = grpc.service()?.clone();
    let spacing = match request.spacing {
        Some(pb::stream_gaussians_request::Spacing::Step(step)) => Spacing::Step(step),
        Some(pb::stream_gaussians_request::Spacing::Fps(fps)) => Spacing::Fps(fps),
        None => Spacing::Source,
    };
    let (quality, served) = resolved_quality(
        &service,
        &request.clip_id,
        request.quality,
        request.keyframes.as_ref(),
        request.prune.as_ref(),
        &request.scene,
        false,
    )
    .await?;
    let served = served.name();
    let stream = StreamRequest {
        start: request.start,
        end: request.end,
        spacing,
        quality,
    };
    let precision: Precision = wire::precision_from_proto(request.precision());
    let compact = match request.compact {
        Some(c) => {
            let defaults = EncodeOptions::default();
            let options = EncodeOptions {
                position_error: Some(c.position_error)
                    .filter(|&e| e != 0.0)
                    .unwrap_or(defaults.position_error),
                keyframe_interval: nonzero(c.keyframe_interval)
                    .unwrap_or(defaults.keyframe_interval),
                ..defaults
            };
            check_compact(&options).map_err(status)?;
            Some(options)
        }
        None => None,
    };
    let sets = streaming::stream(&service.sets, &request.clip_id, &stream)
        .await
        .map_err(status)?;
    let frames: BoxStream<pb::GaussianFrame> = match compact {
        Some(options) => Box::pin(sets.compact(options).map(|piece| match piece {
            Ok((time, bytes)) => Ok(pb::GaussianFrame {
                time,
                gaussians: None,
                c4gv: bytes,
                scene: served.to_owned(),
            }),
            Err(e) => Err(e.into_status()),
        })),
        None => Box::pin(
            ReceiverStream::new(sets.sets).map(move |frame| match frame {
                Ok((time, set)) => Ok(pb::GaussianFrame {
                    time,
                    gaussians: Some(wire::proto(&set, precision)),
                    c4gv: Vec::new(),
                    scene: served.to_owned(),
                }),
                Err(e) => Err(e.into_status()),
            }),
        ),
    };
    Ok(Response::new(frames))
}
