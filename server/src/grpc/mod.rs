//! The gRPC service `c4g.v1.C4G`: the same operations as the REST API, over HTTP/2 on the same
//! port, plus `grpc.health.v1` and reflection (v1 and v1alpha).

use axum::http::HeaderMap;
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_server::{C4g, C4gServer};
use tonic::{Request, Response, Status, Streaming};

use crate::AppState;
use context::{BoxStream, Grpc};

mod cameras;
mod clips;
mod context;
mod convert;
mod gaussians;
mod models;
mod render;
mod segment;
mod stream;
mod tracks;

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
    // Reflection in both versions: v1, and v1alpha, which pip's grpcio-reflection and older
    // grpcurl, Evans and Postman builds speak.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(c4g_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    match reflection().build_v1() {
        Ok(v1) => routes = routes.add_service(v1),
        Err(e) => tracing::warn!("gRPC reflection v1 unavailable: {e}"),
    }
    match reflection().build_v1alpha() {
        Ok(v1alpha) => routes = routes.add_service(v1alpha),
        Err(e) => tracing::warn!("gRPC reflection v1alpha unavailable: {e}"),
    }
    routes
}

#[tonic::async_trait]
impl C4g for Grpc {
    type StreamGaussiansStream = BoxStream<pb::GaussianFrame>;
    type RenderTrajectoryStream = BoxStream<pb::RenderedImage>;

    async fn upload(
        &self,
        request: Request<Streaming<pb::UploadRequest>>,
    ) -> Result<Response<pb::Clip>, Status> {
        clips::upload(self, request).await
    }

    async fn get_clip(&self, request: Request<pb::ClipRef>) -> Result<Response<pb::Clip>, Status> {
        clips::get_clip(self, request).await
    }

    async fn list_clips(
        &self,
        request: Request<pb::ListClipsRequest>,
    ) -> Result<Response<pb::ListClipsResponse>, Status> {
        clips::list_clips(self, request).await
    }

    async fn delete_clip(
        &self,
        request: Request<pb::ClipRef>,
    ) -> Result<Response<pb::DeleteClipResponse>, Status> {
        clips::delete_clip(self, request).await
    }

    async fn decode(
        &self,
        request: Request<pb::DecodeRequest>,
    ) -> Result<Response<pb::DecodeResponse>, Status> {
        gaussians::decode(self, request).await
    }

    async fn stream_gaussians(
        &self,
        request: Request<pb::StreamGaussiansRequest>,
    ) -> Result<Response<Self::StreamGaussiansStream>, Status> {
        stream::stream_gaussians(self, request).await
    }

    async fn render(
        &self,
        request: Request<pb::RenderRequest>,
    ) -> Result<Response<pb::RenderedImage>, Status> {
        render::render(self, request).await
    }

    async fn render_trajectory(
        &self,
        request: Request<pb::RenderTrajectoryRequest>,
    ) -> Result<Response<Self::RenderTrajectoryStream>, Status> {
        render::render_trajectory(self, request).await
    }

    async fn tracks(
        &self,
        request: Request<pb::TracksRequest>,
    ) -> Result<Response<pb::TracksResponse>, Status> {
        tracks::tracks(self, request).await
    }

    async fn segment(
        &self,
        request: Request<pb::SegmentRequest>,
    ) -> Result<Response<pb::SegmentResponse>, Status> {
        segment::segment(self, request).await
    }

    async fn recover_cameras(
        &self,
        request: Request<pb::RecoverCamerasRequest>,
    ) -> Result<Response<pb::RecoveredCameras>, Status> {
        cameras::recover_cameras(self, request).await
    }

    async fn list_models(
        &self,
        request: Request<pb::ListModelsRequest>,
    ) -> Result<Response<pb::ListModelsResponse>, Status> {
        models::list_models(self, request).await
    }
}
