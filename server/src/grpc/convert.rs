//! The proto messages' shapes as the core states them, and back: what every gRPC endpoint group
//! shares.

use c4g_proto::v1 as pb;
use tonic::Status;

use crate::error::status;

use c4g_service::ServiceError;
use c4g_service::clips::intake::cameras::{CameraInput, ClipCameras};
use c4g_service::clips::record::ClipRecord;
use c4g_service::service::Service;
use c4g_service::sets::keyframes::KeyframesSpec;
use c4g_service::sets::quality::{Preset, PruneSpec, QualitySpec};
use c4g_service::sets::scene::Scene;
use c4g_service::views::camera::{CameraSpec, InputSpec, IntrinsicsSpec};
use c4g_service::views::image_formats::ImageFormat;
use c4g_service::views::tracking::TrackQuery;

pub(super) fn clip_proto(record: &ClipRecord, created: bool) -> pb::Clip {
    pb::Clip {
        clip_id: record.id.clone(),
        model: record.model.clone(),
        context_times: record.context_times.clone(),
        source_frames: record.source.frames as u32,
        source_width: record.source.width,
        source_height: record.source.height,
        duration: record.source.duration,
        state: pb::ClipState::Ready as i32,
        feature_bytes: record.feature_bytes(),
        source_kind: record.source.kind.clone(),
        source_fps: record.source.fps,
        created,
        source_warnings: record.source.warnings.clone(),
        cameras: record.cameras.as_ref().map(clip_cameras),
        fitted_json: String::new(),
    }
}

pub(super) fn clip_cameras(c: &ClipCameras) -> pb::ClipCameras {
    pb::ClipCameras {
        format: c.format.clone(),
        scale: c.scale,
        frames: c
            .frames
            .iter()
            .map(|f| pb::ContextCamera {
                time: f.t,
                world_to_camera: f.world_to_camera.clone(),
                fx: f.intrinsics.fx,
                fy: f.intrinsics.fy,
                cx: f.intrinsics.cx,
                cy: f.intrinsics.cy,
            })
            .collect(),
        notes: c.notes.clone(),
    }
}

pub(super) fn camera_spec(camera: Option<pb::Camera>) -> CameraSpec {
    let Some(camera) = camera else {
        return CameraSpec::default();
    };
    CameraSpec {
        world_to_camera: (!camera.world_to_camera.is_empty()).then_some(camera.world_to_camera),
        intrinsics: camera.intrinsics.map(|i| IntrinsicsSpec {
            fx: i.fx,
            fy: i.fy,
            cx: i.cx,
            cy: i.cy,
        }),
        input: camera.input.map(|i| InputSpec {
            at: i.at,
            start: i.start,
            end: i.end,
        }),
    }
}

pub(super) fn background(values: &[f32]) -> Result<[f32; 3], ServiceError> {
    match values {
        [] => Ok([0.0; 3]),
        [r, g, b] => Ok([*r, *g, *b]),
        other => Err(ServiceError::invalid(format!(
            "background needs 3 values (RGB), got {}",
            other.len()
        ))),
    }
}

pub(super) fn image_format(format: i32) -> Result<ImageFormat, ServiceError> {
    match pb::ImageFormat::try_from(format) {
        Ok(pb::ImageFormat::Unspecified | pb::ImageFormat::Png) => Ok(ImageFormat::Png),
        Ok(pb::ImageFormat::DepthF32) => Ok(ImageFormat::Depth),
        Ok(pb::ImageFormat::AlphaF32) => Ok(ImageFormat::Alpha),
        Ok(pb::ImageFormat::FeaturesF32) => Ok(ImageFormat::Features),
        Ok(pb::ImageFormat::FeaturesPcaPng) => Ok(ImageFormat::FeaturesPca),
        Err(_) => Err(ServiceError::invalid(format!(
            "unknown image format {format}"
        ))),
    }
}

