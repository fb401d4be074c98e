//! `Decode`: the Gaussian sets of a clip at times (REST: `api/gaussians.rs`).

use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status};

use crate::error::status;
use crate::wire::{self, Precision};

use super::context::Grpc;
use super::convert::*;

pub(super) async fn decode(
    grpc: &Grpc,
    request: Request<pb::DecodeRequest>,
) -> Result<Response<pb::DecodeResponse>, Status> {
    let request = request.into_inner();
    let precision: Precision = wire::precision_from_proto(request.precision());
    let service = grpc.service()?;
    let (quality, served) = resolved_quality(
        service,
        &request.clip_id,
        request.quality,
        request.keyframes.as_ref(),
        request.prune.as_ref(),
        &request.scene,
        request.features,
    )
    .await?;
    let frames = if request.features {
        service
            .views
            .decode_features(&request.clip_id, request.times, quality)
            .await
            .map_err(status)?
    } else {
        service
            .sets
            .decode(&request.clip_id, request.times, quality)
            .await
            .map_err(status)?
    };
    Ok(Response::new(pb::DecodeResponse {
        frames: frames
            .iter()
            .map(|(t, set)| pb::GaussianFrame {
                time: *t,
                gaussians: Some(wire::proto(set, precision)),
                c4gv: Vec::new(),
                scene: served.name().to_owned(),
            })
            .collect(),
        scene: served.name().to_owned(),
    }))
}
