//! `Render` and `RenderTrajectory`: one view, or a camera path frame by frame (REST: `api/render.rs`).

use c4g_proto::v1 as pb;
use c4g_scene::Trajectory;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::error::{IntoStatus, status};
use c4g_service::ServiceError;
use c4g_service::service::{PathRequest, ViewRequest};
use c4g_service::sets::streaming::{STREAM_AHEAD, plan_sets};
use c4g_service::views::features::FeatureRender;
use c4g_service::views::image_formats::encode_image;

use super::Grpc;
use super::convert::*;

pub(super) async fn render(
    grpc: &Grpc,
    request: Request<pb::RenderRequest>,
) -> Result<Response<pb::RenderedImage>, Status> {
    let request = request.into_inner();
    let format = image_format(request.format).map_err(status)?;
    let view = ViewRequest {
        t: request.time,
        camera: camera_spec(request.camera),
        width: nonzero(request.width),
        height: nonzero(request.height),
        background: background(&request.background).map_err(status)?,
    };
    let quality = quality_spec(request.quality, None, request.prune.as_ref()).map_err(status)?;
    if let Some(render) = FeatureRender::of_format(format) {
        let features = grpc
            .service()?
            .render_features(&request.clip_id, view, quality, render)
            .await
            .map_err(status)?;
        return Ok(Response::new(pb::RenderedImage {
            time: request.time,
            width: features.width,
            height: features.height,
            format: request.format,
            data: features.bytes,
            channels: match render {
                FeatureRender::Raw => features.channels as u32,
                FeatureRender::Pca => 0,
            },
        }));
    }
    let image = grpc
        .service()?
        .render_view(&request.clip_id, view, quality)
        .await
        .map_err(status)?;
    Ok(Response::new(pb::RenderedImage {
        time: request.time,
        width: image.width,
        height: image.height,
        format: request.format,
        data: encode_image(&image, format).map_err(status)?,
        channels: 0,
    }))
}

pub(super) async fn render_trajectory(
    grpc: &Grpc,
    request: Request<pb::RenderTrajectoryRequest>,
) -> Result<Response<super::BoxStream<pb::RenderedImage>>, Status> {
    let request = request.into_inner();
    let service = grpc.service()?.clone();
    let format = image_format(request.format).map_err(status)?;
    if FeatureRender::of_format(format).is_some() {
        return Err(ServiceError::invalid(
            "feature images (IMAGE_FORMAT_FEATURES_F32, IMAGE_FORMAT_FEATURES_PCA_PNG) are \
             single views: use Render",
        )
        .into_status());
    }
    let preset = match request.preset_json.trim() {
        "" => None,
        json => {
            let not_one =
                |e| ServiceError::invalid(format!("preset_json is not a trajectory: {e}"));
            let value: serde_json::Value = serde_json::from_str(json)
                .map_err(not_one)
                .map_err(status)?;
            c4g_service::views::camera::check_preset(&value).map_err(status)?;
            Some(
                serde_json::from_value::<Trajectory>(value)
                    .map_err(not_one)
                    .map_err(status)?,
            )
        }
    };
    let path = PathRequest {
        preset,
        cameras: request
            .cameras
            .into_iter()
            .map(|c| camera_spec(Some(c)))
            .collect(),
        camera: camera_spec(request.camera),
        frames: (request.frames != 0).then_some(request.frames as usize),
        start: request.start,
        end: request.end,
        width: nonzero(request.width),
        height: nonzero(request.height),
        background: background(&request.background).map_err(status)?,
    };
    let record = service
        .store
        .get_or_fetch(&request.clip_id)
        .await
        .map_err(status)?;
    let frames = service.plan_path(&record, &path).map_err(status)?;
    let times: Vec<f64> = frames.iter().map(|(t, _)| *t).collect();
    let quality = quality_spec(
        request.quality,
        request.keyframes.as_ref(),
        request.prune.as_ref(),
    )
    .map_err(status)?;
    let approximation = service
        .approximation(&record, &quality, &times)
        .map_err(status)?;
    let encoding = service.store.encoding(&record.id).await.map_err(status)?;
    let (tx, rx) = mpsc::channel(STREAM_AHEAD);
    let bg = path.background;
    tokio::spawn(async move {
        let plan = match plan_sets(&service, &record.id, &encoding, &times, approximation).await {
            Ok(plan) => plan,
            Err(e) => {
                let _ = tx.send(Err(e.into_status())).await;
                return;
            }
        };
        for (t, camera) in frames {
            let encoding = encoding.clone();
            let plan = plan.clone();
            let result = service
                .work(move |service| {
                    let (_, set) = service
                        .sets_now(&plan, &encoding, &[t])?
                        .pop()
                        .ok_or_else(|| ServiceError::Internal("the decoder gave no set".into()))?;
                    let image = service.render_now(&set, &camera, bg)?;
                    Ok(pb::RenderedImage {
                        time: t,
                        width: image.width,
                        height: image.height,
                        format: request.format,
                        data: encode_image(&image, format)?,
                        channels: 0,
                    })
                })
                .await;
            let end = result.is_err();
            if tx.send(result.map_err(status)).await.is_err() || end {
                return;
            }
        }
    });
    Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
}
