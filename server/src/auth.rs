//! API-key authentication: `Authorization: Bearer <key>` (the scheme in any case, RFC 9110
//! §11.1) or `x-api-key: <key>`, compared in constant time (both sides hashed first, so neither
//! the content nor the length of the key leaks through timing).
//!
//! Open without a key, like REST's `/health` and `/ready`: the gRPC health service
//! (`grpc.health.v1.Health`), so that standard probes (Kubernetes' gRPC probe,
//! `grpc_health_probe`) work on a server with a key. Reflection stays behind the key: it lists
//! the API, which is the key holder's to see.

use axum::extract::{Request, State};
use axum::http::HeaderMap;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;

use crate::AppState;
use crate::error::{ErrorReply, status};
use c4g_service::ServiceError;

/// The configured key, kept only as its hash.
#[derive(Clone)]
pub struct ApiKey {
    digest: [u8; 32],
}

impl std::fmt::Debug for ApiKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ApiKey(..)")
    }
}

impl ApiKey {
    /// Wraps the configured key.
    pub fn new(key: &str) -> Self {
        Self {
            digest: Sha256::digest(key.as_bytes()).into(),
        }
    }

    /// True when `presented` is the key.
    pub fn matches(&self, presented: &str) -> bool {
        let digest: [u8; 32] = Sha256::digest(presented.as_bytes()).into();
        self.digest.ct_eq(&digest).into()
    }

    /// True when the headers (HTTP, or gRPC metadata as headers) carry the key.
    pub fn admits(&self, headers: &HeaderMap) -> bool {
        let bearer = headers
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(bearer_token);
        let plain = headers.get("x-api-key").and_then(|v| v.to_str().ok());
        bearer.or(plain).is_some_and(|k| self.matches(k.trim()))
    }
}

/// The token of an `Authorization` value whose scheme is `Bearer`, in any case.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then_some(token)
}

/// The gRPC health service's path prefix: open, for probes.
const GRPC_HEALTH: &str = "/grpc.health.v1.Health/";

/// Middleware: refuses requests without the key (when one is configured), but for gRPC health
/// checks. gRPC calls get `UNAUTHENTICATED` in gRPC's own framing.
pub async fn require_key(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let open = request.uri().path().starts_with(GRPC_HEALTH);
    match state.api_key() {
        Some(key) if !open && !key.admits(request.headers()) => {
            metrics::counter!("c4g_rejected_total", "reason" => "unauthorized").increment(1);
            if crate::grpc::is_grpc(request.headers()) {
                status(ServiceError::Unauthorized).into_http()
            } else {
                ErrorReply(ServiceError::Unauthorized).into_response()
            }
        }
        _ => next.run(request).await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_exact_key_is_admitted() {
        let key = ApiKey::new("s3cret");
        assert!(key.matches("s3cret"));
        assert!(!key.matches("s3cre"));
        assert!(!key.matches("s3cret "));
        assert!(!key.matches(""));
        let mut headers = HeaderMap::new();
        headers.insert("authorization", "Bearer s3cret".parse().unwrap());
        assert!(key.admits(&headers));
        headers.insert("authorization", "Bearer wrong".parse().unwrap());
        assert!(!key.admits(&headers));
        let mut headers = HeaderMap::new();
        headers.insert("x-api-key", "s3cret".parse().unwrap());
        assert!(key.admits(&headers));
    }

    #[test]
    fn the_key_is_kept_only_as_its_digest_and_compared_whole_at_every_length() {
        let secret = "a-long-secret-0123456789abcdef";
        let key = ApiKey::new(secret);
        // What the server holds and could ever print: 32 bytes of SHA-256, no part of the key.
        assert_eq!(
            key.digest,
            <[u8; 32]>::from(Sha256::digest(secret.as_bytes()))
        );
        assert_eq!(format!("{key:?}"), "ApiKey(..)");
        // Digests of equal length are compared in full (`subtle`), so neither a shared prefix nor
        // the presented key's length decides how soon the comparison ends.
        for n in 0..secret.len() {
            assert!(!key.matches(&secret[..n]), "prefix of {n} bytes");
        }
        for longer in [format!("{secret}0"), format!("{secret}{secret}")] {
            assert!(!key.matches(&longer));
        }
        assert!(!key.matches(&secret.to_uppercase()));
        assert!(key.matches(secret));
    }

    #[test]
    fn only_the_two_documented_headers_carry_a_key() {
        let key = ApiKey::new("s3cret");
        let with = |name: &'static str, value: &str| {
            let mut headers = HeaderMap::new();
            headers.insert(name, value.parse().unwrap());
            key.admits(&headers)
        };
        assert!(with("authorization", "Bearer s3cret"));
        // The scheme is case-insensitive (RFC 9110 §11.1); the key is not.
        assert!(with("authorization", "bearer s3cret"));
        assert!(with("authorization", "BEARER s3cret"));
        assert!(!with("authorization", "Bearer S3CRET"));
        assert!(!with("authorization", "Bearers3cret"));
        assert!(!with("authorization", "Basic s3cret"));
        assert!(!with("authorization", "s3cret"));
        assert!(!with("cookie", "s3cret"));
        assert!(!with("x-api-key", "Bearer s3cret"));
        assert!(!key.admits(&HeaderMap::new()));
    }
}
