//! [`Client`]: where the server is, how to authenticate, and the plumbing every request shares.
//!
//! REST requests go through one `reqwest::Client` (a connection pool); gRPC calls open a channel
//! to the same host and port when they are made, so a client that never streams never speaks
//! HTTP/2, and constructing a client needs neither a runtime nor a reachable server.

use std::time::Duration;

use c4g_proto::v1::c4g_client::C4gClient;
use reqwest::header::{AUTHORIZATION, HeaderMap, HeaderValue, RETRY_AFTER};
use reqwest::{RequestBuilder, Response, StatusCode, Url};
use serde::Deserialize;
use serde::de::DeserializeOwned;
use tonic::metadata::{AsciiMetadataValue, MetadataValue};
use tonic::transport::{Channel, Endpoint};

use crate::Error;
use crate::model::Model;

/// How long to wait for a TCP connection. Requests themselves have no deadline: an upload waits
/// for its encode, and a long video renders for as long as it takes.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// A connection to one c4g server. Cheap to clone (clones share the connection pool).
#[derive(Debug, Clone)]
pub struct Client {
    http: reqwest::Client,
    base: Url,
    grpc: Endpoint,
    grpc_authorization: Option<AsciiMetadataValue>,
}

impl Client {
    /// A client of the server at `base_url` (`http://127.0.0.1:8080`; a bare `host:port` means
    /// `http://host:port`), sending `api_key` as `Authorization: Bearer <key>` when given.
    ///
    /// Only plain `http` is supported: the server speaks h2c and the client carries no TLS stack.
    pub fn new(base_url: &str, api_key: Option<&str>) -> Result<Self, Error> {
        let base = parse_base_url(base_url)?;
        let authorization = api_key
            .filter(|key| !key.is_empty())
            .map(|key| format!("Bearer {key}"));

        let mut headers = HeaderMap::new();
        let mut grpc_authorization = None;
        if let Some(value) = &authorization {
            let invalid = || Error::InvalidInput("the API key must be printable ASCII".to_owned());
            let mut header = HeaderValue::from_str(value).map_err(|_| invalid())?;
            header.set_sensitive(true);
            headers.insert(AUTHORIZATION, header);
            grpc_authorization =
                Some(MetadataValue::try_from(value.as_str()).map_err(|_| invalid())?);
        }
        let http = reqwest::Client::builder()
            .default_headers(headers)
            .connect_timeout(CONNECT_TIMEOUT)
            .user_agent(concat!("c4g-client/", env!("CARGO_PKG_VERSION")))
            .build()?;

        // gRPC paths are absolute (`/c4g.v1.C4G/...`), so the channel gets the origin only.
        let origin = base.origin().ascii_serialization();
        let grpc = Endpoint::from_shared(origin)
            .map_err(|e| Error::InvalidUrl {
                url: base_url.to_owned(),
                reason: e.to_string(),
            })?
            .connect_timeout(CONNECT_TIMEOUT)
            .tcp_nodelay(true);

        Ok(Self {
            http,
            base,
            grpc,
            grpc_authorization,
        })
    }

    /// The server's base URL.
    pub fn base_url(&self) -> &Url {
        &self.base
    }

    /// The served model packages (`GET /v1/models`).
    pub async fn models(&self) -> Result<Vec<Model>, Error> {
        #[derive(Deserialize)]
        struct Models {
            models: Vec<Model>,
        }
        let response = self
            .send(self.http.get(self.url(&["v1", "models"])))
            .await?;
        Ok(json::<Models>(response).await?.models)
    }

    /// The URL of `segments` under the base URL, each segment percent-encoded (clip ids are the
    /// server's, but nothing stops a caller from passing any string).
    pub(crate) fn url(&self, segments: &[&str]) -> Url {
        let mut url = self.base.clone();
        if let Ok(mut path) = url.path_segments_mut() {
            path.pop_if_empty().extend(segments);
        }
        url
    }

    /// The shared request builder.
    pub(crate) fn http(&self) -> &reqwest::Client {
        &self.http
    }

    /// Sends a REST request and turns an error status into [`Error::Api`].
    pub(crate) async fn send(&self, request: RequestBuilder) -> Result<Response, Error> {
        let response = request.send().await?;
        if response.status().is_success() {
            Ok(response)
        } else {
            Err(api_error(response).await)
        }
    }

    /// A gRPC client on a fresh connection to the server.
    pub(crate) async fn grpc(&self) -> Result<C4gClient<Channel>, Error> {
        Ok(C4gClient::new(self.grpc.connect().await?))
    }

