//! The gRPC service `c4g.v1.C4G`: the same operations as the REST API, over HTTP/2 on the same
//! port, plus `grpc.health.v1` and reflection.

use std::pin::Pin;
use std::sync::Arc;

use axum::http::HeaderMap;
use bytes::BytesMut;
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_server::{C4g, C4gServer};
use c4g_scene::Trajectory;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::camera::{CameraSpec, InputSpec, IntrinsicsSpec};
use crate::features::{Click, FeatureRender, SegmentRequest, Selection};
use crate::image_formats::{ImageFormat, encode_image};
use crate::intake::cameras::{CameraInput, ClipCameras};
use crate::intake::{IntakeOptions, Media, MediaKind};
use crate::keyframes::KeyframesSpec;
use crate::quality::{Preset, PruneSpec, QualitySpec};
use crate::recovery::RecoverOptions;
use crate::service::{PathRequest, Service, ViewRequest};
use crate::store::ClipRecord;
use crate::streaming::{STREAM_AHEAD, Spacing, StreamRequest, check_compact, plan_sets};
use crate::tracking::{TrackQuery, TrackRequest, Tracker};
use crate::wire::{self, Precision};
use crate::{AppState, ServiceError};
use c4g_formats::c4gv::EncodeOptions;

/// True when a request is a gRPC call.
pub fn is_grpc(headers: &HeaderMap) -> bool {
    headers
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"))
}

