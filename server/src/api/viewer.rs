//! `/viewer` and `/viewer/{clip}`: the browser viewer, static files embedded in the binary.
//!
//! The files are plain ES modules, HTML and CSS under `server/viewer/`, with no build step and no
//! runtime dependency: the page needs nothing beyond this server. Both page routes answer the
//! same `index.html` (the page reads the clip from its own path); its scripts and stylesheet are
//! under `/viewer/assets/`. Like `/docs` the files are open; the page's own `/v1` calls carry the
//! API key its user types in.

use axum::extract::Path;
use axum::http::header;
use axum::response::{IntoResponse, Response};

use crate::error::ErrorReply;
use c4g_service::ServiceError;
use c4g_service::quoted;

/// The page.
const INDEX: &str = include_str!("../../viewer/index.html");

/// `/viewer/assets/{name}`: name, content type, contents.
const ASSETS: &[(&str, &str, &str)] = &[
    ("viewer.css", CSS, include_str!("../../viewer/viewer.css")),
    ("main.js", JS, include_str!("../../viewer/main.js")),
    ("api.js", JS, include_str!("../../viewer/api.js")),
    ("frames.js", JS, include_str!("../../viewer/frames.js")),
    ("c4gs.js", JS, include_str!("../../viewer/c4gs.js")),
    ("c4gv.js", JS, include_str!("../../viewer/c4gv.js")),
    ("camera.js", JS, include_str!("../../viewer/camera.js")),
    ("splats.js", JS, include_str!("../../viewer/splats.js")),
    ("compare.js", JS, include_str!("../../viewer/compare.js")),
];

const HTML: &str = "text/html; charset=utf-8";
const CSS: &str = "text/css; charset=utf-8";
const JS: &str = "text/javascript; charset=utf-8";

/// Where the page may load from and talk to: this server only (the API key sits in the page's
/// storage); `blob:` images are the server's renders, fetched with the key.
const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; img-src 'self' blob: data:; \
     style-src 'self'; script-src 'self'; connect-src 'self'; object-src 'none'; \
     base-uri 'none'; frame-ancestors 'none'";

pub async fn page() -> Response {
    file(HTML, INDEX)
}

/// The same page for a clip: the script reads the id from the path.
pub async fn clip_page(Path(_clip): Path<String>) -> Response {
    file(HTML, INDEX)
}

pub async fn asset(Path(name): Path<String>) -> Result<Response, ErrorReply> {
    ASSETS
        .iter()
        .find(|(file, _, _)| *file == name)
        .map(|(_, content_type, body)| file(content_type, body))
        .ok_or_else(|| {
            ServiceError::NotFound(format!(
                "the viewer has no file {name_quoted}",
                name_quoted = quoted(&name)
            ))
            .into()
        })
}

fn file(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            // The files change with the binary: revalidate rather than run a stale script.
            (header::CACHE_CONTROL, "no-cache"),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY),
        ],
        body,
    )
        .into_response()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use axum::body::Body;
    use axum::http::Request;
    use clap::Parser;
    use tower::ServiceExt;

    use super::*;
    use crate::AppState;
    use c4g_service::config::Config;

    async fn get(uri: &str) -> (u16, String, String) {
        let app = crate::api::router(AppState::new(Config::parse_from(["c4g-server"]), None));
        let request = Request::builder().uri(uri).body(Body::empty()).unwrap();
        let response = app.oneshot(request).await.unwrap();
        let status = response.status().as_u16();
        let content_type = response
            .headers()
            .get(header::CONTENT_TYPE)
            .map(|v| v.to_str().unwrap().to_owned())
            .unwrap_or_default();
        let body = axum::body::to_bytes(response.into_body(), 1 << 22)
            .await
            .unwrap();
        (
            status,
            content_type,
            String::from_utf8(body.to_vec()).unwrap(),
        )
    }

    /// The names a file loads: `src="/viewer/assets/x"` and `href="..."` in HTML, `from './x.js'`
    /// and `import('./x.js')` in modules.
    fn references(text: &str) -> Vec<String> {
        let mut names = Vec::new();
        for marker in ["/viewer/assets/", "from './", "import('./"] {
            for (at, _) in text.match_indices(marker) {
                let rest = &text[at + marker.len()..];
                let end = rest
                    .find(|c: char| !(c.is_ascii_alphanumeric() || c == '.' || c == '_'))
                    .unwrap_or(rest.len());
                names.push(rest[..end].to_owned());
            }
        }
        names
    }

    #[tokio::test]
    async fn the_page_is_served_at_viewer_and_for_any_clip() {
        for uri in ["/viewer", "/viewer/3f2a00"] {
            let (status, content_type, body) = get(uri).await;
            assert_eq!(status, 200, "{uri}");
            assert_eq!(content_type, HTML);
            assert!(body.contains("<canvas"), "{uri}");
        }
    }

    #[tokio::test]
    async fn every_asset_is_served_with_its_content_type_and_others_are_404() {
        for (name, content_type, body) in ASSETS {
            let (status, served_type, served) = get(&format!("/viewer/assets/{name}")).await;
            assert_eq!(status, 200, "{name}");
            assert_eq!(served_type, *content_type, "{name}");
            assert_eq!(served, *body);
        }
        let (status, content_type, body) = get("/viewer/assets/nothing.js").await;
        assert_eq!(status, 404);
        assert!(
            content_type.starts_with("application/json"),
            "{content_type}"
        );
        assert!(body.contains("not_found"), "{body}");
    }

    #[test]
    fn every_file_the_page_loads_is_embedded_and_every_embedded_file_is_loaded() {
        let mut loaded = references(INDEX);
        for (_, _, body) in ASSETS {
            loaded.extend(references(body));
        }
        for name in &loaded {
            assert!(
                ASSETS.iter().any(|(file, _, _)| file == name),
                "{name} is loaded but not embedded"
            );
        }
        for (file, _, _) in ASSETS {
            assert!(
                loaded.iter().any(|name| name == file),
                "{file} is embedded but nothing loads it"
            );
        }
    }
}
