//! `RecoverCameras`: each context frame's camera by photometric alignment (REST: `api/cameras.rs`).

use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status};

use crate::error::status;
use c4g_service::views::recovery::RecoverOptions;

use super::context::Grpc;
use super::convert::*;

pub(super) async fn recover_cameras(
    grpc: &Grpc,
    request: Request<pb::RecoverCamerasRequest>,
) -> Result<Response<pb::RecoveredCameras>, Status> {
    let request = request.into_inner();
    let options = RecoverOptions {
        refine_focal: request.refine_focal,
    };
    let recovered = grpc
        .service()?
        .views
        .recover_cameras(&request.clip_id, options)
        .await
        .map_err(status)?;
    Ok(Response::new(pb::RecoveredCameras {
        cameras: Some(clip_cameras(&recovered.cameras)),
        fits: recovered
            .fits
            .iter()
            .map(|f| pb::FrameFit {
                time: f.t,
                initial_residual: f.initial_residual,
                residual: f.residual,
                confidence: f.confidence,
                coverage: f.coverage,
                conditioning: f.conditioning,
                iterations: u32::try_from(f.iterations).unwrap_or(u32::MAX),
                converged: f.converged,
            })
            .collect(),
    }))
}
