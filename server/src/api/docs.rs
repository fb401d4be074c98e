//! `/openapi.json` (the REST contract), `/docs` (a page that renders it), `/metrics`, and the
//! JSON 404 for unknown paths.

use crate::{AppState, ServiceError};
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};

/// The OpenAPI 3.1 description of the REST API (kept beside the code; a test checks that it
/// names every route).
pub const OPENAPI: &str = include_str!("../../openapi.json");

pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI).into_response()
}

pub async fn page() -> Html<&'static str> {
    Html(include_str!("docs.html"))
}

pub async fn metrics(State(state): State<AppState>) -> Response {
    match state.metrics() {
        Some(handle) => (
            [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
            handle.render(),
        )
            .into_response(),
        None => (
            StatusCode::NOT_FOUND,
            "metrics are not recorded in this process",
        )
            .into_response(),
    }
}

pub async fn not_found() -> ServiceError {
    ServiceError::NotFound("no such endpoint: see /docs (or /openapi.json) for the API".into())
}
