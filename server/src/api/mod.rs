//! The HTTP routes, one file per endpoint group, and the layers around them.

mod cameras;
mod clips;
mod docs;
mod export;
mod gaussians;
mod health;
mod jobs;
mod json;
pub(crate) mod models;
mod render;
mod scene;
mod segment;
mod stream;
mod tracks;
mod viewer;

use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::routing::{get, post};

use crate::AppState;

/// Every route of the service: REST, and gRPC on the same port.
pub fn router(state: AppState) -> Router {
    let body_limit = state.config().limits().max_body_bytes;
    // JSON bodies are small; uploads (the one route that takes media) get the upload limit.
    let rest = Router::new()
        .route("/v1/models", get(models::list))
        .route(
            "/v1/clips",
            post(clips::upload)
                .get(clips::list)
                .layer(DefaultBodyLimit::max(body_limit)),
        )
        .route("/v1/clips/{id}", get(clips::get).delete(clips::delete))
        .route("/v1/clips/{id}/frames/{index}", get(clips::frame))
        .route("/v1/clips/{id}/gaussians", post(gaussians::decode))
        .route("/v1/clips/{id}/render", post(render::render))
        .route("/v1/clips/{id}/stream", post(stream::stream))
        .route("/v1/clips/{id}/export", post(export::export))
        .route("/v1/clips/{id}/tracks", post(tracks::tracks))
        .route("/v1/clips/{id}/segment", post(segment::segment))
        .route("/v1/clips/{id}/cameras", get(cameras::files))
        .route("/v1/clips/{id}/cameras/recover", post(cameras::recover))
        .route("/v1/clips/{id}/refine", post(jobs::submit))
        .route("/v1/clips/{id}/fit", post(jobs::submit_fit))
        .route("/v1/jobs", get(jobs::list))
        // Cancelling is POST .../cancel; a job's record stays readable (there is no DELETE).
        .route("/v1/jobs/{id}", get(jobs::get))
        .route("/v1/jobs/{id}/cancel", post(jobs::cancel))
        .route("/v1/jobs/{id}/events", get(jobs::events))
        .route("/v1/jobs/{id}/result", get(jobs::result))
        .layer(DefaultBodyLimit::max(json::MAX_JSON_BYTES))
        .with_state(state.clone());
    // The API key guards /v1 and gRPC; health, readiness, metrics, docs and the viewer's files
    // stay open (the viewer's own /v1 calls send the key its user gives it).
    let guarded = rest
        .merge(crate::grpc::routes(state.clone()).into_axum_router())
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            crate::auth::require_key,
        ));
    Router::new()
        .route("/health", get(health::health))
        .route("/ready", get(health::ready))
        .route("/metrics", get(docs::metrics))
        .route("/openapi.json", get(docs::openapi))
        .route("/docs", get(docs::page))
        .route("/viewer", get(viewer::page))
        .route("/viewer/{clip}", get(viewer::clip_page))
        .route("/viewer/assets/{name}", get(viewer::asset))
        .with_state(state)
        .merge(guarded)
        .fallback(docs::not_found)
        .layer(axum::middleware::from_fn(crate::metrics::track))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use axum::body::Body;
    use axum::http::Request;
    use clap::Parser;
    use tower::ServiceExt;

    use super::*;
    use c4g_service::config::Config;

    /// Every path and method `/openapi.json` documents is a route (not the JSON 404 fallback).
    #[tokio::test]
    async fn every_documented_operation_is_routed() {
        let state = AppState::new(Config::parse_from(["c4g-server"]), None);
        let app = router(state);
        let spec: serde_json::Value = serde_json::from_str(docs::OPENAPI).unwrap();
        let paths = spec["paths"].as_object().unwrap();
        assert!(paths.len() >= 11);
        for (path, item) in paths {
            let methods = item.as_object().unwrap().keys();
            for method in methods.filter(|k| *k != "parameters") {
                let uri = path.replace("{id}", "abc").replace("{index}", "0");
                let request = Request::builder()
                    .method(method.to_uppercase().as_str())
                    .uri(&uri)
                    .body(Body::empty())
                    .unwrap();
                let response = app.clone().oneshot(request).await.unwrap();
                assert_ne!(
                    response.status(),
                    405,
                    "{method} {path} is documented but not routed"
                );
                let body = axum::body::to_bytes(response.into_body(), 1 << 20)
                    .await
                    .unwrap();
                let text = String::from_utf8_lossy(&body);
                assert!(
                    !text.contains("no such endpoint"),
                    "{method} {path} is documented but not routed"
                );
            }
        }
    }
}
