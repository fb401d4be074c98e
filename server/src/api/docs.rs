//! `/openapi.json` (the REST contract), `/docs` (a page that renders it), `/metrics`, and the
//! JSON 404 for unknown paths.
//!
//! The contract is exact for the server that serves it: every bound that a setting moves (the
//! largest image side, the most times per request, ...) is marked in `openapi.json` with
//! `"x-c4g-limit": "<setting>"`, and `/openapi.json` answers with the value this server was
//! started with (the file holds the defaults).

use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse, Response};
use serde_json::Value;

use crate::AppState;
use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::config::Limits;

/// The OpenAPI 3.1 description of the REST API with the default limits (kept beside the code;
/// tests check that it names every route and that the server holds to it).
pub const OPENAPI: &str = include_str!("../../openapi.json");

pub async fn openapi(State(state): State<AppState>) -> Response {
    let body = contract(&state.config().limits()).to_string();
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

/// The contract with `limits` in place of the defaults.
pub fn contract(limits: &Limits) -> Value {
    let mut spec: Value = serde_json::from_str(OPENAPI).unwrap_or(Value::Null);
    fill_limits(&mut spec, limits);
    spec
}

/// The value of each setting a bound in the contract may name.
fn limit(name: &str, limits: &Limits) -> Option<Value> {
    Some(match name {
        "C4G_MAX_SIDE" => limits.max_side.into(),
        "C4G_MAX_TIMES" => limits.max_times.into(),
        "C4G_MAX_TRACK_QUERIES" => limits.max_track_queries.into(),
        "C4G_MAX_DURATION_S" => limits.max_duration_s.into(),
        "C4G_MAX_CONTEXT_FRAMES" => limits.max_context_frames.into(),
        "C4G_MAX_SOURCE_FRAMES" => limits.max_source_frames.into(),
        _ => return None,
    })
}

/// Sets every bound marked `x-c4g-limit` (an array's `maxItems`, else a number's `maximum`).
fn fill_limits(value: &mut Value, limits: &Limits) {
    match value {
        Value::Object(fields) => {
            if let Some(bound) = fields
                .get("x-c4g-limit")
                .and_then(Value::as_str)
                .and_then(|name| limit(name, limits))
            {
                let key = if fields.contains_key("maxItems") {
                    "maxItems"
                } else {
                    "maximum"
                };
                fields.insert(key.to_owned(), bound);
            }
            fields.values_mut().for_each(|v| fill_limits(v, limits));
        }
        Value::Array(items) => items.iter_mut().for_each(|v| fill_limits(v, limits)),
        _ => {}
    }
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
        None => ErrorReply(ServiceError::NotFound(
            "metrics are not recorded in this process".into(),
        ))
        .into_response(),
    }
}

pub async fn not_found() -> ErrorReply {
    ServiceError::NotFound("no such endpoint: see /docs (or /openapi.json) for the API".into())
        .into()
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;
    use c4g_service::config::Config;

    fn marked(value: &Value, out: &mut Vec<(String, Value)>) {
        match value {
            Value::Object(fields) => {
                if let Some(name) = fields.get("x-c4g-limit").and_then(Value::as_str) {
                    let bound = fields
                        .get("maxItems")
                        .or_else(|| fields.get("maximum"))
                        .cloned()
                        .unwrap_or(Value::Null);
                    out.push((name.to_owned(), bound));
                }
                fields.values().for_each(|v| marked(v, out));
            }
            Value::Array(items) => items.iter().for_each(|v| marked(v, out)),
            _ => {}
        }
    }

    #[test]
    fn the_file_holds_the_default_limits_and_the_served_contract_the_configured_ones() {
        let defaults = Limits::default();
        let mut found = Vec::new();
        marked(&serde_json::from_str(OPENAPI).unwrap(), &mut found);
        assert!(found.len() >= 10, "{found:?}");
        for (name, bound) in &found {
            let want = limit(name, &defaults).unwrap_or_else(|| panic!("unknown limit {name}"));
            assert_eq!(bound.as_f64(), want.as_f64(), "{name}");
        }
        let small = Config::parse_from([
            "c4g-server",
            "--max-side",
            "128",
            "--max-times",
            "8",
            "--max-duration-s",
            "10",
        ])
        .limits();
        let mut served = Vec::new();
        marked(&contract(&small), &mut served);
        assert_eq!(served.len(), found.len());
        for (name, bound) in &served {
            assert_eq!(
                bound.as_f64(),
                limit(name, &small).unwrap().as_f64(),
                "{name}"
            );
        }
        assert!(served.iter().any(|(n, b)| n == "C4G_MAX_SIDE" && b == 128));
    }
}
