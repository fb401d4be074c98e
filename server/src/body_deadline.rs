//! Slow clients: a request body must arrive within `C4G_BODY_TIMEOUT_S` of its request's
//! headers. Without a bound, a client trickling an upload a byte at a time holds its connection
//! and the bytes read so far for as long as it likes; with it, the request is answered 408
//! `timed_out` (gRPC `DEADLINE_EXCEEDED`) and the connection is closed.
//!
//! Reading a body takes no work slot and no encode slot (those are taken once the body is in),
//! so a slow client delays nobody else; this bounds what it holds. Only time spent *waiting for
//! the client* counts: a frame already received is handed on even past the deadline.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::extract::Request;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body_util::{BodyExt, StreamBody};
use tokio::time::Instant;

use c4g_service::ServiceError;

use crate::error::{ErrorReply, status};

/// `router` with every request body held to `limit`.
pub fn layer(router: Router, limit: Duration) -> Router {
    router.layer(axum::middleware::from_fn(move |request, next| {
        bound(limit, request, next)
    }))
}

async fn bound(limit: Duration, request: Request, next: Next) -> Response {
    let grpc = crate::grpc::is_grpc(request.headers());
    let expired = Arc::new(AtomicBool::new(false));
    let deadline = Instant::now() + limit;
    let flag = expired.clone();
    let request = request.map(|body| with_deadline(body, deadline, limit, grpc, flag));
    let response = next.run(request).await;
    // Over REST the handler saw a body that broke off; the client hears why. A gRPC handler
    // already answered with the status the body's error carries.
    if expired.load(Ordering::SeqCst) && !grpc {
        return ErrorReply(timed_out(limit)).into_response();
    }
    response
}

fn timed_out(limit: Duration) -> ServiceError {
    ServiceError::TimedOut(format!(
        "the request body did not arrive within {:.1} s (C4G_BODY_TIMEOUT_S): send it faster, \
         or in smaller requests",
        limit.as_secs_f64()
    ))
}

/// `body`, failing once `deadline` passes while waiting for the client's next frame.
fn with_deadline(
    body: Body,
    deadline: Instant,
    limit: Duration,
    grpc: bool,
    expired: Arc<AtomicBool>,
) -> Body {
    let frames = futures_util::stream::unfold(Some(body), move |body| {
        let expired = expired.clone();
        async move {
            let mut body = body?;
            match tokio::time::timeout_at(deadline, body.frame()).await {
                Ok(Some(frame)) => Some((frame, Some(body))),
                Ok(None) => None,
                Err(_) => {
                    expired.store(true, Ordering::SeqCst);
                    metrics::counter!("c4g_rejected_total", "reason" => "body_timeout")
                        .increment(1);
                    let error = timed_out(limit);
                    // tonic finds a Status in an error's sources and answers with it.
                    let error = if grpc {
                        axum::Error::new(status(error))
                    } else {
                        axum::Error::new(error)
                    };
                    Some((Err(error), None))
                }
            }
        }
    });
    Body::new(StreamBody::new(frames))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use axum::http::StatusCode;
    use axum::routing::post;
    use tower::ServiceExt;

    use super::*;

    fn app(limit: Duration) -> Router {
        let echo = post(|body: axum::body::Bytes| async move { body.len().to_string() });
        layer(Router::new().route("/", echo), limit)
    }

    #[tokio::test]
    async fn a_body_in_time_passes_and_one_that_stalls_is_answered_408() {
        let quick = Request::post("/").body(Body::from("hello")).unwrap();
        let response = app(Duration::from_secs(5)).oneshot(quick).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK);

        // One byte, then nothing: the client is still "sending" when the deadline passes.
        let (tx, rx) = tokio::sync::mpsc::channel::<Result<axum::body::Bytes, std::io::Error>>(1);
        tx.send(Ok("h".into())).await.unwrap();
        let stalled = Body::from_stream(tokio_stream::wrappers::ReceiverStream::new(rx));
        let request = Request::post("/").body(stalled).unwrap();
        let response = app(Duration::from_millis(50))
            .oneshot(request)
            .await
            .unwrap();
        drop(tx);
        assert_eq!(response.status(), StatusCode::REQUEST_TIMEOUT);
        let body = response.into_body().collect().await.unwrap().to_bytes();
        let text = String::from_utf8_lossy(&body);
        assert!(text.contains("timed_out"), "{text}");
        assert!(text.contains("C4G_BODY_TIMEOUT_S"), "{text}");
    }
}