/// The tonic routes: `c4g.v1.C4G`, health and reflection.
pub fn routes(state: AppState) -> tonic::service::Routes {
    let limit = state.config().limits().max_grpc_message_bytes;
    let state_for_health = state.clone();
    let state_for_workers = state.clone();
    let service = C4gServer::new(Grpc { state })
        .max_decoding_message_size(limit)
        .max_encoding_message_size(usize::MAX);
    let (reporter, health) = tonic_health::server::health_reporter();
    // `c4g.v1.C4G` reports SERVING once the model has loaded, like `/ready`.
    tokio::spawn(async move {
        reporter.set_not_serving::<C4gServer<Grpc>>().await;
        while state_for_health.service().is_err() {
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
        reporter.set_serving::<C4gServer<Grpc>>().await;
    });
    let mut routes = tonic::service::Routes::new(service)
        .add_service(crate::workers::service(state_for_workers))
        .add_service(health);
    match tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(c4g_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
    {
        Ok(reflection) => routes = routes.add_service(reflection),
        Err(e) => tracing::warn!("gRPC reflection unavailable: {e}"),
    }
    routes
}

struct Grpc {
    state: AppState,
}

impl Grpc {
    fn service(&self) -> Result<&Arc<Service>, Status> {
        Ok(self.state.service()?)
    }
}

fn clip_proto(record: &ClipRecord, created: bool) -> pb::Clip {
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
    }
}

fn clip_cameras(c: &ClipCameras) -> pb::ClipCameras {
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

fn camera_spec(camera: Option<pb::Camera>) -> CameraSpec {
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

fn background(values: &[f32]) -> Result<[f32; 3], ServiceError> {
    match values {
        [] => Ok([0.0; 3]),
        [r, g, b] => Ok([*r, *g, *b]),
        other => Err(ServiceError::invalid(format!(
            "background needs 3 values (RGB), got {}",
            other.len()
        ))),
    }
}

fn image_format(format: i32) -> Result<ImageFormat, ServiceError> {
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
fn keyframes_spec(
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
fn track_query(q: &pb::TrackQuery) -> TrackQuery {
    TrackQuery {
        t: q.time,
        x: q.x,
        y: q.y,
    }
}

fn quality_spec(
    quality: i32,
    keyframes: Option<&pb::Keyframes>,
    prune: Option<&pb::Prune>,
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
    })
}

fn nonzero(v: u32) -> Option<u32> {
    (v != 0).then_some(v)
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

#[tonic::async_trait]
impl C4g for Grpc {
    async fn upload(
        &self,
        request: Request<Streaming<pb::UploadRequest>>,
    ) -> Result<Response<pb::Clip>, Status> {
        let service = self.service()?.clone();
        let mut stream = request.into_inner();
        let header = match stream.message().await? {
            Some(pb::UploadRequest {
                part: Some(pb::upload_request::Part::Header(header)),
            }) => header,
            _ => {
                return Err(ServiceError::invalid(
                    "the first message of an upload must be its header",
                )
                .into());
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
                        .into());
                    }
                    data.extend_from_slice(&chunk);
                }
                _ => {
                    return Err(ServiceError::invalid(
                        "after the header an upload sends only chunks",
                    )
                    .into());
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
            cameras: header.cameras.map(given_cameras).transpose()?,
        };
        let media = Media::File {
            data: data.freeze(),
            kind,
        };
        let (record, created) = service.upload(media, options).await?;
        Ok(Response::new(clip_proto(&record, created)))
    }

    async fn get_clip(&self, request: Request<pb::ClipRef>) -> Result<Response<pb::Clip>, Status> {
        let record = self
            .service()?
            .store
            .get_or_fetch(&request.into_inner().clip_id)
            .await?;
        Ok(Response::new(clip_proto(&record, false)))
    }

    async fn list_clips(
        &self,
        _: Request<pb::ListClipsRequest>,
    ) -> Result<Response<pb::ListClipsResponse>, Status> {
        let clips = self.service()?.store.list_all().await?;
        Ok(Response::new(pb::ListClipsResponse {
            clips: clips.iter().map(|r| clip_proto(r, false)).collect(),
        }))
    }

    async fn delete_clip(
        &self,
        request: Request<pb::ClipRef>,
    ) -> Result<Response<pb::DeleteClipResponse>, Status> {
        self.service()?
            .delete(&request.into_inner().clip_id)
            .await?;
        Ok(Response::new(pb::DeleteClipResponse {}))
    }

    async fn decode(
        &self,
        request: Request<pb::DecodeRequest>,
    ) -> Result<Response<pb::DecodeResponse>, Status> {
        let request = request.into_inner();
        let precision: Precision = wire::precision_from_proto(request.precision());
        let quality = quality_spec(
            request.quality,
            request.keyframes.as_ref(),
            request.prune.as_ref(),
        )?;
        let service = self.service()?;
        let frames = if request.features {
            service
                .decode_features(&request.clip_id, request.times, quality)
                .await?
        } else {
            service
                .decode(&request.clip_id, request.times, quality)
                .await?
        };
        Ok(Response::new(pb::DecodeResponse {
            frames: frames
                .iter()
                .map(|(t, set)| pb::GaussianFrame {
                    time: *t,
                    gaussians: Some(wire::proto(set, precision)),
                    c4gv: Vec::new(),
                })
                .collect(),
        }))
    }

    type StreamGaussiansStream = BoxStream<pb::GaussianFrame>;

    async fn stream_gaussians(
        &self,
        request: Request<pb::StreamGaussiansRequest>,
    ) -> Result<Response<Self::StreamGaussiansStream>, Status> {
        let request = request.into_inner();
        let service = self.service()?.clone();
        let spacing = match request.spacing {
            Some(pb::stream_gaussians_request::Spacing::Step(step)) => Spacing::Step(step),
            Some(pb::stream_gaussians_request::Spacing::Fps(fps)) => Spacing::Fps(fps),
            None => Spacing::Source,
        };
        let stream = StreamRequest {
            start: request.start,
            end: request.end,
            spacing,
            quality: quality_spec(
                request.quality,
                request.keyframes.as_ref(),
                request.prune.as_ref(),
            )?,
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
                check_compact(&options)?;
                Some(options)
            }
            None => None,
        };
        let sets = service.stream(&request.clip_id, &stream).await?;
        let frames: BoxStream<pb::GaussianFrame> = match compact {
            Some(options) => Box::pin(sets.compact(options).map(|piece| match piece {
                Ok((time, bytes)) => Ok(pb::GaussianFrame {
                    time,
                    gaussians: None,
                    c4gv: bytes,
                }),
                Err(e) => Err(e.into()),
            })),
            None => Box::pin(
                ReceiverStream::new(sets.sets).map(move |frame| match frame {
                    Ok((time, set)) => Ok(pb::GaussianFrame {
                        time,
                        gaussians: Some(wire::proto(&set, precision)),
                        c4gv: Vec::new(),
                    }),
                    Err(e) => Err(e.into()),
                }),
            ),
        };
        Ok(Response::new(frames))
    }

    async fn render(
        &self,
        request: Request<pb::RenderRequest>,
    ) -> Result<Response<pb::RenderedImage>, Status> {
        let request = request.into_inner();
        let format = image_format(request.format)?;
        let view = ViewRequest {
            t: request.time,
            camera: camera_spec(request.camera),
            width: nonzero(request.width),
            height: nonzero(request.height),
            background: background(&request.background)?,
        };
        let quality = quality_spec(request.quality, None, request.prune.as_ref())?;
        if let Some(render) = FeatureRender::of_format(format) {
            let features = self
                .service()?
                .render_features(&request.clip_id, view, quality, render)
                .await?;
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
        let image = self
            .service()?
            .render_view(&request.clip_id, view, quality)
            .await?;
        Ok(Response::new(pb::RenderedImage {
            time: request.time,
            width: image.width,
            height: image.height,
            format: request.format,
            data: encode_image(&image, format)?,
            channels: 0,
        }))
    }

    type RenderTrajectoryStream = BoxStream<pb::RenderedImage>;

    async fn render_trajectory(
        &self,
        request: Request<pb::RenderTrajectoryRequest>,
    ) -> Result<Response<Self::RenderTrajectoryStream>, Status> {
        let request = request.into_inner();
        let service = self.service()?.clone();
        let format = image_format(request.format)?;
        if FeatureRender::of_format(format).is_some() {
            return Err(ServiceError::invalid(
                "feature images (IMAGE_FORMAT_FEATURES_F32, IMAGE_FORMAT_FEATURES_PCA_PNG) are \
                 single views: use Render",
            )
            .into());
        }
        let preset = match request.preset_json.trim() {
            "" => None,
            json => {
                let not_one =
                    |e| ServiceError::invalid(format!("preset_json is not a trajectory: {e}"));
                let value: serde_json::Value = serde_json::from_str(json).map_err(not_one)?;
                crate::camera::check_preset(&value)?;
                Some(serde_json::from_value::<Trajectory>(value).map_err(not_one)?)
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
            background: background(&request.background)?,
        };
        let record = service.store.get_or_fetch(&request.clip_id).await?;
        let frames = service.plan_path(&record, &path)?;
        let times: Vec<f64> = frames.iter().map(|(t, _)| *t).collect();
        let quality = quality_spec(
            request.quality,
            request.keyframes.as_ref(),
            request.prune.as_ref(),
        )?;
        let approximation = service.approximation(&record, &quality, &times)?;
        let encoding = service.store.encoding(&record.id).await?;
        let (tx, rx) = mpsc::channel(STREAM_AHEAD);
        let bg = path.background;
        tokio::spawn(async move {
            let plan = match plan_sets(&service, &record.id, &encoding, &times, approximation).await
            {
                Ok(plan) => plan,
                Err(e) => {
                    let _ = tx.send(Err(e.into())).await;
                    return;
                }
            };
            for (t, camera) in frames {
                let encoding = encoding.clone();
                let plan = plan.clone();
                let result =
                    service
                        .work(move |service| {
                            let (_, set) =
                                service.sets_now(&plan, &encoding, &[t])?.pop().ok_or_else(
                                    || ServiceError::Internal("the decoder gave no set".into()),
                                )?;
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
                if tx.send(result.map_err(Status::from)).await.is_err() || end {
                    return;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn tracks(
        &self,
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
                .into());
            }
        };
        let track_request = TrackRequest {
            tracker,
            queries: request.queries.iter().map(track_query).collect(),
            times: (!request.times.is_empty()).then_some(request.times),
            width: request.width,
            height: request.height,
            quality: quality_spec(
                request.quality,
                request.keyframes.as_ref(),
                request.prune.as_ref(),
            )?,
        };
        let tracks = self
            .service()?
            .tracks(&request.clip_id, track_request)
            .await?;
        Ok(Response::new(pb::TracksResponse {
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

    async fn segment(
        &self,
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
                .into());
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
        let segment = self
            .service()?
            .segment(&request.clip_id, segment_request)
            .await?;
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

    async fn recover_cameras(
        &self,
        request: Request<pb::RecoverCamerasRequest>,
    ) -> Result<Response<pb::RecoveredCameras>, Status> {
        let request = request.into_inner();
        let options = RecoverOptions {
            refine_focal: request.refine_focal,
        };
        let recovered = self
            .service()?
            .recover_cameras(&request.clip_id, options)
            .await?;
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

    async fn list_models(
        &self,
        _: Request<pb::ListModelsRequest>,
    ) -> Result<Response<pb::ListModelsResponse>, Status> {
        let service = self.service()?;
        let m = service.engine.manifest();
        Ok(Response::new(pb::ListModelsResponse {
            models: vec![pb::Model {
                name: m.name.clone(),
                version: m.version.clone(),
                input_width: m.input.width,
                input_height: m.input.height,
                gaussians_per_set: m.gaussian_count as u32,
                manifest_json: crate::api::models::describe(service).to_string(),
            }],
        }))
    }
}

/// An upload's cameras as the intake reads them.
fn given_cameras(cameras: pb::GivenCameras) -> Result<CameraInput, ServiceError> {
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
