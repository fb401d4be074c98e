//! Prometheus metrics (names in the README): a recorder installed once per process, and a
//! middleware that counts and times every request by route.

use std::time::Instant;

use axum::extract::{MatchedPath, Request};
use axum::middleware::Next;
use axum::response::Response;
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};

/// Histogram buckets, seconds: from a cached decode (~1 ms) to a long encode.
const BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
    60.0, 120.0,
];

/// gRPC methods, so that the `route` label has a bounded set of values.
const GRPC_METHODS: &[&str] = &[
    "Upload",
    "GetClip",
    "ListClips",
    "DeleteClip",
    "Decode",
    "StreamGaussians",
    "Render",
    "RenderTrajectory",
    "ListModels",
];

/// Installs the process-wide recorder; `None` when another is installed already.
pub fn install() -> Option<PrometheusHandle> {
    PrometheusBuilder::new()
        .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), BUCKETS)
        .ok()?
        .install_recorder()
        .ok()
}

/// Counts (`c4g_requests_total`) and times (`c4g_request_duration_seconds`, to the response's
/// head: for a stream, the time to its first message) every request.
pub async fn track(request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().to_string();
    let route = route_label(&request);
    let response = next.run(request).await;
    let status = response
        .headers()
        .get("grpc-status")
        .and_then(|v| v.to_str().ok())
        .map_or_else(
            || response.status().as_u16().to_string(),
            |s| format!("grpc-{s}"),
        );
    let labels = [("method", method), ("route", route)];
    metrics::histogram!("c4g_request_duration_seconds", &labels)
        .record(started.elapsed().as_secs_f64());
    let labels = [
        ("method", labels[0].1.clone()),
        ("route", labels[1].1.clone()),
        ("status", status),
    ];
    metrics::counter!("c4g_requests_total", &labels).increment(1);
    response
}

fn route_label(request: &Request) -> String {
    let path = request.uri().path();
    if let Some(method) = path.strip_prefix("/c4g.v1.C4G/") {
        if GRPC_METHODS.contains(&method) {
            return path.to_owned();
        }
        return "/c4g.v1.C4G/unknown".to_owned();
    }
    request
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_owned(), |p| p.as_str().to_owned())
}
