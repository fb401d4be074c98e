//! Clips over gRPC: `Upload` (a header, then chunks), `GetClip`, `ListClips`, `DeleteClip` (REST: `api/clips.rs`).

use bytes::BytesMut;
use c4g_proto::v1 as pb;
use tonic::{Request, Response, Status, Streaming};

use crate::error::{IntoStatus, status};
use c4g_service::ServiceError;
use c4g_service::clips::intake::{IntakeOptions, Media, MediaKind};

use super::context::Grpc;
use super::convert::*;

pub(super) async fn upload(
    grpc: &Grpc,
    request: Request<Streaming<pb::UploadRequest>>,
) -> Result<Response<pb::Clip>, Status> {
    let service = grpc.service()?.clone();
    let mut stream = request.into_inner();
    let header = match stream.message().await? {
        Some(pb::UploadRequest {
            part: Some(pb::upload_request::Part::Header(header)),
        }) => header,
        _ => {
            return Err(
                ServiceError::invalid("the first message of an upload must be its header")
                    .into_status(),
            );
        }
    };
    let limit = service.limits.max_body_bytes;
    let mut data = BytesMut::new();
    while let Some(message) = stream.message().await? {
        match message.part {
            Some(pb::upload_request::Part::Chunk(chunk)) => {
                if data.len() + chunk.len() > limit {
                    return Err(ServiceError::TooLarge(format!(
                        "the upload is over {limit} bytes (C4G_MAX_BODY_MIB)"
                    ))
                    .into_status());
                }
                data.extend_from_slice(&chunk);
            }
            _ => {
                return Err(
                    ServiceError::invalid("after the header an upload sends only chunks")
                        .into_status(),
                );
            }
        }
    }
    let kind = match pb::MediaKind::try_from(header.kind) {
        Ok(pb::MediaKind::Video) => Some(MediaKind::Video),
        Ok(pb::MediaKind::Zip) => Some(MediaKind::Zip),
        Ok(pb::MediaKind::Tar) => Some(MediaKind::Tar),
        _ => None,
    };
    let sampling = header.sampling.unwrap_or_default();
    let options = IntakeOptions {
        fps: header.fps,
        timestamps: (!header.timestamps.is_empty()).then_some(header.timestamps),
        max_frames: sampling.max_frames.map(|n| n as usize),
        stride: sampling.stride.map(|n| n as usize),
        start: sampling.start,
        end: sampling.end,
        cameras: header
            .cameras
            .map(given_cameras)
            .transpose()
            .map_err(status)?,
    };
    let media = Media::File {
        data: data.freeze(),
        kind,
    };
    let (record, created) = service.upload(media, options).await.map_err(status)?;
    Ok(Response::new(clip_proto(&record, created)))
}

pub(super) async fn get_clip(
    grpc: &Grpc,
    request: Request<pb::ClipRef>,
) -> Result<Response<pb::Clip>, Status> {
    let service = grpc.service()?;
    let record = service
        .store
        .get_or_fetch(&request.into_inner().clip_id)
        .await
        .map_err(status)?;
    let mut clip = clip_proto(&record, false);
    if let Some(fitted) = service.sets.fitted.get(&record.id).await.map_err(status)? {
        clip.fitted_json = serde_json::to_string(&fitted.summary).unwrap_or_default();
    }
    Ok(Response::new(clip))
}

pub(super) async fn list_clips(
    grpc: &Grpc,
    _: Request<pb::ListClipsRequest>,
) -> Result<Response<pb::ListClipsResponse>, Status> {
    let clips = grpc.service()?.store.list_all().await.map_err(status)?;
    Ok(Response::new(pb::ListClipsResponse {
        clips: clips.iter().map(|r| clip_proto(r, false)).collect(),
    }))
}

pub(super) async fn delete_clip(
    grpc: &Grpc,
    request: Request<pb::ClipRef>,
) -> Result<Response<pb::DeleteClipResponse>, Status> {
    grpc.service()?
        .delete(&request.into_inner().clip_id)
        .await
        .map_err(status)?;
    Ok(Response::new(pb::DeleteClipResponse {}))
}