/// The REST shape of a `Keyframes` message; the service checks it.
pub(super) fn keyframes_spec(
    keyframes: Option<&pb::Keyframes>,
) -> Result<Option<KeyframesSpec>, ServiceError> {
    use pb::keyframes::Mode;
    let Some(keyframes) = keyframes else {
        return Ok(None);
    };
    let spec = match &keyframes.mode {
        None => {
            return Err(ServiceError::invalid(
                "Keyframes needs its mode: every_s, count or adaptive (leave keyframes unset to \
                 decode every time exactly)",
            ));
        }
        Some(Mode::EveryS(seconds)) => KeyframesSpec {
            every_s: Some(*seconds),
            ..KeyframesSpec::default()
        },
        Some(Mode::Count(n)) => KeyframesSpec {
            count: Some(*n as usize),
            ..KeyframesSpec::default()
        },
        Some(Mode::Adaptive(adaptive)) => KeyframesSpec {
            tolerance: Some(adaptive.tolerance),
            color_tolerance: adaptive.color_tolerance,
            max: nonzero(adaptive.max).map(|n| n as usize),
            min_interval_s: Some(adaptive.min_interval_s),
            ..KeyframesSpec::default()
        },
    };
    Ok(Some(spec))
}

/// What a request's `quality`, `keyframes` and `prune` ask for; the service checks it.
pub(super) fn track_query(q: &pb::TrackQuery) -> TrackQuery {
    TrackQuery {
        t: q.time,
        x: q.x,
        y: q.y,
    }
}

/// A request's quality options, with its `scene` resolved for `clip_id` once, before any work
/// (`SetSource::resolve_scene`, as REST does: `api/scene.rs`): the spec to serve with and the
/// scene that serves it. `features`: the request reads lifted features (only the feed-forward
/// scene has them).
pub(super) async fn resolved_quality(
    service: &Service,
    clip_id: &str,
    quality: i32,
    keyframes: Option<&pb::Keyframes>,
    prune: Option<&pb::Prune>,
    scene: &str,
    features: bool,
) -> Result<(QualitySpec, Scene), Status> {
    let mut spec = quality_spec(quality, keyframes, prune, scene).map_err(status)?;
    let served = service
        .sets
        .resolve_scene(clip_id, &mut spec, features)
        .await
        .map_err(status)?;
    Ok((spec, served))
}

fn quality_spec(
    quality: i32,
    keyframes: Option<&pb::Keyframes>,
    prune: Option<&pb::Prune>,
    scene: &str,
) -> Result<QualitySpec, ServiceError> {
    let preset = match pb::Quality::try_from(quality) {
        Ok(pb::Quality::Unspecified) => None,
        Ok(pb::Quality::Exact) => Some(Preset::Exact),
        Ok(pb::Quality::Balanced) => Some(Preset::Balanced),
        Ok(pb::Quality::Fast) => Some(Preset::Fast),
        Err(_) => {
            return Err(ServiceError::invalid(format!(
                "unknown quality {quality}: QUALITY_EXACT, QUALITY_BALANCED or QUALITY_FAST"
            )));
        }
    };
    Ok(QualitySpec {
        preset,
        keyframes: keyframes_spec(keyframes)?,
        prune: prune.map(|p| PruneSpec {
            contribution_px: p.contribution_px,
            opacity: p.opacity,
            drop_queries: p.drop_queries,
        }),
        scene: Scene::parse(scene).map_err(ServiceError::invalid)?,
    })
}

pub(super) fn nonzero(v: u32) -> Option<u32> {
    (v != 0).then_some(v)
}

/// An upload's cameras as the intake reads them.
pub(super) fn given_cameras(cameras: pb::GivenCameras) -> Result<CameraInput, ServiceError> {
    use pb::given_cameras::Form;
    let names = (!cameras.names.is_empty()).then_some(cameras.names);
    match cameras.form {
        Some(Form::Json(_)) if names.is_some() => Err(ServiceError::invalid(
            "names match COLMAP images or transforms.json frames to frames; the JSON list is \
             already in frame order",
        )),
        Some(Form::Json(json)) => Ok(CameraInput::Json(json)),
        Some(Form::Colmap(colmap)) => Ok(CameraInput::Colmap {
            cameras: colmap.cameras_txt,
            images: colmap.images_txt,
            names,
        }),
        Some(Form::Transforms(json)) => Ok(CameraInput::Transforms { json, names }),
        None => Err(ServiceError::invalid(
            "cameras needs a form: json, colmap or transforms",
        )),
    }
}
