//! `Segment`: what a click or a feature selects, with its masks (REST: `api/segment.rs`).

use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status};

use crate::error::{IntoStatus, status};
use c4g_service::ServiceError;
use c4g_service::views::features::{Click, SegmentRequest, Selection};

use super::context::Grpc;
use super::convert::*;

pub(super) async fn segment(
    grpc: &Grpc,
    request: Request<pb::SegmentRequest>,
) -> Result<Response<pb::SegmentResponse>, Status> {
    use pb::segment_request::Selection as Pick;
    let request = request.into_inner();
    let selection = match request.selection {
        Some(Pick::Click(click)) => Selection::Click(Click {
            t: click.time,
            x: click.x,
            y: click.y,
        }),
        Some(Pick::Feature(f)) => Selection::Feature {
            feature: f.feature,
            t: f.time,
        },
        None => {
            return Err(ServiceError::invalid(
                "SegmentRequest needs its selection: click or feature",
            )
            .into_status());
        }
    };
    let segment_request = SegmentRequest {
        selection,
        threshold: request.threshold,
        times: (!request.times.is_empty()).then_some(request.times),
        camera: request.camera.map(|c| camera_spec(Some(c))),
        width: nonzero(request.width),
        height: nonzero(request.height),
    };
    let segment = grpc
        .service()?
        .views
        .segment(&request.clip_id, segment_request)
        .await
        .map_err(status)?;
    Ok(Response::new(pb::SegmentResponse {
        width: segment.width,
        height: segment.height,
        time: segment.t,
        threshold: segment.threshold,
        feature: segment.feature,
        gaussians: segment.gaussians,
        masks: segment
            .masks
            .into_iter()
            .map(|m| pb::Mask {
                time: m.t,
                area: m.area,
                counts: m.counts,
            })
            .collect(),
    }))
}