    /// Wraps a gRPC message with the API key's metadata.
    pub(crate) fn grpc_request<T>(&self, message: T) -> tonic::Request<T> {
        let mut request = tonic::Request::new(message);
        if let Some(value) = &self.grpc_authorization {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        request
    }
}

/// Reads a JSON answer, calling a body of another shape malformed rather than a transport error.
pub(crate) async fn json<T: DeserializeOwned>(response: Response) -> Result<T, Error> {
    let bytes = response.bytes().await?;
    serde_json::from_slice(&bytes).map_err(|e| Error::Malformed(e.to_string()))
}

fn parse_base_url(base_url: &str) -> Result<Url, Error> {
    let invalid = |reason: String| Error::InvalidUrl {
        url: base_url.to_owned(),
        reason,
    };
    let with_scheme = if base_url.contains("://") {
        base_url.to_owned()
    } else {
        format!("http://{base_url}")
    };
    let url = Url::parse(&with_scheme).map_err(|e| invalid(e.to_string()))?;
    match url.scheme() {
        "http" => {}
        "https" => {
            return Err(invalid(
                "https is not supported: the client speaks plain HTTP, and gRPC as h2c".to_owned(),
            ));
        }
        other => {
            return Err(invalid(format!(
                "unsupported scheme {other:?}; use http://"
            )));
        }
    }
    if url.host().is_none() {
        return Err(invalid("no host".to_owned()));
    }
    Ok(url)
}

/// Builds [`Error::Api`] from an error answer: the API's JSON body when there is one, else the
/// status's reason and whatever text came back (a proxy's page, an empty body).
async fn api_error(response: Response) -> Error {
    #[derive(Deserialize)]
    struct Body {
        error: String,
        kind: String,
    }
    let status = response.status();
    let retry_after = response
        .headers()
        .get(RETRY_AFTER)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse().ok());
    let body = response.bytes().await.unwrap_or_default();
    let (kind, message) = match serde_json::from_slice::<Body>(&body) {
        Ok(body) => (body.kind, body.error),
        Err(_) => (reason_kind(status), plain_message(status, &body)),
    };
    Error::Api {
        status: status.as_u16(),
        kind,
        message,
        retry_after,
    }
}

fn reason_kind(status: StatusCode) -> String {
    status
        .canonical_reason()
        .unwrap_or("http_error")
        .to_ascii_lowercase()
        .replace([' ', '-'], "_")
}

fn plain_message(status: StatusCode, body: &[u8]) -> String {
    const LIMIT: usize = 500;
    let text = String::from_utf8_lossy(body);
    let text = text.trim();
    if text.is_empty() {
        return status.canonical_reason().unwrap_or("error").to_owned();
    }
    match text.char_indices().nth(LIMIT) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;

    #[test]
    fn a_bare_host_and_port_means_http() {
        let client = Client::new("127.0.0.1:9000", None).unwrap();
        assert_eq!(client.base_url().as_str(), "http://127.0.0.1:9000/");
    }

    #[test]
    fn https_is_refused_with_a_reason() {
        let err = Client::new("https://example.com", None).unwrap_err();
        assert!(matches!(err, Error::InvalidUrl { .. }), "{err}");
    }

    #[test]
    fn urls_keep_a_path_prefix_and_encode_segments() {
        let client = Client::new("http://h:1/prefix/", None).unwrap();
        assert_eq!(
            client.url(&["v1", "clips", "a b/c"]).as_str(),
            "http://h:1/prefix/v1/clips/a%20b%2Fc"
        );
        let client = Client::new("http://h:1", None).unwrap();
        assert_eq!(
            client.url(&["v1", "models"]).as_str(),
            "http://h:1/v1/models"
        );
    }

    #[test]
    fn an_api_key_goes_into_grpc_metadata() {
        let client = Client::new("http://h:1", Some("secret")).unwrap();
        let request = client.grpc_request(());
        assert_eq!(
            request.metadata().get("authorization").unwrap(),
            "Bearer secret"
        );
        let client = Client::new("http://h:1", Some("")).unwrap();
        assert!(client.grpc_request(()).metadata().is_empty());
    }

    #[test]
    fn error_reasons_read_like_kinds() {
        assert_eq!(reason_kind(StatusCode::BAD_GATEWAY), "bad_gateway");
        assert_eq!(plain_message(StatusCode::BAD_GATEWAY, b"  "), "Bad Gateway");
    }
}
