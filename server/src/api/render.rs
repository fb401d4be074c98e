//! `POST /v1/clips/{id}/render`: one camera at one time (PNG, raw depth or alpha, or a feature
//! image: raw lifted features or their PCA colouring, `c4g_service::views::features`), or a camera trajectory
//! over a time range (MP4).

use axum::extract::State;
use axum::http::{HeaderName, HeaderValue, header};
use axum::response::{IntoResponse, Response};
use c4g_scene::Trajectory;
use serde::Deserialize;
use serde_json::Value;

use super::json::{self, ClipId, JsonBody};
use super::scene;
use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::sets::scene::Scene;
use c4g_service::views::camera::CameraSpec;
use c4g_service::views::features::FeatureRender;
use c4g_service::views::image_formats::{ImageFormat, encode_image, encode_mp4, to_rgb8};
use c4g_service::views::render::{DEFAULT_PATH_FRAMES, PathRequest, ViewRequest};

/// Frame rate of trajectory videos when a request does not say.
const DEFAULT_VIDEO_FPS: f64 = 12.0;

/// The frame rates a trajectory video may have.
const VIDEO_FPS: std::ops::RangeInclusive<f64> = 0.01..=240.0;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RenderRequest {
    t: Option<f64>,
    #[serde(default)]
    camera: CameraSpec,
    width: Option<u32>,
    height: Option<u32>,
    #[serde(default)]
    background: [f32; 3],
    format: Option<ImageFormat>,
    trajectory: Option<Trajectory>,
    cameras: Option<Vec<CameraSpec>>,
    frames: Option<usize>,
    start: Option<f64>,
    end: Option<f64>,
    fps: Option<f64>,
    /// A named speed/accuracy trade: exact (the default), balanced, fast.
    quality: Option<Preset>,
    /// A trajectory's sets from keyframes, interpolated between them (default: the preset's).
    keyframes: Option<KeyframesSpec>,
    /// Drop the Gaussians that change nothing visible (default: the preset's).
    prune: Option<PruneSpec>,
    /// Which scene: auto (the default), feed-forward or fitted.
    #[serde(default)]
    scene: Scene,
}

pub async fn render(
    State(state): State<AppState>,
    ClipId(id): ClipId,
    JsonBody(body): JsonBody<Value>,
) -> Result<Response, ErrorReply> {
    let service = state.service()?.clone();
    json::check_body(&body, service.limits.max_times)?;
    let request: RenderRequest = json::typed(body)?;
    let mut quality = QualitySpec {
        preset: request.quality,
        keyframes: request.keyframes,
        prune: request.prune,
        scene: request.scene,
    };
    // An input camera swept over the frames is a path of its own (the same path at new times).
    let is_path =
        request.trajectory.is_some() || request.cameras.is_some() || request.camera.sweeps();
    if !is_path {
        if request.frames.is_some()
            || request.fps.is_some()
            || request.start.is_some()
            || request.end.is_some()
            || request.keyframes.is_some()
        {
            return Err(ServiceError::invalid(
                "frames, fps, start, end and keyframes describe a trajectory: add \"trajectory\", \"cameras\" or an input camera swept over the frames (\"camera\": {\"input\": {\"start\": …, \"end\": …}})",
            ).into());
        }
        let format = request.format.unwrap_or(ImageFormat::Png);
        let record = service.store.get_or_fetch(&id).await?;
        let view = ViewRequest {
            t: request.t.unwrap_or(record.span().0),
            camera: request.camera,
            width: request.width,
            height: request.height,
            background: request.background,
        };
        let t = view.t;
        let features = FeatureRender::of_format(format);
        let served = service
            .sets
            .resolve_scene(&id, &mut quality, features.is_some())
            .await?;
        if let Some(render) = features {
            let features = service
                .views
                .render_features(&id, view, quality, render)
                .await?;
            let mut response = with_headers(
                format,
                features.bytes,
                features.width,
                features.height,
                Some(t),
            );
            response.headers_mut().insert(
                HeaderName::from_static("x-c4g-channels"),
                HeaderValue::from(features.channels),
            );
            return Ok(scene::label(response, served));
        }
        let image = service.views.render_view(&id, view, quality).await?;
        let bytes = encode_image(&image, format)?;
        let response = with_headers(format, bytes, image.width, image.height, Some(t));
        return Ok(scene::label(response, served));
    }
    let format = request.format.unwrap_or(ImageFormat::Mp4);
    if format != ImageFormat::Mp4 {
        return Err(ServiceError::invalid(
            "a trajectory renders as mp4 over REST (gRPC RenderTrajectory streams PNG frames)",
        )
        .into());
    }
    if request.t.is_some() {
        return Err(ServiceError::invalid(
            "a trajectory spans \"start\" to \"end\"; \"t\" is for a single view",
        )
        .into());
    }
    let fps = request.fps.unwrap_or(DEFAULT_VIDEO_FPS);
    if !VIDEO_FPS.contains(&fps) {
        return Err(ServiceError::invalid(format!(
            "fps must be between {} and {}, got {fps}",
            VIDEO_FPS.start(),
            VIDEO_FPS.end()
        ))
        .into());
    }
    // The default frame count, within C4G_MAX_TIMES (explicit cameras are their own count).
    let frames = request.frames.or_else(|| {
        (request.trajectory.is_some() || request.camera.sweeps())
            .then(|| DEFAULT_PATH_FRAMES.min(service.limits.max_times))
    });
    let path = PathRequest {
        preset: request.trajectory,
        cameras: request.cameras.unwrap_or_default(),
        camera: request.camera,
        frames,
        start: request.start,
        end: request.end,
        width: request.width,
        height: request.height,
        background: request.background,
    };
    let served = service.sets.resolve_scene(&id, &mut quality, false).await?;
    let images = service
        .views
        .render_path_all(&id, &path, &quality, |_, image| {
            Ok((image.width, image.height, to_rgb8(&image)))
        })
        .await?;
    let (w, h) = images.first().map_or((0, 0), |&(w, h, _)| (w, h));
    let frames: Vec<Vec<u8>> = images.into_iter().map(|(_, _, rgb)| rgb).collect();
    let video = encode_mp4(
        &service.tools.ffmpeg,
        &service.tools.scratch,
        &frames,
        w,
        h,
        fps,
    )
    .await?;
    Ok(scene::label(
        with_headers(format, video, w, h, None),
        served,
    ))
}

fn with_headers(
    format: ImageFormat,
    bytes: Vec<u8>,
    width: u32,
    height: u32,
    t: Option<f64>,
) -> Response {
    let mut response = ([(header::CONTENT_TYPE, format.content_type())], bytes).into_response();
    let headers = response.headers_mut();
    headers.insert(
        HeaderName::from_static("x-c4g-width"),
        HeaderValue::from(width),
    );
    headers.insert(
        HeaderName::from_static("x-c4g-height"),
        HeaderValue::from(height),
    );
    if let Some(t) = t
        && let Ok(value) = HeaderValue::from_str(&t.to_string())
    {
        headers.insert(HeaderName::from_static("x-c4g-time"), value);
    }
    response
}
