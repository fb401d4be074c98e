//! `Tracks`: query points followed through a clip (REST: `api/tracks.rs`).

use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status};

use crate::error::{IntoStatus, status};
use c4g_service::ServiceError;
use c4g_service::views::tracking::{TrackRequest, Tracker};

use super::context::Grpc;
use super::convert::*;

pub(super) async fn tracks(
    grpc: &Grpc,
    request: Request<pb::TracksRequest>,
) -> Result<Response<pb::TracksResponse>, Status> {
    let request = request.into_inner();
    let tracker = match pb::Tracker::try_from(request.tracker) {
        Ok(pb::Tracker::Unspecified | pb::Tracker::Gaussians) => Tracker::Gaussians,
        Ok(pb::Tracker::Features) => Tracker::Features,
        Err(_) => {
            return Err(ServiceError::invalid(format!(
                "unknown tracker {}: TRACKER_GAUSSIANS or TRACKER_FEATURES",
                request.tracker
            ))
            .into_status());
        }
    };
    let service = grpc.service()?;
    // As REST resolves it (`api/tracks.rs`): the feature tracker reads the feed-forward scene's
    // lifted features.
    let (quality, served) = resolved_quality(
        service,
        &request.clip_id,
        request.quality,
        request.keyframes.as_ref(),
        request.prune.as_ref(),
        &request.scene,
        tracker == Tracker::Features,
    )
    .await?;
    let track_request = TrackRequest {
        tracker,
        queries: request.queries.iter().map(track_query).collect(),
        times: (!request.times.is_empty()).then_some(request.times),
        width: request.width,
        height: request.height,
        quality,
    };
    let tracks = service
        .views
        .tracks(&request.clip_id, track_request)
        .await
        .map_err(status)?;
    Ok(Response::new(pb::TracksResponse {
        scene: served.name().to_owned(),
        tracker: match tracks.tracker {
            Tracker::Gaussians => pb::Tracker::Gaussians,
            Tracker::Features => pb::Tracker::Features,
        } as i32,
        width: tracks.width,
        height: tracks.height,
        times: tracks.times,
        tracks: tracks
            .tracks
            .into_iter()
            .map(|track| pb::Track {
                query: Some(pb::TrackQuery {
                    time: track.query.t,
                    x: track.query.x,
                    y: track.query.y,
                }),
                anchored: track.anchored,
                points: track
                    .points
                    .into_iter()
                    .map(|p| pb::TrackPoint {
                        time: p.t,
                        x: p.x,
                        y: p.y,
                        visible: p.visible,
                        depth: p.depth,
                        position: p.position.to_vec(),
                        similarity: p.similarity,
                    })
                    .collect(),
            })
            .collect(),
    }))
}
