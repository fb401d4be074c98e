//! `Render` and `RenderTrajectory`: one view, or a camera path frame by frame (REST: `api/render.rs`).

use c4g_proto::v1 as pb;
use c4g_scene::Trajectory;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::error::{IntoStatus, status};
use c4g_service::ServiceError;
use c4g_service::views::features::FeatureRender;
use c4g_service::views::image_formats::encode_image;
use c4g_service::views::render::{PathRequest, ViewRequest};

use super::context::{BoxStream, Grpc};
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
    let features = FeatureRender::of_format(format);
    let (quality, served) = resolved_quality(
        grpc.service()?,
        &request.clip_id,
        request.quality,
        None,
        request.prune.as_ref(),
        &request.scene,
        features.is_some(),
    )
    .await?;
    let served = served.name().to_owned();
    if let Some(render) = features {
        let features = grpc
            .service()?
            .views
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
            scene: served,
        }));
    }
    let image = grpc
        .service()?
        .views
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
        scene: served,
    }))
}

pub(super) async fn render_trajectory(
    grpc: &Grpc,
    request: Request<pb::RenderTrajectoryRequest>,
) -> Result<Response<BoxStream<pb::RenderedImage>>, Status> {
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
    let image_format = request.format;
    let frames = service
        .views
        .render_path(&request.clip_id, &path, &quality, move |t, image| {
            Ok(pb::RenderedImage {
                time: t,
                width: image.width,
                height: image.height,
                format: image_format,
                data: encode_image(&image, format)?,
                channels: 0,
                scene: served.to_owned(),
            })
        })
        .await
        .map_err(status)?;
    let frames = ReceiverStream::new(frames).map(|frame| frame.map_err(status));
    Ok(Response::new(Box::pin(frames)))
}
